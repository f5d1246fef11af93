"""Pictures of a finished run (``run --plots``, ``sgad-jax plots RUN_DIR``), drawn with matplotlib's
Agg canvas (no display, no pyplot state).

* ``trajectory.png``: the estimated path against the ground truth seen from above, the estimate
  aligned to the ground truth as ATE aligns it (SE(3), Umeyama), ATE RMSE in the title. "Above" is
  opposite the cameras' mean image-down axis: hand-held and robot cameras are held upright, so that
  axis is close to gravity in any dataset's world frame.
* ``plots/ate_per_frame.png``: each frame's position error after that alignment.
* ``plots/psnr_per_frame.png``: each frame's PSNR (``metrics.json``'s ``per_frame`` when the run
  wrote it, else ``eval.json``'s, else from the saved renders), held-out novel views marked.
* ``plots/compare_XXXXXX.png``: render | ground truth | absolute error of a few frames (needs
  ``renders/``).
"""

from __future__ import annotations

import json
import pathlib

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from sgad_jax.eval import image
from sgad_jax.eval.ate import align_umeyama
from sgad_jax.io.base import DatasetError
from sgad_jax.io.files import atomic_write
from sgad_jax.io.rundir import Run, read_render

DPI = 100


def _save(fig: Figure, path: pathlib.Path) -> pathlib.Path:
    FigureCanvasAgg(fig)
    return atomic_write(path, lambda f: fig.savefig(f, dpi=DPI, format="png"))


def top_view_axes(poses: np.ndarray) -> np.ndarray:
    """(2, 3) world directions of a top view's horizontal axes (rows), from camera-to-world poses.

    Up is the opposite of the cameras' mean image-down axis (OpenCV y); the first axis is the
    cameras' mean viewing direction made horizontal, so the picture looks the way the cameras do.
    """
    R = poses[:, :3, :3]
    up = -R[:, :, 1].mean(0)
    if np.linalg.norm(up) < 1e-6:  # cameras rolled all ways: no horizon to go by
        up = np.array([0.0, 0.0, 1.0])
    up /= np.linalg.norm(up)
    fwd = R[:, :, 2].mean(0)
    fwd = fwd - fwd.dot(up) * up
    if np.linalg.norm(fwd) < 1e-6:
        fwd = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    fwd /= np.linalg.norm(fwd)
    return np.stack([np.cross(fwd, up), fwd])  # right, forward: x to the right, y away from the viewer


def aligned_errors(est: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Estimated positions (f, 3) aligned to the ground truth (SE(3) over the frames where both are
    finite, as :func:`sgad_jax.eval.ate.ate`) and each frame's error in metres (NaN where unknown)."""
    p, q = est[:, :3, 3], gt[:, :3, 3]
    ok = np.isfinite(est).all(axis=(1, 2)) & np.isfinite(gt).all(axis=(1, 2))
    R, t, _ = align_umeyama(p[ok], q[ok])
    aligned = p @ R.T + t
    err = np.where(ok, np.linalg.norm(aligned - q, axis=1), np.nan)
    return aligned, err


def plot_trajectory(path, est: np.ndarray, gt: np.ndarray | None, title: str) -> pathlib.Path:
    """The top view of ``est`` (and ``gt``), both (f, 4, 4) camera-to-world, already aligned."""
    axes = top_view_axes(gt if gt is not None and np.isfinite(gt).all() else est)
    fig = Figure(figsize=(6.4, 5.6))
    ax = fig.add_subplot()
    if gt is not None:
        g = gt[:, :3, 3] @ axes.T
        ax.plot(g[:, 0], g[:, 1], "-", color="0.3", lw=2.0, label="ground truth")
    e = est[:, :3, 3] @ axes.T
    ax.plot(e[:, 0], e[:, 1], "-", color="tab:red", lw=1.2, label="estimate")
    ax.plot(e[:1, 0], e[:1, 1], "o", color="tab:red", ms=5, label="start")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("right (m)")
    ax.set_ylabel("forward (m)")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=9)
    ax.set_title(title, fontsize=11)
    fig.tight_layout()
    return _save(fig, pathlib.Path(path))


def plot_series(path, index, values, *, ylabel: str, title: str, marked=None, marked_label: str = "") -> pathlib.Path:
    fig = Figure(figsize=(7.0, 3.6))
    ax = fig.add_subplot()
    index, values = np.asarray(index), np.asarray(values, float)
    ax.plot(index, values, ".-", color="tab:blue", lw=1.0, ms=4)
    if marked is not None and np.any(marked):
        m = np.asarray(marked, bool)
        ax.plot(index[m], values[m], "o", mfc="none", mec="tab:orange", ms=8, mew=1.5, label=marked_label)
        ax.legend(loc="best", fontsize=9)
    ax.set_xlabel("frame (run index)")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    ax.set_title(title, fontsize=11)
    fig.tight_layout()
    return _save(fig, pathlib.Path(path))


