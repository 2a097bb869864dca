"""A static, self-contained HTML report of a dataset: a pure renderer over plain data.

`write_html_report` takes `SceneView` records (filled from the dataset API by `urd.report`)
and writes one folder that opens from disk with no server and no external assets::

    OUT/index.html                    inline CSS and JS, inline SVG plots and legends
    OUT/img/s000-NAME/shot_00.jpg     full-resolution sRGB views (JPEG, quality 95)
    OUT/img/s000-NAME/shot_00_t.jpg   thumbnails (long side ``thumb_px``, JPEG, quality 90)
    OUT/img/s000-NAME/m00_T_m.jpg     medium views of R̂/T̂ for the comparison slider (2 × thumb_px)
    OUT/.urd-report-contents          every file and folder the report wrote (`CONTENTS`)

Every string from the data is HTML-escaped; images are referenced by relative paths and
load lazily. What the page shows of each scene:

* the shots, S0, DoLP (viridis, legend 0..1) and AoLP (hue = AoLP over 0..180°,
  saturation = DoLP / `AOLP_FULL_SATURATION_DOLP`, value = S0 as displayed), all computed with
  `separate.optics` from the shots;
* the estimated reference angle (drawn on the AoLP colour wheel) and per-shot calibration errors;
* R̂, T̂ (and the reflection-presence map) of every method side by side, each with its
  provenance, and a comparison slider between any two of them;
* once per report, the Malus-law sweep behind the polarizer offset, drawn as an inline SVG plot.

The images, and the display gain they are shown with, come from `urd.report_images`.

The report folder is built in a fresh staging folder beside ``out_dir``, locked while in use,
and renamed into place when complete; the next run removes staging folders that killed runs
left (`_remove_stale_staging`) and puts back a report a killed run had moved aside to replace it
(`_restore_replaced`), and a full disk is reported naming the report folder. An
existing folder is replaced only with ``overwrite=True`` and only when it is empty or an urd
HTML report holding nothing but what the report wrote; a folder inside an urd dataset is
refused (`check_report_folder`).
"""

from __future__ import annotations

import dataclasses
import fcntl
import glob
import html
import json
import math
import os
import re
import shutil
import tempfile
import time
from pathlib import Path
from typing import Callable, Sequence
from urllib.parse import quote

import numpy as np

from urd.core.dataset import enclosing_dataset
from urd.core.errors import DatasetError
from urd.core.files import disk_full, write_error
from urd.core.images import read_stored_tiff, srgb_encode, to_display
from urd.report_assets import CSS, JS, calibration_svg, compare_html, wheel_svg
from urd.report_images import (
    AOLP_FULL_SATURATION_DOLP,
    EXPOSURE_PERCENTILE,
    WrittenImage,
    aolp_image,
    as_hwc,
    colormap_image,
    exposure_gain,
    field_image,
    map_preview,
    polarization_maps,
    write_image,
    write_png,
)

#: Written into index.html; `write_html_report` replaces only folders whose index.html has it.
GENERATOR = "urd report_html 2"

#: In the report folder: every file and folder the report wrote, itself included (relative POSIX
#: paths, one a line); a report holding anything else is not replaced.
CONTENTS = ".urd-report-contents"


class ReportExistsError(DatasetError, FileExistsError):
    """The report folder exists and may not be replaced."""


@dataclasses.dataclass
class ResultView:
    """One separation method's output for a scene.

    Attributes:
        method: method name (any text; escaped on the page).
        r, t: R̂ and T̂, H×W×C float32, linear, on S0's scale (R̂ + T̂ ≈ S0).
        provenance: parameters, weights hash, urd version, time …; JSON-able values (others are
            shown with ``str``).
        confidence: optional H×W reflection-presence map in [0, 1].
        reference_field: optional h×w reference s-direction φ⊥ the method used (deg).
        truth: optional PSNR/SSIM against ground truth ({"T": {"psnr_db", "ssim"}, "R": …}).
        exports: files to link (the polarization maps), absolute paths.
    """

    method: str
    r: np.ndarray
    t: np.ndarray
    provenance: dict
    confidence: np.ndarray | None = None
    reference_field: np.ndarray | None = None
    truth: dict | None = None
    exports: list[Path] = dataclasses.field(default_factory=list)


@dataclasses.dataclass
class CalibrationView:
    """A Malus-law sweep and its fit of the polarizer mounting offset (angles in degrees), with
    the fit's RMS residual (intensity units, `calib.polarizer.malus_fit`) when known. The offset
    and its uncertainty are None when the calibration cannot be read; ``notes`` say what is wrong
    (the sweep lists are then empty)."""

    angles_deg: list[float]
    intensities: list[float]
    fit_angles_deg: list[float]
    fit_intensities: list[float]
    offset_deg: float | None
    uncertainty_deg: float | None
    residual_rms: float | None = None
    notes: list[str] = dataclasses.field(default_factory=list)


