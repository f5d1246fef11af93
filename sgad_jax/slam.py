"""SGAD-SLAM steps composed from ``track`` (and, with the appearance branch, ``map_frame``).

Pure functions over :class:`SLAMState`; the host side is :class:`sgad_jax.system.SLAM` (one frame at
a time) and :func:`sgad_jax.pipeline.run` (a whole dataset: reading, progress, outputs).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from sgad_jax import geometry, gicp, lie, splat
from sgad_jax import mapping
from sgad_jax.config import MapConfig, TrackConfig
from sgad_jax.track import MIN_POINTS, relocalise, solve, track, transform_cloud
from sgad_jax.types import (
    FAIL_DEGENERATE, FAIL_INLIERS, FAIL_JUMP, FAIL_NONFINITE,
    Frame, GeometrySet, InsertInfo, Intrinsics, PixelGaussians, TrackInfo, empty_geometry,
)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SLAMState:
    """What tracking carries from frame to frame."""

    geom: GeometrySet
    T_prev: lie.SE3  # pose of the last tracked frame
    velocity: Float[Array, "6"]  # body-frame twist per unit time of the last motion with dt > 0
    inlier_share: Float[Array, ""]  # of the last accepted frame tracked against T (0 before one)


def init_state(cfg: TrackConfig, T_init: lie.SE3 | None = None) -> SLAMState:
    """Empty state; the first frame is placed at ``T_init`` (identity by default)."""
    T_init = lie.identity() if T_init is None else T_init
    origin = T_init.translation()
    geom = empty_geometry(cfg.capacity, cfg.voxel_size, origin)
    return SLAMState(geom=geom, T_prev=T_init, velocity=jnp.zeros(6), inlier_share=jnp.zeros(()))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Recent:
    """The frames mapping takes neighbours from, newest first, in fixed shapes: the frames queued for
    the next mapping batch (the first ``queued``), then the last mapped ones. ``index`` is the run
    index of each (-1: none yet)."""

    frame: Frame  # (m, h, w)
    pose: lie.SE3  # (m,) camera-to-world
    index: Int[Array, "m"]
    queued: Int[Array, ""]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class RunState:
    """Everything a run carries from frame to frame: tracking's state (with the geometry set T) and
    the recent frames of mapping (None when only tracking runs)."""

    track: SLAMState
    recent: Recent | None


def empty_recent(size: int, height: int, width: int) -> Recent:
    """Room for ``size`` frames (a mapping batch and its frames' neighbours), none yet."""
    z = np.zeros((size, height, width), np.float32)
    frame = Frame(rgb=np.zeros((size, height, width, 3), np.float32), depth=z, depth_filled=z, valid=z.astype(bool))
    pose = lie.SE3(jnp.tile(lie.identity().wxyz_xyz, (size, 1)))
    return Recent(frame=frame, pose=pose, index=jnp.full((size,), -1, jnp.int32), queued=jnp.zeros((), jnp.int32))


def remember(recent: Recent, frame: Frame, pose: lie.SE3, index: Int[Array, ""]) -> Recent:
    """Queue a tracked frame for mapping: it becomes the newest, the oldest is forgotten."""
    push = lambda old, new: jnp.concatenate([jnp.asarray(new)[None], old[:-1]])  # noqa: E731
    return Recent(
        frame=jax.tree.map(push, recent.frame, frame),
        pose=jax.tree.map(push, recent.pose, pose),
        index=push(recent.index, jnp.asarray(index, jnp.int32)),
        queued=jnp.minimum(recent.queued + 1, recent.index.shape[0]),
    )


def predict(cfg: TrackConfig, state: SLAMState, dt: Float[Array, ""]) -> lie.SE3:
    """The pose guess of the next frame: constant velocity ``T_prev exp(v dt)`` (or ``T_prev``)."""
    return state.T_prev @ lie.exp(state.velocity * dt) if cfg.constant_velocity else state.T_prev


def _finite(T: lie.SE3) -> Bool[Array, ""]:
    return jnp.all(jnp.isfinite(T.wxyz_xyz))


def _select(ok: Bool[Array, ""], T: lie.SE3, other: lie.SE3) -> lie.SE3:
    return jax.tree.map(lambda a, b: jnp.where(ok, a, b), T, other)


def _jump(T: lie.SE3, ref: lie.SE3) -> Float[Array, "2"]:
    """Translation (metres) and rotation (radians) from ``ref`` to ``T``."""
    rel = ref.inverse() @ T
    return jnp.stack([jnp.linalg.norm(rel.translation()), jnp.linalg.norm(rel.rotation().log())])


def _share(info: TrackInfo) -> Float[Array, ""]:
    return info.inliers / jnp.maximum(info.points, 1)


def judge(cfg: TrackConfig, info: TrackInfo, T: lie.SE3, jump: Float[Array, "2"], bound: tuple[float, ...]) -> Int[Array, ""]:
    """Failure bits (``sgad_jax.types.FAIL_*``, 0: healthy) of a solved pose ``T`` that moved
    ``jump`` (metres, radians) from where its solve started; ``bound`` in metres and degrees; the
    inlier share must reach ``info.inlier_floor``.

    A poorly conditioned Hessian is no failure by itself: along a corridor GICP keeps the guess's
    component in the direction the walls leave free, which is the best there is (a 30 m corridor
    walk goes down to 2.5e-6 while tracked to millimetres). It is added as a reason when another
    test fails."""
    bits = [
        (~_finite(T), FAIL_NONFINITE),
        (~(_share(info) >= info.inlier_floor) | (info.points == 0), FAIL_INLIERS),  # no point: nothing was tracked
        (~((jump[0] <= bound[0]) & (jump[1] <= jnp.radians(bound[1]))), FAIL_JUMP),
    ]
    failed = sum(jnp.where(b, v, 0) for b, v in bits).astype(jnp.int32)
    return failed + jnp.where((failed > 0) & ~(info.conditioning >= cfg.min_conditioning), FAIL_DEGENERATE, 0).astype(jnp.int32)


def track_step(
    cfg: TrackConfig,
    state: SLAMState,
    depth: Float[Array, "h w"],
    intr: Intrinsics,
    dt: Float[Array, ""],
    guess: lie.SE3 | None = None,
    *,
    differentiable: bool = True,
    key: jax.Array | None = None,
) -> tuple[SLAMState, lie.SE3, TrackInfo, InsertInfo]:
    """Track one frame against T, judge the pose, then add the frame's non-overlapping geometry
    Gaussians to T.

    The first frame meets an empty T and keeps its initial pose. The guess (unless given, e.g. by
    :func:`sgad_jax.mapping.refine_pose`) is the constant-velocity
    prediction ``T_prev exp(v dt)`` (or ``T_prev`` when ``cfg.constant_velocity`` is off), where
    ``dt`` is the time between this depth image and the previous one: velocity in time rather than
    per frame, because TUM's depth and colour streams are not synchronised and consecutive frames
    can be 0, 1 or 2 depth images apart.

    With ``cfg.judge`` the solved pose is judged (:func:`judge`: finite, inlier share against
    ``cfg.min_inlier_share`` times the last accepted frame's, jump from the guess, conditioning).
    A failed pose is relocalised (:func:`sgad_jax.track.relocalise`, then GICP from its result,
    judged again, ``cfg.relocalise``; not a frame without points to match); only on that branch
    of a ``lax.cond``, so healthy frames pay nothing for it. If that fails too, the frame keeps the guess (the previous pose if the
    guess is not finite), adds nothing to T and leaves the velocity as it was. A relocalised
    frame keeps the velocity too (its jump is no motion to extrapolate). A non-finite pose is a
    failure even with ``cfg.judge`` off. The failure bits and ``recovered`` are in the returned
    info. ``key`` draws the relocalisation's
    samples (default: a key folded with T's size, so a run is reproducible).

    With ``differentiable=False`` the pose comes from the solver alone, without the implicit-gradient
    wrapper of :func:`sgad_jax.track.track` (the host loop does not differentiate; it saves ~2 s of
    compilation).
    """
    solver = track if differentiable else solve
    cloud, cloud_t = gicp.frame_clouds(cfg, depth, intr)  # tracked, and what T receives
    guess = predict(cfg, state, dt) if guess is None else guess
    guess = _select(_finite(guess), guess, state.T_prev)
    # The share of matched points depends on how dense they are against the voxels (low-resolution
    # images match few), so a frame is judged against the share of the last accepted one.
    floor = cfg.min_inlier_share * state.inlier_share
    judged = cfg.judge & (state.geom.count > 0)  # the first frame has nothing to be judged against

    def first_failure(T, info):
        # A non-finite pose fails even unjudged: NaN must never reach a pose or the state. A frame
        # without a point (no depth in the tracking range) too: T stays empty, and nothing is tracked.
        unjudged = jnp.where(_finite(T), 0, FAIL_NONFINITE) + jnp.where(cfg.judge & (info.points == 0), FAIL_INLIERS, 0)
        return jnp.where(judged, judge(cfg, info, T, _jump(T, guess), cfg.max_jump), unjudged)

    def solve_from(start):
        T, info = solver(cfg, state.geom, cloud, start)
        return T, dataclasses.replace(info, inlier_floor=floor)

    if cfg.relocalise:
        # Two attempts in a loop, so that the solver is in the program once (it is most of the
        # step's compile time): from the guess, then, only after a failure, from the relocalised pose.
        no_info = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), jax.eval_shape(solve_from, guess)[1])
        k = jax.random.fold_in(jax.random.key(0), state.geom.count) if key is None else key

        # A frame without points to match (all depth missing) has nothing to relocalise.
        has_points = jnp.sum(cloud.valid) >= MIN_POINTS

        def attempt(retry, second):
            start = jax.lax.cond(second & retry, lambda: relocalise(cfg, state.geom, cloud, guess, key=k), lambda: guess)
            T, info = jax.lax.cond(second & ~retry, lambda: (start, no_info), lambda: solve_from(start))
            failure = first_failure(T, info)  # used of the first attempt only
            return retry | (~second & has_points & (failure != 0)), (start, T, info, failure)

        retried, tried = jax.lax.scan(attempt, jnp.zeros((), bool), jnp.array([False, True]))
        (_, T, info, failure), (T0, T1, info1, _) = (jax.tree.map(lambda a, i=i: a[i], tried) for i in (0, 1))
    else:
        T, info = solve_from(guess)
        failure = first_failure(T, info)
    jump = _jump(T, guess)
    info = dataclasses.replace(info, failure=failure, jump=jnp.where(jnp.isfinite(jump), jump, jnp.inf))
    iterations, share, recovered = info.iterations, _share(info), jnp.zeros((), bool)
    if cfg.relocalise:
        bad = judge(cfg, info1, T1, _jump(T1, T0), cfg.max_jump) | judge(cfg, info1, T1, _jump(T1, guess), cfg.relocalise_max_move)
        recovered = retried & (bad == 0)
        iterations = iterations + info1.iterations  # 0 when the second attempt solved nothing
        share = jnp.where(failure != 0, _share(info1), share)
    T = _select(failure == 0, T, _select(recovered, T1, guess) if cfg.relocalise else guess)
    info = dataclasses.replace(info, recovered=recovered, iterations=iterations)
    healthy = failure == 0
    accepted = healthy | recovered
    # A failed frame's points never reach T: its pose is only a guess.
    cloud_w = dataclasses.replace(transform_cloud(T, cloud_t), valid=cloud_t.valid & accepted)
    keyed_by = None
    if cfg.plane_points:  # the points on their planes, in the voxels the measured points fall in
        keyed_by, cloud_w = cloud_w.points, dataclasses.replace(cloud_w, points=lie.transform_points(*lie.rotation_components(T), cloud.points))
    geom = geometry.fuse(state.geom, cloud_w, cfg.fuse_observations, keyed_by) if cfg.fuse_observations > 1 else state.geom
    geom, ins = geometry.insert(geom, cloud_w, keyed_by)
    moved = (dt > 0) & healthy
    velocity = jnp.where(moved, (state.T_prev.inverse() @ T).log() / jnp.where(moved, dt, 1.0), state.velocity)
    velocity = jnp.where(jnp.all(jnp.isfinite(velocity)), velocity, state.velocity)
    share = jnp.where(accepted & (state.geom.count > 0), share, state.inlier_share)
    new = SLAMState(geom=geom, T_prev=T, velocity=velocity, inlier_share=share)
    return new, T, info, ins


