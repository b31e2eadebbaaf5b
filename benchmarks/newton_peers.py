"""Newton peers: the same cloth and hair scenes run by NVIDIA Newton, for the benchmarks to race against.

Newton (PyPI ``newton``, written against 1.8.0 with warp-lang 1.19) is NVIDIA's Warp-based physics
engine. The runners here take plain NumPy arrays, build a Newton model, step whole frames and hand
positions back as NumPy, so the benchmark scripts can time Newton and our solvers on the same inputs.
Units are SI: metres, kilograms, seconds. Y is up: the builder is made with ``up_axis=Y`` and the
gravity vector is passed explicitly (Newton's own default is Z up).

NewtonCloth
    A triangle-mesh cloth. Particles are the mesh vertices with exactly the caller's masses; pinned
    vertices get mass 0 and lose the ACTIVE flag (how Newton's cloth grids fix a vertex).

    * ``solver="vbd"``: ``newton.solvers.SolverVBD`` (Vertex Block Descent: implicit, one local
      Newton step per vertex, colour by colour). Membrane: Newton's FEM triangles; bending: Newton's
      dihedral-angle edges. Defaults from Newton's hanging-cloth example: tri_ke = tri_ka = 1e3 N/m,
      tri_kd = 1e2, edge_ke = 10. The vertex colouring is Newton's (``newton.utils.color_graph`` and
      ``builder.set_coloring``) on the graph ``builder.color(include_bending=True)`` would build.
    * ``solver="xpbd"``: ``newton.solvers.SolverXPBD``. Membrane: distance springs on every mesh
      edge plus the across-the-edge pairs (the spring set of Newton's
      ``add_cloth_mesh(add_springs=True)``); bending: dihedral edges. XPBD solves its constraints
      Jacobi-style and sums the corrections, which diverges when springs are stiff relative to the
      particle masses, so the example's 1e3 N/m / kd 1 springs on 0.1 kg particles are carried over
      as their dimensionless compliance and damping ratios (see ``_xpbd_spring_ke``): per spring,
      ke = m / (36 dt^2) for equal masses m, kd = 0.6 ke dt; edge_ke = 100 * mean particle mass.
      At fine meshes (light particles) this makes the XPBD cloth far softer than the VBD one.
      XPBD ignores the FEM triangles; they are added anyway so the model is a complete cloth.
    * ``stretch_stiffness`` multiplies the membrane stiffness (tri_ke and tri_ka for VBD, spring ke
      for XPBD); None means 1.0, the example values. For XPBD, factors much above ~3 risk the
      Jacobi divergence described above.
    * ``body``: a static triangle mesh (``newton.Mesh`` on body -1) the particles collide with
      through Newton's particle-shape soft contacts (penalty force in VBD, position constraint in
      XPBD), contact ke 1e4 N/m, mu 0.5. Cloth vertices collide as spheres of radius 5 mm
      (``CLOTH_RADIUS``).

NewtonChains
    Hair strands as particle chains: consecutive particles of a strand are joined by XPBD distance
    springs, and particles i and i+2 by soft XPBD "bending" springs (included: they cost one more
    spring per particle, and resist bending only while a strand is near straight). The first
    ``pinned_per_strand`` particles of each strand are fixed (mass 0, inactive). Solver:
    ``SolverXPBD``; ``head`` is a static triangle-mesh collider as for the cloth body. Stretch
    springs are as stiff as XPBD's Jacobi solve allows (each removes half of its error per iteration;
    ke = m / (2 dt^2), ~0.29 N/m for 1e-5 kg particles at dt = 1/240 s), bend springs remove 5%.

How a frame runs (both): ``substeps`` times { clear forces; particle-shape collision detection with
``newton.CollisionPipeline.collide`` (only when there is a collider); ``solver.step`` with
``iterations`` iterations }. Detection runs once per substep, as in Newton's hanging-cloth example
(its Style3D example detects once per frame instead). The pipeline and its contact buffers are made
once, in the constructor.

CUDA graphs: the first ``step_frame`` runs eagerly (kernels load, the solvers do their lazy set-up),
the second captures one frame with ``wp.ScopedCapture`` and launches it, later ones only call
``wp.capture_launch``. The frame always starts and ends in the same state buffer (an odd substep
count copies the result back), so replays chain. XPBD allocates scratch arrays inside ``step``;
Warp's stream-ordered allocator makes that capturable (Newton's own examples capture XPBD the same
way). On CPU the frame simply runs.

Known differences from our solvers
    * Ours, cloth: explicit RK4 mass-spring cloth with vertex-vs-body collision. Newton's VBD and
      XPBD are implicit / position-based and stable at the example's 10 substeps per 1/60 s frame,
      but with a fixed iteration count they do not converge on fine meshes: strain concentrates at
      the pinned vertices (a single pinned vertex carries half the cloth's weight).
    * Ours, hair: PBD strands with shape matching and follow-the-leader, which keeps segment
      lengths exactly. Newton's chains are Jacobi XPBD springs: with 1 iteration and 10 substeps per
      1/24 s frame, a 32-particle strand stretches by tens of percent, more near the root, and
      pushes a little into the head; more iterations or substeps fix most of it.
    * No self-collision in either peer (VBD's particle self-contact is off; XPBD's particle-particle
      contact is switched off by dropping the model's particle hash grid), as in our solvers.
      Newton's hanging-cloth example turns VBD self-contact on.
    * Collision is particle-vs-mesh only, like our vertex-body test: mesh features finer than the
      particle spacing can poke through the cloth.

Building is vectorised: particles, triangles and bending edges go in through Newton's bulk calls
(``add_particles``/``add_triangles``/``add_edges``); Newton has no bulk spring call, so springs are
appended to the builder's spring tables directly. Edges, spring pairs and the colouring graph are
found with one sort of int64 keys. Newton's builder still keeps Python lists and ``finalize`` does
its own mesh analysis, so a 1M-particle cloth takes ~30-40 s to build.

``python benchmarks/newton_peers.py [--device cuda] [--grid N] [--strands S]`` runs a self-test:
hanging cloth, cloth dropped on a sphere, chains on a sphere "head", and on CUDA graph vs eager.
"""

