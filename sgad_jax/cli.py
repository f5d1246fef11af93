"""Command line: ``sgad-jax run [--config PRESET_OR_PATH] [--data PATH] [--out DIR] [--mesh] ...``;
on a finished run: ``sgad-jax mesh RUN_DIR``, ``sgad-jax eval-mesh RUN_DIR --gt-mesh PLY``,
``sgad-jax view RUN_DIR [--port P] [--host H]``.

User mistakes (bad paths, unknown layouts, unreadable images, bad overrides) print one line naming
the file and the problem, and exit with status 2; nothing computed before the error is lost.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys

from sgad_jax.config import ConfigError, apply_overrides, load_preset
from sgad_jax.io.base import DatasetError


DEFAULT_CACHE = "~/.cache/sgad_jax/xla"


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="sgad-jax", description="SGAD-SLAM in JAX: RGB-D tracking and mapping.")
    sub = p.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run", help="run SLAM on a dataset folder (or the built-in synthetic scene)")
    r.add_argument("--config", default=None, help="preset name (demo, tum, replica, 7scenes, scannet, scannetpp) or a .py file; default: picked from the data layout")
    r.add_argument("--data", default=None, help="dataset folder; omit for the built-in synthetic scene")
    r.add_argument("--out", default="runs/latest", help="output folder (default: runs/latest)")
    r.add_argument("--start", type=int, default=None, help="first frame")
    r.add_argument("--stride", type=int, default=None, help="take every N-th frame")
    r.add_argument("--max-frames", type=int, default=None, help="at most N frames")
    r.add_argument("--track-only", action="store_true", help="run the geometry branch (tracking) alone")
    r.add_argument("--save-renders", action="store_true", help="write every frame's rendered colour and depth to OUT/renders/")
    r.add_argument("--mesh", action="store_true", help="after the run, fuse the renders into OUT/mesh.ply (implies --save-renders; settings: --set mesh.voxel=...)")
    r.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE", help="override a config field, e.g. --set track.stride=10 (repeatable)")
    r.add_argument("--devices", type=int, default=None, help="map on N devices of this host (on CPU: N host devices); default: all (CPU: 1)")
    r.add_argument("--checkpoint-every", type=int, default=25, metavar="N", help="checkpoint the run every N frames in OUT/checkpoints (0: never; default 25)")
    r.add_argument("--resume", action="store_true", help="continue the run in --out from its newest checkpoint (same config and data)")
    r.add_argument("--coordinator", default=None, metavar="HOST:PORT", help="multi-process run: the coordinator's address (or $JAX_COORDINATOR_ADDRESS)")
    r.add_argument("--num-processes", type=int, default=None, help="multi-process run: number of processes (or $JAX_NUM_PROCESSES)")
    r.add_argument("--process-id", type=int, default=None, help="multi-process run: this process's id (or $JAX_PROCESS_ID)")
    r.add_argument("--quiet", action="store_true", help="no progress bar")
    r.add_argument(
        "--compile-cache", default=None, metavar="DIR",
        help="keep compiled programs in DIR for later runs ('off': do not); default: $JAX_COMPILATION_CACHE_DIR, else " + DEFAULT_CACHE,
    )
    m = sub.add_parser("mesh", help="fuse a finished run's renders (--save-renders) into RUN_DIR/mesh.ply (TSDF + marching cubes)")
    m.add_argument("run_dir", metavar="RUN_DIR")
    m.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE", help="override a mesh setting, e.g. --set mesh.voxel=0.02 (metres at full resolution)")
    m.add_argument("--compile-cache", default=None, metavar="DIR", help="as for run")
    e = sub.add_parser("eval-mesh", help="score RUN_DIR/mesh.ply against a ground-truth mesh; merges the scores into RUN_DIR/eval.json")
    e.add_argument("run_dir", metavar="RUN_DIR")
    e.add_argument("--gt-mesh", required=True, metavar="PLY", help="ground-truth mesh (PLY), in the world frame of the run's poses")
    e.add_argument("--mesh", default=None, metavar="PLY", help="the mesh to score (default: RUN_DIR/mesh.ply)")
    e.add_argument("--data", default=None, help="the run's dataset folder, if it moved (its measured depth culls the ground truth)")
    e.add_argument("--threshold", type=float, default=0.01, help="metres, for precision / recall / F1 (default 0.01)")
    e.add_argument("--samples", type=int, default=200_000, help="points sampled on each surface (default 200000)")
    e.add_argument("--views", type=int, default=100, help="novel views for depth L1 (default 100)")
    e.add_argument("--band", type=float, default=0.05, help="metres around the observed surface that count as seen (default 0.05)")
    e.add_argument("--seed", type=int, default=0)
    v = sub.add_parser("view", help="serve a finished run (cameras, trajectory, Gaussians, mesh, renders) in a web viewer (viser)")
    v.add_argument("run_dir", metavar="RUN_DIR")
    v.add_argument("--port", type=int, default=8080)
    v.add_argument("--host", default="0.0.0.0", help="interface to listen on (default: all, for a browser on another machine)")
    v.add_argument("--max-splats", type=int, default=300_000, help="at most this many Gaussians shown (subsampled; default 300000)")
    return p


def _mesh_config(run_dir, overrides):
    """The run's saved config (defaults without one) with ``mesh.*`` overrides applied."""
    from sgad_jax.config import SLAMConfig
    from sgad_jax.io.run import run_config

    cfg = run_config(run_dir) or SLAMConfig()
    for item in overrides:
        if not item.strip().startswith("mesh."):
            raise ConfigError(f"--set {item}: only mesh.* settings apply to a finished run")
    return apply_overrides(cfg, list(overrides))


