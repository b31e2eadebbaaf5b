"""PN-triangle detail surface against closed forms, mesh invariants and a float64 reference."""

from math import factorial

import numpy as np
import pytest
import trimesh
import warp as wp

from sim.cloth import ClothModel
from sim.detail import KIND_EDGE, KIND_INTERIOR, KIND_VERTEX, DetailSurface, DetailTopology
from warp_kernels import detail as kernels


def grid(nx, ny, size=1.0):
    """An open (nx x ny)-quad grid in the z = 0 plane, each quad split in two."""
    x, y = np.meshgrid(np.linspace(0.0, size, nx + 1), np.linspace(0.0, size, ny + 1))
    points = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)
    i = np.arange(ny)[:, None] * (nx + 1) + np.arange(nx)[None, :]
    i = i.ravel()
    tris = np.concatenate([np.stack([i, i + 1, i + nx + 2], 1), np.stack([i, i + nx + 2, i + nx + 1], 1)])
    return points, tris


def patch(points, normals, tris, bary, owner):
    """pn_coefficients then pn_evaluate on explicit corner normals."""
    vec = lambda a: wp.array(np.asarray(a, np.float32).reshape(-1, 3), dtype=wp.vec3)  # noqa: E731
    tris = np.asarray(tris).reshape(-1, 3)
    control, coeffs = wp.zeros(10 * len(tris), dtype=wp.vec3), wp.zeros(6 * len(tris), dtype=wp.vec3)
    wp.launch(kernels.pn_coefficients, len(tris),
              [vec(points), vec(normals), wp.array(tris.reshape(-1).astype(np.int32), dtype=wp.int32), control,
               coeffs])
    pos, nrm = wp.zeros(len(owner), dtype=wp.vec3), wp.zeros(len(owner), dtype=wp.vec3)
    wp.launch(kernels.pn_evaluate, len(owner),
              [control, coeffs, wp.array(np.asarray(owner, np.int32), dtype=wp.int32), vec(bary), pos, nrm])
    return control.numpy(), pos.numpy(), nrm.numpy()


def undirected_edge_counts(tris):
    e = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0, return_counts=True)


def reference_surface(points, tris, owner, bary):
    """Float64 PN triangles written from Vlachos et al. 2001: area-weighted vertex normals, control
    points indexed by their exponent triple, the Bernstein sum over all ten of them."""
    x = np.asarray(points, np.float64)
    face_n = np.cross(x[tris[:, 1]] - x[tris[:, 0]], x[tris[:, 2]] - x[tris[:, 0]])
    vn = np.zeros_like(x)
    for k in range(3):
        np.add.at(vn, tris[:, k], face_n)
    vn /= np.linalg.norm(vn, axis=1, keepdims=True)
    P, N = x[tris[owner]], vn[tris[owner]]  # (M, 3 corners, 3)

    def edge_point(i, j):
        w = np.einsum("mk,mk->m", P[:, j] - P[:, i], N[:, i])[:, None]
        return (2.0 * P[:, i] + P[:, j] - w * N[:, i]) / 3.0

    b = {}
    for i in range(3):
        e = [0, 0, 0]
        e[i] = 3
        b[tuple(e)] = P[:, i]
        for j in range(3):
            if j != i:
                e = [0, 0, 0]
                e[i], e[j] = 2, 1
                b[tuple(e)] = edge_point(i, j)
    edge_mean = sum(v for k, v in b.items() if 2 in k) / 6.0
    b[(1, 1, 1)] = edge_mean + (edge_mean - P.mean(axis=1)) / 2.0
    pos = np.zeros((len(owner), 3))
    for (i, j, k), c in b.items():
        m = factorial(3) / (factorial(i) * factorial(j) * factorial(k))
        pos += c * (m * bary[:, 0] ** i * bary[:, 1] ** j * bary[:, 2] ** k)[:, None]

    def edge_normal(i, j):
        d = P[:, j] - P[:, i]
        v = 2.0 * np.einsum("mk,mk->m", d, N[:, i] + N[:, j]) / np.einsum("mk,mk->m", d, d)
        h = N[:, i] + N[:, j] - v[:, None] * d
        return h / np.linalg.norm(h, axis=1, keepdims=True)

    nrm = sum(N[:, i] * (bary[:, i] ** 2)[:, None] for i in range(3))
    for i, j in ((0, 1), (1, 2), (2, 0)):
        nrm += edge_normal(i, j) * (bary[:, i] * bary[:, j])[:, None]
    return pos, nrm / np.linalg.norm(nrm, axis=1, keepdims=True)


