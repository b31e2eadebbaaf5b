"""Hair strand kernels: particle polylines flattened with offsets, one launch for every strand.

Step order (composed by sim.hair_solver.HairSolver), four to six launches per substep:
  predict_positions (integration, pinned roots on the skin, root hold)
  -> [follow_guides]
  -> [shape_match_rotations (full variant) -> shape_match_step] x passes
  -> follow_the_leader (length, collision and the velocity update)
Each launch reads and writes every particle once: work that used to round-trip through a buffer
(window goals, root positions, FTL corrections) is recomputed or carried in registers instead,
because on a GPU the bytes moved, not the arithmetic, set the cost.
"""

import warp as wp

# no gradients are taken through these kernels: skipping the backward passes halves compile time;
# the lean launch path (no grid-stride loop) lowers per-thread overhead
wp.set_module_options({"enable_backward": False, "default_grid_stride": False})

from .collision import ColliderShape, collide_point
from .skinning import bound_position, face_frame

SHAPE_SIMPLIFIED = wp.constant(0)
SHAPE_FULL = wp.constant(1)


@wp.kernel
def predict_positions(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    gravity: wp.vec3,
    wind: wp.vec3,
    air_drag: float,
    damping: float,
    turbulence: float,
    turbulence_scale: float,
    turbulence_rate: float,
    clock: wp.array(dtype=float),
    time_offset: float,
    dt: float,
    bound: int,
    mesh_points: wp.array(dtype=wp.vec3),
    mesh_indices: wp.array(dtype=wp.int32),
    particle_binding: wp.array(dtype=wp.int32),
    bind_triangle: wp.array(dtype=wp.int32),
    bind_barycentric: wp.array(dtype=wp.vec3),
    bind_local: wp.array(dtype=wp.vec3),
    particle_strand: wp.array(dtype=wp.int32),
    root_binding: wp.array(dtype=wp.int32),
    root_local: wp.array(dtype=wp.vec3),
    hold: wp.array(dtype=float),
    hold_stiffness: float,
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
):
    """Symplectic Euler prediction of free particles; air_drag [1/s] pulls velocity toward the local
    wind, damping [1/s] decays it. The gusts' time is clock[0] + time_offset (the clock lives on the
    device, so a captured frame replays at any time).

    With bound != 0 the collider is posed for the end of the step: particles with a binding
    (particle_binding >= 0, the pinned roots) are placed on the skin, and every particle is pulled
    toward its groomed position carried by its root triangle's frame by hold * hold_stiffness: the
    global shape constraint of TressFX (Han & Harada), fading from the root to zero a few
    centimetres out, so the groom's lift and parting survive gravity while the lengths swing.
    """
    i = wp.tid()
    p = x[i]
    vel = v[i]
    if inv_mass[i] == 0.0:
        if bound != 0:
            b = particle_binding[i]
            if b >= 0:
                p = bound_position(mesh_points, mesh_indices, bind_triangle, bind_barycentric, bind_local, b)
    else:
        air = wind
        if turbulence > 0.0:
            # gusts: smooth noise in space and time scaled by the mean wind speed
            q = p * turbulence_scale
            time = (clock[0] + time_offset) * turbulence_rate
            speed = wp.length(wind)
            state = wp.rand_init(7)
            gust = wp.vec3(
                wp.noise(state, wp.vec4(q[0], q[1], q[2], time)),
                wp.noise(state, wp.vec4(q[0] + 31.7, q[1], q[2], time)),
                wp.noise(state, wp.vec4(q[0], q[1] + 57.1, q[2], time)),
            )
            air = wind + gust * (turbulence * speed)
        vel = vel + dt * (gravity + air_drag * (air - vel))
        vel = vel * wp.max(0.0, 1.0 - damping * dt)
        p = p + dt * vel
    if bound != 0:
        w = hold[i] * hold_stiffness
        if w > 0.0:
            s = particle_strand[i]
            rb = root_binding[s]
            root = bound_position(mesh_points, mesh_indices, bind_triangle, bind_barycentric, bind_local, rb)
            target = root + face_frame(mesh_points, mesh_indices, bind_triangle[rb]) * root_local[i]
            p = p + w * (target - p)
    x_out[i] = p
    v_out[i] = vel


