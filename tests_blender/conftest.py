"""bpy tests of the Blender add-on in blender/cfx_blender. They run only in the bpy venv
(`make test-blender`: Python 3.11, bpy 5.0.1, numpy 1.26, this repository installed), never under
the main suite, so nothing here skips: a missing piece is a failure.

The session builds one small scene, simulates it with the add-on and runs the same stage through
`cfx run` of the main venv; the tests then compare and inspect those results."""

import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "blender"))

import blender_scene
import bpy
import cfx_blender


@pytest.fixture(scope="session", autouse=True)
def addon():
    cfx_blender.register()
    yield
    cfx_blender.unregister()


def world_points(obj, depsgraph):
    """The evaluated points of a mesh or curves object in world space, (N, 3) float64."""
    evaluated = obj.evaluated_get(depsgraph)
    if obj.type == 'CURVES':
        data = evaluated.data.attributes["position"].data
        local = np.empty(len(data) * 3, np.float32)
        data.foreach_get("vector", local)
    else:
        mesh = evaluated.to_mesh()
        local = np.empty(len(mesh.vertices) * 3, np.float32)
        mesh.vertices.foreach_get("co", local)
        evaluated.to_mesh_clear()
    matrix = np.array(evaluated.matrix_world, np.float64)
    return local.reshape(-1, 3) @ matrix[:3, :3].T + matrix[:3, 3]


def frames_of(scene, objects):
    """(F, N, 3) world points over the scene's frame range for each object, as Blender plays them."""
    out = [[] for _ in objects]
    for frame in range(scene.frame_start, scene.frame_end + 1):
        scene.frame_set(frame)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        for frames, obj in zip(out, objects):
            frames.append(world_points(obj, depsgraph))
    scene.frame_set(scene.frame_start)
    return [np.stack(frames) for frames in out]


@dataclass
class Simulated:
    built: blender_scene.Built
    cache_path: Path
    rest: dict  # {"hair", "cape": (N, 3)} world points before simulating
    frames: dict  # {"hair", "cape": (F, N, 3)} world points the add-on plays back

    @property
    def scene(self):
        return self.built.scene


@pytest.fixture(scope="session")
def simulated(tmp_path_factory):
    """The test scene simulated by bpy.ops.cfx.simulate()."""
    folder = tmp_path_factory.mktemp("addon")
    built = blender_scene.build("Addon", folder / "cfx_cache.usdc")
    objects = [built.hair, built.cape]
    rest = [frames[0] for frames in frames_of(built.scene, objects)]
    assert bpy.ops.cfx.simulate() == {'FINISHED'}
    frames = frames_of(built.scene, objects)
    return Simulated(built, folder / "cfx_cache.usdc", dict(zip(("hair", "cape"), rest)),
                     dict(zip(("hair", "cape"), frames)))


def cfx_command():
    """`cfx` of the main venv (which `make test` creates), or its Python running sim.cli."""
    venv = REPO / ".venv" / "bin"
    if (venv / "cfx").exists():
        return [str(venv / "cfx")]
    if (venv / "python").exists():
        return [str(venv / "python"), "-m", "sim.cli"]
    raise AssertionError(f"{REPO / '.venv'}: the main venv is missing; run `make install` first")


@dataclass
class CommandLineRun:
    stage_path: Path
    cache_path: Path


@pytest.fixture(scope="session")
def cfx_run(simulated, tmp_path_factory):
    """The simulated scene exported as a tagged stage by the add-on and run by `cfx run`."""
    folder = tmp_path_factory.mktemp("cfx_run")
    stage_path, cache_path = folder / "stage.usda", folder / "cache.usdc"
    bpy.context.window.scene = simulated.scene
    assert bpy.ops.cfx.export_stage(filepath=str(stage_path)) == {'FINISHED'}
    result = subprocess.run(cfx_command() + ["run", str(stage_path), "-o", str(cache_path), "--quiet"], check=False,
                            cwd=REPO, capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert result.returncode == 0, f"cfx run failed ({result.returncode}):\n{result.stderr[-3000:]}"
    return CommandLineRun(stage_path, cache_path)
