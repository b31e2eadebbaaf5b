"""A USD stage as the scene: prims tagged with `cfx:role`, as a DCC exports them, run by `cfx run`.

Input. Every prim whose `cfx:role` is "collider", "hair" or "cloth" takes part; the tag may sit on
the geometry itself or on the Xform above it (Blender writes an object's custom properties on its
Xform, the geometry is its child), and `userProperties:cfx:role` counts too. Colliders are Meshes
(several are merged into one collider); hair is BasisCurves (control points are the strand
vertices, the first one the root; curves marked `cfx:interpolatedFrom`, a cache's render children,
are left out); cloth is Meshes of triangles and quads (several are simulated
as one garment) whose pinned vertices are a per-vertex `primvars:cfx_pinned` (> 0.5) or an int[]
`cfx:pinned`. Settings are attributes
named `cfx:<table>:<key>` on a tagged prim: `solver` (hair solver on a hair prim, cloth solver on a
cloth prim), `detail` (cloth), `scene` (any: preroll, device, stats, graphs). Time comes from the
stage: timeCodesPerSecond, startTimeCode..endTimeCode, one cache frame per time code; positions are
taken in world space at each frame (transforms, deformation, upAxis and metersPerUnit applied).

Output. The cache is a layer over the input: `over`s at the input's prim paths carrying
time-sampled points (and extent) in each prim's own local space and units, plus the engine's
metadata; it sublayers the input, so it opens alone as the animated scene and can also be stacked
over the input in a shot. A detail surface, when asked for, is a new Mesh `cfx_cloth_detail` under
the stage's default prim (at the root without one), in that prim's space (it spans every garment), so
a reference to the cache brings it along.
"""

import math
import os
from dataclasses import dataclass, field

import numpy as np
from pxr import Usd, UsdGeom

from io_usd.cache import INTERPOLATED_FROM
from sim.embed import HostFrame, scene_config
from sim.errors import InputError

ROLES = ("collider", "hair", "cloth")
DETAIL_NAME = "cfx_cloth_detail"  # the detail surface over every garment, under the default prim
SETTING_TABLES = {"hair": ("solver", "scene"), "cloth": ("solver", "detail", "scene"), "collider": ("scene",)}
USD_EXTENSIONS = (".usd", ".usda", ".usdc")


def is_usd_scene(path):
    return os.path.splitext(str(path))[1].lower() in USD_EXTENSIONS


@dataclass
class TaggedPrim:
    role: str
    geometry: Usd.Prim  # the Mesh or BasisCurves
    tagged: list  # the prims that carry the tag and settings (the geometry and/or its Xform)

    @property
    def path(self):
        return str(self.geometry.GetPath())


