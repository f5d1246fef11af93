"""Mapping: the loss decreases, its gradients match finite differences, map_frame vmaps, and the
rendering-based initialisation recovers motion that GICP cannot see."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sgad_jax import lie, slam, splat
from sgad_jax import mapping
from sgad_jax.cli import resolve_config
from sgad_jax.config import DataConfig, MapConfig, SyntheticConfig
from sgad_jax.mapper import neighbour_slots
from sgad_jax.system import compile_step
from sgad_jax.io.synthetic import SyntheticDataset
from sgad_jax.types import Intrinsics, PixelGaussians, make_frame


@pytest.fixture(scope="module")
def room():
    ds = SyntheticDataset(DataConfig(layout="synthetic", synthetic=SyntheticConfig(frames=30, width=48, height=36)))
    frames = [make_frame(ds[i].rgb, ds[i].depth) for i in (0, 1, 2)]
    poses = [lie.from_matrix(ds.gt_poses[i]) for i in (0, 1, 2)]
    return ds.intrinsics, frames, poses


def _views(frames, poses, order):
    pick = lambda xs: [xs[i] for i in order]  # noqa: E731
    return mapping.Views(
        rgb=jnp.stack([f.rgb for f in pick(frames)]),
        depth=jnp.stack([f.depth for f in pick(frames)]),
        valid=jnp.stack([f.valid for f in pick(frames)]),
        pose=jax.tree.map(lambda *x: jnp.stack(x), *pick(poses)),
        present=jnp.ones(len(order), bool),
    )


def test_schedule_spends_the_share_on_the_own_view():
    sched = mapping.view_schedule(MapConfig(iterations=100, current_view_fraction=0.4), 3)
    assert sched[0] == 0
    assert 40 <= np.sum(sched == 0) <= 41
    assert abs(np.sum(sched == 1) - np.sum(sched == 2)) <= 1


def test_neighbour_slots_take_every_gap_th_previous_frame():
    index = np.array([9, 8, 7, 6, 5, 4, 3, 2, -1, -1])  # run indices of the recent frames, newest first
    assert neighbour_slots(index, 0, 2) == [1, 2]  # frame 9: frames 8 and 7
    assert neighbour_slots(index, 1, 2, gap=3) == [4, 7]  # frame 8: frames 5 and 2
    assert neighbour_slots(index, 0, 2, gap=4) == [4]  # frame 9: frame 5; frame 1 is not held
    assert neighbour_slots(index, 7, 2) == []  # frame 2: none held
    assert neighbour_slots(index[:3], 1, 3) == [2]  # the buffer's end


@pytest.mark.slow
def test_mapping_loss_decreases(room):
    intr, frames, poses = room
    cfg = MapConfig(iterations=30)
    views = _views(frames, poses, [1, 0, 2])
    g0 = mapping.init_gaussians(frames[1], intr)
    g, info = jax.jit(mapping.map_frame, static_argnums=0)(cfg, g0, poses[1], views, intr)
    own = np.asarray(info.loss)[np.asarray(info.view) == 0]
    assert own[-1] < 0.6 * own[0]
    assert float(jnp.abs(g.offset).max()) > 0  # offsets were learned
    before = jnp.mean((splat.render_own(g0, poses[1], intr).rgb - frames[1].rgb) ** 2)
    after = jnp.mean((splat.render_own(g, poses[1], intr).rgb - frames[1].rgb) ** 2)
    assert float(after) < 0.5 * float(before)


@pytest.mark.parametrize("radius_init", ["extent", "sigma"])
def test_colour_fit_matches_the_own_view_and_never_grows_the_residual(room, radius_init):
    """The own view over its neighbour's render is linear in the colours: the fit drives it to the
    measured image, and with 3x wider footprints (a badly conditioned blend, where plain fixed-point
    steps diverge) its error still never grows."""
    intr, frames, poses = room
    g0 = mapping.init_gaussians(frames[1], intr, radius_init=radius_init)
    bg = splat.render(jax.tree.map(lambda x: x[None], mapping.init_gaussians(frames[0], intr)), jax.tree.map(lambda x: x[None], poses[0]), poses[1], intr, layers=1)
    fit = jax.jit(mapping.fit_colours, static_argnums=5)
    errors = []
    for steps in range(4):
        rgb = splat.over(splat.render_own(fit(g0, poses[1], frames[1].rgb, intr, bg, steps), poses[1], intr), bg).rgb
        errors.append(float(jnp.mean((rgb - frames[1].rgb) ** 2)))
    assert all(b <= a * (1 + 1e-5) for a, b in zip(errors, errors[1:])), errors
    if radius_init == "extent":
        assert -10 * np.log10(errors[-1]) > 45 and errors[-1] < 1e-2 * errors[0], errors


@pytest.mark.slow
def test_offsets_stay_fixed_in_the_ablation_and_do_not_spoil_the_own_view_fit(room):
    """The ablation keeps every offset at 0; and fitted to its own view alone, a frame with offsets
    learned (the paper's rate: up to 1 cm per step) fits about as well as with offsets fixed:
    offsets may not reorder a pixel's candidates there (when they did, the fit lost 19 dB on a
    real frame)."""
    intr, frames, poses = room
    g0 = mapping.init_gaussians(frames[1], intr)
    views = _views(frames, poses, [1])
    psnr = {}
    for learn in (True, False):
        cfg = MapConfig(iterations=100, learn_offset=learn)
        g, _ = jax.jit(mapping.map_frame, static_argnums=0)(cfg, g0, poses[1], views, intr)
        mse = jnp.mean((splat.render_own(g, poses[1], intr).rgb - frames[1].rgb) ** 2)
        psnr[learn] = -10.0 * float(jnp.log10(mse))
    assert float(jnp.abs(g.offset).max()) == 0.0 and float(jnp.abs(g.rgb - g0.rgb).max()) > 0 and psnr[False] > 30.0
    assert psnr[True] > psnr[False] - 1.0, psnr


def test_offsets_are_learned_from_the_other_views(room):
    """By default the own view's loss sees the Gaussians at their measured depths and holds each
    offset to it by ``|offset|`` (no pull at zero), so a frame fitted to its own view alone keeps
    every offset at 0; with ``offset_in_own_view`` (the paper's loss) the blended depth moves them."""
    intr, frames, poses = room
    g0 = mapping.init_gaussians(frames[1], intr)
    own = _views(frames, poses, [1])
    fit = jax.jit(mapping.map_frame, static_argnums=0)
    alone, _ = fit(MapConfig(iterations=10), g0, poses[1], own, intr)
    paper, _ = fit(MapConfig(iterations=10, offset_in_own_view=True), g0, poses[1], own, intr)
    assert float(jnp.abs(alone.offset).max()) == 0.0 and float(jnp.abs(alone.rgb - g0.rgb).max()) > 0
    assert float(jnp.mean(jnp.abs(paper.offset) > 0)) > 0.5


def test_own_view_pulls_each_offset_back_by_its_own_depth_error(room):
    """The own view's loss does not render the offsets; its only term in them is the depth error
    ``U |offset|`` averaged over the valid pixels: gradient ``U sign(offset) / n_valid`` per
    Gaussian, and none at zero (offsets start there and stay unless other views move them)."""
    intr, frames, poses = room
    views = _views(frames, poses, [1, 0])
    g = mapping.init_gaussians(frames[1], intr)
    offset = jnp.asarray(np.random.default_rng(0).normal(0, 0.01, g.offset.shape), jnp.float32)
    offset = offset.at[::2].set(0.0)
    cfg = MapConfig(weight_depth=0.7)
    grad = jax.jit(jax.grad(lambda o: mapping.view_loss(cfg, dataclasses.replace(g, offset=o), poses[1], views, 0, intr)))(offset)
    valid = np.asarray(views.valid[0], np.float64)
    want = 0.7 * np.sign(np.asarray(offset)) * valid / valid.sum()
    np.testing.assert_allclose(np.asarray(grad), want, rtol=1e-5, atol=1e-12)
    assert (want != 0).sum() > 100 and (np.asarray(grad)[::2] == 0).all()


@pytest.mark.slow
@pytest.mark.parametrize("at_invalid", [True, False])
def test_offsets_without_measured_depth(room, at_invalid):
    """``offset_at_invalid=False`` keeps the offsets of Gaussians at pixels without measured depth
    (here a block whose depth was inpainted) at zero, and learns the others."""
    intr, frames, poses = room
    hole = np.zeros(frames[1].depth.shape, bool)
    hole[10:20, 15:30] = True
    depth = np.where(hole, 0.0, np.asarray(frames[1].depth))
    own = make_frame(frames[1].rgb, depth, np.asarray(frames[1].depth))
    views = _views([frames[0], own, frames[2]], poses, [1, 0, 2])
    cfg = MapConfig(iterations=20, offset_at_invalid=at_invalid)
    g, _ = jax.jit(mapping.map_frame, static_argnums=0)(cfg, mapping.init_gaussians(own, intr), poses[1], views, intr)
    moved = np.abs(np.asarray(g.offset)) > 0
    assert moved[~hole].mean() > 0.5
    assert moved[hole].any() == at_invalid


@pytest.mark.slow
def test_offsets_stay_within_the_sensor_bound(room):
    """Each Adam step is projected onto ``|offset| <= offset_bound * D^2``: with a bound small enough
    that unbounded offsets pass it (0.2 mm per m^2), every offset ends inside it, many at its edge.
    The paper's loss (offsets in the own view too) drives them hardest."""
    intr, frames, poses = room
    views = _views(frames, poses, [1, 0, 2])
    g0 = mapping.init_gaussians(frames[1], intr)
    fit = jax.jit(mapping.map_frame, static_argnums=0)
    free, _ = fit(MapConfig(iterations=20, offset_bound=0.0, offset_in_own_view=True), g0, poses[1], views, intr)
    bounded, _ = fit(MapConfig(iterations=20, offset_bound=2e-4, offset_in_own_view=True), g0, poses[1], views, intr)
    limit = 2e-4 * np.asarray(g0.depth, np.float64) ** 2
    assert (np.abs(np.asarray(free.offset)) > limit).mean() > 0.1
    off = np.abs(np.asarray(bounded.offset))
    assert np.all(off <= limit * (1 + 1e-5))
    assert (off >= limit * (1 - 1e-5)).mean() > 0.1


@pytest.mark.slow
def test_missing_neighbours_iterations_change_nothing(room):
    """A frame without neighbours (the first of a run) ends as if mapped on its own view alone for
    its own-view share of the iterations."""
    intr, frames, poses = room
    g0 = mapping.init_gaussians(frames[1], intr)
    cfg = MapConfig(iterations=12, lr_offset_final=MapConfig.lr_offset)  # no rate decay: it runs over the iterations
    views = dataclasses.replace(_views(frames, poses, [1, 0, 2]), present=jnp.asarray([True, False, False]))
    g, info = jax.jit(mapping.map_frame, static_argnums=0)(cfg, g0, poses[1], views, intr)
    own = int(np.sum(mapping.view_schedule(cfg, 3) == 0))
    assert 0 < own < cfg.iterations and set(np.asarray(info.view).tolist()) == {0, -1}
    # The reference's radius and opacity rates as the 12 iterations scale them (mapping.reach_scale)
    ref_cfg = dataclasses.replace(cfg, iterations=own)
    k = mapping.reach_scale(cfg) / mapping.reach_scale(ref_cfg)
    ref_cfg = dataclasses.replace(ref_cfg, lr_radius=cfg.lr_radius * k, lr_opacity=cfg.lr_opacity * k)
    ref, _ = jax.jit(mapping.map_frame, static_argnums=0)(ref_cfg, g0, poses[1], _views(frames, poses, [1]), intr)
    for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(ref)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-5)


