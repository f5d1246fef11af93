"""Reading a finished run's folder and writing what is derived from it (meshes, ``eval.json``).

A run folder (see :mod:`sgad_jax.pipeline`) holds ``trajectory.txt`` (the i-th pose line is run index
i), ``metrics.json`` (its ``config`` key: the resolved config), ``cameras.json`` (the intrinsics used,
after downscale), ``renders/rgb_XXXXXX.png`` and ``renders/depth_XXXXXX.png`` (16-bit millimetres)
with ``--save-renders``, and ``gaussians/frame_XXXXXX.npz``. Every problem is a one-line
:class:`~sgad_jax.io.base.DatasetError` naming the file.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import re

import cv2
import numpy as np

from sgad_jax.io.base import DatasetError
from sgad_jax.io.export import read_tum_trajectory
from sgad_jax.types import Intrinsics, make_intrinsics


def _folder(run_dir) -> pathlib.Path:
    run = pathlib.Path(run_dir)
    if not run.is_dir():
        raise DatasetError(f"{run}: run folder not found")
    return run


def read_metrics(run_dir) -> dict:
    """``metrics.json`` of a run ({} when absent)."""
    path = _folder(run_dir) / "metrics.json"
    if not path.is_file():
        return {}
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise DatasetError(f"{path}: cannot read ({e.__class__.__name__})") from None


def run_config(run_dir):
    """The run's resolved :class:`~sgad_jax.config.SLAMConfig` from ``metrics.json`` (defaults where a
    key is missing, e.g. from an older run), or None without ``metrics.json``."""
    from sgad_jax import config

    saved = read_metrics(run_dir).get("config")
    if saved is None:
        return None

    def build(cls, d):
        kwargs = {}
        for f in dataclasses.fields(cls):
            if f.name not in d:
                continue
            default = getattr(cls(), f.name)
            value = d[f.name]
            if dataclasses.is_dataclass(default):
                value = build(type(default), value)
            elif isinstance(default, tuple):
                value = tuple(value)
            kwargs[f.name] = value
        return cls(**kwargs)

    try:
        return build(config.SLAMConfig, saved)
    except (TypeError, config.ConfigError) as e:
        raise DatasetError(f"{pathlib.Path(run_dir) / 'metrics.json'}: its config cannot be read ({e})") from None


def read_cameras(run_dir) -> Intrinsics:
    """The run's intrinsics: ``cameras.json`` ({width, height, fx, fy, cx, cy}), else those of the
    dataset named in ``metrics.json``'s config (opened again, after its downscale)."""
    run = _folder(run_dir)
    path = run / "cameras.json"
    if path.is_file():
        try:
            c = json.loads(path.read_text())
            return make_intrinsics(c["fx"], c["fy"], c["cx"], c["cy"], int(c["width"]), int(c["height"]))
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise DatasetError(f"{path}: expected {{width, height, fx, fy, cx, cy}} ({e.__class__.__name__}: {e})") from None
    cfg = run_config(run)
    if cfg is None:
        raise DatasetError(f"{run}: no cameras.json and no metrics.json to find the intrinsics in")
    from sgad_jax.io.datasets import open_dataset

    return open_dataset(cfg.data).intrinsics


def read_poses(run_dir) -> np.ndarray:
    """(f, 4, 4) camera-to-world poses of ``trajectory.txt``."""
    path = _folder(run_dir) / "trajectory.txt"
    if not path.is_file():
        raise DatasetError(f"{path}: not found (not a finished run?)")
    try:
        return read_tum_trajectory(path)[1]
    except ValueError as e:
        raise DatasetError(str(e)) from None


_RENDER = re.compile(r"depth_(\d+)\.png$")


def render_indices(run_dir) -> list[int]:
    """Run indices with both a colour and a depth render, sorted.

    Raises:
        DatasetError: when there are none (the run was made without ``--save-renders``).
    """
    folder = _folder(run_dir) / "renders"
    found = sorted(int(m.group(1)) for p in folder.glob("depth_*.png") if (m := _RENDER.search(p.name)) and (folder / f"rgb_{m.group(1)}.png").is_file()) if folder.is_dir() else []
    if not found:
        raise DatasetError(f"{folder}: no rendered colour and depth (rgb_XXXXXX.png + depth_XXXXXX.png); run with --save-renders")
    return found


