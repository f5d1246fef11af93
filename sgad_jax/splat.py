"""Differentiable splatting of pixel-aligned Gaussians (the appearance branch's renderer).

The image model is 3DGS's front-to-back alpha compositing of isotropic 3D Gaussians projected by
the EWA approximation (2D covariance ``r^2 J J^T + 0.3 I``), with one precise truncation rule that
makes a tile-free, sort-free renderer possible: **Gaussian j contributes to pixel p only if p lies
in the window of size K centred on the pixel nearest to j's projected centre**, the window being the
diamond ``|dx| + |dy| <= K // 2`` (K = 3: the pixel and its 4 neighbours). A Gaussian's projected
sigma is radius / 3 (radius D / f at first: a third of a pixel) widened by the 0.1 px^2 dilation, so
the diamond's missing corners carry about 1% of its weight, and it has 5 candidates per layer
instead of 9: the C^2 compositing terms drop from 81 to 25. The reference renderer
(:mod:`sgad_jax.splat_ref`) implements the same rule densely and is the test oracle.

Two ways of building each pixel's candidate list, both composited the same way:

Candidate lists are "layers": slot images of projected attributes covering the image plus a margin
of ``K // 2`` pixels on every side (Gaussians centred just outside the image still reach it).

* **own view** (:func:`render_own`): a frame's Gaussian (v, u) projects exactly onto pixel (v, u) of
  its own camera, so the candidates of pixel p are the source pixels in the window around p: static shifted
  slices, no binning. It stays exact for target poses near the frame's own pose (the window is fixed,
  the projected centres move), which is what pose gradients need.
* **any view** (:func:`bin_layers` + :func:`gather_layers`): each pixel keeps the ``layers`` nearest
  Gaussians whose projected centre rounds onto it, found by ``layers`` passes of an int32 scatter-min
  on a (quantised log-depth, index) key; the window of these slot images gives the candidates.
  Binning is integer (no gradient) and can be reused across optimiser steps; attributes are gathered
  differentiably. Gaussians beyond the ``layers`` nearest of a pixel are dropped (with opaque
  surfaces they are hidden anyway).

Compositing is sort-free and exact: ``T_j = exp(sum_k [k before j] log(1 - alpha_k))`` over a
pixel's C candidates, with "before" meaning a smaller order key (the depth in the view the
Gaussian would have at its measured depth, see :func:`project`), ties broken by candidate index.
A per-pixel sort is much slower on XLA:CPU.

Layout: per-Gaussian attributes are lists of A arrays in the order of :data:`ATTRS` (stacking
them into one array cost more than compositing on XLA:CPU); images come out as ``(h, w, 3)`` colour, ``(h, w)`` depth and accumulated opacity.
Poses are camera-to-world :class:`jaxlie.SE3`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from sgad_jax import lie
from sgad_jax.types import Intrinsics, PixelGaussians

#: Rows of a projected-attribute array: centre (u, v) in pixels, z-depth, the compositing order key
#: (the z-depth the Gaussian would have at its *measured* depth, offset zero: see :func:`project`),
#: the conic (inverse 2D covariance) ``a, b, c`` of ``a du^2 + 2 b du dv + c dv^2``, opacity, colour.
ATTRS = ("u", "v", "z", "key", "conic_a", "conic_b", "conic_c", "opacity", "r", "g", "b")
NUM_ATTRS = len(ATTRS)
NEAR = 0.01  # metres; Gaussians closer than this to the camera are culled
DILATION = 0.1  # pixels^2 added to the projected covariance (3DGS's low-pass filter)
RADIUS_SIGMAS = 3.0  # a Gaussian's radius is its 3-sigma extent (as a 3DGS splat's screen radius)
MAX_ALPHA = 0.99
_EMPTY = jnp.iinfo(jnp.int32).max


class Render(NamedTuple):
    """A rendered view: colour (h, w, 3), z-depth (h, w) and accumulated opacity (h, w).

    Depth is alpha-blended (not normalised by the accumulated opacity), as in 3DGS-based SLAM.
    """

    rgb: Float[Array, "h w 3"]
    depth: Float[Array, "h w"]
    alpha: Float[Array, "h w"]


def over(front: Render, back: Render) -> Render:
    """``front`` composited over ``back``."""
    rest = 1.0 - front.alpha
    return Render(rgb=front.rgb + rest[..., None] * back.rgb, depth=front.depth + rest * back.depth, alpha=front.alpha + rest * back.alpha)


def surface_depth(r: Render, min_alpha: float = 1e-3) -> Float[Array, "h w"]:
    """The depth of the rendered surface: the blended depth over the accumulated opacity (a pixel
    covered at opacity 0.9 would otherwise read 10% too near); 0 where nothing is rendered."""
    return jnp.where(r.alpha > min_alpha, r.depth / jnp.maximum(r.alpha, min_alpha), 0.0)


def rays(g: PixelGaussians, intr: Intrinsics, v0=0, u0=0) -> tuple[Float[Array, "1 w"], Float[Array, "h 1"]]:
    """``(x / z, y / z)`` of the pixel rays of a frame's Gaussians (or of a crop of them whose first
    pixel is (``v0``, ``u0``)): Gaussian (v, u) sits at ``z * (xz[u], yz[v], 1)`` in its camera,
    ``z = |depth + offset|``."""
    h, w = g.depth.shape[-2:]
    dtype = g.depth.dtype
    xz = ((jnp.arange(w, dtype=dtype) + u0 - intr.cx) / intr.fx)[None, :]
    yz = ((jnp.arange(h, dtype=dtype) + v0 - intr.cy) / intr.fy)[:, None]
    return xz, yz


def project(
    g: PixelGaussians, src_pose: lie.SE3, dst_pose: lie.SE3, intr: Intrinsics, v0=0, u0=0, *, as_rows: bool = False
) -> Float[Array, "A h w"]:
    """Attributes (:data:`ATTRS`) of a frame's Gaussians (or a crop of them starting at pixel
    (``v0``, ``u0``)) seen from camera ``dst_pose``; ``as_rows``: as a list of the A images.

    Culled Gaussians (behind the near plane) get opacity 0. Gaussians are binned and composited in
    the order of ``key``, their depth in the view had they no offset: an offset moves a Gaussian
    along its own pixel's ray, within the sensor's depth error, and in another view a fraction of a
    pixel, while ordered by ``z`` it decides which of two neighbouring Gaussians of a surface hides
    the other, an order the fit of one view learns and no other view shares (as in the own view,
    see :func:`render_own`; measured in docs/method.md).
    """
    R, t = lie.rotation_components(dst_pose.inverse() @ src_pose)
    rows = _project(g, *rays(g, intr, v0, u0), R, t, intr.fx, intr.fy, intr.cx, intr.cy)
    return rows if as_rows else jnp.stack(rows)


def _ewa_parts(x, y, z, radius, fx, fy, cx, cy):
    """Centre (u, v), z-depth (1 behind the near plane) and conic (a, b, c) of Gaussians at camera
    coordinates (x, y, z) with 3-sigma ``radius``, and the intermediates their gradient uses."""
    front = z > NEAR
    zs = jnp.where(front, z, 1.0)
    iz = 1.0 / zs
    xz, yz = x * iz, y * iz
    # EWA: Sigma_2D = r^2 J J^T + dilation, J = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]].
    r2 = jnp.square(radius / RADIUS_SIGMAS) * iz * iz
    s_uu = r2 * fx**2 * (1.0 + xz * xz) + DILATION
    s_vv = r2 * fy**2 * (1.0 + yz * yz) + DILATION
    s_uv = r2 * fx * fy * xz * yz
    det = s_uu * s_vv - s_uv * s_uv
    out = (fx * x * iz + cx, fy * y * iz + cy, zs, s_vv / det, -s_uv / det, s_uu / det)
    return out, (front, iz, xz, yz, r2)


def _camera_points(g: PixelGaussians, xz, yz, R, t):
    """Centres of Gaussians (on rays ``(xz, yz, 1)`` of their camera) in a camera at ``(R, t)``."""
    z = g.z
    p = (xz * z, yz * z, z)
    return tuple(R[i, 0] * p[0] + R[i, 1] * p[1] + R[i, 2] * p[2] + t[i] for i in range(3))


@jax.custom_vjp
def _project(g: PixelGaussians, xz, yz, R, t, fx, fy, cx, cy) -> list[Float[Array, "h w"]]:
    """The :data:`ATTRS` images of :func:`project`. Its backward pass recomputes the forward from
    the inputs and differentiates the EWA projection by hand: autodiff kept a dozen intermediate
    images alive and doubled the projection gradient's scratch memory."""
    # Materialised once, stacked: XLA would otherwise recompute the transform inside each attribute row.
    x, y, z = jax.lax.optimization_barrier(jnp.stack(_camera_points(g, xz, yz, R, t)))
    u, v, zs, ca, cb, cc = _ewa_parts(x, y, z, g.radius, fx, fy, cx, cy)[0]
    opacity = jnp.where(z > NEAR, g.opacity, 0.0)
    # The same arithmetic as z: with offsets fixed the order is bit for bit the depth order.
    key = _camera_points(dataclasses.replace(g, offset=jnp.zeros_like(g.offset)), xz, yz, R, t)[2]
    return [u, v, zs, key, ca, cb, cc, opacity, *(g.rgb[..., c] for c in range(3))]


