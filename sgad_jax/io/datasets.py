"""Loaders of the RGB-D dataset layouts, and :func:`open_dataset` that picks one.

Every loader returns full-resolution colour (uint8 RGB) and depth (float32 metres, 0 = missing) and
camera-to-world ground truth in OpenCV axes (x right, y down, z forward), NaN where unknown; the
base class :class:`~sgad_jax.io.base.Dataset` applies frame selection, downscaling and inpainting.
The conventions (and where the published systems disagree) are in ``docs/method.md``, "Dataset conventions".

Layouts:
    ``tum``        TUM RGB-D: ``rgb.txt``, ``depth.txt``, ``groundtruth.txt``, depth / 5000.
    ``replica``    Replica as distributed by NICE-SLAM: ``results/frame*.jpg``, ``results/depth*.png``,
                   ``traj.txt``, ``cam_params.json``, depth / 6553.5.
    ``7scenes``    7-Scenes in the 3DMatch layout: ``frame-XXXXXX.{color.jpg,depth.png,pose.txt}``.
    ``scannet``    ScanNet SensReader export: ``color/<i>.jpg``, ``depth/<i>.png``, ``pose/<i>.txt``.
    ``scannetpp``  ScanNet++ DSLR, undistorted: ``nerfstudio/transforms_undistorted.json``.
    ``generic``    ``rgb/`` (or ``color/``) and ``depth/`` folders plus ``intrinsics.txt`` / ``.json``.
"""

from __future__ import annotations

import json
import math
import pathlib
import re

import cv2
import numpy as np

from sgad_jax.config import DataConfig
from sgad_jax.io.base import Dataset, DatasetError, read_image
from sgad_jax.io.export import quaternion_to_matrix
from sgad_jax.types import Intrinsics, make_intrinsics

# ScanNet edge crop in pixels (GS uses 12, NICE 10). 0 (no crop) is the SplaTAM / VTGS lineage default.
SCANNET_CROP_EDGE = 0
# ScanNet++ DSLR resize factor: GS / LS / SplaTAM run at half the 1752x1168 undistorted resolution.
SCANNETPP_RESIZE = 0.5

TUM_INTRINSICS = {  # fx, fy, cx, cy at 640x480 (TUM RGB-D file-format page)
    1: (517.3, 516.5, 318.6, 255.3),
    2: (520.9, 521.0, 325.1, 249.7),
    3: (535.4, 539.2, 320.1, 247.6),
}
TUM_FRAME_RATE = 32.0  # association keeps a frame only if it is more than 1/32 s after the last kept one
REPLICA_INTRINSICS = (600.0, 600.0, 599.5, 339.5, 1200, 680)
SEVEN_SCENES_INTRINSICS = (585.0, 585.0, 320.0, 240.0)
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".exr")


# --- small helpers -------------------------------------------------------------------------------


def _require_dir(path: pathlib.Path) -> pathlib.Path:
    path = pathlib.Path(path)
    if not path.is_dir():
        raise DatasetError(f"{path}: folder not found")
    return path


def _numbers(path: pathlib.Path, text: str | None = None) -> np.ndarray:
    """All whitespace-separated numbers of a text file (``inf`` / ``nan`` allowed), as float64."""
    try:
        text = path.read_text() if text is None else text
        return np.array(text.split(), dtype=np.float64)
    except (OSError, UnicodeDecodeError) as e:
        raise DatasetError(f"{path}: cannot read ({e.__class__.__name__})") from None
    except ValueError:
        raise DatasetError(f"{path}: malformed, expected only numbers") from None


def _matrix4(path: pathlib.Path) -> np.ndarray:
    """A 4x4 pose file, as written (ScanNet's ``-inf`` poses included: the ground-truth check
    reports and masks them)."""
    values = _numbers(path)
    if values.size != 16:
        raise DatasetError(f"{path}: malformed pose, expected 16 numbers, got {values.size}")
    return values.reshape(4, 4)


