"""The host loop: read frames, run the jitted SLAM step, write results. Never jitted itself.

Outputs in ``out_dir``:
    ``trajectory.txt``  TUM format ``timestamp tx ty tz qx qy qz qw``, camera-to-world, one line per frame,
                        the pose at the frame's timestamp (:meth:`SLAM.trajectory`).
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
import shutil
import sys
import time

import jax
import jax.numpy as jnp
import cv2
import numpy as np
from tqdm import tqdm

import jax.experimental.multihost_utils

from sgad_jax import checkpoint, lie, paging, scene, slam, splat
from sgad_jax import map as mapping
from sgad_jax.distributed import BatchMapper, frames_mesh
from sgad_jax.eval import image
from sgad_jax.config import ConfigError, SLAMConfig, to_dict
from sgad_jax.eval.ate import ate, rpe
from sgad_jax.io.base import BadFrame, Dataset, DatasetError
from sgad_jax.io.datasets import open_dataset
from sgad_jax.io.export import write_tum_trajectory
from sgad_jax.io.files import write_bytes, write_json
from sgad_jax.io.store import GaussianStore
from sgad_jax.types import FAIL_DEGENERATE, FAIL_INLIERS, FAIL_JUMP, FAIL_NONFINITE, Frame, PixelGaussians, make_frame


@dataclasses.dataclass
class RunResult:
    poses: np.ndarray  # (f, 4, 4) camera-to-world
    timestamps: np.ndarray
    metrics: dict
    live: object = None  # the live viewer (sgad_jax.viewer.LiveView) when one was asked for


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


#: ``metrics.json`` records the resident memory every this many frames (``rss_mb_by_frame``).
RSS_EVERY = 50


def current_rss_mb() -> float:
    """Resident memory now (Linux ``/proc``; the peak elsewhere)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except OSError:
        return peak_rss_mb()


def initial_pose(ds: Dataset) -> lie.SE3:
    """The first frame's ground-truth pose when known (as Gaussian-SLAM does), else identity."""
    T0 = ds.gt_poses[0]
    return lie.from_matrix(T0) if np.isfinite(T0).all() else lie.identity()


def compile_step(tcfg, state: slam.SLAMState, depth, intr, dt, guess=None):
    """The tracking step compiled once for these shapes: ``step(state, depth, intr, dt, guess)``
    (``guess``: a pose, or None for the constant-velocity prediction, as at compile time).

    No derivatives are taken in the host loop, so the plain solver is used, and the state's buffers
    are donated (the geometry set is updated in place).
    """
    step = jax.jit(functools.partial(slam.track_step, differentiable=False), static_argnums=0, donate_argnums=1)
    return step.lower(tcfg, state, depth, intr, dt, guess).compile()


def repeats(depth: np.ndarray, previous: np.ndarray | None) -> bool:
    """Whether a depth image is, bit for bit, the previous frame's (a repeated capture)."""
    return previous is not None and np.array_equal(depth, previous, equal_nan=True)


def host_frame(sample) -> Frame:
    """The frame of a sample as host (numpy) arrays."""
    return jax.tree.map(np.asarray, make_frame(sample.rgb, sample.depth, sample.depth_filled))


#: Image scores of a rendered view: the keys of ``per_frame`` records and of the means in ``metrics.json``.
SCORES = ("psnr", "ssim", "ms_ssim", "lpips", "depth_l1_cm")


