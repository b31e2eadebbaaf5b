"""Frames captured as graphs (CUDA graphs on a GPU, Warp's recorded CPU graphs on the CPU) give what
stepping the same launches one by one gives, and caches written through the asynchronous read-back
equal those written without graphs. The bookkeeping (eager, then captured, then replayed; restored
buffer references; the fallback after a failed capture) is also checked with a faked capture."""

import threading

import numpy as np
import pytest
import warp as wp

from sim import hair_solver
from sim.graphs import AsyncReadback, FrameGraphs
from sim.scene import Scene, demo_scene, hair_demo_scene, quiet_warp, run_scene
from warp_kernels import strands

quiet_warp()
DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not wp.is_cuda_available(), reason="needs CUDA"))]


def _hair_config(device, graphs):
    # odd substeps: the state ping-pong alternates between two graphs; gusts read the device clock
    return hair_demo_scene({"scene": {"device": device, "frames": 6, "preroll": 0.1, "stats": False,
                                      "graphs": graphs},
                            "hair": {"count": 150, "vertices": 12, "style": "wavy"},
                            "solver": {"substeps": 5, "wind": [1.5, 0.0, 0.5], "wind_turbulence": 0.6}})


def _cloth_config(device, graphs):
    # gusts read the device clock here too
    return demo_scene({"scene": {"device": device, "frames": 5, "preroll": 0.0, "stats": False,
                                 "graphs": graphs},
                       "hair": {"enabled": False}, "face": {"enabled": False}, "cloth.detail": {"level": 3},
                       "cloth.solver": {"wind": [1.5, 0.0, 0.5], "wind_turbulence": 0.6}})


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("make", [_hair_config, _cloth_config], ids=["hair", "cloth"])
def test_graph_frames_equal_eager_frames(make, device):
    results = []
    for graphs in (True, False):
        scene = Scene(make(device, graphs))
        scene.advance(0.1, animate=False)
        for _ in range(5):
            scene.advance(1.0 / scene.config.timing.fps)
            if scene.cloth_detail is not None:
                scene.update_detail()
        out = {}
        if scene.model is not None:
            out["hair"] = scene.state.x.numpy()
        if scene.cloth_model is not None:
            out["cloth"] = scene.cloth_state.x.numpy()
            out["detail"] = scene.cloth_detail.positions.numpy()
        results.append((out, scene.graphs.replays))
    (graph, replays), (eager, none) = results
    # each key runs eagerly once and is captured once (a CUDA capture is then launched; a CPU
    # capture runs as it records), then replays
    assert replays >= 1 and none == 0
    moved = 0.0
    for key in eager:
        np.testing.assert_allclose(graph[key], eager[key], atol=1e-6, err_msg=key)
        moved = max(moved, float(np.abs(eager[key]).max()))
    assert moved > 0.0


@pytest.mark.parametrize("proxy", [0.0, 0.04])
def test_hair_and_cloth_frames_side_by_side_equal_one_after_the_other(monkeypatch, proxy):
    """On the CPU the hair's and the cloth's replayed frames run at the same time, each posing its
    own twin of the body (or the cloth a collision proxy, and a twin at the frame's end), with the
    detail surface updated on the cloth's side: hair, garment and detail surface equal stepping one
    solver after the other bit for bit, and both twins end each frame in the same pose."""
    import sim.scene as scene_module

    calls = []
    side_by_side = scene_module.run_side_by_side
    monkeypatch.setattr(scene_module, "run_side_by_side", lambda tasks: (calls.append(len(tasks)), side_by_side(tasks)))
    config = demo_scene({"scene": {"device": "cpu", "fps": 30.0, "frames": 1, "preroll": 0.0, "stats": False},
                         "hair": {"count": 60, "vertices": 10}, "face": {"enabled": False},
                         "solver": {"substeps": 3, "collision": "sphere_tree"}, "cloth.detail": {"level": 2},
                         "cloth.solver": {"body_proxy": proxy}})
    frames = 12
    results = []
    for together in (False, True):
        calls.clear()
        scene = Scene(config)
        scene.side_by_side = together
        scene.solver.set_parts(2)  # one range per core, as the solver starts on two cores
        assert scene.cloth_body is not scene.collider and scene.cloth_body.points.ptr != scene.collider.points.ptr
        assert (scene.cloth_collider is scene.cloth_body) == (proxy == 0.0)
        detail = []
        for _ in range(frames):
            scene.advance(1.0 / 30.0, detail=True)
            detail.append(scene.detail_surface()[0].numpy().copy())
            np.testing.assert_array_equal(scene.cloth_body.points.numpy(), scene.collider.points.numpy())
        # each solver's frames run eagerly, then are captured; after that both replay at once
        assert len(scene.solver.parts) == 2
        assert (len(calls) >= frames - 4 and set(calls) == {2}) if together else calls == []
        results.append((scene.state.x.numpy(), scene.cloth_state.x.numpy(), np.stack(detail)))
    for serial, together in zip(*results):
        np.testing.assert_array_equal(serial, together)
    assert np.abs(results[0][2][-1] - results[0][2][0]).max() > 1e-3  # the body walked the dress along


