"""Built-in head: a closed bust (head, neck, shoulders), its turn-and-nod animation and its scalp.

The bust is a surface swept along the vertical axis: each ring is a superellipse whose half-width,
half-depth, forward offset and exponent follow a profile, with Gaussian bumps for nose, brow, chin
and ears. Units are metres, Y up, the face looks down +Z. Two bones: 0 = body (fixed), 1 = head,
rotating about a pivot in the neck; the neck blends between them.
"""

from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import PchipInterpolator

# height, half-width (x), half-depth (z), forward offset (z), superellipse exponent
_PROFILE = np.array([
    [0.000, 0.200, 0.110, 0.000, 3.0],
    [0.050, 0.214, 0.117, 0.000, 3.0],
    [0.090, 0.205, 0.112, 0.000, 2.6],
    [0.120, 0.165, 0.095, 0.000, 2.2],
    [0.145, 0.100, 0.075, -0.005, 2.0],
    [0.165, 0.062, 0.060, -0.005, 2.0],
    [0.200, 0.055, 0.057, 0.000, 2.0],
    [0.235, 0.058, 0.066, 0.014, 2.0],
    [0.260, 0.063, 0.088, 0.020, 2.0],
    [0.280, 0.068, 0.095, 0.018, 2.1],
    [0.310, 0.073, 0.099, 0.015, 2.2],
    [0.340, 0.077, 0.100, 0.012, 2.3],
    [0.370, 0.079, 0.100, 0.010, 2.3],
    [0.400, 0.077, 0.097, 0.008, 2.2],
    [0.425, 0.070, 0.089, 0.006, 2.1],
    [0.445, 0.058, 0.075, 0.004, 2.0],
    [0.460, 0.042, 0.055, 0.003, 2.0],
    [0.468, 0.025, 0.033, 0.002, 2.0],
    [0.472, 0.000, 0.000, 0.002, 2.0],
])
# feature bumps: height, angle (pi/2 = front), amplitude [m], sigma height, sigma angle
_BUMPS = [
    (0.322, np.pi / 2, 0.018, 0.020, 0.13),  # nose
    (0.352, np.pi / 2, 0.004, 0.010, 0.55),  # brow
    (0.344, np.pi / 2 - 0.42, -0.006, 0.010, 0.12),  # eye sockets
    (0.344, np.pi / 2 + 0.42, -0.006, 0.010, 0.12),
    (0.268, np.pi / 2, 0.006, 0.012, 0.30),  # chin
    (0.335, 0.0, 0.012, 0.024, 0.16),  # ears
    (0.335, np.pi, 0.012, 0.024, 0.16),
]
NECK_PIVOT = (0.0, 0.20, 0.0)


@dataclass
class HeadAsset:
    """A collider mesh with skinning and the region hair may grow from."""

    name: str
    vertices: np.ndarray  # (V, 3) float, metres
    faces: np.ndarray  # (F, 3) int
    skin_indices: np.ndarray  # (V, 4) int
    skin_weights: np.ndarray  # (V, 4) float, rows sum to 1
    scalp_faces: np.ndarray  # (F,) bool
    pivot: tuple = NECK_PIVOT
    num_bones: int = 2


def _smoothstep(t):
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def bust_surface(y, theta):
    """Points (len(y), len(theta), 3) of the bust's smooth surface at heights y [m] and ring angles
    theta [rad] (pi/2 faces front, +Z). Each ring is a superellipse pushed out radially by the bumps."""
    y, theta = np.atleast_1d(np.asarray(y, np.float64)), np.atleast_1d(np.asarray(theta, np.float64))
    prof = PchipInterpolator(_PROFILE[:, 0], _PROFILE[:, 1:], axis=0)
    a, b, cz, e = prof(y).T
    c, s = np.cos(theta)[None, :], np.sin(theta)[None, :]
    ex = 2.0 / e[:, None]
    x = a[:, None] * np.sign(c) * np.abs(c) ** ex
    z = b[:, None] * np.sign(s) * np.abs(s) ** ex
    bump = np.zeros((len(y), len(theta)))
    for hy, ang, amp, sy, sa in _BUMPS:
        d_ang = np.angle(np.exp(1j * (theta[None, :] - ang)))
        bump += amp * np.exp(-0.5 * ((y[:, None] - hy) / sy) ** 2 - 0.5 * (d_ang / sa) ** 2)
    r = np.hypot(x, z)
    scale = (r + bump) / np.maximum(r, 1e-9)
    return np.stack([x * scale, np.repeat(y[:, None], len(theta), 1), z * scale + cz[:, None]], -1)


