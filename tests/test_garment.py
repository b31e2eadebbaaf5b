"""Garments: quad topology and spring pairs, OBJ / USD loading, and dress, skirt and shirt fitted to a body."""

from types import SimpleNamespace

import numpy as np
import pytest
from pxr import Usd, UsdGeom, Vt

from sim.body import procedural_body
from sim.garment import (GARMENTS, GarmentMesh, fit_dress, fit_shirt, fit_skirt, garment_from_file,
                         garment_from_usd)
from sim.sphere_tree import signed_distance, warp_mesh

EASE = 0.012


@pytest.fixture(scope="module")
def body():
    return procedural_body()


@pytest.fixture(scope="module")
def garments(body):
    return {"dress": fit_dress(body), "skirt": fit_skirt(body), "shirt": fit_shirt(body)}


def grid(rows, columns, spacing=0.1):
    """A flat rows x columns quad grid in the XY plane, vertex r * columns + c."""
    r, c = np.meshgrid(np.arange(rows), np.arange(columns), indexing="ij")
    vertices = np.stack([c.ravel() * spacing, -r.ravel() * spacing, np.zeros(rows * columns)], 1)
    v = np.arange(rows * columns).reshape(rows, columns)
    quads = np.stack([v[:-1, :-1], v[1:, :-1], v[1:, 1:], v[:-1, 1:]], -1).reshape(-1, 4)
    return GarmentMesh("grid", vertices, np.full(len(quads), 4), quads.ravel())


def edge_faces(g):
    """Directed polygon edges (a, b) of every face, in face order."""
    starts = np.cumsum(g.face_counts) - g.face_counts
    k = np.arange(len(g.face_indices)) - np.repeat(starts, g.face_counts)
    nxt = np.repeat(starts, g.face_counts) + (k + 1) % np.repeat(g.face_counts, g.face_counts)
    return np.stack([g.face_indices, g.face_indices[nxt]], 1)


def boundary_loops(g):
    """Boundary edges (used by one face) grouped into connected loops, as lists of vertex sets."""
    directed = edge_faces(g)
    undirected, count = np.unique(np.sort(directed, 1), axis=0, return_counts=True)
    boundary = undirected[count == 1]
    parent = {v: v for v in boundary.ravel()}

    def find(v):
        while parent[v] != v:
            v = parent[v]
        return v

    for a, b in boundary:
        parent[find(a)] = find(b)
    loops = {}
    for a, b in boundary:
        loops.setdefault(find(a), []).append((a, b))
    return list(loops.values())


# -- topology and spring pairs --------------------------------------------------------------------------
def test_bending_pairs_on_a_5x5_grid_join_vertices_two_apart_along_rows_and_columns():
    g = grid(5, 5)
    expected = {(r * 5 + c, r * 5 + c + 2) for r in range(5) for c in range(3)}
    expected |= {(r * 5 + c, (r + 2) * 5 + c) for r in range(3) for c in range(5)}
    assert {tuple(p) for p in g.bending_pairs()} == expected and len(g.bending_pairs()) == 30
    assert len(g.edges()) == 40 and len(g.quad_diagonals()) == 32


def test_bending_pair_of_two_triangles_joins_the_corners_opposite_their_shared_edge():
    g = GarmentMesh("kite", np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.0]]), [3, 3], [0, 1, 2, 2, 1, 3])
    np.testing.assert_array_equal(g.bending_pairs(), [[0, 3]])
    np.testing.assert_array_equal(g.edges(), [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]])


def test_quads_split_along_their_first_diagonal():
    g = grid(2, 3)
    np.testing.assert_array_equal(g.triangles(), [[0, 3, 4], [0, 4, 1], [1, 4, 5], [1, 5, 2]])
    np.testing.assert_array_equal(g.quad_diagonals(), [[0, 4], [1, 3], [1, 5], [2, 4]])


@pytest.mark.parametrize("name", list(GARMENTS))
def test_spring_pairs_are_unique_and_never_join_a_vertex_to_itself(garments, name):
    g = garments[name]
    for pairs in (g.edges(), g.quad_diagonals(), g.bending_pairs()):
        assert len(np.unique(np.sort(pairs, 1), axis=0)) == len(pairs)
        assert np.all(pairs[:, 0] != pairs[:, 1])
    everything = np.concatenate([g.edges(), g.quad_diagonals(), g.bending_pairs()])
    assert len(np.unique(np.sort(everything, 1), axis=0)) == len(everything)  # no spring doubled


