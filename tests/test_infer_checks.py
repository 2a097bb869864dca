"""separate.infer: tile and overlap checks, tiling at the default tile size, the fused network."""

import os
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from separate import infer
from separate.infer import STRIP_ROWS, FusedNet, load_model, runner, separate_stack, shipped_weights
from separate.tiling import OVERLAP, TILE, tile_spans
from separate.model import FresnelGate, ResizeUp, SeparationNet
from separate.networks import build_model
from urd.core.errors import WeightsError

SMALL = np.random.default_rng(0).random((3, 40, 48, 3)).astype(np.float32)


@pytest.mark.parametrize("tile,overlap,message", [
    (64, 16, "expected a tile of at least 128 px"),
    (0, 0, "expected a tile of at least 128 px"),
    (-256, 0, "expected a tile of at least 128 px"),
    (300, 160, r"expected a tile of at least 320 px .* got 300"),
    (143, 70, r"expected a tile of at least 140 px .*multiple of 8\), got 143"),   # 136 after rounding, < 2 × 70
    (512, -1, "expected an overlap of at least 0 px, got -1"),
])
def test_bad_tile_or_overlap_is_a_value_error(tile, overlap, message):
    model, _ = load_model()
    with pytest.raises(ValueError, match=message):
        separate_stack(model, SMALL, [0, 45, 90], tile=tile, overlap=overlap, precision="fp32")


def test_non_integer_tile_is_a_type_error():
    model, _ = load_model()
    with pytest.raises(TypeError, match="expected integer tile and overlap"):
        separate_stack(model, SMALL, [0, 45, 90], tile=512.5, precision="fp32")


@pytest.mark.slow
def test_smallest_tile_and_no_overlap_are_accepted():
    model, _ = load_model()
    stack = np.random.default_rng(1).random((3, 300, 280, 3)).astype(np.float32) * 0.5
    for tile, overlap in ((128, 64), (128, 0), (131, 0)):
        r_hat, t_hat = separate_stack(model, stack, [0, 45, 90], tile=tile, overlap=overlap, precision="fp32")
        assert r_hat.shape == t_hat.shape == stack.shape[1:] and np.isfinite(r_hat).all() and np.isfinite(t_hat).all()


@pytest.mark.slow
def test_tiled_matches_whole_image():
    # 776 × 781 px takes 2 × 2 tiles of 512 px with the default overlap (the last column not on
    # the 8-px grid: padded). Measured: 3.9e-5 apart (128 px overlap: 1.1e-3, over the bound).
    # The 24 MP default tiling is 4 × 3 tiles.
    from acquire.virtual_camera import make_glass_scene

    h, w = 776, 781
    assert len(tile_spans(h, 512, OVERLAP)) == len(tile_spans(w, 512, OVERLAP)) == 2
    assert len(tile_spans(6000, TILE, OVERLAP)) == 4 and len(tile_spans(4000, TILE, OVERLAP)) == 3
    model, _ = load_model()
    scene = make_glass_scene(w + 1, h)                                 # the virtual camera's sizes are even
    stack = np.stack([scene.render(np.radians(a))[:, :w] * 0.6 for a in (0, 45, 90)]).astype(np.float32)
    r_whole, t_whole = separate_stack(model, stack, [0, 45, 90], tile=784, precision="fp32")
    r_tiled, t_tiled = separate_stack(model, stack, [0, 45, 90], tile=512, precision="fp32")
    assert max(np.abs(r_whole - r_tiled).max(), np.abs(t_whole - t_tiled).max()) < 1e-3


@pytest.mark.parametrize("strip_rows", [STRIP_ROWS, 16])
@pytest.mark.parametrize("variant", ["resize", "transposed", "direct"])
def test_fused_network_matches_the_module(variant, strip_rows):
    # FusedNet repeats SeparationNet.forward with oneDNN's fused convolutions: it must give the same
    # numbers (measured: 8e-7 in fp32 with the shipped weights), at an odd size and with four shots;
    # "resize": the shipped weights (decoder up-sampling bilinear, ResizeUp); "transposed": the
    # paper's decoder (urd-canonical-transposed); 16 strip rows: the 64 padded rows run as 4 strips
    # at full resolution, 4, 2 and 1 below
    torch.manual_seed(0)
    if variant == "direct":
        model = SeparationNet(width=8, variant="direct").eval()
    else:
        model = load_model("urd-canonical" if variant == "resize" else "urd-canonical-transposed")[0]
        assert isinstance(model.up[0], ResizeUp) == (variant == "resize")
    obs = torch.rand(1, 4, 3, 61, 83)
    angles = list(np.radians([10, 55, 100, 145]))
    scale = torch.tensor([0.4])
    with torch.inference_mode():
        expected = model(obs, angles, scale)
        fp32 = FusedNet(model, strip_rows=strip_rows)(obs, angles, scale)
        bf16 = FusedNet(model, torch.bfloat16, strip_rows)(obs, angles, scale)
    for want, got, rounded in zip(expected, fp32, bf16):
        assert got.shape == want.shape and got.dtype == torch.float32
        torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)
        assert (rounded - want).abs().max() < 0.03 * want.abs().max()   # bf16 rounding of the activations