@dataclass
class UsdScene:
    """What read_usd_scene found: the config and assets a Scene runs, and where results go back."""

    path: str
    config: object  # SceneConfig
    assets: object  # SceneAssets
    frame_space: HostFrame
    start_frame: int
    colliders: list  # TaggedPrim
    hair: list = field(default_factory=list)  # TaggedPrim, strands concatenated in this order
    cloth: list = field(default_factory=list)  # TaggedPrim, garments concatenated in this order
    stage: Usd.Stage = None

    def cache_writer(self, out_path, settings=None, engine_version=None):
        from .cache import CacheWriter
        from .output_file import is_input

        if is_input(out_path, self.path):  # a link to it too
            raise InputError(out_path, None, "the cache would overwrite the scene it sublayers; choose another output")
        t = self.config.timing
        if settings is not None:  # recorded as the stage gave them
            settings = self.frame_space.settings_from_engine(settings)
        writer = CacheWriter(out_path, t.fps, t.start_frame, t.start_frame + t.frames - 1, settings=settings,
                             up_axis=self.frame_space.up_axis, meters_per_unit=self.frame_space.meters_per_unit,
                             engine_version=engine_version, over=self.path)
        for prim in self.colliders:
            writer.add_over(prim.path, "collider", prim.path, animated=False)
        for prim in self.hair:
            writer.add_over(prim.path, "hair", prim.path)
        for prim in self.cloth:
            writer.add_over(prim.path, "cloth", prim.path)
        return writer

    @property
    def detail_parent(self):
        """The stage's default prim, which a reference to the cache brings in; None: the root."""
        prim = self.stage.GetDefaultPrim() if self.stage is not None else None
        return prim if prim and prim.IsValid() else None

    @property
    def detail_path(self):
        parent = self.detail_parent
        return f"{parent.GetPath() if parent is not None else ''}/{DETAIL_NAME}"

    def add_detail(self, writer, triangles):
        """The detail surface as a new Mesh under the default prim, in its space: it spans every garment."""
        writer.add_mesh(self.detail_path, "cloth_detail", None, triangles, normals=True, path=self.detail_path)
        return self.detail_path

    def write_frame(self, writer, frame, samples, normals=None):
        """samples: {"hair", "cloth", "cloth_detail": engine positions}; written in local space."""
        t = Usd.TimeCode(float(frame))
        out = {}
        for role in ("hair", "cloth"):
            offset = 0
            for prim in getattr(self, role) if role in samples else ():
                count = _point_count(prim.geometry)
                out[prim.path] = self._local(prim.geometry, samples[role][offset:offset + count], t)
                offset += count
        local_normals = {}
        if "cloth_detail" in samples:
            parent, path = self.detail_parent, self.detail_path
            out[path] = self._local(parent, samples["cloth_detail"], t)
            if normals and "cloth_detail" in normals:
                world = np.asarray(normals["cloth_detail"], np.float64) @ self.frame_space.rotation
                local_normals[path] = self._local_normals(parent, world, t)
        writer.write_frame(frame, out, local_normals)

    @staticmethod
    def _transform(prim, time):
        """prim's local-to-world 4x4 (USD's row-vector convention), or None where it is the identity."""
        if prim is None:
            return None
        m = np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(time), np.float64)
        return None if np.array_equal(m, np.eye(4)) else m

    def _local(self, prim, engine_points, time):
        """Engine positions in `prim`'s local space and the stage's units (prim None: world space)."""
        world = np.asarray(engine_points, np.float64) @ self.frame_space.rotation / self.frame_space.meters_per_unit
        m = self._transform(prim, time)
        if m is None:
            return world
        return (world - m[3, :3]) @ np.linalg.inv(m[:3, :3])  # USD matrices act on row vectors

    def _local_normals(self, prim, world_normals, time):
        """Unit world normals in `prim`'s local space: by the transpose of its linear part, which
        keeps them perpendicular to the surface under scales."""
        m = self._transform(prim, time)
        if m is None:
            return world_normals
        n = world_normals @ m[:3, :3].T
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def read_usd_scene(path, overrides=None):
    """Read a tagged USD stage into a UsdScene; bad input raises InputError naming the prim and key."""
    from sim.scene import PointCacheMotion, SceneAssets

    from .cache import ENGINE, open_stage

    path = os.fspath(path)
    stage = open_stage(path)
    if stage.GetRootLayer().customLayerData.get("cfx:engine") == ENGINE:
        raise InputError(path, "cfx:engine", "this is a cache cfx wrote, not a shot: run the scene or stage it was "
                                             "made from (cfx info lists what it holds)")
    up, meters = str(UsdGeom.GetStageUpAxis(stage)), UsdGeom.GetStageMetersPerUnit(stage)
    if up not in ("Y", "Z"):
        raise InputError(path, "upAxis", f"must be Y or Z, got {up!r}")
    if not (math.isfinite(meters) and meters > 0.0):
        raise InputError(path, "metersPerUnit", f"must be a positive number, got {meters!r}")
    frame_space = HostFrame(up, meters)
    tagged = _tagged_prims(path, stage)
    colliders = [p for p in tagged if p.role == "collider"]
    hair = [p for p in tagged if p.role == "hair"]
    cloth = [p for p in tagged if p.role == "cloth"]
    if not colliders:
        raise InputError(path, "cfx:role", "no prim is tagged \"collider\" (hair and cloth need something to move with)")
    if not hair and not cloth:
        raise InputError(path, "cfx:role", "no prim is tagged \"hair\" or \"cloth\": nothing to simulate")

    start = int(round(stage.GetStartTimeCode())) if stage.HasAuthoredTimeCodeRange() else 1
    end = int(round(stage.GetEndTimeCode())) if stage.HasAuthoredTimeCodeRange() else start
    if end < start:  # a range typed backwards ran a single frame without a word
        raise InputError(path, "endTimeCode", f"{end} is before startTimeCode {start}")
    frames = end - start + 1
    tables, origins = _settings(path, tagged, frame_space)
    origins.setdefault("scene.fps", "timeCodesPerSecond")
    scene_table = tables.setdefault("scene", {})
    scene_table.setdefault("start_frame", start)
    scene_table.setdefault("frames", frames)
    if overrides and overrides.get("scene"):
        scene_table.update(overrides["scene"])
    try:
        config = scene_config(path, tables, stage.GetTimeCodesPerSecond(), "cpu", bool(hair), bool(cloth), frame_space)
    except InputError as err:
        raise InputError(path, origins.get(err.key, err.key), err.reason) from None

    first = Usd.TimeCode(float(start))
    collider_frames, faces, offset = [], [], 0
    times = [Usd.TimeCode(float(start + k)) for k in range(config.timing.frames)]
    for prim in colliders:
        frames_of_prim = [_world_points(path, prim, frame_space, t) for t in times]
        for t, points in zip(times, frames_of_prim):
            if len(points) != len(frames_of_prim[0]):
                raise InputError(path, f"{prim.path}.points", f"{len(points)} points at time {t.GetValue():g}, "
                                 f"{len(frames_of_prim[0])} at {start}: a collider keeps its points")
        tri = _triangles(path, prim, UsdGeom.Mesh(prim.geometry), first, frames_of_prim[0])
        faces.append(tri + offset)
        collider_frames.append(frames_of_prim)
        offset += len(frames_of_prim[0])
    motion = PointCacheMotion([np.concatenate([c[k] for c in collider_frames]) for k in range(len(times))],
                              config.timing.fps)
    strands = None
    if hair:
        points = [_world_points(path, p, frame_space, first) for p in hair]
        counts = []
        for prim, pts in zip(hair, points):
            c = UsdGeom.BasisCurves(prim.geometry).GetCurveVertexCountsAttr().Get(first)
            if c is None or len(c) == 0:
                raise InputError(path, f"{prim.path}.curveVertexCounts", "not authored")
            counts.append(np.asarray(c, np.int64))
            if counts[-1].sum() != len(pts):
                raise InputError(path, f"{prim.path}.curveVertexCounts",
                                 f"sum to {counts[-1].sum()}, the curves have {len(pts)} points")
        widths = [_widths(path, p, c, first) for p, c in zip(hair, counts)]
        widths = None if any(w is None for w in widths) else np.concatenate(widths) * frame_space.meters_per_unit
        strands = (np.concatenate(points), np.concatenate(counts), widths)
    garment = _garment(path, cloth, frame_space, first) if cloth else None
    assets = SceneAssets("collider", np.concatenate(faces), motion, strands, garment)
    return UsdScene(path, config, assets, frame_space, start, colliders, hair, cloth, stage)


