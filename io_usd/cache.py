"""Time-sampled USD caches: a streaming writer and a reader that loads caches back into arrays.

Layout: /World (defaultPrim) holds one prim per simulated or collider object, each tagged with the
token attribute `cfx:role` (hair, cloth, cloth_detail, collider, face, hair_card). The writer saves
the crate file every few frames, so samples already written live on disk rather than in memory,
and writes under a temporary name that is renamed onto the output only when the run completes.
"""

import math
import os
from dataclasses import dataclass, field

import numpy as np
from pxr import Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, Vt

from sim.errors import InputError

from .output_file import check_output_path, discard, publish, temporary_beside

ROLES = ("hair", "cloth", "cloth_detail", "collider", "face", "hair_card")
OPEN_SURFACES = ("cloth", "cloth_detail", "hair_card")  # meshes written doubleSided
ROOT = "/World"
DEFAULT_CURVE_WIDTH = 1e-4  # m, a hair's width where a scene's curves give none
# on curves drawn from other curves each frame (render children): the path of those curves
INTERPOLATED_FROM = "cfx:interpolatedFrom"
STRAND_ID = "strandId"  # uniform int primvar on the simulated hair: which strand of the groom each curve is


def _vec3f(points):
    return Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(points, dtype=np.float32))


def _extent(points, widths=None):
    """Schema-correct extent: curves are padded by half their widths."""
    if widths is not None:
        return UsdGeom.Curves.ComputeExtent(points, widths)
    return UsdGeom.PointBased.ComputeExtent(points)


ENGINE = "warp-cfx"  # the root layer's cfx:engine in every cache written here


def open_stage(path, source=None, key=None):
    """A user's USD file opened, or InputError(source or path, key, reason): missing, unreadable, not USD."""
    path = os.fspath(path)
    source = path if source is None else source
    if os.path.isdir(path):
        reason = "a folder, not a USD file"
        raise InputError(source, key, f"{path} is {reason}" if source != path else reason)
    if not os.path.isfile(path):
        raise InputError(source, key, f"no such file: {path}" if source != path else "no such file")
    what = "not a USD file" if source == path else f"{os.path.basename(path)} is not a USD file"
    try:
        stage = Usd.Stage.Open(path)
    except Tf.ErrorException as err:
        # "Error in 'function' at line N in file F : 'reason'": the reason is what a user can act on
        first = next((line.strip() for line in str(err).splitlines() if line.strip()), "")
        detail = first.rpartition(" : ")[2].strip("'") if " : " in first else first
        raise InputError(source, key, f"{what} (USD could not open it: {detail})" if detail else what) from None
    if stage is None:
        raise InputError(source, key, what)
    return stage


def check_cache_path(path):
    """Raise InputError (a ValueError) unless `path` names a USD file we can write (.usd, .usdc,
    .usda): see output_file.check_output_path."""
    return check_output_path(path, (".usd", ".usdc", ".usda"), "the cache")


