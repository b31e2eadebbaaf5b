"""Sparse particle cloth (Oshita & Makinouchi §3): spring forces for explicit RK4, the
nearest-vertex body collision with its local walk, and following the body's motion.

Springs are gathered per particle through a CSR adjacency (particle -> incident springs), so the
force pass writes each particle once with no atomics and gives the same result on CPU and CUDA.

Step order (composed by sim.cloth.ClothSolver), the body posed for the end of the step:

    begin_step (following the body, pinned particles' velocities, step counter)
    -> rk4_stage x 4 (the last closes the step)
    -> body_collide
    -> [limit_strain x passes (the last corrects the velocities) -> body_collide] (with strain limiting)
"""

# float(0.0), int(0) and bool(False) declare variables that a kernel reassigns (Warp treats a
# bare literal as a constant); the nested ifs are kept as the kernels were written and verified
# ruff: noqa: UP018, RUF046, SIM102

import warp as wp

from ._options import MODULE_OPTIONS, deferred_module
from .collision import closest_on_triangle, pseudo_normal_weight

wp.set_module_options(MODULE_OPTIONS)

from .skinning import SkinBinding, bound_position, face_frame, face_point
from .strands import air_velocity

# step_in_block's most lanes: a particle per lane for a garment of a few hundred particles (the paper's
# dress has 332), where a lane with two would double each pass's latency. The most that fit: a body
# query's traversal stack takes 128 bytes of shared memory per lane and Warp's tile allocator 4, and a
# block has 48 KB of static shared memory (384 lanes failed to build on the H100, session 41)
BLOCK_STEP_LANES = 352

# closest_in_boxes: the first radius of its growing box queries, about a body's contact range (a
# query of the whole body's boxes would test every triangle)
BOX_QUERY_START = wp.constant(0.01)  # m


@wp.func
def spring_force(xi: wp.vec3, xj: wp.vec3, vi: wp.vec3, vj: wp.vec3, rest: float, k_stretch: float,
                 k_compress: float, damping: float):
    """Force on particle i from the spring (i, j): bi-phase Hooke plus a dashpot along the spring.

    Eq. 1 of Oshita & Makinouchi with the unit direction. The spring is stiff when stretched and soft
    when compressed, so the coarse cloth barely stretches but may shorten where wrinkles are added
    later. The force on j is the negative.

    Inputs:
      xi (vec3, m): position of particle i
      xj (vec3, m): position of particle j
      vi (vec3, m/s): velocity of particle i
      vj (vec3, m/s): velocity of particle j
      rest (float, m): rest length of the spring
      k_stretch (float, N/m): stiffness while longer than rest
      k_compress (float, N/m): stiffness while shorter than rest
      damping (float, N s/m): dashpot coefficient along the spring; 0 gives the purely elastic force
    Returns:
      vec3 (N): force on i; zero when the particles coincide, since the spring then has no direction
    """
    d = xi - xj
    length = wp.length(d)
    if length < 1.0e-12:
        return wp.vec3(0.0)
    n = d / length
    k = k_compress
    if length > rest:
        k = k_stretch
    return -(k * (length - rest) + damping * wp.dot(vi - vj, n)) * n


@wp.struct
class SpringNetwork:
    """A cloth's springs (sim.cloth.ClothModel.springs): per spring, and gathered per particle through a CSR
    adjacency with a slot per spring end, whose constants are copied per slot so that the force pass
    (particle_acceleration) reads them in order.

    Fields:
      adj_start (int32, num_particles + 1): CSR offsets of each particle's adjacency slots
      adj_spring (int32, 2 per spring, one slot per end): spring index of each slot
      adj_other (int32, 2 per spring): the other particle of the slot's spring
      adj_rest (float, 2 per spring, m): rest length of the slot's spring
      adj_k_stretch (float, 2 per spring, N/m): stiffness when stretched
      adj_k_compress (float, 2 per spring, N/m): stiffness when compressed
      adj_damping (float, 2 per spring, N s/m): dashpot coefficient
      spring_i (int32, per spring): first particle of each spring
      spring_j (int32, per spring): second particle of each spring
      spring_rest (float, per spring, m): rest lengths
      spring_k_stretch (float, per spring, N/m): stiffness when stretched
      spring_k_compress (float, per spring, N/m): stiffness when compressed
      spring_damping (float, per spring, N s/m): dashpot coefficients
      spring_limited (int32, per spring): 1 where the strain limit caps the spring's stretch (limit_strain)
    """

    adj_start: wp.array(dtype=wp.int32)
    adj_spring: wp.array(dtype=wp.int32)
    adj_other: wp.array(dtype=wp.int32)
    adj_rest: wp.array(dtype=float)
    adj_k_stretch: wp.array(dtype=float)
    adj_k_compress: wp.array(dtype=float)
    adj_damping: wp.array(dtype=float)
    spring_i: wp.array(dtype=wp.int32)
    spring_j: wp.array(dtype=wp.int32)
    spring_rest: wp.array(dtype=float)
    spring_k_stretch: wp.array(dtype=float)
    spring_k_compress: wp.array(dtype=float)
    spring_damping: wp.array(dtype=float)
    spring_limited: wp.array(dtype=wp.int32)


# inlined: the struct passed per particle to a call would be copied on the CPU
@wp.func(inline=True)
def particle_acceleration(
    p: int,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    drag: wp.array(dtype=float),
    springs: SpringNetwork,
    gravity: wp.vec3,
    wind: wp.vec3,
    damping: float,
):
    """Acceleration a = F/m of one particle: springs, gravity, linear air drag toward the wind, damping.

    The springs are read per adjacency slot (adj_start[p] .. adj_start[p + 1] - 1), each slot holding
    the other particle and the spring's constants, so a particle's springs are one sequential read
    instead of a gather through spring indices. Pinned particles (inv_mass 0) get no acceleration:
    their velocity is prescribed.

    Inputs:
      p (int, index): the particle
      x (vec3, per particle, m): positions
      v (vec3, per particle, m/s): velocities
      inv_mass (float, per particle, 1/kg): inverse masses; 0 pins the particle
      drag (float, per particle, 1/s): air drag coefficient over mass (c/m)
      springs (SpringNetwork): the cloth's springs, per spring and per particle's slot (ClothModel.springs)
      gravity (vec3, m/s^2): acceleration of gravity, e.g. (0, -9.81, 0)
      wind (vec3, m/s): air velocity that the drag pulls toward
      damping (float, 1/s): global velocity damping
    Returns:
      vec3 (m/s^2): acceleration of particle p; zero for pinned particles
    """
    w = inv_mass[p]
    if w == 0.0:
        return wp.vec3(0.0)
    xp = x[p]
    vp = v[p]
    f = wp.vec3(0.0)
    # the arrays read in the loop as locals: read through the struct, the CPU's build loads each one's data
    # pointer again at every slot (the stores around may alias the struct as far as the compiler knows)
    other, rest, k_stretch, k_compress, dashpot = (springs.adj_other, springs.adj_rest, springs.adj_k_stretch,
                                                   springs.adj_k_compress, springs.adj_damping)
    for k in range(springs.adj_start[p], springs.adj_start[p + 1]):
        q = other[k]
        f += spring_force(xp, x[q], vp, v[q], rest[k], k_stretch[k], k_compress[k], dashpot[k])
    return f * w + gravity + drag[p] * (wind - vp) - damping * vp


@wp.kernel
def spring_forces(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    springs: SpringNetwork,
    force: wp.array(dtype=wp.vec3),
):
    """Force of every spring on its first particle (the second gets the negative), for tools and tests.

    The solver gathers forces per particle instead (rk4_stage); this kernel exposes the same force
    law one spring at a time so a host can inspect or verify it.

    Launch: one thread per spring (dim = num_springs).
    Inputs:
      x (vec3, per particle, m): positions
      v (vec3, per particle, m/s): velocities
      springs (SpringNetwork): the cloth's springs, per spring and per particle's slot (ClothModel.springs)
    Outputs:
      force (vec3, per spring, N): force on particle spring_i[s]
    """
    s = wp.tid()
    i = springs.spring_i[s]
    j = springs.spring_j[s]
    force[s] = spring_force(x[i], x[j], v[i], v[j], springs.spring_rest[s], springs.spring_k_stretch[s],
                            springs.spring_k_compress[s], springs.spring_damping[s])


