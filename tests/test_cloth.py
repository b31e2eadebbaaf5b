"""Cloth dynamics against analytic truths and a float64 reference; body collision and following."""

import numpy as np
import pytest
import trimesh
import warp as wp

from sim.cloth import ClothModel, ClothParams, ClothSolver, body_candidates
from sim.collider import UNKNOWN_MOTION, Collider
from warp_kernels import cloth as kernels
from warp_kernels import skinning

PLAIN = dict(damping=0.0, air_drag=0.0, spring_damping=0.0, gravity=(0.0, 0.0, 0.0), follow=False)


def chain(points, k_stretch, k_compress, mass, pinned=(0,), **extra):
    pts = np.asarray(points, np.float64)
    pairs = np.stack([np.arange(len(pts) - 1), np.arange(1, len(pts))], 1)
    params = ClothParams(stretch_stiffness=k_stretch, compress_stiffness=k_compress, **{**PLAIN, **extra})
    return ClothModel(pts, np.zeros((0, 3)), pairs, [], [], list(pinned), params, masses=mass)


def run(model, seconds, dt, state=None, body=None, record=None):
    solver = ClothSolver(model)
    s0 = state or model.state()
    s1 = model.state()
    out = []
    for _ in range(int(round(seconds / dt))):
        solver.step(s0, s1, body, dt)
        s0, s1 = s1, s0
        if record:
            out.append(record(s0))
    return s0, out


def test_rk4_converges_at_fourth_order_on_a_mass_spring():
    # omega = 2 pi; at 3/4 of a period the bob crosses rest at full speed, so the error there is the
    # phase error, O(dt^4) for RK4 (at a turning point it would be the smaller amplitude error)
    k, m, rest, amplitude, seconds = 4.0 * np.pi ** 2, 1.0, 0.1, 0.04, 0.75
    errors = []
    for dt in (1.0 / 20.0, 1.0 / 40.0):
        model = chain([[0, 0, 0], [rest, 0, 0]], k, k, m)
        state = model.state()
        state.x.assign(np.array([[0, 0, 0], [rest + amplitude, 0, 0]], np.float32))
        state, _ = run(model, seconds, dt, state)
        exact = rest + amplitude * np.cos(2.0 * np.pi * seconds)
        errors.append(abs(state.x.numpy()[1, 0] - exact))
    ratio = errors[0] / errors[1]
    assert 13.0 < ratio < 19.0, (errors, ratio)


@pytest.mark.parametrize("pull", ["down", "up"])
def test_hanging_column_deforms_as_the_analytic_static_solution(pull):
    """A column of 8 springs hanging from its top particle: gravity away from the pin stretches the
    springs by their stretch stiffness, toward it compresses them by their compress stiffness (the
    bi-phase springs of Oshita & Makinouchi); spring j from the pin carries n - j + 1 masses, so the
    column's length changes by m g n (n + 1) / (2 k) of the stiffness that side uses."""
    n, rest, k_stretch, k_compress, m, g = 8, 0.05, 400.0, 50.0, 0.01, 9.81
    pts = np.stack([np.zeros(n + 1), -rest * np.arange(n + 1), np.zeros(n + 1)], 1)
    sign = -1.0 if pull == "down" else 1.0
    model = chain(pts, k_stretch, k_compress, m, damping=4.0, gravity=(0.0, sign * g, 0.0))
    state, _ = run(model, 6.0, 1.0 / 600.0)
    change = -state.x.numpy()[-1, 1] - n * rest
    k = k_stretch if pull == "down" else k_compress
    expected = -sign * m * g * n * (n + 1) / (2.0 * k)
    assert abs(change / expected - 1.0) < 0.01, (change, expected)


def test_free_fall_with_linear_drag_matches_the_exponential_approach():
    params = ClothParams(air_drag=0.6, density=0.15, gravity=(0.0, -9.81, 0.0), damping=0.0, follow=False)
    model = ClothModel(np.zeros((1, 3)), np.zeros((0, 3)), [], [], [], [], params, masses=0.01)
    c_over_m = params.air_drag / params.density
    seconds = 1.0
    state, _ = run(model, seconds, 1.0 / 100.0)
    v_inf = 9.81 / c_over_m
    expected = -v_inf * (1.0 - np.exp(-c_over_m * seconds))
    assert abs(state.v.numpy()[0, 1] / expected - 1.0) < 1e-4


def test_a_particle_in_wind_approaches_the_wind_plus_its_fall_speed():
    """Linear drag c/m toward the air's velocity w: from rest, v(t) = (w + g m/c)(1 - exp(-c t / m)),
    in every axis, RK4's answer to 1e-4 of it."""
    wind, gravity = np.array([2.0, 0.0, -1.0]), np.array([0.0, -9.81, 0.0])
    params = ClothParams(air_drag=0.6, density=0.15, gravity=tuple(gravity), wind=tuple(wind), damping=0.0,
                         follow=False)
    model = ClothModel(np.zeros((1, 3)), np.zeros((0, 3)), [], [], [], [], params, masses=0.01)
    c_over_m = params.air_drag / params.density
    seconds = 0.5
    state, _ = run(model, seconds, 1.0 / 100.0)
    expected = (wind + gravity / c_over_m) * (1.0 - np.exp(-c_over_m * seconds))
    np.testing.assert_allclose(state.v.numpy()[0], expected, rtol=1e-4, atol=1e-4 * np.abs(expected).max())


