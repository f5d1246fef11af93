"""Tracking: align a frame's geometry Gaussians to the global set T with GICP (pure functions).

``track`` is jittable, vmappable and differentiable: the pose it returns is the root of the GICP
gradient, so derivatives with respect to the frame's points or the geometry set follow from the
implicit function theorem (``jax.lax.custom_root``), not from unrolling the solver.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from sgad_jax import geometry, gicp, lie
from sgad_jax.config import TrackConfig
from sgad_jax.types import GeometrySet, PointCloud, TrackInfo


def transform_cloud(T: lie.SE3, cloud: PointCloud) -> PointCloud:
    """The cloud in the frame ``T`` maps to: points, covariances and normals."""
    R, t = lie.rotation_components(T)
    return dataclasses.replace(
        cloud,
        points=lie.transform_points(R, t, cloud.points),
        covs=gicp.rotate_sym(R, cloud.covs),
        normals=lie.transform_points(R, jnp.zeros(3), cloud.normals),
    )


def associate(cfg: TrackConfig, geom: GeometrySet, q: Float[Array, "3 m"], valid: Bool[Array, " m"]) -> tuple[Int[Array, " m"], Bool[Array, " m"]]:
    """Correspondences by point-to-surface distance ``|n_b . (q - b)|`` (SGAD-SLAM Sec. 3.3).

    Candidates are the geometry Gaussians of the 2x2x2 voxel block around ``q`` within
    ``cfg.max_correspondence``; among them the one whose surface passes closest to ``q`` wins.

    Returns:
        (index into ``geom`` (m,), found mask (m,)).
    """
    idx, hit = geometry.candidates(geom, q)  # (8, m)
    e = [q[a] - geom.points[a][idx] for a in range(3)]
    d2 = e[0] ** 2 + e[1] ** 2 + e[2] ** 2
    ok = hit & (d2 <= cfg.max_correspondence**2) & valid
    surf = (sum(geom.normals[a][idx] * e[a] for a in range(3)))
    score = jnp.where(ok, surf * surf + cfg.nn_weight * d2, jnp.inf)
    best = jnp.min(score, axis=0)
    # First candidate attaining the minimum, without argmin (slow on XLA:CPU).
    attains = (score == best) & ok
    pick = attains & (jnp.cumsum(attains, axis=0) == 1)
    return jnp.sum(jnp.where(pick, idx, 0), axis=0), jnp.any(ok, axis=0)


def _residuals(cfg, geom, cloud, R, t):
    q = lie.transform_points(R, t, cloud.points)
    j, found = associate(cfg, geom, q, cloud.valid)
    return q, j, found


def cost(cfg: TrackConfig, geom: GeometrySet, cloud: PointCloud, T_wc: lie.SE3) -> Float[Array, ""]:
    """The GICP cost of ``cloud`` (camera frame) placed at ``T_wc`` against ``geom``.

    Correspondences are chosen at ``T_wc`` and held constant under differentiation.
    """
    R, t = lie.rotation_components(T_wc)
    _, j, found = _residuals(cfg, geom, cloud, jax.lax.stop_gradient(R), jax.lax.stop_gradient(t))
    return gicp.gicp_cost(R, t, cloud.points, cloud.covs, geom.points[:, j], geom.covs[:, j], found.astype(jnp.float32))


def _gauss_newton(cfg: TrackConfig, geom: GeometrySet, cloud: PointCloud, T0: lie.SE3) -> tuple[lie.SE3, TrackInfo]:
    def body(state):
        T, it, _, _, _ = state
        R, t = lie.rotation_components(T)
        q, j, found = _residuals(cfg, geom, cloud, R, t)
        w = found.astype(jnp.float32)
        M = gicp.sym_inverse(geom.covs[:, j] + gicp.rotate_sym(R, cloud.covs))
        H, g, c = gicp.linearise(q, q - geom.points[:, j], M, w)
        n_in = jnp.sum(found)
        enough = n_in >= 6
        H = H + 1e-6 * jnp.trace(H) / 6.0 * jnp.eye(6) + jnp.where(enough, 0.0, 1.0) * jnp.eye(6)
        xi = jnp.where(enough, -jnp.linalg.solve(H, g), 0.0)
        T = lie.retract_left(T, xi)
        small = (jnp.max(jnp.abs(xi[:3])) < cfg.tolerance) & (jnp.max(jnp.abs(xi[3:])) < cfg.tolerance)
        return T, it + 1, small | ~enough, c, n_in.astype(jnp.int32)

    def cond(state):
        _, it, done, _, _ = state
        return (it < cfg.max_iterations) & ~done

    init = (T0, jnp.zeros((), jnp.int32), jnp.zeros((), bool), jnp.zeros(()), jnp.zeros((), jnp.int32))
    T, it, done, c, n_in = jax.lax.while_loop(cond, body, init)
    info = TrackInfo(iterations=it, converged=done, cost=c, inliers=n_in, points=jnp.sum(cloud.valid).astype(jnp.int32))
    return T, info


def track(cfg: TrackConfig, geom: GeometrySet, cloud: PointCloud, T_guess: lie.SE3) -> tuple[lie.SE3, TrackInfo]:
    """Estimate the camera-to-world pose of ``cloud`` (camera-frame geometry Gaussians) against T.

    Gauss-Newton on SE(3) from ``T_guess`` until the update falls below ``cfg.tolerance`` or
    ``cfg.max_iterations`` is reached. Differentiable through ``jax.lax.custom_root``: the returned
    pose ``exp(xi*) T_guess`` solves ``d cost / d xi = 0``.

    Args:
        cfg: tracking config.
        geom: the global geometry set T (world frame).
        cloud: the frame's geometry Gaussians, from :func:`sgad_jax.gicp.frame_points`.
        T_guess: initial camera-to-world pose (e.g. constant velocity).

    Returns:
        (T_wc, TrackInfo).
    """

    def grad_at(xi):
        T = lie.exp(xi) @ T_guess
        return jax.grad(lambda eps: cost(cfg, geom, cloud, lie.exp(eps) @ T))(jnp.zeros(6))

    def solve(_, xi0):
        T, info = _gauss_newton(cfg, geom, cloud, lie.exp(xi0) @ T_guess)
        return lie.log(T @ T_guess.inverse()), info

    def tangent_solve(g, y):
        return jnp.linalg.solve(jax.jacfwd(g)(y), y)

    xi, info = jax.lax.custom_root(grad_at, jnp.zeros(6), solve, tangent_solve, has_aux=True)
    return lie.exp(xi) @ T_guess, info
