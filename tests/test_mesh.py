"""TSDF fusion and marching cubes, the mesh scores and the rasteriser, against analytic scenes."""

import json
import math
import pathlib

import numpy as np
import pytest

from sgad_jax.config import MeshConfig
from sgad_jax.eval.mesh import (
    SurfaceDistance,
    Views,
    closest_on_triangles,
    novel_views,
    rasterize_depth,
    score_mesh,
)
from sgad_jax.io.ply import read_mesh_ply, write_mesh_ply
from sgad_jax.mesh import fuse, plan_grid
from sgad_jax.types import make_intrinsics


def look_at(eye, target, up=(0.0, 0.0, 1.0)):
    """Camera-to-world pose (OpenCV axes: z forward, y down) at ``eye`` looking at ``target``."""
    eye, target, up = (np.asarray(a, np.float64) for a in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(z, (0.0, 1.0, 0.0))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], 1)
    T[:3, 3] = eye
    return T


def rays(intr):
    """Camera-frame ray directions (h, w, 3) with z = 1 through every pixel centre."""
    v, u = np.mgrid[0 : intr.height, 0 : intr.width].astype(np.float64)
    fx, fy, cx, cy = intr.as_tuple()
    return np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1)


def sphere_depth(T_wc, intr, centre, radius):
    """Analytic z-depth of a sphere (0 where the ray misses it) and its colour 0.5 + 0.5 n."""
    d = rays(intr) @ T_wc[:3, :3].T  # world directions, camera z = 1
    o = T_wc[:3, 3] - centre
    a, b, c = (d * d).sum(-1), (d * o).sum(-1), o @ o - radius**2
    disc = b * b - a * c
    s = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0))) / a, 0.0)
    hit = (disc > 0) & (s > 0)
    n = (o + s[..., None] * d) / radius
    return np.where(hit, s, 0.0).astype(np.float32), np.where(hit[..., None], 0.5 + 0.5 * n, 0.0).astype(np.float32)


def plane_depth(T_wc, intr, normal, offset):
    """Analytic z-depth of the plane ``normal . p = offset`` (0 where behind the camera)."""
    d = rays(intr) @ T_wc[:3, :3].T
    s = (offset - normal @ T_wc[:3, 3]) / (d @ normal)
    return np.where(s > 0, s, 0.0)


def quad(corners):
    """Two triangles of a quad given by its 4 corners in order."""
    return np.asarray(corners, np.float64), np.array([[0, 1, 2], [0, 2, 3]])


def grid_plane(z, half, n):
    """A square at height ``z`` (|x|, |y| <= half) as an n x n grid of quads (2 n^2 triangles)."""
    t = np.linspace(-half, half, n + 1)
    x, y = np.meshgrid(t, t, indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], -1)
    i = np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]
    i = i.ravel()
    f = np.concatenate([np.stack([i, i + n + 1, i + n + 2], -1), np.stack([i, i + n + 2, i + 1], -1)])
    return v, f


# --- TSDF + marching cubes ------------------------------------------------------------------------


def test_tsdf_sphere_within_a_voxel():
    """Six analytic depth images of a sphere fuse into a mesh whose vertices lie within a voxel of the
    sphere, cover it to its poles, and carry its colour."""
    # pixels (~4 mm on the sphere) finer than the voxels, so the nearest-pixel depth lookup is not the limit
    intr = make_intrinsics(200.0, 200.0, 99.5, 74.5, 200, 150)
    centre, radius = np.array([0.2, -0.1, 0.5]), 0.25
    eyes = [centre + 1.0 * e for e in np.concatenate([np.eye(3), -np.eye(3)])]
    poses = np.stack([look_at(e, centre) for e in eyes])
    frames = []
    for T in poses:
        depth, rgb = sphere_depth(T, intr, centre, radius)
        frames.append((rgb, depth))
    cfg = MeshConfig(voxel=0.01, trunc=0.04)
    vertices, faces, colours, plan = fuse(frames, poses, intr, cfg)
    assert not plan.coarsened and plan.voxel == pytest.approx(0.01)
    assert len(faces) > 1000
    r = np.linalg.norm(vertices - centre, axis=1)
    err = np.abs(r - radius)
    assert err.max() < 0.01 and err.mean() < 0.003, (err.max(), err.mean())
    # the mesh reaches the sphere's extremes along every axis (it is not a patch)
    for axis in range(3):
        assert vertices[:, axis].max() > centre[axis] + radius - 0.01
        assert vertices[:, axis].min() < centre[axis] - radius + 0.01
    # colour: 0.5 + 0.5 n, smeared by the trilinear lookup over a voxel
    n = (vertices - centre) / r[:, None]
    assert np.abs(colours / 255.0 - (0.5 + 0.5 * n)).mean() < 0.05


