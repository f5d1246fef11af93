"""The global geometry set T: one geometry Gaussian per occupied voxel, fixed capacity.

Layout (see :class:`sgad_jax.types.GeometrySet`): ``keys[:count]`` are the packed voxel keys of the
active entries in increasing order, ``slots`` points to each entry's data (stored in insertion
order). Lookups are ``searchsorted`` on ``keys``; insertion appends the data and merges the sorted
new keys (and their slots) in with one scatter.
DESIGN.md measured this at 0.4 ms per 12k queries against 1M entries on XLA:CPU, where a k-d tree
is not an option and a fixed-size spatial hash overflowed.

A point *overlaps* T when its voxel is already occupied; SGAD-SLAM adds a tracked frame's
non-overlapping points to T (Sec. 3.3), and here the first point to reach a voxel keeps it.

Keys pack 10 bits per axis (x lowest), so T covers 1024 voxels per axis centred on ``origin``;
points outside are counted in ``InsertInfo.out_of_range`` and not inserted.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from sgad_jax.types import KEY_EMPTY, GeometrySet, InsertInfo, PointCloud

BITS = 10
SIDE = 1 << BITS
HALF = SIDE // 2


def voxel_coords(geom: GeometrySet, p_w: Float[Array, "3 *m"], shift: float = 0.0) -> list[Int[Array, "*m"]]:
    """Integer voxel coordinates, in ``[0, SIDE)`` when inside the covered cube (check with :func:`pack`)."""
    out = []
    for a in range(3):
        c = jnp.floor((p_w[a] - geom.origin[a]) / geom.voxel_size - shift)
        c = jnp.clip(c, -2 * SIDE, 2 * SIDE)  # keeps the int cast defined for far or non-finite points
        out.append(jnp.where(jnp.isfinite(c), c, -SIDE).astype(jnp.int32) + HALF)
    return out


def pack(c: list[Int[Array, "*m"]]) -> tuple[Int[Array, "*m"], Bool[Array, "*m"]]:
    """Packed key (x lowest) and whether the voxel is inside the covered cube."""
    inside = (c[0] >= 0) & (c[0] < SIDE) & (c[1] >= 0) & (c[1] < SIDE) & (c[2] >= 0) & (c[2] < SIDE)
    key = c[0] + SIDE * (c[1] + SIDE * c[2])
    return jnp.where(inside, key, KEY_EMPTY), inside


def _search(keys: Int[Array, " n"], query: Int[Array, "*m"]) -> Int[Array, "*m"]:
    # The barrier keeps XLA from fusing the key computation into the binary-search loop, which
    # then recomputes it at every step (several times slower on XLA:CPU).
    return jnp.searchsorted(keys, jax.lax.optimization_barrier(query), method="scan_unrolled")


def _find(keys: Int[Array, " n"], query: Int[Array, "*m"]) -> tuple[Int[Array, "*m"], Bool[Array, "*m"]]:
    pos = jnp.minimum(_search(keys, query), keys.shape[0] - 1)
    return pos, (keys[pos] == query) & (query != KEY_EMPTY)


def candidates(geom: GeometrySet, p_w: Float[Array, "3 m"]) -> tuple[Int[Array, "8 m"], Bool[Array, "8 m"]]:
    """Data slots of the entries of the 2x2x2 voxel block nearest each point (so every entry within
    half a voxel per axis), and whether each exists.

    x-neighbours have consecutive keys, so the block needs 4 binary searches instead of 8: the entry
    for key ``k + 1`` sits at the position found for ``k`` or just after it.
    """
    c = voxel_coords(geom, p_w, shift=0.5)
    rows = [pack([c[0], c[1] + dy, c[2] + dz]) for dy, dz in ((0, 0), (1, 0), (0, 1), (1, 1))]
    k0 = jnp.stack([k for k, _ in rows])  # (4, m): the four x-rows of the block
    in1 = jnp.stack([inside for _, inside in rows]) & (c[0] + 1 < SIDE)
    pos, f0 = _find(geom.keys, k0)
    nxt = jnp.minimum(pos + 1, geom.capacity - 1)
    k1 = jnp.where(in1, k0 + 1, KEY_EMPTY)
    at_pos = geom.keys[pos] == k1
    at_nxt = geom.keys[nxt] == k1
    idx = jnp.concatenate([pos, jnp.where(at_pos, pos, nxt)])
    hit = jnp.concatenate([f0, in1 & (at_pos | at_nxt)])
    return geom.slots[idx], hit


def occupied(geom: GeometrySet, p_w: Float[Array, "3 m"]) -> Bool[Array, " m"]:
    """Whether each point's voxel already holds a geometry Gaussian (the overlap test)."""
    key, _ = pack(voxel_coords(geom, p_w))
    return _find(geom.keys, key)[1]


