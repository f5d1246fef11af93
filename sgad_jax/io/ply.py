"""The merged map as a 3D Gaussian Splatting ``.ply`` file, which 3DGS viewers open.

A run's map is every mapped frame's pixel-aligned Gaussians (:class:`~sgad_jax.types.PixelGaussians`):
Gaussian (v, u) of a frame sits at camera depth ``z = |depth + offset|`` on the ray of pixel (v, u),
``x = (u - cx) / fx z``, ``y = (v - cy) / fy z``, moved to the world by the frame's camera-to-world
pose. It is isotropic with standard deviation ``sigma = exp(log_radius) / RADIUS_SIGMAS`` (the
radius is a 3-sigma extent), opacity ``sigmoid(opacity_logit)`` and linear colour ``rgb``.

Every frame re-covers the surface its neighbours saw, so the export merges: one Gaussian per cubic
cell of side ``voxel`` (``voxel = 0`` keeps all), the one seen from the smallest camera depth ``z``
(the finest view of that surface: the pixel footprint and the depth sensor's noise both grow with
``z``), ties to the more opaque. Gaussians that are all but transparent (opacity below
:data:`MIN_OPACITY`) or sit behind the near plane of their own camera are dropped first.

File layout (the 3DGS reference implementation's ``save_ply``): one ``vertex`` element, binary
little-endian, float32 properties ``x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 opacity scale_0 scale_1
scale_2 rot_0 rot_1 rot_2 rot_3``: normals 0, ``f_dc = (rgb - 0.5) / C0`` (degree-0 spherical
harmonics, ``C0 = 1 / (2 sqrt(pi))``), ``opacity`` the logit, ``scale_k = log sigma`` (all three
equal), ``rot`` the unit quaternion ``(w, x, y, z) = (1, 0, 0, 0)``.
"""

from __future__ import annotations

import dataclasses
import math
import os
import pathlib

import numpy as np
import plyfile

from sgad_jax.io.base import DatasetError
from sgad_jax.io.files import atomic_write
from sgad_jax.splat import NEAR, RADIUS_SIGMAS
from sgad_jax.types import Intrinsics, PixelGaussians

#: Degree-0 real spherical harmonic, ``1 / (2 sqrt(pi))``: 3DGS stores colour as ``(rgb - 0.5) / C0``.
SH_C0 = 0.28209479177387814
#: Gaussians less opaque than this are dropped (3DGS prunes below the same opacity).
MIN_OPACITY = 0.005
PROPERTIES = (
    "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
    "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
)
#: Candidates gathered before a merge pass (bounds the export's memory on long runs).
_MERGE_CHUNK = 1 << 22


@dataclasses.dataclass(frozen=True)
class WorldGaussians:
    """Isotropic Gaussians in world coordinates (host arrays, float32; not a pytree).

    Attributes:
        xyz: (n, 3) centres, metres.
        rgb: (n, 3) linear colour (as learned: not clipped to [0, 1]).
        opacity_logit: (n,) ``logit(opacity)``.
        log_sigma: (n,) log of the standard deviation in metres.
    """

    xyz: np.ndarray
    rgb: np.ndarray
    opacity_logit: np.ndarray
    log_sigma: np.ndarray

    def __len__(self) -> int:
        return len(self.xyz)

    @property
    def opacity(self) -> np.ndarray:
        return 1.0 / (1.0 + np.exp(-self.opacity_logit))

    @property
    def sigma(self) -> np.ndarray:
        return np.exp(self.log_sigma)

    def take(self, index) -> "WorldGaussians":
        return WorldGaussians(*(getattr(self, f.name)[index] for f in dataclasses.fields(self)))


@dataclasses.dataclass(frozen=True)
class MergeInfo:
    """Counts of an export: ``total`` Gaussians in the stored frames, ``visible`` after dropping the
    transparent ones and those behind their camera, ``kept`` after merging; ``voxel`` the cell (m)."""

    frames: int
    total: int
    visible: int
    kept: int
    voxel: float


