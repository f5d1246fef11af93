"""The host loop's compiled programs, kept for the life of the process.

A run compiles its tracking step, its mapping batch and (with ``map.render_init``) the pose
refinement for the shapes of its frames. A second run, or a second :class:`sgad_jax.SLAM`, in the
same process with the same config and shapes gets the same executables back instead of tracing,
lowering and compiling them again.
"""

from __future__ import annotations

from typing import Callable, Hashable

import jax

_PROGRAMS: dict[Hashable, jax.stages.Compiled] = {}


def signature(tree) -> tuple:
    """What a compiled program depends on in its arguments: their structure and abstract values
    (shape, dtype, weak type)."""
    leaves, treedef = jax.tree.flatten(tree)
    return treedef, tuple(jax.typeof(x) for x in leaves)


def compiled(key: Hashable, lower: Callable[[], jax.stages.Lowered], options: dict | None = None) -> jax.stages.Compiled:
    """``lower().compile(options)``, once per process for ``key`` (which must name everything the
    program bakes in: static config, closed-over values, :func:`signature` of the arguments)."""
    program = _PROGRAMS.get(key)
    if program is None:
        program = _PROGRAMS[key] = lower().compile(compiler_options=options)
    return program


def clear() -> None:
    """Forget every kept program (as :func:`jax.clear_caches` does for JAX's own caches)."""
    _PROGRAMS.clear()