def test_gusts_vary_the_wind_each_particle_feels_and_the_stages_take_them():
    """Gusty wind (wind_turbulence): each particle's gust, made once a step (kernels.wind_gusts), averages
    out over the cloth and scales with turbulence x wind speed; the RK4 stages pull every particle toward
    the wind plus its own gust: from rest, v = (w + gust)(1 - exp(-c dt / m)) after one step."""
    rng = np.random.default_rng(3)
    points = rng.uniform(-0.5, 0.5, (4000, 3))
    wind = np.array([2.0, 0.0, -1.0])
    speeds = []
    for turbulence in (0.3, 0.6):
        params = ClothParams(air_drag=0.6, density=0.15, gravity=(0.0, 0.0, 0.0), wind=tuple(wind), damping=0.0,
                             follow=False, wind_turbulence=turbulence)
        model = ClothModel(points, np.zeros((0, 3)), [], [], [], [], params, masses=0.01)
        solver = ClothSolver(model)
        solver.set_clock(2.0)
        s0, s1 = model.state(), model.state()
        dt = 1.0 / 240.0
        solver.step(s0, s1, None, dt, time=2.5)
        gusts = solver.gusts.numpy().astype(np.float64)
        c_over_m = params.air_drag / params.density
        np.testing.assert_allclose(s1.v.numpy(), (wind + gusts) * (1.0 - np.exp(-c_over_m * dt)), atol=1e-6)
        rms = np.sqrt((gusts ** 2).sum(axis=1).mean())
        assert np.abs(gusts.mean(axis=0)).max() < 0.15 * rms  # no mean drift: the mean wind is the wind
        speeds.append(rms / (turbulence * np.linalg.norm(wind)))
    assert 0.1 < speeds[0] < 2.0 and speeds[1] == pytest.approx(speeds[0], rel=1e-5)
    steady = ClothModel(points, np.zeros((0, 3)), [], [], [], [], ClothParams(), masses=0.01)
    assert ClothSolver(steady).gusts.shape[0] == 0  # no gusts, nothing made or read


def test_spring_force_kernel_matches_float64_reference():
    rng = np.random.default_rng(4)
    n = 200
    xi, xj = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    vi, vj = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    rest = np.linalg.norm(xi - xj, axis=1) * rng.uniform(0.7, 1.3, n)  # half stretched, half compressed
    ks, kc, c = rng.uniform(10, 100, n), rng.uniform(0.5, 5, n), rng.uniform(0, 0.5, n)
    x = np.concatenate([xi, xj]).astype(np.float32)
    v = np.concatenate([vi, vj]).astype(np.float32)
    f = wp.zeros(n, dtype=wp.vec3)
    f32 = lambda a: wp.array(a.astype(np.float32), dtype=float)  # noqa: E731
    springs = kernels.SpringNetwork()
    springs.spring_i = wp.array(np.arange(n, dtype=np.int32), dtype=wp.int32)
    springs.spring_j = wp.array(np.arange(n, 2 * n, dtype=np.int32), dtype=wp.int32)
    springs.spring_rest, springs.spring_k_stretch, springs.spring_k_compress, springs.spring_damping = (
        f32(rest), f32(ks), f32(kc), f32(c))
    wp.launch(kernels.spring_forces, n, [wp.array(x, dtype=wp.vec3), wp.array(v, dtype=wp.vec3), springs, f])
    xi, xj, vi, vj = (a.astype(np.float32).astype(np.float64) for a in (xi, xj, vi, vj))
    rest, ks, kc, c = (a.astype(np.float32).astype(np.float64) for a in (rest, ks, kc, c))
    d = xi - xj
    length = np.linalg.norm(d, axis=1)
    u = d / length[:, None]
    k = np.where(length > rest, ks, kc)
    ref = -(k * (length - rest) + c * np.einsum("ij,ij->i", vi - vj, u))[:, None] * u
    np.testing.assert_allclose(f.numpy(), ref, rtol=1e-5, atol=1e-5 * np.abs(ref).max())


def rigid_body(name, vertices, faces):
    """A mesh-only collider on one bone, posed at rest."""
    skin_w = np.zeros((len(vertices), 4))
    skin_w[:, 0] = 1.0
    body = Collider(name, vertices, faces, np.zeros((len(vertices), 4), np.int32), skin_w, 1, "cpu", sphere_leaves=0)
    body.set_poses(np.eye(4)[None, None])
    body.apply_pose(0)
    return body


def sphere_body(radius=0.3, subdivisions=4):
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return rigid_body("ball", np.asarray(m.vertices), m.faces)


def grid(n, size, height):
    u = np.linspace(-size / 2, size / 2, n)
    X, Z = np.meshgrid(u, u, indexing="ij")
    pts = np.stack([X.ravel(), np.full(n * n, height), Z.ravel()], 1)
    idx = np.arange(n * n).reshape(n, n)
    quads = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)
    tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    edges = np.concatenate([np.stack([idx[:-1, :].ravel(), idx[1:, :].ravel()], 1),
                            np.stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()], 1)])
    shear = np.concatenate([quads[:, [0, 2]], quads[:, [1, 3]]])
    bend = np.concatenate([np.stack([idx[:-2, :].ravel(), idx[2:, :].ravel()], 1),
                           np.stack([idx[:, :-2].ravel(), idx[:, 2:].ravel()], 1)])
    return pts, tris, edges, shear, bend


def _strain_limited_reference(x, v, pairs, rest, limited, inv_mass, max_stretch, passes, dt):
    """limit_strain's Jacobi passes and their velocity correction in float64: each over-stretched
    spring's correction split by inverse mass and shared over the larger of its ends' counts of such
    springs."""
    x0 = x.copy()
    for _ in range(passes):
        over = [(i, j, r) for (i, j), r, on in zip(pairs, rest, limited, strict=True)
                if on and np.linalg.norm(x[i] - x[j]) > r * (1.0 + max_stretch)]
        count = np.zeros(len(x))
        for i, j, _ in over:
            count[i] += 1.0
            count[j] += 1.0
        corr = np.zeros_like(x)
        for i, j, r in over:
            d = x[i] - x[j]
            length = np.linalg.norm(d)
            excess = (length - r * (1.0 + max_stretch)) * d / (length * max(count[i], count[j]))
            for a, b, sign in ((i, j, 1.0), (j, i, -1.0)):
                if inv_mass[a] > 0.0:
                    corr[a] -= sign * inv_mass[a] / (inv_mass[a] + inv_mass[b]) * excess
        x = x + corr
    return x, v + (x - x0) / dt


