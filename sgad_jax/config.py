"""Configuration: one frozen dataclass per pipeline stage, nested in :class:`SLAMConfig`.

Presets are Python files in ``configs/`` exposing ``get_config()``; command-line overrides use
dotted keys (``--set track.stride=10``), parsed with the type of the field they replace.
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import json
import pathlib
from typing import Any


@dataclasses.dataclass(frozen=True)
class SyntheticConfig:
    """The built-in procedurally textured room (see ``sgad_jax.io.synthetic``)."""

    frames: int = 60
    width: int = 320
    height: int = 240
    depth_noise: float = 0.0  # std of Gaussian depth noise, metres per metre of depth
    seed: int = 0
    # A sudden camera jump (a dropped stretch of frames, a knocked camera) to test tracking health:
    # from frame jump_frame on (0: never) the camera is displaced by jump = (metres, degrees).
    jump_frame: int = 0
    jump: tuple[float, ...] = (0.2, 10.0)


def _check_ranges(section: str, cfg, *, at_least_one=(), positive=(), non_negative=()) -> None:
    """One line naming the first field out of its range (NaN is out of every range): a zero voxel or
    a negative count otherwise fails deep inside a compiled step, or not at all."""
    for names, ok, what in ((at_least_one, lambda v: v >= 1, ">= 1"), (positive, lambda v: v > 0, "> 0"), (non_negative, lambda v: v >= 0, ">= 0")):
        for name in names:
            if not ok(getattr(cfg, name)):
                raise ConfigError(f"{section}.{name}: must be {what}, got {getattr(cfg, name)}")


@dataclasses.dataclass(frozen=True)
class DataConfig:
    path: str = ""  # empty: the built-in synthetic scene
    layout: str = "auto"  # auto | tum | replica | 7scenes | scannet | scannetpp | generic | synthetic
    start: int = 0
    stride: int = 1
    max_frames: int = 0  # 0: all
    downscale: int = 1  # integer factor: colour by area averaging, depth by the block's mean on one surface
    intrinsics: tuple[float, ...] = ()  # (fx, fy, cx, cy) at full resolution; empty: from the dataset
    depth_scale: float = 0.0  # raw units per metre; 0: the dataset's convention
    depth_trunc: float = 0.0  # metres; depth beyond it is treated as missing; 0: keep all
    tum_max_dt: float = 0.08  # TUM rgb/depth/pose association tolerance (s), as every published number
    inpaint: bool = True  # fill missing depth by Navier-Stokes inpainting for the appearance branch
    nonfinite_depth: str = "error"  # NaN/Inf depth pixels: a bad frame (error), or missing depth (missing)
    # The paper's depth-noise ablation (as ../shared/tools/corrupt_depth.py): this share of each
    # frame's valid depth pixels gets N(0, noise_sigma) metres added, drawn from (noise_seed, the
    # depth image), so a frame's noise does not depend on which frames are read or in what order.
    noise_share: float = 0.0
    noise_sigma: float = 0.02
    noise_seed: int = 0
    synthetic: SyntheticConfig = SyntheticConfig()

    def __post_init__(self):
        _check_ranges("data", self, positive=("tum_max_dt",), non_negative=("depth_scale", "depth_trunc"))
        if not 0.0 <= self.noise_share <= 1.0 or self.noise_sigma < 0:
            raise ConfigError(
                f"data.noise_share must lie in [0, 1] and data.noise_sigma be >= 0; got {self.noise_share}, {self.noise_sigma}"
            )


@dataclasses.dataclass(frozen=True)
class TrackConfig:
    """Geometry branch: GICP of every R-th pixel against the global geometry set T."""

    stride: int = 5  # R: take every R-th pixel of the full-resolution depth image (paper: 10 Replica/ScanNet++, 5 TUM/ScanNet); SLAMConfig.tracking divides it by data.downscale
    k: int = 23  # K_c: neighbours for each point's covariance (paper: 10 Replica, 23 TUM, 15 ScanNet)
    window: int = 5  # the K_c neighbours are the nearest in 3D among a window x window patch of the strided grid
    depth_gate: float = 0.1  # a neighbour farther than depth_gate * depth (along z) is another surface
    eps: float = 1e-3  # floor of eigenvalue ratios after scale normalisation
    min_depth: float = 0.1
    max_depth: float = 0.0  # 0: no limit
    # Geometry set: one Gaussian per voxel of this size; a point in an occupied voxel overlaps T.
    # 3 cm with matches within one voxel (max_correspondence), not 2 cm and 5 cm: noisy depth and
    # frames far apart track within 20% of clean (docs/method.md, "Depth outliers").
    voxel_size: float = 0.03
    capacity: int = 1 << 18  # geometry set capacity on the device (Gaussians); see sgad_jax.paging
    # The set is paged (far entries to host memory, the set rebuilt around the camera) when fuller
    # than page_high of its capacity, down to page_low; also when the camera nears its key cube's edge.
    page_high: float = 0.75
    page_low: float = 0.5
    max_iterations: int = 30  # Gauss-Newton steps per solver level (see coarse)
    tolerance: float = 5e-4  # stop when the update's translation (m) and rotation (rad) fall below it
    max_correspondence: float = 0.03  # metres between a point and its match in T (one voxel)
    nn_weight: float = 0.1  # match score (n_b . e)^2 + nn_weight |e|^2: 0 is pure point-to-surface
    constant_velocity: bool = True
    # A depth image identical to the previous frame's (a repeated capture: 7-Scenes repeats ~1 in 5
    # after frame 220 of redkitchen; TUM pairs two colour images with one depth image) keeps the
    # previous frame's pose instead of being tracked again from a moved guess.
    hold_repeated_depth: bool = True
    # Residual weight (z / 1 m)^-p of a point at camera depth z (0: unweighted, as the paper);
    # see docs/method.md, "Departures from the paper".
    depth_weight_power: float = 1.0
    # Coarse to fine: Gauss-Newton first converges on every c-th point for each c in turn, then on
    # all points; () is one level, as in the paper. Same accuracy, fewer full-size steps (docs/method.md).
    coarse: tuple[int, ...] = (3,)
    # Largest multiple of a Gauss-Newton update taken when consecutive updates shrink the same way
    # (Aitken extrapolation, sgad_jax.track._stretch); 1: plain Gauss-Newton. Fewer steps, same
    # accuracy (docs/method.md).
    extrapolation: float = 4.0
    # Tracking health (docs/method.md, "Tracking health"): a solved pose fails when it is not finite,
    # when its share of matched points is under min_inlier_share times the last accepted frame's
    # (the share depends on point density against the voxels), when it moved more than
    # max_jump (metres, degrees) from the guess; a Hessian whose smallest / largest eigenvalue is
    # under min_conditioning is named as a reason beside those (alone it is a corridor, not a
    # failure). A failed frame is relocalised (relocalise_*); if that fails too it
    # keeps the guess and adds nothing to T.
    judge: bool = True
    min_inlier_share: float = 0.3
    max_jump: tuple[float, ...] = (0.15, 8.0)
    min_conditioning: float = 1e-4
    relocalise: bool = True
    relocalise_points: int = 1024  # frame points matched by brute force
    relocalise_map_points: int = 4096  # points of T in front of the guessed camera, drawn at random
    relocalise_iterations: int = 40
    relocalise_gate: tuple[float, ...] = (0.5, 0.05)  # correspondence gate (metres), first and last iteration
    relocalise_max_move: tuple[float, ...] = (1.0, 45.0)  # farthest a relocalised pose may be from the guess (metres, degrees)
    # A sampled depth pixel is used (tracked and inserted into T) only if it lies within
    # median_gate * depth of the median of its full-resolution 3x3 neighbourhood: isolated
    # outliers (noise spikes, flying pixels) are dropped before they bend their neighbours'
    # covariances or enter T. 0: off, as the paper (docs/method.md).
    median_gate: float = 0.01
    # With the gate on, the frame's points are tracked at that 3x3 median depth instead of their own
    # pixel's (false: their own, as the paper); T still receives the measured depths (docs/method.md).
    median_depth: bool = True
    fuse_observations: int = 4  # each entry of T: the mean of its voxel's first N observations (1: the first, as the paper)
    # Each point moved along its normal onto the plane of its K_c window neighbours, and T stores
    # those in the voxels of the measured points: takes a noisy sensor's noise out of T (on in the
    # real-sensor presets, with depth_weight_power = 2; off for exact depth, where it only flattens
    # curved surfaces: docs/method.md, "T's points on their window's plane").
    plane_points: bool = False

    def __post_init__(self):
        _check_ranges(
            "track", self,
            at_least_one=("stride", "capacity", "max_iterations", "fuse_observations", "relocalise_points", "relocalise_map_points", "relocalise_iterations"),
            positive=("depth_gate", "eps", "voxel_size", "max_correspondence"),
            non_negative=("tolerance", "min_depth", "max_depth", "nn_weight", "depth_weight_power", "min_inlier_share", "min_conditioning", "median_gate"),
        )
        if self.window < 3 or self.window % 2 == 0 or not 3 <= self.k <= self.window**2:
            raise ConfigError(f"track.window must be odd and >= 3, and track.k within [3, window^2]; got window {self.window}, k {self.k}")
        if not 0 < self.page_low < self.page_high <= 1:
            raise ConfigError(f"track.page_low and track.page_high: 0 < low < high <= 1; got {self.page_low}, {self.page_high}")
        if any(c < 1 for c in self.coarse):
            raise ConfigError(f"track.coarse: each level takes every c-th point, c >= 1; got {self.coarse}")
        if not self.extrapolation >= 1.0:
            raise ConfigError(f"track.extrapolation: an update can only be lengthened, >= 1; got {self.extrapolation}")
        for name in ("max_jump", "relocalise_gate", "relocalise_max_move"):
            if len(getattr(self, name)) != 2 or min(getattr(self, name)) <= 0:
                raise ConfigError(f"track.{name}: two positive numbers, got {getattr(self, name)}")


@dataclasses.dataclass(frozen=True)
class MapConfig:
    """Appearance branch (pixel-aligned Gaussians at adjusted depth); paper hyper-parameters."""

    # Adam steps a mapped frame (the paper's 100): 15, with the radius and opacity rates scaled to
    # travel as far (mapping.reach_scale), and the colour fit below render held-out views as well
    # in 0.15 of the time (docs/method.md, "Iterations per frame and the colour fit")
    iterations: int = 15
    neighbours: int = 2
    neighbour_gap: int = 1  # the neighbours are every gap-th previous mapped frame (1: the last ones, as the paper)
    # Map every K-th tracked frame (keyframes; neighbours are counted among them); the frames between
    # are rendered from the scene and scored with the rest (docs/method.md, "Keyframes")
    every: int = 1
    # After Adam, this many minimal-residual steps fit the colours to the own view, where the render
    # is linear in them (docs/method.md, "Mapping"); 0: Adam alone
    colour_fit: int = 2
    current_view_fraction: float = 0.7  # paper: at least 0.4; see docs/method.md (neighbour views pull the own view down)
    lr_rgb: float = 0.0025
    lr_radius: float = 0.005
    lr_opacity: float = 0.05
    lr_offset: float = 0.01
    lr_offset_final: float = 0.0001  # the offset's rate decays to this over a frame's iterations (3DGS's positions: 1/100)
    weight_l1: float = 0.8
    weight_ssim: float = 0.2
    weight_depth: float = 1.0
    learn_offset: bool = True  # False: Gaussians stay at the measured depth (the paper's ablation)
    # False: the own view's loss sees the Gaussians at their measured depths and holds each offset
    # to them by weight_depth * |offset|. There a rendered offset changes only the depth, and the
    # depth loss spent it on the compositing's bias (docs/method.md)
    offset_in_own_view: bool = False
    offset_at_invalid: bool = False  # True: also learn the offsets of Gaussians where depth was not measured (see docs/method.md)
    # An offset corrects the measured depth within the sensor's error: |offset| <= offset_bound * D^2
    # (metres; 1.425e-3 is the Kinect's depth std per m^2, Khoshelham and Elberink 2012); 0: unbounded
    offset_bound: float = 1.425e-3
    # Frames mapped together: within a batch, not-yet-mapped neighbours contribute their initial
    # Gaussians; 0: one frame per mapping device (1 on one device: strictly sequential, as the paper).
    batch: int = 0
    learn_neighbours: bool = True  # neighbours as learned (paper Eq. 1); False: their initial Gaussians
    depth_fill: str = "inpaint"  # missing depth for the Gaussians: inpaint (Navier-Stokes) | render (previous frames' Gaussians)
    radius_init: str = "extent"  # initial radius D / f taken as the 3-sigma extent (extent) or as sigma (sigma)
    coverage_mask: bool = True  # neighbour views: fit only pixels the frame's Gaussians cover
    render_init: bool = False  # refine the pose guess by rendering the previous frame's Gaussians
    render_init_iterations: int = 30
    psnr_protocol: str = "whole"  # whole | valid (valid-depth pixels) | zeroed (invalid pixels zeroed)
    host_budget_mb: float = 64.0  # mapped frames' Gaussians kept in host memory; older ones live on disk only

    def __post_init__(self):
        _check_ranges(
            "map", self,
            non_negative=("iterations", "neighbours", "render_init_iterations", "lr_rgb", "lr_radius", "lr_opacity", "lr_offset",
                          "weight_l1", "weight_ssim", "weight_depth", "host_budget_mb"),
        )
        if not 0 <= self.current_view_fraction <= 1:
            raise ConfigError(f"map.current_view_fraction must lie in [0, 1]; got {self.current_view_fraction}")
        choices = {"depth_fill": ("inpaint", "render"), "radius_init": ("extent", "sigma")}
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ConfigError(f"map.{name}: choose {' or '.join(allowed)}, got {getattr(self, name)!r}")
        if self.neighbour_gap < 1:
            raise ConfigError(f"map.neighbour_gap: every gap-th previous mapped frame, gap >= 1; got {self.neighbour_gap}")
        if not 0 < self.lr_offset_final <= self.lr_offset:
            raise ConfigError(f"map.lr_offset_final must lie in (0, map.lr_offset]; got {self.lr_offset_final}")
        if self.offset_bound < 0:
            raise ConfigError(f"map.offset_bound: metres per m^2 of depth, >= 0 (0: unbounded); got {self.offset_bound}")
        if self.batch < 0:
            raise ConfigError(f"map.batch: frames mapped together, >= 1 (0: one per device); got {self.batch}")
        if self.colour_fit < 0:
            raise ConfigError(f"map.colour_fit: fitting steps after Adam, >= 0; got {self.colour_fit}")
        if self.every < 1:
            raise ConfigError(f"map.every: map every K-th frame, K >= 1; got {self.every}")


@dataclasses.dataclass(frozen=True)
class SceneConfig:
    """The scene renderer and what is judged with it: held-out views and merged-map refinement."""

    frames: int = 8  # k: mapped frames whose Gaussians render a view (those that best cover it)
    # priority: each frame's render over the farther frames' (occluders excepted); depth: all
    # Gaussians merged in depth order (docs/method.md, "The scene and held-out views")
    composite: str = "priority"
    layers: int = 4  # with composite=depth: nearest Gaussians kept per pixel slot
    finetune_lr_scale: float = 1.0  # learning rates of the merged-map refinement, times the mapping ones
    # Offsets move in the refinement too. Off by default: with depth compositing the depth loss
    # reached only the front-most Gaussian, and pushing it back ratcheted whole surfaces backwards
    # (docs/method.md); mapping already found no held-out gain in learned offsets.
    finetune_offsets: bool = False
    # Host memory for the refinement's Gaussians and Adam moments (three copies of the map); the
    # rest waits in a temporary folder (a 640x480 frame takes 26 MB)
    finetune_budget_mb: float = 4096.0

    def __post_init__(self):
        _check_ranges("scene", self, non_negative=("finetune_lr_scale", "finetune_budget_mb"))
        if self.composite not in ("priority", "depth"):
            raise ConfigError(f"scene.composite: choose priority or depth, got {self.composite!r}")
        if self.frames < 1 or self.layers < 1:
            raise ConfigError(f"scene.frames and scene.layers: >= 1, got {self.frames} and {self.layers}")


@dataclasses.dataclass(frozen=True)
class ExportConfig:
    """The merged map written by ``--export-ply`` / ``sgad-jax export`` (see ``sgad_jax.io.ply``)."""

    # Merge cell (metres at data.downscale=1, multiplied by the downscale): one Gaussian per cell; 0 keeps all.
    # 5 mm is a 640-wide camera's pixel footprint at about 3 m, so a frame's own coverage keeps its
    # spacing over indoor depths while the frames re-covering the same surface are merged away.
    voxel: float = 0.005

    def __post_init__(self):
        _check_ranges("export", self, non_negative=("voxel",))


@dataclasses.dataclass(frozen=True)
class MeshConfig:
    """TSDF fusion of rendered depth and colour, then marching cubes (``sgad_jax.mesh``)."""

    voxel: float = 0.01  # metres at full resolution (the SLAM papers' 1 cm), times data.downscale
    trunc: float = 0.04  # truncation distance, metres at full resolution (papers: 4 cm), times data.downscale
    max_weight: float = 0.0  # cap of a voxel's accumulated weight; 0: plain running average
    max_voxels: int = 1 << 27  # grid budget (~20 bytes a voxel); a larger grid is coarsened, and says so
    min_depth: float = 0.05  # depth outside [min_depth, max_depth] is not fused
    max_depth: float = 0.0  # 0: no limit

    def __post_init__(self):
        _check_ranges("mesh", self, at_least_one=("max_voxels",), positive=("voxel", "trunc"), non_negative=("max_weight", "min_depth", "max_depth"))


@dataclasses.dataclass(frozen=True)
class SLAMConfig:
    name: str = "default"
    data: DataConfig = DataConfig()
    track: TrackConfig = TrackConfig()
    map: MapConfig = MapConfig()
    scene: SceneConfig = SceneConfig()
    export: ExportConfig = ExportConfig()
    mesh: MeshConfig = MeshConfig()
    seed: int = 0

    def tracking(self) -> TrackConfig:
        """The tracking settings for frames read at ``data.downscale``: ``track.stride`` counts
        full-resolution pixels, so a downscaled frame keeps about as many points (docs/method.md)."""
        return dataclasses.replace(self.track, stride=max(1, self.track.stride // self.data.downscale))


class ConfigError(ValueError):
    """A preset or override that cannot be applied."""


def _parse(text: str, current: Any, key: str) -> Any:
    try:
        if isinstance(current, bool):
            low = text.strip().lower()
            if low in ("1", "true", "yes", "on"):
                return True
            if low in ("0", "false", "no", "off"):
                return False
            raise ValueError(text)
        if isinstance(current, int):
            return int(text)
        if isinstance(current, float):
            return float(text)
        if isinstance(current, tuple):
            text = text.strip().strip("()[]")
            kind = type(current[0]) if current else float
            return tuple(kind(v) for v in text.replace(",", " ").split()) if text else ()
        return text
    except ValueError:
        raise ConfigError(f"--set {key}={text}: expected a value of type {type(current).__name__}") from None


def override(cfg: Any, key: str, text: str, _full: str | None = None) -> Any:
    """Return ``cfg`` with the dotted field ``key`` set from the string ``text``."""
    full = key if _full is None else _full
    head, _, rest = key.partition(".")
    names = [f.name for f in dataclasses.fields(cfg)]
    if head not in names:
        raise ConfigError(f"--set {full}: unknown field '{head}' (choose from {', '.join(names)})")
    current = getattr(cfg, head)
    if rest:
        if not dataclasses.is_dataclass(current):
            raise ConfigError(f"--set {full}: '{head}' has no sub-fields")
        return dataclasses.replace(cfg, **{head: override(current, rest, text, full)})
    if dataclasses.is_dataclass(current):
        raise ConfigError(f"--set {full}: '{head}' is a group; set one of its fields, e.g. {head}.{dataclasses.fields(current)[0].name}")
    return dataclasses.replace(cfg, **{head: _parse(text, current, full)})


def apply_overrides(cfg: SLAMConfig, items: list[str]) -> SLAMConfig:
    for item in items:
        key, sep, text = item.partition("=")
        if not sep:
            raise ConfigError(f"--set {item}: expected key=value")
        cfg = override(cfg, key.strip(), text.strip())
    return cfg


PRESET_DIR = pathlib.Path(__file__).resolve().parent.parent / "configs"


def load_preset(name_or_path: str) -> SLAMConfig:
    """A preset by name (``tum``, ``replica``, ...: ``configs/<name>.py``) or by path to a ``.py`` file."""
    path = pathlib.Path(name_or_path)
    if path.suffix == ".py":
        if not path.is_file():
            raise ConfigError(f"{path}: config file not found")
        spec = importlib.util.spec_from_file_location(f"_sgad_preset_{path.stem}", path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    else:
        try:
            module = importlib.import_module(f"configs.{name_or_path}")
        except ModuleNotFoundError:
            names = sorted(p.stem for p in PRESET_DIR.glob("*.py") if not p.stem.startswith("_"))
            raise ConfigError(f"unknown preset '{name_or_path}' (choose from {', '.join(names)} or give a .py path)") from None
    if not hasattr(module, "get_config"):
        raise ConfigError(f"{name_or_path}: a preset must define get_config()")
    cfg = module.get_config()
    if not isinstance(cfg, SLAMConfig):
        raise ConfigError(f"{name_or_path}: get_config() must return an SLAMConfig")
    return cfg


def to_dict(cfg: Any) -> dict:
    return json.loads(json.dumps(dataclasses.asdict(cfg)))
