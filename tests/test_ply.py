"""3DGS PLY export: file layout (read with plyfile), a render round trip, the merge rule, and on
Replica the exported Gaussians against the ground-truth mesh."""

import dataclasses
import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import plyfile
import pytest
from scipy import spatial

from conftest import shared
from sgad_jax import lie, splat_ref
from sgad_jax.cli import main
from sgad_jax.config import DataConfig, SyntheticConfig
from sgad_jax.io.base import DatasetError
from sgad_jax.io.datasets import open_dataset
from sgad_jax.io.export import write_tum_trajectory
from sgad_jax.io.ply import PROPERTIES, merged_gaussians, read_3dgs_ply, write_3dgs_ply
from sgad_jax.mapping import init_gaussians
from sgad_jax.types import host_frame
from sgad_jax.types import PixelGaussians, make_intrinsics


def _scene(frames=2, width=20, height=16, seed=0):
    """Gaussians of a few frames of the synthetic room, every learnable field perturbed (so that the
    export has to carry offsets, radii, opacities and colours, not just the initial values)."""
    ds = open_dataset(DataConfig(layout="synthetic", synthetic=SyntheticConfig(frames=frames, width=width, height=height)))
    rng = np.random.default_rng(seed)
    gs = []
    for i in range(frames):
        g = jax.tree.map(np.asarray, init_gaussians(host_frame(ds[i]), ds.intrinsics))
        shape = g.depth.shape
        gs.append(PixelGaussians(
            rgb=np.clip(g.rgb + rng.normal(0, 0.05, g.rgb.shape), -0.1, 1.1).astype(np.float32),
            log_radius=(g.log_radius + rng.normal(0, 0.3, shape)).astype(np.float32),
            opacity_logit=rng.uniform(-1.0, 4.0, shape).astype(np.float32),
            offset=rng.normal(0, 0.02, shape).astype(np.float32),
            depth=g.depth,
        ))
    return gs, ds.gt_poses, ds.intrinsics


def _as_frames(w, intr):
    """World Gaussians as a stack of 1x1 "frames" the pixel-aligned renderer takes: Gaussian k is
    pixel (0, 0) of frame k at unit depth, whose camera (identity rotation) is placed so that this
    pixel's ray passes through the Gaussian's centre."""
    n = len(w)
    ray = np.array([-float(intr.cx) / float(intr.fx), -float(intr.cy) / float(intr.fy), 1.0])
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, 3] = w.xyz.astype(np.float64) - ray
    f32 = lambda x: jnp.asarray(x, jnp.float32).reshape(n, 1, 1, *x.shape[1:])  # noqa: E731
    g = PixelGaussians(
        rgb=f32(w.rgb), log_radius=f32(w.log_sigma + np.float32(math.log(3.0))), opacity_logit=f32(w.opacity_logit),
        offset=jnp.zeros((n, 1, 1)), depth=jnp.ones((n, 1, 1)),
    )
    return g, lie.from_matrix(jnp.asarray(T, jnp.float32))


def test_ply_layout_read_by_plyfile(tmp_path):
    gs, poses, intr = _scene()
    w, info = merged_gaussians((gs, poses, intr), voxel=0.0, min_opacity=0.0)
    assert info.total == info.visible == info.kept == 2 * 20 * 16
    path = write_3dgs_ply(tmp_path / "g.ply", w)
    ply = plyfile.PlyData.read(str(path))
    assert not ply.text and ply.byte_order == "<"
    v = ply["vertex"]
    assert [p.name for p in v.properties] == list(PROPERTIES)
    assert all(v.data.dtype[p] == np.dtype("<f4") for p in PROPERTIES)
    assert len(v.data) == len(w)
    assert path.read_bytes().startswith(b"ply\nformat binary_little_endian 1.0\n")
    # the activations a 3DGS viewer applies give back the learned values
    g0 = gs[0]
    np.testing.assert_allclose(1 / (1 + np.exp(-v["opacity"][:5])), 1 / (1 + np.exp(-g0.opacity_logit.reshape(-1)[:5])), rtol=1e-6)
    np.testing.assert_allclose(np.exp(v["scale_1"][:5]), np.exp(g0.log_radius.reshape(-1)[:5]) / 3.0, rtol=1e-5)
    np.testing.assert_allclose(0.5 + 0.28209479177387814 * v["f_dc_2"][:5], g0.rgb[0, :5, 2], atol=1e-6)
    quat = np.stack([v[f"rot_{k}"] for k in range(4)], -1)
    assert (quat == [1, 0, 0, 0]).all() and (v["nx"] == 0).all()
    assert not list(tmp_path.glob(".*tmp"))  # the temporary file was renamed