from __future__ import annotations

import numpy as np

try:
    import warp as wp

    # Keep Warp's banner and per-module load lines quiet; must precede wp.init(). Warp 1.19 has
    # log levels (and ignores config.quiet); older Warp only knows config.quiet.
    if hasattr(wp, "LOG_WARNING") and hasattr(wp.config, "log_level"):
        wp.config.log_level = wp.LOG_WARNING
    else:
        wp.config.quiet = True
    import newton

    _IMPORT_ERROR = None
except ImportError as exc:  # reported through available()
    wp = None
    newton = None
    _IMPORT_ERROR = exc


def available() -> bool:
    """True when Newton (and Warp) can be imported."""
    return _IMPORT_ERROR is None


def version() -> str:
    """Newton's version, or "-" when it cannot be imported."""
    return getattr(newton, "__version__", "-") if newton is not None else "-"


# --- Parameters -----------------------------------------------------------------------------------

# Cloth, following Newton's hanging-cloth example (0.1 kg particles, 10 cm cells, dt = 1/600 s).
VBD_TRI_KE = 1.0e3  # membrane stretch (Lame-like, N/m)
VBD_TRI_KA = 1.0e3  # membrane area preservation (N/m)
VBD_TRI_KD = 1.0e2  # membrane damping
VBD_EDGE_KE = 10.0  # dihedral bending
# XPBD springs: the example's 1e3 N/m springs on 0.1 kg particles at dt = 1/600 s have compliance
# ratio 1 / (ke dt^2 (w_i + w_j)) = 18 and damping ratio gamma = kd / (ke dt) = 0.6. We keep those two
# dimensionless numbers (see _xpbd_spring_ke), so the peer behaves like the example for any masses.
XPBD_CLOTH_RATIO = 18.0
XPBD_CLOTH_GAMMA = 0.6
XPBD_EDGE_KE_PER_KG = 10.0 / 0.1  # the example's edge_ke = 10 on 0.1 kg particles, scaled by mass
CLOTH_EDGE_KD = 0.0
CLOTH_RADIUS = 0.005  # collision radius of a cloth vertex (m)

# Particle-vs-collider contact. VBD averages the model's soft-contact values with the shape's
# material, so both are set to the same numbers.
CONTACT_KE = 1.0e4  # N/m
CONTACT_KD = 1.0e-2
CONTACT_MU = 0.5
CONTACT_GAP = 0.01  # detection distance beyond the particle radius (m); Newton's default

