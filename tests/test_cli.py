"""The command line end to end, and its answers to bad input."""

import errno
import json
import os
import subprocess
import sys

import cv2
import numpy as np
import pytest

from conftest import shared
from sgad_jax.cli import main
from sgad_jax.io.export import read_tum_trajectory

# 3 iterations as test_distributed's 320x240 run: the mapping program comes from the shared cache
SMALL = ["--set", "data.synthetic.frames=10", "--set", "map.iterations=3"]


def _run(args, capsys):
    code = main(args)
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.slow
def test_synthetic_run_as_module(tmp_path):
    """`python -m sgad_jax run` on the built-in scene writes a TUM trajectory and metrics."""
    out = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "sgad_jax", "run", "--out", str(out), "--max-frames", "6", "--quiet", "--save-renders", *SMALL],
        capture_output=True, text=True, timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    stamps, poses = read_tum_trajectory(out / "trajectory.txt")
    assert len(stamps) == 6 and np.isfinite(poses).all()
    m = json.loads((out / "metrics.json").read_text())
    for key in ("frames", "ate_rmse_cm", "ate_mean_cm", "track_ms_median", "compile_s", "peak_rss_mb", "config"):
        assert key in m
    assert m["frames"] == 6 and m["ate_rmse_cm"] < 0.05
    assert m["config"]["data"]["synthetic"]["frames"] == 10
    assert json.loads(proc.stdout.strip().splitlines()[-1])["frames"] == 6
    # the appearance branch: image metrics of every frame's render, and the renders themselves
    for key in ("psnr", "ssim", "ms_ssim", "lpips", "depth_l1_cm", "map_s_per_frame"):
        assert key in m
    assert m["mapped_frames"] == 6 and 20.0 < m["psnr"] < 80.0 and 0.5 < m["ssim"] <= 1.0
    for i in range(6):
        rgb = cv2.imread(str(out / "renders" / f"rgb_{i:06d}.png"), cv2.IMREAD_UNCHANGED)
        depth = cv2.imread(str(out / "renders" / f"depth_{i:06d}.png"), cv2.IMREAD_UNCHANGED)
        assert rgb.shape == (240, 320, 3) and rgb.dtype == np.uint8
        assert depth.shape == (240, 320) and depth.dtype == np.uint16
        assert 500 < np.median(depth) < 10000  # millimetres: the room is metres deep


def _write_generic(root, n=4, bad=None):
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    (root / "intrinsics.txt").write_text("40 40 15.5 11.5\n")
    v, u = np.mgrid[0:24, 0:32]
    for i in range(n):
        cv2.imwrite(str(root / "rgb" / f"{i:04d}.png"), np.full((24, 32, 3), 40 * i, np.uint8))
        depth = (1000 * (1.0 + 0.01 * u + 0.02 * v + 0.002 * i)).astype(np.uint16)
        cv2.imwrite(str(root / "depth" / f"{i:04d}.png"), depth)
    if bad is not None:
        (root / "depth" / f"{bad:04d}.png").write_bytes(b"not a png")


@pytest.mark.slow
def test_corrupt_frame_keeps_results(tmp_path, capsys):
    data, out = tmp_path / "data", tmp_path / "out"
    _write_generic(data, n=4, bad=2)
    code, _, err = _run(["run", "--data", str(data), "--out", str(out), "--quiet", "--track-only", "--plots", "--set", "track.stride=2"], capsys)
    assert code == 2 and "(--plots not made: --resume finishes the run and makes them)" in err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "0002.png" in lines[0] and "Traceback" not in err
    stamps, _ = read_tum_trajectory(out / "trajectory.txt")
    assert len(stamps) == 2  # frames 0 and 1 were tracked before the bad one
    assert "0002.png" in json.loads((out / "metrics.json").read_text())["stopped"]


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--data", "/nonexistent/folder"], "/nonexistent/folder"),
        (["--config", "nosuchpreset"], "nosuchpreset"),
        (["--set", "track.nosuchfield=1"], "nosuchfield"),
        (["--set", "track.stride=abc"], "track.stride"),
        (["--track-only", "--set", "track.coarse=3,0"], "track.coarse"),
        # out of range: each used to fail deep in a compiled step (a traceback), after tracking had
        # begun (results lost), or to run silently wrong
        (["--set", "track.voxel_size=0"], "track.voxel_size: must be > 0, got 0.0"),
        (["--set", "track.voxel_size=nan"], "track.voxel_size: must be > 0, got nan"),
        (["--set", "track.capacity=0"], "track.capacity: must be >= 1"),
        (["--set", "track.k=0"], "track.k within [3, window^2]"),
        (["--set", "track.window=4"], "track.window must be odd"),
        (["--set", "map.neighbours=-1"], "map.neighbours: must be >= 0"),
        (["--set", "map.iterations=-1"], "map.iterations: must be >= 0"),
        (["--set", "data.tum_max_dt=0"], "data.tum_max_dt: must be > 0"),
        (["--finetune", "-5"], "--finetune and --checkpoint-every must be >= 0, got -5 and 25"),
        (["--checkpoint-every", "-3"], "must be >= 0, got 0 and -3"),
        (["--compile-cache", "/etc/passwd"], "--compile-cache /etc/passwd: not a folder"),
        (["--coordinator", "nonsense"], "--coordinator nonsense: expected HOST:PORT"),
        (["--num-processes", "2", "--process-id", "0"], "need --coordinator HOST:PORT"),
        (["--coordinator", "127.0.0.1:1", "--num-processes", "2", "--process-id", "5"], "--process-id must lie in [0, --num-processes); got 5 of 2"),
        (["--config", "demo", "--data", "/nonexistent/folder"], "/nonexistent/folder: folder not found"),
    ],
)
def test_bad_arguments_one_line(tmp_path, capsys, args, needle):
    code, _, err = _run(["run", "--out", str(tmp_path / "o"), "--quiet", *args], capsys)
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and needle in err and "Traceback" not in err