@dataclasses.dataclass
class SceneView:
    """What the report shows of one scene.

    Attributes:
        name: scene name (escaped on the page).
        status: e.g. "ingested", "separated (network, schechner)", "incomplete (3 of 6 shots)".
        shots: (angle_deg, H×W×C float32 linear aligned shot) pairs; may be empty.
        reference_deg: estimated reference angle (reflection s-direction), degrees, or None.
        shot_errors_deg: per-shot calibration errors (degrees, one per shot), or None.
        results: one `ResultView` per separation method.
        notes: warnings to show.
        state: where the scene stands, which colours its badge: one of `BADGE_CLASSES`' keys
            (separated, ingested, captured, incomplete, alignment failed, broken); anything else
            is shown neutral.
        captured_deg: the angles of the shots captured (deg), listed where there are no aligned
            shots to show; empty when unknown.
        next_step: the command line that takes the scene further (e.g. ``urd ingest DATASET``), or "".
    """

    name: str
    status: str
    shots: list[tuple[float, np.ndarray]]
    reference_deg: float | None
    shot_errors_deg: list[float] | None
    results: list[ResultView]
    notes: list[str]
    state: str = ""
    captured_deg: list[float] = dataclasses.field(default_factory=list)
    next_step: str = ""


# ---------------------------------------------------------------------------------------------
# Argument checks


def _check_image(image, what: str, channels: bool = True) -> tuple[int, int]:
    if not isinstance(image, np.ndarray):
        raise TypeError(f"{what}: expected a numpy array, got {type(image).__name__}")
    ok_shape = image.ndim == 2 or (channels and image.ndim == 3 and image.shape[-1] in (1, 3))
    if not ok_shape or 0 in image.shape:
        expected = "H×W×C with C = 1 or 3" if channels else "H×W"
        raise ValueError(f"{what}: expected {expected}, got shape {image.shape}")
    if image.dtype.kind != "f":
        raise ValueError(f"{what}: expected float linear values, got dtype {image.dtype}")
    return image.shape[0], image.shape[1]


def _check_scene(scene: SceneView, index: int) -> None:
    if not isinstance(scene, SceneView):
        raise TypeError(f"scenes[{index}]: expected a SceneView, got {type(scene).__name__}")
    where = f"scene {scene.name!r}"
    sizes = set()
    for k, (angle, image) in enumerate(scene.shots):
        if not math.isfinite(float(angle)):
            raise ValueError(f"{where}: expected finite shot angles (deg), got {angle} for shot {k}")
        sizes.add(_check_image(image, f"{where}, shot {k}"))
    for result in scene.results:
        if not isinstance(result, ResultView):
            raise TypeError(f"{where}: expected ResultView results, got {type(result).__name__}")
        if not isinstance(result.provenance, dict):
            raise TypeError(f"{where}, {result.method}: expected a provenance dict, got {type(result.provenance).__name__}")
        sizes.add(_check_image(result.r, f"{where}, {result.method} R̂"))
        sizes.add(_check_image(result.t, f"{where}, {result.method} T̂"))
        if result.confidence is not None:
            sizes.add(_check_image(result.confidence, f"{where}, {result.method} confidence", channels=False))
        if result.reference_field is not None:
            _check_image(result.reference_field, f"{where}, {result.method} reference field", channels=False)
            if not np.isfinite(result.reference_field).all():
                raise ValueError(f"{where}, {result.method} reference field: expected finite angles (deg), got NaN or "
                                 "infinite values")
    if len(sizes) > 1:
        raise ValueError(f"{where}: expected shots and results of one size H×W, got {sorted(sizes)}")
    if scene.shot_errors_deg is not None and scene.shots and len(scene.shot_errors_deg) != len(scene.shots):
        raise ValueError(f"{where}: expected one calibration error per shot ({len(scene.shots)}), "
                         f"got {len(scene.shot_errors_deg)}")


# ---------------------------------------------------------------------------------------------
# The report folder


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_-]+", "-", text).strip("-")[:40] or "x"


def is_report_folder(path: Path) -> bool:
    """Whether ``path`` is an empty folder or an HTML report urd wrote (which --force may replace
    when it holds nothing else: `check_report_folder`)."""
    return (path.is_dir() and not any(path.iterdir())) or _written_by(path, GENERATOR)


def _written_by(path: Path, generator: str) -> bool:
    """Whether ``path/index.html`` names ``generator`` (`GENERATOR`, or an earlier one) as its maker."""
    index = path / "index.html"
    try:
        return index.is_file() and f'content="{generator}"' in index.read_text(encoding="utf-8", errors="replace")[:2000]
    except OSError:
        return False


def _contents(folder: Path) -> list[str]:
    """Every file, link and folder under ``folder`` (links not followed), as sorted relative POSIX paths."""
    return sorted(Path(top, name).relative_to(folder).as_posix()
                  for top, dirs, files in os.walk(folder) for name in dirs + files)