# -- fitted garments -------------------------------------------------------------------------------
def test_dress_has_about_322_particles_like_the_paper(garments):
    assert abs(len(garments["dress"].vertices) - 322) <= 0.15 * 322


@pytest.mark.parametrize("name", list(GARMENTS))
def test_every_garment_vertex_rests_outside_the_body_by_more_than_half_the_ease(body, garments, name):
    g = garments[name]
    distance, _ = signed_distance(g.vertices, warp_mesh(body.vertices, body.faces))
    assert distance.min() > 0.5 * EASE and g.thickness == EASE


@pytest.mark.parametrize("name", list(GARMENTS))
def test_fitted_garments_are_all_quads_with_consistent_outward_winding(body, garments, name):
    g = garments[name]
    assert np.all(g.face_counts == 4) and len(g.quads()) == len(g.face_counts)
    directed = edge_faces(g)
    assert len(np.unique(directed, axis=0)) == len(directed)  # each directed edge once: one orientation
    q = g.vertices[g.quads()]
    normal = np.cross(q[:, 2] - q[:, 0], q[:, 3] - q[:, 1])
    _, closest = signed_distance(q.mean(1), warp_mesh(body.vertices, body.faces))
    assert np.all(np.einsum("ij,ij->i", normal, q.mean(1) - closest) > 0.0)


@pytest.mark.parametrize("name, holes", [("dress", 4), ("shirt", 4), ("skirt", 2)])
def test_tube_is_closed_around_and_open_only_at_hem_neckline_and_armholes(garments, name, holes):
    """A tube is a sphere with two holes (top and hem, Euler characteristic 0); two straps split the
    top into a neckline and two armholes (four holes, characteristic -2). Every other edge joins two
    faces, so each row closes on itself."""
    g = garments[name]
    undirected, count = np.unique(np.sort(edge_faces(g), 1), axis=0, return_counts=True)
    assert set(count) <= {1, 2}
    loops = boundary_loops(g)
    assert len(loops) == holes
    assert len(g.vertices) - len(undirected) + len(g.face_counts) == 2 - holes
    y = g.vertices[:, 1]
    hem = min(loops, key=lambda loop: y[np.ravel(loop)].mean())
    columns = len(hem)
    assert np.ptp(y[np.ravel(hem)]) < 0.005 and len(np.unique(hem)) == columns  # one closed row
    assert sum(map(len, loops)) == np.count_nonzero(count == 1)
    if holes == 2:  # skirt: the waistband is the top row, as long as the hem
        assert len(max(loops, key=lambda loop: y[np.ravel(loop)].mean())) == columns
    else:
        # top rim minus the strap ends (`width` quads at the front and back of each strap) plus both
        # sides of both straps, m + 1 edges each for m vertices per rail. With R rows of C columns,
        # V = R C + 2 (width + 1) m and F = (R - 1) C + 2 width (m + 1), so V - F = C + 2 m - 2 width.
        width = len(g.pinned) // 4 - 1  # two pinned rows per strap, one vertex per rail
        m, odd = divmod(len(g.vertices) - len(g.face_counts) - columns + 2 * width, 2)
        assert odd == 0 and m >= 2 and width == {"dress": 1, "shirt": 2}[name]
        assert np.count_nonzero(count == 1) == 2 * columns - 4 * width + 4 * (m + 1)


def test_skirt_is_pinned_at_its_waistband_and_dress_at_the_strap_tops(body, garments):
    skirt, dress = garments["skirt"], garments["dress"]
    assert np.allclose(skirt.vertices[skirt.pinned, 1], skirt.vertices[:, 1].max(), atol=0.005)
    assert len(skirt.pinned) == np.count_nonzero(skirt.vertices[:, 1] > skirt.vertices[:, 1].max() - 0.005)
    for key, side in (("shoulder_l", 1.0), ("shoulder_r", -1.0)):
        mine = dress.pinned[np.sign(dress.vertices[dress.pinned, 0]) == side]
        assert 2 <= len(mine) <= 6
        assert np.linalg.norm(dress.vertices[mine] - body.landmarks[key], axis=1).max() < 0.06


@pytest.mark.parametrize("name", list(GARMENTS))
def test_springs_have_similar_rest_lengths(garments, name):
    g = garments[name]
    e = g.edges()
    length = np.linalg.norm(g.vertices[e[:, 0]] - g.vertices[e[:, 1]], axis=1)
    assert length.min() / length.max() > 0.4  # flare widens the hem; the straps are the narrowest


