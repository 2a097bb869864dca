"""``urd ingest``: RAW shots, captured scenes, datasets or polarization-camera frames into a dataset."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from urd.cli.common import bad, choice, fail, given, note_new_dataset, parse_angles, run_guarded, usage, warn, within
from urd.core.dataset import default_root
from urd.core.manifest import printable
from urd.core.progress import TerminalProgress, plural


def ingest(
    ctx: typer.Context,
    source: Optional[Path] = typer.Argument(None, help="A folder of RAW shots, a captured scene folder, a dataset folder, or (with --mosaic) polarization-camera frames (default: the dataset here, as for DATASET, e.g. after 'urd capture').", show_default=False),
    dataset: Optional[Path] = typer.Argument(None, help="Dataset to add scenes to when SOURCE is a RAW folder or mosaics (default: the current folder if it holds dataset.json, else ./dataset).", show_default=False),
    angles: str = typer.Option("0,45,90", help="Polarizer angles of consecutive shots (deg), for RAW folders without a capture manifest."),
    motion: str = typer.Option("euclidean", help="Alignment model: translation, euclidean or homography."),
    half_size: bool = typer.Option(False, help="Decode at half resolution (one pixel per 2x2 CFA tile; ~4x faster)."),
    gap: float = typer.Option(60.0, callback=within(0.0), help="Seconds between shots that start a new scene when grouping by capture time."),
    redo: bool = typer.Option(False, help="Decode and align again scenes that are already ingested (the old aligned stack is replaced only on success)."),
    mosaic: Optional[str] = typer.Option(None, help="SOURCE holds polarization-camera frames (PNG/TIFF) with this layout: imx250mzr, imx250myr or wen2019; one scene per frame, demosaiced at half size (one pixel per 2x2 polarizer cell)."),
    demosaic: str = typer.Option("newton", help="Demosaicing of --mosaic frames: none (sites as they are, unregistered), bilinear, newton (registers the four polarizer sites)."),
    transfer: str = typer.Option("linear", help="Integer frames (8- or 16-bit): linear (sensor codes, polarization cameras) or srgb (frames encoded for display)."),
    jobs: int = typer.Option(1, callback=within(1), help="Worker processes for the scenes of a dataset (SOURCE a dataset folder): each decodes and aligns one scene at a time."),
) -> None:
    """Decode RAW shots to linear images, group them into scenes and align each scene (ECC).

    Already-ingested files (same SHA-256) are skipped; incomplete captures are reported.

    \b
    Example:
      urd ingest                       (the dataset here, e.g. after urd capture)
      urd ingest raw/
      urd ingest raw/ dataset --angles 0,45,90,135
      urd ingest dataset --jobs 2
    """
    from urd.core.align import Motion
    from urd.core.images import Transfer
    from urd.ingest import IngestOptions, ingest as ingest_workflow

    from urd.core.mosaic import Demosaic, MosaicLayout

    opts = IngestOptions(tuple(parse_angles(angles)), choice(Motion, motion, "--motion"), half_size, gap, redo)
    layout = choice(MosaicLayout, mosaic, "--mosaic") if mosaic else None
    method = choice(Demosaic, demosaic, "--demosaic")
    transfer_rule = choice(Transfer, transfer, "--transfer")
    if source is None:
        source = default_root()
        if not (source / "dataset.json").is_file():
            raise bad("SOURCE", f"none given, and {source} holds no dataset: name the folder of RAW shots, the "
                                "scene or the dataset to ingest")
    if not source.exists():
        raise bad("SOURCE", f"{source}: no such folder or file")
    if source.is_file() and not mosaic:
        raise bad("SOURCE", f"{source} is a file; ingest takes a folder (of RAW shots, a captured scene, or a "
                                 "dataset): put the shots in a folder and pass that")
    recorded = (source / "scene.json").is_file() or (source / "dataset.json").is_file()
    if recorded and given(ctx, "angles"):
        raise usage("a scene's angles are in its manifest; --angles is for a folder of RAW files. To "
                                 "record other angles, move the scene folder away and ingest its raw/ files again")
    if recorded and given(ctx, "gap"):
        raise usage("--gap groups a folder of RAW files into scenes by capture time; a dataset's scenes are "
                    "already grouped")
    if recorded and dataset is not None:
        own = source if (source / "dataset.json").is_file() else source.resolve().parent
        if dataset.resolve() != own.resolve():
            raise usage(f"{source} is a {'dataset' if own == source else 'scene'} and is ingested where it is; "
                        "DATASET is for a folder of RAW files or mosaic frames: leave it out")
    if not recorded and dataset is not None and source.is_dir() and dataset.resolve() == source.resolve():
        raise usage(f"expected a DATASET other than the RAW folder {source} itself (the shots go into "
                    "DATASET/scene_NN/raw/): name another folder")
    if jobs > 1 and (not recorded or mosaic):
        raise usage("--jobs is for a dataset or scene folder; a RAW folder or mosaic frames are ingested "
                                 "by one process (ingest them, then the dataset with --jobs)")
    unused = [f"--{name}" for name in ("demosaic", "transfer") if given(ctx, name)]
    if unused and not mosaic:
        names = ", ".join(unused)
        raise usage(f"{names} {'needs' if len(unused) == 1 else 'need'} --mosaic LAYOUT ({names}: for --mosaic frames "
                    "from a polarization camera, not for RAW shots)")
    unused = [f"--{name}" for name in ("angles", "gap", "motion") if given(ctx, name)]
    if unused and mosaic:
        raise usage(f"{', '.join(unused)}: for RAW shots; a --mosaic frame holds its polarizer angles in its layout "
                    "and is one scene, registered as it is taken")
    if mosaic and given(ctx, "half_size"):
        raise usage(f"--{'' if half_size else 'no-'}half-size: for RAW shots; --mosaic frames are always demosaiced at "
                    "half size (one pixel per 2x2 polarizer cell)")
    if not recorded and not mosaic and not given(ctx, "angles") and source.is_dir():
        from urd.ingest import find_raw_files, named_angles

        named = named_angles(run_guarded(find_raw_files, source)[0])
        if named is not None and named != list(opts.angles_deg):
            listed = ",".join(f"{a:g}" for a in named)
            raise usage(f"{source}: urd's own shots, named with their angles ({listed} deg), not the default "
                        f"--angles {','.join(f'{a:g}' for a in opts.angles_deg)}; ingest them with --angles {listed}")
    root = dataset or default_root()
    if not recorded:
        note_new_dataset(root)
    report = run_guarded(ingest_workflow, source, root, opts, layout, method, transfer_rule,
                         progress=TerminalProgress(), jobs=jobs)
    for path in report.ignored:
        typer.echo(f"ignored (not a RAW file name): {printable(str(path.resolve()))}", err=True)
    for note in report.notes:
        warn(note)
    for outcome in report.outcomes:
        for note in outcome.notes:
            warn(note)
        where = outcome.name or ", ".join(printable(p.name) for p in outcome.files)       # file names as given
        if outcome.state == "failed":
            typer.secho(f"FAILED {where}: {printable(str(outcome.error))}", fg=typer.colors.RED, err=True)
        elif outcome.state == "ingested":
            names = ", ".join(printable(p.name) for p in outcome.files)
            origin = f"from {len(outcome.files)} files" if len(outcome.files) > 3 else f"from {names}"
            typer.echo(f"ingested {outcome.name} ({origin})")
        elif outcome.state == "skipped" and outcome.files:            # files of a folder that a scene already holds
            typer.echo(f"skipped {', '.join(printable(p.name) for p in outcome.files)}: {printable(str(outcome.error))}")
        else:
            typer.echo(f"{outcome.state} {where}: {printable(str(outcome.error))}")
    if not report.outcomes:
        typer.echo("nothing to ingest")
    if report.failed:
        failed = len(report.failed)
        fail(f"{failed} of {plural(len(report.outcomes), 'scene')} {'failed or was' if failed == 1 else 'failed or were'} flagged")
    incomplete = [o.name for o in report.outcomes if o.state == "incomplete"]
    if incomplete and len(incomplete) == len(report.outcomes):     # no scene ingested, now or before
        fail(f"nothing to ingest: {plural(len(incomplete), 'incomplete capture')} ({', '.join(incomplete)}); resume "
             f"{'it' if len(incomplete) == 1 else 'them'} with the command above, then ingest again")
