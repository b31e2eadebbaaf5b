"""The comb (sim.comb): grips slide exactly when the hair up to them is too short, hidden hair is
never grabbed, and held hair goes where the comb is dragged, keeping its lengths."""

import numpy as np
import pytest
import trimesh
import warp as wp

from io_usd.preview import Camera
from sim.collider import Collider
from sim.comb import Comb, CombGrip, place_comb
from sim.hair_solver import HairParams, HairSolver
from sim.strands import StrandBuilder
from warp_kernels import strands as strand_kernels

SPACING = 0.01


def _sphere_collider(radius=0.1, subdivisions=4, device="cpu"):
    s = trimesh.creation.icosphere(subdivisions, radius=radius)
    v, f = np.asarray(s.vertices), np.asarray(s.faces)
    return Collider("head", v, f, np.tile([1, 0, 0, 0], (len(v), 1)), np.tile([1.0, 0, 0, 0], (len(v), 1)), 2,
                    device=device, sphere_leaves=0)


def _hanging(roots, count=10):
    """Straight strands hanging down from each root, SPACING apart."""
    steps = np.arange(count)[:, None] * [0.0, -SPACING, 0.0]
    return np.concatenate([r + steps for r in roots]), np.full(len(roots), count)


def _hold(x, grip, target, pinned=2):
    """One hold_in_comb launch on one strand; returns (positions, grip)."""
    x = np.asarray(x, np.float32)
    xa = wp.array(x, dtype=wp.vec3)
    v = wp.zeros(len(x), dtype=wp.vec3)
    start = wp.array([0, len(x)], dtype=int)
    rest = np.r_[0.0, np.linalg.norm(np.diff(x, axis=0), axis=1)].astype(np.float32)
    g = wp.array([grip], dtype=int)
    t = wp.array([target], dtype=wp.vec3)
    bounds = wp.full(len(x), 1.0, dtype=float)  # the length pass's contact bounds, lost where the comb moves hair
    contact = strand_kernels.StrandContact()  # no collider
    contact.clearance = bounds
    wp.launch(strand_kernels.hold_in_comb, 1, [xa, wp.array(x, dtype=wp.vec3), start, wp.array(rest, dtype=float),
                                               pinned, t, t, 1.0, 16, contact, 0.01, g, v, strand_kernels.LaneOrder(),
                                               0])
    if grip >= 0:  # a held strand: every particle after the root was moved
        np.testing.assert_array_equal(bounds.numpy(), np.r_[np.ones(pinned), np.full(len(x) - pinned, np.float32(strand_kernels.NO_BOUND))])
    else:
        np.testing.assert_array_equal(bounds.numpy(), 1.0)
    return xa.numpy().astype(np.float64), int(g.numpy()[0]), rest


@pytest.mark.parametrize("reach, expected", [(0.0299, 4), (0.0301, 5), (0.0599, 7), (0.0601, 8), (0.5, 9)])
def test_grip_slides_exactly_when_the_comb_is_beyond_the_natural_length(reach, expected):
    # root = particle 1 (two pinned); the hair from it to particle g is (g - 1) * SPACING long
    x, _ = _hanging([np.zeros(3)])
    direction = np.array([0.6, -0.8, 0.0])
    target = x[1] + reach * direction
    out, grip, rest = _hold(x, 4, target)
    assert grip == expected
    natural = (grip - 1) * SPACING
    if reach <= 0.09:  # reachable: the held particle is on the comb
        np.testing.assert_allclose(out[grip], target, atol=1e-6)
    else:  # the whole strand is too short: pulled straight toward the comb
        np.testing.assert_allclose(out[grip], x[1] + natural * direction, atol=2e-4)
    seg = np.linalg.norm(np.diff(out, axis=0), axis=1)
    # all but the segment at the root keep their length (a nearly taut chain is laid straight, its
    # segments shortened by at most 1 - TAUT = 0.5%)
    np.testing.assert_allclose(seg[2:], rest[3:], rtol=5e-3)
    # that one converges over the sweeps, slowest when the chain is nearly taut (one launch: 16 sweeps)
    assert abs(seg[1] - SPACING) < 0.1 * SPACING
    np.testing.assert_array_equal(out[:2], x[:2].astype(np.float32))


