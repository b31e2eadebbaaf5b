"""Built-in body: a smooth standing mannequin, its skeleton, skin weights and walk/raise/turn animations.

The surface is the zero level of a signed-distance field: a lofted elliptical torso, round cones for
neck and limbs, ellipsoids for muscles, hands and feet, and the hair bust (`sim.head`) above the neck,
all joined with a smooth minimum and extracted with marching cubes. One field gives one closed,
consistently wound surface, so cloth and hair see a single collider.

Units are metres and seconds, Y up, the character faces +Z with its feet on y = 0 and its left on +X,
arms in an A-pose. The head is the bust lifted by HEAD_OFFSET, so hair grown on the bust's scalp rule
lands on this body's head, and the head bone carries that region rigidly.
"""

import functools
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.interpolate import PchipInterpolator

from .collision_proxy import neighbour_average
from .head import _scalp_faces, _smoothstep, procedural_head
from .sphere_tree import signed_distance, warp_mesh

HEIGHT = 1.70  # crown height [m]
HEAD_OFFSET = (0.0, HEIGHT - 0.472, 0.0)  # bust coordinates + offset = body coordinates (bust crown at 0.472)
_BUST_CUT_Y = 0.18  # bust coordinates: only the bust above this height joins the body
_HEAD_RIGID_Y = (0.17, 0.23)  # bust coordinates: head-bone weight ramps 0 -> 1 (1 exactly above)
ARM_ABDUCTION_DEGREES = 42.0  # rest A-pose: upper arm angle out from the torso
_HEEL_REACH = 0.09  # [m] from the ankle back to where the heel meets the floor

# torso loft: height, half-width (x), half-depth (z), centre z  [m]
_TORSO = np.array([
    [0.770, 0.105, 0.075, -0.010],
    [0.820, 0.152, 0.088, -0.010],
    [0.880, 0.172, 0.100, -0.012],
    [0.950, 0.163, 0.099, -0.010],
    [1.020, 0.138, 0.093, -0.006],
    [1.070, 0.127, 0.088, -0.002],
    [1.130, 0.134, 0.093, 0.000],
    [1.200, 0.148, 0.103, 0.002],
    [1.260, 0.157, 0.106, 0.000],
    [1.320, 0.160, 0.098, -0.008],
    [1.370, 0.158, 0.082, -0.018],
    [1.410, 0.140, 0.068, -0.024],
    [1.440, 0.070, 0.055, -0.024],
])
_TORSO_FIT = PchipInterpolator(_TORSO[:, 0], _TORSO[:, 1:], axis=0)
_TORSO_ROUND = 0.03  # [m] radius of the rounded top and bottom rims of the torso loft
CHEST_Y, WAIST_Y, HIP_Y = 1.24, 1.07, 0.88

JOINTS = ("pelvis", "spine", "chest", "neck", "head",
          "shoulder_l", "upper_arm_l", "forearm_l", "hand_l",
          "shoulder_r", "upper_arm_r", "forearm_r", "hand_r",
          "thigh_l", "shin_l", "foot_l", "thigh_r", "shin_r", "foot_r")
_PARENTS = ("", "pelvis", "spine", "chest", "neck",
            "chest", "shoulder_l", "upper_arm_l", "forearm_l",
            "chest", "shoulder_r", "upper_arm_r", "forearm_r",
            "pelvis", "thigh_l", "shin_l", "pelvis", "thigh_r", "shin_r")


@dataclass(frozen=True, eq=False)
class Skeleton:
    """Joint hierarchy in the rest pose; every joint frame is world aligned at rest (bind = translation).

    `tips` holds where each joint's bone ends: its child joint, or an end point for hands, feet, head.
    """

    names: tuple
    parents: np.ndarray  # (J,) int, -1 for the root; parents precede children
    rest_positions: np.ndarray  # (J, 3) world rest positions [m]
    tips: np.ndarray  # (J, 3) bone end points [m]

    def index(self, name):
        return self.names.index(name)

    @property
    def num_joints(self):
        return len(self.names)


