"""Command line: ``sgad-jax run [--config PRESET_OR_PATH] [--data PATH] [--out DIR] ...``, and for
a finished run's folder ``sgad-jax export RUN_DIR`` (3DGS ``.ply``), ``sgad-jax eval RUN_DIR``
(metrics recomputed from its files), ``sgad-jax plots RUN_DIR`` (pictures), ``sgad-jax mesh
RUN_DIR`` (TSDF mesh of the renders), ``sgad-jax eval-mesh RUN_DIR --gt-mesh PLY`` and
``sgad-jax view RUN_DIR`` (web viewer).

User mistakes (bad paths, unknown layouts, unreadable images, bad overrides) print one line naming
the file and the problem, and exit with status 2; nothing computed before the error is lost.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys

from sgad_jax.config import ConfigError, apply_overrides, load_preset
from sgad_jax.io.base import DatasetError, RunInterrupted


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
    r.add_argument("--holdout-every", type=int, default=0, metavar="N", help="hold frames i > 0, i %% N == 0 out of mapping and score them from the scene afterwards (nvs_* metrics)")
    r.add_argument("--finetune", type=int, default=0, metavar="ITERS", help="refine the merged map for ITERS steps after the sequence, then score the held-out views again")
    r.add_argument("--devices", type=int, default=None, help="map on N devices of this host (on CPU: N host devices); default: all (CPU: 1)")
    r.add_argument("--checkpoint-every", type=int, default=25, metavar="N", help="checkpoint the run every N frames in OUT/checkpoints (0: never; default 25)")
    r.add_argument("--on-bad-frame", choices=("stop", "skip"), default="stop", help="a frame that cannot be used (unreadable, truncated or missing file, no valid depth, NaN depth, bad timestamp): stop (exit status 2, resumable once fixed; default) or skip it (listed in metrics.json as skipped_frames)")
    r.add_argument("--resume", action="store_true", help="continue the run in --out from its newest checkpoint (same config and data); a Ctrl-C stops a run after the frame in hand and checkpoints it there")
    r.add_argument("--coordinator", default=None, metavar="HOST:PORT", help="multi-process run: the coordinator's address (or $JAX_COORDINATOR_ADDRESS)")
    r.add_argument("--num-processes", type=int, default=None, help="multi-process run: number of processes (or $JAX_NUM_PROCESSES)")
    r.add_argument("--process-id", type=int, default=None, help="multi-process run: this process's id (or $JAX_PROCESS_ID)")
    r.add_argument("--quiet", action="store_true", help="no progress bar")
    r.add_argument("--viewer", type=int, default=None, metavar="PORT", help="show the run live in a browser at http://HOST:PORT (viser; cameras, trajectory, measured points); after the run it serves the finished scene until Ctrl-C")
    r.add_argument("--viewer-host", default="0.0.0.0", help="interface for --viewer (default: all)")
    r.add_argument("--export-ply", action="store_true", help="after the run, write the merged Gaussians to OUT/gaussians.ply (as `sgad-jax export`)")
    r.add_argument("--plots", action="store_true", help="after the run, draw OUT/trajectory.png and OUT/plots/ (as `sgad-jax plots`)")
    r.add_argument(
        "--compile-cache", default=None, metavar="DIR",
        help="keep compiled programs in DIR for later runs ('off': do not); default: $JAX_COMPILATION_CACHE_DIR, else " + DEFAULT_CACHE,
    )
    _add_run_dir_commands(sub)
    return p


def _add_run_dir_commands(sub) -> None:
    """The subcommands that read a finished run's folder."""
    e = sub.add_parser("export", help="write a finished run's merged Gaussians as a 3D Gaussian Splatting .ply")
    e.add_argument("run_dir", metavar="RUN_DIR", help="the --out folder of a finished run")
    e.add_argument("--voxel", type=float, default=None, metavar="V", help="merge cell in metres, one Gaussian per cell (0: keep all); default: the run's export.voxel times its data.downscale")
    e.add_argument("--out", default=None, metavar="PLY", help="output file (default: RUN_DIR/gaussians.ply)")
    v = sub.add_parser("eval", help="recompute a finished run's metrics from its files; writes RUN_DIR/eval.json and report.md")
    v.add_argument("run_dir", metavar="RUN_DIR", help="the --out folder of a finished run")
    v.add_argument("--psnr-protocol", default=None, choices=("whole", "valid", "zeroed"), help="PSNR over the whole image, over valid-depth pixels, or with invalid pixels zeroed in both (default: the run's map.psnr_protocol)")
    v.add_argument("--frames", default=None, metavar="SEL", help="frames to score, as run indices: 'all' (default), 'A:B[:S]' (Python slice), or a comma list '0,5,9'")
    v.add_argument("--rerender", action="store_true", help="score the held-out views rendered again from the stored Gaussians (not their saved renders)")
    v.add_argument("--scene-frames", type=int, default=None, metavar="K", help="with --rerender: frames per view (default: the run's scene.frames)")
    v.add_argument("--composite", default=None, choices=("priority", "depth"), help="with --rerender: how a view's frames are composited (default: the run's scene.composite)")
    v.add_argument("--layers", type=int, default=None, metavar="L", help="with --rerender and depth compositing: Gaussians per pixel slot (default: the run's scene.layers)")
    q = sub.add_parser("plots", help="draw a finished run's trajectory and per-frame plots (RUN_DIR/trajectory.png, RUN_DIR/plots/)")
    q.add_argument("run_dir", metavar="RUN_DIR", help="the --out folder of a finished run")
    q.add_argument("--compare", type=int, default=3, metavar="N", help="side-by-side render / ground truth / error images of N frames (default 3; needs renders/)")
    m = sub.add_parser("mesh", help="fuse a finished run's renders (--save-renders) into RUN_DIR/mesh.ply (TSDF + marching cubes)")
    m.add_argument("run_dir", metavar="RUN_DIR")
    m.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE", help="override a mesh setting, e.g. --set mesh.voxel=0.02 (metres at full resolution)")
    m.add_argument("--compile-cache", default=None, metavar="DIR", help="as for run")
    em = sub.add_parser("eval-mesh", help="score RUN_DIR/mesh.ply against a ground-truth mesh; merges the scores into RUN_DIR/eval.json")
    em.add_argument("run_dir", metavar="RUN_DIR")
    em.add_argument("--gt-mesh", required=True, metavar="PLY", help="ground-truth mesh (PLY), in the world frame of the run's poses")
    em.add_argument("--mesh", default=None, metavar="PLY", help="the mesh to score (default: RUN_DIR/mesh.ply)")
    em.add_argument("--data", default=None, help="the run's dataset folder, if it moved (its measured depth culls the ground truth)")
    em.add_argument("--threshold", type=float, default=0.01, help="metres, for precision / recall / F1 (default 0.01)")
    em.add_argument("--samples", type=int, default=200_000, help="points sampled on each surface (default 200000)")
    em.add_argument("--views", type=int, default=100, help="novel views for depth L1 (default 100)")
    em.add_argument("--band", type=float, default=0.05, help="metres around the observed surface that count as seen (default 0.05)")
    em.add_argument("--seed", type=int, default=0)
    w = sub.add_parser("view", help="serve a finished run (cameras, trajectory, Gaussians, mesh, renders) in a web viewer (viser)")
    w.add_argument("run_dir", metavar="RUN_DIR")
    w.add_argument("--port", type=int, default=8080)
    w.add_argument("--host", default="0.0.0.0", help="interface to listen on (default: all, for a browser on another machine)")
    w.add_argument("--max-splats", type=int, default=300_000, help="at most this many Gaussians shown (subsampled; default 300000)")


