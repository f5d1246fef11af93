"""Mapping losses: L1, same-padded SSIM (as in the 3DGS loss) and masked depth L1."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1, SSIM_C2 = 0.01**2, 0.03**2


def _masked_mean(x: Float[Array, "h w"], mask: Bool[Array, "h w"] | Float[Array, "h w"] | None) -> Float[Array, ""]:
    if mask is None:
        return jnp.mean(x)
    m = mask.astype(x.dtype)
    return jnp.sum(x * m) / jnp.maximum(jnp.sum(m), 1.0)


def channel_mean(x: Float[Array, "..."], axis: int) -> Float[Array, "..."]:
    """Mean over a (short) channel axis as a sum of slices: XLA:CPU turns ``jnp.mean(x, axis)``
    followed by a full reduction into one XNNPACK reduction that is much slower."""
    parts = [jax.lax.index_in_dim(x, i, axis, keepdims=False) for i in range(x.shape[axis])]
    return sum(parts) / len(parts)


def l1(pred: Float[Array, "h w c"], target: Float[Array, "h w c"], mask=None) -> Float[Array, ""]:
    """Mean absolute error over the pixels in ``mask`` (all pixels if ``None``), averaged over channels."""
    return _l1_cf(jnp.moveaxis(pred, -1, 0), jnp.moveaxis(target, -1, 0), mask)


def _l1_cf(x: Float[Array, "c h w"], y: Float[Array, "c h w"], mask) -> Float[Array, ""]:
    return _masked_mean(channel_mean(jnp.abs(x - y), 0), mask)


def depth_l1(pred: Float[Array, "h w"], target: Float[Array, "h w"], mask) -> Float[Array, ""]:
    """Mean absolute depth error over ``mask`` (the valid-depth pixels)."""
    return _masked_mean(jnp.abs(pred - target), mask)


def _gauss_window(dtype=np.float32) -> np.ndarray:
    """The SSIM window's normalised 1D Gaussian (11 taps, sigma 1.5), computed in float64."""
    x = np.arange(SSIM_WINDOW, dtype=np.float64) - SSIM_WINDOW // 2
    g = np.exp(-(x**2) / (2.0 * SSIM_SIGMA**2))
    return (g / g.sum()).astype(dtype)


def filter_valid(x: Float[Array, "... h w"]) -> Float[Array, "... h-10 w-10"]:
    """Separable 11x11 Gaussian filter keeping only the outputs whose window lies inside the image.

    A sum of 11 shifted slices per axis, rows first: exact float32 arithmetic on any device (a
    matrix product would be TF32 on GPUs), and on XLA:CPU the loss's forward and backward pass
    are a third faster than with tiled products with a Toeplitz matrix."""
    g = _gauss_window(x.dtype)
    h, w = x.shape[-2:]
    n = SSIM_WINDOW - 1
    y = sum(g[i] * x[..., i : h - n + i, :] for i in range(SSIM_WINDOW))
    return sum(g[i] * y[..., :, i : w - n + i] for i in range(SSIM_WINDOW))


def _blur_same(x: Float[Array, "... h w"]) -> Float[Array, "... h w"]:
    """The same filter with zero padding ('same' output, as 3DGS's conv2d). It is self-adjoint (a
    symmetric kernel with zero padding), which the SSIM gradient uses."""
    p = SSIM_WINDOW // 2
    return filter_valid(jnp.pad(x, [(0, 0)] * (x.ndim - 2) + [(p, p), (p, p)]))


def _ssim(mx, my, sxx, syy, sxy):
    return ((2 * mx * my + SSIM_C1) * (2 * sxy + SSIM_C2)) / ((mx * mx + my * my + SSIM_C1) * (sxx + syy + SSIM_C2))


class SSIMTarget(NamedTuple):
    """A target image (channel-first) with its local means and variances: what SSIM needs of it,
    computed once per view (:func:`ssim_target`) instead of at every optimiser step."""

    image: Float[Array, "c h w"]
    mean: Float[Array, "c h w"]
    var: Float[Array, "c h w"]


def ssim_target(target: Float[Array, "h w c"]) -> SSIMTarget:
    """The SSIM statistics of a target image ``(h, w, c)`` (differentiable)."""
    y = jnp.moveaxis(target, -1, 0)
    my, eyy = _blur_same(jnp.stack([y, y * y]))
    return SSIMTarget(y, my, eyy - my * my)


def _ssim_stats(x, target: SSIMTarget):
    y, my, syy = target
    mx, exx, exy = _blur_same(jnp.stack([x, x * x, x * y]))
    return mx, my, exx - mx * mx, syy, exy - mx * my


