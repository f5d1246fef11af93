"""``sgad-jax view RUN_DIR``: a finished run in the browser (viser), on a headless machine too.

Shows the cameras (frustums, each with its render when the run saved renders), the trajectory, the
merged map (every mapped frame's Gaussians in world coordinates, as viser Gaussian splats, randomly
subsampled to ``max_splats``) and ``mesh.ply`` when there is one. viser is an optional extra
(``pip install 'sgad_jax[viewer]'``), imported only here and only when a viewer is asked for.
"""

from __future__ import annotations

import math
import pathlib
import socket
import sys
import time

import numpy as np

from sgad_jax.camera import backproject_image
from sgad_jax.config import ConfigError
from sgad_jax.io.ply import read_mesh_ply
from sgad_jax.io.rundir import Run, read_render
from sgad_jax.io.base import DatasetError
from sgad_jax.io.export import matrix_to_quaternion

_FRUSTUMS = 200  # at most this many camera frustums (every k-th frame), so the page stays light
_THUMB_WIDTH = 160  # pixels of the render shown in a frustum


def _viser():
    try:
        import viser
    except ImportError:
        raise ConfigError("the viewer needs viser, an optional extra: pip install 'sgad_jax[viewer]'") from None
    return viser


def _server(host: str, port: int):
    """A viser server listening on ``host:port``, or a :class:`ConfigError` naming the address.
    viser starts in a thread of its own: a bad port there is a traceback and a wait that never ends,
    and a taken port makes it move silently to the next, so the address is tried here first."""
    if not 0 <= port <= 65535:
        raise ConfigError(f"port {port}: must be 0-65535")
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)[0]
        with socket.socket(family, kind, proto) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server does: a port in TIME_WAIT is free
            s.bind(address)
    except (OSError, UnicodeError) as err:  # in use, not permitted, unknown or malformed host
        raise ConfigError(f"cannot listen on {host}:{port} ({getattr(err, 'strerror', None) or err})") from None
    return _viser().ViserServer(host=host, port=port, verbose=False)


def merged_gaussians(run_dir, max_count: int, *, seed: int = 0) -> dict:
    """Every mapped frame's Gaussians in world coordinates (:func:`sgad_jax.io.ply.merged_gaussians`,
    none merged away), uniformly subsampled to about ``max_count``.

    Returns:
        ``centers`` (n, 3), ``covariances`` (n, 3, 3), ``rgbs`` (n, 3) in [0, 1], ``opacities`` (n, 1),
        and ``total``, the count before subsampling.
    """
    from sgad_jax.io.ply import merged_gaussians as world_gaussians

    g, _ = world_gaussians(run_dir, voxel=0.0)
    total = len(g)
    if total:
        g = g.take(np.flatnonzero(np.random.default_rng(seed).random(total) < min(1.0, max_count / total)))
    sigma2 = (g.sigma**2).astype(np.float32)
    return {
        "centers": g.xyz.astype(np.float32), "covariances": sigma2[:, None, None] * np.eye(3, dtype=np.float32),
        "rgbs": np.clip(g.rgb, 0.0, 1.0).astype(np.float32), "opacities": g.opacity.astype(np.float32)[:, None], "total": total,
    }


