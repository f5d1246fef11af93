"""Tracking on the analytic synthetic room: known poses recovered, jit / vmap / grad, no recompilation."""

import dataclasses
import functools

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import shared
from sgad_jax import gicp, lie, pipeline, slam
from sgad_jax.system import SLAM, compile_step, initial_pose, repeats
from sgad_jax.cli import resolve_config
from sgad_jax.config import ConfigError, DataConfig, SyntheticConfig, TrackConfig
from sgad_jax.io.synthetic import SyntheticDataset
from sgad_jax.types import make_frame
from sgad_jax.track import _stretch, cost, solve, track

CFG = resolve_config(None, None).track  # the demo preset's: the tests' CLI runs at 320 x 240 share its compiled step


@pytest.fixture(scope="module")
def scene():
    ds = SyntheticDataset(DataConfig(layout="synthetic", synthetic=SyntheticConfig(frames=8, width=320, height=240)))
    T0 = lie.from_matrix(ds.gt_poses[0])
    state = slam.init_state(CFG, lie.from_matrix(ds.gt_poses[0]))  # not T0: the step takes over the state's buffers
    depth0 = jnp.asarray(ds[0].depth)
    # the host loop's compiled step (kept per process: test_repeated_depth_image's SLAM reuses it)
    state, T, _, _, _ = compile_step(CFG, state, depth0, ds.intrinsics, jnp.float32(0.0))(state, depth0, ds.intrinsics, jnp.float32(0.0), None)
    cloud0 = gicp.frame_points(CFG, depth0, ds.intrinsics)
    return ds, state.geom, cloud0, T0


def _errors(T, M_true):
    E = np.linalg.inv(np.asarray(M_true, np.float64)) @ np.asarray(T.as_matrix(), np.float64)
    A = (E[:3, :3] - E[:3, :3].T) / 2  # arctan2 of sin and cos: accurate for small angles, unlike arccos
    angle = np.degrees(np.arctan2(np.linalg.norm([A[2, 1], A[0, 2], A[1, 0]]), (np.trace(E[:3, :3]) - 1) / 2))
    return np.linalg.norm(E[:3, 3]), angle


def test_first_frame_fills_geometry_set(scene):
    """Frame 0 (met with an empty T) adds one Gaussian per occupied voxel, in world coordinates."""
    ds, geom, cloud0, T0 = scene
    n = int(geom.count)
    valid = np.asarray(cloud0.valid)
    M = ds.gt_poses[0]
    p_w = M[:3, :3] @ np.asarray(cloud0.points)[:, valid] + M[:3, 3:]
    voxels = {tuple(v) for v in np.floor((p_w - np.asarray(geom.origin)[:, None]) / CFG.voxel_size).T.astype(int)}
    assert abs(n - len(voxels)) <= 0.002 * n  # float32 vs float64 rounding at voxel borders


def test_recovers_known_pose_exactly(scene):
    """The frame that built T, placed at a perturbed guess, is pulled back to its true pose."""
    ds, geom, cloud0, T0 = scene
    guess = lie.exp(jnp.array([0.012, -0.008, 0.01, 0.004, -0.006, 0.005])) @ T0
    T, info = jax.jit(track, static_argnums=0)(CFG, geom, cloud0, guess)
    t_err, r_err = _errors(T, ds.gt_poses[0])
    assert bool(info.converged)
    assert t_err < 1e-4 and r_err < 0.01, (t_err, r_err)


@pytest.mark.parametrize("j", [1, 3])
def test_tracks_another_view(scene, j):
    """A later frame (1.5-6 cm away) against T of frame 0, from the previous pose as guess."""
    ds, geom, cloud0, T0 = scene
    cloud = gicp.frame_points(CFG, jnp.asarray(ds[j].depth), ds.intrinsics)
    T, info = track(CFG, geom, cloud, lie.from_matrix(ds.gt_poses[j - 1]))
    t_err, r_err = _errors(T, ds.gt_poses[j])
    moved = np.linalg.norm(ds.gt_poses[j][:3, 3] - ds.gt_poses[0][:3, 3])
    assert moved > 0.015
    assert t_err < 5e-4 and r_err < 0.05, (t_err, r_err)


