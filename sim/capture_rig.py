"""A synthetic hair motion capture: stripe-dyed guide hairs filmed by a calibrated camera rig.

The capture method of SPEC §4 dyes a few guide hairs in bands of red, green and blue of a known
width and films them against a white backdrop with calibrated cameras (the paper: 13 guides with
6 stripes of 4 cm, a ring of 8 cameras around the head, 1920x1080). This module makes such a capture
from a simulated scene, so the solving pipeline can be tested against ground truth:

1. simulate the scene (its cache is kept as simulation.usdc) and pick guide strands spread over the
   scalp (farthest-point sampling on the roots);
2. per frame, the centre of every stripe: the arc-length-weighted centroid of the stripe's piece of
   the guide's centre line (truth.npz);
3. a parallel stereo pair in front of the face and a ring of cameras around the head, all in
   OpenCV's convention (capture.json);
4. render the guides as tubes coloured per stripe on the head (and, optionally, the rest of the hair
   in brown) with pyrender, offscreen, to images/CAMERA/NNNN.png, and each camera's view without
   the guides to background/CAMERA.png.

Lighting is mostly ambient (0.55) plus a white directional light shining from each camera along
its view, without shadows, on fully rough materials (a specular highlight would add white): the
channels of a pixel scale together, so a stripe's channel ratios, which the pipeline thresholds on,
hold in light and in shade. Guides are round tubes `guide_width` thick (a dyed lock, 6 mm by
default), so they show from every side and have a true depth for the visibility test; the undyed
hair, when drawn, is camera-facing ribbons at least 1.5 pixels wide. The directory layout is
docs/capture_format.md.
"""

import argparse
import json
import math
import os
import shutil
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from .config import require_nonnegative, require_within
from .errors import InputError

STRIPE_COLORS = ("red", "green", "blue")
# Linear RGB of the dyes. pyrender writes colour**(1/2.2), which lifts the near-zero channels to
# 30-50 of 255; in the images each dye's own channel stays above 4 times the others (skin: 1.15).
DYES = {"red": (0.80, 0.01, 0.01), "green": (0.01, 0.55, 0.02), "blue": (0.01, 0.03, 0.80)}
BACKDROP = (1.0, 1.0, 1.0)
AMBIENT = 0.55  # share of light that does not depend on the surface's orientation
HEADLIGHT = 1.4  # W/m^2 of the directional light that shines from each camera along its view
TUBE_SIDES = 8
VISIBLE_SHARE = 0.5  # a stripe is labelled in a view when at least this share of its centre line shows
HAIR_PIXELS = 1.5  # on-screen width the undyed background hair is never drawn thinner than


@dataclass(frozen=True)
class CaptureConfig:
    """The [capture] table of a scene file: the dyed guides, the camera rig and the image defects."""

    guides: int = 13  # dyed guide hairs, spread over the scalp
    stripe_width: float = 0.04  # m of guide length per coloured band
    guide_width: float = 0.006  # m, thickness a guide is drawn with: a lock of hair, not one strand
    ring_cameras: int = 8  # cameras on a circle around the head (0: the stereo pair only)
    ring_radius: float = 1.2  # m from the head's centre
    ring_elevation: float = 15.0  # degrees the ring sits above the head's centre, looking down at it
    stereo_distance: float = 1.0  # m from the head's centre to the stereo pair, in front of the face
    stereo_baseline: float = 0.12  # m between the parallel stereo cameras
    fov: float = 0.0  # degrees, vertical field of view; 0 fits the hair's reach over the run in every image
    width: int = 960  # pixels
    height: int = 540  # pixels
    noise: float = 0.0  # standard deviation of per-pixel Gaussian noise, in 8-bit levels
    occlusion: float = 0.0  # share of (frame, camera, stripe) hidden on purpose, [0, 1)
    occlusion_frames: int = 3  # a hidden stripe stays hidden for 1 to this many consecutive frames
    background_hair: bool = False  # also draw the undyed hair in brown, hiding parts of the guides
    seed: int = 0  # guide choice, noise and occlusion

    def __post_init__(self):
        if self.guides < 1:
            raise ValueError("guides must be at least 1")
        for name in ("stripe_width", "guide_width", "ring_radius", "stereo_distance", "stereo_baseline"):
            if getattr(self, name) <= 0.0:
                raise ValueError(f"{name} must be positive")
        if self.ring_cameras < 0:
            raise ValueError("ring_cameras must be zero or positive")
        if not -80.0 <= self.ring_elevation <= 80.0:
            raise ValueError("ring_elevation must be within [-80, 80] degrees")
        if self.fov != 0.0 and not 1.0 <= self.fov <= 150.0:
            raise ValueError("fov must be 0 (automatic) or within [1, 150] degrees")
        require_within(self, "width", 16, 8192)
        require_within(self, "height", 16, 8192)
        if self.noise < 0.0:
            raise ValueError("noise must be zero or positive")
        if not 0.0 <= self.occlusion < 1.0:
            raise ValueError("occlusion must be within [0, 1)")
        if self.occlusion_frames < 1:
            raise ValueError("occlusion_frames must be at least 1")
        require_nonnegative(self, "seed")  # NumPy's generators take no negative seeds