class _Mapper:
    """The appearance branch of the host loop: collects tracked frames (with their ``n`` previous
    mapped frames as neighbours) into batches of ``map.batch`` frames, maps each batch (spread over
    the devices, one frame each), scores every frame's render and moves its Gaussians off the
    devices into a :class:`GaussianStore`. Afterwards it renders and scores held-out views from the
    scene (:mod:`sgad_jax.scene`) and refines the merged map."""

    def __init__(self, cfg: SLAMConfig, intr, out: pathlib.Path | None, save_renders: bool, mesh=None):
        self.cfg, self.intr = cfg, intr
        self.n = cfg.map.neighbours
        self.main = jax.process_index() == 0
        self.renders = out / "renders" if (save_renders and out is not None and self.main) else None
        if self.renders is not None:
            self.renders.mkdir(parents=True, exist_ok=True)
        self.store = GaussianStore(None if out is None else out / "gaussians", cfg.map.host_budget_mb)
        self.batch = BatchMapper(cfg.map, intr, mesh)
        self.batch_size = cfg.map.batch or self.batch.size
        self.scene = scene.Scene(cfg.scene, intr, self.store.get)  # the mapped frames, for rendering any view
        self.refine = None
        self.compile_s = 0.0
        self.per_frame: list[dict] = []  # scores of every rendered view, in the order scored
        self.seconds: list[float] = []  # per mapped frame: its batch's time over its batch's frames
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
        if self.lpips_missing and self.main:
            print(f"warning: LPIPS not computed: {self.lpips_missing}", file=sys.stderr)

    def empty_recent(self) -> slam.Recent:
        """The run state's recent frames: room for a batch and its frames' neighbours."""
        return slam.empty_recent(self.batch_size + self.n, self.intr.height, self.intr.width)

    def refine_guess(self, recent: slam.Recent, frame: Frame, guess):
        """Rendering-based initialisation of the pose guess from the previous frame's Gaussians as
        initialised from its RGB-D (so tracking never waits for mapping)."""
        if int(recent.index[0]) < 0:
            return guess
        args = (jax.tree.map(lambda x: x[0], recent.frame), jax.tree.map(lambda x: x[0], recent.pose), frame, guess)
        if self.refine is None:
            t0 = time.perf_counter()
            cfg, intr, its = self.cfg.map, self.intr, self.cfg.map.render_init_iterations

            def fn(prev, pose_prev, frame, guess):
                g_prev = mapping.init_gaussians(prev, intr)
                return mapping.refine_pose(cfg, g_prev, pose_prev, frame, guess, intr, iterations=its)

            self.refine = jax.jit(fn).lower(*args).compile()
            self.compile_s += time.perf_counter() - t0
        return self.refine(*args)

    def push(self, recent: slam.Recent, index: int, frame: Frame, pose: lie.SE3) -> slam.Recent:
        """Queue a tracked frame; map the queue when it fills a batch."""
        recent = slam.remember(recent, frame, pose, index)
        return self.flush(recent) if int(recent.queued) == self.batch_size else recent

    def _neighbour_gaussians(self, index: int, frame: Frame) -> PixelGaussians:
        """A neighbour's fixed Gaussians: its learned ones once mapped (paper Eq. 1), else initial.
        (Mapped means in this run's record: after a resume, a killed run's later files are stale.)"""
        if self.cfg.map.learn_neighbours and index in self.scene.poses:
            return self.store.get(index)
        return jax.tree.map(np.asarray, mapping.init_gaussians(frame, self.intr, radius_init=self.cfg.map.radius_init))

    def flush(self, recent: slam.Recent) -> slam.Recent:
        """Map every queued frame: the batch's neighbours are fixed first (frames of the same batch
        contribute their initial Gaussians), then it runs in chunks of one frame per device (the
        last chunk padded by repeating its last frame), so results do not depend on the devices.
        Returns ``recent`` with an empty queue."""
        queued = int(recent.queued)
        if not queued:
            return recent
        stack = lambda *xs: np.stack(xs)  # noqa: E731
        host = jax.tree.map(np.asarray, recent)
        entry = lambda k: (int(host.index[k]), jax.tree.map(lambda x: x[k], host.frame), jax.tree.map(lambda x: x[k], host.pose))  # noqa: E731
        pending, rows = [entry(k) for k in reversed(range(queued))], []  # oldest first
        for k, (_, frame, pose) in zip(reversed(range(queued)), pending):
            have = [entry(j) for j in range(k + 1, k + 1 + self.n) if host.index[j] >= 0]  # its neighbours, newest first
            nb = have + [have[0] if have else (-1, frame, pose)] * (self.n - len(have))
            rows.append((
                frame,
                pose,
                jax.tree.map(stack, *[self._neighbour_gaussians(i, f) for i, f, _ in nb]),
                jax.tree.map(stack, *[f for _, f, _ in nb]),
                jax.tree.map(stack, *[p for _, _, p in nb]),
                np.asarray([True] * len(have) + [False] * (self.n - len(have))),
            ))
        size = self.batch.size
        results = []
        for c in range(0, len(rows), size):
            chunk = rows[c : c + size]
            chunk = chunk + [chunk[-1]] * (size - len(chunk))
            batch = [jax.tree.map(stack, *col) for col in zip(*chunk)]
            self.compile_s += self.batch.compile(*batch)
            t0 = time.perf_counter()
            gs, rgb, depth = self.batch(*batch)
            real = min(size, len(rows) - c)
            self.seconds += [(time.perf_counter() - t0) / real] * real
            results += [(jax.tree.map(lambda x: x[j], gs), rgb[j], depth[j]) for j in range(real)]
        for (index, frame, pose), (g, rgb, depth) in zip(pending, results):
            pose = np.asarray(pose.as_matrix(), np.float64)
            self.store.put(index, g, pose)
            self.scene.add(index, pose, frame.depth, frame.valid)
            self._score(index, frame, rgb, depth)
        return dataclasses.replace(recent, queued=jnp.zeros((), jnp.int32))

    def _score(self, index: int, frame: Frame, rgb: np.ndarray, depth: np.ndarray, *, kind: str = "", mapped: bool = True) -> dict:
        """Score a render; ``kind`` "" (a frame of the run, kept in ``per_frame``: ``mapped``, or
        between keyframes and rendered from the scene), "nvs" (held out) or "test" (a dataset's
        test view): its renders are written as ``{kind}_rgb_XXXXXX.png``."""
        rgb = np.clip(rgb, 0.0, 1.0)
        scores = image.score_view(rgb, depth, frame.rgb, frame.depth, frame.valid, protocol=self.cfg.map.psnr_protocol, lpips_weights=self.lpips_weights)
        rec = {"index": index, "holdout": kind != "", "mapped": mapped and not kind, **scores}
        if self.renders is not None:
            prefix = f"{kind}_" if kind else ""
            mm = np.clip(depth * 1000.0 + 0.5, 0, 65535).astype(np.uint16)
            for name, img in (("rgb", cv2.cvtColor((rgb * 255.0 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR)), ("depth", mm)):
                write_bytes(self.renders / f"{prefix}{name}_{index:06d}.png", cv2.imencode(".png", img)[1].tobytes())
        if not kind:
            self.per_frame.append(rec)
        return rec

    # The scene: held-out views and the merged-map refinement.
    def score_views(self, indices: list[int], poses: np.ndarray, source, kind: str = "nvs") -> list[dict]:
        """Render each view ``source(i)`` at camera-to-world ``poses[i]`` from the scene and score it
        (``kind`` as in :meth:`_score`; "": frames between keyframes)."""
        if not len(self.scene):
            return []
        recs = []
        desc = f"{kind} views" if kind else "frames between keyframes"
        for index in tqdm(indices, desc=desc, unit="view", disable=not self.main or len(indices) < 5, file=sys.stderr):
            out = self.scene.render(poses[index])
            recs.append(self._score(index, host_frame(source(index)), out.rgb, np.asarray(splat.surface_depth(out)), kind=kind, mapped=False))
        return recs

    def finetune(self, iterations: int, poses: np.ndarray, source, seed: int) -> dict:
        """The merged-map refinement: ``iterations`` Adam steps, each on a random mapped frame's
        view rendered from its ``scene.frames`` best-covering frames, all of whose Gaussians move.
        Every mapped frame's Gaussians and Adam moments are held in host memory meanwhile; the
        refined Gaussians replace the stored ones. Returns the step count, the seconds it took and
        the mean loss of its first and last 50 steps. (Call with the queue mapped.)"""
        mapped = sorted(self.scene.poses)
        if not mapped or iterations <= 0:
            return {}
        params = {i: jax.tree.map(np.asarray, self.store.get(i)) for i in mapped}
        states = {i: jax.tree.map(np.asarray, scene.adam_init(params[i])) for i in mapped}
        frames = functools.lru_cache(maxsize=64)(lambda i: host_frame(source(i)))  # training views, read again
        rng = np.random.default_rng(seed)
        chosen_of = {i: self.scene.frames_for(poses[i]) for i in mapped}
        losses, t0 = [], time.perf_counter()
        for _ in tqdm(range(iterations), desc="refining the merged map", unit="step", disable=not self.main, file=sys.stderr):
            view = mapped[rng.integers(len(mapped))]
            chosen = chosen_of[view]
            gs, ps, present = self.scene.stack(chosen, params.__getitem__)
            st, _, _ = self.scene.stack(chosen, states.__getitem__)
            f = frames(view)
            gs, st, loss = scene.finetune_step(
                self.cfg.map, gs, st, ps, present, f.rgb, f.depth, f.valid, _pose(poses[view]), self.intr,
                composite=self.cfg.scene.composite, layers=self.cfg.scene.layers, lr_scale=self.cfg.scene.finetune_lr_scale, offsets=self.cfg.scene.finetune_offsets,
            )
            gs, st = jax.tree.map(np.asarray, (gs, st))
            for j, i in enumerate(chosen):
                params[i] = jax.tree.map(lambda x: x[j], gs)
                states[i] = jax.tree.map(lambda x: x[j], st)
            losses.append(float(loss))
        for i in mapped:
            self.store.put(i, params[i], self.scene.poses[i])
        if not self.store.temporary:
            self.store.flush()  # the files on disk are the refined Gaussians
        return {"finetune_iterations": iterations, "finetune_s": time.perf_counter() - t0, "finetune_loss_first": float(np.mean(losses[:50])), "finetune_loss_last": float(np.mean(losses[-50:]))}

    def metrics(self) -> dict:
        out = _means(self.per_frame)
        h, w = self.intr.height, self.intr.width
        mean = lambda xs: float(np.mean(xs)) if xs else None  # noqa: E731
        out.update(
            psnr_protocol=self.cfg.map.psnr_protocol,
            mapped_frames=len(self.seconds),
            map_every=self.cfg.map.every,
            map_s_per_frame=mean(self.seconds[self.batch.size :] or self.seconds),
            map_compile_s=self.compile_s,
            devices=self.batch.size,
            map_batch=self.batch_size,
            gaussians_total=len(self.seconds) * h * w,  # the paper's NUM1
            gaussians_on_devices=self.batch.size * (1 + self.n) * h * w,  # NUM2: each device's frame and its neighbours'
            gaussians_host_mb=self.store.memory_mb,
        )
        between = [r for r in self.per_frame if not r.get("mapped", True)]
        if between:  # map.every > 1: the frames rendered from the scene, also in the means above
            out.update(_means(between, "between_"), between_frames=len(between))
        if self.lpips_missing:
            out["lpips_missing"] = self.lpips_missing
        return out

    # Checkpoints (the recent frames are in the run state): the mapped frames' record.
    def state(self) -> tuple[dict, dict]:
        self.store.flush()
        mapped, arrays = self.scene.arrays()
        return arrays, {"mapped": mapped, "per_frame": self.per_frame, "seconds": self.seconds}

    def restore(self, arrays: dict, meta: dict) -> None:
        self.scene.restore(meta["mapped"], arrays)
        self.per_frame = list(meta["per_frame"])
        self.seconds = list(meta["seconds"])


def _means(records: list[dict], prefix: str = "") -> dict:
    """Mean of each score over the records that have it (None when none has)."""
    out = {}
    for key in SCORES:
        xs = [r[key] for r in records if key in r]
        out[prefix + key] = float(np.mean(xs)) if xs else None
    return out


def _pose(T: np.ndarray) -> lie.SE3:
    return jax.tree.map(np.asarray, lie.from_matrix(T))


def failure_reason(cfg, info) -> str:
    """The judgement of a failed tracking step in words, e.g. ``few inliers (0.12 < 0.30)``."""
    bits, parts = int(info.failure), []
    if bits & FAIL_NONFINITE:
        parts.append("non-finite pose")
    if bits & FAIL_INLIERS:
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
    memory and the refinement is not available.
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
    ):
        if holdout_every < 0:
            raise ConfigError(f"--holdout-every must be >= 0, got {holdout_every}")
        self.cfg, self.intr = cfg, intr
        self.holdout_every, self.source = holdout_every, source
        self.holdout: list[int] = []  # run indices of the held-out frames
        self.between: list[int] = []  # frames between keyframes (map.every > 1) not yet rendered and scored
        self._held: dict[int, object] = {}  # their samples, when there is no source to read them again
        self.dropped = {"overflow": 0, "out_of_range": 0}  # points T could not take (InsertInfo)
        self.mapper = None if track_only else _Mapper(cfg, intr, None if out_dir is None else pathlib.Path(out_dir), save_renders, mesh)
        # The whole state carried from frame to frame, one pytree (a checkpoint saves it as is).
        self.state = slam.RunState(slam.init_state(cfg.track, initial_pose), None if self.mapper is None else self.mapper.empty_recent())
        self.pager = paging.Pager(cfg.track, np.asarray(self.state.track.geom.origin))
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
            TrackingDiverged: the pose came out non-finite despite the fallbacks (a bug); the system
                cannot continue.
        """
        frame = None if self.mapper is None else host_frame(sample)
        if self.cfg.track.hold_repeated_depth and repeats(sample.depth, self._last_depth):
            pose = self.poses[-1]
        else:
            pose = self._track(sample, frame)
        self._last_depth = sample.depth
        index = len(self.poses)
        self.poses.append(pose)
        self.stamps.append(float(sample.timestamp))
        self.depth_stamps.append(float(sample.depth_timestamp))
        if self.holdout_every and index > 0 and index % self.holdout_every == 0:
            self.holdout.append(index)
            if self.source is None and self.mapper is not None:
                self._held[index] = sample
        elif self.mapper is not None and index % self.cfg.map.every:
            self.between.append(index)
            if self.source is None:
                self._held[index] = sample
        elif self.mapper is not None:
            self.state = dataclasses.replace(self.state, recent=self.mapper.push(self.state.recent, index, frame, lie.from_matrix(pose)))
        return pose

    def _flush(self) -> None:
        """Map the queued frames."""
        if self.mapper is not None:
            self.state = dataclasses.replace(self.state, recent=self.mapper.flush(self.state.recent))

    def _track(self, sample, frame) -> np.ndarray:
        # The host array as read: the compiled step takes it without jnp.asarray's extra copy.
        depth = sample.depth
        dt = np.float32(sample.depth_timestamp - self.depth_stamps[-1] if self.depth_stamps else 0.0)
        guess = None
        if self._predict is not None:
            guess = self.mapper.refine_guess(self.state.recent, frame, self._predict(self.cfg.track, self.state.track, dt))
        if self._step is None:
            t0 = time.perf_counter()
            self._step = compile_step(self.cfg.track, self.state.track, depth, self.intr, dt, guess)
            self.compile_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        state, T, info, ins = self._step(self.state.track, depth, self.intr, dt, guess)
        pose = np.asarray(T.as_matrix())
        if not np.isfinite(pose).all():
            raise TrackingDiverged("tracking diverged (non-finite pose)")
        self.times.append(time.perf_counter() - t0)
        self.iters.append(int(info.iterations))
        if int(info.failure):
            self.failures.append({"frame": len(self.poses), "reason": failure_reason(self.cfg.track, info), "recovered": bool(info.recovered)})
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

    def judge_scene(self, finetune: int = 0) -> dict:
        """Score the held-out views rendered from the scene at their estimated poses (``nvs_*``
        means, and ``nvs_per_frame``); with ``finetune`` > 0 refine the merged map first, keeping
        the scores before it as ``nvs_*_before_finetune``. Call after :meth:`finish`."""
        if self.mapper is None:
            return {}
        if finetune > 0 and self.source is None:
            raise ConfigError("the merged-map refinement reads the training views again: give SLAM a source")
        self._flush()
        source = self.source or self._held.__getitem__
        poses = self.trajectory()
        out: dict = {"nvs_frames": len(self.holdout)} if self.holdout_every else {}
        scores = self.mapper.score_views(self.holdout, poses, source)
        if finetune > 0:
            if scores:
                out.update({f"{k}_before_finetune": v for k, v in _means(scores, "nvs_").items()})
            out.update(self.mapper.finetune(finetune, poses, source, self.cfg.seed))
            scores = self.mapper.score_views(self.holdout, poses, source)
        if self.holdout_every:
            out.update(_means(scores, "nvs_"), nvs_per_frame=scores)
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


def _identity(cfg: SLAMConfig, ds: Dataset, track_only: bool, holdout_every: int) -> dict:
    """What a checkpoint must match to be resumed: the config, the mode and the dataset's frames."""
    return {
        "config": json.loads(json.dumps(to_dict(cfg))),
        "track_only": track_only,
        "holdout_every": holdout_every,
        "dataset": {"name": ds.name, "layout": ds.layout, "frames": len(ds), "timestamps": [float(t) for t in ds.timestamps[:1]] + [float(t) for t in ds.timestamps[-1:]]},
    }


