"""A deforming collider (head, body): skinned triangle mesh, its wp.Mesh BVH and its sphere tree.

Poses are uploaded once per frame for every substep (`set_poses`), and `apply_pose(k)` skins the
mesh and the sphere-tree centres to pose k with kernels only, so a frame's substeps need no host
work (the prerequisite for capturing a frame in a CUDA graph).

The cloth's body queries read a second BVH, over boxes of the triangles (`triangle_bvh`): `sweep()`
bounds each triangle over all the uploaded poses at once, so one refit serves a frame's every
substep, where the wp.Mesh BVH, fitted to one pose, needs one per substep.
"""

import copy
from functools import partial

import numpy as np
import warp as wp
from scipy.spatial import cKDTree

from warp_kernels import collision, skinning

from .collision_proxy import blend_skin_weights, coarse_remesh
from .graphs import core_slices, launch_on_cores, refit_bvh, run_parallel
from .mesh_topology import unique_pairs
from .sphere_tree import POINTS_PER_SLICE, build_sphere_tree, empty_sphere_tree, signed_distance

# a sweep of the poses is split among the CPU's cores in ranges of at least this many points: a
# range handed to another core costs tens of microseconds, a point about 15 ns per pose (0.4 ms for
# 2,048 points over a 1/60 s frame's 13 poses); one split step a frame, faster in every case timed
SWEEP_POINTS_PER_CORE = 2048
# the largest displacement of a pose is taken on a GPU by at most this many threads, each over a stride
# of the points, that raise Collider.moved with far fewer atomics than a thread per point
DISPLACEMENT_THREADS = 4096
UNKNOWN_MOTION = 1.0e30  # Collider.moved after a pose that did not measure it: lowers every bound to nothing