# Hair chains, as compliance ratios (see _xpbd_spring_ke). A spring with ratio r removes 1 / (1 + r)
# of its error per iteration. An interior particle has two stretch and two bend springs, plus a
# collider contact (relaxation 0.9); XPBD's Jacobi iterations blow up once the fractions meeting at
# a particle sum to about 2. Measured on 32-particle strands at dt = 1/240 s: stretch fraction 0.78
# is stable in free fall but 0.91 diverges, and 0.75 diverges once strands touch the head mesh,
# while 0.5 stays stable. So 0.5 is about as stiff ("near-inextensible") as Newton's particle
# chains can be made; the remaining stretch comes from Jacobi's slow propagation along a strand
# (it shrinks as iterations go up).
CHAIN_STRETCH_RATIO = 1.0  # 0.5 of the error per iteration
CHAIN_BEND_RATIO = 19.0  # 0.05 of the error per iteration: soft, strands droop
CHAIN_GAMMA = 0.0  # no spring damping


# --- Builder helpers ------------------------------------------------------------------------------


def _new_builder(gravity):
    """A Y-up builder with an explicit gravity vector (Newton's default is Z up)."""
    builder = newton.ModelBuilder(up_axis=newton.Axis.Y, gravity=tuple(float(g) for g in gravity))
    return builder


def _add_particles_bulk(builder, points, masses, pinned, radius):
    """Add all particles in one call; pinned ones get mass 0 and lose the ACTIVE flag."""
    n = len(points)
    mass = np.asarray(masses, dtype=np.float64).copy()
    flags = np.full(n, int(newton.ParticleFlags.ACTIVE), dtype=np.int64)
    pinned = np.asarray(pinned, dtype=np.int64).reshape(-1)
    mass[pinned] = 0.0
    flags[pinned] = 0
    builder.add_particles(
        pos=np.asarray(points, dtype=np.float64).tolist(),
        vel=[(0.0, 0.0, 0.0)] * n,
        mass=mass.tolist(),
        radius=[float(radius)] * n,
        flags=flags.tolist(),
    )


def _xpbd_spring_ke(inv_mass, i, j, dt, ratio):
    """Per-spring XPBD stiffness (N/m) that gives every spring the same compliance ratio.

    SolverXPBD corrects a spring by the fraction 1 / (1 + gamma + ratio) of its error per
    iteration, where ratio = compliance / (w_i + w_j) = 1 / (ke dt^2 (w_i + w_j)) and w are inverse
    masses. Its iterations are Jacobi (all constraints at once, corrections summed without
    averaging), so the fractions summed over the springs meeting at a particle must stay well below
    2 or the solve diverges. A fixed stiffness in N/m would therefore be stable or not depending on
    the caller's masses; fixing the ratio instead makes the behaviour mass-independent."""
    w_sum = inv_mass[i] + inv_mass[j]
    # A spring between two fixed particles does nothing; give it ke = 0 rather than infinity.
    return np.where(w_sum > 0.0, 1.0 / (dt * dt * np.maximum(w_sum, 1e-30) * ratio), 0.0)


def _inverse_masses(masses, pinned):
    """Inverse masses as the solver will see them: 0 for pinned or massless particles."""
    inv = np.zeros(len(masses))
    np.divide(1.0, masses, out=inv, where=masses > 0.0)
    inv[np.asarray(pinned, dtype=np.int64).reshape(-1)] = 0.0
    return inv


def _add_springs_bulk(builder, points, i, j, ke, kd):
    """Append springs to the builder's spring tables (what add_spring does, without a Python call
    per spring). ke, kd: scalars or one value per spring. Rest lengths are the distances in points."""
    count = len(i)
    rest = np.linalg.norm(points[i].astype(np.float32) - points[j].astype(np.float32), axis=1)
    builder.spring_indices.extend(np.stack([i, j], axis=1).reshape(-1).tolist())
    builder.spring_stiffness.extend(np.broadcast_to(np.asarray(ke, dtype=np.float64), (count,)).tolist())
    builder.spring_damping.extend(np.broadcast_to(np.asarray(kd, dtype=np.float64), (count,)).tolist())
    builder.spring_control.extend([0.0] * count)
    builder.spring_rest_length.extend(rest.tolist())


