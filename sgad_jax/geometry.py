"""The global geometry set T: one geometry Gaussian per occupied voxel, fixed capacity.

Layout (see :class:`sgad_jax.types.GeometrySet`): the data (point, covariance, normal) of the
``count`` active entries is stored in insertion order; a hash table of voxel keys says where each
entry's data is. The table has at least 8 entries per data slot, in buckets of :data:`BUCKET`; a
key lives in its home bucket (a multiplicative hash of the key) or the next one, so a lookup is
one gather of two adjacent buckets and a comparison, and an insertion touches only the buckets of
the new keys; one bucket past the home buckets takes the last one's spill. Unlike binary searches
in a sorted key array, a lookup is one gather, and an insertion never rebuilds an index of the
whole capacity.
A key whose two buckets are full is dropped and counted as overflow (with the table at most 1/8
full, two buckets of 4 hold 8 keys where 1 is expected; every key reported in ``InsertInfo``).

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

from sgad_jax.types import BUCKET, KEY_EMPTY, GeometrySet, InsertInfo, PointCloud

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


#: Fibonacci hashing: a key times 2^32 / golden ratio (mod 2^32), a bijection of 32-bit words whose
#: top bits are the home bucket; its inverse multiplier recovers the key.
_GOLDEN, _GOLDEN_INV = 2654435769, pow(2654435769, -1, 1 << 32)
#: The hash of no key below 2^30 (keys pack 3 x 10 bits), so it can mark "no new key".
_NO_HASH = 0xFFFFFFFF


def _bucket(geom: GeometrySet, h: Int[Array, "*m"]) -> Int[Array, "*m"]:
    """The home bucket of each hash: its top bits."""
    bits = (geom.bucket_keys.shape[0] - 1).bit_length() - 1  # a power of two of home buckets, and one more
    return (h >> (32 - bits)).astype(jnp.int32)


def _hash(key: Int[Array, "*m"]) -> Int[Array, "*m"]:
    return key.astype(jnp.uint32) * jnp.uint32(_GOLDEN)


def _home(geom: GeometrySet, key: Int[Array, "*m"]) -> Int[Array, "*m"]:
    """Home bucket of each key."""
    return _bucket(geom, _hash(key))


def _lookup(geom: GeometrySet, key: Int[Array, "*m"]) -> tuple[Int[Array, "*m"], Bool[Array, "*m"]]:
    """Data slot of each key (0 where absent) and whether it is in T."""
    # A key's two buckets, b and b + 1, lie side by side (the last home bucket's next one is the
    # extra bucket past them): one gather of 2 * BUCKET entries, cheaper than two bucket gathers
    # joined, and no pair ever wraps to bucket 0.
    start = _home(geom, key) * BUCKET
    dims = jax.lax.GatherDimensionNumbers(offset_dims=(key.ndim,), collapsed_slice_dims=(), start_index_map=(0,))
    pair = jax.lax.gather(geom.bucket_keys.reshape(-1), start[..., None], dims, (2 * BUCKET,), mode="clip")
    eq = (pair == key[..., None]) & (key != KEY_EMPTY)[..., None]
    at = jnp.max(jnp.where(eq, jnp.arange(2 * BUCKET, dtype=jnp.int32), 0), axis=-1)  # a key is stored at most once
    hit = jnp.any(eq, axis=-1)
    return jnp.where(hit, geom.bucket_slots.reshape(-1)[start + at], 0), hit


def candidates(geom: GeometrySet, p_w: Float[Array, "3 m"]) -> tuple[Int[Array, "8 m"], Bool[Array, "8 m"]]:
    """Data slots of the entries of the 2x2x2 voxel block nearest each point (so every entry within
    half a voxel per axis), and whether each exists; x-neighbours second (rows 4-7)."""
    c = voxel_coords(geom, p_w, shift=0.5)
    key = jnp.stack([pack([c[0] + dx, c[1] + dy, c[2] + dz])[0] for dx in (0, 1) for dy, dz in ((0, 0), (1, 0), (0, 1), (1, 1))])
    return _lookup(geom, key)


def occupied(geom: GeometrySet, p_w: Float[Array, "3 m"]) -> Bool[Array, " m"]:
    """Whether each point's voxel already holds a geometry Gaussian (the overlap test)."""
    key, _ = pack(voxel_coords(geom, p_w))
    return _lookup(geom, key)[1]


