"""The demo workflow: the whole pipeline on the simulated rig with bundled photos."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from urd.core.errors import UrdError
from urd.core.progress import Progress


def fresh_folder(folder: Path) -> Path:
    """``folder`` when it does not exist or is empty, else the first of ``folder-2``,
    ``folder-3`` … that does not exist: each demo run gets a dataset of its own."""
    folder = Path(folder)
    if not folder.exists() or (folder.is_dir() and not any(folder.iterdir())):
        return folder
    number = 2
    while folder.with_name(f"{folder.name}-{number}").exists():
        number += 1
    return folder.with_name(f"{folder.name}-{number}")


def run_demo(folder: Path, width: int, height: int, seed: int, precision: str = "auto",
             announce: Callable[[str], None] = print, progress: Progress | None = None):
    """Capture a scene with the simulated ELL14 and virtual camera into a fresh dataset
    (`fresh_folder`; said when it is not ``folder``), ingest it, separate it with the shipped
    network; returns the `urd.separation.Separation` (with PSNR against truth). Interrupted, the
    exception notes where the dataset made so far is."""
    target = fresh_folder(folder)
    if target != Path(folder):
        announce(f"{Path(folder).resolve()} exists (an earlier run): this run writes a fresh dataset, {target.resolve()}")
    folder = target
    try:
        return _run(folder, width, height, seed, precision, announce, progress)
    except KeyboardInterrupt as exc:
        if folder.exists():
            exc.add_note(f"the demo's dataset so far is {folder.resolve()}: delete it, or look at it with 'urd report "
                         f"{folder.resolve()}'; 'urd demo' starts afresh")
        raise


def _run(folder: Path, width: int, height: int, seed: int, precision: str, announce: Callable[[str], None],
         progress: Progress | None):
    """`run_demo`'s steps in ``folder`` (fresh)."""
    from acquire.plan import capture_scene
    from acquire.rig import SimSettings
    from separate.methods import get_method
    from urd.core.align import Motion
    from urd.ingest import IngestOptions, ingest_scene
    from urd.separation import describe_incidence, separate_scene

    sim = SimSettings(offset_deg=0.0, jitter_deg=0.3, width=width, height=height, seed=seed)
    scene = capture_scene(folder, "sim", "virtual", [0.0, 45.0, 90.0], new=True, sim=sim,
                          announce=lambda line: None, progress=progress)
    announce(f"1/3 captured {scene.path.resolve()} (3 DNG shots from the simulated ELL14 and virtual camera)")
    with scene.lock():
        outcome = ingest_scene(scene, IngestOptions(motion=Motion.EUCLIDEAN), progress)
    if outcome.error:
        raise UrdError(outcome.error)
    announce(f"2/3 ingested: decoded to linear RGB and aligned (ECC) in {(scene.path / 'aligned').resolve()}")
    run, info = get_method("network", precision=precision,
                           progress=lambda done, total: progress and progress(done, total, "separate (network)"))
    announce(f"    network precision: {info['parameters']['precision']}")
    result = separate_scene(scene, "network", run, info)
    announce(f"3/3 separated: {scene.results_dir('network').resolve()}")
    announce(f"    {describe_incidence(info['incidence'])}")
    return result