# -- tags and settings ------------------------------------------------------------------------------
def _role(prim):
    for name in ("cfx:role", "userProperties:cfx:role"):
        attr = prim.GetAttribute(name)
        if attr and attr.HasAuthoredValue():
            return str(attr.Get(Usd.TimeCode.EarliestTime())), name
    return None, None


def _tagged_prims(path, stage):
    found = {}
    for prim in stage.Traverse():
        role, attr = _role(prim)
        if role is None:
            continue
        if role not in ROLES:
            raise InputError(path, f"{prim.GetPath()}.{attr}", f"unknown role {role!r} (expected {', '.join(ROLES)})")
        source = prim.GetAttribute(INTERPOLATED_FROM)
        if role == "hair" and source and source.HasAuthoredValue():
            continue  # render children drawn from other strands each frame: nothing to simulate
        kind = UsdGeom.BasisCurves if role == "hair" else UsdGeom.Mesh
        if prim.IsA(kind):
            geometry = prim
        else:
            children = [c for c in prim.GetChildren() if c.IsA(kind)]
            if len(children) != 1:
                what = "BasisCurves" if role == "hair" else "Mesh"
                reason = (f"is tagged {role!r} but is not a {what} and has {len(children)} {what} children "
                          f"(expected the geometry itself or one child)")
                raise InputError(path, str(prim.GetPath()), reason)
            geometry = children[0]
        key = str(geometry.GetPath())
        if key in found:
            if found[key].role != role:
                raise InputError(path, key, f"tagged both {found[key].role!r} and {role!r}")
            found[key].tagged.append(prim)
        else:
            found[key] = TaggedPrim(role, geometry, [prim])
    return list(found.values())


