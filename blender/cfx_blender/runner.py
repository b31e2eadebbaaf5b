"""Driving the engine's Simulation from a Blender scene: everything is read in world space at the
scene's first frame, then the simulation steps frame by frame to the collider as Blender evaluates it.
Several hair objects (or garments) are simulated as one, and their points split back per object."""

import numpy as np

from . import geometry
from .errors import UserError, engine


def scene_fps(scene):
    return scene.render.fps / scene.render.fps_base


class SimulationRun:
    """Reads the inputs and builds the Simulation (which runs the preroll); `frames()` then yields
    (frame, {object name: world points}) from the first frame to the last, leaving the scene at
    each frame while its points are used."""

    def __init__(self, context, targets, settings, device="cpu"):
        Simulation = engine()[0]
        scene = context.scene
        self.context, self.scene, self.targets = context, scene, targets
        self.start, self.end = scene.frame_start, scene.frame_end
        scene.frame_set(self.start)
        depsgraph = context.evaluated_depsgraph_get()
        collider = geometry.mesh_world(targets.collider, depsgraph)
        if len(collider.triangles) == 0:
            raise UserError(f"{targets.collider.name}: the collider mesh has no faces")
        self.collider_vertex_count = len(collider.vertices)
        self.hair = {obj.name: geometry.curves_world(obj, depsgraph) for obj in targets.hair}
        self.garments = {obj.name: geometry.mesh_world(obj, depsgraph, (geometry.PINNED_ATTRIBUTE,))
                         for obj in targets.garments}
        self.simulation = Simulation(
            collider.vertices, collider.triangles, fps=scene_fps(scene), settings=settings,
            up_axis="Z", meters_per_unit=scene.unit_settings.scale_length, device=device,
            source=f"scene '{scene.name}'", **_hair_arguments(self.hair), **_garment_arguments(targets, self.garments))

    @property
    def frame_count(self):
        return self.end - self.start + 1

    def frames(self):
        yield self.start, self._world_points()
        for frame in range(self.start + 1, self.end + 1):
            self.scene.frame_set(frame)
            collider = self.targets.collider
            vertices = geometry.mesh_world_vertices(collider, self.context.evaluated_depsgraph_get())
            if len(vertices) != self.collider_vertex_count:
                raise UserError(f"{collider.name}: the collider has {len(vertices)} vertices at frame {frame} but "
                                f"{self.collider_vertex_count} at frame {self.start}; its topology must not change")
            self.simulation.step(vertices)
            yield frame, self._world_points()

    def _world_points(self):
        out = {}
        if self.hair:
            out.update(_split(self.simulation.hair_points(), {n: len(d.points) for n, d in self.hair.items()}))
        if self.garments:
            out.update(_split(self.simulation.cloth_points(), {n: len(d.vertices) for n, d in self.garments.items()}))
        return out


def _split(points, sizes):
    """Consecutive slices of `points`, one per name, in the order the inputs were concatenated."""
    out, begin = {}, 0
    for name, size in sizes.items():
        out[name] = points[begin:begin + size]
        begin += size
    return out


def _hair_arguments(hair):
    if not hair:
        return {}
    data = list(hair.values())
    return {"hair_points": np.concatenate([d.points for d in data]),
            "hair_counts": np.concatenate([d.counts for d in data]),
            "hair_widths": np.concatenate([d.widths for d in data])}


def _garment_arguments(targets, garments):
    if not garments:
        return {}
    indices, pinned, offset = [], [], 0
    for obj in targets.garments:
        mesh = garments[obj.name]
        indices.append(mesh.face_indices + offset)
        pinned.append(geometry.pinned_vertices(obj, mesh) + offset)
        offset += len(mesh.vertices)
    data = [garments[obj.name] for obj in targets.garments]
    return {"garment_vertices": np.concatenate([d.vertices for d in data]),
            "garment_face_counts": np.concatenate([d.face_counts for d in data]),
            "garment_face_indices": np.concatenate(indices),
            "garment_pinned": np.concatenate(pinned)}
