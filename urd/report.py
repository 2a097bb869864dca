"""Dataset reports: a text summary for terminals, integrity checks (``urd verify``), and the
data behind the HTML report (`urd.report_html`)."""

from __future__ import annotations

import shlex
from collections.abc import Sequence
from pathlib import Path

from urd.core.dataset import SCENE_MANIFEST, Dataset, OffsetCalibration, Scene
from urd.core.errors import DatasetError, ManifestError, UrdError
from urd.core.progress import plural


def report_text(root: Path) -> str:
    """One line per scene (state, angles, calibration, results); broken scenes say why, and so do
    scenes with missing files, a lost ground truth, an unfinished swap or shots taken with another
    polarizer offset than the dataset's calibration; folders holding a scene
    manifest under another name than a scene's are named."""
    ds = Dataset.open(root)
    try:
        calibration = ds.calibration()
        offset = (f"{calibration.offset_deg:.3f} ± {calibration.uncertainty_deg:.3f} deg" if calibration
                  else "not calibrated")
    except (ManifestError, OSError) as exc:        # the scenes are still worth listing
        calibration, offset = None, f"unreadable ({exc})"
    scenes = ds.scenes()
    lines = [f"dataset {ds.root.resolve()}: {plural(len(scenes), 'scene')}; polarizer offset {offset}"]
    for scene in scenes:
        status = scene.status()
        lines.append(f"  {status.describe()}")
        missing = [] if status.state == "broken" else scene.missing_files()
        if missing:
            lines.append(f"    {plural(len(missing), 'listed file')} missing or of another size ({', '.join(missing[:3])}"
                         f"{', …' if len(missing) > 3 else ''}): run urd verify {ds.root}")
        if status.state == "incomplete":
            from acquire.plan import resume_command

            lines.append(f"    resume it with: {resume_command(ds.root, scene)}")
        if status.state != "broken":
            lines += [f"    {note}" for note in (_link_note(scene), scene.lost_truth(), scene.unfinished_swap(),
                                                 _offset_note(scene, calibration)) if note]
        lines += [f"    {line}" for line in _truth_lines(scene)]
    lines += [f"  {name}: {message}" for name, message in ds.misnamed_scenes().items()]
    return "\n".join(lines)


def _link_note(scene: Scene) -> str | None:
    """The symbolic link in ``scene`` (`Scene.refuse_links`), which no command works through, or None."""
    try:
        scene.refuse_links()
    except DatasetError as exc:
        return str(exc)
    return None


def _truth_lines(scene) -> list[str]:
    """One line per result with ground-truth figures: PSNR and SSIM of T̂ and R̂."""
    from urd.report_html import truth_summary

    if scene.status().state == "broken":
        return []
    truths = {method: scene.result(method, verify=False).truth_metrics for method in scene.methods()}
    return [f"{method} vs ground truth: {truth_summary(truth)}" for method, truth in truths.items() if truth]


def verify(root: Path) -> dict[str, list[str]]:
    """Problems per scene (missing or changed files, unreadable manifests), of
    the calibration under the key "calibration" where the dataset has one, and of each folder
    holding a scene manifest under another name than a scene's (`Dataset.misnamed_scenes`);
    empty when intact. ``root`` may also be one scene's folder: then that scene alone."""
    if (Path(root) / SCENE_MANIFEST).is_file():
        scene = Scene(Path(root))
        return {scene.name: scene.verify()}
    ds = Dataset.open(root)
    problems = {scene.name: scene.verify() for scene in ds.scenes()}
    if ds.calibration_path.exists() or ds.sweeps():
        problems["calibration"] = ds.verify_calibration()
    for name, message in ds.misnamed_scenes().items():
        problems.setdefault(name, []).append(message)
    return problems


def _shrink(image, max_side: int):
    """Downscale an H×W×C image so its long side is at most ``max_side`` (area average)."""
    import cv2

    scale = max_side / max(image.shape[:2])
    return image if scale >= 1 else cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)


def _px(size: tuple[int, int]) -> str:
    """An image size (H, W) as "W×H px"."""
    return f"{size[1]}×{size[0]} px"


def _offset_note(scene: Scene, calibration: OffsetCalibration | None) -> str | None:
    """A note when ``scene`` was captured on the stage of the dataset's ``calibration`` with another
    polarizer offset (by more than its uncertainty, or with none recorded), else None; a scene
    captured on another stage, or ingested from RAW files, has the angles it was given."""
    from acquire.rig import calibration_owner, stage_identity

    capture = scene.load(verify=False).get("capture", {})
    if calibration is None or "stage" not in capture:
        return None
    owner = calibration_owner(calibration)
    if owner is not None and stage_identity(capture["stage"]) != owner:
        return None                                   # another stage: the dataset's calibration is not its offset
    taken = capture.get("offset_deg")
    if taken is not None and abs(float(taken) - calibration.offset_deg) <= calibration.uncertainty_deg:
        return None
    how = "with no polarizer offset recorded (0°)" if taken is None else f"with the polarizer offset {float(taken):.3f}°"
    difference = calibration.offset_deg - float(taken or 0.0)
    return (f"its shots were taken {how} while the dataset's calibration says {calibration.offset_deg:.3f}° "
            f"± {calibration.uncertainty_deg:.3f}°, so its angles are off by {difference:+.3f}°")


def _next_step(scene: Scene, state: str) -> str:
    """The command that continues a scene whose capture is unfinished or not ingested, else ""."""
    from acquire.plan import resume_command

    if state == "incomplete":
        return resume_command(scene.path.parent, scene)
    if state == "captured":
        return shlex.join(["urd", "ingest", str(scene.path.parent.resolve())])
    return ""


