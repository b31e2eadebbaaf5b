"""cfx.simulate in bpy: the selected hair and cape play the simulation back through the cache modifier."""

import blender_scene
import bpy
import numpy as np
import pytest
from conftest import frames_of


def test_simulated_objects_play_the_cache_back(simulated):
    scene = simulated.scene
    for name, obj in (("hair", simulated.built.hair), ("cape", simulated.built.cape)):
        modifiers = [mod for mod in obj.modifiers if mod.type == 'MESH_SEQUENCE_CACHE']
        assert len(modifiers) == 1, f"{name}: expected one cache modifier, got {len(modifiers)}"
        assert bpy.path.abspath(modifiers[0].cache_file.filepath) == str(simulated.cache_path)
        frames = simulated.frames[name]
        assert frames.shape[0] == scene.frame_end - scene.frame_start + 1
        assert frames.shape[1:] == simulated.rest[name].shape
        assert np.isfinite(frames).all()
        # the collider turns and travels a few centimetres: everything it carries moves with it
        assert np.abs(frames[-1] - simulated.rest[name]).max() > 0.01, f"{name} did not move"
        assert np.abs(frames[-1] - frames[-2]).max() > 1e-4, f"{name} stopped moving"


def test_hair_keeps_its_segment_lengths(simulated):
    strands = (blender_scene.HAIR_STRANDS, blender_scene.HAIR_POINTS, 3)
    rest = np.linalg.norm(np.diff(simulated.rest["hair"].reshape(strands), axis=1), axis=2)
    for frame in simulated.frames["hair"]:
        lengths = np.linalg.norm(np.diff(frame.reshape(strands), axis=1), axis=2)
        assert np.abs(lengths / rest - 1.0).max() < 0.03


def test_hair_roots_and_pinned_cape_row_follow_the_collider(simulated):
    scene, body = simulated.scene, simulated.built.body
    roots = simulated.frames["hair"][:, ::blender_scene.HAIR_POINTS]
    pinned = simulated.frames["cape"][:, :blender_scene.CAPE_COLUMNS]
    for k, frame in enumerate(range(scene.frame_start, scene.frame_end + 1)):
        scene.frame_set(frame)
        inverse = np.linalg.inv(np.array(body.matrix_world))
        for points in (roots[k], pinned[k]):
            # in the sphere's own frame, bound points stay on its surface
            local = points @ inverse[:3, :3].T + inverse[:3, 3]
            assert np.abs(np.linalg.norm(local, axis=1) - blender_scene.RADIUS).max() < 0.006
    scene.frame_set(scene.frame_start)


def test_simulate_without_selection_names_the_problem(simulated):
    built = simulated.built
    bpy.context.window.scene = built.scene
    blender_scene.select(built.scene, [built.body])
    with pytest.raises(RuntimeError, match="nothing to simulate: select a hair curves object or a garment mesh"):
        bpy.ops.cfx.simulate()
    blender_scene.select(built.scene, [built.hair, built.cape])


def test_simulate_without_collider_names_the_problem(tmp_path):
    scene = blender_scene.new_scene("NoCollider")
    hair = blender_scene.add_hair(scene)
    blender_scene.select(scene, [hair])
    scene.cfx.cache_path = str(tmp_path / "cache.usdc")
    with pytest.raises(RuntimeError, match="no collider: set Collider in the CFX panel"):
        bpy.ops.cfx.simulate()


def test_simulating_again_rewrites_the_cache_and_keeps_one_modifier(tmp_path):
    """Hair only, three frames, no preroll: cheap enough to run twice."""
    built = blender_scene.build("Again", tmp_path / "again.usdc", preroll=0.0)
    scene, hair = built.scene, built.hair
    scene.frame_end = 3
    blender_scene.select(scene, [hair])
    assert bpy.ops.cfx.simulate() == {'FINISHED'}
    first = frames_of(scene, [hair])[0]
    scene.cfx.hair_damping = 8.0  # heavier damping: a visibly different result
    assert bpy.ops.cfx.simulate() == {'FINISHED'}
    second = frames_of(scene, [hair])[0]
    assert len([mod for mod in hair.modifiers if mod.type == 'MESH_SEQUENCE_CACHE']) == 1
    assert len([f for f in bpy.data.cache_files if bpy.path.abspath(f.filepath) == str(tmp_path / "again.usdc")]) == 1
    assert np.abs(second[-1] - first[-1]).max() > 1e-5, "the modifier still plays the first cache"
