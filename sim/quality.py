"""A scene's per-frame quality statistics (a run's `cfx:stats`), computed on the scene's device.

`queue` launches the statistics' kernels behind a frame's work without waiting and returns the
arrays to read back with the frame (sim.graphs.AsyncReadback) and a function that turns what was
read back into numbers, so a run on a GPU never stops to measure. The kernels reduce on the device:
per frame only a few counts come back, beside the positions a cache reads back anyway.

Penetration counts need the sign of a distance. The closest face's pseudo-normal gives it on the
device; the points it calls deeper inside than a statistic's depth are listed there and re-signed
on the host by the winding number, from the frame's read-back points and body pose (a posed body
intersects itself, an arm pressed to the side, where the pseudo-normal can call a point between the
two surfaces inside). Most frames list none.
"""

import numpy as np
import warp as wp

from warp_kernels import cloth as cloth_kernels
from warp_kernels import collision, strands

from .graphs import core_slices, launch_on_cores
from .sphere_tree import signed_distance, warp_mesh

HAIR_SEARCH = 0.03  # m: hair points are looked for this far from the collider; deeper ones go unseen
HAIR_DEPTH = 0.001  # m: hair points deeper inside count (inside_1mm)
ROOT_BAND = 0.005  # m: roots this close to the surface count as on it (root_within_5mm)
CLOTH_SEARCH = 0.05  # m: the same for the cloth and its detail surface
CLOTH_DEPTH = 0.002  # m (cloth_inside_2mm, detail_inside_2mm)
LISTED = 1 << 16  # deep points listed per statistic; a frame with more re-checks every point on the host
PER_CORE = 4096  # the fewest points a CPU core queries on its own (graphs.core_slices)
STRANDS_PER_CORE = 128  # the same in strands of a groom
WALK_PER_CORE = 256  # the same for the walk's check, each particle against the body vertices near it
WALK_GRID = 64  # hash grid cells per axis over the body vertices (walk_agreement)


