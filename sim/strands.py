"""Strand model: static hair data (rest shape, topology, bindings) and per-step state.

Strands are flattened: particle arrays hold every strand back to back and `strand_start` (length
S + 1) gives the offsets, so one kernel launch covers the whole groom. The first `pinned_per_strand`
particles of each strand are bound to collider triangles and follow the collider exactly: one pins
the root, two also pin the root direction as a real follicle does.
"""

from dataclasses import dataclass

import numpy as np
import warp as wp

from warp_kernels import collision, skinning


@dataclass
class HairState:
    """What changes during a run: particle positions [m] and velocities [m/s]."""

    x: wp.array
    v: wp.array


class HairModel:
    """What does not change during a run. Build with StrandBuilder.finalize()."""

    def __init__(self, rest_positions, counts, widths, pinned_per_strand, device, wax=None):
        """wax: per-particle weight in [0, 1] with which the root hold also keeps a waxed strand's
        styled shape (sim.haircut.wax); none by default."""
        rest = np.asarray(rest_positions, dtype=np.float64)
        counts = np.asarray(counts, dtype=np.int64)
        self.device = device
        self.num_strands = len(counts)
        self.num_particles = len(rest)
        self.pinned_per_strand = int(pinned_per_strand)
        if self.pinned_per_strand < 1:
            # follow_the_leader puts each particle at rest length from its parent: a root has none
            raise ValueError(f"pinned_per_strand must be at least 1 (each strand's root is bound), "
                             f"got {pinned_per_strand}")
        self.counts = counts
        self.strand_start_np = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
        self.rest_positions_np = rest.astype(np.float32)
        self.widths_np = np.asarray(widths, dtype=np.float32)
        self.wax_np = np.zeros(self.num_particles, np.float32) if wax is None else np.asarray(wax, np.float32)
        # which strand of the groom each one is: a haircut that removes or reorders strands carries them
        # (sim.haircut.apply), so a cache can name a strand across a change of topology
        self.strand_ids = np.arange(self.num_strands, dtype=np.int32)

        start = self.strand_start_np[:-1]
        local = np.arange(self.num_particles) - np.repeat(start, counts)
        self.particle_strand_np = np.repeat(np.arange(self.num_strands), counts).astype(np.int32)
        is_root = local == 0

        seg = np.zeros(self.num_particles)
        seg[~is_root] = np.linalg.norm(rest[~is_root] - rest[np.flatnonzero(~is_root) - 1], axis=1)
        self.rest_length_np = seg.astype(np.float32)
        self.natural_length_np = np.add.reduceat(seg, start) if self.num_strands else np.zeros(0)
        inv_mass = np.ones(self.num_particles, dtype=np.float32)
        inv_mass[local < self.pinned_per_strand] = 0.0
        self.inv_mass_np = inv_mass

        self._local = local
        self._windows = {}

        def arr(values, dtype):
            return wp.array(values, dtype=dtype, device=device)

        self.rest_positions = arr(self.rest_positions_np, wp.vec3)
        self.strand_start = arr(self.strand_start_np, wp.int32)
        self.particle_strand = arr(self.particle_strand_np, wp.int32)
        self.rest_length = arr(self.rest_length_np, float)
        self.inv_mass = arr(self.inv_mass_np, float)
        self.bind_particle = None  # set by bind_to_mesh
        self.anchor_face = -1  # a root triangle near the middle of the roots (bind_to_mesh)
        self.anchor_center_np = np.zeros(3, np.float32)  # its centroid in the bind pose

    def shape_windows(self, size):
        """Shape-matching windows of `size` consecutive particles (cached per size)."""
        if size not in self._windows:
            self._windows[size] = ShapeWindows(self, size)
        return self._windows[size]

    def state(self):
        return HairState(
            x=wp.array(self.rest_positions_np, dtype=wp.vec3, device=self.device),
            v=wp.zeros(self.num_particles, dtype=wp.vec3, device=self.device),
        )

    def bind_to_mesh(self, mesh_points, mesh_indices, triangles=None, barycentric=None):
        """Bind the pinned particles of every strand to the triangle closest to the strand root.

        mesh_points/mesh_indices are the collider in the pose the rest shape was groomed on.
        triangles (S,) and barycentric (S, 3): each root's triangle and weights, given instead of
        searched (a rebuilt groom keeps its strands' bindings: sim.haircut).
        """
        device = self.device
        pts = wp.array(np.asarray(mesh_points, np.float32), dtype=wp.vec3, device=device)
        idx = wp.array(np.asarray(mesh_indices, np.int32).reshape(-1), dtype=wp.int32, device=device)
        roots = self.rest_positions_np[self.strand_start_np[:-1]]
        if triangles is None:
            mesh = wp.Mesh(points=pts, indices=idx)
            face = wp.zeros(self.num_strands, dtype=wp.int32, device=device)
            bary = wp.zeros(self.num_strands, dtype=wp.vec3, device=device)
            wp.launch(collision.mesh_closest_face, self.num_strands,
                      [wp.array(roots, dtype=wp.vec3, device=device), mesh.id, 1.0e6, face, bary],
                      device=device)
            triangles, barycentric = face.numpy(), bary.numpy()
        self.root_triangle_np = np.asarray(triangles, np.int32).reshape(self.num_strands)
        self.root_barycentric_np = np.asarray(barycentric, np.float32).reshape(self.num_strands, 3)
        k = self.pinned_per_strand
        particle = (self.strand_start_np[:-1, None] + np.arange(k)[None, :]).reshape(-1).astype(np.int32)
        tri = np.repeat(self.root_triangle_np, k).astype(np.int32)
        bw = np.repeat(self.root_barycentric_np, k, axis=0)
        self.bind_particle = wp.array(particle, dtype=wp.int32, device=device)
        binding = np.full(self.num_particles, -1, np.int32)
        binding[particle] = np.arange(len(particle), dtype=np.int32)
        self.particle_binding = wp.array(binding, dtype=wp.int32, device=device)  # binding index or -1
        self.bind_triangle = wp.array(tri, dtype=wp.int32, device=device)
        self.bind_barycentric = wp.array(bw, dtype=wp.vec3, device=device)
        self.bind_local = wp.zeros(len(particle), dtype=wp.vec3, device=device)
        wp.launch(skinning.compute_bindings, len(particle),
                  [pts, idx, self.bind_triangle, self.bind_barycentric,
                   wp.array(self.rest_positions_np[particle], dtype=wp.vec3, device=device),
                   self.bind_local], device=device)
        # every particle's rest offset from its root in the root triangle's frame (root hold)
        self.root_binding = wp.array(np.arange(self.num_strands, dtype=np.int32) * k, dtype=wp.int32, device=device)
        frames = triangle_frames(np.asarray(mesh_points, np.float64)[np.asarray(mesh_indices).reshape(-1, 3)[self.root_triangle_np]])
        offsets = self.rest_positions_np - np.repeat(roots, self.counts, axis=0)
        local = np.einsum("pji,pj->pi", np.repeat(frames, self.counts, axis=0), offsets)
        self.root_local = wp.array(local.astype(np.float32), dtype=wp.vec3, device=device)
        # the root triangle nearest the roots' middle: the hair's contact bounds are kept in the
        # frame it moves with (strands.contact_motion)
        if self.num_strands:
            tri = np.asarray(mesh_indices).reshape(-1, 3)[self.root_triangle_np]
            centroids = np.asarray(mesh_points, np.float64)[tri].mean(1)
            nearest = int(np.argmin(np.linalg.norm(centroids - roots.mean(0), axis=1)))
            self.anchor_face = int(self.root_triangle_np[nearest])
            self.anchor_center_np = centroids[nearest].astype(np.float32)
        return self

    def reach(self, first_strand, strands):
        """How far [m] from the anchor triangle's centroid the particles of `strands` strands from
        `first_strand` can be: each root's distance from it in the bind pose plus its strand's length
        (the length pass keeps every segment at its rest length), with room for the skin around the
        roots to stretch a little. Infinite for an unbound model."""
        if self.anchor_face < 0 or strands == 0:
            return float("inf")
        s = slice(first_strand, first_strand + strands)
        roots = self.rest_positions_np[self.strand_start_np[:-1][s]].astype(np.float64)
        far = np.linalg.norm(roots - self.anchor_center_np, axis=1) + self.natural_length_np[s]
        return float(1.05 * far.max() + 0.005)

    def root_hold_weights(self, length):
        """Per-particle weight of the root hold: 1 at the root, falling linearly to 0 at `length` [m],
        and never below the particle's wax weight."""
        if length <= 0.0:
            return self.wax_np.copy()
        arc = np.cumsum(self.rest_length_np.astype(np.float64))
        arc -= np.repeat(arc[self.strand_start_np[:-1]], self.counts)
        return np.maximum(np.clip(1.0 - arc / length, 0.0, 1.0).astype(np.float32), self.wax_np)


