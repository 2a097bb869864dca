"""Synthesis, model, training loop, inference and `urd separate`."""

import contextlib
import dataclasses
import hashlib
import io
import json
import os
import re
import runpy
import subprocess
import sys
from unittest import mock
from pathlib import Path

import numpy as np
import pytest
import torch

from rig import capture_virtual
from separate import optics
from separate.infer import DEFAULT_WEIGHTS, WEIGHTS_DIR, load_model, match_histograms, separate_stack
from separate.tiling import tile_spans
from separate.model import NOMINAL_ANGLES, SeparationNet, canonical_inputs
from separate.synthesis import AngleMode, SynthesisConfig, Synthesizer, default_pool, load_image_pool, true_side_deg
from separate.train import TrainConfig, lr_at, run_lock, synthesis_batches, synthesis_config, train
from urd.core.dataset import Dataset
from urd.core.errors import TrainingError, WeightsError
from urd.ingest import IngestOptions, ingest_scene

POOL = load_image_pool(None)


def urd(*args):
    return subprocess.run([sys.executable, "-m", "urd.cli", *map(str, args)], capture_output=True, text=True, timeout=900)


def test_synthesis_is_deterministic_and_physically_consistent():
    a = Synthesizer(POOL, SynthesisConfig(patch=64), seed=3).batch(4)
    b = Synthesizer(POOL, SynthesisConfig(patch=64), seed=3).batch(4)
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])
    assert a["obs"].shape == (4, 3, 64, 64, 3) and a["r"].shape == (4, 64, 64, 3)
    # without noise or deformation the shots are Eq. 1 of the layers: S0 of the shots = R_obs + T_obs
    clean = Synthesizer(POOL, SynthesisConfig(patch=64, noise=False, nrd_prob=0.0, angle_noise_deg=0.0), seed=4).batch(4)
    for obs, r, t, angles in zip(clean["obs"], clean["r"], clean["t"], clean["angles"]):
        s0 = optics.stokes_from_images(obs, angles)[0]
        np.testing.assert_allclose(s0, r + t, atol=2e-5)


def test_any_angle_modes_present_the_shots_at_the_estimated_reference():
    assert [true_side_deg(r, 100.0) for r in (10.0, 50.0, 140.0, 145.0)] == [100.0, 140.0, 140.0, 145.0]
    assert true_side_deg(170.0, 5.0) == 170.0 and true_side_deg(120.0, 5.0) == 210.0
    cfg = SynthesisConfig(patch=64, angles=AngleMode.ANY)
    anyside = Synthesizer(POOL, cfg, seed=5).batch(48)
    trueside = Synthesizer(POOL, dataclasses.replace(cfg, angles=AngleMode.ANY_TRUE_SIDE), seed=5).batch(48)
    for batch in (anyside, trueside):
        np.testing.assert_allclose(np.degrees(batch["angles"] - batch["angles"][:, :1]) % 180, [[0, 45, 90]] * 48, atol=1e-3)
    assert set(anyside["shots"]) == {3.0, 4.0, 6.0}

    def off_deg(batch):
        return (np.degrees(batch["angles"][:, 0] - batch["phi_perp"][:, 0, 0]) + 90.0) % 180.0 - 90.0

    wrong = np.abs(off_deg(anyside)) > 45.0
    # the same scenes; where the estimate is on the wrong side, the true-side mode turns it by 90°
    assert 0 < wrong.sum() < 24 and np.abs(off_deg(trueside)).max() <= 45.0
    np.testing.assert_allclose(np.degrees(trueside["angles"][:, 0] - anyside["angles"][:, 0]) % 180, np.where(wrong, 90.0, 0.0), atol=1e-3)
    np.testing.assert_array_equal(trueside["obs"][~wrong], anyside["obs"][~wrong])
    np.testing.assert_array_equal(trueside["t"], anyside["t"])


