"""A dataset from someone else (docs/dataset.md, "Threat model"): symbolic and hard links in it
make no command write, empty or delete anything outside it; an --out inside a dataset is
refused; a killed batch command leaves no worker alive and nothing written after it."""

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from rig import capture_virtual, separated_virtual_scene
from conftest import stop_capture_before_shot
from urd.cli import app
from urd.core.dataset import Dataset
from urd.core.errors import DatasetError
from urd.core.files import atomic_path

SIM = ("--stage", "sim", "--camera", "virtual", "--sim-size", "96x64")
LINKED = "is a symbolic link"


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def urd(*args):
    return subprocess.run([sys.executable, "-m", "urd.cli", *map(str, args)], capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """scene_01 ingested with results of 'none' and ground truth; scene_02 captured, not ingested."""
    ds = Dataset.open_or_create(tmp_path_factory.mktemp("base") / "ds")
    separated_virtual_scene(ds)
    capture_virtual(ds, size=(96, 64), shake_px=1.0, shake_deg=0.1, seed=2)
    other, _ = capture_virtual(Dataset.open_or_create(ds.root.parent / "other"), size=(96, 64), shake_px=1.0,
                               shake_deg=0.1, seed=3)
    shutil.copytree(other.path / "raw", ds.root.parent / "new_raw")              # RAW files the dataset has not
    return ds.root


def snapshot(folder):
    """Every file below ``folder`` (links not followed) → its bytes, every link → its target."""
    files = {}
    for parent, folders, names in os.walk(folder):
        for name in folders + names:
            path = os.path.join(parent, name)
            if os.path.islink(path):
                files[path] = ("link", os.readlink(path))
            elif os.path.isfile(path):
                with open(path, "rb") as fh:
                    files[path] = fh.read()
    return files


def outside_folder(tmp_path):
    """A folder outside the dataset holding a file someone cares about and a hidden one."""
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "authorized_keys").write_bytes(b"ssh-ed25519 AAAA keep me\n")
    (outside / ".secret").write_bytes(b"hidden, keep me too\n")
    return outside


def move_out(folder, outside):
    """Move ``folder`` (of the dataset) outside, with a hidden file beside its files, and leave a link to it."""
    target = outside / folder.name
    shutil.move(folder, target)
    (target / ".secret").write_bytes(b"hidden, keep me\n")
    folder.symlink_to(target, target_is_directory=True)
    return folder


#: Links someone else's dataset may hold: kind → (the link, in the dataset; its target in the
#: outside folder, or None: the dataset's folder itself moved outside).
LINKS = {
    "lock": (".urd.lock", "authorized_keys"),
    "dangling lock": (".urd.lock", "created"),
    "temp file": ("scene_01/aligned/.shot_00.tmp.tiff", "authorized_keys"),
    "scene staging folder": ("scene_01/.staging-x", "."),
    "dataset staging folder": (".staging-x", "."),
    "raw": ("scene_01/raw", None),
    "aligned": ("scene_01/aligned", None),
    "results": ("scene_01/results", None),
    "truth": ("scene_01/truth", None),
}
DATASET_WIDE = ("lock", "dangling lock", "dataset staging folder")


def make_link(root, outside, kind):
    """The link ``kind`` (`LINKS`) in the dataset at ``root``; returns its path."""
    name, target = LINKS[kind]
    if target is None:
        return move_out(root / name, outside)
    (root / name).symlink_to(outside / target)
    return root / name


#: Commands (their arguments after the dataset folder's path is put in for ROOT) and whether they
#: write into scene_01, and so must refuse its links by name.
COMMANDS = {
    "capture new": (("capture", "ROOT", *SIM, "--new-scene", "--angles", "0,60,120"), False),
    "ingest new": (("ingest", "RAW", "ROOT"), False),
    "ingest captured": (("ingest", "ROOT/scene_02"), False),
    "ingest --redo": (("ingest", "ROOT/scene_01", "--redo"), True),
    "separate --force": (("separate", "scene_01", "--dataset", "ROOT", "--method", "none", "--force"), True),
    "calibrate": (("calibrate", "offset", "ROOT", "--stage", "sim", "--camera", "virtual", "--step", "45"), False),
    "verify": (("verify", "ROOT"), True),
}
SLOW_COMMANDS = {
    "ingest --jobs": (("ingest", "ROOT", "--redo", "--jobs", "2"), True),
    "separate --all --jobs": (("separate", "--all", "--jobs", "2", "--force", "--method", "none", "--dataset", "ROOT"), True),
}