def export_ply(run_dir, voxel=None, out=None) -> int:
    from sgad_jax.io.ply import export_run

    if voxel is not None and not (math.isfinite(voxel) and voxel >= 0):  # argparse takes any float, nan and -1 too
        raise ConfigError(f"--voxel {voxel:g}: must be a finite size >= 0 in metres (0: keep all)")
    path, info = export_run(run_dir, voxel, out)
    print(f"sgad-jax export: kept {info.kept} of {info.total} Gaussians ({info.frames} frames; {info.total - info.visible} transparent or behind their camera dropped; voxel {info.voxel:g} m) -> {path}", file=sys.stderr)
    return 0


def draw_plots(run_dir, compare: int = 3) -> int:
    from sgad_jax.io.plots import plot_run

    if compare < 0:
        raise ConfigError(f"--compare {compare}: must be >= 0 (frames to compare)")
    written, notes = plot_run(run_dir, compare=compare)
    for path in written:
        print(f"sgad-jax plots: wrote {path}", file=sys.stderr)
    for note in notes:
        print(f"sgad-jax plots: {note}", file=sys.stderr)
    return 0


def evaluate(run_dir, psnr_protocol=None, frames=None, rerender=False, scene_frames=None, layers=None, composite=None) -> int:
    from sgad_jax.eval.run_eval import evaluate_run

    result = evaluate_run(
        run_dir, psnr_protocol=psnr_protocol, frames=frames, rerender=rerender, scene_frames=scene_frames, layers=layers, composite=composite
    )
    keys = ("frames", "ate_rmse_cm", "ate_mean_cm", "rpe_rmse_cm", "psnr", "ssim", "lpips", "depth_l1_cm", "novel_psnr", "novel_ssim", "novel_lpips", "novel_depth_l1_cm")
    print(json.dumps({k: result[k] for k in keys if k in result}))
    print(f"wrote {run_dir}/eval.json and {run_dir}/report.md", file=sys.stderr)
    return 0


