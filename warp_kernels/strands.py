"""Hair strand kernels: particle polylines flattened with offsets, one launch for every strand.

Step order (composed by sim.hair_solver.HairSolver), a fixed sequence of launches per substep:

    predict_positions (integration, pinned roots on the skin, root hold)
    -> [follow_guides]
    -> [shape_match_rotations (full variant) -> shape_match_step] x passes
    -> anchor_frame -> contact_motion (how far the collider moved near these strands)
    -> [to_lanes, in lane order]
    -> [find_short_lists -> list_leaves_ahead (the sphere tree's walks, in parallel)]
    -> follow_the_leader (length, collision and the velocity update)
    -> [from_lanes, in lane order]

In lane order (lane_slot, a GPU's) the copies in and out are their own launches, each gathering
what it reads so that its writes stay consecutive: stores scattered across a 3.2M-particle array
cost an H100 several times the gathers (measured, see BENCHMARKS.md).

step_strands is the whole sequence from root_frames to follow_the_leader in one launch, guides
included, a thread per strand (after anchor_frame and contact_motion, and the tree walks queued ahead
from the start positions), with the same strands bit for bit. frame_in_block is a whole frame of
those substeps in one launch, a block of lanes per strand and a lane per particle, its state in
registers from the frame's start to its end and the collider posed for every substep ahead of it
(FramePoses), against the sphere tree, the mesh or no collider.

Each launch reads and writes every particle once: work that used to round-trip through a buffer
(window goals, root positions, FTL corrections) is recomputed or carried in registers instead,
because on a GPU the bytes moved, not the arithmetic, set the cost.
"""

# float(0.0), int(0) and bool(False) declare variables that a kernel reassigns (Warp treats a
# bare literal as a constant); the nested ifs are kept as the kernels were written and verified
# ruff: noqa: UP018, RUF046, SIM102

from typing import Any

import warp as wp

from ._options import MODULE_OPTIONS, deferred_module

wp.set_module_options(MODULE_OPTIONS)
# the substep in launches apart (a GPU's way, HairSolver.fused off) with the lanes' copies, the walks
# queued ahead and the length pass's variants: a CPU run steps fused and never launches them, so they
# compile in a module of their own, only for the runs that do
APART = deferred_module(__name__ + ".apart")
# the render children's interpolation (sim.hair_children), launched once a frame by scenes that ask for them
CHILDREN = deferred_module(__name__ + ".children")
# a frame's collider poses made ahead of frame_in_block (HairSolver.frame_in_block, which opts in)
FRAME_POSES = deferred_module(__name__ + ".frame_poses", opt_in=True)

from .collision import (COLLIDE_MESH, COLLIDE_SPHERE_TREE, ColliderShape, collide_point, collide_point_bounded,
                        collide_point_listed, collide_point_listed_loose, collide_point_listed_mesh, list_deep_point,
                        grow_ancestors, pseudo_normal_distance, sphere_tree_nearest)
from .skinning import SkinBinding, bound_position, face_frame, skinned_point, triangle_frame

SHAPE_SIMPLIFIED = wp.constant(0)
TAUT = wp.constant(0.995)  # hold_in_comb: a root-to-comb chain this close to straight is laid straight
SHAPE_FULL = wp.constant(1)
NO_BOUND = wp.constant(-1.0e30)  # a contact bound that says nothing: the next query looks as far as it can
# interpolate_children skips a push only where its bound clears the margin by this much more, for the
# float rounding of the bound's own arithmetic
CHILD_PUSH_TOLERANCE = wp.constant(1.0e-5)  # m
MOTION_GRID = wp.constant(16)  # cells per axis of ContactMotion.cells
# m per count of ContactMotion's fixed-point motions. A float atomic max is a compare-and-swap loop on a
# GPU, and thousands of collider vertices raising the same few cells retried it in turn (contact_motion
# 0.42 ms a launch on an H100 for 6k vertices); an integer max is one native atomic
MOTION_UNIT = wp.constant(1.0e-7)
MOTION_LIMIT = wp.constant(100.0)  # m: motions are counted up to this (1e9 counts, inside int32)
# m: strand_quality's queries look this much beyond what a particle's distance bound leaves in doubt
QUALITY_QUERY_SLACK = wp.constant(0.005)
# rad^2: below this a turn's series (small_turn) needs two terms: the third, a^4 / 3840, is under
# float rounding of the first
SHORT_TURN_SQ = wp.constant(1.0e-3)


@wp.struct
class LaneOrder:
    """Where the length pass keeps its per-particle arrays: in particle order (lanes = 0, the
    arrays unused) or in lane order over all strands, each strand in a lane (see lane_slot).

    Neighbouring strands take neighbouring lanes (sim.hair_solver.lanes_by_root): a warp then steps
    32 strands that meet the head at about the same particles, instead of 32 from all over the
    scalp, each of which keeps it waiting for its own collisions.

    Fields:
      lanes (int): strands in lane order (all of them); 0 for particle order
      lane_of (int32, per strand): each strand's lane
      strand_of (int32, per lane): each lane's strand
    """

    lanes: int
    lane_of: wp.array(dtype=wp.int32)
    strand_of: wp.array(dtype=wp.int32)


@wp.func
def lane_slot(start: int, lane: int, k: int, lanes: int):
    """Where the length pass finds particle k of a strand (whose first particle is `start`): in
    particle order when lanes is 0, else in lane order, k * lanes + lane, where the k-th particles
    of `lanes` strands lie side by side. A thread per lane walking its strand's particles then
    reads, with its warp's 31 neighbours, 32 consecutive elements at each step instead of 32
    far-apart ones.

    Inputs:
      start (int, index): the strand's first particle
      lane (int, index): the strand's lane (LaneOrder.lane_of); unused in particle order
      k (int, index): the particle's place along it, from 0 at the root
      lanes (int): 0 for particle order, else the strands in lane order (all of them)
    Returns:
      int (index): the element of a per-particle array of the length pass that holds the particle
    """
    if lanes > 0:
        return k * lanes + lane
    return start + k


@wp.struct
class StrandForces:
    """What moves free hair particles in the prediction (predicted_position): gravity, air drag
    toward a wind with optional gusts of smooth noise in space and time, and damping.

    Fields:
      gravity (vec3, m/s^2): acceleration of gravity, e.g. (0, -9.81, 0)
      wind (vec3, m/s): mean air velocity
      air_drag (float, 1/s): rate at which velocity is pulled toward the local wind
      damping (float, 1/s): rate at which velocity decays
      turbulence (float, fraction of the wind speed): gust strength; 0 turns gusts off
      turbulence_scale (float, 1/m): spatial frequency of the gusts
      turbulence_rate (float, 1/s): how fast the gust pattern changes
    """

    gravity: wp.vec3
    wind: wp.vec3
    air_drag: float
    damping: float
    turbulence: float
    turbulence_scale: float
    turbulence_rate: float


@wp.func
def air_velocity(wind: wp.vec3, turbulence: float, scale: float, rate: float, p: wp.vec3, time: float):
    """The air's velocity at p: the mean wind, with gusts where turbulence > 0 (smooth noise in space and
    time scaled by the mean wind speed). The hair's gusting_wind and the cloth's wind_gusts.

    Inputs:
      wind (vec3, m/s): the mean wind
      turbulence (float, fraction): gust strength as a fraction of the wind speed; 0 for none
      scale (float, 1/m): the gusts' spatial frequency
      rate (float, 1/s): how fast their pattern changes
      p (vec3, m): where
      time (float, s): the gusts' time
    Returns:
      vec3 (m/s): the air's velocity
    """
    air = wind
    if turbulence > 0.0:
        q = p * scale
        t = time * rate
        speed = wp.length(wind)
        state = wp.rand_init(7)
        gust = wp.vec3(
            wp.noise(state, wp.vec4(q[0], q[1], q[2], t)),
            wp.noise(state, wp.vec4(q[0] + 31.7, q[1], q[2], t)),
            wp.noise(state, wp.vec4(q[0], q[1] + 57.1, q[2], t)),
        )
        air = wind + gust * (turbulence * speed)
    return air


@wp.func
def gusting_wind(forces: StrandForces, p: wp.vec3, time: float):
    """The air's velocity at p for the strands (air_velocity of forces' wind and gusts).

    Inputs:
      forces (StrandForces): the wind and its gusts
      p (vec3, m): where
      time (float, s): the gusts' time
    Returns:
      vec3 (m/s): the air's velocity
    """
    return air_velocity(forces.wind, forces.turbulence, forces.turbulence_scale, forces.turbulence_rate, p, time)


@wp.func(inline=True)
def predicted_position(
    p: wp.vec3,
    vel: wp.vec3,
    inv_mass: float,
    forces: StrandForces,
    air: wp.vec3,
    dt: float,
    skin: SkinBinding,
    binding: int,
    target: wp.vec3,
    weight: float,
):
    """One particle's prediction (predict_positions): a pinned particle with a binding is put on the
    skin, a free one integrates gravity, drag toward the air's velocity (implicit, so stable for any
    drag) and damping, and either is then pulled `weight` of the way to its groomed position carried
    by its root's frame.

    Inputs:
      p (vec3, m): position at the start of the substep
      vel (vec3, m/s): velocity at the start of the substep
      inv_mass (float): 0 marks a pinned particle
      forces (StrandForces): gravity, drag and damping
      air (vec3, m/s): the air's velocity at p (gusting_wind); read only for a free particle
      dt (float, s): substep length
      skin (SkinBinding): the bindings on the collider posed for the end of the substep; read only
          with a binding
      binding (int, index): the pinned particle's binding, -1 for none
      target (vec3, m): the particle's groomed position carried by its root's frame in this pose
          (root origin + root frame * groomed offset); read only when weight > 0
      weight (float, fraction): share of the way to target moved; 0 for none
    Returns:
      vec3 (m): the predicted position
      vec3 (m/s): the velocity after forces; a pinned particle keeps its own
    """
    if inv_mass == 0.0:
        if binding >= 0:
            p = bound_position(skin, binding)
    else:
        # the drag is taken implicitly: explicit, a drag past 2/dt overshot the wind further each substep
        h = dt / (1.0 + forces.air_drag * dt)
        vel = (vel + h * (forces.gravity + forces.air_drag * (air - vel))) * wp.max(0.0, 1.0 - forces.damping * dt)
        p = p + dt * vel
    if weight > 0.0:
        p = p + weight * (target - p)
    return p, vel


@wp.kernel(module=APART)
def predict_positions(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    forces: StrandForces,
    clock: wp.array(dtype=float),
    time_offset: float,
    dt: float,
    bound: int,
    skin: SkinBinding,
    particle_binding: wp.array(dtype=wp.int32),
    particle_strand: wp.array(dtype=wp.int32),
    root_origin: wp.array(dtype=wp.vec3),
    root_frame: wp.array(dtype=wp.mat33),
    root_local: wp.array(dtype=wp.vec3),
    hold: wp.array(dtype=float),
    hold_stiffness: float,
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
    first: int,
):
    """First launch of a hair substep: symplectic Euler prediction, pinned roots on the skin, root hold.

    Free particles integrate gravity, air drag toward the local wind (air_drag, with optional gusts of
    smooth noise in space and time) and damping. The gusts' time is clock[0] + time_offset: the clock
    lives on the device, so a captured frame replays at any time.

    With bound != 0 the collider is posed for the end of the substep: particles with a binding
    (particle_binding >= 0, the pinned roots) are placed on the skin, and every particle is pulled
    toward its groomed position carried by its root triangle's frame by hold * hold_stiffness: the
    global shape constraint of TressFX (Han & Harada), fading from the root to zero a few centimetres
    out, so the groom's lift and parting survive gravity while the lengths swing. With bound == 0 the
    mesh and binding arrays are not read and may be None.

    Launch: one thread per particle of a range of whole strands (dim = particles in the range).
    Inputs:
      x (vec3, per particle, m): positions at the start of the substep
      v (vec3, per particle, m/s): velocities at the start of the substep
      inv_mass (float, per particle): 0 marks pinned particles; other values are not used as masses
      forces (StrandForces): gravity, wind with its gusts, drag and damping
      clock (float, 1 element, s): device clock
      time_offset (float, s): time of this substep relative to clock[0]
      dt (float, s): substep length
      bound (int, flag): non-zero when the strands are bound to the collider below
      skin (SkinBinding): the bindings on the collider posed for the end of the substep
      particle_binding (int32, per particle): binding index of each pinned particle, -1 when unbound
      particle_strand (int32, per particle): strand of each particle
      root_origin (vec3, per strand, m): the root's bound position for this pose (root_frames)
      root_frame (mat33, per strand): the root triangle's frame for this pose (root_frames)
      root_local (vec3, per particle, m): groomed offset from the root in the root triangle's frame
      hold (float, per particle): root-hold weight, 1 at the root falling to 0 along the strand
      hold_stiffness (float, fraction per substep): share of the way to the groomed position moved
      first (int, index): the range's first particle; thread t works on particle first + t (0 for all of them)
    Outputs:
      x_out (vec3, per particle, m): predicted positions
      v_out (vec3, per particle, m/s): velocities after forces; pinned particles keep theirs
    """
    i = wp.tid() + first
    p = x[i]
    binding = int(-1)
    weight = float(0.0)
    target = wp.vec3(0.0)
    if bound != 0:
        if inv_mass[i] == 0.0:
            binding = particle_binding[i]
        weight = hold[i] * hold_stiffness
        if weight > 0.0:
            s = particle_strand[i]
            target = root_origin[s] + root_frame[s] * root_local[i]
    air = gusting_wind(forces, p, clock[0] + time_offset)
    p, vel = predicted_position(p, v[i], inv_mass[i], forces, air, dt, skin, binding, target, weight)
    x_out[i] = p
    v_out[i] = vel


@wp.kernel(module=APART)
def root_frames(
    skin: SkinBinding,
    root_binding: wp.array(dtype=wp.int32),
    root_origin: wp.array(dtype=wp.vec3),
    root_frame: wp.array(dtype=wp.mat33),
    first: int,
):
    """Where each strand's root sits on the posed mesh and its triangle's frame, once per strand: the
    root hold of predict_positions carries every held particle by them, which would otherwise
    rebuild the same frame for each of them.

    Launch: one thread per strand of a range of strands (dim = strands in the range).
    Inputs:
      skin (SkinBinding): the bindings on the collider posed for the end of the substep
      root_binding (int32, per strand): binding of the strand's root particle
      first (int, index): the range's first strand; thread t works on strand first + t (0 for all of them)
    Outputs:
      root_origin (vec3, per strand, m): the root's bound position (skinning.bound_position)
      root_frame (mat33, per strand): its triangle's frame (skinning.face_frame)
    """
    s = wp.tid() + first
    rb = root_binding[s]
    root_origin[s] = bound_position(skin, rb)
    root_frame[s] = face_frame(skin.mesh_points, skin.mesh_indices, skin.triangle[rb])


