"""The fast renderer against the dense reference renderer (forward and vector-Jacobian products)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sgad_jax import lie, splat, splat_ref
from sgad_jax.types import Intrinsics, PixelGaussians

H, W = 10, 14


@pytest.fixture(autouse=True)
def _x64():
    with jax.enable_x64(True):
        yield


def _intr() -> Intrinsics:
    return Intrinsics(fx=jnp.float64(13.0), fy=jnp.float64(14.0), cx=jnp.float64(6.6), cy=jnp.float64(4.7), width=W, height=H)


def _scene(frames: int, seed: int) -> PixelGaussians:
    """Random Gaussians with depths spread over 1-3 m, so that frames overlap at different depths."""
    rng = np.random.default_rng(seed)
    f = lambda *s: jnp.asarray(rng.uniform(*s, size=(frames, H, W)))  # noqa: E731
    return PixelGaussians(
        rgb=jnp.asarray(rng.uniform(0, 1, (frames, H, W, 3))),
        log_radius=jnp.log(f(0.1, 0.5)),
        opacity_logit=f(-2.0, 3.0),
        offset=f(-0.1, 0.1),
        depth=f(1.0, 3.0),
    )


def _poses(n: int, seed: int, scale: float = 0.05) -> lie.SE3:
    return lie.exp(jnp.asarray(np.random.default_rng(seed).normal(0, scale, (n, 6))))


def _pose(seed: int, scale: float = 0.05) -> lie.SE3:
    return lie.exp(jnp.asarray(np.random.default_rng(seed).normal(0, scale, 6)))


def _close(a, b, tol=1e-9):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), atol=tol * max(1.0, float(jnp.abs(y).max())))


def _cotangent(out: splat.Render, seed: int) -> splat.Render:
    rng = np.random.default_rng(seed)
    return jax.tree.map(lambda x: jnp.asarray(rng.normal(size=x.shape)), out)


def _vjp(f, args, seed):
    """``f(*args)`` and its vector-Jacobian product for a random cotangent, each one compiled
    program (run op by op, the renderers compile hundreds of small ones)."""
    out = jax.jit(f)(*args)
    ct = _cotangent(out, seed)
    return out, jax.jit(lambda *a: jax.vjp(f, *a)[1](ct))(*args)


def _max_per_slot(g, poses, view) -> int:
    attrs = splat.project_frames(g, poses, view, _intr())
    u, v = (np.round(np.asarray(attrs[i])).astype(int) for i in (0, 1))
    counts = np.zeros((H + 2, W + 2), int)
    keep = (u >= -1) & (u <= W) & (v >= -1) & (v <= H)
    np.add.at(counts, (v[keep] + 1, u[keep] + 1), 1)
    return int(counts.max())


@pytest.mark.slow
def test_any_view_matches_reference():
    g, poses, view = _scene(2, 0), _poses(2, 1), _pose(2)
    layers = _max_per_slot(g, poses, view)  # no Gaussian is dropped by binning: an exact comparison
    assert 2 <= layers <= 6  # overlapping Gaussians at different depths
    fast = splat.render(g, poses, view, _intr(), layers=layers)
    ref = splat_ref.render(g, poses, view, _intr())
    assert float(ref.alpha.max()) > 0.5  # the scene is visible, with overlap
    _close(fast, ref)
    # The offsets (+-10 cm) reorder Gaussians: the rule (order of the measured depths) matters here.
    in_z_order = splat_ref.render(_at_offset_depth(g), poses, view, _intr())
    assert float(jnp.abs(fast.rgb - in_z_order.rgb).max()) > 1e-3


def _at_offset_depth(g):
    """The same Gaussians (positions and radii) with their offsets folded into the measured depth."""
    return dataclasses.replace(g, depth=g.z, offset=0.0 * g.offset, log_radius=jnp.log(g.radius))


@pytest.mark.parametrize("window", [3, 5])
def test_own_view_matches_reference(window):
    """At its own pose a frame is composited in the order of its measured depths; offsets large
    enough to reverse that order between neighbours show the rule is the reference's."""
    g, pose = _scene(1, 3), _pose(4)
    g = dataclasses.replace(g, offset=5.0 * g.offset)  # +-0.5 m
    z, d = np.asarray(g.z[0]), np.asarray(g.depth[0])
    flipped = np.sum((z[:, 1:] < z[:, :-1]) != (d[:, 1:] < d[:, :-1]))
    assert flipped > 5  # horizontal neighbours whose depth order the offsets reverse
    g1 = jax.tree.map(lambda x: x[0], g)
    pose1 = jax.tree.map(lambda x: x[None], pose)
    fast = splat.render_own(g1, pose, _intr(), window=window)
    _close(fast, splat_ref.render(g, pose1, pose, _intr(), window=window))
    in_z_order = splat_ref.render(_at_offset_depth(g), pose1, pose, _intr(), window=window)
    assert float(jnp.abs(fast.rgb - in_z_order.rgb).max()) > 1e-3


