"""The shape-matching pass (goals recomputed per particle, averaged, applied) against a float64 NumPy
reference, both variants."""

import numpy as np
import pytest
import warp as wp

from conftest import helix
from sim.strands import StrandBuilder
from warp_kernels import strands as kernels


def reference_targets(x, first, size, rest, offsets, variant):
    """float64 NumPy: simplified g_k = c + d_k u; full g_k = c + R r_k with R = polar(sum (x_k - c) r_k^T)."""
    out = np.zeros((len(first), size, 3))
    for w, f in enumerate(first):
        p = x[f:f + size].astype(np.float64)
        c = p.mean(0)
        r = rest[w * size:(w + 1) * size].astype(np.float64)
        if variant == 0:
            u = p[-1] - p[0]
            u /= np.linalg.norm(u)
            out[w] = c + offsets[w * size:(w + 1) * size, None] * u
        else:
            A = (p - c).T @ r
            U, _, Vt = np.linalg.svd(A)
            D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
            out[w] = c + r @ (U @ D @ Vt).T
    return out.reshape(-1, 3)


def reference_apply(x, inv_mass, first, size, targets, stiffness):
    """Each free particle moves by stiffness times the sum of its windows' pulls (goal - x) over the
    window size: a particle held by fewer windows (near the tip) moves less, so each window's pulls,
    which sum to no net force or torque, keep doing so (an average over the windows holding each
    particle gave the ends more weight and left strands swinging without end)."""
    pull = np.zeros_like(x, dtype=np.float64)
    for w, f in enumerate(first):
        pull[f:f + size] += targets[w * size:(w + 1) * size] - x[f:f + size]
    out = x.astype(np.float64).copy()
    move = inv_mass > 0
    out[move] += stiffness * pull[move] / size
    return out


def groom(rng):
    """Three strands: straight, wavy and a curl, each deformed away from its rest shape."""
    straight = np.stack([np.zeros(10), -np.linspace(0, 0.2, 10), np.zeros(10)], 1)
    wavy = np.stack([0.01 * np.sin(np.linspace(0, 6, 12)), -np.linspace(0, 0.25, 12), np.zeros(12)], 1) + [0.1, 0, 0]
    curl = helix(16, 0.01, 0.02, 3.0) + [0.2, 0, 0]
    builder = StrandBuilder()
    for s in (straight, wavy, curl):
        builder.add_strand(s)
    model = builder.finalize("cpu", pinned_per_strand=1)
    x = model.rest_positions_np + rng.normal(0.0, 0.004, model.rest_positions_np.shape).astype(np.float32)
    return model, x.astype(np.float32)


def launch_pass(x, model, win, variant, stiffness=1.0, exact=True, iterations=1, rotations=None, refine=True,
                per_strand=False):
    """One shape_match_step over positions x (after shape_match_rotations unless refine=False):
    (moved positions, rotations). per_strand: the same pass inside strands.step_strands instead
    (fused_pass)."""
    if per_strand:
        return fused_pass(x, model, win.size, variant, stiffness), None
    if rotations is None:
        rotations = wp.zeros(win.count, dtype=wp.quat)
    xs = wp.array(x, dtype=wp.vec3)
    frames = wp.zeros(win.count, dtype=wp.mat33)
    translations = wp.zeros(win.count, dtype=wp.vec3)
    refined = wp.zeros(win.count, dtype=wp.quat)
    wp.copy(refined, rotations)
    # without refine, no refinement step: the windows' goals from the rotations given
    wp.launch(kernels.shape_match_rotations, win.count,
              [xs, win.first, win.size, win.rest_local, win.rest_centroid, int(exact and refine),
               iterations if refine else 0, refined, frames, translations, 0])
    out = wp.zeros_like(xs)
    wp.launch(kernels.shape_match_step, model.num_particles,
              [xs, model.inv_mass, model.particle_strand, win.at, win.size, win.offsets, win.rest_local, frames,
               translations, variant, stiffness, model.strand_start, out, 0])
    return out.numpy(), refined


