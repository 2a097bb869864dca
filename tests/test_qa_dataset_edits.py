"""A dataset edited by hand or left by a failed run (QA): a scene folder under another name is
named by ``urd verify`` and ``urd report``; a folder where an output file must go refuses the
separation before anything changes; a swap a failure left unfinished is reported by verify and
its recovery leaves no temporary link; the report's wording of shots and a lost ground truth."""

import shutil

import pytest
from typer.testing import CliRunner

import urd.core.swap as swap_module
from rig import separated_virtual_scene
from separate.methods import get_method
from urd.cli import app
from urd.core.dataset import Dataset, Scene, SceneStatus
from urd.core.errors import DatasetError
from urd.report import report_text, verify
from urd.separation import separate_scene

SCENE = "scene_01"


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """scene_01: captured with the virtual camera (ground truth), ingested, results of 'none'."""
    ds = Dataset.open_or_create(tmp_path_factory.mktemp("base") / "ds")
    separated_virtual_scene(ds)
    return ds.root


def separate_again(root):
    """``urd separate scene_01 --method none --force``."""
    run, info = get_method("none")
    separate_scene(Dataset.open(root).scene(SCENE), "none", run, info, force=True)


@pytest.mark.usefixtures("wide_terminal")
def test_a_scene_folder_renamed_by_hand_is_named_by_verify_and_report(base, tmp_path):
    root = shutil.copytree(base, tmp_path / "ds")
    (root / SCENE).rename(root / "kitchen")
    for name in ("scene_1", "scene_01 (copy)", "scene_01.bak"):
        shutil.copytree(root / "kitchen", root / name)
    misnamed = ["kitchen", "scene_01 (copy)", "scene_01.bak", "scene_1"]
    assert Dataset.open(root).scene_names() == []                   # still no scene
    problems = verify(root)
    assert sorted(problems) == misnamed
    assert all(len(p) == 1 and "not named scene_NN" in p[0] and "rename it" in p[0] for p in problems.values())
    out = invoke("verify", root)
    assert out.exit_code == 1 and all(f"{name}: " in out.output for name in misnamed)
    text = report_text(root)
    assert "0 scenes" in text and all(f"  {name}: " in text for name in misnamed) and "scene_02" in text


def test_a_folder_where_an_output_file_goes_refuses_the_separation_naming_it(base, tmp_path):
    root = shutil.copytree(base, tmp_path / "ds")
    target = root / SCENE / "results" / "none" / "T.tiff"
    target.unlink()
    target.mkdir()
    before = Scene(root / SCENE).load(verify=False)
    with pytest.raises(DatasetError, match=r"T\.tiff is a folder, not a file.*Nothing was changed.*remove it"):
        separate_again(root)
    assert Scene(root / SCENE).load(verify=False) == before
    assert not list((root / SCENE).glob(".staging-*"))


def stop_a_swap(root, monkeypatch) -> None:
    """Separate scene_01 again with the swap's second placing failing: the new outputs are
    recorded but not all put in place."""
    real_place, calls = swap_module._place, []

    def place_failing_the_second_file(source, target):
        calls.append(target)
        if len(calls) == 2:
            raise IsADirectoryError(21, "Is a directory")
        real_place(source, target)

    monkeypatch.setattr(swap_module, "_place", place_failing_the_second_file)
    with pytest.raises(DatasetError, match="cannot be put in place"):
        separate_again(root)
    monkeypatch.undo()


def test_a_swap_a_failure_left_is_named_by_the_report_and_recovered_without_link_files(base, tmp_path, monkeypatch):
    """The recorded outputs are whole (verify finds nothing wrong); the report says they wait to be
    put in place, and the next command that writes does it, leaving no temporary link."""
    root = shutil.copytree(base, tmp_path / "ds")
    stop_a_swap(root, monkeypatch)
    assert verify(root) == {SCENE: []}
    text = report_text(root)
    assert "not put in place" in text and f"urd ingest {root}" in text
    with Dataset.open(root).lock():                                  # the recovery finishes the swap
        pass
    assert verify(root) == {SCENE: []}
    assert not [p.name for p in (root / SCENE).rglob(".*") if p.name.endswith(".link")]


def test_separating_again_after_a_stopped_swap_finishes_it_before_saying_the_results_exist(base, tmp_path, monkeypatch):
    root = shutil.copytree(base, tmp_path / "ds")
    stop_a_swap(root, monkeypatch)
    assert Scene(root / SCENE).unfinished_swap() is not None
    out = invoke("separate", SCENE, "--dataset", root, "--method", "none")
    assert out.exit_code == 1 and "already has none results" in out.output, out.output
    assert Scene(root / SCENE).unfinished_swap() is None                    # put in place by the refused command
    assert not list((root / SCENE).glob(".staging-*")) and verify(root) == {SCENE: []}


def test_the_shot_count_is_worded_for_none_and_one():
    assert SceneStatus(SCENE, "incomplete", 0, 3, [], []).describe() == (
        "scene_01: 0 shots, INCOMPLETE (0 of 3 shots; resume the capture), nominal angles, no results")
    assert SceneStatus(SCENE, "incomplete", 1, 3, [0.0], []).describe().startswith(
        "scene_01: 1 shot at 0 deg, INCOMPLETE (1 of 3 shots;")


def test_the_report_says_a_stopped_capture_lost_the_ground_truth(base, tmp_path):
    root = shutil.copytree(base, tmp_path / "ds")
    (root / SCENE / "truth").rename(root / SCENE / "truth-incomplete-1")    # what the recovery does
    text = report_text(root)
    assert "no ground truth" in text and "truth-incomplete-1" in text


def test_separate_all_names_a_scene_folder_renamed_by_hand(base, tmp_path):
    root = shutil.copytree(base, tmp_path / "ds")
    shutil.copytree(root / SCENE, root / "kitchen")
    out = invoke("separate", "--all", "--dataset", root, "--method", "none", "--force")
    assert out.exit_code == 0, out.output
    assert "kitchen: holds a scene.json but is not named scene_NN" in out.output


def test_a_link_to_a_scene_is_named_as_one_by_separate_and_verify(base, tmp_path):
    link = tmp_path / "link"
    link.symlink_to(base / SCENE)
    for args in (("separate", link, "--method", "none"), ("verify", link)):
        out = invoke(*args)
        assert out.exit_code == 2, out.output
        assert f"is a symbolic link to the scene {(base / SCENE).resolve()}; give that folder itself" in " ".join(out.output.split())


def test_the_status_says_when_the_stacks_angles_turned_with_the_camera():
    turned = SceneStatus(SCENE, "ingested", 3, 3, [0.0, 45.0, 90.0], [], turned_deg=0.36).describe()
    assert "3 shots at 0,45,90 deg, aligned, the stage's angles turned with the camera by up to 0.36 deg" in turned
    assert "nominal angles" in SceneStatus(SCENE, "ingested", 3, 3, [0.0, 45.0, 90.0], [], turned_deg=0.001).describe()
