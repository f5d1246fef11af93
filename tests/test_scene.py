"""The scene renderer against the dense reference renderer, frame selection, the merged-map
refinement's Adam step against optax, and a held-out-view run end to end."""

import dataclasses
import functools
import json

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from sgad_jax import lie, scene, splat, splat_ref
from sgad_jax import mapping
from sgad_jax.cli import main
from sgad_jax.config import MapConfig
from sgad_jax.types import Intrinsics, PixelGaussians

H, W = 10, 14


def _intr(dtype=jnp.float64) -> Intrinsics:
    return Intrinsics(fx=dtype(13.0), fy=dtype(14.0), cx=dtype(6.6), cy=dtype(4.7), width=W, height=H)


def _frames(k: int, seed: int) -> PixelGaussians:
    rng = np.random.default_rng(seed)
    f = lambda *s: jnp.asarray(rng.uniform(*s, size=(k, H, W)))  # noqa: E731
    return PixelGaussians(
        rgb=jnp.asarray(rng.uniform(0, 1, (k, H, W, 3))), log_radius=jnp.log(f(0.1, 0.4)),
        opacity_logit=f(-1.0, 3.0), offset=f(-0.1, 0.1), depth=f(1.0, 3.0),
    )


def _slot_counts(gs, poses, view, intr, window=3) -> int:
    """The most Gaussians whose centre rounds onto one slot (what ``layers`` must hold)."""
    attrs = splat.project_frames(gs, poses, view, intr)
    u, v = np.round(np.asarray(attrs[0])).astype(int), np.round(np.asarray(attrs[1])).astype(int)
    keep = np.asarray(attrs[2]) > splat.NEAR
    _, counts = np.unique(np.stack([u[keep], v[keep]]), axis=1, return_counts=True)
    return int(counts.max())


#: Layers of the depth-composite tests: enough for every slot of their frames (each asserts it).
DENSE_LAYERS = 6


@functools.partial(jax.jit, static_argnames="renderer")
def _dense_vjp(gs, poses, view, intr, ct, renderer):
    """Gradients of ``<render, ct>`` with respect to the Gaussians' colours, opacities, offsets
    and radii and a perturbation of the view pose (at zero), through the depth composite or the
    dense reference (jitted at module level, so the seeds share one compiled program)."""

    def vjp(g, xi):
        g = dataclasses.replace(gs, rgb=g[0], opacity_logit=g[1], offset=g[2], log_radius=g[3])
        v = lie.exp(xi) @ view
        if renderer == "scene":
            out = scene.render_scene(g, poses, v, intr, composite="depth", layers=DENSE_LAYERS)
        else:
            out = splat_ref.render(g, poses, v, intr)
        return sum(jnp.vdot(o, c) for o, c in zip(out, ct))

    return jax.grad(vjp, argnums=(0, 1))((gs.rgb, gs.opacity_logit, gs.offset, gs.log_radius), jnp.zeros(6, view.wxyz_xyz.dtype))


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_render_scene_matches_the_dense_reference(seed):
    """Depth compositing: values and vector-Jacobian products (colours, opacities, offsets, radii,
    the view pose) of three overlapping frames, with enough layers that no Gaussian is dropped."""
    with jax.enable_x64(True):
        intr = _intr()
        gs = _frames(3, seed)
        poses = lie.exp(jnp.asarray(np.random.default_rng(seed + 10).normal(0, 0.04, (3, 6))))
        view = lie.exp(jnp.asarray(np.random.default_rng(seed + 20).normal(0, 0.04, 6)))
        # one layer count for both seeds (they share the compiled programs), and none is dropped
        assert 2 <= _slot_counts(gs, poses, view, intr) <= DENSE_LAYERS
        fast = scene.render_scene(gs, poses, view, intr, composite="depth", layers=DENSE_LAYERS)
        ref = jax.jit(splat_ref.render)(gs, poses, view, intr)
        for a, b in zip(fast, ref):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-9)

        rng = np.random.default_rng(seed + 30)
        ct = [jnp.asarray(rng.normal(size=x.shape)) for x in ref]
        got = _dense_vjp(gs, poses, view, intr, ct, "scene")
        want = _dense_vjp(gs, poses, view, intr, ct, "reference")
        for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-9)


