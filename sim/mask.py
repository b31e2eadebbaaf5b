"""Projecting an animated face onto a moving mask (Yotsukura et al., HYPERMASK, §2).

A performer wears a plain, roughly planar mask. A tracking camera with an infrared filter sees five
LEDs on it: one at each corner, and a fifth just inside the top-left corner that tells the corners
apart at any in-plane rotation. A projector beside the camera throws a rendered face onto the mask.
Per captured frame:

1. find the LEDs in the infrared image and label them (`detect_leds`, `label_leds`);
2. predict where the four corners will be when the frame reaches the projector, `latency` seconds
   after capture (`LatencyPredictor`, a Kalman filter on the corners' image coordinates, §2.2);
3. warp the face image onto the predicted corners and through the camera-to-projector homography
   found at calibration (`projector_frame`, §2.1).

Conventions. World units are metres with Y up (as in the rest of the project); the mask's own frame
has x to the right and y up as the audience sees it, and it faces +z. Image coordinates follow
`io_usd.preview.Camera`: (0, 0) is the top-left corner of the image, u right, v down, and the centre
of pixel (row r, column c) is (c + 0.5, r + 0.5). Corners are always ordered top-left, top-right,
bottom-right, bottom-left, then the labelling LED.

The mask is modelled as a plane, so the map from the face image through the mask to either image is a
homography and the whole chain is exact for the mask itself. The calibration homography from the
camera to the projector is exact only for points on the plane it was measured on (or for a projector
that shares the camera's centre of projection); the error this leaves elsewhere is reported apart.

Recorded tracks are JSON or CSV files of per-frame LED image coordinates; see `read_track`.
"""

import csv
import json
import math
import os
import sys
from dataclasses import dataclass, field

import numpy as np

from io_usd.output_file import check_output_path, is_input, write_whole

from .errors import InputError

NUM_LEDS = 5  # four corners and the labelling LED
FACE_SIZE = (240, 330)  # face image width, height in pixels: the default mask's aspect ratio

# ==================================================================================================
# Calibration: the camera-to-projector homography from four point pairs
# ==================================================================================================


def _points2(pts, name, count=None):
    pts = np.asarray(pts, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2 or (count is not None and len(pts) != count):
        want = f"({count}, 2)" if count else "(N, 2)"
        raise ValueError(f"{name}: expected {want} points, got shape {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError(f"{name}: points must be finite")
    return pts


def _normalizing_transform(pts):
    """Similarity moving the points' centroid to the origin at mean distance sqrt(2) (Hartley), which
    keeps the 8x8 system well conditioned when the coordinates are hundreds of pixels."""
    centre = pts.mean(0)
    spread = np.mean(np.linalg.norm(pts - centre, axis=1))
    if spread == 0.0:
        raise ValueError("homography: the points all coincide")
    s = math.sqrt(2.0) / spread
    return np.array([[s, 0.0, -s * centre[0]], [0.0, s, -s * centre[1]], [0.0, 0.0, 1.0]])


def homography_8x8(camera_pts, projector_pts):
    """The 3x3 homography H (h9 = 1) taking four camera points exactly onto four projector points.

    Fixing h9 = 1 leaves eight unknowns; clearing the denominator of x' = (h1 x + h2 y + h3) /
    (h7 x + h8 y + 1) and of its y' twin gives two linear rows per point pair (Yotsukura et al., §2.1
    eqs. 5-9):
        x' = h1 x + h2 y + h3 - h7 x x' - h8 y x'
        y' = h4 x + h5 y + h6 - h7 x y' - h8 y y'
    The rows are built on Hartley-normalised coordinates and the result mapped back, so the solve
    stays accurate for pixel coordinates. Raises ValueError when three of the points are collinear.
    """
    src = _points2(camera_pts, "camera_pts", 4)
    dst = _points2(projector_pts, "projector_pts", 4)
    t_src, t_dst = _normalizing_transform(src), _normalizing_transform(dst)
    x, y = (apply_homography(t_src, src)).T
    xp, yp = (apply_homography(t_dst, dst)).T
    zero, one = np.zeros(4), np.ones(4)
    rows_x = np.stack([x, y, one, zero, zero, zero, -x * xp, -y * xp], 1)
    rows_y = np.stack([zero, zero, zero, x, y, one, -x * yp, -y * yp], 1)
    S = np.empty((8, 8))
    S[0::2], S[1::2] = rows_x, rows_y
    Z = np.empty(8)
    Z[0::2], Z[1::2] = xp, yp
    for name, (u, v) in (("camera_pts", (x, y)), ("projector_pts", (xp, yp))):
        # twice the area of each triangle of three of the points (normalised: O(1) when well spread)
        triangles = [(u[j] - u[i]) * (v[k] - v[i]) - (u[k] - u[i]) * (v[j] - v[i]) for i, j, k in
                     ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3))]
        if min(abs(t) for t in triangles) < 1e-9:
            raise ValueError(f"homography_8x8: three of the four {name} are collinear")
    h = np.linalg.solve(S, Z)  # S H' = Z, eq. 9
    H = np.linalg.solve(t_dst, np.append(h, 1.0).reshape(3, 3) @ t_src)
    return H / H[2, 2]


def homography_affine_lsq(camera_pts, projector_pts):
    """H = P C^T (C C^T)^-1 (Yotsukura et al., §2.1 eq. 12): the least-squares fit of P = H C on
    homogeneous columns c_i = (x, y, 1), p_i = (x', y', 1) of N >= 3 point pairs.

    Because every w is 1 the fitted bottom row is exactly (0, 0, 1): this is an affine map. It is
    exact only when the true camera-to-projector map is affine (the paper's assumption that camera
    and projector are far from the mask); for a projective map it leaves a residual, which
    `transfer_error` reports.
    """
    C = np.vstack([_points2(camera_pts, "camera_pts").T, np.ones(len(camera_pts))])
    P = np.vstack([_points2(projector_pts, "projector_pts").T, np.ones(len(projector_pts))])
    if C.shape != P.shape:
        raise ValueError(f"homography_affine_lsq: {C.shape[1]} camera points but {P.shape[1]} projector points")
    CCt = C @ C.T
    if np.linalg.cond(CCt) > 1e14:
        raise ValueError("homography_affine_lsq: degenerate point set (all points collinear)")
    return np.linalg.solve(CCt, C @ P.T).T  # P C^T (C C^T)^-1 without forming the inverse


