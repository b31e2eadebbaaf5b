"""Hair strand solver: position-based dynamics with shape matching (Hayashimoto et al. §3.6),
follow-the-leader inextensibility and head collision, one fixed sequence of launches per substep.
"""

from contextlib import contextmanager
from dataclasses import asdict, dataclass
from functools import partial

import numpy as np
import warp as wp

from warp_kernels import collision, skinning, strands

from .config import require_length_at_most, require_nonnegative, require_positive
from .errors import SimulationError
from .graphs import cpu_cores, refit_bvh, run_parallel

SHAPE_MATCHING = {"simplified": 0, "full": 1, "none": -1}
COLLISION = {"none": 0, "sphere_tree": 1, "mesh": 2}
# the ways a scene steps its hair frames (step_frames_as, [scene] hair_frames)
HAIR_FRAMES = ("substeps", "in_block", "in_warps")
# radius [m] of the length pass's mesh queries for particles known to lie no deeper than this inside: a
# mesh query's cost grows fast with its radius (1k strands on the CPU, full+mesh: 216 -> 186 ms/frame
# against querying collision_search = 2 cm; 5 mm re-queries far particles too often to gain more)
PROBE = 0.01
# find_short_lists queues for listing afresh the particles whose bounds come within this of the margin
LIST_SLACK = 0.0005
# the same before strands.step_strands, which queues from the start positions: also covers how far a
# particle travels in the substep (1k strands on the turning head: 1.5 mm at the 99th percentile)
FUSED_LIST_SLACK = 0.002
# strands from which a GPU steps the hair fused with the frame in lane order (HairSolver.fused): a thread
# per strand, so fewer leave most of an H100 idle. Between the 30k strands timed slower (1.06x) and the
# 100k timed faster (0.94x) on an H100, where the two ratios' line crosses 1 (session 41)
FUSED_GPU_STRANDS = 65000
# strand ranges stepped side by side on the CPU: a few per core, so that a core whose own work is done
# (the cloth's frame beside the hair's) takes over ranges that would otherwise wait for the other core
PARTS_PER_CORE = 3
MAX_PARTS = 8


@contextmanager
def cpu_blocks(device):
    """Launches on the CPU within run a block's lanes as fibers (wp.config.enable_cpu_blocks), as
    kernels that share a block's memory need (strands.frame_in_block); a CUDA device always does."""
    if not wp.get_device(device).is_cpu:
        yield
        return
    before = wp.config.enable_cpu_blocks
    wp.config.enable_cpu_blocks = True
    try:
        yield
    finally:
        wp.config.enable_cpu_blocks = before


@dataclass(frozen=True)
class StrandRange:
    """Consecutive whole strands, with their particles and shape-matching windows (which never
    cross strands): the part of the hair one set of launches steps."""

    first_strand: int
    strands: int
    first_particle: int
    particles: int
    first_window: int
    windows: int


def split_strands(model, windows, count):
    """`count` StrandRanges of about equal particle counts covering every strand in order (fewer
    when there are fewer strands)."""
    start = model.strand_start_np
    cuts = np.searchsorted(start, np.linspace(0, model.num_particles, max(1, count) + 1)[1:-1])
    bounds = np.unique(np.r_[0, cuts, model.num_strands])
    ranges = []
    for s0, s1 in zip(bounds[:-1], bounds[1:]):
        p0, p1 = int(start[s0]), int(start[s1])
        w0, w1 = (int(i) for i in np.searchsorted(windows.first_np, [p0, p1]))
        ranges.append(StrandRange(int(s0), int(s1 - s0), p0, p1 - p0, w0, w1 - w0))
    return ranges