@dataclass
class BodyAsset:
    """A skinned collider mesh of the whole body, with the scalp region hair may grow from."""

    name: str
    vertices: np.ndarray  # (V, 3) float64 [m]
    faces: np.ndarray  # (F, 3) int64, outward winding
    skin_indices: np.ndarray  # (V, 4) int64
    skin_weights: np.ndarray  # (V, 4) float64, rows sum to 1
    scalp_faces: np.ndarray  # (F,) bool
    pivot: tuple  # head joint [m]: the head bone rotates about it
    num_bones: int
    skeleton: Skeleton
    landmarks: dict  # rest-pose garment landmarks [m], see _landmarks
    head_offset: tuple = HEAD_OFFSET  # add to sim.head bust coordinates to get body coordinates


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def _rot_z(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


@functools.lru_cache(maxsize=1)
def default_skeleton():
    """The built-in body's joints (world rest positions [m])."""
    p = {
        "pelvis": (0.0, 0.95, -0.012),
        "spine": (0.0, 1.07, -0.018),
        "chest": (0.0, 1.22, -0.022),
        "neck": (0.0, 1.385, -0.024),
        "head": (0.0, 0.20 + HEAD_OFFSET[1], 0.0),  # the bust's neck pivot
    }
    tips = {"head": (0.0, HEIGHT - 0.03, 0.0)}
    for side, sx in (("l", 1.0), ("r", -1.0)):
        arm = _unit([sx * np.sin(np.radians(ARM_ABDUCTION_DEGREES)), -np.cos(np.radians(ARM_ABDUCTION_DEGREES)), 0.0])
        # the forearm hangs a little steeper and forward of the upper arm: a relaxed elbow
        fore = _unit(_rot_z(sx * -4.0) @ arm + np.array([0.0, 0.0, 0.12]))
        shoulder = np.array([sx * 0.172, 1.372, -0.022])
        elbow = shoulder + 0.285 * arm
        wrist = elbow + 0.245 * fore
        p[f"shoulder_{side}"] = (sx * 0.030, 1.375, -0.010)
        p[f"upper_arm_{side}"] = tuple(shoulder)
        p[f"forearm_{side}"] = tuple(elbow)
        p[f"hand_{side}"] = tuple(wrist)
        tips[f"hand_{side}"] = tuple(wrist + 0.17 * fore)
        p[f"thigh_{side}"] = (sx * 0.088, 0.900, -0.008)
        p[f"shin_{side}"] = (sx * 0.104, 0.480, 0.000)
        p[f"foot_{side}"] = (sx * 0.118, 0.082, -0.022)
        tips[f"foot_{side}"] = (sx * 0.125, 0.025, 0.150)
    rest = np.array([p[n] for n in JOINTS], np.float64)
    parents = np.array([JOINTS.index(q) if q else -1 for q in _PARENTS], np.int64)
    tip = rest.copy()
    for j, name in enumerate(JOINTS):
        children = np.flatnonzero(parents == j)
        if name in tips:
            tip[j] = tips[name]
        elif len(children):
            tip[j] = rest[children[0]] if len(children) == 1 else rest[children].mean(0)
    tip[JOINTS.index("chest")] = rest[JOINTS.index("neck")]  # not the clavicles' mean
    for a in (rest, tip, parents):
        a.setflags(write=False)
    return Skeleton(JOINTS, parents, rest, tip)


# ---- signed-distance primitives: NumPy, (N, 3) points -> (N,) approximate distances [m] -----------------

def _round_cone(p, a, b, ra, rb):
    """Capsule from a to b whose radius tapers linearly from ra to rb (exact for ra == rb)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    ab = b - a
    t = np.clip((p - a) @ ab / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1) - (ra + (rb - ra) * t)


def _ellipsoid(p, centre, radii, axes=np.eye(3)):
    """Ellipsoid with semi-axes `radii` along the rows of `axes`; a distance bound, good near the surface."""
    q = (p - np.asarray(centre)) @ np.asarray(axes).T
    r = np.asarray(radii, np.float64)
    k0 = np.linalg.norm(q / r, axis=1)
    k1 = np.linalg.norm(q / (r * r), axis=1)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)


def _torso(p):
    """Lofted ellipse cross-sections (_TORSO) with rounded top and bottom rims."""
    y0, y1 = _TORSO[0, 0], _TORSO[-1, 0]
    y = np.clip(p[:, 1], y0, y1)
    a, b, cz = _TORSO_FIT(y).T
    a, b = a - _TORSO_ROUND, b - _TORSO_ROUND
    x, z = p[:, 0], p[:, 2] - cz
    k0 = np.hypot(x / a, z / b)
    k1 = np.hypot(x / (a * a), z / (b * b))
    d_xz = k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)
    d_y = np.maximum(y0 + _TORSO_ROUND - p[:, 1], p[:, 1] - (y1 - _TORSO_ROUND))
    outside = np.hypot(np.maximum(d_xz, 0.0), np.maximum(d_y, 0.0))
    return outside + np.minimum(np.maximum(d_xz, d_y), 0.0) - _TORSO_ROUND


def _smin(a, b, k):
    """Polynomial smooth minimum: blends the two surfaces over a band of width k [m] (Quilez)."""
    h = np.maximum(k - np.abs(a - b), 0.0) / k
    return np.minimum(a, b) - 0.25 * k * h * h


@dataclass(frozen=True)
class _Part:
    sdf: object  # (N, 3) -> (N,)
    lo: tuple  # bounding box of the part [m]
    hi: tuple
    blend: float  # smooth-union band [m]
    bone: str  # owner bone; "torso" is shared among pelvis, spine and chest by height


def _box(points, pad):
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    return tuple(pts.min(0) - pad), tuple(pts.max(0) + pad)


def _parts(sk):
    """The body as primitives (the head is added from the bust separately)."""
    P = {n: sk.rest_positions[i] for i, n in enumerate(sk.names)}
    T = {n: sk.tips[i] for i, n in enumerate(sk.names)}
    parts = []

    def cone(a, b, ra, rb, blend, bone):
        lo, hi = _box([a, b], max(ra, rb))
        parts.append(_Part(lambda p, a=a, b=b: _round_cone(p, a, b, ra, rb), lo, hi, blend, bone))

    def ell(c, radii, blend, bone, axes=np.eye(3)):
        lo, hi = _box([c], max(radii))
        parts.append(_Part(lambda p, c=c, axes=axes: _ellipsoid(p, c, radii, axes), lo, hi, blend, bone))

    top = _TORSO[-1, 0]
    parts.append(_Part(_torso, (-0.2, _TORSO[0, 0], -0.15), (0.2, top, 0.15), 0.02, "torso"))
    cone((0.0, 1.37, -0.025), (0.0, 0.21 + HEAD_OFFSET[1], 0.0), 0.068, 0.054, 0.04, "neck")
    for s, sx in (("l", 1.0), ("r", -1.0)):
        ell((sx * 0.066, 0.878, -0.052), (0.080, 0.090, 0.074), 0.04, "pelvis")  # buttocks
        ell((sx * 0.078, 1.230, 0.048), (0.068, 0.064, 0.054), 0.03, "chest")  # chest
        ell((sx * 0.070, 1.400, -0.035), (0.085, 0.035, 0.045), 0.05, "chest")  # trapezius
        # clavicle: under the skin, but it gives the collar some weight on the clavicle bone
        cone(P[f"shoulder_{s}"] + (0, 0.02, 0.02), P[f"upper_arm_{s}"] + (0, 0.02, 0.0), 0.022, 0.028, 0.02,
             f"shoulder_{s}")
        sh, el, wr, tip = P[f"upper_arm_{s}"], P[f"forearm_{s}"], P[f"hand_{s}"], T[f"hand_{s}"]
        ell(sh + (sx * 0.010, -0.012, 0.0), (0.050, 0.058, 0.050), 0.04, f"upper_arm_{s}")  # deltoid
        cone(sh, el, 0.046, 0.034, 0.03, f"upper_arm_{s}")
        cone(el, wr, 0.035, 0.024, 0.02, f"forearm_{s}")
        ell(el + 0.3 * (wr - el) + (0, 0, 0.006), (0.040, 0.070, 0.038), 0.03, f"forearm_{s}",  # forearm muscle
            _frame(wr - el, (0.0, 0.0, 1.0)))
        along = _unit(tip - wr)
        hand = _frame(along, (0.0, 0.0, 1.0))  # rows: across the palm (z-ish), along, thickness
        a, b = wr + 0.030 * along, wr + 0.128 * along  # mitten: a flat round cone, the palm facing the thigh
        mitten = lambda p, a=a, b=b, n=hand[2]: _flat_cone(p, a, b, 0.035, 0.040, n, 0.5)
        parts.append(_Part(mitten, *_box([a, b], 0.045), 0.02, f"hand_{s}"))
        palm = -np.sign(hand[2, 0] * sx) * hand[2]
        cone(wr + 0.030 * along + 0.026 * hand[0] + 0.006 * palm,
             wr + 0.080 * along + 0.046 * hand[0] + 0.010 * palm, 0.013, 0.011, 0.015, f"hand_{s}")  # thumb
        hip, knee, ankle = P[f"thigh_{s}"], P[f"shin_{s}"], P[f"foot_{s}"]
        cone(hip, knee, 0.086, 0.051, 0.05, f"thigh_{s}")
        ell(hip + 0.48 * (knee - hip) + (sx * 0.012, 0.0, 0.012), (0.066, 0.18, 0.068), 0.05, f"thigh_{s}")
        cone(knee, ankle, 0.049, 0.032, 0.04, f"shin_{s}")
        ell(knee + 0.30 * (ankle - knee) + (0.0, 0.0, -0.018), (0.050, 0.11, 0.050), 0.04, f"shin_{s}")  # calf
        heel = np.array([ankle[0], 0.034, -0.060])
        toes = np.array([ankle[0] + sx * 0.010, 0.022, 0.150])
        foot = lambda p, heel=heel, toes=toes: _flat_cone(p, heel, toes, 0.034, 0.022, (1.0, 0.0, 0.0), 1.35)
        lo, hi = _box([heel, toes], 0.05)
        parts.append(_Part(foot, lo, hi, 0.02, f"foot_{s}"))
        cone(ankle + (0, -0.005, 0.005), (ankle[0] + sx * 0.004, 0.040, 0.080), 0.034, 0.028, 0.03, f"foot_{s}")
    return parts


def _flat_cone(p, a, b, ra, rb, axis, scale):
    """Round cone with its cross-section scaled by `scale` along `axis` (a unit vector across it)."""
    axis = _unit(axis)
    q = p + np.outer((p - a) @ axis, axis) * (1.0 / scale - 1.0)
    return _round_cone(q, a, b, ra, rb) * min(scale, 1.0)


def _frame(along, hint):
    """Orthonormal rows (across, along, normal): `across` is `hint` made perpendicular to `along`."""
    along = _unit(along)
    across = _unit(np.asarray(hint, np.float64) - (np.asarray(hint) @ along) * along)
    return np.stack([across, along, np.cross(across, along)])


# ---- building the mesh ----------------------------------------------------------------------------------

def _head_part():
    """The bust above _BUST_CUT_Y, lifted onto the body's neck."""
    head = procedural_head()
    bv = head.vertices + np.asarray(HEAD_OFFSET)
    bust = warp_mesh(bv, head.faces)
    cut = _BUST_CUT_Y + HEAD_OFFSET[1]

    def sdf(p):
        d, _ = signed_distance(p, bust)
        return np.maximum(d.astype(np.float64), cut - p[:, 1])

    lo = bv.min(0)
    lo[1] = cut
    return _Part(sdf, tuple(lo), tuple(bv.max(0)), 0.015, "head")


def _field(parts, points, reach=0.03):
    """Smooth union of the parts at (N, 3) points [m]; each part is only evaluated near its box.

    A part is skipped farther than its blend + `reach` [m] from its box, where it cannot move the surface.
    """
    D = np.ones(len(points))
    columns = [np.ascontiguousarray(points[:, k]) for k in range(3)]
    for part in parts:
        pad = part.blend + reach
        near = np.ones(len(points), bool)
        for k, c in enumerate(columns):
            near &= (c >= part.lo[k] - pad) & (c <= part.hi[k] + pad)
        near = np.flatnonzero(near)
        D[near] = _smin(D[near], part.sdf(points[near]), part.blend)
    return -_smin(-D, points[:, 1], 0.006)  # flat soles: nothing below the floor y = 0


def _project(parts, v, steps=2, eps=5e-4):
    """Newton steps moving points onto the zero level of the field along its gradient."""
    offsets = eps * np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], np.float64)
    for _ in range(steps):
        samples = _field(parts, (v[:, None, :] + offsets[None]).reshape(-1, 3)).reshape(-1, 4)
        d = samples.mean(1)
        g = np.einsum("nk,kj->nj", samples, offsets) / (4.0 * eps * eps)  # tetrahedral difference
        v = v - (d / np.maximum(np.einsum("nj,nj->n", g, g), 1e-6))[:, None] * g
    return v


