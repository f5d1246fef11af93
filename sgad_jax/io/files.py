"""Output files written atomically: into a temporary file in the same folder, flushed, then renamed
over the target, so that a crash or a kill never leaves a half-written file (a leftover temporary
starts with a dot and ends in ``.tmp``)."""

from __future__ import annotations

import json
import os
import pathlib
import tempfile
from collections.abc import Callable
from typing import BinaryIO

from sgad_jax.io.base import DatasetError


_UMASK = os.umask(0o022)  # read once (the only way to read it is to set it), then put back
os.umask(_UMASK)


def atomic_write(path, write: Callable[[BinaryIO], object]) -> pathlib.Path:
    """Call ``write(f)`` on a binary file that becomes ``path`` only once complete. A file that
    cannot be written (a full disk, no permission) raises DatasetError naming it, in one line."""
    path = pathlib.Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as err:
        raise _cannot_write(path, err) from None
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
            os.fchmod(f.fileno(), 0o666 & ~_UMASK)  # mkstemp's 0600 would hide the file from others sharing the folder
        os.replace(tmp, path)
    except BaseException as err:
        pathlib.Path(tmp).unlink(missing_ok=True)
        if isinstance(err, OSError):
            raise _cannot_write(path, err) from None
        raise
    return path


def _cannot_write(path: pathlib.Path, err: OSError) -> DatasetError:
    return DatasetError(f"{path}: cannot write ({err.strerror or err})")


def write_bytes(path, data: bytes) -> pathlib.Path:
    return atomic_write(path, lambda f: f.write(data))


def write_text(path, text: str) -> pathlib.Path:
    return write_bytes(path, text.encode())


def write_json(path, data) -> pathlib.Path:
    return write_text(path, json.dumps(data, indent=2))


def numbered_files(folder: pathlib.Path, prefix: str, suffix: str) -> list[int]:
    """Indices ``i`` of the files ``folder/{prefix}{i:06d}{suffix}``, ascending. Other names (a
    copy such as ``frame_000003 (copy).npz``, ``rgb_3a.png``) are not the run's and are ignored."""
    found = []
    for p in folder.glob(f"{prefix}[0-9]*{suffix}"):
        digits = p.name[len(prefix) : -len(suffix)]
        if digits.isascii() and digits.isdigit() and p.name == f"{prefix}{int(digits):06d}{suffix}":
            found.append(int(digits))
    return sorted(found)