# inlined: a call per particle made the kernels that share it about 1% slower on the CPU
@wp.func(inline=True)
def _rk4_stage_at(
    p: int,
    x0: wp.array(dtype=wp.vec3),
    v0: wp.array(dtype=wp.vec3),
    xs: wp.array(dtype=wp.vec3),
    vs: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    drag: wp.array(dtype=float),
    springs: SpringNetwork,
    gravity: wp.vec3,
    wind: wp.vec3,
    gusts: wp.array(dtype=wp.vec3),
    damping: float,
    weight: float,
    h_next: float,
    close_dt: float,
    acc_x: wp.array(dtype=wp.vec3),
    acc_v: wp.array(dtype=wp.vec3),
    x_next: wp.array(dtype=wp.vec3),
    v_next: wp.array(dtype=wp.vec3),
):
    """rk4_stage for particle p: its body, which step_in_block also runs."""
    air = wind
    if gusts.shape[0] > 0:
        air = wind + gusts[p]
    kv = particle_acceleration(p, xs, vs, inv_mass, drag, springs, gravity, air, damping)
    kx = vs[p]
    sum_x = acc_x[p] + weight * kx
    sum_v = acc_v[p] + weight * kv
    if close_dt > 0.0:
        x_next[p] = x0[p] + (close_dt / 6.0) * sum_x
        v_next[p] = v0[p] + (close_dt / 6.0) * sum_v
        acc_x[p] = wp.vec3(0.0)
        acc_v[p] = wp.vec3(0.0)
    else:
        x_next[p] = x0[p] + h_next * kx
        v_next[p] = v0[p] + h_next * kv
        acc_x[p] = sum_x
        acc_v[p] = sum_v


@wp.kernel
def rk4_stage(
    x0: wp.array(dtype=wp.vec3),
    v0: wp.array(dtype=wp.vec3),
    xs: wp.array(dtype=wp.vec3),
    vs: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    drag: wp.array(dtype=float),
    springs: SpringNetwork,
    gravity: wp.vec3,
    wind: wp.vec3,
    gusts: wp.array(dtype=wp.vec3),
    damping: float,
    weight: float,
    h_next: float,
    close_dt: float,
    acc_x: wp.array(dtype=wp.vec3),
    acc_v: wp.array(dtype=wp.vec3),
    x_next: wp.array(dtype=wp.vec3),
    v_next: wp.array(dtype=wp.vec3),
):
    """One stage of explicit RK4 on y = (x, v) with f(y) = (v, a(x, v)).

    Evaluates the slope k = f(stage state), adds it to the accumulators with the stage's weight and
    writes the next stage's state y0 + h_next * k. Force evaluation and stage update are fused so the
    stage state is read once. Launch it four times per step with (weight, h_next) = (1, dt/2),
    (2, dt/2), (2, dt), (1, 0), ping-ponging the stage buffers; the last (close_dt = dt) closes the
    step instead, y1 = y0 + dt/6 * (k1 + 2 k2 + 2 k3 + k4), and clears the accumulators for the next
    step, so a step needs no launch of its own to finish.

    Launch: one thread per particle (dim = num_particles).
    Inputs:
      x0 (vec3, per particle, m): positions at the start of the step
      v0 (vec3, per particle, m/s): velocities at the start of the step
      xs (vec3, per particle, m): positions of this stage (x0 for the first)
      vs (vec3, per particle, m/s): velocities of this stage (v0 for the first)
      inv_mass (float, per particle, 1/kg): inverse masses; 0 pins the particle
      drag (float, per particle, 1/s): air drag coefficient over mass (c/m)
      springs (SpringNetwork): the cloth's springs, per spring and per particle's slot (ClothModel.springs)
      gravity (vec3, m/s^2): acceleration of gravity, e.g. (0, -9.81, 0)
      wind (vec3, m/s): air velocity that the drag pulls toward
      gusts (vec3, per particle, m/s): the gusts added to it this step (wind_gusts); empty for none
      damping (float, 1/s): global velocity damping
      weight (float): RK4 weight of this stage's slope: 1, 2, 2, 1
      h_next (float, s): time from the step's start to the next stage: dt/2, dt/2, dt (unread when
          close_dt > 0)
      close_dt (float, s): 0 for the first three stages; the step length dt in the last, which closes it
    In/out:
      acc_x (vec3, per particle, m/s): weighted sum of the stages' velocities; zero before the first
          stage, and zero again after the last
      acc_v (vec3, per particle, m/s^2): weighted sum of the stages' accelerations; as acc_x
    Outputs:
      x_next (vec3, per particle, m): positions of the next stage, or at the end of the step when
          close_dt > 0; must not alias xs, which neighbours are still reading
      v_next (vec3, per particle, m/s): velocities likewise; must not alias vs
    """
    _rk4_stage_at(wp.tid(), x0, v0, xs, vs, inv_mass, drag, springs, gravity, wind, gusts, damping, weight, h_next,
                  close_dt, acc_x, acc_v, x_next, v_next)


@wp.kernel
def wind_gusts(
    x: wp.array(dtype=wp.vec3),
    wind: wp.vec3,
    turbulence: float,
    scale: float,
    rate: float,
    clock: wp.array(dtype=float),
    time_offset: float,
    gusts: wp.array(dtype=wp.vec3),
):
    """The gusts of a step's wind at each particle (strands.air_velocity, the noise the hair's wind gusts
    with), once a step: the RK4 stages add them to the mean wind (rk4_stage), so that the noise is not
    evaluated in each of the four. The time is clock[0] + time_offset, the clock on the device, so a
    captured frame replays at any time.

    Launch: one thread per particle (dim = num_particles).
    Inputs:
      x (vec3, per particle, m): positions at the start of the step
      wind (vec3, m/s): the mean wind
      turbulence (float, fraction): gust strength as a fraction of the wind speed
      scale (float, 1/m): the gusts' spatial frequency
      rate (float, 1/s): how fast their pattern changes
      clock (float, 1 element, s): device clock
      time_offset (float, s): the step's start relative to clock[0]
    Outputs:
      gusts (vec3, per particle, m/s): the air's velocity less the mean wind
    """
    i = wp.tid()
    gusts[i] = air_velocity(wind, turbulence, scale, rate, x[i], clock[0] + time_offset) - wind


@wp.func
def _stretched_springs(p: int, x: wp.array(dtype=wp.vec3), springs: SpringNetwork, max_stretch: float):
    """How many of particle p's limited springs are stretched past (1 + max_stretch) rest."""
    count = int(0)
    for k in range(springs.adj_start[p], springs.adj_start[p + 1]):
        s = springs.adj_spring[k]
        if springs.spring_limited[s] != 0:
            q = springs.spring_j[s]
            if q == p:
                q = springs.spring_i[s]
            if wp.length(x[p] - x[q]) > springs.spring_rest[s] * (1.0 + max_stretch):
                count += 1
    return count


# inlined: a call per particle made the kernels that share it about 1% slower on the CPU
@wp.func(inline=True)
def _limit_strain_at(
    p: int,
    x: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    springs: SpringNetwork,
    max_stretch: float,
    x_start: wp.array(dtype=wp.vec3),
    dt: float,
    v: wp.array(dtype=wp.vec3),
    x_out: wp.array(dtype=wp.vec3),
):
    """limit_strain for particle p: its body, which step_in_block also runs."""
    w = inv_mass[p]
    corrected = x[p]
    if w != 0.0:
        count = _stretched_springs(p, x, springs, max_stretch)
        if count > 0:
            # each over-stretched limited spring's correction, split by inverse mass, shared out over the
            # larger of its two ends' numbers of such springs: both ends divide by the same number, so
            # the pass moves no momentum (each end dividing by its own made a free cloth drift)
            corr = wp.vec3(0.0)
            for k in range(springs.adj_start[p], springs.adj_start[p + 1]):
                s = springs.adj_spring[k]
                if springs.spring_limited[s] == 0:
                    continue
                q = springs.spring_j[s]
                if q == p:
                    q = springs.spring_i[s]
                d = x[p] - x[q]
                length = wp.length(d)
                limit = springs.spring_rest[s] * (1.0 + max_stretch)
                if length > limit:
                    wq = inv_mass[q]
                    shared = float(wp.max(count, _stretched_springs(q, x, springs, max_stretch)))
                    corr -= (w / (w + wq)) * (length - limit) * d / (length * shared)
            corrected = x[p] + corr
    if dt > 0.0:
        v[p] = v[p] + (corrected - x_start[p]) / dt
    x_out[p] = corrected


@wp.kernel
def limit_strain(
    x: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    springs: SpringNetwork,
    max_stretch: float,
    x_start: wp.array(dtype=wp.vec3),
    dt: float,
    v: wp.array(dtype=wp.vec3),
    x_out: wp.array(dtype=wp.vec3),
):
    """One Jacobi pass of strain limiting: over-stretched edges are shortened to (1 + max_stretch) rest.

    Explicit springs soft enough to be stable let the cloth sag; this caps the stretch of the limited
    springs directly. Each correction is split by inverse mass and shared out over the larger of its two
    ends' counts of over-stretched springs, the same at both ends, so the pass is order-independent and
    moves no momentum (a particle averaging its own corrections did). Run a few passes, ping-ponging between
    buffers; the last (dt > 0) also adds the velocity change of all the passes' correction, the
    displacement from x_start over dt. Without it the velocities would keep carrying the particles
    toward the stretch the passes just removed.

    Launch: one thread per particle (dim = num_particles).
    Inputs:
      x (vec3, per particle, m): positions before this pass
      inv_mass (float, per particle, 1/kg): inverse masses; pinned particles (0) do not move
      springs (SpringNetwork): the cloth's springs, per spring and per particle's slot (ClothModel.springs)
      max_stretch (float, fraction of rest length): allowed stretch, e.g. 0.03 for 3%
      x_start (vec3, per particle, m): positions before the first pass; read only when dt > 0, and
          may be x_out itself (each thread reads its particle's before writing it)
      dt (float, s): step length in the last pass; 0 in the others, which leave v alone
    In/out:
      v (vec3, per particle, m/s): velocities, corrected in the last pass
    Outputs:
      x_out (vec3, per particle, m): corrected positions; must not alias x
    """
    _limit_strain_at(wp.tid(), x, inv_mass, springs, max_stretch, x_start, dt, v, x_out)