def tan2_quadratic_fit(theta: np.ndarray, phi_perp: float) -> tuple[float, float]:
    """How far a P×P angle-of-incidence map is from a flat pane seen from a point.

    For a flat pane, ±tan θ is an affine function of the position along the plane of incidence
    (`test_parabola_aoi_closed_form`), so of the pixel coordinates: tan²θ is an exact quadratic in
    them whose curvature lies along the plane of incidence only, none along the s-direction φ⊥.
    Returns the quadratic fit's largest residual relative to max tan²θ, and |H·s|/|H| for its
    Hessian H and the unit s-direction s (x right, y up: the optics convention). Pixels clamped
    at 85° are left out.
    """
    p = theta.shape[0]
    rows, cols = np.mgrid[0:p, 0:p].astype(np.float64) / (p - 1)
    keep = theta < np.radians(84.9)
    x, y = cols[keep], -rows[keep]
    design = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=1)
    tan2 = np.tan(theta[keep].astype(np.float64)) ** 2
    coef, *_ = np.linalg.lstsq(design, tan2, rcond=None)
    hessian = np.array([[2 * coef[3], coef[4]], [coef[4], 2 * coef[5]]])
    s_dir = np.array([np.cos(phi_perp), np.sin(phi_perp)])
    return float(np.abs(design @ coef - tan2).max() / tan2.max()), float(np.linalg.norm(hessian @ s_dir) / np.linalg.norm(hessian))


@pytest.mark.parametrize("name", ["DR", "DR+NRD", "DR+NRD+LCG", "DR+LCG"])
def test_ablation_switches(name):
    deforms, lcg = "NRD" in name, name.endswith("LCG")
    cfg = SynthesisConfig.ablation(name, patch=32)
    assert (cfg.nrd_prob > 0) == deforms and cfg.curvature == lcg
    batch = Synthesizer(POOL, dataclasses.replace(cfg, noise=False), seed=0).batch(12)
    low, high = np.radians(cfg.aoi_deg)
    flat, deformed = 0, 0
    for obs, r, t, theta, phi_perp, angles in zip(*(batch[k] for k in ("obs", "r", "t", "theta", "phi_perp", "angles"))):
        assert np.ptp(phi_perp) == 0                                   # one plane of incidence per patch
        if lcg:                                                        # a pane at a finite distance: θ varies
            assert np.ptp(theta) > np.radians(0.1) and theta.max() <= np.radians(85.0) + 1e-6
            flat += max(tan2_quadratic_fit(theta, phi_perp[0, 0])) < 1e-4
        else:                                                          # closed form without LCG: θ ≡ θc
            assert np.ptp(theta) == 0 and low <= theta[0, 0] <= high
        # without noise, undeformed shots are Eq. 1 of the layers, S0 = R_obs + T_obs, except where a shot clips
        # at white (≤ 3% of values: the synthesizer rejects patches with more); NRD moves ≥ 48% (measured)
        deformed += (np.abs(optics.stokes_from_images(obs, angles)[0] - (r + t)) > 1e-4).mean() > 0.1
    assert 0 < deformed < 12 if deforms else deformed == 0             # NRD deforms half the samples
    assert 0 < flat < 12 if lcg else flat == 0                         # LCG curves half the panes


@pytest.mark.parametrize("curved_prob", [0.0, 1.0])
def test_synthesized_panes_follow_the_flat_pane_closed_form_unless_curved(curved_prob):
    # measured on these 10 patches: flat panes fit within 1e-6 (residual) and 1.1e-5 (Hessian along φ⊥);
    # curved ones miss the quadratic by 2e-3 to 0.19
    batch = Synthesizer(POOL, SynthesisConfig(patch=32, curved_prob=curved_prob), seed=0).batch(10)
    fits = [tan2_quadratic_fit(theta, phi_perp[0, 0]) for theta, phi_perp in zip(batch["theta"], batch["phi_perp"])]
    if curved_prob == 0.0:
        assert all(residual < 1e-5 and along_s < 1e-4 for residual, along_s in fits)
    else:
        assert all(residual > 1e-3 for residual, _ in fits)


def test_parabola_aoi_closed_form():
    t = np.linspace(-0.5, 0.5, 11)
    flat = optics.parabola_aoi(np.radians(40), 2.0, 1.0, 0.0, 1, t)
    assert flat[5] == pytest.approx(np.radians(40))
    # a flat pane seen from a point: tan θ grows linearly along it
    x = t * 1.0
    expected = np.arctan((2.0 * np.sin(np.radians(40)) + x) / (2.0 * np.cos(np.radians(40))))
    np.testing.assert_allclose(flat, expected, atol=1e-9)
    bent = optics.parabola_aoi(np.radians(40), 2.0, 1.0, 0.05, 1, t)
    assert bent[5] == pytest.approx(np.radians(40))                   # the vertex's tangent is the flat pane's
    assert np.abs(bent - flat).max() > np.radians(1)
    # seen head-on at the vertex (θc = 0, d = 2, ℓ = 1): the profile is (t, d − κt²) with normal (−2κt, −1),
    # so cos θ = (d + κt²) / √((t² + (d − κt²)²)(1 + 4κ²t²)), symmetric in t, κ = ±4·sagitta/ℓ²
    for convexity in (1, -1):
        kappa = convexity * 4 * 0.05
        cos = (2.0 + kappa * t**2) / np.sqrt((t**2 + (2.0 - kappa * t**2) ** 2) * (1 + 4 * kappa**2 * t**2))
        np.testing.assert_allclose(optics.parabola_aoi(0.0, 2.0, 1.0, 0.05, convexity, t), np.arccos(cos), atol=1e-12)


