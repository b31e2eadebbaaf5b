"""Sparse particle cloth on an animated body (Oshita & Makinouchi §3): explicit RK4 with bi-phase
springs, vertex-only body collision through a cached nearest body vertex, and following the body.

ClothModel holds the garment's rest shape, masses and springs; ClothState the particles and their
contact caches; ClothSolver.step advances state_in -> state_out by dt with a fixed sequence of
kernel launches. The body is a sim.Collider posed for the end of the step.
"""

from dataclasses import asdict, dataclass
from functools import partial

import numpy as np
import warp as wp

from warp_kernels import cloth as kernels
from warp_kernels import collision, skinning

from .config import require_length_at_most, require_nonnegative, require_positive
from .errors import SimulationError
from .graphs import core_slices, run_parallel

# the body collision of a step is split among the CPU's cores in ranges of at least this many
# particles. A collision costs about 0.7 us per particle, a hand-over between threads tens of
# microseconds, more when the other core has been idle: the paper's dress (332 particles) split in
# two ran 17% faster in frames back to back, but 5% slower with 20 ms idle between frames and 2%
# slower through `cfx run`, so it stays one range (BENCHMARKS.md, session 31)
COLLIDE_PARTICLES_PER_CORE = 2048

STRETCH, SHEAR, BEND = 0, 1, 2

# a GPU steps cloths up to this many particles as one launch of one thread block (kernels.step_in_block):
# the paper's dress (332 particles) spends most of a step of six launches waiting on their latency; a
# block's lane with more than two particles would wait longer in each pass than a launch does
BLOCK_STEP_PARTICLES = 2 * kernels.BLOCK_STEP_LANES


@dataclass(frozen=True)
class ClothParams:
    density: float = 0.15  # kg/m^2 of cloth (cotton 0.1-0.2)
    stretch_stiffness: float = 100.0  # N/m, edge springs longer than rest
    compress_stiffness: float = 2.0  # N/m, edge springs shorter than rest (soft: wrinkles come later)
    shear_stiffness: float = 8.0  # N/m, quad diagonals (same stiffness both ways)
    bend_stiffness: float = 0.6  # N/m, springs across an edge
    spring_damping: float = 0.02  # N s/m, dashpot along every spring
    damping: float = 0.3  # 1/s, global velocity damping
    air_drag: float = 0.3  # kg/(m^2 s), linear drag toward the wind per area of cloth
    wind: tuple = (0.0, 0.0, 0.0)  # m/s, the air's velocity, which air_drag pulls toward
    # gust strength as a fraction of the wind speed: the same smooth noise as the hair's gusts, so a skirt
    # flutters in a steady breeze rather than holding one flared shape
    wind_turbulence: float = 0.0
    wind_turbulence_scale: float = 6.0  # 1/m, spatial frequency of the gusts
    wind_turbulence_rate: float = 1.5  # 1/s, how fast the gust pattern changes
    gravity: tuple = (0.0, -9.81, 0.0)  # m/s^2
    friction: float = 0.4  # Coulomb coefficient at body contact
    collision_margin: float = 0.008  # m, kept outside the body; covers the body bulging between particles
    body_proxy: float = 0.0  # m: collide with the body remeshed this coarse (a collision proxy); 0 = the body mesh
    walk_steps: int = 16  # most steps of the nearest-vertex walk before falling back to the BVH
    teleport: float = 0.05  # m, a particle that moved this far in one step restarts from the BVH
    walk_trust_distance: float = 0.015  # m, farther from the body the walk is re-seeded from the BVH ...
    walk_refresh: int = 8  # ... every this many steps, ...
    reseed_drift: float = 0.003  # m: ... once they have drifted this far relative to the body (0: always)
    body_candidates: int = 64  # body triangles gathered per particle at a concave vertex (0: query the BVH)
    candidate_slack: float = 0.008  # m the particle and body may move before those are gathered again
    follow: bool = True  # move particles with the body before each step (§3.4)
    follow_full_within: float = 0.02  # m: particles this close to the body follow it fully ...
    follow_none_beyond: float = 0.08  # m: ... fading to not at all at this distance
    # spring stretch that strain_iterations Jacobi passes pull each step's springs back to (0.03 = 3%; 0 = off);
    # they approach it and the body's contact has the last word, so some edges end past it: the walking dress
    # at 0.03 keeps 99% of its edges within 3.5% with 4 passes, 3.3% with 8 or 16
    strain_limit: float = 0.0
    strain_iterations: int = 4  # Jacobi passes of the strain limit a step
    substeps: int = 0  # per frame; 0 = from the stability bound
    max_speed: float = 50.0  # m/s, faster particles are reported as an explosion

    def __post_init__(self):
        require_positive(self, "density", "stretch_stiffness", "teleport", "walk_refresh", "max_speed")
        # 100 g and a wind of 200 m/s are past any shot; beyond, a frame moved the particles kilometres
        require_length_at_most(self, "gravity", 1000.0)
        require_length_at_most(self, "wind", 200.0)
        require_nonnegative(self, "compress_stiffness", "shear_stiffness", "bend_stiffness", "spring_damping",
                            "damping", "air_drag", "friction", "collision_margin", "body_proxy", "strain_limit",
                            "strain_iterations", "reseed_drift", "candidate_slack", "wind_turbulence",
                            "wind_turbulence_scale", "wind_turbulence_rate", "walk_steps", "walk_trust_distance",
                            "follow_full_within", "substeps", "body_candidates")
        if self.follow_none_beyond < self.follow_full_within:
            raise ValueError("follow_none_beyond must be at least follow_full_within")

    def as_dict(self):
        return asdict(self)


