"""The edges a new user meets on the simulated rig: values the options refuse before anything
is made, failures that leave nothing half-made, ground truth that a stopped capture lost, and
image files and arrays of unusual kinds."""

import shutil

import cv2
import numpy as np
import pytest
import tifffile
import typer
from typer.testing import CliRunner

import urd
from acquire import plan
from acquire.rig import SimSettings
from conftest import ingested_dataset
from urd.cli import app
from urd.cli.common import run_guarded
from urd.core.dataset import Dataset, Scene
from urd.core.errors import CaptureInterrupted, DatasetError, DeviceError, ManifestError, RawFormatError
from urd.core.images import read_image, u16_to_linear
from urd.core.processes import Terminated, kept_note
from separate.methods import get_method
from urd.separation import separate_images

pytestmark = pytest.mark.usefixtures("wide_terminal")
SIM = ("--stage", "sim", "--camera", "virtual", "--sim-size", "96x64")


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return ingested_dataset(tmp_path_factory, "edges")


@pytest.mark.parametrize("options, message", [
    (("--angles", "370,45,90"), "within ±360 deg"),
    (("--angles", "0,,45,90"), "expected comma-separated degrees like 0,45,90"),
    (("--tolerance", "nan"), "expected a finite number"),
    (("--sim-shake", "nan"), "expected a finite number"),
    (("--sim-offset", "inf"), "expected a finite number"),
    (("--seed", "-1"), "expected at least 0"),
    (("--sim-size", "65x49"), "even number of px between 32 and 20000"),
    (("--tolerance", "0"), "expected at least 0.01"),
    (("--scene", "foo"), "expected a scene name like scene_01"),
    (("--reflection", "/nonexistent.png"), "no such image file"),
])
def test_capture_refuses_bad_values_as_usage_errors_and_makes_nothing(tmp_path, options, message):
    out = invoke("capture", tmp_path / "ds", *SIM, *options)
    assert out.exit_code == 2 and message in out.output
    assert not (tmp_path / "ds").exists()


@pytest.mark.parametrize("option", ["--offset", "--jitter"])
def test_sim_stage_refuses_nan_before_serving(option):
    out = invoke("sim-stage", option, "nan")
    assert out.exit_code == 2 and "expected a finite number" in out.output


def test_a_refused_scene_record_leaves_no_scene_folder(tmp_path):
    ds = Dataset.open_or_create(tmp_path / "ds")
    with pytest.raises(ManifestError):
        ds.new_scene("capture", {"angles_deg": [0.0, 45.0, 1000.0], "offset_deg": 0.0, "tolerance_deg": 0.5})
    assert ds.scene_names() == [] and not (tmp_path / "ds" / "scene_01").exists()


def test_a_capture_that_fails_before_its_first_shot_leaves_no_dataset(tmp_path, monkeypatch):
    def run_capture(*args, **kwargs):
        raise DeviceError("ELL14 at address 0 did not answer within the time-out")       # e.g. while homing

    monkeypatch.setattr(plan, "run_capture", run_capture)
    out = invoke("capture", tmp_path / "ds", *SIM)
    assert out.exit_code == 1 and "did not answer" in out.output and "no shot was taken" in out.output
    assert not (tmp_path / "ds").exists()


def test_sigterm_during_a_capture_exits_143_and_ctrl_c_130(tmp_path, monkeypatch):
    def stopped(kind):
        def run_capture(*args, **kwargs):
            raise kind("stopped")
        return run_capture

    for kind, code, said in ((Terminated, 143, "capture stopped by SIGTERM"), (KeyboardInterrupt, 130, "capture interrupted")):
        monkeypatch.setattr(plan, "run_capture", stopped(kind))
        with pytest.raises(CaptureInterrupted, match=said) as caught:
            plan.capture_scene(tmp_path / "ds", "sim", "virtual", sim=SimSettings(width=96, height=64),
                               announce=lambda line: None)
        def capture():
            raise caught.value

        with pytest.raises(typer.Exit) as exited:
            run_guarded(capture)
        assert exited.value.exit_code == code