def _read_json(path: pathlib.Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DatasetError(f"{path}: cannot parse JSON ({str(e).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: malformed, expected a JSON object")
    return data


def _intrinsics(source, fx, fy, cx, cy, width, height) -> Intrinsics:
    try:
        return make_intrinsics(float(fx), float(fy), float(cx), float(cy), int(width), int(height))
    except (TypeError, ValueError) as e:
        raise DatasetError(f"{source}: invalid intrinsics ({e})") from None


def _image_size(path: pathlib.Path) -> tuple[int, int]:
    """(width, height) of an image, read from the file."""
    image = read_image(path, depth=True)
    return image.shape[1], image.shape[0]


def _depth_metres(raw: np.ndarray, scale: float) -> np.ndarray:
    depth = raw.astype(np.float32)
    depth /= np.float32(scale)  # in place: the reader's passes over a frame cost the tracking step cores
    return depth


def _no_gt(n: int) -> np.ndarray:
    return np.full((n, 4, 4), np.nan)


def _natural_key(path: pathlib.Path):
    """Sort key that orders embedded numbers numerically (``2.png`` before ``10.png``)."""
    return [(0, int(t), "") if t.isdigit() else (1, 0, t) for t in re.split(r"(\d+)", path.stem)]


def _frame_key(path: pathlib.Path):
    """What pairs a colour image with its depth image: the numbers in the name (``frame000003.jpg``
    with ``depth000003.png``), or the name itself when it holds none."""
    return tuple(int(t) for t in re.findall(r"\d+", path.stem)) or path.stem


def _by_frame_key(paths: list[pathlib.Path]) -> dict:
    """{``_frame_key``: path}, in the order of ``paths``; two images of one key are an error."""
    keyed = {}
    for p in paths:
        if (twin := keyed.setdefault(_frame_key(p), p)) != p:
            raise DatasetError(f"{p}: same frame number as {twin.name}, cannot tell which one is the frame")
    return keyed


def _numbered_frames(found: dict[int, pathlib.Path], path_of) -> tuple[list[int], list[pathlib.Path]]:
    """(numbers, colour paths) of the frames from the first number found to the last, at their common
    step (a ScanNet export may keep every k-th frame). A number without its colour file gets the path
    ``path_of(number)``: dropping it would shift the frames after it, read, it is a bad frame."""
    numbers = sorted(found)
    step = math.gcd(*np.diff(numbers).tolist()) or 1
    full = range(numbers[0], numbers[-1] + 1, step)
    if len(full) > 2 * len(numbers):  # more missing than present: a stray number, not lost frames
        raise DatasetError(f"{found[numbers[-1]]}: numbered {numbers[-1]}, but only {len(numbers)} frames from {numbers[0]}; a stray file?")
    return list(full), [found.get(n) or path_of(n) for n in full]


def _tum_poses(path: pathlib.Path, rows: list[tuple[int, list[str]]]) -> tuple[np.ndarray, np.ndarray]:
    """(stamps, c2w poses) from TUM trajectory rows ``t tx ty tz qx qy qz qw``."""
    values = _table(path, rows, 8, "malformed trajectory, expected lines 't tx ty tz qx qy qz qw'")
    poses = np.tile(np.eye(4), (len(values), 1, 1))
    poses[:, :3, :3] = quaternion_to_matrix(values[:, 4:8])
    poses[:, :3, 3] = values[:, 1:4]
    return values[:, 0], poses


def _list_rows(path: pathlib.Path) -> list[tuple[int, list[str]]]:
    """(line number, fields) of the non-empty, non-``#`` lines of a list file, split on whitespace.
    A byte-order mark or a stray non-UTF-8 byte (in a comment, say) does not make the file unreadable."""
    try:
        lines = path.read_bytes().decode("utf-8-sig", errors="replace").splitlines()
    except OSError as e:
        raise DatasetError(f"{path}: cannot read ({e.strerror or e.__class__.__name__})") from None
    return [(n, line.split()) for n, line in enumerate(lines, 1) if line.strip() and not line.lstrip().startswith("#")]


def _table(path: pathlib.Path, rows: list[tuple[int, list[str]]], columns: int, expected: str, numeric: int | None = None) -> np.ndarray:
    """The first ``numeric`` (all) of ``columns`` fields of each row as float64; the first row that is
    not that, or whose timestamp (first field) is not a finite number, is named in the error (a NaN
    stamp would otherwise match every frame in the association)."""
    numeric = columns if numeric is None else numeric
    values = np.empty((len(rows), numeric))
    for r, (n, fields) in enumerate(rows):
        try:
            if len(fields) != columns:
                raise ValueError
            values[r] = [float(x) for x in fields[:numeric]]
        except ValueError:
            raise DatasetError(f"{path}: line {n}: {expected}") from None
        if not np.isfinite(values[r, 0]):
            raise DatasetError(f"{path}: line {n}: timestamp {fields[0]!r} is not a finite number")
    return values


class _FileDataset(Dataset):
    """A loader whose frame ``j`` is the image pair ``rgb_paths[j]``, ``depth_paths[j]`` (raw / ``depth_scale``)."""

    rgb_paths: list[pathlib.Path]
    depth_paths: list[pathlib.Path]
    depth_scale: float

    pose_files: list[pathlib.Path] | None = None  # a c2w pose file a frame (7-Scenes, ScanNet)

    def _num_raw(self) -> int:
        return len(self.rgb_paths)

    def _size(self) -> tuple[int, int]:
        """(width, height) of the first selected frame's depth image that can be read: a missing or
        broken one is a bad frame when its turn comes, not a reason to stop at start-up."""
        cfg, first = self.cfg, None
        for j in range(max(cfg.start, 0), len(self.depth_paths), max(cfg.stride, 1)) or range(len(self.depth_paths)):
            try:
                return _image_size(self.depth_paths[j])
            except DatasetError as e:
                first = first or e
        raise first

    def _check_gt(self) -> list[str]:
        """With ``pose_files``, the selected frames' poses are read first, and only they: a malformed
        file of a frame the run does not use must not stop it."""
        if self.pose_files is not None:
            self.gt_poses_raw = _no_gt(len(self.pose_files))
            for j in self.selection:
                if self.pose_files[j].is_file():
                    self.gt_poses_raw[j] = _matrix4(self.pose_files[j])
        return super()._check_gt()

    def _gt_source(self, j: int):
        return self.pose_files[j] if self.pose_files is not None else super()._gt_source(j)

    def _load_raw(self, j):
        depth = _depth_metres(read_image(self.depth_paths[j], depth=True), self.depth_scale)
        return read_image(self.rgb_paths[j], decode=self.colour), depth

    def describe(self, j, *, depth=False):
        return str(self.depth_paths[j]) if depth else f"{self.rgb_paths[j]} (depth {self.depth_paths[j]})"


# --- TUM RGB-D -----------------------------------------------------------------------------------


class TUMDataset(_FileDataset):
    """TUM RGB-D (``rgbd_dataset_freiburg1_xyz`` etc.).

    Association as in every published TUM number (NICE-SLAM, GS, SplaTAM, MonoGS ...): for each
    colour stamp take the nearest depth stamp and the nearest pose stamp, keep the triple when both
    are within ``cfg.tum_max_dt``, then drop a frame unless it comes more than 1/32 s after the last
    kept one. Without ``groundtruth.txt`` only the depth criterion applies and ground truth is NaN.
    Intrinsics are those of freiburg 1, 2 or 3, from ``freiburg1`` / ``fr1`` ... in the folder name
    (freiburg 1 when none matches). Poses are absolute, as in ``groundtruth.txt``.
    """

    layout = "tum"

    def __init__(self, root: pathlib.Path, cfg: DataConfig):
        super().__init__(_require_dir(root), cfg)
        rgb_list, depth_list, gt_file = (self.root / n for n in ("rgb.txt", "depth.txt", "groundtruth.txt"))
        t_rgb, rgb_names = self._read_list(rgb_list)
        t_depth, depth_names = self._read_list(depth_list)
        if not gt_file.is_file():  # the fallback name of the published loaders
            gt_file = self.root / "pose.txt"
        gt_rows = _list_rows(gt_file) if gt_file.is_file() else []
        t_pose, poses = _tum_poses(gt_file, gt_rows) if gt_rows else (None, None)  # no ground truth: not an error
        if len(t_rgb) == 0 or len(t_depth) == 0:
            raise DatasetError(f"{rgb_list if len(t_rgb) == 0 else depth_list}: no frames listed")

        kept, last, unmatched = [], None, {depth_list: 0, gt_file: 0}
        for i, t in enumerate(t_rgb):
            j = int(np.argmin(np.abs(t_depth - t)))
            k = int(np.argmin(np.abs(t_pose - t))) if t_pose is not None else -1
            if abs(t_depth[j] - t) >= cfg.tum_max_dt:
                unmatched[depth_list] += 1
                continue
            if t_pose is not None and abs(t_pose[k] - t) >= cfg.tum_max_dt:
                unmatched[gt_file] += 1
                continue
            # A stamp that goes back in time is kept, for the run to report it as a bad frame.
            if last is None or t - last > 1.0 / TUM_FRAME_RATE or t <= last:
                kept.append((i, j, k))
                last = t
        if not kept:
            raise DatasetError(f"{self.root}: no colour frame has depth within {cfg.tum_max_dt} s")

        self.rgb_paths = [self.root / rgb_names[i] for i, _, _ in kept]
        self.depth_paths = [self.root / depth_names[j] for _, j, _ in kept]
        self.timestamps_raw = np.array([t_rgb[i] for i, _, _ in kept], np.float64)
        # Depth and colour are not synchronised: the geometry of frame i was seen at its depth stamp
        # (two colour frames can even share one depth image), which the motion model needs.
        self.depth_timestamps_raw = np.array([t_depth[j] for _, j, _ in kept], np.float64)
        self.gt_poses_raw = poses[[k for _, _, k in kept]] if t_pose is not None else _no_gt(len(kept))
        self.gt_file = gt_file if t_pose is not None else None
        self.depth_scale = cfg.depth_scale if cfg.depth_scale > 0 else 5000.0
        match = re.search(r"(?:freiburg|fr)([123])", self.root.resolve().name.lower())
        fx, fy, cx, cy = TUM_INTRINSICS[int(match.group(1)) if match else 1]
        self.intrinsics_full = _intrinsics(self.root, fx, fy, cx, cy, *self._size())
        self._finish_init()
        self.warnings += [
            f"{path}: {n} of the {len(t_rgb)} colour frames of {rgb_list.name} have no stamp here within {cfg.tum_max_dt} s; they are left out"
            for path, n in unmatched.items() if n
        ]

    @staticmethod
    def _read_list(path: pathlib.Path) -> tuple[np.ndarray, list[str]]:
        if not path.is_file():
            raise DatasetError(f"{path}: file not found")
        rows = _list_rows(path)
        stamps = _table(path, rows, 2, "malformed list, expected lines 'timestamp filename'", numeric=1)[:, 0]
        return stamps, [fields[1] for _, fields in rows]


# --- Replica -------------------------------------------------------------------------------------


class ReplicaDataset(_FileDataset):
    """Replica renders in the NICE-SLAM layout; ``traj.txt`` line ``i`` is the c2w pose of frame ``i``.

    ``cam_params.json`` is read from the folder or its parent; without it the standard Replica
    camera (1200x680, f 600, c 599.5 339.5) is assumed. Timestamps are the frame numbers; a missing
    number is a bad frame.
    """

    layout = "replica"

    def __init__(self, root: pathlib.Path, cfg: DataConfig):
        super().__init__(_require_dir(root), cfg)
        results = self.root / "results"
        found = sorted(results.glob("frame*.jpg"))
        if not found:
            raise DatasetError(f"{results}: no frame*.jpg images")
        try:
            found = {int(p.stem[len("frame"):]): p for p in found}
        except ValueError:
            raise DatasetError(f"{results}: colour names must be frame<number>.jpg") from None
        pad = len(next(iter(found.values())).stem) - len("frame")
        numbers, self.rgb_paths = _numbered_frames(found, lambda n: results / f"frame{n:0{pad}d}.jpg")
        self.depth_paths = [results / f"depth{p.stem[len('frame'):]}.png" for p in self.rgb_paths]
        self.timestamps_raw = np.array(numbers, np.float64)

        traj = self.root / "traj.txt"
        self.gt_poses_raw = _no_gt(len(numbers))
        if traj.is_file():
            values = _numbers(traj)
            if values.size % 16:
                raise DatasetError(f"{traj}: malformed, expected 16 numbers (row-major 4x4) per line")
            poses = values.reshape(-1, 4, 4)
            for i, n in enumerate(numbers):
                if n < len(poses):
                    self.gt_poses_raw[i] = poses[n]
            self.gt_file = traj

        scale = 6553.5
        params = next((p for d in (self.root, self.root.parent) if (p := d / "cam_params.json").is_file()), None)
        if params is not None:
            cam = _read_json(params).get("camera")
            try:
                k = [float(cam[key]) for key in ("fx", "fy", "cx", "cy", "w", "h")]
                scale = float(cam.get("scale", scale))
            except (TypeError, KeyError, ValueError):
                raise DatasetError(f"{params}: malformed, expected {{'camera': {{w, h, fx, fy, cx, cy}}}}") from None
            if not (math.isfinite(scale) and scale > 0):  # depth / scale would be Inf or negative: no depth at all
                raise DatasetError(f"{params}: camera scale (depth units a metre) must be a positive number, got {cam['scale']!r}")
            self.intrinsics_full = _intrinsics(params, *k)
        else:
            fx, fy, cx, cy, _, _ = REPLICA_INTRINSICS
            self.intrinsics_full = _intrinsics(self.root, fx, fy, cx, cy, *self._size())
        self.depth_scale = cfg.depth_scale if cfg.depth_scale > 0 else scale
        self._finish_init()
        if self.gt_file is not None and not self.has_gt:  # _check_gt is silent when no frame has a pose
            self.warnings.append(f"{traj}: no usable pose for the selected frames ({len(poses)} in the file); the run has no ground truth")


# --- 7-Scenes ------------------------------------------------------------------------------------


class SevenScenesDataset(_FileDataset):
    """Microsoft 7-Scenes, 3DMatch layout (``frame-XXXXXX.color.jpg|png``, ``.depth.png``, ``.pose.txt``).

    The frames live in the folder itself, or in its ``seq-XX/`` subfolders (original release; taken
    in sequence order). Depth is in millimetres, with 0 and 65535 missing. ``camera-intrinsics.txt``
    (3x3) is used when present, else f 585, c (320, 240). Timestamps are the frame numbers, those of
    each sequence after the last of the one before (the positions, when no frame is missing); a
    missing number is a bad frame.
    """

    layout = "7scenes"

    def __init__(self, root: pathlib.Path, cfg: DataConfig):
        super().__init__(_require_dir(root), cfg)
        folders = [self.root] if _seven_scenes_frames(self.root) else sorted(self.root.glob("seq-*/"), key=_natural_key)
        self.rgb_paths, numbers = [], []
        for d in filter(_seven_scenes_frames, folders):
            frames = _seven_scenes_frames(d)
            found = {}
            for p in frames:
                if not (m := re.fullmatch(r"frame-(\d+)", p.name.split(".")[0])):
                    raise DatasetError(f"{p}: colour names must be frame-<number>.color.jpg|png")
                found[int(m.group(1))] = p
            pad, ext = len(m.group(1)), frames[0].suffix
            nums, paths = _numbered_frames(found, lambda n: d / f"frame-{n:0{pad}d}.color{ext}")
            offset = numbers[-1] + 1 if numbers else 0
            numbers += [offset + n for n in nums]
            self.rgb_paths += paths
        if not self.rgb_paths:
            raise DatasetError(f"{self.root}: no frame-XXXXXX.color.jpg/png images (nor in seq-XX/ subfolders)")
        prefixes = [p.parent / p.name.split(".")[0] for p in self.rgb_paths]
        self.depth_paths = [pathlib.Path(f"{q}.depth.png") for q in prefixes]
        self.pose_files = [pathlib.Path(f"{q}.pose.txt") for q in prefixes]
        self.timestamps_raw = np.array(numbers, np.float64)
        self.depth_scale = cfg.depth_scale if cfg.depth_scale > 0 else 1000.0

        k_file = next((p for d in (self.root, folders[0]) if (p := d / "camera-intrinsics.txt").is_file()), None)
        if k_file is not None:
            k = _numbers(k_file)
            if k.size != 9:
                raise DatasetError(f"{k_file}: malformed, expected a 3x3 matrix")
            fx, fy, cx, cy = k[0], k[4], k[2], k[5]
        else:
            fx, fy, cx, cy = SEVEN_SCENES_INTRINSICS
        self.intrinsics_full = _intrinsics(k_file or self.root, fx, fy, cx, cy, *self._size())
        self._finish_init()
        if k_file is None and not cfg.intrinsics:
            self.warnings.append(
                f"{self.root / 'camera-intrinsics.txt'}: not found; using the 7-Scenes defaults fx=fy={fx:g}, cx={cx:g}, cy={cy:g}"
            )

    def _load_raw(self, j):
        raw = read_image(self.depth_paths[j], depth=True)
        depth = _depth_metres(raw, self.depth_scale)
        depth[raw == 65535] = 0.0
        return read_image(self.rgb_paths[j], decode=self.colour), depth


def _seven_scenes_frames(folder: pathlib.Path) -> list[pathlib.Path]:
    return sorted(p for p in folder.glob("frame-*.color.*") if p.suffix.lower() in (".jpg", ".png"))


# --- ScanNet -------------------------------------------------------------------------------------


class ScanNetDataset(_FileDataset):
    """ScanNet as exported by SensReader: ``color/<i>.jpg``, ``depth/<i>.png`` (mm), ``pose/<i>.txt``.

    The folder may also hold these under ``frames/`` (NICE-SLAM). Frames are sorted by their number
    (names are not zero-padded), a missing number a bad frame. Colour (1296x968) is resized to the
    depth size (640x480) with bilinear interpolation, as GS does; intrinsics are those of
    ``intrinsic/intrinsic_depth.txt``.
    Poses that are ``-inf`` in the export become NaN ground truth (masked out of the ATE).

    Args:
        root: the scene folder.
        cfg: data options.
        crop_edge: pixels cropped from each border (GS 12, NICE 10); default ``SCANNET_CROP_EDGE`` (0).
    """

    layout = "scannet"

    def __init__(self, root: pathlib.Path, cfg: DataConfig, crop_edge: int | None = None):
        super().__init__(_require_dir(root), cfg)
        base = self.root / "frames" if (self.root / "frames" / "color").is_dir() else self.root
        color = _require_dir(base / "color")
        found = {int(p.stem): p for p in color.glob("*.jpg") if p.stem.isdigit()}
        if not found:
            raise DatasetError(f"{color}: no <number>.jpg images")
        numbers, self.rgb_paths = _numbered_frames(found, lambda n: color / f"{n}.jpg")
        self.depth_paths = [base / "depth" / f"{p.stem}.png" for p in self.rgb_paths]
        self.pose_files = [base / "pose" / f"{p.stem}.txt" for p in self.rgb_paths]
        self.timestamps_raw = np.array(numbers, np.float64)
        self.depth_scale = cfg.depth_scale if cfg.depth_scale > 0 else 1000.0
        self.crop = SCANNET_CROP_EDGE if crop_edge is None else int(crop_edge)

        width, height = self._size()
        e = self.crop
        if e < 0 or 2 * e >= min(width, height):
            raise DatasetError(f"{self.root}: crop_edge {e} does not fit a {width}x{height} image")
        k_file = base / "intrinsic" / "intrinsic_depth.txt"
        if k_file.is_file():
            k = _numbers(k_file)
            if k.size not in (9, 16):
                raise DatasetError(f"{k_file}: malformed, expected a 4x4 (or 3x3) matrix")
            k = k.reshape(int(math.isqrt(k.size)), -1)
            fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
        elif cfg.intrinsics:
            fx, fy, cx, cy = 1.0, 1.0, e, e  # replaced by cfg.intrinsics in _finish_init
        else:
            raise DatasetError(f"{k_file}: file not found (or set data.intrinsics)")
        self.intrinsics_full = _intrinsics(k_file, fx, fy, cx - e, cy - e, width - 2 * e, height - 2 * e)
        self._finish_init()

    def _load_raw(self, j):
        depth = _depth_metres(read_image(self.depth_paths[j], depth=True), self.depth_scale)
        rgb = read_image(self.rgb_paths[j], decode=self.colour)
        if rgb.shape[:2] != depth.shape:
            if self.colour:
                rgb = cv2.resize(rgb, (depth.shape[1], depth.shape[0]), interpolation=cv2.INTER_LINEAR)
            else:  # black resized is black
                rgb = np.zeros((*depth.shape, 3), np.uint8)
        e = self.crop
        if e:
            rgb, depth = rgb[e:-e, e:-e], depth[e:-e, e:-e]
        return np.ascontiguousarray(rgb), np.ascontiguousarray(depth)


# --- ScanNet++ -----------------------------------------------------------------------------------


class ScanNetPPDataset(_FileDataset):
    """ScanNet++ DSLR images, undistorted (``dslr/undistorted_images``, ``undistorted_depths`` in mm).

    Frames are the ``train`` (or ``test``) names of ``train_test_lists.json`` in file order (the
    ``frames`` of the JSON when that file is missing). Colour and depth are resized by
    ``SCANNETPP_RESIZE`` (876x584 from 1752x1168: colour bilinear on floats then truncated, depth
    nearest), and the JSON intrinsics scaled alike. Poses: ``c2w = P @ T @ P.T``, ``P = diag(1, -1, -1, 1)``
    on the nerfstudio ``transform_matrix`` T, exactly as GS / LS / SplaTAM (absolute).

    Args:
        root: the scene folder or its ``dslr/`` subfolder.
        cfg: data options.
        split: ``"train"`` (the SLAM sequence) or ``"test"`` (novel views).
    """

    layout = "scannetpp"

    def __init__(self, root: pathlib.Path, cfg: DataConfig, split: str = "train"):
        super().__init__(_require_dir(root), cfg)
        if split not in ("train", "test"):
            raise DatasetError(f"{self.root}: unknown ScanNet++ split '{split}' (choose train or test)")
        dslr = self.root / "dslr" if (self.root / "dslr").is_dir() else self.root
        meta_file = dslr / "nerfstudio" / "transforms_undistorted.json"
        if not meta_file.is_file():
            raise DatasetError(f"{meta_file}: file not found")
        meta = _read_json(meta_file)
        try:
            records = {f["file_path"]: f for key in ("frames", "test_frames") for f in meta.get(key, [])}
            names = [f["file_path"] for f in meta["frames" if split == "train" else "test_frames"]]
            w, h = int(meta["w"]), int(meta["h"])
            fx, fy, cx, cy = (float(meta[k]) for k in ("fl_x", "fl_y", "cx", "cy"))
        except (TypeError, KeyError, ValueError):
            raise DatasetError(f"{meta_file}: malformed, expected w, h, fl_x, fl_y, cx, cy and frames[file_path]") from None
        lists_file = dslr / "train_test_lists.json"
        if lists_file.is_file():
            names = _read_json(lists_file).get(split)
            if not isinstance(names, list):
                raise DatasetError(f"{lists_file}: malformed, expected a '{split}' list of image names")
        names = [str(n) for n in names]
        if not names:
            raise DatasetError(f"{dslr}: no {split} frames listed")

        self.rgb_paths = [dslr / "undistorted_images" / n for n in names]
        self.depth_paths = [dslr / "undistorted_depths" / f"{pathlib.Path(n).stem}.png" for n in names]
        flip = np.diag([1.0, -1.0, -1.0, 1.0])
        self.gt_poses_raw = _no_gt(len(names))
        for i, n in enumerate(names):
            if n in records and "transform_matrix" in records[n]:
                t = np.asarray(records[n]["transform_matrix"], np.float64)
                if t.shape != (4, 4):
                    raise DatasetError(f"{meta_file}: malformed transform_matrix of {n}, expected 4x4")
                self.gt_poses_raw[i] = flip @ t @ flip.T
        self.timestamps_raw = np.arange(len(names), dtype=np.float64)
        self.depth_scale = cfg.depth_scale if cfg.depth_scale > 0 else 1000.0
        self.size = (round(w * SCANNETPP_RESIZE), round(h * SCANNETPP_RESIZE))
        sx, sy = self.size[0] / w, self.size[1] / h
        self.intrinsics_full = _intrinsics(meta_file, fx * sx, fy * sy, cx * sx, cy * sy, *self.size)
        self._finish_init()

    def _load_raw(self, j):
        rgb = read_image(self.rgb_paths[j], decode=self.colour)
        raw = read_image(self.depth_paths[j], depth=True)
        if rgb.shape[:2] != raw.shape:
            raise DatasetError(
                f"{self.describe(j)}: colour is {rgb.shape[1]}x{rgb.shape[0]} but depth is {raw.shape[1]}x{raw.shape[0]}"
            )
        if rgb.shape[1::-1] != self.size:
            if self.colour:
                rgb = cv2.resize(rgb.astype(np.float32), self.size, interpolation=cv2.INTER_LINEAR).astype(np.uint8)
            else:  # black resized is black (resizing it cost 4.6 ms a full-size frame)
                rgb = np.zeros((self.size[1], self.size[0], 3), np.uint8)
            raw = cv2.resize(raw, self.size, interpolation=cv2.INTER_NEAREST)
        return rgb, _depth_metres(raw, self.depth_scale)


# --- generic folders -----------------------------------------------------------------------------


class GenericDataset(_FileDataset):
    """Any folder with ``rgb/`` (or ``color/``) and ``depth/`` images, paired by the numbers in their
    names (``frame000003.jpg`` with ``depth000003.png``; by name when it holds none), in name order.

    Intrinsics: ``intrinsics.txt`` (``fx fy cx cy`` or a 3x3 matrix) or ``intrinsics.json``
    (``{fx, fy, cx, cy}``), or ``cfg.intrinsics``. Integer depth is divided by ``cfg.depth_scale``
    (1000, millimetres, by default); floating-point depth (TIFF, EXR) is taken as metres. An optional
    TUM-format ``groundtruth.txt`` is used only when it has exactly one line per frame (its stamps
    then become the timestamps); otherwise (a warning) there is no ground truth and timestamps are positions.
    """

    layout = "generic"

    def __init__(self, root: pathlib.Path, cfg: DataConfig):
        super().__init__(_require_dir(root), cfg)
        rgb_dir = next((self.root / n for n in ("rgb", "color") if (self.root / n).is_dir()), self.root / "rgb")
        depth_dir = self.root / "depth"
        self.rgb_paths = _images(_require_dir(rgb_dir))
        if not self.rgb_paths:
            raise DatasetError(f"{rgb_dir}: no images")
        # Paired by name, not position: with one image missing, position would pair every later
        # colour image with the next frame's depth. Names that share no number at all (each camera's
        # own timestamps) pair in order, when the counts agree.
        colour, depth = _by_frame_key(self.rgb_paths), _by_frame_key(_images(_require_dir(depth_dir)))
        if colour.keys().isdisjoint(depth.keys()) and len(colour) == len(depth):
            self.depth_paths = list(depth.values())
        else:
            for mine, other, folder in ((colour, depth, depth_dir), (depth, colour, rgb_dir)):
                if (lone := next((p for key, p in mine.items() if key not in other), None)) is not None:
                    raise DatasetError(f"{lone}: no image of the same frame number in {folder}")
            self.depth_paths = [depth[key] for key in colour]
        n = len(self.rgb_paths)
        self.timestamps_raw = np.arange(n, dtype=np.float64)
        self.gt_poses_raw = _no_gt(n)
        gt_file, gt_lines = self.root / "groundtruth.txt", None
        if gt_file.is_file() and (gt_lines := len(rows := _list_rows(gt_file))) == n:
            self.timestamps_raw, self.gt_poses_raw = _tum_poses(gt_file, rows)
            self.gt_file = gt_file
        self.depth_scale = cfg.depth_scale if cfg.depth_scale > 0 else 1000.0
        self.intrinsics_full = _intrinsics(self._k_source(), *self._read_k(), *self._size())
        self._finish_init()
        if gt_lines not in (None, n):
            self.warnings.append(f"{gt_file}: {gt_lines} poses for {n} frames, expected one a frame; the run has no ground truth")

    def _k_source(self) -> pathlib.Path:
        txt, js = self.root / "intrinsics.txt", self.root / "intrinsics.json"
        return txt if txt.is_file() or not js.is_file() else js

    def _read_k(self) -> tuple[float, float, float, float]:
        path = self._k_source()
        if not path.is_file():
            if self.cfg.intrinsics:
                return 1.0, 1.0, 0.0, 0.0  # replaced by cfg.intrinsics in _finish_init
            raise DatasetError(f"{self.root}: no intrinsics.txt or intrinsics.json (or set data.intrinsics)")
        if path.suffix == ".json":
            try:
                data = _read_json(path)
                return tuple(float(data[k]) for k in ("fx", "fy", "cx", "cy"))
            except (KeyError, TypeError, ValueError):
                raise DatasetError(f"{path}: malformed, expected {{fx, fy, cx, cy}}") from None
        k = _numbers(path)
        if k.size == 4:
            return tuple(k)
        if k.size == 9:
            return k[0], k[4], k[2], k[5]
        raise DatasetError(f"{path}: malformed, expected 'fx fy cx cy' or a 3x3 matrix")

    def _load_raw(self, j):
        raw = read_image(self.depth_paths[j], depth=True)
        depth = raw.astype(np.float32) if raw.dtype.kind == "f" else _depth_metres(raw, self.depth_scale)
        return read_image(self.rgb_paths[j], decode=self.colour), depth


def _images(folder: pathlib.Path) -> list[pathlib.Path]:
    # Hidden files (macOS "._0.jpg" resource forks) and folders are no images; a broken link is
    # kept, to be named when read.
    return sorted(
        (p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".") and not p.is_dir()),
        key=_natural_key,
    )


