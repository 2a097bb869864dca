"""Ingest: RAW decoding, grouping, ECC alignment accuracy, failure handling."""

import os
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest

from acquire.virtual_camera import make_glass_scene
from conftest import shared_data
from rig import capture_virtual
from urd.core import raw as rawio
from urd.core.dataset import Dataset
from urd.core.errors import RawFormatError
from urd.core.align import Motion
from urd.ingest import IngestOptions, counter_wraps, group_shots, ingest_folder, ingest_scene


def urd(*args):
    return subprocess.run([sys.executable, "-m", "urd.cli", *map(str, args)], capture_output=True, text=True, timeout=600)


def warp_rms(estimate, truth, h, w):
    ys, xs = np.mgrid[0:h:16, 0:w:16]
    pts = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
    return float(np.sqrt(((np.asarray(estimate)[:2] @ pts - np.asarray(truth)[:2] @ pts) ** 2).sum(0).mean()))


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2])
def test_alignment_recovers_known_shake_within_a_tenth_of_a_pixel(tmp_path, seed):
    ds = Dataset.open_or_create(tmp_path / "ds")
    scene, cam = capture_virtual(ds, angles=(0, 45, 90, 135), size=(1024, 768), shake_px=8, shake_deg=1.0, seed=seed)
    outcome = ingest_scene(scene, IngestOptions())
    assert outcome.error is None
    record = scene.load()
    for entry in record["ingest"]["alignment"][1:]:
        truth = cam.shake(entry["shot"])
        assert np.abs(truth[:, 2]).max() > 1.0 or entry["shot"] == 0     # the shake is real
        assert warp_rms(entry["warp"], truth, 768, 1024) < 0.1, entry
    stack, angles = scene.reload().load_stack()
    assert stack.shape == (4, 768, 1024, 3) and stack.dtype == np.float32 and scene.stage_angles_deg() == [0.0, 45.0, 90.0, 135.0]
    np.testing.assert_allclose(angles, [cam.scene_angle_deg(a, i) for i, a in enumerate((0, 45, 90, 135))], atol=0.01)
    codes, _ = scene.load_stack(codes=True)                     # the stored 16-bit codes, 65535 = 1.0
    assert codes.dtype == np.uint16
    np.testing.assert_allclose(codes / np.float32(65535.0), stack, rtol=1e-6)
    # aligned shots agree with the noiseless rendering in the reference frame (away from borders):
    # the reference shot's rendering at the polarizer's angle in the scene's frame, the stack's angle
    for i, angle in enumerate(angles):
        err = np.abs(stack[i] - cam.render(angle, 0))[40:-40, 40:-40].mean()
        assert err < 0.02, (i, err)


def test_the_aligned_stacks_angles_turn_with_the_camera_as_the_polarizer_in_front_of_its_lens(tmp_path):
    from acquire.virtual_camera import shot_truth

    ds = Dataset.open_or_create(tmp_path / "ds")
    scene, cam = capture_virtual(ds, angles=(0, 45, 90), size=(320, 240), shake_px=3, shake_deg=4.0, seed=3)
    assert ingest_scene(scene, IngestOptions()).error is None
    truth = [shot_truth(path)["scene_angle_deg"] for path in scene.raw_paths()]
    turns = [cam.scene_angle_deg(0.0, i) for i in range(3)]
    assert max(abs(t) for t in turns) > 1.0                                   # the camera turned
    stack, angles = scene.reload().load_stack()
    assert scene.stage_angles_deg() == [0.0, 45.0, 90.0]
    np.testing.assert_allclose(angles, truth, atol=0.02)                      # not the stage's: off by the turns
    assert scene.load()["ingest"]["angles_deg"] == angles


def test_glints_clipped_in_the_shot_alone_are_masked_and_the_shot_still_aligns(tmp_path):
    from urd.core.align import align, prepare_target

    ds = Dataset.open_or_create(tmp_path / "ds")
    scene, cam = capture_virtual(ds, angles=(0, 45, 90), size=(640, 480), shake_px=4, shake_deg=0.5, seed=7)
    reference, shot = (rawio.decode(path) for path in scene.raw_paths()[:2])
    rng = np.random.default_rng(0)
    for y, x in zip(rng.integers(20, 440, 60), rng.integers(20, 600, 60)):   # glare the polarizer let through here only
        shot[y:y + 18, x:x + 18] = 1.0
    result = align(prepare_target(reference), shot)
    assert result.ok and result.correlation > 0.7, result                   # unmasked: 0.51, 0.20 px off
    assert warp_rms(result.warp, cam.shake(1), 480, 640) < 0.15


