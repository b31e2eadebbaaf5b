"""Reading evaluated Blender geometry into NumPy arrays, and moving points between world and local space.

Everything here reads the evaluated object (modifiers, shape keys, armatures applied) at the scene's
current frame, so the simulation sees what the viewport shows.
"""

import numpy as np

from .errors import UserError

# Blender draws and exports curves without a radius attribute with this radius (USD widths 0.02)
DEFAULT_CURVE_RADIUS = 0.01
PINNED_ATTRIBUTE = "cfx_pinned"


def world_matrix(obj):
    """The evaluated object's world matrix as a (4, 4) float64 array (column vectors)."""
    return np.array(obj.matrix_world, np.float64)


def uniform_scale(matrix):
    """The scale a (4, 4) matrix applies to lengths (widths), taken as uniform: the cube root of its volume change."""
    return float(np.cbrt(abs(np.linalg.det(matrix[:3, :3]))))


def to_world(points, matrix):
    return np.asarray(points, np.float64) @ matrix[:3, :3].T + matrix[:3, 3]


def to_local(points, matrix):
    """World points into the space whose world matrix is `matrix` (its inverse applied)."""
    inverse = np.linalg.inv(matrix)
    return (np.asarray(points, np.float64) @ inverse[:3, :3].T + inverse[:3, 3]).astype(np.float32)


def _vectors(collection, attribute, count):
    values = np.empty(count * 3, np.float32)
    collection.foreach_get(attribute, values)
    return values.reshape(count, 3)


class MeshData:
    """A mesh in world space: vertices (V, 3) float64, polygons as counts and flat indices, and
    the triangles Blender tessellates them into."""

    def __init__(self, vertices, face_counts, face_indices, triangles, attributes):
        self.vertices, self.face_counts, self.face_indices = vertices, face_counts, face_indices
        self.triangles, self.attributes = triangles, attributes


def mesh_world(obj, depsgraph, point_attributes=()):
    """The evaluated mesh of `obj` in world space, with the named POINT-domain attributes read as
    float arrays (missing ones are left out)."""
    evaluated = obj.evaluated_get(depsgraph)
    mesh = evaluated.to_mesh()
    try:
        count = len(mesh.vertices)
        if count == 0:
            raise UserError(f"{obj.name}: the evaluated mesh has no vertices")
        local = _vectors(mesh.vertices, "co", count)
        face_counts = np.empty(len(mesh.polygons), np.int32)
        mesh.polygons.foreach_get("loop_total", face_counts)
        face_indices = np.empty(len(mesh.loops), np.int32)
        mesh.loops.foreach_get("vertex_index", face_indices)
        mesh.calc_loop_triangles()
        triangles = np.empty(len(mesh.loop_triangles) * 3, np.int32)
        mesh.loop_triangles.foreach_get("vertices", triangles)
        attributes = {name: _point_values(obj, mesh, name, count) for name in point_attributes
                      if name in mesh.attributes}
        return MeshData(to_world(local, world_matrix(evaluated)), face_counts, face_indices,
                        triangles.reshape(-1, 3), attributes)
    finally:
        evaluated.to_mesh_clear()


def mesh_world_vertices(obj, depsgraph):
    """Only the evaluated vertices of `obj` in world space (V, 3): the per-frame read of the collider."""
    evaluated = obj.evaluated_get(depsgraph)
    mesh = evaluated.to_mesh()
    try:
        return to_world(_vectors(mesh.vertices, "co", len(mesh.vertices)), world_matrix(evaluated))
    finally:
        evaluated.to_mesh_clear()


def _point_values(obj, mesh, name, count):
    attribute = mesh.attributes[name]
    if attribute.domain != 'POINT' or attribute.data_type not in ('FLOAT', 'BOOLEAN', 'INT', 'INT8'):
        raise UserError(f"{obj.name}: attribute '{name}' must be a FLOAT or BOOLEAN on the Vertex domain, "
                            f"not {attribute.data_type} on {attribute.domain}")
    values = np.empty(count, bool if attribute.data_type == 'BOOLEAN' else
                      (np.float32 if attribute.data_type == 'FLOAT' else np.int32))
    attribute.data.foreach_get("value", values)
    return values.astype(np.float32)


def pinned_vertices(obj, mesh_data):
    """Indices of the vertices whose `cfx_pinned` attribute is above 0.5 (empty without the attribute)."""
    values = mesh_data.attributes.get(PINNED_ATTRIBUTE)
    if values is None:
        return np.zeros(0, np.int64)
    return np.flatnonzero(values > 0.5)


class CurvesData:
    """Hair curves in world space: points (P, 3) float64, vertices per curve (S,), widths (P,) in
    world units, and the same widths in the object's own units (what a local-space cache stores)."""

    def __init__(self, points, counts, widths, local_widths):
        self.points, self.counts, self.widths, self.local_widths = points, counts, widths, local_widths


def curves_world(obj, depsgraph):
    """The evaluated Curves (hair) data of `obj` in world space; widths are twice the radius, the
    same values Blender's USD exporter writes."""
    evaluated = obj.evaluated_get(depsgraph)
    curves = evaluated.data
    count = len(curves.points)
    if count == 0 or len(curves.curves) == 0:
        raise UserError(f"{obj.name}: the hair curves object has no curves")
    local = _vectors(curves.attributes["position"].data, "vector", count)
    counts = np.empty(len(curves.curves), np.int32)
    curves.curves.foreach_get("points_length", counts)
    if counts.min() < 2:
        raise UserError(f"{obj.name}: every curve needs at least 2 points (the shortest has {counts.min()})")
    radius = curves.attributes.get("radius")
    if radius is not None and radius.domain == 'POINT':
        radii = np.empty(count, np.float32)
        radius.data.foreach_get("value", radii)
    else:
        radii = np.full(count, DEFAULT_CURVE_RADIUS, np.float32)
    matrix = world_matrix(evaluated)
    # the radius is in the object's local units: scale it like the points
    return CurvesData(to_world(local, matrix), counts, 2.0 * radii * uniform_scale(matrix), 2.0 * radii)