def apply_homography(H, pts):
    """Map points (..., 2) by the 3x3 homography H; points sent to infinity come back non-finite."""
    pts = np.asarray(pts, np.float64)
    H = np.asarray(H, np.float64)
    out = pts @ H[:2, :2].T + H[:2, 2]
    w = pts @ H[2, :2] + H[2, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        return out / w[..., None]


def transfer_error(H, src, dst):
    """Per-point distance (N,) between H applied to src and dst, in dst's units."""
    return np.linalg.norm(apply_homography(H, src) - np.asarray(dst, np.float64), axis=-1)


# ==================================================================================================
# The mask, its motion, and the camera and projector that see it
# ==================================================================================================


@dataclass(frozen=True)
class MaskGeometry:
    """A face-sized planar mask. The LEDs sit at its corners; the labelling LED sits inside the
    top-left corner, so it is never on the convex hull of the five and is nearest that corner."""

    width_m: float = 0.16
    height_m: float = 0.22
    label_inset: tuple = (0.22, 0.16)  # labelling LED: fractions of width, height in from top-left

    def plane_points(self):
        """(5, 2) LED positions in the mask plane, metres: the corners, then the labelling LED."""
        w, h = 0.5 * self.width_m, 0.5 * self.height_m
        label = (-w + self.label_inset[0] * self.width_m, h - self.label_inset[1] * self.height_m)
        return np.array([[-w, h], [w, h], [w, -h], [-w, -h], label])

    def leds(self):
        """(5, 3) LED positions in the mask's frame (the mask plane is z = 0, facing +z)."""
        return np.hstack([self.plane_points(), np.zeros((NUM_LEDS, 1))])


@dataclass(frozen=True)
class MotionParams:
    """A performer on stage: a walk across it, a bob with each step, and head turns, nods and
    sways. Each angle and the depth are sums of two sinusoids with seeded frequencies and phases."""

    stage_centre: tuple = (0.0, 1.6, 0.0)  # m, the mask's mean position
    walk_m: float = 0.35  # m, amplitude of the walk across the stage (x)
    walk_period_s: float = 6.0
    depth_m: float = 0.2  # m, amplitude towards and away from the camera (z)
    bob_m: float = 0.012  # m, vertical bob at the step rate
    step_hz: float = 1.8
    turn_deg: float = 25.0  # yaw amplitude (the paper's tracker holds |yaw| <= 30)
    nod_deg: float = 12.0  # pitch amplitude (|pitch| <= 20 in the paper)
    sway_deg: float = 20.0  # roll amplitude (any roll is trackable)
    pivot_m: float = 0.1  # m, the mask sits this far in front of the neck it turns about


def _rotation(yaw, pitch, roll):
    """(N, 3, 3) R = Ry(yaw) Rx(pitch) Rz(roll), angles in radians."""
    cy, sy, cp, sp, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    one, zero = np.ones_like(yaw), np.zeros_like(yaw)
    ry = np.stack([np.stack([cy, zero, sy], -1), np.stack([zero, one, zero], -1), np.stack([-sy, zero, cy], -1)], -2)
    rx = np.stack([np.stack([one, zero, zero], -1), np.stack([zero, cp, -sp], -1), np.stack([zero, sp, cp], -1)], -2)
    rz = np.stack([np.stack([cr, -sr, zero], -1), np.stack([sr, cr, zero], -1), np.stack([zero, zero, one], -1)], -2)
    return ry @ rx @ rz


class MaskMotion:
    """A smooth, seeded rigid motion of the mask: `poses(times)` gives mask-to-world 4x4 matrices
    at any times, so the truth at display time is known exactly."""

    def __init__(self, seed=0, params=MotionParams()):
        self.params = params
        rng = np.random.default_rng(seed)
        # per channel (depth, yaw, pitch, roll): a slow and a quicker sinusoid
        self._freq = np.stack([rng.uniform(0.12, 0.3, 4), rng.uniform(0.45, 0.9, 4)], 1)  # Hz
        self._phase = rng.uniform(0.0, 2.0 * np.pi, (4, 2))
        self._walk_phase, self._bob_phase = rng.uniform(0.0, 2.0 * np.pi, 2)

    def _channels(self, t):
        waves = np.sin(2.0 * np.pi * self._freq[None] * t[:, None, None] + self._phase[None])
        return 0.7 * waves[..., 0] + 0.3 * waves[..., 1]  # (N, 4), each within [-1, 1]

    def poses(self, times):
        p = self.params
        t = np.atleast_1d(np.asarray(times, np.float64))
        c = self._channels(t)
        yaw, pitch, roll = (np.radians(a) * c[:, k] for k, a in ((1, p.turn_deg), (2, p.nod_deg), (3, p.sway_deg)))
        neck = np.stack([
            p.walk_m * np.sin(2.0 * np.pi * t / p.walk_period_s + self._walk_phase),
            p.bob_m * np.abs(np.sin(np.pi * p.step_hz * t + self._bob_phase)),
            p.depth_m * c[:, 0]], 1) + np.asarray(p.stage_centre) - (0.0, 0.0, p.pivot_m)
        out = np.tile(np.eye(4), (len(t), 1, 1))
        out[:, :3, :3] = _rotation(yaw, pitch, roll)
        out[:, :3, 3] = neck + out[:, :3, 2] * p.pivot_m
        return out


@dataclass
class MaskRig:
    """The tracking camera and the projector (both `io_usd.preview.Camera` pinholes), the mask,
    and the calibration homography from camera pixels to projector pixels."""

    camera: object
    projector: object
    geometry: MaskGeometry = field(default_factory=MaskGeometry)
    calibration: np.ndarray = None

    @classmethod
    def default(cls, width=640, height=480, baseline_m=0.06, geometry=MaskGeometry(), calibration_pose=None):
        """A cart 2.2 m in front of the stage centre: the camera, and the projector `baseline_m` to
        its right (and half that higher), turned to the same point, with a slightly wider throw.
        Calibrated on the mask held at `calibration_pose` (default: the stage centre, facing the
        cart), as the paper calibrates on the mask itself."""
        from io_usd.preview import Camera

        target = np.array(MotionParams().stage_centre)
        eye = target + (0.0, -0.1, 2.2)
        camera = Camera.look_at(eye, target, yfov=0.4, width=width, height=height)
        projector = Camera.look_at(eye + (baseline_m, 0.5 * baseline_m, 0.0), target, yfov=0.44, width=width,
                                   height=height)
        rig = cls(camera, projector, geometry)
        if calibration_pose is None:
            calibration_pose = np.eye(4)
            calibration_pose[:3, 3] = target
        rig.calibration = rig.calibrate(calibration_pose)
        return rig

    def led_world(self, poses):
        """(N, 5, 3) world LED positions for mask-to-world poses (N, 4, 4)."""
        poses = np.asarray(poses, np.float64).reshape(-1, 4, 4)
        return self.geometry.leds() @ np.swapaxes(poses[:, :3, :3], 1, 2) + poses[:, None, :3, 3]

    def camera_points(self, poses):
        """(N, 5, 2) LED positions in the tracking camera image."""
        world = self.led_world(poses)
        return self.camera.project(world.reshape(-1, 3)).reshape(world.shape[:2] + (2,))

    def projector_points(self, poses):
        """(N, 5, 2) LED positions in the projector image: where the projector must put them."""
        world = self.led_world(poses)
        return self.projector.project(world.reshape(-1, 3)).reshape(world.shape[:2] + (2,))

    def calibrate(self, pose):
        """The camera-to-projector homography from the four corner LEDs of a mask held at `pose`:
        the four point pairs the paper's operator lines up by hand (§2.1)."""
        return homography_8x8(self.camera_points(pose)[0, :4], self.projector_points(pose)[0, :4])


# ==================================================================================================
# Infrared images: synthesis and LED detection
# ==================================================================================================


def led_image(points, width, height, sigma_px=1.6, noise=0.0, seed=None):
    """(height, width) float32 infrared image: dark, with a Gaussian blob of peak 1 at each point
    (N, 2) (non-finite points are skipped) and optional Gaussian sensor noise, clipped to [0, 1]."""
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    u = np.arange(width) + 0.5
    v = np.arange(height) + 0.5
    gx = np.exp(-0.5 * ((u[None, :] - pts[:, :1]) / sigma_px) ** 2)  # (N, W)
    gy = np.exp(-0.5 * ((v[None, :] - pts[:, 1:]) / sigma_px) ** 2)  # (N, H)
    image = np.einsum("nh,nw->hw", gy, gx).astype(np.float32)  # separable blobs (einsum: BLAS is slow at n = 5)
    if noise > 0.0:
        image += np.float32(noise) * np.random.default_rng(seed).standard_normal(image.shape, np.float32)
    return np.clip(image, 0.0, 1.0, out=image)


def detect_leds(image, threshold=0.35, min_area=2, max_area=400):
    """LED centres (K, 2) in image coordinates, brightest first.

    Pixels above `threshold` are grouped into 8-connected blobs; blobs outside [min_area, max_area]
    pixels (hot pixels, reflections) are dropped; a blob's centre is its centre of mass weighted by
    the intensity above the threshold.
    """
    from scipy import ndimage

    image = np.asarray(image, np.float64)
    if image.ndim == 3:
        image = image.mean(2)
    bright = image > threshold
    labels, count = ndimage.label(bright, structure=np.ones((3, 3)))
    # blob moments from the bright pixels alone: a few hundred, not the whole frame
    rows, cols = np.nonzero(bright)
    blob = labels[rows, cols]
    weight = image[rows, cols] - threshold
    area = np.bincount(blob, minlength=count + 1)[1:]
    flux = np.bincount(blob, weight, minlength=count + 1)[1:]
    with np.errstate(invalid="ignore", divide="ignore"):
        centres = np.stack([np.bincount(blob, weight * cols, minlength=count + 1)[1:] / flux,
                            np.bincount(blob, weight * rows, minlength=count + 1)[1:] / flux], 1)
    keep = (area >= min_area) & (area <= max_area) & (flux > 0.0)
    order = np.argsort(-flux[keep], kind="stable")
    return centres[keep][order] + 0.5


def label_leds(centres):
    """Order five detected LEDs as top-left, top-right, bottom-right, bottom-left, label.

    The labelling LED is the one inside the convex hull of the others; the corner nearest it is the
    top-left; the rest follow clockwise on screen (increasing angle with v pointing down), which holds
    at any in-plane rotation while the mask faces the camera. Returns (5, 2), all NaN unless exactly
    five LEDs in that arrangement were found (a dropped frame).
    """
    from scipy.spatial import ConvexHull, QhullError

    dropped = np.full((NUM_LEDS, 2), np.nan)
    pts = np.asarray(centres, np.float64).reshape(-1, 2)
    if len(pts) != NUM_LEDS or not np.all(np.isfinite(pts)):
        return dropped
    try:
        hull = ConvexHull(pts).vertices
    except QhullError:
        return dropped
    if len(hull) != 4:
        return dropped
    label = pts[np.setdiff1d(np.arange(NUM_LEDS), hull)[0]]
    corners = pts[hull]
    centre = corners.mean(0)
    angle = np.arctan2(corners[:, 1] - centre[1], corners[:, 0] - centre[0])
    corners = corners[np.argsort(angle)]
    first = int(np.argmin(np.linalg.norm(corners - label, axis=1)))
    return np.vstack([np.roll(corners, -first, axis=0), label])


def mask_homography(corners, geometry=MaskGeometry()):
    """The mask's pose in an image: the homography from mask-plane coordinates (metres, x right,
    y up) to the four labelled corner points (4, 2) in that image."""
    return homography_8x8(geometry.plane_points()[:4], corners)


# ==================================================================================================
# Tracks: synthetic, and recorded files
# ==================================================================================================


@dataclass
class LedTrack:
    """Per-frame labelled LED image points of one performance.

    times (N,) capture times in seconds; leds (N, 5, 2) camera pixels ordered as `label_leds`
    returns them, NaN for a frame where the LEDs were not all found; camera_size (width, height);
    calibration the 3x3 camera-to-projector homography; fps the nominal capture rate."""

    times: np.ndarray
    leds: np.ndarray
    camera_size: tuple
    calibration: np.ndarray
    fps: float  # nominal capture rate, Hz
    source: str = "synthetic"

    def __len__(self):
        return len(self.times)


def synthetic_track(rig, motion, frames, fps=30.0, noise=0.02, seed=0):
    """Capture `frames` frames of `motion` at `fps`: render each infrared image (sensor noise
    `noise`, seeded per frame), detect and label its LEDs. Returns an LedTrack."""
    times = np.arange(int(frames)) / float(fps)
    truth = rig.camera_points(motion.poses(times))
    leds = np.stack([label_leds(detect_leds(camera_frame(rig, truth[k], noise, (seed, k))))
                     for k in range(len(times))])
    return LedTrack(times, leds, (rig.camera.width, rig.camera.height), rig.calibration, float(fps))


def camera_frame(rig, led_points, noise=0.02, seed=None):
    """The tracking camera's infrared image of LEDs at image points (5, 2)."""
    return led_image(led_points, rig.camera.width, rig.camera.height, noise=noise, seed=seed)


def write_track(path, track):
    """Write a track as JSON in the format `read_track` reads (dropped frames as empty lists)."""
    frames = [{"time": round(float(t), 6),
               "leds": [] if not np.all(np.isfinite(p)) else np.round(p, 4).tolist()}
              for t, p in zip(track.times, track.leds)]
    doc = {"camera_size": [int(track.camera_size[0]), int(track.camera_size[1])], "fps": float(track.fps),
           "frames": frames}
    if track.calibration is not None:
        w, h = track.camera_size
        corners = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]], np.float64)
        doc["calibration"] = {"camera": corners.tolist(),
                              "projector": np.round(apply_homography(track.calibration, corners), 6).tolist()}
    with open(path, "w") as f:
        json.dump(doc, f, indent=1)


