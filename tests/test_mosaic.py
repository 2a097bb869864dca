"""Polarization mosaics: layouts verified on real captures."""

import cv2
import numpy as np
import pytest

from conftest import shared_data
from separate import optics
from urd.mosaic import ANGLES_DEG, MosaicLayout, build_mosaic, split_mosaic


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


def test_urd_ingest_mosaic_frames_then_separate(tmp_path):
    import subprocess
    import sys

    frame = shared_data("polarization", "imx250mzr-polanalyser", "carps_IMX250MZR.png")
    out = subprocess.run([sys.executable, "-m", "urd.cli", "ingest", str(frame), str(tmp_path / "ds"), "--mosaic", "imx250mzr"],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    from urd.dataset import Dataset
    from urd.ingest import load_stack

    stack, angles = load_stack(Dataset.open(tmp_path / "ds").scene("scene_01"))
    assert stack.shape == (4, 1024, 1224, 3) and angles == [0.0, 45.0, 90.0, 135.0]
    malus = float((stack[0] + stack[2] - stack[1] - stack[3]).mean() / (stack[0] + stack[2]).mean())
    assert abs(malus) < 0.05                                 # I0 + I90 ≈ I45 + I135 within 5 %
    out = subprocess.run([sys.executable, "-m", "urd.cli", "separate", "scene_01", "--dataset", str(tmp_path / "ds"),
                          "--method", "schechner"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
