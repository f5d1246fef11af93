"""A finished run's folder, read back: trajectory, metrics, config, intrinsics, stored Gaussians.

What a run writes (see :mod:`sgad_jax.pipeline`): ``trajectory.txt`` (TUM, camera-to-world),
``metrics.json`` (its ``config`` key the resolved config), ``gaussians/frame_XXXXXX.npz`` per mapped
frame (XXXXXX its index in the run), ``renders/`` with ``--save-renders``, and ``cameras.json``
(``width height fx fy cx cy`` after ``data.downscale``). A run without ``cameras.json`` gets its
intrinsics from its dataset, opened from the config. Every problem is a one-line
:class:`~sgad_jax.io.base.DatasetError` naming the file.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import pathlib
import typing
import zipfile
import zlib

import numpy as np

from sgad_jax.config import DataConfig, ExportConfig, SLAMConfig
from sgad_jax.io.base import DatasetError
from sgad_jax.io.export import read_tum_trajectory
from sgad_jax.io.files import numbered_files, write_json
from sgad_jax.io.store import FIELDS
from sgad_jax.types import Intrinsics, PixelGaussians, make_intrinsics

CAMERA_KEYS = ("width", "height", "fx", "fy", "cx", "cy")


def _from_dict(cls, d: dict):
    """A (nested) config dataclass from its ``dataclasses.asdict`` form; unknown keys are ignored,
    missing ones keep their defaults, lists become tuples where the field is a tuple."""
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name not in d:
            continue
        value, kind = d[f.name], hints[f.name]
        if dataclasses.is_dataclass(kind):
            value = _from_dict(kind, value or {})
        elif isinstance(value, list):
            value = tuple(value)
        kwargs[f.name] = value
    return cls(**kwargs)


class Run:
    """The files of a finished run in ``root`` (read lazily; each property raises a
    :class:`DatasetError` naming the missing or unreadable file)."""

    def __init__(self, root):
        self.root = pathlib.Path(root).expanduser()
        if not self.root.is_dir():
            raise DatasetError(f"{self.root}: run folder not found")

    @functools.cached_property
    def metrics(self) -> dict:
        path = self.root / "metrics.json"
        try:
            metrics = json.loads(path.read_text())
        except FileNotFoundError:
            raise DatasetError(f"{path}: not found (is {self.root} the --out folder of a finished run?)") from None
        except (OSError, ValueError) as err:
            raise DatasetError(f"{path}: unreadable ({err})") from None
        # every reader does metrics.get(...): valid JSON of another shape must fail here, named
        if not isinstance(metrics, dict):
            raise DatasetError(f"{path}: not a JSON object (written by another program?)")
        if not isinstance(metrics.get("config", {}), dict):
            raise DatasetError(f"{path}: its 'config' is not a JSON object (written by another program?)")
        return metrics

    @functools.cached_property
    def data_config(self) -> DataConfig:
        cfg = self.metrics.get("config", {}).get("data")
        if cfg is None:
            raise DatasetError(f"{self.root / 'metrics.json'}: no 'config.data' key (written by another program?)")
        return _from_dict(DataConfig, cfg)

    @functools.cached_property
    def export_config(self) -> ExportConfig:
        return _from_dict(ExportConfig, self.metrics.get("config", {}).get("export", {}))

    @functools.cached_property
    def config(self) -> SLAMConfig:
        return _from_dict(SLAMConfig, self.metrics.get("config", {}))

    @functools.cached_property
    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """``(timestamps (f,), camera-to-world poses (f, 4, 4))``, float64."""
        path = self.root / "trajectory.txt"
        try:
            return read_tum_trajectory(path)
        except FileNotFoundError:
            raise DatasetError(f"{path}: not found (is {self.root} the --out folder of a finished run?)") from None
        except (OSError, UnicodeDecodeError) as err:  # a folder, no permission, not text: not a bad line
            raise DatasetError(f"{path}: unreadable ({getattr(err, 'strerror', None) or err})") from None
        except ValueError as err:  # a bad line, named by read_tum_trajectory
            raise DatasetError(str(err)) from None

    @functools.cached_property
    def dataset(self):
        """The run's dataset (same frame selection and downscale), opened from its config; frame
        ``i`` is the trajectory's row ``i`` (the frames the run skipped are left out)."""
        from sgad_jax.io.datasets import open_dataset

        skipped = [r["source_index"] for r in self.metrics.get("skipped_frames", [])]
        return open_dataset(self.data_config).without(skipped)

    @functools.cached_property
    def intrinsics(self) -> Intrinsics:
        """``cameras.json`` when the run wrote it, else the dataset's intrinsics after downscale."""
        path = self.root / "cameras.json"
        if not path.exists():
            return self.dataset.intrinsics
        try:
            cam = json.loads(path.read_text())
            return make_intrinsics(*(cam[k] for k in ("fx", "fy", "cx", "cy")), int(cam["width"]), int(cam["height"]))
        except KeyError as err:
            raise DatasetError(f"{path}: missing key {err} (need {', '.join(CAMERA_KEYS)})") from None
        except (OSError, ValueError, TypeError) as err:
            raise DatasetError(f"{path}: unreadable ({err})") from None

    def gaussian_frames(self) -> list[int]:
        """Run indices of the frames with stored Gaussians, ascending."""
        return numbered_files(self.root / "gaussians", "frame_", ".npz")

    @contextlib.contextmanager
    def _frame_file(self, index: int):
        """Frame ``index``'s ``.npz``, open; any failure to read it, in the ``with`` body too (its
        arrays are read lazily), becomes a :class:`DatasetError` naming the file."""
        path = self.root / "gaussians" / f"frame_{index:06d}.npz"
        try:
            z = np.load(path)
            if not isinstance(z, np.lib.npyio.NpzFile):  # a bare .npy array under the name
                raise ValueError("not an .npz archive")
            with z:
                yield z
        except FileNotFoundError:
            raise DatasetError(f"{path}: not found") from None
        # zero bytes: EOFError; a cut zip: BadZipFile or zlib.error; a missing field: KeyError
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error) as err:
            raise DatasetError(f"{path}: unreadable ({err or type(err).__name__})") from None

    def gaussians(self, index: int) -> PixelGaussians:
        """Frame ``index``'s stored Gaussians (host float32 arrays)."""
        with self._frame_file(index) as z:
            return PixelGaussians(**{k: np.asarray(z[k], np.float32) for k in FIELDS})

    def mapping_poses(self) -> np.ndarray:
        """``(f, 4, 4)`` camera-to-world poses the frames' Gaussians were mapped at: the ``pose``
        stored with them (on TUM the depth image's, which ``trajectory.txt`` interpolates to the
        colour image's stamp), else the trajectory's."""
        poses = self.trajectory[1].copy()
        for i in self.gaussian_frames():
            with self._frame_file(i) as z:
                if "pose" in z.files and i < len(poses):
                    poses[i] = z["pose"]
        return poses

    def render_frames(self, kind: str = "", *, with_depth: bool = False) -> list[int]:
        """Run indices of the frames with a saved colour render (``renders/rgb_XXXXXX.png``; with
        ``kind`` "nvs" the held-out views' ``renders/nvs_rgb_XXXXXX.png``), and with
        ``with_depth`` its depth render too."""
        prefix = f"{kind}_" if kind else ""
        found = numbered_files(self.root / "renders", f"{prefix}rgb_", ".png")
        if with_depth:
            found = [i for i in found if (self.root / "renders" / f"{prefix}depth_{i:06d}.png").is_file()]
        return found

    @property
    def per_frame(self) -> list[dict]:
        """``metrics.json``'s ``per_frame`` list (empty when the run did not write one)."""
        return list(self.metrics.get("per_frame") or [])