@functools.partial(jax.jit, static_argnames="tolerance")
def _priority_reference(gs, poses, view, intr, tolerance):
    """The priority composite from the dense reference renderer, frame by frame: at each pixel the
    frames' surfaces from the last to the first, each laid over the result so far unless the
    result's covered surface lies nearer than (1 - tolerance) times its own."""
    rgb, depth, alpha = None, None, None
    for j in reversed(range(gs.depth.shape[0])):
        r = splat_ref.render(jax.tree.map(lambda x: x[j : j + 1], gs), jax.tree.map(lambda x: x[j : j + 1], poses), view, intr)
        if rgb is None:
            rgb, depth, alpha = r
            continue
        surf_new = r[1] / jnp.maximum(r[2], 1e-3)
        surf_old = depth / jnp.maximum(alpha, 1e-3)
        old_in_front = jax.lax.stop_gradient((alpha > 0.5) & (surf_old < (1 - tolerance) * surf_new))
        t_new, t_old = 1 - r[2], 1 - alpha
        rgb = jnp.where(old_in_front[..., None], rgb + t_old[..., None] * r[0], r[0] + t_new[..., None] * rgb)
        depth = jnp.where(old_in_front, depth + t_old * r[1], r[1] + t_new * depth)
        alpha = jnp.where(old_in_front, alpha + t_old * r[2], r[2] + t_new * alpha)
    return rgb, depth, alpha


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 2])
def test_priority_render_scene_matches_the_dense_reference(seed):
    """Priority compositing (the default): values and vector-Jacobian products against the dense
    reference renderer of each frame composited by an independent per-pixel rule."""
    with jax.enable_x64(True):
        intr = _intr()
        # frames of two walls (1.5 and 2.5 m, the second a separate surface): within a frame no two
        # Gaussians share a slot, so one layer a frame holds them all, as the dense reference does
        gs = _frames(3, seed)
        wall = jnp.where(jnp.arange(W) < W // 2, 1.5, 2.5)
        gs = dataclasses.replace(gs, depth=jnp.broadcast_to(wall, gs.depth.shape) + 0.3 * jnp.arange(3.0)[:, None, None], offset=0.05 * gs.offset)
        poses = lie.exp(jnp.asarray(np.random.default_rng(seed + 10).normal(0, 0.01, (3, 6))))
        view = lie.exp(jnp.asarray(np.random.default_rng(seed + 20).normal(0, 0.01, 6)))
        assert max(_slot_counts(jax.tree.map(lambda x: x[j : j + 1], gs), jax.tree.map(lambda x: x[j : j + 1], poses), view, intr) for j in range(3)) == 1
        fast = scene.render_scene(gs, poses, view, intr)
        ref = _priority_reference(gs, poses, view, intr, scene.OCCLUSION_TOLERANCE)
        for a, b in zip(fast, ref):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-9)

        rng = np.random.default_rng(seed + 30)
        ct = [jnp.asarray(rng.normal(size=x.shape)) for x in ref]

        def vjp(render, g):
            out = render(dataclasses.replace(gs, rgb=g[0], opacity_logit=g[1], offset=g[2], log_radius=g[3]))
            return sum(jnp.vdot(o, c) for o, c in zip(out, ct))

        pick = (gs.rgb, gs.opacity_logit, gs.offset, gs.log_radius)
        got = jax.grad(lambda g: vjp(lambda x: scene.render_scene(x, poses, view, intr), g))(pick)
        want = jax.grad(lambda g: vjp(lambda x: _priority_reference(x, poses, view, intr, scene.OCCLUSION_TOLERANCE), g))(pick)
        for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-9)


def test_priority_keeps_the_first_frame_but_not_behind_an_occluder():
    """Two frames of one wall 3 m away, coloured red (first) and green (second); the second also
    holds a blue box 1 m away. The wall shows red (the second frame's wall is the same surface,
    5 cm behind), the box shows blue (it is nearer by far more than the tolerance)."""
    with jax.enable_x64(True):
        intr = _intr()
        depth = np.full((2, H, W), 3.0)
        depth[1] += 0.05
        depth[1, 3:6, 4:8] = 1.0
        rgb = np.zeros((2, H, W, 3))
        rgb[0, ..., 0] = 1.0
        rgb[1, ..., 1] = 1.0
        rgb[1, 3:6, 4:8] = (0.0, 0.0, 1.0)
        gs = PixelGaussians(
            rgb=jnp.asarray(rgb), log_radius=jnp.log(jnp.asarray(depth) * 3.0 / 13.0), opacity_logit=jnp.full((2, H, W), 6.0),
            offset=jnp.zeros((2, H, W)), depth=jnp.asarray(depth),
        )
        poses = lie.exp(jnp.zeros((2, 6)))
        out = scene.render_scene(gs, poses, lie.exp(jnp.zeros(6)), intr)
        colour = np.asarray(out.rgb)
        assert colour[1, 1, 0] > 0.95 and colour[1, 1, 1] < 0.05  # the wall: the first frame's red
        assert colour[4, 6, 2] > 0.95 and colour[4, 6, 0] < 0.05  # the box: the second frame's blue
        assert abs(float(out.depth[4, 6] / out.alpha[4, 6]) - 1.0) < 0.01