@pytest.mark.parametrize("passes", [1, 2, 3, 4])
def test_strain_limit_passes_match_a_float64_reference(passes):
    """Any number of passes ends in the state's own buffers with the velocities corrected by the
    whole displacement, as the float64 reference; over-stretched edges shorten, pinned corners stay."""
    pts, tris, edges, shear, bend = grid(7, 0.3, 0.0)
    model = ClothModel(pts, tris, edges, shear, bend, [0, 6], ClothParams(strain_limit=0.03, strain_iterations=passes))
    rng = np.random.default_rng(passes)
    x = pts * np.array([1.12, 1.0, 1.05]) + rng.normal(0.0, 0.004, pts.shape)
    x[[0, 6]] = pts[[0, 6]]
    v = rng.normal(0.0, 0.1, pts.shape)
    state = model.state()
    x_buffer = state.x
    state.x.assign(x.astype(np.float32))
    state.v.assign(v.astype(np.float32))
    dt = 1.0 / 600.0
    ClothSolver(model)._limit_strain(state, dt)
    assert state.x is x_buffer
    limited = model.spring_limited.numpy() != 0
    x32, v32 = x.astype(np.float32).astype(np.float64), v.astype(np.float32).astype(np.float64)
    want_x, want_v = _strain_limited_reference(x32, v32, model.spring_pairs_np, model.spring_rest_np, limited,
                                               model.inv_mass_np, 0.03, passes, dt)
    np.testing.assert_allclose(state.x.numpy(), want_x, atol=2e-7)
    np.testing.assert_allclose(state.v.numpy(), want_v, atol=2e-7 / dt)
    np.testing.assert_array_equal(state.x.numpy()[[0, 6]], x32[[0, 6]])

    def worst(p):
        e = model.spring_pairs_np[limited]
        return (np.linalg.norm(p[e[:, 0]] - p[e[:, 1]], axis=1) / model.spring_rest_np[limited]).max() - 1.0

    assert worst(x) > 0.1 and worst(want_x) < worst(x)


def _on_a_moving_plane(velocity, follow, seconds=0.4, dt=1e-3, friction=0.5):
    """One particle resting on a box's top face while the box moves at `velocity`: (its position less
    the box's displacement and its start, its velocity) after `seconds`."""
    steps = int(round(seconds / dt))
    box = trimesh.creation.box(extents=(3.0, 0.4, 3.0)).subdivide().subdivide()
    plane = rigid_body("plane", np.asarray(box.vertices), np.asarray(box.faces))
    poses = np.repeat(np.eye(4)[None, None], steps + 1, axis=0)
    poses[:, 0, :3, 3] = np.outer(np.arange(steps + 1) * dt, velocity)
    plane.set_poses(poses)
    params = ClothParams(friction=friction, air_drag=0.0, damping=0.0, gravity=(0.0, -9.81, 0.0), follow=follow)
    start = np.array([0.0, 0.2 + params.collision_margin, 0.0])
    model = ClothModel(start[None], np.zeros((0, 3)), [], [], [], [], params, masses=0.01)
    solver, s0, s1 = ClothSolver(model), model.state(), model.state()
    for k in range(1, steps + 1):
        plane.apply_pose(k)
        solver.step(s0, s1, plane, dt)
        s0, s1 = s1, s0
    moved = np.asarray(velocity) * steps * dt
    return s0.x.numpy()[0].astype(np.float64) - moved - start, s0.v.numpy()[0].astype(np.float64)


def test_a_particle_on_a_moving_body_is_carried_once_whether_it_follows_or_not():
    """A particle at rest on a plane that starts sliding at 0.5 m/s: without following, friction
    (mu 0.5) brings it up to the plane's speed after slipping back v^2 / (2 mu g) = 25.5 mm; following
    carries it with the plane from the first step, so it does not slip at all. Following had counted the
    plane's motion twice (its move and friction's velocity), and the particle slid 174 mm ahead over it.
    On a plane rising at 0.5 m/s a followed particle rests at the margin (it bounced 4 mm above)."""
    slip, _ = _on_a_moving_plane((0.5, 0.0, 0.0), follow=False)
    assert abs(slip[0] + 0.5 ** 2 / (2.0 * 0.5 * 9.81)) < 1e-3 and abs(slip[1]) < 1e-3
    carried, v = _on_a_moving_plane((0.5, 0.0, 0.0), follow=True)
    assert np.abs(carried).max() < 1e-3 and np.abs(v).max() < 0.02  # its own velocity: the plane carries it
    lifted, v = _on_a_moving_plane((0.0, 0.5, 0.0), follow=True)
    assert np.abs(lifted).max() < 1e-3 and np.abs(v).max() < 0.02


def test_strain_limiting_moves_no_momentum():
    """A free, unevenly stretched cloth: the strain limit's passes leave the total momentum and the
    centre of mass where they were (each particle averaging its own corrections added 0.058 m/s to the
    centre of mass in one pass, and a falling cloth drifted 12 mm/s off g t)."""
    pts, tris, edges, shear, bend = grid(7, 0.3, 0.0)
    masses = np.random.default_rng(0).uniform(0.5, 2.0, len(pts)) * 1e-3
    model = ClothModel(pts, tris, edges, shear, bend, [], ClothParams(strain_limit=0.03, strain_iterations=4),
                       masses=masses)
    x = pts * np.array([1.0, 1.0, 1.0])
    x[:, 0] *= 1.0 + 0.3 * (pts[:, 0] > 0.0)  # one half stretched 30%, the other not
    state = model.state()
    state.x.assign(x.astype(np.float32))
    state.v.zero_()
    ClothSolver(model)._limit_strain(state, 1e-3)
    after, v = state.x.numpy().astype(np.float64), state.v.numpy().astype(np.float64)
    assert np.abs(after - x).max() > 0.01  # the passes did shorten the stretched half
    np.testing.assert_allclose(masses @ after / masses.sum(), masses @ x / masses.sum(), atol=1e-6)
    assert np.abs(masses @ v).max() < 1e-6 * masses.sum()  # m/s of the centre of mass


