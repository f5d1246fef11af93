"""ATE and RPE (against evo as an oracle), Umeyama alignment, and the TUM trajectory file round trip."""

import copy

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sgad_jax.eval import align_umeyama, ate, rpe
from sgad_jax.io.export import read_tum_trajectory, write_tum_trajectory


def random_rotation(rng):
    q = rng.normal(size=4)
    x, y, z, w = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def random_trajectory(rng, n=50):
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, 3] = np.cumsum(rng.normal(scale=0.05, size=(n, 3)), axis=0)
    for T in poses:
        T[:3, :3] = random_rotation(rng)
    return poses


def se3(R, t):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def test_ate_matches_evo():
    from evo.core import metrics
    from evo.core.trajectory import PoseTrajectory3D

    rng = np.random.default_rng(1)
    gt = random_trajectory(rng, 80)
    est = se3(random_rotation(rng), rng.normal(size=3)) @ gt
    est[:, :3, 3] += rng.normal(scale=0.02, size=(80, 3))
    stamps = np.arange(80) / 30.0
    ref = PoseTrajectory3D(poses_se3=list(gt), timestamps=stamps)
    traj = PoseTrajectory3D(poses_se3=list(est), timestamps=stamps)
    traj = copy.deepcopy(traj)
    traj.align(ref, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, traj))
    ours = ate(est, gt)
    assert ours["pairs"] == 80
    assert ours["rmse_m"] == pytest.approx(ape.get_statistic(metrics.StatisticsType.rmse), rel=1e-9)
    assert ours["mean_m"] == pytest.approx(ape.get_statistic(metrics.StatisticsType.mean), rel=1e-9)
    assert ours["median_m"] == pytest.approx(ape.get_statistic(metrics.StatisticsType.median), rel=1e-9)
    assert ours["max_m"] == pytest.approx(ape.get_statistic(metrics.StatisticsType.max), rel=1e-9)


def test_rpe_matches_evo():
    from evo.core import metrics
    from evo.core.trajectory import PoseTrajectory3D
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(2)
    gt = random_trajectory(rng, 60)
    noise = [se3(Rotation.from_rotvec(rng.normal(scale=0.01, size=3)).as_matrix(), rng.normal(scale=0.01, size=3)) for _ in range(60)]
    est = se3(random_rotation(rng), rng.normal(size=3)) @ gt @ np.stack(noise)
    stamps = np.arange(60) / 30.0
    pair = (PoseTrajectory3D(poses_se3=list(gt), timestamps=stamps), PoseTrajectory3D(poses_se3=list(est), timestamps=stamps))
    ours = rpe(est, gt)
    for relation, value in [
        (metrics.PoseRelation.translation_part, ours["trans_rmse_m"]),
        (metrics.PoseRelation.rotation_angle_deg, ours["rot_rmse_deg"]),
    ]:
        ref = metrics.RPE(relation, delta=1, delta_unit=metrics.Unit.frames, all_pairs=False)
        ref.process_data(pair)
        assert value == pytest.approx(ref.get_statistic(metrics.StatisticsType.rmse), rel=1e-9)
    assert ours["pairs"] == 59


