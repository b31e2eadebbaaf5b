"""Scenes: a head, its animation, a hairstyle and solver settings, run headless to a USD cache.

A scene file is TOML with the tables [scene], [head], [hair] and [solver]; see
examples/scenes/*.toml. The same is reachable from Python: build a SceneConfig (or load_scene), then
run_scene(config, "out.usdc").
"""

import os
import sys
import time
from dataclasses import asdict, dataclass, field

import numpy as np
import warp as wp

from . import __version__
from .collider import Collider
from .config import from_table, load_toml
from .errors import InputError
from .hair_solver import HairParams, HairSolver
from .hairstyle import HairstyleParams, grow_hairstyle, sample_scalp, scalp_area
from .head import HeadAnimation, mesh_head, procedural_head
from .strands import StrandBuilder

HAIR_COLOR = (0.23, 0.14, 0.08)
SKIN_COLOR = (0.85, 0.68, 0.58)


@dataclass(frozen=True)
class TimingConfig:
    fps: float = 24.0  # frames per second written to the cache
    frames: int = 72  # frames written
    start_frame: int = 1  # time code of the first frame
    preroll: float = 1.0  # s simulated before the first frame so the hair has settled
    device: str = "cpu"  # "cpu" or "cuda" (or "cuda:N")
    stats: bool = True  # measure stretch, root drift and penetration every frame

    def __post_init__(self):
        if self.fps <= 0.0:
            raise ValueError("fps must be positive")
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
    turn_degrees: float = 40.0
    turn_period: float = 3.0  # s
    nod_degrees: float = 15.0
    nod_period: float = 1.5  # s
    sphere_leaves: int = 1024  # most leaf spheres in the sphere tree (built for collision = "sphere_tree")

    def __post_init__(self):
        if self.animation not in ("turn_nod", "turn", "nod", "none"):
            raise ValueError("animation must be one of turn_nod, turn, nod, none")
        if self.turn_period <= 0.0 or self.nod_period <= 0.0:
            raise ValueError("turn_period and nod_period must be positive")
        if self.sphere_leaves < 1:
            raise ValueError("sphere_leaves must be at least 1")


@dataclass(frozen=True)
class SceneConfig:
    source: str = "<demo>"  # the scene file this came from, for error messages
    timing: TimingConfig = field(default_factory=TimingConfig)
    head: HeadConfig = field(default_factory=HeadConfig)
    hair: HairstyleParams = field(default_factory=HairstyleParams)
    solver: HairParams = field(default_factory=HairParams)

    def settings(self):
        """Everything that determines the result, for the cache's customLayerData."""
        return {"scene": self.source, "timing": asdict(self.timing), "head": asdict(self.head),
                "hair": asdict(self.hair), "solver": asdict(self.solver)}


SECTIONS = {"scene": ("timing", TimingConfig), "head": ("head", HeadConfig),
            "hair": ("hair", HairstyleParams), "solver": ("solver", HairParams)}


def load_scene(path, overrides=None):
    """Read and validate a TOML scene file. overrides: {"scene": {"frames": 10}, ...}."""
    data = load_toml(path)
    for section in data:
        if section not in SECTIONS:
            raise InputError(path, f"[{section}]", f"unknown table (known: {', '.join(SECTIONS)})")
    return _build_config(str(path), data, overrides)


def demo_scene(overrides=None):
    """The built-in scene: wavy shoulder-length hair on the procedural head turning and nodding."""
    return _build_config("<demo>", {}, overrides)


def _build_config(source, data, overrides):
    overrides = overrides or {}
    parts = {}
    for section, (attr, cls) in SECTIONS.items():
        parts[attr] = from_table(cls, data.get(section, {}), source, section, overrides.get(section))
    config = SceneConfig(source=source, **parts)
    base = os.path.dirname(os.path.abspath(source)) if source != "<demo>" else os.getcwd()
    for key in ("mesh", "scalp_faces", "roots"):
        value = getattr(config.head, key)
        if value and value != "builtin" and not os.path.exists(os.path.join(base, value)):
            raise InputError(source, f"head.{key}", f"file not found: {value}")
    return config


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
        if not mesh.is_watertight:
            raise InputError(config.source, "head.mesh",
                             f"{h.mesh} is not closed (watertight); collisions need an inside and an outside")
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
    idx = data.astype(np.int64).ravel()
    if idx.size == 0 or idx.min() < 0 or idx.max() >= face_count:
        raise InputError(config.source, "head.scalp_faces", f"face indices must lie in [0, {face_count})")
    mask = np.zeros(face_count, bool)
    mask[idx] = True
    return mask


