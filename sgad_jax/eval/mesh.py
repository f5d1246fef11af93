"""Scores of a reconstructed mesh against a ground-truth mesh (host code, numpy and scipy).

Protocol (the SLAM papers' F1 at 1 cm and depth L1 at novel views, with the culling written down):

* **Surface points.** ``samples`` points are drawn uniformly (by area) on each mesh. A point's
  distance to the other mesh is its exact distance to the nearest of that mesh's triangles, among
  the triangles of the ``k`` nearest anchors on that surface (a ``cKDTree`` of every triangle's
  centroid and of area samples, five per triangle, 0.1-2 million in all). Distances between two sample sets would be biased upward by
  about half the sample spacing, which at a 1 cm threshold matters.
* **Culling to what the run saw.** With the run's frames (camera-to-world poses and depth images at
  the run's resolution: the dataset's measured depth where it can be opened, else the run's rendered
  depth), a point is projected into every frame; where it lands inside the image on a pixel with
  valid depth ``D`` (nearest pixel) at camera depth ``z``:

  - a ground-truth point counts if in some frame ``|z - D| <= band`` (on the observed surface);
  - a reconstruction point counts if in some frame ``z <= D + band`` (not hidden behind the observed
    surface: floaters in front of it are kept and cost precision). Points seen by no frame are dropped.

  The ground-truth poses are used for the ground truth when the dataset has them, the run's
  estimated poses for the reconstruction.
* **Accuracy** (cm): mean distance of the kept reconstruction points to the *whole* ground-truth
  mesh; **completion** (cm): mean distance of the kept ground-truth points to the reconstruction;
  **precision** / **recall**: the fractions of those under ``threshold``; **F1** their harmonic mean.
* **Depth L1** (cm): both meshes are rasterised (z-buffer, :func:`rasterize_depth`) at ``views`` novel
  views: a random frame's pose moved by a random rotation of up to ``max_angle_deg`` about a uniform
  axis and a translation uniform in a ball of radius ``max_shift`` (camera frame, seeded). The mean
  ``|D_rec - D_gt|`` over pixels where both meshes are rendered; ``mesh_depth_coverage`` is the
  fraction of pixels with ground truth where the reconstruction is rendered too.
"""

from __future__ import annotations

import dataclasses
import math
import pathlib

import numpy as np
from scipy.spatial import cKDTree

from sgad_jax.types import Intrinsics


def triangle_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=-1)


def sample_surface(vertices: np.ndarray, faces: np.ndarray, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points uniform on the surface (triangle by area, then uniform barycentric): ``(points (n, 3),
    triangle index (n,))``."""
    area = triangle_areas(vertices, faces)
    if len(faces) == 0 or area.sum() <= 0:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    tri = rng.choice(len(faces), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    a, b, c = (vertices[faces[tri, i]] for i in range(3))
    points = (1 - s)[:, None] * a + (s * (1 - r2))[:, None] * b + (s * r2)[:, None] * c
    return points, tri


def closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Closest points on triangles ``(a, b, c)`` to points ``p`` (all (..., 3)), by the Voronoi
    regions of the triangle (Ericson, *Real-Time Collision Detection*, 5.1.5)."""
    ab, ac, ap = b - a, c - a, p - a
    dot = lambda x, y: np.einsum("...i,...i->...", x, y)  # noqa: E731
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp, cp = p - b, p - c
    d3, d4 = dot(ab, bp), dot(ac, bp)
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    div = lambda x, y: x / np.where(np.abs(y) > 1e-30, y, 1e-30)  # noqa: E731  degenerate triangles
    total = va + vb + vc
    v, w = div(vb, total), div(vc, total)
    out = a + ab * v[..., None] + ac * w[..., None]  # inside the face
    bc_w = div(d4 - d3, (d4 - d3) + (d5 - d6))
    # Ericson tests the regions in order A, B, AB, C, AC, BC, face: assigned in reverse so the first wins
    cases = [
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), b + (c - b) * bc_w[..., None]),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + ac * div(d2, d2 - d6)[..., None]),
        ((d6 >= 0) & (d5 <= d6), c),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + ab * div(d1, d1 - d3)[..., None]),
        ((d3 >= 0) & (d4 <= d3), b),
        ((d1 <= 0) & (d2 <= 0), a),
    ]
    for mask, point in cases:
        out = np.where(mask[..., None], point, out)
    return out