def fused_pass(x, model, size, variant, stiffness, lanes=False):
    """The shape pass of strands.step_strands alone, a thread per strand (the CPU's): a substep that
    neither moves x (no forces, dt irrelevant) nor lets its length pass touch it (every particle
    counted as pinned there), with the rotations solved outright; in lane order with lanes."""
    from sim.hair_solver import HairParams, HairSolver

    params = HairParams(shape_matching=["simplified", "full"][variant], shape_window=size, shape_stiffness=stiffness,
                        collision="none")
    solver = HairSolver(model, params, parts=1)
    solver.lanes = lanes
    lane = solver._lanes
    slots = lane.x.shape[0] if lanes else model.num_particles
    order = lane.order if lanes else kernels.LaneOrder()
    xs, zero = wp.array(x, dtype=wp.vec3), wp.zeros(model.num_particles, dtype=wp.vec3)
    out, v = wp.zeros_like(xs), wp.zeros_like(xs)
    shaped = wp.zeros(slots, dtype=wp.vec3)
    wp.launch(kernels.step_strands, model.num_strands,
              [xs, zero, model.strand_start, 1 << 20, kernels.StrandForces(), wp.zeros(1, dtype=float), 0.0, 1.0, 0,
               kernels.SkinBinding(), None, None, 0.0, kernels.GuidePull(), size, variant, 1, stiffness, 1, 1,
               solver.rotations, solver.slots, kernels.StrandContact(), 0.0, shaped, None, out, v, order, 0, 0])
    return out.numpy()


@pytest.mark.parametrize("per_strand", [False, True], ids=["per particle", "in step_strands"])
@pytest.mark.parametrize("variant,size", [(0, 3), (1, 3), (1, 4), (1, 6), (0, 4)])
def test_pass_matches_float64_reference(variant, size, per_strand):
    rng = np.random.default_rng(3)
    model, x = groom(rng)
    win = model.shape_windows(size)
    ref = reference_targets(x, win.first_np, size, win.rest_np, win.offsets_np, variant)
    scale = np.abs(ref).max()
    moved, _ = launch_pass(x, model, win, variant, stiffness=0.4, per_strand=per_strand)
    ref_moved = reference_apply(x, model.inv_mass_np, win.first_np, size, ref, 0.4)
    np.testing.assert_allclose(moved, ref_moved, rtol=1e-5, atol=1e-5 * scale)
    assert np.abs(moved - x).max() > 1e-4  # the pass did move the perturbed strands


@pytest.mark.parametrize("lanes", [False, True], ids=["particle order", "lane order"])
@pytest.mark.parametrize("variant,size", [(0, 3), (1, 4), (0, 5), (1, 6)])
def test_one_thread_per_strand_gives_the_per_particle_pass(variant, size, lanes):
    """The shape pass inside strands.step_strands (a thread per strand, its windows solved in order
    from the root) gives shape_match_step's result bit for bit, pinned particles, strand ends, a
    window whose ends coincide (no direction) and strands of different lengths in lane order included."""
    rng = np.random.default_rng(11)
    model, x = groom(rng)
    x = x.copy()
    x[14] = x[12]  # the wavy strand's window from particle 12 folds back onto its start
    win = model.shape_windows(size)
    per_particle, _ = launch_pass(x, model, win, variant, stiffness=0.7)
    per_strand = fused_pass(x, model, size, variant, 0.7, lanes=lanes)
    np.testing.assert_array_equal(per_strand, per_particle)
    np.testing.assert_array_equal(per_strand[model.inv_mass_np == 0], x[model.inv_mass_np == 0])
    assert np.abs(per_strand - x).max() > 1e-4


def test_lane_copies_put_each_particle_in_its_slot_and_back():
    """to_lanes puts particle k of the strand in lane l at k * strands + l, positions and start
    positions alike (strands of different lengths and out of their order, pinned particles
    included), leaving the slots past a strand's tip untouched; from_lanes brings positions and
    velocities back to particle order unchanged."""
    rng = np.random.default_rng(4)
    model, x = groom(rng)
    counts = np.diff(model.strand_start_np)
    assert counts.min() < counts.max()  # the groom has strands of different lengths
    slots = model.num_strands * int(counts.max())
    lane_x, lane_prev = (wp.full(slots, wp.vec3(7.0, 7.0, 7.0), dtype=wp.vec3) for _ in range(2))
    strand_of = np.array([2, 0, 1], np.int32)  # lane -> strand
    lane_of = np.argsort(strand_of).astype(np.int32)
    order = kernels.LaneOrder()
    order.lanes = model.num_strands
    order.strand_of, order.lane_of = wp.array(strand_of, dtype=wp.int32), wp.array(lane_of, dtype=wp.int32)
    prev = x + rng.normal(0.0, 0.01, x.shape).astype(np.float32)
    wp.launch(kernels.to_lanes, slots, [wp.array(x, dtype=wp.vec3), wp.array(prev, dtype=wp.vec3),
                                        model.strand_start, order, lane_x, lane_prev])
    strand = model.particle_strand_np
    slot = (np.arange(model.num_particles) - model.strand_start_np[strand]) * model.num_strands + lane_of[strand]
    past_tip = np.ones(slots, bool)
    past_tip[slot] = False
    assert past_tip.any()
    for lanes, values in ((lane_x.numpy(), x), (lane_prev.numpy(), prev)):
        np.testing.assert_array_equal(lanes[slot], values)
        np.testing.assert_array_equal(lanes[past_tip], 7.0)
    back_x, back_v = wp.zeros(model.num_particles, dtype=wp.vec3), wp.zeros(model.num_particles, dtype=wp.vec3)
    wp.launch(kernels.from_lanes, slots,
              [lane_x, lane_prev, model.strand_start, order, int(counts.max()), back_x, back_v])
    np.testing.assert_array_equal(back_x.numpy(), x)
    np.testing.assert_array_equal(back_v.numpy(), prev)


