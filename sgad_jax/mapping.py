"""Mapping: learn a frame's pixel-aligned Gaussians (colour, radius, opacity, depth offset).

``map_frame`` is pure: it takes a frame's initial Gaussians, its pose and the views it is fitted to
(its own first, then its neighbours), and returns the optimised Gaussians. Jit it, ``vmap`` it over
frames (their mapping is independent once they are tracked) or differentiate through it.

The loss is SGAD-SLAM's ``rho L1 + tau (1 - SSIM) + sigma U L1_depth`` between a view and the
frame's Gaussians rendered into it (:func:`sgad_jax.losses.mapping_loss`); in a neighbour's view
it is taken over the pixels the frame's Gaussians cover. Neighbours' Gaussians are never changed.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from sgad_jax import lie, losses, splat
from sgad_jax.config import MapConfig
from sgad_jax.types import Frame, Intrinsics, PixelGaussians

#: Opacity of a new Gaussian.
INIT_OPACITY = 0.9
#: A neighbour view's pixel counts in the loss where the frame's Gaussians cover it this much.
COVERAGE = 0.5


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Views:
    """The views a frame is fitted to, stacked ``(v, ...)``: index 0 is the frame itself.

    ``present[k]`` is False for missing neighbours (the first frames of a run); their share of the
    iterations changes nothing.
    """

    rgb: Float[Array, "v h w 3"]
    depth: Float[Array, "v h w"]
    valid: Bool[Array, "v h w"]
    pose: lie.SE3
    present: Bool[Array, " v"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class MapInfo:
    loss: Float[Array, " n"]  # the loss of every iteration
    view: Int[Array, " n"]  # the view each iteration used (0: own; -1: none, a missing neighbour's)


def init_gaussians(frame: Frame, intr: Intrinsics, *, opacity: float = INIT_OPACITY, radius_init: str = "extent") -> PixelGaussians:
    """One Gaussian per pixel at the filled depth, zero offset, radius D / f: the pixel's footprint
    taken as the 3-sigma extent (``radius_init="extent"``) or as sigma (``"sigma"``, 3x larger)."""
    depth = frame.depth_filled
    f = 0.5 * (intr.fx + intr.fy)
    scale = splat.RADIUS_SIGMAS if radius_init == "sigma" else 1.0
    radius = scale * jnp.maximum(depth, 1e-3) / f
    logit = math.log(opacity / (1.0 - opacity))
    return PixelGaussians(
        rgb=frame.rgb,
        log_radius=jnp.log(radius),
        opacity_logit=jnp.full_like(depth, logit),
        offset=jnp.zeros_like(depth),
        depth=depth,
    )


def view_schedule(cfg: MapConfig, views: int) -> np.ndarray:
    """Which view each iteration uses: the own view in a ``current_view_fraction`` share of
    iterations (the first one included), spread evenly, the neighbours in turn otherwise."""
    n, f = cfg.iterations, cfg.current_view_fraction
    out, k = [], 0
    for t in range(n):
        own = views == 1 or math.floor((t + 1) * f + (1 - f)) > math.floor(t * f + (1 - f))
        if own:
            out.append(0)
        else:
            out.append(1 + k % (views - 1))
            k += 1
    return np.asarray(out, np.int32)


def offset_rate(cfg: MapConfig) -> optax.Schedule | float:
    """The offset's learning rate: from ``lr_offset`` down to ``lr_offset_final`` log-linearly over
    the frame's iterations, as 3DGS decays its positions' rate, so the offsets settle at the end
    instead of ending wherever Adam's last steps of about ``lr_offset`` left them."""
    if cfg.lr_offset_final == cfg.lr_offset:
        return cfg.lr_offset
    return optax.exponential_decay(cfg.lr_offset, transition_steps=cfg.iterations, decay_rate=cfg.lr_offset_final / cfg.lr_offset)


#: Adam steps a frame in the paper, whose learning rates are set for them.
PAPER_ITERATIONS = 100
#: The fewest steps the rates are scaled for (the range measured; below it steps of 7% of a
#: radius and 0.33 of an opacity logit would grow further).
FEWEST_SCALED = 15