class CacheWriter:
    """Streams frames into a USD cache. Use as a context manager; on error nothing is left behind.

    path: .usdc (default binary), .usd or .usda. Frames are time codes; fps sets both
    timeCodesPerSecond and framesPerSecond. over: a scene's USD file that this cache is a layer over
    (sublayered, relative to the cache's folder): prims then go where the scene has them (add_over).
    The root layer's customLayerData names the engine and its version (engine_version, default this
    package's), the settings given, and cfx:complete once the last frame is written.
    """

    def __init__(self, path, fps, start_frame, end_frame, settings=None, up_axis="Y",
                 meters_per_unit=1.0, flush_every=8, engine_version=None, over=None):
        self.path = check_cache_path(path)
        self._ascii = self.path.lower().endswith(".usda")
        folder = os.path.dirname(os.path.abspath(self.path))
        self._tmp = temporary_beside(self.path, ".usdc")
        try:
            self.stage = Usd.Stage.CreateNew(self._tmp)
        except Tf.ErrorException as err:
            discard(self._tmp)
            raise InputError(self.path, None, f"cannot write it: {str(err).strip().splitlines()[-1]}") from None
        self.flush_every = max(1, int(flush_every))
        self._since_flush = 0
        self._prims = {}
        self._closed = False

        stage = self.stage
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y if up_axis.upper() == "Y" else UsdGeom.Tokens.z)
        UsdGeom.SetStageMetersPerUnit(stage, float(meters_per_unit))
        stage.SetTimeCodesPerSecond(float(fps))
        stage.SetFramesPerSecond(float(fps))
        stage.SetStartTimeCode(float(start_frame))
        stage.SetEndTimeCode(float(end_frame))
        if over is None:
            stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, ROOT).GetPrim())
        else:
            scene = os.path.relpath(os.path.abspath(over), folder)
            stage.GetRootLayer().subLayerPaths.append(scene)
            default = Sdf.Layer.FindOrOpen(os.path.abspath(over)).defaultPrim
            if default:
                stage.GetRootLayer().defaultPrim = default
        data = {"cfx:engine": ENGINE, "cfx:complete": False}
        if not engine_version:  # every cache says which engine wrote it, whoever calls the writer
            from sim import __version__ as engine_version
        data["cfx:engineVersion"] = str(engine_version)
        if settings:
            data["cfx:settings"] = _usd_dict(settings)
        stage.GetRootLayer().customLayerData = data

    # -- prims -------------------------------------------------------------------------------
    def _tag(self, prim, name, role, kind, **info):
        if role not in ROLES:
            raise ValueError(f"role must be one of {ROLES}, got {role!r}")
        # custom, as DCC importers read only custom attributes (Blender's "All Custom")
        prim.GetPrim().CreateAttribute("cfx:role", Sdf.ValueTypeNames.Token, custom=True).Set(role)
        self._prims[name] = dict(prim=prim, kind=kind, **info)
        return prim

    def add_over(self, name, role, path, animated=True):
        """A prim of the scene this cache is a layer over, at its own path: frames then carry its
        points (in its local space) and extent; its topology and everything else stay the scene's."""
        prim = self.stage.GetPrimAtPath(path)
        if not prim.IsValid() or not prim.IsA(UsdGeom.PointBased):
            raise ValueError(f"{path}: no points-based prim in the scene this cache is over")
        self.stage.OverridePrim(path)
        geom = UsdGeom.BasisCurves(prim) if prim.IsA(UsdGeom.BasisCurves) else UsdGeom.Mesh(prim)
        widths = None
        if prim.IsA(UsdGeom.BasisCurves):
            count = len(geom.GetPointsAttr().Get(Usd.TimeCode.EarliestTime()) or [])
            values = np.asarray(geom.GetWidthsAttr().Get(Usd.TimeCode.EarliestTime()) or [], np.float32)
            hair_width = DEFAULT_CURVE_WIDTH / UsdGeom.GetStageMetersPerUnit(self.stage)  # in the stage's units
            widths = Vt.FloatArray.FromNumpy(values if len(values) == count else np.full(count, values[0] if len(
                values) else hair_width, np.float32))
            if not len(values):  # renderers draw curves without widths a unit wide: the cache gives them the hair's
                over = UsdGeom.BasisCurves(self.stage.GetPrimAtPath(path))
                over.CreateWidthsAttr(widths)
                over.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
        kind = "curves" if widths is not None else "mesh"
        if kind == "mesh" and animated and not geom.GetSubdivisionSchemeAttr().HasAuthoredValue():
            # unauthored, the scheme is Catmull-Clark: DCCs would round off the simulated surface
            UsdGeom.Mesh(self.stage.GetPrimAtPath(path)).CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        tag = prim.GetAttribute("cfx:role")
        if tag and tag.HasAuthoredValue() and str(tag.Get()) == role:  # tagged in the scene already
            self._prims[name] = dict(prim=geom, kind=kind, widths=widths, animated=animated)
            return geom
        return self._tag(geom, name, role, kind, widths=widths, animated=animated)

    def add_mesh(self, name, role, points, faces, color=None, animated=True, face_counts=None, face_indices=None,
                 normals=False, uvs=None, path=None):
        """A mesh from faces (F, k) or a list of index lists, or from USD-style face_counts and
        face_indices (mixed quads and triangles). normals=True: per-vertex normals come with each frame.
        uvs: (V, 2) static per-vertex texture coordinates, written as the `st` primvar.
        path: where the prim goes (default /World/name)."""
        mesh = UsdGeom.Mesh.Define(self.stage, path or f"{ROOT}/{name}")
        if face_counts is not None:
            counts, indices = np.asarray(face_counts), np.asarray(face_indices)
        elif isinstance(faces, np.ndarray) and faces.ndim == 2:
            counts, indices = np.full(len(faces), faces.shape[1]), faces.reshape(-1)
        else:
            counts, indices = np.array([len(f) for f in faces]), np.concatenate(faces)
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(counts.astype(np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(indices.astype(np.int32)))
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        if role in OPEN_SURFACES:  # seen from both sides: renderers may cull a single-sided mesh's back faces
            mesh.CreateDoubleSidedAttr(True)
        _display_color(mesh, color)
        if normals:
            mesh.CreateNormalsAttr()
            mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
        if uvs is not None:
            _texture_coordinates(mesh, uvs)
        self._tag(mesh, name, role, "mesh", animated=animated)
        if not animated and points is not None:
            pts = _vec3f(points)
            mesh.CreatePointsAttr(pts)
            mesh.CreateExtentAttr(_extent(pts))
        return mesh

    def add_blend_shape_rig(self, name, points, faces, shape_names, offsets, color=None, joint="head"):
        """A UsdSkel rig that replays a blend-shape animation: SkelRoot `name` with a one-joint
        Skeleton, a SkelAnimation (joint transform and blendShapeWeights per frame), and the mesh in
        its rest pose with one BlendShape per shape (offsets (S, V, 3), stored sparsely).

        It carries no cfx:role and is invisible: it is the same animation as the role-tagged mesh, in
        the form DCCs retarget (shape keys), not a second copy to draw."""
        base = f"{ROOT}/{name}"
        root = UsdSkel.Root.Define(self.stage, base)
        root.CreateVisibilityAttr(UsdGeom.Tokens.invisible)
        skel = UsdSkel.Skeleton.Define(self.stage, f"{base}/skeleton")
        identity = Vt.Matrix4dArray([Gf.Matrix4d(1.0)])
        skel.CreateJointsAttr([joint])
        skel.CreateBindTransformsAttr(identity)
        skel.CreateRestTransformsAttr(identity)
        anim = UsdSkel.Animation.Define(self.stage, f"{base}/skeleton/animation")
        anim.CreateJointsAttr([joint])
        anim.CreateBlendShapesAttr(list(shape_names))
        anim.CreateTranslationsAttr()
        anim.CreateRotationsAttr()
        anim.CreateScalesAttr()
        anim.CreateBlendShapeWeightsAttr()
        UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])

        mesh = UsdGeom.Mesh.Define(self.stage, f"{base}/mesh")
        faces = np.asarray(faces)
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), faces.shape[1], np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.reshape(-1).astype(np.int32)))
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        pts = _vec3f(points)
        mesh.CreatePointsAttr(pts)
        mesh.CreateExtentAttr(_extent(pts))
        _display_color(mesh, color)
        binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
        binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
        binding.CreateJointIndicesPrimvar(True, 1).Set(Vt.IntArray([0]))
        binding.CreateJointWeightsPrimvar(True, 1).Set(Vt.FloatArray([1.0]))
        binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))
        binding.CreateBlendShapesAttr(list(shape_names))
        targets = []
        for shape_name, offset in zip(shape_names, np.asarray(offsets)):
            moved = np.nonzero(np.abs(offset).max(axis=1) > 0.0)[0]
            shape = UsdSkel.BlendShape.Define(self.stage, f"{base}/mesh/{shape_name}")
            shape.CreateOffsetsAttr(_vec3f(offset[moved]))
            shape.CreatePointIndicesAttr(Vt.IntArray.FromNumpy(moved.astype(np.int32)))
            targets.append(shape.GetPath())
        binding.CreateBlendShapeTargetsRel().SetTargets(targets)
        self._prims[name] = dict(prim=anim, kind="skel")
        return root

    def write_blend_shape_frame(self, name, frame, weights, transform):
        """One frame of a blend-shape rig: shape weights and the joint's 4x4 transform (column vectors)."""
        anim = self._prims[name]["prim"]
        t = Usd.TimeCode(float(frame))
        m = np.asarray(transform, np.float64)
        anim.GetTranslationsAttr().Set(Vt.Vec3fArray([Gf.Vec3f(*m[:3, 3])]), t)
        anim.GetRotationsAttr().Set(Vt.QuatfArray([Gf.Quatf(Gf.Matrix4d(m.T.tolist()).ExtractRotationQuat())]), t)
        anim.GetScalesAttr().Set(Vt.Vec3hArray([Gf.Vec3h(1.0, 1.0, 1.0)]), t)
        anim.GetBlendShapeWeightsAttr().Set(Vt.FloatArray.FromNumpy(np.asarray(weights, np.float32)), t)

    def add_curves(self, name, role, counts, widths, color=None, interpolated_from=None, ids=None):
        """Linear, nonperiodic BasisCurves with per-vertex widths [m]; points come per frame.
        interpolated_from: the name of the curves these are interpolated from each frame (render
        children), kept as the string attribute `cfx:interpolatedFrom` (that prim's path): readers
        that want the simulated strands alone (scoring, a cache read back as a scene) leave them out.
        ids: (C,) an int per curve, the uniform primvar `strandId`, sampled with the topology when it
        changes, so a DCC can follow a strand across cuts that remove others."""
        curves = UsdGeom.BasisCurves.Define(self.stage, f"{ROOT}/{name}")
        if interpolated_from is not None:
            curves.GetPrim().CreateAttribute(INTERPOLATED_FROM, Sdf.ValueTypeNames.String, custom=True).Set(
                f"{ROOT}/{interpolated_from}")
        curves.CreateTypeAttr(UsdGeom.Tokens.linear)
        curves.CreateBasisAttr(UsdGeom.Tokens.bspline)
        curves.CreateWrapAttr(UsdGeom.Tokens.nonperiodic)
        curves.CreateCurveVertexCountsAttr(Vt.IntArray.FromNumpy(np.asarray(counts, np.int32)))
        widths = np.asarray(widths, np.float32)
        widths_vt = Vt.FloatArray.FromNumpy(widths)
        curves.CreateWidthsAttr(widths_vt)
        curves.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
        if color is not None:
            curves.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set([Gf.Vec3f(*color)])
        id_values = None
        if ids is not None:
            id_values = np.asarray(ids, np.int32).copy()
            UsdGeom.PrimvarsAPI(curves).CreatePrimvar(STRAND_ID, Sdf.ValueTypeNames.IntArray,
                                                      UsdGeom.Tokens.uniform).Set(Vt.IntArray.FromNumpy(id_values))
        self._tag(curves, name, role, "curves", widths=widths_vt, animated=True,
                  counts=np.asarray(counts, np.int32).copy(), width_values=widths.copy(), id_values=id_values,
                  frames=[], varying=False)
        return curves

    def _set_curves(self, name, frame, counts, widths, ids=None):
        """A curves prim's topology at `frame` (and its strand ids, if add_curves gave some). Nothing is
        sampled while it stays the one add_curves gave; from its first change on, curveVertexCounts,
        widths and ids are sampled at every frame written (the frames before are filled in), so no
        reader ever interpolates between topologies."""
        info = self._prims[name]
        counts = np.asarray(counts, np.int32)
        widths = np.asarray(widths, np.float32)
        ids = info["id_values"] if ids is None or info["id_values"] is None else np.asarray(ids, np.int32)
        if not info["varying"]:
            if (np.array_equal(counts, info["counts"]) and np.array_equal(widths, info["width_values"])
                    and (ids is None or np.array_equal(ids, info["id_values"]))):
                return
            info["varying"] = True
            first = (info["counts"], info["width_values"], info["id_values"])
            for earlier in info["frames"]:
                self._sample_curves(info["prim"], earlier, *first)
        info["widths"] = Vt.FloatArray.FromNumpy(widths)
        self._sample_curves(info["prim"], frame, counts, widths, ids)

    @staticmethod
    def _sample_curves(curves, frame, counts, widths, ids):
        t = Usd.TimeCode(float(frame))
        curves.GetCurveVertexCountsAttr().Set(Vt.IntArray.FromNumpy(counts), t)
        curves.GetWidthsAttr().Set(Vt.FloatArray.FromNumpy(widths), t)
        if ids is not None:
            UsdGeom.PrimvarsAPI(curves).GetPrimvar(STRAND_ID).Set(Vt.IntArray.FromNumpy(ids), t)

    # -- frames ------------------------------------------------------------------------------
    def write_frame(self, frame, points_by_name, normals_by_name=None, curves=None):
        """Write time samples of points (and extent, and normals where given) at time code `frame`.

        curves: {name: (curveVertexCounts, widths[, strand ids])} of curves prims whose strands may
        change between frames (cut, grown, erased); once they differ from add_curves' they are
        time-sampled."""
        t = Usd.TimeCode(float(frame))
        for name, topology in (curves or {}).items():
            self._set_curves(name, frame, *topology)
        for name, points in points_by_name.items():
            info = self._prims[name]
            if "frames" in info:
                info["frames"].append(frame)
            geom = info["prim"]
            pts = _vec3f(points)
            geom.GetPointsAttr().Set(pts, t)
            geom.GetExtentAttr().Set(_extent(pts, info.get("widths")), t)
        for name, normals in (normals_by_name or {}).items():
            self._prims[name]["prim"].GetNormalsAttr().Set(_vec3f(normals), t)
        self._since_flush += 1
        if self._since_flush >= self.flush_every:
            self.stage.GetRootLayer().Save()
            self._since_flush = 0

    def set_metadata(self, key, value):
        """Add an entry (dicts allowed) to the root layer's customLayerData."""
        layer = self.stage.GetRootLayer()
        data = dict(layer.customLayerData)
        data[key] = _usd_dict(value) if isinstance(value, dict) else value
        layer.customLayerData = data

    # -- lifetime ----------------------------------------------------------------------------
    def close(self):
        """Mark the cache complete and move it onto the output path."""
        if self._closed:
            return
        self.set_metadata("cfx:complete", True)
        layer = self.stage.GetRootLayer()
        try:
            layer.Save()
            if self._ascii:
                if not layer.Export(self.path):
                    raise InputError(self.path, None, "cannot write it")
                discard(self._tmp)
            else:
                publish(self._tmp, self.path)
        except (Tf.ErrorException, OSError) as err:
            raise InputError(self.path, None, f"cannot write it: {str(err).strip().splitlines()[-1]}") from None
        finally:
            self._closed = True
            self.stage = None
            discard(self._tmp)

    def abort(self):
        """Drop the partial cache; the output path is left untouched."""
        self._closed = True
        self.stage = None
        if os.path.exists(self._tmp):
            os.remove(self._tmp)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
        else:
            self.abort()
        return False


