"""Collision queries against a head/body: the sphere tree of Hayashimoto et al. and triangle meshes.

Both are written as @wp.func so a solver kernel can resolve contacts inline (inside its own loop
over a strand); the kernels below expose the same functions over flat point arrays.

Sphere tree layout: nodes in depth-first order, each with a skip index (the next node to visit when
this node's subtree is not entered). Traversal needs no stack: on a hit descend to i + 1, on a miss
or after a leaf jump to the skip index. Leaves are spheres inside the body; inner nodes bound their
children. The walks read each node as two packed values (ColliderShape).
"""

# float(0.0), int(0) and bool(False) declare variables that a kernel reassigns (Warp treats a
# bare literal as a constant)
# ruff: noqa: UP018, RUF046

import warp as wp

from ._options import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)

from .skinning import skinned_point  # noqa: E402

COLLIDE_NONE = wp.constant(0)
COLLIDE_SPHERE_TREE = wp.constant(1)
COLLIDE_MESH = wp.constant(2)
SPHERE_LEAF = wp.constant(-2147483648)  # ColliderShape.links: the flag bit of a leaf sphere
SPHERE_SKIP = wp.constant(2147483647)  # ColliderShape.links: the skip pointer's bits
# listed faces (collide_point_listed_mesh): closest points this close count as one point (above the
# rounding of closest points computed on different faces), and a list is gathered this much beyond
# the nearest face last listed: a smaller box costs less to gather than a list that lasts longer saves
# (in turns against 2 mm: 1 mm 0.96x, 0.5 mm 0.95x, 0.2 mm 0.93x, 0.1 mm 0.91x, none 1.29x, when no
# list can decide; BENCHMARKS.md, sessions 25 and 29)
MESH_TIE = wp.constant(1.0e-5)  # m
MESH_LIST_SLACK = wp.constant(0.0002)  # m


@wp.struct
class ColliderShape:
    """A collider as the kernels see it: its triangle mesh and its sphere tree.

    One struct instead of six arguments keeps the solver kernels' signatures short and lets a
    collider switch between mesh and sphere-tree collision without a different launch.
    sim.Collider.shape holds one; a host fills the fields itself.

    The sphere tree is packed for its walks: a node's centre and radius are one 16-byte read, and its
    skip pointer and leaf flag one more (pack_sphere_tree, sim.sphere_tree.SphereTree.links), where
    four arrays cost a walk four reads per node.

    Fields:
      mesh (uint64): wp.Mesh id of the posed triangle mesh, BVH refitted to the pose
      spheres (vec4, per tree node, m): centre (x, y, z) and radius (w) of each node, in depth-first
          order; inner nodes bound their subtree's leaves
      links (int32, per tree node): the node visited next when this node's subtree is not entered
          (links & SPHERE_SKIP), with SPHERE_LEAF set for leaf spheres (inside the body)
    """

    mesh: wp.uint64
    spheres: wp.array(dtype=wp.vec4)
    links: wp.array(dtype=wp.int32)


@wp.func
def sphere_center(s: wp.vec4):
    """The centre of a packed tree node (ColliderShape.spheres).

    Inputs:
      s (vec4, m): centre and radius
    Returns:
      vec3 (m): the centre
    """
    return wp.vec3(s[0], s[1], s[2])


@wp.func
def sphere_tree_push_out(p: wp.vec3, shape: ColliderShape, margin: float):
    """Move p out of every leaf sphere, inflated by margin, that it lies in.

    One depth-first sweep with skip pointers, no stack. A push out of one leaf can land inside a
    neighbour visited earlier, so collide_point runs it twice.

    Inputs:
      p (vec3, m): the point
      shape (ColliderShape): the collider; only its sphere tree is read
      margin (float, m): distance kept outside the leaf spheres
    Returns:
      vec3 (m): the pushed point (p itself when it was outside every leaf)
    """
    n = shape.spheres.shape[0]
    i = int(0)
    while i < n:
        s = shape.spheres[i]
        link = shape.links[i]
        c = sphere_center(s)
        d = p - c
        r = s[3] + margin
        dist = wp.length(d)
        if dist < r:
            if link < 0:
                if dist > 1.0e-9:
                    p = c + d * (r / dist)
                else:
                    p = c + wp.vec3(0.0, r, 0.0)
                i = link & SPHERE_SKIP
            else:
                i = i + 1
        else:
            i = link & SPHERE_SKIP
    return p


@wp.func
def sphere_tree_depth(p: wp.vec3, shape: ColliderShape):
    """Deepest penetration of p into any leaf sphere, for tests and diagnostics.

    Inputs:
      p (vec3, m): the point
      shape (ColliderShape): the collider; only its sphere tree is read
    Returns:
      float (m): largest radius - distance over the leaves containing p; 0 when outside all
    """
    n = shape.spheres.shape[0]
    i = int(0)
    depth = float(0.0)
    while i < n:
        s = shape.spheres[i]
        link = shape.links[i]
        dist = wp.length(p - sphere_center(s))
        if dist < s[3]:
            if link < 0:
                depth = wp.max(depth, s[3] - dist)
                i = link & SPHERE_SKIP
            else:
                i = i + 1
        else:
            i = link & SPHERE_SKIP
    return depth


@wp.func
def mesh_push_out(p: wp.vec3, mesh: wp.uint64, margin: float, max_dist: float):
    """Project p onto the mesh surface plus margin when it is inside or closer than margin, and
    report p's signed distance from the surface found by the same query.

    Inside points go out along the closest face's normal; outside points move along their own
    direction from the closest point, which stays continuous around edges and corners where the face
    normal jumps.

    Inputs:
      p (vec3, m): the point
      mesh (uint64): wp.Mesh id of a closed, outward-wound mesh
      margin (float, m): distance kept outside the surface
      max_dist (float, m): query radius; a point farther than this from the surface is not seen
    Returns:
      vec3 (m): the pushed point (p itself when nothing was in reach)
      float (m): p's distance from the surface, negative inside; max_dist when nothing was in reach
    """
    q = wp.mesh_query_point_sign_normal(mesh, p, max_dist)
    if not q.result:
        return p, max_dist
    cp = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
    n = wp.mesh_eval_face_normal(mesh, q.face)
    d = p - cp
    dist = wp.length(d)
    if q.sign < 0.0:
        return cp + n * margin, -dist
    if dist < margin:
        if dist > 1.0e-9:
            return cp + d * (margin / dist), dist
        return cp + n * margin, dist
    return p, dist


