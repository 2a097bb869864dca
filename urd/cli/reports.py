"""``urd report`` (a dataset's summary, optionally as an HTML report) and ``urd verify`` (every listed
file against its size and SHA-256)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from urd.cli.common import DATASET_HELP, existing_dataset, fail, refuse_scene_link, run_guarded, usage
from urd.core.progress import TerminalProgress, plural


def report(
    dataset: Optional[Path] = typer.Argument(None, help=DATASET_HELP, show_default=False),
    html: Optional[Path] = typer.Option(None, "--html", help="Also write a self-contained HTML report into this folder (opens from disk: shots, S0/DoLP/AoLP, results side by side with a comparison slider)."),
    force: bool = typer.Option(False, help="Replace an existing HTML report folder."),
) -> None:
    """Summarize a dataset: scenes (incomplete, broken, ingested), angles, calibration, results.

    \b
    Example:
      urd report
      urd report dataset --html report/
    """
    from urd.report import report_html, report_text

    from urd.report_html import check_report_folder

    if force and html is None:
        raise usage("--force replaces an HTML report folder: it goes with --html FOLDER (the text report replaces nothing)")
    root = existing_dataset(dataset)
    if html is not None:
        run_guarded(check_report_folder, html, force)          # before the text report: a refusal says only that
    typer.echo(run_guarded(report_text, root))
    if html is not None:
        index = run_guarded(report_html, root, html, force, progress=TerminalProgress())
        typer.echo(f"wrote {Path(index).resolve()}")


def verify(dataset: Optional[Path] = typer.Argument(None, help=DATASET_HELP + " Or one scene's folder.", show_default=False)) -> None:
    """Check every file a dataset's manifests list against its size and SHA-256; exit 1 on any problem.

    \b
    Example:
      urd verify
      urd verify dataset
      urd verify dataset/scene_01
    """
    from urd.core.dataset import SCENE_NAME
    from urd.report import verify as verify_dataset

    root = existing_dataset(dataset)
    if (root / "scene.json").is_file():
        refuse_scene_link(root, "DATASET")
    problems = run_guarded(verify_dataset, root)
    for name, issues in problems.items():
        for issue in issues:
            typer.secho(f"{name}: {issue}", fg=typer.colors.RED, err=True)
        if not issues:
            typer.echo(f"{name}: ok")
    scenes = sum(bool(SCENE_NAME.match(name)) for name in problems)
    bad_scenes = sum(bool(SCENE_NAME.match(name)) and bool(issues) for name, issues in problems.items())
    misnamed = len(problems) - scenes - ("calibration" in problems)        # folders named like no scene: each a problem
    bad = ([f"{bad_scenes} of {plural(scenes, 'scene')}"] if bad_scenes else []) \
        + (["the calibration"] if problems.get("calibration") else []) + ([plural(misnamed, "misnamed scene folder")] if misnamed else [])
    if bad:
        fail(f"problems in {' and '.join(bad)}")
    what = " and ".join([plural(scenes, "scene")] + (["the calibration"] if "calibration" in problems else []))
    typer.echo(f"{'all ' if scenes > 1 else ''}{what} intact")