@wp.func
def rotation_from_covariance(A: wp.mat33):
    """Optimal rotation of classic shape matching (Mueller et al. 2005): argmax_R trace(R^T A).

    The SVD runs in float64: float32 svd3 loses up to 1e-2 in R when two singular values are close,
    which hair windows (nearly straight or nearly planar) often have. Used to start the warm-started
    refinement below, so it runs once, not every substep.
    """
    Ad = wp.mat33d(A)
    U = wp.mat33d()
    sigma = wp.vec3d()
    V = wp.mat33d()
    wp.svd3(Ad, U, sigma, V)
    R = U * wp.transpose(V)
    if wp.determinant(R) < wp.float64(0.0):
        # reflect the axis of the smallest singular value (the window's normal for planar windows)
        k = int(0)
        if sigma[1] < sigma[k]:
            k = 1
        if sigma[2] < sigma[k]:
            k = 2
        for r in range(3):
            U[r, k] = -U[r, k]
        R = U * wp.transpose(V)
    return wp.mat33(R)


@wp.func
def refine_rotation(q: wp.quat, A: wp.mat33, iterations: int):
    """Turn q toward argmax_R trace(R^T A), warm-started from the last solution.

    With M = A R^T, trace(R'^T A) for R' = exp([w]) R is, to second order, F + w.g - w^T H w / 2
    with g = axial(M - M^T) (= sum_j r_j x a_j) and H = trace(M) I - sym(M). Near the optimum H is
    positive definite and the Newton step w = H^-1 g converges quadratically; elsewhere the step of
    Müller, Bender, Chentanez, Macklin 2016, w = g / |trace(M)|, which never flips, is taken.
    """
    for _it in range(iterations):
        R = wp.quat_to_matrix(q)
        M = A * wp.transpose(R)
        g = wp.vec3(M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1])
        tr = M[0, 0] + M[1, 1] + M[2, 2]
        H = wp.identity(n=3, dtype=float) * (tr * (1.0 + 1.0e-6)) - 0.5 * (M + wp.transpose(M))
        omega = g / (wp.abs(tr) + 1.0e-9)
        if tr > 0.0:
            detH = wp.determinant(H)
            # positive definite: leading minors positive (H[0,0] > 0 and the 2x2 minor > 0 and det > 0)
            minor = H[0, 0] * H[1, 1] - H[0, 1] * H[1, 0]
            if H[0, 0] > 0.0 and minor > 0.0 and detH > 1.0e-12 * tr * tr * tr:
                omega = wp.inverse(H) * g
        angle = wp.length(omega)
        if angle < 1.0e-9:
            break
        if angle > 1.0:
            omega = omega / angle
            angle = 1.0
        q = wp.normalize(wp.quat_from_axis_angle(omega / angle, angle) * q)
    return q


@wp.func
def window_centroid(x: wp.array(dtype=wp.vec3), first: int, size: int):
    c = wp.vec3(0.0)
    for k in range(size):
        c += x[first + k]
    return c / float(size)


@wp.kernel
def shape_match_rotations(
    x: wp.array(dtype=wp.vec3),
    window_first: wp.array(dtype=wp.int32),
    window_size: int,
    window_rest: wp.array(dtype=wp.vec3),
    exact: int,
    iterations: int,
    rotations: wp.array(dtype=wp.quat),
    centroids: wp.array(dtype=wp.vec3),
):
    """Per-window optimal rotation of the rest offsets onto the current window (full variant), and
    the window's centroid, which shape_match_step reads instead of summing the window again.

    exact = 1 solves it outright (float64 SVD); otherwise `iterations` refinement steps continue
    from the rotation stored last time.
    """
    w = wp.tid()
    first = window_first[w]
    base = w * window_size
    centroid = window_centroid(x, first, window_size)
    centroids[w] = centroid
    A = wp.mat33(0.0)
    for k in range(window_size):
        A += wp.outer(x[first + k] - centroid, window_rest[base + k])
    A = A / wp.sqrt(wp.max(wp.ddot(A, A), 1.0e-30))  # scale-free, so the 1e-9 guard is relative
    if exact != 0:
        rotations[w] = wp.quat_from_matrix(rotation_from_covariance(A))
    else:
        rotations[w] = refine_rotation(rotations[w], A, iterations)


