"""A built-in RGB-D sequence: a procedurally textured room with objects, ray-cast analytically.

The world frame has y pointing up with the floor at ``y = 0``; cameras use OpenCV axes (x right,
y down, z forward). The room is the inside of the axis-aligned box ``ROOM_MIN``..``ROOM_MAX``
(6 x 3 x 5 m) holding the boxes ``BOXES`` and spheres ``SPHERES``. Every surface carries a colour
texture (checker, sinusoids) in its own 2-D coordinates and a fixed, view-independent shading, so
the scene is Lambertian and photometrically consistent across views.

Rays are cast through every pixel at once in numpy. Pixel rays are ``R (K^-1 [u, v, 1])``, whose
camera z component is 1, so the ray parameter of the first hit *is* the z-depth.
"""

from __future__ import annotations

import pathlib

import numpy as np

from sgad_jax.config import DataConfig
from sgad_jax.io.base import Dataset, DatasetError
from sgad_jax.types import make_intrinsics

FPS = 30.0
ROOM_MIN = np.array([-3.0, 0.0, -2.5])
ROOM_MAX = np.array([3.0, 3.0, 2.5])
FLOOR_Y = 0.0
# Axis-aligned boxes (lo, hi) standing on the floor or on each other.
BOXES = (
    ((-1.9, 0.0, -0.9), (-0.7, 0.75, 0.1)),  # table
    ((0.4, 0.0, -2.5), (1.6, 1.8, -1.9)),  # cabinet against the back wall
    ((-0.3, 0.0, -1.4), (0.5, 0.3, -0.8)),  # low step
    ((-0.1, 0.3, -1.3), (0.3, 0.6, -1.0)),  # second step on top of it
    ((2.3, 0.0, 0.6), (3.0, 2.4, 1.4)),  # pillar against the right wall
    ((-3.0, 0.0, -2.5), (-2.2, 1.1, -1.5)),  # crate in the back-left corner
)
# Spheres (centre, radius) resting on the floor or on a box.
SPHERES = (
    ((-1.2, 1.05, -0.4), 0.3),  # on the table
    ((1.7, 0.6, -0.6), 0.6),
    ((0.9, 0.2, -0.2), 0.2),
    ((-2.6, 1.45, -2.0), 0.35),  # on the crate
)
_EPS = 1e-9
_LIGHT = (np.array([0.35, 0.8, 0.45]) / np.linalg.norm([0.35, 0.8, 0.45])).astype(np.float32)


# Hue of each surface in 1/16 turns (room faces x-, x+, floor, ceiling, z-, z+, then the boxes and
# the spheres), chosen so that surfaces that touch differ by at least 3/16 of a turn.
_HUES = (0, 13, 3, 11, 6, 9) + (14, 10, 8, 15, 7, 12) + (7, 15, 11, 2)


def _materials() -> np.ndarray:
    """Per-surface texture parameters (fixed, independent of any seed), one column per surface.

    Rows: colour A (3), colour B (3), inverse checker size (1/m), wave angular frequencies along
    u and v (rad/m), wave phase, fine-pattern angular frequency (rad/m).
    """
    count = len(_HUES)
    rng = np.random.default_rng(20240611)
    hue = np.array(_HUES)[:, None] / 16 + np.array([0.0, 1 / 3, 2 / 3])
    light = 0.55 + 0.35 * np.cos(2 * np.pi * hue)
    dark = 0.3 + 0.25 * np.cos(2 * np.pi * (hue + 0.45))  # darker, roughly complementary
    size = rng.uniform(0.15, 0.5, count)
    freq = rng.uniform(-3.0, 3.0, (count, 2))
    phase = rng.uniform(0, 2 * np.pi, count)
    fine = rng.uniform(6.0, 14.0, count)
    return np.vstack([light.T, dark.T, 1.0 / size, 2 * np.pi * freq.T, phase, 2 * np.pi * fine]).astype(np.float32)


# Surface ids: 0-5 room faces (x-, x+, floor, ceiling, z-, z+), then boxes, then spheres.
assert len(_HUES) == 6 + len(BOXES) + len(SPHERES)
_MATERIALS = _materials()  # (11, surfaces)
_BOUNDS = [(lo, hi) for lo, hi in BOXES] + [(np.subtract(c, r), np.add(c, r)) for c, r in SPHERES]  # per object