@wp.func
def walk_to_nearest_vertex(p: wp.vec3, start: int, points: wp.array(dtype=wp.vec3),
                           vv_start: wp.array(dtype=wp.int32), vv_adj: wp.array(dtype=wp.int32), max_steps: int):
    """Greedy walk over the body's vertex adjacency while the distance to p decreases.

    Oshita & Makinouchi §3.3, after Igarashi et al.: a particle moves little per step, so starting
    from last step's nearest vertex finds the new one in a few steps without a spatial search. The
    walk stops at a local minimum, which is the true nearest vertex only on convex parts.

    Inputs:
      p (vec3, m): query point
      start (int, index): body vertex the walk starts from
      points (vec3, per body vertex, m): posed body vertices
      vv_start (int32, num_body_vertices + 1): CSR offsets of the vertex -> vertex adjacency
      vv_adj (int32, per adjacency entry): neighbouring vertices
      max_steps (int): most steps before giving up
    Returns:
      int: the vertex where the walk stopped, or -1 - vertex (negative) when max_steps ran out
    """
    v = start
    d = wp.length_sq(p - points[v])
    steps = int(0)
    while steps < max_steps:
        best = v
        for k in range(vv_start[v], vv_start[v + 1]):
            u = vv_adj[k]
            du = wp.length_sq(p - points[u])
            if du < d:
                d = du
                best = u
        if best == v:
            return v
        v = best
        steps += 1
    return -1 - v


@wp.func
def least_inside_plane(p: wp.vec3, vtx: int, points: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32),
                       vf_start: wp.array(dtype=wp.int32), vf_face: wp.array(dtype=wp.int32)):
    """The plane, of the faces around body vertex vtx, that p lies farthest in front of.

    Near a convex vertex its distance is p's signed distance from the surface (exact where the
    closest point lies inside that face): p is inside when it is behind every plane.

    Inputs:
      p (vec3, m): query point
      vtx (int, index): body vertex, usually the end of walk_to_nearest_vertex
      points (vec3, per body vertex, m): posed body vertices
      indices (int32, 3 per body triangle): body triangles, outward winding
      vf_start (int32, num_body_vertices + 1): CSR offsets of the vertex -> face adjacency
      vf_face (int32, 3 per body triangle): faces incident to each vertex
    Returns:
      float (m): p's signed distance from that plane; -1e30 when vtx has no face
      vec3: the plane's unit normal (zero when vtx has no face)
    """
    best = float(-1.0e30)
    normal = wp.vec3(0.0, 0.0, 0.0)
    for k in range(vf_start[vtx], vf_start[vtx + 1]):
        f = vf_face[k]
        a = points[indices[3 * f + 0]]
        nf = wp.normalize(wp.cross(points[indices[3 * f + 1]] - a, points[indices[3 * f + 2]] - a))
        sd = wp.dot(p - a, nf)
        if sd > best:
            best = sd
            normal = nf
    return best, normal


@wp.func
def face_corners(points: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32), f: int):
    """A body triangle's three vertices and their posed positions (what a box query's candidate
    needs before its distance is taken).

    Inputs:
      points (vec3, per body vertex, m): posed body vertices
      indices (int32, 3 per body triangle): body triangles
      f (int, index): the triangle
    Returns:
      vec3i: its body vertices
      vec3 (m): the first vertex's position
      vec3 (m): the second's
      vec3 (m): the third's
    """
    corners = wp.vec3i(indices[3 * f + 0], indices[3 * f + 1], indices[3 * f + 2])
    return corners, points[corners[0]], points[corners[1]], points[corners[2]]


@wp.func
def nearest_corner(p: wp.vec3, corners: wp.vec3i, points: wp.array(dtype=wp.vec3)):
    """The one of a triangle's three body vertices nearest p: where a walk restarts after a query.

    Inputs:
      p (vec3, m): query point
      corners (vec3i): the triangle's body vertices
      points (vec3, per body vertex, m): posed body vertices
    Returns:
      int: the body vertex
    """
    best = corners[0]
    for c in range(1, 3):
        if wp.length_sq(p - points[corners[c]]) < wp.length_sq(p - points[best]):
            best = corners[c]
    return best


@wp.func
def closest_corner(p: wp.vec3, face: int, points: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32)):
    """nearest_corner of body triangle `face`.

    Inputs:
      p (vec3, m): query point
      face (int, index): body triangle
      points (vec3, per body vertex, m): posed body vertices
      indices (int32, 3 per body triangle): body triangles
    Returns:
      int: the body vertex
    """
    corners, _a, _b, _c = face_corners(points, indices, face)
    return nearest_corner(p, corners, points)


@wp.struct
class FollowRecord:
    """Where each cloth particle was last recorded against the body (follow_record, by body_collide), so
    that begin_step carries it with the face under the body's next pose (Oshita & Makinouchi §3.4).

    Fields:
      face (int32, per particle): body face recorded, -1 when none
      barycentric (vec3, per particle): weights of the face's corners at the particle's closest point
      local (vec3, per particle, m): the particle's offset from that point in the face's frame
          (skinning.face_frame)
    """

    face: wp.array(dtype=wp.int32)
    barycentric: wp.array(dtype=wp.vec3)
    local: wp.array(dtype=wp.vec3)


@wp.func
def follow_record(
    xp: wp.vec3,
    vtx: int,
    points: wp.array(dtype=wp.vec3),
    indices: wp.array(dtype=wp.int32),
    vf_start: wp.array(dtype=wp.int32),
    vf_face: wp.array(dtype=wp.int32),
    p: int,
    recorded: FollowRecord,
):
    """Record particle p relative to its nearest body face, for following the body next step.

    Oshita & Makinouchi §3.4: the faces around the nearest vertex are searched for the closest point;
    its barycentric weights and the offset in that face's frame (skinning.face_frame) let begin_step
    carry the particle rigidly with the face. Only slot p is written.

    Inputs:
      xp (vec3, m): the particle's final position
      vtx (int, index): its nearest body vertex; negative records no face
      points (vec3, per body vertex, m): posed body vertices
      indices (int32, 3 per body triangle): body triangles
      vf_start (int32, num_body_vertices + 1): CSR offsets of the vertex -> face adjacency
      vf_face (int32, 3 per body triangle): faces incident to each vertex
      p (int, index): the particle, the slot written in the outputs
    Outputs:
      recorded (FollowRecord): slot p's face (-1 when none); its weights and offset only when a face is
          found
    """
    recorded.face[p] = -1
    if vtx < 0:
        return
    best_d = float(1.0e30)
    best_f = int(-1)
    best_w = wp.vec3(0.0)
    for k in range(vf_start[vtx], vf_start[vtx + 1]):
        f = vf_face[k]
        w = closest_on_triangle(xp, points[indices[3 * f + 0]], points[indices[3 * f + 1]], points[indices[3 * f + 2]])
        d = wp.length_sq(xp - face_point(points, indices, f, w))
        if d < best_d:
            best_d = d
            best_f = f
            best_w = w
    if best_f >= 0:
        recorded.face[p] = best_f
        recorded.barycentric[p] = best_w
        recorded.local[p] = wp.transpose(face_frame(points, indices, best_f)) * (
            xp - face_point(points, indices, best_f, best_w))


@wp.struct
class BodyClearance:
    """What each cloth particle knows of its distance from the body between BVH queries (body_collide).

    The signed distance from a surface changes by at most the point's own displacement plus the
    largest displacement of the surface, so the distance a query measured stays a lower bound of the
    particle's distance when lowered by how far the body has moved since and how far the particle is
    from where it was measured. While that exceeds the margin the particle cannot touch the body and
    needs no query; the two lowerings together say how far it drifted relative to the body.

    Fields:
      distance (float, per particle, m): signed distance from the body at `at` measured by the last
          query, lowered by the body's motion since (very negative: unknown)
      at (vec3, per particle, m): where the last query measured it
      body_motion (float, per particle, m): how far the body moved since (the sum of
          sim.Collider.moved; very large: never queried)
    """

    distance: wp.array(dtype=float)
    at: wp.array(dtype=wp.vec3)
    body_motion: wp.array(dtype=float)


