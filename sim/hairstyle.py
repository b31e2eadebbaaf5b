"""Hairstyle generators: roots sampled on a scalp, strands grown out of it as straight, wavy or curly.

A strand leaves the scalp at a low angle (root_lift above the surface, leaning the way it falls) and
bends toward a fall direction (down and away from the head's vertical axis, the fringe swept back)
while being pushed out of the head;
waves or curls are then added around that centre line and the polyline is resampled to evenly spaced
vertices. Generation runs once per scene: Python loops here walk along the strand, never per frame.
"""

from dataclasses import dataclass

import numpy as np
import trimesh

from .config import require_nonnegative, require_positive, require_within

STYLES = ("straight", "wavy", "curly")
# rad: a strand whose segments turn by more than this draws its curls or waves as zigzags (the curly example
# at 32 vertices a strand turned 61 degrees a segment and drew as one; at 64, 30 degrees, its curls read round)
SMOOTH_TURN = np.radians(40.0)


def check_color(color):
    """ValueError unless color is three linear RGB values within 0 and 1 (a dataclass's `color`)."""
    if len(color) != 3 or not all(0.0 <= c <= 1.0 for c in color):
        raise ValueError(f"color must be three linear RGB values within 0 and 1, got {list(color)}")


@dataclass(frozen=True)
class HairstyleParams:
    enabled: bool = True  # false: a scene without hair (cloth only)
    style: str = "wavy"  # "straight", "wavy" or "curly"
    count: int = 3000  # strands; ignored when density > 0
    density: float = 0.0  # strands per cm^2 of scalp (0: use count)
    length: float = 0.22  # m, length of the strand's centre line (curls add to the natural length)
    length_jitter: float = 0.15  # relative random variation of length per strand
    vertices: int = 24  # particles per strand (curls and waves draw as curves up to SMOOTH_TURN a segment)
    bend_length: float = 0.02  # m, how soon a strand turns from its root direction to the fall direction
    # degrees between the scalp and a strand's first segment (90: straight out along the normal). The
    # root's first segment is pinned to the head, so a steep one stands up for the whole shot, and a
    # crown of them reads as bristles over bare scalp; hair leaves the scalp at a shallow angle.
    root_lift: float = 30.0
    wave_amplitude: float = 0.006  # m a wavy strand swings to either side of its centre line
    wavelength: float = 0.09  # m along the strand from one wave crest to the next
    curl_radius: float = 0.008  # m, the radius of a curly strand's helix
    curl_pitch: float = 0.03  # m the helix advances per turn
    root_width: float = 1.2e-4  # m, the curves' width at the root, tapering linearly ...
    tip_width: float = 4.0e-5  # m ... to this at the tip
    clearance: float = 0.003  # m, rest shape kept this far off the head
    seed: int = 1  # the random roots, lengths and shapes: the same seed grows the same groom
    color: tuple = (0.23, 0.14, 0.08)  # linear RGB: the curves' displayColor, which previews and DCCs draw
    # render children per simulated strand (sim.hair_children): grown between the simulated strands and
    # carried by them, written as their own curves (hair_children); 0 for none
    children: int = 0
    guides: str = ""  # a cache with captured guide curves (cfx capture solve) the strands follow
    guide_prim: str = "hair_guides"  # the curves prim in that cache

    def __post_init__(self):
        if self.style not in STYLES:
            raise ValueError(f"style must be one of {STYLES}")
        if self.vertices < 3:
            raise ValueError("vertices must be at least 3")
        if self.length <= 0.0:
            raise ValueError("length must be positive")
        if self.count < 1 and self.density <= 0.0:
            raise ValueError("count must be at least 1")
        # a jitter of 1 or more grows strands of zero or negative length
        require_within(self, "length_jitter", 0.0, 1.0, high_open=True)
        require_positive(self, "bend_length", "wavelength", "curl_pitch", "root_width")
        require_nonnegative(self, "density", "wave_amplitude", "curl_radius", "tip_width", "clearance", "seed")
        if not 0.0 < self.root_lift <= 90.0:
            raise ValueError("root_lift must be more than 0 and at most 90 degrees")
        check_color(self.color)
        if not 0 <= self.children <= 64:
            raise ValueError(f"children must be 0 to 64 per simulated strand, got {self.children}")

    def _bending(self):
        """(largest curvature of the styled centre line [1/m], its natural length [m]) for the nominal
        length: a helix of curl_radius and curl_pitch, or a sine of wave_amplitude and wavelength;
        None for straight hair. The root's ramp into the style is left out (it only lowers both)."""
        if self.style == "curly":
            c = self.curl_pitch / (2.0 * np.pi)
            turn = np.hypot(self.curl_pitch, 2.0 * np.pi * self.curl_radius)
            return self.curl_radius / (self.curl_radius ** 2 + c ** 2), self.length * turn / self.curl_pitch
        if self.style == "wavy":
            k = 2.0 * np.pi / self.wavelength
            return self.wave_amplitude * k * k, self.length
        return None

    @property
    def segment_turn(self):
        """Largest angle [rad] between consecutive segments of a strand, from the style's curvature
        and the evenly spaced vertices (None for straight hair). Above about SMOOTH_TURN the curls or
        waves draw as zigzags."""
        bending = self._bending()
        if bending is None:
            return None
        curvature, natural = bending
        return curvature * natural / (self.vertices - 1)

    def vertices_for_smooth_curves(self):
        """The fewest vertices per strand whose segments turn by SMOOTH_TURN or less."""
        curvature, natural = self._bending()
        return int(np.ceil(curvature * natural / SMOOTH_TURN)) + 1


