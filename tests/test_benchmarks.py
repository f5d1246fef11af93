"""The tracking benchmark runs end to end and prints its JSON (it had silently broken once)."""

import json
import pathlib
import subprocess
import sys

import pytest

from conftest import shared

ROOT = pathlib.Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_bench_track_prints_both_trackers():
    data = shared("tum_fr1_xyz")
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "bench_track.py"), "--data", str(data), "--max-frames", "6", "--rounds", "2"],
        capture_output=True, text=True, timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert out["frames"] == 6 and len(out["rounds_ms"]) == 2
    # both trackers follow the camera over 6 frames of fr1/xyz to within a centimetre
    assert out["ours_ate_cm"] < 1.0 and out["small_gicp_ate_cm"] < 1.0