def procedural_head(rings=72, segments=64):
    """The built-in bust: about rings x segments vertices, closed and consistently wound."""
    prof = PchipInterpolator(_PROFILE[:, 0], _PROFILE[:, 1:], axis=0)
    # place rings evenly along the silhouette's arc length so triangles stay well shaped
    y_dense = np.linspace(0.0, _PROFILE[-1, 0], 2000)
    p = prof(y_dense)
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(y_dense), np.diff(p[:, 0])))])
    y = np.interp(np.linspace(0.0, arc[-1], rings + 2)[1:-1], arc, y_dense)
    theta = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    ring_pts = bust_surface(y, theta)

    bottom = np.array([[0.0, 0.0, 0.0]])
    top = np.array([[0.0, _PROFILE[-1, 0], _PROFILE[-1, 3]]])
    vertices = np.concatenate([bottom, ring_pts.reshape(-1, 3), top])
    ring = lambda i: 1 + i * segments + np.arange(segments)  # noqa: E731
    faces = []
    j, jn = np.arange(segments), (np.arange(segments) + 1) % segments
    r0 = ring(0)
    faces.append(np.stack([np.zeros(segments, int), r0[jn], r0[j]], 1))
    for i in range(rings - 1):
        lo, hi = ring(i), ring(i + 1)
        faces.append(np.stack([lo[j], lo[jn], hi[jn]], 1))
        faces.append(np.stack([lo[j], hi[jn], hi[j]], 1))
    last, top_i = ring(rings - 1), len(vertices) - 1
    faces.append(np.stack([last[j], last[jn], np.full(segments, top_i)], 1))
    faces = np.concatenate(faces)[:, ::-1].astype(np.int64)  # outward normals

    w_head = _smoothstep((vertices[:, 1] - 0.165) / (0.255 - 0.165))
    skin_indices = np.tile(np.array([0, 1, 0, 0]), (len(vertices), 1))
    skin_weights = np.zeros((len(vertices), 4))
    skin_weights[:, 0], skin_weights[:, 1] = 1.0 - w_head, w_head

    return HeadAsset("head", vertices, faces, skin_indices, skin_weights, _scalp_faces(vertices, faces))


def _scalp_faces(vertices, faces):
    """Hairline: high on the forehead, above the ears on the sides, low at the nape."""
    centre = vertices[faces].mean(1)
    theta = np.arctan2(centre[:, 2] - 0.01, centre[:, 0])
    front = 0.5 * (1.0 + np.sin(theta))  # 1 at the face, 0 at the back
    hairline = 0.300 + 0.108 * front ** 2
    near_ear = (np.abs(np.cos(theta)) > 0.93) & (centre[:, 1] < 0.372)
    return (centre[:, 1] > hairline) & ~near_ear


def mesh_head(path, vertices, faces, scalp_faces=None):
    """A user head from any mesh: rigid (all weight on the head bone), pivot at its base centre.

    Without a scalp mask, hair grows from the top 35% of the mesh's height.
    """
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    lo, hi = vertices.min(0), vertices.max(0)
    if scalp_faces is None:
        top = vertices[faces].mean(1)[:, 1]
        scalp_faces = top > lo[1] + 0.65 * (hi[1] - lo[1])
    skin_indices = np.tile(np.array([1, 0, 0, 0]), (len(vertices), 1))
    skin_weights = np.zeros((len(vertices), 4))
    skin_weights[:, 0] = 1.0
    pivot = (float(0.5 * (lo[0] + hi[0])), float(lo[1]), float(0.5 * (lo[2] + hi[2])))
    return HeadAsset(str(path), vertices, faces, skin_indices, skin_weights, np.asarray(scalp_faces, bool), pivot)


@dataclass(frozen=True)
class HeadAnimation:
    """Turn (yaw about Y) and nod (pitch about X) of the head bone about the neck pivot.

    Angles in degrees, periods in seconds; motion eases in over `ease_in` seconds from rest.
    """

    turn_degrees: float = 40.0
    turn_period: float = 3.0
    nod_degrees: float = 15.0
    nod_period: float = 1.5
    ease_in: float = 0.5
    pivot: tuple = field(default=NECK_PIVOT)

    @staticmethod
    def preset(name, pivot=NECK_PIVOT):
        presets = {
            "none": dict(turn_degrees=0.0, nod_degrees=0.0),
            "turn": dict(nod_degrees=0.0),
            "nod": dict(turn_degrees=0.0),
            "turn_nod": {},
        }
        if name not in presets:
            raise KeyError(name)
        return HeadAnimation(pivot=tuple(pivot), **presets[name])

    def angles(self, t):
        """(yaw, pitch) in radians at times t (array)."""
        t = np.asarray(t, np.float64)
        ease = _smoothstep(t / self.ease_in) if self.ease_in > 0 else np.ones_like(t)
        yaw = np.radians(self.turn_degrees) * np.sin(2 * np.pi * t / self.turn_period) * ease
        pitch = np.radians(self.nod_degrees) * np.sin(2 * np.pi * t / self.nod_period) * ease
        return yaw, pitch

    def bone_matrices(self, t):
        """(T, 2, 4, 4) column-vector transforms: bone 0 identity, bone 1 the head."""
        yaw, pitch = self.angles(np.atleast_1d(t))
        n = len(yaw)
        cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
        R = np.zeros((n, 3, 3))
        # R = Ry(yaw) @ Rx(pitch): nod in the head's own frame, then turn
        R[:, 0, 0], R[:, 0, 1], R[:, 0, 2] = cy, sy * sp, sy * cp
        R[:, 1, 1], R[:, 1, 2] = cp, -sp
        R[:, 2, 0], R[:, 2, 1], R[:, 2, 2] = -sy, cy * sp, cy * cp
        pivot = np.asarray(self.pivot, np.float64)
        M = np.tile(np.eye(4), (n, 2, 1, 1))
        M[:, 1, :3, :3] = R
        M[:, 1, :3, 3] = pivot - R @ pivot
        return M
