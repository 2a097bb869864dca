"""Run a separation method on a scene (or on image files) and store its results.

Outputs go to ``results/METHOD/`` of a scene (or a chosen folder): ``R.tiff`` and ``T.tiff``,
linear 16-bit RGB with full scale 2.0 (value = DN / 65535 × 2, since R + T = S0 reaches twice
a single shot's white level), and ``R_preview.png`` / ``T_preview.png``, 8-bit sRGB at most 2048 px
long, scaled by one common white point; ``confidence.tiff``, the reflection-presence map
(`separate.reference.presence_map`), ``clipped.png``, the pixels clipped in some shot
(`separate.reference.clipped_mask`; all black when none is), and ``reference_deg.tiff``, the
reference s-direction φ⊥ the polarization methods used (deg, float32, on the reduced grid of at
most 512 px; constant for a global or given reference). With ``maps`` the polarization maps of
`separate.maps.MAPS` are written too (``maps/S0.tiff`` … ``maps/theta.tiff``, float32 at full
resolution, each file's ImageDescription a JSON record of its quantity, unit and the angle
convention). The scene manifest's ``results`` record names the method, its
parameters, the weights' SHA-256 for the network, the files with their hashes, and PSNR/SSIM
against the virtual camera's ground truth when the scene has one.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import functools
import json
import os
import shutil
import tempfile
from pathlib import Path

import cv2
import numpy as np
import tifffile

from separate import metrics, optics
from separate.methods import sees_polarization_of, separate_inspected
from separate.reference import Inspection, resolve_reference
from urd.core.dataset import SCENE_NAME, Scene, enclosing_dataset
from urd.core.errors import DatasetError, ManifestError
from urd.core.files import atomic_path
from urd.core.images import (ORIENTATIONS, Transfer, exif_orientation, linear_image, linear_to_u16, read_raw_codes,
                             read_stored_tiff, to_display)

FULL_SCALE = 2.0
PREVIEW_SIDE = 2048


#: What a result TIFF's ImageDescription says of its values (JSON).
LINEAR_TIFF_DESCRIPTION = json.dumps({"encoding": f"linear light, 65535 = {FULL_SCALE:g} (1 = one shot's white)",
                                      "full_scale": FULL_SCALE, "software": "urd"})


def write_linear_tiff(path: Path, image: np.ndarray, overwrite: bool = False) -> None:
    """Linear H×W×3 → 16-bit TIFF with full scale `FULL_SCALE`, stated in its ImageDescription
    (`LINEAR_TIFF_DESCRIPTION`), atomically."""
    data = linear_to_u16(image, FULL_SCALE)
    with atomic_path(path, overwrite) as tmp:
        tifffile.imwrite(tmp, data, photometric="rgb", description=LINEAR_TIFF_DESCRIPTION, metadata=None)


def write_preview(path: Path, image: np.ndarray, white: float, overwrite: bool = False, max_side: int = PREVIEW_SIDE) -> None:
    """Linear H×W×3 → 8-bit sRGB PNG at most ``max_side`` px long, ``white`` mapping to 255."""
    scale = min(1.0, max_side / max(image.shape[:2]))
    if scale < 1:
        image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    rgb = to_display(image, 1.0 / white)
    write_png(path, rgb[..., ::-1], overwrite)


def _read_mapped(path: Path, shape: tuple[int, ...], scene: Scene) -> np.ndarray:
    """A ground-truth TIFF of ``shape`` (H, W, 3), memory-mapped read-only where the file
    allows it (uncompressed, one contiguous strip; no copy of a 24 MP truth image), else read.
    DatasetError naming the file, and what to do, when it cannot be read or has another shape."""
    try:
        try:
            image = tifffile.memmap(path, mode="r")
        except ValueError:
            image = read_stored_tiff(path)
    except (OSError, ValueError) as exc:              # tifffile.TiffFileError is a ValueError
        problem = f"cannot be read ({exc})"
    else:
        if image.shape == shape:
            return image
        problem = f"has shape {image.shape}, expected {shape} (the results' shape)"
    from acquire.plan import resume_command

    raise DatasetError(f"{scene.name}: ground truth {path} {problem}; move {scene.truth_dir()} away to separate "
                       f"without ground-truth figures; then this writes it again: {resume_command(scene.path.parent, scene)}")


def truth_metrics(scene: Scene, r_hat: np.ndarray, t_hat: np.ndarray, images: np.ndarray, angles_deg: list[float],
                  rows: int = 256) -> dict | None:
    """PSNR/SSIM of R̂, T̂ and of no separation (S0 of the shots ``images`` at ``angles_deg``, the
    same for every method) against the scene's ground truth, if any: R̂ and T̂ as their files hold
    them, within [0, `FULL_SCALE`] (a baseline's negative light is stored as 0).

    Figures are computed 5% inside the border (aligned shots are padded there), with peak 1;
    PSNR over ``rows`` rows at a time (no full-size temporaries), SSIM on the central
    1024×1024 pixels at most. The truth files are checked first (`Scene.truth_files`).
    """
    truth = scene.truth_files()
    if truth is None or "T_obs.tiff" not in truth:
        return None
    r_true, t_true = (_read_mapped(truth.get(name, scene.truth_dir() / name), t_hat.shape, scene)
                      for name in ("R_obs.tiff", "T_obs.tiff"))
    h, w = t_true.shape[:2]
    top, bottom, cols = h // 20, h - h // 20, slice(w // 20, w - w // 20)
    weights = optics.stokes_fit(np.radians(angles_deg))[0] * optics.code_scale(images)

    def s0(region: tuple[slice, slice]) -> np.ndarray:
        return np.tensordot(weights.astype(np.float32), images[(slice(None), *region)], axes=1).astype(np.float32)

    pairs = {"R": lambda region: (np.clip(r_hat[region], 0.0, FULL_SCALE), r_true[region]),
             "T": lambda region: (np.clip(t_hat[region], 0.0, FULL_SCALE), t_true[region]),
             "T_no_separation": lambda region: (s0(region), t_true[region])}
    squared = dict.fromkeys(pairs, 0.0)
    for y in range(top, bottom, rows):
        block = (slice(y, min(bottom, y + rows)), cols)
        for name, pair in pairs.items():
            est, ref = pair(block)
            squared[name] += float(np.square(est - ref).sum(dtype=np.float64))
    count = (bottom - top) * (cols.stop - cols.start) * t_true.shape[2]
    cy, cx = h // 2, w // 2
    centre = (slice(max(top, cy - 512), min(bottom, cy + 512)), slice(max(cols.start, cx - 512), min(cols.stop, cx + 512)))
    out = {}
    for name, pair in pairs.items():
        est, ref = pair(centre)
        out[name] = {"psnr_db": round(float(metrics.psnr_from_mse(squared[name] / count)), 3),
                     "ssim": round(metrics.ssim(np.clip(est, 0, 1), np.clip(ref, 0, 1)), 4)}
    return out


#: The angle convention written into every angle map's metadata.
ANGLE_CONVENTION = "degrees in the image plane from the +x axis (towards increasing column), counter-clockwise as seen (towards row 0)"

#: What ``confidence.tiff`` holds (`separate.reference.presence_map`), written into its metadata.
PRESENCE_QUANTITY = ("reflection presence: the share of reflected light R/S0 read from the polarization alone "
                     "(0 no reflection, 1 all reflection; a smooth hint, not a separation)")


def write_confidence(path: Path, confidence: np.ndarray, overwrite: bool = False) -> None:
    """The reflection-presence map as a float32 TIFF with its quantity (`write_float_map`), atomically."""
    write_float_map(path, confidence, PRESENCE_QUANTITY, "1 (a fraction)", overwrite)


#: The maps whose values are angles in the image plane (`ANGLE_CONVENTION`); θ is an angle of incidence.
IN_PLANE_ANGLES = ("AoLP", "phi_perp")


def write_float_map(path: Path, values: np.ndarray, quantity: str, unit: str, overwrite: bool = False,
                    in_plane: bool = False) -> None:
    """A float32 map (H×W or H×W×C) as a one-page TIFF (RGB where C is 3, the channels of each
    pixel together: what image programs read as an H×W image) whose ImageDescription is JSON:
    ``quantity``, ``unit`` and, for angles in the image plane (``in_plane``), urd's angle
    convention; atomically."""
    values = np.asarray(values, np.float32)
    description = json.dumps({"quantity": quantity, "unit": unit, **({"angle_convention": ANGLE_CONVENTION} if in_plane else {}),
                              "software": "urd"})
    layout = ({"photometric": "rgb"} if values.ndim == 3 and values.shape[2] == 3 else
              {"photometric": "minisblack", "planarconfig": "contig"} if values.ndim == 3 else {"photometric": "minisblack"})
    with atomic_path(path, overwrite) as tmp:
        tifffile.imwrite(tmp, values, description=description, metadata=None, **layout)


#: The stored result files `read_result` checks: name → (what it holds, its dtypes, the numbers of
#: dimensions it may have, the channels of a 3-D one, whether every value must be finite).
RESULT_FILES = {
    "R.tiff": ("H×W×3 (or grey) 16-bit linear codes", ("uint16",), (2, 3), (1, 3), False),
    "T.tiff": ("H×W×3 (or grey) 16-bit linear codes", ("uint16",), (2, 3), (1, 3), False),
    "confidence.tiff": ("an H×W float map of reflection presence", ("float32", "float64"), (2,), (), False),
    "reference_deg.tiff": ("an h×w float map of finite angles (deg)", ("float32", "float64"), (2,), (), True),
}


def read_result(path: Path) -> np.ndarray:
    """A stored result file (`RESULT_FILES`, by its name) as `write_results` wrote it; ManifestError
    naming the file when it holds another layout or dtype (or, for the reference field, a NaN or an
    infinity): damaged, or not written by urd."""
    what, dtypes, dims, channels, finite = RESULT_FILES[Path(path).name]
    values = read_stored_tiff(Path(path))                  # an uncompressed file, as urd writes them
    if (values.dtype.name not in dtypes or values.ndim not in dims or 0 in values.shape
            or (values.ndim == 3 and values.shape[2] not in channels)):
        raise ManifestError(f"{path}: expected {what}, got {values.dtype} of shape {values.shape} (damaged, or not "
                            "written by urd)")
    if finite and not np.isfinite(values).all():
        raise ManifestError(f"{path}: expected {what}, got NaN or infinite values (damaged, or not written by urd)")
    return values


def write_maps(folder: Path, maps: dict[str, np.ndarray], overwrite: bool = False) -> list[Path]:
    """The polarization maps (`separate.maps.polarization_maps`) as ``folder/NAME.tiff``
    (`write_float_map`, units from `separate.maps.MAPS`); returns their paths."""
    from separate.maps import MAPS

    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, values in maps.items():
        unit, meaning = MAPS[name]
        write_float_map(folder / f"{name}.tiff", values, meaning, unit, overwrite, in_plane=name in IN_PLANE_ANGLES)
        paths.append(folder / f"{name}.tiff")
    return paths


def write_mask(path: Path, mask: np.ndarray, overwrite: bool = False) -> None:
    """A boolean mask as an 8-bit PNG (255 = true), atomically."""
    write_png(path, mask.astype(np.uint8) * np.uint8(255), overwrite)


def write_png(path: Path, image: np.ndarray, overwrite: bool = False) -> None:
    """An 8-bit image (H×W, or H×W×3 BGR) as a PNG, atomically: encoded in memory and written by
    Python, so that a full disk is an error naming the file (`urd.core.files.atomic_path`)."""
    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise DatasetError(f"cannot encode {path} as PNG")
    with atomic_path(path, overwrite) as tmp:
        tmp.write_bytes(data.tobytes())


#: The files `write_results` may write (besides ``maps/``).
RESULT_NAMES = ("R.tiff", "T.tiff", "R_preview.png", "T_preview.png", "confidence.tiff", "clipped.png",
                "reference_deg.tiff")


def write_results(folder: Path, r_hat: np.ndarray, t_hat: np.ndarray, overwrite: bool,
                  confidence: np.ndarray | None = None, clipped: np.ndarray | None = None,
                  reference_field: np.ndarray | None = None) -> list[Path]:
    """Write the result files into ``folder`` (R, T as linear TIFF, sRGB previews, and when
    given the reflection-presence map, the clipped pixels as a PNG, 255 = clipped, and the
    reference field, deg), two at a time (encoding and writing release the GIL: 1.9 → 1.1 s
    for 24 MP); return their paths."""
    folder.mkdir(parents=True, exist_ok=True)
    step = max(1, int(np.sqrt(r_hat.size / 3 / 1e6)))                 # percentile of ~1 M samples
    white = float(np.percentile(r_hat[::step, ::step] + t_hat[::step, ::step], 99.5)) or 1.0
    jobs = {folder / "R.tiff": (write_linear_tiff, r_hat), folder / "T.tiff": (write_linear_tiff, t_hat),
            folder / "R_preview.png": (functools.partial(write_preview, white=white), r_hat),
            folder / "T_preview.png": (functools.partial(write_preview, white=white), t_hat)}
    if confidence is not None:
        jobs[folder / "confidence.tiff"] = (write_confidence, confidence)
    if clipped is not None:
        jobs[folder / "clipped.png"] = (write_mask, clipped)
    if reference_field is not None:
        jobs[folder / "reference_deg.tiff"] = (functools.partial(
            write_float_map, quantity="reference s-direction phi_perp used for separation (reduced grid)",
            unit="deg", in_plane=True), reference_field)
    with concurrent.futures.ThreadPoolExecutor(max_workers=2) as pool:
        for done in [pool.submit(write, path, image, overwrite=overwrite) for path, (write, image) in jobs.items()]:
            done.result()
    return list(jobs)


@dataclasses.dataclass
class Separation:
    """What a separation produced: files written, the reference angle used (deg), warnings
    about the input, PSNR/SSIM against ground truth where the scene has one, and how the
    reference was chosen (`reference_kind`)."""

    files: list[Path]
    reference_deg: float
    warnings: list[str]
    truth_metrics: dict | None = None
    reference_kind: str = ""


@dataclasses.dataclass
class Prepared:
    """A scene's separation computed and written into a staging folder inside the scene, not yet
    recorded (`prepare_scene`; `commit_scene` records it). ``staged`` maps final names (relative
    to the scene) to staged paths; ``entry`` is the manifest record."""

    scene: Path
    method: str
    staging: Path
    staged: dict[str, Path]
    entry: dict
    separation: Separation


def prepare_scene(scene: Scene, method: str, run, info: dict, reference: str | float = "auto",
                  maps: bool = False) -> Prepared:
    """The work of `separate_scene` without touching the manifest: separate the ingested stack
    and write the outputs into a new staging folder of the scene (which the dataset's recovery
    removes should the process die before `commit_scene`). Runs without the dataset's lock,
    so that several processes can prepare scenes of one dataset while one commits them."""
    scene.reload()
    scene.truth_files()                                    # damaged ground truth stops it before the work
    _check_results_folder(scene, method)                   # so do a link or a file where the results go
    images, angles = scene.load_stack(codes=True)          # uint16: half the memory of float32
    sees_polarization = sees_polarization_of(info)
    r_hat, t_hat, inspection, used = separate_inspected(images, angles, run, reference, sees_polarization)
    polarization = _maps(images, angles, used) if maps else None
    reference_deg, warnings = inspection.reference_deg, inspection.warnings
    staging = scene.new_staging()
    try:
        with concurrent.futures.ThreadPoolExecutor(max_workers=1) as pool:     # beside the writing (GIL released)
            measured = pool.submit(truth_metrics, scene, r_hat, t_hat, images, angles)
            paths = write_results(staging, r_hat, t_hat, overwrite=False, confidence=inspection.presence_at(r_hat.shape[:2]),
                                  clipped=inspection.clipped,
                                  reference_field=_field_image(used, inspection) if sees_polarization else None)
            metrics_truth = measured.result()
        del images                                        # the largest array
        staged = {f"results/{method}/{p.name}": p for p in paths}
        if polarization is not None:
            staged |= {f"results/{method}/maps/{p.name}": p for p in write_maps(staging / "maps", polarization)}
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    kind = _reference_kind(reference, used, sees_polarization)
    entry = {"angles_deg": angles, **info, "full_scale": FULL_SCALE, "reference_deg": round(reference_deg, 3),
             "reference": kind, "warnings": warnings, "truth_metrics": metrics_truth}
    return Prepared(scene.path, method, staging, staged, entry, Separation([], reference_deg, warnings, metrics_truth, kind))


def _check_results_folder(scene: Scene, method: str) -> None:
    """DatasetError, before any work, when the scene holds a symbolic link (`Scene.refuse_links`)
    or a file stands where its results folders must be."""
    scene.refuse_links()
    for folder in (scene.path / "results", scene.results_dir(method)):
        if folder.exists() and not folder.is_dir():
            raise DatasetError(f"{folder} is a file, not a folder; {scene.name}'s {method} results go there: move it "
                               "away and run the command again")


def commit_scene(prepared: Prepared, force: bool = False) -> Separation:
    """Record a prepared separation in its scene's manifest (the caller holds the dataset's
    lock); earlier results of the method are replaced only with ``force``. The staging folder
    is removed either way."""
    scene = Scene(prepared.scene)
    try:
        result = scene.add_result(prepared.method, prepared.staged, prepared.entry, replace=force)
    finally:
        shutil.rmtree(prepared.staging, ignore_errors=True)
    return dataclasses.replace(prepared.separation, files=list(result.files.values()))


def separate_scene(scene: Scene, method: str, run, info: dict, force: bool = False,
                   reference: str | float = "auto", maps: bool = False) -> Separation:
    """Separate an ingested scene with ``run`` (from `separate.methods.get_method`) and record
    the results in its manifest; earlier results of the method are replaced only with
    ``force``, and only once the new ones are complete; with ``maps`` the polarization maps too
    (module docstring)."""
    with scene.lock():
        scene.reload()
        if not force:
            scene.check_no_results(method)
        separation = commit_scene(prepare_scene(scene, method, run, info, reference, maps), force)
        scene.reload()                                          # commit_scene wrote through its own Scene
    return separation


def add_maps(scene: Scene, method: str, reference: str | float = "auto") -> Separation:
    """Add the polarization maps to a scene's stored results of ``method`` without separating
    again: a Stokes fit of the aligned stack, presented at the reference the separation used
    (its ``reference_deg.tiff``; for a method that sees S0 only, ``reference`` estimated without
    a trial separation). The maps are staged inside the scene and recorded with their hashes.
    DatasetError when the results are missing or already hold maps."""
    with scene.lock():
        scene.reload()
        result = scene.result(method)
        if any(path.parent.name == "maps" for path in result.files.values()):
            raise DatasetError(f"{scene.name}'s {method} results already have maps ({scene.results_dir(method) / 'maps'}); "
                               "pass --force to separate again with maps")
        field_file = result.files.get("reference_deg.tiff")
        used = None if field_file is None else read_result(field_file)      # checked before the stack is read
        images, angles = scene.load_stack(codes=True)
        if used is None:
            inspection, chosen = resolve_reference(images, angles, reference, None)
            used = inspection.field if np.ndim(chosen) == 2 else chosen
        polarization = _maps(images, angles, used)
        del images
        with scene.staging() as staging:
            staged = {f"results/{method}/maps/{p.name}": p for p in write_maps(staging / "maps", polarization)}
            stored = scene.add_result_files(method, staged, f"maps of {method}")
        scene.reload()
    files = [path for path in stored.files.values() if path.parent.name == "maps"]
    return Separation(files, result.reference_deg or 0.0, [], None)


def describe_incidence(incidence: dict) -> str:
    """A line on the angle-of-incidence estimate (`separate.incidence.Incidence.record`) and
    whether the physics-anchored network used it."""
    lo, hi = incidence["range_deg"]
    if incidence.get("given"):
        return f"angle of incidence {incidence['median_deg']:g} deg (given; the network's Fresnel gate on)"
    if incidence["gate"]:
        return (f"angle of incidence {incidence['median_deg']:.0f} deg ({lo:.0f}-{hi:.0f} across the frame; "
                "estimated, the network's Fresnel gate on)")
    return (f"angle of incidence not clear from the shots (clarity {incidence['clarity']:.2f}, sharpness "
            f"{incidence['sharpness']:.3f}): the network ran without its Fresnel gate")


def _maps(images: np.ndarray, angles: list[float], used: float | np.ndarray) -> dict[str, np.ndarray]:
    from separate.maps import polarization_maps

    return polarization_maps(images, angles, used)


def _field_image(used: float | np.ndarray, inspection: Inspection) -> np.ndarray:
    """The reference used, as a map on the reduced grid (deg)."""
    return used if np.ndim(used) == 2 else np.full(inspection.field.shape, float(used), np.float32)


#: `Separation.reference_kind` of a separation presented at a per-pixel reference field.
FIELD_KIND = "estimated per pixel, a field"


def _reference_kind(reference: str | float, used: float | np.ndarray, sees_polarization: bool) -> str:
    """How the reference was chosen (``reference``: "auto", "global" or deg) and what was used
    (a field or an angle), for the manifest and the CLI; "not used" by a method that sees S0 only."""
    if not sees_polarization:
        return "not used"
    if not isinstance(reference, str):
        return "given"
    if np.ndim(used) == 2:
        return FIELD_KIND
    if reference == "auto":
        return "estimated, one angle: the polarization is weak and of one orientation, too little for a field"
    return "estimated, one angle"


#: The smallest image side `separate_images` takes (px): the reference field needs gradients.
MIN_SIDE_PX = 2


def check_out_folder(out: Path, method: str = "METHOD") -> None:
    """DatasetError when ``out`` lies inside an urd dataset: a scene's results are recorded by its
    manifest (`separate_scene`), so the message names the dataset and the command to run."""
    root = enclosing_dataset(out)
    if root is None:
        return
    parts = Path(out).resolve().relative_to(root).parts
    scene = parts[0] if parts and SCENE_NAME.match(parts[0]) else "SCENE"
    raise DatasetError(f"{out} is inside the dataset {root}, whose scenes' results only their manifests record; "
                       f"to separate a scene of it again run 'urd separate {scene} --dataset {root} --method {method} "
                       "--force', or pass an --out outside the dataset")


def separate_images(paths: list[Path], angles_deg: list[float], out: Path, run, transfer: Transfer = Transfer.LINEAR,
                    force: bool = False, reference: str | float = "auto", maps: bool = False,
                    sees_polarization: bool = True) -> Separation:
    """Separate image files (one per angle) into ``out``; existing results only with ``force``;
    with ``maps`` the polarization maps too (``out/maps/``); the reference used is written
    (``reference_deg.tiff``) only for a method that ``sees_polarization``."""
    if len(paths) != len(angles_deg):
        raise ValueError(f"expected one angle per image ({len(paths)} images), got {len(angles_deg)} angles")
    check_out_folder(Path(out))
    check_no_results_in(Path(out), force)
    made = not Path(out).exists()
    check_writable(Path(out))
    try:
        return _separate_into(paths, angles_deg, Path(out), run, transfer, reference, maps, sees_polarization)
    except BaseException:
        if made:
            with contextlib.suppress(OSError):
                Path(out).rmdir()                         # the folder this run made, when nothing is in it
        raise


def _separate_into(paths: list[Path], angles_deg: list[float], out: Path, run, transfer: Transfer,
                   reference: str | float, maps: bool, sees_polarization: bool) -> Separation:
    """The work of `separate_images` once ``out`` is checked: the results written into a
    staging folder inside ``out``, then moved into place."""
    codes = [read_raw_codes(p) for p in paths]
    grey = [Path(p).name for p, c in zip(paths, codes) if c.ndim == 2]
    if 0 < len(grey) < len(paths):
        colour = [Path(p).name for p, c in zip(paths, codes) if c.ndim == 3]
        raise ValueError(f"expected shots that are all grey or all colour, got grey {', '.join(grey)} and colour "
                         f"{', '.join(colour)}")
    loaded = [linear_image(codes.pop(0), p, transfer) for p in paths]
    turned = {Path(p).name: ORIENTATIONS[o] for p in paths if (o := exif_orientation(p)) in ORIENTATIONS}
    if len({im.shape for im in loaded}) > 1:
        sizes = ", ".join(f"{Path(p).name} {im.shape[1]}×{im.shape[0]}" for p, im in zip(paths, loaded))
        stored = f" (as stored; viewers show {', '.join(f'{n} {how}' for n, how in turned.items())} by its EXIF orientation)" if turned else ""
        raise ValueError(f"expected images of one size, got {sizes}{stored}")
    for i in range(len(loaded)):
        for j in range(i + 1, len(loaded)):
            if np.array_equal(loaded[i], loaded[j]):
                raise ValueError(f"{Path(paths[i]).name} and {Path(paths[j]).name} hold the same image: each polarizer "
                                 "angle needs its own shot")
    height, width = loaded[0].shape[:2]
    if min(height, width) < MIN_SIDE_PX:
        raise ValueError(f"expected images of at least {MIN_SIDE_PX}×{MIN_SIDE_PX} pixels, got {width}×{height}")
    stack = np.stack(loaded)
    del loaded
    r_hat, t_hat, inspection, used = separate_inspected(stack, angles_deg, run, reference, sees_polarization)
    polarization = _maps(stack, angles_deg, used) if maps else None
    del stack
    staging = Path(tempfile.mkdtemp(prefix=".urd-staging-", dir=out))   # a failed run leaves the folder as it was
    try:
        staged = write_results(staging, r_hat, t_hat, overwrite=False, confidence=inspection.presence_at(r_hat.shape[:2]),
                               clipped=inspection.clipped,
                               reference_field=_field_image(used, inspection) if sees_polarization else None)
        if polarization is not None:
            staged += write_maps(staging / "maps", polarization)
        paths = []
        for path in staged:
            final = out / path.relative_to(staging)
            final.parent.mkdir(exist_ok=True)
            os.replace(path, final)
            paths.append(final)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    _remove_replaced(out, paths)
    notes = []
    for how in dict.fromkeys(turned.values()):
        names = [name for name, turn in turned.items() if turn == how]
        notes.append(f"{', '.join(names)}: EXIF asks viewers to show {'it' if len(names) == 1 else 'them'} {how}; urd reads "
                     "the pixels as stored (the frame the polarizer angles are measured in) and writes the results so")
    return Separation(paths, inspection.reference_deg, notes + inspection.warnings,
                      reference_kind=_reference_kind(reference, used, sees_polarization))


def check_no_results_in(out: Path, force: bool = False) -> None:
    """DatasetError, before any work, when the folder ``out`` holds results of an earlier run of
    separating image files and not ``force``."""
    existing = sorted(p.name for p in out.glob("*") if p.name in RESULT_NAMES or p.name == "maps") \
        if out.is_dir() and not force else []
    if existing:
        raise DatasetError(f"{out} already holds results ({', '.join(existing)}); pass --force to replace them, "
                           "or another --out")


def check_writable(folder: Path) -> None:
    """Make ``folder`` (and its parents) if needed and check that a file can be written into it,
    before any work; DatasetError naming the folder and what to do when not."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise DatasetError(f"cannot write into the output folder {folder} ({exc.strerror or exc}); nothing was "
                           "separated. Choose another --out, or make this one writable") from exc


def _remove_replaced(out: Path, written: list[Path]) -> None:
    """Remove the result files of an earlier run in ``out`` that this run (--force) did not write
    again (a reference map, polarization maps), so that the folder holds one run's results."""
    from separate.maps import MAPS

    earlier = [out / name for name in RESULT_NAMES] + [out / "maps" / f"{name}.tiff" for name in MAPS]
    for path in earlier:
        if path not in written and path.is_file():
            path.unlink()
    with contextlib.suppress(OSError):
        (out / "maps").rmdir()                             # only when empty
