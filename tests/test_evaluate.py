"""The evaluation's pure parts: condition generators, photo loader, plots, tolerance checks."""

import dataclasses
import json
import math

import cv2
import numpy as np
import pytest
import tifffile

from separate import bench_check, bench_plan, bench_run, crossval, optics, plots, robustness, scoring, speed
from separate.bench_check import BenchmarkMismatch
from separate.robustness import AXES, Condition, Noise
from conftest import shared_data


def layers(p: int = 96, seed: int = 0) -> dict[str, np.ndarray]:
    """Smooth random layers (textured enough for phase correlation), one θ and φ⊥ per patch."""
    rng = np.random.default_rng(seed)
    r, t = (cv2.GaussianBlur(rng.random((p, p, 3)).astype(np.float32), (0, 0), 1.5) * 0.4 for _ in range(2))
    return {"r": r, "t": t, "theta": np.full((p, p), 0.9, np.float32), "phi_perp": np.full((p, p), 0.4, np.float32)}


def quiet(draws):
    """The same draws without sensor noise."""
    return dataclasses.replace(draws, noise=np.zeros_like(draws.noise))


def radiances(sample):
    rho = optics.reflectance(sample["theta"])[..., None]
    return sample["r"] / rho, sample["t"] / (1 - rho)


def blob_layers(p: int = 96) -> dict[str, np.ndarray]:
    """Both layers a Gaussian blob (σ = 6 px) in the patch's centre: its centroid tracks shifts exactly."""
    ys, xs = np.mgrid[0:p, 0:p].astype(np.float32)
    blob = np.exp(-((xs - p / 2) ** 2 + (ys - p / 2) ** 2) / (2 * 6.0**2))[..., None] * np.float32([0.3, 0.4, 0.5])
    return {"r": blob, "t": blob * 0.5, "theta": np.full((p, p), 0.9, np.float32), "phi_perp": np.full((p, p), 0.4, np.float32)}


def centroid(image: np.ndarray) -> np.ndarray:
    """(x, y) centroid of an image's luminance."""
    weight = image.mean(axis=2)
    ys, xs = np.mgrid[0 : weight.shape[0], 0 : weight.shape[1]]
    return np.array([(xs * weight).sum(), (ys * weight).sum()]) / weight.sum()


def test_shift_image_moves_content_by_the_given_pixels():
    image = blob_layers()["r"]
    moved = centroid(robustness.shift_image(image, 1.2, -1.6)) - centroid(image)
    np.testing.assert_allclose(moved, [1.2, -1.6], atol=0.01)
    whole = robustness.shift_image(image, 2.0, -1.0)
    np.testing.assert_allclose(whole[20:-20, 20:-20], image[21:-19, 18:-22], atol=1e-6)
    assert np.array_equal(robustness.shift_image(image, 0.0, 0.0), image)


def test_misalignment_of_2px_shifts_every_later_shot_by_2px_and_leaves_the_first():
    sample = blob_layers()
    draws = quiet(robustness.draw_nuisances(0, sample["r"].shape))
    aligned, _, _ = robustness.render_condition(sample, Condition(), draws)
    moved, _, _ = robustness.render_condition(sample, Condition(misalign_px=2.0), draws)
    assert np.array_equal(aligned[0], moved[0])
    for k in (1, 2):
        shift = centroid(moved[k]) - centroid(aligned[k])
        assert np.hypot(*shift) == pytest.approx(2.0, abs=0.01)
        direction = draws.shift_directions[k]
        np.testing.assert_allclose(shift, [2 * math.cos(direction), 2 * math.sin(direction)], atol=0.01)


def test_angle_error_stays_within_its_bound_and_calibration_gives_the_true_angles():
    sample = layers()
    draws = quiet(robustness.draw_nuisances(1, sample["r"].shape))
    shots, given, true = robustness.render_condition(sample, Condition(angle_error_deg=4.0), draws)
    assert given == [0.0, 45.0, 90.0]
    errors = np.subtract(true, given)
    assert np.all(np.abs(errors) <= 4.0) and np.any(errors != 0)
    _, calibrated, true_again = robustness.render_condition(sample, Condition(angle_error_deg=4.0, calibrated=True), draws)
    assert calibrated == true == true_again
    i_r, i_t = radiances(sample)
    phi0 = float(sample["phi_perp"][0, 0]) - np.radians(draws.phi_perp_offset_deg)
    for shot, angle in zip(shots, true):
        expected = optics.render(i_r, i_t, sample["theta"], sample["phi_perp"], phi0 + np.radians(angle))
        np.testing.assert_allclose(shot, np.clip(expected, 0, 1), atol=1e-6)