def test_flat_mesh_with_equal_normals_tessellates_to_its_linear_interpolation():
    pts, tris = grid(4, 3)
    rng = np.random.default_rng(1)
    pts[:, :2] += rng.uniform(-0.05, 0.05, (len(pts), 2))  # uneven triangles, still planar
    rot = trimesh.transformations.rotation_matrix(0.7, [1.0, 2.0, 0.5])[:3, :3]
    pts = pts @ rot.T + [0.3, -0.2, 0.1]
    surface = DetailSurface(tris, len(pts), 6)
    positions, normals = (a.numpy() for a in surface.update(pts))
    topo = surface.topology
    linear = np.einsum("mk,mkj->mj", topo.bary, pts[tris[topo.owner_face]])
    assert np.abs(positions - linear).max() < 1e-6
    assert np.abs(normals - rot[:, 2]).max() < 1e-6


def test_unit_sphere_octant_matches_the_closed_form_centre_and_centroid():
    axes = np.eye(3)
    control, pos, nrm = patch(axes, axes, [[0, 1, 2]], [[1 / 3, 1 / 3, 1 / 3]], [0])
    assert np.abs(control[9] - 0.5).max() < 1e-6  # b111
    assert np.abs(control[3] - [1.0, 1.0 / 3.0, 0.0]).max() < 1e-6  # b210 = (2 P1 + P2 + N1) / 3
    assert np.abs(pos[0] - 4.0 / 9.0).max() < 1e-4  # 0.4444
    assert np.abs(nrm[0] - 1.0 / np.sqrt(3.0)).max() < 1e-4  # 0.5774


def test_patch_passes_through_its_corners_with_their_normals():
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(3, 3))
    face_n = np.cross(pts[1] - pts[0], pts[2] - pts[0])
    normals = face_n / np.linalg.norm(face_n) + 0.4 * rng.normal(size=(3, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    _, pos, nrm = patch(pts, normals, [[0, 1, 2]], np.eye(3), [0, 0, 0])
    assert np.abs(pos - pts).max() < 1e-6
    assert np.abs(nrm - normals).max() < 1e-6


MESHES = {
    "triangle": (np.eye(3), np.array([[0, 1, 2]])),
    "tetrahedron": (np.vstack([np.zeros(3), np.eye(3)]), np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])),
    "icosphere": (trimesh.creation.icosphere(1).vertices, trimesh.creation.icosphere(1).faces),
    "grid": grid(5, 3),
}