def _project_fwd(*args):
    return _project(*args), args


def _project_bwd(args, cts):
    g, xz, yz, R, t, fx, fy, cx, cy = args
    gu, gv, gz, _, gca, gcb, gcc, gop = cts[:8]  # the order key has no gradient
    (x, y, z), pull_points = jax.vjp(_camera_points, g, xz, yz, R, t)
    x, y, z = jax.lax.optimization_barrier(jnp.stack((x, y, z)))
    radius, pull_radius = jax.vjp(lambda g: g.radius, g)
    _, pull_opacity = jax.vjp(lambda g: g.opacity, g)
    (_, _, _, ca, cb, cc), (front, iz, xz_, yz_, r2) = _ewa_parts(x, y, z, radius, fx, fy, cx, cy)
    # Conic C = S^-1, so dC = -C dS C: the gradient with respect to the covariance S is
    # H = -C G C, G = [[gca, gcb / 2], [gcb / 2, gcc]]; s_uv sits in both off-diagonal entries.
    m00, m01 = gca * ca + 0.5 * gcb * cb, gca * cb + 0.5 * gcb * cc
    m10, m11 = 0.5 * gcb * ca + gcc * cb, 0.5 * gcb * cb + gcc * cc
    g_uu = -(ca * m00 + cb * m10)
    g_vv = -(cb * m01 + cc * m11)
    g_uv = -2.0 * (ca * m01 + cb * m11)
    fxx, fyy, fxy = fx * fx, fy * fy, fx * fy
    g_r2 = g_uu * fxx * (1.0 + xz_ * xz_) + g_vv * fyy * (1.0 + yz_ * yz_) + g_uv * fxy * xz_ * yz_
    g_xz = gu * fx + r2 * (g_uu * fxx * 2.0 * xz_ + g_uv * fxy * yz_)
    g_yz = gv * fy + r2 * (g_vv * fyy * 2.0 * yz_ + g_uv * fxy * xz_)
    g_iz = g_r2 * 2.0 * jnp.square(radius / RADIUS_SIGMAS) * iz + g_xz * x + g_yz * y
    g_z = jnp.where(front, gz - g_iz * iz * iz, 0.0)
    g_radius = g_r2 * 2.0 * jnp.square(iz / RADIUS_SIGMAS) * radius

    def total(gr, like):
        """The gradient of a scalar (or broadcast) input: a sum, also over the manual axes
        (``shard_map``) along which ``like`` is replicated and ``gr`` is not."""
        out = jnp.sum(gr, axis=tuple(range(gr.ndim - jnp.ndim(like)))).reshape(jnp.shape(like))
        axes = tuple(sorted(_varying_axes(out) - _varying_axes(like)))
        return jax.lax.psum(out, axes) if axes else out

    g_fx = total(gu * xz_ + r2 * (g_uu * 2.0 * fx * (1.0 + xz_ * xz_) + g_uv * fy * xz_ * yz_), fx)
    g_fy = total(gv * yz_ + r2 * (g_vv * 2.0 * fy * (1.0 + yz_ * yz_) + g_uv * fx * xz_ * yz_), fy)
    d_g, d_xz, d_yz, d_R, d_t = pull_points((g_xz * iz, g_yz * iz, g_z))
    d_rgb = dataclasses.replace(jax.tree.map(jnp.zeros_like, g), rgb=jnp.stack(cts[8:], axis=-1))
    d_g = jax.tree.map(lambda *xs: sum(xs), d_g, pull_radius(g_radius)[0], pull_opacity(jnp.where(front, gop, 0.0))[0], d_rgb)
    return d_g, d_xz, d_yz, d_R, d_t, g_fx, g_fy, total(gu, cx), total(gv, cy)