def test_ungripped_strands_are_untouched():
    x, _ = _hanging([np.zeros(3)])
    out, grip, _ = _hold(x, -1, [1.0, 1.0, 1.0])
    assert grip == -1
    np.testing.assert_array_equal(out, x.astype(np.float32))


def test_hidden_hair_behind_the_head_is_never_grabbed():
    collider = _sphere_collider()
    # strands in front of the head and behind it, overlapping on screen
    front = [[x, -0.02, 0.102] for x in np.linspace(-0.04, 0.04, 5)]
    back = [[x, -0.02, -0.102] for x in np.linspace(-0.04, 0.04, 5)]
    points, counts = _hanging(front + back, 12)
    start = np.r_[0, np.cumsum(counts)]
    camera = Camera.look_at([0.0, 0.0, 1.0], [0.0, 0.0, 0.0], width=400, height=400)
    row = camera.project([[0.0, -0.06, 0.102]])[0, 1]  # a stroke across the hair, over the head
    comb = place_comb(camera, [[100, row], [300, row]], collider, points, start)
    assert sorted(comb.strands) == [0, 1, 2, 3, 4]
    held = start[comb.strands] + comb.grip
    np.testing.assert_allclose(points[held, 1], -0.06, atol=SPACING / 2 + 1e-9)
    assert np.all(np.abs(np.linalg.norm(comb.curve, axis=1) - 0.1) < 2e-3)  # the comb lies on the head
    with pytest.raises(ValueError, match="does not touch the head"):
        place_comb(camera, [[0, 0], [20, 0]], collider, points, start)


@pytest.mark.parametrize("drag", [(30.0, -40.0), (0.0, -40.0)])  # the second folds straight hair onto itself
def test_lifted_hair_follows_the_comb_and_falls_when_released(drag):
    collider = _sphere_collider()
    roots = [[x, 0.0, 0.102] for x in np.linspace(-0.03, 0.03, 4)]
    points, counts = _hanging(roots, 12)
    model = StrandBuilder().add_strands(points, counts).finalize("cpu")
    model.bind_to_mesh(collider.posed_points(), collider.faces_np)
    params = HairParams(substeps=4, collision="none", shape_matching="none")
    solver = HairSolver(model, params)
    a, b = model.state(), model.state()
    camera = Camera.look_at([0.0, -0.05, 1.0], [0.0, -0.05, 0.0], width=400, height=400)
    row = camera.project([[0.0, -0.06, 0.102]])[0, 1]
    comb = place_comb(camera, [[120, row], [280, row]], collider, points, model.strand_start.numpy())
    assert len(comb.strands) == 4
    grip = CombGrip(model, comb)
    solver.comb = grip
    offset = comb.drag_offset(drag)  # up (and to the right) on the screen
    assert offset[1] > 0.0 and abs(offset[2]) < 1e-12
    dt = 1.0 / 24 / params.substeps
    for frame in range(6):
        solver.set_clock(frame / 24)
        grip.move_to(offset * min(1.0, (frame + 1) / 3))
        for k in range(1, params.substeps + 1):
            solver.step(a, b, collider, dt, frame / 24 + k * dt)
            a, b = b, a
    x = a.x.numpy().copy()  # on the CPU numpy() is a view of the buffer the next steps reuse
    held = model.strand_start.numpy()[comb.strands] + grip.grips()
    np.testing.assert_allclose(x[held], comb.anchor + offset, atol=1e-5)
    rest = model.rest_length.numpy()
    seg = np.linalg.norm(x[1:] - x[:-1], axis=1)
    inner = np.ones(len(seg), bool)
    inner[np.cumsum(counts)[:-1] - 1] = False
    np.testing.assert_allclose(seg[inner], rest[1:][inner], rtol=0.05)
    solver.comb = None  # release: the lifted hair falls back
    for k in range(12):
        solver.step(a, b, collider, dt, 0.25 + k * dt)
        a, b = b, a
    assert np.all(a.x.numpy()[held, 1] < x[held, 1] - 1e-3)


