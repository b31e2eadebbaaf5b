"""Face rig: a face mesh with named feature points, FACS action units, the 13 mouth parameters and
the six basic emotions, riding the same head the hair grows on.

Every action unit and every mouth parameter is a set of feature-point displacement vectors. The rest
of the face follows by interpolation: for each shape, a compactly supported radial basis (Wendland
C2) interpolant through its moved feature points and the feature points it must hold still (those
within its radius), evaluated in the face's unrolled surface coordinates. The result is one offset
field per shape, so the whole rig is a linear blend-shape rig: a frame is rest + sum(weight * offset),
applied by warp_kernels.skinning.blend_shape_bound_points on the posed head, and exported unchanged
as UsdSkel blend shapes.

Units: metres for geometry, millimetres for the authored displacement vectors (at AU intensity 1, or
per millimetre of a mouth parameter), given in each feature point's surface frame. Head-local axes:
Y up, the face looks down +Z, +X is the character's left.
"""

from dataclasses import dataclass, field

import math

import numpy as np
import warp as wp

from warp_kernels import skinning

from .head import _smoothstep, bust_surface
from .mouth import MOUTH_PARAMETERS, NUM_MOUTH_PARAMETERS, VOWEL_SHAPES
from .rigid import rigid_fit

# -- the built-in face: a grid over the front of the bust ---------------------------------------

# rows: bust heights [m], denser across the lips and the eyes; columns: ring-angle offsets from the
# front [rad] (positive = the character's left)
_ROWS = (0.240, 0.248, 0.256, 0.264, 0.270, 0.275, 0.2795, 0.2835, 0.287, 0.2905, 0.2945, 0.2985, 0.3035, 0.309, 0.315, 0.321,
         0.327, 0.3325, 0.337, 0.3415, 0.346, 0.3505, 0.355, 0.3605, 0.3665, 0.3735, 0.3815, 0.3905, 0.400)
_HALF_COLUMNS = (0.0, 0.06, 0.12, 0.18, 0.24, 0.30, 0.36, 0.42, 0.48, 0.55, 0.63, 0.72, 0.84, 0.98, 1.15, 1.35)
_MOUTH_ROW = 9  # the lips part along this row
_CORNER = 0.30  # ring-angle offset of the mouth corners [rad]
_MUZZLE = 0.004  # m the face rises over the bust around the mouth
_LIP_GAP = 0.008  # the lips' separation in the unrolled coordinates [m], so upper and lower lip interpolate apart
# toward its border the face eases from floating over the head's curved surface to lying on the head's own
# triangles, lifted this share of `lift`: a face floating 2 mm out to its edge shows a step all round it, and
# a narrower band (1.5 cm) shows as a ridge across the forehead
BORDER_BAND = 0.03  # m, measured along the surface from the border
BORDER_LIFT_SHARE = 0.2

# name: (ring-angle offset [rad], height [m], lip) with lip "upper"/"lower" for the parted row;
# names ending in _l have a mirrored _r twin
_FEATURES = {
    "upper_lip_top": (0.0, 0.2985, None), "upper_lip_top_l": (0.18, 0.2985, None),
    "upper_lip_bottom": (0.0, 0.2905, "upper"), "upper_lip_bottom_l": (0.18, 0.2905, "upper"),
    "lower_lip_top": (0.0, 0.2905, "lower"), "lower_lip_top_l": (0.18, 0.2905, "lower"),
    "lower_lip_bottom": (0.0, 0.2795, None), "lower_lip_bottom_l": (0.18, 0.2795, None),
    "mouth_corner_l": (_CORNER, 0.2905, None),
    "chin": (0.0, 0.270, None), "chin_bottom": (0.0, 0.264, None), "jaw_l": (0.84, 0.275, None),
    "nose_tip": (0.0, 0.321, None), "nose_wing_l": (0.18, 0.309, None),
    "nasolabial_l": (0.36, 0.3035, None), "cheek_l": (0.72, 0.315, None), "buccal_l": (0.55, 0.2835, None),
    "eye_upper_l": (0.42, 0.3505, None), "eye_lower_l": (0.42, 0.3325, None),
    "eye_inner_l": (0.30, 0.3415, None), "eye_outer_l": (0.55, 0.3415, None),
    "brow_inner_l": (0.18, 0.3605, None), "brow_mid_l": (0.42, 0.3665, None), "brow_outer_l": (0.63, 0.3605, None),
    "forehead": (0.0, 0.3905, None), "forehead_l": (0.48, 0.3905, None),
    "temple_l": (0.98, 0.355, None), "ear_l": (1.35, 0.3325, None),
}


def _expand_sides(table):
    out = {}
    for name, value in table.items():
        if name.endswith("_l"):
            out[name] = value
            out[name[:-2] + "_r"] = (-value[0],) + tuple(value[1:])
        else:
            out[name] = value
    return out


FEATURE_POINTS = tuple(_expand_sides(_FEATURES))  # 48 names

# -- shapes: action units and mouth parameters ----------------------------------------------------
# Vectors are (outward, up, forward) in millimetres in each feature point's surface frame (feature_frame):
# forward along the surface normal, up and outward in the tangent plane ("outward" is toward +X on the
# left side, -X on the right), so authored motions slide along the face rather than into it.
# A name without _l/_r that has sided twins ("brow_inner") moves both, mirrored.


@dataclass
class ShapeDefinition:
    """One blend shape: which feature points move by how much, and how far the motion spreads."""

    name: str
    description: str
    radius: float  # m, support of the interpolation around each constrained feature point
    vectors: dict = field(default_factory=dict)  # feature name (or sided base name) -> (out, up, fwd) mm