@pytest.mark.parametrize("n", [1, 2, 3, 6])
@pytest.mark.parametrize("name", sorted(MESHES))
def test_vertex_and_face_counts_follow_the_tessellation_formula(name, n):
    pts, tris = MESHES[name]
    topo = DetailTopology(tris, len(pts), n)
    v, e, f = len(pts), len(undirected_edge_counts(tris)[0]), len(tris)
    assert topo.counts == (v + e * (n - 1) + f * (n - 1) * (n - 2) // 2, f * n * n)
    assert len(topo.edges) == e and topo.triangles.shape == (f * n * n, 3)
    assert np.array_equal(np.bincount(topo.kind, minlength=3), [v, e * (n - 1), f * (n - 1) * (n - 2) // 2])
    used = np.bincount(topo.triangles.ravel(), minlength=topo.num_vertices)
    assert used.min() > 0  # every detail vertex is in some detail triangle


def test_closed_icosphere_gives_a_closed_consistently_wound_manifold():
    sphere = trimesh.creation.icosphere(1)
    topo = DetailTopology(sphere.faces, len(sphere.vertices), 6)
    _, counts = undirected_edge_counts(topo.triangles)
    assert counts.min() == 2 and counts.max() == 2
    t = topo.triangles
    directed = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    assert len(np.unique(directed, axis=0)) == len(directed)  # each edge once per direction: one winding
    v, e, f = topo.num_vertices, len(counts), len(t)
    assert v - e + f == 2  # Euler characteristic of a sphere


def test_open_grid_has_detail_boundary_only_along_the_coarse_boundary():
    pts, tris = grid(4, 3)
    n = 6
    topo = DetailTopology(tris, len(pts), n)
    coarse_edges, coarse_counts = undirected_edge_counts(tris)
    edges, counts = undirected_edge_counts(topo.triangles)
    assert counts.max() == 2
    boundary = edges[counts == 1]
    assert len(boundary) == n * np.count_nonzero(coarse_counts == 1)
    # every boundary detail vertex is a coarse boundary vertex or lies on a coarse boundary edge
    on_boundary_edge = np.isin(topo.coarse_edge, np.flatnonzero(coarse_counts == 1))
    coarse_boundary_vertices = np.unique(coarse_edges[coarse_counts == 1])
    on_boundary_vertex = np.isin(topo.coarse_vertex, coarse_boundary_vertices)
    assert np.all((on_boundary_edge | on_boundary_vertex)[boundary])


def test_kernels_match_a_float64_reference_on_a_noisy_icosphere():
    sphere = trimesh.creation.icosphere(2)
    rng = np.random.default_rng(3)
    pts = sphere.vertices * rng.uniform(0.9, 1.1, (len(sphere.vertices), 1))
    surface = DetailSurface(sphere.faces, len(pts), 6)
    positions, normals = (a.numpy() for a in surface.update(pts.astype(np.float32)))
    topo = surface.topology
    ref_pos, ref_nrm = reference_surface(pts.astype(np.float32), sphere.faces, topo.owner_face, topo.bary)
    assert np.abs(positions - ref_pos).max() < 1e-6
    assert np.abs(normals - ref_nrm).max() < 1e-6


def test_adjacent_patches_share_their_edge_curve():
    # the welded mesh evaluates an edge vertex from its owner face only; with one normal per coarse
    # vertex the other face's patch passes through the same point, so the weld hides no crack
    sphere = trimesh.creation.icosphere(1)
    rng = np.random.default_rng(5)
    pts = sphere.vertices * rng.uniform(0.8, 1.2, (len(sphere.vertices), 1))
    surface = DetailSurface(sphere.faces, len(pts), 6)
    positions = surface.update(pts)[0].numpy()
    topo = surface.topology
    v = np.flatnonzero(topo.kind == KIND_EDGE)
    ends = np.sort(topo.edges[topo.coarse_edge[v]], axis=1)
    has = lambda k: (sphere.faces == ends[:, k, None, None]).any(axis=2)  # noqa: E731  (M, T)
    both = has(0) & has(1)
    both[np.arange(len(v)), topo.owner_face[v]] = False
    other = np.argmax(both, axis=1)
    assert np.all(both.sum(axis=1) == 1)
    same = sphere.faces[topo.owner_face[v]][:, :, None] == sphere.faces[other][:, None, :]  # (M, owner, other)
    bary = np.einsum("mj,mjk->mk", topo.bary[v], same.astype(float))
    _, pos, _ = patch(pts, surface.coarse_normals.numpy(), sphere.faces, bary, other)
    assert np.abs(pos - positions[v]).max() < 1e-6


def test_hierarchy_levels_are_the_divisors_and_parents_are_coarser():
    topo = DetailTopology([[0, 1, 2]], 3, 6)
    assert topo.level_steps == [1, 2, 3, 6]
    assert np.array_equal(np.bincount(topo.level), [3, 3, 7, 15])
    sphere = trimesh.creation.icosphere(1)
    for n in (1, 2, 3, 4, 6, 7, 12):
        topo = DetailTopology(sphere.faces, len(sphere.vertices), n)
        counts = np.bincount(topo.level, minlength=len(topo.level_steps))
        assert len(counts) == len(topo.level_steps) and counts.sum() == topo.num_vertices
        assert np.array_equal(np.diff(topo.level_start), counts)
        assert np.all(np.diff(topo.level[topo.level_order]) >= 0)
        assert np.array_equal(topo.level == 0, topo.kind == KIND_VERTEX)
        child = topo.level > 0
        assert np.all(topo.parent[~child] == -1)
        assert np.all(topo.level[topo.parent[child]] < topo.level[child])
        # a vertex of level l lies on the 1/d_l grid of its owner face
        d = np.array(topo.level_steps)[topo.level]
        scaled = topo.bary * d[:, None]
        assert np.abs(scaled - np.round(scaled)).max() < 1e-9
    assert len(DetailTopology(sphere.faces, len(sphere.vertices), 6).level_steps) == 4


def test_parent_is_the_nearest_coarser_vertex_of_the_owner_face():
    for n in (2, 3, 4, 6, 8, 12):
        topo = DetailTopology([[0, 1, 2]], 3, n)  # one face: every vertex is owned by it
        for v in np.flatnonzero(topo.level > 0):
            coarser = topo.level < topo.level[v]
            dist = np.sum((topo.bary[coarser] - topo.bary[v]) ** 2, axis=1)
            assert np.isclose(np.sum((topo.bary[topo.parent[v]] - topo.bary[v]) ** 2), dist.min())
            # the lift's gate reads the four nearest coarser points, nearest first
            listed = topo.coarser[v][topo.coarser[v] >= 0]
            assert len(listed) == min(4, np.count_nonzero(coarser)) and listed[0] == topo.parent[v]
            assert np.all(topo.level[listed] < topo.level[v])
            np.testing.assert_allclose(np.sum((topo.bary[listed] - topo.bary[v]) ** 2, axis=1),
                                       np.sort(dist)[:len(listed)], atol=1e-12)
    # on a mesh, the midpoint of a coarse edge (level 1 for even n) hangs from an end of that edge
    topo = DetailTopology(trimesh.creation.icosphere(1).faces, 42, 6)
    mids = np.flatnonzero((topo.level == 1) & (topo.kind == KIND_EDGE))
    ends = topo.edges[topo.coarse_edge[mids]]
    assert len(mids) == len(topo.edges)
    assert np.all((topo.parent[mids] == ends[:, 0]) | (topo.parent[mids] == ends[:, 1]))


def test_degenerate_edges_and_triangles_give_finite_unit_output():
    # vertex 3 sits on vertex 0 (a zero-length edge); triangle (0, 1, 4) is collinear (zero area)
    pts = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0], [0.5, 0.0, 0.0],
                    [5.0, 5.0, 5.0], [5.0, 5.0, 5.0], [5.0, 5.0, 5.0]])
    tris = np.array([[0, 1, 2], [0, 2, 3], [3, 2, 1], [0, 1, 4], [5, 6, 7]])
    surface = DetailSurface(tris, len(pts), 6)
    for _ in range(2):  # the second update starts from the first one's normals
        positions, normals = (a.numpy() for a in surface.update(pts))
        assert np.all(np.isfinite(positions)) and np.all(np.isfinite(normals))
        assert np.abs(np.linalg.norm(normals, axis=1) - 1.0).max() < 1e-5
    assert np.allclose(positions[surface.topology.owner_face == 4], 5.0)  # a point stays a point