def reach_scale(cfg: MapConfig) -> float:
    """The factor on the radius and opacity rates: ``100 / iterations`` for 15 to 100 steps (at
    most 100 / 15 below, 1 above). Adam moves a parameter by about its rate a step, and over the
    paper's 100 steps these two travel one way nearly all along (a frame's radii grow by about
    20%, its opacities from 0.9 to 0.97), so with fewer steps at the paper's rates they stop short
    (docs/method.md, "Iterations per frame and the colour fit")."""
    return PAPER_ITERATIONS / min(max(cfg.iterations, FEWEST_SCALED), PAPER_ITERATIONS)


def optimizer(cfg: MapConfig) -> optax.GradientTransformation:
    """Adam with the paper's per-attribute learning rates, those of radius and opacity times
    :func:`reach_scale` (depth frozen; offset too if disabled)."""
    labels = PixelGaussians(rgb="rgb", log_radius="radius", opacity_logit="opacity", offset="offset", depth="frozen")
    reach = reach_scale(cfg)
    return optax.multi_transform(
        {
            "rgb": optax.adam(cfg.lr_rgb),
            "radius": optax.adam(cfg.lr_radius * reach),
            "opacity": optax.adam(cfg.lr_opacity * reach),
            "offset": optax.adam(offset_rate(cfg)) if cfg.learn_offset else optax.set_to_zero(),
            "frozen": optax.set_to_zero(),
        },
        labels,
    )


def bound_offsets(cfg: MapConfig, g: PixelGaussians) -> PixelGaussians:
    """Project the offsets onto ``|offset| <= cfg.offset_bound * depth^2`` (the sensor's depth error;
    beyond it a Gaussian no longer sits on the surface its pixel measured)."""
    if cfg.offset_bound <= 0:
        return g
    b = cfg.offset_bound * jnp.square(g.depth)
    return dataclasses.replace(g, offset=jnp.clip(g.offset, -b, b))


def _one(tree):
    """A single frame's pytree as a stack of one (what :func:`sgad_jax.splat.render` takes)."""
    return jax.tree.map(lambda x: x[None], tree)


def render_into(
    g: PixelGaussians, pose: lie.SE3, view_pose: lie.SE3, intr: Intrinsics, own, window: int, *, own_at_pose: bool = True,
    own_offsets: bool = True,
) -> splat.Render:
    """The frame's Gaussians in a view: the exact own-view path, or one binned layer elsewhere.
    ``own_at_pose``: the own view is seen at ``pose`` itself (``view_pose`` ignored there; the
    faster own-pose renderer, whose image does not depend on the pose, see
    :func:`sgad_jax.splat.render_own`); ``False`` renders it at ``view_pose``, so that the own
    view's pose gradient can be checked (``tests/test_mapping.py``). ``own_offsets=False``: the own
    view sees the Gaussians at their measured depths (``map.offset_in_own_view``)."""

    def own_view(_):
        go = g if own_offsets else dataclasses.replace(g, offset=jnp.zeros_like(g.offset))
        return splat.render_own(go, pose, intr, window=window, view_pose=None if own_at_pose else view_pose)

    def other_view(_):
        return splat.render(_one(g), _one(pose), view_pose, intr, layers=1, window=window)

    return jax.lax.cond(own, own_view, other_view, None)


