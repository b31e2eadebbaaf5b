"""Which objects a simulation takes: the scene's collider, the selected hair curves and garments."""

from dataclasses import dataclass, field

from .errors import UserError


@dataclass
class Targets:
    collider: object
    hair: list = field(default_factory=list)  # CURVES objects
    garments: list = field(default_factory=list)  # MESH objects other than the collider

    @property
    def simulated(self):
        return self.hair + self.garments


def collider_of(scene):
    """The scene's collider object, or UserError saying why there is none usable."""
    collider = scene.cfx.collider
    if collider is None:
        raise UserError("no collider: set Collider in the CFX panel to the mesh the hair and garment follow")
    if collider.type != 'MESH':
        raise UserError(f"{collider.name}: the collider must be a mesh object, not {collider.type}")
    if scene.objects.get(collider.name) is None:
        raise UserError(f"{collider.name}: the collider is not in scene '{scene.name}'")
    return collider


def simulation_targets(context):
    """The collider plus the selected CURVES objects (hair) and MESH objects other than the collider
    (garments); UserError when there is nothing to simulate."""
    collider = collider_of(context.scene)
    selected = list(context.selected_objects)
    hair = [obj for obj in selected if obj.type == 'CURVES']
    garments = [obj for obj in selected if obj.type == 'MESH' and obj != collider]
    if not hair and not garments:
        raise UserError(f"nothing to simulate: select a hair curves object or a garment mesh "
                            f"(other than the collider '{collider.name}')")
    return Targets(collider, hair, garments)
