"""Polarization mosaics: layouts verified on real captures; demosaicing that registers the four
polarizer sites (no false polarization at edges), on synthetic mosaics with known truth and on
the real captures."""

import cv2
import numpy as np
import pytest

from conftest import shared_data
from separate import optics
from urd.core.mosaic import ANGLES_DEG, Demosaic, MosaicLayout, build_mosaic, demosaic, split_mosaic

PHI = np.radians(ANGLES_DEG)


@pytest.mark.parametrize("layout", list(MosaicLayout))
def test_build_then_split_round_trip(layout):
    rng = np.random.default_rng(0)
    channels = 1 if layout.spec.colours is None else 3
    flat = rng.random((1, 1, 1, channels)).astype(np.float32) * np.ones((4, 16, 24, channels), np.float32)
    flat *= np.arange(1, 5, dtype=np.float32)[:, None, None, None]
    stack, angles = split_mosaic(build_mosaic(flat, layout), layout)
    assert angles == list(ANGLES_DEG) and stack.shape == (4, 8, 12, channels)
    np.testing.assert_allclose(stack, flat[:, ::2, ::2], rtol=1e-6)


def test_bad_mosaic_shape():
    with pytest.raises(ValueError, match="divisible by 4"):
        split_mosaic(np.zeros((6, 8)), MosaicLayout.WEN2019)