@dataclass
class ClothState:
    """Positions [m], velocities [m/s] and the body-contact caches that persist between steps."""

    x: wp.array
    v: wp.array
    nearest: wp.array  # cached nearest body vertex per particle (-1: unknown)
    follow: kernels.FollowRecord  # where each particle was last recorded against the body (face -1: none)
    contact: wp.array  # 1 where the particle touched the body in the last step
    clearance: kernels.BodyClearance  # lower bounds of the distance from the body, kept between queries


UNKNOWN = 1.0e30  # a distance never measured is -UNKNOWN, the body's motion since never measured +UNKNOWN


def unknown_clearance(count, device):
    """A kernels.BodyClearance for `count` particles that knows nothing yet: the first pass queries."""
    clearance = kernels.BodyClearance()
    clearance.distance = wp.full(count, -UNKNOWN, dtype=float, device=device)
    clearance.at = wp.zeros(count, dtype=wp.vec3, device=device)
    clearance.body_motion = wp.full(count, UNKNOWN, dtype=float, device=device)
    return clearance


def follow_record(count, device):
    """A kernels.FollowRecord for `count` particles with nothing recorded yet."""
    record = kernels.FollowRecord()
    record.face = wp.full(count, -1, dtype=wp.int32, device=device)
    record.barycentric = wp.zeros(count, dtype=wp.vec3, device=device)
    record.local = wp.zeros(count, dtype=wp.vec3, device=device)
    return record


def body_candidates(count, capacity, device):
    """A kernels.BodyCandidates for `count` particles with room for `capacity` body triangles each,
    nothing gathered yet; capacity 0 makes body_collide query the BVH instead."""
    c = kernels.BodyCandidates()
    c.corners = wp.zeros(max(1, count * capacity), dtype=wp.vec3i, device=device)
    c.distance = wp.zeros(max(1, count * capacity), dtype=float, device=device)
    c.count = wp.full(max(1, count), -1, dtype=wp.int32, device=device)
    c.center = wp.zeros(max(1, count), dtype=wp.vec3, device=device)
    c.radius = wp.zeros(max(1, count), dtype=float, device=device)
    c.body_motion = wp.zeros(max(1, count), dtype=float, device=device)
    c.capacity = capacity
    return c


