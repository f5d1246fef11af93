"""Any scene size: a camera walks a corridor whose surface is many times the device set's capacity
and far beyond its key cube; T is paged to host memory and back, and tracking holds."""

import dataclasses
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sgad_jax import geometry, lie, paging
from sgad_jax.config import SLAMConfig, TrackConfig
from sgad_jax.eval.ate import ate, rpe
from sgad_jax.io.synthetic import look_at
from sgad_jax.system import SLAM
from sgad_jax.types import PointCloud, empty_geometry, make_intrinsics

HALL = (np.array([-1.2, 0.0, -3.0]), np.array([1.2, 2.6, 45.0]))  # the corridor's inside


def _pillars(seed=3):
    """Boxes along the walls and on the floor at irregular spacing (what fixes the pose along the
    corridor's axis, which its plain walls leave free)."""
    rng = np.random.default_rng(seed)
    boxes, z = [], -2.0
    while z < 44.0:
        side = rng.choice([-1, 1])
        depth, width, height = rng.uniform(0.15, 0.5), rng.uniform(0.2, 0.6), rng.uniform(0.8, 2.6)
        x0 = HALL[1][0] - depth if side > 0 else HALL[0][0]
        boxes.append((np.array([x0, 0.0, z]), np.array([x0 + depth, height, z + width])))
        if rng.uniform() < 0.4:
            c = rng.uniform(-0.5, 0.5)
            boxes.append((np.array([c - 0.2, 0.0, z + 0.3]), np.array([c + 0.2, rng.uniform(0.2, 0.6), z + 0.6])))
        z += rng.uniform(0.6, 1.4)
    return boxes


BOXES = _pillars()