def _extract(parts, h, relax_iterations):
    """Marching cubes on a grid of spacing h [m], then relax the vertices and project them back.

    Marching cubes places vertices by linear interpolation along grid edges, which leaves
    grid-aligned ripples; averaging with neighbours and re-projecting onto the field's zero level
    removes them and evens out the triangles.
    """
    import trimesh
    from skimage.measure import marching_cubes

    lo = np.array([-0.80, -0.04, -0.20])
    hi = np.array([0.80, HEIGHT + 0.04, 0.28])
    axes = [np.arange(lo[k], hi[k] + h, h) for k in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
    D = _field(parts, grid.reshape(-1, 3)).reshape(grid.shape[:3])
    verts, faces, _, _ = marching_cubes(D, level=0.0, spacing=(h, h, h), gradient_direction="ascent")
    mesh = trimesh.Trimesh(verts + lo, faces, process=True)
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    pieces = mesh.split(only_watertight=False)
    if len(pieces) > 1:
        mesh = max(pieces, key=lambda m: len(m.faces))
    if mesh.volume < 0:
        mesh.invert()
    v = np.asarray(mesh.vertices, np.float64)
    avg = neighbour_average(mesh.edges_unique, len(mesh.vertices))
    for _ in range(relax_iterations):
        v = _project(parts, 0.5 * v + 0.5 * (avg @ v), steps=1)
    v = _project(parts, v, steps=2)
    return trimesh.Trimesh(v, mesh.faces, process=False)


def _skin_weights(mesh, parts, sk, falloff=0.012, smooth_iterations=8):
    """Weights from each vertex's distance to the parts each bone owns, smoothed over the surface.

    A vertex belongs to the parts it lies on (distance ~0) and fades from parts it is `falloff` [m]
    or more away from, so joints blend over roughly one limb radius. The torso loft is shared among
    pelvis, spine and chest by height; the head is rigid above the neck.
    """
    v = np.asarray(mesh.vertices, np.float64)
    J = sk.num_joints
    bone = {n: i for i, n in enumerate(sk.names)}
    dist = np.stack([part.sdf(v) for part in parts], 1)
    affinity = np.exp(-(dist - dist.min(1, keepdims=True)) / falloff)
    W = np.zeros((len(v), J))
    y = v[:, 1]
    ys = [sk.rest_positions[bone[n], 1] for n in ("pelvis", "spine", "chest")]
    up = lambda y0, y1: _smoothstep((y - y0) / (y1 - y0))  # noqa: E731
    torso_share = {"pelvis": 1.0 - up(ys[0], ys[1]), "spine": up(ys[0], ys[1]) * (1.0 - up(ys[1], ys[2] + 0.05)),
                   "chest": up(ys[1], ys[2] + 0.05)}
    for k, part in enumerate(parts):
        if part.bone == "torso":
            for n, share in torso_share.items():
                W[:, bone[n]] += affinity[:, k] * share
        else:
            W[:, bone[part.bone]] += affinity[:, k]
    W /= W.sum(1, keepdims=True)

    # uniform Laplacian smoothing of the weights removes creases where the nearest part changes
    A = neighbour_average(mesh.edges_unique, len(mesh.vertices))
    for _ in range(smooth_iterations):
        W = 0.5 * W + 0.5 * (A @ W)

    # the head above the neck is rigid on the head bone, so hair roots follow it exactly
    yb = y - HEAD_OFFSET[1]
    r = np.hypot(v[:, 0], v[:, 2])
    w_head = _smoothstep((yb - _HEAD_RIGID_Y[0]) / (_HEAD_RIGID_Y[1] - _HEAD_RIGID_Y[0]))
    w_head = np.where(yb >= _HEAD_RIGID_Y[1], 1.0, w_head * (1.0 - _smoothstep((r - 0.09) / 0.03)))
    W[:, bone["head"]] = 0.0
    W *= ((1.0 - w_head) / np.maximum(W.sum(1), 1e-12))[:, None]
    W[:, bone["head"]] = w_head

    idx = np.argsort(-W, axis=1)[:, :4]
    w = np.take_along_axis(W, idx, 1)
    w[w < 1e-3] = 0.0
    w /= w.sum(1, keepdims=True)
    idx[w == 0.0] = 0
    return idx.astype(np.int64), w


def _landmarks(v, sk, parts):
    """Garment landmarks in the rest pose [m] (heights are floats, points (3,) arrays)."""
    P = {n: sk.rest_positions[i] for i, n in enumerate(sk.names)}
    out = {"neck_base": np.array([0.0, 1.41, -0.024])}  # neck axis where it meets the trapezius
    for s, sx in (("l", 1.0), ("r", -1.0)):
        # top of the shoulder half way from the neck to the shoulder joint, where a strap rests:
        # bisect the field down a vertical line from open air (1.55 m) to inside the body (1.30 m)
        x = sx * 0.5 * (0.06 + abs(P[f"upper_arm_{s}"][0]))
        lo, hi = 1.30, 1.55
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if _field(parts, np.array([[x, mid, -0.03]]))[0] < 0.0 else (lo, mid)
        out[f"shoulder_{s}"] = np.array([x, 0.5 * (lo + hi), -0.03])
    between = (np.abs(v[:, 0]) < 0.01) & (v[:, 1] > 0.5) & (v[:, 1] < 1.0)
    out.update(chest_y=CHEST_Y, waist_y=WAIST_Y, hip_y=HIP_Y, crotch_y=float(v[between, 1].min()),
               knee_y=float(P["shin_l"][1]), ankle_y=float(P["foot_l"][1]), height=float(v[:, 1].max()))
    return out


@functools.lru_cache(maxsize=4)
def _build(resolution, relax_iterations):
    sk = default_skeleton()
    parts = _parts(sk) + [_head_part()]
    mesh = _extract(parts, resolution, relax_iterations)
    v = np.asarray(mesh.vertices, np.float64)
    f = np.asarray(mesh.faces, np.int64)
    idx, w = _skin_weights(mesh, parts, sk)
    scalp = _scalp_faces(v - np.asarray(HEAD_OFFSET), f)
    arrays = dict(vertices=v, faces=f, skin_indices=idx, skin_weights=w, scalp_faces=scalp)
    for a in arrays.values():
        a.setflags(write=False)
    return BodyAsset("body", pivot=tuple(float(c) for c in sk.rest_positions[sk.index("head")]),
                     num_bones=sk.num_joints, skeleton=sk, landmarks=_landmarks(v, sk, parts), **arrays)


def procedural_body(resolution=0.0125, relax_iterations=4):
    """The built-in mannequin: ~1.70 m, closed, about 12k vertices at the default resolution.

    resolution [m]: marching-cubes grid spacing (vertex count grows as 1 / resolution^2);
    relax_iterations: rounds of neighbour averaging and re-projection onto the surface.
    Built once per argument set; each call returns fresh, writable copies of the arrays.
    """
    asset = _build(float(resolution), int(relax_iterations))
    copies = {k: np.array(getattr(asset, k)) for k in ("vertices", "faces", "skin_indices", "skin_weights",
                                                          "scalp_faces")}
    lm = {k: (np.array(x) if isinstance(x, np.ndarray) else x) for k, x in asset.landmarks.items()}
    return replace(asset, landmarks=lm, **copies)


def scalp_mask(vertices, faces, head_offset=HEAD_OFFSET):
    """sim.head's hairline rule applied to a body mesh whose head is the bust lifted by head_offset."""
    return _scalp_faces(np.asarray(vertices, np.float64) - np.asarray(head_offset), np.asarray(faces))


# ---- animation -------------------------------------------------------------------------------------------

def _axis_angle(axis, angle):
    """(T, 3, 3) rotations by angle[t] [rad] about a fixed unit axis (Rodrigues)."""
    x, y, z = _unit(axis)
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)