def test_grid_budget_coarsens_and_says_so():
    lo, hi = np.zeros(3), np.full(3, 4.0)
    plan = plan_grid(lo, hi, 0.01, 0.04, 1 << 20)
    assert plan.coarsened and plan.voxels <= 1 << 20 and plan.voxel > 0.01
    assert plan.trunc / plan.voxel == pytest.approx(4.0)
    fine = plan_grid(lo, np.full(3, 0.5), 0.01, 0.04, 1 << 20)
    assert not fine.coarsened and fine.voxel == 0.01
    # the grid covers the box plus the truncation on every side
    assert (fine.origin <= lo - 0.04).all() and (fine.origin + 0.01 * (np.array(fine.shape) - 1) >= 0.5 + 0.04).all()
    with pytest.raises(ValueError, match="no valid depth"):
        plan_grid(np.full(3, np.inf), np.full(3, -np.inf), 0.01, 0.04, 1 << 20)


def test_mesh_ply_roundtrip(tmp_path):
    v = np.random.default_rng(0).normal(size=(10, 3)).astype(np.float32)
    f = np.array([[0, 1, 2], [3, 4, 5], [7, 8, 9]])
    c = np.arange(30, dtype=np.uint8).reshape(10, 3)
    write_mesh_ply(tmp_path / "m.ply", v, f, c)
    from plyfile import PlyData

    ply = PlyData.read(str(tmp_path / "m.ply"))
    assert ply.text is False and [p.name for p in ply["vertex"].properties] == ["x", "y", "z", "red", "green", "blue"]
    assert ply["face"].properties[0].name == "vertex_indices"
    v2, f2, c2 = read_mesh_ply(tmp_path / "m.ply")
    np.testing.assert_array_equal(v2, v)
    np.testing.assert_array_equal(f2, f)
    np.testing.assert_array_equal(c2, c)


# --- distances and the rasteriser -----------------------------------------------------------------


def test_closest_point_on_triangle_against_dense_sampling():
    """Exact point-triangle distances against the minimum over a fine barycentric grid of the triangle."""
    rng = np.random.default_rng(1)
    g = np.linspace(0, 1, 201)
    s, t = np.meshgrid(g, g)
    keep = s + t <= 1
    s, t = s[keep], t[keep]
    for _ in range(20):
        a, b, c = rng.normal(size=(3, 3))
        p = rng.normal(size=(50, 3)) * 2
        q = closest_on_triangles(p, a, b, c)
        exact = np.linalg.norm(q - p, axis=1)
        dense = a + s[:, None] * (b - a) + t[:, None] * (c - a)
        brute = np.linalg.norm(p[:, None] - dense[None], axis=-1).min(1)
        spacing = max(np.linalg.norm(b - a), np.linalg.norm(c - a), np.linalg.norm(c - b)) / 200
        assert (exact <= brute + 1e-9).all() and (brute - exact < spacing).all()


def test_surface_distance_of_a_plane():
    v, f = grid_plane(0.0, 1.0, 3)
    rng = np.random.default_rng(2)
    p = np.concatenate([rng.uniform(-1, 1, (500, 2)), rng.uniform(-0.3, 0.3, (500, 1))], 1)
    np.testing.assert_allclose(SurfaceDistance(v, f)(p), np.abs(p[:, 2]), atol=1e-9)


