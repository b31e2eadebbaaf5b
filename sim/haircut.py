"""Haircut studio: cut, thin, grow, erase, wax and re-initialise simulated strands between frames.

The cutting trainer of Hayashimoto et al. (§3.1 basic operations, §3.4 cuts, §3.5 wax) as tools on a
running simulation. Every tool is an edit between two frames: the groom is read into NumPy (a
`Groom`), edited, and the scene's HairModel, solver and states are rebuilt from it. Kept particles
carry their positions and velocities over bit for bit and every strand keeps its root binding, so
the frame after an edit continues the motion; the solver's frame graphs are captured again for the
new buffers. Nothing here runs per substep: the step stays one launch per kernel.

Python API (on a sim.Scene with hair; every call returns an `Edit` naming the strands it changed)::

    import sim
    from io_usd.preview import Camera
    from sim import haircut

    scene = sim.Scene(sim.load_scene("examples/scenes/haircut.toml"))
    scene.advance(1.0)
    cam = Camera.look_at(eye=(0, 0.3, 1.2), target=(0, 0.3, 0), yfov=0.6, width=960, height=720)
    haircut.blunt_cut(scene, haircut.Plane(point=(0, 0.25, 0), normal=(0, 1, 0)))
    haircut.chop_cut(scene, haircut.Stroke([[300, 520], [660, 520]], cam), amplitude=10, period=30)
    haircut.thinning_cut(scene, haircut.Plane((0, 0.22, 0), (0, 1, 0)), fraction=0.5, seed=3)
    haircut.grow(scene, 0.03, region=haircut.Sphere((0, 0.45, 0.1), 0.05))
    haircut.erase(scene, haircut.Brush([[480, 200]], cam, radius=25))
    haircut.wax(scene, haircut.Sphere((0, 0.35, 0.12), 0.04), drag=(60, -80), camera=cam)
    drag = haircut.start_wax(scene, haircut.Sphere((0, 0.3, 0.1), 0.04), offset=(0, 0.03, -0.02))
    for share in (0.25, 0.5, 0.75, 1.0):  # a drag over frames: a share of the way each frame
        drag.to(scene, share)
        scene.advance(1 / 24)
    haircut.initialise(scene)

Cut lines are a `Plane` (point, normal) or a `Stroke` (pixel points and the camera they were drawn
in: the cut surface is swept by the stroke along the camera's rays). A strand is cut where its
polyline first crosses the surface beyond its pinned root particles. Regions (which strands erase,
grow and wax act on) are a `Sphere` or a `Brush` (a stroke with a radius in pixels); erase and grow
test roots, wax tests tips unless told `select="roots"`. Screen strokes go through sim.strokes
(rays through pixels, the points a brush covers, drags parallel to the image), which the comb and
the studio share.

On arrays, without a Scene: `Groom.from_model(model, state)` reads a HairModel and HairState into
NumPy; `cut(groom, surface)`, `thin(...)`, `extend(...)`, `style_tips(...)` and `Groom.select(...)`
return an edited Groom (and the strands they changed), `first_crossings(points, counts, surface)`
finds where strands cross a `CutSurface` (`Plane(...).surface()`, `Stroke(...).surface()`, or their
`zigzag(...)`), and `apply(scene, groom)` installs a Groom in a Scene.

Scene files script the same as a timeline, one `[[haircut]]` table per event, applied after the
simulation reaches `frame` and before that frame is written::

    [[haircut]]
    frame = 12
    tool = "blunt"                       # blunt, chop, thinning, grow, erase, wax, initialise
    plane = { point = [0.0, 0.25, 0.0], normal = [0.0, 1.0, 0.0] }
    section = { center = [0.0, 0.4, -0.1], radius = 0.12 }   # optional: only strands rooted here

    [[haircut]]
    frame = 24
    tool = "chop"                        # or "thinning" (fraction = 0.5, seed = 1)
    stroke = [[300, 520], [660, 520]]    # pixels, (0, 0) top-left, v down
    camera = { eye = [0.0, 0.3, 1.2], target = [0.0, 0.3, 0.0], yfov = 0.6, width = 960, height = 720 }
    amplitude = 10                       # zigzag depth: pixels with a stroke, metres with a plane
    period = 30
    seed = 2

    [[haircut]]
    frame = 36
    tool = "wax"                         # grow: length = 0.03; erase: a region only
    sphere = { center = [0.0, 0.35, 0.12], radius = 0.04 }    # or stroke + radius (px) + camera
    drag = [60, -80]                     # pixels, with camera; or offset = [dx, dy, dz] or target = [x, y, z]
    camera = { eye = [0.0, 0.3, 1.2], target = [0.0, 0.3, 0.0] }
    strength = 0.5                       # how firmly the styled shape holds, [0, 1]
    until = 42                           # optional: the drag eased over frames 36-42 (no cut in between)

Caches record the changing topology: sim.scene.run_scene hands each frame's curveVertexCounts and
widths to io_usd.cache.CacheWriter, which time-samples them once they change.
"""

from dataclasses import asdict, dataclass, fields, replace

import numpy as np

from . import strokes
from .errors import InputError

TOOLS = ("blunt", "chop", "thinning", "grow", "erase", "wax", "initialise", "comb")
CUT_TOOLS = ("blunt", "chop", "thinning")


# -- lines and regions ------------------------------------------------------------------------------
@dataclass(frozen=True)
class Plane:
    """A cut plane through `point` [m] with normal `normal` (any length)."""

    point: tuple
    normal: tuple

    def __post_init__(self):
        p, n = np.asarray(self.point, np.float64), np.asarray(self.normal, np.float64)
        if p.shape != (3,) or n.shape != (3,) or not (np.all(np.isfinite(p)) and np.all(np.isfinite(n))):
            raise ValueError("a plane needs a finite 3D point and normal")
        if np.linalg.norm(n) < 1e-12:
            raise ValueError("a plane's normal must not be zero")

    def surface(self):
        n = _unit(np.asarray(self.normal, np.float64))
        return CutSurface.from_pieces(np.asarray(self.point, np.float64)[None], n[None])

    def zigzag(self, amplitude, period, seed=0, jitter=0.5, points=None, along=None):
        """The plane folded into teeth: offset along its normal by a zigzag of the coordinate along
        `along` (an in-plane direction; default the one most nearly horizontal, or X), covering
        `points`' extent. amplitude and period in metres."""
        o, n = np.asarray(self.point, np.float64), _unit(np.asarray(self.normal, np.float64))
        e = _in_plane(n, along)
        u = (np.asarray(points, np.float64).reshape(-1, 3) - o) @ e if points is not None and len(points) else np.zeros(1)
        c, h = _teeth(float(u.min()) - period, float(u.max()) + period, amplitude, period, seed, jitter)
        a, b = o + c[:-1, None] * e + h[:-1, None] * n, o + c[1:, None] * e + h[1:, None] * n
        normal = _unit(np.cross(b - a, np.cross(n, e)[None]))
        normal *= np.sign(normal @ n)[:, None]
        across = np.repeat(e[None], len(a), 0)
        # strip k lies between its teeth's coordinates: u >= c_k (past a) and u <= c_k+1 (short of b)
        return CutSurface(a, normal, np.stack([a, b], 1), np.stack([across, -across], 1))