@wp.func
def window_goal(x: wp.array(dtype=wp.vec3), first: int, size: int, k: int, rest: wp.array(dtype=wp.vec3),
                offsets: wp.array(dtype=float), rotations: wp.array(dtype=wp.quat),
                centroids: wp.array(dtype=wp.vec3), variant: int, w: int):
    """Goal of slot k of window w (its particles first .. first + size - 1).

    simplified (Hayashimoto et al. §3.6, window of 3): g_k = c + d_k u along the current first-to-last
    direction u, with d_k the rest offset along the rest first-to-last direction. No rotation, so
    curls straighten.
    full (Mueller et al. 2005): g_k = c + R r_k with r_k the rest offset from the rest centroid and R
    the window's optimal rotation and c its centroid, both from shape_match_rotations. A window of 3
    holds bend angles only; wider windows also hold torsion, so helices keep their shape.
    """
    if variant == SHAPE_SIMPLIFIED:
        e = x[first + size - 1] - x[first]
        length = wp.length(e)
        if length < 1.0e-12:
            return x[first + k]
        return window_centroid(x, first, size) + offsets[w * size + k] * (e / length)
    return centroids[w] + wp.quat_rotate(rotations[w], rest[w * size + k])


@wp.kernel
def shape_match_step(
    x: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    particle_strand: wp.array(dtype=wp.int32),
    window_at: wp.array(dtype=wp.int32),
    window_size: int,
    window_rest: wp.array(dtype=wp.vec3),
    window_offsets: wp.array(dtype=float),
    rotations: wp.array(dtype=wp.quat),
    centroids: wp.array(dtype=wp.vec3),
    variant: int,
    stiffness: float,
    x_out: wp.array(dtype=wp.vec3),
):
    """One shape-matching pass: each free particle moves toward the average goal of the windows
    that contain it (Jacobi: every goal is computed from x, results go to x_out).

    window_at[j] is the window starting at particle j (-1 if none); windows never cross strands,
    so a window starting at i - k inside this strand holds particle i at slot k. Each particle
    computes the goals of its windows itself instead of reading them from a buffer of goals: the
    neighbours' positions it reads are in cache, a goal buffer would be a round trip to memory.
    """
    i = wp.tid()
    p = x[i]
    if inv_mass[i] == 0.0:
        x_out[i] = p
        return
    strand = particle_strand[i]
    goal = wp.vec3(0.0)
    count = float(0.0)
    for k in range(window_size):
        j = i - k
        if j >= 0:
            if particle_strand[j] == strand:
                w = window_at[j]
                if w >= 0:
                    goal += window_goal(x, j, window_size, k, window_rest, window_offsets, rotations, centroids, variant, w)
                    count += 1.0
    if count > 0.0:
        p = p + stiffness * (goal / count - p)
    x_out[i] = p


@wp.kernel
def follow_the_leader(
    x: wp.array(dtype=wp.vec3),
    x_prev: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    strand_start: wp.array(dtype=wp.int32),
    rest_length: wp.array(dtype=float),
    pinned_per_strand: int,
    collide_mode: int,
    shape: ColliderShape,
    margin: float,
    search: float,
    use_clearance: int,
    clearance: wp.array(dtype=float),
    ftl_damping: float,
    dt: float,
    v: wp.array(dtype=wp.vec3),
):
    """Inextensibility by follow-the-leader (Mueller et al. 2012), root to tip, one thread per strand,
    then the velocities.

    Each particle is put at its rest distance from its parent; a contact push-out is resolved inline
    and the particle is then put back on the sphere of rest radius, so every segment leaves with its
    exact rest length. With use_clearance != 0, clearance (collision.points_clearance of the
    positions before this pass, computed in parallel) skips the collider query for particles that
    moved too little to touch: the same result with fewer queries in this serial loop, which on a
    GPU is latency-bound. Velocities are v = (x - x_prev) / dt minus ftl_damping * d_(i+1) / dt for free
    particles, d_(i+1) the child's correction (dynamic FTL); the correction is carried to the next
    particle in a register rather than stored.
    """
    s = wp.tid()
    start = strand_start[s]
    end = strand_start[s + 1]
    for i in range(start, end):
        correction = wp.vec3(0.0)
        if i - start >= pinned_per_strand:
            parent = x[i - 1]
            predicted = x[i]
            length = rest_length[i]
            d = predicted - parent
            dist = wp.length(d)
            if dist < 1.0e-12:
                d = wp.vec3(0.0, -1.0, 0.0)
                if i - start >= 2:
                    d = parent - x[i - 2]
                dist = wp.length(d)
            p = parent + d * (length / dist)
            near = True
            if use_clearance != 0:
                near = clearance[i] - wp.length(p - predicted) <= margin + 1.0e-6
            if collide_mode != 0 and near:
                # putting the particle back at rest length can re-enter the collider near a crease
                # (between two spheres, in a concave corner); a second round settles it
                for _round in range(2):
                    pushed = collide_point(p, collide_mode, shape, margin, search)
                    if pushed == p:
                        break
                    p = pushed
                    d = p - parent
                    dist = wp.length(d)
                    if dist > 1.0e-12:
                        p = parent + d * (length / dist)
            correction = p - predicted
            x[i] = p
        if i > start:
            j = i - 1
            vel = (x[j] - x_prev[j]) / dt
            if inv_mass[j] > 0.0:
                vel = vel - (ftl_damping / dt) * correction
            v[j] = vel
    last = end - 1
    v[last] = (x[last] - x_prev[last]) / dt


