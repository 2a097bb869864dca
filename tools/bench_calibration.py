"""Accuracy of the per-shot angle calibration (`urd calibrate shots`) on the simulated rig, printed.

Captures scenes with the simulated ELL14 and the virtual camera (each shot off its commanded
angle by a random error of ``--jitter`` deg std, the camera shaken by up to ``--shake`` px),
ingests them, calibrates the shots and compares the errors found with the true ones (each DNG
records its true angle), both without their common rotation (the mounting offset's part). One
line per seed: the largest error of the found angles and that error over its reported 1σ.

    python tools/bench_calibration.py [--seeds 8] [--size 768x512] [--shake 4] [--jitter 2]
    python tools/bench_calibration.py --size 1024x768 --shake 0       # from a tripod
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from acquire.plan import capture_scene
from acquire.rig import SimSettings
from acquire.virtual_camera import shot_truth
from calib.store import calibrate_shots
from urd.core.errors import CalibrationError, UrdError
from urd.ingest import IngestOptions, ingest_scene

from toolargs import Formatter, scene_size

ANGLES_DEG = [0.0, 30.0, 60.0, 90.0, 120.0, 150.0]


def number(low: float, kind: type = float):
    """An argparse type: a finite number (``kind``) of at least ``low``."""
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not low <= value < float("inf"):
            raise argparse.ArgumentTypeError(f"expected at least {low:g}, got {text}")
        return value
    return parse


def calibrate_seed(seed: int, width: int, height: int, shake: float, jitter: float) -> float | None:
    """Capture, ingest and calibrate one scene; print its line and return its largest error (deg), None if refused."""
    with tempfile.TemporaryDirectory(prefix="urd-calib-") as folder:
        sim = SimSettings(jitter_deg=jitter, width=width, height=height, shake_px=shake,
                          shake_deg=0.5 if shake else 0.0, seed=seed)
        scene = capture_scene(Path(folder) / "ds", "sim", "virtual", ANGLES_DEG, sim=sim, announce=lambda line: None)
        ingest_scene(scene, IngestOptions())
        try:
            result = calibrate_shots(scene)
        except CalibrationError as exc:
            print(f"seed {seed}: refused ({exc})")
            return None
        true = np.array([shot_truth(scene.path / shot["file"])["scene_angle_deg"] for shot in scene.load()["shots"]])
        base = np.array(scene.uncalibrated_angles_deg())        # the stage's angles turned with the camera, aligned frame
    error = np.array(result.errors_deg) - (true - base - np.mean(true - base))
    worst = float(np.abs(error).max())
    sigma, shot = np.array(result.uncertainty_deg), int(np.argmax(np.abs(error)))
    print(f"seed {seed}: largest error {worst:.2f} deg, {worst / sigma[shot]:.1f} "
          f"of that shot's reported 1 sigma; worst error/sigma of any shot {np.abs(error / sigma).max():.1f} "
          f"(reported {sigma.min():.2f}-{sigma.max():.2f} deg)")
    return worst


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=Formatter)
    parser.add_argument("--seeds", type=number(1, int), default=8, help="scenes, one per seed 0..N-1")
    parser.add_argument("--size", type=scene_size(), default="768x512", help="scene size WxH (px)")
    parser.add_argument("--shake", type=number(0.0), default=4.0, help="camera shake between shots, max translation (px)")
    parser.add_argument("--jitter", type=number(0.0), default=2.0,
                        help="per-shot angle error the encoder does not see, std (deg)")
    args = parser.parse_args()
    width, height = args.size
    worst = []
    try:
        for seed in range(args.seeds):
            found = calibrate_seed(seed, width, height, args.shake, args.jitter)
            if found is not None:
                worst.append(found)
    except UrdError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    if worst:
        print(f"{width}x{height}, shake {args.shake:g} px, jitter {args.jitter:g} deg: largest error "
              f"{min(worst):.2f}-{max(worst):.2f} deg over {len(worst)} seeds, median {np.median(worst):.2f} deg")
    return 0


if __name__ == "__main__":
    sys.exit(main())