def test_rasterizer_against_an_analytic_plane():
    """Depth of a tilted plane (a grid of triangles) equals the ray-plane intersection at every covered
    pixel; a nearer square in front of it wins the z-buffer; pixels off the mesh are 0."""
    intr = make_intrinsics(50.0, 55.0, 31.5, 23.5, 64, 48)
    T = look_at((0.1, -0.2, -2.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0))
    v, f = grid_plane(0.0, 0.6, 5)
    R = np.array([[1, 0, 0], [0, math.cos(0.4), -math.sin(0.4)], [0, math.sin(0.4), math.cos(0.4)]])
    v = v @ R.T
    normal = R @ np.array([0.0, 0.0, 1.0])
    depth = rasterize_depth(v, f, T, intr)
    expect = plane_depth(T, intr, normal, 0.0)
    covered = depth > 0
    assert 300 < covered.sum() < covered.size
    np.testing.assert_allclose(depth[covered], expect[covered], rtol=1e-9)
    # pixels whose ray hits the plane inside the square are all covered (no cracks between triangles)
    hit = rays(intr) @ T[:3, :3].T * expect[..., None] + T[:3, 3]
    local = hit @ R
    inside = (np.abs(local[..., :2]) < 0.6 - 1e-6).all(-1)
    assert (covered == inside).all()
    # a square in front occludes
    front, ff = grid_plane(-0.5, 0.2, 1)
    both = np.concatenate([v, front]), np.concatenate([f, ff + len(v)])
    d2 = rasterize_depth(*both, T, intr)
    near = plane_depth(T, intr, np.array([0.0, 0.0, 1.0]), -0.5)
    p_near = rays(intr) @ T[:3, :3].T * near[..., None] + T[:3, 3]
    occluded = (np.abs(p_near[..., :2]) < 0.2 - 1e-6).all(-1)
    assert occluded.sum() > 20
    np.testing.assert_allclose(d2[occluded], near[occluded], rtol=1e-9)
    np.testing.assert_allclose(d2[covered & ~occluded], expect[covered & ~occluded], rtol=1e-9)


# --- scores ---------------------------------------------------------------------------------------


def _plane_scene():
    """A camera 1 m above the floor z = 0 looking down; the ground truth is a 6 m floor."""
    intr = make_intrinsics(40.0, 40.0, 23.5, 17.5, 48, 36)
    T = look_at((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0))
    depth = plane_depth(T, intr, np.array([0.0, 0.0, 1.0]), 0.0).astype(np.float32)
    return intr, Views(T[None], depth[None]), grid_plane(0.0, 3.0, 6)


def test_score_mesh_of_itself_is_perfect():
    intr, seen, gt = _plane_scene()
    s = score_mesh(gt, gt, intr, seen, samples=20000, views=5)
    assert s["mesh_f1"] == 1.0 and s["mesh_precision"] == 1.0 and s["mesh_recall"] == 1.0
    assert s["mesh_accuracy_cm"] < 1e-6 and s["mesh_completion_cm"] < 1e-6 and s["mesh_depth_l1_cm"] < 1e-6
    # culling: only the floor under the camera's ~1.2 x 0.9 m footprint of the 36 m^2 counts
    footprint = (48 / 40) * (36 / 40)
    assert s["mesh_gt_points_kept"] / 20000 == pytest.approx(footprint / 36, rel=0.1)
    assert s["mesh_depth_coverage"] > 0.99


@pytest.mark.parametrize("shift", [0.02, -0.02, 0.005])
def test_score_mesh_of_a_shifted_copy(shift):
    """The floor moved by ``shift`` along its normal: every distance is |shift|, so precision and recall
    at 1 cm are 0 for 2 cm and 1 for 0.5 cm; depth L1 is the analytic difference of the two planes."""
    intr, seen, gt = _plane_scene()
    v, f = gt
    rec = (v + [0.0, 0.0, shift], f)
    views = novel_views(seen.poses, 4, seed=3, max_angle_deg=10, max_shift=0.1)
    s = score_mesh(rec, gt, intr, seen, samples=20000, views=views)
    ok = abs(shift) < 0.01
    assert s["mesh_precision"] == float(ok) and s["mesh_recall"] == float(ok) and s["mesh_f1"] == float(ok)
    assert s["mesh_accuracy_cm"] == pytest.approx(100 * abs(shift), rel=1e-6)
    assert s["mesh_completion_cm"] == pytest.approx(100 * abs(shift), rel=1e-6)
    n = np.array([0.0, 0.0, 1.0])
    diffs = [np.abs(plane_depth(T, intr, n, shift) - plane_depth(T, intr, n, 0.0)) for T in views]
    assert s["mesh_depth_l1_cm"] == pytest.approx(100 * np.mean(diffs), rel=1e-6)


