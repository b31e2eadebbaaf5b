"""The engine for a host application (Blender, Houdini, Maya): NumPy arrays in, NumPy arrays out.

A host hands over its collider mesh, hair curves and garment in its own coordinates (up axis and
units), then steps frame by frame with the collider's positions at each new frame:

    simulation = Simulation(head_points, head_triangles, fps=24, hair_points=p, hair_counts=c, up_axis="Z")
    for frame in range(2, 49):
        simulation.step(head_points_at(frame))
        draw(simulation.hair_points())

It is the same Scene that `cfx run` drives (same kernels, same substeps, same collider interpolation
between frames), so a host and the command line agree to float rounding on the same input. The
kernels underneath are documented in docs/kernels.md for hosts that launch them directly.
"""

import threading

import numpy as np

from .errors import InputError

# the tables a host may pass as settings: everything else in a scene file names geometry or files
HOST_TABLES = ("scene", "solver", "cloth")


class HostFrame:
    """A host's coordinates against the engine's (metres, Y up): a scale and, for Z up, a quarter
    turn about X. Both are exact in float arithmetic for unit scales, so round trips are lossless."""

    def __init__(self, up_axis="Y", meters_per_unit=1.0):
        up = str(up_axis).upper()
        if up not in ("Y", "Z"):
            raise ValueError(f"up_axis must be 'Y' or 'Z', got {up_axis!r}")
        if not meters_per_unit > 0.0:
            raise ValueError(f"meters_per_unit must be positive, got {meters_per_unit!r}")
        self.up_axis, self.meters_per_unit = up, float(meters_per_unit)
        # host (x, y, z) with Z up -> engine (x, z, -y): gravity along -Y lands along the host's -Z
        self.rotation = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]) if up == "Z" else np.eye(3)

    def to_engine(self, points):
        """Host positions (..., 3) -> engine metres, Y up (float64)."""
        p = np.asarray(points, np.float64) @ self.rotation.T
        return p * self.meters_per_unit if self.meters_per_unit != 1.0 else p

    def from_engine(self, points):
        """Engine positions (..., 3) -> host coordinates (float32)."""
        p = np.asarray(points, np.float64) @ self.rotation
        if self.meters_per_unit != 1.0:
            p = p / self.meters_per_unit
        return p.astype(np.float32)

    def direction_to_engine(self, vector):
        """A host vector setting (gravity, wind) in engine axes; units are already SI."""
        return tuple(float(v) for v in self.rotation @ np.asarray(vector, np.float64))

    def direction_from_engine(self, vector):
        """An engine vector setting back in the host's axes (direction_to_engine's inverse)."""
        return tuple(float(v) for v in np.asarray(vector, np.float64) @ self.rotation)

    def settings_from_engine(self, settings):
        """A scene's settings (SceneConfig.settings()) with the vector settings (gravity, wind) in the
        host's axes, as the host gave them, for a cache over the host's stage."""
        out = dict(settings)
        for table in ("solver", "cloth_solver"):
            if table in out:
                out[table] = {k: list(self.direction_from_engine(v)) if k in ("gravity", "wind") else v
                              for k, v in out[table].items()}
        return out


# Simulations stepped from several threads take turns: two scenes advancing at once share Warp's launch
# state and recorded CPU graphs, and crashed the process (std::bad_alloc, a segfault)
_TURNS = threading.RLock()
# collider frames a Simulation keeps: a step interpolates between the last two
MOTION_FRAMES_KEPT = 4