def hostile(base, tmp_path, kind):
    """A copy of the base dataset with the link ``kind``; (its root, the outside folder, the link)."""
    root = tmp_path / "ds"
    shutil.copytree(base, root, symlinks=True)
    (root / ".urd.lock").unlink(missing_ok=True)
    outside = outside_folder(tmp_path)
    return root, outside, make_link(root, outside, kind)


def check_refused_or_harmless(base, tmp_path, kind, command, in_process):
    root, outside, link = hostile(base, tmp_path, kind)
    before = snapshot(outside)
    args, writes_scene = command
    args = [str(a).replace("ROOT", str(root)).replace("RAW", str(base.parent / "new_raw")) for a in args]
    if in_process:
        out = invoke(*args)
        code, text = out.exit_code, out.output
    else:
        out = urd(*args)
        code, text = out.returncode, out.stdout + out.stderr
    assert snapshot(outside) == before, text
    assert not (outside / "created").exists()
    if kind in DATASET_WIDE and args[0] != "verify" or kind not in DATASET_WIDE and writes_scene:
        assert code != 0 and f"{link} {LINKED}" in text, text
    return root, text


@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("kind", LINKS)
def test_a_link_in_a_dataset_leaves_the_outside_byte_identical(base, tmp_path, kind, command):
    check_refused_or_harmless(base, tmp_path, kind, COMMANDS[command], in_process=True)


@pytest.mark.slow
@pytest.mark.parametrize("command", SLOW_COMMANDS)
@pytest.mark.parametrize("kind", ["lock", "temp file", "aligned", "results"])
def test_a_link_in_a_dataset_leaves_the_outside_byte_identical_with_worker_processes(base, tmp_path, kind, command):
    check_refused_or_harmless(base, tmp_path, kind, SLOW_COMMANDS[command], in_process=False)


def test_a_hard_linked_lock_or_a_fifo_is_refused_naming_the_file(base, tmp_path):
    root = tmp_path / "ds"
    shutil.copytree(base, root, symlinks=True)
    outside = outside_folder(tmp_path)
    before = snapshot(outside)
    (root / ".urd.lock").unlink(missing_ok=True)
    os.link(outside / "authorized_keys", root / ".urd.lock")
    out = invoke("separate", "scene_01", "--dataset", root, "--method", "none", "--force")
    assert out.exit_code == 1 and f"{root / '.urd.lock'} has other hard links" in out.output, out.output
    assert snapshot(outside) == before
    (root / ".urd.lock").unlink()
    os.mkfifo(root / ".urd.lock")
    out = invoke("separate", "scene_01", "--dataset", root, "--method", "none", "--force")
    assert out.exit_code == 1 and f"{root / '.urd.lock'} is not a regular file" in out.output, out.output
    assert "Errno" not in out.output


def interrupted_capture(root, monkeypatch):
    """A capture at 96×64 stopped (Ctrl-C) before its second shot."""
    stop_capture_before_shot(monkeypatch)
    out = invoke("capture", root, *SIM, "--seed", "3", "--angles", "0,60,120")
    monkeypatch.undo()
    assert out.exit_code == 130, out.output


@pytest.mark.parametrize("kind", ["lock", "dangling lock", "temp file", "scene staging folder", "dataset staging folder",
                                  "raw", "aligned", "truth"])
