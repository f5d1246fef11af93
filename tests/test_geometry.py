"""The geometry set T: insertion invariants and candidate lookup against a brute-force oracle."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sgad_jax import geometry
from sgad_jax.types import KEY_EMPTY, PointCloud, empty_geometry

VOXEL = 0.05


def _cloud(points, valid=None):
    m = points.shape[1]
    return PointCloud(
        points=jnp.asarray(points, jnp.float32),
        covs=jnp.tile(jnp.array([1.0, 1.0, 1e-3, 0, 0, 0])[:, None], (1, m)),
        normals=jnp.tile(jnp.array([0.0, 0.0, 1.0])[:, None], (1, m)),
        valid=jnp.ones(m, bool) if valid is None else jnp.asarray(valid),
    )


def _voxels(points):
    return {tuple(v) for v in np.floor(points / VOXEL).T.astype(int)}


def _check_invariants(g):
    """Every stored key once, at its home bucket or the next, buckets filled from the left; the
    slots are exactly [0, count), and each key is the voxel of its slot's point."""
    n = int(g.count)
    keys, slots = np.asarray(g.bucket_keys), np.asarray(g.bucket_slots)
    used = keys != KEY_EMPTY
    assert used.sum() == n and len(set(keys[used].tolist())) == n
    assert np.all(np.diff(used.astype(int), axis=1) <= 0)  # no free entry before a used one
    assert sorted(slots[used].tolist()) == list(range(n))
    home = np.asarray(geometry._home(g, jnp.asarray(keys[used])))
    bucket = np.nonzero(used)[0]
    assert np.all((bucket == home) | (bucket == home + 1))
    k, _ = geometry.pack(geometry.voxel_coords(g, g.points[:, slots[used]]))
    np.testing.assert_array_equal(np.asarray(k), keys[used])


@pytest.mark.slow
def test_insert_keeps_one_gaussian_per_voxel():
    rng = np.random.default_rng(0)
    g = empty_geometry(4096, VOXEL)
    insert = jax.jit(geometry.insert)
    seen = set()
    for step in range(4):
        pts = rng.uniform(-0.4, 0.4, (3, 500)).astype(np.float32)
        valid = rng.uniform(size=500) > 0.1
        g, info = insert(g, _cloud(pts, valid))
        new = _voxels(pts[:, valid]) - seen
        seen |= new
        assert int(info.inserted) == len(new)
        assert int(g.count) == len(seen)
        _check_invariants(g)
    # The first point to reach a voxel keeps it: re-inserting stored points changes nothing.
    before = np.asarray(g.points).copy()
    g2, info = insert(g, _cloud(np.asarray(g.points[:, :500])))
    assert int(info.inserted) == 0
    np.testing.assert_array_equal(np.asarray(g2.points), before)


def test_insert_in_chunks_keeps_the_first_point_of_each_voxel():
    # More new points than one chunk takes, many voxels reached again in a later chunk: each voxel
    # must still hold the first valid point (lowest index) to reach it, as a plain loop finds it.
    rng = np.random.default_rng(1)
    m = 3 * geometry.CHUNK + 100
    pts = rng.uniform(-0.3, 0.3, (3, m)).astype(np.float32)  # ~1700 voxels for ~3200 points
    valid = rng.uniform(size=m) > 0.2
    g, info = jax.jit(geometry.insert)(empty_geometry(8192, VOXEL), _cloud(pts, valid))
    first = {}
    for i in np.nonzero(valid)[0]:
        first.setdefault(tuple(np.floor(pts[:, i] / VOXEL).astype(int)), i)
    assert int(info.inserted) == int(g.count) == len(first) and int(info.overflow) == 0
    _check_invariants(g)
    stored = np.asarray(g.points[:, : int(g.count)])
    want = pts[:, sorted(first.values())]
    np.testing.assert_array_equal(stored[:, np.lexsort(stored)], want[:, np.lexsort(want)])


@pytest.mark.slow
def test_insert_reports_overflow_and_range():
    g = empty_geometry(64, VOXEL)
    pts = np.stack([np.arange(100) * VOXEL + VOXEL / 2, np.zeros(100), np.zeros(100)]).astype(np.float32)
    pts[0, -1] = 1e3  # far outside the 1024-voxel cube
    g, info = geometry.insert(g, _cloud(pts))
    assert int(g.count) == 64 and int(info.inserted) == 64
    assert int(info.overflow) == 99 - 64
    assert int(info.out_of_range) == 1
    _check_invariants(g)


