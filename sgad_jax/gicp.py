"""Generalized ICP on SE(3), written for XLA:CPU.

SGAD-SLAM's geometry branch (paper Sec. 3.3, after GS-ICP SLAM):

1. every R-th pixel of the depth image is back-projected;
2. each point's covariance comes from its K_c nearest neighbours, searched (exactly, by rank
   counting or a sorted list) among a window of the strided image grid, with neighbours across depth jumps excluded;
3. "ellipse scale" normalisation: the covariance keeps its shape but its eigenvalues are divided by
   the middle one (floored at ``eps``); the eigenvector of the smallest eigenvalue is the normal;
4. the GICP cost ``sum e^T (C_b + R C_a R^T)^-1 e``, ``e = T a - b`` (Segal et al. 2009, eq. 2),
   minimised by Gauss-Newton with left updates ``T <- exp(xi) T``.

Symmetric 3x3 matrices are stored as their six entries ``(xx, yy, zz, xy, xz, yz)`` along the
leading axis, vectors as ``(3, m)``. All per-point maths is component-wise on ``(m,)`` arrays: on XLA:CPU that is several times
faster than batched ``einsum`` / ``eigh`` on ``(m, 3, 3)``.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from sgad_jax import camera
from sgad_jax.lie import transform_points
from sgad_jax.config import TrackConfig
from sgad_jax.types import Intrinsics, PointCloud

# ----------------------------------------------------------------------------------------------
# Symmetric 3x3 helpers (component-wise)


def sym_to_mat(c: Float[Array, "6 *m"]) -> Float[Array, "*m 3 3"]:
    xx, yy, zz, xy, xz, yz = c
    return jnp.stack(
        [jnp.stack([xx, xy, xz], -1), jnp.stack([xy, yy, yz], -1), jnp.stack([xz, yz, zz], -1)], -2
    )


def mat_to_sym(m: Float[Array, "*m 3 3"]) -> Float[Array, "6 *m"]:
    return jnp.stack([m[..., 0, 0], m[..., 1, 1], m[..., 2, 2], m[..., 0, 1], m[..., 0, 2], m[..., 1, 2]])


_TINY = float(jnp.finfo(jnp.float32).tiny)

#: arccos(x) = sqrt(1 - x) * poly(x) on [0, 1], error under 2e-8 (Abramowitz and Stegun 4.4.46).
_ACOS = (1.5707963050, -0.2145988016, 0.0889789874, -0.0501743046, 0.0308918810, -0.0170881256, 0.0066700901, -0.0012624911)


def _arccos(x):
    """``arccos`` of ``x`` in [-1, 1] by a polynomial: XLA:CPU computes ``jnp.arccos`` through a
    scalar ``atan2``, one element at a time, 8-10% of the tracking step's time."""
    a = jnp.abs(x)
    poly = _ACOS[-1]
    for c in _ACOS[-2::-1]:
        poly = poly * a + c
    r = jnp.sqrt(1.0 - a) * poly
    return jnp.where(x < 0, math.pi - r, r)


def _sym_eigenvalues(xx, yy, zz, xy, xz, yz):
    """Eigenvalues (largest, middle, smallest) of a symmetric 3x3 matrix, closed form.

    Trigonometric method (O. K. Smith, "Eigenvalues of a symmetric 3x3 matrix", CACM 1961).
    """
    q = (xx + yy + zz) / 3.0
    p1 = xy * xy + xz * xz + yz * yz
    a, b, c = xx - q, yy - q, zz - q
    p2 = a * a + b * b + c * c + 2.0 * p1
    p = jnp.sqrt(jnp.maximum(p2, 1e-30) / 6.0)
    det = a * (b * c - yz * yz) - xy * (xy * c - yz * xz) + xz * (xy * yz - b * xz)
    # An exactly isotropic matrix has det = 0 and p^3 below float32's range: 0 / 0 without the floor.
    r = jnp.clip(det / jnp.maximum(2.0 * p * p * p, _TINY), -1.0, 1.0)
    phi = _arccos(r) / 3.0
    l1 = q + 2.0 * p * jnp.cos(phi)
    l3 = q + 2.0 * p * jnp.cos(phi + 2.0 * math.pi / 3.0)
    l2 = 3.0 * q - l1 - l3
    return l1, l2, l3


