"""A structured-light depth sensor (Kinect v1 / Asus Xtion class) simulated on a copy of Replica's exact
depth: the stand-in for "another sensor" in docs/method.md, since no such sequence is in the shared data.

Each depth image becomes disparity (``f`` 580 px, baseline 7.5 cm), gets N(0, 0.062 px) noise (an axial
error of 1.425e-3 z^2 m, Khoshelham and Elberink 2012), is quantised to 1/8 px, loses the pixels
shadowed from the projector (a surface more than 3% nearer within 4 px towards it) and 0.5% of the
rest at random, and is turned back into depth: about 8 mm RMS error at Replica's 1-3.7 m. Colour images
are linked, not copied. Two options bring in what a real camera adds: ``--correlation-px`` shares the
disparity noise among neighbouring pixels (a sensor matches windows of pixels), ``--k1`` gives the
depth camera a radial lens distortion that the dataset's pinhole intrinsics do not model.
``--scale`` makes the room larger (its depth and the trajectory's translations times the factor)
before the sensor sees it, so that more of it lies where the sensor is noisy.

Usage::

    python benchmarks/sim_structured_light.py ../shared/data/replica_office0 /tmp/sim0 --seed 0
    python benchmarks/bench_track.py --data /tmp/sim0/rendered_100 --config 7scenes --rounds 1
"""

from __future__ import annotations

import argparse
import json
import pathlib
import shutil

import cv2
import numpy as np

REPLICA_SCALE = 6553.5  # depth PNG units per metre
F_PX, BASELINE_M = 580.0, 0.075
DISPARITY_SIGMA_PX, DISPARITY_STEP_PX = 0.062, 1 / 8
SHADOW_PX, SHADOW_NEARER, DROPOUT = 4, 0.97, 0.005


def simulate(z: np.ndarray, rng: np.random.Generator, correlation_px: float = 0.0) -> np.ndarray:
    """Depth in metres (0 = missing) as the simulated sensor measures it. With ``correlation_px``
    the disparity noise is white noise blurred by a Gaussian of that sigma (rescaled to the same
    per-pixel sigma), as a sensor matching a window of pixels shares its error among neighbours;
    quantising that smooth field gives contiguous terraces instead of per-pixel dithering."""
    valid = z > 0
    d = np.where(valid, F_PX * BASELINE_M / np.where(valid, z, 1.0), 0.0)
    noise = rng.normal(0.0, 1.0, d.shape)
    if correlation_px > 0:
        noise = cv2.GaussianBlur(noise, (0, 0), correlation_px)
        noise /= noise.std()
    d = np.round((d + DISPARITY_SIGMA_PX * noise) / DISPARITY_STEP_PX) * DISPARITY_STEP_PX
    shadow = np.zeros_like(valid)
    for s in range(1, SHADOW_PX + 1):  # the projector sits to the left of the camera
        near = np.zeros_like(z)
        near[:, s:] = z[:, :-s]
        shadow |= (near > 0) & (near < SHADOW_NEARER * z)
    keep = valid & ~shadow & (d > 0) & (rng.random(z.shape) >= DROPOUT)
    return np.where(keep, F_PX * BASELINE_M / np.where(keep, d, 1.0), 0.0)


def distort(z: np.ndarray, fx: float, fy: float, cx: float, cy: float, k1: float) -> np.ndarray:
    """The depth image of a camera with radial distortion ``k1`` (``x_d = x_u (1 + k1 r_u^2)`` in
    normalised coordinates) seeing what the pinhole image ``z`` shows: each pixel takes the depth of
    the ray through its undistorted position (nearest pixel; 0 outside the image)."""
    h, w = z.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    xd, yd = (u - cx) / fx, (v - cy) / fy
    xu, yu = xd, yd
    for _ in range(20):  # fixed-point inversion; converges for |k1| r^2 well below 1
        s = 1.0 + k1 * (xu * xu + yu * yu)
        xu, yu = xd / s, yd / s
    maps = (fx * xu + cx).astype(np.float32), (fy * yu + cy).astype(np.float32)
    return cv2.remap(z.astype(np.float32), *maps, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0).astype(np.float64)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("src", help="a Replica scene folder (cam_params.json, rendered_100/results/...)")
    ap.add_argument("dst", help="where the copy goes (replaced)")
    ap.add_argument("--sequence", default="rendered_100")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--correlation-px", type=float, default=0.0, help="blur sigma of the disparity noise (0: independent pixels)")
    ap.add_argument("--k1", type=float, default=0.0, help="radial lens distortion of the depth camera, unmodelled by the intrinsics")
    ap.add_argument("--scale", type=float, default=1.0, help="the scene's size factor (depth and camera translations)")
    args = ap.parse_args()
    if not args.scale > 0:
        ap.error(f"--scale: a positive factor, got {args.scale}")
    src, dst = pathlib.Path(args.src).resolve(), pathlib.Path(args.dst)
    results = src / args.sequence / "results"
    if not results.is_dir() or not (src / "cam_params.json").is_file():
        ap.error(f"{src}: not a Replica scene folder with {args.sequence}/results and cam_params.json")
    shutil.rmtree(dst, ignore_errors=True)
    (dst / args.sequence / "results").mkdir(parents=True)
    shutil.copy(src / "cam_params.json", dst)
    traj = np.loadtxt(src / args.sequence / "traj.txt", ndmin=2)
    traj[:, [3, 7, 11]] *= args.scale  # row-major 4x4 camera-to-world: the translation column
    np.savetxt(dst / args.sequence / "traj.txt", traj)
    rng = np.random.default_rng(args.seed)
    cam = json.loads((src / "cam_params.json").read_text())["camera"]
    for path in sorted(results.iterdir()):
        out = dst / args.sequence / "results" / path.name
        if not path.name.startswith("depth"):
            out.symlink_to(path)
            continue
        z = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float64) / REPLICA_SCALE * args.scale
        if args.k1:
            z = distort(z, cam["fx"], cam["fy"], cam["cx"], cam["cy"], args.k1)
        cv2.imwrite(str(out), np.clip(np.round(simulate(z, rng, args.correlation_px) * REPLICA_SCALE), 0, 65535).astype(np.uint16))
    print(f"{dst / args.sequence}: {len(list(results.glob('depth*')))} depth images simulated (seed {args.seed})")


if __name__ == "__main__":
    main()
