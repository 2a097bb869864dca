"""The CEILNet baseline: edge map, the two-stage network, training through `urd train`'s code."""

import hashlib
import shutil

import cv2
import numpy as np
import pytest
import torch
from test_baselines import ANGLES, layers

from separate import metrics
from separate.baselines.ceilnet import WEIGHTS, CEILNet, edge_map
from separate.infer import DEFAULT_WEIGHTS, load_model
from separate.methods import get_method
from separate.train import TrainConfig, lr_at, train


def test_edge_map_closed_form():
    image = torch.zeros(1, 3, 5, 5)
    image[:, :, 2, 2] = 1.0                             # one bright pixel in three channels
    edges = edge_map(image)[0, 0]
    assert edges[2, 2] == pytest.approx(3.0)            # 4 neighbours × 3 channels / 4
    assert edges[1, 2] == edges[2, 1] == pytest.approx(0.75) and edges[1, 1] == 0 and edges[0, 0] == 0


def test_ceilnet_sees_only_the_unpolarized_image():
    model = CEILNet(width=8, blocks=1).eval()
    obs = torch.rand(2, 3, 3, 21, 30)
    r_hat, t_hat = model(obs)
    assert r_hat.shape == t_hat.shape == (2, 3, 21, 30)
    torch.testing.assert_close(r_hat + t_hat, obs[:, 0] + obs[:, 2])           # layers add up to S0
    swapped = torch.stack([obs[:, 2], obs[:, 0] + obs[:, 2] - obs[:, 1], obs[:, 0]], dim=1)
    torch.testing.assert_close(model(swapped)[1], t_hat, atol=1e-5, rtol=1e-5)  # same S0, other polarization
    model.train()
    assert len(model(obs)) == 3 and model(obs)[2].shape == (2, 1, 21, 30)


class Interrupted(Exception):
    """Raised from the progress callback: the run stops as if killed after that step."""


@pytest.mark.slow
def test_ceilnet_training_resumes_from_last_pt_with_its_weights_and_optimizer(tmp_path):
    cfg = TrainConfig(variant="ceilnet", width=8, blocks=1, patch=32, batch=8, micro_batch=8, lr=2e-3, steps=6,
                      val_samples=8, val_every=3, ckpt_every=3, precision="fp32", threads=1)

    def stop_at_3(record):
        if record["step"] == 3:
            raise Interrupted

    run = tmp_path / "run"
    with pytest.raises(Interrupted):
        train(cfg, run, progress=stop_at_3)
    saved = torch.load(run / "last.pt", weights_only=True)
    assert saved["step"] == 3
    # a copy of the stopped run whose checkpoint holds other weights (same step, same optimizer state)
    shift = 0.05
    tampered = tmp_path / "tampered"
    shutil.copytree(run, tampered)
    torch.save({**saved, "model": {k: v + shift for k, v in saved["model"].items()}}, tampered / "last.pt")

    steps = []
    record = train(cfg, run, progress=lambda r: steps.append(r["step"]))
    train(cfg, tampered)
    # the step count continues: only steps 4..6 run, the learning rate follows the schedule from there
    assert steps == [4, 5, 6] and record["step"] == 6 and record["lr"] == lr_at(cfg, 6) and np.isfinite(record["psnr_t"])
    resumed = torch.load(run / "last.pt", weights_only=True)
    assert resumed["step"] == 6
    # Adam's own step counters went on from the checkpoint's 3 (a fresh optimizer would stand at 3 now)
    assert {int(s["step"]) for s in saved["optim"]["state"].values()} == {3}
    assert {int(s["step"]) for s in resumed["optim"]["state"].values()} == {6}
    # the weights went on from the checkpoint's: with the warm-up's small learning rate three Adam steps move
    # each weight by < 1e-3, so the resumed run ends near the checkpoint and the tampered one near its shifted copy
    tampered_end = torch.load(tampered / "last.pt", weights_only=True)["model"]
    for name, start in saved["model"].items():
        assert (resumed["model"][name] - start).abs().max() < 1e-3, name
        assert (tampered_end[name] - (start + shift)).abs().max() < 1e-3, name
    model, info = load_model(run / "best.pt")
    assert isinstance(model, CEILNet) and info["config"]["blocks"] == 1


def test_shipped_ceilnet_weights_separate_a_stack():
    model, info = load_model(WEIGHTS)
    assert isinstance(model, CEILNet) and info["card"]["training"]["steps"] > 0
    stack = np.random.default_rng(0).random((3, 40, 48, 3), dtype=np.float32)
    run, info = get_method("ceilnet")
    r_hat, t_hat = run(stack, [0.0, 45.0, 90.0])
    s0 = stack[0] + stack[2]
    assert r_hat.min() >= 0 and t_hat.min() >= 0                       # R̂ = S0 − T̂, clipped at 0 as every method's
    both = (r_hat > 0) & (t_hat > 0)
    np.testing.assert_allclose((r_hat + t_hat)[both], s0[both], atol=1e-4)
    assert both.mean() > 0.5 and (r_hat + t_hat >= s0 - 1e-4).all()
    assert info["weights"]["sha256"] == hashlib.sha256(WEIGHTS.read_bytes()).hexdigest()
    with pytest.raises(ValueError, match="not CEILNet"):
        get_method("ceilnet", weights=DEFAULT_WEIGHTS)


def test_shipped_ceilnet_removes_a_strong_blurred_reflection():
    refl, trans = layers()
    image = (0.7 * trans + 0.5 * cv2.GaussianBlur(refl, (0, 0), 4)).astype(np.float32)
    run, _ = get_method("ceilnet")
    _, t_hat = run(np.stack([image / 2] * 3), ANGLES)               # unpolarized: every shot is S0/2
    assert metrics.psnr(t_hat, 0.7 * trans) > metrics.psnr(image, 0.7 * trans) + 1.0