def _run_dir_command(args) -> int:
    try:
        if args.command == "export":
            return export_ply(args.run_dir, args.voxel, args.out)
        if args.command == "plots":
            return draw_plots(args.run_dir, args.compare)
        if args.command == "eval":
            return evaluate(args.run_dir, args.psnr_protocol, args.frames, args.rerender, args.scene_frames, args.layers, args.composite)
        return _mesh_or_view(args)
    except (ConfigError, DatasetError) as err:
        print(f"sgad-jax {args.command}: error: {err}", file=sys.stderr)
        return 2


def _mesh_config(run_dir, overrides):
    """The run's saved config (defaults without one) with ``mesh.*`` overrides applied."""
    import pathlib

    from sgad_jax.config import SLAMConfig
    from sgad_jax.io.rundir import Run

    cfg = Run(run_dir).config if (pathlib.Path(run_dir) / "metrics.json").is_file() else SLAMConfig()
    for item in overrides:
        if not item.strip().startswith("mesh."):
            raise ConfigError(f"--set {item}: only mesh.* settings apply to a finished run")
    return apply_overrides(cfg, list(overrides))


def _make_mesh(run_dir, cfg) -> dict:
    from sgad_jax.mesh import mesh_run

    return mesh_run(run_dir, cfg.mesh, cfg.data.downscale, log=lambda line: print(f"sgad-jax: {line}", file=sys.stderr))


def _mesh_or_view(args) -> int:
    """``mesh``, ``eval-mesh`` and ``view``."""
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
        folder = os.path.expanduser(choice)
        if os.path.exists(folder) and not os.path.isdir(folder):  # JAX would warn at length and run without it
            raise ConfigError(f"--compile-cache {choice}: not a folder")
        jax.config.update("jax_compilation_cache_dir", folder)


_PRESET_FOR_LAYOUT = {"tum": "tum", "replica": "replica", "7scenes": "7scenes", "scannet": "scannet", "scannetpp": "scannetpp", "generic": "tum", "synthetic": "demo"}


