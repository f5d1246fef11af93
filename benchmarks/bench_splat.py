"""Splatting and mapping speed on real frames (no CPU peer exists: every other differentiable
Gaussian rasteriser needs CUDA).

Times, each as the median of ``--repeats`` calls after one warm-up call whose time is reported as
compile time:

* the own-view fast path (a frame's Gaussians into its own view) at 640x480 and 320x240, forward
  and forward + backward (gradient of a scalar loss with respect to every Gaussian attribute);
* the neighbour path: the current frame's Gaussians and 2 neighbours' into one 640x480 view
  (the general path for all three: binned afresh in every call, 2 layers), forward + backward;
* the same three frames composed as the pipeline renders a frame's view (``render_frame``: the
  current frame's Gaussians by the own-pose path over its 2 neighbours', binned in one layer),
  forward + backward with respect to all three frames' Gaussians;
* the scene renderer (``render_scene``, priority compositing): 8 frames' Gaussians (the three
  read, repeated) into one 640x480 view, forward;
* one full ``map_frame`` at 640x480 and 320x240 with 2 neighbour views, with the data's preset's
  iterations and colour fit (``--iterations``, ``--colour-fit`` to change them).

Usage::

    python benchmarks/bench_splat.py [--data ../shared/data/tum_fr1_xyz] [--repeats 5] [--keep-freed-memory]

Prints one JSON object with ``own_640x480_fwd_ms``, ``own_640x480_fwd_bwd_ms``,
``own_320x240_fwd_ms``, ``own_320x240_fwd_bwd_ms``, ``neighbours2_640x480_fwd_ms``,
``neighbours2_640x480_fwd_bwd_ms``, ``neighbours2_pipeline_640x480_fwd_ms``,
``neighbours2_pipeline_640x480_fwd_bwd_ms``, ``scene_640x480_k8_fwd_ms``, ``map_frame_640x480_s``, ``map_frame_320x240_s``,
``map_s_per_input_frame_640x480`` (``map_frame_640x480_s`` over the data's default preset's ``map.every``), ``compile_s``
(total; ``compile_s_by_entry`` each) and the settings. Without ``--data`` (or when the folder is missing) the built-in synthetic scene is used.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time

import numpy as np


def _timed(fn, *args, repeats: int) -> tuple[float, float]:
    """(compile + first call seconds, median seconds of ``repeats`` further calls)."""
    import jax

    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return first, float(np.median(times))


def keep_freed_memory() -> bool:
    """Make glibc's ``malloc`` keep what the process frees (one arena, no ``mmap`` for large blocks,
    no trimming); True if it applied. The same as starting with ``MALLOC_ARENA_MAX=1
    MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=2147483647``.

    XLA:CPU allocates a call's scratch afresh, and glibc maps such blocks from the system and
    unmaps them when freed, so each call touches its scratch as new pages. Keeping them speeds up
    the neighbour path's gradient, but slows ``map_frame`` and tracking (one arena for all
    threads), so ``sgad-jax run`` keeps malloc's settings (docs/method.md).
    """
    import ctypes
    import ctypes.util

    try:
        mallopt = ctypes.CDLL(ctypes.util.find_library("c")).mallopt
    except (OSError, TypeError, AttributeError):  # not glibc
        return False
    m_trim_threshold, m_mmap_max, m_arena_max = -1, -4, -8  # <malloc.h>
    return all(mallopt(opt, value) == 1 for opt, value in ((m_arena_max, 1), (m_mmap_max, 0), (m_trim_threshold, 2**31 - 1)))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", default=os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "tum_fr1_xyz"))
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--iterations", type=int, default=None, help="Adam iterations a mapped frame (default: the data's preset's)")
    p.add_argument("--colour-fit", type=int, default=None, help="colour-fit steps after them (default: the preset's)")
    p.add_argument("--keep-freed-memory", action="store_true", help="tune glibc malloc to keep freed memory (see keep_freed_memory)")
    args = p.parse_args(argv)
    kept = keep_freed_memory() if args.keep_freed_memory else False  # before JAX starts its threads

    import jax
    import jax.numpy as jnp

    from sgad_jax import lie, scene, slam, splat
    from sgad_jax import mapping
    from sgad_jax.cli import resolve_config
    from sgad_jax.config import DataConfig
    from sgad_jax.io.datasets import open_dataset
    from sgad_jax.types import make_frame

    path = args.data if os.path.isdir(args.data) else ""
    preset = resolve_config(None, path or None).map
    cfg = dataclasses.replace(
        preset,
        iterations=preset.iterations if args.iterations is None else args.iterations,
        colour_fit=preset.colour_fit if args.colour_fit is None else args.colour_fit,
    )
    out: dict = {
        "data": path or "synthetic", "repeats": args.repeats, "iterations": cfg.iterations, "colour_fit": cfg.colour_fit, "device": jax.devices()[0].device_kind,
        "keep_freed_memory": kept,
    }
    compile_s: dict[str, float] = {}

    def load(downscale: int):
        ds = open_dataset(DataConfig(path=path, downscale=downscale, max_frames=3))
        frames = [make_frame(ds[i].rgb, ds[i].depth, ds[i].depth_filled) for i in range(3)]
        poses = [lie.from_matrix(m) if np.isfinite(m).all() else lie.identity() for m in ds.gt_poses[:3]]
        return ds.intrinsics, frames, poses

    def loss(r: splat.Render):
        return jnp.sum(r.rgb) + jnp.sum(r.depth) + jnp.sum(r.alpha)

    for downscale in (1, 2):
        intr, frames, poses = load(downscale)
        size = f"{intr.width}x{intr.height}"
        g = mapping.init_gaussians(frames[2], intr)
        own_fwd = jax.jit(lambda g: splat.render_own(g, poses[2], intr))
        own_bwd = jax.jit(jax.grad(lambda g: loss(splat.render_own(g, poses[2], intr))))
        for key, fn in ((f"own_{size}_fwd", own_fwd), (f"own_{size}_fwd_bwd", own_bwd)):
            compile_s[key], t = _timed(fn, g, repeats=args.repeats)
            out[key + "_ms"] = 1000 * t
        if downscale == 1:
            stack = lambda *xs: jnp.stack(xs)  # noqa: E731
            gs = jax.tree.map(stack, *[mapping.init_gaussians(f, intr) for f in frames])
            ps = jax.tree.map(stack, *poses)
            nb_fwd = jax.jit(lambda gs: splat.render(gs, ps, poses[2], intr))
            nb_bwd = jax.jit(jax.grad(lambda gs: loss(splat.render(gs, ps, poses[2], intr))))
            for key, fn in ((f"neighbours2_{size}_fwd", nb_fwd), (f"neighbours2_{size}_fwd_bwd", nb_bwd)):
                compile_s[key], t = _timed(fn, gs, repeats=args.repeats)
                out[key + "_ms"] = 1000 * t
            # The scene renderer: k = 8 frames (the three read, repeated at their poses) into a view.
            k8 = jax.tree.map(lambda x: jnp.concatenate([x, x, x[:2]]), gs)
            p8 = jax.tree.map(lambda x: jnp.concatenate([x, x, x[:2]]), ps)
            key = f"scene_{size}_k8_fwd"
            compile_s[key], t = _timed(lambda g: scene.render_scene(g, p8, poses[2], intr), k8, repeats=args.repeats)
            out[key + "_ms"] = 1000 * t
            nb_poses = jax.tree.map(stack, poses[1], poses[0])

            def frame_view(gs):  # the current frame (index 2) over its neighbours
                nb = jax.tree.map(lambda x: x[:2][::-1], gs)
                return mapping.render_frame(jax.tree.map(lambda x: x[2], gs), poses[2], splat.render(nb, nb_poses, poses[2], intr, layers=1), intr)

            pipe_fwd = jax.jit(frame_view)
            pipe_bwd = jax.jit(jax.grad(lambda gs: loss(frame_view(gs))))
            for key, fn in ((f"neighbours2_pipeline_{size}_fwd", pipe_fwd), (f"neighbours2_pipeline_{size}_fwd_bwd", pipe_bwd)):
                compile_s[key], t = _timed(fn, gs, repeats=args.repeats)
                out[key + "_ms"] = 1000 * t
        # one mapped frame
        stack = lambda *xs: jnp.stack(xs)  # noqa: E731
        nb = jax.tree.map(stack, frames[1], frames[0])
        nb_poses = jax.tree.map(stack, poses[1], poses[0])
        nb_gs = jax.tree.map(stack, *[mapping.init_gaussians(f, intr) for f in (frames[1], frames[0])])
        step = jax.jit(lambda f, p, g, n, np_: slam.map_step(cfg, f, p, g, n, np_, jnp.ones(2, bool), intr))
        key = f"map_frame_{size}"
        compile_s[key], t = _timed(step, frames[2], poses[2], nb_gs, nb, nb_poses, repeats=max(1, args.repeats // 2))
        out[key + "_s"] = t
        if downscale == 1:  # per input frame at the data's default preset's keyframe spacing
            out["map_every"] = cfg.every
            out[f"map_s_per_input_frame_{size}"] = t / out["map_every"]
    out["compile_s"] = sum(compile_s.values())
    out["compile_s_by_entry"] = compile_s
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
