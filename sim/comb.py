"""The comb: lift hair with a virtual comb placed by a stroke on the screen (the cutting trainer's
lifting tool, Hayashimoto et al. §3.3).

Placing. The stroke is resampled at an even spacing in pixels; each sample's view ray is cast onto
the head (the collider mesh, where the paper used its sphere tree) and a Catmull-Rom curve through
the hits is the comb, lying on the head. The comb moves only within the plane through its centre
that faces the camera, so a drag on the screen moves it parallel to the screen at its own depth.

Grabbing. A strand is grabbed where, on the screen, the stroke crosses one of its segments whose
two particles the camera can see (Collider.visible_from): hair behind the head is never taken. The
particle at the crossing is held.

Holding. Each substep the strands.hold_in_comb kernel puts the held particle where the comb has it,
keeps the hair between root and comb at its segment lengths, lets the rest hang, and slides the
grip toward the tip whenever the comb is farther from the root than the hair up to the grip is
long. Releasing drops the hair back to the solver.
"""

import itertools
from dataclasses import dataclass

import numpy as np
import warp as wp
from scipy.interpolate import CubicHermiteSpline

from warp_kernels import strands as strand_kernels

from . import strokes

SWEEPS = 8  # backward/forward sweeps of the root-to-comb chain per substep
_SERIALS = itertools.count(1)  # graph keys: a new grip is a new set of arrays, never an old one's id


def catmull_rom(points, samples_per_span=8):
    """The uniform Catmull-Rom curve through `points`, sampled densely: each tangent is half the
    difference of the neighbours (one-sided at the ends)."""
    points = np.asarray(points, np.float64)
    if len(points) < 2:
        return points
    tangents = np.gradient(points, axis=0)
    knots = np.arange(len(points), dtype=np.float64)
    spline = CubicHermiteSpline(knots, points, tangents, axis=0)
    return spline(np.linspace(0.0, knots[-1], (len(points) - 1) * samples_per_span + 1))


