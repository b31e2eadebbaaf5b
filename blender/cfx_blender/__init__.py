"""Warp CFX for Blender: simulate the selected hair curves and garment meshes against a collider
mesh with the Warp CFX engine, play the result back on the objects, and export it as USD.

The engine (this repository's `sim` and `io_usd` packages) must be pip-installed into Blender's
Python; the add-on only imports it when an operator runs, so it registers without it."""

import bpy

from . import export, panel, properties, simulate, tagging

classes = (
    properties.CFX_SceneSettings,
    simulate.CFX_OT_simulate,
    export.CFX_OT_export_cache,
    tagging.CFX_OT_tag,
    tagging.CFX_OT_export_stage,
    panel.CFX_PT_panel,
)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.types.Scene.cfx = bpy.props.PointerProperty(type=properties.CFX_SceneSettings)


def unregister():
    del bpy.types.Scene.cfx
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
