"""Tracking ATE under the paper's depth noise: sgad_jax (and optionally small_gicp) over noise levels and seeds.

Each noise level and seed reads the sequence with ``data.noise_share`` / ``data.noise_seed`` set
(a share of each depth image's valid pixels plus N(0, ``data.noise_sigma``)), runs the host loop's
tracking step (``system.compile_step``, compiled once per config) over it with the repeated-depth
and timestamp rules of ``sgad-jax run``, and prints one JSON line per run: ``ours_ate_cm``, the
frames judged failed (``tracking_failures``, as a run's ``metrics.json`` lists them) and, with
``--peer``, ``small_gicp_ate_cm`` (VGICP as in ``bench_track.py``).

Usage::

    python benchmarks/bench_noise.py --data ../shared/data/7scenes_redkitchen --max-frames 200 \\
        [--levels 0,0.1,0.2,0.3,0.4] [--seeds 0,1] [--peer] [--set track.median_gate=0 ...]
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default="", help="dataset folder (default: the synthetic scene)")
    ap.add_argument("--config", default=None)
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--stride", type=int, default=1)
    ap.add_argument("--max-frames", type=int, default=0)
    ap.add_argument("--levels", default="0,0.1,0.2,0.3,0.4", help="noisy shares of the valid depth pixels")
    ap.add_argument("--seeds", default="0,1", help="noise seeds (the clean level runs once)")
    ap.add_argument("--peer", action="store_true", help="also run small_gicp on the same frames")
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    args = ap.parse_args()

    import jax.numpy as jnp

    from bench_track import _small_gicp_track, read_sequence
    from sgad_jax import lie, slam, system
    from sgad_jax.cli import resolve_config
    from sgad_jax.eval.ate import ate

    seeds = [int(s) for s in args.seeds.split(",")]
    steps = {}
    for level in (float(x) for x in args.levels.split(",")):
        for seed in seeds[:1] if level == 0 else seeds:
            noise = [f"data.noise_share={level}", f"data.noise_seed={seed}", f"data.stride={args.stride}"]
            cfg = resolve_config(args.config, args.data or None, start=args.start, max_frames=args.max_frames, overrides=args.overrides + noise)
            ds, depths, repeated, depth_stamps, frame_stamps, dts = read_sequence(cfg)
            tcfg, intr = cfg.tracking(), ds.intrinsics
            T0 = system.initial_pose(ds)
            T0_matrix = np.asarray(T0.as_matrix(), np.float64)  # before the state's buffers are donated
            if (tcfg, intr) not in steps:
                steps[tcfg, intr] = system.compile_step(tcfg, slam.init_state(tcfg, T0), jnp.asarray(depths[0]), intr, dts[0])
            step = steps[tcfg, intr]
            state, poses, failures = slam.init_state(tcfg, T0), [], 0
            for depth, dt, same in zip(depths, dts, repeated):
                if same:
                    poses.append(poses[-1])
                    continue
                state, _, pose, info, _ = step(state, depth, intr, dt, None)
                poses.append(np.asarray(pose))
                failures += int(info.failure) != 0
            score = lambda p: 100 * ate(lie.interpolate(p, depth_stamps, frame_stamps), ds.gt_poses)["rmse_m"]  # noqa: E731
            out = {"data": ds.name, "frames": len(depths), "start": args.start, "stride": args.stride,
                   "noise_share": level, "noise_sigma": cfg.data.noise_sigma, "seed": seed, "ours_ate_cm": score(np.stack(poses)), "tracking_failures": failures}
            if args.peer:
                peer, _ = _small_gicp_track(depths, repeated, intr, T0_matrix, tcfg.stride, tcfg.k, 0.05, 0.1, 2)
                out["small_gicp_ate_cm"] = score(peer)
            print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