@wp.func
def closest_on_triangle(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3):
    """Barycentric weights of the point of triangle abc closest to p (Ericson, RTCD §5.1.5).

    Inputs:
      p (vec3, m): query point
      a (vec3, m): corner 0
      b (vec3, m): corner 1
      c (vec3, m): corner 2
    Returns:
      vec3: weights of a, b, c (non-negative, summing to 1)
    """
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    if d1 <= 0.0 and d2 <= 0.0:
        return wp.vec3(1.0, 0.0, 0.0)
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= 0.0 and d4 <= d3:
        return wp.vec3(0.0, 1.0, 0.0)
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        t = d1 / (d1 - d3)
        return wp.vec3(1.0 - t, t, 0.0)
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= 0.0 and d5 <= d6:
        return wp.vec3(0.0, 0.0, 1.0)
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        t = d2 / (d2 - d6)
        return wp.vec3(1.0 - t, 0.0, t)
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return wp.vec3(0.0, 1.0 - t, t)
    denom = 1.0 / (va + vb + vc)
    return wp.vec3(va * denom, vb * denom, vc * denom)


@wp.func
def corner_angle(at: wp.vec3, b: wp.vec3, c: wp.vec3):
    """The angle of a triangle at one corner.

    Inputs:
      at (vec3, m): the corner
      b (vec3, m): another corner
      c (vec3, m): the third corner
    Returns:
      float (radians): the angle between the edges to b and to c
    """
    return wp.acos(wp.clamp(wp.dot(wp.normalize(b - at), wp.normalize(c - at)), -1.0, 1.0))


@wp.func
def pseudo_normal_weight(q: wp.vec3, w: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3, tie: float):
    """The weight of a triangle's normal in the angle-weighted pseudo-normal (Baerentzen and Aanaes)
    at a point of the triangle: its angle at a corner, pi on an edge, 2 pi inside.

    Inputs:
      q (vec3, m): the point, the triangle's closest point to some query
      w (vec3): q's barycentric weights of a, b, c
      a (vec3, m): corner 0
      b (vec3, m): corner 1
      c (vec3, m): corner 2
      tie (float, m): a point this close to a corner is at it
    Returns:
      float (radians): the weight
    """
    if wp.length(q - a) < tie:
        return corner_angle(a, b, c)
    if wp.length(q - b) < tie:
        return corner_angle(b, c, a)
    if wp.length(q - c) < tie:
        return corner_angle(c, a, b)
    if w[0] * w[1] * w[2] == 0.0:
        return wp.pi
    return 2.0 * wp.pi


@wp.func
def keep_nearest(d: float, i: int, b0: float, b1: float, b2: float, b3: float, i0: int, i1: int, i2: int, i3: int):
    """Insert item i at distance d into the five nearest so far, after the equally near ones: one bubble
    pass down. Call only when d < b4; the five are kept in named registers (an indexed vector lives
    in memory), and the fifth's item is never needed.

    Inputs:
      d (float, m): the new item's distance
      i (int, index): the new item
      b0 (float, m): the nearest distance so far
      b1 (float, m): the second nearest
      b2 (float, m): the third nearest
      b3 (float, m): the fourth nearest (the fifth, b4, is replaced)
      i0 (int, index): the nearest item so far, -1 for none
      i1 (int, index): the second nearest
      i2 (int, index): the third nearest
      i3 (int, index): the fourth nearest
    Returns:
      float, float, float, float, float, int, int, int, int: the new b0 .. b4 and i0 .. i3
    """
    b4 = d
    if b3 > d:
        b4 = b3
        b3, i3 = d, i
        if b2 > d:
            b3, i3 = b2, i2
            b2, i2 = d, i
            if b1 > d:
                b2, i2 = b1, i1
                b1, i1 = d, i
                if b0 > d:
                    b1, i1 = b0, i0
                    b0, i0 = d, i
    return b0, b1, b2, b3, b4, i0, i1, i2, i3


@wp.func
def ascending(listed: wp.vec4i):
    """The four listed items in ascending order, missing ones (-1) last.

    Inputs:
      listed (vec4i): items (indices), -1 for missing ones
    Returns:
      vec4i: the same items, ascending, the missing ones last
    """
    for a in range(1, 4):
        b = a
        while b > 0 and (listed[b - 1] < 0 or (listed[b] >= 0 and listed[b] < listed[b - 1])):
            t = listed[b]
            listed[b] = listed[b - 1]
            listed[b - 1] = t
            b -= 1
    return listed


@wp.func
def mesh_face_distance(p: wp.vec3, points: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32), f: int):
    """Distance from p to face f of an indexed mesh, and the face's closest point; a sliver (no
    trustworthy normal, skipped by Warp's queries too) is reported 1e30 away.

    Inputs:
      p (vec3, m): the point
      points (vec3, per vertex, m): mesh vertices
      indices (int32, 3 per face): mesh faces
      f (int, index): the face
    Returns:
      float (m): the distance, 1e30 for a sliver
      vec3 (m): the closest point of the face
      vec3: the closest point's barycentric weights of the face's corners
    """
    a = points[indices[3 * f + 0]]
    b = points[indices[3 * f + 1]]
    c = points[indices[3 * f + 2]]
    e0 = b - a
    e1 = c - a
    e2 = c - b
    w = closest_on_triangle(p, a, b, c)
    q = w[0] * a + w[1] * b + w[2] * c
    d = wp.length(p - q)
    n = wp.cross(e0, e1)
    size = 1.0e-6 * (wp.dot(e0, e0) + wp.dot(e1, e1) + wp.dot(e2, e2))
    if wp.dot(n, n) < size * size:
        d = 1.0e30
    return d, q, w


