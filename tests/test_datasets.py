"""Dataset loaders: tiny folders in each real layout (see shared/DATASETS.md), then the real data if present."""

from __future__ import annotations

import json
import math
import os
import pathlib
import shutil
import threading
import time

import cv2
import jax
import numpy as np
import pytest

from sgad_jax.config import DataConfig
from sgad_jax.io import datasets as ds
from sgad_jax.config import ConfigError, SLAMConfig, apply_overrides
from sgad_jax.io import base
from sgad_jax.io.base import DatasetError, add_depth_noise, inpaint_depth, read_image
from sgad_jax.io.datasets import (
    GenericDataset,
    ReplicaDataset,
    ScanNetDataset,
    ScanNetPPDataset,
    SevenScenesDataset,
    TUMDataset,
    detect_layout,
    open_dataset,
)

H, W = 24, 32  # small frames wherever the layout allows


# --- writing helpers -----------------------------------------------------------------------------


def write_rgb(path: pathlib.Path, rgb) -> None:
    """Write an RGB image (``rgb`` is a (h, w, 3) array or a constant (r, g, b) at H x W)."""
    rgb = np.asarray(rgb, np.uint8)
    if rgb.ndim == 1:
        rgb = np.broadcast_to(rgb, (H, W, 3))
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1]))


def write_depth(path: pathlib.Path, depth, shape=(H, W)) -> None:
    """Write a uint16 depth PNG (``depth`` is an array or a constant)."""
    depth = np.asarray(depth)
    if depth.ndim == 0:
        depth = np.full(shape, depth)
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), depth.astype(np.uint16))


def translate(x, y, z) -> np.ndarray:
    t = np.eye(4)
    t[:3, 3] = x, y, z
    return t


def rot_z(theta) -> np.ndarray:
    c, s = math.cos(theta), math.sin(theta)
    r = np.eye(4)
    r[:2, :2] = [[c, -s], [s, c]]
    return r


def cfg(path, **kw) -> DataConfig:
    return DataConfig(path=str(path), **kw)


# --- fixtures in each layout ---------------------------------------------------------------------

T0 = 1305031452.0
# rgb stamps: a, b, b + 0.02 (depth of b 0.01 s before it, but dropped: < 1/32 s after b), c, c + 0.5 (no depth
# within 0.08 s),
# 3.0 (depth but no pose: ground truth ends at T0 + 1). Depth at each listed stamp + 0.01 s.
TUM_RGB = [0.0, 1 / 30, 1 / 30 + 0.02, 2 / 30, 2 / 30 + 0.5, 3.0]
TUM_DEPTH = {0: 1, 1: 2, 3: 3, 5: 7}  # rgb entry -> depth in metres of the depth image 0.01 s later
QZ = (0.0, 0.0, 2 * math.sin(math.pi / 4), 2 * math.cos(math.pi / 4))  # 90 deg about z, not normalised