def test_armholes_leave_the_a_posed_arms_free(body, garments):
    lm = body.landmarks
    arm = body.vertices[(np.abs(body.vertices[:, 0]) > 0.22) & (body.vertices[:, 1] > lm["waist_y"])]
    for name in ("dress", "shirt"):
        gap = np.linalg.norm(arm[:, None] - garments[name].vertices[None], axis=2).min()
        assert gap > 0.03, name


def test_dress_lengths_order_their_hems(body):
    hems = [fit_dress(body, particles=200, length=length).vertices[:, 1].min() for length in ("mini", "knee", "midi")]
    assert hems[0] > hems[1] > hems[2]
    assert abs(hems[1] - body.landmarks["knee_y"]) < 0.1
    with pytest.raises(ValueError, match="length"):
        fit_dress(body, length="floor")


def test_fitting_uses_only_vertices_faces_and_landmarks_and_follows_body_size(body, garments):
    scale = 1.1
    big = SimpleNamespace(vertices=body.vertices * scale, faces=body.faces,
                          landmarks={k: v * scale for k, v in body.landmarks.items()})
    dress = fit_dress(big)
    distance, _ = signed_distance(dress.vertices, warp_mesh(big.vertices, big.faces))
    assert distance.min() > 0.5 * EASE
    assert abs(len(dress.vertices) - 322) <= 0.15 * 322
    ref = garments["dress"].vertices
    assert np.ptp(dress.vertices[:, 1]) == pytest.approx(scale * np.ptp(ref[:, 1]), rel=0.05)


def test_garments_registry_names_each_fitter(garments):
    assert GARMENTS == {"dress": fit_dress, "skirt": fit_skirt, "shirt": fit_shirt}
    assert all(garments[name].name == name for name in GARMENTS)


def test_coarse_quads_do_not_cut_into_the_body_between_their_corners(body):
    skirt = fit_skirt(body, particles=60)
    q = skirt.vertices[skirt.quads()]
    u, v = (a.ravel() for a in np.meshgrid(np.linspace(0, 1, 9), np.linspace(0, 1, 9)))
    weights = np.stack([(1 - u) * (1 - v), u * (1 - v), u * v, (1 - u) * v], 1)
    surface = np.einsum("sc,qcj->qsj", weights, q).reshape(-1, 3)
    distance, _ = signed_distance(surface, warp_mesh(body.vertices, body.faces))
    assert len(skirt.vertices) == 60 and distance.min() > 0.0


# -- loading --------------------------------------------------------------------------------------------
def write_usd_mesh(path, points, counts, indices, meters_per_unit=None):
    stage = Usd.Stage.CreateNew(str(path))
    if meters_per_unit is not None:
        UsdGeom.SetStageMetersPerUnit(stage, meters_per_unit)
    UsdGeom.Xform.Define(stage, "/World")
    mesh = UsdGeom.Mesh.Define(stage, "/World/dress")
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(points, np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.asarray(counts, np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.asarray(indices, np.int32)))
    stage.GetRootLayer().Save()
    return stage


def test_usd_loader_round_trips_points_and_polygons(tmp_path, garments):
    g = garments["dress"]
    counts = np.concatenate([g.face_counts, [3]])
    indices = np.concatenate([g.face_indices, g.face_indices[:3]])  # and one triangle
    stage = write_usd_mesh(tmp_path / "dress.usda", g.vertices, counts, indices, meters_per_unit=1.0)
    for source in (str(tmp_path / "dress.usda"), stage):
        loaded = garment_from_usd(source, "/World/dress", pinned=g.pinned)
        np.testing.assert_allclose(loaded.vertices, g.vertices, atol=1e-6)
        np.testing.assert_array_equal(loaded.face_counts, counts)
        np.testing.assert_array_equal(loaded.face_indices, indices)
        np.testing.assert_array_equal(loaded.pinned, g.pinned)
    assert garment_from_file(tmp_path / "dress.usda").name == "dress"  # first mesh prim
    assert len(garment_from_usd(tmp_path / "dress.usda", "").vertices) == len(g.vertices)


def test_usd_loader_converts_centimetres_to_metres(tmp_path):
    g = grid(3, 3)
    write_usd_mesh(tmp_path / "cm.usda", g.vertices * 100.0, g.face_counts, g.face_indices, meters_per_unit=0.01)
    np.testing.assert_allclose(garment_from_usd(tmp_path / "cm.usda", "/World/dress").vertices, g.vertices,
                               atol=1e-6)