def test_phi_perp_offset_puts_the_first_shot_at_s_or_p():
    sample = layers()
    draws = quiet(robustness.draw_nuisances(2, sample["r"].shape))
    i_r, i_t = radiances(sample)
    r_s, r_p = optics.fresnel_reflectance(0.9)
    for offset, alpha in ((0.0, r_s), (90.0, r_p)):
        shots, _, _ = robustness.render_condition(sample, Condition(phi_perp_offset_deg=offset), draws)
        np.testing.assert_allclose(shots[0], alpha * i_r / 2 + (1 - alpha) * i_t / 2, atol=1e-6)


def test_angle_sets_give_one_shot_per_angle():
    sample = layers(64)
    draws = robustness.draw_nuisances(3, sample["r"].shape)
    for count in (3, 4, 6):
        cond = dict(AXES[4].levels)[str(count)]
        shots, given, _ = robustness.render_condition(sample, cond, draws)
        assert shots.shape == (count, 64, 64, 3) and len(given) == count
        assert shots.dtype == np.float32 and shots.min() >= 0 and shots.max() <= 1


def test_noise_levels_grow_and_share_their_draws():
    sample = layers(64)
    draws = robustness.draw_nuisances(4, sample["r"].shape)
    clean, _, _ = robustness.render_condition(sample, Condition(), quiet(draws))
    residuals = [robustness.render_condition(sample, Condition(noise=level), draws)[0] - clean for level in Noise]
    spreads = [float(r.std()) for r in residuals]
    assert spreads[0] < spreads[1] < spreads[2]
    assert np.corrcoef(residuals[0].ravel(), residuals[2].ravel())[0, 1] > 0.9


def test_draws_are_deterministic_per_patch():
    a, b = robustness.draw_nuisances(5, (8, 8, 3)), robustness.draw_nuisances(5, (8, 8, 3))
    c = robustness.draw_nuisances(6, (8, 8, 3))
    assert np.array_equal(a.noise, b.noise) and a.phi_perp_offset_deg == b.phi_perp_offset_deg
    assert not np.array_equal(a.noise, c.noise)
    assert -45 <= a.phi_perp_offset_deg <= 45 and np.all(np.abs(a.angle_units) <= 1)


def test_condition_checks_its_arguments():
    with pytest.raises(ValueError, match="3 to 6 angles"):
        Condition(angles_deg=(0, 90))
    with pytest.raises(ValueError, match="≥ 0"):
        Condition(misalign_px=-1)
    with pytest.raises(ValueError, match="'deafening' is not a valid Noise"):
        Condition(noise="deafening")


def test_quick_axes_keep_two_levels_each_and_conditions_are_shared():
    for axis in AXES:
        assert len(axis.conditions(quick=True)) == 2
        assert [label for label, _ in axis.conditions(quick=True)] == list(axis.quick)
    assert AXES[0].levels[0][1] == AXES[1].levels[0][1] == Condition()


def test_robustness_rows_per_axis_level_and_method():
    data = {k: np.stack([layers(64, s)[k] for s in range(2)]) for k in ("r", "t", "theta", "phi_perp")}
    run_none, _ = scoring.make_method("none")
    calls = []

    def counting(images, angles):
        calls.append(len(angles))
        return run_none(images, angles)

    def picky(images, angles):
        if len(angles) > 3:
            raise ValueError("expected 3 angles")
        return run_none(images, angles)

    rows = robustness.robustness(data, AXES, {"none": run_none, "counted": counting, "picky": picky}, quick=True)
    assert len(rows) == 3 * 2 * len(AXES)
    unique = {cond for axis in AXES for _, cond in axis.conditions(True)}
    assert len(calls) == 2 * len(unique)
    assert all(len(r["psnr_t_per_patch"]) == 2 for r in rows)
    six = [r for r in rows if r["axis"] == "angles" and r["condition"] == "6"]
    assert {r["method"] for r in six} == {"none", "counted", "picky"} and 6 in calls
    refused = next(r for r in six if r["method"] == "picky")
    assert refused["failed"] == 2 and refused["failure"] == "expected 3 angles" and math.isnan(refused["psnr_t"])
    assert all(r["failed"] == 0 for r in rows if r["method"] != "picky" or r["condition"] != "6")
    assert scoring.gap(six, "none", "picky") is None and scoring.gap(six, "none", "counted")["mean"] == 0
    flat = bench_check.flatten_figures({}, rows, [])
    assert flat["robustness/angles/6/picky/failed"] == 2 and "robustness/angles/6/picky/psnr_t" not in flat


