"""Garments for the cloth solver: quad meshes loaded from OBJ / USD or fitted around a body at rest.

Oshita & Makinouchi drape a one-piece dress of about 322 particles over a walking body, with springs
on polygon edges, shear springs on quad diagonals and bending springs between vertices two edges
apart (§3), so garments here keep their quads and say which vertex pairs those springs join.

Fitted garments are tubes: rows along the height, columns around the body, closed around and open at
top and bottom. A row follows the convex outline of the torso's horizontal cross-section (loops that
do not enclose the torso axis, the A-posed arms, are left out; below the crotch the legs stand in),
grown by `ease`. Below the waist the outline hangs straight down from the widest part above it and
below the hips it widens into an A-line cone. Straps are quad strips from the front of the top row
over the shoulders to its back. Columns sit at equal arc length around each row, column 0 at the
front centre and column C/4 on the body's left (+X); rows are spaced so quads come out near square.
Every vertex ends `ease` outside the body and every quad at least ease / 4 outside it (coarse quads
could otherwise cut through a curve between corners that clear it).
"""

import os
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial import ConvexHull, QhullError, cKDTree

from .asset_cache import cached_arrays
from .errors import InputError
from .mesh_topology import unique_pairs
from .sphere_tree import signed_distance, warp_mesh

DEGENERATE_EDGE = 1e-9  # m, an edge shorter than this is treated as zero length
USD_EXTENSIONS = (".usd", ".usda", ".usdc", ".usdz")


@dataclass
class GarmentMesh:
    """A garment's rest shape: polygons as USD faceVertexCounts / faceVertexIndices (3 or 4 corners)."""

    name: str
    vertices: np.ndarray  # (N, 3) float64, metres
    face_counts: np.ndarray  # (F,) int64, 3 or 4
    face_indices: np.ndarray  # (sum(face_counts),) int64
    pinned: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # vertices bound to the body
    thickness: float = 0.0  # m, how far outside the body it was fitted (0 when unknown)

    def __post_init__(self):
        self.vertices = np.asarray(self.vertices, np.float64).reshape(-1, 3)
        self.face_counts = np.asarray(self.face_counts, np.int64).reshape(-1)
        self.face_indices = np.asarray(self.face_indices, np.int64).reshape(-1)
        self.pinned = np.asarray(self.pinned, np.int64).reshape(-1)

    def _corners(self):
        """Per face corner: its vertex, the next one, the one before and the one after next."""
        counts = self.face_counts
        n = np.repeat(counts, counts)
        base = np.repeat(np.cumsum(counts) - counts, counts)
        k = np.arange(len(self.face_indices)) - base
        at = lambda step: self.face_indices[base + (k + step) % n]  # noqa: E731
        return at(0), at(1), at(-1), at(2)

    def quads(self):
        """(Q, 4) corners of the four-sided faces, in face order."""
        starts = (np.cumsum(self.face_counts) - self.face_counts)[self.face_counts == 4]
        return self.face_indices[starts[:, None] + np.arange(4)]

    def triangles(self):
        """(T, 3): triangles as they are, quads split along their first diagonal (corners 0-2)."""
        from io_usd.cache import fan_triangles

        return fan_triangles(self.face_counts, self.face_indices)

    def edges(self):
        """(E, 2) unique undirected polygon edges, each sorted (i < j)."""
        a, b, _, _ = self._corners()
        return unique_pairs(np.sort(np.stack([a, b], 1), 1))

    def quad_diagonals(self):
        """(2Q, 2) both diagonals of every quad (0-2 then 1-3), each sorted, for shear springs."""
        q = self.quads()
        return np.sort(np.stack([q[:, [0, 2]], q[:, [1, 3]]], 1).reshape(-1, 2), 1)

    def bending_pairs(self):
        """(B, 2) unique sorted vertex pairs two edges apart across an edge, for bending springs.

        Rule: for every edge (a, b) shared by exactly two faces, each face contributes its far corner
        next to a and its far corner next to b (a triangle has one far corner for both); the pairs
        join the two faces' corners next to a, and next to b. On a quad grid that pairs each vertex
        with the one two steps along its row and along its column (i, i + 2), on triangles the two
        corners opposite the shared edge, and across a triangle-quad edge the triangle's apex with
        both of the quad's far corners. Pairs that are already edges, or a vertex with itself, are
        left out.
        """
        a, b, before_a, after_b = self._corners()
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        far_lo = np.where(a < b, before_a, after_b)
        far_hi = np.where(a < b, after_b, before_a)
        _, group, count = np.unique(lo * len(self.vertices) + hi, return_inverse=True, return_counts=True)
        order = np.argsort(group.reshape(-1), kind="stable")
        first = (np.cumsum(count) - count)[count == 2]
        h1, h2 = order[first], order[first + 1]
        pairs = np.concatenate([np.stack([far_lo[h1], far_lo[h2]], 1), np.stack([far_hi[h1], far_hi[h2]], 1)])
        pairs = unique_pairs(np.sort(pairs, 1))
        pairs = pairs[pairs[:, 0] != pairs[:, 1]]
        n = len(self.vertices)
        edge_codes = self.edges() @ np.array([n, 1])
        return pairs[~np.isin(pairs @ np.array([n, 1]), edge_codes)]


