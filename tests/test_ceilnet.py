"""The CEILNet baseline: edge map, the two-stage network, training through `urd train`'s code."""

import hashlib

import cv2
import numpy as np
import pytest
import torch
from test_baselines import ANGLES, layers

from separate import metrics
from separate.baselines.ceilnet import WEIGHTS, CEILNet, edge_map
from separate.infer import DEFAULT_WEIGHTS, load_model
from separate.methods import get_method
from separate.train import TrainConfig, train


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


def test_ceilnet_trains_and_resumes(tmp_path):
    cfg = TrainConfig(variant="ceilnet", width=8, blocks=1, patch=32, batch=8, micro_batch=8, lr=2e-3, steps=6,
                      val_samples=8, val_every=3, ckpt_every=3, precision="fp32", threads=1)
    record = train(cfg, tmp_path)
    assert record["step"] == 6 and np.isfinite(record["psnr_t"])
    model, info = load_model(tmp_path / "best.pt")
    assert isinstance(model, CEILNet) and info["config"]["blocks"] == 1


def test_shipped_ceilnet_weights_separate_a_stack():
    model, info = load_model(WEIGHTS)
    assert isinstance(model, CEILNet) and info["card"]["training"]["steps"] > 0
    stack = np.random.default_rng(0).random((3, 40, 48, 3), dtype=np.float32)
    run, info = get_method("ceilnet")
    r_hat, t_hat = run(stack, [0.0, 45.0, 90.0])
    np.testing.assert_allclose(r_hat + t_hat, stack[0] + stack[2], atol=1e-4)
    assert info["weights"]["sha256"] == hashlib.sha256(WEIGHTS.read_bytes()).hexdigest()
    with pytest.raises(ValueError, match="not CEILNet"):
        get_method("ceilnet", weights=DEFAULT_WEIGHTS)


def test_shipped_ceilnet_removes_a_strong_blurred_reflection():
    refl, trans = layers()
    image = (0.7 * trans + 0.5 * cv2.GaussianBlur(refl, (0, 0), 4)).astype(np.float32)
    run, _ = get_method("ceilnet")
    _, t_hat = run(np.stack([image / 2] * 3), ANGLES)               # unpolarized: every shot is S0/2
    assert metrics.psnr(t_hat, 0.7 * trans) > metrics.psnr(image, 0.7 * trans) + 1.0
