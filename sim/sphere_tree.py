"""Sphere tree of a closed mesh (Hayashimoto et al. §3.3 uses one around the head for collisions).

Leaves are spheres inside the mesh chosen greedily to cover its surface; inner nodes bound their
children and are laid out depth first with skip pointers (see warp_kernels.collision).
"""

import heapq
from dataclasses import dataclass

import numpy as np
import warp as wp
from scipy.spatial import cKDTree

from warp_kernels import collision

from .asset_cache import cached_arrays
from .graphs import launch_on_cores

# the fewest points signed_distance queries on a CPU core of their own
POINTS_PER_SLICE = 4096


@dataclass
class SphereTree:
    centers: np.ndarray  # (n, 3) [m], depth-first order
    radii: np.ndarray  # (n,) [m]
    skip: np.ndarray  # (n,) int32
    is_leaf: np.ndarray  # (n,) int32

    @property
    def leaf_count(self):
        return int(self.is_leaf.sum())

    def leaves(self):
        mask = self.is_leaf.astype(bool)
        return self.centers[mask], self.radii[mask]

    def links(self):
        """Each node's skip pointer with the leaf flag (collision.SPHERE_LEAF) set on leaves, as
        collision.ColliderShape.links holds them (int32)."""
        flag = np.where(self.is_leaf != 0, collision.SPHERE_LEAF, 0).astype(np.int32)
        return np.asarray(self.skip, np.int32) | flag


def warp_mesh(vertices, faces, device="cpu", winding=False):
    """A wp.Mesh of NumPy arrays; winding=True also supports winding-number signs (signed_distance)."""
    return wp.Mesh(points=wp.array(np.asarray(vertices, np.float32), dtype=wp.vec3, device=device),
                   indices=wp.array(np.asarray(faces, np.int32).reshape(-1), dtype=wp.int32, device=device),
                   support_winding_number=winding)


def signed_distance(points, mesh, device="cpu", max_dist=1.0e6, winding=False):
    """Signed distance of points to a closed wp.Mesh (negative inside) and closest surface points.
    winding=True signs by the winding number (collision.mesh_signed_distance; the mesh must support it)."""
    pts = wp.array(np.asarray(points, np.float32), dtype=wp.vec3, device=device)
    n = len(pts)
    dist = wp.zeros(n, dtype=float, device=device)
    closest = wp.zeros(n, dtype=wp.vec3, device=device)
    # a groom's every particle: slices side by side on the CPU's cores
    launch_on_cores(collision.mesh_signed_distance, n, [pts, mesh.id, float(max_dist), int(winding), dist, closest],
                    device, sliced={0, 4, 5}, per_core=POINTS_PER_SLICE)
    return dist.numpy(), closest.numpy()


def build_sphere_tree(vertices, faces, max_leaves=1024, tolerance=None, device="cpu", grid=90, samples=20000):
    """Cover the surface of a closed mesh with at most max_leaves inner spheres, then build the tree.

    tolerance [m]: a surface sample counts as covered when it lies within tolerance of a sphere's
    surface; defaults to 0.35% of the bounding-box diagonal (2 mm on the built-in bust, where the
    surface then lies 0.7 mm beyond the spheres at the median and 1.7 mm at the 95th percentile). Candidate centres lie on a grid of
    `grid` cells along the diagonal; `samples` extra random surface points join the vertices and
    face centres as the points to cover (more samples close the gaps between spheres).
    Built once per mesh and settings: the asset cache keeps the tree between runs.
    """
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    # the grid's inside test runs on `device`, whose float32 queries may round differently
    where = "cuda" if wp.get_device(device).is_cuda else "cpu"
    settings = (int(max_leaves), None if tolerance is None else float(tolerance), int(grid), int(samples), where)
    tree = cached_arrays("sphere_tree", (vertices, faces, settings), lambda: vars(_build_sphere_tree(
        vertices, faces, max_leaves, tolerance, device, grid, samples)))
    return SphereTree(**tree)