def build_scene(server, run_dir, *, max_splats: int = 300_000) -> dict:
    """Add the run's cameras, trajectory, Gaussians and mesh to a viser server's scene; a summary."""
    run = Run(run_dir)
    poses = run.trajectory[1]
    intr = run.intrinsics
    finite = np.flatnonzero(np.isfinite(poses).all((1, 2)))
    scene = server.scene
    scene.set_up_direction("-y")  # OpenCV camera axes: the first camera's y points down
    summary = {"frames": len(poses)}

    renders = set(run.render_frames())
    fov = 2 * math.atan2(intr.height / 2, float(intr.fy))
    step = max(1, math.ceil(len(finite) / _FRUSTUMS))
    for i in finite[::step]:
        T = poses[i]
        x, y, z, w = matrix_to_quaternion(T[:3, :3])
        image = None
        if i in renders:
            rgb, _ = read_render(run.root, int(i))
            s = max(1, rgb.shape[1] // _THUMB_WIDTH)
            image = (rgb[::s, ::s] * 255 + 0.5).astype(np.uint8)
        scene.add_camera_frustum(
            f"/cameras/{i:06d}", fov=fov, aspect=intr.width / intr.height, scale=0.08, color=(40, 90, 220),
            image=image, wxyz=(w, x, y, z), position=tuple(T[:3, 3]),
        )
    if len(finite) >= 2:
        centres = poses[finite, :3, 3]
        segments = np.stack([centres[:-1], centres[1:]], 1).astype(np.float32)
        scene.add_line_segments("/trajectory", segments, colors=(220, 60, 40), thickness=0.005)
    summary["cameras"] = len(finite[::step])

    g = merged_gaussians(run.root, max_splats) if run.gaussian_frames() else {"centers": [], "total": 0}
    if len(g["centers"]):
        scene.add_gaussian_splats("/gaussians", centers=g["centers"], covariances=g["covariances"], rgbs=g["rgbs"], opacities=g["opacities"])
    summary.update(gaussians_shown=int(len(g["centers"])), gaussians_total=int(g["total"]))

    mesh_path = run.root / "mesh.ply"
    if mesh_path.is_file():
        import trimesh  # a dependency of viser

        vertices, faces, colours = read_mesh_ply(mesh_path)
        mesh = trimesh.Trimesh(vertices=vertices, faces=faces, vertex_colors=colours, process=False)
        scene.add_mesh_trimesh("/mesh", mesh, visible=not len(g["centers"]))
        summary["mesh_faces"] = int(len(faces))
    return summary


def serve(run_dir, *, host: str = "0.0.0.0", port: int = 8080, max_splats: int = 300_000, block: bool = True):
    """Serve the run on ``http://host:port`` until interrupted (``block=False``: return the server)."""
    _viser()  # a missing extra is said before anything else
    run = pathlib.Path(run_dir)
    if not run.is_dir():
        raise DatasetError(f"{run}: run folder not found")
    Run(run).trajectory  # a bad folder fails before the server starts
    server = _server(host, port)
    summary = build_scene(server, run, max_splats=max_splats)
    shown = f"{summary['gaussians_shown']} of {summary['gaussians_total']} Gaussians"
    print(f"sgad-jax view: {run} ({summary['frames']} frames, {shown}{', mesh' if 'mesh_faces' in summary else ''}) at http://{host}:{server.get_port()}", file=sys.stderr, flush=True)
    if not block:
        return server
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        server.stop()


class LiveView:
    """``sgad-jax run --viewer PORT``: the run as it happens. Each tracked frame adds its camera
    and extends the trajectory; every ``points_every``-th frame adds its measured points (every
    ``stride``-th pixel, coloured). When the run ends, :meth:`finish` adds the finished run's scene
    (merged Gaussians, mesh) as ``sgad-jax view`` shows it. Built only when asked for."""

    def __init__(self, intr, *, host: str = "0.0.0.0", port: int = 8080, points_every: int = 5, stride: int = 4):
        self.server = _server(host, port)
        self.server.scene.set_up_direction("-y")
        self.intr, self.points_every, self.stride = intr, points_every, stride
        self.centres: list[np.ndarray] = []
        print(f"sgad-jax: live viewer at http://{host}:{self.server.get_port()}", file=sys.stderr, flush=True)

    def frame(self, index: int, pose: np.ndarray, sample) -> None:
        """Show tracked frame ``index`` (camera-to-world ``pose``, the sample it was tracked from)."""
        intr, scene = self.intr, self.server.scene
        x, y, z, w = matrix_to_quaternion(pose[:3, :3])
        fov = 2 * math.atan2(intr.height / 2, float(intr.fy))
        scene.add_camera_frustum(f"/cameras/{index:06d}", fov=fov, aspect=intr.width / intr.height, scale=0.05, color=(40, 90, 220), wxyz=(w, x, y, z), position=tuple(pose[:3, 3]))
        self.centres.append(pose[:3, 3])
        if len(self.centres) >= 2:
            c = np.asarray(self.centres, np.float32)
            scene.add_line_segments("/trajectory", np.stack([c[:-1], c[1:]], 1), colors=(220, 60, 40), thickness=0.005)
        if index % self.points_every == 0:
            s = self.stride
            cam = np.asarray(backproject_image(sample.depth, intr))[::s, ::s]
            rgb, ok = sample.rgb[::s, ::s], sample.depth[::s, ::s] > 0
            world = cam[ok] @ pose[:3, :3].T + pose[:3, 3]
            scene.add_point_cloud(f"/points/{index:06d}", points=world.astype(np.float32), colors=rgb[ok], point_size=0.01)

    def finish(self, run_dir) -> None:
        """Replace the live points by the finished run's scene, and keep serving until Ctrl-C."""
        self.server.scene.reset()
        summary = build_scene(self.server, run_dir)
        print(f"sgad-jax: run finished ({summary['frames']} frames); the viewer serves it until Ctrl-C", file=sys.stderr, flush=True)
        try:
            while True:
                time.sleep(3600)
        except KeyboardInterrupt:
            self.server.stop()
