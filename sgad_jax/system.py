"""Streaming SGAD-SLAM on the host: :class:`SLAM` tracks each frame as it arrives (the jitted
``slam.track_step``), carries the run's state as one pytree, and hands tracked frames to the
:class:`~sgad_jax.mapper.Mapper`. :func:`sgad_jax.pipeline.run` drives it over a dataset."""

from __future__ import annotations

import dataclasses
import os
import pathlib
import time

import jax
import numpy as np

from sgad_jax import checkpoint, lie, paging, programs, slam
from sgad_jax.config import ConfigError, SLAMConfig
from sgad_jax.io.base import Dataset, DatasetError
from sgad_jax.mapper import Mapper, means
from sgad_jax.types import FAIL_DEGENERATE, FAIL_INLIERS, FAIL_JUMP, FAIL_NONFINITE, host_frame


def initial_pose(ds: Dataset) -> lie.SE3:
    """The first frame's ground-truth pose when known (as Gaussian-SLAM does), else identity."""
    T0 = ds.gt_poses[0]
    return lie.from_matrix(T0) if np.isfinite(T0).all() else lie.identity()


#: XLA:CPU vectorises for 256-bit registers by default; the tracking step's many small loops run
#: faster 512 wide, on AVX-512 and AVX2 machines alike, with the same poses up to float32 rounding
#: (docs/method.md). jaxlib 0.10.2 miscompiles atan at that width: a test compares the two compiles.
TRACK_CPU_OPTIONS = {"xla_cpu_prefer_vector_width": 512}


def _host_step(tcfg, state, depth, intr, dt, guess):
    state, T, info, ins = slam.track_step(tcfg, state, depth, intr, dt, guess, differentiable=False)
    return state, T, T.as_matrix(), info, ins


def compile_step(tcfg, state: slam.SLAMState, depth, intr, dt, guess=None):
    """The tracking step compiled once for these shapes: ``step(state, depth, intr, dt, guess)``
    (``guess``: a pose, or None for the constant-velocity prediction, as at compile time) returns
    ``slam.track_step``'s ``(state, T, info, insertion)`` with ``T``'s 4x4 matrix after ``T``
    (made in the program: outside it, a few eager operations a frame).

    No derivatives are taken in the host loop, so the plain solver is used, and the state's buffers
    are donated (the geometry set is updated in place).
    """
    step = jax.jit(_host_step, static_argnums=0, donate_argnums=1)
    args = (state, depth, intr, dt, guess)
    options = TRACK_CPU_OPTIONS if jax.default_backend() == "cpu" else None
    return programs.compiled(("track", tcfg, programs.signature(args)), lambda: step.lower(tcfg, *args), options)


def repeats(depth: np.ndarray, previous: np.ndarray | None) -> bool:
    """Whether a depth image is, bit for bit, the previous frame's (a repeated capture)."""
    if previous is None:
        return False
    # Every 16th pixel first: two captures differ almost everywhere, so that settles nearly every
    # frame, and the full comparison (a pass over both images on the run's main thread) is rare.
    sparse = (slice(None, None, 16),) * 2
    return np.array_equal(depth[sparse], previous[sparse], equal_nan=True) and np.array_equal(depth, previous, equal_nan=True)


def failure_reason(cfg, info) -> str:
    """The judgement of a failed tracking step in words, e.g. ``few inliers (0.12 < 0.30)``."""
    bits, parts = int(info.failure), []
    if bits & FAIL_NONFINITE:
        parts.append("non-finite pose")
    if bits & FAIL_INLIERS and int(info.points) == 0:
        parts.append(f"no point to track (no depth within track.min_depth / max_depth, {cfg.min_depth:g} / {cfg.max_depth:g} m)")
    elif bits & FAIL_INLIERS:
        parts.append(f"few inliers ({int(info.inliers) / max(int(info.points), 1):.2f} < {float(info.inlier_floor):.2f})")
    if bits & FAIL_JUMP:
        t, r = (float(v) for v in np.asarray(info.jump))
        parts.append(f"jump ({t:.3f} m, {np.degrees(r):.1f} deg > {cfg.max_jump[0]:g} m, {cfg.max_jump[1]:g} deg)")
    if bits & FAIL_DEGENERATE:
        parts.append(f"degenerate ({float(info.conditioning):.1e} < {cfg.min_conditioning:.1e})")
    return ", ".join(parts)