class Simulation:
    """Hair and a garment against an animated collider, driven one frame at a time from NumPy.

    collider_vertices (V, 3) and collider_faces (F, 3): the collider at the first frame, in host
    coordinates; hair_points (P, 3) with hair_counts (S,) vertices per strand, root first (roots are
    bound to the nearest collider triangle and follow it); garment_vertices (G, 3) with polygons as
    garment_face_counts and flat garment_face_indices, and garment_pinned vertex indices bound to the
    collider. settings: tables as in a scene file ({"scene": {"preroll": 1.0}, "solver": {...},
    "cloth": {"solver": {...}, "detail": {...}}}); gravity and wind there are in host axes.
    The constructor simulates the preroll with the collider held still; hair_points() and
    cloth_points() are then the first frame, and each step() adds one frame.
    """

    def __init__(self, collider_vertices, collider_faces, *, fps=24.0, hair_points=None, hair_counts=None,
                 hair_widths=None, garment_vertices=None, garment_face_counts=None, garment_face_indices=None,
                 garment_pinned=None, settings=None, up_axis="Y", meters_per_unit=1.0, device="cpu",
                 source="<host>"):
        from .garment import checked_garment
        from .scene import PointCacheMotion, Scene, SceneAssets, check_collider_frames, quiet_warp

        self.source = source
        if isinstance(meters_per_unit, bool) or not isinstance(meters_per_unit, (int, float, np.number)) \
                or not np.isfinite(meters_per_unit):
            raise InputError(source, "meters_per_unit", f"expected a finite number, got {meters_per_unit!r}")
        try:
            self.frame_space = HostFrame(up_axis, meters_per_unit)
        except ValueError as err:
            raise InputError(source, "up_axis" if "up_axis" in str(err) else "meters_per_unit", str(err)) from None
        vertices = self._points(collider_vertices, "collider_vertices")
        try:
            faces = np.asarray(collider_faces, np.int64)
        except (TypeError, ValueError):
            given = repr(collider_faces)[:60]
            raise InputError(source, "collider_faces", f"expected (F, 3) integer triangles, got {given}") from None
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise InputError(source, "collider_faces", f"expected (F, 3) triangles, got shape {faces.shape}")
        if faces.min() < 0 or faces.max() >= len(vertices):
            raise InputError(source, "collider_faces", f"indices must lie in [0, {len(vertices)})")
        if np.asarray(collider_faces).dtype.kind not in "iu":
            raise InputError(source, "collider_faces", "expected integer vertex indices")
        check_collider_frames(source, "collider_vertices", "the collider", vertices[None], faces)
        hair = garment = None
        if hair_points is not None:
            if hair_counts is None:
                raise InputError(source, "hair_counts", "hair_points need the vertex count of each strand")
            points = self._points(hair_points, "hair_points")
            counts = np.asarray(hair_counts)
            if counts.ndim != 1 or counts.dtype.kind not in "iuf" or not np.all(counts == np.round(counts)):
                raise InputError(source, "hair_counts", "expected a 1-D array of whole vertex counts per strand")
            widths = None
            if hair_widths is not None:
                widths = np.asarray(hair_widths, np.float64).reshape(-1)
                if len(widths) != len(points) or not (np.all(np.isfinite(widths)) and widths.min() >= 0.0):
                    raise InputError(source, "hair_widths", f"expected {len(points)} finite widths, zero or positive")
                widths = widths * self.frame_space.meters_per_unit
            hair = (points, counts.astype(np.int64), widths)
        if garment_vertices is not None:
            if garment_face_counts is None or garment_face_indices is None:
                raise InputError(source, "garment_face_counts", "a garment needs its polygons (counts and indices)")
            garment = checked_garment(source, "garment", "garment", self._points(garment_vertices, "garment_vertices"),
                                      np.asarray(garment_face_counts), np.asarray(garment_face_indices),
                                      None if garment_pinned is None else np.asarray(garment_pinned, np.int64))
        config = scene_config(source, settings, fps, device, hair is not None, garment is not None, self.frame_space)
        self.fps = config.timing.fps
        self._motion = PointCacheMotion([vertices], self.fps, keep=MOTION_FRAMES_KEPT)
        quiet_warp()
        with _TURNS:
            self.scene = Scene(config, SceneAssets("collider", faces, self._motion, hair, garment))
            self.frame = 0
            if config.timing.preroll > 0.0:
                self.scene.advance(config.timing.preroll, animate=False)

    def _points(self, values, key):
        points = np.asarray(values, np.float64)
        if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
            raise InputError(self.source, key, f"expected (N, 3) positions, got shape {points.shape}")
        if not np.all(np.isfinite(points)):
            raise InputError(self.source, key, "positions contain NaN or infinity")
        return self.frame_space.to_engine(points)

    def step(self, collider_points):
        """Advance one frame (1/fps) to the collider's positions at the new frame, host coordinates."""
        points = self._points(collider_points, "collider_points")
        if points.shape != self._motion.frames[0].shape:
            raise InputError(self.source, "collider_points",
                             f"expected {len(self._motion.frames[0])} positions, got {len(points)}")
        self._motion.append(points)
        with _TURNS:
            self.scene.advance(1.0 / self.fps, detail=True)
        self.frame += 1
        bad = self.scene.solver.report_unhealthy if self.scene.model is not None else None
        if bad is not None:
            count, first = self.scene.solver.count_unhealthy(self.scene.state)
            bad(count.numpy(), first.numpy(), self.frame, "hair")
        if self.scene.cloth_model is not None:
            count, first = self.scene.cloth_solver.count_unhealthy(self.scene.cloth_state)
            self.scene.cloth_solver.report_unhealthy(count.numpy(), first.numpy(), self.frame, "cloth")

    def hair_points(self):
        """(P, 3) float32 strand vertices in host coordinates, or None without hair."""
        scene = self.scene
        return None if scene.model is None else self.frame_space.from_engine(scene.state.x.numpy())

    def cloth_points(self):
        """(G, 3) float32 garment vertices in host coordinates, or None without a garment."""
        scene = self.scene
        return None if scene.cloth_model is None else self.frame_space.from_engine(scene.cloth_state.x.numpy())

    def detail_points(self):
        """The detail surface over the garment (positions (D, 3), triangles (T, 3)) in host
        coordinates, or None unless settings ask for cloth.detail.level > 0."""
        detail = self.scene.detail_surface()
        if detail is None:
            return None
        return self.frame_space.from_engine(detail[0].numpy()), self.scene.cloth_detail.triangles_np


