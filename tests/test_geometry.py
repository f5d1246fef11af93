"""The geometry set T: insertion invariants and candidate lookup against a brute-force oracle."""

import jax
import jax.numpy as jnp
import numpy as np

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
    n = int(g.count)
    keys = np.asarray(g.keys)
    assert np.all(np.diff(keys[:n]) > 0) and np.all(keys[n:] == KEY_EMPTY)
    slots = np.asarray(g.slots[:n])
    assert sorted(slots) == list(range(n))
    k, _ = geometry.pack(geometry.voxel_coords(g, g.points[:, slots]))
    np.testing.assert_array_equal(np.asarray(k), keys[:n])


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


def test_insert_reports_overflow_and_range():
    g = empty_geometry(64, VOXEL)
    pts = np.stack([np.arange(100) * VOXEL + VOXEL / 2, np.zeros(100), np.zeros(100)]).astype(np.float32)
    pts[0, -1] = 1e3  # far outside the 1024-voxel cube
    g, info = geometry.insert(g, _cloud(pts))
    assert int(g.count) == 64 and int(info.inserted) == 64
    assert int(info.overflow) == 99 - 64
    assert int(info.out_of_range) == 1
    _check_invariants(g)


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


def test_occupied():
    g = empty_geometry(256, VOXEL)
    g, _ = geometry.insert(g, _cloud(np.array([[0.01], [0.01], [0.01]], np.float32)))
    probe = jnp.array([[0.04, 0.06, -0.01], [0.02, 0.02, 0.02], [0.03, 0.03, 0.03]])
    np.testing.assert_array_equal(np.asarray(geometry.occupied(g, probe)), [True, False, False])


def test_running_count_matches_numpy_cumsum():
    """The matrix-product running count equals numpy's cumulative sum, for lengths below, at and
    above one block, not multiples of it, and up to 2^18 (three levels of blocks)."""
    rng = np.random.default_rng(7)
    for n in (1, 5, 64, 65, 4096, 5000, 1 << 18):
        flags = rng.random(n) < rng.uniform(0.01, 0.99)
        got = np.asarray(jax.jit(geometry.running_count)(jnp.asarray(flags)))
        np.testing.assert_array_equal(got, np.cumsum(flags))
    dense = np.ones(1 << 18, bool)  # the largest counts: exact in float32 below 2^24
    np.testing.assert_array_equal(np.asarray(geometry.running_count(jnp.asarray(dense))), np.arange(1, (1 << 18) + 1))
