"""cfx.export_cache: the simulated result as one USD cache in world space (Z up), collider included,
each prim tagged with its cfx:role, the way `cfx run` writes its own caches.

Hair and cloth points come from the add-on's cache (local space) and are carried to world space with
each object's matrix at that frame; the collider is read as Blender evaluates it."""

import os
from typing import ClassVar

import bpy
import numpy as np
from bpy_extras.io_utils import ExportHelper

from . import geometry, playback
from .errors import UserError, engine
from .runner import scene_fps
from .selection import collider_of


class _CachedPrim:
    """One simulated object's prim in the add-on's cache: topology, and raw (local) points per frame."""

    def __init__(self, stage, path):
        from pxr import UsdGeom

        self.stage = stage  # the prim expires with its stage
        prim = stage.GetPrimAtPath(path)
        self.curves = prim.IsA(UsdGeom.BasisCurves) if prim else False
        if not prim or not (self.curves or prim.IsA(UsdGeom.Mesh)):
            raise LookupError(path)
        self.points_attr = UsdGeom.PointBased(prim).GetPointsAttr()
        if self.curves:
            curves = UsdGeom.BasisCurves(prim)
            self.counts, self.widths = curves.GetCurveVertexCountsAttr().Get(), curves.GetWidthsAttr().Get()
        else:
            mesh = UsdGeom.Mesh(prim)
            self.counts, self.indices = mesh.GetFaceVertexCountsAttr().Get(), mesh.GetFaceVertexIndicesAttr().Get()

    def points(self, frame):
        return np.array(self.points_attr.Get(float(frame)), np.float64)


def _cache_prims(simulated):
    """{object name: _CachedPrim} for the simulated objects, and the (start, end) frames of their cache."""
    from pxr import Usd

    stages, out = {}, {}
    for obj, mod in simulated:
        path = bpy.path.abspath(mod.cache_file.filepath)
        if path not in stages:
            if not os.path.exists(path):
                raise UserError(f"{obj.name}: its cache {path} is missing: simulate again")
            stages[path] = Usd.Stage.Open(path)
        try:
            out[obj.name] = _CachedPrim(stages[path], mod.object_path)
        except LookupError:
            raise UserError(f"{obj.name}: the cache {path} has no mesh or curves at {mod.object_path}: "
                            "simulate again") from None
    stage = next(iter(stages.values()))
    return out, (round(stage.GetStartTimeCode()), round(stage.GetEndTimeCode()))


def export_world_cache(context, path):
    """Write the collider and every simulated object of the scene, world space, to `path`."""
    CacheWriter = engine()[1]
    scene = context.scene
    collider = collider_of(scene)
    simulated = playback.simulated_objects(scene)
    if not simulated:
        raise UserError("nothing simulated in this scene: run Simulate first")
    prims, (start, end) = _cache_prims(simulated)
    names = playback.prim_names([collider] + [obj for obj, _ in simulated])
    frame = scene.frame_current
    try:
        scene.frame_set(start)
        depsgraph = context.evaluated_depsgraph_get()
        body = geometry.mesh_world(collider, depsgraph)
        with CacheWriter(path, scene_fps(scene), start, end, up_axis="Z",
                         meters_per_unit=scene.unit_settings.scale_length) as writer:
            writer.add_mesh(names[collider.name], "collider", None, None, face_counts=body.face_counts,
                            face_indices=body.face_indices)
            for obj, _ in simulated:
                prim = prims[obj.name]
                if prim.curves:  # the cache holds widths in the object's units, the export world ones
                    scale = geometry.uniform_scale(geometry.world_matrix(obj.evaluated_get(depsgraph)))
                    writer.add_curves(names[obj.name], "hair", prim.counts, np.asarray(prim.widths) * scale)
                else:
                    writer.add_mesh(names[obj.name], "cloth", None, None, face_counts=prim.counts,
                                    face_indices=prim.indices)
            for f in range(start, end + 1):
                scene.frame_set(f)
                depsgraph = context.evaluated_depsgraph_get()
                points = {names[collider.name]: geometry.mesh_world_vertices(collider, depsgraph)}
                for obj, _ in simulated:
                    points[names[obj.name]] = geometry.to_world(
                        prims[obj.name].points(f), geometry.world_matrix(obj.evaluated_get(depsgraph)))
                writer.write_frame(f, points)
    finally:
        scene.frame_set(frame)
    return len(simulated) + 1, end - start + 1


class CFX_OT_export_cache(bpy.types.Operator, ExportHelper):
    """Export the simulated hair, garments and the collider as one USD cache in world space"""

    bl_idname = "cfx.export_cache"
    bl_label = "Export Cache"
    bl_options: ClassVar[set] = {'REGISTER'}

    filename_ext = ".usdc"
    check_extension = False  # any of .usd/.usdc/.usda is kept as typed
    filter_glob: bpy.props.StringProperty(default="*.usd;*.usdc;*.usda", options={'HIDDEN'})

    def execute(self, context):
        try:
            prims, frames = export_world_cache(context, self.filepath)
        except ValueError as err:  # UserError, or the cache writer refusing the path
            self.report({'ERROR'}, str(err))
            return {'CANCELLED'}
        self.report({'INFO'}, f"exported {prims} prims x {frames} frames to {self.filepath}")
        return {'FINISHED'}