def test_model_shapes_residual_and_canonical_layer():
    model = SeparationNet(width=8)
    obs = torch.rand(2, 3, 3, 40, 52)
    r_hat, t_hat = model(obs)
    assert r_hat.shape == t_hat.shape == (2, 3, 40, 52)
    shots, i_perp, i_par = canonical_inputs(obs)
    torch.testing.assert_close(shots, obs)
    torch.testing.assert_close(i_perp + i_par, obs[:, 0] + obs[:, 2])
    # four shots at 0/45/90/135 give the same canonical images as three
    four = torch.cat([obs, (obs[:, 1] + (obs[:, 0] + obs[:, 2]) - 2 * obs[:, 1])[:, None]], dim=1)
    _, p4, q4 = canonical_inputs(four, tuple(np.radians([0, 45, 90, 135])))
    torch.testing.assert_close(p4, i_perp, atol=1e-5, rtol=1e-5)
    assert sum(p.numel() for p in SeparationNet(16).parameters()) > 1_000_000
    direct = SeparationNet(width=8, variant="direct")
    assert direct.head.in_channels == 9 and model.head.in_channels == 15


@pytest.mark.slow
def test_training_improves_the_validation_psnr(tmp_path):
    # a high peak learning rate, so that the 200-step warm-up still moves a 20-step run; measured with seed 0:
    # validation PSNR of T̂ 23.5 dB after 5 steps, 26.4 dB after 20 (+2.9 dB; seeds 1–3 gain 1.4–2.0 dB)
    cfg = TrainConfig(width=8, patch=32, batch=8, micro_batch=4, lr=0.1, steps=20, val_samples=16, val_every=5,
                      ckpt_every=10, precision="fp32", threads=1)
    records = []
    last = train(cfg, tmp_path, progress=records.append)
    psnr = [r["psnr_t"] for r in records if "psnr_t" in r]
    assert [r["step"] for r in records] == list(range(1, 21)) and last["step"] == 20 and len(psnr) == 4
    assert psnr[-1] > psnr[0] + 1.0
    best = torch.load(tmp_path / "best.pt", weights_only=True)
    assert best["best_psnr_t"] == max(psnr) and torch.load(tmp_path / "last.pt", weights_only=True)["step"] == 20
    logged = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert [r["psnr_t"] for r in logged] == psnr


def test_log_mse_loss_is_the_mean_log_of_each_samples_error_and_weighs_samples_alike():
    t = torch.zeros(2, 3, 4, 4)
    r = torch.zeros(2, 3, 4, 4)
    t_hat = t.clone()
    t_hat[0] += 0.1                                   # sample 0: MSE 1e-2; sample 1: MSE 1e-4
    t_hat[1] += 0.01
    outputs = (r.clone(), t_hat)
    expected = 1e-3 * ((np.log(1e-2 + 1e-6) + np.log(1e-4 + 1e-6)) / 2 + np.log(1e-6))
    assert SeparationNet.loss(outputs, r, t, "log-mse").item() == pytest.approx(expected, rel=1e-5)
    assert SeparationNet.loss(outputs, r, t).item() == pytest.approx((1e-2 + 1e-4) / 2, rel=1e-5)
    t_hat.requires_grad_(True)
    SeparationNet.loss((r, t_hat), r, t, "log-mse").backward()
    per_sample = t_hat.grad.abs().sum(dim=(1, 2, 3))  # ∂ log(MSE) = ∂ MSE / MSE: the 10× smaller error pulls 10× harder
    assert per_sample[1].item() == pytest.approx(10 * per_sample[0].item(), rel=0.02)
    with pytest.raises(ValueError, match="expected loss in"):
        SeparationNet.loss(outputs, r, t, "l1")