ACTION_UNITS = {
    1: ShapeDefinition("AU01", "inner brow raiser", 0.030,
                       {"brow_inner": (0.0, 9.0, 0.5), "brow_mid": (0.0, 4.0, 0.0), "forehead": (0.0, 3.0, 0.0)}),
    2: ShapeDefinition("AU02", "outer brow raiser", 0.030, {"brow_outer": (0.0, 6.0, 0.0), "brow_mid": (0.0, 3.5, 0.0)}),
    4: ShapeDefinition("AU04", "brow lowerer", 0.025, {"brow_inner": (-4.0, -6.0, 0.5), "brow_mid": (-2.0, -4.0, 0.0)}),
    5: ShapeDefinition("AU05", "upper lid raiser", 0.012, {"eye_upper": (0.0, 2.5, 0.3)}),
    6: ShapeDefinition("AU06", "cheek raiser", 0.030,
                       {"cheek": (0.0, 4.0, 1.5), "eye_lower": (0.0, 1.5, 0.0), "eye_outer": (0.0, 1.0, 0.0)}),
    7: ShapeDefinition("AU07", "lid tightener", 0.012, {"eye_lower": (0.0, 1.8, 0.0), "eye_upper": (0.0, -1.2, 0.0)}),
    9: ShapeDefinition("AU09", "nose wrinkler", 0.025,
                       {"nose_wing": (0.0, 3.0, 0.5), "nasolabial": (0.0, 2.5, 0.5), "brow_inner": (-0.5, -2.0, 0.0),
                        "upper_lip_top": (0.0, 1.5, 0.0)}),
    12: ShapeDefinition("AU12", "lip corner puller", 0.030,
                        {"mouth_corner": (6.0, 5.0, -2.0), "upper_lip_bottom": (3.0, 1.5, -1.0),
                         "lower_lip_top": (3.0, 1.5, -1.0), "upper_lip_top": (2.0, 1.0, -0.5),
                         "lower_lip_bottom": (2.0, 1.0, -0.5), "nasolabial": (1.0, 2.0, 0.5), "cheek": (0.0, 1.5, 1.0)}),
    15: ShapeDefinition("AU15", "lip corner depressor", 0.025,
                        {"mouth_corner": (0.0, -5.0, 0.0), "lower_lip_top": (0.0, -1.5, 0.0),
                         "lower_lip_bottom": (0.0, -1.5, 0.0), "upper_lip_bottom": (0.0, -1.5, 0.0)}),
    16: ShapeDefinition("AU16", "lower lip depressor", 0.020,
                        {"lower_lip_top": (0.0, -3.0, 0.5), "lower_lip_bottom": (0.0, -3.0, 0.5)}),
    20: ShapeDefinition("AU20", "lip stretcher", 0.030,
                        {"mouth_corner": (6.0, -1.5, -1.5), "upper_lip_bottom": (3.0, -0.5, -0.5),
                         "lower_lip_top": (3.0, -0.5, -0.5), "upper_lip_top": (2.5, 0.0, 0.0),
                         "lower_lip_bottom": (2.5, 0.0, 0.0)}),
    23: ShapeDefinition("AU23", "lip tightener", 0.020,
                        {"mouth_corner": (-2.5, 0.0, 0.5), "upper_lip_top": (0.0, -1.5, 0.0),
                         "lower_lip_bottom": (0.0, 1.5, 0.0), "upper_lip_bottom": (-1.0, -0.5, 0.5),
                         "lower_lip_top": (-1.0, 0.5, 0.5)}),
    26: ShapeDefinition("AU26", "jaw drop", 0.040,
                        {"chin": (0.0, -10.0, -1.5), "chin_bottom": (0.0, -10.0, -1.5), "jaw": (0.0, -5.0, 0.0),
                         "lower_lip_top": (0.0, -8.5, -0.5), "lower_lip_bottom": (0.0, -9.0, -1.0),
                         "mouth_corner": (0.0, -3.5, 0.0), "buccal": (0.0, -3.0, 0.0)}),
}
# the centre lip points move a little more than their side twins
_CENTRE_AND_SIDES = lambda base, centre, side: {base: centre, base + "_l": side, base + "_r": side}  # noqa: E731


def _lip(base, axis, side_share):
    vec = np.zeros(3)
    vec[axis] = 1.0
    out = {base: tuple(vec)}
    out[base + "_l"] = out[base + "_r"] = tuple(side_share * vec)
    return out


MOUTH_SHAPES = {
    "upper_lip_top_vertical": _lip("upper_lip_top", 1, 0.7),
    "upper_lip_top_depth": _lip("upper_lip_top", 2, 0.7),
    "upper_lip_bottom_vertical": _lip("upper_lip_bottom", 1, 0.8),
    "upper_lip_bottom_depth": _lip("upper_lip_bottom", 2, 0.8),
    "lower_lip_top_vertical": _lip("lower_lip_top", 1, 0.8),
    "lower_lip_top_depth": _lip("lower_lip_top", 2, 0.8),
    "lower_lip_bottom_vertical": _lip("lower_lip_bottom", 1, 0.8),
    "lower_lip_bottom_depth": _lip("lower_lip_bottom", 2, 0.8),
    "jaw_vertical": {"chin": (0.0, 1.0, 0.0), "chin_bottom": (0.0, 1.0, 0.0), "jaw": (0.0, 0.5, 0.0),
                     "buccal": (0.0, 0.25, 0.0)},
    "corner_vertical": {"mouth_corner": (0.0, 1.0, 0.0)},
    "corner_horizontal": {"mouth_corner": (1.0, 0.0, 0.0)},
    "corner_depth": {"mouth_corner": (0.0, 0.0, 1.0)},
    "lip_width": {"upper_lip_bottom": (1.0, 0.0, 0.0), "lower_lip_top": (1.0, 0.0, 0.0),
                  "upper_lip_top": (0.6, 0.0, 0.0), "lower_lip_bottom": (0.6, 0.0, 0.0)},
}
assert tuple(MOUTH_SHAPES) == MOUTH_PARAMETERS