def test_ground_truth_a_stopped_capture_lost_is_reported_and_written_by_the_next_capture(tmp_path):
    root = tmp_path / "ds"
    assert invoke("capture", root, *SIM).exit_code == 0
    (root / "scene_01" / "truth").rename(root / "scene_01" / "truth-incomplete-1")   # what the recovery does
    out = invoke("verify", root)
    assert out.exit_code == 1 and "no ground truth" in out.output and "truth-incomplete-1" in out.output
    out = invoke("capture", root, *SIM)
    assert out.exit_code == 0 and "writing the ground truth of" in out.output
    assert Dataset.open(root).scene_names() == ["scene_01"]
    assert invoke("verify", root).exit_code == 0
    assert not list((root / "scene_01").glob("truth-incomplete-*"))         # the torn copy goes once the truth is whole
    other = tmp_path / "other"
    assert invoke("capture", other, *SIM).exit_code == 0
    shutil.move(other / "scene_01" / "truth", tmp_path / "truth-moved-away")    # the user's choice, not a stop
    out = invoke("capture", other, *SIM)
    assert out.exit_code == 0 and "writing the ground truth" not in out.output
    assert Dataset.open(other).scene_names() == ["scene_01", "scene_02"]


def test_ingest_refuses_a_dataset_argument_it_would_ignore(dataset, tmp_path):
    out = invoke("ingest", dataset / "scene_01", tmp_path / "elsewhere")
    assert out.exit_code == 2 and "is ingested where it is" in out.output
    assert not (tmp_path / "elsewhere").exists()
    raw = tmp_path / "raw"
    raw.mkdir()
    out = invoke("ingest", raw, raw)
    assert out.exit_code == 2 and "other than the RAW folder" in out.output and not (raw / "dataset.json").exists()


def test_calibrate_offset_refuses_a_damaged_calibration_before_the_sweep(tmp_path):
    root = tmp_path / "ds"
    Dataset.open_or_create(root)
    (root / "calibration.json").write_text("{bad")
    out = invoke("calibrate", "offset", root, "--stage", "sim", "--camera", "virtual")
    assert out.exit_code == 1 and "the sweep was not started" in out.output
    assert not (root / "calibration").exists()


def test_a_scene_given_as_its_own_folder_dot_is_named(dataset, monkeypatch):
    monkeypatch.chdir(dataset / "scene_01")
    assert Scene(".").name == "scene_01"
    out = invoke("verify", ".")
    assert out.exit_code == 0 and "scene_01: ok" in out.output


def test_files_no_manifest_lists_in_a_results_folder_are_not_replaced_without_force(dataset):
    folder = dataset / "scene_01" / "results" / "none"
    folder.mkdir(parents=True)
    (folder / "T.tiff").write_text("my notes")
    try:
        out = invoke("separate", "scene_01", "--dataset", dataset, "--method", "none")
        assert out.exit_code == 1 and "holds files no manifest lists (T.tiff)" in out.output
        assert (folder / "T.tiff").read_text() == "my notes"
    finally:
        shutil.rmtree(folder)


def test_maps_on_existing_results_refuse_options_they_would_ignore(dataset):
    assert invoke("separate", "scene_01", "--dataset", dataset, "--method", "schechner", "--force").exit_code == 0
    out = invoke("separate", "scene_01", "--dataset", dataset, "--method", "schechner", "--maps", "--reference", "45")
    assert out.exit_code == 2 and "--reference" in out.output and "pass --force" in out.output
    assert not (dataset / "scene_01" / "results" / "schechner" / "maps").exists()