def sample_scalp(vertices, faces, face_mask, count, seed=1):
    """Area-weighted random roots on the masked faces: (points, face index, barycentric, normals)."""
    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), process=False)
    candidates = np.flatnonzero(face_mask)
    if len(candidates) == 0:
        raise ValueError("the scalp region has no faces")
    area = mesh.area_faces[candidates]
    rng = np.random.default_rng(seed)
    face = candidates[rng.choice(len(candidates), size=count, p=area / area.sum())]
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    bary = np.stack([1.0 - s, s * (1.0 - r2), s * r2], 1)
    tri = mesh.vertices[mesh.faces[face]]
    points = np.einsum("nk,nkj->nj", bary, tri)
    normals = np.einsum("nk,nkj->nj", bary, mesh.vertex_normals[mesh.faces[face]])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return points, face, bary, normals


def scalp_area(vertices, faces, face_mask):
    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), process=False)
    return float(mesh.area_faces[np.asarray(face_mask, bool)].sum())


def grow_hairstyle(params, roots, normals, push_out, axis_point=(0.0, 0.0, 0.0)):
    """Grow strands from roots (S, 3) with scalp normals (S, 3).

    push_out(points, margin) -> points keeps the rest shape outside the head (a Collider.push_out).
    Returns (points (S * vertices, 3), counts (S,), widths (S * vertices,)).
    """
    p = params
    rng = np.random.default_rng(p.seed + 7)
    roots = np.asarray(roots, np.float64)
    normals = np.asarray(normals, np.float64)
    n_strands = len(roots)
    lengths = p.length * (1.0 + p.length_jitter * rng.uniform(-1.0, 1.0, n_strands))

    fine = max(4 * p.vertices, 64)
    step = lengths / (fine - 1)
    fall = _fall_direction(roots, np.asarray(axis_point, np.float64))
    centre = np.empty((n_strands, fine, 3))
    centre[:, 0] = roots
    d = _root_direction(normals, fall, p.root_lift)
    # the clearance is reached as a strand leaving at root_lift would reach it over a flat scalp: the
    # full clearance at once would stand every root up along its normal for the first 3 mm
    margins = np.minimum(p.clearance, np.sin(np.radians(p.root_lift)) * step.min() * np.arange(fine))
    for k in range(1, fine):
        turn = 1.0 - np.exp(-step / p.bend_length)
        d = _normalize(d + turn[:, None] * (fall - d))
        prev = centre[:, k - 1]
        q = push_out(prev + d * step[:, None], margins[k])
        d = _normalize(q - prev)
        centre[:, k] = prev + d * step[:, None]

    shaped = centre + _style_offsets(p, centre, rng)
    ramp = int(np.count_nonzero(margins < p.clearance))
    for k in range(1, ramp):
        shaped[:, k] = push_out(shaped[:, k], margins[k])
    shaped[:, ramp:] = push_out(shaped[:, ramp:].reshape(-1, 3), p.clearance).reshape(n_strands, fine - ramp, 3)
    points = _resample(shaped, p.vertices)
    t = np.linspace(0.0, 1.0, p.vertices)
    widths = np.tile(p.root_width + (p.tip_width - p.root_width) * t, n_strands)
    return points.reshape(-1, 3), np.full(n_strands, p.vertices), widths


