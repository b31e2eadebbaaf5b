"""Tagging objects for `cfx run`: the `cfx:role` custom property (collider, hair, cloth) and the
`cfx:<table>:<key>` settings, which Blender's USD exporter (export_custom_properties) writes as custom
attributes on each object's Xform prim, names kept as they are because they already carry a namespace.

cfx.tag tags the selection with one role, or (role AUTO) tags what cfx.simulate would take;
cfx.export_stage tags like AUTO and exports a stage `cfx run` reads, in one click."""

import os
from typing import ClassVar

import bpy
from bpy_extras.io_utils import ExportHelper

from . import playback
from .errors import UserError
from .properties import custom_properties
from .selection import simulation_targets

ROLE_PROPERTY = "cfx:role"


def untag(obj):
    """Remove every `cfx:` custom property (role and settings) from `obj`."""
    for key in [key for key in obj.keys() if key.startswith("cfx:")]:  # noqa: SIM118 (ID properties, not a dict)
        del obj[key]


def tag(obj, role, props):
    """Give `obj` the role and the scene's current settings for that role, replacing earlier tags."""
    untag(obj)
    obj[ROLE_PROPERTY] = role
    for key, value in custom_properties(props, role).items():
        obj[key] = value


def tag_targets(context, targets):
    props = context.scene.cfx
    tag(targets.collider, "collider", props)
    for obj in targets.hair:
        tag(obj, "hair", props)
    for obj in targets.garments:
        tag(obj, "cloth", props)


class CFX_OT_tag(bpy.types.Operator):
    """Tag the selected objects for `cfx run` (cfx:role and the CFX settings as custom properties)"""

    bl_idname = "cfx.tag"
    bl_label = "Tag for cfx run"
    bl_options: ClassVar[set] = {'REGISTER', 'UNDO'}

    role: bpy.props.EnumProperty(
        name="Role", default='AUTO',
        items=(('AUTO', "Auto", "The collider, selected hair curves as hair, selected meshes as cloth"),
               ('collider', "Collider", "The selected meshes are the collider"),
               ('hair', "Hair", "The selected curves objects are hair"),
               ('cloth', "Cloth", "The selected meshes are garments"),
               ('NONE', "Clear", "Remove the cfx tags from the selected objects")))

    def execute(self, context):
        try:
            if self.role == 'AUTO':
                targets = simulation_targets(context)
                tag_targets(context, targets)
                count = 1 + len(targets.simulated)
            else:
                count = self._tag_selection(context)
        except UserError as err:
            self.report({'ERROR'}, str(err))
            return {'CANCELLED'}
        self.report({'INFO'}, f"tagged {count} object(s)")
        return {'FINISHED'}

    def _tag_selection(self, context):
        wanted = 'CURVES' if self.role == "hair" else 'MESH'
        selected = list(context.selected_objects)
        if self.role == 'NONE':
            for obj in selected:
                untag(obj)
            return len(selected)
        fitting = [obj for obj in selected if obj.type == wanted]
        if not fitting:
            raise UserError(f"nothing to tag as {self.role}: select a {wanted.lower()} object")
        for obj in fitting:
            tag(obj, self.role, context.scene.cfx)
        return len(fitting)


class CFX_OT_export_stage(bpy.types.Operator, ExportHelper):
    """Tag the collider, selected hair and garments and export them as a USD stage for `cfx run`"""

    bl_idname = "cfx.export_stage"
    bl_label = "Export Stage for cfx run"
    bl_options: ClassVar[set] = {'REGISTER'}

    filename_ext = ".usda"
    check_extension = False  # any of .usd/.usdc/.usda is kept as typed
    filter_glob: bpy.props.StringProperty(default="*.usd;*.usdc;*.usda", options={'HIDDEN'})

    def execute(self, context):
        path = self.filepath
        if os.path.splitext(path)[1].lower() not in (".usd", ".usdc", ".usda"):
            self.report({'ERROR'}, f"{path}: a USD stage must end in .usd, .usdc or .usda")
            return {'CANCELLED'}
        try:
            targets = simulation_targets(context)
        except UserError as err:
            self.report({'ERROR'}, str(err))
            return {'CANCELLED'}
        tag_targets(context, targets)
        export_stage(context, [targets.collider] + targets.simulated, path)
        self.report({'INFO'}, f"exported {1 + len(targets.simulated)} tagged object(s) to {path}")
        return {'FINISHED'}


def export_stage(context, objects, path):
    """Blender's USD export of exactly `objects`, animated, with custom properties, and with the
    add-on's cache modifiers off so the stage holds the unsimulated input. Modifiers are evaluated
    with their viewport settings, as cfx.simulate reads them, so both simulate the same geometry."""
    view_layer = context.view_layer
    selected, active = list(context.selected_objects), view_layer.objects.active
    scene = context.scene
    try:
        for obj in selected:
            obj.select_set(False)
        for obj in objects:
            obj.select_set(True)
        with playback.cache_modifiers_disabled(objects):
            bpy.ops.wm.usd_export(filepath=path, selected_objects_only=True, export_animation=True,
                                  export_custom_properties=True, evaluation_mode='VIEWPORT',
                                  convert_scene_units='CUSTOM', meters_per_unit=scene.unit_settings.scale_length)
    finally:
        for obj in objects:
            obj.select_set(False)
        for obj in selected:
            obj.select_set(True)
        view_layer.objects.active = active
