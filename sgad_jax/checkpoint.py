"""Checkpoints of a run with orbax: everything needed to continue it.

A checkpoint is an orbax step folder under ``OUT/checkpoints/`` holding ``arrays`` (a flat dict of
arrays: the run state pytree :class:`sgad_jax.slam.RunState`, the trajectory so far, the mapped
frames' footprints) and ``meta`` (JSON:
the config, the dataset's identity, the position, per-frame scores). Orbax writes a step to a
temporary folder and renames it when complete, so a run killed at any moment (SIGKILL included)
leaves the previous complete checkpoint to resume from.
"""

from __future__ import annotations

import logging
import os
import pathlib
import re

import jax
import numpy as np
import orbax.checkpoint as ocp

from sgad_jax.config import ConfigError
from sgad_jax.io.base import DatasetError


def _manager(root: pathlib.Path) -> ocp.CheckpointManager:
    options = ocp.CheckpointManagerOptions(max_to_keep=2, enable_async_checkpointing=False)
    return ocp.CheckpointManager(root.absolute(), options=options)


def save(root: pathlib.Path, step: int, arrays: dict[str, np.ndarray], meta: dict) -> None:
    """Write checkpoint ``step`` (the number of frames done) under ``root``; DatasetError (one line)
    when it cannot be written, e.g. on a full disk (the previous checkpoint stays)."""
    # orbax's writer threads log a failed write with its traceback; the error raised here says it in one line
    absl_log = logging.getLogger("absl")
    level = absl_log.level
    absl_log.setLevel(logging.CRITICAL)
    try:
        with _manager(root) as mngr:
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
    finally:
        absl_log.setLevel(level)


def latest(root: pathlib.Path) -> tuple[dict[str, np.ndarray], dict] | None:
    """The newest complete checkpoint under ``root`` as ``(arrays, meta)``, or None."""
    if not root.is_dir():
        return None
    with _manager(root) as mngr:
        step = mngr.latest_step()
        if step is None:
            return None
        got = mngr.restore(step, args=ocp.args.Composite(arrays=ocp.args.StandardRestore(), meta=ocp.args.JsonRestore()))
    return {k: np.asarray(v) for k, v in got["arrays"].items()}, dict(got["meta"])


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