# -- cameras ----------------------------------------------------------------------------------------
@dataclass
class CaptureCamera:
    """A calibrated pinhole camera in OpenCV's convention: `world_to_camera` (4x4) maps world points
    (metres, Y up) to camera coordinates with x right, y down, z forward, and a pixel is
    (u, v) = K (x/z, y/z, 1) with (0, 0) the top-left corner of the top-left pixel."""

    name: str
    group: str  # "stereo" or "ring"
    K: np.ndarray  # (3, 3)
    world_to_camera: np.ndarray  # (4, 4)

    @classmethod
    def look_at(cls, name, group, eye, target, K, up=(0.0, 1.0, 0.0)):
        eye, target = np.asarray(eye, np.float64), np.asarray(target, np.float64)
        forward = _unit(target - eye)
        right = _unit(np.cross(forward, up))
        rotation = np.stack([right, np.cross(forward, right), forward])  # rows: x right, y down, z forward
        return cls.from_rotation(name, group, rotation, eye, K)

    @classmethod
    def from_rotation(cls, name, group, rotation, eye, K):
        extrinsic = np.eye(4)
        extrinsic[:3, :3] = rotation
        extrinsic[:3, 3] = -rotation @ np.asarray(eye, np.float64)
        return cls(name, group, np.asarray(K, np.float64), extrinsic)

    @property
    def centre(self):
        """The camera's position in the world."""
        r, t = self.world_to_camera[:3, :3], self.world_to_camera[:3, 3]
        return -r.T @ t

    @property
    def projection(self):
        """The 3x4 matrix K [R | t]."""
        return self.K @ self.world_to_camera[:3]

    def to_camera(self, points):
        """World points (..., 3) in camera coordinates (..., 3)."""
        points = np.asarray(points, np.float64)
        return points @ self.world_to_camera[:3, :3].T + self.world_to_camera[:3, 3]

    def project(self, points):
        """World points (..., 3) to pixels (..., 2); NaN for points not in front of the camera."""
        local = self.to_camera(points)
        z = local[..., 2:3]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (local[..., :2] / z) @ self.K[:2, :2].T + self.K[:2, 2]
        return np.where(z > 1e-9, uv, np.nan)

    def gl_pose(self):
        """Camera-to-world in OpenGL's axes (x right, y up, looking down -z), as pyrender wants it."""
        return np.linalg.inv(self.world_to_camera) @ np.diag([1.0, -1.0, -1.0, 1.0])

    def to_json(self):
        return {"name": self.name, "group": self.group, "K": self.K.tolist(),
                "world_to_camera": self.world_to_camera.tolist()}

    @classmethod
    def from_json(cls, data):
        return cls(str(data["name"]), str(data["group"]), np.asarray(data["K"], np.float64),
                   np.asarray(data["world_to_camera"], np.float64))


def project(camera, points):
    """Pixel coordinates (..., 2) of world points (..., 3) in `camera` (a CaptureCamera)."""
    return camera.project(points)


def intrinsics(focal, width, height):
    """K for square pixels with the principal point at the image centre."""
    return np.array([[focal, 0.0, 0.5 * width], [0.0, focal, 0.5 * height], [0.0, 0.0, 1.0]])


def rig_cameras(config, centre, reach):
    """The stereo pair and the ring, all aimed at `centre` [m]. With config.fov = 0 each group's
    focal length fits a sphere of radius `reach` around the centre into its images. ValueError,
    naming the setting, when cameras would stand inside that sphere."""
    c = config
    centre = np.asarray(centre, np.float64)

    def focal(distance, offset=0.0):
        if c.fov > 0.0:
            return 0.5 * c.height / math.tan(math.radians(0.5 * c.fov))
        if reach + offset >= distance:
            key = "ring_radius" if offset == 0.0 else "stereo_distance"
            raise ValueError(f"{key} must exceed the hair's reach from the head's centre ({reach:.2f} m), "
                             f"got {distance:.2f} m")
        margin = 1.05
        half_v = margin * math.asin(reach / distance)
        half_h = margin * math.asin(min(1.0, (reach + offset) / distance))
        return min(0.5 * c.height / math.tan(half_v), 0.5 * c.width / math.tan(half_h))

    cameras = []
    # the pair looks along -Z at the face (+Z), the right camera `baseline` along the left one's +x
    k_stereo = intrinsics(focal(c.stereo_distance, 0.5 * c.stereo_baseline), c.width, c.height)
    rotation = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    for name, side in (("stereo_l", -0.5), ("stereo_r", 0.5)):
        eye = centre + [side * c.stereo_baseline, 0.0, c.stereo_distance]
        cameras.append(CaptureCamera.from_rotation(name, "stereo", rotation, eye, k_stereo))
    k_ring = intrinsics(focal(c.ring_radius), c.width, c.height)
    elevation = math.radians(c.ring_elevation)
    for k in range(c.ring_cameras):
        azimuth = 2.0 * math.pi * k / c.ring_cameras  # 0 in front of the face, turning toward +X
        direction = np.array([math.sin(azimuth) * math.cos(elevation), math.sin(elevation),
                              math.cos(azimuth) * math.cos(elevation)])
        cameras.append(CaptureCamera.look_at(f"ring_{k}", "ring", centre + c.ring_radius * direction, centre, k_ring))
    return cameras


