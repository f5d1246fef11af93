"""What a finished run's folder gives a user: `sgad-jax eval` (metrics recomputed from the files,
ATE also against evo), `--plots` / `sgad-jax plots` pictures, `--export-ply`. One short synthetic
run (4 frames at 80x60, 5 mapping iterations) serves every test."""

import copy
import json
import shutil

import numpy as np
import pytest

from sgad_jax.cli import main
from sgad_jax.io.export import read_tum_trajectory
from sgad_jax.io.ply import read_3dgs_ply

RUN = [
    "--max-frames", "4", "--quiet", "--save-renders", "--plots", "--export-ply",
    "--set", "data.synthetic.frames=4", "--set", "data.synthetic.width=80", "--set", "data.synthetic.height=60",
    "--set", "map.iterations=3",  # the size and iterations of test_scene's runs: their compiled programs are shared
    # Without the colour fit: its exact self-fits render above 8-bit PNG precision (about 59 dB),
    # where re-scoring the written renders could not reproduce the run's PSNR
    "--set", "map.colour_fit=0",
]
PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "synthetic"
    assert main(["run", "--out", str(out), *RUN]) == 0
    return out


def _png_size(path):
    data = path.read_bytes()
    assert data[:8] == PNG, f"{path} is not a PNG"
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


@pytest.mark.slow
def test_run_with_plots_and_export(run_dir, capsys):
    files = ["trajectory.png", "plots/ate_per_frame.png", "plots/psnr_per_frame.png", "plots/compare_000000.png", "plots/compare_000003.png"]
    for name in files:
        w, h = _png_size(run_dir / name)
        assert 300 <= w <= 2000 and 200 <= h <= 2000, (name, w, h)
        assert (run_dir / name).stat().st_size > 10_000  # drawn, not blank
    w, h = _png_size(run_dir / "plots/compare_000000.png")
    assert w > 2 * h  # three images side by side
    g = read_3dgs_ply(run_dir / "gaussians.ply")
    assert 0 < len(g) <= 4 * 80 * 60
    assert np.isfinite(g.xyz).all() and (g.opacity >= 0.005).all()


@pytest.mark.slow
def test_eval_reproduces_the_run(run_dir, capsys):
    assert main(["eval", str(run_dir)]) == 0
    ev = json.loads((run_dir / "eval.json").read_text())
    m = json.loads((run_dir / "metrics.json").read_text())
    # trajectory.txt keeps 9 significant digits: ATE agrees far below 1e-6 cm
    assert ev["ate_rmse_cm"] == pytest.approx(m["ate_rmse_cm"], abs=1e-6)
    assert ev["ate_mean_cm"] == pytest.approx(m["ate_mean_cm"], abs=1e-6)
    assert ev["rpe_rmse_cm"] == pytest.approx(m["rpe_rmse_cm"], abs=1e-5)
    # renders are 8-bit PNGs (depth in mm): image metrics agree to their quantisation
    assert ev["psnr"] == pytest.approx(m["psnr"], abs=0.05)
    assert ev["ssim"] == pytest.approx(m["ssim"], abs=2e-3)
    assert ev["depth_l1_cm"] == pytest.approx(m["depth_l1_cm"], abs=5e-3)
    if m.get("lpips") is not None:  # the LPIPS weights are installed
        assert ev["lpips"] == pytest.approx(m["lpips"], abs=5e-3)
    assert ev["frames"] == ev["rendered_frames"] == 4 and len(ev["per_frame"]) == 4
    report = (run_dir / "report.md").read_text()
    assert "ate_rmse_cm" in report and f"{m['ate_rmse_cm']:.4f}" in report


@pytest.mark.slow
def test_eval_ate_matches_evo(run_dir):
    """The ATE recomputed from the run's files against evo's APE on the same trajectory and ground
    truth (an independent implementation of the alignment and the error)."""
    from evo.core import metrics
    from evo.core.trajectory import PoseTrajectory3D

    from sgad_jax.eval.run_eval import evaluate_run
    from sgad_jax.io.rundir import Run

    stamps, est = read_tum_trajectory(run_dir / "trajectory.txt")
    gt = Run(run_dir).dataset.gt_poses[: len(est)]
    ref = PoseTrajectory3D(poses_se3=list(gt), timestamps=stamps)
    traj = copy.deepcopy(PoseTrajectory3D(poses_se3=list(est), timestamps=stamps))
    traj.align(ref, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, traj))
    ev = evaluate_run(run_dir, write=False)
    assert ev["ate_rmse_cm"] == pytest.approx(100 * ape.get_statistic(metrics.StatisticsType.rmse), abs=1e-6)
    assert ev["ate_mean_cm"] == pytest.approx(100 * ape.get_statistic(metrics.StatisticsType.mean), abs=1e-6)


@pytest.mark.slow
def test_eval_protocols_and_frames(run_dir, capsys):
    from sgad_jax.eval.run_eval import evaluate_run

    whole = evaluate_run(run_dir, frames="1:3", write=False)
    assert [r["index"] for r in whole["per_frame"]] == [1, 2] and whole["frames"] == 2
    assert whole["ate_rmse_cm"] is None  # fewer than 3 frames: no alignment
    listed = evaluate_run(run_dir, frames="0,2,3", psnr_protocol="zeroed", write=False)
    assert [r["index"] for r in listed["per_frame"]] == [0, 2, 3] and listed["psnr_protocol"] == "zeroed"
    assert main(["eval", str(run_dir), "--frames", "7"]) == 2
    assert "outside the run's 4 frames" in capsys.readouterr().err
    assert main(["eval", str(run_dir), "--frames", "a:b"]) == 2