class TrackingDiverged(DatasetError):
    """A frame's pose came out non-finite."""


class SLAM:
    """Streaming SGAD-SLAM: feed frames one at a time (a live camera, or :func:`run` over a dataset).

    ``add(sample)`` tracks the frame (an :class:`~sgad_jax.io.base.RGBDSample`, or anything with
    ``rgb`` uint8, ``depth`` metres, ``depth_filled``, ``depth_timestamp``) and returns its
    camera-to-world pose at once; mapping follows in batches of ``map.batch`` frames. ``finish()``
    maps what is queued and returns the metrics (without ATE, which needs ground truth);
    ``judge_scene()`` then scores the held-out views and refines the merged map.

    With ``holdout_every`` N > 0 the frames of run index ``i > 0``, ``i % N == 0`` are held out:
    tracked, but never mapped nor anyone's neighbour. ``source(i)`` reads frame ``i`` again (the
    held-out views and the refinement's training views); without it held-out frames are kept in
    memory and the refinement is not available. ``progress``: progress bars on the held-out scoring
    and the refinement.
    """

    def __init__(
        self,
        cfg: SLAMConfig,
        intr,
        *,
        initial_pose: lie.SE3 | None = None,
        out_dir: str | os.PathLike | None = None,
        track_only: bool = False,
        save_renders: bool = False,
        mesh=None,
        holdout_every: int = 0,
        source=None,
        progress: bool = True,
    ):
        if holdout_every < 0:
            raise ConfigError(f"--holdout-every must be >= 0, got {holdout_every}")
        self.cfg, self.intr = cfg, intr
        self.track_cfg = cfg.tracking()
        self._step_intr = jax.device_put(intr)  # once: host scalars would be copied in at every step
        self.holdout_every, self.source = holdout_every, source
        self.holdout: list[int] = []  # run indices of the held-out frames
        self.between: list[int] = []  # frames between keyframes (map.every > 1) not yet rendered and scored
        self._held: dict[int, object] = {}  # their samples, when there is no source to read them again
        self.dropped = {"overflow": 0, "out_of_range": 0}  # points T could not take (InsertInfo)
        self.mapper = None if track_only else Mapper(cfg, intr, None if out_dir is None else pathlib.Path(out_dir), save_renders, mesh, progress=progress)
        # The whole state carried from frame to frame, one pytree (a checkpoint saves it as is).
        self.state = slam.RunState(slam.init_state(self.track_cfg, initial_pose), None if self.mapper is None else self.mapper.empty_recent())
        self.pager = paging.Pager(self.track_cfg, np.asarray(self.state.track.geom.origin))
        render_init = self.mapper is not None and cfg.map.render_init
        self._predict = jax.jit(slam.predict, static_argnums=0) if render_init else None
        self._step = None
        self.poses: list[np.ndarray] = []
        self.stamps: list[float] = []
        self.depth_stamps: list[float] = []
        self.times: list[float] = []
        self.iters: list[int] = []
        self.failures: list[dict] = []  # tracking_failures of the metrics: frame, reason, recovered
        self._last_depth: np.ndarray | None = None
        self.compile_s: float | None = None

    def __len__(self) -> int:
        return len(self.poses)

    @property
    def repeated(self) -> int:
        """Frames that kept the previous frame's pose (their depth image repeated it): every other
        frame was tracked and timed."""
        return len(self.poses) - len(self.times)

    def add(self, sample) -> np.ndarray:
        """Track one frame (and queue it for mapping); returns its 4x4 camera-to-world pose at its
        depth image's stamp (:meth:`trajectory` has the poses at the frames' own timestamps).

        A frame whose depth image is identical to the previous frame's (``track.hold_repeated_depth``)
        is not tracked again: the same measurement gets the same pose, and the motion model goes on
        from it. Tracking it again would start from the constant-velocity guess, and GICP keeps part
        of a guess's offset along directions the geometry constrains weakly (on 7-Scenes about 1 cm
        per repeated frame, where the ground truth does not move).

        A frame whose tracking is judged a failure (``slam.track_step``) is recorded in
        :attr:`failures` and, unless relocalised, gets the guess as its pose.

        Raises:
            ValueError: the depth image is not float metres of the intrinsics' size.
            TrackingDiverged: the pose came out non-finite despite the fallbacks (a bug); the system
                cannot continue.
        """
        index = len(self.poses)
        depth = sample.depth
        if tuple(np.shape(depth)) != (self.intr.height, self.intr.width) or not np.issubdtype(depth.dtype, np.floating):
            # integer sensor units would be taken for metres, another size fails deep in a compiled step
            raise ValueError(f"frame {index}: depth must be float metres of the intrinsics' size ({self.intr.height}, {self.intr.width}); got {depth.dtype} {tuple(np.shape(depth))}")
        frame = None if self.mapper is None else host_frame(sample, fill=self.maps(index))
        if self.track_cfg.hold_repeated_depth and repeats(sample.depth, self._last_depth):
            pose = self.poses[-1]
        else:
            pose = self._track(sample, frame)
        if getattr(sample, "depth_device", None) is not None:
            sample.depth_device = None  # released: a sample kept for scoring keeps its host arrays only
        self._last_depth = sample.depth
        self.poses.append(pose)
        self.stamps.append(float(sample.timestamp))
        self.depth_stamps.append(float(sample.depth_timestamp))
        if self.held_out(index):
            self.holdout.append(index)
            if self.source is None and self.mapper is not None:
                self._held[index] = sample
        elif self.mapper is not None and not self.maps(index):
            self.between.append(index)
            if self.source is None:
                self._held[index] = sample
        elif self.mapper is not None:
            self.state = dataclasses.replace(self.state, recent=self.mapper.push(self.state.recent, index, frame, lie.from_matrix(pose)))
        return pose

    def held_out(self, index: int) -> bool:
        """Whether the frame of run index ``index`` is held out (tracked, never mapped)."""
        return bool(self.holdout_every) and index > 0 and index % self.holdout_every == 0

    def maps(self, index: int) -> bool:
        """Whether the frame of run index ``index`` is mapped: mapping runs, the frame is not held
        out, and it is a keyframe (``map.every``)."""
        return self.mapper is not None and not self.held_out(index) and index % self.cfg.map.every == 0

    def _flush(self) -> None:
        """Map the queued frames."""
        if self.mapper is not None:
            self.state = dataclasses.replace(self.state, recent=self.mapper.flush(self.state.recent))

    def _track(self, sample, frame) -> np.ndarray:
        # The device copy the reader staged (Dataset.frames), else the host array as read (the
        # compiled step copies it in, without jnp.asarray's extra copy).
        depth = sample.depth if getattr(sample, "depth_device", None) is None else sample.depth_device
        dt = np.float32(sample.depth_timestamp - self.depth_stamps[-1] if self.depth_stamps else 0.0)
        guess = None
        if self._predict is not None:
            guess = self.mapper.refine_guess(self.state.recent, frame, self._predict(self.track_cfg, self.state.track, dt))
        if self._step is None:
            t0 = time.perf_counter()
            self._step = compile_step(self.track_cfg, self.state.track, depth, self._step_intr, dt, guess)
            self.compile_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        state, _, pose, info, ins = self._step(self.state.track, depth, self._step_intr, dt, guess)
        pose = np.asarray(pose)
        if not np.isfinite(pose).all():
            raise TrackingDiverged("tracking diverged (non-finite pose)")
        self.times.append(time.perf_counter() - t0)
        self.iters.append(int(info.iterations))
        if int(info.failure):
            self.failures.append({"frame": len(self.poses), "reason": failure_reason(self.track_cfg, info), "recovered": bool(info.recovered)})
        self.dropped["overflow"] += int(ins.overflow)
        self.dropped["out_of_range"] += int(ins.out_of_range)
        if self.pager.due(state.geom, pose[:3, 3]):
            state = dataclasses.replace(state, geom=self.pager.page(state.geom, pose, len(self.poses)))
        self.state = dataclasses.replace(self.state, track=state)
        return pose

    def finish(self) -> dict:
        """Map the queued frames, render and score the frames between keyframes from the scene; the
        run's metrics so far."""
        if self.mapper is not None:
            self._flush()
            if not self.mapper.store.temporary:
                self.mapper.store.flush()
            if self.between:
                self.mapper.score_views(self.between, self.trajectory(), self.source or self._held.__getitem__, kind="")
                self.between = []
        steady = self.times[1:] if len(self.times) > 1 else self.times
        metrics = {
            "track_ms_median": 1000 * float(np.median(steady)) if steady else None,
            "track_iterations_mean": float(np.mean(self.iters)) if self.iters else None,
            "repeated_depth_frames": self.repeated,
            "tracking_failures": list(self.failures),
            "geometry_gaussians": int(self.state.track.geom.count) + self.pager.host_entries,
            "geometry_on_device": int(self.state.track.geom.count),
            "geometry_pages": self.pager.events,
            "geometry_dropped_points": dict(self.dropped),
            "compile_s": self.compile_s,
        }
        if self.mapper is None:
            metrics["mapping"] = "not run (--track-only)"
        else:
            metrics.update(self.mapper.metrics())
        return metrics

    def judge_scene(self, finetune: int = 0, stop=None, out: dict | None = None) -> dict:
        """Score the held-out views rendered from the scene at their estimated poses (``nvs_*``
        means, and ``nvs_per_frame``); with ``finetune`` > 0 refine the merged map first, keeping
        the scores before it as ``nvs_*_before_finetune``; the refinement ends early once ``stop()``
        is true. Call after :meth:`finish`. The results are added to ``out`` (returned) as they
        come, so a caller that passes it keeps the scores taken before an error."""
        out = {} if out is None else out
        if self.mapper is None:
            return out
        if finetune > 0 and self.source is None:
            raise ConfigError("the merged-map refinement reads the training views again: give SLAM a source")
        self._flush()
        source = self.source or self._held.__getitem__
        poses = self.trajectory()
        if self.holdout_every:
            out["nvs_frames"] = len(self.holdout)
        scores = self.mapper.score_views(self.holdout, poses, source)
        if finetune > 0:
            if scores:
                out.update({f"{k}_before_finetune": v for k, v in means(scores, "nvs_").items()})
            out.update(self.mapper.finetune(finetune, poses, source, self.cfg.seed, stop=stop))
            scores = self.mapper.score_views(self.holdout, poses, source)
        if self.holdout_every:
            out.update(means(scores, "nvs_"), nvs_per_frame=scores)
        return out

    def trajectory(self) -> np.ndarray:
        """``(f, 4, 4)`` camera-to-world poses at the frames' timestamps.

        Tracking estimates each frame's pose at its depth image's stamp (what :meth:`add` returns).
        Where the frame's timestamp is another one (TUM: the colour image's, 12-17 ms from the depth
        image's, long enough for 0.5 cm of camera motion on ``fr1/xyz``), the pose at that time
        is interpolated between the tracked poses around it (:func:`sgad_jax.lie.interpolate`).
        """
        if not self.poses:
            return np.zeros((0, 4, 4))
        return lie.interpolate(np.stack(self.poses), np.asarray(self.depth_stamps), np.asarray(self.stamps))

    def checkpoint_state(self) -> tuple[dict, dict]:
        """``(arrays, meta)``: everything needed to continue (queued frames are mapped first)."""
        self._flush()
        arrays = checkpoint.flatten("state", self.state)
        arrays.update(
            poses=np.asarray(self.poses).reshape(-1, 4, 4),
            stamps=np.asarray(self.stamps, np.float64),
            depth_stamps=np.asarray(self.depth_stamps, np.float64),
        )
        if self.pager.host_entries:  # orbax does not save empty arrays
            arrays["geometry_archive"] = self.pager.archive
        meta = {"frames": len(self.poses), "times": self.times, "iters": self.iters, "holdout": self.holdout, "between": self.between, "pages": self.pager.events, "dropped": self.dropped, "tracking_failures": self.failures}
        if self.mapper is not None:
            more, meta["mapper"] = self.mapper.state()
            arrays.update(more)
        return arrays, meta

    def restore(self, arrays: dict, meta: dict) -> None:
        self.state = checkpoint.unflatten("state", arrays, self.state)
        self.poses = list(arrays["poses"])
        self.stamps = [float(t) for t in arrays["stamps"]]
        self.depth_stamps = [float(t) for t in arrays["depth_stamps"]]
        self.times, self.iters, self.holdout = list(meta["times"]), list(meta["iters"]), list(meta["holdout"])
        self.between = list(meta.get("between", []))
        self.pager.archive = np.asarray(arrays.get("geometry_archive", np.zeros((12, 0))), np.float32).reshape(12, -1)
        self.pager.events, self.dropped = list(meta.get("pages", [])), dict(meta.get("dropped", self.dropped))
        self.failures = list(meta.get("tracking_failures", []))
        if self.mapper is not None:
            self.mapper.restore(arrays, meta["mapper"])
