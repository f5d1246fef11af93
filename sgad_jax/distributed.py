"""Mapping across devices and hosts with JAX's own runtime.

Once frames are tracked their mapping is independent (:func:`sgad_jax.slam.map_step` reads only
tracked frames and poses), so a batch of frames is mapped by ``vmap`` on each device and
``shard_map`` over a one-axis mesh of all devices of all processes. Each device maps the same
one-frame-per-device program whatever the device count, so results do not depend on it.

* One host, N devices: on CPU call :func:`use_cpu_devices` before anything touches JAX (the CLI's
  ``--devices N`` does); on GPU/TPU the host's devices are used as they are.
* Several hosts: :func:`initialize` (``jax.distributed.initialize``; CPU collectives over gloo),
  then every process runs the same host loop; each maps the frames on its devices and the renders
  are gathered so that every process scores every frame.
"""

from __future__ import annotations

import functools
import os
import re
import time

import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from sgad_jax import programs, slam, splat
from sgad_jax.config import ConfigError, MapConfig
from sgad_jax.types import Intrinsics

#: The mesh axis frames are spread over.
AXIS = "frames"


def use_cpu_devices(n: int) -> None:
    """Expose ``n`` XLA:CPU devices (one host). Must run before JAX initialises its backends."""
    if n < 1:
        raise ConfigError(f"--devices must be >= 1, got {n}")
    if n > 1:
        jax.config.update("jax_num_cpu_devices", n)


def initialize(coordinator: str | None = None, num_processes: int | None = None, process_id: int | None = None) -> None:
    """Join a multi-process run (``jax.distributed.initialize``); arguments left ``None`` come from
    the environment as JAX reads it (``JAX_COORDINATOR_ADDRESS``, ``JAX_NUM_PROCESSES``,
    ``JAX_PROCESS_ID``, or a cluster such as SLURM). CPU devices talk over gloo."""
    coordinator = coordinator or os.environ.get("JAX_COORDINATOR_ADDRESS")
    if num_processes is None and "JAX_NUM_PROCESSES" in os.environ:
        num_processes = int(os.environ["JAX_NUM_PROCESSES"])
    if process_id is None and "JAX_PROCESS_ID" in os.environ:
        process_id = int(os.environ["JAX_PROCESS_ID"])
    # JAX says these as a traceback, or fails deep in its client; one line here
    if (num_processes is not None or process_id is not None) and not coordinator:
        raise ConfigError("--num-processes / --process-id need --coordinator HOST:PORT (the address of process 0)")
    if coordinator and not re.fullmatch(r".+:\d{1,5}", coordinator):
        raise ConfigError(f"--coordinator {coordinator}: expected HOST:PORT, e.g. 10.0.0.1:1234")
    if num_processes is not None and (num_processes < 1 or process_id is None or not 0 <= process_id < num_processes):
        raise ConfigError(f"--process-id must lie in [0, --num-processes); got {process_id} of {num_processes}")
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    try:
        jax.distributed.initialize(coordinator, num_processes=num_processes, process_id=process_id)
    except (ValueError, RuntimeError) as err:
        raise ConfigError(f"cannot join the run at {coordinator}: {str(err).splitlines()[0]}") from None


def frames_mesh(per_process: int | None = None) -> Mesh:
    """A one-axis mesh over the first ``per_process`` devices of every process (default: all)."""
    chosen = []
    for p in range(jax.process_count()):
        local = [d for d in jax.devices() if d.process_index == p]
        if per_process is not None and per_process > len(local):
            raise ConfigError(
                f"{per_process} devices asked for, but process {p} has {len(local)} ({local[0].platform}); "
                "on CPU pass --devices before anything else starts JAX"
            )
        chosen += local[:per_process]
    return Mesh(np.asarray(chosen), (AXIS,))


class BatchMapper:
    """Maps ``mesh.size`` tracked frames at once, one per device.

    Call it with host (numpy) pytrees stacked along a leading batch axis of length ``size``:
    ``frames, poses, neighbour_gaussians, neighbours, neighbour_poses, present`` as for
    :func:`sgad_jax.slam.map_step`. It returns the whole batch's Gaussians and renders (``rgb`` and
    the surface's ``depth``, :func:`sgad_jax.splat.surface_depth`), numpy, gathered from every process: a later frame's neighbours are learned
    Gaussians that any process may have mapped.
    """

    def __init__(self, cfg: MapConfig, intr: Intrinsics, mesh: Mesh | None = None):
        self.mesh = frames_mesh() if mesh is None else mesh
        self.size = self.mesh.size
        self.sharding = NamedSharding(self.mesh, P(AXIS))
        self.cfg, self.intr = cfg, intr
        step = functools.partial(slam.map_step, cfg, intr=intr)

        def local(*batch):
            # One frame per device: the step on it directly (a vmap over an axis of one would
            # trace the whole step a second time to batch it).
            g, out, _ = step(*jax.tree.map(lambda x: x[0], batch))
            return jax.tree.map(lambda x: x[None], (g, out.rgb, splat.surface_depth(out)))

        self._fn = jax.jit(jax.shard_map(local, mesh=self.mesh, in_specs=P(AXIS), out_specs=P(AXIS)))
        self._compiled = None

    def _global(self, host):
        n = {len(x) for x in jax.tree.leaves(host)}
        if n != {self.size}:  # each device maps exactly one frame: another length would be cut short
            raise ValueError(f"BatchMapper on {self.size} device(s) takes batches of {self.size} frames, got {sorted(n)}")
        return jax.tree.map(lambda x: jax.make_array_from_callback(x.shape, self.sharding, lambda idx: x[idx]), host)

    def compile(self, *batch) -> float:
        """Compile for the batch's shapes once (the first call does it otherwise); returns the
        seconds it took (0 when already compiled)."""
        if self._compiled is not None:
            return 0.0
        t0 = time.perf_counter()
        args = self._global(batch)
        devices = tuple(d.id for d in self.mesh.devices.flat)
        key = ("map", self.cfg, self.intr.as_tuple(), self.intr.width, self.intr.height, devices, programs.signature(args))
        self._compiled = programs.compiled(key, lambda: self._fn.lower(*args))
        return time.perf_counter() - t0

    def __call__(self, *batch):
        self.compile(*batch)
        g, rgb, depth = self._compiled(*self._global(batch))
        return jax.tree.map(_gather, g), _gather(rgb), _gather(depth)


def _gather(x: jax.Array) -> np.ndarray:
    """The whole of a frames-sharded array on every process."""
    if x.is_fully_addressable:
        return np.asarray(x)
    return np.asarray(multihost_utils.process_allgather(x, tiled=True))