def view_loss(
    cfg: MapConfig,
    g: PixelGaussians,
    pose: lie.SE3,
    views: Views,
    k,
    intr: Intrinsics,
    background: splat.Render | None = None,
    *,
    window: int = 3,
    targets: losses.SSIMTarget | None = None,
    own_at_pose: bool = True,
):
    """The mapping loss of the frame's Gaussians in view ``k`` (0: own view, over ``background``);
    ``targets``: the views' colour as :func:`sgad_jax.losses.ssim_target` (stacked), if computed;
    ``own_at_pose``: the own view is the frame's camera at ``pose`` (see :func:`render_into`)."""
    view = jax.tree.map(lambda x: x[k], views)
    target = view.rgb if targets is None else jax.tree.map(lambda x: x[k], targets)
    out = render_into(g, pose, view.pose, intr, k == 0, window, own_at_pose=own_at_pose, own_offsets=cfg.offset_in_own_view)
    if background is not None:
        keep = jnp.asarray(k == 0, out.alpha.dtype)
        out = splat.over(out, jax.tree.map(lambda x: keep * x, background))
    covered = jax.lax.stop_gradient(out.alpha) > COVERAGE if cfg.coverage_mask else jnp.ones_like(out.alpha, bool)
    mask = jnp.where(k == 0, 1.0, jnp.asarray(covered, out.alpha.dtype))
    # Depth is compared after normalising by the accumulated opacity: at a partly covered pixel the
    # blended depth is short by (1 - alpha) z, which is not a geometric error.
    depth = out.depth / jnp.maximum(out.alpha, 1e-3)
    loss = losses.mapping_loss(
        out.rgb, depth, target, view.depth, view.valid, mask,
        weight_l1=cfg.weight_l1, weight_ssim=cfg.weight_ssim, weight_depth=cfg.weight_depth,
    )
    if not cfg.offset_in_own_view:
        # The own view measures each Gaussian's depth directly: its depth term for the offsets is
        # per Gaussian, |z - D| = |offset|, free of the blending's bias (docs/method.md, "Mapping").
        # Written as offset * sign(offset), whose gradient at zero is zero (jnp.abs's is 1).
        anchor = losses.depth_l1(g.offset * jax.lax.stop_gradient(jnp.sign(g.offset)), 0.0, view.valid)
        loss = loss + jnp.where(k == 0, cfg.weight_depth * anchor, 0.0)
    return loss


def fit_colours(
    g: PixelGaussians, pose: lie.SE3, target: Float[Array, "h w 3"], intr: Intrinsics, background: splat.Render | None,
    steps: int, *, window: int = 3, own_offsets: bool = False,
) -> PixelGaussians:
    """Fit the colours to the own view by ``steps`` minimal-residual steps. There the render over
    the fixed ``background`` is ``A c + b``, linear in the colours ``c`` with ``A`` the blending
    of the frame's Gaussians; each step moves ``c`` along the residual ``r = target - A c - b`` by
    the ``alpha`` that minimises ``|r - alpha A r|``, so the residual never grows."""
    go = g if own_offsets else dataclasses.replace(g, offset=jnp.zeros_like(g.offset))

    def blend(c):
        return splat.render_own(dataclasses.replace(go, rgb=c), pose, intr, window=window)

    def step(_, c):
        r = target - render_frame(dataclasses.replace(go, rgb=c), pose, background, intr, window=window).rgb
        ar = blend(r).rgb
        alpha = jnp.sum(r * ar) / jnp.maximum(jnp.sum(ar * ar), 1e-12)
        return c + alpha * r

    return dataclasses.replace(g, rgb=jax.lax.fori_loop(0, steps, step, g.rgb))