def _foreign_entry(folder: Path) -> str | None:
    """The first entry under the report folder ``folder`` that its `CONTENTS` list does not name
    (relative POSIX path), or None when it holds only what the report wrote."""
    try:
        listed = set((folder / CONTENTS).read_text(encoding="utf-8", errors="replace").splitlines())
    except OSError:
        listed = set()
    return next((entry for entry in _contents(folder) if entry not in listed), None)


def check_report_folder(out_dir: Path, overwrite: bool = False) -> None:
    """Check, before any work, that a report may be written into ``out_dir``: outside any urd
    dataset; absent, or with ``overwrite`` empty or an urd report holding only what it wrote; its
    parent writable (made when missing).

    Raises:
        ReportExistsError: ``out_dir`` exists and may not be replaced (the message says why).
        DatasetError: ``out_dir`` lies inside a dataset, or its parent cannot be written.
    """
    out_dir = Path(out_dir)
    dataset = enclosing_dataset(out_dir)
    if dataset is not None:
        raise DatasetError(f"{out_dir} is inside the dataset {dataset}, whose folders urd reads as scenes and "
                           "their files; write the report into a folder outside the dataset")
    if out_dir.exists() or out_dir.is_symlink():
        if out_dir.is_symlink() or not is_report_folder(out_dir):
            earlier = "an urd HTML report of an earlier urd, which did not record its files: remove it yourself, or " \
                if _written_by(out_dir, "urd report_html 1") else "not an urd HTML report; "
            raise ReportExistsError(f"{out_dir}: exists and is {earlier}choose another folder for the report")
        if not overwrite:
            raise ReportExistsError(f"{out_dir}: report folder already exists; pass --force to replace it, or "
                                    "another folder")
        foreign = _foreign_entry(out_dir)
        if foreign is not None:
            raise ReportExistsError(f"{out_dir}: holds {out_dir / foreign}, which urd's report did not write; "
                                    "move it out of the folder, or choose another folder for the report")
    try:
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=out_dir.parent):
            pass
    except OSError as exc:
        raise DatasetError(f"cannot write the report folder {out_dir} ({exc.strerror or exc}); choose another "
                           "folder for the report, or make its parent writable") from exc


def _staging_prefix(out_dir: Path) -> str:
    """How the staging folders of the report ``out_dir`` begin (a random suffix follows)."""
    return f".{out_dir.name}.staging-"


def _lock_folder(folder: Path) -> int | None:
    """An open descriptor of ``folder`` holding its exclusive lock (released when closed, or when
    its process dies), or None when another process holds it or it cannot be opened (a link is
    not followed)."""
    try:
        fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return None
    return fd


def _restore_replaced(out_dir: Path, settled_s: float = 10.0) -> None:
    """The report a run killed between its two renames left aside (``.NAME.old-*/report``, older
    than ``settled_s``: a live run holds one for a moment): put back at ``out_dir`` when nothing is
    there (the newest), else removed with its folder. Folders of other contents are left alone."""
    pattern = glob.escape(f".{out_dir.name}.old-") + "[a-z0-9_]" * 8          # tempfile.mkdtemp's names
    for folder in sorted(out_dir.parent.glob(pattern), key=lambda path: path.stat().st_mtime, reverse=True):
        kept = folder / "report"
        if (folder.is_symlink() or not kept.is_dir() or kept.is_symlink() or [p.name for p in folder.iterdir()] != ["report"]
                or folder.stat().st_mtime > time.time() - settled_s):
            continue
        if not out_dir.exists() and not out_dir.is_symlink():
            os.rename(kept, out_dir)
        shutil.rmtree(folder, ignore_errors=True)


def _remove_stale_staging(out_dir: Path, started: float) -> None:
    """Remove the staging folders of ``out_dir`` that runs killed before finishing left beside
    it: those made before ``started`` (a time.time()) whose lock no live run holds."""
    pattern = glob.escape(_staging_prefix(out_dir)) + "[a-z0-9_]" * 8          # tempfile.mkdtemp's names
    for folder in out_dir.parent.glob(pattern):
        fd = _lock_folder(folder)
        if fd is None:
            continue
        try:
            if os.fstat(fd).st_mtime < started:
                shutil.rmtree(folder, ignore_errors=True)
        finally:
            os.close(fd)


# ---------------------------------------------------------------------------------------------
# HTML pieces

_e = html.escape


def _url(path: str) -> str:
    """A relative POSIX path as an escaped URL for href/src: percent-encoded, so that #, % and ?
    in folder or file names stay part of the path."""
    return _e(quote(path))


def _fmt(value: float, digits: int = 2) -> str:
    return f"{value:.{digits}f}".replace("-", "−")


def _fmt_signed(value: float, digits: int = 2) -> str:
    return ("+" if value > 0 else "") + _fmt(value, digits)


def _figure(image: WrittenImage, caption: str, extra: str = "", label: str = "") -> str:
    """A thumbnail linking to its full view; ``caption`` and ``extra`` are HTML."""
    (w, h), (tw, th) = image.size, image.thumb_size
    title = _e(f"{label} — {w}×{h}, click for full resolution" if label else f"{w}×{h}")
    return (f'<figure style="flex: 0 1 {tw}px; min-width: {min(tw, 120)}px"><a class="zoom" href="{_url(image.full)}" data-caption="{_e(label)}" title="{title}">'
            f'<img src="{_url(image.thumb)}" width="{tw}" height="{th}" loading="lazy" alt="{_e(label)}"></a>'
            f"<figcaption>{caption}</figcaption>{extra}</figure>")


