"""Render children: the kernel against a float64 reference of the same rule, a rigid motion of head
and hair carrying them rigidly, and a scene writing them to its cache outside the head, unstretched."""

import numpy as np
import pytest
import warp as wp

from io_usd import CacheReader
from io_usd.score import score_caches
from sim.cli import main
from sim.hair_children import choose_parents
from sim.scene import Scene, hair_demo_scene
from warp_kernels import collision
from warp_kernels import strands as strand_kernels

VERTICES = 8


@pytest.fixture(scope="module")
def scene():
    return Scene(hair_demo_scene({"scene": {"device": "cpu", "preroll": 0.0, "stats": False},
                                  "hair": {"count": 40, "vertices": VERTICES, "length": 0.12, "children": 3}}))


def _rigid(angle=np.radians(40.0), shift=(0.03, -0.02, 0.05)):
    c, s = np.cos(angle), np.sin(angle)
    m = np.eye(4)
    m[:3, :3] = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]) @ np.array([[1, 0, 0], [0, np.cos(0.3), -np.sin(0.3)],
                                                                          [0, np.sin(0.3), np.cos(0.3)]])
    m[:3, 3] = shift
    return m


def _place(scene, x):
    scene.state.x.assign(x.astype(np.float32))
    children = scene.children.queue(scene.state.x, scene.collider, scene.config.solver.collision_margin)
    return children.numpy().astype(np.float64).reshape(-1, VERTICES, 3)


def _posed(scene, m):
    scene.collider.set_poses(np.stack([m, m])[None])  # both bones: the whole bust moves rigidly
    scene.collider.apply_pose(0)


def test_children_are_their_groom_at_rest_and_move_rigidly_with_head_and_hair(scene):
    kids = scene.children
    rest = kids.child_rest.numpy().astype(np.float64).reshape(-1, VERTICES, 3)
    parents = scene.model.rest_positions_np.astype(np.float64)
    try:
        np.testing.assert_allclose(_place(scene, parents), rest, atol=2e-6)
        m = _rigid()
        _posed(scene, m)
        moved = _place(scene, parents @ m[:3, :3].T + m[:3, 3])
        np.testing.assert_allclose(moved, rest @ m[:3, :3].T + m[:3, 3], atol=2e-5)
    finally:
        _posed(scene, np.eye(4))


def test_children_follow_their_parents_as_the_float64_reference_does(scene):
    """Parents lifted by smooth, different displacements (upward, away from the head, so no push
    acts): the kernel's children against the rule in float64, with the head turned."""
    kids, model = scene.children, scene.model
    rng = np.random.default_rng(3)
    rest = model.rest_positions_np.astype(np.float64).reshape(-1, VERTICES, 3)
    child_rest = kids.child_rest.numpy().astype(np.float64).reshape(-1, VERTICES, 3)
    ramp = np.linspace(0.0, 1.0, VERTICES)[None, :, None]
    lift = (np.array([0.0, 0.02, 0.0]) + rng.normal(size=(len(rest), 1, 3)) * 0.004) * ramp
    lift[:, :2] = 0.0  # the pinned root particles stay with the head
    m = _rigid(np.radians(25.0))
    R, t = m[:3, :3], m[:3, 3]
    try:
        _posed(scene, m)
        got = _place(scene, (rest + lift).reshape(-1, 3) @ R.T + t)
    finally:
        _posed(scene, np.eye(4))
    parents, weights = kids.parents.numpy(), kids.weights.numpy().astype(np.float64)
    want = child_rest @ R.T + t
    displaced = want + np.einsum("cj,cjvk->cvk", weights, lift[parents] @ R.T)
    for k in range(2, VERTICES):  # follow the leader at the groomed lengths
        length = np.linalg.norm(child_rest[:, k] - child_rest[:, k - 1], axis=1, keepdims=True)
        step = displaced[:, k] - want[:, k - 1]
        want[:, k] = want[:, k - 1] + length * step / np.linalg.norm(step, axis=1, keepdims=True)
    np.testing.assert_allclose(got, want, atol=5e-6)
    assert np.abs(got - child_rest @ R.T - t).max() > 0.01  # the lift did move them


@pytest.mark.parametrize("lanes", [False, True])
def test_the_strands_contact_bounds_spare_pushes_without_changing_the_children(lanes):
    """interpolate_children with the hair solver's contact bounds against the mesh (mesh_clearance) gives
    the children of pushing every vertex, bit for bit, after frames of a turning head with hair lying
    on it, with the bounds in particle order or in a GPU's lane order (each particle's slot read);
    bounds that claim every point is 1 m clear change them (the pushes were read from the bounds, and
    some were needed)."""
    scene = Scene(hair_demo_scene({"scene": {"device": "cpu", "preroll": 0.0, "stats": False},
                                   "head": {"animation": "turn"},
                                   "hair": {"count": 60, "vertices": VERTICES, "length": 0.15, "children": 3},
                                   "solver": {"collision": "mesh"}}))
    if lanes:
        scene.solver.fused = False
        scene.solver.set_parts(1)
        scene.solver.set_lanes(True)
        assert scene.solver.mesh_clearance()[1] is not None
    for _ in range(3):
        scene.advance(1.0 / 24.0)
    kids, margin, x = scene.children, scene.config.solver.collision_margin, scene.state.x
    bounds = scene.solver.mesh_clearance()
    assert bounds is not None
    clearance = bounds[0].numpy()
    known = clearance > 0.5 * strand_kernels.NO_BOUND
    assert known.mean() > 0.5 and np.any(clearance[known] > margin + 0.005)  # many parents are clear of the head
    every = kids.queue(x, scene.collider, margin).numpy().copy()
    spared = kids.queue(x, scene.collider, margin, bounds).numpy().copy()
    np.testing.assert_array_equal(spared, every)
    far = wp.full(len(clearance), 1.0, dtype=float, device="cpu")
    blind = kids.queue(x, scene.collider, margin, (far, bounds[1])).numpy()
    assert np.abs(blind - every).max() > 1e-4
    assert scene.solver.mesh_clearance() is not None
    scene.solver.contact_bounds = False
    assert scene.solver.mesh_clearance() is None