def test_positions_on_pixel_rays():
    """A Gaussian's centre, projected into its own camera, is its pixel at depth |D + offset|."""
    gs, poses, intr = _scene(frames=1)
    w, _ = merged_gaussians(([gs[0]], poses, intr), voxel=0.0, min_opacity=0.0)
    T_cw = np.linalg.inv(poses[0])
    p = w.xyz.astype(np.float64) @ T_cw[:3, :3].T + T_cw[:3, 3]
    v, u = np.divmod(np.arange(len(p)), 20)
    np.testing.assert_allclose(float(intr.fx) * p[:, 0] / p[:, 2] + float(intr.cx), u, atol=1e-3)
    np.testing.assert_allclose(float(intr.fy) * p[:, 1] / p[:, 2] + float(intr.cy), v, atol=1e-3)
    np.testing.assert_allclose(p[:, 2], np.abs(gs[0].depth + gs[0].offset).reshape(-1), rtol=1e-5)


def test_round_trip_renders_the_same_image(tmp_path):
    gs, poses, intr = _scene(frames=2)
    w, _ = merged_gaussians((gs, poses, intr), voxel=0.0, min_opacity=0.0)
    back = read_3dgs_ply(write_3dgs_ply(tmp_path / "g.ply", w))
    np.testing.assert_array_equal(back.xyz, w.xyz)
    np.testing.assert_array_equal(back.opacity_logit, w.opacity_logit)
    np.testing.assert_allclose(back.rgb, w.rgb, atol=1e-6)
    np.testing.assert_allclose(back.log_sigma, w.log_sigma, atol=1e-6)
    # a view between the two cameras, moved back a little: both frames' Gaussians in sight
    view = poses[0].copy()
    view[:3, 3] = 0.5 * (poses[0][:3, 3] + poses[1][:3, 3]) - 0.1 * poses[0][:3, 2]
    view = lie.from_matrix(jnp.asarray(view, jnp.float32))
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *gs)
    # A PLY holds positions only: its Gaussians are composited by their depth in the view, as the
    # frames' Gaussians are when their measured depth is where they sit (offset folded in).
    stacked = dataclasses.replace(stacked, depth=stacked.z, offset=jnp.zeros_like(stacked.offset))
    ref = splat_ref.render(stacked, lie.from_matrix(jnp.asarray(poses, jnp.float32)), view, intr)
    got = splat_ref.render(*_as_frames(back, intr), view, intr)
    assert float(ref.alpha.mean()) > 0.5  # the view sees the scene
    np.testing.assert_allclose(got.rgb, ref.rgb, atol=2e-5)
    np.testing.assert_allclose(got.depth, ref.depth, rtol=2e-5, atol=2e-5)
    np.testing.assert_allclose(got.alpha, ref.alpha, atol=2e-5)


def test_merge_keeps_the_nearest_view_per_voxel():
    """Two cameras look at the plane z = 2 from 1 m and 2 m away; with 5 cm cells the nearer
    camera's Gaussian wins every shared cell, and the count is the number of occupied cells."""
    intr = make_intrinsics(20.0, 20.0, 9.5, 7.5, 20, 16)
    ones = np.ones((16, 20), np.float32)

    def plane_frame(cam_z, colour):
        return PixelGaussians(
            rgb=np.full((16, 20, 3), colour, np.float32), log_radius=np.log(0.01 * ones), opacity_logit=2 * ones,
            offset=0 * ones, depth=(2.0 - cam_z) * ones,
        )

    poses = np.tile(np.eye(4), (2, 1, 1))
    poses[0, 2, 3], poses[1, 2, 3] = 0.0, 1.0  # the second camera is nearer the plane
    frames = [plane_frame(0.0, 0.2), plane_frame(1.0, 0.8)]
    voxel = 0.05
    w, info = merged_gaussians((frames, poses, intr), voxel=voxel)
    every, _ = merged_gaussians((frames, poses, intr), voxel=0.0)
    cells = {tuple(c) for c in np.floor(every.xyz / voxel).astype(int)}
    assert info.total == info.visible == 2 * 320 and info.kept == len(cells) == len(w)
    near_cells = {tuple(c) for c in np.floor(every.xyz[320:] / voxel).astype(int)}
    from_near = np.isclose(w.rgb[:, 0], 0.8)
    assert {tuple(c) for c in np.floor(w.xyz[from_near] / voxel).astype(int)} == near_cells
    assert from_near.sum() == len(near_cells)


def test_transparent_dropped():
    intr = make_intrinsics(20.0, 20.0, 9.5, 7.5, 20, 16)
    ones = np.ones((16, 20), np.float32)
    logit = np.where(np.arange(20) < 5, -10.0, 3.0) * ones  # 5 columns with opacity 4.5e-5
    g = PixelGaussians(rgb=np.zeros((16, 20, 3), np.float32), log_radius=-5 * ones, opacity_logit=logit, offset=0 * ones, depth=ones)
    _, info = merged_gaussians(([g], np.eye(4)[None], intr), voxel=0.0)
    assert (info.total, info.visible) == (320, 15 * 16)


