"""Pytrees of sgad_jax: intrinsics, RGB-D frames, pixel-aligned Gaussians, the geometry set.

All are frozen dataclasses registered with ``jax.tree_util.register_dataclass``. Fields that fix
shapes (image size, capacity) are static metadata; everything else is an array. Build them with the
``make_*`` / ``empty_*`` factories, update them with ``dataclasses.replace``.

Shape vocabulary: ``h w`` image, ``n`` Gaussians, ``m`` points, ``f`` frames, ``*b`` optional batch.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

_static = functools.partial(dataclasses.field, metadata=dict(static=True))


def _pytree(cls):
    return jax.tree_util.register_dataclass(dataclasses.dataclass(frozen=True)(cls))


@_pytree
class Intrinsics:
    """Pinhole intrinsics (OpenCV axes: x right, y down, z forward). Distortion is ignored."""

    fx: Float[Array, "*b"]
    fy: Float[Array, "*b"]
    cx: Float[Array, "*b"]
    cy: Float[Array, "*b"]
    width: int = _static()
    height: int = _static()

    def scaled(self, factor: int) -> "Intrinsics":
        """Intrinsics of the image downscaled by an integer ``factor`` (pixel ``j`` of the small image
        covers pixels ``[f j, f j + f)``; its centre is at ``f j + (f - 1) / 2``)."""
        f = float(factor)
        return Intrinsics(
            fx=self.fx / f,
            fy=self.fy / f,
            cx=(self.cx - (f - 1.0) / 2.0) / f,
            cy=(self.cy - (f - 1.0) / 2.0) / f,
            width=self.width // factor,
            height=self.height // factor,
        )

    def as_tuple(self) -> tuple[float, float, float, float]:
        return float(self.fx), float(self.fy), float(self.cx), float(self.cy)


def make_intrinsics(fx, fy, cx, cy, width: int, height: int) -> Intrinsics:
    f32 = lambda v: np.float32(v)  # noqa: E731
    if width <= 0 or height <= 0 or not (fx > 0 and fy > 0 and np.isfinite([fx, fy, cx, cy]).all()):
        raise ValueError(f"invalid intrinsics fx={fx} fy={fy} cx={cx} cy={cy} width={width} height={height}")
    return Intrinsics(f32(fx), f32(fy), f32(cx), f32(cy), int(width), int(height))


@_pytree
class Frame:
    """One RGB-D frame on device.

    ``depth`` is the measured depth (0 where missing) used by tracking; ``depth_filled`` has the
    holes inpainted (Navier-Stokes) for the appearance branch.
    """

    rgb: Float[Array, "*b h w 3"]
    depth: Float[Array, "*b h w"]
    depth_filled: Float[Array, "*b h w"]
    valid: Bool[Array, "*b h w"]


def make_frame(rgb, depth, depth_filled=None) -> Frame:
    """Frame from host arrays: ``rgb`` uint8 or float in [0, 1], ``depth`` in metres (0 = missing)."""
    rgb = np.asarray(rgb)
    if rgb.dtype == np.uint8:
        rgb = rgb.astype(np.float32) / 255.0
    depth = np.asarray(depth, np.float32)
    valid = np.isfinite(depth) & (depth > 0)
    depth = np.where(valid, depth, 0.0).astype(np.float32)
    filled = depth if depth_filled is None else np.asarray(depth_filled, np.float32)
    return Frame(
        rgb=jnp.asarray(rgb, jnp.float32),
        depth=jnp.asarray(depth),
        depth_filled=jnp.asarray(filled),
        valid=jnp.asarray(valid),
    )


def host_frame(sample, *, fill: bool = True) -> Frame:
    """The frame of a sample (``rgb``, ``depth``, ``depth_filled``) as host (numpy) arrays; without
    ``fill`` its ``depth_filled`` is the measured depth (a view that is scored or fitted to, not
    mapped, needs no inpainting)."""
    return jax.tree.map(np.asarray, make_frame(sample.rgb, sample.depth, sample.depth_filled if fill else None))


@_pytree
class PixelGaussians:
    """The pixel-aligned Gaussians of one frame (SGAD-SLAM, Sec. 3): one per pixel, on its ray.

    Gaussian (v, u) sits at z-depth ``|depth + offset|`` on the ray of pixel (v, u) of the frame it was
    made from, in that frame's camera. It is isotropic. The learnable fields are stored the way they
    are optimised: ``rgb`` linear colour, ``log_radius`` (radius in metres = ``exp``), ``opacity_logit``
    (opacity = ``sigmoid``), ``offset`` (metres along the ray, in z). ``depth`` is the (inpainted)
    measured depth, a constant.
    """

    rgb: Float[Array, "*b h w 3"]
    log_radius: Float[Array, "*b h w"]
    opacity_logit: Float[Array, "*b h w"]
    offset: Float[Array, "*b h w"]
    depth: Float[Array, "*b h w"]

    @property
    def radius(self) -> Float[Array, "*b h w"]:
        # Scaled with the Gaussian's depth: moved along its ray it keeps its footprint in its own
        # view, so an offset is purely geometric and cannot stand in for the radius there.
        scale = jnp.where(self.depth > 0, self.z / jnp.where(self.depth > 0, self.depth, 1.0), 1.0)
        return jnp.exp(self.log_radius) * scale

    @property
    def opacity(self) -> Float[Array, "*b h w"]:
        return jax.nn.sigmoid(self.opacity_logit)

    @property
    def z(self) -> Float[Array, "*b h w"]:
        """Depth of each Gaussian's centre in its own camera."""
        return jnp.abs(self.depth + self.offset)