def _display_color(gprim, color):
    """A constant colour (3,) or per-vertex colours (V, 3)."""
    if color is None:
        return
    color = np.asarray(color, np.float32)
    if color.ndim == 1:
        gprim.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set([Gf.Vec3f(*color.tolist())])
    else:
        gprim.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex).Set(_vec3f(color))


def _texture_coordinates(mesh, uvs):
    """Per-vertex `primvars:st` (TexCoord2f), the name renderers and DCCs look for."""
    uvs = np.ascontiguousarray(uvs, dtype=np.float32)
    if uvs.ndim != 2 or uvs.shape[1] != 2:
        raise ValueError(f"uvs: expected (V, 2) texture coordinates, got shape {uvs.shape}")
    primvar = UsdGeom.PrimvarsAPI(mesh.GetPrim()).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                                 UsdGeom.Tokens.vertex)
    primvar.Set(Vt.Vec2fArray.FromNumpy(uvs))


def _usd_dict(d):
    """customLayerData accepts nested dicts of bool, int, float, str; tuples become float lists."""
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out[k] = _usd_dict(v)
        elif isinstance(v, (list, tuple)):
            out[k] = Vt.DoubleArray([float(x) for x in v]) if all(
                isinstance(x, (int, float)) for x in v) else Vt.StringArray([str(x) for x in v])
        elif isinstance(v, (bool, int, float, str)):
            out[k] = v
        elif v is None:
            continue
        else:
            out[k] = str(v)
    return out