@pytest.mark.parametrize("proxy", [0.0, 0.04])
def test_a_cloth_frame_refits_the_detail_surfaces_body_beside_its_substeps(proxy):
    """The detail surface's lift queries the body's mesh after the cloth's frame: a CPU frame refits
    its BVH beside the last substep (the cloth collides with the body's swept triangle boxes, not the
    mesh), or, colliding with a proxy, poses the body beside all the substeps, on another core. The
    garment and its detail surface are the eager frames' bit for bit, and the body's BVH is fresh
    after each frame."""
    config = demo_scene({"scene": {"device": "cpu", "fps": 30.0, "frames": 1, "preroll": 0.0, "stats": False},
                         "hair": {"enabled": False}, "face": {"enabled": False}, "cloth.detail": {"level": 2},
                         "cloth.solver": {"body_proxy": proxy}})
    results = []
    for graphs in (True, False):
        scene = Scene(config)
        scene.graphs.enabled = graphs
        for _ in range(4):
            scene.advance(1.0 / 30.0, detail=True)
            assert not scene.cloth_body.bvh_stale
        results.append((scene.cloth_state.x.numpy(), scene.detail_surface()[0].numpy()))
        if graphs:
            cloth = [graph for key, (graph, _) in scene.graphs._graphs.items() if key[0] == "cloth"]
            for graph in cloth:
                beside = [step for step in graph.steps if isinstance(step, tuple)
                          and any(callable(s) for branch in step for s in branch.steps)]
                assert len(beside) == 1 and len(beside[0]) == 2  # the substeps (or the last), and the body's pose
            assert cloth
    for with_graphs, eager in zip(*results):
        np.testing.assert_array_equal(with_graphs, eager)


def test_one_motion_evaluation_poses_every_solver_at_its_own_substep_times(monkeypatch):
    """A frame evaluates the body's motion once, at the union of the solvers' substep times (hair
    at 4 and cloth at 12 substeps share the hair's 5 times); each solver gets the poses of its own
    times, bit for bit as if the motion were evaluated for it alone."""
    scene = Scene(demo_scene({"scene": {"device": "cpu", "fps": 60.0, "frames": 1, "preroll": 0.0, "stats": False},
                              "hair": {"count": 20, "vertices": 8}, "face": {"enabled": False},
                              "solver": {"substeps": 4}, "cloth.detail": {"level": 0}}))
    evaluated = []
    motion_poses = scene._motion_poses
    monkeypatch.setattr(scene, "_motion_poses", lambda times: (evaluated.append(len(times)), motion_poses(times))[1])
    t0, frame_dt = 0.3, 1.0 / 60.0
    for frame in range(3):
        poses = scene._substep_poses(t0, frame_dt, [4, 12], animate=True)
        assert evaluated == [13] * (frame + 1)  # 5 + 13 times, 5 of them shared
        for n in (4, 12):
            times, got = poses[n]
            np.testing.assert_allclose(times, t0 + frame_dt * np.arange(n + 1) / n, rtol=0, atol=1e-12)
            np.testing.assert_array_equal(got, motion_poses(times))
        np.testing.assert_array_equal(poses[4][1], poses[12][1][::3])
        assert np.abs(poses[12][1][-1] - poses[12][1][0]).max() > 1e-3  # the body moves within the frame
        t0 = t0 + frame_dt  # as advance steps the clock
    held = scene._substep_poses(t0, frame_dt, [4, 12], animate=False)
    np.testing.assert_allclose(held[12][1], np.broadcast_to(motion_poses(np.array([t0])), held[12][1].shape), atol=1e-6)
    assert scene._substep_poses(t0, frame_dt, [], animate=True) == {}


def test_detail_surface_is_updated_once_per_frame():
    """Each update of the detail surface carries its wrinkle heights a frame further, so asking for
    this frame's surface twice, or after advance(detail=True) made it, does not update it again."""
    def scene():
        return Scene(demo_scene({"scene": {"device": "cpu", "frames": 1, "preroll": 0.0, "stats": False},
                                 "hair": {"enabled": False}, "face": {"enabled": False},
                                 "cloth.detail": {"level": 3}}))

    once, asked = scene(), scene()
    for _ in range(3):
        once.advance(1.0 / 24.0)
        once.update_detail()
        asked.advance(1.0 / 24.0, detail=True)
        first = asked.detail_surface()[0].numpy().copy()
        np.testing.assert_array_equal(asked.detail_surface()[0].numpy(), first)
    np.testing.assert_array_equal(asked.cloth_detail.height.numpy(), once.cloth_detail.height.numpy())
    assert once.cloth_detail.height.numpy().max() > 0.0
    once.update_detail()  # an explicit update does carry the heights again
    assert not np.array_equal(asked.cloth_detail.height.numpy(), once.cloth_detail.height.numpy())


