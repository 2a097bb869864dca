"""Where the network runs (--device auto|cpu|cuda): the choice, its refusal and the GPU tile,
checked on the CPU (torch's view of CUDA patched where a GPU is needed)."""

import pytest
import torch
from typer.testing import CliRunner

from separate import precision
from separate.infer import FP32_TILE, MODULE_TILE, FusedNet, default_tile, load_model, runner
from separate.tiling import TILE
from separate.precision import Device, gpu_tile, resolve_device
from urd.cli import app


@pytest.mark.parametrize("cuda,choice,expected", [
    (False, "auto", "cpu"), (True, "auto", "cuda"), (True, "cpu", "cpu"), (False, "cpu", "cpu"), (True, "cuda", "cuda"),
    (True, Device.AUTO, "cuda"),
], ids=["no-cuda-auto", "cuda-auto", "cuda-cpu", "no-cuda-cpu", "cuda-cuda", "cuda-Device.AUTO"])
def test_auto_takes_cuda_only_where_torch_sees_it(monkeypatch, cuda, choice, expected):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: cuda)
    assert resolve_device(choice) == torch.device(expected)


def test_cuda_without_cuda_and_unknown_names_are_refused(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match=r"device 'cuda': torch .* sees no CUDA device; use device 'cpu'"):
        resolve_device("cuda")
    with pytest.raises(ValueError, match="expected device auto, cpu or cuda, got 'gpu'"):
        resolve_device("gpu")


def test_gpu_tile_grows_with_free_memory_and_precision():
    tiles = [gpu_tile(free, bf16=False) for free in (2 * 2**30, 16 * 2**30, 80 * 2**30)]
    assert tiles == sorted(tiles) and all(t % 8 == 0 for t in tiles)
    assert tiles[0] ** 2 * precision.MODULE_BYTES_PER_PIXEL <= precision.GPU_MEMORY_SHARE * 2 * 2**30
    assert gpu_tile(16 * 2**30, bf16=True) > tiles[1]
    assert gpu_tile(10**15, bf16=True) == precision.MAX_GPU_TILE


@pytest.mark.parametrize("fused", [True, False], ids=["oneDNN", "without-oneDNN"])
def test_the_cpu_path_is_unchanged(monkeypatch, fused):
    if fused and not FusedNet.available():
        pytest.skip("this torch has no oneDNN fused convolutions")
    monkeypatch.setattr(FusedNet, "available", staticmethod(lambda: fused))
    model, _ = load_model()
    run = runner(model, "fp32", torch.device("cpu"))
    if fused:
        assert isinstance(run, FusedNet)
        assert default_tile(model, "cpu", "bf16") == TILE and default_tile(model, "cpu", "fp32") == FP32_TILE < TILE
    else:
        assert not isinstance(run, FusedNet)
        assert default_tile(model, "cpu", "bf16") == default_tile(model, "cpu", "fp32") == MODULE_TILE
        obs = torch.rand(1, 3, 3, 32, 32)
        r_hat, t_hat = run(obs, [0.0, 45.0, 90.0], torch.ones(1), torch.full((1,), 0.87))
        assert r_hat.shape == t_hat.shape == (1, 3, 32, 32) and r_hat.dtype == torch.float32


def test_cli_device_cuda_without_cuda_exits_2_naming_the_way_out(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    for k in range(3):
        (tmp_path / f"shot_{k}.tiff").write_bytes(b"")                   # refused before they are read
    shots = [arg for k in range(3) for arg in ("--images", str(tmp_path / f"shot_{k}.tiff"))]
    out = CliRunner().invoke(app, ["separate", *shots, "--out", str(tmp_path / "out"), "--device", "cuda"])
    assert out.exit_code == 2 and not (tmp_path / "out").exists()
    assert "Invalid value for '--device'" in out.output and "sees no CUDA device" in out.output and "use device 'cpu'" in out.output
    out = CliRunner().invoke(app, ["separate", "scene_01", "--dataset", str(tmp_path), "--method", "kong",
                                   "--device", "cpu"])
    assert out.exit_code == 2 and "--device" in out.output and "not kong" in out.output