def test_rpe_angle_is_exact_for_small_rotations_in_float32_and_off_so3_ground_truth():
    """Each step's estimate turns 0.001 degrees more than the truth (the analytic answer): poses
    stored in float32 (a run's trajectory) and ground truth whose rotations are 1e-4 off
    orthonormal (7-Scenes' KinectFusion poses) must not change that."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(4)
    n, extra = 30, 1e-3
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    gt, est = [np.eye(4)], [np.eye(4)]
    for a in axes:
        move = Rotation.from_rotvec(np.radians(0.05) * a).as_matrix()
        gt.append(gt[-1] @ se3(move, 0.01 * a))
        est.append(est[-1] @ se3(move @ Rotation.from_rotvec(np.radians(extra) * a).as_matrix(), 0.01 * a))
    gt, est = np.stack(gt), np.stack(est)
    assert rpe(est, gt)["rot_rmse_deg"] == pytest.approx(extra, rel=1e-6)
    assert rpe(est.astype(np.float32), gt)["rot_rmse_deg"] == pytest.approx(extra, rel=0.05)  # arccos gave 0.02
    skewed = gt.copy()
    skewed[:, :3, :3] *= 1 + 1e-4 * rng.normal(size=(n + 1, 3, 3))  # not quite rotations
    assert rpe(est, skewed)["rot_rmse_deg"] == pytest.approx(extra, rel=0.05)


def test_rpe_sees_one_jump_only():
    """A trajectory that is exact up to a rigid motion except for one step: only that pair errs."""
    rng = np.random.default_rng(3)
    gt = random_trajectory(rng, 20)
    jump = se3(np.eye(3), np.array([0.03, 0.0, 0.04]))
    est = gt.copy()
    est[10:] = jump @ est[10:]  # from frame 10 on, the trajectory is shifted by 5 cm
    est = se3(random_rotation(rng), rng.normal(size=3)) @ est
    est[5] = np.nan  # pairs (4, 5) and (5, 6) are skipped
    out = rpe(est, gt)
    assert out["pairs"] == 17
    assert out["trans_mean_m"] == pytest.approx(0.05 / 17, rel=1e-9)
    assert out["rot_rmse_deg"] == pytest.approx(0.0, abs=1e-5)
    with pytest.raises(ValueError, match="consecutive"):
        rpe(np.full((4, 4, 4), np.nan), gt[:4])


def test_known_transform_recovered():
    rng = np.random.default_rng(2)
    gt = random_trajectory(rng)
    R0, t0 = random_rotation(rng), rng.normal(size=3) * 3
    est = se3(R0, t0) @ gt
    R, t, s = align_umeyama(est[:, :3, 3], gt[:, :3, 3])
    np.testing.assert_allclose(R, R0.T, atol=1e-10)
    np.testing.assert_allclose(t, -R0.T @ t0, atol=1e-10)
    assert s == 1.0
    result = ate(est, gt)
    assert result["rmse_m"] < 1e-10 and result["max_m"] < 1e-10


def test_scale_recovered_and_no_reflection():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(30, 3))
    R0 = random_rotation(rng)
    y = 2.5 * x @ R0.T + [1.0, -2.0, 0.5]
    R, t, s = align_umeyama(x, y, with_scale=True)
    assert s == pytest.approx(2.5) and np.allclose(R, R0) and np.allclose(t, [1.0, -2.0, 0.5])
    mirrored = x * [1, 1, -1]  # best orthogonal map would be a reflection: must stay a rotation
    R, _, _ = align_umeyama(x, mirrored)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_non_finite_pairs_ignored():
    rng = np.random.default_rng(4)
    gt = random_trajectory(rng, 20)
    est = se3(random_rotation(rng), [1, 2, 3]) @ gt
    est[:, :3, 3] += rng.normal(scale=0.01, size=(20, 3))
    reference = ate(est[5:], gt[5:])
    gt_nan, est_bad = gt.copy(), est.copy()
    gt_nan[:3] = np.nan
    est_bad[3:5, 0, 3] = np.inf
    result = ate(est_bad, gt_nan)
    assert result["pairs"] == 15
    assert result["rmse_m"] == pytest.approx(reference["rmse_m"], rel=1e-12)
    gt_nan[:18] = np.nan
    with pytest.raises(ValueError, match="at least 3"):
        ate(est, gt_nan)
    with pytest.raises(ValueError):
        ate(est[:5], gt)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(3, 40))
def test_ate_invariant_to_rigid_motion(seed, n):
    rng = np.random.default_rng(seed)
    gt = random_trajectory(rng, n)
    est = gt.copy()
    est[:, :3, 3] += rng.normal(scale=0.05, size=(n, 3))
    G = se3(random_rotation(rng), rng.normal(size=3) * 10)
    a, b = ate(est, gt), ate(G @ est, gt)
    assert b["rmse_m"] == pytest.approx(a["rmse_m"], rel=1e-6, abs=1e-9)
    assert a["rmse_m"] <= np.sqrt(np.mean(np.sum((est - gt)[:, :3, 3] ** 2, 1))) + 1e-12  # alignment never hurts


def quaternion_to_rotation(x, y, z, w):
    """Standard unit-quaternion (Hamilton) to rotation-matrix formula, for checking the writer."""
    return np.array(
        [
            [w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z],
        ]
    )


def test_tum_round_trip(tmp_path):
    rng = np.random.default_rng(5)
    poses = random_trajectory(rng, 40)
    # rotations where the trace is not the largest term (near and at 180 degrees), and identity
    for i, axis in enumerate(np.eye(3)):
        poses[i, :3, :3] = 2 * np.outer(axis, axis) - np.eye(3)
    poses[3, :3, :3] = np.eye(3)
    stamps = 1305031102.175304 + np.arange(40) / 30.0
    path = tmp_path / "sub" / "traj.txt"
    write_tum_trajectory(path, stamps, poses)
    assert [p.name for p in path.parent.iterdir()] == ["traj.txt"]  # no temporary left behind
    lines = [ln for ln in path.read_text().splitlines() if not ln.startswith("#")]
    assert len(lines) == 40 and lines[0].split()[0] == f"{stamps[0]:.6f}"
    ts, back = read_tum_trajectory(path)
    np.testing.assert_allclose(ts, stamps, atol=1e-6, rtol=0)
    np.testing.assert_allclose(back, poses, atol=1e-6)
    for line, T in zip(lines, poses):
        values = np.array(line.split()[1:], float)
        q = values[3:]
        assert abs(np.linalg.norm(q) - 1) < 1e-8 and q[3] >= 0
        np.testing.assert_allclose(values[:3], T[:3, 3], rtol=1e-8, atol=1e-12)
        np.testing.assert_allclose(quaternion_to_rotation(*q), T[:3, :3], atol=1e-7)


def test_tum_quaternion_matches_evo(tmp_path):
    from evo.tools import file_interface

    rng = np.random.default_rng(6)
    poses = random_trajectory(rng, 25)
    path = tmp_path / "traj.txt"
    write_tum_trajectory(path, np.arange(25) / 30.0, poses)
    traj = file_interface.read_tum_trajectory_file(str(path))
    np.testing.assert_allclose(np.array(traj.poses_se3), poses, atol=1e-7)
    ours = np.array([ln.split()[4:] for ln in path.read_text().splitlines() if not ln.startswith("#")], float)
    from evo.core.trajectory import PoseTrajectory3D

    wxyz = PoseTrajectory3D(poses_se3=list(poses), timestamps=np.arange(25.0)).orientations_quat_wxyz
    wxyz *= np.sign(wxyz[:, :1])  # evo does not fix the sign; ours has w >= 0
    np.testing.assert_allclose(ours, wxyz[:, [1, 2, 3, 0]], atol=1e-8)


def test_tum_read_errors(tmp_path):
    path = tmp_path / "bad.txt"
    path.write_text("# header\n\n0.0 1 2 3 0 0 0 1\n0.1 1 2 3 0 0\n")
    with pytest.raises(ValueError, match=r"bad.txt:4"):
        read_tum_trajectory(path)
    path.write_text("# only a comment\n")
    ts, poses = read_tum_trajectory(path)
    assert ts.shape == (0,) and poses.shape == (0, 4, 4)