def frame_to_world(g: PixelGaussians, T_wc: np.ndarray, intr: Intrinsics) -> tuple[WorldGaussians, np.ndarray]:
    """One frame's Gaussians in the world, flattened row-major (pixel (v, u) is entry ``v w + u``).

    Args:
        g: the frame's Gaussians, fields ``(h, w[, 3])``.
        T_wc: (4, 4) camera-to-world pose of the frame.
        intr: the intrinsics the frame was mapped with (after downscale).

    Returns:
        the Gaussians and (n,) their camera depth ``z`` in their own frame.
    """
    depth = np.asarray(g.depth, np.float64)
    h, w = depth.shape
    if (h, w) != (intr.height, intr.width):
        raise ValueError(f"Gaussians of {w}x{h} pixels, intrinsics of {intr.width}x{intr.height}")
    fx, fy, cx, cy = intr.as_tuple()
    z = np.abs(depth + np.asarray(g.offset, np.float64))
    v, u = np.mgrid[0:h, 0:w]
    p_c = np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], -1).reshape(-1, 3)
    T = np.asarray(T_wc, np.float64)
    p_w = p_c @ T[:3, :3].T + T[:3, 3]
    log_sigma = np.asarray(g.log_radius, np.float32).reshape(-1) - np.float32(math.log(RADIUS_SIGMAS))
    out = WorldGaussians(
        xyz=p_w.astype(np.float32),
        rgb=np.asarray(g.rgb, np.float32).reshape(-1, 3),
        opacity_logit=np.asarray(g.opacity_logit, np.float32).reshape(-1),
        log_sigma=log_sigma.astype(np.float32),
    )
    return out, z.reshape(-1).astype(np.float32)


def _concat(parts: list[WorldGaussians]) -> WorldGaussians:
    if not parts:
        z = np.zeros((0,), np.float32)
        return WorldGaussians(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), z, z)
    return WorldGaussians(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in dataclasses.fields(WorldGaussians)))


def _best_per_voxel(g: WorldGaussians, z: np.ndarray, voxel: float) -> tuple[WorldGaussians, np.ndarray]:
    """The Gaussian of smallest camera depth in each occupied voxel (ties: the more opaque, then
    the earlier one)."""
    cells = np.floor(g.xyz.astype(np.float64) / voxel).astype(np.int64)
    # One sort key per cell: rows of the cell indices, ranked (np.unique on rows), then lexsort.
    _, cell_id = np.unique(cells, axis=0, return_inverse=True)
    cell_id = cell_id.reshape(-1)
    order = np.lexsort((np.arange(len(z)), -g.opacity_logit, z, cell_id))
    first = np.ones(len(order), bool)
    first[1:] = cell_id[order[1:]] != cell_id[order[:-1]]
    keep = np.sort(order[first])
    return g.take(keep), z[keep]