def test_full_variant_goals_are_a_rigid_motion_of_the_rest_window():
    # a rigidly rotated and shifted rest strand is already at its goal: a full-strength pass keeps it
    rng = np.random.default_rng(5)
    model, _ = groom(rng)
    angle = 0.7
    R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    x = (model.rest_positions_np @ R.T + [0.05, 0.1, -0.2]).astype(np.float32)
    win = model.shape_windows(4)
    moved, _ = launch_pass(x, model, win, 1, stiffness=1.0)
    np.testing.assert_allclose(moved, x, atol=2e-6)


def test_simplified_variant_keeps_a_rigidly_moved_straight_strand():
    """The simplified goals c + d_k u (the window's centroid and chord) hold a straight strand's rest shape
    wherever it is moved rigidly, with uneven segments too: a check of the rest offsets d_k that the
    float64 reference above reads from the model rather than making them itself."""
    spacing = np.cumsum([0.0, 0.01, 0.02, 0.015, 0.03, 0.01, 0.025, 0.02, 0.012, 0.018])
    rest = np.stack([0.3 * spacing, -spacing, 0.2 * spacing], 1)
    model = StrandBuilder().add_strand(rest).finalize("cpu", pinned_per_strand=1)
    angle = 1.1
    R = np.array([[1, 0, 0], [0, np.cos(angle), -np.sin(angle)], [0, np.sin(angle), np.cos(angle)]])
    x = (model.rest_positions_np @ R.T + [0.1, -0.05, 0.3]).astype(np.float32)
    for size in (3, 4, 6):
        moved, _ = launch_pass(x, model, model.shape_windows(size), 0, stiffness=1.0)
        np.testing.assert_allclose(moved, x, atol=2e-6)


def test_warm_started_rotations_track_the_exact_solution():
    """Refinement (Mueller et al. 2016) from last step's rotations converges to the float64 SVD answer."""
    rng = np.random.default_rng(8)
    model, x0 = groom(rng)
    win = model.shape_windows(6)
    _, rotations = launch_pass(x0, model, win, 1, exact=True)
    # the next substep: every particle moved a little (a hair substep moves ~1 mm)
    x1 = (x0 + rng.normal(0.0, 0.001, x0.shape)).astype(np.float32)
    ref = reference_apply(x1, model.inv_mass_np, win.first_np, 6,
                          reference_targets(x1, win.first_np, 6, win.rest_np, win.offsets_np, 1), 1.0)
    scale = np.abs(ref).max()
    stale, _ = launch_pass(x1, model, win, 1, rotations=wp.array(rotations.numpy(), dtype=wp.quat), refine=False)
    errors = [np.abs(stale - ref).max()]  # last step's rotations, not refined
    for iterations in (1, 2, 4):
        warm = wp.array(rotations.numpy(), dtype=wp.quat)
        moved, _ = launch_pass(x1, model, win, 1, exact=False, iterations=iterations, rotations=warm)
        errors.append(np.abs(moved - ref).max())
    # Newton steps near the warm start converge quadratically: two reach float32 round-off
    assert errors[1] < 0.1 * errors[0] and errors[2] < 1e-6 and errors[3] < 1e-6, errors
    np.testing.assert_allclose(moved, ref, rtol=1e-5, atol=1e-5 * scale)