_project.defvjp(_project_fwd, _project_bwd)


def _varying_axes(x) -> set[str]:
    """The ``shard_map`` mesh axes along which ``x`` varies (JAX's manual axis type)."""
    aval = jax.typeof(x)
    mat = getattr(aval, "manual_axis_type", None)
    return set(mat.varying) if mat is not None else set(getattr(aval, "vma", ()))


def _offset_classes(window: int) -> tuple[list[tuple[int, int, int]], list[int]]:
    """The distinct ``(du^2, du dv, dv^2)`` of a window's candidate offsets (a Gaussian seen from
    a pixel of its own window, in its own view at its own pose, is this far from the pixel's
    centre), and the class of each offset of :func:`window_offsets`."""
    r = window // 2
    keys = [((r - dx) ** 2, (r - dx) * (r - dy), (r - dy) ** 2) for dy, dx in window_offsets(window)]
    classes = sorted(set(keys))
    return classes, [classes.index(k) for k in keys]


def project_own(g: PixelGaussians, intr: Intrinsics, window: int, v0=0, u0=0) -> list[Float[Array, "h w"]]:
    """Attributes of a frame's Gaussians (or a crop from pixel (``v0``, ``u0``)) in their own view
    at their own pose, where Gaussian (v, u) projects exactly onto pixel (v, u): z-depth, the
    compositing order key (the measured depth ``D``, see :func:`render_own`), then the opacity
    (clamped to :data:`MAX_ALPHA`) it has at each offset class of :func:`_offset_classes` (the
    candidate windows are fixed, so these are per-Gaussian images), then colour.

    The same image model as :func:`project` followed by :func:`_alpha`, without positions:
    compositing needs no exponential per candidate and no position gradients.
    """
    z = g.z
    front = z > NEAR
    zs = jnp.where(front, z, 1.0)
    xz, yz = rays(g, intr, v0, u0)
    r2 = jnp.square(g.radius / (RADIUS_SIGMAS * zs))
    s_uu = r2 * intr.fx**2 * (1.0 + xz * xz) + DILATION
    s_vv = r2 * intr.fy**2 * (1.0 + yz * yz) + DILATION
    s_uv = r2 * intr.fx * intr.fy * (xz * yz)
    det = s_uu * s_vv - s_uv * s_uv
    opacity = jnp.where(front, g.opacity, 0.0)
    alphas = []
    for du2, dudv, dv2 in _offset_classes(window)[0]:
        if du2 == dudv == dv2 == 0:
            raw = opacity
        else:
            raw = opacity * jnp.exp(-0.5 * (du2 * s_vv - 2 * dudv * s_uv + dv2 * s_uu) / det)
        alphas.append(jnp.minimum(raw, MAX_ALPHA))
    return [zs, g.depth, *alphas, *(g.rgb[..., c] for c in range(3))]