@dataclass
class Stroke:
    """A cut line drawn on screen: pixel points (K >= 2, 2) and the io_usd.preview.Camera they were
    drawn in. The cut surface is the fan of view rays through the stroke."""

    pixels: np.ndarray
    camera: object

    def __post_init__(self):
        self.pixels = strokes.as_stroke(self.pixels)
        if len(self.pixels) < 2:
            raise ValueError("a cut stroke needs at least two points")

    def surface(self):
        return CutSurface.swept(self.camera, self.pixels)

    def zigzag(self, amplitude, period, seed=0, jitter=0.5, points=None, along=None):
        """The stroke made jagged on screen (amplitude and period in pixels), then swept."""
        return CutSurface.swept(self.camera, zigzag_stroke(self.pixels, amplitude, period, seed, jitter))


@dataclass(frozen=True)
class Sphere:
    """A region: points within `radius` [m] of `center`."""

    center: tuple
    radius: float

    def contains(self, points):
        return np.linalg.norm(np.asarray(points, np.float64) - np.asarray(self.center, np.float64), axis=1) <= self.radius


@dataclass
class Brush:
    """A region brushed on screen: points whose projection lies within `radius` pixels of the
    stroke (one point is a dab) in `camera` (sim.strokes.stroke_covers)."""

    stroke: np.ndarray
    camera: object
    radius: float = 20.0

    def contains(self, points):
        return strokes.stroke_covers(points, self.camera, self.stroke, self.radius)


def zigzag_stroke(pixels, amplitude, period, seed=0, jitter=0.5):
    """A jagged copy of a screen polyline: teeth every period / 2 pixels of its length, alternately
    `amplitude` pixels to either side (each tooth up to `jitter` of that shallower, seeded)."""
    s = strokes.as_stroke(pixels)
    seg = np.diff(s, axis=0)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(seg, axis=1))])
    c, h = _teeth(0.0, arc[-1], amplitude, period, seed, jitter)
    at = np.unique(np.concatenate([arc, c[(c > 0.0) & (c < arc[-1])]]))
    offset = np.interp(at, c, h)
    normal = np.stack([-seg[:, 1], seg[:, 0]], 1) / np.maximum(np.linalg.norm(seg, axis=1, keepdims=True), 1e-12)
    k = np.clip(np.searchsorted(arc, at, side="right") - 1, 0, len(seg) - 1)
    side = normal[k]
    corner = np.isin(at, arc[1:-1])  # at the stroke's own corners, the mean of both segments' normals
    side[corner] = _unit(normal[k[corner]] + normal[k[corner] - 1])
    base = np.stack([np.interp(at, arc, s[:, 0]), np.interp(at, arc, s[:, 1])], 1)
    return base + offset[:, None] * side


def _teeth(lo, hi, amplitude, period, seed, jitter):
    """Tooth coordinates c (every period / 2, at a seeded phase, covering [lo, hi]) and heights h."""
    if period <= 0.0:
        raise ValueError("a zigzag's period must be positive")
    half = 0.5 * period
    phase = np.random.default_rng(seed).random() * period
    m = np.arange(int(np.floor((lo - phase) / half)) - 1, int(np.ceil((hi - phase) / half)) + 2)
    c = phase + m * half
    depth = 1.0 - float(jitter) * _hash01(seed, m)
    h = np.where(m % 2 == 0, 1.0, -1.0) * amplitude * depth
    return c, h


def _hash01(seed, m):
    """Uniform [0, 1) per integer m, fixed by seed (so a tooth keeps its depth whatever the extent)."""
    x = np.asarray(m, np.int64).astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
    x = x + np.uint64((int(seed) * 0xBF58476D1CE4E5B9) % 2 ** 64)
    x ^= x >> np.uint64(31)
    x *= np.uint64(0x94D049BB133111EB)
    x ^= x >> np.uint64(29)
    return (x >> np.uint64(11)).astype(np.float64) / float(2 ** 53)


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


def _in_plane(n, along=None):
    if along is not None:
        e = np.asarray(along, np.float64) - (np.asarray(along, np.float64) @ n) * n
        if np.linalg.norm(e) > 1e-9:
            return _unit(e)
    e = np.cross(n, [0.0, 1.0, 0.0])
    if np.linalg.norm(e) < 1e-6:
        e = np.array([1.0, 0.0, 0.0]) - n[0] * n
    return _unit(e)