def mouth_shape_definitions():
    return [ShapeDefinition("mouth_" + name, f"mouth parameter {i + 1}: {name.replace('_', ' ')} (per mm)",
                            0.040 if name == "jaw_vertical" else 0.022, vectors)
            for i, (name, vectors) in enumerate(MOUTH_SHAPES.items())]


# the six basic emotions as action-unit mixes (intensities 0..1)
EMOTIONS = {
    "neutral": {},
    "happiness": {6: 1.0, 12: 1.0},
    "sadness": {1: 1.0, 4: 1.0, 15: 1.0},
    "surprise": {1: 1.0, 2: 1.0, 5: 1.0, 26: 1.0},
    "fear": {1: 1.0, 2: 1.0, 4: 1.0, 5: 1.0, 20: 1.0, 26: 1.0},
    "anger": {4: 1.0, 5: 1.0, 7: 1.0, 23: 1.0},
    "disgust": {9: 1.0, 15: 1.0, 16: 1.0},
}

SKIN = (0.85, 0.68, 0.58)
LIPS = (0.70, 0.36, 0.36)
MOUTH_INSIDE = (0.22, 0.07, 0.07)
BROWS = (0.28, 0.19, 0.13)
EYE_WHITE = (0.93, 0.92, 0.90)
IRIS = (0.18, 0.12, 0.08)


@dataclass
class FaceMesh:
    """A face surface with feature points. vertices are in the head's rest frame [m]."""

    vertices: np.ndarray  # (V, 3)
    faces: np.ndarray  # (F, 3)
    features: dict  # name -> vertex index
    surface_uv: np.ndarray  # (V, 2) unrolled surface coordinates [m] the interpolation measures in
    colors: np.ndarray  # (V, 3) display colours
    normals: np.ndarray  # (V, 3) unit surface normals, outward: "forward" of the feature frames
    name: str = "builtin"

    @property
    def num_vertices(self):
        return len(self.vertices)


def _unrolled_coordinates(thetas, rows):
    """Arc length along each bust ring from the front [m] (signed), for ring angles `thetas`."""
    dense = np.linspace(0.0, max(_HALF_COLUMNS) + 0.05, 800)
    out = np.zeros((len(rows), len(thetas)))
    for i, y in enumerate(rows):
        ring = bust_surface([y], np.pi / 2 - dense)[0]
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(ring, axis=0), axis=1))])
        out[i] = np.sign(thetas) * np.interp(np.abs(thetas), dense, arc)
    return out


def _refine(values, times):
    """`times` - 1 evenly spaced values inserted between each pair of neighbours."""
    t = np.arange(times) / times
    inner = (values[:-1, None] * (1.0 - t) + values[1:, None] * t).reshape(-1)
    return np.concatenate([inner, values[-1:]])


