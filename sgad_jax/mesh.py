"""A triangle mesh from depth and colour images: TSDF fusion (jitted JAX), then marching cubes.

Fusion is the projective truncated signed distance of KinectFusion (Newcombe et al. 2011), as the
SLAM papers mesh their maps (1 cm voxels, 4 cm truncation at full resolution; both scale with
``data.downscale``):

* The grid is dense over the bounding box of every frame's observed points (valid depth, back-projected
  along the frame's pose) plus the truncation distance and one voxel. A grid over ``mesh.max_voxels``
  is coarsened (the voxel and the truncation grow together) and :class:`GridPlan` says so.
* A voxel's centre ``p_w`` goes into each frame's camera; where it projects inside the image onto a
  pixel with valid depth ``D`` (nearest pixel), its signed distance along the optical axis is
  ``sdf = D - z``. Voxels with ``sdf > -trunc`` (not hidden more than the truncation behind the
  surface) take ``min(sdf / trunc, 1)`` and the pixel's colour into a running average of weight 1 per
  observation: plain averaging, or capped at ``mesh.max_weight`` when that is positive.
* The surface is the zero level set (``skimage.measure.marching_cubes``) on the voxels observed at
  least once, eroded by one voxel (3x3x3): scikit-image tests the mask at one corner of each cube, so without
  the erosion cubes that reach into unobserved voxels (initialised as free space) make false walls.
  Vertex colours are trilinear in the colour grid, over observed voxels only.

Integration is one jitted call per frame with fixed shapes: the grid is swept in slabs along x
(``lax.map``) so the temporary arrays stay small whatever the grid size.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import sys

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from sgad_jax.config import ConfigError, MeshConfig
from sgad_jax.types import Intrinsics

#: bytes a voxel costs: TSDF, weight and RGB as float32
VOXEL_BYTES = 20
#: voxels swept at once by one integration step (slabs of the grid along x)
_SWEEP_VOXELS = 1 << 20


@functools.partial(jax.tree_util.register_dataclass, data_fields=["tsdf", "weight", "rgb", "origin"], meta_fields=["voxel", "trunc", "max_weight"])
@dataclasses.dataclass(frozen=True)
class TSDFVolume:
    """Dense TSDF grid; voxel ``(i, j, k)`` has its centre at ``origin + voxel * (i, j, k)`` (world, m)."""

    tsdf: Float[Array, "x y z"]  # truncated signed distance over the truncation, in [-1, 1]
    weight: Float[Array, "x y z"]  # observations so far (0: never observed)
    rgb: Float[Array, "x y z 3"]  # average colour, linear [0, 1]
    origin: Float[Array, "3"]
    voxel: float
    trunc: float
    max_weight: float = 0.0


@dataclasses.dataclass(frozen=True)
class GridPlan:
    """Where and how fine the grid is; ``coarsened`` when the budget forced a larger voxel."""

    origin: np.ndarray  # (3,) centre of voxel (0, 0, 0)
    shape: tuple[int, int, int]
    voxel: float
    trunc: float
    coarsened: bool
    requested_voxel: float

    @property
    def voxels(self) -> int:
        return int(np.prod(self.shape))


def check_config(cfg: MeshConfig) -> None:
    """Raise a :class:`ConfigError` when ``mesh.max_voxels`` is below the coarsest grid (truncation
    plus one voxel on each side), which sent :func:`plan_grid`'s coarsening to infinity. (The
    config itself refuses values out of range.)"""
    smallest = (math.floor(2 + 2 * cfg.trunc / cfg.voxel) + 2) ** 3
    if cfg.max_voxels < smallest:
        raise ConfigError(f"mesh.max_voxels: must be >= {smallest} (the coarsest grid for mesh.trunc / mesh.voxel = {cfg.trunc / cfg.voxel:g}), got {cfg.max_voxels}")


def scaled_params(cfg: MeshConfig, downscale: int = 1) -> tuple[float, float]:
    """``(voxel, trunc)`` in metres for images downscaled by ``downscale``."""
    return cfg.voxel * downscale, cfg.trunc * downscale


@jax.jit
def observed_bounds(depth: Float[Array, "h w"], T_wc: Float[Array, "4 4"], intr: Intrinsics, min_depth: float, max_depth: float) -> tuple[Float[Array, "3"], Float[Array, "3"]]:
    """World-space ``(lo, hi)`` of a frame's valid depth points (``+inf, -inf`` when none is valid)."""
    h, w = depth.shape
    v, u = jnp.meshgrid(jnp.arange(h, dtype=jnp.float32), jnp.arange(w, dtype=jnp.float32), indexing="ij")
    ok = (depth > min_depth) & ((max_depth <= 0) | (depth < max_depth))
    p_c = jnp.stack([(u - intr.cx) / intr.fx * depth, (v - intr.cy) / intr.fy * depth, depth], -1)
    p_w = p_c @ T_wc[:3, :3].T + T_wc[:3, 3]
    lo = jnp.where(ok[..., None], p_w, jnp.inf).min((0, 1))
    hi = jnp.where(ok[..., None], p_w, -jnp.inf).max((0, 1))
    return lo, hi