def _unique_pairs(a, b, n):
    """Unique unordered pairs (a, b) of indices below n, via one int64 key each (np.unique on
    rows is several times slower)."""
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    key = np.unique(lo * np.int64(n) + hi)
    return key // n, key % n


def _bending_edges(tris, n):
    """Interior and border edges as rows [opposite0, opposite1, v0, v1] (Newton's bending-edge
    layout; opposite1 = -1 on the border). Triangle (opposite0, v0, v1) and (opposite1, v1, v0) keep
    the mesh's winding. Built with one sort of int64 keys; on a non-manifold edge only the first two
    triangles are used."""
    v0 = tris.reshape(-1)  # half-edge slots: (t0, t1 | t2), (t1, t2 | t0), (t2, t0 | t1)
    v1 = tris[:, [1, 2, 0]].reshape(-1)
    opp = tris[:, [2, 0, 1]].reshape(-1)
    key = np.minimum(v0, v1) * np.int64(n) + np.maximum(v0, v1)
    order = np.argsort(key, kind="stable")
    key = key[order]
    first = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    count = np.diff(np.r_[first, len(key)])
    h0 = order[first]
    second = np.where(count > 1, order[np.minimum(first + 1, len(key) - 1)], -1)
    o1 = np.where(second >= 0, opp[np.maximum(second, 0)], -1)
    return np.stack([opp[h0], o1, v0[h0], v1[h0]], axis=1)


def _add_static_mesh(builder, mesh):
    """A static triangle-mesh collider (shape on body -1) that particles collide with."""
    vertices, faces = mesh
    vertices = np.asarray(vertices, dtype=np.float32)
    faces = np.asarray(faces, dtype=np.int32).reshape(-1)
    cfg = builder.default_shape_cfg.copy()
    cfg.ke = CONTACT_KE
    cfg.kd = CONTACT_KD
    cfg.mu = CONTACT_MU
    # compute_inertia is pointless for a static collider (and slow for big meshes).
    collider = newton.Mesh(vertices, faces, compute_inertia=False)
    return builder.add_shape_mesh(body=-1, mesh=collider, cfg=cfg)


# --- Shared runner --------------------------------------------------------------------------------


def _finalize(builder, collider, device):
    """The model with the static collider mesh (if any), our contact constants and no
    particle-particle contact."""
    if collider is not None:
        _add_static_mesh(builder, collider)
    model = builder.finalize(device=device)
    model.soft_contact_ke = CONTACT_KE
    model.soft_contact_kd = CONTACT_KD
    model.soft_contact_mu = CONTACT_MU
    _disable_particle_particle_contact(model)
    return model


class _NewtonRunner:
    """Owns model, two states, control, optional collision pipeline, solver and the CUDA graph."""

    def _setup(self, model, solver, *, frame_dt, substeps, has_collider):
        self.model = model
        self.solver = solver
        self.device = model.device
        self.frame_dt = float(frame_dt)
        self.substeps = int(substeps)
        self.sim_dt = self.frame_dt / self.substeps
        self.num_particles = int(model.particle_count)

        # Two fixed buffers; a frame always starts from (and, after copy-back, ends in) _state_a.
        self._state_a = model.state()
        self._state_b = model.state()
        self.control = model.control()

        # Created once here: the pipeline allocates its buffers at construction, so collide()
        # is safe to record in a graph.
        self.collision_pipeline = None
        self.contacts = None
        if has_collider:
            self.collision_pipeline = newton.CollisionPipeline(model, soft_contact_gap=CONTACT_GAP)
            self.contacts = self.collision_pipeline.contacts()

        self._graph = None
        self._use_graph = True  # the self-test turns this off to compare graph and eager frames
        self._frames = 0

    def _simulate_frame(self):
        """One frame of substeps. Swaps local references only; ends back in _state_a."""
        s_in, s_out = self._state_a, self._state_b
        for _ in range(self.substeps):
            s_in.clear_forces()
            if self.collision_pipeline is not None:
                self.collision_pipeline.collide(s_in, self.contacts)
            self.solver.step(s_in, s_out, self.control, self.contacts, self.sim_dt)
            s_in, s_out = s_out, s_in
        if s_in is not self._state_a:
            # Odd number of substeps: the result sits in _state_b. Copy it home so that the next
            # frame (or the next graph replay, whose pointers are fixed) reads the new state.
            wp.copy(self._state_a.particle_q, s_in.particle_q)
            wp.copy(self._state_a.particle_qd, s_in.particle_qd)

    def step_frame(self):
        """Advance one frame. On CUDA: frame 1 runs eagerly (warm-up), frame 2 is captured into a
        CUDA graph and launched, later frames only replay the graph."""
        if self._graph is not None:
            wp.capture_launch(self._graph)
        elif self._use_graph and self.device.is_cuda and self._frames >= 1:
            # Kernels are loaded and the solvers' lazy set-up ran in the eager frame. Capture only
            # records the launches, so launch the graph to actually advance this frame.
            with wp.ScopedCapture(device=self.device) as capture:
                self._simulate_frame()
            self._graph = capture.graph
            wp.capture_launch(self._graph)
        else:
            self._simulate_frame()
        self._frames += 1

    def positions(self) -> np.ndarray:
        """(N, 3) float64 copy of the current particle positions."""
        return self._state_a.particle_q.numpy().astype(np.float64)


