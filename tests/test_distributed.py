"""Mapping across devices and processes, the Gaussian store, checkpoints and resume, streaming."""

import dataclasses
import json
import pathlib
import signal
import socket
import subprocess
import sys

import jax
import numpy as np
import pytest

from sgad_jax import lie, mapping, pipeline, programs, scene, slam, splat
from sgad_jax.cli import main, resolve_config
from sgad_jax.distributed import BatchMapper
from sgad_jax.io.datasets import open_dataset
from sgad_jax.io.export import read_tum_trajectory
from sgad_jax.io.store import GaussianStore
from sgad_jax.mapping import init_gaussians
from sgad_jax.pipeline import run
from sgad_jax.system import SLAM, initial_pose
from sgad_jax.types import host_frame
from sgad_jax.types import PixelGaussians

TINY = ["data.synthetic.width=80", "data.synthetic.height=60", "data.synthetic.frames=8", "map.iterations=3", "map.batch=2"]
TINY_ARGS = [a for kv in TINY for a in ("--set", kv)]
ROOT = pathlib.Path(__file__).resolve().parents[1]


def _cli(*args, env=None, **kw):
    return subprocess.Popen(
        [sys.executable, "-m", "sgad_jax", "run", "--quiet", *TINY_ARGS, *args],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=env, **kw,
    )


def _finish(proc, timeout=600):
    out, err = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, err[-3000:]
    return out


def _results(out: pathlib.Path):
    _, poses = read_tum_trajectory(out / "trajectory.txt")
    return poses, json.loads((out / "metrics.json").read_text())


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_batch_mapper_matches_map_step():
    """One batch through shard_map + vmap equals the plain jitted map_step frame by frame."""
    cfg = resolve_config(None, None, overrides=TINY)
    # The paper's step sizes (rates unscaled, mapping.reach_scale): Adam's first step is a full
    # rate whatever the gradient's size, so a rounding-level gradient of either sign moves a
    # parameter by +-rate, and scaled rates would turn the two programs' rounding into a 0.3 gap
    k = mapping.reach_scale(cfg.map)
    cfg = dataclasses.replace(cfg, map=dataclasses.replace(cfg.map, lr_radius=cfg.map.lr_radius / k, lr_opacity=cfg.map.lr_opacity / k))
    ds = open_dataset(cfg.data)
    intr = ds.intrinsics
    frames = [host_frame(ds[i]) for i in range(3)]
    poses = [jax.tree.map(np.asarray, lie.from_matrix(ds.gt_poses[i])) for i in range(3)]
    stack = lambda *xs: np.stack(xs)  # noqa: E731
    nb = jax.tree.map(stack, frames[1], frames[0])
    nb_gs = jax.tree.map(stack, *[jax.tree.map(np.asarray, init_gaussians(f, intr)) for f in (frames[1], frames[0])])
    nb_poses = jax.tree.map(stack, poses[1], poses[0])
    present = np.array([True, False])
    batch = [jax.tree.map(lambda x: x[None], t) for t in (frames[2], poses[2], nb_gs, nb, nb_poses, present)]
    mapper = BatchMapper(cfg.map, intr)
    two = [jax.tree.map(lambda x: np.concatenate([x, x]), t) for t in batch]
    with pytest.raises(ValueError, match="batches of 1 frames, got \\[2\\]"):  # not silently cut to one
        mapper(*two)
    gs, rgb, depth = mapper(*batch)
    g_ref, out_ref, _ = jax.jit(lambda *a: slam.map_step(cfg.map, *a, intr))(frames[2], poses[2], nb_gs, nb, nb_poses, present)
    # Two programs compiled apart round differently in float32, and Adam's normalised steps carry a
    # rounding difference on: a few 1e-5 relative after the steps; an error would be far larger.
    for a, b in zip(jax.tree.leaves(jax.tree.map(lambda x: x[0], gs)), jax.tree.leaves(g_ref)):
        np.testing.assert_allclose(a, np.asarray(b), rtol=5e-5, atol=1e-6)
    np.testing.assert_allclose(rgb[0], np.asarray(out_ref.rgb), atol=1e-5)
    np.testing.assert_allclose(depth[0], np.asarray(splat.surface_depth(out_ref)), atol=1e-5)