@pytest.mark.slow
def test_unalignable_scene_is_flagged_and_no_stack_is_written(tmp_path):
    ds = Dataset.open_or_create(tmp_path / "ds")
    scene, _ = capture_virtual(ds, size=(512, 384), seed=3)
    other_glass = make_glass_scene(512, 384, reflection=None, transmission=None, theta_center_deg=30)
    other_glass.transmission = np.ascontiguousarray(other_glass.reflection[::-1, ::-1])
    other_glass.reflection = np.ascontiguousarray(other_glass.reflection[:, ::-1] * 0.1)
    other, _ = capture_virtual(ds, size=(512, 384), seed=4, glass=other_glass)
    # replace shot 2 of the first scene by a shot of another scene (and fix up the manifest hash)
    record = scene.load()
    src = other.path / other.load()["shots"][2]["file"]
    dst = scene.path / record["shots"][2]["file"]
    shutil.copyfile(src, dst)
    from urd.core.files import write_json_atomic
    record["shots"][2].update(scene.file_record(dst))
    write_json_atomic(scene.manifest_path, record)
    out = urd("ingest", scene.path)
    assert out.returncode == 1 and "alignment failed" in out.stderr
    assert not (scene.path / "aligned").exists()
    assert scene.load()["ingest"]["ok"] is False
    again = urd("ingest", scene.path)                      # not "already ingested": what failed, and the way out
    assert again.returncode == 0 and "its alignment failed" in again.stdout and "--redo tries again" in again.stdout


