"""Tracking health: a failed frame is detected, reported, kept out of T, and tracking recovers.

The oracles are independent of the judgement: ground-truth poses of the synthetic room, and a
geometry set built by inserting every frame at its ground-truth pose.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import cKDTree

from sgad_jax import geometry, gicp, lie, slam
from sgad_jax.cli import resolve_config
from sgad_jax.config import DataConfig, SLAMConfig, SyntheticConfig, TrackConfig
from sgad_jax.io.synthetic import SyntheticDataset, jump_pose
from sgad_jax.system import SLAM, compile_step
from sgad_jax.track import transform_cloud
from sgad_jax.types import FAIL_DEGENERATE, FAIL_INLIERS, FAIL_JUMP, FAIL_NONFINITE, TrackInfo, empty_geometry

# 320 x 240: T dense enough for its voxels (at 80 x 60 even clean frames lack matches).
CFG = resolve_config(None, None).track  # the demo preset's: the tests' CLI runs at 320 x 240 share its compiled step
JUMP = 5  # the frame from which the camera is displaced by 20 cm and 10 degrees


def STEP(cfg, state, depth, intr, dt, guess=None):
    """The host loop's compiled tracking step (kept per process: the `SLAM` runs here reuse it).
    It takes over ``state``'s buffers."""
    return compile_step(cfg, state, depth, intr, dt, guess)(state, depth, intr, dt, guess)


def _room(jump_frame: int = 0, frames: int = 9) -> SyntheticDataset:
    return SyntheticDataset(DataConfig(layout="synthetic", synthetic=SyntheticConfig(frames=frames, width=320, height=240, jump_frame=jump_frame)))


def _errors(T: np.ndarray, M_true: np.ndarray) -> tuple[float, float]:
    E = np.linalg.inv(M_true) @ np.asarray(T, np.float64)
    A = (E[:3, :3] - E[:3, :3].T) / 2
    return np.linalg.norm(E[:3, 3]), np.degrees(np.arctan2(np.linalg.norm([A[2, 1], A[0, 2], A[1, 0]]), (np.trace(E[:3, :3]) - 1) / 2))


def _run(cfg: TrackConfig, ds: SyntheticDataset, depths=None):
    """Poses, infos and geometry counts of the pure step over ``ds`` (or over ``depths``)."""
    depths = [ds[i].depth for i in range(len(ds))] if depths is None else depths
    state = slam.init_state(cfg, lie.from_matrix(ds.gt_poses[0]))
    poses, infos, counts = [], [], []
    for i, depth in enumerate(depths):
        state, T, _, info, _ = STEP(cfg, state, jnp.asarray(depth), ds.intrinsics, jnp.float32(0.0 if i == 0 else 1 / 30))
        poses.append(np.asarray(T.as_matrix()))
        infos.append(jax.tree.map(np.asarray, info))
        counts.append(int(state.geom.count))
    return poses, infos, counts, state


def _reference_points(cfg: TrackConfig, ds: SyntheticDataset) -> np.ndarray:
    """Points of the geometry set that ground-truth poses build from the same frames (T receives
    the measured depths, not the median ones the frame is tracked at)."""
    geom = empty_geometry(cfg.capacity, cfg.voxel_size, ds.gt_poses[0][:3, 3])
    for i in range(len(ds)):
        cloud = gicp.frame_clouds(cfg, jnp.asarray(ds[i].depth), ds.intrinsics)[1]
        geom, _ = geometry.insert(geom, transform_cloud(lie.from_matrix(ds.gt_poses[i]), cloud))
    return np.asarray(geom.points)[:, : int(geom.count)].T


@pytest.fixture(scope="module")
def jumped():
    return _room(JUMP)


@pytest.mark.slow
def test_clean_sequence_reports_no_failure():
    ds = _room()
    poses, infos, _, _ = _run(CFG, ds)
    assert [int(i.failure) for i in infos] == [0] * len(ds)
    for T, M in zip(poses, ds.gt_poses):
        t, r = _errors(T, M)
        assert t < 1e-3 and r < 0.05