@pytest.mark.slow
def test_map_frame_vmaps_over_frames(room):
    intr, frames, poses = room
    cfg = MapConfig(iterations=4)
    stack = lambda *x: jnp.stack(x)  # noqa: E731
    gs = jax.tree.map(stack, *[mapping.init_gaussians(f, intr) for f in frames[:2]])
    ps = jax.tree.map(stack, *poses[:2])
    vs = jax.tree.map(stack, _views(frames, poses, [0, 1]), _views(frames, poses, [1, 0]))
    batched, _ = jax.vmap(lambda g, p, v: mapping.map_frame(cfg, g, p, v, intr))(gs, ps, vs)
    one, _ = mapping.map_frame(cfg, jax.tree.map(lambda x: x[1], gs), poses[1], _views(frames, poses, [1, 0]), intr)
    np.testing.assert_allclose(np.asarray(batched.offset[1]), np.asarray(one.offset), atol=1e-5)


@pytest.mark.slow
@pytest.mark.parametrize("view", [0, 1])
def test_loss_gradients_match_finite_differences(room, view):
    """d loss / d offsets and d loss / d pose (tangent), float64, in the own and a neighbour view."""
    intr, frames, poses = room
    with jax.enable_x64(True):
        f64 = lambda t: jax.tree.map(lambda x: jnp.asarray(x, jnp.float64) if jnp.issubdtype(x.dtype, jnp.floating) else x, t)  # noqa: E731
        intr64 = Intrinsics(*(jnp.float64(v) for v in intr.as_tuple()), width=intr.width, height=intr.height)
        views = f64(_views(frames, poses, [1, 0]))
        g = f64(mapping.init_gaussians(frames[1], intr))
        rng = np.random.default_rng(view)
        # Compositing follows the measured depths: untie those of the room's flat walls, or the
        # smallest pose step reorders tied neighbours.
        g = dataclasses.replace(g, offset=jnp.asarray(rng.normal(0, 0.01, g.offset.shape)),
                                depth=g.depth + jnp.asarray(rng.normal(0, 0.01, g.depth.shape)))
        pose = f64(poses[1])
        cfg = MapConfig()

        def loss(offset, xi):  # the own view rendered at the view's pose: its pose gradient is not zero
            return mapping.view_loss(cfg, dataclasses.replace(g, offset=offset), lie.exp(xi) @ pose, views, view, intr64, own_at_pose=False)

        xi0 = jnp.zeros(6)
        g_off, g_xi = jax.jit(jax.grad(loss, argnums=(0, 1)))(g.offset, xi0)
        loss = jax.jit(loss)  # evaluated 14 times: one program, not each operation compiled apart
        d_off = jnp.asarray(rng.normal(size=g.offset.shape))
        # Small steps: compositing order jumps where two Gaussians' depths cross; with 1e-8 steps
        # the chance that any of the ~10^4 neighbouring pairs crosses is about 1%.
        eps = 1e-8
        fd = (loss(g.offset + eps * d_off, xi0) - loss(g.offset - eps * d_off, xi0)) / (2 * eps)
        np.testing.assert_allclose(float(jnp.vdot(g_off, d_off)), float(fd), rtol=1e-4, atol=1e-9)
        for i in range(6):
            e = jnp.zeros(6).at[i].set(eps)
            fd = (loss(g.offset, e) - loss(g.offset, -e)) / (2 * eps)
            np.testing.assert_allclose(float(g_xi[i]), float(fd), rtol=1e-4, atol=1e-7)


