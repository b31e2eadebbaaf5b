"""Procedural body motion: the built-in character's walk, arm raise and turn as bone matrices.

One thread evaluates one time: the local joint rotations of the chosen motion, then forward
kinematics down the joint hierarchy. A frame asks for a dozen times (every solver's substeps), so
the whole evaluation is one short launch. Float64 throughout: the matrices are the motion's exact
answer, rigid to 1e-12, and at t = 0 the rest pose bit for bit (every angle is scaled by an ease-in
that is exactly 0 there), so a garment fitted at rest starts free of penetration.
"""

import math

import warp as wp

from ._options import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)

MOTION_NONE = wp.constant(0)
MOTION_WALK = wp.constant(1)
MOTION_ARM_RAISE = wp.constant(2)
MOTION_TURN = wp.constant(3)

F64 = wp.float64
PI = wp.constant(wp.float64(math.pi))  # wp.pi is a float32
TWO_PI = wp.constant(wp.float64(2.0 * math.pi))
FOUR_PI = wp.constant(wp.float64(4.0 * math.pi))


@wp.struct
class BodyMotion:
    """A motion preset and the skeleton it moves (sim.body.BodyAnimation fills one).

    Angles are in radians, converted on the host. The skeleton's joint frames are world aligned at
    rest, so the bind pose of every joint is a translation.

    Fields:
      motion (int): MOTION_NONE, MOTION_WALK, MOTION_ARM_RAISE or MOTION_TURN
      ease_in_s (float64, s): the ease-in's duration; every motion but the turn is scaled by a
          smoothstep from 0 at t = 0 to 1 at ease_in_s (0: no ease-in)
      in_place (int, flag): walk: non-zero keeps the root at z = 0 (a treadmill walk)
      stride_hz (float64, 1/s): walk: strides (two steps) per second
      speed (float64, m/s): walk: forward speed after the ease-in
      stance_fraction (float64, fraction): walk: part of each leg's cycle with the foot down
      reach (float64, m): walk: half the ankle's travel relative to the hip
      foot_clearance (float64, m): walk: ankle lift at mid-swing
      heel_rise (float64, rad): walk: foot pitch at toe-off
      toe_up (float64, rad): walk: foot pitch at heel strike
      toe (float64, m): walk: forward distance from the ankle to the toe the foot pivots on
      heel (float64, m): walk: distance from the ankle back to the heel the foot pivots on
      ankle_height (float64, m): walk: the ankle's rest height above the floor
      pelvis_drop (float64, m): walk: mean lowering of the pelvis
      pelvis_bob (float64, m): walk: vertical oscillation, two per stride
      pelvis_sway (float64, m): walk: side shift over the stance foot
      pelvis_yaw (float64, rad): walk: pelvis turn amplitude
      pelvis_roll (float64, rad): walk: swing-side hip drop
      torso_twist (float64, rad): walk: chest counter-rotation
      arm_swing (float64, rad): walk: shoulder flexion amplitude
      arm_swing_back (float64, rad): walk: the swing's centre behind the body
      arm_lower (float64, rad): walk: arms brought down from the rest pose
      elbow_bend (float64, rad): walk: mean elbow flexion
      arm_hinge_l (vec3d): walk: unit axis the left upper arm swings about
      arm_hinge_r (vec3d): walk: and the right
      fore_hinge_l (vec3d): walk: unit axis the left elbow bends about
      fore_hinge_r (vec3d): walk: and the right
      raise_angle (float64, rad): arm raise: the upper arms' turn at the top, clavicles included
      raise_s (float64, s): arm raise and turn: duration of each way up (or round)
      hold_s (float64, s): arm raise and turn: hold at the top and at rest
      clavicle_share (float64, fraction): arm raise: part of the turn taken by the clavicles
      turn_angle (float64, rad): turn: yaw at the top
      turn_s (float64, s): turn: duration of each way round
      head_lead_s (float64, s): turn: how far the head leads the pelvis (the chest half that)
      rest (vec3d, per joint, m): world rest positions; parents precede children
      parents (int32, per joint): parent joint, -1 for the root
      pelvis (int, index): the named joints' indices in rest, for the presets
      spine (int, index): joint index
      chest (int, index): joint index
      neck (int, index): joint index
      head (int, index): joint index
      shoulder_l (int, index): joint index (clavicle)
      shoulder_r (int, index): joint index
      upper_arm_l (int, index): joint index
      upper_arm_r (int, index): joint index
      forearm_l (int, index): joint index
      forearm_r (int, index): joint index
      thigh_l (int, index): joint index
      thigh_r (int, index): joint index
      shin_l (int, index): joint index
      shin_r (int, index): joint index
      foot_l (int, index): joint index
      foot_r (int, index): joint index
    """

    motion: int
    ease_in_s: wp.float64
    in_place: int
    stride_hz: wp.float64
    speed: wp.float64
    stance_fraction: wp.float64
    reach: wp.float64
    foot_clearance: wp.float64
    heel_rise: wp.float64
    toe_up: wp.float64
    toe: wp.float64
    heel: wp.float64
    ankle_height: wp.float64
    pelvis_drop: wp.float64
    pelvis_bob: wp.float64
    pelvis_sway: wp.float64
    pelvis_yaw: wp.float64
    pelvis_roll: wp.float64
    torso_twist: wp.float64
    arm_swing: wp.float64
    arm_swing_back: wp.float64
    arm_lower: wp.float64
    elbow_bend: wp.float64
    arm_hinge_l: wp.vec3d
    arm_hinge_r: wp.vec3d
    fore_hinge_l: wp.vec3d
    fore_hinge_r: wp.vec3d
    raise_angle: wp.float64
    raise_s: wp.float64
    hold_s: wp.float64
    clavicle_share: wp.float64
    turn_angle: wp.float64
    turn_s: wp.float64
    head_lead_s: wp.float64
    rest: wp.array(dtype=wp.vec3d)
    parents: wp.array(dtype=wp.int32)
    pelvis: int
    spine: int
    chest: int
    neck: int
    head: int
    shoulder_l: int
    shoulder_r: int
    upper_arm_l: int
    upper_arm_r: int
    forearm_l: int
    forearm_r: int
    thigh_l: int
    thigh_r: int
    shin_l: int
    shin_r: int
    foot_l: int
    foot_r: int


