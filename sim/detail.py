"""The detail surface of a coarse garment (Oshita & Makinouchi §4.1): every coarse triangle becomes
a curved PN triangle (Vlachos, Peters, Boyd & Mitchell 2001) tessellated n x n, so a few hundred
simulated particles drive a smooth mesh of thousands of vertices.

DetailTopology is built once in NumPy: the welded detail mesh and, per detail vertex, the coarse face
that evaluates it and its barycentric weights there, plus a coarse-to-fine hierarchy. DetailSurface
holds it on the device and evaluates it each frame with three launches.

    surface = DetailSurface.from_cloth(cloth_model, tessellation=6)
    positions, normals = surface.update(state.x)      # wp.arrays of surface.counts[0] vec3
"""

from dataclasses import dataclass
from functools import partial

import numpy as np
import warp as wp

from warp_kernels import detail as kernels

from .config import require_nonnegative, require_positive
from .graphs import cpu_cores, run_parallel
from .mesh_topology import unique_pairs

KIND_VERTEX, KIND_EDGE, KIND_INTERIOR = 0, 1, 2
# a level of the lift with at least this many samples per CPU core is split among the cores: smaller
# ones cost less than handing work to another thread
SPLIT_SAMPLES = 1024
# coarser samples whose clearances bound a detail sample's (the lift's gate; a wp.vec4i each)
BOUNDED_BY = 4
# Jacobi passes of the slope limit (§4.3.4): each carries a lowered sample's limit one ring further, and a
# limit applied once leaves the samples it lowered steeper than max_slope above their own neighbours, so
# the more often the heights were updated the lower they sat; four reach the limit's fixed point in the
# squeezed sheet of the tests (wrinkles a centimetre high) and in the walking dress
SLOPE_PASSES = 4


def _lattice(n):
    """The (n+1)(n+2)/2 lattice points of one triangle as integer weights (i0, i1, i2) summing to n
    (of corners 0, 1, 2), with `index[i1, i2]` the position of a point in that list."""
    weights = np.array([(n - a - b, a, b) for b in range(n + 1) for a in range(n + 1 - b)], np.int64)
    index = np.full((n + 1, n + 1), -1, np.int64)
    index[weights[:, 1], weights[:, 2]] = np.arange(len(weights))
    return weights, index


def _hierarchy(weights, n, bounded_by=BOUNDED_BY):
    """Level and nearest coarser lattice points of every lattice point.

    The levels are the divisors d_0 = 1 < d_1 < ... < d_L = n of n: a point belongs to the first
    level l whose grid of step 1/d_l contains it (all weights multiples of n / d_l). For n = 6 the
    steps are 1, 1/2, 1/3, 1/6, so level 0 is the corners and level 3 everything left; a prime n has
    two levels. `coarser[p]` lists the bounded_by points of strictly coarser levels nearest p
    (Euclidean distance of the barycentric weights, proportional to distance in an equilateral
    triangle; ties go to the coarser level, then to the earlier lattice point), -1 where there are
    fewer; its first, the parent, is the nearest.
    """
    divisors = [d for d in range(1, n + 1) if n % d == 0]
    level = np.empty(len(weights), np.int64)
    for p, w in enumerate(weights):
        level[p] = next(k for k, d in enumerate(divisors) if np.all(w * d % n == 0))
    coarser = np.full((len(weights), bounded_by), -1, np.int64)
    for p, w in enumerate(weights):
        if level[p] == 0:
            continue
        candidates = np.flatnonzero(level < level[p])
        dist = np.sum((weights[candidates] - w) ** 2, axis=1)
        nearest = candidates[np.lexsort((candidates, level[candidates], dist))[:bounded_by]]
        coarser[p, :len(nearest)] = nearest
    return divisors, level, coarser