@pytest.mark.parametrize("j", [1, 3, 4])
def test_coarse_to_fine_and_extrapolation_are_as_accurate_as_plain_gauss_newton(scene, j):
    """Converging on every 3rd point first, then on all, and stretching updates that keep
    shrinking the same way, recover the true pose as closely as plain Gauss-Newton on the full
    cost (all within the noise-free bound of T's 3 cm voxels, 1.5e-4 m / 0.01 degree)."""
    ds, geom, cloud0, T0 = scene
    cloud = gicp.frame_points(CFG, jnp.asarray(ds[j].depth), ds.intrinsics)
    guess = lie.from_matrix(ds.gt_poses[j - 1])
    for levels in ((), (3,)):
        for stretch in (1.0, 4.0):
            T, info = solve(dataclasses.replace(CFG, coarse=levels, extrapolation=stretch), geom, cloud, guess)
            t_err, r_err = _errors(T, ds.gt_poses[j])
            assert bool(info.converged) and t_err < 1.5e-4 and r_err < 0.01, (levels, stretch, t_err, r_err)


def test_coarse_levels_must_take_points():
    with pytest.raises(ConfigError, match="track.coarse"):
        TrackConfig(coarse=(3, 0))


def test_extrapolation_can_only_lengthen_updates():
    with pytest.raises(ConfigError, match="track.extrapolation"):
        TrackConfig(extrapolation=0.5)


def test_stretch_sums_a_geometric_sequence_of_updates():
    """Updates shrinking by rho in one direction leave xi / (1 - rho) to go: a stretch of
    1 / (1 - rho), capped at cfg.extrapolation; an update that turns back is taken as it is."""
    cfg = TrackConfig(extrapolation=4.0)
    prev = jnp.array([0.004, -0.002, 0.001, 0.0005, 0.0, -0.001])
    for rho, want in ((0.5, 2.0), (0.2, 1.25), (0.9, 4.0), (-0.5, 1.0), (0.0, 1.0)):
        assert float(_stretch(cfg, rho * prev, prev)) == pytest.approx(want, rel=1e-5), rho
    turned = jnp.array([0.002, 0.004, 0.0, 0.0, 0.0, 0.0])  # orthogonal to prev
    assert float(_stretch(cfg, turned, prev)) == pytest.approx(1.0)
    assert float(_stretch(cfg, prev, jnp.zeros(6))) == 1.0  # a level's first step
    assert float(_stretch(TrackConfig(extrapolation=1.0), 0.5 * prev, prev)) == 1.0


@pytest.mark.slow
def test_extrapolation_takes_fewer_steps_on_real_frames():
    """On TUM fr1/xyz (a handheld camera: constant-velocity guesses off by up to 2 cm) stretched
    updates reach the solver's tolerance in fewer steps than plain Gauss-Newton, at poses within a
    millimetre of its."""
    data = shared("tum_fr1_xyz")
    runs = {}
    for stretch in (1.0, 4.0):
        cfg = resolve_config(None, str(data), overrides=[f"track.extrapolation={stretch}"])
        runs[stretch] = pipeline.run(cfg, track_only=True, progress=False)
    plain, fast = runs[1.0], runs[4.0]
    steps = [r.metrics["track_iterations_mean"] for r in (plain, fast)]
    # TUM: 5.6 -> 4.8 steps a frame without the preset's plane points, 5.1 -> 4.4 with them
    assert steps[1] < 0.9 * steps[0], steps
    assert np.abs(fast.poses[:, :3, 3] - plain.poses[:, :3, 3]).max() < 1e-3


@pytest.mark.slow
def test_vmap_over_guesses(scene):
    ds, geom, cloud0, T0 = scene
    xis = jnp.array([[0.01, 0, 0, 0, 0, 0], [0, -0.01, 0.005, 0, 0.003, 0], [0, 0, 0, 0.005, 0, -0.004]])
    guesses = jax.vmap(lambda xi: lie.exp(xi) @ T0)(xis)
    Ts, infos = jax.jit(jax.vmap(lambda g: track(CFG, geom, cloud0, g)))(guesses)
    for k in range(3):
        t_err, r_err = _errors(jax.tree.map(lambda a: a[k], Ts), ds.gt_poses[0])
        assert t_err < 1e-4 and r_err < 0.01
    assert infos.iterations.shape == (3,)


