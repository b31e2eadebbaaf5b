"""cfx.export_cache writes the simulated result as one world-space cache; cfx.export_stage writes
the tagged input stage `cfx run` reads (what Blender's exporter makes of the tags is checked here)."""

import blender_scene
import bpy
import numpy as np
from conftest import world_points
from pxr import Usd, UsdGeom


def _role_prims(stage):
    return {str(prim.GetAttribute("cfx:role").Get()): prim for prim in stage.Traverse()
            if prim.GetAttribute("cfx:role").HasAuthoredValue()}


def test_export_cache_writes_roles_frames_and_points(simulated, tmp_path):
    path = tmp_path / "exported.usda"
    bpy.context.window.scene = simulated.scene
    assert bpy.ops.cfx.export_cache(filepath=str(path)) == {'FINISHED'}
    stage = Usd.Stage.Open(str(path))
    scene = simulated.scene
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (scene.frame_start, scene.frame_end)
    prims = _role_prims(stage)
    assert sorted(prims) == ["cloth", "collider", "hair"]
    assert prims["hair"].IsA(UsdGeom.BasisCurves) and prims["cloth"].IsA(UsdGeom.Mesh)
    frames = list(range(scene.frame_start, scene.frame_end + 1))
    body = simulated.built.body
    for role, name in (("hair", "hair"), ("cloth", "cape"), ("collider", "body")):
        attr = UsdGeom.PointBased(prims[role]).GetPointsAttr()
        assert attr.GetTimeSamples() == frames, f"{role}: time samples {attr.GetTimeSamples()}"
        for k, frame in enumerate(frames):
            points = np.array(attr.Get(frame), np.float64)
            if role == "collider":
                scene.frame_set(frame)
                expected = world_points(body, bpy.context.evaluated_depsgraph_get())
            else:
                expected = simulated.frames[name][k]
            assert points.shape == expected.shape
            assert np.abs(points - expected).max() < 1e-6, f"{role} at frame {frame}"
    scene.frame_set(scene.frame_start)


def test_export_stage_tags_objects_the_way_cfx_run_reads_them(simulated, cfx_run):
    """What Blender 5.0's USD exporter makes of the add-on's tags: custom properties become custom
    attributes on the object's Xform (names with a namespace kept as they are, time-sampled on an
    animated object), the `cfx_pinned` point attribute becomes primvars:cfx_pinned, poly curves
    become linear BasisCurves, and the cache modifiers are left out of the exported geometry."""
    stage = Usd.Stage.Open(str(cfx_run.stage_path))
    built = simulated.built
    hair, cape, body = (stage.GetPrimAtPath(f"/root/{obj.name}") for obj in (built.hair, built.cape, built.body))
    start = Usd.TimeCode(stage.GetStartTimeCode())
    assert hair.GetAttribute("cfx:role").Get() == "hair"
    assert hair.GetAttribute("cfx:solver:substeps").Get() == 6
    assert abs(cape.GetAttribute("cfx:solver:strain_limit").Get() - 0.05) < 1e-6
    assert abs(cape.GetAttribute("cfx:scene:preroll").Get() - 0.2) < 1e-6
    assert body.GetAttribute("cfx:role").Get(start) == "collider"

    curves = UsdGeom.BasisCurves(next(c for c in hair.GetChildren() if c.IsA(UsdGeom.BasisCurves)))
    assert curves.GetTypeAttr().Get() == UsdGeom.Tokens.linear
    assert list(curves.GetCurveVertexCountsAttr().Get()) == [blender_scene.HAIR_POINTS] * blender_scene.HAIR_STRANDS
    assert np.allclose(curves.GetWidthsAttr().Get(), 2 * blender_scene.HAIR_RADIUS)
    assert not curves.GetPointsAttr().GetTimeSamples(), "the stage holds the hair's input, not the simulation"

    mesh = next(c for c in cape.GetChildren() if c.IsA(UsdGeom.Mesh))
    pinned = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("cfx_pinned")
    assert pinned and pinned.GetInterpolation() == UsdGeom.Tokens.vertex
    expected = (np.arange(blender_scene.CAPE_COLUMNS * blender_scene.CAPE_ROWS) < blender_scene.CAPE_COLUMNS)
    assert np.array_equal(np.array(pinned.Get()) > 0.5, expected)