def bin_layers(
    attrs: Sequence[Float[Array, " n"]], intr: Intrinsics, layers: int, *, window: int = 3, near: float = NEAR, far: float = 100.0
) -> Int[Array, "l H W"]:
    """Indices of the ``layers`` nearest Gaussians whose centre rounds onto each slot (-1: none); the
    slots cover the image and a margin of ``window // 2``.

    Integer work only (the result carries no gradient). Depth order is by the log of the order key
    (see :func:`project`) quantised to the bits left over by the index in an int32 key, then by index.
    """
    attrs = jax.lax.stop_gradient(attrs)
    n = attrs[0].shape[-1]
    r = window // 2
    h, w = intr.height + 2 * r, intr.width + 2 * r
    id_bits = max(1, math.ceil(math.log2(n)))
    depth_bits = 31 - id_bits
    if depth_bits < 6:
        raise ValueError(f"too many Gaussians to bin in one call: {n}")
    u = jnp.round(attrs[0]).astype(jnp.int32) + r
    v = jnp.round(attrs[1]).astype(jnp.int32) + r
    z = attrs[3]
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h) & (attrs[7] > 0) & (attrs[2] > near)
    pix = jnp.where(inside, v * w + u, h * w)  # out-of-image Gaussians go to a dump bucket
    levels = (1 << depth_bits) - 1
    q = jnp.clip(jnp.log(jnp.maximum(z, near) / near) / math.log(far / near), 0.0, 1.0) * levels
    key = (q.astype(jnp.int32) << id_bits) | jnp.arange(n, dtype=jnp.int32)
    key = jnp.where(inside, key, _EMPTY)
    out = []
    for _ in range(layers):
        best = jnp.full((h * w + 1,), _EMPTY, jnp.int32).at[pix].min(key)
        won = key == best[pix]
        key = jnp.where(won, _EMPTY, key)
        best = best[: h * w]
        out.append(jnp.where(best == _EMPTY, -1, best & ((1 << id_bits) - 1)))
    return jnp.stack(out).reshape(layers, h, w)


@jax.custom_vjp
def gather_layers(attrs: Sequence[Float[Array, " n"]], index: Int[Array, "l H W"]) -> list[Float[Array, "l H W"]]:
    """Slot images of the binned Gaussians' attributes (empty slots: all zero, so opacity 0).

    ``index`` must hold each Gaussian at most once (as :func:`bin_layers` does): the gradient is
    then a gather too, by the inverse map (the slot of each Gaussian), instead of a scatter-add.
    """
    safe = jnp.maximum(index, 0)
    return [jnp.where(index >= 0, a[safe], 0.0) for a in attrs]


def _gather_layers_fwd(attrs, index):
    return gather_layers(attrs, index), (index, attrs[0].shape[-1])


def _gather_layers_bwd(res, grads):
    index, n = res
    flat = index.reshape(-1)
    slot = jnp.full((n,), -1, jnp.int32).at[jnp.where(flat >= 0, flat, n)].set(jnp.arange(flat.size, dtype=jnp.int32), mode="drop")
    safe = jnp.maximum(slot, 0)
    return [jnp.where(slot >= 0, g.reshape(-1)[safe], 0.0) for g in grads], None


gather_layers.defvjp(_gather_layers_fwd, _gather_layers_bwd)


def window_offsets(window: int) -> list[tuple[int, int]]:
    """Slot offsets ``(dy, dx)`` (from the window's corner) of a pixel's candidates: the diamond
    ``|dy - r| + |dx - r| <= r``, ``r = window // 2`` (for K = 3 the pixel and its 4 neighbours)."""
    r = window // 2
    return [(dy, dx) for dy in range(window) for dx in range(window) if abs(dy - r) + abs(dx - r) <= r]