@pytest.mark.slow
def test_cost_gradient_matches_finite_differences(scene):
    """d cost / d xi at a perturbed pose (correspondences held) against central differences."""
    ds, geom, cloud0, T0 = scene
    T = lie.exp(jnp.array([0.003, -0.002, 0.001, 0.001, 0.0, -0.001])) @ T0
    f = jax.jit(lambda xi: cost(CFG, geom, cloud0, lie.exp(xi) @ T))
    grad = jax.jit(jax.grad(f))(jnp.zeros(6))
    # Correspondences are piecewise constant in the pose and re-picked at every evaluation: with a
    # 0.2 mm step few of them switch, hence the 2 % tolerance.
    h = 2e-4
    fd = np.array([(f(h * e) - f(-h * e)) / (2 * h) for e in np.eye(6)])
    np.testing.assert_allclose(grad, fd, rtol=0.02, atol=0.02 * np.abs(fd).max())


@pytest.mark.slow
def test_implicit_gradient_of_tracked_pose(scene):
    """Shifting every point of the frame by d (camera frame) moves the optimum by -R d exactly."""
    ds, geom, cloud0, T0 = scene
    guess = lie.exp(jnp.array([0.004, 0.003, -0.002, 0.0, 0.002, 0.0])) @ T0

    def tracked_translation(d):
        shifted = dataclasses.replace(cloud0, points=cloud0.points + d[:, None])
        T, _ = track(CFG, geom, shifted, guess)
        return T.translation()

    J = jax.jit(jax.jacrev(tracked_translation))(jnp.zeros(3))  # one program: op by op it compiles ~1,200 small ones
    R = np.asarray(T0.rotation().as_matrix())
    np.testing.assert_allclose(J, -R, atol=5e-3)


def test_depth_weighted_cost(scene):
    """The weighted cost is the unweighted cost with each point's term scaled by (z / 1 m)^-p:
    summed over narrow depth bands of the frame's points (each band's unweighted cost, from the
    valid mask, times its depth^-p), for p = 1 and 2."""
    ds, geom, cloud0, T0 = scene
    z = np.asarray(cloud0.points[2])
    valid = np.asarray(cloud0.valid)
    T = lie.exp(jnp.array([0.003, -0.002, 0.001, 0.001, 0.0, -0.001])) @ T0
    unweighted = dataclasses.replace(CFG, depth_weight_power=0.0)
    cost_jit = jax.jit(cost, static_argnums=0)
    edges = np.arange(z[valid].min(), z[valid].max() + 0.02, 0.01)
    bands = [(lo + hi) / 2 for lo, hi in zip(edges[:-1], edges[1:])]
    parts = [
        float(cost_jit(unweighted, geom, dataclasses.replace(cloud0, valid=jnp.asarray(valid & (z >= lo) & (z < hi))), T))
        for lo, hi in zip(edges[:-1], edges[1:])
    ]
    for p in (1.0, 2.0):
        weighted = cost(dataclasses.replace(CFG, depth_weight_power=p), geom, cloud0, T)
        expected = sum(c * max(zb, 0.3) ** -p for c, zb in zip(parts, bands))
        np.testing.assert_allclose(float(weighted), expected, rtol=0.01)
        assert abs(float(weighted) - sum(parts)) > 0.05 * sum(parts)  # the weights matter here


@pytest.mark.slow
def test_track_step_does_not_recompile(scene):
    ds = scene[0]
    # the host loop's jit (the plain solver, the state donated): the fixture's program, from the cache
    @functools.wraps(slam.track_step)
    def plain(cfg, state, depth, intr, dt, guess):
        return slam.track_step(cfg, state, depth, intr, dt, guess, differentiable=False)

    traced = chex.assert_max_traces(plain, n=1)
    step = jax.jit(traced, static_argnums=0, donate_argnums=1)
    state = slam.init_state(CFG, lie.from_matrix(ds.gt_poses[0]))
    for i in range(4):
        state, T, info, ins = step(CFG, state, jnp.asarray(ds[i].depth), ds.intrinsics, jnp.float32(i / 30), None)
    t_err, _ = _errors(T, ds.gt_poses[3])
    assert t_err < 1e-3
    assert int(ins.overflow) == 0


