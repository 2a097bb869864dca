"""Benchmark of polarization demosaicing (`urd.core.mosaic.demosaic`): false polarization at edges.

For each method of `urd.core.mosaic.Demosaic` it prints the DoLP on edges and on flat regions, and
the runtime per megapixel of mosaic, on

(a) synthetic mosaics with known truth, rendered with `separate.optics` (4× supersampled, then
    area-reduced: sharp but band-limited edges): unpolarized and polarized discs and boxes, a
    Siemens star, a 1/f texture under uniform polarization, a smooth background; mono
    (IMX250MZR layout), mono with Gaussian noise σ = 0.005 (1.3 DN at 8 bit), and colour
    (Wen 2019 layout); and a photo through glass (urd's case): two BSDS500 test photos as
    reflection and transmission, rendered with `separate.optics.render` (paper Eq. 1; θ = 55°,
    φ⊥ = 10°, reflection ×3), mono and colour, when ../shared/data/natural is present. Also the
    errors against the truth: mean |ΔDoLP| on edges and on flat regions, RMSE of S0 (relative:
    divided by the mean true S0), DoLP and AoLP (AoLP where the true DoLP ≥ 0.1, in degrees);
(b) every real mosaic in ../shared/data/polarization: the four IMX250MZR frames (no truth) and
    Wen 2019 scene61 net_input.png (colour; truth: its gt_*.png, taken with a rotated
    polarizer);
(c) the Lapray 2018 near-infrared division-of-time frames, mosaicked here in the IMX250MZR
    layout (truth known, but its four angles are up to ~0.3 px misregistered and their noise
    is independent, which penalizes methods that borrow detail across channels).

Definitions. All figures are on the output grid of ``demosaic(..., half_size=True)`` (one pixel
per 2×2 polarizer cell; the truth is the cell mean of each angle) unless ``--full-size``.
Stokes parameters come from the mean over colour channels; DoLP is clipped to [0, 1]. The
reference S0 is the truth where it is known, else (real mono frames) the sum of each cell's four
pixels divided by 2, which is the same for every method. g = |∇S0| (central differences).
Valid pixels: S0 at or above its 20th percentile and no pixel of the cell at the frame's
saturation code. Edges: valid pixels with g at or above the 95th percentile of g over valid
pixels. Flat: valid pixels whose largest g within 5×5 pixels is at most the median of g. The
"edge"/"flat" figures are the median DoLP over those masks; on flat regions it is the scene's
own polarization, on edges the excess over it is false polarization.

Usage: python tools/bench_demosaic.py [--full-size] [--size 1024] [--markdown]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from separate import optics
from urd.core.mosaic import ANGLES_DEG, Demosaic, MosaicLayout, build_mosaic, demosaic

from toolargs import Formatter

SHARED = Path(__file__).resolve().parent.parent.parent / "shared" / "data"
DATA = SHARED / "polarization"
PHOTOS = SHARED / "natural" / "bsds500" / "test"
PHI = np.radians(ANGLES_DEG)


def synthetic_scene(size: int, channels: int, seed: int = 0) -> np.ndarray:
    """Full-resolution truth (4, size, size, channels) float32 in [0, 1] at 0/45/90/135."""
    rng = np.random.default_rng(seed)
    ss = 4
    n = size * ss
    yy, xx = np.mgrid[:n, :n].astype(np.float32) / ss
    s0 = 0.15 + 0.2 * xx / size
    dolp = np.full_like(s0, 0.05)
    aolp = np.full_like(s0, np.radians(20.0))
    tint = np.ones((n, n, channels), np.float32)

    def paint(mask, value, d, a):
        s0[mask], dolp[mask], aolp[mask] = value, d, a
        tint[mask] = rng.uniform(0.4, 1.0, channels) if channels > 1 else 1.0

    # Siemens star: 36 unpolarized spokes
    cy, cx, radius = 0.27 * size, 0.27 * size, 0.22 * size
    rr, theta = np.hypot(yy - cy, xx - cx), np.arctan2(yy - cy, xx - cx)
    star = rr < radius
    paint(star & (np.sin(18 * theta) > 0), 0.7, 0.0, 0.0)
    paint(star & (np.sin(18 * theta) <= 0), 0.1, 0.0, 0.0)
    # 1/f texture under uniform polarization
    noise = np.fft.ifft2(np.fft.fft2(rng.normal(size=(size, size))) / np.maximum(np.hypot(*np.meshgrid(
        np.fft.fftfreq(size), np.fft.fftfreq(size))), 1.0 / size)).real
    texture = cv2.resize(((noise - noise.min()) / np.ptp(noise)).astype(np.float32), (n, n), interpolation=cv2.INTER_NEAREST)
    box = (yy > 0.55 * size) & (yy < 0.95 * size) & (xx > 0.05 * size) & (xx < 0.45 * size)
    paint(box, 0.1 + 0.8 * texture[box], 0.3, np.radians(-30.0))
    # discs and boxes, unpolarized or polarized, on the right half
    for _ in range(14):
        y0, x0, r = rng.uniform(0.05, 0.95) * size, rng.uniform(0.5, 0.95) * size, rng.uniform(0.03, 0.12) * size
        shape = (np.hypot(yy - y0, xx - x0) < r) if rng.random() < 0.5 else (np.abs(yy - y0) < r) & (np.abs(xx - x0) < 0.6 * r)
        paint(shape, rng.uniform(0.05, 0.9), rng.choice([0.0, 0.0, 0.3, 0.6]), rng.uniform(-np.pi / 2, np.pi / 2))
    stokes = optics.stokes_from_polarization(s0, dolp, aolp)[..., None] * tint
    images = np.stack([optics.intensity_from_stokes(stokes, phi) for phi in PHI]).astype(np.float32)
    return np.stack([cv2.resize(im, (size, size), interpolation=cv2.INTER_AREA).reshape(size, size, channels) for im in images])


def glass_scene(reflection: Path, transmission: Path) -> np.ndarray:
    """Truth (4, 320, 480, 3) float32: two photos seen through glass at 0/45/90/135 (Eq. 1)."""
    def load(path: Path) -> np.ndarray:
        image = cv2.imread(str(path))[..., ::-1]
        image = image if image.shape[0] < image.shape[1] else np.rot90(image)
        return optics.photo_to_linear(np.ascontiguousarray(image[:320, :480])).astype(np.float32)

    i_r, i_t = load(reflection), load(transmission)
    return np.stack([optics.render(3 * i_r, i_t, np.radians(55.0), np.radians(10.0), phi) for phi in PHI]).astype(np.float32)


def cell_mean(stack: np.ndarray) -> np.ndarray:
    """(N, H, W, C) → (N, H/2, W/2, C): mean of each 2×2 cell."""
    return (stack[:, 0::2, 0::2] + stack[:, 0::2, 1::2] + stack[:, 1::2, 0::2] + stack[:, 1::2, 1::2]) / 4


def stokes_of(stack: np.ndarray) -> np.ndarray:
    return optics.stokes_from_images(stack.mean(axis=-1), PHI)


def masks(s0: np.ndarray, saturated: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Edge and flat masks from the reference S0 (see the module docstring)."""
    valid = s0 >= np.quantile(s0, 0.2)
    if saturated is not None:
        valid &= ~saturated
    gy, gx = np.gradient(s0.astype(np.float32))
    g = np.hypot(gx, gy)
    edges = valid & (g >= np.quantile(g[valid], 0.95))
    flat = valid & (cv2.dilate(g, np.ones((5, 5), np.uint8)) <= np.median(g[valid]))
    return edges, flat


