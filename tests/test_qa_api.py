"""`urd.separate` and `urd.polarization_maps` as a library user calls them: every method checks the
stack, the user's torch state is left alone, the warnings the CLI prints reach Python, and the
inputs no method can use are refused with ValueError or TypeError."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import urd
from separate import optics

ANGLES = [0, 45, 90, 135]


def pane_stack(h: int = 64, w: int = 48) -> np.ndarray:
    """Shots at `ANGLES` of a pane at θ = 50°, φ⊥ = 20°: a striped transmission, a reflection on the right half."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    t = np.stack([0.3 + 0.2 * np.sin(xx / 7 + k) for k in range(3)], -1)
    r = np.stack([0.4 + 0.3 * np.cos(yy / 5 + k) * (xx > w // 2) for k in range(3)], -1)
    return np.stack([optics.render(r, t, np.radians(50), np.radians(20), np.radians(a)) for a in ANGLES]).astype(np.float32)


@pytest.mark.parametrize("method", ["none", "li-brown", "arvanitopoulos"])
def test_the_methods_that_see_s0_only_check_the_stack_like_the_others(method):
    stack = pane_stack()
    bad = stack.copy()
    bad[0, 0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="expected finite pixel values"):
        urd.separate(bad, ANGLES, method=method)
    with pytest.raises(ValueError, match=r"expected a stack of shape \(N>=3, H, W, C\)"):
        urd.separate(stack[..., 0], ANGLES, method=method)
    with pytest.raises(TypeError, match="expected images as a numpy array"):
        urd.separate(stack.tolist(), ANGLES, method=method)


def test_angles_and_codes_urd_cannot_use_are_refused():
    stack = pane_stack()
    with pytest.raises(ValueError, match="expected finite polarizer angles"):
        urd.separate(stack, [0, 45, float("nan"), 135], method="schechner")
    with pytest.raises(TypeError, match=r"8- or 16-bit codes"):
        urd.separate(np.rint(stack * 65535).astype(np.uint32), ANGLES, method="schechner")
    with pytest.raises(ValueError, match="read with 1.0 as white"):
        urd.separate(stack * 65535, ANGLES, method="schechner")
    with pytest.raises(ValueError, match=r"read with 0.0 as black, and .* lie below -0.05"):
        urd.separate(stack * 2 - 1, ANGLES, method="schechner")
    with pytest.raises(ValueError, match="read with 1.0 as white"):            # the maps read the stack alike
        urd.polarization_maps(stack * 255, ANGLES)
    for angles in (45, "0,45,90,135", ["0", "45", "90", "135"], [True, 45, 90, 135], [0, [45], 90, 135]):
        with pytest.raises(TypeError, match="expected the polarizer angles as"):
            urd.separate(stack, angles, method="schechner")
    with pytest.raises(ValueError, match=r"expected 4 angles \(one per shot\), got \[\]"):
        urd.separate(stack, [], method="schechner")
    with pytest.raises(ValueError, match=r"\(N>=3, H, W, C\) with C = 1 or 3 .*, got \(0, 64, 48, 3\)"):
        urd.separate(stack[:0], [], method="schechner")


@pytest.mark.parametrize("method", ["network", "schechner", "kong", "farid", "none"])
def test_every_method_refuses_channels_first_and_channel_counts_other_than_1_or_3(method):
    stack = pane_stack()
    for bad in (np.ascontiguousarray(stack[:3].transpose(0, 3, 1, 2)), stack[..., :0], np.concatenate([stack, stack[..., :1]], -1)):
        with pytest.raises(ValueError, match=r"with C = 1 or 3 channels \(grey or RGB, channels last\), got \("):
            urd.separate(bad, ANGLES[: len(bad)], method=method)
    with pytest.raises(ValueError, match="with C = 1 or 3 channels"):
        urd.polarization_maps(np.ascontiguousarray(stack[:3].transpose(0, 3, 1, 2)), ANGLES[:3])


def test_options_urd_uses_inside_are_not_options_of_the_api_and_a_method_is_named_by_a_string():
    stack = pane_stack()
    with pytest.raises(ValueError, match=r"unknown options \['uses_reference'\] for network"):
        urd.separate(stack, ANGLES, uses_reference=False)
    with pytest.raises(ValueError, match=r"unknown method \['schechner'\]"):
        urd.separate(stack, ANGLES, method=["schechner"])
    with pytest.raises(TypeError, match="expected integer tile"):
        urd.separate(stack, ANGLES, tile=True)
    with pytest.raises(ValueError, match=r"theta_deg to be a finite number ≥ 10 and ≤ 80 or null, got 0.8"):
        urd.separate(stack, ANGLES, method="schechner", theta_deg=0.8)      # radians where degrees are asked
    by_array = urd.separate(stack, ANGLES, method="schechner", reference=np.array(20.0))
    by_float = urd.separate(stack, ANGLES, method="schechner", reference=20.0)
    np.testing.assert_array_equal(by_array.transmission, by_float.transmission)


def test_polarization_maps_issue_the_stacks_warnings_as_separate_does():
    stack = np.stack([optics.render(np.full((32, 32, 3), 0.3), np.full((32, 32, 3), 0.2), np.radians(50), np.radians(20),
                                    np.radians(a)) for a in (0, 30, 60)]).astype(np.float32)
    with pytest.warns(UserWarning, match=r"span only 60 deg"):
        urd.polarization_maps(stack, [0, 30, 60])


def test_polarization_maps_refuse_a_method_that_cannot_settle_the_side_and_bad_arguments():
    stack = pane_stack()
    assert abs(float(np.median(urd.polarization_maps(stack, ANGLES)["phi_perp"])) - 20.0) < 1.0
    with pytest.raises(ValueError, match="sees only S0"):
        urd.polarization_maps(stack, ANGLES, method="li-brown")
    with pytest.raises(ValueError, match="unknown method 'bogus'"):
        urd.polarization_maps(stack, ANGLES, reference=30, method="bogus")
    with pytest.raises(ValueError, match="expected reference 'auto', 'global' or a finite angle"):
        urd.polarization_maps(stack, ANGLES, reference=None)


@pytest.mark.filterwarnings("ignore:the side of the reference was decided")
def test_the_network_leaves_the_callers_torch_state_alone():
    stack = pane_stack()
    torch.manual_seed(0)
    expected = torch.rand(1).item()
    torch.manual_seed(0)
    plain = urd.separate(stack, ANGLES, precision="fp32")
    assert torch.rand(1).item() == expected                  # the random stream is where the caller left it
    default = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    try:
        wide = urd.separate(stack, ANGLES, precision="fp32")
    finally:
        torch.set_default_dtype(default)
    assert wide.transmission.dtype == np.float32
    np.testing.assert_allclose(wide.transmission, plain.transmission, atol=1e-6)


def test_the_stacks_warnings_reach_python_and_a_dark_frame_gives_dark_layers():
    stack = pane_stack()
    with pytest.warns(UserWarning) as caught:                 # with them: "shots 0 and 1 are identical", ...
        urd.separate(np.stack([stack[0]] * 3), [0, 45, 90], method="schechner")
    assert any("the polarizer is not turning" in str(w.message) for w in caught)
    with pytest.warns(UserWarning) as caught:
        layers = urd.separate(np.zeros((3, 16, 16, 3), np.float32), [0, 45, 90], method="kong")
    assert any("nothing can be separated" in str(w.message) for w in caught)
    assert not layers.transmission.any() and not layers.reflection.any()


@pytest.mark.filterwarnings("ignore:the side of the reference was decided")
def test_colour_matching_keeps_the_transmission_in_the_units_of_s0():
    """The paper's colour correction matches T̂ to a shot through the polarizer, which carries
    about half of S0: matched as it is, T̂ came out at half its brightness."""
    stack = pane_stack(96, 96)
    s0_mean = float(optics.stokes_from_images(stack, np.radians(ANGLES))[0].mean())
    plain = urd.separate(stack, ANGLES)
    matched = urd.separate(stack, ANGLES, colour_match=True)
    assert 0.9 < matched.transmission.mean() / plain.transmission.mean() < 1.25     # the darkest shot's reflection added
    assert matched.transmission.mean() < s0_mean


def test_the_networks_switches_and_angle_of_incidence_are_checked_for_their_type():
    stack = pane_stack()
    for option, value in (("colour_match", "no"), ("return_copies", 1)):
        with pytest.raises(TypeError, match=f"expected {option} True or False, got"):
            urd.separate(stack, ANGLES, **{option: value})
    for value in (True, "30"):
        with pytest.raises(TypeError, match=r"expected an angle of incidence in \(0, 90\) deg as a number"):
            urd.separate(stack, ANGLES, incidence_deg=value)
    for value in (float("nan"), 90):
        with pytest.raises(ValueError, match=r"expected an angle of incidence in \(0, 90\) deg, got"):
            urd.separate(stack, ANGLES, incidence_deg=value)


@pytest.mark.filterwarnings("ignore:the side of the reference was decided")
def test_angles_spread_too_little_are_named_in_a_warning_by_every_method_the_network_refuses_them():
    stack = pane_stack()
    narrow = [0.0, 10.0, 20.0, 30.0]
    with pytest.warns(UserWarning, match=r"span only 30 deg: their Stokes fit has [0-9.]+x the noise of 0/45/90"):
        urd.separate(stack, narrow, method="schechner")
    with pytest.raises(ValueError, match="spanning at least 70 deg"):
        urd.separate(stack, narrow)


def test_the_theta_map_of_a_stack_that_does_not_tell_the_angle_of_incidence_is_nan():
    black = np.zeros((3, 64, 64, 3), np.float32)
    with pytest.warns(UserWarning):
        maps = urd.polarization_maps(black, [0, 45, 90])
    assert np.isnan(maps["theta"]).all()                   # not Brewster's angle shown as an estimate
    told = urd.polarization_maps(pane_stack(), ANGLES)["theta"]
    assert np.isfinite(told).all() and abs(float(np.median(told)) - 50.0) < 10.0


def test_a_scene_is_named_by_a_string(tmp_path):
    from urd.core.dataset import Dataset

    ds = Dataset.open_or_create(tmp_path / "ds")
    with pytest.raises(TypeError, match="expected a scene name such as 'scene_01', got 1"):
        ds.scene(1)