# -- cut surfaces -----------------------------------------------------------------------------------
@dataclass
class CutSurface:
    """A surface made of planar pieces: piece k is the plane through origin[k] with unit normal[k],
    limited to the points q with (q - bound_origin[k, m]) . bound_normal[k, m] >= 0 for m = 0, 1
    (zero bound normals: no limit). A plane is one unlimited piece, a swept stroke one wedge per
    stroke segment, a chop's zigzag one strip or wedge per tooth face."""

    origin: np.ndarray  # (K, 3)
    normal: np.ndarray  # (K, 3)
    bound_origin: np.ndarray  # (K, 2, 3)
    bound_normal: np.ndarray  # (K, 2, 3)

    @classmethod
    def from_pieces(cls, origin, normal):
        k = len(origin)
        return cls(np.asarray(origin, np.float64), _unit(normal), np.zeros((k, 2, 3)), np.zeros((k, 2, 3)))

    @classmethod
    def swept(cls, camera, pixels):
        """The fan of view rays through a screen polyline: a wedge (eye, ray a, ray b) per segment."""
        eye, d = strokes.pixel_rays(camera, strokes.as_stroke(pixels))
        a, b = d[:-1], d[1:]
        n = np.cross(a, b)
        keep = np.linalg.norm(n, axis=1) > 1e-12  # a segment of zero length sweeps nothing
        a, b, n, eye = a[keep], b[keep], _unit(n[keep]), eye[:-1][keep]
        # inside the wedge: between ray a and ray b, w . (n x a) >= 0 and w . (b x n) >= 0
        bounds = np.stack([np.cross(n, a), np.cross(b, n)], 1)
        return cls(eye, n, np.stack([eye, eye], 1), bounds)

    def _inside(self, q, k):
        """(M, k) mask: does q (M, k, 3), a point on piece k's plane, lie within that piece?"""
        ok = np.ones(q.shape[:2], bool)
        for m in range(2):
            ok &= np.einsum("nkj,kj->nk", q - self.bound_origin[None, k, m], self.bound_normal[k, m]) >= -1e-12
        return ok

    def intersect(self, a, b, block=1 << 21):
        """Where segments a -> b (M, 3) first meet the surface: parameter t in [0, 1], or NaN.
        Work goes in blocks of about `block` segment-piece pairs, so memory stays bounded."""
        a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
        best = np.full(len(a), np.inf)
        rows = max(1, min(len(a), block))
        chunk = max(1, block // rows)
        offset = np.einsum("kj,kj->k", self.origin, self.normal)
        for r0 in range(0, len(a), rows):
            ra, rb = a[r0:r0 + rows], b[r0:r0 + rows]
            for k0 in range(0, len(self.origin), chunk):
                k = np.arange(k0, min(k0 + chunk, len(self.origin)))
                sa, sb = ra @ self.normal[k].T - offset[k], rb @ self.normal[k].T - offset[k]
                cross = (sa * sb <= 0.0) & (sa != sb)
                with np.errstate(divide="ignore", invalid="ignore"):
                    t = np.where(cross, sa / (sa - sb), np.inf)
                q = ra[:, None] + np.where(cross, t, 0.0)[..., None] * (rb - ra)[:, None]
                t = np.where(cross & self._inside(q, k), t, np.inf)
                best[r0:r0 + rows] = np.minimum(best[r0:r0 + rows], t.min(axis=1))
        return np.where(np.isfinite(best), best, np.nan)

    def distance(self, points):
        """Distance (N,) from points to the surface, measured to the pieces whose extent contains the
        point's foot on their plane; +inf where there is none (for checking points on the surface)."""
        p = np.asarray(points, np.float64).reshape(-1, 3)
        k = np.arange(len(self.origin))
        s = np.einsum("nkj,kj->nk", p[:, None] - self.origin[None], self.normal)
        foot = p[:, None] - s[..., None] * self.normal[None]
        return np.where(self._inside(foot, k), np.abs(s), np.inf).min(axis=1)


def first_crossings(points, counts, surface, pinned=2, strands=None):
    """Where each strand first crosses `surface` beyond its `pinned` root particles.

    points (P, 3) flattened strands with `counts` vertices each; strands: (S,) bool, which to test.
    Returns (segment (S,) int: global index of the particle the crossing segment starts at, -1 where
    the strand does not cross; t (S,): the crossing's fraction along that segment)."""
    points = np.asarray(points, np.float64)
    counts = np.asarray(counts, np.int64)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    strand = np.repeat(np.arange(len(counts)), counts)
    local = np.arange(len(points)) - start[strand]
    usable = (local >= pinned - 1) & (local < counts[strand] - 1)
    if strands is not None:
        usable &= np.asarray(strands, bool)[strand]
    i = np.flatnonzero(usable)
    t = surface.intersect(points[i], points[i + 1])
    hit = np.isfinite(t)
    i, t = i[hit], t[hit]
    segment, frac = np.full(len(counts), -1, np.int64), np.zeros(len(counts))
    first, at = np.unique(strand[i], return_index=True)  # i is sorted, so the first hit per strand
    segment[first], frac[first] = i[at], t[at]
    return segment, frac


# -- the groom as arrays ----------------------------------------------------------------------------
@dataclass
class Groom:
    """Strands as flat NumPy arrays: the model's rest positions (in the pose the groom was bound
    on), the state's positions and velocities (world), widths, wax weights, vertices per strand, the
    number of pinned particles per strand, and for each strand the strand of the scene's model it
    came from (whose root binding it keeps)."""

    rest: np.ndarray  # (P, 3) m
    x: np.ndarray  # (P, 3) m
    v: np.ndarray  # (P, 3) m/s
    widths: np.ndarray  # (P,) m
    wax: np.ndarray  # (P,) how firmly the root hold keeps the styled shape, [0, 1] (HairModel.wax_np)
    counts: np.ndarray  # (S,)
    origin: np.ndarray  # (S,) index into the model's strands
    pinned: int = 2

    @classmethod
    def from_model(cls, model, state=None):
        x = state.x.numpy() if state is not None else model.rest_positions_np
        v = state.v.numpy() if state is not None else np.zeros_like(x)
        return cls(model.rest_positions_np.copy(), np.array(x, np.float32), np.array(v, np.float32),
                   model.widths_np.copy(), model.wax_np.copy(), model.counts.copy(), np.arange(model.num_strands),
                   model.pinned_per_strand)

    @property
    def start(self):
        return np.concatenate([[0], np.cumsum(self.counts)[:-1]]).astype(np.int64)

    @property
    def tips(self):
        return self.start + self.counts - 1

    def strand_of(self):
        return np.repeat(np.arange(len(self.counts)), self.counts)

    def lengths(self, positions=None):
        """Polyline length of every strand, of `positions` (default the current x) [m]."""
        p = np.asarray(self.x if positions is None else positions, np.float64)
        seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
        seg[(np.cumsum(self.counts) - 1)[:-1]] = 0.0  # no segment across strands
        return np.add.reduceat(np.concatenate([seg, [0.0]]), self.start) if len(self.counts) else np.zeros(0)

    def natural_lengths(self):
        return self.lengths(self.rest)

    def select(self, keep):
        """The strands where keep (S,) is True."""
        keep = np.asarray(keep, bool)
        mask = np.repeat(keep, self.counts)
        return replace(self, rest=self.rest[mask], x=self.x[mask], v=self.v[mask], widths=self.widths[mask],
                       wax=self.wax[mask], counts=self.counts[keep], origin=self.origin[keep])

    def splice(self, keep, extra_counts=None, rest=None, x=None, v=None, widths=None, wax=None):
        """Keep the first keep[s] particles of strand s and append extra_counts[s] new particles to
        it, taken in order from the flat arrays rest, x, v, widths, wax (sum(extra_counts) rows)."""
        keep = np.asarray(keep, np.int64)
        extra_counts = np.zeros_like(keep) if extra_counts is None else np.asarray(extra_counts, np.int64)
        counts = keep + extra_counts
        strand = np.repeat(np.arange(len(counts)), counts)
        local = np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)
        old = local < keep[strand]
        src = self.start[strand] + local
        extra_at = np.repeat(np.cumsum(extra_counts) - extra_counts, counts) + local - keep[strand]

        def merged(a, new):
            out = np.empty((len(local),) + a.shape[1:], a.dtype)
            out[old] = a[src[old]]
            if (~old).any():
                out[~old] = np.asarray(new, a.dtype)[extra_at[~old]]
            return out

        return replace(self, rest=merged(self.rest, rest), x=merged(self.x, x), v=merged(self.v, v),
                       widths=merged(self.widths, widths), wax=merged(self.wax, wax), counts=counts)


@dataclass
class Edit:
    """What a tool did: `strands` are the indices (in the groom before the edit) it changed."""

    tool: str
    strands: np.ndarray
    surface: CutSurface = None  # the cut surface of a cut
    targets: np.ndarray = None  # where wax put the tips (W, 3)
    event: int = None  # the [[haircut]] event that made it, in a timeline (run_events)