def test_render_scene_hides_padding_frames():
    with jax.enable_x64(True):
        intr = _intr()
        gs = _frames(3, 5)
        poses = lie.exp(jnp.asarray(np.random.default_rng(5).normal(0, 0.04, (3, 6))))
        view = lie.exp(jnp.zeros(6))
        two = jax.tree.map(lambda x: x[:2], gs), jax.tree.map(lambda x: x[:2], poses)
        assert _slot_counts(gs, poses, view, intr) <= DENSE_LAYERS  # the hidden frame's Gaussians are binned too
        padded = scene.render_scene(gs, poses, view, intr, jnp.array([True, True, False]), composite="depth", layers=DENSE_LAYERS)
        ref = jax.jit(splat_ref.render)(*two, view, intr)
        for a, b in zip(padded, ref):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-9)


def test_select_frames_prefers_frames_seeing_the_view():
    """Cameras along a wall: the view's own neighbourhood wins, a camera facing away and one whose
    footprint is off to the side do not count."""
    intr = Intrinsics(fx=50.0, fy=50.0, cx=31.5, cy=23.5, width=64, height=48)
    depth, valid = np.full((48, 64), 2.0, np.float32), np.ones((48, 64), bool)
    poses, pts = [], []
    for x in np.linspace(-2.0, 2.0, 9):  # looking down +z at a wall 2 m away
        T = np.eye(4)
        T[0, 3] = x
        poses.append(T)
        pts.append(scene.footprint(depth, valid, T, intr))
    away = np.diag([-1.0, 1.0, -1.0, 1.0])  # at the origin, looking down -z
    poses.append(away)
    pts.append(scene.footprint(depth, valid, away, intr))
    view = np.eye(4)
    view[0, 3] = 0.1
    chosen = scene.select_frames(view, np.stack(poses), np.stack(pts), intr, 3)
    assert list(chosen) == [4, 5, 3]  # the cameras at x = 0, 0.5, -0.5
    assert 9 not in scene.select_frames(view, np.stack(poses), np.stack(pts), intr, 10)


@pytest.mark.slow
def test_finetune_step_is_adam_on_the_present_frames():
    """One refinement step equals optax's Adam with the mapping's learning rates on the present
    frames' Gaussians (measured depth fixed), and leaves a padding frame as it was; with the
    offsets' bound, the step ends inside it."""
    intr = _intr(jnp.float32)
    gs = jax.tree.map(lambda x: x.astype(jnp.float32), _frames(2, 3))
    poses = lie.exp(jnp.asarray(np.random.default_rng(3).normal(0, 0.03, (2, 6)), jnp.float32))
    present = jnp.array([True, False])
    rng = np.random.default_rng(4)
    rgb = jnp.asarray(rng.uniform(0, 1, (H, W, 3)), jnp.float32)
    depth = jnp.asarray(rng.uniform(1, 3, (H, W)), jnp.float32)
    valid = jnp.ones((H, W), bool)
    view = lie.exp(jnp.zeros(6, jnp.float32))
    # The paper's 100 steps: mapping.optimizer's rates unscaled, as the refinement's are
    cfg = MapConfig(iterations=mapping.PAPER_ITERATIONS, offset_at_invalid=True, offset_bound=0.0)
    new, state, loss = scene.finetune_step(cfg, gs, scene.adam_init(gs), poses, present, rgb, depth, valid, view, intr, layers=6, offsets=True)
    bounded, _, _ = scene.finetune_step(MapConfig(offset_at_invalid=True, offset_bound=1e-4), gs, scene.adam_init(gs), poses, present, rgb, depth, valid, view, intr, layers=6, offsets=True)
    limit = 1e-4 * np.asarray(gs.depth[0], np.float64) ** 2
    assert np.all(np.abs(np.asarray(bounded.offset[0])) <= limit * (1 + 1e-5)) and np.any(np.abs(np.asarray(new.offset[0])) > limit)

    def loss_fn(g):
        out = scene.render_scene(g, poses, view, intr, present, layers=6)
        return mapping.losses.mapping_loss(out.rgb, out.depth / jnp.maximum(out.alpha, 1e-3), rgb, depth, valid)

    grad = jax.jit(jax.grad(loss_fn))(gs)
    opt = mapping.optimizer(cfg)
    first = jax.tree.map(lambda x: x[0], gs)
    upd, _ = opt.update(jax.tree.map(lambda x: x[0], grad), opt.init(first), first)
    want = optax.apply_updates(first, upd)
    for a, b in zip(jax.tree.leaves(jax.tree.map(lambda x: x[0], new)), jax.tree.leaves(want)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-6)
    for a, b in zip(jax.tree.leaves(jax.tree.map(lambda x: x[1], new)), jax.tree.leaves(jax.tree.map(lambda x: x[1], gs))):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert np.asarray(state.count).tolist() == [1.0, 0.0] and np.isfinite(float(loss))
    # by default the offsets stay as mapping left them
    kept, _, _ = scene.finetune_step(cfg, gs, scene.adam_init(gs), poses, present, rgb, depth, valid, view, intr, layers=6)
    np.testing.assert_array_equal(np.asarray(kept.offset), np.asarray(gs.offset))
    np.testing.assert_allclose(np.asarray(kept.rgb[0]), np.asarray(new.rgb[0]), rtol=1e-5, atol=1e-6)


