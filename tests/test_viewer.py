"""``sgad-jax view``: answers HTTP on its port on a headless machine, and fails cleanly on bad input."""

import json
import os
import socket
import subprocess
import sys
import threading
import time
import urllib.request

import numpy as np
import pytest

from sgad_jax.io.export import write_tum_trajectory
from sgad_jax.io.ply import write_mesh_ply

pytest.importorskip("viser", reason="the viewer extra (viser) is not installed")


def fabricate_run(root, frames=3, h=12, w=16):
    """A run folder as the pipeline writes it: trajectory, cameras.json, Gaussians, one render, a mesh."""
    import cv2

    rng = np.random.default_rng(0)
    poses = np.tile(np.eye(4), (frames, 1, 1))
    poses[:, 0, 3] = 0.1 * np.arange(frames)
    write_tum_trajectory(root / "trajectory.txt", np.arange(frames, dtype=float), poses)
    (root / "cameras.json").write_text(json.dumps({"width": w, "height": h, "fx": 20.0, "fy": 20.0, "cx": 7.5, "cy": 5.5}))
    (root / "gaussians").mkdir()
    for i in range(frames):
        np.savez(
            root / "gaussians" / f"frame_{i:06d}.npz",
            rgb=rng.random((h, w, 3), dtype=np.float32), log_radius=np.full((h, w), np.log(0.02), np.float32),
            opacity_logit=np.full((h, w), 2.0, np.float32), offset=np.zeros((h, w), np.float32), depth=np.full((h, w), 1.5, np.float32),
        )
    (root / "renders").mkdir()
    cv2.imwrite(str(root / "renders" / "rgb_000000.png"), np.full((h, w, 3), 128, np.uint8))
    cv2.imwrite(str(root / "renders" / "depth_000000.png"), np.full((h, w), 1500, np.uint16))
    write_mesh_ply(root / "mesh.ply", [[0, 0, 1], [1, 0, 1], [0, 1, 1]], [[0, 1, 2]], [[255, 0, 0]] * 3)
    return poses


def test_merged_gaussians_in_world_coordinates(tmp_path):
    """Gaussian (v, u) of frame i lies on pixel (v, u)'s ray at |depth + offset|, moved by the frame's pose."""
    from sgad_jax.viewer import merged_gaussians

    fabricate_run(tmp_path)
    g = merged_gaussians(tmp_path, max_count=10_000)
    assert g["total"] == 3 * 12 * 16 and len(g["centers"]) == g["total"]
    assert np.allclose(g["centers"][:, 2], 1.5)
    # frame 0 (identity): x spans (u - cx) / fx * z over u = 0..15; the others are shifted by 0.1 m per frame
    xs = np.sort(np.unique(np.round(g["centers"][:, 0], 5)))
    assert xs.min() == pytest.approx(-7.5 / 20 * 1.5) and xs.max() == pytest.approx(7.5 / 20 * 1.5 + 0.2)
    assert np.allclose(g["covariances"][:, 0, 0], (0.02 / 3) ** 2) and np.allclose(g["opacities"], 1 / (1 + np.exp(-2.0)))
    few = merged_gaussians(tmp_path, max_count=100)
    assert 40 < len(few["centers"]) < 200  # subsampled to about the count asked for


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_view_answers_http(tmp_path):
    fabricate_run(tmp_path)
    port = _free_port()
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([os.getcwd(), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.Popen(
        [sys.executable, "-m", "sgad_jax", "view", str(tmp_path), "--host", "127.0.0.1", "--port", str(port)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
    )
    try:
        deadline, status = time.monotonic() + 60, None
        while time.monotonic() < deadline and proc.poll() is None:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=2) as r:
                    status = r.status
                    body = r.read(200)
                break
            except OSError:
                time.sleep(0.5)
        assert proc.poll() is None, proc.stderr.read().decode()
        assert status == 200 and body
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()


def test_view_bad_folder_one_line(tmp_path, capsys):
    from sgad_jax.cli import main

    assert main(["view", str(tmp_path / "nowhere")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "run folder not found" in err


@pytest.mark.slow
def test_run_with_live_viewer_answers_http_while_and_after_it_runs(tmp_path):
    """`sgad-jax run --viewer PORT` serves the page during the run (the cameras appear as frames
    are tracked) and, when it is done, the finished scene until it is stopped."""
    port = _free_port()
    out = tmp_path / "run"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([os.getcwd(), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.Popen(
        [sys.executable, "-m", "sgad_jax", "run", "--out", str(out), "--track-only", "--quiet", "--max-frames", "40",
         "--set", "data.synthetic.frames=40", "--checkpoint-every", "0", "--viewer", str(port), "--viewer-host", "127.0.0.1"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
    )
    try:
        deadline, during, after = time.monotonic() + 300, None, None
        while time.monotonic() < deadline and proc.poll() is None:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=2) as r:
                    if r.status == 200:
                        done = (out / "metrics.json").exists()
                        during = during or not done
                        if done:
                            after = True
                            break
            except OSError:
                pass
            time.sleep(0.2)
        assert proc.poll() is None, proc.stderr.read().decode()
        assert after, "the viewer answered after the run"
        assert during, "the viewer answered while frames were being tracked"
    finally:
        proc.terminate()
        proc.wait(timeout=30)


@pytest.mark.parametrize("taken", [False, True], ids=["out_of_range", "in_use"])
def test_view_bad_port_one_line(tmp_path, capsys, taken):
    """A port out of range, or one in use, is one line and status 2. viser starts in a thread of its
    own: there a bad port was a traceback and a wait that never ended, and a taken one a silent move
    to the next port. The command runs in a thread here so that a hang fails the test."""
    from sgad_jax.cli import main

    fabricate_run(tmp_path)
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1] if taken else 99999
        code = []
        argv = ["view", str(tmp_path), "--host", "127.0.0.1", "--port", str(port)]
        worker = threading.Thread(target=lambda: code.append(main(argv)), daemon=True)
        worker.start()
        worker.join(60)
    assert code == [2], "sgad-jax view did not return"
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(port) in err, err


def test_a_taken_live_viewer_port_stops_the_run_before_it_clears_the_folder(tmp_path, capsys):
    """`run --viewer PORT` into the folder of an earlier run, the port taken: one line, and the
    earlier run's files are all still there (they used to be removed before the port was tried)."""
    from sgad_jax.cli import main

    out = tmp_path / "run"
    fabricate_run(out)
    (out / "gaussians.ply").write_text("an earlier run's")
    before = sorted(p.relative_to(out) for p in out.rglob("*"))
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        code = main(["run", "--quiet", "--out", str(out), "--viewer", str(port), "--viewer-host", "127.0.0.1", "--set", "data.synthetic.frames=3"])
    assert code == 2 and "cannot listen on 127.0.0.1" in capsys.readouterr().err
    assert sorted(p.relative_to(out) for p in out.rglob("*")) == before