def read_render(run_dir, index: int) -> tuple[np.ndarray, np.ndarray]:
    """Frame ``index``'s render: colour (h, w, 3) float32 in [0, 1], depth (h, w) float32 metres (0: none)."""
    folder = pathlib.Path(run_dir) / "renders"
    rgb_path, depth_path = folder / f"rgb_{index:06d}.png", folder / f"depth_{index:06d}.png"
    rgb = cv2.imread(str(rgb_path), cv2.IMREAD_COLOR)
    if rgb is None:
        raise DatasetError(f"{rgb_path}: cannot read the image")
    depth = cv2.imread(str(depth_path), cv2.IMREAD_UNCHANGED)
    if depth is None or depth.dtype != np.uint16 or depth.ndim != 2:
        raise DatasetError(f"{depth_path}: expected a 16-bit single-channel PNG in millimetres")
    if depth.shape != rgb.shape[:2]:
        raise DatasetError(f"{depth_path}: size {depth.shape[::-1]} differs from its colour render's {rgb.shape[1::-1]}")
    return cv2.cvtColor(rgb, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0, depth.astype(np.float32) / 1000.0


class Renders:
    """The renders of a run as a re-iterable sequence of ``(rgb, depth)`` (read lazily each pass)."""

    def __init__(self, run_dir, indices):
        self.run_dir, self.indices = run_dir, list(indices)

    def __len__(self):
        return len(self.indices)

    def __iter__(self):
        for i in self.indices:
            yield read_render(self.run_dir, i)


def write_mesh_ply(path, vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray | None = None) -> None:
    """Binary little-endian PLY: vertices ``x y z`` (float32) and ``red green blue`` (uchar) when
    given, faces ``vertex_indices`` (list of int32); written atomically."""
    from plyfile import PlyData, PlyElement

    vertices = np.asarray(vertices, np.float32).reshape(-1, 3)
    fields = [("x", "f4"), ("y", "f4"), ("z", "f4")]
    if colours is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    v = np.empty(len(vertices), fields)
    v["x"], v["y"], v["z"] = vertices.T
    if colours is not None:
        c = np.asarray(colours, np.uint8).reshape(-1, 3)
        v["red"], v["green"], v["blue"] = c.T
    f = np.empty(len(faces), [("vertex_indices", "i4", (3,))])
    f["vertex_indices"] = np.asarray(faces, np.int32).reshape(-1, 3)
    path = pathlib.Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    PlyData([PlyElement.describe(v, "vertex"), PlyElement.describe(f, "face")], text=False, byte_order="<").write(str(tmp))
    os.replace(tmp, path)


def read_mesh_ply(path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``(vertices (m, 3) float64, faces (k, 3) int64, colours (m, 3) uint8 or None)`` of a PLY
    triangle mesh (polygons with more than three corners are fanned into triangles)."""
    from plyfile import PlyData

    path = pathlib.Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: mesh file not found")
    try:
        ply = PlyData.read(str(path))
        v = ply["vertex"].data
        vertices = np.stack([v["x"], v["y"], v["z"]], -1).astype(np.float64)
        names = v.dtype.names
        colours = np.stack([v["red"], v["green"], v["blue"]], -1).astype(np.uint8) if {"red", "green", "blue"} <= set(names) else None
        faces = []
        if "face" in ply:
            data = ply["face"].data
            key = "vertex_indices" if "vertex_indices" in data.dtype.names else "vertex_index"
            polys = data[key]
            try:
                arr = np.stack(polys).astype(np.int64) if len(polys) else np.zeros((0, 3), np.int64)
            except ValueError:  # mixed polygon sizes
                arr = None
            if arr is not None and arr.ndim == 2 and arr.shape[1] == 3:
                faces = arr
            else:
                faces = np.array([(p[0], p[k], p[k + 1]) for p in polys for k in range(1, len(p) - 1)], np.int64).reshape(-1, 3)
        faces = np.asarray(faces, np.int64).reshape(-1, 3)
    except DatasetError:
        raise
    except Exception as e:  # plyfile raises several kinds on malformed files
        raise DatasetError(f"{path}: not a readable PLY triangle mesh ({e.__class__.__name__}: {e})") from None
    if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise DatasetError(f"{path}: face indices outside the {len(vertices)} vertices")
    return vertices, faces, colours


def merge_eval_json(run_dir, values: dict) -> pathlib.Path:
    """Merge ``values`` into ``RUN_DIR/eval.json`` (created when absent), atomically."""
    path = _folder(run_dir) / "eval.json"
    current = {}
    if path.is_file():
        try:
            current = json.loads(path.read_text())
        except ValueError:
            raise DatasetError(f"{path}: exists but is not JSON; move it away to write the scores") from None
    current.update(values)
    tmp = path.with_name(f".eval.json.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(current, indent=2))
    os.replace(tmp, path)
    return path