# -- loading ------------------------------------------------------------------------------------------
def garment_from_file(path, pinned=None, name=None):
    """A garment from a mesh file. OBJ is read here so quads stay quads (trimesh would triangulate);
    USD goes to garment_from_usd (its first Mesh prim); other formats load through trimesh."""
    path = str(path)
    if not os.path.isfile(path):
        raise InputError(path, None, "file not found")
    ext = os.path.splitext(path)[1].lower()
    name = name or os.path.splitext(os.path.basename(path))[0]
    if ext in USD_EXTENSIONS:
        return garment_from_usd(path, None, pinned=pinned, name=name)
    if ext == ".obj":
        vertices, counts, indices = _read_obj(path)
    else:
        import trimesh

        try:
            mesh = trimesh.load(path, force="mesh", process=False)
        except Exception as err:  # trimesh raises many types for unreadable files
            raise InputError(path, None, f"cannot read: {err}") from None
        faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), np.int64).reshape(-1, 3)
        vertices, counts, indices = np.asarray(mesh.vertices), np.full(len(faces), 3), faces.reshape(-1)
    return checked_garment(path, None, name, vertices, counts, indices, pinned)


def garment_from_usd(path_or_stage, prim_path=None, pinned=None, name=None):
    """A garment from the UsdGeom.Mesh at prim_path (None or "": the stage's first Mesh): points at
    the earliest time, in world space, scaled to metres where the stage authors metersPerUnit."""
    from pxr import Usd, UsdGeom

    if isinstance(path_or_stage, Usd.Stage):
        stage, source = path_or_stage, path_or_stage.GetRootLayer().identifier
    else:
        from io_usd.cache import open_stage

        source = str(path_or_stage)
        stage = open_stage(source, key=prim_path)
    if not prim_path:
        prim = next((p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)), None)
        if prim is None:
            raise InputError(source, None, "no UsdGeom.Mesh prim on the stage")
    else:
        prim = stage.GetPrimAtPath(str(prim_path))
        if not prim.IsValid():
            raise InputError(source, prim_path, "no such prim")
        if not prim.IsA(UsdGeom.Mesh):
            raise InputError(source, prim_path, f"is a {prim.GetTypeName() or 'typeless prim'}, not a Mesh")
    key = str(prim.GetPath())
    mesh, time = UsdGeom.Mesh(prim), Usd.TimeCode.EarliestTime()
    points, counts, indices = (a.Get(time) for a in (mesh.GetPointsAttr(), mesh.GetFaceVertexCountsAttr(),
                                                     mesh.GetFaceVertexIndicesAttr()))
    if points is None or counts is None or indices is None:
        raise InputError(source, key, "points, faceVertexCounts or faceVertexIndices not authored")
    points = np.asarray(points, np.float64).reshape(-1, 3)
    xform = np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(time), np.float64)
    if not np.allclose(xform, np.eye(4)):
        points = points @ xform[:3, :3] + xform[3, :3]  # USD matrices act on row vectors
    if UsdGeom.StageHasAuthoredMetersPerUnit(stage):
        points = points * UsdGeom.GetStageMetersPerUnit(stage)
    return checked_garment(source, key, name or prim.GetName(), points, np.asarray(counts), np.asarray(indices),
                           pinned)


