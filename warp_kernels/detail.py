"""Curved PN triangles (Vlachos, Peters, Boyd & Mitchell 2001): the smooth detail surface that
Oshita & Makinouchi §4.1 lay over the coarse simulated garment every frame.

Each coarse triangle becomes a cubic Bezier patch for position and a quadratic one for the normal,
built from its three corners and their vertex normals only, so the patches of neighbouring triangles
meet along a shared edge curve whenever the corners share their normals. Three launches per frame:
coarse_vertex_normals (per coarse vertex), pn_coefficients (per coarse triangle), pn_evaluate (per
detail vertex).

Coefficient layout, slot 10 f + k of `control` and 6 f + k of `normal_coeffs` for triangle f:

    control:       b300 b030 b003 b210 b120 b021 b012 b102 b201 b111
    normal_coeffs: n200 n020 n002 n110 n011 n101

Index i of b_ijk goes with corner 0 (P1, weight w), j with corner 1 (P2, weight u), k with corner 2
(P3, weight v); a barycentric vec3 (w0, w1, w2) of corners 0, 1, 2 is (w, u, v).

Over the PN surface, the detail surface moves each vertex along its control direction by a height
dh (Oshita & Makinouchi eqs. 2-3): force-driven wrinkles (§4.3), lifted out of the body with a
coarse-to-fine test (§4.2), shaded with normals blended by height (§4.4). Those kernels follow below.
A frame (composed by sim.detail.ClothDetail) runs, after the three PN launches:

    relax_heights
    -> [wrinkles: cloth.elastic_forces -> carry_forces -> vertical_forces -> edge_length_deficit
        -> vertex_deficit -> faces_without_compression -> wrinkle_heights -> add_heights
        -> [smooth_heights] x passes -> constrain_heights]
    -> [lift_out_of_body per hierarchy level, coarse to fine]
    -> displace_along_directions -> surface_vertex_normals
"""

# float(0.0), int(0) and bool(False) declare variables that a kernel reassigns (Warp treats a
# bare literal as a constant); the nested ifs are kept as the kernels were written and verified
# ruff: noqa: UP018, RUF046, SIM102

import warp as wp

from ._options import MODULE_OPTIONS
from .cloth import closest_corner, least_inside_plane, walk_to_nearest_vertex

wp.set_module_options(MODULE_OPTIONS)


@wp.func
def normalize_or(v: wp.vec3, fallback: wp.vec3):
    """v / |v|, or fallback where v is too short to have a direction.

    Inputs:
      v (vec3): vector to normalize
      fallback (vec3): returned when |v| <= 1e-30
    Returns:
      vec3: unit vector (or the fallback as given)
    """
    length = wp.length(v)
    if length > 1.0e-30:
        return v / length
    return fallback


@wp.func
def pn_edge_point(pi: wp.vec3, pj: wp.vec3, ni: wp.vec3):
    """Control point b_ij next to corner i on edge ij.

    The point a third of the way to Pj, projected into the tangent plane of corner i (Vlachos et al.
    2001, §3.1: b_ij = (2 Pi + Pj - w_ij Ni) / 3, w_ij = (Pj - Pi) . Ni), so the patch leaves corner i
    tangent to its normal.

    Inputs:
      pi (vec3, m): corner i
      pj (vec3, m): corner j
      ni (vec3): unit normal at corner i
    Returns:
      vec3 (m): the control point
    """
    w = wp.dot(pj - pi, ni)
    return (2.0 * pi + pj - w * ni) / 3.0


@wp.func
def pn_edge_normal(pi: wp.vec3, pj: wp.vec3, ni: wp.vec3, nj: wp.vec3):
    """Mid-edge coefficient of the quadratic normal patch.

    The average normal reflected in the plane perpendicular to the edge (Vlachos et al. 2001, §3.2:
    n_ij = normalize(Ni + Nj - v_ij (Pj - Pi)), v_ij = 2 (Pj - Pi) . (Ni + Nj) / |Pj - Pi|^2), which
    lets the normal capture inflections a linear blend would miss. A zero-length edge has no plane to
    reflect in: v_ij = 0 there.

    Inputs:
      pi (vec3, m): corner i
      pj (vec3, m): corner j
      ni (vec3): unit normal at corner i
      nj (vec3): unit normal at corner j
    Returns:
      vec3: unit normal coefficient
    """
    d = pj - pi
    dd = wp.dot(d, d)
    v = float(0.0)
    if dd > 1.0e-30:
        v = 2.0 * wp.dot(d, ni + nj) / dd
    return normalize_or(ni + nj - v * d, normalize_or(ni + nj, ni))


@wp.func
def pn_triangle_coefficients(p1: wp.vec3, p2: wp.vec3, p3: wp.vec3, n1: wp.vec3, n2: wp.vec3, n3: wp.vec3,
                             f: int, control: wp.array(dtype=wp.vec3), normal_coeffs: wp.array(dtype=wp.vec3)):
    """The ten cubic control points and six quadratic normal coefficients of one PN triangle.

    Built from the three corners and their normals only, so neighbouring patches agree along a
    shared edge whenever the corners share their normals. Written to slots 10 f .. 10 f + 9 and
    6 f .. 6 f + 5 (layout in the module docstring).

    Inputs:
      p1 (vec3, m): corner 0
      p2 (vec3, m): corner 1
      p3 (vec3, m): corner 2
      n1 (vec3): unit normal at corner 0
      n2 (vec3): unit normal at corner 1
      n3 (vec3): unit normal at corner 2
      f (int, index): the triangle, which selects the output slots
    Outputs:
      control (vec3, 10 per triangle, m): cubic control points b300 .. b111
      normal_coeffs (vec3, 6 per triangle): quadratic normal coefficients n200 .. n101
    """
    b210 = pn_edge_point(p1, p2, n1)
    b120 = pn_edge_point(p2, p1, n2)
    b021 = pn_edge_point(p2, p3, n2)
    b012 = pn_edge_point(p3, p2, n3)
    b102 = pn_edge_point(p3, p1, n3)
    b201 = pn_edge_point(p1, p3, n1)
    # Vlachos et al. 2001, §3.1: the centre moves from the flat centroid V past the mean edge point E
    e = (b210 + b120 + b021 + b012 + b102 + b201) / 6.0
    c = (p1 + p2 + p3) / 3.0
    b111 = e + 0.5 * (e - c)
    o = 10 * f
    control[o + 0] = p1
    control[o + 1] = p2
    control[o + 2] = p3
    control[o + 3] = b210
    control[o + 4] = b120
    control[o + 5] = b021
    control[o + 6] = b012
    control[o + 7] = b102
    control[o + 8] = b201
    control[o + 9] = b111
    o = 6 * f
    normal_coeffs[o + 0] = n1
    normal_coeffs[o + 1] = n2
    normal_coeffs[o + 2] = n3
    normal_coeffs[o + 3] = pn_edge_normal(p1, p2, n1, n2)
    normal_coeffs[o + 4] = pn_edge_normal(p2, p3, n2, n3)
    normal_coeffs[o + 5] = pn_edge_normal(p3, p1, n3, n1)