def _number_pairs(value, path, key, count=None):
    """A list of [u, v] number pairs as an (N, 2) array, or InputError naming path and key."""
    if not isinstance(value, list) or not all(
            isinstance(p, (list, tuple)) and len(p) == 2
            and all(isinstance(c, (int, float)) and not isinstance(c, bool) for c in p) for p in value):
        raise InputError(path, key, "expected a list of [u, v] number pairs")
    pts = np.array(value, np.float64).reshape(-1, 2)
    if count is not None and len(pts) != count:
        raise InputError(path, key, f"expected {count} points, got {len(pts)}")
    if not np.all(np.isfinite(pts)):
        raise InputError(path, key, "coordinates must be finite")
    return pts


def _check_times(times, path):
    if len(times) == 0:
        raise InputError(path, "frames", "the track has no frames")
    if not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0.0):
        raise InputError(path, "time", "frame times must be finite and strictly increasing")
    return times


def read_track(path, rig=None):
    """Read a recorded LED track.

    JSON (.json):
        {"camera_size": [640, 480],             # tracking camera image, pixels
         "fps": 30,                             # used for frames without a "time"
         "calibration": {"camera": [[u, v] x 4], "projector": [[x, y] x 4]},   # optional
         "frames": [{"time": 0.0, "leds": [[u, v], ...]}, ...]}
    CSV (.csv): a header row `time,u1,v1,u2,v2,u3,v3,u4,v4,u5,v5` and one row per frame; empty
    cells mark a frame without a full detection.

    LED points are camera pixels (origin at the image's top-left corner, v down) in any order: they
    are labelled on reading. A frame with other than five points counts as dropped. Whatever the file
    leaves out (camera size, calibration; everything but the frames for CSV) comes from `rig`
    (default: `MaskRig.default()`). Raises InputError naming the file and key.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise InputError(path, None, "no such track file")
    ext = os.path.splitext(path)[1].lower()
    if ext == ".json":
        times, raw, size, calibration, fps = _read_json_track(path)
    elif ext == ".csv":
        times, raw = _read_csv_track(path)
        size, calibration, fps = None, None, None
    else:
        raise InputError(path, None, f"unknown track type {ext or '(none)'!r}; use .json or .csv")
    if rig is None:
        rig = MaskRig.default(*(size or (640, 480)))
    leds = np.stack([label_leds(p) for p in raw])
    if not np.any(np.isfinite(leds[:, 0, 0])):
        raise InputError(path, "frames", "no frame has five LEDs in a mask arrangement (four corners and one inside)")
    size = size or (rig.camera.width, rig.camera.height)
    if fps is None:
        fps = 1.0 / float(np.median(np.diff(times))) if len(times) > 1 else 30.0
    return LedTrack(times, leds, tuple(size), rig.calibration if calibration is None else calibration, float(fps), path)


def _read_json_track(path):
    try:
        with open(path) as f:
            doc = json.load(f)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise InputError(path, None, f"not a readable JSON file ({err})") from None
    if not isinstance(doc, dict):
        raise InputError(path, None, "expected a JSON object with a 'frames' list")
    known = {"format", "camera_size", "fps", "calibration", "frames"}
    unknown = sorted(set(doc) - known)
    if unknown:
        raise InputError(path, unknown[0], f"unknown key (expected one of {', '.join(sorted(known))})")
    frames = doc.get("frames")
    if not isinstance(frames, list) or not frames:
        raise InputError(path, "frames", "expected a non-empty list of {time, leds} objects")
    size = doc.get("camera_size")
    if size is not None:
        if (not isinstance(size, list) or len(size) != 2
                or not all(isinstance(s, int) and not isinstance(s, bool) and s > 0 for s in size)):
            raise InputError(path, "camera_size", "expected [width, height], positive integers")
        size = tuple(size)
    fps = doc.get("fps")
    if fps is not None and (isinstance(fps, bool) or not isinstance(fps, (int, float)) or not fps > 0):
        raise InputError(path, "fps", "expected a positive number")
    calibration = None
    if "calibration" in doc:
        cal = doc["calibration"]
        if not isinstance(cal, dict) or set(cal) != {"camera", "projector"}:
            raise InputError(path, "calibration", "expected {\"camera\": 4 points, \"projector\": 4 points}")
        cam = _number_pairs(cal["camera"], path, "calibration.camera", 4)
        proj = _number_pairs(cal["projector"], path, "calibration.projector", 4)
        try:
            calibration = homography_8x8(cam, proj)
        except ValueError as err:
            raise InputError(path, "calibration", str(err)) from None
    times, raw = [], []
    for k, frame in enumerate(frames):
        key = f"frames[{k}]"
        if not isinstance(frame, dict) or "leds" not in frame:
            raise InputError(path, key, "expected an object with 'leds' (and 'time')")
        extra = sorted(set(frame) - {"time", "leds"})
        if extra:
            raise InputError(path, f"{key}.{extra[0]}", "unknown key (expected time, leds)")
        if "time" in frame:
            t = frame["time"]
            if isinstance(t, bool) or not isinstance(t, (int, float)):
                raise InputError(path, f"{key}.time", "expected a number of seconds")
        elif fps is not None:
            t = k / fps
        else:
            raise InputError(path, f"{key}.time", "missing (give every frame a time, or the track an fps)")
        times.append(float(t))
        raw.append(_number_pairs(frame["leds"] if frame["leds"] is not None else [], path, f"{key}.leds"))
    return _check_times(np.array(times), path), raw, size, calibration, fps


def _read_csv_track(path):
    header = ["time"] + [f"{c}{i}" for i in range(1, NUM_LEDS + 1) for c in "uv"]
    try:
        with open(path, newline="") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(path, None, f"not a readable CSV file ({err})") from None
    if not rows or [c.strip() for c in rows[0]] != header:
        raise InputError(path, "header", f"expected the header row {','.join(header)}")
    times, raw = [], []
    for line, row in enumerate(rows[1:], start=2):
        if not any(c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise InputError(path, f"line {line}", f"expected {len(header)} columns, got {len(row)}")
        cells = [c.strip() for c in row]
        try:
            values = [float(c) if c else math.nan for c in cells]
        except ValueError:
            bad = next(i for i, c in enumerate(cells) if c and not _is_float(c))
            raise InputError(path, f"line {line}.{header[bad]}", f"not a number: {cells[bad]!r}") from None
        if math.isnan(values[0]):
            raise InputError(path, f"line {line}.time", "missing")
        pts = np.array(values[1:]).reshape(-1, 2)
        raw.append(pts if np.all(np.isfinite(pts)) else np.zeros((0, 2)))
        times.append(values[0])
    return _check_times(np.array(times), path), raw


def _is_float(text):
    try:
        float(text)
    except ValueError:
        return False
    return True


# ==================================================================================================
# Latency: predict where the mask will be when the frame is shown (§2.2)
# ==================================================================================================


class LatencyPredictor:
    """A Kalman filter on the eight corner coordinates in the camera image, predicting them
    `latency` seconds after the last capture (Yotsukura et al., §2.2: the capture-to-projection
    delay dt is measured once and the filter predicts that far ahead).

    Why image coordinates rather than a 3D pose: they are what is measured, the projector needs
    nothing else (they go through the calibration homography), and over a tenth of a second the
    perspective motion of each corner is smooth enough for a kinematic model. Each coordinate is an
    independent constant-velocity (model="velocity", white-noise acceleration of `process_noise`
    px/s^2 standard deviation) or constant-acceleration (model="acceleration", white-noise jerk
    in px/s^3) process, observed with `measurement_noise` px standard deviation.
    """

    def __init__(self, latency, model="velocity", process_noise=None, measurement_noise=0.3):
        from filterpy.common import Q_discrete_white_noise
        from filterpy.kalman import KalmanFilter

        if model not in ("velocity", "acceleration"):
            raise ValueError(f"LatencyPredictor: model must be 'velocity' or 'acceleration', got {model!r}")
        self.latency = float(latency)
        self.order = 2 if model == "velocity" else 3  # state per coordinate: position, velocity (, acceleration)
        if process_noise is None:
            process_noise = 1000.0  # tuned on MaskMotion seen by MaskRig.default(); scales with focal length
        self.process_var = float(process_noise) ** 2
        self.kf = KalmanFilter(dim_x=8 * self.order, dim_z=8)
        self.kf.H = np.kron(np.eye(8), np.eye(1, self.order))
        self.kf.R = np.eye(8) * float(measurement_noise) ** 2
        self._process_noise = Q_discrete_white_noise  # (order, dt, variance, block_size) -> Q
        self.last_time = None

    def _transition(self, dt):
        step = np.array([[1.0, dt, 0.5 * dt * dt], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])[:self.order, :self.order]
        return np.kron(np.eye(8), step)

    def update(self, time, corners):
        """Feed the corners (4, 2) captured at `time` (NaN: not detected; the filter coasts) and
        return the corners predicted for time + latency, (4, 2); NaN until the first detection."""
        z = np.asarray(corners, np.float64).reshape(8)
        seen = bool(np.all(np.isfinite(z)))
        if self.last_time is None:
            if not seen:
                return np.full((4, 2), np.nan)
            self.kf.x = np.zeros((8 * self.order, 1))
            self.kf.x[::self.order, 0] = z
            spread = np.array([self.kf.R[0, 0], 1e3 ** 2, 1e4 ** 2])[:self.order]
            self.kf.P = np.diag(np.tile(spread, 8))  # position known, derivatives not at all
        else:
            dt = float(time) - self.last_time
            if dt <= 0.0:
                raise ValueError(f"LatencyPredictor: time went from {self.last_time} to {time}")
            self.kf.predict(F=self._transition(dt),
                            Q=self._process_noise(self.order, dt, self.process_var, block_size=8))
            if seen:
                self.kf.update(z)
        self.last_time = float(time)
        ahead = self._transition(self.latency) @ self.kf.x
        return ahead[::self.order, 0].reshape(4, 2)


def predict_track(track, latency, model="velocity", **filter_options):
    """(N, 4, 2) corners each frame predicts for its capture time + latency."""
    predictor = LatencyPredictor(latency, model, **filter_options)
    return np.stack([predictor.update(t, p[:4]) for t, p in zip(track.times, track.leds)])


def projection_error(shown_corners, true_projector_corners, calibration):
    """Per-frame mean distance (N,), in projector pixels, between where the projector put the mask's
    corners (the camera-image corners it used, `shown_corners` (N, 4, 2), through the calibration)
    and where the corners really were when the frame was shown (N, 4, 2). NaN where either is
    unknown."""
    shown = apply_homography(calibration, np.asarray(shown_corners, np.float64))
    return np.linalg.norm(shown - np.asarray(true_projector_corners, np.float64), axis=-1).mean(-1)


def recorded_truth(track, latency):
    """For a recorded track, where the corners were in the projector image at each frame's display
    time: the recorded corners interpolated linearly at capture time + latency, through the
    calibration. NaN past the end of the track or next to a dropped frame."""
    flat = track.leds[:, :4].reshape(len(track), 8)
    shown_at = track.times + float(latency)
    corners = np.stack([np.interp(shown_at, track.times, flat[:, c], right=np.nan) for c in range(8)], 1)
    return apply_homography(track.calibration, corners.reshape(-1, 4, 2))


def error_summary(errors, warmup):
    """(mean, max) of per-frame errors after the first `warmup` frames, ignoring NaN."""
    e = np.asarray(errors, np.float64)[int(warmup):]
    e = e[np.isfinite(e)]
    return (float(e.mean()), float(e.max())) if len(e) else (math.nan, math.nan)


# ==================================================================================================
# Face images and projector frames
# ==================================================================================================

MARKERS = np.array([[230, 40, 40], [40, 200, 60], [50, 90, 240], [240, 210, 40]], np.uint8)  # TL, TR, BR, BL


def drawn_face(width=FACE_SIZE[0], height=FACE_SIZE[1], time=0.0):
    """(height, width, 3) uint8: a drawn frontal face that talks (the mouth opens and closes with
    `time`, seconds) on a dim backdrop, with a coloured square in each corner (red top-left, green
    top-right, blue bottom-right, yellow bottom-left) that shows how the image lands on the mask."""
    v, u = np.mgrid[0:height, 0:width] + 0.5
    x, y = (u - 0.5 * width) / (0.5 * width), (v - 0.5 * height) / (0.5 * height)  # [-1, 1], y down

    def ellipse(cx, cy, rx, ry):
        return ((x - cx) / rx) ** 2 + ((y - cy) / ry) ** 2 <= 1.0

    image = np.empty((height, width, 3))
    image[:] = (0.16, 0.15, 0.2)
    skin = np.array([0.93, 0.74, 0.62])
    head = ellipse(0.0, 0.0, 0.86, 0.9)
    image[head] = skin * (1.0 - 0.25 * np.clip(np.hypot(x, y / 1.05), 0.0, 1.0) ** 3)[head, None]
    for side in (-1.0, 1.0):
        image[ellipse(0.33 * side, -0.2, 0.17, 0.075)] = (0.97, 0.97, 0.95)
        image[ellipse(0.33 * side, -0.2, 0.065, 0.06)] = (0.25, 0.17, 0.1)
        image[ellipse(0.33 * side, -0.37, 0.2, 0.03)] = (0.35, 0.22, 0.14)
    image[ellipse(0.0, 0.12, 0.09, 0.16) & (y > 0.05)] *= 0.88  # nose
    opening = 0.02 + 0.09 * np.sin(2.0 * np.pi * 1.6 * time) ** 2
    image[ellipse(0.0, 0.48, 0.3, opening + 0.035)] = (0.72, 0.3, 0.3)  # lips
    image[ellipse(0.0, 0.48, 0.24, opening)] = (0.22, 0.05, 0.07)  # inside of the mouth
    out = np.round(255 * np.clip(image, 0.0, 1.0)).astype(np.uint8)
    m = max(4, min(width, height) // 10)
    out[:m, :m], out[:m, -m:], out[-m:, -m:], out[-m:, :m] = MARKERS
    return out


def builtin_face_cache(path, fps):
    """The built-in head (no hair, still) speaking the demo line with a smile, simulated to a cache at
    `path`: the face `cfx mask` projects when no cache is given."""
    from .lipsync import DEMO_LINE_PATH, SAMPLE_RATE, load_audio
    from .scene import _build_config, run_scene

    seconds = len(load_audio(DEMO_LINE_PATH)) / SAMPLE_RATE
    data = {"scene": {"frames": int(math.ceil(seconds * fps)) + 2, "fps": float(fps), "preroll": 0.0, "stats": False},
            "head": {"animation": "none"}, "hair": {"enabled": False},
            "face": {"audio": "builtin", "expressions": [{"frame": 1, "emotion": "happiness", "weight": 0.7}]}}
    run_scene(_build_config("<mask>", data, None), path, progress=False)
    return path


class CacheFace:
    """Frontal renders of the head in a USD cache (io_usd.preview), one per display time; the
    cache's timeline loops. Only the face meshes are drawn (role "face", else the "collider"): hair
    and garments are not part of a mask. Each frame is framed on its own, square on from the front
    (+Z) around the top `head_m` of those meshes, so a walking character's face stays centred."""

    def __init__(self, path, width=FACE_SIZE[0], height=FACE_SIZE[1], head_m=0.25):
        from io_usd.cache import CacheReader
        from io_usd.preview import FrameRenderer

        path = os.fspath(path)
        if not os.path.isfile(path):
            raise InputError(path, None, "no such cache file")
        try:
            self.reader = CacheReader(path)
        except Exception as err:  # usd-core raises its own Tf errors for unreadable files
            raise InputError(path, None, f"not a readable USD cache ({err})") from None
        roles = {p.role for p in self.reader.prims.values()}
        wanted = "face" if "face" in roles else "collider"
        self.names = [n for n, p in self.reader.prims.items() if p.role == wanted and p.kind != "curves"]
        if not self.names:
            raise InputError(path, None, "the cache has no face or collider mesh to render")
        self.frames = self.reader.frames()
        self.head_units = head_m / (self.reader.meters_per_unit or 1.0)
        self.width, self.height = int(width), int(height)
        # black around the head: the projector then sends no light past the face
        self._renderer = FrameRenderer(self.reader, self.width, self.height, background=(0.0, 0.0, 0.0),
                                       names=self.names)

    def frame_at(self, time):
        """The cache frame shown at `time` seconds, looping over the cache."""
        fps = self.reader.fps or 24.0
        return self.frames[int(round(time * fps)) % len(self.frames)]

    def __call__(self, time):
        from io_usd.preview import Camera

        frame = self.frame_at(time)
        pts = np.concatenate([self.reader.points(n, frame).reshape(-1, 3) for n in self.names]).astype(np.float64)
        head = pts[pts[:, 1] >= pts[:, 1].max() - self.head_units]
        camera = Camera.frame_points(head, self.width, self.height, yaw_degrees=0.0, pitch_degrees=0.0, margin=1.02)
        return self._renderer.render(frame, camera)

    def close(self):
        self._renderer.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def _as_rgb(image):
    """Any image array, (H, W), (H, W, 3) or (H, W, 4), uint8 or float in [0, 1], as float RGB."""
    image = np.asarray(image)
    scale = 255.0 if image.dtype == np.uint8 else 1.0
    image = image.astype(np.float64) / scale
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] not in (3, 4):
        raise ValueError(f"face image: expected (H, W), (H, W, 3) or (H, W, 4), got shape {image.shape}")
    return image[..., :3]