def _rx(a):
    return _axis_angle((1.0, 0.0, 0.0), a)


def _ry(a):
    return _axis_angle((0.0, 1.0, 0.0), a)


def _rz(a):
    return _axis_angle((0.0, 0.0, 1.0), a)


def _min_jerk(u):
    u = np.clip(u, 0.0, 1.0)
    return u * u * u * (10.0 + u * (-15.0 + 6.0 * u))


@dataclass(frozen=True)
class BodyAnimation:
    """Procedural body motion from the rest pose: presets "walk", "arm_raise", "turn" and "none".

    Every motion is scaled by an ease-in that is exactly 0 at t = 0, so the pose at t = 0 is the rest
    pose bit for bit and garments fitted at rest start free of penetration. Angles in degrees, lengths
    in metres, times in seconds.
    """

    motion: str = "none"
    ease_in_s: float = 0.6
    # walk: feet follow planted-stance / swing paths and the legs are solved with two-bone IK
    step_length_m: float = 0.60  # heel-to-heel distance of one step
    cadence_steps_per_s: float = 1.8
    in_place: bool = False  # True: a treadmill walk, the root stays at z = 0
    stance_fraction: float = 0.6  # part of each leg's cycle with the foot on the ground
    foot_clearance_m: float = 0.07  # ankle lift at mid-swing
    heel_rise_degrees: float = 18.0  # foot pitch at toe-off
    toe_up_degrees: float = 8.0  # foot pitch at heel strike
    pelvis_drop_m: float = 0.035  # mean lowering of the pelvis while walking
    pelvis_bob_m: float = 0.012  # vertical oscillation, two per stride
    pelvis_sway_m: float = 0.022  # side shift over the stance foot
    pelvis_yaw_degrees: float = 5.0
    pelvis_roll_degrees: float = 4.0  # swing-side hip drop
    torso_twist_degrees: float = 7.0  # chest counter-rotation
    arm_swing_degrees: float = 16.0  # shoulder flexion amplitude
    arm_swing_back_degrees: float = 4.0  # the swing is centred this far behind the body
    arm_lower_degrees: float = 24.0  # arms brought down from the A-pose while walking
    elbow_bend_degrees: float = 15.0  # mean elbow flexion while walking (+-50%, most when the arm is ahead)
    # arm raise: from the A-pose to raise_to_degrees (angle from the torso) and back, repeating
    raise_to_degrees: float = 150.0
    raise_s: float = 1.5
    hold_s: float = 0.5
    clavicle_share: float = 0.2  # part of the raise taken by the clavicles (shrug)
    # turn: yaw about the vertical through the pelvis and back, repeating; head and chest lead the pelvis
    turn_degrees: float = 90.0
    turn_s: float = 2.0
    head_lead_s: float = 0.25
    skeleton: Skeleton = field(default=None, compare=False, repr=False)

    @staticmethod
    def preset(name, skeleton=None, **overrides):
        if name not in ("walk", "arm_raise", "turn", "none"):
            raise KeyError(name)
        return BodyAnimation(motion=name, skeleton=skeleton, **overrides)

    @property
    def _sk(self):
        return self.skeleton if self.skeleton is not None else default_skeleton()

    # -- pose: root offset (T, 3) and local joint rotations (T, J, 3, 3) about each rest joint
    def local_pose(self, times):
        t = np.atleast_1d(np.asarray(times, np.float64))
        sk = self._sk
        R = np.tile(np.eye(3), (len(t), sk.num_joints, 1, 1))
        root = np.zeros((len(t), 3))
        ease = _smoothstep(t / self.ease_in_s) if self.ease_in_s > 0 else np.ones_like(t)
        if self.motion == "walk":
            self._walk(t, ease, R, root)
        elif self.motion == "arm_raise":
            self._arm_raise(t, ease, R)
        elif self.motion == "turn":
            self._turn(t, R)
        return root, R

    def bone_matrices(self, times):
        """(T, J, 4, 4) skinning matrices (world pose @ inverse bind): skinned = sum_k w_k M[b_k] @ rest."""
        root, R = self.local_pose(times)
        return _skinning_matrices(self._sk, root, R)

    def joint_positions(self, times):
        """(T, J, 3) world joint positions [m]."""
        M = self.bone_matrices(times)
        p = self._sk.rest_positions
        return np.einsum("tjab,jb->tja", M[:, :, :3, :3], p) + M[:, :, :3, 3]

    # -- motions
    def _arm_raise(self, t, ease, R):
        sk = self._sk
        cycle = 2.0 * (self.raise_s + self.hold_s)
        u = np.mod(t, cycle)
        up = _smoothstep(u / self.raise_s) - _smoothstep((u - self.raise_s - self.hold_s) / self.raise_s)
        total = np.radians(self.raise_to_degrees - ARM_ABDUCTION_DEGREES) * up * ease
        for s, sx in (("l", 1.0), ("r", -1.0)):
            R[:, sk.index(f"shoulder_{s}")] = _rz(sx * self.clavicle_share * total)
            R[:, sk.index(f"upper_arm_{s}")] = _rz(sx * (1.0 - self.clavicle_share) * total)

    def _turn(self, t, R):
        sk = self._sk
        delay = self.head_lead_s  # the body holds still while the head starts the turn

        def yaw(tt):
            cycle = 2.0 * (self.turn_s + self.hold_s)
            u = np.mod(np.maximum(tt - delay, 0.0), cycle)
            a = _smoothstep(u / self.turn_s) - _smoothstep((u - self.turn_s - self.hold_s) / self.turn_s)
            return np.radians(self.turn_degrees) * a * (tt > delay)

        pelvis, chest, head = yaw(t), yaw(t + 0.5 * self.head_lead_s), yaw(t + self.head_lead_s)
        R[:, sk.index("pelvis")] = _ry(pelvis)
        R[:, sk.index("spine")] = _ry(0.5 * (chest - pelvis))
        R[:, sk.index("chest")] = _ry(0.5 * (chest - pelvis))
        R[:, sk.index("neck")] = _ry(0.5 * (head - chest))
        R[:, sk.index("head")] = _ry(0.5 * (head - chest))

    def _walk(self, t, ease, R, root):
        sk = self._sk
        P = sk.rest_positions
        stride_hz = 0.5 * self.cadence_steps_per_s
        speed = self.step_length_m * self.cadence_steps_per_s  # [m/s]
        phase_l = np.mod(stride_hz * t, 1.0)  # 0 = left heel strike
        cyc = 2.0 * np.pi * phase_l

        # root: forward distance is the integral of speed * ease, in closed form
        if not self.in_place:
            te = self.ease_in_s
            u = np.clip(t / te, 0.0, 1.0) if te > 0 else np.ones_like(t)
            root[:, 2] = speed * (te * (u ** 3 - 0.5 * u ** 4) + np.maximum(t - te, 0.0))
        midstance = 0.5 * self.stance_fraction
        root[:, 1] = ease * (-self.pelvis_drop_m + self.pelvis_bob_m * np.cos(4.0 * np.pi * (phase_l - midstance)))
        root[:, 0] = ease * self.pelvis_sway_m * np.sin(cyc)

        # the pelvis turns with the swinging leg and drops on its side; the chest turns against it
        yaw = -np.radians(self.pelvis_yaw_degrees) * np.cos(cyc) * ease
        roll = np.radians(self.pelvis_roll_degrees) * np.sin(cyc) * ease
        R_pelvis = _ry(yaw) @ _rz(roll)
        R[:, sk.index("pelvis")] = R_pelvis
        chest_yaw = np.radians(self.torso_twist_degrees) * np.cos(cyc) * ease  # in the world
        R[:, sk.index("spine")] = _ry(0.4 * (chest_yaw - yaw)) @ _rz(-0.6 * roll)
        R[:, sk.index("chest")] = _ry(0.6 * (chest_yaw - yaw)) @ _rz(-0.4 * roll)
        # the head keeps looking ahead
        R[:, sk.index("neck")] = _ry(-0.5 * chest_yaw)
        R[:, sk.index("head")] = _ry(-0.5 * chest_yaw)

        # arms: lowered from the A-pose, swinging against the legs
        swing = np.radians(self.arm_swing_degrees) * np.cos(cyc) * ease
        back = np.radians(self.arm_swing_back_degrees) * ease
        lower = np.radians(self.arm_lower_degrees) * ease
        bend = np.radians(self.elbow_bend_degrees) * ease
        for s, sx, sgn in (("l", 1.0, -1.0), ("r", -1.0, 1.0)):
            i_up, i_fore = sk.index(f"upper_arm_{s}"), sk.index(f"forearm_{s}")
            arm = P[i_fore] - P[i_up]
            hinge = _unit(np.cross(arm, (0.0, 0.0, 1.0)))  # positive angle swings the arm forward
            R[:, i_up] = _rz(-sx * lower) @ _axis_angle(hinge, sgn * swing - back)
            fore_hinge = _unit(np.cross(P[sk.index(f"hand_{s}")] - P[i_fore], (0.0, 0.0, 1.0)))
            R[:, i_fore] = _axis_angle(fore_hinge, bend * (1.0 + 0.5 * sgn * np.cos(cyc)))

        # legs: two-bone IK to ankle targets given in the walking (root) frame; the thigh's local
        # rotation cancels the pelvis's, so each leg swings in a plane fixed in the world
        pelvis_shift = root + P[0] - np.einsum("tab,b->ta", R_pelvis, P[0])  # exactly 0 at rest
        for s, offset in (("l", 0.0), ("r", 0.5)):
            phase = np.mod(phase_l + offset, 1.0)
            i_hip, i_knee, i_ankle = (sk.index(n + s) for n in ("thigh_", "shin_", "foot_"))
            ankle_rel, pitch = self._foot_path(phase)
            target = P[i_ankle] + ease[:, None] * ankle_rel
            target[:, 2] += root[:, 2]
            hip = np.einsum("tab,b->ta", R_pelvis, P[i_hip]) + pelvis_shift
            a_hip, a_knee, a_abd = _leg_ik(P[i_hip], P[i_knee], P[i_ankle], hip, target)
            R_leg = _rz(a_abd) @ _rx(a_hip)
            R[:, i_hip] = np.swapaxes(R_pelvis, 1, 2) @ R_leg
            R[:, i_knee] = _rx(a_knee)
            R[:, i_ankle] = _rx(ease * pitch - a_hip - a_knee)

    def _foot_path(self, phase):
        """Ankle offset from its rest position (T, 3) and world foot pitch [rad], before easing.

        Stance: the ankle moves back under the hip at walking speed (less a little heel-to-toe roll)
        and the heel rises before toe-off. Swing: a minimum-jerk path forward, lifted by the clearance.
        """
        beta = self.stance_fraction
        reach = beta * self.step_length_m - 0.03  # half the ankle's travel relative to the hip [m]
        rise = np.radians(self.heel_rise_degrees)
        off = np.zeros((len(phase), 3))
        stance = phase < beta
        u = np.where(stance, phase / beta, (phase - beta) / (1.0 - beta))
        late = _smoothstep((u - 0.6) / 0.4)  # heel rise over the last 40% of stance
        heel_up = np.where(stance, rise * late, rise * (1.0 - _smoothstep(u / 0.5)))
        strike = np.radians(self.toe_up_degrees)
        toe_up = np.where(stance, -strike * (1.0 - _smoothstep(u / 0.15)), -strike * _smoothstep((u - 0.6) / 0.4))
        pitch = heel_up + toe_up
        s = _min_jerk(u)
        off[:, 2] = np.where(stance, reach * (1.0 - 2.0 * u), reach * (2.0 * s - 1.0))
        # a pitched foot pivots on its toe (heel up) or heel (toe up), which lifts the ankle
        sk = self._sk
        i = sk.index("foot_l")
        height = sk.rest_positions[i, 1]
        toe, heel = sk.tips[i, 2] - sk.rest_positions[i, 2], _HEEL_REACH
        lift = np.where(pitch > 0, toe, heel) * np.sin(np.abs(pitch)) - height * (1.0 - np.cos(pitch))
        off[:, 1] = lift + np.where(stance, 0.0, self.foot_clearance_m * np.sin(np.pi * u) ** 2)
        return off, pitch


