"""The tracking, noise and parallel-mapping benchmarks run end to end and print their JSON (the
first and the last had silently broken once); the structured-light simulation follows its error model."""

import json
import pathlib
import subprocess
import sys

import numpy as np
import pytest

from conftest import shared

ROOT = pathlib.Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_bench_track_prints_both_trackers():
    data = shared("tum_fr1_xyz")
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "bench_track.py"), "--data", str(data), "--max-frames", "6", "--rounds", "2"],
        capture_output=True, text=True, timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert out["frames"] == 6 and len(out["rounds_ms"]) == 2
    # both trackers follow the camera over 6 frames of fr1/xyz to within a centimetre
    assert out["ours_ate_cm"] < 1.0 and out["small_gicp_ate_cm"] < 1.0
    # a frame-to-frame error is below the camera's motion (fr1/xyz moves about 1 cm a frame)
    assert 0.0 < out["ours_rpe_cm"] < 1.0 and 0.0 < out["small_gicp_rpe_cm"] < 1.0


def test_structured_light_simulation_against_its_error_model():
    """The simulated sensor's depth error on a flat wall matches its own model worked out by hand:
    disparity noise N(0, 0.062 px) plus the 1/8-px rounding (variance step^2 / 12), carried to depth
    by dz = z^2 / (f b) dd; a nearer box hides the 4 px of wall right of it from the projector (on
    the camera's left), and about 0.5% of the rest drops out."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import sim_structured_light as sim

    rng = np.random.default_rng(0)
    z = np.full((400, 600), 2.0)
    out = sim.simulate(z, rng)
    seen = out > 0
    sigma_d = np.hypot(sim.DISPARITY_SIGMA_PX, sim.DISPARITY_STEP_PX / np.sqrt(12))
    expected = 2.0**2 / (sim.F_PX * sim.BASELINE_M) * sigma_d
    rms = np.sqrt(np.mean((out[seen] - 2.0) ** 2))
    assert abs(rms / expected - 1) < 0.1, (rms, expected)
    assert 0.003 < 1 - seen.mean() < 0.007
    box = z.copy()
    box[100:300, 200:400] = 1.0  # a nearer box: its right edge has the wall behind it
    seen = sim.simulate(box, np.random.default_rng(1)) > 0
    right_of_box = ~seen[100:300, 400:410]
    assert right_of_box[:, :4].mean() > 0.95 and right_of_box[:, 4:].mean() < 0.02
    assert (~seen[100:300, 190:200]).mean() < 0.02  # left of it: nothing hidden
    # Correlated noise (a sensor matching windows of pixels): the same per-pixel error, now shared
    # with the neighbours (white noise blurred by sigma 2 px: a neighbour correlation of exp(-1/16)
    # before the rounding, which lowers it).
    out = sim.simulate(z, np.random.default_rng(2), correlation_px=2.0)
    err = np.where(out > 0, out - 2.0, np.nan)
    assert abs(np.sqrt(np.nanmean(err**2)) / expected - 1) < 0.1
    a, b = err[:, :-1].ravel(), err[:, 1:].ravel()
    both = np.isfinite(a) & np.isfinite(b)
    assert np.corrcoef(a[both], b[both])[0, 1] > 0.6


def test_structured_light_simulation_lens_distortion():
    """``distort`` on a tilted plane: each pixel holds the plane's depth along the ray through its
    undistorted position, worked out by hand (plane z = 2 + 0.5 X: z = 2 / (1 - 0.5 x_u)), with
    x_d = x_u (1 + k1 r_u^2) inverted by bisection here, not by the script's fixed-point loop."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import sim_structured_light as sim

    f, cx, cy, k1 = 300.0, 199.5, 149.5, -0.05
    u, v = np.meshgrid(np.arange(400.0), np.arange(300.0))
    plane = 2.0 / (1.0 - 0.5 * (u - cx) / f)  # the pinhole camera's image of the plane
    out = sim.distort(plane, f, f, cx, cy, k1)
    xd, yd = (u - cx) / f, (v - cy) / f
    lo, hi = np.zeros_like(xd), np.ones_like(xd) * 2.0  # the undistorted radius over the distorted one
    for _ in range(60):
        mid = (lo + hi) / 2
        rd = mid * np.hypot(xd, yd) * (1 + k1 * (mid * np.hypot(xd, yd)) ** 2)
        below = rd < np.hypot(xd, yd)
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    xu = xd * lo
    expected = 2.0 / (1.0 - 0.5 * xu)
    inside = out > 0
    # nearest-pixel sampling: within the depth change of 0.75 pixel along x (dz/dx_u = z^2 / 4)
    tol = 0.75 * expected**2 / 4 / f + 1e-5
    assert np.all(np.abs(out - expected)[inside] < tol[inside])
    # barrel (k1 < 0): the corners' rays lie outside the pinhole image, so only they are missing
    assert inside[150, 200] and not inside[0, 0] and 0.9 < inside.mean() < 0.99
    assert np.median(np.abs(out - plane)[inside] / tol[inside]) > 1  # it moved away from the pinhole image


