"""What the CLI says: help with examples and -h, progress of the slow baselines, and error
messages that name the problem, the choices and the way out."""

import os
import re
import shlex
import shutil
import subprocess
import sys

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from separate.baselines import arvanitopoulos, kong, li_brown
from separate.tiling import MIN_TILE, OVERLAP
from conftest import ingested_dataset
from urd.cli import app
from urd.core.dataset import Dataset

pytestmark = pytest.mark.usefixtures("wide_terminal")
SIM = ("--stage", "sim", "--camera", "virtual")


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def urd(*args, cwd=None):
    env = {**os.environ, "COLUMNS": "200"}
    return subprocess.run([sys.executable, "-m", "urd.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=300, env=env, cwd=cwd)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """A dataset with one captured and ingested 256×192 scene (scene_01)."""
    return ingested_dataset(tmp_path_factory, "messages")


def leaf_commands(command=None, path=()):
    """Every command path of the CLI (groups included), e.g. ('calibrate', 'offset')."""
    command = command or typer.main.get_command(app)
    paths = []
    for name, sub in getattr(command, "commands", {}).items():
        paths.append(path + (name,))
        paths += leaf_commands(sub, path + (name,))
    return paths


COMMANDS = leaf_commands()


def test_the_command_list_covers_every_command():
    assert {"capture", "ingest", "separate", "verify", "demo"} <= {p[0] for p in COMMANDS}
    assert ("calibrate", "offset") in COMMANDS and ("calibrate", "shots") in COMMANDS


@pytest.mark.parametrize("command", COMMANDS, ids=" ".join)
def test_every_command_accepts_h_and_shows_examples_that_parse(command):
    out = invoke(*command, "-h")
    assert out.exit_code == 0, out.output
    _, _, after = out.stdout.partition("Example:\n")
    examples = [line.strip() for line in after.split("\n\n")[0].splitlines()]
    assert examples, out.stdout
    for example in examples:
        words = shlex.split(example)
        assert words[: len(command) + 1] == ["urd", *command], example
        parsed = invoke(*words[1:], "--help")                 # unknown options or choices fail to parse
        assert parsed.exit_code == 0, (example, parsed.output)


@pytest.mark.parametrize("module,options", [(kong, {"steps": 4}), (li_brown, {}), (arvanitopoulos, {})],
                         ids=["kong", "li_brown", "arvanitopoulos"])
@pytest.mark.slow
def test_the_slow_baselines_report_progress_through_a_callback(module, options):
    stack = np.random.default_rng(0).uniform(0.1, 0.5, (3, 64, 64, 3)).astype(np.float32)
    calls = []
    module.separate(stack, [0.0, 45.0, 90.0], progress=lambda done, total: calls.append((done, total)), **options)
    assert len(calls) > 2
    assert len({total for _, total in calls}) == 1 and calls[-1] == (calls[-1][1], calls[-1][1])
    assert [done for done, _ in calls] == sorted(done for done, _ in calls)


@pytest.mark.slow
def test_a_baseline_shows_progress_on_the_terminal_and_records_no_callback(dataset):
    out = urd("separate", "scene_01", "--dataset", dataset, "--method", "li-brown")
    assert out.returncode == 0, out.stderr
    assert "separate (li-brown)" in out.stderr and "100%" in out.stderr
    result = Dataset.open(dataset).scene("scene_01").load(verify=False)["results"]["li-brown"]
    assert "progress" not in result["parameters"]


def test_images_that_do_not_exist_are_a_usage_error_before_the_network_is_set_up(tmp_path):
    (tmp_path / "b.tiff").write_bytes(b"")
    out = invoke("separate", "--images", tmp_path / "a.tiff", "--images", tmp_path / "b.tiff", "--images",
                 tmp_path / "c.tiff", "--angles", "0,45,90", "--out", tmp_path / "out")
    assert out.exit_code == 2 and "--images" in out.stderr and "a.tiff" in out.stderr and "c.tiff" in out.stderr
    assert "b.tiff" not in out.stderr and "precision" not in out.stderr and not (tmp_path / "out").exists()


def test_a_missing_dataset_is_said_to_be_missing_with_how_to_make_one(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for args in (("report",), ("verify",), ("separate", "scene_01"), ("calibrate", "shots", "scene_01")):
        out = invoke(*args)
        assert out.exit_code == 1, (args, out.output)
        assert "no dataset: " in out.stderr and "does not exist" in out.stderr and "urd capture" in out.stderr and "urd ingest" in out.stderr
    assert not (tmp_path / "dataset").exists()


def test_a_raw_file_given_to_ingest_is_said_to_be_a_file(tmp_path, monkeypatch, dataset):
    monkeypatch.chdir(tmp_path)
    shot = next((dataset / "scene_01" / "raw").glob("*.dng"))
    out = invoke("ingest", shot)
    assert out.exit_code == 2 and "is a file; ingest takes a folder" in out.stderr
    assert not (tmp_path / "dataset").exists()


@pytest.mark.parametrize("args,choices", [
    (("ingest", "raw", "--motion", "spin"), "translation, euclidean, homography"),
    (("ingest", "raw", "--transfer", "gamma"), "linear, srgb"),
    (("ingest", "raw", "--mosaic", "bayer"), "imx250mzr, imx250myr, wen2019"),
    (("ingest", "raw", "--mosaic", "wen2019", "--demosaic", "magic"), "none, bilinear, newton"),
    (("separate", "--images", "a.tif", "--images", "b.tif", "--images", "c.tif", "--transfer", "gamma"), "linear, srgb"),
    (("capture", "--stage", "sim", "--camera", "polaroid"), "gphoto2, virtual"),
    (("calibrate", "offset", "--stage", "sim", "--camera", "polaroid"), "gphoto2, virtual"),
    (("demo", "demo", "--precision", "fp16"), "auto, fp32 or bf16"),
])
def test_a_bad_choice_exits_2_and_lists_the_choices(tmp_path, monkeypatch, args, choices):
    monkeypatch.chdir(tmp_path)
    out = invoke(*args)
    assert out.exit_code == 2 and choices in out.stderr, out.output
    assert list(tmp_path.iterdir()) == []                          # nothing created


def test_the_tile_help_states_the_minimum_the_code_enforces():
    stated = re.search(r"--tile\b.*?at\s+least\s+(\d+)", invoke("separate", "-h").stdout, re.S)
    assert stated and int(stated.group(1)) == max(MIN_TILE, 2 * OVERLAP)


def test_argument_checks_come_before_the_existing_results_check(dataset):
    assert invoke("separate", "scene_01", "--dataset", dataset, "--method", "network", "--force").exit_code == 0
    minimum = max(MIN_TILE, 2 * OVERLAP)
    out = invoke("separate", "scene_01", "--dataset", dataset, "--method", "network", "--tile", minimum - 8)
    assert out.exit_code == 2 and f"at least {minimum} px" in out.stderr and "already has" not in out.stderr
    out = invoke("separate", "scene_01", "--dataset", dataset, "--method", "network", "--tile", minimum)
    assert out.exit_code == 1 and "already has network results" in out.stderr and "precision" not in out.stderr


def test_the_networks_refusals_come_before_torch_is_imported(dataset, tmp_path):
    """torch costs ~2 s per process: a command that is refused does not wait for it."""
    invoke("separate", "scene_01", "--dataset", dataset)                  # the scene has network results
    refused = [(["separate", "scene_01", "--dataset", str(dataset), "--precision", "fp16"], 2),
               (["separate", "scene_01", "--dataset", str(dataset)], 1),
               (["separate", "--images", "a.tiff", "--images", "b.tiff", "--out", "elsewhere"], 2),
               (["bench", "--methods", "none,netwrk"], 2)]
    script = ("import sys\nfrom urd.cli import app\n"
              f"for args, _ in {refused!r}:\n"
              "    try:\n        app(args)\n    except SystemExit as exc:\n        print('exit', exc.code)\n"
              "print('torch imported:', 'torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=tmp_path)
    assert out.stdout.split("\n")[:4] == [f"exit {code}" for _, code in refused], out.stdout + out.stderr
    assert "torch imported: False" in out.stdout
    for says in ("fp32 or bf16, got 'fp16'", "already has network results", "got 2 files", "unknown 'netwrk'"):
        assert says in out.stderr


def test_keep_copies_is_recorded_for_the_network_and_refused_for_a_baseline(dataset):
    out = invoke("separate", "scene_01", "--dataset", dataset, "--method", "kong", "--keep-copies")
    assert out.exit_code == 2 and "--return-copies/--keep-copies is for the network" in out.stderr
    out = invoke("separate", "scene_01", "--dataset", dataset, "--method", "network", "--keep-copies", "--force")
    assert out.exit_code == 0, out.output
    result = Dataset.open(dataset).scene("scene_01").load(verify=False)["results"]["network"]
    assert result["parameters"]["return_copies"] is False


def test_no_precision_line_before_no_such_scene(dataset):
    out = invoke("separate", "scene_09", "--dataset", dataset, "--method", "network")
    assert out.exit_code == 2 and "no scene 'scene_09'" in out.stderr and "precision" not in out.stderr


@pytest.mark.slow
def test_raw_files_given_to_separate_point_to_ingest_without_opencv_warnings(dataset):
    shots = sorted((dataset / "scene_01" / "raw").glob("*.dng"))
    for args in ([arg for shot in shots for arg in ("--images", shot)], ["--images", *shots[:2]], [shots[0]]):
        out = urd("separate", *args, "--method", "none")                 # --images a.dng b.dng: b.dng is the scene
        assert out.returncode == 2 and "RAW files" in out.stderr and "urd ingest" in out.stderr, out.stderr
        assert "WARN" not in out.stderr


def test_verify_counts_one_scene_in_the_singular(dataset):
    out = invoke("verify", dataset)
    assert out.exit_code == 0 and "1 scene intact" in out.stdout and "scenes" not in out.stdout
    out = invoke("verify", dataset / "scene_01")                      # one scene's folder
    assert out.exit_code == 0 and "scene_01: ok" in out.stdout and "1 scene intact" in out.stdout


def test_report_counts_one_scene_in_the_singular(dataset):
    out = invoke("report", dataset)
    assert out.exit_code == 0 and ": 1 scene;" in out.stdout


def test_verify_does_not_tell_you_to_run_verify(tmp_path):
    root = tmp_path / "ds"
    assert invoke("capture", root, *SIM, "--sim-size", "96x64").exit_code == 0
    shot = next((root / "scene_01" / "raw").glob("*.dng"))
    shot.write_bytes(shot.read_bytes()[::-1])
    out = invoke("verify", root)
    assert out.exit_code == 1 and "problems in 1 of 1 scene" in out.stderr
    assert "does not match the manifest" in out.stderr and "urd verify" not in out.stderr


def test_ingest_says_which_options_it_cannot_apply(tmp_path, dataset):
    raw = tmp_path / "raw"
    shutil.copytree(dataset / "scene_01" / "raw", raw)
    assert invoke("ingest", raw, tmp_path / "new", "--angles", "0,45,90").exit_code == 0
    out = invoke("ingest", raw, tmp_path / "new", "--angles", "0,60,120")
    assert out.exit_code == 0 and "already ingested as scene_01 at 0,45,90 deg (not 0,60,120: a scene keeps the angles" in out.stdout
    for args, reason in (((tmp_path / "new" / "scene_01", "--redo", "--angles", "0,60,120"), "a scene's angles are in its manifest"),
                         ((raw, tmp_path / "other", "--demosaic", "bilinear"), "--demosaic: for --mosaic frames"),
                         ((raw, tmp_path / "other", "--jobs", "2"), "--jobs is for a dataset or scene folder"),
                         ((tmp_path / "nowhere", tmp_path / "other"), "no such folder or file")):
        out = invoke("ingest", *args)
        assert out.exit_code == 2 and reason in " ".join(out.stderr.split()), (args, out.output)
    assert not (tmp_path / "other").exists()


def test_images_replaced_with_force_leave_one_runs_results(tmp_path, dataset):
    shots = [a for p in sorted((dataset / "scene_01" / "aligned").glob("*.tiff")) for a in ("--images", p)]
    assert invoke("separate", *shots, "--method", "schechner", "--maps", "--out", tmp_path / "out").exit_code == 0
    assert (tmp_path / "out" / "reference_deg.tiff").is_file() and (tmp_path / "out" / "maps" / "S0.tiff").is_file()
    out = invoke("separate", *shots, "--method", "none", "--force", "--out", tmp_path / "out")
    assert out.exit_code == 0, out.output
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [
        "R.tiff", "R_preview.png", "T.tiff", "T_preview.png", "clipped.png", "confidence.tiff"]


def test_an_existing_html_report_is_refused_before_anything_is_printed(tmp_path):
    root = tmp_path / "ds"
    assert invoke("capture", root, *SIM, "--sim-size", "96x64").exit_code == 0
    assert invoke("report", root, "--html", tmp_path / "rep").exit_code == 0
    out = invoke("report", root, "--html", tmp_path / "rep")
    assert out.exit_code == 1 and out.stdout == "" and "already exists; pass --force to replace it" in out.stderr
    assert invoke("report", root, "--html", tmp_path / "rep", "--force").exit_code == 0
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    for target in (tmp_path / "mine", tmp_path / "mine" / "notes.txt"):
        out = invoke("report", root, "--html", target, "--force")
        assert out.exit_code == 1 and "is not an urd HTML report; choose another folder" in out.stderr
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep"


def test_report_points_at_missing_and_truncated_files(tmp_path):
    root = tmp_path / "ds"
    assert invoke("capture", root, *SIM, "--sim-size", "96x64").exit_code == 0
    shots = sorted((root / "scene_01" / "raw").glob("*.dng"))
    shots[0].unlink()
    shots[1].write_bytes(shots[1].read_bytes()[:100])
    out = invoke("report", root)
    assert out.exit_code == 0
    assert f"2 listed files missing or of another size (raw/{shots[0].name}, raw/{shots[1].name}): run urd verify" in out.stdout


def test_verify_checks_the_calibration_and_report_lists_the_scenes_whatever_its_state(tmp_path):
    root = tmp_path / "ds"
    assert invoke("capture", root, *SIM, "--sim-size", "96x64").exit_code == 0
    assert invoke("calibrate", "offset", root, *SIM, "--step", "30").exit_code == 0
    out = invoke("verify", root)
    assert out.exit_code == 0 and "calibration: ok" in out.stdout and "1 scene and the calibration intact" in out.stdout
    shot = next((root / "calibration" / "sweep_01" / "raw").glob("*.dng"))
    shot.write_bytes(shot.read_bytes()[::-1])
    out = invoke("verify", root)
    assert out.exit_code == 1 and "problems in the calibration" in out.stderr
    assert re.search(rf"^calibration: .*sweep_01/raw/{shot.name}.* does not match the manifest", out.stderr, re.M)
    (root / "calibration.json").write_text("{not json")
    out = invoke("verify", root)
    assert out.exit_code == 1 and "calibration.json" in out.stderr
    out = invoke("report", root)
    assert out.exit_code == 0 and "polarizer offset unreadable (" in out.stdout and "scene_01" in out.stdout


def test_scene_folders_made_from_a_raw_folder_follow_the_umask(tmp_path, dataset):
    raw = tmp_path / "raw"
    shutil.copytree(dataset / "scene_01" / "raw", raw)
    assert invoke("ingest", raw, tmp_path / "new").exit_code == 0
    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "new" / "scene_01").stat().st_mode & 0o777 == 0o777 & ~umask


# 11. results are easy to read: the demo names the previews to open and explains clipped.png; mosaic ingest
#     says which frame became which scene

def test_the_demo_ends_with_the_previews_to_open_and_what_clipped_png_means(tmp_path):
    out = invoke("demo", tmp_path / "demo", "--size", "192x128")
    assert out.exit_code == 0, out.output
    line = next(line for line in out.stdout.splitlines() if line.startswith("open the previews: "))
    previews = line.removeprefix("open the previews: ").split("  ")
    assert [p.rsplit("/", 1)[1] for p in previews] == ["T_preview.png", "R_preview.png"]
    assert all(os.path.isfile(p) for p in previews)
    assert "clipped.png: no pixel is clipped in any shot (the mask is all black)" in out.stdout


@pytest.mark.slow
def test_separate_says_which_angle_of_incidence_the_network_used_and_takes_a_given_one(tmp_path):
    import json

    import cv2

    out = invoke("demo", tmp_path / "demo", "--size", "384x256")
    assert out.exit_code == 0, out.output
    scene = tmp_path / "demo" / "scene_01"
    truth = float(np.median(cv2.imread(str(scene / "truth" / "theta_deg.tiff"), cv2.IMREAD_UNCHANGED)))
    record = json.loads((scene / "scene.json").read_text())["results"]["network"]["incidence"]
    assert record["gate"] and record["median_deg"] == pytest.approx(truth, abs=4.0)
    lo, hi = record["range_deg"]
    assert f"angle of incidence {record['median_deg']:.0f} deg ({lo:.0f}-{hi:.0f} across the frame; estimated" in out.stdout
    given = invoke("separate", scene, "--force", "--incidence", "47.5")
    assert given.exit_code == 0, given.output
    assert "angle of incidence 47.5 deg (given; the network's Fresnel gate on)" in given.stdout
    entry = json.loads((scene / "scene.json").read_text())["results"]["network"]
    assert entry["incidence"]["given"] and entry["parameters"]["incidence_deg"] == 47.5
    ungated = invoke("separate", scene, "--force", "--weights", "urd-canonical", "--incidence", "40")
    assert ungated.exit_code == 1 and "physics-anchored network" in ungated.stderr
    assert json.loads((scene / "scene.json").read_text())["results"]["network"] == entry     # nothing replaced
    for args, reason in ((("--incidence", "90"), "between 0 and 90"),
                         (("--method", "schechner", "--incidence", "40"), "--param theta_deg=DEG")):
        bad = invoke("separate", scene, "--force", *args)
        assert bad.exit_code == 2 and reason in bad.stderr, bad.output


def test_mosaic_ingest_names_the_frame_of_each_scene(tmp_path):
    frames = tmp_path / "frames"
    frames.mkdir()
    rng = np.random.default_rng(0)
    import cv2

    for name in ("left.png", "right.png"):
        cv2.imwrite(str(frames / name), rng.integers(20, 200, (64, 96), dtype=np.uint8))
    out = invoke("ingest", frames, tmp_path / "ds", "--mosaic", "imx250mzr", "--demosaic", "bilinear")
    assert out.exit_code == 0, out.output
    assert "ingested scene_01 (from left.png)" in out.stdout and "ingested scene_02 (from right.png)" in out.stdout


@pytest.mark.slow
def test_training_says_from_which_step_it_resumes(tmp_path):
    config = tmp_path / "tiny.toml"
    config.write_text('width = 8\npatch = 64\nbatch = 2\nmicro_batch = 2\nsteps = 2\nval_samples = 2\nval_every = 2\n')
    first = invoke("train", config, tmp_path / "run")
    assert first.exit_code == 0, first.output
    assert "step 2: loss" in first.output and "min of training" in first.output
    config.write_text(config.read_text().replace("steps = 2", "steps = 3"))
    again = invoke("train", config, tmp_path / "run")
    assert again.exit_code == 0, again.output
    assert f"resuming {tmp_path / 'run'} from step 2 of 3" in again.output and "stopped at step 3" in again.output


def test_a_dataset_made_in_a_folder_of_other_files_says_so_and_leaves_them(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    (folder / "notes.txt").write_text("mine")
    first = invoke("capture", folder, *SIM, "--sim-size", "96x64")
    assert first.exit_code == 0, first.output
    assert "holds other files but no urd dataset: the dataset is made there, beside them" in first.stderr
    assert (folder / "notes.txt").read_text() == "mine" and (folder / "scene_01" / "scene.json").is_file()
    again = invoke("capture", folder, *SIM, "--sim-size", "96x64")       # now a dataset: nothing to say
    assert again.exit_code == 0 and "no urd dataset" not in again.stderr
    new = invoke("capture", tmp_path / "new", *SIM, "--sim-size", "96x64")
    assert new.exit_code == 0 and "no urd dataset" not in new.stderr


def test_no_note_where_the_command_refuses_a_dataset_inside_another_and_hidden_files_do_not_count(tmp_path):
    root = tmp_path / "ds"
    assert invoke("capture", root, *SIM, "--sim-size", "96x64").exit_code == 0
    nested = invoke("capture", root / "scene_01", *SIM, "--sim-size", "96x64")
    assert nested.exit_code == 1 and "cannot hold another" in nested.stderr and "no urd dataset" not in nested.stderr
    hidden = tmp_path / "hidden"
    hidden.mkdir()
    (hidden / ".DS_Store").write_bytes(b"")
    out = invoke("capture", hidden, *SIM, "--sim-size", "96x64")
    assert out.exit_code == 0 and "no urd dataset" not in out.stderr


def test_an_ingest_that_fails_in_a_folder_of_other_files_says_so_and_leaves_only_them(tmp_path):
    raw = tmp_path / "raw"
    raw.mkdir()
    (raw / "readme.txt").write_text("no shots here")
    folder = tmp_path / "photos"
    folder.mkdir()
    (folder / "notes.txt").write_text("mine")
    out = invoke("ingest", raw, folder)
    assert out.exit_code == 1 and "holds other files but no urd dataset" in out.stderr
    assert sorted(p.name for p in folder.iterdir()) == ["notes.txt"]          # no dataset.json, no lock left


def test_angles_given_in_radians_are_named_so_with_their_degrees():
    out = invoke("separate", "--images", "a.png", "--images", "b.png", "--images", "c.png", "--angles", "0,0.785,1.571")
    assert out.exit_code == 2 and "these look like radians: in degrees they are 0,45,90" in out.stderr
    out = invoke("separate", "--images", "a.png", "--images", "b.png", "--images", "c.png", "--angles", "0,10,20")
    assert out.exit_code == 2 and "radians" not in out.stderr