@wp.struct
class BodyCandidates:
    """The body triangles near each particle at a concave body vertex, gathered from the BVH now and
    then so that the steps between test only those (body_collide).

    A triangle left out lay farther than radius from center when the others were gathered; it can
    since have come no closer to the particle than radius - |x - center| - body_motion. While that is
    at least a query's radius, the gathered triangles give the query's answer. They are kept in
    order of their distance at gathering, so a test stops at the first one that cannot come closer
    than the best found.

    Fields:
      corners (vec3i, capacity per particle): the gathered triangles' body vertices, particle p's in
          slots p * capacity .. p * capacity + count - 1
      distance (float, capacity per particle, m): each one's distance from center when gathered,
          ascending
      count (int32, per particle): triangles gathered; -1 when none were (or more than capacity)
      center (vec3, per particle, m): where they were gathered
      radius (float, per particle, m): how far from center they were gathered
      body_motion (float, per particle, m): how far the body has moved since (the sum of
          sim.Collider.moved)
      capacity (int): slots per particle
    """

    corners: wp.array(dtype=wp.vec3i)
    distance: wp.array(dtype=float)
    count: wp.array(dtype=wp.int32)
    center: wp.array(dtype=wp.vec3)
    radius: wp.array(dtype=float)
    body_motion: wp.array(dtype=float)
    capacity: int


@wp.struct
class BodySurface:
    """The body a cloth collides with, posed for the end of a step (sim.collider.Collider and its
    adjacency), as body_collide and step_in_block read it.

    Fields:
      points (vec3, per body vertex, m): the body posed for the end of the step
      prev_points (vec3, per body vertex, m): the body at the start of the step; the surface velocity
          is (points - prev_points) / dt
      indices (int32, 3 per body triangle): body triangles, outward winding
      vv_start (int32, num_body_vertices + 1): CSR offsets of the vertex -> vertex adjacency
      vv_adj (int32, per adjacency entry): neighbouring vertices
      vf_start (int32, num_body_vertices + 1): CSR offsets of the vertex -> face adjacency
      vf_face (int32, 3 per body triangle): faces incident to each vertex
      concave (int32, per body vertex): 1 where the vertex is concave or a saddle (walk not trusted)
      bvh (uint64): wp.Bvh id over boxes of the body triangles, in face order, that hold them in this
          pose (sim.Collider.triangle_bvh: swept over the frame's poses, or fitted to this one)
      mesh (uint64): 0, or a wp.Mesh id over the same posed points with its BVH refitted to this pose:
          its nearest-first query (wp.mesh_query_point_sign_normal) then answers the closest-point
          queries instead of the growing box queries of bvh (closest_in_boxes), whose reach of many
          triangles keeps a GPU's launch waiting on its slowest thread; gatherings still read bvh
      moved (float, 1 element, m): largest displacement of a body vertex from prev_points to points
          (sim.Collider.moved)
      tie (float, m): distances this close count as equal when signing a closest point
    """

    points: wp.array(dtype=wp.vec3)
    prev_points: wp.array(dtype=wp.vec3)
    indices: wp.array(dtype=wp.int32)
    vv_start: wp.array(dtype=wp.int32)
    vv_adj: wp.array(dtype=wp.int32)
    vf_start: wp.array(dtype=wp.int32)
    vf_face: wp.array(dtype=wp.int32)
    concave: wp.array(dtype=wp.int32)
    bvh: wp.uint64
    mesh: wp.uint64
    moved: wp.array(dtype=float)
    tie: float


@wp.struct
class BodyContactParams:
    """The settings of the cloth's body collision (sim.cloth.ClothParams), as body_collide reads them.

    Fields:
      max_steps (int): most steps of the nearest-vertex walk before falling back to the BVH
      teleport (float, m): a particle that moved farther in one step restarts from the BVH
      trust_distance (float, m): beyond this distance from its vertex a particle is re-seeded
          periodically
      reseed_radius (float, m): BVH query radius when re-seeding; farther particles keep their walk
      refresh (int, steps): re-seed period of far particles; at least 1
      reseed_drift (float, m): far particles that drifted less than this relative to the body since
          their last query skip the re-seed; 0 re-seeds them all
      margin (float, m): distance kept outside the body
      friction (float): Coulomb friction coefficient
      candidate_slack (float, m): a gathering of triangles (BodyCandidates) reaches this much farther
          than the query it serves, so it lasts until the particle and the body have moved this far
          between them
    """

    max_steps: int
    teleport: float
    trust_distance: float
    reseed_radius: float
    refresh: int
    reseed_drift: float
    margin: float
    friction: float
    candidate_slack: float


@wp.func
def gather_candidates(xp: wp.vec3, radius: float, bvh: wp.uint64, points: wp.array(dtype=wp.vec3),
                      indices: wp.array(dtype=wp.int32), p: int, candidates: BodyCandidates):
    """Gather the body triangles within radius of xp for particle p (BodyCandidates), nearest first.

    Inputs:
      xp (vec3, m): where to gather
      radius (float, m): how far to look
      bvh (uint64): wp.Bvh id over boxes of the body triangles, in face order, that hold them in this
          pose (sim.Collider.triangle_bvh)
      points (vec3, per body vertex, m): posed body vertices
      indices (int32, 3 per body triangle): body triangles
      p (int, index): the particle, whose slots are written
    In/out:
      candidates (BodyCandidates): particle p's gathering; count -1 when more than capacity were near
    Returns:
      int: the triangles gathered, -1 when more than capacity were near
    """
    base = p * candidates.capacity
    n = int(0)
    full = bool(False)
    query = wp.bvh_query_aabb(bvh, xp - wp.vec3(radius), xp + wp.vec3(radius))
    f = int(0)
    while wp.bvh_query_next(query, f):
        corners, a, b, c = face_corners(points, indices, f)
        w = closest_on_triangle(xp, a, b, c)
        d = wp.length(xp - (w[0] * a + w[1] * b + w[2] * c))
        if d <= radius:
            if n == candidates.capacity:
                full = True
                break
            else:
                # insertion keeps the slots in ascending distance
                k = n
                while k > 0:
                    if candidates.distance[base + k - 1] <= d:
                        break
                    candidates.distance[base + k] = candidates.distance[base + k - 1]
                    candidates.corners[base + k] = candidates.corners[base + k - 1]
                    k -= 1
                candidates.distance[base + k] = d
                candidates.corners[base + k] = corners
                n += 1
    if full:
        n = -1
    candidates.count[p] = n
    candidates.center[p] = xp
    candidates.radius[p] = radius
    candidates.body_motion[p] = 0.0
    return n


@wp.func
def signed_closest_step(xp: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3, corners: wp.vec3i,
                        points: wp.array(dtype=wp.vec3), tie: float, best: float, found: bool, closest: wp.vec3,
                        normal: wp.vec3, corner: int, weighted: wp.vec3):
    """One triangle's turn in a search for the closest body point, signed as
    wp.mesh_query_point_sign_normal signs it (closest_candidate, closest_in_boxes).

    The sign is that of the angle-weighted pseudo-normal (Baerentzen and Aanaes) at the closest
    feature: the normals of the triangles equally close (within tie) are summed, weighted by the
    angle each has at a shared corner, pi at a shared edge, 2 pi inside (pseudo_normal_weight).

    Inputs:
      xp (vec3, m): query point
      a (vec3, m): the triangle's first corner
      b (vec3, m): its second
      c (vec3, m): its third
      corners (vec3i): the triangle's body vertices, a's, b's and c's
      points (vec3, per body vertex, m): posed body vertices
      tie (float, m): distances this close count as equal (1e-3 of the body's mean edge, as Warp's)
      best (float, m): the distance to beat, the search's radius at first
      found (bool): whether any triangle beat it
      closest (vec3, m): the closest point so far
      normal (vec3): its triangle's unit normal
      corner (int, index): its triangle's corner nearest xp (where a walk restarts)
      weighted (vec3): the weighted normals of the triangles that tie with it
    Returns:
      float, bool, vec3, vec3, int, vec3: best, found, closest, normal, corner and weighted after
          this triangle's turn
    """
    e0 = b - a
    e1 = c - a
    e2 = c - b
    n = wp.cross(e0, e1)
    if wp.length(n) < 1.0e-6 * (wp.dot(e0, e0) + wp.dot(e1, e1) + wp.dot(e2, e2)):
        return best, found, closest, normal, corner, weighted  # a sliver: no trustworthy normal (nor for Warp)
    w = closest_on_triangle(xp, a, b, c)
    q = w[0] * a + w[1] * b + w[2] * c
    d = wp.length(xp - q)
    if d < best + tie:
        unit = wp.normalize(n)
        weight = pseudo_normal_weight(q, w, a, b, c, tie)
        if d > best - tie:
            weighted = weighted + weight * unit
        else:
            weighted = weight * unit
        if d < best:
            best = d
            found = True
            closest = q
            normal = unit
            corner = nearest_corner(xp, corners, points)
    return best, found, closest, normal, corner, weighted