def _warp(image, to_image, shape):
    """`image` resampled into an output of `shape` through the homography `to_image` that maps the
    input's image coordinates to the output's (pixel centres at +0.5, as everywhere here). Only the
    bounding box of the input's footprint is resampled: a mask covers a small part of a frame."""
    from skimage.transform import ProjectiveTransform, warp

    h, w = image.shape[:2]
    out = np.zeros(tuple(shape) + image.shape[2:])
    rect = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])
    depth = rect @ to_image[2, :2] + to_image[2, 2]
    lo, hi = np.zeros(2, int), np.array([shape[1], shape[0]])
    if np.all(depth > 0) or np.all(depth < 0):  # the footprint is a bounded quad
        quad = apply_homography(to_image, rect)
        lo = np.clip(np.floor(quad.min(0)).astype(int) - 1, 0, hi)
        hi = np.clip(np.ceil(quad.max(0)).astype(int) + 1, lo, hi)
    if np.any(hi <= lo):
        return out
    # output window index -> input index: shift by the window, then undo the +0.5 pixel centres
    to_window = np.array([[1.0, 0.0, 0.5 + lo[0]], [0.0, 1.0, 0.5 + lo[1]], [0.0, 0.0, 1.0]])
    from_input = np.array([[1.0, 0.0, -0.5], [0.0, 1.0, -0.5], [0.0, 0.0, 1.0]])
    index_map = from_input @ np.linalg.inv(to_image) @ to_window
    window = (hi[1] - lo[1], hi[0] - lo[0])
    out[lo[1]:hi[1], lo[0]:hi[0]] = warp(image, ProjectiveTransform(index_map), output_shape=window, order=1,
                                         mode="constant", cval=0.0)
    return out