#: An insertion works on the frame's new points (those in empty voxels) in chunks of this many:
#: after the first frame, a tracked frame brings a few hundred new points of its ~10k, so one
#: chunk usually takes them all, and its sort and searches cost a fraction of a whole frame's.
CHUNK = 1024


def insert(geom: GeometrySet, cloud_w: PointCloud, keyed_by: Float[Array, "3 m"] | None = None) -> tuple[GeometrySet, InsertInfo]:
    """Add the points of ``cloud_w`` (world frame) whose voxels are empty; one per voxel.
    ``keyed_by``: the world points whose voxels decide that (default: ``cloud_w``'s own).

    Fixed shapes throughout, and nothing proportional to the capacity. The points in empty voxels
    are gathered in index order and inserted a chunk at a time (a ``while_loop``; none when there
    are none), each chunk checked against the set as the previous chunks left it. Within a chunk:
    the new key hashes are sorted (one 32-bit word, so grouped by home bucket; a sort carrying the
    point indices along is much slower on XLA:CPU), the lowest point index of each voxel is found by
    a scatter-min (so over all chunks, the first point to reach a voxel owns it), each distinct new
    key is ranked within its home bucket and placed in the bucket's next free entries, or in the
    next bucket's when the home bucket is full; its data is appended at slots
    ``[count, count + inserted)``. When capacity runs out, or both buckets of a key are full, the
    remaining points are dropped and counted in ``InsertInfo.overflow`` (once per chunk that meets
    the key).
    """
    key, inside = pack(voxel_coords(geom, cloud_w.points if keyed_by is None else keyed_by))
    todo = cloud_w.valid & inside & ~_lookup(geom, key)[1]
    m = key.shape[0]
    chunk = min(m, CHUNK)
    n = jnp.sum(todo)
    order = jnp.nonzero(todo, size=m + chunk, fill_value=m)[0]  # indices of the new points, then m

    def step(state):
        geom, i, inserted, overflow = state
        index = jax.lax.dynamic_slice(order, (i,), (chunk,))
        k = jnp.where(index < m, key[jnp.minimum(index, m - 1)], KEY_EMPTY)
        new = (index < m) & ~_lookup(geom, k)[1]  # earlier chunks may have filled the voxel
        geom, n_new, distinct = _place(geom, k, new, cloud_w, jnp.minimum(index, m - 1))
        return geom, i + chunk, inserted + n_new, overflow + distinct - n_new

    zero = jnp.zeros((), jnp.int32)
    geom, _, inserted, overflow = jax.lax.while_loop(lambda s: s[1] < n, step, (geom, zero, zero, zero))
    info = InsertInfo(inserted=inserted, overflow=overflow, out_of_range=jnp.sum(cloud_w.valid & ~inside).astype(jnp.int32))
    return geom, info