@wp.func
def closest_candidate(xp: wp.vec3, max_dist: float, tie: float, points: wp.array(dtype=wp.vec3), p: int,
                      candidates: BodyCandidates):
    """The closest point of particle p's gathered body triangles to xp within max_dist, signed as
    wp.mesh_query_point_sign_normal signs it (signed_closest_step). The gathering must hold every
    triangle within max_dist of xp (BodyCandidates).

    Inputs:
      xp (vec3, m): query point
      max_dist (float, m): how far to look
      tie (float, m): distances this close count as equal (1e-3 of the body's mean edge, as Warp's)
      points (vec3, per body vertex, m): posed body vertices
      p (int, index): the particle whose gathering is searched
      candidates (BodyCandidates): the gathering; count >= 0
    Returns:
      bool: whether any triangle lies within max_dist
      float (m): signed distance, negative inside the body
      vec3: the closest triangle's unit normal
      int: the closest triangle's corner nearest xp (where a walk restarts)
    """
    base = p * candidates.capacity
    # how much closer than at its gathering a triangle can have come since
    slack = wp.length(xp - candidates.center[p]) + candidates.body_motion[p]
    best = max_dist
    found = bool(False)
    closest = wp.vec3(0.0)
    normal = wp.vec3(0.0)
    corner = int(-1)
    weighted = wp.vec3(0.0)
    for k in range(candidates.count[p]):
        if candidates.distance[base + k] - slack > best + tie:
            break  # this one and every later one are farther than the best
        corners = candidates.corners[base + k]
        best, found, closest, normal, corner, weighted = signed_closest_step(
            xp, points[corners[0]], points[corners[1]], points[corners[2]], corners, points, tie, best, found,
            closest, normal, corner, weighted)
    sign = float(-1.0)
    if wp.dot(weighted, xp - closest) > 0.0:
        sign = 1.0
    return found, sign * best, normal, corner


@wp.func
def closest_in_boxes(xp: wp.vec3, max_dist: float, tie: float, bvh: wp.uint64, points: wp.array(dtype=wp.vec3),
                     indices: wp.array(dtype=wp.int32)):
    """The closest body point to xp within max_dist, signed as wp.mesh_query_point_sign_normal signs
    it (signed_closest_step): the answer of a wp.Mesh query, from boxes that need only hold the
    triangles (swept over a frame's poses, sim.Collider.sweep) rather than fit one pose.

    A box query has no nearest-first pruning: it returns every triangle whose box meets the query's.
    So the radius starts at BOX_QUERY_START and grows fourfold up to max_dist until a triangle lies
    within it (the closest within a radius is the closest of all), and a triangle whose own box in
    this pose lies farther than the best so far is passed over untested.

    Inputs:
      xp (vec3, m): query point
      max_dist (float, m): how far to look
      tie (float, m): distances this close count as equal (1e-3 of the body's mean edge, as Warp's)
      bvh (uint64): wp.Bvh id over boxes of the body triangles, in face order, that hold them in this
          pose (sim.Collider.triangle_bvh)
      points (vec3, per body vertex, m): posed body vertices
      indices (int32, 3 per body triangle): body triangles
    Returns:
      bool: whether any triangle lies within max_dist
      float (m): signed distance, negative inside the body
      vec3: the closest triangle's unit normal
      int: the closest triangle's corner nearest xp (where a walk restarts)
    """
    found = bool(False)
    best = float(0.0)
    closest = wp.vec3(0.0)
    normal = wp.vec3(0.0)
    corner = int(-1)
    weighted = wp.vec3(0.0)
    radius = wp.min(max_dist, BOX_QUERY_START)
    searching = bool(True)
    while searching:
        best = radius
        query = wp.bvh_query_aabb(bvh, xp - wp.vec3(radius), xp + wp.vec3(radius))
        f = int(0)
        while wp.bvh_query_next(query, f):
            corners, a, b, c = face_corners(points, indices, f)
            outside = wp.max(wp.max(wp.min(wp.min(a, b), c) - xp, xp - wp.max(wp.max(a, b), c)), wp.vec3(0.0))
            reach = best + tie
            if wp.length_sq(outside) <= reach * reach:
                best, found, closest, normal, corner, weighted = signed_closest_step(
                    xp, a, b, c, corners, points, tie, best, found, closest, normal, corner, weighted)
        if found or radius >= max_dist:
            searching = False
        else:
            radius = wp.min(max_dist, 4.0 * radius)
    sign = float(-1.0)
    if wp.dot(weighted, xp - closest) > 0.0:
        sign = 1.0
    return found, sign * best, normal, corner


def _body_collide_for(boxes):
    """_body_collide_at compiled with the box queries of the closest points (boxes), or without them
    for a caller that always passes a mesh (its nearest-first queries answer instead)."""

    # inlined: a call per particle made the kernels that share it about 1% slower on the CPU
    @wp.func(inline=True, name="_body_collide_at" + ("" if boxes else "_mesh"))
    def _body_collide_at(
        p: int,
        x: wp.array(dtype=wp.vec3),
        x_prev: wp.array(dtype=wp.vec3),
        v: wp.array(dtype=wp.vec3),
        inv_mass: wp.array(dtype=float),
        body: BodySurface,
        params: BodyContactParams,
        step_count: wp.array(dtype=wp.int32),
        first_pass: int,
        dt: float,
        nearest_in: wp.array(dtype=wp.int32),
        clearance_in: BodyClearance,
        record: int,
        nearest: wp.array(dtype=wp.int32),
        clearance: BodyClearance,
        candidates: BodyCandidates,
        contact: wp.array(dtype=wp.int32),
        fallbacks: wp.array(dtype=wp.int32),
        recorded: FollowRecord,
        carried: wp.array(dtype=wp.vec3),
        part: int,
    ):
        """body_collide for particle p: its body, which step_in_block also runs."""
        contact[p] = 0
        # the last query's distance carried to this pose and position
        xp = x[p]
        measured = clearance_in.distance[p]
        at = clearance_in.at[p]
        body_motion = clearance_in.body_motion[p]
        if first_pass != 0:
            measured -= body.moved[0]
            body_motion += body.moved[0]
            if candidates.capacity > 0:
                candidates.body_motion[p] = candidates.body_motion[p] + body.moved[0]
        away = wp.length(xp - at)
        bound = measured - away
        drift = body_motion + away
        if inv_mass[p] == 0.0:
            nearest[p] = nearest_in[p]
            clearance.distance[p] = measured
            clearance.at[p] = at
            clearance.body_motion[p] = body_motion
            if record != 0:
                recorded.face[p] = -1
            return
        vtx = nearest_in[p]
        trusted = vtx >= 0
        clear = bool(False)  # the clearance alone shows the particle cannot touch the body
        search = float(1.0e6)  # BVH query radius when the walk is not trusted
        listed = bool(False)  # the query is answered from the particle's gathered triangles
        if trusted:
            if wp.length(xp - x_prev[p]) > params.teleport:
                trusted = False
        if trusted:
            vtx = walk_to_nearest_vertex(xp, vtx, body.points, body.vv_start, body.vv_adj, params.max_steps)
            if vtx < 0:
                trusted = False
                vtx = -1 - vtx
            else:
                reach = wp.length(xp - body.points[vtx])
                far = reach > params.trust_distance
                if body.concave[vtx] != 0 and not far:
                    if bound > params.margin:
                        clear = True
                    else:
                        trusted = False
                        # the closest surface point is no farther than the vertex the walk reached; and
                        # while the particle cannot be deeper inside than the margin, a query of twice
                        # the margin tells a touch from none just as well (a BVH query's cost grows
                        # with its radius)
                        search = reach + params.margin
                        if bound > -params.margin:
                            search = wp.min(search, 2.0 * params.margin)
                        listed = candidates.capacity > 0
                elif far and step_count[0] % params.refresh == 0 and drift >= params.reseed_drift and (
                        bound <= params.trust_distance or body_motion >= params.reseed_drift):
                    # a wrong vertex matters where the particle may be near enough to touch (its bound
                    # says so) or where the body moves under its follow record; a particle swaying clear of
                    # a still body keeps its walk
                    trusted = False
                    # a far particle needs the right vertex only where it can touch or follow the body,
                    # so its query looks no farther than reseed_radius
                    search = wp.min(reach + params.margin, params.reseed_radius)
        n = wp.vec3(float(0.0), float(0.0), float(0.0))
        depth = float(0.0)  # how far to move along n to reach margin outside the surface
        hit = bool(False)
        if trusted:
            # behind every incident face: the least-inside face decides the projection (at a concave
            # vertex the faces do not, and the clearance has already said no)
            if not clear:
                best, nf = least_inside_plane(xp, vtx, body.points, body.indices, body.vf_start, body.vf_face)
                if best < params.margin and body.vf_start[vtx + 1] > body.vf_start[vtx]:
                    hit = True
                    n = nf
                    depth = params.margin - best
        else:
            at = xp
            body_motion = 0.0
            measured = search  # nothing within the radius; a particle deeper inside than it is not seen
            found = bool(False)
            sd = float(0.0)
            nf = wp.vec3(0.0)
            corner = int(0)
            if listed:
                used = float(1.0e30)  # how far the particle and the body have moved since the gathering
                if candidates.count[p] >= 0:
                    used = wp.length(xp - candidates.center[p]) + candidates.body_motion[p]
                valid = used + search <= candidates.radius[p]
                # a body that moves a quarter of the slack per step would use a new gathering up within
                # a few steps: the BVH answers instead
                renew = step_count[0] % params.refresh == 0 and used > 0.5 * params.candidate_slack
                if (not valid or renew) and 4.0 * body.moved[0] <= params.candidate_slack:
                    wp.atomic_add(fallbacks, part, 1)
                    # not valid when more triangles were near than it has room for
                    valid = gather_candidates(xp, search + params.candidate_slack, body.bvh, body.points,
                                              body.indices, p, candidates) >= 0
                if valid:
                    found, sd, nf, corner = closest_candidate(xp, search, body.tie, body.points, p, candidates)
                else:
                    listed = False
            if not listed:
                wp.atomic_add(fallbacks, part, 1)
                if body.mesh != wp.uint64(0):
                    q = wp.mesh_query_point_sign_normal(body.mesh, xp, search)
                    if q.result:
                        found = True
                        sd = q.sign * wp.length(xp - wp.mesh_eval_position(body.mesh, q.face, q.u, q.v))
                        nf = wp.mesh_eval_face_normal(body.mesh, q.face)
                        corner = closest_corner(xp, q.face, body.points, body.indices)
                elif wp.static(boxes):
                    found, sd, nf, corner = closest_in_boxes(xp, search, body.tie, body.bvh, body.points, body.indices)
            if found:
                measured = sd
                # restart the cache at the closest corner of the closest face, then settle it locally
                vtx = walk_to_nearest_vertex(xp, corner, body.points, body.vv_start, body.vv_adj, params.max_steps)
                if vtx < 0:
                    vtx = -1 - vtx
                if sd < params.margin:
                    hit = True
                    n = nf
                    depth = params.margin - sd
        nearest[p] = vtx
        clearance.distance[p] = measured
        clearance.at[p] = at
        clearance.body_motion[p] = body_motion
        if hit:
            x[p] = xp + depth * n
            # the body's velocity less what following already moved the particle by this step: counted in
            # its velocity too, a particle resting on a moving body slid over it at the body's speed
            vb = (body.points[vtx] - body.prev_points[vtx] - carried[p]) / dt
            rel = v[p] - vb
            vn = wp.dot(rel, n)
            if vn < 0.0:
                tangent = rel - vn * n
                speed = wp.length(tangent)
                if speed > 1.0e-12:
                    tangent = tangent * wp.max(0.0, 1.0 - params.friction * (-vn) / speed)
                rel = tangent
            v[p] = vb + rel
            contact[p] = 1
        if record != 0:
            follow_record(x[p], vtx, body.points, body.indices, body.vf_start, body.vf_face, p, recorded)

    return _body_collide_at