def _null_vector(xx, yy, zz, xy, xz, yz, lam):
    """Unit vector spanning the null space of ``A - lam I`` (eigenvector of ``lam``).

    The cross product of two rows of ``A - lam I`` is orthogonal to both; the pair with the largest
    cross product is the best conditioned.
    """
    r0 = (xx - lam, xy, xz)
    r1 = (xy, yy - lam, yz)
    r2 = (xz, yz, zz - lam)

    def cross(a, b):
        return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])

    cands = [cross(r0, r1), cross(r0, r2), cross(r1, r2)]
    norms = [c[0] ** 2 + c[1] ** 2 + c[2] ** 2 for c in cands]
    best = cands[0]
    best_n = norms[0]
    for c, n in zip(cands[1:], norms[1:]):
        take = n > best_n
        best = tuple(jnp.where(take, ci, bi) for ci, bi in zip(c, best))
        best_n = jnp.where(take, n, best_n)
    inv = jnp.where(best_n > 0, jax.lax.rsqrt(jnp.where(best_n > 0, best_n, 1.0)), 0.0)
    return tuple(ci * inv for ci in best)


@jax.custom_jvp
def _materialise(tree):
    """``tree`` unchanged, but computed once and stored, never recomputed by its readers.

    XLA:CPU fuses cheap element-wise producers into each of their consumers, so a value read by
    several output rows (the eigen-decomposition below feeds nine) is recomputed for each of them.
    A one-turn ``while_loop`` whose turn count XLA cannot see stops that: its result is a stored
    buffer. (An optimisation barrier does not: XLA:CPU drops it before fusion; a loop that passes
    its input through unchanged is folded away.)
    Differentiable: the tangent passes straight through.
    """
    first = jax.tree.leaves(tree)[0]
    zero = (first.ravel()[0].astype(jnp.float32) > jnp.inf).astype(jnp.int32)  # 0, unknown to XLA
    init = (zero, tree, jax.tree.map(jnp.zeros_like, tree))
    return jax.lax.while_loop(lambda c: c[0] < 1, lambda c: (c[0] + 1, c[1], c[1]), init)[2]


@_materialise.defjvp
def _materialise_jvp(primals, tangents):
    return _materialise(primals[0]), tangents[0]


def normalise_covariance(cov: Float[Array, "6 *m"], eps: float) -> tuple[Float[Array, "6 *m"], Float[Array, "3 *m"], Bool[Array, "*m"]]:
    """Ellipse-scale normalisation (SGAD-SLAM Sec. 3.3) and normals.

    Returns the covariance with eigenvalues ``(l1/l2, 1, max(l3/l2, eps))``, the unit eigenvector of
    the smallest eigenvalue (the surface normal, sign arbitrary) and a flag that is False where the
    shape is degenerate (``l2 < eps l1``: points on a line, or a single point).
    """
    xx, yy, zz, xy, xz, yz = cov
    l1, l2, l3 = _sym_eigenvalues(xx, yy, zz, xy, xz, yz)
    n = _null_vector(xx, yy, zz, xy, xz, yz, l3)
    ok = (l2 > eps * l1) & (l1 > 0)
    l2s = jnp.where(ok, l2, 1.0)
    # Raise the smallest eigenvalue to eps * l2 along n, then divide by l2.
    bump = jnp.maximum(eps * l2s - l3, 0.0)
    n, l2s, bump, ok = _materialise((n, l2s, bump, ok))
    nn = (n[0] * n[0], n[1] * n[1], n[2] * n[2], n[0] * n[1], n[0] * n[2], n[1] * n[2])
    out = jnp.stack([(c + bump * d) / l2s for c, d in zip((xx, yy, zz, xy, xz, yz), nn)])
    return out, jnp.stack(n), ok


# ----------------------------------------------------------------------------------------------
# Frame preprocessing