def triangle_frames(tri):
    """(T, 3, 3) frames with columns edge tangent, bitangent, normal (as skinning.triangle_frame)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t = (b - a) / np.linalg.norm(b - a, axis=1, keepdims=True)
    return np.stack([t, np.cross(n, t), n], axis=2)


class ShapeWindows:
    """Every run of `size` consecutive particles inside a strand, with its rest data.

    rest_local (per particle) and rest_centroid (per window): rest positions X and the windows' rest
    centroids C0 from the strand's root, what the full variant's windows are solved and applied with
    (warp_kernels.strands.window_rotation, window_frame).
    offsets: d_k = r_k . U0 with r_k = X_k - C0, the offsets along the rest first-to-last direction
    (simplified).
    rest_np: the offsets r_k themselves, on the host (a reference for tests).
    """

    def __init__(self, model, size):
        if size < 2:
            raise ValueError("shape-matching windows need at least 2 particles")
        rest = model.rest_positions_np.astype(np.float64)
        counts = np.repeat(model.counts, model.counts)
        first = np.flatnonzero(model._local + size <= counts).astype(np.int32)
        at = np.full(model.num_particles, -1, dtype=np.int32)
        at[first] = np.arange(len(first), dtype=np.int32)
        pts = rest[first[:, None] + np.arange(size)[None, :]]  # (W, size, 3)
        r = pts - pts.mean(axis=1, keepdims=True)
        u = pts[:, -1] - pts[:, 0]
        u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
        self.size = size
        self.count = len(first)
        self.first_np, self.at_np = first, at
        self.rest_np = r.reshape(-1, 3).astype(np.float32)
        self.offsets_np = np.einsum("wkj,wj->wk", r, u).reshape(-1).astype(np.float32)
        root = rest[model.strand_start_np[model.particle_strand_np]]
        self.rest_local_np = (rest - root).astype(np.float32)
        self.rest_centroid_np = (pts.mean(axis=1) - root[first]).astype(np.float32)
        d = model.device
        self.first = wp.array(first, dtype=wp.int32, device=d)
        self.at = wp.array(at, dtype=wp.int32, device=d)
        self.offsets = wp.array(self.offsets_np, dtype=float, device=d)
        self.rest_local = wp.array(self.rest_local_np, dtype=wp.vec3, device=d)
        self.rest_centroid = wp.array(self.rest_centroid_np, dtype=wp.vec3, device=d)


class StrandBuilder:
    """Collects strands (polylines of rest positions) and widths, then finalizes a HairModel."""

    def __init__(self):
        self._points, self._counts, self._widths = [], [], []

    def add_strands(self, points, counts, widths=None):
        """points: (P, 3) flattened polylines [m]; counts: vertices per strand; widths: (P,) [m]."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        counts = np.asarray(counts, dtype=np.int64).reshape(-1)
        if counts.sum() != len(points):
            raise ValueError(f"strand counts sum to {counts.sum()} but {len(points)} points were given")
        if np.any(counts < 2):
            raise ValueError("every strand needs at least 2 vertices")
        if not np.all(np.isfinite(points)):
            raise ValueError("strand points contain NaN or infinity")
        if widths is None:
            widths = np.full(len(points), 1e-4)
        self._points.append(points)
        self._counts.append(counts)
        self._widths.append(np.asarray(widths, dtype=np.float64).reshape(-1))
        return self

    def add_strand(self, points, widths=None):
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return self.add_strands(points, [len(points)], widths)

    def finalize(self, device="cpu", pinned_per_strand=2):
        if not self._points:
            raise ValueError("no strands were added")
        counts = np.concatenate(self._counts)
        if np.any(counts <= pinned_per_strand):
            raise ValueError(f"every strand needs more than {pinned_per_strand} vertices "
                             f"when {pinned_per_strand} are pinned")
        return HairModel(np.concatenate(self._points), counts, np.concatenate(self._widths),
                         pinned_per_strand, device)