def _body_collide(boxes):
    """body_collide compiled with the box queries (boxes) or for a mesh always given (mesh != 0)."""
    collide_body = _body_collide_for(boxes)

    # the mesh's variant is a GPU's (ClothSolver.mesh_queries): a module of its own, compiled where launched
    @wp.kernel(module=None if boxes else deferred_module(__name__ + ".body_collide_mesh"),
               name="body_collide" + ("" if boxes else "_mesh"))
    def body_collide(
        x: wp.array(dtype=wp.vec3),
        x_prev: wp.array(dtype=wp.vec3),
        v: wp.array(dtype=wp.vec3),
        inv_mass: wp.array(dtype=float),
        body: BodySurface,
        params: BodyContactParams,
        step_count: wp.array(dtype=wp.int32),
        first_pass: int,
        dt: float,
        nearest_in: wp.array(dtype=wp.int32),
        clearance_in: BodyClearance,
        record: int,
        nearest: wp.array(dtype=wp.int32),
        clearance: BodyClearance,
        candidates: BodyCandidates,
        contact: wp.array(dtype=wp.int32),
        fallbacks: wp.array(dtype=wp.int32),
        recorded: FollowRecord,
        carried: wp.array(dtype=wp.vec3),
        first: int,
        part: int,
    ):
        """Vertex-only body collision of Oshita & Makinouchi §3.3, with friction and the follow record.

        Each particle walks from its cached nearest body vertex to a local minimum of distance and is
        inside when it lies behind every face incident to that vertex; it is then put on the surface
        (plus margin) and its velocity relative to the body loses its inward part, with Coulomb friction
        on the tangential part. Where the walk is not trusted (no cache yet, a jump farther than teleport
        since the last step, a walk that ran out of steps, a concave vertex near the body) a BVH
        closest-point query decides and restarts the cache. Particles farther than trust_distance cannot
        collide, but their walk can stall between limbs; they are re-seeded from the BVH every refresh
        steps, all on the same step (on a GPU a launch lasts as long as its slowest thread, so re-seeds
        staggered over every step would make every launch wait for a query), once they have drifted
        reseed_drift relative to the body since their last query (a particle that kept still on a body
        that kept still would find the same vertex again), and only where a wrong vertex could matter:
        where the particle may be within trust_distance of the body, or where the body itself has moved
        reseed_drift under its follow record. Near a concave vertex the query is skipped
        while the particle's clearance (BodyClearance, a lower bound of its signed distance lowered by
        its own and the body's motion) stays above the margin: it cannot touch the body, which is the
        query's own answer. Where it does need one, it tests the body triangles gathered near it
        (BodyCandidates) instead of walking the BVH, for as long as the gathering holds every triangle the
        query could find; the gathering is renewed when it no longer does, and on the refresh steps once
        it has used half its slack, so that on a GPU the renewals mostly wait in the launches that
        re-seed. With record != 0 the final position is also recorded against the nearest body face
        (follow_record) for begin_step of the next step.

        Each particle touches only its own entries, so ranges of them may run side by side (one per CPU
        core, sim.cloth.ClothSolver); each counts its queries in a row of fallbacks of its own.

        Launch: one thread per particle of a range (dim = particles in the range).
        Inputs:
          x_prev (vec3, per particle, m): positions at the start of the step, for the teleport test
          inv_mass (float, per particle, 1/kg): inverse masses; pinned particles (0) are not collided
          body (BodySurface): the body posed for the end of the step, and the start's pose
          params (BodyContactParams): the walk's, the re-seeding's and the contact's settings
          step_count (int32, 1 element): the step counter of begin_step, which times the re-seeding
          first_pass (int, flag): non-zero in the step's first pass, which lowers the clearances by
              body.moved; a second pass in the same pose must not lower them again
          dt (float, s): step length
          nearest_in (int32, per particle): cached nearest body vertex from the last step, -1 when unknown
          clearance_in (BodyClearance): the clearances from the last pass; may be clearance itself
          record (int, flag): non-zero records the follow data
          carried (vec3, per particle, m): how far begin_step's following moved each particle this step;
              the contact takes it off the body's motion, so a particle the body already carried keeps
              still on it rather than being given the body's velocity a second time
          first (int, index): the range's first particle; thread t collides particle first + t
          part (int, index): the range's element of fallbacks
        In/out:
          x (vec3, per particle, m): positions, pushed outside the body
          v (vec3, per particle, m/s): velocities, made non-penetrating relative to the body
          candidates (BodyCandidates): the triangles gathered near particles at concave vertices;
              capacity 0 queries the BVH instead
          fallbacks (int32, per range): element `part` incremented once per BVH query or gathering (zero
              them to count one launch)
        Outputs:
          nearest (int32, per particle): nearest body vertex after this pass; may be nearest_in itself
          clearance (BodyClearance): the clearances after this pass
          contact (int32, per particle): 1 where the particle was pushed out, else 0
          recorded (FollowRecord): each particle's place on its nearest face; written only when record != 0
        """
        collide_body(wp.tid() + first, x, x_prev, v, inv_mass, body, params, step_count, first_pass, dt, nearest_in,
                     clearance_in, record, nearest, clearance, candidates, contact, fallbacks, recorded, carried, part)

    return body_collide


# with the box queries (the CPU's, and whenever mesh may be 0), and without them for a mesh always
# given (a GPU's, ClothSolver.mesh_queries): sm_90 registers 118 -> 89
BODY_COLLIDE = {boxes: _body_collide(boxes) for boxes in (True, False)}
body_collide = BODY_COLLIDE[True]


@wp.func
def nearest_vertex(p: wp.vec3, points: wp.array(dtype=wp.vec3)):
    """Exhaustive nearest vertex of p: the first of equally near ones.

    Inputs:
      p (vec3, m): the point
      points (vec3, per vertex, m): the vertices; at least one
    Returns:
      int (index): the nearest vertex
    """
    best = int(0)
    d = wp.length_sq(p - points[0])
    for i in range(1, points.shape[0]):
        di = wp.length_sq(p - points[i])
        if di < d:
            d = di
            best = i
    return best