def _place(geom: GeometrySet, key, new, cloud_w: PointCloud, index) -> tuple[GeometrySet, Int[Array, ""], Int[Array, ""]]:
    """Insert the points ``index`` of ``cloud_w`` (ascending) whose ``key`` is ``new``; returns
    the set, the number inserted and the number of distinct new keys."""
    m = key.shape[0]
    nb = geom.bucket_keys.shape[0]  # the home buckets and the extra one
    end = nb * BUCKET  # an entry index past the table: scatters there are dropped
    h = jnp.where(new, _hash(key), jnp.uint32(_NO_HASH))
    hs = jnp.sort(h)  # points that add nothing sort last
    b = _bucket(geom, hs)
    skey = (hs * jnp.uint32(_GOLDEN_INV)).astype(jnp.int32)
    first = (hs != jnp.uint32(_NO_HASH)) & jnp.concatenate([jnp.ones((1,), bool), hs[1:] != hs[:-1]])
    at = jnp.where(new, jnp.searchsorted(hs, h, side="left", method="scan"), m)  # the first position of its key
    src = jnp.full((m,), m - 1, jnp.int32).at[at].min(jnp.arange(m, dtype=jnp.int32), mode="drop")
    before = jnp.cumsum(first) - first  # distinct new keys before this position
    take = first & (before < geom.capacity - geom.count)
    # Rank among the new keys of its home bucket: distinct keys since the bucket's first position.
    rank = before - before[jnp.searchsorted(b, b, side="left", method="scan")]

    def filled(table, bucket):
        return jnp.sum(table[bucket] != KEY_EMPTY, axis=-1)

    # Home buckets first, then what did not fit goes to the next bucket, after that one's own keys.
    free = BUCKET - filled(geom.bucket_keys, b)
    home = take & (rank < free)
    entry = jnp.where(home, b * BUCKET + BUCKET - free + rank, end)
    table = geom.bucket_keys.reshape(-1).at[entry].set(skey, mode="drop").reshape(nb, BUCKET)
    b2 = b + 1
    pos = filled(table, b2) + rank - free
    spill = take & ~home & (pos < BUCKET)
    entry = jnp.where(spill, b2 * BUCKET + pos, entry)
    table = table.reshape(-1).at[jnp.where(spill, entry, end)].set(skey, mode="drop").reshape(nb, BUCKET)
    placed = home | spill
    slot = geom.count + jnp.cumsum(placed) - placed
    slots = geom.bucket_slots.reshape(-1).at[entry].set(slot, mode="drop").reshape(nb, BUCKET)
    n_new = jnp.sum(placed).astype(jnp.int32)

    def append(old, vals):
        return old.at[:, jnp.where(placed, slot, geom.capacity)].set(vals[:, index[src]], mode="drop")

    out = dataclasses.replace(
        geom,
        bucket_keys=table,
        bucket_slots=slots,
        points=append(geom.points, cloud_w.points),
        covs=append(geom.covs, cloud_w.covs),
        normals=append(geom.normals, cloud_w.normals),
        weights=geom.weights.at[jnp.where(placed, slot, geom.capacity)].set(1.0, mode="drop"),
        count=geom.count + n_new,
    )
    return out, n_new, jnp.sum(first).astype(jnp.int32)


def fuse(geom: GeometrySet, cloud_w: PointCloud, cap: int, keyed_by: Float[Array, "3 m"] | None = None) -> GeometrySet:
    """Average the points of ``cloud_w`` (world frame) whose voxels T already holds into those
    entries' positions, a running mean of the voxel's first ``cap`` observations: a noisy first
    observation does not fix the surface for good, and a settled entry does not follow the drift
    of later frames. Shapes and normals stay the first ones'. ``keyed_by`` as in :func:`insert`.

    Sparse: each point adds ``(p - old) / (w + n)`` to its entry (``w`` the entry's weight, ``n``
    the points of this frame in the voxel), which sums to the new mean; only the count is dense.
    """
    key, inside = pack(voxel_coords(geom, cloud_w.points if keyed_by is None else keyed_by))
    slot, hit = _lookup(geom, key)
    upd = cloud_w.valid & inside & hit & (geom.weights[slot] < cap)
    target = jnp.where(upd, slot, geom.capacity)
    n = jnp.zeros_like(geom.weights).at[target].add(1.0, mode="drop")[slot]
    step = (cloud_w.points - geom.points[:, slot]) / (geom.weights[slot] + n)
    points = geom.points.at[:, target].add(jnp.where(upd, step, 0.0), mode="drop")
    return dataclasses.replace(geom, points=points, weights=geom.weights.at[target].add(1.0, mode="drop"))
