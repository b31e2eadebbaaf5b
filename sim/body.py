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
import threading
from dataclasses import dataclass, field, replace

import numpy as np
import warp as wp
from scipy.interpolate import PchipInterpolator

from warp_kernels import body_motion

from .asset_cache import cached_arrays
from .collision_proxy import neighbour_average
from .head import _scalp_faces, _smoothstep, procedural_head
from .sphere_tree import signed_distance, warp_mesh

HEIGHT = 1.70  # crown height [m]
HEAD_OFFSET = (0.0, HEIGHT - 0.472, 0.0)  # bust coordinates + offset = body coordinates (bust crown at 0.472)
_BUST_CUT_Y = 0.18  # bust coordinates: only the bust above this height joins the body
_HEAD_RIGID_Y = (0.17, 0.23)  # bust coordinates: head-bone weight ramps 0 -> 1 (1 exactly above)
ARM_ABDUCTION_DEGREES = 42.0  # rest A-pose: upper arm angle out from the torso
_HEEL_REACH = 0.09  # [m] from the ankle back to where the heel meets the floor
KEPT_LAUNCH_TIMES = 64  # BodyAnimation.bone_matrices keeps its launch for requests of up to this many times
# the named joints the motion kernel addresses (body_motion.BodyMotion), and those each preset moves
_KERNEL_JOINTS = ("pelvis", "spine", "chest", "neck", "head", "shoulder_l", "shoulder_r", "upper_arm_l", "upper_arm_r",
                  "forearm_l", "forearm_r", "thigh_l", "thigh_r", "shin_l", "shin_r", "foot_l", "foot_r")
_MOTION_JOINTS = {
    "none": (),
    "walk": tuple(n for n in _KERNEL_JOINTS if not n.startswith("shoulder")) + ("hand_l", "hand_r"),
    "arm_raise": ("shoulder_l", "shoulder_r", "upper_arm_l", "upper_arm_r"),
    "turn": ("pelvis", "spine", "chest", "neck", "head"),
}

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


_ARRAYS = ("vertices", "faces", "skin_indices", "skin_weights", "scalp_faces")
_LANDMARK = "landmark."  # prefix of the landmarks' keys among a cached body's arrays


def _build_arrays(resolution, relax_iterations):
    """The mesh, skinning, scalp and landmarks as named arrays (what the asset cache stores)."""
    sk = default_skeleton()
    parts = _parts(sk) + [_head_part()]
    mesh = _extract(parts, resolution, relax_iterations)
    v = np.asarray(mesh.vertices, np.float64)
    f = np.asarray(mesh.faces, np.int64)
    idx, w = _skin_weights(mesh, parts, sk)
    scalp = _scalp_faces(v - np.asarray(HEAD_OFFSET), f)
    arrays = dict(vertices=v, faces=f, skin_indices=idx, skin_weights=w, scalp_faces=scalp)
    arrays.update({_LANDMARK + k: np.asarray(x, np.float64) for k, x in _landmarks(v, sk, parts).items()})
    return arrays


