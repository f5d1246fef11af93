"""SE(3) and camera maths: round trips and Jacobians against finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sgad_jax import camera, lie
from sgad_jax.types import make_intrinsics

vec = st.lists(st.floats(-1.0, 1.0), min_size=6, max_size=6).map(np.array)


@settings(deadline=None, max_examples=30)
@given(vec)
def test_exp_log_round_trip(xi):
    T = lie.exp(jnp.asarray(xi, jnp.float32))
    np.testing.assert_allclose(lie.log(T), xi, atol=2e-5)
    M = np.asarray(lie.to_matrix(T))
    np.testing.assert_allclose(M[:3, :3] @ M[:3, :3].T, np.eye(3), atol=1e-5)
    np.testing.assert_allclose(np.asarray(lie.to_matrix(lie.from_matrix(M))), M, atol=1e-5)


@pytest.mark.parametrize("angle", [0.0, 1e-4, 2e-3, 0.05, 0.0999, 0.1001, 0.7, 3.0])
def test_exp_matches_the_matrix_exponential(angle):
    """Against ``expm`` of the 4x4 twist matrix in float64, across the series / closed-form switch
    and at the small angles where jaxlie 1.5's ``SE3.exp`` is off by ``[omega]_x rho / 2``."""
    axis = np.array([0.3, -0.5, 0.81]) / np.linalg.norm([0.3, -0.5, 0.81])
    xi = np.concatenate([[0.9, -0.4, 1.3], angle * axis])
    hat = np.zeros((4, 4))
    hat[:3, :3] = [[0, -xi[5], xi[4]], [xi[5], 0, -xi[3]], [-xi[4], xi[3], 0]]
    hat[:3, 3] = xi[:3]
    with jax.enable_x64(True):
        want = np.asarray(jax.scipy.linalg.expm(jnp.asarray(hat)))
    got = np.asarray(lie.to_matrix(lie.exp(jnp.asarray(xi, jnp.float32))))
    np.testing.assert_allclose(got, want, atol=3e-6)
    np.testing.assert_allclose(np.asarray(lie.log(lie.exp(jnp.asarray(xi, jnp.float32)))), xi, atol=1e-5)


@settings(deadline=None, max_examples=20)
@given(vec, st.lists(st.floats(-3, 3), min_size=3, max_size=3).map(np.array))
def test_transform_points_matches_matrix(xi, p):
    T = lie.exp(jnp.asarray(xi, jnp.float32))
    R, t = lie.rotation_components(T)
    got = lie.transform_points(R, t, jnp.asarray(p, jnp.float32)[:, None])[:, 0]
    M = np.asarray(lie.to_matrix(T), np.float64)
    np.testing.assert_allclose(got, M[:3, :3] @ p + M[:3, 3], atol=1e-5)


def test_point_jacobian_matches_finite_differences():
    """d(exp(xi) T p)/d xi at 0 = [I | -[q]x] (jaxlie tangent order: translation, rotation)."""
    with jax.enable_x64(True):
        T = lie.exp(jnp.array([0.3, -0.2, 0.5, 0.1, 0.4, -0.3], jnp.float64))
        p = jnp.array([0.7, -1.2, 2.5], jnp.float64)

        def f(xi):
            return (lie.exp(xi) @ T) @ p

        eps = 1e-6
        fd = np.stack([(f(eps * e) - f(-eps * e)) / (2 * eps) for e in np.eye(6)], axis=1)
        np.testing.assert_allclose(lie.point_jacobian(T @ p), fd, atol=1e-8)


def test_backproject_project_round_trip():
    intr = make_intrinsics(517.3, 516.5, 318.6, 255.3, 640, 480)
    rng = np.random.default_rng(0)
    u, v = rng.uniform(0, 640, 50), rng.uniform(0, 480, 50)
    z = rng.uniform(0.2, 6.0, 50)
    p = camera.backproject(jnp.asarray(u), jnp.asarray(v), jnp.asarray(z), intr)
    u2, v2, z2 = camera.project(p, intr)
    np.testing.assert_allclose(u2, u, rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(v2, v, rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(z2, z, rtol=1e-6)


def test_scaled_intrinsics_map_block_centres():
    """A pixel of the image downscaled by f (block [f j, f j + f)) sees the ray of the block's centre."""
    intr = make_intrinsics(500.0, 510.0, 320.5, 240.5, 640, 480)
    for f in (2, 3, 4):
        small = intr.scaled(f)
        assert (small.width, small.height) == (640 // f, 480 // f)
        j, i = 7, 11
        x_small = (j - float(small.cx)) / float(small.fx)
        x_full = (f * j + (f - 1) / 2 - float(intr.cx)) / float(intr.fx)
        y_small = (i - float(small.cy)) / float(small.fy)
        y_full = (f * i + (f - 1) / 2 - float(intr.cy)) / float(intr.fy)
        assert abs(x_small - x_full) < 1e-6 and abs(y_small - y_full) < 1e-6


def _hat(xi):
    v, w = xi[:3], xi[3:]
    m = np.zeros((4, 4))
    m[:3, :3] = [[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]
    m[:3, 3] = v
    return m


def test_interpolate_follows_a_constant_twist():
    """Poses sampled along T0 expm(t xi^) (scipy's matrix exponential as the oracle), one sample
    time repeated as when two colour frames share a depth image; queried between samples, before
    the first and after the last: the constant-twist motion is recovered."""
    from scipy.linalg import expm

    xi = np.array([0.3, -0.1, 0.2, 0.4, -0.2, 0.3])  # per second
    T0 = np.asarray(lie.to_matrix(lie.exp(jnp.array([0.5, 1.0, -0.3, 0.2, 0.1, -0.4]))), np.float64)
    at_time = lambda t: T0 @ expm(t * _hat(xi))  # noqa: E731
    times = np.array([0.0, 0.033, 0.033, 0.070, 0.101, 0.135])
    at = times + np.array([-0.015, 0.016, -0.016, 0.012, 0.015, 0.017])
    got = lie.interpolate(np.stack([at_time(t) for t in times]), times, at)
    np.testing.assert_allclose(got, np.stack([at_time(t) for t in at]), atol=2e-6)


def test_interpolate_keeps_poses_at_their_own_time():
    poses = np.stack([np.asarray(lie.to_matrix(lie.exp(jnp.full(6, 0.1 * k))), np.float64) for k in range(4)])
    times = np.array([0.0, 0.1, 0.2, 0.3])
    np.testing.assert_array_equal(lie.interpolate(poses, times, times), poses)
    at = times.copy()
    at[2] = 0.25  # only that frame moves, half way to the next pose
    got = lie.interpolate(poses, times, at)
    np.testing.assert_array_equal(np.delete(got, 2, 0), np.delete(poses, 2, 0))
    mid = np.asarray(lie.to_matrix(lie.exp(jnp.full(6, 0.25))), np.float64)  # exp(a) exp(b) = exp(a+b) for parallel twists
    np.testing.assert_allclose(got[2], mid, atol=2e-6)
    at[0], times[3] = np.nan, np.nan  # frames without a stamp keep their poses
    got = lie.interpolate(poses, times, at)
    np.testing.assert_array_equal(got[[0, 1, 3]], poses[[0, 1, 3]])
    np.testing.assert_allclose(got[2], mid, atol=2e-6)