def timed(frame: np.ndarray, layout: MosaicLayout, method: Demosaic, half_size: bool) -> tuple[np.ndarray, float]:
    """Demosaic, best of two runs; seconds per megapixel of mosaic."""
    best = float("inf")
    for _ in range(2):
        start = time.perf_counter()
        stack, _ = demosaic(frame, layout, method, half_size=half_size)
        best = min(best, time.perf_counter() - start)
    return stack, best / (frame.size / 1e6)


def rmse(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x, dtype=np.float64))))


def evaluate(frame, layout, half_size, truth=None, saturated=None):
    """Rows of figures per method for one mosaic; ``truth`` (4, H', W', C) on the output grid."""
    rows = {}
    if truth is not None:
        ref = stokes_of(truth)
        true_dolp, true_aolp = np.clip(optics.dolp(ref), 0, 1), optics.aolp(ref)
    else:
        cells = frame.astype(np.float32)
        ref_s0 = (cells[0::2, 0::2] + cells[0::2, 1::2] + cells[1::2, 0::2] + cells[1::2, 1::2]) / 2
        if not half_size:
            ref_s0 = np.repeat(np.repeat(ref_s0, 2, axis=0), 2, axis=1)
        ref = ref_s0[None]
    if saturated is not None and not half_size:
        saturated = np.repeat(np.repeat(saturated, 2, axis=0), 2, axis=1)
    edges, flat = masks(ref[0], saturated)
    for method in Demosaic:
        stack, s_per_mp = timed(frame, layout, method, half_size)
        stokes = stokes_of(stack)
        dolp = np.clip(optics.dolp(stokes), 0, 1)
        row = {"edge": float(np.median(dolp[edges])), "flat": float(np.median(dolp[flat])), "s_per_mp": s_per_mp}
        if truth is not None:
            strong = true_dolp >= 0.1
            d_aolp = (optics.aolp(stokes) - true_aolp + np.pi / 2) % np.pi - np.pi / 2
            row |= {"err_edge": float(np.abs(dolp - true_dolp)[edges].mean()), "err_flat": float(np.abs(dolp - true_dolp)[flat].mean()),
                    "rel_rmse_s0": rmse(stokes[0] - ref[0]) / float(ref[0].mean()), "rmse_dolp": rmse(dolp - true_dolp),
                    "rmse_aolp_deg": float(np.degrees(rmse(d_aolp[strong])))}
        rows[method.value] = row
    return rows


