"""A custom loop: feed your own RGB-D frames, without ground truth, to the streaming SLAM object.

:class:`sgad_jax.system.SLAM` takes frames one at a time (``add`` returns the frame's
camera-to-world pose at once; mapping follows in batches), ``finish`` maps what is queued and
returns the metrics, ``trajectory`` the poses at the frames' timestamps. A frame is anything with
``rgb`` (h, w, 3) uint8, ``depth`` (h, w) float32 metres (0 where missing), ``depth_filled`` (depth
with holes filled, used by mapping; here the depth itself), ``timestamp`` and ``depth_timestamp``
(seconds). Here the frames are images of the built-in synthetic room standing in for a camera's;
its ground truth is used only at the end, to show how far the estimate is from it.

Run: ``python examples/custom_frames.py [--frames 8 --width 160 --height 120]``.
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from sgad_jax import load_preset, open_dataset
from sgad_jax.config import DataConfig, SyntheticConfig
from sgad_jax.eval.ate import ate
from sgad_jax.io.export import write_tum_trajectory
from sgad_jax.system import SLAM
from sgad_jax.types import make_intrinsics


@dataclasses.dataclass
class MyFrame:
    rgb: np.ndarray  # (h, w, 3) uint8
    depth: np.ndarray  # (h, w) float32 metres, 0 = missing
    timestamp: float
    depth_timestamp: float

    @property
    def depth_filled(self) -> np.ndarray:
        return self.depth


def my_camera(n: int, width: int, height: int):
    """Frames and intrinsics from "a camera" (here the synthetic room) and, for the check at the
    end only, its true poses."""
    ds = open_dataset(DataConfig(layout="synthetic", synthetic=SyntheticConfig(frames=n, width=width, height=height)))
    fx, fy, cx, cy = ds.intrinsics.as_tuple()
    frames = [MyFrame(s.rgb, s.depth, timestamp=i / 30.0, depth_timestamp=i / 30.0) for i, s in enumerate(ds)]
    return frames, (fx, fy, cx, cy), ds.gt_poses


def main(frames: int = 8, width: int = 160, height: int = 120, iterations: int = 10, trajectory_file=None, verbose: bool = True) -> dict:
    """Returns ``{"poses", "trajectory", "metrics", "ate_rmse_cm"}``."""
    images, (fx, fy, cx, cy), truth = my_camera(frames, width, height)
    intr = make_intrinsics(fx, fy, cx, cy, width, height)
    cfg = load_preset("demo")
    cfg = dataclasses.replace(cfg, map=dataclasses.replace(cfg.map, iterations=iterations))
    # No ground truth: the first camera is the world frame (initial_pose defaults to identity).
    slam = SLAM(cfg, intr)
    poses = [slam.add(f) for f in images]
    metrics = slam.finish()
    traj = slam.trajectory()
    if trajectory_file:
        write_tum_trajectory(trajectory_file, np.array([f.timestamp for f in images]), traj)
    # Only for this demonstration: the estimate against the room's true poses, re-based to the
    # first camera as the estimate is, then ATE-aligned.
    rebased = np.linalg.inv(truth[0]) @ truth
    err = ate(traj, rebased)["rmse_m"] * 100 if frames >= 3 else None
    if verbose:
        print(f"tracked and mapped {len(traj)} frames; mean PSNR of the renders {metrics['psnr']:.2f} dB")
        print(f"last pose (camera-to-world, first camera = world):\n{np.array2string(traj[-1], precision=4, suppress_small=True)}")
        if err is not None:
            print(f"ATE RMSE against the true poses: {err:.3f} cm")
    return {"poses": np.stack(poses), "trajectory": traj, "metrics": metrics, "ate_rmse_cm": err}


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=8)
    p.add_argument("--width", type=int, default=160)
    p.add_argument("--height", type=int, default=120)
    p.add_argument("--trajectory", default=None, help="write the estimate to this TUM file")
    a = p.parse_args()
    main(a.frames, a.width, a.height, trajectory_file=a.trajectory)