# -- tools on arrays --------------------------------------------------------------------------------
def cut(groom, surface, strands=None):
    """Blunt (and chop) cut: a new tip exactly where each strand first crosses `surface`; the rest
    shape is truncated at the same fraction of the crossed segment. Returns (groom, changed)."""
    seg, t = first_crossings(groom.x, groom.counts, surface, groom.pinned, strands)
    hit = seg >= 0
    i, f = seg[hit], t[hit]

    def at(a):
        a = np.asarray(a, np.float64)
        w = f.reshape((-1,) + (1,) * (a.ndim - 1))
        return a[i] + w * (a[i + 1] - a[i])

    keep = groom.counts.copy()
    keep[hit] = i - groom.start[hit] + 1
    new = groom.splice(keep, hit.astype(np.int64), at(groom.rest), at(groom.x), at(groom.v), at(groom.widths),
                       at(groom.wax))
    return new, np.flatnonzero(hit)


def thin(groom, surface, fraction=0.5, seed=0, strands=None):
    """Thinning cut: of the strands crossing `surface`, each with probability `fraction` ends at a
    particle drawn at random (seeded) between the crossing and its old tip. Returns (groom, changed)."""
    if not 0.0 <= fraction <= 1.0:
        raise ValueError("fraction must be in [0, 1]")
    seg, _ = first_crossings(groom.x, groom.counts, surface, groom.pinned, strands)
    hit = np.flatnonzero(seg >= 0)
    rng = np.random.default_rng(seed)
    chosen, draw = rng.random(len(hit)) < fraction, rng.random(len(hit))
    j = seg[hit] - groom.start[hit]  # the crossing segment starts at local particle j
    choices = groom.counts[hit] - j - 2  # particles strictly between the crossing and the old tip
    take = chosen & (choices > 0)
    keep = groom.counts.copy()
    keep[hit[take]] = j[take] + 1 + np.minimum((draw[take] * choices[take]).astype(np.int64), choices[take] - 1) + 1
    return groom.splice(keep), hit[take]


def extend(groom, length, strands=None):
    """Grow: add `length` [m] at the tips along each strand's last segment, in segments as close to
    the strand's mean rest spacing as divide `length` evenly. Returns (groom, changed)."""
    if length <= 0.0:
        raise ValueError("length must be positive")
    s = np.arange(len(groom.counts)) if strands is None else np.flatnonzero(strands)
    tip = groom.tips[s]
    spacing = groom.natural_lengths()[s] / np.maximum(groom.counts[s] - 1, 1)
    n = np.maximum(1, np.round(length / np.maximum(spacing, 1e-9))).astype(np.int64)
    step = length / n

    def direction(p):
        p = np.asarray(p, np.float64)
        d = p[tip] - p[tip - 1]
        flat = np.linalg.norm(d, axis=1) < 1e-9  # a tip cut at its parent: use the strand's chord
        d[flat] = p[tip[flat]] - p[groom.start[s][flat]]
        return _unit(d)

    k = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n) + 1
    owner = np.repeat(np.arange(len(s)), n)
    along = (k * np.repeat(step, n))[:, None]
    extra = np.zeros(len(groom.counts), np.int64)
    extra[s] = n
    new = groom.splice(groom.counts, extra,
                       rest=groom.rest[tip][owner] + along * direction(groom.rest)[owner],
                       x=groom.x[tip][owner] + along * direction(groom.x)[owner],
                       v=groom.v[tip][owner], widths=groom.widths[tip][owner], wax=groom.wax[tip][owner])
    return new, s


def style_tips(groom, strands, targets, to_rest=None, push_out=None, iterations=64, hold=True, strength=0.5):
    """Wax (§3.5): move each selected strand's tip toward its target (W, 3) [m], never farther from
    the strand's follicle (its last pinned particle) than the natural length of the free part, and
    re-project the strand through the pinned root to the tip with its rest segment lengths (FABRIK:
    backward from the tip, forward from the root). With hold, the styled shape becomes the rest shape
    and the root hold keeps it along the whole strand with weight `strength` (HairModel wax):
    to_rest(points, strand indices) maps world points to the rest pose (default: unchanged).
    push_out(points) keeps the styled strand out of the head. Returns (groom, changed, targets)."""
    s = np.flatnonzero(strands) if np.asarray(strands).dtype == bool else np.asarray(strands, np.int64)
    targets = np.asarray(targets, np.float64).reshape(-1, 3)
    if len(targets) == 1 and len(s) > 1:
        targets = np.repeat(targets, len(s), 0)
    if len(s) == 0:
        return groom, s, targets
    k, counts, start = groom.pinned, groom.counts[s], groom.start[s]
    nmax = int(counts.max())
    idx = np.minimum(start[:, None] + np.arange(nmax)[None], start[:, None] + counts[:, None] - 1)
    valid = np.arange(nmax)[None] < counts[:, None]
    p = groom.x[idx].astype(np.float64)
    rest = groom.rest[idx].astype(np.float64)
    seg = np.zeros((len(s), nmax))
    seg[:, 1:] = np.linalg.norm(np.diff(rest, axis=1), axis=2) * valid[:, 1:]
    anchor = p[:, k - 1]
    reach = seg[:, k:].sum(axis=1)
    d = targets - anchor
    dist = np.linalg.norm(d, axis=1)
    scale = np.where(dist > reach, reach * (1.0 - 1e-7) / np.maximum(dist, 1e-300), 1.0)
    targets = anchor + d * scale[:, None]
    last = counts - 1
    rows = np.arange(len(s))

    def toward(a, b, length):
        """b moved along a -> b to `length` from a."""
        dd = b - a
        n = np.linalg.norm(dd, axis=1, keepdims=True)
        flat = n[:, 0] < 1e-12
        dd[flat] = [0.0, -1.0, 0.0]
        n[flat] = 1.0
        return a + dd * (length[:, None] / n)

    def forward():
        for i in range(k, nmax):
            on = valid[:, i]
            p[on, i] = toward(p[on, i - 1], p[on, i], seg[on, i])

    for _ in range(iterations):
        p[rows, last] = targets
        for i in range(nmax - 2, k - 1, -1):
            on = i < last
            p[on, i] = toward(p[on, i + 1], p[on, i], seg[on, i + 1])
        if push_out is not None:
            free = valid.copy()
            free[:, :k] = False
            p[free] = push_out(p[free])
        forward()
        if np.max(np.linalg.norm(p[rows, last] - targets, axis=1)) < 1e-7:
            break
    x, restn, v, waxn = groom.x.copy(), groom.rest.copy(), groom.v.copy(), groom.wax.copy()
    free = valid.copy()
    free[:, :k] = False
    x[idx[free]] = p[free]
    v[idx[valid]] = 0.0
    if hold:
        owner = np.repeat(s, free.sum(axis=1))
        mapped = p[free] if to_rest is None else to_rest(p[free], owner)
        restn[idx[free]] = mapped
        waxn[idx[free]] = np.maximum(waxn[idx[free]], float(strength))
    return replace(groom, x=x, rest=restn, v=v, wax=waxn), s, p[rows, last]