@pytest.mark.slow
def test_candidates_find_every_entry_within_half_a_voxel():
    rng = np.random.default_rng(1)
    g = empty_geometry(8192, VOXEL)
    g, _ = geometry.insert(g, _cloud(rng.uniform(-0.5, 0.5, (3, 3000)).astype(np.float32)))
    n = int(g.count)
    stored = np.asarray(g.points)[:, :n]
    q = rng.uniform(-0.45, 0.45, (3, 400)).astype(np.float32)
    slots, hit = geometry.candidates(g, jnp.asarray(q))
    slots, hit = np.asarray(slots), np.asarray(hit)
    for i in range(q.shape[1]):
        found = set(slots[hit[:, i], i])
        near = set(np.nonzero(np.all(np.abs(stored - q[:, i : i + 1]) < VOXEL / 2, axis=0))[0])
        assert near <= found, i
        # and nothing beyond the 2x2x2 block (at most 1.5 voxels away per axis)
        assert all(np.all(np.abs(stored[:, s] - q[:, i]) < 1.5 * VOXEL + 1e-6) for s in found)
        assert len(found) == hit[:, i].sum()  # no duplicates


@pytest.mark.slow
def test_occupied():
    g = empty_geometry(256, VOXEL)
    g, _ = geometry.insert(g, _cloud(np.array([[0.01], [0.01], [0.01]], np.float32)))
    probe = jnp.array([[0.04, 0.06, -0.01], [0.02, 0.02, 0.02], [0.03, 0.03, 0.03]])
    np.testing.assert_array_equal(np.asarray(geometry.occupied(g, probe)), [True, False, False])


@pytest.mark.slow
def test_full_buckets_spill_then_overflow():
    """A table of 2 buckets (8 entries: one home bucket and the one for its spill) for 20 new
    voxels: keys go to their home bucket, then the next one; what fits nowhere is dropped and
    counted, the data of the rest is intact and found."""
    g = empty_geometry(64, VOXEL)
    g = dataclasses.replace(g, bucket_keys=g.bucket_keys[:2], bucket_slots=g.bucket_slots[:2])
    pts = np.stack([np.arange(20) * VOXEL + VOXEL / 2, np.zeros(20), np.zeros(20)]).astype(np.float32)
    g, info = geometry.insert(g, _cloud(pts))
    assert int(info.inserted) == 8 and int(info.overflow) == 12 and int(g.count) == 8
    _check_invariants(g)
    found = np.asarray(geometry.occupied(g, jnp.asarray(pts)))
    assert found.sum() == 8
    # The kept points are the ones whose voxels are found, stored at their slots.
    kept = {tuple(np.round(p, 6)) for p in np.asarray(g.points[:, :8]).T}
    assert kept == {tuple(np.round(p, 6)) for p in pts[:, found].T}
    # Inserting the same points again changes nothing.
    g2, info = geometry.insert(g, _cloud(pts[:, found]))
    assert int(info.inserted) == 0
    np.testing.assert_array_equal(np.asarray(g2.bucket_keys), np.asarray(g.bucket_keys))