def map_frame(
    cfg: MapConfig,
    g: PixelGaussians,
    pose: lie.SE3,
    views: Views,
    intr: Intrinsics,
    background: splat.Render | None = None,
    *,
    window: int = 3,
) -> tuple[PixelGaussians, MapInfo]:
    """Optimise a frame's Gaussians ``g`` (at camera-to-world ``pose``) for ``cfg.iterations`` Adam
    steps on its own view and its neighbours' (``views``, own view first), then fit the colours to
    the own view in ``cfg.colour_fit`` steps (:func:`fit_colours`).

    ``background`` is the neighbours' (fixed) Gaussians rendered into the own view; the frame's
    Gaussians are composited over it there, as in :func:`render_frame`. The own view is the
    frame's camera at ``pose``, rendered by the own-pose path (composited in measured-depth order,
    as every view is: see :func:`sgad_jax.splat.project`).
    """
    schedule = jnp.asarray(view_schedule(cfg, views.present.shape[0]))
    opt = optimizer(cfg)
    # A missing neighbour's iterations run like the others (which path an iteration takes depends
    # on the schedule alone: under vmap a data-dependent branch would run both paths at every
    # iteration) and their update is discarded: fitting the own view through the other-view path
    # instead (in the view-depth order it had before the order key) made a first frame with learned
    # offsets chatter.
    present = views.present
    targets = jax.vmap(losses.ssim_target)(views.rgb)  # fixed: computed once, not at every step

    def step(carry, k):
        g, state = carry
        loss, grad = jax.value_and_grad(view_loss, argnums=1)(
            cfg, g, pose, views, k, intr, background, window=window, targets=targets
        )
        if not cfg.offset_at_invalid:
            grad = dataclasses.replace(grad, offset=grad.offset * views.valid[0])
        updates, new_state = opt.update(grad, state, g)
        new = (bound_offsets(cfg, optax.apply_updates(g, updates)), new_state)
        return jax.tree.map(lambda a, b: jnp.where(present[k], a, b), new, (g, state)), (loss, jnp.where(present[k], k, -1))

    # The optimiser state is selected by `present` in each step: make it vary like `present` from
    # the start (under shard_map a scan's carry must keep its manual-axis type).
    state = jax.tree.map(lambda x: jnp.where(present[0], x, x), opt.init(g))
    (g, _), (loss, used) = jax.lax.scan(step, (g, state), schedule)
    if cfg.colour_fit:
        g = fit_colours(g, pose, views.rgb[0], intr, background, cfg.colour_fit, window=window, own_offsets=cfg.offset_in_own_view)
    return g, MapInfo(loss=loss, view=used)


def render_frame(g: PixelGaussians, pose: lie.SE3, background: splat.Render | None, intr: Intrinsics, *, window: int = 3) -> splat.Render:
    """A frame's view: its own Gaussians composited over its neighbours' (``background``, from
    :func:`sgad_jax.splat.render` of the neighbours, one layer), the image its mapping loss was fitted to. Own Gaussians come first,
    neighbours fill what they leave uncovered: each frame's Gaussians are fitted to its own view,
    so mixing two frames' fits of one surface by depth would blend them."""
    own = splat.render_own(g, pose, intr, window=window)
    return own if background is None else splat.over(own, background)


def refine_pose(
    cfg: MapConfig,
    g_prev: PixelGaussians,
    pose_prev: lie.SE3,
    frame: Frame,
    guess: lie.SE3,
    intr: Intrinsics,
    *,
    iterations: int = 30,
    lr: float = 2e-3,
    tol: float = 1e-6,
    window: int = 3,
) -> lie.SE3:
    """Rendering-based pose initialisation: refine ``guess`` by minimising the photometric and depth
    error of the previous frame's Gaussians rendered into the current frame, over a left tangent
    update ``exp(xi) guess`` (pixels covered by the render and with valid depth; the binning is
    redone at every step).

    Solved by ``optimistix.minimise`` with Adam (``optx.OptaxMinimiser``), at most ``iterations``
    steps, stopping early once a step moves the pose by less than ``tol`` (metres and radians).
    Adam rather than a quasi-Newton solver: the loss is an L1 whose mask changes with the pose, and
    on the test plane of ``tests/test_mapping.py`` BFGS ended 2.7 mm from the true motion against
    Adam's 0.5 mm (docs/method.md)."""

    def loss_fn(xi, _):
        out = splat.render(_one(g_prev), _one(pose_prev), lie.exp(xi) @ guess, intr, layers=1, window=window)
        mask = (jax.lax.stop_gradient(out.alpha) > COVERAGE) & frame.valid
        # Colour and depth normalised by the accumulated opacity: at fractional pixel positions the
        # coverage of a frame's Gaussians dips, which says nothing about the pose.
        norm = 1.0 / jnp.maximum(out.alpha, 1e-3)
        rgb, depth = out.rgb * norm[..., None], out.depth * norm
        return cfg.weight_l1 * losses.l1(rgb, frame.rgb, mask) + cfg.weight_depth * losses.depth_l1(depth, frame.depth, mask)

    solver = optx.OptaxMinimiser(optax.adam(lr), rtol=0.0, atol=tol)
    xi0 = jnp.zeros(6, guess.wxyz_xyz.dtype)
    sol = optx.minimise(loss_fn, solver, xi0, max_steps=iterations, throw=False)
    return lie.exp(sol.value) @ guess
