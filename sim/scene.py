"""Scenes: a head, its animation, a hairstyle and solver settings, run headless to a USD cache.

A scene file is TOML with the tables [scene], [head], [hair] and [solver]; see
examples/scenes/*.toml. The same is reachable from Python: build a SceneConfig (or load_scene), then
run_scene(config, "out.usdc").
"""

import functools
import math
import os
import sys
import threading
import time
import warnings
from dataclasses import asdict, dataclass, field, replace

import numpy as np
import warp as wp

import warp_kernels

from . import __version__
from .cloth import ClothModel, ClothParams, ClothSolver
from .collider import Collider
from .detail import ClothDetail, DetailParams, pn_surface_points
from .config import LIMITS, from_table, load_toml, require_positive, require_within
from .graphs import AsyncReadback, FrameGraphs, cpu_cores, run_parallel, run_side_by_side
from .errors import InputError, raise_if_stopped
from .asset_cache import cached_arrays
from .capture_rig import CaptureConfig
from .face import SKIN, FaceAnimation, FaceConfig, FaceRig, builtin_face, face_from_file, parse_expressions
from .hair_children import HairChildren
from .hair_solver import HAIR_FRAMES, HairParams, HairSolver, deferred_step_modules
from .comb import before_frame as comb_before_frame
from .haircut import parse_timeline, run_events
from .hairstyle import HairstyleParams, check_color, grow_hairstyle, sample_scalp, scalp_area
from .head import HeadAnimation, mesh_head, procedural_head
from .quality import QualityProbe
from .strands import StrandBuilder

HAIR_COLOR = HairstyleParams.color
SKIN_COLOR = SKIN  # the head is drawn in the skin its face is painted with, so the face's edge does not show


@dataclass(frozen=True)
class TimingConfig:
    fps: float = 24.0  # frames per second written to the cache
    frames: int = 72  # frames written
    start_frame: int = 1  # time code of the first frame
    preroll: float = 1.0  # s simulated before the first frame so the hair has settled
    device: str = "cpu"  # "cpu" or "cuda" (or "cuda:N")
    stats: bool = True  # measure stretch, root drift and penetration every frame
    graphs: bool = True  # capture each solver's frame once (a CUDA graph, or a recorded CPU graph) and replay it
    # "in_block": each hair frame in one launch, a block of lanes per strand (HairSolver.frame_in_block);
    # "in_warps": the same with 32 strands a block side by side (HairSolver.frame_warps); GPU experiments,
    # "substeps" the launches of each substep
    hair_frames: str = "substeps"

    def __post_init__(self):
        if self.hair_frames not in HAIR_FRAMES:
            raise ValueError('hair_frames must be "substeps", "in_block" or "in_warps"')
        # a frame longer than a second is no shot's rate; near zero a frame's step overflowed float32 (fps 1e-300)
        if self.fps < 1.0:
            raise ValueError(f"fps must be at least 1, got {self.fps!r}")
        if self.frames < 1:
            raise ValueError("frames must be at least 1")
        if self.preroll < 0.0:
            raise ValueError("preroll must be zero or positive")


@dataclass(frozen=True)
class HeadConfig:
    mesh: str = "builtin"  # "builtin" or a mesh file trimesh loads (metres, Y up)
    scalp_faces: str = ""  # .npy of scalp face indices or a boolean face mask (mesh files)
    roots: str = ""  # .npy/.txt of (N, 3) root points; overrides the scalp sampling
    animation: str = "turn_nod"  # "turn_nod", "turn", "nod" or "none"
    turn_degrees: float = 40.0  # degrees the head turns to either side
    turn_period: float = 3.0  # s, one turn there and back
    nod_degrees: float = 15.0  # degrees the head nods down and up
    nod_period: float = 1.5  # s, one nod
    sphere_leaves: int = 1024  # most leaf spheres in the sphere tree (built for collision = "sphere_tree")

    def __post_init__(self):
        if self.animation not in ("turn_nod", "turn", "nod", "none"):
            raise ValueError("animation must be one of turn_nod, turn, nod, none")
        require_positive(self, "turn_period", "nod_period")
        require_within(self, "turn_degrees", -180.0, 180.0)
        require_within(self, "nod_degrees", -90.0, 90.0)
        if self.sphere_leaves < 1:
            raise ValueError("sphere_leaves must be at least 1")


@dataclass(frozen=True)
class BodyConfig:
    """A character body as the collider (instead of the head bust): built in, or a user's mesh."""

    enabled: bool = False  # set by the presence of a [body] table
    mesh: str = "builtin"  # "builtin", a mesh file (with `points`), or a USD file (with `prim`)
    points: str = ""  # .npy of (frames, V, 3) vertex positions animating a mesh file, one per frame
    prim: str = ""  # prim path of a UsdGeom.Mesh with time-sampled points, when mesh is a USD file
    animation: str = "walk"  # built-in body: "walk", "arm_raise", "turn" or "none"
    in_place: bool = False  # built-in walk: stay on the spot instead of walking forward

    def __post_init__(self):
        if self.animation not in ("walk", "arm_raise", "turn", "none"):
            raise ValueError("animation must be one of walk, arm_raise, turn, none")


@dataclass(frozen=True)
class GarmentConfig:
    """The garment simulated as cloth; its solver settings are the [cloth.solver] table."""

    enabled: bool = False  # set by the presence of a [cloth] table
    garment: str = "dress"  # "dress", "skirt", "shirt" (fitted to the built-in body) or a mesh/USD file
    prim: str = ""  # prim path of the garment's UsdGeom.Mesh when garment is a USD file
    pinned: str = ""  # .npy of vertex indices bound to the body, for a garment file
    # the particle count a built-in garment is meshed to, within a few percent (the paper's one-piece dress has 322;
    # the built-in dress then has 332)
    particles: int = 322
    ease: float = 0.012  # m, how far outside the body a built-in garment is fitted
    color: tuple = (0.25, 0.35, 0.55)  # linear RGB: the garment's and its detail surface's displayColor

    def __post_init__(self):
        if self.particles < 16:
            raise ValueError("particles must be at least 16")
        if self.ease <= 0.0:
            raise ValueError("ease must be positive")
        check_color(self.color)


@dataclass(frozen=True)
class SceneConfig:
    source: str = "<demo>"  # the scene file this came from, for error messages
    timing: TimingConfig = field(default_factory=TimingConfig)
    head: HeadConfig = field(default_factory=HeadConfig)
    hair: HairstyleParams = field(default_factory=HairstyleParams)
    solver: HairParams = field(default_factory=HairParams)
    body: BodyConfig = field(default_factory=BodyConfig)
    cloth: GarmentConfig = field(default_factory=GarmentConfig)
    cloth_solver: ClothParams = field(default_factory=ClothParams)
    cloth_detail: DetailParams = field(default_factory=DetailParams)
    face: FaceConfig = field(default_factory=FaceConfig)
    capture: CaptureConfig = field(default_factory=CaptureConfig)  # cfx capture synth only
    haircut: tuple = ()  # sim.haircut.HaircutEvent, one per [[haircut]] table: the grooming timeline
    given_geometry: bool = False  # the geometry comes as SceneAssets: head, body and garment tables do not apply

    def settings(self):
        """Everything that determines the result, for the cache's customLayerData."""
        out = {"scene": self.source, "timing": asdict(self.timing)}
        if not self.given_geometry:
            out["body" if self.body.enabled else "head"] = asdict(self.body if self.body.enabled else self.head)
        if self.hair.enabled:
            out.update(solver=asdict(self.solver))
            if not self.given_geometry:
                out.update(hair=asdict(self.hair))
        if self.cloth.enabled:
            out.update(cloth_solver=asdict(self.cloth_solver), cloth_detail=asdict(self.cloth_detail))
            if not self.given_geometry:
                out.update(cloth=asdict(self.cloth))
        if self.haircut:
            out["haircut"] = {f"{k}": event.as_dict() for k, event in enumerate(self.haircut)}
        if self.face.enabled:
            face = asdict(self.face)
            face["expressions"] = [{"frame": k.frame, "emotion": k.emotion, "weight": k.weight,
                                    "aus": {str(a): v for a, v in k.action_units}} for k in self.face.expressions]
            out["face"] = face
        return out


SECTIONS = {"scene": ("timing", TimingConfig), "head": ("head", HeadConfig),
            "hair": ("hair", HairstyleParams), "solver": ("solver", HairParams),
            "body": ("body", BodyConfig), "cloth": ("cloth", GarmentConfig), "face": ("face", FaceConfig),
            "capture": ("capture", CaptureConfig)}


