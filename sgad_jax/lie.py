"""SE(3) helpers on top of jaxlie.

Conventions used everywhere in sgad_jax:

* ``T_wc`` maps camera coordinates to world coordinates (camera-to-world), ``p_w = T_wc @ p_c``.
* Tangent vectors follow jaxlie: ``(v_x, v_y, v_z, w_x, w_y, w_z)``, translation then rotation.
* Updates are applied on the left, in the world frame: ``T <- exp(xi) @ T``. The derivative of
  ``exp(xi) @ T @ p`` at ``xi = 0`` is ``[I | -[q]_x]`` with ``q = T @ p`` (see :func:`point_jacobian`).
"""

from __future__ import annotations

import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, Float

SE3 = jaxlie.SE3
SO3 = jaxlie.SO3


def from_matrix(m: Float[Array, "*b 4 4"]) -> SE3:
    """SE(3) from a homogeneous matrix (rotation re-orthonormalised by jaxlie's quaternion path)."""
    return SE3.from_matrix(jnp.asarray(m, jnp.float32))


def to_matrix(T: SE3) -> Float[Array, "*b 4 4"]:
    return T.as_matrix()


def identity() -> SE3:
    return SE3.identity()


def exp(xi: Float[Array, "*b 6"]) -> SE3:
    """``exp`` of a twist ``(rho, omega)``: rotation ``exp(omega)``, translation ``V rho`` with the
    left Jacobian ``V = I + a [omega]_x + b [omega]_x^2``.

    Not ``jaxlie.SE3.exp``: jaxlie 1.5 takes ``V = R`` for ``|omega|^2`` below its epsilon (in
    float32, rotations under 3.2 mrad), which is off by ``[omega]_x rho / 2``, so that
    ``exp(log(T))`` missed ``T`` by up to 0.16% of its translation. Here ``a`` and ``b`` are series
    below 0.1 rad (error < 1e-10), closed forms above."""
    rho, omega = xi[..., :3], xi[..., 3:]
    th2 = jnp.sum(jnp.square(omega), axis=-1, keepdims=True)
    small = th2 < 1e-2
    th2s = jnp.where(small, 1.0, th2)  # no 0 / 0 in the unused branch (its gradient would be NaN)
    th = jnp.sqrt(th2s)
    a = jnp.where(small, 0.5 - th2 / 24.0 + th2 * th2 / 720.0, (1.0 - jnp.cos(th)) / th2s)
    b = jnp.where(small, 1.0 / 6.0 - th2 / 120.0 + th2 * th2 / 5040.0, (th - jnp.sin(th)) / (th2s * th))
    w_rho = jnp.cross(omega, rho)
    t = rho + a * w_rho + b * jnp.cross(omega, w_rho)
    return SE3.from_rotation_and_translation(SO3.exp(omega), t)


def log(T: SE3) -> Float[Array, "*b 6"]:
    return T.log()


def retract_left(T: SE3, xi: Float[Array, "6"]) -> SE3:
    """``exp(xi) @ T``: the update used by the Gauss-Newton solvers."""
    return exp(xi) @ T


def rotation_components(T: SE3) -> tuple[Float[Array, "3 3"], Float[Array, "3"]]:
    """(R, t) as arrays, for component-wise maths."""
    m = T.as_matrix()
    return m[..., :3, :3], m[..., :3, 3]


def transform_points(R: Float[Array, "3 3"], t: Float[Array, "3"], p: Float[Array, "3 *m"]) -> Float[Array, "3 *m"]:
    """``R p + t`` for component-major points, written component-wise (faster than a batched
    matmul on XLA:CPU)."""
    x, y, z = p
    return jnp.stack([R[i, 0] * x + R[i, 1] * y + R[i, 2] * z + t[i] for i in range(3)])


def interpolate(poses: np.ndarray, times: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Camera-to-world poses at times ``at`` from poses sampled at ``times`` (non-decreasing;
    repeated times keep their first pose): geodesic interpolation ``A exp(w log(A^-1 B))`` between
    the samples around each query, extrapolation from the nearest pair outside them. A query equal
    to its own sample's time (``at[i] == times[i]``), or where either is not finite, returns that
    pose unchanged.

    TUM's colour and depth images are not synchronised: tracking estimates each frame's pose at its
    depth image's stamp, and this moves it to the colour stamp that labels the frame.

    Args:
        poses: (n, 4, 4) poses at ``times``.
        times: (n,) sample times.
        at: (n,) query times, one per pose.

    Returns:
        (n, 4, 4) float64 poses.
    """
    poses, times, at = np.asarray(poses), np.asarray(times, np.float64), np.asarray(at, np.float64)
    out = np.array(poses, np.float64)
    finite = np.isfinite(times)
    t, first = np.unique(times[finite], return_index=True)
    first = np.flatnonzero(finite)[first]
    moved = (at != times) & finite & np.isfinite(at)
    if len(t) < 2 or not moved.any():
        return out
    k = np.clip(np.searchsorted(t, at[moved], side="right") - 1, 0, len(t) - 2)
    w = (at[moved] - t[k]) / (t[k + 1] - t[k])
    A, B = from_matrix(poses[first][k]), from_matrix(poses[first][k + 1])
    T = A @ exp(jnp.asarray(w, jnp.float32)[:, None] * (A.inverse() @ B).log())
    out[moved] = np.asarray(T.as_matrix(), np.float64)
    return out


def point_jacobian(q: Float[Array, "*m 3"]) -> Float[Array, "*m 3 6"]:
    """d(exp(xi) q)/d xi at xi = 0, i.e. ``[I | -[q]_x]`` (for tests and readability)."""
    x, y, z = q[..., 0], q[..., 1], q[..., 2]
    zero, one = jnp.zeros_like(x), jnp.ones_like(x)
    rows = [
        [one, zero, zero, zero, z, -y],
        [zero, one, zero, -z, zero, x],
        [zero, zero, one, y, -x, zero],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)

