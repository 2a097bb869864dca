"""Image quality figures: mutual information from one bincount, as np.histogram2d would give it; SSIM as scikit-image gives it."""

import numpy as np
import pytest

from separate import metrics


def histogram2d_information(a: np.ndarray, b: np.ndarray, bins: int = 32) -> float:
    """Mutual information (nats) from ``np.histogram2d`` over each image's 1–99% range: what
    `metrics.mutual_information` must reproduce bit for bit."""
    lo_a, hi_a = np.percentile(a, [1, 99])
    lo_b, hi_b = np.percentile(b, [1, 99])
    joint, _, _ = np.histogram2d(a.ravel(), b.ravel(), bins=bins, range=[[lo_a, hi_a + 1e-9], [lo_b, hi_b + 1e-9]])
    p = joint / max(joint.sum(), 1)
    pa, pb = p.sum(axis=1, keepdims=True), p.sum(axis=0, keepdims=True)
    nz = p > 0
    return float((p[nz] * np.log(p[nz] / (pa @ pb)[nz])).sum())


def pairs():
    """Value pairs with ties, values on bin edges, a constant image and a wide range of scales."""
    rng = np.random.default_rng(7)
    a = rng.normal(size=5000) * 30
    yield a, 0.3 * a + rng.normal(size=5000)
    yield np.round(a, 0), np.round(a / 4) * 4                  # many values exactly on edges
    ramp = np.linspace(0.0, 1.0, 3300)
    yield ramp, ramp[::-1].copy()
    yield a * 1e-4, np.zeros_like(a)
    yield rng.exponential(size=(64, 48)), rng.exponential(size=(64, 48))


@pytest.mark.parametrize("k", range(5))
def test_mutual_information_equals_the_histogram2d_figure(k):
    a, b = list(pairs())[k]
    assert metrics.mutual_information(a, b) == histogram2d_information(a, b)


def test_mutual_information_rows_gives_each_rows_figure():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(4, 2000))
    b = a * np.array([[0.0], [0.5], [1.0], [-2.0]]) + rng.normal(size=(4, 2000))
    rows = metrics.mutual_information_rows(a, b)
    assert rows.tolist() == [histogram2d_information(x, y) for x, y in zip(a, b)]
    assert rows[0] < rows[1] < rows[2]                         # more shared signal, more information


def test_mutual_information_refuses_non_finite_values():
    a = np.array([0.0, 1.0, np.nan, 2.0])
    with pytest.raises(ValueError, match="finite"):
        metrics.mutual_information(a, a)


def test_ssim_is_scikit_images_structural_similarity():
    from skimage.metrics import structural_similarity

    rng = np.random.default_rng(5)
    for shape, noise in (((96, 128, 3), 0.002), ((64, 80, 3), 0.05), ((40, 33, 1), 0.3), ((7, 9, 3), 0.1)):
        truth = rng.random(shape).astype(np.float32)
        truth = (truth + np.roll(truth, 1, axis=0) + np.roll(truth, 1, axis=1)) / 3      # some structure
        estimate = np.clip(truth + rng.normal(0, noise, shape), 0, 1)                   # float64
        want = structural_similarity(estimate, truth, channel_axis=-1, data_range=1.0)
        assert metrics.ssim(estimate, truth) == pytest.approx(want, abs=1e-6)
    assert metrics.ssim(truth, truth) == pytest.approx(1.0, abs=1e-6)
    with pytest.raises(ValueError, match="sides ≥ 7"):
        metrics.ssim(truth[:6], truth[:6])