def _build_sphere_tree(vertices, faces, max_leaves, tolerance, device, grid, samples):
    lo, hi = vertices.min(0), vertices.max(0)
    diag = float(np.linalg.norm(hi - lo))
    tol = 0.0035 * diag if tolerance is None else float(tolerance)

    step = diag / grid
    axes = [np.arange(lo[k] + 0.5 * step, hi[k], step) for k in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    dist, _ = signed_distance(grid, warp_mesh(vertices, faces, device), device)
    inside = dist < -0.25 * step
    cand_c, cand_r = grid[inside], -dist[inside]

    points = [vertices, vertices[faces].mean(1)]
    if samples:
        import trimesh

        points.append(trimesh.sample.sample_surface(trimesh.Trimesh(vertices, faces, process=False), samples,
                                                    seed=0)[0])
    samples = np.concatenate(points)
    # the samples each candidate covers, as CSR rows
    hits = cKDTree(samples).query_ball_point(cand_c, cand_r + tol, workers=-1, return_sorted=False)
    start = np.concatenate([[0], np.cumsum([len(h) for h in hits])]).astype(np.int64)
    covered = np.concatenate([np.asarray(h, np.int64) for h in hits]) if len(hits) else np.zeros(0, np.int64)
    chosen = greedy_cover(start, covered, len(samples), max_leaves)
    return _hierarchy(cand_c[chosen], cand_r[chosen])


def greedy_cover(start, covered, num_samples, max_sets):
    """Greedy set cover: repeatedly the candidate that covers the most samples not yet covered (the
    lowest index among equals), until max_sets are chosen or nothing more is covered.

    Candidate k covers samples covered[start[k]:start[k + 1]]. Evaluated lazily: what a candidate
    would add only shrinks as samples get covered, so a gain computed earlier bounds it from above
    and only the candidate on top of the heap needs counting again; it is chosen once its fresh gain
    still leads. The choices are those of recounting every candidate at every step.
    """
    uncovered = np.ones(num_samples, bool)
    heap = [(-int(g), k) for k, g in enumerate(np.diff(start)) if g > 0]
    heapq.heapify(heap)
    chosen = []
    while heap and len(chosen) < max_sets:
        _, k = heapq.heappop(heap)
        rows = covered[start[k]:start[k + 1]]
        gain = int(np.count_nonzero(uncovered[rows]))
        if gain == 0:
            continue
        if heap and (-gain, k) > heap[0]:
            heapq.heappush(heap, (-gain, k))  # another may now cover more: counted next
            continue
        chosen.append(k)
        uncovered[rows] = False
    return np.asarray(chosen, np.int64)


def empty_sphere_tree():
    """A tree with no nodes: collision and penetration queries against it find nothing."""
    return SphereTree(np.zeros((0, 3), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int32),
                      np.zeros(0, np.int32))


def _hierarchy(leaf_c, leaf_r):
    centers, radii, skip, is_leaf = [], [], [], []

    def visit(idx):
        node = len(centers)
        c = leaf_c[idx].mean(0)
        r = float(np.max(np.linalg.norm(leaf_c[idx] - c, axis=1) + leaf_r[idx]))
        centers.append(c)
        radii.append(r)
        skip.append(-1)
        is_leaf.append(int(len(idx) == 1))
        if len(idx) > 1:
            axis = int(np.argmax(np.ptp(leaf_c[idx], axis=0)))
            order = idx[np.argsort(leaf_c[idx, axis], kind="stable")]
            half = len(order) // 2
            visit(order[:half])
            visit(order[half:])
        else:
            centers[node], radii[node] = leaf_c[idx[0]], float(leaf_r[idx[0]])
        skip[node] = len(centers)

    visit(np.arange(len(leaf_c)))
    return SphereTree(np.asarray(centers, np.float32), np.asarray(radii, np.float32),
                      np.asarray(skip, np.int32), np.asarray(is_leaf, np.int32))