@pytest.mark.slow
def test_plots_mark_held_out_views_and_need_no_renders(run_dir, tmp_path, capsys):
    """`sgad-jax plots` on a copy whose metrics.json has per_frame rows (two held out) and no
    renders: the PSNR plot is drawn from per_frame and the comparisons are skipped with a note."""
    copy_dir = tmp_path / "copy"
    shutil.copytree(run_dir, copy_dir, ignore=shutil.ignore_patterns("renders", "plots", "*.png", "eval.json"))
    m = json.loads((copy_dir / "metrics.json").read_text())
    m["per_frame"] = [{"index": i, "psnr": 30.0 + i, "ssim": 0.9, "depth_l1_cm": 1.0, "holdout": i in (1, 3)} for i in range(4)]
    (copy_dir / "metrics.json").write_text(json.dumps(m))
    assert main(["plots", str(copy_dir)]) == 0
    err = capsys.readouterr().err
    assert "compare_*.png not drawn" in err
    from sgad_jax.io.plots import _psnr_rows
    from sgad_jax.io.rundir import Run

    rows, source = _psnr_rows(Run(copy_dir))
    assert source == "metrics.json" and [r["holdout"] for r in rows] == [False, True, False, True]
    for name in ("trajectory.png", "plots/ate_per_frame.png", "plots/psnr_per_frame.png"):
        _png_size(copy_dir / name)
    assert not list((copy_dir / "plots").glob("compare_*.png"))
    assert main(["plots", str(tmp_path / "missing")]) == 2


def _defect(run_dir, dest, defect):
    """A copy of the run with one defect, as a crash, a stray copy or another program leaves it."""
    shutil.copytree(run_dir, dest)
    if defect == "metrics_list":
        (dest / "metrics.json").write_text("[]")
    elif defect == "empty_npz":
        (dest / "gaussians" / "frame_000003.npz").write_bytes(b"")
    elif defect == "trajectory_dir":
        (dest / "trajectory.txt").unlink()
        (dest / "trajectory.txt").mkdir()
    return dest


@pytest.mark.slow
@pytest.mark.parametrize(
    "defect, args, needle",
    [
        ("metrics_list", ["export"], "metrics.json: not a JSON object"),
        ("metrics_list", ["eval"], "metrics.json: not a JSON object"),
        ("metrics_list", ["plots"], "metrics.json: not a JSON object"),
        ("metrics_list", ["mesh", "--compile-cache", "off"], "metrics.json: not a JSON object"),
        ("empty_npz", ["export"], "frame_000003.npz: unreadable"),
        ("empty_npz", ["eval", "--rerender"], "frame_000003.npz: unreadable"),
        ("trajectory_dir", ["export"], "trajectory.txt: unreadable"),
        (None, ["export", "--voxel", "-1"], "--voxel -1: must be"),
        (None, ["plots", "--compare", "-3"], "--compare -3: must be >= 0"),
    ],
)
def test_bad_run_files_one_line(run_dir, tmp_path, capsys, defect, args, needle):
    """A damaged run folder or a bad option: one line naming the file (or option), status 2."""
    bad = _defect(run_dir, tmp_path / "bad", defect)
    assert main([args[0], str(bad), *args[1:]]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err, err


@pytest.mark.slow
def test_stray_files_in_a_run_are_ignored(run_dir, tmp_path, capsys):
    """Files whose names are not the run's exact pattern (a file manager's copy, a hand-named render)
    are not the run's: export, eval and mesh read the run's own files and ignore them."""
    from sgad_jax.io.rundir import Run

    odd = shutil.copytree(run_dir, tmp_path / "odd")
    shutil.copy(odd / "gaussians" / "frame_000003.npz", odd / "gaussians" / "frame_000003 (copy).npz")
    for name in ("rgb_3a.png", "rgb_3.png", "rgb_0000003.png"):
        shutil.copy(odd / "renders" / "rgb_000003.png", odd / "renders" / name)
    assert Run(odd).gaussian_frames() == Run(odd).render_frames() == [0, 1, 2, 3]
    assert main(["export", str(odd)]) == 0
    assert "(4 frames;" in capsys.readouterr().err
    assert main(["eval", str(odd)]) == 0
    assert json.loads((odd / "eval.json").read_text())["rendered_frames"] == 4
    assert main(["mesh", str(odd), "--set", "mesh.voxel=0.04", "--compile-cache", "off"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["frames"] == 4


def test_merge_eval_json_refuses_a_list(tmp_path):
    """eval.json holding valid JSON that is not an object: one line naming it, the file left as it was."""
    from sgad_jax.io.base import DatasetError
    from sgad_jax.io.rundir import merge_eval_json

    (tmp_path / "eval.json").write_text("[1, 2]")
    with pytest.raises(DatasetError, match="eval.json: exists but is not a JSON object"):
        merge_eval_json(tmp_path, {"mesh_f1": 0.5})
    assert (tmp_path / "eval.json").read_text() == "[1, 2]"
