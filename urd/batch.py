"""Whole datasets at once: ``urd separate --all [--jobs N]``.

The scenes to separate are every ingested scene without results of the method (every ingested
scene with ``force``); with ``maps``, scenes that hold results of the method get the polarization
maps added to them without separating again (`urd.separation.add_maps`). Each is prepared (`urd.separation.prepare_scene`: separated, outputs
written into a staging folder of the scene) by one of ``jobs`` worker processes, and committed
to its manifest by this process, which holds the dataset's lock throughout: one writer, so a
kill leaves every scene committed so far intact and the next run's recovery removes what was
staged for the others. A scene that fails is reported and the others go on. Workers share the
CPU: each runs torch on cores ÷ jobs threads.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import os
from pathlib import Path
from typing import Iterator

from urd.core.dataset import Dataset, Scene
from urd.core.processes import kept_note, process_pool
from urd.core.progress import Progress, plural


@dataclasses.dataclass
class BatchOutcome:
    """One scene of a batch: its name, ``state`` ("separated", "maps added", "skipped" or "failed") and a
    detail (the error, or why it was skipped)."""

    scene: str
    state: str
    detail: str = ""


def stale_results(scene: Scene, method: str) -> str:
    """"STALE <method> results: <why>" for results the manifest marks stale."""
    return f"STALE {method} results: {scene.stale_reason(method)}"


def targets(ds: Dataset, method: str, force: bool) -> tuple[list[Scene], list[BatchOutcome]]:
    """The scenes to separate and the outcomes of those left out (not ingested, failed ingest,
    already separated without ``force``, broken)."""
    chosen, skipped = [], []
    for scene in ds.scenes():
        status = scene.status()
        if status.state == "broken":
            skipped.append(BatchOutcome(scene.name, "failed", status.problem or "broken"))
        elif not scene.is_ingested() or not scene.ingest_outcome()[0]:
            skipped.append(BatchOutcome(scene.name, "skipped", "not ingested (run urd ingest first)"))
        elif method in scene.methods() and not force:
            lost = [name for name, path in scene.result(method, verify=False).files.items() if not path.is_file()]
            what = stale_results(scene, method) if method in status.stale else f"{method} results"
            skipped.append(BatchOutcome(scene.name, "failed", f"its {method} results lack {', '.join(lost)}: see urd verify; "
                                        "--force separates it again") if lost else
                           BatchOutcome(scene.name, "skipped", f"has {what}; --force replaces them"))
        else:
            chosen.append(scene)
    return chosen, skipped


def _prepare(path: str, method: str, options: dict, reference: str | float, maps: bool, threads: int):
    """Worker: prepare one scene (`urd.separation.prepare_scene`), a network on ``threads`` torch threads."""
    from separate.methods import NETWORKS, get_method
    from urd.separation import prepare_scene

    if method in NETWORKS:                      # the classical methods run without torch
        import torch

        torch.set_num_threads(threads)
    run, info = get_method(method, reference=reference, **options)
    return prepare_scene(Scene(Path(path)), method, run, info, reference, maps)


def separate_all(root: Path, method: str, options: dict, force: bool = False, reference: str | float = "auto",
                 maps: bool = False, jobs: int = 1, progress: Progress | None = None) -> list[BatchOutcome]:
    """Separate every scene of the dataset at ``root`` that needs it (module docstring).

    Args:
        root: the dataset folder.
        method, options: the method and its options (`separate.methods.get_method`; picklable,
            no callbacks).
        force: also scenes that have results of the method (replaced once the new ones are complete).
        reference, maps: as `urd.separation.separate_scene`.
        jobs: worker processes (1: in this process).
        progress: called with (scenes done, scenes total, label).

    Returns:
        One `BatchOutcome` per scene of the dataset.
    """
    from urd.separation import commit_scene

    if jobs < 1:
        raise ValueError(f"expected at least 1 job, got {jobs}")
    ds = Dataset.open(root)
    with ds.lock():
        chosen, outcomes = targets(ds, method, force)
        if maps and not force:
            outcomes = [_add_maps(ds.scene(o.scene), method, reference)
                        if o.state == "skipped" and method in ds.scene(o.scene).methods() else o
                        for o in outcomes]
        threads = max(1, (os.cpu_count() or 1) // jobs)
        label = f"separate --all ({method}, {plural(jobs, 'job')})"
        if progress:
            progress(0, len(chosen), label)
        try:
            for done, (scene, prepared) in enumerate(_prepared(chosen, method, options, reference, maps, jobs, threads), 1):
                try:
                    if isinstance(prepared, BaseException):
                        raise prepared
                    commit_scene(prepared, force)
                    outcomes.append(BatchOutcome(scene.name, "separated"))
                except Exception as exc:  # noqa: BLE001 - one scene's failure, whatever it is, must not stop the others
                    outcomes.append(BatchOutcome(scene.name, "failed", f"{type(exc).__name__}: {exc}"))
                if progress:
                    progress(done, len(chosen), label)
        except KeyboardInterrupt as exc:
            exc.add_note(kept_note([o.scene for o in outcomes if o.state == "separated"], "separated", force))
            raise
    return sorted(outcomes, key=lambda o: o.scene)


def _add_maps(scene: Scene, method: str, reference: str | float) -> BatchOutcome:
    """``--all --maps`` on a scene that holds results of the method: the maps added to them
    (`urd.separation.add_maps`), or why not."""
    from urd.separation import add_maps

    if method in scene.status().stale:
        return BatchOutcome(scene.name, "skipped", f"has {stale_results(scene, method)}; maps would not match "
                                                   "them (--force separates again with maps)")
    try:
        add_maps(scene, method, reference)
    except Exception as exc:  # noqa: BLE001 - one scene's failure, whatever it is, must not stop the others
        already = "already have maps" in str(exc)
        return BatchOutcome(scene.name, "skipped" if already else "failed",
                            f"has {method} results with maps (--force separates again)" if already else
                            f"{type(exc).__name__}: {exc}")
    return BatchOutcome(scene.name, "maps added", f"to the {method} results (not separated again)")


def _prepared(scenes: list[Scene], method: str, options: dict, reference: str | float, maps: bool, jobs: int,
              threads: int) -> Iterator[tuple[Scene, object]]:
    """(scene, its `urd.separation.Prepared` or the exception that stopped it), one at a time in
    this process (``jobs`` = 1) or as ``jobs`` worker processes finish them."""
    if jobs == 1:
        for scene in scenes:
            try:
                yield scene, _prepare(str(scene.path), method, options, reference, maps, threads)
            except Exception as exc:  # noqa: BLE001 - reported as the scene's failure by separate_all
                yield scene, exc
        return
    with process_pool(jobs) as pool:                    # workers die with this process; an interrupt kills them
        futures = {pool.submit(_prepare, str(scene.path), method, options, reference, maps, threads): scene
                   for scene in scenes}
        for future in concurrent.futures.as_completed(futures):
            error = future.exception()
            yield futures[future], error if error is not None else future.result()