# -- guides and stripes -----------------------------------------------------------------------------
def choose_guides(roots, count, seed=0, eligible=None):
    """Indices of `count` strands whose roots (N, 3) spread over the scalp: farthest-point sampling
    from a seeded random start, then ordered around the head from the face (+Z) toward +X."""
    roots = np.asarray(roots, np.float64)
    candidates = np.flatnonzero(np.ones(len(roots), bool) if eligible is None else eligible)
    if len(candidates) < count:
        raise ValueError(f"only {len(candidates)} strands are long enough to carry a stripe, {count} guides asked for")
    pts = roots[candidates]
    chosen = [int(np.random.default_rng(seed).integers(len(pts)))]
    distance = np.linalg.norm(pts - pts[chosen[0]], axis=1)
    for _ in range(count - 1):
        chosen.append(int(np.argmax(distance)))
        distance = np.minimum(distance, np.linalg.norm(pts - pts[chosen[-1]], axis=1))
    chosen = candidates[chosen]
    centre = roots.mean(0)
    azimuth = np.mod(np.arctan2(roots[chosen, 0] - centre[0], roots[chosen, 2] - centre[2]), 2.0 * np.pi)
    return chosen[np.lexsort((-roots[chosen, 1], azimuth))]


def arc_lengths(points):
    """Arc length from the first vertex at every vertex of polylines (..., n, 3) -> (..., n)."""
    seg = np.linalg.norm(np.diff(points, axis=-2), axis=-1)
    return np.concatenate([np.zeros(seg.shape[:-1] + (1,)), np.cumsum(seg, axis=-1)], axis=-1)


def points_at(points, s):
    """Points at arc lengths s (P, m) along polylines (P, n, 3), linear between vertices (clamped)."""
    points = np.asarray(points, np.float64)
    arc = arc_lengths(points)
    i = np.sum(s[:, :, None] >= arc[:, None, 1:-1], axis=-1)  # segment index, 0..n-2
    a0, a1 = np.take_along_axis(arc, i, 1), np.take_along_axis(arc, i + 1, 1)
    w = np.clip((s - a0) / np.maximum(a1 - a0, 1e-12), 0.0, 1.0)[..., None]
    p0 = np.take_along_axis(points, i[..., None], 1)
    p1 = np.take_along_axis(points, i[..., None] + 1, 1)
    return (1.0 - w) * p0 + w * p1


def stripe_centres(points, stripes, width, max_stripes=None):
    """Centre of every stripe of polylines (P, n, 3): the arc-length-weighted centroid of the centre
    line over arc lengths [k w, (k + 1) w). stripes (P,) counts each polyline's whole stripes.
    Returns (P, max_stripes, 3), NaN past a polyline's last stripe.

    A segment contributes its part inside the stripe, weighted by that part's length, at that part's
    midpoint: the exact centroid of a polyline."""
    points = np.asarray(points, np.float64)
    stripes = np.asarray(stripes, np.int64)
    k_max = int(stripes.max()) if max_stripes is None else int(max_stripes)
    arc = arc_lengths(points)
    lo = width * np.arange(k_max)[None, :, None]
    a = np.maximum(arc[:, None, :-1], lo)  # (P, K, n - 1): each segment clipped to each stripe
    b = np.minimum(arc[:, None, 1:], lo + width)
    part = np.clip(b - a, 0.0, None)
    seg = np.maximum(arc[:, 1:] - arc[:, :-1], 1e-12)[:, None, :]
    t = ((0.5 * (a + b) - arc[:, None, :-1]) / seg)[..., None]
    mid = points[:, None, :-1] + t * np.diff(points, axis=1)[:, None]
    total = part.sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        centres = np.einsum("pkn,pknj->pkj", part, mid) / total[..., None]
    centres[np.arange(k_max)[None, :] >= stripes[:, None]] = np.nan
    return centres


def stripe_samples(points, stripes, width, samples):
    """Centre-line samples of each guide's pieces for drawing and visibility tests: pieces
    0..stripes-1 are the dyed stripes, piece `stripes` the undyed rest up to the tip, and pieces
    after that collapse onto the tip. points (P, n, 3) -> (P, max_stripes + 1, samples, 3), and the
    piece's valid mask (P, max_stripes + 1)."""
    points = np.asarray(points, np.float64)
    stripes = np.asarray(stripes, np.int64)
    pieces = int(stripes.max()) + 1
    length = arc_lengths(points)[:, -1]
    k = np.arange(pieces)[None, :]
    start = np.minimum(k * width, length[:, None])
    end = np.where(k < stripes[:, None], start + width, length[:, None])
    u = np.linspace(0.0, 1.0, samples)
    s = start[..., None] + (end - start)[..., None] * u
    out = points_at(points, s.reshape(len(points), -1)).reshape(len(points), pieces, samples, 3)
    valid = (k < stripes[:, None]) | ((k == stripes[:, None]) & (length[:, None] - start > 1e-4))
    return out, valid