# -- scenes -----------------------------------------------------------------------------------------
def groom_of(scene):
    """The scene's hair as a Groom (NumPy copies of its model and state)."""
    if scene.model is None:
        raise ValueError("the scene has no hair")
    return Groom.from_model(scene.model, scene.state)


def apply(scene, groom):
    """Make `groom` the scene's hair: a new HairModel (each strand keeps the root binding of the
    strand it came from), solver and states; positions and velocities from the groom."""
    from .strands import HairModel

    if len(groom.counts) == 0:
        raise ValueError("the edit would leave no strands")
    old = scene.model
    model = HairModel(groom.rest, groom.counts, groom.widths, groom.pinned, scene.device, wax=groom.wax)
    model.strand_ids = old.strand_ids[groom.origin]
    model.bind_to_mesh(scene.groom_points, scene.head.faces, old.root_triangle_np[groom.origin],
                       old.root_barycentric_np[groom.origin])
    _install(scene, model, groom.x, groom.v)
    return model


def _install(scene, model, x, v):
    import warp as wp

    from .hair_solver import HairSolver
    from .strands import HairState

    bounds = scene.solver.contact_bounds
    scene.model = model
    scene.solver = HairSolver(model, scene.config.solver)
    scene.solver.contact_bounds = bounds
    scene.solver.step_frames_as(scene.config.timing.hair_frames)
    x, v = np.asarray(x, np.float32), np.asarray(v, np.float32)
    scene.state, scene._scratch = (HairState(wp.array(x, dtype=wp.vec3, device=scene.device),
                                             wp.array(v, dtype=wp.vec3, device=scene.device)) for _ in range(2))
    if scene.guides is not None:
        from .guides import GuideTargets

        scene.guides = GuideTargets(model, scene.guides.frames, scene.guides.fps)
    # buffers are new: frames captured for the old ones must not be replayed (ids can be reused)
    scene.graphs.forget("hair")


def _root_frames(model, mesh_points, faces):
    """(S, 3, 3) frames (tangent, bitangent, normal columns) of each strand's root triangle."""
    from .strands import triangle_frames

    tri = np.asarray(mesh_points, np.float64)[np.asarray(faces).reshape(-1, 3)[model.root_triangle_np]]
    return triangle_frames(tri)


def _pose_maps(scene, model):
    """Per-strand rigid maps between the world (the collider as posed now) and the pose the model
    was bound on, carried by each root's triangle frame: (to_rest, to_world), each taking points
    (N, 3) and the strand (N,) of each point."""
    faces = np.asarray(scene.head.faces).reshape(-1, 3)
    groom_pts = np.asarray(scene.groom_points, np.float64)
    now_pts = scene.collider.points.numpy().astype(np.float64)
    groom_frames, now_frames = _root_frames(model, groom_pts, faces), _root_frames(model, now_pts, faces)
    rest_root = model.rest_positions_np[model.strand_start_np[:-1]].astype(np.float64)
    # each root is its binding: a barycentric point plus an offset in the triangle's frame
    tri, bary = faces[model.root_triangle_np], model.root_barycentric_np.astype(np.float64)
    local = np.einsum("nji,nj->ni", groom_frames, rest_root - np.einsum("nk,nkj->nj", bary, groom_pts[tri]))
    world_root = np.einsum("nk,nkj->nj", bary, now_pts[tri]) + np.einsum("nij,nj->ni", now_frames, local)

    def to_rest(points, strands):
        rel = np.einsum("nji,nj->ni", now_frames[strands], np.asarray(points, np.float64) - world_root[strands])
        return rest_root[strands] + np.einsum("nij,nj->ni", groom_frames[strands], rel)

    def to_world(points, strands):
        rel = np.einsum("nji,nj->ni", groom_frames[strands], np.asarray(points, np.float64) - rest_root[strands])
        return world_root[strands] + np.einsum("nij,nj->ni", now_frames[strands], rel)

    return to_rest, to_world


def _section_mask(groom, section):
    if section is None:
        return None
    return section.contains(groom.x[groom.start])


def _seen_in(scene, region, points):
    """region.contains(points), and for a Brush only the points its camera sees past the head: what
    is hidden from the view a stroke was drawn in is not touched (§3.3)."""
    inside = np.asarray(region.contains(points), bool)
    if isinstance(region, Brush) and inside.any():
        inside[inside] = scene.collider.visible_from(np.asarray(points)[inside], region.camera.eye)
    return inside


def _seen_cut(scene, line, groom, surface, mask):
    """For a Stroke, `mask` less the strands whose crossing of the cut surface the camera cannot see
    (behind the head): scissors drawn over the face do not cut the hair at the back."""
    if not isinstance(line, Stroke):
        return mask
    seg, t = first_crossings(groom.x, groom.counts, surface, groom.pinned, mask)
    hit = np.flatnonzero(seg >= 0)
    keep = np.ones(len(groom.counts), bool) if mask is None else np.asarray(mask, bool).copy()
    if len(hit):
        i = seg[hit]
        points = groom.x[i] + t[hit, None] * (groom.x[i + 1] - groom.x[i])
        keep[hit[~scene.collider.visible_from(points, line.camera.eye)]] = False
    return keep


def _line_surface(line, groom, zigzag=None):
    if zigzag is None:
        return line.surface()
    return line.zigzag(points=groom.x, **zigzag)


def blunt_cut(scene, line, section=None):
    """Blunt cut (§3.4): strands crossing `line` (a Plane or a Stroke) end exactly on it. section: a
    region (Sphere, Brush) limiting the cut to strands rooted inside it."""
    g = groom_of(scene)
    surface = _line_surface(line, g)
    new, changed = cut(g, surface, _seen_cut(scene, line, g, surface, _section_mask(g, section)))
    if len(changed):
        apply(scene, new)
    return Edit("blunt", changed, surface=surface)


def chop_cut(scene, line, amplitude=None, period=None, jitter=0.5, seed=0, section=None, along=None):
    """Chop cut (§3.4): the cut line made jagged, scissors entering along the strands: a zigzag with
    teeth `amplitude` deep every `period` (metres for a Plane, pixels for a Stroke; defaults 1.2 cm /
    12 px deep, 3 cm / 30 px apart), each tooth up to `jitter` shallower at random (seeded)."""
    metres = isinstance(line, Plane)
    amplitude = (0.012 if metres else 12.0) if amplitude is None else float(amplitude)
    period = (0.03 if metres else 30.0) if period is None else float(period)
    g = groom_of(scene)
    zigzag = {"amplitude": amplitude, "period": period, "seed": seed, "jitter": jitter, "along": along}
    surface = _line_surface(line, g, zigzag)
    new, changed = cut(g, surface, _seen_cut(scene, line, g, surface, _section_mask(g, section)))
    if len(changed):
        apply(scene, new)
    return Edit("chop", changed, surface=surface)