def test_cloth_draped_on_a_ball_ends_outside_it():
    body = sphere_body()
    pts, tris, edges, shear, bend = grid(20, 0.9, 0.35)
    model = ClothModel(pts, tris, edges, shear, bend, [], ClothParams())
    dt = model.stable_dt
    state, _ = run(model, 1.0, dt, body=body)
    r = np.linalg.norm(state.x.numpy(), axis=1)
    assert r.min() > 0.3  # nothing inside the ball
    margin = model.params.collision_margin
    assert np.mean(r < 0.3 + margin + 0.002) > 0.15  # and the cloth really rests on it, at the margin
    seg = np.linalg.norm(state.x.numpy()[edges[:, 0]] - state.x.numpy()[edges[:, 1]], axis=1)
    assert np.percentile(seg / model.spring_rest_np[:len(edges)] - 1.0, 99) < 0.05  # stiff in stretch


@pytest.mark.parametrize("friction", [0.0, 0.2, 0.5])
def test_a_particle_on_an_incline_slides_as_coulomb_friction_allows(friction):
    """One particle resting on a plane tilted 20 degrees: it slides with a = g (sin t - mu cos t) when
    mu < tan t (0.364), and holds when mu exceeds it (within a millimetre in 0.5 s: the contact is made
    at the step's end, so each step starts a little off the plane)."""
    g, tilt, seconds, dt = 9.81, np.radians(20.0), 0.5, 1e-3
    box = trimesh.creation.box(extents=(3.0, 0.4, 3.0)).subdivide().subdivide()
    turn = np.array([[np.cos(tilt), -np.sin(tilt), 0.0], [np.sin(tilt), np.cos(tilt), 0.0], [0.0, 0.0, 1.0]])
    plane = rigid_body("incline", np.asarray(box.vertices) @ turn.T, np.asarray(box.faces))
    normal, downhill = turn @ [0.0, 1.0, 0.0], turn @ [-1.0, 0.0, 0.0]
    params = ClothParams(friction=friction, air_drag=0.0, damping=0.0, gravity=(0.0, -g, 0.0), follow=False)
    start = normal * (0.2 + params.collision_margin)  # on the top face, 0.2 m above the box's centre
    model = ClothModel(start[None], np.zeros((0, 3)), [], [], [], [], params, masses=0.01)
    state, _ = run(model, seconds, dt, body=plane)
    x, v = state.x.numpy()[0].astype(np.float64), state.v.numpy()[0].astype(np.float64)
    accel = max(0.0, g * (np.sin(tilt) - friction * np.cos(tilt)))
    assert abs(v @ downhill - accel * seconds) < 0.01 * g * np.sin(tilt) * seconds
    assert abs((x - start) @ downhill - 0.5 * accel * seconds ** 2) < 1e-3
    assert abs(x @ normal - 0.2 - params.collision_margin) < 1e-3  # on the plane, not through it


