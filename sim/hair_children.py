"""Render children: strands grown between the simulated ones and carried by them each frame.

A groom simulated with a few thousand strands shows the scalp between them; production grooms add
many more strands for the picture, each following the simulated strands near it. A child here is
grown by the same hairstyle as the simulated strands, from a root of its own on the scalp, so its
shape (waves, curls, its side of the parting) is its own. Each frame it keeps that shape carried
rigidly with the head, plus the weighted displacements of three simulated strands (choose_parents:
near in root and in shape) from their own groomed shapes carried the same way; displacements are
blended, not shapes, so a child near the parting does not average the strands swept to either side.
Then, root to tip, each vertex is put back at its groomed distance from the one before and kept
outside the head (warp_kernels.strands.interpolate_children). Children are written to the cache
beside the simulated hair (`hair_children`); they take no part in the simulation.
"""

import numpy as np
import warp as wp
from scipy.spatial import cKDTree

from warp_kernels import strands

from .graphs import launch_on_cores
from .strands import triangle_frames

NEIGHBOURS = 3  # simulated strands a child follows (the kernel's vec3i)
# m: how deep the pushes out of the collider look at least, and past the longest segment: a vertex is
# walked from one outside, a segment away, and a mesh query costs more the farther it looks (3k children
# of 24 vertices a frame on one core: 144 ms looking 5 cm, 27 ms looking 1 cm)
SEARCH = 0.01
CANDIDATES = 8  # nearest roots among which a child's parents are the closest in shape


def choose_parents(parents, children):
    """(parents (C, 3) int32, weights (C, 3) float32) for children (C, V, 3) among strands parents
    (S, V, 3), both groomed shapes: of the CANDIDATES strands whose roots are nearest a child's
    root, the NEIGHBOURS nearest in root distance plus shape (the mean distance between their
    vertices with the roots put together), weighted by the inverse square of that sum. A child
    beside the parting then follows the strands swept its own way, not those across it, whose
    displacements from their own shapes would otherwise carry it off.
    """
    k = min(CANDIDATES, len(parents))
    dist, idx = cKDTree(parents[:, 0]).query(children[:, 0], k=k)
    dist, idx = np.asarray(dist).reshape(len(children), k), np.asarray(idx).reshape(len(children), k)
    own = children - children[:, :1]
    theirs = parents[idx] - parents[idx][:, :, :1]  # (C, k, V, 3)
    score = dist + np.linalg.norm(theirs - own[:, None], axis=3).mean(axis=2)
    order = np.argsort(score, axis=1)[:, :NEIGHBOURS]
    n = order.shape[1]
    chosen = np.take_along_axis(idx, order, axis=1)
    w = 1.0 / np.maximum(np.take_along_axis(score, order, axis=1), 1e-4) ** 2
    w /= w.sum(axis=1, keepdims=True)
    out_parents = np.zeros((len(children), NEIGHBOURS), np.int32)
    out_weights = np.zeros((len(children), NEIGHBOURS), np.float32)
    out_parents[:, :n], out_weights[:, :n] = chosen, w
    return out_parents, out_weights


class HairChildren:
    """Children of a HairModel whose strands all have the same vertex count.

    points (C * V, 3): the children's groomed shapes, V vertices each, in the pose `groom_points` of the
    collider the model is bound on; widths (C * V,): their widths.
    """

    def __init__(self, model, points, widths, groom_points, faces):
        counts = np.asarray(model.counts)
        vertices = int(counts[0])
        if not np.all(counts == vertices):
            raise ValueError("children follow strands of one vertex count; these have "
                             f"{counts.min()} to {counts.max()}")
        points = np.asarray(points, np.float64).reshape(-1, 3)
        if len(points) % vertices:
            raise ValueError(f"{len(points)} child vertices are not whole strands of {vertices}")
        self.vertices = vertices
        self.count = len(points) // vertices
        self.counts = np.full(self.count, vertices)
        self.widths_np = np.asarray(widths, np.float32)
        device = model.device

        parents, weights = choose_parents(model.rest_positions_np.reshape(-1, vertices, 3),
                                          points.reshape(-1, vertices, 3))

        self.anchor_face = int(model.anchor_face)
        if self.anchor_face >= 0:
            a, b, c = (np.asarray(groom_points, np.float64)[v] for v in np.asarray(faces)[self.anchor_face])
            self.rest_frame = wp.mat33(*triangle_frames(np.array([[a, b, c]]))[0].reshape(-1))
            self.rest_center = wp.vec3(*((a + b + c) / 3.0))
        else:
            self.rest_frame, self.rest_center = wp.identity(3, dtype=float), wp.vec3(0.0)
        self._model = model
        self.child_rest = wp.array(points.astype(np.float32), dtype=wp.vec3, device=device)
        self.parents = wp.array(parents, dtype=wp.vec3i, device=device)
        self.weights = wp.array(weights, dtype=wp.vec3, device=device)
        self.points = wp.zeros(len(points), dtype=wp.vec3, device=device)
        self._none_float = wp.zeros(0, dtype=float, device=device)  # no contact bounds: every vertex pushed
        self._none_int = wp.zeros(0, dtype=wp.int32, device=device)
        longest = np.linalg.norm(np.diff(points.reshape(-1, vertices, 3), axis=1), axis=2).max()
        self.search = max(SEARCH, float(longest) + 0.005)

    def queue(self, x, collider, margin, bounds=None):
        """Launch the children's placement for positions x of the model's particles and the
        collider as posed now, kept `margin` [m] outside it; returns the device array it fills
        (valid once the launch has run). bounds: (clearance, slot_of) from HairSolver.mesh_clearance(),
        lower bounds of the particles' distances from this collider's mesh at x, which spare the
        pushes of child vertices they show clear of it (the same children); None pushes every vertex."""
        m = self._model
        collider.fresh_mesh()
        clearance, slot_of = bounds if bounds is not None else (self._none_float, self._none_int)
        inputs = [x, m.rest_positions, m.strand_start, self.child_rest, self.parents, self.weights, self.vertices,
                  collider.points, collider.indices, self.anchor_face, self.rest_frame, self.rest_center,
                  collider.shape, m.pinned_per_strand, float(margin), self.search,
                  clearance, slot_of if slot_of is not None else self._none_int, 0, self.points]
        launch_on_cores(strands.interpolate_children, self.count, inputs, m.device, first=len(inputs) - 2)
        return self.points