#: Up to this many entries (min(k, n - k) of n), :func:`_nearest` keeps a sorted list instead of
#: counting ranks: the list costs about 2t compare-and-selects per offset against the ranks' fixed
#: n, so it wins for short lists (TUM drops the 2 farthest of 25) and loses beyond about t = 6.
_LIST_MAX = 4


def _nearest(D: Float[Array, "n *m"], k: int) -> Bool[Array, "n *m"]:
    """Whether each of the ``n`` candidate distances is among the ``k`` smallest (ties: the lower
    candidate index first) and finite, i.e. ``rank < k`` with ``rank_o = #{o' : D_o' < D_o, or
    D_o' = D_o and o' < o}``. No ``top_k`` or sort (slow on XLA:CPU).

    When ``k`` or ``n - k`` is small, one pass over the candidates keeps a sorted list of the k
    nearest (or the n - k farthest, those dropped) with their indices; a candidate comes after
    every listed one of equal distance, as its index is higher. Otherwise each rank is counted: a
    loop over ``o'`` (rolled but for 5 steps a turn, so that the program and its compile time stay
    small) with 8-bit counts, which keep the ``(n, *m)`` counts read and written each turn small.
    """
    n = D.shape[0]
    if k >= n:
        return jnp.isfinite(D)
    order = jnp.arange(n).reshape((n,) + (1,) * (D.ndim - 1))
    if min(k, n - k) <= _LIST_MAX:
        drop = n - k < k
        t = n - k if drop else k
        ahead = (lambda x, s: x >= s) if drop else (lambda x, s: x < s)  # noqa: E731

        def visit(o, lists):
            s, ix = lists
            go = [ahead(D[o], si) for si in s]  # the new candidate goes before entry i
            shift = lambda a, new: tuple(  # noqa: E731
                jnp.where(go[0], new, a[0]) if i == 0 else jnp.where(go[i - 1], a[i - 1], jnp.where(go[i], new, a[i]))
                for i in range(t)
            )
            return shift(s, D[o]), shift(ix, o)

        blank = jnp.full(D.shape[1:], -jnp.inf if drop else jnp.inf, D.dtype)
        init = ((blank,) * t, (jnp.full(D.shape[1:], -1, jnp.int32),) * t)
        ix = jax.lax.fori_loop(0, n, visit, init, unroll=5)[1]
        listed = functools.reduce(jnp.logical_or, [i == order for i in ix])
        return (~listed if drop else listed) & jnp.isfinite(D)
    counts = jnp.int8 if n <= 127 else jnp.int32

    def count(o2, rank):
        d2 = D[o2]
        return rank + ((d2 < D) | ((d2 == D) & (o2 < order))).astype(counts)

    rank = jax.lax.fori_loop(0, n, count, jnp.zeros(D.shape, counts), unroll=5)
    return (rank < k) & jnp.isfinite(D)  # ranks < n


def _median_consistent(
    depth: Float[Array, "h w"], d: Float[Array, "hs ws"], s: int, off: int, gate: float
) -> tuple[Bool[Array, "hs ws"], Float[Array, "hs ws"]]:
    """Whether each strided pixel's depth ``d`` lies within ``gate * d`` of the median of the
    measured depths of its full-resolution 3x3 neighbourhood (itself included), and that median.

    A depth pixel far from its neighbourhood's median is an outlier (a noise spike, a flying pixel
    at an edge): kept, it is a point off the surface in the frame and, once inserted, in the
    geometry set, and through the 5x5 window it tilts its neighbours' normals. The median of a
    plane's 3x3 depths is its centre value whatever the slope (the values pair up around it), so
    clean surfaces pass, and it ignores outliers while they are fewer than half the neighbourhood.
    """
    hs, ws = d.shape
    h, w = depth.shape
    # Pad by one pixel only if a 3x3 neighbourhood reaches past the image (a copy of the full image).
    inside = off >= 1 and off + s * (hs - 1) + 1 < h and off + s * (ws - 1) + 1 < w
    pad, off = (depth, off - 1) if inside else (jnp.pad(depth, 1), off)
    vals = []
    for di in (0, 1, 2):
        for dj in (0, 1, 2):
            q = jax.lax.slice(pad, (off + di, off + dj), (off + di + s * (hs - 1) + 1, off + dj + s * (ws - 1) + 1), (s, s))
            vals.append(jnp.where(jnp.isfinite(q) & (q > 0), q, jnp.inf))  # missing depth sorts last
    # Odd-even transposition sort of the nine values, element-wise (a sort along an axis is slow on XLA:CPU).
    for sweep in range(9):
        for a in range(sweep % 2, 8, 2):
            vals[a], vals[a + 1] = jnp.minimum(vals[a], vals[a + 1]), jnp.maximum(vals[a], vals[a + 1])
    n = sum((v < jnp.inf).astype(jnp.int32) for v in vals)
    lo, hi = (n - 1) // 2, n // 2  # the two middle measured values (one when n is odd)
    med = 0.5 * sum(jnp.where(lo == k, v, 0.0) + jnp.where(hi == k, v, 0.0) for k, v in enumerate(vals))
    return jnp.abs(d - med) <= gate * d, med