def test_unknown_layout(tmp_path, capsys):
    (tmp_path / "stuff").mkdir()
    (tmp_path / "stuff" / "readme.txt").write_text("hello")
    code, _, err = _run(["run", "--data", str(tmp_path / "stuff"), "--out", str(tmp_path / "o"), "--quiet"], capsys)
    assert code == 2 and "stuff" in err and len(err.strip().splitlines()) == 1


@pytest.mark.slow
def test_tum_real_frames(tmp_path, capsys):
    data = shared("tum_fr1_xyz")
    out = tmp_path / "tum"
    code, stdout, _ = _run(["run", "--data", str(data), "--out", str(out), "--max-frames", "8", "--track-only", "--quiet"], capsys)
    assert code == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["frames"] == 8 and m["config"]["track"]["k"] == 23 and m["ate_rmse_cm"] < 2.0
    stamps, _ = read_tum_trajectory(out / "trajectory.txt")
    assert stamps[0] == pytest.approx(1305031102.175304, abs=1e-5)  # TUM timestamps, not indices


@pytest.mark.slow
def test_compile_cache_serves_a_second_run(tmp_path):
    """`--compile-cache DIR`: the first run stores its compiled tracking step there; a second run of
    the same command finds it (writes no new entry) and gets the same trajectory; `off` writes none."""
    cache = tmp_path / "cache"
    runs, entries = [], []
    for i in range(2):
        out = tmp_path / f"run{i}"
        proc = subprocess.run(
            [sys.executable, "-m", "sgad_jax", "run", "--out", str(out), "--max-frames", "4", "--quiet", "--track-only",
             "--compile-cache", str(cache), *SMALL],
            capture_output=True, text=True, timeout=600,
        )
        assert proc.returncode == 0, proc.stderr
        entries.append(sorted(p.name for p in cache.iterdir()))
        runs.append(read_tum_trajectory(out / "trajectory.txt")[1])
    assert entries[0] and entries[1] == entries[0]
    np.testing.assert_array_equal(runs[0], runs[1])
    proc = subprocess.run(
        [sys.executable, "-m", "sgad_jax", "run", "--out", str(tmp_path / "off"), "--max-frames", "4", "--quiet", "--track-only",
         "--compile-cache", "off", *SMALL],
        capture_output=True, text=True, timeout=600, env={**os.environ, "JAX_COMPILATION_CACHE_DIR": str(tmp_path / "env")},
    )
    assert proc.returncode == 0, proc.stderr
    assert not (tmp_path / "env").exists() or not any((tmp_path / "env").iterdir())


