"""Trajectory files in the TUM RGB-D format: ``timestamp tx ty tz qx qy qz qw`` per line.

Poses are camera-to-world; the quaternion is Hamilton ``(x, y, z, w)``, unit, with ``w >= 0``.
"""

from __future__ import annotations

import pathlib

import numpy as np

from sgad_jax.io.files import write_text

HEADER = "# timestamp tx ty tz qx qy qz qw"


def matrix_to_quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(x, y, z, w)`` (..., 4) with ``w >= 0`` of rotation matrices (..., 3, 3).

    Branch-by-trace (Shepperd) method: of ``4 x^2, 4 y^2, 4 z^2, 4 w^2`` (from the trace and the
    diagonal) the largest picks the component to divide by, so the square root is taken of a number
    of at least 1 and the result is accurate for every rotation, 180 degrees included.
    """
    R = np.asarray(R, np.float64)
    m = R.reshape(-1, 3, 3)
    r = lambda i, j: m[:, i, j]  # noqa: E731
    trace = r(0, 0) + r(1, 1) + r(2, 2)
    xx, yy, zz, ww = 1 + 2 * r(0, 0) - trace, 1 + 2 * r(1, 1) - trace, 1 + 2 * r(2, 2) - trace, 1 + trace
    xy, xz, yz = r(0, 1) + r(1, 0), r(0, 2) + r(2, 0), r(1, 2) + r(2, 1)
    xw, yw, zw = r(2, 1) - r(1, 2), r(0, 2) - r(2, 0), r(1, 0) - r(0, 1)
    outer = np.stack([[xx, xy, xz, xw], [xy, yy, yz, yw], [xz, yz, zz, zw], [xw, yw, zw, ww]])  # 4 q q^T
    outer = np.moveaxis(outer, -1, 0)  # (n, 4, 4)
    k = np.stack([xx, yy, zz, ww], -1).argmax(-1)
    row = outer[np.arange(len(m)), k]  # 4 q_k q
    q = row / (2.0 * np.sqrt(row[np.arange(len(m)), k]))[:, None]
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    q *= np.where(q[:, 3:] < 0, -1.0, 1.0)
    return q.reshape(R.shape[:-2] + (4,))


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of quaternions ``(x, y, z, w)`` (..., 4), normalised first; a
    zero quaternion gives NaN, an unknown pose, which the loaders report as such."""
    q = np.asarray(q, np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        x, y, z, w = np.moveaxis(q / np.linalg.norm(q, axis=-1, keepdims=True), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def write_tum_trajectory(path, timestamps: np.ndarray, poses: np.ndarray) -> None:
    """Write camera-to-world poses as a TUM trajectory file, atomically (temporary file, then rename).

    Timestamps get 6 decimals, positions and quaternions 9 significant digits. Non-finite poses
    are written as ``nan`` values.

    Args:
        path: output file; missing parent folders are created.
        timestamps: (n,) seconds.
        poses: (n, 4, 4) camera-to-world matrices.

    Raises:
        ValueError: if the shapes do not match.
    """
    path = pathlib.Path(path)
    ts, T = np.asarray(timestamps, np.float64).reshape(-1), np.asarray(poses, np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or len(T) != len(ts):
        raise ValueError(f"{path}: need (n,) timestamps and (n, 4, 4) poses, got {ts.shape} and {T.shape}")
    with np.errstate(invalid="ignore"):
        q = matrix_to_quaternion(T[:, :3, :3])
    lines = [HEADER] + [
        f"{t:.6f} " + " ".join(f"{v:.9g}" for v in (*p, *r)) for t, p, r in zip(ts, T[:, :3, 3], q)
    ]
    write_text(path, "\n".join(lines) + "\n")


def read_tum_trajectory(path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory file (blank lines and lines starting with '#' are skipped).

    Args:
        path: the file; values may be separated by spaces, tabs or commas.

    Returns:
        timestamps (n,) float64 and camera-to-world poses (n, 4, 4) float64.

    Raises:
        FileNotFoundError: if the file does not exist.
        ValueError: naming the file and line, if a line does not hold 8 numbers.
    """
    path = pathlib.Path(path)
    rows = []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        try:
            values = [float(v) for v in line.replace(",", " ").split()]
        except ValueError:
            values = []
        if len(values) != 8:
            raise ValueError(f"{path}:{number}: expected 8 numbers 'timestamp tx ty tz qx qy qz qw', got {line!r}")
        rows.append(values)
    data = np.array(rows, np.float64).reshape(-1, 8)
    poses = np.tile(np.eye(4), (len(data), 1, 1))
    poses[:, :3, :3] = quaternion_to_matrix(data[:, 4:8]) if len(data) else np.zeros((0, 3, 3))
    poses[:, :3, 3] = data[:, 1:4]
    return data[:, 0].copy(), poses