@wp.func
def mesh_nearest_faces(p: wp.vec3, mesh: wp.uint64, radius: float):
    """The four faces of a mesh nearest p within radius, and the distance of the fifth nearest.

    Inputs:
      p (vec3, m): the point
      mesh (uint64): wp.Mesh id, its BVH refitted to the pose
      radius (float, m): how far to look
    Returns:
      vec4i: the four nearest faces in ascending face order, -1 for missing ones (fewer than four
          within radius)
      float (m): the fifth nearest face's distance, or radius; every unlisted face is at least
          this far from p
    """
    m = wp.mesh_get(mesh)
    # the five best so far, ascending, in named registers as sphere_tree_nearest keeps them
    b0, b1, b2, b3, b4 = float(radius), float(radius), float(radius), float(radius), float(radius)
    i0, i1, i2, i3 = int(-1), int(-1), int(-1), int(-1)
    query = wp.mesh_query_aabb(mesh, p - wp.vec3(radius), p + wp.vec3(radius))
    f = int(0)
    while wp.mesh_query_aabb_next(query, f):
        d, _q, _w = mesh_face_distance(p, m.points, m.indices, f)
        if d < b4:
            b0, b1, b2, b3, b4, i0, i1, i2, i3 = keep_nearest(d, f, b0, b1, b2, b3, i0, i1, i2, i3)
    # ascending face order, so that every list holding the same faces visits them in the same order
    return ascending(wp.vec4i(i0, i1, i2, i3)), b4


@wp.func(inline=False)
def listed_faces_push_out(p: wp.vec3, mesh: wp.uint64, margin: float, search: float, faces: wp.vec4i,
                          beyond: float):
    """mesh_push_out over listed faces only, where they decide it.

    The nearest listed face is the mesh's nearest when every unlisted face is farther (beyond) than
    it by more than MESH_TIE; the faces sharing the nearest point are then all listed too, and the
    angle-weighted pseudo-normal of Baerentzen and Aanaes over them signs the distance, as
    wp.mesh_query_point_sign_normal signs it. The answer depends only on those faces, taken in
    ascending order, so any list that decides gives the same one bit for bit.

    Inputs:
      p (vec3, m): the point
      mesh (uint64): wp.Mesh id, its BVH refitted to the pose (only its points and faces are read)
      margin (float, m): distance kept outside the surface
      search (float, m): query radius: a surface farther than this is not seen
      faces (vec4i): the listed faces, ascending, -1 for none (mesh_nearest_faces)
      beyond (float, m): lower bound of p's distance from every unlisted face
    Returns:
      vec3 (m): the pushed point (p itself when nothing is within search)
      float (m): p's signed distance from the surface, negative inside; search when nothing is within it.
          When the faces did not decide: the nearest listed face's distance (capped at search), an
          upper bound of p's distance from the surface
      bool: whether the listed faces decided
    """
    m = wp.mesh_get(mesh)
    best = search
    nearest = int(-1)
    closest = wp.vec3(0.0)
    weights = wp.vec3(0.0)
    distances = wp.vec4(1.0e30)
    for k in range(4):
        f = faces[k]
        if f >= 0:
            d, q, w = mesh_face_distance(p, m.points, m.indices, f)
            distances[k] = d
            if d < best:  # ascending faces: of equally near ones the first stays
                best = d
                nearest = f
                closest = q
                weights = w
    if beyond <= best + MESH_TIE:
        return p, best, False  # an unlisted face may be as near
    if nearest < 0:
        return p, search, True
    # the faces sharing the nearest point sign it by their angle-weighted normals
    weighted = wp.vec3(0.0)
    for k in range(4):
        f = faces[k]
        if distances[k] < best + MESH_TIE:
            q = closest  # the nearest face's, from the loop above
            w = weights
            if f != nearest:
                _d, q, w = mesh_face_distance(p, m.points, m.indices, f)
            a = m.points[m.indices[3 * f + 0]]
            b = m.points[m.indices[3 * f + 1]]
            c = m.points[m.indices[3 * f + 2]]
            weighted += pseudo_normal_weight(q, w, a, b, c, MESH_TIE) * wp.normalize(wp.cross(b - a, c - a))
    a = m.points[m.indices[3 * nearest + 0]]
    n = wp.normalize(wp.cross(m.points[m.indices[3 * nearest + 1]] - a, m.points[m.indices[3 * nearest + 2]] - a))
    away = p - closest
    if wp.dot(weighted, away) <= 0.0:
        return closest + n * margin, -best, True
    if best < margin:
        if best > 1.0e-9:
            return closest + away * (margin / best), best, True
        return closest + n * margin, best, True
    return p, best, True


# not inlined, nor listed_faces_push_out: the length pass's serial loop (follow_leader) is capped at
# 128 registers on a GPU, and the lists inlined there doubled its spills in every collision mode
# (sm_90: 396 / 592 bytes stored / loaded without the lists, 1012 / 1472 inlined, 604 / 644 not)
@wp.func(inline=False)
def collide_point_listed_mesh(p: wp.vec3, mesh: wp.uint64, margin: float, search: float, limit: float,
                              faces: wp.vec4i, origin: wp.vec3, beyond: float):
    """collide_point_bounded for the mesh, through a list of the faces near the point.

    Resting contact queries the mesh every step; the four faces nearest the point and a bound on
    all others (mesh_nearest_faces) answer those queries instead, a few triangle tests, for as
    long as beyond - |p - origin| keeps the nearest listed face the nearest. Otherwise the list is
    gathered again at p (out to MESH_LIST_SLACK beyond the nearest listed face, at most limit), and
    where even a fresh list cannot decide (five or more faces equally near, or none within a search
    as far as limit) the BVH query answers. Which of the two answers a point gets
    depends only on the point, never on the list it came with, so skipping queries changes nothing.

    Inputs:
      p (vec3, m): the point
      mesh (uint64): wp.Mesh id, its BVH refitted to the pose
      margin (float, m): distance kept outside the surface
      search (float, m): query radius: a surface farther than this is not seen
      limit (float, m): the farthest a list may reach, at least search: the distance within which
          the caller bounds the collider's motion
      faces (vec4i): the list, ascending, -1 for none
      origin (vec3, m): where beyond holds
      beyond (float, m): lower bound of the distance from origin to every unlisted face (NO_BOUND
          or any negative value: no list)
    Returns:
      vec3 (m): the resolved point, as mesh_push_out resolves it
      float (m): p's signed distance, capped at search (mesh_push_out's)
      vec4i: the list after the call
      vec3 (m): where the returned beyond holds
      float (m): the returned list's beyond
    """
    pushed, distance, decided = listed_faces_push_out(p, mesh, margin, search, faces, beyond - wp.length(p - origin))
    if decided:
        return pushed, distance, faces, origin, beyond
    # the surface is no farther than the nearest listed face: a gathering that far (and the slack)
    # holds the nearest faces, and costs less than one as far as the query. It looks no farther than
    # limit: beyond it the caller does not follow the collider's motion, so a bound there would not hold
    listed, fifth = mesh_nearest_faces(p, mesh, wp.min(distance + MESH_LIST_SLACK, limit))
    pushed, distance, decided = listed_faces_push_out(p, mesh, margin, search, listed, fifth)
    if not decided:
        pushed, distance = mesh_push_out(p, mesh, margin, search)
    return pushed, distance, listed, p, fifth