@wp.func
def pn_point(control: wp.array(dtype=wp.vec3), f: int, bary: wp.vec3):
    """Position on the cubic Bezier patch of triangle f.

    Sum over i+j+k=3 of b_ijk 3!/(i! j! k!) w^i u^j v^k (Vlachos et al. 2001, eq. 1).

    Inputs:
      control (vec3, 10 per triangle, m): cubic control points (pn_coefficients)
      f (int, index): the triangle
      bary (vec3): weights (w, u, v) of the triangle's corners 0, 1, 2
    Returns:
      vec3 (m): the point on the patch
    """
    w = bary[0]
    u = bary[1]
    v = bary[2]
    o = 10 * f
    return (control[o + 0] * (w * w * w) + control[o + 1] * (u * u * u) + control[o + 2] * (v * v * v)
            + control[o + 3] * (3.0 * w * w * u) + control[o + 4] * (3.0 * w * u * u)
            + control[o + 5] * (3.0 * u * u * v) + control[o + 6] * (3.0 * u * v * v)
            + control[o + 7] * (3.0 * w * v * v) + control[o + 8] * (3.0 * w * w * v)
            + control[o + 9] * (6.0 * w * u * v))


@wp.func
def pn_normal(normal_coeffs: wp.array(dtype=wp.vec3), f: int, bary: wp.vec3):
    """Unit normal of the quadratic normal patch of triangle f.

    n200 w^2 + n020 u^2 + n002 v^2 + n110 w u + n011 u v + n101 w v, normalized (Vlachos et al. 2001,
    eq. 2). Where it vanishes (corner normals pointing against each other) the linearly interpolated
    corner normals stand in, then (0, 1, 0).

    Inputs:
      normal_coeffs (vec3, 6 per triangle): quadratic normal coefficients (pn_coefficients)
      f (int, index): the triangle
      bary (vec3): weights (w, u, v) of the triangle's corners 0, 1, 2
    Returns:
      vec3: unit normal
    """
    w = bary[0]
    u = bary[1]
    v = bary[2]
    o = 6 * f
    n1 = normal_coeffs[o + 0]
    n2 = normal_coeffs[o + 1]
    n3 = normal_coeffs[o + 2]
    n = (n1 * (w * w) + n2 * (u * u) + n3 * (v * v) + normal_coeffs[o + 3] * (w * u)
         + normal_coeffs[o + 4] * (u * v) + normal_coeffs[o + 5] * (w * v))
    return normalize_or(n, normalize_or(w * n1 + u * n2 + v * n3, wp.vec3(0.0, 1.0, 0.0)))


@wp.kernel
def coarse_vertex_normals(
    points: wp.array(dtype=wp.vec3),
    triangles: wp.array(dtype=wp.int32),
    vf_start: wp.array(dtype=wp.int32),
    vf_face: wp.array(dtype=wp.int32),
    normals: wp.array(dtype=wp.vec3),
):
    """Area-weighted vertex normals of the coarse mesh, gathered over the vertex -> faces CSR.

    Gathering instead of scattering needs no atomics and sums in a fixed order, so the result does
    not depend on thread scheduling. The sum
    of the face cross products (twice the area times the unit normal) is normalized. Where it has no
    reliable direction, because the incident faces have zero area or cancel (the cloth folded flat
    onto itself), the vertex keeps its previous normal, so the caller passes last frame's normals in;
    a previous value that is not a unit vector becomes (0, 1, 0).

    Launch: one thread per coarse vertex (dim = num_coarse_vertices).
    Inputs:
      points (vec3, per coarse vertex, m): coarse positions (the cloth particles)
      triangles (int32, 3 per coarse triangle): coarse triangles
      vf_start (int32, num_coarse_vertices + 1): CSR offsets of the vertex -> face adjacency
      vf_face (int32, 3 per coarse triangle): faces incident to each vertex
    In/out:
      normals (vec3, per coarse vertex): last frame's unit normals in, this frame's out
    """
    p = wp.tid()
    s = wp.vec3(0.0)
    total = float(0.0)
    for k in range(vf_start[p], vf_start[p + 1]):
        f = vf_face[k]
        a = points[triangles[3 * f + 0]]
        c = wp.cross(points[triangles[3 * f + 1]] - a, points[triangles[3 * f + 2]] - a)
        s += c
        total += wp.length(c)
    length = wp.length(s)
    if length > 1.0e-30 and length > 1.0e-6 * total:
        normals[p] = s / length
    elif not (wp.abs(wp.length_sq(normals[p]) - 1.0) < 1.0e-3):
        normals[p] = wp.vec3(0.0, 1.0, 0.0)