def test_hair_in_strand_ranges_side_by_side_equals_one_range():
    """A CPU frame steps the solver's strand ranges as branches replayed on threads at once: three
    ranges (more than this machine may have cores) give the one-range strands bit for bit, and the
    replayed frames do hold the parallel steps."""
    from sim.hair_solver import HairSolver

    results = []
    for parts in (1, 3):
        scene = Scene(_hair_config("cpu", True))
        scene.solver = HairSolver(scene.model, scene.config.solver, parts=parts)
        assert len(scene.solver.parts) == parts
        assert sum(r.strands for r in scene.solver.parts) == scene.model.num_strands
        scene.advance(0.1, animate=False)
        for _ in range(5):
            scene.advance(1.0 / scene.config.timing.fps)
        steps = [step for graph, _ in scene.graphs._graphs.values() for step in graph.steps]
        branched = [step for step in steps if isinstance(step, tuple)]
        # each substep first refits the mesh beside the motion measure (two branches), then steps the ranges
        ranges = [step for step in branched if len(step) != 2]
        assert len(branched) - len(ranges) == 10  # 5 substeps in each of the two graphs
        assert (len(ranges) > 0) == (parts > 1) and all(len(step) == parts for step in ranges)
        results.append(scene.state.x.numpy())
    np.testing.assert_array_equal(results[0], results[1])
    assert np.abs(results[0] - Scene(_hair_config("cpu", True)).state.x.numpy()).max() > 0.01  # the hair moved


def _parallel_steps(recorded):
    """The parallel steps (tuples of branches) of recorded CPU frames, those inside branches too."""
    found = []
    for frame in recorded:
        for step in frame.steps:
            if isinstance(step, tuple):
                found.append(step)
                found += _parallel_steps(step)
    return found


def test_cloth_in_particle_ranges_with_a_split_sweep_equals_one_range(monkeypatch):
    """A CPU frame of the cloth alone sweeps the body's poses in ranges of its points and collides
    its particles in ranges, each a branch replayed on threads at once: three ranges of each give the
    garment, the detail surface and the count of BVH queries of one range bit for bit, and the
    replayed frames do hold the parallel steps."""
    import sim.collider as collider_module

    results = []
    for parts in (1, 3):
        monkeypatch.setattr(collider_module, "SWEEP_POINTS_PER_CORE", 1 if parts > 1 else 10**9)
        monkeypatch.setattr(collider_module, "core_slices", lambda dim, device, per_core=1, n=parts: n)
        scene = Scene(_cloth_config("cpu", True))
        scene.cloth_solver.set_parts(parts)
        scene.cloth_detail.split_levels(1)  # the detail's lift in one range: only the cloth's branches are counted
        for _ in range(6):
            scene.advance(1.0 / scene.config.timing.fps, detail=True)
        steps = _parallel_steps(graph for graph, _ in scene.graphs._graphs.values())
        # besides the ranges, the last substep runs beside the refit of the body's BVH for the detail
        branched = [len(step) for step in steps if not any(callable(s) for branch in step for s in branch.steps)]
        # per frame one sweep and a collision per cloth substep (with strain limiting, two)
        assert len(branched) >= scene.cloth_substeps + 1 if parts > 1 else branched == []
        assert set(branched) <= {parts} and len(steps) > len(branched)
        results.append((scene.cloth_state.x.numpy(), scene.detail_surface()[0].numpy(),
                        scene.cloth_solver.fallback_count(), scene.cloth_collider.moved.numpy()))
    for one, split in zip(*results):
        np.testing.assert_array_equal(one, split)
    assert results[0][2] > 0  # the walk did fall back to the BVH


@pytest.mark.parametrize("device", DEVICES)
def test_async_readback_caches_equal(tmp_path, device):
    from io_usd.cache import CacheReader

    paths = []
    for graphs in (True, False):
        paths.append(tmp_path / f"hair_{graphs}.usdc")
        run_scene(_hair_config(device, graphs), paths[-1], progress=False)
    a, b = CacheReader(paths[0]), CacheReader(paths[1])
    assert a.frames("hair") == b.frames("hair") and len(a.frames("hair")) == 6
    for f in a.frames("hair"):
        np.testing.assert_allclose(a.points("hair", f), b.points("hair", f), atol=1e-6)


class FakeCapture:
    """Stands in for wp.ScopedCapture: records that a capture happened and hands out a token."""

    count = 0
    fail = False

    def __init__(self, device=None, **kwargs):
        self.graph = None

    def __enter__(self):
        if FakeCapture.fail:
            raise RuntimeError("operation not permitted when stream is capturing")
        FakeCapture.count += 1
        self.graph = f"graph{FakeCapture.count}"
        return self

    def __exit__(self, *exc):
        return False


@pytest.fixture
def fake_graphs(monkeypatch):
    launched = []
    FakeCapture.count, FakeCapture.fail = 0, False
    monkeypatch.setattr(wp, "ScopedCapture", FakeCapture)
    monkeypatch.setattr(wp, "capture_launch", lambda graph: launched.append(graph))
    graphs = FrameGraphs("cuda" if wp.is_cuda_available() else "cpu")
    graphs.device = type("FakeCuda", (), {"is_cuda": True, "is_cpu": False})()  # a launch follows a capture
    return graphs, launched