# --- layout detection ----------------------------------------------------------------------------

LOADERS: dict[str, type[Dataset]] = {
    "tum": TUMDataset,
    "replica": ReplicaDataset,
    "scannetpp": ScanNetPPDataset,
    "scannet": ScanNetDataset,
    "7scenes": SevenScenesDataset,
    "generic": GenericDataset,
}
LAYOUTS = (*LOADERS, "synthetic")

_SIGNATURES = {  # in order of detection: the more specific layouts first
    "tum": lambda p: (p / "rgb.txt").is_file() or (p / "depth.txt").is_file(),  # one missing: say so, as TUM
    "replica": lambda p: any((p / "results").glob("frame*.jpg")),
    "scannetpp": lambda p: any((d / "nerfstudio" / "transforms_undistorted.json").is_file() for d in (p, p / "dslr")),
    "scannet": lambda p: any(
        (d / "color").is_dir() and (d / "depth").is_dir() and ((d / "pose").is_dir() or (d / "intrinsic").is_dir())
        for d in (p, p / "frames")
    ),
    "7scenes": lambda p: bool(_seven_scenes_frames(p)) or any(_seven_scenes_frames(d) for d in p.glob("seq-*/")),
    "generic": lambda p: ((p / "rgb").is_dir() or (p / "color").is_dir()) and (p / "depth").is_dir(),
}