def load_scene(path, overrides=None):
    """Read and validate a TOML scene file. overrides: {"scene": {"frames": 10}, ...}."""
    data = load_toml(path)
    known = (*SECTIONS, "haircut")
    for section in data:
        if section not in known:
            raise InputError(path, f"[{section}]", f"unknown table (known: {', '.join(known)})")
    return _build_config(str(path), data, overrides)


DEMO = {"scene": {"frames": 84}, "body": {"animation": "walk"},
        "cloth": {"garment": "dress", "solver": {"strain_limit": 0.03}}, "hair": {"count": 2000},
        "face": {"audio": "builtin", "audio_start": 4.0,
                 "expressions": [{"frame": 1, "emotion": "neutral"}, {"frame": 24, "emotion": "happiness", "weight": 0.8},
                                 {"frame": 70, "emotion": "surprise", "weight": 0.5}]}}


def demo_scene(overrides=None):
    """The built-in scene: the character walks in a one-piece dress, with wavy shoulder-length hair,
    and says a line, smiling."""
    return _build_config("<demo>", {k: dict(v) for k, v in DEMO.items()}, overrides)


def hair_demo_scene(overrides=None):
    """Hair alone: wavy shoulder-length hair on the built-in head bust turning and nodding."""
    return _build_config("<demo>", {}, overrides)


def _build_config(source, data, overrides, check_files=True):
    """check_files=False: the geometry comes as SceneAssets, so the tables name no files to check."""
    overrides = overrides or {}
    data = {k: dict(v) if isinstance(v, dict) else v for k, v in data.items()}
    timeline = data.pop("haircut", [])
    cloth_table = dict(data.get("cloth", {}))
    solver_table = cloth_table.pop("solver", {})
    detail_table = cloth_table.pop("detail", {})
    if "cloth" in data:
        data["cloth"] = {"enabled": True, **cloth_table}
    if "body" in data:
        data["body"] = {"enabled": True, **data["body"]}
    expressions = ()
    if "face" in data:
        face_table = dict(data["face"]) if isinstance(data["face"], dict) else data["face"]
        if isinstance(face_table, dict):
            expressions = parse_expressions(face_table.pop("expressions", []), source)
            face_table = {"enabled": True, **face_table}
        data["face"] = face_table
    parts = {}
    for section, (attr, cls) in SECTIONS.items():
        parts[attr] = from_table(cls, data.get(section, {}), source, section, overrides.get(section))
    parts["cloth_solver"] = from_table(ClothParams, solver_table, source, "cloth.solver",
                                       overrides.get("cloth.solver"))
    parts["cloth_detail"] = from_table(DetailParams, detail_table, source, "cloth.detail",
                                       overrides.get("cloth.detail"))
    if expressions:
        parts["face"] = replace(parts["face"], expressions=expressions)
    parts["haircut"] = parse_timeline(timeline, source, parts["timing"])
    if parts["haircut"] and not parts["hair"].enabled:
        raise InputError(source, "haircut", "the scene has no hair to cut ([hair] enabled = false)")
    config = SceneConfig(source=source, given_geometry=not check_files, **parts)
    if not check_files:
        return config
    base = os.path.dirname(os.path.abspath(source)) if source != "<demo>" else os.getcwd()
    files = [("head", k, getattr(config.head, k)) for k in ("mesh", "scalp_faces", "roots")]
    files += [("body", k, getattr(config.body, k)) for k in ("mesh", "points")]
    files += [("cloth", k, getattr(config.cloth, k)) for k in ("pinned",)]
    files += [("hair", "guides", config.hair.guides)]
    files += [("face", k, getattr(config.face, k)) for k in ("mesh", "features", "mouth")]
    if config.face.audio != "builtin":
        files.append(("face", "audio", config.face.audio))
    if config.cloth.garment not in _garment_names():
        files.append(("cloth", "garment", config.cloth.garment))
    for section, key, value in files:
        if value and value != "builtin" and not os.path.exists(os.path.join(base, value)):
            where = os.path.normpath(os.path.join(base, value))
            missing = value + (f" (paths are taken from the scene file's folder: {where})" if where != value else "")
            if (section, key) == ("cloth", "garment"):
                reason = f"not a built-in garment ({', '.join(_garment_names())}) nor a file: {missing}"
            else:
                reason = f"file not found: {missing}"
            raise InputError(source, f"{section}.{key}", reason)
    f = config.face
    if f.enabled and f.mesh == "builtin" and (config.head.mesh != "builtin" if not config.body.enabled
                                              else config.body.mesh != "builtin"):
        raise InputError(source, "face.mesh", "the built-in face fits only the built-in head and body: give "
                                              "face.mesh and face.features for your own head")
    if f.enabled and f.mesh == "builtin" and f.features:
        raise InputError(source, "face.features", "the built-in face has its own feature points: features go with "
                                                  "a face.mesh file")
    if f.enabled and f.mesh != "builtin" and not f.features:
        raise InputError(source, "face.features", "a face mesh needs its feature-point map (JSON name -> vertex)")
    if config.cloth.enabled and not config.body.enabled and config.cloth.garment in _garment_names():
        raise InputError(source, "cloth.garment", "built-in garments are fitted to the built-in body: add a [body] table")
    return config


def _garment_names():
    return ("dress", "skirt", "shirt")


def _resolve(config, name):
    base = os.path.dirname(os.path.abspath(config.source)) if config.source != "<demo>" else os.getcwd()
    return os.path.join(base, name)


def _load_head(config):
    import trimesh

    h = config.head
    if h.mesh == "builtin":
        head = procedural_head()
    else:
        path = _resolve(config, h.mesh)
        try:
            mesh = trimesh.load(path, force="mesh", process=True)
        except Exception as err:  # trimesh raises many types for unreadable files
            raise InputError(config.source, "head.mesh", f"cannot read {h.mesh}: {err}") from None
        if len(mesh.faces) == 0 or not np.all(np.isfinite(mesh.vertices)):
            raise InputError(config.source, "head.mesh", f"{h.mesh} has no faces or non-finite vertices")
        check_collider_frames(config.source, "head.mesh", h.mesh, np.asarray(mesh.vertices)[None], mesh.faces)
        if not mesh.is_watertight:
            raise InputError(config.source, "head.mesh",
                             f"{h.mesh} is not closed (watertight); collisions need an inside and an outside")
        with warnings.catch_warnings():  # trimesh divides by the volume for the centre of mass
            warnings.simplefilter("ignore")
            volume = abs(mesh.volume)
        if not volume > 1e-9:  # flat: closed, but with no inside either
            raise InputError(config.source, "head.mesh", f"{h.mesh} encloses no volume; collisions need an inside")
        scalp = None
        if h.scalp_faces:
            scalp = _load_face_mask(config, len(mesh.faces))
        head = mesh_head(h.mesh, mesh.vertices, mesh.faces, scalp)
    if h.scalp_faces and h.mesh == "builtin":
        head.scalp_faces = _load_face_mask(config, len(head.faces))
    return head


def _load_face_mask(config, face_count):
    path = _resolve(config, config.head.scalp_faces)
    try:
        data = np.load(path)
    except (OSError, ValueError) as err:
        raise InputError(config.source, "head.scalp_faces", f"cannot read {config.head.scalp_faces}: {err}") from None
    if data.dtype == bool:
        if data.shape != (face_count,):
            raise InputError(config.source, "head.scalp_faces",
                             f"mask has {data.size} entries, the mesh has {face_count} faces")
        return data
    if not (np.issubdtype(data.dtype, np.number) and np.all(np.isfinite(data))):
        raise InputError(config.source, "head.scalp_faces", "expected face indices (integers) or a boolean face mask")
    idx = data.astype(np.int64).ravel()
    if idx.size == 0 or idx.min() < 0 or idx.max() >= face_count:
        raise InputError(config.source, "head.scalp_faces", f"face indices must lie in [0, {face_count})")
    mask = np.zeros(face_count, bool)
    mask[idx] = True
    return mask