# -- geometry to draw -------------------------------------------------------------------------------
def _unit(v, fallback=None):
    v = np.asarray(v, np.float64)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    out = v / np.maximum(n, 1e-12)
    if fallback is not None:
        small = n[..., 0] < 1e-12
        out[small] = fallback[small]
    return out


def tube_mesh(pieces, valid, radius, colors, sides=TUBE_SIDES):
    """Round tubes along guides cut into pieces. pieces (G, P, M, 3): consecutive pieces of a guide
    share their end point; valid (G, P); colors (G, P, 3) linear RGB per piece.

    The rings are built once along each whole guide with a parallel-transported frame, so pieces join
    without a crack; a piece's rings are then copied so each colour ends sharply at its boundary.
    Returns vertices (V, 3), normals (V, 3), colors (V, 3) float32, faces (F, 3) int32 and the
    (guide, piece) of every face (F, 2)."""
    g, p, m, _ = pieces.shape
    line = np.concatenate([pieces[:, :, :-1].reshape(g, p * (m - 1), 3), pieces[:, -1:, -1]], axis=1)
    tangent = _unit(np.gradient(line, axis=1))
    normal = np.empty_like(line)
    seed_axis = np.where(np.abs(tangent[:, :1, 1:2]) < 0.9, [[[0.0, 1.0, 0.0]]], [[[1.0, 0.0, 0.0]]])
    normal[:, 0] = _unit(np.cross(tangent[:, 0], seed_axis[:, 0]))
    for j in range(1, line.shape[1]):
        previous = normal[:, j - 1]
        n = previous - np.sum(previous * tangent[:, j], -1, keepdims=True) * tangent[:, j]
        normal[:, j] = _unit(n, fallback=previous)
    binormal = np.cross(tangent, normal)
    angle = 2.0 * np.pi * np.arange(sides) / sides
    around = np.cos(angle)[:, None] * normal[:, :, None] + np.sin(angle)[:, None] * binormal[:, :, None]
    ring = line[:, :, None] + radius * around  # (G, L, sides, 3)

    index = (np.arange(p)[:, None] * (m - 1) + np.arange(m)[None, :])  # (P, M) ring of each piece sample
    vertices = ring[:, index].reshape(-1, 3)
    normals = around[:, index].reshape(-1, 3)
    rgb = np.broadcast_to(np.asarray(colors, np.float64)[:, :, None, None], (g, p, m, sides, 3)).reshape(-1, 3)

    base = np.arange(g * p * m * sides).reshape(g, p, m, sides)
    s0, s1 = np.arange(sides), (np.arange(sides) + 1) % sides
    a, b = base[:, :, :-1][..., s0], base[:, :, :-1][..., s1]
    c, d = base[:, :, 1:][..., s0], base[:, :, 1:][..., s1]
    quads = np.stack([np.stack([a, b, d], -1), np.stack([a, d, c], -1)], -2)  # (G, P, M-1, sides, 2, 3)
    shape = quads.shape[:-1]
    owner = np.stack([np.broadcast_to(np.arange(g)[:, None, None, None, None], shape).reshape(-1),
                      np.broadcast_to(np.arange(p)[None, :, None, None, None], shape).reshape(-1)], 1)
    keep = np.broadcast_to(valid[:, :, None, None, None], shape).reshape(-1)
    faces = quads.reshape(-1, 3)[keep]
    return (vertices.astype(np.float32), normals.astype(np.float32), rgb.astype(np.float32),
            faces.astype(np.int32), owner[keep])