def _make_mesh(run_dir, cfg) -> dict:
    from sgad_jax.mesh import mesh_run

    return mesh_run(run_dir, cfg.mesh, cfg.data.downscale, log=lambda line: print(f"sgad-jax: {line}", file=sys.stderr))


def _other_command(args) -> int:
    """``mesh``, ``eval-mesh`` and ``view``: work on a finished run's folder."""
    try:
        if args.command == "view":
            from sgad_jax import viewer

            viewer.serve(args.run_dir, host=args.host, port=args.port, max_splats=args.max_splats)
            return 0
        if args.command == "mesh":
            use_compile_cache(args.compile_cache)
            print(json.dumps(_make_mesh(args.run_dir, _mesh_config(args.run_dir, args.overrides))))
        else:
            from sgad_jax.eval.mesh import eval_mesh_run

            scores = eval_mesh_run(
                args.run_dir, args.gt_mesh, data=args.data, mesh=args.mesh, threshold=args.threshold,
                samples=args.samples, views=args.views, band=args.band, seed=args.seed,
            )
            print(json.dumps({k: v for k, v in scores.items() if k.startswith("mesh_") and not isinstance(v, str)}))
            print(f"wrote {args.run_dir}/eval.json", file=sys.stderr)
    except (ConfigError, DatasetError) as err:
        print(f"sgad-jax: error: {err}", file=sys.stderr)
        return 2
    return 0


def use_compile_cache(choice: str | None) -> None:
    """Point JAX's persistent compilation cache at ``choice`` (or the environment's, or the
    default folder; ``"off"``: no cache): a later run with the same shapes and config loads its
    programs instead of compiling them again (tracking ~10 s, mapping ~20 s on a 2-core CPU)."""
    import jax

    if choice is None:
        choice = os.environ.get("JAX_COMPILATION_CACHE_DIR") or DEFAULT_CACHE
    if choice.lower() == "off":
        jax.config.update("jax_enable_compilation_cache", False)
    else:
        jax.config.update("jax_compilation_cache_dir", os.path.expanduser(choice))


_PRESET_FOR_LAYOUT = {"tum": "tum", "replica": "replica", "7scenes": "7scenes", "scannet": "scannet", "scannetpp": "scannetpp", "generic": "tum", "synthetic": "demo"}


def resolve_config(preset=None, data=None, *, start=None, stride=None, max_frames=None, overrides=()):
    """The config of a run: the preset (by default the one for the data's layout, or the demo),
    the data folder and frame selection, then the dotted overrides."""
    from sgad_jax.io.datasets import detect_layout

    if preset is None:
        preset = "demo" if not data else _PRESET_FOR_LAYOUT[detect_layout(data)]
    cfg = load_preset(preset)
    selection = {"path": data, "start": start, "stride": stride, "max_frames": max_frames}
    cfg = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, **{k: v for k, v in selection.items() if v is not None}))
    return apply_overrides(cfg, list(overrides))


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.command != "run":
        return _other_command(args)
    try:
        from sgad_jax import distributed  # before anything starts JAX's backends

        use_compile_cache(args.compile_cache)

        if args.devices is not None:
            distributed.use_cpu_devices(args.devices)
        if args.coordinator or args.num_processes or args.process_id is not None or "JAX_COORDINATOR_ADDRESS" in os.environ:
            distributed.initialize(args.coordinator, args.num_processes, args.process_id)
        cfg = resolve_config(
            args.config, args.data, start=args.start, stride=args.stride, max_frames=args.max_frames, overrides=args.overrides
        )
        from sgad_jax import pipeline

        if args.mesh and args.track_only:
            raise ConfigError("--mesh fuses the renders of the mapping branch: it cannot go with --track-only")
        result = pipeline.run(
            cfg, args.out, track_only=args.track_only, save_renders=args.save_renders or args.mesh, progress=not args.quiet,
            resume=args.resume, checkpoint_every=args.checkpoint_every, devices=args.devices,
        )
        import jax

        if args.mesh and jax.process_index() == 0:
            info = _make_mesh(args.out, cfg)
            print(f"wrote {info['mesh']} ({info['vertices']} vertices, {info['faces']} faces, {100 * info['voxel_m']:.3g} cm voxels)", file=sys.stderr)
    except (ConfigError, DatasetError) as err:
        print(f"sgad-jax: error: {err}", file=sys.stderr)
        return 2
    m = result.metrics
    keys = ("frames", "ate_rmse_cm", "ate_mean_cm", "track_ms_median", "psnr", "ssim", "ms_ssim", "lpips", "depth_l1_cm", "map_s_per_frame", "compile_s", "peak_rss_mb")
    summary = {k: m[k] for k in keys if k in m}
    import jax

    if jax.process_index() == 0:
        print(json.dumps(summary))
        print(f"wrote {args.out}/trajectory.txt and {args.out}/metrics.json", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