def strand_block(strands, device):
    """Lanes per block for the length pass's launch (a thread per strand) on `device`: Warp's 256, or
    on a GPU fewer, down to one warp, where 256 would leave streaming multiprocessors without a block.
    Each thread runs a strand's serial loop and its warp issues mostly for the few lanes that query
    the collider (an H100, 1k strands on the mesh: 4.1 of 32 lanes active), so warps crowded onto few
    SMs share their issue slots: in blocks of 256, 1k strands ran on 4 of the 132 SMs and 10k on 40.
    Smaller blocks: 10k strands, full shape matching on the mesh, 31.4 -> 28.6 ms a frame; 1k about 1%
    (session 41)."""
    d = wp.get_device(device)
    if not d.is_cuda or d.sm_count <= 0:
        return 256
    return int(min(256, max(32, strands // d.sm_count // 32 * 32)))


def length_paths(mode, contact_bounds, mesh_lists):
    """The collision paths (strands.PATHS_*) the length pass takes against collision mode `mode` (with
    HairSolver.contact_bounds and mesh_lists): the pass is compiled with only those, for fewer spilled
    registers."""
    if mode == COLLISION["mesh"] and mesh_lists:
        return strands.PATHS_ALL  # a mesh query goes through a list even without the bounds
    if mode == COLLISION["sphere_tree"] and contact_bounds:
        return strands.PATHS_SPHERE_LISTS
    return strands.PATHS_QUERIES


def fused_fit(mode, variant, contact_bounds, mesh_lists):
    """The key of strands.STEP_STRANDS the fused substep launches against collision mode `mode` with
    shape-matching variant `variant`: the pass compiled with only the collision paths it takes and, where
    it allows, simplified shape matching alone (the same strands, fewer registers spilled on a GPU)."""
    fit = (length_paths(mode, contact_bounds, mesh_lists), variant != SHAPE_MATCHING["full"])
    return fit if fit in strands.STEP_STRANDS else (strands.PATHS_ALL, False)


def deferred_step_modules(params, device):
    """The deferred Warp modules (warp_kernels._options.deferred_module) of the substep a HairSolver with
    `params` steps by default on `device` against a collider, for a first run to compile beside the
    others (warp_kernels.load) rather than at its first frame: the fused substep's variant on a CPU
    (the sphere tree with simplified shape matching, or no collider), a list; None on a CUDA device,
    whose load takes every module by default."""
    from warp_kernels._options import DEFERRED

    if wp.get_device(device).is_cuda:
        return None
    fit = fused_fit(COLLISION[params.collision], SHAPE_MATCHING[params.shape_matching], True, True)
    name = strands.STEP_STRANDS[fit].module.name
    return [name] if name in DEFERRED else []


def _contact_motion(device):
    motion = strands.ContactMotion()
    motion.moved = wp.zeros(1, dtype=wp.int32, device=device)
    motion.rigid = wp.array([np.eye(4)], dtype=wp.mat44, device=device)
    motion.center = wp.zeros(1, dtype=wp.vec3, device=device)
    motion.cells = wp.zeros(strands.MOTION_GRID**3, dtype=wp.int32, device=device)
    return motion


def lanes_by_root(model):
    """(strands,) int32: the strand of each lane, neighbouring roots in neighbouring lanes.

    A warp of the length pass steps 32 lanes together, each step as long as its slowest lane, and
    grooms list their strands in any order (sample_scalp: at random). Strands rooted side by side
    meet the head at about the same particles, so lanes in the order of a k-d tree over the roots'
    rest positions put the strands that collide in the same warps and leave others free (a model of
    the pass's warps over 10k strands on a turning head: 0.47x the collision work of the grown
    order, BENCHMARKS.md)."""
    from scipy.spatial import cKDTree

    roots = model.rest_positions_np[model.strand_start_np[:-1]]
    if len(roots) < 2:
        return np.arange(len(roots), dtype=np.int32)
    return cKDTree(roots, leafsize=8).indices.astype(np.int32)


@dataclass(frozen=True)
class _Lanes:
    """The length pass's arrays in lane order (strands.LaneOrder, lane_slot) over every strand."""

    strands: int
    longest: int  # particles of the longest strand: slots = strands * longest
    order: strands.LaneOrder
    slot: np.ndarray  # (particles,) each particle's slot
    x: wp.array  # vec3 positions, predicted in and resolved out
    prev: wp.array  # vec3 positions at the start of the substep
    v: wp.array  # vec3 velocities out
    inv_mass: wp.array
    rest_length: wp.array


@dataclass(frozen=True)
class HairParams:
    substeps: int = 10  # solver steps per output frame
    gravity: tuple = (0.0, -9.81, 0.0)  # m/s^2 (Y up)
    damping: float = 0.6  # 1/s, velocity decay
    air_drag: float = 2.0  # 1/s, pulls velocity toward the wind velocity
    wind: tuple = (0.0, 0.0, 0.0)  # m/s, the air's velocity, which air_drag pulls toward
    wind_turbulence: float = 0.0  # gust strength as a fraction of the wind speed
    wind_turbulence_scale: float = 6.0  # 1/m, spatial frequency of the gusts
    wind_turbulence_rate: float = 1.5  # 1/s, how fast the gust pattern changes
    shape_matching: str = "full"  # "full" (per-window rotation), "simplified" (the paper), "none"
    shape_stiffness: float = 0.5  # fraction of the way to the goal per pass (at stiffness_rate), (0, 1]
    shape_iterations: int = 2  # goal/apply passes per substep; more passes restore shape faster
    shape_window: int = 0  # particles per window, 2..8; 0 = 3 for simplified (the paper), 6 for full
    rotation_iterations: int = 1  # warm-started Newton steps on each window rotation per pass (full)
    root_stiffness: float = 0.3  # pull toward the groom carried by the root frame, per substep (at stiffness_rate)
    # substeps/s at which shape_stiffness and root_stiffness are given: other substep lengths get the share
    # that gives the same stiffness (as XPBD's compliance), so the look does not depend on the substeps (per
    # share, 160 substeps a frame had held a strand out 5-7 times stiffer than 10)
    stiffness_rate: float = 240.0
    root_hold_length: float = 0.06  # m from the root over which that pull fades to zero
    # share of a particle's follow-the-leader correction taken off its parent's velocity (dynamic FTL), [0.7, 1]:
    # 1 swings a hanging strand at its true period, 0.9 (Mueller et al.) some 5% faster but calms fast tips; at 1
    # a kicked curl without shape matching or damping gains energy (60-340 times), at 0.85 and below a chain's
    # higher modes do (1.1-4x): 0.9-0.95 is where both settle
    ftl_damping: float = 0.9
    collision: str = "mesh"  # "mesh" (wp.Mesh BVH), "sphere_tree" (the paper), "none"
    collision_margin: float = 0.0015  # m, hair kept this far outside the collider
    collision_search: float = 0.02  # m, mesh queries look this far: deeper penetrations go unseen
    max_speed: float = 100.0  # m/s, faster particles are reported as an explosion
    guide_stiffness: float = 20.0  # 1/s, how fast strands take their captured guides' shape ([hair] guides)

    def __post_init__(self):
        if self.shape_matching not in SHAPE_MATCHING:
            raise ValueError(f"shape_matching must be one of {sorted(SHAPE_MATCHING)}")
        if self.collision not in COLLISION:
            raise ValueError(f"collision must be one of {sorted(COLLISION)}")
        if not (0.0 < self.shape_stiffness <= 1.0):
            raise ValueError("shape_stiffness must be in (0, 1]")
        if self.shape_window != 0 and not (2 <= self.shape_window <= 8):
            raise ValueError("shape_window must be 0 (automatic) or 2 to 8")
        if not (0.0 <= self.root_stiffness <= 1.0):
            raise ValueError("root_stiffness must be in [0, 1]")
        if not (0.7 <= self.ftl_damping <= 1.0):
            # below, a free strand gains energy; above, the correction overshoots (tests/test_strand_dynamics)
            raise ValueError("ftl_damping must be in [0.7, 1]")
        if self.rotation_iterations < 1:
            raise ValueError("rotation_iterations must be at least 1")
        if self.shape_iterations < 1:
            raise ValueError("shape_iterations must be at least 1")
        if self.substeps < 1:
            raise ValueError("substeps must be at least 1")
        require_positive(self, "collision_search", "max_speed", "stiffness_rate")
        # 100 g and a wind of 200 m/s are past any shot; beyond, a frame moved the particles kilometres
        require_length_at_most(self, "gravity", 1000.0)
        require_length_at_most(self, "wind", 200.0)
        require_nonnegative(self, "damping", "air_drag", "wind_turbulence", "wind_turbulence_scale",
                            "wind_turbulence_rate", "root_hold_length", "collision_margin", "guide_stiffness")

    def as_dict(self):
        return asdict(self)

    def substep_shares(self, dt):
        """(shape share per pass, root hold share) for substeps of dt: the shares given at substeps of
        1/stiffness_rate s, each read as a constraint of fixed compliance a (share = 1 / (1 + a / dt^2),
        XPBD), which keeps its stiffness at any substep length. A share of 1 (rigid) stays 1."""
        ratio = (1.0 / (self.stiffness_rate * dt)) ** 2

        def share(given):
            return given if given <= 0.0 or given >= 1.0 else 1.0 / (1.0 + (1.0 / given - 1.0) * ratio)

        return share(self.shape_stiffness), share(self.root_stiffness)

    @property
    def window_size(self):
        if self.shape_window:
            return self.shape_window
        # a window of 3 fixes bend angles only; torsion needs 4 or more, and windows spanning most
        # of a curl's turn restore a kicked helix within a few seconds (tests/test_strand_dynamics.py)
        return 3 if self.shape_matching == "simplified" else 6


class HairSolver:
    """Advances a HairModel's state by one substep: state_in -> state_out."""

    def __init__(self, model, params=HairParams(), parts=None):
        """parts: how many StrandRanges to step separately (self.parts); by default a few per CPU
        core on the CPU, where Warp runs a launch on one thread, and one on a GPU."""
        self.model = model
        self.params = params
        device = model.device
        self.windows = model.shape_windows(params.window_size)
        self.whole = StrandRange(0, model.num_strands, 0, model.num_particles, 0, self.windows.count)
        self.reach = model.reach(0, model.num_strands)  # m: how far from the anchor a particle can be
        # how the collider moved near the strands in the substep (strands.contact_motion), measured once
        # for every part: the strands' reach, which sets what it covers, is about the same for any part
        self._motion = _contact_motion(device)
        self._lanes = None
        self.hold = wp.array(model.root_hold_weights(params.root_hold_length), dtype=float, device=device)
        self._particle_order = strands.LaneOrder()  # lanes = 0: the length pass's arrays in particle order
        if parts is None:
            parts = 1 if wp.get_device(device).is_cuda else min(PARTS_PER_CORE * cpu_cores(), MAX_PARTS)
        self.set_parts(parts)
        # per-window rotation of the full variant, refined from its last value (warm start)
        self.rotations = wp.zeros(max(self.windows.count, 1), dtype=wp.quat, device=device)
        # and what its goals need of it (strands.window_frame), for the passes launched apart
        self.frames = wp.zeros(max(self.windows.count, 1), dtype=wp.mat33, device=device)
        self.translations = wp.zeros(max(self.windows.count, 1), dtype=wp.vec3, device=device)
        self._rotations_exact = True
        # contact bounds of the length pass (see strands.follow_the_leader), per particle in the pass's
        # order (set with lanes): clearance (NO_BOUND = unknown, a full query), the four sphere-tree leaves
        # or mesh faces nearest each particle (near_leaves), and a bound on the distance to all others (beyond)
        self.contact_bounds = True  # False queries every particle every substep (same result, slower)
        # walk the sphere tree for the particles whose leaf lists run short in parallel passes before the
        # length pass (strands.find_short_lists, list_leaves_ahead), the same strands: on a GPU the walks
        # then leave the serial loop, where a warp waits for its slowest strand; a CPU runs each strand
        # in turn anyway
        self.leaves_ahead = wp.get_device(device).is_cuda
        # the length pass in lane order (strands.lane_slot) on a GPU, where a warp's strands then read
        # consecutive memory at each step of their serial loops; a CPU thread walks one strand's
        # cache lines and gains nothing from the copies in and out
        self.lanes = wp.get_device(device).is_cuda and len(self.parts) == 1
        # a whole substep in one launch (strands.step_strands); with leaves_ahead the walks are queued
        # from the start positions. On by default on the CPU, where it was measured faster, and on a GPU
        # for simplified shape matching from FUSED_GPU_STRANDS strands, with the frame kept in lane order
        # (frame_lanes below). An H100 against the sphere tree (loose lists, session 41): 100k strands
        # 11.45 ms a frame fused against 12.15 apart, 30k 6.76 against 6.36, 1k 4.08 against 3.24 (a
        # thread per strand leaves most of the GPU idle); full shape matching on the mesh at 100k 50.2
        # against 46.5. In particle order the fused substep's scattered stores cost more (16.75 at 100k)
        self.fused = not wp.get_device(device).is_cuda or (
            self.lanes and model.num_strands >= FUSED_GPU_STRANDS and self.params.shape_matching != "full")
        # mesh collisions through lists of the nearest faces kept with the contact bounds
        # (collision.collide_point_listed_mesh), on the CPU, where they saved 6% of the real-time hair's
        # frame; a GPU queries the BVH, since gathering a list inside the length pass's serial loop kept
        # its warps waiting: 100k strands, full+mesh on an H100, 93.0 ms per frame with the lists, 53.5
        # without (same run, session 34)
        self.mesh_lists = not wp.get_device(device).is_cuda
        # the length pass reads each particle's inputs while the particle before it is placed
        # (strands.FOLLOW_THE_LEADER_AHEAD; the bounded-queries and sphere-list passes): the same strands,
        # the loop's chain no longer waiting on memory at each step, but more live registers. Off: an
        # H100 timed it 1-7% faster, less than loose_lists, which it excludes (session 41)
        self.read_ahead = False
        # the length pass walks the sphere tree only where a particle may be inside a leaf its list does
        # not hold, not wherever one may be within the margin (with leaves_ahead; fused, with simplified
        # shape matching): the margin to such leaves is restored a substep later, by the lists made ahead
        # in parallel (strands.FOLLOW_THE_LEADER_LOOSE, STEP_STRANDS_LOOSE). A walk in the serial loop
        # keeps a warp's other strands waiting: an H100, simplified shape matching on the sphere tree,
        # 14.73 -> 12.15 ms a frame at 100k strands, 4.55 -> 3.24 at 1k (session 41). None: the device's
        # way, loose on a GPU wherever the pass has a loose variant; True insists (an error where it
        # cannot), False never
        self.loose_lists = None
        # a frame's substeps keep the state in lane order (begin_frame, end_frame): the fused substep
        # then reads and writes each strand's state with its warp's strands side by side, where per
        # particle they lie a strand apart, and the copies into and out of the lanes are made once a
        # frame rather than every substep. Needs fused and lanes, and no comb holding strands (whose
        # frames run the fused substep in particle order); on with the GPU's fused substep
        self.frame_lanes = wp.get_device(device).is_cuda and self.fused
        # lanes per block of the length pass (strand_block); a second size builds its module again
        self.strand_block = strand_block(model.num_strands, device)
        # whole frames in one launch each (step_frame, strands.frame_in_block): a block of lanes per strand,
        # a lane per particle, the state in registers across the frame's substeps and the collider posed
        # for all of them ahead. Any shape matching against the sphere tree, the mesh (its BVH queried, as a
        # GPU does) or no collider, strands of up to 64 particles; it reads the strands in particle order,
        # so setting it sets lanes off. With loose_lists (a GPU's default) each lane walks for its own
        # short list ahead of the chain. Off by default until a GPU has timed it (the CPU runs a block's
        # lanes as fibers, for its tests)
        self._frame_in_block = False
        # the frame's layout: a block per strand (a lane per particle), or with frame_warps 32 strands a block
        # side by side (a lane per strand, each warp a run of 4 particles along them: strands.FRAME_IN_WARPS),
        # so that each step of the length pass's chain places a particle of 32 strands at once; frame_layout,
        # a (side, groups, run) of strands.frame_variant, sets any other (a GPU's timings choose), None leaves
        # frame_warps to choose
        self.frame_warps = False
        self.frame_layout = None
        self._longest = int(np.diff(model.strand_start_np).max()) if model.num_strands else 0  # particles
        # (key, FramePoses, per-substep ContactMotion rows, the sphere trees' centres and radii per pose,
        # a wp.Mesh per pose) for step_frame
        self._frame_poses = None
        self._frame = None  # [the lanes' x, v, x', v'; which pair holds the state] for frame_lanes
        self._in_frame = False  # between begin_frame and end_frame with the state in the lanes
        self._no_shape = collision.ColliderShape()  # the length pass without a collider (mode 0)
        self.shape_scratch = wp.zeros(model.num_particles, dtype=wp.vec3, device=device)
        # each strand's root position and frame in the substep's pose (strands.root_frames)
        self.root_origin = wp.zeros(model.num_strands, dtype=wp.vec3, device=device)
        self.root_frame = wp.zeros(model.num_strands, dtype=wp.mat33, device=device)
        self._waxed = bool(model.wax_np.any())  # waxed strands hold their shape even without a root hold
        self._bad_count = wp.zeros(1, dtype=wp.int32, device=device)
        self._first_bad = wp.zeros(1, dtype=wp.int32, device=device)
        # time-dependent forces (gusts, captured guides) read the time from the device, so a frame's
        # launches captured once in a CUDA graph replay at any time: step(time=t) passes t - clock
        self.clock = wp.zeros(1, dtype=float, device=device)
        self._clock_time = 0.0
        self.comb = None  # a sim.comb.CombGrip holding strands, or None
        self._pulled = None  # (guides, dt, rate, strands.GuidePull) last made by _pull

    @property
    def lanes(self):
        """Whether the length pass runs in lane order (strands.lane_slot): the same strands, bit for
        bit. Setting it is set_lanes(on) with the lanes following the roots."""
        return self._lanes is not None

    @lanes.setter
    def lanes(self, on):
        self.set_lanes(on)

    def set_lanes(self, on, by_root=True):
        """Run the length pass in lane order (on) or particle order, the same strands bit for bit.
        by_root puts neighbouring roots in neighbouring lanes (lanes_by_root), else the lanes keep
        the model's strand order. Lane order steps all strands as one range, so it needs one part
        (set_parts(1)); setting it forgets the contact bounds, and frames captured before must be
        forgotten."""
        m, dev = self.model, self.model.device
        if on and len(self.parts) > 1:
            raise ValueError("the length pass in lane order steps all strands as one range: set_parts(1) first")
        self._lanes = None
        slots = m.num_particles
        if on:
            counts = np.diff(m.strand_start_np)
            longest = int(counts.max()) if len(counts) else 0
            slots = m.num_strands * longest
            order = strands.LaneOrder()
            order.lanes = m.num_strands
            strand_of = lanes_by_root(m) if by_root else np.arange(m.num_strands, dtype=np.int32)
            lane_of = np.empty_like(strand_of)
            lane_of[strand_of] = np.arange(len(strand_of), dtype=strand_of.dtype)
            order.strand_of = wp.array(strand_of, dtype=wp.int32, device=dev)
            order.lane_of = wp.array(lane_of, dtype=wp.int32, device=dev)
            # where each particle's slot is, and each slot's particle (-1 past a strand's tip)
            strand = m.particle_strand_np
            slot = (np.arange(m.num_particles) - m.strand_start_np[strand]) * m.num_strands + lane_of[strand]
            particle = np.full(slots, -1, np.int64)
            particle[slot] = np.arange(m.num_particles)
            held = particle >= 0

            def in_lanes(values):
                lane = np.zeros(slots, np.float32)
                lane[held] = np.asarray(values, np.float32)[particle[held]]
                return wp.array(lane, dtype=float, device=dev)

            self._lanes = _Lanes(m.num_strands, longest, order, slot, *(wp.zeros(slots, dtype=wp.vec3, device=dev)
                                                                        for _ in range(3)),
                                 in_lanes(m.inv_mass.numpy()), in_lanes(m.rest_length_np))
        # what strands.step_strands reads per particle and per window, in the length pass's order
        self._slot_of = (self._lanes.slot if on else np.arange(m.num_particles), slots)
        self.slots = self._strand_slots()
        self.clearance = wp.full(slots, strands.NO_BOUND, dtype=float, device=dev)
        self.near_leaves = wp.full(slots, wp.vec4i(-1, -1, -1, -1), dtype=wp.vec4i, device=dev)
        self.beyond = wp.full(slots, strands.NO_BOUND, dtype=float, device=dev)
        self._short = wp.zeros(slots, dtype=wp.int32, device=dev)  # strands.find_short_lists' queue

    def _strand_slots(self):
        """strands.StrandSlots with each particle's values at its slot (self._slot_of: each particle's
        slot, and the number of slots). The groomed offsets are the model's at this call
        (self._slots_root_local): a later bind_to_mesh makes _step_fused build them again."""
        m, dev, win = self.model, self.model.device, self.windows
        slot, slots = self._slot_of
        self._slots_root_local = getattr(m, "root_local", None)

        def arranged(values, dtype, fill=0):
            values = np.asarray(values)
            out = np.full((slots,) + values.shape[1:], fill, values.dtype)
            out[slot] = values
            return wp.array(out, dtype=dtype, device=dev)

        per = strands.StrandSlots()
        per.slots = slots
        per.inv_mass = arranged(m.inv_mass.numpy(), float)
        per.rest_length = arranged(m.rest_length_np, float)
        per.hold = arranged(self.hold.numpy(), float)
        local = self._slots_root_local.numpy() if self._slots_root_local is not None else np.zeros((m.num_particles, 3))
        per.root_local = arranged(local.astype(np.float32), wp.vec3)
        per.window_at = arranged(win.at_np.astype(np.int32), wp.int32, fill=-1)
        # each window's size values at the slot of its first particle, the k-th at k * slots + that slot
        offsets = np.zeros((win.size, slots), np.float32)
        starts = slot[win.first_np]
        offsets[:, starts] = win.offsets_np.reshape(-1, win.size).T
        per.offsets = wp.array(offsets.reshape(-1), dtype=float, device=dev)
        per.rest_local = arranged(win.rest_local_np, wp.vec3)
        rest_centroid = np.zeros((slots, 3), np.float32)
        rest_centroid[starts] = win.rest_centroid_np
        per.rest_centroid = wp.array(rest_centroid, dtype=wp.vec3, device=dev)
        per.centroids = wp.zeros(slots, dtype=wp.vec3, device=dev)
        per.axes = wp.zeros(slots, dtype=wp.vec3, device=dev)
        per.frames = wp.zeros(slots, dtype=wp.mat33, device=dev)
        per.translations = wp.zeros(slots, dtype=wp.vec3, device=dev)
        return per

    def particle_bounds(self):
        """The length pass's contact bounds in particle order, as NumPy: (clearance [m], the four listed
        leaves or faces, the bound on every other one [m]) per particle, whichever order the solver keeps."""
        bounds = (self.clearance.numpy(), self.near_leaves.numpy(), self.beyond.numpy())
        if self._lanes is None:
            return bounds
        return tuple(b[self._lanes.slot] for b in bounds)

    def mesh_clearance(self):
        """(clearance, slot_of) for readers of the particles' distances from the collider's mesh:
        the length pass's contact bounds, lower bounds of each particle's signed distance from the mesh
        as posed for the end of the last substep, at its position then (per slot; slot_of gives each
        particle's slot, None where they are the same), or None where they are not bounds of the mesh
        (another collision mode, or contact_bounds off)."""
        if self.params.collision != "mesh" or not self.contact_bounds:
            return None
        if self._lanes is None:
            return self.clearance, None
        if getattr(self, "_slot_array", (None, None))[0] is not self._lanes:
            self._slot_array = (self._lanes, wp.array(self._lanes.slot.astype(np.int32), dtype=wp.int32,
                                                      device=self.model.device))
        return self.clearance, self._slot_array[1]

    def set_parts(self, count):
        """Step the strands as `count` StrandRanges (self.parts) from now on: the same strands, a
        different share of the CPU's cores. Frames captured with the old ranges must be forgotten."""
        if count > 1 and self.lanes:
            raise ValueError("the length pass in lane order steps all strands as one range: set lanes off first")
        self.parts = split_strands(self.model, self.windows, count)
        # how many particles of each range strands.find_short_lists queued
        self._short_count = {r: wp.zeros(1, dtype=wp.int32, device=self.model.device)
                             for r in [*self.parts, self.whole]}

    def set_clock(self, time):
        """Set the device clock to `time` [s] (e.g. a frame's start, before launching its graph)."""
        self._clock_time = float(time)
        self.clock.fill_(self._clock_time)

    def step(self, state_in, state_out, collider, dt, time=0.0, guides=None, part=None):
        """One substep. The collider must already be posed for the end of the substep, by
        Collider.apply_pose(k): the contact bounds subtract how far that moved it near the strands.
        Guides (a sim.guides.GuideTargets) pull the strands toward captured motion at `time`.

        part: one of self.parts (a StrandRange) steps only those strands. The first part measures
        how the collider moved near the strands, which every part reads, so step the parts of a
        substep in order; branches() gives the same substep as functions that may run at once.

        With self.fused (the CPU's default) the substep is one launch per part after the collider's
        motion (strands.step_strands), with the same strands bit for bit as the launches below.
        Between begin_frame and end_frame (frame_lanes) the state lives in lane order and state_in
        and state_out are neither read nor written."""
        if part is None or part is self.parts[0]:
            self._measure_motion(collider)
        self._step_part(state_in, state_out, collider, dt, time, guides, part)

    def branches(self, state_in, state_out, collider, dt, time=0.0, guides=None):
        """One substep (see step) as branches for sim.graphs.run_parallel: launches the measure of
        how the collider moved near the strands now and returns a function per part that launches
        the rest of the substep for its strands. Each touches only its part's particles and windows,
        so they may run in any order or at the same time (on the CPU's cores); all must run before
        the next substep."""
        self._measure_motion(collider)
        return [partial(self._step_part, state_in, state_out, collider, dt, time, guides, part) for part in self.parts]

    def _step_part(self, state_in, state_out, collider, dt, time, guides, part):
        """step() for one part (None: all strands) once the collider's motion is measured."""
        m, p, dev = self.model, self.params, self.model.device
        r = part if part is not None else self.whole
        offset = float(time - self._clock_time)
        variant = SHAPE_MATCHING[p.shape_matching]
        win = self.windows
        passes = p.shape_iterations if variant >= 0 and win.count > 0 else 0
        if self.fused:
            self._step_fused(state_in, state_out, collider, dt, offset, variant, passes, part, r, guides)
            return
        # shape passes ping-pong between two buffers and must end in state_out.x: an odd number of
        # passes starts from the scratch buffer
        predicted, other = (state_out.x, self.shape_scratch) if passes % 2 == 0 else (self.shape_scratch, state_out.x)
        bound = m.bind_particle is not None and collider is not None
        c = collider
        lane = self._lanes
        lanes = lane.strands if lane is not None else 0
        order = lane.order if lanes else self._particle_order
        shape_share, hold = p.substep_shares(dt)
        hold = hold if p.root_hold_length > 0.0 or self._waxed else 0.0
        skin = c.skin_binding(m) if bound else skinning.SkinBinding()
        if bound and hold > 0.0:
            wp.launch(strands.root_frames, r.strands,
                      [skin, m.root_binding, self.root_origin, self.root_frame, r.first_strand], device=dev)
        wp.launch(strands.predict_positions, r.particles,
                  [state_in.x, state_in.v, m.inv_mass, self._forces(), self.clock, offset, dt, int(bound), skin,
                   m.particle_binding if bound else None, m.particle_strand,
                   self.root_origin, self.root_frame, m.root_local if bound else None, self.hold, hold,
                   predicted, state_out.v, r.first_particle], device=dev)
        if guides is not None and p.guide_stiffness > 0.0:
            wp.launch(strands.follow_guides, r.particles,
                      [predicted, m.inv_mass, m.particle_strand, m.strand_start, self._pull(guides, dt), self.clock,
                       offset, r.first_particle], device=dev)
        src, dst = predicted, other
        exact = int(self._rotations_exact)  # the first pass after a reset solves outright, later ones refine
        for _ in range(passes):
            if variant == SHAPE_MATCHING["full"] and r.windows > 0:
                wp.launch(strands.shape_match_rotations, r.windows,
                          [src, win.first, win.size, win.rest_local, win.rest_centroid, exact, p.rotation_iterations,
                           self.rotations, self.frames, self.translations, r.first_window], device=dev)
                exact = 0
            wp.launch(strands.shape_match_step, r.particles,
                      [src, m.inv_mass, m.particle_strand, win.at, win.size, win.offsets, win.rest_local, self.frames,
                       self.translations, variant, shape_share, m.strand_start, dst, r.first_particle],
                      device=dev)
            src, dst = dst, src
        if variant == SHAPE_MATCHING["full"] and (part is None or part is self.parts[-1]):
            self._rotations_exact = False  # once every part has solved its windows outright
        mode = COLLISION[p.collision] if collider is not None else 0
        x, x_prev, v, inv_mass, rest = state_out.x, state_in.x, state_out.v, m.inv_mass, m.rest_length
        if lanes:
            wp.launch(strands.to_lanes, lane.strands * lane.longest,
                      [state_out.x, state_in.x, m.strand_start, order, lane.x, lane.prev], device=dev)
            x, x_prev, v, inv_mass, rest = lane.x, lane.prev, lane.v, lane.inv_mass, lane.rest_length
        contact = self.strand_contact(c, mode)
        if mode != 0 and self.contact_bounds and self.leaves_ahead and mode != COLLISION["mesh"]:
            dim, first = (lane.strands * lane.longest, 0) if lanes else (r.particles, r.first_particle)
            count = self._short_count[r]
            count.zero_()
            wp.launch(strands.find_short_lists, dim,
                      [x, x_prev, m.particle_strand, m.strand_start, m.pinned_per_strand, contact, LIST_SLACK, order,
                       0, first, count, self._short], device=dev)
            wp.launch(strands.list_leaves_ahead, dim,
                      [x_prev, contact, count, self._short, first, m.strand_start, order, 0], device=dev)
        paths = self._length_paths(mode)
        length_passes = strands.FOLLOW_THE_LEADER_AHEAD if self.read_ahead and paths != strands.PATHS_ALL else (
            strands.FOLLOW_THE_LEADER)
        length_pass = length_passes[paths]
        if self._loose(self.leaves_ahead and not self.read_ahead) and paths == strands.PATHS_SPHERE_LISTS:
            if not self.leaves_ahead or self.read_ahead:
                raise ValueError("loose_lists restores the margin through the lists made ahead (leaves_ahead on) "
                                 "and is compiled reading in turn (read_ahead off)")
            length_pass = strands.FOLLOW_THE_LEADER_LOOSE[paths]
        wp.launch(length_pass, r.strands,
                  [x, x_prev, inv_mass, m.strand_start, rest, m.pinned_per_strand, contact,
                   p.ftl_damping, dt, v, order, r.first_strand], device=dev, block_dim=self.strand_block)
        if lanes:
            wp.launch(strands.from_lanes, lane.strands * lane.longest,
                      [lane.x, lane.v, m.strand_start, order, lane.longest, state_out.x, state_out.v], device=dev)
        self._comb(state_in, state_out, contact, dt, offset, order, r)

    def strand_contact(self, c, mode):
        """Collider c as the length pass meets it in collision mode `mode` (strands.StrandContact), with
        this solver's contact bounds."""
        p = self.params
        contact = strands.StrandContact()
        contact.mode = mode
        contact.shape = c.shape if c else self._no_shape
        contact.margin = p.collision_margin
        contact.search = p.collision_search
        # a sphere-tree query costs little more for a longer reach, and its nearest-leaf list then lasts longer
        contact.probe = min(PROBE, p.collision_search) if mode == COLLISION["mesh"] else p.collision_search
        contact.use_bounds = int(self.contact_bounds)
        contact.mesh_lists = int(self.mesh_lists)
        contact.motion = self._motion
        contact.strand_reach = self.reach
        contact.clearance, contact.near_leaves, contact.beyond = self.clearance, self.near_leaves, self.beyond
        return contact

    def _length_paths(self, mode):
        return length_paths(mode, self.contact_bounds, self.mesh_lists)

    def _forces(self):
        """The parameters' forces as the kernels take them (strands.StrandForces)."""
        p = self.params
        forces = strands.StrandForces()
        forces.gravity, forces.wind = wp.vec3(*p.gravity), wp.vec3(*p.wind)
        forces.air_drag, forces.damping = p.air_drag, p.damping
        forces.turbulence, forces.turbulence_scale = p.wind_turbulence, p.wind_turbulence_scale
        forces.turbulence_rate = p.wind_turbulence_rate
        return forces

    def _pull(self, guides, dt):
        """The guides' strands.GuidePull for substeps of dt (stiffness 0: none), kept for the last
        guides, dt and rate asked for."""
        rate = self.params.guide_stiffness if guides is not None else 0.0
        if self._pulled is None or self._pulled[:3] != (guides, dt, rate):
            pull = guides.pull(1.0 - np.exp(-rate * dt)) if rate > 0.0 else strands.GuidePull()
            self._pulled = (guides, dt, rate, pull)
        return self._pulled[3]

    def _measure_motion(self, c):
        """Launch the measure of how collider c moved near the strands this substep
        (strands.contact_motion) into self._motion, for the contact bounds of the length pass; and
        where the strands query c's mesh and its BVH was left stale (Collider.apply_pose(k,
        refit=False)), its refit beside the measure, which does not read it: on the CPU's cores at
        once (sim.graphs.run_parallel), where the refit alone would leave all but one idle."""
        mode = COLLISION[self.params.collision] if c is not None else 0
        refit = mode == COLLISION["mesh"] and c.bvh_stale
        measure = mode != 0 and self.contact_bounds
        if refit and measure:
            # the longer branch first: this thread takes it while a helper wakes for the other
            run_parallel([partial(self._launch_motion, c, mode), c.refit_mesh])
        elif refit:
            c.refit_mesh()
        elif measure:
            self._launch_motion(c, mode)

    def _launch_motion(self, c, mode, motion=None):
        m, p, dev = self.model, self.params, self.model.device
        motion, adjacency = self._motion if motion is None else motion, c.adjacency()
        wp.launch(strands.anchor_frame, strands.MOTION_GRID ** 3,
                  [c.prev_points, c.points, c.indices, m.anchor_face, motion], device=dev)
        mesh = mode == COLLISION["mesh"]  # the sphere tree's strands see only its leaves
        wp.launch(strands.contact_motion, (len(c.points) if mesh else 0) + len(c.sphere_centers),
                  [c.prev_points, c.points, c.prev_sphere_centers, c.sphere_centers, c.sphere_radii,
                   c.sphere_is_leaf, adjacency.vv_start, adjacency.vv_adj, int(m.anchor_face >= 0), int(mesh),
                   self.reach, p.collision_search, motion], device=dev)

    def _comb(self, state_in, state_out, contact, dt, offset, order, r):
        if self.comb is not None:  # held strands, blending the comb's move across the frame's substeps
            blend = min(max(offset / (dt * self.params.substeps), 0.0), 1.0) if dt > 0.0 else 1.0
            self.comb.launch(self.model, state_out, state_in, blend, dt, contact, order, r)

    def _loose(self, available):
        """Whether this substep's length pass takes the loose lists (loose_lists): its own setting, or
        with None a GPU's way wherever the pass has a loose variant (available)."""
        if self.loose_lists is None:
            return wp.get_device(self.model.device).is_cuda and available
        return bool(self.loose_lists)

    def begin_frame(self, state):
        """Start a frame of substeps that keeps the state in lane order (frame_lanes, with fused and
        lanes; otherwise nothing happens): state is copied into the lanes here, the substeps' step()
        then read and write only the lanes, not their state_in and state_out, and end_frame copies the
        result back. Nothing may read or change the states between the two."""
        lane = self._lanes
        if not (self.frame_lanes and self.fused and lane is not None and self.comb is None):
            return
        if self._frame is None or len(self._frame[0][0]) != lane.strands * lane.longest:
            slots, dev = lane.strands * lane.longest, self.model.device
            self._frame = [[wp.zeros(slots, dtype=wp.vec3, device=dev) for _ in range(4)], 0]
        buffers = self._frame[0]
        self._frame[1] = 0
        wp.launch(strands.to_lanes, len(buffers[0]),
                  [state.x, state.v, self.model.strand_start, lane.order, buffers[0], buffers[1]],
                  device=self.model.device)
        self._in_frame = True

    def end_frame(self, state):
        """End the frame begin_frame started: the lanes' state copied back into state."""
        if not self._in_frame:
            return
        buffers, at = self._frame
        lane = self._lanes
        wp.launch(strands.from_lanes, len(buffers[0]),
                  [buffers[2 * at], buffers[2 * at + 1], self.model.strand_start, lane.order, lane.longest, state.x,
                   state.v], device=self.model.device)
        self._in_frame = False

    @property
    def frame_in_block(self):
        """Whether the scene steps this solver's frames with step_frame (strands.frame_in_block), a launch
        a frame; while a comb holds strands it steps substeps. Setting it on sets lanes off (the kernel
        reads the strands in particle order); frames captured before must be forgotten
        (sim.graphs.FrameGraphs.clear)."""
        return self._frame_in_block

    @frame_in_block.setter
    def frame_in_block(self, on):
        if on and self.lanes:
            self.set_lanes(False)
        self._frame_in_block = bool(on)

    def step_frames_as(self, way):
        """Step the scene's frames as `way` ([scene] hair_frames, one of HAIR_FRAMES) names: "substeps" a
        substep at a time (step), "in_block" a launch a frame with a block per strand (step_frame), "in_warps"
        a launch a frame with 32 strands a block (frame_warps)."""
        if way not in HAIR_FRAMES:
            raise ValueError(f"hair frames are stepped as one of {', '.join(HAIR_FRAMES)}, not {way!r}")
        self.frame_in_block = way != "substeps"
        self.frame_warps = way == "in_warps"

    def frame_layout_used(self):
        """The (side, groups, run) layout step_frame launches (strands.frame_variant): frame_layout where set,
        else FRAME_IN_WARPS' with frame_warps, else a block per strand of the fewest lanes that hold the
        longest strand (the most lanes where none does)."""
        if self.frame_layout is not None:
            return tuple(int(n) for n in self.frame_layout)
        if self.frame_warps:
            return strands.FRAME_IN_WARPS_LAYOUT
        return 1, min([n for n in strands.FRAME_LANES if n >= self._longest] or [max(strands.FRAME_LANES)]), 1

    def frame_in_block_misfit(self, collider):
        """Why step_frame cannot step this solver's frames against `collider` (a line naming the way they
        are stepped, as [scene] hair_frames does), or None."""
        p, longest = self.params, self._longest
        layout = self.frame_layout_used()
        if self.frame_layout is not None:
            way = f"hair frames in layout {'x'.join(map(str, layout))}"
        else:
            way = f"hair frames {'in_warps' if self.frame_warps else 'in_block'}"
        if strands.frame_layout_misfit(layout) is not None:
            return f"{way}: {strands.frame_layout_misfit(layout)}"
        _side, groups, run = layout
        if self.comb is not None:
            return f"{way} do not step strands held by a comb"
        if p.substeps > strands.FRAME_SUBSTEPS:
            return f"{way} take at most {strands.FRAME_SUBSTEPS} substeps a frame, not {p.substeps}"
        if longest > groups * run:
            return f"{way} take strands of at most {groups * run} particles, not {longest}"
        if self.lanes:
            return f"{way} read the strands in particle order: set lanes off"
        if self.loose_lists and not self.contact_bounds and collider is not None and p.collision == "sphere_tree":
            return f"{way} keep the loose lists with the contact bounds: set contact_bounds on"
        return None

    def step_frame(self, state_in, state_out, collider, dt, times, guides=None, listed=None):
        """A whole frame of len(times) - 1 substeps of dt in one launch (strands.frame_in_block, laid out as
        frame_layout_used says), the same strands bit for bit as step() at each substep
        (times: the substeps' ends, after the frame's start). The collider is posed here for the end of
        every substep, Collider.apply_pose(k) for k = 1, 2, ... without refits (the sphere tree and the
        skin only), listed vertices only (an int32 array, or None for all) at every pose but the last;
        it must be at the frame's first pose (times[0]) on entry and is left at its last.
        Raises ValueError where frame_in_block_misfit names a reason."""
        misfit = self.frame_in_block_misfit(collider)
        if misfit is not None:
            raise ValueError(misfit)
        m, p, dev = self.model, self.params, self.model.device
        substeps = len(times) - 1
        mode = COLLISION[p.collision] if collider is not None else 0
        bound = m.bind_particle is not None and collider is not None
        poses = self._pose_frame(collider, times, listed, mode, bound)
        shape_share, hold = p.substep_shares(dt)
        hold = hold if p.root_hold_length > 0.0 or self._waxed else 0.0
        variant = SHAPE_MATCHING[p.shape_matching]
        passes = p.shape_iterations if variant >= 0 and self.windows.count > 0 else 0
        if getattr(m, "root_local", None) is not self._slots_root_local:
            self.slots = self._strand_slots()  # bound to a mesh since the slots were made
        paths = {0: strands.PATHS_NONE, COLLISION["sphere_tree"]: strands.PATHS_SPHERE_LISTS,
                 COLLISION["mesh"]: strands.PATHS_QUERIES}[mode]
        # loose lists (loose_lists, a GPU's way): each lane walks for its own list ahead of the chain
        loose = mode == COLLISION["sphere_tree"] and self.contact_bounds and self._loose(True)
        contact = self.strand_contact(collider, mode)
        skin = collider.skin_binding(m) if bound else skinning.SkinBinding()

        # one launch for every strand: the CPU's fibers share one arena for the blocks' memory, which
        # launches of the parts side by side on its cores overflow
        simplified = variant != SHAPE_MATCHING["full"]
        layout = self.frame_layout_used()
        side, groups, _run = layout
        kernel = strands.frame_variant(layout, paths, loose, simplified)
        with cpu_blocks(dev):
            wp.launch_tiled(kernel, dim=[-(-m.num_strands // side)], block_dim=side * groups, device=dev,
                            inputs=[state_in.x, state_in.v, m.strand_start, m.pinned_per_strand, self._forces(),
                                    self.clock, poses, substeps, dt, int(bound), skin,
                                    m.particle_binding if bound else None, m.root_binding if bound else None,
                                    hold if bound else 0.0, self._pull(guides, dt), self.windows.size, variant,
                                    passes, shape_share, int(self._rotations_exact), p.rotation_iterations,
                                    self.rotations, self.slots, contact, p.ftl_damping, FUSED_LIST_SLACK,
                                    state_out.x, state_out.v, 0])
        if variant == SHAPE_MATCHING["full"] and passes > 0:
            self._rotations_exact = False  # the later frames refine the rotations from their last values

    def _pose_frame(self, c, times, listed, mode, bound):
        """strands.FramePoses of collider c for the frame's substeps, row 0 its pose on entry and row k
        pose k: a skinned collider's poses made at once (_skin_frame), others applied in turn (see
        step_frame) and what the substeps read of each copied into its row; the collider's motion near
        the strands measured into them where the contact bounds need it, and against the mesh a BVH
        refitted to each pose. The collider is left at the last pose, every vertex posed (and its own
        BVH refitted where the strands query the mesh)."""
        dev = self.model.device
        substeps = len(times) - 1
        mesh = mode == COLLISION["mesh"]
        vertices = len(c.points) if bound or mesh else 1
        nodes = len(c.sphere_nodes) if mode != 0 else 0
        key = (substeps, vertices, nodes, mesh)
        if self._frame_poses is None or self._frame_poses[0] != key:
            poses = strands.FramePoses()
            poses.points = wp.zeros((substeps + 1, vertices), dtype=wp.vec3, device=dev)
            poses.spheres = wp.zeros((substeps + 1, max(nodes, 1)), dtype=wp.vec4, device=dev)
            poses.moved = wp.zeros((substeps, 1), dtype=wp.int32, device=dev)
            poses.rigid = wp.zeros((substeps, 1), dtype=wp.mat44, device=dev)
            poses.center = wp.zeros((substeps, 1), dtype=wp.vec3, device=dev)
            poses.cells = wp.zeros((substeps, strands.MOTION_GRID ** 3), dtype=wp.int32, device=dev)
            rows = []
            for k in range(substeps):
                motion = strands.ContactMotion()
                motion.moved, motion.rigid, motion.center = poses.moved[k], poses.rigid[k], poses.center[k]
                motion.cells = poses.cells[k]
                rows.append(motion)
            # the sphere tree's centres and radii of each pose (_skin_frame)
            trees = [wp.zeros((substeps + 1, max(nodes, 1)), dtype=t, device=dev) for t in (wp.vec3, float)]
            # a BVH over each pose's row of points (not row 0: no substep queries the frame's start), built
            # where the collider's own was, at the rest pose, so that refitted to a pose it answers a query
            # as the collider's does, equidistant triangles included
            meshes = []
            for k in range(1, substeps + 1 if mesh else 1):
                wp.copy(poses.points[k], c.rest_points)
                meshes.append(wp.Mesh(points=poses.points[k], indices=c.indices))
            poses.meshes = wp.array([0] + [each.id for each in meshes] if mesh else [0] * (substeps + 1),
                                    dtype=wp.uint64, device=dev)
            self._frame_poses = (key, poses, rows, trees, meshes)
        _, poses, rows, trees, meshes = self._frame_poses
        offsets = np.zeros(strands.FRAME_SUBSTEPS, np.float32)
        offsets[:substeps] = [float(t - self._clock_time) for t in times[1:]]
        poses.offsets = strands.frame_offsets(*offsets)
        if c is None:
            return poses
        if c.bone_matrices is not None and c._swept is None:
            self._skin_frame(c, poses, trees, substeps, listed, mode, bound, nodes)
        else:
            for k in range(1, substeps + 1):  # point caches: the poses as the substeps one by one apply them
                c.apply_pose(k, refit=False, listed=None if k == substeps or mesh else listed)
                if bound or mesh:
                    wp.copy(poses.points[k], c.points)
                if nodes > 0:
                    wp.copy(poses.spheres[k], c.sphere_nodes)
                if mode != 0 and self.contact_bounds:
                    self._launch_motion(c, mode, rows[k - 1])
        for each in meshes:
            refit_bvh(each)
        if mesh:
            c.refit_mesh()  # the BVH the host queries after the frame, at its last pose
        return poses

    def _skin_frame(self, c, poses, trees, substeps, listed, mode, bound, nodes):
        """A skinned collider's poses for every substep of a frame in six launches (strands.FRAME_POSES:
        the listed vertices, the sphere tree skinned, refitted and packed, the motions), where applying
        them in turn takes some ten launches and copies a substep: the same rows. The collider is left
        at the frame's last pose, every vertex skinned, as the substeps leave it (its pose before is the
        frame's first)."""
        m, p, dev = self.model, self.params, self.model.device
        centers, radii = trees
        mesh = mode == COLLISION["mesh"]
        if bound or mesh:
            wp.copy(poses.points[0], c.points)
            if listed is None or mesh:
                if getattr(self, "_every_vertex", None) is None or len(self._every_vertex) != len(c.points):
                    self._every_vertex = wp.array(np.arange(len(c.points), dtype=np.int32), device=dev)
                listed = self._every_vertex
            wp.launch(strands.skin_listed_poses, (substeps, len(listed)),
                      [c.rest_points, c.skin_indices, c.skin_weights, c.bone_matrices, c.num_bones, listed,
                       poses.points], device=dev)
        if nodes > 0:
            wp.copy(centers[0], c.sphere_centers)
            wp.launch(strands.skin_sphere_poses, (substeps, nodes),
                      [c.sphere_rest_centers, c.sphere_skin_indices, c.sphere_skin_weights, c.bone_matrices,
                       c.num_bones, c.sphere_radii, c.sphere_is_leaf, centers, radii], device=dev)
            wp.launch(strands.refit_sphere_poses, (substeps, nodes),
                      [centers, radii, c.sphere_parent, c.sphere_is_leaf], device=dev)
            wp.launch(strands.pack_sphere_poses, (substeps, nodes), [centers, radii, poses.spheres], device=dev)
        if mode != 0 and self.contact_bounds:
            motion = [poses.moved, poses.rigid, poses.center, poses.cells]
            wp.launch(strands.anchor_frames, (substeps, strands.MOTION_GRID ** 3),
                      [poses.points, c.indices, m.anchor_face, *motion], device=dev)
            adjacency = c.adjacency()
            # the sphere tree's strands see only its leaves, the mesh's its vertices and leaves
            wp.launch(strands.contact_motions, (substeps, (len(c.points) if mesh else 0) + nodes),
                      [poses.points, centers, radii, c.sphere_is_leaf, adjacency.vv_start, adjacency.vv_adj,
                       int(m.anchor_face >= 0), int(mesh), self.reach, p.collision_search, *motion], device=dev)
        c.apply_pose(substeps, refit=False)

    def _step_fused(self, state_in, state_out, c, dt, offset, variant, passes, part, r, guides):
        """step() as one launch per range (strands.step_strands), after the collider's motion."""
        m, p, dev = self.model, self.params, self.model.device
        mode = COLLISION[p.collision] if c is not None else 0
        bound = m.bind_particle is not None and c is not None
        shape_share, hold = p.substep_shares(dt)
        hold = hold if p.root_hold_length > 0.0 or self._waxed else 0.0
        if getattr(m, "root_local", None) is not self._slots_root_local:
            self.slots = self._strand_slots()  # bound to a mesh since the slots were made
        lane = self._lanes
        order = lane.order if lane is not None else self._particle_order
        # the last pass reads `shaped`; in particle order that is state_out.x itself, which the length
        # pass overwrites behind its windows
        shaped, spare = (lane.x, lane.prev) if lane is not None else (state_out.x, self.shape_scratch)
        x_in, v_in, x_out, v_out, by_particle = state_in.x, state_in.v, state_out.x, state_out.v, 1
        if self._in_frame:  # the state in lane order: this substep's pair in, the other out
            buffers, at = self._frame
            x_in, v_in, x_out, v_out = buffers[2 * at], buffers[2 * at + 1], buffers[2 - 2 * at], buffers[3 - 2 * at]
            self._frame[1] = 1 - at
            by_particle = 0
        contact = self.strand_contact(c, mode)
        if mode == COLLISION["sphere_tree"] and self.contact_bounds and self.leaves_ahead:
            # the walks of the lists that would run short, queued from the start positions
            dim, first = (lane.strands * lane.longest, 0) if lane is not None else (r.particles, r.first_particle)
            count = self._short_count[r]
            count.zero_()
            wp.launch(strands.find_short_lists, dim,
                      [x_in, x_in, m.particle_strand, m.strand_start, m.pinned_per_strand, contact, FUSED_LIST_SLACK,
                       order, by_particle, first, count, self._short], device=dev)
            wp.launch(strands.list_leaves_ahead, dim,
                      [x_in, contact, count, self._short, first, m.strand_start, order, by_particle], device=dev)
        fit = fused_fit(mode, variant, self.contact_bounds, self.mesh_lists)
        step = strands.STEP_STRANDS[fit]
        if self._loose(fit in strands.STEP_STRANDS_LOOSE and self.leaves_ahead) and mode == COLLISION["sphere_tree"]:
            if fit not in strands.STEP_STRANDS_LOOSE or not self.leaves_ahead:
                raise ValueError("loose_lists in the fused substep takes simplified shape matching against the "
                                 "sphere tree, with the lists made ahead (leaves_ahead on)")
            step = strands.STEP_STRANDS_LOOSE[fit]
        wp.launch(step, r.strands,
                  [x_in, v_in, m.strand_start, m.pinned_per_strand, self._forces(), self.clock,
                   offset, dt, int(bound), c.skin_binding(m) if bound else skinning.SkinBinding(),
                   m.particle_binding if bound else None, m.root_binding if bound else None, hold if bound else 0.0,
                   self._pull(guides, dt), self.windows.size, variant, passes, shape_share,
                   int(self._rotations_exact), p.rotation_iterations, self.rotations, self.slots,
                   contact, p.ftl_damping, shaped, spare, x_out, v_out, order,
                   1 - by_particle, 0 if lane is not None else r.first_strand], device=dev)
        if variant == SHAPE_MATCHING["full"] and passes > 0 and (part is None or part is self.parts[-1]):
            self._rotations_exact = False
        self._comb(state_in, state_out, contact, dt, offset, order, r)

    def contact_motion(self):
        """What the last substep measured of the collider's motion near the strands, as NumPy:
        (largest relative displacement [m], the anchor's rigid motion as a 4x4 matrix, the anchor's
        centre [m])."""
        motion = self._motion
        moved = float(motion.moved.numpy()[0]) * strands.MOTION_UNIT  # counted in fixed point, rounded up
        return moved, motion.rigid.numpy()[0], motion.center.numpy()[0]

    def motion_cells(self):
        """The last substep's motion per cell of the grid around the anchor (strands.ContactMotion.cells),
        as NumPy: (MOTION_GRID^3,) float64 [m], flattened x-major."""
        return self._motion.cells.numpy().astype(np.float64) * strands.MOTION_UNIT

    def reset(self):
        """Forget warm-start data and contact bounds; call after moving the state or the collider
        discontinuously (a new groom, a cut, a jump in time). Frames captured in CUDA graphs must be
        captured again (sim.graphs.FrameGraphs.clear)."""
        self._rotations_exact = True
        self.clearance.fill_(strands.NO_BOUND)
        self.beyond.fill_(strands.NO_BOUND)

    def count_unhealthy(self, state):
        """Launch the count of non-finite or too fast particles without waiting: (count, first
        particle) as one-element device arrays, for report_unhealthy once they are read back."""
        self._bad_count.zero_()
        self._first_bad.fill_(np.iinfo(np.int32).max)
        wp.launch(strands.count_unhealthy, self.model.num_particles,
                  [state.x, state.v, self.params.max_speed, self._bad_count, self._first_bad],
                  device=self.model.device)
        return self._bad_count, self._first_bad

    def report_unhealthy(self, bad, first, frame, prim):
        """Raise SimulationError naming the frame and prim if count_unhealthy found any particle."""
        bad, i = int(np.ravel(bad)[0]), int(np.ravel(first)[0])
        if bad:
            strand = int(self.model.particle_strand_np[i])
            raise SimulationError(frame, prim, f"{bad} particles are non-finite or faster than "
                                  f"{self.params.max_speed} m/s (first: particle {i}, strand {strand})")

    def check_health(self, state, frame, prim):
        """Raise SimulationError naming the frame and prim if any particle is NaN or too fast."""
        bad, first = self.count_unhealthy(state)
        self.report_unhealthy(bad.numpy(), first.numpy(), frame, prim)