def frame_points(cfg: TrackConfig, depth: Float[Array, "h w"], intr: Intrinsics) -> PointCloud:
    """The points a depth frame is tracked with (the first of :func:`frame_clouds`)."""
    return frame_clouds(cfg, depth, intr)[0]


def frame_clouds(cfg: TrackConfig, depth: Float[Array, "h w"], intr: Intrinsics) -> tuple[PointCloud, PointCloud]:
    """Geometry Gaussians of one depth frame, in camera coordinates: the points it is tracked with
    and the points T receives (the same cloud unless ``cfg.median_depth`` moves the tracked ones).

    Takes every ``cfg.stride``-th pixel (offset ``stride // 2``), and for each point the ``cfg.k``
    nearest neighbours (itself included) in 3-D among the ``cfg.window`` x ``cfg.window`` patch of the
    strided grid around it, skipping neighbours with missing depth or a depth jump larger than
    ``cfg.depth_gate * depth``. The neighbours are exact (ties broken by window position,
    :func:`_nearest`): a k-nearest-neighbour search restricted to the patch. With
    ``cfg.median_gate > 0``, pixels far from their 3x3 median are missing depth from the start
    (:func:`_median_consistent`), and with ``cfg.median_depth`` the tracked points sit at that
    median while T receives them at their measured depths, with the tracked points' covariances
    and normals (tracked against T built from median depths, long noisy sequences drifted; one
    neighbour search for both, not one each: docs/method.md, "Depth outliers"). With
    ``cfg.plane_points`` the tracked points are moved onto their window's plane, and T's cloud keeps
    the measured points: T stores the tracked ones in the measured ones' voxels
    (:func:`sgad_jax.slam.track_step`).

    Args:
        cfg: tracking config (stride R, k K_c, window, depth_gate, eps, min/max depth).
        depth: (h, w) measured depth in metres, 0 where missing.
        intr: intrinsics of ``depth``.

    Returns:
        Two PointClouds with ``m = ceil((h - R//2) / R) * ceil((w - R//2) / R)`` points.
    """
    s = cfg.stride
    off = s // 2
    d = depth[off::s, off::s]
    u, v = camera.pixel_grid(depth.shape[0], depth.shape[1], stride=s, offset=off)
    valid = jnp.isfinite(d) & (d > cfg.min_depth)
    if cfg.max_depth > 0:
        valid = valid & (d < cfg.max_depth)
    tracked = d
    if cfg.median_gate > 0:
        ok, med = _median_consistent(depth, d, s, off, cfg.median_gate)
        valid = valid & ok
        if cfg.median_depth:  # nine measurements, not one: noise that passed the gate is mostly removed
            tracked = med
    cloud = _cloud(cfg, tracked, valid, u, v, intr)
    if tracked is d and not cfg.plane_points:
        return cloud, cloud
    measured = _back_project(jnp.where(cloud.valid.reshape(d.shape), d, 0.0), u, v, intr)
    return cloud, dataclasses.replace(cloud, points=jnp.stack(measured).reshape(3, -1))