class DetailTopology:
    """The welded n x n tessellation of a coarse triangle mesh, built once.

    Detail vertices come in three blocks: the V coarse vertices (detail index = coarse index), then
    n - 1 per unique coarse edge (`edges`, ordered from its lower to its higher vertex index), then
    (n - 1)(n - 2) / 2 per coarse face interior. Faces sharing a coarse edge share its detail
    vertices, so the detail mesh is closed where the coarse mesh is. Detail triangle
    f n^2 + k is the k-th of coarse face f (`coarse_face`) and wound like it.

    Per detail vertex: `owner_face` (the lowest-indexed coarse face containing it; its patch evaluates
    the vertex), `bary` (float64 weights of the owner's corners 0, 1, 2), `kind` (KIND_VERTEX,
    KIND_EDGE, KIND_INTERIOR), `coarse_vertex` / `coarse_edge` (or -1), and the hierarchy `level` /
    `coarser` (its first column is `parent`) described in `_hierarchy`;
    `level_order[level_start[l]:level_start[l + 1]]` are the vertices of level l, for one launch per
    level. `level_steps` are the divisors defining the levels.
    """

    def __init__(self, triangles, num_points, tessellation=6):
        tris = np.asarray(triangles, np.int64).reshape(-1, 3)
        n, nv, nt = int(tessellation), int(num_points), len(tris)
        if n < 1:
            raise ValueError(f"tessellation must be at least 1, got {tessellation}")
        if nt and (tris.min() < 0 or tris.max() >= nv):
            raise ValueError(f"triangle indices must lie in [0, {nv}); found {tris.min()}..{tris.max()}")
        repeated = (tris[:, 0] == tris[:, 1]) | (tris[:, 1] == tris[:, 2]) | (tris[:, 2] == tris[:, 0])
        if np.any(repeated):
            raise ValueError(f"{np.count_nonzero(repeated)} triangles repeat a vertex index "
                             f"(first: triangle {np.flatnonzero(repeated)[0]})")
        unused = np.bincount(tris.reshape(-1), minlength=nv) == 0
        if np.any(unused):
            raise ValueError(f"{np.count_nonzero(unused)} coarse vertices belong to no triangle "
                             f"(first: vertex {np.flatnonzero(unused)[0]}); the detail surface has no patch for them")
        self.tessellation, self.num_coarse_points, self.coarse_triangles = n, nv, tris

        # unique coarse edges; local edge l of a face joins its corners l and l + 1
        corner_pairs = np.stack([tris, np.roll(tris, -1, axis=1)], axis=2)  # (T, 3, 2)
        self.edges, face_edge = unique_pairs(np.sort(corner_pairs, axis=2).reshape(-1, 2), return_inverse=True)
        face_edge = face_edge.reshape(nt, 3)
        ne = len(self.edges)
        per_interior = (n - 1) * (n - 2) // 2
        edge_base, interior_base = nv, nv + ne * (n - 1)
        self.num_vertices = interior_base + nt * per_interior
        self.num_faces = nt * n * n

        # lattice[f, p]: detail index of lattice point p of face f
        weights, index = _lattice(n)
        lattice = np.empty((nt, len(weights)), np.int64)
        interior_rank = 0
        for p, w in enumerate(weights):
            zeros = np.flatnonzero(w == 0)
            if len(zeros) == 2:
                lattice[:, p] = tris[:, int(np.argmax(w))]
            elif len(zeros) == 1:
                a = (int(zeros[0]) + 1) % 3  # the edge opposite the zero weight runs from corner a to b
                b = (a + 1) % 3
                # the step along the edge counts from its lower-indexed end
                t = np.where(tris[:, a] > tris[:, b], w[a], w[b])
                lattice[:, p] = edge_base + face_edge[:, a] * (n - 1) + t - 1
            else:
                lattice[:, p] = interior_base + np.arange(nt) * per_interior + interior_rank
                interior_rank += 1

        # owner face: the lowest-indexed face containing the vertex; its lattice point gives the bary
        faces = np.repeat(np.arange(nt), len(weights))
        flat = lattice.reshape(-1)
        owner = np.full(self.num_vertices, nt, np.int64)
        np.minimum.at(owner, flat, faces)
        mine = faces == owner[flat]
        point = np.empty(self.num_vertices, np.int64)
        point[flat[mine]] = np.tile(np.arange(len(weights)), nt)[mine]
        self.owner_face = owner
        self.bary = weights[point] / float(n)
        zeros = np.count_nonzero(weights == 0, axis=1)
        self.kind = np.select([zeros == 2, zeros == 1], [KIND_VERTEX, KIND_EDGE], KIND_INTERIOR)[point]
        ids = np.arange(self.num_vertices)
        self.coarse_vertex = np.where(self.kind == KIND_VERTEX, ids, -1)
        self.coarse_edge = np.where(self.kind == KIND_EDGE, (ids - edge_base) // max(n - 1, 1), -1)

        self.level_steps, point_level, point_coarser = _hierarchy(weights, n)
        self.level = point_level[point]
        from_points = point_coarser[point]
        self.coarser = np.where(from_points >= 0, lattice[owner[:, None], np.maximum(from_points, 0)], -1)
        self.parent = self.coarser[:, 0]
        self.level_order = np.argsort(self.level, kind="stable")
        self.level_start = np.searchsorted(self.level[self.level_order], np.arange(len(self.level_steps) + 1))

        # n^2 triangles per face: "up" (a, b), (a+1, b), (a, b+1) and "down" (a+1, b), (a+1, b+1),
        # (a, b+1) in the weights (a, b) of corners 1 and 2, both wound like corners 0, 1, 2
        local = [(index[a, b], index[a + 1, b], index[a, b + 1]) for b in range(n) for a in range(n - b)]
        local += [(index[a + 1, b], index[a + 1, b + 1], index[a, b + 1]) for b in range(n - 1)
                  for a in range(n - 1 - b)]
        local = np.array(local, np.int64)
        self.triangles = lattice[:, local].reshape(-1, 3)
        # lattice[f, lattice_index[a, b]]: the detail vertex at weights (n - a - b, a, b) / n of face f
        self.lattice, self.lattice_index = lattice, index
        self.coarse_face = np.repeat(np.arange(nt), n * n)

        # coarse vertex -> incident faces (CSR) for the normal gather
        vf = tris.reshape(-1)
        order = np.argsort(vf, kind="stable")
        self.coarse_vf_start = np.concatenate([[0], np.cumsum(np.bincount(vf, minlength=nv))])
        self.coarse_vf_face = np.repeat(np.arange(nt), 3)[order]

    @property
    def faces_of(self):
        """The coarse face each detail vertex lies in (its owner face), e.g. to skip the detail
        vertices of coarse faces far from the body."""
        return self.owner_face

    @property
    def counts(self):
        return self.num_vertices, self.num_faces

    def detail_vertex_neighbours(self):
        """Vertex adjacency of the detail mesh as CSR (start (N+1,), adj): the neighbours of vertex i
        are adj[start[i]:start[i + 1]], ascending."""
        t = self.triangles
        e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
        e = unique_pairs(np.concatenate([e, e[:, ::-1]]))  # lexicographic: grouped by first vertex
        start = np.concatenate([[0], np.cumsum(np.bincount(e[:, 0], minlength=self.num_vertices))])
        return start, e[:, 1].copy()


class DetailSurface:
    """A DetailTopology on the device, evaluated from the coarse points each frame.

    update() launches coarse_vertex_normals, pn_coefficients and pn_evaluate and returns the detail
    positions and unit normals; the arrays are reused, so the next update overwrites them.
    """

    def __init__(self, triangles, num_points, tessellation=6, device="cpu"):
        self.device = device
        self.topology = topo = DetailTopology(triangles, num_points, tessellation)
        arr = lambda a, t: wp.array(a, dtype=t, device=device)  # noqa: E731
        self.triangles = arr(topo.coarse_triangles.reshape(-1).astype(np.int32), wp.int32)
        self.vf_start = arr(topo.coarse_vf_start.astype(np.int32), wp.int32)
        self.vf_face = arr(topo.coarse_vf_face.astype(np.int32), wp.int32)
        self.owner_face = arr(topo.owner_face.astype(np.int32), wp.int32)
        self.bary = arr(topo.bary.astype(np.float32), wp.vec3)
        nt = len(topo.coarse_triangles)
        # unit fallback for vertices whose faces have no area yet (see coarse_vertex_normals)
        self.coarse_normals = arr(np.tile(np.float32([0.0, 1.0, 0.0]), (num_points, 1)), wp.vec3)
        self.control = wp.zeros(10 * nt, dtype=wp.vec3, device=device)
        self.normal_coeffs = wp.zeros(6 * nt, dtype=wp.vec3, device=device)
        self.positions = wp.zeros(topo.num_vertices, dtype=wp.vec3, device=device)
        self.normals = wp.zeros(topo.num_vertices, dtype=wp.vec3, device=device)

    @classmethod
    def from_cloth(cls, model, tessellation=6):
        """Over a sim.ClothModel (or anything with triangles_np, num_particles and device)."""
        return cls(model.triangles_np, model.num_particles, tessellation, model.device)

    @property
    def counts(self):
        """(detail vertices, detail triangles)."""
        return self.topology.counts

    @property
    def triangles_np(self):
        """(F, 3) detail triangles, wound like their coarse triangles."""
        return self.topology.triangles

    def update(self, points):
        """Detail (positions, normals) for coarse points: a wp.array of vec3 on this device (a NumPy
        (V, 3) array is copied over first)."""
        topo, dev = self.topology, self.device
        if not isinstance(points, wp.array):
            points = wp.array(np.asarray(points, np.float32).reshape(-1, 3), dtype=wp.vec3, device=dev)
        if points.shape[0] != topo.num_coarse_points:
            raise ValueError(f"expected {topo.num_coarse_points} coarse points, got {points.shape[0]}")
        wp.launch(kernels.coarse_vertex_normals, topo.num_coarse_points,
                  [points, self.triangles, self.vf_start, self.vf_face, self.coarse_normals], device=dev)
        wp.launch(kernels.pn_coefficients, len(topo.coarse_triangles),
                  [points, self.coarse_normals, self.triangles, self.control, self.normal_coeffs], device=dev)
        wp.launch(kernels.pn_evaluate, topo.num_vertices,
                  [self.control, self.normal_coeffs, self.owner_face, self.bary, self.positions, self.normals],
                  device=dev)
        return self.positions, self.normals


def pn_surface_points(vertices, normals, triangles, face, bary, device="cpu"):
    """(points, unit normals), NumPy (N, 3), on the PN triangles (Vlachos et al. 2001) of a mesh
    (vertices (V, 3), unit vertex normals (V, 3), triangles (F, 3)) at barycentric weights bary (N, 3) of
    triangles face (N,): the curved surface the detail surface lays over the coarse cloth
    (kernels.pn_coefficients, pn_evaluate), here for points given on any mesh's flat triangles, such as
    the closest points of a face grid snapped onto the head (sim.scene)."""
    arr = lambda a, t, k=np.float32: wp.array(np.ascontiguousarray(a, k), dtype=t, device=device)  # noqa: E731
    faces = np.asarray(triangles).reshape(-1, 3)
    control = wp.zeros(10 * len(faces), dtype=wp.vec3, device=device)
    normal_coeffs = wp.zeros(6 * len(faces), dtype=wp.vec3, device=device)
    wp.launch(kernels.pn_coefficients, len(faces), [arr(vertices, wp.vec3), arr(normals, wp.vec3),
                                                    arr(faces.reshape(-1), wp.int32, np.int32), control,
                                                    normal_coeffs], device=device)
    points = wp.zeros(len(face), dtype=wp.vec3, device=device)
    out_normals = wp.zeros(len(face), dtype=wp.vec3, device=device)
    wp.launch(kernels.pn_evaluate, len(face), [control, normal_coeffs, arr(face, wp.int32, np.int32),
                                               arr(bary, wp.vec3), points, out_normals], device=device)
    return points.numpy().astype(np.float64), out_normals.numpy().astype(np.float64)


@dataclass(frozen=True)
class DetailParams:
    """The detail surface over a simulated garment (Oshita & Makinouchi §4)."""

    level: int = 6  # tessellation level: n x n detail triangles per coarse triangle (the paper: 6); 0 = none
    margin: float = 0.003  # m, detail vertices kept this far outside the body
    # tests of samples with finer ones look at least band beyond the margin: one found no nearer spares
    # its finer neighbours within band of it
    band: float = 0.01  # m (§4.2)
    # eq. 3 carries dh from the last frame; carrying all of it would keep a lift forever after the
    # contact ends (only wrinkles and the dh >= 0 clamp ever lower it), so a share is carried:
    height_carry: float = 0.85  # share of the height carried over a frame of 1/reference_fps s (eq. 3)
    wrinkles: bool = True  # force-driven wrinkles (§4.3)
    k_out_plane: float = 1.0  # m/(N s), how far a sample may move per unit vertical force and time (eq. 12)
    max_slope: float = 0.6  # a sample rises at most this times its distance above a neighbour (§4.3.4)
    smoothing: int = 2  # Jacobi passes over the heights before the constraints (0: the paper's model)
    h_normal: float = 0.004  # m, height at which the displaced surface's normal fully takes over (eq. 13)
    # the paper's height updates (the carry, eq. 11's length change, the smoothing passes) are per frame;
    # they are read as those of a frame at this rate and scaled to the time an update spans, so the
    # wrinkles do not depend on the scene's fps (taken per update, 48 fps had 60% of the heights of 24):
    reference_fps: float = 24.0  # frames/s at which height_carry and the smoothing passes are given

    def __post_init__(self):
        if self.level < 0:
            raise ValueError("level must be 0 (no detail surface) or positive")
        if not (0.0 <= self.height_carry <= 1.0):
            raise ValueError("height_carry must be in [0, 1]")
        if self.smoothing < 0:
            raise ValueError("smoothing must be zero or positive")
        require_nonnegative(self, "margin", "band", "k_out_plane", "max_slope", "h_normal")
        require_positive(self, "reference_fps")


class ClothDetail:
    """The per-frame detail surface of a garment: PN surface, wrinkle heights, lift out of the body,
    blended normals. update(cloth_model, cloth_state, body, dt) -> (positions, normals) wp.arrays."""

    def __init__(self, cloth_model, params=DetailParams(), device="cpu"):
        self.params, self.device = params, device
        self.surface = DetailSurface(cloth_model.triangles_np, cloth_model.num_particles, params.level, device)
        top = self.surface.topology
        n, nt = top.tessellation, len(top.coarse_triangles)
        arr = lambda a, t: wp.array(np.ascontiguousarray(a), dtype=t, device=device)  # noqa: E731
        nv = top.num_vertices

        # face grid in (a, b) order of warp_kernels.detail.grid_slot: a, b = weights of corners 1, 2
        slots = [(a, b) for a in range(n + 1) for b in range(n + 1 - a)]
        grid = np.stack([top.lattice[:, top.lattice_index[a, b]] for a, b in slots], axis=1)
        self.face_grid = arr(grid.reshape(-1).astype(np.int32), wp.int32)
        self.corner_vertex = arr(top.coarse_triangles.reshape(-1).astype(np.int32), wp.int32)
        self.owner_face = arr(top.owner_face.astype(np.int32), wp.int32)
        self.bary = arr(top.bary.astype(np.float32), wp.vec3)
        self.kind = arr(top.kind.astype(np.int32), wp.int32)
        self.coarse_edge = arr(np.maximum(top.coarse_edge, 0).astype(np.int32), wp.int32)
        self.coarser = arr(top.coarser.astype(np.int32), wp.vec4i)
        self.levels = [arr(top.level_order[top.level_start[k]:top.level_start[k + 1]].astype(np.int32), wp.int32)
                       for k in range(len(top.level_steps))]
        self.split_levels(1 if wp.get_device(device).is_cuda else cpu_cores())
        start, adj = top.detail_vertex_neighbours()
        self.nbr_start, self.nbr = arr(start.astype(np.int32), wp.int32), arr(adj.astype(np.int32), wp.int32)
        t = top.triangles.reshape(-1)
        order = np.argsort(t, kind="stable")
        self.detail_tris = arr(t.astype(np.int32), wp.int32)
        self.vf_start = arr(np.concatenate([[0], np.cumsum(np.bincount(t, minlength=nv))]).astype(np.int32), wp.int32)
        self.vf_face = arr(np.repeat(np.arange(len(top.triangles)), 3)[order].astype(np.int32), wp.int32)

        # coarse edges: which face and side walks each, its rest length, the faces' three edges
        edges = top.edges
        key = {tuple(e): k for k, e in enumerate(map(tuple, edges))}
        edge_face = np.full(len(edges), -1, np.int64)
        edge_side = np.zeros(len(edges), np.int64)
        face_edges = np.zeros((nt, 3), np.int64)
        sides = ((0, 1), (0, 2), (1, 2))  # grid lines: corner 0 -> 1, corner 0 -> 2, corner 1 -> 2
        for f, tri in enumerate(top.coarse_triangles):
            for s, (c0, c1) in enumerate(sides):
                e = key[tuple(sorted((int(tri[c0]), int(tri[c1]))))]
                face_edges[f, s] = e
                if edge_face[e] < 0:
                    edge_face[e], edge_side[e] = f, s
        rest = cloth_model.rest_positions_np.astype(np.float64)
        rest_base = self.surface.update(wp.array(rest.astype(np.float32), dtype=wp.vec3, device=device))[0].numpy()
        self._rest_edge_np = self._polyline_lengths(rest_base.astype(np.float64), grid, edge_face, edge_side, n)
        # the farthest each sample's children lie from it at rest: its tests look this far (with slack
        # for stretch), so a sample found farther from the body spares its children
        child = np.flatnonzero(top.parent >= 0)
        self.spread = np.zeros(nv)
        np.maximum.at(self.spread, top.parent[child], np.linalg.norm(rest_base[child] - rest_base[top.parent[child]],
                                                                      axis=1))
        self.reach = arr(self.query_radius(self.spread).astype(np.float32), float)
        self.edge_face, self.edge_side = arr(edge_face.astype(np.int32), wp.int32), arr(edge_side.astype(np.int32), wp.int32)
        self.face_edges = arr(face_edges.reshape(-1).astype(np.int32), wp.int32)
        ve = np.concatenate([edges[:, 0], edges[:, 1]])
        ve_order = np.argsort(ve, kind="stable")
        self.ve_start = arr(np.concatenate([[0], np.cumsum(np.bincount(ve, minlength=cloth_model.num_particles))])
                            .astype(np.int32), wp.int32)
        self.ve_edge = arr(np.tile(np.arange(len(edges)), 2)[ve_order].astype(np.int32), wp.int32)
        self.num_edges, self.tessellation = len(edges), n

        z = lambda count, t=float: wp.zeros(count, dtype=t, device=device)  # noqa: E731
        self.height, self.height_tmp, self.change = z(nv), z(nv), z(nv)
        self.vertical, self.clearance = z(nv), z(nv)
        self.body_vertex, self.probe_point = arr(np.full(nv, -1, np.int32), wp.int32), z(nv, wp.vec3)
        self.force = z(nv, wp.vec3)
        nt = len(top.coarse_triangles)
        # carry_forces' scratch: each line's transmissions, and the edges' blends
        self.line_shares, self.edge_forces = z(nt * max(3, n - 2) * (n + 1)), z(3 * nt * (n + 1), wp.vec3)
        self.positions, self.normals = z(nv, wp.vec3), z(nv, wp.vec3)
        self.coarse_force = z(cloth_model.num_particles, wp.vec3)
        self.coarse_deficit = z(cloth_model.num_particles)
        self.edge_deficit = z(len(edges))
        self.rest_edge = arr(self._rest_edge_np.astype(np.float32), float)
        self.side = 1.0  # +1 when the garment's winding faces away from the body, -1 when it faces it
        self._side_known = False
        self.uncompressed = z(nt, wp.int32)

    def split_levels(self, parts, min_samples=SPLIT_SAMPLES):
        """Split each level of the lift into up to `parts` runs of at least min_samples samples
        (self.level_parts), which a captured CPU frame replays on as many cores at once (a level's
        samples read only coarser levels' results). One part on a GPU, where a launch fills the device."""
        self.level_parts = []
        for level in self.levels:
            k = max(1, min(parts, len(level) // max(min_samples, 1)))
            self.level_parts.append([level[len(level) * i // k:len(level) * (i + 1) // k] for i in range(k)])
        # samples tested and BVH queries among them, a pair per part (parts on different cores would
        # lose each other's counts in one pair)
        most = max(len(p) for p in self.level_parts)
        self.queries = wp.zeros(2 * most, dtype=wp.int32, device=self.device)
        self._part_queries = [self.queries[2 * i:2 * i + 2] for i in range(most)]

    @staticmethod
    def _polyline_lengths(p, grid, edge_face, edge_side, n):
        """Rest length of every coarse edge measured along its PN curve on the rest shape (p, the PN
        surface's positions at rest)."""
        slots = {(a, b): k for k, (a, b) in enumerate((a, b) for a in range(n + 1) for b in range(n + 1 - a))}
        out = np.zeros(len(edge_face))
        for s, walk in enumerate(([(k, 0) for k in range(n + 1)], [(0, k) for k in range(n + 1)],
                                  [(n - k, k) for k in range(n + 1)])):
            mask = edge_side == s
            idx = grid[edge_face[mask]][:, [slots[w] for w in walk]]
            out[mask] = np.linalg.norm(np.diff(p[idx], axis=1), axis=2).sum(axis=1)
        return out

    @property
    def triangles_np(self):
        return self.surface.topology.triangles

    def update(self, cloth_model, cloth_state, body, dt):
        """Evaluate this frame's detail surface from the coarse state; body (a Collider) may be None."""
        p, dev, nv = self.params, self.device, self.surface.topology.num_vertices
        base, pn_normals = self.surface.update(cloth_state.x)
        wp.launch(kernels.relax_heights, nv, [self.height, p.height_carry ** (dt * p.reference_fps)], device=dev)
        if p.wrinkles:
            self._wrinkles(cloth_model, cloth_state, base, dt)
        self.queries.zero_()
        if body is not None and not self._side_known:
            self.side = self._outward_side(base, pn_normals, body)
            self._side_known = True
        if body is not None:
            adj, walk = body.adjacency(), cloth_model.params
            for parts in self.level_parts:
                run_parallel([partial(wp.launch, kernels.lift_out_of_body, len(part),
                                      [base, pn_normals, part, self.coarser, body.mesh.id,
                                       body.points, body.indices, adj.vv_start, adj.vv_adj, adj.vf_start, adj.vf_face,
                                       adj.concave, walk.walk_steps, walk.teleport, walk.walk_trust_distance,
                                       self.side, p.margin, self.reach, self.height, self.clearance, self.body_vertex,
                                       self.probe_point, queries], device=dev)
                              for part, queries in zip(parts, self._part_queries)])
        wp.launch(kernels.displace_along_directions, nv, [base, pn_normals, self.side, self.height, self.positions],
                  device=dev)
        wp.launch(kernels.surface_vertex_normals, nv,
                  [self.positions, self.detail_tris, self.vf_start, self.vf_face, pn_normals, self.height, p.h_normal,
                   self.normals], device=dev)
        return self.positions, self.normals

    def query_radius(self, spread):
        """The smallest query radius of a sample's lift test (kernels.lift_out_of_body), given how far
        its children lie from it (spread, m; 0 for none): far enough that a sample found no nearer
        spares them, at least band beyond the margin; for a sample without children the margin alone
        decides."""
        p = self.params
        return np.where(spread > 0.0, p.margin + np.maximum(p.band, 1.25 * spread), p.margin)

    def _outward_side(self, base, normals, body):
        """Which way the PN normals face relative to the body: the garment may be wound either way."""
        x, n = base.numpy(), normals.numpy()
        _, face, bary = body.closest_points(x)
        closest = np.einsum("nk,nkj->nj", bary, body.points.numpy()[body.faces_np[face]])
        return 1.0 if np.sum(np.einsum("ij,ij->i", n, x - closest)) >= 0.0 else -1.0

    def carry_forces(self, positions, coarse_force, force):
        """Launch eqs. 4-5: the coarse particles' forces carried to every detail sample (force), along
        the grid lines of the detail positions; the three stages of kernels.carry_forces."""
        n, nt = self.tessellation, len(self.surface.topology.coarse_triangles)
        for stage, lines in ((0, 3), (1, n - 2), (2, n - 2)):
            if lines > 0:
                wp.launch(kernels.carry_forces, (nt, lines),
                          [self.face_grid, self.owner_face, n, positions, self.corner_vertex, coarse_force, stage,
                           self.line_shares, self.edge_forces, force], device=self.device)

    def _wrinkles(self, cm, st, base, dt):
        from warp_kernels import cloth as cloth_kernels

        p, dev, nv, n = self.params, self.device, self.surface.topology.num_vertices, self.tessellation
        nt = len(self.surface.topology.coarse_triangles)
        wp.launch(cloth_kernels.elastic_forces, cm.num_particles,
                  [st.x, cm.springs, self.coarse_force], device=dev)
        self.carry_forces(base, self.coarse_force, self.force)
        wp.launch(kernels.vertical_forces, nv, [base, self.nbr_start, self.nbr, self.force, self.vertical], device=dev)
        wp.launch(kernels.edge_length_deficit, self.num_edges, [self.face_grid, self.edge_face, self.edge_side, n, base,
                                                                self.rest_edge, self.edge_deficit], device=dev)
        wp.launch(kernels.vertex_deficit, cm.num_particles, [self.ve_start, self.ve_edge, self.edge_deficit,
                                                             self.coarse_deficit], device=dev)
        wp.launch(kernels.faces_without_compression, nt, [self.face_edges, self.edge_deficit, self.uncompressed],
                  device=dev)
        wp.launch(kernels.wrinkle_heights, nv, [self.owner_face, self.bary, self.corner_vertex, self.coarse_deficit,
                                                self.nbr_start, self.nbr, self.vertical, self.height, p.k_out_plane,
                                                dt, dt * p.reference_fps, self.change], device=dev)
        wp.launch(kernels.add_heights, nv, [self.height, self.change], device=dev)
        # a pass halfway to the neighbours' mean in a reference frame, that share of it in a shorter update (and
        # halfway still in a longer one: further would overshoot toward a checkerboard)
        weight = 0.5 * min(dt * p.reference_fps, 1.0)
        for _ in range(p.smoothing):
            wp.launch(kernels.smooth_heights, nv, [self.nbr_start, self.nbr, self.height, weight, self.height_tmp],
                      device=dev)
            self.height, self.height_tmp = self.height_tmp, self.height
        for _ in range(SLOPE_PASSES):
            wp.launch(kernels.constrain_heights, nv, [base, self.nbr_start, self.nbr, self.owner_face, self.kind,
                                                      self.coarse_edge, self.edge_deficit, self.uncompressed,
                                                      p.max_slope, self.height, self.height_tmp], device=dev)
            self.height, self.height_tmp = self.height_tmp, self.height

    def query_counts(self):
        """(samples tested, BVH queries among them) in the last update, summed over the parts."""
        counts = self.queries.numpy()
        return int(counts[0::2].sum()), int(counts[1::2].sum())

    def query_fraction(self):
        """Share of detail vertices the hierarchical penetration test tested in the last update."""
        return self.query_counts()[0] / max(1, self.surface.topology.num_vertices)

    def bvh_fraction(self):
        """Share of the last update's tested detail vertices that the body's BVH decided (the rest
        walked over its vertices)."""
        tested, bvh = self.query_counts()
        return bvh / max(1, tested)