def _settings(path, tagged, frame_space):
    """{table: {key: value}} from `cfx:<table>:<key>` attributes, and where each came from."""
    tables, origins = {}, {}
    for prim in tagged:
        for holder in prim.tagged:
            for attr in holder.GetAttributes():
                name = attr.GetName()
                bare = name[len("userProperties:"):] if name.startswith("userProperties:") else name
                if not bare.startswith("cfx:") or bare in ("cfx:role", "cfx:pinned") or not attr.HasAuthoredValue():
                    continue
                parts = bare.split(":")
                where = f"{holder.GetPath()}.{name}"
                if len(parts) != 3 or parts[1] not in SETTING_TABLES[prim.role]:
                    raise InputError(path, where, f"expected cfx:<table>:<key> with a table of "
                                                  f"{', '.join(SETTING_TABLES[prim.role])} on a {prim.role} prim")
                table = parts[1]
                section = {("solver", "cloth"): ("cloth", "solver"), ("detail", "cloth"): ("cloth", "detail")}.get(
                    (table, prim.role), (table,))
                value = _python_value(attr.Get(Usd.TimeCode.EarliestTime()))
                target = tables
                for level in section:
                    target = target.setdefault(level, {})
                key = parts[2]
                if key in target and target[key] != value:
                    raise InputError(path, where, f"conflicts with {origins['.'.join(section) + '.' + key]}")
                target[key] = value
                origins[".".join(section) + "." + key] = where
    return tables, origins


