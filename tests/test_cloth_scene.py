"""Cloth in scenes: the dress on the walking built-in body, user bodies and garments, the demo."""

import numpy as np
import pytest
import trimesh
import warp as wp
from pxr import Usd, UsdGeom, Vt

import sim
from io_usd import CacheReader, validation_errors
from sim.cli import main
from sim.scene import Scene
from sim.sphere_tree import signed_distance, warp_mesh
from warp_kernels import cloth as kernels


@pytest.mark.slow
def test_walk_agrees_with_brute_force_and_leaves_nothing_inside_after_a_stride():
    config = sim.demo_scene({"hair": {"enabled": False}})
    scene = Scene(config)
    scene.advance(0.5, animate=False)
    fps = config.timing.fps
    stride = 2.0 / 1.8  # two steps at the walk's cadence of 1.8 steps/s
    agree, total, skippable = 0, 0, 0
    free = scene.cloth_model.inv_mass_np > 0
    for _ in range(int(np.ceil(stride * fps))):
        scene.advance(1.0 / fps)
        st, body = scene.cloth_state, scene.collider
        truth = wp.zeros(scene.cloth_model.num_particles, dtype=wp.int32)
        wp.launch(kernels.nearest_vertex_brute_force, len(truth), [st.x, body.points, truth])
        x, pts = st.x.numpy(), body.points.numpy()
        walk, brute = st.nearest.numpy(), truth.numpy()
        near = np.linalg.norm(x - pts[brute], axis=1)
        tie = np.isclose(np.linalg.norm(x - pts[walk], axis=1), near, rtol=1e-6)
        # where the cache matters: particles that can touch or follow the body
        used = free & (near <= scene.cloth_solver.reseed_radius)
        agree += np.count_nonzero(((walk == brute) | tie)[used])
        total += np.count_nonzero(used)
        # the clearances that let body_collide skip queries stay below the true distance on the moving body
        sdf, _ = signed_distance(x, warp_mesh(pts, scene.head.faces))
        c = st.clearance
        bound = c.distance.numpy() - np.linalg.norm(x - c.at.numpy(), axis=1)
        known = free & (c.distance.numpy() > -1e29)
        assert np.all(bound[known] <= sdf[known] + 1e-4), (bound - sdf)[known].max()
        skippable += np.count_nonzero(bound[known] > scene.cloth_solver.params.collision_margin)
    assert agree / total >= 0.99, agree / total
    assert skippable > 0
    sdf, _ = signed_distance(scene.cloth_state.x.numpy(), warp_mesh(scene.collider.points.numpy(), scene.head.faces))
    assert sdf[free].min() > -0.001  # nothing inside the body after a full stride


def test_boxes_refitted_each_substep_walk_the_dress_as_the_swept_boxes_do():
    """A GPU's cloth frame (Scene.cloth_sweep off: the body's BVHs refitted to every substep's pose,
    closest points from the wp.Mesh, ClothSolver.mesh_queries, each step one launch of one block,
    ClothSolver.block_step) and the CPU's (triangle boxes bounded once over the frame's poses, a step
    as its launches) answer the same closest-point queries, with the same nearest triangle wherever
    it is unique: the walking dress ends the same."""
    dresses = []
    for sweep in (True, False):
        scene = Scene(sim.demo_scene({"hair": {"enabled": False}, "face": {"enabled": False}}))
        scene.cloth_sweep = sweep
        scene.cloth_solver.mesh_queries = not sweep
        scene.cloth_solver.block_step = not sweep
        start = scene.cloth_state.x.numpy().copy()
        scene.advance(0.1, animate=False)
        scene.advance(4 / scene.config.timing.fps)
        dresses.append(scene.cloth_state.x.numpy().copy())
    gap = np.linalg.norm(dresses[0] - dresses[1], axis=1)
    assert gap.max() < 1e-5, gap.max()  # bit for bit here; a tie between two triangles could differ
    assert np.abs(dresses[1] - start).max() > 0.02  # the dress moved
    sdf, _ = signed_distance(dresses[1], warp_mesh(scene.collider.points.numpy(), scene.head.faces))
    free = scene.cloth_model.inv_mass_np > 0
    assert sdf[free].min() > -0.001