def builtin_face(project=None, lift=0.002, head_offset=(0.0, 0.0, 0.0), resolution=3):
    """The built-in face over the front of the built-in bust: 29 x 31 vertices refined `resolution`
    times (resolution 2: 57 x 61, 3: 85 x 91), the lips parted
    along one row, a dark mouth lining behind them, and the 48 feature points.

    project(points) -> (surface points, unit normals[, flat points]) snaps the grid onto the actual
    collider (the bust, or the body whose head is the bust moved by head_offset): a smooth surface
    over it and, where the collider is drawn as flat triangles, the points on those; without it the
    grid sits on the bust's analytic surface. Vertices are lifted `lift` metres off the surface so
    the face draws over the head it rides; within BORDER_BAND of the grid's border at the forehead and
    the sides they ease onto the flat points, lifted BORDER_LIFT_SHARE of that, so the face's edge meets
    the head without a step.
    """
    rows = _refine(np.asarray(_ROWS), resolution)
    half = _refine(np.asarray(_HALF_COLUMNS), resolution)
    mouth_row = int(np.argmin(np.abs(rows - _ROWS[_MOUTH_ROW])))
    cols = np.concatenate([-half[:0:-1], half])  # right side first, so +X (left) grows with the index
    nr, nc = len(rows), len(cols)
    grid = bust_surface(rows, np.pi / 2 - cols)  # (nr, nc, 3)
    uv_u = _unrolled_coordinates(cols, rows)
    uv = np.stack([uv_u, np.repeat(rows[:, None], nc, 1)], -1)
    index = np.arange(nr * nc).reshape(nr, nc)
    points, uvs = [grid.reshape(-1, 3)], [uv.reshape(-1, 2)]

    # part the lips: the mouth row's inner vertices get a lower-lip twin, and both get a twin for the
    # mouth lining that closes the gap from behind when the mouth opens
    inner = np.nonzero(np.abs(cols) < _CORNER - 1e-9)[0]
    n0 = nr * nc
    lower = dict(zip(inner, n0 + np.arange(len(inner))))
    lining_up = dict(zip(inner, n0 + len(inner) + np.arange(len(inner))))
    lining_lo = dict(zip(inner, n0 + 2 * len(inner) + np.arange(len(inner))))
    mouth_pts = grid[mouth_row, inner]
    lower_uv = uv[mouth_row, inner] - np.array([0.0, _LIP_GAP])
    points += [mouth_pts, mouth_pts, mouth_pts]
    uvs += [lower_uv, uv[mouth_row, inner], lower_uv]
    vertices = np.concatenate(points)
    surface_uv = np.concatenate(uvs)
    # everything below the lips measures distance in the opened coordinates too, so the jaw moves
    # apart from the upper lip; the gap closes towards the mouth corners and beyond
    below = np.arange(n0) < mouth_row * nc
    fade = np.clip(2.0 - np.abs(np.tile(cols, nr)) / _CORNER, 0.0, 1.0)
    surface_uv[:n0, 1] -= np.where(below, _LIP_GAP * fade, 0.0)

    faces = []
    for i in range(nr - 1):
        for j in range(nc - 1):
            a, b, c, d = index[i, j], index[i, j + 1], index[i + 1, j + 1], index[i + 1, j]
            if i == mouth_row - 1:  # the row below the lips uses the lower-lip twins
                d = lower.get(j, d)
                c = lower.get(j + 1, c)
            faces += [(a, b, c), (a, c, d)]
    for j0, j1 in zip(inner[:-1], inner[1:]):  # lining strip, visible only when the lips part
        faces += [(lining_lo[j0], lining_lo[j1], lining_up[j1]), (lining_lo[j0], lining_up[j1], lining_up[j0])]
    # the strip ends at the shared corner vertices
    left_c, right_c = index[mouth_row, inner[-1] + 1], index[mouth_row, inner[0] - 1]
    faces += [(lining_lo[inner[-1]], left_c, lining_up[inner[-1]]), (lining_lo[inner[0]], lining_up[inner[0]], right_c)]
    faces = np.asarray(faces, np.int64)

    vertices = vertices + np.asarray(head_offset, np.float64)
    if project is not None:
        surface, normals, *flat = project(vertices)
        flat = flat[0] if flat else surface
    else:
        surface, normals = vertices, _analytic_normals(vertices - np.asarray(head_offset), rows, cols, index, n0, mouth_row)
        flat = surface
    # distance along the surface to the grid's border at the forehead and the sides; under the chin, which
    # the jaw moves (1 mm inward for an open mouth), the face keeps its whole lift
    border = np.minimum(np.minimum(uv_u - uv_u[:, :1], uv_u[:, -1:] - uv_u), (rows[-1] - rows)[:, None])
    inside = np.ones(len(vertices))
    inside[:n0] = _smoothstep(border.reshape(-1) / BORDER_BAND)
    surface = flat + inside[:, None] * (surface - flat)
    lift = lift * (BORDER_LIFT_SHARE + (1.0 - BORDER_LIFT_SHARE) * inside)
    # the bust has no mouth: raise a muzzle under the lips (as teeth and gums do), so lips that move
    # back or slide over the curved face stay in front of the head; the lining sits deeper, behind them
    k = len(inner)
    col = np.concatenate([np.tile(cols, nr), np.tile(cols[inner], 3)])
    row = np.concatenate([np.repeat(rows, nc), np.full(3 * k, rows[mouth_row])])
    dy = row - rows[mouth_row]
    e = (col / (1.5 * _CORNER)) ** 2 + (dy / np.where(dy > 0.0, 0.018, 0.032)) ** 2  # down over the chin
    muzzle = _MUZZLE * _smoothstep(1.0 - e)
    lifted = surface + (lift + muzzle)[:, None] * normals
    lining = np.array(list(lining_up.values()) + list(lining_lo.values()))
    lifted[lining] = surface[lining] + (0.25 * lift[lining] + muzzle[lining])[:, None] * normals[lining]

    features = {}
    for name, (dt, y, lip) in _expand_sides(_FEATURES).items():
        i, j = int(np.argmin(np.abs(rows - y))), int(np.argmin(np.abs(cols - dt)))
        v = index[i, j]
        if lip == "lower":
            v = lower[j]
        features[name] = int(v)
    if len(set(features.values())) != len(features):
        raise AssertionError("two feature points share a vertex")

    colors = _paint(rows, cols, index, lower, lining, mouth_row)
    return FaceMesh(lifted, faces, features, surface_uv, colors, normals)


def _analytic_normals(vertices, rows, cols, index, n0, mouth_row):
    """Unit normals of the bust surface at the grid (twins copy their original's)."""
    eps = 1e-4
    du = bust_surface(rows, np.pi / 2 - cols + eps) - bust_surface(rows, np.pi / 2 - cols - eps)
    dv = bust_surface(rows + eps, np.pi / 2 - cols) - bust_surface(rows - eps, np.pi / 2 - cols)
    n = np.cross(du, dv).reshape(-1, 3)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where((n[:, 2] < 0)[:, None], -n, n)  # outward: the face looks down +Z
    out = np.zeros_like(vertices)
    out[:n0] = n
    mouth = index[mouth_row, np.abs(cols) < _CORNER - 1e-9]
    k = len(mouth)
    for t in range(3):
        out[n0 + t * k: n0 + (t + 1) * k] = n[mouth]
    return out


def _soft(d, width):
    """1 inside (d < 0), easing to 0 over `width` outside: soft edges read smoothly through vertex colours."""
    return _smoothstep(1.0 - d / width)


