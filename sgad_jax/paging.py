"""Any scene size with a fixed-size geometry set: T on the device holds the surface around the
camera; the rest waits in host memory and comes back when the camera does.

The device set has a fixed capacity and its keys cover a cube of ``SIDE`` voxels around its
origin (:mod:`sgad_jax.geometry`). After a tracked frame the host checks two things: the set is
fuller than ``track.page_high`` of its capacity, or the camera has moved more than a quarter of
the cube's side from the origin. Either way it *pages*: the device entries and the host archive
are pooled (one entry per voxel; the device's wins), the set is rebuilt around the camera (origin
on the same voxel grid) with the entries nearest a point :data:`AHEAD` in front of the camera (what
the next frames see), up to ``track.page_low`` of its capacity and inside the new cube, and the
rest goes to the archive. Nothing is lost, device memory
stays fixed, and every page is recorded (:attr:`Pager.events`).
"""

from __future__ import annotations

import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

from sgad_jax import geometry
from sgad_jax.config import ConfigError, TrackConfig
from sgad_jax.types import GeometrySet, PointCloud, empty_geometry

#: Entries are inserted into a rebuilt set this many at a time (one compiled program).
REBUILD_CHUNK = 8192
#: Metres in front of the camera of the point whose nearest entries stay on the device: about an
#: indoor view's median depth, so little of what is kept lies behind the camera.
AHEAD = 2.0


@functools.partial(jax.jit, donate_argnums=0)
def _insert(geom: GeometrySet, cloud: PointCloud) -> GeometrySet:
    return geometry.insert(geom, cloud)[0]


def entries(geom: GeometrySet) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The active entries' points (3, c), covariances (6, c) and normals (3, c) on the host."""
    c = int(geom.count)
    return np.asarray(geom.points[:, :c]), np.asarray(geom.covs[:, :c]), np.asarray(geom.normals[:, :c])


def rebuild(like: GeometrySet, origin: np.ndarray, points: np.ndarray, covs: np.ndarray, normals: np.ndarray) -> GeometrySet:
    """A set of ``like``'s capacity and voxel size around ``origin`` holding the given entries
    (one per voxel, in order: an entry whose voxel is taken is dropped)."""
    geom = empty_geometry(like.capacity, like.voxel_size, origin)
    for s in range(0, points.shape[1], REBUILD_CHUNK):
        part = [a[:, s : s + REBUILD_CHUNK] for a in (points, covs, normals)]
        n = part[0].shape[1]
        pad = lambda a: np.pad(a, ((0, 0), (0, REBUILD_CHUNK - n)))  # noqa: E731
        cloud = PointCloud(points=pad(part[0]), covs=pad(part[1]), normals=pad(part[2]), valid=np.arange(REBUILD_CHUNK) < n)
        geom = _insert(geom, jax.tree.map(jnp.asarray, cloud))
    return geom


class Pager:
    """The host side of T: the archive of entries paged out, and the paging policy (module doc)."""

    def __init__(self, cfg: TrackConfig, origin):
        if not 0.0 < cfg.page_low < cfg.page_high <= 1.0:
            raise ConfigError(f"track.page_low and track.page_high must satisfy 0 < low < high <= 1, got {cfg.page_low}, {cfg.page_high}")
        self.cfg = cfg
        self.grid = np.asarray(origin, np.float64)  # the voxel grid's anchor: every origin is on it
        self.archive = np.zeros((12, 0), np.float32)  # rows: point (3), covariance (6), normal (3)
        self.events: list[dict] = []

    def _reach(self) -> float:
        return 0.25 * geometry.SIDE * self.cfg.voxel_size

    def due(self, geom: GeometrySet, position: np.ndarray) -> bool:
        """Whether the set must be paged with the camera at ``position`` (world, metres)."""
        full = int(geom.count) > self.cfg.page_high * geom.capacity
        return full or np.abs(position - np.asarray(geom.origin)).max() > self._reach()

    def page(self, geom: GeometrySet, pose: np.ndarray, frame: int) -> GeometrySet:
        """The set rebuilt around the camera at ``pose`` (camera-to-world 4x4; see the module
        doc); records the event."""
        position = pose[:3, 3]
        centre_w = position + AHEAD * pose[:3, 2]
        t0 = time.perf_counter()
        v = self.cfg.voxel_size
        pool = np.concatenate([np.concatenate(entries(geom)), self.archive], axis=1)
        keys = np.floor((pool[:3] - self.grid[:, None]) / v).astype(np.int64)
        _, first = np.unique(keys, axis=1, return_index=True)  # one entry per voxel, the device's first
        pool, keys = pool[:, np.sort(first)], keys[:, np.sort(first)]
        origin = self.grid + v * np.round((position - self.grid) / v)
        centre = np.round((origin - self.grid) / v).astype(np.int64)
        inside = (np.abs(keys - centre[:, None]) < geometry.HALF - 1).all(axis=0)
        dist = np.linalg.norm(pool[:3] - centre_w[:, None], axis=0)
        order = np.argsort(np.where(inside, dist, np.inf), kind="stable")
        n_keep = min(int(inside.sum()), int(self.cfg.page_low * geom.capacity))
        keep, rest = order[:n_keep], order[n_keep:]
        new = rebuild(geom, origin, pool[:3, keep], pool[3:9, keep], pool[9:, keep])
        self.archive = pool[:, rest]
        self.events.append({"frame": frame, "device": int(new.count), "host": int(self.archive.shape[1]), "reach_m": float(dist[keep].max()) if n_keep else 0.0, "seconds": time.perf_counter() - t0})
        return new

    @property
    def host_entries(self) -> int:
        return int(self.archive.shape[1])