@pytest.mark.slow
def test_demo_walks_the_dress_with_stretch_and_penetration_in_bounds(tmp_path):
    out = str(tmp_path / "demo.usdc")
    config = sim.demo_scene({"hair": {"count": 150}, "scene": {"preroll": 0.5}})
    result = sim.run_scene(config, out, progress=False)
    assert validation_errors(out) == []
    reader = CacheReader(out)
    assert set(reader.prims) == {"body", "hair", "cloth", "cloth_detail", "face"}
    assert reader.prims["cloth"].role == "cloth" and reader.prims["body"].role == "collider"
    frames = reader.frames("cloth")
    assert len(frames) >= 48 and reader.fps >= 24
    cloth = reader.prims["cloth"]
    edges = set()
    at = 0
    for n in cloth.counts:  # polygon edges, as the stretch springs are
        f = cloth.indices[at:at + n]
        edges.update(tuple(sorted((int(f[k]), int(f[(k + 1) % n])))) for k in range(n))
        at += n
    edges = np.array(sorted(edges))
    faces = reader.triangles("body")
    from sim.body import procedural_body
    from sim.garment import fit_dress

    garment = fit_dress(procedural_body(), particles=config.cloth.particles, ease=config.cloth.ease)
    rest = np.linalg.norm(garment.vertices[edges[:, 0]] - garment.vertices[edges[:, 1]], axis=1)
    for frame in frames:
        x = reader.points("cloth", frame).astype(np.float64)
        assert np.all(np.isfinite(x))
        stretch = np.linalg.norm(x[edges[:, 0]] - x[edges[:, 1]], axis=1) / rest - 1.0
        assert np.percentile(stretch, 99) <= 0.05, frame  # 99th-percentile edge stretch at every frame
        body = reader.points("body", frame)
        sdf, _ = signed_distance(x, warp_mesh(body, faces), max_dist=1.0)
        assert np.mean(sdf < -0.002) < 0.005, frame
    assert result.stats["walk_agreement"] >= 0.99
    # the character talks: the lips part and close again, and the face rides the walking head
    assert reader.prims["face"].role == "face" and len(reader.frames("face")) == len(frames)
    rig = Scene(config).face_rig
    upper, lower = rig.mesh.features["upper_lip_bottom"], rig.mesh.features["lower_lip_top"]
    gaps = np.array([np.linalg.norm(np.subtract(*reader.points("face", f)[[upper, lower]])) for f in frames])
    assert gaps.max() > 0.005 and gaps.min() < 0.0005 and np.mean(gaps > 0.002) > 0.2
    for frame in frames[::12]:
        body = warp_mesh(reader.points("body", frame), faces)
        sdf, _ = signed_distance(reader.points("face", frame), body, max_dist=1.0)
        assert np.percentile(sdf, 5) > 0.0 and np.percentile(sdf, 50) < 0.004, frame
    # the detail surface: 8x the coarse vertices or more, unit normals, manifold, outside the body
    detail = reader.prims["cloth_detail"]
    assert reader.prims["cloth_detail"].role == "cloth_detail"
    assert detail.num_points >= 8 * reader.prims["cloth"].num_points
    tris = reader.triangles("cloth_detail")
    e = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    _, uses = np.unique(e, axis=0, return_counts=True)
    assert uses.max() <= 2  # no non-manifold edge
    for frame in frames[::6]:
        n = reader.normals("cloth_detail", frame)
        np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-4)
        x = reader.points("cloth_detail", frame)
        sdf, _ = signed_distance(x, warp_mesh(reader.points("body", frame), faces), max_dist=1.0)
        assert np.mean(sdf < -0.002) < 0.01, frame
    z = [reader.points("body", f)[:, 2].mean() for f in (frames[0], frames[-1])]
    assert z[1] - z[0] > 0.5  # the character walked forward


def _sheet_obj(path, n=8, size=0.5, height=0.36):
    lines = []
    u = np.linspace(-size / 2, size / 2, n)
    for i in range(n):
        for j in range(n):
            lines.append(f"v {u[i]:.6f} {height:.6f} {u[j]:.6f}")
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j + 1
            lines.append(f"f {a} {a + n} {a + n + 1} {a + 1}")
    path.write_text("\n".join(lines) + "\n")


def _ball_frames(frames=12, radius=0.3):
    ball = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    shift = np.linspace(0.0, 0.1, frames)
    return ball, np.stack([ball.vertices + [s, 0.0, 0.0] for s in shift])


@pytest.mark.parametrize("proxy", ["", "[cloth.solver]\nbody_proxy = 0.05\n"], ids=["body", "proxy"])
def test_scene_with_a_usd_body_point_cache_and_a_garment_file(tmp_path, proxy):
    """A USD point cache drives the body, and a collision proxy of it as well: the sheet stays out
    of the moving ball itself either way."""
    ball, frames = _ball_frames()
    stage = Usd.Stage.CreateNew(str(tmp_path / "body.usda"))
    stage.SetTimeCodesPerSecond(24)
    mesh = UsdGeom.Mesh.Define(stage, "/Body")
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(ball.faces), 3, np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(ball.faces.reshape(-1).astype(np.int32)))
    for k, pts in enumerate(frames):
        mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(pts.astype(np.float32)), k)
    stage.Save()
    _sheet_obj(tmp_path / "sheet.obj")
    scene = tmp_path / "scene.toml"
    scene.write_text('[scene]\nframes = 12\npreroll = 0.0\n[body]\nmesh = "body.usda"\nprim = "/Body"\n'
                     '[hair]\nenabled = false\n[cloth]\ngarment = "sheet.obj"\n' + proxy)
    out = str(tmp_path / "out.usdc")
    assert main(["run", str(scene), "-o", out, "-q"]) == 0
    reader = CacheReader(out)
    assert set(reader.prims) == {"body", "cloth", "cloth_detail"} and reader.prims["cloth"].counts.tolist() == [4] * 49
    np.testing.assert_allclose(reader.points("body", 12), frames[11], atol=1e-6)  # the point cache plays back
    x = reader.points("cloth", 12)
    r = np.linalg.norm(x - frames[11].mean(0), axis=1)
    assert r.min() > 0.3 - 0.002  # the sheet fell onto the moving ball and stays outside it


