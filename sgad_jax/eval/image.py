"""Image metrics of renders: PSNR (three protocols), SSIM, MS-SSIM, LPIPS.

Images are float ``(h, w, 3)`` in [0, 1]. SSIM and MS-SSIM follow ``pytorch_msssim`` (11x11 Gaussian
window, sigma 1.5, data range 1, valid filtering), which matches scikit-image's
``structural_similarity(gaussian_weights=True, sigma=1.5, use_sample_covariance=False)``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from sgad_jax.losses import SSIM_WINDOW, _blur_same

PROTOCOLS = ("whole", "valid", "zeroed")
MS_SSIM_WEIGHTS = (0.0448, 0.2856, 0.3001, 0.2363, 0.1333)
#: MS-SSIM needs every side larger than (window - 1) * 2^4 (pytorch_msssim's assertion).
MS_SSIM_MIN_SIZE = (SSIM_WINDOW - 1) * 2**4 + 1
_C1, _C2 = 0.01**2, 0.03**2


class LPIPSUnavailable(RuntimeError):
    """No LPIPS weights could be found."""


def psnr(
    pred: Float[Array, "h w 3"], target: Float[Array, "h w 3"], mask: Bool[Array, "h w"] | None = None, protocol: str = "whole"
) -> float:
    """PSNR in dB (data range 1) under one of the papers' protocols:

    * ``whole``: MSE over all pixels (Gaussian-SLAM);
    * ``valid``: MSE over the pixels where ``mask`` (valid depth) holds (Point-SLAM);
    * ``zeroed``: both images zeroed where ``mask`` is false, MSE over all pixels (SplaTAM, GS-ICP).
    """
    if protocol not in PROTOCOLS:
        raise ValueError(f"unknown PSNR protocol {protocol!r}; expected one of {', '.join(PROTOCOLS)}")
    pred, target = np.asarray(pred, np.float64), np.asarray(target, np.float64)
    if protocol != "whole" and mask is None:
        raise ValueError(f"PSNR protocol {protocol!r} needs the valid-depth mask")
    err = (pred - target) ** 2
    if protocol == "whole":
        mse = err.mean()
    elif protocol == "valid":
        m = np.asarray(mask, bool)
        mse = err[m].mean() if m.any() else np.nan
    else:
        mse = (err * np.asarray(mask, bool)[..., None]).mean()
    return float(-10.0 * np.log10(max(mse, 1e-20)))


def _ssim_cs(x: Float[Array, "c h w"], y: Float[Array, "c h w"]):
    """Per-channel mean SSIM and contrast-structure term with valid filtering."""
    r = SSIM_WINDOW // 2
    mx, my, exx, eyy, exy = (b[..., r:-r, r:-r] for b in _blur_same(jnp.concatenate([x, y, x * x, y * y, x * y])).reshape(5, *x.shape))
    sxx, syy, sxy = exx - mx * mx, eyy - my * my, exy - mx * my
    cs = (2 * sxy + _C2) / (sxx + syy + _C2)
    ssim = (2 * mx * my + _C1) / (mx * mx + my * my + _C1) * cs
    return jnp.mean(ssim, axis=(-2, -1)), jnp.mean(cs, axis=(-2, -1))


def _chw(img) -> Float[Array, "c h w"]:
    return jnp.moveaxis(jnp.asarray(img, jnp.float32), -1, 0)


@jax.jit
def _ssim(pred, target):
    return jnp.mean(_ssim_cs(_chw(pred), _chw(target))[0])


def ssim(pred: Float[Array, "h w 3"], target: Float[Array, "h w 3"]) -> float:
    """Single-scale SSIM (mean over pixels and channels)."""
    if min(np.shape(pred)[:2]) < SSIM_WINDOW:
        raise ValueError(f"SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels, got {np.shape(pred)[:2]}")
    return float(_ssim(pred, target))


def _avg_pool2(x: Float[Array, "c h w"]) -> Float[Array, "c h2 w2"]:
    """2x2 average pooling, zero-padding an odd side by one pixel on both ends (pytorch_msssim)."""
    ph, pw = x.shape[-2] % 2, x.shape[-1] % 2
    x = jnp.pad(x, ((0, 0), (ph, ph), (pw, pw)))
    h, w = x.shape[-2] // 2 * 2, x.shape[-1] // 2 * 2
    x = x[:, :h, :w]
    return x.reshape(x.shape[0], h // 2, 2, w // 2, 2).mean(axis=(2, 4))


@jax.jit
def _ms_ssim(pred, target):
    x, y = _chw(pred), _chw(target)
    terms = []
    for level in range(len(MS_SSIM_WEIGHTS)):
        s, cs = _ssim_cs(x, y)
        if level < len(MS_SSIM_WEIGHTS) - 1:
            terms.append(jax.nn.relu(cs))
            x, y = _avg_pool2(x), _avg_pool2(y)
    terms.append(jax.nn.relu(s))
    w = jnp.asarray(MS_SSIM_WEIGHTS)[:, None]
    return jnp.mean(jnp.prod(jnp.stack(terms) ** w, axis=0))


def ms_ssim(pred: Float[Array, "h w 3"], target: Float[Array, "h w 3"]) -> float:
    """Multi-scale SSIM (5 scales, the weights of Wang et al. 2003), as ``pytorch_msssim.ms_ssim``."""
    if min(np.shape(pred)[:2]) < MS_SSIM_MIN_SIZE:
        raise ValueError(f"MS-SSIM needs images of at least {MS_SSIM_MIN_SIZE} pixels per side, got {np.shape(pred)[:2]}")
    return float(_ms_ssim(pred, target))


def lpips(pred: Float[Array, "h w 3"], target: Float[Array, "h w 3"]) -> float:
    """AlexNet LPIPS (placeholder until the weights loader lands)."""
    raise LPIPSUnavailable("LPIPS weights not available")
