"""Mapping losses and image metrics against direct, independent computations."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sgad_jax import losses
from sgad_jax.eval import image


def _pair(h=40, w=52, seed=0):
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:h, 0:w] / 9.0
    a = np.stack([0.5 + 0.4 * np.sin(u + c) * np.cos(v - c) for c in range(3)], -1)
    b = np.clip(a + rng.normal(0, 0.05, a.shape) + 0.1 * np.sin(3 * u)[..., None], 0, 1)
    return a.astype(np.float32), b.astype(np.float32)


def _ssim_direct(a, b, pad: bool):
    """SSIM map by explicit 11x11 window sums (zero padding if ``pad``, else valid positions only)."""
    x = np.arange(11) - 5
    g = np.exp(-(x**2) / (2 * 1.5**2))
    win = np.outer(g, g) / np.outer(g, g).sum()
    if pad:
        a = np.pad(a, ((5, 5), (5, 5), (0, 0)))
        b = np.pad(b, ((5, 5), (5, 5), (0, 0)))
    h, w = a.shape[0] - 10, a.shape[1] - 10
    out = np.zeros((h, w, a.shape[2]))
    for i in range(h):
        for j in range(w):
            pa, pb = a[i : i + 11, j : j + 11].astype(np.float64), b[i : i + 11, j : j + 11].astype(np.float64)
            mx = np.einsum("ij,ijc->c", win, pa)
            my = np.einsum("ij,ijc->c", win, pb)
            sxx = np.einsum("ij,ijc->c", win, pa * pa) - mx**2
            syy = np.einsum("ij,ijc->c", win, pb * pb) - my**2
            sxy = np.einsum("ij,ijc->c", win, pa * pb) - mx * my
            out[i, j] = ((2 * mx * my + 1e-4) * (2 * sxy + 9e-4)) / ((mx**2 + my**2 + 1e-4) * (sxx + syy + 9e-4))
    return out.mean(-1)


def test_loss_ssim_is_same_padded_ssim():
    a, b = _pair(24, 30)
    np.testing.assert_allclose(np.asarray(losses.ssim_map(jnp.asarray(a), jnp.asarray(b))), _ssim_direct(a, b, pad=True), atol=1e-4)  # float32 E[x^2] - mu^2


def test_l1_and_depth_l1_with_masks():
    a, b = _pair()
    mask = np.zeros(a.shape[:2], bool)
    mask[5:20, 10:30] = True
    np.testing.assert_allclose(float(losses.l1(a, b, mask)), np.abs(a - b)[mask].mean(), rtol=1e-5)
    np.testing.assert_allclose(float(losses.depth_l1(a[..., 0], b[..., 0], mask)), np.abs(a[..., 0] - b[..., 0])[mask].mean(), rtol=1e-5)


def test_eval_ssim_is_valid_filtered_ssim():
    a, b = _pair(30, 36)
    assert abs(image.ssim(a, b) - _ssim_direct(a, b, pad=False).mean()) < 2e-5


def test_eval_ssim_matches_scikit_image():
    from skimage import metrics
    a, b = _pair(64, 80, seed=3)
    ref = metrics.structural_similarity(
        a.astype(np.float64), b.astype(np.float64), gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0, channel_axis=-1
    )
    assert abs(image.ssim(a, b) - ref) < 2e-5


def test_psnr_protocols():
    target = np.zeros((4, 5, 3))
    pred = np.zeros((4, 5, 3))
    pred[0, 0] = 0.1  # an error at a valid pixel
    pred[3, 4] = 0.3  # and at an invalid one
    valid = np.ones((4, 5), bool)
    valid[3, 4] = False
    mse_whole = (3 * 0.01 + 3 * 0.09) / 60
    mse_valid = (3 * 0.01) / 57
    mse_zeroed = (3 * 0.01) / 60
    assert image.psnr(pred, target) == pytest.approx(-10 * np.log10(mse_whole))
    assert image.psnr(pred, target, valid, protocol="valid") == pytest.approx(-10 * np.log10(mse_valid))
    assert image.psnr(pred, target, valid, protocol="zeroed") == pytest.approx(-10 * np.log10(mse_zeroed))
    with pytest.raises(ValueError, match="unknown PSNR protocol"):
        image.psnr(pred, target, valid, protocol="masked")
    with pytest.raises(ValueError, match="needs the valid-depth mask"):
        image.psnr(pred, target, protocol="valid")


def test_ms_ssim_of_identical_images_is_one_and_small_images_are_refused():
    a, b = _pair(170, 180)
    assert image.ms_ssim(a, a) == pytest.approx(1.0, abs=1e-6)
    assert 0.0 < image.ms_ssim(a, b) < 1.0
    with pytest.raises(ValueError, match="at least 161"):
        image.ms_ssim(a[:100], b[:100])


@pytest.mark.slow
def test_ssim_loss_gradient_matches_autodiff_of_a_dense_window():
    """The hand-written SSIM gradient (pred, target and mask) against autodiff of SSIM computed with
    an explicit 11x11 window (a dense 2D convolution, float64)."""
    from jax.scipy.signal import convolve2d

    with jax.enable_x64(True):
        a, b = (jnp.asarray(x, jnp.float64) for x in _pair(23, 29, seed=4))
        x = np.arange(11) - 5
        g = np.exp(-(x**2) / (2 * 1.5**2))
        win = jnp.asarray(np.outer(g, g) / np.outer(g, g).sum())
        mask = jnp.asarray(np.random.default_rng(5).random(a.shape[:2]) > 0.3, jnp.float64)

        def dense(p, t, m):
            blur = lambda z: jnp.stack([convolve2d(z[..., c], win, mode="same") for c in range(3)], -1)  # noqa: E731
            mx, my = blur(p), blur(t)
            sxx, syy, sxy = blur(p * p) - mx**2, blur(t * t) - my**2, blur(p * t) - mx * my
            s = ((2 * mx * my + 1e-4) * (2 * sxy + 9e-4)) / ((mx**2 + my**2 + 1e-4) * (sxx + syy + 9e-4))
            return 1.0 - jnp.sum(s.mean(-1) * m) / jnp.sum(m)

        ours = jax.grad(losses.ssim_loss, argnums=(0, 1, 2))(a, b, mask)
        ref = jax.grad(dense, argnums=(0, 1, 2))(a, b, mask)
        assert float(losses.ssim_loss(a, b, mask)) == pytest.approx(float(dense(a, b, mask)), abs=1e-12)
        for o, r in zip(ours, ref):
            assert float(jnp.abs(r).max()) > 1e-6
            np.testing.assert_allclose(np.asarray(o), np.asarray(r), atol=1e-10)
