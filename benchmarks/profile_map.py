"""Where the time of one mapped frame goes, part by part, beside a floor for each part.

One TUM frame at 640x480 with its 2 neighbours, as ``sgad-jax run`` maps it (``slam.map_step``,
``map.iterations`` steps, 70% of them on the own view, then ``map.colour_fit``). Each part is
jitted alone and timed as the median of ``--repeats`` calls after a warm-up call: the own-view
step (render forward and backward, loss forward and backward, the whole step), the neighbour-view
step, the Adam update, the neighbours' background render, the colour fit, then the host work after
mapping (image metrics, PNG and npz writes). ``step_share_s`` is each step's time times the
number of iterations that take it.

The compute floor of a jitted part is its FLOPs (XLA's cost analysis) over the machine's measured
peak (a large float32 matrix product): the time the part would take if its arithmetic ran at the
speed of a matrix product. ``mbytes`` is XLA's count of bytes accessed by the part's operations
(before caches: an upper bound on memory traffic), for reading which parts move data rather than
compute.

Parts jitted alone fuse differently from the same code inside the whole step. ``--trace DIR``
also runs the whole ``map_step`` once under ``jax.profiler.trace`` and charges each of its
compiled operations (XLA:CPU thunks) to the innermost ``sgad_jax`` source line it came from (the
compiled HLO's stack frames): ``trace_ms`` lists the lines that took the most time.

Usage::

    python benchmarks/profile_map.py [--data ../shared/data/tum_fr1_xyz] [--repeats 5] [--trace DIR]

Prints one JSON object: ``parts`` (``{name: {"ms", "floor_ms", "gflop", "mbytes"}}``),
``map_frame_640x480_s`` (the whole ``map_step``), ``peak_gflops``, the device, and with
``--trace`` ``trace_ms`` (``{"file.py:function:line": ms}``, the 25 largest).
"""

from __future__ import annotations

import argparse
import collections
import glob
import gzip
import json
import os
import re
import sys
import tempfile
import time

import numpy as np


def _median_ms(fn, repeats: int) -> float:
    import jax

    jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return 1000.0 * float(np.median(times))


def _hlo_table(lines: list[str], name: str) -> dict[int, str]:
    """One of the compiled HLO text's id tables (``FileNames``, ``StackFrames``, ...)."""
    if name not in lines:
        return {}
    out = {}
    for line in lines[lines.index(name) + 1 :]:
        m = re.match(r"^(\d+) (.*)$", line)
        if not m:
            break
        out[int(m.group(1))] = m.group(2)
    return out