def write_png16(path, image):
    cv2.imwrite(str(path), image[..., ::-1] if image.ndim == 3 else image)


def test_photo_loader_reads_8_and_16_bit_files(tmp_path):
    rng = np.random.default_rng(0)
    rgb16 = rng.integers(0, 65536, (40, 60, 3), dtype=np.uint16)
    expected = np.round(rgb16 / 257).astype(np.uint8)
    write_png16(tmp_path / "a.png", rgb16)
    tifffile.imwrite(tmp_path / "b.tiff", rgb16)
    tifffile.imwrite(tmp_path / "c.tif", rgb16[..., 1])
    rgba8 = rng.integers(0, 256, (40, 60, 4), dtype=np.uint8)
    cv2.imwrite(str(tmp_path / "d.png"), cv2.cvtColor(rgba8, cv2.COLOR_RGBA2BGRA))
    np.testing.assert_array_equal(crossval.load_photo(tmp_path / "a.png"), expected)
    np.testing.assert_array_equal(crossval.load_photo(tmp_path / "b.tiff"), expected)
    grey = crossval.load_photo(tmp_path / "c.tif")
    assert grey.shape == (40, 60, 3) and np.array_equal(grey[..., 0], expected[..., 1]) and np.array_equal(grey[..., 2], expected[..., 1])
    np.testing.assert_array_equal(crossval.load_photo(tmp_path / "d.png"), rgba8[..., :3])
    cv2.imwrite(str(tmp_path / "e.jpg"), np.full((700, 350, 3), 128, np.uint8))
    assert crossval.load_photo(tmp_path / "e.jpg").shape == (512, 256, 3)
    assert len(crossval.load_photos(tmp_path)) == 5


def test_photo_loader_rejects_what_it_cannot_use(tmp_path):
    tifffile.imwrite(tmp_path / "f.tif", np.zeros((8, 8, 3), np.float32), photometric="rgb")
    with pytest.raises(ValueError, match="8- or 16-bit"):
        crossval.load_photo(tmp_path / "f.tif")
    with pytest.raises(ValueError, match="expected a photo ending in"):
        crossval.load_photo(tmp_path / "g.bmp")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="got none"):
        crossval.load_photos(tmp_path / "empty")
    with pytest.raises(ValueError, match="at least 2 photos"):
        crossval.synthetic_set([np.zeros((100, 100, 3), np.uint8)] * 3, 1, 128)


def test_plots_are_pngs_of_the_requested_size(tmp_path):
    plots.plot_lines(tmp_path / "l.png", ["0", "2", "4"], {"a": [20.0, 21.5, float("nan")], "b": [25.0, 24.0, 23.0]},
                        "title", "x", "y", intervals={"a": [(19, 21), (21, 22), (0, 0)]}, size=(640, 400))
    plots.plot_bars(tmp_path / "b.png", ["m1", "m2"], {"set1": [20.0, 30.0], "set2": [25.0, float("nan")]},
                       "title", "y", size=(500, 360))
    lines, bars = cv2.imread(str(tmp_path / "l.png")), cv2.imread(str(tmp_path / "b.png"))
    assert lines.shape == (400, 640, 3) and bars.shape == (360, 500, 3)
    assert (lines < 128).any() and (bars != 255).any()
    with pytest.raises(ValueError, match="expected 2 values"):
        plots.plot_lines(None, ["0", "1"], {"a": [1.0]}, "t", "x", "y")


def test_nice_ticks_cover_the_range_with_round_steps():
    ticks = plots.nice_ticks(17.3, 31.2)
    assert ticks[0] <= 17.3 and ticks[-1] >= 31.2
    step = ticks[1] - ticks[0]
    assert step / 10 ** math.floor(math.log10(step)) in (1, 2, 2.5, 5)
    assert plots.nice_ticks(3.0, 3.0)[0] <= 3.0 <= plots.nice_ticks(3.0, 3.0)[-1]