def _candidates(layers: list[Float[Array, "l H W"]], window: int) -> list[list[Float[Array, "h w"]]]:
    """Candidates of every pixel (each the list of its A attribute images): the window of every
    layer, as shifted slices. ``layers`` is the list of the A attributes' slot images: on XLA:CPU
    stacking them into one array (a concatenation) cost more than compositing."""
    h, w = layers[0].shape[-2] - window + 1, layers[0].shape[-1] - window + 1
    return [
        [a[l, dy : dy + h, dx : dx + w] for a in layers]
        for l in range(layers[0].shape[0])
        for dy, dx in window_offsets(window)
    ]


def _alpha(cand, pu, pv):
    """Opacity of a candidate at every pixel, with the pieces its derivative needs."""
    u, v, z, _key, ca, cb, cc, opacity = cand[:8]
    du, dv = pu - u, pv - v
    gauss = jnp.exp(-0.5 * (ca * du * du + 2.0 * cb * du * dv + cc * dv * dv))
    raw = opacity * gauss
    return jnp.minimum(raw, MAX_ALPHA), raw, gauss, du, dv


def _in_front(zs, k, j):
    """Candidate k is composited before candidate j: nearer, or as near with a lower index."""
    return zs[k] <= zs[j] if k < j else zs[k] < zs[j]


def _forward(layers, window, row0=0, exact=False):
    """Candidates, opacities, depths, blending weights and compositing order keys of the pixels of
    ``layers`` (rows from ``row0``).

    ``layers`` hold :data:`ATTRS` (composited in the order of their keys), or with ``exact`` the own-pose
    attributes of :func:`project_own` (each candidate's opacity is then read from its offset
    class's image, ``parts`` is just it; composited in the order of the measured depths).
    """
    cands = _candidates(layers, window)
    h, w = cands[0][0].shape
    dtype = layers[0].dtype
    if exact:
        cls = _offset_classes(window)[1]
        parts = [(c[2 + cls[j % len(cls)]],) for j, c in enumerate(cands)]
        zs, keys = [c[0] for c in cands], [c[1] for c in cands]
    else:
        pv = (jnp.arange(h) + row0).astype(dtype)[:, None]
        pu = jnp.arange(w, dtype=dtype)[None, :]
        parts = [_alpha(c, pu, pv) for c in cands]
        zs, keys = [c[2] for c in cands], [c[3] for c in cands]
    alphas = [p[0] for p in parts]
    qs = [1.0 - a for a in alphas]
    n = len(cands)
    weights = []
    for j in range(n):
        trans = jnp.ones_like(alphas[j])
        for k in range(n):
            if k != j:
                trans = trans * jnp.where(_in_front(keys, k, j), qs[k], 1.0)
        weights.append(alphas[j] * trans)
    return cands, parts, qs, zs, weights, keys


def composite(layers: Sequence[Float[Array, "l H W"]], window: int = 3) -> Render:
    """Front-to-back alpha compositing of every pixel's window candidates (sort-free, exact).

    ``layers`` (the A attributes' slot images, a list or an ``(A, l, H, W)`` array) cover the image
    plus a margin of ``window // 2`` pixels on each side. Transmittance
    is ``T_j = prod_k [k in front of j] (1 - alpha_k)``; the C^2 pairwise terms are unrolled over
    (h, w) images, which XLA:CPU fuses into single loops (a reduction over a (C, C, h, w) tensor
    is far slower). The backward pass is written by hand in the same form (autodiff of the
    unrolled graph is far slower than the forward pass).
    """
    return _composite(window, list(layers))


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _composite(window, layers):
    rgb, depth, alpha = _blend(*_forward(layers, window))
    return Render(rgb=jnp.moveaxis(rgb, 0, -1), depth=depth, alpha=alpha)


def _blend(cands, _parts, _qs, zs, weights, _keys):
    """Colour ``(3, h, w)``, depth and accumulated opacity from the candidates' blending weights."""
    rgb = jnp.stack([sum(wj * c[ch - 3] for wj, c in zip(weights, cands)) for ch in range(3)])
    return rgb, sum(wj * zj for wj, zj in zip(weights, zs)), sum(weights)


def _composite_fwd(window, layers):
    return _composite(window, layers), layers


#: Pixels per band of the backward passes (32 rows of 640), so that their temporaries stay in
#: cache; the binned path divides it by its layer count. Measured choices: docs/method.md.
BAND_PIXELS = 32 * 640


