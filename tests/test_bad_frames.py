"""Bad frames: each kind gets one line naming the file and the problem; a run stops (resumable)
or skips them (listed with their reasons)."""

import json
import shutil

import cv2
import numpy as np
import pytest

from conftest import shared
from sgad_jax.cli import main
from sgad_jax.config import DataConfig
from sgad_jax.io.base import BadFrame, DatasetError, read_image
from sgad_jax.io.datasets import TUMDataset, open_dataset
from sgad_jax.io.export import read_tum_trajectory


def _generic(root, n=6):
    """A generic-layout folder of ``n`` small frames; returns the depth paths."""
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    (root / "intrinsics.txt").write_text("40 40 15.5 11.5\n")
    v, u = np.mgrid[0:24, 0:32]
    paths = []
    for i in range(n):
        cv2.imwrite(str(root / "rgb" / f"{i:04d}.png"), np.full((24, 32, 3), 40 * i, np.uint8))
        paths.append(root / "depth" / f"{i:04d}.png")
        cv2.imwrite(str(paths[-1]), (1000 * (1.0 + 0.01 * u + 0.02 * v)).astype(np.uint16))
    return paths


@pytest.mark.parametrize("suffix", [".png", ".jpg"])
def test_truncated_image_is_named(tmp_path, suffix):
    path = tmp_path / f"img{suffix}"
    cv2.imwrite(str(path), np.random.default_rng(0).integers(0, 255, (48, 64, 3), dtype=np.uint8))
    assert read_image(path).shape == (48, 64, 3)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(DatasetError, match="truncated") as err:
        read_image(path)
    assert str(path) in str(err.value)


def test_depth_problems_are_bad_frames(tmp_path):
    depth = _generic(tmp_path / "d")
    cv2.imwrite(str(depth[1]), np.zeros((24, 32), np.uint16))  # all zero
    depth[2].write_bytes(b"not a png")  # unreadable (a missing file is the TUM case below)
    f32 = np.ones((24, 32), np.float32)
    f32[3, 4] = np.nan
    depth[3].unlink()
    cv2.imwrite(str(depth[3].with_suffix(".tiff")), f32)  # NaN in a float depth image
    cv2.imwrite(str(depth[4]), np.full((20, 32), 1000, np.uint16))  # another size
    ds = open_dataset(DataConfig(path=str(tmp_path / "d")))
    items = list(ds.frames(skip_bad=True))
    assert [type(x) is BadFrame for x in items] == [False, True, True, True, True, False]
    reasons = [x.reason for x in items[1:5]]
    assert "0001.png" in reasons[0] and "no valid pixel" in reasons[0]
    assert "0002.png" in reasons[1] and "cannot decode" in reasons[1]
    assert "0003.tiff" in reasons[2] and "NaN/Inf" in reasons[2]
    assert "0004.png" in reasons[3] and "24" in reasons[3] and "20" in reasons[3]
    assert all("\n" not in r for r in reasons)
    # without skip_bad the first bad frame raises after the good one before it
    gen = ds.frames()
    assert next(gen).index == 0
    with pytest.raises(DatasetError, match="no valid pixel"):
        next(gen)
    # NaN as the marker of missing depth, when the user says so
    nan_ok = open_dataset(DataConfig(path=str(tmp_path / "d"), nonfinite_depth="missing"))
    d = nan_ok[3].depth
    assert d[3, 4] == 0.0 and (np.delete(d.ravel(), 3 * 32 + 4) == 1.0).all()