def test_following_keeps_body_relative_coordinates_under_rigid_motion():
    body = sphere_body()
    rng = np.random.default_rng(2)
    directions = rng.normal(size=(50, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    pts = directions * (0.3 + rng.uniform(0.002, 0.015, (50, 1)))  # within follow_full_within of the body
    model = ClothModel(pts, np.zeros((0, 3)), [], [], [], [], ClothParams(), masses=0.001)
    state = model.state()
    wp.launch(kernels.nearest_vertex_brute_force, 50, [state.x, body.points, state.nearest])
    # a collision pass with no margin (nothing is inside the ball) records the follow coordinates
    steps, fallbacks = wp.zeros(1, dtype=wp.int32), wp.zeros(1, dtype=wp.int32)
    before = state.x.numpy().copy()  # on the CPU numpy() is a view of the array
    solver = ClothSolver(model, ClothParams(collision_margin=0.0, friction=0.0, teleport=1.0, walk_trust_distance=1.0))
    wp.launch(kernels.body_collide, 50,
              [state.x, state.x, state.v, model.inv_mass, solver.body_surface(body), solver.contact_params(), steps,
               1, 1e-3, state.nearest, state.clearance, 1, state.nearest, state.clearance, solver.candidates,
               state.contact, fallbacks, state.follow, solver.carried, 0, 0])
    np.testing.assert_array_equal(state.x.numpy(), before)
    assert np.all(state.follow.face.numpy() >= 0)
    angle = 0.8
    R = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, [0.3, -0.1, 0.2]
    body.set_poses(M[None, None])
    body.apply_pose(0)
    wp.launch(kernels.begin_step, 50, [state.x, state.v, model.inv_mass, body.points, body.indices, 1, state.follow,
                                       0.02, 0.08, 0, None,
                                       skinning.SkinBinding(), 1e-3, steps, solver.carried])
    assert steps.numpy()[0] == 1
    np.testing.assert_allclose(state.x.numpy(), pts @ R.T + M[:3, 3], atol=1e-5)
    np.testing.assert_allclose(solver.carried.numpy(), state.x.numpy() - before, atol=1e-6)  # for the contact


def test_collider_moved_is_the_largest_vertex_displacement_of_the_last_pose():
    body = sphere_body()
    poses = np.repeat(np.eye(4)[None, None], 3, axis=0)
    poses[1, 0, :3, 3] = [0.003, -0.004, 0.0]  # 5 mm
    angle = 0.1
    poses[2, 0, :2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
    poses[2, 0, :3, 3] = poses[1, 0, :3, 3]
    body.set_poses(poses)
    body.apply_pose(1)
    assert body.moved.numpy()[0] == pytest.approx(0.005, rel=1e-5)
    body.apply_pose(2)  # a turn by 0.1 rad about the z axis: the equator moves 2 r sin(0.05)
    rim = np.linalg.norm(body.rest_points_np[:, :2], axis=1).max()
    assert body.moved.numpy()[0] == pytest.approx(2.0 * rim * np.sin(0.05), rel=1e-4)
    body.reset_motion()  # the pose is also the last one: nothing moved
    assert body.moved.numpy()[0] == 0.0
    body.apply_pose(0, refit=False)  # a pose for the sphere tree only says nothing of the mesh's motion
    assert body.moved.numpy()[0] == np.float32(UNKNOWN_MOTION)



def test_largest_displacement_strides_to_the_largest_move():
    """collision.largest_displacement: each thread takes the largest move over a stride of the points
    and raises the maximum with it; the largest of 1,000 random moves, whichever thread's stride holds
    it, for one thread, a few, and one per point."""
    from warp_kernels import collision

    rng = np.random.default_rng(3)
    before = rng.normal(size=(1000, 3)).astype(np.float32)
    for threads, where in ((1, 999), (3, 0), (7, 517), (1000, 400)):
        after = before + rng.uniform(-0.01, 0.01, size=before.shape).astype(np.float32)
        after[where] += 0.2
        moved = wp.zeros(1, dtype=float)
        wp.launch(collision.largest_displacement, threads,
                  [wp.array(before, dtype=wp.vec3), wp.array(after, dtype=wp.vec3), len(before), threads, moved])
        want = np.linalg.norm(after.astype(np.float64) - before, axis=1).max()
        assert moved.numpy()[0] == pytest.approx(want, rel=1e-6)


def _sliding_ball_poses(steps):
    """Poses of a ball that slides along x and rises into cloth above it, one per step."""
    poses = np.repeat(np.eye(4)[None, None], steps + 1, axis=0)
    poses[:, 0, 0, 3] = 0.0015 * np.arange(steps + 1)
    poses[:, 0, 1, 3] = 0.0004 * np.arange(steps + 1)
    angle = 0.004 * np.arange(steps + 1)  # and turns, so that its triangles do not just translate
    poses[:, 0, 0, 0], poses[:, 0, 0, 1] = np.cos(angle), -np.sin(angle)
    poses[:, 0, 1, 0], poses[:, 0, 1, 1] = np.sin(angle), np.cos(angle)
    return poses


def test_a_sweep_poses_as_the_skinned_path_and_its_boxes_hold_every_pose():
    """Collider.sweep skins every uploaded pose at once: apply_pose(k) then gives the points and the
    motion of the skinned path bit for bit, and each triangle's swept box holds it in every pose; a
    sweep of the same poses given as points (a point cache) gives the same boxes."""
    steps = 6
    poses = _sliding_ball_poses(steps)
    skinned, swept, cached = (sphere_body(subdivisions=2) for _ in range(3))
    for body in (skinned, swept):
        body.set_poses(poses)
    points = []
    for k in range(steps + 1):
        points.append(_skinned(skinned, k))
    cached.set_point_poses(np.stack(points))
    swept.sweep()
    cached.sweep()
    lower, upper = swept._boxes.lower.numpy(), swept._boxes.upper.numpy()
    np.testing.assert_array_equal(cached._boxes.lower.numpy(), lower)
    np.testing.assert_array_equal(cached._boxes.upper.numpy(), upper)
    skinned.apply_pose(0)
    for k in range(steps + 1):
        skinned.apply_pose(k)
        for body in (swept, cached):
            body.apply_pose(k, refit=False)
            np.testing.assert_array_equal(body.points.numpy(), skinned.points.numpy())
            if k > 0:
                assert body.moved.numpy()[0] == skinned.moved.numpy()[0] > 0.0015
        corners = swept.points.numpy()[swept.faces_np]
        assert np.all(corners.min(axis=1) >= lower) and np.all(corners.max(axis=1) <= upper)
    # the boxes bound the poses and no more: the first and last poses' corners reach every face of them
    first, last = (poses[[0, -1], 0, :3, :3] @ swept.rest_points_np.T).transpose(0, 2, 1) + poses[[0, -1], 0, :3, 3][:, None]
    ends = np.concatenate([first[swept.faces_np], last[swept.faces_np]], axis=1)
    np.testing.assert_allclose(lower, ends.min(axis=1), atol=1e-4)  # the arc between bulges them by 2e-5 m
    np.testing.assert_allclose(upper, ends.max(axis=1), atol=1e-4)
    swept.set_poses(poses)  # a new upload ends the sweep: poses are skinned one by one again
    swept.apply_pose(2)
    np.testing.assert_array_equal(swept.points.numpy(), _skinned(skinned, 2))


def _skinned(body, k):
    body.apply_pose(k)
    return body.points.numpy().copy()  # on the CPU numpy() is a view of the array, which the next pose overwrites


def test_cloth_on_a_swept_body_steps_as_on_one_refitted_every_step():
    """The cloth's queries of triangle boxes swept over all the steps' poses (one refit) find what
    boxes fitted to each pose find, and what the wp.Mesh's nearest-first query finds (a GPU's way,
    ClothSolver.mesh_queries): cloth on a ball that slides, turns and rises into it ends where it
    ends with a refit per step."""
    pts, tris, edges, shear, bend = grid(12, 0.8, 0.36)
    model = ClothModel(pts, tris, edges, shear, bend, [], ClothParams(walk_refresh=2))
    dt, steps = model.stable_dt, 120
    poses = _sliding_ball_poses(steps)
    finals, queries = [], []
    for sweep, mesh_queries in ((False, False), (True, False), (False, True)):
        body = sphere_body()
        body.set_poses(poses)
        if sweep:
            body.sweep()
        solver = ClothSolver(model)
        solver.mesh_queries = mesh_queries
        s0, s1 = model.state(), model.state()
        body.apply_pose(0, refit=not sweep)
        body.reset_motion()
        contacts = 0
        for k in range(1, steps + 1):
            body.apply_pose(k, refit=not sweep)
            solver.step(s0, s1, body, dt)
            s0, s1 = s1, s0
            contacts += int(s0.contact.numpy().sum())
        finals.append(s0.x.numpy())
        queries.append(solver.fallback_count())
        assert contacts > 100  # the ball pushed into the cloth
        assert body.signed_distance(s0.x.numpy()).min() > 0.0
    assert queries[0] == queries[1] == queries[2] > 0
    np.testing.assert_allclose(finals[1], finals[0], atol=1e-6)
    np.testing.assert_allclose(finals[2], finals[0], atol=1e-6)



def _cloth_on_the_sliding_ball(params, steps, block=None, threads=None):
    """(final state, BVH queries, contacts over the steps): a 12 x 12 cloth pinned at two corners bound to a ball that slides,
    turns and rises into it; block None steps with the launches, True as one block of `threads`."""
    pts, tris, edges, shear, bend = grid(12, 0.8, 0.29)
    model = ClothModel(pts, tris, edges, shear, bend, [0, 11], params)
    poses = _sliding_ball_poses(steps)
    body = sphere_body(subdivisions=3)
    body.set_poses(poses)
    body.apply_pose(0)
    body.reset_motion()
    model.bind_to_mesh(body.points.numpy(), body.faces_np)
    solver = ClothSolver(model)
    solver.block_step = bool(block)
    if threads is not None:
        solver.block_threads = threads
    s0, s1 = model.state(), model.state()
    contacts = 0
    for k in range(1, steps + 1):
        body.apply_pose(k)
        solver.step(s0, s1, body, model.stable_dt)
        s0, s1 = s1, s0
        contacts += int(s0.contact.numpy().sum())
    return s0, solver.fallback_count(), contacts


@pytest.mark.parametrize("passes", [0, 1, 3], ids=["no strain limit", "1 strain pass", "3 strain passes"])
def test_a_step_in_one_block_is_the_launches_bit_for_bit(passes, monkeypatch):
    """kernels.step_in_block (a GPU's step of a small cloth, ClothSolver.block_step) runs the step's
    launches as the passes of one thread block, with barriers between them: the same cloth bit for
    bit, run by one thread and by 64 threads that interleave at the barriers (the CPU's fibers,
    wp.config.enable_cpu_blocks), where a missing barrier would read a neighbour's stale stage."""
    params = ClothParams(strain_limit=0.01 if passes else 0.0, strain_iterations=max(passes, 1), walk_refresh=2)
    steps = 40
    want, queries, contacts = _cloth_on_the_sliding_ball(params, steps)
    assert queries > 0 and contacts > 20  # the ball pushes into the cloth
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    for threads in (1, 64):
        got, got_queries, got_contacts = _cloth_on_the_sliding_ball(params, steps, block=True, threads=threads)
        assert (got_queries, got_contacts) == (queries, contacts)
        for name in ("x", "v", "nearest", "contact"):
            np.testing.assert_array_equal(getattr(got, name).numpy(), getattr(want, name).numpy(), err_msg=name)
        for name in ("face", "barycentric", "local"):
            np.testing.assert_array_equal(getattr(got.follow, name).numpy(), getattr(want.follow, name).numpy(),
                                          err_msg=name)
        np.testing.assert_array_equal(got.clearance.distance.numpy(), want.clearance.distance.numpy())


def test_a_step_in_one_block_without_a_body_is_the_launches_bit_for_bit(monkeypatch):
    """step_in_block with no body to collide with or follow (its body arguments None): a hanging
    chain with a strain limit, the same bit for bit as the launches, with 1 and 16 fiber lanes."""
    model = chain([[0.05 * i, 0.0, 0.0] for i in range(40)], 50.0, 5.0, 0.01, gravity=(0.0, -9.81, 0.0),
                  strain_limit=0.01, strain_iterations=2)
    want, _ = run(model, 0.2, 1e-3)
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    for threads in (1, 16):
        solver = ClothSolver(model)
        solver.block_step, solver.block_threads = True, threads
        s0, s1 = model.state(), model.state()
        for _ in range(200):
            solver.step(s0, s1, None, 1e-3)
            s0, s1 = s1, s0
        np.testing.assert_array_equal(s0.x.numpy(), want.x.numpy())
        np.testing.assert_array_equal(s0.v.numpy(), want.v.numpy())
    assert want.x.numpy()[-1, 1] < -0.15  # the chain swung down

def test_body_clearance_stays_a_lower_bound_of_the_distance_on_a_moving_body():
    """The bounds that let body_collide skip queries never claim more room than there is: cloth
    falls on a ball that slides and rises into it, re-seeded every other step."""
    body = sphere_body()
    pts, tris, edges, shear, bend = grid(12, 0.8, 0.36)
    model = ClothModel(pts, tris, edges, shear, bend, [], ClothParams(walk_refresh=2))
    dt = model.stable_dt
    steps = 120
    poses = np.repeat(np.eye(4)[None, None], steps + 1, axis=0)
    poses[:, 0, 0, 3] = 0.0015 * np.arange(steps + 1)
    poses[:, 0, 1, 3] = 0.0004 * np.arange(steps + 1)
    body.set_poses(poses)
    solver = ClothSolver(model)
    s0, s1 = model.state(), model.state()
    checked = touching = 0
    for k in range(1, steps + 1):
        body.apply_pose(k)
        solver.step(s0, s1, body, dt)
        s0, s1 = s1, s0
        x = s0.x.numpy()
        distance, at = s0.clearance.distance.numpy(), s0.clearance.at.numpy()
        bound = distance - np.linalg.norm(x - at, axis=1)
        known = distance > -1e29
        sd = body.signed_distance(x)
        assert np.all(bound[known] <= sd[known] + 1e-5), (k, (bound - sd)[known].max())
        checked += np.count_nonzero(known)
        touching += np.count_nonzero(s0.contact.numpy())
    assert checked == steps * model.num_particles  # every particle was queried on the first step
    assert touching > 300  # the ball really pushed into the cloth


def test_dress_at_rest_skips_the_queries_its_clearance_and_gatherings_rule_out():
    """On a still body the dress settles with under a third of the BVH queries of re-seeding every
    far particle on schedule (only those that drifted, and could touch the body or follow it), and
    the particles at concave vertices that touch the body test their gathered triangles instead of
    querying: the queries left wait for the re-seeding steps. The dress lands where querying every
    time would have put it."""
    from sim.body import procedural_body
    from sim.garment import fit_dress

    body_mesh = procedural_body()
    garment = fit_dress(body_mesh, particles=322)
    finals, queries, off_schedule = [], [], []
    for params in (ClothParams(reseed_drift=0.0, body_candidates=0), ClothParams(body_candidates=0), ClothParams()):
        model = ClothModel.from_garment(garment, params)
        body = rigid_body("body", body_mesh.vertices, body_mesh.faces)
        body.reset_motion()
        model.bind_to_mesh(body.posed_points(), body.faces_np)
        solver = ClothSolver(model)
        s0, s1 = model.state(), model.state()
        dt = 1.0 / 60.0 / model.substeps_for(1.0 / 60.0)
        count = stray = between = 0
        for k in range(240):
            solver.fallbacks.zero_()
            solver.step(s0, s1, body, dt)
            s0, s1 = s1, s0
            if k >= 12:  # after the first frame's seeding
                made = solver.fallback_count()
                count += made
                if solver.step_count.numpy()[0] % params.walk_refresh != 0:
                    between += 1
                    stray += made > 0
        finals.append(s0.x.numpy())
        queries.append(count)
        off_schedule.append(stray / between)
        assert body.signed_distance(s0.x.numpy()).min() > 0.0
    assert queries[1] < 0.4 * queries[0], queries
    assert queries[2] < 0.25 * queries[1], queries
    # the share of the steps between re-seeding ones that query (on a GPU each waits for its slowest query)
    assert off_schedule[1] > 0.9 and off_schedule[2] < 0.1, off_schedule
    np.testing.assert_allclose(finals[1], finals[0], atol=1e-4)
    np.testing.assert_allclose(finals[2], finals[0], atol=1e-4)


@wp.kernel
def _gathered_against_the_bvh(centers: wp.array(dtype=wp.vec3), queries: wp.array(dtype=wp.vec3), radius: float,
                              search: float, body_motion: float, tie: float, mesh: wp.uint64, bvh: wp.uint64,
                              points: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32),
                              candidates: kernels.BodyCandidates, listed: wp.array(dtype=wp.vec4),
                              boxed: wp.array(dtype=wp.vec4), queried: wp.array(dtype=wp.vec4),
                              corners: wp.array(dtype=wp.vec3i)):
    p = wp.tid()
    kernels.gather_candidates(centers[p], radius, bvh, points, indices, p, candidates)
    candidates.body_motion[p] = body_motion
    xq = queries[p]
    if candidates.count[p] >= 0:
        found, sd, n, corner = kernels.closest_candidate(xq, search, tie, points, p, candidates)
        listed[p] = wp.vec4(sd, n[0], n[1], n[2]) if found else wp.vec4(1.0e30)
        corners[p] = wp.vec3i(corner, -1, -1)
    found, sd, n, corner = kernels.closest_in_boxes(xq, search, tie, bvh, points, indices)
    boxed[p] = wp.vec4(sd, n[0], n[1], n[2]) if found else wp.vec4(1.0e30)
    corners[p] = wp.vec3i(corners[p][0], corner, -1)
    q = wp.mesh_query_point_sign_normal(mesh, xq, search)
    queried[p] = wp.vec4(1.0e30)
    if q.result:
        n = wp.mesh_eval_face_normal(mesh, q.face)
        queried[p] = wp.vec4(q.sign * wp.length(xq - wp.mesh_eval_position(mesh, q.face, q.u, q.v)), n[0], n[1], n[2])
        corners[p] = wp.vec3i(corners[p][0], corners[p][1], kernels.closest_corner(xq, q.face, points, indices))


def test_gathered_triangles_answer_as_the_bvh_query_at_concave_vertices():
    """closest_candidate over a particle's gathered triangles, and closest_in_boxes over the
    triangle boxes, give wp.mesh_query_point_sign_normal's distance, sign and normal (the gathering
    wherever its slack covers the particle's and the body's motion): points around the body's
    concave vertices (armpits, crotch, neck), inside and out."""
    from sim.body import procedural_body

    body_mesh = procedural_body()
    body = rigid_body("body", body_mesh.vertices, body_mesh.faces)
    adj = body.adjacency()
    rng = np.random.default_rng(11)
    concave = np.flatnonzero(adj.concave.numpy())
    n, search, slack, motion = 4000, 0.016, 0.008, 0.002
    vertices = body.posed_points()[rng.choice(concave, n)]
    centers = vertices + rng.normal(scale=0.008, size=(n, 3))  # about half inside the body
    step = rng.normal(size=(n, 3))
    step *= (rng.uniform(0.0, slack - motion, (n, 1)) / np.linalg.norm(step, axis=1, keepdims=True))
    capacity = 160
    candidates = body_candidates(n, capacity, "cpu")
    listed, boxed, queried = (wp.zeros(n, dtype=wp.vec4) for _ in range(3))
    corners = wp.zeros(n, dtype=wp.vec3i)
    wp.launch(_gathered_against_the_bvh, n,
              [wp.array(centers, dtype=wp.vec3), wp.array(centers + step, dtype=wp.vec3), search + slack, search,
               motion, adj.tie, body.mesh.id, body.triangle_bvh.id, body.points, body.indices, candidates, listed,
               boxed, queried, corners])
    count = candidates.count.numpy()
    assert count.min() >= 0 and count.max() < capacity
    queried = queried.numpy()
    found = queried[:, 0] < 1e29
    assert found.mean() > 0.9 and (queried[found, 0] < 0.0).mean() > 0.3  # near the surface, on both sides
    for k, answer in enumerate((listed.numpy(), boxed.numpy())):
        np.testing.assert_array_equal(answer[:, 0] < 1e29, found)
        np.testing.assert_allclose(answer[found, 0], queried[found, 0], atol=1e-6)  # the signed distance
        # the closest point's nearest body vertex, where a walk restarts; the triangle, and so the
        # normal, may differ where the closest point is on an edge or corner shared by equally close
        # triangles
        assert np.mean(corners.numpy()[found, k] == corners.numpy()[found, 2]) > 0.999
        same = np.linalg.norm(answer[found, 1:] - queried[found, 1:], axis=1) < 1e-5
        assert same.mean() > 0.9
    # nearest first, which lets the test stop at the first that cannot come closer than the best found
    distance = candidates.distance.numpy().reshape(n, capacity)
    both = np.arange(1, capacity) < count[:, None]
    assert np.all(np.diff(distance, axis=1)[both] >= 0.0)


def _chain(masses, params):
    """A straight chain along x with its first particle fixed: moved along the chain its springs are
    exactly linear and the bound on its stiffest mode is attained (the chain Laplacian itself)."""
    n = len(masses)
    pts = np.stack([0.02 * np.arange(n), np.zeros(n), np.zeros(n)], 1)
    edges = np.stack([np.arange(n - 1), np.arange(1, n)], 1)
    return ClothModel(pts, np.zeros((0, 3)), edges, [], [], [0], params, masses=masses)


def _growth(model, dt, steps):
    """How much a small random motion along the chain (1e-4 m/s) grows over `steps` RK4 steps of dt:
    its largest speed afterwards over its largest speed before."""
    rng = np.random.default_rng(5)
    state = model.state()
    v = np.zeros((model.num_particles, 3), np.float32)
    v[1:, 0] = rng.uniform(-1e-4, 1e-4, model.num_particles - 1)
    state.v.assign(v)
    state, _ = run(model, steps * dt, dt, state=state)
    speed = np.abs(state.v.numpy()).max()
    return float(speed / np.abs(v).max()) if np.isfinite(speed) else np.inf


@pytest.mark.parametrize("mode", ["springs", "dashpots"])
def test_stability_bound_is_the_rk4_limit_of_the_stiffest_mode(mode):
    """The step bound comes from the largest eigenvalue of the mass-weighted spring Laplacian over the
    free particles. On a straight chain that eigenvalue is the stiffest mode's own, so RK4 at the
    bound (10% inside the limit: 2 sqrt(2) on the imaginary axis, 2.785 on the real one) keeps a small
    motion bounded, as does 2% inside the limit, while 5% past it the motion grows by orders of magnitude within 100 steps; Gershgorin's row sums,
    the bound before, sit well inside it."""
    masses = np.random.default_rng(1).uniform(0.5e-3, 2e-3, 24)
    quiet = dict(gravity=(0.0, 0.0, 0.0), damping=0.0, air_drag=0.0)
    if mode == "springs":
        params = ClothParams(stretch_stiffness=100.0, compress_stiffness=100.0, spring_damping=0.0, **quiet)
        limit = 2.0 * np.sqrt(2.0)
    else:
        params = ClothParams(stretch_stiffness=1e-9, compress_stiffness=1e-9, spring_damping=0.05, **quiet)
        limit = 2.785
    model = _chain(masses, params)
    # the step at which the stiffest mode sits exactly on the edge of RK4's stability region
    edge = model.stable_dt / 0.9 * (1.0 if mode == "springs" else limit / 2.78)
    assert _growth(model, model.stable_dt, 400) < 10.0  # energy is conserved (springs) or decays
    assert _growth(model, 0.98 * edge, 400) < 10.0
    assert _growth(model, 1.05 * edge, 100) > 1e4
    # a float64 reference of the eigenvalue, and Gershgorin's looser bound on it
    n = len(masses)
    lap = np.zeros((n, n))
    for i in range(n - 1):
        lap[i, i] += 1.0
        lap[i + 1, i + 1] += 1.0
        lap[i, i + 1] = lap[i + 1, i] = -1.0
    weight = params.stretch_stiffness if mode == "springs" else params.spring_damping
    free = lap[1:, 1:] * weight / np.sqrt(np.outer(masses[1:], masses[1:]))
    top = np.linalg.eigvalsh(free)[-1]
    expected = 0.9 * (2.0 * np.sqrt(2.0) / np.sqrt(top) if mode == "springs" else 2.78 / top)
    assert model.stable_dt == pytest.approx(expected, rel=1e-6)
    gershgorin = np.abs(free).sum(axis=1).max()
    assert (top / gershgorin) < 0.8


def test_stability_bound_picks_substeps_that_stay_stable():
    pts, tris, edges, shear, bend = grid(12, 0.5, 0.0)
    params = ClothParams(stretch_stiffness=400.0)
    model = ClothModel(pts, tris, edges, shear, bend, [0, 11], params)
    frame = 1.0 / 24.0
    substeps = model.substeps_for(frame)
    assert substeps == int(np.ceil(frame / model.stable_dt))
    state, _ = run(model, 0.5, frame / substeps)
    assert np.all(np.isfinite(state.x.numpy())) and np.abs(state.v.numpy()).max() < 10.0
