"""The per-frame quality statistics (sim.quality) against a float64 NumPy reference of each number."""

import numpy as np
import pytest
import trimesh
import warp as wp

import sim.quality as quality
from sim.collider import Collider
from sim.scene import Scene, demo_scene, run_scene
from warp_kernels import collision
from warp_kernels import strands as strands_kernels

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not wp.is_cuda_available(), reason="needs CUDA"))]


def small_walk(device, frames=1):
    return demo_scene({"scene": {"device": device, "frames": frames, "preroll": 0.0}, "face": {"enabled": False},
                       "hair": {"count": 200, "vertices": 12}, "cloth.detail": {"level": 2}})


def reference_stats(scene):
    """The statistics computed on the host from the scene's arrays, one number at a time."""
    m = scene.model
    x = scene.state.x.numpy().astype(np.float64)
    has_parent = m.rest_length_np > 0.0
    previous = np.flatnonzero(has_parent) - 1
    stretch = np.abs(np.linalg.norm(x[has_parent] - x[previous], axis=1) / m.rest_length_np[has_parent] - 1.0)
    sdf = scene.collider.signed_distance(x, max_dist=quality.HAIR_SEARCH)  # winding-checked signs
    roots = np.abs(sdf[m.strand_start_np[:-1]])
    out = {"max_stretch": stretch.max(), "root_distance_max": roots.max(),
           "root_within_5mm": np.mean(roots <= quality.ROOT_BAND), "inside_1mm": np.mean(sdf < -quality.HAIR_DEPTH)}
    cm, st = scene.cloth_model, scene.cloth_state
    c = st.x.numpy().astype(np.float64)
    edges = cm.spring_pairs_np[cm.spring_kind_np == 0]
    rest = cm.spring_rest_np[cm.spring_kind_np == 0]
    moved = (cm.inv_mass_np[edges[:, 0]] > 0) | (cm.inv_mass_np[edges[:, 1]] > 0)
    strain = np.linalg.norm(c[edges[moved, 0]] - c[edges[moved, 1]], axis=1) / rest[moved] - 1.0
    body = scene.cloth_body
    pts = scene.cloth_collider.points.numpy().astype(np.float64)
    gap = np.linalg.norm(c[:, None] - pts[None], axis=2)
    truth = gap.argmin(axis=1)
    near = gap[np.arange(len(c)), truth]
    walked = st.nearest.numpy()
    counted = (cm.inv_mass_np > 0) & (near <= scene.cloth_solver.reseed_radius)
    agree = (walked == truth) | np.isclose(gap[np.arange(len(c)), np.maximum(walked, 0)], near, rtol=1e-6, atol=1e-9)
    detail = scene.cloth_detail
    tested, bvh = detail.query_counts()
    out.update(cloth_stretch_p99=np.percentile(strain, 99), cloth_stretch_max=strain.max(),
               cloth_inside_2mm=np.mean(body.signed_distance(c, quality.CLOTH_SEARCH) < -quality.CLOTH_DEPTH),
               walk_agreement=np.mean(agree[counted]) if counted.any() else 1.0,
               detail_inside_2mm=np.mean(body.signed_distance(detail.positions.numpy(), quality.CLOTH_SEARCH)
                                         < -quality.CLOTH_DEPTH),
               detail_queries=tested / detail.surface.topology.num_vertices, detail_bvh=bvh / max(1, tested))
    return out


@pytest.fixture(scope="module", params=DEVICES)
def walking(request):
    scene = Scene(small_walk(request.param))
    scene.advance(3 / 24, detail=True)
    return scene


def test_statistics_equal_the_host_reference(walking):
    got, want = walking.measure(), reference_stats(walking)
    assert set(got) == set(want)
    for key in want:
        np.testing.assert_allclose(got[key], want[key], rtol=1e-6, atol=1e-12, err_msg=key)
    assert 0.0 < want["max_stretch"] < 0.01 and want["walk_agreement"] > 0.9 and want["detail_queries"] > 0.0
    assert walking.cloth_stats() == {k: got[k] for k in ("cloth_stretch_p99", "cloth_stretch_max",
                                                          "cloth_inside_2mm", "walk_agreement")}