@wp.func
def rotation_from_covariance(A: wp.mat33):
    """Optimal rotation of classic shape matching (Mueller et al. 2005): argmax_R trace(R^T A).

    The SVD runs in float64: float32 svd3 loses up to 1e-2 in R when two singular values are close,
    which hair windows (nearly straight or nearly planar) often have. It only starts the warm-started
    refinement (refine_rotation), so it runs once, not every substep.

    Inputs:
      A (mat33): covariance sum_k (x_k - c) r_k^T of current and rest offsets; any scale
    Returns:
      mat33: proper rotation (determinant +1); a reflection is turned into one by flipping the axis
          of the smallest singular value
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
def small_turn(omega: wp.vec3, angle_sq: float):
    """The unit quaternion turning by |omega| radians about omega, for |omega| <= 1 radian.

    sin(a/2)/a and cos(a/2) as series in a^2, cut where the next term is below float rounding for
    a <= 1: no square root, division, sine or cosine (refine_rotation takes one per window and pass).
    Below SHORT_TURN_SQ, the turns between substeps, two terms already are.

    Inputs:
      omega (vec3, rad): the rotation vector, no longer than 1
      angle_sq (float, rad^2): |omega|^2
    Returns:
      quat: the rotation, unit to float rounding
    """
    a2 = angle_sq
    s = float(0.0)
    c = float(0.0)
    if a2 < SHORT_TURN_SQ:
        s = 0.5 - a2 * (1.0 / 48.0)
        c = 1.0 - a2 * (1.0 / 8.0)
    else:
        s = 0.5 + a2 * (-1.0 / 48.0 + a2 * (1.0 / 3840.0 + a2 * (-1.0 / 645120.0 + a2 * (1.0 / 185794560.0))))
        c = 1.0 + a2 * (-1.0 / 8.0 + a2 * (1.0 / 384.0 + a2 * (-1.0 / 46080.0 + a2 * (1.0 / 10321920.0))))
    return wp.quat(omega[0] * s, omega[1] * s, omega[2] * s, c)


@wp.func
def rotation_matrix(q: wp.quat):
    """The rotation matrix of a unit quaternion, from its ten pairwise products: wp.quat_to_matrix
    rotates the three axes one by one, about four times the arithmetic, and shape matching takes
    two per window and pass.

    Inputs:
      q (quat): a unit quaternion (x, y, z, w)
    Returns:
      mat33: its rotation
    """
    x = q[0]
    y = q[1]
    z = q[2]
    w = q[3]
    xx = x * x
    yy = y * y
    zz = z * z
    xy = x * y
    xz = x * z
    yz = y * z
    wx = w * x
    wy = w * y
    wz = w * z
    return wp.mat33(1.0 - 2.0 * (yy + zz), 2.0 * (xy - wz), 2.0 * (xz + wy),
                    2.0 * (xy + wz), 1.0 - 2.0 * (xx + zz), 2.0 * (yz - wx),
                    2.0 * (xz - wy), 2.0 * (yz + wx), 1.0 - 2.0 * (xx + yy))


@wp.func
def refine_rotation(q: wp.quat, A: wp.mat33, iterations: int):
    """Turn q toward argmax_R trace(R^T A), warm-started from the last solution.

    With M = A R^T, trace(R'^T A) for R' = exp([w]) R is, to second order, F + w.g - w^T H w / 2
    with g = axial(M - M^T) (= sum_j r_j x a_j) and H = trace(M) I - sym(M). Near the optimum H is
    positive definite and the Newton step w = H^-1 g converges quadratically; elsewhere the step of
    Müller, Bender, Chentanez, Macklin 2016, w = g / |trace(M)|, which never flips, is taken. Steps
    are capped at 1 radian.

    Inputs:
      q (quat): rotation to start from, usually last substep's
      A (mat33, m^2): covariance of current and rest offsets, unscaled: the positive-definite test
          and the fallback's guard are relative to A's size (windows of 0.1 mm or more stay clear of
          float32's smallest normal numbers)
      iterations (int): most Newton steps; stops early when a step is below 1e-9 radians
    Returns:
      quat: the refined unit rotation
    """
    for _it in range(iterations):
        R = rotation_matrix(q)
        M = A * wp.transpose(R)
        g = wp.vec3(M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1])
        tr = M[0, 0] + M[1, 1] + M[2, 2]
        # H = tr (1 + 1e-6) I - sym(M) is symmetric: its six cofactors give both the leading minors
        # (positive definite: all positive) and the Newton step adj(H) g / det(H)
        d = tr * (1.0 + 1.0e-6)
        h00 = d - M[0, 0]
        h11 = d - M[1, 1]
        h22 = d - M[2, 2]
        h01 = -0.5 * (M[0, 1] + M[1, 0])
        h02 = -0.5 * (M[0, 2] + M[2, 0])
        h12 = -0.5 * (M[1, 2] + M[2, 1])
        c00 = h11 * h22 - h12 * h12
        c01 = h02 * h12 - h01 * h22
        c02 = h01 * h12 - h02 * h11
        det = h00 * c00 + h01 * c01 + h02 * c02
        minor = h00 * h11 - h01 * h01
        omega = wp.vec3(0.0)
        if tr > 0.0 and h00 > 0.0 and minor > 0.0 and det > 1.0e-12 * tr * tr * tr:
            c11 = h00 * h22 - h02 * h02
            c12 = h01 * h02 - h00 * h12
            omega = wp.vec3(c00 * g[0] + c01 * g[1] + c02 * g[2], c01 * g[0] + c11 * g[1] + c12 * g[2],
                            c02 * g[0] + c12 * g[1] + minor * g[2]) * (1.0 / det)
        else:
            # the step of Müller et al.; its guard relative to A's size (A is not normalised)
            omega = g / wp.max(wp.abs(tr) + 1.0e-9 * wp.sqrt(wp.ddot(A, A)), 1.0e-30)
        angle_sq = wp.dot(omega, omega)
        if angle_sq < 1.0e-18:
            break
        if angle_sq > 1.0:
            omega = omega / wp.sqrt(angle_sq)
            angle_sq = 1.0
        q = small_turn(omega, angle_sq) * q
        # both factors are unit to rounding, so |q|^2 = 1 + e with e tiny: one Newton step of the
        # norm, q (3 - |q|^2) / 2, leaves an error of e^2, without wp.normalize's root and divisions
        q = q * (1.5 - 0.5 * wp.dot(q, q))
    return q


@wp.func
def window_centroid(x: Any, first: int, stride: int, size: int):
    """Mean position of a window's particles, held at first, first + stride, ... (size of them).

    Inputs:
      x (vec3, per particle or lane slot, m): positions, an array or a block's shared tile (frame_in_block)
      first (int, index): element of the window's first particle
      stride (int): elements from one particle of the strand to the next (1 in particle order, the
          lane count in lane order, see lane_slot)
      size (int): particles in the window
    Returns:
      vec3 (m): centroid
    """
    c = wp.vec3(0.0)
    for k in range(size):
        c += x[first + k * stride]
    return c / float(size)


@wp.func
def window_rotation(x: Any, first: int, stride: int, size: int, rest_local: Any, rest_centroid: wp.vec3, q: wp.quat,
                    exact: int, iterations: int):
    """A window's optimal rotation of its rest offsets onto its current particles, and its centroid
    (full variant): solved outright (exact != 0) or refined from q, its last rotation.

    Inputs:
      x (vec3, per particle or lane slot, m): current positions, an array or a block's shared tile
      first (int, index): element of the window's first particle
      stride (int): elements from one particle to the next (window_centroid)
      size (int): particles in the window
      rest_local (vec3, per particle or lane slot, m): rest positions from the strand's root, in the
          order of x (an array, or a tile with x)
      rest_centroid (vec3, m): the window's rest centroid from the strand's root
      q (quat): the window's last rotation; read only when exact == 0
      exact (int, flag): non-zero solves from scratch (float64 SVD)
      iterations (int): refinement steps when exact == 0
    Returns:
      quat: the window's rotation
      vec3 (m): its centroid
    """
    # the rest offsets sum to zero, so offsets from the window's first particle give the covariance
    # of offsets from its centroid without waiting for the centroid
    x0 = x[first]
    A = wp.mat33(0.0)
    c = x0
    for k in range(1, size):
        p = x[first + k * stride]
        c += p
        A += wp.outer(p - x0, rest_local[first + k * stride] - rest_centroid)
    centroid = c / float(size)
    if exact != 0:
        return wp.quat_from_matrix(rotation_from_covariance(A)), centroid
    return refine_rotation(q, A, iterations), centroid


@wp.func
def window_frame(q: wp.quat, centroid: wp.vec3, rest_centroid: wp.vec3):
    """A full window's goals as one map of its particles' rest positions.

    Its goal for a particle, c + R (X - C0) with X the particle's rest position and C0 the window's
    rest centroid, is R L + t with L = X - root, the rest position from the strand's root, and
    t = c - R (C0 - root). A particle's goals summed over its windows are then (sum R) L + sum t: the
    windows' matrices are summed and applied once, instead of every window rotating an offset of
    its own (shape_match_step, shaped_position). Rest positions from the root, not from the world's
    origin, keep the terms that cancel in that sum no longer than a strand.

    Inputs:
      q (quat): the window's rotation
      centroid (vec3, m): its current centroid c
      rest_centroid (vec3, m): its rest centroid from the strand's root, C0 - root
    Returns:
      mat33: R
      vec3 (m): t
    """
    R = rotation_matrix(q)
    return R, centroid - R * rest_centroid


@wp.func
def solved_window(x: Any, first: int, stride: int, size: int, rest_local: Any, rest_centroid: wp.vec3,
                  rotations: wp.array(dtype=wp.quat), w: int, exact: int, iterations: int):
    """A full window solved (window_rotation) and its goal map (window_frame); its rotation kept.

    Inputs:
      x (vec3, per particle or lane slot, m): current positions, an array or a block's shared tile
      first (int, index): element of the window's first particle
      stride (int): elements from one particle to the next (window_centroid)
      size (int): particles in the window
      rest_local (vec3, per particle or lane slot, m): rest positions from the strand's root, in the
          order of x
      rest_centroid (vec3, m): the window's rest centroid from the strand's root
      w (int, index): the window
      exact (int, flag): non-zero solves from scratch
      iterations (int): refinement steps when exact == 0
    In/out:
      rotations (quat, per window): the window's last rotation in, its new one out
    Returns:
      mat33: the goal map's rotation R
      vec3 (m): its translation t
    """
    q, c = window_rotation(x, first, stride, size, rest_local, rest_centroid, rotations[w], exact, iterations)
    rotations[w] = q
    return window_frame(q, c, rest_centroid)


@wp.func
def full_shaped_position(p: wp.vec3, k: int, count: int, window_size: int, stiffness: float, frames: Any,
                         translations: Any, at: int, stride: int, rest_local: wp.vec3):
    """A free particle moved by the pulls (goal - p) of the full windows holding it (window_frame),
    summed and divided by the window size: each window's pulls add to no net force or torque, so the
    pass moves no momentum (a mean over the windows holding each particle weighted the ends more and
    left strands on a still head swinging without end).

    The windows holding the k-th particle of a strand start at its k - window_size + 1 .. k, those
    inside the strand; the sums run over exactly those, with no test per window, so the matrix sum
    is not carried through branches.

    Inputs:
      p (vec3, m): the particle's position before the pass
      k (int, index): its place along its strand
      count (int): the strand's particles
      window_size (int): particles per window
      stiffness (float, fraction): share of the way to the goal moved, in (0, 1]
      frames (mat33, per window or slot): the windows' rotations (an array, or a block's shared tile)
      translations (vec3, per window or slot, m): the windows' goal translations (likewise)
      at (int, index): where frames and translations hold the window starting at the particle
          (whether or not one does); the one starting j particles before is at at - j * stride
      stride (int): elements from one window of the strand to the next
      rest_local (vec3, m): the particle's rest position from its strand's root
    Returns:
      vec3 (m): the particle's position after the pass; p itself when no window holds it
    """
    nearest = k - wp.min(k, count - window_size)
    farthest = wp.min(k, window_size - 1)
    if farthest < nearest:
        return p
    frame_sum = wp.mat33(0.0)
    goal = wp.vec3(0.0)
    for j in range(nearest, farthest + 1):
        frame_sum += frames[at - j * stride]
        goal += translations[at - j * stride]
    goal += frame_sum * rest_local
    return p + stiffness * (goal - float(farthest - nearest + 1) * p) / float(window_size)


@wp.kernel(module=APART)
def shape_match_rotations(
    x: wp.array(dtype=wp.vec3),
    window_first: wp.array(dtype=wp.int32),
    window_size: int,
    rest_local: wp.array(dtype=wp.vec3),
    window_rest_centroid: wp.array(dtype=wp.vec3),
    exact: int,
    iterations: int,
    rotations: wp.array(dtype=wp.quat),
    frames: wp.array(dtype=wp.mat33),
    translations: wp.array(dtype=wp.vec3),
    first: int,
):
    """Per-window optimal rotation of the rest offsets onto the current window (full variant).

    Also stores the window's goals as a map of rest positions (window_frame), which shape_match_step
    reads instead of solving the window again. exact = 1 solves it outright (float64 SVD); otherwise
    iterations refinement steps continue from the rotation stored last time, which is cheaper and,
    between substeps, as good.

    Launch: one thread per window of a range of whole strands (dim = windows in the range).
    Inputs:
      x (vec3, per particle, m): current positions
      window_first (int32, per window): first particle of each window
      window_size (int): particles per window
      rest_local (vec3, per particle, m): rest positions from each strand's root
          (sim.strands.ShapeWindows.rest_local)
      window_rest_centroid (vec3, per window, m): the window's rest centroid from its strand's root
          (sim.strands.ShapeWindows.rest_centroid)
      exact (int, flag): non-zero solves from scratch (first substep, after a reset)
      iterations (int): refinement steps when exact == 0
      first (int, index): the range's first window; thread t works on window first + t (0 for all of them)
    In/out:
      rotations (quat, per window): last rotations in (read only when exact == 0), new ones out
    Outputs:
      frames (mat33, per window): each window's rotation as a matrix (window_frame)
      translations (vec3, per window, m): the translation of each window's goals (window_frame)
    """
    w = wp.tid() + first
    rest_centroid = window_rest_centroid[w]
    q, centroid = window_rotation(x, window_first[w], 1, window_size, rest_local, rest_centroid, rotations[w], exact,
                                  iterations)
    rotations[w] = q
    R, t = window_frame(q, centroid, rest_centroid)
    frames[w] = R
    translations[w] = t


@wp.func
def window_direction(x: Any, first: int, stride: int, size: int):
    """Unit first-to-last direction of a window, the axis of the simplified variant's goals.

    Inputs:
      x (vec3, per particle or lane slot, m): current positions, an array or a block's shared tile
      first (int, index): element of the window's first particle
      stride (int): elements from one particle to the next (window_centroid)
      size (int): particles per window
    Returns:
      vec3: the unit direction (zero when degenerate)
      bool: false when the first and last particles coincide, so there is no direction
    """
    e = x[first + (size - 1) * stride] - x[first]
    length = wp.length(e)
    if length < 1.0e-12:
        return wp.vec3(0.0), False
    return e / length, True


@wp.func
def simplified_goal(x: wp.array(dtype=wp.vec3), first: int, size: int, k: int, offsets: wp.array(dtype=float),
                    w: int):
    """Goal position of slot k of window w (its particles first .. first + size - 1), simplified variant.

    simplified (Hayashimoto et al. §3.6, window of 3): g_k = c + d_k u along the current first-to-last
    direction u, with d_k the rest offset along the rest first-to-last direction. No rotation, so
    curls straighten. The full variant (Mueller et al. 2005) has g_k = c + R r_k with r_k the rest
    offset from the rest centroid, and R and c the window's optimal rotation and centroid
    (shape_match_rotations, window_frame); a window of 3 holds bend angles only, wider windows also
    hold torsion, so helices keep their shape.

    Inputs:
      x (vec3, per particle, m): current positions
      first (int, index): first particle of the window
      size (int): particles per window
      k (int, index): slot within the window, 0 .. size - 1
      offsets (float, size per window, m): rest offsets along the rest first-to-last direction
      w (int, index): the window
    Returns:
      vec3 (m): the goal; the particle's own position for a degenerate window
    """
    u, straight = window_direction(x, first, 1, size)
    if not straight:
        return x[first + k]
    return window_centroid(x, first, 1, size) + offsets[w * size + k] * u


@wp.kernel(module=APART)
def shape_match_step(
    x: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    particle_strand: wp.array(dtype=wp.int32),
    window_at: wp.array(dtype=wp.int32),
    window_size: int,
    window_offsets: wp.array(dtype=float),
    rest_local: wp.array(dtype=wp.vec3),
    frames: wp.array(dtype=wp.mat33),
    translations: wp.array(dtype=wp.vec3),
    variant: int,
    stiffness: float,
    strand_start: wp.array(dtype=wp.int32),
    x_out: wp.array(dtype=wp.vec3),
    first: int,
):
    """One shape-matching pass: each free particle moves by its windows' pulls toward their goals,
    summed and divided by the window size (full_shaped_position), so no momentum is moved.

    Jacobi: every goal is computed from x and results go to x_out. window_at[j] is the window starting
    at particle j (-1 if none); windows never cross strands, so a window starting at i - k inside this
    strand holds particle i at slot k. Each particle computes the goals of its windows itself instead
    of reading them from a buffer of goals: the neighbours' positions it reads are in cache, a goal
    buffer would be a round trip to memory.

    Launch: one thread per particle of a range of whole strands (dim = particles in the range).
    Inputs:
      x (vec3, per particle, m): positions before this pass
      inv_mass (float, per particle): 0 marks pinned particles, which are copied through
      particle_strand (int32, per particle): strand of each particle
      window_at (int32, per particle): window starting at each particle, -1 when none
      window_size (int): particles per window
      window_offsets (float, window_size per window, m): rest offsets along the rest first-to-last
          direction (simplified)
      rest_local (vec3, per particle, m): rest positions from each strand's root (full;
          sim.strands.ShapeWindows.rest_local)
      frames (mat33, per window): from shape_match_rotations (full variant only)
      translations (vec3, per window, m): from shape_match_rotations (full variant only)
      variant (int): SHAPE_SIMPLIFIED or SHAPE_FULL
      stiffness (float, fraction): share of the way to the goal moved per pass, in (0, 1]
      strand_start (int32, num_strands + 1): first particle of each strand, then the total count
      first (int, index): the range's first particle; thread t works on particle first + t (0 for all of them)
    Outputs:
      x_out (vec3, per particle, m): positions after this pass; must not alias x
    """
    i = wp.tid() + first
    p = x[i]
    strand = particle_strand[i]
    if inv_mass[i] == 0.0:
        x_out[i] = p
        return
    if variant == SHAPE_SIMPLIFIED:
        goal = wp.vec3(0.0)
        count = float(0.0)
        for k in range(window_size):
            j = i - k
            if j >= 0:
                if particle_strand[j] == strand:
                    w = window_at[j]
                    if w >= 0:
                        goal += simplified_goal(x, j, window_size, k, window_offsets, w)
                        count += 1.0
        p = p + stiffness * (goal - count * p) / float(window_size)
    else:
        # a strand's windows are numbered in order from its root
        start = strand_start[strand]
        p = full_shaped_position(p, i - start, strand_start[strand + 1] - start, window_size, stiffness, frames,
                                 translations, window_at[start] + i - start, 1, rest_local[i])
    x_out[i] = p


@wp.struct
class ContactMotion:
    """How the collider moved near a range of strands in the last substep, as contact_motion measured
    it: what the contact bounds of follow_the_leader are lowered by.

    Fields:
      moved (int32, 1 element, MOTION_UNIT): largest displacement of a collider vertex or leaf sphere
          within reach, measured in the frame that rigid carries along, rounded up (motion_units)
      rigid (mat44, 1 element): the rigid motion of the anchor triangle over the substep (identity
          without an anchor); distances seen in the frame it carries change only by relative motion
      center (vec3, 1 element, m): the anchor triangle's centroid after the substep; every particle
          within reach of it is covered by moved
      cells (int32, per cell of a MOTION_GRID^3 grid, MOTION_UNIT): the same largest displacement for each
          cell of a grid around center spanning reach + search each way (motion_cell): only the
          collider within search of a cell counts for it, so hair on the crown is not charged for
          the shoulders
    """

    moved: wp.array(dtype=wp.int32)
    rigid: wp.array(dtype=wp.mat44)
    center: wp.array(dtype=wp.vec3)
    cells: wp.array(dtype=wp.int32)


@wp.struct
class StrandContact:
    """The collider as the hair's length pass meets it (follow_the_leader, step_strands), and the contact
    bounds each particle keeps of it between substeps.

    Fields:
      mode (int): COLLIDE_NONE, COLLIDE_SPHERE_TREE or COLLIDE_MESH
      shape (ColliderShape): the collider; an empty struct when mode is COLLIDE_NONE
      margin (float, m): distance kept outside the collider
      search (float, m): query radius
      probe (float, m): query radius, at most search, for particles whose bound shows them no deeper
          than probe inside; read only when use_bounds != 0
      use_bounds (int, flag): non-zero skips the queries the contact bounds rule out
      mesh_lists (int, flag): mesh queries through lists of the nearest faces kept with the contact
          bounds (collide_point_listed_mesh); zero queries the BVH (mesh_push_out: a GPU's default, the
          gathering of a list inside the serial loop keeps a warp waiting longer than the walk it saves)
      motion (ContactMotion): how the collider moved near the strands (contact_motion, with the same
          strand_reach and search); read only when use_bounds != 0
      strand_reach (float, m): the strands' reach from the anchor given to contact_motion
      clearance (float, per particle or lane slot, m): lower bounds of each particle's distance from the
          collider where it started the substep (NO_BOUND: unknown); written only when mode != COLLIDE_NONE
      near_leaves (vec4i, per particle or lane slot): the leaf spheres (or, with mesh_lists, mesh faces)
          listed for each particle, ascending, -1 for none; read and written only with use_bounds != 0
      beyond (float, per particle or lane slot, m): lower bound of the distance to every unlisted leaf
          or face; ignored where clearance is NO_BOUND; lists kept only
    """

    mode: int
    shape: ColliderShape
    margin: float
    search: float
    probe: float
    use_bounds: int
    mesh_lists: int
    motion: ContactMotion
    strand_reach: float
    clearance: wp.array(dtype=float)
    near_leaves: wp.array(dtype=wp.vec4i)
    beyond: wp.array(dtype=float)


@wp.func
def motion_units(distance: float):
    """A displacement as ContactMotion counts it: in MOTION_UNIT, rounded up (two counts over the
    float product's rounding), so a motion read back is never less than the one measured.

    Inputs:
      distance (float, m): a displacement, at least 0
    Returns:
      int: counts of MOTION_UNIT, at most MOTION_LIMIT's
    """
    return int(wp.min(distance, MOTION_LIMIT) * (1.0 / MOTION_UNIT)) + 2


@wp.func
def motion_cell(p: wp.vec3, center: wp.vec3, half: float):
    """The cell of ContactMotion.cells holding p, clamped to the grid.

    Inputs:
      p (vec3, m): a point
      center (vec3, m): the grid's centre (ContactMotion.center)
      half (float, m): the grid's half width, reach + search
    Returns:
      vec3i: the cell's coordinates, each in [0, MOTION_GRID)
    """
    u = (p - center + wp.vec3(half)) * (float(MOTION_GRID) / (2.0 * half))
    top = MOTION_GRID - 1
    return wp.vec3i(wp.clamp(int(wp.floor(u[0])), 0, top), wp.clamp(int(wp.floor(u[1])), 0, top),
                    wp.clamp(int(wp.floor(u[2])), 0, top))


@wp.func
def motion_near(motion: ContactMotion, p: wp.vec3, half: float):
    """How far the collider moved near p (a point within reach of the centre) in the last substep.

    Inputs:
      motion (ContactMotion): as contact_motion left it
      p (vec3, m): the point
      half (float, m): the grid's half width, reach + search
    Returns:
      float (m): the largest displacement counted for p's cell
    """
    c = motion_cell(p, motion.center[0], half)
    return float(motion.cells[(c[0] * MOTION_GRID + c[1]) * MOTION_GRID + c[2]]) * MOTION_UNIT


@wp.func
def bound_lowering(motion: ContactMotion, start: wp.vec3, p: wp.vec3, half: float):
    """How far a contact bound held at a particle's start position (before the substep, in the
    collider's last pose) falls by the time the particle is at p in the new pose.

    Inputs:
      motion (ContactMotion): as contact_motion left it
      start (vec3, m): the particle's position at the start of the substep
      p (vec3, m): the particle's position now, within reach of motion.center
      half (float, m): the motion grid's half width, reach + search
    Returns:
      vec3 (m): start carried by the anchor's rigid motion (where the bound now holds but for the
          collider's own motion)
      float (m): |p - carried| plus the collider's largest motion near p
    """
    carried = wp.transform_point(motion.rigid[0], start)
    return carried, wp.length(p - carried) + motion_near(motion, p, half)


@wp.kernel
def anchor_frame(
    points_before: wp.array(dtype=wp.vec3),
    points: wp.array(dtype=wp.vec3),
    indices: wp.array(dtype=wp.int32),
    anchor_face: int,
    motion: ContactMotion,
):
    """The first launch of contact_motion's pair: the rigid motion that carries the anchor
    triangle's frame (skinning.triangle_frame) from the previous pose to the new one, and the
    triangle's new centroid.

    Launch: one thread per cell of the motion grid (dim = MOTION_GRID^3): the first also writes the
    frame, each zeroes its cell (one thread zeroing them all made a serial launch of every substep).
    Inputs:
      points_before (vec3, per vertex, m): collider vertices in the previous pose
      points (vec3, per vertex, m): and in the new one
      indices (int32, 3 per triangle): collider triangles
      anchor_face (int): a triangle the strands' roots move with; below 0 for none (the identity,
          centred at the origin)
    Outputs:
      motion (ContactMotion): rigid (x -> R x + t: R the frame's turn, t taking the old centroid to
          the new one) and center written, moved and cells zeroed
    """
    anchor_motion(points_before, points, indices, anchor_face, motion, wp.tid())


@wp.func
def anchor_motion(
    points_before: wp.array(dtype=wp.vec3),
    points: wp.array(dtype=wp.vec3),
    indices: wp.array(dtype=wp.int32),
    anchor_face: int,
    motion: ContactMotion,
    cell: int,
):
    """anchor_frame's work for one cell of the motion grid (the first cell also the rigid motion).

    Inputs:
      points_before (vec3, per vertex, m): collider vertices in the previous pose
      points (vec3, per vertex, m): and in the new one
      indices (int32, 3 per triangle): collider triangles
      anchor_face (int): the anchor triangle, below 0 for none
      cell (int, index): the cell
    Outputs:
      motion (ContactMotion): the cell zeroed; from cell 0 also rigid, center and moved
    Returns:
      nothing: motion's arrays are written
    """
    motion.cells[cell] = 0
    if cell > 0:
        return
    rotation = wp.identity(3, dtype=float)
    before = wp.vec3(0.0)
    after = wp.vec3(0.0)
    if anchor_face >= 0:
        a0 = points_before[indices[3 * anchor_face]]
        b0 = points_before[indices[3 * anchor_face + 1]]
        c0 = points_before[indices[3 * anchor_face + 2]]
        a1 = points[indices[3 * anchor_face]]
        b1 = points[indices[3 * anchor_face + 1]]
        c1 = points[indices[3 * anchor_face + 2]]
        rotation = triangle_frame(a1, b1, c1) * wp.transpose(triangle_frame(a0, b0, c0))
        before = (a0 + b0 + c0) / 3.0
        after = (a1 + b1 + c1) / 3.0
    t = after - rotation * before
    motion.rigid[0] = wp.mat44(rotation[0, 0], rotation[0, 1], rotation[0, 2], t[0],
                               rotation[1, 0], rotation[1, 1], rotation[1, 2], t[1],
                               rotation[2, 0], rotation[2, 1], rotation[2, 2], t[2],
                               0.0, 0.0, 0.0, 1.0)
    motion.center[0] = after
    motion.moved[0] = 0


@wp.kernel
def contact_motion(
    points_before: wp.array(dtype=wp.vec3),
    points: wp.array(dtype=wp.vec3),
    centers_before: wp.array(dtype=wp.vec3),
    centers: wp.array(dtype=wp.vec3),
    radii: wp.array(dtype=float),
    is_leaf: wp.array(dtype=wp.int32),
    neighbor_start: wp.array(dtype=wp.int32),
    neighbors: wp.array(dtype=wp.int32),
    local: int,
    vertices: int,
    reach: float,
    search: float,
    motion: ContactMotion,
):
    """How far the collider moved near a range of strands, relative to an anchor triangle.

    Distances do not change under a rigid motion, so a particle's distance from the collider changes
    by at most its own displacement and the collider's, both measured after undoing the anchor's
    rigid motion (anchor_frame, launched first): on a walking body the head and the hair near it
    barely move in that frame. Only the collider near the strands counts: a triangle with a point
    within reach + search of the anchor's new centre has every corner within reach + search of it
    plus that corner's longest edge in the new pose, and one entirely farther is more than search
    from any particle within reach, beyond any bound follow_the_leader keeps. So the arms and legs
    of a walking body, which move fast, do not shrink the bounds of the hair. Strands that collide
    with the sphere tree only need its leaves counted (vertices = 0), not the mesh.

    The same displacements are also kept per cell of a grid around the anchor (motion.cells): a
    vertex or leaf raises only the cells within search of its triangles or sphere, since a particle
    in any other cell is farther than search from them and no bound follow_the_leader keeps exceeds
    search. A particle on the crown is then not charged for the shoulders moving under the ends.

    Launch: one thread per vertex and sphere-tree node (dim = len(points) + len(centers)), or per
    node only when vertices == 0 (dim = len(centers)).
    Inputs:
      points_before (vec3, per vertex, m): mesh vertices in the previous pose
      points (vec3, per vertex, m): and in the new one
      centers_before (vec3, per tree node, m): sphere centres in the previous pose
      centers (vec3, per tree node, m): and in the new one
      radii (float, per tree node, m): sphere radii; leaf radii do not change with the pose
      is_leaf (int32, per tree node): 1 for leaf spheres; inner nodes are not counted
      neighbor_start (int32, vertices + 1): CSR offsets of each vertex's edge neighbours
      neighbors (int32, per vertex-neighbour pair): the neighbours (sim.Collider.adjacency)
      local (int, flag): 0 counts every vertex and leaf (no anchor triangle)
      vertices (int, flag): 0 counts the sphere tree's leaves only, not the mesh vertices
      reach (float, m): every particle of the strands lies within this of the anchor's centroid
      search (float, m): the largest contact bound follow_the_leader keeps (its query radius)
    In/out:
      motion (ContactMotion): rigid and center read; moved raised to the largest displacement, and
          each cell to the largest near it
    """
    raise_motion(wp.tid(), points_before, points, centers_before, centers, radii, is_leaf, neighbor_start, neighbors,
                 local, vertices, reach, search, motion)


@wp.func
def raise_motion(
    thread: int,
    points_before: wp.array(dtype=wp.vec3),
    points: wp.array(dtype=wp.vec3),
    centers_before: wp.array(dtype=wp.vec3),
    centers: wp.array(dtype=wp.vec3),
    radii: wp.array(dtype=float),
    is_leaf: wp.array(dtype=wp.int32),
    neighbor_start: wp.array(dtype=wp.int32),
    neighbors: wp.array(dtype=wp.int32),
    local: int,
    vertices: int,
    reach: float,
    search: float,
    motion: ContactMotion,
):
    """contact_motion's work for one thread: one vertex or leaf sphere's move raises the motion.

    Inputs:
      thread (int, index): the thread of contact_motion's launch
      points_before (vec3, per vertex, m): mesh vertices in the previous pose
      points (vec3, per vertex, m): and in the new one
      centers_before (vec3, per tree node, m): sphere centres in the previous pose
      centers (vec3, per tree node, m): and in the new one
      radii (float, per tree node, m): sphere radii
      is_leaf (int32, per tree node): 1 for leaf spheres
      neighbor_start (int32, vertices + 1): CSR offsets of each vertex's edge neighbours
      neighbors (int32, per vertex-neighbour pair): the neighbours
      local (int, flag): 0 counts every vertex and leaf
      vertices (int, flag): 0 counts the sphere tree's leaves only
      reach (float, m): the strands' reach from the anchor's centroid
      search (float, m): the largest contact bound follow_the_leader keeps
    In/out:
      motion (ContactMotion): rigid and center read; moved and the cells raised
    Returns:
      nothing: motion's arrays are raised
    """
    i = thread
    rigid = motion.rigid[0]
    n = points.shape[0]
    if vertices == 0:
        i += n
    q = wp.vec3(0.0)
    q_before = wp.vec3(0.0)
    if i < n:
        q = points[i]
        q_before = points_before[i]
    else:
        if is_leaf[i - n] == 0:
            return
        q = centers[i - n]
        q_before = centers_before[i - n]
    moved = wp.length(q - wp.transform_point(rigid, q_before))
    if moved <= 0.0:
        return  # moved with the anchor: raises neither the maximum nor a cell
    center = motion.center[0]
    gap = wp.length(q - center) - reach - search
    # every point of a vertex's triangles lies within its longest edge of it, every point of a leaf
    # within its radius
    extent = float(0.0)
    if i < n:
        for k in range(neighbor_start[i], neighbor_start[i + 1]):
            extent = wp.max(extent, wp.length(points[neighbors[k]] - q))
    else:
        extent = radii[i - n]
    if local != 0 and gap - extent > 0.0:
        return
    # integer maxima (MOTION_UNIT): native atomics, where a float's would retry under contention
    units = motion_units(moved)
    if units > motion.moved[0]:
        wp.atomic_max(motion.moved, 0, units)
    # the cells within search of the vertex's triangles or the leaf: a particle in any other cell is
    # more than search from them, beyond every bound follow_the_leader keeps
    half = reach + search
    pad = wp.vec3(search + extent)
    lo = q - pad
    hi = q + pad
    for a in range(3):
        if hi[a] < center[a] - half or lo[a] > center[a] + half:
            return
    c0 = motion_cell(lo, center, half)
    c1 = motion_cell(hi, center, half)
    for a in range(c0[0], c1[0] + 1):
        for b in range(c0[1], c1[1] + 1):
            for c in range(c0[2], c1[2] + 1):
                cell = (a * MOTION_GRID + b) * MOTION_GRID + c
                if units > motion.cells[cell]:
                    wp.atomic_max(motion.cells, cell, units)


@wp.kernel(module=APART)
def to_lanes(
    x: wp.array(dtype=wp.vec3),
    x_prev: wp.array(dtype=wp.vec3),
    strand_start: wp.array(dtype=wp.int32),
    order: LaneOrder,
    lane_x: wp.array(dtype=wp.vec3),
    lane_prev: wp.array(dtype=wp.vec3),
):
    """Copy what the length pass reads into lane order (lane_slot): the predicted positions and the
    positions at the start of the substep.

    Launch: one thread per lane slot (dim = order.lanes * the longest strand's particle count): the
    reads are gathered, the writes consecutive.
    Inputs:
      x (vec3, per particle, m): predicted positions
      x_prev (vec3, per particle, m): positions at the start of the substep
      strand_start (int32, num_strands + 1): first particle of each strand, then the total count
      order (LaneOrder): the lane order
    Outputs:
      lane_x (vec3, per lane slot, m): x in lane order; the slots past a strand's tip are left as
          they were
      lane_prev (vec3, per lane slot, m): x_prev in lane order, likewise
    """
    t = wp.tid()
    k = t / order.lanes
    s = order.strand_of[t - k * order.lanes]
    start = strand_start[s]
    if k < strand_start[s + 1] - start:
        lane_x[t] = x[start + k]
        lane_prev[t] = x_prev[start + k]


@wp.kernel(module=APART)
def from_lanes(
    lane_x: wp.array(dtype=wp.vec3),
    lane_v: wp.array(dtype=wp.vec3),
    strand_start: wp.array(dtype=wp.int32),
    order: LaneOrder,
    longest: int,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
):
    """Copy the length pass's positions and velocities back from lane order to particle order.

    Launch: one thread per lane slot, lane by lane (dim = order.lanes * longest): thread t copies
    particle t % longest of the strand in lane t / longest. A warp then writes one strand's
    consecutive particles and gathers them from its lane's slots, and the next warps gather from the
    neighbouring lanes, in the same memory sectors. (A thread per particle in particle order would
    gather, with lanes that follow the roots, from lanes scattered over the whole scalp: twice the
    time on an H100.)
    Inputs:
      lane_x (vec3, per lane slot, m): positions in lane order
      lane_v (vec3, per lane slot, m/s): velocities in lane order
      strand_start (int32, num_strands + 1): first particle of each strand, then the total count
      order (LaneOrder): the lane order
      longest (int): particles of the longest strand
    Outputs:
      x (vec3, per particle, m): the positions in particle order
      v (vec3, per particle, m/s): the velocities in particle order
    """
    t = wp.tid()
    lane = t / longest
    k = t - lane * longest
    s = order.strand_of[lane]
    start = strand_start[s]
    if k < strand_start[s + 1] - start:
        slot = lane_slot(start, lane, k, order.lanes)
        x[start + k] = lane_x[slot]
        v[start + k] = lane_v[slot]


@wp.func
def list_runs_short(p: wp.vec3, start: wp.vec3, i: int, contact: StrandContact, slack: float):
    """Whether the length pass would find a particle's sphere-tree leaf list run short at p: both its
    contact bound and its unlisted-leaf bound, lowered as follow_leader lowers them, within slack of
    the margin (or its bounds unknown). A particle beyond the strands' reach is queried outright, and
    its list never runs short.

    Inputs:
      p (vec3, m): where the particle is expected (predicted, or its start with slack to cover the
          substep's travel)
      start (vec3, m): its position at the start of the substep, where the bounds hold
      i (int, index): its element of the contact bounds
      contact (StrandContact): the collider's settings, its motion and the contact bounds
      slack (float, m): how far short of margin a bound may be and still run short
    Returns:
      bool: true where a walk down the tree should list the particle afresh (list_leaves)
    """
    if wp.length(p - contact.motion.center[0]) > contact.strand_reach:
        return False  # follow_leader queries such a particle outright
    _carried, lowered = bound_lowering(contact.motion, start, p, contact.strand_reach + contact.search)
    bound = float(NO_BOUND)
    unlisted = float(NO_BOUND)
    held = contact.clearance[i]
    if held > 0.5 * NO_BOUND:
        bound = held - lowered
        unlisted = contact.beyond[i] - lowered
    return bound <= contact.margin + slack and unlisted <= contact.margin + slack


@wp.func
def list_leaves(i: int, start: wp.vec3, contact: StrandContact):
    """List a particle's nearest sphere-tree leaves afresh, with its contact bounds, where its start
    position lies in the collider's new pose (carried by the anchor's rigid motion).

    Inputs:
      i (int, index): the particle's element of the contact bounds
      start (vec3, m): its position at the start of the substep
    In/out:
      contact (StrandContact): its motion and shape read; the particle's near_leaves, clearance and
          beyond written (sphere_tree_nearest)
    Returns:
      nothing: the bounds are written into contact's arrays
    """
    carried = wp.transform_point(contact.motion.rigid[0], start)
    leaves, nearest, fifth = sphere_tree_nearest(carried, contact.shape, contact.search)
    contact.near_leaves[i] = leaves
    contact.clearance[i] = nearest
    contact.beyond[i] = fifth


@wp.kernel(module=APART)
def find_short_lists(
    x: wp.array(dtype=wp.vec3),
    x_prev: wp.array(dtype=wp.vec3),
    particle_strand: wp.array(dtype=wp.int32),
    strand_start: wp.array(dtype=wp.int32),
    pinned_per_strand: int,
    contact: StrandContact,
    slack: float,
    order: LaneOrder,
    by_particle: int,
    first: int,
    short_count: wp.array(dtype=wp.int32),
    queue: wp.array(dtype=wp.int32),
):
    """Queue, before follow_the_leader, the particles whose sphere-tree leaf lists that pass would
    find run short, for list_leaves_ahead to list afresh: the tree walks leave its serial loop.

    follow_the_leader walks the tree for a particle whose contact bound and unlisted-leaf bound have
    both fallen to margin. Here both are lowered as it would lower them, at the predicted position
    instead of the one it settles on; a particle where both come within slack of margin (or whose
    bounds are unknown) is queued. A walk costs a hundred node visits, and a warp runs as long as its
    longest walk: queued, the walks fill whole warps instead of a few lanes of most warps.

    Launch: one thread per particle of a range of particles (dim = particles in the range), or in
    lane order one thread per lane slot (dim = order.lanes * the longest strand), after contact_motion;
    sphere-tree collision with contact bounds only. The per-particle arrays are in the order
    follow_the_leader reads them (lane_slot).
    Inputs:
      x (vec3, per particle, m): predicted positions (those follow_the_leader starts from); before
          step_strands, which predicts them itself, the start positions, with slack covering how far
          a particle travels in the substep
      x_prev (vec3, per particle, m): positions at the start of the substep, where the bounds hold
      particle_strand (int32, per particle): the strand of each particle (particle order only)
      strand_start (int32, num_strands + 1): first particle of each strand, then the total count
      pinned_per_strand (int): leading particles of each strand that follow_the_leader leaves alone
      contact (StrandContact): the collider's settings, its motion and the contact bounds (anchored at
          x_prev) that follow_the_leader will read
      slack (float, m): how far short of margin a bound may be from running out and still be listed
      order (LaneOrder): particle order, or the lane order (then first is 0)
      by_particle (int, flag): non-zero: x and x_prev are in particle order even in lane order (the
          state step_strands starts from)
      first (int, index): the range's first particle; thread t works on particle first + t
    In/out:
      short_count (int32, 1 element): particles queued, zero before the launch
    Outputs:
      queue (int32, per particle of the range): the queued particles' indices, from element first,
          in no particular order
    """
    i = wp.tid() + first
    k = int(0)
    j = i  # the particle's element of x and x_prev
    if order.lanes > 0:
        k = i / order.lanes
        s = order.strand_of[i - k * order.lanes]
        if k >= strand_start[s + 1] - strand_start[s]:
            return  # a slot past the strand's tip
        if by_particle != 0:
            j = strand_start[s] + k
    else:
        k = i - strand_start[particle_strand[i]]
    if k < pinned_per_strand:
        return
    if list_runs_short(x[j], x_prev[j], i, contact, slack):
        queue[first + wp.atomic_add(short_count, 0, 1)] = i


@wp.kernel(module=APART)
def list_leaves_ahead(
    x_prev: wp.array(dtype=wp.vec3),
    contact: StrandContact,
    short_count: wp.array(dtype=wp.int32),
    queue: wp.array(dtype=wp.int32),
    first: int,
    strand_start: wp.array(dtype=wp.int32),
    order: LaneOrder,
    by_particle: int,
):
    """List afresh the four sphere-tree leaves nearest each particle find_short_lists queued.

    The list is made at the particle's start position carried into the new pose (where the bounds
    are anchored), and the bounds are set to that point's distances, which hold there in the new
    pose, so the lowering follow_the_leader applies next keeps them lower bounds. The strands are
    those that querying every particle gives.

    Launch: one thread per particle of a range of particles, as find_short_lists (dim = the same),
    right after it; threads past the queue's length return at once.
    Inputs:
      x_prev (vec3, per particle, m): positions at the start of the substep, where the bounds hold
      short_count (int32, 1 element): particles queued
      queue (int32, per particle of the range): the queued particles, from element first
      first (int, index): the range's first particle
      strand_start (int32, num_strands + 1): first particle of each strand, then the total count;
          read only with by_particle in lane order
      order (LaneOrder): the order of the queue and the bounds (find_short_lists')
      by_particle (int, flag): non-zero: x_prev is in particle order even in lane order
    In/out:
      contact (StrandContact): the collider posed for the end of the substep (the tree's distances
          capped at its search) and its motion in; the queued particles' bounds out: their nearest leaf
          distance (clearance), four nearest leaves (near_leaves) and fifth nearest leaf distance (beyond)
    """
    t = wp.tid()
    if t >= short_count[0]:
        return
    i = queue[first + t]
    j = i  # the particle's element of x_prev
    if by_particle != 0 and order.lanes > 0:
        k = i / order.lanes
        j = strand_start[order.strand_of[i - k * order.lanes]] + k
    list_leaves(i, x_prev[j], contact)


# The collision paths a length pass is compiled with: lists of the nearest sphere-tree leaves and mesh
# faces kept with the contact bounds, or bounded queries only. A kernel carries the code of every path
# it may take, and its serial loop pays for the registers that code spills at every particle step:
# on sm_90 follow_the_leader spills 632 bytes with every path, 88 with the sphere tree's alone, none
# with the bounded queries alone (benchmarks/cuda_resources.py). The solver launches the variant its
# collision needs (FOLLOW_THE_LEADER); step_strands, the CPU's, keeps every path.
PATHS_QUERIES = 0  # bounded queries only (collide_point_bounded): the sphere tree walked, the mesh's BVH
PATHS_SPHERE_LISTS = 1  # the sphere tree alone, its leaf lists and walks: for COLLIDE_SPHERE_TREE only
PATHS_ALL = 2  # every path: both lists (collide_point_listed, collide_point_listed_mesh) and the queries
PATHS_NONE = -1  # no collider: the placement alone, contact.mode read as 0 (frame_in_block's own)
PATH_NAMES = {PATHS_NONE: "_none", PATHS_QUERIES: "_queries", PATHS_SPHERE_LISTS: "_sphere_lists", PATHS_ALL: ""}


@wp.func
def held_bounds(i: int, lists: int, contact: StrandContact):
    """The contact bounds a particle holds as the length pass reaches it, for follow_leader.

    Inputs:
      i (int, index): the particle's element of the contact-bound arrays
      lists (int, flag): non-zero also reads the particle's list and its bound
      contact (StrandContact): its bounds; nothing is read unless contact.use_bounds
    Returns:
      float (m): contact.clearance[i], NO_BOUND unread
      vec4i: contact.near_leaves[i], (-1, -1, -1, -1) unread
      float (m): contact.beyond[i], NO_BOUND unread
    """
    held = float(NO_BOUND)
    held_leaves = wp.vec4i(-1, -1, -1, -1)
    held_beyond = float(NO_BOUND)
    if contact.use_bounds != 0:
        held = contact.clearance[i]
        if lists != 0:
            held_leaves = contact.near_leaves[i]
            held_beyond = contact.beyond[i]
    return held, held_leaves, held_beyond


@wp.func(inline=True)
def leader_placement(parent: wp.vec3, before: wp.vec3, k: int, predicted: wp.vec3, length: float):
    """Where follow-the-leader puts a particle before its contacts (follow_leader): at its rest distance
    from its parent, toward its prediction (where the prediction is on the parent, along the segment
    before, or down for a strand's first free particle). Its move from the prediction is the correction
    whose share ftl_damping the parent's velocity gives up (dynamic FTL). A contact's push is not part of
    it: the push is the collider's on the particle, not the segment's pull on the parent, and fed back it
    set hair ends resting on a shoulder buzzing. The length pass writes the parent's velocity between the
    placement and the contacts, so that no correction is kept through them.

    Inputs:
      parent (vec3, m): the parent's resolved position
      before (vec3, m): the grandparent's resolved position; read only when k >= 2 and the prediction is
          on the parent
      k (int, index): the particle's place along its strand
      predicted (vec3, m): where the particle was predicted and shape-matched to
      length (float, m): its rest distance to the parent
    Returns:
      vec3 (m): the placement
    """
    d = predicted - parent
    dist = wp.length(d)
    if dist < 1.0e-12:
        d = wp.vec3(0.0, -1.0, 0.0)
        if k >= 2:
            d = parent - before
        dist = wp.length(d)
    return parent + d * (length / dist)


def _follow_leader(paths, ahead=False, loose=False):
    """follow_leader compiled with the collision paths `paths` (PATHS_*); with `ahead` it takes the
    bounds held at the start as values (held, held_leaves, held_beyond) instead of reading them.
    loose (PATHS_SPHERE_LISTS only): a leaf list that runs short is refilled by a walk down the tree
    only where the particle may be inside a leaf it does not hold (collision.collide_point_listed_loose)."""

    @wp.func(inline=True, name="follow_leader" + PATH_NAMES[paths] + ("_ahead" if ahead else "") +
             ("_loose" if loose else ""))
    def follow_leader(
        parent: wp.vec3,
        placed: wp.vec3,
        length: float,
        i: int,
        start: wp.vec3,
        contact: StrandContact,
        held: float,
        held_leaves: wp.vec4i,
        held_beyond: float,
    ):
        """One particle of the length pass (follow_the_leader, step_strands) after its placement at rest
        distance from its parent (leader_placement): pushed out of the collider and put back on that
        sphere, its contact bounds kept or renewed.

        Compiled ahead (follow_the_leader's variant that reads a particle ahead), the bounds held at
        the start come as values (held, held_leaves, held_beyond), read by the caller (held_bounds)
        while the particle before is placed; otherwise it reads them from contact's clearance, near_leaves
        and beyond where it needs them, and those three arguments are unread.

        Inputs:
          parent (vec3, m): the parent's resolved position
          placed (vec3, m): the particle's placement (leader_placement)
          length (float, m): its rest distance to the parent
          i (int, index): its element of the contact-bound arrays (lane_slot)
          start (vec3, m): its position at the start of the substep, where the bounds hold
          contact (StrandContact): the collider, the query settings and the contact bounds
          held (float, m): contact.clearance[i] at the start, compiled ahead; read only with use_bounds
          held_leaves (vec4i): near_leaves[i] at the start, compiled ahead; read only with a list
          held_beyond (float, m): beyond[i] at the start, compiled ahead; likewise
        In/out:
          contact.clearance, contact.near_leaves, contact.beyond: the particle's bounds, read at the
              start (unless compiled ahead) and kept or renewed at the result
        Returns:
          vec3 (m): the resolved position
        """
        p = placed
        colliding = contact.mode
        if wp.static(paths == PATHS_NONE):
            colliding = 0  # a constant: no collision code is compiled in
        if colliding != 0:
            bound = float(NO_BOUND)
            # the lists near each particle are kept with the bounds; mesh queries go through a list
            # even without them (one made for the query), so that skipping queries changes nothing
            # a path left out of this variant is a constant False: the compiler drops its code
            listed_mesh = bool(False)
            if wp.static(paths >= PATHS_ALL):
                listed_mesh = contact.mode == COLLIDE_MESH and contact.mesh_lists != 0
            listed = bool(False)
            if wp.static(paths >= PATHS_SPHERE_LISTS):
                listed = contact.use_bounds != 0 and (contact.mode == COLLIDE_SPHERE_TREE or listed_mesh)
            leaves = wp.vec4i(-1, -1, -1, -1)
            unlisted = float(NO_BOUND)
            if contact.use_bounds != 0:
                from_center = p - contact.motion.center[0]
                if wp.dot(from_center, from_center) <= contact.strand_reach * contact.strand_reach:
                    _carried, lowered = bound_lowering(contact.motion, start, p, contact.strand_reach + contact.search)
                    at_start = held
                    if wp.static(not ahead):
                        at_start = contact.clearance[i]
                    bound = at_start - lowered
                    if listed and at_start > 0.5 * NO_BOUND:
                        if wp.static(ahead):
                            leaves = held_leaves
                            unlisted = held_beyond - lowered
                        else:
                            leaves = contact.near_leaves[i]
                            unlisted = contact.beyond[i] - lowered
            origin = p
            queried_here = contact.use_bounds == 0 or bound <= contact.margin + 1.0e-5
            if queried_here:
                # a particle known to be no deeper than probe inside needs only a probe-sized
                # query: one within probe finds what a search-sized one finds, and one that finds
                # nothing shows it outside (a query's cost grows fast with its radius)
                reach = contact.search
                if contact.use_bounds != 0 and bound > -contact.probe:
                    reach = contact.probe
                # putting the particle back at rest length can re-enter the collider near a
                # crease (between two spheres, in a concave corner); a second round settles it
                queried = p
                for _round in range(2):
                    queried = p
                    pushed = p
                    if listed_mesh:
                        pushed, bound, leaves, origin, unlisted = collide_point_listed_mesh(
                            p, contact.shape.mesh, contact.margin, reach, contact.search, leaves, origin, unlisted)
                    elif listed:
                        if wp.static(loose):
                            pushed, bound, leaves, origin, unlisted = collide_point_listed_loose(
                                p, contact.shape, contact.margin, reach, leaves, origin, unlisted)
                        else:
                            pushed, bound, leaves, origin, unlisted = collide_point_listed(
                                p, contact.shape, contact.margin, reach, leaves, origin, unlisted)
                    else:
                        mode = contact.mode
                        if wp.static(paths == PATHS_SPHERE_LISTS):
                            mode = COLLIDE_SPHERE_TREE  # a constant: the mesh's query is not compiled in
                        pushed, bound = collide_point_bounded(p, mode, contact.shape, contact.margin, reach)
                    reach = contact.search
                    if pushed == p:
                        break
                    p = pushed
                    d = p - parent
                    dist = wp.length(d)
                    if dist > 1.0e-12:
                        p = parent + d * (length / dist)
                bound = bound - wp.length(p - queried)
            contact.clearance[i] = bound
            if listed:
                # a list not queried is the one read above, and its bound holds at p itself
                if queried_here:
                    contact.near_leaves[i] = leaves
                    unlisted = unlisted - wp.length(p - origin)
                contact.beyond[i] = unlisted
        return p
    return follow_leader


follow_leader = _follow_leader(PATHS_ALL)


def _follow_the_leader(paths, ahead=False, loose=False):
    """follow_the_leader compiled with the collision paths `paths` (PATHS_*), reading each particle's
    inputs in its turn or, with `ahead`, while the particle before it is placed; `loose` walks the
    sphere tree only where a particle may be inside an unlisted leaf (_follow_leader)."""
    follow = follow_leader if paths == PATHS_ALL and not ahead else _follow_leader(paths, ahead, loose)

    # 178 registers uncapped (CUDA, H100): one 256-thread block per SM, 8 warps to hide the serial loop's
    # latency; capped at 128, two blocks fit and the pass ran 30% faster (100k strands: 10.3 -> 7.3 ms
    # per frame) despite 352 bytes of spills. The CPU ignores the cap.
    @wp.kernel(module=APART, cuda_max_registers=128,
               name="follow_the_leader" + PATH_NAMES[paths] + ("_ahead" if ahead else "") +
               ("_loose" if loose else ""))
    def follow_the_leader(
        x: wp.array(dtype=wp.vec3),
        x_prev: wp.array(dtype=wp.vec3),
        inv_mass: wp.array(dtype=float),
        strand_start: wp.array(dtype=wp.int32),
        rest_length: wp.array(dtype=float),
        pinned_per_strand: int,
        contact: StrandContact,
        ftl_damping: float,
        dt: float,
        v: wp.array(dtype=wp.vec3),
        order: LaneOrder,
        first: int,
    ):
        """Inextensibility by follow-the-leader (Mueller et al. 2012), root to tip, then the velocities.

        Each particle is put at its rest distance from its parent; a contact push-out is resolved inline
        and the particle is then put back on the sphere of rest radius, so every segment leaves with its
        exact rest length. Velocities are v = (x - x_prev) / dt minus ftl_damping * d_(i+1) / dt for
        free particles, d_(i+1) the child's move to rest length (dynamic FTL; without a contact's push, see
        leader_placement), carried to the next particle in a register rather than stored.

        Contact bounds (contact.use_bounds != 0): each particle keeps a lower bound of its distance from the
        collider, set by its last query and lowered every substep by how far it and the collider near it
        moved, both seen in the frame that follows the anchor triangle (contact_motion, motion_near): the
        particle's move is measured from x_prev carried by motion.rigid. While that bound stays above
        margin no query could push the particle, so none is made: most hair is centimetres from the
        head, and the queries of this serial loop are its cost. A particle farther than the strands' reach
        from motion.center gets a full query. The result is the same as querying every particle,
        except for particles already deeper than search inside the collider, which no query sees
        anyway until they are within margin of its surface. A caller that moves particles or the collider in any other
        way must set their bounds to NO_BOUND first.

        Sphere tree with bounds: each particle also keeps the four leaf spheres nearest it and a lower
        bound of its distance from every other leaf (lowered like the contact bound). While that bound
        stays above margin a query tests only those four leaves (collide_point_listed), which is most of
        the queries of hair lying on the body; the result is again the same as querying the tree. On a
        GPU, find_short_lists and list_leaves_ahead first list afresh, in parallel, the leaves of the
        particles whose lists would run short here.

        The per-particle arrays it reads, keeps and writes are in particle order or all in lane order
        (order, lane_slot: to_lanes copies them there and from_lanes back; a thread per lane). On a GPU
        lane order makes each step of the loop read and write consecutive memory across a warp's
        strands; in particle order (the CPU's, where a thread walks one strand's cache lines) a warp
        touches 32 cache lines per array per step. Writing the results straight back in particle order
        instead (stores scattered a strand apart) was measured slower on an H100 than from_lanes.

        Launch: one thread per strand of a range of strands (dim = strands in the range).
        Inputs:
          x_prev (vec3, per particle, m): positions at the start of the substep (where the bounds hold)
          inv_mass (float, per particle): 0 marks pinned particles, whose velocity is not damped
          strand_start (int32, num_strands + 1): first particle of each strand, then the total count
          rest_length (float, per particle, m): rest distance to the previous particle (unused for roots)
          pinned_per_strand (int): leading particles of each strand left where they are; at least 1,
              since a root has no parent to follow (with 0 it would read the previous strand's tip)
          ftl_damping (float, fraction): share of the child's move to rest length taken off the velocity, [0.7, 1]
          dt (float, s): substep length
          order (LaneOrder): particle order, or the lane order (then first is 0 and thread t works on
              lane t)
          first (int, index): the range's first strand; thread t works on strand first + t (0 for all of them)
        In/out:
          x (vec3, per particle, m): predicted positions in; lengths and collisions resolved out (the
              loop reads each particle's parent back from it)
          contact (StrandContact): the collider and its settings; its contact bounds at x_prev in, at x out
        Outputs:
          v (vec3, per particle, m/s): velocities at the end of the substep
        """
        s = wp.tid() + first
        lane = s
        lanes = order.lanes
        if lanes > 0:
            s = order.strand_of[lane]
        start = strand_start[s]
        count = strand_start[s + 1] - start
        parent = wp.vec3(0.0)  # the last two particles as resolved, carried in registers
        before = wp.vec3(0.0)
        if wp.static(ahead):
            # each particle's inputs are read while the particle before it is placed, so that the loop's
            # chain waits on its arithmetic rather than on memory (a particle's slot is its own: read
            # early, it holds what it would hold in its turn); copies, since the loop reassigns them
            lists = int(0)
            if wp.static(paths >= PATHS_SPHERE_LISTS):
                lists = int(contact.mode != 0)
            i = lane_slot(start, lane, 0, lanes)
            p_next, rest_next = wp.vec3(x[i]), float(rest_length[i])
            start_next, mass_next = wp.vec3(x_prev[i]), float(inv_mass[i])
            held_next, leaves_next, beyond_next = held_bounds(i, lists, contact)
            start_parent = wp.vec3(0.0)  # the parent's start position and inverse mass, for its velocity
            mass_parent = float(0.0)
            for k in range(count):
                i = lane_slot(start, lane, k, lanes)
                p, rest, x_start, mass = p_next, rest_next, start_next, mass_next
                held, held_leaves, held_beyond = held_next, leaves_next, beyond_next
                if k + 1 < count:
                    n = lane_slot(start, lane, k + 1, lanes)
                    p_next, rest_next = wp.vec3(x[n]), float(rest_length[n])
                    start_next, mass_next = wp.vec3(x_prev[n]), float(inv_mass[n])
                    held_next, leaves_next, beyond_next = held_bounds(n, lists, contact)
                correction = wp.vec3(0.0)
                if k >= pinned_per_strand:
                    placed = leader_placement(parent, before, k, p, rest)
                    correction = placed - p
                    p = placed
                if k > 0:
                    vel = (parent - start_parent) / dt
                    if mass_parent > 0.0:
                        vel = vel - (ftl_damping / dt) * correction
                    v[lane_slot(start, lane, k - 1, lanes)] = vel
                if k >= pinned_per_strand:
                    p = follow(parent, p, rest, i, x_start, contact, held, held_leaves, held_beyond)
                    x[i] = p
                before = parent
                parent = p
                start_parent = x_start
                mass_parent = mass
            v[lane_slot(start, lane, count - 1, lanes)] = (parent - start_parent) / dt
        else:
            for k in range(count):
                i = lane_slot(start, lane, k, lanes)
                p = x[i]
                correction = wp.vec3(0.0)
                if k >= pinned_per_strand:
                    placed = leader_placement(parent, before, k, p, rest_length[i])
                    correction = placed - p
                    p = placed
                if k > 0:
                    j = lane_slot(start, lane, k - 1, lanes)
                    vel = (parent - x_prev[j]) / dt
                    if inv_mass[j] > 0.0:
                        vel = vel - (ftl_damping / dt) * correction
                    v[j] = vel
                if k >= pinned_per_strand:
                    p = follow(parent, p, rest_length[i], i, x_prev[i], contact, NO_BOUND, wp.vec4i(-1, -1, -1, -1),
                               NO_BOUND)
                    x[i] = p
                before = parent
                parent = p
            j = lane_slot(start, lane, count - 1, lanes)
            v[j] = (parent - x_prev[j]) / dt

    return follow_the_leader


FOLLOW_THE_LEADER = {paths: _follow_the_leader(paths) for paths in (PATHS_QUERIES, PATHS_SPHERE_LISTS, PATHS_ALL)}
# the GPU's paths reading a particle ahead (HairSolver.read_ahead): the same strands; more live registers
# (sm_90 spills: bounded queries none either way, sphere lists 88 -> 220 bytes), less of the loop waiting on memory
FOLLOW_THE_LEADER_AHEAD = {paths: _follow_the_leader(paths, ahead=True) for paths in (PATHS_QUERIES,
                                                                                       PATHS_SPHERE_LISTS)}
# the sphere tree's pass walking only where a particle may be inside an unlisted leaf (HairSolver.loose_lists,
# a GPU experiment): the margin to such leaves is restored a substep later, through the lists made ahead
FOLLOW_THE_LEADER_LOOSE = {PATHS_SPHERE_LISTS: _follow_the_leader(PATHS_SPHERE_LISTS, loose=True)}
follow_the_leader = FOLLOW_THE_LEADER[PATHS_ALL]

@wp.func
def guide_point(guide_points: wp.array(dtype=wp.vec3), g: int, count: int, s: float):
    """Point at normalised arc parameter s along guide g, linear between its vertices.

    Inputs:
      guide_points (vec3, count per guide, m): guide polylines back to back
      g (int, index): the guide's block in guide_points (frame * num_guides + guide for follow_guides)
      count (int): vertices per guide, evenly spaced along the arc; at least 2
      s (float): arc parameter, 0 at the root and 1 at the tip; clamped to [0, 1]
    Returns:
      vec3 (m): the point
    """
    u = wp.clamp(s, 0.0, 1.0) * float(count - 1)
    k = wp.min(int(u), count - 2)
    t = u - float(k)
    return (1.0 - t) * guide_points[g * count + k] + t * guide_points[g * count + k + 1]


@wp.struct
class GuidePull:
    """Captured guides that pull a hair substep's strands (sim.guides.GuideTargets.pull): each free
    particle moves toward its strand's root plus the weighted guides' offsets from their roots at the
    particle's normalised arc position, the guides linear between captured frames (held past the
    ends), so captured motion drives the shape while each strand stays on its own root.

    Fields:
      strand_guides (vec3i, per strand): up to three guide indices
      weights (vec3, per strand): weight of each guide, summing to 1; 0 skips a slot
      param (float, per particle): normalised arc length from the root (0) to the tip (1)
      points (vec3, frames * guides * vertices, m): captured guides, frame-major
      frames (int): captured frames
      guides (int): guides per frame
      vertices (int): vertices per guide, evenly spaced along its arc; at least 2
      fps (float, 1/s): frames per second of the capture, which starts at time 0
      stiffness (float, fraction per substep): share of the way to the target moved, e.g.
          1 - exp(-rate * dt); 0 for no pull (the arrays are then not read)
    """

    strand_guides: wp.array(dtype=wp.vec3i)
    weights: wp.array(dtype=wp.vec3)
    param: wp.array(dtype=float)
    points: wp.array(dtype=wp.vec3)
    frames: int
    guides: int
    vertices: int
    fps: float
    stiffness: float


@wp.func
def guide_frames(pull: GuidePull, time: float):
    """The two captured frames around `time` and the weight of the second.

    Inputs:
      pull (GuidePull): the guides
      time (float, s): the substep's time
    Returns:
      int (index): the earlier frame
      int (index): the later frame
      float: the later frame's weight, in [0, 1]
    """
    u = wp.clamp(time * pull.fps, 0.0, float(pull.frames - 1))
    f = wp.min(int(u), wp.max(pull.frames - 2, 0))
    t = wp.min(u - float(f), 1.0)
    return f, wp.min(f + 1, pull.frames - 1), t


@wp.func(inline=True)
def guided_position(pull: GuidePull, p: wp.vec3, root: wp.vec3, strand: int, i: int, f: int, f1: int, t: float):
    """A free particle moved `pull.stiffness` of the way toward its guided position.

    Inputs:
      pull (GuidePull): the guides
      p (vec3, m): the particle's position
      root (vec3, m): its strand's root (pinned, so no thread moves it)
      strand (int, index): its strand
      i (int, index): the particle
      f (int, index): the earlier captured frame (guide_frames)
      f1 (int, index): the later captured frame
      t (float): the later frame's weight
    Returns:
      vec3 (m): the pulled position
    """
    g = pull.strand_guides[strand]
    w = pull.weights[strand]
    s = pull.param[i]
    offset = wp.vec3(0.0)
    for k in range(3):
        if w[k] > 0.0:
            a = f * pull.guides + g[k]
            b = f1 * pull.guides + g[k]
            shape = (1.0 - t) * (guide_point(pull.points, a, pull.vertices, s) - pull.points[a * pull.vertices])
            shape += t * (guide_point(pull.points, b, pull.vertices, s) - pull.points[b * pull.vertices])
            offset += w[k] * shape
    return p + pull.stiffness * (root + offset - p)


@wp.struct
class StrandSlots:
    """What step_strands reads per particle and per shape window, in the order of its contact bounds
    (particle order, or lane order, lane_slot): slot-ordered arrays let a warp's threads, each walking
    one strand, read side by side in lane order. The windows' data sit at the slot of the window's
    first particle, the k-th of `size` values of a window at k * slots + its slot.

    Fields:
      slots (int): elements per array (particles, or lanes * the longest strand)
      inv_mass (float, per slot): 0 marks pinned particles
      rest_length (float, per slot, m): rest distance to the previous particle
      hold (float, per slot): root-hold weight
      root_local (vec3, per slot, m): groomed offset from the root in the root triangle's frame; read
          only for bound strands with a root hold
      window_at (int32, per slot): the window starting at the slot's particle, -1 for none (or past a
          strand's tip)
      offsets (float, window_size * slots, m): rest offsets along the rest axis (simplified variant)
      rest_local (vec3, per slot, m): rest position from the strand's root (full variant)
      rest_centroid (vec3, per slot, m): the rest centroid from the strand's root of the window
          starting at the slot (full variant)
      centroids (vec3, per slot, m): scratch, the centroid of the window starting at the slot
          (simplified variant)
      axes (vec3, per slot): scratch, that window's axis, zero when degenerate (simplified variant)
      frames (mat33, per slot): scratch, that window's rotation (full variant, window_frame)
      translations (vec3, per slot, m): scratch, that window's goal translation (full variant,
          window_frame)
    """

    slots: int
    inv_mass: wp.array(dtype=float)
    rest_length: wp.array(dtype=float)
    hold: wp.array(dtype=float)
    root_local: wp.array(dtype=wp.vec3)
    window_at: wp.array(dtype=wp.int32)
    offsets: wp.array(dtype=float)
    rest_local: wp.array(dtype=wp.vec3)
    rest_centroid: wp.array(dtype=wp.vec3)
    centroids: wp.array(dtype=wp.vec3)
    axes: wp.array(dtype=wp.vec3)
    frames: wp.array(dtype=wp.mat33)
    translations: wp.array(dtype=wp.vec3)


@wp.func(inline=True)
def update_window(
    x: wp.array(dtype=wp.vec3),
    slot: int,
    stride: int,
    window_size: int,
    variant: int,
    exact: int,
    iterations: int,
    rotations: wp.array(dtype=wp.quat),
    per: StrandSlots,
):
    """Solve the window that starts at the particle in `slot`, if one does, and keep what its goals
    need at that slot: its centroid and axis (simplified variant, the axis zero when degenerate), or
    its goals' map (full variant, as shape_match_rotations: window_frame), its rotation kept per
    window for the next warm start.

    Inputs:
      x (vec3, per slot, m): positions before the shape pass
      slot (int, index): the slot of the window's first particle
      stride (int): slots from one particle of a strand to the next (window_centroid)
      window_size (int): particles per window
      variant (int): SHAPE_SIMPLIFIED or SHAPE_FULL
      exact (int, flag): non-zero solves a rotation from scratch (full)
      iterations (int): rotation refinement steps when exact == 0 (full)
    In/out:
      rotations (quat, per window): the window's last rotation in, its new one out (full)
    Outputs:
      per (StrandSlots): the window's centroid and axis, or its frame and translation, written at
          the slot (its particles read them)
    """
    w = per.window_at[slot]
    if w >= 0:
        if variant == SHAPE_SIMPLIFIED:
            u, _straight = window_direction(x, slot, stride, window_size)
            per.centroids[slot] = window_centroid(x, slot, stride, window_size)
            per.axes[slot] = u
        else:
            R, t = solved_window(x, slot, stride, window_size, per.rest_local, per.rest_centroid[slot], rotations, w,
                                 exact, iterations)
            per.frames[slot] = R
            per.translations[slot] = t


@wp.func(inline=True)
def shaped_position(
    p: wp.vec3,
    slot: int,
    stride: int,
    k: int,
    count: int,
    window_size: int,
    variant: int,
    stiffness: float,
    per: StrandSlots,
):
    """The particle in `slot`, k-th of its strand, moved by the summed pulls of the windows that hold
    it over the window size, once those are solved (update_window): the goals and their order of
    shape_match_step.

    Inputs:
      p (vec3, m): the particle's position before the pass
      slot (int, index): its slot
      stride (int): slots from one particle of a strand to the next (window_centroid)
      k (int, index): its place along the strand
      count (int): the strand's particles
      window_size (int): particles per window
      variant (int): SHAPE_SIMPLIFIED or SHAPE_FULL
      stiffness (float, fraction): share of the way to the goal moved, in (0, 1]
      per (StrandSlots): inverse masses, the rest positions, and the windows as update_window left them
    Returns:
      vec3 (m): the particle's position after the pass; a pinned particle's stays where it was
    """
    if per.inv_mass[slot] == 0.0:
        return p
    if variant != SHAPE_SIMPLIFIED:
        return full_shaped_position(p, k, count, window_size, stiffness, per.frames, per.translations, slot, stride,
                                    per.rest_local[slot])
    return simplified_shaped_position(p, k, slot, stride, slot, stride, window_size, stiffness, per.window_at,
                                      per.centroids, per.axes, per.offsets, per.slots)


@wp.func(inline=True)
def simplified_shaped_position(
    p: wp.vec3,
    k: int,
    at: int,
    stride: int,
    slot: int,
    slot_stride: int,
    window_size: int,
    stiffness: float,
    window_at: Any,
    centroids: Any,
    axes: Any,
    offsets: wp.array(dtype=float),
    slots: int,
):
    """A free particle, k-th of its strand, moved by the summed pulls of the simplified windows that
    hold it over the window size (shaped_position's simplified variant), the windows read from arrays
    (per slot) or from a block's shared tiles (per lane, frame_in_block).

    Inputs:
      p (vec3, m): the particle's position before the pass
      k (int, index): its place along the strand
      at (int, index): its element of window_at, centroids and axes
      stride (int): elements of those from one particle of the strand to the next
      slot (int, index): its slot of offsets (StrandSlots)
      slot_stride (int): slots of offsets from one particle of the strand to the next (stride, unless
          the tiles hold the strands side by side while the slots are in particle order: FRAME_IN_WARPS)
      window_size (int): particles per window
      stiffness (float, fraction): share of the way to the goal moved, in (0, 1]
      window_at (int32, per element): the window starting at the element's particle, -1 for none
      centroids (vec3, per element, m): the centroid of the window starting there (update_window)
      axes (vec3, per element): its axis, zero when degenerate
      offsets (float, window_size * slots, m): rest offsets along the rest axis (StrandSlots.offsets)
      slots (int): elements per row of offsets
    Returns:
      vec3 (m): the particle's position after the pass
    """
    goal = wp.vec3(0.0)
    held = float(0.0)
    for j in range(window_size):
        if k - j >= 0:
            first = at - j * stride
            w = window_at[first]
            if w >= 0:
                u = axes[first]
                if u == wp.vec3(0.0):
                    goal += p  # a degenerate window holds its particles where they are
                else:
                    goal += centroids[first] + offsets[j * slots + slot - j * slot_stride] * u
                held += 1.0
    return p + stiffness * (goal - held * p) / float(window_size)


@wp.func
def shape_strand(
    x: wp.array(dtype=wp.vec3),
    first: int,
    stride: int,
    count: int,
    window_size: int,
    variant: int,
    stiffness: float,
    exact: int,
    iterations: int,
    rotations: wp.array(dtype=wp.quat),
    per: StrandSlots,
    x_out: wp.array(dtype=wp.vec3),
):
    """One shape-matching pass over one strand (step_strands' passes before its last): the windows
    solved in order from the root, each particle moved once every window holding it is.

    Inputs:
      x (vec3, per slot, m): positions before the pass
      first (int, index): the slot of the strand's first particle
      stride (int): slots from one particle to the next (window_centroid)
      count (int): the strand's particles
      window_size (int): particles per window
      variant (int): SHAPE_SIMPLIFIED or SHAPE_FULL
      stiffness (float, fraction): share of the way to the goal moved, in (0, 1]
      exact (int, flag): non-zero solves the rotations from scratch (full)
      iterations (int): rotation refinement steps when exact == 0 (full)
    In/out:
      rotations (quat, per window): the strand's window rotations (full)
      per (StrandSlots): the windows; their centroids and axes (simplified) or frames and translations
          (full) written
    Outputs:
      x_out (vec3, per slot, m): positions after the pass; must not alias x
    """
    for k in range(count):
        slot = first + k * stride
        update_window(x, slot, stride, window_size, variant, exact, iterations, rotations, per)
        x_out[slot] = shaped_position(x[slot], slot, stride, k, count, window_size, variant, stiffness, per)


@wp.func
def predict_strand(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    start: int,
    first: int,
    stride: int,
    count: int,
    forces: StrandForces,
    time: float,
    dt: float,
    bound: int,
    skin: SkinBinding,
    particle_binding: wp.array(dtype=wp.int32),
    origin: wp.vec3,
    frame: wp.mat33,
    hold_stiffness: float,
    per: StrandSlots,
    pull: GuidePull,
    strand: int,
    guide_frame: int,
    guide_next: int,
    guide_weight: float,
    lane_state: int,
    x_out: wp.array(dtype=wp.vec3),
):
    """predict_positions and follow_guides for one strand, whose root frame the caller has
    (root_frames).

    Inputs:
      x (vec3, per particle or per slot, m): positions at the start of the substep
      v (vec3, per particle or per slot, m/s): velocities at the start of the substep
      start (int, index): the strand's first particle
      first (int, index): the slot of the strand's first particle
      stride (int): slots from one particle to the next (window_centroid)
      count (int): the strand's particles
      forces (StrandForces): gravity, wind with its gusts, drag and damping
      time (float, s): the gusts' time
      dt (float, s): substep length
      bound (int, flag): non-zero when the strand is bound to the collider
      skin (SkinBinding): the bindings on the collider posed for the end of the substep
      particle_binding (int32, per particle): binding index of each pinned particle, -1 when unbound
      origin (vec3, m): the root's position in this pose
      frame (mat33): the root triangle's frame in this pose
      hold_stiffness (float, fraction per substep): share of the way to the groomed position moved
      per (StrandSlots): inverse masses, root-hold weights and groomed offsets
      pull (GuidePull): captured guides; pull.stiffness 0 for none
      strand (int, index): the strand
      guide_frame (int, index): the guides' earlier captured frame (guide_frames)
      guide_next (int, index): their later captured frame
      guide_weight (float): the later frame's weight
      lane_state (int, flag): non-zero: x and v are per slot (a frame kept in lane order), else per
          particle
    Outputs:
      x_out (vec3, per slot, m): the strand's predicted positions
    """
    root = wp.vec3(0.0)  # the strand's predicted root, which the guides' targets hang from
    for k in range(count):
        i = start + k
        slot = first + k * stride
        at = i
        if lane_state != 0:
            at = slot
        inv_mass = per.inv_mass[slot]
        binding = int(-1)
        weight = float(0.0)
        target = wp.vec3(0.0)
        if bound != 0:
            if inv_mass == 0.0:
                binding = particle_binding[i]
            weight = per.hold[slot] * hold_stiffness
            if weight > 0.0:
                target = origin + frame * per.root_local[slot]
        p = x[at]
        p, _vel = predicted_position(p, v[at], inv_mass, forces, gusting_wind(forces, p, time), dt, skin, binding,
                                     target, weight)
        if k == 0:
            root = p
        if pull.stiffness > 0.0:
            if inv_mass != 0.0:
                p = guided_position(pull, p, root, strand, i, guide_frame, guide_next, guide_weight)
        x_out[slot] = p


def _step_strands(paths, simplified=False, loose=False):
    """step_strands compiled with the collision paths `paths` (PATHS_*) of its length pass, and with
    `simplified` for simplified shape matching only (variant is then read as SHAPE_SIMPLIFIED);
    `loose` walks the sphere tree only where a particle may be inside an unlisted leaf (_follow_leader)."""
    follow = follow_leader if paths == PATHS_ALL else _follow_leader(paths, loose=loose)
    name = "step_strands" + PATH_NAMES[paths] + ("_simplified" if simplified else "") + ("_loose" if loose else "")
    # every path, the CPU's default, in this module; a variant only where its case launches it
    module = None if paths == PATHS_ALL and not simplified else deferred_module(f"{__name__}.{name}")

    @wp.kernel(module=module, cuda_max_registers=128, name=name)
    def step_strands(
        x: wp.array(dtype=wp.vec3),
        v: wp.array(dtype=wp.vec3),
        strand_start: wp.array(dtype=wp.int32),
        pinned_per_strand: int,
        forces: StrandForces,
        clock: wp.array(dtype=float),
        time_offset: float,
        dt: float,
        bound: int,
        skin: SkinBinding,
        particle_binding: wp.array(dtype=wp.int32),
        root_binding: wp.array(dtype=wp.int32),
        hold_stiffness: float,
        pull: GuidePull,
        window_size: int,
        variant: int,
        passes: int,
        stiffness: float,
        exact: int,
        rotation_iterations: int,
        rotations: wp.array(dtype=wp.quat),
        per: StrandSlots,
        contact: StrandContact,
        ftl_damping: float,
        shaped: wp.array(dtype=wp.vec3),
        spare: wp.array(dtype=wp.vec3),
        x_out: wp.array(dtype=wp.vec3),
        v_out: wp.array(dtype=wp.vec3),
        order: LaneOrder,
        lane_state: int,
        first: int,
    ):
        """A whole hair substep in one launch, a thread per strand: root frame, prediction, the guides'
        pull, shape matching and the length pass with its collisions and velocities, the same strands
        as the launches from root_frames to follow_the_leader.

        Those launches each read and write every particle once; here a strand stays with one thread
        from start to end, so its particles are read once and written once, the predicted and the
        shape-matched positions stay in that thread's cache, and no launch waits for another. The
        last shape pass is folded into the length pass: the window starting at each particle is solved
        just before the particle is placed, from positions no particle of it has left yet, so that pass
        needs no buffer of its own and each particle is read once more, not twice. Everything but the
        state (x, v and the results) is read per slot (StrandSlots), so in lane order a warp's threads
        read side by side.

        contact_motion (and anchor_frame) must run first, as for follow_the_leader; find_short_lists and
        list_leaves_ahead may, from the start positions.

        Launch: one thread per strand of a range of strands (dim = strands in the range), or in lane
        order one per lane (then first is 0).
        Inputs:
          x (vec3, per particle, m): positions at the start of the substep (where the bounds hold); per
              slot with lane_state
          v (vec3, per particle, m/s): velocities at the start of the substep; per slot with lane_state
          strand_start (int32, num_strands + 1): first particle of each strand, then the total count
          pinned_per_strand (int): leading particles of each strand the length pass leaves alone (>= 1)
          forces (StrandForces): gravity, wind with its gusts, drag and damping
          clock (float, 1 element, s): device clock
          time_offset (float, s): time of this substep relative to clock[0]
          dt (float, s): substep length
          bound (int, flag): non-zero when the strands are bound to the collider (the arrays below are
              read only then)
          skin (SkinBinding): the bindings on the collider posed for the end of the substep
          particle_binding (int32, per particle): binding index of each pinned particle, -1 when unbound
          root_binding (int32, per strand): binding of the strand's root particle (read when
              hold_stiffness > 0)
          hold_stiffness (float, fraction per substep): share of the way to the groomed position moved
          pull (GuidePull): captured guides the predicted strands are pulled toward; pull.stiffness 0
              for none
          window_size (int): particles per window
          variant (int): SHAPE_SIMPLIFIED or SHAPE_FULL
          passes (int): shape-matching passes, 0 for none
          stiffness (float, fraction): share of the way to the goal moved per pass, in (0, 1]
          exact (int, flag): non-zero solves the first pass's rotations from scratch (full)
          rotation_iterations (int): rotation refinement steps per pass otherwise (full)
          ftl_damping (float, fraction): share of the child's move to rest length taken off the velocity, [0.7, 1]
          order (LaneOrder): particle order, or the lane order: the order of the slots (per, shaped,
              spare and the contact bounds)
          lane_state (int, flag): non-zero: the state (x, v, x_out, v_out) is per slot too, in lane
              order, a frame's substeps kept there (HairSolver.frame_lanes): every read and write of a
              warp's strands then lies side by side, where per particle they lie a strand apart
          first (int, index): the range's first strand; thread t works on strand first + t
        In/out:
          rotations (quat, per window): window rotations, refined from their last values (full)
          per (StrandSlots): the particles and windows per slot; the windows' centroids and axes, or frames
              and translations, written
          contact (StrandContact): the collider and its settings; its contact bounds per slot, at x in,
              at x_out out (follow_the_leader)
        Outputs:
          shaped (vec3, per slot, m): scratch, the last pass's input; may be x_out itself in particle order
          spare (vec3, per slot, m): scratch for two passes or more; None otherwise
          x_out (vec3, per particle, m): positions at the end of the substep; per slot with lane_state
          v_out (vec3, per particle, m/s): velocities at the end of the substep; per slot with lane_state
        """
        s = wp.tid() + first
        lane = s
        lanes = order.lanes
        shapes = variant
        if wp.static(simplified):
            shapes = int(SHAPE_SIMPLIFIED)  # a constant: the full variant's code is not compiled in
        stride = int(1)
        if lanes > 0:
            s = order.strand_of[lane]
            stride = lanes
        start = strand_start[s]
        count = strand_start[s + 1] - start
        base = lane_slot(start, lane, 0, lanes)
        origin = wp.vec3(0.0)
        frame = wp.mat33(0.0)
        if bound != 0:
            if hold_stiffness > 0.0:
                rb = root_binding[s]
                origin = bound_position(skin, rb)
                frame = face_frame(skin.mesh_points, skin.mesh_indices, skin.triangle[rb])
        time = clock[0] + time_offset
        guide_frame, guide_next, guide_weight = int(0), int(0), float(0.0)
        if pull.stiffness > 0.0:
            guide_frame, guide_next, guide_weight = guide_frames(pull, time)
        # every pass but the last ping-pongs between spare and shaped, ending in shaped
        inner = wp.max(passes - 1, 0)
        if inner % 2 == 0:
            predict_strand(x, v, start, base, stride, count, forces, time, dt, bound, skin, particle_binding, origin,
                           frame, hold_stiffness, per, pull, s, guide_frame, guide_next, guide_weight, lane_state,
                           shaped)
        else:
            predict_strand(x, v, start, base, stride, count, forces, time, dt, bound, skin, particle_binding, origin,
                           frame, hold_stiffness, per, pull, s, guide_frame, guide_next, guide_weight, lane_state,
                           spare)
        for n in range(inner):
            solve = int(0)
            if n == 0:
                solve = exact
            if (inner - 1 - n) % 2 == 0:
                shape_strand(spare, base, stride, count, window_size, shapes, stiffness, solve, rotation_iterations,
                             rotations, per, shaped)
            else:
                shape_strand(shaped, base, stride, count, window_size, shapes, stiffness, solve, rotation_iterations,
                             rotations, per, spare)
        last_exact = int(0)
        if inner == 0:
            last_exact = exact
        # the last pass and the length pass, root to tip; x_out may be shaped itself, so each window is
        # solved before its first particle is placed
        parent = wp.vec3(0.0)
        before = wp.vec3(0.0)
        # where the state of particle k is: its particle, or with lane_state its slot (state_step apart)
        state_base, state_step = int(start), int(1)
        if lane_state != 0:
            state_base, state_step = base, stride
        for k in range(count):
            i = base + k * stride
            at = state_base + k * state_step
            p = shaped[i]
            if passes > 0:
                update_window(shaped, i, stride, window_size, shapes, last_exact, rotation_iterations, rotations, per)
                p = shaped_position(p, i, stride, k, count, window_size, shapes, stiffness, per)
            correction = wp.vec3(0.0)
            if k >= pinned_per_strand:
                placed = leader_placement(parent, before, k, p, per.rest_length[i])
                correction = placed - p
                p = placed
            if k > 0:
                vel = (parent - x[at - state_step]) / dt
                if per.inv_mass[i - stride] > 0.0:
                    vel = vel - (ftl_damping / dt) * correction
                v_out[at - state_step] = vel
            if k >= pinned_per_strand:
                p = follow(parent, p, per.rest_length[i], i, x[at], contact, NO_BOUND, wp.vec4i(-1, -1, -1, -1),
                           NO_BOUND)
            x_out[at] = p
            before = parent
            parent = p
        last = state_base + (count - 1) * state_step
        v_out[last] = (parent - x[last]) / dt

    return step_strands


# every path: the CPU's fused substep; a GPU's cases with their own paths only, for fewer spilled
# registers (sm_90: every path 964/1056 bytes; the sphere tree, simplified, 112/100; bounded queries,
# the mesh through its BVH, 36/32, simplified 0/0)
STEP_STRANDS = {(PATHS_ALL, False): _step_strands(PATHS_ALL),
                (PATHS_SPHERE_LISTS, True): _step_strands(PATHS_SPHERE_LISTS, simplified=True),
                (PATHS_QUERIES, False): _step_strands(PATHS_QUERIES),
                (PATHS_QUERIES, True): _step_strands(PATHS_QUERIES, simplified=True)}
# the sphere tree's fused substep with loose lists (HairSolver.loose_lists with fused, a GPU experiment)
STEP_STRANDS_LOOSE = {(PATHS_SPHERE_LISTS, True): _step_strands(PATHS_SPHERE_LISTS, simplified=True, loose=True)}
step_strands = STEP_STRANDS[(PATHS_ALL, False)]

# substeps a frame_in_block launch takes at most (FramePoses.offsets)
FRAME_SUBSTEPS = 32
frame_offsets = wp.types.vector(length=FRAME_SUBSTEPS, dtype=float)


@wp.struct
class FramePoses:
    """The collider posed for every substep of a frame, ahead of it, as frame_in_block reads it: row j
    of each array is what the launches of substep j would read of the collider (Collider.apply_pose
    for the end of the substep, contact_motion over it).

    Fields:
      points (vec3, per pose * collider vertex, m): the posed vertices (the bindings' skin), row 0 the
          frame's start and row j + 1 the end of substep j; rows of one element where the strands are
          not bound
      spheres (vec4, per pose * sphere-tree node, m): the packed sphere tree (ColliderShape.spheres),
          rows as points
      meshes (uint64, per pose): wp.Mesh ids over each row of points, refitted to it (mesh collisions;
          0 otherwise)
      moved (int32, per substep * 1 element, MOTION_UNIT): ContactMotion.moved of each substep
      rigid (mat44, per substep * 1 element): ContactMotion.rigid of each substep
      center (vec3, per substep * 1 element, m): ContactMotion.center of each substep
      cells (int32, per substep * MOTION_GRID^3 cells, MOTION_UNIT): ContactMotion.cells of each substep
      offsets (vec32f, s): each substep's end relative to the clock, FRAME_SUBSTEPS of them
    """

    points: wp.array2d(dtype=wp.vec3)
    spheres: wp.array2d(dtype=wp.vec4)
    meshes: wp.array(dtype=wp.uint64)
    moved: wp.array2d(dtype=wp.int32)
    rigid: wp.array2d(dtype=wp.mat44)
    center: wp.array2d(dtype=wp.vec3)
    cells: wp.array2d(dtype=wp.int32)
    offsets: frame_offsets


@wp.func
def block_sync(tile: Any):
    """A barrier across the block: the masked write of nothing, which every lane calls, syncs; a
    shared tile read before it may be written after it.

    Inputs:
      tile (Any, per lane): a shared tile of the block (its first element is read, nothing written)
    Returns:
      nothing: every lane of the block has reached the barrier when any returns
    """
    wp.tile_scatter_masked(tile, 0, tile[0], False)



@wp.func
def motion_row(moved: wp.array2d(dtype=wp.int32), rigid: wp.array2d(dtype=wp.mat44), center: wp.array2d(dtype=wp.vec3),
               cells: wp.array2d(dtype=wp.int32), r: int):
    """Row r of a frame's motions (FramePoses) as one substep's ContactMotion.

    Inputs:
      moved (int32, per substep * 1 element, MOTION_UNIT): the substeps' ContactMotion.moved
      rigid (mat44, per substep * 1 element): their ContactMotion.rigid
      center (vec3, per substep * 1 element, m): their ContactMotion.center
      cells (int32, per substep * MOTION_GRID^3 cells, MOTION_UNIT): their ContactMotion.cells
      r (int, index): the substep
    Returns:
      ContactMotion: views of row r
    """
    motion = ContactMotion()
    motion.moved = moved[r]
    motion.rigid = rigid[r]
    motion.center = center[r]
    motion.cells = cells[r]
    return motion


@wp.func
def substep_contact(contact: StrandContact, poses: FramePoses, j: int):
    """The strands' contact for substep j of a frame in one launch: its collider shape's spheres and
    mesh those of pose j + 1, its motion row j (motion_row); contact itself without a collider.

    Inputs:
      contact (StrandContact): the collider's settings and the contact bounds
      poses (FramePoses): the collider for each substep
      j (int, index): the substep
    Returns:
      StrandContact: contact with the substep's shape and motion
    """
    touching = contact
    if contact.mode != 0:
        shape = contact.shape
        shape.spheres = poses.spheres[j + 1]
        shape.mesh = poses.meshes[j + 1]
        touching.shape = shape
        touching.motion = motion_row(poses.moved, poses.rigid, poses.center, poses.cells, j)
    return touching


@wp.func
def held_target(posed: SkinBinding, rb: int, local: wp.vec3):
    """Where the root hold pulls a particle: its groomed position carried by its root's frame.

    Inputs:
      posed (SkinBinding): the bindings at the substep's pose
      rb (int, index): the binding of the particle's strand's root
      local (vec3, m): the particle's groomed position in its root's frame (StrandSlots.root_local)
    Returns:
      vec3 (m): the target
    """
    return bound_position(posed, rb) + face_frame(posed.mesh_points, posed.mesh_indices, posed.triangle[rb]) * local


@wp.kernel(module=FRAME_POSES)
def skin_listed_poses(
    rest_points: wp.array(dtype=wp.vec3),
    skin_indices: wp.array(dtype=wp.vec4i),
    skin_weights: wp.array(dtype=wp.vec4),
    bone_matrices: wp.array(dtype=wp.mat44),
    num_bones: int,
    listed: wp.array(dtype=wp.int32),
    points: wp.array2d(dtype=wp.vec3),
):
    """skinning.skin_listed_points for every substep's pose of a frame at once (FramePoses.points):
    row r + 1 takes pose r + 1 of the uploaded ones.

    Launch: one thread per substep and listed point (dim = (substeps, len(listed))).
    Inputs:
      rest_points (vec3, per point, m): points in the bind pose
      skin_indices (vec4i, per point): bone of each influence, within one pose
      skin_weights (vec4, per point): weight of each influence; 0 skips it
      bone_matrices (mat44, num_poses * num_bones, m): per pose and bone, bind pose to posed
      num_bones (int): bones per pose
      listed (int32, per listed point): the points to skin
    Outputs:
      points (vec3, per pose * point, m): the listed points skinned, rows 1 to substeps
    """
    r, t = wp.tid()
    i = listed[t]
    points[r + 1, i] = skinned_point(rest_points, skin_indices, skin_weights, bone_matrices, (r + 1) * num_bones, i)


@wp.kernel(module=FRAME_POSES)
def skin_sphere_poses(
    rest_centers: wp.array(dtype=wp.vec3),
    skin_indices: wp.array(dtype=wp.vec4i),
    skin_weights: wp.array(dtype=wp.vec4),
    bone_matrices: wp.array(dtype=wp.mat44),
    num_bones: int,
    radii: wp.array(dtype=float),
    is_leaf: wp.array(dtype=wp.int32),
    centers: wp.array2d(dtype=wp.vec3),
    posed_radii: wp.array2d(dtype=float),
):
    """The sphere tree's centres skinned to every substep's pose of a frame at once, with the inner
    radii cleared (Collider.apply_pose's skin_points and collision.clear_inner_radii): row r + 1 takes
    pose r + 1.

    Launch: one thread per substep and tree node (dim = (substeps, num_nodes)).
    Inputs:
      rest_centers (vec3, per tree node, m): node centres in the bind pose
      skin_indices (vec4i, per tree node): bone of each influence (the nearest vertex's)
      skin_weights (vec4, per tree node): weight of each influence
      bone_matrices (mat44, num_poses * num_bones, m): per pose and bone, bind pose to posed
      num_bones (int): bones per pose
      radii (float, per tree node, m): the tree's radii, leaves' read
      is_leaf (int32, per tree node): 1 for leaves
    Outputs:
      centers (vec3, per pose * tree node, m): posed centres, rows 1 to substeps
      posed_radii (float, per pose * tree node, m): leaf radii, inner radii 0 (refit_sphere_poses grows
          them)
    """
    r, i = wp.tid()
    centers[r + 1, i] = skinned_point(rest_centers, skin_indices, skin_weights, bone_matrices, (r + 1) * num_bones, i)
    radius = float(0.0)
    if is_leaf[i] != 0:
        radius = radii[i]
    posed_radii[r + 1, i] = radius


@wp.kernel(module=FRAME_POSES)
def refit_sphere_poses(
    centers: wp.array2d(dtype=wp.vec3),
    radii: wp.array2d(dtype=float),
    parent: wp.array(dtype=wp.int32),
    is_leaf: wp.array(dtype=wp.int32),
):
    """collision.refit_sphere_tree for every substep's pose of a frame at once (after skin_sphere_poses).

    Launch: one thread per substep and tree node (dim = (substeps, num_nodes)); inner nodes' return.
    Inputs:
      centers (vec3, per pose * tree node, m): posed centres
      parent (int32, per tree node): parent node, -1 for the root
      is_leaf (int32, per tree node): 1 for leaves
    In/out:
      radii (float, per pose * tree node, m): rows 1 to substeps: inner radii grown to bound their leaves
    """
    r, j = wp.tid()
    if is_leaf[j] != 0:
        grow_ancestors(centers[r + 1], radii[r + 1], parent, j)


@wp.kernel(module=FRAME_POSES)
def pack_sphere_poses(
    centers: wp.array2d(dtype=wp.vec3),
    radii: wp.array2d(dtype=float),
    spheres: wp.array2d(dtype=wp.vec4),
):
    """collision.pack_sphere_tree for every substep's pose of a frame at once (FramePoses.spheres).

    Launch: one thread per substep and tree node (dim = (substeps, num_nodes)).
    Inputs:
      centers (vec3, per pose * tree node, m): posed centres
      radii (float, per pose * tree node, m): refitted radii
    Outputs:
      spheres (vec4, per pose * tree node, m): rows 1 to substeps: centre and radius side by side
    """
    r, i = wp.tid()
    c = centers[r + 1, i]
    spheres[r + 1, i] = wp.vec4(c[0], c[1], c[2], radii[r + 1, i])


@wp.kernel(module=FRAME_POSES)
def anchor_frames(
    points: wp.array2d(dtype=wp.vec3),
    indices: wp.array(dtype=wp.int32),
    anchor_face: int,
    moved: wp.array2d(dtype=wp.int32),
    rigid: wp.array2d(dtype=wp.mat44),
    center: wp.array2d(dtype=wp.vec3),
    cells: wp.array2d(dtype=wp.int32),
):
    """anchor_frame for every substep of a frame at once: substep r from pose r to pose r + 1.

    Launch: one thread per substep and motion-grid cell (dim = (substeps, MOTION_GRID^3)).
    Inputs:
      points (vec3, per pose * collider vertex, m): FramePoses.points (the anchor's vertices read)
      indices (int32, 3 per triangle): collider triangles
      anchor_face (int): the anchor triangle, below 0 for none
    Outputs:
      moved (int32, per substep * 1 element, MOTION_UNIT): zeroed
      rigid (mat44, per substep * 1 element): each substep's anchor motion
      center (vec3, per substep * 1 element, m): the anchor's centroid after each substep
      cells (int32, per substep * MOTION_GRID^3 cells, MOTION_UNIT): zeroed
    """
    r, cell = wp.tid()
    anchor_motion(points[r], points[r + 1], indices, anchor_face, motion_row(moved, rigid, center, cells, r), cell)


@wp.kernel(module=FRAME_POSES)
def contact_motions(
    points: wp.array2d(dtype=wp.vec3),
    centers: wp.array2d(dtype=wp.vec3),
    radii: wp.array2d(dtype=float),
    is_leaf: wp.array(dtype=wp.int32),
    neighbor_start: wp.array(dtype=wp.int32),
    neighbors: wp.array(dtype=wp.int32),
    local: int,
    vertices: int,
    reach: float,
    search: float,
    moved: wp.array2d(dtype=wp.int32),
    rigid: wp.array2d(dtype=wp.mat44),
    center: wp.array2d(dtype=wp.vec3),
    cells: wp.array2d(dtype=wp.int32),
):
    """contact_motion for every substep of a frame at once (after anchor_frames): substep r from pose
    r to pose r + 1.

    Launch: one thread per substep and vertex and tree node (dim = (substeps, vertices + nodes)), or per
    substep and node only when vertices == 0.
    Inputs:
      points (vec3, per pose * collider vertex, m): FramePoses.points
      centers (vec3, per pose * tree node, m): posed sphere centres
      radii (float, per pose * tree node, m): their radii
      is_leaf (int32, per tree node): 1 for leaf spheres
      neighbor_start (int32, vertices + 1): CSR offsets of each vertex's edge neighbours
      neighbors (int32, per vertex-neighbour pair): the neighbours
      local (int, flag): 0 counts every vertex and leaf
      vertices (int, flag): 0 counts the sphere tree's leaves only
      reach (float, m): the strands' reach from the anchor's centroid
      search (float, m): the largest contact bound follow_the_leader keeps
    In/out:
      moved (int32, per substep * 1 element, MOTION_UNIT): raised
      rigid (mat44, per substep * 1 element): read
      center (vec3, per substep * 1 element, m): read
      cells (int32, per substep * MOTION_GRID^3 cells, MOTION_UNIT): raised
    """
    r, t = wp.tid()
    raise_motion(t, points[r], points[r + 1], centers[r], centers[r + 1], radii[r + 1], is_leaf, neighbor_start,
                 neighbors, local, vertices, reach, search, motion_row(moved, rigid, center, cells, r))

# the arguments of a hair frame in one launch (frame_in_block, every layout), documented apart from its story
_FRAME_ARGUMENTS = """
        Inputs:
          x (vec3, per particle, m): positions at the start of the frame
          v (vec3, per particle, m/s): velocities at the start of the frame
          strand_start (int32, num_strands + 1): first particle of each strand, then the total count
          pinned_per_strand (int): leading particles of each strand the length pass leaves alone (>= 1)
          forces (StrandForces): gravity, wind with its gusts, drag and damping
          clock (float, 1 element, s): device clock
          poses (FramePoses): the collider for each substep and the substeps' times
          substeps (int): substeps of the frame, at most FRAME_SUBSTEPS
          dt (float, s): substep length
          bound (int, flag): non-zero when the strands are bound to the collider
          skin (SkinBinding): the bindings (its points replaced by each substep's row of poses.points)
          particle_binding (int32, per particle): binding index of each pinned particle, -1 when unbound
          root_binding (int32, per strand): binding of the strand's root particle
          hold_stiffness (float, fraction per substep): share of the way to the groomed position moved
          pull (GuidePull): captured guides; pull.stiffness 0 for none
          window_size (int): particles per window
          variant (int): SHAPE_SIMPLIFIED or SHAPE_FULL (read only by the variants compiled for both)
          passes (int): shape-matching passes a substep, 0 for none
          stiffness (float, fraction): share of the way to the goal moved per pass, in (0, 1]
          exact (int, flag): non-zero solves the first substep's first pass's rotations from scratch (full)
          rotation_iterations (int): rotation refinement steps per pass otherwise (full)
          per (StrandSlots): the particles and windows in particle order (its scratch is not used)
          ftl_damping (float, fraction): share of the child's move to rest length taken off the velocity, [0.7, 1]
          list_slack (float, m): the loose variant's slack of list_runs_short at the substep's start
              positions (hair_solver.FUSED_LIST_SLACK, as step_strands' walks queued ahead)
          first (int, index): the range's first strand, block 0's first
        In/out:
          rotations (quat, per window): window rotations, refined from their last values (full)
          contact (StrandContact): the collider's settings and the contact bounds per particle (its
              shape's spheres and its motion replaced by each substep's rows of poses)
        Outputs:
          x_out (vec3, per particle, m): positions at the end of the frame
          v_out (vec3, per particle, m/s): velocities at the end of the frame
"""


# the layouts of a hair frame in one launch, (side, groups, run): a block holds `side` strands side by side (a
# lane each) and `groups` threads along every one of them, each thread a run of `run` particles; thread t works
# on lane t % side's particles (t // side) * run ... (t // side) * run + run - 1, and a shared tile's element
# k * side + l holds particle k of lane l's strand. FRAME_IN_BLOCK's: a block per strand, a thread per particle
# (1, 32, 1) for strands of up to 32 particles, (1, 64, 1) up to 64; FRAME_IN_WARPS': 32 strands a block and
# FRAME_WARPS warps along them, each a run of FRAME_RUN particles, so that each step of the length pass's chain
# places a particle of 32 strands at once
FRAME_LANES = (32, 64)
FRAME_WARPS = 8
FRAME_STRANDS = 32
FRAME_RUN = FRAME_STRANDS // FRAME_WARPS
FRAME_IN_WARPS_LAYOUT = (FRAME_STRANDS, FRAME_WARPS, FRAME_RUN)
frame_handover = wp.types.matrix(shape=(2, 3), dtype=float)
# the variants each layout compiles: (paths, loose, simplified); those for full shape matching take either at
# run time
FRAME_VARIANTS = ((PATHS_NONE, False, True), (PATHS_SPHERE_LISTS, False, True), (PATHS_SPHERE_LISTS, True, True),
                  (PATHS_QUERIES, False, True), (PATHS_NONE, False, False), (PATHS_SPHERE_LISTS, False, False),
                  (PATHS_QUERIES, False, False))


def _frame_kernel(name, side, groups, run, paths, loose, simplified, cap, listed=True):
    """A hair frame in one launch laid out as `side` strands a block, `groups` threads along each and
    `run` particles a thread (see FRAME_LANES), its length pass compiled with the collision paths `paths`
    (PATHS_SPHERE_LISTS; PATHS_QUERIES for the mesh, its BVH queried; or PATHS_NONE for no collider: no
    collision code); `loose`: the lists that would run short are walked for before the chain, which walks
    only where a particle may be inside an unlisted leaf (step_strands' loose variant, with the walks of
    find_short_lists and list_leaves_ahead); `simplified`: simplified shape matching alone (variant read as
    SHAPE_SIMPLIFIED), else either; `cap`: its registers on CUDA; `listed`: its module among the deferred
    ones (warp_kernels._options.deferred_module), False for a layout built at run time for a timing."""
    # the length pass's step with the contact bounds as values, read for every particle before the chain
    follow = _follow_leader(paths, ahead=True, loose=loose)
    elements = side * groups * run
    collides = paths != PATHS_NONE
    lists = paths == PATHS_SPHERE_LISTS
    run_rows = wp.types.matrix(shape=(run, 3), dtype=float)  # a thread's particles' vec3s, a row each
    run_masses = wp.types.vector(length=run, dtype=float)

    # opt in: launched only where a run asks for it (HairSolver.frame_in_block), so a GPU's start does not
    # compile its variants
    module = deferred_module(f"{__name__}.{name}", block_dim=side * groups, opt_in=True, listed=listed)
    if run > 1:
        # the loops over a thread's run unrolled (its registers indexed by constants), the chain's turns not:
        # its walk, the length pass's step with its collisions, compiled once rather than once a group
        wp.set_module_options({"max_unroll": run}, module=module)

    @wp.kernel(module=module, cuda_max_registers=cap, name=name)
    def frame_in_block(
        x: wp.array(dtype=wp.vec3),
        v: wp.array(dtype=wp.vec3),
        strand_start: wp.array(dtype=wp.int32),
        pinned_per_strand: int,
        forces: StrandForces,
        clock: wp.array(dtype=float),
        poses: FramePoses,
        substeps: int,
        dt: float,
        bound: int,
        skin: SkinBinding,
        particle_binding: wp.array(dtype=wp.int32),
        root_binding: wp.array(dtype=wp.int32),
        hold_stiffness: float,
        pull: GuidePull,
        window_size: int,
        variant: int,
        passes: int,
        stiffness: float,
        exact: int,
        rotation_iterations: int,
        rotations: wp.array(dtype=wp.quat),
        per: StrandSlots,
        contact: StrandContact,
        ftl_damping: float,
        list_slack: float,
        x_out: wp.array(dtype=wp.vec3),
        v_out: wp.array(dtype=wp.vec3),
        first: int,
    ):
        """A whole frame of hair substeps in one launch: the state stays on chip (registers and the block's
        shared tiles) from the frame's start to its end, and what a particle needs of its neighbours
        (windows, parents, the FTL corrections) passes through shared memory, not global memory. Compiled
        per layout (side, groups, run): a block holds `side` strands side by side, a lane each, and `groups`
        threads along every one of them, each thread a run of `run` consecutive particles. FRAME_IN_BLOCK's
        layouts are a block per strand and a thread per particle, (1, 32, 1) and (1, 64, 1), whose chain
        places a particle a barrier with one lane working; FRAME_IN_WARPS' is (32, 8, 4), 8 warps of runs of
        4 along 32 strands, whose chain places a particle of 32 strands at each step, a barrier a run.

        Each substep is step_strands' against the sphere tree, the mesh (a BVH per substep's pose, queried)
        or no collider: the same strands, bit for bit. Prediction, the guides' pull and the shape passes run
        a thread per run: it solves the window starting at each of its particles (simplified: its centroid
        and axis; full: its rotation, warm-started per window, and goal map), and every particle then moves
        by the summed pulls of the windows holding it over the window size. The contact bounds are read
        before the length pass's chain, for every particle at once, so that no step of the chain waits on
        them; compiled loose, every thread first walks the sphere tree for its particles' lists where
        step_strands' walks queued ahead would (list_runs_short at the substep's start, list_leaves), and
        the chain walks only where a particle may be inside an unlisted leaf. The chain: the threads along
        a strand in turn each place their run (follow_leader, with its collisions and contact bounds) and
        hand the last two placements to the next; the placements go to x_out (the particles' final
        positions at the frame's end), which the block reads back after the chain for the velocities with
        each child's correction.

        The collider is posed for every substep ahead of the frame (FramePoses): the launches between
        substeps that step_strands needs (apply_pose, contact_motion) are all made before this one.

        Launch: one thread per run (dim = [ceil(strands / side)], block_dim = side * groups) with
        wp.launch_tiled, every strand of at most groups * run particles; on the CPU with
        wp.config.enable_cpu_blocks (a block's threads as fibers); first: block b works on strands
        first + side * b ... first + side * b + side - 1.
        """
        block, t = wp.tid()
        lane = t % side
        group = t // side
        strands_total = strand_start.shape[0] - 1
        s = first + block * side + lane
        live = s < strands_total
        s = wp.min(s, strands_total - 1)  # lanes past the last strand shadow it and write nothing
        start = strand_start[s]
        count = strand_start[s + 1] - start
        placed = wp.tile_zeros(shape=elements, dtype=wp.vec3, storage="shared")  # predicted: the chain's input
        # the substep's start positions: a thread's own in the tile rather than its registers, where the chain
        # reads them too
        starts = wp.tile_zeros(shape=elements, dtype=wp.vec3, storage="shared")
        lengths = wp.tile_zeros(shape=elements, dtype=float, storage="shared")
        centroids = wp.tile_zeros(shape=elements, dtype=wp.vec3, storage="shared")
        axes = wp.tile_zeros(shape=elements, dtype=wp.vec3, storage="shared")
        window_at = wp.tile_zeros(shape=elements, dtype=wp.int32, storage="shared")
        # a turn's last two placements (rows: the last, the one before it), handed to the next at one barrier
        handovers = wp.tile_zeros(shape=side, dtype=frame_handover, storage="shared")
        held_at = wp.tile_zeros(shape=wp.static(elements if collides else 1), dtype=float, storage="shared")
        leaves_at = wp.tile_zeros(shape=wp.static(elements if lists else 1), dtype=wp.vec4i, storage="shared")
        beyond_at = wp.tile_zeros(shape=wp.static(elements if lists else 1), dtype=float, storage="shared")
        # the full variant's windows: their goal maps, and the particles' rest positions from the root
        frames = wp.tile_zeros(shape=wp.static(elements if not simplified else 1), dtype=wp.mat33, storage="shared")
        rest = wp.tile_zeros(shape=wp.static(elements if not simplified else 1), dtype=wp.vec3, storage="shared")
        shapes = variant
        if wp.static(simplified):
            shapes = int(SHAPE_SIMPLIFIED)  # a constant: the full variant's code is not compiled in
        vel = run_rows()
        inv_mass = run_masses()
        for h in range(wp.static(run)):
            k = group * run + h
            e = k * side + lane
            here = live and k < count
            i = start + wp.min(k, count - 1)  # particles past the tip shadow it and write nothing
            w = int(-1)
            if here:
                w = per.window_at[i]
            wp.tile_scatter_masked(window_at, e, w, True)
            wp.tile_scatter_masked(lengths, e, per.rest_length[i], True)
            if wp.static(not simplified):
                wp.tile_scatter_masked(rest, e, per.rest_local[i], here)
            wp.tile_scatter_masked(starts, e, x[i], True)
            vel[h] = v[i]
            inv_mass[h] = per.inv_mass[i]
        rb = int(0)
        if bound != 0:
            rb = root_binding[s]
        # a bound that is not a constant to Warp: loops over a run that index no registers by it are not
        # unrolled, so their heavy code (the windows' solves, the tree walks) is compiled once, not `run` times
        each = int(run)
        # the chain's turns (runs): every group's where strands lie side by side; a block per strand takes as
        # many as its particles need (the same in every lane, so all of them meet each turn's barrier)
        turns = int(groups)
        if wp.static(side == 1):
            turns = wp.min(turns, (count + run - 1) // run)
        for j in range(substeps):
            time = clock[0] + poses.offsets[j]
            posed = skin
            if bound != 0:
                posed.mesh_points = poses.points[j + 1]
            if forces.turbulence > 0.0:
                # the gusts' noise at each particle, in the axes tile until the shape passes: in a loop the
                # compiler does not unroll, its code (most of the prediction's) is compiled once, not `run` times
                for h in range(each):
                    e = (group * run + h) * side + lane
                    wp.tile_scatter_masked(axes, e, gusting_wind(forces, starts[e], time), True)
            p = run_rows()
            for h in range(wp.static(run)):
                i = start + wp.min(group * run + h, count - 1)
                binding = int(-1)
                weight = float(0.0)
                target = wp.vec3(0.0)
                if bound != 0:
                    if inv_mass[h] == 0.0:
                        binding = particle_binding[i]
                    weight = per.hold[i] * hold_stiffness
                    if weight > 0.0:
                        target = held_target(posed, rb, per.root_local[i])
                e = (group * run + h) * side + lane
                air = forces.wind
                if forces.turbulence > 0.0:
                    air = axes[e]
                q, _vel = predicted_position(starts[e], vel[h], inv_mass[h], forces, air, dt, posed, binding, target,
                                             weight)
                p[h] = q
            if pull.stiffness > 0.0:
                guide_frame, guide_next, guide_weight = guide_frames(pull, time)
                block_sync(placed)
                for h in range(wp.static(run)):
                    k = group * run + h
                    wp.tile_scatter_masked(placed, k * side + lane, p[h], live and k < count)
                root = placed[lane]
                for h in range(wp.static(run)):
                    k = group * run + h
                    if live and k < count and inv_mass[h] != 0.0:
                        p[h] = guided_position(pull, p[h], root, s, start + k, guide_frame, guide_next, guide_weight)
            for shape_pass in range(passes):
                block_sync(placed)
                for h in range(wp.static(run)):
                    k = group * run + h
                    wp.tile_scatter_masked(placed, k * side + lane, p[h], live and k < count)
                if shapes == SHAPE_SIMPLIFIED:
                    for h in range(each):
                        k = group * run + h
                        e = k * side + lane
                        c = wp.vec3(0.0)
                        u = wp.vec3(0.0)
                        if live and k < count and window_at[e] >= 0:
                            u, _straight = window_direction(placed, e, side, window_size)
                            c = window_centroid(placed, e, side, window_size)
                        wp.tile_scatter_masked(centroids, e, c, True)
                        wp.tile_scatter_masked(axes, e, u, True)
                    for h in range(wp.static(run)):
                        k = group * run + h
                        if live and k < count and inv_mass[h] != 0.0:
                            p[h] = simplified_shaped_position(p[h], k, k * side + lane, side, start + k, 1,
                                                              window_size, stiffness, window_at, centroids, axes,
                                                              per.offsets, per.slots)
                if wp.static(not simplified):
                    if shapes != SHAPE_SIMPLIFIED:
                        # as update_window and shaped_position: the window at each particle solved, then every
                        # particle moved by the summed pulls of the windows holding it over the window size
                        solve = int(0)
                        if j == 0 and shape_pass == 0:
                            solve = exact
                        for h in range(each):
                            k = group * run + h
                            e = k * side + lane
                            R = wp.mat33(0.0)
                            c = wp.vec3(0.0)
                            w = window_at[e]
                            if live and k < count and w >= 0:
                                R, c = solved_window(placed, e, side, window_size, rest, per.rest_centroid[start + k],
                                                     rotations, w, solve, rotation_iterations)
                            wp.tile_scatter_masked(frames, e, R, True)
                            wp.tile_scatter_masked(centroids, e, c, True)  # the goal translations, here
                        for h in range(wp.static(run)):
                            k = group * run + h
                            if live and k < count and inv_mass[h] != 0.0:
                                p[h] = full_shaped_position(p[h], k, count, window_size, stiffness, frames, centroids,
                                                            k * side + lane, side, per.rest_local[start + k])
            touching = substep_contact(contact, poses, j)
            # what the chain reads of each particle, written where it reads it before the chain starts
            block_sync(placed)
            for h in range(wp.static(run)):
                k = group * run + h
                here = live and k < count
                wp.tile_scatter_masked(placed, k * side + lane, p[h], here)
                if here and k < pinned_per_strand:
                    x_out[start + k] = p[h]  # a pinned particle stays where it was predicted
            for h in range(each):
                k = group * run + h
                e = k * side + lane
                here = live and k < count
                i = start + wp.min(k, count - 1)
                if wp.static(loose):
                    if here and k >= pinned_per_strand and touching.use_bounds != 0:
                        p0 = starts[e]
                        if list_runs_short(p0, p0, i, touching, list_slack):
                            list_leaves(i, p0, touching)
                if wp.static(collides):
                    held, held_leaves, held_beyond = held_bounds(i, int(touching.mode == COLLIDE_SPHERE_TREE),
                                                                 touching)
                    wp.tile_scatter_masked(held_at, e, held, here)
                    if wp.static(lists):
                        wp.tile_scatter_masked(leaves_at, e, held_leaves, here)
                        wp.tile_scatter_masked(beyond_at, e, held_beyond, here)
            # the chain, one loop of steps: step k is group k // run's, which takes the last two placements from
            # the group before it at its first step and hands its own to the next at its last, a barrier a run
            parent = placed[lane]
            before = parent
            for k in range(turns * run):
                h = k % run
                mine = group == k // run
                if mine and h == 0 and k > 0:
                    handover = handovers[lane]
                    parent = handover[0]
                    before = handover[1]
                if mine and live and k < count:
                    e = k * side + lane
                    q = placed[e]
                    if k >= pinned_per_strand:
                        held = float(NO_BOUND)
                        held_leaves = wp.vec4i(-1, -1, -1, -1)
                        held_beyond = float(NO_BOUND)
                        if wp.static(collides):
                            held = held_at[e]
                        if wp.static(lists):
                            held_leaves = leaves_at[e]
                            held_beyond = beyond_at[e]
                        placed_k = leader_placement(parent, before, k, q, lengths[e])
                        v_out[start + k] = placed_k - q  # its correction, for its parent's velocity below
                        q = follow(parent, placed_k, lengths[e], start + k, starts[e], touching, held, held_leaves,
                                   held_beyond)
                        x_out[start + k] = q
                    before = parent
                    parent = q
                if h == run - 1:
                    wp.tile_scatter_masked(handovers, lane, wp.matrix_from_rows(parent, before), mine)
            # the velocities from the placements the chain left in x_out, less each child's correction, which it
            # left in v_out (free until the frame's end writes the velocities there)
            for h in range(wp.static(run)):
                k = group * run + h
                e = k * side + lane
                q = p[h]
                if live and k < count:
                    q = x_out[start + k]
                step_v = (q - starts[e]) / dt
                if live and k + 1 < count and inv_mass[h] > 0.0:
                    step_v = step_v - (ftl_damping / dt) * v_out[start + k + 1]
                vel[h] = step_v
                wp.tile_scatter_masked(starts, e, q, True)  # read above by this thread alone
        for h in range(wp.static(run)):
            k = group * run + h
            if live and k < count:
                x_out[start + k] = starts[k * side + lane]
                v_out[start + k] = vel[h]

    frame_in_block.func.__doc__ += _FRAME_ARGUMENTS
    return frame_in_block


_FRAME_KERNELS = {}


def frame_layout_misfit(layout):
    """Why no block holds `layout` (side, groups, run: see FRAME_LANES), a line, or None."""
    if len(layout) != 3 or min(layout) < 1 or layout[0] * layout[1] > 1024:
        return (f"a frame's layout takes side, groups and run >= 1 and at most 1024 threads a block "
                f"(side x groups), not {'x'.join(map(str, layout))}")
    return None


def frame_variant(layout, paths, loose=False, simplified=True):
    """The frame_in_block kernel for `layout` (side, groups, run: see FRAME_LANES) and its length pass's
    collision paths `paths`, `loose` and `simplified` (_frame_kernel), compiled in a module of its own at
    its first launch: FRAME_IN_BLOCK's and FRAME_IN_WARPS' layouts, or any other a GPU is to time
    (HairSolver.frame_layout). Raises ValueError for a layout no block holds (frame_layout_misfit)."""
    layout = tuple(int(n) for n in layout)
    misfit = frame_layout_misfit(layout)
    if misfit is not None:
        raise ValueError(misfit)
    side, groups, run = layout
    key = (side, groups, run, paths, loose, simplified)
    if key not in _FRAME_KERNELS:
        suffix = PATH_NAMES[paths] + ("_loose" if loose else "") + ("" if simplified else "_full")
        listed = True
        if side == 1 and run == 1 and groups in FRAME_LANES:
            name = f"frame_in_block_{groups}"
        elif (side, groups, run) == FRAME_IN_WARPS_LAYOUT:
            name = "frame_in_warps"
        else:
            name, listed = f"frame_{side}x{groups}x{run}", False
        # sm_90, a block per strand: the sphere tree's takes 191 registers uncapped (10 one-warp blocks an SM),
        # at 128 16 blocks with 380/348 bytes of spills (at 96 about 1 KB); without a collider 115, at 96 21
        # blocks with 56/48 bytes (at 64, 32 blocks: 260/296). Untimed on a GPU: capped where spills stay near
        # 100 bytes or less; the full variants at 128 (without a collider 412/324 bytes at 96). 32 strands a
        # block: 128 (uncapped 237-255), two blocks an SM; a block of more threads as the SM's 64k registers allow
        cap = 96 if side == 1 and paths == PATHS_NONE and simplified else min(128, 65536 // (side * groups))
        _FRAME_KERNELS[key] = _frame_kernel(name + suffix, side, groups, run, paths, loose, simplified, cap, listed)
    return _FRAME_KERNELS[key]


# keyed by (lanes, paths, loose, simplified): a block per strand
FRAME_IN_BLOCK = {(lanes, *variant): frame_variant((1, lanes, 1), *variant)
                  for lanes in FRAME_LANES for variant in FRAME_VARIANTS}
# keyed by (paths, loose, simplified): 32 strands a block; its tiles take 58 KB of shared memory without a
# collider, 83 KB with the sphere tree, 111 KB for full shape matching on the mesh (two blocks an SM)
FRAME_IN_WARPS = {variant: frame_variant(FRAME_IN_WARPS_LAYOUT, *variant) for variant in FRAME_VARIANTS}
frame_in_block = FRAME_IN_BLOCK[(32, PATHS_SPHERE_LISTS, False, True)]


@wp.func
def _toward(anchor: wp.vec3, p: wp.vec3, length: float):
    d = p - anchor
    dist = wp.length(d)
    if dist < 1.0e-12:
        return anchor + wp.vec3(0.0, -length, 0.0)
    return anchor + d * (length / dist)


@wp.kernel
def hold_in_comb(
    x: wp.array(dtype=wp.vec3),
    x_prev: wp.array(dtype=wp.vec3),
    strand_start: wp.array(dtype=int),
    rest_length: wp.array(dtype=float),
    pinned_per_strand: int,
    grip_from: wp.array(dtype=wp.vec3),
    grip_to: wp.array(dtype=wp.vec3),
    blend: float,
    iterations: int,
    contact: StrandContact,
    dt: float,
    grip: wp.array(dtype=int),
    v: wp.array(dtype=wp.vec3),
    order: LaneOrder,
    first: int,
):
    """Strands held by a comb: the gripped particle sits on the comb, the hair between root and comb
    keeps its segment lengths, and the hair beyond hangs from the comb.

    Hair slides through a comb: when the comb is farther from the root than the natural length of
    hair up to the grip, the grip moves toward the tip until that length suffices (or the tip is
    reached and the strand is pulled straight toward the comb). The root-to-grip chain is solved
    with both ends fixed by alternating forward and backward follow-the-leader sweeps (FABRIK),
    ending on the comb. A last sweep from the root keeps the hair out of the collider and the lengths
    right: from the first particle it pushes out, or the first segment more than 1% off its rest
    length, the rest follow at rest length, so where the comb would pull hair into the head (or a
    one-segment chain cannot take up its slack) the held particle stops short of the comb. The hair
    beyond follows the gripped particle. Runs after follow_the_leader; strands with grip < 0 are left
    untouched.

    Launch: one thread per strand of a range of strands (dim = strands in the range).
    Inputs:
      x_prev (vec3, per particle, m): positions at the start of the substep
      strand_start (int, num_strands + 1): first particle of each strand
      rest_length (float, per particle, m): rest distance to the previous particle (unused for roots)
      pinned_per_strand (int): particles at the start of each strand bound to the skin (at least 1)
      grip_from (vec3, per strand, m): where the comb holds each gripped strand at the frame's start
      grip_to (vec3, per strand, m): and at its end (the comb is dragged during the frame)
      blend (float, fraction): how far through the frame this substep ends, (0, 1]
      iterations (int): backward/forward sweep pairs for the root-to-grip chain
      dt (float, s): substep length
      order (LaneOrder): the order of the contact bounds, as follow_the_leader's
      first (int, index): the range's first strand; thread t works on strand first + t (0 for all of them)
    In/out:
      x (vec3, per particle, m): positions after follow_the_leader in; held by the comb out
      grip (int, per strand): particle index within the strand held by the comb, -1 for none; moves
          toward the tip as the hair slides
      v (vec3, per particle, m/s): velocities, recomputed for the moved particles of gripped strands
      contact (StrandContact): the collider (mode none, sphere tree or mesh: held hair is kept out of
          the head, the comb cannot pull hair into it; queried within its search radius, kept its
          margin out); the contact bounds (clearance) of the particles this moves set to NO_BOUND
    """
    s = wp.tid() + first
    g = grip[s]
    if g < 0:
        return
    lane = s
    if order.lanes > 0:
        lane = order.lane_of[s]
    start = strand_start[s]
    end = strand_start[s + 1]
    root = start + pinned_per_strand - 1
    target = grip_from[s] + (grip_to[s] - grip_from[s]) * blend
    held = wp.min(wp.max(start + g, root + 1), end - 1)
    natural = float(0.0)
    for i in range(root + 1, held + 1):
        natural += rest_length[i]
    reach = wp.length(target - x[root])
    while reach > natural and held < end - 1:
        held += 1
        natural += rest_length[held]
    grip[s] = held - start
    if reach >= TAUT * natural:
        # (nearly) taut, where the sweeps converge slowest: the chain lies straight toward the comb,
        # each segment shortened by at most 1 - TAUT; a strand too short to reach is pulled straight
        scale = wp.min(reach / natural, 1.0)
        direction = (target - x[root]) / reach
        along = float(0.0)
        for k in range(root + 1, held + 1):
            along += rest_length[k] * scale
            x[k] = x[root] + direction * along
        target = x[held]
    else:
        # a chain folded back along one line (straight hair lifted straight up) cannot take up its
        # slack without leaving that line, and the sweeps never leave it: bow it sideways a little
        axis = (target - x[root]) / wp.max(reach, 1.0e-9)
        side = wp.cross(axis, wp.vec3(0.0, 0.0, 1.0))
        if wp.length(side) < 1.0e-3:
            side = wp.cross(axis, wp.vec3(1.0, 0.0, 0.0))
        side = wp.normalize(side)
        spread = float(0.0)
        for k in range(root + 1, held):
            off = x[k] - x[root]
            spread = wp.max(spread, wp.length(off - axis * wp.dot(off, axis)))
        bow = 0.1 * (natural - reach)
        if spread < 0.01 * bow:  # only a chain lying on the line: a bent one bends further by itself
            for k in range(root + 1, held):
                x[k] = x[k] + side * (bow * wp.sin(3.14159265 * float(k - root) / float(held - root)))
        for _sweep in range(iterations):
            for k in range(root + 1, held):
                x[k] = _toward(x[k - 1], x[k], rest_length[k])
            x[held] = target
            for k in range(held - 1, root, -1):
                x[k] = _toward(x[k + 1], x[k], rest_length[k + 1])
    # a last sweep from the root keeps every length and the head out: the comb cannot pull hair
    # into the head, so where it tries, the held particle stops short of the comb
    follow = int(0)  # once a particle had to be pushed out, the ones after it follow at rest length
    for k in range(root + 1, end):
        p = x[k]
        if wp.abs(wp.length(p - x[k - 1]) - rest_length[k]) > 0.01 * rest_length[k]:
            follow = 1  # a chain too short to take up its slack (one segment) or not yet converged
        if k > held or follow != 0:
            p = _toward(x[k - 1], p, rest_length[k])
        if contact.mode != 0:
            pushed = collide_point(p, contact.mode, contact.shape, contact.margin, contact.search)
            if wp.length(pushed - p) > 0.0:
                p = _toward(x[k - 1], pushed, rest_length[k])
                follow = 1
        x[k] = p
        v[k] = (x[k] - x_prev[k]) / dt
        contact.clearance[lane_slot(start, lane, k - start, order.lanes)] = NO_BOUND


@wp.kernel
def count_unhealthy(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    max_speed: float,
    bad_count: wp.array(dtype=wp.int32),
    first_bad: wp.array(dtype=wp.int32),
):
    """Count particles that are non-finite or faster than max_speed and remember the lowest index.

    Used to stop a run with a clear message instead of writing an exploded cache; both results are
    device arrays, so the check can be queued without waiting.

    Launch: one thread per particle (dim = num_particles).
    Inputs:
      x (vec3, per particle, m): positions
      v (vec3, per particle, m/s): velocities
      max_speed (float, m/s): speed above which a particle counts as exploded
    In/out:
      bad_count (int32, 1 element): incremented per bad particle; zero it before the launch
      first_bad (int32, 1 element): lowest bad index (atomic min); fill with the int32 maximum before
    """
    i = wp.tid()
    p = x[i]
    vel = v[i]
    finite = wp.isfinite(p) and wp.isfinite(vel)
    if (not finite) or wp.length(vel) > max_speed:
        wp.atomic_add(bad_count, 0, 1)
        wp.atomic_min(first_bad, 0, i)


@wp.kernel
def strand_quality(
    x: wp.array(dtype=wp.vec3),
    first: int,
    part: int,
    rest_length: wp.array(dtype=float),
    strand_start: wp.array(dtype=wp.int32),
    mesh: wp.uint64,
    max_dist: float,
    depth: float,
    band: float,
    worst: wp.array2d(dtype=float),
    roots_near: wp.array2d(dtype=wp.int32),
    deep_count: wp.array2d(dtype=wp.int32),
    deep_listed: wp.array2d(dtype=wp.int32),
):
    """A groom's quality statistics against the collider, queued with a frame (sim.quality): the
    largest segment stretch, how far the roots lie from the surface, and the particles deeper
    inside than depth by the closest face's pseudo-normal (listed for the host to re-sign by the
    winding number, collision.list_deep_point).

    A thread walks a strand from its root, carrying a lower bound of each particle's signed
    distance: a signed distance changes by at most the distance moved (it changes sign only where
    it is zero), so a particle's is at least its parent's less the segment between them. A particle
    whose bound shows it cannot lie deeper than depth is not queried; the others are queried no
    farther than the bound leaves in doubt. A query that finds nothing within radius r proves the
    particle at least r outside when its bound is above -r. A query's cost grows with its radius,
    and most particles of a groom lie a few centimetres out, where a query of max_dist finds nothing
    only after searching all of it: the distances counted are the same as querying every particle
    out to max_dist, except where a self-intersecting pose gives the pseudo-normal's sign jumps
    away from the surface.

    Launch: one thread per strand from first (dim = strands counted).
    Inputs:
      x (vec3, per particle, m): positions
      first (int, index): the first strand of the launch
      part (int, index): the launch's row of the outputs (launches side by side on a CPU's cores
          each reduce into their own: collision.list_deep_point)
      rest_length (float, per particle, m): rest distance to the previous particle, 0 for a root
      strand_start (int32, strands + 1): each strand's first particle
      mesh (uint64): wp.Mesh id of the posed collider
      max_dist (float, m): query radius: farther roots report it, deeper particles are not seen
      depth (float, m): how deep a particle must lie to count
      band (float, m): roots within this of the surface count as near
    In/out:
      worst (float, rows * 2): the largest |segment / rest - 1| (computed in float64) and the largest
          |root distance| [m], by atomic max
      roots_near (int32, rows * 1): roots within band of the surface
      deep_count (int32, rows * 1): particles deeper than depth (all three zeroed before the launch)
    Outputs:
      deep_listed (int32, rows * any length): the first particles counted deep
    """
    s = wp.tid() + first
    start = strand_start[s]
    end = strand_start[s + 1]
    stretch = wp.float64(0.0)
    lower = float(-1.0e30)  # a lower bound of the particle's signed distance: none yet
    for i in range(start, end):
        p = x[i]
        if i == start:
            d = pseudo_normal_distance(mesh, p, max_dist)
            wp.atomic_max(worst, part, 1, wp.abs(d))
            if wp.abs(d) <= band:
                wp.atomic_add(roots_near, part, 0, 1)
            if d < max_dist:
                lower = d
            list_deep_point(d, depth, i, part, deep_count, deep_listed)
            continue
        length = wp.length(wp.vec3d(p) - wp.vec3d(x[i - 1]))
        rest = rest_length[i]
        if rest > 0.0:
            stretch = wp.max(stretch, wp.abs(length / wp.float64(rest) - wp.float64(1.0)))
        lower -= float(length)
        if lower < -depth:
            # a little beyond the doubt, so that finding nothing leaves a bound that lasts a segment
            radius = wp.min(max_dist, -lower + QUALITY_QUERY_SLACK)
            d = pseudo_normal_distance(mesh, p, radius)  # radius itself when nothing is that near
            if d < radius:
                lower = d
                list_deep_point(d, depth, i, part, deep_count, deep_listed)
            elif lower > -radius:
                lower = radius
    wp.atomic_max(worst, part, 0, float(stretch))


@wp.kernel(module=APART)
def follow_guides(
    x: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    particle_strand: wp.array(dtype=wp.int32),
    strand_start: wp.array(dtype=wp.int32),
    pull: GuidePull,
    clock: wp.array(dtype=float),
    time_offset: float,
    first: int,
):
    """Pull each free particle toward the shape of its captured guides (GuidePull).

    x is updated in place: the strand's root must be pinned (inv_mass 0), since other threads read
    it while they write.

    Launch: one thread per particle of a range of whole strands (dim = particles in the range).
    Inputs:
      inv_mass (float, per particle): 0 marks pinned particles, which are left alone
      particle_strand (int32, per particle): strand of each particle
      strand_start (int32, num_strands + 1): first particle of each strand, then the total count
      pull (GuidePull): the guides and how hard they pull
      clock (float, 1 element, s): device clock
      time_offset (float, s): time of this substep relative to clock[0]
      first (int, index): the range's first particle; thread t works on particle first + t (0 for all of them)
    In/out:
      x (vec3, per particle, m): positions, moved toward the targets
    """
    i = wp.tid() + first
    if inv_mass[i] == 0.0:
        return
    f, f1, t = guide_frames(pull, clock[0] + time_offset)
    strand = particle_strand[i]
    x[i] = guided_position(pull, x[i], x[strand_start[strand]], strand, i, f, f1, t)


@wp.kernel(module=CHILDREN)
def interpolate_children(
    x: wp.array(dtype=wp.vec3),
    parent_rest: wp.array(dtype=wp.vec3),
    strand_start: wp.array(dtype=wp.int32),
    child_rest: wp.array(dtype=wp.vec3),
    child_parents: wp.array(dtype=wp.vec3i),
    child_weights: wp.array(dtype=wp.vec3),
    vertices: int,
    collider_points: wp.array(dtype=wp.vec3),
    collider_indices: wp.array(dtype=wp.int32),
    anchor_face: int,
    rest_frame: wp.mat33,
    rest_center: wp.vec3,
    shape: ColliderShape,
    pinned: int,
    margin: float,
    search: float,
    clearance: wp.array(dtype=float),
    slot_of: wp.array(dtype=wp.int32),
    first: int,
    children: wp.array(dtype=wp.vec3),
):
    """Place the render children: each child's groomed shape carried rigidly with the head (the anchor
    triangle's motion from the groom's pose), plus its parents' displacements from their own shapes
    carried the same way, weighted; then, root to tip, each vertex pushed out of the collider's mesh,
    put back at its groomed distance from the one before (follow the leader, as the strands' length
    pass) and pushed out again. A rigid motion of the head and hair moves the children rigidly, and at the
    groom's pose they are their groomed shapes. Blended displacements alone stretch a child whose
    parents move apart, and over a curved head can carry it inside (a strand over the ear settling
    past one above it): the walk and the push keep it whole and outside.

    A push moves only a point within margin of the mesh or inside it, so none is made where the
    strands' contact bounds show the point farther: a parent particle at least c from the mesh puts a
    point d from it at least c - d away, and the walk's move lowers that bound by its length. The
    children are those of pushing every vertex, bit for bit.

    Launch: one thread per child of a range of children (dim = children in the range).
    Inputs:
      x (vec3, per particle, m): the simulated strands' positions
      parent_rest (vec3, per particle, m): their groomed shapes, in the groom's pose
      strand_start (int32, num_strands + 1): first particle of each simulated strand, then the total
      child_rest (vec3, per child vertex, m): the children's groomed shapes, in the groom's pose
      child_parents (vec3i, per child): the three simulated strands a child follows
      child_weights (vec3, per child): and their weights (summing to 1; 0 for a missing parent)
      vertices (int): vertices of every child and of every simulated strand
      collider_points (vec3, per vertex, m): the collider as posed now
      collider_indices (int32, 3 per triangle): its triangles
      anchor_face (int): the triangle the roots move with (HairModel.anchor_face); below 0 for none
      rest_frame (mat33): skinning.triangle_frame of the anchor triangle in the groom's pose
      rest_center (vec3, m): the anchor triangle's centroid in the groom's pose
      shape (ColliderShape): the collider, its mesh's BVH fitted to the pose
      pinned (int): vertices at the root of every strand that move with the head (kept rigid)
      margin (float, m): distance kept outside the collider
      search (float, m): mesh query radius; deeper penetrations are not seen
      clearance (float, per particle or lane slot, m): lower bounds of the simulated particles'
          distances from this mesh at x (the hair solver's contact bounds against it); empty for none
      slot_of (int32, per particle): each particle's element of clearance; empty where they are the same
      first (int, index): the range's first child; thread t works on child first + t
    Outputs:
      children (vec3, per child vertex, m): the children's positions
    """
    child = wp.tid() + first
    turn = wp.identity(3, dtype=float)
    center = rest_center
    if anchor_face >= 0:
        a = collider_points[collider_indices[3 * anchor_face]]
        b = collider_points[collider_indices[3 * anchor_face + 1]]
        c = collider_points[collider_indices[3 * anchor_face + 2]]
        turn = triangle_frame(a, b, c) * wp.transpose(rest_frame)
        center = (a + b + c) / 3.0
    parents = child_parents[child]
    weights = child_weights[child]
    first = child * vertices
    prev = wp.vec3(0.0)
    for k in range(vertices):
        i = first + k
        p = turn * (child_rest[i] - rest_center) + center
        if k >= pinned:
            for j in range(3):
                q = strand_start[parents[j]] + k
                p += weights[j] * (x[q] - (turn * (parent_rest[q] - rest_center) + center))
            # out of the collider, back to its length from the vertex before, and out again: a vertex
            # blended deep inside comes out beside the one before, not a push's depth off its length
            rest_length = wp.length(child_rest[i] - child_rest[i - 1])
            room = float(NO_BOUND)  # a lower bound of p's distance from the mesh
            if clearance.shape[0] > 0:
                for j in range(3):
                    q = strand_start[parents[j]] + k
                    e = q
                    if slot_of.shape[0] > 0:
                        e = slot_of[q]
                    room = wp.max(room, clearance[e] - wp.length(p - x[q]))
            pushed = room <= margin + CHILD_PUSH_TOLERANCE
            if pushed:
                p = collide_point(p, COLLIDE_MESH, shape, margin, search)
            walked = prev + rest_length * wp.normalize(p - prev)
            if pushed or room - wp.length(walked - p) <= margin + CHILD_PUSH_TOLERANCE:
                walked = collide_point(walked, COLLIDE_MESH, shape, margin, search)
            p = walked
        children[i] = p
        prev = p