def make_tum(root: pathlib.Path, gt: bool = True) -> pathlib.Path:
    header = "# list\n# file: 'x.bag'\n# timestamp filename\n"
    rgb_lines, depth_lines = [], []
    for i, dt in enumerate(TUM_RGB):
        t = T0 + dt
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        write_rgb(root / f"rgb/{t:.6f}.png", (10 * i, 0, 0))
        if i in TUM_DEPTH:
            td = t + 0.01
            depth_lines.append(f"{td:.6f} depth/{td:.6f}.png")
            write_depth(root / f"depth/{td:.6f}.png", 5000 * TUM_DEPTH[i])
    (root / "rgb.txt").write_text(header + "\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text(header + "\n".join(depth_lines) + "\n")
    if gt:  # 100 Hz from T0 - 0.02 to T0 + 1.0; tx = stamp - T0
        q = " ".join(f"{v:.6f}" for v in QZ)
        lines = [f"{T0 - 0.02 + k / 100:.4f} {-0.02 + k / 100:.4f} 1 2 {q}" for k in range(103)]
        header = "# ground truth\n# file\n# timestamp tx ty tz qx qy qz qw\n"
        (root / "groundtruth.txt").write_text(header + "\n".join(lines))
    return root


REPLICA_K = dict(w=W, h=H, fx=20.0, fy=21.0, cx=15.5, cy=11.5, scale=6553.5)


def make_replica(root: pathlib.Path, n: int = 3, cam_params: bool = True) -> pathlib.Path:
    scene = root / "Replica" / "room0"
    for i in range(n):
        write_rgb(scene / f"results/frame{i:06d}.jpg", (0, 40 * i, 0))
        write_depth(scene / f"results/depth{i:06d}.png", round(6553.5 * (1.5 + i)))
    poses = [translate(0.1 * i, 0, 0) for i in range(n + 2)]  # longer than the frames, like the real traj.txt
    np.savetxt(scene / "traj.txt", np.stack([p.reshape(-1) for p in poses]))
    if cam_params:
        (root / "Replica" / "cam_params.json").write_text(json.dumps({"camera": REPLICA_K}))
    return scene


def make_7scenes(root: pathlib.Path, n: int = 3, intrinsics: bool = True, start: int = 0) -> pathlib.Path:
    for i in range(n):
        stem = root / f"frame-{i:06d}"
        write_rgb(pathlib.Path(f"{stem}.color.png"), (0, 0, 50 + start + i))
        depth = np.full((H, W), 1500 + 100 * (start + i))
        depth[0, 0], depth[0, 1] = 65535, 0
        write_depth(pathlib.Path(f"{stem}.depth.png"), depth)
        np.savetxt(f"{stem}.pose.txt", rot_z(0.1 * i) @ translate(start + i, 2, 3))
    if intrinsics:
        np.savetxt(root / "camera-intrinsics.txt", np.array([[30.0, 0, 16], [0, 31.0, 12], [0, 0, 1]]))
    return root


SCANNET_N = 12


def make_scannet(root: pathlib.Path, n: int = SCANNET_N) -> pathlib.Path:
    for i in range(n):
        write_rgb(root / f"color/{i}.jpg", np.full((2 * H, 2 * W, 3), 10 * i))  # colour camera is larger
        write_depth(root / f"depth/{i}.png", 1000 + 100 * i)
        pose = np.full((4, 4), -np.inf) if i == 1 else translate(i, 0, 0)
        (root / "pose").mkdir(exist_ok=True)
        np.savetxt(root / f"pose/{i}.txt", pose, fmt="%f")
    (root / "intrinsic").mkdir()
    k = np.eye(4)
    k[0, 0], k[1, 1], k[0, 2], k[1, 2] = 30.0, 31.0, 15.5, 11.5
    np.savetxt(root / "intrinsic/intrinsic_depth.txt", k, fmt="%f")
    return root


PP_NAMES = ["DSC00001.JPG", "DSC00002.JPG", "DSC00003.JPG"]
PP_W, PP_H = 64, 48  # shrunk from 1752x1168; the loader takes the size from the JSON


def make_scannetpp(root: pathlib.Path, lists: bool = True) -> pathlib.Path:
    dslr = root / "dslr"
    poses = {n: rot_z(0.3) @ translate(1 + i, 2 + i, 3 + i) for i, n in enumerate(PP_NAMES)}
    for i, n in enumerate(PP_NAMES):
        write_rgb(dslr / "undistorted_images" / n, np.full((PP_H, PP_W, 3), (60 * (i + 1), 0, 0)))
        write_depth(dslr / "undistorted_depths" / (n[:-4] + ".png"), 1500 + 500 * i, shape=(PP_H, PP_W))
    frame = lambda n: {"file_path": n, "transform_matrix": poses[n].tolist(), "is_bad": False}  # noqa: E731
    meta = dict(w=PP_W, h=PP_H, fl_x=40.0, fl_y=42.0, cx=32.0, cy=24.0, camera_model="PINHOLE",
                frames=[frame(n) for n in PP_NAMES[:2]], test_frames=[frame(PP_NAMES[2])])
    (dslr / "nerfstudio").mkdir(parents=True)
    (dslr / "nerfstudio" / "transforms_undistorted.json").write_text(json.dumps(meta))
    if lists:  # train order differs from the JSON order: file order of the lists must win
        (dslr / "train_test_lists.json").write_text(json.dumps({"train": [PP_NAMES[1], PP_NAMES[0]], "test": [PP_NAMES[2]]}))
    return root


def make_generic(root: pathlib.Path, n: int = 3, k: str = "20 21 15.5 11.5") -> pathlib.Path:
    for i in range(n):
        write_rgb(root / f"rgb/{i:04d}.png", (i, 2 * i, 3 * i))
        write_depth(root / f"depth/{i:04d}.png", 2000 + 250 * i)
    (root / "intrinsics.txt").write_text(k + "\n")
    return root


# --- TUM -----------------------------------------------------------------------------------------


def test_tum_association_drop_rule_and_poses(tmp_path):
    root = make_tum(tmp_path / "rgbd_dataset_freiburg1_desk")
    d = TUMDataset(root, cfg(root))
    # kept: a, b, c. b + 0.02 falls under the 1/32 s rule, c + 0.5 has no depth, T0 + 3 has no pose.
    assert len(d) == 3
    np.testing.assert_allclose(d.timestamps - T0, [0.0, 1 / 30, 2 / 30], atol=1e-6)
    assert [float(s.depth.max()) for s in d] == pytest.approx([1.0, 2.0, 3.0])
    assert [int(s.rgb[0, 0, 0]) for s in d] == [0, 10, 30]
    # nearest 100 Hz pose stamps to 0, 0.0333, 0.0667 are 0.00, 0.03, 0.07 (tx = stamp offset)
    np.testing.assert_allclose(d.gt_poses[:, :3, 3], [[0.0, 1, 2], [0.03, 1, 2], [0.07, 1, 2]], atol=1e-9)
    np.testing.assert_allclose(d.gt_poses[0, :3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-6)
    np.testing.assert_allclose(d.gt_poses[:, 3], np.tile([0, 0, 0, 1.0], (3, 1)))
    k = d.intrinsics
    assert k.as_tuple() == pytest.approx((517.3, 516.5, 318.6, 255.3))
    assert (k.width, k.height) == (W, H)
    assert d.has_gt and d.layout == "tum" and detect_layout(root) == "tum"


def test_tum_without_groundtruth_and_tolerance(tmp_path):
    root = make_tum(tmp_path / "tum_fr2_x", gt=False)
    d = TUMDataset(root, cfg(root))
    # no pose criterion: the frame at T0 + 3 comes back, gt is NaN
    np.testing.assert_allclose(d.timestamps - T0, [0.0, 1 / 30, 2 / 30, 3.0], atol=1e-6)
    assert np.isnan(d.gt_poses).all() and not d.has_gt
    assert d.intrinsics.as_tuple() == pytest.approx((520.9, 521.0, 325.1, 249.7))
    with pytest.raises(DatasetError, match="no colour frame"):  # depth is 0.01 s away
        TUMDataset(root, cfg(root, tum_max_dt=0.005))
    d = TUMDataset(root, cfg(root, depth_scale=1000.0, intrinsics=(1.0, 2.0, 3.0, 4.0)))
    assert float(d[0].depth.max()) == pytest.approx(5.0)
    assert d.intrinsics.as_tuple() == (1.0, 2.0, 3.0, 4.0)
    for bad in [(0.0, 2.0, 3.0, 4.0), (1.0, 2.0, 3.0)]:
        with pytest.raises(DatasetError, match="data.intrinsics") as e:
            TUMDataset(root, cfg(root, intrinsics=bad))
        assert str(root) in str(e.value)


@pytest.mark.parametrize("name, fx", [("rgbd_dataset_freiburg3_long_office", 535.4), ("fr2_desk", 520.9), ("mydata", 517.3)])
def test_tum_intrinsics_from_folder_name(tmp_path, name, fx):
    root = make_tum(tmp_path / name)
    assert float(TUMDataset(root, cfg(root)).intrinsics.fx) == pytest.approx(fx)


def test_quaternion_matches_hamilton_rotation():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(20, 4))
    v = rng.normal(size=3)
    r = ds.quaternion_to_matrix(q)

    def mul(a, b):  # Hamilton product, scalar-last (x, y, z, w)
        ax, ay, az, aw = a
        bx, by, bz, bw = b
        return np.array([aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
                         aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz])

    for qi, ri in zip(q, r):
        qi = qi / np.linalg.norm(qi)
        conj = qi * [-1, -1, -1, 1]
        np.testing.assert_allclose(ri @ v, mul(mul(qi, [*v, 0.0]), conj)[:3], atol=1e-12)
        assert np.linalg.det(ri) == pytest.approx(1.0)


# --- Replica -------------------------------------------------------------------------------------


def test_replica(tmp_path):
    scene = make_replica(tmp_path)
    d = ReplicaDataset(scene, cfg(scene))
    assert len(d) == 3 and detect_layout(scene) == "replica"
    np.testing.assert_allclose(d.timestamps, [0, 1, 2])
    assert d.intrinsics.as_tuple() == pytest.approx((20.0, 21.0, 15.5, 11.5))
    assert (d.intrinsics.width, d.intrinsics.height) == (W, H)
    for i, s in enumerate(d):
        assert s.depth.shape == (H, W)
        np.testing.assert_allclose(s.depth, 1.5 + i, atol=1e-4)  # round(6553.5 * m) / 6553.5
        np.testing.assert_allclose(s.pose_gt, translate(0.1 * i, 0, 0), atol=1e-12)
        assert abs(int(s.rgb[5, 5, 1]) - 40 * i) <= 2  # JPEG


def test_replica_cam_params_in_folder_and_defaults(tmp_path):
    scene = make_replica(tmp_path, cam_params=False)
    d = ReplicaDataset(scene, cfg(scene))
    assert d.intrinsics.as_tuple() == (600.0, 600.0, 599.5, 339.5)
    (scene / "cam_params.json").write_text(json.dumps({"camera": dict(REPLICA_K, fx=25.0, scale=1000.0)}))
    d = ReplicaDataset(scene, cfg(scene))
    assert float(d.intrinsics.fx) == 25.0
    assert float(d[0].depth.max()) == pytest.approx(round(6553.5 * 1.5) / 1000.0)


# --- 7-Scenes ------------------------------------------------------------------------------------


@pytest.mark.parametrize("ext, params", [(".png", []), (".jpg", []), (".jpg", [cv2.IMWRITE_JPEG_PROGRESSIVE, 1]), (".bmp", [])])
@pytest.mark.parametrize("h, w", [(37, 53), (480, 640), (1, 300)])
def test_colour_checked_without_decoding_has_the_decoded_size(tmp_path, ext, params, h, w):
    """``decode=False`` reads the size from the header; cv2's decode of the same file is the oracle.
    A JPEG's start-of-frame comes after an EXIF-like segment of its own length; BMP is decoded."""
    path = tmp_path / f"c{ext}"
    assert cv2.imwrite(str(path), np.random.default_rng(0).integers(0, 255, (h, w, 3), dtype=np.uint8), params)
    if ext == ".jpg":  # an APP1 segment of 300 bytes between SOI and the frame header
        data = path.read_bytes()
        path.write_bytes(data[:2] + b"\xff\xe1" + (302).to_bytes(2, "big") + b"\xff" * 300 + data[2:])
    decoded = read_image(path)
    checked = read_image(path, decode=False)
    assert checked.shape == decoded.shape == (h, w, 3) and checked.dtype == np.uint8
    assert (checked == decoded).all() if ext == ".bmp" else not checked.any()  # BMP: decoded after all


@pytest.mark.parametrize("make, loader", [
    (lambda r: make_tum(r / "rgbd_dataset_freiburg1_desk"), TUMDataset),
    (make_replica, ReplicaDataset),
    (lambda r: make_7scenes(r / "redkitchen"), SevenScenesDataset),
    (lambda r: make_scannet(r / "scene0000_00"), ScanNetDataset),  # colour larger than depth: resized
    (make_scannetpp, ScanNetPPDataset),  # both resized
    (make_generic, GenericDataset),
])
def test_every_loader_without_colour_decoding_gives_black_of_the_decoded_size(tmp_path, make, loader):
    root = make(tmp_path)
    decoded, checked = loader(root, cfg(root)), loader(root, cfg(root))
    checked.colour = False
    for i in range(len(decoded)):
        a, b = decoded[i], checked[i]
        assert b.rgb.shape == a.rgb.shape and b.rgb.dtype == a.rgb.dtype and not b.rgb.any()
        np.testing.assert_array_equal(b.depth, a.depth)


def test_colour_not_decoded_still_finds_cut_missing_and_mismatched_images(tmp_path):
    root = make_7scenes(tmp_path / "redkitchen")
    d = SevenScenesDataset(root, cfg(root))
    d.colour = False
    for i, s in enumerate(d):
        assert s.rgb.shape == (H, W, 3) and not s.rgb.any()
        assert s.depth[5, 5] == pytest.approx(1.5 + 0.1 * i)
    cut, gone, small = (root / f"frame-{i:06d}.color.png" for i in range(3))
    cut.write_bytes(cut.read_bytes()[:-20])
    gone.unlink()
    write_rgb(small, np.zeros((H - 2, W, 3)))
    for i, (path, what) in enumerate([(cut, "truncated"), (gone, "file not found"), (small, "colour is")]):
        with pytest.raises(DatasetError, match=what) as e:
            d[i]
        assert str(path) in str(e.value)
    huge = bytearray(small.read_bytes())  # a header claiming 100000 x 100000 pixels: an error, not 28 GB of black
    huge[16:24] = (100000).to_bytes(4, "big") * 2
    small.write_bytes(bytes(huge))
    with pytest.raises(DatasetError, match="cannot decode") as e:
        d[2]
    assert str(small) in str(e.value) and "\n" not in str(e.value)


def test_7scenes(tmp_path):
    root = make_7scenes(tmp_path / "redkitchen")
    d = SevenScenesDataset(root, cfg(root))
    assert len(d) == 3 and detect_layout(root) == "7scenes"
    assert d.intrinsics.as_tuple() == (30.0, 31.0, 16.0, 12.0)
    for i, s in enumerate(d):
        assert s.depth[0, 0] == 0 and s.depth[0, 1] == 0  # 65535 and 0 are missing
        assert s.depth[5, 5] == pytest.approx(1.5 + 0.1 * i)
        assert s.rgb[3, 3].tolist() == [0, 0, 50 + i]
        np.testing.assert_allclose(s.pose_gt, rot_z(0.1 * i) @ translate(i, 2, 3), atol=1e-12)
    (root / "camera-intrinsics.txt").unlink()
    assert SevenScenesDataset(root, cfg(root)).intrinsics.as_tuple() == (585.0, 585.0, 320.0, 240.0)


def test_7scenes_seq_subfolders(tmp_path):
    make_7scenes(tmp_path / "seq-02", n=2, start=10)
    make_7scenes(tmp_path / "seq-01", n=2, start=0)
    assert detect_layout(tmp_path) == "7scenes"
    d = SevenScenesDataset(tmp_path, cfg(tmp_path))
    assert [s.rgb[0, 0, 2] for s in d] == [50, 51, 60, 61]


# --- ScanNet -------------------------------------------------------------------------------------


def test_scannet_numeric_sort_inf_poses_and_resize(tmp_path):
    root = make_scannet(tmp_path / "scene0000_00")
    d = ScanNetDataset(root, cfg(root))
    assert len(d) == SCANNET_N and detect_layout(root) == "scannet"
    np.testing.assert_allclose(d.timestamps, np.arange(SCANNET_N))
    assert d.intrinsics.as_tuple() == (30.0, 31.0, 15.5, 11.5)
    assert (d.intrinsics.width, d.intrinsics.height) == (W, H)  # depth size, no crop by default
    valid = np.isfinite(d.gt_poses).all(axis=(1, 2))
    assert valid.tolist() == [i != 1 for i in range(SCANNET_N)]
    assert np.isnan(d.gt_poses[1]).all()
    np.testing.assert_allclose(d.gt_poses[11], translate(11, 0, 0))
    for i in (0, 2, 10, 11):  # 10 and 11 sort after 9, not after 1
        s = d[i]
        assert s.rgb.shape == (H, W, 3) and s.depth.shape == (H, W)
        assert s.depth[3, 3] == pytest.approx(1.0 + 0.1 * i)
        assert abs(int(s.rgb[3, 3, 0]) - 10 * i) <= 2


def test_scannet_crop_and_frames_subfolder(tmp_path):
    make_scannet(tmp_path / "frames", n=2)
    assert detect_layout(tmp_path) == "scannet"
    d = ScanNetDataset(tmp_path, cfg(tmp_path), crop_edge=3)
    assert (d.intrinsics.width, d.intrinsics.height) == (W - 6, H - 6)
    assert d.intrinsics.as_tuple() == (30.0, 31.0, 12.5, 8.5)
    assert d[0].depth.shape == (H - 6, W - 6) and d[0].rgb.shape == (H - 6, W - 6, 3)


def test_selection_start_stride_max_frames(tmp_path):
    root = make_scannet(tmp_path)
    d = open_dataset(cfg(root, start=1, stride=3, max_frames=3))
    assert len(d) == 3
    np.testing.assert_allclose(d.timestamps, [1, 4, 7])
    assert np.isnan(d.gt_poses[0]).all()
    np.testing.assert_allclose(d.gt_poses[1:, 0, 3], [4, 7])
    samples = list(d)
    assert [s.index for s in samples] == [0, 1, 2] and [s.source_index for s in samples] == [1, 4, 7]
    assert [s.depth[0, 0] for s in samples] == pytest.approx([1.1, 1.4, 1.7])
    with pytest.raises(DatasetError, match="no frames selected"):
        open_dataset(cfg(root, start=SCANNET_N))


# --- depth noise (the paper's corruption, data.noise_*) ----------------------------------------------


def test_depth_noise_share_statistics_and_determinism():
    rng = np.random.default_rng(7)
    depth = rng.uniform(0.5, 4.0, (300, 400)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.25] = 0.0
    out = add_depth_noise(depth, 0.4, 0.02, seed=3, key=11)
    valid = depth > 0
    changed = out != depth
    assert not (changed & ~valid).any() and (out[~valid] == 0).all()  # missing depth stays missing
    assert changed[valid].mean() == pytest.approx(0.4, abs=0.01)  # a share of the *valid* pixels
    diff = (out - depth)[changed].astype(np.float64)
    assert abs(diff.mean()) < 1e-3 and diff.std() == pytest.approx(0.02, rel=0.02)
    np.testing.assert_array_equal(out, add_depth_noise(depth, 0.4, 0.02, seed=3, key=11))
    assert not np.array_equal(out, add_depth_noise(depth, 0.4, 0.02, seed=4, key=11))
    assert not np.array_equal(out, add_depth_noise(depth, 0.4, 0.02, seed=3, key=12))
    near = add_depth_noise(np.full((50, 50), 0.01, np.float32), 1.0, 0.5, seed=0, key=0)
    assert near.min() == pytest.approx(1e-3)  # floored at 1 mm, as corrupt_depth.py: never made missing
    np.testing.assert_array_equal(add_depth_noise(depth, 0.0, 0.02, seed=0, key=0), depth)


def test_depth_noise_option_is_per_frame_whatever_the_selection(tmp_path):
    root = make_scannet(tmp_path)
    noisy = lambda **kw: open_dataset(cfg(root, noise_share=0.5, noise_sigma=0.05, noise_seed=2, **kw))  # noqa: E731
    a = {s.source_index: s.depth for s in noisy()}
    b = {s.source_index: s.depth for s in noisy(start=1, stride=3)}
    clean = {s.source_index: s.depth for s in open_dataset(cfg(root))}
    assert b.keys() <= a.keys()
    for j in b:
        np.testing.assert_array_equal(a[j], b[j])
        assert 0 < (a[j] != clean[j]).mean() < 1
    later = open_dataset(cfg(root, noise_share=0.5, noise_sigma=0.05, noise_seed=2))
    np.testing.assert_array_equal(later[3].depth, a[3])  # read out of order


def test_depth_noise_set_from_the_command_line():
    c = apply_overrides(SLAMConfig(), ["data.noise_share=0.4", "data.noise_sigma=0.03", "data.noise_seed=5"])
    assert (c.data.noise_share, c.data.noise_sigma, c.data.noise_seed) == (0.4, 0.03, 5)
    with pytest.raises(ConfigError, match="noise_share"):
        DataConfig(noise_share=1.5)


def test_real_tum_depth_noise_keeps_shared_depth_images_shared():
    """TUM pairs 7 depth images of fr1/xyz's first 37 frames with two colour images each: one depth
    file gets one noise (as corrupt_depth.py, which rewrites the file), so they stay repeats."""
    d = open_dataset(cfg(_real("tum_fr1_xyz"), noise_share=0.4))
    depths = [d[i].depth for i in range(len(d))]
    assert sum(np.array_equal(a, b) for a, b in zip(depths[1:], depths[:-1])) == 7


# --- ScanNet++ -----------------------------------------------------------------------------------


def test_scannetpp_order_resize_intrinsics_and_pose_conversion(tmp_path):
    root = make_scannetpp(tmp_path / "8b5caf3398")
    for folder in (root, root / "dslr"):
        assert detect_layout(folder) == "scannetpp"
        d = ScanNetPPDataset(folder, cfg(folder))
        assert len(d) == 2
        k = d.intrinsics
        assert (k.width, k.height) == (PP_W // 2, PP_H // 2)
        assert k.as_tuple() == (20.0, 21.0, 16.0, 12.0)
        s0, s1 = d[0], d[1]  # train list order: DSC00002 then DSC00001
        assert s0.rgb.shape == (PP_H // 2, PP_W // 2, 3)
        np.testing.assert_allclose(s0.depth, 2.0)
        np.testing.assert_allclose(s1.depth, 1.5)
        assert abs(int(s0.rgb[5, 5, 0]) - 120) <= 3 and abs(int(s1.rgb[5, 5, 0]) - 60) <= 3
        # T = Rz(0.3) @ translate(x, y, z) -> world y, z flipped: t = (x', -y', -z'), R = Rz(-0.3)
        t = (rot_z(0.3) @ translate(2, 3, 4))[:3, 3]
        np.testing.assert_allclose(s0.pose_gt[:3, 3], t * [1, -1, -1], atol=1e-12)
        np.testing.assert_allclose(s0.pose_gt[:3, :3], rot_z(-0.3)[:3, :3], atol=1e-12)


def test_scannetpp_without_lists_and_test_split(tmp_path):
    root = make_scannetpp(tmp_path, lists=False)
    d = ScanNetPPDataset(root, cfg(root))
    expected = [(rot_z(0.3) @ translate(1 + i, 2 + i, 3 + i))[:3, 3] * [1, -1, -1] for i in range(2)]  # JSON order
    np.testing.assert_allclose(d.gt_poses[:, :3, 3], expected, atol=1e-12)
    d = ScanNetPPDataset(root, cfg(root), split="test")
    assert len(d) == 1 and d[0].depth[0, 0] == pytest.approx(2.5)
    np.testing.assert_allclose(d.gt_poses[0, :3, 3], (rot_z(0.3) @ translate(3, 4, 5))[:3, 3] * [1, -1, -1], atol=1e-12)


# --- generic -------------------------------------------------------------------------------------


@pytest.mark.parametrize("k", ["20 21 15.5 11.5", "20 0 15.5\n0 21 11.5\n0 0 1"])
def test_generic(tmp_path, k):
    root = make_generic(tmp_path, k=k)
    d = open_dataset(cfg(root))
    assert isinstance(d, GenericDataset) and detect_layout(root) == "generic"
    assert len(d) == 3 and d.intrinsics.as_tuple() == (20.0, 21.0, 15.5, 11.5)
    assert np.isnan(d.gt_poses).all()
    for i, s in enumerate(d):
        np.testing.assert_allclose(s.depth, 2.0 + 0.25 * i)
        assert s.rgb[0, 0].tolist() == [i, 2 * i, 3 * i]


def test_generic_json_float_depth_and_groundtruth(tmp_path):
    root = make_generic(tmp_path)
    (root / "intrinsics.txt").unlink()
    (root / "intrinsics.json").write_text(json.dumps(dict(fx=10, fy=11, cx=12, cy=13)))
    for i in range(3):  # float TIFF depth in metres replaces the PNGs
        (root / f"depth/{i:04d}.png").unlink()
        assert cv2.imwrite(str(root / f"depth/{i:04d}.tiff"), np.full((H, W), 0.5 + i, np.float32))
    lines = [f"{100 + i} {i} 0 0 0 0 0 1" for i in range(2)]
    (root / "groundtruth.txt").write_text("# t tx ty tz qx qy qz qw\n" + "\n".join(lines))  # 2 lines, 3 frames
    d = GenericDataset(root, cfg(root))
    assert d.intrinsics.as_tuple() == (10.0, 11.0, 12.0, 13.0)
    assert [float(s.depth[0, 0]) for s in d] == [0.5, 1.5, 2.5]
    assert np.isnan(d.gt_poses).all()  # ignored: not one line per frame
    (root / "groundtruth.txt").write_text("\n".join(lines + ["102 2 0 0 0 0 0 1"]))
    d = GenericDataset(root, cfg(root))
    np.testing.assert_allclose(d.timestamps, [100, 101, 102])
    np.testing.assert_allclose(d.gt_poses[:, 0, 3], [0, 1, 2])


# --- downscaling and inpainting (shared base behaviour) ------------------------------------------


def test_downscale(tmp_path):
    root = make_generic(tmp_path, n=1)
    yy, xx = np.mgrid[:H, :W]
    write_rgb(root / "rgb/0000.png", np.where(((yy + xx) % 2 == 0)[..., None], 200, 0) * np.ones(3))
    depth = np.full((H, W), 2000)
    depth[:, W // 2 + 1 :] = 3000  # a depth edge through the middle of the blocks of column W // 4
    depth[:2, :4] = [[0, 2000, 0, 0], [2010, 0, 0, 0]]  # a block with two holes, a block with none valid
    write_depth(root / "depth/0000.png", depth)
    s = GenericDataset(root, cfg(root, downscale=2, inpaint=False))[0]
    assert s.rgb.shape == (H // 2, W // 2, 3) and s.depth.shape == (H // 2, W // 2)
    np.testing.assert_array_equal(s.rgb, 100)  # area average of the 0/200 checkerboard
    assert s.depth[0, 0] == pytest.approx(2.005) and s.depth[0, 1] == 0  # mean of the valid ones; none valid
    np.testing.assert_array_equal(s.depth[:, W // 4], 2.0)  # across the edge: the nearer surface, nothing between
    np.testing.assert_array_equal(s.depth[:, W // 4 + 1 :], 3.0)
    k = GenericDataset(root, cfg(root, downscale=2)).intrinsics
    # small pixel u covers full pixels 2u, 2u + 1: its centre 2u + 0.5 maps to u
    assert k.as_tuple() == pytest.approx((10.0, 10.5, (15.5 - 0.5) / 2, (11.5 - 0.5) / 2))
    assert (k.width, k.height) == (W // 2, H // 2)


@pytest.mark.parametrize("factor", [2, 3])
def test_downscaled_depth_of_a_slanted_plane_is_the_plane_at_the_scaled_pixel_centres(factor):
    """Oracle: the plane's depth along the ray of each downscaled pixel, through the scaled intrinsics."""
    from sgad_jax.io.base import downscale_rgbd
    from sgad_jax.types import Intrinsics

    full = Intrinsics(fx=300.0, fy=290.0, cx=47.5, cy=35.5, width=96, height=72)
    n, d = np.array([0.3, -0.2, 1.0]), 2.0  # plane n . X = d, about 45 degrees to the rays at the edges

    def plane_depth(k: Intrinsics) -> np.ndarray:
        v, u = np.mgrid[: k.height, : k.width].astype(np.float64)
        return d / (n[0] * (u - k.cx) / k.fx + n[1] * (v - k.cy) / k.fy + n[2])

    rgb = np.zeros((full.height, full.width, 3), np.uint8)
    _, small = downscale_rgbd(rgb, plane_depth(full), factor)
    want = plane_depth(full.scaled(factor))
    # the block mean differs from the centre's depth only at second order (1/z, not z, is linear)
    np.testing.assert_allclose(small, want, rtol=2e-4)
    if factor % 2 == 0:  # an even block has no centre pixel: any one of its pixels is half a pixel off
        one_pixel = plane_depth(full)[factor // 2 :: factor, factor // 2 :: factor]
        assert np.abs(one_pixel - want).max() > 10 * np.abs(small - want).max()


def test_inpainting(tmp_path):
    root = make_generic(tmp_path, n=1)
    depth = np.full((H, W), 2000)
    depth[8:14, 10:18] = 0
    write_depth(root / "depth/0000.png", depth)
    s = GenericDataset(root, cfg(root))[0]
    assert (s.depth[8:14, 10:18] == 0).all() and (s.depth[s.depth > 0] == 2.0).all()
    assert (s.depth_filled > 0).all()
    np.testing.assert_allclose(s.depth_filled, 2.0, atol=0.05)
    s = GenericDataset(root, cfg(root, inpaint=False))[0]
    np.testing.assert_array_equal(s.depth_filled, s.depth)


# --- open_dataset, detect_layout and errors ------------------------------------------------------


def test_open_dataset_auto_and_explicit(tmp_path):
    root = make_tum(tmp_path / "fr1")
    assert isinstance(open_dataset(cfg(root)), TUMDataset)
    assert isinstance(open_dataset(cfg(root, layout="tum")), TUMDataset)


def test_open_dataset_synthetic():
    assert type(open_dataset(DataConfig())).__name__ == "SyntheticDataset"


def test_missing_folder_and_unknown_layout(tmp_path):
    missing = tmp_path / "nope"
    calls = (lambda: open_dataset(cfg(missing)), lambda: detect_layout(missing), lambda: TUMDataset(missing, cfg(missing)))
    for call in calls:
        with pytest.raises(DatasetError, match="folder not found") as e:
            call()
        assert str(missing) in str(e.value)
    with pytest.raises(DatasetError) as e:
        open_dataset(cfg(tmp_path, layout="kitti"))
    assert "kitti" in str(e.value) and "scannetpp" in str(e.value)
    with pytest.raises(DatasetError) as e:
        open_dataset(cfg(tmp_path))  # empty folder
    assert str(tmp_path) in str(e.value) and "tum" in str(e.value) and "\n" not in str(e.value)


def test_missing_and_corrupt_images(tmp_path):
    root = make_tum(tmp_path / "fr1")
    d = TUMDataset(root, cfg(root))
    rgb1 = root / f"rgb/{T0 + 1 / 30:.6f}.png"
    rgb1.unlink()
    with pytest.raises(DatasetError, match="file not found") as e:
        d[1]
    assert str(rgb1) in str(e.value)
    depth2 = root / f"depth/{T0 + 2 / 30 + 0.01:.6f}.png"
    depth2.write_bytes(b"not a png at all")
    with pytest.raises(DatasetError, match="cannot decode") as e:
        d[2]
    assert str(depth2) in str(e.value)


def test_size_mismatch(tmp_path):
    root = make_generic(tmp_path)
    bad = root / "rgb/0001.png"
    write_rgb(bad, np.zeros((H - 4, W, 3)))
    d = GenericDataset(root, cfg(root))
    d[0]
    with pytest.raises(DatasetError, match="colour is") as e:
        d[1]
    assert str(bad) in str(e.value)
    bad_depth = root / "depth/0002.png"
    write_depth(bad_depth, 1000, shape=(H, W + 2))
    with pytest.raises(DatasetError) as e:
        d[2]
    assert str(bad_depth) in str(e.value)


def test_frames_read_in_order_and_fail_at_the_bad_frame(tmp_path):
    root = make_generic(tmp_path, n=6)
    d = GenericDataset(root, cfg(root))
    got = list(d.frames(start=2))
    assert [s.index for s in got] == [2, 3, 4, 5]
    for s in got:
        want = d[s.index]
        assert np.array_equal(s.depth, want.depth) and np.array_equal(s.rgb, want.rgb)
    assert not any("depth_filled" in vars(s) for s in got)  # inpainted only when first asked for
    filled = list(d.frames(start=3, fill=lambda i: i == 4))  # ... or with the batch, for mapping
    assert ["depth_filled" in vars(s) for s in filled] == [False, True, False]
    np.testing.assert_array_equal(filled[1].depth_filled, inpaint_depth(filled[1].depth))
    assert all(s.depth_device is None for s in got)  # staged on the device only when asked
    staged = list(d.frames(start=4, stage=jax.device_put))
    assert all(isinstance(s.depth_device, jax.Array) and np.array_equal(np.asarray(s.depth_device), s.depth) for s in staged)
    # Frame 3 is corrupt: it is read (and fails) in the batch of frames 0-5, before frame 0 is
    # handed out, but the error comes when its turn comes, after every frame before it.
    bad = root / "depth/0003.png"
    bad.write_bytes(b"not a png")
    seen = []
    with pytest.raises(DatasetError, match="cannot decode") as e:
        for s in d.frames():
            seen.append(s.index)
    assert seen == [0, 1, 2] and str(bad) in str(e.value)


def test_frames_read_a_batch_at_once_and_no_further(tmp_path, monkeypatch):
    """A batch's frames are read at the same time (two at once here: each read waits at a barrier
    for another), all of them before the first is handed out (no read beside the caller's work),
    and never more than a batch ahead of the frame handed out."""
    root = make_generic(tmp_path, n=7)
    d = GenericDataset(root, cfg(root))
    monkeypatch.setattr(base, "READ_BATCH_FRAMES", 2)
    monkeypatch.setattr(base, "_cores", lambda: 2)
    together, real, handed, ahead = threading.Barrier(2, timeout=10), GenericDataset._read_ahead, [-1], []

    done = set()

    def read(self, i, fill, stage):
        ahead.append(i - handed[0])
        if i < 6:  # the last batch holds frame 6 alone
            together.wait()
        sample = real(self, i, fill, stage)
        time.sleep(0.05 * (i % 2))  # the batch's second frame finishes last
        done.add(i)
        return sample

    monkeypatch.setattr(GenericDataset, "_read_ahead", read)
    for s in d.frames():
        assert s.index == handed[0] + 1
        assert {s.index - s.index % 2, min(s.index - s.index % 2 + 1, 6)} <= done  # its whole batch is read
        handed[0] = s.index
    assert handed[0] == 6 and len(ahead) == 7 and max(ahead) <= 2


def test_malformed_files(tmp_path):
    root = make_tum(tmp_path / "fr1")
    (root / "groundtruth.txt").write_text("1 2 3\n")
    with pytest.raises(DatasetError, match="malformed") as e:
        TUMDataset(root, cfg(root))
    assert str(root / "groundtruth.txt") in str(e.value)
    (root / "groundtruth.txt").unlink()
    (root / "rgb.txt").write_text("abc rgb/x.png\n")
    with pytest.raises(DatasetError, match="malformed") as e:
        TUMDataset(root, cfg(root))
    assert str(root / "rgb.txt") in str(e.value)

    scene = make_replica(tmp_path / "r")
    (scene / "traj.txt").write_text("1 2 3\n")
    with pytest.raises(DatasetError, match="malformed") as e:
        ReplicaDataset(scene, cfg(scene))
    assert str(scene / "traj.txt") in str(e.value)

    seven = make_7scenes(tmp_path / "s")
    (seven / "frame-000001.pose.txt").write_text("1 0 0\n0 1 x\n")
    with pytest.raises(DatasetError) as e:
        SevenScenesDataset(seven, cfg(seven))
    assert str(seven / "frame-000001.pose.txt") in str(e.value)

    gen = make_generic(tmp_path / "g", k="1 2 3")
    with pytest.raises(DatasetError, match="malformed") as e:
        GenericDataset(gen, cfg(gen))
    assert str(gen / "intrinsics.txt") in str(e.value)
    (gen / "intrinsics.txt").unlink()
    with pytest.raises(DatasetError, match="intrinsics") as e:
        GenericDataset(gen, cfg(gen))
    assert str(gen) in str(e.value)
    assert len(GenericDataset(gen, cfg(gen, intrinsics=(5.0, 5.0, 16.0, 12.0)))) == 3

    (gen / "depth/0002.png").unlink()
    with pytest.raises(DatasetError) as e:
        GenericDataset(gen, cfg(gen))
    assert str(gen / "rgb") in str(e.value) and str(gen / "depth") in str(e.value)

    pp = make_scannetpp(tmp_path / "pp")
    meta = pp / "dslr/nerfstudio/transforms_undistorted.json"
    meta.write_text("{not json")
    with pytest.raises(DatasetError) as e:
        ScanNetPPDataset(pp, cfg(pp))
    assert str(meta) in str(e.value)


def test_empty_folders(tmp_path):
    (tmp_path / "rgb").mkdir()
    (tmp_path / "depth").mkdir()
    with pytest.raises(DatasetError, match="no images") as e:
        GenericDataset(tmp_path, cfg(tmp_path))
    assert str(tmp_path / "rgb") in str(e.value)
    (tmp_path / "results").mkdir()
    with pytest.raises(DatasetError) as e:
        ReplicaDataset(tmp_path, cfg(tmp_path))
    assert str(tmp_path / "results") in str(e.value)


# --- files missing, misnamed or malformed (one line naming the file; run-usable problems warn) ------


def _bad_frames(d) -> dict[int, str]:
    return {x.index: x.reason for x in d.frames(skip_bad=True) if isinstance(x, base.BadFrame)}


def test_generic_pairs_colour_and_depth_by_frame_number(tmp_path):
    root = tmp_path / "g"
    for i in range(4):  # other prefixes, other padding: the numbers pair them
        write_rgb(root / f"rgb/frame{i:06d}.png", (i, 0, 0))
        write_depth(root / f"depth/depth{i}.png", 1000 * (i + 1))
    (root / "intrinsics.txt").write_text("20 21 15.5 11.5\n")
    d = GenericDataset(root, cfg(root))
    assert [float(s.depth[0, 0]) for s in d] == [1.0, 2.0, 3.0, 4.0]
    (root / "depth/depth2.png").rename(root / "depth/depth30.png")  # counts still agree
    with pytest.raises(DatasetError, match="no image of the same frame number") as e:
        GenericDataset(root, cfg(root))
    assert str(e.value).startswith(f"{root / 'rgb/frame000002.png'}: ") and "\n" not in str(e.value)
    (root / "rgb/frame000002.png").unlink()  # the lone one is now the depth image
    with pytest.raises(DatasetError, match="no image of the same frame number") as e:
        GenericDataset(root, cfg(root))
    assert str(e.value).startswith(f"{root / 'depth/depth30.png'}: ")
    stamps = tmp_path / "stamps"  # each camera's own timestamps in the names: no number shared, paired in order
    for i in range(3):
        write_rgb(stamps / f"rgb/{100 + i}.031.png", (i, 0, 0))
        write_depth(stamps / f"depth/{100 + i}.017.png", 1000 * (i + 1))
    (stamps / "intrinsics.txt").write_text("20 21 15.5 11.5\n")
    assert [float(s.depth[0, 0]) for s in GenericDataset(stamps, cfg(stamps))] == [1.0, 2.0, 3.0]


def test_a_stray_frame_number_far_beyond_the_rest_is_named(tmp_path):
    """Filling the numbering's gaps with bad frames must not turn one stray file into a million."""
    root = make_7scenes(tmp_path / "s", n=4)
    shutil.copy(root / "frame-000001.color.png", root / "frame-000999.color.png")
    with pytest.raises(DatasetError, match="frame-000999.color.png: numbered 999, but only 5 frames from 0; a stray file"):
        open_dataset(cfg(root))


def test_generic_skips_hidden_files_and_folders(tmp_path):
    root = make_generic(tmp_path)
    (root / "rgb/._0000.png").write_bytes(b"macOS resource fork")
    (root / "depth/sub.png").mkdir()
    d = GenericDataset(root, cfg(root))
    assert [p.name for p in d.rgb_paths] == [p.name for p in d.depth_paths] == ["0000.png", "0001.png", "0002.png"]


@pytest.mark.parametrize("layout", ["7scenes", "replica", "scannet"])
def test_a_missing_colour_file_is_a_bad_frame_and_later_frames_keep_their_numbers(tmp_path, layout):
    if layout == "7scenes":
        root = make_7scenes(tmp_path / "s", n=6)
        gone, depth_of = root / "frame-000003.color.png", lambda i: 1.5 + 0.1 * i
    elif layout == "replica":
        root = make_replica(tmp_path / "r", n=6)
        gone, depth_of = root / "results/frame000003.jpg", lambda i: 1.5 + i
    else:
        root = make_scannet(tmp_path / "sc", n=6)
        gone, depth_of = root / "color/3.jpg", lambda i: 1.0 + 0.1 * i
    full = open_dataset(cfg(root))
    gone.unlink()
    d = open_dataset(cfg(root))
    assert len(d) == 6 and d.timestamps.tolist() == full.timestamps.tolist() == [0, 1, 2, 3, 4, 5]
    np.testing.assert_array_equal(d.gt_poses, full.gt_poses)
    assert list(_bad_frames(d)) == [3] and _bad_frames(d)[3] == f"{gone}: file not found"
    assert d[4].depth[5, 5] == pytest.approx(depth_of(4), abs=1e-3)


def test_a_scannet_export_of_every_kth_frame_has_no_gap(tmp_path):
    root = make_scannet(tmp_path, n=10)
    for i in range(10):
        if i % 3:
            for f in (f"color/{i}.jpg", f"depth/{i}.png", f"pose/{i}.txt"):
                (root / f).unlink()
    d = open_dataset(cfg(root))
    assert d.timestamps.tolist() == [0, 3, 6, 9] and not _bad_frames(d) and not d.warnings


def test_a_missing_first_depth_image_is_a_bad_frame_not_a_start_up_error(tmp_path):
    root = make_7scenes(tmp_path, n=4)
    (root / "frame-000000.depth.png").unlink()
    d = open_dataset(cfg(root))
    assert (d.intrinsics.width, d.intrinsics.height) == (W, H)
    assert _bad_frames(d) == {0: f"{root / 'frame-000000.depth.png'}: file not found"}
    assert len(open_dataset(cfg(root, start=1))) == 3
    for i in range(1, 4):
        (root / f"frame-{i:06d}.depth.png").unlink()
    with pytest.raises(DatasetError, match="file not found") as e:  # no depth at all: the first one is named
        open_dataset(cfg(root))
    assert str(root / "frame-000000.depth.png") in str(e.value)


def test_pose_files_are_read_for_the_selected_frames_and_named_in_warnings(tmp_path):
    root = make_7scenes(tmp_path / "s", n=6)
    (root / "frame-000005.pose.txt").write_text("not a pose\n")
    d = open_dataset(cfg(root, max_frames=3))  # outside the selection: not read
    assert len(d) == 3 and np.isfinite(d.gt_poses).all() and d.warnings == []
    with pytest.raises(DatasetError, match="malformed") as e:
        open_dataset(cfg(root))
    assert str(root / "frame-000005.pose.txt") in str(e.value)
    (root / "frame-000004.pose.txt").unlink()
    assert open_dataset(cfg(root, max_frames=5)).warnings == [
        f"{root / 'frame-000004.pose.txt'}: the ground-truth pose is missing for 1 of 5 frames (first: run frame 4); ATE leaves them out"
    ]
    scan = make_scannet(tmp_path / "sc", n=4)  # pose/1.txt is -inf
    w = open_dataset(cfg(scan)).warnings
    assert len(w) == 1 and w[0].startswith(f"{scan / 'pose/1.txt'}: the ground-truth pose holds Inf/NaN for 1 of 4 frames")


@pytest.mark.parametrize("camera", [dict(scale=0), dict(scale=-6553.5), dict(scale="nan"), dict(w=0), dict(h=-680)])
def test_replica_cam_params_must_be_positive(tmp_path, camera):
    scene = make_replica(tmp_path)
    params = scene.parent / "cam_params.json"
    params.write_text(json.dumps({"camera": {**REPLICA_K, **camera}}).replace('"nan"', "NaN"))
    with pytest.raises(DatasetError) as e:
        ReplicaDataset(scene, cfg(scene))
    assert str(e.value).startswith(f"{params}: ") and "\n" not in str(e.value)


def test_ground_truth_or_intrinsics_left_out_is_a_warning(tmp_path):
    gen = make_generic(tmp_path / "g")
    (gen / "groundtruth.txt").write_text("".join(f"{i} {i} 0 0 0 0 0 1\n" for i in range(2)))  # 2 lines, 3 frames
    d = GenericDataset(gen, cfg(gen))
    assert np.isnan(d.gt_poses).all()
    assert d.warnings == [f"{gen / 'groundtruth.txt'}: 2 poses for 3 frames, expected one a frame; the run has no ground truth"]

    scene = make_replica(tmp_path / "r")
    (scene / "traj.txt").write_text("")
    w = ReplicaDataset(scene, cfg(scene)).warnings
    assert len(w) == 1 and w[0].startswith(f"{scene / 'traj.txt'}: no usable pose")
    (scene / "traj.txt").unlink()
    assert ReplicaDataset(scene, cfg(scene)).warnings == []  # no ground truth at all is fine

    seven = make_7scenes(tmp_path / "s", intrinsics=False)
    w = SevenScenesDataset(seven, cfg(seven)).warnings
    assert len(w) == 1 and w[0].startswith(f"{seven / 'camera-intrinsics.txt'}: not found") and "585" in w[0]
    assert SevenScenesDataset(seven, cfg(seven, intrinsics=(30.0, 30.0, 16.0, 12.0))).warnings == []


def test_7scenes_sequences_in_natural_order_numbered_on(tmp_path):
    make_7scenes(tmp_path / "seq-10", n=2, start=10)
    make_7scenes(tmp_path / "seq-2", n=2, start=0)
    d = SevenScenesDataset(tmp_path, cfg(tmp_path))
    assert [s.rgb[0, 0, 2] for s in d] == [50, 51, 60, 61] and d.timestamps.tolist() == [0, 1, 2, 3]


# --- real data (shared/data) ---------------------------------------------------------------------


def _shared_data() -> pathlib.Path:
    env = os.environ.get("SGAD_SHARED_DATA")
    path = pathlib.Path(env) if env else pathlib.Path(__file__).resolve().parents[2] / "shared" / "data"
    if not path.is_dir():
        pytest.skip(f"real data not found at {path} (set SGAD_SHARED_DATA)")
    return path


def _real(name: str) -> pathlib.Path:
    path = _shared_data() / name
    if not path.is_dir():
        pytest.skip(f"{path} is missing")
    return path


def test_real_tum_fr1_xyz():
    root = _real("tum_fr1_xyz")
    d = open_dataset(cfg(root))
    assert isinstance(d, TUMDataset) and len(d) == 37  # 37 listed frames, all associated, none dropped
    assert d.intrinsics.as_tuple() == pytest.approx((517.3, 516.5, 318.6, 255.3))
    assert (d.intrinsics.width, d.intrinsics.height) == (640, 480)
    assert d.timestamps[0] == pytest.approx(1305031102.175304) and d.timestamps[-1] == pytest.approx(1305031103.375327)
    # nearest groundtruth line: 1305031102.1758 1.3405 0.6266 1.6575 0.6574 0.6126 -0.2949 -0.3248
    pose = d.gt_poses[0]
    np.testing.assert_allclose(pose[:3, 3], [1.3405, 0.6266, 1.6575])
    np.testing.assert_allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-9)
    s = d[0]
    valid = s.depth[s.depth > 0]
    assert 0.5 < valid.min() and valid.max() < 5.0 and 0.1 < (s.depth == 0).mean() < 0.4
    assert s.rgb.shape == (480, 640, 3) and s.rgb.dtype == np.uint8


def test_real_replica_rendered_100():
    root = _real("replica_office0/rendered_100")
    d = open_dataset(cfg(root))
    assert isinstance(d, ReplicaDataset) and len(d) == 100
    assert d.intrinsics.as_tuple() == (600.0, 600.0, 599.5, 339.5)
    assert (d.intrinsics.width, d.intrinsics.height) == (1200, 680)
    np.testing.assert_allclose(d.gt_poses[0, :3, 3], [-0.3569159214564542, -0.6602722315763628, 0.8192365926179191])
    s = d[99]
    valid = s.depth[s.depth > 0]
    assert s.depth.shape == (680, 1200) and 0.1 < valid.min() and valid.max() < 10.0


def test_real_replica_real_frames():
    root = _real("replica_office0/real_frames")
    d = open_dataset(cfg(root))
    assert len(d) == 4 and d.has_gt and np.isfinite(d.gt_poses).all()


def test_real_7scenes_redkitchen():
    root = _real("7scenes_redkitchen")
    d = open_dataset(cfg(root))
    assert isinstance(d, SevenScenesDataset) and len(d) == 400
    assert d.intrinsics.as_tuple() == (585.0, 585.0, 320.0, 240.0)
    np.testing.assert_allclose(d.gt_poses[0, :3, 3], [-0.34045634, 0.016469818, 0.29656917])
    s = d[0]
    valid = s.depth[s.depth > 0]
    assert s.depth.shape == (480, 640) and 0.3 < valid.min() and valid.max() < 6.0
