"""The whole-run job behind ``sgad-jax run``: read a dataset's frames, feed them to
:class:`sgad_jax.system.SLAM`, checkpoint, and write the results. Never jitted itself.

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
Both are written when the run ends, including when it stops early on bad input or on SIGINT /
SIGTERM (then with ``"stopped": "<why>"``), so that no computed result is lost.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import dataclasses
import functools
import json
import os
import pathlib
import resource
import shutil
import signal
import sys
import threading
import time

import jax
import jax.experimental.multihost_utils
import numpy as np
from tqdm import tqdm

from sgad_jax import checkpoint
from sgad_jax.config import ConfigError, SLAMConfig, to_dict
from sgad_jax.distributed import frames_mesh
from sgad_jax.eval.ate import ate, rpe
from sgad_jax.io.base import BadFrame, Dataset, DatasetError, RunInterrupted
from sgad_jax.io.datasets import open_dataset
from sgad_jax.io.export import write_tum_trajectory
from sgad_jax.io.files import write_json
from sgad_jax.mapper import means
from sgad_jax.system import SLAM, TrackingDiverged, initial_pose


@dataclasses.dataclass
class RunResult:
    poses: np.ndarray  # (f, 4, 4) camera-to-world
    timestamps: np.ndarray
    metrics: dict
    live: object = None  # the live viewer (sgad_jax.viewer.LiveView) when one was asked for


@contextlib.contextmanager
def _stop_requests(enabled: bool):
    """While a run tracks, maps and refines: the first SIGINT or SIGTERM only asks it to stop after
    the frame or refinement step in hand (the signal's number is appended to the list yielded), so
    that the state is whole when it is written and checkpointed; a second acts as it would
    without this (Ctrl-C raises KeyboardInterrupt). A signal the process ignores (a background
    job's SIGINT) stays ignored. Only in the main thread of a one-process run: the processes of a
    multi-process run must stop together, which a signal to one of them cannot arrange."""
    requested: list[int] = []
    if not enabled or threading.current_thread() is not threading.main_thread():
        yield requested
        return
    previous = {s: h for s in (signal.SIGINT, signal.SIGTERM) if (h := signal.getsignal(s)) is not signal.SIG_IGN}

    def handler(signum, frame):
        if not requested:
            requested.append(signum)
            return
        signal.signal(signum, previous[signum])
        if callable(previous[signum]):
            previous[signum](signum, frame)
        else:
            signal.raise_signal(signum)

    for s in previous:
        signal.signal(s, handler)
    try:
        yield requested
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


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


@functools.cache
def _malloc_trim():
    """glibc's ``malloc_trim``; None for another C library."""
    try:
        return ctypes.CDLL(ctypes.util.find_library("c")).malloc_trim
    except (OSError, TypeError, AttributeError):
        return None


def release_freed_memory() -> None:
    """Give the memory that glibc's ``malloc`` holds freed back to the system (nothing elsewhere).

    glibc raises its mmap threshold to the largest block freed (a 640x480 frame's 8 MB arrays), then
    serves such blocks from heaps it seldom shrinks, so a long run's RSS crept up by about 0.2 MB a
    frame though nothing leaked. A call takes about 35 ms at 640x480; the run makes one every
    :data:`RSS_EVERY` frames. (A fixed threshold, ``MALLOC_MMAP_THRESHOLD_``, also held RSS flat
    but cost a fifth of the run's speed in page faults.)"""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


def _identity(cfg: SLAMConfig, ds: Dataset, track_only: bool, holdout_every: int) -> dict:
    """What a checkpoint must match to be resumed: the config, the mode and the dataset's frames."""
    config = json.loads(json.dumps(to_dict(cfg)))
    if config["data"]["path"]:  # `data`, `data/` and its absolute path are one folder
        config["data"]["path"] = str(pathlib.Path(config["data"]["path"]).expanduser().resolve())
    return {
        "config": config,
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

    The first SIGINT (Ctrl-C) or SIGTERM stops the run after the frame in hand, as a bad frame does
    with ``"stop"`` (written, and checkpointed at the next frame), or ends the refinement after the
    step in hand (the held-out views scored as it is), then raises RunInterrupted.

    Raises:
        DatasetError: on bad input (after writing whatever was computed before it).
        RunInterrupted: on SIGINT or SIGTERM (after the same).
        ConfigError: when the checkpoint to resume was made with another config or dataset.
    """
    if on_bad_frame not in ("stop", "skip"):
        raise ConfigError(f"--on-bad-frame must be stop or skip, got {on_bad_frame!r}")
    if finetune < 0 or checkpoint_every < 0:
        raise ConfigError(f"--finetune and --checkpoint-every must be >= 0, got {finetune} and {checkpoint_every}")
    notes = []
    if track_only and (holdout_every or finetune):  # as `... --track-only` appended to a mapping command
        notes.append("--holdout-every and --finetune judge and refine the map: ignored with --track-only")
        holdout_every = finetune = 0
    ds = open_dataset(cfg.data)
    ds.colour = not track_only or viewer is not None  # tracking alone never looks at colour (the live view does)
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
    live = None
    if viewer is not None and main:  # before an earlier run's outputs go: a taken port must not cost them
        from sgad_jax.viewer import LiveView

        live = LiveView(ds.intrinsics, host=viewer[0], port=viewer[1])
    if out is not None and restored is None and main:
        for stale in (out / "gaussians", out / "renders", out / "checkpoints", out / "plots"):
            shutil.rmtree(stale, ignore_errors=True)
        for stale in ("gaussians.ply", "mesh.ply", "eval.json", "report.md", "trajectory.png"):  # an earlier run's exports
            (out / stale).unlink(missing_ok=True)
    if out is not None and jax.process_count() > 1:
        jax.experimental.multihost_utils.sync_global_devices("sgad_jax: outputs cleared")
    mesh = None if track_only else frames_mesh(devices)
    kept: list[int] = []  # the run index of each tracked frame (the rows of trajectory.txt)
    skipped: list[dict] = []
    system = SLAM(
        cfg, ds.intrinsics, initial_pose=initial_pose(ds), out_dir=out, track_only=track_only, save_renders=save_renders,
        mesh=mesh, holdout_every=holdout_every, source=lambda k: ds[kept[k]], progress=progress,
    )
    if holdout_every >= len(ds):  # frames i > 0 with i % N == 0 are held out
        notes.append(f"--holdout-every {holdout_every}: the run has {len(ds)} frames, so none is held out")
    ds.warnings += notes
    if main:
        for line in ds.warnings:
            print(f"sgad-jax: warning: {line}", file=sys.stderr)
    start = 0
    if restored is not None:
        meta = restored[1]["run"]
        system.restore(restored[0], meta)
        kept[:] = meta.get("kept", range(len(system)))
        skipped[:] = meta.get("skipped", [])
        start = meta.get("next", len(system))

    saved = start if restored is not None else -1  # the step last written (a bad frame can follow it)

    def save_checkpoint(next_frame: int) -> None:
        nonlocal saved
        if next_frame == saved:  # orbax refuses to write a step twice; that one holds this state
            return
        arrays, meta = system.checkpoint_state()
        meta.update(kept=kept, skipped=skipped, next=next_frame)
        checkpoint.save(ckpt_root, next_frame, arrays, {"identity": identity, "run": meta})
        saved = next_frame

    stopped, interrupted = None, None
    rss_trace = []
    t_run = time.perf_counter()
    what = "tracking" if track_only else "tracking + mapping"
    bar = tqdm(total=len(ds), initial=start, desc=f"{what} {ds.name}", unit="frame", disable=not (progress and main), file=sys.stderr)
    saving = ckpt_root is not None and checkpoint_every > 0
    with _stop_requests(jax.process_count() == 1) as requests:
        try:
            # `fill`: the frames the system will map, by run index (a skipped frame shifts the system's
            # count; a wrong guess only moves a frame's inpainting back to the main thread or wastes it).
            # `stage`: depth goes to the device with its batch, not inside the tracking step.
            for sample in ds.frames(start, skip_bad=True, fill=None if track_only else system.maps, stage=jax.device_put):
                i = sample.index
                problem = sample.reason if isinstance(sample, BadFrame) else _timestamp_problem(ds, sample, system.stamps)
                if problem and on_bad_frame == "stop":
                    stopped = problem
                    if saving and i > 0:
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
                    release_freed_memory()
                    rss_trace.append([i + 1, current_rss_mb()])
                due = saving and (i + 1) % checkpoint_every == 0 and i + 1 < len(ds)
                if due or (saving and requests):
                    save_checkpoint(i + 1)
                if requests:  # SIGINT / SIGTERM: stop here, with the state whole
                    interrupted = requests[0]
                    stopped = f"interrupted by {signal.Signals(interrupted).name} after {i + 1} of {len(ds)} frames"
                    if saving:
                        stopped += f"; --resume continues from frame {i + 1}"
                    break
        except DatasetError as err:
            stopped = str(err)
        finally:
            bar.close()

        metrics = {"frames": len(system), "dataset": ds.name, "layout": ds.layout}
        try:
            run_metrics = system.finish()
        except DatasetError as err:  # e.g. the disk filled up: the trajectory may still fit
            stopped, run_metrics = stopped or str(err), {}
        # Every input frame tracked, mapped or rendered from the scene, and scored; compilation apart.
        compiled = (run_metrics.get("compile_s") or 0.0) + (run_metrics.get("map_compile_s") or 0.0)
        if len(system) > start:
            run_metrics["s_per_input_frame"] = (time.perf_counter() - t_run - compiled) / (len(system) - start)
        if requests and not stopped:  # asked during the last frames' mapping: stop before the scoring
            interrupted = requests[0]
            stopped = f"interrupted by {signal.Signals(interrupted).name} after all {len(ds)} frames" + (", before the held-out views were scored" if holdout_every or finetune else "")
        if not stopped:
            try:
                system.judge_scene(finetune, stop=lambda: bool(requests), out=run_metrics)
            except DatasetError as err:  # e.g. the disk filled up under the refinement's spilled state; the scores before it stay
                stopped = str(err)
            done = run_metrics.get("finetune_iterations", finetune)
            if requests and done < finetune:  # the refinement was cut short (its views scored as it was)
                interrupted = requests[0]
                stopped = f"interrupted by {signal.Signals(interrupted).name} after all {len(ds)} frames, in the refinement ({done} of {finetune} steps)"
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
    if interrupted:
        raise RunInterrupted(stopped, interrupted)
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
    return {"test_frames": len(recs), **means(recs, "test_"), "test_per_frame": recs}


def _check_writable(out: pathlib.Path) -> None:
    """Fail before any work when the output folder cannot be written."""
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / f".sgad_write_test.{os.getpid()}"  # one per process: the processes of a run share the folder
        probe.write_bytes(b"")  # plain I/O: the OSError names the folder below
        probe.unlink()
    except OSError as err:
        raise DatasetError(f"{out}: the output folder cannot be written ({err.strerror or err})") from None