def thinning_cut(scene, line, fraction=0.5, seed=0, section=None):
    """Thinning cut (§3.4): of the strands crossing `line`, a `fraction` (drawn with `seed`) end at a
    random particle beyond the crossing, which thins the volume unevenly."""
    g = groom_of(scene)
    surface = _line_surface(line, g)
    new, changed = thin(g, surface, fraction, seed, _seen_cut(scene, line, g, surface, _section_mask(g, section)))
    if len(changed):
        apply(scene, new)
    return Edit("thinning", changed, surface=surface)


def grow(scene, length, region=None):
    """Grow (§3.1): add `length` [m] at the tips of the strands rooted in `region` (default all)."""
    g = groom_of(scene)
    mask = None if region is None else _seen_in(scene, region, g.x[g.start])
    new, changed = extend(g, float(length), mask)
    if len(changed):
        apply(scene, new)
    return Edit("grow", changed)


def erase(scene, region):
    """Erase (§3.1): remove the strands whose roots lie in `region` (a Sphere or a Brush)."""
    g = groom_of(scene)
    inside = _seen_in(scene, region, g.x[g.start])
    if inside.all():
        raise ValueError("erase would remove every strand")
    if inside.any():
        apply(scene, g.select(~inside))
    return Edit("erase", np.flatnonzero(inside))


def wax(scene, region, drag=None, camera=None, offset=None, target=None, select="tips", hold=True, strength=0.5):
    """Wax (§3.5): drag the tips of the strands selected by `region` (their tips inside it, or
    their roots with select="roots") and hold the styled shape as the strands' new rest shape.

    The drag is `drag` = (du, dv) pixels in `camera`, within the plane through each tip parallel to
    the image; or a world `offset` (3,) [m]; or a world `target` (3,) every selected tip is pulled to.
    A tip stops where the strand would be pulled straight (the natural length of its free part from
    its follicle, the last pinned particle, toward the target: never beyond its natural length from
    the root) and the strand is re-laid from root to tip with its rest lengths. Tips behind the
    camera of a drag are left alone. The styled shape becomes the strand's rest shape
    and the root hold keeps it along the whole strand with weight `strength` in [0, 1] (times
    solver.root_stiffness per substep), as wax does against gravity. hold=False drags without
    waxing: the strand springs back to its old rest shape. The whole drag lands at once; to draw it
    over frames, start_wax(...) and move the WaxDrag a share of the way each frame."""
    return start_wax(scene, region, drag, camera, offset, target, select, hold, strength).to(scene, 1.0)


@dataclass
class WaxDrag:
    """A wax drag under way: the strands it took and where their tips started and are going, both
    in the pose the groom is bound on, so the drag goes with a moving head. to(scene, share) lays
    the tips `share` of the way (wax's rules at each step), waxing each step's shape with hold."""

    strands: np.ndarray  # (S,) strand indices
    start: np.ndarray  # (S, 3) tips when the drag began, rest pose
    goal: np.ndarray  # (S, 3) where the tips are dragged to, rest pose
    counts: np.ndarray  # vertices of every strand of the groom when the drag began: a cut ends the drag
    hold: bool = True
    strength: float = 0.5

    def to(self, scene, share):
        g = groom_of(scene)
        if not np.array_equal(g.counts, self.counts):
            raise ValueError("another edit changed the strands of this wax drag")
        to_rest, to_world = _pose_maps(scene, scene.model)
        goal = to_world(self.start + float(share) * (self.goal - self.start), self.strands)
        new, changed, reached = style_tips(g, self.strands, goal, to_rest, _push_out(scene), hold=self.hold,
                                           strength=self.strength)
        if len(changed):
            apply(scene, new)
        return Edit("wax", changed, targets=reached)


def start_wax(scene, region, drag=None, camera=None, offset=None, target=None, select="tips", hold=True,
              strength=0.5):
    """Select the strands and their tips' goals as wax does (same arguments), and return the WaxDrag
    without moving anything."""
    if sum(a is not None for a in (drag, offset, target)) != 1:
        raise ValueError("wax needs exactly one of drag (with camera), offset or target")
    if drag is not None and camera is None:
        raise ValueError("a drag in pixels needs the camera it was made in")
    if select not in ("tips", "roots"):
        raise ValueError("select must be 'tips' or 'roots'")
    if not 0.0 <= strength <= 1.0:
        raise ValueError("strength must be in [0, 1]")
    g = groom_of(scene)
    where = g.x[g.tips] if select == "tips" else g.x[g.start]
    s = np.flatnonzero(_seen_in(scene, region, where))
    tips = g.x[g.tips[s]].astype(np.float64)
    if drag is not None:
        goal = tips + strokes.screen_drag(camera, tips, drag)
        seen = np.all(np.isfinite(goal), axis=1)
        s, tips, goal = s[seen], tips[seen], goal[seen]
    elif offset is not None:
        goal = tips + np.asarray(offset, np.float64)
    else:
        goal = np.repeat(np.asarray(target, np.float64)[None], len(s), 0)
    to_rest, _ = _pose_maps(scene, scene.model)
    return WaxDrag(s, to_rest(tips, s), to_rest(goal, s), g.counts.copy(), hold, strength)


def _push_out(scene):
    p = scene.config.solver
    if p.collision == "none":
        return None
    return lambda points: scene.collider.push_out(points, p.collision_margin, search=p.collision_search).astype(np.float64)


def initialise(scene):
    """Initialise (§3.1): back to the scene's template hairstyle ([hair] table or given strands),
    laid on the head where it is now, at rest."""
    template = scene.hair_template
    _, to_world = _pose_maps(scene, template)
    x = to_world(template.rest_positions_np, template.particle_strand_np)
    _install(scene, template, x, np.zeros_like(x))
    return Edit("initialise", np.arange(template.num_strands))


# -- the timeline -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class CameraSpec:
    """A camera in a scene file: io_usd.preview.Camera.look_at's arguments."""

    eye: tuple
    target: tuple
    up: tuple = (0.0, 1.0, 0.0)
    yfov: float = 0.6  # rad, vertical field of view
    width: int = 960  # px
    height: int = 720  # px

    def camera(self):
        from io_usd.preview import Camera

        return Camera.look_at(self.eye, self.target, self.up, self.yfov, self.width, self.height)