def face_to_projector(face_shape, corners, calibration, geometry=MaskGeometry()):
    """The homography from face image coordinates to projector pixels when the face image's corners
    are put on the mask corners seen at camera points `corners` (4, 2): face image -> mask plane
    (a scale) -> camera image (`mask_homography`) -> projector (the calibration)."""
    h, w = face_shape[:2]
    to_mask = np.array([[geometry.width_m / w, 0.0, -0.5 * geometry.width_m],
                        [0.0, -geometry.height_m / h, 0.5 * geometry.height_m], [0.0, 0.0, 1.0]])
    return np.asarray(calibration, np.float64) @ mask_homography(corners, geometry) @ to_mask


def projector_frame(face, corners, calibration, size, geometry=MaskGeometry()):
    """(height, width, 3) uint8 projector image that puts `face` (any image array) on the mask whose
    corners the camera sees (or is predicted to see) at `corners` (4, 2). Black elsewhere, and all
    black when the corners are unknown (NaN)."""
    width, height = size
    corners = np.asarray(corners, np.float64)
    if not np.all(np.isfinite(corners)):
        return np.zeros((height, width, 3), np.uint8)
    face = _as_rgb(face)
    out = _warp(face, face_to_projector(face.shape, corners, calibration, geometry), (height, width))
    return np.round(255 * np.clip(out, 0.0, 1.0)).astype(np.uint8)