def test_scene_with_a_mesh_body_and_per_frame_points(tmp_path, capsys):
    ball, frames = _ball_frames()
    ball.export(tmp_path / "ball.obj")
    np.save(tmp_path / "frames.npy", frames)
    _sheet_obj(tmp_path / "sheet.obj")
    scene = tmp_path / "scene.toml"
    scene.write_text('[scene]\nframes = 6\npreroll = 0.0\n[body]\nmesh = "ball.obj"\npoints = "frames.npy"\n'
                     '[hair]\nenabled = false\n[cloth]\ngarment = "sheet.obj"\ncolor = [0.6, 0.1, 0.1]\n'
                     '[cloth.solver]\nstrain_limit = 0.03\n')
    out = str(tmp_path / "out.usdc")
    assert main(["run", str(scene), "-o", out, "-q"]) == 0
    for prim in ("cloth", "cloth_detail"):  # the garment's colour is both meshes' displayColor
        np.testing.assert_allclose(CacheReader(out).prims[prim].color, (0.6, 0.1, 0.1), atol=1e-6)
    err = capsys.readouterr().err
    assert "substeps per frame, from the RK4 stability bound" in err  # the bound is reported
    stats = CacheReader(out).metadata["cfx:stats"]
    assert stats["cloth_substeps"] == int(np.ceil((1 / 24) / stats["cloth_stable_dt"]))
    np.testing.assert_allclose(CacheReader(out).points("body", 6), frames[5], atol=1e-6)
    bad = tmp_path / "bad.toml"
    np.save(tmp_path / "short.npy", frames[:, :10])
    bad.write_text(scene.read_text().replace("frames.npy", "short.npy"))
    assert main(["run", str(bad), "-o", str(tmp_path / "bad.usdc"), "-q"]) == 2
    bad.write_text(scene.read_text().replace("strain_limit = 0.03", "strain_limt = 0.03"))
    assert main(["run", str(bad), "-o", str(tmp_path / "bad.usdc"), "-q"]) == 2


def test_built_in_garment_without_the_built_in_body_is_refused(tmp_path, capsys):
    scene = tmp_path / "scene.toml"
    scene.write_text('[cloth]\ngarment = "dress"\n')
    assert main(["run", str(scene), "-o", str(tmp_path / "x.usdc"), "-q"]) == 2
    assert "cloth.garment" in capsys.readouterr().err
    scene.write_text('[body]\n[cloth]\ngarment = "robe"\n')  # a typo: the message lists the built-in ones
    assert main(["run", str(scene), "-o", str(tmp_path / "x.usdc"), "-q"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "cloth.garment: not a built-in garment (dress, skirt, shirt) nor a file: robe" in err


def test_hair_on_a_body_file_needs_a_scalp(tmp_path, capsys):
    ball, frames = _ball_frames()
    ball.export(tmp_path / "ball.obj")
    scene = tmp_path / "scene.toml"
    scene.write_text('[scene]\nframes = 2\npreroll = 0.0\n[body]\nmesh = "ball.obj"\n[hair]\ncount = 10\n')
    assert main(["run", str(scene), "-o", str(tmp_path / "x.usdc"), "-q"]) == 2
    assert "head.scalp_faces" in capsys.readouterr().err
    np.save(tmp_path / "top.npy", np.flatnonzero(ball.triangles_center[:, 1] > 0.25))
    scene.write_text(scene.read_text().replace('[hair]', '[head]\nscalp_faces = "top.npy"\n[hair]\nvertices = 6\nlength = 0.1'))
    assert main(["run", str(scene), "-o", str(tmp_path / "x.usdc"), "-q"]) == 0
    roots = CacheReader(str(tmp_path / "x.usdc")).points("hair", 1).reshape(10, 6, 3)[:, 0]
    assert roots[:, 1].min() > 0.24


def test_a_fitted_garment_on_a_body_file_is_one_line_naming_the_key(tmp_path, capsys):
    ball, _ = _ball_frames()
    ball.export(tmp_path / "ball.obj")
    scene = tmp_path / "scene.toml"
    scene.write_text('[scene]\nframes = 2\npreroll = 0.0\n[body]\nmesh = "ball.obj"\n[hair]\nenabled = false\n'
                     '[cloth]\ngarment = "skirt"\n')
    assert main(["run", str(scene), "-o", str(tmp_path / "x.usdc"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "cloth.garment: the fitted skirt fits the built-in body only" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "x.usdc").exists()