@pytest.fixture(scope="module")
def reference_run(tmp_path_factory):
    """The uninterrupted one-device CLI run of the tiny scene: (poses, metrics), shared by the
    tests that compare other ways of running it against it. In this process, so that the runs
    here that need no process of their own reuse its compiled programs."""
    out = tmp_path_factory.mktemp("reference") / "one"
    assert main(["run", "--quiet", *TINY_ARGS, "--out", str(out), "--devices", "1"]) == 0
    return _results(out)


@pytest.mark.slow
def test_two_devices_and_two_processes_match_one(tmp_path, reference_run):
    """With one `map.batch` (2, in TINY), `--devices 2` and a 2-process localhost run give the
    1-device trajectory and metrics (there a batch runs in two chunks); a later batch's neighbours
    are learned Gaussians, some mapped by the other process."""
    _finish(_cli("--out", str(tmp_path / "two"), "--devices", "2"))
    port = _free_port()
    procs = [_cli("--out", str(tmp_path / "mp"), "--coordinator", f"localhost:{port}", "--num-processes", "2", "--process-id", str(k)) for k in (1, 0)]
    for p in procs:
        _finish(p)
    ref_poses, ref = reference_run
    assert ref["devices"] == 1 and ref["mapped_frames"] == 8
    for name, devices, processes in (("two", 2, 1), ("mp", 2, 2)):
        poses, m = _results(tmp_path / name)
        assert m["devices"] == devices and m["processes"] == processes and m["map_batch"] == 2
        np.testing.assert_allclose(poses, ref_poses, atol=1e-5)
        assert abs(m["psnr"] - ref["psnr"]) < 0.01
        for key in ("ssim", "lpips", "depth_l1_cm"):
            assert abs(m[key] - ref[key]) < 1e-4, key
        # every frame's Gaussians were written once, whichever process mapped it
        assert sorted(p.name for p in (tmp_path / name / "gaussians").glob("*.npz")) == [f"frame_{i:06d}.npz" for i in range(8)]


def _killed_run(out: pathlib.Path, *, at_commit: int = 0, at_file: str = "", resume: bool = False):
    """A run that SIGKILLs itself at a fixed point: inside its ``at_commit``-th checkpoint commit
    (after orbax wrote the data, before its rename of the temporary folder), or just before it
    moves the finished file named ``at_file`` into place (mid-run, between checkpoints)."""
    code = f"""
import os, signal, sys
commits = []
real_rename, real_replace = os.rename, os.replace
def rename(src, dst, *a, **k):
    if "checkpoints" in str(dst) and os.path.basename(dst).isdigit():  # orbax commits step dst
        commits.append(dst)
        if len(commits) == {at_commit}:
            os.kill(os.getpid(), signal.SIGKILL)
    return real_rename(src, dst, *a, **k)
def replace(src, dst, *a, **k):
    if os.path.basename(dst) == {at_file!r}:
        os.kill(os.getpid(), signal.SIGKILL)
    return real_replace(src, dst, *a, **k)
os.rename, os.replace = rename, replace
from sgad_jax.cli import main
sys.exit(main(sys.argv[1:]))
"""
    args = ["run", "--quiet", *TINY_ARGS, "--out", str(out), "--checkpoint-every", "2", *(["--resume"] if resume else [])]
    proc = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
    assert not (out / "metrics.json").exists()


def _steps(out: pathlib.Path) -> list[int]:
    return sorted(int(p.name) for p in (out / "checkpoints").iterdir() if p.name.isdigit())