@wp.func
def sphere_tree_clearance(p: wp.vec3, shape: ColliderShape, search: float):
    """Distance from p to the nearest leaf sphere's surface (negative inside one), capped at search.

    Branch and bound: a node's sphere bounds its leaves' spheres, so a node no nearer than the best
    leaf so far cannot hold a nearer one.

    Inputs:
      p (vec3, m): the point
      shape (ColliderShape): the collider; only its sphere tree is read
      search (float, m): the cap; nodes farther than this are not entered
    Returns:
      float (m): min over the leaves of |p - centre| - radius, or search when that is larger
    """
    best = search
    n = shape.spheres.shape[0]
    i = int(0)
    while i < n:
        s = shape.spheres[i]
        link = shape.links[i]
        d = wp.length(p - sphere_center(s)) - s[3]
        if d < best:
            if link < 0:
                best = d
                i = link & SPHERE_SKIP
            else:
                i = i + 1
        else:
            i = link & SPHERE_SKIP
    return best


@wp.func
def sphere_tree_nearest(p: wp.vec3, shape: ColliderShape, search: float):
    """The four leaf spheres nearest p, and the distances of the nearest and of the fifth nearest.

    Branch and bound on the fifth-best distance so far; distances are |p - centre| - radius, capped
    at search. The nearest distance is the one sphere_tree_clearance returns.

    Inputs:
      p (vec3, m): the point
      shape (ColliderShape): the collider; only its sphere tree is read
      search (float, m): the cap; nodes farther than this are not entered
    Returns:
      vec4i: the four nearest leaves' node indices in ascending order, -1 for missing ones (fewer
          than four leaves within search)
      float (m): the nearest leaf's distance, or search when that is larger
      float (m): the fifth nearest leaf's distance, or search; every unlisted leaf is at least this far
    """
    # the five best so far, ascending; kept in named registers (an indexed vector lives in memory);
    # float() makes each its own variable, not another name for search
    b0, b1, b2, b3, b4 = float(search), float(search), float(search), float(search), float(search)
    i0, i1, i2, i3 = int(-1), int(-1), int(-1), int(-1)  # the fifth's node is never needed
    n = shape.spheres.shape[0]
    i = int(0)
    while i < n:
        s = shape.spheres[i]
        link = shape.links[i]
        e = p - sphere_center(s)
        r = s[3]
        reach = b4 + r
        # a node is entered, or a leaf tested, on its squared distance, without the square root; the
        # margin takes every node the exact distance would (and a few more, which change nothing)
        near = reach > 0.0 and wp.dot(e, e) < reach * reach * 1.0001
        leaf = link < 0
        if near and leaf:
            d = wp.length(e) - r
            if d < b4:
                b0, b1, b2, b3, b4, i0, i1, i2, i3 = keep_nearest(d, i, b0, b1, b2, b3, i0, i1, i2, i3)
        # the next node without a branch: the walk's turns are too irregular to predict
        i = wp.where(near and not leaf, i + 1, link & SPHERE_SKIP)
    # ascending node order, the order in which a sweep of the tree meets them
    return ascending(wp.vec4i(i0, i1, i2, i3)), b0, b4


@wp.func
def listed_spheres_push_out(p: wp.vec3, shape: ColliderShape, margin: float, leaves: wp.vec4i, origin: wp.vec3,
                            beyond: float, zone: float):
    """collide_point for the sphere tree (two sweeps) over the listed leaves only.

    Unlisted leaves are at least beyond - |q - origin| from any point q; while that stays above
    margin at every point the sweeps pass, the tree's sweeps would push out of the same leaves in
    the same (ascending) order, so the result is theirs bit for bit. With zone below margin the
    sweeps go on while it stays above zone (above zero: no unlisted leaf contains the point, the
    loose lists' test, collide_point_listed_loose).

    Inputs:
      p (vec3, m): the point
      shape (ColliderShape): the collider; only its sphere tree is read
      margin (float, m): distance kept outside the leaf spheres
      leaves (vec4i): leaf node indices in ascending order, -1 for none (sphere_tree_nearest)
      origin (vec3, m): where beyond holds
      beyond (float, m): lower bound of the distance from origin to every unlisted leaf
      zone (float, m): the sweeps stop where a point they pass comes within this of an unlisted
          leaf: margin + 1e-5 for the tree's answer
    Returns:
      vec3 (m): the pushed point
      bool: false when a point the sweeps passed came within zone of an unlisted leaf (with zone
          above margin the result is then not the tree's)
    """
    for _sweep in range(2):
        for k in range(4):
            i = leaves[k]
            if i >= 0:
                s = shape.spheres[i]
                c = sphere_center(s)
                d = p - c
                r = s[3] + margin
                dist = wp.length(d)
                if dist < r:
                    if dist > 1.0e-9:
                        p = c + d * (r / dist)
                    else:
                        p = c + wp.vec3(0.0, r, 0.0)
                    if beyond - wp.length(p - origin) <= zone:
                        return p, False
    return p, True