class QualityProbe:
    """The statistics' device buffers of one scene, reused frame after frame."""

    def __init__(self, scene):
        self.scene = scene
        self._buffers = {}
        self._cloth_edges = None  # (cloth model, the edges its strain statistics measure, their rest lengths)
        self.host_meshes = HostMeshes()  # the read-back poses that deep points are re-signed against
        # the body vertices near each cloth particle (walk_agreement); built on first use, it allocates
        self._walk_grid = None

    @property
    def _grid(self):
        if self._walk_grid is None:
            self._walk_grid = wp.HashGrid(WALK_GRID, WALK_GRID, WALK_GRID, device=self.scene.device)
        return self._walk_grid

    def _zeros(self, arrays, name, shape, dtype):
        """A zeroed device buffer kept under `name` (reallocated when a haircut changes its shape),
        also put in `arrays` for the read-back; the zeroing is queued behind the previous frame's
        read-back copy."""
        buffer = self._buffers.get(name)
        if buffer is None or buffer.shape != shape:
            buffer = self._buffers[name] = wp.zeros(shape, dtype=dtype, device=self.scene.device)
        else:
            buffer.zero_()
        arrays[name] = buffer
        return buffer

    def _deep(self, arrays, name, points, rows):
        """(count, listed) buffers for collision.list_deep_point over `points` points in `rows` slices."""
        return (self._zeros(arrays, f"quality_{name}_deep", (rows, 1), wp.int32),
                self._zeros(arrays, f"quality_{name}_listed", (rows, max(1, min(points, LISTED))), wp.int32))

    def queue(self, hair=True, cloth=True, detail=True):
        """Launch this frame's statistics without waiting. Returns ({name: wp.array} to read back,
        finish): finish({name: NumPy array}) gives the statistics by name. Names other than the
        scene's own outputs (the collider's, hair, cloth, cloth_detail) start with quality_."""
        scene, arrays, parts = self.scene, {}, []
        device = scene.device
        if hair and scene.model is not None:
            m, collider = scene.model, scene.collider
            rows = core_slices(m.num_strands, device, STRANDS_PER_CORE)
            worst = self._zeros(arrays, "quality_hair_worst", (rows, 2), float)
            near = self._zeros(arrays, "quality_hair_roots_near", (rows, 1), wp.int32)
            count, listed = self._deep(arrays, "hair", m.num_particles, rows)
            launch_on_cores(strands.strand_quality, m.num_strands,
                            [scene.state.x, 0, 0, m.rest_length, m.strand_start, collider.fresh_mesh().id, HAIR_SEARCH,
                             HAIR_DEPTH, ROOT_BAND, worst, near, count, listed],
                            device, first=1, part=2, per_core=STRANDS_PER_CORE)
            arrays.update({"hair": scene.state.x, scene.collider_name: collider.points})
            parts.append(_hair_part(m.num_particles, m.num_strands, scene.collider_name, collider.faces_np,
                                    self.host_meshes))
        cloth = cloth and scene.cloth_model is not None
        detail = detail and scene.cloth_detail is not None
        if cloth or detail:
            body = scene.cloth_body  # the body itself, also where the cloth collides with a proxy of it
            body_key = scene.collider_name if body is scene.collider else "quality_cloth_body"
            arrays[body_key] = body.points
        if cloth:
            cm, st = scene.cloth_model, scene.cloth_state
            n = cm.num_particles
            rows = core_slices(n, device, PER_CORE)
            count, listed = self._deep(arrays, "cloth", n, rows)
            launch_on_cores(collision.count_deep_points, n,
                            [st.x, 0, 0, body.fresh_mesh().id, CLOTH_SEARCH, CLOTH_DEPTH, count, listed], device,
                            first=1, part=2, per_core=PER_CORE)
            # every particle against the vertices near it of the mesh the walk runs on (the collision
            # proxy's, if any), found by a hash grid
            radius = scene.cloth_solver.reseed_radius
            walked_on = scene.cloth_collider.points
            self._grid.build(walked_on, radius)
            rows = core_slices(n, device, WALK_PER_CORE)
            agreement = self._zeros(arrays, "quality_cloth_walk", (rows, 2), wp.int32)
            launch_on_cores(cloth_kernels.walk_agreement, n,
                            [st.x, 0, 0, walked_on, self._grid.id, st.nearest, cm.inv_mass, radius, agreement],
                            device, first=1, part=2, per_core=WALK_PER_CORE)
            arrays["cloth"] = st.x
            if self._cloth_edges is None or self._cloth_edges[0] is not cm:
                self._cloth_edges = (cm, *_measured_edges(cm))
            parts.append(_cloth_part(n, *self._cloth_edges[1:], body_key, body.faces_np, self.host_meshes))
        if detail:
            points = scene.cloth_detail.positions
            rows = core_slices(len(points), device, PER_CORE)
            count, listed = self._deep(arrays, "detail", len(points), rows)
            launch_on_cores(collision.count_deep_points, len(points),
                            [points, 0, 0, body.fresh_mesh().id, CLOTH_SEARCH, CLOTH_DEPTH, count, listed], device,
                            first=1, part=2, per_core=PER_CORE)
            arrays.update({"cloth_detail": points, "quality_detail_queries": scene.cloth_detail.queries})
            parts.append(_detail_part(len(points), body_key, body.faces_np, self.host_meshes))

        def finish(data):
            stats = {}
            for part in parts:
                stats.update(part(data))
            return stats

        return arrays, finish


class HostMeshes:
    """CPU wp.Meshes over read-back collider poses, one per triangle list and kind of sign, kept from
    frame to frame and refitted to each new pose: building one that signs by the winding number takes
    about 17 ms for the built-in body, refitting it 7 ms (a plain one 0.5 ms), and a pose whose
    self-contact leaves points to re-sign (an arm pressed to the side) mostly lasts for frames."""

    def __init__(self):
        self._meshes = {}  # (id(faces), winding) -> (faces, mesh, the points it was refitted to)

    def get(self, points, faces, winding=False):
        """A mesh of `faces` (kept alive here, so its id names it) over `points`, signing by the
        winding number if asked."""
        points = np.asarray(points, np.float32)
        key = (id(faces), bool(winding))
        entry = self._meshes.get(key)
        if entry is None or entry[2].shape != points.shape:
            mesh = warp_mesh(points, faces, "cpu", winding=winding)
            self._meshes[key] = (faces, mesh, points.copy())
            return mesh
        _, mesh, fitted = entry
        if not np.array_equal(fitted, points):
            mesh.points.assign(points)
            mesh.refit()  # also the winding number's data
            fitted[...] = points
        return mesh


