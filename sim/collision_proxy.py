"""Collision proxies: a closed collider surface remeshed coarser, embedded in the original.

A coarse garment (a few hundred particles a few centimetres apart) gains nothing from colliding with
every triangle of a render-resolution body, yet posing that body and refitting its BVH at every
substep is most of the garment's cost. The proxy is the same surface at a chosen spacing: marching
cubes of the collider's signed distance, relaxed and projected back onto the collider, so every
proxy vertex lies on the original surface at fixed barycentric weights of one original triangle.
That embedding carries the collider's motion over: skin weights blend the triangle's corners, and a
point-cache pose maps onto the proxy by the same weights.
"""

import numpy as np
import scipy.sparse
import warp as wp

from warp_kernels import collision

from .sphere_tree import signed_distance, warp_mesh


def coarse_remesh(vertices, faces, spacing, device="cpu", relax_iterations=3):
    """Remesh a closed, outward-wound surface at about `spacing` [m] between vertices.

    Returns (faces (M, 3) int32, source_face (N,) int, barycentric (N, 3) float64): the proxy's
    triangles and, for each of its N vertices, the original triangle it lies on and its weights
    there. Features thinner than about `spacing` (fingers, ears) may close up or vanish; a solver
    that needs them needs a finer spacing.
    """
    import trimesh
    from skimage.measure import marching_cubes

    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    h = float(spacing)
    if not h > 0.0:
        raise ValueError("the proxy spacing must be positive")
    mesh = warp_mesh(v, f, device, winding=True)
    lo = v.min(0) - 2.0 * h
    axes = [np.arange(lo[k], v.max(0)[k] + 2.0 * h, h) for k in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
    # a grid point with the wrong sign would close a small shell around itself: the winding number
    # is right also deep inside, where the closest face is ambiguous
    distance, _ = signed_distance(grid.reshape(-1, 3), mesh, device, winding=True)
    verts, tris, _, _ = marching_cubes(distance.reshape(grid.shape[:3]), level=0.0, spacing=(h, h, h))
    proxy = trimesh.Trimesh(verts + lo, tris, process=True)
    proxy.update_faces(proxy.nondegenerate_faces())
    proxy.remove_unreferenced_vertices()
    if proxy.volume < 0.0:
        proxy.invert()
    # marching cubes leaves grid-aligned ripples and slivers: relax toward the neighbours' average
    # and project back onto the surface, which evens the triangles out
    average = neighbour_average(np.asarray(proxy.edges_unique), len(proxy.vertices))
    p = np.asarray(proxy.vertices, np.float64)
    for _ in range(relax_iterations):
        _, p = signed_distance(0.5 * p + 0.5 * (average @ p), mesh, device)
        p = p.astype(np.float64)
    points = wp.array(p.astype(np.float32), dtype=wp.vec3, device=device)
    face = wp.zeros(len(p), dtype=wp.int32, device=device)
    bary = wp.zeros(len(p), dtype=wp.vec3, device=device)
    wp.launch(collision.mesh_closest_face, len(p), [points, mesh.id, 1.0e6, face, bary], device=device)
    bary = bary.numpy().astype(np.float64)
    bary /= bary.sum(1, keepdims=True)
    return np.asarray(proxy.faces, np.int32), face.numpy().astype(np.int64), bary


def blend_skin_weights(corners, barycentric, skin_indices, skin_weights, num_bones, influences=4):
    """Skin weights of points embedded in triangles: each corner's weights scaled by its barycentric
    weight, summed per bone, and the `influences` largest kept and renormalised.

    corners (N, 3): the triangle corners (vertex indices); barycentric (N, 3); skin_indices and
    skin_weights (V, 4) of the vertices. Returns (indices (N, influences) int32, weights float32).
    """
    n = len(corners)
    dense = np.zeros((n, max(int(num_bones), influences)))  # at least `influences` columns, unused ones 0
    rows = np.arange(n)
    for k in range(3):
        for j in range(skin_indices.shape[1]):
            # one (k, j) pair names each row once, so the += accumulates without collisions
            dense[rows, skin_indices[corners[:, k], j]] += barycentric[:, k] * skin_weights[corners[:, k], j]
    order = np.argsort(-dense, axis=1)[:, :influences]
    weights = np.take_along_axis(dense, order, 1)
    weights /= np.maximum(weights.sum(1, keepdims=True), 1e-12)
    order[weights == 0.0] = 0
    return order.astype(np.int32), weights.astype(np.float32)


def neighbour_average(edges, count):
    """Sparse (count, count) matrix averaging each vertex's edge neighbours."""
    ones = np.ones(2 * len(edges))
    adjacency = scipy.sparse.coo_matrix((ones, (np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]])),
                                        shape=(count, count)).tocsr()
    return scipy.sparse.diags(1.0 / np.maximum(np.asarray(adjacency.sum(1)).ravel(), 1.0)) @ adjacency
