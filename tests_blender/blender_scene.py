"""A small test scene built with bpy: a keyframed UV sphere collider, a hair curves object rooted on
it, and a 6 x 6 cape whose top row is pinned to it. Sizes in metres (scale_length 1, Z up)."""

import math
from dataclasses import dataclass

import bpy
import numpy as np

RADIUS = 0.1
FRAME_START, FRAME_END = 1, 7
HAIR_STRANDS, HAIR_POINTS, HAIR_LENGTH, HAIR_WAVE, HAIR_RADIUS = 12, 10, 0.06, 0.006, 0.0005
CAPE_COLUMNS, CAPE_ROWS, CAPE_TOP, CAPE_ROW_SPACING = 6, 6, -0.05, 0.015


def new_scene(name):
    """An empty scene made current, leaving earlier scenes (and their data) alone."""
    scene = bpy.data.scenes.new(name)
    bpy.context.window.scene = scene
    return scene


def _link(scene, obj):
    scene.collection.objects.link(obj)
    return obj


def add_collider(scene):
    """A UV sphere that translates and turns over the frame range (object transform keyframes)."""
    bpy.ops.mesh.primitive_uv_sphere_add(radius=RADIUS, segments=16, ring_count=8, location=(0.0, 0.0, 0.0))
    body = bpy.context.active_object
    body.name = "Body"
    body.keyframe_insert("location", frame=FRAME_START)
    body.keyframe_insert("rotation_euler", frame=FRAME_START)
    body.location = (0.03, 0.0, 0.02)
    body.rotation_euler = (0.0, 0.0, 0.5)
    body.keyframe_insert("location", frame=FRAME_END)
    body.keyframe_insert("rotation_euler", frame=FRAME_END)
    return body


def hair_positions():
    """Wavy strands growing out of the upper half of the sphere, root first, tilted down a little.

    Wavy, not straight: the hair solver's shape matching finds each window's rotation from its
    points, and collinear points leave the turn about the strand undetermined, which makes straight
    strands amplify float rounding far beyond the 1e-5 m the tests compare at."""
    strands = []
    along = np.linspace(0.0, 1.0, HAIR_POINTS)[:, None]
    phase = 3.0 * math.pi * along
    for i in range(HAIR_STRANDS):
        longitude = 2.0 * math.pi * i / HAIR_STRANDS
        latitude = math.radians(20.0 + 25.0 * (i % 3))
        normal = np.array([math.cos(latitude) * math.cos(longitude), math.cos(latitude) * math.sin(longitude),
                           math.sin(latitude)])
        direction = normal - np.array([0.0, 0.0, 0.4])
        direction /= np.linalg.norm(direction)
        side = np.cross(direction, (0.0, 0.0, 1.0))
        side /= np.linalg.norm(side)
        lift = np.cross(side, direction)
        # roots a millimetre out: the polygonal sphere lies inside the true one between its vertices
        root = normal * (RADIUS + 0.001)
        wave = HAIR_WAVE * (np.sin(phase) * side + (1.0 - np.cos(phase)) * lift)
        strands.append(root + HAIR_LENGTH * along * direction + wave)
    return np.concatenate(strands).astype(np.float32)


def add_hair(scene):
    """A Curves (hair) object with poly strands and a per-point radius."""
    curves = bpy.data.hair_curves.new("HairCurves")
    curves.add_curves([HAIR_POINTS] * HAIR_STRANDS)
    curves.set_types(type='POLY')
    curves.attributes["position"].data.foreach_set("vector", hair_positions().ravel())
    radius = curves.attributes.new("radius", 'FLOAT', 'POINT')
    radius.data.foreach_set("value", np.full(HAIR_STRANDS * HAIR_POINTS, HAIR_RADIUS, np.float32))
    return _link(scene, bpy.data.objects.new("Hair", curves))


def cape_positions():
    """A sheet hanging behind the sphere from its lower half: the top row lies on the sphere."""
    xs = np.linspace(-0.04, 0.04, CAPE_COLUMNS)
    top_y = -np.sqrt(RADIUS ** 2 - xs ** 2 - CAPE_TOP ** 2)
    rows = []
    for r in range(CAPE_ROWS):
        z = CAPE_TOP - r * CAPE_ROW_SPACING
        rows.append(np.stack([xs, top_y - 0.004 * (r > 0), np.full_like(xs, z)], axis=1))
    return np.concatenate(rows)


def add_cape(scene):
    """A 6 x 6 quad grid with the `cfx_pinned` float attribute set on its top row."""
    points = cape_positions()
    faces = [(r * CAPE_COLUMNS + c, r * CAPE_COLUMNS + c + 1, (r + 1) * CAPE_COLUMNS + c + 1,
              (r + 1) * CAPE_COLUMNS + c) for r in range(CAPE_ROWS - 1) for c in range(CAPE_COLUMNS - 1)]
    mesh = bpy.data.meshes.new("CapeMesh")
    mesh.from_pydata(points.tolist(), [], faces)
    mesh.update()
    pinned = mesh.attributes.new("cfx_pinned", 'FLOAT', 'POINT')
    pinned.data.foreach_set("value", (np.arange(len(points)) < CAPE_COLUMNS).astype(np.float32))
    return _link(scene, bpy.data.objects.new("Cape", mesh))


@dataclass
class Built:
    scene: object
    body: object
    hair: object
    cape: object


def build(name, cache_path, preroll=0.2):
    """The whole scene, with the add-on's settings pointing at the sphere and `cache_path`; hair and
    cape are selected, the hair active, ready for bpy.ops.cfx.simulate(). Object names are unique
    across the file, so a second scene's objects get suffixes: use the returned objects."""
    scene = new_scene(name)
    scene.frame_start, scene.frame_end = FRAME_START, FRAME_END
    scene.render.fps, scene.render.fps_base = 24, 1.0
    body = add_collider(scene)
    hair, cape = add_hair(scene), add_cape(scene)
    scene.cfx.collider = body
    scene.cfx.cache_path = str(cache_path)
    scene.cfx.preroll = preroll
    scene.cfx.hair_substeps = 6
    scene.cfx.cloth_strain_limit = 0.05
    select(scene, [hair, cape])
    scene.frame_set(FRAME_START)
    return Built(scene, body, hair, cape)


def select(scene, objects):
    view_layer = bpy.context.view_layer
    for obj in scene.objects:
        obj.select_set(False)
    for obj in objects:
        obj.select_set(True)
    view_layer.objects.active = objects[0]