def test_offsets_change_only_the_depth_of_the_own_view():
    """An offset moves a Gaussian along its own pixel's ray and its radius scales with its depth, so
    in its own view it keeps its pixel and footprint: colour and opacity are those of zero offsets
    (the reference renderer, and the fast own-view path), the depth is not."""
    g, pose = _scene(1, 3), _pose(4)
    pose1 = jax.tree.map(lambda x: x[None], pose)
    zero = dataclasses.replace(g, offset=0.0 * g.offset)
    ref, ref0 = (splat_ref.render(x, pose1, pose, _intr()) for x in (g, zero))
    fast = splat.render_own(jax.tree.map(lambda x: x[0], g), pose, _intr())
    for r in (ref, fast):
        np.testing.assert_allclose(np.asarray(r.rgb), np.asarray(ref0.rgb), atol=1e-9)
        np.testing.assert_allclose(np.asarray(r.alpha), np.asarray(ref0.alpha), atol=1e-9)
    assert float(jnp.abs(ref.depth - ref0.depth).max()) > 1e-2


@pytest.mark.slow
@pytest.mark.parametrize("band", [None, 3])
def test_vjp_matches_reference_including_pose(band, monkeypatch):
    """Gradients with respect to the Gaussians, the viewing pose, the frames' poses and the
    intrinsics. ``band=3``: the backward pass runs in row bands of a few slot rows."""
    if band:
        monkeypatch.setattr(splat, "BAND_PIXELS", band * _intr().width)
    g, poses, view = _scene(2, 5), _poses(2, 6), _pose(7)
    layers = _max_per_slot(g, poses, view)
    moved = jax.vmap(lambda e, p: lie.exp(e) @ p)

    def fast(g, xi, eta, intr):
        return splat.render(g, moved(eta, poses), lie.exp(xi) @ view, intr, layers=layers)

    def ref(g, xi, eta, intr):
        return splat_ref.render(g, moved(eta, poses), lie.exp(xi) @ view, intr)

    args = (g, jnp.zeros(6), jnp.zeros((2, 6)), _intr())
    (_, gf), (_, gr) = _vjp(fast, args, 8), _vjp(ref, args, 8)
    assert float(jnp.abs(gr[1]).max()) > 1e-3  # the pose gradients are not trivially zero
    assert float(jnp.abs(gr[2]).max()) > 1e-3
    assert min(abs(float(x)) for x in jax.tree.leaves(gr[3])) > 1e-3  # nor those of fx, fy, cx, cy
    _close(gf, gr, tol=1e-8)