def _python_value(value):
    if isinstance(value, (bool, int, float, str)):
        return value
    if hasattr(value, "__len__") and not isinstance(value, str):
        return [_python_value(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return str(value)


# -- geometry ---------------------------------------------------------------------------------------
def _point_count(prim):
    points = UsdGeom.PointBased(prim).GetPointsAttr().Get(Usd.TimeCode.EarliestTime())
    return 0 if points is None else len(points)


def _world_points(path, prim, frame_space, time):
    points = UsdGeom.PointBased(prim.geometry).GetPointsAttr().Get(time)
    if points is None or len(points) == 0:
        raise InputError(path, f"{prim.path}.points", "not authored")
    p = np.asarray(points, np.float64).reshape(-1, 3)
    if not np.all(np.isfinite(p)):
        raise InputError(path, f"{prim.path}.points", f"non-finite positions at time {time.GetValue():g}")
    m = np.asarray(UsdGeom.Xformable(prim.geometry).ComputeLocalToWorldTransform(time), np.float64)
    if not np.array_equal(m, np.eye(4)):
        p = p @ m[:3, :3] + m[3, :3]
    return frame_space.to_engine(p)


def _triangles(path, prim, mesh, time, points):
    """The collider's faces as triangles, checked against its points (engine metres)."""
    from sim.scene import check_collider_frames

    from .cache import fan_triangles

    counts, indices = mesh.GetFaceVertexCountsAttr().Get(time), mesh.GetFaceVertexIndicesAttr().Get(time)
    if counts is None or indices is None or len(counts) == 0:
        raise InputError(path, prim.path, "faceVertexCounts or faceVertexIndices not authored")
    counts, indices = np.asarray(counts, np.int64), np.asarray(indices, np.int64)
    if counts.sum() != len(indices) or counts.min() < 3:
        raise InputError(path, f"{prim.path}.faceVertexCounts", "does not match faceVertexIndices")
    if indices.min() < 0 or indices.max() >= len(points):
        raise InputError(path, f"{prim.path}.faceVertexIndices", f"must lie in [0, {len(points)})")
    tri = fan_triangles(counts, indices)
    # a zero scale or every face collapsed (exploded the hair), a span of kilometres: as for mesh files
    check_collider_frames(path, prim.path, prim.geometry.GetName(), points[None], tri)
    return tri


def _widths(path, prim, counts, time):
    """Per-vertex widths of a curves prim (host units) from vertex, uniform (per curve) or constant
    values; None when not authored."""
    widths = UsdGeom.BasisCurves(prim.geometry).GetWidthsAttr().Get(time)
    if widths is None or len(widths) == 0:
        return None
    widths = np.asarray(widths, np.float64)
    if not (np.all(np.isfinite(widths)) and widths.min() >= 0.0):  # tapered tips may be 0
        raise InputError(path, f"{prim.path}.widths", "must be finite and zero or positive")
    if len(widths) == counts.sum():
        return widths
    if len(widths) == len(counts):
        return np.repeat(widths, counts)
    return np.full(counts.sum(), widths[0])


def _garment(path, prims, frame_space, time):
    """One garment of every cloth prim (a dress and its belt simulate as one cloth), each checked
    on its own first so errors name the prim."""
    from sim.garment import checked_garment

    parts, offset = [], 0
    for prim in prims:
        mesh = UsdGeom.Mesh(prim.geometry)
        counts, indices = mesh.GetFaceVertexCountsAttr().Get(time), mesh.GetFaceVertexIndicesAttr().Get(time)
        if counts is None or indices is None:
            raise InputError(path, prim.path, "faceVertexCounts or faceVertexIndices not authored")
        points = _world_points(path, prim, frame_space, time)
        part = checked_garment(path, prim.path, prim.geometry.GetName(), points, np.asarray(counts),
                               np.asarray(indices), _pinned(path, prim, len(points), time))
        parts.append((part, offset))
        offset += len(points)
    if len(parts) == 1:
        return parts[0][0]
    return checked_garment(path, ", ".join(p.path for p in prims), "garments",
                           np.concatenate([g.vertices for g, _ in parts]),
                           np.concatenate([g.face_counts for g, _ in parts]),
                           np.concatenate([g.face_indices + o for g, o in parts]),
                           np.concatenate([g.pinned + o for g, o in parts]))


def _pinned(path, prim, count, time):
    primvar = UsdGeom.PrimvarsAPI(prim.geometry).GetPrimvar("cfx_pinned")
    if primvar and primvar.HasAuthoredValue():
        values = np.asarray(primvar.ComputeFlattened(time), np.float64).reshape(-1)
        if len(values) != count:
            raise InputError(path, f"{prim.path}.primvars:cfx_pinned", f"has {len(values)} values for {count} points")
        return np.flatnonzero(values > 0.5)
    for holder in prim.tagged + [prim.geometry]:
        attr = holder.GetAttribute("cfx:pinned")
        if attr and attr.HasAuthoredValue():
            return np.asarray(attr.Get(time), np.int64).reshape(-1)
    return None
