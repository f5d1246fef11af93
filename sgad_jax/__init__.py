"""sgad_jax: SGAD-SLAM (CVPR 2026) in JAX.

Public API (pure functions over pytrees; see README.md):

* types: :class:`Intrinsics`, :class:`Frame`, :class:`PixelGaussians`, :class:`GeometrySet`,
  :class:`PointCloud`, :class:`TrackInfo`, :class:`InsertInfo`
* tracking: :func:`frame_points` (geometry Gaussians of a depth image), :func:`track` (GICP on SE(3)
  against the geometry set), :func:`track_cost`, :func:`insert` (add non-overlapping Gaussians),
  :func:`relocalise` (wide-basin ICP for a frame GICP lost)
* splatting and mapping: :func:`render_own` (a frame into its own view), :func:`render` (frames into
  any view), :func:`render_scene` (the scene at any pose from its best-covering frames, chosen by
  :func:`select_frames`; :class:`Scene` on the host), :func:`init_gaussians`, :func:`map_frame`, :func:`refine_pose` (rendering-based pose
  initialisation)
* SLAM steps: :class:`RunState` (the whole state of a run: :class:`SLAMState` of tracking and the
  :class:`Recent` frames of mapping), :func:`init_state`, :func:`track_step`, :func:`remember`, :func:`map_step`
* configuration: :class:`SLAMConfig` and its stage configs, :func:`load_preset`
* a finished run's folder: :mod:`sgad_jax.io.ply` (3DGS export), :mod:`sgad_jax.eval.run_eval`,
  :mod:`sgad_jax.io.plots`, :mod:`sgad_jax.viewer`
* meshes: :mod:`sgad_jax.mesh` (TSDF fusion, marching cubes), :mod:`sgad_jax.eval.mesh` (scores)
* host side: :func:`open_dataset`, :func:`run`
"""

from sgad_jax.config import DataConfig, ExportConfig, MapConfig, MeshConfig, SLAMConfig, SyntheticConfig, TrackConfig, load_preset
from sgad_jax.geometry import insert
from sgad_jax.gicp import frame_points
from sgad_jax.mapping import MapInfo, Views, init_gaussians, map_frame, refine_pose
from sgad_jax.slam import Recent, RunState, SLAMState, empty_recent, init_state, map_step, remember, track_step
from sgad_jax.scene import Scene, render_scene, select_frames
from sgad_jax.splat import Render, render, render_own
from sgad_jax.track import cost as track_cost
from sgad_jax.track import relocalise, track, transform_cloud
from sgad_jax.types import (
    Frame,
    GeometrySet,
    InsertInfo,
    Intrinsics,
    PixelGaussians,
    PointCloud,
    TrackInfo,
    empty_geometry,
    make_frame,
    make_intrinsics,
)


def open_dataset(cfg: DataConfig):
    """Open a dataset folder (or the synthetic scene); see :mod:`sgad_jax.io.datasets`."""
    from sgad_jax.io.datasets import open_dataset as _open

    return _open(cfg)


def run(cfg: SLAMConfig, out_dir=None, **kwargs):
    """Run the pipeline over ``cfg.data``; see :func:`sgad_jax.pipeline.run`."""
    from sgad_jax.pipeline import run as _run

    return _run(cfg, out_dir, **kwargs)


__version__ = "0.1.0"
__all__ = [
    "DataConfig", "ExportConfig", "MapConfig", "MeshConfig", "SLAMConfig", "SyntheticConfig", "TrackConfig", "load_preset",
    "insert", "frame_points", "RunState", "Recent", "SLAMState", "empty_recent", "remember", "init_state", "track_step", "track_cost", "track", "relocalise",
    "transform_cloud", "Frame", "GeometrySet", "InsertInfo", "Intrinsics", "PixelGaussians",
    "PointCloud", "TrackInfo", "empty_geometry", "make_frame", "make_intrinsics", "open_dataset", "run",
    "MapInfo", "Views", "init_gaussians", "map_frame", "refine_pose", "map_step", "Render", "render", "render_own",
    "Scene", "render_scene", "select_frames",
]