def _back_project(d, u, v, intr: Intrinsics):
    """Camera-frame coordinates ``(x, y, z)`` of depths ``d`` at pixels ``(u, v)``, as separate
    arrays for the component-wise maths (:func:`sgad_jax.camera.backproject` stacks them last)."""
    return d * (u - intr.cx) / intr.fx, d * (v - intr.cy) / intr.fy, d


def _cloud(cfg: TrackConfig, d, valid, u, v, intr: Intrinsics) -> PointCloud:
    """Points of the strided depths ``d`` where ``valid``, with their window covariances."""
    d = jnp.where(valid, d, 0.0)
    p = _back_project(d, u, v, intr)

    r = cfg.window // 2
    hs, ws = d.shape
    pad = lambda a: jnp.pad(a, r)  # noqa: E731
    shifted = lambda a, di, dj: jax.lax.dynamic_slice(a, (r + di, r + dj), (hs, ws))  # noqa: E731
    pp, vp = [pad(c) for c in p], pad(valid)
    gate = cfg.depth_gate * d
    neigh, dist = [], []
    for di in range(-r, r + 1):
        for dj in range(-r, r + 1):
            q = [shifted(c, di, dj) for c in pp]
            ok = shifted(vp, di, dj) & (jnp.abs(q[2] - d) <= gate)
            d2 = (q[0] - p[0]) ** 2 + (q[1] - p[1]) ** 2 + (q[2] - p[2]) ** 2
            neigh.append(q)
            dist.append(jnp.where(ok, d2, jnp.inf))
    w = list(_nearest(jnp.stack(dist), cfg.k).astype(jnp.float32))
    cnt = sum(w)
    inv = 1.0 / jnp.maximum(cnt, 1.0)
    mean = [sum(wi * q[c] for wi, q in zip(w, neigh)) * inv for c in range(3)]
    cov = jnp.stack([
        sum(wi * (q[a] - mean[a]) * (q[b] - mean[b]) for wi, q in zip(w, neigh)) * inv
        for a, b in ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
    ])
    cov, cnt = _materialise((cov, cnt))
    cov_n, normal, ok = normalise_covariance(cov, cfg.eps)
    valid = valid & ok & (cnt >= min(cfg.k, 5))
    if cfg.plane_points:  # onto the window's plane: the noise across the surface averaged over K_c points
        off = sum(normal[c] * (p[c] - mean[c]) for c in range(3))
        p = [jnp.where(valid, p[c] - off * normal[c], p[c]) for c in range(3)]
    eye = jnp.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0])[:, None, None]
    return PointCloud(
        points=jnp.stack(p).reshape(3, -1),
        covs=jnp.where(valid, cov_n, eye).reshape(6, -1),
        normals=jnp.where(valid, normal, 0.0).reshape(3, -1),
        valid=valid.reshape(-1),
    )


# ----------------------------------------------------------------------------------------------
# The GICP cost and its Gauss-Newton linearisation


def rotate_sym(R: Float[Array, "3 3"], c: Float[Array, "6 *m"]) -> Float[Array, "6 *m"]:
    """``R C R^T`` for symmetric ``C`` in six-entry form, component-wise."""
    C = [[c[0], c[3], c[4]], [c[3], c[1], c[5]], [c[4], c[5], c[2]]]
    RC = [[R[i, 0] * C[0][j] + R[i, 1] * C[1][j] + R[i, 2] * C[2][j] for j in range(3)] for i in range(3)]
    out = lambda i, j: RC[i][0] * R[j, 0] + RC[i][1] * R[j, 1] + RC[i][2] * R[j, 2]  # noqa: E731
    return jnp.stack([out(0, 0), out(1, 1), out(2, 2), out(0, 1), out(0, 2), out(1, 2)])


def sym_inverse(c: Float[Array, "6 *m"]) -> Float[Array, "6 *m"]:
    """Inverse of a symmetric positive-definite 3x3 (adjugate / determinant), NaN-safe."""
    xx, yy, zz, xy, xz, yz = c
    a00 = yy * zz - yz * yz
    a11 = xx * zz - xz * xz
    a22 = xx * yy - xy * xy
    a01 = xz * yz - xy * zz
    a02 = xy * yz - xz * yy
    a12 = xy * xz - xx * yz
    det = xx * a00 + xy * a01 + xz * a02
    ok = det > 1e-20
    inv = jnp.where(ok, 1.0 / jnp.where(ok, det, 1.0), 0.0)
    return jnp.stack([a00, a11, a22, a01, a02, a12]) * inv