@wp.kernel
def count_unhealthy(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    max_speed: float,
    bad_count: wp.array(dtype=wp.int32),
    first_bad: wp.array(dtype=wp.int32),
):
    """Count particles that are non-finite or faster than max_speed [m/s]; remember the lowest index."""
    i = wp.tid()
    p = x[i]
    vel = v[i]
    finite = wp.isfinite(p) and wp.isfinite(vel)
    if (not finite) or wp.length(vel) > max_speed:
        wp.atomic_add(bad_count, 0, 1)
        wp.atomic_min(first_bad, 0, i)


@wp.func
def guide_point(guide_points: wp.array(dtype=wp.vec3), g: int, count: int, s: float):
    """Point at normalised arc parameter s in [0, 1] along guide g (count vertices, evenly spaced)."""
    u = wp.clamp(s, 0.0, 1.0) * float(count - 1)
    k = wp.min(int(u), count - 2)
    t = u - float(k)
    return (1.0 - t) * guide_points[g * count + k] + t * guide_points[g * count + k + 1]


@wp.kernel
def follow_guides(
    x: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    particle_strand: wp.array(dtype=wp.int32),
    strand_start: wp.array(dtype=wp.int32),
    strand_guides: wp.array(dtype=wp.vec3i),
    strand_guide_weights: wp.array(dtype=wp.vec3),
    particle_param: wp.array(dtype=float),
    guide_frames: wp.array(dtype=wp.vec3),
    num_frames: int,
    num_guides: int,
    guide_vertices: int,
    guide_fps: float,
    clock: wp.array(dtype=float),
    time_offset: float,
    stiffness: float,
):
    """Pull each free particle toward its captured guides' shape: the strand's own root plus the
    weighted guides' offsets from their roots at the particle's normalised arc position. The guides
    are linear between captured frames (guide_frames: frame-major, held past the ends) at time
    clock[0] + time_offset. stiffness is the fraction of the way moved this substep."""
    i = wp.tid()
    if inv_mass[i] == 0.0:
        return
    u = wp.clamp((clock[0] + time_offset) * guide_fps, 0.0, float(num_frames - 1))
    f = wp.min(int(u), wp.max(num_frames - 2, 0))
    t = wp.min(u - float(f), 1.0)
    f1 = wp.min(f + 1, num_frames - 1)
    strand = particle_strand[i]
    g = strand_guides[strand]
    w = strand_guide_weights[strand]
    s = particle_param[i]
    offset = wp.vec3(0.0)
    for k in range(3):
        if w[k] > 0.0:
            a = f * num_guides + g[k]
            b = f1 * num_guides + g[k]
            shape = (1.0 - t) * (guide_point(guide_frames, a, guide_vertices, s) - guide_frames[a * guide_vertices])
            shape += t * (guide_point(guide_frames, b, guide_vertices, s) - guide_frames[b * guide_vertices])
            offset += w[k] * shape
    target = x[strand_start[strand]] + offset
    x[i] = x[i] + stiffness * (target - x[i])