def test_ground_truth_problems_are_reported_once(tmp_path):
    root = tmp_path / "replica"
    (root / "results").mkdir(parents=True)
    rows = []
    for i in range(5):
        cv2.imwrite(str(root / "results" / f"frame{i:06d}.jpg"), np.full((24, 32, 3), 90, np.uint8))
        cv2.imwrite(str(root / "results" / f"depth{i:06d}.png"), np.full((24, 32), 6553, np.uint16))
        T = np.eye(4)
        T[0, 3] = 0.1 * i
        rows.append(" ".join(map(str, T.ravel())))
    rows[2] = rows[2].replace("0.2", "inf", 1)
    (root / "traj.txt").write_text("\n".join(rows[:4]) + "\n")  # frame 4 has no line
    (root / "cam_params.json").write_text(json.dumps({"camera": {"w": 32, "h": 24, "fx": 20, "fy": 20, "cx": 15.5, "cy": 11.5, "scale": 6553.5}}))
    ds = open_dataset(DataConfig(path=str(root)))
    assert len(ds.warnings) == 2
    assert all("traj.txt" in w for w in ds.warnings)
    assert "Inf/NaN for 1 of 5 frames (first: run frame 2)" in ds.warnings[0]
    assert "missing for 1 of 5 frames (first: run frame 4)" in ds.warnings[1]
    known = np.isfinite(ds.gt_poses).all(axis=(1, 2))
    assert known.tolist() == [True, True, False, True, False]
    assert np.isnan(ds.gt_poses[2]).all()