def _load_roots(config):
    path = _resolve(config, config.head.roots)
    try:
        roots = np.load(path) if path.endswith(".npy") else np.loadtxt(path, ndmin=2)
    except (OSError, ValueError) as err:
        raise InputError(config.source, "head.roots", f"cannot read {config.head.roots}: {err}") from None
    if roots.ndim != 2 or roots.shape[1] != 3 or len(roots) == 0 or not np.all(np.isfinite(roots)):
        raise InputError(config.source, "head.roots", "expected a non-empty (N, 3) array of finite points")
    return roots


class HairScene:
    """An assembled scene: collider, hair model, solver, animation. Build with HairScene(config)."""

    def __init__(self, config):
        self.config = config
        device = config.timing.device
        if device.startswith("cuda") and not wp.is_cuda_available():
            raise InputError(config.source, "scene.device", f"device '{device}' is not available (no CUDA driver)")
        try:
            wp.get_device(device)
        except (ValueError, RuntimeError):
            raise InputError(config.source, "scene.device", f"device '{device}' is not available") from None
        self.device = device
        self.head = _load_head(config)
        h = config.head
        turns, nods = h.animation in ("turn", "turn_nod"), h.animation in ("nod", "turn_nod")
        self.animation = HeadAnimation(turn_degrees=h.turn_degrees if turns else 0.0, turn_period=h.turn_period,
                                       nod_degrees=h.nod_degrees if nods else 0.0, nod_period=h.nod_period,
                                       pivot=self.head.pivot)
        leaves = h.sphere_leaves if config.solver.collision == "sphere_tree" else 0
        self.collider = Collider("head", self.head.vertices, self.head.faces, self.head.skin_indices,
                                 self.head.skin_weights, self.head.num_bones, device, leaves)
        self.collider.set_poses(self.animation.bone_matrices([0.0]))
        self.collider.apply_pose(0)
        self.model = self._groom()
        self.solver = HairSolver(self.model, config.solver)
        self.state = self.model.state()
        self._scratch = self.model.state()
        self.time = 0.0

    def _groom(self):
        cfg, head = self.config, self.head
        rest_points = self.collider.posed_points()
        if cfg.head.roots:
            roots = _load_roots(cfg)
            roots, normals = self._project_roots(roots)
        else:
            count = cfg.hair.count
            if cfg.hair.density > 0.0:
                count = max(1, int(round(cfg.hair.density * scalp_area(head.vertices, head.faces, head.scalp_faces) * 1e4)))
            try:
                roots, _, _, normals = sample_scalp(head.vertices, head.faces, head.scalp_faces, count, cfg.hair.seed)
            except ValueError as err:
                raise InputError(cfg.source, "head.scalp_faces", str(err)) from None
        axis = np.array([0.5 * (head.vertices[:, 0].min() + head.vertices[:, 0].max()), 0.0,
                         0.5 * (head.vertices[:, 2].min() + head.vertices[:, 2].max())])
        points, counts, widths = grow_hairstyle(cfg.hair, roots, normals, self.collider.push_out, axis)
        model = StrandBuilder().add_strands(points, counts, widths).finalize(self.device, pinned_per_strand=2)
        return model.bind_to_mesh(rest_points, head.faces)

    def _project_roots(self, roots):
        import trimesh

        closest, face, bary = self.collider.closest_points(roots)
        normals = trimesh.Trimesh(self.head.vertices, self.head.faces, process=False).vertex_normals
        n = np.einsum("nk,nkj->nj", bary, normals[self.head.faces[face]])
        return closest, n / np.linalg.norm(n, axis=1, keepdims=True)

    def substep_dt(self):
        return 1.0 / (self.config.timing.fps * self.config.solver.substeps)

    def advance(self, duration, animate=True):
        """Simulate `duration` seconds in substeps; with animate=False the head holds its pose."""
        fps, substeps = self.config.timing.fps, self.config.solver.substeps
        frames = int(round(duration * fps))
        dt = self.substep_dt()
        for _ in range(frames):
            t0 = self.time
            times = t0 + dt * np.arange(1, substeps + 1) if animate else np.full(substeps, t0)
            self.collider.set_poses(self.animation.bone_matrices(times))
            for k in range(substeps):
                self.collider.apply_pose(k)
                self.solver.step(self.state, self._scratch, self.collider, dt, float(times[k]))
                self.state, self._scratch = self._scratch, self.state
            if animate:
                self.time = t0 + substeps * dt

    def measure(self):
        """Per-frame quality numbers: worst segment stretch, root drift, points inside the head."""
        m = self.model
        x = self.state.x.numpy().astype(np.float64)
        seg = np.linalg.norm(x[1:] - x[:-1], axis=1)
        child = np.arange(1, m.num_particles)
        keep = m.rest_length_np[child] > 0.0
        stretch = np.abs(seg[keep] / m.rest_length_np[child][keep] - 1.0)
        sdf = self.collider.signed_distance(x, max_dist=0.03)
        roots = m.strand_start_np[:-1]
        return {
            "max_stretch": float(stretch.max()) if stretch.size else 0.0,
            "root_distance_max": float(np.abs(sdf[roots]).max()),
            "root_within_5mm": float(np.mean(np.abs(sdf[roots]) <= 0.005)),
            "inside_1mm": float(np.mean(sdf < -0.001)),
        }