@pytest.mark.parametrize("batch,theta_shape", [(1, (1,)), (2, (2,)), (2, (2, 1, 9, 11))])
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_gate_inputs_written_in_one_pass_are_the_concatenation(batch, theta_shape, dtype):
    # FusedNet asks for the gate's input in its own dtype and channels-last layout; it must be the
    # concatenation (T̂, S0, the three bands, θ/(π/2)) converted, value for value.
    gen = torch.Generator().manual_seed(batch)
    t_net, s0, *d_bands = (torch.rand((batch, 3, 9, 11), generator=gen) for _ in range(5))
    theta = torch.rand(theta_shape, generator=gen)
    reference = FresnelGate.inputs(t_net, s0, d_bands, theta).to(dtype, memory_format=torch.channels_last)
    one_pass = FresnelGate.inputs(t_net, s0, d_bands, theta, dtype)
    assert one_pass.shape == (batch, 16, 9, 11) and one_pass.dtype == dtype
    assert one_pass.is_contiguous(memory_format=torch.channels_last)
    assert torch.equal(one_pass, reference)
    expected = (theta.view(-1, 1, 1) if theta.ndim == 1 else theta[:, 0]) / (np.pi / 2)
    assert torch.equal(one_pass[:, -1], expected.expand(batch, 9, 11).to(dtype))


def test_shipped_weights_load_by_name():
    assert {"urd-canonical", "urd-canonical-transposed", "urd-direct", "ceilnet"} <= set(shipped_weights())
    model, info = load_model("urd-canonical-transposed")
    assert Path(info["file"]).name == "urd-canonical-transposed.pt" and not isinstance(model.up[0], ResizeUp)
    assert isinstance(load_model()[0].up[0], ResizeUp)                      # the default decoder resizes
    with pytest.raises(WeightsError, match="not found .*shipped: .*urd-canonical-transposed"):
        load_model("urd-canonical-nonexistent")


def test_a_small_file_naming_a_huge_network_is_refused_before_the_network_is_built(tmp_path, monkeypatch):
    import separate.infer as infer

    built = []
    monkeypatch.setattr(infer, "build_model", lambda config: built.append(config) or build_model(config))
    torch.save({"model": {}, "model_config": {"width": 700, "variant": "canonical", "channels": 3}}, tmp_path / "big.pt")
    with pytest.raises(WeightsError, match=r"big.pt is corrupt or does not fit the model: its tensors are not those "
                                           r"of the network its model_config names \(0 tensors for \d+; first difference: "):
        load_model(tmp_path / "big.pt")
    assert len(built) == 1                                  # on the meta device only: never with memory behind it
    model, _ = load_model("urd-canonical")
    torch.save({"model": model.state_dict(), "model_config": {**model.config(), "width": 24}}, tmp_path / "wide.pt")
    with pytest.raises(WeightsError, match="first difference: "):
        load_model(tmp_path / "wide.pt")


