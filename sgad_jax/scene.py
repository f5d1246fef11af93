"""The scene as a radiance field: render any pose from the mapped frames that cover it.

A scene is the set of every mapped frame's learned pixel-aligned Gaussians at its pose. A view is
rendered from the ``k`` mapped frames that best cover it (:func:`select_frames`, on the host), put
in priority order, nearest camera first (:func:`priority`). :func:`render_scene` (pure, jitted,
fixed shapes) renders each frame's Gaussians into the view and composites the frames' images in
that order, each over the later ones, except where a later frame's surface lies in front by more
than :data:`OCCLUSION_TOLERANCE` of the depth: each frame's Gaussians are a fit of its own view,
so the nearest fit is shown whole instead of interleaving several by depth (docs/method.md,
"The scene and held-out views"). ``composite="depth"`` merges all frames in depth order instead.

:func:`finetune_step` is one Adam step of the merged-map refinement (the paper fine-tunes the merged
map before judging novel views): a training view rendered from its ``k`` frames, whose Gaussians
are all trainable.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from sgad_jax import lie, losses, splat
from sgad_jax import mapping
from sgad_jax.config import MapConfig, SceneConfig
from sgad_jax.types import Intrinsics, PixelGaussians

#: Coverage scores closer than this count as equal.
SCORE_STEP = 0.1
#: Footprint samples per frame: a grid of this many rows and columns of its depth image.
FOOTPRINT_GRID = (24, 32)
#: The view's cells that :func:`select_frames` covers.
VIEW_CELLS = (12, 16)
#: A later frame's surface shows in front of an earlier one's where it is nearer by more than this
#: share of the earlier one's depth (an occluder), not where the two are one surface fitted twice.
OCCLUSION_TOLERANCE = 0.1
#: Priority order: camera distance plus this many metres per radian between the optical axes.
ANGLE_METRES = 0.1
#: A frame's surface counts where its opacity reaches this.
COVERED = 0.5


@functools.partial(jax.jit, static_argnames=("composite", "layers", "window"))
def render_scene(
    gs: PixelGaussians,
    poses: lie.SE3,
    view_pose: lie.SE3,
    intr: Intrinsics,
    present: Bool[Array, " k"] | None = None,
    *,
    composite: str = "priority",
    layers: int = 4,
    window: int = 3,
) -> splat.Render:
    """Colour, depth and opacity of the view at camera-to-world ``view_pose`` rendered from the
    Gaussians of ``k`` frames ``gs`` (stacked ``(k, h, w)``, in priority order) at camera-to-world
    ``poses``. ``present`` (``(k,)``) hides frames that are padding.

    ``composite="priority"``: each frame rendered alone (its nearest Gaussian per pixel slot, so
    its own occlusions hold), then composited front to back in the frames' order, a later frame
    coming forward only where its surface is nearer than the earlier result's by more than
    :data:`OCCLUSION_TOLERANCE` of the depth (:func:`priority_over`). ``"depth"``: all Gaussians
    binned together, the ``layers`` nearest per slot, composited in true depth order.
    """
    if present is not None:
        hide = jnp.where(present, 0.0, -1e4)[:, None, None]
        gs = dataclasses.replace(gs, opacity_logit=gs.opacity_logit + hide)
    if composite == "depth":
        return splat.render(gs, poses, view_pose, intr, layers=layers, window=window)
    if composite != "priority":
        raise ValueError(f"composite: priority or depth, got {composite!r}")
    one = lambda x: x[None]  # noqa: E731
    each = jax.vmap(lambda g, p: splat.render(jax.tree.map(one, g), jax.tree.map(one, p), view_pose, intr, layers=1, window=window))(gs, poses)
    out = jax.tree.map(lambda x: x[-1], each)
    for j in range(gs.depth.shape[0] - 2, -1, -1):
        out = priority_over(jax.tree.map(lambda x: x[j], each), out)
    return out


def priority_over(front: splat.Render, back: splat.Render, tolerance: float = OCCLUSION_TOLERANCE) -> splat.Render:
    """``front`` over ``back``, except at pixels where ``back``'s surface is covered and nearer than
    ``front``'s by more than ``tolerance`` of ``front``'s depth: there ``back`` occludes it."""
    near_front = front.depth / jnp.maximum(front.alpha, 1e-3)
    near_back = back.depth / jnp.maximum(back.alpha, 1e-3)
    occludes = jax.lax.stop_gradient((back.alpha > COVERED) & (near_back < (1.0 - tolerance) * near_front))
    a, b = splat.over(front, back), splat.over(back, front)
    return splat.Render(
        rgb=jnp.where(occludes[..., None], b.rgb, a.rgb), depth=jnp.where(occludes, b.depth, a.depth), alpha=jnp.where(occludes, b.alpha, a.alpha)
    )


def priority(view_pose: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Order of the frames at camera-to-world ``poses`` for a view: camera distance plus
    :data:`ANGLE_METRES` per radian between the optical axes, smallest first."""
    dist = np.linalg.norm(poses[:, :3, 3] - view_pose[:3, 3], axis=1)
    angle = np.arccos(np.clip(poses[:, :3, 2] @ view_pose[:3, 2], -1.0, 1.0))
    return np.argsort(dist + ANGLE_METRES * angle, kind="stable")