def on_mask_view(projector_image, camera_corners, projector_corners, camera_size, ambient=0.12):
    """What the tracking camera would see in visible light: the projector's image landing on the
    mask (true corners `camera_corners` in this view, `projector_corners` in the projector), over a
    dim stage. The map from this view to the projector through the planar mask is a homography, so
    this is exact for the mask. (H, W, 3) uint8."""
    from skimage.draw import polygon

    width, height = camera_size
    light = _warp(_as_rgb(projector_image), homography_8x8(projector_corners, camera_corners), (height, width))
    view = np.full((height, width, 3), 0.06)
    corners = np.asarray(camera_corners, np.float64)
    rows, cols = polygon(corners[:, 1] - 0.5, corners[:, 0] - 0.5, (height, width))
    view[rows, cols] = np.clip(ambient + (1.0 - ambient) * light[rows, cols], 0.0, 1.0)
    return np.round(255 * view).astype(np.uint8)


def camera_view(ir_image, measured, predicted):
    """The infrared camera image for people: the LEDs, the measured mask outline (green, with the
    top-left corner ringed) and the outline predicted for display time (magenta). (H, W, 3) uint8."""
    from PIL import Image, ImageDraw

    grey = np.round(255 * np.clip(0.1 + 0.9 * np.asarray(ir_image, np.float64), 0.0, 1.0)).astype(np.uint8)
    image = Image.fromarray(np.repeat(grey[..., None], 3, axis=2))
    draw = ImageDraw.Draw(image)
    for quad, colour in ((measured, (60, 220, 90)), (predicted, (235, 60, 220))):
        quad = np.asarray(quad, np.float64)[:4]
        if np.all(np.isfinite(quad)):
            draw.polygon([tuple(p) for p in quad], outline=colour)
    first = np.asarray(measured, np.float64)[0]
    if np.all(np.isfinite(first)):
        draw.ellipse([first[0] - 5, first[1] - 5, first[0] + 5, first[1] + 5], outline=(60, 220, 90))
    return np.asarray(image)