def run(
    cfg: SLAMConfig,
    out_dir: str | os.PathLike | None = None,
    *,
    track_only: bool = False,
    save_renders: bool = False,
    progress: bool = True,
    resume: bool = False,
    checkpoint_every: int = 0,
    devices: int | None = None,
    holdout_every: int = 0,
    finetune: int = 0,
    on_bad_frame: str = "stop",
    viewer: tuple[str, int] | None = None,
) -> RunResult:
    """Run SLAM over ``cfg.data`` and write the outputs to ``out_dir`` (if given).

    With ``checkpoint_every`` N > 0 (and an ``out_dir``) the run is checkpointed every N frames in
    ``out_dir/checkpoints``; ``resume`` continues from the newest checkpoint there (the config and
    dataset must be the same) instead of starting over. Mapping uses ``devices`` devices of each
    process (default: all; see :mod:`sgad_jax.distributed`). ``holdout_every`` N > 0 holds every
    N-th frame out of mapping and scores it from the scene afterwards (``nvs_*`` in the metrics);
    ``finetune`` > 0 refines the merged map for that many steps before (see :class:`SLAM`).

    A frame that cannot be used (an unreadable or truncated image, a missing file, depth with no
    valid pixel or with NaN/Inf, mismatched sizes, a timestamp not after the previous frame's)
    stops the run with ``on_bad_frame="stop"``: everything before it is written, and checkpointed
    (with ``checkpoint_every`` > 0) so that ``resume`` continues from it once it is fixed. With
    ``"skip"`` the frame is left out and listed in the metrics' ``skipped_frames``; run indices
    (renders, Gaussians, ``per_frame``) then count the frames kept, the rows of ``trajectory.txt``.
    ``viewer`` (host, port) serves the run live in a browser (:class:`sgad_jax.viewer.LiveView`,
    returned in the result).

    Raises:
        DatasetError: on bad input (after writing whatever was computed before it).
        ConfigError: when the checkpoint to resume was made with another config or dataset.
    """
    if on_bad_frame not in ("stop", "skip"):
        raise ConfigError(f"--on-bad-frame must be stop or skip, got {on_bad_frame!r}")
    ds = open_dataset(cfg.data)
    out = None if out_dir is None else pathlib.Path(out_dir)
    if out is not None:
        _check_writable(out)
    main = jax.process_index() == 0
    identity = _identity(cfg, ds, track_only, holdout_every)
    ckpt_root = None if out is None or jax.process_count() > 1 else out / "checkpoints"
    if resume and ckpt_root is None:
        raise ConfigError("--resume needs --out (and a single-process run)")
    restored = checkpoint.latest(ckpt_root) if resume else None
    if resume and restored is None and main:
        print(f"sgad-jax: no checkpoint in {ckpt_root} yet: starting from the first frame", file=sys.stderr)
    if restored is not None and restored[1]["identity"] != identity:
        saved = restored[1]["identity"]
        what = "dataset" if saved["dataset"] != identity["dataset"] else "mode (--track-only)" if saved["track_only"] != track_only else "config"
        raise ConfigError(f"cannot resume {ckpt_root}: it was made with another {what}; rerun with the same settings or a new --out")
    if restored is not None and "depth_stamps" not in restored[0]:
        raise ConfigError(f"cannot resume {ckpt_root}: it was written by an older sgad_jax (no depth stamps); rerun without --resume or with a new --out")
    if out is not None and restored is None and main:
        for stale in (out / "gaussians", out / "renders", out / "checkpoints"):
            shutil.rmtree(stale, ignore_errors=True)
    if out is not None and jax.process_count() > 1:
        jax.experimental.multihost_utils.sync_global_devices("sgad_jax: outputs cleared")
    mesh = None if track_only else frames_mesh(devices)
    kept: list[int] = []  # the run index of each tracked frame (the rows of trajectory.txt)
    skipped: list[dict] = []
    system = SLAM(
        cfg, ds.intrinsics, initial_pose=initial_pose(ds), out_dir=out, track_only=track_only, save_renders=save_renders,
        mesh=mesh, holdout_every=holdout_every, source=lambda k: ds[kept[k]],
    )
    if main:
        for line in ds.warnings:
            print(f"sgad-jax: warning: {line}", file=sys.stderr)
    live = None
    if viewer is not None and main:
        from sgad_jax.viewer import LiveView

        live = LiveView(ds.intrinsics, host=viewer[0], port=viewer[1])
    start = 0
    if restored is not None:
        meta = restored[1]["run"]
        system.restore(restored[0], meta)
        kept[:] = meta.get("kept", range(len(system)))
        skipped[:] = meta.get("skipped", [])
        start = meta.get("next", len(system))

    def save_checkpoint(next_frame: int) -> None:
        arrays, meta = system.checkpoint_state()
        meta.update(kept=kept, skipped=skipped, next=next_frame)
        checkpoint.save(ckpt_root, next_frame, arrays, {"identity": identity, "run": meta})

    stopped = None
    rss_trace = []
    t_run = time.perf_counter()
    what = "tracking" if track_only else "tracking + mapping"
    bar = tqdm(total=len(ds), initial=start, desc=f"{what} {ds.name}", unit="frame", disable=not (progress and main), file=sys.stderr)
    try:
        for sample in ds.frames(start, skip_bad=True):
            i = sample.index
            problem = sample.reason if isinstance(sample, BadFrame) else _timestamp_problem(ds, sample, system.stamps)
            if problem and on_bad_frame == "stop":
                stopped = problem
                if ckpt_root is not None and checkpoint_every > 0 and i > 0:
                    save_checkpoint(i)  # resumable from the bad frame once it is fixed
                break
            if problem:
                skipped.append({"index": i, "source_index": sample.source_index, "reason": problem})
                if main:
                    tqdm.write(f"sgad-jax: skipped: {problem}", file=sys.stderr)
            else:
                try:
                    pose = system.add(sample)
                except TrackingDiverged as err:
                    raise DatasetError(f"{ds.name} frame {sample.source_index}: {err}") from None
                kept.append(i)
                if live is not None:
                    live.frame(len(system) - 1, pose, sample)
            bar.update(1)
            if (i + 1) % RSS_EVERY == 0:
                rss_trace.append([i + 1, current_rss_mb()])
            if ckpt_root is not None and checkpoint_every > 0 and (i + 1) % checkpoint_every == 0 and i + 1 < len(ds):
                save_checkpoint(i + 1)
    except DatasetError as err:
        stopped = str(err)
    finally:
        bar.close()

    metrics = {"frames": len(system), "dataset": ds.name, "layout": ds.layout}
    run_metrics = system.finish()
    # Every input frame tracked, mapped or rendered from the scene, and scored; compilation apart.
    compiled = (run_metrics.get("compile_s") or 0.0) + (run_metrics.get("map_compile_s") or 0.0)
    if len(system) > start:
        run_metrics["s_per_input_frame"] = (time.perf_counter() - t_run - compiled) / (len(system) - start)
    if not stopped:
        run_metrics.update(system.judge_scene(finetune))
    poses_np = system.trajectory()
    stamps_np = np.asarray(system.stamps, np.float64)
    gt = ds.gt_poses[kept]
    if len(poses_np) >= 3 and np.isfinite(gt).all(axis=(1, 2)).sum() >= 3:
        err = ate(poses_np, gt)
        metrics.update(ate_rmse_cm=100 * err["rmse_m"], ate_mean_cm=100 * err["mean_m"], ate_pairs=err["pairs"])
        drift = rpe(poses_np, gt)
        metrics.update(rpe_rmse_cm=100 * drift["trans_rmse_m"], rpe_rot_rmse_deg=drift["rot_rmse_deg"])
    else:
        metrics.update(ate_rmse_cm=None, ate_mean_cm=None, rpe_rmse_cm=None, rpe_rot_rmse_deg=None)
    metrics.update(run_metrics)
    if not stopped and system.mapper is not None and ds.layout == "scannetpp":
        metrics.update(_score_test_views(system, gt, poses_np, ds))
    metrics["skipped_frames"] = skipped
    if ds.warnings:
        metrics["data_warnings"] = ds.warnings
    if restored is not None:
        metrics["resumed_from_frame"] = start
    metrics.update(processes=jax.process_count(), peak_rss_mb=peak_rss_mb(), rss_mb_by_frame=rss_trace, config=to_dict(cfg))
    if stopped:
        metrics["stopped"] = stopped
    if system.mapper is not None:
        metrics["per_frame"] = sorted(system.mapper.per_frame + metrics.pop("nvs_per_frame", []), key=lambda r: r["index"])
    if out is not None and main:
        out.mkdir(parents=True, exist_ok=True)
        write_tum_trajectory(out / "trajectory.txt", stamps_np, poses_np)
        intr = ds.intrinsics
        write_json(out / "cameras.json", {"width": intr.width, "height": intr.height, "fx": float(intr.fx), "fy": float(intr.fy), "cx": float(intr.cx), "cy": float(intr.cy)})
        write_json(out / "metrics.json", metrics)
    if stopped:
        raise DatasetError(stopped)
    return RunResult(poses=poses_np, timestamps=stamps_np, metrics=metrics, live=live)