def _tum_copy(tmp_path):
    """A copy of tum_fr1_xyz, and three frames with depth images of their own (TUM pairs some
    colour images with a shared depth image)."""
    src = shared("tum_fr1_xyz")
    dst = tmp_path / "rgbd_dataset_freiburg1_xyz"
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("accelerometer.txt"))
    ds = TUMDataset(dst, DataConfig(path=str(dst)))
    counts = {p: ds.depth_paths.count(p) for p in ds.depth_paths}
    own = [i for i in range(3, len(ds) - 3) if counts[ds.depth_paths[i]] == 1]
    picks = own[1], own[len(own) // 2], own[-2]
    return dst, ds, picks


@pytest.mark.slow
def test_bad_tum_frames_stop_resume_and_skip(tmp_path, capsys):
    """The acceptance case: one colour PNG truncated, one depth PNG deleted, one depth image
    zeroed. stop: status 2, one line naming the first bad file, and --resume after the fix gives
    the clean run's trajectory; skip: the run completes, lists the three frames with reasons, and
    its ATE is within 10 % of the clean run's."""
    data, ds, (a, b, c) = _tum_copy(tmp_path)
    base = ["--data", str(data), "--track-only", "--quiet"]
    assert main(["run", *base, "--out", str(tmp_path / "clean")]) == 0
    clean = json.loads((tmp_path / "clean" / "metrics.json").read_text())
    assert clean["skipped_frames"] == []

    keep = {p: p.read_bytes() for p in (ds.rgb_paths[a], ds.depth_paths[b], ds.depth_paths[c])}

    def corrupt():
        ds.rgb_paths[a].write_bytes(keep[ds.rgb_paths[a]][:-2000])
        ds.depth_paths[b].unlink()
        cv2.imwrite(str(ds.depth_paths[c]), np.zeros((480, 640), np.uint16))
        capsys.readouterr()

    corrupt()

    out = tmp_path / "stop"
    assert main(["run", *base, "--out", str(out), "--checkpoint-every", "10"]) == 2
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and str(ds.rgb_paths[a]) in lines[0] and "truncated" in lines[0] and "Traceback" not in err
    assert len(read_tum_trajectory(out / "trajectory.txt")[0]) == a  # every frame before it
    for path, content in keep.items():  # fixed
        path.write_bytes(content)
    assert main(["run", *base, "--out", str(out), "--checkpoint-every", "10", "--resume"]) == 0
    resumed = json.loads((out / "metrics.json").read_text())
    assert resumed["resumed_from_frame"] == a and resumed["frames"] == len(ds)
    np.testing.assert_allclose(read_tum_trajectory(out / "trajectory.txt")[1], read_tum_trajectory(tmp_path / "clean" / "trajectory.txt")[1], atol=1e-5)

    corrupt()
    out = tmp_path / "skip"
    assert main(["run", *base, "--out", str(out), "--on-bad-frame", "skip"]) == 0
    err = capsys.readouterr().err
    m = json.loads((out / "metrics.json").read_text())
    assert [r["index"] for r in m["skipped_frames"]] == [a, b, c]
    assert "truncated" in m["skipped_frames"][0]["reason"] and "not found" in m["skipped_frames"][1]["reason"]
    assert "no valid pixel" in m["skipped_frames"][2]["reason"]
    assert sum("skipped:" in ln for ln in err.splitlines()) == 3
    assert m["frames"] == len(ds) - 3 == len(read_tum_trajectory(out / "trajectory.txt")[0])
    assert abs(m["ate_rmse_cm"] - clean["ate_rmse_cm"]) <= 0.1 * clean["ate_rmse_cm"]


@pytest.mark.slow
def test_timestamps_must_increase(tmp_path, capsys):
    root = tmp_path / "tum"
    for sub in ("rgb", "depth"):
        (root / sub).mkdir(parents=True)
    v, u = np.mgrid[0:480, 0:640]  # TUM's size and preset: the tracking step of the other TUM runs, from the shared cache
    stamps = [1.0, 2.0, 1.5, 3.0, 4.0]  # the third goes back in time
    for k, t in enumerate(stamps):
        cv2.imwrite(str(root / "rgb" / f"{k}.png"), np.full((480, 640, 3), 100, np.uint8))
        cv2.imwrite(str(root / "depth" / f"{k}.png"), (5000 * (1.0 + 0.0005 * u + 0.0007 * v)).astype(np.uint16))
    (root / "rgb.txt").write_text("".join(f"{t} rgb/{k}.png\n" for k, t in enumerate(stamps)))
    (root / "depth.txt").write_text("".join(f"{t + 0.001} depth/{k}.png\n" for k, t in enumerate(stamps)))
    out = tmp_path / "out"
    code = main(["run", "--data", str(root), "--out", str(out), "--track-only", "--quiet", "--on-bad-frame", "skip"])
    assert code == 0
    m = json.loads((out / "metrics.json").read_text())
    assert len(m["skipped_frames"]) == 1 and "rgb/2.png" in m["skipped_frames"][0]["reason"]
    assert "not after the previous frame's" in m["skipped_frames"][0]["reason"]


def _tiny_tum(root, n=5):
    """A TUM-layout folder of ``n`` small frames 0.1 s apart, with ground truth."""
    for sub in ("rgb", "depth"):
        (root / sub).mkdir(parents=True)
    for k in range(n):
        cv2.imwrite(str(root / "rgb" / f"{k}.png"), np.full((24, 32, 3), 100, np.uint8))
        cv2.imwrite(str(root / "depth" / f"{k}.png"), np.full((24, 32), 5000, np.uint16))
    (root / "rgb.txt").write_text("# colour\n" + "".join(f"{1 + 0.1 * k:.3f} rgb/{k}.png\n" for k in range(n)))
    (root / "depth.txt").write_text("# depth\n" + "".join(f"{1.001 + 0.1 * k:.3f} depth/{k}.png\n" for k in range(n)))
    (root / "groundtruth.txt").write_text("".join(f"{1 + 0.05 * k:.3f} {0.01 * k} 0 0 0 0 0 1\n" for k in range(2 * n)))
    return root


@pytest.mark.parametrize("name,line", [("rgb.txt", 3), ("depth.txt", 2), ("groundtruth.txt", 4)])
def test_a_timestamp_that_is_not_a_number_is_named_with_its_line(tmp_path, name, line):
    """A NaN stamp compares false with every tolerance, so the association would take it for the
    nearest of all frames (one depth image or one pose for the whole run): an error with its line."""
    root = _tiny_tum(tmp_path / "tum")
    lines = (root / name).read_text().splitlines(keepends=True)
    lines[line - 1] = "nan " + lines[line - 1].split(maxsplit=1)[1]
    (root / name).write_text("".join(lines))
    with pytest.raises(DatasetError) as err:
        open_dataset(DataConfig(path=str(root)))
    assert str(err.value) == f"{root / name}: line {line}: timestamp 'nan' is not a finite number"


def test_tum_lists_tolerate_a_byte_order_mark_and_odd_bytes_and_report_unmatched_frames(tmp_path):
    root = _tiny_tum(tmp_path / "tum")
    rgb = (root / "rgb.txt").read_bytes()
    (root / "rgb.txt").write_bytes(b"\xef\xbb\xbf# caf\xe9 (latin-1)\n" + rgb)  # a BOM, and a byte that is not UTF-8
    depth = (root / "depth.txt").read_text().splitlines(keepends=True)
    (root / "depth.txt").write_text("".join(depth[:3]))  # depth for the first two colour frames only
    ds = open_dataset(DataConfig(path=str(root)))
    assert len(ds) == 2 and ds.layout == "tum"
    assert ds.warnings == [f"{root / 'depth.txt'}: 3 of the 5 colour frames of rgb.txt have no stamp here within 0.08 s; they are left out"]
    (root / "depth.txt").unlink()  # rgb.txt alone is still TUM: the missing list is named
    with pytest.raises(DatasetError, match=f"^{root / 'depth.txt'}: file not found$"):
        open_dataset(DataConfig(path=str(root)))


def test_images_that_cannot_be_frames_say_why(tmp_path):
    depth8 = tmp_path / "depth8.png"
    cv2.imwrite(str(depth8), np.full((24, 32), 200, np.uint8))  # a preview or a mask, not depth
    folder = tmp_path / "folder.png"
    folder.mkdir()
    dangling = tmp_path / "dangling.png"
    dangling.symlink_to(tmp_path / "nowhere.png")
    loop = tmp_path / "loop.png"
    loop.symlink_to(loop)
    for path, depth, why in [(depth8, True, "depth image is 8-bit"), (folder, False, "a folder, not a file"), (dangling, False, "broken symbolic link"), (loop, False, "broken symbolic link")]:
        with pytest.raises(DatasetError) as err:
            read_image(path, depth=depth)
        assert str(err.value).startswith(f"{path}: {why}")
    cv2.imwrite(str(depth8), np.full((24, 32), 200, np.uint16))
    assert read_image(depth8, depth=True).dtype == np.uint16


def test_a_bad_frame_after_a_checkpoint_stops_in_one_line_and_resumes_from_any_spelling_of_the_path(tmp_path, capsys):
    """The frame after a periodic checkpoint is bad: the stop writes that checkpoint's step again
    (orbax refuses a step twice); --resume with the folder spelled another way, while the frame is
    still bad, stops again the same way; fixed, it completes. A fresh run into the folder removes an
    earlier run's exports, which would no longer match it."""
    depth = _generic(tmp_path / "d")
    good = depth[3].read_bytes()
    depth[3].write_bytes(b"not a png")
    out = tmp_path / "out"
    out.mkdir()
    for stale in ("gaussians.ply", "mesh.ply", "eval.json", "report.md", "trajectory.png"):
        (out / stale).write_text("an earlier run's")
    args = ["run", "--track-only", "--quiet", "--out", str(out), "--checkpoint-every", "3"]
    (tmp_path / "x").mkdir()
    for spelling, resume in [(tmp_path / "d", []), (f"{tmp_path / 'd'}/", ["--resume"]), (tmp_path / "x" / ".." / "d", ["--resume"])]:
        code = main([*args, "--data", str(spelling), *resume])
        err = capsys.readouterr().err
        lines = [ln for ln in err.splitlines() if ln.strip()]
        assert code == 2 and len(lines) == 1 and "0003.png: cannot decode" in lines[0] and "Traceback" not in err
        assert len(read_tum_trajectory(out / "trajectory.txt")[0]) == 3
    assert not any((out / stale).exists() for stale in ("gaussians.ply", "mesh.ply", "eval.json", "report.md", "trajectory.png"))
    depth[3].write_bytes(good)
    assert main([*args, "--data", str(tmp_path / "d") + "/", "--resume"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["resumed_from_frame"] == 3 and m["frames"] == 6
