"""Contact sheets of every real capture in ../shared/data/polarization, per method.

    python tools/contact_sheets.py [--out contact-sheets] [--size 512] [--methods none,network,schechner,kong]
                                   [--weights FILE]

One PNG per capture: a row per method with S0 | T̂ | R̂ | DoLP | AoLP (hue = AoLP over 0-180°,
brightness = DoLP) and the presence map, all sRGB-encoded with one white point per capture
(the 99.5th percentile of S0); the reference each method used (as `urd separate` chooses it:
the estimated field, its side settled by a trial separation where it was only assumed,
`urd.separation.separate_inspected`) and the share of light put into R̂ are written on the row.
Prints one line per capture and method.
"""

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from separate import optics
from separate.methods import get_method
from urd.core import samples
from urd.separation import separate_inspected
from urd.core.images import srgb_to_linear, to_display

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("--out", type=Path, default=Path("contact-sheets"))
parser.add_argument("--size", type=int, default=512, help="long side of the reduced captures (px)")
parser.add_argument("--methods", default="none,network,schechner,kong")
parser.add_argument("--weights", type=Path, help="the network's weights (default: shipped)")
args = parser.parse_args()
args.out.mkdir(parents=True, exist_ok=True)


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


for capture in samples.captures():
    stack, angles = samples.load(capture, args.size)
    stokes = optics.stokes_from_images(stack, np.radians(angles))
    s0 = stokes[0]
    white = float(np.percentile(s0, 99.5)) or 1.0
    dolp = np.clip(optics.dolp(stokes.mean(axis=-1)), 0, 1)
    rows = []
    for name in args.methods.split(","):
        run, _ = get_method(name, **({"weights": args.weights} if name == "network" and args.weights else {}))
        started = time.time()
        r_hat, t_hat, inspection, used = separate_inspected(stack, angles, run, "auto")
        seconds = time.time() - started
        presence = inspection.presence_at(stack.shape[1:3])
        low, high = float(np.min(used)), float(np.max(used))
        reference = f"{low:.0f}-{high:.0f}" if high - low >= 0.5 else f"{low:.0f}"
        share = float(r_hat.sum() / max(s0.sum(), 1e-9))
        rows.append(np.hstack([tile(s0, f"{name}: S0", white), tile(t_hat, f"T ({1 - share:.0%} of S0)", white),
                               tile(r_hat, f"R ({share:.0%}), ref {reference} deg", white),
                               tile(dolp, "DoLP (0..1)", 1.0), tile(aolp_tile(stokes), "AoLP (hue)", 1.0),
                               tile(presence, "presence", 1.0)]))
        print(f"{capture.name:22s} {name:10s} R share {share:6.1%}  ref {reference:>7s} deg  T min {t_hat.min():+.3f}  "
              f"R min {r_hat.min():+.3f}  {seconds:5.1f} s")
    for warning in inspection.warnings:
        print(f"{capture.name:22s} warning: {warning}")
    sheet = np.vstack(rows)
    cv2.imwrite(str(args.out / f"{capture.name}.png"), sheet[..., ::-1])
    print(f"wrote {(args.out / f'{capture.name}.png').resolve()}")
