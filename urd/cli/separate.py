"""``urd separate``: one scene, image files (``--images``) or every scene of a dataset (``--all``)
into reflection R and transmission T, or polarization maps added to existing results."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import typer

from urd.cli.common import (DATASET_HELP, bad, choice, existing_dataset, fail, given, parse_angles, parse_params, parse_reference,
                            refuse_weights_folder, report_truth, resolve_scene, run_guarded, show_previews, usage, warn, within)
from urd.core.errors import DatasetError
from urd.core.files import check_writable
from urd.core.progress import TerminalProgress, plural

#: Baselines that report progress (their ``separate`` takes a ``progress`` callback).
PROGRESS_BASELINES = ("kong", "arvanitopoulos", "li-brown")


def separate(
    ctx: typer.Context,
    scene: Optional[str] = typer.Argument(None, help="Scene name (scene_12) in --dataset, or a scene folder. Omit with --images."),
    dataset: Optional[Path] = typer.Option(None, help=DATASET_HELP, show_default=False),
    method: str = typer.Option("network", help="network (the paper's, shipped weights); baselines: schechner, kong, farid (polarization), li-brown, arvanitopoulos, ceilnet (single image: they see S0 only); none (T = S0)."),
    images: Optional[list[Path]] = typer.Option(None, "--images", help="Separate image files instead of a scene (repeat: one file per angle, 3 or more)."),
    angles: str = typer.Option("0,45,90", help="Polarizer angles of --images (deg)."),
    transfer: str = typer.Option("linear", help="Integer --images (8- or 16-bit): linear (sensor codes, a raw converter's linear output) or srgb (photos and exports encoded for display). Float files are always linear."),
    out: Path = typer.Option(Path("separated"), help="Output folder for --images."),
    reference: str = typer.Option("auto", help="Reference angle (deg): the glass's s-direction, where the reflection is brightest; 'auto' estimates it per pixel from the shots (a smooth field, for wide views and curved panes; one angle where the polarization is weak and of one orientation), 'global' one angle for the whole view."),
    weights: Optional[Path] = typer.Option(None, help="Weights file of the network or ceilnet, or a shipped one by name: urd-anchored (the default: the network anchored to the Fresnel inversion by a learned gate), urd-canonical (the same network without the gate), urd-canonical-transposed (the paper's decoder), urd-direct, ceilnet."),
    tile: Optional[int] = typer.Option(None, help="Network tile size (px, at least 320: twice the 160 px overlap; default for the network 2048 in bf16, 1408 in fp32 (CPU), for ceilnet 1024); memory grows with it, not with the image.", show_default=False),
    precision: str = typer.Option("auto", help="Network arithmetic: auto (bf16 where the CPU or GPU runs it natively, else fp32), fp32 or bf16."),
    device: str = typer.Option("auto", help="Where the network runs: auto (a CUDA GPU where torch sees one, else the CPU), cpu or cuda."),
    colour_match: bool = typer.Option(False, help="Match each colour channel's histogram of T to the darkest observation's (paper §3.4)."),
    return_copies: Optional[bool] = typer.Option(None, "--return-copies/--keep-copies", help="Network: move light that R shows as a local copy of T (the scene's own polarization: sky, no glass) back into T (separate/copies.py). Default: --return-copies.", show_default=False),
    incidence: Optional[float] = typer.Option(None, "--incidence", help="Network: the angle of incidence on the glass (deg, between the camera's axis and the pane's normal) where you know it; the network's Fresnel gate uses it instead of the estimate from the shots. Schechner takes it as --param theta_deg=DEG.", show_default=False),
    param: Optional[list[str]] = typer.Option(None, "--param", help="A baseline's parameter as NAME=VALUE (repeat), e.g. --method kong --param smoothness=0.5; an unknown NAME is refused with the method's parameter names (docs/baselines.md)."),
    force: bool = typer.Option(False, help="Replace existing results of this method (only once the new ones are complete)."),
    maps: bool = typer.Option(False, "--maps", help="Also write the polarization maps: S0, S1, S2, DoLP, AoLP, phi_perp, theta as float32 TIFF with units (results/METHOD/maps/); on a scene that has results of the method, adds the maps to them without separating again."),
    all_scenes: bool = typer.Option(False, "--all", help="Every ingested scene of the dataset without results of this method (with --force: every ingested scene)."),
    jobs: int = typer.Option(1, callback=within(1), help="With --all: worker processes, each on cores/jobs threads."),
) -> None:
    """Separate a scene into reflection R and transmission T (linear 16-bit TIFF, sRGB previews,
    a reflection-presence map and the reference angle used), or every scene with --all.

    \b
    Example:
      urd separate scene_01
      urd separate scene_01 --method kong --param smoothness=0.5
      urd separate --all --jobs 2 --dataset dataset
      urd separate scene_01 --maps --reference global
      urd separate --images a.tif --images b.tif --images c.tif --angles 0,45,90 --transfer srgb
    """
    from separate.methods import METHODS, NETWORKS, S0_ONLY, get_method
    from urd.core.images import Transfer, stored_bits
    from urd.core.raw import RAW_SUFFIXES
    from urd.separation import FIELD_KIND, add_maps, check_no_results_in, check_out_folder, describe_incidence, sees_polarization_of, separate_images, separate_scene

    if method not in METHODS:
        raise bad("--method", f"expected one of {', '.join(sorted(METHODS))}, got {method!r}")
    refuse_weights_folder(weights, "--weights")
    raws = [Path(name).name for name in [*(images or []), *([scene] if scene else [])]
            if Path(name).suffix.lower() in RAW_SUFFIXES]
    if raws:
        raise usage(f"{', '.join(raws)}: RAW files; separate takes an ingested scene, or with --images "
                                 "decoded images (TIFF, PNG, JPEG). Ingest RAW shots with 'urd ingest FOLDER', "
                                 "then run 'urd separate SCENE'")
    if all_scenes and (scene is not None or images):
        raise usage("expected --all alone, without a scene name or --images")
    if jobs > 1 and not all_scenes:
        raise usage("--jobs is for --all (one scene runs in one process)")
    if images is None and scene is None and not all_scenes:
        raise usage("expected a scene name, --all or --images")
    if images and scene is not None:
        raise usage(f"expected a scene name or --images, not both (got {scene!r} and --images)")
    if images and dataset is not None:
        raise usage("--dataset is for a scene or --all; the results of --images go into --out")
    if given(ctx, "reference") and method in S0_ONLY and not maps:
        raise usage(f"--reference: {method} sees S0 alone, so no reference angle changes its layers (with --maps it "
                    "sets the φ⊥ map)")
    unused = [f"--{name.replace('_', '-')}" for name in ("weights", "tile", "precision", "device", "colour_match")
              if given(ctx, name)]
    if unused and method not in NETWORKS:
        raise usage(f"{', '.join(unused)}: for the networks (network, ceilnet), not {method}")
    unused = [f"--{name}" for name in ("angles", "out", "transfer") if given(ctx, name)]
    if unused and not images:
        raise usage(f"{', '.join(unused)}: for --images; a scene's angles come from its manifest and its "
                                 "results go into the scene's results/METHOD/")
    transfer_rule = choice(Transfer, transfer, "--transfer")
    if return_copies is not None and method != "network":
        raise usage(f"--return-copies/--keep-copies is for the network, not {method}")
    return_copies = return_copies is not False
    if incidence is not None and method != "network":
        raise usage(f"--incidence is for the network, not {method}" + (
            " (use --param theta_deg=DEG)" if method == "schechner" else ""))
    if incidence is not None and not 0 < incidence < 90:
        raise bad("--incidence", f"expected between 0 and 90 deg, got {incidence:g}")
    if param and method in NETWORKS + ("none",):
        raise usage(f"--param is for the baselines; {method} takes its own options")
    params = parse_params(param or [])
    if params:                                           # checked as the method is made: a usage error, before any work
        from separate.methods import get_method
        try:
            get_method(method, **params)
        except (TypeError, ValueError) as exc:
            raise bad("--param", str(exc)) from None
    forced = parse_reference(reference)
    angle_list = parse_angles(angles) if images else None
    if method in NETWORKS:                               # the names only: torch comes after every check
        from separate import optics
        from separate.precision import parse_device, parse_precision
        from separate.tiling import OVERLAP, check_tiling
        if images:
            try:
                optics.check_angles([math.radians(a) for a in angle_list], min_span=math.radians(optics.MIN_SPAN_DEG))
            except ValueError as exc:
                raise bad("--angles", f"{exc} for the {method}") from None
        try:
            parse_device(device)
        except ValueError as exc:
            raise bad("--device", str(exc)) from None
        try:
            parse_precision(precision)
        except ValueError as exc:
            raise bad("--precision", str(exc)) from None
        try:
            if tile is not None:
                check_tiling(tile, OVERLAP)
        except ValueError as exc:
            raise bad("--tile", str(exc)) from None
    if images and len(images) != len(angle_list):
        raise usage(f"expected one --images file per angle of --angles {angles}, got {len(images)} files")
    if images:
        missing = [str(p) for p in images if not Path(p).is_file()]
        if missing:
            raise bad("--images", f"{', '.join(missing)}: no such file")
        try:
            check_out_folder(out, method)
        except DatasetError as exc:
            raise bad("--out", str(exc)) from None
        if out.exists() and not out.is_dir():
            raise bad("--out", f"{out} is a file, not a folder; name a folder for the results")
        eight_bit = [Path(p).name for p in images if stored_bits(p) == 8]
        if not given(ctx, "transfer") and eight_bit:
            warn(f"8-bit images ({', '.join(eight_bit)}) are read as linear sensor codes (--transfer linear, the "
                 "default); a photo from an ordinary camera or an editor's export is sRGB-encoded: pass --transfer srgb for it")
        run_guarded(check_no_results_in, out, force)
    target = None if images or all_scenes else run_guarded(resolve_scene, scene, dataset)
    adding_maps = target is not None and maps and not force and method in run_guarded(target.methods)
    if adding_maps:
        fixed = ("reference",) if "reference_deg.tiff" in run_guarded(target.result, method).files else ()
        ignored = [f"--{name.replace('_', '-')}" for name in ("weights", "tile", "precision", "device", "colour_match",
                                                             "return_copies", "incidence", "param", *fixed)
                   if given(ctx, name)]
        if ignored:
            raise usage(f"{', '.join(ignored)}: {target.name} has {method} results, to which --maps adds the maps "
                        "without separating again (at the reference they were separated at); pass --force to "
                        "separate again with these options")
        stale = run_guarded(target.status).stale
        if stale and method in stale:
            raise usage(f"{target.name}'s {method} results are stale (the scene changed since they were made): maps of "
                        "the new shots would not match them; pass --force to separate again with maps")
    if target is not None and not force and not adding_maps:
        run_guarded(target.check_no_results, method)
    if target is not None:
        run_guarded(target.check_ingested)                   # before the network is set up and its precision told
        run_guarded(check_writable, target.path, "the separation")
    network_device = chosen = None
    if method in NETWORKS:                               # torch is imported for the networks only, after the checks above
        from separate.precision import describe, resolve, resolve_device
        try:
            network_device = resolve_device(device)
        except ValueError as exc:
            raise bad("--device", str(exc)) from None
        chosen = resolve(precision, network_device)
    if all_scenes:
        separate_dataset(dataset, method, weights, tile, chosen, colour_match, return_copies, incidence, params, force,
                         forced, maps, jobs, network_device)
        return
    if adding_maps:
        result = run_guarded(add_maps, target, method, forced)
        typer.echo(f"added the polarization maps to {target.name}'s {method} results (a Stokes fit; not separated again)")
        for path in result.files:
            typer.echo(f"wrote {Path(path).resolve()}")
        return
    bar = TerminalProgress()

    def show(done: int, total: int) -> None:
        bar(done, total, f"separate ({method})")

    if method in NETWORKS:
        options = {"weights": weights, "tile": tile, "precision": chosen.value, "device": network_device.type,
                   "colour_match": colour_match, "progress": show,
                   **({"return_copies": return_copies, "incidence_deg": incidence} if method == "network" else {})}
        typer.echo(f"precision: {describe(chosen, network_device)}" + (f" on {network_device.type}" if network_device.type != "cpu" else ""), err=True)
    else:
        options = {**params, "progress": show} if method in PROGRESS_BASELINES else params
    run, info = run_guarded(get_method, method, reference=forced, **options)
    # separate.methods records a baseline's keywords as its parameters: the callback is not one
    if images:
        result = run_guarded(separate_images, images, angle_list, out, run, transfer_rule, force, forced, maps,
                             sees_polarization_of(info))
    else:
        result = run_guarded(separate_scene, target, method, run, info, force, forced, maps)
    bar.close()
    for line in result.warnings:
        warn(line)
    if sees_polarization_of(info):
        field = " around it: reference_deg.tiff" if result.reference_kind == FIELD_KIND else ""
        typer.echo(f"reference angle {result.reference_deg:.1f} deg ({result.reference_kind}{field})")
    if "incidence" in info:
        typer.echo(describe_incidence(info["incidence"]))
    for path in result.files:
        typer.echo(f"wrote {Path(path).resolve()}")
    report_truth(result.truth_metrics)
    show_previews(result.files)


def separate_dataset(dataset: Optional[Path], method: str, weights: Optional[Path], tile: Optional[int], chosen,
                     colour_match: bool, return_copies: bool, incidence: Optional[float], params: dict, force: bool,
                     reference, maps: bool, jobs: int, network_device=None) -> None:
    """``urd separate --all``: every scene that needs it (`urd.batch.separate_all`), one line per
    scene; exit 1 when any failed, or when no scene is ingested.
    ``network_device``: the networks' torch device."""
    from separate.methods import NETWORKS, get_method
    from urd.batch import separate_all
    from urd.core.dataset import Dataset

    root = existing_dataset(dataset)
    options = ({"weights": weights, "tile": tile, "precision": chosen.value, "device": network_device.type,
                "colour_match": colour_match, **({"return_copies": return_copies, "incidence_deg": incidence} if method == "network" else {})}
               if method in NETWORKS else params)
    run_guarded(get_method, method, **options)              # bad weights or parameters: one error, not one per scene
    outcomes = run_guarded(separate_all, root, method, options, force, reference, maps, jobs, progress=TerminalProgress())
    for outcome in outcomes:
        typer.echo(f"{outcome.scene}: {outcome.state}{': ' + outcome.detail if outcome.detail else ''}")
    for name, message in run_guarded(lambda: Dataset.open(root).misnamed_scenes()).items():
        warn(f"{name}: {message}")
    failed = sum(o.state == "failed" for o in outcomes)
    done = sum(o.state == "separated" for o in outcomes)
    mapped = sum(o.state == "maps added" for o in outcomes)
    typer.echo(f"{plural(done, 'scene')} separated with {method}, " + (f"maps added to {mapped}, " if mapped else "") +
               f"{failed} failed" + (
        f"; results in each scene's results/{method}/ (look at them: urd report {root} --html report)" if done else ""))
    if failed:
        raise typer.Exit(1)
    if not outcomes:
        fail(f"nothing was separated: {root} holds no scene yet; capture one (urd capture) or ingest RAW shots "
             "(urd ingest FOLDER) first")
    if all(o.state == "skipped" and o.detail.startswith("not ingested") for o in outcomes):
        fail(f"nothing was separated: no scene is ingested yet; run urd ingest {root} first")