def scene_config(source, settings, fps, device, hair, cloth, frame_space, frames=1):
    """A SceneConfig for geometry given as SceneAssets: the host's settings tables, checked like a
    scene file's, with hair and cloth switched on where given. Vector settings arrive in host axes."""
    from .scene import _build_config

    if settings is not None and not isinstance(settings, dict):
        raise InputError(source, "settings", f"expected a dict of tables, got {type(settings).__name__}")
    settings = {k: dict(v) if isinstance(v, dict) else v for k, v in (settings or {}).items()}
    for table, value in settings.items():
        if table not in HOST_TABLES:
            raise InputError(source, f"[{table}]", f"not a setting the host passes (known: {', '.join(HOST_TABLES)})")
        if not isinstance(value, dict):
            raise InputError(source, f"[{table}]", f"expected a table (dict), got {type(value).__name__}")
    if isinstance(fps, bool) or not isinstance(fps, (int, float, np.number)):
        raise InputError(source, "fps", f"expected a number, got {fps!r}")
    scene = {"fps": float(fps), "frames": int(frames), "device": device, **settings.get("scene", {})}
    data = {"scene": scene, "hair": {"enabled": bool(hair)}}
    solver = dict(settings.get("solver", {}))
    cloth_tables = dict(settings.get("cloth", {}))
    for key in cloth_tables:
        if key not in ("solver", "detail"):
            raise InputError(source, f"cloth.{key}", "the host gives the garment itself: only the [cloth.solver] "
                                                     "and [cloth.detail] tables apply")
    cloth_solver = dict(cloth_tables.get("solver", {}))
    for table in (solver, cloth_solver):
        for key in ("gravity", "wind"):
            value = table.get(key)
            if isinstance(value, np.ndarray):  # a host's vectors are often arrays
                value = value.tolist()
            if isinstance(value, (list, tuple)) and len(value) == 3:
                table[key] = list(frame_space.direction_to_engine(value))
    if solver:
        data["solver"] = solver
    if cloth:
        data["cloth"] = {"solver": cloth_solver, "detail": dict(cloth_tables.get("detail", {}))}
    return _build_config(source, data, None, check_files=False)