def map_step(
    cfg: MapConfig,
    frame: Frame,
    pose: lie.SE3,
    neighbour_gaussians: PixelGaussians,
    neighbours: Frame,
    neighbour_poses: lie.SE3,
    present: Bool[Array, " n"],
    intr: Intrinsics,
) -> tuple[PixelGaussians, splat.Render, mapping.MapInfo]:
    """Map one tracked frame and render its view (SGAD-SLAM Eq. 1).

    ``neighbours`` (frames, their Gaussians and poses) are stacked with a fixed count ``n``;
    ``present`` marks the real ones (the first frames of a run have fewer). The neighbours'
    Gaussians are fixed: their learned ones when they were mapped before (the paper), their initial
    ones (:func:`sgad_jax.mapping.init_gaussians`) when they are mapped in the same batch; the caller
    chooses, so any set of tracked frames can be mapped at once (``vmap``, devices, hosts).
    With ``cfg.depth_fill == "render"`` the frame's missing depth is the neighbours' rendered depth
    where they cover the pixel (inpainted elsewhere). Returns the frame's Gaussians, its rendered
    view (own Gaussians over the neighbours') and the mapping record.
    """
    hide = jnp.where(present, 0.0, -1e4)[:, None, None]
    neighbour_gaussians = dataclasses.replace(neighbour_gaussians, opacity_logit=neighbour_gaussians.opacity_logit + hide)
    background = splat.render(neighbour_gaussians, neighbour_poses, pose, intr, layers=1)
    if cfg.depth_fill == "render":
        covered = background.alpha > mapping.COVERAGE
        seen = background.depth / jnp.maximum(background.alpha, 1e-3)
        frame = dataclasses.replace(frame, depth_filled=jnp.where(frame.valid, frame.depth, jnp.where(covered, seen, frame.depth_filled)))
    views = mapping.Views(
        rgb=jnp.concatenate([frame.rgb[None], neighbours.rgb]),
        depth=jnp.concatenate([frame.depth[None], neighbours.depth]),
        valid=jnp.concatenate([frame.valid[None], neighbours.valid]),
        pose=jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), pose, neighbour_poses),
        present=jnp.concatenate([jnp.ones(1, bool), present]),
    )
    g0 = mapping.init_gaussians(frame, intr, radius_init=cfg.radius_init)
    g, info = mapping.map_frame(cfg, g0, pose, views, intr, background)
    return g, mapping.render_frame(g, pose, background, intr), info
