"""Property-based corruption of input folders: every outcome is a usable frame, a bad frame with
one line naming its file, or (for a folder that cannot be opened) one line naming the folder or
file; never a traceback, never a hang."""

import json

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from sgad_jax.cli import main
from sgad_jax.config import DataConfig
from sgad_jax.io.base import BadFrame, DatasetError, RGBDSample, read_image
from sgad_jax.io.datasets import open_dataset

CORRUPTIONS = ("none", "cut_rgb", "cut_depth", "garbage_depth", "zero_depth", "missing_65535", "nan_depth", "size")


def _frame(rng, h, w):
    v, u = np.mgrid[0:h, 0:w]
    rgb = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
    depth = (1000 * (1.0 + 0.01 * u + 0.02 * v)).astype(np.uint16)
    return rgb, depth


def _write_folder(root, kinds, h, w, k, cut, seed):
    """A generic-layout folder with one frame per entry of ``kinds``; returns the clean images."""
    rng = np.random.default_rng(seed)
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    (root / "intrinsics.txt").write_text(" ".join(map(str, k)) + "\n")
    clean = []
    for i, kind in enumerate(kinds):
        rgb, depth = _frame(rng, h, w)
        rgb_path, depth_path = root / "rgb" / f"{i:03d}.png", root / "depth" / f"{i:03d}.png"
        if kind == "nan_depth":
            depth_path = depth_path.with_suffix(".tiff")
            f = depth.astype(np.float32) / 1000
            f[rng.integers(h), rng.integers(w)] = np.nan
            cv2.imwrite(str(depth_path), f)
        elif kind == "zero_depth":
            cv2.imwrite(str(depth_path), np.zeros_like(depth))
        elif kind == "missing_65535":
            depth[: h // 2] = 65535
            cv2.imwrite(str(depth_path), depth)
        else:
            cv2.imwrite(str(depth_path), depth)
        cv2.imwrite(str(rgb_path), rgb[: h - (kind == "size"), :, ::-1])
        if kind in ("cut_rgb", "cut_depth"):
            path = rgb_path if kind == "cut_rgb" else depth_path
            data = path.read_bytes()
            path.write_bytes(data[: max(1, int(cut * len(data)))])
        if kind == "garbage_depth":
            depth_path.write_bytes(rng.integers(0, 255, 200, dtype=np.uint8).tobytes())
        clean.append((rgb, depth))
    return clean


def _one_line_naming(message: str, paths) -> bool:
    return "\n" not in message and any(str(p) in message for p in paths)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    kinds=st.lists(st.sampled_from(CORRUPTIONS), min_size=1, max_size=4),
    h=st.integers(3, 33),
    w=st.integers(3, 41),
    f=st.floats(5.0, 500.0),
    c=st.tuples(st.floats(0.0, 1.0), st.floats(0.0, 1.0)),
    cut=st.floats(0.0, 0.999),
    seed=st.integers(0, 2**16),
)
def test_loader_fuzz(tmp_path_factory, kinds, h, w, f, c, cut, seed):
    root = tmp_path_factory.mktemp("fuzz")
    k = (f, f * 1.1, c[0] * (w - 1), c[1] * (h - 1))
    clean = _write_folder(root, kinds, h, w, k, cut, seed)
    try:
        ds = open_dataset(DataConfig(path=str(root)))
    except DatasetError as err:  # the first frame's depth sets the size: it may be what is broken
        assert _one_line_naming(str(err), [root])
        return
    items = list(ds.frames(skip_bad=True))
    assert len(items) == len(kinds)
    for item, kind, (rgb, depth) in zip(items, kinds, clean):
        if isinstance(item, BadFrame):
            assert _one_line_naming(item.reason, [root / "rgb", root / "depth"]), item.reason
            assert kind != "none" and kind != "missing_65535"
            continue
        assert isinstance(item, RGBDSample)
        assert kind not in ("zero_depth", "nan_depth", "garbage_depth", "size")
        np.testing.assert_array_equal(item.rgb, rgb)  # a frame that passes is the frame written
        assert np.isfinite(item.depth).all() and (item.depth >= 0).all() and item.depth.any()
        if kind != "cut_depth":
            np.testing.assert_allclose(item.depth, depth / 1000.0, rtol=1e-6)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(kind=st.sampled_from(["png", "jpg", "other"]), body=st.binary(max_size=64), ended=st.booleans(), segments=st.lists(st.integers(0, 255), max_size=6))