def _colorbar(lo: str, hi: str, what: str) -> str:
    ramp = colormap_image(np.linspace(0, 1, 9)[None, :])[0]
    stops = ", ".join(f"rgb({r},{g},{b})" for r, g, b in ramp)
    return (f'<div class="colorbar" role="img" aria-label="{_e(what)} legend, {lo} to {hi}">'
            f'<div class="ramp" style="background: linear-gradient(to right, {stops})"></div>'
            f'<div class="ticks"><span>{lo}</span><span>{_e(what)}</span><span>{hi}</span></div></div>')


def _field_colorbar(lo: float, hi: float) -> str:
    """The legend of a reference field spanning ``lo``..``hi`` (deg): its ends mod 180°, saying so
    when the range passes a multiple of 180° (the field wraps: φ⊥ and φ⊥ + 180° are one direction)."""
    wraps = math.floor(lo / 180.0) != math.floor(hi / 180.0)
    return _colorbar(f"{_fmt(lo % 180.0, 1)}°", f"{_fmt(hi % 180.0, 1)}°", "φ⊥, wraps at 180°" if wraps else "φ⊥")


def _calibration_html(cal: CalibrationView) -> str:
    offset = ("unknown" if cal.offset_deg is None
              else f"<b>{_fmt(cal.offset_deg, 3)}° ± {_fmt(cal.uncertainty_deg, 3)}°</b>")
    facts = [f"<dt>polarizer offset</dt><dd>{offset}</dd>"]
    if cal.angles_deg:
        facts.append(f"<dt>sweep</dt><dd>{len(cal.angles_deg)} stage angles</dd>")
    if cal.fit_intensities:
        peak = float(cal.fit_angles_deg[int(np.argmax(cal.fit_intensities))])
        facts.append(f"<dt>fit maximum</dt><dd>stage angle {_fmt(peak, 1)}° (shaded: ± the offset's uncertainty)</dd>")
    if cal.residual_rms is not None:
        swing = max(cal.fit_intensities) - min(cal.fit_intensities) if cal.fit_intensities else 0.0
        rel = f" ({100 * cal.residual_rms / swing:.2g}% of the modulation)" if swing > 0 else ""
        facts.append(f"<dt>RMS residual</dt><dd>{cal.residual_rms:.3g}{rel}</dd>")
    notes = '<ul class="notes">' + "".join(f"<li>{_e(note)}</li>" for note in cal.notes) + "</ul>" if cal.notes else ""
    plot = f'<div class="plotbox">{calibration_svg(cal)}</div>' if cal.angles_deg or cal.fit_angles_deg else ""
    return (f'<section class="card" id="calibration"><h2>Polarizer calibration</h2>{notes}'
            '<p class="muted">Malus-law sweep of a polarized target: measured mean intensity per stage angle (dots) '
            "and the least-squares fit I(a) = c0 + c1·cos 2a + c2·sin 2a (line).</p>"
            f'<div class="row">{plot}<dl class="facts">{"".join(facts)}</dl>'
            "</div></section>")


def _provenance_html(provenance: dict) -> str:
    rows = []
    for key, value in provenance.items():
        if isinstance(value, (str, int, float, bool)) or value is None:
            cell = _e(str(value))
        else:
            text = json.dumps(value, ensure_ascii=False, default=str)
            if len(text) > 80:
                text = json.dumps(value, indent=1, ensure_ascii=False, default=str)
            cell = f"<pre>{_e(text)}</pre>"
        rows.append(f"<tr><th>{_e(str(key))}</th><td>{cell}</td></tr>")
    body = "".join(rows) or '<tr><td class="muted">none recorded</td></tr>'
    return f'<details class="prov"><summary>provenance</summary><table class="kv">{body}</table></details>'


#: A scene's state (`SceneView.state`) → the class that colours its badge (`report_assets.CSS`).
BADGE_CLASSES = {"separated": "separated", "ingested": "ingested", "captured": "captured",
                 "incomplete": "incomplete", "alignment failed": "broken", "broken": "broken"}


def _status_badge(scene: SceneView) -> str:
    return f'<span class="badge {BADGE_CLASSES.get(scene.state, "other")}">{_e(scene.status)}</span>'


def _shot_count(scene: SceneView) -> int:
    """How many shots the scene has: those captured where known, else the aligned ones."""
    return len(scene.captured_deg) or len(scene.shots)


# ---------------------------------------------------------------------------------------------
# One scene


#: How the ground-truth figures of a result (`urd.separation.truth_metrics`) are labelled.
TRUTH_LABELS = {"T": "T̂", "R": "R̂", "T_no_separation": "no separation (S0 as T)"}


