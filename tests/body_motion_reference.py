"""A float64 NumPy reference of warp_kernels.body_motion: the built-in body's motions evaluated as
arrays over all times at once, independently of the kernel's one-thread-per-time code.

It was the product's own implementation until the motion moved into a Warp kernel (a frame's
evaluation cost 2.4 ms of NumPy every eighth frame there, against tens of microseconds now).
"""

import numpy as np

from sim.body import _HEEL_REACH, ARM_ABDUCTION_DEGREES, _unit, default_skeleton
from sim.head import _smoothstep


def _skeleton(anim):
    return anim.skeleton if anim.skeleton is not None else default_skeleton()


def bone_matrices(anim, times):
    """(T, J, 4, 4) skinning matrices of BodyAnimation `anim` at `times`, as the kernel computes them."""
    root, R = local_pose(anim, times)
    return _skinning_matrices(_skeleton(anim), root, R)


def _axis_angle(axis, angle):
    """(T, 3, 3) rotations by angle[t] [rad] about a fixed unit axis (Rodrigues)."""
    x, y, z = _unit(axis)
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)


def _rx(a):
    return _axis_angle((1.0, 0.0, 0.0), a)


def _ry(a):
    return _axis_angle((0.0, 1.0, 0.0), a)


def _rz(a):
    return _axis_angle((0.0, 0.0, 1.0), a)


def _min_jerk(u):
    u = np.clip(u, 0.0, 1.0)
    return u * u * u * (10.0 + u * (-15.0 + 6.0 * u))


def local_pose(anim, times):
    t = np.atleast_1d(np.asarray(times, np.float64))
    sk = _skeleton(anim)
    R = np.tile(np.eye(3), (len(t), sk.num_joints, 1, 1))
    root = np.zeros((len(t), 3))
    ease = _smoothstep(t / anim.ease_in_s) if anim.ease_in_s > 0 else np.ones_like(t)
    if anim.motion == "walk":
        _walk(anim, t, ease, R, root)
    elif anim.motion == "arm_raise":
        _arm_raise(anim, t, ease, R)
    elif anim.motion == "turn":
        _turn(anim, t, R)
    return root, R


def _arm_raise(anim, t, ease, R):
    sk = _skeleton(anim)
    cycle = 2.0 * (anim.raise_s + anim.hold_s)
    u = np.mod(t, cycle)
    up = _smoothstep(u / anim.raise_s) - _smoothstep((u - anim.raise_s - anim.hold_s) / anim.raise_s)
    total = np.radians(anim.raise_to_degrees - ARM_ABDUCTION_DEGREES) * up * ease
    for s, sx in (("l", 1.0), ("r", -1.0)):
        R[:, sk.index(f"shoulder_{s}")] = _rz(sx * anim.clavicle_share * total)
        R[:, sk.index(f"upper_arm_{s}")] = _rz(sx * (1.0 - anim.clavicle_share) * total)


def _turn(anim, t, R):
    sk = _skeleton(anim)
    delay = anim.head_lead_s  # the body holds still while the head starts the turn

    def yaw(tt):
        cycle = 2.0 * (anim.turn_s + anim.hold_s)
        u = np.mod(np.maximum(tt - delay, 0.0), cycle)
        a = _smoothstep(u / anim.turn_s) - _smoothstep((u - anim.turn_s - anim.hold_s) / anim.turn_s)
        return np.radians(anim.turn_degrees) * a * (tt > delay)

    pelvis, chest, head = yaw(t), yaw(t + 0.5 * anim.head_lead_s), yaw(t + anim.head_lead_s)
    R[:, sk.index("pelvis")] = _ry(pelvis)
    R[:, sk.index("spine")] = _ry(0.5 * (chest - pelvis))
    R[:, sk.index("chest")] = _ry(0.5 * (chest - pelvis))
    R[:, sk.index("neck")] = _ry(0.5 * (head - chest))
    R[:, sk.index("head")] = _ry(0.5 * (head - chest))