@pytest.mark.slow
def test_config_checks_the_loss_and_a_log_mse_run_trains(tmp_path):
    for text, message in (('loss = "l1"\n', "expected loss in"), ('variant = "ceilnet"\nloss = "log-mse"\n', "'l2' for ceilnet")):
        (tmp_path / "bad.toml").write_text(text)
        with pytest.raises(ValueError, match=message):
            TrainConfig.from_toml(tmp_path / "bad.toml")
    cfg = TrainConfig(width=4, patch=32, batch=2, micro_batch=2, steps=2, val_samples=2, val_every=2,
                      precision="fp32", threads=1, loss="log-mse")
    records = []
    train(cfg, tmp_path / "run", progress=records.append)
    assert all(r["loss"] < 0 for r in records)         # 1e-3 × log of an MSE below 1
    assert 'loss = "log-mse"' in (tmp_path / "run" / "config.toml").read_text()


def test_train_seed_option_overrides_the_config(tmp_path, monkeypatch):
    from typer.testing import CliRunner

    import separate.train
    from urd.cli import app

    seen = []
    monkeypatch.setattr(separate.train, "train", lambda cfg, run_dir, init, progress: seen.append(cfg) or {"step": 0})
    cfg = tmp_path / "tiny.toml"
    cfg.write_text("seed = 3\nsteps = 1\n")
    for extra in ([], ["--seed", "5"]):
        result = CliRunner().invoke(app, ["train", str(cfg), str(tmp_path / "run"), *extra])
        assert result.exit_code == 0, result.output
    assert [c.seed for c in seen] == [3, 5] and seen[1].steps == 1
    result = CliRunner().invoke(app, ["train", str(cfg), str(tmp_path / "run"), "--seed", "-1"])
    assert result.exit_code == 2


@pytest.mark.slow
def test_a_run_folder_is_trained_by_one_process_and_resumed_only_with_its_settings(tmp_path):
    cfg = TrainConfig(width=4, patch=32, batch=2, micro_batch=2, steps=1, val_samples=2, val_every=1, precision="fp32", threads=1)
    (tmp_path / "run").mkdir()
    with run_lock(tmp_path / "run"):                  # as another process training there would
        with pytest.raises(TrainingError, match=rf"being trained by another process \(pid {os.getpid()}\)"):
            train(cfg, tmp_path / "run")
    assert not (tmp_path / "run" / "last.pt").exists()
    train(cfg, tmp_path / "run")
    with pytest.raises(TrainingError, match=r"other settings \(lr 0.005 → 0.001, seed 0 → 1\)"):
        train(dataclasses.replace(cfg, steps=2, seed=1, lr=1e-3), tmp_path / "run")
    assert train(dataclasses.replace(cfg, steps=2, threads=2), tmp_path / "run")["step"] == 2   # longer: allowed


@pytest.mark.slow
def test_synthesis_workers_draw_seeded_streams_and_end_with_the_run(tmp_path):
    import multiprocessing

    cfg = TrainConfig(width=4, patch=32, batch=4, micro_batch=2, steps=3, val_samples=2, val_every=3,
                      precision="fp32", threads=1, workers=2)
    pool, synthesis = default_pool("train"), synthesis_config(cfg)
    with synthesis_batches(cfg, seed=11, size=2) as batches:
        drawn = [next(batches) for _ in range(2)]
    assert not multiprocessing.active_children()
    expected = [Synthesizer(pool, synthesis, seed=seed).batch(2) for seed in (11, 11 + 1_000_003)]   # worker k: seed + 1_000_003 k
    assert all(np.array_equal(d[k], e[k]) for d, e in zip(drawn, expected) for k in e)
    with synthesis_batches(dataclasses.replace(cfg, workers=0), seed=11, size=2) as batches:
        assert np.array_equal(next(batches)["obs"], expected[0]["obs"])
    records = []                                       # one worker is enough to see it end with the run
    assert train(dataclasses.replace(cfg, workers=1), tmp_path / "run", progress=records.append)["step"] == 3
    assert [r["step"] for r in records] == [1, 2, 3] and np.isfinite(records[-1]["psnr_t"])
    assert not multiprocessing.active_children()


def test_learning_rate_follows_steps_or_training_time_whichever_is_further():
    cfg = TrainConfig(lr=1e-3, lr_min=1e-5, steps=1000)
    assert lr_at(cfg, 600, wall_s=1e9) == lr_at(cfg, 600)                 # no time schedule: time is ignored
    timed = dataclasses.replace(cfg, schedule_minutes=10.0)
    assert lr_at(timed, 600, wall_s=0.0) == lr_at(cfg, 600)                # steps further along than time
    assert lr_at(timed, 300, wall_s=300.0) == pytest.approx(lr_at(cfg, 500))  # half the minutes: mid-cosine
    assert lr_at(timed, 300, wall_s=601.0) == pytest.approx(1e-5)          # time is up: lr_min