@wp.func
def smoothstep(u: wp.float64):
    """3u^2 - 2u^3 of u clamped to [0, 1].

    Inputs:
      u (float64): the argument
    Returns:
      float64: 0 below 0, 1 above 1, smooth between
    """
    u = wp.clamp(u, F64(0.0), F64(1.0))
    return u * u * (F64(3.0) - F64(2.0) * u)


@wp.func
def min_jerk(u: wp.float64):
    """The minimum-jerk profile 10u^3 - 15u^4 + 6u^5 of u clamped to [0, 1].

    Inputs:
      u (float64): the argument
    Returns:
      float64: 0 below 0, 1 above 1, with zero velocity and acceleration at both ends
    """
    u = wp.clamp(u, F64(0.0), F64(1.0))
    return u * u * u * (F64(10.0) + u * (F64(-15.0) + F64(6.0) * u))


@wp.func
def floor_mod(x: wp.float64, period: wp.float64):
    """x modulo a positive period, in [0, period) for negative x too (as NumPy's mod).

    Inputs:
      x (float64): the value
      period (float64): the period, > 0
    Returns:
      float64: the remainder
    """
    r = wp.mod(x, period)
    if r < F64(0.0):
        r += period
    return r


@wp.func
def axis_angle(axis: wp.vec3d, angle: wp.float64):
    """The rotation by angle about a unit axis (Rodrigues).

    Inputs:
      axis (vec3d): unit axis
      angle (float64, rad): right-handed angle
    Returns:
      mat33d: the rotation
    """
    K = wp.mat33d(F64(0.0), -axis[2], axis[1], axis[2], F64(0.0), -axis[0], -axis[1], axis[0], F64(0.0))
    return wp.identity(3, dtype=wp.float64) + wp.sin(angle) * K + (F64(1.0) - wp.cos(angle)) * (K * K)