# samples a side of the tent around each vertex that its colour averages (_paint)
PAINT_SAMPLES = 8


def _paint_at(row, col):
    """Display colours at face coordinates (row: height [m], col: angle from the front [rad]): lips,
    brows and eyes on skin, with soft edges."""
    skin = np.asarray(SKIN, np.float64)
    colors = np.tile(skin, (len(row), 1))

    def blend(mask, rgb):
        colors[:] = colors * (1.0 - mask[:, None]) + np.asarray(rgb) * mask[:, None]

    # lips: thickest at the middle, tapering to the corners, with a dip in the upper lip's edge
    a = np.clip(np.abs(col) / _CORNER, 0.0, 1.5)
    taper = np.sqrt(np.clip(1.0 - a ** 2, 0.0, 1.0))
    mouth_y = _ROWS[_MOUTH_ROW]
    upper_edge = mouth_y + (0.0085 - 0.0015 * np.exp(-(col / 0.05) ** 2)) * taper
    lower_edge = mouth_y - 0.0095 * taper
    inside = np.maximum(row - upper_edge, lower_edge - row)
    blend(_soft(inside, 0.002) * (a < 1.0 + 1e-9), LIPS)
    brow_y = np.interp(np.abs(col), [0.12, 0.42, 0.72], [0.3600, 0.3670, 0.3585])
    brow_h = np.interp(np.abs(col), [0.12, 0.30, 0.72], [0.0040, 0.0035, 0.0015])
    along = np.clip((np.abs(col) - 0.12) / 0.60, -1.0, 2.0)
    blend(_soft(np.abs(row - brow_y) - brow_h, 0.002) * _soft(np.maximum(-along, along - 1.0) * 0.6, 0.03), BROWS)
    for side in (-1.0, 1.0):
        e = np.sqrt(((col - side * 0.425) / 0.13) ** 2 + ((row - 0.3415) / 0.0060) ** 2)
        blend(_soft(e - 1.0, 0.35), EYE_WHITE)
        blend(_soft(e - 0.42, 0.25), IRIS)
    return colors


def _paint(rows, cols, index, lower, lining, mouth_row):
    """Display colours of the face's vertices: _paint_at averaged with the tent around each vertex,
    1 at it and 0 at the rows and columns before and after it (PAINT_SAMPLES^2 points), the prefilter
    that suits colours interpolated linearly across the triangles. Taken at the vertex alone, a brow's or
    an eye's edge falls between vertices all in or all out, and the colours draw it as a staircase of the
    grid's cells; averaged over the vertex's own cell (a box) a slanted brow still showed steps; with the
    tent its edges draw soft and straight. Lip vertices are painted at the mouth row as their twins, the
    lining dark."""
    nr, nc = index.shape
    k = len(lower)
    col = np.concatenate([np.tile(cols, nr), np.tile(cols[list(lower)], 3)])
    row = np.concatenate([np.repeat(rows, nc), np.full(3 * k, rows[mouth_row])])

    def half_gaps(values):
        gaps = np.diff(values)
        return 0.5 * np.concatenate([gaps[:1], gaps]), 0.5 * np.concatenate([gaps, gaps[-1:]])

    below, above = half_gaps(rows)
    left, right = half_gaps(cols)
    row_lo = np.concatenate([np.repeat(below, nc), np.zeros(3 * k)])  # the mouth row's twins: along the row only
    row_hi = np.concatenate([np.repeat(above, nc), np.zeros(3 * k)])
    col_lo = np.concatenate([np.tile(left, nr), np.tile(left[list(lower)], 3)])
    col_hi = np.concatenate([np.tile(right, nr), np.tile(right[list(lower)], 3)])
    t = (np.arange(PAINT_SAMPLES) + 0.5) / PAINT_SAMPLES * 2.0 - 1.0  # -1 .. 1, the cell's centres
    tent = 1.0 - np.abs(t)
    colors = np.zeros((len(row), 3))
    for u, wu in zip(t, tent):
        r = row + 2.0 * np.where(u < 0.0, row_lo, row_hi) * u
        for w, ww in zip(t, tent):
            colors += wu * ww * _paint_at(r, col + 2.0 * np.where(w < 0.0, col_lo, col_hi) * w)
    colors /= tent.sum() ** 2
    colors[lining] = MOUTH_INSIDE
    return colors


# -- the rig --------------------------------------------------------------------------------------


def _wendland(r):
    r = np.clip(r, 0.0, 1.0)
    return (1.0 - r) ** 4 * (4.0 * r + 1.0)


def feature_frame(mesh, name):
    """Columns (outward, up, forward) at a feature point: forward is the surface normal, up the
    head's +Y and outward its +X (mirrored on the right side) laid into the tangent plane, so a
    feature moved "up" slides along the face instead of sinking into it."""
    n = mesh.normals[mesh.features[name]]
    up = np.array([0.0, 1.0, 0.0]) - n[1] * n
    up /= np.linalg.norm(up)
    side = np.array([-1.0 if name.endswith("_r") else 1.0, 0.0, 0.0])
    out = side - np.dot(side, n) * n - np.dot(side, up) * up
    out /= np.linalg.norm(out)
    return np.stack([out, up, n], 1)


def _feature_vectors(definition, mesh):
    """Expand sided base names; returns {feature name: displacement [m] in head axes}."""
    out = {}
    for name, vec in definition.vectors.items():
        names = [name] if name in mesh.features else [name + "_l", name + "_r"]
        for n in names:
            if n not in mesh.features:
                raise KeyError(f"{definition.name}: unknown feature point '{name}'")
            out[n] = feature_frame(mesh, n) @ (1e-3 * np.asarray(vec, np.float64))
    return out