def _bands(ct: Render):
    """Row bands of a backward pass: band height, count, the rows added to complete the last band,
    and the image cotangents ``(5, rows, w)`` (colour, depth, opacity) padded to whole bands."""
    h, w = ct.depth.shape
    band = min(h, max(1, BAND_PIXELS // w))
    nb = -(-h // band)
    extra = nb * band - h
    g_img = jnp.concatenate([jnp.moveaxis(ct.rgb, -1, 0), ct.depth[None], ct.alpha[None]])
    return band, nb, extra, jnp.pad(g_img, ((0, 0), (0, extra), (0, 0)))


def _composite_bwd(window, layers, ct):
    """Backward pass, band by band: a loop over bands of slot rows, each band's gradients written
    in place into the slot-gradient images (no overlap-add afterwards, no padded copy of the layers).

    The slots of rows ``[y0, y0 + band)`` are candidates of the pixel rows ``[y0 - 2r, y0 + band)``:
    each band runs the compositing backward over the ``band + 2r`` pixel rows from ``s0`` (that
    start, clamped into the image) and keeps the slot rows it has complete."""
    r = window // 2
    l, rows, wp = layers[0].shape
    g_img = jnp.concatenate([jnp.moveaxis(ct.rgb, -1, 0), ct.depth[None], ct.alpha[None]])
    # Bands shrink with the candidate count: their per-candidate images should stay in cache.
    band = max(1, min(rows - 4 * r, BAND_PIXELS // (wp * l)))
    short = band + 4 * r - rows  # > 0 only for images of fewer than 2r + 1 rows
    if short > 0:
        layers = [jnp.pad(a, ((0, 0), (0, short), (0, 0))) for a in layers]
        g_img = jnp.pad(g_img, ((0, 0), (0, short), (0, 0)))
    total = max(rows, band + 4 * r)

    def body(i, grads):
        y0 = jnp.minimum(i * band, rows - band)  # the last band overlaps its predecessor
        s0 = jnp.clip(y0 - 2 * r, 0, total - band - 4 * r)
        lay = [jax.lax.dynamic_slice_in_dim(a, s0, band + 4 * r, axis=1) for a in layers]
        g = jax.lax.dynamic_slice_in_dim(g_img, s0, band + 2 * r, axis=1)
        per = _band_bwd(window, lay, g[:3], g[3], g[4], s0)
        keep = [jax.lax.dynamic_slice_in_dim(p, y0 - s0, band, axis=1) for p in per]
        return [jax.lax.dynamic_update_slice_in_dim(a, k, y0, axis=1) for a, k in zip(grads, keep)]

    zeros = [jnp.zeros_like(a, shape=(l, total, wp)) for a in layers]  # varying like the layers under shard_map
    grads = jax.lax.fori_loop(0, -(-rows // band), body, zeros)
    return ([a[:, :rows] for a in grads],)


def _overlap_add(per_band: Array, band: int, halo: int, axis: int) -> Array:
    """Assemble per-band slot gradients ``(nb, ..., band + halo, ...)`` (rows on ``axis`` of a
    band) into one array: band i covers rows ``[i band, i band + band + halo)``, so its last
    ``halo`` rows are added onto the first rows of band i + 1."""
    rows = axis + 1
    take = lambda x, a, b: jax.lax.slice_in_dim(x, a, b, axis=rows)  # noqa: E731
    tops, tails = take(per_band, 0, band), take(per_band, band, band + halo)
    if halo:
        first = jax.lax.slice_in_dim(tops, 1, None, axis=0)
        head = take(first, 0, halo) + jax.lax.slice_in_dim(tails, 0, -1, axis=0)
        tops = jnp.concatenate([jax.lax.slice_in_dim(tops, 0, 1, axis=0),
                                jnp.concatenate([head, take(first, halo, band)], axis=rows)], axis=0)
    tops = jnp.moveaxis(tops, 0, axis)  # (..., nb, band, ...)
    shape = tops.shape[:axis] + (tops.shape[axis] * band,) + tops.shape[axis + 2 :]
    return jnp.concatenate([tops.reshape(shape), tails[-1]], axis=axis)


def _band_bwd(window, layers, g_rgb, g_depth, g_acc, row0, exact=False):
    """Gradients of one band's slots (a list of A images ``(l, band + 2r, W)``) from the band's
    image cotangents (``exact``: own-pose attributes, see :func:`_forward`)."""
    cands, parts, qs, zs, weights, keys = _forward(layers, window, row0, exact)
    n = len(cands)
    parts = [list(p) for p in jax.lax.optimization_barrier([jnp.stack(p) for p in parts])]
    # s_j: d loss / d weight_j; ws_j = weight_j s_j.
    ss = [g_rgb[0] * c[-3] + g_rgb[1] * c[-2] + g_rgb[2] * c[-1] + g_depth * zs[j] + g_acc for j, c in enumerate(cands)]
    # Materialise the per-candidate images once: left to itself, XLA fuses (and so recomputes) the
    # C-term products into each of their C consumers.
    if exact:
        # Here qs and zs are slices of the materialised layer: recomputing them is free, stacking
        # them is not (and the general path is slower stacked).
        weights, ss = (list(x) for x in jax.lax.optimization_barrier((jnp.stack(weights), jnp.stack(ss))))
    else:
        weights, ss, qs, zs = (list(x) for x in jax.lax.optimization_barrier(
            (jnp.stack(weights), jnp.stack(ss), jnp.stack(qs), jnp.stack(zs))))
    ws = [wj * sj for wj, sj in zip(weights, ss)]
    g_alphas = []
    for j in range(n):
        alpha = parts[j][0]
        # d loss / d alpha_j = T_j s_j - (sum of ws_m over candidates m behind j) / (1 - alpha_j)
        behind = sum(jnp.where(_in_front(keys, j, m), ws[m], 0.0) for m in range(n) if m != j)
        trans = weights[j] / jnp.maximum(alpha, 1e-30)
        g_alpha = trans * ss[j] - behind / qs[j]
        # exact: the clamp to MAX_ALPHA is differentiated with the attributes (project_own)
        g_alphas.append(g_alpha if exact else jnp.where(parts[j][1] < MAX_ALPHA, g_alpha, 0.0))
    g_alphas = list(jax.lax.optimization_barrier(jnp.stack(g_alphas)))
    # Each candidate's gradient rows and the attributes (indices into the layers) they belong to.
    grads, rows = [], []
    cls = _offset_classes(window)[1]
    for j in range(n):
        colour = [weights[j] * g_rgb[ch] for ch in range(3)]
        if exact:
            grads.append(jnp.stack([weights[j] * g_depth, g_alphas[j], *colour]))
            a = len(layers)
            rows.append([0, 2 + cls[j % len(cls)], a - 3, a - 2, a - 1])
            continue
        alpha, raw, gauss, du, dv = parts[j]
        u, v, z, _key, ca, cb, cc, opacity = cands[j][:8]
        g_power = -g_alphas[j] * raw
        grads.append(
            jnp.stack(
                [
                    -g_power * (ca * du + cb * dv),
                    -g_power * (cb * du + cc * dv),
                    weights[j] * g_depth,
                    0.5 * g_power * du * du,
                    g_power * du * dv,
                    0.5 * g_power * dv * dv,
                    g_alphas[j] * gauss,
                    *colour,
                ]
            )
        )
        rows.append([a for a in range(NUM_ATTRS) if ATTRS[a] != "key"])  # the key has no gradient
    if layers[0].shape[0] == 1:
        # One layer: materialising the per-candidate gradients is faster; with more layers their
        # images no longer fit in cache and letting XLA fuse them into the slot sums is faster.
        grads = list(jax.lax.optimization_barrier(jnp.stack(grads)))
    # Scatter the candidates' gradients back onto their slots (the transpose of _candidates).
    k = window
    offsets = window_offsets(window)
    no = len(offsets)

    def slots(a, l):
        terms = [
            jnp.pad(grads[j][i], ((dy, k - 1 - dy), (dx, k - 1 - dx)))
            for j, (dy, dx) in zip(range(l * no, (l + 1) * no), offsets)
            for i, attr in enumerate(rows[j])
            if attr == a
        ]
        return sum(terms) if terms else jnp.zeros_like(layers[a][l])

    return [jnp.stack([slots(a, l) for l in range(layers[0].shape[0])]) for a in range(len(layers))]


_composite.defvjp(_composite_fwd, _composite_bwd)


def render_own(g: PixelGaussians, pose: lie.SE3, intr: Intrinsics, *, window: int = 3, view_pose: lie.SE3 | None = None) -> Render:
    """Fast path: a frame's Gaussians (at camera-to-world ``pose``) rendered into its own view.

    Without ``view_pose`` the frame is seen at its own pose, where every Gaussian projects exactly
    onto its pixel: the image does not depend on ``pose`` (its gradient is zero) and compositing
    reads each candidate's opacity from per-Gaussian images (:func:`project_own`). There a pixel's
    candidates are composited in the order of their *measured* depths ``D`` (the order the sensor
    saw), not of ``|D + offset|``: an offset moves a Gaussian along its own pixel's ray, which in
    this view changes its footprint and depth, not which window neighbour it hides. (Ordered by
    ``|D + offset|``, offsets of a few millimetres reorder neighbours on a flat surface, where
    measured depths are equal or nearly so, from one Adam step to the next, and the colour fit
    chatters: on 10 TUM frames at 320x240, 42.6 dB against 48.8 dB with this rule.)
    A ``view_pose`` may differ slightly from ``pose``: the candidate windows stay at the source
    pixels, the projected centres move, so gradients with respect to either pose are exact; the
    candidates are then composited in the order of their keys, as in any other view (:func:`project`).
    The backward pass runs in row bands of about :data:`BAND_PIXELS` pixels, the projection's included.
    """
    exact = view_pose is None
    return _render_own(window, exact, g, pose, pose if exact else view_pose, intr)


def _pad_gaussians(g: PixelGaussians, r: int, extra: int) -> PixelGaussians:
    """The Gaussians padded by ``r`` rows and columns on each side and ``extra`` more rows at the
    bottom (depth 1, the rest 0; :func:`_own_band` empties those slots)."""

    def pad(x, value=0.0):
        return jnp.pad(x, [(r, r + extra), (r, r)] + [(0, 0)] * (x.ndim - 2), constant_values=value)

    return dataclasses.replace(jax.tree.map(pad, g), depth=pad(g.depth, 1.0))


def _own_band(window, exact, gb, row, pose, view_pose, intr):
    """The own-view candidate layer ``(A, 1, band + 2r, W + 2r)`` of pixel rows
    ``[row, row + band)``, from the padded Gaussians' rows ``[row, row + band + 2r)``: slot (v, u)
    holds Gaussian (v - r, u - r); slots outside the image are empty (all attributes 0).
    ``exact``: the attributes of :func:`project_own` (the poses are not used)."""
    r = window // 2
    if exact:
        attrs = project_own(gb, intr, window, row - r, -r)
    else:
        attrs = project(gb, pose, view_pose, intr, row - r, -r, as_rows=True)
    hb, wb = gb.depth.shape
    v = jnp.arange(hb) + row - r
    u = jnp.arange(wb) - r
    inside = ((v >= 0) & (v < intr.height))[:, None] & ((u >= 0) & (u < intr.width))[None, :]
    return [jnp.where(inside, a, 0.0)[None] for a in attrs]


@functools.partial(jax.custom_vjp, nondiff_argnums=(0, 1))
def _render_own(window, exact, g, pose, view_pose, intr) -> Render:
    # The forward pass in one piece: XLA:CPU runs it fastest whole (a scan over bands writes each
    # band's output in an unvectorised in-place update).
    gp = _pad_gaussians(g, window // 2, 0)
    rgb, depth, alpha = _blend(*_forward(_own_band(window, exact, gp, 0, pose, view_pose, intr), window, exact=exact))
    return Render(rgb=jnp.moveaxis(rgb, 0, -1), depth=depth, alpha=alpha)


def _render_own_fwd(window, exact, g, pose, view_pose, intr):
    return _render_own(window, exact, g, pose, view_pose, intr), (g, pose, view_pose, intr)


def _render_own_bwd(window, exact, res, ct):
    """Band by band: recompute the band's layer, composite's backward (:func:`_band_bwd`), then the
    projection's VJP; Gaussian gradients are overlap-added, pose and intrinsics gradients summed."""
    g, pose, view_pose, intr = res
    h, w = g.depth.shape[-2:]
    r = window // 2
    band, nb, extra, g_img = _bands(ct)
    gp = _pad_gaussians(g, r, extra)

    def body(acc, i):
        row = i * band
        gb = jax.tree.map(lambda x: jax.lax.dynamic_slice_in_dim(x, row, band + 2 * r, axis=0), gp)
        layer, pull = jax.vjp(lambda gb, *rest: _own_band(window, exact, gb, row, *rest), gb, pose, view_pose, intr)
        gi = jax.lax.dynamic_slice_in_dim(g_img, row, band, axis=1)
        d_gb, *d_rest = pull(_band_bwd(window, layer, gi[:3], gi[3], gi[4], row, exact))
        return jax.tree.map(jnp.add, acc, tuple(d_rest)), d_gb

    zeros = jax.tree.map(jnp.zeros_like, (pose, view_pose, intr))
    (d_pose, d_view, d_intr), per_band = jax.lax.scan(body, zeros, jnp.arange(nb))
    d_g = jax.tree.map(lambda x: _overlap_add(x, band, 2 * r, axis=0)[r : r + h, r : r + w], per_band)
    return d_g, d_pose, d_view, d_intr


_render_own.defvjp(_render_own_fwd, _render_own_bwd)


def project_frames(gs: PixelGaussians, poses: lie.SE3, view_pose: lie.SE3, intr: Intrinsics) -> list[Float[Array, " n"]]:
    """Attributes (:data:`ATTRS`, a list of A arrays) of a stack of frames' Gaussians ``(f, h, w)``
    seen from ``view_pose``, flattened."""
    rows = jax.vmap(functools.partial(project, as_rows=True), in_axes=(0, 0, None, None))(gs, poses, view_pose, intr)
    return [a.reshape(-1) for a in rows]


def render(
    gs: PixelGaussians,
    poses: lie.SE3,
    view_pose: lie.SE3,
    intr: Intrinsics,
    *,
    layers: int = 2,
    window: int = 3,
) -> Render:
    """General path: the Gaussians of frames ``gs`` (stacked, ``(f, h, w)``) at camera-to-world
    ``poses`` rendered into the camera ``view_pose`` (binned afresh)."""
    attrs = project_frames(gs, poses, view_pose, intr)
    return composite(gather_layers(attrs, bin_layers(attrs, intr, layers, window=window)), window)