@pytest.mark.slow
def test_resume_after_sigkill_matches_uninterrupted_run(tmp_path, reference_run):
    """Killed inside a checkpoint commit, then (resumed) between checkpoints while writing a
    frame's Gaussians; the last resume gives the uninterrupted run's trajectory and scores."""
    ref_poses, ref_m = reference_run
    out = tmp_path / "killed"
    _killed_run(out, at_commit=2)
    assert _steps(out) == [2]  # step 4 was being committed: the previous checkpoint is the newest
    _killed_run(out, at_file="frame_000005.npz", resume=True)
    assert not (out / "gaussians" / "frame_000005.npz").exists()
    newest = _steps(out)[-1]
    assert newest > 2  # the resumed run committed a checkpoint of its own before frame 5
    assert main(["run", "--quiet", *TINY_ARGS, "--out", str(out), "--checkpoint-every", "2", "--resume"]) == 0
    poses, m = _results(out)
    np.testing.assert_allclose(poses, ref_poses, atol=1e-6)
    for key in ("ate_rmse_cm", "psnr", "ssim", "lpips", "depth_l1_cm", "mapped_frames", "frames", "gaussians_total"):
        assert abs(m[key] - ref_m[key]) <= 1e-4, (key, m[key], ref_m[key])
    assert m["resumed_from_frame"] == newest
    # (the killed write's temporary file, `.frame_000005.<pid>.npz`, stays behind: not matched here)
    assert sorted(p.name for p in (out / "gaussians").glob("frame_*.npz")) == [f"frame_{i:06d}.npz" for i in range(8)]


@pytest.mark.slow
@pytest.mark.parametrize("at", [6, 8])
def test_ctrl_c_stops_between_frames_and_resume_matches_uninterrupted_run(tmp_path, reference_run, at):
    """SIGINT (Ctrl-C) while the 6th frame is processed: exit status 130, one line, the 6 frames'
    trajectory and metrics written and checkpointed (off the --checkpoint-every schedule; at a
    mapping batch's end, as a checkpoint maps the queued frames); --resume then gives the
    uninterrupted run's trajectory and scores. At the last (8th) frame the resumed run has no frame
    left: it only finishes (the same scores)."""
    code = f"""
import signal, sys
signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a terminal (pytest's workers ignore it)
from sgad_jax.system import SLAM
real_add = SLAM.add
def add(self, sample):
    pose = real_add(self, sample)
    if len(self.poses) == {at}:
        signal.raise_signal(signal.SIGINT)  # as a Ctrl-C while that frame is processed
    return pose
SLAM.add = add
from sgad_jax.cli import main
sys.exit(main(sys.argv[1:]))
"""
    out = tmp_path / "interrupted"
    args = ["run", "--quiet", *TINY_ARGS, "--out", str(out), "--checkpoint-every", "4"]
    proc = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert proc.returncode == 128 + signal.SIGINT, proc.stderr[-2000:]
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and f"interrupted by SIGINT after {at} of 8 frames" in lines[0] and "--resume" in lines[0]
    poses, m = _results(out)
    assert len(poses) == at and m["frames"] == at and m["stopped"].startswith("interrupted by SIGINT")
    assert _steps(out) == [4, at]
    ref_poses, ref_m = reference_run
    assert main(["run", "--quiet", *TINY_ARGS, "--out", str(out), "--checkpoint-every", "4", "--resume"]) == 0
    poses, m = _results(out)
    np.testing.assert_allclose(poses, ref_poses, atol=1e-6)
    for key in ("ate_rmse_cm", "psnr", "ssim", "depth_l1_cm", "mapped_frames", "frames", "gaussians_total"):
        assert abs(m[key] - ref_m[key]) <= 1e-4, (key, m[key], ref_m[key])
    assert m["resumed_from_frame"] == at and "stopped" not in m