def rk4_stable_dt(masses, pairs, stiffness, dashpot, decay, fixed=()):
    """The longest explicit RK4 step [s] that keeps every linear mode of a spring network stable,
    with a 10% margin.

    Whatever the particles' positions, a spring's stiffness matrix (k along it, k (1 - rest/length)
    across it) is at most k times the identity, and likewise for its dashpot, so the squared
    frequencies and the decay rates of the free particles (fixed ones do not move) are at most the
    largest eigenvalue of M^-1/2 L M^-1/2, L the graph Laplacian weighted by stiffness (resp.
    dashpot), plus the uniform `decay` [1/s] for the latter. RK4 is stable for |omega dt| <= 2 sqrt(2)
    on the imaginary axis and |lambda dt| <= 2.78 on the real one. The eigenvalues come from Lanczos
    iterations (3 s for a million particles); Gershgorin's row sums, which bound the same
    eigenvalues from above (10-60% loosely on garments), are the fallback.

    masses (P,) [kg]; pairs (S, 2) particle indices; stiffness (S,) [N/m]; dashpot [N s/m] per spring
    or one for all; fixed: indices of particles that do not move.
    """
    masses = np.asarray(masses, np.float64)
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    free = np.ones(len(masses), bool)
    free[np.asarray(fixed, np.int64)] = False
    omega2 = _largest_laplacian_eigenvalue(masses, pairs, np.asarray(stiffness, np.float64), free)
    rate = decay + _largest_laplacian_eigenvalue(masses, pairs, np.broadcast_to(np.asarray(dashpot, np.float64),
                                                                                 (len(pairs),)), free)
    bounds = [2.0 * np.sqrt(2.0) / np.sqrt(omega2) if omega2 > 0.0 else np.inf, 2.78 / rate if rate > 0.0 else np.inf]
    return float(0.9 * min(bounds))


def _largest_laplacian_eigenvalue(masses, pairs, weights, free):
    """Largest eigenvalue of M^-1/2 L M^-1/2 over the free particles (0 when none), from above."""
    import scipy.sparse
    from scipy.sparse.linalg import ArpackNoConvergence, eigsh

    n = len(masses)
    if not free.any() or len(pairs) == 0:
        return 0.0
    i, j = pairs[:, 0], pairs[:, 1]
    a = scipy.sparse.coo_matrix((np.r_[weights, weights], (np.r_[i, j], np.r_[j, i])), shape=(n, n)).tocsr()
    laplacian = scipy.sparse.diags(np.asarray(a.sum(axis=1)).ravel()) - a
    scale = scipy.sparse.diags(1.0 / np.sqrt(masses[free]))
    matrix = (scale @ laplacian[free][:, free] @ scale).tocsr()
    gershgorin = float(np.max(np.asarray(abs(matrix).sum(axis=1)).ravel()))
    if matrix.shape[0] <= 400:
        return min(float(np.linalg.eigvalsh(matrix.toarray())[-1]), gershgorin)
    try:
        value, vector = eigsh(matrix, k=1, which="LA", tol=1e-4, v0=np.ones(matrix.shape[0]))
    except ArpackNoConvergence:
        return gershgorin
    # a Ritz value lies below the eigenvalue it approximates; its residual bounds the distance
    residual = float(np.linalg.norm(matrix @ vector[:, 0] - value[0] * vector[:, 0]))
    return min(float(value[0]) + residual, gershgorin)