def test_resuming_a_capture_writes_and_deletes_nothing_outside_through_a_link(tmp_path, monkeypatch, kind):
    root = tmp_path / "ds"
    interrupted_capture(root, monkeypatch)
    outside = outside_folder(tmp_path)
    for folder in ("aligned", "truth"):
        (root / "scene_01" / folder).mkdir(exist_ok=True)
    (root / ".urd.lock").unlink()
    link = make_link(root, outside, kind)
    before = snapshot(outside)
    resume = ("capture", root, *SIM, "--seed", "3", "--angles", "0,60,120", "--scene", "scene_01")
    out = invoke(*resume)
    assert out.exit_code == 1 and f"{link} {LINKED}" in out.output, out.output
    assert snapshot(outside) == before and not (outside / "created").exists()
    link.unlink()
    if LINKS[kind][1] is None:
        shutil.move(outside / link.name, link)
    shutil.rmtree(root / "scene_01" / "truth")
    out = invoke(*resume)
    assert out.exit_code == 0, out.output
    assert Dataset.open(root).scene("scene_01").verify() == []


def test_a_linked_scene_folder_is_neither_written_nor_recovered_through(base, tmp_path):
    root = tmp_path / "ds"
    shutil.copytree(base, root, symlinks=True)
    outside = outside_folder(tmp_path)
    shutil.move(root / "scene_01", outside / "scene_01")
    (outside / "scene_01/aligned/.shot_01.tmp.tiff").write_bytes(b"a leftover temp file, outside")
    (root / "scene_01").symlink_to(outside / "scene_01", target_is_directory=True)
    before = snapshot(outside)
    out = invoke("separate", "scene_01", "--dataset", root, "--method", "none", "--force")
    assert out.exit_code == 1 and f"{root / 'scene_01'} {LINKED}" in out.output, out.output
    out = invoke("verify", root)
    assert out.exit_code == 1 and f"{root / 'scene_01'} {LINKED}" in out.output, out.output
    assert snapshot(outside) == before


def test_an_out_folder_inside_a_dataset_is_refused_naming_the_dataset_and_the_command(base, tmp_path):
    root = tmp_path / "ds"
    shutil.copytree(base, root, symlinks=True)
    before = snapshot(root)
    images = sorted((root / "scene_01/aligned").glob("*.tiff"))
    args = [a for path in images for a in ("--images", path)]
    out = invoke("separate", *args, "--angles", "0,45,90", "--method", "none", "--force",
                 "--out", root / "scene_01/results/none")
    assert out.exit_code == 2, out.output
    assert str(root) in out.output and "urd separate scene_01 --dataset" in out.output
    assert snapshot(root) == before
    out = invoke("verify", root)
    assert out.exit_code == 0, out.output


def test_one_pixel_images_are_refused_with_a_clear_message(tmp_path):
    import numpy as np
    import tifffile

    paths = []
    for i in range(3):
        paths.append(tmp_path / f"p{i}.tiff")
        tifffile.imwrite(paths[-1], np.full((1, 1, 3), 1000 * (i + 1), np.uint16), photometric="rgb")
    out = invoke("separate", *[a for p in paths for a in ("--images", p)], "--method", "none", "--out", tmp_path / "out")
    assert out.exit_code == 1 and "1×1" in out.output and "gradient" not in out.output, out.output


def test_a_full_disk_is_said_as_such_naming_the_file(tmp_path, monkeypatch):
    import errno

    target = tmp_path / "R.tiff"
    with pytest.raises(DatasetError, match=f"disk full: {target}"):
        with atomic_path(target) as tmp:
            raise OSError(errno.ENOSPC, "No space left on device", str(tmp))
    short = OSError("147456 requested and 20344 written")
    monkeypatch.setattr(os, "statvfs", lambda _: os.statvfs_result((4096,) * 3 + (0, 0) + (0,) * 5))
    with pytest.raises(DatasetError, match=f"disk full: {target}"):
        with atomic_path(target):
            raise short
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------- a killed command stops whole

SLOWED = '''"""urd's command line with every worker's output writes delayed by {delay} s (a slow scene)."""
import time

import urd.ingest
import urd.separation


def slowed(write):
    def slow(*args, **kwargs):
        time.sleep({delay})
        return write(*args, **kwargs)
    return slow


urd.separation.write_results = slowed(urd.separation.write_results)
urd.ingest.write_aligned = slowed(urd.ingest.write_aligned)

if __name__ == "__main__":
    from urd.cli import main

    main()
'''
DELAY_S = 2