@example(kind="png", body=b"\x00\x00\x00\x0dIHDR" + (100000).to_bytes(4, "big") * 2 + b"\x08\x02\x00\x00\x00", ended=True, segments=[])
@example(kind="png", body=b"\x00\x00\x00\x0dIHDR" + (5).to_bytes(4, "big") + (4).to_bytes(4, "big") + b"\x08\x02\x00\x00\x00", ended=True, segments=[])
def test_colour_checked_without_decoding_fuzz(tmp_path_factory, kind, body, ended, segments):
    """Random bytes behind a PNG or JPEG signature (JPEG: random markers with random lengths), with
    or without an end marker: checking colour without decoding it gives an image or one line naming
    the file, never another exception."""
    head = {"png": b"\x89PNG\r\n\x1a\n", "jpg": b"\xff\xd8", "other": b""}[kind]
    if kind == "jpg":
        head += b"".join(b"\xff" + bytes([m]) + (len(body) % 7).to_bytes(2, "big") for m in segments)
    tail = {"png": b"\x00\x00\x00\x00IEND\xaeB`\x82", "jpg": b"\xff\xd9", "other": b""}[kind] if ended else b""
    path = tmp_path_factory.mktemp("colour") / f"c.{kind}"
    path.write_bytes(head + body + tail)
    try:
        image = read_image(path, decode=False)
    except DatasetError as err:
        assert _one_line_naming(str(err), [path])
        return
    assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3
    if kind == "png" and body[4:8] == b"IHDR":  # the size the header gives
        assert image.shape[:2] == (int.from_bytes(body[12:16], "big"), int.from_bytes(body[8:12], "big"))


@pytest.mark.parametrize("make", ["empty", "no_depth", "bad_intrinsics", "mismatch"])
def test_broken_folders_one_line(tmp_path, make):
    root = tmp_path / "d"
    root.mkdir()
    if make != "empty":
        _write_folder(root, ["none", "none"], 12, 16, (20, 20, 7.5, 5.5), 0.5, 0)
    if make == "no_depth":
        for p in (root / "depth").iterdir():
            p.unlink()
    if make == "bad_intrinsics":
        (root / "intrinsics.txt").write_text("20 20 nan 5\n")
    if make == "mismatch":
        (root / "rgb" / "001.png").unlink()
    with pytest.raises(DatasetError) as err:
        open_dataset(DataConfig(path=str(root)))
    assert _one_line_naming(str(err.value), [root])


@pytest.mark.slow
@settings(max_examples=2, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(kinds=st.lists(st.sampled_from(CORRUPTIONS[1:]), min_size=1, max_size=2), where=st.integers(1, 5), seed=st.integers(0, 2**16))
@example(kinds=["missing_65535"], where=1, seed=0)  # no bad frame at all: both policies complete
def test_pipeline_fuzz_skips_and_stops(tmp_path_factory, kinds, where, seed):
    """Whole runs (tracking only) over a folder with corrupted frames among good ones: skip
    completes and lists exactly the bad frames; stop exits with status 2 and one line, keeping the
    frames before."""
    root = tmp_path_factory.mktemp("run")
    all_kinds = ["none"] * 8
    for j, kind in enumerate(kinds):
        all_kinds[min(7, where + 2 * j)] = kind
    _write_folder(root, all_kinds, 24, 32, (40.0, 40.0, 15.5, 11.5), 0.5, seed)
    bad = [i for i, kind in enumerate(all_kinds) if kind not in ("none", "missing_65535", "cut_depth", "cut_rgb")]
    cut = [i for i, kind in enumerate(all_kinds) if kind in ("cut_depth", "cut_rgb")]
    out = root / "out"
    common = ["run", "--data", str(root), "--track-only", "--quiet", "--set", "track.stride=2", "--checkpoint-every", "0"]
    assert main([*common, "--out", str(out), "--on-bad-frame", "skip"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    skipped = [r["index"] for r in m["skipped_frames"]]
    assert set(bad) <= set(skipped) <= set(bad) | set(cut)  # a cut PNG is bad unless only its end marker's CRC went
    assert m["frames"] == 8 - len(skipped)
    code = main([*common, "--out", str(root / "stop")])
    if not skipped:
        assert code == 0
        return
    assert code == 2
    assert json.loads((root / "stop" / "metrics.json").read_text())["frames"] == min(skipped)
