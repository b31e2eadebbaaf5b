"""The face rig: action units, mouth parameters, emotions, the Warp kernels against NumPy, the posed
face on a moving head, and the UsdSkel blend-shape export against the rig."""

import numpy as np
import pytest

from sim.errors import InputError
from sim.face import (ACTION_UNITS, EMOTIONS, FEATURE_POINTS, ExpressionKey, FaceAnimation, FaceRig,
                      builtin_face, feature_frame, interpolate_shape)
from sim.rigid import rigid_fit
from sim.mouth import MOUTH_PARAMETERS, VOWEL_SHAPES, VOWELS, mouth_from_weights, nearest_vowel


@pytest.fixture(scope="module")
def rig():
    from sim.scene import quiet_warp

    quiet_warp()
    return FaceRig(builtin_face(resolution=1), "cpu")


def _expected_feature_moves(rig, definition):
    """Feature name -> displacement [m] from the authored (outward, up, forward) mm in its surface frame."""
    out = {}
    for name, vec in definition.vectors.items():
        names = [name] if name in rig.mesh.features else [name + "_l", name + "_r"]
        for n in names:
            out[n] = feature_frame(rig.mesh, n) @ (1e-3 * np.asarray(vec))
    return out


def test_feature_frames_follow_the_surface(rig):
    for name in ("upper_lip_top", "chin", "mouth_corner_l", "mouth_corner_r", "brow_mid_l", "ear_r"):
        F = feature_frame(rig.mesh, name)
        np.testing.assert_allclose(F.T @ F, np.eye(3), atol=1e-9)  # orthonormal
        np.testing.assert_allclose(F[:, 2], rig.mesh.normals[rig.mesh.features[name]])
        assert F[1, 1] > 0.5  # "up" is mostly +Y
        assert F[0, 0] * (-1 if name.endswith("_r") else 1) > 0.0  # "outward" leaves the midline


def test_face_has_the_papers_feature_points(rig):
    assert len(FEATURE_POINTS) == 48
    assert set(rig.mesh.features) == set(FEATURE_POINTS)
    assert len(set(rig.mesh.features.values())) == 48
    # left features sit at +X, their twins mirrored
    v = rig.mesh.vertices
    for name in FEATURE_POINTS:
        if name.endswith("_l"):
            a, b = v[rig.mesh.features[name]], v[rig.mesh.features[name[:-2] + "_r"]]
            assert a[0] > 0.005 and b[0] < -0.005
            np.testing.assert_allclose(a * [-1, 1, 1], b, atol=2e-3)


@pytest.mark.parametrize("au", sorted(ACTION_UNITS))
def test_action_unit_moves_its_features_exactly_and_nothing_outside(rig, au):
    k = rig.au_numbers.index(au)
    weights = np.zeros(rig.num_shapes)
    weights[k] = 1.0
    moved = rig.deform(weights) - rig.mesh.vertices.astype(np.float32)  # float32, as the kernel sees them
    expected = _expected_feature_moves(rig, ACTION_UNITS[au])
    for name, vec in expected.items():
        np.testing.assert_allclose(moved[rig.mesh.features[name]], vec, atol=1e-6)
    # every other feature point stays put (the interpolant's own values: nothing overwrites them)
    for name, vertex in rig.mesh.features.items():
        if name not in expected:
            np.testing.assert_allclose(moved[vertex], 0.0, atol=1e-6, err_msg=name)
    # vertices farther than the radius from every constrained point do not move at all
    uv = rig.mesh.surface_uv
    centres = uv[[rig.mesh.features[n] for n in rig.constrained[k]]]
    far = np.linalg.norm(uv[:, None] - centres[None], axis=-1).min(1) >= ACTION_UNITS[au].radius
    assert far.sum() >= 40  # the jaw's 4 cm reach holds nearly every feature point: 48 vertices lie beyond them all
    assert np.all(moved[far] == 0.0)
    # and it does move a neighbourhood, smoothly (no vertex beyond 1.5x the largest authored move)
    biggest = max(np.linalg.norm(v) for v in expected.values())
    assert np.linalg.norm(moved, axis=1).max() <= 1.5 * biggest