def look_at(eye, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """Camera-to-world pose (4, 4) of a camera at ``eye`` looking at ``target`` (OpenCV axes).

    Args:
        eye: (3,) camera centre in the world.
        target: (3,) a point on the optical axis.
        up: (3,) world direction that appears up in the image (must not be parallel to the view).

    Returns:
        (4, 4) float64 camera-to-world matrix with columns right, down, forward, eye.
    """
    eye, target, up = (np.asarray(a, np.float64) for a in (eye, target, up))
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([right, down, forward])
    T[:3, 3] = eye
    return T


def camera_trajectory(frames: int) -> np.ndarray:
    """The ground-truth camera-to-world poses (frames, 4, 4) of the built-in sequence at 30 fps.

    The camera walks an ellipse (1.8 x 0.8 m, period 10.5 s, 0.8-1.9 cm per frame, about 1 m in
    the first 60 frames) at eye height with a small vertical bob, looking towards the back of the
    room at a target that sways left / right and up / down (yaw and pitch oscillation, under 1.5
    degrees per frame). The motion stays in this region for any length of sequence.
    """
    t = np.arange(frames) / FPS
    eye = np.column_stack([0.9 * np.sin(0.6 * t), 1.45 + 0.1 * np.sin(1.1 * t), 1.3 + 0.4 * np.cos(0.6 * t)])
    target = np.column_stack([1.4 * np.sin(0.8 * t + 0.3), 0.9 + 0.35 * np.sin(0.65 * t), np.full_like(t, -2.0)])
    return np.stack([look_at(e, g) for e, g in zip(eye, target)]) if frames else np.zeros((0, 4, 4))


def jump_pose(metres: float, degrees: float) -> np.ndarray:
    """The camera-frame displacement (4, 4) of ``data.synthetic.jump``: ``metres`` along an oblique
    axis (right, down and back, so the view changes in every direction) and a turn of ``degrees``
    about a mostly vertical axis."""
    t = np.array([1.0, 0.5, -0.5]) / np.sqrt(1.5)
    w = np.array([0.2, 1.0, 0.1]) / np.linalg.norm([0.2, 1.0, 0.1]) * np.radians(degrees)
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    th = np.linalg.norm(w)
    R = np.eye(3) + (np.sin(th) / th * K + (1 - np.cos(th)) / th**2 * K @ K if th > 0 else 0)
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, metres * t
    return M


def _first_axis(tx: np.ndarray, ty: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Index (0, 1, 2) of the per-axis distance (x, y or else z) that equals ``t``."""
    return np.where(tx == t, 0, np.where(ty == t, 1, 2))


def _window(lo, hi, T: np.ndarray, fx, fy, cx, cy, width: int, height: int):
    """Image rows and columns (slices) that can see the box ``lo..hi``; None if none can.

    With every corner in front of the camera, a convex object projects inside the bounding
    rectangle of its corners' projections; otherwise all pixels are kept.
    """
    corners = np.array(np.meshgrid(*zip(lo, hi), indexing="ij")).reshape(3, -1)
    pc = T[:3, :3].T @ (corners - T[:3, 3:])
    if (pc[2] <= 1e-6).any():
        return slice(0, height), slice(0, width)
    u, v = fx * pc[0] / pc[2] + cx, fy * pc[1] / pc[2] + cy
    c0, c1 = max(int(np.floor(u.min())), 0), min(int(np.ceil(u.max())) + 1, width)
    r0, r1 = max(int(np.floor(v.min())), 0), min(int(np.ceil(v.max())) + 1, height)
    return (slice(r0, r1), slice(c0, c1)) if r0 < r1 and c0 < c1 else None


def _intersect(o: np.ndarray, d: np.ndarray, windows: list):
    """First hit of rays ``o + t d`` (``d``: (3, h, w)) from inside the room.

    Args:
        o: (3,) ray origin.
        d: (3, h, w) ray directions.
        windows: per object (boxes, then spheres), the (rows, cols) slices of rays to test, or None.

    Returns:
        t, surface id, axis of the face normal (3 for spheres), sign of the normal; each (h, w).
    """
    d = np.where(d == 0.0, 1e-12, d)  # no infinities times zero below
    inv = 1.0 / d
    # Room: the ray leaves the box through the face it reaches first.
    tr = [(np.where(d[k] > 0, ROOM_MAX[k], ROOM_MIN[k]) - o[k]) * inv[k] for k in range(3)]
    t = np.minimum(np.minimum(tr[0], tr[1]), tr[2])
    axis = _first_axis(tr[0], tr[1], t)
    positive = np.where(axis == 0, d[0], np.where(axis == 1, d[1], d[2])) > 0
    surf = 2 * axis + positive
    sign = np.where(positive, np.float32(-1), np.float32(1))  # inward normal
    for k, ((lo, hi), win) in enumerate(zip(BOXES, windows)):  # slab test from outside
        if win is None:
            continue
        dw, iw, tw = d[(slice(None), *win)], inv[(slice(None), *win)], t[win]
        near, far = [], []
        for a in range(3):
            t1, t2 = (lo[a] - o[a]) * iw[a], (hi[a] - o[a]) * iw[a]
            near.append(np.minimum(t1, t2))
            far.append(np.maximum(t1, t2))
        tn = np.maximum(np.maximum(near[0], near[1]), near[2])
        hit = (tn <= np.minimum(np.minimum(far[0], far[1]), far[2])) & (tn > _EPS) & (tn < tw)
        if hit.any():
            ax = _first_axis(near[0][hit], near[1][hit], tn[hit])
            tw[hit], surf[win][hit], axis[win][hit] = tn[hit], 6 + k, ax
            sign[win][hit] = -np.sign(dw[:, hit][ax, np.arange(len(ax))])
    for k, ((c, r), win) in enumerate(zip(SPHERES, windows[len(BOXES) :])):
        if win is None:
            continue
        dw, tw = d[(slice(None), *win)], t[win]
        oc = o - np.asarray(c)
        b = dw[0] * oc[0] + dw[1] * oc[1] + dw[2] * oc[2]
        aa = dw[0] * dw[0] + dw[1] * dw[1] + dw[2] * dw[2]
        disc = b * b - aa * (oc @ oc - r * r)
        ts = (-b - np.sqrt(np.maximum(disc, 0.0))) / aa
        hit = (disc > 0) & (ts > _EPS) & (ts < tw)
        tw[hit], surf[win][hit], axis[win][hit] = ts[hit], 6 + len(BOXES) + k, 3
    return t, surf, axis, sign


def _shade(p: np.ndarray, surf: np.ndarray, axis: np.ndarray, sign: np.ndarray) -> np.ndarray:
    """Colour (3, n) in [0, 1] of hit points ``p`` ((3, n)) from their surface's texture and normal.

    Texture coordinates (u, v) are metres in the surface's own 2-D frame: (z, y), (x, z) and (x, y)
    on faces normal to x, y and z; longitude and colatitude (times the radius) on a sphere.
    """
    p = p.astype(np.float32)
    u = np.where(axis == 0, p[2], p[0])
    v = np.where(axis == 1, p[2], p[1])
    lit = np.where(axis == 0, _LIGHT[0], np.where(axis == 1, _LIGHT[1], _LIGHT[2])) * sign  # cos(normal, light)
    sph = np.flatnonzero(axis == 3)
    if len(sph):
        k = surf[sph] - 6 - len(BOXES)
        centres = np.array([c for c, _ in SPHERES], np.float32)[k].T
        radii = np.array([r for _, r in SPHERES], np.float32)[k]
        q = (p[:, sph] - centres) / radii  # unit normal
        lit[sph] = _LIGHT @ q
        u[sph] = radii * np.arctan2(q[2], q[0])
        v[sph] = radii * np.arccos(np.clip(q[1], -1.0, 1.0))
    m = np.take(_MATERIALS, surf, axis=1)
    checker = (np.floor(u * m[6]) + np.floor(v * m[6])).astype(np.int32) & 1
    wave = np.sin(m[7] * u + m[8] * v + m[9])
    fine = np.sin(m[10] * u) * np.sin(m[10] * v)
    gain = (0.825 + 0.175 * wave) * (0.9 + 0.1 * fine) * (0.7 + 0.3 * lit)  # fixed, view-independent shading
    return np.where(checker.astype(bool), m[3:6], m[0:3]) * gain


def raycast(T_wc: np.ndarray, fx: float, fy: float, cx: float, cy: float, width: int, height: int):
    """Render the built-in scene from an arbitrary camera.

    Args:
        T_wc: (4, 4) camera-to-world pose (OpenCV axes); the camera must be inside the room.
        fx, fy, cx, cy: pinhole intrinsics in pixels.
        width, height: image size in pixels.

    Returns:
        rgb: (height, width, 3) uint8 colour.
        depth: (height, width) float32 z-depth (metres) of the first surface hit by each pixel's ray.
    """
    T = np.asarray(T_wc, np.float64)
    o = T[:3, 3]
    if not ((o > ROOM_MIN).all() and (o < ROOM_MAX).all()):
        raise ValueError(f"camera centre {o} is outside the room {ROOM_MIN}..{ROOM_MAX}")
    x = (np.arange(width) - cx) / fx
    y = (np.arange(height) - cy) / fy
    R = T[:3, :3]  # world direction of pixel (u, v): R [x_u, y_v, 1]
    d = R[:, 0, None, None] * x + R[:, 1, None, None] * y[:, None] + R[:, 2, None, None]
    windows = [_window(lo, hi, T, fx, fy, cx, cy, width, height) for lo, hi in _BOUNDS]
    t, surf, axis, sign = _intersect(o, d, windows)
    colour = _shade((o[:, None, None] + t * d).reshape(3, -1), surf.ravel(), axis.ravel(), sign.ravel())
    rgb = (np.clip(colour, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8).T.reshape(height, width, 3)
    return rgb, t.astype(np.float32)


class SyntheticDataset(Dataset):
    """The built-in textured room (``data.layout = synthetic`` or an empty ``data.path``).

    Frames are rendered on demand from ``cfg.synthetic`` (frames, width, height, depth_noise, seed).
    Ground truth is exact; timestamps are ``index / 30``. With ``depth_noise > 0`` depth gets
    Gaussian noise of standard deviation ``depth_noise * depth`` and about 1% of pixels are missing
    (0); both are deterministic functions of the seed and the frame index. Colour is noise-free.
    """

    layout = "synthetic"

    def __init__(self, cfg: DataConfig):
        super().__init__(pathlib.Path("synthetic"), cfg)
        s = cfg.synthetic
        if s.frames <= 0:
            raise DatasetError(f"{self.root}: data.synthetic.frames must be > 0, got {s.frames}")
        if s.width < 16 or s.height < 16:
            raise DatasetError(f"{self.root}: data.synthetic image size must be at least 16x16, got {s.width}x{s.height}")
        if not np.isfinite(s.depth_noise) or s.depth_noise < 0:
            raise DatasetError(f"{self.root}: data.synthetic.depth_noise must be >= 0, got {s.depth_noise}")
        if s.seed < 0:
            raise DatasetError(f"{self.root}: data.synthetic.seed must be >= 0, got {s.seed}")
        self.synthetic = s
        # The sensor's true intrinsics: frames are rendered with these even if data.intrinsics overrides them.
        self.camera = make_intrinsics(0.9 * s.width, 0.9 * s.width, (s.width - 1) / 2, (s.height - 1) / 2, s.width, s.height)
        self.intrinsics_full = self.camera
        self.timestamps_raw = np.arange(s.frames, dtype=np.float64) / FPS
        self.gt_poses_raw = camera_trajectory(s.frames)
        if s.jump_frame > 0:
            if len(s.jump) != 2:
                raise DatasetError(f"{self.root}: data.synthetic.jump is (metres, degrees), got {s.jump}")
            self.gt_poses_raw[s.jump_frame :] = self.gt_poses_raw[s.jump_frame :] @ jump_pose(*s.jump)
        self._finish_init()

    def _num_raw(self) -> int:
        return self.synthetic.frames

    def _load_raw(self, j: int) -> tuple[np.ndarray, np.ndarray]:
        s = self.synthetic
        rgb, depth = raycast(self.gt_poses_raw[j], *self.camera.as_tuple(), s.width, s.height)
        if s.depth_noise > 0:
            rng = np.random.default_rng([s.seed, j])
            noise = rng.standard_normal(depth.shape, dtype=np.float32)
            depth = depth * (1.0 + np.float32(s.depth_noise) * noise)
            depth[(rng.random(depth.shape) < 0.01) | (depth <= 0)] = 0.0
        return rgb, depth.astype(np.float32)
