"""Deforming colliders and surface bindings.

A collider mesh is posed by linear blend skinning; anything attached to it (hair roots, pinned
particles, later garment pins) is stored as a triangle binding: triangle index, barycentric point and
an offset expressed in the triangle's orthonormal frame, so a rigid motion of the triangle moves the
bound point rigidly and exactly.
"""

import warp as wp

from ._options import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)


@wp.func
def triangle_frame(a: wp.vec3, b: wp.vec3, c: wp.vec3):
    """Orthonormal frame of a triangle: the basis in which bound offsets are stored.

    Any rigid motion of the triangle turns this frame with it, so an offset expressed in it follows
    the triangle exactly.

    Inputs:
      a (vec3, m): corner 0
      b (vec3, m): corner 1
      c (vec3, m): corner 2
    Returns:
      mat33: columns are the edge tangent (along b - a), the bitangent (normal x tangent) and the
          unit normal (along (b - a) x (c - a))
    """
    n = wp.normalize(wp.cross(b - a, c - a))
    t = wp.normalize(b - a)
    s = wp.cross(n, t)
    return wp.matrix_from_cols(t, s, n)


@wp.func
def face_frame(points: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32), f: int):
    """triangle_frame of face f of an indexed triangle mesh.

    Inputs:
      points (vec3, per mesh vertex, m): mesh vertices
      indices (int32, 3 per triangle): mesh triangles
      f (int, index): the triangle
    Returns:
      mat33: columns tangent, bitangent, unit normal (see triangle_frame)
    """
    return triangle_frame(points[indices[3 * f + 0]], points[indices[3 * f + 1]], points[indices[3 * f + 2]])


@wp.func
def face_point(points: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32), f: int, w: wp.vec3):
    """The point with barycentric weights w on face f.

    Inputs:
      points (vec3, per mesh vertex, m): mesh vertices
      indices (int32, 3 per triangle): mesh triangles
      f (int, index): the triangle
      w (vec3): weights of the triangle's corners 0, 1, 2
    Returns:
      vec3 (m): the point
    """
    return w[0] * points[indices[3 * f + 0]] + w[1] * points[indices[3 * f + 1]] + w[2] * points[indices[3 * f + 2]]


@wp.func
def skinned_point(rest_points: wp.array(dtype=wp.vec3), skin_indices: wp.array(dtype=wp.vec4i),
                  skin_weights: wp.array(dtype=wp.vec4), bone_matrices: wp.array(dtype=wp.mat44), bone_offset: int,
                  i: int):
    """Linear blend skinning of point i with up to four influences (see skin_points).

    Inputs:
      rest_points (vec3, per point, m): points in the bind pose
      skin_indices (vec4i, per point): bone of each influence, within one pose
      skin_weights (vec4, per point): weight of each influence; 0 skips it
      bone_matrices (mat44, num_poses * num_bones, m): per pose and bone, bind pose to posed
      bone_offset (int, index): first matrix of the pose to apply
      i (int, index): the point
    Returns:
      vec3 (m): the skinned point
    """
    p = rest_points[i]
    idx = skin_indices[i]
    w = skin_weights[i]
    out = wp.vec3(0.0)
    for k in range(4):
        if w[k] > 0.0:
            out += w[k] * wp.transform_point(bone_matrices[bone_offset + idx[k]], p)
    return out


@wp.kernel
def skin_points(
    rest_points: wp.array(dtype=wp.vec3),
    skin_indices: wp.array(dtype=wp.vec4i),
    skin_weights: wp.array(dtype=wp.vec4),
    bone_matrices: wp.array(dtype=wp.mat44),
    bone_offset: int,
    points: wp.array(dtype=wp.vec3),
):
    """Linear blend skinning with up to four influences per point.

    bone_matrices may hold several poses back to back (e.g. one per substep, uploaded once per
    frame); bone_offset selects one, so stepping through the substeps needs no upload.

    Launch: one thread per point (dim = len(rest_points)).
    Inputs:
      rest_points (vec3, per point, m): points in the bind pose
      skin_indices (vec4i, per point): bone of each influence, within one pose
      skin_weights (vec4, per point): weight of each influence; 0 skips it; expected to sum to 1 (not
          normalized here)
      bone_matrices (mat44, num_poses * num_bones, m): per pose and bone, the 4x4 transform from the
          bind pose to the posed one, for column vectors (translation in the last column)
      bone_offset (int, index): first matrix of the pose to apply, k * num_bones for pose k
    Outputs:
      points (vec3, per point, m): skinned points
    """
    i = wp.tid()
    points[i] = skinned_point(rest_points, skin_indices, skin_weights, bone_matrices, bone_offset, i)