def test_frames_run_eager_then_captured_then_replayed_with_references_restored(fake_graphs):
    graphs, launched = fake_graphs
    buffers = ["a", "b"]
    calls = []

    def frame():  # an odd number of ping-pong swaps per frame, like 5 substeps
        calls.append(tuple(buffers))
        for _ in range(3):
            buffers.reverse()

    refs = (lambda: tuple(buffers)), (lambda value: buffers.__setitem__(slice(None), value))
    seen = []
    for _ in range(6):
        graphs.run(("hair", buffers[0]), frame, refs)
        seen.append(buffers[0])
    # every frame ends in the other buffer, with or without a graph
    assert seen == ["b", "a", "b", "a", "b", "a"]
    # two keys (one per starting buffer): each runs eagerly once, is captured (and launched) once,
    # then replays
    assert calls == [("a", "b"), ("b", "a"), ("a", "b"), ("b", "a")]
    assert launched == ["graph1", "graph2", "graph1", "graph2"] and graphs.replays == 4


def test_a_failed_capture_falls_back_to_eager_frames_without_losing_a_frame(fake_graphs):
    graphs, launched = fake_graphs
    FakeCapture.fail = True
    state = {"frames": 0, "buffer": "a"}

    def frame():
        state["frames"] += 1
        state["buffer"] = "b" if state["buffer"] == "a" else "a"

    refs = (lambda: state["buffer"]), (lambda value: state.__setitem__("buffer", value))
    with pytest.warns(RuntimeWarning, match="graph capture failed"):
        for _ in range(3):
            graphs.run("cloth", frame, refs)
    assert state["frames"] == 3 and state["buffer"] == "b"  # three real frames, references consistent
    assert not graphs.enabled and launched == []


def test_clear_forgets_captured_frames(fake_graphs):
    graphs, launched = fake_graphs
    for _ in range(3):
        graphs.run("detail", lambda: None)
    graphs.clear()
    graphs.run("detail", lambda: None)  # eager again after clear
    assert launched == ["graph1", "graph1"]


def test_async_readback_on_the_cpu_copies_at_once():
    a = wp.array(np.arange(12, dtype=np.float32).reshape(4, 3), dtype=wp.vec3)
    wait = AsyncReadback("cpu").begin({"x": a})
    a.fill_(wp.vec3(9.0, 9.0, 9.0))  # later work must not change what was read back
    np.testing.assert_array_equal(wait()["x"], np.arange(12, dtype=np.float32).reshape(4, 3))


def _count_refits(monkeypatch):
    """A list that gains an item at every refit of a wp.Mesh's BVH."""
    refits = []
    refit = wp.Mesh.refit
    monkeypatch.setattr(wp.Mesh, "refit", lambda mesh: (refits.append(1), refit(mesh))[1])
    return refits


def _three_hair_frames(collision, refit_every_pose, refits, head=None, contact_bounds=True):
    """A small groom's scene after three frames (eager, captured, replayed) of 4 substeps colliding by
    `collision`, `refits` cleared after the scene is built; refit_every_pose: every pose refits the
    BVH first, as Collider.apply_pose's default does."""
    scene = Scene(hair_demo_scene({"scene": {"device": "cpu", "frames": 3, "preroll": 0.0, "stats": False},
                                   "head": head or {}, "hair": {"count": 60, "vertices": 10, "style": "wavy"},
                                   "solver": {"substeps": 4, "collision": collision}}))
    scene.solver.contact_bounds = contact_bounds
    if refit_every_pose:
        pose = scene.collider.apply_pose
        scene.collider.apply_pose = lambda k, refit=True, listed=None, pose=pose: pose(k, True)
    refits.clear()
    for _ in range(3):
        scene.advance(1.0 / scene.config.timing.fps)
    return scene


def test_sphere_tree_hair_frames_leave_the_bvh_to_the_first_query_and_step_the_same_hair(monkeypatch):
    """Hair colliding with the sphere tree makes no mesh queries, so its frames do not refit the
    collider's BVH, and poses before a frame's last move only the root triangles' vertices: the
    strands and the frame's final body are bit-identical to posing all of it and refitting every
    substep, and the first host query after the frames refits it once and answers as one built on
    the posed mesh."""
    refits = _count_refits(monkeypatch)
    results = []
    for always in (False, True):
        scene = _three_hair_frames("sphere_tree", always, refits, {"sphere_leaves": 128})
        results.append((scene.state.x.numpy(), scene.collider.points.numpy(), len(refits)))
        if not always:
            listed = scene._hair_root_vertices().numpy()
            assert 0 < len(listed) < len(scene.collider.points) / 10  # the first query refits the BVH to the posed mesh, later ones do not
            rng = np.random.default_rng(1)
            points = scene.collider.points.numpy()[rng.choice(len(scene.collider.points), 300)]
            points += rng.normal(scale=0.01, size=points.shape)
            got, _, _ = scene.collider.closest_points(points)
            again, _, _ = scene.collider.closest_points(points)
            assert len(refits) == 1
            scene.collider.mesh.refit()
            np.testing.assert_array_equal(got, scene.collider.closest_points(points)[0])
            np.testing.assert_array_equal(again, got)
    (lean, lean_body, lean_refits), (full, full_body, full_refits) = results
    np.testing.assert_array_equal(lean, full)
    np.testing.assert_array_equal(lean_body, full_body)
    assert (lean_refits, full_refits) == (0, 15)  # none against one per pose (the frame's first and 4 substeps)


