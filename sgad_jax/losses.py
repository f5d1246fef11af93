"""Mapping losses: L1, same-padded SSIM (as in the 3DGS loss) and masked depth L1."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
_C1, _C2 = 0.01**2, 0.03**2


def _masked_mean(x: Float[Array, "h w"], mask: Bool[Array, "h w"] | Float[Array, "h w"] | None) -> Float[Array, ""]:
    if mask is None:
        return jnp.mean(x)
    m = mask.astype(x.dtype)
    return jnp.sum(x * m) / jnp.maximum(jnp.sum(m), 1.0)


def l1(pred: Float[Array, "h w c"], target: Float[Array, "h w c"], mask=None) -> Float[Array, ""]:
    """Mean absolute error over the pixels in ``mask`` (all pixels if ``None``), averaged over channels."""
    return _masked_mean(jnp.mean(jnp.abs(pred - target), axis=-1), mask)


def depth_l1(pred: Float[Array, "h w"], target: Float[Array, "h w"], mask) -> Float[Array, ""]:
    """Mean absolute depth error over ``mask`` (the valid-depth pixels)."""
    return _masked_mean(jnp.abs(pred - target), mask)


def _gauss_kernel(dtype) -> Float[Array, " k"]:
    x = jnp.arange(SSIM_WINDOW, dtype=dtype) - SSIM_WINDOW // 2
    k = jnp.exp(-(x**2) / (2 * SSIM_SIGMA**2))
    return k / jnp.sum(k)


def _blur_same(x: Float[Array, "c h w"]) -> Float[Array, "c h w"]:
    """Separable 11x11 Gaussian filter with zero padding ('same' output, as 3DGS's conv2d)."""
    k = _gauss_kernel(x.dtype)
    c = x.shape[0]
    dn = ("NCHW", "OIHW", "NCHW")
    p = SSIM_WINDOW // 2
    y = jax.lax.conv_general_dilated(
        x[None], jnp.tile(k[None, None, :, None], (c, 1, 1, 1)), (1, 1), ((p, p), (0, 0)), dimension_numbers=dn, feature_group_count=c
    )
    y = jax.lax.conv_general_dilated(
        y, jnp.tile(k[None, None, None, :], (c, 1, 1, 1)), (1, 1), ((0, 0), (p, p)), dimension_numbers=dn, feature_group_count=c
    )
    return y[0]


def ssim_map(pred: Float[Array, "h w c"], target: Float[Array, "h w c"]) -> Float[Array, "h w"]:
    """Per-pixel SSIM (channel mean) with a same-padded 11x11 Gaussian window, sigma 1.5, data range 1.

    This is the SSIM of the 3DGS training loss (zero padding at the border); the evaluation metric
    with valid filtering is :func:`sgad_jax.eval.image.ssim`.
    """
    x, y = jnp.moveaxis(pred, -1, 0), jnp.moveaxis(target, -1, 0)
    mx, my = _blur_same(x), _blur_same(y)
    sxx = _blur_same(x * x) - mx * mx
    syy = _blur_same(y * y) - my * my
    sxy = _blur_same(x * y) - mx * my
    s = ((2 * mx * my + _C1) * (2 * sxy + _C2)) / ((mx * mx + my * my + _C1) * (sxx + syy + _C2))
    return jnp.mean(s, axis=0)


def ssim_loss(pred, target, mask=None) -> Float[Array, ""]:
    """``1 - SSIM`` averaged over ``mask``."""
    return 1.0 - _masked_mean(ssim_map(pred, target), mask)


def mapping_loss(
    rgb: Float[Array, "h w 3"],
    depth: Float[Array, "h w"],
    target_rgb: Float[Array, "h w 3"],
    target_depth: Float[Array, "h w"],
    valid: Bool[Array, "h w"],
    mask=None,
    *,
    weight_l1: float = 0.8,
    weight_ssim: float = 0.2,
    weight_depth: float = 1.0,
) -> Float[Array, ""]:
    """SGAD-SLAM's mapping loss ``rho L1 + tau (1 - SSIM) + sigma U L1_depth`` on the pixels in ``mask``."""
    depth_mask = valid if mask is None else valid & (mask > 0)
    return (
        weight_l1 * l1(rgb, target_rgb, mask)
        + weight_ssim * ssim_loss(rgb, target_rgb, mask)
        + weight_depth * depth_l1(depth, target_depth, depth_mask)
    )