def resolve_config(preset=None, data=None, *, start=None, stride=None, max_frames=None, overrides=()):
    """The config of a run: the preset (by default the one for the data's layout, or the demo),
    the data folder and frame selection, then the dotted overrides."""
    from sgad_jax.io.datasets import detect_layout

    if preset is None:
        preset = "demo" if not data else _PRESET_FOR_LAYOUT[detect_layout(data)]
    cfg = load_preset(preset)
    # absolute, so that the run's saved config finds the data from any folder (eval --rerender, eval-mesh)
    path = os.path.abspath(os.path.expanduser(data)) if data else None
    selection = {"path": path, "start": start, "stride": stride, "max_frames": max_frames}
    if path and cfg.data.layout == "synthetic":  # the demo preset with --data: the data, as its layout says
        selection["layout"] = "auto"
    cfg = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, **{k: v for k, v in selection.items() if v is not None}))
    return apply_overrides(cfg, list(overrides))


def _not_made(args) -> str:
    """What a stopped run leaves out of what was asked for after it (said, not skipped in silence)."""
    asked = [flag for flag, on in (("--export-ply", args.export_ply), ("--mesh", args.mesh), ("--plots", args.plots)) if on]
    return f" ({', '.join(asked)} not made: --resume finishes the run and makes them)" if asked else ""


def main(argv: list[str] | None = None) -> int:
    try:
        return _main(argv)
    except KeyboardInterrupt:  # a second Ctrl-C in a run (the first stops it cleanly), or one outside a run's loop
        print("sgad-jax: interrupted: stopped at once, without writing what was in hand", file=sys.stderr)
        return 130


def _main(argv: list[str] | None) -> int:
    args = _parser().parse_args(argv)
    if args.command != "run":
        return _run_dir_command(args)
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
            holdout_every=args.holdout_every, finetune=args.finetune, on_bad_frame=args.on_bad_frame,
            viewer=None if args.viewer is None else (args.viewer_host, args.viewer),
        )
        import jax

        if args.mesh and jax.process_index() == 0:
            info = _make_mesh(args.out, cfg)
            print(f"wrote {info['mesh']} ({info['vertices']} vertices, {info['faces']} faces, {100 * info['voxel_m']:.3g} cm voxels)", file=sys.stderr)
    except (ConfigError, DatasetError) as err:
        print(f"sgad-jax: error: {err}{_not_made(args) if isinstance(err, DatasetError) else ''}", file=sys.stderr)
        return 2
    except RunInterrupted as err:  # 128 + the signal's number, as a shell reports it
        print(f"sgad-jax: {err}; wrote {args.out}/trajectory.txt and {args.out}/metrics.json{_not_made(args)}", file=sys.stderr)
        return 128 + err.signum
    m = result.metrics
    keys = ("frames", "ate_rmse_cm", "ate_mean_cm", "track_ms_median", "psnr", "ssim", "ms_ssim", "lpips", "depth_l1_cm", "nvs_psnr_before_finetune", "nvs_psnr", "nvs_ssim", "nvs_lpips", "map_s_per_frame", "compile_s", "peak_rss_mb")
    summary = {k: m[k] for k in keys if k in m}
    import jax

    if jax.process_index() == 0:
        print(json.dumps(summary))
        print(f"wrote {args.out}/trajectory.txt and {args.out}/metrics.json", file=sys.stderr)
        # after the run, from its files, exactly as the subcommands on a finished run
        try:
            if args.export_ply and args.track_only:
                print("sgad-jax: --export-ply skipped: a --track-only run has no map", file=sys.stderr)
            elif args.export_ply:
                export_ply(args.out)
            if args.plots:
                draw_plots(args.out)
            if result.live is not None:
                result.live.finish(args.out)
        except (ConfigError, DatasetError) as err:
            print(f"sgad-jax: error: {err}", file=sys.stderr)
            return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