def raycast_depth(T, intr) -> np.ndarray:
    """z-depth of the corridor seen from camera-to-world ``T`` (analytic: slabs of boxes)."""
    v, u = np.mgrid[0 : intr.height, 0 : intr.width].astype(np.float64)
    d_cam = np.stack([(u - float(intr.cx)) / float(intr.fx), (v - float(intr.cy)) / float(intr.fy), np.ones_like(u)], -1)
    d = d_cam @ T[:3, :3].T  # camera z component 1: the ray parameter is the z-depth
    o = T[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t_hall = np.min(np.where(d > 0, (HALL[1] - o) * inv, (HALL[0] - o) * inv), axis=-1)
        t = t_hall
        for lo, hi in BOXES:
            if lo[2] > o[2] + 8.0 or hi[2] < o[2] - 8.0:  # beyond the depth the test tracks with
                continue
            t1, t2 = (lo - o) * inv, (hi - o) * inv
            near, far = np.max(np.minimum(t1, t2), -1), np.min(np.maximum(t1, t2), -1)
            t = np.where((near <= far) & (near > 0) & (near < t), near, t)
    return t.astype(np.float32)


def walk(frames_out: int, frames_back: int, forward_m: float, back_m: float) -> np.ndarray:
    """Camera-to-world poses: along the corridor and partly back (facing forward throughout),
    easing in and out, with the gaze swaying between the walls."""
    k = np.arange(frames_out + frames_back, dtype=np.float64)
    z = np.where(
        k <= frames_out,
        forward_m * (1 - np.cos(np.pi * np.minimum(k, frames_out) / frames_out)) / 2,
        forward_m - back_m * (1 - np.cos(np.pi * (k - frames_out) / max(frames_back, 1))) / 2,
    )
    yaw = 0.15 * np.sin(k / 40.0)
    poses = []
    for zi, a, ki in zip(z, yaw, k):
        eye = np.array([0.15 * np.sin(ki / 50.0), 1.4, zi])
        poses.append(look_at(eye, eye + np.array([np.sin(a), -0.1, np.cos(a)])))
    return np.stack(poses)


def _track(poses, capacity, intr, cfg_track):
    cfg = dataclasses.replace(SLAMConfig(), track=dataclasses.replace(cfg_track, capacity=capacity))
    system = SLAM(cfg, intr, initial_pose=lie.from_matrix(poses[0]), track_only=True)
    for i, T in enumerate(poses):
        depth = raycast_depth(T, intr)
        system.add(types.SimpleNamespace(depth=depth, timestamp=i / 30.0, depth_timestamp=i / 30.0))
    return system, system.finish()


TRACK = TrackConfig(voxel_size=0.05, max_correspondence=0.05, max_depth=6.0, stride=2, window=5, k=10)  # matches within a voxel, as the defaults
INTR = make_intrinsics(60.0, 60.0, 39.5, 29.5, 80, 60)


@pytest.mark.slow
def test_corridor_longer_than_the_device_set():
    poses = walk(480, 120, forward_m=24.0, back_m=6.0)  # 30 m walked (at most 8 cm a frame); 24 m beyond the start
    assert 29.0 < np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum() < 31.0
    capacity = 1 << 15  # 32768 Gaussians of 5 cm: about 80 m^2, under a third of what the walk sees
    system, m = _track(poses, capacity, INTR, TRACK)
    est = system.trajectory()
    # It did not fit: the set was paged, the host holds the rest, nothing was dropped.
    assert len(m["geometry_pages"]) >= 5
    assert m["geometry_gaussians"] > 2 * capacity and m["geometry_on_device"] <= capacity
    assert m["geometry_dropped_points"] == {"overflow": 0, "out_of_range": 0}
    # Walking back brings the paged-out surface back: the way back adds little new.
    back = [e for e in m["geometry_pages"] if e["frame"] > 480]
    assert back, "the way back paged too"
    # ... and tracking is as good as on a short run of the same walk (per-frame drift).
    short, _ = _track(poses[:60], capacity, INTR, TRACK)
    long_rpe = rpe(est, poses)["trans_rmse_m"]
    short_rpe = rpe(short.trajectory(), poses[:60])["trans_rmse_m"]
    assert long_rpe < 1.5 * short_rpe + 1e-3, (long_rpe, short_rpe)
    assert ate(est, poses)["rmse_m"] < 0.05
    # The end pose, after 30 m: within 0.2% of the way walked (no drift runs away where T was
    # paged; the plain walls leave the corridor's axis to the pillars alone).
    assert np.linalg.norm(est[-1, :3, 3] - poses[-1, :3, 3]) < 0.06


def test_paging_keeps_every_voxel_once():
    """A set paged around a new position: the device keeps the entries nearest it, the archive the
    rest, no voxel twice, none lost; a second page back restores the first set's voxels."""
    rng = np.random.default_rng(0)
    v = 0.05
    pts = rng.uniform([-10, -1, -1], [30, 1, 1], (6000, 3)).T.astype(np.float32)
    cloud = PointCloud(points=jnp.asarray(pts), covs=jnp.tile(jnp.asarray([1.0, 1, 1, 0, 0, 0])[:, None], (1, 6000)), normals=jnp.zeros((3, 6000)), valid=jnp.ones(6000, bool))
    cfg = TrackConfig(voxel_size=v, capacity=8192, page_low=0.25, page_high=0.9)
    geom, _ = jax.jit(geometry.insert)(empty_geometry(cfg.capacity, v), cloud)
    keys0 = {tuple(k) for k in np.floor(np.asarray(geom.points[:, : int(geom.count)]).T / v).astype(int)}
    pager = paging.Pager(cfg, np.zeros(3))
    eye = np.array([25.0 - paging.AHEAD, 0.0, 0.0])
    far = pager.page(geom, look_at(eye, eye + [1.0, 0.0, 0.0]), frame=1)  # facing +x, 2 m short of x = 25
    on_device = np.asarray(far.points[:, : int(far.count)])
    assert int(far.count) == int(0.25 * 8192)
    assert np.allclose(np.asarray(far.origin), eye)
    # the entries nearest the point ahead of the camera: all on the device are nearer than any on the host
    centre = np.array([[25.0], [0.0], [0.0]])
    assert np.linalg.norm(on_device - centre, axis=0).max() <= np.linalg.norm(pager.archive[:3] - centre, axis=0).min() + 1e-6
    both = np.concatenate([on_device, pager.archive[:3]], axis=1)
    keys = [tuple(k) for k in np.floor(both.T / v).astype(int)]
    assert len(keys) == len(set(keys)) and set(keys) == keys0
    # The device set answers lookups at its new origin: each entry's voxel is occupied.
    assert bool(geometry.occupied(far, jnp.asarray(on_device)).all())
    back = pager.page(far, look_at(np.zeros(3), [1.0, 0.0, 0.0]), frame=2)
    again = np.concatenate([np.asarray(back.points[:, : int(back.count)]), pager.archive[:3]], axis=1)
    assert {tuple(k) for k in np.floor(again.T / v).astype(int)} == keys0
