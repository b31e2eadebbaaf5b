"""Deforming colliders and surface bindings.

A collider mesh is posed by linear blend skinning; anything attached to it (hair roots, pinned
particles, later garment pins) is stored as a triangle binding: triangle index, barycentric point and
an offset expressed in the triangle's orthonormal frame, so a rigid motion of the triangle moves the
bound point rigidly and exactly.
"""

import warp as wp

# no gradients are taken through these kernels: skipping the backward passes halves compile time;
# the lean launch path (no grid-stride loop) lowers per-thread overhead
wp.set_module_options({"enable_backward": False, "default_grid_stride": False})


@wp.func
def triangle_frame(a: wp.vec3, b: wp.vec3, c: wp.vec3):
    """Orthonormal frame of a triangle: columns are edge tangent, bitangent, unit normal."""
    n = wp.normalize(wp.cross(b - a, c - a))
    t = wp.normalize(b - a)
    s = wp.cross(n, t)
    return wp.matrix_from_cols(t, s, n)


@wp.func
def face_frame(points: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32), f: int):
    """triangle_frame of face f of an indexed triangle mesh."""
    return triangle_frame(points[indices[3 * f + 0]], points[indices[3 * f + 1]], points[indices[3 * f + 2]])


@wp.func
def face_point(points: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32), f: int, w: wp.vec3):
    """The point with barycentric weights w (of corners 0, 1, 2) on face f."""
    return w[0] * points[indices[3 * f + 0]] + w[1] * points[indices[3 * f + 1]] + w[2] * points[indices[3 * f + 2]]


@wp.kernel
def skin_points(
    rest_points: wp.array(dtype=wp.vec3),
    skin_indices: wp.array(dtype=wp.vec4i),
    skin_weights: wp.array(dtype=wp.vec4),
    bone_matrices: wp.array(dtype=wp.mat44),
    bone_offset: int,
    points: wp.array(dtype=wp.vec3),
):
    """Linear blend skinning with up to four influences; bone_offset selects the pose (e.g. a substep)."""
    i = wp.tid()
    p = rest_points[i]
    idx = skin_indices[i]
    w = skin_weights[i]
    out = wp.vec3(0.0)
    for k in range(4):
        if w[k] > 0.0:
            out += w[k] * wp.transform_point(bone_matrices[bone_offset + idx[k]], p)
    points[i] = out


@wp.func
def bound_position(mesh_points: wp.array(dtype=wp.vec3), mesh_indices: wp.array(dtype=wp.int32),
                   bind_triangle: wp.array(dtype=wp.int32), bind_barycentric: wp.array(dtype=wp.vec3),
                   bind_local: wp.array(dtype=wp.vec3), b: int):
    """Where binding b puts its point on the posed mesh: the barycentric point plus the offset in the
    triangle frame."""
    f = bind_triangle[b]
    return face_point(mesh_points, mesh_indices, f, bind_barycentric[b]) + face_frame(mesh_points, mesh_indices, f) * bind_local[b]


@wp.kernel
def evaluate_bindings(
    mesh_points: wp.array(dtype=wp.vec3),
    mesh_indices: wp.array(dtype=wp.int32),
    bind_particle: wp.array(dtype=wp.int32),
    bind_triangle: wp.array(dtype=wp.int32),
    bind_barycentric: wp.array(dtype=wp.vec3),
    bind_local: wp.array(dtype=wp.vec3),
    positions: wp.array(dtype=wp.vec3),
):
    """Place each bound particle at its barycentric point plus its offset in the triangle frame."""
    b = wp.tid()
    positions[bind_particle[b]] = bound_position(mesh_points, mesh_indices, bind_triangle, bind_barycentric, bind_local, b)


@wp.kernel
def compute_bindings(
    mesh_points: wp.array(dtype=wp.vec3),
    mesh_indices: wp.array(dtype=wp.int32),
    bind_triangle: wp.array(dtype=wp.int32),
    bind_barycentric: wp.array(dtype=wp.vec3),
    positions: wp.array(dtype=wp.vec3),
    bind_local: wp.array(dtype=wp.vec3),
):
    """Inverse of evaluate_bindings: express a world point in its triangle's frame."""
    b = wp.tid()
    f = bind_triangle[b]
    frame = face_frame(mesh_points, mesh_indices, f)
    bind_local[b] = wp.transpose(frame) * (positions[b] - face_point(mesh_points, mesh_indices, f, bind_barycentric[b]))


@wp.func
def blended_offset(shape_start: wp.array(dtype=wp.int32), shape_index: wp.array(dtype=wp.int32),
                   shape_offset: wp.array(dtype=wp.vec3), weights: wp.array(dtype=float), v: int):
    """Sum of vertex v's blend-shape offsets (stored per vertex, CSR) times the shapes' weights."""
    d = wp.vec3(0.0)
    for k in range(shape_start[v], shape_start[v + 1]):
        d += weights[shape_index[k]] * shape_offset[k]
    return d


@wp.kernel
def blend_shape_points(
    rest_points: wp.array(dtype=wp.vec3),
    shape_start: wp.array(dtype=wp.int32),
    shape_index: wp.array(dtype=wp.int32),
    shape_offset: wp.array(dtype=wp.vec3),
    weights: wp.array(dtype=float),
    points: wp.array(dtype=wp.vec3),
):
    """Rest points plus weighted blend-shape offsets, in the rig's own (rest) frame."""
    v = wp.tid()
    points[v] = rest_points[v] + blended_offset(shape_start, shape_index, shape_offset, weights, v)


@wp.kernel
def blend_shape_bound_points(
    shape_start: wp.array(dtype=wp.int32),
    shape_index: wp.array(dtype=wp.int32),
    shape_offset: wp.array(dtype=wp.vec3),
    weights: wp.array(dtype=float),
    rest_mesh_points: wp.array(dtype=wp.vec3),
    mesh_points: wp.array(dtype=wp.vec3),
    mesh_indices: wp.array(dtype=wp.int32),
    bind_triangle: wp.array(dtype=wp.int32),
    bind_barycentric: wp.array(dtype=wp.vec3),
    bind_local: wp.array(dtype=wp.vec3),
    points: wp.array(dtype=wp.vec3),
):
    """A blend-shape rig riding a deforming mesh: each vertex is bound to a triangle (evaluate_bindings)
    and its offset, authored in the rest pose, turns with that triangle's frame."""
    v = wp.tid()
    f = bind_triangle[v]
    d = blended_offset(shape_start, shape_index, shape_offset, weights, v)
    rest_frame = face_frame(rest_mesh_points, mesh_indices, f)
    frame = face_frame(mesh_points, mesh_indices, f)
    points[v] = face_point(mesh_points, mesh_indices, f, bind_barycentric[v]) + frame * (
        bind_local[v] + wp.transpose(rest_frame) * d)