def scene_view(scene, max_side: int = 2048, calibration: OffsetCalibration | None = None):
    """What the HTML report shows of one scene (`urd.report_html.SceneView`), images at most
    ``max_side`` px long. Shots or results that cannot be read, and results of another size than
    the shots (or than the first result shown), are left out with a note saying why; a scene
    captured with another polarizer offset than the dataset's ``calibration`` gets a note. A scene
    holding a symbolic link (its folder one, or a file or folder in it) is shown as broken, naming
    the link: a dataset from someone else could show files from anywhere through it."""
    from urd.core.images import u16_to_linear
    from urd.report_html import ResultView, SceneView
    from urd.separation import read_result

    status = scene.status()
    notes = [status.problem] if status.problem else []
    if status.state == "broken":
        return SceneView(scene.name, status.describe(), [], None, None, [], notes, state="broken")
    link = _link_note(scene)
    if link is not None:
        return SceneView(scene.name, "BROKEN (a symbolic link)", [], None, None, [], [f"not shown: {link}"], state="broken")
    offset_note = _offset_note(scene, calibration)
    if offset_note:
        notes.append(offset_note)
    shots, reference, results, size = [], None, [], None
    if status.state == "ingested":
        try:
            stack, angles = scene.load_stack()
        except (OSError, ValueError) as exc:
            notes.append(f"shots not shown: {exc}")
        else:
            shots, size = [(angle, _shrink(image, max_side)) for angle, image in zip(angles, stack)], stack.shape[1:3]
            del stack
    for method in scene.methods():
        try:
            result = scene.result(method)
            r, t = (u16_to_linear(read_result(result.files[f"{name}.tiff"]), result.full_scale) for name in ("R", "T"))
            confidence, field = (None if path is None else read_result(path)
                                 for path in (result.files.get(name) for name in ("confidence.tiff", "reference_deg.tiff")))
        except (OSError, ValueError) as exc:
            notes.append(f"{method}: {exc}")
            continue
        size = size or r.shape[:2]
        odd = next((image.shape[:2] for image in (r, t, confidence) if image is not None and image.shape[:2] != size), None)
        if odd is not None:
            notes.append(f"{method}: not shown: its results are {_px(odd)}, the {'shots' if shots else 'results shown'} "
                         f"{_px(size)}; separate it again: urd separate {scene.name} --dataset {scene.path.parent} "
                         f"--method {method} --force")
            continue
        r, t = (_shrink(image, max_side) for image in (r, t))
        confidence = None if confidence is None else _shrink(confidence, max_side)
        reference = result.reference_deg if result.reference_deg is not None else reference
        notes += [f"{method}: {w}" for w in result.warnings]
        exports = [path.resolve() for path in result.files.values() if path.parent.name == "maps"]
        results.append(ResultView(method, r, t, result.description, confidence, field, result.truth_metrics, exports))
    state = "separated" if results else status.state
    return SceneView(scene.name, status.describe().split(": ", 1)[1], shots, reference, scene.shot_errors_deg(),
                     results, notes, state, list(status.angles_deg), _next_step(scene, status.state))


def calibration_view(ds):
    """The Malus-law sweep behind the dataset's offset calibration (`urd.report_html.CalibrationView`),
    None when there is none; an unreadable calibration or sweep gives a view with a note saying why."""
    import numpy as np

    from calib.polarizer import malus_fit
    from calib.store import sweep_intensities
    from separate.optics import stokes_matrix
    from urd.core.dataset import Scene
    from urd.report_html import CalibrationView

    try:
        calibration = ds.calibration()
    except (ManifestError, OSError) as exc:
        return CalibrationView([], [], [], [], None, None, notes=[f"the calibration cannot be read: {exc}"])
    if calibration is None or calibration.sweep is None:
        return None
    try:
        angles, values = sweep_intensities(Scene(calibration.sweep))
        stokes, rms, _ = malus_fit(angles, values)
    except (UrdError, OSError, ValueError) as exc:
        return CalibrationView([], [], [], [], calibration.offset_deg, calibration.uncertainty_deg,
                               notes=[f"the sweep {calibration.sweep} cannot be shown: {exc}"])
    grid = np.arange(0.0, 180.5, 1.0)
    return CalibrationView(angles, values, grid.tolist(), (stokes_matrix(np.radians(grid)) @ stokes).tolist(),
                           calibration.offset_deg, calibration.uncertainty_deg, rms)


def report_html(root, out, overwrite: bool = False, progress=None):
    """Write the static HTML report of the dataset at ``root`` into ``out``; returns index.html.
    Damaged scenes and calibrations are shown with a note saying what is wrong."""
    from urd.report_html import check_report_folder, write_html_report

    ds = Dataset.open(root)
    check_report_folder(out, overwrite)              # before the scenes are read, which takes a while
    try:
        calibration = ds.calibration()
    except (ManifestError, OSError):                 # `calibration_view` says why
        calibration = None
    return write_html_report(SceneViews(ds.scenes(), calibration), out, f"urd dataset {ds.root.resolve().name}",
                             calibration_view(ds), overwrite=overwrite,
                             progress=progress and (lambda d, t: progress(d, t, "report: writing scenes")))


class SceneViews(Sequence):
    """The `scene_view` of each scene, made when asked for (the HTML report writes one scene's
    images at a time and lets them go, so its memory does not grow with the dataset)."""

    def __init__(self, scenes: list[Scene], calibration: OffsetCalibration | None):
        self.scenes, self.calibration = scenes, calibration

    def __len__(self) -> int:
        return len(self.scenes)

    def __getitem__(self, index: int):
        return scene_view(self.scenes[index], calibration=self.calibration)