def _plane_frame(t_xy, intr: Intrinsics, z: float = 1.5):
    """A camera looking down +z at a textured plane z = const, translated by ``t_xy``: depth is
    constant (GICP sees no in-plane motion), colour is a smooth texture fixed to the plane.

    (GICP run after the refined guess on this noise-free plane snaps to the nearest alignment of the
    two frames' regular point grids, 5 cm apart here, so the test checks the refined guess itself.)"""
    v, u = np.mgrid[0 : intr.height, 0 : intr.width].astype(np.float64)
    X = (u - float(intr.cx)) / float(intr.fx) * z + t_xy[0]
    Y = (v - float(intr.cy)) / float(intr.fy) * z + t_xy[1]
    rgb = np.stack([0.5 + 0.4 * np.sin(7 * X + 2 * Y), 0.5 + 0.4 * np.cos(5 * Y - 3 * X), 0.5 + 0.3 * np.sin(4 * X * Y + 3 * X)], -1)
    depth = np.full(X.shape, z)
    return make_frame(rgb.astype(np.float32), depth.astype(np.float32))


@pytest.mark.slow
def test_rendering_init_recovers_motion_that_gicp_misses():
    intr = Intrinsics(fx=jnp.float32(60.0), fy=jnp.float32(60.0), cx=jnp.float32(39.5), cy=jnp.float32(29.5), width=80, height=60)
    shift = np.array([0.04, -0.03])
    f0, f1 = _plane_frame((0.0, 0.0), intr), _plane_frame(shift, intr)
    true1 = lie.exp(jnp.array([shift[0], shift[1], 0.0, 0.0, 0.0, 0.0]))
    tcfg = resolve_config(None, None).track  # the demo preset's: the host loop's step at 80 x 60, from the shared cache
    state = slam.init_state(tcfg)
    track = compile_step(tcfg, state, f0.depth, intr, jnp.float32(0.0))
    state, _, _, _, _ = track(state, f0.depth, intr, jnp.float32(0.0), None)
    # GICP alone from the previous pose: the plane gives no in-plane constraint.
    _, T_gicp, _, _, _ = track(state, f1.depth, intr, jnp.float32(0.0), None)
    err_gicp = np.linalg.norm(np.asarray(T_gicp.translation() - true1.translation()))
    assert err_gicp > 0.03
    # Rendering-based initialisation from frame 0's Gaussians finds the motion from the texture.
    g0 = mapping.init_gaussians(f0, intr)
    refine = jax.jit(mapping.refine_pose, static_argnums=0, static_argnames="iterations")
    guess = refine(MapConfig(), g0, lie.identity(), f1, lie.identity(), intr, iterations=60)
    err = np.linalg.norm(np.asarray(guess.translation() - true1.translation()))
    assert err < 0.005, (err, err_gicp)


