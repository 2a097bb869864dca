"""The quick evaluation's figures checked against the committed expected values.

`flatten_figures` gives a run's checkable figures by key; `check_figures` compares them with
the expected ones within `TOLERANCES`; `verify_expected` checks a whole expected document
(separate/expected-quick.json, shipped in the package; made by `expected_document`) and raises `BenchmarkMismatch`
naming every figure out of tolerance.
"""

from __future__ import annotations

import math
from typing import Sequence

from separate.bench_plan import Settings
from separate.scoring import SCORES, gap
from urd.core.errors import UrdError

#: The command that rewrites the expected values of the quick run (after new weights).
UPDATE_COMMAND = "python tools/bench_paper.py --quick --update-expected"
EXPECTED_SCHEMA = "urd.bench.expected-quick"


class BenchmarkMismatch(UrdError, ValueError):
    """Figures of the quick evaluation differ from the committed expected values beyond their tolerance."""


#: Tolerances of the quick check by figure kind: ("abs", dB or units) or ("rel", fraction).
TOLERANCES = {"psnr": ("abs", 0.3), "gap": ("abs", 0.3), "ssim": ("abs", 0.01), "rmse": ("rel", 0.05), "failed": ("abs", 0)}


def flatten_figures(crossval: dict[str, list[dict]], robust: list[dict], robust_gaps: list[dict]) -> dict[str, float]:
    """The checkable figures by key: ``crossval/SET/METHOD/{rmse,psnr,ssim}_{t,r}``,
    ``crossval/SET/gap_t`` (network − direct), ``robustness/AXIS/LEVEL/METHOD/psnr_{t,r}``,
    ``robustness/AXIS/LEVEL/gap_t``, and ``.../METHOD/failed`` (patches refused) where a method
    refused any; figures that are not finite (every patch refused) are left out."""
    out = {}
    for name, rows in crossval.items():
        for row in rows:
            for key in SCORES:
                out[f"crossval/{name}/{row['method']}/{key}"] = row[key]
            if row.get("failed"):
                out[f"crossval/{name}/{row['method']}/failed"] = row["failed"]
        g = gap(rows)
        if g:
            out[f"crossval/{name}/gap_t"] = g["mean"]
    for row in robust:
        prefix = f"robustness/{row['axis']}/{row['condition']}/{row['method']}"
        for key in ("psnr_t", "psnr_r"):
            out[f"{prefix}/{key}"] = row[key]
        if row.get("failed"):
            out[f"{prefix}/failed"] = row["failed"]
    for g in robust_gaps:
        out[f"robustness/{g['axis']}/{g['condition']}/gap_t"] = g["mean"]
    return {k: float(v) for k, v in out.items() if math.isfinite(v)}


def tolerance_for(key: str, tolerances: dict = TOLERANCES) -> tuple[str, float]:
    """The (kind, value) tolerance of a figure key, by the kind its last part names."""
    last = key.rsplit("/", 1)[-1]
    for kind, tol in tolerances.items():
        if last.startswith(kind):
            return tol
    raise ValueError(f"expected a figure key ending in one of {sorted(tolerances)}_*, got {key!r}")


def check_figures(measured: dict[str, float], expected: dict[str, float], tolerances: dict = TOLERANCES,
                  absent_prefixes: Sequence[str] = ()) -> list[str]:
    """One line per expected figure that is out of tolerance or not measured (unless its key
    starts with one of ``absent_prefixes``: sets whose photos are not on this machine), and
    per refusal count (``.../failed``) that is not expected; empty when every figure agrees.
    A missing refusal count is 0; other figures measured but not expected are not checked."""
    problems = []
    for key, want in sorted(expected.items()):
        got = measured.get(key, 0.0 if key.endswith("/failed") else None)
        if got is None:
            if not any(key.startswith(p) for p in absent_prefixes):
                problems.append(f"{key}: expected {want:.4g}, not measured")
            continue
        kind, tol = tolerance_for(key, tolerances)
        allowed = tol if kind == "abs" else tol * abs(want)
        if not (abs(got - want) <= allowed):
            problems.append(f"{key}: measured {got:.4g}, expected {want:.4g} ± {allowed:.3g}"
                            + (f" ({tol:.0%})" if kind == "rel" else ""))
    for key, got in sorted(measured.items()):
        if key.endswith("/failed") and key not in expected:
            problems.append(f"{key}: the method refused {got:.0f} patch(es), expected none")
    return problems


def expected_document(figures: dict[str, float], settings: Settings, env: dict, weights: dict,
                      robust_source: str = "bsds500-test") -> dict:
    """The contents of ``expected-quick.json`` for a quick run's figures (values to 6
    significant digits), with the photo set its robustness patches came from."""
    return {"schema": EXPECTED_SCHEMA, "version": 1, "made_by": UPDATE_COMMAND, "robust_source": robust_source,
            "made": {"commit": env["commit"], "date": env["date"], "cpu": env["cpu"], "precision": env["precision"]},
            "weights": weights, "settings": settings.fingerprint(),
            "tolerances": {k: list(v) for k, v in TOLERANCES.items()},
            "figures": {k: float(f"{v:.6g}") for k, v in figures.items()}}


def verify_expected(figures: dict[str, float], document: dict, settings: Settings, weights: dict,
                    absent_prefixes: Sequence[str] = (), source: str = "expected-quick.json",
                    robust_source: str = "bsds500-test") -> list[str]:
    """Check a quick run against an expected document; returns notes (the weights differ, or
    the robustness figures were not checked because their patches came from another photo
    set than the document's) when every checked figure agrees; raises `BenchmarkMismatch`
    naming every figure out of tolerance (and the weights that changed), or when the quick
    settings changed."""
    if document.get("schema") != EXPECTED_SCHEMA:
        raise BenchmarkMismatch(f"{source}: expected schema {EXPECTED_SCHEMA!r}, got {document.get('schema')!r}")
    if document.get("settings") != settings.fingerprint():
        raise BenchmarkMismatch(f"{source} was made with other quick settings than this urd's; regenerate it: {UPDATE_COMMAND}")
    tolerances = {k: tuple(v) for k, v in document.get("tolerances", {}).items()} or TOLERANCES
    notes = []
    if document.get("weights") != weights:
        notes.append(f"the weights differ from those {source} was made with ({weights_line(document.get('weights', {}))})")
    made = document.get("made", {})
    if document.get("robust_source", robust_source) != robust_source:
        notes.append(f"robustness figures not checked: {source} has them on {document['robust_source']} patches, "
                     f"this run on {robust_source} patches (its photos are not on this machine)")
        figures = {k: v for k, v in figures.items() if not k.startswith("robustness/")}
        absent_prefixes = [*absent_prefixes, "robustness/"]
    problems = check_figures(figures, document["figures"], tolerances, absent_prefixes)
    if problems:
        hint = [f"made at commit {made.get('commit', '?')} on {made.get('cpu', '?')}, precision {made.get('precision', '?')}"]
        raise BenchmarkMismatch(f"{len(problems)} figure(s) of the quick evaluation differ from {source}:\n  "
                                + "\n  ".join(problems + notes + hint)
                                + f"\nIf the change is intended (new weights, new methods), regenerate: {UPDATE_COMMAND}")
    return notes


def weights_line(weights: dict) -> str:
    """The weights a run used, one line: name, file and the first 12 hex digits of the SHA-256 per network."""
    return ", ".join(f"{name} {info.get('file', '?')} sha256 {info.get('sha256', '?')[:12]}" for name, info in weights.items())
