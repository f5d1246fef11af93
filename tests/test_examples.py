"""The scripts in examples/ run, on tiny inputs, and show what they claim."""

import importlib.util
import pathlib
import sys

import numpy as np
import pytest

from sgad_jax.io.export import read_tum_trajectory

EXAMPLES = pathlib.Path(__file__).resolve().parents[1] / "examples"


def _load(name):
    spec = importlib.util.spec_from_file_location(f"example_{name}", EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # a dataclass looks its module up there
    spec.loader.exec_module(module)
    assert module.__doc__ and callable(module.main)
    return module


@pytest.mark.slow
def test_pose_gradient_matches_finite_differences():
    r = _load("pose_gradient").main(width=32, height=24, verbose=False)
    assert np.abs(r["finite_difference"]).max() > 1e-3  # away from the minimum: a gradient to check
    assert r["max_rel_error"] < 1e-5
    np.testing.assert_allclose(r["grad"], r["finite_difference"], rtol=1e-4, atol=1e-8)


@pytest.mark.slow
def test_vmap_of_map_frame_equals_a_loop():
    r = _load("vmap_map_frame").main(frames=2, width=32, height=24, iterations=3, verbose=False)
    assert r["offset"].shape == (2, 24, 32)
    assert r["max_abs_difference"] < 5e-5  # float32 rounding of two programs, carried on by Adam's steps
    assert (r["loss"][:, -1] < r["loss"][:, 0]).all()  # the batched fit does fit


@pytest.mark.slow
def test_custom_loop_without_ground_truth(tmp_path):
    out = tmp_path / "traj.txt"
    r = _load("custom_frames").main(frames=4, width=64, height=48, iterations=3, trajectory_file=out, verbose=False)
    assert r["trajectory"].shape == (4, 4, 4) and np.isfinite(r["trajectory"]).all()
    np.testing.assert_allclose(r["trajectory"][0], np.eye(4), atol=1e-6)  # the first camera is the world
    assert r["ate_rmse_cm"] < 2.0  # tracked, not just returned (the room moves ~1 cm per frame)
    assert r["metrics"]["mapped_frames"] == 4 and r["metrics"]["psnr"] > 20.0
    stamps, poses = read_tum_trajectory(out)
    assert len(stamps) == 4 and np.allclose(poses, r["trajectory"], atol=1e-6)
