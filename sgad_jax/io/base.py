"""The dataset interface shared by every loader: host-side numpy, never jitted.

A loader subclasses :class:`Dataset` and implements ``_num_raw``, ``_load_raw`` (colour uint8 and
depth in metres at full resolution for the dataset's own frame ``j``), and sets ``intrinsics_full``,
``timestamps_raw`` and ``gt_poses_raw``. The base class applies what every layout shares: frame
selection (start, stride, max frames), depth truncation, integer downscaling and inpainting.
"""

from __future__ import annotations

import concurrent.futures
import copy
import dataclasses
import functools
import os
import pathlib
import zlib

import cv2
import numpy as np

from sgad_jax.config import DataConfig
from sgad_jax.types import Intrinsics, make_intrinsics


class DatasetError(Exception):
    """Bad input, or an output that cannot be written: the message is one line naming the file
    and the problem."""


class RunInterrupted(Exception):
    """SIGINT (Ctrl-C) or SIGTERM stopped a run after a frame or refinement step; what it computed
    is written."""

    def __init__(self, message: str, signum: int):
        super().__init__(message)
        self.signum = signum


@dataclasses.dataclass(frozen=True)
class BadFrame:
    """A frame that could not be read (yielded by :meth:`Dataset.frames` with ``skip_bad``)."""

    index: int  # position in the run's frame selection
    source_index: int  # position in the dataset's own frame list
    reason: str  # one line naming the file and the problem


@dataclasses.dataclass
class RGBDSample:
    """One frame on the host.

    Attributes:
        index: position in the run (0-based, after start / stride / max frames).
        source_index: position in the dataset's own frame list.
        timestamp: seconds (TUM) or the source index.
        depth_timestamp: when the depth image was taken, in the same unit (TUM: its own stamp,
            which differs from the colour stamp; elsewhere equal to ``timestamp``).
        rgb: (h, w, 3) uint8 colour (black when the dataset does not decode colour, ``Dataset.colour``).
        depth: (h, w) float32 measured depth in metres, 0 where missing.
        pose_gt: (4, 4) float64 camera-to-world ground truth (OpenCV axes), NaN if unknown.
        inpaint: whether :attr:`depth_filled` inpaints the holes of ``depth``.
        depth_device: ``depth`` already on the device, where the reader staged it
            (:meth:`Dataset.frames`' ``stage``), else None.
    """

    index: int
    source_index: int
    timestamp: float
    depth_timestamp: float
    rgb: np.ndarray
    depth: np.ndarray
    pose_gt: np.ndarray
    inpaint: bool = True
    depth_device: object = dataclasses.field(default=None, repr=False, compare=False)

    @functools.cached_property
    def depth_filled(self) -> np.ndarray:
        """(h, w) float32 depth with holes inpainted (``depth`` itself if inpainting is off).

        Computed on first use: inpainting is costly, and tracking never needs it.
        """
        return inpaint_depth(self.depth) if self.inpaint else self.depth