@pytest.mark.slow
def test_sudden_jump_is_detected_and_relocalised(jumped):
    """The 20 cm / 10 degree jump is judged a failure, relocalisation finds the true pose, and the
    set T stays on the true surfaces (every stored point within a voxel of the ground-truth set)."""
    ds = jumped
    step_t, step_r = _errors(ds.gt_poses[JUMP], ds.gt_poses[JUMP - 1])
    assert step_t > 0.18 and step_r > 9.0  # the jump is there (plus the camera's own motion)
    poses, infos, counts, state = _run(CFG, ds)
    failed = [i for i, info in enumerate(infos) if int(info.failure)]
    assert failed == [JUMP]
    assert bool(infos[JUMP].recovered)
    for k in range(JUMP, min(JUMP + 3, len(ds))):
        t, r = _errors(poses[k], ds.gt_poses[k])
        assert t < 0.01 and r < 0.5, (k, t, r)
    stored = np.asarray(state.geom.points)[:, : counts[-1]].T
    d, _ = cKDTree(_reference_points(CFG, ds)).query(stored)
    assert np.quantile(d, 0.999) < CFG.voxel_size, np.quantile(d, [0.5, 0.99, 0.999, 1.0])


@pytest.mark.slow
def test_failed_frames_never_reach_the_geometry_set(jumped):
    """Without relocalisation the jump frame (and those after it, whose guesses miss as badly) keep
    their guess, add nothing to T, and the pose after the jump is the constant-velocity guess."""
    ds = jumped
    cfg = dataclasses.replace(CFG, relocalise=False)
    poses, infos, counts, _ = _run(cfg, ds)
    assert all(int(i.failure) == 0 for i in infos[:JUMP])
    assert int(infos[JUMP].failure) != 0 and not bool(infos[JUMP].recovered)
    assert counts[JUMP:] == [counts[JUMP - 1]] * (len(ds) - JUMP)
    # The guess at the jump: the previous pose moved on by the last motion (the synthetic camera's
    # speed is nearly constant), so within a few millimetres of where it would have been unjumped.
    unjumped = ds.gt_poses[JUMP] @ np.linalg.inv(jump_pose(*ds.synthetic.jump))
    t, _ = _errors(poses[JUMP], unjumped)
    assert t < 0.005
    assert all(np.isfinite(p).all() for p in poses)


@pytest.mark.slow
def test_invalid_depth_gives_a_finite_pose_and_a_record():
    """An all-NaN and an all-zero depth image: finite poses, FAIL_INLIERS, nothing added to T;
    the frame after them is tracked as before. The host loop reports them in tracking_failures."""
    ds = _room(frames=5)
    depths = [ds[i].depth for i in range(len(ds))]
    depths[2] = np.full_like(depths[2], np.nan)
    depths[3] = np.zeros_like(depths[3])
    poses, infos, counts, _ = _run(CFG, ds, depths)
    for k in (2, 3):
        assert np.isfinite(poses[k]).all()
        assert int(infos[k].failure) & FAIL_INLIERS and not int(infos[k].failure) & FAIL_NONFINITE
        assert not bool(infos[k].recovered)
        assert counts[k] == counts[1]
    t, r = _errors(poses[4], ds.gt_poses[4])
    assert t < 1e-3 and r < 0.05
    # With no point to match there is nothing to relocalise: no more solver steps than without relocalisation.
    _, plain, _, _ = _run(dataclasses.replace(CFG, relocalise=False), ds, depths)
    assert [int(infos[k].iterations) for k in (2, 3)] == [int(plain[k].iterations) for k in (2, 3)]

    system = SLAM(SLAMConfig(track=CFG), ds.intrinsics, initial_pose=lie.from_matrix(ds.gt_poses[0]), track_only=True)
    for i in range(len(ds)):
        system.add(dataclasses.replace(ds[i], depth=depths[i]))
    failures = system.finish()["tracking_failures"]
    assert [f["frame"] for f in failures] == [2, 3]
    assert all(f["reason"].startswith("no point to track (no depth within track.min_depth / max_depth, 0.1 / 0 m)") and f["recovered"] is False for f in failures), failures
    # No frame with depth in the tracking range: T stays empty and every frame, the first too, is a
    # failure (they used to pass unjudged, at the initial pose, with nothing said)
    short = SLAM(SLAMConfig(track=dataclasses.replace(CFG, max_depth=0.01)), ds.intrinsics, track_only=True)
    for i in range(len(ds)):
        short.add(ds[i])
    assert [f["frame"] for f in short.finish()["tracking_failures"]] == list(range(len(ds)))
    arrays, meta = system.checkpoint_state()
    again = SLAM(SLAMConfig(track=CFG), ds.intrinsics, track_only=True)
    again.restore(arrays, meta)
    assert again.finish()["tracking_failures"] == failures