def test_read_errors(tmp_path):
    with pytest.raises(DatasetError, match="not found"):
        read_3dgs_ply(tmp_path / "none.ply")
    (tmp_path / "bad.ply").write_bytes(b"hello")
    with pytest.raises(DatasetError, match="bad.ply"):
        read_3dgs_ply(tmp_path / "bad.ply")
    pts = np.zeros(3, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    plyfile.PlyData([plyfile.PlyElement.describe(pts, "vertex")]).write(str(tmp_path / "points.ply"))
    with pytest.raises(DatasetError, match="not a 3D Gaussian Splatting file"):
        read_3dgs_ply(tmp_path / "points.ply")


def test_export_command_on_a_fabricated_run(tmp_path, capsys):
    """`sgad-jax export RUN_DIR` on a run folder as the pipeline writes it (with cameras.json)."""
    from sgad_jax.cli import main

    gs, poses, intr = _scene(frames=2)
    run = tmp_path / "run"
    (run / "gaussians").mkdir(parents=True)
    for i, g in enumerate(gs):
        np.savez(run / "gaussians" / f"frame_{i:06d}.npz", **{k: getattr(g, k) for k in ("rgb", "log_radius", "opacity_logit", "offset", "depth")})
    write_tum_trajectory(run / "trajectory.txt", np.arange(2.0), poses)
    fx, fy, cx, cy = intr.as_tuple()
    (run / "cameras.json").write_text(json.dumps(dict(width=intr.width, height=intr.height, fx=fx, fy=fy, cx=cx, cy=cy)))
    (run / "metrics.json").write_text(json.dumps({"config": {"data": {"downscale": 1}, "export": {"voxel": 0.005}}}))
    assert main(["export", str(run), "--voxel", "0"]) == 0
    out = capsys.readouterr()
    w = read_3dgs_ply(run / "gaussians.ply")
    expected, _ = merged_gaussians((gs, poses, intr), voxel=0.0)
    np.testing.assert_allclose(w.xyz, expected.xyz, atol=1e-5)  # trajectory.txt keeps 9 digits
    assert f"kept {len(w)} of {2 * 20 * 16} Gaussians" in out.err
    assert main(["export", str(run), "--out", str(tmp_path / "m.ply")]) == 0  # default voxel
    assert len(read_3dgs_ply(tmp_path / "m.ply")) <= len(w)
    assert main(["export", str(tmp_path / "nothing")]) == 2
    assert "run folder not found" in capsys.readouterr().err


@pytest.mark.slow
def test_replica_gaussians_on_the_mesh(tmp_path):
    """A short Replica run's exported opaque Gaussians lie on the ground-truth surface (median
    distance below 1 cm), measured against points sampled densely on the mesh's triangles."""
    data = shared("replica_office0/rendered_100")
    mesh_path = data.parent / "office0_mesh.ply"
    out = tmp_path / "run"
    args = ["run", "--data", str(data), "--out", str(out), "--max-frames", "2", "--quiet", "--set", "data.downscale=2", "--set", "map.iterations=5", "--export-ply"]
    assert main(args) == 0
    w = read_3dgs_ply(out / "gaussians.ply")
    opaque = w.xyz[w.opacity > 0.5]
    assert len(opaque) > 10000
    margin = 0.05
    # Samples 3 mm apart put at most ~2 mm between a point on the surface and the nearest sample;
    # 20,000 of the Gaussians give the median to well under a millimetre.
    samples = _mesh_samples(mesh_path, 0.003, opaque.min(0) - margin, opaque.max(0) + margin)
    some = opaque[np.random.default_rng(0).permutation(len(opaque))[:20000]]
    dist = spatial.cKDTree(samples).query(some, workers=1)[0]
    print(f"replica: {len(opaque)} opaque of {len(w)} Gaussians, distance to the mesh median {100 * np.median(dist):.3f} cm, "
          f"90th percentile {100 * np.percentile(dist, 90):.3f} cm")
    assert np.median(dist) < 0.01, np.median(dist)


def _mesh_samples(path, spacing, lo, hi):
    """Points on every triangle of a PLY mesh that reaches into the box ``[lo, hi]``, no farther than
    ``spacing`` apart along each edge (a barycentric grid per triangle)."""
    ply = plyfile.PlyData.read(str(path))
    v = np.stack([ply["vertex"][k] for k in "xyz"], -1).astype(np.float64)
    tri = v[np.stack(ply["face"].data["vertex_indices"])[:, :3]]
    tri = tri[((tri.max(1) >= lo) & (tri.min(1) <= hi)).all(1)]
    steps = np.maximum(1, np.ceil(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=-1).max(1) / spacing)).astype(int)
    out = []
    for k in np.unique(steps):
        t = tri[steps == k]
        i, j = np.mgrid[0 : k + 1, 0 : k + 1]
        a, b = (i[i + j <= k] / k)[None, :, None], (j[i + j <= k] / k)[None, :, None]
        out.append((t[:, None, 0] * (1 - a - b) + t[:, None, 1] * a + t[:, None, 2] * b).reshape(-1, 3))
    return np.concatenate(out)