@wp.kernel
def pn_coefficients(
    points: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
    triangles: wp.array(dtype=wp.int32),
    control: wp.array(dtype=wp.vec3),
    normal_coeffs: wp.array(dtype=wp.vec3),
):
    """PN coefficients of every coarse triangle, the second of the three detail-surface launches.

    Launch: one thread per coarse triangle (dim = num_coarse_triangles).
    Inputs:
      points (vec3, per coarse vertex, m): coarse positions
      normals (vec3, per coarse vertex): unit vertex normals (coarse_vertex_normals)
      triangles (int32, 3 per coarse triangle): coarse triangles
    Outputs:
      control (vec3, 10 per coarse triangle, m): cubic control points
      normal_coeffs (vec3, 6 per coarse triangle): quadratic normal coefficients
    """
    f = wp.tid()
    i0 = triangles[3 * f + 0]
    i1 = triangles[3 * f + 1]
    i2 = triangles[3 * f + 2]
    pn_triangle_coefficients(points[i0], points[i1], points[i2], normals[i0], normals[i1], normals[i2], f, control,
                             normal_coeffs)


@wp.kernel
def pn_evaluate(
    control: wp.array(dtype=wp.vec3),
    normal_coeffs: wp.array(dtype=wp.vec3),
    owner_face: wp.array(dtype=wp.int32),
    bary: wp.array(dtype=wp.vec3),
    positions: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
):
    """Position and unit normal of each detail vertex on the patch of its owner face.

    A vertex on a coarse edge (or at a coarse corner) is evaluated from one owner face only, so the
    detail mesh, whose faces share such vertices by index, is watertight by construction even where
    the two patches of a seam differ (split normals); the seam then follows the owner face's curve.

    Launch: one thread per detail vertex (dim = num_detail_vertices).
    Inputs:
      control (vec3, 10 per coarse triangle, m): cubic control points
      normal_coeffs (vec3, 6 per coarse triangle): quadratic normal coefficients
      owner_face (int32, per detail vertex): coarse triangle that evaluates the vertex
      bary (vec3, per detail vertex): weights of the owner face's corners 0, 1, 2
    Outputs:
      positions (vec3, per detail vertex, m): points on the PN surface
      normals (vec3, per detail vertex): unit PN normals
    """
    i = wp.tid()
    f = owner_face[i]
    positions[i] = pn_point(control, f, bary[i])
    normals[i] = pn_normal(normal_coeffs, f, bary[i])


@wp.kernel
def lift_out_of_body(
    base: wp.array(dtype=wp.vec3),
    direction: wp.array(dtype=wp.vec3),
    vertices: wp.array(dtype=wp.int32),
    coarser: wp.array(dtype=wp.vec4i),
    mesh: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    indices: wp.array(dtype=wp.int32),
    vv_start: wp.array(dtype=wp.int32),
    vv_adj: wp.array(dtype=wp.int32),
    vf_start: wp.array(dtype=wp.int32),
    vf_face: wp.array(dtype=wp.int32),
    concave: wp.array(dtype=wp.int32),
    walk_steps: int,
    teleport: float,
    trust_distance: float,
    side: float,
    margin: float,
    reach: wp.array(dtype=float),
    height: wp.array(dtype=float),
    clearance: wp.array(dtype=float),
    body_vertex: wp.array(dtype=wp.int32),
    probe_point: wp.array(dtype=wp.vec3),
    queries: wp.array(dtype=wp.int32),
):
    """Oshita & Makinouchi §4.2 for one refinement level: raise heights so detail vertices leave the body.

    Every sample ends a level with a clearance: a lower bound of its distance outside the body. The
    distance to a surface changes no faster than the point moves, so each sample of a coarser level
    (already final) bounds this one's clearance by its own less their distance apart. The best of
    the nearest few such bounds is kept; while it stays above margin the sample cannot be inside and
    takes it untested. Most vertices are thus never tested, and no sample is skipped that could be
    inside, whatever its coarse face touches (the paper tests the faces whose particles touch; a
    face can cut the body between particles that do not). The corners (level 0,
    the coarse particles, which the coarse collision keeps outside) are always tested. Each vertex
    moves along its control direction times side. Launch the levels from coarse to fine, each after
    the last.

    A test is the coarse cloth's (body_collide, §3.3): a greedy walk over the body's vertices from
    the vertex this sample found last time (or, new to the test, that of the nearest coarser sample
    with one), then the planes of the faces around the vertex it stops at: the least-inside plane
    gives the signed distance and the direction to lift along. Where the walk is not to be trusted
    (no start, a jump farther than teleport since the last test, a walk out of steps, a concave
    vertex, a vertex farther than trust_distance) a BVH closest-point query decides instead and
    restarts the walk. Its radius is the sample's reach, widened to the margin less the best coarser
    bound (the bound limits how deep inside the sample can be), so a sample pushed deep inside
    between frames is still found, while one whose coarser samples lie well outside searches no
    farther than its reach. A walk costs a fraction of a query on a body of tens of thousands of
    triangles.

    Launch: one thread per detail vertex of this level (dim = len(vertices)).
    Inputs:
      base (vec3, per detail vertex, m): PN surface positions
      direction (vec3, per detail vertex): unit control directions (the PN normals)
      vertices (int32, per vertex of this level): detail vertices of this level
      coarser (vec4i, per detail vertex): nearest samples of coarser levels, the nearest (the parent)
          first, -1 past the last and on level 0 (corners)
      mesh (uint64): wp.Mesh id of the posed body, its BVH refitted to this pose
      points (vec3, per body vertex, m): the posed body (the mesh's points)
      indices (int32, 3 per body triangle): body triangles, outward winding
      vv_start (int32, num_body_vertices + 1): CSR offsets of the body's vertex -> vertex adjacency
      vv_adj (int32, per adjacency entry): neighbouring vertices
      vf_start (int32, num_body_vertices + 1): CSR offsets of the vertex -> face adjacency
      vf_face (int32, 3 per body triangle): faces incident to each vertex
      concave (int32, per body vertex): 1 where the vertex is concave or a saddle (walk not trusted)
      walk_steps (int): most steps of a walk before the BVH decides
      teleport (float, m): a sample that moved farther since its last test starts from the BVH
      trust_distance (float, m): a walk that stops farther from its vertex leaves it to the BVH
      side (float): +1 or -1, whichever makes side * direction point away from the body
      margin (float, m): distance kept outside the body
      reach (float, per detail vertex, m): the smallest query radius; a sample found no nearer
          spares the finer samples within reach - margin of it (sized to the farthest of its
          children; the margin alone for a sample without children, which has none to spare)
    In/out:
      height (float, per detail vertex, m): heights along the control direction, raised where inside
      clearance (float, per detail vertex, m): written for this level's vertices, read for their parents
      body_vertex (int32, per detail vertex): body vertex each sample's last test ended at (-1 none)
      probe_point (vec3, per detail vertex, m): where each sample was last tested
      queries (int32, 2 elements): incremented per test (element 0) and per BVH query (element 1)
    """
    k = wp.tid()
    i = vertices[k]
    n = direction[i] * side
    p = base[i] + height[i] * n
    bounds = coarser[i]
    radius = reach[i]
    pa = bounds[0]
    if pa >= 0:
        bound = float(-1.0e30)
        for s in range(4):
            j = bounds[s]
            if j >= 0:
                bound = wp.max(bound, clearance[j] - wp.length(p - (base[j] + height[j] * side * direction[j])))
        if bound > margin:
            clearance[i] = bound
            return
        # the sample is at most -bound inside; the margin covers a coarser clearance that a lift
        # overstated (measured from a face plane, not the body)
        radius = wp.max(radius, margin - bound)
    wp.atomic_add(queries, 0, 1)
    vtx = body_vertex[i]
    if vtx >= 0:
        if wp.length(p - probe_point[i]) > teleport:
            vtx = -1
    for s in range(4):  # new to the test: start where the nearest coarser sample's last test ended
        if vtx < 0 and bounds[s] >= 0:
            vtx = body_vertex[bounds[s]]
    probe_point[i] = p
    trusted = vtx >= 0
    if trusted:
        vtx = walk_to_nearest_vertex(p, vtx, points, vv_start, vv_adj, walk_steps)
        if vtx < 0:
            trusted = False
            vtx = -1 - vtx
        elif concave[vtx] != 0 or wp.length(p - points[vtx]) > trust_distance:
            trusted = False
    sd = radius  # a query that finds nothing shows the sample at least its radius outside
    nb = wp.vec3(0.0, 0.0, 0.0)
    if trusted:
        sd, nb = least_inside_plane(p, vtx, points, indices, vf_start, vf_face)
    else:
        wp.atomic_add(queries, 1, 1)
        if vtx >= 0:
            # the surface is no farther than the vertex the walk reached (a query's cost grows with its radius)
            sd = wp.min(radius, wp.length(p - points[vtx]) * 1.001 + 1.0e-6)
        q = wp.mesh_query_point_sign_normal(mesh, p, sd)
        if q.result:
            cp = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
            nb = wp.mesh_eval_face_normal(mesh, q.face)
            sd = q.sign * wp.length(p - cp)
            vtx = closest_corner(p, q.face, points, indices)  # where the next test's walk starts
    body_vertex[i] = vtx
    if sd < margin:
        # move along the control direction until the point is `margin` outside the surface plane; where
        # the direction leads into the body (the garment folded over, its outer side facing the body)
        # a raised sample would go deeper with every lift, so it is lowered towards the base instead
        along = wp.dot(n, nb)
        h = height[i]
        if along > 0.0:
            h = h + (margin - sd) / wp.max(along, 0.2)
        else:
            h = wp.max(h - (margin - sd) / wp.max(-along, 0.2), 0.0)
        sd = sd + (h - height[i]) * along
        height[i] = h
    clearance[i] = sd


