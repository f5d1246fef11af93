"""Absolute trajectory error (ATE): translational RMSE after a closed-form rigid alignment."""

from __future__ import annotations

import numpy as np


def align_umeyama(est: np.ndarray, gt: np.ndarray, with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares similarity (or rigid) transform mapping ``est`` onto ``gt`` (Umeyama 1991).

    Minimises ``sum_i |gt_i - (s R est_i + t)|^2`` in closed form from the SVD of the
    cross-covariance; a reflection is never returned (``det R = +1``).

    Args:
        est: (n, 3) points to move.
        gt: (n, 3) target points, paired with ``est``.
        with_scale: also estimate the scale ``s``; otherwise ``s = 1``.

    Returns:
        R (3, 3), t (3,) and s (float), all float64.

    Raises:
        ValueError: if the shapes differ or are not (n, 3) with n >= 3.
    """
    x, y = np.asarray(est, np.float64), np.asarray(gt, np.float64)
    if x.shape != y.shape or x.ndim != 2 or x.shape[1] != 3 or len(x) < 3:
        raise ValueError(f"align_umeyama needs two (n, 3) arrays with n >= 3, got {x.shape} and {y.shape}")
    mx, my = x.mean(0), y.mean(0)
    xc, yc = x - mx, y - my
    U, D, Vt = np.linalg.svd(yc.T @ xc / len(x))
    S = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2] = -1.0
    R = (U * S) @ Vt
    s = float((D * S).sum() / (xc * xc).sum(1).mean()) if with_scale else 1.0
    return R, my - s * R @ mx, s


def ate(est_poses: np.ndarray, gt_poses: np.ndarray) -> dict:
    """ATE of camera-to-world poses after SE(3) alignment of the estimated positions to ground truth.

    Pairs where either pose has a non-finite entry (e.g. frames without ground truth) are ignored.

    Args:
        est_poses: (n, 4, 4) estimated camera-to-world poses.
        gt_poses: (n, 4, 4) ground-truth camera-to-world poses, paired by index.

    Returns:
        dict with ``rmse_m``, ``mean_m``, ``median_m``, ``max_m`` (floats, metres) and ``pairs``
        (number of pairs used).

    Raises:
        ValueError: if the shapes differ or fewer than 3 valid pairs remain.
    """
    est, gt = np.asarray(est_poses, np.float64), np.asarray(gt_poses, np.float64)
    if est.shape != gt.shape or est.ndim != 3 or est.shape[1:] != (4, 4):
        raise ValueError(f"ate needs two (n, 4, 4) pose arrays of equal length, got {est.shape} and {gt.shape}")
    valid = np.isfinite(est).all(axis=(1, 2)) & np.isfinite(gt).all(axis=(1, 2))
    n = int(valid.sum())
    if n < 3:
        raise ValueError(f"ate needs at least 3 pose pairs with finite estimate and ground truth, got {n} of {len(est)}")
    p, q = est[valid, :3, 3], gt[valid, :3, 3]
    R, t, _ = align_umeyama(p, q)
    err = np.linalg.norm(p @ R.T + t - q, axis=1)
    return dict(
        rmse_m=float(np.sqrt(np.mean(err**2))),
        mean_m=float(err.mean()),
        median_m=float(np.median(err)),
        max_m=float(err.max()),
        pairs=n,
    )


def _on_so3(T: np.ndarray) -> np.ndarray:
    """The poses with their rotations projected onto SO(3) (SVD): 7-Scenes' ground-truth rotations
    are off by up to 1e-4, float32 ones by 1e-7; either is read as a rotation of its own."""
    T = T.copy()
    ok = np.isfinite(T).all(axis=(1, 2))
    U, _, Vt = np.linalg.svd(T[ok, :3, :3])
    D = np.ones((len(U), 3))
    D[:, 2] = np.sign(np.linalg.det(U @ Vt))
    T[ok, :3, :3] = (U * D[:, None, :]) @ Vt
    return T


def rpe(est_poses: np.ndarray, gt_poses: np.ndarray) -> dict:
    """Relative pose error between consecutive frames (TUM's RPE with a step of one frame).

    For each pair (i, i + 1) the error is ``(G_i^-1 G_{i+1})^-1 (E_i^-1 E_{i+1})``: the estimated
    motion against the true one, independent of any alignment (frame-to-frame drift). Pairs with a
    non-finite pose among their four are ignored.

    Returns:
        dict with ``trans_rmse_m``, ``trans_mean_m`` (metres), ``rot_rmse_deg`` and ``pairs``.

    Raises:
        ValueError: if the shapes differ or no valid pair remains.
    """
    est, gt = np.asarray(est_poses, np.float64), np.asarray(gt_poses, np.float64)
    if est.shape != gt.shape or est.ndim != 3 or est.shape[1:] != (4, 4):
        raise ValueError(f"rpe needs two (n, 4, 4) pose arrays of equal length, got {est.shape} and {gt.shape}")
    ok = np.isfinite(est).all(axis=(1, 2)) & np.isfinite(gt).all(axis=(1, 2))
    ok = ok[:-1] & ok[1:]
    if not ok.any():
        raise ValueError(f"rpe needs two consecutive frames with finite estimate and ground truth, got none of {len(est)}")
    est, gt = _on_so3(est), _on_so3(gt)
    step = lambda T: np.linalg.inv(T[:-1][ok]) @ T[1:][ok]  # noqa: E731
    err = np.linalg.inv(step(gt)) @ step(est)
    trans = np.linalg.norm(err[:, :3, 3], axis=1)
    # the angle from sine and cosine: arccos alone turns a float32 pose's 1e-7 rounding into 0.02 degrees
    R = err[:, :3, :3]
    sin = 0.5 * np.linalg.norm(np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], -1), axis=-1)
    rot = np.degrees(np.arctan2(sin, (np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0))
    return dict(
        trans_rmse_m=float(np.sqrt(np.mean(trans**2))),
        trans_mean_m=float(trans.mean()),
        rot_rmse_deg=float(np.sqrt(np.mean(rot**2))),
        pairs=int(ok.sum()),
    )
