"""Tracking speed and accuracy: sgad_jax against small_gicp on the same frames, in one process.

The peer is small_gicp (C++, PyPI ``small-gicp``) run frame-to-model: every R-th depth pixel, covariances from K_c neighbours (its k-d tree),
VGICP against its own Gaussian voxel map (5 cm voxels), constant-velocity guess, the aligned frame
inserted into the map, 2 threads. Both sides are timed per frame from a depth image in memory to
an updated map (preprocessing included); compile time is reported separately.

Usage::

    python benchmarks/bench_track.py --data ../shared/data/tum_fr1_xyz [--config tum] [--start 0] [--max-frames 0]

Both trackers run the sequence in turn ``--rounds`` times (default 5): each tracker's time is the
median over the rounds of its per-frame median, and ``ratio`` the median of the rounds' ratios, so
that the machine's drift from minute to minute weighs on both alike (``rounds_ms`` lists them).

Prints one JSON object: ours_ms_median, small_gicp_ms_median, ratio (ours / peer), ours_ate_cm,
small_gicp_ate_cm (ATE RMSE, SE(3)-aligned, of both trajectories moved to the frames' colour stamps
as ``sgad-jax run`` writes them; ``*_ate_cm_at_depth_stamps``: the poses as tracked), ours_rpe_cm and
small_gicp_rpe_cm (frame-to-frame RPE RMSE, translation, at the colour stamps: the error of each
frame's registration, which a whole sequence's ATE mixes with drift), ours_compile_s, frames, and
the settings.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np


def _strided_points(depth: np.ndarray, intr, stride: int) -> np.ndarray:
    off = stride // 2
    d = depth[off::stride, off::stride]
    v, u = np.mgrid[off : depth.shape[0] : stride, off : depth.shape[1] : stride]
    m = d > 0.1
    fx, fy, cx, cy = intr.as_tuple()
    z = d[m].astype(np.float64)
    return np.stack([(u[m] - cx) / fx * z, (v[m] - cy) / fy * z, z], axis=1)


def _small_gicp_track(depths, repeated, intr, T0, stride, k, voxel, max_corr, threads):
    import small_gicp

    vmap = small_gicp.GaussianVoxelMap(voxel)
    poses, times = [], []
    T_prev = T_prev2 = T0
    for depth, same in zip(depths, repeated):
        if same:  # the rule of `sgad-jax run` for both trackers: a repeated depth image keeps its pose
            poses.append(T_prev)
            continue
        t0 = time.perf_counter()
        pc = small_gicp.PointCloud(_strided_points(depth, intr, stride))
        small_gicp.estimate_covariances(pc, num_neighbors=k, num_threads=threads)
        if poses:
            guess = T_prev @ np.linalg.inv(T_prev2) @ T_prev
            res = small_gicp.align(vmap, pc, guess, max_correspondence_distance=max_corr, num_threads=threads)
            T = res.T_target_source
        else:
            T = T0
        vmap.insert(pc, T)
        times.append(time.perf_counter() - t0)
        poses.append(T)
        T_prev2, T_prev = T_prev, T
    return np.stack(poses), np.asarray(times)


def _median_ms(f, *args, repeats=20, donated=False) -> float:
    """Median time of ``f(*args)`` after a warm-up call. ``donated``: ``f`` updates its first
    argument in place (as the tracking step does), so each call gets a fresh copy of it, made
    outside the timed region."""
    import jax
    import jax.numpy as jnp

    times = []
    for _ in range(repeats + 1):
        call = (jax.block_until_ready(jax.tree.map(jnp.copy, args[0])), *args[1:]) if donated else args
        t0 = time.perf_counter()
        jax.block_until_ready(f(*call))
        times.append(time.perf_counter() - t0)
    return 1000 * float(np.median(times[1:]))


def _stage_times(tcfg, geom, depth, intr, T) -> dict:
    """Each stage of our step on the last frame at its tracked pose (medians, ms). Point extraction
    and insertion run once per frame and are timed as calls; a Gauss-Newton step and a candidate
    lookup run inside the solver's loop and are timed there, as the cost of one more iteration
    (a separate call per step would add the call's own overhead), on the full
    cloud and on the first coarse level (``*_coarse``: every ``tcfg.coarse[0]``-th point). Each
    stage is compiled with the step's compiler options, so it runs as it does inside the step."""
    import dataclasses

    import jax

    from sgad_jax import geometry, gicp, system
    from sgad_jax.track import _gauss_newton, transform_cloud

    options = system.TRACK_CPU_OPTIONS if jax.default_backend() == "cpu" else None

    def program(f, *args, donate=()):
        return jax.jit(f, donate_argnums=donate).lower(*args).compile(compiler_options=options)

    cloud = jax.jit(gicp.frame_points, static_argnums=0)(tcfg, depth, intr)

    def per_iteration(points, fresh):  # fresh=0: a lookup before every step; 1e9: only the first
        def run(n):
            cf = dataclasses.replace(tcfg, max_iterations=n, tolerance=0.0)
            return program(lambda g, cl, T: _gauss_newton(cf, g, cl, T, fresh)[0].wxyz_xyz, geom, points, T)

        return (_median_ms(run(8), geom, points, T) - _median_ms(run(1), geom, points, T)) / 7

    # Both clouds, as the step extracts them (the tracked one and, with median depths, the one T receives).
    out = {"frame_points": _median_ms(program(lambda d, i: gicp.frame_clouds(tcfg, d, i), depth, intr), depth, intr)}
    for name, c in (("", 1), *(("_coarse", c) for c in tcfg.coarse[:1])):  # coarse: every c-th point
        points = jax.tree.map(lambda a, c=c: a[..., ::c], cloud)
        step = per_iteration(points, 1e9)
        out["gauss_newton_step" + name] = step
        out["candidate_lookup" + name] = per_iteration(points, 0.0) - step
    cloud_w = transform_cloud(T, cloud)
    out["insert"] = _median_ms(program(geometry.insert, geom, cloud_w, donate=(0,)), geom, cloud_w, donated=True)
    return out


def read_sequence(cfg):
    """Every frame of ``cfg.data`` read first (timings exclude file I/O): the dataset, the depth
    images, which repeat the previous one, the depth and frame stamps, and the time since the
    previous depth image (a repeated one moves the clock on, as in ``SLAM.add``)."""
    from sgad_jax import system
    from sgad_jax.io.datasets import open_dataset

    ds = open_dataset(cfg.data)
    samples = [ds[i] for i in range(len(ds))]
    depths = [s.depth for s in samples]
    hold = cfg.track.hold_repeated_depth
    repeated = [hold and system.repeats(d, prev) for d, prev in zip(depths, [None, *depths[:-1]])]
    depth_stamps = np.array([s.depth_timestamp for s in samples])
    frame_stamps = np.array([s.timestamp for s in samples])
    dts = np.diff(depth_stamps, prepend=depth_stamps[0]).astype(np.float32)
    return ds, depths, repeated, depth_stamps, frame_stamps, dts


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--config", default=None, help="preset (default: from the layout)")
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--max-frames", type=int, default=0)
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--peer-voxel", type=float, default=0.05)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=5, help="whole-sequence passes of both trackers, in turn")
    args = ap.parse_args()
    if args.rounds < 1:
        ap.error(f"--rounds must be at least 1, got {args.rounds}")

    import jax
    import jax.numpy as jnp

    from sgad_jax import lie, slam, system
    from sgad_jax.cli import resolve_config
    from sgad_jax.eval.ate import ate, rpe

    cfg = resolve_config(args.config, args.data, start=args.start, max_frames=args.max_frames, overrides=args.overrides)
    ds, depths, repeated, depth_stamps, frame_stamps, dts = read_sequence(cfg)
    gt = ds.gt_poses
    intr = ds.intrinsics
    tcfg = cfg.tracking()

    # Ours: compile once; then both trackers run the whole sequence in turn, `--rounds` times, so
    # that each round's pair of medians is measured within seconds of each other (a shared
    # machine's speed drifts within minutes). Poses and ATEs are the first round's (every
    # round computes the same).
    # Depth and intrinsics on the device before the step, as `sgad-jax run` stages them (its reader
    # copies each depth with its batch; the intrinsics once).
    staged, intr_dev = [jax.device_put(d) for d in depths], jax.device_put(intr)
    t0 = time.perf_counter()
    step = system.compile_step(tcfg, slam.init_state(tcfg, system.initial_pose(ds)), staged[0], intr_dev, dts[0])
    compile_s = time.perf_counter() - t0

    def run_ours():
        state = slam.init_state(tcfg, system.initial_pose(ds))
        poses, times, iters = [], [], []
        for depth, dt, same in zip(staged, dts, repeated):
            if same:
                poses.append(poses[-1])
                continue
            t0 = time.perf_counter()
            state, T, pose, info, _ = step(state, depth, intr_dev, dt, None)
            pose = np.asarray(pose)
            times.append(time.perf_counter() - t0)
            poses.append(pose)
            iters.append(int(info.iterations))
        return np.stack(poses), times, iters, state, T

    T0 = np.asarray(system.initial_pose(ds).as_matrix(), np.float64)
    rounds = []
    for r in range(args.rounds):
        ours_r, ours_t, iters_r, state, T = run_ours()
        peer_r, peer_t = _small_gicp_track(depths, repeated, intr, T0, tcfg.stride, tcfg.k, args.peer_voxel, 2 * args.peer_voxel, args.threads)
        if r == 0:
            ours, peer, iters = ours_r, peer_r, iters_r
        rounds.append((1000 * float(np.median(ours_t[1:])), 1000 * float(np.median(peer_t[1:]))))
    stages = _stage_times(tcfg, state.geom, jnp.asarray(depths[-1]), intr, T)
    ours_ms = float(np.median([o for o, _ in rounds]))
    peer_ms = float(np.median([p for _, p in rounds]))
    ours_at_frames, peer_at_frames = (lie.interpolate(p, depth_stamps, frame_stamps) for p in (ours, peer))
    out = {
        "data": os.path.abspath(args.data),
        "frames": len(depths),
        "resolution": f"{intr.width}x{intr.height}",
        "stride": tcfg.stride,
        "k": tcfg.k,
        "repeated_depth_frames": int(sum(repeated)),
        "ours_ms_median": ours_ms,
        "small_gicp_ms_median": peer_ms,
        "ratio": float(np.median([o / p for o, p in rounds])),  # median of the rounds' ratios
        "rounds_ms": [{"ours": o, "small_gicp": p, "ratio": o / p} for o, p in rounds],
        # Both trajectories moved from the depth stamps to the frames' (colour) stamps, as
        # `sgad-jax run` writes its trajectory; and as tracked, at the depth stamps.
        "ours_ate_cm": 100 * ate(ours_at_frames, gt)["rmse_m"],
        "small_gicp_ate_cm": 100 * ate(peer_at_frames, gt)["rmse_m"],
        "ours_rpe_cm": 100 * rpe(ours_at_frames, gt)["trans_rmse_m"],
        "small_gicp_rpe_cm": 100 * rpe(peer_at_frames, gt)["trans_rmse_m"],
        "ours_ate_cm_at_depth_stamps": 100 * ate(ours, gt)["rmse_m"],
        "small_gicp_ate_cm_at_depth_stamps": 100 * ate(peer, gt)["rmse_m"],
        "ours_compile_s": compile_s,
        "ours_iterations_mean": float(np.mean(iters[1:])),
        "ours_stage_ms": stages,
        "small_gicp_voxel_m": args.peer_voxel,
        "threads": args.threads,
        "jax_backend": jax.default_backend(),
        "device": jax.devices()[0].device_kind,
    }
    json.dump(out, sys.stdout, indent=2)
    print()


if __name__ == "__main__":
    main()