def read_image(path: pathlib.Path, *, depth: bool = False, decode: bool = True) -> np.ndarray:
    """Colour as (h, w, 3) uint8 RGB, or depth as a raw 2-D array; DatasetError when it cannot be read.

    With ``decode`` false, a colour PNG or JPEG is checked, not decoded (a run that only tracks
    never looks at colour, and decoding it took a core's milliseconds a frame from the tracking
    step): it must be readable, whole (its end marker present) and give its size in its header;
    the result is black of that size. Other formats, or a header that does not parse, are decoded.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        why = "a folder, not a file" if path.is_dir() else "broken symbolic link" if path.is_symlink() else "file not found"
        raise DatasetError(f"{path}: {why}")
    try:
        data = np.fromfile(path, np.uint8)
    except OSError as err:
        raise DatasetError(f"{path}: cannot read ({err.strerror or err})") from None
    if _truncated(data):
        raise DatasetError(f"{path}: truncated image file (it ends before the image does)")
    size = None if decode or depth else _header_size(memoryview(data))
    if size is not None:
        return np.zeros((size[1], size[0], 3), np.uint8)
    flags = cv2.IMREAD_UNCHANGED if depth else cv2.IMREAD_COLOR
    image = cv2.imdecode(data, flags) if data.size else None
    if image is None:
        raise DatasetError(f"{path}: cannot decode image (corrupt or unsupported format)")
    if depth:
        if image.ndim != 2:
            raise DatasetError(f"{path}: depth image must have one channel, got shape {image.shape}")
        if image.dtype.itemsize < 2:  # 8 bits cannot hold a depth map (a mask or a preview saved in its place)
            raise DatasetError(f"{path}: depth image is 8-bit, expected 16-bit integer or float depth")
        return image
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


#: :meth:`Dataset.frames` reads frames in batches of at most this many bytes of images (depth, and
#: colour and inpainted depth where they are made) and at most ``READ_BATCH_FRAMES`` frames.
READ_BATCH_BYTES = 48 << 20
READ_BATCH_FRAMES = 32


def _cores() -> int:
    """The cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _truncated(data: np.ndarray) -> bool:
    """Whether a PNG or JPEG file stops before its end marker. (OpenCV decodes a cut JPEG without
    an error, filling the missing rows with grey, so the marker is the only sign.)"""
    head, tail = bytes(data[:4]), bytes(data[-64:])
    if head.startswith(b"\x89PNG"):
        return b"IEND" not in tail[-16:]
    if head.startswith(b"\xff\xd8"):
        return b"\xff\xd9" not in tail
    return False


#: JPEG start-of-frame markers (they carry the image size): C0-CF but DHT, JPG and DAC.
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
#: Larger sizes in a header are left to the decoder (which refuses what it cannot hold), so that a
#: corrupt header does not become a black image of many gigabytes.
_HEADER_MAX_PIXELS = 1 << 26


def _header_size(data: memoryview) -> tuple[int, int] | None:
    """(width, height) from a PNG's IHDR or a JPEG's start-of-frame segment; None for another
    format, a header that does not parse, or a size beyond ``_HEADER_MAX_PIXELS``."""
    size = _header_fields(data)
    return size if size is not None and 0 < size[0] * size[1] <= _HEADER_MAX_PIXELS else None


def _header_fields(data: memoryview) -> tuple[int, int] | None:
    if data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR" and len(data) >= 24:
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    if data[:2] != b"\xff\xd8":
        return None
    pos = 2  # the segments after SOI: 0xFF, marker, then (but for RSTn / TEM) a 2-byte length
    while pos + 9 <= len(data) and data[pos] == 0xFF:
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
        elif marker in _JPEG_SOF:
            return int.from_bytes(data[pos + 7 : pos + 9], "big"), int.from_bytes(data[pos + 5 : pos + 7], "big")
        elif marker == 0x01 or 0xD0 <= marker <= 0xD7:
            pos += 2
        elif marker in (0xD9, 0xDA):  # the end, or the scan, before any frame header
            return None
        else:
            pos += 2 + int.from_bytes(data[pos + 2 : pos + 4], "big")
    return None


def inpaint_depth(depth: np.ndarray, radius: int = 5) -> np.ndarray:
    """Fill missing depth (0) with OpenCV's Navier-Stokes inpainting (``cv2.INPAINT_NS``).

    cv2.inpaint takes 8-bit or 32-bit float single-channel images; holes are where the mask is set.
    An all-missing frame is returned unchanged (nothing to propagate from).
    """
    missing = depth <= 0
    if not missing.any() or missing.all():
        return depth.astype(np.float32)
    filled = cv2.inpaint(depth.astype(np.float32), missing.astype(np.uint8), radius, cv2.INPAINT_NS)
    return np.where(missing, np.maximum(filled, 0.0), depth).astype(np.float32)