@wp.func
def collide_point_listed(p: wp.vec3, shape: ColliderShape, margin: float, search: float, leaves: wp.vec4i,
                         origin: wp.vec3, beyond: float):
    """collide_point_bounded for the sphere tree, through a list of the leaves near the point.

    While beyond - |p - origin| stays above margin only the listed leaves can push p, so only they
    are tested (a few distance checks instead of a walk down the tree); otherwise, or when a push
    leaves that zone, the tree is queried and the list refilled at p. The pushed point is the
    tree's bit for bit; the distance is a lower bound of the tree's.

    Inputs:
      p (vec3, m): the point
      shape (ColliderShape): the collider; only its sphere tree is read
      margin (float, m): distance kept outside the leaf spheres
      search (float, m): cap of the distances of a tree query
      leaves (vec4i): the list (sphere_tree_nearest), ascending, -1 for none
      origin (vec3, m): where beyond holds
      beyond (float, m): lower bound of the distance from origin to every unlisted leaf
    Returns:
      vec3 (m): the resolved point
      float (m): lower bound of p's distance from the collider, capped at search after a tree query
      vec4i: the list after the call
      vec3 (m): where the returned beyond holds
      float (m): the returned list's beyond
    """
    beyond_here = beyond - wp.length(p - origin)
    if beyond_here > margin + 1.0e-5:
        distance = beyond_here
        for k in range(4):
            i = leaves[k]
            if i >= 0:
                s = shape.spheres[i]
                distance = wp.min(distance, wp.length(p - sphere_center(s)) - s[3])
        if distance > margin + 1.0e-6:
            return p, distance, leaves, origin, beyond
        pushed, kept = listed_spheres_push_out(p, shape, margin, leaves, origin, beyond, margin + 1.0e-5)
        if kept:
            return pushed, distance, leaves, origin, beyond
    listed, nearest, fifth = sphere_tree_nearest(p, shape, search)
    if nearest > margin + 1.0e-6:
        return p, nearest, listed, p, fifth
    # the fresh list usually serves the push too, without the tree's two sweeps
    pushed, kept = listed_spheres_push_out(p, shape, margin, listed, p, fifth, margin + 1.0e-5)
    if kept:
        return pushed, nearest, listed, p, fifth
    return collide_point(p, COLLIDE_SPHERE_TREE, shape, margin, search), nearest, listed, p, fifth


@wp.func
def collide_point_listed_loose(p: wp.vec3, shape: ColliderShape, margin: float, search: float, leaves: wp.vec4i,
                               origin: wp.vec3, beyond: float):
    """collide_point_listed that walks the tree only where p may be inside a leaf its list does not
    hold, not wherever one may be within margin of it: the margin to unlisted leaves is left for later.

    For a length pass on a GPU, where a walk down the tree keeps the other 31 strands of a warp
    waiting. While beyond - |p - origin| stays above zero no unlisted leaf contains p, so the listed
    leaves push it (a push whose sweeps pass a point an unlisted leaf may contain walks, as in
    collide_point_listed); the distance returned is then at most that bound, below margin, so the
    caller's next lists, made ahead of its pass in parallel (strands.find_short_lists,
    list_leaves_ahead), list p afresh and the next pass restores the margin.

    Inputs:
      p (vec3, m): the point
      shape (ColliderShape): the collider; only its sphere tree is read
      margin (float, m): distance kept outside the leaf spheres
      search (float, m): cap of the distances of a tree query
      leaves (vec4i): the list (sphere_tree_nearest), ascending, -1 for none
      origin (vec3, m): where beyond holds
      beyond (float, m): lower bound of the distance from origin to every unlisted leaf
    Returns:
      vec3 (m): the resolved point
      float (m): lower bound of p's distance from the collider (before a push by the listed leaves)
      vec4i: the list after the call (refilled only by a walk)
      vec3 (m): where the returned beyond holds
      float (m): the returned list's beyond
    """
    distance = beyond - wp.length(p - origin)
    walk = distance <= 0.0
    pushed = p
    if not walk:
        # collide_point_listed's loop, not a shared function: one spilled more registers in step_strands
        # (sm_90: 964/1056 -> 1004/1064 bytes)
        for k in range(4):
            i = leaves[k]
            if i >= 0:
                s = shape.spheres[i]
                distance = wp.min(distance, wp.length(p - sphere_center(s)) - s[3])
        if distance > margin + 1.0e-6:
            return p, distance, leaves, origin, beyond
        pushed, kept = listed_spheres_push_out(p, shape, margin, leaves, origin, beyond, 0.0)
        walk = not kept
    if walk:  # one call site: the walk's code compiled in once
        return collide_point_listed(p, shape, margin, search, leaves, origin, beyond)
    return pushed, distance, leaves, origin, beyond


@wp.func
def collide_point(p: wp.vec3, mode: int, shape: ColliderShape, margin: float, search: float):
    """Resolve one point against the collider with the chosen representation.

    Inputs:
      p (vec3, m): the point
      mode (int): COLLIDE_NONE, COLLIDE_SPHERE_TREE or COLLIDE_MESH
      shape (ColliderShape): the collider
      margin (float, m): distance kept outside the collider
      search (float, m): mesh query radius; bounds the query's cost and the deepest penetration seen
    Returns:
      vec3 (m): the resolved point
    """
    if mode == COLLIDE_SPHERE_TREE:
        # two sweeps: a push out of one leaf can land inside a neighbour visited earlier
        p = sphere_tree_push_out(p, shape, margin)
        p = sphere_tree_push_out(p, shape, margin)
    elif mode == COLLIDE_MESH:
        p, _distance = mesh_push_out(p, shape.mesh, margin, search)
    return p