@wp.kernel
def nearest_vertex_brute_force(x: wp.array(dtype=wp.vec3), points: wp.array(dtype=wp.vec3),
                               nearest: wp.array(dtype=wp.int32)):
    """Exhaustive nearest body vertex of every particle: the truth the walk is measured against.

    Launch: one thread per particle (dim = num_particles).
    Inputs:
      x (vec3, per particle, m): positions
      points (vec3, per body vertex, m): posed body vertices; at least one
    Outputs:
      nearest (int32, per particle): index of the nearest body vertex
    """
    p = wp.tid()
    nearest[p] = nearest_vertex(x[p], points)


@wp.kernel
def walk_agreement(
    x: wp.array(dtype=wp.vec3),
    first: int,
    part: int,
    points: wp.array(dtype=wp.vec3),
    grid: wp.uint64,
    walked: wp.array(dtype=wp.int32),
    inv_mass: wp.array(dtype=float),
    radius: float,
    counts: wp.array2d(dtype=wp.int32),
):
    """Count how often the nearest-vertex walk (body_collide's follow) found the nearest body
    vertex, against an exhaustive search of the vertices within radius (a quality statistic).

    Only free particles within radius of the body count: farther ones neither touch nor follow it,
    and their walk is not kept exact. So the truth is the nearest of the vertices a hash grid over
    the posed body lists near the particle, the first of equally near ones as nearest_vertex picks
    it. A walk that ends on another vertex equally near (within 1e-6 of the distance, relative, or
    1e-9 m) agrees. Distances are compared in float64.

    Launch: one thread per particle from first (dim = particles counted).
    Inputs:
      x (vec3, per particle, m): positions
      first (int, index): the first particle of the launch
      part (int, index): the launch's row of counts (launches side by side on a CPU's cores each
          count in their own: collision.list_deep_point)
      points (vec3, per body vertex, m): the posed vertices the walk runs on
      grid (uint64): wp.HashGrid id over points, built with cells of radius or larger
      walked (int32, per particle): the walk's vertex (ClothState.nearest), -1 for none
      inv_mass (float, per particle): 0 marks pinned particles
      radius (float, m): particles farther from the nearest vertex are not counted
    In/out:
      counts (int32, rows * 2): particles that agree, particles counted (zero them first)
    """
    p = wp.tid() + first
    if inv_mass[p] <= 0.0:
        return
    xp = x[p]
    truth = int(-1)
    best = float(0.0)
    query = wp.hash_grid_query(grid, xp, radius)
    i = int(0)
    while wp.hash_grid_query_next(query, i):
        di = wp.length_sq(xp - points[i])
        if truth < 0 or di < best or (di == best and i < truth):
            truth = i
            best = di
    if truth < 0:
        return
    q = wp.vec3d(xp)
    near = wp.length(q - wp.vec3d(points[truth]))
    if near > wp.float64(radius):
        return
    wp.atomic_add(counts, part, 1, 1)
    w = walked[p]
    if w == truth:
        wp.atomic_add(counts, part, 0, 1)
        return
    walked_distance = wp.length(q - wp.vec3d(points[wp.max(w, 0)]))
    if wp.abs(walked_distance - near) <= wp.float64(1.0e-9) + wp.float64(1.0e-6) * near:
        wp.atomic_add(counts, part, 0, 1)


# inlined: a call per particle made the kernels that share it about 1% slower on the CPU
@wp.func(inline=True)
def _begin_step_at(
    p: int,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    points: wp.array(dtype=wp.vec3),
    indices: wp.array(dtype=wp.int32),
    follow: int,
    recorded: FollowRecord,
    full_within: float,
    none_beyond: float,
    pins: int,
    particle_binding: wp.array(dtype=wp.int32),
    pinned: SkinBinding,
    dt: float,
    step_count: wp.array(dtype=wp.int32),
    carried: wp.array(dtype=wp.vec3),
):
    """begin_step for particle p: its body, which step_in_block also runs."""
    if p == 0:
        step_count[0] = step_count[0] + 1
    carried[p] = wp.vec3(0.0)
    if inv_mass[p] == 0.0:
        if pins != 0:
            b = particle_binding[p]
            if b >= 0:
                target = bound_position(pinned, b)
                v[p] = (target - x[p]) / dt
        return
    if follow == 0:
        return
    f = recorded.face[p]
    if f < 0:
        return
    offset = recorded.local[p]
    dist = wp.length(offset)
    w = float(1.0)
    if dist > full_within:
        t = wp.clamp((dist - full_within) / wp.max(none_beyond - full_within, 1.0e-9), 0.0, 1.0)
        w = 1.0 - t * t * (3.0 - 2.0 * t)
    if w <= 0.0:
        return
    target = face_point(points, indices, f, recorded.barycentric[p]) + face_frame(points, indices, f) * offset
    move = w * (target - x[p])
    x[p] = x[p] + move
    carried[p] = move


@wp.kernel
def begin_step(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    points: wp.array(dtype=wp.vec3),
    indices: wp.array(dtype=wp.int32),
    follow: int,
    recorded: FollowRecord,
    full_within: float,
    none_beyond: float,
    pins: int,
    particle_binding: wp.array(dtype=wp.int32),
    pinned: SkinBinding,
    dt: float,
    step_count: wp.array(dtype=wp.int32),
    carried: wp.array(dtype=wp.vec3),
):
    """Everything before the integration, in one pass over the particles.

    The body is posed for the end of the step. Three things happen:

    - following (Oshita & Makinouchi §3.4, follow != 0): free particles take their recorded
      face-relative coordinates under the body's new pose; particles farther than full_within from the
      body follow less, none beyond none_beyond, so a skirt's hem is not dragged rigidly with a leg;
    - with pins != 0, pinned particles with a binding (particle_binding >= 0) get the velocity that
      carries them in a straight line to their bound position at the step's end;
    - the step counter goes up by one; it lives on the device so captured frames advance it.

    Launch: one thread per particle (dim = num_particles).
    Inputs:
      inv_mass (float, per particle, 1/kg): inverse masses; 0 marks pinned particles
      points (vec3, per body vertex, m): body posed for the end of the step; None when follow and pins
          are both 0
      indices (int32, 3 per body triangle): body triangles; None when follow and pins are both 0
      follow (int, flag): non-zero moves free particles with the body
      recorded (FollowRecord): where body_collide recorded each particle on the body
      full_within (float, m): particles this close to the body follow it fully
      none_beyond (float, m): particles this far away do not follow; at least full_within
      pins (int, flag): non-zero drives the bound pinned particles
      particle_binding (int32, per particle): binding index of each pinned particle, -1 when unbound;
          this may be None and pinned empty when pins is 0
      pinned (SkinBinding): the pinned particles' bindings on the body posed for the end of the step
      dt (float, s): step length
    In/out:
      x (vec3, per particle, m): positions, moved with the body where followed
      v (vec3, per particle, m/s): velocities; set for the bound pinned particles
      step_count (int32, 1 element): step counter, incremented by one
    Outputs:
      carried (vec3, per particle, m): how far following moved each particle (0 where it did not), which
          body_collide takes off the body's motion: the particle's velocity is its own, not the body's
    """
    _begin_step_at(wp.tid(), x, v, inv_mass, points, indices, follow, recorded, full_within, none_beyond, pins,
                   particle_binding, pinned, dt, step_count, carried)


@wp.func_native("WP_TILE_SYNC();")
def _block_sync():
    """Wait for every thread of the block (a CUDA __syncthreads; a fiber switch on the CPU)."""
    ...