@wp.kernel
def skin_listed_points(
    rest_points: wp.array(dtype=wp.vec3),
    skin_indices: wp.array(dtype=wp.vec4i),
    skin_weights: wp.array(dtype=wp.vec4),
    bone_matrices: wp.array(dtype=wp.mat44),
    bone_offset: int,
    listed: wp.array(dtype=wp.int32),
    points: wp.array(dtype=wp.vec3),
):
    """skin_points for the listed points only; the others keep what they hold. For a solver that
    reads a few of a body's points in most substeps (hair reads its root triangles).

    Launch: one thread per listed point (dim = len(listed)).
    Inputs:
      rest_points (vec3, per point, m): points in the bind pose
      skin_indices (vec4i, per point): bone of each influence, within one pose
      skin_weights (vec4, per point): weight of each influence; 0 skips it
      bone_matrices (mat44, num_poses * num_bones, m): per pose and bone, bind pose to posed
      bone_offset (int, index): first matrix of the pose to apply, k * num_bones for pose k
      listed (int32, per listed point): the points to skin
    Outputs:
      points (vec3, per point, m): the listed points skinned
    """
    i = listed[wp.tid()]
    points[i] = skinned_point(rest_points, skin_indices, skin_weights, bone_matrices, bone_offset, i)


@wp.struct
class SkinBinding:
    """Points bound to the triangles of a posed mesh (compute_bindings): hair roots, pinned cloth.

    Fields:
      mesh_points (vec3, per mesh vertex, m): posed mesh vertices
      mesh_indices (int32, 3 per triangle): mesh triangles
      triangle (int32, per binding): triangle of each binding
      barycentric (vec3, per binding): weights of that triangle's corners
      local (vec3, per binding, m): offset in that triangle's frame (compute_bindings)
    """

    mesh_points: wp.array(dtype=wp.vec3)
    mesh_indices: wp.array(dtype=wp.int32)
    triangle: wp.array(dtype=wp.int32)
    barycentric: wp.array(dtype=wp.vec3)
    local: wp.array(dtype=wp.vec3)


# inlined: left to the compiler, the CPU's copies of the struct per particle made the fused hair substep
# 3% slower (the real-time hair on two cores, benchmarks/turns.py)
@wp.func(inline=True)
def bound_position(binding: SkinBinding, b: int):
    """Where binding b puts its point on the posed mesh.

    The barycentric point carries the position, the offset in the triangle frame carries what lies
    off the surface (a hair root above the skin), so the bound point moves rigidly with the triangle.

    Inputs:
      binding (SkinBinding): the posed mesh and the bindings
      b (int, index): the binding
    Returns:
      vec3 (m): the bound point
    """
    f = binding.triangle[b]
    return (face_point(binding.mesh_points, binding.mesh_indices, f, binding.barycentric[b])
            + face_frame(binding.mesh_points, binding.mesh_indices, f) * binding.local[b])


@wp.kernel
def evaluate_bindings(
    binding: SkinBinding,
    bind_particle: wp.array(dtype=wp.int32),
    positions: wp.array(dtype=wp.vec3),
):
    """Place each bound particle at its barycentric point plus its offset in the triangle frame.

    Launch: one thread per binding (dim = num_bindings).
    Inputs:
      binding (SkinBinding): the posed mesh and the bindings
      bind_particle (int32, per binding): particle each binding places
    Outputs:
      positions (vec3, per particle, m): only the bound particles' entries are written
    """
    b = wp.tid()
    positions[bind_particle[b]] = bound_position(binding, b)


