"""The host side of mapping: batches of tracked frames mapped on the devices, their Gaussians kept in
a :class:`~sgad_jax.io.store.GaussianStore`, every render scored, and the scene's held-out views and
merged-map refinement afterwards. Used by :class:`sgad_jax.system.SLAM`."""

from __future__ import annotations

import dataclasses
import functools
import pathlib
import sys
import time

import cv2
import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from sgad_jax import lie, mapping, programs, scene, slam, splat
from sgad_jax.config import ConfigError, SLAMConfig
from sgad_jax.distributed import BatchMapper
from sgad_jax.eval import image, lpips_weights
from sgad_jax.io.files import write_bytes
from sgad_jax.io.store import GaussianStore
from sgad_jax.types import Frame, PixelGaussians, host_frame


#: Image scores of a rendered view: the keys of ``per_frame`` records and of the means in ``metrics.json``.
SCORES = ("psnr", "ssim", "ms_ssim", "lpips", "depth_l1_cm")


def neighbour_slots(index: np.ndarray, k: int, n: int, gap: int = 1) -> list[int]:
    """The slots of :class:`~sgad_jax.slam.Recent` (run indices ``index``, newest first, -1 empty)
    holding the neighbours of the frame in slot ``k``, newest first: every ``gap``-th of the ``n * gap``
    frames before it, those there are."""
    return [j for j in range(k + gap, k + 1 + n * gap, gap) if j < len(index) and index[j] >= 0]