def merged_gaussians(source, voxel: float | None = None, *, min_opacity: float = MIN_OPACITY) -> tuple[WorldGaussians, MergeInfo]:
    """World-space Gaussians of every mapped frame, merged to one per ``voxel`` cell.

    Args:
        source: a finished run's folder (its ``gaussians/``, ``trajectory.txt`` and intrinsics, see
            :class:`sgad_jax.io.rundir.Run`), or a tuple ``(frames, poses, intr)``: ``frames`` a
            mapping from run index to :class:`PixelGaussians` (or a sequence, index = position),
            ``poses`` (f, 4, 4) camera-to-world poses indexed by run index, ``intr`` the intrinsics.
        voxel: cell side in metres; 0 keeps every Gaussian; None: the run's ``export.voxel``
            times its ``data.downscale`` (a folder), 0 for a tuple.
        min_opacity: Gaussians less opaque than this are dropped.

    Returns:
        the Gaussians (frames in run order, pixels row-major within a frame when nothing is merged)
        and the counts.

    Raises:
        DatasetError: a file of the run is missing or unreadable, or a frame has no pose.
    """
    if isinstance(source, (str, os.PathLike)):
        from sgad_jax.io.rundir import Run

        run = Run(source)
        poses = run.mapping_poses()
        intr = run.intrinsics
        indices = run.gaussian_frames()
        if not indices:
            raise DatasetError(f"{run.root / 'gaussians'}: no frame_XXXXXX.npz files (a --track-only run, or one stopped before a frame was mapped, has no map)")
        load = run.gaussians
        if voxel is None:
            voxel = run.export_config.voxel * run.data_config.downscale
        where = str(run.root / "trajectory.txt")
    else:
        frames, poses, intr = source
        indices = sorted(frames) if isinstance(frames, dict) else list(range(len(frames)))
        load = frames.__getitem__
        voxel = 0.0 if voxel is None else voxel
        where = "poses"
    if voxel < 0:
        raise ValueError(f"voxel must be >= 0 (0: keep all), got {voxel}")
    poses = np.asarray(poses, np.float64)
    logit_min = math.log(min_opacity / (1.0 - min_opacity)) if min_opacity > 0 else -np.inf
    total = visible = 0
    parts, depths, pending = [], [], 0
    kept, kept_z = _concat([]), np.zeros((0,), np.float32)
    for i in indices:
        if i >= len(poses) or not np.isfinite(poses[i]).all():
            raise DatasetError(f"{where}: frame {i} has stored Gaussians but no finite pose")
        g, z = frame_to_world(load(i), poses[i], intr)
        total += len(g)
        ok = (g.opacity_logit >= logit_min) & (z > NEAR) & np.isfinite(g.xyz).all(1)
        g, z = g.take(ok), z[ok]
        visible += len(g)
        parts.append(g)
        depths.append(z)
        pending += len(g)
        if voxel > 0 and pending >= _MERGE_CHUNK:
            kept, kept_z = _best_per_voxel(_concat([kept, *parts]), np.concatenate([kept_z, *depths]), voxel)
            parts, depths, pending = [], [], 0
    if voxel > 0:
        kept, _ = _best_per_voxel(_concat([kept, *parts]), np.concatenate([kept_z, *depths]), voxel)
    else:
        kept = _concat(parts)
    return kept, MergeInfo(frames=len(indices), total=total, visible=visible, kept=len(kept), voxel=float(voxel))


def write_3dgs_ply(path, gaussians: WorldGaussians, *, comments: tuple[str, ...] = ()) -> pathlib.Path:
    """Write Gaussians as a 3DGS ``.ply`` (layout in the module docstring), atomically.

    Args:
        path: output file; missing parent folders are created.
        gaussians: the Gaussians.
        comments: lines for the header's ``comment`` records.

    Returns:
        the path written.
    """
    path = pathlib.Path(path)
    g = gaussians
    n = len(g)
    data = np.zeros(n, dtype=[(name, "<f4") for name in PROPERTIES])
    for k, name in enumerate("xyz"):
        data[name] = g.xyz[:, k]
    for k in range(3):
        data[f"f_dc_{k}"] = (g.rgb[:, k] - 0.5) / SH_C0
        data[f"scale_{k}"] = g.log_sigma
    data["opacity"] = g.opacity_logit
    data["rot_0"] = 1.0
    element = plyfile.PlyElement.describe(data, "vertex")
    ply = plyfile.PlyData([element], text=False, byte_order="<", comments=list(comments))
    atomic_write(path, ply.write)
    return path


def read_3dgs_ply(path) -> WorldGaussians:
    """Read a 3DGS ``.ply`` back (colour from the DC term only; ``log_sigma`` is the mean of the
    three log scales, exact for the isotropic Gaussians :func:`write_3dgs_ply` writes).

    Raises:
        DatasetError: the file is missing, not a PLY, or lacks a 3DGS property.
    """
    path = pathlib.Path(path)
    try:
        ply = plyfile.PlyData.read(str(path))
        v = ply["vertex"].data
    except FileNotFoundError:
        raise DatasetError(f"{path}: not found") from None
    except (OSError, ValueError, KeyError, plyfile.PlyParseError) as err:
        raise DatasetError(f"{path}: not a readable PLY with a vertex element ({err})") from None
    missing = [p for p in PROPERTIES[:13] if p not in v.dtype.names]
    if missing:
        raise DatasetError(f"{path}: not a 3D Gaussian Splatting file (no {', '.join(missing)})")
    col = lambda name: np.asarray(v[name], np.float32)  # noqa: E731
    return WorldGaussians(
        xyz=np.stack([col("x"), col("y"), col("z")], -1),
        rgb=np.stack([0.5 + SH_C0 * col(f"f_dc_{k}") for k in range(3)], -1).astype(np.float32),
        opacity_logit=col("opacity"),
        log_sigma=np.mean([col(f"scale_{k}") for k in range(3)], axis=0).astype(np.float32),
    )