def _walk(anim, t, ease, R, root):
    sk = _skeleton(anim)
    P = sk.rest_positions
    stride_hz = 0.5 * anim.cadence_steps_per_s
    speed = anim.step_length_m * anim.cadence_steps_per_s  # [m/s]
    phase_l = np.mod(stride_hz * t, 1.0)  # 0 = left heel strike
    cyc = 2.0 * np.pi * phase_l

    # root: forward distance is the integral of speed * ease, in closed form
    if not anim.in_place:
        te = anim.ease_in_s
        u = np.clip(t / te, 0.0, 1.0) if te > 0 else np.ones_like(t)
        root[:, 2] = speed * (te * (u ** 3 - 0.5 * u ** 4) + np.maximum(t - te, 0.0))
    midstance = 0.5 * anim.stance_fraction
    root[:, 1] = ease * (-anim.pelvis_drop_m + anim.pelvis_bob_m * np.cos(4.0 * np.pi * (phase_l - midstance)))
    root[:, 0] = ease * anim.pelvis_sway_m * np.sin(cyc)

    # the pelvis turns with the swinging leg and drops on its side; the chest turns against it
    yaw = -np.radians(anim.pelvis_yaw_degrees) * np.cos(cyc) * ease
    roll = np.radians(anim.pelvis_roll_degrees) * np.sin(cyc) * ease
    R_pelvis = _ry(yaw) @ _rz(roll)
    R[:, sk.index("pelvis")] = R_pelvis
    chest_yaw = np.radians(anim.torso_twist_degrees) * np.cos(cyc) * ease  # in the world
    R[:, sk.index("spine")] = _ry(0.4 * (chest_yaw - yaw)) @ _rz(-0.6 * roll)
    R[:, sk.index("chest")] = _ry(0.6 * (chest_yaw - yaw)) @ _rz(-0.4 * roll)
    # the head keeps looking ahead
    R[:, sk.index("neck")] = _ry(-0.5 * chest_yaw)
    R[:, sk.index("head")] = _ry(-0.5 * chest_yaw)

    # arms: lowered from the A-pose, swinging against the legs
    swing = np.radians(anim.arm_swing_degrees) * np.cos(cyc) * ease
    back = np.radians(anim.arm_swing_back_degrees) * ease
    lower = np.radians(anim.arm_lower_degrees) * ease
    bend = np.radians(anim.elbow_bend_degrees) * ease
    for s, sx, sgn in (("l", 1.0, -1.0), ("r", -1.0, 1.0)):
        i_up, i_fore = sk.index(f"upper_arm_{s}"), sk.index(f"forearm_{s}")
        arm = P[i_fore] - P[i_up]
        hinge = _unit(np.cross(arm, (0.0, 0.0, 1.0)))  # positive angle swings the arm forward
        R[:, i_up] = _rz(-sx * lower) @ _axis_angle(hinge, sgn * swing - back)
        fore_hinge = _unit(np.cross(P[sk.index(f"hand_{s}")] - P[i_fore], (0.0, 0.0, 1.0)))
        R[:, i_fore] = _axis_angle(fore_hinge, bend * (1.0 + 0.5 * sgn * np.cos(cyc)))

    # legs: two-bone IK to ankle targets given in the walking (root) frame; the thigh's local
    # rotation cancels the pelvis's, so each leg swings in a plane fixed in the world
    pelvis_shift = root + P[0] - np.einsum("tab,b->ta", R_pelvis, P[0])  # exactly 0 at rest
    for s, offset in (("l", 0.0), ("r", 0.5)):
        phase = np.mod(phase_l + offset, 1.0)
        i_hip, i_knee, i_ankle = (sk.index(n + s) for n in ("thigh_", "shin_", "foot_"))
        ankle_rel, pitch = _foot_path(anim, phase)
        target = P[i_ankle] + ease[:, None] * ankle_rel
        target[:, 2] += root[:, 2]
        hip = np.einsum("tab,b->ta", R_pelvis, P[i_hip]) + pelvis_shift
        a_hip, a_knee, a_abd = _leg_ik(P[i_hip], P[i_knee], P[i_ankle], hip, target)
        R_leg = _rz(a_abd) @ _rx(a_hip)
        R[:, i_hip] = np.swapaxes(R_pelvis, 1, 2) @ R_leg
        R[:, i_knee] = _rx(a_knee)
        R[:, i_ankle] = _rx(ease * pitch - a_hip - a_knee)