@pytest.mark.slow
def test_held_out_views_end_to_end(tmp_path, capsys):
    """`--holdout-every 4 --finetune 3 --save-renders` on the synthetic scene: held-out frames are
    tracked (in the trajectory) but get no Gaussians, are rendered from the scene and scored before
    and after the refinement, and their renders are written under the nvs_ names."""
    out = tmp_path / "nvs"
    args = ["run", "--quiet", "--out", str(out), "--holdout-every", "4", "--finetune", "3", "--save-renders", "--checkpoint-every", "0"]
    for kv in ("data.synthetic.width=80", "data.synthetic.height=60", "data.synthetic.frames=9", "map.iterations=3", "scene.frames=3"):
        args += ["--set", kv]
    assert main(args) == 0
    assert "refining" not in capsys.readouterr().err  # --quiet: no progress bar, the refinement's included
    m = json.loads((out / "metrics.json").read_text())
    held = [4, 8]
    assert m["frames"] == 9 and m["nvs_frames"] == 2 and m["mapped_frames"] == 7
    assert len((out / "trajectory.txt").read_text().strip().splitlines()) == 1 + 9
    stored = sorted(p.name for p in (out / "gaussians").glob("*.npz"))
    assert stored == [f"frame_{i:06d}.npz" for i in range(9) if i not in held]
    for key in ("nvs_psnr", "nvs_ssim", "nvs_lpips", "nvs_depth_l1_cm", "nvs_psnr_before_finetune"):
        assert key in m and (m[key] is None or np.isfinite(m[key])), key
    assert 10.0 < m["nvs_psnr"] < m["psnr"]  # a real image, below the training views' self-fit
    assert m["finetune_iterations"] == 3 and m["finetune_loss_first"] != m["finetune_loss_last"]  # steps 1 and 3, not both the mean of all
    assert [r["index"] for r in m["per_frame"] if r["holdout"]] == held
    assert [r["index"] for r in m["per_frame"] if not r["holdout"]] == [i for i in range(9) if i not in held]
    for i in held:
        assert (out / "renders" / f"nvs_rgb_{i:06d}.png").is_file() and (out / "renders" / f"nvs_depth_{i:06d}.png").is_file()
        assert not (out / "renders" / f"rgb_{i:06d}.png").exists()
    cams = json.loads((out / "cameras.json").read_text())
    assert (cams["width"], cams["height"]) == (80, 60)
    # the stored Gaussians are the refined ones: rendered again from the files, the held-out views
    # score what the run recorded (their saved 8-bit renders score within rounding of it)
    from sgad_jax.eval.run_eval import evaluate_run

    again = evaluate_run(out, rerender=True, write=False)
    assert again["novel_psnr"] == pytest.approx(m["nvs_psnr"], abs=1e-3)
    assert evaluate_run(out, write=False)["novel_psnr"] == pytest.approx(m["nvs_psnr"], abs=0.1)
    # with no room in memory (every frame's Gaussians and moments in its temporary folder) the
    # refinement gives the same Gaussians as with all of them in memory
    spilled = tmp_path / "spilled"
    assert main([*args[:3], str(spilled), *args[4:], "--set", "scene.finetune_budget_mb=0.05"]) == 0
    assert json.loads((spilled / "metrics.json").read_text())["nvs_psnr"] == m["nvs_psnr"]
    for name in stored:
        with np.load(out / "gaussians" / name) as a, np.load(spilled / "gaussians" / name) as b:
            for key in a.files:
                np.testing.assert_array_equal(a[key], b[key], err_msg=f"{name} {key}")