def ssim_map(pred: Float[Array, "h w c"], target: Float[Array, "h w c"]) -> Float[Array, "h w"]:
    """Per-pixel SSIM (channel mean) with a same-padded 11x11 Gaussian window, sigma 1.5, data range 1.

    This is the SSIM of the 3DGS training loss (zero padding at the border); the evaluation metric
    with valid filtering is :func:`sgad_jax.eval.image.ssim`.
    """
    return channel_mean(_ssim(*_ssim_stats(jnp.moveaxis(pred, -1, 0), ssim_target(target))), 0)


@jax.custom_vjp
def _weighted_ssim(x: Float[Array, "c h w"], target: SSIMTarget, weight: Float[Array, "h w"]) -> Float[Array, ""]:
    """``sum_p weight(p) mean_c SSIM(x, y)(c, p)``, with a hand-written gradient: 3 blurs instead
    of autodiff's transposed ones and the layout copies it made on XLA:CPU. The target's gradient
    is returned with respect to its image, mean and variance (autodiff of :func:`ssim_target`
    carries it on to the image)."""
    return _weighted_ssim_fwd(x, target, weight)[0]


def _weighted_ssim_fwd(x, target, weight):
    stats = _ssim_stats(x, target)
    s = _ssim(*stats)
    return jnp.sum(weight * channel_mean(s, 0)), (x, target.image, weight, stats, s)


def _weighted_ssim_bwd(res, g):
    x, y, weight, (mx, my, sxx, syy, sxy), s = res
    gw = g * weight / x.shape[0]
    a1, a2 = 2 * mx * my + SSIM_C1, 2 * sxy + SSIM_C2
    b1, b2 = mx * mx + my * my + SSIM_C1, sxx + syy + SSIM_C2
    g_sxy = gw * 2 * a1 / (b1 * b2)  # d s / d sxy
    g_var = -gw * s / b2  # d s / d sxx = d s / d syy
    # d s / d mx through s's own mx terms and through sxx = E[x^2] - mx^2, sxy = E[xy] - mx my.
    g_mx = gw * (2 * my * a2 / (b1 * b2) - 2 * mx * s / b1) - 2 * mx * g_var - my * g_sxy
    g_my = gw * (2 * mx * a2 / (b1 * b2) - 2 * my * s / b1) - mx * g_sxy
    b_mx, b_exx, b_exy = _blur_same(jnp.stack([g_mx, g_var, g_sxy]))  # the blur is self-adjoint
    dx = b_mx + 2 * x * b_exx + y * b_exy
    return dx, SSIMTarget(x * b_exy, g_my, g_var), g * channel_mean(s, 0)


_weighted_ssim.defvjp(_weighted_ssim_fwd, _weighted_ssim_bwd)


def ssim_loss(pred, target, mask=None) -> Float[Array, ""]:
    """``1 - SSIM`` averaged over ``mask`` (the same-padded SSIM of :func:`ssim_map`)."""
    return _ssim_loss_cf(jnp.moveaxis(pred, -1, 0), ssim_target(target), mask)


def _ssim_loss_cf(x: Float[Array, "c h w"], target: SSIMTarget, mask) -> Float[Array, ""]:
    m = jnp.ones(x.shape[1:], x.dtype) if mask is None else mask.astype(x.dtype)
    return 1.0 - _weighted_ssim(x, target, m / jnp.maximum(jnp.sum(m), 1.0))


def mapping_loss(
    rgb: Float[Array, "h w 3"],
    depth: Float[Array, "h w"],
    target_rgb: Float[Array, "h w 3"] | SSIMTarget,
    target_depth: Float[Array, "h w"],
    valid: Bool[Array, "h w"],
    mask=None,
    *,
    weight_l1: float = 0.8,
    weight_ssim: float = 0.2,
    weight_depth: float = 1.0,
) -> Float[Array, ""]:
    """SGAD-SLAM's mapping loss ``rho L1 + tau (1 - SSIM) + sigma U L1_depth`` on the pixels in
    ``mask``. The target colour may be given as its :func:`ssim_target` (an optimiser loop then
    computes its statistics once)."""
    depth_mask = valid if mask is None else valid & (mask > 0)
    target = target_rgb if isinstance(target_rgb, SSIMTarget) else ssim_target(target_rgb)
    # Channel-first inside: the renderer composites channel-first, and on XLA:CPU reductions over a
    # minor channel axis are much slower.
    x = jnp.moveaxis(rgb, -1, 0)
    return (
        weight_l1 * _l1_cf(x, target.image, mask)
        + weight_ssim * _ssim_loss_cf(x, target, mask)
        + weight_depth * depth_l1(depth, target_depth, depth_mask)
    )