@pytest.mark.slow
def test_a_training_time_schedule_reaches_lr_min_in_a_fresh_and_a_resumed_run(tmp_path):
    cfg = TrainConfig(width=4, patch=32, batch=2, micro_batch=2, steps=3, val_samples=2, val_every=3, lr=1e-2,
                      lr_min=1e-5, precision="fp32", threads=1, schedule_minutes=1e-9)
    records = []
    train(cfg, tmp_path, progress=records.append)
    train(dataclasses.replace(cfg, steps=5), tmp_path, progress=records.append)
    assert [r["step"] for r in records] == [1, 2, 3, 4, 5]
    assert all(r["lr"] == pytest.approx(1e-5) for r in records)
    untimed = []
    train(dataclasses.replace(cfg, schedule_minutes=0.0), tmp_path / "untimed", progress=untimed.append)
    assert untimed[0]["lr"] > 5e-5                                        # by steps alone: warming up, 8.5e-5


def torchrun_train(config: Path, run_dir: Path) -> subprocess.CompletedProcess:
    """``urd train CONFIG RUN_DIR`` under torchrun: two CPU ranks (gloo), one thread each."""
    import socket

    with socket.socket() as sock:                      # a free port for the rendezvous
        sock.bind(("127.0.0.1", 0))
        port = str(sock.getsockname()[1])
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_port", port,
                           "-m", "urd.cli", "train", str(config), str(run_dir)], capture_output=True, text=True,
                          timeout=600, env=env)


@pytest.mark.slow
def test_ddp_with_two_gloo_processes(tmp_path):
    cfg = tmp_path / "ddp.toml"
    cfg.write_text('width = 8\npatch = 32\nbatch = 16\nmicro_batch = 4\nsteps = 4\nval_samples = 8\nval_every = 4\nprecision = "fp32"\nthreads = 1\n')
    out = torchrun_train(cfg, tmp_path / "run")                     # two micro-batches per rank: one without a sync
    assert out.returncode == 0, out.stderr[-2000:]
    state = torch.load(tmp_path / "run" / "last.pt", weights_only=True)
    assert state["step"] == 4 and "2 processes" in state["trained_on"]


@pytest.mark.slow
@pytest.mark.parametrize("case", ["best.pt without last.pt", "a resume while another process trains"])
def test_a_start_rank_0_refuses_ends_every_rank_with_its_reason(tmp_path, case):
    # rank 0 refuses the run folder; rank 1 is told why instead of waiting in the rendezvous until
    # torchrun kills it
    cfg = tmp_path / "ddp.toml"
    tiny = 'width = 4\npatch = 32\nbatch = 4\nmicro_batch = 2\nsteps = 2\nval_samples = 4\nprecision = "fp32"\nthreads = 1\n'
    cfg.write_text(tiny)
    run_dir = tmp_path / "run"
    if case == "best.pt without last.pt":
        run_dir.mkdir()
        (run_dir / "best.pt").write_bytes(b"an earlier run's weights")
        reason, holder = "holds best.pt of an earlier run but no last.pt", contextlib.nullcontext()
    else:
        train(TrainConfig.from_toml(cfg), run_dir)
        cfg.write_text(tiny.replace("steps = 2", "steps = 4"))
        reason, holder = "is being trained by another process", run_lock(run_dir)
    before = {path.name: path.read_bytes() for path in run_dir.iterdir() if path.is_file()}
    with holder:
        out = torchrun_train(cfg, run_dir)
    assert out.returncode != 0
    assert sum(reason in line for line in out.stderr.splitlines()) == 2, out.stderr[-3000:]   # rank 0's, and rank 1's
    assert "rank 0 did not start the run" in out.stderr and "SIGKILL" not in out.stderr
    assert {path.name: path.read_bytes() for path in run_dir.iterdir() if path.is_file()} == before


@pytest.mark.parametrize("tile,overlap", [(64, 32), (512, 128), (768, 160), (1024, 0)])
def test_tiles_cover_the_axis_on_the_8_px_grid_with_the_overlap(tile, overlap):
    for size in range(1, 7000, 13):
        spans = tile_spans(size, tile, overlap)
        assert spans[0][0] == 0 and spans[-1][1] == size
        assert all(start % 8 == 0 and 0 < end - start <= tile for start, end in spans)
        assert all(a[1] - b[0] >= overlap and b[0] > a[0] for a, b in zip(spans, spans[1:]))
    assert len(tile_spans(6000, 768, 160)) == 10 and tile_spans(700, 768, 160) == [(0, 700)]