def deep_after_winding(points, body_points, faces, count, listed, search, depth, meshes=None):
    """How many points lie deeper inside the body than depth: of those the pseudo-normal called so
    (count per row, the first of them listed in the row), the ones the winding number calls so too.
    meshes: a HostMeshes to take the body's meshes from (built afresh without)."""
    count = np.asarray(count).reshape(-1)
    if not count.any():
        return 0
    meshes = meshes if meshes is not None else HostMeshes()
    wound_mesh = meshes.get(body_points, faces, winding=True)
    if np.all(count <= listed.shape[1]):
        deep = np.concatenate([row[:c] for row, c in zip(listed, count)])
        wound = signed_distance(points[deep], wound_mesh, "cpu", search, winding=True)[0]
        return int(np.sum(wound < -depth))
    # more than the list holds: every point again, by both signs
    pseudo = signed_distance(points, meshes.get(body_points, faces), "cpu", search)[0]
    wound = signed_distance(points, wound_mesh, "cpu", search, winding=True)[0]
    return int(np.sum((pseudo < -depth) & (wound < -depth)))


def _deep(data, name, points, body_key, faces, search, depth, meshes):
    return deep_after_winding(data[points], data[body_key], faces, data[f"quality_{name}_deep"],
                              data[f"quality_{name}_listed"], search, depth, meshes)


def _hair_part(particles, strand_count, body_key, faces, meshes):
    def hair(data):
        worst = data["quality_hair_worst"].max(axis=0)
        deep = _deep(data, "hair", "hair", body_key, faces, HAIR_SEARCH, HAIR_DEPTH, meshes)
        return {"max_stretch": float(worst[0]), "root_distance_max": float(worst[1]),
                "root_within_5mm": int(data["quality_hair_roots_near"].sum()) / max(1, strand_count),
                "inside_1mm": deep / max(1, particles)}

    return hair


def _measured_edges(cm):
    """The cloth's stretch edges whose strain the statistics report, and their rest lengths."""
    edges = cm.spring_pairs_np[cm.spring_kind_np == 0]
    rest = cm.spring_rest_np[cm.spring_kind_np == 0]
    # the edges the solver moves: one between two pinned particles (a strap bound to a shoulder)
    # stretches with the body's skin, whatever the cloth does
    moved = (cm.inv_mass_np[edges[:, 0]] > 0) | (cm.inv_mass_np[edges[:, 1]] > 0)
    if moved.any():
        edges, rest = edges[moved], rest[moved]
    return edges, rest


def _cloth_part(n, edges, rest, body_key, faces, meshes):
    def cloth(data):
        x = data["cloth"].astype(np.float64)
        strain = np.linalg.norm(x[edges[:, 0]] - x[edges[:, 1]], axis=1) / rest - 1.0
        deep = _deep(data, "cloth", "cloth", body_key, faces, CLOTH_SEARCH, CLOTH_DEPTH, meshes)
        agree, counted = (int(c) for c in data["quality_cloth_walk"].sum(axis=0))
        return {"cloth_stretch_p99": float(np.percentile(strain, 99)), "cloth_stretch_max": float(strain.max()),
                "cloth_inside_2mm": deep / max(1, n), "walk_agreement": agree / counted if counted else 1.0}

    return cloth


def _detail_part(vertices, body_key, faces, meshes):
    def detail(data):
        deep = _deep(data, "detail", "cloth_detail", body_key, faces, CLOTH_SEARCH, CLOTH_DEPTH, meshes)
        queries = data["quality_detail_queries"]
        tested, bvh = int(queries[0::2].sum()), int(queries[1::2].sum())
        return {"detail_inside_2mm": deep / max(1, vertices), "detail_queries": tested / max(1, vertices),
                "detail_bvh": bvh / max(1, tested)}

    return detail
