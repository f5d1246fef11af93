"""``sgad-jax eval RUN_DIR``: a finished run's metrics recomputed from its files alone.

Trajectory metrics from ``trajectory.txt`` against the dataset's ground truth (opened from the
config in ``metrics.json``): ATE RMSE / mean / median / max after SE(3) alignment of positions
(:func:`sgad_jax.eval.ate.ate`) and RPE between consecutive frames. Image metrics from the saved
renders (``renders/``, written by ``run --save-renders``) against the dataset's frames: PSNR under an
explicit protocol, SSIM, MS-SSIM (images large enough), LPIPS (when its weights are installed) and
rendered depth L1 in cm over valid-depth pixels. The renders are 8-bit colour and millimetre depth PNGs, so depth L1 differs
from the run's (float) figure by up to ~0.05 mm, and PSNR by tenths of a dB on held-out views but by
1-6 dB on training views fitted within a quantisation step: rounding snaps most pixels onto the
8-bit image they were fitted to.

Frames listed in ``metrics.json``'s ``per_frame`` with ``holdout: true`` are novel views: their
scores are averaged apart (``novel_*`` keys) and not mixed into the training-view means.
Results go to ``RUN_DIR/eval.json`` (with the protocol, the frame selection and, for every metric the
run recorded too, the run's value) and a short ``RUN_DIR/report.md``.
"""

from __future__ import annotations


import numpy as np

from sgad_jax.config import ConfigError
from sgad_jax import splat
from sgad_jax.eval import image, lpips_weights
from sgad_jax.eval.ate import ate, rpe
from sgad_jax.io.base import DatasetError
from sgad_jax.io.files import write_json, write_text
from sgad_jax.io.rundir import Run, read_render
from sgad_jax.types import make_frame

IMAGE_KEYS = ("psnr", "ssim", "ms_ssim", "lpips", "depth_l1_cm")
COMPARED = ("ate_rmse_cm", "ate_mean_cm", "rpe_rmse_cm", "rpe_rot_rmse_deg", "psnr", "ssim", "ms_ssim", "lpips", "depth_l1_cm")


def select_frames(spec: str | None, n: int) -> list[int]:
    """Run indices chosen by ``spec``: None or ``"all"``; ``"A:B[:S]"`` (a Python slice of
    ``range(n)``); or ``"i,j,k"``.

    Raises:
        ConfigError: a malformed selection or an index outside ``[0, n)``.
    """
    if spec is None or spec.strip().lower() == "all":
        return list(range(n))
    text = spec.strip()
    try:
        if ":" in text:
            parts = [int(p) if p.strip() else None for p in text.split(":")]
            if len(parts) > 3:
                raise ValueError
            chosen = list(range(n))[slice(*parts)]
        else:
            chosen = sorted({int(p) for p in text.replace(" ", "").split(",") if p})
    except ValueError:
        raise ConfigError(f"--frames {spec}: expected 'all', 'A:B[:S]' or a comma list of frame indices") from None
    bad = [i for i in chosen if not 0 <= i < n]
    if bad:
        raise ConfigError(f"--frames {spec}: frame {bad[0]} is outside the run's {n} frames")
    if not chosen:
        raise ConfigError(f"--frames {spec}: selects no frame of the run's {n}")
    return chosen


def _mean(xs):
    xs = [x for x in xs if x is not None and np.isfinite(x)]
    return float(np.mean(xs)) if xs else None


def render_held_out(run: Run, indices: list[int], scene_frames: int | None = None, layers: int | None = None, composite: str | None = None) -> dict:
    """Held-out views rendered again from the run's stored Gaussians by the scene renderer at
    their estimated poses (``scene_frames``, ``layers`` and ``composite`` default to the run's ``scene`` config):
    ``{index: Render}``. Lets the renderer's settings be compared without mapping again."""
    import dataclasses

    from sgad_jax import scene

    cfg = run.config.scene
    cfg = dataclasses.replace(cfg, frames=scene_frames or cfg.frames, layers=layers or cfg.layers, composite=composite or cfg.composite)
    sc = scene.Scene(cfg, run.intrinsics, run.gaussians)
    mapped_at = run.mapping_poses()
    for i in run.gaussian_frames():
        f = make_frame(run.dataset[i].rgb, run.dataset[i].depth)
        sc.add(i, mapped_at[i], np.asarray(f.depth), np.asarray(f.valid))
    _, poses = run.trajectory
    return {i: sc.render(poses[i]) for i in indices}


