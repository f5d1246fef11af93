import atexit
import importlib.metadata
import os
import pathlib
import shutil
import tempfile

import pytest

# The tests start CLI runs in subprocesses that compile the same programs as each other and as the
# test process: JAX's persistent compilation cache, in a folder of this session, compiles each once.
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    _cache = tempfile.mkdtemp(prefix="sgad-jax-tests-xla-")
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _cache
    atexit.register(shutil.rmtree, _cache, ignore_errors=True)
# Every program, not only those that took a second to compile (JAX's default): the many small ones
# are compiled again by each CLI subprocess and by each test module after its caches are cleared.
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")

# Most of the suite's time is XLA:CPU compiling the unrolled renderer for tiny inputs. Its older loop
# emitters, and LLVM without its optimisation passes, compile it in far less time and compute the
# same values up to float32 rounding (the tests' tolerances hold either way); the package keeps
# XLA's defaults, which run faster. Only for the jaxlib it was measured on: XLA aborts on a flag it
# does not know. Flags the caller sets win.
_FAST_COMPILE = {
    "xla_cpu_use_fusion_emitters": "false",
    "xla_backend_optimization_level": "0",
    "xla_llvm_disable_expensive_passes": "true",
}
if importlib.metadata.version("jaxlib").startswith("0.10."):
    _flags = os.environ.get("XLA_FLAGS", "")
    _flags += "".join(f" --{k}={v}" for k, v in _FAST_COMPILE.items() if k not in _flags)
    os.environ["XLA_FLAGS"] = _flags.strip()

SHARED_DATA = pathlib.Path(os.environ.get("SGAD_SHARED_DATA", pathlib.Path(__file__).resolve().parents[2] / "shared" / "data"))


def shared(name: str) -> pathlib.Path:
    """A folder of ../shared/data, or skip the test when it is absent."""
    path = SHARED_DATA / name
    if not path.is_dir():
        pytest.skip(f"real data {path} not available (set SGAD_SHARED_DATA to the shared/data folder)")
    return path


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop each test module's compiled programs when it ends. XLA:CPU maps every executable's
    code into memory, and one process running the whole suite otherwise accumulates tens of
    thousands of mappings, near the kernel's per-process limit (vm.max_map_count, 65530), past
    which compilation crashes."""
    yield
    import gc

    import jax

    from sgad_jax import programs

    jax.clear_caches()
    programs.clear()
    gc.collect()