class Studio:
    """One offscreen pyrender context and scene for a fixed set of cameras: a white backdrop,
    mostly ambient light plus a weak light at the camera, no shadows. Geometry is shown by name
    (replacing what had that name), and each render returns the image and the depth buffer."""

    def __init__(self, cameras, width, height):
        from io_usd.preview import SupersampledOffscreen, _pyrender

        pyrender = self._pyrender = _pyrender()
        self.cameras = list(cameras)
        self.width, self.height = int(width), int(height)
        self._gl = SupersampledOffscreen(self.width, self.height)
        self.scene = pyrender.Scene(bg_color=np.array([*BACKDROP, 1.0]), ambient_light=np.full(3, AMBIENT))
        self._camera_nodes = []
        for cam in self.cameras:
            # in the drawn image's pixels, with (0, 0) its corner: K's entries scaled
            (fx, _, cx), (_, fy, cy) = self._gl.supersample * cam.K[:2]
            lens = pyrender.IntrinsicsCamera(fx, fy, cx, cy, znear=0.02, zfar=50.0)
            self._camera_nodes.append(self.scene.add(lens, pose=cam.gl_pose(), name=cam.name))
        self._light = self.scene.add(pyrender.DirectionalLight(color=np.ones(3), intensity=HEADLIGHT))
        self._nodes = {}
        self._materials = {}

    def show(self, name, vertices, faces, normals, colors=None, color=None, double_sided=True):
        """Draw a triangle mesh under `name`: per-vertex linear RGB `colors` or one `color`."""
        pyrender = self._pyrender
        self.hide(name)
        if len(faces) == 0:
            return
        key = (tuple(color) if color is not None else None, double_sided)
        if key not in self._materials:
            # a fully rough dielectric: a highlight would add white and wash out the dye's channel ratios
            self._materials[key] = pyrender.MetallicRoughnessMaterial(
                baseColorFactor=(*(color if color is not None else (1.0, 1.0, 1.0)), 1.0),
                metallicFactor=0.0, roughnessFactor=1.0, doubleSided=double_sided)
        primitive = pyrender.Primitive(positions=np.asarray(vertices, np.float32),
                                       normals=np.asarray(normals, np.float32), indices=np.asarray(faces, np.int32),
                                       color_0=colors, material=self._materials[key])
        self._nodes[name] = self.scene.add(pyrender.Mesh([primitive], name=name), name=name)

    def hide(self, name):
        node = self._nodes.pop(name, None)
        if node is not None:
            self.scene.remove_node(node)

    def render(self, camera_index):
        """(H, W, 3) uint8 image and (H, W) float32 depth along the view axis [m] of the nearest
        surface in each pixel (0: backdrop)."""
        self.scene.main_camera_node = self._camera_nodes[camera_index]
        self.scene.set_pose(self._light, self.cameras[camera_index].gl_pose())
        return self._gl.render_with_depth(self.scene, self._pyrender.RenderFlags.NONE)

    def close(self):
        if self._gl is not None:
            self._gl.delete()
            self._gl = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def stripe_visibility(camera, samples, depth, tolerance):
    """Share (...,) of each stripe's centre-line samples (..., M, 3) that `camera` sees: inside the
    image, with nothing drawn more than `tolerance` [m] in front of them in the depth buffer."""
    shape = samples.shape[:-2]
    pts = samples.reshape(-1, 3)
    uv = camera.project(pts)
    z = camera.to_camera(pts)[:, 2]
    h, w = depth.shape
    inside = np.isfinite(uv).all(1) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    col = np.clip(np.nan_to_num(uv[:, 0]), 0, w - 1).astype(np.int64)
    row = np.clip(np.nan_to_num(uv[:, 1]), 0, h - 1).astype(np.int64)
    seen = depth[row, col]
    unblocked = (seen == 0.0) | (seen > z - tolerance)
    return (inside & unblocked).reshape(*shape, samples.shape[-2]).mean(-1)


def occlusion_mask(frames, cameras, stripes, share, longest, rng):
    """(frames, cameras, guides, max_stripes) bool: stripes hidden on purpose in runs of 1 to `longest`
    frames, about `share` of all; never in the first frame, where the stripes are named."""
    stripes = np.asarray(stripes, np.int64)
    shape = (frames, cameras, len(stripes), int(stripes.max()))
    hidden = np.zeros(shape, bool)
    if share <= 0.0:
        return hidden
    starts = rng.random(shape) < share / (0.5 * (1 + longest))
    starts[0] = False
    length = rng.integers(1, longest + 1, shape)
    for offset in range(longest):
        hidden[offset:] |= (starts & (length > offset))[:frames - offset]
    hidden &= np.arange(shape[-1])[None, None, None, :] < stripes[None, None, :, None]
    return hidden


# -- the capture ------------------------------------------------------------------------------------
@dataclass
class SynthResult:
    path: str
    frames: int
    cameras: int
    guides: int
    stripes: int  # dyed stripes over all guides
    images: int
    simulate_seconds: float
    render_seconds: float
    run: object = None  # the simulation's sim.RunResult


@dataclass
class _Recording:
    """What the simulation leaves for the renderer, frame by frame."""

    guides: np.ndarray = None  # strand indices
    lengths: np.ndarray = None  # the guides' rest lengths [m]
    frames: list = field(default_factory=list)
    head: list = field(default_factory=list)  # posed collider points
    guide_points: list = field(default_factory=list)  # (G, n, 3)
    hair: list = field(default_factory=list)  # other strands' points, when drawn
    hair_counts: np.ndarray = None
    hair_widths: np.ndarray = None
    hair_keep: np.ndarray = None  # per-particle mask of the strands that are not guides
    head_faces: np.ndarray = None
    extent: list = field(default_factory=list)  # a sample of the hair's points, per frame
    extent_keep: np.ndarray = None

    def reach(self):
        """Centre of the hair's swept bounding box and the farthest sampled point from it."""
        points = np.concatenate(self.extent).astype(np.float64)
        centre = 0.5 * (points.min(0) + points.max(0))
        return centre, float(np.linalg.norm(points - centre, axis=1).max())