# --- Cloth ----------------------------------------------------------------------------------------


class NewtonCloth(_NewtonRunner):
    """Triangle-mesh cloth on Newton's VBD or XPBD solver, optionally draped on a static mesh."""

    def __init__(
        self,
        vertices,
        triangles,
        masses,
        pinned,
        *,
        solver="vbd",
        device="cpu",
        gravity=(0.0, -9.81, 0.0),
        frame_dt=1 / 60,
        substeps=10,
        iterations=10,
        body=None,
        stretch_stiffness=None,
    ):
        """vertices (N,3) m, triangles (T,3) int, masses (N,) kg per particle (used as given),
        pinned: indices held fixed. solver: "vbd" or "xpbd". body: None or (vertices (M,3),
        faces (F,3)), a static collider. stretch_stiffness: None for the example defaults, else a
        factor on the membrane stiffness."""
        if not available():
            raise RuntimeError(f"newton is not importable: {_IMPORT_ERROR}")
        if solver not in ("vbd", "xpbd"):
            raise ValueError(f"solver must be 'vbd' or 'xpbd', got {solver!r}")
        self.solver_name = solver
        scale = 1.0 if stretch_stiffness is None else float(stretch_stiffness)

        vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
        tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
        masses = np.asarray(masses, dtype=np.float64).reshape(-1)
        if len(masses) != len(vertices):
            raise ValueError("masses must have one entry per vertex")

        builder = _new_builder(gravity)
        _add_particles_bulk(builder, vertices, masses, pinned, CLOTH_RADIUS)

        sim_dt = float(frame_dt) / int(substeps)
        tri_count = len(tris)
        # XPBD does not solve FEM triangles; they still go in (with the example's values) so the
        # model is a complete cloth.
        tri_ke = VBD_TRI_KE * (scale if solver == "vbd" else 1.0)
        tri_ka = VBD_TRI_KA * (scale if solver == "vbd" else 1.0)
        builder.add_triangles(
            tris[:, 0],
            tris[:, 1],
            tris[:, 2],
            tri_ke=np.full(tri_count, tri_ke),
            tri_ka=np.full(tri_count, tri_ka),
            tri_kd=np.full(tri_count, VBD_TRI_KD),
            tri_drag=np.zeros(tri_count),
            tri_lift=np.zeros(tri_count),
        )

        # Bending edges [opposite0, opposite1, v0, v1] (opposite1 = -1 on the border).
        edges = _bending_edges(tris, len(vertices))
        edge_count = len(edges)
        if solver == "vbd":
            edge_ke = VBD_EDGE_KE
        else:
            free = masses[masses > 0.0]
            edge_ke = XPBD_EDGE_KE_PER_KG * (float(free.mean()) if len(free) else 0.0)
        builder.add_edges(
            edges[:, 0],
            edges[:, 1],
            edges[:, 2],
            edges[:, 3],
            edge_ke=[edge_ke] * edge_count,
            edge_kd=[CLOTH_EDGE_KD] * edge_count,
        )

        if solver == "xpbd":
            si, sj = _cloth_spring_pairs(edges, len(vertices))
            ke = _xpbd_spring_ke(_inverse_masses(masses, pinned), si, sj, sim_dt, XPBD_CLOTH_RATIO / scale)
            _add_springs_bulk(builder, vertices, si, sj, ke, XPBD_CLOTH_GAMMA * ke * sim_dt)
        else:
            # VBD solves one colour of independent vertices at a time. The coupling graph is what
            # builder.color(include_bending=True) builds (triangle edges plus the two opposite
            # vertices of each bending edge), i.e. the same pairs as the XPBD spring set; building
            # it with int64 keys here and calling Newton's colouring directly is ~2x faster than
            # builder.color() at 1M particles.
            gi, gj = _cloth_spring_pairs(edges, len(vertices))
            graph = wp.array(np.stack([gi, gj], axis=1).astype(np.int32), dtype=int, device="cpu")
            builder.set_coloring(newton.utils.color_graph(len(vertices), graph))

        model = _finalize(builder, body, device)

        if solver == "vbd":
            sim = newton.solvers.SolverVBD(model, iterations=int(iterations), particle_enable_self_contact=False)
        else:
            sim = newton.solvers.SolverXPBD(model, iterations=int(iterations))
        self._setup(model, sim, frame_dt=frame_dt, substeps=substeps, has_collider=body is not None)