def test_detail_surface_follows_a_cloth_model_and_reports_its_counts():
    pts, tris = grid(3, 2)
    edges = undirected_edge_counts(tris)[0]
    model = ClothModel(pts, tris, edges, [], [], [0])
    surface = DetailSurface.from_cloth(model, tessellation=3)
    assert surface.counts == (len(pts) + len(edges) * 2 + len(tris), len(tris) * 9)
    assert surface.triangles_np.shape == (len(tris) * 9, 3)
    positions, _ = surface.update(model.state().x)
    assert np.abs(positions.numpy()[: len(pts)] - pts).max() < 1e-6  # corners are the coarse points


def test_vertex_neighbours_are_the_detail_mesh_edges():
    pts, tris = MESHES["grid"]
    topo = DetailTopology(tris, len(pts), 3)
    start, adj = topo.detail_vertex_neighbours()
    edges = undirected_edge_counts(topo.triangles)[0]
    assert start[-1] == 2 * len(edges)
    rows = np.repeat(np.arange(topo.num_vertices), np.diff(start))
    pairs = np.sort(np.stack([rows, adj], 1), axis=1)
    assert np.array_equal(np.unique(pairs, axis=0), edges)
    interior = np.flatnonzero(topo.kind == KIND_INTERIOR)
    assert np.all(np.diff(start)[interior] == 6)  # a regular lattice inside each face