_WIDE_VS_DEFAULT = """
import json, jax, jax.numpy as jnp, numpy as np
from sgad_jax import gicp, lie, slam, system
from sgad_jax.cli import resolve_config
from sgad_jax.config import DataConfig, SyntheticConfig
from sgad_jax.io.synthetic import SyntheticDataset
cfg = resolve_config(None, None).track
ds = SyntheticDataset(DataConfig(layout="synthetic", synthetic=SyntheticConfig(frames=5, width=320, height=240)))
wide = system.TRACK_CPU_OPTIONS
depth = jnp.asarray(ds[1].depth)
clouds = jax.jit(lambda d: gicp.frame_clouds(cfg, d, ds.intrinsics)).lower(depth)
a, b = (jax.tree.leaves(clouds.compile(o)(depth)) for o in (None, wide))
init = lambda: slam.init_state(cfg, lie.from_matrix(ds.gt_poses[0]))
lowered = jax.jit(system._host_step, static_argnums=0).lower(cfg, init(), depth, ds.intrinsics, jnp.float32(0), None)
runs = []
for options in (None, wide):
    step, state, poses = lowered.compile(options), init(), []
    for i in range(len(ds)):
        state, _, pose, _, _ = step(state, jnp.asarray(ds[i].depth), ds.intrinsics, jnp.float32(i / 30), None)
        poses.append(np.asarray(pose))
    runs.append((np.stack(poses), int(state.geom.count)))
print(json.dumps({
    "clouds": max(float(np.max(np.abs(np.asarray(x, np.float64) - np.asarray(y, np.float64)))) for x, y in zip(a, b)),
    "pose": float(np.abs(runs[1][0] - runs[0][0]).max()),
    "count": [runs[0][1], runs[1][1]],
}))
"""