@dataclass(frozen=True)
class HaircutEvent:
    """One [[haircut]] table: a tool applied at `frame`; only the keys its tool takes are set."""

    frame: int
    tool: str
    plane: tuple = None  # (point, normal)
    stroke: tuple = None  # ((u, v), ...) pixels: a cut line, or a brush path
    camera: CameraSpec = None
    sphere: tuple = None  # (center, radius): a region
    radius: float = 20.0  # px, a brush stroke's radius
    section: tuple = None  # (center, radius): only strands rooted in this sphere are cut
    amplitude: float = None  # chop: zigzag depth (m with a plane, px with a stroke)
    period: float = None  # chop: zigzag period (m with a plane, px with a stroke)
    jitter: float = 0.5  # chop: how much shallower a tooth may be, [0, 1]
    along: tuple = None  # chop with a plane: the in-plane direction the teeth run along
    fraction: float = 0.5  # thinning: share of the crossing strands thinned, [0, 1]
    seed: int = 0  # chop, thinning
    length: float = None  # grow: m added at the tips
    drag: tuple = None  # wax: (du, dv) pixels in camera
    offset: tuple = None  # wax: world displacement [m]
    target: tuple = None  # wax: world point [m]
    select: str = "tips"  # wax: select strands by their "tips" or "roots" in the region
    hold: bool = True  # wax: false drags without making the shape the rest shape
    moves: tuple = None  # comb: ((frame, du, dv), ...) its drag in pixels, reached at each frame
    release: int = None  # comb: the frame from which the hair is free again
    strength: float = 0.5  # wax: how firmly the styled shape is held, [0, 1]
    until: int = None  # wax: the frame the drag reaches its goal, eased over the frames from `frame`

    def line(self):
        if self.plane is not None:
            return Plane(*self.plane)
        return Stroke(np.asarray(self.stroke, np.float64), self.camera.camera())

    def region(self):
        if self.sphere is not None:
            return Sphere(*self.sphere)
        if self.stroke is not None:
            return Brush(np.asarray(self.stroke, np.float64), self.camera.camera(), self.radius)
        return None

    def as_dict(self):
        """The keys set, for the cache's settings."""
        default = HaircutEvent(0, "")
        out = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name in ("frame", "tool") or value != getattr(default, f.name):
                out[f.name] = asdict(value) if isinstance(value, CameraSpec) else value
        return out


def run_event(scene, event):
    """Apply one HaircutEvent to a scene; returns the Edit."""
    t = event.tool
    section = Sphere(*event.section) if event.section is not None else None
    if t == "blunt":
        return blunt_cut(scene, event.line(), section)
    if t == "chop":
        return chop_cut(scene, event.line(), event.amplitude, event.period, event.jitter, event.seed, section,
                        event.along)
    if t == "thinning":
        return thinning_cut(scene, event.line(), event.fraction, event.seed, section)
    if t == "grow":
        return grow(scene, event.length, event.region())
    if t == "erase":
        return erase(scene, event.region())
    if t == "comb":
        from .comb import start_comb

        start_comb(scene, event.stroke, event.camera.camera(), event)
        return Edit("comb", scene.held_comb.comb.strands)
    if t == "wax":
        camera = event.camera.camera() if event.camera is not None else None
        drag = start_wax(scene, event.region(), event.drag, camera, event.offset, event.target, event.select,
                         event.hold, event.strength)
        if event.until is not None and event.until > event.frame:
            scene.wax_drags[id(event)] = drag
        return drag.to(scene, wax_share(event, event.frame))
    return initialise(scene)


def wax_share(event, frame):
    """How much of a timeline wax's drag is done at `frame`: smoothstep over the frames from its
    frame to its until (all of it at once without until), so the tips start and stop gently."""
    from .head import _smoothstep

    if event.until is None or event.until <= event.frame:
        return 1.0
    return float(_smoothstep((frame - event.frame + 1) / (event.until - event.frame + 1)))


def run_events(scene, events, frame):
    """Apply the timeline's events at `frame`, in file order, and move the waxes dragged over
    frames (until) that are under way; returns their Edits."""
    edits = []
    for k, event in enumerate(events):
        try:
            if event.frame == frame:
                edits.append(run_event(scene, event))
            elif id(event) in scene.wax_drags and event.frame < frame <= event.until:
                edits.append(scene.wax_drags[id(event)].to(scene, wax_share(event, frame)))
                if frame == event.until:
                    del scene.wax_drags[id(event)]
            else:
                continue
            edits[-1].event = k
        except ValueError as err:
            raise InputError(scene.config.source, f"haircut[{k}]", f"frame {frame}: {err}") from None
    return edits


_LINE = ("plane", "stroke", "camera", "section")
_REGION = ("sphere", "stroke", "radius", "camera")
KEYS = {
    "blunt": _LINE,
    "chop": _LINE + ("amplitude", "period", "jitter", "along", "seed"),
    "thinning": _LINE + ("fraction", "seed"),
    "grow": ("length",) + _REGION,
    "erase": _REGION,
    "wax": _REGION + ("drag", "offset", "target", "select", "hold", "strength", "until"),
    "initialise": (),
    "comb": ("stroke", "camera", "moves", "release"),
}


def parse_timeline(entries, source, timing=None):
    """[[haircut]] tables -> HaircutEvents; errors name the entry and key (haircut[3].tool)."""
    if not isinstance(entries, list):
        raise InputError(source, "haircut", "expected an array of tables ([[haircut]])")
    events = tuple(_parse_event(entry, source, f"haircut[{i}]", timing) for i, entry in enumerate(entries))
    for i, event in enumerate(events):
        if event.tool != "wax" or event.until is None:
            continue
        for k, other in enumerate(events):
            # a drag keeps its strands by index: only wax and the comb leave every strand as it is
            during = event.frame < other.frame <= event.until or (other.frame == event.frame and k > i)
            if during and other.tool not in ("wax", "comb"):
                raise InputError(source, f"haircut[{k}].frame", f"a {other.tool} at frame {other.frame} would change "
                                 f"the strands haircut[{i}] drags until frame {event.until}")
    return events