def plot_compare(path, rgb: np.ndarray, target: np.ndarray, title: str) -> pathlib.Path:
    """Render | ground truth | mean absolute error over the channels (0 to 0.25 on the colour bar)."""
    h, w = target.shape[:2]
    width = 12.0
    fig = Figure(figsize=(width, width / 3 * h / w + 0.9))
    axs = fig.subplots(1, 3)
    err = np.abs(rgb - target).mean(-1)
    for ax, img, name in zip(axs, (rgb, target), ("render", "ground truth")):
        ax.imshow(np.clip(img, 0, 1))
        ax.set_title(name, fontsize=10)
    im = axs[2].imshow(err, cmap="inferno", vmin=0.0, vmax=0.25)
    axs[2].set_title("|render - ground truth|", fontsize=10)
    fig.colorbar(im, ax=axs[2], fraction=0.035, pad=0.02)
    for ax in axs:
        ax.set_axis_off()
    fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    return _save(fig, pathlib.Path(path))


def _psnr_rows(run: Run) -> tuple[list[dict], str]:
    """Per-frame PSNR rows ``{"index", "psnr", "holdout"}`` and where they came from."""
    rows = [r for r in run.per_frame if r.get("psnr") is not None]
    if rows:
        return rows, "metrics.json"
    ev = run.root / "eval.json"
    if ev.exists():
        try:
            rows = [r for r in json.loads(ev.read_text()).get("per_frame", []) if r.get("psnr") is not None]
        except ValueError:
            rows = []
        if rows:
            return rows, "eval.json"
    protocol = run.config.map.psnr_protocol
    rows = []
    for i in run.render_frames():
        rgb, _ = read_render(run.root, i)
        f = run.dataset[i]
        target = f.rgb.astype(np.float32) / 255.0
        valid = f.depth > 0
        rows.append({"index": i, "psnr": float(image.psnr(rgb, target, valid, protocol=protocol)), "holdout": False})
    return rows, f"renders/, {protocol} protocol"


def plot_run(run_dir, *, compare: int = 3) -> tuple[list[pathlib.Path], list[str]]:
    """Draw every picture the run's files allow; returns the files written and notes on those that
    could not be drawn (no ground truth, no renders)."""
    run = Run(run_dir)
    _, est = run.trajectory
    if len(est) == 0:
        raise DatasetError(f"{run.root / 'trajectory.txt'}: no frames to draw")
    written, notes = [], []
    try:
        gt = run.dataset.gt_poses[: len(est)]
    except DatasetError as err:
        gt, notes = None, [f"no ground truth: the dataset could not be opened ({err})"]
    have_gt = gt is not None and len(est) >= 3 and np.isfinite(gt).all(axis=(1, 2)).sum() >= 3
    why = "no ground truth" if gt is None or np.isfinite(gt).all(axis=(1, 2)).sum() < min(3, len(est)) else "fewer than 3 frames to align"
    name = run.metrics.get("dataset", run.root.name)
    if have_gt:
        aligned, err = aligned_errors(est, gt)
        shown = est.copy()
        shown[:, :3, 3] = aligned
        rmse = 100 * float(np.sqrt(np.nanmean(err**2)))
        written.append(plot_trajectory(run.root / "trajectory.png", shown, gt, f"{name}: ATE RMSE {rmse:.2f} cm ({len(est)} frames)"))
        written.append(plot_series(
            run.root / "plots" / "ate_per_frame.png", np.arange(len(est)), 100 * err,
            ylabel="position error (cm)", title=f"{name}: error after SE(3) alignment (RMSE {rmse:.2f} cm)",
        ))
    else:
        written.append(plot_trajectory(run.root / "trajectory.png", est, None, f"{name}: estimated trajectory ({why})"))
        notes.append(f"plots/ate_per_frame.png not drawn: {why}")
    rows, source = _psnr_rows(run)
    if rows:
        held = [bool(r.get("holdout")) for r in rows]
        mean_train = np.mean([r["psnr"] for r, h in zip(rows, held) if not h]) if not all(held) else float("nan")
        written.append(plot_series(
            run.root / "plots" / "psnr_per_frame.png", [r["index"] for r in rows], [r["psnr"] for r in rows],
            ylabel="PSNR (dB)", title=f"{name}: PSNR per frame (mean {mean_train:.2f} dB; from {source})",
            marked=held, marked_label="held-out view",
        ))
    else:
        notes.append("plots/psnr_per_frame.png not drawn: no per-frame scores and no renders (run with --save-renders)")
    rendered = run.render_frames()
    if rendered and compare > 0:
        pick = sorted({rendered[k] for k in np.linspace(0, len(rendered) - 1, min(compare, len(rendered))).round().astype(int)})
        protocol = run.config.map.psnr_protocol
        for i in pick:
            rgb, _ = read_render(run.root, i)
            f = run.dataset[i]
            target = f.rgb.astype(np.float32) / 255.0
            p = float(image.psnr(rgb, target, f.depth > 0, protocol=protocol))
            written.append(plot_compare(run.root / "plots" / f"compare_{i:06d}.png", rgb, target, f"{name} frame {i}: PSNR {p:.2f} dB ({protocol})"))
    elif compare > 0:
        notes.append("plots/compare_*.png not drawn: no renders (run with --save-renders)")
    return written, notes