@pytest.mark.parametrize("weights", ["urd-canonical", "urd-anchored"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_strips_give_the_whole_tile_bit_for_bit(dtype, weights):
    # FusedNet's strips (_chain, and _anchor for the gate and its band blurs) read each strip with
    # the rows its operations reach: the result must not differ by a single bit from one strip
    # covering the tile, for a batch of two
    torch.manual_seed(1)
    model = load_model(weights)[0]
    obs = torch.rand(2, 3, 3, 93, 70)
    angles, scale = list(np.radians([0, 45, 90])), torch.tensor([0.3, 0.5])
    theta = {"theta": torch.linspace(0.6, 1.2, 93)[None, None, :, None].expand(2, 1, 93, 70)} if weights == "urd-anchored" else {}
    with torch.inference_mode():
        whole = FusedNet(model, dtype, strip_rows=1024)(obs, angles, scale, **theta)
        strips = FusedNet(model, dtype, strip_rows=24)(obs, angles, scale, **theta)      # 4, 4, 3 and 2 strips per level
    for a, b in zip(whole, strips):
        if weights == "urd-anchored":
            # the anchor's elementwise functions (sigmoid, the Fresnel terms) run over strips of other
            # lengths, whose vector loops end at other pixels: a few pixels differ by one float32
            # rounding (up to 6e-8 here); a strip reading wrong rows changes whole rows
            torch.testing.assert_close(a, b, rtol=0.0, atol=1e-6)
        else:
            assert torch.equal(a, b)


def test_runner_falls_back_to_the_module_for_other_networks():
    class Halves(torch.nn.Module):
        channels = 3

        def forward(self, obs, angles, scale):
            s0 = obs[:, 0] + obs[:, 2]
            return s0 / 2, s0 / 2

    run = runner(Halves(), "fp32")
    assert not isinstance(run, FusedNet)
    r_hat, t_hat = separate_stack(Halves(), SMALL, [0, 45, 90], precision="fp32")
    np.testing.assert_allclose(r_hat, (SMALL[0] + SMALL[2]) / 2, atol=1e-6)
    with pytest.raises(TypeError, match="expected a SeparationNet"):
        FusedNet(Halves())
    with pytest.raises(ValueError, match="strip_rows of at least 8"):
        FusedNet(SeparationNet(width=8), strip_rows=4)


def test_presenting_tile_by_tile_matches_presenting_the_stack():
    from separate.presentation import present

    model, _ = load_model()
    rng = np.random.default_rng(2)
    s0, dolp, aolp = rng.random((3, 200, 180, 3))                  # physical shots: none negative
    angles = [5.0, 50.0, 95.0, 140.0]
    stack = np.stack([s0 * (1 + dolp * np.cos(2 * (np.radians(a) - np.pi * aolp))) / 4 for a in angles]).astype(np.float32)
    shots, angles3 = present(stack, angles, 30.0)
    r_want, t_want = separate_stack(model, shots, angles3, tile=128, overlap=32, precision="fp32")
    r_got, t_got = separate_stack(model, stack, angles, tile=128, overlap=32, precision="fp32", reference_deg=30.0)
    # one exposure scale, from the shots as given: the same as from presented ones where nothing is clipped
    np.testing.assert_allclose(r_got, r_want, atol=1e-5)
    np.testing.assert_allclose(t_got, t_want, atol=1e-5)
    with pytest.raises(ValueError, match="expected a finite reference angle"):
        separate_stack(model, stack, angles, reference_deg=float("nan"))


@pytest.mark.slow
def test_codes_read_only_and_reversed_stacks_separate_as_their_float_values():
    model, _ = load_model()
    rng = np.random.default_rng(3)
    codes = rng.integers(0, 40000, (3, 160, 200, 3), dtype=np.uint16)
    floats = codes.astype(np.float32) / 65535
    r_want, t_want = separate_stack(model, floats, [0, 45, 90], tile=128, overlap=32, precision="fp32", reference_deg=20.0)
    read_only = codes.copy()
    read_only.flags.writeable = False
    reversed_rows = codes[:, ::-1].copy()[:, ::-1]               # the same values, negative row strides
    reversed_floats = floats[:, ::-1].copy()[:, ::-1]           # floats are wrapped, not converted: a copy is needed
    assert reversed_rows.strides[1] < 0 and reversed_floats.strides[1] < 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")                           # torch warns on a read-only array it would wrap
        big_endian = codes.astype(">u2")
    for stack in (codes, read_only, reversed_rows, reversed_floats, big_endian):
            r_got, t_got = separate_stack(model, stack, [0, 45, 90], tile=128, overlap=32, precision="fp32", reference_deg=20.0)
            np.testing.assert_allclose(r_got, r_want, atol=1e-5)
            np.testing.assert_allclose(t_got, t_want, atol=1e-5)
    # no reference: four shots passed on as they are, only scaled from codes
    four = rng.integers(0, 40000, (4, 96, 120, 3), dtype=np.uint16)
    got = separate_stack(model, four, [0, 45, 90, 135], tile=128, overlap=32, precision="fp32")
    want = separate_stack(model, four.astype(np.float32) / 65535, [0, 45, 90, 135], tile=128, overlap=32, precision="fp32")
    np.testing.assert_allclose(got, want, atol=1e-5)


def test_precision_auto_follows_what_the_hardware_runs(monkeypatch):
    from separate.precision import Precision, native_bf16, resolve

    monkeypatch.delenv("ONEDNN_MAX_CPU_ISA", raising=False)
    monkeypatch.delenv("DNNL_MAX_CPU_ISA", raising=False)
    monkeypatch.setattr(torch.cpu, "get_capabilities", lambda: {"avx2": True, "avx512_bf16": False, "amx_bf16": False})
    assert not native_bf16() and resolve("auto") is Precision.FP32 and resolve("bf16") is Precision.BF16
    monkeypatch.setattr(torch.cpu, "get_capabilities", lambda: {"avx2": True, "avx512_bf16": True, "amx_bf16": False})
    assert native_bf16() and resolve("auto") is Precision.BF16
    # oneDNN capped below AVX512_CORE_BF16 (as an administrator may, or to try an AVX2 machine) emulates bf16
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "AVX2")
    assert not native_bf16() and resolve("auto") is Precision.FP32
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "avx512_core_bf16")
    assert native_bf16()
    with pytest.raises(ValueError, match="expected precision auto, fp32 or bf16"):
        resolve("fp16")