@dataclass
class RunResult:
    path: str
    frames: int
    strands: int
    particles: int
    seconds: float
    stats: dict


def run_scene(config, out_path, progress=True, on_frame=None):
    """Simulate `config` and stream it to a USD cache at out_path. Returns a RunResult.

    The cache is written under a temporary name and moved onto out_path only when every frame is
    done; an error (bad input, NaN) leaves out_path untouched.
    """
    from io_usd.cache import CacheWriter, check_cache_path

    check_cache_path(out_path)  # before minutes of simulation, not after
    started = time.perf_counter()
    quiet_warp()
    scene = HairScene(config)
    t = config.timing
    if t.preroll > 0.0:
        scene.advance(t.preroll, animate=False)
    end_frame = t.start_frame + t.frames - 1
    worst = {"max_stretch": 0.0, "root_distance_max": 0.0, "root_within_5mm": 1.0, "inside_1mm": 0.0}
    bar = _progress(t.frames, progress)
    with CacheWriter(out_path, t.fps, t.start_frame, end_frame, settings=config.settings(),
                     engine_version=__version__) as writer:
        writer.add_mesh("head", "collider", scene.head.vertices, scene.head.faces, color=SKIN_COLOR)
        writer.add_curves("hair", "hair", scene.model.counts, scene.model.widths_np, color=HAIR_COLOR)
        for i in range(t.frames):
            frame = t.start_frame + i
            if i > 0:
                scene.advance(1.0 / t.fps)
            scene.solver.check_health(scene.state, frame, "/World/hair")
            writer.write_frame(frame, {"head": scene.collider.posed_points(), "hair": scene.state.x.numpy()})
            if t.stats:
                s = scene.measure()
                worst = {"max_stretch": max(worst["max_stretch"], s["max_stretch"]),
                         "root_distance_max": max(worst["root_distance_max"], s["root_distance_max"]),
                         "root_within_5mm": min(worst["root_within_5mm"], s["root_within_5mm"]),
                         "inside_1mm": max(worst["inside_1mm"], s["inside_1mm"])}
            if on_frame:
                on_frame(frame, scene)
            bar.update(1)
        bar.close()
        stats = worst if t.stats else {}
        writer.set_metadata("cfx:stats", stats)
    return RunResult(os.fspath(out_path), t.frames, scene.model.num_strands, scene.model.num_particles,
                     time.perf_counter() - started, stats)


def quiet_warp():
    """Keep Warp's start-up banner and per-module compile lines out of the CLI's output."""
    if hasattr(wp, "LOG_WARNING") and hasattr(wp.config, "log_level"):
        wp.config.log_level = wp.LOG_WARNING
    else:  # warp-lang before the log levels
        wp.config.quiet = True


def _progress(total, enabled):
    from tqdm import tqdm

    return tqdm(total=total, unit="frame", desc="simulating", file=sys.stderr, disable=not enabled,
                dynamic_ncols=True)