def truth_summary(truth: dict) -> str:
    """PSNR and SSIM against ground truth as one line of plain text."""
    return ", ".join(f"{TRUTH_LABELS.get(key, key)} {float(v['psnr_db']):.2f} dB (SSIM {float(v['ssim']):.3f})"
                     for key, v in truth.items() if isinstance(v, dict) and "psnr_db" in v and "ssim" in v)


def _truth_line(truth: dict) -> str:
    """PSNR and SSIM against ground truth, one paragraph."""
    summary = truth_summary(truth)
    return f'<p class="truth">vs ground truth: {_e(summary)}</p>' if summary else ""


def best_method(scene: SceneView) -> tuple[str, float, float | None] | None:
    """The method whose T̂ is closest to the ground truth (highest PSNR), its PSNR and that of no
    separation (dB); None when no result has ground-truth figures."""
    scored = [(float(r.truth["T"]["psnr_db"]), r.method, r.truth.get("T_no_separation", {}).get("psnr_db"))
              for r in scene.results if r.truth and isinstance(r.truth.get("T"), dict) and "psnr_db" in r.truth["T"]]
    if not scored:
        return None
    psnr, method, plain = max(scored)
    return method, psnr, None if plain is None else float(plain)


def _best_html(scene: SceneView) -> str:
    """One line naming the method that scored best against the ground truth, where there is one."""
    best = best_method(scene)
    if best is None:
        return ""
    method, psnr, plain = best
    among = f"best of {len(scene.results)} methods" if len(scene.results) > 1 else "the only method here"
    baseline = f"; no separation (S0 as T̂) {_fmt(plain)} dB" if plain is not None else ""
    return (f'<p class="best">Against the ground truth, <b>{_e(method)}</b> recovers T̂ with {_fmt(psnr)} dB PSNR '
            f"({among}{baseline}; higher is better).</p>")


def _exports_html(exports: list[Path], links_from: Path, root: Path, stem: str) -> str:
    """Links to the exported polarization maps: a PNG preview of each (written under ``root``
    as ``stem_map_NAME.png``, `map_preview`) and its float32 TIFF, relative to the report
    folder ``links_from``."""
    if not exports:
        return ""
    links = []
    for path in exports:
        try:
            rgb, span = map_preview(path.stem, read_stored_tiff(path))
        except (OSError, ValueError) as exc:
            links.append(f"{_e(path.stem)} (cannot be read: {_e(str(exc))})")
            continue
        write_png(root / f"{stem}_map_{path.stem}.png", rgb)
        data = _url(Path(os.path.relpath(path, links_from)).as_posix())
        links.append(f'<a href="{_url(f"{stem}_map_{path.stem}.png")}">{_e(path.stem)}</a> '
                     f'<span class="muted">({_e(span)}; <a href="{data}">TIFF</a>)</span>')
    return ('<p class="small">polarization maps, previews over the stated range, AoLP as hue and the others in '
            "viridis (black: dark pixels, NaN in the data); TIFF: the float32 data, units in each file's description: "
            + " · ".join(links) + "</p>")