class SurfaceDistance:
    """Distance of points to a triangle mesh: the exact distance to the nearest of the candidate
    triangles owning the ``k`` nearest anchors (centroids plus area samples) of the surface."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, *, anchors: int | None = None, k: int = 16, seed: int = 0):
        self.vertices, self.faces, self.k = np.asarray(vertices, np.float64), np.asarray(faces, np.int64), k
        if anchors is None:  # a few per triangle, so that large triangles are found by their area too
            anchors = int(np.clip(5 * len(self.faces), 100_000, 2_000_000))
        points, tri = sample_surface(self.vertices, self.faces, max(0, anchors - len(self.faces)), np.random.default_rng(seed))
        centroids = self.vertices[self.faces].mean(1)
        self.owner = np.concatenate([np.arange(len(self.faces)), tri])
        self.tree = cKDTree(np.concatenate([centroids, points]))

    def __call__(self, points: np.ndarray, chunk: int = 8192) -> np.ndarray:
        points = np.asarray(points, np.float64)
        if len(self.faces) == 0:
            return np.full(len(points), np.inf)
        k = min(self.k, len(self.owner))
        out = np.empty(len(points))
        for s in range(0, len(points), chunk):
            p = points[s : s + chunk]
            _, idx = self.tree.query(p, k=k)
            tri = self.faces[self.owner[idx.reshape(len(p), k)]]  # (c, k, 3)
            a, b, c = (self.vertices[tri[..., i]] for i in range(3))
            q = closest_on_triangles(p[:, None, :], a, b, c)
            out[s : s + chunk] = np.linalg.norm(q - p[:, None, :], axis=-1).min(1)
        return out


def rasterize_depth(vertices: np.ndarray, faces: np.ndarray, T_wc: np.ndarray, intr: Intrinsics, *, near: float = 0.01, chunk: int = 1 << 22) -> np.ndarray:
    """Z-buffer depth image (h, w) of a triangle mesh seen from camera-to-world ``T_wc``; 0 where empty.

    Pixel ``(v, u)`` samples the point ``(u, v)`` (pixel centres at integers, as
    :func:`sgad_jax.camera.project`); the depth is interpolated as ``1 / z``, linear in the image.
    Triangles with a corner nearer than ``near`` are skipped (no clipping).
    """
    w, h = intr.width, intr.height
    fx, fy, cx, cy = intr.as_tuple()
    T = np.asarray(T_wc, np.float64)
    p = (np.asarray(vertices, np.float64) - T[:3, 3]) @ T[:3, :3]
    z = p[:, 2]
    zs = np.where(z > near, z, 1.0)
    u, v = fx * p[:, 0] / zs + cx, fy * p[:, 1] / zs + cy
    faces = np.asarray(faces, np.int64)
    faces = faces[(z[faces] > near).all(1)]
    U, V, Z = u[faces], v[faces], z[faces]
    x0 = np.clip(np.ceil(U.min(1)), 0, w).astype(np.int64)
    x1 = np.clip(np.floor(U.max(1)), -1, w - 1).astype(np.int64)
    y0 = np.clip(np.ceil(V.min(1)), 0, h).astype(np.int64)
    y1 = np.clip(np.floor(V.max(1)), -1, h - 1).astype(np.int64)
    keep = (x1 >= x0) & (y1 >= y0)
    U, V, Z, x0, x1, y0, y1 = (a[keep] for a in (U, V, Z, x0, x1, y0, y1))
    bw = x1 - x0 + 1
    sizes = bw * (y1 - y0 + 1)
    zbuf = np.full(h * w, np.inf)
    ends = np.cumsum(sizes)
    start = 0
    while start < len(sizes):
        base = ends[start - 1] if start else 0
        stop = max(start + 1, int(np.searchsorted(ends, base + chunk, side="right")))
        sl = slice(start, stop)
        n = sizes[sl]
        t = np.repeat(np.arange(stop - start), n)
        k = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
        px = (x0[sl][t] + k % bw[sl][t]).astype(np.float64)
        py = (y0[sl][t] + k // bw[sl][t]).astype(np.float64)
        u0, u1, u2 = (U[sl][t, i] for i in range(3))
        v0, v1, v2 = (V[sl][t, i] for i in range(3))
        den = (v1 - v2) * (u0 - u2) + (u2 - u1) * (v0 - v2)
        ok = np.abs(den) > 1e-12
        den = np.where(ok, den, 1.0)
        l0 = ((v1 - v2) * (px - u2) + (u2 - u1) * (py - v2)) / den
        l1 = ((v2 - v0) * (px - u2) + (u0 - u2) * (py - v2)) / den
        l2 = 1.0 - l0 - l1
        eps = -1e-9  # shared edges: a pixel centre on an edge belongs to both triangles, never to none
        inside = ok & (l0 >= eps) & (l1 >= eps) & (l2 >= eps)
        inv = l0 / Z[sl][t, 0] + l1 / Z[sl][t, 1] + l2 / Z[sl][t, 2]
        pix = (py * w + px).astype(np.int64)
        np.minimum.at(zbuf, pix[inside], 1.0 / inv[inside])
        start = stop
    zbuf[~np.isfinite(zbuf)] = 0.0
    return zbuf.reshape(h, w)


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def novel_views(poses: np.ndarray, n: int, *, seed: int = 0, max_angle_deg: float = 10.0, max_shift: float = 0.1) -> np.ndarray:
    """``n`` camera-to-world poses near a trajectory: a random pose of ``poses`` moved, in its camera
    frame, by a rotation of uniform angle up to ``max_angle_deg`` about a uniform axis and a
    translation uniform in the ball of radius ``max_shift`` (metres)."""
    rng = np.random.default_rng(seed)
    poses = np.asarray(poses, np.float64)
    poses = poses[np.isfinite(poses).all((1, 2))]
    out = np.empty((n, 4, 4))
    for i in range(n):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        d = rng.normal(size=3)
        d *= max_shift * rng.random() ** (1 / 3) / np.linalg.norm(d)
        delta = np.eye(4)
        delta[:3, :3] = _rotation(axis, math.radians(max_angle_deg) * rng.random())
        delta[:3, 3] = d
        out[i] = poses[rng.integers(len(poses))] @ delta
    return out


def visibility(points: np.ndarray, poses: np.ndarray, depths, intr: Intrinsics, band: float) -> tuple[np.ndarray, np.ndarray]:
    """For each point, ``(on_surface, not_behind)``: whether in some frame it lands inside the image on
    valid depth ``D`` with ``|z - D| <= band``, and with ``z <= D + band``."""
    fx, fy, cx, cy = intr.as_tuple()
    on, front = np.zeros(len(points), bool), np.zeros(len(points), bool)
    for T, D in zip(poses, depths):
        T = np.asarray(T, np.float64)
        if not np.isfinite(T).all():
            continue
        p = (points - T[:3, 3]) @ T[:3, :3]
        z = p[:, 2]
        zs = np.where(z > 1e-6, z, 1.0)
        u = np.round(fx * p[:, 0] / zs + cx).astype(np.int64)
        v = np.round(fy * p[:, 1] / zs + cy).astype(np.int64)
        h, w = D.shape
        inside = (z > 1e-6) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        d = np.where(inside, D[np.clip(v, 0, h - 1), np.clip(u, 0, w - 1)], 0.0)
        valid = inside & (d > 0)
        on |= valid & (np.abs(z - d) <= band)
        front |= valid & (z <= d + band)
    return on, front


@dataclasses.dataclass(frozen=True)
class Views:
    """Frames that define what was seen: camera-to-world poses (f, 4, 4) and depth (f, h, w), metres."""

    poses: np.ndarray
    depths: np.ndarray


def score_mesh(
    rec: tuple[np.ndarray, np.ndarray],
    gt: tuple[np.ndarray, np.ndarray],
    intr: Intrinsics,
    seen_gt: Views,
    seen_rec: Views | None = None,
    *,
    threshold: float = 0.01,
    samples: int = 200_000,
    band: float = 0.05,
    views: np.ndarray | int = 100,
    seed: int = 0,
) -> dict:
    """Accuracy, completion, precision, recall, F1 and novel-view depth L1 of a mesh (module docstring).

    Args:
        rec: the reconstruction's ``(vertices (m, 3), faces (k, 3))``, world metres.
        gt: the ground truth's.
        intr: intrinsics of the depth images and of the novel views.
        seen_gt: frames that cull the ground truth (its poses; depth at the run's resolution).
        seen_rec: frames that cull the reconstruction (the estimated poses); default ``seen_gt``.
        threshold: metres, for precision, recall and F1.
        samples: points drawn on each surface.
        band: metres, the culling tolerance around the observed surface.
        views: novel views (n, 4, 4) camera-to-world, or how many to draw around ``seen_gt.poses``.
        seed: of the surface samples and the novel views.

    Returns:
        ``mesh_f1``, ``mesh_precision``, ``mesh_recall``, ``mesh_accuracy_cm``, ``mesh_completion_cm``,
        ``mesh_depth_l1_cm``, ``mesh_depth_coverage`` and the protocol's settings and counts.
    """
    seen_rec = seen_gt if seen_rec is None else seen_rec
    rng = np.random.default_rng(seed)
    rv, rf = (np.asarray(a) for a in rec)
    gv, gf = (np.asarray(a) for a in gt)
    rec_pts, _ = sample_surface(rv, rf, samples, rng)
    gt_pts, _ = sample_surface(gv, gf, samples, rng)
    gt_pts = gt_pts[visibility(gt_pts, seen_gt.poses, seen_gt.depths, intr, band)[0]]
    rec_pts = rec_pts[visibility(rec_pts, seen_rec.poses, seen_rec.depths, intr, band)[1]]
    acc = SurfaceDistance(gv, gf, seed=seed + 1)(rec_pts) if len(rec_pts) else np.zeros(0)
    comp = SurfaceDistance(rv, rf, seed=seed + 2)(gt_pts) if len(gt_pts) else np.zeros(0)
    mean = lambda x: float(np.mean(x)) if len(x) else float("nan")  # noqa: E731
    precision = mean(acc < threshold) if len(rec_pts) else 0.0
    recall = mean(comp < threshold) if len(gt_pts) else float("nan")
    f1 = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0

    if isinstance(views, (int, np.integer)):
        views = novel_views(seen_gt.poses, int(views), seed=seed)
    total, both, gt_pixels = 0.0, 0, 0
    for T in views:
        d_gt = rasterize_depth(gv, gf, T, intr)
        d_rec = rasterize_depth(rv, rf, T, intr)
        m = (d_gt > 0) & (d_rec > 0)
        total += float(np.abs(d_rec - d_gt)[m].sum())
        both += int(m.sum())
        gt_pixels += int((d_gt > 0).sum())
    return {
        "mesh_f1": f1,
        "mesh_precision": precision,
        "mesh_recall": recall,
        "mesh_accuracy_cm": 100 * mean(acc),
        "mesh_completion_cm": 100 * mean(comp),
        "mesh_depth_l1_cm": 100 * total / both if both else float("nan"),
        "mesh_depth_coverage": both / gt_pixels if gt_pixels else 0.0,
        "mesh_threshold_cm": 100 * threshold,
        "mesh_cull_band_cm": 100 * band,
        "mesh_samples": samples,
        "mesh_rec_points_kept": int(len(rec_pts)),
        "mesh_gt_points_kept": int(len(gt_pts)),
        "mesh_views": int(len(views)),
    }


def eval_mesh_run(run_dir, gt_mesh, *, data: str | None = None, mesh: str | None = None, **kwargs) -> dict:
    """Score ``RUN_DIR/mesh.ply`` (or ``mesh``) against ``gt_mesh`` and merge the keys into
    ``RUN_DIR/eval.json``. The frames that cull are the dataset's (measured depth, ground-truth poses
    for the ground truth) when the run's dataset (or ``data``) opens, else the run's renders.

    Raises:
        DatasetError: a missing or unreadable file, named.
    """
    from sgad_jax.io.base import DatasetError
    from sgad_jax.io.ply import read_mesh_ply
    from sgad_jax.io.rundir import Run, merge_eval_json, read_render

    run = Run(run_dir)
    rec_path = pathlib.Path(mesh) if mesh else run.root / "mesh.ply"
    if not rec_path.is_file():
        raise DatasetError(f"{rec_path}: no mesh (make it with `sgad-jax mesh {run.root}` or run with --mesh)")
    rv, rf, _ = read_mesh_ply(rec_path)
    gv, gf, _ = read_mesh_ply(gt_mesh)
    if len(gf) == 0:
        raise DatasetError(f"{gt_mesh}: the ground-truth mesh has no faces")
    poses = run.trajectory[1]
    intr = run.intrinsics
    cfg = run.config if (run.root / "metrics.json").is_file() else None
    seen_gt = seen_rec = None
    source = "renders"
    if cfg is not None:
        from sgad_jax.io.datasets import open_dataset

        dcfg = cfg.data if data is None else dataclasses.replace(cfg.data, path=data)
        try:
            ds = open_dataset(dcfg)
        except DatasetError:
            ds = None
        if ds is not None and len(ds) >= len(poses) and (ds.intrinsics.width, ds.intrinsics.height) == (intr.width, intr.height):
            depths = np.stack([ds[i].depth for i in range(len(poses))])
            gt_poses = ds.gt_poses[: len(poses)]
            use_gt = np.isfinite(gt_poses).all()
            seen_rec = Views(poses, depths)
            seen_gt = Views(gt_poses if use_gt else poses, depths)
            source = "dataset"
    if seen_gt is None:
        indices = run.render_frames(with_depth=True)
        if not indices:
            raise DatasetError(f"{run.root / 'renders'}: no depth renders to cull with, and the run's dataset does not open")
        depths = np.stack([read_render(run.root, i)[1] for i in indices])
        seen_gt = seen_rec = Views(poses[indices], depths)
    scores = score_mesh((rv, rf), (gv, gf), intr, seen_gt, seen_rec, **kwargs)
    scores["mesh_cull_depth"] = source
    scores["mesh_gt"] = str(gt_mesh)
    merge_eval_json(run.root, scores)
    return scores