def test_deep_points_are_counted_and_checked_also_beyond_the_list(walking, monkeypatch):
    """Hair pushed into the body: the listed deep points are re-signed on the host; with a list too
    short for them every point is checked there instead, to the same count."""
    state = walking.state
    before = state.x.numpy().copy()
    try:
        x = before.copy()
        start = walking.model.strand_start_np
        roots, tips = x[start[:-1]], start[1:] - 1
        # every tip 5 mm below its root, toward the middle of the scalp: inside the head
        inward = roots.mean(axis=0) - roots
        x[tips] = roots + 0.005 * inward / np.linalg.norm(inward, axis=1, keepdims=True)
        state.x.assign(x)
        want = reference_stats(walking)["inside_1mm"]
        assert want > 0.5 * len(tips) / len(x)
        assert walking.measure()["inside_1mm"] == pytest.approx(want)
        monkeypatch.setattr(quality, "LISTED", 3)
        walking.quality._buffers.clear()
        assert walking.measure()["inside_1mm"] == pytest.approx(want)
    finally:
        state.x.assign(before)
        walking.quality._buffers.clear()


def test_points_a_self_intersecting_pose_puts_inside_by_mistake_are_not_counted():
    # the folded shape of tests/test_collision.py: a ball, and outside it a small ball wound inside out
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    fold = trimesh.creation.icosphere(subdivisions=2, radius=0.05)
    v = np.concatenate([ball.vertices, fold.vertices + [0.5, 0.0, 0.0]]).astype(np.float32)
    f = np.concatenate([ball.faces, fold.faces[:, ::-1] + len(ball.vertices)]).astype(np.int32)
    weights = np.zeros((len(v), 4))
    weights[:, 0] = 1.0
    body = Collider("folded", v, f, np.zeros((len(v), 4), np.int32), weights, 1, "cpu", sphere_leaves=0)
    rng = np.random.default_rng(1)
    u = rng.normal(size=(30, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    points = np.concatenate([[0.5, 0.0, 0.0] + 0.06 * u, 0.25 * u]).astype(np.float32)  # outside; 5 cm inside
    # the collider's mesh is on the CPU, so is every array launched with it (a GPU machine's default is CUDA)
    count, listed = wp.zeros((1, 1), dtype=wp.int32, device="cpu"), wp.zeros((1, 64), dtype=wp.int32, device="cpu")
    wp.launch(collision.count_deep_points, len(points),
              [wp.array(points, dtype=wp.vec3, device="cpu"), 0, 0, body.mesh.id, 0.1, 0.005, count, listed],
              device="cpu")
    assert count.numpy()[0, 0] == 60  # the pseudo-normal calls every point deeper than 5 mm
    assert quality.deep_after_winding(points, v, f, count.numpy(), listed.numpy(), 0.1, 0.005) == 30
    short = listed.numpy()[:, :10]
    assert quality.deep_after_winding(points, v, f, count.numpy(), short, 0.1, 0.005) == 30


def test_strands_walked_from_the_root_count_every_deep_particle_a_query_of_each_would():
    """strand_quality queries a particle only where the bound carried from its parent leaves room
    for it to lie deeper than the depth counted, and no farther than that room: strands crossing a
    ball at every depth, lying on it, hovering over it and far from it give the roots, the stretch
    and the deep particles (counted and listed) of an exact query of every particle."""
    ball = trimesh.creation.icosphere(subdivisions=4, radius=0.1)
    v, f = ball.vertices.astype(np.float32), ball.faces.astype(np.int32)
    rng = np.random.default_rng(12)
    strands, counts = [], []
    for k in range(400):
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        root = 0.1 * u if k % 4 else (0.1 + rng.uniform(0.0, 0.05)) * u  # most on the ball, some off it
        # heading in, along, or out of the ball, in segments of 2 to 15 mm
        turn = rng.normal(size=3)
        heading = (turn - np.dot(turn, u) * u) / np.linalg.norm(turn - np.dot(turn, u) * u)
        heading = heading * np.cos(rng.uniform(-1.2, 1.2)) - u * np.sin(rng.uniform(-0.6, 1.2))
        n = int(rng.integers(4, 20))
        steps = rng.uniform(0.002, 0.015) * (heading + 0.3 * rng.normal(size=(n - 1, 3)))
        strands.append(np.concatenate([[root], root + np.cumsum(steps, axis=0)]))
        counts.append(n)
    x = np.concatenate(strands).astype(np.float32)
    start = np.r_[0, np.cumsum(counts)].astype(np.int32)
    rest = np.zeros(len(x), np.float32)
    segment = np.linalg.norm(np.diff(x.astype(np.float64), axis=0), axis=1)
    inner = np.setdiff1d(np.arange(len(x)), start[:-1])
    rest[inner] = segment[inner - 1] / rng.uniform(0.98, 1.02, size=len(inner))
    depth, search, band = 0.001, 0.03, 0.005
    rows = 2
    cpu = "cpu"  # quality.warp_mesh builds on the CPU; a GPU machine's default device is CUDA
    worst = wp.zeros((rows, 2), dtype=float, device=cpu)
    near, count = wp.zeros((rows, 1), dtype=wp.int32, device=cpu), wp.zeros((rows, 1), dtype=wp.int32, device=cpu)
    listed = wp.zeros((rows, len(x)), dtype=wp.int32, device=cpu)
    mesh = quality.warp_mesh(v, f)
    half = len(counts) // 2
    for row, (a, b) in enumerate(((0, half), (half, len(counts)))):  # two launches, as on two cores
        wp.launch(strands_kernels.strand_quality, b - a,
                  [wp.array(x, dtype=wp.vec3, device=cpu), a, row, wp.array(rest, device=cpu),
                   wp.array(start, device=cpu), mesh.id, search, depth, band, worst, near, count, listed], device=cpu)
    sdf = quality.signed_distance(x, mesh, "cpu", search)[0]  # every particle queried to search
    seen = np.abs(sdf) < search
    deep = np.flatnonzero(seen & (sdf < -depth))
    roots = np.abs(sdf[start[:-1]])
    assert 50 < len(deep) < 0.5 * len(x)  # deep and shallow, inside and out
    assert np.sum(count.numpy()) == len(deep)
    got = np.sort(np.concatenate([listed.numpy()[r, :c] for r, c in enumerate(count.numpy()[:, 0])]))
    np.testing.assert_array_equal(got, deep)
    stretch = np.abs(segment[inner - 1] / rest[inner].astype(np.float64) - 1.0).max()
    assert worst.numpy()[:, 0].max() == pytest.approx(stretch, rel=1e-6)
    assert worst.numpy()[:, 1].max() == pytest.approx(roots.max(), rel=1e-6)
    assert near.numpy().sum() == np.sum(roots <= band)


def test_kept_host_meshes_refit_to_each_pose_and_sign_as_fresh_ones():
    """HostMeshes keeps one mesh per triangle list and kind of sign, refitted when the pose changes:
    the same signed distances as meshes built afresh for each pose, winding number included."""
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    v0, f = ball.vertices.astype(np.float32), ball.faces.astype(np.int32)
    rng = np.random.default_rng(4)
    points = (0.35 * rng.uniform(-1.0, 1.0, size=(200, 3))).astype(np.float32)
    meshes = quality.HostMeshes()
    first = meshes.get(v0, f, winding=True)
    for pose in range(3):
        turn = trimesh.transformations.rotation_matrix(0.4 * pose, [0.3, 1.0, 0.2])[:3, :3]
        v = (v0 @ turn.T * (1.0 + 0.1 * pose) + [0.02 * pose, 0.0, 0.0]).astype(np.float32)
        for winding in (False, True):
            kept = meshes.get(v, f, winding=winding)
            fresh = quality.warp_mesh(v, f, "cpu", winding=winding)
            got = quality.signed_distance(points, kept, "cpu", 0.1, winding=winding)[0]
            want = quality.signed_distance(points, fresh, "cpu", 0.1, winding=winding)[0]
            np.testing.assert_allclose(got, want, rtol=0.0, atol=1e-7)
        assert meshes.get(v, f, winding=True) is first  # refitted, not rebuilt
    assert np.any(got < -0.01) and np.any(got > 0.01)


@pytest.mark.parametrize("device", DEVICES)
def test_a_run_reports_the_worst_of_its_frames_statistics(tmp_path, device):
    """A run queues each frame's statistics and finishes them as it writes the frame: the worst over
    the frames of what measure() gives at each frame."""
    seen = []
    result = run_scene(small_walk(device, frames=3), tmp_path / "walk.usdc", progress=False,
                       on_frame=lambda frame, scene: seen.append(scene.measure()))
    assert len(seen) == 3
    for key in ("max_stretch", "root_distance_max", "inside_1mm", "cloth_stretch_p99", "cloth_inside_2mm",
                "detail_inside_2mm", "detail_queries"):
        assert result.stats[key] == pytest.approx(max(s[key] for s in seen)), key
    assert result.stats["root_within_5mm"] == pytest.approx(min(s["root_within_5mm"] for s in seen))
    assert result.stats["walk_agreement"] == pytest.approx(np.mean([s["walk_agreement"] for s in seen]))
    assert result.stats["walk_agreement_worst_frame"] == pytest.approx(min(s["walk_agreement"] for s in seen))
