"""Contact sheets of every real capture in ../shared/data/polarization, per method.

    python tools/contact_sheets.py [--out contact-sheets] [--size 512] [--methods none,network,schechner,kong]
                                   [--weights FILE]

One PNG per capture: a row per method with S0 | T̂ | R̂ | DoLP | AoLP (hue = AoLP over 0-180°,
brightness = DoLP) and the presence map, all sRGB-encoded with one white point per capture
(the 99.5th percentile of S0); the reference each method used (as `urd separate` chooses it:
the estimated field, its side settled by a trial separation where it was only assumed,
`urd.separation.separate_inspected`) and the share of light put into R̂ are written on the row.
Prints one line per capture and method. An existing sheet in --out is replaced only with --force.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from separate import optics
from separate.methods import METHODS, get_method
from urd.core import samples
from urd.core.errors import UrdError
from urd.core.images import srgb_to_linear, to_display
from urd.separation import separate_inspected

from toolargs import Formatter, positive


def method_list(text: str) -> list[str]:
    """Comma-separated names of `separate.methods.METHODS`."""
    names = [name for name in text.split(",") if name]
    if not names or any(name not in METHODS for name in names):
        raise argparse.ArgumentTypeError(f"expected some of {', '.join(sorted(METHODS))}, got {text!r}")
    return names


def tile(image: np.ndarray, label: str, white: float) -> np.ndarray:
    """An sRGB 8-bit tile of a linear image (H×W×3 or H×W), with a label."""
    out = np.ascontiguousarray(to_display(image, 1.0 / white))
    cv2.putText(out, label, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(out, label, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def aolp_tile(stokes: np.ndarray) -> np.ndarray:
    """AoLP as hue (0-180°), DoLP as value, in linear RGB."""
    lum = stokes.mean(axis=-1)
    hue = (np.degrees(optics.aolp(lum)) % 180.0).astype(np.float32)        # OpenCV hue: 0..180
    value = np.clip(optics.dolp(lum) * 4, 0, 1).astype(np.float32)
    hsv = np.stack([hue * 2, np.ones_like(hue), value], axis=-1)
    return srgb_to_linear(cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB))


def sheet(capture: samples.Capture, runs: dict, size: int) -> np.ndarray:
    """One capture's contact sheet (8-bit sRGB, RGB order): a row per method of ``runs``; prints a line per method."""
    stack, angles = samples.load(capture, size)
    stokes = optics.stokes_from_images(stack, np.radians(angles))
    s0 = stokes[0]
    white = float(np.percentile(s0, 99.5)) or 1.0
    dolp = np.clip(optics.dolp(stokes.mean(axis=-1)), 0, 1)
    rows = []
    for name, run in runs.items():
        started = time.time()
        r_hat, t_hat, inspection, used = separate_inspected(stack, angles, run, "auto")
        seconds = time.time() - started
        presence = inspection.presence_at(stack.shape[1:3])
        low, high = float(np.min(used)), float(np.max(used))
        reference = f"{low:.0f}-{high:.0f}" if high - low >= 0.5 else f"{low:.0f}"
        share = float(r_hat.sum() / max(s0.sum(), 1e-9))
        rows.append(np.hstack([tile(s0, f"{name}: S0", white), tile(t_hat, f"T ({float(t_hat.sum() / max(s0.sum(), 1e-9)):.0%} of S0)", white),
                               tile(r_hat, f"R ({share:.0%}), ref {reference} deg", white),
                               tile(dolp, "DoLP (0..1)", 1.0), tile(aolp_tile(stokes), "AoLP (hue)", 1.0),
                               tile(presence, "presence", 1.0)]))
        print(f"{capture.name:22s} {name:10s} R share {share:6.1%}  ref {reference:>7s} deg  T min {t_hat.min():+.3f}  "
              f"R min {r_hat.min():+.3f}  {seconds:5.1f} s")
    for warning in inspection.warnings:
        print(f"{capture.name:22s} warning: {warning}")
    return np.vstack(rows)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=Formatter)
    parser.add_argument("--out", type=Path, default=Path("contact-sheets"), help="folder of the sheets, one CAPTURE.png each")
    parser.add_argument("--size", type=positive, default=512, help="long side of the reduced captures (px)")
    parser.add_argument("--methods", type=method_list, default="none,network,schechner,kong",
                        help=f"comma-separated methods, a row each: some of {', '.join(sorted(METHODS))}")
    parser.add_argument("--weights", type=Path, help="the network's weights (default: shipped)")
    parser.add_argument("--force", action="store_true", help="replace sheets already in --out")
    args = parser.parse_args()
    captures = samples.captures()
    if not captures:
        print(f"error: no real captures in {samples.SHARED}", file=sys.stderr)
        return 1
    targets = {capture.name: args.out / f"{capture.name}.png" for capture in captures}
    existing = [path.name for path in targets.values() if path.exists()]
    if existing and not args.force:
        print(f"error: {args.out} already holds {', '.join(existing)}; remove them, choose another --out, "
              "or pass --force", file=sys.stderr)
        return 1
    try:
        runs = {name: get_method(name, **({"weights": args.weights} if name == "network" and args.weights else {}))[0]
                for name in args.methods}
        args.out.mkdir(parents=True, exist_ok=True)
        for capture in captures:
            cv2.imwrite(str(targets[capture.name]), sheet(capture, runs, args.size)[..., ::-1])
            print(f"wrote {targets[capture.name].resolve()}")
    except UrdError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:
        print(f"error: cannot write in {args.out} ({exc.strerror or exc})", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
