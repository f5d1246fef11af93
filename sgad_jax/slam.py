"""SGAD-SLAM steps composed from ``track`` (and, with the appearance branch, ``map_frame``).

Pure functions over :class:`SLAMState`; the host loop (file reading, progress, outputs) lives in
``sgad_jax.pipeline``.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from sgad_jax import geometry, gicp, lie
from sgad_jax.config import TrackConfig
from sgad_jax.track import track, transform_cloud
from sgad_jax.types import GeometrySet, InsertInfo, Intrinsics, TrackInfo, empty_geometry


@functools.partial(jax.tree_util.register_dataclass, data_fields=["geom", "T_prev", "T_prev2", "frames"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class SLAMState:
    """What tracking carries from frame to frame."""

    geom: GeometrySet
    T_prev: lie.SE3  # pose of the last tracked frame
    T_prev2: lie.SE3  # pose of the one before
    frames: Int[Array, ""]  # frames tracked so far


def init_state(cfg: TrackConfig, T_init: lie.SE3 | None = None) -> SLAMState:
    """Empty state; the first frame is placed at ``T_init`` (identity by default)."""
    T_init = lie.identity() if T_init is None else T_init
    origin = T_init.translation()
    geom = empty_geometry(cfg.capacity, cfg.voxel_size, origin)
    return SLAMState(geom=geom, T_prev=T_init, T_prev2=T_init, frames=jnp.zeros((), jnp.int32))


def track_step(
    cfg: TrackConfig, state: SLAMState, depth: Float[Array, "h w"], intr: Intrinsics
) -> tuple[SLAMState, lie.SE3, TrackInfo, InsertInfo]:
    """Track one frame against T, then add its non-overlapping geometry Gaussians to T.

    The first frame meets an empty T and keeps its initial pose. The guess is the constant-velocity
    prediction (or the previous pose when ``cfg.constant_velocity`` is off).
    """
    cloud = gicp.frame_points(cfg, depth, intr)
    guess = lie.constant_velocity(state.T_prev, state.T_prev2) if cfg.constant_velocity else state.T_prev
    T, info = track(cfg, state.geom, cloud, guess)
    geom, ins = geometry.insert(state.geom, transform_cloud(T, cloud))
    new = SLAMState(geom=geom, T_prev=T, T_prev2=state.T_prev, frames=state.frames + 1)
    return new, T, info, ins