# ==================================================================================================
# The command: cfx mask [TRACK] -o OUT.mp4
# ==================================================================================================


def add_mask_arguments(parser):
    """The `cfx mask` options on an argparse (sub)parser."""
    parser.add_argument("track", nargs="?", help="recorded LED track (.json or .csv); default: a synthetic, "
                                                 "seeded performance")
    parser.add_argument("-o", "--output", required=True, help="projector frames as .mp4")
    parser.add_argument("--cache", help="USD cache whose face (or head) is rendered onto the mask")
    parser.add_argument("--face", choices=("builtin", "drawn"), default="builtin",
                        help="without --cache: the built-in face speaking its demo line (default), or a flat "
                             "drawn test face with corner markers")
    parser.add_argument("--latency", type=float, default=0.1, help="seconds from capture to projection (default 0.1)")
    parser.add_argument("--frames", type=int, help="frames to render (default: the whole track, or 150 synthetic)")
    parser.add_argument("--fps", type=float, default=30.0, help="capture rate of a synthetic track, Hz (default 30)")
    parser.add_argument("--size", default="640x480", help="camera and projector image WIDTHxHEIGHT (default 640x480)")
    parser.add_argument("--no-predict", action="store_true",
                        help="project at the last measured pose (no Kalman filter)")
    parser.add_argument("--model", choices=("velocity", "acceleration"), default="velocity",
                        help="Kalman motion model (default velocity)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the synthetic performance")
    parser.add_argument("--sheet", help="also write a PNG contact sheet: camera, projector and on-mask views")
    parser.add_argument("--save-track", help="also write the track used, as JSON")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bar")


@dataclass(frozen=True)
class MaskOptions:
    size: tuple
    latency: float  # s
    frames: int  # 0: the whole recorded track
    fps: float  # Hz
    output: str


def _options(args):
    try:
        width, height = (int(s) for s in str(args.size).lower().split("x"))
    except ValueError:
        raise InputError("--size", None, f"expected WIDTHxHEIGHT, got {args.size!r}") from None
    if width < 16 or height < 16 or width % 2 or height % 2:
        raise InputError("--size", None, f"width and height must be even and at least 16 (MP4), got {width}x{height}")
    if not (math.isfinite(args.latency) and 0.0 <= args.latency <= 10.0):  # 1e300 failed far down the line
        raise InputError("--latency", None, f"must be from 0 to 10 seconds, got {args.latency}")
    if args.frames is not None and args.frames < 1:
        raise InputError("--frames", None, f"must be at least 1, got {args.frames}")
    if not (math.isfinite(args.fps) and args.fps > 0.0):
        raise InputError("--fps", None, f"must be positive, got {args.fps}")
    check_output_path(args.output, (".mp4",), "the output")
    if args.sheet:
        check_output_path(args.sheet, (".png",), "the contact sheet")
    if args.save_track:
        check_output_path(args.save_track, (".json",), "the saved track")
        if args.track and is_input(args.save_track, args.track):
            raise InputError(args.save_track, None, "is the track read (--save-track would rewrite it, rounded); "
                                                    "choose another file")
    # the most a run can hold: a billion frames or a 100,000-pixel-wide projector ran out of memory
    if args.frames is not None and args.frames > 100_000:
        raise InputError("--frames", None, f"at most 100,000, got {args.frames}")
    if max(width, height) > 8192:
        raise InputError("--size", None, f"at most 8192 pixels a side, got {width}x{height}")
    if args.fps < 1.0 or args.fps > 1000.0:
        raise InputError("--fps", None, f"must be from 1 to 1000 frames a second, got {args.fps:g}")
    return MaskOptions((width, height), float(args.latency), args.frames or 0, float(args.fps), args.output)


