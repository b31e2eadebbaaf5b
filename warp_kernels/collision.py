"""Collision queries against a head/body: the sphere tree of Hayashimoto et al. and triangle meshes.

Both are written as @wp.func so a solver kernel can resolve contacts inline (inside its own loop
over a strand); the kernels below expose the same functions over flat point arrays.

Sphere tree layout: nodes in depth-first order, each with a `skip` index (the next node to visit when
this node's subtree is not entered). Traversal needs no stack: on a hit descend to i + 1, on a miss
or after a leaf jump to skip[i]. Leaves are spheres inside the body; inner nodes bound their children.
"""

import warp as wp

# no gradients are taken through these kernels: skipping the backward passes halves compile time;
# the lean launch path (no grid-stride loop) lowers per-thread overhead
wp.set_module_options({"enable_backward": False, "default_grid_stride": False})

COLLIDE_NONE = wp.constant(0)
COLLIDE_SPHERE_TREE = wp.constant(1)
COLLIDE_MESH = wp.constant(2)


@wp.struct
class ColliderShape:
    """A collider as the kernels see it: its triangle mesh (a wp.Mesh id, BVH refitted to the pose)
    and its sphere tree (centres, radii, skip indices, leaf flags). sim.Collider.shape holds one."""

    mesh: wp.uint64
    centers: wp.array(dtype=wp.vec3)
    radii: wp.array(dtype=float)
    skip: wp.array(dtype=wp.int32)
    is_leaf: wp.array(dtype=wp.int32)


@wp.func
def sphere_tree_push_out(p: wp.vec3, shape: ColliderShape, margin: float):
    """Move p out of every leaf sphere (inflated by margin) it lies in."""
    centers, radii, skip, is_leaf = shape.centers, shape.radii, shape.skip, shape.is_leaf
    n = centers.shape[0]
    i = int(0)
    while i < n:
        d = p - centers[i]
        r = radii[i] + margin
        dist = wp.length(d)
        if dist < r:
            if is_leaf[i] != 0:
                if dist > 1.0e-9:
                    p = centers[i] + d * (r / dist)
                else:
                    p = centers[i] + wp.vec3(0.0, r, 0.0)
                i = skip[i]
            else:
                i = i + 1
        else:
            i = skip[i]
    return p


@wp.func
def sphere_tree_depth(p: wp.vec3, shape: ColliderShape):
    """Deepest penetration of p into any leaf sphere (0 when outside all)."""
    centers, radii, skip, is_leaf = shape.centers, shape.radii, shape.skip, shape.is_leaf
    n = centers.shape[0]
    i = int(0)
    depth = float(0.0)
    while i < n:
        dist = wp.length(p - centers[i])
        if dist < radii[i]:
            if is_leaf[i] != 0:
                depth = wp.max(depth, radii[i] - dist)
                i = skip[i]
            else:
                i = i + 1
        else:
            i = skip[i]
    return depth


@wp.func
def mesh_push_out(p: wp.vec3, mesh: wp.uint64, margin: float, max_dist: float):
    """Project p onto the surface (plus margin along the face normal) when inside or within margin."""
    q = wp.mesh_query_point_sign_normal(mesh, p, max_dist)
    if q.result:
        cp = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
        n = wp.mesh_eval_face_normal(mesh, q.face)
        if q.sign < 0.0:
            p = cp + n * margin
        else:
            d = p - cp
            dist = wp.length(d)
            if dist < margin:
                if dist > 1.0e-9:
                    p = cp + d * (margin / dist)
                else:
                    p = cp + n * margin
    return p


@wp.func
def collide_point(p: wp.vec3, mode: int, shape: ColliderShape, margin: float, search: float):
    """Resolve one point against the collider; `search` [m] bounds the mesh query (cost and depth)."""
    if mode == COLLIDE_SPHERE_TREE:
        # two sweeps: a push out of one leaf can land inside a neighbour visited earlier
        p = sphere_tree_push_out(p, shape, margin)
        p = sphere_tree_push_out(p, shape, margin)
    elif mode == COLLIDE_MESH:
        p = mesh_push_out(p, shape.mesh, margin, search)
    return p


