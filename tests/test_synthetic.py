"""The built-in synthetic room: sizes, plausible depth, texture, exact geometry, trajectory, noise."""

import dataclasses

import numpy as np
import pytest

from sgad_jax.config import DataConfig, SyntheticConfig
from sgad_jax.io.base import DatasetError
from sgad_jax.io.synthetic import FLOOR_Y, ROOM_MAX, SPHERES, SyntheticDataset, look_at, raycast


def make(frames=12, width=64, height=48, depth_noise=0.0, seed=0, **data):
    return SyntheticDataset(DataConfig(synthetic=SyntheticConfig(frames, width, height, depth_noise, seed), **data))


def backproject(depth, T_wc, fx, fy, cx, cy):
    """World points (h, w, 3) of a z-depth image, written out independently of the renderer."""
    v, u = np.mgrid[: depth.shape[0], : depth.shape[1]]
    pc = np.stack([(u - cx) / fx * depth, (v - cy) / fy * depth, depth], -1).astype(np.float64)
    return pc @ T_wc[:3, :3].T + T_wc[:3, 3]


def test_sizes_counts_and_metadata():
    ds = make(frames=7, width=80, height=60)
    assert len(ds) == 7 and ds.layout == "synthetic" and ds.name == "synthetic"
    k = ds.intrinsics
    assert (k.width, k.height) == (80, 60)
    assert k.as_tuple() == pytest.approx((72.0, 72.0, 39.5, 29.5))
    s = ds[6]
    assert s.rgb.shape == (60, 80, 3) and s.rgb.dtype == np.uint8
    assert s.depth.shape == (60, 80) and s.depth.dtype == np.float32
    assert s.timestamp == pytest.approx(6 / 30)
    assert ds.has_gt and ds.gt_poses.shape == (7, 4, 4)
    np.testing.assert_allclose(ds.timestamps, np.arange(7) / 30)


@pytest.mark.parametrize(
    "synthetic",
    [dict(frames=0), dict(width=15), dict(height=8), dict(depth_noise=-0.1), dict(depth_noise=float("nan"))],
)
def test_invalid_settings(synthetic):
    with pytest.raises(DatasetError, match="synthetic"):
        SyntheticDataset(DataConfig(synthetic=dataclasses.replace(SyntheticConfig(), **synthetic)))


def test_depth_plausible_and_texture_present():
    ds = make(frames=60, width=160, height=120)
    for i in (0, 29, 59):
        s = ds[i]
        plausible = (s.depth > 0.3) & (s.depth < 8.0)
        assert plausible.mean() > 0.95
        assert s.rgb.reshape(-1, 3).std(0).min() > 20  # every channel varies
        # texture inside one surface too: a 16 x 16 patch at the centre is not flat
        assert s.rgb[52:68, 72:88].astype(float).std() > 5


