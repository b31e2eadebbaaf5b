"""Newton peers: the same cloth and hair scenes run by NVIDIA Newton, for the benchmarks to race against.

Newton (PyPI ``newton``, written for 1.8) is NVIDIA's Warp-based physics engine. The runners here take
plain NumPy arrays, build a Newton model, step whole frames and hand positions back as NumPy, so the
benchmark scripts can time Newton and our solvers on identical inputs. Units are SI throughout: metres,
kilograms, seconds; Y is up and gravity defaults to -9.81 m/s^2 along Y (Newton's own default is Z up,
so the builder is created with ``up_axis=Y`` and the gravity vector is passed explicitly).

NewtonCloth
    A triangle-mesh cloth. Particles are the mesh vertices with exactly the caller's masses (pinned
    vertices get mass 0 and lose the ACTIVE flag, Newton's way of holding a particle fixed).

    * ``solver="vbd"``: ``newton.solvers.SolverVBD`` (Vertex Block Descent, implicit). Membrane:
      Newton's StVK-style FEM triangles (``tri_ke``/``tri_ka``/``tri_kd``); bending: Newton's
      dihedral-angle edges (``edge_ke``). The particle graph is coloured with ``builder.color()``
      (VBD solves one colour at a time). Defaults follow Newton's hanging-cloth example:
      tri_ke = tri_ka = 1e3, tri_kd = 1e2, edge_ke = 10.
    * ``solver="xpbd"``: ``newton.solvers.SolverXPBD`` (Jacobi-style XPBD). Membrane: distance springs
      on every mesh edge plus the "across the edge" pairs (the same spring set Newton's
      ``add_cloth_mesh(add_springs=True)`` makes), ke = 1e3 N/m, kd = 1; bending: dihedral edges,
      edge_ke = 10. (XPBD ignores the FEM triangles; they are still added so the model is complete.)
    * ``stretch_stiffness`` multiplies the membrane stiffness (tri_ke/tri_ka for VBD, spring ke for
      XPBD); None means 1.0, i.e. the example defaults.
    * ``body``: a static triangle mesh (``newton.Mesh`` on shape body -1) that particles collide
      with through Newton's particle-shape "soft contacts" (penalty contact in VBD, positional
      contact constraint in XPBD). Cloth vertices collide as spheres of radius ``CLOTH_RADIUS``.

NewtonChains
    Hair strands as particle chains (Newton's way of doing rope with particles): consecutive
    particles of a strand are joined by stiff XPBD distance springs, and particles i and i+2 by
    softer "bending" springs (XPBD handles them the same way; they only resist bending while the
    strand is near straight, and cost one more spring per particle). The first ``pinned_per_strand``
    particles of each strand are fixed (mass 0, inactive). Solver: ``SolverXPBD``. ``head`` is a
    static triangle-mesh collider, as for the cloth body.

How a frame runs (both runners): ``substeps`` times { clear forces; particle-shape collision
detection (``newton.CollisionPipeline.collide``); ``solver.step`` with ``iterations`` solver
iterations }. Collision detection runs once per substep, as Newton's hanging-cloth example does
(the Style3D example detects once per frame instead); without a collider there is no collision
pipeline at all. The pipeline and its contact buffers are created once, in the constructor.

On CUDA the first ``step_frame`` runs eagerly (kernels compile and load, solvers finish lazy set-up),
then one frame of substeps is captured into a CUDA graph with ``wp.ScopedCapture`` and every later
frame is a single ``wp.capture_launch``. The state ping-pong is arranged so the captured frame ends
with the state in the buffer it started from (odd substep counts copy back), so replays chain. On
CPU the frame is just run.

Known differences from our solvers
    * Ours, cloth: explicit RK4 mass-spring cloth, with vertex-vs-body collision against the body.
      Newton's VBD is implicit FEM (one block-Gauss-Seidel sweep per colour per iteration), and
      Newton's XPBD is position-based; both are unconditionally stable at the example's 10
      substeps, so they take far fewer substeps than an explicit integrator needs.
    * Ours, hair: PBD strands with shape matching and follow-the-leader. Newton has neither: its
      chains are XPBD springs solved Jacobi-style (all springs in parallel, corrections summed), so
      with few iterations long strands stretch more than a Gauss-Seidel / FTL solver would.
    * No self-collision in either peer (VBD's particle self-contact is off, and XPBD's
      particle-particle contact is switched off by clearing the model's particle hash grid),
      matching our solvers, which have none either. Newton's hanging-cloth example turns VBD
      self-contact on; it is a large extra cost at 1M particles.
    * Collision is particle-vs-mesh only (no edge or face contact), like our vertex-body test:
      mesh features smaller than the particle spacing can poke through the cloth.

Building is vectorised: particles, triangles, bending edges (``newton.utils.MeshAdjacency``) and
springs are added in bulk (Newton has ``add_particles``/``add_triangles``/``add_edges`` but no bulk
spring call, so springs are appended to the builder's spring tables directly, with the rest
lengths computed in NumPy). Newton's builder still keeps Python lists internally, so building and
finalizing 1M particles takes seconds, not milliseconds; VBD's graph colouring adds more.
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
except Exception as exc:  # pragma: no cover - reported through available()
    wp = None
    newton = None
    _IMPORT_ERROR = exc


def available() -> bool:
    """True when Newton (and Warp) can be imported."""
    return _IMPORT_ERROR is None


# --- Parameters -----------------------------------------------------------------------------------

# Cloth, following Newton's hanging-cloth example.
VBD_TRI_KE = 1.0e3  # membrane stretch (Lame-like, N/m)
VBD_TRI_KA = 1.0e3  # membrane area preservation (N/m)
VBD_TRI_KD = 1.0e2  # membrane damping
XPBD_SPRING_KE = 1.0e3  # edge/shear springs (N/m); XPBD compliance = 1 / ke
XPBD_SPRING_KD = 1.0  # spring damping (N s/m)
CLOTH_EDGE_KE = 10.0  # dihedral bending
CLOTH_EDGE_KD = 0.0
CLOTH_RADIUS = 0.005  # collision radius of a cloth vertex (m)

# Particle-vs-collider contact. VBD averages the model's soft-contact values with the shape's
# material, so both are set to the same numbers.
CONTACT_KE = 1.0e4  # N/m
CONTACT_KD = 1.0e-2
CONTACT_MU = 0.5
CONTACT_GAP = 0.01  # detection distance beyond the particle radius (m); Newton's default

# Hair chains. With a 1e-5 kg particle and dt = 1/240 s the XPBD compliance 1/(ke dt^2) of a
# 1e3 N/m spring is ~1e-4 of the particle's inverse mass: close to inextensible.
CHAIN_STRETCH_KE = 1.0e3
CHAIN_STRETCH_KD = 1.0e-3
CHAIN_BEND_KE = 1.0e-1  # i -- i+2 springs: soft, so strands droop but do not fold sharply
CHAIN_BEND_KD = 0.0


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
        pos=[tuple(p) for p in np.asarray(points, dtype=np.float64).tolist()],
        vel=[(0.0, 0.0, 0.0)] * n,
        mass=mass.tolist(),
        radius=[float(radius)] * n,
        flags=flags.tolist(),
    )


def _add_springs_bulk(builder, i, j, ke, kd):
    """Append springs to the builder's spring tables (what add_spring does, without a Python call
    per spring). Rest lengths come from the current particle positions."""
    i = np.asarray(i, dtype=np.int64)
    j = np.asarray(j, dtype=np.int64)
    q = np.asarray(builder.particle_q, dtype=np.float32)
    rest = np.linalg.norm(q[i] - q[j], axis=1)
    count = len(i)
    builder.spring_indices.extend(np.stack([i, j], axis=1).reshape(-1).tolist())
    builder.spring_stiffness.extend([float(ke)] * count)
    builder.spring_damping.extend([float(kd)] * count)
    builder.spring_control.extend([0.0] * count)
    builder.spring_rest_length.extend(rest.tolist())


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
        elif self.device.is_cuda and self._frames >= 1:
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

        tri_count = len(tris)
        if solver == "vbd":
            tri_ke, tri_ka, tri_kd = VBD_TRI_KE * scale, VBD_TRI_KA * scale, VBD_TRI_KD
        else:
            # XPBD does not solve FEM triangles; keep the example's values for completeness.
            tri_ke, tri_ka, tri_kd = VBD_TRI_KE, VBD_TRI_KA, VBD_TRI_KD
        builder.add_triangles(
            tris[:, 0],
            tris[:, 1],
            tris[:, 2],
            tri_ke=np.full(tri_count, tri_ke),
            tri_ka=np.full(tri_count, tri_ka),
            tri_kd=np.full(tri_count, tri_kd),
            tri_drag=np.zeros(tri_count),
            tri_lift=np.zeros(tri_count),
        )

        # Bending edges [opposite0, opposite1, v0, v1] (opposite1 = -1 on the border).
        edges = newton.utils.MeshAdjacency(tris).edge_indices.astype(np.int64)
        edge_count = len(edges)
        builder.add_edges(
            edges[:, 0],
            edges[:, 1],
            edges[:, 2],
            edges[:, 3],
            edge_ke=[CLOTH_EDGE_KE] * edge_count,
            edge_kd=[CLOTH_EDGE_KD] * edge_count,
        )

        if solver == "xpbd":
            si, sj = _cloth_spring_pairs(edges)
            _add_springs_bulk(builder, si, sj, XPBD_SPRING_KE * scale, XPBD_SPRING_KD)
        else:
            # VBD solves one colour of independent vertices at a time; bending edges couple the
            # two opposite vertices too, so they take part in the colouring.
            builder.color(include_bending=True)

        if body is not None:
            _add_static_mesh(builder, body)

        model = builder.finalize(device=device)
        model.soft_contact_ke = CONTACT_KE
        model.soft_contact_kd = CONTACT_KD
        model.soft_contact_mu = CONTACT_MU
        _disable_particle_particle_contact(model)

        if solver == "vbd":
            sim = newton.solvers.SolverVBD(model, iterations=int(iterations), particle_enable_self_contact=False)
        else:
            sim = newton.solvers.SolverXPBD(model, iterations=int(iterations))
        self._setup(model, sim, frame_dt=frame_dt, substeps=substeps, has_collider=body is not None)


def _cloth_spring_pairs(edges):
    """Unique particle pairs for XPBD cloth springs: each mesh edge, the four edge-to-opposite
    pairs and the opposite-opposite (shear/bend) pair, as add_cloth_mesh(add_springs=True) does."""
    o0, o1, v0, v1 = edges[:, 0], edges[:, 1], edges[:, 2], edges[:, 3]
    has0 = o0 >= 0
    has1 = o1 >= 0
    both = has0 & has1
    a = np.concatenate([v0, o0[has0], o0[has0], o1[has1], o1[has1], o0[both]])
    b = np.concatenate([v1, v0[has0], v1[has0], v0[has1], v1[has1], o1[both]])
    pairs = np.unique(np.stack([np.minimum(a, b), np.maximum(a, b)], axis=1), axis=0)
    return pairs[:, 0], pairs[:, 1]


def _disable_particle_particle_contact(model):
    """Turn off XPBD's particle-particle contact (a hash-grid rebuild and query every substep).

    XPBD runs it whenever particle_max_radius > 0; the per-particle radii used for collider
    contact stay as they are. Our solvers have no self-collision, so neither do the peers."""
    model.particle_max_radius = 0.0
    model.particle_grid = None


# --- Hair chains ----------------------------------------------------------------------------------


class NewtonChains(_NewtonRunner):
    """Hair strands as Newton particle chains.

    Stretch: XPBD distance springs between consecutive particles of a strand, ke = 1e3 N/m.
    Bending: softer XPBD springs between particles i and i+2 of a strand, ke = 0.1 N/m (Newton
    has no particle-only bending element; these springs are its cheapest stand-in).
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
        _add_springs_bulk(builder, stretch, stretch + 1, CHAIN_STRETCH_KE, CHAIN_STRETCH_KD)
        _add_springs_bulk(builder, bend, bend + 2, CHAIN_BEND_KE, CHAIN_BEND_KD)

        if head is not None:
            _add_static_mesh(builder, head)

        model = builder.finalize(device=device)
        model.soft_contact_ke = CONTACT_KE
        model.soft_contact_kd = CONTACT_KD
        model.soft_contact_mu = CONTACT_MU
        _disable_particle_particle_contact(model)

        sim = newton.solvers.SolverXPBD(model, iterations=int(iterations))
        self._setup(model, sim, frame_dt=frame_dt, substeps=substeps, has_collider=head is not None)
