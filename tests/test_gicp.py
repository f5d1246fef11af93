"""GICP building blocks against independent oracles: numpy eigh / inv, brute-force kNN, autodiff,
finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sgad_jax import gicp, lie
from sgad_jax.config import TrackConfig
from sgad_jax.types import make_intrinsics


def _spd(seed):
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    lam = np.sort(rng.uniform(0.01, 2.0, 3))[::-1] * np.array([1.0, 1.0, rng.choice([1.0, 1e-2, 1e-4])])
    return (Q * lam) @ Q.T


@pytest.mark.slow
@settings(deadline=None, max_examples=40)
@given(st.integers(0, 10_000))
def test_normalise_covariance_matches_eigh(seed):
    C = _spd(seed)
    eps = 1e-3
    out, n, ok = gicp.normalise_covariance(gicp.mat_to_sym(jnp.asarray(C, jnp.float32)[None]), eps)
    lam, V = np.linalg.eigh(C)  # ascending
    l3, l2, l1 = lam
    assert bool(ok[0])
    want = V @ np.diag([max(l3 / l2, eps), 1.0, l1 / l2]) @ V.T
    np.testing.assert_allclose(np.asarray(gicp.sym_to_mat(out))[0], want, rtol=2e-3, atol=2e-3 * l1 / l2)
    # The normal is the eigenvector of the smallest eigenvalue (up to sign), when it is distinct.
    if l3 < 0.5 * l2:
        assert abs(abs(float(np.dot(np.asarray(n)[:, 0], V[:, 0]))) - 1.0) < 1e-3


def test_arccos_polynomial_against_float64():
    """The polynomial ``arccos`` of the closed-form eigenvalues against numpy's in float64, over
    [-1, 1] with both ends and both sides of 0: within float32 rounding of the angle (the
    polynomial's own error is 2e-8)."""
    x = np.concatenate([np.linspace(-1.0, 1.0, 20001), [-1.0, -0.0, 0.0, 1.0, np.nextafter(np.float32(1), np.float32(0))]]).astype(np.float32)
    got = np.asarray(gicp._arccos(jnp.asarray(x)), np.float64)
    np.testing.assert_allclose(got, np.arccos(x.astype(np.float64)), atol=5e-7, rtol=0)


@pytest.mark.parametrize("scale", [1e-6, 1e-4, 1.0, 4.0])
def test_normalise_covariance_of_a_ball(scale):
    """An exactly isotropic covariance is a valid shape (no normal direction): the identity after
    normalisation, finite, kept; the eigenvalues are all ``scale``."""
    cov = jnp.asarray([[scale], [scale], [scale], [0.0], [0.0], [0.0]], jnp.float32)
    np.testing.assert_allclose(np.stack(gicp._sym_eigenvalues(*cov))[:, 0], [scale] * 3, rtol=1e-6)
    out, n, ok = gicp.normalise_covariance(cov, 1e-3)
    assert bool(ok[0]) and np.isfinite(np.asarray(n)).all()
    np.testing.assert_allclose(np.asarray(out)[:, 0], [1, 1, 1, 0, 0, 0], atol=1e-6)


def test_sym_helpers_match_numpy():
    rng = np.random.default_rng(1)
    C = np.stack([_spd(s) for s in range(10)])
    with jax.enable_x64(True):
        c6 = gicp.mat_to_sym(jnp.asarray(C))
        np.testing.assert_allclose(np.asarray(gicp.sym_to_mat(gicp.sym_inverse(c6))), np.linalg.inv(C), rtol=1e-8)
        R = np.asarray(lie.to_matrix(lie.exp(jnp.asarray(rng.normal(size=6)))))[:3, :3]
        np.testing.assert_allclose(np.asarray(gicp.sym_to_mat(gicp.rotate_sym(jnp.asarray(R), c6))), R @ C @ R.T, atol=1e-12)
        e = rng.normal(size=(10, 3))
        np.testing.assert_allclose(gicp.mahalanobis(jnp.asarray(e.T), c6), np.einsum("ni,nij,nj->n", e, C, e), rtol=1e-10)


def _bumpy_depth(h=40, w=48):
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    depth = 1.5 + 0.2 * np.sin(u / 7.0) * np.cos(v / 5.0) + 0.002 * u
    depth[:, w // 2 :] += 0.6  # a depth jump: neighbours across it must be excluded
    depth[5:9, 5:9] = 0.0  # missing depth
    return depth


@pytest.mark.parametrize("k", [1, 3, 4, 5, 10, 20, 21, 23, 24, 25, 30])
def test_nearest_matches_a_stable_sort(k):
    """k smallest of each column by a stable argsort (ties: lower index first), infinities never;
    values from a small set, so that ties are everywhere. k = 1-4 and 21-24 take the sorted-list
    path, 5-20 the rank counts."""
    rng = np.random.default_rng(k)
    D = rng.choice(np.array([0.0, 0.5, 0.5, 1.0, 2.0, np.inf], np.float32), size=(25, 40, 3))
    want = np.zeros(D.shape, bool)
    order = np.argsort(D, axis=0, kind="stable")[:k]
    np.put_along_axis(want, order, True, axis=0)
    want &= np.isfinite(D)
    np.testing.assert_array_equal(np.asarray(jax.jit(gicp._nearest, static_argnums=1)(jnp.asarray(D), k)), want)


def _points(d, off, s):
    vv, uu = np.mgrid[off : off + s * d.shape[0] : s, off : off + s * d.shape[1] : s]
    return np.stack([(uu - 23.5) / 60.0 * d, (vv - 19.5) / 60.0 * d, d], -1)


def _knn(cfg, P, d_pick, i, j):
    """Grid indices of point (i, j)'s k nearest window neighbours (itself included): 3-D distance
    among the points ``P`` of the strided grid, stable sort, depth-jump gate on ``d_pick``."""
    r, (hs, ws) = cfg.window // 2, d_pick.shape
    cands = [
        (a, b)
        for di in range(-r, r + 1)
        for dj in range(-r, r + 1)
        for a, b in [(i + di, j + dj)]
        if 0 <= a < hs and 0 <= b < ws and d_pick[a, b] > cfg.min_depth and abs(d_pick[a, b] - d_pick[i, j]) <= cfg.depth_gate * d_pick[i, j]
    ]
    dist = np.array([np.sum((P[a, b] - P[i, j]) ** 2) for a, b in cands])
    return [cands[n] for n in np.argsort(dist, kind="stable")[: cfg.k]]


def _check_knn_covariances(cfg, cloud, d_pick, d_cov):
    """Each point's covariance against numpy: its k nearest window neighbours picked on the depths
    ``d_pick`` (3-D distance, stable sort, depth-jump gate), the covariance of those neighbours'
    points at the depths ``d_cov``; points at ``d_cov``."""
    off, s = cfg.stride // 2, cfg.stride
    P, Q = _points(d_pick, off, s), _points(d_cov, off, s)
    hs, ws = d_pick.shape
    checked = 0
    for i in range(hs):
        for j in range(ws):
            if d_pick[i, j] <= cfg.min_depth:
                assert not bool(cloud.valid[i * ws + j])
                continue
            nb = np.array([Q[a, b] for a, b in _knn(cfg, P, d_pick, i, j)])
            lam, V = np.linalg.eigh(np.cov(nb.T, bias=True))
            if not bool(cloud.valid[i * ws + j]) or lam[1] < 1e-2 * lam[2]:
                continue
            want = V @ np.diag([max(lam[0] / lam[1], cfg.eps), 1.0, lam[2] / lam[1]]) @ V.T
            got = np.asarray(gicp.sym_to_mat(cloud.covs[:, i * ws + j]))
            np.testing.assert_allclose(got, want, rtol=5e-3, atol=5e-3 * lam[2] / lam[1])
            np.testing.assert_allclose(np.asarray(cloud.points[:, i * ws + j]), Q[i, j], rtol=1e-6)
            checked += 1
    assert checked > 0.8 * hs * ws - 20


@pytest.mark.parametrize("k,window", [(10, 5), (23, 5), (6, 3), (30, 7), (4, 5)])
def test_frame_points_match_brute_force_knn(k, window):
    """Covariance of each point from its k nearest (3-D) among the window, recomputed in numpy."""
    # The outlier gate is off: this checks the neighbour search alone (the gate has its own tests).
    cfg = TrackConfig(stride=2, k=k, window=window, depth_gate=0.1, eps=1e-3, median_gate=0.0)
    intr = make_intrinsics(60.0, 60.0, 23.5, 19.5, 48, 40)
    depth = _bumpy_depth()
    _check_knn_covariances(cfg, gicp.frame_points(cfg, jnp.asarray(depth), intr), depth[1::2, 1::2], depth[1::2, 1::2])


@pytest.mark.parametrize("k,window", [(15, 5), (23, 5)])
def test_frame_clouds_at_median_and_measured_depths(k, window):
    """With ``median_depth`` the tracked cloud sits at each pixel's 3x3 median depth, with its
    nearest neighbours' covariances there; T's cloud is the same Gaussians at the measured depths:
    both against numpy."""
    cfg = TrackConfig(stride=2, k=k, window=window, depth_gate=0.1, eps=1e-3, median_gate=0.01, median_depth=True)
    intr = make_intrinsics(60.0, 60.0, 23.5, 19.5, 48, 40)
    depth = _bumpy_depth()
    depth = np.where(depth > 0, depth + np.random.default_rng(0).normal(0.0, 1e-3, depth.shape), 0.0).astype(np.float32)
    tracked, to_t = gicp.frame_clouds(cfg, jnp.asarray(depth), intr)
    h, w = depth.shape
    med = np.zeros((h // 2, w // 2), np.float32)
    for i, y in enumerate(range(1, h, 2)):
        for j, x in enumerate(range(1, w, 2)):
            vals = depth[max(y - 1, 0) : y + 2, max(x - 1, 0) : x + 2]
            med[i, j] = np.median(vals[vals > 0]) if depth[y, x] > 0 else 0.0
    # The 1 mm noise passes the 1% gate but for the edges of the depth jump and the hole: drop those.
    measured = depth[1::2, 1::2]
    kept = np.abs(measured - med) <= 0.01 * measured
    med, measured = np.where(kept, med, 0.0), np.where(kept, measured, 0.0)
    _check_knn_covariances(cfg, tracked, med, med)
    for field in ("covs", "normals", "valid"):
        np.testing.assert_array_equal(np.asarray(getattr(to_t, field)), np.asarray(getattr(tracked, field)))
    ok = np.asarray(to_t.valid)
    assert ok.sum() > 0.8 * ok.size - 20
    want = _points(measured, 1, 2).reshape(-1, 3)[ok]
    np.testing.assert_allclose(np.asarray(to_t.points).T[ok], want, rtol=1e-6)
    assert np.abs(want[:, 2] - med.reshape(-1)[ok]).max() > 5e-4  # the two clouds' depths differ


def test_plane_points_on_their_window_plane():
    """With ``plane_points`` each point is its own moved along its normal onto the plane through
    the mean of its K_c window neighbours (numpy), covariances and normals unchanged; T's cloud
    keeps the measured points (they key the voxels)."""
    base = TrackConfig(stride=2, k=15, window=5, median_gate=0.0)
    cfg = TrackConfig(stride=2, k=15, window=5, median_gate=0.0, plane_points=True)
    intr = make_intrinsics(60.0, 60.0, 23.5, 19.5, 48, 40)
    depth = _bumpy_depth()
    depth = np.where(depth > 0, depth + np.random.default_rng(1).normal(0.0, 3e-3, depth.shape), 0.0).astype(np.float32)
    plain = gicp.frame_points(base, jnp.asarray(depth), intr)
    tracked, to_t = gicp.frame_clouds(cfg, jnp.asarray(depth), intr)
    for field in ("covs", "normals", "valid"):
        np.testing.assert_array_equal(np.asarray(getattr(tracked, field)), np.asarray(getattr(plain, field)))
        np.testing.assert_array_equal(np.asarray(getattr(to_t, field)), np.asarray(getattr(plain, field)))
    np.testing.assert_array_equal(np.asarray(to_t.points), np.asarray(plain.points))
    d = depth[1::2, 1::2]
    P = _points(d, 1, 2)
    ok, n = np.asarray(plain.valid), np.asarray(plain.normals)
    moved = 0.0
    for i in range(d.shape[0]):
        for j in range(d.shape[1]):
            m = i * d.shape[1] + j
            if not ok[m]:
                continue
            mean = np.mean([P[a, b] for a, b in _knn(cfg, P, d, i, j)], axis=0)
            want = P[i, j] - n[:, m] * (n[:, m] @ (P[i, j] - mean))
            np.testing.assert_allclose(np.asarray(tracked.points[:, m]), want, atol=2e-5)
            moved = max(moved, float(np.linalg.norm(want - P[i, j])))
    assert ok.sum() > 300 and moved > 3e-3  # the noise moved points by millimetres


def test_plane_points_take_the_noise_out_of_a_plane():
    """A tilted plane with N(0, 3 mm) on every depth pixel: the points on their window planes lie
    several times closer to the true plane than the measured points T receives by default."""
    h, w, f = 240, 320, 300.0
    intr = make_intrinsics(f, f, (w - 1) / 2, (h - 1) / 2, w, h)
    n = np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0])  # plane through (0, 0, 1)
    v, u = np.mgrid[0:h, 0:w]
    rays = np.stack([(u - (w - 1) / 2) / f, (v - (h - 1) / 2) / f, np.ones((h, w))])
    depth = n[2] / np.tensordot(n, rays, 1) + np.random.default_rng(0).normal(0.0, 3e-3, (h, w))
    rms = {}
    for on in (False, True):
        tracked, to_t = gicp.frame_clouds(TrackConfig(plane_points=on), jnp.asarray(depth, jnp.float32), intr)
        ok = np.asarray(to_t.valid)
        rms[on] = np.sqrt(np.mean((n @ np.asarray((tracked if on else to_t).points)[:, ok] - n[2]) ** 2))
    assert rms[False] > 2e-3 and rms[True] < 0.3 * rms[False], rms


@pytest.mark.slow
def test_frame_points_plane_normals():
    """On a tilted plane every normal is the plane's and the covariance is flat (eps floor)."""
    cfg = TrackConfig(stride=4, k=10)
    intr = make_intrinsics(100.0, 100.0, 31.5, 23.5, 64, 48)
    n = np.array([0.2, -0.3, 1.0]) / np.linalg.norm([0.2, -0.3, 1.0])
    v, u = np.mgrid[0:48, 0:64].astype(np.float64)
    ray = np.stack([(u - 31.5) / 100.0, (v - 23.5) / 100.0, np.ones_like(u)], -1)
    depth = (2.0 / (ray @ n)).astype(np.float32)  # plane n . p = 2
    cloud = gicp.frame_points(cfg, jnp.asarray(depth), intr)
    normals = np.asarray(cloud.normals)[:, np.asarray(cloud.valid)]
    assert normals.shape[1] > 100
    np.testing.assert_allclose(np.abs(n @ normals), 1.0, atol=1e-3)
    C = np.asarray(gicp.sym_to_mat(cloud.covs[:, np.asarray(cloud.valid)]))
    assert np.allclose(np.einsum("i,nij,j->n", n, C, n), 1e-3, rtol=0.05)


def test_materialise_is_the_identity_under_jit_vmap_and_grad():
    """The fusion stop returns its input, batches, and passes gradients (here of sum x^2 sin y)."""
    rng = np.random.default_rng(3)
    x, y = jnp.asarray(rng.normal(size=(4, 7)), jnp.float32), jnp.asarray(rng.normal(size=(4, 7)), jnp.float32)
    flag = x > 0
    out = jax.jit(gicp._materialise)((x, (y, flag)))
    np.testing.assert_array_equal(out[0], x)
    np.testing.assert_array_equal(out[1][0], y)
    np.testing.assert_array_equal(out[1][1], flag)
    np.testing.assert_array_equal(jax.vmap(gicp._materialise)(x), x)
    f = lambda a, b: jnp.sum(gicp._materialise((a * a, jnp.sin(b)))[0] * jnp.sin(b))  # noqa: E731
    ga, gb = jax.jit(jax.grad(f, argnums=(0, 1)))(x, y)
    np.testing.assert_allclose(ga, 2 * x * np.sin(y), rtol=1e-6)
    np.testing.assert_allclose(gb, x * x * np.cos(y), rtol=1e-5, atol=1e-7)


def _pairs(seed, m):
    """Random point pairs ``a, b`` (3, m), SPD matrices ``Ca, Cb`` (6, m), weights and a pose (float64)."""
    rng = np.random.default_rng(seed)
    sym = lambda offset: gicp.mat_to_sym(jnp.asarray(np.stack([_spd(s + offset) for s in range(m)])))  # noqa: E731
    return (
        jnp.asarray(rng.normal(size=(3, m))), jnp.asarray(rng.normal(size=(3, m))), sym(0), sym(100),
        jnp.asarray(rng.uniform(0.1, 1, m)), lie.exp(jnp.asarray(rng.normal(size=6) * 0.3)),
    )


@pytest.mark.slow
def test_linearise_matches_autodiff():
    """H = J^T M J and g = J^T M e with J = d e / d xi (left perturbation), from jax.jacfwd."""
    with jax.enable_x64(True):
        m = 7
        a, b, M, _, w, T = _pairs(2, m)

        def residual(xi):
            R, t = lie.rotation_components(lie.exp(xi) @ T)
            return lie.transform_points(R, t, a) - b

        J = jax.jacfwd(residual)(jnp.zeros(6))  # (3, m, 6)
        e = residual(jnp.zeros(6))
        Mm = np.asarray(gicp.sym_to_mat(M))
        H_want = sum(w[k] * J[:, k, :].T @ Mm[k] @ J[:, k, :] for k in range(m))
        g_want = sum(w[k] * J[:, k, :].T @ Mm[k] @ e[:, k] for k in range(m))
        R, t = lie.rotation_components(T)
        H, g, c = gicp.linearise(lie.transform_points(R, t, a), e, M, w)
        np.testing.assert_allclose(H, H_want, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(g, g_want, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(c, sum(w[k] * e[:, k] @ Mm[k] @ e[:, k] for k in range(m)), rtol=1e-10)


@pytest.mark.slow
def test_gicp_cost_gradient_matches_finite_differences():
    """Gradient of the GICP cost (M depends on R too) with respect to the pose, in float64."""
    with jax.enable_x64(True):
        a, b, Ca, Cb, w, T = _pairs(3, 20)

        def f(xi):
            R, t = lie.rotation_components(lie.exp(xi) @ T)
            return gicp.gicp_cost(R, t, a, Ca, b, Cb, w)

        grad = jax.jit(jax.grad(f))(jnp.zeros(6))
        f = jax.jit(f)
        h = 1e-6
        fd = np.array([(f(h * e) - f(-h * e)) / (2 * h) for e in np.eye(6)])
        np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-8)