def test_score_mesh_culling_rules():
    """Half the floor reconstructed: recall ~1/2, precision 1. A piece 30 cm under the floor (hidden
    behind the observed surface) is dropped; the same piece 30 cm above it (a floater) costs precision."""
    intr, seen, gt = _plane_scene()
    half = quad([(-3, -3, 0), (0, -3, 0), (0, 3, 0), (-3, 3, 0)])
    s = score_mesh(half, gt, intr, seen, samples=40000, views=3)
    assert s["mesh_precision"] == 1.0 and s["mesh_recall"] == pytest.approx(0.5, abs=0.03)

    def plus(piece_z):
        piece = quad([(-0.2, -0.2, piece_z), (0.2, -0.2, piece_z), (0.2, 0.2, piece_z), (-0.2, 0.2, piece_z)])
        v = np.concatenate([gt[0], piece[0]])
        return v, np.concatenate([gt[1], piece[1] + len(gt[0])])

    hidden = score_mesh(plus(-0.3), gt, intr, seen, samples=40000, views=3)
    assert hidden["mesh_precision"] == 1.0
    floater = score_mesh(plus(0.3), gt, intr, seen, samples=40000, views=3)
    # the floater's share of the kept reconstruction area: 0.16 m^2 against the ~1.08 m^2 floor seen
    seen_floor = (48 / 40) * (36 / 40)
    assert 1 - floater["mesh_precision"] == pytest.approx(0.16 / (0.16 + seen_floor), rel=0.15)
    assert floater["mesh_recall"] == 1.0


# --- the command line on a fabricated run folder --------------------------------------------------


def uv_sphere(centre, radius, n=120):
    """A latitude-longitude triangulation of a sphere (chord error radius * (1 - cos(pi / n)))."""
    th, ph = np.meshgrid(np.linspace(0, np.pi, n + 1), np.linspace(0, 2 * np.pi, 2 * n + 1), indexing="ij")
    v = centre + radius * np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1).reshape(-1, 3)
    i = (np.arange(n)[:, None] * (2 * n + 1) + np.arange(2 * n)[None, :]).ravel()
    f = np.concatenate([np.stack([i, i + 2 * n + 1, i + 2 * n + 2], -1), np.stack([i, i + 2 * n + 2, i + 1], -1)])
    return v, f