def _time_by_source_line(hlo: str, trace_dir: str, top: int = 25) -> dict[str, float]:
    """Milliseconds of the traced operations, summed by the innermost ``sgad_jax`` source line of
    each (an operation without one keeps its own name)."""
    lines = hlo.split("\n")
    files = {k: v.strip('"') for k, v in _hlo_table(lines, "FileNames").items()}
    funcs = {k: v.strip('"') for k, v in _hlo_table(lines, "FunctionNames").items()}
    ours = {}  # file location id -> "file.py:function:line", for locations inside sgad_jax
    for k, v in _hlo_table(lines, "FileLocations").items():
        m = re.search(r"file_name_id=(\d+) function_name_id=(\d+) line=(\d+)", v)
        if m and "sgad_jax" in files.get(int(m.group(1)), ""):
            ours[k] = f"{os.path.basename(files[int(m.group(1))])}:{funcs.get(int(m.group(2)), '?')}:{m.group(3)}"
    frames = {}
    for k, v in _hlo_table(lines, "StackFrames").items():
        m = re.search(r"file_location_id=(\d+) parent_frame_id=(\d+)", v)
        if m:
            frames[k] = (int(m.group(1)), int(m.group(2)))
    op_frame = {m.group(1): int(m.group(2)) for m in re.finditer(r"\n\s*%?([\w.\-]+) = [^\n]*?stack_frame_id=(\d+)", hlo)}

    def source(op: str) -> str:
        frame, seen = op_frame.get(op), set()
        while frame in frames and frame not in seen:  # innermost frame first
            seen.add(frame)
            loc, frame = frames[frame]
            if loc in ours:
                return ours[loc]
        return op

    totals: dict[str, float] = collections.defaultdict(float)
    for path in glob.glob(os.path.join(trace_dir, "**", "*.trace.json.gz"), recursive=True):
        with gzip.open(path) as f:
            events = json.load(f).get("traceEvents", [])
        for e in events:  # complete events; Python frames ("$...") and the executor's spans skipped
            if e.get("ph") == "X" and not e.get("name", "$").startswith(("$", "ThunkExecutor")):
                totals[source(e["name"])] += e.get("dur", 0.0) / 1000.0
    return {k: round(v, 1) for k, v in sorted(totals.items(), key=lambda kv: -kv[1])[:top]}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", default=os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "tum_fr1_xyz"))
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--trace", metavar="DIR", help="also trace the whole step once into DIR and time it by source line")
    args = p.parse_args(argv)

    import cv2
    import jax
    import jax.numpy as jnp
    import optax

    from sgad_jax import lie, losses, slam, splat
    from sgad_jax import mapping
    from sgad_jax.config import DataConfig, MapConfig
    from sgad_jax.eval import image, lpips_weights
    from sgad_jax.io.datasets import open_dataset
    from sgad_jax.types import make_frame

    path = args.data if os.path.isdir(args.data) else ""
    ds = open_dataset(DataConfig(path=path, max_frames=3))
    intr = ds.intrinsics
    frames = [make_frame(ds[i].rgb, ds[i].depth, ds[i].depth_filled) for i in range(3)]
    poses = [lie.from_matrix(m) if np.isfinite(m).all() else lie.identity() for m in ds.gt_poses[:3]]
    cfg = MapConfig()
    stack = lambda *xs: jnp.stack(xs)  # noqa: E731
    nb = jax.tree.map(stack, frames[1], frames[0])
    nb_poses = jax.tree.map(stack, poses[1], poses[0])
    nb_gs = jax.tree.map(stack, *[mapping.init_gaussians(f, intr) for f in (frames[1], frames[0])])
    present = jnp.ones(2, bool)
    frame, pose = frames[2], poses[2]

    # Machine floors: a float32 matrix product and a copy, both large.
    a = jnp.ones((2048, 2048), jnp.float32)
    mm = jax.jit(lambda a: a @ a)
    peak = 2 * 2048**3 / (_median_ms(lambda: mm(a), args.repeats) / 1000) / 1e9

    parts: dict[str, dict] = {}

    def part(name, fn, *xs):
        compiled = jax.jit(fn).lower(*xs).compile()
        cost = compiled.cost_analysis()
        cost = cost[0] if isinstance(cost, list) else cost
        flops, nbytes = float(cost.get("flops", 0.0)), float(cost.get("bytes accessed", 0.0))
        ms = _median_ms(lambda: compiled(*xs), args.repeats)
        floor = 1000 * flops / (peak * 1e9)
        parts[name] = {"ms": round(ms, 2), "floor_ms": round(floor, 2), "gflop": round(flops / 1e9, 3), "mbytes": round(nbytes / 1e6, 1)}

    background = jax.jit(lambda g, p: splat.render(g, p, pose, intr, layers=1))(nb_gs, nb_poses)
    views = mapping.Views(
        rgb=jnp.concatenate([frame.rgb[None], nb.rgb]), depth=jnp.concatenate([frame.depth[None], nb.depth]),
        valid=jnp.concatenate([frame.valid[None], nb.valid]),
        pose=jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), pose, nb_poses), present=jnp.ones(3, bool),
    )
    g0 = mapping.init_gaussians(frame, intr)
    targets = jax.vmap(losses.ssim_target)(views.rgb)
    own = splat.render_own(g0, pose, intr)
    target0 = jax.tree.map(lambda x: x[0], targets)

    part("background_render", lambda g, p: splat.render(g, p, pose, intr, layers=1), nb_gs, nb_poses)
    part("own_render_fwd", lambda g: splat.render_own(g, pose, intr), g0)
    part("own_render_fwd_bwd", jax.grad(lambda g: jnp.sum(splat.render_own(g, pose, intr).rgb)), g0)
    loss_vg = jax.value_and_grad(
        lambda rgb, d: losses.mapping_loss(rgb, d, target0, frame.depth, frame.valid, jnp.ones_like(frame.depth)), argnums=(0, 1)
    )
    part("loss_fwd_bwd", loss_vg, own.rgb, own.depth)
    nb_pose = jax.tree.map(lambda x: x[0], nb_poses)
    part("neighbour_render_fwd_bwd", jax.grad(lambda g: jnp.sum(splat.render(mapping._one(g), mapping._one(pose), nb_pose, intr, layers=1).rgb)), g0)
    for k, name in ((0, "own_view_step"), (1, "neighbour_view_step")):
        part(name, lambda g, k=k: jax.value_and_grad(mapping.view_loss, argnums=1)(cfg, g, pose, views, k, intr, background, targets=targets), g0)
    opt = mapping.optimizer(cfg)
    part("adam_update", lambda g, s: optax.apply_updates(g, opt.update(g, s, g)[0]), g0, opt.init(g0))
    part("frame_render", lambda g: mapping.render_frame(g, pose, background, intr), g0)
    if cfg.colour_fit:
        part("colour_fit", lambda g: mapping.fit_colours(g, pose, frame.rgb, intr, background, cfg.colour_fit).rgb, g0)

    schedule = mapping.view_schedule(cfg, 3)
    own_steps = int((schedule == 0).sum())
    parts["own_view_step"]["step_share_s"] = round(own_steps * parts["own_view_step"]["ms"] / 1000, 2)
    parts["neighbour_view_step"]["step_share_s"] = round((cfg.iterations - own_steps) * parts["neighbour_view_step"]["ms"] / 1000, 2)

    step = jax.jit(lambda f, p, g, n, q: slam.map_step(cfg, f, p, g, n, q, present, intr))
    map_s = _median_ms(lambda: step(frame, pose, nb_gs, nb, nb_poses), max(1, args.repeats // 2)) / 1000
    trace_ms = None
    if args.trace:
        with jax.profiler.trace(args.trace):
            jax.block_until_ready(step(frame, pose, nb_gs, nb, nb_poses))
        hlo = step.lower(frame, pose, nb_gs, nb, nb_poses).compile().as_text()
        trace_ms = _time_by_source_line(hlo, args.trace)

    # Host work after mapping a frame.
    rgb, target = np.clip(np.asarray(own.rgb), 0, 1), np.asarray(frame.rgb)
    weights = lpips_weights.load_lpips_weights()
    host = {
        "psnr": lambda: image.psnr(rgb, target, np.asarray(frame.valid)),
        "ssim": lambda: image.ssim(rgb, target),
        "ms_ssim": lambda: image.ms_ssim(rgb, target),
        "lpips": (lambda: image.lpips(rgb, target, weights)) if weights is not None else None,
        "png_writes": lambda: (cv2.imencode(".png", (rgb * 255).astype(np.uint8)), cv2.imencode(".png", np.asarray(own.depth * 1000, np.uint16))),
    }
    with tempfile.TemporaryDirectory() as tmp:
        host["npz_write"] = lambda: np.savez(os.path.join(tmp, "g.npz"), **{k: np.asarray(getattr(g0, k)) for k in ("rgb", "log_radius", "opacity_logit", "offset", "depth")})
        for name, fn in host.items():
            if fn is not None:
                parts["host_" + name] = {"ms": round(_median_ms(fn, args.repeats), 2)}

    out = {
        "data": path or "synthetic", "size": f"{intr.width}x{intr.height}", "iterations": cfg.iterations, "own_view_steps": own_steps,
        "device": jax.devices()[0].device_kind, "peak_gflops": round(peak, 1),
        "map_frame_640x480_s" if (intr.width, intr.height) == (640, 480) else f"map_frame_{intr.width}x{intr.height}_s": round(map_s, 3),
        "parts": parts,
    }
    if trace_ms is not None:
        out["trace_ms"] = trace_ms
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