@pytest.mark.slow
def test_map_step_compiles_once_for_a_sequence(room):
    """Fixed shapes: the first frames (fewer neighbours) and later ones share one compiled step."""
    import chex

    intr, frames, poses = room
    cfg = MapConfig(iterations=2)
    traced = chex.assert_max_traces(slam.map_step, n=1)
    step = jax.jit(lambda *a: traced(cfg, *a, intr))
    stack = lambda *xs: jnp.stack(xs)  # noqa: E731
    for i, present in ((1, [True, False]), (2, [True, True])):
        nb = jax.tree.map(stack, frames[i - 1], frames[0])
        nb_gs = jax.tree.map(stack, *[mapping.init_gaussians(f, intr) for f in (frames[i - 1], frames[0])])
        nb_poses = jax.tree.map(stack, poses[i - 1], poses[0])
        _, out, _ = step(frames[i], poses[i], nb_gs, nb, nb_poses, jnp.asarray(present))
        assert np.isfinite(np.asarray(out.rgb)).all()
    chex.clear_trace_counter()


def test_fewer_iterations_scale_the_radius_and_opacity_steps():
    """Adam's first step moves each parameter by its rate; with fewer than the paper's 100
    iterations the radius and opacity rates are raised by 100 / iterations (at most 100 / 15), the
    others not."""
    z = jnp.zeros((2, 2))
    g = PixelGaussians(rgb=jnp.zeros((2, 2, 3)), log_radius=z, opacity_logit=z, offset=z, depth=z)
    grad = jax.tree.map(jnp.ones_like, g)
    for iterations, scale in ((100, 1.0), (400, 1.0), (20, 5.0), (15, 100 / 15), (5, 100 / 15)):
        cfg = MapConfig(iterations=iterations)
        opt = mapping.optimizer(cfg)
        step, _ = opt.update(grad, opt.init(g), g)
        np.testing.assert_allclose(np.asarray(step.log_radius), -cfg.lr_radius * scale, rtol=1e-4)
        np.testing.assert_allclose(np.asarray(step.opacity_logit), -cfg.lr_opacity * scale, rtol=1e-4)
        np.testing.assert_allclose(np.asarray(step.rgb), -cfg.lr_rgb, rtol=1e-4)
        np.testing.assert_allclose(np.asarray(step.offset), -cfg.lr_offset, rtol=1e-4)