@wp.func
def rotation_x(angle: wp.float64):
    """axis_angle about +x.

    Inputs:
      angle (float64, rad): right-handed angle
    Returns:
      mat33d: the rotation
    """
    return axis_angle(wp.vec3d(F64(1.0), F64(0.0), F64(0.0)), angle)


@wp.func
def rotation_y(angle: wp.float64):
    """axis_angle about +y.

    Inputs:
      angle (float64, rad): right-handed angle
    Returns:
      mat33d: the rotation
    """
    return axis_angle(wp.vec3d(F64(0.0), F64(1.0), F64(0.0)), angle)


@wp.func
def rotation_z(angle: wp.float64):
    """axis_angle about +z.

    Inputs:
      angle (float64, rad): right-handed angle
    Returns:
      mat33d: the rotation
    """
    return axis_angle(wp.vec3d(F64(0.0), F64(0.0), F64(1.0)), angle)


@wp.func
def foot_path(m: BodyMotion, phase: wp.float64):
    """Where the walk puts an ankle at a phase of its leg's cycle, relative to its rest position and
    before the ease-in, and the foot's pitch.

    Stance: the ankle moves back under the hip at walking speed and the heel rises before toe-off.
    Swing: a minimum-jerk path forward, lifted by the clearance. A pitched foot pivots on its toe
    (heel up) or heel (toe up), which lifts the ankle.

    Inputs:
      m (BodyMotion): the walk
      phase (float64, fraction): 0 at heel strike, the stance until stance_fraction, then the swing
    Returns:
      vec3d (m): the ankle's offset
      float64 (rad): the foot's world pitch, positive heel up
    """
    beta = m.stance_fraction
    stance = phase < beta
    u = (phase - beta) / (F64(1.0) - beta)
    heel_up = m.heel_rise * (F64(1.0) - smoothstep(u / F64(0.5)))
    toe_up = -m.toe_up * smoothstep((u - F64(0.6)) / F64(0.4))
    z = m.reach * (F64(2.0) * min_jerk(u) - F64(1.0))
    arc = wp.sin(PI * u)
    lift = m.foot_clearance * (arc * arc)
    if stance:
        u = phase / beta
        heel_up = m.heel_rise * smoothstep((u - F64(0.6)) / F64(0.4))  # over the last 40% of stance
        toe_up = -m.toe_up * (F64(1.0) - smoothstep(u / F64(0.15)))
        z = m.reach * (F64(1.0) - F64(2.0) * u)
        lift = F64(0.0)
    pitch = heel_up + toe_up
    pivot = m.heel
    if pitch > F64(0.0):
        pivot = m.toe
    y = pivot * wp.sin(wp.abs(pitch)) - m.ankle_height * (F64(1.0) - wp.cos(pitch)) + lift
    return wp.vec3d(F64(0.0), y, z), pitch


@wp.func
def leg_plane_angles(d: wp.vec3d, l1: wp.float64, l2: wp.float64):
    """World thigh and shin angles (about x, from straight down, positive backward) of a two-bone leg
    whose ankle lies at d from the hip in the sagittal plane, the knee forward of the hip-ankle line.
    A target out of reach straightens the leg.

    Inputs:
      d (vec3d, m): ankle minus hip; its x is ignored
      l1 (float64, m): the thigh's length in the plane
      l2 (float64, m): the shin's
    Returns:
      float64 (rad): the thigh's angle
      float64 (rad): the shin's angle
    """
    dist = wp.clamp(wp.sqrt(d[1] * d[1] + d[2] * d[2]), wp.abs(l1 - l2) + F64(1.0e-6),
                    (l1 + l2) * (F64(1.0) - F64(1.0e-9)))
    to_target = wp.atan2(-d[2], -d[1])
    at_hip = wp.acos(wp.clamp((l1 * l1 + dist * dist - l2 * l2) / (F64(2.0) * l1 * dist), F64(-1.0), F64(1.0)))
    at_ankle = wp.acos(wp.clamp((l2 * l2 + dist * dist - l1 * l1) / (F64(2.0) * l2 * dist), F64(-1.0), F64(1.0)))
    return to_target - at_hip, to_target + at_ankle