def test_ingest_folder_groups_by_time_and_reports_bad_files(tmp_path, monkeypatch):
    ds = Dataset.open_or_create(tmp_path / "cap")
    scenes = [capture_virtual(ds, size=(256, 192), seed=s)[0] for s in (5, 6, 7, 8, 9)]
    raw_dir = tmp_path / "raw"
    raw_dir.mkdir()
    for k, scene in enumerate(scenes):
        for i, shot in enumerate(scene.load()["shots"]):
            shutil.copyfile(scene.path / shot["file"], raw_dir / f"IMG_{k}{i}.dng")
    # scene 1: truncated file; scene 2: a text file named .dng; scene 3: one shot missing
    data = (raw_dir / "IMG_11.dng").read_bytes()
    (raw_dir / "IMG_11.dng").write_bytes(data[: len(data) // 3])
    (raw_dir / "IMG_21.dng").write_text("not a raw file")
    (raw_dir / "IMG_32.dng").unlink()
    (raw_dir / "notes.txt").write_text("sidecar")
    t0 = time.time() - 10000
    for path in raw_dir.glob("IMG_*.dng"):
        k, i = int(path.stem[4]), int(path.stem[5])
        os.utime(path, (t0 + 1000 * k + i, t0 + 1000 * k + i))
    opts = IngestOptions(gap_s=100)
    from urd import ingest as ingest_mod
    monkeypatch.setattr(ingest_mod, "capture_time", lambda p, meta: p.stat().st_mtime)  # the staged times
    report = ingest_folder(raw_dir, Dataset.open_or_create(tmp_path / "ds"), opts)
    outcomes, ignored = report.outcomes, report.ignored
    assert ignored == [raw_dir / "notes.txt"]
    good = [o for o in outcomes if o.error is None]
    errors = {o.files[0].name[:5]: o.error for o in outcomes if o.error}
    assert len(good) == 2 and Dataset.open(tmp_path / "ds").scene_names() == ["scene_01", "scene_02"]
    assert "IMG_11.dng" in errors["IMG_1"] and "truncated" in errors["IMG_1"]
    assert "IMG_21.dng" in errors["IMG_2"] and "not a RAW file" in errors["IMG_2"]
    assert "wrong shot count" in errors["IMG_3"]
    assert not [p for p in (tmp_path / "ds").iterdir() if p.name.startswith(".")]


@pytest.mark.slow
def test_mixed_sizes_and_missing_folder(tmp_path):
    ds = Dataset.open_or_create(tmp_path / "cap")
    a, _ = capture_virtual(ds, size=(256, 192), seed=1)
    b, _ = capture_virtual(ds, size=(320, 192), seed=2)
    raw_dir = tmp_path / "raw"
    raw_dir.mkdir()
    files = [a.path / s["file"] for s in a.load()["shots"][:2]] + [b.path / b.load()["shots"][2]["file"]]
    for i, f in enumerate(files):
        shutil.copyfile(f, raw_dir / f"x{i}.dng")
    out = urd("ingest", raw_dir, tmp_path / "ds")
    assert out.returncode == 1 and "FAILED x0.dng, x1.dng, x2.dng: x2.dng: size 320×192 differs" in out.stderr
    assert ".staging-" not in out.stderr and "another camera or setting" in out.stderr
    out = urd("ingest", tmp_path / "nowhere", tmp_path / "ds")
    assert out.returncode == 2 and "no such folder" in out.stderr


def test_real_camera_raws_decode_linear_and_the_scanner_is_rejected():
    canon = shared_data("raw", "canon_eos550d_magiclantern_colorchart.dng")
    img = rawio.decode(canon)
    assert img.shape == (1156, 1734, 3) and img.dtype == np.float32
    assert -0.1 < img.min() and img.max() < 2.0 and 0.01 < img.mean() < 0.5     # linear, not clipped
    import rawpy
    with rawpy.imread(str(canon)) as raw:      # LibRaw's linear rendering has the same colour balance
        ref = raw.postprocess(gamma=(1, 1), no_auto_bright=True, use_camera_wb=True, output_bps=16) / 65535.0
    ours, theirs = img.mean(axis=(0, 1)), ref.mean(axis=(0, 1))
    np.testing.assert_allclose(ours / ours[1], theirs / theirs[1], rtol=0.03)
    half = rawio.decode(canon, half_size=True)
    assert half.shape == (578, 867, 3)
    assert abs(half.mean() - img.mean()) < 0.01          # same linear scale at half size
    meta = rawio.metadata(shared_data("raw", "kodak_dc50.kdc"))
    assert meta["model"].startswith("Kodak") and meta["exposure_s"] == pytest.approx(0.00435, rel=1e-3)
    assert meta["colour"].startswith("camera RGB") and rawio.metadata(canon)["colour"] == "linear sRGB"
    with pytest.raises(RawFormatError, match="not a colour-filter-array camera image"):
        rawio.decode(shared_data("raw", "nikon_coolscan_iv_scanner.nef"))


def test_virtual_dng_decodes_to_the_rendered_linear_scene(tmp_path):
    ds = Dataset.open_or_create(tmp_path / "ds")
    scene, cam = capture_virtual(ds, size=(256, 192), shake_px=0, shake_deg=0, seed=1)
    for shot in scene.load()["shots"]:
        img = rawio.decode(scene.path / shot["file"])
        expected = cam.render(shot["angle_commanded_deg"], shot["index"])
        np.testing.assert_allclose(img.mean(axis=(0, 1)), expected.mean(axis=(0, 1)), rtol=0.01)


def test_a_new_dataset_that_gets_no_scene_is_not_left_behind(tmp_path):
    from urd.ingest import ingest

    raw_dir = tmp_path / "raw"
    raw_dir.mkdir()
    for i in range(3):
        (raw_dir / f"IMG_{i}.dng").write_text("not a raw file")
    report = ingest(raw_dir, tmp_path / "new", IngestOptions())
    assert len(report.failed) == 1 and not (tmp_path / "new").exists()
    (tmp_path / "mine").mkdir()                                            # the user's folder stays, empty
    ingest(raw_dir, tmp_path / "mine", IngestOptions())
    assert (tmp_path / "mine").is_dir() and list((tmp_path / "mine").iterdir()) == []


def test_identical_files_are_not_a_scene(tmp_path):
    from urd.ingest import ingest

    ds = Dataset.open_or_create(tmp_path / "cap")
    scene, _ = capture_virtual(ds, size=(96, 64), seed=1)
    raw_dir = tmp_path / "raw"
    raw_dir.mkdir()
    shot = scene.path / scene.load()["shots"][0]["file"]
    for i in range(3):
        shutil.copyfile(shot, raw_dir / f"x{i}.dng")
    report = ingest(raw_dir, tmp_path / "ds", IngestOptions())
    assert [o.error for o in report.outcomes] == [
        "x0.dng and x1.dng are the same file (identical content): a scene needs one shot per polarizer angle"]
    assert not (tmp_path / "ds").exists()
    shutil.copyfile(shot, raw_dir / "x3.dng")                            # four shots for three angles: the count fails
    report = ingest(raw_dir, tmp_path / "ds", IngestOptions())
    assert [o.state for o in report.outcomes] == ["failed"]
    assert "is not a multiple of 3 angles" in report.outcomes[0].error
    assert "; x0.dng and x1.dng are the same file (identical content)" in report.outcomes[0].error


def test_shots_taken_together_split_into_several_scenes_are_pointed_out(tmp_path, monkeypatch):
    from urd import ingest as ingest_mod

    ds = Dataset.open_or_create(tmp_path / "cap")
    raw_dir = tmp_path / "raw"
    raw_dir.mkdir()
    for k in range(2):
        scene, _ = capture_virtual(ds, size=(96, 64), shake_px=0, shake_deg=0, seed=k)
        for i, shot in enumerate(scene.load()["shots"]):
            path = raw_dir / f"IMG_{3 * k + i}.dng"
            shutil.copyfile(scene.path / shot["file"], path)
            os.utime(path, (1e9 + 3 * k + i, 1e9 + 3 * k + i))           # six shots within seconds
    monkeypatch.setattr(ingest_mod, "capture_time", lambda p, meta: p.stat().st_mtime)
    report = ingest_mod.ingest(raw_dir, tmp_path / "ds", IngestOptions())
    assert [o.state for o in report.outcomes] == ["ingested", "ingested"]
    assert report.notes == ["6 shots taken together (IMG_0.dng … IMG_5.dng) became 2 scenes of 3 angles; if they are "
                            "one capture at 6 angles, move those scenes away and ingest the files again with --angles"]


@pytest.mark.slow
def test_shots_aligned_and_written_two_at_a_time_are_the_bytes_of_one_at_a_time(tmp_path, monkeypatch):
    import urd.ingest as ingest_module
    from urd.core.align import luminance

    image = np.random.default_rng(0).random((64, 96, 3), dtype=np.float32)
    assert np.array_equal(luminance(image), image.mean(axis=2))
    aligned = {}
    for threads in (1, 2):
        monkeypatch.setattr(ingest_module, "INGEST_THREADS", threads)
        ds = Dataset.open_or_create(tmp_path / f"threads{threads}")
        scene, _ = capture_virtual(ds, angles=(0, 45, 90, 135), size=(320, 240), shake_px=4, shake_deg=0.5, seed=7)
        ingest_scene(scene, IngestOptions())
        aligned[threads] = [p.read_bytes() for p in sorted((scene.path / "aligned").glob("*.tiff"))]
    assert len(aligned[1]) == 4 and aligned[1] == aligned[2]


def test_a_reference_prepared_once_aligns_every_shot_as_the_reference_itself_and_is_not_changed(tmp_path):
    from urd.core.align import align, prepare_target

    ds = Dataset.open_or_create(tmp_path / "ds")                 # 320×240: sizes OpenCV's DFT takes as they are,
    scene, _ = capture_virtual(ds, angles=(0, 45, 90, 135), size=(320, 240), shake_px=4, shake_deg=0.5, seed=7)
    shots = [rawio.decode(path) for path in scene.raw_paths()]   # where phaseCorrelate windows its inputs in place
    target = prepare_target(shots[0])
    kept = [(rep.copy(), mask.copy()) for rep, mask in target.pyramid]
    for shot in shots[1:]:
        assert align(target, shot).record() == align(shots[0], shot).record()
    assert all(np.array_equal(rep, a) and np.array_equal(mask, b) for (rep, mask), (a, b) in zip(target.pyramid, kept))


def test_a_counter_rolling_over_among_shots_of_one_second_is_named(tmp_path):
    files = []
    for name in ("IMG_9998.CR2", "IMG_9999.CR2", "IMG_0001.CR2"):         # not RAW: their times are the files'
        files.append(tmp_path / name)
        files[-1].write_bytes(b"x")
        os.utime(files[-1], (1_700_000_000, 1_700_000_000))
    groups, failures, notes = group_shots(files, {}, 3, 60.0)
    assert [[f.name for f in g] for g in groups] == [["IMG_0001.CR2", "IMG_9998.CR2", "IMG_9999.CR2"]] and not failures
    assert len(notes) == 1 and "these file numbers wrap around" in notes[0]
    os.utime(files[2], (1_700_000_002, 1_700_000_002))                  # the rolled-over shot a second later: no tie with it
    groups, _, notes = group_shots(files, {}, 3, 60.0)
    assert [f.name for f in groups[0]] == ["IMG_9998.CR2", "IMG_9999.CR2", "IMG_0001.CR2"] and notes == []
    assert counter_wraps(["IMG_9998.CR2", "IMG_9999.CR2", "IMG_0001.CR2"])
    assert not counter_wraps(["IMG_0041.CR2", "IMG_0042.CR2", "IMG_0043.CR2"])
    assert not counter_wraps(["shot_00_000.0deg.dng", "a.dng"]) and not counter_wraps(["DSC_1.NEF", "DSC_2.NEF"])


def test_an_interrupted_ingest_decodes_no_further_shot_and_leaves_no_staging(tmp_path, monkeypatch):
    import threading

    import urd.ingest as ingest_module

    ds = Dataset.open_or_create(tmp_path / "ds")
    scene, _ = capture_virtual(ds, angles=(0, 30, 60, 90, 120, 150), size=(96, 64), shake_px=0, shake_deg=0)
    first_two = {path.name for path in scene.raw_paths()[:2]}
    decoded, held, real_decode = [], threading.Event(), rawio.decode

    def decode(path, half_size=False):                        # shots 2.. wait, as a 24 MP decode takes seconds
        decoded.append(path.name)
        if path.name not in first_two:
            held.wait(60.0)
        return real_decode(path, half_size)

    def progress(done, total, label):
        if done == 1:
            raise KeyboardInterrupt                           # Ctrl-C, in the main thread, after the first shot

    real_shutdown = ingest_module.ThreadPoolExecutor.shutdown

    def shutdown(pool, wait=True, *, cancel_futures=False):   # the held decodes go on once the queue is cancelled
        real_shutdown(pool, wait=False, cancel_futures=cancel_futures)
        held.set()
        real_shutdown(pool, wait=wait)

    monkeypatch.setattr(ingest_module.rawio, "decode", decode)
    monkeypatch.setattr(ingest_module.ThreadPoolExecutor, "shutdown", shutdown)
    with pytest.raises(KeyboardInterrupt):
        ingest_module.prepare_ingest(scene, IngestOptions(), progress)
    never = {path.name for path in scene.raw_paths()[4:]}    # two threads: at most shots 2 and 3 had begun
    assert first_two <= set(decoded) and not never & set(decoded), decoded
    assert not list(scene.path.glob(".staging-*"))


def test_shots_of_one_second_are_ordered_by_their_file_numbers_as_numbers(tmp_path):
    files = []
    for name in ("frame_10.raw", "frame_11.raw", "frame_8.raw", "frame_9.raw"):   # not RAW: their times are the files'
        files.append(tmp_path / name.replace(".raw", ".dng"))
        files[-1].write_bytes(b"x")
        os.utime(files[-1], (1_700_000_000, 1_700_000_000))
    groups, failures, notes = group_shots(files, {}, 4, 60.0)
    assert [[f.name for f in g] for g in groups] == [["frame_8.dng", "frame_9.dng", "frame_10.dng", "frame_11.dng"]]
    assert not failures and not notes


def test_a_scene_failing_with_an_os_error_is_reported_and_the_next_is_ingested(tmp_path, monkeypatch):
    """One scene's failure outside urd's own errors (EIO of a network share while it is read)
    fails that scene, named, as with --jobs; the scenes after it are still ingested."""
    import urd.ingest as ingest_module

    ds = Dataset.open_or_create(tmp_path / "ds")
    first, _ = capture_virtual(ds, size=(96, 64), shake_px=1.0, shake_deg=0.1, seed=1)
    second, _ = capture_virtual(ds, size=(96, 64), shake_px=1.0, shake_deg=0.1, seed=2)
    process = ingest_module.process_scene

    def flaky(scene, *args, **kwargs):
        if scene.name == first.name:
            raise OSError(5, "Input/output error", str(scene.path / "raw"))
        return process(scene, *args, **kwargs)

    monkeypatch.setattr(ingest_module, "process_scene", flaky)
    report = ingest_module.ingest(ds.root, ds.root, IngestOptions())
    states = {o.name: (o.state, o.error) for o in report.outcomes}
    assert states[first.name][0] == "failed" and states[first.name][1].startswith("OSError: [Errno 5] Input/output error")
    assert states[second.name] == ("ingested", None)


def test_a_redo_says_which_results_went_stale_and_that_the_shot_calibration_was_removed(tmp_path):
    from calib.polarizer import ShotErrors
    from rig import separated_virtual_scene

    scene = separated_virtual_scene(Dataset.open_or_create(tmp_path / "ds"))
    record = ShotErrors([0.1, -0.2, 0.1], [0.05, 0.05, 0.05], 400, 4, None).record()
    scene.set_shot_calibration(record, [0.1, 44.8, 90.1])
    again = ingest_scene(scene.reload(), IngestOptions(redo=True))            # the same aligned files: nothing to renew
    assert again.state == "ingested" and again.notes == [] and scene.reload().status().calibrated
    assert scene.stale_reason("none") is not None                             # separated before the calibration
    outcome = ingest_scene(scene.reload(), IngestOptions(redo=True, motion=Motion.TRANSLATION))
    assert outcome.state == "ingested", outcome
    said = " ".join(outcome.notes)
    assert "results of none are stale" in said and f"urd separate scene_01 --dataset {scene.path.parent} --method none --force" in said
    assert "per-shot angle calibration was of the earlier alignment and is removed" in said
    assert "earlier alignment" in scene.reload().stale_reason("none")
    assert ingest_scene(scene, IngestOptions(redo=True)).notes == [
        f"scene_01: results of none are stale (of the earlier alignment); renew them with: urd separate scene_01 "
        f"--dataset {scene.path.parent} --method none --force"]


def test_urds_own_shots_named_with_other_angles_than_the_default_are_refused_naming_the_option(tmp_path):
    from typer.testing import CliRunner

    from urd.cli import app
    from urd.ingest import named_angles

    scene, _ = capture_virtual(Dataset.open_or_create(tmp_path / "ds"), angles=(0, 30, 60, 90), size=(96, 64),
                               shake_px=0, shake_deg=0)
    folder = tmp_path / "raw"
    shutil.copytree(scene.path / "raw", folder)
    assert named_angles(sorted(folder.iterdir())) == [0.0, 30.0, 60.0, 90.0]
    out = CliRunner().invoke(app, ["ingest", str(folder), str(tmp_path / "new")])
    assert out.exit_code == 2 and "ingest them with --angles 0,30,60,90" in " ".join(out.output.split()), out.output
    assert not (tmp_path / "new").exists()
    out = CliRunner().invoke(app, ["ingest", str(folder), str(tmp_path / "new"), "--angles", "0,30,60,90"])
    assert out.exit_code == 0 and "ingested scene_01 (from 4 files)" in out.output, out.output
    (folder / "shot_00_000.0deg.dng").rename(folder / "IMG_0001.dng")        # not all urd's: the names say nothing
    assert named_angles(sorted(folder.iterdir())) is None


def test_a_scene_ingested_before_turns_were_recorded_keeps_the_stage_angles_its_results_were_made_at(tmp_path):
    ds = Dataset.open_or_create(tmp_path / "ds")
    scene, _ = capture_virtual(ds, angles=(0, 45, 90), size=(320, 240), shake_px=3, shake_deg=4.0, seed=3)
    assert ingest_scene(scene, IngestOptions()).error is None
    record = scene.load()
    assert all("turn_deg" in entry for entry in record["ingest"]["alignment"][1:])
    assert scene.reload().angles_deg() != [0.0, 45.0, 90.0]
    for entry in record["ingest"]["alignment"]:                # as urd wrote it before
        entry.pop("turn_deg", None)
    from urd.core.files import write_json_atomic

    write_json_atomic(scene.manifest_path, record)
    assert scene.reload().angles_deg() == [0.0, 45.0, 90.0] == scene.uncalibrated_angles_deg()


def test_an_interrupted_redo_says_what_the_scenes_it_kept_superseded(tmp_path, monkeypatch):
    import urd.ingest as ingest_module
    from rig import separated_virtual_scene

    ds = Dataset.open_or_create(tmp_path / "ds")
    first, second = separated_virtual_scene(ds, seed=1), separated_virtual_scene(ds, seed=2)
    real, calls = ingest_module.ingest_scene, []

    def stopped_at_the_second(scene, opts, progress=None):
        calls.append(scene.name)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(scene, opts, progress)

    monkeypatch.setattr(ingest_module, "ingest_scene", stopped_at_the_second)
    with pytest.raises(KeyboardInterrupt) as stopped:
        ingest_module.ingest(ds.root, ds.root, IngestOptions(redo=True, motion=Motion.TRANSLATION))
    notes = stopped.value.__notes__
    assert notes[0].startswith("1 scene ingested before it (scene_01) kept, the others unchanged")
    assert any(note.startswith("scene_01: results of none are stale") for note in notes), notes
    assert first.reload().stale_reason("none") and not second.reload().stale_reason("none")
