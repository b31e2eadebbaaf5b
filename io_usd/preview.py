"""Offscreen previews of caches: PNG stills, contact sheets, and MP4 or GIF playback of the timeline.

Rendering goes through pyrender on EGL, so it needs no display. pyrender is imported lazily (inside
functions, after choosing the GL platform) so that importing this module stays cheap and does not
claim OpenGL for a process that may later want the on-screen viewer.

Hair is drawn as camera-facing ribbons about two pixels wide: real strands are ~0.1 mm, far below a
pixel, and would otherwise vanish or alias into noise.
"""

import contextlib
import dataclasses
import functools
import math
import os
import sys

import numpy as np

from .cache import CacheReader, fan_triangles
from .output_file import check_output_path, discard, publish, temporary_beside

# Background is written by glClear, so it is a display (sRGB) value; material colours are linear.
BACKGROUND = (0.86, 0.86, 0.85)
DEFAULT_COLORS = {
    "hair": (0.16, 0.085, 0.04),
    "hair_card": (0.16, 0.085, 0.04),
    "collider": (0.74, 0.48, 0.37),
    "face": (0.74, 0.48, 0.37),
    "cloth": (0.28, 0.36, 0.50),
    "cloth_detail": (0.28, 0.36, 0.50),
}
FALLBACK_COLOR = (0.5, 0.5, 0.5)
HAIR_PIXELS = 1.75  # on-screen width a strand is never drawn thinner than
EXTENSIONS = (".png", ".mp4", ".gif")
# Images are drawn this many times wider and taller, one sample per pixel, and averaged down, instead
# of through pyrender's 4x multisampled framebuffer: llvmpipe (Mesa's software GL, what EGL gives a
# machine without a GPU) rasterises multisampled triangles several times slower, and our pictures
# are mostly thin hair triangles. The same four samples per pixel, each shaded: the demo's preview
# frame 830 -> 270 ms, a close-up of its hair 1280 -> 800 ms, a capture image 390 -> 280 ms.
SUPERSAMPLE = 2
# Named views, (camera yaw about +Y from the front (+Z), pitch above the horizon) in degrees. The
# character faces +Z, so "left" looks at its left side (+X). A pitch of 90 would leave look_at's up
# vector undefined; "top" looks down steeply enough to show the crown and the parting.
VIEWS = {
    "three-quarter": (25.0, 10.0),
    "front": (0.0, 0.0),
    "left": (90.0, 0.0),
    "right": (-90.0, 0.0),
    "back": (180.0, 0.0),
    "top": (0.0, 75.0),
}
TURNAROUND = ("front", "left", "back", "right")


def _pyrender():
    """pyrender, imported on first use with the offscreen EGL platform unless one was chosen (or
    the on-screen viewer already imported it)."""
    if "pyrender" in sys.modules:
        return sys.modules["pyrender"]
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    if not hasattr(np, "infty"):  # pyrender 0.1.45 still uses the alias numpy 2 removed
        np.infty = np.inf
    import pyrender

    return pyrender