@wp.func
def leg_ik(hip_rest: wp.vec3d, knee_rest: wp.vec3d, ankle_rest: wp.vec3d, hip: wp.vec3d, target: wp.vec3d):
    """Hip flexion, knee flexion (about x, from rest) and hip abduction (about z) that put the ankle on
    target, solved in the sagittal plane. Angles are differences from the same solve for the rest
    pose, so the rest target gives exactly zero.

    Inputs:
      hip_rest (vec3d, m): the hip joint at rest
      knee_rest (vec3d, m): the knee joint at rest
      ankle_rest (vec3d, m): the ankle joint at rest
      hip (vec3d, m): the posed hip
      target (vec3d, m): where the ankle should go
    Returns:
      float64 (rad): hip flexion
      float64 (rad): knee flexion
      float64 (rad): hip abduction
    """
    thigh = knee_rest - hip_rest
    shin = ankle_rest - knee_rest
    l1 = wp.sqrt(thigh[1] * thigh[1] + thigh[2] * thigh[2])
    l2 = wp.sqrt(shin[1] * shin[1] + shin[2] * shin[2])
    thigh_0, shin_0 = leg_plane_angles(ankle_rest - hip_rest, l1, l2)
    d = target - hip
    thigh_w, shin_w = leg_plane_angles(d, l1, l2)
    a_hip = thigh_w - thigh_0
    a_knee = (shin_w - shin_0) - a_hip
    a_abd = wp.asin(wp.clamp((d[0] - (ankle_rest[0] - hip_rest[0])) / (l1 + l2), F64(-1.0), F64(1.0)))
    return a_hip, a_knee, a_abd


@wp.func
def walk_leg(m: BodyMotion, phase: wp.float64, ease: wp.float64, root: wp.vec3d, pelvis: wp.mat33d,
             pelvis_shift: wp.vec3d, hip: int, knee: int, ankle: int, rotations: wp.array(dtype=wp.mat33d),
             first: int):
    """One leg of the walk: two-bone IK to the foot path's ankle target, given in the walking (root)
    frame. The thigh's local rotation cancels the pelvis's, so the leg swings in a plane fixed in
    the world.

    Inputs:
      m (BodyMotion): the walk
      phase (float64, fraction): the leg's phase (foot_path)
      ease (float64, fraction): the ease-in's value
      root (vec3d, m): the root's offset
      pelvis (mat33d): the pelvis's rotation
      pelvis_shift (vec3d, m): where the pelvis's rotation about the root joint moves its children
      hip (int, index): the thigh joint
      knee (int, index): the shin joint
      ankle (int, index): the foot joint
      first (int, index): the time's first element of rotations
    Outputs:
      rotations (mat33d, per time and joint): the leg's three local rotations written
    """
    ankle_rel, pitch = foot_path(m, phase)
    target = m.rest[ankle] + ease * ankle_rel
    target = wp.vec3d(target[0], target[1], target[2] + root[2])
    at = pelvis * m.rest[hip] + pelvis_shift
    a_hip, a_knee, a_abd = leg_ik(m.rest[hip], m.rest[knee], m.rest[ankle], at, target)
    rotations[first + hip] = wp.transpose(pelvis) * (rotation_z(a_abd) * rotation_x(a_hip))
    rotations[first + knee] = rotation_x(a_knee)
    rotations[first + ankle] = rotation_x(ease * pitch - a_hip - a_knee)