def interpolate_shape(mesh, definition):
    """Offset field (V, 3) [m] of one shape: exact at its moved feature points, zero at every other
    feature point, zero farther than its radius from all the feature points it constrains.

    The field is a sum of Wendland functions of the radius around the constrained points, so it reaches
    a radius beyond each of them: the feature points held at zero (anchors) are those within the radius
    of a constrained point, gathered until no other lies that close (holding only those near the moved
    points left the next ring free to move: AU9 moved the lower lip 0.12 mm).

    Returns (offsets, constrained feature names)."""
    moved = _feature_vectors(definition, mesh)
    uv = mesh.surface_uv
    R = definition.radius
    names = list(moved)
    free = [n for n in mesh.features if n not in moved]
    while free:
        held = uv[[mesh.features[n] for n in names]]
        near = [n for n in free if np.min(np.linalg.norm(held - uv[mesh.features[n]], axis=1)) < R]
        if not near:
            break
        names += near
        free = [n for n in free if n not in near]
    centres = uv[[mesh.features[n] for n in names]]
    values = np.zeros((len(names), 3))
    values[:len(moved)] = [moved[n] for n in moved]
    gaps = np.linalg.norm(centres[:, None] - centres[None], axis=-1) + np.eye(len(names))
    i, j = np.unravel_index(np.argmin(gaps), gaps.shape)
    if gaps[i, j] < 1e-5:
        raise ValueError(f"{definition.name}: feature points '{names[i]}' and '{names[j]}' coincide in the face's "
                         "surface coordinates; parted lips need separate vertices")
    A = _wendland(np.linalg.norm(centres[:, None] - centres[None], axis=-1) / R)
    coeffs = np.linalg.solve(A, values)
    B = _wendland(np.linalg.norm(uv[:, None] - centres[None], axis=-1) / R)
    return B @ coeffs, names


class FaceRig:
    """Blend shapes for the action units and the mouth parameters over a FaceMesh.

    weights: one per shape in `shape_names` order: AU intensities (0..1) first, then the 13 mouth
    parameters in millimetres. `deform(weights)` evaluates the rig in the rest frame with a Warp
    kernel; `attach(...)` binds it to a collider so `posed_points` follows the moving head.
    """

    def __init__(self, mesh, device="cpu", action_units=None):
        self.mesh = mesh
        self.device = device
        self.action_units = dict(ACTION_UNITS if action_units is None else action_units)
        self.definitions = [self.action_units[k] for k in sorted(self.action_units)] + mouth_shape_definitions()
        self.au_numbers = sorted(self.action_units)
        self.shape_names = [d.name for d in self.definitions]
        fields = [interpolate_shape(mesh, d) for d in self.definitions]
        self.offsets = np.stack([f[0] for f in fields])  # (S, V, 3) m
        self.constrained = [f[1] for f in fields]
        self._upload()
        self._binding = None

    @property
    def num_shapes(self):
        return len(self.shape_names)

    def set_action_unit(self, number, vectors, radius=None, description=None):
        """Edit (or add) an action unit: vectors maps feature names to (outward, up, forward) mm."""
        old = self.action_units.get(number)
        d = ShapeDefinition(f"AU{number:02d}", description or (old.description if old else f"action unit {number}"),
                            radius or (old.radius if old else 0.025), dict(vectors))
        if old is None:
            raise KeyError(f"AU{number} is not in this rig (it has {self.au_numbers}); build the rig with it")
        k = self.au_numbers.index(number)
        self.action_units[number] = d
        self.definitions[k] = d
        self.offsets[k], self.constrained[k] = interpolate_shape(self.mesh, d)
        self._upload()

    def _upload(self):
        S, V = self.offsets.shape[:2]
        nz = np.abs(self.offsets).max(axis=2) > 0.0  # (S, V)
        vert, shape = np.nonzero(nz.T)  # sorted by vertex
        start = np.concatenate([[0], np.cumsum(np.bincount(vert, minlength=V))]).astype(np.int32)
        self.shape_start = wp.array(start, dtype=wp.int32, device=self.device)
        self.shape_index = wp.array(shape.astype(np.int32), dtype=wp.int32, device=self.device)
        self.shape_offset = wp.array(self.offsets[shape, vert].astype(np.float32), dtype=wp.vec3, device=self.device)
        self.rest = wp.array(self.mesh.vertices.astype(np.float32), dtype=wp.vec3, device=self.device)
        self._weights = wp.zeros(S, dtype=float, device=self.device)
        self._out = wp.zeros(V, dtype=wp.vec3, device=self.device)
        self._rest_out = wp.zeros(V, dtype=wp.vec3, device=self.device)  # the unexpressed face, for head_transform

    def weights(self, action_units=None, mouth=None):
        """Shape weights from {AU number: intensity} and 13 mouth parameters [mm]."""
        w = np.zeros(self.num_shapes)
        for au, value in (action_units or {}).items():
            if au not in self.au_numbers:
                raise KeyError(f"AU{au} is not in this rig (it has {self.au_numbers})")
            w[self.au_numbers.index(au)] = value
        if mouth is not None:
            w[len(self.au_numbers):] = np.asarray(mouth, np.float64).reshape(NUM_MOUTH_PARAMETERS)
        return w

    def deform(self, weights):
        """Rest-frame vertex positions (V, 3) for one weight vector."""
        self._weights.assign(np.asarray(weights, np.float32))
        wp.launch(skinning.blend_shape_points, self.mesh.num_vertices,
                  [self.rest, self.shape_start, self.shape_index, self.shape_offset, self._weights, self._out],
                  device=self.device)
        return self._out.numpy().copy()

    def attach(self, collider):
        """Bind every face vertex to its nearest triangle of the collider in its current (rest) pose."""
        _, face, bary = collider.closest_points(self.mesh.vertices)
        arr = lambda a, t: wp.array(a, dtype=t, device=self.device)  # noqa: E731
        tri, bary = arr(face.astype(np.int32), wp.int32), arr(bary.astype(np.float32), wp.vec3)
        local = wp.zeros(self.mesh.num_vertices, dtype=wp.vec3, device=self.device)
        wp.launch(skinning.compute_bindings, self.mesh.num_vertices,
                  [collider.points, collider.indices, tri, bary, self.rest, local], device=self.device)
        self._binding = (arr(collider.points.numpy(), wp.vec3), tri, bary, local)

    def posed_points(self, collider, weights, out=None):
        """World positions of the face on the collider's current pose: the rig's own wp.array (or
        `out`), overwritten by the next posed_points or head_transform call."""
        if self._binding is None:
            self.attach(collider)
        out = self._out if out is None else out
        rest_mesh, tri, bary, local = self._binding
        self._weights.assign(np.asarray(weights, np.float32))
        wp.launch(skinning.blend_shape_bound_points, self.mesh.num_vertices,
                  [self.shape_start, self.shape_index, self.shape_offset, self._weights, rest_mesh, collider.points,
                   collider.indices, tri, bary, local, out], device=self.device)
        return out

    def queue_frame(self, collider, weights):
        """Launch this pose's face and its unexpressed face without waiting for either: (posed,
        rest_posed) wp.arrays; head_transform_from(rest_posed as NumPy) gives the head transform."""
        rest_posed = self.posed_points(collider, np.zeros(self.num_shapes), out=self._rest_out)
        return self.posed_points(collider, weights), rest_posed

    def head_transform(self, collider):
        """The rigid transform (4x4, column vectors) taking the face's rest frame to the collider's
        current pose: a least-squares fit (Kabsch) over the undeformed bound face, which is exact
        where the head moves rigidly. UsdSkel drives the exported rig's single joint with it."""
        rest_posed = self.posed_points(collider, np.zeros(self.num_shapes), out=self._rest_out)
        return self.head_transform_from(rest_posed.numpy())

    def head_transform_from(self, rest_posed):
        """head_transform from the unexpressed face's posed points (V, 3)."""
        return rigid_fit(self.mesh.vertices, np.asarray(rest_posed, np.float64))