class ClothModel:
    """Rest shape, lumped masses and springs of a garment. Build with ClothModel.from_garment or
    directly from triangles and spring pairs."""

    def __init__(self, vertices, triangles, stretch_pairs, shear_pairs, bend_pairs, pinned, params=ClothParams(),
                 device="cpu", name="cloth", face_counts=None, face_indices=None, masses=None):
        """masses [kg] per particle override the lumped masses (density x a third of each face's area)."""
        x = np.asarray(vertices, np.float64)
        tris = np.asarray(triangles, np.int64).reshape(-1, 3)
        self.name, self.device, self.params = name, device, params
        self.num_particles = len(x)
        self.rest_positions_np = x.astype(np.float32)
        self.triangles_np = tris
        self.face_counts_np = np.full(len(tris), 3) if face_counts is None else np.asarray(face_counts)
        self.face_indices_np = tris.reshape(-1) if face_indices is None else np.asarray(face_indices)
        if masses is None:
            area = 0.5 * np.linalg.norm(np.cross(x[tris[:, 1]] - x[tris[:, 0]], x[tris[:, 2]] - x[tris[:, 0]]), axis=1)
            vertex_area = np.bincount(tris.reshape(-1), np.repeat(area / 3.0, 3), minlength=len(x))
            if np.any(vertex_area <= 0.0):
                raise ValueError(f"{name}: {np.count_nonzero(vertex_area <= 0)} vertices belong to no face of "
                                 "positive area")
            self.mass_np = params.density * vertex_area
        else:
            self.mass_np = np.broadcast_to(np.asarray(masses, np.float64), (len(x),)).copy()
        self.pinned_np = np.unique(np.asarray(pinned, np.int64)) if pinned is not None else np.zeros(0, np.int64)
        inv_mass = 1.0 / self.mass_np
        inv_mass[self.pinned_np] = 0.0
        self.inv_mass_np = inv_mass.astype(np.float32)

        p = params
        groups = [(stretch_pairs, STRETCH, p.stretch_stiffness, p.compress_stiffness),
                  (shear_pairs, SHEAR, p.shear_stiffness, p.shear_stiffness),
                  (bend_pairs, BEND, p.bend_stiffness, p.bend_stiffness)]
        pairs, kind, ks, kc = [], [], [], []
        for g, k, k_s, k_c in groups:
            g = np.asarray(g, np.int64).reshape(-1, 2)
            pairs.append(g)
            kind.append(np.full(len(g), k))
            ks.append(np.full(len(g), k_s))
            kc.append(np.full(len(g), k_c))
        pairs = np.concatenate(pairs) if sum(len(g) for g in pairs) else np.zeros((0, 2), np.int64)
        self.spring_pairs_np, self.spring_kind_np = pairs, np.concatenate(kind)
        self.spring_rest_np = np.linalg.norm(x[pairs[:, 0]] - x[pairs[:, 1]], axis=1)
        if np.any(self.spring_rest_np <= 1e-9):
            raise ValueError(f"{name}: {np.count_nonzero(self.spring_rest_np <= 1e-9)} springs have zero rest length")
        k_stretch, k_compress = np.concatenate(ks), np.concatenate(kc)

        # particle -> incident springs (CSR), so the force pass gathers without atomics
        ends = np.concatenate([pairs[:, 0], pairs[:, 1]])
        springs = np.tile(np.arange(len(pairs)), 2)
        order = np.argsort(ends, kind="stable")
        adj_start = np.concatenate([[0], np.cumsum(np.bincount(ends, minlength=len(x)))])

        self.stable_dt = rk4_stable_dt(self.mass_np, pairs, np.maximum(k_stretch, k_compress), p.spring_damping,
                                       p.damping + p.air_drag / p.density, self.pinned_np)

        arr = lambda a, t: wp.array(a, dtype=t, device=device)  # noqa: E731
        self.inv_mass = arr(self.inv_mass_np, float)
        self.drag = arr(np.full(len(x), p.air_drag / p.density, np.float32), float)
        self.adj_start = arr(adj_start.astype(np.int32), wp.int32)
        self.adj_spring = arr(springs[order].astype(np.int32), wp.int32)
        # per adjacency slot: the other particle and the spring's constants, read sequentially by RK4
        slot_spring = springs[order]
        slot_end = np.concatenate([pairs[:, 1], pairs[:, 0]])[order]
        self.adj_other = arr(slot_end.astype(np.int32), wp.int32)
        self.adj_rest = arr(self.spring_rest_np[slot_spring].astype(np.float32), float)
        self.adj_k_stretch = arr(k_stretch[slot_spring].astype(np.float32), float)
        self.adj_k_compress = arr(k_compress[slot_spring].astype(np.float32), float)
        self.adj_damping = arr(np.full(len(slot_spring), p.spring_damping, np.float32), float)
        self.spring_i = arr(pairs[:, 0].astype(np.int32), wp.int32)
        self.spring_j = arr(pairs[:, 1].astype(np.int32), wp.int32)
        self.spring_rest = arr(self.spring_rest_np.astype(np.float32), float)
        self.spring_k_stretch = arr(k_stretch.astype(np.float32), float)
        self.spring_k_compress = arr(k_compress.astype(np.float32), float)
        self.spring_damping = arr(np.full(len(pairs), p.spring_damping, np.float32), float)
        self.spring_limited = arr((self.spring_kind_np == STRETCH).astype(np.int32), wp.int32)
        # the arrays above as the kernels take them
        self.springs = kernels.SpringNetwork()
        for name in kernels.SpringNetwork.vars:
            setattr(self.springs, name, getattr(self, name))
        self.pinned = arr(self.pinned_np.astype(np.int32), wp.int32)
        self.bind_particle = None

    @classmethod
    def from_garment(cls, garment, params=ClothParams(), device="cpu"):
        """A sim.garment.GarmentMesh: edges stretch, quad diagonals shear, bending pairs bend."""
        return cls(garment.vertices, garment.triangles(), garment.edges(), garment.quad_diagonals(),
                   garment.bending_pairs(), garment.pinned, params, device, garment.name,
                   garment.face_counts, garment.face_indices)

    def substeps_for(self, frame_dt):
        """Substeps per frame: the user's, or the fewest that respect the stability bound."""
        if self.params.substeps > 0:
            return self.params.substeps
        return max(1, int(np.ceil(frame_dt / self.stable_dt)))

    def state(self):
        d, n = self.device, self.num_particles
        return ClothState(
            x=wp.array(self.rest_positions_np, dtype=wp.vec3, device=d),
            v=wp.zeros(n, dtype=wp.vec3, device=d),
            nearest=wp.full(n, -1, dtype=wp.int32, device=d),
            follow=follow_record(n, d),
            contact=wp.zeros(n, dtype=wp.int32, device=d),
            clearance=unknown_clearance(n, d),
        )

    def bind_to_mesh(self, mesh_points, mesh_indices):
        """Bind the pinned particles to their closest body triangles (the hair roots' binding)."""
        if len(self.pinned_np) == 0:
            return self
        d = self.device
        pts = wp.array(np.asarray(mesh_points, np.float32), dtype=wp.vec3, device=d)
        idx = wp.array(np.asarray(mesh_indices, np.int32).reshape(-1), dtype=wp.int32, device=d)
        mesh = wp.Mesh(points=pts, indices=idx)
        pinned_x = wp.array(self.rest_positions_np[self.pinned_np], dtype=wp.vec3, device=d)
        self.bind_triangle = wp.zeros(len(self.pinned_np), dtype=wp.int32, device=d)
        self.bind_barycentric = wp.zeros(len(self.pinned_np), dtype=wp.vec3, device=d)
        self.bind_local = wp.zeros(len(self.pinned_np), dtype=wp.vec3, device=d)
        wp.launch(collision.mesh_closest_face, len(self.pinned_np),
                  [pinned_x, mesh.id, 1.0e6, self.bind_triangle, self.bind_barycentric], device=d)
        wp.launch(skinning.compute_bindings, len(self.pinned_np),
                  [pts, idx, self.bind_triangle, self.bind_barycentric, pinned_x, self.bind_local], device=d)
        self.bind_particle = self.pinned
        binding = np.full(self.num_particles, -1, np.int32)
        binding[self.pinned_np] = np.arange(len(self.pinned_np), dtype=np.int32)
        self.particle_binding = wp.array(binding, dtype=wp.int32, device=d)  # binding index or -1
        return self