def read_render(root, index: int, kind: str = "") -> tuple[np.ndarray, np.ndarray | None]:
    """Frame ``index``'s saved render (``kind`` "nvs": a held-out view's): colour (h, w, 3) float32
    in [0, 1] (8-bit PNG) and depth (h, w) float32 metres (16-bit millimetre PNG; None if absent)."""
    import cv2

    root = pathlib.Path(root)
    prefix = f"{kind}_" if kind else ""
    rgb_path, depth_path = root / "renders" / f"{prefix}rgb_{index:06d}.png", root / "renders" / f"{prefix}depth_{index:06d}.png"
    bgr = cv2.imread(str(rgb_path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise DatasetError(f"{rgb_path}: missing or not an image (renders are written by `run --save-renders`)")
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0
    depth = None
    if depth_path.exists():
        mm = cv2.imread(str(depth_path), cv2.IMREAD_UNCHANGED)
        if mm is None or mm.dtype != np.uint16:
            raise DatasetError(f"{depth_path}: not a 16-bit depth image")
        depth = mm.astype(np.float32) / 1000.0
    return rgb, depth


def merge_eval_json(run_dir, values: dict) -> pathlib.Path:
    """Merge ``values`` into ``RUN_DIR/eval.json`` (created when absent), atomically."""
    path = Run(run_dir).root / "eval.json"
    current = {}
    if path.is_file():
        try:
            current = json.loads(path.read_text())
        except ValueError:
            current = None
        if not isinstance(current, dict):  # not JSON, or a list: nothing to merge the scores into
            raise DatasetError(f"{path}: exists but is not a JSON object; move it away to write the scores")
    current.update(values)
    write_json(path, current)
    return path
