"""Mapped frames' Gaussians off the devices: in host memory up to a budget, then on disk.

Each frame's :class:`~sgad_jax.types.PixelGaussians` is one uncompressed ``.npz`` file
``frame_XXXXXX.npz`` (XXXXXX: the frame's index in the run; fields ``rgb``, ``log_radius``,
``opacity_logit``, ``offset``, ``depth``, float32, each ``(h, w[, 3])``; and ``pose``, the 4x4
camera-to-world pose the frame was mapped at, when given), written atomically. The
newest frames stay in memory as well while they fit the budget, so a run's memory does not grow with
its length.
"""

from __future__ import annotations

import collections
import dataclasses
import os
import pathlib
import shutil
import tempfile
import weakref

import numpy as np

from sgad_jax.io.files import atomic_write, numbered_files
from sgad_jax.types import PixelGaussians

FIELDS = tuple(f.name for f in dataclasses.fields(PixelGaussians))


class GaussianStore:
    """``put(index, gaussians)`` / ``get(index)``; ``root=None`` spills to a temporary folder that
    is removed by :meth:`close` or when the store is garbage-collected."""

    def __init__(self, root: str | os.PathLike | None, budget_mb: float):
        self.temporary = root is None
        self.root = pathlib.Path(tempfile.mkdtemp(prefix="sgad_gaussians_") if root is None else root)
        self.root.mkdir(parents=True, exist_ok=True)
        # a temporary folder goes when the store does (or at exit)
        self._remove = weakref.finalize(self, shutil.rmtree, self.root, True) if self.temporary else None
        self.budget = int(budget_mb * 2**20)
        self._memory: collections.OrderedDict[int, PixelGaussians] = collections.OrderedDict()
        self._bytes = 0
        self._on_disk: set[int] = set(numbered_files(self.root, "frame_", ".npz"))
        self.count = 0  # Gaussians put so far
        self._poses: dict[int, np.ndarray] = {}

    def path(self, index: int) -> pathlib.Path:
        return self.root / f"frame_{index:06d}.npz"

    def put(self, index: int, g: PixelGaussians, pose: np.ndarray | None = None) -> None:
        g = PixelGaussians(**{k: np.asarray(getattr(g, k), np.float32) for k in FIELDS})
        if pose is not None:
            self._poses[index] = np.asarray(pose, np.float64)
        self.count += g.depth.size
        if index in self._memory:
            self._bytes -= _nbytes(self._memory.pop(index))
        self._on_disk.discard(index)
        self._memory[index] = g
        self._bytes += _nbytes(g)
        while self._bytes > self.budget and self._memory:
            old, og = self._memory.popitem(last=False)
            self._write(old, og)
            self._bytes -= _nbytes(og)

    def get(self, index: int) -> PixelGaussians:
        if index in self._memory:
            return self._memory[index]
        if index not in self._on_disk:
            raise KeyError(f"frame {index} has no stored Gaussians in {self.root}")
        with np.load(self.path(index)) as z:
            return PixelGaussians(**{k: z[k] for k in FIELDS})

    def __contains__(self, index: int) -> bool:
        return index in self._memory or index in self._on_disk

    def flush(self) -> None:
        """Write every frame still only in memory to disk (it stays in memory too)."""
        for index, g in self._memory.items():
            self._write(index, g)

    def close(self) -> None:
        """Remove a temporary store's folder now (a store with a root keeps its files)."""
        if self._remove is not None:
            self._remove()

    def _write(self, index: int, g: PixelGaussians) -> None:
        if index in self._on_disk:
            return
        extra = {"pose": self._poses[index]} if index in self._poses else {}
        atomic_write(self.path(index), lambda f: np.savez(f, **{k: getattr(g, k) for k in FIELDS}, **extra))
        self._on_disk.add(index)

    @property
    def memory_mb(self) -> float:
        return self._bytes / 2**20


def _nbytes(g: PixelGaussians) -> int:
    return sum(getattr(g, k).nbytes for k in FIELDS)