def _read_obj(path):
    """Vertices and polygons (sizes kept) of an OBJ's 'v' and 'f' lines; other lines are ignored."""
    vertices, counts, indices = [], [], []
    with open(path, encoding="utf-8", errors="replace") as f:
        for number, line in enumerate(f, 1):
            words = line.split()
            if not words or words[0] not in ("v", "f"):
                continue
            try:
                if words[0] == "v":
                    vertices.append([float(w) for w in words[1:4]])
                    if len(vertices[-1]) != 3:
                        raise ValueError("a vertex needs three coordinates")
                else:
                    corners = [int(w.split("/")[0]) for w in words[1:]]
                    counts.append(len(corners))
                    indices.extend(c - 1 if c > 0 else len(vertices) + c for c in corners)
            except ValueError as err:
                raise InputError(path, f"line {number}", f"cannot parse {words[0]!r}: {err}") from None
    return np.asarray(vertices, np.float64).reshape(-1, 3), np.asarray(counts, np.int64), np.asarray(indices, np.int64)


def checked_garment(source, prim, name, vertices, counts, indices, pinned=None, thickness=0.0):
    """A GarmentMesh from raw arrays, or InputError(source, prim, reason) for what the solver cannot take."""
    vertices = np.asarray(vertices, np.float64)
    counts, indices = np.asarray(counts, np.int64).reshape(-1), np.asarray(indices, np.int64).reshape(-1)
    fail = lambda reason: InputError(source, prim, reason)  # noqa: E731
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0:
        raise fail(f"expected (N, 3) vertices, got shape {vertices.shape}")
    if len(counts) == 0:
        raise fail("no faces")
    if not np.all(np.isfinite(vertices)):
        raise fail(f"{int((~np.isfinite(vertices)).any(1).sum())} vertices are NaN or infinite")
    if counts.min() < 3 or counts.max() > 4:
        bad = int(np.flatnonzero((counts < 3) | (counts > 4))[0])
        raise fail(f"face {bad} has {counts[bad]} corners; garments take triangles and quads only")
    if counts.sum() != len(indices):
        raise fail(f"faceVertexCounts sum to {counts.sum()} but there are {len(indices)} face vertex indices")
    if indices.min() < 0 or indices.max() >= len(vertices):
        raise fail(f"face vertex indices must lie in [0, {len(vertices)})")
    garment = GarmentMesh(name, vertices, counts, indices, np.zeros(0, np.int64), float(thickness))
    a, b, _, _ = garment._corners()
    length = np.linalg.norm(vertices[a] - vertices[b], axis=1)
    if length.min() < DEGENERATE_EDGE:
        k = int(np.argmin(length))
        raise fail(f"zero-length edge between vertices {a[k]} and {b[k]}")
    if pinned is not None:
        pinned = np.unique(np.asarray(pinned, np.int64).reshape(-1))
        if len(pinned) and (pinned.min() < 0 or pinned.max() >= len(vertices)):
            raise fail(f"pinned vertex indices must lie in [0, {len(vertices)})")
        garment.pinned = pinned
    return garment


# -- fitting around a body ----------------------------------------------------------------------------
def _hull(points):
    """Counter-clockwise (in x, z) convex hull corners of 2D points."""
    points = np.asarray(points, np.float64).reshape(-1, 2)
    return points[ConvexHull(points).vertices]


def _grow(outline, distance, directions=32):
    """Convex outline grown by `distance` (Minkowski sum with a 32-gon, which lies inside the disc by
    at most 0.5%)."""
    if distance <= 0.0:
        return outline
    a = np.linspace(0.0, 2.0 * np.pi, directions, endpoint=False)
    disc = distance * np.stack([np.cos(a), np.sin(a)], 1)
    return _hull(outline[:, None, :] + disc[None])


def _perimeter(outline):
    return float(np.linalg.norm(outline - np.roll(outline, 1, 0), axis=1).sum())