@wp.func
def clearance(p: wp.vec3, mode: int, shape: ColliderShape, margin: float, search: float):
    """How far p may move before collide_point (same margin and search) could push it: a point
    displaced by less than clearance - margin is left where it is.

    Sphere tree: the distance to the nearest leaf sphere, capped at `search`. Mesh: the signed
    distance (negative inside) when the surface is within 2 search; otherwise search + margin, since
    collide_point's query (radius search) cannot reach the surface from a point that moved less
    than search.
    """
    if mode == COLLIDE_SPHERE_TREE:
        # branch and bound: a node's sphere bounds its leaves' spheres, so a node no nearer than the
        # best leaf so far cannot hold a nearer one
        best = search
        centers, radii, skip, is_leaf = shape.centers, shape.radii, shape.skip, shape.is_leaf
        n = centers.shape[0]
        i = int(0)
        while i < n:
            d = wp.length(p - centers[i]) - radii[i]
            if d < best:
                if is_leaf[i] != 0:
                    best = d
                    i = skip[i]
                else:
                    i = i + 1
            else:
                i = skip[i]
        return best
    if mode == COLLIDE_MESH:
        q = wp.mesh_query_point_sign_normal(shape.mesh, p, 2.0 * search)
        if q.result:
            return q.sign * wp.length(p - wp.mesh_eval_position(shape.mesh, q.face, q.u, q.v))
        return search + margin
    return 1.0e30


@wp.kernel
def points_clearance(
    points: wp.array(dtype=wp.vec3),
    mode: int,
    shape: ColliderShape,
    margin: float,
    search: float,
    out: wp.array(dtype=float),
):
    """clearance() of every point, in parallel (the strand solver's serial length pass then queries
    only the particles that may touch)."""
    i = wp.tid()
    out[i] = clearance(points[i], mode, shape, margin, search)


@wp.kernel
def push_points_out(
    points: wp.array(dtype=wp.vec3),
    mode: int,
    shape: ColliderShape,
    margin: float,
    search: float,
):
    i = wp.tid()
    points[i] = collide_point(points[i], mode, shape, margin, search)


@wp.kernel
def mesh_signed_distance(
    points: wp.array(dtype=wp.vec3),
    mesh: wp.uint64,
    max_dist: float,
    distance: wp.array(dtype=float),
    closest: wp.array(dtype=wp.vec3),
):
    """Signed distance to a closed mesh (negative inside) and the closest point; max_dist where none."""
    i = wp.tid()
    p = points[i]
    q = wp.mesh_query_point_sign_normal(mesh, p, max_dist)
    if q.result:
        cp = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
        closest[i] = cp
        distance[i] = q.sign * wp.length(p - cp)
    else:
        closest[i] = p
        distance[i] = max_dist


@wp.kernel
def sphere_tree_penetration(points: wp.array(dtype=wp.vec3), shape: ColliderShape, depth: wp.array(dtype=float)):
    i = wp.tid()
    depth[i] = sphere_tree_depth(points[i], shape)


@wp.kernel
def mesh_closest_face(
    points: wp.array(dtype=wp.vec3),
    mesh: wp.uint64,
    max_dist: float,
    face: wp.array(dtype=wp.int32),
    barycentric: wp.array(dtype=wp.vec3),
):
    """Closest triangle and barycentric coordinates (weights of vertices 0, 1, 2); face -1 if none."""
    i = wp.tid()
    q = wp.mesh_query_point_no_sign(mesh, points[i], max_dist)
    if q.result:
        face[i] = q.face
        barycentric[i] = wp.vec3(q.u, q.v, 1.0 - q.u - q.v)
    else:
        face[i] = -1
        barycentric[i] = wp.vec3(0.0)


@wp.kernel
def clear_inner_radii(radii: wp.array(dtype=float), is_leaf: wp.array(dtype=wp.int32)):
    """First half of refit_sphere_tree: inner nodes start from radius 0."""
    i = wp.tid()
    if is_leaf[i] == 0:
        radii[i] = 0.0


@wp.kernel
def refit_sphere_tree(
    centers: wp.array(dtype=wp.vec3),
    radii: wp.array(dtype=float),
    parent: wp.array(dtype=wp.int32),
    is_leaf: wp.array(dtype=wp.int32),
):
    """After the node centres are skinned (and clear_inner_radii), grow each inner node to bound the
    leaves of its subtree: every leaf raises each ancestor's radius to reach past it. One thread per
    leaf and a walk up the tree, rather than one thread per node scanning its subtree, whose root
    thread alone would read the whole tree."""
    j = wp.tid()
    if is_leaf[j] == 0:
        return
    c = centers[j]
    r = radii[j]
    a = parent[j]
    while a >= 0:
        wp.atomic_max(radii, a, wp.length(c - centers[a]) + r)
        a = parent[a]