def test_jump_pose_is_the_configured_displacement():
    M = jump_pose(0.2, 10.0)
    assert np.linalg.norm(M[:3, 3]) == pytest.approx(0.2)
    assert np.degrees(np.arccos((np.trace(M[:3, :3]) - 1) / 2)) == pytest.approx(10.0, rel=1e-6)
    np.testing.assert_allclose(M[:3, :3] @ M[:3, :3].T, np.eye(3), atol=1e-12)


def test_judge_sets_one_bit_per_reason():
    """Each criterion alone sets its bit (degeneracy only beside another); a healthy solve sets none."""
    cfg = TrackConfig()
    info = TrackInfo(
        iterations=jnp.int32(5), converged=jnp.bool_(True), cost=jnp.float32(1.0), inliers=jnp.int32(900),
        points=jnp.int32(1000), conditioning=jnp.float32(1e-2), failure=jnp.int32(0), recovered=jnp.bool_(False),
        jump=jnp.zeros(2), inlier_floor=jnp.float32(0.3 * 0.95),
    )
    T = lie.identity()
    ok_jump = jnp.array([0.05, np.radians(3.0)])
    assert int(slam.judge(cfg, info, T, ok_jump, cfg.max_jump)) == 0
    nan_T = lie.SE3(jnp.full(7, jnp.nan))
    assert int(slam.judge(cfg, info, nan_T, ok_jump, cfg.max_jump)) & FAIL_NONFINITE
    few = dataclasses.replace(info, inliers=jnp.int32(200))
    assert int(slam.judge(cfg, few, T, ok_jump, cfg.max_jump)) == FAIL_INLIERS
    assert int(slam.judge(cfg, info, T, jnp.array([0.2, 0.0]), cfg.max_jump)) == FAIL_JUMP
    assert int(slam.judge(cfg, info, T, jnp.array([0.0, np.radians(10.0)]), cfg.max_jump)) == FAIL_JUMP
    flat = dataclasses.replace(info, conditioning=jnp.float32(1e-6))
    assert int(slam.judge(cfg, flat, T, ok_jump, cfg.max_jump)) == 0  # a corridor: degenerate, not failed
    assert int(slam.judge(cfg, flat, T, jnp.array([0.2, 0.0]), cfg.max_jump)) == FAIL_JUMP | FAIL_DEGENERATE
    empty = dataclasses.replace(info, inliers=jnp.int32(0), points=jnp.int32(0))
    assert int(slam.judge(cfg, empty, T, ok_jump, cfg.max_jump)) == FAIL_INLIERS


@pytest.mark.slow
def test_non_finite_guess_falls_back_to_the_previous_pose():
    """A NaN guess (a broken rendering-based initialisation, say) is replaced by the previous pose,
    from which GICP tracks the frame as usual."""
    ds = _room(frames=3)
    state = slam.init_state(CFG, lie.from_matrix(ds.gt_poses[0]))
    for i in range(2):
        state, _, _, _, _ = STEP(CFG, state, jnp.asarray(ds[i].depth), ds.intrinsics, jnp.float32(i / 30))
    nan_guess = lie.SE3(jnp.full(7, jnp.nan))
    state, T, _, info, _ = STEP(CFG, state, jnp.asarray(ds[2].depth), ds.intrinsics, jnp.float32(1 / 30), nan_guess)
    assert np.isfinite(np.asarray(T.as_matrix())).all() and np.isfinite(np.asarray(state.velocity)).all()
    t, r = _errors(np.asarray(T.as_matrix()), ds.gt_poses[2])
    assert int(info.failure) == 0 and t < 1e-3 and r < 0.05