@wp.func
def walk_pose(m: BodyMotion, t: wp.float64, ease: wp.float64, rotations: wp.array(dtype=wp.mat33d), first: int):
    """The walk at time t: the pelvis bobs, sways, turns with the swinging leg and drops on its side;
    the chest turns against it and the head keeps looking ahead; the arms, lowered from the rest
    pose, swing against the legs; the feet follow planted-stance and swing paths (walk_leg).

    Inputs:
      m (BodyMotion): the walk
      t (float64, s): the time
      ease (float64, fraction): the ease-in's value at t
      first (int, index): the time's first element of rotations
    Outputs:
      rotations (mat33d, per time and joint): the walk's local rotations written
    Returns:
      vec3d (m): the root's offset
    """
    phase_l = floor_mod(m.stride_hz * t, F64(1.0))  # 0 at the left heel strike
    cyc = TWO_PI * phase_l
    forward = F64(0.0)
    if m.in_place == 0:
        # the integral of speed * ease, in closed form
        te = m.ease_in_s
        u = F64(1.0)
        if te > F64(0.0):
            u = wp.clamp(t / te, F64(0.0), F64(1.0))
        forward = m.speed * (te * (u * u * u - F64(0.5) * u * u * u * u) + wp.max(t - te, F64(0.0)))
    midstance = F64(0.5) * m.stance_fraction
    root = wp.vec3d(ease * m.pelvis_sway * wp.sin(cyc),
                    ease * (-m.pelvis_drop + m.pelvis_bob * wp.cos(FOUR_PI * (phase_l - midstance))),
                    forward)
    yaw = -m.pelvis_yaw * wp.cos(cyc) * ease
    roll = m.pelvis_roll * wp.sin(cyc) * ease
    pelvis = rotation_y(yaw) * rotation_z(roll)
    rotations[first + m.pelvis] = pelvis
    chest_yaw = m.torso_twist * wp.cos(cyc) * ease  # in the world
    rotations[first + m.spine] = rotation_y(F64(0.4) * (chest_yaw - yaw)) * rotation_z(F64(-0.6) * roll)
    rotations[first + m.chest] = rotation_y(F64(0.6) * (chest_yaw - yaw)) * rotation_z(F64(-0.4) * roll)
    rotations[first + m.neck] = rotation_y(F64(-0.5) * chest_yaw)
    rotations[first + m.head] = rotation_y(F64(-0.5) * chest_yaw)

    swing = m.arm_swing * wp.cos(cyc) * ease
    back = m.arm_swing_back * ease
    lower = m.arm_lower * ease
    bend = m.elbow_bend * ease
    rotations[first + m.upper_arm_l] = rotation_z(-lower) * axis_angle(m.arm_hinge_l, -swing - back)
    rotations[first + m.forearm_l] = axis_angle(m.fore_hinge_l, bend * (F64(1.0) - F64(0.5) * wp.cos(cyc)))
    rotations[first + m.upper_arm_r] = rotation_z(lower) * axis_angle(m.arm_hinge_r, swing - back)
    rotations[first + m.forearm_r] = axis_angle(m.fore_hinge_r, bend * (F64(1.0) + F64(0.5) * wp.cos(cyc)))

    pelvis_shift = root + m.rest[0] - pelvis * m.rest[0]  # exactly 0 at rest
    walk_leg(m, phase_l, ease, root, pelvis, pelvis_shift, m.thigh_l, m.shin_l, m.foot_l, rotations, first)
    walk_leg(m, floor_mod(phase_l + F64(0.5), F64(1.0)), ease, root, pelvis, pelvis_shift, m.thigh_r, m.shin_r,
             m.foot_r, rotations, first)
    return root


@wp.func
def arm_raise_pose(m: BodyMotion, t: wp.float64, ease: wp.float64, rotations: wp.array(dtype=wp.mat33d),
                   first: int):
    """The arm raise at time t: from the rest pose up and back, repeating, the clavicles taking their
    share of the turn.

    Inputs:
      m (BodyMotion): the arm raise
      t (float64, s): the time
      ease (float64, fraction): the ease-in's value at t
      first (int, index): the time's first element of rotations
    Outputs:
      rotations (mat33d, per time and joint): the shoulders' and upper arms' local rotations written
    """
    u = floor_mod(t, F64(2.0) * (m.raise_s + m.hold_s))
    up = smoothstep(u / m.raise_s) - smoothstep((u - m.raise_s - m.hold_s) / m.raise_s)
    total = m.raise_angle * up * ease
    rotations[first + m.shoulder_l] = rotation_z(m.clavicle_share * total)
    rotations[first + m.upper_arm_l] = rotation_z((F64(1.0) - m.clavicle_share) * total)
    rotations[first + m.shoulder_r] = rotation_z(-m.clavicle_share * total)
    rotations[first + m.upper_arm_r] = rotation_z(-(F64(1.0) - m.clavicle_share) * total)