def test_mesh_hair_refits_the_bvh_beside_its_motion_measure_and_steps_the_same_hair(monkeypatch):
    """Hair colliding with the mesh refits the collider's BVH itself, in a branch beside the launches
    that measure the body's motion (which do not read it), instead of the pose refitting it before:
    on the CPU the refit then has a core of its own; without contact bounds (no measure) it refits
    alone. The strands are bit-identical to posing and refitting first, with one refit per substep
    all the same, and after the frames the BVH is fresh: a host query answers without refitting it
    again."""
    refits = _count_refits(monkeypatch)
    results = []
    for first, bounds in ((True, True), (False, True), (False, False)):
        scene = _three_hair_frames("mesh", first, refits, contact_bounds=bounds)
        assert not scene.collider.bvh_stale
        results.append((scene.state.x.numpy(), len(refits)))
        if not first:
            steps = [step for graph, _ in scene.graphs._graphs.values() for step in graph.steps]
            beside = [step for step in steps if isinstance(step, tuple) and any(callable(s) for s in step[1].steps)]
            # each captured frame's 4 substeps: the motion's launches, and the refit
            assert len(beside) % 4 == 0 and (len(beside) > 0) == bounds and all(len(step) == 2 for step in beside)
            points = scene.collider.points.numpy()[::97] + 0.003
            got, _, _ = scene.collider.closest_points(points)
            assert len(refits) == 12
            scene.collider.mesh.refit()
            np.testing.assert_array_equal(got, scene.collider.closest_points(points)[0])
    (first_x, first_refits), *beside = results
    for x, refit_count in beside:
        np.testing.assert_array_equal(x, first_x)
        assert refit_count == 12  # one per substep
    assert first_refits == 15  # posing first also refits each frame's first pose
    assert np.abs(first_x - Scene(scene.config).state.x.numpy()).max() > 0.01  # the hair moved


def test_calls_on_the_cores_run_once_each_nest_and_raise_their_errors(monkeypatch):
    """run_on_cores runs every call exactly once on at most one thread per core, returns only once
    the calls other threads took are done, runs a step inside one of its calls (a branch's own
    parallel step) without waiting on itself, and raises an error from any call."""
    import time as clock

    import sim.graphs as graphs

    monkeypatch.setattr(graphs, "cpu_cores", lambda: 2)
    ran, lock = [], threading.Lock()

    def call(name, seconds=0.0, inner=()):
        def run():
            clock.sleep(seconds)
            if inner:
                graphs.run_on_cores([call(f"{name}.{k}", seconds) for k in inner])
            with lock:
                ran.append((name, threading.get_ident()))
        return run

    graphs.run_on_cores([call(k, 0.01) for k in "abcd"] + [call("e", 0.01, inner=(0, 1, 2))])
    assert sorted(name for name, _ in ran) == ["a", "b", "c", "d", "e", "e.0", "e.1", "e.2"]
    assert len({thread for _, thread in ran}) <= 3  # this thread and the pool's, two at a time

    def fail():
        clock.sleep(0.02)  # taken by whichever thread is free: a helper's error reaches the caller too
        raise RuntimeError("bad call")

    for order in ([fail, call("x")], [call("y", 0.01), fail]):
        with pytest.raises(RuntimeError, match="bad call"):
            graphs.run_on_cores(order)


def test_frames_side_by_side_share_the_cores_without_more_threads_than_cores(monkeypatch):
    """A frame's parallel branches, beside another frame on two cores: its own thread replays them,
    the other frame's thread helps once its frame is done, every branch runs once, no third thread
    joins in, and an error in a branch reaches the caller."""
    import time as clock

    import sim.graphs as graphs

    monkeypatch.setattr(graphs, "cpu_cores", lambda: 2)
    ran, busy = [], []

    def replay(graph):
        busy.append(1)
        assert len(busy) <= 2  # never more branches at once than cores
        ran.append((graph, threading.get_ident()))
        clock.sleep(0.02)
        busy.pop()
        if graph == "bad":
            raise RuntimeError("bad branch")

    class Branch:  # a recorded branch whose replay only notes itself
        def __init__(self, name):
            self.launch = lambda: replay(name)

    threads = {}

    def hair():
        threads["hair"] = threading.get_ident()
        for step in range(3):
            graphs._sharing.run_branches(tuple(Branch(f"{step}.{k}") for k in range(4)))

    def cloth():
        threads["cloth"] = threading.get_ident()
        clock.sleep(0.05)  # done early: helps the hair after this

    graphs.run_side_by_side([hair, cloth])
    assert sorted(g for g, _ in ran) == sorted(f"{s}.{k}" for s in range(3) for k in range(4))
    helpers = {t for _, t in ran}
    assert helpers == {threads["hair"], threads["cloth"]}  # the cloth's thread helped, no other did
    assert graphs._sharing is None

    ran.clear()
    with pytest.raises(RuntimeError, match="bad branch"):
        graphs.run_side_by_side([lambda: graphs._sharing.run_branches(tuple(map(Branch, ("ok", "bad", "ok2")))),
                                 lambda: None])
    assert sorted(g for g, _ in ran) == ["bad", "ok", "ok2"]


def _fast_hair_config(device):
    return hair_demo_scene({"scene": {"device": device, "frames": 4, "preroll": 0.0, "stats": False},
                            "head": {"sphere_leaves": 128, "animation": "turn_nod"},
                            "hair": {"count": 200, "vertices": 16, "style": "wavy"},
                            "solver": {"substeps": 4, "collision": "sphere_tree", "shape_matching": "simplified",
                                       "shape_iterations": 1}})