def information(R: Float[Array, "3 3"], cov_a: Float[Array, "6 *m"], cov_b: Float[Array, "6 *m"]) -> Float[Array, "6 *m"]:
    """The GICP information matrix ``(C_b + R C_a R^T)^-1`` of each correspondence."""
    return sym_inverse(cov_b + rotate_sym(R, cov_a))


def mahalanobis(e: Float[Array, "3 *m"], M: Float[Array, "6 *m"]) -> Float[Array, "*m"]:
    """``e^T M e`` for symmetric ``M`` in six-entry form."""
    x, y, z = e
    return M[0] * x * x + M[1] * y * y + M[2] * z * z + 2.0 * (M[3] * x * y + M[4] * x * z + M[5] * y * z)


def gicp_cost(
    R: Float[Array, "3 3"],
    t: Float[Array, "3"],
    src: Float[Array, "3 m"],
    src_cov: Float[Array, "6 m"],
    dst: Float[Array, "3 m"],
    dst_cov: Float[Array, "6 m"],
    weight: Float[Array, " m"],
) -> Float[Array, ""]:
    """``sum_i w_i e_i^T (C_b + R C_a R^T)^-1 e_i`` with ``e_i = R a_i + t - b_i`` (differentiable)."""
    e = transform_points(R, t, src) - dst
    return jnp.sum(jnp.where(weight > 0, weight * mahalanobis(e, information(R, src_cov, dst_cov)), 0.0))


def linearise(
    q: Float[Array, "3 m"], e: Float[Array, "3 m"], M: Float[Array, "6 m"], weight: Float[Array, " m"]
) -> tuple[Float[Array, "6 6"], Float[Array, "6"], Float[Array, ""]]:
    """Gauss-Newton normal equations ``H = sum J^T M J``, ``g = sum J^T M e`` for ``J = [I | -[q]_x]``.

    The information matrix ``M`` is held fixed during the step (the usual GICP approximation).
    """
    x, y, z = q
    Mxx, Myy, Mzz, Mxy, Mxz, Myz = (M[i] * weight for i in range(6))
    Mm = ((Mxx, Mxy, Mxz), (Mxy, Myy, Myz), (Mxz, Myz, Mzz))
    zero = None
    # Columns of J as 3-tuples (None = 0, 1.0 = constant one), for tangent (vx, vy, vz, wx, wy, wz).
    cols = [
        (1.0, zero, zero), (zero, 1.0, zero), (zero, zero, 1.0),
        (zero, -z, y), (z, zero, -x), (-y, x, zero),
    ]

    def mul_col(col):  # M @ col, component-wise
        out = []
        for i in range(3):
            acc = 0.0
            for k in range(3):
                if col[k] is None:
                    continue
                acc = acc + (Mm[i][k] if isinstance(col[k], float) else Mm[i][k] * col[k])
            out.append(acc)
        return out

    def dot(col, vec):
        acc = 0.0
        for k in range(3):
            if col[k] is None:
                continue
            acc = acc + (vec[k] if isinstance(col[k], float) else col[k] * vec[k])
        return acc

    Mcols = [mul_col(c) for c in cols]
    upper = {(a, b): jnp.sum(dot(cols[a], Mcols[b])) for a in range(6) for b in range(a, 6)}
    H = jnp.stack([jnp.stack([upper[min(a, b), max(a, b)] for b in range(6)]) for a in range(6)])
    Me = [Mm[i][0] * e[0] + Mm[i][1] * e[1] + Mm[i][2] * e[2] for i in range(3)]
    g = jnp.stack([jnp.sum(dot(c, Me)) for c in cols])
    cost = jnp.sum(e[0] * Me[0] + e[1] * Me[1] + e[2] * Me[2])
    return H, g, cost