def _leg_ik(hip_rest, knee_rest, ankle_rest, hip, target):
    """Hip flexion, knee flexion (Rx angles from rest) and hip abduction (Rz) putting the ankle on target.

    Solved in the sagittal (y, z) plane with the knee bending forward; a target out of reach
    straightens the leg. Angles are differences from the same solve for the rest pose, so the rest
    target gives exactly zero.
    """
    thigh, shin = knee_rest - hip_rest, ankle_rest - knee_rest
    l1, l2 = np.hypot(thigh[1], thigh[2]), np.hypot(shin[1], shin[2])

    def solve(d):  # world thigh and shin angles from straight down, positive backward (as Rx)
        dist = np.clip(np.hypot(d[:, 1], d[:, 2]), abs(l1 - l2) + 1e-6, (l1 + l2) * (1.0 - 1e-9))
        to_target = np.arctan2(-d[:, 2], -d[:, 1])
        at_hip = np.arccos(np.clip((l1 * l1 + dist * dist - l2 * l2) / (2.0 * l1 * dist), -1.0, 1.0))
        at_ankle = np.arccos(np.clip((l2 * l2 + dist * dist - l1 * l1) / (2.0 * l2 * dist), -1.0, 1.0))
        return to_target - at_hip, to_target + at_ankle  # knee forward of the hip-ankle line

    d = target - hip
    thigh_0, shin_0 = solve((ankle_rest - hip_rest)[None])
    thigh_w, shin_w = solve(d)
    a_hip = thigh_w - thigh_0
    a_knee = (shin_w - shin_0) - a_hip
    a_abd = np.arcsin(np.clip((d[:, 0] - (ankle_rest[0] - hip_rest[0])) / (l1 + l2), -1.0, 1.0))
    return a_hip, a_knee, a_abd


def _skinning_matrices(sk, root, R):
    """M_j = M_parent @ T(p_j) R_j T(-p_j), M_root = T(root) T(p_0) R_0 T(-p_0): identity when R = I, root = 0."""
    n, J = R.shape[:2]
    M = np.zeros((n, J, 4, 4))
    M[:, :, 3, 3] = 1.0
    p = sk.rest_positions
    for j in range(J):
        local = np.zeros((n, 4, 4))
        local[:, :3, :3] = R[:, j]
        local[:, :3, 3] = p[j] - np.einsum("tab,b->ta", R[:, j], p[j])
        local[:, 3, 3] = 1.0
        if sk.parents[j] < 0:
            local[:, :3, 3] += root
            M[:, j] = local
        else:
            M[:, j] = M[:, sk.parents[j]] @ local
    return M