def plan_grid(lo: np.ndarray, hi: np.ndarray, voxel: float, trunc: float, max_voxels: int) -> GridPlan:
    """The grid over ``[lo, hi]`` widened by the truncation and one voxel; coarsened to fit ``max_voxels``.

    Raises:
        ValueError: when the box is empty or not finite (no valid depth anywhere).
    """
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    if not (np.isfinite(lo).all() and np.isfinite(hi).all() and (hi >= lo).all()):
        raise ValueError("no valid depth in any frame: nothing to fuse")
    requested, scale = voxel, 1.0
    while True:
        v, t = voxel * scale, trunc * scale
        margin = t + v
        shape = tuple(int(n) for n in np.ceil((hi - lo + 2 * margin) / v).astype(int) + 1)
        if math.prod(shape) <= max_voxels:
            break
        # the next scale that fits, assuming the count goes with scale^-3 (then checked again)
        scale *= max(1.01, (math.prod(shape) / max_voxels) ** (1 / 3))
    return GridPlan(origin=lo - margin, shape=shape, voxel=v, trunc=t, coarsened=scale > 1.0, requested_voxel=requested)


def empty_volume(plan: GridPlan, max_weight: float = 0.0) -> TSDFVolume:
    """A grid of unobserved voxels (weight 0; TSDF 1, i.e. free space, which the mask hides)."""
    return TSDFVolume(
        tsdf=jnp.ones(plan.shape, jnp.float32),
        weight=jnp.zeros(plan.shape, jnp.float32),
        rgb=jnp.zeros(plan.shape + (3,), jnp.float32),
        origin=jnp.asarray(plan.origin, jnp.float32),
        voxel=float(plan.voxel),
        trunc=float(plan.trunc),
        max_weight=float(max_weight),
    )


def _update_voxel(trunc: float, max_weight: float, p_w, tsdf, weight, rgb, depth, image, T_wc, intr: Intrinsics, min_depth, max_depth):
    """One voxel's new ``(tsdf, weight, rgb)`` after one frame."""
    h, w = depth.shape
    p_c = T_wc[:3, :3].T @ (p_w - T_wc[:3, 3])
    z = p_c[2]
    safe = jnp.where(z > 1e-6, z, 1.0)
    u = jnp.round(intr.fx * p_c[0] / safe + intr.cx).astype(jnp.int32)
    v = jnp.round(intr.fy * p_c[1] / safe + intr.cy).astype(jnp.int32)
    inside = (z > 1e-6) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    uc, vc = jnp.clip(u, 0, w - 1), jnp.clip(v, 0, h - 1)
    d = depth[vc, uc]
    valid = inside & (d > min_depth) & ((max_depth <= 0) | (d < max_depth))
    sdf = d - z
    update = valid & (sdf > -trunc)
    obs = jnp.minimum(sdf / trunc, 1.0)
    new_w = weight + 1.0
    new_tsdf = (tsdf * weight + obs) / new_w
    new_rgb = (rgb * weight + image[vc, uc]) / new_w
    if max_weight > 0:
        new_w = jnp.minimum(new_w, max_weight)
    return jnp.where(update, new_tsdf, tsdf), jnp.where(update, new_w, weight), jnp.where(update, new_rgb, rgb)