def insert(geom: GeometrySet, cloud_w: PointCloud) -> tuple[GeometrySet, InsertInfo]:
    """Add the points of ``cloud_w`` (world frame) whose voxels are empty; one per voxel.

    Fixed shapes throughout: the new keys are sorted (m log m), then merged with the existing sorted
    keys by computing every entry's final position with ``searchsorted`` and one scatter per array.
    When capacity runs out the remaining points are dropped and counted in ``InsertInfo.overflow``.
    """
    key, inside = pack(voxel_coords(geom, cloud_w.points))
    _, exists = _find(geom.keys, key)
    new = cloud_w.valid & inside & ~exists
    key = jnp.where(new, key, KEY_EMPTY)
    m = key.shape[0]
    order = jnp.argsort(key, stable=True)
    skey = key[order]
    first = jnp.concatenate([jnp.ones((1,), bool), skey[1:] != skey[:-1]]) & (skey != KEY_EMPTY)
    rank = jnp.cumsum(first) - 1
    take = first & (rank < geom.capacity - geom.count)
    n_new = jnp.sum(take).astype(jnp.int32)
    # Compact the accepted new keys to the front, still sorted.
    dest = jnp.where(take, rank, m)
    nkeys = jnp.full((m,), KEY_EMPTY).at[dest].set(skey, mode="drop")
    nsrc = jnp.zeros((m,), jnp.int32).at[dest].set(order, mode="drop")
    # Final positions: an old entry moves up by the number of new keys below it, a new entry by the
    # number of old keys below it. Data goes to slots [count, count + n_new).
    # (# new keys below old key i) = (# new keys whose insertion point is <= i): a histogram of the
    # insertion points and a cumulative sum, cheaper than searching every old key among the new.
    fresh = jnp.arange(m) < n_new
    below = _search(geom.keys, nkeys)
    shift = jnp.cumsum(jnp.zeros(geom.capacity, jnp.int32).at[jnp.where(fresh, below, geom.capacity)].add(1, mode="drop"))
    old_pos = jnp.where(geom.active, jnp.arange(geom.capacity) + shift, geom.capacity)
    new_pos = jnp.where(fresh, jnp.arange(m) + below, geom.capacity)
    new_slot = jnp.where(fresh, geom.count + jnp.arange(m), geom.capacity)

    def merge(old, new, fill):
        out = jnp.full(old.shape, fill, old.dtype).at[old_pos].set(old, mode="drop")
        return out.at[new_pos].set(new, mode="drop")

    def append(old, new):
        return old.at[:, new_slot].set(new[:, nsrc], mode="drop")

    out = dataclasses.replace(
        geom,
        keys=merge(geom.keys, nkeys, KEY_EMPTY),
        slots=merge(geom.slots, geom.count + jnp.arange(m, dtype=jnp.int32), 0),
        points=append(geom.points, cloud_w.points),
        covs=append(geom.covs, cloud_w.covs),
        normals=append(geom.normals, cloud_w.normals),
        count=geom.count + n_new,
    )
    info = InsertInfo(
        inserted=n_new,
        overflow=(jnp.sum(first) - n_new).astype(jnp.int32),
        out_of_range=jnp.sum(cloud_w.valid & ~inside).astype(jnp.int32),
    )
    return out, info