def test_separated_layers_hold_no_negative_light():
    """A backbone whose R̂ goes below 0 (as the anchored network's does without its gate, where its
    training clipped it) gives R̂ clipped at 0 and T̂ as the network has it."""
    model = SeparationNet(width=8).eval()
    with torch.no_grad():
        model.tail.weight.zero_()
        model.tail.bias.copy_(torch.tensor([0.3] * 3 + [-0.5] * 3 + [20.0, 20.0]))   # T̃ 0.3, R̃ −0.5, ξ∥ = ξ⊥ = 1
        r_module, t_module = model(torch.from_numpy(SMALL.transpose(0, 3, 1, 2))[None], scale=torch.tensor([1.0]))
    assert (r_module < 0).all()                                    # the network itself answers negative light
    r_hat, t_hat = separate_stack(model, SMALL, [0, 45, 90], tile=128, overlap=0, precision="fp32")
    np.testing.assert_array_equal(r_hat, 0.0)
    assert (t_module > 0).all() and t_hat.min() > 0                  # T̂: the constant T̃ at the stack's exposure
    np.testing.assert_allclose(t_hat, t_hat.mean(), rtol=1e-5)


@pytest.mark.skipif(infer._glibc() is None, reason="glibc's malloc only")
def test_a_tiles_freed_blocks_are_kept_inside_the_block_and_handed_back_after_it():
    def resident_mb() -> float:
        return int(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20

    with infer._freed_blocks_kept():
        before = resident_mb()
        block = np.ones(200 * 2**20, np.uint8)          # 200 MB: glibc maps it afresh unless the block keeps it
        del block
        kept = resident_mb() - before
    handed_back = resident_mb() - before
    assert kept > 150 and handed_back < 50, (kept, handed_back)


def test_internal_arguments_are_checked_type_first_and_bad_sizes_are_refused():
    """The stack's type before its shape and angles; rows processed at a time and the copies
    test's window are checked, not left to a numpy or OpenCV error (or to uninitialised memory)."""
    from separate.copies import copy_share
    from separate.maps import polarization_maps
    from separate.presentation import present, present_field

    stack = np.full((3, 16, 16, 3), 0.3, np.float32)
    with pytest.raises(TypeError, match="expected images as a numpy array, got list"):
        infer.check_inputs(stack.tolist(), [0, 45, 90])
    with pytest.raises(TypeError, match="8- or 16-bit codes"):
        infer.check_inputs(stack.astype(np.int32), [0, 45])
    for rows, error in ((0, ValueError), (-1, ValueError), (2.5, TypeError), (True, TypeError)):
        for call in (lambda rows=rows: present(stack, [0, 45, 90], 10.0, rows=rows),
                     lambda rows=rows: present_field(stack, [0, 45, 90], np.zeros((16, 16), np.float32), rows=rows),
                     lambda rows=rows: polarization_maps(stack, [0, 45, 90], 10.0, rows=rows)):
            with pytest.raises(error, match="expected rows a whole number of at least 1"):
                call()
    layer = stack[0]
    for sigma, rho in ((float("nan"), (0.4, 0.8)), (float("inf"), (0.4, 0.8)), (0.0, (0.4, 0.8)), (8.0, (0.4,))):
        with pytest.raises(ValueError, match="expected 0 < sigma"):
            copy_share(layer, layer, sigma=sigma, rho=rho)
