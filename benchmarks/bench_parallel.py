"""Mapping throughput across devices: the same tracked frames mapped with 1, 2 and 4 devices.

Each device count runs in a fresh process (XLA:CPU fixes its device count when it starts: on CPU
the devices are ``jax_num_cpu_devices`` host devices sharing the machine's cores). Frames are mapped
at their ground-truth poses in batches of one frame per device through
:class:`sgad_jax.distributed.BatchMapper`, the path of ``sgad-jax run --devices N``; after one
batch to compile and warm up, the time of mapping ``--frames`` frames gives frames per second.

Usage::

    python benchmarks/bench_parallel.py [--data ../shared/data/tum_fr1_xyz] [--frames 8]
                                        [--downscale 2] [--iterations 100] [--devices 1,2,4]

Prints one JSON object with ``fps_N`` for each device count N (frames per second), ``peak_rss_mb``
(the largest of the runs), ``compile_s_N`` per device count, the settings and the device kind.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time


def worker(args) -> dict:
    from sgad_jax import distributed

    distributed.use_cpu_devices(args.worker)
    import jax
    import numpy as np

    from sgad_jax import lie
    from sgad_jax.config import DataConfig, MapConfig
    from sgad_jax.io.datasets import open_dataset
    from sgad_jax.mapping import init_gaussians
    from sgad_jax.types import host_frame

    path = args.data if os.path.isdir(args.data) else ""
    n = args.worker
    ds = open_dataset(DataConfig(path=path, downscale=args.downscale, max_frames=args.frames + n + 2))
    frames = [host_frame(ds[i]) for i in range(len(ds))]
    # the neighbours' Gaussians as first initialised: the same work as mapped ones
    gaussians = [jax.tree.map(np.asarray, init_gaussians(f, ds.intrinsics)) for f in frames]
    poses = [jax.tree.map(np.asarray, lie.from_matrix(m) if np.isfinite(m).all() else lie.identity()) for m in ds.gt_poses]
    mapper = distributed.BatchMapper(MapConfig(iterations=args.iterations), ds.intrinsics, distributed.frames_mesh(n))
    stack = lambda *xs: np.stack(xs)  # noqa: E731

    def batch(first: int):
        rows = []
        for i in range(first, first + n):
            nb = [i - 1, i - 2]
            rows.append((frames[i], poses[i], *(jax.tree.map(stack, *[xs[k] for k in nb]) for xs in (gaussians, frames, poses)), np.ones(2, bool)))
        return [jax.tree.map(stack, *col) for col in zip(*rows)]

    t0 = time.perf_counter()
    mapper(*batch(2))  # compile and warm up
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    for first in range(2 + n, 2 + n + args.frames, n):
        mapper(*batch(first))
    seconds = time.perf_counter() - t0
    return {
        "devices": len(jax.devices()),
        "device": jax.devices()[0].device_kind,
        "fps": args.frames / seconds,
        "compile_s": compile_s,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", default=os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "tum_fr1_xyz"))
    p.add_argument("--frames", type=int, default=8, help="frames timed (a multiple of each device count)")
    p.add_argument("--downscale", type=int, default=2)
    p.add_argument("--iterations", type=int, default=100)
    p.add_argument("--devices", default="1,2,4", help="device counts to time, comma-separated")
    p.add_argument("--worker", type=int, default=0, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(args)))
        return 0
    counts = [int(c) for c in args.devices.split(",")]
    if args.frames % math.lcm(*counts):
        p.error(f"--frames must be a multiple of each device count ({args.devices})")
    out: dict = {"data": args.data if os.path.isdir(args.data) else "synthetic", "frames": args.frames, "downscale": args.downscale, "iterations": args.iterations}
    peak = 0.0
    for n in counts:
        cmd = [sys.executable, __file__, "--worker", str(n), "--data", args.data, "--frames", str(args.frames), "--downscale", str(args.downscale), "--iterations", str(args.iterations)]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            sys.stderr.write(proc.stderr)
            return 1
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        if r["devices"] != n:
            sys.stderr.write(f"bench_parallel: asked for {n} devices, the worker had {r['devices']}\n")
            return 1
        out[f"fps_{n}"] = r["fps"]
        out[f"compile_s_{n}"] = r["compile_s"]
        out["device"] = r["device"]
        peak = max(peak, r["peak_rss_mb"])
    out["peak_rss_mb"] = peak
    out["cpu_cores"] = os.cpu_count()
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
