"""Pinhole camera maths: pixel grid, back-projection, projection (OpenCV axes)."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from sgad_jax.types import Intrinsics


def pixel_grid(height: int, width: int, *, stride: int = 1, offset: int = 0) -> tuple[Float[Array, "h w"], Float[Array, "h w"]]:
    """Pixel centres ``(u, v)`` of every ``stride``-th pixel starting at ``offset`` (u: column, v: row)."""
    v = jnp.arange(offset, height, stride, dtype=jnp.float32)
    u = jnp.arange(offset, width, stride, dtype=jnp.float32)
    return jnp.meshgrid(u, v, indexing="xy")


def backproject(
    u: Float[Array, "*s"], v: Float[Array, "*s"], depth: Float[Array, "*s"], intr: Intrinsics
) -> Float[Array, "*s 3"]:
    """Camera-frame point of pixel ``(u, v)`` at z-depth ``depth``."""
    x = (u - intr.cx) / intr.fx * depth
    y = (v - intr.cy) / intr.fy * depth
    return jnp.stack([x, y, depth], axis=-1)


def backproject_image(depth: Float[Array, "h w"], intr: Intrinsics) -> Float[Array, "h w 3"]:
    u, v = pixel_grid(depth.shape[-2], depth.shape[-1])
    return backproject(u, v, depth, intr)


def project(p_c: Float[Array, "*s 3"], intr: Intrinsics, min_depth: float = 1e-6) -> tuple[Float[Array, "*s"], Float[Array, "*s"], Float[Array, "*s"]]:
    """Pixel coordinates ``(u, v)`` and depth ``z`` of camera-frame points.

    Points at ``z <= min_depth`` get a safe denominator (NaN-free gradients); mask them with ``z``.
    """
    z = p_c[..., 2]
    safe = jnp.where(z > min_depth, z, 1.0)
    u = intr.fx * p_c[..., 0] / safe + intr.cx
    v = intr.fy * p_c[..., 1] / safe + intr.cy
    return u, v, z