def test_last_bucket_spills_into_the_extra_bucket():
    """Six voxels whose home is the last home bucket: four stay there, two go to the bucket past
    it (none to bucket 0), and a lookup finds all six at their slots (the lookup reads a key's
    two buckets as one block)."""
    g = empty_geometry(64, VOXEL)
    nb = g.bucket_keys.shape[0] - 1  # home buckets
    xs = (np.arange(4000) % 1000 - 500 + 0.5) * VOXEL
    pts = np.stack([xs, np.zeros_like(xs), np.full_like(xs, (np.arange(4000) // 1000 - 2 + 0.5) * VOXEL)]).astype(np.float32)
    key, _ = geometry.pack(geometry.voxel_coords(g, jnp.asarray(pts)))
    last = np.nonzero(np.asarray(geometry._home(g, key)) == nb - 1)[0][:6]
    assert len(last) == 6
    g, info = geometry.insert(g, _cloud(pts[:, last]))
    assert int(info.inserted) == 6 and int(info.overflow) == 0
    _check_invariants(g)
    used = np.asarray(g.bucket_keys) != KEY_EMPTY
    assert used[nb - 1].sum() == 4 and used[nb].sum() == 2 and used.sum() == 6
    slot, hit = geometry._lookup(g, key[last])
    assert np.asarray(hit).all()
    np.testing.assert_allclose(np.asarray(g.points[:, np.asarray(slot)]), pts[:, last])


def test_fuse_is_the_running_mean_of_each_voxels_observations():
    """Against a host computation voxel by voxel: after an insertion and two fused frames, every
    entry is the mean of the points that fell in its voxel while it had fewer than ``cap``, with
    their count as its weight; points in empty voxels change nothing (insert takes them)."""
    rng = np.random.default_rng(1)
    v = 0.05
    def cloud(p, valid=None):
        m = p.shape[1]
        return PointCloud(points=jnp.asarray(p, jnp.float32), covs=jnp.tile(jnp.asarray([1.0, 1, 1, 0, 0, 0])[:, None], (1, m)),
                          normals=jnp.zeros((3, m)), valid=jnp.ones(m, bool) if valid is None else jnp.asarray(valid))
    first = rng.uniform(0.0, 1.0, (3, 300))
    geom, _ = jax.jit(geometry.insert)(empty_geometry(4096, v), cloud(first))
    frames = [first[:, rng.permutation(300)[:200]] + rng.normal(0, 0.01, (3, 200)) for _ in range(2)]
    valid = rng.uniform(size=200) < 0.8
    cap = 2
    fuse = jax.jit(geometry.fuse, static_argnums=2)
    g = fuse(geom, cloud(frames[0], valid), cap)
    g = fuse(g, cloud(frames[1]), cap)
    # the oracle: every observation grouped by voxel key
    key = lambda p: [tuple(k) for k in np.floor(p.T / v).astype(int)]  # noqa: E731
    c = int(geom.count)
    entries = np.asarray(geom.points[:, :c])
    obs = {k: [p] for k, p in zip(key(entries), entries.T)}
    for pts in (frames[0][:, valid], frames[1]):
        before = {k: len(v_) for k, v_ in obs.items()}  # a frame's points in a voxel go in together
        for p in pts.T:
            k = key(p[:, None])[0]
            if k in obs and before[k] < cap:
                obs[k].append(p)
    want = np.stack([np.mean(obs[k], axis=0) for k in key(entries)], axis=1)
    np.testing.assert_allclose(np.asarray(g.points[:, :c]), want, atol=1e-5)
    np.testing.assert_array_equal(np.asarray(g.weights[:c]), [len(obs[k]) for k in key(entries)])
    assert int(g.count) == c and (np.asarray(g.weights[c:]) == 0).all()


def test_points_keyed_by_other_points():
    """``keyed_by``: insert and fuse place each point of the cloud in the voxel of its key point, not
    its own (T keeps plane-projected points in the voxels of the measured ones): against a host
    grouping by the keys' voxels."""
    rng = np.random.default_rng(2)
    keys = [rng.uniform(0.0, 1.0, (3, 300)).astype(np.float32)]
    keys.append(keys[0][:, rng.permutation(300)[:200]] + rng.normal(0, 0.01, (3, 200)).astype(np.float32))
    shift = np.float32([[0.03], [-0.02], [0.04]])  # most stored points lie in another voxel than their key
    geom, info = jax.jit(geometry.insert)(empty_geometry(4096, VOXEL), _cloud(keys[0] + shift), jnp.asarray(keys[0]))
    g = jax.jit(geometry.fuse, static_argnums=2)(geom, _cloud(keys[1] + shift), 2, jnp.asarray(keys[1]))
    obs = {}
    for i, k in enumerate(np.floor(keys[0].T / VOXEL).astype(int)):
        obs.setdefault(tuple(k), [keys[0][:, i] + shift[:, 0]])  # the first point of a voxel owns it
    assert int(info.inserted) == len(obs) == int(geom.count)
    for i, k in enumerate(np.floor(keys[1].T / VOXEL).astype(int)):  # each entry has one observation: all go in
        if tuple(k) in obs:
            obs[tuple(k)].append(keys[1][:, i] + shift[:, 0])
    voxels = np.array(list(obs), np.float32).T
    slot, hit = geometry._lookup(g, geometry.pack(geometry.voxel_coords(g, jnp.asarray((voxels + 0.5) * VOXEL)))[0])
    assert np.asarray(hit).all()
    np.testing.assert_allclose(np.asarray(g.points[:, np.asarray(slot)]), np.stack([np.mean(o, 0) for o in obs.values()], 1), atol=1e-5)
