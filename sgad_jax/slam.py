"""SGAD-SLAM steps composed from ``track`` (and, with the appearance branch, ``map_frame``).

Pure functions over :class:`SLAMState`; the host loop (file reading, progress, outputs) lives in
``sgad_jax.pipeline``.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from sgad_jax import geometry, gicp, lie
from sgad_jax.config import TrackConfig
from sgad_jax.track import solve, track, transform_cloud
from sgad_jax.types import GeometrySet, InsertInfo, Intrinsics, TrackInfo, empty_geometry


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SLAMState:
    """What tracking carries from frame to frame."""

    geom: GeometrySet
    T_prev: lie.SE3  # pose of the last tracked frame
    velocity: Float[Array, "6"]  # body-frame twist per unit time of the last motion with dt > 0


def init_state(cfg: TrackConfig, T_init: lie.SE3 | None = None) -> SLAMState:
    """Empty state; the first frame is placed at ``T_init`` (identity by default)."""
    T_init = lie.identity() if T_init is None else T_init
    origin = T_init.translation()
    geom = empty_geometry(cfg.capacity, cfg.voxel_size, origin)
    return SLAMState(geom=geom, T_prev=T_init, velocity=jnp.zeros(6))


def track_step(
    cfg: TrackConfig,
    state: SLAMState,
    depth: Float[Array, "h w"],
    intr: Intrinsics,
    dt: Float[Array, ""],
    *,
    differentiable: bool = True,
) -> tuple[SLAMState, lie.SE3, TrackInfo, InsertInfo]:
    """Track one frame against T, then add its non-overlapping geometry Gaussians to T.

    The first frame meets an empty T and keeps its initial pose. The guess is the constant-velocity
    prediction ``T_prev exp(v dt)`` (or ``T_prev`` when ``cfg.constant_velocity`` is off), where
    ``dt`` is the time between this depth image and the previous one: velocity in time rather than
    per frame, because TUM's depth and colour streams are not synchronised and consecutive frames
    can be 0, 1 or 2 depth images apart.

    With ``differentiable=False`` the pose comes from the solver alone, without the implicit-gradient
    wrapper of :func:`sgad_jax.track.track` (the host loop does not differentiate; it saves ~2 s of
    compilation).
    """
    cloud = gicp.frame_points(cfg, depth, intr)
    guess = state.T_prev @ lie.exp(state.velocity * dt) if cfg.constant_velocity else state.T_prev
    T, info = (track if differentiable else solve)(cfg, state.geom, cloud, guess)
    geom, ins = geometry.insert(state.geom, transform_cloud(T, cloud))
    moved = dt > 0
    velocity = jnp.where(moved, (state.T_prev.inverse() @ T).log() / jnp.where(moved, dt, 1.0), state.velocity)
    new = SLAMState(geom=geom, T_prev=T, velocity=velocity)
    return new, T, info, ins