@wp.func
def collide_point_bounded(p: wp.vec3, mode: int, shape: ColliderShape, margin: float, search: float):
    """collide_point(), and how far p is from the collider: the bound that lets a caller skip p's
    next queries while p and the collider have moved less than that distance minus margin.

    Mesh: one query gives both, the push and p's signed distance when the surface is within search;
    beyond, search (the sign is not known there: a point deeper than search inside is not seen,
    as collide_point does not see it). Sphere tree: the nearest leaf's distance, capped at search,
    and the push sweeps only when it is within margin, where collide_point would push.

    Inputs:
      p (vec3, m): the point
      mode (int): COLLIDE_NONE, COLLIDE_SPHERE_TREE or COLLIDE_MESH
      shape (ColliderShape): the collider
      margin (float, m): distance kept outside the collider
      search (float, m): mesh query radius, and the cap of the distance returned
    Returns:
      vec3 (m): the resolved point, as collide_point() resolves it
      float (m): p's distance from the collider (negative inside), capped at search; 1e30 for
          COLLIDE_NONE
    """
    if mode == COLLIDE_MESH:
        return mesh_push_out(p, shape.mesh, margin, search)
    if mode == COLLIDE_SPHERE_TREE:
        distance = sphere_tree_clearance(p, shape, search)
        # push_out pushes within margin of a leaf; the tolerance keeps rounding from skipping a push
        if distance > margin + 1.0e-6:
            return p, distance
        return collide_point(p, mode, shape, margin, search), distance
    return p, 1.0e30


@wp.kernel
def points_clearance(
    points: wp.array(dtype=wp.vec3),
    mode: int,
    shape: ColliderShape,
    margin: float,
    search: float,
    out: wp.array(dtype=float),
):
    """The distance collide_point_bounded() reports for every point, in parallel.

    Launch: one thread per point (dim = len(points)).
    Inputs:
      points (vec3, per point, m): positions
      mode (int): COLLIDE_NONE, COLLIDE_SPHERE_TREE or COLLIDE_MESH
      shape (ColliderShape): the collider
      margin (float, m): distance kept outside the collider
      search (float, m): mesh query radius and cap of the distance
    Outputs:
      out (float, per point, m): each point's distance from the collider, negative inside, capped
          at search
    """
    i = wp.tid()
    _pushed, distance = collide_point_bounded(points[i], mode, shape, margin, search)
    out[i] = distance


@wp.kernel
def push_points_out(
    points: wp.array(dtype=wp.vec3),
    mode: int,
    shape: ColliderShape,
    margin: float,
    search: float,
):
    """collide_point() on every point, in place: a host-side push-out, e.g. while grooming.

    Launch: one thread per point (dim = len(points)).
    Inputs:
      mode (int): COLLIDE_NONE, COLLIDE_SPHERE_TREE or COLLIDE_MESH
      shape (ColliderShape): the collider
      margin (float, m): distance kept outside the collider
      search (float, m): mesh query radius; deeper penetrations are not seen
    In/out:
      points (vec3, per point, m): positions, pushed out of the collider
    """
    i = wp.tid()
    points[i] = collide_point(points[i], mode, shape, margin, search)


@wp.kernel
def mesh_signed_distance(
    points: wp.array(dtype=wp.vec3),
    mesh: wp.uint64,
    max_dist: float,
    winding: int,
    distance: wp.array(dtype=float),
    closest: wp.array(dtype=wp.vec3),
):
    """Signed distance of every point to a closed mesh (negative inside) and its closest surface point.

    The sign comes from the closest face's pseudo-normal, or with winding != 0 from the generalized
    winding number: slower, but right also where the closest point is ambiguous (the centre of a
    sphere, deep inside a limb), where the normal's sign can flip.

    Launch: one thread per point (dim = len(points)).
    Inputs:
      points (vec3, per point, m): query points
      mesh (uint64): wp.Mesh id of a closed, outward-wound mesh (built with support_winding_number
          when winding != 0)
      max_dist (float, m): query radius
      winding (int, flag): non-zero signs by the winding number
    Outputs:
      distance (float, per point, m): signed distance; max_dist where no surface is within reach
      closest (vec3, per point, m): closest surface point; the point itself where none is within reach
    """
    i = wp.tid()
    p = points[i]
    if winding != 0:
        q = wp.mesh_query_point_sign_winding_number(mesh, p, max_dist)
    else:
        q = wp.mesh_query_point_sign_normal(mesh, p, max_dist)
    if q.result:
        cp = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
        closest[i] = cp
        distance[i] = q.sign * wp.length(p - cp)
    else:
        closest[i] = p
        distance[i] = max_dist


@wp.func
def pseudo_normal_distance(mesh: wp.uint64, p: wp.vec3, max_dist: float):
    """Signed distance of p to a closed mesh, signed by the closest face's pseudo-normal: the
    distance mesh_signed_distance gives with winding = 0.

    Inputs:
      mesh (uint64): wp.Mesh id of a closed, outward-wound mesh
      p (vec3, m): the point
      max_dist (float, m): query radius
    Returns:
      float (m): signed distance, negative inside; max_dist where no surface is within reach
    """
    q = wp.mesh_query_point_sign_normal(mesh, p, max_dist)
    if q.result:
        return q.sign * wp.length(p - wp.mesh_eval_position(mesh, q.face, q.u, q.v))
    return max_dist


@wp.func
def list_deep_point(distance: float, depth: float, i: int, part: int, count: wp.array2d(dtype=wp.int32),
                    listed: wp.array2d(dtype=wp.int32)):
    """Count point i when it lies deeper inside than depth, and list it while the list has room.
    Launches that run side by side on the CPU's cores (sim.graphs.launch_on_cores) each count and list
    in their own row: a CPU's atomics are not atomic across launches.

    Inputs:
      distance (float, m): the point's signed distance (negative inside)
      depth (float, m): how deep a point must lie to count
      i (int, index): the point
      part (int, index): the launch's row
    In/out:
      count (int32, rows * 1): points counted so far per row (may exceed the list's length)
    Outputs:
      listed (int32, rows * any length): the first points each row counted, in any order
    """
    if distance < -depth:
        slot = wp.atomic_add(count, part, 0, 1)
        if slot < listed.shape[1]:
            listed[part, slot] = i