@pytest.mark.parametrize("stack,angles,message", [
    (np.zeros((2, 16, 16, 3)), [0, 45], "N>=3"),
    (np.zeros((3, 16, 16, 3)), [0, 30, 60], "spanning at least 70"),
    (np.full((3, 16, 16, 3), np.nan), [0, 45, 90], "NaN"),
])
def test_bad_inputs(stack, angles, message):
    model, _ = load_model()
    with pytest.raises(ValueError, match=message):
        separate_stack(model, stack.astype(np.float32), angles)


def test_negative_pixels_are_clipped_to_zero():
    # separate.infer: negative pixels (decoding noise below black) are clipped to 0, in the exposure scale too
    model, _ = load_model()
    stack = np.random.default_rng(0).random((3, 32, 40, 3)).astype(np.float32) * 0.5
    stack[0, :4] = -0.05
    stack[2, :, :3] = -0.2
    r_hat, t_hat = separate_stack(model, stack, [0, 45, 90], precision="fp32")
    r_clip, t_clip = separate_stack(model, np.clip(stack, 0.0, None), [0, 45, 90], precision="fp32")
    np.testing.assert_array_equal(r_hat, r_clip)
    np.testing.assert_array_equal(t_hat, t_clip)


def test_monochrome_shots_give_grey_layers_for_one_or_three_equal_channels():
    model, _ = load_model("urd-canonical")             # the module is called alone below: no θ for a gate
    rng = np.random.default_rng(1)
    r, t = rng.random((2, 48, 64)).astype(np.float32)
    grey = np.stack([0.3 * r * (1 + 0.8 * np.cos(2 * (phi - 0.2))) + 0.5 * t for phi in NOMINAL_ANGLES])[..., None].astype(np.float32)
    r1, t1 = separate_stack(model, grey, [0, 45, 90], precision="fp32")
    r3, t3 = separate_stack(model, np.repeat(grey, 3, axis=-1), [0, 45, 90], precision="fp32")
    assert r1.shape == t1.shape == (48, 64, 1) and r3.shape == t3.shape == (48, 64, 3)
    assert all(np.array_equal(x[..., 0], x[..., k]) for x in (r3, t3) for k in (1, 2))
    np.testing.assert_allclose(t1[..., 0], t3[..., 0], atol=1e-6)
    with torch.no_grad():
        raw_r, raw_t = model(torch.from_numpy(np.repeat(grey, 3, axis=-1).transpose(0, 3, 1, 2))[None], NOMINAL_ANGLES)
    assert raw_t[0].std(dim=0).max() > 1e-4             # the RGB network alone tints a grey input
    np.testing.assert_allclose(t3[..., 0], raw_t[0].clamp_min(0).mean(dim=0).numpy(), atol=1e-4)   # no negative light
    np.testing.assert_allclose(r3[..., 0], raw_r[0].mean(dim=0).numpy(), atol=1e-4)


def test_missing_and_corrupt_weights(tmp_path):
    with pytest.raises(WeightsError, match="not found"):
        load_model(tmp_path / "none.pt")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(DEFAULT_WEIGHTS.read_bytes()[:1000])
    with pytest.raises(WeightsError, match="corrupt"):
        load_model(bad)


@pytest.mark.slow
def test_urd_separate_on_a_simulated_scene_beats_no_separation(tmp_path):
    ds = Dataset.open_or_create(tmp_path / "ds")
    scene, _ = capture_virtual(ds, size=(512, 384), shake_px=4, shake_deg=0.5, seed=7)
    ingest_scene(scene, IngestOptions())
    out = urd("separate", "scene_01", "--dataset", tmp_path / "ds")
    assert out.returncode == 0, out.stderr
    entry = scene.load()["results"]["network"]
    assert entry["weights"]["sha256"]
    assert {"R.tiff", "T.tiff", "R_preview.png", "T_preview.png", "confidence.tiff", "clipped.png"} <= {
        Path(f["file"]).name for f in entry["files"]}
    figures = entry["truth_metrics"]
    assert figures["T"]["psnr_db"] > figures["T_no_separation"]["psnr_db"] + 3
    out = urd("separate", "scene_01", "--dataset", tmp_path / "ds")
    assert out.returncode == 1 and "scene_01 already has network results" in out.stderr and "--force" in out.stderr
    files = [scene.path / f"aligned/shot_0{i}.tiff" for i in range(3)]
    args = [a for f in files for a in ("--images", f)]
    out = urd("separate", *args, "--out", tmp_path / "files")
    assert out.returncode == 0 and (tmp_path / "files" / "T.tiff").is_file()
    (tmp_path / "files" / "R.tiff").unlink()                                # a half-replaced folder must not happen
    kept = {p.name: p.read_bytes() for p in (tmp_path / "files").iterdir()}
    out = urd("separate", *args, "--method", "kong", "--out", tmp_path / "files")
    assert out.returncode == 1 and "already holds results (R_preview.png, T.tiff, T_preview.png" in out.stderr and "--force" in out.stderr
    assert {p.name: p.read_bytes() for p in (tmp_path / "files").iterdir()} == kept
    out = urd("separate", *args[:4], "--out", tmp_path / "two")
    assert out.returncode == 2 and "expected one --images file per angle of --angles 0,45,90, got 2 files" in out.stderr


