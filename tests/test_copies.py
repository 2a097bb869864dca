"""separate.copies: light that R̂ shows as a copy of T̂ goes back to T̂; a reflection of another
scene stays."""

import cv2
import numpy as np
import pytest

from separate.copies import copy_share, return_copies


def texture(seed: int, shape: tuple[int, int], sigma: float = 2.0) -> np.ndarray:
    """A positive random texture, H×W×3 float32 (mean ~0.5)."""
    noise = np.random.default_rng(seed).normal(size=(*shape, 3)).astype(np.float32)
    smooth = cv2.GaussianBlur(noise, (0, 0), sigma)
    return (0.5 + 0.5 * smooth / smooth.std()).clip(0.05, None).astype(np.float32)


def ramp(shape: tuple[int, int], low: float, high: float) -> np.ndarray:
    """A smooth multiplier turning from ``low`` to ``high`` across the columns, H×W×1."""
    return np.linspace(low, high, shape[1], dtype=np.float32)[None, :, None].repeat(shape[0], 0)


@pytest.mark.parametrize("shape", [(200, 260), (700, 1100)])
def test_a_reflection_layer_that_copies_the_transmission_goes_back_to_it(shape):
    """No glass: the scene's own polarization, read as R̂ = k(x)·T̂ with a smooth k (and a green
    tint, as a sensor's crosstalk gives), is returned to T̂; at either size, below and above
    the statistics' grid."""
    t_hat = texture(1, shape)
    r_hat = t_hat * ramp(shape, 0.05, 0.3) * np.array([0.5, 1.0, 0.6], np.float32)
    r_out, t_out = return_copies(r_hat, t_hat)
    assert r_out.sum() < 0.1 * r_hat.sum()
    np.testing.assert_allclose(t_out, t_hat + r_hat, rtol=0.1)


def test_a_reflection_of_another_scene_stays_in_the_reflection():
    shape = (256, 256)
    t_hat, r_hat = texture(2, shape), 0.4 * texture(3, shape)
    coarse = ramp(shape, 0.3, 1.0)                         # both layers brighter on one side
    r_out, t_out = return_copies(r_hat * coarse, t_hat * coarse)
    assert r_out.sum() > 0.98 * (r_hat * coarse).sum()


def test_a_partial_copy_is_returned_in_part():
    """R̂ holds a real reflection plus a copy of T̂: less than the whole R̂ moves, and not the
    reflection's share."""
    shape = (256, 256)
    t_hat, reflection = texture(4, shape), 0.3 * texture(5, shape)
    r_hat = reflection + 0.2 * t_hat
    r_out, _ = return_copies(r_hat, t_hat)
    assert 0.6 * reflection.sum() < r_out.sum() < 0.98 * r_hat.sum()


def test_the_sum_is_kept_the_layers_stay_non_negative_and_the_inputs_untouched():
    shape = (128, 160)
    t_hat = texture(6, shape)
    r_hat = 0.2 * t_hat + 0.1 * texture(7, shape)
    r_hat[:10] = 0.0
    before = (r_hat.copy(), t_hat.copy())
    r_out, t_out = return_copies(r_hat, t_hat)
    np.testing.assert_allclose(r_out + t_out, r_hat + t_hat, atol=1e-6)
    assert r_out.sum() < 0.8 * r_hat.sum()                 # half of R̂ copies T̂ here
    assert r_out.min() >= 0.0 and (t_out >= t_hat).all()
    np.testing.assert_array_equal(r_hat, before[0])
    np.testing.assert_array_equal(t_hat, before[1])
    assert r_out.dtype == np.float32 and r_out.shape == r_hat.shape


def test_one_channel_and_float64_layers_come_back_as_float32_of_their_shape():
    shape = (96, 700)
    t_hat = texture(8, shape)[..., :1].astype(np.float64)
    r_hat = 0.3 * t_hat
    r_out, t_out = return_copies(r_hat, t_hat)
    assert r_out.shape == t_out.shape == (96, 700, 1) and r_out.dtype == t_out.dtype == np.float32
    assert r_out.sum() < 0.1 * r_hat.sum()


def test_arguments_are_checked():
    image = np.ones((8, 8, 3), np.float32)
    with pytest.raises(ValueError, match="one shape"):
        copy_share(image, image[..., :1])
    with pytest.raises(ValueError, match="H×W×C"):
        copy_share(image[..., 0], image[..., 0])
    with pytest.raises(ValueError, match="float"):
        copy_share(image.astype(np.uint16), image.astype(np.uint16))
    with pytest.raises(ValueError, match="C ≤ 4"):
        copy_share(np.ones((8, 8, 5), np.float32), np.ones((8, 8, 5), np.float32))
    with pytest.raises(ValueError, match="rho"):
        copy_share(image, image, rho=(0.9, 0.5))
    with pytest.raises(ValueError, match="sigma"):
        copy_share(image, image, sigma=0.0)