def test_comb_drag_stays_in_the_plane_facing_the_camera():
    camera = Camera.look_at([1.0, 0.5, 1.0], [0.0, 0.0, 0.0], width=300, height=300)
    comb = Comb(camera, np.zeros((2, 3)), np.zeros(3), -camera.pose[:3, 2], np.zeros(0, int), np.zeros(0, int),
                np.zeros((0, 3)))
    move = comb.drag_offset([25.0, -10.0])
    assert abs(np.dot(move, comb.normal)) < 1e-12
    np.testing.assert_allclose(camera.project([move])[0] - camera.project([np.zeros(3)])[0], [25.0, -10.0], atol=1e-6)


# -- the comb in a scene's timeline --------------------------------------------------------------------
def _timeline_config(events, frames=10, solver=None):
    from sim.scene import _build_config

    data = {"scene": {"frames": frames, "preroll": 0.2, "stats": False}, "head": {"animation": "none"},
            "hair": {"style": "straight", "count": 120, "length": 0.3, "vertices": 12},
            "solver": {"substeps": 4, **(solver or {})}, "haircut": events}
    return _build_config("<test>", data, None)


SIDE = {"eye": [1.0, 0.32, 0.0], "target": [0.0, 0.32, 0.0], "yfov": 0.6, "width": 480, "height": 360}


@pytest.mark.parametrize("in_block", [False, True], ids=["substeps", "frame-in-block"])
def test_a_timeline_comb_lifts_holds_and_releases(in_block, monkeypatch):
    """A comb placed at frame 2 across the side's lengths, lifted 40 px by frame 5, released at 8,
    stepped the way run_scene steps a timeline: the held particles reach the comb, dragged in the
    side view's image plane, stay there, and fall once released. in_block: the hair's frames in one
    launch (HairSolver.frame_in_block, simplified shape matching on the sphere tree), which give way
    to substeps while the comb holds strands."""
    from sim.comb import before_frame
    from sim.haircut import run_events
    from sim.hair_solver import HairSolver
    from sim.scene import Scene

    comb = {"frame": 2, "tool": "comb", "stroke": [[200, 230], [240, 232], [280, 230]], "camera": SIDE,
            "moves": [[5, 0, -40]], "release": 8}
    config = _timeline_config([comb], solver={"shape_matching": "simplified", "collision": "sphere_tree"}
                              if in_block else None)
    scene = Scene(config)
    scene.solver.frame_in_block = in_block
    whole_frames = []
    step_frame = HairSolver.step_frame
    monkeypatch.setattr(HairSolver, "step_frame",
                        lambda *a, **k: whole_frames.append(scene.solver.comb is None) or step_frame(*a, **k))
    scene.advance(config.timing.preroll, animate=False)
    held = {}
    for frame in range(1, 11):
        if frame > 1:
            before_frame(scene, config.haircut, frame)
            scene.advance(1.0 / 24.0)
        run_events(scene, config.haircut, frame)
        grip = scene.held_comb
        if grip is not None:
            at = scene.model.strand_start_np[grip.comb.strands] + grip.grips()
            held[frame] = (scene.state.x.numpy()[at].copy(), grip.comb.anchor + grip.comb.drag_offset([0, -40]), at)
        elif frame >= 8:
            held[frame] = (scene.state.x.numpy()[held[7][2]].copy(), None, held[7][2])
    assert set(held) >= {2, 5, 6, 7, 8, 10} and scene.solver.comb is None
    for frame in (5, 6, 7):
        x, target, _ = held[frame]
        reached = np.linalg.norm(x - target, axis=1) < 1e-3
        assert reached.mean() > 0.8  # the rest were stopped short by the head
    assert np.median(held[7][0][:, 1] - held[2][0][:, 1]) > 0.04  # 40 px at about 0.9 m: 6 cm
    assert np.median(held[10][0][:, 1] - held[7][0][:, 1]) < -0.005  # released, it falls back
    # the preroll before the comb and frames 8 to 10 after its release, none while it holds strands
    assert len(whole_frames) == (8 if in_block else 0) and all(whole_frames)


