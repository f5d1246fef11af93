"""Tracking: align a frame's geometry Gaussians to the global set T with GICP (pure functions).

``track`` is jittable, vmappable and differentiable: the pose it returns is the root of the GICP
gradient, so derivatives with respect to the frame's points or the geometry set follow from the
implicit function theorem (``jax.lax.custom_root``), not from unrolling the solver.

Speed on XLA:CPU comes from splitting the correspondence search in two: the candidates of every
point (the geometry Gaussians of the 2x2x2 voxel block around it) are looked up in T once and
cached as dense ``(c, 8, m)`` arrays; each Gauss-Newton iteration then picks the best candidate with
plain arithmetic and gathers its covariance. The lookup is repeated only when a point of the frame
may have moved by more than a quarter voxel since the last one. The solver runs coarse to fine (``TrackConfig.coarse``): it converges on every
3rd point first, so that the steps on the full cloud start next to its solution; and it lengthens
updates that keep shrinking the same way (``TrackConfig.extrapolation``, :func:`_stretch`).
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


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Candidates:
    """Possible matches in T of each point of a frame: 8 per point, with the data that chooses
    among them; the covariance is taken for the chosen one only (from the geometry set's ``covs``)."""

    points: Float[Array, "3 8 m"]
    normals: Float[Array, "3 8 m"]
    slots: Int[Array, "8 m"]
    ok: Bool[Array, "8 m"]
    covs: Float[Array, "6 n"]


def gather_candidates(geom: GeometrySet, q: Float[Array, "3 m"], valid: Bool[Array, " m"]) -> Candidates:
    """The geometry Gaussians of the 2x2x2 voxel block around each world point ``q``."""
    slots, hit = geometry.candidates(geom, q)
    take = lambda a: jnp.stack([row[slots] for row in a])  # noqa: E731
    return Candidates(points=take(geom.points), normals=take(geom.normals), slots=slots, ok=hit & valid, covs=geom.covs)


def match(cfg: TrackConfig, cand: Candidates, q: Float[Array, "3 m"]) -> tuple[Float[Array, "3 m"], Float[Array, "6 m"], Bool[Array, " m"]]:
    """Pick each point's correspondence by point-to-surface distance (SGAD-SLAM Sec. 3.3).

    The score of candidate ``b`` is ``(n_b . e)^2 + nn_weight |e|^2`` with ``e = q - b``, among the
    candidates within ``cfg.max_correspondence``; ``nn_weight = 0`` is the pure point-to-surface
    distance ``|n_b . (q - b)|``, a small weight breaks its ties between far points of one plane.

    Returns:
        (residual ``q - b`` (3, m), the match's covariance (6, m), found mask (m,)).
    """
    # Written on (8, m) rows: XLA:CPU is much slower on the same maths over (3, 8, m) tensors.
    e = [q[a][None] - cand.points[a] for a in range(3)]
    d2 = e[0] * e[0] + e[1] * e[1] + e[2] * e[2]
    ok = cand.ok & (d2 <= cfg.max_correspondence**2)
    surf = cand.normals[0] * e[0] + cand.normals[1] * e[1] + cand.normals[2] * e[2]
    score = jnp.where(ok, surf * surf + cfg.nn_weight * d2, jnp.inf)
    best = jnp.min(score, axis=0)
    # The first candidate attaining the minimum (argmin is slow on XLA:CPU), then its point and
    # covariance by one gather each, cheaper than a one-hot sum over the 8 rows. (Only the chosen
    # candidate's covariance is gathered: eight per lookup would cost more than one per match.)
    n, m = score.shape
    row = jnp.arange(n, dtype=jnp.int32)[:, None]
    first = jnp.min(jnp.where((score == best) & ok, row, n - 1), axis=0)
    at = first * m + jnp.arange(m, dtype=jnp.int32)
    found = jnp.any(ok, axis=0)
    pick = lambda rows: jnp.stack([jnp.where(found, r.reshape(-1)[at], 0.0) for r in rows])  # noqa: E731
    slot = cand.slots.reshape(-1)[at]
    cov_b = jnp.stack([jnp.where(found, c[slot], 0.0) for c in cand.covs])
    return jnp.where(found, q - pick(cand.points), 0.0), cov_b, found


MIN_POINTS = 6  # matched points a 6-DoF pose update needs

#: Points nearer than this (metres) get the residual weight of a point at this depth.
_WEIGHT_NEAR = 0.3


def depth_weights(cfg: TrackConfig, cloud: PointCloud) -> Float[Array, " m"]:
    """Residual weight of each point, ``(z / 1 m)^-p`` for its camera-frame depth ``z`` and
    ``p = cfg.depth_weight_power`` (0: all 1, the paper's unweighted cost).

    Depth noise of RGB-D sensors grows with depth (Kinect v1: its standard deviation grows as
    z^2), while the scale-normalised covariances of the paper give every point the same weight
    whatever its depth; ``1 / z`` gives near, precise points more say (see docs/method.md,
    "Departures from the paper").
    """
    return jnp.maximum(cloud.points[2], _WEIGHT_NEAR) ** (-cfg.depth_weight_power)


def cost(cfg: TrackConfig, geom: GeometrySet, cloud: PointCloud, T_wc: lie.SE3) -> Float[Array, ""]:
    """The GICP cost ``sum w e^T (C_b + R C_a R^T)^-1 e`` of ``cloud`` (camera frame) at ``T_wc``,
    ``w`` from :func:`depth_weights`.

    Correspondences are chosen at ``T_wc`` and held constant under differentiation.
    """
    R, t = lie.rotation_components(T_wc)
    q = lie.transform_points(R, t, cloud.points)
    cand = gather_candidates(geom, jax.lax.stop_gradient(q), cloud.valid)
    e, cov_b, found = match(cfg, cand, q)
    cost_b = depth_weights(cfg, cloud) * gicp.mahalanobis(e, gicp.information(R, cloud.covs, cov_b))
    return jnp.sum(jnp.where(found, cost_b, 0.0))


# Candidates looked up at pose T_ref serve while the pose stays within this many voxels of T_ref;
# on coarse levels, whose pose only seeds the next level, twice as long (fewer lookups, same
# accuracy; on the full cloud 0.5 let 7-Scenes drift more, see docs/method.md).
_FRESH, _FRESH_COARSE = 0.25, 0.5


def _moved(T: lie.SE3, T_ref: lie.SE3, reach: Float[Array, ""]) -> Float[Array, ""]:
    """Largest displacement of a point within ``reach`` metres of the camera between two poses."""
    d = (T_ref.inverse() @ T).log()
    return jnp.linalg.norm(d[:3]) + reach * jnp.linalg.norm(d[3:])


def _stretch(cfg: TrackConfig, xi: Float[Array, "6"], xi_prev: Float[Array, "6"]) -> Float[Array, ""]:
    """How far to take the Gauss-Newton update ``xi``, as a multiple of it (1 to ``cfg.extrapolation``).

    With correspondences picked again at every step, Gauss-Newton GICP converges only linearly:
    consecutive updates often point the same way and shrink by a steady ratio ``rho`` (0.4-0.75 in
    the TUM frames we looked at). The rest of such a path is ``xi (1 + rho + rho^2 + ...) =
    xi / (1 - rho)``, which this takes in one step (Aitken's extrapolation), with ``rho`` the
    projection of ``xi`` on the previous update (metres and radians alike), clipped to
    ``[0, 1 - 1 / cfg.extrapolation]``. Updates that turn or grow get ``rho = 0``: a plain step.
    The solver stops at an update below its tolerance and takes that one unstretched, so where it
    can stop is where plain Gauss-Newton stops.
    """
    rho = jnp.dot(xi, xi_prev) / jnp.maximum(jnp.dot(xi_prev, xi_prev), 1e-30)
    return 1.0 / (1.0 - jnp.clip(rho, 0.0, 1.0 - 1.0 / cfg.extrapolation))


def solve(cfg: TrackConfig, geom: GeometrySet, cloud: PointCloud, T0: lie.SE3) -> tuple[lie.SE3, TrackInfo]:
    """Gauss-Newton GICP from ``T0`` (not differentiable: use :func:`track` for gradients).

    Coarse to fine: for each ``c`` in ``cfg.coarse`` the solver first converges on every ``c``-th
    point of the cloud, from the previous level's pose; the last level is the whole cloud, so the
    result is a converged pose of the full cost whatever the levels. ``info.iterations`` counts the
    steps of all levels.
    """
    steps = 0
    for c in (*cfg.coarse, 1):
        level = cloud if c == 1 else jax.tree.map(lambda a, c=c: a[..., ::c], cloud)
        T0, info = _gauss_newton(cfg, geom, level, T0, _FRESH if c == 1 else _FRESH_COARSE)
        steps = steps + info.iterations
    return T0, dataclasses.replace(info, iterations=steps)


def _gauss_newton(cfg: TrackConfig, geom: GeometrySet, cloud: PointCloud, T0: lie.SE3, fresh_voxels: float) -> tuple[lie.SE3, TrackInfo]:
    """Gauss-Newton GICP of one level, from ``T0``, until convergence or ``cfg.max_iterations``;
    candidates are looked up again whenever a point of ``cloud`` has moved ``fresh_voxels`` voxels."""
    # How far a rotation can move a point: the farthest point of this cloud from the camera, a
    # tighter bound than an assumed constant, so candidates are looked up no more often than needed.
    reach = jnp.max(jnp.where(cloud.valid, jnp.sqrt(jnp.sum(cloud.points * cloud.points, axis=0)), 0.0))
    weight = depth_weights(cfg, cloud)

    def step(cand, T, xi_prev):
        R, t = lie.rotation_components(T)
        q = lie.transform_points(R, t, cloud.points)
        e, cov_b, found = match(cfg, cand, q)
        M = gicp.information(R, cloud.covs, cov_b)
        H_raw, g, c = gicp.linearise(q, e, M, found.astype(jnp.float32) * weight)
        n_in = jnp.sum(found).astype(jnp.int32)
        enough = n_in >= MIN_POINTS
        H = H_raw + (1e-6 * jnp.trace(H_raw) / 6.0 + jnp.where(enough, 0.0, 1.0)) * jnp.eye(6)
        xi = jnp.where(enough, -jnp.linalg.solve(H, g), 0.0)
        done = jnp.all(jnp.abs(xi) < cfg.tolerance) | ~enough
        stretch = jnp.where(done, 1.0, _stretch(cfg, xi, xi_prev))
        return lie.retract_left(T, stretch * xi), done, c, n_in, xi, H_raw

    def outer(state):
        # Look the candidates up at the current pose, then iterate on them until convergence or
        # until the pose has moved fresh_voxels away from where they were looked up.
        T_ref = state[0]
        R, t = lie.rotation_components(T_ref)
        cand = gather_candidates(geom, lie.transform_points(R, t, cloud.points), cloud.valid)

        def inner(s):
            T, it, _, _, _, xi, _, k = s
            T, done, c, n_in, xi, H = step(cand, T, xi)
            return T, it + 1, done, c, n_in, xi, H, k + 1

        def near(T):
            return _moved(T, T_ref, reach) < fresh_voxels * geom.voxel_size

        def fresh(s):
            T, it, done, _, _, _, _, k = s
            return (k == 0) | ((it < cfg.max_iterations) & ~done & near(T))

        # One step always (so that a non-finite pose cannot stall the outer loop), then more while
        # the candidates are still fresh (a do-while, so that the step is traced once).
        # Convergence counts only if the pose ended close to where the candidates were looked up:
        # candidates from afar can miss the nearest Gaussians.
        T, it, done, c, n_in, xi, H, _ = jax.lax.while_loop(fresh, inner, (*state, jnp.zeros((), jnp.int32)))
        return T, it, done & near(T), c, n_in, xi, H

    def more(state):
        return (state[1] < cfg.max_iterations) & ~state[2]

    init = (T0, jnp.zeros((), jnp.int32), jnp.zeros((), bool), jnp.zeros(()), jnp.zeros((), jnp.int32), jnp.zeros(6), jnp.zeros((6, 6)))
    T, it, done, c, n_in, _, H = jax.lax.while_loop(more, outer, init)
    info = TrackInfo(
        iterations=it, converged=done, cost=c, inliers=n_in, points=jnp.sum(cloud.valid).astype(jnp.int32),
        conditioning=conditioning(H), failure=jnp.zeros((), jnp.int32), recovered=jnp.zeros((), bool), jump=jnp.zeros(2), inlier_floor=jnp.zeros(()),
    )
    return T, info


def conditioning(H: Float[Array, "6 6"]) -> Float[Array, ""]:
    """Smallest over largest eigenvalue of a Gauss-Newton Hessian (0 when it is zero or not finite):
    near 0, some direction of motion is not constrained by the matches (a corridor, a single plane)."""
    ok = jnp.all(jnp.isfinite(H))
    lam = jnp.linalg.eigvalsh(jnp.where(ok, H, 0.0))
    return jnp.where(ok & (lam[-1] > 0), jnp.maximum(lam[0], 0.0) / jnp.where(lam[-1] > 0, lam[-1], 1.0), 0.0)


def track(cfg: TrackConfig, geom: GeometrySet, cloud: PointCloud, T_guess: lie.SE3) -> tuple[lie.SE3, TrackInfo]:
    """Estimate the camera-to-world pose of ``cloud`` (camera-frame geometry Gaussians) against T.

    Gauss-Newton on SE(3) from ``T_guess`` until every component of the update falls below
    ``cfg.tolerance`` or ``cfg.max_iterations`` is reached. Differentiable through
    ``jax.lax.custom_root``: the returned pose ``exp(xi*) T_guess`` solves ``d cost / d xi = 0``.

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

    # The solver runs outside custom_root (whose has_aux path rejects integer diagnostics); the root
    # it found is handed to custom_root, which supplies the implicit derivatives.
    T_sol, info = solve(cfg, geom, cloud, T_guess)
    xi_sol = jax.lax.stop_gradient(lie.log(T_sol @ T_guess.inverse()))

    def tangent_solve(g, y):
        return jnp.linalg.solve(jax.jacfwd(g)(y), y)

    xi = jax.lax.custom_root(grad_at, jnp.zeros(6), lambda f, x0: xi_sol, tangent_solve)
    return lie.exp(xi) @ T_guess, info


def relocalise(cfg: TrackConfig, geom: GeometrySet, cloud: PointCloud, T0: lie.SE3, *, key: jax.Array) -> lie.SE3:
    """A wide-basin pose estimate from ``T0`` for a frame that GICP could not track.

    GICP's candidates are the 2x2x2 voxels around each point, so it cannot pull in an error of
    more than a voxel or two. Here ``cfg.relocalise_points`` of the frame's points are matched by
    brute force to their nearest among ``cfg.relocalise_map_points`` points of T drawn at random in
    front of the guessed camera, and the pose follows from point-to-plane ICP (plus
    ``cfg.nn_weight`` times point-to-point, for the directions a plane leaves free) with a
    correspondence gate that shrinks geometrically from ``relocalise_gate[0]`` to ``[1]``.
    Not differentiable; the result seeds a normal :func:`solve`.
    """
    k_frame, k_map = jax.random.split(key)
    m, n = cloud.points.shape[-1], geom.capacity
    p_frame, p_map = min(cfg.relocalise_points, m), min(cfg.relocalise_map_points, n)
    # Valid points first, in random order (top_k of a score where validity outweighs the noise).
    _, ia = jax.lax.top_k(jax.random.uniform(k_frame, (m,)) + cloud.valid, p_frame)
    a, a_ok = cloud.points[:, ia], cloud.valid[ia]
    reach = jnp.max(jnp.where(a_ok, jnp.sqrt(jnp.sum(a * a, axis=0)), 0.0))
    # Points of T within a wide cone in front of the guessed camera (60 degrees off axis, up to the
    # frame's reach plus the largest move allowed), then the rest of T.
    Rc, tc = lie.rotation_components(T0.inverse())
    p_c = lie.transform_points(Rc, tc, geom.points)
    dist = jnp.sqrt(jnp.sum(p_c * p_c, axis=0))
    ahead = (p_c[2] > 0.5 * dist) & (dist < reach + cfg.relocalise_max_move[0])
    score = jax.random.uniform(k_map, (n,)) + ahead + jnp.where(geom.active, 0.0, -4.0)
    _, ib = jax.lax.top_k(score, p_map)
    b, nb, b_ok = geom.points[:, ib], geom.normals[:, ib], geom.active[ib]
    b2 = jnp.where(b_ok, jnp.sum(b * b, axis=0), jnp.inf)
    w = cfg.nn_weight
    # Information of (n . e)^2 + w |e|^2 for each map point: n n^T + w I, as six entries.
    M_b = jnp.stack([nb[0] * nb[0] + w, nb[1] * nb[1] + w, nb[2] * nb[2] + w, nb[0] * nb[1], nb[0] * nb[2], nb[1] * nb[2]])
    g0, g1 = cfg.relocalise_gate
    steps = cfg.relocalise_iterations

    def step(i, T):
        gate = g0 * (g1 / g0) ** (i / max(steps - 1, 1))
        R, t = lie.rotation_components(T)
        q = lie.transform_points(R, t, a)
        d2 = jnp.sum(q * q, axis=0)[:, None] + b2[None, :] - 2.0 * jnp.matmul(q.T, b, precision=jax.lax.Precision.HIGHEST)
        j = jnp.argmin(d2, axis=1)
        ok = a_ok & (jnp.min(d2, axis=1) < gate * gate)
        e = jnp.where(ok, q - b[:, j], 0.0)
        H, g, _ = gicp.linearise(q, e, M_b[:, j], ok.astype(jnp.float32))
        enough = jnp.sum(ok) >= MIN_POINTS
        H = H + (1e-6 * jnp.trace(H) / 6.0 + jnp.where(enough, 0.0, 1.0)) * jnp.eye(6)
        xi = jnp.where(enough, -jnp.linalg.solve(H, g), 0.0)
        return lie.retract_left(T, jnp.where(jnp.all(jnp.isfinite(xi)), xi, 0.0))

    return jax.lax.fori_loop(0, steps, step, T0)
