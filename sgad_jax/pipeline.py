"""The host loop: read frames, run the jitted SLAM step, write results. Never jitted itself.

Outputs in ``out_dir``:
    ``trajectory.txt``  TUM format ``timestamp tx ty tz qx qy qz qw``, camera-to-world, one line per frame.
    ``metrics.json``    frames, ATE (RMSE and mean, Horn SE(3) alignment) when ground truth exists,
                        steady-state tracking time, compile time, peak RSS, the resolved config.
Both are written when the run ends, including when it stops early on bad input (then with
``"stopped": "<the error>"``), so that no computed result is lost.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import pathlib
import resource
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from sgad_jax import lie, slam
from sgad_jax.config import SLAMConfig, to_dict
from sgad_jax.eval.ate import ate
from sgad_jax.io.base import Dataset, DatasetError
from sgad_jax.io.datasets import open_dataset
from sgad_jax.io.export import write_tum_trajectory


@dataclasses.dataclass
class RunResult:
    poses: np.ndarray  # (f, 4, 4) camera-to-world
    timestamps: np.ndarray
    metrics: dict


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def initial_pose(ds: Dataset) -> lie.SE3:
    """The first frame's ground-truth pose when known (as Gaussian-SLAM does), else identity."""
    T0 = ds.gt_poses[0]
    return lie.from_matrix(T0) if np.isfinite(T0).all() else lie.identity()


def compile_step(tcfg, state: slam.SLAMState, depth, intr, dt):
    """The tracking step compiled once for these shapes: ``step(state, depth, intr, dt)``.

    No derivatives are taken in the host loop, so the plain solver is used, and the state's buffers
    are donated (the geometry set is updated in place).
    """
    step = jax.jit(functools.partial(slam.track_step, differentiable=False), static_argnums=0, donate_argnums=1)
    return step.lower(tcfg, state, depth, intr, dt).compile()


def run(cfg: SLAMConfig, out_dir: str | os.PathLike | None = None, *, track_only: bool = True, progress: bool = True) -> RunResult:
    """Run SLAM over ``cfg.data`` and write the outputs to ``out_dir`` (if given).

    Raises:
        DatasetError: on bad input (after writing whatever was computed before it).
    """
    ds = open_dataset(cfg.data)
    intr = ds.intrinsics
    tcfg = cfg.track
    state = slam.init_state(tcfg, initial_pose(ds))

    poses, stamps, times, iters = [], [], [], []
    last_depth_t = None
    compile_s = None
    stopped = None
    bar = tqdm(total=len(ds), desc=f"tracking {ds.name}", unit="frame", disable=not progress, file=sys.stderr)
    try:
        for i in range(len(ds)):
            sample = ds[i]
            depth = jnp.asarray(sample.depth)
            dt = jnp.float32(0.0 if last_depth_t is None else sample.depth_timestamp - last_depth_t)
            last_depth_t = sample.depth_timestamp
            if compile_s is None:
                t0 = time.perf_counter()
                compiled = compile_step(tcfg, state, depth, intr, dt)
                compile_s = time.perf_counter() - t0
            t0 = time.perf_counter()
            state, T, info, _ = compiled(state, depth, intr, dt)
            pose = np.asarray(T.as_matrix())
            times.append(time.perf_counter() - t0)
            if not np.isfinite(pose).all():
                raise DatasetError(f"{ds.name} frame {sample.source_index}: tracking diverged (non-finite pose)")
            poses.append(pose)
            stamps.append(sample.timestamp)
            iters.append(int(info.iterations))
            bar.update(1)
    except DatasetError as err:
        stopped = str(err)
    finally:
        bar.close()

    poses_np = np.stack(poses) if poses else np.zeros((0, 4, 4))
    stamps_np = np.asarray(stamps, np.float64)
    metrics = {"frames": len(poses), "dataset": ds.name, "layout": ds.layout}
    gt = ds.gt_poses[: len(poses)]
    if len(poses) >= 3 and np.isfinite(gt).all(axis=(1, 2)).sum() >= 3:
        err = ate(poses_np, gt)
        metrics.update(ate_rmse_cm=100 * err["rmse_m"], ate_mean_cm=100 * err["mean_m"], ate_pairs=err["pairs"])
    else:
        metrics.update(ate_rmse_cm=None, ate_mean_cm=None)
    steady = times[1:] if len(times) > 1 else times
    metrics.update(
        track_ms_median=1000 * float(np.median(steady)) if steady else None,
        track_iterations_mean=float(np.mean(iters)) if iters else None,
        geometry_gaussians=int(state.geom.count),
        compile_s=compile_s,
        peak_rss_mb=peak_rss_mb(),
        mapping="not run (--track-only)" if track_only else "not implemented yet: tracking only",
        config=to_dict(cfg),
    )
    if stopped:
        metrics["stopped"] = stopped
    if out_dir is not None:
        out = pathlib.Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        write_tum_trajectory(out / "trajectory.txt", stamps_np, poses_np)
        tmp = out / "metrics.json.tmp"
        tmp.write_text(json.dumps(metrics, indent=2))
        os.replace(tmp, out / "metrics.json")
    if stopped:
        raise DatasetError(stopped)
    return RunResult(poses=poses_np, timestamps=stamps_np, metrics=metrics)