def test_obj_loader_keeps_quads_and_reads_negative_and_slashed_indices(tmp_path):
    path = tmp_path / "patch.obj"
    path.write_text("# two quads and a triangle\no patch\nv 0 0 0\nv 1 0 0\nv 2 0 0\nv 0 1 0\nv 1 1 0\nv 2 1 0\n"
                    "vt 0 0\nvn 0 0 1\nf 1/1/1 2/1/1 5/1/1 4/1/1\nf 2//1 3//1 6//1 5//1\nf -1 -2 -4\n")
    g = garment_from_file(path, pinned=[0, 3])
    np.testing.assert_array_equal(g.face_counts, [4, 4, 3])
    np.testing.assert_array_equal(g.face_indices, [0, 1, 4, 3, 1, 2, 5, 4, 5, 4, 2])
    assert len(g.quad_diagonals()) == 4 and g.name == "patch"
    np.testing.assert_array_equal(g.pinned, [0, 3])


BAD_OBJ = {
    "no faces": "v 0 0 0\nv 1 0 0\nv 0 1 0\n",
    "NaN": "v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n",
    "5 corners": "v 0 0 0\nv 1 0 0\nv 2 1 0\nv 1 2 0\nv 0 1 0\nf 1 2 3 4 5\n",
    "zero-length": "v 0 0 0\nv 1 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3 4\n",
    "cannot parse": "v 0 0 zero\nf 1 2 3\n",
}


@pytest.mark.parametrize("reason", list(BAD_OBJ))
def test_bad_obj_raises_value_error_naming_the_file_and_reason(tmp_path, reason):
    path = tmp_path / "bad.obj"
    path.write_text(BAD_OBJ[reason])
    with pytest.raises(ValueError) as err:
        garment_from_file(path)
    message = str(err.value)
    assert str(path) in message and "\n" not in message
    assert {"no faces": "no faces", "NaN": "NaN", "5 corners": "5 corners", "zero-length": "zero-length",
            "cannot parse": "line 1"}[reason] in message


def test_missing_or_wrong_files_raise_value_error_naming_file_and_prim(tmp_path):
    with pytest.raises(ValueError, match="missing.obj: file not found"):
        garment_from_file(tmp_path / "missing.obj")
    g = grid(2, 2)
    write_usd_mesh(tmp_path / "g.usda", g.vertices, g.face_counts, g.face_indices)
    with pytest.raises(ValueError, match=r"g.usda: /World/nothing: no such prim"):
        garment_from_usd(tmp_path / "g.usda", "/World/nothing")
    with pytest.raises(ValueError, match=r"g.usda: /World: is a Xform, not a Mesh"):
        garment_from_usd(tmp_path / "g.usda", "/World")
    with pytest.raises(ValueError, match=r"pinned vertex indices"):
        garment_from_usd(tmp_path / "g.usda", "/World/dress", pinned=[4])
    (tmp_path / "junk.usda").write_text("not usd at all")
    with pytest.raises(ValueError, match="junk.usda: not a USD file \\(USD could not open it: .+\\)"):
        garment_from_usd(tmp_path / "junk.usda")


# -- preview --------------------------------------------------------------------------------------------
def test_dress_renders_over_the_torso_and_leaves_the_arms_bare(tmp_path, body, garments):
    from PIL import Image

    from io_usd.cache import CacheReader, CacheWriter
    from io_usd.preview import Camera, render_frame

    dress = garments["dress"]
    path = str(tmp_path / "dress.usdc")
    with CacheWriter(path, fps=24, start_frame=1, end_frame=1) as w:
        w.add_mesh("body", "collider", body.vertices, body.faces)
        w.add_mesh("dress", "cloth", dress.vertices, dress.quads())
        w.write_frame(1, {"body": body.vertices, "dress": dress.vertices})
    camera = Camera.frame_points(body.vertices, 240, 320, yaw_degrees=0.0, pitch_degrees=5.0)
    image = render_frame(CacheReader(path), 1, camera, shadows=False)
    Image.fromarray(image).save("/tmp/garment_dress_test.png")
    rgb = image.astype(int)
    bluish = lambda uv: rgb[int(uv[1]), int(uv[0]), 2] > rgb[int(uv[1]), int(uv[0]), 0] + 15  # noqa: E731
    lm = body.landmarks
    torso = camera.project(np.array([[0.0, y, 0.3] for y in (lm["waist_y"], lm["hip_y"], lm["crotch_y"])]))
    arm = camera.project(body.vertices[(np.abs(body.vertices[:, 0]) > 0.3) & (body.vertices[:, 1] > 0.95)])
    assert all(bluish(uv) for uv in torso)
    assert not any(bluish(uv) for uv in arm[::25])