def test_a_failed_images_run_with_force_keeps_the_earlier_results_whole(tmp_path, monkeypatch):
    rng = np.random.default_rng(0)
    paths = []
    for k in range(3):
        paths.append(tmp_path / f"shot_{k}.tiff")
        tifffile.imwrite(paths[-1], (rng.random((48, 64, 3)) * 30000).astype(np.uint16), photometric="rgb")
    out = tmp_path / "out"
    run, _ = get_method("schechner")
    separate_images(paths, [0.0, 45.0, 90.0], out, run)
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    def broken(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr("urd.separation.write_preview", broken)
    with pytest.raises(OSError, match="disk full"):
        separate_images(paths[::-1], [0.0, 45.0, 90.0], out, run, force=True)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_a_failed_images_run_leaves_no_output_folder_it_made(tmp_path):
    run, _ = get_method("none")
    with pytest.raises(DatasetError, match="no such file"):
        separate_images([tmp_path / "nope.tiff"] * 3, [0.0, 45.0, 90.0], tmp_path / "new", run)
    assert not (tmp_path / "new").exists()


def test_lzw_and_grey_with_alpha_tiffs_are_read(tmp_path):
    rgb = (np.arange(32 * 40 * 3).reshape(32, 40, 3) % 65536).astype(np.uint16)
    assert cv2.imwrite(str(tmp_path / "lzw.tiff"), rgb[..., ::-1])          # OpenCV writes LZW
    with tifffile.TiffFile(tmp_path / "lzw.tiff") as tif:
        assert tif.pages[0].compression == 5
    np.testing.assert_array_equal(read_image(tmp_path / "lzw.tiff"), rgb / np.float32(65535))
    grey_alpha = np.stack([rgb[..., 0], np.full((32, 40), 65535, np.uint16)], axis=-1)
    tifffile.imwrite(tmp_path / "ga.tiff", grey_alpha, photometric="minisblack", extrasamples=["unassalpha"])
    image = read_image(tmp_path / "ga.tiff")
    assert image.shape == (32, 40, 3)
    np.testing.assert_array_equal(image[..., 1], rgb[..., 0] / np.float32(65535))


def test_the_network_takes_a_stack_of_any_memory_layout():
    rng = np.random.default_rng(1)
    stack = (rng.random((3, 40, 56, 3)) * 0.5).astype(np.float32)
    plain = urd.separate(stack, [0, 45, 90]).transmission
    transposed = np.ascontiguousarray(stack.transpose(0, 3, 1, 2)).transpose(0, 2, 3, 1)
    np.testing.assert_array_equal(urd.separate(transposed, [0, 45, 90]).transmission, plain)
    np.testing.assert_array_equal(urd.separate(np.asfortranarray(stack), [0, 45, 90]).transmission, plain)


@pytest.mark.parametrize("shape", [(3, 2, 900, 3), (3, 1, 1, 3), (3, 0, 8, 3)])
def test_frames_too_thin_to_inspect_are_refused_with_their_size(shape):
    with pytest.raises(ValueError, match="at least 2 px on a side, at most 128 times as long as wide"):
        urd.separate(np.full(shape, 0.2, np.float32), [0, 45, 90], method="schechner")


def test_the_demo_refuses_a_sensor_too_small_to_align_and_makes_nothing(tmp_path):
    out = invoke("demo", tmp_path / "demo", "--size", "64x48")
    assert out.exit_code == 2 and "between 128 and 20000" in out.output and not (tmp_path / "demo").exists()


def test_calibrate_offset_refuses_a_nan_target_angle_before_the_sweep(tmp_path):
    out = invoke("calibrate", "offset", tmp_path / "ds", "--stage", "sim", "--camera", "virtual", "--target-angle", "nan")
    assert out.exit_code == 2 and "expected a finite number" in out.output and not (tmp_path / "ds").exists()


def test_float_files_are_read_with_white_at_one_and_named_when_not(tmp_path):
    tifffile.imwrite(tmp_path / "ok.tiff", np.full((8, 8, 3), 0.5, np.float32), photometric="rgb")
    np.testing.assert_array_equal(read_image(tmp_path / "ok.tiff"), 0.5)
    tifffile.imwrite(tmp_path / "hdr.tiff", np.full((8, 8, 3), 10.0, np.float32), photometric="rgb")
    with pytest.raises(RawFormatError, match=r"hdr.tiff: float pixels are read with 1.0 as white, and 100.0% of these exceed it"):
        read_image(tmp_path / "hdr.tiff")
    tifffile.imwrite(tmp_path / "nan.tiff", np.full((8, 8, 3), np.nan, np.float32), photometric="rgb")
    with pytest.raises(RawFormatError, match=r"nan.tiff: 192 NaN or infinite pixel values"):
        read_image(tmp_path / "nan.tiff")
    with pytest.raises(DatasetError, match="is a folder, not an image file"):
        read_image(tmp_path)
    (tmp_path / "bad.tiff").write_bytes(b"not a tiff")
    with pytest.raises(RawFormatError) as caught:
        read_image(tmp_path / "bad.tiff")
    assert str(caught.value).count("bad.tiff") == 1


def test_images_of_different_sizes_are_named_with_their_sizes(tmp_path):
    for name, (h, w) in (("a.tiff", (32, 40)), ("b.tiff", (32, 40)), ("c.tiff", (30, 40))):
        tifffile.imwrite(tmp_path / name, np.full((h, w, 3), 1000, np.uint16), photometric="rgb")
    out = invoke("separate", "--images", tmp_path / "a.tiff", "--images", tmp_path / "b.tiff", "--images",
                 tmp_path / "c.tiff", "--method", "none", "--out", tmp_path / "out")
    assert out.exit_code == 1 and "a.tiff 40×32, b.tiff 40×32, c.tiff 40×30" in out.output


def test_a_dataset_given_as_the_scene_is_named_as_one(dataset):
    out = invoke("separate", dataset, "--method", "none")
    assert out.exit_code == 2 and "is a dataset; give one of its scenes (scene_01)" in out.output


def test_separate_all_refuses_bad_weights_once(dataset, tmp_path):
    out = invoke("separate", "--all", "--dataset", dataset, "--weights", tmp_path / "nosuch.pt", "--force")
    assert out.exit_code == 2 and out.output.count("nosuch.pt") == 1 and "failed" not in out.output


def test_an_empty_folder_of_mosaic_frames_is_an_error_and_makes_no_dataset(tmp_path):
    (tmp_path / "frames").mkdir()
    out = invoke("ingest", tmp_path / "frames", tmp_path / "ds", "--mosaic", "imx250mzr")
    assert out.exit_code == 1 and "no image files to ingest" in out.output and not (tmp_path / "ds").exists()


def test_an_interrupted_forced_run_says_that_running_it_again_redoes_the_kept_scenes():
    assert kept_note(["scene_01"], "separated").endswith("run the same command again to do them")
    assert "it does the kept ones again too" in kept_note(["scene_01"], "separated", forced=True)


@pytest.mark.parametrize("args, message", [
    (("--virtual",), "cannot write in"), (("--semireal",), "cannot write in"), (("--ablation",), "cannot write in"),
])
def test_bench_checks_its_output_folder_before_the_run(tmp_path, args, message):
    (tmp_path / "afile").write_text("")
    out = invoke("bench", *args, "--out", tmp_path / "afile")
    assert out.exit_code == 2 and message in out.output and "--out" in out.output


@pytest.mark.parametrize("args, message", [
    (("--quick", "--methods", "schechner"), "--methods: not used by this run"),
    (("--ablation", "--methods", "schechner"), "--methods: not used by this run"),
    (("--quick", "--full"), "--quick or --full, not both"),
    (("--out", "x"), "--out: not used by this run"),
    (("--methods", ",,"), "expected at least one method"),
])
def test_bench_refuses_options_it_would_ignore(args, message):
    out = invoke("bench", *args)
    assert out.exit_code == 2 and message in out.output


def test_the_truth_figures_describe_the_stored_files(dataset):
    assert invoke("separate", "scene_01", "--dataset", dataset, "--method", "schechner", "--force").exit_code == 0
    scene = Dataset.open(dataset).scene("scene_01")
    result = scene.result("schechner")
    t_hat = u16_to_linear(tifffile.imread(result.files["T.tiff"]), result.full_scale)
    t_true = tifffile.imread(scene.truth_dir() / "T_obs.tiff")
    h, w = t_true.shape[:2]
    inside = (slice(h // 20, h - h // 20), slice(w // 20, w - w // 20))
    stored = 10 * np.log10(1 / np.mean((t_hat[inside] - t_true[inside]) ** 2, dtype=np.float64))
    assert scene.load()["results"]["schechner"]["truth_metrics"]["T"]["psnr_db"] == pytest.approx(stored, abs=0.01)


def test_a_report_folder_is_judged_before_force_is_asked_for(dataset, tmp_path):
    mine = tmp_path / "documents"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    out = invoke("report", dataset, "--html", mine)
    assert out.exit_code == 1 and "is not an urd HTML report" in out.output and "--force" not in out.output
    old = tmp_path / "old-report"
    old.mkdir()
    (old / "index.html").write_text('<meta name="generator" content="urd report_html 1">')
    out = invoke("report", dataset, "--html", old, "--force")
    assert out.exit_code == 1 and "of an earlier urd, which did not record its files" in out.output
    assert (old / "index.html").exists() and (mine / "notes.txt").read_text() == "keep"


@pytest.mark.parametrize("method", ["network", "ceilnet", "none", "schechner"])
def test_an_option_a_method_does_not_take_is_a_value_error_naming_it(method):
    with pytest.raises(ValueError, match=r"unknown (options|parameters) \['foo'\]"):
        urd.separate(np.full((3, 16, 16, 3), 0.2, np.float32), [0, 45, 90], method=method, foo=1)


def test_signals_within_a_deferred_block_take_effect_as_it_ends():
    import signal

    from urd.core.processes import interrupts_deferred

    reached, before = [], signal.getsignal(signal.SIGINT)
    with pytest.raises(KeyboardInterrupt):
        with interrupts_deferred():
            signal.raise_signal(signal.SIGINT)          # to this thread: os.kill may reach another thread, later
            reached.append("after the signal")
    assert reached == ["after the signal"]
    assert signal.getsignal(signal.SIGINT) is before


def test_an_installed_urd_benchmarks_into_the_working_folder_and_checks_against_its_shipped_figures(tmp_path):
    """`urd bench` writes into ./urd-bench, never into the installed package or the source tree,
    and the quick run's expected figures travel inside the package."""
    from pathlib import Path

    from separate.bench_run import DEFAULT_OUT

    assert DEFAULT_OUT == Path("urd-bench")                    # in this source checkout too
    import subprocess
    import sys

    from separate.bench_run import EXPECTED_QUICK

    assert EXPECTED_QUICK.is_file() and EXPECTED_QUICK.parent.name == "separate"
    assert "expected-quick.json" in (Path(__file__).parents[1] / "pyproject.toml").read_text()
    installed = tmp_path / "site"
    (installed / "separate").mkdir(parents=True)
    probe = ("import runpy, sys; from pathlib import Path; import separate.provenance as p; p.REPO = Path(sys.argv[1]); "
             "ns = runpy.run_path(sys.argv[2]); print(ns['DEFAULT_OUT'])")
    done = subprocess.run([sys.executable, "-c", probe, str(installed), str(Path(__file__).parents[1] / "separate" / "bench_run.py")],
                          cwd=tmp_path, capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "urd-bench"


def test_the_ablation_outside_a_source_checkout_says_it_needs_one(tmp_path):
    from separate.ablation import ablation_runs

    with pytest.raises(ValueError, match="run it from a source checkout"):
        ablation_runs([0, 1], tmp_path / "runs", configs=tmp_path / "configs")


def test_ingest_without_a_source_takes_the_dataset_here_as_capture_made_it(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    out = CliRunner().invoke(app, ["ingest"])
    assert out.exit_code == 2 and "none given, and dataset holds no dataset" in out.output
    out = CliRunner().invoke(app, ["capture", "--stage", "sim", "--camera", "virtual", "--sim-size", "96x64"])
    assert out.exit_code == 0, out.output
    out = CliRunner().invoke(app, ["ingest"])
    assert out.exit_code == 0 and "ingested scene_01" in out.output
    assert Dataset.open(tmp_path / "dataset").scene("scene_01").ingest_outcome() == (True, None)


def test_a_capture_without_shake_is_a_tripod_neither_shifted_nor_turned(tmp_path):
    out = CliRunner().invoke(app, ["capture", str(tmp_path / "ds"), "--stage", "sim", "--camera", "virtual",
                                   "--sim-size", "96x64", "--sim-shake", "0"])
    assert out.exit_code == 0, out.output
    scene = Dataset.open(tmp_path / "ds").scene("scene_01")
    camera = scene.load()["capture"]["camera"]
    assert camera["shake_px"] == 0 and camera["shake_deg"] == 0
    from acquire.virtual_camera import shot_truth

    warps = [shot_truth(path)["shake_matrix"] for path in scene.raw_paths()]
    assert len(warps) == 3 and all(np.array_equal(m, np.eye(3)[:2]) for m in warps)


@pytest.mark.parametrize("options, message", [
    (("--weights", "nonexistent.pt"), "nonexistent.pt: no such file (shipped weights, by name: ceilnet, urd-anchored"),
    (("--method", "farid", "--reference", "1e300"), "an angle within ±360 deg, got '1e300'"),
])
def test_separate_refuses_a_missing_weights_file_and_an_absurd_reference_as_usage_errors(dataset, options, message):
    out = invoke("separate", "scene_01", "--dataset", dataset, *options)
    assert out.exit_code == 2 and message in " ".join(out.output.split()), out.output


def test_a_given_reference_is_the_policy_the_manifest_records(tmp_path_factory):
    root = ingested_dataset(tmp_path_factory, "given-reference")
    assert invoke("separate", "scene_01", "--dataset", root, "--method", "schechner", "--reference", "-10").exit_code == 0
    entry = Dataset.open(root).scene("scene_01").load()["results"]["schechner"]
    assert entry["reference_deg"] == 170.0 and entry["reference_policy"].startswith("fixed: 170 deg")


@pytest.mark.parametrize("command, message", [
    (("separate", "--images", "{t}/a.tif", "--images", "{t}/b.tif", "--images", "{t}/c.tif", "--dataset", "{t}/ds"),
     "--dataset is for a scene or --all; the results of --images go into --out"),
    (("separate", "scene_01", "--dataset", "{t}/ds", "--method", "li-brown", "--reference", "30"),
     "--reference: li-brown sees S0 alone"),
    (("report", "{t}/ds", "--force"), "--force replaces an HTML report folder: it goes with --html FOLDER"),
])
def test_options_that_would_change_nothing_are_refused_as_usage_errors(tmp_path, command, message):
    out = invoke(*(word.format(t=tmp_path) for word in command))
    assert out.exit_code == 2 and message in " ".join(out.output.split()), out.output


def test_gap_on_a_dataset_is_a_usage_error(dataset):
    out = invoke("ingest", dataset, "--gap", "10")
    assert out.exit_code == 2 and "--gap groups a folder of RAW files into scenes" in " ".join(out.output.split())


def test_a_scene_folder_that_cannot_be_written_is_said_before_the_separation_runs(tmp_path_factory, monkeypatch):
    import errno
    import tempfile
    from pathlib import Path

    import urd.separation as separation

    root = ingested_dataset(tmp_path_factory, "read-only")
    scene_path = root / "scene_01"
    real_mkstemp, ran = tempfile.mkstemp, []

    def mkstemp(*args, dir=None, **kwargs):              # a read-only mount: nothing can be made in the scene
        if dir is not None and Path(dir).resolve() == scene_path.resolve():
            raise OSError(errno.EROFS, "Read-only file system")
        return real_mkstemp(*args, dir=dir, **kwargs)

    monkeypatch.setattr(tempfile, "mkstemp", mkstemp)
    monkeypatch.setattr(separation, "separate_inspected", lambda *a, **k: ran.append(1))
    out = invoke("separate", "scene_01", "--dataset", root, "--method", "schechner")
    assert out.exit_code == 1 and "Read-only file system); the separation would fail at its end: nothing was done" in \
        " ".join(out.output.split()), out.output
    assert not ran


def test_an_interrupted_demo_says_where_its_dataset_is_and_what_to_do_with_it(tmp_path, monkeypatch):
    import urd.separation as separation

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt                                # Ctrl-C while the network runs

    monkeypatch.setattr(separation, "separate_scene", stopped)
    out = invoke("demo", tmp_path / "demo", "--size", "256x192")
    said = " ".join(out.output.split())
    assert out.exit_code == 130 and f"the demo's dataset so far is {tmp_path / 'demo'}: delete it" in said, out.output
    assert "'urd demo' starts afresh" in said and (tmp_path / "demo" / "scene_01" / "aligned").is_dir()


def test_urd_keeps_ignoring_an_interrupt_its_shell_told_it_to_ignore():
    import signal

    from urd.core import processes

    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)           # a background job of a shell script
        processes.handle_interrupts()
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
        assert signal.getsignal(signal.SIGTERM) is processes._interrupt
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