class Mapper:
    """The appearance branch of the host loop: collects tracked frames (with ``n`` previous mapped
    frames as neighbours, every ``map.neighbour_gap``-th) into batches of ``map.batch`` frames,
    maps each batch (spread over the devices, one frame each), scores every frame's render and moves its Gaussians off the
    devices into a :class:`GaussianStore`. Afterwards it renders and scores held-out views from the
    scene (:mod:`sgad_jax.scene`) and refines the merged map."""

    def __init__(self, cfg: SLAMConfig, intr, out: pathlib.Path | None, save_renders: bool, mesh=None, *, progress: bool = True):
        self.cfg, self.intr = cfg, intr
        self.n = cfg.map.neighbours
        self.main = jax.process_index() == 0
        self.progress = progress  # bars on the scene's long steps (held-out scoring, refinement)
        self.renders = out / "renders" if (save_renders and out is not None and self.main) else None
        if self.renders is not None:
            self.renders.mkdir(parents=True, exist_ok=True)
        self.store = GaussianStore(None if out is None else out / "gaussians", cfg.map.host_budget_mb)
        self.batch = BatchMapper(cfg.map, intr, mesh)
        self.batch_size = cfg.map.batch or self.batch.size
        self.scene = scene.Scene(cfg.scene, intr, self.store.get)  # the mapped frames, for rendering any view
        self.refine = None
        self.compile_s = 0.0
        self.per_frame: list[dict] = []  # scores of every rendered view, in the order scored
        self.seconds: list[float] = []  # per mapped frame: its batch's time over its batch's frames
        if cfg.map.psnr_protocol not in image.PSNR_PROTOCOLS:
            raise ConfigError(f"map.psnr_protocol must be one of {', '.join(image.PSNR_PROTOCOLS)}, got {cfg.map.psnr_protocol!r}")
        self.lpips_missing: str | None = None
        try:
            self.lpips_weights = lpips_weights.load_lpips_weights()
        except lpips_weights.LPIPSUnavailable as err:  # a corrupt weight file
            self.lpips_weights, self.lpips_missing = None, str(err)
        if self.lpips_weights is None and self.lpips_missing is None:
            try:
                image.lpips(np.zeros((32, 32, 3)), np.zeros((32, 32, 3)))
            except lpips_weights.LPIPSUnavailable as err:  # its message says where it looked and what to do
                self.lpips_missing = str(err)
        if self.lpips_missing and self.main:
            print(f"warning: LPIPS not computed: {self.lpips_missing}", file=sys.stderr)

    def empty_recent(self) -> slam.Recent:
        """The run state's recent frames: room for a batch and its frames' neighbours."""
        return slam.empty_recent(self.batch_size + self.n * self.cfg.map.neighbour_gap, self.intr.height, self.intr.width)

    def refine_guess(self, recent: slam.Recent, frame: Frame, guess):
        """Rendering-based initialisation of the pose guess from the previous frame's Gaussians as
        initialised from its RGB-D (so tracking never waits for mapping)."""
        if int(recent.index[0]) < 0:
            return guess
        args = (jax.tree.map(lambda x: x[0], recent.frame), jax.tree.map(lambda x: x[0], recent.pose), frame, guess)
        if self.refine is None:
            t0 = time.perf_counter()
            cfg, intr, its = self.cfg.map, self.intr, self.cfg.map.render_init_iterations

            def fn(prev, pose_prev, frame, guess):
                g_prev = mapping.init_gaussians(prev, intr)
                return mapping.refine_pose(cfg, g_prev, pose_prev, frame, guess, intr, iterations=its)

            key = ("refine", cfg, intr.as_tuple(), intr.width, intr.height, programs.signature(args))
            self.refine = programs.compiled(key, lambda: jax.jit(fn).lower(*args))
            self.compile_s += time.perf_counter() - t0
        return self.refine(*args)

    def push(self, recent: slam.Recent, index: int, frame: Frame, pose: lie.SE3) -> slam.Recent:
        """Queue a tracked frame; map the queue when it fills a batch."""
        recent = slam.remember(recent, frame, pose, index)
        return self.flush(recent) if int(recent.queued) == self.batch_size else recent

    def _neighbour_gaussians(self, index: int, frame: Frame) -> PixelGaussians:
        """A neighbour's fixed Gaussians: its learned ones once mapped (paper Eq. 1), else initial.
        (Mapped means in this run's record: after a resume, a killed run's later files are stale.)"""
        if self.cfg.map.learn_neighbours and index in self.scene.poses:
            return self.store.get(index)
        return jax.tree.map(np.asarray, mapping.init_gaussians(frame, self.intr, radius_init=self.cfg.map.radius_init))

    def flush(self, recent: slam.Recent) -> slam.Recent:
        """Map every queued frame: the batch's neighbours are fixed first (frames of the same batch
        contribute their initial Gaussians), then it runs in chunks of one frame per device (the
        last chunk padded by repeating its last frame), so results do not depend on the devices.
        Returns ``recent`` with an empty queue."""
        queued = int(recent.queued)
        if not queued:
            return recent
        stack = lambda *xs: np.stack(xs)  # noqa: E731
        host = jax.tree.map(np.asarray, recent)
        entry = lambda k: (int(host.index[k]), jax.tree.map(lambda x: x[k], host.frame), jax.tree.map(lambda x: x[k], host.pose))  # noqa: E731
        pending, rows = [entry(k) for k in reversed(range(queued))], []  # oldest first
        for k, (_, frame, pose) in zip(reversed(range(queued)), pending):
            have = [entry(j) for j in neighbour_slots(host.index, k, self.n, self.cfg.map.neighbour_gap)]
            nb = have + [have[0] if have else (-1, frame, pose)] * (self.n - len(have))
            rows.append((
                frame,
                pose,
                jax.tree.map(stack, *[self._neighbour_gaussians(i, f) for i, f, _ in nb]),
                jax.tree.map(stack, *[f for _, f, _ in nb]),
                jax.tree.map(stack, *[p for _, _, p in nb]),
                np.asarray([True] * len(have) + [False] * (self.n - len(have))),
            ))
        size = self.batch.size
        results = []
        for c in range(0, len(rows), size):
            chunk = rows[c : c + size]
            chunk = chunk + [chunk[-1]] * (size - len(chunk))
            batch = [jax.tree.map(stack, *col) for col in zip(*chunk)]
            self.compile_s += self.batch.compile(*batch)
            t0 = time.perf_counter()
            gs, rgb, depth = self.batch(*batch)
            real = min(size, len(rows) - c)
            self.seconds += [(time.perf_counter() - t0) / real] * real
            results += [(jax.tree.map(lambda x: x[j], gs), rgb[j], depth[j]) for j in range(real)]
        for (index, frame, pose), (g, rgb, depth) in zip(pending, results):
            pose = np.asarray(pose.as_matrix(), np.float64)
            self.store.put(index, g, pose)
            self.scene.add(index, pose, frame.depth, frame.valid)
            self._score(index, frame, rgb, depth)
        return dataclasses.replace(recent, queued=jnp.zeros((), jnp.int32))

    def _score(self, index: int, frame: Frame, rgb: np.ndarray, depth: np.ndarray, *, kind: str = "", mapped: bool = True) -> dict:
        """Score a render; ``kind`` "" (a frame of the run, kept in ``per_frame``: ``mapped``, or
        between keyframes and rendered from the scene), "nvs" (held out) or "test" (a dataset's
        test view): its renders are written as ``{kind}_rgb_XXXXXX.png``."""
        rgb = np.clip(rgb, 0.0, 1.0)
        scores = image.score_view(rgb, depth, frame.rgb, frame.depth, frame.valid, protocol=self.cfg.map.psnr_protocol, lpips_weights=self.lpips_weights)
        rec = {"index": index, "holdout": kind != "", "mapped": mapped and not kind, **scores}
        if self.renders is not None:
            prefix = f"{kind}_" if kind else ""
            mm = np.clip(depth * 1000.0 + 0.5, 0, 65535).astype(np.uint16)
            for name, img in (("rgb", cv2.cvtColor((rgb * 255.0 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR)), ("depth", mm)):
                write_bytes(self.renders / f"{prefix}{name}_{index:06d}.png", cv2.imencode(".png", img)[1].tobytes())
        if not kind:
            self.per_frame.append(rec)
        return rec

    # The scene: held-out views and the merged-map refinement.
    def score_views(self, indices: list[int], poses: np.ndarray, source, kind: str = "nvs") -> list[dict]:
        """Render each view ``source(i)`` at camera-to-world ``poses[i]`` from the scene and score it
        (``kind`` as in :meth:`_score`; "": frames between keyframes)."""
        if not len(self.scene):
            return []
        recs = []
        desc = f"{kind} views" if kind else "frames between keyframes"
        for index in tqdm(indices, desc=desc, unit="view", disable=not (self.progress and self.main) or len(indices) < 5, file=sys.stderr):
            out = self.scene.render(poses[index])
            recs.append(self._score(index, host_frame(source(index), fill=False), out.rgb, np.asarray(splat.surface_depth(out)), kind=kind, mapped=False))
        return recs

    def finetune(self, iterations: int, poses: np.ndarray, source, seed: int, stop=None) -> dict:
        """The merged-map refinement: ``iterations`` Adam steps, each on a random mapped frame's
        view rendered from its ``scene.frames`` best-covering frames, all of whose Gaussians move;
        fewer when ``stop()`` turns true (a Ctrl-C). The refined frames' Gaussians and Adam moments
        are held in host memory up to ``scene.finetune_budget_mb``, the rest in a temporary folder
        meanwhile; the refined Gaussians then replace the stored ones.
        Returns the steps taken, the seconds they took and the mean loss of the first and last 50 (of each half, when fewer than 100).
        (Call with the queue mapped.)"""
        mapped = sorted(self.scene.poses)
        if not mapped or iterations <= 0:
            return {}
        # The refined frames' Gaussians and Adam moments (the others are read from the store), in
        # host memory up to scene.finetune_budget_mb and beyond it in a temporary folder: a long
        # run's would not fit (three copies of its map).
        params, mu, nu = (GaussianStore(None, self.cfg.scene.finetune_budget_mb / 3) for _ in range(3))
        count: dict[int, np.ndarray] = {}  # Adam's step count of each frame refined so far

        def gaussians(i: int) -> PixelGaussians:
            return params.get(i) if i in count else self.store.get(i)

        def state(i: int) -> scene.AdamState:
            if i not in count:
                return jax.tree.map(np.asarray, scene.adam_init(self.store.get(i)))
            return scene.AdamState(mu=mu.get(i), nu=nu.get(i), count=count[i])

        frames = functools.lru_cache(maxsize=64)(lambda i: host_frame(source(i), fill=False))  # training views, read again
        rng = np.random.default_rng(seed)
        chosen_of = {i: self.scene.frames_for(poses[i]) for i in mapped}
        losses, t0 = [], time.perf_counter()
        for _ in tqdm(range(iterations), desc="refining the merged map", unit="step", disable=not (self.progress and self.main), file=sys.stderr):
            if stop is not None and stop():
                break
            view = mapped[rng.integers(len(mapped))]
            chosen = chosen_of[view]
            gs, ps, present = self.scene.stack(chosen, gaussians)
            st, _, _ = self.scene.stack(chosen, state)
            f = frames(view)
            gs, st, loss = scene.finetune_step(
                self.cfg.map, gs, st, ps, present, f.rgb, f.depth, f.valid, _pose(poses[view]), self.intr,
                composite=self.cfg.scene.composite, layers=self.cfg.scene.layers, lr_scale=self.cfg.scene.finetune_lr_scale, offsets=self.cfg.scene.finetune_offsets,
            )
            gs, st = jax.tree.map(np.asarray, (gs, st))
            for j, i in enumerate(chosen):  # copies: a slice would keep the whole stack alive
                params.put(i, jax.tree.map(lambda x: x[j].copy(), gs))
                mu.put(i, jax.tree.map(lambda x: x[j].copy(), st.mu))
                nu.put(i, jax.tree.map(lambda x: x[j].copy(), st.nu))
                count[i] = st.count[j]
            losses.append(float(loss))
        for i in count:  # the frames no step chose keep their stored Gaussians
            self.store.put(i, params.get(i), self.scene.poses[i])
        for store in (params, mu, nu):
            store.close()
        if not self.store.temporary:
            self.store.flush()  # the files on disk are the refined Gaussians
        k = max(1, min(50, len(losses) // 2))  # the first and last k steps, apart (else a short refinement's overlap)
        first, last = (float(np.mean(part)) if losses else None for part in (losses[:k], losses[-k:]))
        return {"finetune_iterations": len(losses), "finetune_s": time.perf_counter() - t0, "finetune_loss_first": first, "finetune_loss_last": last}

    def metrics(self) -> dict:
        out = means(self.per_frame)
        h, w = self.intr.height, self.intr.width
        mean = lambda xs: float(np.mean(xs)) if xs else None  # noqa: E731
        out.update(
            psnr_protocol=self.cfg.map.psnr_protocol,
            mapped_frames=len(self.seconds),
            map_every=self.cfg.map.every,
            map_s_per_frame=mean(self.seconds[self.batch.size :] or self.seconds),
            map_compile_s=self.compile_s,
            devices=self.batch.size,
            map_batch=self.batch_size,
            gaussians_total=len(self.seconds) * h * w,  # the paper's NUM1
            gaussians_on_devices=self.batch.size * (1 + self.n) * h * w,  # NUM2: each device's frame and its neighbours'
            gaussians_host_mb=self.store.memory_mb,
        )
        between = [r for r in self.per_frame if not r.get("mapped", True)]
        if between:  # map.every > 1: the frames rendered from the scene, also in the means above
            out.update(means(between, "between_"), between_frames=len(between))
        if self.lpips_missing:
            out["lpips_missing"] = self.lpips_missing
        return out

    # Checkpoints (the recent frames are in the run state): the mapped frames' record.
    def state(self) -> tuple[dict, dict]:
        self.store.flush()
        mapped, arrays = self.scene.arrays()
        return arrays, {"mapped": mapped, "per_frame": self.per_frame, "seconds": self.seconds}

    def restore(self, arrays: dict, meta: dict) -> None:
        self.scene.restore(meta["mapped"], arrays)
        self.per_frame = list(meta["per_frame"])
        self.seconds = list(meta["seconds"])


def means(records: list[dict], prefix: str = "") -> dict:
    """Mean of each score over the records that have it (None when none has)."""
    out = {}
    for key in SCORES:
        xs = [r[key] for r in records if key in r]
        out[prefix + key] = float(np.mean(xs)) if xs else None
    return out


def _pose(T: np.ndarray) -> lie.SE3:
    return jax.tree.map(np.asarray, lie.from_matrix(T))