def synthesize(scene_config, capture_config, out_dir, progress=True):
    """Simulate `scene_config` and write a capture directory (docs/capture_format.md) to out_dir.

    The directory is built under a temporary name beside out_dir and renamed only when complete, so
    an error leaves no partial capture; an existing capture at out_dir is replaced, any other
    non-empty folder is refused. Returns a SynthResult."""
    from .scene import run_scene

    c = capture_config
    out_dir = os.path.abspath(os.fspath(out_dir))
    _check_output(out_dir)
    if not scene_config.hair.enabled:
        raise InputError(scene_config.source, "hair.enabled", "a hair capture needs hair")
    longest = scene_config.hair.length * (1.0 + scene_config.hair.length_jitter)
    if longest < c.stripe_width:
        raise InputError(scene_config.source, "capture.stripe_width",
                         f"{c.stripe_width} m is longer than the longest strand ({longest:.3f} m)")
    parent = os.path.dirname(out_dir)
    os.makedirs(parent, exist_ok=True)
    tmp = os.path.join(parent, f".{os.path.basename(out_dir)}.partial-{os.getpid()}")
    if os.path.exists(tmp):
        shutil.rmtree(tmp)
    os.makedirs(tmp)
    try:
        started = time.perf_counter()
        record = _Recording()
        run = run_scene(scene_config, os.path.join(tmp, "simulation.usdc"), progress,
                        on_frame=lambda frame, scene: _record(record, frame, scene, scene_config, c))
        simulated = time.perf_counter() - started
        try:
            cameras = rig_cameras(c, *record.reach())
        except ValueError as err:
            raise InputError(scene_config.source, f"capture.{str(err).split()[0]}", str(err)) from None
        result = _write_capture(tmp, record, cameras, scene_config, c, progress)
        _replace_dir(tmp, out_dir)
    finally:
        if os.path.exists(tmp):
            shutil.rmtree(tmp, ignore_errors=True)
    run.path = os.path.join(out_dir, "simulation.usdc")
    result.path, result.run, result.simulate_seconds = out_dir, run, simulated
    result.render_seconds = time.perf_counter() - started - simulated
    return result