# -- camera -----------------------------------------------------------------------------------------
@dataclasses.dataclass
class Camera:
    """A pinhole camera: vertical field of view, image size and a camera-to-world pose.

    The pose follows OpenGL / pyrender: the camera looks down its local -Z with +Y up. Pixel
    coordinates put (0, 0) at the top-left corner of the image, u to the right, v down, so the
    centre of pixel (row r, column c) is at (c + 0.5, r + 0.5).
    """

    yfov: float
    width: int
    height: int
    pose: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
    znear: float = 0.01
    zfar: float = 100.0

    @classmethod
    def look_at(cls, eye, target, up=(0.0, 1.0, 0.0), yfov=0.6, width=960, height=720, znear=0.01, zfar=100.0):
        eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
        forward = target - eye
        if np.linalg.norm(forward) == 0:
            raise ValueError("look_at: eye and target are the same point")
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, up)
        if np.linalg.norm(right) < 1e-9:  # looking straight along `up`: any perpendicular will do
            right = np.cross(forward, [1.0, 0.0, 0.0] if abs(forward[0]) < 0.9 else [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        pose = np.eye(4)
        pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, np.cross(right, forward), -forward, eye
        return cls(float(yfov), int(width), int(height), pose, float(znear), float(zfar))

    @classmethod
    def frame_points(cls, points, width, height, yaw_degrees=25.0, pitch_degrees=10.0, yfov=0.6, margin=1.12):
        """A camera looking from the front (+Z) turned by yaw about Y and raised by pitch, panned and
        pulled back just enough that every point is in view with `margin` to spare, their image
        centred."""
        points = np.asarray(points, np.float64).reshape(-1, 3)
        centre = 0.5 * (points.min(0) + points.max(0))
        yaw, pitch = math.radians(yaw_degrees), math.radians(pitch_degrees)
        back = np.array([math.sin(yaw) * math.cos(pitch), math.sin(pitch), math.cos(yaw) * math.cos(pitch)])
        axes = cls.look_at(centre + back, centre).pose[:3, :3]
        local = (points - centre) @ axes  # right, up, back components
        tan_y = math.tan(0.5 * yfov) / margin
        tangents = (tan_y * width / height, tan_y)
        # From eye = centre + a right + b up + d back, a point (x, y, z) is in view when
        # d >= z + |x - a| / tan_x (and likewise for y, b). Per axis the largest such bound is
        # smallest with the offset that balances the two sides.
        offset, distance = np.zeros(2), 0.0
        for k, tan in enumerate(tangents):
            lower = np.max(local[:, 2] + local[:, k] / tan)
            upper = np.max(local[:, 2] - local[:, k] / tan)
            offset[k] = 0.5 * tan * (lower - upper)
            distance = max(distance, 0.5 * (lower + upper))
        radius = max(float(np.linalg.norm(local, axis=1).max()), 1e-3)
        distance = max(distance, float(local[:, 2].max()) + 1e-3 * radius)
        eye = centre + axes @ np.array([offset[0], offset[1], distance])
        camera = cls.look_at(eye, eye - back, yfov=yfov, width=width, height=height,
                             znear=max(1e-4, 0.5 * (distance - float(local[:, 2].max()))),
                             zfar=distance + 4.0 * radius)
        # the axis with room to spare is centred only approximately; pan it the rest of the way
        for _ in range(2):
            uv = camera.project(points)
            du, dv = 0.5 * (uv.min(0) + uv.max(0)) - (0.5 * width, 0.5 * height)
            camera.pose[:3, 3] += (du * axes[:, 0] - dv * axes[:, 1]) * distance / camera.focal
        return camera

    @classmethod
    def frame_bounds(cls, lo, hi, width, height, yaw_degrees=25.0, pitch_degrees=10.0, yfov=0.6, margin=1.12):
        """A camera that sees the whole box lo..hi (see frame_points), its image centred."""
        lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        return cls.frame_points(corners, width, height, yaw_degrees, pitch_degrees, yfov, margin)

    @property
    def eye(self):
        return np.asarray(self.pose, np.float64)[:3, 3].copy()

    @property
    def focal(self):
        """Focal length in pixels (square pixels, so the same horizontally and vertically)."""
        return 0.5 * self.height / math.tan(0.5 * self.yfov)

    def intrinsics(self):
        """3x3 K for the pixel convention in the class docstring."""
        f = self.focal
        return np.array([[f, 0.0, 0.5 * self.width], [0.0, f, 0.5 * self.height], [0.0, 0.0, 1.0]])

    def to_camera(self, points):
        """World points (N, 3) in camera coordinates (x right, y up, -z forward)."""
        pose = np.asarray(self.pose, np.float64)
        return (np.asarray(points, np.float64).reshape(-1, 3) - pose[:3, 3]) @ pose[:3, :3]

    def depth(self, points):
        """Distance in front of the camera along its view axis; <= 0 means behind it."""
        return -self.to_camera(points)[:, 2]

    def project(self, points):
        """World points (N, 3) to pixel coordinates (N, 2); points not in front of the camera give NaN."""
        local = self.to_camera(points)
        depth = -local[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack([local[:, 0] / depth, -local[:, 1] / depth], 1) * self.focal
        uv += (0.5 * self.width, 0.5 * self.height)
        uv[depth <= 0] = np.nan
        return uv


# -- hair ribbons -----------------------------------------------------------------------------------
def _per_vertex(values, counts, default=0.0):
    """Per-vertex values from vertex, per-curve or constant USD interpolation."""
    n = int(np.sum(counts))
    values = None if values is None else np.asarray(values, np.float64).reshape(-1)
    if values is None or values.size == 0:  # none authored
        return np.full(n, default, np.float64)
    if values.size == n:
        return values
    if values.size == len(counts):
        return np.repeat(values, counts)
    if values.size == 1:
        return np.full(n, values[0])
    raise ValueError(f"{values.size} values fit neither {n} vertices nor {len(counts)} curves")


def _normalize(v, fallback=None):
    length = np.linalg.norm(v, axis=-1, keepdims=True)
    out = v / np.maximum(length, 1e-30)
    if fallback is not None:
        bad = length[..., 0] < 1e-12
        out[bad] = fallback[bad] if np.ndim(fallback) > 1 else fallback
    return out


def strand_tangents(points, counts):
    """Per-vertex tangent (not normalised): the chord between a vertex's neighbours on its strand,
    one-sided at the root and tip."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    counts = np.asarray(counts, np.int64)
    starts = np.cumsum(counts) - counts
    strand = np.repeat(np.arange(len(counts)), counts)
    index = np.arange(len(points))
    prev = np.maximum(index - 1, starts[strand])
    nxt = np.minimum(index + 1, starts[strand] + counts[strand] - 1)
    return points[nxt] - points[prev]


def hair_ribbons(points, counts, widths, eye, min_width=0.0, roundness=0.6, twist=None):
    """Camera-facing ribbons for linear curves.

    points (N, 3), counts (S,) vertices per strand, widths per vertex (or per strand, or one value),
    eye (3,) the camera position, min_width a scalar or per-vertex world width the caller picks so a
    strand covers a pixel or two. Each vertex becomes two, vertex 2i = P_i - a_i w_i / 2 and
    2i + 1 = P_i + a_i w_i / 2, where the across-direction a_i is perpendicular to the tangent
    (`strand_tangents`) and to the direction to the eye. Each segment becomes two triangles wound
    to face the eye. Normals start from the view direction (made perpendicular to the tangent),
    turned about the tangent by the per-strand angle `twist` (radians, optional) so neighbouring
    strands catch the light differently, then lean towards -a and +a by `roundness` so a ribbon
    shades like a thin cylinder. Segments come nearest the eye first, so that a depth test rejects
    the strands behind before they are shaded (llvmpipe: a close-up of the demo's hair 960 -> 760 ms).

    Returns (vertices (2N, 3) float32, faces (2 * segments, 3) int32, normals (2N, 3) float32).
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    counts = np.asarray(counts, np.int64)
    n = len(points)
    if int(counts.sum()) != n:
        raise ValueError(f"hair_ribbons: counts add up to {int(counts.sum())}, but there are {n} points")
    tangent = _normalize(strand_tangents(points, counts))
    to_eye = np.asarray(eye, np.float64) - points
    view = _normalize(to_eye, fallback=np.array([0.0, 0.0, 1.0]))
    # a strand seen end-on has no defined across-direction; any perpendicular to the view will do
    side = np.where(np.abs(view[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    across = _normalize(np.cross(tangent, view), fallback=_normalize(np.cross(side, view)))

    width = np.maximum(_per_vertex(widths, counts), np.broadcast_to(np.asarray(min_width, np.float64), (n,)))
    half = 0.5 * width[:, None] * across
    vertices = np.empty((2 * n, 3))
    vertices[0::2], vertices[1::2] = points - half, points + half

    facing = _normalize(view - np.sum(view * tangent, 1, keepdims=True) * tangent, fallback=view)
    if twist is not None:  # (tangent, across, facing) is orthonormal, so this rotates about the tangent
        angle = np.repeat(np.broadcast_to(np.asarray(twist, np.float64), counts.shape), counts)[:, None]
        facing = np.cos(angle) * facing + np.sin(angle) * across
    normals = np.empty((2 * n, 3))
    normals[0::2] = _normalize(facing - roundness * across)
    normals[1::2] = _normalize(facing + roundness * across)

    has_next = np.ones(n, bool)
    has_next[(np.cumsum(counts) - 1)[counts > 0]] = False
    first = np.flatnonzero(has_next)
    i = 2 * first[np.argsort(np.einsum("ij,ij->i", to_eye[first], to_eye[first]), kind="stable")]
    faces = np.stack([np.stack([i, i + 1, i + 3], 1), np.stack([i, i + 3, i + 2], 1)], 1).reshape(-1, 3)
    return vertices.astype(np.float32), faces.astype(np.int32), normals.astype(np.float32)


def hair_colors(counts, color=None, seed=0, variation=0.15, root=0.4):
    """Per-vertex linear RGB (N, 3): the base colour with a seeded per-strand variation in brightness
    and warmth, darkened towards the root where real hair is shadowed by the strands around it."""
    counts = np.asarray(counts, np.int64)
    base = np.asarray(color if color is not None else DEFAULT_COLORS["hair"], np.float64)
    rng = np.random.default_rng(seed)
    brightness = np.exp(variation * rng.standard_normal(len(counts)))
    warmth = 1.0 + 0.4 * variation * rng.standard_normal(len(counts))
    strand_rgb = base * brightness[:, None] * np.stack([warmth, np.ones_like(warmth), 1.0 / warmth], 1)
    starts = np.cumsum(counts) - counts
    strand = np.repeat(np.arange(len(counts)), counts)
    along = (np.arange(int(counts.sum())) - starts[strand]) / np.maximum(counts[strand] - 1, 1)
    ramp = root + (1.0 - root) * np.minimum(1.0, along / 0.6) ** 0.8
    return np.clip(strand_rgb[strand] * ramp[:, None], 0.0, 1.0)


# -- scenes -----------------------------------------------------------------------------------------
def _smooth_normals(vertices, faces):
    face_n = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
    normals = np.zeros_like(vertices, dtype=np.float64)
    for k in range(3):  # area-weighted, since the cross product's length is twice the area
        np.add.at(normals, faces[:, k], face_n)
    return _normalize(normals, fallback=np.array([0.0, 1.0, 0.0]))


class SceneBuilder:
    """Turns one cache frame into pyrender meshes. Topology and hair colours are computed once."""

    def __init__(self, reader, seed=0, hair_pixels=HAIR_PIXELS, names=None):
        self.reader = reader
        self.names = names  # draw only these prims (default: all)
        self.seed = seed
        self.hair_pixels = hair_pixels
        self._triangles = {}
        self._strand_looks = {}
        self._materials = {}

    def _color(self, prim):
        return prim.color if prim.color is not None else DEFAULT_COLORS.get(prim.role, FALLBACK_COLOR)

    def _material(self, prim, pyrender):
        if prim.name not in self._materials:
            curves = prim.kind == "curves"
            painted = curves or prim.vertex_colors is not None  # these carry vertex colours
            rgb = (1.0, 1.0, 1.0) if painted else self._color(prim)
            self._materials[prim.name] = pyrender.MetallicRoughnessMaterial(
                baseColorFactor=(*rgb, 1.0), metallicFactor=0.0, roughnessFactor=0.45 if curves else 0.65,
                doubleSided=prim.role != "collider")
        return self._materials[prim.name]

    def mesh(self, name, frame, eye, focal):
        """pyrender.Mesh of prim `name` at `frame`; curves face `eye`, at least hair_pixels wide for
        a camera with `focal` pixels focal length. None for an empty prim."""
        pyrender = _pyrender()
        prim = self.reader.prims[name]
        points = self.reader.points(name, frame)
        if len(points) == 0:
            return None
        if prim.kind == "curves":
            # strands cut, grown or erased (a haircut) change the counts from frame to frame
            counts = self.reader.counts(name, frame)
            widths = self.reader.widths(name, frame) if prim.varying else prim.widths
            key = (name, counts.tobytes()) if prim.varying else name
            if key not in self._strand_looks:
                colors = np.repeat(hair_colors(counts, self._color(prim), self.seed), 2, 0)
                twist = np.random.default_rng(self.seed + 1).normal(0.0, 0.6, len(counts))
                self._strand_looks[key] = colors, twist
            colors, twist = self._strand_looks[key]
            distance = np.linalg.norm(points - np.asarray(eye, np.float32), axis=1)
            vertices, faces, normals = hair_ribbons(points, counts, widths, eye, twist=twist,
                                                    min_width=self.hair_pixels * distance / focal)
        else:
            if name not in self._triangles:
                self._triangles[name] = fan_triangles(prim.counts, prim.indices)
            faces = self._triangles[name]
            normals = self.reader.normals(name, frame) if prim.role == "cloth_detail" else None
            if normals is None or len(normals) != len(points):
                normals = _smooth_normals(points.astype(np.float64), faces)
            vertices, colors = points, prim.vertex_colors
            if colors is not None and len(colors) != len(points):
                colors = None
        primitive = pyrender.Primitive(positions=vertices, normals=normals, indices=faces, color_0=colors,
                                       material=self._material(prim, pyrender))
        return pyrender.Mesh([primitive], name=name)

    def meshes(self, frame, eye, focal):
        # a garment's detail surface replaces its coarse simulation mesh in the picture
        has_detail = any(p.role == "cloth_detail" for p in self.reader.prims.values())
        names = [n for n, p in self.reader.prims.items() if not (has_detail and p.role == "cloth")
                 and (self.names is None or n in self.names)]
        out = {name: self.mesh(name, frame, eye, focal) for name in names}
        return {k: v for k, v in out.items() if v is not None}


def _light_direction(camera_pose, azimuth_degrees, elevation_degrees):
    """World direction towards a light given relative to the camera: azimuth turns it to the right
    of the camera, elevation raises it; 180 azimuth is behind the subject."""
    az, el = math.radians(azimuth_degrees), math.radians(elevation_degrees)
    local = np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])
    return np.asarray(camera_pose, np.float64)[:3, :3] @ local


@functools.lru_cache(maxsize=None)
def _key_light(pyrender):
    """pyrender's DirectionalLight with its shadow map fitted to the scene's bounding sphere.

    pyrender spans the map over twice the scene's diagonal, so only a quarter of its texels land
    on the subject; fitting it halves the texel size, which sharpens hair shadows and narrows the
    shadow acne band along the terminator. Relies on the private hook _get_shadow_camera
    (pyrender 0.1.45), with the depth range left as pyrender sets it since its bias scales with it.
    """

    class KeyLight(pyrender.DirectionalLight):
        def _get_shadow_camera(self, scene_scale):
            return pyrender.OrthographicCamera(xmag=0.55 * scene_scale, ymag=0.55 * scene_scale,
                                               znear=0.01 * scene_scale, zfar=10 * scene_scale)

    return KeyLight


def build_scene(builder, frame, camera, background=BACKGROUND):
    """A pyrender.Scene of the frame seen by `camera`. The lights follow the camera so every view
    angle reads the same: a directional key (the only one that casts shadows, since pyrender
    shadows every directional light and fill shadows just streak the face), and a fill and a rim
    as distant point lights. Drawn at any multiple of the camera's size (SupersampledOffscreen), it
    shows the same picture, strands as wide in the camera's pixels."""
    pyrender = _pyrender()
    scene = pyrender.Scene(bg_color=np.array([*background, 1.0], np.float64), ambient_light=np.full(3, 0.25))
    for name, mesh in builder.meshes(frame, camera.eye, camera.focal).items():
        scene.add(mesh, name=name)
    scene.add(pyrender.PerspectiveCamera(yfov=camera.yfov, aspectRatio=camera.width / camera.height,
                                         znear=camera.znear, zfar=camera.zfar), pose=camera.pose)
    key = _light_direction(camera.pose, -35, 40)
    scene.add(_key_light(pyrender)(color=np.ones(3), intensity=3.0),
              pose=Camera.look_at(key, np.zeros(3)).pose)  # a light shines down its -Z
    centre, far = scene.centroid, 3.0 * max(scene.scale, 1e-3)
    for azimuth, elevation, intensity in ((55, 0, 1.1), (165, 35, 2.0)):  # fill, rim
        pose = np.eye(4)
        pose[:3, 3] = centre + far * _light_direction(camera.pose, azimuth, elevation)
        scene.add(pyrender.PointLight(color=np.ones(3), intensity=intensity * far * far), pose=pose)
    return scene


@contextlib.contextmanager
def _single_sampled(pyrender):
    """pyrender's main framebuffer allocated with one sample per pixel while inside: it always asks
    for 4 (pyrender 0.1.45), so the module's GL entry point is swapped for the call and put back."""
    module = sys.modules[pyrender.Renderer.__module__]
    allocate = module.glRenderbufferStorageMultisample
    module.glRenderbufferStorageMultisample = lambda target, _samples, *size: allocate(target, 0, *size)
    try:
        yield
    finally:
        module.glRenderbufferStorageMultisample = allocate


class SupersampledOffscreen:
    """pyrender's offscreen renderer for width x height images drawn `supersample` times wider and
    taller, one sample per pixel, and averaged down (see SUPERSAMPLE). A perspective camera (field
    of view and aspect ratio) sees the same at any size; an intrinsics camera's focal lengths and
    principal point must be given in drawn pixels, `supersample` times the image's."""

    def __init__(self, width, height, supersample=SUPERSAMPLE):
        """Near the GL's largest framebuffer, fewer samples are drawn; beyond it, ValueError."""
        from OpenGL.GL import GL_MAX_RENDERBUFFER_SIZE, glGetIntegerv

        if int(supersample) < 1:
            raise ValueError(f"supersample must be 1 or more, got {supersample}")
        self.width, self.height = int(width), int(height)
        self._pyrender = _pyrender()
        self._gl = self._pyrender.OffscreenRenderer(self.width, self.height)  # its context is now current
        limit = int(glGetIntegerv(GL_MAX_RENDERBUFFER_SIZE))
        if max(self.width, self.height) > limit:
            self.delete()
            raise ValueError(f"image size {self.width}x{self.height}: larger than this GL draws "
                             f"({limit} pixels a side)")
        self.supersample = min(int(supersample), limit // max(self.width, self.height))
        self.resize(self.width, self.height)

    def resize(self, width, height):
        self.width, self.height = int(width), int(height)
        s = self.supersample
        self._gl.viewport_width, self._gl.viewport_height = self.width * s, self.height * s

    def render(self, scene, flags, **options):
        """(H, W, 3) uint8 image of a scene built for the drawn size: each pixel the mean of its
        samples (a multisample resolve's box filter)."""
        return self.render_with_depth(scene, flags, depth=False, **options)[0]

    def render_with_depth(self, scene, flags, depth=True, **options):
        """(image, depth): render's image and (H, W) float32 the distance along the view axis of
        the nearest surface any of a pixel's samples saw, 0 where all saw the background (as
        pyrender's depth); None with depth=False."""
        from PIL import Image

        with _single_sampled(self._pyrender):
            color, drawn_depth = self._gl.render(scene, flags=flags, **options)
        color = np.ascontiguousarray(color[:, :, :3])
        s = self.supersample
        if s == 1:
            return color, drawn_depth if depth else None
        nearest = None
        if depth:
            drawn_depth = np.where(drawn_depth > 0.0, drawn_depth, np.inf)
            nearest = functools.reduce(np.minimum, (drawn_depth[i::s, j::s] for i in range(s) for j in range(s)))
            nearest[np.isinf(nearest)] = 0.0
        return np.asarray(Image.fromarray(color).reduce(s)), nearest

    def delete(self):
        if self._gl is not None:
            self._gl.delete()
            self._gl = None


class FrameRenderer:
    """One offscreen GL context for rendering many frames of one cache. Use as a context manager.
    Frames are drawn SUPERSAMPLE times larger and averaged down (see SUPERSAMPLE)."""

    def __init__(self, reader, width, height, background=BACKGROUND, seed=0, hair_pixels=HAIR_PIXELS,
                 shadows=True, names=None, supersample=SUPERSAMPLE):
        pyrender = _pyrender()
        self.builder = SceneBuilder(reader, seed=seed, hair_pixels=hair_pixels, names=names)
        self.background = background
        # shadow maps are what separate the outer hair from the inner and ground it on the skin
        self.flags = pyrender.RenderFlags.SHADOWS_DIRECTIONAL if shadows else pyrender.RenderFlags.NONE
        self._gl = SupersampledOffscreen(width, height, supersample)

    def render(self, frame, camera):
        """(camera.height, camera.width, 3) uint8 image of `frame`."""
        return self._draw(camera, build_scene(self.builder, frame, camera, self.background))

    def render_sequence(self, shots, camera_of):
        """The images of `shots`, (frame, view) pairs, in order, each seen by camera_of(frame, view).
        The next shot's scene is built on a second thread while the GL draws this one: its NumPy work
        and the wait for the GL both release the GIL."""
        from concurrent.futures import ThreadPoolExecutor

        shots = list(shots)

        def build(shot):
            camera = camera_of(*shot)
            return camera, build_scene(self.builder, shot[0], camera, self.background)

        with ThreadPoolExecutor(1) as pool:
            pending = [pool.submit(build, s) for s in shots[:1]]
            for k in range(len(shots)):
                camera, scene = pending.pop().result()
                pending += [pool.submit(build, s) for s in shots[k + 1:k + 2]]
                yield self._draw(camera, scene)

    def _draw(self, camera, scene):
        if (self._gl.width, self._gl.height) != (camera.width, camera.height):
            self._gl.resize(camera.width, camera.height)
        return self._gl.render(scene, self.flags)

    def close(self):
        if self._gl is not None:
            self._gl.delete()
            self._gl = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def render_frame(reader, frame, camera, renderer=None, **style):
    """(H, W, 3) uint8 image of `frame`. Pass a FrameRenderer to reuse its GL context across frames;
    style keywords (background, seed, hair_pixels, shadows) go to a FrameRenderer made for this call."""
    if renderer is not None:
        return renderer.render(frame, camera)
    with FrameRenderer(reader, camera.width, camera.height, **style) as own:
        return own.render(frame, camera)


def scene_points(reader, frames, names=None):
    """The points of prims `names` (default all) over `frames`, stacked (N, 3); a unit box's corners
    for an empty cache."""
    chunks = [reader.points(name, frame) for frame in frames for name in (names or reader.prims)]
    chunks = [c.reshape(-1, 3) for c in chunks if len(c)]
    if not chunks:
        return np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
    return np.concatenate(chunks)


def auto_camera(reader, width, height, frames=None, names=None, **view):
    """A camera framing prims `names` (default: everything) over `frames` (default: all), sampling at
    most five of them; view keywords (yaw_degrees, pitch_degrees, yfov, margin) go to Camera.frame_points."""
    frames = list(frames) if frames else reader.frames()
    picks = sorted({frames[int(round(k))] for k in np.linspace(0, len(frames) - 1, min(5, len(frames)))})
    return Camera.frame_points(scene_points(reader, picks, names), width, height, **view)


def focus_prims(reader, focus):
    """Names of the prims called `focus` or with role `focus` (e.g. "face"); ValueError if none."""
    names = [n for n, p in reader.prims.items() if focus in (n, p.role)]
    if not names:
        known = sorted(set(reader.prims) | {p.role for p in reader.prims.values()})
        raise ValueError(f"{reader.path}: nothing to focus on called '{focus}' (prims and roles: {', '.join(known)})")
    return names


# -- output -----------------------------------------------------------------------------------------
def _font(size):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1 has only the fixed bitmap font
        return ImageFont.load_default()


def contact_sheet(images, labels=None, columns=None, background=BACKGROUND):
    """A grid of equally sized (H, W, 3) uint8 images, `columns` wide (default: near-square),
    each labelled in its top-left corner. The sheet is columns * W by rows * H pixels."""
    from PIL import Image, ImageDraw

    if not len(images):
        raise ValueError("contact_sheet: no images")
    h, w = images[0].shape[:2]
    columns = int(columns) if columns else math.ceil(math.sqrt(len(images)))
    rows = math.ceil(len(images) / columns)
    fill = tuple(int(round(255 * c)) for c in background)
    sheet = Image.new("RGB", (columns * w, rows * h), fill)
    draw = ImageDraw.Draw(sheet)
    font = _font(max(9, h // 20))  # a caption, not a headline: at 720 lines a 36-pixel face keeps clear of the subject
    pad = max(2, h // 90)
    for k, image in enumerate(images):
        x, y = (k % columns) * w, (k // columns) * h
        sheet.paste(Image.fromarray(np.asarray(image, np.uint8)), (x, y))
        draw.rectangle([x, y, x + w - 1, y + h - 1], outline=(150, 150, 148))
        if labels is not None and k < len(labels):
            text = str(labels[k])
            box = draw.textbbox((x + 2 * pad, y + pad), text, font=font)
            draw.rectangle([box[0] - pad, box[1] - pad, box[2] + pad, box[3] + pad], fill=(40, 40, 40))
            draw.text((x + 2 * pad, y + pad), text, fill=(240, 240, 240), font=font)
    return sheet


def _choose_frames(cache_path, available, ext, frame, frames):
    if frame is not None and frames is not None:
        raise ValueError(f"{cache_path}: pass frame or frames, not both")
    have = set(available)
    if isinstance(frames, range):  # a range asks for what the cache has of it
        chosen = [f for f in frames if f in have]
        if not chosen:
            raise ValueError(f"{cache_path}: no frame of {frames.start}:{frames.stop - 1}:{frames.step} is in the "
                             f"cache (it has {len(available)} frames, {available[0]} to {available[-1]})")
    elif frames is not None:
        chosen = [int(f) for f in frames]
        if not chosen:
            raise ValueError(f"{cache_path}: frames is empty")
    elif frame is not None:
        chosen = [int(frame)]
    else:
        chosen = [available[-1]] if ext == ".png" else list(available)
    missing = [f for f in chosen if f not in have]
    if missing:
        raise ValueError(f"{cache_path}: frame {missing[0]} is not in the cache "
                         f"(it has {len(available)} frames, {available[0]} to {available[-1]})")
    return chosen


def write_images(images, labels, tmp, ext, fps, columns):
    """Write the rendered images (an iterable, consumed once) to tmp; movies stream frame by frame."""
    from PIL import Image

    if ext == ".mp4":
        import imageio.v2 as imageio

        writer = imageio.get_writer(tmp, format="FFMPEG", mode="I", fps=fps, codec="libx264", quality=8,
                                    macro_block_size=2, ffmpeg_log_level="error")
        # closed on failure too: imageio's context manager closes only on success, which left ffmpeg
        # running until garbage collection, writing tmp after the caller had cleaned it up
        try:
            for image in images:
                writer.append_data(image)
        finally:
            writer.close()
        return
    images = list(images)
    if ext == ".png":
        image = Image.fromarray(images[0]) if len(images) == 1 else contact_sheet(images, labels, columns)
        image.save(tmp, format="PNG")
    else:
        # Pillow folds a frame identical to the one before into it (adding its duration), so a
        # still stretch of the timeline plays at the right speed but reads back as fewer frames.
        frames = [Image.fromarray(im) for im in images]
        # browsers slow frames shorter than 20 ms down to 100 ms, so never ask for less
        frames[0].save(tmp, format="GIF", save_all=True, append_images=frames[1:], loop=0,
                       duration=max(20, int(round(1000.0 / fps))), disposal=1)


def resolve_views(views):
    """[(label, yaw, pitch)] for `views`: names from VIEWS, "turnaround" (front, left, back, right),
    or (yaw, pitch) pairs in degrees. None or empty is the three-quarter view."""
    resolved = []
    for view in views or ("three-quarter",):
        if isinstance(view, str):
            if view == "turnaround":
                resolved += [(name, *VIEWS[name]) for name in TURNAROUND]
            elif view in VIEWS:
                resolved.append((view, *VIEWS[view]))
            else:
                raise ValueError(f"unknown view {view!r}: use {', '.join(VIEWS)}, turnaround or YAW,PITCH in degrees")
        else:
            yaw, pitch = (float(a) for a in view)
            if not (math.isfinite(yaw) and math.isfinite(pitch) and -89.0 <= pitch <= 89.0):
                raise ValueError(f"view yaw {yaw:g}, pitch {pitch:g}: the pitch must be within -89 to 89 degrees")
            resolved.append((f"yaw {yaw:g}, pitch {pitch:g}", yaw, pitch))
    return resolved


def preview(cache_path, out_path, frame=None, frames=None, width=960, height=720, columns=None, camera=None,
            shadows=True, follow=False, focus=None, progress=True, views=None, labels=None):
    """Render a cache to an image or a movie and return out_path.

    The extension picks the output: .png is one frame (default the last) or, when `frames` lists
    several, a contact sheet of width x height tiles labelled with their frame numbers; .mp4 and .gif
    play `frames` (default all) at the cache's fps. A given camera sets the image size and view;
    otherwise one frames the whole scene from each of `views` (see resolve_views; default the
    three-quarter view), or with follow=True each frame on its own (a camera that tracks a walking
    character); focus (a prim name or role, e.g. "face") frames just those prims. Several views put
    their tiles side by side, labelled: one row of a .png's sheet per frame, one movie frame of them.
    labels: a contact sheet's tile labels, one per frame, instead of the frame numbers (one view).
    shadows=False saves about 40% of the render time on software GL; progress=False hides the progress
    bar. The file appears only once fully written.
    """
    cache_path, out_path = os.fspath(cache_path), os.fspath(out_path)
    ext = os.path.splitext(out_path)[1].lower()
    check_output_path(out_path, EXTENSIONS, "the preview")
    if camera is not None and views:
        raise ValueError(f"{out_path}: pass a camera or views, not both")
    try:
        angles = [(None, None, None)] if camera is not None else resolve_views(views)
    except ValueError as err:
        raise ValueError(f"{out_path}: {err}") from None
    if not os.path.isfile(cache_path):
        raise FileNotFoundError(f"{cache_path}: no such cache file")
    reader = CacheReader(cache_path)
    if not reader.prims:
        raise ValueError(f"{cache_path}: the cache has no cfx prims to draw")
    chosen = _choose_frames(cache_path, reader.frames(), ext, frame, frames)
    names = focus_prims(reader, focus) if focus else None
    if camera is None:
        if width <= 0 or height <= 0:
            raise ValueError(f"{out_path}: image size must be positive, got {width}x{height}")
        width, height = int(width), int(height)
        fixed = [auto_camera(reader, width, height, chosen, names, yaw_degrees=yaw, pitch_degrees=pitch)
                 for _, yaw, pitch in angles]
    else:
        width, height, fixed = camera.width, camera.height, [camera]
    if ext == ".mp4" and (width % 2 or height % 2):
        raise ValueError(f"{out_path}: MP4 needs an even width and height, got {width}x{height}")

    from tqdm import tqdm

    tmp = temporary_beside(out_path)
    bar = tqdm(total=len(chosen), desc=f"preview {os.path.basename(out_path)}", unit="frame", file=sys.stderr,
               disable=not progress or len(chosen) < 2, leave=False)
    view_labels = [label for label, _, _ in angles]
    several = len(angles) > 1
    if labels is not None:
        labels = [str(label) for label in labels]
        if several or len(labels) != len(chosen):
            raise ValueError(f"{out_path}: labels needs one label per frame ({len(chosen)}) and one view")
    elif not several:
        labels = [f"frame {f}" for f in chosen]
    elif len(chosen) == 1:
        labels = view_labels
    else:
        labels = [f"frame {f}, {label}" for f in chosen for label in view_labels]
    try:
        with FrameRenderer(reader, width, height, shadows=shadows) as renderer:
            def camera_of(f, k):
                if not follow:
                    return fixed[k]
                _, yaw, pitch = angles[k]
                return auto_camera(reader, width, height, [f], names, yaw_degrees=yaw, pitch_degrees=pitch)

            def images():
                shots = [(f, k) for f in chosen for k in range(len(angles))]
                row = []
                for image in renderer.render_sequence(shots, camera_of):
                    row.append(image)
                    if len(row) < len(angles):
                        continue
                    bar.update(1)
                    if several and ext != ".png":  # a movie frame holds every view
                        yield np.asarray(contact_sheet(row, view_labels, columns=len(row)))
                    else:
                        yield from row
                    row = []

            write_images(images(), labels, tmp, ext, reader.fps or 24.0, len(angles) if several else columns)
        publish(tmp, out_path)
    finally:
        bar.close()
        discard(tmp)
    return out_path