@wp.kernel
def compute_bindings(
    mesh_points: wp.array(dtype=wp.vec3),
    mesh_indices: wp.array(dtype=wp.int32),
    bind_triangle: wp.array(dtype=wp.int32),
    bind_barycentric: wp.array(dtype=wp.vec3),
    positions: wp.array(dtype=wp.vec3),
    bind_local: wp.array(dtype=wp.vec3),
):
    """Inverse of evaluate_bindings: express each world point in its triangle's frame.

    Run once on the mesh in the pose the points were authored on; the triangle and weights usually
    come from collision.mesh_closest_face. Note that positions is indexed by binding here, while
    evaluate_bindings writes positions indexed by particle.

    Launch: one thread per binding (dim = num_bindings).
    Inputs:
      mesh_points (vec3, per mesh vertex, m): mesh vertices in the binding pose
      mesh_indices (int32, 3 per triangle): mesh triangles
      bind_triangle (int32, per binding): triangle of each binding
      bind_barycentric (vec3, per binding): weights of that triangle's corners
      positions (vec3, per binding, m): the world point of each binding
    Outputs:
      bind_local (vec3, per binding, m): offset of each point from its barycentric point, in the
          triangle frame
    """
    b = wp.tid()
    f = bind_triangle[b]
    frame = face_frame(mesh_points, mesh_indices, f)
    bind_local[b] = wp.transpose(frame) * (positions[b] - face_point(mesh_points, mesh_indices, f, bind_barycentric[b]))


@wp.func
def blended_offset(shape_start: wp.array(dtype=wp.int32), shape_index: wp.array(dtype=wp.int32),
                   shape_offset: wp.array(dtype=wp.vec3), weights: wp.array(dtype=float), v: int):
    """Sum of vertex v's blend-shape offsets times the shapes' weights.

    Offsets are stored per vertex (CSR) and only where non-zero, so a vertex reads just the shapes
    that move it instead of every shape.

    Inputs:
      shape_start (int32, num_vertices + 1): CSR offsets of each vertex's entries
      shape_index (int32, per entry): shape of each entry
      shape_offset (vec3, per entry, m per unit weight): the vertex's offset in that shape
      weights (float, per shape): weight of each shape
      v (int, index): the vertex
    Returns:
      vec3 (m): the blended offset
    """
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
    """Rest points plus weighted blend-shape offsets, in the rig's own (rest) frame.

    Launch: one thread per rig vertex (dim = num_vertices).
    Inputs:
      rest_points (vec3, per vertex, m): the neutral shape
      shape_start (int32, num_vertices + 1): CSR offsets of each vertex's entries
      shape_index (int32, per entry): shape of each entry
      shape_offset (vec3, per entry, m per unit weight): the vertex's offset in that shape
      weights (float, per shape): weight of each shape
    Outputs:
      points (vec3, per vertex, m): the deformed shape
    """
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
    """A blend-shape rig riding a deforming mesh (a face on a turning head).

    Each vertex is bound to a triangle (compute_bindings, on rest_mesh_points) and its blend-shape
    offset, authored in the rest pose, turns with that triangle's frame, so expressions follow the
    head without a separate transform.

    Launch: one thread per rig vertex (dim = num_vertices).
    Inputs:
      shape_start (int32, num_vertices + 1): CSR offsets of each vertex's entries
      shape_index (int32, per entry): shape of each entry
      shape_offset (vec3, per entry, m per unit weight): the vertex's offset in that shape
      weights (float, per shape): weight of each shape
      rest_mesh_points (vec3, per mesh vertex, m): the carrying mesh in the pose the rig was bound on
      mesh_points (vec3, per mesh vertex, m): the carrying mesh in its current pose
      mesh_indices (int32, 3 per triangle): the carrying mesh's triangles
      bind_triangle (int32, per vertex): triangle each rig vertex is bound to
      bind_barycentric (vec3, per vertex): weights of that triangle's corners
      bind_local (vec3, per vertex, m): offset of the rest vertex in that triangle's frame
    Outputs:
      points (vec3, per vertex, m): posed and expressed rig vertices
    """
    v = wp.tid()
    f = bind_triangle[v]
    d = blended_offset(shape_start, shape_index, shape_offset, weights, v)
    rest_frame = face_frame(rest_mesh_points, mesh_indices, f)
    frame = face_frame(mesh_points, mesh_indices, f)
    points[v] = face_point(mesh_points, mesh_indices, f, bind_barycentric[v]) + frame * (
        bind_local[v] + wp.transpose(rest_frame) * d)