@pytest.mark.slow
def test_scannetpp_test_views_are_scored_from_the_scene(tmp_path):
    """A ScanNet++ DSLR folder made from the synthetic room (6 train views, 2 test views among them):
    the test views are rendered at their ground-truth poses carried into the estimated trajectory's
    frame, scored as ``test_*`` and written under the test_ names."""
    import cv2

    from sgad_jax.config import DataConfig, SyntheticConfig
    from sgad_jax.io.synthetic import SyntheticDataset

    syn = SyntheticDataset(DataConfig(layout="synthetic", synthetic=SyntheticConfig(frames=60, width=160, height=120)))
    dslr = tmp_path / "scene" / "dslr"
    flip = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV camera axes -> nerfstudio's
    frames, test = [], []
    for i in range(8):
        s = syn[i]
        name = f"DSC{i:05d}.JPG"
        (dslr / "undistorted_images").mkdir(parents=True, exist_ok=True)
        (dslr / "undistorted_depths").mkdir(parents=True, exist_ok=True)
        assert cv2.imwrite(str(dslr / "undistorted_images" / name), np.ascontiguousarray(s.rgb[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, 98])
        assert cv2.imwrite(str(dslr / "undistorted_depths" / f"DSC{i:05d}.png"), (s.depth * 1000).round().astype(np.uint16))
        rec = {"file_path": name, "transform_matrix": (flip @ syn.gt_poses[i] @ flip).tolist()}
        (test if i in (3, 6) else frames).append(rec)
    fx, fy, cx, cy = syn.intrinsics.as_tuple()
    meta = dict(w=160, h=120, fl_x=fx, fl_y=fy, cx=cx, cy=cy, camera_model="PINHOLE", frames=frames, test_frames=test)
    (dslr / "nerfstudio").mkdir()
    (dslr / "nerfstudio" / "transforms_undistorted.json").write_text(json.dumps(meta))
    out = tmp_path / "run"
    args = ["run", "--quiet", "--data", str(tmp_path / "scene"), "--out", str(out), "--save-renders", "--checkpoint-every", "0"]
    for kv in ("map.iterations=3", "scene.frames=3", "track.stride=2"):
        args += ["--set", kv]
    assert main(args) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["frames"] == 6 and m["test_frames"] == 2 and len(m["test_per_frame"]) == 2
    assert 18.0 < m["test_psnr"] < m["psnr"]
    assert (out / "renders" / "test_rgb_000000.png").is_file() and (out / "renders" / "test_rgb_000001.png").is_file()


@pytest.mark.slow
def test_keyframes_map_every_third_frame_and_score_the_rest(tmp_path):
    """`map.every=3` with `--holdout-every 4` on 9 synthetic frames: frames 0, 3, 6 are mapped
    (Gaussians stored), 4 and 8 are held out, and 1, 2, 5, 7 are rendered from the scene and scored
    with the mapped ones (renders under the training names, `mapped: false`)."""
    out = tmp_path / "keyframes"
    args = ["run", "--quiet", "--out", str(out), "--holdout-every", "4", "--save-renders", "--checkpoint-every", "0"]
    for kv in ("data.synthetic.width=80", "data.synthetic.height=60", "data.synthetic.frames=9", "map.iterations=3", "scene.frames=3", "map.every=3"):
        args += ["--set", kv]
    assert main(args) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["mapped_frames"] == 3 and m["between_frames"] == 4 and m["nvs_frames"] == 2 and m["map_every"] == 3
    assert sorted(p.name for p in (out / "gaussians").glob("*.npz")) == [f"frame_{i:06d}.npz" for i in (0, 3, 6)]
    frames = {r["index"]: r for r in m["per_frame"] if not r["holdout"]}
    assert sorted(frames) == [0, 1, 2, 3, 5, 6, 7]
    assert [i for i in sorted(frames) if frames[i]["mapped"]] == [0, 3, 6]
    for i in frames:
        assert (out / "renders" / f"rgb_{i:06d}.png").is_file()
    assert m["psnr"] == pytest.approx(np.mean([r["psnr"] for r in frames.values()]))
    assert m["between_psnr"] == pytest.approx(np.mean([frames[i]["psnr"] for i in (1, 2, 5, 7)]))
    assert m["s_per_input_frame"] > 0
