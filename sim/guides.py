"""Captured guide strands driving simulated hair (beyond the capture paper, which leaves this open).

Each simulated strand follows up to three captured guides whose roots are nearest its own,
weighted by inverse distance: at normalised arc position s its target is its own root plus the
guides' offsets from their roots at s. The solver pulls free particles toward the target with a
stiffness in 1/s before shape matching and the length constraint, so the hair keeps its own length,
collisions and detail while moving as the capture did.
"""

import numpy as np
import warp as wp
from scipy.spatial import cKDTree

from warp_kernels import strands


class GuideTargets:
    """guide_frames (F, G, M, 3) sampled at `fps` from time 0; each guide resampled to M evenly
    spaced vertices along its arc length."""

    def __init__(self, model, guide_frames, fps, neighbours=3):
        frames = np.asarray(guide_frames, np.float64)
        if frames.ndim != 4 or frames.shape[-1] != 3 or frames.shape[2] < 2 or not np.all(np.isfinite(frames)):
            raise ValueError("guides must be finite (frames, guides, vertices >= 2, 3) positions")
        self.frames = _even(frames.reshape(-1, *frames.shape[2:]), frames.shape[2]).reshape(frames.shape)
        self.fps = float(fps)
        self.num_guides, self.vertices = self.frames.shape[1], self.frames.shape[2]
        device = model.device
        roots = model.rest_positions_np[model.strand_start_np[:-1]].astype(np.float64)
        k = min(neighbours, self.num_guides)
        dist, idx = cKDTree(self.frames[0, :, 0]).query(roots, k=k)
        dist, idx = np.asarray(dist).reshape(len(roots), k), np.asarray(idx).reshape(len(roots), k)
        w = 1.0 / np.maximum(dist, 1e-4) ** 2
        w /= w.sum(1, keepdims=True)
        guides = np.zeros((len(roots), 3), np.int32)
        weights = np.zeros((len(roots), 3), np.float32)
        guides[:, :k], weights[:, :k] = idx, w
        # normalised arc length of each particle along its strand's rest shape
        rest = model.rest_positions_np.astype(np.float64)
        seg = np.linalg.norm(np.diff(rest, axis=0), axis=1)
        seg[model.strand_start_np[1:-1] - 1] = 0.0  # no segment across strands
        arc = np.concatenate([[0.0], np.cumsum(seg)])
        start = model.strand_start_np
        base = np.repeat(arc[start[:-1]], model.counts)
        total = np.repeat(arc[start[1:] - 1] - arc[start[:-1]], model.counts)
        param = (arc - base) / np.maximum(total, 1e-9)
        self.strand_guides = wp.array(guides, dtype=wp.vec3i, device=device)
        self.strand_guide_weights = wp.array(weights, dtype=wp.vec3, device=device)
        self.particle_param = wp.array(param.astype(np.float32), dtype=float, device=device)
        # every captured frame on the device, frame-major: the kernel interpolates in time itself, so
        # nothing is uploaded per substep and a captured frame replays at any time
        self.num_frames = len(self.frames)
        self.frame_points = wp.array(self.frames.reshape(-1, 3).astype(np.float32), dtype=wp.vec3, device=device)

    def pull(self, stiffness):
        """These guides as the kernels take them (strands.GuidePull), pulling `stiffness` of the way
        to their targets per substep."""
        pull = strands.GuidePull()
        pull.strand_guides, pull.weights = self.strand_guides, self.strand_guide_weights
        pull.param = self.particle_param
        pull.points, pull.frames, pull.guides = self.frame_points, self.num_frames, self.num_guides
        pull.vertices, pull.fps, pull.stiffness = self.vertices, self.fps, float(stiffness)
        return pull


def _even(polylines, count):
    """Polylines (P, n, 3) resampled to `count` points evenly spaced along each one's arc length."""
    from .capture_rig import arc_lengths, points_at

    total = arc_lengths(polylines)[:, -1]
    return points_at(polylines, total[:, None] * np.linspace(0.0, 1.0, count)[None])


def read_guides(path, prim="hair_guides"):
    """(frames, guides, vertices, 3) and fps from a cache's curves prim (e.g. a `cfx capture solve`
    result). Guides with different vertex counts are resampled to the largest count."""
    from io_usd.cache import CacheReader

    reader = CacheReader(path)
    if prim not in reader.prims or reader.prims[prim].kind != "curves":
        curves = [n for n, p in reader.prims.items() if p.kind == "curves"]
        raise ValueError(f"{path}: no curves prim '{prim}' (curves here: {', '.join(curves) or 'none'})")
    counts = reader.prims[prim].counts
    m = int(counts.max())
    starts = np.concatenate([[0], np.cumsum(counts)])
    frames = []
    for f in reader.frames(prim):
        pts = reader.points(prim, f).astype(np.float64)
        frames.append(np.concatenate([_even(pts[None, a:b], m) for a, b in zip(starts[:-1], starts[1:])]))
    return np.asarray(frames), reader.fps or 24.0
