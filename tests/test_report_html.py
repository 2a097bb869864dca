"""The static HTML report (`urd.report_html`): pure image functions (`urd.report_images`), the
files and links it writes, escaping, atomic folder handling, and the page in a real browser.

The browser test drives the system Chromium through Selenium and the system chromedriver
(Debian packages ``chromium`` and ``chromium-driver``, pip package ``selenium`` of the ``test``
extra); it skips with the reason when the system packages are missing. It saves screenshots into the folder named by the environment
variable ``URD_SCREENSHOT_DIR`` when set, else into the test's temporary folder.
"""

from __future__ import annotations

import html
import os
import re
import shutil
import time
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import urlsplit

import cv2
import numpy as np
import pytest

from separate import optics
from urd.report_html import (
    CalibrationView,
    ReportExistsError,
    ResultView,
    SceneView,
    write_html_report,
)
from urd.report_images import aolp_image, polarization_maps
from urd.core.images import srgb_encode

H, W = 96, 128
EVIL_NAME = "scene <script>window.__xss = 1</script> & \"quoted\""
EVIL_PROVENANCE = "<img src=x onerror=\"window.__xss = 2\">"


def _layers(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Smooth coloured transmission with a checker, a bright reflected bar and disc (linear)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    u, v = xx / W, yy / H
    checker = ((xx // 16 + yy // 16) % 2).astype(np.float32)
    i_t = np.stack([0.25 + 0.5 * u, 0.2 + 0.5 * v, 0.55 - 0.3 * u], -1) * (0.7 + 0.3 * checker[..., None])
    bar = np.exp(-(((xx - yy * 1.2 - 20 - 10 * seed) / 9.0) ** 2))
    disc = ((xx - 88) ** 2 + (yy - 30) ** 2 < 18**2).astype(np.float32)
    i_r = (np.maximum(bar, disc)[..., None] * np.array([1.6, 1.5, 1.2], np.float32)
           + 0.02 * rng.random((H, W, 3), np.float32))
    return i_r.astype(np.float32), i_t.astype(np.float32)


def _scene(name: str, angles_deg: list[float], seed: int, methods: int = 2, errors: bool = False) -> SceneView:
    """Shots rendered by the optics core at θ = 50°, φ⊥ = 10°, and results near the truth."""
    i_r, i_t = _layers(seed)
    theta, phi_perp = np.radians(50.0), np.radians(10.0)
    shots = [(a, optics.render(i_r, i_t, theta, phi_perp, np.radians(a)).astype(np.float32)) for a in angles_deg]
    r_obs, t_obs = (x.astype(np.float32) for x in optics.observable_layers(i_r, i_t, theta))
    results = []
    if methods >= 1:
        confidence = np.clip(r_obs.mean(-1) / r_obs.mean(-1).max(), 0, 1).astype(np.float32)
        results.append(ResultView("network", r_obs, t_obs,
                                  {"weights_sha256": "ab" * 32, "urd_version": "0.1.0", "tile": 512,
                                   "time": "2026-01-02T03:04:05Z", "note": EVIL_PROVENANCE,
                                   "params": {"colour_match": False, "bf16": False}}, confidence))
    if methods >= 2:
        leak = cv2.GaussianBlur(r_obs, (0, 0), 3.0) * 0.4
        results.append(ResultView("schechner", r_obs - leak, t_obs + leak,
                                  {"theta_deg": 48.7, "urd_version": "0.1.0"}))
    return SceneView(name, "separated (network, schechner)" if methods else "ingested", shots, 10.0 if methods else None,
                     [0.4, -0.3, 0.1, -0.2][: len(shots)] if errors else None, results, [])


def _calibration() -> CalibrationView:
    rng = np.random.default_rng(3)
    angles = np.arange(0.0, 180.0, 15.0)
    peak = 33.0

    def curve(a):
        return 0.05 + 0.4 * np.cos(np.radians(a - peak)) ** 2

    grid = np.arange(0.0, 180.5, 1.0)
    return CalibrationView(angles.tolist(), (curve(angles) + 0.004 * rng.standard_normal(angles.size)).tolist(),
                           grid.tolist(), curve(grid).tolist(), offset_deg=(0.0 - peak) % 180.0, uncertainty_deg=0.8,
                           residual_rms=0.00412)


def _scenes() -> list[SceneView]:
    incomplete = _scene("scene_03", [0.0, 45.0], seed=2, methods=0)
    incomplete.status, incomplete.notes = "incomplete (2 of 3 shots)", ["capture interrupted: resume with urd capture"]
    return [_scene("scene_01", [0.0, 45.0, 90.0], seed=0, errors=True),
            _scene(EVIL_NAME, [0.0, 45.0, 90.0, 135.0], seed=1),
            incomplete]


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> Path:
    calls = []
    index = write_html_report(_scenes(), tmp_path_factory.mktemp("report") / "out", "urd test <report>", _calibration(),
                              progress=lambda done, total: calls.append((done, total)))
    assert calls[0] == (0, 3) and calls[-1] == (3, 3)
    return index


class _Links(HTMLParser):
    """Every URL-like attribute (src, href, option values of the comparison selects) and every tag."""

    def __init__(self):
        super().__init__()
        self.urls: list[tuple[str, str]] = []
        self.imgs: list[dict] = []
        self.texts: list[str] = []

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        for key in ("src", "href"):
            if attrs.get(key) is not None:
                self.urls.append((tag, attrs[key]))
        if tag == "option":
            self.urls.append((tag, attrs["value"]))
        if tag == "img":
            self.imgs.append(attrs)

    def handle_data(self, data):
        self.texts.append(data)


def _parse(index: Path) -> _Links:
    parser = _Links()
    parser.feed(index.read_text(encoding="utf-8"))
    return parser


# ---------------------------------------------------------------------------------------------
# Pure functions


def test_srgb_encode_hand_checked_values():
    x = np.array([0.0, 0.0031308, 0.18, 0.5, 1.0, 2.0, -1.0, np.nan], np.float32)
    np.testing.assert_allclose(srgb_encode(x), [0.0, 0.04045, 0.46135, 0.73536, 1.0, 1.0, 0.0, 0.0], atol=2e-4)


def test_polarization_maps_recover_known_stokes():
    rng = np.random.default_rng(0)
    s0 = rng.uniform(0.2, 1.0, (H, W, 3)).astype(np.float32)
    p = rng.uniform(0.0, 0.9, (H, W)).astype(np.float32)
    psi = rng.uniform(-np.pi / 2 + 0.01, np.pi / 2, (H, W)).astype(np.float32)
    s1, s2 = s0 * (p * np.cos(2 * psi))[..., None], s0 * (p * np.sin(2 * psi))[..., None]
    shots = [(a, ((s0 + s1 * np.cos(2 * np.radians(a)) + s2 * np.sin(2 * np.radians(a))) / 2).astype(np.float32))
             for a in (0.0, 45.0, 90.0, 135.0)]
    s0_hat, dolp_hat, aolp_hat = polarization_maps(shots)
    np.testing.assert_allclose(s0_hat, s0, atol=1e-5)
    np.testing.assert_allclose(dolp_hat, p, atol=1e-4)
    np.testing.assert_allclose(np.angle(np.exp(2j * (aolp_hat - psi))), 0.0, atol=1e-3)


def test_aolp_image_hue_saturation_value():
    aolp = np.radians(np.array([[0.0, 45.0, 90.0, 135.0, 180.0, 30.0]]))
    rgb = aolp_image(aolp, np.array([[1.0, 1.0, 1.0, 1.0, 1.0, 0.0]]), np.array([[1.0, 1.0, 1.0, 1.0, 1.0, 0.5]]))
    # hue = 2·AoLP: 0° red, 45° → 90° chartreuse, 90° → 180° cyan, 135° → 270° violet, 180° ≡ 0°; DoLP 0 → grey of value
    assert rgb.tolist() == [[[255, 0, 0], [128, 255, 0], [0, 255, 255], [128, 0, 255], [255, 0, 0], [128, 128, 128]]]


# ---------------------------------------------------------------------------------------------
# Files, links, escaping


def test_report_writes_every_linked_file_and_only_relative_links(report):
    out = report.parent
    links = _parse(report)
    assert len(links.imgs) >= 20
    local = 0
    for tag, url in links.urls:
        if url.startswith("#") or url.startswith("data:"):
            continue
        assert not urlsplit(url).scheme and not url.startswith("/"), f"{tag} links {url!r}: not a relative path"
        path = out / url
        assert path.is_file() and path.stat().st_size > 0, f"{tag} links {url}, which was not written"
        assert path.resolve().is_relative_to(out.resolve())
        local += 1
    assert local >= 40
    for img in links.imgs:
        assert img.get("loading") == "lazy", img
    page = report.read_text(encoding="utf-8")
    assert "http://" not in page and "https://" not in page
    assert not re.search(r"url\((?!#)", page), "CSS or SVG refers to an external url()"
    assert "<style>" in page and "<script>" in page and '<link rel="stylesheet"' not in page
    # no stray files: every image file is linked from the page
    linked = {url for _, url in links.urls}
    written = {p.relative_to(out).as_posix() for p in out.rglob("*.jpg")}
    assert written and written <= linked


def test_report_shows_scene_content(report):
    page = report.read_text(encoding="utf-8")
    out = report.parent
    # scene 1: three shots with their calibration errors, S0/DoLP/AoLP, two methods, a slider, provenance
    assert page.count('class="card scene"') == 3
    assert "φ = 45.0°" in page and "calib. error −0.30°" in page and "calib. error +0.40°" in page
    assert "reference angle φ⊥ = <b>10.00°</b>" in page
    assert page.count('class="wheel"') == 2 and page.count('class="compare"') == 2
    assert page.count('class="method"') == 4 and page.count("<summary>provenance</summary>") == 4
    assert "weights_sha256" in page and "ab" * 32 in page
    assert "Exposure: S0, R̂, T̂ ×" in page
    # scene 3 has two shots: no maps, and the page says why
    assert "no polarization maps: 2 shot(s)" in page and "capture interrupted" in page
    # the calibration plot: one dot per sweep angle, the fit curve, the offset
    svg = page[page.index('id="calibration"'):page.index("</section>", page.index('id="calibration"'))]
    assert svg.count('class="pt"') == 12 and 'class="fit"' in svg and "147.000° ± 0.800°" in svg
    assert "<dt>RMS residual</dt><dd>0.00412 (" in svg                  # the fit's own figure (calibration.json's)
    # the full views keep full resolution; the thumbnails are no larger than thumb_px
    full = cv2.imread(str(out / "img/s000-scene_01/shot_00.jpg"))
    assert full.shape == (H, W, 3)


def test_thumbnails_have_the_requested_long_side(tmp_path):
    index = write_html_report(_scenes()[:1], tmp_path / "r", "t", thumb_px=64)
    folder = index.parent / "img/s000-scene_01"
    assert cv2.imread(str(folder / "shot_00_t.jpg")).shape == (48, 64, 3)
    assert cv2.imread(str(folder / "m00_network_T_m.jpg")).shape == (H, W, 3)   # 2 × 64 ≥ 128: not upscaled
    assert 'width="64" height="48"' in index.read_text(encoding="utf-8")


def test_strings_from_data_are_escaped(report):
    page = report.read_text(encoding="utf-8")
    assert "<script>window.__xss" not in page and EVIL_PROVENANCE not in page
    assert html.escape(EVIL_NAME) in page and html.escape(EVIL_PROVENANCE) in page
    assert "<title>urd test &lt;report&gt;</title>" in page
    assert page.count("<script>") == 1          # the page's own script only
    texts = "".join(_parse(report).texts)
    assert EVIL_NAME in texts and EVIL_PROVENANCE in texts


def test_existing_folder_is_never_silently_replaced(tmp_path):
    out = tmp_path / "report"
    scenes = _scenes()[:1]
    write_html_report(scenes, out, "first")
    with pytest.raises(FileExistsError, match=re.escape(str(out))):
        write_html_report(scenes, out, "second")
    assert "<title>first</title>" in (out / "index.html").read_text(encoding="utf-8")
    write_html_report(scenes, out, "second", overwrite=True)
    assert "<title>second</title>" in (out / "index.html").read_text(encoding="utf-8")
    # a folder that is not a report is refused even with overwrite, and left as it was
    other = tmp_path / "photos"
    other.mkdir()
    (other / "keep.txt").write_text("mine")
    with pytest.raises(ReportExistsError, match="not an urd HTML report"):
        write_html_report(scenes, other, "x", overwrite=True)
    assert (other / "keep.txt").read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["photos", "report"]     # no staging left behind


def test_a_report_a_killed_run_moved_aside_to_replace_it_is_put_back(tmp_path):
    out = tmp_path / "report"
    scenes = _scenes()[:1]
    write_html_report(scenes, out, "first")
    aside = tmp_path / ".report.old-k2x9q1zz"            # a kill between the two renames of a replacement
    aside.mkdir()
    out.rename(aside / "report")
    os.utime(aside, (time.time() - 60, time.time() - 60))
    with pytest.raises(FileExistsError, match=re.escape(str(out))):    # put back, so replacing it asks again
        write_html_report(scenes, out, "second")
    assert "<title>first</title>" in (out / "index.html").read_text(encoding="utf-8") and not aside.exists()
    aside.mkdir()
    (aside / "report").mkdir()
    os.utime(aside, (time.time() - 60, time.time() - 60))
    write_html_report(scenes, out, "third", overwrite=True)           # a report is there: the one aside is removed
    assert "<title>third</title>" in (out / "index.html").read_text(encoding="utf-8")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report"]


def test_failure_midway_leaves_no_folder(tmp_path):
    def stop(done, total):
        if done == 1:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        write_html_report(_scenes(), tmp_path / "r", "t", progress=stop)
    assert list(tmp_path.iterdir()) == []


def test_bad_views_are_refused_with_expected_and_got(tmp_path):
    scene = _scenes()[0]
    scene.results[1].t = scene.results[1].t[:50]
    with pytest.raises(ValueError, match=r"expected shots and results of one size H×W, got \[\(50, 128\), \(96, 128\)\]"):
        write_html_report([scene], tmp_path / "r", "t")
    scene = _scenes()[0]
    scene.shots[0] = (0.0, (scene.shots[0][1] * 255).astype(np.uint8))
    with pytest.raises(ValueError, match="expected float linear values, got dtype uint8"):
        write_html_report([scene], tmp_path / "r", "t")
    with pytest.raises(ValueError, match="expected 32..4096 px, got 8"):
        write_html_report([], tmp_path / "r", "t", thumb_px=8)
    assert not (tmp_path / "r").exists()


# ---------------------------------------------------------------------------------------------
# In a real browser


def _chrome(tmp_path: Path):
    """A headless system Chromium under Selenium, or a skip naming what is missing."""
    from selenium import webdriver                          # a declared test dependency: missing is a failure
    from selenium.webdriver.chrome.service import Service

    browser = next((shutil.which(n) for n in ("chromium", "chromium-browser") if shutil.which(n)), None)
    driver = shutil.which("chromedriver")
    if browser is None or driver is None:
        pytest.skip("no system Chromium and chromedriver (apt-get install chromium chromium-driver)")
    options = webdriver.ChromeOptions()
    options.binary_location = browser
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--window-size=1280,1000",
                "--hide-scrollbars", "--force-device-scale-factor=1", f"--user-data-dir={tmp_path / 'chrome-profile'}"):
        options.add_argument(arg)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    return webdriver.Chrome(service=Service(driver), options=options)


def _wait(predicate, timeout_s: float = 15.0, what: str = "condition"):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


@pytest.mark.slow
def test_report_in_a_real_browser(report, tmp_path):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support.ui import Select

    shots_dir = Path(os.environ.get("URD_SCREENSHOT_DIR") or tmp_path / "screenshots")
    shots_dir.mkdir(parents=True, exist_ok=True)
    browser = _chrome(tmp_path)
    try:
        browser.get(report.as_uri())
        assert browser.title == "urd test <report>"
        assert browser.execute_script("return window.__xss") is None, "markup from the data ran as script"
        headings = [h.text for h in browser.find_elements(By.CSS_SELECTOR, "section.scene h2")]
        assert EVIL_NAME in headings

        # every image loads once scrolled into view (they are lazy)
        images = browser.find_elements(By.TAG_NAME, "img")
        assert len(images) >= 20
        for img in images:
            browser.execute_script("arguments[0].scrollIntoView({block: 'center'})", img)
            _wait(lambda img=img: browser.execute_script("return arguments[0].complete && arguments[0].naturalWidth > 0", img),
                  what=f"image {img.get_attribute('src')}")
        sources = browser.execute_script("return Array.from(document.images, i => i.currentSrc)")
        assert all(url.startswith(report.parent.as_uri() + "/img/") for url in sources), sources

        # the comparison slider: the keyboard moves it to the left end, a drag to a quarter
        box = browser.find_element(By.CSS_SELECTOR, ".compare")
        stage, top = box.find_element(By.CSS_SELECTOR, ".cmp-stage"), box.find_element(By.CSS_SELECTOR, ".cmp-a")
        divider, slider = box.find_element(By.CSS_SELECTOR, ".cmp-divider"), box.find_element(By.CSS_SELECTOR, ".cmp-range")
        browser.execute_script("arguments[0].scrollIntoView({block: 'center'})", stage)

        def state():
            return (browser.execute_script("return getComputedStyle(arguments[0]).clipPath", top),
                    divider.rect["x"] - stage.rect["x"])

        clip, x = state()
        assert clip == "inset(0px 50% 0px 0px)" and abs(x - stage.rect["width"] / 2) < 3
        slider.send_keys(Keys.HOME)
        clip, x = state()
        assert slider.get_attribute("value") == "0" and clip == "inset(0px 100% 0px 0px)" and abs(x) < 3
        ActionChains(browser).move_to_element_with_offset(stage, -stage.rect["width"] / 4, 0).click_and_hold() \
            .move_by_offset(2, 0).release().perform()
        clip, x = state()
        assert abs(float(slider.get_attribute("value")) - 25) < 2.5 and abs(x - stage.rect["width"] / 4) < 4, (clip, x)

        # the selects swap the images being compared
        left = Select(box.find_element(By.CSS_SELECTOR, ".cmp-left"))
        labels = [o.text for o in left.options]
        assert labels == ["S0 (input)", "network · T̂", "network · R̂", "schechner · T̂", "schechner · R̂"]
        assert left.first_selected_option.text == "network · T̂"
        assert Select(box.find_element(By.CSS_SELECTOR, ".cmp-right")).first_selected_option.text == "schechner · T̂"
        left.select_by_visible_text("network · R̂")
        assert top.get_attribute("src").endswith("m00_network_R_m.jpg")
        assert box.find_element(By.CSS_SELECTOR, ".cmp-tag.left").text == "network · R̂"
        _wait(lambda: browser.execute_script("return arguments[0].complete && arguments[0].naturalWidth > 0", top),
              what="the newly selected image")
        ActionChains(browser).move_to_element_with_offset(stage, stage.rect["width"] / 5, 0).click().perform()
        box.screenshot(str(shots_dir / "report_compare.png"))

        # a thumbnail opens the full-resolution view; Esc closes it
        thumb = browser.find_element(By.CSS_SELECTOR, "a.zoom")
        browser.execute_script("arguments[0].scrollIntoView({block: 'center'})", thumb)
        thumb.click()
        viewer = browser.find_element(By.ID, "viewer")
        assert viewer.is_displayed()
        full = viewer.find_element(By.TAG_NAME, "img")
        _wait(lambda: browser.execute_script("return arguments[0].naturalWidth", full) == W, what="the full view")
        browser.save_screenshot(str(shots_dir / "report_viewer.png"))
        browser.find_element(By.TAG_NAME, "body").send_keys(Keys.ESCAPE)
        assert not viewer.is_displayed()

        # provenance opens; screenshots: the top of the page and the whole page
        summary = browser.find_element(By.CSS_SELECTOR, "details.prov summary")
        browser.execute_script("arguments[0].scrollIntoView({block: 'center'})", summary)
        summary.click()
        assert "weights_sha256" in browser.find_element(By.CSS_SELECTOR, "details.prov table").text
        browser.execute_script("window.scrollTo(0, 0)")
        browser.save_screenshot(str(shots_dir / "report_top.png"))
        height = browser.execute_script("return document.documentElement.scrollHeight")
        browser.set_window_size(1280, height + 100)
        browser.save_screenshot(str(shots_dir / "report_full.png"))
        assert (shots_dir / "report_full.png").stat().st_size > 10_000

        errors = [entry for entry in browser.get_log("browser") if entry["level"] in ("SEVERE", "ERROR")]
        assert errors == [], errors
    finally:
        browser.quit()


def test_results_without_shots_compare_one_method(tmp_path):
    scene = _scenes()[0]
    scene.shots, scene.shot_errors_deg, scene.results = [], [0.2, -0.1, 0.0], scene.results[:1]
    page = write_html_report([scene], tmp_path / "r", "t").read_text(encoding="utf-8")
    assert "<h3>Polarization</h3>" not in page and "errors: +0.20°, −0.10°, 0.00°" in page
    assert "k = 1 / 99.5th percentile of R̂ + T̂ of network" in page
    selected = re.findall(r'<option value="([^"]+)" selected>', page)
    assert [Path(v).name for v in selected] == ["m00_network_T_m.jpg", "m00_network_R_m.jpg"]