def test_structured_light_simulation_scaled_room(tmp_path):
    """``--scale 2``: the trajectory's translations doubled and its rotations kept, exactly; the
    sensor sees a wall twice as far (median depth within the rounding's bias of 2x)."""
    import cv2

    src = tmp_path / "replica"
    (src / "rendered_100" / "results").mkdir(parents=True)
    (src / "cam_params.json").write_text(json.dumps({"camera": {"w": 64, "h": 48, "fx": 60.0, "fy": 60.0, "cx": 31.5, "cy": 23.5, "scale": 6553.5}}))
    cv2.imwrite(str(src / "rendered_100" / "results" / "depth000000.png"), np.full((48, 64), round(1.5 * 6553.5), np.uint16))
    cv2.imwrite(str(src / "rendered_100" / "results" / "frame000000.jpg"), np.zeros((48, 64, 3), np.uint8))
    T = np.eye(4)
    T[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = [0.25, -0.5, 1.0]
    np.savetxt(src / "rendered_100" / "traj.txt", T.reshape(1, 16))
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "sim_structured_light.py"), str(src), str(tmp_path / "big"), "--scale", "2"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    got = np.loadtxt(tmp_path / "big" / "rendered_100" / "traj.txt").reshape(4, 4)
    np.testing.assert_array_equal(got[:3, :3], T[:3, :3])
    np.testing.assert_array_equal(got[:3, 3], [0.5, -1.0, 2.0])
    z = cv2.imread(str(tmp_path / "big" / "rendered_100" / "results" / "depth000000.png"), cv2.IMREAD_UNCHANGED) / 6553.5
    assert abs(np.median(z[z > 0]) / 3.0 - 1) < 0.01


@pytest.mark.slow
def test_bench_noise_counts_tracking_failures():
    """bench_noise reports the frames the tracker judged failed: the synthetic camera's 20 cm /
    10 degree jump is one, and tracking recovers from it (the ATE stays at millimetres)."""
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "bench_noise.py"), "--levels", "0",
         "--set", "data.synthetic.frames=10", "--set", "data.synthetic.jump_frame=5"],
        capture_output=True, text=True, timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert out["frames"] == 10 and out["noise_share"] == 0.0
    assert out["tracking_failures"] == 1
    assert out["ours_ate_cm"] < 0.5


@pytest.mark.slow
def test_bench_parallel_maps_on_one_and_two_devices():
    """bench_parallel drives BatchMapper with the arguments of slam.map_step (it once fell behind
    a change of that signature) and times each device count in a process with that many devices."""
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "bench_parallel.py"), "--data", "", "--devices", "1,2",
         "--frames", "2", "--iterations", "2", "--downscale", "4"],
        capture_output=True, text=True, timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert out["data"] == "synthetic" and out["frames"] == 2
    assert out["fps_1"] > 0 and out["fps_2"] > 0 and "fps_4" not in out