@wp.func
def turn_yaw(m: BodyMotion, t: wp.float64):
    """The turn's yaw of a body part at time t: round and back, repeating, after head_lead_s at rest.

    Inputs:
      m (BodyMotion): the turn
      t (float64, s): the part's time (the head's and chest's lead added)
    Returns:
      float64 (rad): the yaw
    """
    u = floor_mod(wp.max(t - m.head_lead_s, F64(0.0)), F64(2.0) * (m.turn_s + m.hold_s))
    a = smoothstep(u / m.turn_s) - smoothstep((u - m.turn_s - m.hold_s) / m.turn_s)
    if t > m.head_lead_s:
        return m.turn_angle * a
    return F64(0.0)


@wp.func
def turn_pose(m: BodyMotion, t: wp.float64, rotations: wp.array(dtype=wp.mat33d), first: int):
    """The turn at time t: yaw about the vertical through the pelvis, the head and chest leading.

    Inputs:
      m (BodyMotion): the turn
      t (float64, s): the time
      first (int, index): the time's first element of rotations
    Outputs:
      rotations (mat33d, per time and joint): the spine's local rotations written
    """
    pelvis = turn_yaw(m, t)
    chest = turn_yaw(m, t + F64(0.5) * m.head_lead_s)
    head = turn_yaw(m, t + m.head_lead_s)
    rotations[first + m.pelvis] = rotation_y(pelvis)
    rotations[first + m.spine] = rotation_y(F64(0.5) * (chest - pelvis))
    rotations[first + m.chest] = rotation_y(F64(0.5) * (chest - pelvis))
    rotations[first + m.neck] = rotation_y(F64(0.5) * (head - chest))
    rotations[first + m.head] = rotation_y(F64(0.5) * (head - chest))


@wp.kernel
def body_bone_matrices(times: wp.array(dtype=wp.float64), m: BodyMotion, rotations: wp.array(dtype=wp.mat33d),
                       bones: wp.array(dtype=wp.mat44d)):
    """The motion's skinning matrices (world pose times inverse bind) at each time: the local joint
    rotations, each about its rest joint, composed down the hierarchy. M_root = T(root) T(p) R T(-p)
    and M_j = M_parent T(p_j) R_j T(-p_j): the identity wherever R = I and the root is still.

    Launch: one thread per time (dim = len(times)).
    Inputs:
      times (float64, per time, s): the times
      m (BodyMotion): the motion and its skeleton
    Outputs:
      rotations (mat33d, per time and joint): scratch, the local rotations
      bones (mat44d, per time and joint, m): skinning matrices for column vectors; the matrices of
          time k start at k * num_joints
    """
    k = wp.tid()
    t = times[k]
    joints = m.rest.shape[0]
    first = k * joints
    for j in range(joints):
        rotations[first + j] = wp.identity(3, dtype=wp.float64)
    ease = F64(1.0)
    if m.ease_in_s > F64(0.0):
        ease = smoothstep(t / m.ease_in_s)
    root = wp.vec3d(F64(0.0))
    if m.motion == MOTION_WALK:
        root = walk_pose(m, t, ease, rotations, first)
    elif m.motion == MOTION_ARM_RAISE:
        arm_raise_pose(m, t, ease, rotations, first)
    elif m.motion == MOTION_TURN:
        turn_pose(m, t, rotations, first)
    for j in range(joints):
        R = rotations[first + j]
        p = m.rest[j]
        offset = p - R * p
        parent = m.parents[j]
        if parent < 0:
            offset = offset + root
        local = wp.mat44d(R[0, 0], R[0, 1], R[0, 2], offset[0],
                          R[1, 0], R[1, 1], R[1, 2], offset[1],
                          R[2, 0], R[2, 1], R[2, 2], offset[2],
                          F64(0.0), F64(0.0), F64(0.0), F64(1.0))
        if parent >= 0:
            local = bones[first + parent] * local
        bones[first + j] = local