def test_invalid_meshes_are_rejected_with_the_reason():
    with pytest.raises(ValueError, match="repeat a vertex"):
        DetailTopology([[0, 0, 1]], 2, 6)
    with pytest.raises(ValueError, match="belong to no triangle"):
        DetailTopology([[0, 1, 2]], 4, 6)
    with pytest.raises(ValueError, match="must lie in"):
        DetailTopology([[0, 1, 3]], 3, 6)


def _carried(points, i, first, last):
    """Eq. 5 along a line of points, in float64: the force at sample i blended between the ends by
    the share of the transmission (eq. 4) up to i, counting half of i's own."""
    c = []
    for k in range(1, len(points) - 1):
        d0, d1 = points[k] - points[k - 1], points[k + 1] - points[k]
        l0, l1 = np.linalg.norm(d0), np.linalg.norm(d1)
        c.append(1.0 if min(l0, l1) < 1e-12 else max(d0 @ d1 / (l0 * l1), 0.01))
    c = np.array(c)
    upto = c[: i - 1].sum() + 0.5 * c[i - 1]
    t = upto / c.sum() if c.sum() > 1e-12 else 0.5
    return first + t * (last - first)


@pytest.mark.parametrize("n", [2, 3, 6])
def test_carried_forces_match_a_float64_reference_of_eqs_4_5_on_a_crumpled_surface(n):
    """carry_forces against a per-sample float64 reading of eqs. 4-5 on a crumpled grid: corners
    take their particle's force, edge samples blend along the edge, interior samples average the
    blends along their two grid lines, whose ends lie on the edges."""
    from sim.detail import ClothDetail, DetailParams

    pts, tris = grid(3, 2)
    edges = undirected_edge_counts(tris)[0]
    model = ClothModel(pts, tris, edges, [], [], [0])
    detail = ClothDetail(model, DetailParams(level=n))
    top = detail.surface.topology
    assert top.tessellation == n
    rng = np.random.default_rng(n)
    positions = rng.normal(0.0, 1.0, (top.num_vertices, 3))  # folds of every angle, some past 90 degrees
    coarse = rng.normal(0.0, 1.0, (len(pts), 3))
    force = wp.zeros(top.num_vertices, dtype=wp.vec3)
    detail.carry_forces(wp.array(positions.astype(np.float32), dtype=wp.vec3),
                        wp.array(coarse.astype(np.float32), dtype=wp.vec3), force)
    x = positions.astype(np.float32).astype(np.float64)
    f = coarse.astype(np.float32).astype(np.float64)
    expected = np.full((top.num_vertices, 3), np.nan)
    for face, corners in enumerate(top.coarse_triangles):
        at = lambda a, b: top.lattice[face, top.lattice_index[a, b]]  # noqa: E731
        f0, f1, f2 = f[corners]

        def edge(points, i, first, last):
            return _carried(x[[at(a, b) for a, b in points]], i, first, last)

        e01 = [(k, 0) for k in range(n + 1)]
        e02 = [(0, k) for k in range(n + 1)]
        e12 = [(n - k, k) for k in range(n + 1)]
        for a in range(n + 1):
            for b in range(n + 1 - a):
                v = at(a, b)
                if top.owner_face[v] != face:
                    continue
                if (a, b) == (0, 0):
                    value = f0
                elif a == n:
                    value = f1
                elif b == n:
                    value = f2
                elif b == 0:
                    value = edge(e01, a, f0, f1)
                elif a == 0:
                    value = edge(e02, b, f0, f2)
                elif a + b == n:
                    value = edge(e12, b, f1, f2)
                else:
                    along_a = edge([(a, k) for k in range(n - a + 1)], b, edge(e01, a, f0, f1), edge(e12, n - a, f1, f2))
                    along_b = edge([(k, b) for k in range(n - b + 1)], a, edge(e02, b, f0, f2), edge(e12, b, f1, f2))
                    value = 0.5 * (along_a + along_b)
                assert np.isnan(expected[v, 0])  # every sample has one owner
                expected[v] = value
    assert not np.isnan(expected).any()
    np.testing.assert_allclose(force.numpy(), expected, rtol=0, atol=2e-5 * np.abs(f).max())