def export_run(run_dir, voxel: float | None = None, out=None) -> tuple[pathlib.Path, MergeInfo]:
    """Merge a finished run's Gaussians and write them to ``out`` (default ``RUN_DIR/gaussians.ply``).

    ``voxel``: metres, as in :func:`merged_gaussians` (None: the run's ``export.voxel`` times its
    downscale).
    """
    gaussians, info = merged_gaussians(run_dir, voxel)
    out = pathlib.Path(run_dir) / "gaussians.ply" if out is None else pathlib.Path(out)
    note = f"sgad_jax export: {info.kept} of {info.total} Gaussians of {info.frames} frames, voxel {info.voxel:g} m"
    return write_3dgs_ply(out, gaussians, comments=(note,)), info


# --- triangle meshes (mesh.ply) ---


def write_mesh_ply(path, vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray | None = None) -> None:
    """Binary little-endian PLY: vertices ``x y z`` (float32) and ``red green blue`` (uchar) when
    given, faces ``vertex_indices`` (list of int32); written atomically."""
    from plyfile import PlyData, PlyElement

    vertices = np.asarray(vertices, np.float32).reshape(-1, 3)
    fields = [("x", "f4"), ("y", "f4"), ("z", "f4")]
    if colours is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    v = np.empty(len(vertices), fields)
    v["x"], v["y"], v["z"] = vertices.T
    if colours is not None:
        c = np.asarray(colours, np.uint8).reshape(-1, 3)
        v["red"], v["green"], v["blue"] = c.T
    f = np.empty(len(faces), [("vertex_indices", "i4", (3,))])
    f["vertex_indices"] = np.asarray(faces, np.int32).reshape(-1, 3)
    ply = PlyData([PlyElement.describe(v, "vertex"), PlyElement.describe(f, "face")], text=False, byte_order="<")
    atomic_write(path, ply.write)


def read_mesh_ply(path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``(vertices (m, 3) float64, faces (k, 3) int64, colours (m, 3) uint8 or None)`` of a PLY
    triangle mesh (polygons with more than three corners are fanned into triangles)."""
    from plyfile import PlyData

    path = pathlib.Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: mesh file not found")
    try:
        ply = PlyData.read(str(path))
        v = ply["vertex"].data
        vertices = np.stack([v["x"], v["y"], v["z"]], -1).astype(np.float64)
        names = v.dtype.names
        colours = np.stack([v["red"], v["green"], v["blue"]], -1).astype(np.uint8) if {"red", "green", "blue"} <= set(names) else None
        faces = []
        if "face" in ply:
            data = ply["face"].data
            key = "vertex_indices" if "vertex_indices" in data.dtype.names else "vertex_index"
            polys = data[key]
            try:
                arr = np.stack(polys).astype(np.int64) if len(polys) else np.zeros((0, 3), np.int64)
            except ValueError:  # mixed polygon sizes
                arr = None
            if arr is not None and arr.ndim == 2 and arr.shape[1] == 3:
                faces = arr
            else:
                faces = np.array([(p[0], p[k], p[k + 1]) for p in polys for k in range(1, len(p) - 1)], np.int64).reshape(-1, 3)
        faces = np.asarray(faces, np.int64).reshape(-1, 3)
    except DatasetError:
        raise
    except Exception as e:  # plyfile raises several kinds on malformed files
        raise DatasetError(f"{path}: not a readable PLY triangle mesh ({e.__class__.__name__}: {e})") from None
    if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise DatasetError(f"{path}: face indices outside the {len(vertices)} vertices")
    return vertices, faces, colours
