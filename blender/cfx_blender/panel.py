"""The CFX tab of the 3D view's sidebar (N panel): collider, cache, settings and the buttons."""

import bpy


class CFX_PT_panel(bpy.types.Panel):
    bl_label = "Warp CFX"
    bl_idname = "CFX_PT_panel"
    bl_space_type = 'VIEW_3D'
    bl_region_type = 'UI'
    bl_category = "CFX"

    def draw(self, context):
        props = context.scene.cfx
        layout = self.layout
        layout.use_property_split = True
        layout.prop(props, "collider")
        layout.prop(props, "cache_path")
        layout.prop(props, "device")
        layout.prop(props, "preroll")

        hair = layout.column(heading="Hair")
        hair.prop(props, "hair_substeps", text="Substeps")
        hair.prop(props, "hair_damping", text="Damping")
        hair.prop(props, "hair_shape_stiffness", text="Stiffness")
        cloth = layout.column(heading="Cloth")
        cloth.prop(props, "cloth_substeps", text="Substeps")
        cloth.prop(props, "cloth_strain_limit", text="Strain Limit")

        layout.operator("cfx.simulate", icon='PLAY')
        layout.operator("cfx.export_cache", icon='EXPORT')
        row = layout.row(align=True)
        row.operator("cfx.tag", text="Tag for cfx run").role = 'AUTO'
        row.operator("cfx.export_stage", text="Export Stage", icon='FILE')