def _crossings(a0, a1, b0, b1):
    """Segments a (N, 2 ends) against segments b (M, 2 ends) on the screen: (N, M) parameters
    along a where they cross, NaN where they do not."""
    da, db = a1 - a0, b1 - b0
    denom = da[:, None, 0] * db[None, :, 1] - da[:, None, 1] * db[None, :, 0]
    w = b0[None, :, :] - a0[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (w[..., 0] * db[None, :, 1] - w[..., 1] * db[None, :, 0]) / denom
        t = (w[..., 0] * da[:, None, 1] - w[..., 1] * da[:, None, 0]) / denom
    hit = (np.abs(denom) > 1e-12) & (s >= 0.0) & (s <= 1.0) & (t >= 0.0) & (t <= 1.0)
    return np.where(hit, s, np.nan)


@dataclass
class Comb:
    """A placed comb: its curve on the head, the plane it moves in, and the strands it holds."""

    camera: object  # io_usd.preview.Camera
    curve: np.ndarray  # (K, 3) the comb on the head, for drawing
    centre: np.ndarray  # (3,) a point of the plane the comb moves in
    normal: np.ndarray  # (3,) the plane's normal: the view direction
    strands: np.ndarray  # (G,) strands held
    grip: np.ndarray  # (G,) particle within each held strand
    anchor: np.ndarray  # (G, 3) the held particles' positions when grabbed
    offset: np.ndarray = None  # (3,) how far the comb has been dragged

    def __post_init__(self):
        if self.offset is None:
            self.offset = np.zeros(3)

    def drag_offset(self, pixels):
        """The world displacement (3,) of a drag by (du, dv) pixels: parallel to the screen, at the
        comb's depth, so the comb stays under the cursor."""
        return strokes.screen_drag(self.camera, self.centre[None], pixels)[0]


def place_comb(camera, stroke, collider, points, strand_start, pinned_per_strand=2, spacing=6.0):
    """Put a comb on the head along a screen stroke and grab the visible strands it crosses.

    points: (P, 3) current hair positions; strand_start: (S + 1,) offsets. Raises ValueError when
    the stroke misses the head."""
    samples = strokes.resample_stroke(stroke, spacing)
    if len(samples) < 2:
        raise ValueError("a comb stroke needs two distinct points")
    origins, directions = strokes.pixel_rays(camera, samples)
    eye = camera.eye
    t = collider.ray_hits(origins, directions)
    if not np.any(t > 0.0):
        raise ValueError("the comb stroke does not touch the head")
    hits = eye + directions[t > 0.0] * t[t > 0.0, None]
    curve = catmull_rom(hits)
    centre = curve.mean(0)
    forward = -np.asarray(camera.pose, np.float64)[:3, 2]

    points = np.asarray(points, np.float64)
    start = np.asarray(strand_start, np.int64)
    seen = collider.visible_from(points, eye)
    uv = camera.project(points)
    strand_of = np.repeat(np.arange(len(start) - 1), np.diff(start))
    local = np.arange(len(points)) - start[strand_of]
    # hair segments (i - 1, i) past the pinned roots with both ends in view and in front of the camera
    i = np.flatnonzero((local >= pinned_per_strand) & seen & np.r_[False, seen[:-1]]
                       & np.all(np.isfinite(uv), 1) & np.r_[False, np.all(np.isfinite(uv[:-1]), 1)])
    line = samples
    crossing = _crossings(uv[i - 1], uv[i], line[:-1], line[1:])
    crossed = np.isfinite(crossing).any(1)
    i, along = i[crossed], np.nanmin(crossing[crossed], 1)
    strands, grips = [], []
    for s in np.unique(strand_of[i]):  # the crossing nearest the root holds the strand
        k = np.argmin(np.where(strand_of[i] == s, local[i], np.iinfo(np.int64).max))
        particle = i[k] if along[k] >= 0.5 else i[k] - 1
        strands.append(s)
        grips.append(max(int(local[particle]), pinned_per_strand))
    strands, grips = np.asarray(strands, np.int64), np.asarray(grips, np.int64)
    anchor = points[start[strands] + grips] if len(strands) else np.zeros((0, 3))
    return Comb(camera, curve, centre, forward, strands, grips, anchor)


class CombGrip:
    """The comb's hold on the device, read by HairSolver each substep (strands.hold_in_comb)."""

    def __init__(self, model, comb):
        device = model.device
        grip = np.full(model.num_strands, -1, np.int32)
        grip[comb.strands] = comb.grip
        targets = np.zeros((model.num_strands, 3), np.float32)
        targets[comb.strands] = comb.anchor
        self.comb, self.model, self.event = comb, model, None
        self.serial = next(_SERIALS)
        self.grip = wp.array(grip, dtype=int, device=device)
        self.grip_from = wp.array(targets, dtype=wp.vec3, device=device)
        self.grip_to = wp.array(targets, dtype=wp.vec3, device=device)
        self._targets = targets

    def move_to(self, offset):
        """The comb's offset at the end of the next frame: substeps blend from where it is now."""
        self.grip_from.assign(self._targets)
        moved = self._targets.copy()
        moved[self.comb.strands] = self.comb.anchor + np.asarray(offset, np.float64)
        self._targets = moved.astype(np.float32)
        self.grip_to.assign(self._targets)
        self.comb.offset = np.asarray(offset, np.float64)

    def grips(self):
        """(G,) current grip particle of each held strand (they slide toward the tips)."""
        return self.grip.numpy()[self.comb.strands]

    def launch(self, model, state_out, state_in, blend, dt, contact, order, part):
        """Hold the gripped strands of `part` (a sim.hair_solver.StrandRange) after the length pass;
        `contact` (a strands.StrandContact) is the collider and the length pass's contact bounds, which the
        moved particles lose, in its order (`order`, a strands.LaneOrder)."""
        wp.launch(strand_kernels.hold_in_comb, part.strands,
                  [state_out.x, state_in.x, model.strand_start, model.rest_length, model.pinned_per_strand,
                   self.grip_from, self.grip_to, float(blend), SWEEPS, contact, float(dt), self.grip, state_out.v,
                   order, part.first_strand], device=model.device)


# -- on a scene, from a timeline ---------------------------------------------------------------------
def start_comb(scene, stroke, camera, event=None):
    """Place a comb on the scene's head along `stroke` seen through `camera` and hold the hair it
    crosses; ValueError when it misses the head or crosses no visible hair."""
    m = scene.model
    comb = place_comb(camera, stroke, scene.collider, scene.state.x.numpy(), m.strand_start_np, m.pinned_per_strand)
    if len(comb.strands) == 0:
        raise ValueError("the comb stroke crosses no hair the camera sees")
    scene.held_comb = scene.solver.comb = CombGrip(m, comb)
    scene.held_comb.event = event
    return comb


def comb_drag(event, frame):
    """The comb's drag (du, dv) in pixels at `frame`: its `moves` keys [[frame, du, dv], ...]
    interpolated linearly, from no drag at the frame it was placed, held after the last key."""
    keys = [(float(event.frame), 0.0, 0.0)] + [tuple(map(float, k)) for k in (event.moves or ())]
    f, du, dv = (np.array(c) for c in zip(*keys))
    return np.array([np.interp(frame, f, du), np.interp(frame, f, dv)])


def before_frame(scene, events, frame):
    """Before the scene advances into `frame`: the comb placed by the latest comb event still held
    moves to where its keys put it at `frame`; a released comb lets go. After an edit rebuilt the
    groom under the comb (a cut of the lifted hair), the same strands are taken again, grips clamped
    to shortened strands; an edit that removed strands releases it."""
    held = [e for e in events if e.tool == "comb" and e.frame < frame and (e.release is None or e.release > frame)]
    grip = scene.held_comb
    same = grip is not None and held and (grip.event.frame, grip.event.stroke) == (held[-1].frame, held[-1].stroke)
    if not same:
        scene.held_comb = scene.solver.comb = None
        return
    grip.event = held[-1]  # the timeline as it stands: a live session adds moves as the comb is dragged
    if grip.model is not scene.model:
        if scene.model.num_strands != grip.model.num_strands:
            scene.held_comb = scene.solver.comb = None
            return
        comb = grip.comb
        comb.grip = np.minimum(grip.grips(), scene.model.counts[comb.strands] - 1)
        regrip = CombGrip(scene.model, comb)
        regrip.event, regrip._targets = grip.event, grip._targets
        scene.held_comb = grip = regrip
    scene.solver.comb = grip
    grip.move_to(grip.comb.drag_offset(comb_drag(grip.event, frame)))