def children(pid):
    """Every live descendant of ``pid`` (from /proc)."""
    parents = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as fh:
                    fields = fh.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            parents.setdefault(int(fields[1]), []).append(int(entry))
    result, pending = [], list(parents.get(pid, []))
    while pending:
        child = pending.pop()
        result.append(child)
        pending += parents.get(child, [])
    return result


def alive(pid):
    """Whether ``pid`` runs (a zombie nobody reaped does not)."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def tree(root):
    """Every path below ``root`` with its size and modification time (ns)."""
    return {path: (path.stat().st_size, path.stat().st_mtime_ns) if path.is_file() else None
            for path in sorted(root.rglob("*"))}


def wait_for(condition, what, limit_s=300):
    import time

    for _ in range(int(limit_s * 10)):
        if condition():
            return
        time.sleep(0.1)
    raise AssertionError(f"gave up waiting for {what}")


@pytest.fixture
def two_scenes(tmp_path):
    """A dataset of two ingested scenes (96×64) with results of 'none'."""
    ds = Dataset.open_or_create(tmp_path / "ds")
    for seed in (1, 2):
        separated_virtual_scene(ds, seed)
    return ds.root


KILLED = {
    "separate --all --jobs 2": ("separate", "--all", "--jobs", "2", "--force", "--method", "none", "--dataset"),
    "ingest --jobs 2": ("ingest", "--redo", "--jobs", "2"),
}


@pytest.mark.slow
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGKILL], ids=["SIGTERM", "SIGKILL"])
@pytest.mark.parametrize("command", KILLED)
def test_a_killed_batch_leaves_no_process_and_no_late_write_and_the_next_run_completes(two_scenes, tmp_path, command,
                                                                                         signum):
    import time

    script = tmp_path / "slowed_urd.py"
    script.write_text(SLOWED.format(delay=DELAY_S))
    args = [*KILLED[command], two_scenes] if command.startswith("separate") else [*KILLED[command][:1], two_scenes,
                                                                                   *KILLED[command][1:]]
    log = tmp_path / "stderr.txt"
    with open(log, "w") as stderr:                            # not a pipe: a surviving worker would hold it open
        main = subprocess.Popen([sys.executable, script, *map(str, args)], stdout=subprocess.DEVNULL, stderr=stderr)
    workers = []
    try:
        wait_for(lambda: list(two_scenes.glob("scene_*/.staging-*")) or main.poll() is not None, "a worker's staging folder")
        assert main.poll() is None, log.read_text()
        workers = children(main.pid)
        assert len(workers) >= 2, workers                     # two workers (and multiprocessing's resource tracker)
        main.send_signal(signum)
        main.wait(timeout=5)
        wait_for(lambda: not any(alive(pid) for pid in workers), "the workers to end", limit_s=5)
    finally:
        for pid in [main.pid, *workers]:                      # nothing left behind should the test fail
            if alive(pid):
                os.kill(pid, signal.SIGKILL)
        main.wait()
    stderr = log.read_text()
    if signum == signal.SIGTERM:
        assert main.returncode == 143 and "stopped by SIGTERM" in stderr and "run the same command again" in stderr, stderr
    settled = tree(two_scenes)
    time.sleep(DELAY_S + 1)                                   # a surviving worker would write by now
    assert tree(two_scenes) == settled
    plain = [str(a) for a in args if a not in ("--jobs", "2")]
    out = invoke(*plain)
    assert out.exit_code == 0, out.output
    assert not list(two_scenes.glob("**/.staging-*"))
    assert invoke("verify", two_scenes).exit_code == 0


def test_verify_during_a_swap_checks_the_new_manifest_again(base, tmp_path, monkeypatch):
    import urd.core.shots as shots_module

    root = tmp_path / "ds"
    shutil.copytree(base, root, symlinks=True)
    writer = Dataset.open(root).scene("scene_01")
    entry = {k: v for k, v in writer.load(verify=False)["results"]["none"].items() if k not in ("files", "time", "method")}
    layers = {name: (root / "scene_01/results/none" / name).read_bytes() for name in ("R.tiff", "T.tiff")}
    staged = {}
    for name, other in (("R.tiff", "T.tiff"), ("T.tiff", "R.tiff")):            # the layers' bytes swapped
        staged[f"results/none/{name}"] = root / "scene_01" / f"new_{name}"
        staged[f"results/none/{name}"].write_bytes(layers[other])
    real_hash, swapped = shots_module._hash, []

    def hash_while_another_command_swaps(*args, **kwargs):
        if not swapped:
            swapped.append(writer.add_result("none", staged, entry, replace=True))
        return real_hash(*args, **kwargs)

    monkeypatch.setattr(shots_module, "_hash", hash_while_another_command_swaps)
    assert Dataset.open(root).scene("scene_01").verify() == []
    assert swapped and (root / "scene_01/results/none/R.tiff").read_bytes() == layers["T.tiff"]
    assert not (root / "scene_01/results/none/T_preview.png").exists()


def test_a_hard_link_in_a_scene_is_replaced_never_written_through(base, tmp_path):
    root = tmp_path / "ds"
    shutil.copytree(base, root, symlinks=True)
    outside = outside_folder(tmp_path)
    for name in ("scene_01/aligned/shot_00.tiff", "scene_01/results/none/T.tiff", "scene_01/scene.json"):
        shutil.copy(root / name, outside / Path(name).name)
        (root / name).unlink()
        os.link(outside / Path(name).name, root / name)
    before = snapshot(outside)
    assert invoke("ingest", root / "scene_01", "--redo").exit_code == 0
    assert invoke("separate", "scene_01", "--dataset", root, "--method", "none", "--force").exit_code == 0
    assert snapshot(outside) == before
    assert invoke("verify", root).exit_code == 0


@pytest.mark.parametrize("damage", ["{not json", '{"schema_version": 1, "shots": 7}'])
def test_maps_asked_of_a_scene_whose_manifest_is_damaged_is_one_error_line(tmp_path, damage):
    """``urd separate SCENE --maps`` reads the scene's results before anything else: a damaged
    scene.json is exit 1 with urd's message, not a traceback."""
    ds = Dataset.open_or_create(tmp_path / "ds")
    scene = separated_virtual_scene(ds)
    (scene.path / "scene.json").write_text(damage)
    result = CliRunner().invoke(app, ["separate", scene.name, "--dataset", str(ds.root), "--maps", "--method", "none"])
    assert result.exit_code == 1, result.output
    assert isinstance(result.exception, SystemExit)
    assert result.output.startswith("Error: ") and "scene.json" in result.output