@pytest.mark.slow
def test_training_continues_from_the_shipped_weights(tmp_path):
    canonical = WEIGHTS_DIR / "urd-canonical.pt"                               # the shipped network's backbone
    upsample = load_model(canonical)[1]["config"].get("upsample", "transposed")
    cfg = TrainConfig(width=16, patch=32, batch=4, micro_batch=4, steps=1, val_samples=8, val_every=1, threads=1,
                      upsample=upsample)
    scratch = train(cfg, tmp_path / "scratch")
    tuned = train(cfg, tmp_path / "tuned", init=canonical)
    assert tuned["psnr_t"] > scratch["psnr_t"] + 3
    origin = torch.load(tmp_path / "tuned" / "last.pt", weights_only=True)["init"]
    assert origin["sha256"] == hashlib.sha256(canonical.read_bytes()).hexdigest()
    assert torch.load(tmp_path / "scratch" / "last.pt", weights_only=True)["init"] is None
    log = [json.loads(line) for line in (tmp_path / "tuned" / "log.jsonl").read_text().splitlines()]
    assert log[0]["step"] == 0 and log[0]["patches_seen"] == 0 and log[0]["psnr_t"] > scratch["psnr_t"] + 3   # the starting weights, validated
    best = torch.load(tmp_path / "tuned" / "best.pt", weights_only=True)
    assert best["best_psnr_t"] == max(log[0]["psnr_t"], tuned["psnr_t"])
    assert best["step"] == (0 if log[0]["psnr_t"] >= tuned["psnr_t"] else 1)
    assert json.loads((tmp_path / "scratch" / "log.jsonl").read_text().splitlines()[0])["step"] == 1

    root = Path(__file__).resolve().parents[1]

    def export(parent):
        """tools/export_weights.py in this process (torch is loaded already): its exit code, stdout, stderr."""
        argv = ["export_weights.py", str(tmp_path / "tuned" / "last.pt"), str(tmp_path / "w.pt"), "--parent", str(parent)]
        with mock.patch.object(sys, "argv", argv), mock.patch.object(sys, "path", [str(root / "tools"), *sys.path]), \
                contextlib.redirect_stdout(io.StringIO()) as stdout:
            try:
                runpy.run_path(str(root / "tools" / "export_weights.py"), run_name="__main__")
            except SystemExit as exc:
                return (exc.code if isinstance(exc.code, int) else 1), stdout.getvalue(), str(exc.code)
        return 0, stdout.getvalue(), ""

    code, printed, _ = export(canonical.with_suffix(".json"))
    assert code == 0 and json.loads(printed)["sha256"]
    card = json.loads((tmp_path / "w.json").read_text())
    first = (tmp_path / "w.pt").read_bytes()
    assert export(canonical.with_suffix(".json"))[0] == 0 and (tmp_path / "w.pt").read_bytes() == first   # the same weights: the file kept
    assert json.loads((tmp_path / "w.json").read_text())["sha256"] == card["sha256"] == hashlib.sha256(first).hexdigest()
    shipped = json.loads(canonical.with_suffix(".json").read_text())
    assert len(card["stages"]) == len(shipped.get("stages", [None])) + 1
    assert card["total"]["steps"] == shipped.get("total", shipped["training"])["steps"] + 1
    code, _, stderr = export(root / "separate/weights/ceilnet.json")
    assert code != 0 and "does not describe" in stderr


def test_histogram_matching_undoes_a_monotone_per_channel_change():
    rng = np.random.default_rng(3)
    reference = rng.gamma(2.0, 0.1, size=(120, 90, 3)).astype(np.float32)
    washed = np.stack([0.5 * reference[..., 0] + 0.1, np.sqrt(reference[..., 1]), reference[..., 2] ** 2], axis=-1)
    matched = match_histograms(washed, reference)
    assert np.abs(matched - reference).max() < 0.02 * reference.max()
    assert np.abs(washed - reference).max() > 0.2 * reference.max()
    with pytest.raises(ValueError, match="equal C"):
        match_histograms(washed, reference[..., :1])