def add_depth_noise(depth: np.ndarray, share: float, sigma: float, seed: int, key: int) -> np.ndarray:
    """The paper's depth corruption (``../shared/tools/corrupt_depth.py``): each valid pixel is
    picked with probability ``share`` and gets ``N(0, sigma)`` metres added, floored at 1 mm.

    Drawn from ``(seed, key)``, ``key`` naming the depth image (the loader uses a checksum of its
    content), so that each image's noise is fixed whatever the frame selection or read order, and
    a repeated capture (TUM pairs some depth images with two colour images; 7-Scenes repeats whole
    captures under new names) stays the same measurement, with the same noise. (corrupt_depth.py also rounds to the file's depth
    unit, 0.2-1 mm, which is left out here.)

    Args:
        depth: (h, w) depth in metres, 0 where missing.
    """
    rng = np.random.default_rng([seed, key])
    valid = depth > 0
    pick = valid & (rng.random(depth.shape) < share)
    out = depth.astype(np.float64)
    out[pick] = np.maximum(out[pick] + rng.normal(0.0, sigma, int(pick.sum())), 1e-3)
    return out.astype(np.float32)


def downscale_rgbd(rgb: np.ndarray, depth: np.ndarray, factor: int, *, spread: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Colour by area averaging. Depth: a block whose valid depths agree within ``spread`` (relative)
    is one surface and gets their mean, the depth at the block's centre where the scaled intrinsics
    put it (one pixel of the block would sit half a full-resolution pixel off: on Replica that
    doubles the depth's error against the scene's mesh); a block across a depth edge gets its
    nearest depth, so no depth between two surfaces is made up; an empty block stays missing."""
    if factor == 1:
        return rgb, depth
    h, w = depth.shape
    hs, ws = h // factor, w // factor
    rgb = cv2.resize(rgb[: hs * factor, : ws * factor], (ws, hs), interpolation=cv2.INTER_AREA)
    blocks = depth[: hs * factor, : ws * factor].reshape(hs, factor, ws, factor).swapaxes(1, 2).reshape(hs, ws, -1)
    valid = blocks > 0
    count = valid.sum(-1)
    near = np.where(valid, blocks, np.inf).min(-1)
    far = np.where(valid, blocks, 0).max(-1)
    mean = np.where(valid, blocks, 0).sum(-1) / np.maximum(count, 1)
    out = np.where(far - near <= spread * near, mean, near)
    return rgb, np.where(count > 0, out, 0).astype(depth.dtype)


class Dataset:
    """Base class of every loader; see the module docstring."""

    layout: str = "?"
    #: Decode colour images (False: only check them, each frame's colour black; see :func:`read_image`).
    colour: bool = True
    intrinsics_full: Intrinsics
    timestamps_raw: np.ndarray  # (N,) float64
    depth_timestamps_raw: np.ndarray | None = None  # (N,) float64, when depth has stamps of its own
    gt_poses_raw: np.ndarray  # (N, 4, 4) float64, NaN where unknown
    gt_file: pathlib.Path | None = None  # where the ground truth is read from, for messages

    def __init__(self, root: pathlib.Path, cfg: DataConfig):
        self.root = pathlib.Path(root)
        self.cfg = cfg

    # --- implemented by loaders -------------------------------------------------------------
    def _num_raw(self) -> int:
        raise NotImplementedError

    def _load_raw(self, j: int) -> tuple[np.ndarray, np.ndarray]:
        """(rgb uint8 (H, W, 3), depth float32 metres (H, W)) of the dataset's own frame ``j``."""
        raise NotImplementedError

    # --- shared -----------------------------------------------------------------------------
    def _finish_init(self) -> None:
        """Call at the end of a loader's ``__init__``: validates options and selects frames."""
        cfg = self.cfg
        if cfg.stride < 1 or cfg.start < 0 or cfg.max_frames < 0 or cfg.downscale < 1:
            raise DatasetError(
                f"{self.root}: invalid frame selection start={cfg.start} stride={cfg.stride} "
                f"max_frames={cfg.max_frames} downscale={cfg.downscale}"
            )
        if cfg.intrinsics:
            if len(cfg.intrinsics) != 4:
                raise DatasetError(f"{self.root}: data.intrinsics needs 4 values (fx, fy, cx, cy), got {cfg.intrinsics}")
            fx, fy, cx, cy = cfg.intrinsics
            base = self.intrinsics_full
            try:
                self.intrinsics_full = make_intrinsics(fx, fy, cx, cy, base.width, base.height)
            except ValueError as e:
                raise DatasetError(f"{self.root}: data.intrinsics: {e}") from None
        n = self._num_raw()
        selection = np.arange(cfg.start, n, cfg.stride)
        if cfg.max_frames:
            selection = selection[: cfg.max_frames]
        if len(selection) == 0:
            raise DatasetError(f"{self.root}: no frames selected ({n} frames, start={cfg.start}, stride={cfg.stride})")
        self.selection = selection
        if cfg.nonfinite_depth not in ("error", "missing"):
            raise DatasetError(f"{self.root}: data.nonfinite_depth must be error or missing, got {cfg.nonfinite_depth!r}")
        self.warnings = self._check_gt()
        self.intrinsics = self.intrinsics_full.scaled(cfg.downscale) if cfg.downscale > 1 else self.intrinsics_full

    def _check_gt(self) -> list[str]:
        """Ground-truth poses that are missing or hold Inf/NaN for some of the selected frames (not
        for all: a dataset without ground truth is fine) become unknown (NaN), with one line each
        kind saying so: a run needs no ground truth, only its ATE leaves those frames out."""
        gt = np.array(self.gt_poses_raw, np.float64)
        sel = gt[self.selection]
        known = np.isfinite(sel).all(axis=(1, 2))
        if known.all() or not np.isfinite(sel).any():
            return []
        missing = np.isnan(sel).all(axis=(1, 2))
        lines = []
        for what, bad in (("holds Inf/NaN", ~known & ~missing), ("is missing", missing)):
            if bad.any():
                first = int(np.flatnonzero(bad)[0])
                lines.append(f"{self._gt_source(self.selection[first])}: the ground-truth pose {what} for {int(bad.sum())} of {len(sel)} frames (first: run frame {first}); ATE leaves them out")
        gt[self.selection[~known]] = np.nan
        self.gt_poses_raw = gt
        return lines

    def _gt_source(self, j: int):
        """The file that holds frame ``j``'s ground truth (named in warnings)."""
        return self.gt_file or self.root

    def without(self, source_indices) -> "Dataset":
        """A shallow copy whose selection leaves out the dataset's own frames ``source_indices``."""
        other = copy.copy(self)
        other.selection = self.selection[~np.isin(self.selection, np.asarray(list(source_indices), int))]
        return other

    @property
    def name(self) -> str:
        return self.root.name

    def __len__(self) -> int:
        return len(self.selection)

    @property
    def timestamps(self) -> np.ndarray:
        return np.asarray(self.timestamps_raw)[self.selection]

    @property
    def gt_poses(self) -> np.ndarray:
        return np.asarray(self.gt_poses_raw)[self.selection]

    @property
    def has_gt(self) -> bool:
        return bool(np.isfinite(self.gt_poses).all(axis=(1, 2)).any())

    def __getitem__(self, i: int) -> RGBDSample:
        if not 0 <= i < len(self):
            raise IndexError(i)
        j = int(self.selection[i])
        rgb, depth = self._load_raw(j)
        full = self.intrinsics_full
        if depth.shape != (full.height, full.width):
            raise DatasetError(
                f"{self.describe(j)}: depth is {depth.shape[1]}x{depth.shape[0]}, expected {full.width}x{full.height}"
            )
        if rgb.shape[:2] != depth.shape:
            raise DatasetError(
                f"{self.describe(j)}: colour is {rgb.shape[1]}x{rgb.shape[0]} but depth is {depth.shape[1]}x{depth.shape[0]}"
            )
        depth = np.asarray(depth, np.float32)
        if not np.isfinite(depth.sum()):  # one pass; the per-pixel check only when something is not finite
            finite = np.isfinite(depth)
            if self.cfg.nonfinite_depth != "missing" and not finite.all():
                raise DatasetError(
                    f"{self.describe(j, depth=True)}: depth holds {int((~finite).sum())} NaN/Inf pixels "
                    "(set data.nonfinite_depth=missing if they mark missing depth)"
                )
            depth = np.where(finite, depth, 0.0).astype(np.float32)
        depth = np.maximum(depth, np.float32(0.0))  # negative depth is missing
        if self.cfg.noise_share > 0:
            depth = add_depth_noise(depth, self.cfg.noise_share, self.cfg.noise_sigma, self.cfg.noise_seed, zlib.crc32(depth.tobytes()))
        if self.cfg.depth_trunc > 0:
            depth = np.where(depth <= self.cfg.depth_trunc, depth, 0.0).astype(np.float32)
        if not depth.any():
            raise DatasetError(f"{self.describe(j, depth=True)}: depth image has no valid pixel (all zero or beyond data.depth_trunc)")
        rgb, depth = downscale_rgbd(rgb, depth, self.cfg.downscale)
        return RGBDSample(
            index=i,
            source_index=j,
            timestamp=float(self.timestamps_raw[j]),
            depth_timestamp=float((self.timestamps_raw if self.depth_timestamps_raw is None else self.depth_timestamps_raw)[j]),
            rgb=rgb,
            depth=depth,
            pose_gt=np.asarray(self.gt_poses_raw[j], np.float64),
            inpaint=self.cfg.inpaint,
        )

    def frames(self, start: int = 0, *, skip_bad: bool = False, fill=None, stage=None):
        """``self[i]`` for ``i`` from ``start`` on, read in batches: a batch's frames are decoded
        at once, one per core, then handed out in order while nothing reads; for the frames ``i``
        with ``fill(i)`` true the depth is also inpainted (:attr:`RGBDSample.depth_filled`, which
        mapping needs) in the batch, and with ``stage`` (e.g. ``jax.device_put``) each depth is
        copied to the device there too (:attr:`RGBDSample.depth_device`, which the tracking step
        takes), so that the copy is not made inside the step.

        Why batches and not a thread reading beside the caller: the tracking step keeps every core
        busy, so decoding beside it slows it (a 16-bit depth PNG is 2.5 ms of libpng), and decoding
        on all cores between steps is faster overall (docs/method.md, "Frames are read in batches").

        A frame that cannot be read raises its :class:`DatasetError` when its turn comes, after
        every frame before it has been yielded; with ``skip_bad`` it is yielded as a
        :class:`BadFrame` instead, and reading goes on.
        """
        full = self.intrinsics_full
        pixels = full.width * full.height // max(self.cfg.downscale, 1) ** 2
        per_pixel = 4 + 3 * self.colour + 4 * (fill is not None) + 4 * (stage is not None)  # depth, RGB, inpainted, staged
        batch = max(1, min(READ_BATCH_FRAMES, READ_BATCH_BYTES // (per_pixel * pixels)))
        pool = concurrent.futures.ThreadPoolExecutor(min(_cores(), batch), thread_name_prefix="sgad-read")
        try:
            for first in range(start, len(self), batch):
                futures = [pool.submit(self._read_ahead, i, fill, stage) for i in range(first, min(first + batch, len(self)))]
                # The whole batch before the first frame: handed out as soon as it is read, a frame's
                # step would share the cores with the rest of the batch's decoding.
                concurrent.futures.wait(futures)
                for i, future in enumerate(futures, first):
                    try:
                        sample = future.result()
                    except DatasetError as err:
                        if not skip_bad:
                            raise
                        sample = BadFrame(i, int(self.selection[i]), str(err))
                    yield sample
        finally:
            pool.shutdown(wait=True, cancel_futures=True)  # at most the batch's reads in hand

    def _read_ahead(self, i: int, fill, stage) -> RGBDSample:
        sample = self[i]
        if fill is not None and fill(i):
            sample.depth_filled  # noqa: B018 (computed and cached now, with the batch)
        if stage is not None:
            sample.depth_device = stage(sample.depth)
        return sample

    def describe(self, j: int, *, depth: bool = False) -> str:
        """A file or folder naming frame ``j`` (its depth image with ``depth``), for error
        messages; loaders may override."""
        return f"{self.root} frame {j}"

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]
