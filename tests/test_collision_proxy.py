"""Collision proxies: a collider remeshed coarser, embedded in it, and the dress colliding with one."""

import numpy as np
import pytest
import trimesh

import sim
from sim.cli import main
from sim.collider import Collider
from sim.collision_proxy import coarse_remesh
from sim.scene import Scene
from sim.sphere_tree import signed_distance, warp_mesh

RADIUS = 0.2


def _ball():
    return trimesh.creation.icosphere(subdivisions=5, radius=RADIUS)


def _rot_z(degrees):
    a = np.radians(degrees)
    m = np.eye(4)
    m[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    return m


def test_a_sphere_remeshed_coarser_is_closed_outward_and_lies_on_the_sphere():
    ball = _ball()
    faces, source_face, bary = coarse_remesh(ball.vertices, ball.faces, 0.04)
    corners = ball.faces[source_face]
    points = np.einsum("nk,nkj->nj", bary, ball.vertices[corners])
    proxy = trimesh.Trimesh(points, faces, process=False)
    assert proxy.is_watertight and proxy.volume > 0.0  # closed and wound outward
    assert len(faces) < len(ball.faces) / 10  # 20k triangles -> a few hundred
    # every vertex on the source surface, whose chords lie within 0.03 mm of the sphere
    np.testing.assert_allclose(np.linalg.norm(points, axis=1), RADIUS, atol=1e-4)
    np.testing.assert_allclose(bary.sum(1), 1.0, atol=1e-6)
    assert bary.min() >= -1e-6
    # even triangles about 4 cm across: the chords cut the volume by about 3 * sagitta / radius
    edges = np.linalg.norm(points[proxy.edges_unique[:, 0]] - points[proxy.edges_unique[:, 1]], axis=1)
    assert 0.02 < np.median(edges) < 0.05 and edges.min() > 0.002
    assert 0.95 < proxy.volume / (4.0 / 3.0 * np.pi * RADIUS**3) < 0.995


def test_a_proxy_takes_the_colliders_point_poses_exactly_and_its_skinned_poses_closely():
    ball = _ball()
    v = np.asarray(ball.vertices, np.float32)
    # two bones blended across x: bone 1 turns about z, so the skin bends through the middle
    w1 = np.clip(0.5 + v[:, 0] / (2 * RADIUS), 0.0, 1.0)
    indices = np.tile([0, 1, 0, 0], (len(v), 1))
    weights = np.stack([1.0 - w1, w1, np.zeros_like(w1), np.zeros_like(w1)], 1)
    body = Collider("ball", v, ball.faces, indices, weights, 2, sphere_leaves=0)
    proxy = body.proxy(0.04)
    corners, bary, count = proxy._embedding
    assert count == len(v) and len(proxy.faces_np) < len(ball.faces) / 10

    # a point cache of the collider drives the proxy by the embedding, exactly
    rng = np.random.default_rng(3)
    poses = v[None] + rng.normal(0.0, 0.01, (2, len(v), 3)).astype(np.float32)
    proxy.set_point_poses(poses)
    proxy.apply_pose(1)
    expected = np.einsum("nk,nkj->nj", bary.astype(np.float64), poses[1][corners].astype(np.float64))
    np.testing.assert_allclose(proxy.points.numpy(), expected, atol=2e-6)
    with pytest.raises(ValueError, match="point poses must have"):
        proxy.set_point_poses(poses[:, :10])

    # skinned by the same bones: exact under one rigid motion, within a few mm of the embedded
    # points when the blend bends the surface (linear blending does not commute with the embedding)
    bend = np.stack([np.eye(4), _rot_z(30.0)])
    for matrices, tolerance in ((np.stack([_rot_z(30.0)] * 2), 1e-6), (bend, 4e-3)):
        body.set_poses(matrices[None])
        body.apply_pose(0)
        proxy.set_poses(matrices[None])
        proxy.apply_pose(0)
        embedded = np.einsum("nk,nkj->nj", bary.astype(np.float64), body.points.numpy()[corners].astype(np.float64))
        np.testing.assert_allclose(proxy.points.numpy(), embedded, atol=tolerance)


@pytest.mark.slow
def test_the_dress_colliding_with_a_body_proxy_stays_out_of_the_body_itself():
    """A stride of the walk against a 2.5 cm proxy: nothing inside the render body in any frame,
    the same stretch and about the same drape as colliding with the body itself."""
    runs = {}
    for spacing in (0.0, 0.025):
        config = sim.demo_scene({"hair": {"enabled": False}, "face": {"enabled": False},
                                 "cloth.solver": {"body_proxy": spacing}})
        scene = Scene(config)
        scene.advance(0.5, animate=False)
        deepest = 0.0  # the detail surface's deepest vertex inside the body over the stride
        for _ in range(27):  # a stride: two steps at 1.8 steps/s
            scene.advance(1.0 / config.timing.fps, detail=True)
            sd = scene.cloth_body.signed_distance(scene.cloth_detail.positions.numpy(), max_dist=0.05)
            deepest = min(deepest, float(sd.min()))
        assert deepest > -0.002, f"body_proxy {spacing}: a detail vertex {-1000 * deepest:.1f} mm inside"
        runs[spacing] = scene, scene.cloth_state.x.numpy().copy(), scene.measure()
    exact, proxied = runs[0.0], runs[0.025]
    scene = proxied[0]
    assert len(scene.cloth_collider.faces_np) < len(scene.head.faces) / 3
    free = scene.cloth_model.inv_mass_np > 0
    sdf, _ = signed_distance(proxied[1], warp_mesh(scene.collider.points.numpy(), scene.head.faces))
    assert sdf[free].min() > 0.002  # the 8 mm margin, less the proxy's chords inside the body
    assert proxied[2]["cloth_inside_2mm"] == 0.0 and proxied[2]["detail_inside_2mm"] == 0.0
    assert abs(proxied[2]["cloth_stretch_p99"] - exact[2]["cloth_stretch_p99"]) < 0.01
    assert np.linalg.norm(proxied[1] - exact[1], axis=1).mean() < 0.01


def test_cloth_stretch_counts_the_edges_the_solver_moves():
    """An edge between two pinned particles (a strap bound to the shoulder) stretches with the body's
    skin: the stretch reported is over the edges with a free end, checked against NumPy."""
    config = sim.demo_scene({"hair": {"enabled": False}, "face": {"enabled": False},
                             "cloth.solver": {"body_proxy": 0.025}})
    scene = Scene(config)
    scene.advance(2.0 / config.timing.fps)
    cm = scene.cloth_model
    pinned = cm.inv_mass_np == 0
    edges = cm.spring_pairs_np[cm.spring_kind_np == 0]
    rest = cm.spring_rest_np[cm.spring_kind_np == 0]
    both = pinned[edges[:, 0]] & pinned[edges[:, 1]]
    assert both.any() and not both.all()
    # stretch one pinned-pinned edge by half, as a body's skin could
    a, b = edges[np.flatnonzero(both)[0]]
    x = scene.cloth_state.x.numpy()
    x[b] = x[a] + 1.5 * (x[b] - x[a]) * rest[np.flatnonzero(both)[0]] / np.linalg.norm(x[b] - x[a])
    scene.cloth_state.x.assign(x)
    stats = scene.cloth_stats()
    strain = np.linalg.norm(x[edges[:, 0]] - x[edges[:, 1]], axis=1) / rest - 1.0
    assert strain.max() > 0.49
    np.testing.assert_allclose(stats["cloth_stretch_max"], strain[~both].max(), rtol=1e-5)
    np.testing.assert_allclose(stats["cloth_stretch_p99"], np.percentile(strain[~both], 99), rtol=1e-5)
    assert stats["cloth_stretch_max"] < 0.2


def test_a_negative_proxy_spacing_is_refused(tmp_path, capsys):
    scene = tmp_path / "scene.toml"
    scene.write_text('[hair]\nenabled = false\n[cloth]\ngarment = "dress"\n[cloth.solver]\nbody_proxy = -0.02\n')
    assert main(["run", str(scene), "-o", str(tmp_path / "out.usdc"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "cloth.solver.body_proxy" in err and "zero or positive" in err
    assert not (tmp_path / "out.usdc").exists()