@wp.kernel
def relax_heights(height: wp.array(dtype=float), keep: float):
    """Decay the carried heights, so a lift ends when the contact does.

    Heights carry over between frames (eq. 3); carried whole they would keep a lift forever.

    Launch: one thread per detail vertex (dim = num_detail_vertices).
    Inputs:
      keep (float, fraction): share of last frame's height kept, in [0, 1]
    In/out:
      height (float, per detail vertex, m): heights, scaled and clamped to >= 0
    """
    i = wp.tid()
    height[i] = wp.max(height[i] * keep, 0.0)


@wp.kernel
def displace_along_directions(
    base: wp.array(dtype=wp.vec3),
    direction: wp.array(dtype=wp.vec3),
    side: float,
    height: wp.array(dtype=float),
    positions: wp.array(dtype=wp.vec3),
):
    """Final detail vertices P_i = P_smoothed,i + dh_i n_i (eq. 2), n_i oriented away from the body.

    Launch: one thread per detail vertex (dim = num_detail_vertices).
    Inputs:
      base (vec3, per detail vertex, m): PN surface positions
      direction (vec3, per detail vertex): unit control directions (the PN normals)
      side (float): +1 or -1, whichever makes side * direction point away from the body
      height (float, per detail vertex, m): heights dh
    Outputs:
      positions (vec3, per detail vertex, m): displaced positions
    """
    i = wp.tid()
    positions[i] = base[i] + height[i] * side * direction[i]


@wp.kernel
def surface_vertex_normals(
    positions: wp.array(dtype=wp.vec3),
    triangles: wp.array(dtype=wp.int32),
    vf_start: wp.array(dtype=wp.int32),
    vf_face: wp.array(dtype=wp.int32),
    pn_normals: wp.array(dtype=wp.vec3),
    height: wp.array(dtype=float),
    h_normal: float,
    normals: wp.array(dtype=wp.vec3),
):
    """Shading normals of the displaced surface (Oshita & Makinouchi §4.4, eqs. 13-14).

    The displaced surface's own normal is blended with the PN normal by alpha = min(1, dh / h_normal),
    so flat regions keep the smooth PN shading and raised ones show their folds.

    Launch: one thread per detail vertex (dim = num_detail_vertices).
    Inputs:
      positions (vec3, per detail vertex, m): displaced positions
      triangles (int32, 3 per detail triangle): detail triangles
      vf_start (int32, num_detail_vertices + 1): CSR offsets of the vertex -> face adjacency
      vf_face (int32, 3 per detail triangle): detail faces incident to each vertex
      pn_normals (vec3, per detail vertex): unit PN normals
      height (float, per detail vertex, m): heights dh
      h_normal (float, m): height at which the displaced normal fully takes over
    Outputs:
      normals (vec3, per detail vertex): unit shading normals
    """
    i = wp.tid()
    alpha = wp.clamp(height[i] / wp.max(h_normal, 1.0e-9), 0.0, 1.0)
    deform = pn_normals[i]
    if alpha > 0.0:  # flat samples (no height) keep the PN normal: their faces are not summed
        n = wp.vec3(0.0)
        for k in range(vf_start[i], vf_start[i + 1]):
            f = vf_face[k]
            a = positions[triangles[3 * f]]
            n += wp.cross(positions[triangles[3 * f + 1]] - a, positions[triangles[3 * f + 2]] - a)
        if wp.length(n) > 1.0e-20:
            deform = wp.normalize(n)
    blended = alpha * deform + (1.0 - alpha) * pn_normals[i]
    if wp.length(blended) > 1.0e-12:
        normals[i] = wp.normalize(blended)
    else:
        normals[i] = pn_normals[i]