def footprint(depth: np.ndarray, valid: np.ndarray, pose: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """``(m, 3)`` world points of a grid of a frame's valid depth pixels (NaN where invalid): what
    :func:`select_frames` projects into a view to judge how much of it the frame sees."""
    h, w = depth.shape
    gv, gu = FOOTPRINT_GRID
    v = np.linspace(0, h - 1, gv).round().astype(int)
    u = np.linspace(0, w - 1, gu).round().astype(int)
    vv, uu = np.meshgrid(v, u, indexing="ij")
    z = np.where(valid[vv, uu], depth[vv, uu], np.nan)
    fx, fy, cx, cy = intr.as_tuple()
    p = np.stack([(uu - cx) / fx * z, (vv - cy) / fy * z, z], -1).reshape(-1, 3)
    return p @ pose[:3, :3].T + pose[:3, 3]


def select_frames(view_pose: np.ndarray, poses: np.ndarray, footprints: np.ndarray, intr: Intrinsics, k: int) -> np.ndarray:
    """Indices (into ``poses``) of the at most ``k`` frames that best cover the view, in the order
    chosen.

    Greedy cover: each pick is the frame whose footprint (``(f, m, 3)`` world points) lands in the
    most cells of a :data:`VIEW_CELLS` grid of the view not yet covered; among equals, the better
    score (the share of its footprint in the view, in front of it, times the cosine between the
    optical axes, compared in steps of :data:`SCORE_STEP`), then the nearer camera. So the first
    frames cover the whole view between them (along a video: frames on both sides of it), the rest
    add the nearest views of the same surface.
    """
    if len(poses) == 0:
        return np.zeros(0, int)
    T_cw = np.linalg.inv(view_pose)
    p = footprints @ T_cw[:3, :3].T + T_cw[:3, 3]  # (f, m, 3) in the view's camera
    z = p[..., 2]
    gv, gu = VIEW_CELLS
    with np.errstate(invalid="ignore", divide="ignore"):
        fx, fy, cx, cy = intr.as_tuple()
        u, v = fx * p[..., 0] / z + cx + 0.5, fy * p[..., 1] / z + cy + 0.5
        inside = (z > splat.NEAR) & (u >= 0) & (u < intr.width) & (v >= 0) & (v < intr.height)
        cell = np.where(inside, (v * gv // intr.height) * gu + u * gu // intr.width, gv * gu).astype(int)
    cover = np.zeros((len(poses), gv * gu + 1), bool)
    cover[np.arange(len(poses))[:, None], cell] = True
    cover = cover[:, :-1]
    counted = np.isfinite(footprints[..., 0]).sum(1)
    cos = np.clip(poses[:, :3, 2] @ view_pose[:3, 2], 0.0, 1.0)
    score = np.floor(inside.sum(1) / np.maximum(counted, 1) * cos / SCORE_STEP)
    dist = np.linalg.norm(poses[:, :3, 3] - view_pose[:3, 3], axis=1)
    left = score > 0
    covered = np.zeros(gv * gu, bool)
    chosen = []
    while len(chosen) < k and left.any():
        gain = (cover & ~covered).sum(1)
        order = np.lexsort((dist, -score, -gain))
        best = next(j for j in order if left[j])
        chosen.append(best)
        covered |= cover[best]
        left[best] = False
    return np.asarray(chosen or [int(np.argmin(dist))], int)


class Scene:
    """Host-side index of the mapped frames: each frame's pose and footprint, and a ``get(index)``
    that reads its Gaussians (device, host memory or disk). Renders any view from the
    ``cfg.frames`` frames that cover it best."""

    def __init__(self, cfg: SceneConfig, intr: Intrinsics, get):
        self.cfg, self.intr, self.get = cfg, intr, get
        self.poses: dict[int, np.ndarray] = {}
        self.points: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        return len(self.poses)

    def add(self, index: int, pose: np.ndarray, depth: np.ndarray, valid: np.ndarray) -> None:
        """Index a mapped frame (camera-to-world ``pose``, its measured depth)."""
        self.poses[index] = np.asarray(pose, np.float64)
        # float32: of the host memory that grows with the run, this index is most (9 KB a frame)
        self.points[index] = footprint(np.asarray(depth), np.asarray(valid), self.poses[index], self.intr).astype(np.float32)

    def frames_for(self, view_pose: np.ndarray) -> list[int]:
        """The mapped frames that render the view (:func:`select_frames`), in priority order
        (:func:`priority`)."""
        mapped = sorted(self.poses)
        poses = np.stack([self.poses[i] for i in mapped])
        pts = np.stack([self.points[i] for i in mapped])
        chosen = select_frames(view_pose, poses, pts, self.intr, self.cfg.frames)
        return [mapped[chosen[j]] for j in priority(view_pose, poses[chosen])]

    def stack(self, chosen: list[int], get=None) -> tuple[PixelGaussians, lie.SE3, np.ndarray]:
        """The chosen frames' (Gaussians, poses, present), padded to ``cfg.frames``."""
        get = get or self.get
        padded = chosen + [chosen[0]] * (self.cfg.frames - len(chosen))
        gs = jax.tree.map(lambda *x: np.stack(x), *[get(i) for i in padded])
        poses = jax.tree.map(lambda *x: np.stack(x), *[lie.from_matrix(self.poses[i]) for i in padded])
        return gs, poses, np.arange(self.cfg.frames) < len(chosen)

    def render(self, view_pose: np.ndarray) -> splat.Render:
        """The view at camera-to-world ``view_pose`` (numpy colour, depth, opacity)."""
        gs, poses, present = self.stack(self.frames_for(view_pose))
        out = render_scene(gs, poses, lie.from_matrix(view_pose), self.intr, present, composite=self.cfg.composite, layers=self.cfg.layers)
        return jax.tree.map(np.asarray, out)

    # checkpoints
    def arrays(self) -> tuple[list[int], dict]:
        mapped = sorted(self.poses)
        h, w = FOOTPRINT_GRID
        return mapped, {
            "scene_poses": np.asarray([self.poses[i] for i in mapped]).reshape(-1, 4, 4),
            "scene_points": np.asarray([self.points[i] for i in mapped]).reshape(-1, h * w, 3),
        }

    def restore(self, mapped: list[int], arrays: dict) -> None:
        self.poses = {i: arrays["scene_poses"][k] for k, i in enumerate(mapped)}
        self.points = {i: arrays["scene_points"][k] for k, i in enumerate(mapped)}


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class AdamState:
    """Per-frame Adam moments of the merged-map refinement (``count``: the frame's own steps)."""

    mu: PixelGaussians
    nu: PixelGaussians
    count: Float[Array, "*b"]


def adam_init(g: PixelGaussians) -> AdamState:
    zeros = jax.tree.map(jnp.zeros_like, g)
    return AdamState(mu=zeros, nu=zeros, count=jnp.zeros(g.depth.shape[:-2]))


def _learning_rates(cfg: MapConfig, scale: float) -> PixelGaussians:
    return PixelGaussians(
        rgb=cfg.lr_rgb * scale,
        log_radius=cfg.lr_radius * scale,
        opacity_logit=cfg.lr_opacity * scale,
        offset=cfg.lr_offset * scale if cfg.learn_offset else 0.0,
        depth=0.0,
    )


@functools.partial(jax.jit, static_argnames=("cfg", "composite", "layers", "lr_scale", "offsets"))
def finetune_step(
    cfg: MapConfig,
    gs: PixelGaussians,
    state: AdamState,
    poses: lie.SE3,
    present: Bool[Array, " k"],
    rgb: Float[Array, "h w 3"],
    depth: Float[Array, "h w"],
    valid: Bool[Array, "h w"],
    view_pose: lie.SE3,
    intr: Intrinsics,
    *,
    composite: str = "priority",
    layers: int = 4,
    lr_scale: float = 1.0,
    offsets: bool = False,
) -> tuple[PixelGaussians, AdamState, Float[Array, ""]]:
    """One Adam step of the merged-map refinement: the mapping loss of the training view (``rgb``,
    ``depth``, ``valid`` at ``view_pose``) rendered from frames ``gs`` (``(k, h, w)``), whose
    Gaussians all move (padding frames, ``present`` False, do not). Learning rates are the
    mapping's times ``lr_scale``; the measured depth stays fixed, the offset too unless ``offsets``
    (and learned in mapping)."""

    def loss_fn(g):
        out = render_scene(g, poses, view_pose, intr, present, composite=composite, layers=layers)
        # depth normalised by the accumulated opacity, as in mapping (partial cover is not a depth error)
        d = out.depth / jnp.maximum(out.alpha, 1e-3)
        return losses.mapping_loss(out.rgb, d, rgb, depth, valid, weight_l1=cfg.weight_l1, weight_ssim=cfg.weight_ssim, weight_depth=cfg.weight_depth)

    loss, grad = jax.value_and_grad(loss_fn)(gs)
    if not cfg.offset_at_invalid:
        grad = dataclasses.replace(grad, offset=jnp.where(gs.depth > 0, grad.offset, 0.0))
    b1, b2, eps = 0.9, 0.999, 1e-8
    count = state.count + present
    c = count[:, None, None]
    mu = jax.tree.map(lambda m, g: b1 * m + (1 - b1) * g, state.mu, grad)
    nu = jax.tree.map(lambda n, g: b2 * n + (1 - b2) * g * g, state.nu, grad)
    lr = _learning_rates(cfg, lr_scale)
    if not offsets:
        lr = dataclasses.replace(lr, offset=0.0)

    def update(p, m, n, a):
        cc = c[..., None] if p.ndim == 4 else c
        step = a * (m / (1 - b1**jnp.maximum(cc, 1))) / (jnp.sqrt(n / (1 - b2**jnp.maximum(cc, 1))) + eps)
        keep = present.reshape((-1,) + (1,) * (p.ndim - 1))
        return jnp.where(keep, p - step, p)

    new = jax.tree.map(update, gs, mu, nu, lr)
    if offsets:
        new = mapping.bound_offsets(cfg, new)
    keep = lambda a, b: jnp.where(present.reshape((-1,) + (1,) * (a.ndim - 1)), a, b)  # noqa: E731
    state = AdamState(mu=jax.tree.map(keep, mu, state.mu), nu=jax.tree.map(keep, nu, state.nu), count=count)
    return new, state, loss