class Collider:
    def __init__(self, name, vertices, faces, skin_indices, skin_weights, num_bones, device="cpu",
                 sphere_leaves=1024):
        """sphere_leaves = 0 skips the sphere tree (a few seconds to build) for mesh-only collisions."""
        self.name = name
        self.device = device
        self.rest_points_np = np.asarray(vertices, np.float32)
        self.faces_np = np.asarray(faces, np.int32).reshape(-1, 3)
        self.num_bones = int(num_bones)
        skin_indices = np.asarray(skin_indices, np.int32).reshape(-1, 4)
        skin_weights = np.asarray(skin_weights, np.float32).reshape(-1, 4)
        self.skin_indices_np, self.skin_weights_np = skin_indices, skin_weights

        arr = lambda a, t: wp.array(a, dtype=t, device=device)  # noqa: E731
        self.rest_points = arr(self.rest_points_np, wp.vec3)
        self.points = arr(self.rest_points_np, wp.vec3)
        self.prev_points = arr(self.rest_points_np, wp.vec3)  # the pose before, for surface velocities
        # the largest displacement of a vertex from prev_points to points: how far the surface moved
        # (UNKNOWN_MOTION after a pose that did not measure it)
        self.moved = wp.zeros(1, dtype=float, device=device)
        self._pose_points = None  # poses given as point arrays instead of bone matrices
        self.indices = arr(self.faces_np.reshape(-1), wp.int32)
        self.skin_indices = arr(skin_indices, wp.vec4i)
        self.skin_weights = arr(skin_weights, wp.vec4)
        self.mesh = wp.Mesh(points=self.points, indices=self.indices)

        if sphere_leaves > 0:
            self.tree = build_sphere_tree(self.rest_points_np, self.faces_np, max_leaves=sphere_leaves,
                                          device=device)
        else:
            self.tree = empty_sphere_tree()
        # sphere centres move with the skin weights of their nearest surface vertex
        _, nearest = cKDTree(self.rest_points_np).query(self.tree.centers.reshape(-1, 3))
        nearest = np.asarray(nearest, np.int64).reshape(-1)
        self.sphere_rest_centers = arr(self.tree.centers, wp.vec3)
        self.sphere_centers = arr(self.tree.centers, wp.vec3)
        self.prev_sphere_centers = arr(self.tree.centers, wp.vec3)
        self.sphere_radii = arr(self.tree.radii, float)
        self.sphere_is_leaf = arr(self.tree.is_leaf, wp.int32)
        self.sphere_links = arr(self.tree.links(), wp.int32)
        # the centres and radii packed side by side for the walks (collision.ColliderShape)
        self.sphere_nodes = wp.zeros(len(self.tree.radii), dtype=wp.vec4, device=device)
        self._pack_spheres()
        self.sphere_parent = arr(_parents(self.tree.skip), wp.int32)
        self.sphere_skin_indices = arr(skin_indices[nearest], wp.vec4i)
        self.sphere_skin_weights = arr(skin_weights[nearest], wp.vec4)
        self.shape = self._shape()
        self.bone_matrices = None
        self._pose_buffers = {}
        self._adjacency = None
        self._embedding = None  # a proxy's (corners, barycentric, source vertex count): see proxy()
        self.bvh_stale = False  # the BVH lags the points: the next host query refits it first (fresh_mesh)
        self._winding = None  # a mesh over the same points signing by winding numbers, built on demand
        self._boxes = None  # the triangle boxes and their BVH (triangle_bvh), built on demand
        self._swept = None  # (pose points, motion into each pose) of the last sweep of the uploaded poses

    def _shape(self):
        """What the collision kernels take: the mesh and the sphere tree (arrays refitted in place)."""
        shape = collision.ColliderShape()
        shape.mesh = self.mesh.id
        shape.spheres, shape.links = self.sphere_nodes, self.sphere_links
        return shape

    def _pack_spheres(self):
        wp.launch(collision.pack_sphere_tree, len(self.sphere_nodes),
                  [self.sphere_centers, self.sphere_radii, self.sphere_nodes], device=self.device)

    def twin(self, spheres=True):
        """The same collider with a pose of its own: it shares the rest shape, skinning, sphere-tree
        layout and adjacency, and owns its posed points, BVH and sphere centres. Two solvers that
        step side by side (sim.scene) each pose their own twin, so neither sees the other's substeps.
        spheres=False leaves the sphere tree out (mesh queries only): a solver that never reads it
        (the cloth) then does not refit it at every substep."""
        twin = copy.copy(self)
        twin.points, twin.prev_points = wp.clone(self.points), wp.clone(self.prev_points)
        twin.moved = wp.clone(self.moved)
        twin.mesh = wp.Mesh(points=twin.points, indices=self.indices)
        if spheres:
            twin.sphere_centers = wp.clone(self.sphere_centers)
            twin.prev_sphere_centers = wp.clone(self.prev_sphere_centers)
            twin.sphere_radii = wp.clone(self.sphere_radii)  # inner radii are refitted in place
            twin.sphere_nodes = wp.clone(self.sphere_nodes)
        else:  # every sphere array empty: the tree's launches cover no spheres, and Warp skips them
            twin.tree = empty_sphere_tree()
            empty = lambda dtype: wp.empty(0, dtype=dtype, device=self.device)  # noqa: E731
            twin.sphere_rest_centers = twin.sphere_centers = twin.prev_sphere_centers = empty(wp.vec3)
            twin.sphere_radii, twin.sphere_nodes = empty(float), empty(wp.vec4)
            twin.sphere_is_leaf, twin.sphere_links = empty(wp.int32), empty(wp.int32)
            twin.sphere_parent = empty(wp.int32)
            twin.sphere_skin_indices, twin.sphere_skin_weights = empty(wp.vec4i), empty(wp.vec4)
        twin.shape = twin._shape()
        twin.bone_matrices = twin._pose_points = None
        twin._pose_buffers = {}
        twin._adjacency = self.adjacency()
        twin.bvh_stale = False
        twin._winding = None
        twin._boxes = twin._swept = None
        return twin

    def proxy(self, spacing):
        """A coarser collider over the same surface (sim.collision_proxy), with its own pose: its
        vertices are about `spacing` [m] apart on this collider's rest surface, each at fixed
        barycentric weights of one of its triangles. It takes this collider's poses: the same bone
        matrices (set_poses; skin weights blended from the triangle's corners) or this collider's
        point poses (set_point_poses maps them by the weights). Mesh queries only: no sphere tree."""
        faces, source_face, bary = coarse_remesh(self.rest_points_np, self.faces_np, spacing, self.device)
        corners = self.faces_np[source_face]
        rest = np.einsum("nk,nkj->nj", bary, self.rest_points_np[corners].astype(np.float64))
        indices, weights = blend_skin_weights(corners, bary, self.skin_indices_np, self.skin_weights_np,
                                              self.num_bones)
        proxy = Collider(f"{self.name} proxy", rest, faces, indices, weights, self.num_bones, self.device,
                         sphere_leaves=0)
        proxy._embedding = (corners, bary.astype(np.float32), len(self.rest_points_np))
        return proxy

    def set_point_poses(self, points):
        """points: (K, V, 3) vertex positions for K upcoming poses (a point cache, e.g. from USD); a
        proxy takes the poses of the collider it was made from."""
        pts = np.asarray(points, np.float32)
        if self._embedding is not None:
            corners, bary, count = self._embedding
            if pts.size % (3 * count):
                raise ValueError(f"{self.name}: point poses must have {count} points each")
            pts = np.einsum("nk,pnkj->pnj", bary, pts.reshape(-1, count, 3)[:, corners])
        pts = np.ascontiguousarray(pts.reshape(-1, 3))
        if len(pts) % len(self.rest_points_np):
            raise ValueError(f"{self.name}: point poses must have {len(self.rest_points_np)} points each")
        self._pose_points = self._pose_buffer(pts, wp.vec3)
        self.bone_matrices = None
        self._swept = None

    def set_poses(self, matrices):
        """matrices: (K, num_bones, 4, 4) bone transforms for K upcoming poses (e.g. substeps)."""
        m = np.ascontiguousarray(np.asarray(matrices, np.float32).reshape(-1, 4, 4))
        self.bone_matrices = self._pose_buffer(m, wp.mat44)
        self._pose_points = None
        self._swept = None

    def _pose_buffer(self, values, dtype):
        """One device buffer per pose count, refilled in place: solvers with different substep counts
        each keep the buffer their captured frames read."""
        key = (dtype, values.shape)
        buffer = self._pose_buffers.get(key)
        if buffer is None:
            buffer = self._pose_buffers[key] = wp.array(values, dtype=dtype, device=self.device)
        else:
            buffer.assign(values)
        return buffer

    def apply_pose(self, k, refit=True, listed=None):
        """Pose the mesh, its BVH and the sphere tree to pose k of the uploaded ones; the pose before
        stays in prev_points and prev_sphere_centers (surface velocities, hair contact bounds).
        refit=False leaves the BVH at an earlier pose, which saves most of the cost: for steps that
        read only the points and the sphere tree (hair colliding with the sphere tree), or the
        triangle BVH of a sweep, never for mesh queries; the caller marks it stale (bvh_stale) once
        the frame is done, and the host queries below refit it first. listed (an int32 array of
        vertices, with refit=False): a skinned pose moves only those, the rest keep an earlier pose,
        for steps that read only them (a pose the host may read, such as a frame's last, must move
        all). After a sweep of the uploaded poses, pose k is the swept one, its motion measured
        there, and only the mesh moves (see sweep)."""
        if listed is not None and refit:
            raise ValueError("a pose of listed vertices leaves the others behind: its BVH cannot be refitted")
        wp.copy(self.prev_points, self.points)
        self.bvh_stale = not refit
        n = len(self.rest_points_np)
        if self._swept is not None:
            if listed is not None:
                raise ValueError("a swept pose moves every vertex: it takes no list")
            poses, moved = self._swept
            wp.copy(self.points, poses, 0, k * n, n)
            wp.copy(self.moved, moved, 0, k, 1)
            if refit:
                refit_bvh(self.mesh)
            return
        wp.copy(self.prev_sphere_centers, self.sphere_centers)
        if not refit:  # a refit measures the motion (_refit_pose); a fill first would be one more launch
            self.moved.fill_(UNKNOWN_MOTION)
        if self._pose_points is not None:
            wp.copy(self.points, self._pose_points, 0, k * n, n)
            if refit:
                self._refit_pose()
        else:  # the sphere tree follows skinned poses only
            offset = k * self.num_bones
            if listed is not None:
                wp.launch(skinning.skin_listed_points, len(listed),
                          [self.rest_points, self.skin_indices, self.skin_weights, self.bone_matrices, offset, listed,
                           self.points], device=self.device)
            else:
                wp.launch(skinning.skin_points, len(self.points),
                          [self.rest_points, self.skin_indices, self.skin_weights, self.bone_matrices, offset,
                           self.points], device=self.device)
            if refit:
                self._refit_pose()
            wp.launch(skinning.skin_points, len(self.sphere_centers),
                      [self.sphere_rest_centers, self.sphere_skin_indices, self.sphere_skin_weights,
                       self.bone_matrices, offset, self.sphere_centers], device=self.device)
            wp.launch(collision.clear_inner_radii, len(self.sphere_centers), [self.sphere_radii, self.sphere_is_leaf],
                      device=self.device)
            wp.launch(collision.refit_sphere_tree, len(self.sphere_centers),
                      [self.sphere_centers, self.sphere_radii, self.sphere_parent, self.sphere_is_leaf],
                      device=self.device)
            self._pack_spheres()

    def skin_binding(self, bound):
        """The bindings of `bound` (a model with bind_triangle, bind_barycentric and bind_local, made by
        skinning.compute_bindings on this collider's triangles) on the current pose, as kernels read them
        (warp_kernels.skinning.SkinBinding)."""
        binding = skinning.SkinBinding()
        binding.mesh_points, binding.mesh_indices = self.points, self.indices
        binding.triangle, binding.barycentric = bound.bind_triangle, bound.bind_barycentric
        binding.local = bound.bind_local
        return binding

    def adjacency(self):
        """CSR vertex->vertex and vertex->face adjacency and per-vertex concave flags, built once
        (the cloth's nearest-vertex walk runs on them)."""
        if self._adjacency is None:
            self._adjacency = _Adjacency(self.rest_points_np, self.faces_np, self.device)
        return self._adjacency

    def _refit_pose(self):
        """The BVHs refitted to a pose just applied (not swept), and its motion measured."""
        self.refit_mesh()
        self._measure_motion()

    def refit_mesh(self):
        """Refit the mesh's BVH (and the triangle boxes, where no sweep bounds them) to the current
        points, without measuring the motion: for a solver that refits a pose left stale
        (apply_pose(k, refit=False)) itself, beside work that does not read the BVH
        (HairSolver.step)."""
        refit_bvh(self.mesh)
        if self._boxes is not None and self._swept is None:  # the boxes follow a refitted pose
            self._boxes.fit(self.points, self.points, self.indices)
        self.bvh_stale = False

    @property
    def triangle_bvh(self):
        """A wp.Bvh over boxes of the triangles (in face order): of the current pose where
        apply_pose refits, of every uploaded pose after sweep(). Built at first use."""
        if self._boxes is None:
            self._boxes = _TriangleBoxes(len(self.rest_points_np), len(self.faces_np), self.device)
            self._boxes.fit(self.points, self.points, self.indices, build=True)
        return self._boxes.bvh

    def sweep(self):
        """Bound each triangle over all the uploaded poses (triangle_bvh), so that queries of it hold
        at every one of them with one refit: a frame's substeps need no refit each. The poses are
        skinned here, at once, with the motion into each measured, and until the next upload
        apply_pose(k) takes pose k from them and moves the mesh only: the sphere tree stays where it
        was, and the wp.Mesh BVH moves only where apply_pose refits it."""
        self.triangle_bvh  # noqa: B018  (built at first use)
        b, n = self._boxes, len(self.rest_points_np)
        skinned = self._pose_points is None
        count = len(self.bone_matrices) // self.num_bones if skinned else len(self._pose_points) // n
        poses = b.buffer(("poses", count), count * n, wp.vec3) if skinned else self._pose_points
        moved = b.buffer(("moved", count), count, float)
        # ranges of the points side by side on the CPU's cores, each raising its own row of motions
        parts = core_slices(n, self.device, per_core=SWEEP_POINTS_PER_CORE)
        cuts = [n * k // parts for k in range(parts + 1)]
        rows = moved if parts == 1 else b.buffer(("moved rows", count, parts), count * parts, float)
        rows.zero_()
        run_parallel([partial(wp.launch, collision.sweep_poses, cuts[k + 1] - cuts[k],
                              [int(skinned), self.rest_points, self.skin_indices, self.skin_weights,
                               self.bone_matrices, self.num_bones, n, count, poses, b.point_lower, b.point_upper,
                               rows, cuts[k], k], device=self.device) for k in range(parts)])
        if parts > 1:
            wp.launch(collision.largest_of_rows, count, [rows, parts, count, moved], device=self.device)
        b.fit(b.point_lower, b.point_upper, self.indices)
        self._swept = (poses, moved)

    def _measure_motion(self):
        """moved for the pose just applied: a pose with a refitted BVH is one mesh queries read, and the
        cloth's contact bounds (kernels.cloth.BodyClearance) are lowered by how far it moved."""
        self.moved.zero_()
        n = len(self.points)
        # a CPU runs its threads one after another: one per point reads the points in order
        threads = n if wp.get_device(self.device).is_cpu else max(1, min(n, DISPLACEMENT_THREADS))
        wp.launch(collision.largest_displacement, threads, [self.prev_points, self.points, n, threads, self.moved],
                  device=self.device)

    def reset_motion(self):
        """Make the current pose also the previous one (after a jump, so surfaces have no velocity)."""
        wp.copy(self.prev_points, self.points)
        self.moved.zero_()

    def fresh_mesh(self):
        """The posed mesh with its BVH refitted to the current points (a refit only if stale)."""
        if self.bvh_stale:
            self.mesh.refit()
            self.bvh_stale = False
        return self.mesh

    def push_out(self, points, margin, mode=collision.COLLIDE_MESH, search=0.05):
        """Project (N, 3) NumPy points out of the collider in its current pose; returns NumPy.

        Only penetrations shallower than `search` [m] are seen (grooming moves in small steps).
        """
        pts = wp.array(np.asarray(points, np.float32), dtype=wp.vec3, device=self.device)
        self.fresh_mesh()
        # a groom's every point, many times while it grows: slices side by side on the CPU's cores
        launch_on_cores(collision.push_points_out, len(pts), [pts, int(mode), self.shape, float(margin), float(search)],
                        self.device, sliced={0}, per_core=POINTS_PER_SLICE)
        return pts.numpy()

    def signed_distance(self, points, max_dist=1.0e6):
        """Signed distance [m] of (N, 3) points to the posed mesh (negative inside).

        Points farther than max_dist from the surface report +max_dist. The closest face's
        pseudo-normal signs every point, and the mesh's winding number re-signs those it calls
        inside: a posed body intersects itself (an arm pressed to the side), where the pseudo-normal
        can call a point between the two surfaces inside.
        """
        points = np.asarray(points)
        distance = signed_distance(points, self.fresh_mesh(), self.device, max_dist)[0]
        inside = np.flatnonzero(distance < 0.0)
        if inside.size:
            if self._winding is None:
                self._winding = wp.Mesh(points=self.points, indices=self.indices, support_winding_number=True)
            else:
                self._winding.refit()  # the points may have moved since: refitting also updates the winding data
            distance[inside] = signed_distance(points[inside], self._winding, self.device, max_dist, winding=True)[0]
        return distance

    def closest_points(self, points):
        """Closest surface points of the posed mesh, their faces and barycentric weights."""
        pts = wp.array(np.asarray(points, np.float32), dtype=wp.vec3, device=self.device)
        face = wp.zeros(len(pts), dtype=wp.int32, device=self.device)
        bary = wp.zeros(len(pts), dtype=wp.vec3, device=self.device)
        wp.launch(collision.mesh_closest_face, len(pts), [pts, self.fresh_mesh().id, 1.0e6, face, bary],
                  device=self.device)
        face, bary = face.numpy(), bary.numpy().astype(np.float64)
        tri = self.points.numpy()[self.faces_np[face]].astype(np.float64)
        return np.einsum("nk,nkj->nj", bary, tri), face, bary

    def visible_from(self, points, eye, tolerance=1.0e-3):
        """(N,) bool: which points a camera at `eye` sees past the posed mesh (grooming tools touch
        only those); points within `tolerance` [m] of where their sight line meets the mesh count as seen."""
        pts = wp.array(np.asarray(points, np.float32).reshape(-1, 3), dtype=wp.vec3, device=self.device)
        visible = wp.zeros(len(pts), dtype=wp.int32, device=self.device)
        wp.launch(collision.visible_from_eye, len(pts),
                  [pts, self.fresh_mesh().id, wp.vec3(*np.asarray(eye, np.float32)), float(tolerance), visible],
                  device=self.device)
        return visible.numpy().astype(bool)

    def ray_hits(self, origins, directions, max_t=100.0):
        """Distance [m] along each ray (N, 3 origins and unit directions) to the posed mesh, -1 for a miss."""
        arr = lambda a: wp.array(np.asarray(a, np.float32).reshape(-1, 3), dtype=wp.vec3, device=self.device)  # noqa: E731
        o, d = arr(origins), arr(directions)
        t = wp.zeros(len(o), dtype=float, device=self.device)
        wp.launch(collision.first_ray_hits, len(o), [o, d, self.fresh_mesh().id, float(max_t), t], device=self.device)
        return t.numpy()

    def sphere_tree_depth(self, points):
        """Deepest penetration [m] of each point into the posed sphere tree's leaves."""
        pts = wp.array(np.asarray(points, np.float32), dtype=wp.vec3, device=self.device)
        depth = wp.zeros(len(pts), dtype=float, device=self.device)
        wp.launch(collision.sphere_tree_penetration, len(pts),
                  [pts, self.shape, depth],
                  device=self.device)
        return depth.numpy()

    def posed_points(self):
        return self.points.numpy()


class _TriangleBoxes:
    """Boxes of a collider's triangles, the wp.Bvh over them, and the buffers a sweep fills."""

    def __init__(self, num_points, num_triangles, device):
        z = lambda count: wp.zeros(count, dtype=wp.vec3, device=device)  # noqa: E731
        self.device = device
        self.point_lower, self.point_upper = z(num_points), z(num_points)
        self.lower, self.upper = z(num_triangles), z(num_triangles)
        self.bvh = None
        self._buffers = {}  # per pose count: captured frames read the ones they were captured with

    def fit(self, lower, upper, indices, build=False):
        """The triangle boxes from their corners' boxes (lower, upper per point), and the BVH refitted
        (or built) over them."""
        wp.launch(collision.triangle_bounds, len(self.lower), [indices, lower, upper, self.lower, self.upper],
                  device=self.device)
        if build:
            self.bvh = wp.Bvh(self.lower, self.upper)
        else:
            refit_bvh(self.bvh)

    def buffer(self, key, count, dtype):
        if key not in self._buffers:
            self._buffers[key] = wp.zeros(count, dtype=dtype, device=self.device)
        return self._buffers[key]


def _parents(skip):
    """Parent of every node of a depth-first tree with skip pointers (node i's subtree is i + 1 ..
    skip[i] - 1); -1 for the root."""
    parent = np.full(len(skip), -1, np.int32)
    stack = []
    for i in range(len(skip)):
        while stack and skip[stack[-1]] <= i:
            stack.pop()
        if stack:
            parent[i] = stack[-1]
        stack.append(i)
    return parent


class _Adjacency:
    def __init__(self, vertices, faces, device):
        n = len(vertices)
        e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        e = unique_pairs(np.sort(np.concatenate([e, e[:, ::-1]]), axis=1))
        pairs = np.concatenate([e, e[:, ::-1]])
        pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
        vv_start = np.concatenate([[0], np.cumsum(np.bincount(pairs[:, 0], minlength=n))])
        vf = np.stack([faces.reshape(-1), np.repeat(np.arange(len(faces)), 3)], 1)
        vf = vf[np.argsort(vf[:, 0], kind="stable")]
        vf_start = np.concatenate([[0], np.cumsum(np.bincount(vf[:, 0], minlength=n))])
        # a vertex is concave (or a saddle) when a neighbour rises above its tangent plane: there the
        # "behind every incident face" test and the greedy walk are not trustworthy
        fn = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
        vn = np.zeros_like(vertices)
        for k in range(3):
            np.add.at(vn, faces[:, k], fn)
        vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-30)
        d = vertices[pairs[:, 1]] - vertices[pairs[:, 0]]
        rise = np.einsum("ij,ij->i", d, vn[pairs[:, 0]]) / np.maximum(np.linalg.norm(d, axis=1), 1e-30)
        concave = np.zeros(n, np.int32)
        np.maximum.at(concave, pairs[:, 0], (rise > 0.05).astype(np.int32))
        arr = lambda a, t: wp.array(a, dtype=t, device=device)  # noqa: E731
        self.vv_start, self.vv_adj = arr(vv_start.astype(np.int32), wp.int32), arr(pairs[:, 1].astype(np.int32), wp.int32)
        self.vf_start, self.vf_face = arr(vf_start.astype(np.int32), wp.int32), arr(vf[:, 1].astype(np.int32), wp.int32)
        self.concave = arr(concave, wp.int32)
        self.concave_fraction = float(concave.mean())
        # distances this close count as equal when signing a closest point, as wp.Mesh's queries do
        # (1e-3 of the mean edge)
        edges = np.linalg.norm(vertices[faces] - vertices[np.roll(faces, 1, axis=1)], axis=2)
        self.tie = 1.0e-3 * float(edges.mean()) if len(faces) else 0.0
