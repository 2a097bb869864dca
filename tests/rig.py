"""Helpers: capture scenes on the simulated rig through the real driver and plan."""

import serial

from acquire.ell14 import Ell14
from acquire.plan import new_capture_scene, run_capture
from acquire.sim_ell14 import SimulatedEll14
from acquire.virtual_camera import VirtualCamera, make_glass_scene


def capture_virtual(ds, angles=(0.0, 45.0, 90.0), size=(768, 512), shake_px=8.0, shake_deg=1.0, seed=0,
                    offset_deg=0.0, jitter_deg=0.0, scene=None, glass=None):
    """Capture one scene with the simulated stage and the virtual camera; return (scene, camera)."""
    glass = glass or make_glass_scene(*size)
    target = new_capture_scene(ds, angles, offset_deg=0.0)
    with SimulatedEll14(sim_offset_deg=offset_deg, sim_jitter_deg=jitter_deg, seed=seed) as sim, \
            serial.Serial(sim.port_name, 9600, timeout=0.05) as port:
        cam = VirtualCamera(glass, sim.true_angle_deg, shake_px, shake_deg, seed=seed)
        run_capture(target, Ell14(port), cam, list(angles))
        cam.write_truth(target.path / "truth")
    return target, cam


def separated_virtual_scene(ds, seed=1):
    """A small scene (96×64) captured with the virtual camera (ground truth), ingested and
    separated by 'none': the start of tests that damage or interrupt a dataset."""
    from separate.methods import get_method
    from urd.ingest import IngestOptions, ingest_scene
    from urd.separation import separate_scene

    scene, _ = capture_virtual(ds, size=(96, 64), shake_px=1.0, shake_deg=0.1, seed=seed)
    assert ingest_scene(scene, IngestOptions()).error is None
    run, info = get_method("none")
    separate_scene(scene, "none", run, info)
    return scene
