"""Evaluation metrics."""

from sgad_jax.eval.ate import align_umeyama, ate

__all__ = ["align_umeyama", "ate"]