def _timestamp_problem(ds: Dataset, sample, stamps: list[float]) -> str | None:
    """Why a frame's timestamp cannot follow the previous tracked frame's (None when it can)."""
    if not np.isfinite(sample.timestamp):
        return f"{ds.describe(sample.source_index)}: timestamp {sample.timestamp} is not finite"
    if stamps and sample.timestamp <= stamps[-1]:
        return f"{ds.describe(sample.source_index)}: timestamp {sample.timestamp:.6f} is not after the previous frame's {stamps[-1]:.6f}"
    return None


def _score_test_views(system: SLAM, gt: np.ndarray, est: np.ndarray, ds: Dataset) -> dict:
    """A dataset's own test views (ScanNet++ DSLR ``test``) rendered from the scene at their
    ground-truth poses carried into the estimated trajectory's frame (the SE(3) alignment of the
    estimated to the ground-truth poses, least squares in rotation, then in position): ``test_*``
    means and ``test_per_frame``."""
    from sgad_jax.io.datasets import ScanNetPPDataset

    try:
        test = ScanNetPPDataset(ds.root, dataclasses.replace(ds.cfg, start=0, stride=1, max_frames=0), split="test")
    except DatasetError as err:
        return {"test_views": f"not scored: {err}"}
    ok = np.isfinite(gt).all(axis=(1, 2))
    if ok.sum() < 3:
        return {"test_views": "not scored: fewer than 3 frames with ground truth to align the trajectory"}
    # Rotations and positions together: positions alone leave the rotation about a straight path free.
    M = np.einsum("fij,fkj->ik", gt[ok, :3, :3], est[ok, :3, :3])
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    A = np.eye(4)  # estimated frame -> ground-truth frame
    A[:3, :3], A[:3, 3] = R, (gt[ok, :3, 3] - est[ok, :3, 3] @ R.T).mean(0)
    poses = np.linalg.inv(A)[None] @ test.gt_poses
    scored = [i for i in range(len(test)) if np.isfinite(poses[i]).all()]
    recs = system.mapper.score_views(scored, poses, test.__getitem__, kind="test")
    return {"test_frames": len(recs), **_means(recs, "test_"), "test_per_frame": recs}


def _check_writable(out: pathlib.Path) -> None:
    """Fail before any work when the output folder cannot be written."""
    try:
        out.mkdir(parents=True, exist_ok=True)
        write_bytes(out / ".sgad_write_test", b"")
        (out / ".sgad_write_test").unlink()
    except OSError as err:
        raise DatasetError(f"{out}: the output folder cannot be written ({err.strerror or err})") from None