def test_kernel_matches_float64_blend_of_offsets(rig):
    rng = np.random.default_rng(3)
    w = rng.uniform(-1.0, 1.0, rig.num_shapes)
    w[len(rig.au_numbers):] *= 8.0  # mouth parameters in mm
    ref = rig.mesh.vertices + np.einsum("s,svk->vk", w, rig.offsets)
    np.testing.assert_allclose(rig.deform(w), ref, atol=2e-6)


def test_mouth_parameters_move_their_control_points_in_millimetres(rig):
    mouth = np.zeros(len(MOUTH_PARAMETERS))
    mouth[MOUTH_PARAMETERS.index("jaw_vertical")] = -12.0
    mouth[MOUTH_PARAMETERS.index("corner_horizontal")] = 5.0
    moved = rig.deform(rig.weights(None, mouth)) - rig.mesh.vertices
    f = rig.mesh.features
    frame = lambda n: feature_frame(rig.mesh, n)  # noqa: E731
    np.testing.assert_allclose(moved[f["chin"]], frame("chin") @ [0.0, -0.012, 0.0], atol=1e-6)
    np.testing.assert_allclose(moved[f["mouth_corner_l"]], frame("mouth_corner_l") @ [0.005, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(moved[f["mouth_corner_r"]], frame("mouth_corner_r") @ [0.005, 0.0, 0.0], atol=1e-6)
    assert moved[f["mouth_corner_l"], 0] > 0.004 and moved[f["mouth_corner_r"], 0] < -0.004  # mirrored
    jaw_only = rig.weights(None, np.eye(len(MOUTH_PARAMETERS))[MOUTH_PARAMETERS.index("jaw_vertical")] * -12.0)
    held = rig.deform(jaw_only) - rig.mesh.vertices
    np.testing.assert_allclose(held[f["upper_lip_bottom"]], 0.0, atol=1e-6)  # the jaw opens below the upper lip


def test_vowel_bases_interpolate_and_open_the_mouth(rig):
    f = rig.mesh.features
    gap = {}
    for v in VOWELS:
        p = rig.deform(rig.weights(None, VOWEL_SHAPES[VOWELS.index(v)]))
        gap[v] = p[f["upper_lip_bottom"], 1] - p[f["lower_lip_top"], 1]
    assert gap["closed"] == pytest.approx(0.0, abs=1e-6)
    assert gap["a"] > gap["o"] > gap["e"] > gap["i"] > 0.0  # /a/ opens widest
    halfway = mouth_from_weights([0.5, 0, 0, 0, 0, 0.5])  # half /a/, half closed
    np.testing.assert_allclose(halfway, 0.5 * VOWEL_SHAPES[0])
    assert list(nearest_vowel(VOWEL_SHAPES)) == list(range(6))


def test_emotions_are_the_facs_mixes():
    as_sets = {k: set(v) for k, v in EMOTIONS.items()}
    assert as_sets["happiness"] == {6, 12}
    assert as_sets["sadness"] == {1, 4, 15}
    assert as_sets["surprise"] == {1, 2, 5, 26}
    assert as_sets["fear"] == {1, 2, 4, 5, 20, 26}
    assert as_sets["anger"] == {4, 5, 7, 23}
    assert as_sets["disgust"] == {9, 15, 16}


def test_expressions_blend_with_smoothstep(rig):
    anim = FaceAnimation([ExpressionKey(1.0, "neutral"), ExpressionKey(11.0, "happiness", weight=0.8)])
    assert anim.action_units(0.0) == {}
    assert anim.action_units(6.0)[12] == pytest.approx(0.4)  # smoothstep(0.5) = 0.5
    assert anim.action_units(3.5)[12] == pytest.approx(0.8 * 0.15625)  # smoothstep(0.25)
    assert anim.action_units(20.0) == {6: 0.8, 12: 0.8}
    w = anim.weights(rig, 11.0)
    assert w[rig.au_numbers.index(12)] == pytest.approx(0.8)


def test_editing_an_action_unit_changes_the_rig(rig):
    rig2 = FaceRig(rig.mesh, "cpu")
    rig2.set_action_unit(12, {"mouth_corner": (0.0, 10.0, 0.0)})
    moved = rig2.deform(rig2.weights({12: 1.0})) - rig2.mesh.vertices
    up = feature_frame(rig2.mesh, "mouth_corner_r")[:, 1]
    np.testing.assert_allclose(moved[rig2.mesh.features["mouth_corner_r"]], 0.010 * up, atol=1e-6)
    with pytest.raises(KeyError):
        rig2.weights({27: 1.0})


def test_posed_face_rides_a_rigidly_moving_head(rig):
    """On a head turned and nodded rigidly, the bound face is the rest-frame face moved by the same
    rigid transform, and head_transform recovers that transform."""
    from sim.collider import Collider
    from sim.head import HeadAnimation, procedural_head

    head = procedural_head()
    weights = np.zeros((len(head.vertices), 4))
    weights[:, 0] = 1.0
    index = np.tile([1, 0, 0, 0], (len(head.vertices), 1))
    col = Collider("head", head.vertices, head.faces, index, weights, 2, "cpu", sphere_leaves=0)
    face = FaceRig(builtin_face(resolution=1, project=lambda p: _project(col, head, p)), "cpu")
    face.attach(col)
    M = HeadAnimation(turn_degrees=30.0, nod_degrees=12.0).bone_matrices([0.7])
    col.set_poses(M)
    col.apply_pose(0)
    w = face.weights(EMOTIONS["surprise"], VOWEL_SHAPES[0])
    posed = face.posed_points(col, w).numpy().copy()
    T = M[0, 1]
    ref = face.deform(w).astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(posed, ref, atol=1e-5)
    np.testing.assert_allclose(face.head_transform(col), T, atol=1e-5)


def _project(collider, head, points):
    import trimesh

    normals = trimesh.Trimesh(head.vertices, head.faces, process=False).vertex_normals
    closest, f, bary = collider.closest_points(points)
    n = np.einsum("nk,nkj->nj", bary, normals[head.faces[f]])
    return closest, n / np.linalg.norm(n, axis=1, keepdims=True)


def test_rigid_fit_recovers_a_transform():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(50, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = q, [0.1, -0.2, 0.3]
    np.testing.assert_allclose(rigid_fit(a, a @ q.T + T[:3, 3]), T, atol=1e-12)
    # a batch of frames: each recovered, including the identity
    batch = np.stack([a, a @ q.T + T[:3, 3]])
    np.testing.assert_allclose(rigid_fit(a, batch), np.stack([np.eye(4), T]), atol=1e-12)


def test_interpolation_is_compact(rig):
    d = ACTION_UNITS[5]
    offsets, names = interpolate_shape(rig.mesh, d)
    assert set(names) >= {"eye_upper_l", "eye_upper_r"}
    assert (np.abs(offsets).max(1) > 0).sum() < 0.1 * rig.mesh.num_vertices  # the lids, not the face


# -- scenes and USD ----------------------------------------------------------------------------


def _face_scene(tmp_path, extra=""):
    path = tmp_path / "face.toml"
    path.write_text(f"""
[scene]
frames = 6
preroll = 0.0
stats = false

[head]
animation = "turn_nod"

[hair]
enabled = false

[face]
resolution = 1

[[face.expressions]]
frame = 1
emotion = "neutral"

[[face.expressions]]
frame = 6
emotion = "fear"
{extra}
""")
    return path


def _usdskel_points(stage, time):
    """The exported rig evaluated by UsdSkel itself: blend shapes, then skinning."""
    from pxr import Usd, UsdGeom, UsdSkel, Vt

    root = UsdSkel.Root(stage.GetPrimAtPath("/World/face_rig"))
    cache = UsdSkel.Cache()
    cache.Populate(root, Usd.PrimDefaultPredicate)
    binding = cache.ComputeSkelBindings(root, Usd.PrimDefaultPredicate)[0]
    skel = cache.GetSkelQuery(binding.GetSkeleton())
    target = binding.GetSkinningTargets()[0]
    query = UsdSkel.BlendShapeQuery(UsdSkel.BindingAPI(target.GetPrim()))
    t = Usd.TimeCode(time)
    weights = skel.GetAnimQuery().ComputeBlendShapeWeights(t)
    mapper = target.GetBlendShapeMapper()
    if mapper and not mapper.IsNull():
        weights = mapper.Remap(weights)
    sub_weights, shape_idx, sub_idx = query.ComputeSubShapeWeights(weights)
    pts = Vt.Vec3fArray(UsdGeom.Mesh(target.GetPrim()).GetPointsAttr().Get(t))
    assert query.ComputeDeformedPoints(sub_weights, shape_idx, sub_idx, query.ComputeBlendShapePointIndices(),
                                       query.ComputeSubShapePointOffsets(), pts)
    blended = np.array(pts, np.float64)
    assert target.ComputeSkinnedPoints(skel.ComputeSkinningTransforms(t), pts, t)
    return blended, np.array(pts, np.float64)


def test_usdskel_blend_shapes_equal_the_rig(tmp_path):
    from pxr import Usd, UsdGeom

    from sim.scene import Scene, load_scene, run_scene

    path = _face_scene(tmp_path)
    out = tmp_path / "face.usdc"
    run_scene(load_scene(path), out, progress=False)
    stage = Usd.Stage.Open(str(out))
    face = UsdGeom.Mesh(stage.GetPrimAtPath("/World/face"))
    assert face.GetPrim().GetAttribute("cfx:role").Get() == "face"
    assert len(face.GetPointsAttr().GetTimeSamples()) == 6
    rig = Scene(load_scene(path)).face_rig
    anim = FaceAnimation(load_scene(path).face.expressions)
    for frame in (1, 4, 6):
        blended, skinned = _usdskel_points(stage, frame)
        # the blend shapes alone are the rig's own deformation in its rest frame
        np.testing.assert_allclose(blended, rig.deform(anim.weights(rig, frame)), atol=1e-5)
        # and skinned by the head joint they are the cached face on the turning, nodding head
        np.testing.assert_allclose(skinned, np.array(face.GetPointsAttr().Get(frame)), atol=1e-5)
    # the face really changes: fear opens the jaw by about a centimetre
    f = rig.mesh.features
    p1, p6 = (np.array(face.GetPointsAttr().Get(t)) for t in (1, 6))
    gap = lambda p: np.linalg.norm(p[f["upper_lip_bottom"]] - p[f["lower_lip_top"]])  # noqa: E731
    assert gap(p1) < 1e-4 and gap(p6) > 0.007
    from io_usd.validate import validation_errors

    assert validation_errors(str(out)) == []


def test_bad_face_input_is_one_clear_error(tmp_path):
    from sim.scene import load_scene

    path = _face_scene(tmp_path, '\n[[face.expressions]]\nframe = 9\nemotion = "smug"\n')
    with pytest.raises(InputError) as err:
        load_scene(path)
    assert "face.expressions[2].emotion" in str(err.value) and "smug" in str(err.value)
    path.write_text('[hair]\nenabled = false\n[face]\n[[face.expressions]]\nframe = 1\naus = { "99" = 1.0 }\n')
    with pytest.raises(InputError, match=r"face.expressions\[0\].aus.99"):
        load_scene(path)
    path.write_text('[head]\nmesh = "head.obj"\n[face]\n')
    (tmp_path / "head.obj").write_text("v 0 0 0\n")
    with pytest.raises(InputError, match="face.mesh"):
        load_scene(path)


def test_a_users_face_mesh_and_feature_map(tmp_path):
    """A face brought as a mesh file plus a JSON feature map rides the head like the built-in one."""
    import json

    import trimesh

    from sim.scene import Scene, load_scene

    face = builtin_face(resolution=1)
    v = face.vertices.copy()
    # part the lips in the file: the lower-lip and lining twins (the last 3 x 9 vertices) drop 1 mm
    twins = np.arange(len(v)) >= len(v) - 3 * 9
    v[twins, 1] -= 0.001
    trimesh.Trimesh(v, face.faces, process=False).export(tmp_path / "face.obj")
    (tmp_path / "face.json").write_text(json.dumps(face.features))
    path = _face_scene(tmp_path, "")
    path.write_text(path.read_text().replace("resolution = 1", 'mesh = "face.obj"\nfeatures = "face.json"'))
    scene = Scene(load_scene(path))
    assert scene.face_rig.mesh.num_vertices == len(v)
    moved = scene.face_rig.deform(scene.face_rig.weights({26: 1.0})) - scene.face_rig.mesh.vertices
    chin = feature_frame(scene.face_rig.mesh, "chin") @ [0.0, -0.010, -0.0015]
    np.testing.assert_allclose(moved[face.features["chin"]], chin, atol=1e-6)

    (tmp_path / "face.json").write_text(json.dumps({k: i for k, i in list(face.features.items())[:10]}))
    with pytest.raises(InputError, match="missing feature points"):
        Scene(load_scene(path))


def test_no_expression_or_mouth_shape_sinks_the_face_into_the_head():
    """The face floats over the head: every emotion and vowel (and their extremes mixed) keeps every
    vertex, lips and mouth lining included, outside the bust it was built on."""
    from sim.head import procedural_head
    from sim.sphere_tree import signed_distance, warp_mesh

    head = procedural_head()
    rig = FaceRig(builtin_face(resolution=1), "cpu")
    mesh = warp_mesh(head.vertices, head.faces)
    shapes = [rig.weights(EMOTIONS[e], VOWEL_SHAPES[v]) for e in EMOTIONS for v in range(len(VOWELS))]
    rest, _ = signed_distance(rig.mesh.vertices, mesh)
    lifted = rest > 1e-3  # all but the border's band at the forehead and the sides, which lies 0.4 mm out
    for w in shapes:
        sdf, _ = signed_distance(rig.deform(w), mesh)
        assert sdf[lifted].min() > 0.0003 and sdf.min() > 0.00025


def test_a_mouth_track_drives_the_mouth_and_bad_tracks_are_named(tmp_path):
    from sim.scene import Scene, load_scene

    track = np.zeros((6, 13))
    track[2:] = VOWEL_SHAPES[VOWELS.index("a")]
    np.save(tmp_path / "mouth.npy", track)
    path = _face_scene(tmp_path, "")
    path.write_text(path.read_text().replace("resolution = 1", 'resolution = 1\nmouth = "mouth.npy"\naudio_start = 1'))
    scene = Scene(load_scene(path))
    rig, anim = scene.face_rig, scene.face_animation
    np.testing.assert_allclose(anim.weights(rig, 4.0)[len(rig.au_numbers):], VOWEL_SHAPES[0])  # row 3
    np.testing.assert_allclose(anim.weights(rig, 2.0)[len(rig.au_numbers):], 0.0)
    np.save(tmp_path / "mouth.npy", np.zeros((6, 12)))
    with pytest.raises(InputError, match=r"face.mouth.*\(6, 12\)"):
        Scene(load_scene(path))
    np.save(tmp_path / "mouth.npy", np.full((6, 13), 1e30))  # it blew the face up in a cache marked complete
    with pytest.raises(InputError, match=r"face.mouth: mouth parameters are millimetres: at most 100"):
        Scene(load_scene(path))


def test_example_face_scene_loads():
    from pathlib import Path

    from sim.scene import load_scene

    config = load_scene(Path(__file__).resolve().parents[1] / "examples" / "scenes" / "face_talk.toml")
    assert config.face.enabled and config.face.audio == "builtin"
    assert [k.emotion for k in config.face.expressions] == ["neutral", "happiness", "surprise"]


def test_feature_colours_are_the_paint_filtered_by_the_tent_over_each_vertex():
    """The built-in face's vertex colours are _paint_at averaged with the tent of the grid around each
    vertex (1 at the vertex, 0 at its neighbours; the prefilter that suits colours interpolated linearly
    across the triangles), so brows, eyes and lips draw soft straight edges, not steps of the grid
    (a box over the vertex's own cell still left steps along slanted brows): against a 40 x 40 midpoint
    quadrature of the same tent at every grid vertex near the brows and eyes, within 0.01 of each
    channel; a colour taken at the vertex alone misses by more than 0.1 there."""
    from sim import face as face_module

    mesh = face_module.builtin_face(resolution=2)
    rows = face_module._refine(np.asarray(face_module._ROWS), 2)
    half = face_module._refine(np.asarray(face_module._HALF_COLUMNS), 2)
    cols = np.concatenate([-half[:0:-1], half])
    i, j = np.meshgrid(np.arange(1, len(rows) - 1), np.arange(1, len(cols) - 1), indexing="ij")
    i, j = i.ravel(), j.ravel()
    near = np.abs(rows[i] - 0.35) < 0.03  # brows and eyes
    i, j = i[near], j[near]
    t = (np.arange(40) + 0.5) / 40.0 * 2.0 - 1.0
    want, total = np.zeros((len(i), 3)), 0.0
    for u in t:
        r = rows[i] + np.where(u < 0.0, rows[i] - rows[i - 1], rows[i + 1] - rows[i]) * u
        for w in t:
            c = cols[j] + np.where(w < 0.0, cols[j] - cols[j - 1], cols[j + 1] - cols[j]) * w
            weight = (1.0 - abs(u)) * (1.0 - abs(w))
            want += weight * face_module._paint_at(r, c)
            total += weight
    want /= total
    got = mesh.colors[i * len(cols) + j]
    assert np.abs(got - want).max() < 0.01
    point = face_module._paint_at(rows[i], cols[j])
    assert np.abs(point - want).max() > 0.1  # the edges are where averaging matters


def test_pn_surface_points_lie_on_the_curved_surface_a_coarse_mesh_stands_for():
    """On an icosphere of 320 triangles (its vertices on a sphere of 10 cm, its normals radial), points
    on the flat triangles sit up to 1.8 mm inside the sphere; on its PN triangles (pn_surface_points, the
    surface the face is projected onto) within 0.05 mm of it, with normals within 1e-3 of the radial ones,
    and a mesh vertex stays where it is."""
    import trimesh

    from sim.detail import pn_surface_points

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
    vertices, faces = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    normals = vertices / np.linalg.norm(vertices, axis=1, keepdims=True)
    rng = np.random.default_rng(2)
    face = rng.integers(0, len(faces), 2000)
    bary = rng.dirichlet(np.ones(3), 2000)
    flat = np.einsum("nk,nkj->nj", bary, vertices[faces[face]])
    curved, n = pn_surface_points(vertices, normals, faces, face, bary)
    assert np.abs(np.linalg.norm(flat, axis=1) - 0.1).max() > 1.5e-3
    assert np.abs(np.linalg.norm(curved, axis=1) - 0.1).max() < 1e-4
    radial = curved / np.linalg.norm(curved, axis=1, keepdims=True)
    assert np.abs(np.einsum("ij,ij->i", n, radial) - 1.0).max() < 1e-3
    at_corner, _ = pn_surface_points(vertices, normals, faces, np.arange(5), np.tile([1.0, 0.0, 0.0], (5, 1)))
    np.testing.assert_allclose(at_corner, vertices[faces[:5, 0]], atol=1e-7)


def test_a_finer_built_in_face_rides_the_head_outside_it_and_meets_it_at_its_border():
    """The built-in face at resolution 3 (close-ups), projected onto the head's PN surface and lifted 2 mm:
    away from its border every vertex lies outside the head's mesh by at least a millimetre and a half
    (measured 1.62 mm), so the head never shows through it; its border at the forehead and the sides
    lies on the head's triangles, 0.4 mm out, so its edge shows no step (it stood 2 mm proud)."""
    import trimesh

    import sim.face as face_module
    from sim.scene import Scene, hair_demo_scene

    scene = Scene(hair_demo_scene({"hair": {"enabled": False}, "face": {"enabled": True, "resolution": 3}}))
    mesh = scene.face_rig.mesh
    points = mesh.vertices
    head = trimesh.Trimesh(scene.head.vertices, scene.head.faces, process=False)
    closest, face, bary = scene.collider.closest_points(points)
    outward = np.einsum("ij,ij->i", points - closest, head.face_normals[face])
    assert len(points) > 7000 and outward.min() > 3e-4
    nr = len(face_module._refine(np.asarray(face_module._ROWS), 3))
    nc = 2 * len(face_module._refine(np.asarray(face_module._HALF_COLUMNS), 3)) - 1  # both sides share column 0
    i, j = np.divmod(np.arange(nr * nc), nc)
    border = (i == nr - 1) | (j == 0) | (j == nc - 1)
    np.testing.assert_allclose(outward[:nr * nc][border], 0.2 * 0.002, atol=5e-5)
    u, v = mesh.surface_uv[:nr * nc, 0], mesh.surface_uv[:nr * nc, 1]
    band = face_module.BORDER_BAND
    far = (np.abs(u) < np.abs(u).reshape(nr, nc).max(axis=1).repeat(nc) - band) & (v < v.max() - band)
    assert far.sum() > 2000 and outward[:nr * nc][far].min() > 1.5e-3
