"""``jax.vmap`` of :func:`sgad_jax.map_frame` over a batch of frames.

Once frames are tracked their mapping is independent, so one batched call optimises several
frames' Gaussians at once (what :mod:`sgad_jax.distributed` spreads over devices). Each frame is
fitted to its own view and one neighbour's; the batched result is compared with a Python loop of
single calls.

Run: ``python examples/vmap_map_frame.py [--frames 4 --iterations 10]``.
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np

from sgad_jax import MapConfig, Views, init_gaussians, lie, make_frame, map_frame, open_dataset
from sgad_jax.config import DataConfig, SyntheticConfig


def _stack(*xs):
    return jnp.stack(xs)


def main(frames: int = 4, width: int = 64, height: int = 48, iterations: int = 10, verbose: bool = True) -> dict:
    """Returns ``{"offset", "loss", "max_abs_difference"}``: the batched offsets (f, h, w), the
    batched loss curves (f, iterations) and the largest difference from the loop over any field."""
    ds = open_dataset(DataConfig(layout="synthetic", synthetic=SyntheticConfig(frames=frames + 1, width=width, height=height)))
    intr = ds.intrinsics
    fr = [make_frame(ds[i].rgb, ds[i].depth, ds[i].depth_filled) for i in range(frames + 1)]
    poses = [lie.from_matrix(jnp.asarray(ds.gt_poses[i], jnp.float32)) for i in range(frames + 1)]
    cfg = MapConfig(iterations=iterations)

    def views(i):  # frame i + 1, its own view first, then frame i's as the neighbour
        own, nb = i + 1, i
        return Views(
            rgb=jnp.stack([fr[own].rgb, fr[nb].rgb]), depth=jnp.stack([fr[own].depth, fr[nb].depth]),
            valid=jnp.stack([fr[own].valid, fr[nb].valid]), pose=jax.tree.map(_stack, poses[own], poses[nb]),
            present=jnp.ones(2, bool),
        )

    gs = [init_gaussians(fr[i + 1], intr) for i in range(frames)]
    vs = [views(i) for i in range(frames)]
    ps = poses[1:]

    one = jax.jit(lambda g, p, v: map_frame(cfg, g, p, v, intr))
    batched = jax.jit(jax.vmap(lambda g, p, v: map_frame(cfg, g, p, v, intr)))
    out_b, info_b = batched(jax.tree.map(_stack, *gs), jax.tree.map(_stack, *ps), jax.tree.map(_stack, *vs))
    loop = [one(g, p, v) for g, p, v in zip(gs, ps, vs)]
    out_l = jax.tree.map(_stack, *[g for g, _ in loop])
    diff = max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(jax.tree.leaves(out_b), jax.tree.leaves(out_l)))
    loss = np.asarray(info_b.loss)
    if verbose:
        print(f"{frames} frames of {width}x{height}, {iterations} iterations each, in one vmapped call")
        print("loss, first -> last iteration:", ", ".join(f"{a:.4f} -> {b:.4f}" for a, b in zip(loss[:, 0], loss[:, -1])))
        print(f"largest difference from a Python loop of single calls: {diff:.2e}")
    return {"offset": np.asarray(out_b.offset), "loss": loss, "max_abs_difference": diff}


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=4)
    p.add_argument("--iterations", type=int, default=10)
    a = p.parse_args()
    main(a.frames, iterations=a.iterations)