def test_a_comb_over_the_length_pass_in_lane_order_holds_the_same_strands():
    """The comb resets the contact bounds of the hair it moves in the length pass's own order: with
    the pass in lane order (a GPU's way, here on the CPU) a timeline comb gives the strands of
    particle order bit for bit, head collision on."""
    from sim.comb import before_frame
    from sim.haircut import run_events
    from sim.scene import Scene

    comb = {"frame": 2, "tool": "comb", "stroke": [[200, 230], [240, 232], [280, 230]], "camera": SIDE,
            "moves": [[4, 0, -40]], "release": 6}
    config = _timeline_config([comb])
    assert config.solver.collision != "none"
    results = []
    for lanes in (False, True):
        scene = Scene(config)
        scene.solver = HairSolver(scene.model, config.solver, parts=1)
        scene.solver.lanes = lanes
        scene.advance(config.timing.preroll, animate=False)
        held = 0
        for frame in range(1, 8):
            if frame > 1:
                before_frame(scene, config.haircut, frame)
                scene.advance(1.0 / 24.0)
            run_events(scene, config.haircut, frame)
            held += scene.held_comb is not None
        assert held >= 3
        results.append(scene.state.x.numpy().copy())
    np.testing.assert_array_equal(results[1], results[0])


@pytest.mark.parametrize("change, key", [({"moves": [[1, 0, 5]]}, "moves"), ({"release": 2}, "release"),
                                         ({"stroke": [[5, 5]]}, "stroke"), ({"moves": [[4, 1]]}, "moves")])
def test_bad_comb_tables_name_the_key(change, key):
    from sim.errors import InputError

    comb = {"frame": 2, "tool": "comb", "stroke": [[200, 230], [280, 230]], "camera": SIDE, **change}
    with pytest.raises(InputError) as err:
        _timeline_config([comb])
    assert err.value.key == f"haircut[0].{key}"


@pytest.mark.skipif(not wp.is_cuda_available(), reason="needs CUDA")
def test_comb_and_visibility_kernels_agree_on_cuda():
    """The comb's hold, the sight-line test and the ray hits give the CPU's numbers on a GPU."""
    results = {}
    for device in ("cpu", "cuda:0"):
        with wp.ScopedDevice(device):
            collider = _sphere_collider(device=device)
            x, _ = _hanging([np.zeros(3)])
            out, grip, _ = _hold(x, 4, x[1] + 0.045 * np.array([0.6, -0.8, 0.0]))
            probes = np.array([[0.0, 0.0, 0.3], [0.0, 0.0, -0.3], [0.12, 0.0, 0.0]])
            seen = collider.visible_from(probes, [0.0, 0.0, 1.0])
            hits = collider.ray_hits(np.tile([0.0, 0.0, 1.0], (2, 1)), [[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
            results[device] = (out, grip, seen, hits)
    cpu, gpu = results["cpu"], results["cuda:0"]
    np.testing.assert_allclose(gpu[0], cpu[0], atol=1e-6)
    assert gpu[1] == cpu[1]
    np.testing.assert_array_equal(gpu[2], cpu[2])
    np.testing.assert_allclose(gpu[3], cpu[3], atol=1e-6)