def fabricate_sphere_run(root, with_renders=True):
    """A run folder as the pipeline writes it: trajectory, cameras.json and analytic renders of a sphere."""
    import cv2

    from sgad_jax.io.export import write_tum_trajectory

    intr = make_intrinsics(200.0, 200.0, 99.5, 74.5, 200, 150)
    centre, radius = np.array([0.2, -0.1, 0.5]), 0.25
    eyes = [centre + 1.0 * e for e in np.concatenate([np.eye(3), -np.eye(3)])]
    poses = np.stack([look_at(e, centre) for e in eyes])
    root.mkdir(parents=True, exist_ok=True)
    write_tum_trajectory(root / "trajectory.txt", np.arange(len(poses), dtype=float), poses)
    (root / "cameras.json").write_text(json.dumps({"width": 200, "height": 150, "fx": 200.0, "fy": 200.0, "cx": 99.5, "cy": 74.5}))
    if with_renders:
        (root / "renders").mkdir()
        for i, T in enumerate(poses):
            depth, rgb = sphere_depth(T, intr, centre, radius)
            cv2.imwrite(str(root / "renders" / f"rgb_{i:06d}.png"), cv2.cvtColor((rgb * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR))
            cv2.imwrite(str(root / "renders" / f"depth_{i:06d}.png"), (depth * 1000 + 0.5).astype(np.uint16))
    return intr, poses, centre, radius


def test_cli_mesh_and_eval_mesh(tmp_path, capsys):
    from sgad_jax.cli import main

    run = tmp_path / "run"
    _, _, centre, radius = fabricate_sphere_run(run)
    assert main(["mesh", str(run), "--compile-cache", "off"]) == 0
    info = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert info["voxel_m"] == pytest.approx(0.01) and info["frames"] == 6
    v, f, c = read_mesh_ply(run / "mesh.ply")
    assert len(f) == info["faces"] > 1000 and c is not None
    assert np.abs(np.linalg.norm(v - centre, axis=1) - radius).max() < 0.01
    write_mesh_ply(tmp_path / "gt.ply", *uv_sphere(centre, radius))
    (run / "eval.json").write_text(json.dumps({"ate_rmse_cm": 1.5}))
    assert main(["eval-mesh", str(run), "--gt-mesh", str(tmp_path / "gt.ply"), "--samples", "20000", "--views", "3"]) == 0
    scores = json.loads((run / "eval.json").read_text())
    assert scores["ate_rmse_cm"] == 1.5  # merged, not replaced
    assert scores["mesh_cull_depth"] == "renders"  # no metrics.json: the renders say what was seen
    assert scores["mesh_f1"] > 0.97 and scores["mesh_accuracy_cm"] < 0.3 and scores["mesh_completion_cm"] < 0.3
    # at grazing pixels near the silhouette a 1 mm radial error is centimetres of depth: a loose bound
    # here; the plane tests check the depth L1 exactly
    assert scores["mesh_depth_l1_cm"] < 2.0 and scores["mesh_depth_coverage"] > 0.9
    # coarser voxels from the command line
    assert main(["mesh", str(run), "--set", "mesh.voxel=0.02", "--set", "mesh.trunc=0.08"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["voxel_m"] == pytest.approx(0.02)


@pytest.mark.parametrize(
    "args, needle",
    [
        (["mesh", "{run}"], "--save-renders"),
        (["mesh", "{tmp}/nowhere"], "run folder not found"),
        (["mesh", "{run}", "--set", "map.iterations=3"], "only mesh.*"),
        (["eval-mesh", "{run}", "--gt-mesh", "{tmp}/missing.ply"], "no mesh"),
        # settings fusion cannot use, said before the renders are looked for (the config refuses the first two)
        (["mesh", "{run}", "--set", "mesh.voxel=0"], "mesh.voxel: must be > 0, got 0.0"),
        (["mesh", "{run}", "--set", "mesh.voxel=-0.01"], "mesh.voxel: must be > 0, got -0.01"),
        (["mesh", "{run}", "--set", "mesh.max_voxels=100"], "mesh.max_voxels: must be >= 1728"),
    ],
)
def test_cli_mesh_errors_one_line(tmp_path, capsys, args, needle):
    from sgad_jax.cli import main

    run = tmp_path / "run"
    fabricate_sphere_run(run, with_renders=False)
    code = main([a.format(run=run, tmp=tmp_path) for a in args])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and needle in err, err


def test_run_with_mesh_flag(tmp_path, capsys, monkeypatch):
    """``run --mesh`` asks the pipeline for renders and fuses them into mesh.ply when the run ends (the
    pipeline itself is stood in for by a fabricated run, so the test costs no SLAM run)."""
    from sgad_jax import cli, pipeline

    asked = {}

    def fake_run(cfg, out, **kwargs):
        asked.update(kwargs)
        fabricate_sphere_run(pathlib.Path(out))
        return pipeline.RunResult(poses=np.zeros((0, 4, 4)), timestamps=np.zeros(0), metrics={"frames": 6})

    monkeypatch.setattr(pipeline, "run", fake_run)
    out = tmp_path / "run"
    assert cli.main(["run", "--out", str(out), "--quiet", "--mesh", "--compile-cache", "off"]) == 0
    assert asked["save_renders"] is True
    assert "mesh.ply" in capsys.readouterr().err
    v, f, c = read_mesh_ply(out / "mesh.ply")
    assert len(f) > 1000 and np.abs(np.linalg.norm(v - [0.2, -0.1, 0.5], axis=1) - 0.25).max() < 0.01
    assert cli.main(["run", "--out", str(out), "--mesh", "--track-only"]) == 2
