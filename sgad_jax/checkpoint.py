"""Checkpoints of a run with orbax: everything needed to continue it.

A checkpoint is an orbax step folder under ``OUT/checkpoints/`` holding ``arrays`` (a flat dict of
arrays: the run state pytree :class:`sgad_jax.slam.RunState`, the trajectory so far, the mapped
frames' footprints) and ``meta`` (JSON:
the config, the dataset's identity, the position, per-frame scores). Orbax writes a step to a
temporary folder and renames it when complete, so a run killed at any moment (SIGKILL included)
leaves the previous complete checkpoint to resume from.
"""

from __future__ import annotations

import contextlib
import logging
import os
import pathlib
import re
import shutil
import sys

import jax
import numpy as np
import orbax.checkpoint as ocp

from sgad_jax.config import ConfigError
from sgad_jax.io.base import DatasetError


@contextlib.contextmanager
def _quiet_orbax():
    """orbax logs a failed write or read (with its traceback) on top of raising it; the errors
    raised here say it in one line."""
    absl_log = logging.getLogger("absl")
    level = absl_log.level
    absl_log.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        absl_log.setLevel(level)


def _manager(root: pathlib.Path) -> ocp.CheckpointManager:
    options = ocp.CheckpointManagerOptions(max_to_keep=2, enable_async_checkpointing=False)
    return ocp.CheckpointManager(root.absolute(), options=options)


def save(root: pathlib.Path, step: int, arrays: dict[str, np.ndarray], meta: dict) -> None:
    """Write checkpoint ``step`` (the number of frames done) under ``root``; DatasetError (one line)
    when it cannot be written, e.g. on a full disk (the previous checkpoint stays)."""
    try:
        with _quiet_orbax(), _manager(root) as mngr:
            mngr.save(step, args=ocp.args.Composite(arrays=ocp.args.StandardSave(arrays), meta=ocp.args.JsonSave(meta)), force=True)
    except OSError as err:
        raise DatasetError(f"{root}: cannot write checkpoint {step} ({err.strerror or err})") from None
    except ValueError as err:  # tensorstore reports I/O failures as "STATUS_CODE: ..." ValueErrors
        text = str(err)
        if not re.match(r"[A-Z_]+: ", text):
            raise
        code = re.search(r"os_error_code='?(\d+)", text)
        reason = os.strerror(int(code.group(1))) if code else text.split(":")[0]
        raise DatasetError(f"{root}: cannot write checkpoint {step} ({reason})") from None


def latest(root: pathlib.Path) -> tuple[dict[str, np.ndarray], dict] | None:
    """The newest readable checkpoint under ``root`` as ``(arrays, meta)``, or None when there is
    none. A damaged step (a file cut or deleted, a stray folder) is passed over with a warning line
    for the one before it; DatasetError (one line) when every step is damaged."""
    if not root.is_dir():
        return None
    damaged = []
    with _quiet_orbax(), _manager(root) as mngr:
        for step in sorted(mngr.all_steps(), reverse=True):
            try:
                got = mngr.restore(step, args=ocp.args.Composite(arrays=ocp.args.StandardRestore(), meta=ocp.args.JsonRestore()))
                meta = dict(got["meta"])
                if not {"identity", "run"} <= meta.keys():
                    raise KeyError("meta has no identity or run")
            except Exception as err:  # orbax and tensorstore raise many kinds (ValueError, KeyError, JSON errors) for one cause
                damaged.append((f"{root / str(step)}: damaged checkpoint ({str(err).splitlines()[0][:120] if str(err) else type(err).__name__})", step))
                continue
            for line, bad in damaged:
                print(f"sgad-jax: warning: {line}; removed, resuming from step {step}", file=sys.stderr)
                shutil.rmtree(root / str(bad), ignore_errors=True)  # the run writes that step again
            return {k: np.asarray(v) for k, v in got["arrays"].items()}, meta
    if damaged:
        raise DatasetError(f"{damaged[0][0]}, and no older one is readable: rerun without --resume or with a new --out")
    return None


def flatten(prefix: str, tree) -> dict[str, np.ndarray]:
    """``{prefix/i: leaf}`` for the leaves of ``tree`` (restored by :func:`unflatten`)."""
    return {f"{prefix}/{i:03d}": np.asarray(x) for i, x in enumerate(jax.tree.leaves(tree))}


def unflatten(prefix: str, arrays: dict[str, np.ndarray], like):
    """The tree with the structure of ``like`` from the leaves :func:`flatten` wrote."""
    leaves, treedef = jax.tree.flatten(like)
    keys = [f"{prefix}/{i:03d}" for i in range(len(leaves))]
    stored = sorted(k for k in arrays if k.startswith(prefix + "/"))
    if stored != keys or any(np.shape(arrays[k]) != np.shape(ref) for k, ref in zip(keys, leaves)):
        raise ConfigError(
            f"checkpoint {prefix} does not fit this run ({len(stored)} arrays, this run has {len(leaves)}, or their shapes differ):"
            " made with other settings or by another sgad_jax version; rerun without --resume or with a new --out"
        )
    got = [arrays[k] for k in keys]
    return jax.tree.unflatten(treedef, [jax.numpy.asarray(g, dtype=np.asarray(r).dtype) for g, r in zip(got, leaves)])