@pytest.mark.slow
@pytest.mark.parametrize("band", [None, 3])
def test_own_view_vjp_matches_reference_for_a_nearby_view(band, monkeypatch):
    """The own-view fast path keeps the source window; gradients w.r.t. the viewing pose and the
    frame's pose are exact, whole-image or in row bands (``band=3``: 4 bands, forward and backward)."""
    if band:
        monkeypatch.setattr(splat, "BAND_PIXELS", band * _intr().width)
    g, pose = _scene(1, 9), _pose(10)
    g1 = jax.tree.map(lambda x: x[0], g)
    intr = _intr()

    def fast(g1, xi, eta):
        return splat.render_own(g1, lie.exp(eta) @ pose, intr, view_pose=lie.exp(xi) @ pose)

    def ref(g1, xi, eta):
        src = jax.tree.map(lambda x: x[None], lie.exp(eta) @ pose)
        return splat_ref.render(jax.tree.map(lambda x: x[None], g1), src, lie.exp(xi) @ pose, intr)

    xi = jnp.zeros(6)
    eta = jnp.full(6, 1e-3)  # the frame's own pose slightly off its viewing pose
    (out, gf), (ref_out, gr) = _vjp(fast, (g1, xi, eta), 11), _vjp(ref, (g1, xi, eta), 11)
    _close(out, ref_out)
    assert float(jnp.abs(gr[2]).max()) > 1e-3
    _close(gf, gr, tol=1e-8)


@pytest.mark.parametrize("window,band", [(3, None), (3, 3), (5, 4)])
def test_own_view_at_own_pose_vjp_matches_reference(window, band, monkeypatch):
    """The own-pose fast path (no ``view_pose``: per-Gaussian opacity images, no positions):
    gradients with respect to every Gaussian attribute, whole-image or in row bands."""
    if band:
        monkeypatch.setattr(splat, "BAND_PIXELS", band * _intr().width)
    g, pose = _scene(1, 18), _pose(19)
    g1 = jax.tree.map(lambda x: x[0], g)
    intr = _intr()
    fast = lambda g1: splat.render_own(g1, pose, intr, window=window)  # noqa: E731
    ref = lambda g1: splat_ref.render(  # noqa: E731
        jax.tree.map(lambda x: x[None], g1), jax.tree.map(lambda x: x[None], pose), pose, intr, window=window
    )
    out, vf = jax.vjp(fast, g1)
    ref_out, vr = jax.vjp(ref, g1)
    _close(out, ref_out)
    ct = _cotangent(out, 20)
    gf, gr = vf(ct), vr(ct)
    assert float(jnp.abs(gr[0].offset).max()) > 1e-3  # offsets matter (footprint and rendered depth)
    _close(gf, gr, tol=1e-8)


@pytest.mark.slow
def test_renderer_vmaps_over_views():
    g, poses, views = _scene(2, 12), _poses(2, 13), _poses(3, 14)
    batched = jax.vmap(lambda v: splat.render(g, poses, v, _intr(), layers=2))(views)
    for i in range(3):
        one = splat.render(g, poses, jax.tree.map(lambda x: x[i], views), _intr(), layers=2)
        _close(jax.tree.map(lambda x: x[i], batched), one)


def test_binning_keeps_the_nearest_layers():
    """With fewer layers than Gaussians per pixel, the kept ones are the nearest by measured depth
    (the order key), whatever their offsets."""
    g, poses, view = _scene(3, 15), _poses(3, 16, scale=0.0), _pose(17, scale=0.0)
    attrs = splat.project_frames(g, poses, view, _intr())
    idx = np.asarray(splat.bin_layers(attrs, _intr(), 2, window=3))
    z = np.asarray(g.depth).reshape(-1)  # the poses are equal: the key is the measured depth
    np.testing.assert_allclose(np.asarray(attrs[3]), z, rtol=1e-12)
    r = 1
    for v in range(H):
        for u in range(W):
            # all three frames share the pose: pixel (v, u) holds Gaussian (v, u) of each frame
            here = [f * H * W + v * W + u for f in range(3)]
            want = sorted(here, key=lambda j: z[j])[:2]
            assert list(idx[:, v + r, u + r]) == want