@_pytree
class GeometrySet:
    """The global set T of geometry Gaussians, one per occupied voxel, fixed capacity.

    The data (point, covariance, normal) of the ``count`` active entries is stored in insertion
    order, slots ``[0, count)``. A hash table says where each voxel's data is:
    ``bucket_keys[i, j]`` is a packed voxel key (``KEY_EMPTY`` if free; buckets fill from
    ``j = 0``) and ``bucket_slots[i, j]`` its data slot; a power of two of home buckets and one
    more, which takes the last home bucket's spill (see :mod:`sgad_jax.geometry`).
    Covariances are scale-normalised (middle eigenvalue 1) and stored as their six unique entries
    ``xx yy zz xy xz yz``.
    """

    bucket_keys: Int[Array, "nb bucket"]
    bucket_slots: Int[Array, "nb bucket"]
    points: Float[Array, "3 n"]
    covs: Float[Array, "6 n"]
    normals: Float[Array, "3 n"]
    weights: Float[Array, " n"]  # observations averaged into each point (sgad_jax.geometry.fuse)
    count: Int[Array, ""]
    origin: Float[Array, "3"]
    voxel_size: float = _static()

    @property
    def capacity(self) -> int:
        return self.points.shape[-1]

    @property
    def active(self) -> Bool[Array, " n"]:
        return jnp.arange(self.capacity) < self.count


KEY_EMPTY = np.int32(2**31 - 1)
#: Entries per hash bucket of a geometry set; a key is stored in its home bucket or the next one.
BUCKET = 4


def empty_geometry(capacity: int, voxel_size: float, origin=(0.0, 0.0, 0.0)) -> GeometrySet:
    """An empty geometry set; voxel keys cover 1024 voxels per axis centred on ``origin``."""
    if capacity <= 0 or voxel_size <= 0:
        raise ValueError(f"geometry set needs capacity > 0 and voxel_size > 0, got {capacity}, {voxel_size}")
    buckets = 1 << max(1, (2 * capacity - 1).bit_length())
    return GeometrySet(
        # At least 8 table entries per data slot, a power of two of home buckets, and one bucket
        # more for the last home bucket's spill.
        bucket_keys=jnp.full((buckets + 1, BUCKET), KEY_EMPTY, jnp.int32),
        bucket_slots=jnp.zeros((buckets + 1, BUCKET), jnp.int32),
        points=jnp.zeros((3, capacity), jnp.float32),
        covs=jnp.zeros((6, capacity), jnp.float32),
        normals=jnp.zeros((3, capacity), jnp.float32),
        weights=jnp.zeros((capacity,), jnp.float32),
        count=jnp.zeros((), jnp.int32),
        origin=jnp.asarray(origin, jnp.float32),
        voxel_size=float(voxel_size),
    )


@_pytree
class PointCloud:
    """Geometry Gaussians of one frame (strided pixels), masked; component-major like GeometrySet."""

    points: Float[Array, "3 m"]
    covs: Float[Array, "6 m"]
    normals: Float[Array, "3 m"]
    valid: Bool[Array, " m"]


#: Bits of ``TrackInfo.failure``: why a tracked pose was judged unhealthy (see ``sgad_jax.slam``).
FAIL_NONFINITE, FAIL_INLIERS, FAIL_JUMP, FAIL_DEGENERATE = 1, 2, 4, 8


@_pytree
class TrackInfo:
    """Diagnostics of one tracking step.

    ``conditioning`` is the smallest over the largest eigenvalue of the last Gauss-Newton Hessian.
    ``failure`` is a bitmask of ``FAIL_*`` (0: healthy) judged by :func:`sgad_jax.slam.track_step` on
    its first solve, whose figures (inliers, conditioning, ``jump``: translation in metres and
    rotation in radians from the guess) this info keeps, with ``inlier_floor``, the inlier share
    it had to reach; ``recovered`` says whether the
    relocalisation that follows a failure gave a healthy pose. :func:`sgad_jax.track.solve` alone
    leaves ``failure`` 0 and ``jump`` 0.
    """

    iterations: Int[Array, "*b"]
    converged: Bool[Array, "*b"]
    cost: Float[Array, "*b"]
    inliers: Int[Array, "*b"]
    points: Int[Array, "*b"]
    conditioning: Float[Array, "*b"]
    failure: Int[Array, "*b"]
    recovered: Bool[Array, "*b"]
    jump: Float[Array, "*b 2"]
    inlier_floor: Float[Array, "*b"]


@_pytree
class InsertInfo:
    """Diagnostics of one insertion into the geometry set."""

    inserted: Int[Array, ""]
    overflow: Int[Array, ""]
    out_of_range: Int[Array, ""]


__all__ = [
    "Intrinsics",
    "make_intrinsics",
    "Frame",
    "make_frame",
    "PixelGaussians",
    "GeometrySet",
    "empty_geometry",
    "KEY_EMPTY",
    "PointCloud",
    "TrackInfo",
    "FAIL_NONFINITE",
    "FAIL_INLIERS",
    "FAIL_JUMP",
    "FAIL_DEGENERATE",
    "InsertInfo",
]