def _scene_html(scene: SceneView, index: int, root: Path, folder: str, thumb_px: int, links_from: Path) -> str:
    """Write one scene's images under ``root / folder`` and return its section (links to data
    files relative to the final report folder ``links_from``)."""
    if scene.shots or scene.results:
        (root / folder).mkdir(parents=True)
    anchor = f"scene-{index:03d}"
    notes = list(scene.notes)
    s0 = maps = None
    if len(scene.shots) >= 3:
        try:
            s0, dolp_map, aolp_map = polarization_maps(scene.shots)
            maps = (dolp_map, aolp_map)
        except ValueError as exc:
            notes.append(f"no polarization maps: {exc}")
    elif scene.shots:
        notes.append(f"no polarization maps: {len(scene.shots)} shot(s), Stokes parameters need 3 or more angles")
    if s0 is not None:
        gain, basis = exposure_gain(s0), "S0"
    elif scene.shots:
        gain, basis = exposure_gain(2 * np.mean([as_hwc(im) for _, im in scene.shots], axis=0)), "2 × the mean shot"
    elif scene.results:
        gain, basis = exposure_gain(as_hwc(scene.results[0].r) + as_hwc(scene.results[0].t)), \
            f"R̂ + T̂ of {scene.results[0].method}"
    else:
        gain, basis = 1.0, ""

    meta = [_status_badge(scene)]
    if scene.reference_deg is not None:
        meta.append(f'<span class="fact">reference angle φ⊥ = <b>{_fmt(float(scene.reference_deg))}°</b></span>')
    if scene.shots:
        meta.append(f'<span class="fact">{len(scene.shots)} shots, {scene.shots[0][1].shape[1]}×{scene.shots[0][1].shape[0]} px</span>')
    parts = [f'<section class="card scene" id="{anchor}"><div class="scene-head"><h2>{_e(scene.name)}</h2>'
             f'<div class="meta">{"".join(meta)}</div></div>']
    if notes:
        parts.append('<ul class="notes">' + "".join(f"<li>{_e(str(n))}</li>" for n in notes) + "</ul>")
    if basis:
        parts.append(f'<p class="muted small">Exposure: S0, R̂, T̂ × {gain:.3g}, shots × {2 * gain:.3g} '
                     f"(k = 1 / {EXPOSURE_PERCENTILE:g}th percentile of {_e(basis)} = 1 / {1 / gain:.3g}), then sRGB.</p>")

    if scene.shots:
        figs = []
        for k, (angle, image) in enumerate(scene.shots):
            written = write_image(root, f"{folder}/shot_{k:02d}", to_display(image, 2 * gain), thumb_px)
            caption = f"φ = {_fmt(float(angle), 1)}°"
            if scene.shot_errors_deg is not None:
                caption += f' <span class="err">calib. error {_fmt_signed(float(scene.shot_errors_deg[k]))}°</span>'
            figs.append(_figure(written, caption, label=f"{scene.name} shot {k} at {float(angle):.1f}°"))
        parts.append(f'<h3>Shots</h3><div class="row strip">{"".join(figs)}</div>')
    elif scene.captured_deg:
        angles = ", ".join(f"{_fmt(float(a), 1)}°" for a in scene.captured_deg)
        parts.append(f"<h3>Shots</h3><p>{len(scene.captured_deg)} captured, at φ = {angles}; no aligned images yet.</p>")
    elif scene.shot_errors_deg:
        parts.append("<h3>Shot calibration</h3><p>errors: "
                     + ", ".join(f"{_fmt_signed(float(e))}°" for e in scene.shot_errors_deg) + "</p>")
    if scene.next_step:
        parts.append(f'<p class="next">To continue: <code>{_e(scene.next_step)}</code></p>')

    s0_image = None
    if maps is not None:
        dolp_map, aolp_map = maps
        s0_image = write_image(root, f"{folder}/s0", to_display(s0, gain), thumb_px, mid=bool(scene.results))
        value = srgb_encode(s0.mean(axis=-1) * gain)
        dolp_image = write_image(root, f"{folder}/dolp", colormap_image(dolp_map), thumb_px)
        aolp_written = write_image(root, f"{folder}/aolp", aolp_image(aolp_map, dolp_map, value), thumb_px)
        wheel_note = "dashed line: reference angle φ⊥" if scene.reference_deg is not None else ""
        parts.append('<h3>Polarization</h3><div class="row">'
                     + _figure(s0_image, "S0 (unpolarized intensity)", label=f"{scene.name} S0")
                     + _figure(dolp_image, "DoLP", _colorbar("0", "1", "DoLP"), label=f"{scene.name} DoLP")
                     + _figure(aolp_written, f"AoLP as hue; saturation DoLP / {AOLP_FULL_SATURATION_DOLP:g}, value S0",
                               label=f"{scene.name} AoLP")
                     + f'<figure class="legend">{wheel_svg(f"wheel-{index}", scene.reference_deg)}'
                     f'<figcaption>AoLP legend: hue by angle 0–180°, white centre unpolarized{"; " + wheel_note if wheel_note else ""}</figcaption></figure>'
                     "</div>")

    if scene.results:
        rows, options = [], []
        if s0_image is not None:
            options.append((s0_image.mid, "S0 (input)"))
        for m, result in enumerate(scene.results):
            stem = f"{folder}/m{m:02d}_{_slug(result.method)}"
            r_img = write_image(root, f"{stem}_R", to_display(result.r, gain), thumb_px, mid=True)
            t_img = write_image(root, f"{stem}_T", to_display(result.t, gain), thumb_px, mid=True)
            options += [(t_img.mid, f"{result.method} · T̂"), (r_img.mid, f"{result.method} · R̂")]
            cells = [_figure(r_img, "R̂ (reflection)", label=f"{scene.name} {result.method} R̂"),
                     _figure(t_img, "T̂ (transmission)", label=f"{scene.name} {result.method} T̂")]
            if result.confidence is not None:
                c_img = write_image(root, f"{stem}_conf", colormap_image(result.confidence), thumb_px)
                cells.append(_figure(c_img, "reflection presence (a hint: 0 none, 1 all reflection)", _colorbar("0", "1", "presence"),
                                     label=f"{scene.name} {result.method} reflection presence"))
            if result.reference_field is not None:
                field_rgb, lo, hi = field_image(result.reference_field)
                f_img = write_image(root, f"{stem}_phi", field_rgb, max(32, thumb_px // 3))     # a smooth field: small
                cells.append(_figure(f_img, "reference φ⊥ used", _field_colorbar(lo, hi),
                                     label=f"{scene.name} {result.method} reference φ⊥"))
            truth = _truth_line(result.truth) if result.truth else ""
            rows.append(f'<div class="method"><div class="method-name">{_e(result.method)}</div>{truth}'
                        f'<div class="row">{"".join(cells)}</div>{_exports_html(result.exports, links_from, root, stem)}'
                        f'{_provenance_html(result.provenance)}</div>')
        parts.append(f'<h3>Separation ({len(scene.results)} method{"s" if len(scene.results) > 1 else ""})</h3>'
                     + _best_html(scene) + "".join(rows))
        t_first = 1 if s0_image is not None else 0                        # options: [S0], T̂, R̂ per method
        right = t_first + 2 if len(scene.results) > 1 else (0 if s0_image is not None else t_first + 1)
        parts.append(compare_html(options, t_first, right, scene.results[0].t.shape[:2], anchor, thumb_px))
    parts.append("</section>")
    return "".join(parts)


# ---------------------------------------------------------------------------------------------
# The page


def _howto_html() -> str:
    return ('<section class="card howto"><h2>Reading this page</h2><ul>'
            "<li><b>Each scene</b> is one capture through glass: first its <b>shots</b>, one per polarizer angle φ; then "
            "its <b>polarization</b> (S0: the image without a polarizer; DoLP: how polarized each pixel is, 0 to 1; "
            "AoLP: in which direction); then <b>one row per separation method</b>: R̂, the reflection it took out, "
            "T̂, the scene behind the glass, the reflection-presence map and the reference φ⊥ it used. A slider "
            "below compares any two of them.</li>"
            "<li><b>Which method did best</b>: where a scene has ground truth (the virtual camera's scenes), a line "
            "names the method whose T̂ came closest (PSNR in dB, higher is better), and the table above lists it.</li>"
            "<li><b>Reflection presence</b> is a hint from the polarization alone of how much of each pixel is "
            "reflected light (0 none, 1 all); it is not the separation. Light that is polarized for other reasons "
            "(glossy or metal objects, sky seen through the pane) lights it up too, on transmitted objects.</li>"
            "<li><b>Polarization maps</b> (with <code>urd separate --maps</code>): PNG previews to look at, "
            "float32 TIFFs with units for analysis.</li>"
            f"<li>Details: images are linear light shown in sRGB: per scene, S0, R̂ and T̂ are multiplied by k = 1 / "
            f"({EXPOSURE_PERCENTILE:g}th percentile of S0), shots by 2k (a shot records "
            "(S0 + S1 cos 2φ + S2 sin 2φ)/2), then sRGB-encoded and clipped; the factor is stated with each scene.</li>"
            "<li>S0, DoLP and AoLP are the least-squares Stokes fit of the aligned shots; DoLP and AoLP are those of the "
            "Stokes vector summed over the colour channels.</li>"
            "<li>A shot's φ is the polarizer's angle in the aligned stack: the stage's angle plus the shot's turn "
            "against the first shot (the polarizer in front of the lens turns with the camera), or the angle "
            "<code>urd calibrate shots</code> measured; these are the angles each method separated at.</li>"
            f"<li>AoLP is shown as hue (0° red, 60° green, 120° blue, over 0–180°), saturation DoLP / "
            f"{AOLP_FULL_SATURATION_DOLP:g}, value from S0. Angles: in the image plane from +x, counter-clockwise as seen.</li>"
            "<li>R̂ + T̂ ≈ S0 for every method, except where T̂ was colour-matched (--colour-match). Click any thumbnail for the full-resolution view (JPEG previews; "
            "the dataset's linear 16-bit TIFFs are the data).</li></ul></section>")


def _toc_row(s: SceneView, i: int) -> str:
    """The Scenes table's row of scene ``s``, the ``i``-th on the page."""
    return (f'<tr><td><a href="#scene-{i:03d}">{_e(s.name)}</a></td><td>{_status_badge(s)}</td>'
            f"<td>{_shot_count(s)}</td><td>{_e(', '.join(r.method for r in s.results)) or '—'}</td>"
            f"<td>{_fmt(float(s.reference_deg)) + '°' if s.reference_deg is not None else '—'}</td>"
            f"<td>{_best_cell(s)}</td></tr>")


def _toc_html(rows: Sequence[str]) -> str:
    """The Scenes table of the rows `_toc_row` made."""
    if not rows:
        return '<nav class="card toc"><h2>Scenes</h2><p class="muted">no scenes yet</p></nav>'
    return ('<nav class="card toc"><h2>Scenes</h2><div class="scroll"><table><thead><tr><th>scene</th><th>status</th><th>shots</th>'
            f"<th>methods</th><th>reference angle</th><th>best T̂ vs ground truth</th></tr></thead><tbody>{''.join(rows)}</tbody>"
            "</table></div></nav>")


def _best_cell(scene: SceneView) -> str:
    best = best_method(scene)
    return "—" if best is None else f"{_e(best[0])}, {_fmt(best[1])} dB"


def write_html_report(scenes: list[SceneView], out_dir: Path, title: str, calibration: CalibrationView | None = None,
                      thumb_px: int = 320, progress: Callable[[int, int], None] | None = None,
                      overwrite: bool = False) -> Path:
    """Write the static HTML report of ``scenes`` into the folder ``out_dir``.

    Args:
        scenes: what to show, one `SceneView` per scene, in page order; each is taken once, its
            images written and let go, so a sequence that makes its views on demand
            (`urd.report.report_html`'s) keeps one scene's images in memory at a time.
        out_dir: the report folder; it must not exist unless ``overwrite`` (see below).
        title: page title (escaped).
        calibration: the Malus-law sweep behind the polarizer offset, if any.
        thumb_px: long side of the thumbnails on the page (px, 32..4096); the comparison slider
            uses 2 × thumb_px views, clicks open the full resolution.
        progress: called as ``progress(done, total)`` with counts of scenes written.
        overwrite: replace an existing report folder (one this function wrote and nothing else
            was added to, or an empty folder); anything else is never replaced.

    Returns:
        The path of ``out_dir / "index.html"``.

    Raises:
        ReportExistsError (a FileExistsError): ``out_dir`` exists and ``overwrite`` is false, or it
            is not an urd HTML report, or it holds files the report did not write.
        DatasetError: ``out_dir`` lies inside an urd dataset, or cannot be written (DiskFullError
            naming it when its disk is full).
        TypeError, ValueError: malformed views (wrong types, shapes, dtypes, non-finite angles).
    """
    if not isinstance(thumb_px, int) or isinstance(thumb_px, bool):
        raise TypeError(f"thumb_px: expected an int, got {type(thumb_px).__name__}")
    if not 32 <= thumb_px <= 4096:
        raise ValueError(f"thumb_px: expected 32..4096 px, got {thumb_px}")
    if calibration is not None and not isinstance(calibration, CalibrationView):
        raise TypeError(f"calibration: expected a CalibrationView, got {type(calibration).__name__}")
    if calibration is not None and len(calibration.angles_deg) != len(calibration.intensities):
        raise ValueError(f"calibration: expected one intensity per angle ({len(calibration.angles_deg)}), "
                         f"got {len(calibration.intensities)}")
    if calibration is not None and len(calibration.fit_angles_deg) != len(calibration.fit_intensities):
        raise ValueError(f"calibration: expected one fit intensity per fit angle ({len(calibration.fit_angles_deg)}), "
                         f"got {len(calibration.fit_intensities)}")
    out_dir = Path(out_dir)
    _restore_replaced(out_dir)
    check_report_folder(out_dir, overwrite)
    started = time.time()
    try:
        staging = Path(tempfile.mkdtemp(prefix=_staging_prefix(out_dir), dir=out_dir.parent))
    except OSError as exc:
        raise write_error(out_dir, exc) from exc
    held = os.open(staging, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        fcntl.flock(held, fcntl.LOCK_EX)            # marks it live (`_remove_stale_staging`); waits only for a check
        _remove_stale_staging(out_dir, started)
        sections, rows = [], []
        for i in range(len(scenes)):
            if progress:
                progress(i, len(scenes))
            scene = scenes[i]
            _check_scene(scene, i)
            sections.append(_scene_html(scene, i, staging, f"img/s{i:03d}-{_slug(scene.name)}", thumb_px, out_dir.resolve()))
            rows.append(_toc_row(scene, i))
            del scene
        count = f"{len(scenes)} scene{'s' if len(scenes) != 1 else ''}"
        page = ('<!doctype html>\n<html lang="en"><head><meta charset="utf-8">'
                '<meta name="viewport" content="width=device-width, initial-scale=1">'
                f'<meta name="generator" content="{GENERATOR}"><title>{_e(title)}</title>'
                f'<link rel="icon" href="data:,"><style>{CSS}</style></head><body><main>'
                f'<header><h1>{_e(title)}</h1><p class="muted">{count}'
                f'{" · polarizer calibrated" if calibration is not None and calibration.offset_deg is not None else ""}'
                " · static report written by urd</p></header>"
                + _toc_html(rows) + _howto_html()
                + (_calibration_html(calibration) if calibration is not None else "")
                + "".join(sections)
                + '</main><div id="viewer" hidden><div class="bar"><span class="caption"></span>'
                '<button type="button">close ✕</button></div><div class="holder"></div></div>'
                f"<script>{JS}</script></body></html>\n")
        (staging / "index.html").write_text(page, encoding="utf-8")
        (staging / CONTENTS).write_text("\n".join(sorted([*_contents(staging), CONTENTS])) + "\n", encoding="utf-8")
        os.chmod(staging, 0o755)
        if out_dir.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.old-", dir=out_dir.parent))
            os.rename(out_dir, old / "report")
            try:
                os.rename(staging, out_dir)
            except BaseException:
                os.rename(old / "report", out_dir)
                raise
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.rename(staging, out_dir)
    except BaseException as exc:
        full = isinstance(exc, OSError) and not isinstance(exc, DatasetError) and disk_full(exc, out_dir.parent)
        shutil.rmtree(staging, ignore_errors=True)
        if full:
            raise write_error(out_dir, exc, full=True) from exc
        raise
    finally:
        os.close(held)
    if progress:
        progress(len(scenes), len(scenes))
    return out_dir / "index.html"