@functools.lru_cache(maxsize=4)
def _build(resolution, relax_iterations):
    arrays = cached_arrays("body", ("procedural_body", resolution, relax_iterations),
                           lambda: _build_arrays(resolution, relax_iterations))
    landmarks = {k[len(_LANDMARK):]: (float(a) if a.ndim == 0 else a) for k, a in arrays.items()
                 if k.startswith(_LANDMARK)}
    for a in arrays.values():
        a.setflags(write=False)
    sk = default_skeleton()
    return BodyAsset("body", pivot=tuple(float(c) for c in sk.rest_positions[sk.index("head")]),
                     num_bones=sk.num_joints, skeleton=sk, landmarks=landmarks, **{k: arrays[k] for k in _ARRAYS})


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

    def bone_matrices(self, times):
        """(T, J, 4, 4) float64 skinning matrices (world pose @ inverse bind): skinned = sum_k w_k M[b_k] @ rest.

        One launch of warp_kernels.body_motion on the CPU evaluates every time: a frame's dozen
        substep poses cost tens of microseconds, not a NumPy evaluation's milliseconds."""
        t = np.atleast_1d(np.asarray(times, np.float64))
        joints = self._sk.num_joints
        if len(t) == 0:
            return np.zeros((0, joints, 4, 4))
        with self._launch_lock:
            # one recorded launch and its buffers per count of times: a frame asks for the same count
            # every time, and building a launch costs more than running it (long requests, rare and
            # 4 kB per time, are not kept)
            launch = self._launches.get(len(t))
            if launch is None:
                buffers = (wp.empty(len(t), dtype=wp.float64, device="cpu"),
                           wp.empty(len(t) * joints, dtype=wp.mat33d, device="cpu"),
                           wp.empty(len(t) * joints, dtype=wp.mat44d, device="cpu"))
                command = wp.launch(body_motion.body_bone_matrices, len(t), [buffers[0], self._kernel_motion,
                                    *buffers[1:]], device="cpu", record_cmd=True)
                launch = (buffers[0], buffers[2], command)
                if len(t) <= KEPT_LAUNCH_TIMES:
                    self._launches[len(t)] = launch
            time_buffer, bones, command = launch
            time_buffer.numpy()[:] = t
            command.launch()
            return bones.numpy().reshape(len(t), joints, 4, 4).copy()

    @functools.cached_property
    def _launches(self):
        return {}

    @functools.cached_property
    def _launch_lock(self):
        return threading.Lock()

    @functools.cached_property
    def _kernel_motion(self):
        """The body_motion.BodyMotion of this animation (angles in radians, derived walk constants)."""
        sk = self._sk
        m = body_motion.BodyMotion()
        m.motion = {"none": body_motion.MOTION_NONE, "walk": body_motion.MOTION_WALK,
                    "arm_raise": body_motion.MOTION_ARM_RAISE, "turn": body_motion.MOTION_TURN}[self.motion]
        missing = [name for name in _MOTION_JOINTS[self.motion] if name not in sk.names]
        if missing:
            raise ValueError(f"the {self.motion} motion needs the skeleton's joints {', '.join(missing)}")
        for name in _KERNEL_JOINTS:  # -1 for a joint this skeleton lacks and the motion leaves alone
            setattr(m, name, sk.index(name) if name in sk.names else -1)
        m.ease_in_s = self.ease_in_s
        m.in_place = int(self.in_place)
        m.stride_hz = 0.5 * self.cadence_steps_per_s
        m.speed = self.step_length_m * self.cadence_steps_per_s
        m.stance_fraction = self.stance_fraction
        m.reach = self.stance_fraction * self.step_length_m - 0.03  # less a little heel-to-toe roll
        m.foot_clearance = self.foot_clearance_m
        m.heel_rise, m.toe_up = np.radians(self.heel_rise_degrees), np.radians(self.toe_up_degrees)
        m.pelvis_drop, m.pelvis_bob, m.pelvis_sway = self.pelvis_drop_m, self.pelvis_bob_m, self.pelvis_sway_m
        for name in ("pelvis_yaw", "pelvis_roll", "torso_twist", "arm_swing", "arm_swing_back", "arm_lower",
                     "elbow_bend"):
            setattr(m, name, np.radians(getattr(self, name + "_degrees")))
        P = sk.rest_positions
        if self.motion == "walk":
            foot = sk.index("foot_l")  # both feet pivot as the left one is shaped
            m.toe, m.heel, m.ankle_height = sk.tips[foot, 2] - P[foot, 2], _HEEL_REACH, P[foot, 1]
            for s in ("l", "r"):
                # a positive angle about each hinge swings the arm forward and bends the elbow
                arm = P[sk.index(f"forearm_{s}")] - P[sk.index(f"upper_arm_{s}")]
                fore = P[sk.index(f"hand_{s}")] - P[sk.index(f"forearm_{s}")]
                setattr(m, f"arm_hinge_{s}", wp.vec3d(*_unit(np.cross(arm, (0.0, 0.0, 1.0)))))
                setattr(m, f"fore_hinge_{s}", wp.vec3d(*_unit(np.cross(fore, (0.0, 0.0, 1.0)))))
        m.raise_angle = np.radians(self.raise_to_degrees - ARM_ABDUCTION_DEGREES)
        m.raise_s, m.hold_s, m.clavicle_share = self.raise_s, self.hold_s, self.clavicle_share
        m.turn_angle, m.turn_s, m.head_lead_s = np.radians(self.turn_degrees), self.turn_s, self.head_lead_s
        m.rest = wp.array(P, dtype=wp.vec3d, device="cpu")
        m.parents = wp.array(sk.parents, dtype=wp.int32, device="cpu")
        return m

    def joint_positions(self, times):
        """(T, J, 3) world joint positions [m]."""
        M = self.bone_matrices(times)
        p = self._sk.rest_positions
        return np.einsum("tjab,jb->tja", M[:, :, :3, :3], p) + M[:, :, :3, 3]
