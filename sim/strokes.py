"""Screen strokes: what a line drawn over a camera's image means in the 3D scene.

The grooming tools (cuts, erase, wax here; the comb and an interactive studio elsewhere) take their
input as a stroke, a polyline of pixel coordinates (u, v), seen through an `io_usd.preview.Camera`
(pixel (0, 0) at the top-left corner, v down, the camera looking down its local -Z). This module
turns strokes into world-space things: rays through the pixels, the region a brush of some pixel
radius covers, and drags within the plane parallel to the image. NumPy in, NumPy out.
"""

import numpy as np


def as_stroke(stroke):
    """A stroke as a (K, 2) float64 array of finite pixel coordinates; ValueError otherwise."""
    s = np.asarray(stroke, np.float64)
    if s.ndim != 2 or s.shape[1] != 2 or len(s) == 0:
        raise ValueError(f"a stroke is a list of [u, v] pixel points, got shape {s.shape}")
    if not np.all(np.isfinite(s)):
        raise ValueError("a stroke's pixel points must be finite")
    return s


def pixel_rays(camera, pixels):
    """Rays from the camera's eye through pixels (N, 2): (origins (N, 3), unit directions (N, 3))."""
    uv = np.asarray(pixels, np.float64).reshape(-1, 2)
    f = camera.focal
    local = np.stack([(uv[:, 0] - 0.5 * camera.width) / f, -(uv[:, 1] - 0.5 * camera.height) / f,
                      -np.ones(len(uv))], 1)
    pose = np.asarray(camera.pose, np.float64)
    d = local @ pose[:3, :3].T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.repeat(pose[None, :3, 3], len(uv), 0), d


def resample_stroke(stroke, spacing):
    """The stroke's polyline sampled every `spacing` pixels along its length, both ends included
    (the comb of Hayashimoto et al. §3.3 casts one ray per sample)."""
    s = as_stroke(stroke)
    if len(s) == 1:
        return s.copy()
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(s, axis=0), axis=1))])
    n = max(2, int(np.ceil(arc[-1] / max(float(spacing), 1e-9))) + 1)
    want = np.linspace(0.0, arc[-1], n)
    return np.stack([np.interp(want, arc, s[:, 0]), np.interp(want, arc, s[:, 1])], 1)


def stroke_rays(camera, stroke, spacing=None):
    """Rays through a stroke's points (or through samples every `spacing` pixels along it)."""
    points = as_stroke(stroke) if spacing is None else resample_stroke(stroke, spacing)
    return pixel_rays(camera, points)


def stroke_distance(points, camera, stroke):
    """Pixel distance (N,) from each world point's projection to the stroke's polyline; +inf for
    points behind the camera. A one-point stroke is a dab: the distance to that pixel."""
    s = as_stroke(stroke)
    uv = camera.project(np.asarray(points, np.float64).reshape(-1, 3))
    best = np.full(len(uv), np.inf)
    ok = np.all(np.isfinite(uv), axis=1)
    q = uv[ok]
    if len(s) == 1:
        best[ok] = np.linalg.norm(q - s[0], axis=1)
        return best
    a, b = s[:-1], s[1:]
    ab = b - a
    t = np.einsum("nkj,kj->nk", q[:, None, :] - a[None], ab) / np.maximum(np.einsum("kj,kj->k", ab, ab), 1e-18)
    closest = a[None] + np.clip(t, 0.0, 1.0)[..., None] * ab[None]
    best[ok] = np.linalg.norm(q[:, None, :] - closest, axis=2).min(axis=1)
    return best


def stroke_covers(points, camera, stroke, radius):
    """Which world points (N, 3) a brush of `radius` pixels dragged along the stroke covers, seen
    through `camera`. Depth is not tested: a point hidden behind the head is covered too."""
    return stroke_distance(points, camera, stroke) <= float(radius)


def screen_drag(camera, points, drag):
    """World displacements (N, 3) that move each point by `drag` = (du, dv) pixels on screen while
    keeping it in the plane through it parallel to the image (its depth is unchanged)."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    depth = camera.depth(p)
    pose = np.asarray(camera.pose, np.float64)
    du, dv = (float(c) for c in drag)
    scale = np.where(depth > 0.0, depth, np.nan) / camera.focal
    return scale[:, None] * (du * pose[None, :3, 0] - dv * pose[None, :3, 1])