def test_parents_are_chosen_by_root_and_shape_so_the_parting_splits_them():
    """Strands either side of a parting, swept apart: a child on one side follows only strands of
    its own side, however near the other side's roots are."""
    s = np.linspace(0.0, 0.2, 6)[:, None]
    left = [np.array([-0.002 - 0.004 * i, 0.0, 0.0]) + s * [-1.0, -1.0, 0.0] for i in range(4)]
    right = [np.array([0.002 + 0.004 * i, 0.0, 0.0]) + s * [1.0, -1.0, 0.0] for i in range(4)]
    parents = np.array(left + right)
    child = np.array([[0.0005, 0.0, 0.0]]) + s * [1.0, -1.0, 0.0]
    chosen, weights = choose_parents(parents, child[None])
    assert set(chosen[0]) <= {4, 5, 6, 7} and abs(weights.sum() - 1.0) < 1e-6


def test_a_scene_writes_children_outside_the_head_at_their_lengths(tmp_path, capsys):
    scene_file = tmp_path / "scene.toml"
    scene_file.write_text('[scene]\nframes = 3\npreroll = 0.2\n[head]\nanimation = "turn"\n'
                          f'[hair]\ncount = 30\nvertices = {VERTICES}\nlength = 0.15\nchildren = 4\n')
    out = str(tmp_path / "kids.usdc")
    assert main(["run", str(scene_file), "-o", out]) == 0
    assert "30 strands (240 particles) and 120 render children" in capsys.readouterr().err
    reader = CacheReader(out)
    kids = reader.prims["hair_children"]
    assert kids.role == "hair" and len(kids.counts) == 120 and set(kids.counts) == {VERTICES}
    head = next(n for n, p in reader.prims.items() if p.role == "collider")
    lengths = None
    for f in reader.frames():
        points = reader.points("hair_children", f)
        mesh = wp.Mesh(points=wp.array(reader.points(head, f), dtype=wp.vec3, device="cpu"),
                       indices=wp.array(reader.triangles(head).reshape(-1).astype(np.int32), dtype=wp.int32,
                                        device="cpu"))
        distance = wp.zeros(len(points), dtype=float, device="cpu")
        wp.launch(collision.mesh_signed_distance, len(points),
                  [wp.array(points, dtype=wp.vec3, device="cpu"), mesh.id, 0.1, 0, distance,
                   wp.zeros(len(points), dtype=wp.vec3, device="cpu")], device="cpu")
        assert distance.numpy().min() > -1e-4  # none inside (roots sit on the scalp)
        segments = np.linalg.norm(np.diff(points.reshape(-1, VERTICES, 3), axis=1), axis=2)
        lengths = segments if lengths is None else lengths
        change = np.abs(segments / lengths - 1.0)
        # the walk keeps the lengths; the push out of the head after it moves a few vertices a little (3 of
        # 840 segments by 1-3.1% here since the shape pass moves no momentum: 1.1% at most before)
        assert np.median(change) < 1e-5 and change.max() < 0.05 and np.mean(change > 0.01) < 0.01
    # marked as drawn from the strands: scoring compares the strands alone (a cache with children
    # scores as the same hair without them)
    assert kids.interpolated_from == "/World/hair" and reader.prims["hair"].interpolated_from is None
    capsys.readouterr()
    bare = scene_file.read_text().replace("children = 4", "children = 0")
    (tmp_path / "bare.toml").write_text(bare)
    assert main(["run", str(tmp_path / "bare.toml"), "-o", str(tmp_path / "bare.usdc"), "-q"]) == 0
    report = score_caches(out, str(tmp_path / "bare.usdc"), size=(160, 160), images=False)
    assert report.result_strands == report.target_strands == 30
    assert report.matched_fraction == 1.0 and report.length_agreement == pytest.approx(1.0, abs=1e-6)
    assert min(report.ious.values()) > 0.999
    capsys.readouterr()
    scene_file.write_text('[hair]\nchildren = 2\n[[haircut]]\nframe = 2\ntool = "blunt"\n'
                          'plane = { point = [0.0, 0.3, 0.0], normal = [0.0, 1.0, 0.0] }\n')
    assert main(["run", str(scene_file), "-o", str(tmp_path / "cut.usdc"), "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "hair.children: a haircut changes the strands children follow" in err
    scene_file.write_text('[hair]\nchildren = -1\n')
    assert main(["run", str(scene_file), "-o", str(tmp_path / "bad.usdc"), "-q"]) == 2
    assert "hair.children: children must be 0 to 64" in capsys.readouterr().err
