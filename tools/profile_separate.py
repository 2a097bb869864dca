"""Where `urd.separate` spends its time on a large scene, printed as a table (cProfile).

Renders a window scene with the virtual camera's optics (`acquire.virtual_camera.make_glass_scene`:
the bundled photos, θ across the pane) at 0/45/90°, stored as uint16 codes as `urd separate`
loads a scene; by default weakly polarized with one orientation (a dim reflection at a low angle
of incidence), so that the side of the reference is tried (`separate.reference.decide_side`).
Then profiles one `urd.separate` call (the network, reference "auto") and prints the cumulative
time of each step: the reference (inspection and the side trial), the θ estimate, the network's
input, backbone and Fresnel anchor, the tiles' presentation, the copies' return.

    python tools/profile_separate.py [--size 6000x4000] [--threads 1] [--wall] [--strong]

Times are CPU seconds of this process by default (``time.process_time``: steady on a shared
machine; with ``--threads 1`` they are the seconds one core needs); ``--wall`` measures wall
time instead.
"""

import argparse
import cProfile
import pstats
import time

import numpy as np
import torch

import urd
from acquire.virtual_camera import GlassScene, make_glass_scene
from urd.core.images import linear_to_u16

from toolargs import Formatter, positive, scene_size

#: The steps reported: (label, file suffix, function name).
STEPS = [
    ("urd.separate, total", "urd/api.py", "separate"),
    ("reference: inspection + side trial (resolve_reference)", "separate/reference.py", "resolve_reference"),
    ("  inspection of the stack (inspect_stack)", "separate/reference.py", "inspect_stack"),
    ("  side trial: both sides separated (decide_side)", "separate/reference.py", "decide_side"),
    ("θ estimate (estimate_incidence)", "separate/incidence.py", "estimate_incidence"),
    ("θ searches, every one (information_by_incidence)", "separate/incidence.py", "information_by_incidence"),
    ("network run, tiled (separate_stack)", "separate/infer.py", "separate_stack"),
    ("  tiles presented at the reference (patch)", "separate/infer.py", "patch"),
    ("  network input (FusedNet._network_input)", "separate/infer.py", "_network_input"),
    ("  backbone convolutions (FusedNet.backbone)", "separate/infer.py", "backbone"),
    ("  Fresnel anchor: bases, bands, gate (FusedNet._anchor)", "separate/infer.py", "_anchor"),
    ("    of it the gate's convolutions (FusedNet._gate)", "separate/infer.py", "_gate"),
    ("copies returned to T (return_copies)", "separate/copies.py", "return_copies"),
]


def scene_stack(width: int, height: int, strong: bool) -> tuple[np.ndarray, list[float]]:
    """Three shots (3, H, W, 3) uint16 codes of the window scene at 0/45/90°."""
    scene = make_glass_scene(width, height, theta_center_deg=50.0 if strong else 20.0)
    if not strong:
        scene = GlassScene(scene.reflection * 0.03, scene.transmission, scene.theta, scene.phi_perp)
    angles = [0.0, 45.0, 90.0]
    shots = np.empty((3, height, width, 3), np.uint16)
    for k, angle in enumerate(angles):
        shots[k] = linear_to_u16(scene.render(np.radians(angle)))
    return shots, angles


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=Formatter)
    # each side at least 256: the warm-up call separates a 256² corner
    parser.add_argument("--size", type=scene_size(low=256), default="6000x4000", help="scene size WxH (px)")
    parser.add_argument("--threads", type=positive, default=1, help="torch threads")
    parser.add_argument("--wall", action="store_true", help="wall-clock time instead of CPU time")
    parser.add_argument("--strong", action="store_true", help="a strongly polarized scene (no side trial)")
    args = parser.parse_args()
    width, height = args.size
    torch.set_num_threads(args.threads)
    images, angles = scene_stack(width, height, args.strong)
    urd.separate(images[:, :256, :256], angles)                  # imports and oneDNN's first call, not profiled
    profile = cProfile.Profile(time.perf_counter if args.wall else time.process_time)
    profile.runcall(urd.separate, images, angles)
    stats = pstats.Stats(profile).stats
    cumulative = {}
    for (path, _, name), (_, _, _, cum, _) in stats.items():
        for label, suffix, function in STEPS:
            if name == function and path.endswith(suffix):
                cumulative[label] = cumulative.get(label, 0.0) + cum
    total = cumulative[STEPS[0][0]]
    unit = "wall s" if args.wall else "CPU s"
    print(f"scene {width}×{height}, 3 shots, {'strongly' if args.strong else 'weakly'} polarized; "
          f"torch threads {args.threads}; {unit}")
    print(f"| step | {unit} | share |\n|---|---|---|")
    for label, _, _ in STEPS:
        if label in cumulative:
            print(f"| {label} | {cumulative[label]:.2f} | {100 * cumulative[label] / total:.0f}% |")


if __name__ == "__main__":
    main()