# -- wrinkles (Oshita & Makinouchi §4.3) ------------------------------------------------------------
# Every coarse face carries a triangular grid of (n + 1)(n + 2) / 2 detail vertices: grid point (a, b)
# lies at barycentric weights ((n - a - b), a, b) / n of the face's corners 0, 1, 2, and face_grid maps
# it to the welded detail vertex. Lines of the grid are where forces are carried (eq. 5).


@wp.func
def grid_slot(a: int, b: int, n: int):
    """Slot of grid point (a, b) within one face's block of face_grid (row a, column b).

    Inputs:
      a (int): weight of corner 1 in grid steps, 0 .. n
      b (int): weight of corner 2 in grid steps, 0 .. n - a
      n (int): tessellation level
    Returns:
      int: the slot, 0 .. (n + 1)(n + 2) / 2 - 1
    """
    return a * (n + 1) - (a * (a - 1)) // 2 + b


@wp.func
def transmission(p_prev: wp.vec3, p: wp.vec3, p_next: wp.vec3):
    """Eq. 4: how much force passes a sample, the cosine of the turn between its two segments.

    A fold passes little force. Clamped so a fold sharper than 90 degrees still passes a trace.

    Inputs:
      p_prev (vec3, m): previous sample on the line
      p (vec3, m): the sample
      p_next (vec3, m): next sample on the line
    Returns:
      float: transmission in [0.01, 1]; 1 where a segment has no length
    """
    d0 = p - p_prev
    d1 = p_next - p
    l0 = wp.length(d0)
    l1 = wp.length(d1)
    if l0 < 1.0e-12 or l1 < 1.0e-12:
        return 1.0
    return wp.max(wp.dot(d0, d1) / (l0 * l1), 0.01)