def test_tolerance_checker_names_each_figure_out_of_tolerance():
    expected = {"crossval/x/network/psnr_t": 30.0, "crossval/x/network/rmse_t": 0.04, "crossval/x/network/ssim_t": 0.8,
                "crossval/x/gap_t": 0.5, "crossval/absent/none/psnr_t": 20.0}
    good = {"crossval/x/network/psnr_t": 30.25, "crossval/x/network/rmse_t": 0.0415, "crossval/x/network/ssim_t": 0.805,
            "crossval/x/gap_t": 0.3, "crossval/y/none/psnr_t": 1.0}
    assert bench_check.check_figures(good, expected, absent_prefixes=["crossval/absent/"]) == []
    bad = {**good, "crossval/x/network/psnr_t": 29.5, "crossval/x/network/rmse_t": 0.05}
    problems = bench_check.check_figures(bad, expected)
    assert len(problems) == 3
    assert any(p.startswith("crossval/x/network/psnr_t: measured 29.5") for p in problems)
    assert any(p.startswith("crossval/x/network/rmse_t") for p in problems)
    assert any(p.startswith("crossval/absent/none/psnr_t") and "not measured" in p for p in problems)
    assert bench_check.check_figures({"crossval/x/network/psnr_t": float("nan")}, {"crossval/x/network/psnr_t": 30.0})
    assert bench_check.check_figures({"a/m/failed": 1.0}, {}) == ["a/m/failed: the method refused 1 patch(es), expected none"]
    assert bench_check.check_figures({}, {"a/m/failed": 1.0}) == ["a/m/failed: measured 0, expected 1 ± 0"]
    with pytest.raises(ValueError, match="expected a figure key"):
        bench_check.tolerance_for("crossval/x/network/seconds")


def test_verify_expected_raises_naming_the_figures_and_the_update_command():
    settings = bench_plan.settings_for(quick=True)
    weights = {"network": {"file": "urd-canonical.pt", "sha256": "ab" * 32}}
    env = {"commit": "c0ffee", "date": "today", "cpu": "a CPU", "precision": "fp32"}
    figures = {"robustness/noise/high/network/psnr_t": 28.0, "robustness/noise/high/gap_t": 0.2}
    document = json.loads(json.dumps(bench_check.expected_document(figures, settings, env, weights)))
    assert bench_check.verify_expected(figures, document, settings, weights) == []
    notes = bench_check.verify_expected(figures, document, settings, {"network": {"file": "new.pt", "sha256": "cd" * 32}})
    assert notes and "weights differ" in notes[0]
    with pytest.raises(BenchmarkMismatch) as info:
        bench_check.verify_expected({**figures, "robustness/noise/high/network/psnr_t": 27.0}, document, settings, weights)
    assert "robustness/noise/high/network/psnr_t: measured 27" in str(info.value)
    assert bench_check.UPDATE_COMMAND in str(info.value) and "gap_t" not in str(info.value)
    elsewhere = bench_check.verify_expected({**figures, "robustness/noise/high/network/psnr_t": 20.0}, document, settings,
                                         weights, robust_source="skimage-bundled")
    assert len(elsewhere) == 1 and "robustness figures not checked" in elsewhere[0]
    with pytest.raises(BenchmarkMismatch, match="other quick settings"):
        bench_check.verify_expected(figures, document, bench_plan.settings_for(quick=False), weights)


def test_flatten_figures_and_gap():
    per = [30.0, 31.0, 29.0]
    rows = [{"method": m, "rmse_t": 0.1, "psnr_t": np.mean(p), "ssim_t": 0.5, "rmse_r": 0.1, "psnr_r": 20.0, "ssim_r": 0.4,
             "psnr_t_per_patch": p} for m, p in (("network", per), ("direct", [v - 0.5 for v in per]))]
    g = scoring.gap(rows)
    assert g["mean"] == pytest.approx(0.5) and g["wins"] == 3 and g["ci95"][0] == pytest.approx(0.5)
    assert scoring.gap(rows[:1]) is None
    flat = bench_check.flatten_figures({"s": rows}, [], [])
    assert flat["crossval/s/gap_t"] == pytest.approx(0.5) and flat["crossval/s/direct/psnr_t"] == pytest.approx(29.5)
    assert len(flat) == 13