def run_mask(args):
    """`cfx mask`: track the mask (a recorded or a synthetic track), predict across the latency,
    render the projector frames to MP4, and report the projection error with and without
    prediction on stderr. Returns the exit status."""
    from io_usd.preview import write_images
    from tqdm import tqdm

    opts = _options(args)
    width, height = opts.size
    if args.track:
        track = read_track(args.track, MaskRig.default(width, height))
        if opts.frames:
            track = LedTrack(track.times[:opts.frames], track.leds[:opts.frames], track.camera_size,
                             track.calibration, track.fps, track.source)
        truth = recorded_truth(track, opts.latency)
        true_camera = apply_homography(np.linalg.inv(track.calibration), truth)
        calibration_alone = None

        def infrared(k):
            return led_image(track.leds[k], *track.camera_size)
    else:
        rig = MaskRig.default(width, height)
        motion = MaskMotion(args.seed)
        track = synthetic_track(rig, motion, opts.frames or 150, opts.fps, seed=args.seed)
        truth = rig.projector_points(motion.poses(track.times + opts.latency))[:, :4]
        true_camera = rig.camera_points(motion.poses(track.times + opts.latency))[:, :4]
        calibration_alone = projection_error(true_camera, truth, track.calibration)

        def infrared(k):
            return camera_frame(rig, rig.camera_points(motion.poses(track.times[k]))[0], seed=(args.seed, k))
    measured = track.leds[:, :4]
    predicted = predict_track(track, opts.latency, args.model)
    shown = measured if args.no_predict else predicted
    warmup = int(math.ceil(0.5 * track.fps))  # the filter's first half second: its velocity is still settling
    errors = {"no prediction": projection_error(measured, truth, track.calibration),
              "Kalman prediction": projection_error(predicted, truth, track.calibration)}
    if calibration_alone is not None:
        errors["calibration alone"] = calibration_alone

    scratch = None
    cache = args.cache
    if not cache and args.face == "builtin":
        import tempfile

        scratch = tempfile.TemporaryDirectory(prefix="cfx-mask-")
        cache = builtin_face_cache(os.path.join(scratch.name, "face.usdc"), track.fps)
    face = CacheFace(cache) if cache else None
    draw_face = face if face is not None else (lambda t: drawn_face(time=t))
    display = track.times + opts.latency
    progress = tqdm(range(len(track)), desc=f"mask {os.path.basename(opts.output)}", unit="frame", file=sys.stderr,
                    disable=args.quiet or len(track) < 2, leave=False)
    try:
        frames = (projector_frame(draw_face(display[k]), shown[k], track.calibration, (width, height))
                  for k in progress)
        write_whole(opts.output, lambda tmp: write_images(frames, None, tmp, ".mp4", track.fps, None))
        if args.sheet:
            picks = np.unique(np.linspace(min(warmup, len(track) - 1), len(track) - 1, 4).round().astype(int))
            sheet = _sheet(picks, track, infrared, {"predicted": predicted, "not predicted": measured},
                           truth, true_camera, draw_face, opts.latency, (width, height))
            write_whole(args.sheet, lambda tmp: sheet.save(tmp, format="PNG"))
        if args.save_track:  # last: a run that fails leaves no track behind either
            write_whole(args.save_track, lambda tmp: write_track(tmp, track))
    finally:
        progress.close()
        if face is not None:
            face.close()
        if scratch is not None:
            scratch.cleanup()

    mode = "without prediction" if args.no_predict else f"with {args.model} Kalman prediction"
    print(f"wrote {opts.output}: {len(track)} projector frames {width}x{height} at {track.fps:g} fps, {mode}",
          file=sys.stderr)
    dropped = int(np.sum(~np.isfinite(measured[:, 0, 0])))
    print(f"  latency {1e3 * opts.latency:.0f} ms, {len(track)} captures ({dropped} without all five LEDs); "
          f"projection error in projector px after the first {warmup} frames:", file=sys.stderr)
    if len(track) <= warmup:
        print(f"    none measured: the errors count from frame {warmup + 1} (the filter settling), and the track has "
              f"{len(track)} frames", file=sys.stderr)
        errors = {}
    for name, e in errors.items():
        mean, worst = error_summary(e, warmup)
        print(f"    {name + ':':19s} mean {mean:6.2f}, max {worst:6.2f}", file=sys.stderr)
    if calibration_alone is not None and errors:
        print("    (calibration alone: the mask off the plane the homography was measured on, no latency)",
              file=sys.stderr)
    if args.sheet:
        print(f"wrote {args.sheet}", file=sys.stderr)
    return 0


def _zoom(image, corners, size, extent=1.7):
    """A tile of `size` cut from `image` around the quad `corners`, `extent` times its radius."""
    from PIL import Image

    width, height = size
    centre = corners.mean(0)
    radius = extent * max(np.linalg.norm(corners - centre, axis=1).max(), 4.0)
    half = radius * np.array([width / height, 1.0] if width >= height else [1.0, height / width])
    box = tuple(float(c) for c in (*(centre - half), *(centre + half)))
    stage = tuple(int(c) for c in image[0, 0])
    return np.asarray(Image.fromarray(image).transform((width, height), Image.Transform.EXTENT, box,
                                                       Image.Resampling.BILINEAR, fillcolor=stage))


def _sheet(picks, track, infrared, corner_sets, truth, true_camera, draw_face, latency, size):
    """Contact sheet, a row per picked frame: the camera's infrared view, the projector frame, and
    the mask seen up close at display time with each of `corner_sets` ({name: (N, 4, 2)})."""
    from PIL import Image

    from io_usd.preview import contact_sheet

    tiles, labels = [], []
    for k in picks:
        k = int(k)
        face = draw_face(track.times[k] + latency)
        first = next(iter(corner_sets.values()))
        camera = Image.fromarray(camera_view(infrared(k), track.leds[k], first[k]))
        tiles.append(np.asarray(camera.resize(size, Image.Resampling.BILINEAR) if camera.size != size else camera))
        labels.append(f"camera t={track.times[k]:.2f}s")
        for n, (name, corners) in enumerate(corner_sets.items()):
            projected = projector_frame(face, corners[k], track.calibration, size)
            if n == 0:
                tiles.append(projected)
                labels.append(f"projector, {name}")
            if np.all(np.isfinite(true_camera[k])) and np.all(np.isfinite(truth[k])):
                view = _zoom(on_mask_view(projected, true_camera[k], truth[k], track.camera_size), true_camera[k], size)
                error = projection_error(corners[k:k + 1], truth[k:k + 1], track.calibration)[0]
                labels.append(f"on the mask, {name}: {error:.1f} px")
            else:
                view = np.zeros((size[1], size[0], 3), np.uint8)
                labels.append(f"on the mask, {name}: unknown")
            tiles.append(view)
    return contact_sheet(tiles, labels, columns=2 + len(corner_sets))