# -- animation ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ExpressionKey:
    """At `frame` the face holds this mix: an emotion preset scaled by `weight`, plus explicit AUs."""

    frame: float
    emotion: str = "neutral"
    weight: float = 1.0
    action_units: tuple = ()  # ((AU number, intensity), ...)

    def intensities(self):
        mix = {au: self.weight * v for au, v in EMOTIONS[self.emotion].items()}
        for au, v in self.action_units:
            mix[int(au)] = mix.get(int(au), 0.0) + float(v)
        return mix


class FaceAnimation:
    """Expression keys eased into each other (smoothstep between consecutive keys, held outside),
    plus an optional mouth track (T, 13) [mm] starting at `mouth_start` frame."""

    def __init__(self, keys=(), mouth=None, mouth_start=0.0):
        self.keys = sorted(keys, key=lambda k: k.frame)
        self.mouth = None if mouth is None else np.asarray(mouth, np.float64)
        self.mouth_start = float(mouth_start)

    def action_units(self, frame):
        if not self.keys:
            return {}
        frames = [k.frame for k in self.keys]
        if frame <= frames[0]:
            return self.keys[0].intensities()
        if frame >= frames[-1]:
            return self.keys[-1].intensities()
        i = int(np.searchsorted(frames, frame, side="right")) - 1
        a, b = self.keys[i], self.keys[i + 1]
        s = float(_smoothstep((frame - a.frame) / (b.frame - a.frame)))
        ia, ib = a.intensities(), b.intensities()
        return {au: (1.0 - s) * ia.get(au, 0.0) + s * ib.get(au, 0.0) for au in set(ia) | set(ib)}

    def mouth_at(self, frame):
        if self.mouth is None:
            return np.zeros(NUM_MOUTH_PARAMETERS)
        k = int(round(frame - self.mouth_start))
        if k < 0 or k >= len(self.mouth):
            return np.zeros(NUM_MOUTH_PARAMETERS)
        return self.mouth[k]

    def weights(self, rig, frame):
        aus = {au: v for au, v in self.action_units(frame).items() if au in rig.au_numbers}
        return rig.weights(aus, self.mouth_at(frame))


def vowel_weights(rig, vowel_weights6):
    """Shape weights of a mouth interpolated from the six bases (a, i, u, e, o, closed)."""
    return rig.weights(None, np.asarray(vowel_weights6, np.float64) @ VOWEL_SHAPES)


# -- scene configuration --------------------------------------------------------------------------