@functools.partial(jax.jit, donate_argnums=0)
def integrate(
    vol: TSDFVolume,
    depth: Float[Array, "h w"],
    rgb: Float[Array, "h w 3"],
    T_wc: Float[Array, "4 4"],
    intr: Intrinsics,
    min_depth: float = 0.0,
    max_depth: float = 0.0,
) -> TSDFVolume:
    """Fuse one frame (depth in metres, 0 where missing; colour in [0, 1]; camera-to-world pose)."""
    nx, ny, nz = vol.tsdf.shape
    j, k = jnp.meshgrid(jnp.arange(ny, dtype=jnp.float32), jnp.arange(nz, dtype=jnp.float32), indexing="ij")
    one = functools.partial(_update_voxel, vol.trunc, vol.max_weight)
    axes = (0, 0, 0, 0) + (None,) * 6
    update = jax.vmap(jax.vmap(one, in_axes=axes), in_axes=axes)

    def slab(args):
        i, tsdf, weight, colour = args
        p_w = vol.origin + vol.voxel * jnp.stack([jnp.full_like(j, i), j, k], -1)
        return update(p_w, tsdf, weight, colour, depth, rgb, T_wc, intr, min_depth, max_depth)

    batch = max(1, min(nx, _SWEEP_VOXELS // max(1, ny * nz)))
    tsdf, weight, colour = jax.lax.map(slab, (jnp.arange(nx, dtype=jnp.float32), vol.tsdf, vol.weight, vol.rgb), batch_size=batch)
    return dataclasses.replace(vol, tsdf=tsdf, weight=weight, rgb=colour)


def extract_mesh(vol: TSDFVolume) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Marching cubes of the zero level on the observed voxels eroded by one (host code).

    Returns:
        vertices (m, 3) float32 world metres, faces (k, 3) int32, colours (m, 3) uint8; empty arrays
        when there is no surface.
    """
    from scipy import ndimage
    from skimage import measure

    tsdf, weight, rgb = (np.array(a) for a in (vol.tsdf, vol.weight, vol.rgb))  # writable copies for skimage
    # a full 3x3x3 erosion: whichever corner of a cube the mask is tested at, all eight are observed
    mask = ndimage.binary_erosion(weight > 0, structure=np.ones((3, 3, 3), bool), border_value=0)
    empty = (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros((0, 3), np.uint8))
    if not mask.any() or tsdf[mask].min() > 0 or tsdf[mask].max() < 0:
        return empty
    verts, faces, _, _ = measure.marching_cubes(tsdf, level=0.0, mask=mask, allow_degenerate=False)
    if len(faces) == 0:
        return empty
    # colour: trilinear over observed voxels only (unobserved ones hold no colour)
    observed = (weight > 0).astype(np.float32)
    coords = verts.T
    norm = ndimage.map_coordinates(observed, coords, order=1, mode="nearest")
    colours = np.stack(
        [ndimage.map_coordinates(rgb[..., c] * observed, coords, order=1, mode="nearest") for c in range(3)], -1
    ) / np.maximum(norm, 1e-6)[:, None]
    vertices = (np.asarray(vol.origin, np.float64) + vol.voxel * verts).astype(np.float32)
    return vertices, faces.astype(np.int32), np.clip(colours * 255.0 + 0.5, 0, 255).astype(np.uint8)


def fuse(frames, poses: np.ndarray, intr: Intrinsics, cfg: MeshConfig, downscale: int = 1, *, log=None):
    """TSDF fusion of a sequence and its mesh.

    Args:
        frames: a re-iterable sequence of ``(rgb (h, w, 3) float [0, 1], depth (h, w) metres)``; it is
            read twice (bounds, then fusion).
        poses: (f, 4, 4) camera-to-world.
        intr: the images' intrinsics.
        cfg: voxel, truncation (at full resolution), weight cap, grid budget, depth range.
        downscale: the images' downscale factor (scales voxel and truncation).
        log: called with a line of text when the grid is coarsened (default: stderr).

    Returns:
        ``(vertices, faces, colours, plan)`` (see :func:`extract_mesh`, :class:`GridPlan`).
    """
    poses = np.asarray(poses, np.float32)
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for (_, depth), T in zip(frames, poses):
        if not np.isfinite(T).all():
            continue
        a, b = observed_bounds(jnp.asarray(depth, jnp.float32), T, intr, cfg.min_depth, cfg.max_depth)
        lo, hi = np.minimum(lo, np.asarray(a)), np.maximum(hi, np.asarray(b))
    voxel, trunc = scaled_params(cfg, downscale)
    plan = plan_grid(lo, hi, voxel, trunc, cfg.max_voxels)
    if plan.coarsened:
        (log or (lambda s: print(s, file=sys.stderr)))(
            f"mesh: a {voxel * 100:.3g} cm grid over {np.round(hi - lo, 2).tolist()} m would exceed mesh.max_voxels="
            f"{cfg.max_voxels}; coarsened to {plan.voxel * 100:.3g} cm voxels, {plan.trunc * 100:.3g} cm truncation"
        )
    vol = empty_volume(plan, cfg.max_weight)
    for (rgb, depth), T in zip(frames, poses):
        if np.isfinite(T).all():
            vol = integrate(vol, jnp.asarray(depth, jnp.float32), jnp.asarray(rgb, jnp.float32), T, intr, cfg.min_depth, cfg.max_depth)
    vertices, faces, colours = extract_mesh(vol)
    return vertices, faces, colours, plan


def mesh_run(run_dir, cfg: MeshConfig | None = None, downscale: int | None = None, *, log=None) -> dict:
    """Fuse a finished run's renders (``renders/rgb_*.png``, ``renders/depth_*.png``) along its
    ``trajectory.txt`` with its ``cameras.json`` intrinsics into ``RUN_DIR/mesh.ply``.

    Args:
        run_dir: the run folder.
        cfg: mesh settings; default: the run's config's ``mesh`` (from ``metrics.json``).
        downscale: the run's ``data.downscale``; default: from ``metrics.json`` (else 1).
        log: called with lines of text worth telling the user (default: stderr).

    Returns:
        a summary: path, vertex and face counts, voxel and truncation used, frames fused.

    Raises:
        DatasetError: a missing or unreadable file, named.
        ConfigError: a mesh setting fusion cannot use (:func:`check_config`).
    """
    from sgad_jax.io.base import DatasetError
    from sgad_jax.io.ply import write_mesh_ply
    from sgad_jax.io.rundir import Run, read_render

    run = Run(run_dir)
    saved = run.config if (run.root / "metrics.json").is_file() else None
    cfg = cfg if cfg is not None else (saved.mesh if saved is not None else MeshConfig())
    downscale = downscale if downscale is not None else (saved.data.downscale if saved is not None else 1)
    check_config(cfg)  # before the renders are read: a bad setting is the first thing to fix
    indices = run.render_frames(with_depth=True)
    if not indices:
        raise DatasetError(f"{run.root / 'renders'}: no rendered colour and depth (rgb_XXXXXX.png + depth_XXXXXX.png); run with --save-renders")
    poses = run.mapping_poses()  # the poses the renders were made at
    if indices[-1] >= len(poses):
        raise DatasetError(f"{run.root / 'renders'}: render {indices[-1]} has no pose in trajectory.txt ({len(poses)} lines)")
    intr = run.intrinsics
    rgb, _ = read_render(run.root, indices[0])
    if rgb.shape[:2] != (intr.height, intr.width):
        raise DatasetError(f"{run.root / 'renders'}: renders are {rgb.shape[1]}x{rgb.shape[0]}, the cameras {intr.width}x{intr.height}")
    renders = _Renders(run.root, indices)
    try:
        vertices, faces, colours, plan = fuse(renders, poses[indices], intr, cfg, downscale, log=log)
    except ValueError as e:
        raise DatasetError(f"{run.root / 'renders'}: {e}") from None
    path = run.root / "mesh.ply"
    write_mesh_ply(path, vertices, faces, colours)
    return {
        "mesh": str(path), "vertices": int(len(vertices)), "faces": int(len(faces)), "frames": len(indices),
        "voxel_m": plan.voxel, "trunc_m": plan.trunc, "grid": list(plan.shape), "coarsened": plan.coarsened,
    }


class _Renders:
    """A run's renders as a re-iterable sequence of ``(rgb, depth)``, read lazily on each pass."""

    def __init__(self, root, indices):
        self.root, self.indices = root, list(indices)

    def __len__(self):
        return len(self.indices)

    def __iter__(self):
        from sgad_jax.io.rundir import read_render

        for i in self.indices:
            yield read_render(self.root, i)