def detect_layout(path) -> str:
    """The layout name of a dataset folder, from the files it holds.

    Raises:
        DatasetError: the folder does not exist or matches no layout.
    """
    path = _require_dir(path)
    for name, matches in _SIGNATURES.items():
        if matches(path):
            return name
    raise DatasetError(f"{path}: no known dataset layout found (looked for {', '.join(_SIGNATURES)})")


def open_dataset(cfg: DataConfig) -> Dataset:
    """The dataset that ``cfg`` describes: the synthetic scene when ``cfg.path`` is empty.

    Raises:
        DatasetError: unknown layout, missing folder, or any problem with the files.
    """
    if cfg.layout != "auto" and cfg.layout not in LAYOUTS:
        raise DatasetError(f"unknown dataset layout '{cfg.layout}' (choose from auto, {', '.join(LAYOUTS)})")
    if cfg.path and cfg.layout == "synthetic":
        raise DatasetError(f"data.layout=synthetic is the built-in scene, but data.path is {cfg.path}: set data.layout=auto to read it")
    if not cfg.path:
        from sgad_jax.io.synthetic import SyntheticDataset

        return SyntheticDataset(cfg)
    path = _require_dir(pathlib.Path(cfg.path).expanduser())
    layout = detect_layout(path) if cfg.layout == "auto" else cfg.layout
    return LOADERS[layout](path, cfg)