@dataclass(frozen=True)
class FaceConfig:
    """The [face] table: the animated face on the scene's head. [[face.expressions]] entries are
    {frame, emotion, weight, aus = {"12" = 0.5, ...}} keys eased into each other."""

    enabled: bool = False  # set by the presence of a [face] table
    mesh: str = "builtin"  # "builtin" (fits the built-in head and body) or a face mesh file
    features: str = ""  # JSON {feature name: vertex index} for a face mesh file
    # built-in face: grid refinement (1: ~930 vertices, 2: ~3,500, 3: ~7,800, 4: ~13,800); 3 draws brows and eyes
    # crisp in a close-up (vertex colours are no finer than the grid), 4 crisper still
    resolution: int = 3
    lift: float = 0.002  # m the face floats off the head surface, so it draws over it
    audio: str = ""  # a WAV the character speaks (lip sync); "builtin" for the demo line
    mouth: str = ""  # instead of audio: .npy or .csv of (T, 13) mouth parameters [mm], one row per frame
    audio_start: float = 1.0  # frame at which the audio (or the mouth track) starts
    # lip-sync weights: "general", a training voice's name, or a folder of a.wav i.wav u.wav e.wav o.wav to
    # choose the best set for (speaker adaptation)
    voice: str = "general"
    expressions: tuple = ()  # ExpressionKey, from [[face.expressions]]

    def __post_init__(self):
        if self.resolution < 1 or self.resolution > 4:
            raise ValueError("resolution must be 1, 2, 3 or 4")
        if self.lift < 0.0:
            raise ValueError("lift must be zero or positive")
        if self.audio and self.mouth:
            raise ValueError("audio and mouth both drive the mouth: give one")


def parse_expressions(entries, source):
    """[[face.expressions]] tables -> ExpressionKeys, with errors naming the entry and key."""
    from .errors import InputError

    if not isinstance(entries, list):
        raise InputError(source, "face.expressions", "expected an array of tables ([[face.expressions]])")
    keys = []
    for i, entry in enumerate(entries):
        where = f"face.expressions[{i}]"
        if not isinstance(entry, dict):
            raise InputError(source, where, "expected a table")
        unknown = set(entry) - {"frame", "emotion", "weight", "aus"}
        if unknown:
            raise InputError(source, f"{where}.{sorted(unknown)[0]}", "unknown key (known: frame, emotion, weight, aus)")
        frame = entry.get("frame")
        if isinstance(frame, bool) or not isinstance(frame, (int, float)) or not math.isfinite(frame):
            raise InputError(source, f"{where}.frame", f"expected a finite number, got {frame!r}")
        emotion = entry.get("emotion", "neutral")
        if emotion not in EMOTIONS:
            raise InputError(source, f"{where}.emotion", f"unknown emotion {emotion!r} (known: {', '.join(EMOTIONS)})")
        weight = entry.get("weight", 1.0)
        if isinstance(weight, bool) or not isinstance(weight, (int, float)) or not 0.0 <= weight <= 1.0:
            raise InputError(source, f"{where}.weight", f"expected a number from 0 to 1, got {weight!r}")
        aus = entry.get("aus", {})
        if not isinstance(aus, dict):
            raise InputError(source, f"{where}.aus", "expected a table of AU number = intensity")
        pairs = []
        for k, v in aus.items():
            if not str(k).isdigit() or int(k) not in ACTION_UNITS:
                raise InputError(source, f"{where}.aus.{k}",
                                 f"unknown action unit (known: {', '.join(str(a) for a in ACTION_UNITS)})")
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 <= v <= 1.0:
                raise InputError(source, f"{where}.aus.{k}", f"expected an intensity from 0 to 1, got {v!r}")
            pairs.append((int(k), float(v)))
        if any(k.frame == frame for k in keys):  # one would silently win over the other
            raise InputError(source, f"{where}.frame", f"another expression is keyed at frame {frame:g}")
        keys.append(ExpressionKey(float(frame), emotion, float(weight), tuple(pairs)))
    return tuple(keys)


def face_from_file(mesh_path, features_path):
    """A user's face mesh (any format trimesh reads, metres, head axes) with a JSON feature map.

    Distances for the interpolation are measured in the frontal (X, Y) projection, so the mesh should
    face +Z; a parted mouth keeps its lips apart by their own separate vertices."""
    import json

    import trimesh

    mesh = trimesh.load(mesh_path, force="mesh", process=False)
    if len(mesh.faces) == 0 or not np.all(np.isfinite(mesh.vertices)):
        raise ValueError(f"{mesh_path} has no faces or non-finite vertices")
    with open(features_path) as f:
        raw = json.load(f)
    if not isinstance(raw, dict):
        raise ValueError(f"{features_path}: expected an object of feature name -> vertex index")
    features = {}
    for name, idx in raw.items():
        if name not in FEATURE_POINTS:
            raise ValueError(f"{features_path}: unknown feature point '{name}'")
        if isinstance(idx, bool) or not isinstance(idx, int) or not 0 <= idx < len(mesh.vertices):
            raise ValueError(f"{features_path}: {name}: vertex index must be an integer in [0, {len(mesh.vertices)})")
        features[name] = idx
    missing = [n for n in FEATURE_POINTS if n not in features]
    if missing:
        raise ValueError(f"{features_path}: missing feature points {', '.join(missing[:4])}"
                         + (f" and {len(missing) - 4} more" if len(missing) > 4 else ""))
    v = np.asarray(mesh.vertices, np.float64)
    colors = np.tile(np.asarray(SKIN, np.float64), (len(v), 1))
    normals = np.asarray(mesh.vertex_normals, np.float64)
    normals = np.where((normals[:, 2:3] < 0.0), -normals, normals)  # the face looks down +Z
    return FaceMesh(v, np.asarray(mesh.faces, np.int64), features, v[:, :2].copy(), colors, normals, str(mesh_path))