def _proxy_dress_config(device):
    return demo_scene({"scene": {"device": device, "frames": 4, "preroll": 0.0, "stats": False},
                       "hair": {"enabled": False}, "face": {"enabled": False},
                       "cloth.solver": {"body_proxy": 0.025}, "cloth.detail": {"level": 4}})


@pytest.mark.skipif(not wp.is_cuda_available(), reason="needs CUDA")
@pytest.mark.parametrize("make,fused_from", [(_fast_hair_config, None), (_fast_hair_config, 1), (_proxy_dress_config, None)],
                         ids=["hair-spheres", "hair-spheres-fused", "dress-proxy"])
def test_cuda_frames_follow_cpu_frames(make, fused_from, monkeypatch):
    """The real-time paths (sphere-tree hair with listed skinning and contact bounds; the dress
    against its proxy with a walked detail lift) give on CUDA what they give on the CPU, to float32
    rounding carried over a few animated frames, and to the collision margin where the GPU's loose
    lists spare a walk. fused_from: the strands from which a GPU steps fused with the frame in lanes
    (hair_solver.FUSED_GPU_STRANDS, lowered so that this small head of hair takes the way of 100k)."""
    if fused_from is not None:
        monkeypatch.setattr(hair_solver, "FUSED_GPU_STRANDS", fused_from)
    out = []
    for device in ("cpu", "cuda"):
        scene = Scene(make(device))
        if fused_from is not None and device == "cuda":
            assert scene.solver.fused and scene.solver.frame_lanes
        start = (scene.state if scene.model is not None else scene.cloth_state).x.numpy().copy()
        for _ in range(4):
            scene.advance(1.0 / scene.config.timing.fps)
            if scene.cloth_detail is not None:
                scene.update_detail()
        if scene.model is not None:
            out.append({"hair": scene.state.x.numpy()})
        else:
            out.append({"cloth": scene.cloth_state.x.numpy(), "detail": scene.cloth_detail.positions.numpy()})
        moved = out[-1]["hair" if scene.model is not None else "cloth"]
        assert np.abs(moved - start).max() > 0.01, device  # the frames did move the hair or the dress
    for key in out[0]:
        assert np.isfinite(out[1][key]).all(), key
        np.testing.assert_allclose(out[1][key], out[0][key], atol=2e-3, err_msg=key)


def _same_hair_frames(make, device, configure):
    """Four captured frames of the scene make(device) with its solver set by configure(solver, False)
    and then configure(solver, True): the same hair, to float32 rounding (bit for bit on the CPU)."""
    out = []
    for way in (False, True):
        scene = Scene(make(device))
        configure(scene.solver, way)
        start = scene.state.x.numpy().copy()
        for _ in range(4):
            scene.advance(1.0 / scene.config.timing.fps)
        out.append(scene.state.x.numpy())
        assert np.abs(out[-1] - start).max() > 0.01  # the frames moved the hair
    assert np.isfinite(out[1]).all()
    np.testing.assert_allclose(out[1], out[0], atol=1e-4)
    if device == "cpu":
        np.testing.assert_array_equal(out[1], out[0])


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("make", [lambda device: _hair_config(device, True), _fast_hair_config],
                         ids=["hair-mesh", "hair-spheres"])
def test_fused_hair_frames_follow_the_launches_apart(make, device):
    """strands.step_strands (HairSolver.fused; on CUDA only for many strands) captured in the frame's graph,
    with the device's defaults (on CUDA lane order and the sphere tree's walks queued ahead): the
    frames of the launches apart, to float32 rounding (bit for bit on the CPU)."""
    def configure(solver, fused):
        solver.fused = fused
        solver.loose_lists = False  # the loose lists' walks differ between the two passes, within the margin

    _same_hair_frames(make, device, configure)


@pytest.mark.parametrize("device", DEVICES)
def test_read_ahead_length_pass_frames_follow_the_pass_in_turn(device):
    """The length pass that reads each particle a step ahead (HairSolver.read_ahead, a GPU's option)
    captured in the frame's graph with the device's other defaults: the frames of the pass reading in
    turn, to float32 rounding (bit for bit on the CPU)."""
    def configure(solver, ahead):
        solver.fused = False  # the length pass is its own launch
        solver.read_ahead = ahead
        solver.loose_lists = False  # which reading ahead excludes

    _same_hair_frames(_fast_hair_config, device, configure)


@pytest.mark.parametrize("device", DEVICES)
def test_a_frame_kept_in_lanes_follows_the_fused_frames(device):
    """The scene's captured hair frames with the state kept in lane order across each frame
    (HairSolver.frame_lanes, begin_frame and end_frame around the substeps): the frames of the fused
    substeps on the particle-order state, bit for bit on the CPU, to float32 rounding on CUDA."""
    kept_frames = []

    def configure(solver, kept):
        solver.set_parts(1)
        solver.fused, solver.lanes, solver.frame_lanes = True, True, kept
        solver.loose_lists = False
        kept_frames.append(solver)

    _same_hair_frames(_fast_hair_config, device, configure)
    assert [solver._frame is not None for solver in kept_frames] == [False, True]