def test_paired_gain_is_the_mean_per_patch_difference_with_an_interval_around_it():
    from separate.bench import format_paired, paired_gain

    rng = np.random.default_rng(0)
    base = rng.uniform(20, 35, 200)
    rows = [{"method": "a", "psnr_t_per_patch": base + 0.5 + rng.normal(0, 0.3, 200)},
            {"method": "b", "psnr_t_per_patch": base}]
    g = paired_gain(rows, "a", "b")
    assert abs(g["mean"] - 0.5) < 0.1 and g["ci95"][0] < g["mean"] < g["ci95"][1]
    assert 0.3 < g["ci95"][0] and g["ci95"][1] < 0.7 and g["wins"] > 180 and g["count"] == 200
    assert paired_gain(rows, "b", "a")["mean"] == -g["mean"]
    assert "+0.5" in format_paired(rows, "a", "b")
    with pytest.raises(ValueError, match="'c'"):
        paired_gain(rows, "a", "c")


def test_a_paired_gain_over_patches_cut_from_one_capture_resamples_whole_captures():
    """Two patches of each capture that score alike are one observation, not two: resampling
    captures gives the interval of the captures' own differences, wider than patch resampling."""
    from separate.bench import paired_gain

    per_capture = np.random.default_rng(1).normal(1.0, 1.0, 10)
    twice = np.repeat(per_capture, 2)
    rows = [{"method": "a", "psnr_t_per_patch": twice}, {"method": "b", "psnr_t_per_patch": np.zeros(20)}]
    grouped = paired_gain(rows, "a", "b", groups=[f"capture-{k // 2}" for k in range(20)])
    once = paired_gain([{"method": "a", "psnr_t_per_patch": per_capture}, {"method": "b", "psnr_t_per_patch": np.zeros(10)}],
                       "a", "b")
    naive = paired_gain(rows, "a", "b")
    assert grouped["mean"] == pytest.approx(once["mean"]) and grouped["count"] == 20
    assert grouped["ci95"] == pytest.approx(once["ci95"], abs=0.05)
    assert naive["ci95"][1] - naive["ci95"][0] < 0.8 * (grouped["ci95"][1] - grouped["ci95"][0])
    with pytest.raises(ValueError, match="one group label per patch"):
        paired_gain(rows, "a", "b", groups=["x"] * 3)


@pytest.mark.slow
def test_benchmark_scores_methods_and_weights_given_by_path():
    from separate.bench import format_aoi_table, run_benchmark

    rows = run_benchmark(["none", f"shipped={DEFAULT_WEIGHTS}"], count=4, size=64)
    assert [r["method"] for r in rows] == ["none", "shipped"]
    assert rows[1]["psnr_t"] > rows[0]["psnr_t"] + 3 and 0 < rows[1]["ssim_t"] <= 1
    table = format_aoi_table(rows).splitlines()
    counts = [int(c) for c in re.findall(r"\((\d+)\)", table[0])]
    assert sum(counts) == 4 and [line.split(" | ")[0] for line in table[2:]] == ["| none", "| shipped"]
    by_band = [float(v) for v in table[3].strip("| ").split(" | ")[1:] if v != "–"]
    assert min(by_band) <= rows[1]["psnr_t"] <= max(by_band)


@pytest.mark.slow
def test_training_refuses_init_weights_of_another_architecture(tmp_path):
    from separate.model import with_resize_upsampling

    cfg = TrainConfig(width=16, patch=32, batch=4, micro_batch=4, steps=1, val_samples=8, val_every=1, threads=1,
                      upsample="resize")
    transposed = WEIGHTS_DIR / "urd-canonical-transposed.pt"
    with pytest.raises(WeightsError, match="tools/resize_upsampling.py"):
        train(cfg, tmp_path / "run", init=transposed)                  # transposed weights, resize config
    resized = with_resize_upsampling(load_model(transposed)[0])
    init = tmp_path / "resize-init.pt"
    torch.save({"model": resized.state_dict(), "model_config": resized.config()}, init)
    record = train(cfg, tmp_path / "run2", init=init)
    saved = torch.load(tmp_path / "run2" / "last.pt", weights_only=True)
    assert saved["model_config"]["upsample"] == "resize" and record["psnr_t"] > 20