@pytest.mark.slow
@pytest.mark.skipif(jax.default_backend() != "cpu", reason="the 512-bit vectors are an XLA:CPU option")
def test_step_compiled_for_wide_vectors_tracks_as_the_default_compile():
    """`compile_step` compiles the step with `TRACK_CPU_OPTIONS` (512-bit vectors) on CPU. XLA:CPU
    has miscompiled functions at that width (jaxlib 0.10.2's atan returns wrong values,
    jax-ml/jax#39352): the step compiled so must give the default compile's frame clouds (points,
    covariances, normals) and poses. In a process of its own, with XLA's default flags: the suite's
    fast-compile flags (conftest.py) take another path."""
    import json
    import os
    import subprocess
    import sys

    env = {**os.environ, "XLA_FLAGS": ""}
    out = subprocess.run([sys.executable, "-c", _WIDE_VS_DEFAULT], env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    diff = json.loads(out.stdout.strip().splitlines()[-1])
    # Float32 rounding differs (rsqrt, sums) between the two: a pose a few 1e-6 off moves points
    # across voxel borders, so T's size agrees within 0.2%.
    n0, n1 = diff["count"]
    assert diff["clouds"] < 1e-4 and diff["pose"] < 1e-5 and abs(n1 - n0) <= 0.002 * n0, diff


def test_repeats_is_bit_for_bit_equality():
    """`repeats` (a sparse grid first, then every pixel) against the definition: equal arrays."""
    depth = np.random.default_rng(0).random((48, 64)).astype(np.float32)
    assert not repeats(depth, None)
    assert repeats(depth, depth.copy())
    for at in ((0, 0), (1, 1), (47, 63), (16, 17)):  # on the sparse grid, and between its rows and columns
        other = depth.copy()
        other[at] = np.nextafter(other[at], np.float32(2))
        assert not repeats(other, depth) and not np.array_equal(other, depth)
    assert not repeats(depth[:, :32], depth)

def test_depth_in_sensor_units_or_of_another_size_is_refused(scene):
    """The library takes depth as float metres of the intrinsics' size: uint16 millimetres would be
    taken for metres, another size failed deep inside the compiled step."""
    from sgad_jax.config import SLAMConfig

    ds = scene[0]
    system = SLAM(SLAMConfig(track=CFG), ds.intrinsics, initial_pose=lie.from_matrix(ds.gt_poses[0]), track_only=True)
    s = ds[0]
    for depth, what in [((1000 * s.depth).astype(np.uint16), "uint16"), (s.depth[:-2], "float32")]:
        with pytest.raises(ValueError, match=f"frame 0: depth must be float metres of the intrinsics' size .*got {what}"):
            system.add(dataclasses.replace(s, depth=depth))
    assert system.poses == []


@pytest.mark.slow
@pytest.mark.parametrize("hold", [True, False])
def test_repeated_depth_image(scene, hold):
    """A frame whose depth image repeats the previous one (7-Scenes' repeated captures) keeps that
    frame's pose when ``hold_repeated_depth`` is on, and the frames after it are tracked as before."""
    from sgad_jax.config import SLAMConfig

    ds = scene[0]
    cfg = SLAMConfig(track=dataclasses.replace(CFG, hold_repeated_depth=hold))
    system = SLAM(cfg, ds.intrinsics, initial_pose=lie.from_matrix(ds.gt_poses[0]), track_only=True)
    s1, s2 = ds[1], ds[2]
    t = (s1.timestamp + s2.timestamp) / 2  # a repeated capture between frames 1 and 2
    repeat = dataclasses.replace(s1, index=2, timestamp=t, depth_timestamp=t, depth=s1.depth.copy())
    poses = [system.add(s) for s in (ds[0], s1, repeat, dataclasses.replace(s2, index=3))]
    assert system.repeated == (1 if hold else 0)
    assert len(system.times) == (3 if hold else 4)
    assert np.array_equal(poses[1], poses[2]) == hold
    for k, gt_index in ((1, 1), (3, 2)):
        E = np.linalg.inv(ds.gt_poses[gt_index]) @ poses[k]
        assert np.linalg.norm(E[:3, 3]) < 1e-3
    assert system.finish()["repeated_depth_frames"] == system.repeated


@pytest.mark.slow
def test_staged_depth_tracks_as_the_host_array(scene):
    """A depth the reader staged on the device (`Dataset.frames`' ``stage``) gives the host array's
    poses to the bit, and the system releases the staged copy once the frame is added."""
    from sgad_jax.config import SLAMConfig

    ds = scene[0]
    runs = []
    for stage in (False, True):
        system = SLAM(SLAMConfig(track=CFG), ds.intrinsics, initial_pose=lie.from_matrix(ds.gt_poses[0]), track_only=True)
        samples = [ds[i] for i in range(3)]
        for s in samples:
            s.depth_device = jax.device_put(s.depth) if stage else None
        runs.append(np.stack([system.add(s) for s in samples]))
        assert all(s.depth_device is None for s in samples)
    np.testing.assert_array_equal(*runs)


@pytest.mark.slow
def test_run_state_scans_over_a_sequence_like_the_host_loop():
    """The run state is one pytree and the step is pure: `lax.scan` of tracking and queueing each
    frame for mapping (`slam.track_step`, `slam.remember`) over a synthetic sequence gives the host
    loop's poses and leaves the same recent frames (`sgad_jax.system.SLAM`, mapping included)."""
    cfg = resolve_config(None, None, overrides=["data.synthetic.width=80", "data.synthetic.height=60", "data.synthetic.frames=6", "map.iterations=3"])
    ds = SyntheticDataset(cfg.data)
    system = SLAM(cfg, ds.intrinsics, initial_pose=initial_pose(ds))
    host_poses = np.stack([system.add(ds[i]) for i in range(len(ds))])
    frames = jax.tree.map(lambda *x: jnp.stack(x), *[make_frame(ds[i].rgb, ds[i].depth, ds[i].depth_filled) for i in range(len(ds))])
    dts = jnp.asarray(np.diff(ds.timestamps, prepend=ds.timestamps[0]), jnp.float32)
    state = slam.RunState(slam.init_state(cfg.track, lie.from_matrix(ds.gt_poses[0])), slam.empty_recent(3, 60, 80))

    def step(state, xs):
        frame, dt, index = xs
        track, T, _, _ = slam.track_step(cfg.track, state.track, frame.depth, ds.intrinsics, dt, differentiable=False)
        return slam.RunState(track, slam.remember(state.recent, frame, T, index)), T.as_matrix()

    final, poses = jax.jit(lambda s, xs: jax.lax.scan(step, s, xs))(state, (frames, dts, jnp.arange(len(ds))))
    np.testing.assert_allclose(np.asarray(poses), host_poses, atol=1e-5)
    np.testing.assert_array_equal(np.asarray(final.recent.index), np.asarray(system.state.recent.index))
    np.testing.assert_allclose(np.asarray(final.recent.pose.as_matrix()), np.asarray(system.state.recent.pose.as_matrix()), atol=1e-5)
    np.testing.assert_array_equal(np.asarray(final.recent.frame.rgb), np.asarray(system.state.recent.frame.rgb))


# --- depth outliers (track.median_gate) -------------------------------------------------------


def _corner_depth(T_wc: np.ndarray, h: int = 240, w: int = 320, f: float = 300.0) -> np.ndarray:
    """Depth of a room corner (walls x = 0.6 and x = -0.7, floor y = 0.5, back wall z = 1.5) seen
    from camera-to-world pose ``T_wc``, ray-cast analytically."""
    planes = [((1.0, 0, 0), 0.6), ((-1.0, 0, 0), 0.7), ((0, 1.0, 0), 0.5), ((0, 0, 1.0), 1.5)]
    v, u = np.mgrid[0:h, 0:w]
    rays = np.tensordot(T_wc[:3, :3], np.stack([(u - (w - 1) / 2) / f, (v - (h - 1) / 2) / f, np.ones((h, w))]), 1)
    z = np.full((h, w), np.inf)
    for n, c in planes:
        n = np.asarray(n)
        den = np.tensordot(n, rays, 1)
        z = np.minimum(z, np.where(den > 1e-9, (c - n @ T_wc[:3, 3]) / np.where(den > 1e-9, den, 1.0), np.inf))
    return z.astype(np.float32)


def test_median_gate_matches_numpy_and_passes_steep_planes():
    """The gate's median of the valid 3x3 depths equals numpy's nanmedian; a plane seen almost
    edge-on (neighbouring depths 10% apart) passes whole, since its 3x3 median is the centre."""
    rng = np.random.default_rng(0)
    d = rng.uniform(1.0, 2.0, (30, 40)).astype(np.float32)
    d[rng.random(d.shape) < 0.2] = 0.0
    s, off = 5, 2
    got, med = gicp._median_consistent(jnp.asarray(d), jnp.asarray(d[off::s, off::s]), s, off, 0.1)
    pad = np.pad(d, 1).astype(np.float64)
    near = np.stack([pad[off + i :: s, off + j :: s][:6, :8] for i in range(3) for j in range(3)])
    centre = d[off::s, off::s]
    want_med = np.nanmedian(np.where(near > 0, near, np.nan), axis=0)
    np.testing.assert_array_equal(np.asarray(got), np.abs(centre - want_med) <= 0.1 * centre)
    np.testing.assert_allclose(np.asarray(med), want_med, rtol=1e-6)
    steep = (1.0 + 0.1 * np.arange(40))[None, :].repeat(30, 0).astype(np.float32)  # 10% per pixel along u
    ok, med = gicp._median_consistent(jnp.asarray(steep), jnp.asarray(steep[off::s, off::s]), s, off, 0.01)
    assert np.asarray(ok)[:, :-1].all()
    np.testing.assert_allclose(np.asarray(med)[1:-1, :-1], steep[off::s, off::s][1:-1, :-1], rtol=1e-6)


def test_median_gate_drops_depth_outliers_and_keeps_normals_on_a_plane():
    """40% of a tilted plane's pixels moved by N(0, 2 cm): with the 3x3 median gate the surviving
    points stay near the plane and their normals near its normal; without it they do not. Placed
    at the median depth (the default) they are closer still than at their own pixel's depth."""
    from sgad_jax.io.base import add_depth_noise
    from sgad_jax.types import make_intrinsics

    h, w, f = 240, 320, 300.0
    intr = make_intrinsics(f, f, (w - 1) / 2, (h - 1) / 2, w, h)
    n = np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0])  # plane through (0, 0, 1)
    v, u = np.mgrid[0:h, 0:w]
    rays = np.stack([(u - (w - 1) / 2) / f, (v - (h - 1) / 2) / f, np.ones((h, w))])
    depth = add_depth_noise((n[2] / np.tensordot(n, rays, 1)).astype(np.float32), 0.4, 0.02, seed=0, key=0)
    stats = {}
    for gate, at_median in ((0.0, False), (0.01, False), (0.01, True)):
        cloud = gicp.frame_points(TrackConfig(stride=5, k=23, median_gate=gate, median_depth=at_median), jnp.asarray(depth), intr)
        ok = np.asarray(cloud.valid)
        angle = np.degrees(np.arccos(np.clip(np.abs(n @ np.asarray(cloud.normals)[:, ok]), 0.0, 1.0)))
        off_plane = n @ np.asarray(cloud.points)[:, ok] - n[2]
        stats[gate, at_median] = np.median(angle), np.sqrt(np.mean(off_plane**2)), ok.mean()
    assert stats[0.01, False][0] < 2.5 and stats[0.01, False][1] < 0.004 and stats[0.01, False][2] > 0.6  # degrees, metres, share kept
    assert stats[0.0, False][0] > 5.0 and stats[0.0, False][1] > 0.01
    assert stats[0.01, True][1] < 0.6 * stats[0.01, False][1] and stats[0.01, True][0] < stats[0.01, False][0]
    assert stats[0.01, True][2] == stats[0.01, False][2]  # the same points kept


