"""cfx.simulate: simulate the selected hair and garments against the scene's collider over the
scene's frame range, write the result to the add-on's USD cache (points in each object's local
space) and play it back on the objects through a cache modifier."""

from typing import ClassVar

import bpy

from . import geometry, playback
from .errors import UserError, engine, engine_errors
from .properties import engine_settings
from .runner import SimulationRun, scene_fps
from .selection import simulation_targets


def cache_path(scene):
    """The absolute cache path, or UserError when it cannot be resolved."""
    path = scene.cfx.cache_path.strip()
    if not path:
        raise UserError("no cache path: set Cache in the CFX panel")
    if path.startswith("//") and not bpy.data.filepath:
        raise UserError(f"cache path '{path}' is relative to the .blend file: save the file first or choose an "
                        "absolute path")
    return bpy.path.abspath(path)


class _Progress:
    """The window manager's progress counter where there is one (headless bpy has none to show)."""

    def __init__(self, context, total):
        self.wm = context.window_manager
        if self.wm is not None:
            self.wm.progress_begin(0, total)

    def update(self, value):
        if self.wm is not None:
            self.wm.progress_update(value)

    def end(self):
        if self.wm is not None:
            self.wm.progress_end()


def simulate_to_cache(context, targets, path):
    """Run the simulation and stream it into the cache at `path`; returns the prim name per object."""
    CacheWriter = engine()[1]
    scene = context.scene
    props = scene.cfx
    settings = engine_settings(props)
    run = SimulationRun(context, targets, settings, device=props.device)
    names = playback.prim_names(targets.simulated)
    progress = _Progress(context, run.frame_count)
    try:
        with CacheWriter(path, scene_fps(scene), run.start, run.end, settings=settings, up_axis="Z",
                         meters_per_unit=scene.unit_settings.scale_length) as writer:
            for obj in targets.hair:
                hair = run.hair[obj.name]
                writer.add_curves(names[obj.name], "hair", hair.counts, hair.local_widths)
            for obj in targets.garments:
                garment = run.garments[obj.name]
                writer.add_mesh(names[obj.name], "cloth", None, None, face_counts=garment.face_counts,
                                face_indices=garment.face_indices)
            for done, (frame, world) in enumerate(run.frames()):
                depsgraph = context.evaluated_depsgraph_get()
                # local space at this frame, so parented or animated objects play back where they are
                writer.write_frame(frame, {
                    names[obj.name]: geometry.to_local(world[obj.name], geometry.world_matrix(
                        obj.evaluated_get(depsgraph))) for obj in targets.simulated})
                progress.update(done + 1)
    finally:
        progress.end()
    return names


class CFX_OT_simulate(bpy.types.Operator):
    """Simulate the selected hair curves and garment meshes against the collider over the scene's frame range"""

    bl_idname = "cfx.simulate"
    bl_label = "Simulate"
    bl_options: ClassVar[set] = {'REGISTER', 'UNDO'}

    def execute(self, context):
        scene = context.scene
        frame = scene.frame_current
        try:
            targets = simulation_targets(context)
            path = cache_path(scene)
            engine()
            with playback.cache_modifiers_disabled(targets.simulated):
                names = simulate_to_cache(context, targets, path)
            cache_file = playback.cache_file_for(path)
            for obj in targets.simulated:
                playback.attach_cache(obj, cache_file, names[obj.name])
        except UserError as err:
            self.report({'ERROR'}, str(err))
            return {'CANCELLED'}
        except engine_errors() as err:
            self.report({'ERROR'}, f"simulation failed: {err}")
            return {'CANCELLED'}
        finally:
            scene.frame_set(frame)
        self.report({'INFO'}, f"simulated {len(targets.simulated)} object(s), frames {scene.frame_start}-"
                              f"{scene.frame_end}, into {path}")
        return {'FINISHED'}