def _ring(outline, columns, axis):
    """`columns` points at equal arc length around a convex outline, the first where the outline
    crosses the front (+Z) of `axis`, then turning toward +X."""
    loop = outline[::-1]  # counter-clockwise in (x, z) runs +X -> +Z; we want +Z -> +X
    nxt = np.roll(loop, -1, 0)
    dx = nxt[:, 0] - loop[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (axis[0] - loop[:, 0]) / dx
    z = loop[:, 1] + t * (nxt[:, 1] - loop[:, 1])
    crossing = np.flatnonzero((t >= 0.0) & (t < 1.0) & (z > axis[1]))
    if len(crossing) == 0:
        raise ValueError(f"the garment outline does not enclose the torso axis (x, z) = {axis.round(3)}")
    k = int(crossing[0])
    seg = np.linalg.norm(nxt - loop, axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    total = s[-1]
    start = s[k] + t[k] * seg[k]
    target = (start + total * np.arange(columns) / columns) % total
    closed = np.vstack([loop, loop[:1]])
    return np.stack([np.interp(target, s, closed[:, 0]), np.interp(target, s, closed[:, 1])], 1)


def _offset_surface(points, mesh, distance, both_ways=False):
    """Points moved along the body normal to `distance` outside the surface: only those closer
    than that (or all of them, pulling in too, with both_ways)."""
    sd, closest = signed_distance(points, mesh)
    away = points - closest
    norm = np.linalg.norm(away, axis=1, keepdims=True)
    normal = np.where(norm > 1e-9, away / np.maximum(norm, 1e-12), 0.0) * np.sign(sd)[:, None]
    move = (sd < distance) if not both_ways else np.ones(len(points), bool)
    move &= norm[:, 0] > 1e-9
    out = points.copy()
    out[move] = closest[move] + distance * normal[move]
    return out


class _BodySections:
    """Horizontal cross-sections of a body, split into connected loops, as convex outlines in (x, z)."""

    def __init__(self, body):
        import trimesh

        self.landmarks = body.landmarks
        self.mesh = trimesh.Trimesh(np.asarray(body.vertices, np.float64), np.asarray(body.faces, np.int64),
                                    process=False)
        self.wp_mesh = warp_mesh(self.mesh.vertices, self.mesh.faces)
        # each face's height range: a section intersects only the faces spanning its height
        heights = self.mesh.vertices[self.mesh.faces, 1]
        self._face_low, self._face_high = heights.min(axis=1), heights.max(axis=1)
        self._cache = {}
        lm = self.landmarks
        cx = 0.5 * (float(lm["shoulder_l"][0]) + float(lm["shoulder_r"][0]))
        waist = self.loops(float(lm["waist_y"]))
        if not waist:
            raise ValueError(f"the body has no cross-section at waist_y = {lm['waist_y']:.3f}")
        centre = min((loop.mean(0) for loop in waist), key=lambda c: abs(c[0] - cx))
        self.axis = np.array([cx, centre[1]])  # (x, z) of the vertical torso axis
        self.reach = np.inf  # not needed yet: the hips' loop encloses the axis
        hips = self.torso(float(lm["hip_y"]))
        self.reach = float(np.abs(hips[:, 0] - cx).max())  # legs lie within the hips' half-width

    def loops(self, y):
        """Points (n, 2) of each connected loop of the section at height y."""
        import trimesh

        # the faces within a micrometre of the plane: the rest lie wholly on one side and give no line
        spanning = np.flatnonzero((self._face_low <= y + 1e-6) & (self._face_high >= y - 1e-6))
        if len(spanning) == 0:
            return []
        lines = trimesh.intersections.mesh_plane(self.mesh, [0.0, 1.0, 0.0], [0.0, y, 0.0],
                                                 local_faces=spanning)[:, :, [0, 2]]
        if len(lines) == 0:
            return []
        # segments whose ends meet form a loop; matching ends by position (not by face adjacency)
        # also joins segments through mesh vertices that lie exactly on the plane
        ends = lines.reshape(-1, 2)
        n = len(ends)
        touching = cKDTree(ends).query_pairs(1e-7, output_type="ndarray")
        links = np.concatenate([np.arange(n).reshape(-1, 2), touching])
        graph = scipy.sparse.coo_matrix((np.ones(len(links)), (links[:, 0], links[:, 1])), shape=(n, n))
        count, label = connected_components(graph, directed=False)
        return [ends[label == k] for k in range(count)]

    def split(self, y):
        """(torso outline or None, other loops' points) at height y. The torso is every loop whose hull
        encloses the axis; where none does (below the crotch), the loops centred within the hips'
        half-width of it (the legs)."""
        key = round(float(y), 5)
        if key not in self._cache:
            hulls = []
            for points in self.loops(y):
                try:
                    hulls.append(_hull(points))
                except QhullError:  # a sliver loop with fewer than 3 distinct points
                    continue
            inside = [np.all(_edge_side(h, self.axis) >= -1e-9) for h in hulls]
            if not any(inside):
                inside = [abs(h.mean(0)[0] - self.axis[0]) < self.reach for h in hulls]
            torso = [h for h, keep in zip(hulls, inside) if keep]
            others = [h for h, keep in zip(hulls, inside) if not keep]
            self._cache[key] = (_hull(np.concatenate(torso)) if torso else None, others)
        return self._cache[key]

    def torso(self, y):
        outline, _ = self.split(y)
        if outline is None:
            raise ValueError(f"the body has no torso cross-section at y = {y:.3f}")
        return outline

    def neck_half_width(self):
        """Half-width of the neck 4 cm above the shoulder landmarks."""
        lm = self.landmarks
        torso = self.torso(0.5 * (float(lm["shoulder_l"][1]) + float(lm["shoulder_r"][1])) + 0.04)
        return float(np.abs(torso[:, 0] - self.axis[0]).max())

    def armpit_y(self, step=0.005, gap=0.01, widening=1.15):
        """Lowest height above chest_y where an arm loop comes within `gap` of the torso outline, or
        the torso outline suddenly widens (the arm merged into it)."""
        lm = self.landmarks
        top = min(float(lm["shoulder_l"][1]), float(lm["shoulder_r"][1]))
        half_width = lambda o: np.abs(o[:, 0] - self.axis[0]).max()  # noqa: E731
        chest = half_width(self.torso(float(lm["chest_y"])))
        for y in np.arange(float(lm["chest_y"]), top, step):
            torso, others = self.split(y)
            if torso is None or half_width(torso) > widening * chest:
                return y
            for loop in others:
                if np.min(np.linalg.norm(loop[:, None] - torso[None], axis=2)) < gap or \
                        np.all(_edge_side(torso, loop.mean(0)) >= 0.0):
                    return y
        return top


def _edge_side(outline, point):
    """Per edge of a counter-clockwise outline: > 0 where `point` lies on its inner side."""
    nxt = np.roll(outline, -1, 0)
    e, r = nxt - outline, point - outline
    return e[:, 0] * r[:, 1] - e[:, 1] * r[:, 0]


@dataclass(frozen=True)
class _TubeShape:
    """Outline of a fitted tube at any height: the torso section, hanging straight down below
    `drape_from` (each outline is the hull of every section from there down), widening below `flare_from`
    by tan(flare) per metre, grown by `ease`."""

    sections: _BodySections
    ease: float
    drape_from: float
    flare_from: float
    flare: float  # radians
    step: float = 0.01  # m, spacing of the sections the drape gathers

    def outline(self, y):
        torso = self.sections.torso(y)
        if y < self.drape_from:
            above = np.arange(self.drape_from, y, -self.step)
            torso = _hull(np.concatenate([torso] + [self.sections.torso(h) for h in above]))
        widen = max(0.0, self.flare_from - y) * np.tan(self.flare)
        return _grow(torso, widen + self.ease)


def _row_profile(shape, y_top, y_bottom, samples=41):
    """Heights from y_top down to y_bottom and v(y) = integral dy / perimeter(y) from the top: rows at
    equal steps of columns * v are spaced like the columns at each height, so quads come out square."""
    y = np.linspace(y_top, y_bottom, samples)
    inv = np.array([1.0 / _perimeter(shape.outline(h)) for h in y])
    return y, np.concatenate([[0.0], np.cumsum(0.5 * (inv[1:] + inv[:-1]) * np.abs(np.diff(y)))])


def _rows(profile, count):
    """`count` row heights at equal steps of v."""
    y, v = profile
    return np.interp(np.linspace(0.0, v[-1], count), v, y)


def _tube(shape, rows_y, columns):
    """(R, C, 3) ring vertices, pushed out wherever the planar rings come closer than `ease` to the body."""
    rings = []
    for y in rows_y:
        xz = _ring(shape.outline(y), columns, shape.sections.axis)
        rings.append(np.stack([xz[:, 0], np.full(columns, y), xz[:, 1]], 1))
    points = np.concatenate(rings)
    for _ in range(3):
        points = _offset_surface(points, shape.sections.wp_mesh, shape.ease)
    return points.reshape(len(rows_y), columns, 3)


def _strap_layout(sections, top_ring, shoulder, width, spacing, ease, mirror):
    """Where a strap `width` quads wide over one shoulder meets the top ring (its rails' front and back
    columns), its rails as straight polylines front -> shoulder -> back (rails, 3, 3), and how many
    vertices each rail gets between its ends (about one per `spacing`)."""
    columns = len(top_ring)
    index = (-np.arange(columns)) % columns if mirror else np.arange(columns)  # mirror: walk toward -X
    x = np.abs(top_ring[index, 0] - sections.axis[0])
    sx = abs(float(shoulder[0]) - sections.axis[0])
    clear = sections.neck_half_width() + 0.02 + ease
    offsets = np.arange(width + 1)
    # centred on the shoulder landmark, moved outward where the inner rail would climb the neck, and
    # leaving at least one quad of the top rim under each arm between the front and back ends
    cost = lambda cols: abs(x[cols].mean() - sx) + 10.0 * max(0.0, clear - x[cols].min())  # noqa: E731
    front = min([j for j in range(1, columns) if j + width < columns / 4], key=lambda j: cost(j + offsets))
    back = min([j for j in range(columns // 2) if j - width > columns / 4], key=lambda j: cost(j - offsets))
    front_cols, back_cols = index[front + offsets], index[back - offsets]
    ends_f, ends_b = top_ring[front_cols], top_ring[back_cols]
    apex = np.stack([0.5 * (ends_f[:, 0] + ends_b[:, 0]), np.full(width + 1, float(shoulder[1]) + ease),
                     np.full(width + 1, float(shoulder[2]))], 1)
    paths = np.stack([ends_f, apex, ends_b], 1)
    length = np.linalg.norm(np.diff(paths, axis=1), axis=2).sum(1).mean()
    return front_cols, back_cols, paths, max(1, int(round(length / spacing)) - 1)


def _strap_rails(sections, paths, inner, ease):
    """(rails, inner, 3) strap vertices: each rail's polyline resampled evenly and laid onto the
    surface `ease` outside the body, staying in the upright plane through its two ends (so the rails
    keep their spacing where the shoulder slopes under them)."""
    ends_f, ends_b = paths[:, 0], paths[:, -1]
    across = np.cross(ends_b - ends_f, [0.0, 1.0, 0.0])
    across /= np.linalg.norm(across, axis=1, keepdims=True)

    def onto_surface(p, both_ways):
        p = _offset_surface(p.reshape(-1, 3), sections.wp_mesh, ease, both_ways).reshape(p.shape)
        if both_ways:
            p -= np.einsum("rkj,rj->rk", p - ends_f[:, None], across)[..., None] * across[:, None]
        return p

    for _ in range(6):
        paths = _resample(paths, inner + 2)
        for _ in range(3):
            paths[:, 1:-1] = onto_surface(paths[:, 1:-1], True)
    paths = _resample(paths, inner + 2)
    return onto_surface(paths[:, 1:-1], False)


def _resample(paths, count):
    """Polylines (P, K, 3) resampled to `count` points each at equal arc length."""
    out = np.empty((len(paths), count, 3))
    for p, path in enumerate(paths):
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
        t = np.linspace(0.0, s[-1], count)
        out[p] = np.stack([np.interp(t, s, path[:, k]) for k in range(3)], 1)
    return out


def _assemble(name, rings, straps, pin_rows, ease):
    """GarmentMesh from (R, C, 3) rings (row 0 on top) and straps (front cols, back cols, (rails, m, 3),
    mirrored). Pinned: the `pin_rows` strap rows nearest each apex, or the top row without straps."""
    rows, columns, _ = rings.shape
    grid = np.arange(rows * columns).reshape(rows, columns)
    nxt = np.roll(grid, -1, 1)
    faces = [np.stack([grid[:-1], grid[1:], nxt[1:], nxt[:-1]], -1).reshape(-1, 4)]
    vertices, pinned, start = [rings.reshape(-1, 3)], [], rows * columns
    for front_cols, back_cols, rails, mirrored in straps:
        inner = rails.shape[1]
        ids = start + np.arange(rails.shape[0] * inner).reshape(rails.shape[0], inner)
        path = np.concatenate([grid[0, front_cols][:, None], ids, grid[0, back_cols][:, None]], 1)  # (rails, m+2)
        a, b, c, d = path[:-1, :-1], path[1:, :-1], path[1:, 1:], path[:-1, 1:]
        # rail r+1 lies outward of rail r; mirroring flips which way round keeps the tube's orientation
        quad = np.stack([a, d, c, b] if mirrored else [a, b, c, d], -1)
        faces.append(quad.transpose(1, 0, 2).reshape(-1, 4))
        top = np.argsort(-rails[:, :, 1].mean(0))[:pin_rows]
        pinned.append(ids[:, top].reshape(-1))
        vertices.append(rails.reshape(-1, 3))
        start += ids.size
    faces = np.concatenate(faces)
    pinned = np.sort(np.concatenate(pinned)) if pinned else grid[0]
    return GarmentMesh(name, np.concatenate(vertices), np.full(len(faces), 4), faces.reshape(-1), pinned,
                       float(ease))


def _clear_faces(garment, mesh, clearance, samples=5, iterations=8):
    """Move quad corners out along the body normal until every bilinear sample of every quad lies
    `clearance` outside the body: coarse quads can cut into the body between corners that clear it."""
    quads = garment.quads()
    w = np.linspace(0.0, 1.0, samples)
    u, v = (a.ravel() for a in np.meshgrid(w, w))
    weights = np.stack([(1 - u) * (1 - v), u * (1 - v), u * v, (1 - u) * v], 1)  # (S, 4) bilinear
    points = garment.vertices.copy()
    for _ in range(iterations):
        at = np.einsum("sc,qcj->qsj", weights, points[quads]).reshape(-1, 3)
        sd, closest = signed_distance(at, mesh)
        bad = np.flatnonzero(sd < clearance)
        if len(bad) == 0:
            break
        normal = (at[bad] - closest[bad]) * np.sign(sd[bad])[:, None]
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
        q, k = np.divmod(bad, len(weights))
        wk = weights[k]
        # the smallest corner moves that carry the sample `clearance - sd` along the normal, averaged
        # over the samples each corner serves
        step = wk[:, :, None] * ((clearance - sd[bad]) / (wk * wk).sum(1))[:, None, None] * normal[:, None, :]
        push, count = np.zeros_like(points), np.zeros(len(points))
        np.add.at(push, quads[q].ravel(), step.reshape(-1, 3))
        np.add.at(count, quads[q].ravel(), (wk > 0).ravel())
        points += push / np.maximum(count, 1.0)[:, None]
    garment.vertices = points
    return garment


def _fit(name, sections, particles, ease, y_top, y_bottom, flare_degrees, strap_width, drape_from, pin_rows=2):
    """A tube from y_top down to y_bottom, plus straps about `strap_width` metres wide (at least one
    quad) when that is > 0, its column count chosen so the vertex count comes closest to `particles`."""
    if not ease > 0.0:
        raise ValueError(f"ease must be a positive distance in metres, got {ease}")
    lm = sections.landmarks
    shape = _TubeShape(sections, float(ease), float(drape_from), float(lm["hip_y"]), np.radians(flare_degrees))
    top = shape.outline(y_top)
    shoulders = (("shoulder_l", False), ("shoulder_r", True)) if strap_width > 0 else ()

    def strap_layouts(ring):
        columns = len(ring)
        spacing = _perimeter(top) / columns
        quads = int(np.clip(round(strap_width / spacing), 1, columns // 4 - 2))
        return [(mirror, *_strap_layout(sections, ring, lm[key], quads, spacing, ease, mirror))
                for key, mirror in shoulders]

    profile, best = _row_profile(shape, y_top, y_bottom), None
    for columns in range(12 if shoulders else 8, 4 * int(np.sqrt(particles)) + 2, 2):  # even: left, right mirror
        xz = _ring(top, columns, sections.axis)
        ring = np.stack([xz[:, 0], np.full(columns, y_top), xz[:, 1]], 1)
        strap = sum(len(front) * inner for _, front, _, _, inner in strap_layouts(ring))
        square = columns * profile[1][-1] + 1.0  # rows for square quads
        for rows in sorted({max(2, int(np.floor(square))), max(2, int(np.ceil(square)))}):
            count = rows * columns + strap
            if best is None or abs(count - particles) < abs(best[0] - particles):
                best = (count, columns, rows)
    _, columns, rows = best
    rings = _tube(shape, _rows(profile, rows), columns)
    straps = [(front, back, _strap_rails(sections, paths, inner, ease), mirror)
              for mirror, front, back, paths, inner in strap_layouts(rings[0])]
    return _clear_faces(_assemble(name, rings, straps, pin_rows, ease), sections.wp_mesh, 0.25 * ease)


def _lerp(a, b, t):
    return float(a) + (float(b) - float(a)) * t


HEMLINES = {  # dress hem height: (from landmark, to landmark, fraction of the way)
    "mini": ("crotch_y", "knee_y", 0.5),
    "knee": ("crotch_y", "knee_y", 0.9),
    "midi": ("knee_y", "ankle_y", 0.4),
}


def fit_dress(body, particles=322, ease=0.012, length="knee", flare_degrees=10.0, strap_width=0.035):
    """A sleeveless one-piece dress: a bodice from 3 cm below the armpits, fitted down to the hips, an
    A-line skirt to `length` ("mini", "knee" or "midi") widening by `flare_degrees`, and a strap over
    each shoulder about `strap_width` metres (at least one quad) wide. About `particles` vertices
    (Oshita & Makinouchi's dress has 322). Pinned: the two strap rows on top of each shoulder."""
    if length not in HEMLINES:
        raise ValueError(f"length must be one of {sorted(HEMLINES)}, got {length!r}")

    def fit():
        sections = _BodySections(body)
        lm = sections.landmarks
        a, b, t = HEMLINES[length]
        return _fit("dress", sections, particles, ease, sections.armpit_y() - 0.03, _lerp(lm[a], lm[b], t),
                    flare_degrees, strap_width, float(lm["waist_y"]))

    return _fitted(body, ("dress", particles, ease, length, flare_degrees, strap_width), fit)


def fit_skirt(body, particles=180, ease=0.012, flare_degrees=14.0):
    """A flared skirt from the waist to above the knee. Pinned: the waistband (top row)."""
    def fit():
        sections = _BodySections(body)
        lm = sections.landmarks
        return _fit("skirt", sections, particles, ease, float(lm["waist_y"]),
                    _lerp(lm["crotch_y"], lm["knee_y"], 0.7), flare_degrees, 0.0, float(lm["waist_y"]))

    return _fitted(body, ("skirt", particles, ease, flare_degrees), fit)


def fit_shirt(body, particles=240, ease=0.012, strap_width=0.09):
    """A sleeveless top (tank top) from 3 cm below the armpits to just below the hips, with shoulder
    panels about `strap_width` metres wide that leave the neck and the arms free. Pinned: the two
    panel rows on top of each shoulder."""
    def fit():
        sections = _BodySections(body)
        lm = sections.landmarks
        return _fit("shirt", sections, particles, ease, sections.armpit_y() - 0.03,
                    _lerp(lm["hip_y"], lm["crotch_y"], 0.25), 3.0, strap_width, float(lm["waist_y"]))

    return _fitted(body, ("shirt", particles, ease, strap_width), fit)


def _fitted(body, settings, fit):
    """fit() through the asset cache: a garment is fitted once per body rest shape, landmarks and settings."""
    def build():
        g = fit()
        return dict(name=np.array(g.name), vertices=g.vertices, face_counts=g.face_counts,
                    face_indices=g.face_indices, pinned=g.pinned, thickness=np.array(g.thickness))

    a = cached_arrays("garment", (settings, np.asarray(body.vertices, np.float64), np.asarray(body.faces, np.int64),
                                  body.landmarks), build)
    return GarmentMesh(str(a["name"]), a["vertices"], a["face_counts"], a["face_indices"], a["pinned"],
                       float(a["thickness"]))


GARMENTS = {"dress": fit_dress, "skirt": fit_skirt, "shirt": fit_shirt}