def _record(record, frame, scene, scene_config, c):
    model = scene.model
    x = scene.state.x.numpy()
    start = model.strand_start_np
    if record.guides is None:
        eligible = model.natural_length_np >= c.stripe_width
        try:
            record.guides = choose_guides(x[start[:-1]], c.guides, c.seed, eligible)
        except ValueError as err:
            raise InputError(scene_config.source, "capture.guides", str(err)) from None
        record.lengths = model.natural_length_np[record.guides].astype(np.float64)
        record.head_faces = np.asarray(scene.head.faces, np.int32)
        every = max(1, model.num_strands // 400)  # a few hundred strands are enough to frame the hair
        record.extent_keep = np.repeat(np.arange(model.num_strands) % every == 0, model.counts)
        others = np.setdiff1d(np.arange(model.num_strands), record.guides)
        record.hair_counts = model.counts[others]
        keep = np.repeat(np.isin(np.arange(model.num_strands), others), model.counts)
        record.hair_widths = model.widths_np[keep]
        record.hair_keep = keep
    g = record.guides
    n = int(model.counts[g].max())
    # a shorter guide repeats its tip: zero-length segments change neither arc length nor stripes
    index = np.minimum(start[g][:, None] + np.arange(n)[None, :], (start[g + 1] - 1)[:, None])
    record.frames.append(int(frame))
    record.head.append(np.asarray(scene.collider.posed_points(), np.float32).copy())
    record.guide_points.append(x[index].astype(np.float64))
    if c.background_hair:
        record.hair.append(x[record.hair_keep].copy())
    record.extent.append(np.concatenate([x[record.extent_keep], record.guide_points[-1].reshape(-1, 3)]))


def _write_capture(folder, record, cameras, scene_config, c, progress):
    """Truth, images and capture.json of a recorded run, into `folder`."""
    frames = np.asarray(record.frames, np.int64)
    guides = np.stack(record.guide_points)  # (F, G, n, 3)
    f_count, g_count, n = guides.shape[:3]
    # whole stripes of the rest length: the solver keeps every segment at its rest length
    stripes = np.floor(record.lengths / c.stripe_width + 1e-9).astype(np.int64)
    k_max = int(stripes.max())
    centres = stripe_centres(guides.reshape(-1, n, 3), np.tile(stripes, f_count), c.stripe_width, k_max)
    centres = centres.reshape(f_count, g_count, k_max, 3)
    hidden = occlusion_mask(f_count, len(cameras), stripes, c.occlusion, c.occlusion_frames,
                            np.random.default_rng(c.seed + 1))
    visible = _render_views(folder, record, cameras, c, guides, stripes, hidden, progress)
    labels = {cam.name: _labels(cam, centres[0], visible[0, i], c.width, c.height) for i, cam in enumerate(cameras)}

    np.savez(os.path.join(folder, "truth.npz"), stripe_centres=centres, guide_points=guides, frames=frames,
             occluded=hidden, visible=visible, guide_strands=record.guides.astype(np.int64),
             cameras=np.array([cam.name for cam in cameras]))
    description = {
        "version": 1,
        "fps": float(scene_config.timing.fps),
        "frames": [int(f) for f in frames],
        "image_size": [c.width, c.height],
        "units": "m",
        "stripe": {"width": c.stripe_width, "colors": list(STRIPE_COLORS)},
        "guides": [{"name": f"g{g:02d}", "root": guides[0, g, 0].tolist(), "stripes": int(stripes[g])}
                   for g in range(g_count)],
        "cameras": [cam.to_json() for cam in cameras],
        "stereo": {"left": "stereo_l", "right": "stereo_r", "baseline": c.stereo_baseline},
        "first_frame_labels": labels,
    }
    _write_json(os.path.join(folder, "capture.json"), description)  # last: its presence marks a whole capture
    images = (f_count + 1) * len(cameras)
    return SynthResult(folder, f_count, len(cameras), g_count, int(stripes.sum()), images, 0.0, 0.0)


def _render_views(folder, record, cameras, c, guides, stripes, hidden, progress):
    """Write every camera's images and backgrounds; returns the share of each stripe each view
    sees, (frames, cameras, guides, max_stripes), NaN where a guide has fewer stripes."""
    from tqdm import tqdm

    from io_usd.preview import _smooth_normals, hair_colors

    from .scene import HAIR_COLOR, SKIN_COLOR

    k_max = int(stripes.max())
    no_stripe = np.arange(k_max)[None, :] >= stripes[:, None]
    segment = float(np.median(np.diff(arc_lengths(guides[0]), axis=1)))
    samples = int(np.clip(math.ceil(2.0 * c.stripe_width / max(segment, 1e-4)) + 1, 9, 33))
    colors = np.empty((len(stripes), k_max + 1, 3))
    colors[:] = HAIR_COLOR  # the undyed rest of a guide
    for k in range(k_max):
        colors[:, k] = np.where(no_stripe[:, k:k + 1], HAIR_COLOR, DYES[STRIPE_COLORS[k % 3]])
    hair_rgb = np.repeat(hair_colors(record.hair_counts, HAIR_COLOR, c.seed), 2, 0) if c.background_hair else None
    for cam in cameras:
        os.makedirs(os.path.join(folder, "images", cam.name))
    os.makedirs(os.path.join(folder, "background"))
    visible = np.full(hidden.shape, np.nan, np.float32)
    bar = tqdm(total=(len(guides) + 1) * len(cameras), unit="image", desc="rendering", file=sys.stderr,
               disable=not progress, dynamic_ncols=True)
    # noise and PNG compression run beside the renderer (both release the GIL); every image seeds
    # its own noise, so the result does not depend on which thread gets there first
    with bar, Studio(cameras, c.width, c.height) as studio, _Writer(folder, c.noise, c.seed, bar) as writer:
        for i, frame in enumerate(record.frames):
            head = record.head[i]
            studio.show("head", head, record.head_faces, _smooth_normals(head.astype(np.float64), record.head_faces),
                        color=SKIN_COLOR, double_sided=False)
            pieces, valid = stripe_samples(guides[i], stripes, c.stripe_width, samples)
            vertices, normals, rgb, faces, owner = tube_mesh(pieces, valid, 0.5 * c.guide_width, colors)
            dyed = owner[:, 1] < k_max
            for ci, cam in enumerate(cameras):
                if c.background_hair:
                    _show_hair(studio, cam, record.hair[i], record.hair_counts, record.hair_widths, hair_rgb)
                if i == 0:  # each camera's view without the dyed guides, for background subtraction
                    studio.hide("guides")
                    writer.save(studio.render(ci)[0], (-1, ci), "background", f"{cam.name}.png")
                drop = np.zeros(len(faces), bool)
                drop[dyed] = hidden[i, ci][owner[dyed, 0], owner[dyed, 1]]
                studio.show("guides", vertices, faces[~drop], normals, colors=rgb)
                image, depth = studio.render(ci)
                writer.save(image, (i, ci), "images", cam.name, f"{frame:04d}.png")
                seen = stripe_visibility(cam, pieces[:, :k_max], depth, c.guide_width)
                seen[hidden[i, ci]] = 0.0
                seen[no_stripe] = np.nan
                visible[i, ci] = seen
    return visible


class _Writer:
    """Adds sensor noise to images and writes them as PNG on two worker threads."""

    def __init__(self, folder, noise, seed, bar, workers=2):
        from concurrent.futures import ThreadPoolExecutor

        self.folder, self.noise, self.seed, self.bar = folder, noise, seed, bar
        self._pool = ThreadPoolExecutor(workers)
        self._pending = []

    def save(self, image, key, *path):
        while len(self._pending) > 8:  # bound the images held in memory
            self._pending.pop(0).result()
        self._pending.append(self._pool.submit(self._write, image, key, os.path.join(self.folder, *path)))

    def _write(self, image, key, path):
        from PIL import Image

        if self.noise > 0.0:
            rng = np.random.default_rng([self.seed, 2, key[0] + 1, key[1]])
            noisy = rng.standard_normal(image.shape, dtype=np.float32)
            noisy *= self.noise
            noisy += image
            image = np.clip(np.rint(noisy, out=noisy), 0, 255, out=noisy).astype(np.uint8)
        Image.fromarray(image).save(path, format="PNG", compress_level=1)
        self.bar.update(1)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        try:
            for future in self._pending:
                future.result()
        finally:
            self._pool.shutdown(wait=True, cancel_futures=True)
        return False


def _show_hair(studio, camera, points, counts, widths, rgb):
    from io_usd.preview import hair_ribbons

    eye = camera.centre
    distance = np.linalg.norm(points - eye, axis=1)
    vertices, faces, normals = hair_ribbons(points, counts, widths, eye, roundness=0.3,
                                            min_width=HAIR_PIXELS * distance / camera.K[0, 0])
    studio.show("hair", vertices, faces, normals, colors=rgb.astype(np.float32))


def _labels(camera, centres, seen, width, height):
    """The first frame's naming in one camera: every stripe it sees, at its centre's projection."""
    out = []
    uv = camera.project(centres.reshape(-1, 3)).reshape(centres.shape[:-1] + (2,))
    for g, k in zip(*np.nonzero(np.nan_to_num(seen) >= VISIBLE_SHARE)):
        u, v = uv[g, k]
        if 0.0 <= u < width and 0.0 <= v < height:
            out.append({"guide": int(g), "stripe": int(k), "uv": [float(u), float(v)]})
    return out


def _write_json(path, data):
    with open(path, "w") as f:
        json.dump(data, f, indent=1)
        f.write("\n")


def _check_output(out_dir):
    from io_usd.output_file import check_output_folder

    check_output_folder(out_dir)
    if os.path.exists(out_dir):
        if os.listdir(out_dir) and not os.path.isfile(os.path.join(out_dir, "capture.json")):
            raise InputError(out_dir, None, "is a non-empty folder that is not a capture; refusing to overwrite it")


def _replace_dir(tmp, out_dir):
    old = None
    if os.path.exists(out_dir):
        old = f"{out_dir}.old-{os.getpid()}"
        os.rename(out_dir, old)
    os.rename(tmp, out_dir)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


# -- scene files and the command line ---------------------------------------------------------------
def load_capture_scene(path, overrides=None, capture_overrides=None):
    """A scene file with a [capture] table -> (SceneConfig, CaptureConfig). overrides as for
    sim.load_scene; capture_overrides {"width": 1920, ...} replace [capture] keys."""
    from .scene import load_scene

    overrides = dict(overrides or {})
    if capture_overrides:
        overrides["capture"] = dict(capture_overrides)
    config = load_scene(path, overrides)
    return config, config.capture


def add_synth_arguments(parser):
    """Options of `cfx capture synth SCENE -o DIR`."""
    parser.add_argument("scene", help="TOML scene; its [capture] table sets the guides, cameras and images")
    parser.add_argument("-o", "--output", required=True, help="capture directory to write")
    parser.add_argument("--frames", type=int, help="override the number of frames")
    parser.add_argument("--size", help="WIDTHxHEIGHT of the images, e.g. 1920x1080")
    parser.add_argument("--noise", type=float, help="per-pixel Gaussian noise, standard deviation in 8-bit levels")
    parser.add_argument("--occlusion", type=float, help="share of stripe-frames hidden on purpose per camera, [0, 1)")
    parser.add_argument("--guides", type=int, help="number of dyed guide hairs")
    parser.add_argument("--seed", type=int, help="seed of the guide choice, noise and occlusion")
    parser.add_argument("--background-hair", action=argparse.BooleanOptionalAction, default=None,
                        help="also draw the undyed hair, which hides parts of the guides")
    parser.add_argument("--device", help="override the simulation device (cpu, cuda, cuda:0)")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars")


def run_synth(args):
    """`cfx capture synth`: returns the exit status (errors are raised as InputError / SimulationError)."""
    scene = {}
    if args.frames is not None:
        scene["frames"] = args.frames
    if args.device:
        scene["device"] = args.device
    capture = {key: getattr(args, key) for key in ("noise", "occlusion", "guides", "seed", "background_hair")
               if getattr(args, key) is not None}
    if args.size:
        try:
            width, height = (int(v) for v in args.size.lower().split("x"))
        except ValueError:
            raise InputError("command line", "--size",
                             f"expected WIDTHxHEIGHT, e.g. 1920x1080, got {args.size!r}") from None
        capture.update(width=width, height=height)
    scene_config, capture_config = load_capture_scene(args.scene, {"scene": scene}, capture)
    out = os.path.realpath(args.output) + os.sep
    if os.path.realpath(args.scene).startswith(out):  # the capture folder is replaced whole
        raise InputError(args.output, None, f"holds the scene file {args.scene}, which replacing the capture would "
                                            "delete; choose another output")
    result = synthesize(scene_config, capture_config, args.output, progress=not args.quiet)
    print(f"wrote {result.path}: {result.frames} frames from {result.cameras} cameras, {result.guides} guides with "
          f"{result.stripes} stripes; simulated in {result.simulate_seconds:.1f} s, rendered {result.images} images "
          f"in {result.render_seconds:.1f} s", file=sys.stderr)
    return 0