@wp.kernel
def count_deep_points(
    points: wp.array(dtype=wp.vec3),
    first: int,
    part: int,
    mesh: wp.uint64,
    max_dist: float,
    depth: float,
    count: wp.array2d(dtype=wp.int32),
    listed: wp.array2d(dtype=wp.int32),
):
    """Count and list the points the closest face's pseudo-normal puts deeper inside a closed mesh
    than depth (a quality statistic: the host re-signs the listed ones by the winding number).

    Launch: one thread per point from first (dim = points counted, first + dim <= len(points)).
    Inputs:
      points (vec3, per point, m): the points
      first (int, index): the first point of the launch
      part (int, index): the launch's row of count and listed
      mesh (uint64): wp.Mesh id of a closed, outward-wound mesh
      max_dist (float, m): query radius: deeper points are not seen
      depth (float, m): how deep a point must lie to count
    In/out:
      count (int32, rows * 1): points counted (zero it first)
    Outputs:
      listed (int32, rows * any length): the first points counted (list_deep_point)
    """
    i = wp.tid() + first
    list_deep_point(pseudo_normal_distance(mesh, points[i], max_dist), depth, i, part, count, listed)


@wp.kernel
def visible_from_eye(
    points: wp.array(dtype=wp.vec3),
    mesh: wp.uint64,
    eye: wp.vec3,
    tolerance: float,
    visible: wp.array(dtype=wp.int32),
):
    """Whether each point can be seen from a pinhole camera at `eye`, with the mesh as the occluder.

    Grooming tools act only on what the artist sees: a strand behind the head must not be combed or
    cut by a stroke drawn over the face. Points on or just outside the surface (roots) count as
    visible through `tolerance`.

    Launch: one thread per point (dim = len(points)).
    Inputs:
      points (vec3, per point, m): query points, e.g. hair particles
      mesh (uint64): wp.Mesh id of the occluder (the collider)
      eye (vec3, m): the camera's centre
      tolerance (float, m): hits this close to the point do not hide it
    Outputs:
      visible (int32, per point): 1 where the segment from the eye to the point misses the mesh, else 0
    """
    i = wp.tid()
    to_point = points[i] - eye
    distance = wp.length(to_point)
    visible[i] = 1
    if distance > tolerance:
        q = wp.mesh_query_ray(mesh, eye, to_point / distance, distance - tolerance)
        if q.result:
            visible[i] = 0


@wp.kernel
def first_ray_hits(
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    mesh: wp.uint64,
    max_t: float,
    hit_t: wp.array(dtype=float),
):
    """Where each ray first meets the mesh: a camera's pixel rays onto the head place a comb.

    Launch: one thread per ray (dim = len(origins)).
    Inputs:
      origins (vec3, per ray, m): ray starts
      directions (vec3, per ray): unit directions
      mesh (uint64): wp.Mesh id of the surface
      max_t (float, m): farthest hit looked for
    Outputs:
      hit_t (float, per ray, m): distance along the ray to the first hit, -1 where it misses
    """
    i = wp.tid()
    q = wp.mesh_query_ray(mesh, origins[i], directions[i], max_t)
    hit_t[i] = -1.0
    if q.result:
        hit_t[i] = q.t


@wp.kernel
def sphere_tree_penetration(points: wp.array(dtype=wp.vec3), shape: ColliderShape, depth: wp.array(dtype=float)):
    """sphere_tree_depth() of every point: how deep each lies inside the sphere tree's leaves.

    Launch: one thread per point (dim = len(points)).
    Inputs:
      points (vec3, per point, m): query points
      shape (ColliderShape): the collider; only its sphere tree is read
    Outputs:
      depth (float, per point, m): deepest penetration, 0 when outside every leaf
    """
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
    """Closest triangle of a mesh and the barycentric weights of the closest point, for bindings.

    The result feeds skinning.compute_bindings: a point bound this way rides the triangle.

    Launch: one thread per point (dim = len(points)).
    Inputs:
      points (vec3, per point, m): query points
      mesh (uint64): wp.Mesh id
      max_dist (float, m): query radius
    Outputs:
      face (int32, per point): closest triangle, -1 when none is within max_dist
      barycentric (vec3, per point): weights of the triangle's vertices 0, 1, 2; zero when none
    """
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
    """First half of refit_sphere_tree: inner nodes start from radius 0.

    A separate launch, because refit_sphere_tree grows radii with atomic max from many threads and
    needs every inner radius reset before any thread starts.

    Launch: one thread per tree node (dim = num_nodes).
    Inputs:
      is_leaf (int32, per tree node): 1 for leaves, 0 for inner nodes
    In/out:
      radii (float, per tree node, m): inner radii set to 0, leaf radii kept
    """
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
    """Grow each inner node to bound the leaves of its subtree after the centres were skinned.

    Every leaf raises each ancestor's radius to reach past it (atomic max). One thread per leaf and a
    walk up the tree, rather than one thread per node scanning its subtree, whose root thread alone
    would read the whole tree. Run clear_inner_radii first.

    Launch: one thread per tree node (dim = num_nodes); inner nodes' threads return at once.
    Inputs:
      centers (vec3, per tree node, m): posed node centres
      parent (int32, per tree node): parent node, -1 for the root
      is_leaf (int32, per tree node): 1 for leaves, 0 for inner nodes
    In/out:
      radii (float, per tree node, m): leaf radii read; inner radii grown to bound their leaves
    """
    j = wp.tid()
    if is_leaf[j] != 0:
        grow_ancestors(centers, radii, parent, j)


@wp.func
def grow_ancestors(centers: wp.array(dtype=wp.vec3), radii: wp.array(dtype=float), parent: wp.array(dtype=wp.int32),
                   j: int):
    """Raise every ancestor of leaf j to reach past it (refit_sphere_tree's walk up the tree).

    Inputs:
      centers (vec3, per tree node, m): posed node centres
      parent (int32, per tree node): parent node, -1 for the root
      j (int, index): a leaf
    In/out:
      radii (float, per tree node, m): the leaf's radius read; its ancestors' raised (atomic max)
    Returns:
      nothing: the radii are raised in place
    """
    c = centers[j]
    r = radii[j]
    a = parent[j]
    while a >= 0:
        wp.atomic_max(radii, a, wp.length(c - centers[a]) + r)
        a = parent[a]


@wp.kernel
def pack_sphere_tree(centers: wp.array(dtype=wp.vec3), radii: wp.array(dtype=float), spheres: wp.array(dtype=wp.vec4)):
    """Last step of a refit (after refit_sphere_tree): each node's centre and radius side by side,
    as the walks read them (ColliderShape.spheres).

    Launch: one thread per tree node (dim = num_nodes).
    Inputs:
      centers (vec3, per tree node, m): posed node centres
      radii (float, per tree node, m): refitted radii
    Outputs:
      spheres (vec4, per tree node, m): centre (x, y, z) and radius (w)
    """
    i = wp.tid()
    c = centers[i]
    spheres[i] = wp.vec4(c[0], c[1], c[2], radii[i])