def evaluate_run(
    run_dir, *, psnr_protocol: str | None = None, frames: str | None = None, write: bool = True,
    rerender: bool = False, scene_frames: int | None = None, layers: int | None = None, composite: str | None = None,
) -> dict:
    """Recompute a finished run's metrics from its files; see the module docstring.

    Args:
        run_dir: the run's ``--out`` folder.
        psnr_protocol: ``whole``, ``valid`` or ``zeroed``; None: the run's ``map.psnr_protocol``.
        frames: frame selection (:func:`select_frames`); trajectory metrics use the same frames.
        write: write ``eval.json`` and ``report.md`` into the run folder.
        rerender: score the held-out views rendered again from the stored Gaussians
            (:func:`render_held_out`, with ``scene_frames``, ``layers`` and ``composite``) instead of their saved renders.

    Returns:
        the contents of ``eval.json``.

    Raises:
        DatasetError: a file of the run or of its dataset is missing or unreadable.
        ConfigError: a bad protocol or frame selection.
    """
    run = Run(run_dir)
    protocol = psnr_protocol or run.config.map.psnr_protocol
    if protocol not in image.PSNR_PROTOCOLS:
        raise ConfigError(f"--psnr-protocol must be one of {', '.join(image.PSNR_PROTOCOLS)}, got {protocol!r}")
    _, poses = run.trajectory
    chosen = select_frames(frames, len(poses))
    ds = run.dataset
    if len(ds) < len(poses):
        raise DatasetError(f"{run.root / 'trajectory.txt'}: {len(poses)} poses but the dataset {ds.root} has {len(ds)} frames selected")
    result: dict = {"run": str(run.root), "dataset": ds.name, "frames": len(chosen), "frame_selection": frames or "all", "psnr_protocol": protocol}

    est, gt = poses[chosen], ds.gt_poses[chosen]
    if len(chosen) >= 3 and np.isfinite(gt).all(axis=(1, 2)).sum() >= 3:
        e = ate(est, gt)
        result.update(ate_rmse_cm=100 * e["rmse_m"], ate_mean_cm=100 * e["mean_m"], ate_median_cm=100 * e["median_m"], ate_max_cm=100 * e["max_m"], ate_pairs=e["pairs"])
        try:
            d = rpe(est, gt)
            result.update(rpe_rmse_cm=100 * d["trans_rmse_m"], rpe_rot_rmse_deg=d["rot_rmse_deg"], rpe_pairs=d["pairs"])
        except ValueError:  # no two consecutive frames with ground truth
            pass
    else:
        result["ate_rmse_cm"] = None
        result["trajectory_note"] = "no ATE: fewer than 3 selected frames with ground truth"

    holdout = {int(r["index"]) for r in run.per_frame if r.get("holdout")}
    rendered = set(run.render_frames()) | set(run.render_frames("nvs"))
    fresh = render_held_out(run, sorted(holdout & set(chosen)), scene_frames, layers, composite) if rerender else {}
    per_frame = []
    try:  # LPIPS only where its weights are installed and intact, as in the run
        weights = lpips_weights.load_lpips_weights() if (fresh or rendered) else None
    except lpips_weights.LPIPSUnavailable:
        weights = None
    for i in chosen:
        if i in fresh:
            rgb, depth = np.clip(fresh[i].rgb, 0.0, 1.0), np.asarray(splat.surface_depth(fresh[i]))
        elif i in rendered:
            rgb, depth = read_render(run.root, i, "nvs" if i in holdout else "")
        else:
            continue
        sample = ds[i]
        f = make_frame(sample.rgb, sample.depth)
        target, target_depth, valid = (np.asarray(x) for x in (f.rgb, f.depth, f.valid))
        if rgb.shape != target.shape:
            raise DatasetError(f"{run.root / 'renders'}: render {i} is {rgb.shape[1]}x{rgb.shape[0]}, the dataset frame {target.shape[1]}x{target.shape[0]} (another downscale?)")
        per_frame.append({"index": i, "holdout": i in holdout, **image.score_view(rgb, depth, target, target_depth, valid, protocol=protocol, lpips_weights=weights)})
    result["rendered_frames"] = len(per_frame)
    if not per_frame:
        result["image_note"] = "no image metrics: no renders of the selected frames (run with --save-renders)"
    train = [r for r in per_frame if not r["holdout"]]
    novel = [r for r in per_frame if r["holdout"]]
    for key in IMAGE_KEYS:
        result[key] = _mean([r.get(key) for r in train])
        if novel:
            result[f"novel_{key}"] = _mean([r.get(key) for r in novel])
    result["per_frame"] = per_frame
    recorded = run.metrics
    result["recorded"] = {k: recorded.get(k) for k in COMPARED if recorded.get(k) is not None}
    if write:
        write_json(run.root / "eval.json", result)
        write_text(run.root / "report.md", report(result))
    return result


def report(result: dict) -> str:
    """A short Markdown summary of :func:`evaluate_run`'s result."""
    fmt = lambda v, d=4: "n/a" if v is None else f"{v:.{d}f}"  # noqa: E731
    rec = result.get("recorded", {})
    lines = [
        f"# Evaluation of `{result['run']}`",
        "",
        f"Dataset `{result['dataset']}`, {result['frames']} frames ({result['frame_selection']}), "
        f"{result['rendered_frames']} with renders; PSNR protocol `{result['psnr_protocol']}`.",
        "",
        "| metric | recomputed | in metrics.json |",
        "|---|---|---|",
    ]
    for key in COMPARED:
        if key in result:
            lines.append(f"| {key} | {fmt(result[key])} | {fmt(rec.get(key))} |")
    for key in IMAGE_KEYS:
        if f"novel_{key}" in result:
            lines.append(f"| novel-view {key} | {fmt(result[f'novel_{key}'])} | |")
    lines += [
        "",
        "ATE: RMSE of camera positions after the closed-form SE(3) alignment (Umeyama, no scale) of the",
        "estimated to the ground-truth positions; RPE: consecutive-frame relative pose error. Image",
        "metrics are computed from the 8-bit colour and millimetre depth PNGs in `renders/`: rounding",
        "snaps a training view fitted within a quantisation step onto its image, so its PSNR can read",
        "1-6 dB above the run's own (float) figure; held-out views differ by tenths of a dB.",
    ]
    for note in ("trajectory_note", "image_note"):
        if note in result:
            lines.append(f"\nNote: {result[note]}.")
    return "\n".join(lines) + "\n"