def _free_hair_config(device):
    # no collider, two shape passes, gusts that read each substep's time; odd substeps
    return hair_demo_scene({"scene": {"device": device, "frames": 4, "preroll": 0.0, "stats": False},
                            "head": {"animation": "turn_nod"},
                            "hair": {"count": 120, "vertices": 12, "style": "wavy"},
                            "solver": {"substeps": 5, "collision": "none", "shape_matching": "simplified",
                                       "shape_iterations": 2, "wind": [1.5, 0.0, 0.5], "wind_turbulence": 0.6}})


def _long_hair_config(device):
    # strands of 40 particles: blocks of 64 lanes, 24 of them past every tip
    return hair_demo_scene({"scene": {"device": device, "frames": 4, "preroll": 0.0, "stats": False},
                            "head": {"sphere_leaves": 128, "animation": "turn_nod"},
                            "hair": {"count": 60, "vertices": 40, "style": "straight"},
                            "solver": {"substeps": 4, "collision": "sphere_tree", "shape_matching": "simplified",
                                       "shape_iterations": 1}})


def _mesh_hair_config(device):
    return hair_demo_scene({"scene": {"device": device, "frames": 4, "preroll": 0.0, "stats": False},
                            "head": {"sphere_leaves": 128, "animation": "turn_nod"},
                            "hair": {"count": 150, "vertices": 16, "style": "wavy"},
                            "solver": {"substeps": 4, "collision": "mesh", "shape_matching": "simplified",
                                       "shape_iterations": 1}})


def _full_mesh_config(device):
    # the default model, full shape matching (windows of 6) against the mesh, on the turning head
    return hair_demo_scene({"scene": {"device": device, "frames": 4, "preroll": 0.0, "stats": False},
                            "head": {"animation": "turn_nod"},
                            "hair": {"count": 120, "vertices": 16, "style": "curly"},
                            "solver": {"substeps": 4}})


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("make,way", [(_fast_hair_config, "in_block"), (_free_hair_config, "in_block"),
                                      (_long_hair_config, "in_block"), (_mesh_hair_config, "in_block"),
                                      (_full_mesh_config, "in_block"), (_fast_hair_config, "in_warps"),
                                      (_free_hair_config, "in_warps"), (_mesh_hair_config, "in_warps"),
                                      (_full_mesh_config, "in_warps"), (_fast_hair_config, (8, 4, 4)),
                                      (_full_mesh_config, (1, 8, 2))],
                         ids=["spheres", "no-collider", "64-lanes", "mesh", "full-mesh", "spheres-in-warps",
                              "no-collider-in-warps", "mesh-in-warps", "full-mesh-in-warps", "spheres-8x4x4",
                              "full-mesh-1x8x2"])
def test_frames_in_block_follow_the_substeps(make, way, device):
    """A whole frame in one launch (HairSolver.frame_in_block, the collider posed for every substep ahead,
    against the mesh a BVH for each pose), a block of lanes per strand (strands.FRAME_IN_BLOCK), 32
    strands a block side by side (frame_warps, strands.FRAME_IN_WARPS) or another layout (frame_layout:
    8 strands a block in 4 runs of 4 particles; a block per strand in 8 runs of 2), captured in the frame's
    graph: the frames of the substeps one by one, to float32 rounding (bit for bit on the CPU)."""
    def configure(solver, whole):
        solver.loose_lists = False  # the loose lists' walks differ, within the margin
        solver.mesh_lists = False  # the frame queries the mesh's BVH, as a GPU does
        solver.step_frames_as((way if isinstance(way, str) else "in_block") if whole else "substeps")
        if whole and not isinstance(way, str):
            solver.frame_layout = way
        assert not (whole and solver.lanes)

    _same_hair_frames(make, device, configure)


def test_a_frame_in_block_poses_the_collider_at_once_as_the_substeps_do(monkeypatch):
    """A skinned collider's poses for a frame in block are made in six launches (HairSolver._skin_frame,
    strands.FRAME_POSES) instead of applied substep by substep: the same hair bit for bit, and the
    collider left where the substeps leave it (every vertex and sphere at the frame's last pose)."""
    made = []
    skin_frame = hair_solver.HairSolver._skin_frame
    monkeypatch.setattr(hair_solver.HairSolver, "_skin_frame", lambda *a: made.append(1) or skin_frame(*a))
    out = []
    for whole in (False, True):
        scene = Scene(_fast_hair_config("cpu"))
        scene.solver.frame_in_block = whole
        for _ in range(3):
            scene.advance(1.0 / scene.config.timing.fps)
        c = scene.collider
        out.append([scene.state.x.numpy(), scene.state.v.numpy(), c.points.numpy(), c.sphere_nodes.numpy()])
    assert len(made) == 3
    for name, a, b in zip(("x", "v", "collider points", "sphere tree"), *out, strict=True):
        np.testing.assert_array_equal(b, a, err_msg=name)

