"""The add-on's scene settings (`scene.cfx`) and how they map onto the engine's settings tables.

The same table drives two things: the `settings` dict handed to sim.embed.Simulation, and the
`cfx:<table>:<key>` custom properties that tag objects for `cfx run`, so the add-on and the command
line always simulate with the same values.
"""

import bpy

# (property name, engine table, engine key, which tagged objects carry it as a custom property)
# "any" settings go on every tagged object; "hair" / "cloth" ones on the hair / garment objects.
SETTINGS = (
    ("preroll", ("scene",), "preroll", "any"),
    ("hair_substeps", ("solver",), "substeps", "hair"),
    ("hair_damping", ("solver",), "damping", "hair"),
    ("hair_shape_stiffness", ("solver",), "shape_stiffness", "hair"),
    ("cloth_substeps", ("cloth", "solver"), "substeps", "cloth"),
    ("cloth_strain_limit", ("cloth", "solver"), "strain_limit", "cloth"),
)


def _is_mesh(_self, obj):
    return obj.type == 'MESH'


class CFX_SceneSettings(bpy.types.PropertyGroup):
    collider: bpy.props.PointerProperty(
        name="Collider", type=bpy.types.Object, poll=_is_mesh,
        description="Mesh the hair roots and pinned garment vertices are bound to, and that everything collides with")
    cache_path: bpy.props.StringProperty(
        name="Cache", subtype='FILE_PATH', default="//cfx_cache.usdc",
        description="USD file the simulation is written to and played back from (.usdc, .usd or .usda)")
    device: bpy.props.EnumProperty(
        name="Device", default="cpu",
        items=(("cpu", "CPU", "Run the Warp kernels on the CPU"),
               ("cuda", "CUDA", "Run the Warp kernels on the first NVIDIA GPU")))
    preroll: bpy.props.FloatProperty(
        name="Preroll", default=1.0, min=0.0, soft_max=5.0, unit='TIME_ABSOLUTE',
        description="Seconds simulated with the collider held still before the first frame, so everything settles")
    hair_substeps: bpy.props.IntProperty(
        name="Hair Substeps", default=10, min=1, soft_max=40,
        description="Hair solver steps per frame")
    hair_damping: bpy.props.FloatProperty(
        name="Hair Damping", default=0.6, min=0.0, soft_max=10.0,
        description="Velocity decay of the hair, per second")
    hair_shape_stiffness: bpy.props.FloatProperty(
        name="Hair Stiffness", default=0.5, min=0.001, max=1.0,
        description="How far each shape-matching pass pulls strands back toward their groomed shape")
    cloth_substeps: bpy.props.IntProperty(
        name="Cloth Substeps", default=0, min=0, soft_max=200,
        description="Cloth solver steps per frame; 0 picks them from the stability bound")
    cloth_strain_limit: bpy.props.FloatProperty(
        name="Strain Limit", default=0.0, min=0.0, soft_max=0.2, subtype='FACTOR',
        description="Largest edge stretch kept after each cloth step (0.03 = 3%); 0 turns the limit off")


def engine_settings(props):
    """The Simulation `settings` dict: {"scene": {...}, "solver": {...}, "cloth": {"solver": {...}}}."""
    settings = {}
    for name, table, key, _owner in SETTINGS:
        node = settings
        for part in table:
            node = node.setdefault(part, {})
        node[key] = getattr(props, name)
    return settings


def custom_properties(props, role):
    """The `cfx:<table>:<key>` custom properties an object tagged with `role` carries for `cfx run`:
    scene keys on every tagged object, solver keys on the hair or garment they belong to."""
    out = {}
    for name, table, key, owner in SETTINGS:
        if owner == "any" or owner == role:
            # `cfx run` reads cloth settings from the garment's own cfx:solver:<key>, like the hair's
            section = table[-1]
            out[f"cfx:{section}:{key}"] = getattr(props, name)
    return out