def _parse_event(entry, source, where, timing):
    def fail(key, reason):
        raise InputError(source, f"{where}.{key}" if key else where, reason)

    if not isinstance(entry, dict):
        fail(None, "expected a table")
    tool = entry.get("tool")
    if tool == "initialize":
        tool = "initialise"
    if tool not in TOOLS:
        fail("tool", f"expected one of {', '.join(TOOLS)}, got {tool!r}")
    known = ("frame", "tool") + KEYS[tool]
    for key in entry:
        if key not in known:
            fail(key, f"unknown key for tool {tool} (known: {', '.join(known)})")
    frame = entry.get("frame")
    if isinstance(frame, bool) or not isinstance(frame, int):
        fail("frame", f"expected an integer frame, got {frame!r}")
    if timing is not None and frame < timing.start_frame:
        fail("frame", f"frame {frame} is before the first frame ({timing.start_frame})")
    kw = {"frame": frame, "tool": tool}

    def number(key, lo=None, hi=None, positive=False):
        value = entry[key]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
            fail(key, f"expected a finite number, got {value!r}")
        if positive and value <= 0:
            fail(key, f"must be positive, got {value!r}")
        if lo is not None and hi is not None and not lo <= value <= hi:
            fail(key, f"must be in [{lo}, {hi}], got {value!r}")
        if lo is not None and value < lo:
            fail(key, f"must be at least {lo}, got {value!r}")
        if hi is not None and value > hi:
            fail(key, f"must be at most {hi}, got {value!r}")
        return float(value)

    def vector(value, n, key):
        ok = isinstance(value, list) and len(value) == n and all(
            isinstance(c, (int, float)) and not isinstance(c, bool) and np.isfinite(c) for c in value)
        if not ok:
            fail(key, f"expected a list of {n} finite numbers, got {value!r}")
        return tuple(float(c) for c in value)

    def table(key, names):
        value = entry[key]
        if not isinstance(value, dict):
            fail(key, f"expected a table with {', '.join(names)}")
        for k in value:
            if k not in names:
                fail(f"{key}.{k}", f"unknown key (known: {', '.join(names)})")
        for k in names:
            if k not in value and k not in ("up", "yfov", "width", "height"):
                fail(f"{key}.{k}", "missing")
        return value

    def sphere(key):
        t = table(key, ("center", "radius"))
        radius = t["radius"]
        if isinstance(radius, bool) or not isinstance(radius, (int, float)) or not 0 < radius <= 10.0:
            fail(f"{key}.radius", f"expected metres, more than 0 and at most 10, got {radius!r}")
        return (vector(t["center"], 3, f"{key}.center"), float(radius))

    if "plane" in entry:
        t = table("plane", ("point", "normal"))
        kw["plane"] = (vector(t["point"], 3, "plane.point"), vector(t["normal"], 3, "plane.normal"))
        if np.linalg.norm(kw["plane"][1]) == 0.0:
            fail("plane.normal", "must not be zero")
    if "camera" in entry:
        t = table("camera", ("eye", "target", "up", "yfov", "width", "height"))
        cam = {"eye": vector(t["eye"], 3, "camera.eye"), "target": vector(t["target"], 3, "camera.target")}
        if "up" in t:
            cam["up"] = vector(t["up"], 3, "camera.up")
        if np.allclose(cam["eye"], cam["target"]):
            fail("camera.target", "must differ from camera.eye")
        if "yfov" in t:
            y = t["yfov"]
            if isinstance(y, bool) or not isinstance(y, (int, float)) or not 0.0 < y < np.pi:
                fail("camera.yfov", f"expected radians in (0, pi), got {y!r}")
            cam["yfov"] = float(y)
        for k in ("width", "height"):
            if k in t:
                if isinstance(t[k], bool) or not isinstance(t[k], int) or t[k] < 1:
                    fail(f"camera.{k}", f"expected a positive integer (pixels), got {t[k]!r}")
                cam[k] = t[k]
        kw["camera"] = CameraSpec(**cam)
    if "stroke" in entry:
        s = entry["stroke"]
        if not isinstance(s, list) or not s:
            fail("stroke", "expected a list of [u, v] pixel points")
        kw["stroke"] = tuple(vector(p, 2, "stroke") for p in s)
        if tool in ("blunt", "chop", "thinning", "comb") and len(set(kw["stroke"])) < 2:
            fail("stroke", "a cut or comb line needs two distinct points")
        if "camera" not in kw:
            fail("camera", "a stroke needs the camera it was drawn in")
    if "sphere" in entry:
        kw["sphere"] = sphere("sphere")
    if "section" in entry:
        kw["section"] = sphere("section")
    # a grow past 10 m is no character's; a brush's radius is pixels, a chop's teeth metres (pixels along a
    # stroke), one tooth per period across the hair: a period of a nanometre asked for 10^8 of them
    ranges = (("radius", None, 1e4), ("length", None, 10.0), ("amplitude", None, 1e4), ("period", 1e-3, 1e4))
    for key, lo, hi in ranges:
        if key in entry:
            kw[key] = number(key, lo, hi, positive=True)
    for key in ("jitter", "fraction", "strength"):
        if key in entry:
            kw[key] = number(key, 0.0, 1.0)
    if "seed" in entry:
        if isinstance(entry["seed"], bool) or not isinstance(entry["seed"], int):
            fail("seed", f"expected an integer, got {entry['seed']!r}")
        kw["seed"] = entry["seed"]
    if "along" in entry:
        kw["along"] = vector(entry["along"], 3, "along")
    for key, n in (("drag", 2), ("offset", 3), ("target", 3)):
        if key in entry:
            kw[key] = vector(entry[key], n, key)
    if "select" in entry:
        if entry["select"] not in ("tips", "roots"):
            fail("select", f"expected 'tips' or 'roots', got {entry['select']!r}")
        kw["select"] = entry["select"]
    if "hold" in entry:
        if not isinstance(entry["hold"], bool):
            fail("hold", f"expected a boolean, got {entry['hold']!r}")
        kw["hold"] = entry["hold"]

    if "moves" in entry:
        moves = entry["moves"]
        if not isinstance(moves, list):
            fail("moves", "expected a list of [frame, du, dv] (pixels)")
        keys = tuple(vector(m, 3, "moves") for m in moves)
        frames = [k[0] for k in keys]
        if any(f != int(f) for f in frames) or frames != sorted(frames) or (frames and frames[0] <= frame):
            fail("moves", "frames must be whole, increasing and after the comb's frame")
        kw["moves"] = keys
    if "until" in entry:
        until = entry["until"]
        if isinstance(until, bool) or not isinstance(until, int) or until < frame:
            fail("until", f"expected the frame the drag ends, {frame} or later, got {until!r}")
        kw["until"] = until
    if "release" in entry:
        release = entry["release"]
        if isinstance(release, bool) or not isinstance(release, int) or release <= frame:
            fail("release", f"expected a frame after {frame}, got {release!r}")
        kw["release"] = release
    if tool == "comb" and ("stroke" not in kw or len(kw["stroke"]) < 2):
        fail("stroke", "a comb is placed by a stroke of at least two points, with its camera")
    if tool in CUT_TOOLS:
        if ("plane" in kw) == ("stroke" in kw):
            fail("plane", f"a {tool} cut needs a line: plane = {{point, normal}} or stroke + camera")
        if "stroke" in kw and len(kw["stroke"]) < 2:
            fail("stroke", "a cut stroke needs at least two points")
    if tool in ("grow", "erase", "wax"):
        if "sphere" in kw and "stroke" in kw:
            fail("stroke", "give one region: sphere, or stroke with radius and camera")
        if tool != "grow" and "sphere" not in kw and "stroke" not in kw:
            fail("sphere", f"{tool} needs a region: sphere = {{center, radius}} or stroke + radius + camera")
    if tool == "grow" and "length" not in kw:
        fail("length", "grow needs the length to add [m]")
    if tool == "wax":
        given = [k for k in ("drag", "offset", "target") if k in kw]
        if len(given) != 1:
            fail("drag", "wax needs exactly one of drag (pixels, with camera), offset or target")
        if given == ["drag"] and "camera" not in kw:
            fail("camera", "a drag in pixels needs the camera it was made in")
    return HaircutEvent(**kw)