def _foot_path(anim, phase):
    """Ankle offset from its rest position (T, 3) and world foot pitch [rad], before easing.

    Stance: the ankle moves back under the hip at walking speed (less a little heel-to-toe roll)
    and the heel rises before toe-off. Swing: a minimum-jerk path forward, lifted by the clearance.
    """
    beta = anim.stance_fraction
    reach = beta * anim.step_length_m - 0.03  # half the ankle's travel relative to the hip [m]
    rise = np.radians(anim.heel_rise_degrees)
    off = np.zeros((len(phase), 3))
    stance = phase < beta
    u = np.where(stance, phase / beta, (phase - beta) / (1.0 - beta))
    late = _smoothstep((u - 0.6) / 0.4)  # heel rise over the last 40% of stance
    heel_up = np.where(stance, rise * late, rise * (1.0 - _smoothstep(u / 0.5)))
    strike = np.radians(anim.toe_up_degrees)
    toe_up = np.where(stance, -strike * (1.0 - _smoothstep(u / 0.15)), -strike * _smoothstep((u - 0.6) / 0.4))
    pitch = heel_up + toe_up
    s = _min_jerk(u)
    off[:, 2] = np.where(stance, reach * (1.0 - 2.0 * u), reach * (2.0 * s - 1.0))
    # a pitched foot pivots on its toe (heel up) or heel (toe up), which lifts the ankle
    sk = _skeleton(anim)
    i = sk.index("foot_l")
    height = sk.rest_positions[i, 1]
    toe, heel = sk.tips[i, 2] - sk.rest_positions[i, 2], _HEEL_REACH
    lift = np.where(pitch > 0, toe, heel) * np.sin(np.abs(pitch)) - height * (1.0 - np.cos(pitch))
    off[:, 1] = lift + np.where(stance, 0.0, anim.foot_clearance_m * np.sin(np.pi * u) ** 2)
    return off, pitch


def _leg_ik(hip_rest, knee_rest, ankle_rest, hip, target):
    """Hip flexion, knee flexion (Rx angles from rest) and hip abduction (Rz) putting the ankle on target.

    Solved in the sagittal (y, z) plane with the knee bending forward; a target out of reach
    straightens the leg. Angles are differences from the same solve for the rest pose, so the rest
    target gives exactly zero.
    """
    thigh, shin = knee_rest - hip_rest, ankle_rest - knee_rest
    l1, l2 = np.hypot(thigh[1], thigh[2]), np.hypot(shin[1], shin[2])

    def solve(d):  # world thigh and shin angles from straight down, positive backward (as Rx)
        dist = np.clip(np.hypot(d[:, 1], d[:, 2]), abs(l1 - l2) + 1e-6, (l1 + l2) * (1.0 - 1e-9))
        to_target = np.arctan2(-d[:, 2], -d[:, 1])
        at_hip = np.arccos(np.clip((l1 * l1 + dist * dist - l2 * l2) / (2.0 * l1 * dist), -1.0, 1.0))
        at_ankle = np.arccos(np.clip((l2 * l2 + dist * dist - l1 * l1) / (2.0 * l2 * dist), -1.0, 1.0))
        return to_target - at_hip, to_target + at_ankle  # knee forward of the hip-ankle line

    d = target - hip
    thigh_0, shin_0 = solve((ankle_rest - hip_rest)[None])
    thigh_w, shin_w = solve(d)
    a_hip = thigh_w - thigh_0
    a_knee = (shin_w - shin_0) - a_hip
    a_abd = np.arcsin(np.clip((d[:, 0] - (ankle_rest[0] - hip_rest[0])) / (l1 + l2), -1.0, 1.0))
    return a_hip, a_knee, a_abd


def _skinning_matrices(sk, root, R):
    """M_j = M_parent @ T(p_j) R_j T(-p_j), M_root = T(root) T(p_0) R_0 T(-p_0): identity when R = I, root = 0."""
    n, J = R.shape[:2]
    M = np.zeros((n, J, 4, 4))
    M[:, :, 3, 3] = 1.0
    p = sk.rest_positions
    for j in range(J):
        local = np.zeros((n, 4, 4))
        local[:, :3, :3] = R[:, j]
        local[:, :3, 3] = p[j] - np.einsum("tab,b->ta", R[:, j], p[j])
        local[:, 3, 3] = 1.0
        if sk.parents[j] < 0:
            local[:, :3, 3] += root
            M[:, j] = local
        else:
            M[:, j] = M[:, sk.parents[j]] @ local
    return M