def test_floor_and_sphere_geometry_exact():
    """Back-project pixels of chosen views by hand and check they land on the analytic surfaces."""
    w, h, f = 97, 73, 80.0
    cx, cy = (w - 1) / 2, (h - 1) / 2  # pixel (h // 2, w // 2) is on the optical axis
    # looking steeply down at an empty patch of floor near the front of the room
    T = look_at([0.0, 1.6, 1.2], [0.0, FLOOR_Y, 2.0])
    _, depth = raycast(T, f, f, cx, cy, w, h)
    pts = backproject(depth, T, f, f, cx, cy)
    floor = np.abs(pts[..., 1] - FLOOR_Y) < 1e-3
    assert floor.mean() > 0.5
    centre = pts[h // 2, w // 2]
    assert centre[1] == pytest.approx(FLOOR_Y, abs=1e-5)
    # on the optical axis the hit is where the ray (eye -> target) meets the floor
    np.testing.assert_allclose(centre, [0.0, FLOOR_Y, 2.0], atol=1e-5)
    # facing the back-right large sphere: the centre pixel lies on it, at distance r from its centre
    c, r = np.array(SPHERES[1][0]), SPHERES[1][1]
    T = look_at([0.5, 1.4, 1.0], c)
    _, depth = raycast(T, f, f, cx, cy, w, h)
    p = backproject(depth, T, f, f, cx, cy)[h // 2, w // 2]
    assert np.linalg.norm(p - c) == pytest.approx(r, abs=1e-5)
    # and the z-depth is distance to the centre minus the radius (axis through the centre)
    assert depth[h // 2, w // 2] == pytest.approx(np.linalg.norm(c - [0.5, 1.4, 1.0]) - r, abs=1e-5)
    # an upward view sees the ceiling
    T = look_at([0.0, 1.5, 0.0], [0.0, ROOM_MAX[1], 0.0], up=(0.0, 0.0, -1.0))
    _, depth = raycast(T, f, f, cx, cy, w, h)
    np.testing.assert_allclose(backproject(depth, T, f, f, cx, cy)[..., 1], ROOM_MAX[1], atol=1e-5)


def test_trajectory_smooth_and_valid():
    poses = make(frames=300).gt_poses
    R = poses[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    assert steps.max() < 0.10 and steps.min() > 0.001
    rel = np.einsum("nji,njk->nik", R[:-1], R[1:])
    angle = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert angle.max() < 5.0
    assert 0.5 < steps[:59].sum() < 1.5  # about a metre over the default 60 frames


def test_depth_noise_deterministic_with_configured_std():
    clean = make(frames=3, width=160, height=120)[2].depth
    a = make(frames=3, width=160, height=120, depth_noise=0.01, seed=3)[2]
    b = make(frames=3, width=160, height=120, depth_noise=0.01, seed=3)[2]
    c = make(frames=3, width=160, height=120, depth_noise=0.01, seed=4)[2]
    np.testing.assert_array_equal(a.depth, b.depth)
    assert not np.array_equal(a.depth, c.depth)
    missing = a.depth == 0
    assert 0.005 < missing.mean() < 0.02
    rel = (a.depth[~missing] - clean[~missing]) / clean[~missing]
    assert rel.std() == pytest.approx(0.01, rel=0.05)
    assert abs(rel.mean()) < 1e-3
    assert (a.depth_filled > 0).all()  # holes inpainted by the base class
    assert (clean > 0).all()  # no holes without noise


def test_frame_selection_and_downscale_through_base_class():
    full = make(frames=20)
    ds = make(frames=20, start=3, stride=2, max_frames=5)
    np.testing.assert_array_equal(ds.selection, [3, 5, 7, 9, 11])
    s = ds[1]
    assert (s.index, s.source_index) == (1, 5)
    np.testing.assert_array_equal(s.depth, full[5].depth)
    np.testing.assert_array_equal(s.pose_gt, full.gt_poses_raw[5])
    np.testing.assert_allclose(ds.timestamps, np.array([3, 5, 7, 9, 11]) / 30)
    small = make(frames=20, downscale=2)[0]
    assert small.rgb.shape == (24, 32, 3) and small.depth.shape == (24, 32)
    with pytest.raises(DatasetError):
        make(frames=5, start=5)


def test_screen_space_culling_changes_nothing(monkeypatch):
    """Random views (also next to objects) render identically with every object tested on every pixel."""
    import sgad_jax.io.synthetic as synthetic

    rng = np.random.default_rng(0)
    views = []
    while len(views) < 40:
        eye = rng.uniform(synthetic.ROOM_MIN + 0.05, synthetic.ROOM_MAX - 0.05)
        in_box = any((eye > lo).all() and (eye < hi).all() for lo, hi in np.array(synthetic.BOXES))
        in_sphere = any(np.linalg.norm(eye - c) < r for c, r in synthetic.SPHERES)
        if not (in_box or in_sphere):
            views.append(look_at(eye, eye + rng.normal(size=3)))
    culled = [raycast(T, 40.0, 40.0, 31.5, 23.5, 64, 48) for T in views]
    monkeypatch.setattr(synthetic, "_window", lambda *args: (slice(0, 48), slice(0, 64)))
    for T, (rgb, depth) in zip(views, culled):
        rgb_all, depth_all = raycast(T, 40.0, 40.0, 31.5, 23.5, 64, 48)
        np.testing.assert_array_equal(depth, depth_all)
        np.testing.assert_array_equal(rgb, rgb_all)