@dataclass
class CachePrim:
    name: str
    path: str
    role: str
    kind: str  # "mesh" or "curves"
    num_points: int
    counts: np.ndarray  # curveVertexCounts or faceVertexCounts
    indices: np.ndarray = field(default=None)  # faceVertexIndices (meshes)
    widths: np.ndarray = field(default=None)  # curves
    color: tuple = field(default=None)
    vertex_colors: np.ndarray = field(default=None)  # (V, 3) where displayColor is per vertex
    varying: bool = False  # curves whose curveVertexCounts change over time (a haircut): see counts()
    interpolated_from: str = None  # the path of the curves these are drawn from (render children), or None


class CacheReader:
    """Reads a cache written by CacheWriter (or any stage with cfx:role prims) back into arrays.

    Positions come out in the engine's frame: world space, metres, Y up. For our own caches that is
    what is stored; a cache layered over a DCC's scene stores local points in the scene's units and
    axes, and the reader applies the prim's transform and the stage's upAxis and metersPerUnit."""

    def __init__(self, path):
        self.path = os.fspath(path)
        if not os.path.exists(self.path):
            raise FileNotFoundError(f"{self.path}: no such cache")
        self.stage = open_stage(self.path)
        s = self.stage
        self.fps = s.GetTimeCodesPerSecond()
        if not (math.isfinite(s.GetStartTimeCode()) and math.isfinite(s.GetEndTimeCode())):
            raise ValueError(f"{self.path}: startTimeCode and endTimeCode must be finite")
        self.start_frame = int(round(s.GetStartTimeCode()))
        self.end_frame = int(round(s.GetEndTimeCode()))
        self.up_axis = str(UsdGeom.GetStageUpAxis(s))
        self.meters_per_unit = UsdGeom.GetStageMetersPerUnit(s)
        self.metadata = dict(s.GetRootLayer().customLayerData)
        from sim.embed import HostFrame

        self._frame = HostFrame(self.up_axis, self.meters_per_unit)
        self._engine_frame = self.up_axis.upper() == "Y" and self.meters_per_unit == 1.0
        self.prims = {}
        for prim in s.Traverse():
            role_attr = prim.GetAttribute("cfx:role")
            if not role_attr or not role_attr.HasAuthoredValue():
                continue
            name = prim.GetName()
            role = str(role_attr.Get(Usd.TimeCode.EarliestTime()))  # DCCs may time-sample it
            color = vertex_colors = None
            gprim = UsdGeom.Gprim(prim)
            dc = gprim.GetDisplayColorPrimvar()
            if dc and dc.HasAuthoredValue():
                values = np.array(dc.Get(), np.float32)
                if dc.GetInterpolation() == UsdGeom.Tokens.vertex:
                    vertex_colors = values
                elif len(values):  # an empty array leaves the default colour
                    color = tuple(float(c) for c in values.reshape(-1, 3)[0])
            if prim.IsA(UsdGeom.BasisCurves):
                c = UsdGeom.BasisCurves(prim)
                start = Usd.TimeCode(self.start_frame)
                counts = c.GetCurveVertexCountsAttr().Get(start)
                if counts is None:
                    raise ValueError(f"{self.path}: {prim.GetPath()}.curveVertexCounts: not authored")
                counts = np.array(counts, np.int32)
                widths = np.array(c.GetWidthsAttr().Get(start) or [], np.float32)
                source = prim.GetAttribute(INTERPOLATED_FROM)
                self.prims[name] = CachePrim(name, str(prim.GetPath()), role, "curves", int(counts.sum()),
                                             counts, widths=widths, color=color,
                                             varying=c.GetCurveVertexCountsAttr().GetNumTimeSamples() > 0,
                                             interpolated_from=str(source.Get()) if source and source.HasAuthoredValue()
                                             else None)
            elif prim.IsA(UsdGeom.Mesh):
                m = UsdGeom.Mesh(prim)
                counts, indices = m.GetFaceVertexCountsAttr().Get(), m.GetFaceVertexIndicesAttr().Get()
                if counts is None or indices is None:
                    raise ValueError(f"{self.path}: {prim.GetPath()}: faceVertexCounts or faceVertexIndices not "
                                     "authored")
                counts, indices = np.array(counts, np.int32), np.array(indices, np.int32)
                pts = m.GetPointsAttr().Get(Usd.TimeCode(self.start_frame))
                self.prims[name] = CachePrim(name, str(prim.GetPath()), role, "mesh",
                                             0 if pts is None else len(pts), counts, indices=indices, color=color,
                                             vertex_colors=vertex_colors)

    @property
    def complete(self):
        """False for an interrupted run's cache (cfx:complete false, or anything but true: a string
        "false" read as true); true for a stage no engine wrote."""
        return self.metadata.get("cfx:complete", True) is True

    def frames(self, name=None):
        """Time codes with point samples: of prim `name`, or of any prim. A prim with static points
        reports the start frame."""
        names = [name] if name else list(self.prims)
        frames = set()
        for n in names:
            attr = UsdGeom.PointBased(self.stage.GetPrimAtPath(self.prims[n].path)).GetPointsAttr()
            samples = attr.GetTimeSamples()
            frames.update(int(round(t)) for t in samples) if samples else frames.add(self.start_frame)
        return sorted(frames) or [self.start_frame]

    def counts(self, name, frame):
        """curveVertexCounts of a curves prim at `frame` (they change where strands were cut, grown
        or erased); faceVertexCounts of a mesh."""
        prim = self.prims[name]
        if not prim.varying:
            return prim.counts
        attr = UsdGeom.BasisCurves(self.stage.GetPrimAtPath(prim.path)).GetCurveVertexCountsAttr()
        return np.array(attr.Get(Usd.TimeCode(float(frame))), np.int32)

    def widths(self, name, frame):
        """Widths of a curves prim at `frame` (one per vertex, per curve or constant)."""
        prim = self.prims[name]
        if not prim.varying:
            return prim.widths
        attr = UsdGeom.BasisCurves(self.stage.GetPrimAtPath(prim.path)).GetWidthsAttr()
        return np.array(attr.Get(Usd.TimeCode(float(frame))) or [], np.float32)

    def normals(self, name, frame):
        """Per-vertex normals of a mesh prim at `frame`, or None where the cache has none."""
        attr = UsdGeom.Mesh(self.stage.GetPrimAtPath(self.prims[name].path)).GetNormalsAttr()
        value = attr.Get(Usd.TimeCode(float(frame))) if attr and attr.HasAuthoredValue() else None
        return None if value is None else np.array(value, dtype=np.float32)

    def points(self, name, frame):
        """Positions (P, 3) float32 of prim `name` at `frame`: world space, metres, Y up."""
        prim = self.stage.GetPrimAtPath(self.prims[name].path)
        t = Usd.TimeCode(float(frame))
        points = np.array(UsdGeom.PointBased(prim).GetPointsAttr().Get(t), dtype=np.float32)
        m = np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(t), np.float64)
        identity = np.array_equal(m, np.eye(4))
        if identity and self._engine_frame:
            return points
        world = points.astype(np.float64)
        if not identity:
            world = world @ m[:3, :3] + m[3, :3]  # USD matrices act on row vectors
        return self._frame.to_engine(world).astype(np.float32)

    def read_points(self, name):
        """All frames of one prim: (frames, points, 3) float32, or a list of (points, 3) arrays per
        frame when the number of points changes (cut hair)."""
        frames = [self.points(name, f) for f in self.frames(name)]
        if len({len(f) for f in frames}) > 1:
            return frames
        return np.stack(frames)

    def triangles(self, name):
        """Triangulated faces of a mesh prim as (T, 3), each polygon fanned from its first corner."""
        prim = self.prims[name]
        return fan_triangles(prim.counts, prim.indices)


def fan_triangles(counts, indices):
    """Triangles (T, 3) of polygons given as USD faceVertexCounts / faceVertexIndices, each polygon
    fanned from its first corner."""
    counts, indices = np.asarray(counts, np.int64), np.asarray(indices, np.int64)
    fans = np.maximum(counts - 2, 0)
    first = np.repeat(np.cumsum(counts) - counts, fans)
    k = np.arange(int(fans.sum())) - np.repeat(np.cumsum(fans) - fans, fans) + 1
    return np.stack([indices[first], indices[first + k], indices[first + k + 1]], 1)


def read_cache(path):
    """The whole cache as arrays: {name: {"role", "kind", "points": (F, P, 3), ...}} plus "frames"."""
    reader = CacheReader(path)
    out = {"frames": reader.frames(), "fps": reader.fps}
    for name, prim in reader.prims.items():
        out[name] = dict(role=prim.role, kind=prim.kind, points=reader.read_points(name), counts=prim.counts,
                         indices=prim.indices, widths=prim.widths)
    return out