def _cloth_spring_pairs(edges, n):
    """Unique particle pairs for XPBD cloth springs: each mesh edge, the four edge-to-opposite
    pairs and the opposite-opposite (shear/bend) pair, as add_cloth_mesh(add_springs=True) does."""
    o0, o1, v0, v1 = edges[:, 0], edges[:, 1], edges[:, 2], edges[:, 3]
    has0 = o0 >= 0
    has1 = o1 >= 0
    both = has0 & has1
    a = np.concatenate([v0, o0[has0], o0[has0], o1[has1], o1[has1], o0[both]])
    b = np.concatenate([v1, v0[has0], v1[has0], v0[has1], v1[has1], o1[both]])
    return _unique_pairs(a, b, n)


def _disable_particle_particle_contact(model):
    """Turn off XPBD's particle-particle contact (a hash-grid rebuild and query every substep).

    XPBD runs it whenever particle_max_radius > 0; the per-particle radii used for collider
    contact stay as they are. Our solvers have no self-collision, so neither do the peers."""
    model.particle_max_radius = 0.0
    model.particle_grid = None


# --- Hair chains ----------------------------------------------------------------------------------


class NewtonChains(_NewtonRunner):
    """Hair strands as Newton particle chains.

    Stretch: XPBD distance springs between consecutive particles of a strand, as stiff as the
    Jacobi solve allows (each removes half its error per iteration; ke = m / (2 dt^2) per spring,
    ~0.29 N/m for 1e-5 kg particles at dt = 1/240 s).
    Bending: soft XPBD springs between particles i and i+2 of a strand (5% of the error per
    iteration). Newton has no particle-only bending element; these springs are its cheapest
    stand-in.
    The first ``pinned_per_strand`` particles of every strand are fixed (mass 0, inactive).
    Solver: newton.solvers.SolverXPBD, ``iterations`` Jacobi iterations per substep.
    """

    def __init__(
        self,
        points,
        strand_start,
        *,
        pinned_per_strand=2,
        device="cpu",
        gravity=(0, -9.81, 0),
        frame_dt=1 / 24,
        substeps=10,
        iterations=1,
        head=None,
        particle_radius=0.0005,
        mass=1e-5,
    ):
        """points (P,3) m, strand_start (S+1,) int CSR offsets (strand s = points[start[s]:start[s+1]]).
        head: None or (vertices, faces), a static triangle-mesh collider."""
        if not available():
            raise RuntimeError(f"newton is not importable: {_IMPORT_ERROR}")
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        start = np.asarray(strand_start, dtype=np.int64).reshape(-1)
        n = len(points)
        if start[0] != 0 or start[-1] != n or np.any(np.diff(start) < 0):
            raise ValueError("strand_start must be CSR offsets from 0 to len(points)")

        # Per particle: its strand and its index along the strand, without a loop over strands.
        lengths = np.diff(start)
        strand_of = np.repeat(np.arange(len(lengths)), lengths)
        local = np.arange(n) - start[strand_of]

        pinned = np.nonzero(local < int(pinned_per_strand))[0]
        builder = _new_builder(gravity)
        _add_particles_bulk(builder, points, np.full(n, float(mass)), pinned, particle_radius)

        # Particle p links to p+1 (stretch) and p+2 (bend) when they lie on the same strand.
        idx = np.arange(n)
        stretch = idx[local < lengths[strand_of] - 1]
        bend = idx[local < lengths[strand_of] - 2]
        # Springs between two pinned particles do nothing; leave them out.
        stretch = stretch[local[stretch] + 1 >= pinned_per_strand]
        bend = bend[local[bend] + 2 >= pinned_per_strand]
        sim_dt = float(frame_dt) / int(substeps)
        inv_mass = _inverse_masses(np.full(n, float(mass)), pinned)
        for first, offset, ratio in ((stretch, 1, CHAIN_STRETCH_RATIO), (bend, 2, CHAIN_BEND_RATIO)):
            ke = _xpbd_spring_ke(inv_mass, first, first + offset, sim_dt, ratio)
            _add_springs_bulk(builder, points, first, first + offset, ke, CHAIN_GAMMA * ke * sim_dt)

        model = _finalize(builder, head, device)

        sim = newton.solvers.SolverXPBD(model, iterations=int(iterations))
        self._setup(model, sim, frame_dt=frame_dt, substeps=substeps, has_collider=head is not None)