def _normalize(v):
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def _root_direction(normals, fall, lift_degrees):
    """Unit directions root_lift above the scalp, leaning toward the fall direction's part along
    the surface (the normal where the fall is along it)."""
    along = fall - np.sum(fall * normals, axis=1, keepdims=True) * normals
    leaning = np.linalg.norm(along, axis=1, keepdims=True) > 1e-6
    lift = np.radians(lift_degrees)
    return np.where(leaning, np.cos(lift) * _normalize(along) + np.sin(lift) * normals, normals)


def _fall_direction(roots, axis_point, part=0.012):
    """Down and away from the head's vertical axis; hair in front of the ears is parted at
    x = part and swept to its side and back, so it frames the face instead of covering it."""
    out = roots - axis_point
    out[:, 1] = 0.0
    out = _normalize(out)
    side = np.where(roots[:, 0] - axis_point[0] >= part, 1.0, -1.0)
    swept = _normalize(np.stack([side, np.zeros_like(side), np.full_like(side, -0.7)], 1))
    front = np.clip((out[:, 2] - 0.2) / 0.8, 0.0, 1.0)[:, None]  # 0 at and behind the ears, 1 at the face
    out = _normalize((1.0 - front) * out + front * swept)
    # front hair first runs along the scalp toward the part's side, then falls
    down = np.array([0.0, -1.0, 0.0])
    return _normalize((1.0 - 0.6 * front) * down + (0.2 + 1.0 * front) * out)


def _style_offsets(p, centre, rng):
    if p.style == "straight":
        return np.zeros_like(centre)
    n_strands, fine, _ = centre.shape
    tangent = _normalize(np.gradient(centre, axis=1))
    # parallel-transported frame along each centre line
    n1 = np.empty_like(centre)
    seed_dir = np.cross(tangent[:, 0], np.array([0.0, 1.0, 0.0]))
    bad = np.linalg.norm(seed_dir, axis=1) < 1e-6
    seed_dir[bad] = np.cross(tangent[bad, 0], np.array([1.0, 0.0, 0.0]))
    n1[:, 0] = _normalize(seed_dir)
    for k in range(1, fine):
        v = n1[:, k - 1] - np.sum(n1[:, k - 1] * tangent[:, k], 1, keepdims=True) * tangent[:, k]
        n1[:, k] = _normalize(v)
    n2 = np.cross(tangent, n1)
    arc = np.concatenate([np.zeros((n_strands, 1)),
                          np.cumsum(np.linalg.norm(np.diff(centre, axis=1), axis=2), axis=1)], axis=1)
    ramp = np.clip(arc / 0.03, 0.0, 1.0)[..., None]
    # neighbouring strands wave in step, as real wavy locks do, with a little scatter
    phase = rng.normal(0.0, 0.6, (n_strands, 1))
    if p.style == "wavy":
        wave = np.sin(2.0 * np.pi * arc / p.wavelength + phase)[..., None]
        return ramp * p.wave_amplitude * wave * n1
    angle = (2.0 * np.pi * arc / p.curl_pitch + phase)[..., None]
    return ramp * p.curl_radius * (np.cos(angle) * n1 + np.sin(angle) * n2)


def _resample(polylines, count):
    """Resample each (S, K, 3) polyline to `count` vertices evenly spaced along its arc length."""
    n_strands, k, _ = polylines.shape
    seg = np.linalg.norm(np.diff(polylines, axis=1), axis=2)
    arc = np.concatenate([np.zeros((n_strands, 1)), np.cumsum(seg, axis=1)], axis=1)
    want = arc[:, -1:] * np.linspace(0.0, 1.0, count)[None, :]
    # searchsorted on each row at once: offset rows so they never interleave
    offset = (np.arange(n_strands) * (arc[:, -1].max() + 1.0))[:, None]
    idx = np.searchsorted((arc + offset).ravel(), (want + offset).ravel(), side="right") - 1
    idx = np.clip(idx - np.repeat(np.arange(n_strands) * k, count), 0, k - 2).reshape(n_strands, count)
    rows = np.arange(n_strands)[:, None]
    a0, a1 = arc[rows, idx], arc[rows, idx + 1]
    w = ((want - a0) / np.maximum(a1 - a0, 1e-12))[..., None]
    return (1.0 - w) * polylines[rows, idx] + w * polylines[rows, idx + 1]