@wp.kernel
def largest_displacement(
    before: wp.array(dtype=wp.vec3),
    after: wp.array(dtype=wp.vec3),
    count: int,
    threads: int,
    moved: wp.array(dtype=float),
):
    """The largest distance any point moved, for bounds on how far a surface moved (sim.Collider.moved).

    Each thread takes the largest move of the points a stride of `threads` apart, then raises moved
    only if that beats the maximum so far: a GPU's float atomic maximum is a compare-and-swap loop,
    which a thread per point on one address retried in turn (an H100 spent 24 us a launch on the
    walking body), and fewer threads, most of which skip it, ask far fewer times.

    Launch: one thread per stride of the points (dim = threads, at most count).
    Inputs:
      before (vec3, per point, m): positions before the move
      after (vec3, per point, m): and after it
      count (int): points
      threads (int): threads launched
    In/out:
      moved (float, 1 element, m): raised to the largest |after - before|; zero it first
    """
    i = wp.tid()
    d = float(0.0)
    while i < count:
        d = wp.max(d, wp.length(after[i] - before[i]))
        i += threads
    if d > moved[0]:
        wp.atomic_max(moved, 0, d)


@wp.kernel
def sweep_poses(
    skinned: int,
    rest_points: wp.array(dtype=wp.vec3),
    skin_indices: wp.array(dtype=wp.vec4i),
    skin_weights: wp.array(dtype=wp.vec4),
    bone_matrices: wp.array(dtype=wp.mat44),
    num_bones: int,
    num_points: int,
    num_poses: int,
    poses: wp.array(dtype=wp.vec3),
    lower: wp.array(dtype=wp.vec3),
    upper: wp.array(dtype=wp.vec3),
    moved: wp.array(dtype=float),
    first: int,
    part: int,
):
    """Each point's bounding box over a run of poses, and how far the points moved into each pose;
    the poses skinned here (skinning.skin_points for every pose at once) or given.

    A range of the points may be swept on its own (one per CPU core, sim.Collider.sweep): each range
    raises a row of moved of its own, since a CPU's atomics are not atomic across launches running
    at once, and largest_of_rows takes the largest over the rows.

    Launch: one thread per point of a range (dim = points in the range).
    Inputs:
      skinned (int, flag): non-zero skins the poses of bone_matrices into poses; zero reads poses
      rest_points (vec3, per point, m): points in the bind pose (skinned; may be None otherwise)
      skin_indices (vec4i, per point): bone of each influence, within one pose (skinned)
      skin_weights (vec4, per point): weight of each influence; 0 skips it (skinned)
      bone_matrices (mat44, num_poses * num_bones, m): per pose and bone, bind pose to posed (skinned)
      num_bones (int): matrices per pose
      num_points (int): points per pose
      num_poses (int): poses, at least 1
      first (int, index): the range's first point; thread t sweeps point first + t
      part (int, index): the row of moved the range raises
    In/out:
      poses (vec3, num_poses * num_points, m): the poses' points back to back: written (skinned) or
          read
      moved (float, num_poses per row, m): row `part` raised to the largest distance a point of the
          range moved from pose k - 1 to pose k (as largest_displacement); zero it first; element 0
          of a row is left as it is
    Outputs:
      lower (vec3, per point, m): each point's box over the poses, its least corner
      upper (vec3, per point, m): and its greatest
    """
    i = wp.tid() + first
    row = part * num_poses
    p = wp.vec3(0.0)
    lo = p
    hi = p
    for k in range(num_poses):
        q = wp.vec3(0.0)
        if skinned != 0:
            q = skinned_point(rest_points, skin_indices, skin_weights, bone_matrices, k * num_bones, i)
            poses[k * num_points + i] = q
        else:
            q = poses[k * num_points + i]
        if k == 0:
            lo = q
            hi = q
        else:
            d = wp.length(q - p)
            if d > moved[row + k]:  # most threads skip the atomic once a large motion is in (largest_displacement)
                wp.atomic_max(moved, row + k, d)
            lo = wp.min(lo, q)
            hi = wp.max(hi, q)
        p = q
    lower[i] = lo
    upper[i] = hi


@wp.kernel
def largest_of_rows(rows: wp.array(dtype=float), count: int, columns: int, largest: wp.array(dtype=float)):
    """The largest value of each column over rows of values (the rows of ranges swept side by side,
    sweep_poses).

    Launch: one thread per column (dim = columns).
    Inputs:
      rows (float, count * columns): the rows back to back
      count (int): rows
      columns (int): values per row
    Outputs:
      largest (float, per column): each column's largest value
    """
    k = wp.tid()
    best = rows[k]
    for r in range(1, count):
        best = wp.max(best, rows[r * columns + k])
    largest[k] = best


@wp.kernel
def triangle_bounds(
    indices: wp.array(dtype=wp.int32),
    lower: wp.array(dtype=wp.vec3),
    upper: wp.array(dtype=wp.vec3),
    triangle_lower: wp.array(dtype=wp.vec3),
    triangle_upper: wp.array(dtype=wp.vec3),
):
    """Each triangle's bounding box from its corners' boxes (points: lower = upper), for a wp.Bvh.

    Launch: one thread per triangle (dim = len(indices) // 3).
    Inputs:
      indices (int32, 3 per triangle): corners
      lower (vec3, per point, m): each point's box, its least corner
      upper (vec3, per point, m): and its greatest
    Outputs:
      triangle_lower (vec3, per triangle, m): each triangle's box, its least corner
      triangle_upper (vec3, per triangle, m): and its greatest
    """
    f = wp.tid()
    a = indices[3 * f + 0]
    b = indices[3 * f + 1]
    c = indices[3 * f + 2]
    triangle_lower[f] = wp.min(wp.min(lower[a], lower[b]), lower[c])
    triangle_upper[f] = wp.max(wp.max(upper[a], upper[b]), upper[c])