@wp.kernel
def _refine(q: wp.array(dtype=wp.quat), A: wp.array(dtype=wp.mat33), iterations: int, out: wp.array(dtype=wp.quat)):
    i = wp.tid()
    out[i] = kernels.refine_rotation(q[i], A[i], iterations)


def test_refinement_is_scale_free_and_lands_on_the_polar_rotation():
    """refine_rotation takes the covariance unscaled: windows of 0.1 mm, 1 cm and 10 m turn the same
    way, and from a start up to 3 rad off, sixteen steps (Müller et al.'s steps, capped at a radian,
    where the Newton step's Hessian is not positive definite, then Newton steps) reach the float64
    polar rotation."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(21)
    count = 64
    truth = Rotation.random(count, random_state=22)
    rest = rng.normal(0.0, 1.0, (count, 6, 3))
    rest -= rest.mean(1, keepdims=True)
    current = np.einsum("wij,wkj->wki", truth.as_matrix(), rest) + rng.normal(0.0, 0.05, (count, 6, 3))
    A = np.einsum("wki,wkj->wij", current - current.mean(1, keepdims=True), rest)
    U, _, Vt = np.linalg.svd(A)
    polar = U @ Vt  # proper rotations here: the noise is small against the windows' spread
    assert np.all(np.linalg.det(polar) > 0)
    off = Rotation.from_rotvec(rng.normal(0.0, 1.0, (count, 3)) * rng.uniform(0.3, 2.6, (count, 1)) / np.sqrt(3))
    start = (off * Rotation.from_matrix(polar)).as_quat().astype(np.float32)  # x, y, z, w: Warp's order
    found = {}
    for scale in (1e-4, 1e-2, 10.0):
        out = wp.zeros(count, dtype=wp.quat)
        wp.launch(_refine, count, [wp.array(start, dtype=wp.quat), wp.array((A * scale**2).astype(np.float32),
                                                                               dtype=wp.mat33), 16, out])
        found[scale] = out.numpy()
    for scale, q in found.items():
        R = Rotation.from_quat(q.astype(np.float64)).as_matrix()
        assert np.abs(R - polar).max() < 1e-6, scale
        np.testing.assert_allclose(np.abs(np.sum(q * found[1e-2], 1)), 1.0, atol=1e-6)


@wp.kernel
def _rotation_matrices(q: wp.array(dtype=wp.quat), out: wp.array(dtype=wp.mat33)):
    i = wp.tid()
    out[i] = kernels.rotation_matrix(q[i])


def test_rotation_matrix_of_a_quaternion_matches_scipy():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(2)
    q = rng.normal(size=(500, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    out = wp.zeros(len(q), dtype=wp.mat33)
    wp.launch(_rotation_matrices, len(q), [wp.array(q.astype(np.float32), dtype=wp.quat), out])
    np.testing.assert_allclose(out.numpy(), Rotation.from_quat(q).as_matrix(), atol=5e-7)  # (x, y, z, w) order


@pytest.mark.parametrize("variant,size", [(0, 3), (1, 4), (1, 6)], ids=["simplified 3", "full 4", "full 6"])
def test_a_pass_moves_no_momentum(variant, size):
    """With every particle free, a pass moves each strand's centre of mass nowhere, and full shape
    matching (exact rotations) turns no strand about it: each window's pulls sum to no net force
    or torque, and every particle's move is its windows' pulls over the window size. Averaged over
    the windows holding each particle instead, the ends counted more and a strand on a still head
    kept swinging: 9 of 12 wavy strands still swept up to 93 mm after 10 s, every curl 180-260 mm."""
    rng = np.random.default_rng(5)
    model, x = groom(rng)
    model.inv_mass.assign(np.ones(model.num_particles, np.float32))
    win = model.shape_windows(size)
    moved, _ = launch_pass(x, model, win, variant, stiffness=0.6)
    x, moved = x.astype(np.float64), moved.astype(np.float64)
    start = model.strand_start_np
    for a, b in zip(start[:-1], start[1:]):
        before, after = x[a:b], moved[a:b]
        assert np.abs(after - before).max() > 1e-4
        np.testing.assert_allclose(after.mean(0), before.mean(0), atol=2e-7)
        if variant == 1:
            c = before.mean(0)
            torque = np.cross(before - c, after - before).sum(0)
            assert np.linalg.norm(torque) < 1e-3 * np.abs(before - c).max() * np.abs(after - before).max()
