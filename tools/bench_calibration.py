"""Accuracy of the per-shot angle calibration (`urd calibrate shots`) on the simulated rig, printed.

Captures scenes with the simulated ELL14 and the virtual camera (each shot off its commanded
angle by a random error of ``--jitter`` deg std, the camera shaken by up to ``--shake`` px),
ingests them, calibrates the shots and compares the errors found with the true ones (each DNG
records its true angle), both without their common rotation (the mounting offset's part). One
line per seed: the largest error of the found angles and that error over its reported 1σ.

    python tools/bench_calibration.py [--seeds 8] [--size 768x512] [--shake 4] [--jitter 2]
    python tools/bench_calibration.py --size 1024x768 --shake 0       # from a tripod
"""

import argparse
import tempfile
from pathlib import Path

import numpy as np

from acquire.plan import capture_scene
from acquire.rig import SimSettings
from acquire.virtual_camera import shot_truth
from calib.store import calibrate_shots
from urd.core.errors import CalibrationError
from urd.ingest import IngestOptions, ingest_scene

ANGLES_DEG = [0.0, 30.0, 60.0, 90.0, 120.0, 150.0]

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("--seeds", type=int, default=8)
parser.add_argument("--size", default="768x512")
parser.add_argument("--shake", type=float, default=4.0, help="camera shake between shots, max translation (px)")
parser.add_argument("--jitter", type=float, default=2.0, help="per-shot angle error the encoder does not see, std (deg)")
args = parser.parse_args()
width, height = (int(v) for v in args.size.split("x"))

worst = []
for seed in range(args.seeds):
    with tempfile.TemporaryDirectory(prefix="urd-calib-") as folder:
        sim = SimSettings(jitter_deg=args.jitter, width=width, height=height, shake_px=args.shake,
                          shake_deg=0.5 if args.shake else 0.0, seed=seed)
        scene = capture_scene(Path(folder) / "ds", "sim", "virtual", ANGLES_DEG, sim=sim, announce=lambda line: None)
        ingest_scene(scene, IngestOptions())
        try:
            result = calibrate_shots(scene)
        except CalibrationError as exc:
            print(f"seed {seed}: refused ({exc})")
            continue
        true = np.array([shot_truth(scene.path / shot["file"])["true_angle_deg"] for shot in scene.load()["shots"]])
    error = np.array(result.errors_deg) - (true - ANGLES_DEG - np.mean(true - ANGLES_DEG))
    worst.append(float(np.abs(error).max()))
    print(f"seed {seed}: largest error {worst[-1]:.2f} deg, {np.abs(error / np.array(result.uncertainty_deg)).max():.1f} "
          f"of its reported 1 sigma (reported {min(result.uncertainty_deg):.2f}-{max(result.uncertainty_deg):.2f} deg)")
if worst:
    print(f"{args.size}, shake {args.shake:g} px, jitter {args.jitter:g} deg: largest error {min(worst):.2f}-{max(worst):.2f} "
          f"deg over {len(worst)} seeds, median {np.median(worst):.2f} deg")
