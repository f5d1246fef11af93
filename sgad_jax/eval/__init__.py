"""Evaluation metrics."""

from sgad_jax.eval.ate import align_umeyama, ate, rpe
from sgad_jax.eval.image import lpips, ms_ssim, psnr, ssim
from sgad_jax.eval.lpips_weights import LPIPSChecksumError, LPIPSUnavailable, LPIPSWeights, fetch_lpips_weights, load_lpips_weights

__all__ = [
    "LPIPSChecksumError",
    "LPIPSUnavailable",
    "LPIPSWeights",
    "align_umeyama",
    "ate",
    "rpe",
    "fetch_lpips_weights",
    "load_lpips_weights",
    "lpips",
    "ms_ssim",
    "psnr",
    "ssim",
]
