"""The add-on against `cfx run`: the stage the add-on exports (Blender's own USD exporter, objects
tagged) runs on the command line to the same positions, and that cache imports back into Blender."""

import blender_scene
import bpy
import numpy as np
from conftest import world_points
from pxr import Usd, UsdGeom

TOLERANCE = 1e-5  # metres


def _prim(stage, role):
    """The geometry prim of the object tagged `role` (the tag sits on its Xform, as Blender writes it)."""
    for prim in stage.Traverse():
        attr = prim.GetAttribute("cfx:role")
        if attr and attr.HasAuthoredValue() and attr.Get(Usd.TimeCode.EarliestTime()) == role:
            return prim if prim.IsA(UsdGeom.PointBased) else next(
                child for child in prim.GetChildren() if child.IsA(UsdGeom.PointBased))
    raise AssertionError(f"no prim tagged {role!r}")


def _world(prim, frame):
    """Points of `prim` at `frame` in world space: local points times the local-to-world transform."""
    time = Usd.TimeCode(float(frame))
    points = np.array(UsdGeom.PointBased(prim).GetPointsAttr().Get(time), np.float64)
    matrix = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(time), np.float64)
    return points @ matrix[:3, :3] + matrix[3, :3]  # USD matrices act on row vectors


def test_cfx_run_matches_the_addon_on_every_frame(simulated, cfx_run):
    stage = Usd.Stage.Open(str(cfx_run.cache_path))
    scene = simulated.scene
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (scene.frame_start, scene.frame_end)
    for role, name in (("hair", "hair"), ("cloth", "cape")):
        prim = _prim(stage, role)
        for k, frame in enumerate(range(scene.frame_start, scene.frame_end + 1)):
            error = np.abs(_world(prim, frame) - simulated.frames[name][k]).max()
            assert error < TOLERANCE, f"{name} at frame {frame}: add-on and cfx run differ by {error:.2e} m"


def test_cfx_run_cache_imports_into_blender_animated(cfx_run):
    input_stage = Usd.Stage.Open(str(cfx_run.stage_path))
    hair_path, cloth_path = (str(_prim(input_stage, role).GetPath()) for role in ("hair", "cloth"))
    scene = blender_scene.new_scene("Imported")
    assert bpy.ops.wm.usd_import(filepath=str(cfx_run.cache_path)) == {'FINISHED'}
    assert (scene.frame_start, scene.frame_end) == (input_stage.GetStartTimeCode(), input_stage.GetEndTimeCode())

    played = {mod.object_path: obj for obj in scene.objects for mod in obj.modifiers
              if mod.type == 'MESH_SEQUENCE_CACHE'}
    assert hair_path in played and cloth_path in played, f"cache modifiers read {sorted(played)}"
    hair, cloth = played[hair_path], played[cloth_path]
    assert hair.type == 'CURVES' and cloth.type == 'MESH'
    counts = {hair.name: blender_scene.HAIR_STRANDS * blender_scene.HAIR_POINTS,
              cloth.name: blender_scene.CAPE_COLUMNS * blender_scene.CAPE_ROWS}
    seen = {hair.name: [], cloth.name: []}
    for frame in (scene.frame_start, (scene.frame_start + scene.frame_end) // 2, scene.frame_end):
        scene.frame_set(frame)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        for obj in (hair, cloth):
            points = world_points(obj, depsgraph)
            assert len(points) == counts[obj.name], f"{obj.name} at frame {frame}: {len(points)} points"
            seen[obj.name].append(points)
    for name, frames in seen.items():
        assert np.abs(frames[1] - frames[0]).max() > 1e-3 and np.abs(frames[2] - frames[1]).max() > 1e-3, \
            f"{name} does not move between frames"