@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("warps", [False, True], ids=["block-a-strand", "in-warps"])
def test_frames_in_block_with_loose_lists_follow_the_fused_substeps(warps, device):
    """frame_in_block with loose lists (a GPU's way: every lane walks for its own list that would run
    short before the chain, the chain walks only inside unlisted leaves): the frames of the fused
    substeps with their walks queued ahead and loose lists, to float32 rounding (bit for bit on the
    CPU), and on the CPU the same lists and contact bounds."""
    solvers = []

    def configure(solver, whole):
        solver.fused, solver.leaves_ahead, solver.loose_lists = True, True, True
        solver.frame_in_block, solver.frame_warps = whole, warps
        solvers.append(solver)

    _same_hair_frames(_fast_hair_config, device, configure)
    if device == "cpu":
        for bounds, block_bounds in zip(solvers[0].particle_bounds(), solvers[1].particle_bounds(), strict=True):
            np.testing.assert_array_equal(block_bounds, bounds)

def test_a_frame_in_block_names_what_it_cannot_step():
    """frame_in_block takes strands of up to 64 particles and up to FRAME_SUBSTEPS substeps: otherwise
    the scene's first frame raises, naming why, before it moves the collider or the hair."""
    from dataclasses import replace

    from sim.strands import StrandBuilder

    scene = Scene(hair_demo_scene({"scene": {"device": "cpu", "frames": 1, "preroll": 0.0, "stats": False},
                                   "hair": {"count": 20, "vertices": 70}, "solver": {"substeps": 2}}))
    scene.solver.frame_in_block = True
    start = scene.state.x.numpy().copy()
    points = scene.collider.points.numpy().copy()
    with pytest.raises(ValueError, match="70"):
        scene.advance(1.0 / scene.config.timing.fps)
    np.testing.assert_array_equal(scene.state.x.numpy(), start)
    np.testing.assert_array_equal(scene.collider.points.numpy(), points)
    scene = Scene(_hair_config("cpu", False))  # full shape matching against the mesh
    solver = hair_solver.HairSolver(scene.model, scene.solver.params)
    assert solver.frame_in_block_misfit(scene.collider) is None
    assert solver.frame_in_block_misfit(None) is None
    solver = hair_solver.HairSolver(scene.model, replace(solver.params, substeps=40))
    assert "40" in solver.frame_in_block_misfit(None)
    points = np.stack([np.zeros(70), -np.linspace(0.0, 0.7, 70), np.zeros(70)], axis=1)
    model = StrandBuilder().add_strands(points, [70], np.full(70, 1e-4)).finalize("cpu", pinned_per_strand=2)
    solver = hair_solver.HairSolver(model, hair_solver.HairParams(collision="none", shape_matching="none"))
    assert "70" in solver.frame_in_block_misfit(None)
    model = StrandBuilder().add_strands(points[:40], [40], np.full(40, 1e-4)).finalize("cpu", pinned_per_strand=2)
    solver = hair_solver.HairSolver(model, hair_solver.HairParams(collision="none", shape_matching="none"))
    assert solver.frame_in_block_misfit(None) is None  # a block of 64 lanes per strand
    solver.step_frames_as("in_warps")
    assert "hair frames in_warps take strands of at most 32 particles, not 40" in solver.frame_in_block_misfit(None)
    solver.frame_layout = (16, 8, 5)  # runs of 5: 40 particles
    assert solver.frame_layout_used() == (16, 8, 5) and solver.frame_in_block_misfit(None) is None
    solver.frame_layout = (16, 8, 4)
    assert "hair frames in layout 16x8x4 take strands of at most 32 particles" in solver.frame_in_block_misfit(None)
    solver.frame_layout = (64, 32, 2)
    assert "at most 1024 threads a block (side x groups), not 64x32x2" in solver.frame_in_block_misfit(None)
    solver.frame_layout = (16, 8)
    assert "not 16x8" in solver.frame_in_block_misfit(None)
    with pytest.raises(ValueError, match="64x32x2"):
        strands.frame_variant((64, 32, 2), strands.PATHS_NONE)
    with pytest.raises(ValueError, match="in_warps"):
        solver.step_frames_as("warps")


@pytest.mark.parametrize("device", DEVICES)
def test_frames_in_warps_step_strands_of_mixed_lengths(device):
    """FRAME_IN_WARPS' layout after a blunt cut (strands of 3 to 16 particles side by side in a block, each lane's
    chain ending at its own tip, windows only inside each strand): the frames of the substeps, to float32
    rounding (bit for bit on the CPU)."""
    from sim import haircut

    out = []
    for way in ("substeps", "in_warps"):
        scene = Scene(_fast_hair_config(device))
        scene.solver.loose_lists = False
        scene.advance(1.0 / scene.config.timing.fps)
        haircut.blunt_cut(scene, haircut.Plane(point=(0.0, 0.3, 0.0), normal=(0.0, 1.0, 0.25)))
        counts = np.diff(scene.model.strand_start_np)
        assert counts.min() < 8 and counts.max() == 16 and len(np.unique(counts)) > 5
        scene.solver.loose_lists = False
        scene.solver.step_frames_as(way)
        for _ in range(3):
            scene.advance(1.0 / scene.config.timing.fps)
        out.append(scene.state.x.numpy())
    assert np.isfinite(out[1]).all()
    np.testing.assert_allclose(out[1], out[0], atol=1e-4)
    if device == "cpu":
        np.testing.assert_array_equal(out[1], out[0])
