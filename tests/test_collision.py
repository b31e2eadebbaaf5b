"""Head collisions: the sphere tree is inside the head, and settled hair ends outside the head."""

import functools

import numpy as np
import pytest
import trimesh

from sim.collider import Collider
from sim.hair_solver import HairParams, HairSolver
from sim.hairstyle import HairstyleParams, grow_hairstyle, sample_scalp
from sim.head import HeadAnimation
from sim.sphere_tree import signed_distance
from sim.strands import StrandBuilder
from warp_kernels import strands as strand_kernels


def test_procedural_head_is_a_closed_outward_mesh(head):
    mesh = trimesh.Trimesh(head.vertices, head.faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert 0.012 < mesh.volume < 0.025  # m^3: a bust, not a sphere of the wrong scale
    assert head.scalp_faces.sum() > 1000
    np.testing.assert_allclose(head.skin_weights.sum(1), 1.0)


def test_head_animation_starts_at_rest_and_turns():
    anim = HeadAnimation()
    np.testing.assert_allclose(anim.bone_matrices([0.0])[0], np.eye(4)[None].repeat(2, 0), atol=1e-12)
    yaw, pitch = anim.angles(np.array([anim.turn_period / 4.0]))
    assert abs(np.degrees(yaw[0]) - anim.turn_degrees) < 1e-6
    M = anim.bone_matrices([0.6, 1.3])[:, 1]
    np.testing.assert_allclose(np.einsum("nij,nkj->nik", M[:, :3, :3], M[:, :3, :3]), np.eye(3)[None].repeat(2, 0),
                               atol=1e-12)  # rotations stay orthonormal
    np.testing.assert_allclose((M[:, :3, :3] @ anim.pivot) + M[:, :3, 3], np.tile(anim.pivot, (2, 1)), atol=1e-12)


def test_sphere_tree_leaves_lie_inside_the_head_and_cover_it(head, head_collider):
    centers, radii = head_collider.tree.leaves()
    sdf = head_collider.signed_distance(centers)
    assert np.all(sdf + radii <= 1e-3)  # every leaf sphere inside the surface (1 mm tolerance)
    # the surface lies close outside the union of spheres (fresh samples, not those the build covered)
    surface, _ = trimesh.sample.sample_surface(trimesh.Trimesh(head.vertices, head.faces, process=False), 5000,
                                               seed=5)
    gap = np.min(np.linalg.norm(surface[:, None] - centers[None], axis=2) - radii[None], axis=1)
    assert np.median(gap) < 0.001 and np.percentile(gap, 95) < 0.0025
    # inner nodes bound their subtree (depth-first layout with skip pointers)
    t = head_collider.tree
    for i in np.flatnonzero(t.is_leaf == 0):
        sub = np.arange(i + 1, t.skip[i])
        leaves = sub[t.is_leaf[sub] == 1]
        reach = np.linalg.norm(t.centers[leaves] - t.centers[i], axis=1) + t.radii[leaves]
        assert np.all(reach <= t.radii[i] + 1e-6)


def test_lazy_greedy_cover_chooses_what_recounting_every_candidate_chooses():
    """Against the plain greedy (every candidate's gain recounted at every step, the lowest index
    among equals), on random sets full of ties and on sets that cover everything before the limit."""
    from sim.sphere_tree import greedy_cover

    rng = np.random.default_rng(11)
    for sets, samples, size, limit in ((300, 500, 12, 60), (200, 80, 6, 500), (50, 1000, 200, 20)):
        rows = [rng.choice(samples, rng.integers(0, size + 1), replace=False) for _ in range(sets)]
        start = np.concatenate([[0], np.cumsum([len(r) for r in rows])])
        covered = np.concatenate(rows).astype(np.int64)
        dense = np.zeros((sets, samples))
        for k, r in enumerate(rows):
            dense[k, r] = 1.0
        uncovered, want = np.ones(samples), []
        while len(want) < limit and uncovered.any():
            gain = dense @ uncovered
            if gain.max() <= 0:
                break
            want.append(int(np.argmax(gain)))
            uncovered[dense[want[-1]] > 0] = 0.0
        assert greedy_cover(start, covered, samples, limit).tolist() == want


def test_a_cached_sphere_tree_is_the_tree_built_without_the_cache(head, tmp_path, monkeypatch):
    from sim.sphere_tree import build_sphere_tree

    monkeypatch.setenv("CFX_CACHE_DIR", str(tmp_path))
    built = build_sphere_tree(head.vertices, head.faces, max_leaves=64)
    cached = build_sphere_tree(head.vertices, head.faces, max_leaves=64)
    monkeypatch.setenv("CFX_CACHE_DIR", "off")
    fresh = build_sphere_tree(head.vertices, head.faces, max_leaves=64)
    assert fresh.leaf_count == 64 and len(list(tmp_path.glob("sphere_tree-*.npz"))) == 1
    for key in ("centers", "radii", "skip", "is_leaf"):
        for tree in (built, cached):
            assert getattr(tree, key).dtype == getattr(fresh, key).dtype
            assert np.array_equal(getattr(tree, key), getattr(fresh, key))


@pytest.mark.parametrize("mode", ["sphere_tree", "mesh"])
def test_settled_hair_ends_outside_the_head(head, head_collider, mode):
    roots, _, _, normals = sample_scalp(head.vertices, head.faces, head.scalp_faces, 150, seed=2)
    pts, counts, widths = grow_hairstyle(HairstyleParams(style="straight", vertices=12, length=0.2), roots,
                                         normals, head_collider.push_out)
    model = StrandBuilder().add_strands(pts, counts, widths).finalize("cpu").bind_to_mesh(
        head_collider.posed_points(), head.faces)
    # start the strands pointing into the head: collisions must push them out as they fall
    solver = HairSolver(model, HairParams(collision=mode))
    s0, s1 = model.state(), model.state()
    for _ in range(240):
        solver.step(s0, s1, head_collider, 1.0 / 240.0)
        s0, s1 = s1, s0
    x = s0.x.numpy()
    free = model.inv_mass_np > 0
    if mode == "sphere_tree":
        assert head_collider.sphere_tree_depth(x[free]).max() < 1e-4
    else:
        sdf = head_collider.signed_distance(x[free])
        assert np.mean(sdf < -0.001) < 0.005
        assert sdf.min() > -0.003


def test_groomed_rest_shape_clears_the_head(head, head_collider):
    roots, _, _, normals = sample_scalp(head.vertices, head.faces, head.scalp_faces, 200, seed=9)
    for style in ("straight", "wavy", "curly"):
        params = HairstyleParams(style=style, vertices=20, length=0.25)
        pts, counts, _ = grow_hairstyle(params, roots, normals, head_collider.push_out)
        assert pts.shape == (200 * 20, 3) and np.all(counts == 20)
        strands = pts.reshape(200, 20, 3)
        np.testing.assert_allclose(strands[:, 0], roots, atol=1e-6)
        sdf = head_collider.signed_distance(strands[:, 2:].reshape(-1, 3))
        assert sdf.min() > 0.0, style
        seg = np.linalg.norm(np.diff(strands, axis=1), axis=2)
        assert np.abs(seg / seg.mean(axis=1, keepdims=True) - 1.0).max() < 0.35  # evenly resampled
        natural = seg.sum(1)
        if style == "straight":
            assert np.all(np.abs(natural / 0.25 - 1.0) < params.length_jitter + 0.02)
        else:
            assert np.median(natural) > 0.25  # waves and curls add length to the centre line


def test_a_pose_of_listed_vertices_moves_only_those_and_keeps_the_last_pose_before(head):
    import warp as wp

    from sim.collider import Collider

    c = Collider("head", head.vertices, head.faces, head.skin_indices, head.skin_weights, head.num_bones, "cpu")
    c.set_poses(HeadAnimation(ease_in=0.0).bone_matrices([0.2, 0.5]))
    c.apply_pose(1)
    turned = c.points.numpy().copy()
    c.apply_pose(0)
    before = c.points.numpy().copy()
    listed = np.unique(head.faces[head.scalp_faces][:50])  # a patch of scalp, as hair roots would list
    c.apply_pose(1, refit=False, listed=wp.array(listed.astype(np.int32), dtype=wp.int32, device="cpu"))
    after, others = c.points.numpy(), np.setdiff1d(np.arange(len(head.vertices)), listed)
    np.testing.assert_array_equal(after[listed], turned[listed])  # skinned as a full pose skins them
    np.testing.assert_array_equal(after[others], before[others])
    np.testing.assert_array_equal(c.prev_points.numpy(), before)
    assert np.abs(turned - before)[listed].max() > 1e-3 and c.bvh_stale
    with pytest.raises(ValueError, match="cannot be refitted"):
        c.apply_pose(1, listed=wp.array(listed.astype(np.int32), dtype=wp.int32, device="cpu"))


def test_refitted_sphere_tree_bounds_each_subtree_exactly(head):
    from sim.collider import Collider

    c = Collider("head", head.vertices, head.faces, head.skin_indices, head.skin_weights, head.num_bones, "cpu")
    c.set_poses(HeadAnimation().bone_matrices([0.4]))  # turned and nodded: centres move, radii must follow
    c.apply_pose(0)
    centers, radii, t = c.sphere_centers.numpy(), c.sphere_radii.numpy(), c.tree
    assert not np.allclose(centers, t.centers)
    for i in np.flatnonzero(t.is_leaf == 0):
        sub = np.arange(i + 1, t.skip[i])
        leaves = sub[t.is_leaf[sub] == 1]
        expected = np.max(np.linalg.norm(centers[leaves] - centers[i], axis=1) + radii[leaves])
        assert abs(radii[i] - expected) < 1e-6
    # the walks read the posed tree packed: centre and radius side by side, skip pointer and leaf flag
    shape = c.shape
    np.testing.assert_array_equal(shape.spheres.numpy(), np.concatenate([centers, radii[:, None]], axis=1))
    links = shape.links.numpy()
    np.testing.assert_array_equal(links < 0, t.is_leaf != 0)
    np.testing.assert_array_equal(links & 0x7FFFFFFF, t.skip)


def _hair_on_a_turning_head(head, sphere_leaves, substeps, dt, strands, seed, ragged=False):
    """A head turning and nodding fast (a quarter turn in 0.25 s) posed for substeps of dt, and wavy
    hair grown on it: (collider at pose 0, strand model, the grown points). ragged: strands cut to
    5 to 12 particles, as a haircut leaves them."""
    moving = Collider("head", head.vertices, head.faces, head.skin_indices, head.skin_weights, head.num_bones, "cpu",
                      sphere_leaves=sphere_leaves)
    anim = HeadAnimation(turn_degrees=45.0, turn_period=1.0, nod_degrees=15.0, nod_period=0.8, ease_in=0.0)
    moving.set_poses(anim.bone_matrices(dt * np.arange(substeps + 1)))
    moving.apply_pose(0)
    roots, _, _, normals = sample_scalp(head.vertices, head.faces, head.scalp_faces, strands, seed=seed)
    pts, counts, widths = grow_hairstyle(HairstyleParams(style="wavy", vertices=12, length=0.2), roots, normals,
                                         moving.push_out)
    if ragged:
        keep = np.random.default_rng(seed).integers(5, 13, len(counts))
        starts = np.r_[0, np.cumsum(counts)[:-1]]
        rows = np.concatenate([start + np.arange(n) for start, n in zip(starts, keep, strict=True)])
        pts, counts, widths = pts[rows], keep, widths[rows]
    model = StrandBuilder().add_strands(pts, counts, widths).finalize("cpu").bind_to_mesh(moving.posed_points(),
                                                                                          head.faces)
    return moving, model, pts



@pytest.mark.parametrize("collision,shape_matching,passes,ragged", [
    ("sphere_tree", "simplified", 1, False), ("mesh", "full", 2, True), ("none", "simplified", 1, False)])
def test_a_frame_kept_in_lanes_gives_the_strands_of_the_fused_substeps(head, collision, shape_matching, passes,
                                                                        ragged):
    """HairSolver.frame_lanes: begin_frame copies the state into lane order, the fused substeps
    (strands.step_strands with lane_state) read and write only the lanes, and end_frame copies it
    back: at the end of every frame of five substeps, x and v bit for bit those of the fused substeps
    on the particle-order state, with the sphere tree's walks queued ahead from the lanes, on a
    turning head, for strands of one length and of many."""
    substeps, dt, frame = 20, 1.0 / 240.0, 5
    moving, model, _pts = _hair_on_a_turning_head(head, 256, substeps, dt, 40, 7, ragged=ragged)
    params = HairParams(collision=collision, shape_matching=shape_matching, shape_iterations=passes,
                        wind=(1.5, 0.0, 0.5), wind_turbulence=0.6)
    runs = []
    for kept in (False, True):
        solver = HairSolver(model, params, parts=1)
        solver.fused, solver.lanes, solver.leaves_ahead, solver.frame_lanes = True, True, True, kept
        s0, s1 = model.state(), model.state()
        moving.apply_pose(0)
        ends = []
        for k in range(1, substeps + 1):
            if k % frame == 1:
                solver.begin_frame(s0)
            moving.apply_pose(k)
            solver.step(s0, s1, moving, dt, time=k * dt)
            s0, s1 = s1, s0
            if k % frame == 0:
                solver.end_frame(s0)
                ends.append((s0.x.numpy().copy(), s0.v.numpy().copy()))
        assert solver._in_frame is False and (solver._frame is not None) == kept
        runs.append(ends)
    for (x, v), (x_kept, v_kept) in zip(*runs, strict=True):
        np.testing.assert_array_equal(x_kept, x)
        np.testing.assert_array_equal(v_kept, v)
    assert np.abs(runs[0][-1][1]).max() > 0.1  # the hair swung

@pytest.mark.parametrize("mode,ahead,lanes,lists", [
    ("sphere_tree", False, False, True), ("mesh", False, False, True), ("sphere_tree", True, False, True),
    ("sphere_tree", True, True, True), ("mesh", False, True, True), ("mesh", False, True, False)])
def test_contact_bounds_are_the_distance_and_skipping_queries_changes_nothing(head, head_collider, mode, ahead,
                                                                              lanes, lists):
    """ahead: the tree walks of the lists that run short made in a parallel pass first; lanes: the
    length pass in lane order; lists off: mesh queries through the BVH (all three a GPU's way), here
    on the CPU; the strands are the same as those of querying every particle in particle order."""
    import warp as wp

    from warp_kernels import collision

    c = head_collider
    rng = np.random.default_rng(4)
    surface, _ = trimesh.sample.sample_surface(trimesh.Trimesh(head.vertices, head.faces, process=False), 400, seed=3)
    points = (surface + rng.normal(0.0, 0.01, surface.shape)).astype(np.float32)
    out = wp.zeros(len(points), dtype=float)
    search, margin = 0.02, 0.0015
    code = {"sphere_tree": collision.COLLIDE_SPHERE_TREE, "mesh": collision.COLLIDE_MESH}[mode]
    wp.launch(collision.points_clearance, len(points),
              [wp.array(points, dtype=wp.vec3), int(code), c.shape, margin, search, out])
    got = out.numpy()
    if mode == "mesh":
        # the signed distance where the surface is within search; beyond, search
        truth = c.signed_distance(points)
        near = np.abs(truth) < search - 1e-4
        assert near.mean() > 0.8 and np.any(truth < -search)  # deep inside points are part of the test
        np.testing.assert_allclose(got[near], truth[near], atol=2e-5)
        np.testing.assert_allclose(got[np.abs(truth) > search + 1e-4], search)
    else:
        centers, radii = c.sphere_centers.numpy(), c.sphere_radii.numpy()
        leaf = c.tree.is_leaf == 1
        truth = np.min(np.linalg.norm(points[:, None] - centers[leaf][None], axis=2) - radii[leaf][None], axis=1)
        np.testing.assert_allclose(got, np.minimum(truth, search), atol=2e-5)

    # hair on a head turning and nodding fast (a quarter turn in 0.25 s), with and without the
    # contact bounds: the same strands, while most queries are skipped
    substeps, dt = 60, 1.0 / 240.0
    moving, model, pts = _hair_on_a_turning_head(head, 256 if mode == "sphere_tree" else 0, substeps, dt, 60, 2)
    results, skipped = [], []
    for use in (True, False):
        solver = HairSolver(model, HairParams(collision=mode), parts=1)
        solver.contact_bounds = use
        solver.leaves_ahead = ahead
        solver.lanes = lanes and use
        solver.mesh_lists = lists
        s0, s1 = model.state(), model.state()
        moving.apply_pose(0)
        kept, moved = 0, 0.0
        for k in range(1, substeps + 1):
            moving.apply_pose(k)
            moved = max(moved, float(np.linalg.norm(moving.points.numpy() - moving.prev_points.numpy(), axis=1).max()))
            solver.step(s0, s1, moving, dt)
            s0, s1 = s1, s0
            bounds = solver.particle_bounds()[0]
            kept += int(np.sum(bounds > margin + 1e-5))
            if use and mode == "sphere_tree":  # every bound is a lower bound of the distance where it is held
                x, leaf = s0.x.numpy().astype(np.float64), moving.tree.is_leaf == 1
                centers, radii = moving.sphere_centers.numpy()[leaf], moving.sphere_radii.numpy()[leaf]
                truth = np.min(np.linalg.norm(x[:, None] - centers[None], axis=2) - radii[None], axis=1)
                known = bounds > 0.5 * strand_kernels.NO_BOUND
                assert np.all(bounds[known] <= truth[known] + 1e-5)
        results.append(s0.x.numpy())
        skipped.append(kept / (substeps * model.num_particles))
    print(f"{mode}: {100 * skipped[0]:.0f}% of the bounds above the margin, head moved up to {1e3 * moved:.1f} mm per substep")
    np.testing.assert_array_equal(results[0], results[1])
    assert np.abs(results[0] - pts).max() > 0.01  # the hair fell and swung
    assert moved > 2e-3  # the head moved up to this much in one substep
    assert skipped[0] > 0.5  # over half the particles were clear of the head (their next query may be skipped)
    # and the hair stays out of the collider it was given
    if mode == "mesh":
        depth = -np.minimum(moving.signed_distance(results[0]), 0.0)
    else:
        depth = moving.sphere_tree_depth(results[0])
    print(f"deepest {1e3 * depth.max():.2f} mm")
    assert depth.max() < 1e-4


@pytest.mark.parametrize("collision,shape_matching,passes,order", [
    ("sphere_tree", "simplified", 1, "parts"), ("mesh", "full", 2, "parts"), ("none", "simplified", 2, "parts"),
    ("sphere_tree", "full", 3, "lanes"), ("mesh", "none", 1, "lanes"), ("sphere_tree", "simplified", 1, "lanes ahead"),
    ("mesh", "full", 2, "lanes ragged"), ("mesh", "simplified", 1, "lanes bvh"),
    ("sphere_tree", "simplified", 1, "lanes ahead read ahead"), ("mesh", "full", 1, "lanes bvh read ahead")])
def test_one_launch_substep_gives_the_same_strands_as_the_launches_apart(head, collision, shape_matching, passes,
                                                                        order):
    """strands.step_strands (HairSolver.fused) against root_frames, predict_positions, the shape passes
    and follow_the_leader launched apart, in gusting wind on a turning head: every substep's x and v
    bit for bit, the full variant's warm-started rotations too, over two strand ranges or in lane order,
    and with the tree walks queued ahead (a GPU's way: from the start positions when fused), on
    strands of different lengths (lane slots past a strand's tip), and with the mesh queried through
    its BVH instead of the lists of nearest faces (bvh, a GPU's way), and with the length pass reading
    each particle's inputs a particle ahead (HairSolver.read_ahead)."""
    substeps, dt = 30, 1.0 / 240.0
    moving, model, pts = _hair_on_a_turning_head(head, 256, substeps, dt, 40, 11, ragged=order.endswith("ragged"))
    if order.endswith("ragged"):
        assert len(set(np.diff(model.strand_start_np))) > 3
    params = HairParams(collision=collision, shape_matching=shape_matching, shape_iterations=passes,
                        wind=(1.5, 0.0, 0.5), wind_turbulence=0.6)
    runs = []
    for fused in (False, True):
        solver = HairSolver(model, params, parts=1 if order.startswith("lanes") else 2)
        solver.leaves_ahead = "lanes ahead" in order
        solver.lanes = order.startswith("lanes")
        solver.mesh_lists = "bvh" not in order
        solver.read_ahead = order.endswith("read ahead")
        solver.fused = fused
        s0, s1 = model.state(), model.state()
        moving.apply_pose(0)
        frames = []
        for k in range(1, substeps + 1):
            moving.apply_pose(k)
            for part in solver.parts:
                solver.step(s0, s1, moving, dt, time=k * dt, part=part)
            s0, s1 = s1, s0
            frames.append((s0.x.numpy().copy(), s0.v.numpy().copy(), solver.rotations.numpy().copy()))
        runs.append(frames)
    for (x, v, q), (x_fused, v_fused, q_fused) in zip(*runs, strict=True):
        np.testing.assert_array_equal(x_fused, x)
        np.testing.assert_array_equal(v_fused, v)
        np.testing.assert_array_equal(q_fused, q)
    x, v, _ = runs[0][-1]
    assert np.abs(x - pts).max() > 0.01 and np.abs(v).max() > 0.1  # the hair swung
    if collision != "none":  # free particles lie on the head, and none inside it
        free = model.inv_mass.numpy() > 0.0
        depth = moving.sphere_tree_depth(x) if collision == "sphere_tree" else -np.minimum(moving.signed_distance(x), 0)
        assert depth.max() < 1e-4
        assert np.sum(moving.signed_distance(x[free]) < 3e-3) > 10


@pytest.mark.parametrize("shape_matching,passes", [("none", 1), ("simplified", 1), ("full", 2)])
def test_lane_order_gives_the_same_strands_and_velocities(head, shape_matching, passes):
    """The length pass in lane order reads what to_lanes copies there and from_lanes copies its
    positions and velocities back: every substep's x and v are those of particle order, bit for
    bit."""
    substeps, dt = 30, 1.0 / 240.0
    moving, model, pts = _hair_on_a_turning_head(head, 256, substeps, dt, 30, 7)
    params = HairParams(collision="sphere_tree", shape_matching=shape_matching, shape_iterations=passes)
    runs = []
    for lanes in (False, True):
        solver = HairSolver(model, params, parts=1)
        solver.leaves_ahead = True
        solver.lanes = lanes
        if lanes:  # neighbouring roots in neighbouring lanes, not the grown order
            assert np.any(solver._lanes.order.strand_of.numpy() != np.arange(model.num_strands))
        s0, s1 = model.state(), model.state()
        moving.apply_pose(0)
        frames = []
        for k in range(1, substeps + 1):
            moving.apply_pose(k)
            solver.step(s0, s1, moving, dt)
            s0, s1 = s1, s0
            frames.append((s0.x.numpy().copy(), s0.v.numpy().copy()))
        runs.append(frames)
    for (x, v), (x_lanes, v_lanes) in zip(*runs, strict=True):
        np.testing.assert_array_equal(x_lanes, x)
        np.testing.assert_array_equal(v_lanes, v)
    x, v = runs[0][-1]
    assert np.abs(x - pts).max() > 0.01 and np.abs(v).max() > 0.1  # the hair swung


@pytest.mark.parametrize("fused", [False, True])
def test_the_loose_length_pass_keeps_the_strands_outside_the_head_within_the_margin_of_the_exact_one(head,
                                                                                                   monkeypatch,
                                                                                                   fused):
    """HairSolver.loose_lists, a GPU's way run on the CPU with the lists made ahead, in the launches
    apart (lane order) or fused: the loose pass (strands.FOLLOW_THE_LEADER_LOOSE, STEP_STRANDS_LOOSE)
    is the one launched; after every substep on the turning head no free particle is inside a leaf
    sphere, and every particle lies within the margin of where the exact pass puts it. Without the
    lists made ahead, or fused with full shape matching, it is refused."""
    import warp as wp

    substeps, dt = 30, 1.0 / 240.0
    moving, model, pts = _hair_on_a_turning_head(head, 256, substeps, dt, 60, 7)
    params = HairParams(collision="sphere_tree", shape_matching="simplified", shape_iterations=1)
    free = model.inv_mass.numpy() > 0.0
    launched, launch = [], wp.launch

    def spy(kernel, *args, **kwargs):
        launched.append(kernel)
        return launch(kernel, *args, **kwargs)

    monkeypatch.setattr(wp, "launch", spy)
    runs = []
    for loose in (False, True):
        solver = HairSolver(model, params, parts=1)
        solver.fused, solver.leaves_ahead, solver.lanes, solver.loose_lists = fused, True, not fused, loose
        s0, s1 = model.state(), model.state()
        moving.apply_pose(0)
        launched.clear()
        frames = []
        for k in range(1, substeps + 1):
            moving.apply_pose(k)
            solver.step(s0, s1, moving, dt)
            s0, s1 = s1, s0
            x = s0.x.numpy().copy()
            frames.append(x)
            if loose:
                assert moving.sphere_tree_depth(x[free]).max() < 1e-6
        lists = strand_kernels.PATHS_SPHERE_LISTS
        kernel = (strand_kernels.STEP_STRANDS_LOOSE[(lists, True)] if fused
                  else strand_kernels.FOLLOW_THE_LEADER_LOOSE[lists])
        assert (kernel in launched) == loose
        runs.append(np.array(frames))
    exact, loose = runs
    assert np.abs(loose - exact).max() <= params.collision_margin
    assert np.abs(exact[-1] - pts).max() > 0.01  # the hair swung
    solver.leaves_ahead = False
    with pytest.raises(ValueError, match="lists made ahead"):
        solver.step(s0, s1, moving, dt)
    if fused:
        full = HairSolver(model, HairParams(collision="sphere_tree", shape_matching="full"), parts=1)
        full.leaves_ahead, full.loose_lists = True, True
        with pytest.raises(ValueError, match="simplified shape matching"):
            full.step(s0, s1, moving, dt)


def test_a_gpus_length_pass_gives_every_multiprocessor_a_block_where_the_strands_allow(monkeypatch):
    """hair_solver.strand_block: Warp's 256 lanes on the CPU and for many strands; on a GPU of 132 SMs
    (an H100) fewer lanes per block, in whole warps, so that 1k or 10k strands reach more of its SMs."""
    import warp as wp

    from sim import hair_solver

    assert hair_solver.strand_block(1000, "cpu") == 256

    class H100:
        is_cuda, sm_count = True, 132

    monkeypatch.setattr(wp, "get_device", lambda device=None: H100())
    blocks = {n: hair_solver.strand_block(n, "cuda") for n in (1000, 10000, 20000, 100000)}
    assert blocks == {1000: 32, 10000: 64, 20000: 128, 100000: 256}
    for n, lanes in blocks.items():
        assert lanes % 32 == 0 and (-(-n // lanes) >= 132 or lanes == 32)  # every SM a block, or one warp each


@pytest.mark.parametrize("lanes,fused", [(False, False), (True, False), (False, True), (True, True)])
def test_leaves_ahead_lists_the_nearest_leaves_where_the_length_pass_would_run_short(head, monkeypatch, lanes, fused):
    """find_short_lists and list_leaves_ahead, caught around their launches on a turning head: a particle whose bounds,
    lowered as follow_the_leader lowers them (a NumPy reference of the motion grid), come within
    slack of the margin at its predicted position gets the four leaves nearest its start position
    carried into the new pose, and that point's distances as its bounds (a float64 reference over all
    leaves); every other particle keeps its bounds and list. lanes: the same in lane order. fused:
    before strands.step_strands, from the start positions (in particle order) with the wider slack."""
    import warp as wp

    from sim import hair_solver

    substeps, dt = 24, 1.0 / 240.0
    moving, model, _ = _hair_on_a_turning_head(head, 256, substeps, dt, 40, 5)
    params = HairParams(collision="sphere_tree")
    solver = HairSolver(model, params, parts=1)
    solver.leaves_ahead = True
    solver.lanes = lanes
    solver.fused = fused
    seen, launch = [], wp.launch
    order = solver._lanes.slot if lanes else np.arange(model.num_particles)  # each particle's element
    positions = np.arange(model.num_particles) if fused else order  # ... of the positions queued from

    queued = []

    def spy(kernel, dim, inputs=(), *args, **kwargs):
        if kernel is strand_kernels.find_short_lists:
            # copies: on the CPU numpy() views the array, which the length pass goes on to change
            queued.append((inputs[0].numpy()[positions].astype(np.float64),
                           inputs[1].numpy()[positions].astype(np.float64),
                           [solver.clearance.numpy()[order], solver.near_leaves.numpy()[order],
                            solver.beyond.numpy()[order]]))
        if kernel is not strand_kernels.list_leaves_ahead:
            return launch(kernel, dim, inputs, *args, **kwargs)
        launch(kernel, dim, inputs, *args, **kwargs)
        motion = inputs[1].motion  # the strands.StrandContact
        x, x_prev, before = queued.pop()
        seen.append((x, x_prev, before, [solver.clearance.numpy()[order], solver.near_leaves.numpy()[order],
                                         solver.beyond.numpy()[order]], motion.rigid.numpy()[0].astype(np.float64),
                     motion.center.numpy()[0].astype(np.float64),
                     motion.cells.numpy().astype(np.float64) * strand_kernels.MOTION_UNIT,
                     moving.sphere_centers.numpy().astype(np.float64)))

    monkeypatch.setattr(wp, "launch", spy)
    s0, s1 = model.state(), model.state()
    for k in range(1, substeps + 1):
        moving.apply_pose(k)
        solver.step(s0, s1, moving, dt)
        s0, s1 = s1, s0
    assert len(seen) == substeps
    radii = moving.sphere_radii.numpy().astype(np.float64)
    leaf = np.flatnonzero(moving.tree.is_leaf == 1)
    free = np.arange(model.num_particles) - model.strand_start_np[model.particle_strand_np] >= model.pinned_per_strand
    margin, search = params.collision_margin, params.collision_search
    slack = hair_solver.FUSED_LIST_SLACK if fused else hair_solver.LIST_SLACK
    reach, grid = solver.reach, strand_kernels.MOTION_GRID
    half = reach + search
    listed_total = 0
    for x, x_prev, before, after, rigid, center, cells, centers in seen:
        carried = x_prev @ rigid[:3, :3].T + rigid[:3, 3]
        cell = np.clip(np.floor((x - center + half) * grid / (2.0 * half)).astype(int), 0, grid - 1)
        near = cells[(cell[:, 0] * grid + cell[:, 1]) * grid + cell[:, 2]]
        lowered = np.linalg.norm(x - carried, axis=1) + near
        known = before[0] > 0.5 * strand_kernels.NO_BOUND
        within = np.linalg.norm(x - center, axis=1) <= reach
        short = free & within & (~known | ((before[0] - lowered <= margin + slack) &
                                           (before[2] - lowered <= margin + slack)))
        # the kernel's float32 arithmetic decides the cases this close to the threshold
        edge = known & (np.abs(np.minimum(before[0], before[2]) - lowered - margin - slack) < 1e-6)
        dist = np.linalg.norm(carried[short][:, None] - centers[leaf][None], axis=2) - radii[leaf][None]
        ranked = np.sort(dist, axis=1)
        got_short = ~edge[short]
        np.testing.assert_allclose(after[0][short][got_short], np.minimum(ranked[:, 0], search)[got_short], atol=2e-5)
        np.testing.assert_allclose(after[2][short][got_short], np.minimum(ranked[:, 4], search)[got_short], atol=2e-5)
        # the four nearest within search, ascending node indices, -1 after them
        order = np.argsort(dist, axis=1)[:, :4]
        nearest4 = np.where(np.take_along_axis(dist, order, axis=1) < search, leaf[order], np.iinfo(np.int32).max)
        nearest4 = np.sort(nearest4, axis=1)
        nearest4[nearest4 == np.iinfo(np.int32).max] = -1
        np.testing.assert_array_equal(after[1][short][got_short], nearest4[got_short])
        kept = ~short & ~edge
        for b, a in zip(before, after, strict=True):
            np.testing.assert_array_equal(a[kept], b[kept])
        listed_total += np.count_nonzero(short)
    assert 0 < listed_total < 0.5 * substeps * np.count_nonzero(free)


@functools.cache
def _listed_queries():
    """Kernels around collision.sphere_tree_nearest, collide_point_listed and collide_point_listed_loose,
    for the tests below (made once)."""
    import warp as wp

    from warp_kernels import collision

    @wp.kernel
    def nearest(points: wp.array(dtype=wp.vec3), shape: collision.ColliderShape, search: float,
                leaves: wp.array(dtype=wp.vec4i), first: wp.array(dtype=float), fifth: wp.array(dtype=float)):
        i = wp.tid()
        listed, d1, d5 = collision.sphere_tree_nearest(points[i], shape, search)
        leaves[i] = listed
        first[i] = d1
        fifth[i] = d5

    @wp.kernel
    def listed(points: wp.array(dtype=wp.vec3), origins: wp.array(dtype=wp.vec3), leaves: wp.array(dtype=wp.vec4i),
               beyond: wp.array(dtype=float), shape: collision.ColliderShape, margin: float, search: float,
               out: wp.array(dtype=wp.vec3), tree: wp.array(dtype=wp.vec3), kept: wp.array(dtype=int)):
        i = wp.tid()
        pushed, _d, _leaves, origin, _beyond = collision.collide_point_listed(points[i], shape, margin, search,
                                                                               leaves[i], origins[i], beyond[i])
        out[i] = pushed
        tree[i] = collision.collide_point(points[i], collision.COLLIDE_SPHERE_TREE, shape, margin, search)
        kept[i] = int(origin == origins[i])

    @wp.kernel
    def loose(points: wp.array(dtype=wp.vec3), origins: wp.array(dtype=wp.vec3), leaves: wp.array(dtype=wp.vec4i),
              beyond: wp.array(dtype=float), shape: collision.ColliderShape, margin: float, search: float,
              out: wp.array(dtype=wp.vec3), distance: wp.array(dtype=float), exact: wp.array(dtype=wp.vec3),
              kept: wp.array(dtype=int)):
        i = wp.tid()
        pushed, d, _leaves, origin, _beyond = collision.collide_point_listed_loose(points[i], shape, margin, search,
                                                                                  leaves[i], origins[i], beyond[i])
        out[i] = pushed
        distance[i] = d
        kept[i] = int(origin == origins[i])
        q, _d2, _leaves2, _origin2, _beyond2 = collision.collide_point_listed(points[i], shape, margin, search,
                                                                             leaves[i], origins[i], beyond[i])
        exact[i] = q

    return nearest, listed, loose


def _lists_near(head, collider, count, seed, rng, search):
    """Points about 4 mm from the head's surface (float32) and the leaf lists made there
    (sphere_tree_nearest): (points, lists, nearest distance, fifth distance), the last three as Warp arrays."""
    import warp as wp

    nearest = _listed_queries()[0]
    surface, _ = trimesh.sample.sample_surface(trimesh.Trimesh(head.vertices, head.faces, process=False), count,
                                               seed=seed)
    origins = (surface + rng.normal(0.0, 0.004, surface.shape)).astype(np.float32)
    n = len(origins)
    leaves, first, fifth = wp.zeros(n, dtype=wp.vec4i), wp.zeros(n, dtype=float), wp.zeros(n, dtype=float)
    wp.launch(nearest, n, [wp.array(origins, dtype=wp.vec3), collider.shape, search, leaves, first, fifth])
    return origins, leaves, first, fifth


def test_listed_leaves_are_the_nearest_and_resolve_points_as_the_tree_does(head, head_collider):
    """sphere_tree_nearest lists the four leaves nearest a point and the fifth one's distance (a float64
    reference over all leaves); a point about 2 mm from where its list was made, resolved through
    the list, lands exactly where the tree's own sweeps put it, and the list is kept for most points."""
    import warp as wp

    _nearest, listed, _loose = _listed_queries()
    c = head_collider
    rng = np.random.default_rng(8)
    search, margin = 0.02, 0.0015
    origins, leaves, first, fifth = _lists_near(head, c, 500, 4, rng, search)
    n = len(origins)
    centers, radii = c.sphere_centers.numpy().astype(np.float64), c.sphere_radii.numpy().astype(np.float64)
    leaf = np.flatnonzero(c.tree.is_leaf == 1)
    dist = np.linalg.norm(origins[:, None].astype(np.float64) - centers[leaf][None], axis=2) - radii[leaf][None]
    order = np.argsort(dist, axis=1)
    ranked = np.take_along_axis(dist, order, axis=1)
    got = leaves.numpy()
    for i in range(n):
        within = ranked[i, :4] < search
        expected = np.sort(leaf[order[i, :4]][within])
        np.testing.assert_array_equal(got[i][:len(expected)], expected)
        assert np.all(got[i][len(expected):] == -1)
    np.testing.assert_allclose(first.numpy(), np.minimum(ranked[:, 0], search), atol=2e-6)
    np.testing.assert_allclose(fifth.numpy(), np.minimum(ranked[:, 4], search), atol=2e-6)
    assert np.mean(ranked[:, 0] < margin) > 0.2  # many points are pushed, some out of two leaves or more

    moved = (origins + rng.normal(0.0, 0.001, origins.shape)).astype(np.float32)
    out, tree, kept = wp.zeros(n, dtype=wp.vec3), wp.zeros(n, dtype=wp.vec3), wp.zeros(n, dtype=int)
    wp.launch(listed, n, [wp.array(moved, dtype=wp.vec3), wp.array(origins, dtype=wp.vec3), leaves, fifth, c.shape,
                          margin, search, out, tree, kept])
    np.testing.assert_array_equal(out.numpy(), tree.numpy())
    assert np.mean(np.any(tree.numpy() != moved, axis=1)) > 0.3  # many points were pushed
    assert 0.55 < kept.numpy().mean() < 1.0  # most lists served; the others were refilled from the tree


def test_a_loose_list_walks_only_where_the_point_may_be_inside_a_leaf_it_does_not_hold(head, head_collider):
    """collide_point_listed_loose (the length pass of HairSolver.loose_lists): lists made at points near
    the head and asked 1.5 mm away. Where the list's bound at the point is at or below zero (an
    unlisted leaf may contain it) or a push leaves the list's zone, it walks and answers as
    collide_point_listed, bit for bit; where the bound lies between zero and the margin it keeps its
    list, pushes with the listed leaves only, and leaves the point outside every leaf (a float64
    reference over all leaves), within the margin of the exact answer, with a distance at most the
    margin, so that the next list is made afresh."""
    import warp as wp

    _nearest, _listed, loose = _listed_queries()
    c = head_collider
    rng = np.random.default_rng(9)
    search, margin = 0.02, 0.0015
    origins, leaves, _first, fifth = _lists_near(head, c, 2000, 5, rng, search)
    n = len(origins)
    step = rng.normal(size=origins.shape)
    moved = (origins + 0.0015 * step / np.linalg.norm(step, axis=1, keepdims=True)).astype(np.float32)
    out, exact = wp.zeros(n, dtype=wp.vec3), wp.zeros(n, dtype=wp.vec3)
    distance, kept = wp.zeros(n, dtype=float), wp.zeros(n, dtype=int)
    wp.launch(loose, n, [wp.array(moved, dtype=wp.vec3), wp.array(origins, dtype=wp.vec3), leaves, fifth, c.shape,
                         margin, search, out, distance, exact, kept])
    out, exact, distance, kept = out.numpy(), exact.numpy(), distance.numpy(), kept.numpy().astype(bool)
    bound = fifth.numpy().astype(np.float64) - np.linalg.norm((moved - origins).astype(np.float64), axis=1)
    walked = ~kept
    np.testing.assert_array_equal(out[walked], exact[walked])
    assert np.all(walked[bound <= 0.0])  # an unlisted leaf may contain the point: it walks
    spared = kept & (bound <= margin)  # short lists the exact pass walks for and the loose one keeps
    assert spared.sum() > 20
    centers, radii = c.sphere_centers.numpy().astype(np.float64), c.sphere_radii.numpy().astype(np.float64)
    leaf = np.flatnonzero(c.tree.is_leaf == 1)
    inside = radii[leaf][None] - np.linalg.norm(out[spared][:, None].astype(np.float64) - centers[leaf][None], axis=2)
    assert inside.max() < 1e-6  # outside every leaf, listed or not
    assert np.abs(out[spared] - exact[spared]).max() <= margin + 1e-6
    assert np.all(distance[spared] <= margin + 1e-6)
    true = np.linalg.norm(moved[kept][:, None].astype(np.float64) - centers[leaf][None], axis=2) - radii[leaf][None]
    assert np.all(distance[kept] <= true.min(axis=1) + 1e-6)  # a lower bound before the push


def test_visibility_from_an_eye_matches_the_sphere_it_sees():
    """Points 2 mm above a sphere of radius R = 0.1 seen from D = 1 m away: a point is seen while its
    sight line clears the ball, i.e. up to the angle from the eye direction where that line is
    tangent, acos(R / D) + acos(R / r); points behind the occluder are hidden whatever their distance."""
    from sim.collider import Collider

    sphere = trimesh.creation.icosphere(5, radius=0.1)
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    collider = Collider("ball", v, f, np.tile([1, 0, 0, 0], (len(v), 1)), np.tile([1.0, 0, 0, 0], (len(v), 1)), 2,
                        sphere_leaves=0)
    eye = np.array([0.0, 0.0, 1.0])
    rng = np.random.default_rng(3)
    d = rng.normal(size=(4000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    points = 0.102 * d  # just outside the tessellated surface, like hair roots
    seen = collider.visible_from(points, eye)
    cosine = d[:, 2]
    limit = np.cos(np.arccos(0.1 / 1.0) + np.arccos(0.1 / 0.102))
    clear = np.abs(cosine - limit) > 0.02  # away from the grazing rim, where tessellation decides
    np.testing.assert_array_equal(seen[clear], (cosine > limit)[clear])
    behind = np.array([[0.0, 0.0, -0.3], [0.05, 0.0, -0.2], [0.0, 0.02, -1.5]])
    assert not collider.visible_from(behind, eye).any()
    assert collider.visible_from([[0.5, 0.0, 0.0], [0.0, 0.0, 0.5]], eye).all()


def test_contact_motion_follows_the_anchor_and_counts_only_the_collider_near_the_hair():
    """A head (bone 0) with hair and a hand (bone 1). The head's rigid motion is undone, so it moves
    nothing; the hand counts only once it comes within the hair's reach (NumPy float64 reference of
    the rule); and a hand sweeping through the hair from afar leaves the strands bit-identical to
    querying every particle."""
    from sim.collider import Collider

    head_v, head_f = (np.asarray(a) for a in (trimesh.creation.icosphere(3, radius=0.1).vertices,
                                               trimesh.creation.icosphere(3, radius=0.1).faces))
    hand = trimesh.creation.icosphere(2, radius=0.05)
    v = np.concatenate([head_v, np.asarray(hand.vertices) + [0.8, 0.0, 0.0]])
    f = np.concatenate([head_f, np.asarray(hand.faces) + len(head_v)])
    bone = np.r_[np.zeros(len(head_v), int), np.ones(len(hand.vertices), int)]
    skin = np.zeros((len(v), 4), int)
    skin[:, 0] = bone
    weights = np.tile([1.0, 0.0, 0.0, 0.0], (len(v), 1))
    collider = Collider("body", v, f, skin, weights, 2, "cpu", sphere_leaves=0)

    def pose(angle, head_shift, hand_shift):
        c, s = np.cos(angle), np.sin(angle)
        b = np.tile(np.eye(4), (2, 1, 1))
        b[0, :2, :2] = [[c, -s], [s, c]]
        b[0, :3, 3], b[1, :3, 3] = head_shift, hand_shift
        return b

    # the hand far away, then brought next to the hair, then swept through it and out again
    hand_path = [[0.0, 0.0, 0.0], [0.0, 0.3, 0.0]] + [[x - 0.8, 0.2, 0.0] for x in np.linspace(0.2, -0.3, 40)]
    poses = np.array([pose(0.02 * k, [0.002 * k, 0.0, 0.0], h) for k, h in enumerate(hand_path)])
    collider.set_poses(poses)
    collider.apply_pose(0)
    rng = np.random.default_rng(4)
    up = rng.normal(size=(40, 3)) * [0.4, 0.0, 0.4] + [0.0, 1.0, 0.0]
    up /= np.linalg.norm(up, axis=1, keepdims=True)
    pts = (0.1 * up[:, None] + 0.001 * up[:, None] + 0.02 * np.arange(8)[None, :, None] * up[:, None]).reshape(-1, 3)
    model = StrandBuilder().add_strands(pts, np.full(40, 8), np.full(40 * 8, 1e-4)).finalize("cpu").bind_to_mesh(
        collider.posed_points(), f)
    params = HairParams(collision="mesh", gravity=(0.0, 0.0, 0.0))
    results = []
    for use in (True, False):
        solver = HairSolver(model, params)
        solver.contact_bounds = use
        s0, s1 = model.state(), model.state()
        collider.apply_pose(0)
        for k in range(1, len(poses)):
            before = collider.points.numpy().astype(np.float64)
            collider.apply_pose(k)
            solver.step(s0, s1, collider, 1.0 / 240.0)
            s0, s1 = s1, s0
            if not use:
                continue
            moved, rigid, center = solver.contact_motion()
            after = collider.points.numpy().astype(np.float64)
            turn = poses[k, 0] @ np.linalg.inv(poses[k - 1, 0])
            np.testing.assert_allclose(rigid, turn, atol=2e-6)  # the head bone's own motion
            # the rule in float64: a vertex counts when one of its edges reaches within reach + search
            reach, search = solver.reach, params.collision_search
            edge = np.zeros(len(after))
            for a, b in ((0, 1), (1, 2), (2, 0)):
                length = np.linalg.norm(after[f[:, a]] - after[f[:, b]], axis=1)
                np.maximum.at(edge, f[:, a], length)
                np.maximum.at(edge, f[:, b], length)
            near = np.linalg.norm(after - center, axis=1) - reach - search - edge <= 0.0
            relative = np.linalg.norm(after - (before @ turn[:3, :3].T + turn[:3, 3]), axis=1)
            expected = relative[near].max()
            assert abs(moved - expected) < 2e-6
            # and per cell of the grid around the anchor: a vertex raises the cells within search +
            # its longest edge of it
            grid = strand_kernels.MOTION_GRID
            half = reach + search
            size = 2.0 * half / grid
            cells = np.zeros((grid,) * 3)
            for q, m, e in zip(after[near], relative[near], edge[near]):
                lo, hi = q - search - e, q + search + e
                if m <= 0.0 or np.any(hi < center - half) or np.any(lo > center + half):
                    continue
                a, b = (np.clip(np.floor((x - center + half) / size).astype(int), 0, grid - 1) for x in (lo, hi))
                block = cells[a[0]:b[0] + 1, a[1]:b[1] + 1, a[2]:b[2] + 1]
                np.maximum(block, m, out=block)
            got = solver.motion_cells().reshape(cells.shape)
            np.testing.assert_allclose(got, cells, atol=2e-6)
            assert got.max() == pytest.approx(moved, abs=2e-6)
            if k == 3:  # the hand beside the hair raises only the cells near it
                assert 0.0 < np.mean(got > 0.0) < 0.5
            if k == 1:  # the hand moved 30 cm but far away; the head turned rigidly
                assert near[len(head_v):].sum() == 0 and moved < 1e-5
                assert np.linalg.norm(after - before, axis=1)[: len(head_v)].max() > 1e-3
            if k == 3:
                assert near[len(head_v):].all() and moved > 0.01
        results.append(s0.x.numpy())
    np.testing.assert_array_equal(results[0], results[1])
    assert np.abs(results[0] - model.rest_positions_np).max() > 0.02  # the hand pushed the hair aside


@pytest.mark.slow
def test_hair_on_a_walking_body_skips_queries_by_the_motion_near_it_and_steps_the_same_strands():
    """Long hair on the walking body colliding with its sphere tree: the shoulders move under the
    ends while the crown rides the head, so the motion grid charges the cells near the shoulders
    only. The strands equal querying every particle bit for bit, with fewer tree queries than one
    maximum over the whole collider would allow."""
    from sim.scene import Scene, demo_scene

    config = demo_scene({"scene": {"device": "cpu", "fps": 60.0, "preroll": 0.0, "stats": False},
                         "face": {"enabled": False}, "cloth": {"enabled": False},
                         "hair": {"count": 150, "vertices": 16},
                         "solver": {"substeps": 4, "collision": "sphere_tree"}})
    results, spread = [], []
    for use in (True, False):
        scene = Scene(config)
        scene.solver.contact_bounds = use
        scene.advance(0.25)  # into the stride
        for _ in range(15):
            scene.advance(1.0 / 60.0)
            if use:  # one measure per substep serves every range of strands
                cells = scene.solver.motion_cells()
                moved, _, _ = scene.solver.contact_motion()
                assert cells.max() == pytest.approx(moved, abs=1e-7)
                spread.append((np.mean(cells > 0.0), np.mean(cells < 0.5 * moved)))
        results.append(scene.state.x.numpy())
    np.testing.assert_array_equal(results[0], results[1])
    charged, below_half = np.mean(spread, axis=0)
    assert 0.0 < charged < 0.5 and below_half > 0.5  # most of the grid is charged less than the maximum


def test_signed_distance_re_signs_points_a_self_intersecting_pose_puts_inside_by_mistake():
    # a ball and, outside it, a small ball wound inside out: the shape a skinned limb folding into
    # itself leaves, where the closest face's normal points away from points that are outside
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    fold = trimesh.creation.icosphere(subdivisions=2, radius=0.05)
    v = np.concatenate([ball.vertices, fold.vertices + [0.5, 0.0, 0.0]])
    f = np.concatenate([ball.faces, fold.faces[:, ::-1] + len(ball.vertices)])
    weights = np.zeros((len(v), 4))
    weights[:, 0] = 1.0
    body = Collider("folded", v, f, np.zeros((len(v), 4), np.int32), weights, 1, "cpu", sphere_leaves=0)
    body.set_poses(np.eye(4)[None, None])
    body.apply_pose(0)
    rng = np.random.default_rng(0)
    u = rng.normal(size=(40, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    around_fold = [0.5, 0.0, 0.0] + 0.06 * u  # 1 cm outside the small ball: outside the body
    inside_ball = 0.25 * u  # 5 cm inside the ball
    d = body.signed_distance(np.concatenate([around_fold, inside_ball]))
    np.testing.assert_allclose(d[:40], 0.01, atol=2e-3)
    np.testing.assert_allclose(d[40:], -0.05, atol=2e-3)
    # the pseudo-normal alone calls the first ones inside
    assert np.all(signed_distance(around_fold, body.fresh_mesh())[0] < 0.0)


def test_signed_distance_in_slices_on_the_cores_equals_one_launch(head, head_collider, monkeypatch):
    import warp as wp

    import sim.graphs
    import sim.sphere_tree
    from warp_kernels import collision

    rng = np.random.default_rng(5)
    points = (head.vertices[rng.integers(0, len(head.vertices), 1000)] + rng.normal(0.0, 0.02, (1000, 3)))
    mesh = head_collider.fresh_mesh()
    pts = wp.array(points.astype(np.float32), dtype=wp.vec3)
    dist, closest = wp.zeros(1000, dtype=float), wp.zeros(1000, dtype=wp.vec3)
    wp.launch(collision.mesh_signed_distance, 1000, [pts, mesh.id, 0.03, 0, dist, closest])
    monkeypatch.setattr(sim.sphere_tree, "POINTS_PER_SLICE", 100)
    monkeypatch.setattr(sim.graphs, "cpu_cores", lambda: 3)  # three slices, whatever this machine has
    calls = []
    run = sim.graphs.run_on_cores
    monkeypatch.setattr(sim.graphs, "run_on_cores", lambda launches: calls.append(len(launches)) or run(launches))
    got, got_closest = signed_distance(points, mesh, max_dist=0.03)
    assert calls == [3]
    np.testing.assert_array_equal(got, dist.numpy())
    np.testing.assert_array_equal(got_closest, closest.numpy())
    assert np.any(got < 0.0) and np.any((got > 0.0) & (got < 0.03)) and np.any(got == np.float32(0.03))


def test_listed_faces_answer_as_the_bvh_query_does(head, head_collider):
    """Mesh queries through a list of the nearest faces (collide_point_listed_mesh): the push and the
    signed distance of the BVH's query (mesh_push_out), to rounding, for points outside, inside and
    beyond the query's reach; and a list gathered at a nearby point, where it decides, gives the
    fresh list's answer bit for bit (so lists kept between steps change nothing)."""
    import warp as wp

    from warp_kernels import collision

    @wp.kernel
    def resolve(points: wp.array(dtype=wp.vec3), listed_at: wp.array(dtype=wp.vec3), mesh: wp.uint64, margin: float,
                search: float, pushed: wp.array(dtype=wp.vec3), distance: wp.array(dtype=float),
                bvh_pushed: wp.array(dtype=wp.vec3), bvh_distance: wp.array(dtype=float),
                kept_pushed: wp.array(dtype=wp.vec3), kept_distance: wp.array(dtype=float),
                kept: wp.array(dtype=wp.int32), fresh: wp.array(dtype=wp.int32)):
        i = wp.tid()
        p = points[i]
        faces, fifth = collision.mesh_nearest_faces(p, mesh, search)
        _q, _d, decided = collision.listed_faces_push_out(p, mesh, margin, search, faces, fifth)
        fresh[i] = wp.where(decided, 1, 0)  # the list answered, not the BVH
        none = wp.vec4i(-1, -1, -1, -1)
        q, d, _faces, _origin, _beyond = collision.collide_point_listed_mesh(p, mesh, margin, search, search, none,
                                                                              p, -1.0e30)
        pushed[i] = q
        distance[i] = d
        q, d = collision.mesh_push_out(p, mesh, margin, search)
        bvh_pushed[i] = q
        bvh_distance[i] = d
        # a list made 3 mm away, then asked at p
        o = listed_at[i]
        faces, fifth = collision.mesh_nearest_faces(o, mesh, search)
        q, d, decided = collision.listed_faces_push_out(p, mesh, margin, search, faces, fifth - wp.length(p - o))
        kept_pushed[i] = q
        kept_distance[i] = d
        kept[i] = wp.where(decided, 1, 0)

    rng = np.random.default_rng(11)
    surface, _ = trimesh.sample.sample_surface(trimesh.Trimesh(head.vertices, head.faces, process=False), 600, seed=7)
    points = (surface + rng.normal(0.0, 0.006, surface.shape)).astype(np.float32)
    step = rng.normal(size=points.shape)
    listed_at = (points + 0.003 * step / np.linalg.norm(step, axis=1, keepdims=True)).astype(np.float32)
    margin, search = 0.0015, 0.01
    arr = lambda a, t: wp.array(a, dtype=t)  # noqa: E731
    out = [wp.zeros(len(points), dtype=t) for t in (wp.vec3, float) * 3 + (wp.int32, wp.int32)]
    wp.launch(resolve, len(points), [arr(points, wp.vec3), arr(listed_at, wp.vec3), head_collider.mesh.id, margin,
                                     search, *out])
    pushed, distance, bvh_pushed, bvh_distance, kept_pushed, kept_distance, kept, fresh = (a.numpy() for a in out)
    truth = head_collider.signed_distance(points)
    assert np.mean(truth < 0.0) > 0.2 and np.mean(truth > margin) > 0.2 and np.any(np.abs(truth) > search)
    near = np.abs(truth) < search - 1e-4
    assert fresh[near].mean() > 0.95  # within reach a fresh list answers (the BVH only where five faces tie)
    np.testing.assert_allclose(distance, bvh_distance, atol=2e-6)
    # a point inside whose nearest point lies on an edge goes out along either face's normal: the
    # BVH takes the face its walk met first, the list the lower face index; both are margin from
    # the same nearest point
    apart = np.linalg.norm(pushed - bvh_pushed, axis=1)
    tie = apart > 2e-6
    assert tie.mean() < 0.01 and np.all(truth[tie] < 0.0) and np.all(apart[tie] <= 2.0 * margin)
    moved = np.linalg.norm(pushed - points, axis=1) > 0.0
    assert moved.mean() > 0.2  # inside and within the margin: pushed
    # the kept lists decide for some points (a list lasts while the points move less than the gap
    # to the fifth face), and where they do they answer as the fresh ones
    decided = kept == 1
    assert decided.mean() > 0.2
    np.testing.assert_array_equal(kept_pushed[decided], pushed[decided])
    np.testing.assert_array_equal(kept_distance[decided], distance[decided])