@pytest.mark.slow
def test_median_gate_tracks_noisy_depth_closer_to_the_true_pose():
    """A frame of a room corner tracked against T built from another, both with 40% of their depth
    pixels moved by N(0, 2 cm): dropping the outliers (the default) recovers the known motion to
    about a millimetre, several times closer than with them kept; on clean depth it changes nothing."""
    from scipy.spatial.transform import Rotation

    from sgad_jax.io.base import add_depth_noise
    from sgad_jax.types import make_intrinsics

    intr = make_intrinsics(300.0, 300.0, 159.5, 119.5, 320, 240)
    M1 = np.eye(4)
    M1[:3, :3] = Rotation.from_rotvec([0.004, -0.006, 0.003]).as_matrix()
    M1[:3, 3] = [0.012, -0.008, 0.01]
    D0, D1 = _corner_depth(np.eye(4)), _corner_depth(M1)
    err = {}
    for gate in (0.0, 0.01):
        cfg = TrackConfig(median_gate=gate, coarse=(), capacity=1 << 15)
        step = jax.jit(lambda st, d, cfg=cfg: slam.track_step(cfg, st, d, intr, jnp.float32(0.0), differentiable=False)[:2])
        for seed in range(3):
            st, _ = step(slam.init_state(cfg), jnp.asarray(add_depth_noise(D0, 0.4, 0.02, seed, 0)))
            _, T = step(st, jnp.asarray(add_depth_noise(D1, 0.4, 0.02, seed, 1)))
            err[gate, seed] = _errors(T, M1)[0]
        st, _ = step(slam.init_state(cfg), jnp.asarray(D0))
        err[gate, "clean"] = _errors(step(st, jnp.asarray(D1))[1], M1)[0]
    gated, plain = [np.mean([err[g, s] for s in range(3)]) for g in (0.01, 0.0)]
    assert gated < 1.2e-3 and plain > 3 * gated, (gated, plain)
    assert all(err[0.01, s] < err[0.0, s] for s in range(3))
    assert abs(err[0.01, "clean"] - err[0.0, "clean"]) < 2e-4 and err[0.01, "clean"] < 1e-3


def test_downscaled_frames_are_tracked_with_as_many_points():
    """track.stride counts full-resolution pixels: a frame read at data.downscale=2 keeps about as
    many tracked points as at full resolution (at the raw stride it kept a quarter, and 7-Scenes'
    400 frames at 320x240 tracked to 4.4 cm against 2.5 cm at 640x480)."""
    counts = {}
    for d in (1, 2):
        cfg = resolve_config(None, None, overrides=[f"data.downscale={d}", "data.synthetic.frames=1"])
        ds = SyntheticDataset(cfg.data)
        counts[d] = int(gicp.frame_points(cfg.tracking(), jnp.asarray(ds[0].depth), ds.intrinsics).valid.sum())
    assert counts[1] > 1000
    assert 0.8 < counts[2] / counts[1] < 2.0, counts