def test_unwritable_output_folder_fails_before_any_work(tmp_path, capsys):
    from sgad_jax.cli import main

    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    assert main(["run", "--quiet", "--track-only", "--out", str(blocker / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(blocker / "out") in err[0] and "cannot be written" in err[0]


FREED_IN_THE_HEAP = """
import numpy as np
from sgad_jax.pipeline import current_rss_mb, release_freed_memory
big = np.ones(9 * 2**20 // 8); del big  # freed from its own mapping: glibc's mmap threshold rises past it
base = current_rss_mb()
blocks = [np.ones(2**19) for _ in range(20)]  # 4 MB each, now served from the heap
keep = blocks[-1]; del blocks  # the last block pins the heap's top, so free() cannot shrink it
freed = current_rss_mb()
release_freed_memory()
print(base, freed, current_rss_mb())
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="needs /proc for the resident size")
def test_memory_freed_in_the_heap_goes_back_to_the_system():
    """What let a long run's resident memory creep up without a leak: blocks freed inside glibc's
    heap stay resident until ``release_freed_memory`` (which the run calls every RSS_EVERY frames)."""
    proc = subprocess.run([sys.executable, "-c", FREED_IN_THE_HEAP], capture_output=True, text=True, check=True)
    base, freed, after = map(float, proc.stdout.split())
    if freed - base < 50:
        pytest.skip(f"this C library returned the freed blocks itself ({freed - base:.0f} MB kept)")
    assert after - base < 15, (base, freed, after)


@pytest.mark.slow
def test_full_disk_mid_run_is_one_line_and_keeps_the_trajectory(tmp_path, capsys, monkeypatch):
    """The output disk fills up while a mapping run writes its frames' Gaussians (at the
    checkpoint after frame 4): one line naming the file and the problem, exit status 2, no
    temporary file left, and the trajectory and metrics of the frames done still written."""
    from sgad_jax.io import store

    real, calls = np.savez, []

    def savez(f, **arrays):
        calls.append(1)
        if len(calls) >= 3:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(f, **arrays)

    monkeypatch.setattr(store.np, "savez", savez)
    out = tmp_path / "run"
    code, _, err = _run(["run", "--quiet", *SMALL, "--out", str(out), "--checkpoint-every", "4"], capsys)
    assert code == 2
    lines = [ln for ln in err.splitlines() if ln.strip()]
    frame = out / "gaussians" / "frame_000002.npz"
    assert len(lines) == 1 and f"{frame}: cannot write (No space left on device)" in lines[0] and "Traceback" not in err
    assert not frame.exists() and not list((out / "gaussians").glob(".*.tmp"))
    stamps, _ = read_tum_trajectory(out / "trajectory.txt")
    m = json.loads((out / "metrics.json").read_text())
    assert len(stamps) == m["frames"] == 4 and "No space left on device" in m["stopped"]


@pytest.mark.slow
def test_full_disk_in_the_refinement_is_one_line_and_keeps_the_trajectory(tmp_path, capsys, monkeypatch):
    """The disk fills up under the refinement's spilled Gaussians (its temporary folder): one line
    naming the file, exit status 2, and the run's trajectory and metrics still written."""
    from sgad_jax.io import store

    real = store.atomic_write

    def atomic_write(path, write):
        if "sgad_gaussians_" in str(path):  # a temporary store's file (the run's own are under --out)

            def write(f):
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        return real(path, write)

    monkeypatch.setattr(store, "atomic_write", atomic_write)
    out = tmp_path / "run"
    args = ["run", "--quiet", "--out", str(out), "--checkpoint-every", "0", "--holdout-every", "4", "--finetune", "3"]
    for kv in ("data.synthetic.width=80", "data.synthetic.height=60", "data.synthetic.frames=9", "map.iterations=3", "scene.frames=3", "scene.finetune_budget_mb=0.05"):
        args += ["--set", kv]
    code, _, err = _run(args, capsys)
    assert code == 2
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "cannot write (No space left on device)" in lines[0] and "Traceback" not in err
    stamps, _ = read_tum_trajectory(out / "trajectory.txt")
    m = json.loads((out / "metrics.json").read_text())
    assert len(stamps) == m["frames"] == 9 and "No space left on device" in m["stopped"]
    assert m["nvs_frames"] == 2 and 5 < m["nvs_psnr_before_finetune"] < 60  # the held-out scores before the refinement


def test_checkpoint_write_failures_are_one_line(tmp_path, monkeypatch):
    """orbax's I/O errors (tensorstore's status-coded ValueErrors, OSErrors) become one line naming
    the checkpoint folder; other errors pass through."""
    import orbax.checkpoint as ocp

    from sgad_jax import checkpoint
    from sgad_jax.io.base import DatasetError

    arrays, meta = {"x": np.zeros(3, np.float32)}, {"identity": {"a": 1}, "run": {}}
    for raised, reason in [
        (ValueError("RESOURCE_EXHAUSTED: Error writing \"x/0\": Failed to write 8 bytes: No space left on device [os_error_code='28']"), "No space left on device"),
        (PermissionError(errno.EACCES, os.strerror(errno.EACCES)), os.strerror(errno.EACCES)),
    ]:
        monkeypatch.setattr(ocp.CheckpointManager, "save", lambda self, *a, raised=raised, **k: (_ for _ in ()).throw(raised))
        with pytest.raises(DatasetError) as err:
            checkpoint.save(tmp_path / "ckpt", 4, arrays, meta)
        assert str(err.value) == f"{tmp_path / 'ckpt'}: cannot write checkpoint 4 ({reason})"
    monkeypatch.setattr(ocp.CheckpointManager, "save", lambda self, *a, **k: (_ for _ in ()).throw(ValueError("a bug")))
    with pytest.raises(ValueError, match="a bug"):
        checkpoint.save(tmp_path / "ckpt", 4, arrays, meta)
    monkeypatch.undo()
    checkpoint.save(tmp_path / "ckpt", 4, arrays, meta)  # and the real one writes
    got, got_meta = checkpoint.latest(tmp_path / "ckpt")
    assert got_meta == meta and np.array_equal(got["x"], arrays["x"])


def test_a_damaged_checkpoint_is_passed_over_for_the_one_before(tmp_path, capsys):
    """The newest step cut short by hand or by a crash of the disk (its meta gone), or a stray step
    folder: --resume takes the step before with a warning line, and removes the damaged one so
    that the run can write that step again; with no readable step, one line."""
    import shutil

    from sgad_jax import checkpoint
    from sgad_jax.io.base import DatasetError

    root = tmp_path / "ckpt"
    for step in (4, 8):
        checkpoint.save(root, step, {"x": np.full(3, step, np.float32)}, {"identity": {}, "run": {"next": step}})
    shutil.rmtree(root / "8" / "meta")
    (root / "12").mkdir()  # a stray folder
    capsys.readouterr()
    arrays, meta = checkpoint.latest(root)
    assert meta["run"]["next"] == 4 and (arrays["x"] == 4).all()
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 2 and all("damaged checkpoint" in ln and "resuming from step 4" in ln for ln in err)
    assert sorted(p.name for p in root.iterdir()) == ["4"]
    checkpoint.save(root, 8, {"x": np.full(3, 8, np.float32)}, {"identity": {}, "run": {"next": 8}})  # written again
    shutil.rmtree(root / "8" / "arrays")
    shutil.rmtree(root / "4" / "meta")
    with pytest.raises(DatasetError, match=f"^{root / '8'}: damaged checkpoint .*no older one is readable"):
        checkpoint.latest(root)


def test_output_files_follow_the_umask(tmp_path):
    """Not mkstemp's 0600: a folder shared by the processes of a run, or with other users, can read them."""
    from sgad_jax.io.files import write_text

    umask = os.umask(0o022)
    os.umask(umask)
    assert (write_text(tmp_path / "a.json", "{}").stat().st_mode & 0o777) == 0o666 & ~umask != 0o600


def test_the_data_path_is_saved_absolute_and_the_demo_preset_reads_it(tmp_path, monkeypatch):
    """A run's config names its data from any folder (`eval --rerender`, `eval-mesh` read it again
    later); `--config demo --data DIR` reads DIR, where the demo's synthetic layout ignored it."""
    from sgad_jax.cli import resolve_config

    (tmp_path / "rgb").mkdir()
    monkeypatch.chdir(tmp_path.parent)
    cfg = resolve_config("demo", f"{tmp_path.name}/rgb/..")
    assert cfg.data.path == str(tmp_path) and cfg.data.layout == "auto"
    assert resolve_config("demo").data.layout == "synthetic"


def test_options_that_would_do_nothing_say_so(tmp_path, capsys):
    """`--holdout-every` / `--finetune` on a track-only run (no map to judge), and a held-out
    interval longer than the run: a warning line each, in metrics.json too, not silence."""
    out = tmp_path / "o"
    args = ["run", "--quiet", "--out", str(out), "--track-only", "--checkpoint-every", "0", "--set", "data.synthetic.frames=4",
            "--set", "data.synthetic.width=80", "--set", "data.synthetic.height=60", "--holdout-every", "8", "--finetune", "5"]
    code, _, err = _run(args, capsys)
    assert code == 0 and "ignored with --track-only" in err
    assert json.loads((out / "metrics.json").read_text())["data_warnings"] == ["--holdout-every and --finetune judge and refine the map: ignored with --track-only"]
    code, _, err = _run([a for a in args if a != "--track-only"], capsys)
    assert code == 0 and "--holdout-every 8: the run has 4 frames, so none is held out" in err


def test_plots_of_a_two_frame_run_say_why_there_is_no_error_plot(tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["run", "--quiet", "--out", str(out), "--track-only", "--set", "data.synthetic.frames=2", "--set", "data.synthetic.width=80", "--set", "data.synthetic.height=60"]) == 0
    code, _, err = _run(["plots", str(out)], capsys)
    assert code == 0 and "ate_per_frame.png not drawn: fewer than 3 frames to align" in err  # the scene has ground truth
