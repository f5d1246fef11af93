"""Slow, dense reference renderer: the test oracle of :mod:`sgad_jax.splat`.

Written independently of the fast paths and as plainly as possible: every pixel looks at every
Gaussian, keeps those whose rounded projected centre is within the diamond window (the image model's
truncation rule, see :mod:`sgad_jax.splat`), sorts them by the depth in the view each would have at
its measured depth, without its offset (ties by index), and composites
front to back with a cumulative product. Memory is O(pixels x Gaussians): small scenes only.
"""

from __future__ import annotations

import jax.numpy as jnp

from sgad_jax import lie
from sgad_jax.splat import DILATION, MAX_ALPHA, NEAR, RADIUS_SIGMAS, Render
from sgad_jax.types import Intrinsics, PixelGaussians


def _gaussians_in_view(gs: PixelGaussians, poses: lie.SE3, view_pose: lie.SE3, intr: Intrinsics):
    """Flattened (n,) centre, depth, the depth of the same ray's point at the measured depth,
    conic, opacity and (n, 3) colour of all frames' Gaussians in the view."""
    f, h, w = gs.depth.shape
    K = jnp.array([[intr.fx, 0.0, intr.cx], [0.0, intr.fy, intr.cy], [0.0, 0.0, 1.0]], gs.depth.dtype)
    v, u = jnp.meshgrid(jnp.arange(h), jnp.arange(w), indexing="ij")
    pix = jnp.stack([u, v, jnp.ones_like(u)], -1).astype(gs.depth.dtype)  # (h, w, 3)
    rays = pix @ jnp.linalg.inv(K).T  # z = 1
    pts_src = rays[None] * gs.z[..., None]  # (f, h, w, 3)
    world_from_src = poses.as_matrix()  # (f, 4, 4)
    view_from_world = view_pose.inverse().as_matrix()
    M = view_from_world[None] @ world_from_src  # (f, 4, 4)
    pts = jnp.einsum("fij,fhwj->fhwi", M[:, :3, :3], pts_src) + M[:, None, None, :3, 3]
    pts = pts.reshape(-1, 3)
    measured = jnp.einsum("fj,fhwj->fhw", M[:, 2, :3], rays[None] * gs.depth[..., None]) + M[:, None, None, 2, 3]
    z = pts[:, 2]
    uv = (pts @ K.T)[:, :2] / z[:, None]
    # EWA Jacobian of the projection at each centre; isotropic 3D covariance r^2 I.
    x, y = pts[:, 0], pts[:, 1]
    zero = jnp.zeros_like(z)
    J = jnp.stack(
        [jnp.stack([intr.fx / z, zero, -intr.fx * x / z**2], -1), jnp.stack([zero, intr.fy / z, -intr.fy * y / z**2], -1)],
        -2,
    )  # (n, 2, 3)
    r2 = ((gs.radius / RADIUS_SIGMAS) ** 2).reshape(-1)
    cov = r2[:, None, None] * (J @ jnp.swapaxes(J, -1, -2)) + DILATION * jnp.eye(2, dtype=z.dtype)
    conic = jnp.linalg.inv(cov)
    opacity = jnp.where(z > NEAR, gs.opacity.reshape(-1), 0.0)
    return uv, z, measured.reshape(-1), conic, opacity, gs.rgb.reshape(-1, 3)


def render(
    gs: PixelGaussians, poses: lie.SE3, view_pose: lie.SE3, intr: Intrinsics, *, window: int = 3
) -> Render:
    """Render frames ``gs`` (stacked ``(f, h, w)``) at ``poses`` into ``view_pose``, densely, in the
    order of each Gaussian's depth in the view at its measured depth ``gs.depth``."""
    uv, z, measured, conic, opacity, rgb = _gaussians_in_view(gs, poses, view_pose, intr)
    h, w = intr.height, intr.width
    r = window // 2
    pv, pu = jnp.meshgrid(jnp.arange(h), jnp.arange(w), indexing="ij")
    p = jnp.stack([pu, pv], -1).reshape(-1, 1, 2).astype(z.dtype)  # (P, 1, 2)
    centre = jnp.round(uv)  # (n, 2)
    in_window = (jnp.sum(jnp.abs(p - centre[None]), axis=-1) <= r) & (z[None] > NEAR)  # (P, n), the diamond
    d = p - uv[None]  # (P, n, 2)
    power = 0.5 * jnp.einsum("pni,nij,pnj->pn", d, conic, d)
    alpha = jnp.where(in_window, jnp.minimum(opacity[None] * jnp.exp(-power), MAX_ALPHA), 0.0)
    order = jnp.argsort(measured, stable=True)  # ties by index; the same for every pixel
    a = alpha[:, order]
    trans = jnp.cumprod(jnp.concatenate([jnp.ones_like(a[:, :1]), 1.0 - a[:, :-1]], axis=1), axis=1)
    wgt = a * trans
    color = wgt @ rgb[order]
    depth = wgt @ z[order]
    return Render(rgb=color.reshape(h, w, 3), depth=depth.reshape(h, w), alpha=wgt.sum(1).reshape(h, w))