def test_wen2019_layout_reproduces_the_published_colour_mosaic_exactly():
    folder = shared_data("polarization", "wen2019-rgbpol", "scene61")
    gt = np.stack([cv2.imread(str(folder / f"gt_{a}.png"))[..., ::-1] for a in (0, 45, 90, 135)])
    mosaic = cv2.imread(str(folder / "net_input.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(build_mosaic(gt, MosaicLayout.WEN2019), mosaic)
    # Sony's colour layout orders the polarizers differently: it does not reproduce the file
    assert (build_mosaic(gt, MosaicLayout.IMX250MYR) != mosaic).mean() > 0.3
    stack, _ = split_mosaic(mosaic, MosaicLayout.WEN2019)
    np.testing.assert_array_equal(stack[1, ::2, ::2, 0], gt[1, 0::4, 1::4, 0])   # 45°, red, exact samples


def test_imx250mzr_polarizer_target_gives_four_filters_45_degrees_apart():
    path = shared_data("polarization", "imx250mzr-polanalyser", "polarizer_IMX250MZR.png")
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    stack, angles = split_mosaic(raw, MosaicLayout.IMX250MZR)
    stokes = optics.stokes_from_images(stack[..., 0], np.radians(angles))
    s0 = cv2.GaussianBlur(stokes[0], (0, 0), 3).astype(np.float32)
    circles = cv2.HoughCircles(np.clip(s0 / s0.max() * 255, 0, 255).astype(np.uint8), cv2.HOUGH_GRADIENT,
                               dp=2, minDist=200, param1=60, param2=60, minRadius=80, maxRadius=140)[0]
    assert len(circles) == 4
    yy, xx = np.mgrid[: s0.shape[0], : s0.shape[1]]
    aolps = []
    for x, y, r in sorted(circles, key=lambda c: c[0]):       # filters labelled 0, 45, 90, 135
        inside = (yy - y) ** 2 + (xx - x) ** 2 < (0.6 * r) ** 2
        psi = np.angle(np.mean(np.exp(2j * optics.aolp(stokes)[inside]))) / 2
        aolps.append(np.degrees(psi) % 180)
        dark = int(np.argmin([stack[k, ..., 0][inside].mean() for k in range(4)]))
        assert abs((angles[dark] - aolps[-1] - 90 + 90) % 180 - 90) <= 22.5  # dark channel ⟂ AoLP
    steps = [((b - a + 90) % 180) - 90 for a, b in zip(aolps, aolps[1:])]
    assert all(abs(s + 45) < 7 for s in steps), (aolps, steps)               # −45° per filter, in order


@pytest.mark.slow
def test_urd_ingest_mosaic_frames_then_separate(tmp_path):
    import subprocess
    import sys

    frame = shared_data("polarization", "imx250mzr-polanalyser", "carps_IMX250MZR.png")
    out = subprocess.run([sys.executable, "-m", "urd.cli", "ingest", str(frame), str(tmp_path / "ds"), "--mosaic", "imx250mzr"],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    from urd.core.dataset import Dataset

    stack, angles = Dataset.open(tmp_path / "ds").scene("scene_01").load_stack()
    assert stack.shape == (4, 1024, 1224, 3) and angles == [0.0, 45.0, 90.0, 135.0]
    malus = float((stack[0] + stack[2] - stack[1] - stack[3]).mean() / (stack[0] + stack[2]).mean())
    assert abs(malus) < 0.05                                 # I0 + I90 ≈ I45 + I135 within 5 %
    out = subprocess.run([sys.executable, "-m", "urd.cli", "separate", "scene_01", "--dataset", str(tmp_path / "ds"),
                          "--method", "schechner"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr


def synthetic_truth(size=192, channels=1, seed=0):
    """(4, size, size, channels) float32 at 0/45/90/135 from known Stokes parameters: a smooth
    weakly polarized background, unpolarized and polarized boxes and discs with sharp (4×
    supersampled) edges, and an unpolarized Siemens star."""
    rng = np.random.default_rng(seed)
    ss, n = 4, size * 4
    yy, xx = np.mgrid[:n, :n].astype(np.float32) / ss
    s0 = 0.2 + 0.1 * xx / size
    dolp, aolp = np.full_like(s0, 0.05), np.full_like(s0, 0.4)
    tint = np.ones((n, n, channels), np.float32)
    rr, theta = np.hypot(yy - size / 4, xx - size / 4), np.arctan2(yy - size / 4, xx - size / 4)
    shapes = [((rr < size / 5) & (np.sin(12 * theta) > 0), 0.8, 0.0, 0.0), ((rr < size / 5) & (np.sin(12 * theta) <= 0), 0.1, 0.0, 0.0)]
    for k in range(8):
        y0, x0, r = rng.uniform(0.1, 0.9) * size, rng.uniform(0.5, 0.9) * size, rng.uniform(0.05, 0.12) * size
        inside = (np.hypot(yy - y0, xx - x0) < r) if k % 2 else (np.abs(yy - y0) < r) & (np.abs(xx - x0) < 0.7 * r)
        shapes.append((inside, rng.uniform(0.05, 0.9), [0.0, 0.4][k % 2], rng.uniform(-1.5, 1.5)))
    for inside, value, d, a in shapes:
        s0[inside], dolp[inside], aolp[inside] = value, d, a
        tint[inside] = rng.uniform(0.4, 1.0, channels) if channels > 1 else 1.0
    stokes = optics.stokes_from_polarization(s0, dolp, aolp)[..., None] * tint
    images = [optics.intensity_from_stokes(stokes, phi).astype(np.float32) for phi in PHI]
    return np.stack([cv2.resize(im, (size, size), interpolation=cv2.INTER_AREA).reshape(size, size, channels) for im in images])


def cell_mean(stack):
    return (stack[:, 0::2, 0::2] + stack[:, 0::2, 1::2] + stack[:, 1::2, 0::2] + stack[:, 1::2, 1::2]) / 4


def dolp_of(stack):
    return np.clip(optics.dolp(optics.stokes_from_images(stack.mean(axis=-1), PHI)), 0, 1)


def edge_and_flat(s0):
    """Edges: the strongest 5% of |∇S0|; flat: no gradient above the median within 5×5 pixels."""
    gy, gx = np.gradient(s0.astype(np.float32))
    g = np.hypot(gx, gy)
    return g >= np.quantile(g, 0.95), cv2.dilate(g, np.ones((5, 5), np.uint8)) <= np.median(g)


@pytest.mark.parametrize("layout", [MosaicLayout.IMX250MZR, MosaicLayout.WEN2019])
def test_registered_demosaicing_removes_false_edge_polarization_of_a_synthetic_scene(layout):
    channels = 1 if layout.spec.colours is None else 3
    truth = synthetic_truth(channels=channels)
    cells = cell_mean(truth)
    true_dolp = dolp_of(cells)
    edges, flat = edge_and_flat(optics.stokes_from_images(cells.mean(axis=-1), PHI)[0])
    assert edges.sum() > 300 and flat.sum() > 500
    mosaic = build_mosaic(truth, layout)
    err = {}
    for method in Demosaic:
        stack, angles = demosaic(mosaic, layout, method)
        assert angles == list(ANGLES_DEG) and stack.shape == cells.shape and stack.dtype == np.float32
        error = np.abs(dolp_of(stack) - true_dolp)
        err[method] = error[edges].mean(), error[flat].mean()
        assert err[method][1] < (5e-3 if method is Demosaic.NONE else 1e-3), (method, err[method])   # flat areas: right
    assert err[Demosaic.NONE][0] > 0.1                                   # the unregistered sites: false DoLP at edges
    assert err[Demosaic.BILINEAR][0] < 0.5 * err[Demosaic.NONE][0], err
    assert err[Demosaic.NEWTON][0] < 0.5 * err[Demosaic.NONE][0], err
    assert err[Demosaic.NEWTON][0] < 0.85 * err[Demosaic.BILINEAR][0], err     # the gradient-aware one is better still


def test_full_size_keeps_each_sites_sample_and_newton_keeps_more_detail_of_s0_than_bilinear():
    layout = MosaicLayout.IMX250MZR
    truth = synthetic_truth()
    mosaic = build_mosaic(truth, layout)
    s0_true = optics.stokes_from_images(truth[..., 0], PHI)[0][4:-4, 4:-4]
    rmse = {}
    for method in (Demosaic.BILINEAR, Demosaic.NEWTON):
        stack, _ = demosaic(mosaic, layout, method, half_size=False)
        assert stack.shape == truth.shape
        for r in range(2):
            for c in range(2):
                k = ANGLES_DEG.index(layout.spec.angles[r][c])
                np.testing.assert_allclose(stack[k, r::2, c::2, 0], mosaic[r::2, c::2], atol=1e-6)
        s0 = optics.stokes_from_images(stack[..., 0], PHI)[0][4:-4, 4:-4]
        rmse[method] = float(np.sqrt(np.mean((s0 - s0_true) ** 2)))
    assert rmse[Demosaic.NEWTON] < 0.8 * rmse[Demosaic.BILINEAR], rmse


@pytest.mark.parametrize("method", list(Demosaic))
@pytest.mark.parametrize("layout", list(MosaicLayout))
@pytest.mark.parametrize("half_size", [True, False])
def test_demosaic_of_uniform_polarized_light_is_exact(method, layout, half_size):
    channels = 1 if layout.spec.colours is None else 3
    stokes = np.array([0.6, 0.6 * 0.5 * np.cos(1.0), 0.6 * 0.5 * np.sin(1.0)], np.float32)[:, None] * np.linspace(0.5, 1, channels)
    flat = np.stack([optics.intensity_from_stokes(stokes, phi) for phi in PHI])[:, None, None, :] * np.ones((1, 16, 24, 1), np.float32)
    stack, angles = demosaic(build_mosaic(flat.astype(np.float32), layout), layout.value, method.value, half_size=half_size)
    size = (8, 12) if half_size else (16, 24)
    assert angles == list(ANGLES_DEG) and stack.shape == (4, *size, channels)
    np.testing.assert_allclose(stack, flat[:, : size[0], : size[1]], rtol=1e-5)
    np.testing.assert_allclose(dolp_of(stack), 0.5, atol=1e-5)


def test_demosaic_none_is_the_split_and_keeps_integer_codes_in_their_units():
    raw = np.random.default_rng(2).integers(0, 4096, (8, 12)).astype(np.uint16)
    stack, _ = demosaic(raw, MosaicLayout.IMX250MZR, Demosaic.NONE)
    np.testing.assert_array_equal(stack, split_mosaic(raw, MosaicLayout.IMX250MZR)[0])
    assert stack[0, 0, 0, 0] == raw[1, 1] and stack[2, 0, 0, 0] == raw[0, 0]   # 0° bottom right, 90° top left
    full, _ = demosaic(raw, MosaicLayout.IMX250MZR, Demosaic.NONE, half_size=False)
    np.testing.assert_array_equal(full[:, ::2, ::2], stack)
    np.testing.assert_array_equal(full[:, 1::2, 1::2], stack)
    newton, _ = demosaic(raw, MosaicLayout.IMX250MZR, Demosaic.NEWTON)
    assert newton.min() >= raw.min() and newton.max() <= raw.max()      # cubic overshoot clipped to the frame's range


def test_the_colour_sensor_puts_each_polarizer_block_under_one_colour_block():
    """IMX250MYR's 4×4 tile: polarizers [[90, 45], [135, 0]] within colour blocks [[R, G], [G, B]]."""
    for (r, c), angle, colour in (((0, 0), 90, 0), ((3, 3), 0, 2), ((1, 2), 135, 1), ((0, 1), 45, 0)):
        raw = np.zeros((16, 16), np.uint16)
        raw[r::4, c::4] = 1000
        stack, angles = split_mosaic(raw, MosaicLayout.IMX250MYR)
        lit = [(angles[k], channel) for k in range(4) for channel in range(3) if stack[k, ..., channel].any()]
        assert lit == [(angle, colour)]


@pytest.mark.parametrize("frame, layout, method, kwargs, error, match", [
    ([[1, 2], [3, 4]], MosaicLayout.IMX250MZR, Demosaic.NEWTON, {}, TypeError, "expected frame as a numpy array"),
    (np.zeros((4, 4), bool), MosaicLayout.IMX250MZR, Demosaic.NEWTON, {}, TypeError, "got a bool array"),
    (np.zeros((4, 4)), 3, Demosaic.NEWTON, {}, TypeError, "expected layout as MosaicLayout"),
    (np.zeros((4, 4)), MosaicLayout.IMX250MZR, None, {}, TypeError, "expected method as Demosaic"),
    (np.zeros((4, 4)), MosaicLayout.IMX250MZR, Demosaic.NEWTON, {"half_size": 1}, TypeError, "expected half_size as a bool"),
    (np.zeros((4, 4, 3)), MosaicLayout.IMX250MZR, Demosaic.NEWTON, {}, ValueError, r"2-D mosaic .* got shape \(4, 4, 3\)"),
    (np.zeros((6, 8)), MosaicLayout.WEN2019, Demosaic.BILINEAR, {}, ValueError, "divisible by 4, got shape"),
    (np.zeros((5, 8)), MosaicLayout.IMX250MZR, Demosaic.BILINEAR, {}, ValueError, "divisible by 2, got shape"),
    (np.zeros((0, 8)), MosaicLayout.IMX250MZR, Demosaic.BILINEAR, {}, ValueError, "non-empty"),
    (np.full((4, 4), np.nan), MosaicLayout.IMX250MZR, Demosaic.NEWTON, {}, ValueError, "expected finite values, got 16"),
    (np.zeros((4, 4)), "imx250", Demosaic.NEWTON, {}, ValueError, "expected layout one of imx250mzr, imx250myr, wen2019, got 'imx250'"),
    (np.zeros((4, 4)), MosaicLayout.IMX250MZR, "cubic", {}, ValueError, "expected method one of none, bilinear, newton, got 'cubic'"),
])
def test_demosaic_checks_its_arguments(frame, layout, method, kwargs, error, match):
    with pytest.raises(error, match=match):
        demosaic(frame, layout, method, **kwargs)


def test_demosaic_names_are_the_cli_values():
    assert [m.value for m in Demosaic] == ["none", "bilinear", "newton"]
    assert Demosaic("newton") is Demosaic.NEWTON


@pytest.mark.slow
@pytest.mark.parametrize("name", ["camera", "polarizer"])
def test_registered_demosaicing_of_real_imx250mzr_frames_removes_false_edge_polarization(name):
    raw = cv2.imread(str(shared_data("polarization", "imx250mzr-polanalyser", f"{name}_IMX250MZR.png")), cv2.IMREAD_UNCHANGED)
    cells = raw.astype(np.float32)
    s0 = (cells[0::2, 0::2] + cells[0::2, 1::2] + cells[1::2, 0::2] + cells[1::2, 1::2]) / 2   # the same for every method
    saturated = (raw == 255)[0::2, 0::2] | (raw == 255)[0::2, 1::2] | (raw == 255)[1::2, 0::2] | (raw == 255)[1::2, 1::2]
    valid = (s0 >= np.quantile(s0, 0.2)) & ~saturated
    gy, gx = np.gradient(s0)
    g = np.hypot(gx, gy)
    edges = valid & (g >= np.quantile(g[valid], 0.95))
    flat = valid & (cv2.dilate(g, np.ones((5, 5), np.uint8)) <= np.median(g[valid]))
    edge, flat_dolp = {}, {}
    for method in Demosaic:
        dolp = dolp_of(demosaic(raw, MosaicLayout.IMX250MZR, method)[0])
        edge[method], flat_dolp[method] = float(np.median(dolp[edges])), float(np.median(dolp[flat]))
    assert edge[Demosaic.NONE] > 1.5 * flat_dolp[Demosaic.NONE], (edge, flat_dolp)       # false polarization at edges
    for method in (Demosaic.BILINEAR, Demosaic.NEWTON):
        assert edge[method] < 0.7 * edge[Demosaic.NONE], (method, edge)
        assert edge[method] < 1.5 * flat_dolp[method] + 0.01, (method, edge, flat_dolp)   # edges now look like the flat areas


@pytest.mark.slow
def test_registered_demosaicing_of_the_real_wen2019_colour_mosaic_against_its_truth():
    folder = shared_data("polarization", "wen2019-rgbpol", "scene61")
    gt = np.stack([cv2.imread(str(folder / f"gt_{a}.png"))[..., ::-1] for a in (0, 45, 90, 135)]).astype(np.float32)
    mosaic = cv2.imread(str(folder / "net_input.png"), cv2.IMREAD_UNCHANGED)
    cells = cell_mean(gt)
    true_dolp = dolp_of(cells)
    edges, _ = edge_and_flat(optics.stokes_from_images(cells.mean(axis=-1), PHI)[0])
    err = {m: float(np.abs(dolp_of(demosaic(mosaic, MosaicLayout.WEN2019, m)[0]) - true_dolp)[edges].mean()) for m in Demosaic}
    assert err[Demosaic.BILINEAR] < 0.3 * err[Demosaic.NONE], err
    assert err[Demosaic.NEWTON] < err[Demosaic.BILINEAR], err


def test_redo_demosaics_a_frame_again_as_it_was_ingested(tmp_path):
    import hashlib

    from typer.testing import CliRunner

    from urd.cli import app
    from urd.core.dataset import Dataset

    frame = tmp_path / "frames" / "frame.png"
    frame.parent.mkdir()
    cv2.imwrite(str(frame), np.random.default_rng(0).integers(1000, 60000, (64, 96), dtype=np.uint16))
    runner = CliRunner()
    assert runner.invoke(app, ["ingest", str(frame.parent), str(tmp_path / "ds"), "--mosaic", "imx250mzr",
                               "--demosaic", "bilinear"]).exit_code == 0
    scene = Dataset.open(tmp_path / "ds").scene("scene_01")
    aligned = sorted((scene.path / "aligned").glob("*.tiff"))
    digests = [hashlib.sha256(p.read_bytes()).hexdigest() for p in aligned]
    aligned[1].unlink()                                              # a damaged scene: rebuilt from its frame
    for args in (["ingest", str(scene.path), "--redo"], ["ingest", str(tmp_path / "ds"), "--redo", "--jobs", "2"]):
        out = runner.invoke(app, args)
        assert out.exit_code == 0 and "ingested scene_01" in out.stdout, out.output
        assert [hashlib.sha256(p.read_bytes()).hexdigest() for p in aligned] == digests
        assert scene.reload().ingest_options() == {"mosaic": "imx250mzr", "demosaic": "bilinear", "transfer": "linear"}
    assert Dataset.open(tmp_path / "ds").scene("scene_01").verify() == []
