"""Methods' options checked when the method is made: baseline parameters by type and range, the
network's weights, its recorded tile, and the reference as any real number."""

import inspect

import numpy as np
import pytest
from typer.testing import CliRunner

from conftest import ingested_dataset
from separate.baselines import arvanitopoulos, ceilnet, kong, li_brown, schechner
from separate.methods import check_reference, get_method
from urd.cli import app

ANGLES = [0.0, 45.0, 90.0]


def small_stack(size: int = 16) -> np.ndarray:
    """Three shots (3, size, size, 3) float32 linear with some texture."""
    return np.random.default_rng(0).uniform(0.1, 0.9, (3, size, size, 3)).astype(np.float32)


@pytest.mark.parametrize("method, name, value, expected", [
    ("kong", "smoothness", "abc", "kong parameter smoothness to be a finite number ≥ 0, got 'abc'"),
    ("kong", "smoothness", -1, "kong parameter smoothness to be a finite number ≥ 0, got -1"),
    ("kong", "smoothness", float("nan"), "smoothness to be a finite number ≥ 0, got nan"),
    ("kong", "min_side", 1, "kong parameter min_side to be an integer ≥ 2, got 1"),
    ("kong", "steps", 1e9, "kong parameter steps to be an integer ≥ 1, got 1000000000.0"),
    ("kong", "steps", True, "steps to be an integer ≥ 1, got True"),
    ("schechner", "grid_step_deg", 0, "schechner parameter grid_step_deg to be a finite number ≥ 0.01 and ≤ 20, got 0"),
    ("schechner", "theta_deg", 95, "schechner parameter theta_deg to be a finite number ≥ 10 and ≤ 80 or null, got 95"),
    ("schechner", "theta_deg", 0.8, "theta_deg to be a finite number ≥ 10 and ≤ 80 or null, got 0.8"),   # radians
    ("schechner", "theta_deg", "35", "theta_deg to be a finite number ≥ 10 and ≤ 80 or null, got '35'"),
    ("arvanitopoulos", "lam", "x", "arvanitopoulos parameter lam to be a finite number > 0 and < 50000, got 'x'"),
    ("li-brown", "lam", -1.0, "li_brown parameter lam to be a finite number ≥ 0, got -1.0"),
])
def test_a_bad_baseline_parameter_is_refused_when_the_method_is_made(method, name, value, expected):
    with pytest.raises(ValueError) as raised:
        get_method(method, **{name: value})
    assert expected in str(raised.value)


def test_baseline_parameters_are_recorded_as_their_defaults_types():
    _, info = get_method("kong", steps=np.int64(5), smoothness=2, min_side=np.uint8(8))
    assert info["parameters"] == {"steps": 5, "smoothness": 2.0, "min_side": 8}
    assert [type(v) for v in info["parameters"].values()] == [int, float, int]
    _, info = get_method("schechner", theta_deg=np.float32(35.0))
    assert info["parameters"] == {"theta_deg": 35.0} and type(info["parameters"]["theta_deg"]) is float
    assert get_method("schechner", theta_deg=None)[1]["parameters"] == {"theta_deg": None}


@pytest.mark.parametrize("module", [schechner, kong, li_brown, arvanitopoulos])
def test_every_numeric_baseline_parameter_has_a_range(module):
    numeric = {name for name, parameter in list(inspect.signature(module.separate).parameters.items())[2:]
               if name != "progress" and not isinstance(parameter.default, bool)}
    assert set(getattr(module, "PARAM_RANGES", {})) == numeric


@pytest.mark.parametrize("method, name, inside, outside", [
    ("kong", "smoothness", 0.0, -1e-9),
    ("kong", "steps", 1, 0),
    ("kong", "min_side", 2, 1),
    ("schechner", "theta_deg", 10.0, 9.99),
    ("schechner", "theta_deg", 80.0, 80.01),
    ("schechner", "grid_step_deg", 0.01, 0.009),
    ("schechner", "grid_step_deg", 20.0, 20.5),
    ("li-brown", "lam", 0.0, -1e-9),
    ("arvanitopoulos", "lam", 1e-6, 0.0),
    ("arvanitopoulos", "lam", 49_999.0, 50_000.0),
])
def test_a_ranges_edge_runs_to_finite_layers_and_the_value_past_it_is_refused(method, name, inside, outside):
    run, _ = get_method(method, reference=0.0, **{name: inside})
    r_hat, t_hat = run(small_stack(), ANGLES)
    assert np.isfinite(r_hat).all() and np.isfinite(t_hat).all()
    with pytest.raises(ValueError, match=f"parameter {name} to be"):
        get_method(method, **{name: outside})


def test_the_network_refuses_ceilnet_weights():
    with pytest.raises(ValueError, match="weights ceilnet.pt hold CEILNet, not the polarization network: use the method 'ceilnet'"):
        get_method("network", weights=ceilnet.WEIGHTS, device="cpu")


def test_ceilnet_refuses_the_networks_weights_pointing_to_method_network():
    with pytest.raises(ValueError, match="weights urd-anchored hold a .* network, not CEILNet: use the method 'network'"):
        get_method("ceilnet", weights="urd-anchored", device="cpu")


def test_the_network_records_the_tile_it_uses():
    _, info = get_method("network", tile=333, device="cpu")
    assert info["parameters"]["tile"] == 328


def test_a_reference_is_any_finite_real_number():
    for reference in (np.float32(10.0), np.int64(10), np.float64(10.0)):
        assert check_reference(reference) == 10.0 and type(check_reference(reference)) is float
        assert "fixed: 10 deg" in get_method("schechner", reference=reference)[1]["reference_policy"]
    for reference in (np.float32("nan"), np.True_, True, "north"):
        with pytest.raises(ValueError, match="expected reference"):
            check_reference(reference)


@pytest.mark.slow
@pytest.mark.parametrize("param, said", [("grid_step_deg=abc", "schechner parameter grid_step_deg to be a finite number"),
                                         ("foo=1", "unknown parameters ['foo'] for schechner")])
def test_the_cli_says_a_bad_parameter_as_a_usage_error_before_it_says_the_results_exist(tmp_path_factory, param, said):
    root = ingested_dataset(tmp_path_factory, "params")
    if not (root / "scene_01" / "results" / "schechner").is_dir():
        assert CliRunner().invoke(app, ["separate", "scene_01", "--dataset", str(root), "--method", "schechner"]).exit_code == 0
    result = CliRunner().invoke(app, ["separate", "scene_01", "--dataset", str(root), "--method", "schechner", "--param", param])
    assert result.exit_code == 2 and "Invalid value for '--param'" in result.output, result.output
    assert said in " ".join(result.output.split()) and "Traceback" not in result.output


@pytest.mark.parametrize("params, said", [
    (["smoothness=NaN"], "Invalid value for '--param': expected a finite number for smoothness, got NaN"),
    (["smoothness=-Infinity"], "Invalid value for '--param': expected a finite number for smoothness, got -Infinity"),
    (["smoothness=0.5", "smoothness=0.7"], "smoothness is given twice (smoothness=0.5 and smoothness=0.7); give it once"),
])
def test_a_parameter_given_twice_or_not_finite_is_a_usage_error_naming_param(tmp_path, params, said):
    args = ["separate", "scene_01", "--dataset", str(tmp_path), "--method", "kong"]
    for item in params:
        args += ["--param", item]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 2 and said in " ".join(result.output.split()), result.output