def test_settings_and_speed_stack():
    assert bench_plan.settings_for(quick=True).crossval_methods == ("none", "network", "direct", "schechner")
    with pytest.raises(ValueError, match="only in the full run"):
        bench_plan.settings_for(quick=True, large=True)
    stack = speed.speed_stack(64, 96)
    assert stack.shape == (3, 64, 96, 3) and stack.dtype == np.float32 and 0 <= stack.min() and stack.max() <= 1
    assert np.array_equal(stack, speed.speed_stack(64, 96))
    timing = speed.time_method("none", 64, 96)
    assert timing["seconds"] >= 0 and timing["peak_rss_mb"] > 0


@pytest.mark.slow
def test_run_isolated_returns_the_result_or_the_child_error():
    assert speed.run_isolated(plots.nice_ticks, (0.0, 1.0), timeout_s=120)[0] == 0.0
    with pytest.raises(RuntimeError, match="only in the full run"):
        speed.run_isolated(bench_plan.settings_for, (True, True), timeout_s=120)


def test_bsds_set_is_the_benchmark_set():
    from separate.bench import benchmark_set
    from separate.synthesis import load_image_pool

    folder = shared_data("natural", "bsds500", "test")
    ours = crossval.synthetic_set(load_image_pool([folder]), 2, 128)
    theirs = benchmark_set(2, 128)
    assert all(np.array_equal(ours[k], theirs[k]) for k in ("obs", "r", "t"))


def test_driver_writes_outputs_updates_and_checks_expected_values(tmp_path, monkeypatch):
    from separate.synthesis import load_image_pool

    tiny = bench_plan.Settings(True, ("none",), 2, 64, ("none",), 2, 64, ("none",), (64, 96), False, 2, 3)
    monkeypatch.setattr(bench_run, "settings_for", lambda quick, large=False: tiny)
    monkeypatch.setattr(bench_run, "photo_pools", lambda images_dir=None: [
        ("bsds500-test", "absent here", None), ("skimage-bundled", "bundled", load_image_pool(None))])
    monkeypatch.setattr(bench_run, "synthesis_throughput", lambda count: [
        {"mode": "classic", "patches": count, "size": 128, "patches_per_s": 1.0, "rejected": 0}])
    monkeypatch.setattr(bench_run, "run_isolated", lambda function, args, timeout_s=0: (
        function(*args) if function is speed.time_method else
        {"steps_per_s": 1.0, "patches_per_s": 16.0, "steps_timed": 1, "patch": 64, "batch": 16, "threads": 1, "precision": "fp32"}))
    expected = tmp_path / "expected.json"
    result = bench_run.run_evaluation(tmp_path, True, update_expected=True, expected_path=expected, command="urd bench --quick")
    folder = tmp_path / "quick"
    assert result["check"]["status"] == "updated" and expected.is_file()
    assert all((folder / name).is_file() for name in result["files"])
    report = (folder / "tables.md").read_text()
    assert "`urd bench --quick`" in report and "Not measured: the photos are not on this machine." in report
    assert cv2.imread(str(folder / "robustness_noise.png")).shape == (540, 900, 3)
    again = bench_run.run_evaluation(tmp_path, True, expected_path=expected)
    assert again["check"]["status"] == "passed" and again["figures"] == result["figures"]
    document = json.loads(expected.read_text())
    key = "robustness/noise/high/none/psnr_t"
    document["figures"][key] += 1.0
    expected.write_text(json.dumps(document))
    with pytest.raises(BenchmarkMismatch, match=key):
        bench_run.run_evaluation(tmp_path, True, expected_path=expected)
    assert "FAILED" in (folder / "tables.md").read_text()
    with pytest.raises(ValueError, match="only with quick"):
        bench_run.run_evaluation(tmp_path, False, update_expected=True)


def test_photo_pools_name_the_users_folder_and_never_replace_an_absent_set(tmp_path, monkeypatch):
    monkeypatch.setattr(crossval, "SHARED_NATURAL", tmp_path / "no-shared-data")
    photos = tmp_path / "mine"
    photos.mkdir()
    tifffile.imwrite(photos / "a.tif", np.full((300, 400, 3), 40000, np.uint16))
    cv2.imwrite(str(photos / "b.png"), np.full((300, 400, 3), 7, np.uint8))
    pools = crossval.photo_pools(photos)
    assert [(name, pool is None) for name, _, pool in pools] == [
        ("bsds500-test", True), ("skimage-bundled", False), ("images-mine", False)]
    assert [int(p[0, 0, 0]) for p in pools[2][2]] == [156, 7]