def _step_in_block(boxes):
    """step_in_block compiled with the box queries (boxes) or for a mesh always given (mesh != 0)."""
    collide_body = _body_collide_for(boxes)

    # a GPU's way for a small cloth (ClothSolver.block_step): a module of its own, compiled where launched
    @wp.kernel(module=deferred_module(__name__ + ".step_in_block", block_dim=BLOCK_STEP_LANES),
               launch_bounds=BLOCK_STEP_LANES,
               name="step_in_block" + ("" if boxes else "_mesh"))
    def step_in_block(
        n: int,
        x0: wp.array(dtype=wp.vec3),
        v0: wp.array(dtype=wp.vec3),
        inv_mass: wp.array(dtype=float),
        drag: wp.array(dtype=float),
        springs: SpringNetwork,
        gravity: wp.vec3,
        wind: wp.vec3,
        gusts: wp.array(dtype=wp.vec3),
        damping: float,
        dt: float,
        x_stage: wp.array(dtype=wp.vec3),
        v_stage: wp.array(dtype=wp.vec3),
        x_scratch: wp.array(dtype=wp.vec3),
        v_scratch: wp.array(dtype=wp.vec3),
        acc_x: wp.array(dtype=wp.vec3),
        acc_v: wp.array(dtype=wp.vec3),
        follow: int,
        recorded_in: FollowRecord,
        full_within: float,
        none_beyond: float,
        pins: int,
        particle_binding: wp.array(dtype=wp.int32),
        pinned: SkinBinding,
        step_count: wp.array(dtype=wp.int32),
        carried: wp.array(dtype=wp.vec3),
        strain_passes: int,
        max_stretch: float,
        collide: int,
        body: BodySurface,
        params: BodyContactParams,
        nearest_in: wp.array(dtype=wp.int32),
        clearance_in: BodyClearance,
        x: wp.array(dtype=wp.vec3),
        v: wp.array(dtype=wp.vec3),
        nearest: wp.array(dtype=wp.int32),
        clearance: BodyClearance,
        candidates: BodyCandidates,
        contact: wp.array(dtype=wp.int32),
        fallbacks: wp.array(dtype=wp.int32),
        recorded: FollowRecord,
    ):
        """A whole step of a small cloth in one launch: begin_step, the four rk4_stage, body_collide and
        the strain limit's passes with its second body_collide, as sim.cloth.ClothSolver.step launches
        them, the same particles bit for bit. The threads of one block stride over the particles and wait
        for each other (a block barrier) wherever a pass reads what other particles' threads wrote: a
        garment of a few hundred particles spends most of a step of six launches waiting on their
        latency, and one block keeps the whole step on one streaming multiprocessor.

        Passes that read only their own particle run in the same stride without a barrier: body_collide
        after the last stage and after the last strain pass. With collide != 0 the first body_collide
        records the follow data unless strain passes follow (then the second does), as ClothSolver.

        Launch: one thread per lane of one block (dim = 1, wp.launch_tiled with block_dim lanes).
        At most BLOCK_STEP_LANES lanes, the kernel's launch bound: the CUDA compiler fits its registers to
        that many (168 on sm_90, with 192 bytes of spills, 32 without the box queries; unbounded, 204
        registers and at most 256 lanes).
        A CPU runs one lane unless wp.config.enable_cpu_blocks is set (then its lanes are fibers that
        switch at the barriers).
        Inputs:
          n (int): particles
          inv_mass (float, per particle, 1/kg): inverse masses; 0 pins the particle
          drag (float, per particle, 1/s): air drag coefficient over mass (c/m)
          springs (SpringNetwork): the cloth's springs, per spring and per particle's slot (ClothModel.springs)
          gravity (vec3, m/s^2): acceleration of gravity
          wind (vec3, m/s): air velocity that the drag pulls toward
          gusts (vec3, per particle, m/s): the gusts added to it this step (wind_gusts); empty for none
          damping (float, 1/s): global velocity damping
          dt (float, s): step length
          follow (int, flag): non-zero moves free particles with the body (begin_step)
          recorded_in (FollowRecord): the follow record of the last step (begin_step's)
          full_within (float, m): particles this close to the body follow it fully
          none_beyond (float, m): particles this far away do not follow
          pins (int, flag): non-zero drives the bound pinned particles (begin_step)
          particle_binding (int32, per particle): binding of each pinned particle, -1 when unbound
          pinned (SkinBinding): the pinned particles' bindings on the body posed for the end of the step
          strain_passes (int): Jacobi passes of the strain limit (limit_strain); 0 for none
          max_stretch (float, fraction of rest length): allowed stretch of the limited springs
          collide (int, flag): non-zero collides with the body (body_collide); body and params are
              unread otherwise and may be empty
          body (BodySurface): the body posed for the end of the step (begin_step reads its points and
              indices where it follows or pins)
          params (BodyContactParams): the body collision's settings
          nearest_in (int32, per particle): cached nearest body vertex from the last step, -1 unknown
          clearance_in (BodyClearance): the clearances of the last step
        In/out:
          x0 (vec3, per particle, m): positions at the start of the step, moved with the body where
              followed
          v0 (vec3, per particle, m/s): velocities at the start of the step; set for bound pins
          x_stage (vec3, per particle, m): stage scratch
          v_stage (vec3, per particle, m/s): stage scratch
          x_scratch (vec3, per particle, m): stage scratch
          v_scratch (vec3, per particle, m/s): stage scratch
          acc_x (vec3, per particle, m/s): RK4 accumulator; zero before the step and after it
          acc_v (vec3, per particle, m/s^2): RK4 accumulator; likewise
          step_count (int32, 1 element): step counter, incremented by one
          carried (vec3, per particle, m): scratch, begin_step's following for body_collide (begin_step)
          candidates (BodyCandidates): the triangles gathered near particles at concave vertices
          fallbacks (int32, 1 element): incremented once per BVH query or gathering
        Outputs:
          x (vec3, per particle, m): positions at the end of the step
          v (vec3, per particle, m/s): velocities at the end of the step
          nearest (int32, per particle): nearest body vertex after the step
          clearance (BodyClearance): the clearances after the step
          contact (int32, per particle): 1 where the last body_collide pushed the particle out
          recorded (FollowRecord): the follow record for the next step (follow != 0)
        """
        _block, lane = wp.tid()
        stride = wp.block_dim()
        p = lane
        while p < n:
            _begin_step_at(p, x0, v0, inv_mass, body.points, body.indices, follow, recorded_in, full_within,
                           none_beyond, pins, particle_binding,
                           pinned, dt, step_count, carried)
            p += stride
        _block_sync()
        # RK4 stages ping-pong as ClothSolver.step's launches: x0 -> stage -> scratch -> stage -> x
        p = lane
        while p < n:
            _rk4_stage_at(p, x0, v0, x0, v0, inv_mass, drag, springs, gravity, wind, gusts, damping, 1.0, 0.5 * dt, 0.0,
                          acc_x, acc_v, x_stage, v_stage)
            p += stride
        _block_sync()
        p = lane
        while p < n:
            _rk4_stage_at(p, x0, v0, x_stage, v_stage, inv_mass, drag, springs, gravity, wind, gusts, damping, 2.0,
                          0.5 * dt, 0.0, acc_x, acc_v, x_scratch, v_scratch)
            p += stride
        _block_sync()
        p = lane
        while p < n:
            _rk4_stage_at(p, x0, v0, x_scratch, v_scratch, inv_mass, drag, springs, gravity, wind, gusts, damping, 2.0,
                          dt, 0.0, acc_x, acc_v, x_stage, v_stage)
            p += stride
        _block_sync()
        record = follow != 0 and strain_passes == 0
        p = lane
        while p < n:
            _rk4_stage_at(p, x0, v0, x_stage, v_stage, inv_mass, drag, springs, gravity, wind, gusts, damping, 1.0, 0.0,
                          dt, acc_x, acc_v, x, v)
            if collide != 0:  # its own particle only: no barrier after the stage
                collide_body(p, x, x0, v, inv_mass, body, params, step_count, 1, dt, nearest_in, clearance_in,
                             int(record), nearest, clearance, candidates, contact, fallbacks, recorded, carried, 0)
            p += stride
        if strain_passes == 0:
            return
        _block_sync()
        # the strain passes ping-pong as ClothSolver._limit_strain: x -> scratch -> stage -> scratch ... -> x,
        # and a single pass reads a copy of x in stage
        start = x
        if strain_passes == 1:
            start = x_stage
            p = lane
            while p < n:
                x_stage[p] = x[p]
                p += stride
            _block_sync()
        for k in range(strain_passes):
            last = k == strain_passes - 1
            src = start
            dst = x_scratch
            if k > 0:
                src = wp.where(k % 2 == 1, x_scratch, x_stage)
                dst = wp.where(k % 2 == 1, x_stage, x_scratch)
            if last:
                dst = x
            p = lane
            while p < n:
                _limit_strain_at(p, src, inv_mass, springs, max_stretch, start, wp.where(last, dt, 0.0), v, dst)
                if last and collide != 0:  # contact has the last word, in the same pose
                    collide_body(p, x, x, v, inv_mass, body, params, step_count, 0, dt, nearest, clearance, follow,
                                 nearest, clearance, candidates, contact, fallbacks, recorded, carried, 0)
                p += stride
            if not last:
                _block_sync()

    return step_in_block


# as BODY_COLLIDE: without the box queries, sm_90 spills at 384 lanes 192/172 -> 32/40 bytes
STEP_IN_BLOCK = {boxes: _step_in_block(boxes) for boxes in (True, False)}
step_in_block = STEP_IN_BLOCK[True]


@wp.kernel
def elastic_forces(
    x: wp.array(dtype=wp.vec3),
    springs: SpringNetwork,
    force: wp.array(dtype=wp.vec3),
):
    """Net elastic spring force on each particle, without damping, gravity or drag.

    This is the elastic force that drives the detail surface's wrinkles (Oshita & Makinouchi
    §4.3.1), carried to the detail samples by detail.carry_forces.

    Launch: one thread per particle (dim = num_particles).
    Inputs:
      x (vec3, per particle, m): positions
      springs (SpringNetwork): the cloth's springs, per spring and per particle's slot (ClothModel.springs)
    Outputs:
      force (vec3, per particle, N): sum of the spring forces on the particle
    """
    p = wp.tid()
    f = wp.vec3(0.0)
    still = wp.vec3(0.0)  # no dashpot: velocities do not enter
    for k in range(springs.adj_start[p], springs.adj_start[p + 1]):
        s = springs.adj_spring[k]
        q = springs.spring_j[s]
        if q == p:
            q = springs.spring_i[s]
        f += spring_force(x[p], x[q], still, still, springs.spring_rest[s], springs.spring_k_stretch[s],
                          springs.spring_k_compress[s], 0.0)
    force[p] = f