# --- Self-test ------------------------------------------------------------------------------------


def _sphere_mesh(radius, rings=24, segments=48):
    """Closed UV sphere centred at the origin: (vertices, faces) wound outward."""
    theta = np.linspace(0.0, np.pi, rings + 1)[1:-1]
    phi = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    ring = np.stack([np.sin(t) * np.cos(p), np.cos(t), np.sin(t) * np.sin(p)], -1).reshape(-1, 3)
    verts = np.concatenate([[[0.0, 1.0, 0.0]], ring, [[0.0, -1.0, 0.0]]]) * radius
    r = np.arange(rings - 1)[:, None] * segments + 1
    a = r + np.arange(segments)
    b = r + (np.arange(segments) + 1) % segments
    quads = np.concatenate([np.stack([a[:-1], a[1:], b[1:]], -1), np.stack([a[:-1], b[1:], b[:-1]], -1)])
    top = np.stack([np.zeros(segments, int), b[0], a[0]], -1)
    bottom = np.stack([np.full(segments, len(verts) - 1), a[-1], b[-1]], -1)
    return verts, np.concatenate([top, quads.reshape(-1, 3), bottom])


def _grid_cloth(n, size, height, vertical):
    """n x n grid of 2(n-1)^2 triangles; vertical hangs in the XY plane from y = height + size."""
    u = np.linspace(0.0, size, n)
    a, b = np.meshgrid(u, u, indexing="ij")
    if vertical:
        pts = np.stack([a.ravel() - size / 2, height + b.ravel(), np.zeros(n * n)], 1)
    else:
        pts = np.stack([a.ravel() - size / 2, np.full(n * n, height), b.ravel() - size / 2], 1)
    idx = np.arange(n * n).reshape(n, n)
    q = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)
    return pts, np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]]), idx