@wp.func
def line_point(face: int, n: int, a0: int, b0: int, da: int, db: int, k: int, face_grid: wp.array(dtype=wp.int32)):
    """Detail vertex at step k of the grid line from (a0, b0) in direction (da, db) on a coarse face.

    Inputs:
      face (int, index): the coarse face
      n (int): tessellation level
      a0 (int): start of the line, weight of corner 1 in grid steps
      b0 (int): start of the line, weight of corner 2 in grid steps
      da (int): step of a per sample, -1, 0 or 1
      db (int): step of b per sample, -1, 0 or 1
      k (int, index): the sample along the line
      face_grid (int32, (n + 1)(n + 2) / 2 per coarse triangle): detail vertex of each grid point
    Returns:
      int: detail vertex index
    """
    return face_grid[face * ((n + 1) * (n + 2) // 2) + grid_slot(a0 + k * da, b0 + k * db, n)]


@wp.func
def carry_along_line(face: int, n: int, a0: int, b0: int, da: int, db: int, count: int,
                     face_grid: wp.array(dtype=wp.int32), owner_face: wp.array(dtype=wp.int32),
                     positions: wp.array(dtype=wp.vec3), f_first: wp.vec3, f_last: wp.vec3, blend: int,
                     shares: wp.array(dtype=float), scratch: int, kept: wp.array(dtype=wp.vec3), keep_at: int,
                     force: wp.array(dtype=wp.vec3)):
    """Eq. 5 along one grid line: the force at every inner sample, blended between the line's end
    forces by the share of transmission (eq. 4) accumulated from the first sample up to it, counting
    half of its own; a straight line blends linearly. Two passes: the transmissions and their total,
    then the running shares. Only samples this face owns are written to force.

    Inputs:
      face (int, index): the coarse face
      n (int): tessellation level
      a0 (int): start of the line, weight of corner 1 in grid steps
      b0 (int): start of the line, weight of corner 2 in grid steps
      da (int): step of a per sample
      db (int): step of b per sample
      count (int): samples on the line, the two ends included
      face_grid (int32, (n + 1)(n + 2) / 2 per coarse triangle): detail vertex of each grid point
      owner_face (int32, per detail vertex): coarse triangle that owns each detail vertex
      positions (vec3, per detail vertex, m): detail positions the transmission is measured on
      f_first (vec3, N): force at sample 0
      f_last (vec3, N): force at sample count - 1
      blend (int, flag): 0 writes each force, 1 averages it with the force already written there
      scratch (int, index): this line's first slot in shares (n + 1 slots)
      keep_at (int, index): where sample k's blended force goes in kept (keep_at + k); -1 keeps none
    Outputs:
      shares (float, n + 1 per line): scratch: the line's transmissions
      kept (vec3, per kept sample, N): every inner sample's blended force, owned or not (keep_at >= 0)
      force (vec3, per detail vertex, N): the inner samples' forces (read first where blend != 0)
    """
    total = float(0.0)
    for k in range(1, count - 1):
        c = transmission(positions[line_point(face, n, a0, b0, da, db, k - 1, face_grid)],
                         positions[line_point(face, n, a0, b0, da, db, k, face_grid)],
                         positions[line_point(face, n, a0, b0, da, db, k + 1, face_grid)])
        shares[scratch + k] = c
        total += c
    upto = float(0.0)
    for k in range(1, count - 1):
        c = shares[scratch + k]
        t = float(0.5)
        if total > 1.0e-12:
            t = (upto + 0.5 * c) / total
        upto += c
        value = f_first + t * (f_last - f_first)
        if keep_at >= 0:
            kept[keep_at + k] = value
        v = line_point(face, n, a0, b0, da, db, k, face_grid)
        if owner_face[v] == face:
            if blend != 0:
                value = 0.5 * (force[v] + value)
            force[v] = value


@wp.kernel
def carry_forces(
    face_grid: wp.array(dtype=wp.int32),
    owner_face: wp.array(dtype=wp.int32),
    n: int,
    positions: wp.array(dtype=wp.vec3),
    corner_vertex: wp.array(dtype=wp.int32),
    coarse_force: wp.array(dtype=wp.vec3),
    stage: int,
    shares: wp.array(dtype=float),
    edge_forces: wp.array(dtype=wp.vec3),
    force: wp.array(dtype=wp.vec3),
):
    """Elastic force at every detail sample of the coarse faces (eqs. 4-5), one grid line per thread.

    Corners take their coarse particle's force, edge samples blend the edge's ends, interior samples
    average the blends along the grid's two line directions between edge samples. Shared samples are
    written by their owner face only, so each is written once. Each line is walked twice
    (carry_along_line); the edges' blends, kept, are the interior lines' end forces. Three stages,
    each a launch: 0 the three edges (and the corners), 1 the lines of constant a, 2 the lines of
    constant b averaged into them. A thread per line rather than per face: at high levels (n = 60
    has 118 interior lines per face) one thread per face is a long serial chain on a GPU.

    Launch: one thread per grid line of every coarse triangle (dim = (num_coarse_triangles, 3) for
    stage 0, (num_coarse_triangles, n - 2) for stages 1 and 2; none for n < 3).
    Inputs:
      face_grid (int32, (n + 1)(n + 2) / 2 per coarse triangle): detail vertex of each grid point
      owner_face (int32, per detail vertex): coarse triangle that owns each detail vertex
      n (int): tessellation level
      positions (vec3, per detail vertex, m): PN surface positions
      corner_vertex (int32, 3 per coarse triangle): coarse vertex at each corner (the coarse
          triangles)
      coarse_force (vec3, per coarse vertex, N): elastic force on each particle (cloth.elastic_forces)
      stage (int): 0 edges, 1 lines of constant a, 2 lines of constant b (after 1)
    Outputs:
      shares (float, (n + 1) * max(3, n - 2) per coarse triangle): scratch, each line's transmissions
      edge_forces (vec3, 3 (n + 1) per coarse triangle, N): the edges' blends (stage 0; read by 1 and 2)
      force (vec3, per detail vertex, N): force carried to each detail sample
    """
    f, line = wp.tid()
    scratch = (f * wp.max(3, n - 2) + line) * (n + 1)
    e01 = 3 * f * (n + 1)  # the blends at sample k of the edges from corner 0 to 1, 0 to 2 and 1 to 2
    e02 = e01 + n + 1
    e12 = e02 + n + 1
    if stage == 0:
        slots = (n + 1) * (n + 2) // 2
        f0 = coarse_force[corner_vertex[3 * f]]
        f1 = coarse_force[corner_vertex[3 * f + 1]]
        f2 = coarse_force[corner_vertex[3 * f + 2]]
        if line == 0:
            v0 = face_grid[f * slots + grid_slot(0, 0, n)]
            v1 = face_grid[f * slots + grid_slot(n, 0, n)]
            v2 = face_grid[f * slots + grid_slot(0, n, n)]
            if owner_face[v0] == f:
                force[v0] = f0
            if owner_face[v1] == f:
                force[v1] = f1
            if owner_face[v2] == f:
                force[v2] = f2
            carry_along_line(f, n, 0, 0, 1, 0, n + 1, face_grid, owner_face, positions, f0, f1, 0, shares, scratch,
                             edge_forces, e01, force)
        elif line == 1:
            carry_along_line(f, n, 0, 0, 0, 1, n + 1, face_grid, owner_face, positions, f0, f2, 0, shares, scratch,
                             edge_forces, e02, force)
        else:
            carry_along_line(f, n, n, 0, -1, 1, n + 1, face_grid, owner_face, positions, f1, f2, 0, shares, scratch,
                             edge_forces, e12, force)
    elif stage == 1:
        # the line of constant a from (a, 0) to (a, n - a); its ends lie on edges, whose forces
        # follow from the same rule
        a = line + 1
        carry_along_line(f, n, a, 0, 0, 1, n - a + 1, face_grid, owner_face, positions, edge_forces[e01 + a],
                         edge_forces[e12 + n - a], 0, shares, scratch, edge_forces, -1, force)
    else:
        # the line of constant b from (0, b) to (n - b, b), averaged in
        b = line + 1
        carry_along_line(f, n, 0, b, 1, 0, n - b + 1, face_grid, owner_face, positions, edge_forces[e02 + b],
                         edge_forces[e12 + b], 1, shares, scratch, edge_forces, -1, force)


@wp.kernel
def vertical_forces(
    positions: wp.array(dtype=wp.vec3),
    nbr_start: wp.array(dtype=wp.int32),
    nbr: wp.array(dtype=wp.int32),
    force: wp.array(dtype=wp.vec3),
    vertical: wp.array(dtype=float),
):
    """Eqs. 6-7: the out-of-plane push on each sample, v_i = sum_j (p_i - p_j)/|p_i - p_j| . ef_j.

    Positive when neighbours push toward i (the sample bulges), negative when they pull away (it
    flattens).

    Launch: one thread per detail vertex (dim = num_detail_vertices).
    Inputs:
      positions (vec3, per detail vertex, m): PN surface positions
      nbr_start (int32, num_detail_vertices + 1): CSR offsets of the detail vertex adjacency
      nbr (int32, per adjacency entry): neighbouring detail vertices
      force (vec3, per detail vertex, N): carried forces (carry_forces)
    Outputs:
      vertical (float, per detail vertex, N): vertical force
    """
    i = wp.tid()
    total = float(0.0)
    for k in range(nbr_start[i], nbr_start[i + 1]):
        j = nbr[k]
        d = positions[i] - positions[j]
        length = wp.length(d)
        if length > 1.0e-12:
            total += wp.dot(d / length, force[j])
    vertical[i] = total


@wp.kernel
def edge_length_deficit(
    face_grid: wp.array(dtype=wp.int32),
    edge_face: wp.array(dtype=wp.int32),
    edge_side: wp.array(dtype=wp.int32),
    n: int,
    positions: wp.array(dtype=wp.vec3),
    rest_length: wp.array(dtype=float),
    deficit: wp.array(dtype=float),
):
    """Eq. 8 per coarse edge: rest length minus the length of the detail polyline along it.

    Signed so compression is positive: a compressed edge has length to give to wrinkles.

    Launch: one thread per coarse edge (dim = num_coarse_edges).
    Inputs:
      face_grid (int32, (n + 1)(n + 2) / 2 per coarse triangle): detail vertex of each grid point
      edge_face (int32, per coarse edge): a face containing the edge, whose grid line walks it
      edge_side (int32, per coarse edge): which side of that face: 0 = corner 0 -> 1,
          1 = corner 0 -> 2, 2 = corner 1 -> 2
      n (int): tessellation level
      positions (vec3, per detail vertex, m): PN surface positions
      rest_length (float, per coarse edge, m): length of the same polyline on the rest shape
    Outputs:
      deficit (float, per coarse edge, m): rest minus current length
    """
    e = wp.tid()
    f = edge_face[e]
    side = edge_side[e]
    a0 = int(0)
    da = int(1)
    db = int(0)
    if side == 1:
        da = 0
        db = 1
    elif side == 2:
        a0 = n
        da = -1
        db = 1
    length = float(0.0)
    for k in range(n):
        length += wp.length(positions[line_point(f, n, a0, 0, da, db, k + 1, face_grid)]
                            - positions[line_point(f, n, a0, 0, da, db, k, face_grid)])
    deficit[e] = rest_length[e] - length


@wp.kernel
def vertex_deficit(
    ve_start: wp.array(dtype=wp.int32),
    ve_edge: wp.array(dtype=wp.int32),
    edge_deficit: wp.array(dtype=float),
    out: wp.array(dtype=float),
):
    """A coarse vertex's required length change: the mean deficit over its edges (§4.3.2).

    Launch: one thread per coarse vertex (dim = num_coarse_vertices).
    Inputs:
      ve_start (int32, num_coarse_vertices + 1): CSR offsets of the vertex -> edge adjacency
      ve_edge (int32, 2 per coarse edge): edges incident to each vertex
      edge_deficit (float, per coarse edge, m): edge_length_deficit
    Outputs:
      out (float, per coarse vertex, m): mean deficit; 0 for a vertex without edges
    """
    i = wp.tid()
    total = float(0.0)
    count = float(0.0)
    for k in range(ve_start[i], ve_start[i + 1]):
        total += edge_deficit[ve_edge[k]]
        count += 1.0
    out[i] = total / wp.max(count, 1.0)


@wp.kernel
def wrinkle_heights(
    owner_face: wp.array(dtype=wp.int32),
    bary: wp.array(dtype=wp.vec3),
    corner_vertex: wp.array(dtype=wp.int32),
    coarse_deficit: wp.array(dtype=float),
    nbr_start: wp.array(dtype=wp.int32),
    nbr: wp.array(dtype=wp.int32),
    vertical: wp.array(dtype=float),
    height: wp.array(dtype=float),
    k_out_plane: float,
    dt: float,
    frames: float,
    change: wp.array(dtype=float),
):
    """Eqs. 9-12: the height change dh_deformation of each sample.

    Required length change: the coarse vertices' deficits interpolated over the face (no
    transmission). Expected change: each neighbour adds k |v_i - v_j|, positive when the sample
    pushed harder is already the higher one (the surface spreads), negative otherwise (eq. 10).
    dh_length = required / expected where length is missing and rising adds it (eq. 11), limited by
    the force-driven k v_i dt (eq. 12). Elsewhere a sample may only sink (eq. 11 read with §4.3.4).
    Eq. 11 is a change per update, not per time: it is read as the change over a reference frame
    (DetailParams.reference_fps, 1/24 s) and scaled by `frames`, the reference frames this update
    spans, as eq. 12 scales with dt, so the heights do not depend on how often the surface is updated.

    Launch: one thread per detail vertex (dim = num_detail_vertices).
    Inputs:
      owner_face (int32, per detail vertex): coarse triangle of each detail vertex
      bary (vec3, per detail vertex): weights of the owner face's corners 0, 1, 2
      corner_vertex (int32, 3 per coarse triangle): coarse vertex at each corner
      coarse_deficit (float, per coarse vertex, m): vertex_deficit
      nbr_start (int32, num_detail_vertices + 1): CSR offsets of the detail vertex adjacency
      nbr (int32, per adjacency entry): neighbouring detail vertices
      vertical (float, per detail vertex, N): vertical_forces
      height (float, per detail vertex, m): current heights
      k_out_plane (float, m/(N s)): how far a sample may move per unit vertical force and time
      dt (float, s): time since the last update (a frame)
      frames (float): reference frames in dt (dt times DetailParams.reference_fps)
    Outputs:
      change (float, per detail vertex, m): height change to add (add_heights)
    """
    i = wp.tid()
    f = owner_face[i]
    w = bary[i]
    required = (w[0] * coarse_deficit[corner_vertex[3 * f]] + w[1] * coarse_deficit[corner_vertex[3 * f + 1]]
                + w[2] * coarse_deficit[corner_vertex[3 * f + 2]])
    expected = float(0.0)
    for k in range(nbr_start[i], nbr_start[i + 1]):
        j = nbr[k]
        dv = vertical[i] - vertical[j]
        if dv * (height[i] - height[j]) >= 0.0:
            expected += k_out_plane * wp.abs(dv)
        else:
            expected -= k_out_plane * wp.abs(dv)
    by_force = k_out_plane * vertical[i] * dt
    if required > 0.0 and expected > 0.0:
        change[i] = wp.min(required / expected * frames, by_force)
    else:
        # eq. 11 read with §4.3.4: only missing length raises a wrinkle; where the cloth is stretched,
        # or rising would not add length, a sample may only sink (forces pulling it flat)
        change[i] = wp.min(0.0, by_force)


@wp.kernel
def constrain_heights(
    positions: wp.array(dtype=wp.vec3),
    nbr_start: wp.array(dtype=wp.int32),
    nbr: wp.array(dtype=wp.int32),
    owner_face: wp.array(dtype=wp.int32),
    kind: wp.array(dtype=wp.int32),
    coarse_edge: wp.array(dtype=wp.int32),
    edge_deficit: wp.array(dtype=float),
    face_uncompressed: wp.array(dtype=wp.int32),
    max_slope: float,
    height_in: wp.array(dtype=float),
    height_out: wp.array(dtype=float),
):
    """§4.3.4: keep the heights plausible after the wrinkle update.

    dh >= 0; no sample rises more than max_slope times its distance above a neighbour (the
    neighbour-to-neighbour length limit); no wrinkle inside a face none of whose edges is
    compressed (the paper's all-stretched faces included) nor on a coarse edge that is not
    compressed. One pass limits each sample by its neighbours' heights before the pass; passes
    repeated, each carrying a lowered sample's limit a ring further, reach the heights that meet
    every limit (the highest such heights below the update's). A sample at height 0 cannot be
    lowered and skips its neighbours: most of a garment is (87% of the walking dress's samples).

    Launch: one thread per detail vertex (dim = num_detail_vertices), once per pass.
    Inputs:
      positions (vec3, per detail vertex, m): PN surface positions
      nbr_start (int32, num_detail_vertices + 1): CSR offsets of the detail vertex adjacency
      nbr (int32, per adjacency entry): neighbouring detail vertices
      owner_face (int32, per detail vertex): coarse triangle of each detail vertex
      kind (int32, per detail vertex): 0 coarse vertex, 1 on a coarse edge, 2 face interior
      coarse_edge (int32, per detail vertex): coarse edge of a kind-1 vertex (any valid index otherwise)
      edge_deficit (float, per coarse edge, m): edge_length_deficit
      face_uncompressed (int32, per coarse triangle): faces_without_compression
      max_slope (float, m/m): largest rise per distance to a neighbour
      height_in (float, per detail vertex, m): heights before the pass
    Outputs:
      height_out (float, per detail vertex, m): constrained heights; must not alias height_in
    """
    i = wp.tid()
    h = wp.max(height_in[i], 0.0)
    if kind[i] == 2 and face_uncompressed[owner_face[i]] != 0:
        h = 0.0
    if kind[i] == 1:
        if edge_deficit[coarse_edge[i]] <= 0.0:
            h = 0.0
    if h > 0.0:
        for k in range(nbr_start[i], nbr_start[i + 1]):
            j = nbr[k]
            h = wp.min(h, wp.max(height_in[j], 0.0) + max_slope * wp.length(positions[i] - positions[j]))
    height_out[i] = h


@wp.kernel
def faces_without_compression(
    face_edges: wp.array(dtype=wp.int32),
    edge_deficit: wp.array(dtype=float),
    uncompressed: wp.array(dtype=wp.int32),
):
    """Flag coarse faces none of whose edges is shorter than at rest (§4.3.4): they get no wrinkles.

    Launch: one thread per coarse triangle (dim = num_coarse_triangles).
    Inputs:
      face_edges (int32, 3 per coarse triangle): the face's edges (sides 0 -> 1, 0 -> 2, 1 -> 2)
      edge_deficit (float, per coarse edge, m): edge_length_deficit
    Outputs:
      uncompressed (int32, per coarse triangle): 1 where no edge is compressed, else 0
    """
    f = wp.tid()
    s = int(1)
    for k in range(3):
        if edge_deficit[face_edges[3 * f + k]] > 0.0:
            s = 0
    uncompressed[f] = s


@wp.kernel
def add_heights(height: wp.array(dtype=float), change: wp.array(dtype=float)):
    """Apply the wrinkle update: height += change.

    A separate launch because wrinkle_heights reads the neighbours' heights, which must not change
    while it runs.

    Launch: one thread per detail vertex (dim = num_detail_vertices).
    Inputs:
      change (float, per detail vertex, m): wrinkle_heights
    In/out:
      height (float, per detail vertex, m): heights
    """
    i = wp.tid()
    height[i] = height[i] + change[i]


@wp.kernel
def smooth_heights(
    nbr_start: wp.array(dtype=wp.int32),
    nbr: wp.array(dtype=wp.int32),
    height_in: wp.array(dtype=float),
    weight: float,
    height_out: wp.array(dtype=float),
):
    """One Jacobi pass `weight` of the way to the neighbours' mean height (half the way over a
    reference frame of DetailParams.reference_fps, that share of it over a shorter update).

    Per-sample forces are noisy, and unsmoothed heights read as pimples rather than folds.

    Launch: one thread per detail vertex (dim = num_detail_vertices).
    Inputs:
      nbr_start (int32, num_detail_vertices + 1): CSR offsets of the detail vertex adjacency
      nbr (int32, per adjacency entry): neighbouring detail vertices
      height_in (float, per detail vertex, m): heights before the pass
      weight (float, fraction): share of the way to the mean, in [0, 1]
    Outputs:
      height_out (float, per detail vertex, m): smoothed heights; must not alias height_in
    """
    i = wp.tid()
    total = float(0.0)
    count = float(0.0)
    for k in range(nbr_start[i], nbr_start[i + 1]):
        total += height_in[nbr[k]]
        count += 1.0
    h = height_in[i]
    if count > 0.0:
        h = (1.0 - weight) * h + weight * total / count
    height_out[i] = h