@pytest.mark.parametrize("edit, named", [
    (lambda entry: entry.update(files=[f for f in entry["files"] if not f["file"].endswith("/R.tiff")]), "missing R.tiff"),
    (lambda entry: entry.update(warnings=5), "field 'warnings' has type int"),
    (lambda entry: entry.update(reference_deg="abc"), "field 'reference_deg' has type str"),
])
def test_a_results_record_edited_out_of_shape_is_a_broken_scene_in_reports(tmp_path, edit, named):
    """Results records are checked as the rest of a manifest: one edited out of shape makes the
    scene BROKEN, named, in `urd report` (text and HTML) and `urd verify`, not a traceback."""
    import json

    ds = Dataset.open_or_create(tmp_path / "ds")
    scene = separated_virtual_scene(ds)
    record = json.loads((scene.path / "scene.json").read_text())
    edit(record["results"]["none"])
    (scene.path / "scene.json").write_text(json.dumps(record))
    for args in (["report", str(ds.root)], ["report", str(ds.root), "--html", str(tmp_path / "report")], ["verify", str(ds.root)]):
        result = CliRunner().invoke(app, args)
        assert result.exception is None or isinstance(result.exception, SystemExit), (args, result.output)
        assert named in " ".join(result.output.split()), (args, result.output)
