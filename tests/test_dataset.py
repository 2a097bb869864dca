"""Manifests: round trip, validation naming the field, hashes, atomic writes."""

import json
import os
import signal
import subprocess
import sys

import pytest

from urd.core import dataset, files
from urd.core.errors import DatasetError, ManifestError


def make_scene(tmp_path):
    ds = dataset.Dataset.open_or_create(tmp_path / "ds")
    scene = ds.new_scene("test", {"stage": {"kind": "ELL14", "port": "sim"}})
    (scene.path / "raw").mkdir()
    for i, angle in enumerate((0, 45, 90)):
        path = scene.path / "raw" / f"shot_{i:02d}.dng"
        files.write_bytes_atomic(path, bytes([i]) * 1000)
        scene.add_shot(i, path, angle, angle_measured_deg=angle + 0.01)
    return ds, scene, scene.load()


def test_manifest_round_trip(tmp_path):
    ds, scene, record = make_scene(tmp_path)
    assert ds.scene_names() == ["scene_01"]
    assert ds.scene("scene_01").load() == record
    assert ds.next_scene_name() == "scene_02"
    assert repr(ds) == f"Dataset({str(ds.root)!r})" and repr(scene) == f"Scene({str(scene.path)!r})"
    (ds.root / "scene_02").write_text("a stray file with a scene's name")
    assert ds.scene_names() == ["scene_01"] and ds.next_scene_name() == "scene_03"
    assert ds.new_scene("test", {}).path.name == "scene_03"


def test_corrupted_file_is_rejected_by_hash(tmp_path):
    _, scene, _ = make_scene(tmp_path)
    path = scene.path / "raw" / "shot_01.dng"
    data = bytearray(path.read_bytes())
    data[10] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(ManifestError, match="shot_01.dng.*SHA-256"):
        scene.load()


@pytest.mark.parametrize("field", ["name", "shots", "provenance"])
def test_missing_field_is_named(tmp_path, field):
    _, scene, record = make_scene(tmp_path)
    del record[field]
    scene.manifest_path.write_text(json.dumps(record))
    with pytest.raises(ManifestError, match=f"missing field '{field}'"):
        scene.load()


def test_missing_shot_field_is_named_with_its_index(tmp_path):
    _, scene, record = make_scene(tmp_path)
    del record["shots"][2]["sha256"]
    scene.manifest_path.write_text(json.dumps(record))
    with pytest.raises(ManifestError, match=r"shots\[2\]: missing field 'sha256'"):
        scene.load()


def test_wrong_type_and_schema_are_named(tmp_path):
    _, scene, record = make_scene(tmp_path)
    record["shots"][0]["size"] = "big"
    scene.manifest_path.write_text(json.dumps(record))
    with pytest.raises(ManifestError, match=r"shots\[0\]: field 'size'"):
        scene.load()
    record["shots"][0]["size"] = 1000
    record["schema"] = "other"
    scene.manifest_path.write_text(json.dumps(record))
    with pytest.raises(ManifestError, match="field 'schema'"):
        scene.load()


def test_scene_folders_are_never_reused(tmp_path):
    ds, scene, _ = make_scene(tmp_path)
    with pytest.raises(DatasetError, match="already exists"):
        ds.new_scene("test", {}, "scene_01")
    with pytest.raises(DatasetError, match="no scene 'scene_07'"):
        ds.scene("scene_07")


def test_no_silent_overwrite(tmp_path):
    path = tmp_path / "a.bin"
    files.write_bytes_atomic(path, b"one")
    with pytest.raises(DatasetError, match="refusing to overwrite"):
        files.write_bytes_atomic(path, b"two")
    assert path.read_bytes() == b"one"


def test_interrupted_write_leaves_old_manifest_intact(tmp_path):
    path = tmp_path / "scene.json"
    files.write_json_atomic(path, {"version": "old"})
    # A child process starts writing a large manifest and is killed mid-write.
    code = (
        "import sys, urd.core.files as f, pathlib, time\n"
        "p = pathlib.Path(sys.argv[1])\n"
        "with f.atomic_path(p, overwrite=True) as tmp:\n"
        "    with open(tmp, 'w') as fh:\n"
        "        fh.write('{\"version\": \"new\", \"pad\": \"' + 'x' * 100000)\n"
        "        fh.flush()\n"
        "        print('writing', flush=True)\n"
        "        time.sleep(30)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", code, str(path)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "writing"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert json.loads(path.read_text()) == {"version": "old"}
    # the exception path cleans its temporary file
    with pytest.raises(RuntimeError):
        with files.atomic_path(path, overwrite=True) as tmp:
            tmp.write_text("partial")
            raise RuntimeError("boom")
    assert json.loads(path.read_text()) == {"version": "old"}
    assert not [p for p in tmp_path.iterdir() if "tmp" in p.name and p.stat().st_size == len("partial")]


def test_a_writer_failing_without_an_errno_on_a_full_disk_is_a_disk_full_error(tmp_path, monkeypatch):
    from urd.core.errors import DiskFullError

    path = tmp_path / "last.pt"
    monkeypatch.setattr(files, "MIN_FREE_BYTES", 1 << 62)          # the disk as good as full
    with pytest.raises(DiskFullError, match=r"disk full: .*last.pt \(nothing was changed"):
        with files.atomic_path(path) as tmp:
            tmp.write_bytes(b"part")
            raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 817664 vs 817552")   # torch.save
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_an_aligned_shot_replaced_by_a_compressed_file_is_refused_before_its_pixels_are_allocated(tmp_path_factory):
    import numpy as np
    import tifffile

    from conftest import ingested_dataset

    scene = dataset.Dataset.open(ingested_dataset(tmp_path_factory, "bomb")).scene("scene_01")
    path = scene.path / "aligned" / "shot_01.tiff"
    tifffile.imwrite(path, np.zeros((4000, 6000, 3), np.uint16), photometric="rgb", compression="zlib")
    record = scene.load()                                   # the manifest made to name the new file, as a hostile one would
    for rec in record["ingest"]["aligned"]:
        if rec["file"] == "aligned/shot_01.tiff":
            rec.update(size=path.stat().st_size, sha256=files.sha256_file(path))
    files.write_json_atomic(scene.manifest_path, record)
    with pytest.raises(DatasetError, match=r"shot_01.tiff: not an image as urd writes them .*compression (zlib|adobe_deflate)"):
        scene.reload().load_stack()


@pytest.mark.parametrize("replacement", ["float32", "smaller"])
def test_an_aligned_stack_of_mixed_images_is_refused_by_name(tmp_path_factory, replacement):
    import numpy as np
    import tifffile

    from conftest import ingested_dataset

    scene = dataset.Dataset.open(ingested_dataset(tmp_path_factory, f"mixed-{replacement}")).scene("scene_01")
    codes, _ = scene.load_stack(codes=True)
    path = scene.path / "aligned" / "shot_01.tiff"
    shot = codes[1].astype(np.float32) if replacement == "float32" else codes[1, :-8]
    tifffile.imwrite(path, shot, photometric="rgb")
    record = scene.load()                                   # the manifest made to name the new file, as if urd wrote it
    for rec in record["ingest"]["aligned"]:
        if rec["file"] == "aligned/shot_01.tiff":
            rec.update(size=path.stat().st_size, sha256=files.sha256_file(path))
    files.write_json_atomic(scene.manifest_path, record)
    with pytest.raises(DatasetError, match="not one stack of 16-bit images of one size.*--redo"):
        scene.reload().load_stack(codes=True)
