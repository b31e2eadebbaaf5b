"""The built-in body: a closed human-sized mesh, a rigid head for hair, and animations that start at rest."""

import body_motion_reference as reference  # tests/body_motion_reference.py
import numpy as np
import pytest
import trimesh

from sim.body import BodyAnimation, procedural_body
from sim.collider import Collider
from sim.sphere_tree import signed_distance, warp_mesh

PRESETS = ("walk", "arm_raise", "turn", "none")
STRIDE_S = 2.0 / BodyAnimation().cadence_steps_per_s


@pytest.fixture(scope="module")
def body():
    return procedural_body()


@pytest.fixture(scope="module")
def collider(body):
    return Collider("body", body.vertices, body.faces, body.skin_indices, body.skin_weights, body.num_bones,
                    "cpu", sphere_leaves=0)


def posed(collider, anim, times):
    collider.set_poses(anim.bone_matrices(times))
    out = []
    for k in range(len(times)):
        collider.apply_pose(k)
        out.append(collider.posed_points().astype(np.float64))
    return np.stack(out)


def test_body_is_one_closed_outward_surface_of_human_size(body):
    mesh = trimesh.Trimesh(body.vertices, body.faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert len(mesh.split(only_watertight=False)) == 1
    assert 0.05 < mesh.volume < 0.08  # m^3, positive: outward winding
    assert 8_000 <= len(body.vertices) <= 20_000
    lo, hi = body.vertices.min(0), body.vertices.max(0)
    assert 1.65 < hi[1] < 1.75 and abs(lo[1]) < 0.002  # standing on y = 0
    assert abs(lo[0] + hi[0]) < 0.01  # left-right symmetric
    assert body.vertices.dtype == np.float64 and body.faces.dtype == np.int64


def test_body_faces_plus_z_with_left_on_plus_x(body):
    sk = body.skeleton
    head = body.vertices[body.vertices[:, 1] > body.pivot[1] + 0.05]
    assert head[:, 2].max() > -head[:, 2].min()  # the nose points forward
    for side, sign in (("l", 1.0), ("r", -1.0)):
        for joint in ("upper_arm_", "hand_", "thigh_", "foot_"):
            assert sign * sk.rest_positions[sk.index(joint + side), 0] > 0.05


def test_skeleton_has_the_named_joints_in_parent_order(body):
    sk = body.skeleton
    for name in ("pelvis", "spine", "chest", "neck", "head", "shoulder_l", "shoulder_r", "upper_arm_l",
                 "upper_arm_r", "forearm_l", "forearm_r", "hand_l", "hand_r", "thigh_l", "thigh_r", "shin_l",
                 "shin_r", "foot_l", "foot_r"):
        assert name in sk.names
    assert sk.parents[sk.index("pelvis")] == -1
    assert all(p < j for j, p in enumerate(sk.parents) if p >= 0)
    assert body.num_bones == sk.num_joints
    assert np.allclose(body.pivot, sk.rest_positions[sk.index("head")])


def test_a_pose_arms_are_about_42_degrees_from_the_torso(body):
    sk = body.skeleton
    arm = sk.rest_positions[sk.index("forearm_l")] - sk.rest_positions[sk.index("upper_arm_l")]
    angle = np.degrees(np.arctan2(arm[0], -arm[1]))
    assert 40.0 <= angle <= 45.0


def test_skin_weights_are_non_negative_and_sum_to_one(body):
    assert body.skin_weights.shape == body.skin_indices.shape == (len(body.vertices), 4)
    assert body.skin_weights.min() >= 0.0
    assert np.abs(body.skin_weights.sum(1) - 1.0).max() < 1e-12
    assert body.skin_indices.min() >= 0 and body.skin_indices.max() < body.num_bones


def test_scalp_is_on_the_head_and_weighted_only_to_the_head_bone(body):
    sk = body.skeleton
    assert 300 < body.scalp_faces.sum() < len(body.faces) // 4
    scalp_vertices = np.unique(body.faces[body.scalp_faces])
    assert body.vertices[scalp_vertices, 1].min() > sk.rest_positions[sk.index("head"), 1] + 0.05
    assert np.all(body.skin_indices[scalp_vertices, 0] == sk.index("head"))
    assert np.all(body.skin_weights[scalp_vertices, 0] == 1.0)


@pytest.mark.parametrize("name", PRESETS)
def test_every_preset_starts_exactly_at_the_rest_pose(name):
    for anim in (BodyAnimation.preset(name), BodyAnimation.preset(name, in_place=True)):
        M = anim.bone_matrices([0.0])
        assert M.shape == (1, 19, 4, 4) and M.dtype == np.float64
        assert np.abs(M - np.eye(4)).max() <= 1e-12
        assert np.array_equal(M, np.broadcast_to(np.eye(4), M.shape))  # bit for bit


@pytest.mark.parametrize("name", PRESETS)
def test_bone_matrices_are_rigid_transforms(name):
    M = BodyAnimation.preset(name).bone_matrices(np.linspace(0.0, 6.0, 61))
    R = M[..., :3, :3]
    assert np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max() < 1e-12
    assert np.abs(np.linalg.det(R) - 1.0).max() < 1e-12
    assert np.array_equal(M[..., 3, :], np.broadcast_to([0.0, 0.0, 0.0, 1.0], M[..., 3, :].shape))


@pytest.mark.parametrize("name", PRESETS)
def test_bone_matrices_equal_a_float64_numpy_reference(name):
    """The motion kernel (one thread per time) against the same motions evaluated as NumPy arrays
    over all times at once, before and after the ease-in, at negative and late times, and with
    other parameters than the preset's."""
    times = np.concatenate([[0.0, -0.4], np.linspace(0.0, 7.0, 141), [250.0]])
    others = {"step_length_m": 0.8, "stance_fraction": 0.55, "arm_swing_degrees": 25.0, "raise_to_degrees": 120.0,
              "hold_s": 0.2, "turn_degrees": 45.0, "head_lead_s": 0.4, "ease_in_s": 1.1}
    for overrides in ({}, {"in_place": True}, {"ease_in_s": 0.0}, others):
        anim = BodyAnimation.preset(name, **overrides)
        got, want = anim.bone_matrices(times), reference.bone_matrices(anim, times)
        assert got.shape == want.shape == (len(times), 19, 4, 4)
        np.testing.assert_allclose(got[:, :, :3, :3], want[:, :, :3, :3], rtol=0, atol=1e-12)
        np.testing.assert_allclose(got[:, :, :3, 3], want[:, :, :3, 3], rtol=1e-12, atol=1e-12)  # 270 m walked
        if name != "none":
            assert np.abs(want - np.eye(4)).max() > 0.1  # the reference moved: the comparison means something


def test_bone_matrices_of_later_calls_leave_earlier_results_alone():
    anim = BodyAnimation.preset("walk")
    first = anim.bone_matrices([0.5, 0.6])
    kept = first.copy()
    second = anim.bone_matrices([1.5, 1.6])  # the same count of times: the same launch, its buffers reused
    np.testing.assert_array_equal(first, kept)
    assert np.abs(second - first).max() > 0.1


def test_unknown_preset_is_a_key_error():
    with pytest.raises(KeyError):
        BodyAnimation.preset("moonwalk")


def test_head_moves_rigidly_while_walking(body, collider):
    head = np.unique(body.faces[body.scalp_faces])
    times = np.linspace(0.0, 2.0 * STRIDE_S, 9)
    pts = posed(collider, BodyAnimation.preset("walk"), times)[:, head]
    rest = np.linalg.norm(body.vertices[head, None] - body.vertices[None, head], axis=-1)
    for p in pts:
        assert np.abs(np.linalg.norm(p[:, None] - p[None], axis=-1) - rest).max() < 1e-5
    assert np.ptp(pts[:, :, 2].mean(1)) > 1.0  # and it did travel


def test_walk_alternates_the_feet_and_advances_one_step_length_per_step():
    anim = BodyAnimation.preset("walk")
    sk = anim.skeleton or procedural_body().skeleton
    t = np.linspace(2.0 * STRIDE_S, 3.0 * STRIDE_S, 41)  # one full stride after the ease-in
    J = anim.joint_positions(t)
    lead = J[:, sk.index("foot_l"), 2] - J[:, sk.index("foot_r"), 2]  # > 0: left foot ahead
    assert lead.max() > 0.4 and lead.min() < -0.4
    root = J[:, sk.index("pelvis"), 2]
    steps = anim.cadence_steps_per_s * (t[-1] - t[0])
    assert root[-1] - root[0] == pytest.approx(anim.step_length_m * steps, rel=1e-9)
    assert np.all(np.diff(root) > 0.0)
    in_place = BodyAnimation.preset("walk", in_place=True).joint_positions(t)[:, sk.index("pelvis"), 2]
    assert np.abs(in_place).max() < 0.05


def test_walk_flexes_hips_about_25_degrees_and_bends_knees_in_swing():
    anim = BodyAnimation.preset("walk", in_place=True)
    sk = procedural_body().skeleton
    t = np.linspace(2.0 * STRIDE_S, 3.0 * STRIDE_S, 61)
    J = anim.joint_positions(t)
    thigh = J[:, sk.index("shin_l")] - J[:, sk.index("thigh_l")]
    shin = J[:, sk.index("foot_l")] - J[:, sk.index("shin_l")]
    flexion = np.degrees(np.arctan2(thigh[:, 2], -thigh[:, 1]))
    assert 20.0 < flexion.max() < 40.0 and -25.0 < flexion.min() < -5.0
    knee = np.degrees(np.arccos(np.einsum("ij,ij->i", thigh, shin) / np.linalg.norm(thigh, axis=1)
                                / np.linalg.norm(shin, axis=1)))
    assert 45.0 < knee.max() < 70.0


def test_walking_feet_stay_on_the_floor_and_volume_is_kept(body, collider):
    times = np.linspace(2.0 * STRIDE_S, 3.0 * STRIDE_S, 13)
    pts = posed(collider, BodyAnimation.preset("walk"), times)
    assert np.all(np.isfinite(pts))
    rest_volume = trimesh.Trimesh(body.vertices, body.faces, process=False).volume
    for p in pts:
        assert -0.003 < p[:, 1].min() < 0.01  # a foot is always down, neither sunk nor floating
        volume = trimesh.Trimesh(p, body.faces, process=False).volume
        assert abs(volume / rest_volume - 1.0) < 0.1


def test_arm_raise_lifts_the_hands_above_the_head_at_its_peak():
    anim = BodyAnimation.preset("arm_raise")
    sk = procedural_body().skeleton
    peak = anim.raise_s + 0.5 * anim.hold_s
    J = anim.joint_positions([peak])[0]
    for s in ("l", "r"):
        shoulder, elbow, hand = (J[sk.index(n + s)] for n in ("upper_arm_", "forearm_", "hand_"))
        assert hand[1] > shoulder[1] + 0.3 and hand[1] > J[sk.index("head"), 1]
        arm = elbow - shoulder
        assert np.degrees(np.arccos(-arm[1] / np.linalg.norm(arm))) == pytest.approx(anim.raise_to_degrees, abs=2.0)
    back = anim.joint_positions([2.0 * (anim.raise_s + anim.hold_s)])[0]
    assert np.allclose(back, sk.rest_positions, atol=1e-9)


def test_turn_faces_plus_x_at_its_peak_and_comes_back():
    anim = BodyAnimation.preset("turn")
    sk = procedural_body().skeleton
    peak = anim.head_lead_s + anim.turn_s + 0.5 * anim.hold_s
    settled = anim.head_lead_s + 2.0 * anim.turn_s + anim.hold_s + 0.1  # head, chest and pelvis all back
    M = anim.bone_matrices([peak, settled])
    for bone in ("pelvis", "chest", "head", "foot_l"):
        assert np.allclose(M[0, sk.index(bone), :3, 2], [1.0, 0.0, 0.0], atol=1e-6)  # the body's +Z now points +X
    assert np.allclose(M[1], np.eye(4), atol=1e-12)


def test_landmarks_are_ordered_and_shoulders_lie_on_the_surface(body):
    lm = body.landmarks
    heights = [lm[k] for k in ("ankle_y", "knee_y", "crotch_y", "hip_y", "waist_y", "chest_y")]
    assert np.all(np.diff(heights) > 0.05)
    assert lm["chest_y"] < lm["neck_base"][1] < lm["height"]
    assert lm["height"] == pytest.approx(body.vertices[:, 1].max())
    mesh = warp_mesh(body.vertices, body.faces)
    for side, sign in (("l", 1.0), ("r", -1.0)):
        p = np.asarray(lm["shoulder_" + side])
        assert sign * p[0] > 0.08 and 1.35 < p[1] < 1.5
        assert np.allclose(p * [-1.0, 1.0, 1.0], lm["shoulder_" + ("r" if side == "l" else "l")])  # mirror images
        assert abs(signed_distance(p[None], mesh)[0][0]) < 1e-3
        above = p + np.array([[0.0, 0.01, 0.0]])
        assert signed_distance(above, mesh)[0][0] > 0.005  # the top of the shoulder: open sky above it


def test_procedural_body_is_cached_and_hands_out_copies():
    a = procedural_body()
    a.vertices[:] = 0.0
    a.scalp_faces[:] = False
    b = procedural_body()
    assert b.vertices[:, 1].max() > 1.6 and b.scalp_faces.any()
    assert b.skeleton is a.skeleton  # immutable, shared


def test_a_skeleton_without_the_moved_joints_is_refused_and_one_without_others_moves():
    from sim.body import Skeleton, default_skeleton

    sk = default_skeleton()
    keep = [j for j, name in enumerate(sk.names) if not name.startswith(("thigh", "shin", "foot"))]  # no legs
    remap = {old: new for new, old in enumerate(keep)}
    legless = Skeleton(tuple(sk.names[j] for j in keep), np.array([remap.get(sk.parents[j], -1) for j in keep]),
                       sk.rest_positions[keep], sk.tips[keep])
    with pytest.raises(ValueError, match="walk motion needs the skeleton's joints thigh_l"):
        BodyAnimation.preset("walk", skeleton=legless).bone_matrices([0.5])
    for name in ("turn", "arm_raise", "none"):  # these move no leg: the same matrices as the full skeleton's
        full = BodyAnimation.preset(name).bone_matrices([0.9, 2.1])
        np.testing.assert_array_equal(BodyAnimation.preset(name, skeleton=legless).bone_matrices([0.9, 2.1]),
                                      full[:, keep])