def _read_array(path, delimiter=None):
    """A .npy file, or a text table (whitespace or `delimiter` separated) as a 2-D array; the caller
    checks the shape. NumPy's warning on an empty text file is left to that check's one line."""
    if path.endswith(".npy"):
        return np.load(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return np.loadtxt(path, delimiter=delimiter, ndmin=2)


def _load_roots(config):
    path = _resolve(config, config.head.roots)
    try:
        roots = _read_array(path)
    except (OSError, ValueError) as err:
        raise InputError(config.source, "head.roots", f"cannot read {config.head.roots}: {err}") from None
    if roots.ndim != 2 or roots.shape[1] != 3 or len(roots) == 0 or not np.all(np.isfinite(roots)):
        raise InputError(config.source, "head.roots", "expected a non-empty (N, 3) array of finite points")
    return roots


@dataclass
class SceneAssets:
    """Geometry handed to a Scene instead of read from the files its config names: the tagged prims
    of a USD stage (io_usd.scene_input) or a host application's arrays (sim.embed). Metres, Y up."""

    collider_name: str
    collider_faces: np.ndarray  # (F, 3) triangles
    motion: "PointCacheMotion"  # the collider's vertex positions per frame (frame 0 is the rest pose)
    hair: tuple = None  # (points (P, 3), vertices per strand (S,), widths (P,) or None); roots first
    garment: object = None  # a sim.garment.GarmentMesh


class Scene:
    """An assembled scene: a collider (head bust or body) and its motion, optional hair, optional
    cloth. Build with Scene(config), then advance(); the states are scene.state (hair) and scene.cloth_state.
    assets: geometry given directly (SceneAssets) instead of through the config's files."""

    def __init__(self, config, assets=None, announce=False):
        """announce: say on stderr when the kernels take more than a second to load (load_kernels)."""
        self.config = config
        self.assets = assets
        device = config.timing.device
        if device.startswith("cuda") and not wp.is_cuda_available():
            raise InputError(config.source, "scene.device", f"device '{device}' is not available (no CUDA driver)")
        try:
            wp.get_device(device)
        except (ValueError, RuntimeError):
            raise InputError(config.source, "scene.device", f"device '{device}' is not available") from None
        self.device = device
        # the hair's fused variant, where its case takes one, compiled beside the six modules
        load_kernels(device, announce, deferred_step_modules(config.solver, device) if config.hair.enabled else None)
        self.time = 0.0
        self._root_vertices = None  # (hair model, its root triangles' collider vertices)
        self.graphs = FrameGraphs(device, config.timing.graphs)
        self.quality = QualityProbe(self)  # the per-frame statistics (measure(), run_scene)
        leaves = config.head.sphere_leaves if config.hair.enabled and config.solver.collision == "sphere_tree" else 0
        if assets is not None:
            self.head = mesh_head(assets.collider_name, assets.motion.frames[0], assets.collider_faces)
            self._motion, self.collider_name = assets.motion, assets.collider_name
        elif config.body.enabled:
            self.head, self._motion = _load_body(config)
            self.collider_name = "body"
        else:
            self.head = _load_head(config)
            h = config.head
            turns, nods = h.animation in ("turn", "turn_nod"), h.animation in ("nod", "turn_nod")
            self._motion = HeadAnimation(turn_degrees=h.turn_degrees if turns else 0.0, turn_period=h.turn_period,
                                         nod_degrees=h.nod_degrees if nods else 0.0, nod_period=h.nod_period,
                                         pivot=self.head.pivot)
            self.collider_name = "head"
        if isinstance(self._motion, PointCacheMotion) and leaves:
            raise InputError(config.source, "solver.collision", "the sphere tree follows skinned colliders only; "
                             "a collider animated by points needs collision = \"mesh\"")
        self.collider = Collider(self.collider_name, self.head.vertices, self.head.faces, self.head.skin_indices,
                                 self.head.skin_weights, self.head.num_bones, device, leaves)
        self._pose(self.collider, self._motion_poses(np.array([0.0])))
        self.collider.apply_pose(0)
        self.collider.reset_motion()

        self.model = self.solver = self.state = self.guides = self.hair_template = self.children = None
        self.held_comb = None  # a sim.comb.CombGrip while a comb holds hair (haircut timelines, cfx studio)
        self.wax_drags = {}  # id of a sim.haircut.HaircutEvent -> WaxDrag: timeline waxes dragged over frames (until)
        # the pose the groom is bound on: haircut edits map styled shapes back into it
        self.groom_points = self.collider.posed_points().copy()  # a copy: on the CPU numpy() is a view
        if config.hair.enabled:
            self.model = self._groom()
            self.children = self._children()
            self.hair_template = self.model  # what a haircut's "initialise" returns to
            self.solver = HairSolver(self.model, config.solver)
            self.solver.step_frames_as(config.timing.hair_frames)
            misfit = self.solver.frame_in_block_misfit(self.collider) if self.solver.frame_in_block else None
            if misfit is not None:
                raise InputError(config.source, "scene.hair_frames", misfit)
            self.state, self._scratch = self.model.state(), self.model.state()
            self.guides = None
            if config.hair.guides:
                from .guides import GuideTargets, read_guides

                try:
                    frames, fps = read_guides(_resolve(config, config.hair.guides), config.hair.guide_prim)
                    self.guides = GuideTargets(self.model, frames, fps)
                except ValueError as err:
                    raise InputError(config.source, "hair.guides", str(err)) from None
        self.cloth_model = self.cloth_solver = self.cloth_state = self.cloth_detail = None
        self.cloth_collider = self.cloth_body = None
        self.side_by_side = True  # False steps the cloth after the hair (the same result, slower on the CPU)
        # the cloth's body queries read triangle boxes bounded once over the frame's poses (Collider.sweep)
        # on the CPU, where that saved the BVH refits of every substep; a GPU refits the body to each
        # substep's pose, so that its closest-point queries go nearest first through the wp.Mesh
        # (ClothSolver.mesh_queries): the walking dress on an H100, 15.9 ms per frame swept, 17.8 refitted
        # with the boxes' queries, 9.8 refitted with the mesh's (BENCHMARKS.md, session 34)
        self.cloth_sweep = not wp.get_device(self.device).is_cuda
        self._frames = 0  # frames simulated, so the detail surface is updated once per frame
        self._detail_frame = -1
        if config.cloth.enabled:
            garment = assets.garment if assets is not None else _load_garment(config, self.head)
            try:
                self.cloth_model = ClothModel.from_garment(garment, config.cloth_solver, device)
            except ValueError as err:
                raise InputError(config.source, "cloth.garment", str(err)) from None
            # the cloth poses a collider of its own (a twin, or a coarser proxy), so its frames and the
            # hair's touch no common data and may run side by side (advance); cloth_body is the body
            # itself posed at the cloth's frame ends, which the detail surface lifts out of
            self.cloth_body = self.collider.twin(spheres=False) if self.model is not None else self.collider
            self.cloth_collider = self.cloth_body
            if config.cloth_solver.body_proxy > 0.0:
                try:
                    self.cloth_collider = self.collider.proxy(config.cloth_solver.body_proxy)
                except ValueError as err:
                    raise InputError(config.source, "cloth.solver.body_proxy", str(err)) from None
                self._pose(self.cloth_collider, self._motion_poses(np.array([0.0])))
                self.cloth_collider.apply_pose(0)
                self.cloth_collider.reset_motion()
            self.cloth_model.bind_to_mesh(self.cloth_collider.posed_points(), self.cloth_collider.faces_np)
            # beside a hair solver the hair's ranges fill the other cores, and a collision split among
            # them would only add hand-overs between threads (the real-time fast row ran 3-5% slower)
            self.cloth_solver = ClothSolver(self.cloth_model, parts=1 if self.model is not None else None)
            self.cloth_state, self._cloth_scratch = self.cloth_model.state(), self.cloth_model.state()
            self.cloth_substeps = self.cloth_model.substeps_for(1.0 / config.timing.fps)
            top = LIMITS[("cloth.solver", "substeps")]
            if self.cloth_substeps > top:  # stiff springs on light cloth: the run would not finish
                step = 1e6 * self.cloth_model.stable_dt
                raise InputError(config.source, "cloth.solver",
                                 f"stable steps of {step:.3g} us need {self.cloth_substeps:,} substeps a frame, at "
                                 f"most {top:,}: soften the springs or damping, or make the cloth heavier (density)")
            if config.cloth_detail.level > 0:
                self.cloth_detail = ClothDetail(self.cloth_model, config.cloth_detail, device)
        self.face_rig = self.face_animation = None
        if config.face.enabled:
            mesh = self._face_mesh()
            if self.model is not None:  # where the face reaches over the scalp it takes the scalp's tint too
                mesh.colors = self._tinted_over_scalp(mesh.colors, mesh.vertices)
            self.face_rig = FaceRig(mesh, device)
            self.face_rig.attach(self.collider)
            self.face_animation = FaceAnimation(config.face.expressions, _mouth_track(config),
                                                config.face.audio_start)

    def _tinted_over_scalp(self, colors, points):
        """colors (N, 3) of points lying over the head, plus the scalp's tint under each (head_colors)."""
        _, face, bary = self.collider.closest_points(points)
        tint = head_colors(self.head, self.config.hair.color) - np.asarray(SKIN_COLOR)
        under = np.einsum("nk,nkj->nj", bary, tint[np.asarray(self.head.faces).reshape(-1, 3)[face]])
        return np.clip(np.asarray(colors, np.float64) + under, 0.0, 1.0)

    def _face_mesh(self):
        cfg = self.config
        if cfg.face.mesh != "builtin":
            try:
                return face_from_file(_resolve(cfg, cfg.face.mesh), _resolve(cfg, cfg.face.features))
            except (OSError, ValueError) as err:
                raise InputError(cfg.source, "face.mesh", str(err)) from None
        import trimesh

        normals = trimesh.Trimesh(self.head.vertices, self.head.faces, process=False).vertex_normals

        def project(points):
            # onto the head's PN surface (as the detail surface over the cloth): a face grid finer than the
            # head's triangles, snapped onto them flat, shows their facets in its shading; its border meets
            # the triangles the head is drawn with
            closest, face, bary = self.collider.closest_points(points)
            return (*pn_surface_points(self.head.vertices, normals, self.head.faces, face, bary), closest)

        offset = getattr(self.head, "head_offset", (0.0, 0.0, 0.0)) if cfg.body.enabled else (0.0, 0.0, 0.0)
        return builtin_face(project, cfg.face.lift, offset, cfg.face.resolution)

    def queue_outputs(self, frame):
        """Launch everything a cache frame needs on the current state without waiting: ({name:
        wp.array} to read back, face weights or None). Names: the collider's, hair, cloth,
        cloth_detail (+ _normals), face and face_rest (the unexpressed face, for the head transform),
        and the solvers' health counts (hair_bad/_first, cloth_bad/_first)."""
        arrays, weights = {self.collider_name: self.collider.points}, None
        if self.model is not None:
            arrays["hair"] = self.state.x
            arrays["hair_bad"], arrays["hair_first"] = self.solver.count_unhealthy(self.state)
            if self.children is not None:
                arrays["hair_children"] = self.children.queue(self.state.x, self.collider,
                                                              self.config.solver.collision_margin,
                                                              self.solver.mesh_clearance())
        if self.cloth_model is not None:
            arrays["cloth"] = self.cloth_state.x
            arrays["cloth_bad"], arrays["cloth_first"] = self.cloth_solver.count_unhealthy(self.cloth_state)
            detail = self.detail_surface()
            if detail is not None:
                arrays["cloth_detail"], arrays["cloth_detail_normals"] = detail
        if self.face_rig is not None:
            weights = self.face_animation.weights(self.face_rig, frame)
            arrays["face"], arrays["face_rest"] = self.face_rig.queue_frame(self.collider, weights)
        return arrays, weights

    def _pose(self, collider, poses):
        """Upload `poses` (_motion_poses at some times) into `collider`; apply_pose(k) picks one."""
        if isinstance(self._motion, PointCacheMotion):
            collider.set_point_poses(poses)
        else:
            collider.set_poses(poses)

    def _motion_poses(self, times):
        """The body's motion at `times`: per-time vertex positions of a point cache, else bone matrices."""
        if isinstance(self._motion, PointCacheMotion):
            return self._motion.points(times)
        return self._motion.bone_matrices(times)

    def _substep_poses(self, t0, frame_dt, substep_counts, animate):
        """{substeps: (times, poses)} for a frame from t0 split into each of `substep_counts`: the
        motion is evaluated once, at every distinct time (hair at 4 and cloth at 12 substeps share
        the hair's 5 times)."""
        if not substep_counts:
            return {}
        counts = tuple(sorted(set(substep_counts)))
        times = {n: (t0 + (frame_dt / n) * np.arange(0, n + 1) if animate else np.full(n + 1, t0)) for n in counts}
        first, picks = _shared_substep_times(counts)
        poses = self._motion_poses(np.concatenate(list(times.values()))[first])
        return {n: (times[n], poses[pick]) for n, pick in zip(counts, picks, strict=True)}

    def _groom(self):
        cfg, head = self.config, self.head
        rest_points = self.groom_points
        if self.assets is not None:
            points, counts, widths = self.assets.hair
            try:
                model = StrandBuilder().add_strands(points, counts, widths).finalize(self.device, pinned_per_strand=2)
            except ValueError as err:
                raise InputError(cfg.source, "hair", str(err)) from None
            return model.bind_to_mesh(rest_points, head.faces)
        if cfg.head.roots:
            roots, normals = self._project_roots(_load_roots(cfg))
        else:
            count = cfg.hair.count
            if cfg.hair.density > 0.0:
                count = max(1, int(round(cfg.hair.density * scalp_area(head.vertices, head.faces, head.scalp_faces) * 1e4)))
            try:
                roots, _, _, normals = sample_scalp(head.vertices, head.faces, head.scalp_faces, count, cfg.hair.seed)
            except ValueError as err:
                raise InputError(cfg.source, "head.scalp_faces", str(err)) from None
        points, counts, widths = self._grown(cfg.hair, roots, normals)
        model = StrandBuilder().add_strands(points, counts, widths).finalize(self.device, pinned_per_strand=2)
        return model.bind_to_mesh(rest_points, head.faces)

    def _grown(self, params, roots, normals):
        """grow_hairstyle's (points, counts, widths) for `params` from roots and normals on the head in
        the groom's pose: grown once per style, roots and head shape (on a CPU or a GPU: their float32
        queries may round differently), and kept between runs by the asset cache."""
        head = self.head
        scalp = head.vertices[np.unique(head.faces[head.scalp_faces])]
        axis = np.array([0.5 * (scalp[:, 0].min() + scalp[:, 0].max()), 0.0, 0.5 * (scalp[:, 2].min() + scalp[:, 2].max())])
        grower = "cuda" if wp.get_device(self.device).is_cuda else "cpu"
        # neither the colour nor the children are the strands' shape: a change finds them already grown
        shape = replace(params, color=HAIR_COLOR, children=0)
        grown = cached_arrays("groom", (shape, roots, normals, self.groom_points, head.faces, axis, grower),
                              lambda: dict(zip(("points", "counts", "widths"),
                                               grow_hairstyle(params, roots, normals, self.collider.push_out, axis))))
        return grown["points"], grown["counts"], grown["widths"]

    def _children(self):
        """The render children ([hair] children per simulated strand), grown from roots of their own
        on the scalp with the groom's style (another seed), or None."""
        cfg, head = self.config, self.head
        if cfg.hair.children == 0:
            return None
        if self.assets is not None:
            raise InputError(cfg.source, "hair.children", "children grow with a groom the scene grows; this "
                             "scene's strands are given (a USD stage or a cache)")
        if cfg.haircut:
            raise InputError(cfg.source, "hair.children", "a haircut changes the strands children follow: "
                             "leave children out of a scene with [[haircut]] events")
        count = cfg.hair.children * self.model.num_strands
        roots, _, _, normals = sample_scalp(head.vertices, head.faces, head.scalp_faces, count, cfg.hair.seed + 1)
        points, _, widths = self._grown(replace(cfg.hair, seed=cfg.hair.seed + 1), roots, normals)
        return HairChildren(self.model, points, widths, self.groom_points, head.faces)

    def _project_roots(self, roots):
        import trimesh

        closest, face, bary = self.collider.closest_points(roots)
        off = np.linalg.norm(closest - roots, axis=1)
        far = ~(off <= ROOT_REACH)  # NaN too: a root beyond the closest-point query's reach
        if far.any():
            raise InputError(self.config.source, "head.roots", f"{far.sum()} of {len(roots)} roots lie more than "
                             f"{100 * ROOT_REACH:g} cm off the head (farthest {np.nanmax(off):.3g} m): roots are "
                             "points on the scalp, in metres")
        normals = trimesh.Trimesh(self.head.vertices, self.head.faces, process=False).vertex_normals
        n = np.einsum("nk,nkj->nj", bary, normals[self.head.faces[face]])
        return closest, n / np.linalg.norm(n, axis=1, keepdims=True)

    def advance(self, duration, animate=True, detail=False):
        """Simulate `duration` seconds; with animate=False the collider holds its pose (preroll).
        Hair and cloth each take their own substeps across the frame, each against its own twin of the
        collider posed the same way; on a CUDA device each solver's frame is one graph launch, on the
        CPU their replayed frames run side by side on the cores (sim.graphs). detail=True also updates
        the cloth's detail surface after the last frame, on the cloth's side (detail_surface())."""
        fps = self.config.timing.fps
        frame_dt = 1.0 / fps
        frames = int(round(duration * fps))
        counts = ([self.config.solver.substeps] if self.model is not None else []) + \
                 ([self.cloth_substeps] if self.cloth_model is not None else [])
        for index in range(frames):
            t0 = self.time
            self._frames += 1
            poses = self._substep_poses(t0, frame_dt, counts, animate)
            tasks = []
            if self.model is not None:
                self.solver.set_clock(t0)
                # a comb adds a launch per substep: its frames are other graphs
                held = getattr(self.solver.comb, "serial", 0)
                mesh = self.config.solver.collision == "mesh"
                tasks.append(self._solver_frame(("hair", held), self.collider, poses[self.config.solver.substeps],
                                                frame_dt, animate, self._step_hair, self._hair_refs, bvh=mesh,
                                                refit_in_step=mesh, listed=None if mesh else self._hair_root_vertices(),
                                                around=(lambda: self.solver.begin_frame(self.state),
                                                        lambda: self.solver.end_frame(self.state)),
                                                whole=self._step_hair_frame if self.solver.frame_in_block and not held
                                                else None))
            if self.cloth_model is not None:
                self.cloth_solver.set_clock(t0)
                body = self.cloth_body if self.cloth_body is not self.cloth_collider else None
                # the cloth queries the body's triangle boxes, swept over the frame or refitted to each
                # substep; the detail's lift queries the mesh of the body after the frame (end_pose, or
                # the collider's last pose)
                sweep = self.cloth_sweep
                tasks.append(self._solver_frame("cloth", self.cloth_collider, poses[self.cloth_substeps],
                                                frame_dt, animate, self._step_cloth, self._cloth_refs, bvh=not sweep,
                                                end_pose=body, sweep=sweep,
                                                refit_last=body is None and self.cloth_detail is not None))
            # only replays run side by side: a capture records every launch on the device
            together = (self.side_by_side and len(tasks) > 1 and not wp.get_device(self.device).is_cuda
                        and all(self.graphs.captured(key) for key, _ in tasks))
            last_detail = detail and index == frames - 1 and self.cloth_detail is not None
            if together and last_detail:
                run_cloth = tasks[-1][1]

                def cloth_then_detail():  # the detail on the cloth's side once its frame is captured too
                    run_cloth()
                    if self.graphs.captured(self._detail_key()):
                        self._update_detail()

                tasks[-1] = (tasks[-1][0], cloth_then_detail)
            if together:
                run_side_by_side([task for _, task in tasks])
            else:
                for _, task in tasks:
                    task()
            if last_detail and self._detail_frame != self._frames:
                self._update_detail()
            if animate:
                self.time = t0 + frame_dt

    def _solver_frame(self, name, collider, substep_poses, frame_dt, animate, step, refs, bvh=True, end_pose=None,
                      listed=None, sweep=False, refit_last=False, refit_in_step=False, around=None, whole=None):
        """One solver's frame against `collider`, substep_poses = (times, poses) at the start and the
        end of each substep: the poses are uploaded now, and the returned (graph key, task) runs the
        frame. bvh=False: the solver makes no mesh queries, so the BVH is not refitted at all, and the
        collider is left marked stale: a host query after the frame refits it first
        (Collider.fresh_mesh), most frames none does. listed (with bvh=False): the only collider
        vertices the solver reads; every pose but the frame's last, which the host may read, moves
        only those. sweep (with bvh=False): the solver queries the triangle boxes only, bounded once
        over all the frame's poses (Collider.sweep); refit_last: the mesh BVH is refitted at the
        frame's last pose all the same (for the detail surface's lift after it), beside the last
        substep. end_pose: another collider the frame poses once, beside the substeps (the body
        beside a cloth's collision proxy). On the CPU, work beside other work runs on another core
        (sim.graphs.run_parallel).
        refit_in_step (with bvh): the step refits the BVH itself, beside work that does not read it
        (HairSolver.step), so the poses leave it stale.
        around: (begin, end) called before the first substep and after the last (the hair's
        HairSolver.begin_frame and end_frame).
        whole: whole(dt, times, listed) steps every substep at once, posing the collider itself and, with
        bvh, leaving its BVH refitted at the last pose (the hair's HairSolver.step_frame), in place of a
        step per substep."""
        times, poses = substep_poses
        substeps = len(times) - 1
        dt = frame_dt / substeps
        self._pose(collider, poses)  # the frame's poses, uploaded into the buffer the graph reads
        if end_pose is not None:
            self._pose(end_pose, poses[-1:])

        def steps():
            if whole is not None:
                whole(dt, times, listed)
                return
            refit = bvh and not refit_in_step
            for k in range(1, substeps + 1):
                last = k == substeps
                collider.apply_pose(k, refit=refit, listed=None if last else listed)
                if last and refit_last and not refit:
                    # a BVH for after the frame, refitted beside the last substep, which does not read it
                    run_parallel([functools.partial(step, dt, float(times[k])), collider.refit_mesh])
                else:
                    step(dt, float(times[k]))

        def frame():
            # start from the frame's first pose: the collider was left at the last frame's end, or
            # at another time by a reset, and surface velocities (cloth friction) come from
            # consecutive poses; nothing queries this pose, so its BVH is not refitted
            if sweep:
                collider.sweep()
            collider.apply_pose(0, refit=False, listed=listed)
            collider.reset_motion()
            if around is not None:
                around[0]()
            if end_pose is None:
                steps()
            else:  # the other collider, which the substeps never read, is posed beside them (another core)
                run_parallel([steps, functools.partial(end_pose.apply_pose, 0)])
            if around is not None:
                around[1]()

        def run():
            self.graphs.run(key, frame, refs)
            collider.bvh_stale = not (bvh or refit_last)

        key = (name, animate, id(refs[0]()[0]))
        return key, run

    def _hair_root_vertices(self):
        """The collider vertices of the hair's root triangles, the only ones its sphere-tree substeps
        read (root hold and binding, the contact bounds' anchor); kept per groom, as a frame's graph
        reads the array."""
        if self._root_vertices is None or self._root_vertices[0] is not self.model:
            faces = self.collider.faces_np[self.model.root_triangle_np] if self.model.bind_particle is not None \
                else np.zeros((0, 3), np.int32)
            self._root_vertices = (self.model, wp.array(np.unique(faces).astype(np.int32), dtype=wp.int32,
                                                        device=self.device))
        return self._root_vertices[1]

    @property
    def _hair_refs(self):
        def put(value):
            self.state, self._scratch = value
        return (lambda: (self.state, self._scratch)), put

    @property
    def _cloth_refs(self):
        def put(value):
            self.cloth_state, self._cloth_scratch = value
        return (lambda: (self.cloth_state, self._cloth_scratch)), put

    def _step_hair(self, dt, t):
        # the solver's strand ranges, side by side on the CPU's cores once the frame is a graph
        run_parallel(self.solver.branches(self.state, self._scratch, self.collider, dt, t, self.guides))
        self.state, self._scratch = self._scratch, self.state

    def _step_hair_frame(self, dt, times, listed):
        self.solver.step_frame(self.state, self._scratch, self.collider, dt, times, self.guides, listed)
        self.state, self._scratch = self._scratch, self.state

    def _step_cloth(self, dt, t):
        self.cloth_solver.step(self.cloth_state, self._cloth_scratch, self.cloth_collider, dt, t - dt)
        self.cloth_state, self._cloth_scratch = self._cloth_scratch, self.cloth_state

    def update_detail(self):
        """Update the detail surface over the garment from the cloth's state and return it
        (positions, normals), or None without one. Each update carries the last one's wrinkle
        heights a frame further: call it once per frame, or use detail_surface()."""
        if self.cloth_detail is None:
            return None
        self._update_detail()
        return self.cloth_detail.positions, self.cloth_detail.normals

    def detail_surface(self):
        """This frame's detail surface (positions, normals), or None: updated only if this frame has
        not updated it yet (advance(detail=True) does so beside the hair)."""
        if self.cloth_detail is None:
            return None
        if self._detail_frame != self._frames:
            self._update_detail()
        return self.cloth_detail.positions, self.cloth_detail.normals

    def _detail_key(self):
        return "detail", id(self.cloth_state), id(self.cloth_detail.height)

    def _update_detail(self):
        detail = self.cloth_detail

        def put(value):
            detail.height, detail.height_tmp = value

        self.graphs.run(self._detail_key(),
                        lambda: detail.update(self.cloth_model, self.cloth_state, self.cloth_body,
                                              1.0 / self.config.timing.fps),
                        ((lambda: (detail.height, detail.height_tmp)), put))
        self._detail_frame = self._frames

    def measure(self):
        """This frame's quality numbers, waiting for them (sim.quality; a run queues them instead):
        hair stretch, root drift and penetration, cloth edge stretch and penetration, how often the
        cloth's nearest-vertex walk agrees with brute force, and the detail surface's penetration and
        query shares."""
        return self._measured()

    def cloth_stats(self):
        """measure()'s cloth numbers only (cloth_stretch_p99, cloth_stretch_max, cloth_inside_2mm,
        walk_agreement)."""
        return self._measured(hair=False, detail=False)

    def _measured(self, **parts):
        arrays, finish = self.quality.queue(**parts)
        return finish({name: a.numpy() for name, a in arrays.items()})


KERNELS_NOTICE_S = 1.0  # a load slower than this is compiling: say why the run has not started


def load_kernels(device, announce=False, deferred=None):
    """Every kernel module for `device`, compiled (or read from Warp's kernel cache) side by side
    before the first launch (warp_kernels.load): a first run on a cold kernel cache waits for the
    longest module, not for all of them in turn. deferred: the deferred modules the run will launch
    too (warp_kernels.load). announce: when that takes longer than KERNELS_NOTICE_S, one line on
    stderr says what the wait is."""
    if not announce:
        warp_kernels.load(device, cpu_cores(), deferred=deferred)
        return
    done = threading.Event()

    def notice():
        if not done.wait(KERNELS_NOTICE_S):
            print(f"cfx: compiling the Warp kernels for {device}, once per machine and Warp version "
                  f"(on a two-core CPU 10-20 s, some of it at the first launch of a module)", file=sys.stderr,
                  flush=True)

    teller = threading.Thread(target=notice, daemon=True)
    teller.start()
    try:
        warp_kernels.load(device, cpu_cores(), deferred=deferred)
    finally:
        done.set()
        teller.join()


@functools.lru_cache(maxsize=8)
def _shared_substep_times(counts):
    """For substep counts (ascending) splitting one frame: where each distinct time first appears in
    the counts' times laid end to end (n + 1 times for n substeps), and for each count the rows of
    those distinct times that are its own. Substep k of n is k/n of the frame, so the times are
    compared as integers, multiples of 1/lcm(counts)."""
    common = math.lcm(*counts)
    keys = [np.arange(0, n + 1) * (common // n) for n in counts]
    distinct, first = np.unique(np.concatenate(keys), return_index=True)
    return first, tuple(np.searchsorted(distinct, k) for k in keys)


class PointCacheMotion:
    """A collider animated by per-frame vertex positions, linearly interpolated between frames.
    Frames can be appended as a host application delivers them (sim.embed)."""

    def __init__(self, frames, fps, keep=None):
        """keep: frames held back (the latest ones; earlier times read the oldest kept), for a host
        that appends frames without end (sim.embed kept every frame: +562 MB over 600 frames of a
        41k-vertex collider); None keeps all."""
        self.frames = [np.asarray(f, np.float64) for f in frames]
        self.fps = float(fps)
        self.keep, self.first = keep, 0  # first: the frame number of frames[0]

    def append(self, points):
        self.frames.append(np.asarray(points, np.float64))
        if self.keep is not None and len(self.frames) > self.keep:
            del self.frames[0]
            self.first += 1

    def points(self, times):
        n = len(self.frames)
        f = np.clip(np.asarray(times) * self.fps - self.first, 0.0, n - 1)
        i = np.minimum(np.floor(f).astype(int), n - 2) if n > 1 else np.zeros(len(f), int)
        w = f - i if n > 1 else np.zeros(len(f))
        j = np.minimum(i + 1, n - 1)
        return np.stack([(1.0 - w[k]) * self.frames[i[k]] + w[k] * self.frames[j[k]] for k in range(len(f))])


def _load_body(config):
    """The body collider and its motion: the built-in body with a preset, or a user's point cache."""
    b = config.body
    if b.mesh == "builtin":
        from .body import BodyAnimation, procedural_body

        body = procedural_body()
        animation = BodyAnimation.preset(b.animation)
        if b.animation == "walk" and b.in_place:
            from dataclasses import replace

            animation = replace(animation, in_place=True)
        return body, animation
    path = _resolve(config, b.mesh)
    if path.lower().endswith((".usd", ".usda", ".usdc")):
        vertices, faces, frames, fps = _read_usd_body(config, path)
    else:
        import trimesh

        try:
            mesh = trimesh.load(path, force="mesh", process=False)
        except Exception as err:  # trimesh raises many types for unreadable files
            raise InputError(config.source, "body.mesh", f"cannot read {b.mesh}: {err}") from None
        vertices, faces, fps = np.asarray(mesh.vertices), np.asarray(mesh.faces), config.timing.fps
        frames = vertices[None]
        if b.points:
            try:
                frames = np.load(_resolve(config, b.points))
            except (OSError, ValueError) as err:
                raise InputError(config.source, "body.points", f"cannot read {b.points}: {err}") from None
            if frames.ndim != 3 or frames.shape[1:] != vertices.shape or not np.all(np.isfinite(frames)):
                raise InputError(config.source, "body.points",
                                 f"expected finite (frames, {len(vertices)}, 3) positions, got {frames.shape}")
    if len(faces) == 0 or not np.all(np.isfinite(vertices)):
        raise InputError(config.source, "body.mesh", f"{b.mesh} has no faces or non-finite points")
    key = "body.points" if b.points else "body.mesh"
    if len(frames) == 0:
        raise InputError(config.source, key, "holds no frames")
    check_collider_frames(config.source, key, b.points or b.mesh, frames, faces)
    h = config.head
    if config.hair.enabled and not (h.scalp_faces or h.roots):
        raise InputError(config.source, "head.scalp_faces", "hair on a body from a file needs head.scalp_faces or "
                         "head.roots (or [hair] enabled = false)")
    scalp = _load_face_mask(config, len(faces)) if h.scalp_faces else None
    body = mesh_head(b.mesh, frames[0], faces, scalp)
    return body, PointCacheMotion(frames, fps)


def _read_usd_body(config, path):
    from pxr import Usd, UsdGeom

    from io_usd.cache import fan_triangles, open_stage

    stage = open_stage(path, config.source, "body.mesh")
    prim = stage.GetPrimAtPath(config.body.prim) if config.body.prim else None
    if prim is None or not prim.IsValid() or not prim.IsA(UsdGeom.Mesh):
        raise InputError(config.source, "body.prim", f"no UsdGeom.Mesh at '{config.body.prim}' in {config.body.mesh}")
    mesh = UsdGeom.Mesh(prim)
    counts, indices = mesh.GetFaceVertexCountsAttr().Get(), mesh.GetFaceVertexIndicesAttr().Get()
    times = mesh.GetPointsAttr().GetTimeSamples() or [Usd.TimeCode.Default()]
    frames = [mesh.GetPointsAttr().Get(t) for t in times]
    if not counts or not indices or any(f is None or len(f) != len(frames[0]) for f in frames) or not len(frames[0]):
        raise InputError(config.source, "body.prim", f"{config.body.prim} in {config.body.mesh} needs faces and "
                                                     "points, the same number of points at every time sample")
    frames = np.stack([np.asarray(f, np.float64) for f in frames])
    return frames[0], fan_triangles(counts, indices), frames, stage.GetTimeCodesPerSecond()


# m: a collider larger than this is no character in metres (a mesh in centimetres is 100 times too large)
COLLIDER_SPAN = 10.0
# m: roots farther off the head than this are not on its scalp
ROOT_REACH = 0.05


def check_collider_frames(source, key, name, frames, faces):
    """InputError unless every frame (F, V, 3) of a head or body mesh indexes its points, has a face
    with area, and spans at most COLLIDER_SPAN (all points at one spot, or a scale of 0, exploded the
    hair; a mesh in centimetres flung it off)."""
    faces = np.asarray(faces, np.int64)
    if faces.min() < 0 or faces.max() >= frames.shape[1]:
        raise InputError(source, key, f"{name}: face indices must lie in [0, {frames.shape[1]})")
    span = float(np.max(frames.max(axis=1) - frames.min(axis=1)))
    if span > COLLIDER_SPAN:
        raise InputError(source, key, f"{name} spans {span:.3g} m; meshes are read in metres (at most "
                                             f"{COLLIDER_SPAN:g} m): scale one in centimetres by 0.01")
    a, b, c = (frames[:, faces[:, k]] for k in range(3))
    area = np.linalg.norm(np.cross(b - a, c - a), axis=2).max(axis=1)
    if not np.all(area > 0.0):
        first = int(np.argmin(area > 0.0))
        raise InputError(source, key, f"{name}: no face has any area in frame index {first} (every point in "
                                             "one spot?)")


def _load_garment(config, body):
    from . import garment as garments

    c = config.cloth
    if c.garment in _garment_names():
        if getattr(body, "landmarks", None) is None:  # fitting needs the built-in body's shoulders, waist, hips
            raise InputError(config.source, "cloth.garment", f"the fitted {c.garment} fits the built-in body only: "
                             f"a body from {config.body.mesh} needs a garment mesh (an OBJ or USD file)")
        return garments.GARMENTS[c.garment](body, particles=c.particles, ease=c.ease)
    path = _resolve(config, c.garment)
    pinned = None
    if c.pinned:
        try:
            pinned = np.load(_resolve(config, c.pinned)).astype(np.int64).ravel()
        except (OSError, ValueError) as err:
            raise InputError(config.source, "cloth.pinned", f"cannot read {c.pinned}: {err}") from None
    try:
        if path.lower().endswith((".usd", ".usda", ".usdc")):
            return garments.garment_from_usd(path, c.prim, pinned=pinned)
        return garments.garment_from_file(path, pinned=pinned)
    except ValueError as err:
        raise InputError(config.source, "cloth.garment", str(err)) from None


@dataclass
class RunResult:
    path: str
    frames: int
    strands: int
    particles: int
    seconds: float
    stats: dict
    cloth_particles: int = 0
    cloth_substeps_fixed: bool = False
    face_vertices: int = 0
    children: int = 0  # render children written beside the strands (hair_children)
    idle_events: tuple = ()  # "haircut[k] (tool at frame f)" of the timeline's events that changed no strands


def _check_not_an_input(config, out_path):
    """InputError if out_path (or a link to it) is a file the scene reads: the cache would replace it."""
    if config.source == "<demo>" or config.given_geometry:
        return
    base = os.path.dirname(os.path.abspath(config.source))
    inputs = {"scene": config.source}
    for section, keys in (("head", ("mesh", "scalp_faces", "roots")), ("body", ("mesh", "points")),
                          ("cloth", ("pinned", "garment")), ("hair", ("guides",)),
                          ("face", ("mesh", "features", "mouth", "audio"))):
        for key in keys:
            value = getattr(getattr(config, SECTIONS[section][0]), key, None)
            if isinstance(value, str) and value and value != "builtin":
                inputs[f"{section}.{key}"] = os.path.join(base, value)
    from io_usd.output_file import is_input

    for key, path in inputs.items():
        if is_input(out_path, path):
            raise InputError(out_path, None, f"is the scene's {key} input: the cache would replace it; "
                                             "choose another output")


def run_scene(config, out_path, progress=True, on_frame=None, stage=None):
    """Simulate `config` and stream it to a USD cache at out_path. Returns a RunResult.

    stage: an io_usd.scene_input.UsdScene (config is then stage.config): its geometry is simulated
    and the cache is written as a layer over that stage.
    The cache is written under a temporary name and moved onto out_path only when every frame is
    done; an error (bad input, NaN) leaves out_path untouched.
    """
    from io_usd.cache import CacheWriter, check_cache_path

    check_cache_path(out_path)  # before minutes of simulation, not after
    _check_not_an_input(config, out_path)
    started = time.perf_counter()
    quiet_warp()
    scene = Scene(config, stage.assets if stage is not None else None, announce=progress)
    t = config.timing
    if t.preroll > 0.0:
        scene.advance(t.preroll, animate=False)
    end_frame = t.start_frame + t.frames - 1
    worst, agreement = {}, []
    larger_is_worse = ("max_stretch", "root_distance_max", "inside_1mm", "cloth_stretch_p99", "cloth_stretch_max",
                       "cloth_inside_2mm", "detail_inside_2mm", "detail_queries", "detail_bvh")
    bar = _progress(t.frames, progress)
    hair_prim, cloth_prim = "/World/hair", "/World/cloth"
    if stage is not None:
        hair_prim = ", ".join(p.path for p in stage.hair)
        cloth_prim = ", ".join(p.path for p in stage.cloth) or cloth_prim
    if stage is not None:  # entered at once: a stop in between left the partial file behind
        opened = stage.cache_writer(out_path, settings=config.settings(), engine_version=__version__)
    else:
        opened = CacheWriter(out_path, t.fps, t.start_frame, end_frame, settings=config.settings(),
                             engine_version=__version__)
    with opened as writer:
        if stage is None:
            _add_prims(writer, scene)
        elif scene.cloth_detail is not None:
            stage.add_detail(writer, scene.cloth_detail.triangles_np)
        # one frame behind: frame i's results are copied back behind its work while the host writes
        # frame i - 1, so USD output overlaps the next frame's simulation on a GPU
        readback, pending = AsyncReadback(scene.device), None

        first_counts = scene.model.counts if scene.model is not None else None
        idle = []

        def write(frame, wait, weights, hair, finish_stats):
            data = wait()
            curves = None
            if hair is not None:  # the hair's model and solver when the frame was queued (haircuts replace them)
                model, solver = hair
                solver.report_unhealthy(data["hair_bad"], data["hair_first"], frame, hair_prim)
                curves = {"hair": (model.counts, model.widths_np, model.strand_ids)}
                if stage is not None and not np.array_equal(model.counts, first_counts):
                    raise InputError(config.source, "haircut", "a cache layered over a USD stage keeps the "
                                     "stage's curves: cut strands in a scene of their own")
            if scene.cloth_model is not None:
                scene.cloth_solver.report_unhealthy(data["cloth_bad"], data["cloth_first"], frame, cloth_prim)
            if finish_stats is not None:  # of a healthy frame only
                for key, value in finish_stats(data).items():
                    if key == "walk_agreement":  # reported over the whole run and for the worst frame
                        agreement.append(value)
                        key = "walk_agreement_worst_frame"
                    if key not in worst:
                        worst[key] = value
                    else:
                        worst[key] = max(worst[key], value) if key in larger_is_worse else min(worst[key], value)
            samples = {name: data[name] for name in (scene.collider_name, "hair", "hair_children", "cloth",
                                                     "cloth_detail") if name in data}
            normals = {"cloth_detail": data["cloth_detail_normals"]} if "cloth_detail_normals" in data else {}
            if stage is not None:  # the layer over a DCC's scene: its prims, in their local spaces
                stage.write_frame(writer, frame, samples, normals)
                bar.update(1)
                return
            if weights is not None:
                _check_finite(data["face"], frame, "/World/face")
                transform = scene.face_rig.head_transform_from(data["face_rest"])
                samples["face"] = data["face"]
                writer.write_blend_shape_frame("face_rig", frame, weights, transform)
                if t.stats:  # how far the expression and speech move the face, in its own frame
                    local = (data["face"] - transform[:3, 3]) @ transform[:3, :3]
                    move = float(np.linalg.norm(local - scene.face_rig.mesh.vertices, axis=1).max())
                    worst["face_max_offset"] = max(worst.get("face_max_offset", 0.0), move)
            writer.write_frame(frame, samples, normals, curves=curves)
            bar.update(1)

        for i in range(t.frames):
            raise_if_stopped()
            frame = t.start_frame + i
            if i > 0:
                if config.haircut:  # a comb in the hair moves to where the timeline has it at this frame
                    comb_before_frame(scene, config.haircut, frame)
                scene.advance(1.0 / t.fps, detail=True)
            if config.haircut:
                for edit in run_events(scene, config.haircut, frame):
                    event = config.haircut[edit.event]
                    if event.frame == frame and edit.tool != "initialise" and not len(edit.strands):
                        idle.append(f"haircut[{edit.event}] ({event.tool} at frame {frame})")
            arrays, weights = scene.queue_outputs(frame)
            hair = (scene.model, scene.solver) if scene.model is not None else None
            finish_stats = None
            if t.stats:  # queued behind the frame and read back with it, like the frame itself
                queued, finish_stats = scene.quality.queue()
                arrays.update(queued)
            ready = (frame, readback.begin(arrays), weights, hair, finish_stats)
            if on_frame:
                on_frame(frame, scene)
            if pending is not None:
                write(*pending)
            pending = ready
        if pending is not None:
            write(*pending)
        bar.close()
        if agreement:
            worst["walk_agreement"] = float(np.mean(agreement))
        if scene.cloth_model is not None:
            worst["cloth_substeps"] = scene.cloth_substeps
            worst["cloth_stable_dt"] = scene.cloth_model.stable_dt
        writer.set_metadata("cfx:stats", worst)
        raise_if_stopped()  # a stop swallowed on the way is still a stop: no cache is committed
    strands = scene.model.num_strands if scene.model is not None else 0
    particles = scene.model.num_particles if scene.model is not None else 0
    cloth = scene.cloth_model.num_particles if scene.cloth_model is not None else 0
    face = scene.face_rig.mesh.num_vertices if scene.face_rig is not None else 0
    children = scene.children.count if scene.children is not None else 0
    return RunResult(os.fspath(out_path), t.frames, strands, particles, time.perf_counter() - started, worst, cloth,
                     config.cloth_solver.substeps > 0, face, children, tuple(idle))


# the scalp under the hair is painted toward the shade of the hair's roots, as groomers tint a scalp: bare
# skin showed through a parting and at the crown as a white line, and halfway to the hair's own colour
# still read as light tan once lit
SCALP_TINT = 0.9  # share of the way from the skin to the root shade
ROOT_SHADE = 0.5  # the root shade: the hair's colour darkened this much, as the roots sit in its shadow


def head_colors(head, hair_color=None):
    """The collider's displayColor: the skin, or with hair (hair_color) per-vertex colours whose scalp,
    head.scalp_faces, is tinted SCALP_TINT of the way to the roots' shade, easing off over the ring of
    vertices at the scalp's edge (each vertex by the share of its faces on the scalp)."""
    if hair_color is None:
        return SKIN_COLOR
    faces = np.asarray(head.faces).reshape(-1, 3)
    on_scalp = np.asarray(head.scalp_faces, bool)
    total = np.bincount(faces.ravel(), minlength=len(head.vertices))
    scalp = np.bincount(faces[on_scalp].ravel(), minlength=len(head.vertices))
    share = SCALP_TINT * scalp / np.maximum(total, 1)
    skin, roots = np.asarray(SKIN_COLOR, np.float64), ROOT_SHADE * np.asarray(hair_color, np.float64)
    return skin + share[:, None] * (roots - skin)


def _add_prims(writer, scene):
    """Our own cache layout: one prim per object under /World."""
    hair_color = scene.config.hair.color if scene.model is not None else None
    writer.add_mesh(scene.collider_name, "collider", scene.head.vertices, scene.head.faces,
                    color=head_colors(scene.head, hair_color))
    if scene.model is not None:
        writer.add_curves("hair", "hair", scene.model.counts, scene.model.widths_np, color=scene.config.hair.color,
                          ids=scene.model.strand_ids)
    if scene.children is not None:
        writer.add_curves("hair_children", "hair", scene.children.counts, scene.children.widths_np,
                          color=scene.config.hair.color, interpolated_from="hair")
    if scene.cloth_model is not None:
        cm = scene.cloth_model
        writer.add_mesh("cloth", "cloth", cm.rest_positions_np, None, color=scene.config.cloth.color,
                        face_counts=cm.face_counts_np, face_indices=cm.face_indices_np)
    if scene.cloth_detail is not None:
        writer.add_mesh("cloth_detail", "cloth_detail", None, scene.cloth_detail.triangles_np,
                        color=scene.config.cloth.color, normals=True)
    if scene.face_rig is not None:
        rig = scene.face_rig
        writer.add_mesh("face", "face", None, rig.mesh.faces, color=rig.mesh.colors)
        writer.add_blend_shape_rig("face_rig", rig.mesh.vertices, rig.mesh.faces, rig.shape_names, rig.offsets,
                                   color=rig.mesh.colors)


def _check_finite(points, frame, prim):
    from .errors import SimulationError

    if not np.all(np.isfinite(points)):
        raise SimulationError(frame, prim, "non-finite positions")


MOUTH_LIMIT_MM = 100.0  # a mouth parameter this large would move the lips off the head


def _mouth_track(config):
    """Mouth parameters (T, 13) [mm] per frame from the face's audio, or None without audio."""
    f = config.face
    if f.mouth:
        path = _resolve(config, f.mouth)
        try:
            track = _read_array(path, delimiter=",")
        except (OSError, ValueError) as err:
            raise InputError(config.source, "face.mouth", f"cannot read {f.mouth}: {err}") from None
        if track.ndim != 2 or track.shape[1] != 13 or not np.all(np.isfinite(track)):
            raise InputError(config.source, "face.mouth", f"expected (frames, 13) finite mouth parameters, got {track.shape}")
        if np.abs(track).max(initial=0.0) > MOUTH_LIMIT_MM:  # 1e30 mm blew the face up in a cache marked complete
            raise InputError(config.source, "face.mouth", f"mouth parameters are millimetres: at most "
                                                          f"{MOUTH_LIMIT_MM:g} in size, got {np.abs(track).max():.3g}")
        return track.astype(np.float64)
    if not f.audio:
        return None
    from . import lipsync

    samples = lipsync.load_audio(lipsync.DEMO_LINE_PATH if f.audio == "builtin" else _resolve(config, f.audio))
    return lipsync.mouth_track(samples, config.timing.fps, _lipsync_weights(config))


def _lipsync_weights(config):
    """The face.voice setting: the general set, a training voice's set, or the set that best
    reproduces a speaker's five vowels (a folder of a.wav ... o.wav: speaker adaptation)."""
    from . import lipsync

    voice = config.face.voice
    bank = lipsync.load_bank()
    if voice in bank.names:
        return bank.sets[bank.names.index(voice)]
    folder = _resolve(config, voice)
    if not os.path.isdir(folder):
        raise InputError(config.source, "face.voice",
                         f"expected one of {', '.join(bank.names)} or a folder of a.wav i.wav u.wav e.wav o.wav")
    vowels = {}
    for v in lipsync.SPOKEN_VOWELS:
        path = os.path.join(folder, f"{v}.wav")
        if not os.path.isfile(path):
            raise InputError(config.source, "face.voice", f"{voice} has no {v}.wav (speaker adaptation needs all five vowels)")
        vowels[v] = lipsync.load_audio(path)
    return lipsync.choose_weights(bank, vowels).weights


# Warp's native library prints this straight to file descriptor 2 when a machine has no CUDA
# driver, on every start. A CPU run needs no driver, and a scene that asks for CUDA gets its own
# error (Scene: "scene.device: device 'cuda' is not available"), so the line is only noise.
_NO_DRIVER_LINE = "Could not find or load the NVIDIA CUDA driver"


def quiet_warp():
    """Keep Warp's start-up banner, per-module compile lines and its no-CUDA-driver warning out of
    the CLI's output. Initialises Warp; anything else it prints while starting is passed on."""
    if hasattr(wp, "LOG_WARNING") and hasattr(wp.config, "log_level"):
        wp.config.log_level = wp.LOG_WARNING
    else:  # warp-lang before the log levels
        wp.config.quiet = True
    _init_warp_filtered()


def _init_warp_filtered():
    import tempfile

    sys.stderr.flush()
    try:
        saved = os.dup(2)
    except OSError:  # no descriptor 2 to redirect (a host that closed it): start Warp as it is
        wp.init()
        return
    with tempfile.TemporaryFile() as caught:
        os.dup2(caught.fileno(), 2)
        try:
            wp.init()
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
        caught.seek(0)
        printed = caught.read().decode("utf-8", "replace")
    kept = "".join(line for line in printed.splitlines(keepends=True) if _NO_DRIVER_LINE not in line)
    if kept:
        sys.stderr.write(kept)
        sys.stderr.flush()


def _progress(total, enabled):
    from tqdm import tqdm

    return tqdm(total=total, unit="frame", desc="simulating", file=sys.stderr, disable=not enabled,
                dynamic_ncols=True)
