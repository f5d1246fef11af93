"""The host loop: read frames, run the jitted SLAM step, write results. Never jitted itself.

Outputs in ``out_dir``:
    ``trajectory.txt``  TUM format ``timestamp tx ty tz qx qy qz qw``, camera-to-world, one line per frame.
    ``metrics.json``    frames, ATE (RMSE and mean, Horn SE(3) alignment) when ground truth exists,
                        steady-state tracking time, compile time, peak RSS, the resolved config;
                        unless tracking only: the mean PSNR / SSIM / MS-SSIM / LPIPS and rendered
                        depth L1 (cm, valid pixels) of every frame's render along the estimated
                        trajectory, and the mapping time per frame.
    ``renders/``        with ``save_renders``: ``rgb_XXXXXX.png`` and ``depth_XXXXXX.png`` (16-bit,
                        millimetres) of every frame, XXXXXX its 0-based index in the run.
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
import cv2
import numpy as np
from tqdm import tqdm

from sgad_jax import lie, slam
from sgad_jax import map as mapping
from sgad_jax.eval import image
from sgad_jax.config import ConfigError, SLAMConfig, to_dict
from sgad_jax.eval.ate import ate
from sgad_jax.io.base import Dataset, DatasetError
from sgad_jax.io.datasets import open_dataset
from sgad_jax.io.export import write_tum_trajectory
from sgad_jax.types import make_frame


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


def compile_step(tcfg, state: slam.SLAMState, depth, intr, dt, guess=None):
    """The tracking step compiled once for these shapes: ``step(state, depth, intr, dt)``.

    No derivatives are taken in the host loop, so the plain solver is used, and the state's buffers
    are donated (the geometry set is updated in place).
    """
    step = jax.jit(functools.partial(slam.track_step, differentiable=False), static_argnums=0, donate_argnums=1)
    return step.lower(tcfg, state, depth, intr, dt, guess).compile()


class _Mapper:
    """The appearance branch of the host loop: maps each tracked frame against its ``n`` previous
    frames, renders it, scores the render and keeps only what the next frames need."""

    def __init__(self, cfg: SLAMConfig, intr, out: pathlib.Path | None, save_renders: bool):
        self.cfg, self.intr = cfg, intr
        self.n = cfg.map.neighbours
        self.renders = out / "renders" if (save_renders and out is not None) else None
        if self.renders is not None:
            self.renders.mkdir(parents=True, exist_ok=True)
        self.recent: list[tuple] = []  # (frame, pose, gaussians) of the last n frames, newest first
        self.step = None
        self.refine = None
        self.compile_s = 0.0
        self.scores: dict[str, list[float]] = {k: [] for k in ("psnr", "ssim", "ms_ssim", "lpips", "depth_l1_cm")}
        self.seconds: list[float] = []
        if cfg.map.psnr_protocol not in image.PSNR_PROTOCOLS:
            raise ConfigError(f"map.psnr_protocol must be one of {', '.join(image.PSNR_PROTOCOLS)}, got {cfg.map.psnr_protocol!r}")
        self.lpips_missing: str | None = None
        try:
            self.lpips_weights = image.load_lpips_weights()
        except image.LPIPSUnavailable as err:  # a corrupt weight file
            self.lpips_weights, self.lpips_missing = None, str(err)
        if self.lpips_weights is None and self.lpips_missing is None:
            try:
                image.lpips(np.zeros((32, 32, 3)), np.zeros((32, 32, 3)))
            except image.LPIPSUnavailable as err:  # its message says where it looked and what to do
                self.lpips_missing = str(err)
        if self.lpips_missing:
            print(f"warning: LPIPS not computed: {self.lpips_missing}", file=sys.stderr)

    def _neighbours(self, frame, pose):
        """The last ``n`` frames, stacked; missing ones (at the start) padded and marked absent."""
        have = self.recent[: self.n]
        filler = have[0] if have else (frame, pose, mapping.init_gaussians(frame, self.intr))
        rows = have + [filler] * (self.n - len(have))
        stack = lambda *xs: jnp.stack(xs)  # noqa: E731
        frames, poses, gs = (jax.tree.map(stack, *col) for col in zip(*rows))
        return frames, poses, gs, jnp.asarray([True] * len(have) + [False] * (self.n - len(have)))

    def refine_guess(self, frame, guess):
        """Rendering-based initialisation of the pose guess from the previous frame's Gaussians."""
        if not self.recent:
            return guess
        if self.refine is None:
            t0 = time.perf_counter()
            fn = functools.partial(mapping.refine_pose, self.cfg.map, iterations=self.cfg.map.render_init_iterations)
            _, pose_prev, g_prev = self.recent[0]
            self.refine = jax.jit(fn).lower(g_prev, pose_prev, frame, guess, self.intr).compile()
            self.compile_s += time.perf_counter() - t0
        _, pose_prev, g_prev = self.recent[0]
        return self.refine(g_prev, pose_prev, frame, guess, self.intr)

    def __call__(self, index: int, sample, pose_matrix: np.ndarray) -> None:
        frame = make_frame(sample.rgb, sample.depth, sample.depth_filled)
        pose = lie.from_matrix(pose_matrix)
        args = (frame, pose, *self._neighbours(frame, pose), self.intr)
        if self.step is None:
            t0 = time.perf_counter()
            self.step = jax.jit(functools.partial(slam.map_step, self.cfg.map)).lower(*args).compile()
            self.compile_s += time.perf_counter() - t0
        t0 = time.perf_counter()
        g, out, _ = self.step(*args)
        jax.block_until_ready(g)
        self.seconds.append(time.perf_counter() - t0)
        self.recent = [(frame, pose, g)] + self.recent[: self.n - 1]
        self._score(index, frame, out)

    def _score(self, index: int, frame, out) -> None:
        rgb = np.clip(np.asarray(out.rgb), 0.0, 1.0)
        depth = np.asarray(out.depth)
        target, valid = np.asarray(frame.rgb), np.asarray(frame.valid)
        self.scores["psnr"].append(float(image.psnr(rgb, target, valid, protocol=self.cfg.map.psnr_protocol)))
        self.scores["ssim"].append(float(image.ssim(rgb, target)))
        if min(rgb.shape[:2]) >= image.MS_SSIM_MIN_SIZE:
            self.scores["ms_ssim"].append(float(image.ms_ssim(rgb, target)))
        if self.lpips_weights is not None:
            self.scores["lpips"].append(float(image.lpips(rgb, target, self.lpips_weights)))
        if valid.any():
            self.scores["depth_l1_cm"].append(100.0 * float(np.abs(depth - np.asarray(frame.depth))[valid].mean()))
        if self.renders is not None:
            cv2.imwrite(str(self.renders / f"rgb_{index:06d}.png"), cv2.cvtColor((rgb * 255.0 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR))
            mm = np.clip(depth * 1000.0 + 0.5, 0, 65535).astype(np.uint16)
            cv2.imwrite(str(self.renders / f"depth_{index:06d}.png"), mm)

    def metrics(self) -> dict:
        mean = lambda xs: float(np.mean(xs)) if xs else None  # noqa: E731
        out = {k: mean(v) for k, v in self.scores.items()}
        out.update(
            psnr_protocol=self.cfg.map.psnr_protocol,
            mapped_frames=len(self.seconds),
            map_s_per_frame=mean(self.seconds[1:] or self.seconds),
            map_compile_s=self.compile_s,
        )
        if self.lpips_missing:
            out["lpips_missing"] = self.lpips_missing
        return out


def run(
    cfg: SLAMConfig,
    out_dir: str | os.PathLike | None = None,
    *,
    track_only: bool = False,
    save_renders: bool = False,
    progress: bool = True,
) -> RunResult:
    """Run SLAM over ``cfg.data`` and write the outputs to ``out_dir`` (if given).

    Raises:
        DatasetError: on bad input (after writing whatever was computed before it).
    """
    ds = open_dataset(cfg.data)
    intr = ds.intrinsics
    tcfg = cfg.track
    state = slam.init_state(tcfg, initial_pose(ds))
    out = None if out_dir is None else pathlib.Path(out_dir)
    mapper = None if track_only else _Mapper(cfg, intr, out, save_renders)
    render_init = mapper is not None and cfg.map.render_init
    predict = jax.jit(slam.predict, static_argnums=0) if render_init else None

    poses, stamps, times, iters = [], [], [], []
    last_depth_t = None
    compile_s = None
    stopped = None
    what = "tracking" if track_only else "tracking + mapping"
    bar = tqdm(total=len(ds), desc=f"{what} {ds.name}", unit="frame", disable=not progress, file=sys.stderr)
    try:
        for i in range(len(ds)):
            sample = ds[i]
            depth = jnp.asarray(sample.depth)
            dt = jnp.float32(0.0 if last_depth_t is None else sample.depth_timestamp - last_depth_t)
            last_depth_t = sample.depth_timestamp
            guess = None
            if render_init:
                guess = mapper.refine_guess(make_frame(sample.rgb, sample.depth, sample.depth_filled), predict(tcfg, state, dt))
            if compile_s is None:
                t0 = time.perf_counter()
                compiled = compile_step(tcfg, state, depth, intr, dt, guess)
                compile_s = time.perf_counter() - t0
            t0 = time.perf_counter()
            state, T, info, _ = compiled(state, depth, intr, dt, guess)
            pose = np.asarray(T.as_matrix())
            times.append(time.perf_counter() - t0)
            if not np.isfinite(pose).all():
                raise DatasetError(f"{ds.name} frame {sample.source_index}: tracking diverged (non-finite pose)")
            poses.append(pose)
            stamps.append(sample.timestamp)
            iters.append(int(info.iterations))
            if mapper is not None:
                mapper(i, sample, pose)
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
    )
    if mapper is None:
        metrics["mapping"] = "not run (--track-only)"
    else:
        metrics.update(mapper.metrics())
    metrics.update(peak_rss_mb=peak_rss_mb(), config=to_dict(cfg))
    if stopped:
        metrics["stopped"] = stopped
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        write_tum_trajectory(out / "trajectory.txt", stamps_np, poses_np)
        tmp = out / "metrics.json.tmp"
        tmp.write_text(json.dumps(metrics, indent=2))
        os.replace(tmp, out / "metrics.json")
    if stopped:
        raise DatasetError(stopped)
    return RunResult(poses=poses_np, timestamps=stamps_np, metrics=metrics)