def show(title: str, rows: dict) -> None:
    keys = list(next(iter(rows.values())))
    print(f"\n{title}")
    print(f"  {'method':9s} " + " ".join(f"{k:>13s}" for k in keys))
    for name, row in rows.items():
        print(f"  {name:9s} " + " ".join(f"{row[k]:13.4f}" for k in keys))


def read(path: Path) -> np.ndarray:
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)


def mosaic_side(text: str) -> int:
    """A side of the synthetic mosaics: a multiple of 4 of at least 64 px."""
    if not text.isdigit() or int(text) < 64 or int(text) % 4:
        raise argparse.ArgumentTypeError(f"expected a multiple of 4 of at least 64 (px), got {text!r}")
    return int(text)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=Formatter)
    parser.add_argument("--full-size", action="store_true", help="evaluate at every pixel instead of one pixel per 2×2 cell")
    parser.add_argument("--size", type=mosaic_side, default=1024, help="side of the synthetic mosaics (px, multiple of 4)")
    parser.add_argument("--markdown", action="store_true", help="also print a summary table in Markdown")
    args = parser.parse_args()
    half = not args.full_size
    grid = (lambda stack: cell_mean(stack)) if half else (lambda stack: stack)
    results = {}
    print(f"output grid: {'one pixel per 2×2 cell (half size)' if half else 'every pixel (full size)'}")

    mono, colour = MosaicLayout.IMX250MZR, MosaicLayout.WEN2019
    truth = synthetic_scene(args.size, 1)
    results["synthetic mono"] = evaluate(build_mosaic(truth, mono), mono, half, grid(truth))
    noisy = build_mosaic(truth, mono) + np.random.default_rng(1).normal(0, 0.005, (args.size, args.size)).astype(np.float32)
    results["synthetic mono, noise 0.005"] = evaluate(noisy, mono, half, grid(truth))
    truth = synthetic_scene(args.size, 3)
    results["synthetic colour (wen2019)"] = evaluate(build_mosaic(truth, colour), colour, half, grid(truth))
    photos = sorted(PHOTOS.glob("*.jpg"))[:2]
    if len(photos) == 2:
        truth = glass_scene(*photos)
        grey = truth.mean(axis=-1, keepdims=True)
        results["synthetic glass mono"] = evaluate(build_mosaic(grey, mono), mono, half, grid(grey))
        results["synthetic glass colour (wen2019)"] = evaluate(build_mosaic(truth, colour), colour, half, grid(truth))

    for path in sorted((DATA / "imx250mzr-polanalyser").glob("*_IMX250MZR.png")):
        raw = read(path)
        sat = raw >= np.iinfo(raw.dtype).max
        sat = sat[0::2, 0::2] | sat[0::2, 1::2] | sat[1::2, 0::2] | sat[1::2, 1::2]
        results[f"real {path.stem}"] = evaluate(raw, mono, half, saturated=sat)
    scene = DATA / "wen2019-rgbpol" / "scene61"
    if scene.is_dir():
        gt = np.stack([read(scene / f"gt_{a:g}.png")[..., ::-1] for a in ANGLES_DEG]).astype(np.float32)
        results["real wen2019 scene61"] = evaluate(read(scene / "net_input.png"), colour, half, grid(gt))
    for folder in sorted(p for p in (DATA / "lapray2018-nir").glob("*") if p.is_dir()):
        frames = np.stack([read(folder / f"nir_{a:g}.tif") for a in ANGLES_DEG])[..., None]
        results[f"lapray {folder.name} (mosaicked here)"] = evaluate(build_mosaic(frames, mono), mono, half,
                                                                    grid(frames.astype(np.float32)))
    for title, rows in results.items():
        show(title, rows)
    if args.markdown:
        markdown(results)


def markdown(results: dict) -> None:
    """Two summary tables: against known truth, and the real mosaics."""
    methods = [d.value for d in Demosaic]
    truth_sets = [k for k, rows in results.items() if "err_edge" in rows["none"]]
    print("\nFalse polarization against known truth: mean |ΔDoLP| on edges (RMSE of DoLP in brackets)\n")
    print("| method | " + " | ".join(truth_sets) + " |")
    print("|---|" + "---|" * len(truth_sets))
    for m in methods:
        cells = [f"{results[k][m]['err_edge']:.3f} ({results[k][m]['rmse_dolp']:.3f})" for k in truth_sets]
        print(f"| {m} | " + " | ".join(cells) + " |")
    real = [k for k in results if k.startswith("real")]
    print("\nReal mosaics: median DoLP on edges / on flat regions; runtime (median over the IMX250MZR frames)\n")
    print("| method | " + " | ".join(k.removeprefix("real ").removesuffix("_IMX250MZR") for k in real) + " | s per MP |")
    print("|---|" + "---|" * (len(real) + 1))
    for m in methods:
        speed = np.median([results[k][m]["s_per_mp"] for k in real if "IMX250MZR" in k] or [float("nan")])
        cells = [f"{results[k][m]['edge']:.3f} / {results[k][m]['flat']:.3f}" for k in real]
        print(f"| {m} | " + " | ".join(cells) + f" | {speed:.3f} |")


if __name__ == "__main__":
    main()