@pytest.mark.slow
def test_sigterm_in_the_refinement_ends_it_and_keeps_the_run(tmp_path, monkeypatch):
    """SIGTERM during the merged-map refinement (as from a job scheduler): the step in hand ends
    it, the held-out views are scored as refined so far, everything is written, exit status 143."""
    real, calls = scene.finetune_step, []

    def step(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            signal.raise_signal(signal.SIGTERM)
        return real(*args, **kwargs)

    monkeypatch.setattr(scene, "finetune_step", step)
    original = signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:
        out = tmp_path / "refined"
        code = main(["run", "--quiet", *TINY_ARGS, "--out", str(out), "--holdout-every", "4", "--finetune", "6", "--checkpoint-every", "0"])
    finally:
        signal.signal(signal.SIGTERM, original)
    assert code == 128 + signal.SIGTERM
    poses, m = _results(out)
    assert len(poses) == m["frames"] == 8 and len(calls) == m["finetune_iterations"] == 2
    assert "interrupted by SIGTERM after all 8 frames, in the refinement (2 of 6 steps)" == m["stopped"]
    assert m["nvs_frames"] == 1 and m["nvs_psnr"] > 20 and m["nvs_psnr_before_finetune"] > 20


@pytest.mark.slow
def test_a_stop_signal_during_the_last_mapping_skips_the_scoring_and_says_so(tmp_path, monkeypatch):
    """SIGTERM while the last frames are mapped (after the loop): the run is written with the
    signal's exit status and a `stopped` line, instead of going on to score and exit 0."""
    real = SLAM.finish

    def finish(self):
        signal.raise_signal(signal.SIGTERM)
        return real(self)

    monkeypatch.setattr(SLAM, "finish", finish)
    original = signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:
        out = tmp_path / "run"
        code = main(["run", "--quiet", *TINY_ARGS, "--out", str(out), "--holdout-every", "4", "--checkpoint-every", "0"])
    finally:
        signal.signal(signal.SIGTERM, original)
    assert code == 128 + signal.SIGTERM
    poses, m = _results(out)
    assert len(poses) == m["frames"] == 8 and "nvs_psnr" not in m and m["psnr"] > 20
    assert m["stopped"] == "interrupted by SIGTERM after all 8 frames, before the held-out views were scored"


def test_a_second_ctrl_c_is_one_line_and_status_130(monkeypatch, capsys):
    def run(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline, "run", run)
    assert main(["run", "--quiet"]) == 130
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("sgad-jax: interrupted") and "Traceback" not in err


def test_first_stop_signal_is_a_request_and_a_second_ctrl_c_aborts():
    original = signal.getsignal(signal.SIGINT)
    try:
        signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a terminal
        before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
        with pipeline._stop_requests(True) as requests:
            signal.raise_signal(signal.SIGTERM)  # as from a job scheduler: recorded, nothing raised
            assert requests == [signal.SIGTERM]
            with pytest.raises(KeyboardInterrupt):
                signal.raise_signal(signal.SIGINT)
        assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before
        with pipeline._stop_requests(False) as requests:  # multi-process runs: signals act as usual
            assert signal.getsignal(signal.SIGTERM) == before[1]
        assert requests == []
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # a background job's: stays ignored
        with pipeline._stop_requests(True) as requests:
            signal.raise_signal(signal.SIGINT)
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN and requests == []
    finally:
        signal.signal(signal.SIGINT, original)


@pytest.mark.slow
def test_resume_refuses_another_config_and_starts_over_without_checkpoint(tmp_path, capsys, reference_run):
    # in this process: the runs share the reference run's compiled programs (a kill is not needed here)
    cli = lambda *args: (main(["run", "--quiet", *TINY_ARGS, *args]), capsys.readouterr().err)  # noqa: E731
    out = tmp_path / "run"
    assert cli("--out", str(out), "--checkpoint-every", "2", "--max-frames", "3")[0] == 0
    code, err = cli("--out", str(out), "--resume", "--max-frames", "3", "--set", "map.lr_rgb=0.01")
    assert code == 2 and "cannot resume" in err and "config" in err
    # killed before its first checkpoint: --resume starts over
    code, err = cli("--out", str(tmp_path / "fresh"), "--resume", "--max-frames", "3")
    assert code == 0 and "no checkpoint" in err
    assert _results(tmp_path / "fresh")[1]["frames"] == 3


def _gaussians(seed, h=30, w=40):
    r = np.random.default_rng(seed)
    return PixelGaussians(
        rgb=r.random((h, w, 3), np.float32), log_radius=r.random((h, w), np.float32), opacity_logit=r.random((h, w), np.float32),
        offset=r.random((h, w), np.float32), depth=r.random((h, w), np.float32),
    )


def test_gaussian_store_spills_beyond_budget(tmp_path):
    one_mb = 1 / 2**20 * 30 * 40 * 7 * 4  # one frame, in MB
    store = GaussianStore(tmp_path / "g", budget_mb=2.5 * one_mb)
    for i in range(10):
        store.put(i, _gaussians(i))
        assert store.memory_mb <= 2.5 * one_mb
    assert store.count == 10 * 30 * 40
    for i in range(10):
        assert i in store
        for a, b in zip(jax.tree.leaves(store.get(i)), jax.tree.leaves(_gaussians(i))):
            np.testing.assert_array_equal(a, b)
    # the oldest frames are on disk only; flush writes the rest
    assert len(list((tmp_path / "g").glob("*.npz"))) == 8
    store.flush()
    assert len(list((tmp_path / "g").glob("*.npz"))) == 10
    with pytest.raises(KeyError, match="frame 11"):
        store.get(11)
    temp = GaussianStore(None, budget_mb=0)
    temp.put(0, _gaussians(0))
    root = temp.root
    assert (root / "frame_000000.npz").exists()
    temp.close()
    assert not root.exists()


@pytest.mark.slow
def test_streaming_api_matches_run(reference_run):
    """Feeding frames one at a time to `SLAM` gives `run`'s trajectory and scores, with the
    programs the run compiled in this process (none compiled again)."""
    ref_poses, ref = reference_run
    cfg = resolve_config(None, None, overrides=TINY)
    ds = open_dataset(cfg.data)
    kept = dict(programs._PROGRAMS)
    system = SLAM(cfg, ds.intrinsics, initial_pose=initial_pose(ds))
    poses = np.stack([system.add(ds[i]) for i in range(len(ds))])
    m = system.finish()
    assert programs._PROGRAMS.keys() == kept.keys() and system._step is kept[next(k for k in kept if k[0] == "track")]
    np.testing.assert_allclose(poses, ref_poses, atol=1e-6)
    for key in ("psnr", "ssim", "depth_l1_cm", "mapped_frames"):
        assert m[key] == pytest.approx(ref[key], abs=1e-6)
    # the stored Gaussians of a frame render its view as scored
    g = system.mapper.store.get(3)
    assert g.rgb.shape == (60, 80, 3) and np.isfinite(g.offset).all()


@pytest.mark.slow
def test_run_with_rendering_init(tmp_path):
    """`map.render_init` in the host loop: the guess refined from the previous frame's Gaussians,
    then GICP; the synthetic trajectory stays accurate."""
    cfg = resolve_config(None, None, max_frames=6, overrides=["map.iterations=3", "map.render_init=true", "map.render_init_iterations=10"])
    result = run(cfg, tmp_path / "ri", progress=False)
    assert result.metrics["frames"] == 6 and result.metrics["ate_rmse_cm"] < 0.05
    assert result.metrics["mapped_frames"] == 6


def test_checkpoint_of_an_older_geometry_layout_is_refused():
    """A geometry set saved before the hash table (a key array of shape (capacity,)) does not
    load into today's layout: a clear error, not a wrongly shaped state."""
    from sgad_jax import checkpoint
    from sgad_jax.config import ConfigError
    from sgad_jax.types import empty_geometry

    geom = empty_geometry(64, 0.02)
    arrays = checkpoint.flatten("state", geom)
    assert checkpoint.unflatten("state", arrays, geom).bucket_keys.shape == geom.bucket_keys.shape
    arrays["state/000"] = np.zeros(64, np.int32)  # the old sorted-key array
    with pytest.raises(ConfigError, match="another sgad_jax version"):
        checkpoint.unflatten("state", arrays, geom)