class ClothSolver:
    """Explicit RK4 (every stage a full force evaluation), then strain limiting, body collision and
    the record for following the body."""

    def __init__(self, model, params=None, parts=None):
        """parts: how many ranges of particles the body collision of a step is split into (set_parts);
        by default one per CPU core with at least COLLIDE_PARTICLES_PER_CORE particles, one on a GPU."""
        self.model = model
        self.params = params or model.params
        d, n = model.device, model.num_particles
        z = lambda: wp.zeros(n, dtype=wp.vec3, device=d)  # noqa: E731
        self.x_stage, self.v_stage, self.x_scratch, self.v_scratch = z(), z(), z(), z()
        self.acc_x, self.acc_v = z(), z()
        self.carried = z()  # how far following moved each particle this step (kernels.begin_step)
        self.set_parts(core_slices(n, d, per_core=COLLIDE_PARTICLES_PER_CORE) if parts is None else parts)
        # far particles re-seed their nearest vertex from the BVH only within this radius: beyond it
        # they neither collide nor follow the body
        p = self.params
        self.reseed_radius = max(2.0 * p.walk_trust_distance, p.follow_none_beyond if p.follow else 0.0) + p.collision_margin
        self.step_count = wp.zeros(1, dtype=wp.int32, device=d)  # on the device: captured frames advance it
        # the wind's gusts at each particle, made once a step (kernels.wind_gusts) where the wind gusts; their
        # time is the device clock plus the step's offset from it, so that a captured frame replays at any time
        self.gusts = z() if p.wind_turbulence > 0.0 else wp.zeros(0, dtype=wp.vec3, device=d)
        self.clock = wp.zeros(1, dtype=float, device=d)
        self._clock_time = 0.0
        self._bad_count = wp.zeros(1, dtype=wp.int32, device=d)
        self._first_bad = wp.zeros(1, dtype=wp.int32, device=d)
        self.candidates = body_candidates(0, 0, d)  # kernels.BodyCandidates, allocated for the first body
        self._candidates_body = None
        # a GPU answers the body's closest-point queries through the wp.Mesh, nearest first, where its BVH
        # is refitted to the pose (not swept: Collider.bvh_stale); the box queries of the triangle BVH
        # (kernels.cloth.closest_in_boxes), which grow until a triangle lies within them, reach many
        # triangles for a far particle, and a launch waits on its slowest thread (the walking dress on an
        # H100: body_collide 0.21 -> 0.09 ms per launch). The CPU keeps the boxes, which need no refit
        # per substep after a sweep
        self.mesh_queries = wp.get_device(d).is_cuda
        # a small cloth on a GPU takes a whole step in one launch of one block (step_in_block; an H100,
        # the paper's dress: 0.97 -> 0.78 ms a frame, the walking dress 9.39 -> 8.65, session 41); the
        # CPU's launches run the body collision on all its cores
        self.block_step = wp.get_device(d).is_cuda and n <= BLOCK_STEP_PARTICLES
        # lanes of that block: one size for every cloth, the one its module is compiled for (each size is
        # a build of the whole module, and its shared memory must fit a block at that size)
        self.block_threads = kernels.BLOCK_STEP_LANES

    def set_parts(self, count):
        """Collide the particles with the body as `count` ranges from now on, side by side on the CPU's
        cores (sim.graphs.run_parallel): the same result, bit for bit. Frames captured with the old
        ranges must be forgotten. Each range counts its BVH queries and gatherings in an element of
        fallbacks of its own, which zeroes them."""
        n = self.model.num_particles
        count = max(1, min(int(count), n))
        self._collide_cuts = [n * k // count for k in range(count + 1)]
        self.fallbacks = wp.zeros(count, dtype=wp.int32, device=self.model.device)

    def _candidates_for(self, body):
        """The gatherings of body triangles for this body: allocated at its first step (a frame's
        first run is eager), forgotten when another body comes."""
        capacity = self.params.body_candidates
        if body is self._candidates_body or capacity == 0:
            return self.candidates
        self.candidates = body_candidates(self.model.num_particles, capacity, self.model.device)
        self._candidates_body = body
        return self.candidates

    def set_clock(self, time):
        """Set the device clock to `time` [s] (e.g. a frame's start, before launching its graph)."""
        self._clock_time = float(time)
        self.clock.fill_(self._clock_time)

    def step(self, state_in, state_out, body, dt, time=0.0):
        """One step of dt from `time` [s] (the wind's gusts are those of that time). `body` (a Collider or
        None) must be posed for the end of the step, its triangle boxes holding that pose
        (Collider.apply_pose refits them, or a sweep of the frame's poses holds them all: Collider.sweep).
        With block_step (a GPU's default for a small cloth) the step is one launch of one thread block,
        the same particles as the launches below."""
        m, p, dev, n = self.model, self.params, self.model.device, self.model.num_particles
        pins = body is not None and m.bind_particle is not None
        if p.wind_turbulence > 0.0:
            wp.launch(kernels.wind_gusts, n, [state_in.x, wp.vec3(*p.wind), p.wind_turbulence, p.wind_turbulence_scale,
                                              p.wind_turbulence_rate, self.clock, float(time - self._clock_time),
                                              self.gusts], device=dev)
        # a strain limit of no passes still collides twice, which the block's step does not do
        if self.block_step and (p.strain_limit == 0.0 or p.strain_iterations > 0):
            self._step_in_block(state_in, state_out, body, dt, pins)
            return
        wp.launch(kernels.begin_step, n,
                  [state_in.x, state_in.v, m.inv_mass, body.points if body else None, body.indices if body else None,
                   int(body is not None and p.follow), state_in.follow, p.follow_full_within, p.follow_none_beyond,
                   int(pins),
                   m.particle_binding if pins else None, body.skin_binding(m) if pins else skinning.SkinBinding(), dt,
                   self.step_count, self.carried],
                  device=dev)
        # RK4 on y = (x, v): stages at 0, dt/2, dt/2, dt, each a full force evaluation; stage states
        # ping-pong between two buffer pairs because neighbours read a stage while it is replaced, and
        # the last stage closes the step into state_out
        x0, v0 = state_in.x, state_in.v
        xs, vs = x0, v0
        buffers = ((self.x_stage, self.v_stage), (self.x_scratch, self.v_scratch))
        for k, (weight, h_next) in enumerate(((1.0, 0.5 * dt), (2.0, 0.5 * dt), (2.0, dt), (1.0, 0.0))):
            last = k == 3
            xn, vn = (state_out.x, state_out.v) if last else buffers[k % 2]
            wp.launch(kernels.rk4_stage, n,
                      [x0, v0, xs, vs, m.inv_mass, m.drag, m.springs, wp.vec3(*p.gravity), wp.vec3(*p.wind),
                       self.gusts, p.damping, weight, h_next, dt if last else 0.0,
                       self.acc_x, self.acc_v, xn, vn], device=dev)
            xs, vs = xn, vn
        if body is not None:
            limit = p.strain_limit > 0.0
            # the follow record is taken by the last collision pass, on the final positions
            self._collide(state_in, state_out, body, dt, record=p.follow and not limit, first=True)
        if p.strain_limit > 0.0:
            self._limit_strain(state_out, dt)
            if body is not None:  # contact has the last word, in the same pose
                self._collide(state_out, state_out, body, dt, record=p.follow, first=False)

    def _step_in_block(self, state_in, state_out, body, dt, pins):
        """step() as one launch of one thread block (kernels.step_in_block), the same particles bit for bit."""
        m, p, n = self.model, self.params, self.model.num_particles
        passes = p.strain_iterations if p.strain_limit > 0.0 else 0
        surface = self.body_surface(body) if body is not None else kernels.BodySurface()
        candidates = self._candidates_for(body) if body is not None else self.candidates
        binding = [m.particle_binding, body.skin_binding(m)] if pins else [None, skinning.SkinBinding()]
        # with a mesh given, its queries answer every closest point: the step compiled without the boxes'
        wp.launch_tiled(kernels.STEP_IN_BLOCK[surface.mesh == 0], dim=[1], inputs=[
            n, state_in.x, state_in.v, m.inv_mass, m.drag, m.springs, wp.vec3(*p.gravity), wp.vec3(*p.wind), self.gusts,
            p.damping, dt, self.x_stage, self.v_stage, self.x_scratch, self.v_scratch, self.acc_x, self.acc_v,
            int(body is not None and p.follow), state_in.follow, p.follow_full_within, p.follow_none_beyond, int(pins),
            *binding, self.step_count, self.carried,
            passes, p.strain_limit,
            int(body is not None), surface, self.contact_params(), state_in.nearest, state_in.clearance, state_out.x,
            state_out.v, state_out.nearest, state_out.clearance, candidates, state_out.contact, self.fallbacks,
            state_out.follow],
            block_dim=self.block_threads, device=m.device)

    def body_surface(self, body):
        """The posed body as the collision kernels read it (kernels.BodySurface). Its mesh is the wp.Mesh
        whose nearest-first queries answer the closest points (its BVH refitted to this pose, with
        mesh_queries), or 0 for the triangle boxes' queries."""
        adj, surface = body.adjacency(), kernels.BodySurface()
        surface.points = body.points
        surface.prev_points = body.prev_points
        surface.indices = body.indices
        surface.vv_start, surface.vv_adj = adj.vv_start, adj.vv_adj
        surface.vf_start, surface.vf_face = adj.vf_start, adj.vf_face
        surface.concave = adj.concave
        surface.bvh = body.triangle_bvh.id
        surface.mesh = body.mesh.id if self.mesh_queries and not body.bvh_stale else 0
        surface.moved = body.moved
        surface.tie = adj.tie
        return surface

    def contact_params(self):
        """The body collision's settings (kernels.BodyContactParams), from params as they are now."""
        p, c = self.params, kernels.BodyContactParams()
        c.max_steps = p.walk_steps
        c.teleport = p.teleport
        c.trust_distance = p.walk_trust_distance
        c.reseed_radius = self.reseed_radius
        c.refresh = max(1, p.walk_refresh)
        c.reseed_drift = p.reseed_drift
        c.margin = p.collision_margin
        c.friction = p.friction
        c.candidate_slack = p.candidate_slack
        return c

    def _collide(self, state_prev, state, body, dt, record, first):
        m = self.model
        candidates = self._candidates_for(body)
        surface = self.body_surface(body)
        inputs = [state.x, state_prev.x, state.v, m.inv_mass, surface, self.contact_params(), self.step_count,
                  int(first), dt, state_prev.nearest, state_prev.clearance, int(record), state.nearest, state.clearance,
                  candidates, state.contact, self.fallbacks, state.follow, self.carried]
        cuts = self._collide_cuts
        # with a mesh given, its queries answer every closest point: the pass compiled without the boxes'
        kernel = kernels.BODY_COLLIDE[surface.mesh == 0]
        run_parallel([partial(wp.launch, kernel, b - a, [*inputs, a, k], device=m.device)
                      for k, (a, b) in enumerate(zip(cuts[:-1], cuts[1:]))])

    def fallback_count(self):
        """BVH queries and gatherings of the body collisions since fallbacks was last zeroed."""
        return int(self.fallbacks.numpy().sum())

    def _limit_strain(self, state, dt):
        """The strain limit's passes on state.x, ping-ponging through the scratch buffers so that the
        last writes state.x, which until then holds the positions before the first (the last pass's
        velocity correction reads them)."""
        m, p, dev, n = self.model, self.params, self.model.device, self.model.num_particles
        passes = p.strain_iterations
        start = state.x
        if passes == 1:  # the one pass cannot read and write state.x
            wp.copy(self.x_stage, state.x)
            start = self.x_stage
        src, spare = start, self.x_scratch
        for k in range(passes):
            last = k == passes - 1
            dst = state.x if last else spare
            wp.launch(kernels.limit_strain, n,
                      [src, m.inv_mass, m.springs, p.strain_limit, start, dt if last else 0.0, state.v, dst],
                      device=dev)
            # the pass's input becomes the next one's spare, except state.x, which only the last writes
            src, spare = dst, (self.x_stage if src is state.x else src)

    def count_unhealthy(self, state):
        """Launch the count of non-finite or too fast particles without waiting: (count, first
        particle) as one-element device arrays, for report_unhealthy once they are read back."""
        from warp_kernels import strands

        self._bad_count.zero_()
        self._first_bad.fill_(np.iinfo(np.int32).max)
        wp.launch(strands.count_unhealthy, self.model.num_particles,
                  [state.x, state.v, self.params.max_speed, self._bad_count, self._first_bad], device=self.model.device)
        return self._bad_count, self._first_bad

    def report_unhealthy(self, bad, first, frame, prim):
        """Raise SimulationError naming the frame and prim if count_unhealthy found any particle."""
        bad = int(np.ravel(bad)[0])
        if bad:
            raise SimulationError(frame, prim, f"{bad} cloth particles are non-finite or faster than "
                                  f"{self.params.max_speed} m/s (first: particle {int(np.ravel(first)[0])})")

    def check_health(self, state, frame, prim):
        bad, first = self.count_unhealthy(state)
        self.report_unhealthy(bad.numpy(), first.numpy(), frame, prim)