def _self_test(device, n, strands, frames, compare=True):
    """Physical checks and timings; on CUDA also graph replay against eager frames."""
    import time

    def timed(runner):
        runner.step_frame()  # warm-up (and, on CUDA, the next call captures)
        runner.step_frame()
        wp.synchronize_device(runner.device)
        t0 = time.perf_counter()
        for _ in range(frames):
            runner.step_frame()
        wp.synchronize_device(runner.device)
        return (time.perf_counter() - t0) / frames * 1e3

    def stretch(x, x0, tris):
        e = np.unique(np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), 1), axis=0)
        strain = np.linalg.norm(x[e[:, 0]] - x[e[:, 1]], axis=1) / np.linalg.norm(x0[e[:, 0]] - x0[e[:, 1]], axis=1) - 1
        return "median {:.3f} p99 {:.3f} max {:.3f}".format(*np.percentile(strain, [50, 99, 100]))

    sphere_r = 0.3
    sphere = _sphere_mesh(sphere_r)
    for solver in ("vbd", "xpbd"):
        pts, tris, idx = _grid_cloth(n, 1.0, 1.0, vertical=True)
        masses = np.full(n * n, 0.2 / (n * n))  # 200 g/m^2
        pins = [idx[0, -1], idx[-1, -1]]
        t0 = time.perf_counter()
        cloth = NewtonCloth(pts, tris, masses, pins, solver=solver, device=device)
        build = time.perf_counter() - t0
        ms = timed(cloth)
        x = cloth.positions()
        print(f"cloth {solver} hanging: N={cloth.num_particles} build {build:.2f} s, {ms:.2f} ms/frame, "
              f"lowest y {x[:, 1].min():.3f} (was 1.0), edge stretch {stretch(x, pts, tris)}, "
              f"pins moved {np.abs(x[pins] - pts[pins]).max():.1e}, finite {np.isfinite(x).all()}")

        pts, tris, _ = _grid_cloth(n, 1.0, sphere_r + 0.05, vertical=False)
        cloth = NewtonCloth(pts, tris, masses, [], solver=solver, device=device, body=sphere)
        lowest = np.inf
        for _ in range(frames + 2):
            cloth.step_frame()
            lowest = min(lowest, float((np.linalg.norm(cloth.positions(), axis=1) - sphere_r).min()))
        print(f"cloth {solver} on sphere: min distance to sphere over {frames + 2} frames {lowest:.4f} m "
              f"(vertex radius {CLOTH_RADIUS})")

        if compare and wp.get_device(device).is_cuda:
            eager = NewtonCloth(pts, tris, masses, [], solver=solver, device=device, body=sphere)
            eager._use_graph = False
            graphed = NewtonCloth(pts, tris, masses, [], solver=solver, device=device, body=sphere)
            for _ in range(6):
                eager.step_frame()
                graphed.step_frame()
            diff = np.abs(eager.positions() - graphed.positions()).max()
            print(f"cloth {solver}: graph vs eager after 6 frames, max |dx| = {diff:.2e} m "
                  f"(graph captured: {graphed._graph is not None})")

    seg, length = 0.005, 32
    rng = np.random.default_rng(0)
    head_r = 0.1
    head = _sphere_mesh(head_r)
    d = rng.normal(size=(strands, 3))
    d[:, 1] = np.abs(d[:, 1]) + 0.5
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    tangent = np.cross(d, [0.0, 1.0, 1e-3])
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    k = np.arange(length)[None, :, None]
    pts = d[:, None] * (head_r + 1e-3 + np.minimum(k, 2) * seg) + tangent[:, None] * np.maximum(k - 2, 0) * seg
    pts = pts.reshape(-1, 3)
    start = np.arange(strands + 1) * length
    t0 = time.perf_counter()
    hair = NewtonChains(pts, start, device=device, head=head)
    build = time.perf_counter() - t0
    ms = timed(hair)
    x = hair.positions().reshape(strands, length, 3)
    seg_stretch = np.linalg.norm(np.diff(x, axis=1), axis=2) / seg - 1
    print(f"chains: {strands} x {length} = {hair.num_particles} particles, build {build:.2f} s, {ms:.2f} ms/frame, "
          f"min distance to head {(np.linalg.norm(x, axis=2) - head_r).min():.4f} m, "
          f"segment stretch mean {seg_stretch.mean():.3f} max {seg_stretch.max():.3f}, "
          f"tip below root {(x[:, 0, 1] - x[:, -1, 1]).mean():.3f} m, finite {np.isfinite(x).all()}")
    if compare and wp.get_device(device).is_cuda:
        # Contacts are appended with atomics, so even two eager runs differ a little; compare
        # graph-vs-eager against eager-vs-eager.
        runs = [NewtonChains(pts, start, device=device, head=head) for _ in range(3)]
        runs[0]._use_graph = runs[1]._use_graph = False
        for _ in range(6):
            for r in runs:
                r.step_frame()
        x0, x1, x2 = (r.positions() for r in runs)
        print(f"chains: after 6 frames max |dx| graph vs eager {np.abs(x2 - x0).max():.2e} m, "
              f"eager vs eager {np.abs(x1 - x0).max():.2e} m (graph captured: {runs[2]._graph is not None})")


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description="Smoke-test the Newton peers (small sizes on cpu).")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--grid", type=int, default=20, help="cloth grid side (particles = grid^2)")
    parser.add_argument("--strands", type=int, default=50)
    parser.add_argument("--frames", type=int, default=10)
    parser.add_argument("--no-compare", action="store_true", help="skip the CUDA graph-vs-eager runs")
    args = parser.parse_args()
    if not available():
        raise SystemExit(f"newton is not importable: {_IMPORT_ERROR}")
    _self_test(args.device, args.grid, args.strands, args.frames, compare=not args.no_compare)
