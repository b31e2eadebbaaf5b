"""Hair motion capture: stripe-dyed guide hairs filmed by calibrated cameras, solved to strands.

After the capture method of the seed paper (hair extensions dyed in horizontal stripes, §4-§5):

1. per image (§4.2): split RGB, keep pixels whose channel ratio passes a per-colour threshold, subtract
   the background, close (dilate, then erode), median-filter, label connected regions, drop the small
   ones, and take each region's centroid (`segment_image`);
2. labels (§4.2.3): the stripes are named on the first frame of each camera (`first_frame_labels` in
   capture.json), then followed from frame to frame by nearest neighbour among blobs of the same
   colour (`LabelTracker`). Where the paper fixes failures by hand, here every camera's
   triangulation of the previous frames tells each camera where to look, and a camera's label that
   the others outvote is dropped (`label_capture`);
3. 3D (§4.3): the parallel stereo pair by the paper's eq. 2 (`stereo_triangulate`) and every camera
   that sees a stripe by linear triangulation refined on the reprojection error, its views chosen by
   the pair of views most others agree with (`triangulate`); a stripe centre farther from its root
   and its guide's other stripes than the hair between them allows is rejected (`chain_outliers`);
4. gaps (§4.4): short runs of missing frames are interpolated, long runs hold the last position
   (`fill_gaps`);
5. cleaning (§5.1): per strand, a point that bends the strand more than an angle threshold is taken
   from the previous frame, segment lengths are set from the stripe width, and a cubic spline
   resamples the strand (`reject_kinks`, `normalise_lengths`, `resample_strands`);
6. density (§5.2): strands interpolated between neighbouring guides (eq. 6) and inner layers whose
   motion fades toward the scalp (`strand_neighbours`, `interpolate_strands`, `inner_layers`);
7. output: a USD cache of guides, all strands and hair cards (`sim.hair_cards`), plus a JSON report
   measured against the ground truth of a synthetic capture (`solve`).

The capture directory is described in docs/capture_format.md. Pixel coordinates: (0, 0) is the
top-left corner of the top-left pixel, so pixel (row r, column c) has its centre at (c + 0.5, r + 0.5).

Where the capture carries the head (simulation.usdc with a collider prim), its rigid motion is
estimated from the scalp and the strands are cleaned, densified and layered in the head's frame:
roots ride on the head, the previous frame's points are compared after the head has moved, and the
inner layers' motion decays relative to the head, not to the world.
"""

import json
import math
import os
import sys
import zipfile
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from .capture_rig import CaptureCamera
from .errors import InputError
from .rigid import rigid_fit

COLOR_CHANNELS = {"red": 0, "green": 1, "blue": 2}
GROUPS = ("stereo", "ring")
CAPTURE_KEYS = {"version", "fps", "frames", "image_size", "units", "stripe", "guides", "cameras", "stereo",
                "first_frame_labels"}
GUIDE_COLOR = (0.85, 0.25, 0.2)
HAIR_COLOR = (0.32, 0.22, 0.14)
CARD_COLOR = (0.45, 0.32, 0.2)
SKIN_COLOR = (0.86, 0.7, 0.6)

# ==================================================================================================
# The capture directory
# ==================================================================================================


@dataclass(frozen=True, eq=False)
class Capture:
    """A capture directory read and checked (see docs/capture_format.md)."""

    path: str
    fps: float
    frames: np.ndarray  # (F,) time codes
    image_size: tuple  # (width, height) px
    stripe_width: float  # m
    colors: tuple  # colour names, cycling along each guide from the root
    guide_names: tuple
    roots: np.ndarray  # (G, 3) at the first frame, m
    stripes: np.ndarray  # (G,) whole stripes per guide
    cameras: tuple  # CaptureCamera, ...
    stereo: tuple  # (left index, right index, baseline m) or None
    first_frame_labels: dict  # camera name -> (marker indices (n,), uv (n, 2))
    truth: dict = field(default=None)  # truth.npz arrays, or None for a real capture

    @property
    def num_markers(self):
        return int(self.stripes.sum())

    @property
    def marker_offsets(self):
        """Index of guide g's first stripe among all markers (markers run guide by guide, root first)."""
        return np.concatenate([[0], np.cumsum(self.stripes)[:-1]]).astype(np.int64)

    @property
    def marker_guide(self):
        return np.repeat(np.arange(len(self.stripes)), self.stripes)

    @property
    def marker_stripe(self):
        return np.arange(self.num_markers) - np.repeat(self.marker_offsets, self.stripes)

    @property
    def marker_channel(self):
        """RGB channel (0, 1, 2) of each marker's dye: stripe k has colour colors[k % len(colors)]."""
        channels = np.array([COLOR_CHANNELS[c] for c in self.colors])
        return channels[self.marker_stripe % len(self.colors)]

    @property
    def marker_names(self):
        return [f"{self.guide_names[g]}:{k}" for g, k in zip(self.marker_guide, self.marker_stripe)]

    def image_path(self, camera, frame):
        return os.path.join(self.path, "images", camera, f"{int(frame):04d}.png")

    def background_path(self, camera):
        return os.path.join(self.path, "background", f"{camera}.png")

    def truth_markers(self):
        """Ground-truth stripe centres per marker (F, M, 3), or None."""
        if self.truth is None:
            return None
        centres = self.truth["stripe_centres"]
        return centres[:, self.marker_guide, self.marker_stripe]


def load_capture(capture_dir, check_images=True):
    """Read and check capture.json (and truth.npz where present). Raises InputError naming the file,
    the key and the reason for anything missing or malformed."""
    capture_dir = os.fspath(capture_dir)
    source = os.path.join(capture_dir, "capture.json")
    if not os.path.isdir(capture_dir):
        raise InputError(capture_dir, None, "no such capture directory")
    if not os.path.isfile(source):
        raise InputError(source, None, "missing: not a capture directory")
    try:
        with open(source, encoding="utf-8") as f:
            doc = json.load(f)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as err:
        raise InputError(source, None, f"cannot read JSON: {str(err) or type(err).__name__}") from None
    if not isinstance(doc, dict):
        raise InputError(source, None, "expected a JSON object")
    unknown = sorted(set(doc) - CAPTURE_KEYS)
    if unknown:
        raise InputError(source, unknown[0], f"unknown key (expected {', '.join(sorted(CAPTURE_KEYS))})")
    for key in ("fps", "frames", "image_size", "stripe", "guides", "cameras", "first_frame_labels"):
        if key not in doc:
            raise InputError(source, key, "missing")
    if doc.get("version", 1) != 1:
        raise InputError(source, "version", f"unsupported version {doc['version']!r} (this reader knows 1)")
    if doc.get("units", "m") != "m":
        raise InputError(source, "units", f"expected \"m\", got {doc['units']!r}")

    fps = _number(doc["fps"], source, "fps", positive=True)
    frames = _int_list(doc["frames"], source, "frames")
    if len(frames) == 0 or np.any(np.diff(frames) <= 0):
        raise InputError(source, "frames", "expected a non-empty, increasing list of time codes")
    size = _int_list(doc["image_size"], source, "image_size")
    if len(size) != 2 or np.any(size <= 0):
        raise InputError(source, "image_size", "expected [width, height] in pixels")

    stripe = doc["stripe"]
    if not isinstance(stripe, dict) or set(stripe) - {"width", "colors"} or "width" not in stripe:
        raise InputError(source, "stripe", "expected {\"width\": metres, \"colors\": [...]}")
    width = _number(stripe["width"], source, "stripe.width", positive=True)
    colors = stripe.get("colors", ["red", "green", "blue"])
    if not isinstance(colors, list) or not colors or any(c not in COLOR_CHANNELS for c in colors):
        raise InputError(source, "stripe.colors", f"expected a list of {', '.join(COLOR_CHANNELS)}")

    guides = doc["guides"]
    if not isinstance(guides, list) or not guides:
        raise InputError(source, "guides", "expected a non-empty list")
    names, roots, stripes = [], [], []
    for g, guide in enumerate(guides):
        key = f"guides[{g}]"
        if not isinstance(guide, dict) or "root" not in guide or "stripes" not in guide:
            raise InputError(source, key, "expected {\"name\", \"root\": [x, y, z], \"stripes\": n}")
        names.append(str(guide.get("name", f"g{g:02d}")))
        roots.append(_array(guide["root"], (3,), source, f"{key}.root"))
        n = guide["stripes"]
        if not isinstance(n, int) or isinstance(n, bool) or n < 1:
            raise InputError(source, f"{key}.stripes", f"expected a positive whole number, got {n!r}")
        stripes.append(n)
    stripes = np.array(stripes, np.int64)

    cameras = []
    if not isinstance(doc["cameras"], list) or len(doc["cameras"]) < 2:
        raise InputError(source, "cameras", "expected a list of at least two cameras")
    for c, cam in enumerate(doc["cameras"]):
        key = f"cameras[{c}]"
        if not isinstance(cam, dict) or not {"name", "K", "world_to_camera"} <= set(cam):
            raise InputError(source, key, "expected {\"name\", \"group\", \"K\", \"world_to_camera\"}")
        K = _array(cam["K"], (3, 3), source, f"{key}.K")
        if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]):
            raise InputError(source, f"{key}.K", "expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
        M = _array(cam["world_to_camera"], (4, 4), source, f"{key}.world_to_camera")
        R = M[:3, :3]
        rigid = np.allclose(R @ R.T, np.eye(3), atol=1e-5) and np.linalg.det(R) > 0
        if not rigid or not np.allclose(M[3], [0, 0, 0, 1]):
            raise InputError(source, f"{key}.world_to_camera", "expected a rigid transform (rotation and translation)")
        group = cam.get("group", "ring")
        if group not in GROUPS:
            raise InputError(source, f"{key}.group", f"expected one of {', '.join(GROUPS)}, got {group!r}")
        cameras.append(CaptureCamera(str(cam["name"]), group, K, M))
    camera_names = [c.name for c in cameras]
    if len(set(camera_names)) != len(camera_names):
        raise InputError(source, "cameras", "camera names must be unique")

    stereo = None
    if doc.get("stereo") is not None:
        s = doc["stereo"]
        if not isinstance(s, dict) or set(s) != {"left", "right", "baseline"}:
            raise InputError(source, "stereo", "expected {\"left\", \"right\", \"baseline\"}")
        for side in ("left", "right"):
            if s[side] not in camera_names:
                raise InputError(source, f"stereo.{side}", f"no camera named {s[side]!r}")
        left, right = camera_names.index(s["left"]), camera_names.index(s["right"])
        baseline = _number(s["baseline"], source, "stereo.baseline", positive=True)
        _check_parallel(cameras[left], cameras[right], baseline, source)
        stereo = (left, right, baseline)

    offsets = np.concatenate([[0], np.cumsum(stripes)[:-1]])
    labels = {}
    if not isinstance(doc["first_frame_labels"], dict):
        raise InputError(source, "first_frame_labels", "expected {camera: [{guide, stripe, uv}, ...]}")
    for cam_name, entries in doc["first_frame_labels"].items():
        key = f"first_frame_labels.{cam_name}"
        if cam_name not in camera_names:
            raise InputError(source, key, "no such camera")
        if not isinstance(entries, list):
            raise InputError(source, key, "expected a list of {guide, stripe, uv}")
        markers, uvs = [], []
        for i, e in enumerate(entries):
            if not isinstance(e, dict) or set(e) != {"guide", "stripe", "uv"}:
                raise InputError(source, f"{key}[{i}]", "expected {\"guide\", \"stripe\", \"uv\"}")
            g, k = e["guide"], e["stripe"]
            if not isinstance(g, int) or not 0 <= g < len(stripes):
                raise InputError(source, f"{key}[{i}].guide", f"expected a guide index below {len(stripes)}, got {g!r}")
            if not isinstance(k, int) or not 0 <= k < stripes[g]:
                raise InputError(source, f"{key}[{i}].stripe", f"guide {g} has {stripes[g]} stripes, got {k!r}")
            markers.append(offsets[g] + k)
            uvs.append(_array(e["uv"], (2,), source, f"{key}[{i}].uv"))
        if len(set(markers)) != len(markers):
            raise InputError(source, key, "a stripe is named twice")
        labels[cam_name] = (np.array(markers, np.int64), np.array(uvs, np.float64).reshape(-1, 2))

    capture = Capture(capture_dir, fps, frames, (int(size[0]), int(size[1])), width, tuple(colors), tuple(names),
                      np.array(roots), stripes, tuple(cameras), stereo, labels,
                      _load_truth(capture_dir, len(frames), len(stripes), int(stripes.max()), len(cameras)))
    if check_images:
        for cam in cameras:
            if not os.path.isfile(capture.background_path(cam.name)):
                raise InputError(capture.background_path(cam.name), None, "missing background image")
            for frame in frames:
                if not os.path.isfile(capture.image_path(cam.name, frame)):
                    raise InputError(capture.image_path(cam.name, frame), None, "missing image")
    return capture


def _load_truth(capture_dir, frames, guides, max_stripes, cameras):
    path = os.path.join(capture_dir, "truth.npz")
    if not os.path.isfile(path):
        return None
    try:
        with np.load(path) as data:
            truth = {k: np.array(data[k]) for k in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:  # a truncated .npz is a bad zip
        raise InputError(path, None, f"cannot read: {str(err) or type(err).__name__}") from None
    if "stripe_centres" not in truth:
        raise InputError(path, "stripe_centres", "missing")
    centres = truth["stripe_centres"]
    if centres.dtype.kind != "f":  # NaN marks a stripe a guide does not have
        raise InputError(path, "stripe_centres", f"expected floating-point positions, got {centres.dtype}")
    if centres.ndim != 4 or centres.shape[:2] != (frames, guides) or centres.shape[2] < max_stripes \
            or centres.shape[3] != 3:
        raise InputError(path, "stripe_centres", f"expected ({frames}, {guides}, >= {max_stripes}, 3), "
                                                 f"got {centres.shape}")
    occluded = truth.get("occluded")
    if occluded is not None and occluded.shape[:2] != (frames, cameras):
        raise InputError(path, "occluded", f"expected ({frames}, {cameras}, guides, stripes), got {occluded.shape}")
    return truth


def _check_parallel(left, right, baseline, source):
    """The paper's eq. 2 needs a rectified pair: same intrinsics and orientation, the right camera
    `baseline` along the left's +x."""
    R_l, R_r = left.world_to_camera[:3, :3], right.world_to_camera[:3, :3]
    angle = math.degrees(math.acos(np.clip((np.trace(R_l.T @ R_r) - 1.0) / 2.0, -1.0, 1.0)))
    if angle > 0.5 or not np.allclose(left.K, right.K, rtol=1e-3, atol=1e-3):
        raise InputError(source, "stereo", f"{left.name} and {right.name} are not a parallel pair "
                                           f"(orientations differ by {angle:.2f} degrees, or K differs)")
    offset = left.world_to_camera[:3, 3] - right.world_to_camera[:3, 3]  # right centre in left's frame
    if abs(offset[0] - baseline) > 0.01 * baseline + 1e-4 or np.linalg.norm(offset[1:]) > 0.01 * baseline + 1e-4:
        raise InputError(source, "stereo.baseline", f"the calibration puts {right.name} at {offset.round(4).tolist()} "
                                                    f"in {left.name}'s frame, not {baseline} m along +x")


def _number(value, source, key, positive=False):
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(source, key, f"expected a number, got {value!r}")
    if positive and value <= 0:
        raise InputError(source, key, f"expected a positive number, got {value!r}")
    return float(value)


def _int_list(value, source, key):
    if not isinstance(value, list) or any(isinstance(v, bool) or not isinstance(v, int) for v in value):
        raise InputError(source, key, "expected a list of whole numbers")
    return np.array(value, np.int64)


def _array(value, shape, source, key):
    try:
        a = np.array(value, np.float64)
    except (TypeError, ValueError):
        raise InputError(source, key, f"expected numbers of shape {shape}") from None
    if a.shape != shape or not np.all(np.isfinite(a)):
        raise InputError(source, key, f"expected finite numbers of shape {shape}, got {value!r}")
    return a


def read_image(path, size=None):
    """An RGB image as float32 (H, W, 3) in [0, 1]; checks its (width, height) against `size`."""
    import imageio.v3 as iio

    try:
        image = iio.imread(path)
    except (OSError, ValueError, SyntaxError) as err:  # Pillow raises SyntaxError for a broken PNG
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise InputError(path, None, f"cannot read image: {first}") from None
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] < 3:
        raise InputError(path, None, f"expected an RGB image, got shape {image.shape}")
    if size is not None and (image.shape[1], image.shape[0]) != tuple(size):
        raise InputError(path, None, f"image is {image.shape[1]}x{image.shape[0]}, capture.json says "
                                     f"{size[0]}x{size[1]}")
    scale = 65535.0 if image.dtype == np.uint16 else 255.0 if image.dtype == np.uint8 else 1.0
    return image[..., :3].astype(np.float32) / np.float32(scale)


# ==================================================================================================
# 1. Per image: colour regions and their centroids (§4.2)
# ==================================================================================================


@dataclass(frozen=True)
class SegmentParams:
    """Stripe detection in one image."""

    ratio_threshold: tuple = (0.5, 0.5, 0.5)  # channel / (R + G + B) a red, green, blue pixel must reach
    min_brightness: float = 0.15  # (R + G + B) / 3 below this is too dark for a ratio to mean anything
    background_difference: float = 0.1  # largest channel difference from the background image, 0..1
    closing_px: int = 1  # dilations, then as many erosions (3x3)
    median_px: int = 3  # median filter window
    min_area_px: int = 12  # smaller regions are noise


@dataclass(frozen=True, eq=False)
class Blobs:
    """The regions found in one image: channel (0 red, 1 green, 2 blue), centroid (u, v) px, area px."""

    channel: np.ndarray  # (n,) int
    uv: np.ndarray  # (n, 2)
    area: np.ndarray  # (n,) int

    def __len__(self):
        return len(self.channel)

    def records(self, colors=("red", "green", "blue")):
        """[(colour, u, v, area), ...]"""
        return [(colors[c], float(u), float(v), int(a)) for c, (u, v), a in zip(self.channel, self.uv, self.area)]


def color_masks(image, background, params=SegmentParams()):
    """(3, H, W) masks of red, green and blue dye, before the morphology: the per-channel ratio
    thresholds (Section 4.2.1; a pixel passing any of them is dyed, their union), gated by brightness
    and by the difference from the background image (Section 4.2.2)."""
    image = np.asarray(image, np.float32)
    total = image.sum(axis=2)
    ratio = image / np.maximum(total, 1e-6)[..., None]
    thresholds = np.asarray(params.ratio_threshold, np.float32)
    passed = ratio >= thresholds
    # a pixel belongs to the colour it passes most clearly (only matters for thresholds below 0.5)
    winner = np.argmax(ratio - thresholds, axis=2)
    dyed = passed.any(axis=2) & (total >= 3.0 * params.min_brightness)
    if background is not None:
        dyed &= _differs(image, background, params.background_difference)
    return (winner[None] == np.arange(3)[:, None, None]) & dyed[None]


def _differs(image, background, threshold):
    """(H, W): pixels where some channel differs from the background's by `threshold` or more (the
    channels compared one by one: NumPy reduces across the last axis of an image slowly)."""
    far = np.abs(image - np.asarray(background, np.float32)) >= threshold
    return far[..., 0] | far[..., 1] | far[..., 2]


# 8-connected within a colour plane, never between planes
_PLANE = np.zeros((3, 3, 3), bool)
_PLANE[1] = True


def clean_masks(masks, params=SegmentParams()):
    """The (3, H, W) colour masks after the closing (dilations, then as many erosions; outside the
    image counts as dyed for the erosions) and the median filter (outside counts as not dyed)."""
    from scipy import ndimage

    if params.closing_px > 0:
        masks = ndimage.binary_dilation(masks, structure=_PLANE, iterations=params.closing_px)
        masks = ndimage.binary_erosion(masks, structure=_PLANE, iterations=params.closing_px, border_value=1)
    if params.median_px > 1:
        masks = ndimage.median_filter(masks.astype(np.uint8), size=(1, params.median_px, params.median_px),
                                      mode="constant") > 0
    return masks


def segment_image(image, background=None, params=SegmentParams()):
    """Stripe regions and their centroids in one RGB image (H, W, 3), float in [0, 1]. All three
    colours go through the morphology and labelling together, as planes of one (3, H, W) stack whose
    structuring elements never reach across planes.

    The work is done in the window around the pixels that differ from the background (or the dyed
    pixels, without one), padded by what the closing and the median filter can reach: outside it
    every mask stays empty, so the regions, their order and their centroids are those of the whole
    image (the dyed hair is a small part of a studio frame)."""
    from scipy import ndimage

    image = np.asarray(image, np.float32)
    margin = 2 * params.closing_px + params.median_px // 2 + 2
    if background is not None:
        background = np.asarray(background, np.float32)
        window = _padded_window(_differs(image, background, params.background_difference), margin)
        masks = color_masks(image[window], background[window], params) if window else None
    else:
        masks = color_masks(image, None, params)
        window = _padded_window(masks.any(axis=0), margin)
        masks = masks[(slice(None),) + window] if window else None
    empty = Blobs(np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0, np.int64))
    if masks is None:
        return empty
    labels, count = ndimage.label(clean_masks(masks, params), structure=_PLANE)
    if count == 0:
        return empty
    area = np.bincount(labels.ravel(), minlength=count + 1)[1:]
    keep = np.nonzero(area >= params.min_area_px)[0] + 1
    if len(keep) == 0:
        return empty
    # centroids as sums of whole pixel coordinates over counts: exact sums, so the same numbers as
    # ndimage.center_of_mass over the whole image
    at = np.flatnonzero(labels)
    label = labels.ravel()[at]
    k, r, c = np.unravel_index(at, labels.shape)
    sums = [np.bincount(label, weights=(v + offset).astype(np.float64), minlength=count + 1)[keep]
            for v, offset in ((k, 0), (r, window[0].start), (c, window[1].start))]
    n = area[keep - 1].astype(np.float64)
    channel = np.rint(sums[0] / n).astype(np.int64)
    uv = np.stack([sums[2] / n, sums[1] / n], axis=1) + 0.5  # (column, row) of a pixel centre -> image coordinates
    return Blobs(channel, uv, area[keep - 1].astype(np.int64))


def _padded_window(mask, margin):
    """(row slice, column slice) of the box around the True pixels of `mask`, grown by `margin` and
    clipped to the image; None when there are none."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if len(rows) == 0:
        return None
    h, w = mask.shape
    return (slice(max(0, rows[0] - margin), min(h, rows[-1] + 1 + margin)),
            slice(max(0, cols[0] - margin), min(w, cols[-1] + 1 + margin)))


# ==================================================================================================
# 2. Labels: named on the first frame, followed by nearest neighbour (§4.2.3)
# ==================================================================================================


@dataclass(frozen=True)
class TrackParams:
    """Frame-to-frame labelling in one camera."""

    max_jump_px: float = 40.0  # farthest a stripe's centroid may move between consecutive frames
    first_frame_px: float = 40.0  # farthest a named label may be from the blob it names
    predict_motion: bool = True  # look for a stripe where its last velocity carries it, not where it was
    max_search_frames: int = 3  # after missed frames the search radius grows up to this many jumps
    use_3d: bool = True  # predict from the other cameras' triangulation where there is one
    reproject_px: float = 12.0  # search radius around a prediction projected from 3D
    ambiguous_px: float = 8.0  # a blob this near another same-colour stripe's prediction is suspect
    # (crossed stripes merge into one blob; predictions miss by a few px, neighbouring stripes by more)
    max_jump_3d: float = 0.01  # m per frame since last trusted: farthest a triangulated marker may land
    # from its 3D prediction (stripe centres accelerate by a few mm per frame; a label that took
    # another stripe of its colour lands centimetres away, even where two cameras agree on it)


class LabelTracker:
    """Follows the labelled stripes of one camera across frames.

    Frame 0: each named label takes the nearest blob of its colour. Later frames: each label takes the
    nearest blob of its colour to where it was last seen (moved on by its last velocity when
    `predict_motion`), the paper's nearest-neighbour rule. Labels and blobs of a colour are paired by a
    minimum-total-distance assignment, so two labels never share a blob; pairs farther than the search
    radius are refused and the label is missing in this frame. The radius is `max_jump_px` per frame
    since the label was last seen, up to `max_search_frames` frames.

    `update` may be given predictions projected from the markers' 3D tracks (every camera's
    triangulation, `TrackParams.use_3d`): these replace the label's own 2D history, with the radius
    `reproject_px`, so a label that took a neighbour's blob while its own stripe was hidden comes back
    to its stripe, and a stripe not named in this camera's first frame is named once it is seen."""

    def __init__(self, marker_channel, named_markers, named_uv, params=TrackParams()):
        self.channel = np.asarray(marker_channel, np.int64)
        m = len(self.channel)
        self.params = params
        self.last = np.full((m, 2), np.nan)
        self.last_t = np.full(m, -1, np.int64)
        self.prev = np.full((m, 2), np.nan)
        self.prev_t = np.full(m, -1, np.int64)
        self._seed = np.full((m, 2), np.nan)
        self._seed[np.asarray(named_markers, np.int64)] = np.asarray(named_uv, np.float64).reshape(-1, 2)
        self._undo = None
        self.t = 0

    def predict(self):
        """Where each label is expected in the next frame from its own 2D history (M, 2) (NaN where
        unknown), and the search radius (M,) px."""
        p = self.params
        m = len(self.channel)
        if self.t == 0:
            return self._seed.copy(), np.full(m, p.first_frame_px)
        seen = self.last_t >= 0
        predicted = self.last.copy()
        if p.predict_motion:
            moving = seen & (self.prev_t >= 0)
            step = (self.t - self.last_t[moving]) / (self.last_t[moving] - self.prev_t[moving])
            predicted[moving] += step[:, None] * (self.last[moving] - self.prev[moving])
        since = np.clip(self.t - self.last_t, 1, p.max_search_frames)
        return predicted, np.where(seen, p.max_jump_px * since, np.nan)

    def update(self, blobs, projected=None):
        """Label one frame's blobs: (M, 2) uv (NaN where missing) and (M,) blob index (-1).
        projected: (M, 2) predictions from 3D (NaN where none), used after the first frame."""
        from scipy.optimize import linear_sum_assignment

        predicted, radius = self.predict()
        if projected is not None and self.t > 0:
            use = np.all(np.isfinite(projected), axis=1)
            predicted[use], radius[use] = projected[use], self.params.reproject_px
        m = len(self.channel)
        active = np.all(np.isfinite(predicted), axis=1)
        index = np.full(m, -1, np.int64)
        for c in np.unique(self.channel[active]):
            labels = np.nonzero(active & (self.channel == c))[0]
            candidates = np.nonzero(blobs.channel == c)[0]
            if len(candidates) == 0:
                continue
            dist = np.linalg.norm(predicted[labels, None] - blobs.uv[None, candidates], axis=2)
            allowed = dist <= radius[labels, None]
            rows, cols = linear_sum_assignment(np.where(allowed, dist, 1e9))
            ok = allowed[rows, cols]
            index[labels[rows[ok]]] = candidates[cols[ok]]

        found = index >= 0
        uv = np.full((m, 2), np.nan)
        uv[found] = blobs.uv[index[found]]
        self._undo = (self.last.copy(), self.last_t.copy(), self.prev.copy(), self.prev_t.copy())
        self.prev[found], self.prev_t[found] = self.last[found], self.last_t[found]
        self.last[found], self.last_t[found] = uv[found], self.t
        self.t += 1
        return uv, index

    def reject(self, markers):
        """Forget the last frame's observations of `markers` (M,) bool, found inconsistent with the
        other cameras: their 2D history is as if they had been missing."""
        if self._undo is None:
            return
        last, last_t, prev, prev_t = self._undo
        self.last[markers], self.last_t[markers] = last[markers], last_t[markers]
        self.prev[markers], self.prev_t[markers] = prev[markers], prev_t[markers]


def label_capture(capture, params, progress=False, roots=None):
    """Segment every image and label its stripes, frame by frame (Section 4.2).

    With `params.track.use_3d`, each frame's labels are triangulated at once (leaving out blobs whose
    area is off the label's median so far or that lie near another same-colour stripe's prediction,
    see `_ambiguous_labels`, and markers that break their guide's chain, see `chain_outliers`, or
    land farther from their 3D prediction than `max_jump_3d` allows); an observation the other
    cameras outvote is forgotten by its camera's tracker, and the next frame's labels are looked for
    where the markers' 3D tracks project (a marker lost last frame: where it was last trusted).
    roots: (F, G, 3) the guides' roots per frame (default: capture.roots, still).
    Returns uv (C, F, M, 2), blob areas (C, F, M), rejected (C, F, M) bool, blobs found (C, F)."""
    F, M, C = len(capture.frames), capture.num_markers, len(capture.cameras)
    roots = np.broadcast_to(capture.roots, (F,) + capture.roots.shape) if roots is None else roots
    trackers, backgrounds = [], []
    for cam in capture.cameras:
        named, uv0 = capture.first_frame_labels.get(cam.name, (np.zeros(0, np.int64), np.zeros((0, 2))))
        trackers.append(LabelTracker(capture.marker_channel, named, uv0, params.track))
        backgrounds.append(read_image(capture.background_path(cam.name), capture.image_size))
    uv = np.full((C, F, M, 2), np.nan)
    area = np.full((C, F, M), np.nan)
    rejected = np.zeros((C, F, M), bool)
    blob_counts = np.zeros((C, F), np.int64)
    points = np.full((F, M, 3), np.nan)  # markers trusted for predicting the next frames
    held, held_f = np.full((M, 3), np.nan), np.full(M, -1, np.int64)  # each marker's last trusted point
    ambiguous = np.zeros((C, M), bool)
    same = (capture.marker_channel[:, None] == capture.marker_channel[None, :]) & ~np.eye(M, dtype=bool)
    bar = _progress(F, progress, "labelling")
    for f, frame in enumerate(capture.frames):
        ahead = _predict_points(points, f, params.track.predict_motion) if params.track.use_3d and f > 0 else None
        if ahead is not None:
            # a marker missing last frame is looked for where it was last trusted, not by 2D history
            # alone, which would lead its labels to whichever blob of its colour lies near
            ahead = np.where(np.isfinite(ahead), ahead, held)
        for c, cam in enumerate(capture.cameras):
            blobs = segment_image(read_image(capture.image_path(cam.name, frame), capture.image_size),
                                  backgrounds[c], params.segment)
            projected = cam.project(ahead) if ahead is not None else None
            uv[c, f], index = trackers[c].update(blobs, projected)
            if projected is not None:
                ambiguous[c] = _ambiguous_labels(uv[c, f], projected, same, params.track.ambiguous_px)
            area[c, f, index >= 0] = blobs.area[index[index >= 0]]
            blob_counts[c, f] = len(blobs)
        if params.track.use_3d:
            suspect = suspect_areas(area[:, :f + 1], params.area_ratio)[:, -1] | ambiguous
            x, views, _, used = _triangulate(uv[:, f], capture.cameras, params.refine, params.outlier_px,
                                             suspect=suspect, consensus=params.consensus)
            broken = chain_outliers(x[None], roots[f][None], capture, params.chain_tolerance)[0] \
                if params.chain_tolerance > 0 else np.zeros(M, bool)
            if ahead is not None and params.track.max_jump_3d > 0:
                # two cameras whose labels took the same wrong stripe agree with each other, so no vote
                # can catch them; the marker's own 3D track can
                since = np.where(held_f >= 0, f - held_f, 1)
                jump = np.linalg.norm(x - ahead, axis=1)
                broken |= np.isfinite(jump) & (jump > params.track.max_jump_3d * since)
            seen = np.all(np.isfinite(uv[:, f]), -1)
            outvoted = seen & ((~used.T & (views >= 2)[None]) | broken[None])  # (C, M)
            rejected[:, f] = outvoted | (ambiguous & seen)
            for c in np.nonzero(outvoted.any(1))[0]:
                trackers[c].reject(outvoted[c])
            # only markers from clean views predict: a merged blob's centroid would lead its label astray
            clean = ~broken & ~np.any(used.T & suspect, axis=0)
            points[f] = np.where(clean[:, None], x, np.nan)
            trusted = np.all(np.isfinite(points[f]), 1)
            held[trusted], held_f[trusted] = points[f, trusted], f
        bar.update(1)
    bar.close()
    return uv, area, rejected, blob_counts


def _ambiguous_labels(uv, projected, same, radius_px):
    """Labels (M,) whose blob lies within `radius_px` of the predicted projection of another stripe
    of its colour (same: (M, M) bool): two stripes that cross in a view merge into one blob whose
    centroid lies between them, its area steady while they stay crossed, and either label may hold
    it. Such a view is left out of triangulation wherever two others remain."""
    other = np.linalg.norm(uv[:, None] - projected[None], axis=2)
    other = np.where(same & np.isfinite(other), other, np.inf).min(1)
    return np.all(np.isfinite(uv), 1) & (other <= radius_px)


def _predict_points(points, f, moving):
    """Where the markers (M, 3) should be at frame f from frames f - 1 and f - 2 (NaN where unknown)."""
    last = points[f - 1]
    if not moving or f < 2:
        return last
    step = last - points[f - 2]
    return np.where(np.isfinite(step), last + step, last)


def label_swaps(uv, truth_uv, marker_channel, tolerance_px=5.0):
    """Labelled observations that belong to another stripe, against projected ground truth.

    uv, truth_uv: (F, M, 2) one camera's labels and the true projections of every marker. An
    observation is mislabelled when it lies more than `tolerance_px` from its own stripe's projection
    and nearer to another stripe of the same colour. A swap is the start of a run of mislabelled
    observations of one marker (an observation correct again ends the run).
    Returns (mislabelled (F, M) bool, swaps (F, M) bool)."""
    uv, truth_uv = np.asarray(uv), np.asarray(truth_uv)
    own = np.linalg.norm(uv - truth_uv, axis=2)
    other = np.linalg.norm(uv[:, :, None] - truth_uv[:, None, :], axis=3)  # (F, M, M)
    same = (marker_channel[:, None] == marker_channel[None, :]) & ~np.eye(len(marker_channel), dtype=bool)
    other = np.where(same[None] & np.isfinite(other), other, np.inf).min(axis=2)
    labelled = np.isfinite(own)
    wrong = labelled & (own > tolerance_px) & (other < own)
    swaps = np.zeros_like(wrong)
    # walk forward over labelled observations only: a run starts where the last labelled one was right
    last_wrong = np.zeros(wrong.shape[1], bool)
    for f in range(wrong.shape[0]):
        swaps[f] = wrong[f] & ~last_wrong
        last_wrong = np.where(labelled[f], wrong[f], last_wrong)
    return wrong, swaps


def suspect_areas(area, ratio=1.6):
    """Observations (C, F, M) whose blob area is off its own median (per camera and marker, over the
    frames) by more than `ratio` either way: a stripe partly hidden, or merged with another of its
    colour, whose centroid is not the stripe's."""
    seen = np.isfinite(area)
    median = np.nanmedian(np.where(seen.any(1, keepdims=True), area, 0.0), axis=1, keepdims=True)
    return seen & ((area * ratio < median) | (area > ratio * median))


# ==================================================================================================
# 3. Triangulation (§4.3)
# ==================================================================================================


def stereo_triangulate(uv_left, uv_right, K, baseline):
    """Points in the left camera's frame (..., 3) from a parallel pair, by the paper's eq. 2:
    X = b u / (u - u'), Y = b v / (u - u'), Z = b f / (u - u'), with u, v measured from the principal
    point. With non-square pixels (fx != fy) v is rescaled by fx / fy first, which is eq. 2 in
    pixels of width fx. The left camera's v (the row) is used; in a rectified pair v = v'."""
    uv_left, uv_right = np.asarray(uv_left, np.float64), np.asarray(uv_right, np.float64)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    u = uv_left[..., 0] - cx
    v = (uv_left[..., 1] - cy) * (fx / fy)
    disparity = u - (uv_right[..., 0] - cx)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(disparity > 0, baseline / disparity, np.nan)
    return np.stack([scale * u, scale * v, scale * fx], -1)


def camera_to_world(points, world_to_camera):
    """Camera-frame points (..., 3) to world."""
    R, t = world_to_camera[:3, :3], world_to_camera[:3, 3]
    return (np.asarray(points) - t) @ R


def triangulate(uv, cameras, refine=True, outlier_px=3.0, iterations=5, suspect=None, consensus=True):
    """Points seen by two or more calibrated cameras, all at once.

    uv: (C, N, 2) pixel coordinates per camera (NaN where a camera does not see point n).
    Linear triangulation (DLT): the null vector, by SVD, of two rows x P3 - P1, y P3 - P2 per view in
    normalised image coordinates (K^-1 applied), which keeps the system well conditioned. With
    `consensus`, a point seen by three or more cameras first keeps only the views that agree with
    its best pair of views (`_consensus_views`). With `refine`, Gauss-Newton steps on the pixel
    reprojection error follow; then, while a point's worst view (of three or more) is off by more
    than `outlier_px`, that view is dropped and the point solved again (a partly hidden stripe shifts
    its centroid in one view).
    suspect: (C, N) bool, views to leave out wherever two or more others remain (blobs whose area
    says they are partly hidden or merged with another stripe); they count half in the consensus.

    Returns points (N, 3) (NaN with fewer than two views), views used (N,), RMS reprojection
    error (N,) px."""
    points, views, rms, _ = _triangulate(uv, cameras, refine, outlier_px, iterations, suspect, consensus)
    return points, views, rms


def _triangulate(uv, cameras, refine=True, outlier_px=3.0, iterations=5, suspect=None, consensus=True):
    """`triangulate`, also returning the views used (N, C) bool."""
    uv = np.asarray(uv, np.float64)
    Ks = np.stack([c.K for c in cameras])
    Rt = np.stack([c.world_to_camera[:3] for c in cameras])  # (C, 3, 4)
    seen = np.all(np.isfinite(uv), axis=2).T  # (N, C)
    suspect = np.zeros_like(seen) if suspect is None else np.asarray(suspect, bool).T & seen
    if consensus:
        seen = _consensus_views(uv, Ks, Rt, seen, outlier_px, suspect)
    trusted = seen & ~suspect
    seen = np.where((trusted.sum(1) >= 2)[:, None], trusted, seen)
    while True:
        points = _dlt(uv, Ks, Rt, seen)
        if refine:
            points = _gauss_newton(points, uv, Ks, Rt, seen, iterations)
        error = _reprojection_error(points, uv, Ks, Rt, seen)  # (N, C), NaN where not seen
        worst = np.nanargmax(np.where(seen, error, -1.0), axis=1)
        worst_error = np.take_along_axis(np.where(seen, error, 0.0), worst[:, None], 1)[:, 0]
        drop = (seen.sum(1) >= 3) & (worst_error > outlier_px)
        if not drop.any():
            break
        seen[np.nonzero(drop)[0], worst[drop]] = False
    views = seen.sum(1)
    points[views < 2] = np.nan
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.sqrt((np.where(seen, error, 0.0) ** 2).sum(1) / views)
    rms[views < 2] = np.nan
    return points, views, rms, seen & (views >= 2)[:, None]


def _consensus_views(uv, Ks, Rt, seen, outlier_px, suspect, chunk_rows=20000):
    """For points seen by three or more cameras: the views that agree with the best pair.

    Every pair of views is triangulated on its own and scored by how many of the point's views
    reproject within `outlier_px` in front of their cameras (a suspect view counts half); the best
    pair's agreeing views are kept.
    Unlike dropping the worst view one at a time, this holds when two of five views are wrong (two
    labels on a merged blob, a stripe half hidden). Points where no pair wins two views keep theirs."""
    C = len(Ks)
    multi = np.nonzero(seen.sum(1) >= 3)[0]
    if len(multi) == 0:
        return seen
    a, b = np.triu_indices(C, 1)
    P = len(a)
    seen = seen.copy()
    step = max(1, chunk_rows // P)
    for start in range(0, len(multi), step):
        idx = multi[start:start + step]
        n = len(idx)
        s = seen[idx]  # (n, C)
        pair = np.zeros((P, n, C), bool)
        both = s[:, a] & s[:, b]  # (n, P)
        pair[np.arange(P)[:, None], np.arange(n)[None, :], a[:, None]] = both.T
        pair[np.arange(P)[:, None], np.arange(n)[None, :], b[:, None]] = both.T
        tiled = np.tile(uv[:, idx], (1, P, 1))  # (C, P n, 2): row p n + i is point i
        points = _dlt(tiled, Ks, Rt, pair.reshape(P * n, C))
        every = np.tile(s, (P, 1))
        error = _reprojection_error(points, tiled, Ks, Rt, every)
        depth = np.einsum("cj,nj->nc", Rt[:, 2, :3], np.nan_to_num(points)) + Rt[:, 2, 3]
        agree = every & (np.nan_to_num(error, nan=np.inf) <= outlier_px) & (depth > 0)
        weight = np.where(np.tile(suspect[idx], (P, 1)), 0.5, 1.0)
        score = (agree * weight).sum(1) - 1e-3 * np.where(agree, error, 0.0).sum(1) / max(outlier_px, 1e-9)
        score = np.where(both.T.reshape(-1), score, -np.inf).reshape(P, n)
        best = np.argmax(score, axis=0)
        chosen = agree.reshape(P, n, C)[best, np.arange(n)]
        keep = chosen.sum(1) >= 2
        seen[idx[keep]] = chosen[keep]
    return seen


def _dlt(uv, Ks, Rt, seen):
    C, N = uv.shape[:2]
    ones = np.ones((C, N, 1))
    xn = np.concatenate([np.nan_to_num(uv), ones], 2) @ np.linalg.inv(Ks).transpose(0, 2, 1)  # (C, N, 3)
    rows_x = xn[..., 0:1] * Rt[:, None, 2] - Rt[:, None, 0]  # (C, N, 4)
    rows_y = xn[..., 1:2] * Rt[:, None, 2] - Rt[:, None, 1]
    w = seen.T[..., None].astype(np.float64)
    A = np.concatenate([rows_x * w, rows_y * w], 0).transpose(1, 0, 2)  # (N, 2C, 4)
    _, _, vt = np.linalg.svd(A)
    h = vt[:, -1]
    with np.errstate(divide="ignore", invalid="ignore"):
        return h[:, :3] / h[:, 3:4]


def _gauss_newton(points, uv, Ks, Rt, seen, iterations):
    """Minimise the summed squared pixel reprojection error over each point (3 unknowns), batched."""
    good = np.all(np.isfinite(points), 1) & (seen.sum(1) >= 2)
    w = (seen & good[:, None]).T[..., None]  # (C, N, 1): points seen once are left alone
    x = np.where(good[:, None], points, 0.0)
    target = np.nan_to_num(uv)
    for _ in range(iterations):
        cam = np.einsum("cij,nj->cni", Rt[:, :, :3], x) + Rt[:, None, :, 3]  # (C, N, 3)
        z = cam[..., 2:3]
        fx, fy = Ks[:, None, 0, 0:1], Ks[:, None, 1, 1:2]
        proj = np.concatenate([fx * cam[..., 0:1] / z + Ks[:, None, 0, 2:3] + Ks[:, None, 0, 1:2] * cam[..., 1:2] / z,
                               fy * cam[..., 1:2] / z + Ks[:, None, 1, 2:3]], 2)
        r = (proj - target) * w  # (C, N, 2)
        # d proj / d cam, then chain through R
        zero = np.zeros_like(z)
        du = np.concatenate([fx / z, Ks[:, None, 0, 1:2] / z, -(proj[..., 0:1] - Ks[:, None, 0, 2:3]) / z], 2)
        dv = np.concatenate([zero, fy / z, -(proj[..., 1:2] - Ks[:, None, 1, 2:3]) / z], 2)
        J = np.stack([du, dv], 2) @ Rt[:, None, :, :3]  # (C, N, 2, 3)
        J = J * w[..., None]
        JtJ = np.einsum("cnki,cnkj->nij", J, J)
        JtJ += (1e-12 * np.trace(JtJ, axis1=1, axis2=2) + 1e-12)[:, None, None] * np.eye(3)
        Jtr = np.einsum("cnki,cnk->ni", J, r)
        x = x - np.linalg.solve(JtJ, Jtr[..., None])[..., 0]
    return np.where(good[:, None], x, np.nan)


def _reprojection_error(points, uv, Ks, Rt, seen):
    cam = np.einsum("cij,nj->cni", Rt[:, :, :3], np.nan_to_num(points)) + Rt[:, None, :, 3]
    pix = cam @ Ks.transpose(0, 2, 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = pix[..., :2] / pix[..., 2:3]
    error = np.linalg.norm(proj - uv, axis=2).T  # (N, C)
    return np.where(seen & np.isfinite(error), error, np.nan)


def chain_outliers(markers, roots, capture, tolerance=1.25, slack=0.003):
    """Markers (F, M, 3) that lie farther along their guide than its stripes allow: the centre of
    stripe k is w/2 + k w of hair from the root and (k - j) w from the centre of stripe j, and a
    chord is never longer than its arc. Each guide is walked from its root (roots (F, G, 3)); a
    centre beyond `tolerance` times the hair length (plus `slack` m) from the last consistent point
    is an outlier (a label that took another guide's stripe). Returns (F, M) bool."""
    markers = np.asarray(markers, np.float64)
    w = capture.stripe_width
    out = np.zeros(markers.shape[:2], bool)
    anchor = np.array(roots, np.float64, copy=True)  # (F, G, 3)
    anchor_arc = np.full(anchor.shape[:2], -0.5 * w)  # arc length of the anchor, from the first centre
    offsets = capture.marker_offsets
    for k in range(int(capture.stripes.max())):
        g = np.nonzero(capture.stripes > k)[0]
        m = offsets[g] + k
        x = markers[:, m]
        budget = tolerance * (k * w - anchor_arc[:, g]) + slack
        d = np.linalg.norm(x - anchor[:, g], axis=-1)
        finite = np.all(np.isfinite(x), -1)
        ok = finite & (d <= budget)
        out[:, m] = finite & ~ok
        anchor[:, g] = np.where(ok[..., None], x, anchor[:, g])
        anchor_arc[:, g] = np.where(ok, k * w, anchor_arc[:, g])
    return out


# ==================================================================================================
# 4. Gap filling (§4.4)
# ==================================================================================================


def fill_gaps(track, max_gap=5):
    """Fill missing frames (NaN rows along axis 0) of marker tracks (F, ..., 3).

    The rule, per marker, for a frame in a run of missing frames:
    - between two good frames, in a run of at most `max_gap` frames: linear interpolation between
      the good frames on either side (exact for linear motion);
    - in a longer run: the last good position before the run, for every frame of the run (the paper
      holds the previous frame's position once a marker has been lost for long);
    - before the first good frame: the first good position; after the last: the last good one;
    - a marker never seen stays NaN.
    Returns (filled track, interpolated (F, ...) bool, held (F, ...) bool)."""
    track = np.asarray(track, np.float64)
    F = track.shape[0]
    good = np.all(np.isfinite(track), axis=-1)  # (F, ...)
    idx = np.arange(F).reshape((F,) + (1,) * (good.ndim - 1))
    prev = np.maximum.accumulate(np.where(good, idx, -1), axis=0)
    nxt = np.flip(np.minimum.accumulate(np.flip(np.where(good, idx, F), 0), axis=0), 0)
    missing = ~good
    has_prev, has_next = prev >= 0, nxt < F
    interpolate = missing & has_prev & has_next & (nxt - prev - 1 <= max_gap)
    held = missing & ~interpolate & (has_prev | has_next)

    p = np.take_along_axis(track, np.clip(prev, 0, F - 1)[..., None], 0)
    n = np.take_along_axis(track, np.clip(nxt, 0, F - 1)[..., None], 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = ((idx - prev) / (nxt - prev))[..., None]
    out = track.copy()
    out = np.where(interpolate[..., None], (1.0 - s) * p + s * n, out)
    out = np.where((held & has_prev)[..., None], p, out)
    out = np.where((held & ~has_prev)[..., None], n, out)
    return out, interpolate, held


# ==================================================================================================
# 5. Cleaning each strand (§5.1)
# ==================================================================================================


def segment_angles(points):
    """Angles (..., K - 2) [rad] between consecutive segment vectors of polylines (..., K, 3) (eq. 4)."""
    seg = np.diff(points, axis=-2)
    a, b = seg[..., :-1, :], seg[..., 1:, :]
    cos = np.sum(a * b, -1) / np.maximum(np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1), 1e-300)
    return np.arccos(np.clip(cos, -1.0, 1.0))


def reject_kinks(strands, max_angle_deg=80.0):
    """Strands over time (F, S, K, 3): where the angle between segments j and j + 1 exceeds the
    threshold, point j + 1 is replaced by its position in the previous (already cleaned) frame.

    Points are checked root to tip, each after the replacements before it, so a single stray
    centroid (which kinks both of its segments) is the one replaced, not its neighbour. The first
    frame has no previous frame and is kept. Returns (cleaned, replaced (F, S, K) bool)."""
    out = np.array(strands, np.float64, copy=True)
    replaced = np.zeros(out.shape[:-1], bool)
    limit = math.radians(max_angle_deg)
    for f in range(1, out.shape[0]):
        for j in range(1, out.shape[2] - 1):
            a = out[f, :, j] - out[f, :, j - 1]
            b = out[f, :, j + 1] - out[f, :, j]
            cos = np.sum(a * b, -1) / np.maximum(np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1), 1e-300)
            kink = np.arccos(np.clip(cos, -1.0, 1.0)) > limit
            out[f, kink, j + 1] = out[f - 1, kink, j + 1]
            replaced[f, kink, j + 1] = True
    return out, replaced


def stripe_chain_lengths(stripes, stripe_width, tip=True):
    """Target segment lengths of a guide's chain through the centres of `stripes` (stripe indices,
    increasing): the centre of stripe k is (k + 1/2) w of hair from the root, so root -> first centre
    is w/2 when stripe 0 is seen and w between the centres of consecutive stripes; with `tip`, the
    last centre -> the end of its stripe, w/2."""
    arc = (np.asarray(stripes, np.float64) + 0.5) * stripe_width
    if tip:
        arc = np.append(arc, arc[-1] + 0.5 * stripe_width)
    return np.diff(np.concatenate([[0.0], arc]))


def normalise_lengths(points, lengths):
    """Polylines (..., K, 3) with segment j set to lengths[j] (K - 1 of them, or K to extend a tip
    along the last segment), root kept, each point moved along the direction from its already
    corrected predecessor (follow-the-leader), so the measured shape is kept as closely as the
    lengths allow."""
    points = np.asarray(points, np.float64)
    lengths = np.asarray(lengths, np.float64)
    K = points.shape[-2]
    out = np.empty(points.shape[:-2] + (len(lengths) + 1, 3))
    out[..., 0, :] = points[..., 0, :]
    for j in range(len(lengths)):
        if j + 1 < K:
            d = points[..., j + 1, :] - out[..., j, :]
        else:  # the tip, straight on from the last segment
            d = out[..., j, :] - out[..., j - 1, :]
        d = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-300)
        out[..., j + 1, :] = out[..., j, :] + lengths[j] * d
    return out


def resample_strands(points, vertices, samples_per_span=32):
    """Polylines (..., K, 3) through a cubic spline (parameterised by chord length) to `vertices`
    points at uniform arc length along the spline (eq. 5)."""
    from scipy.interpolate import CubicSpline

    points = np.asarray(points, np.float64)
    shape = points.shape[:-2]
    K = points.shape[-2]
    flat = points.reshape(-1, K, 3)
    chord = np.linalg.norm(np.diff(flat, axis=1), axis=-1)
    knots = np.concatenate([np.zeros((len(flat), 1)), np.cumsum(chord, 1)], 1)
    knots /= np.maximum(knots[:, -1:], 1e-300)  # (n, K) in [0, 1]
    s = np.linspace(0.0, 1.0, (K - 1) * samples_per_span + 1)
    if K == 2 or np.allclose(knots, knots[:1]):  # one spline for all (the usual case after normalising)
        kind = "not-a-knot" if K > 3 else "natural"
        dense = CubicSpline(knots[0], flat, axis=1, bc_type=kind)(s) if K > 2 else \
            flat[:, :1] + s[None, :, None] * (flat[:, 1:] - flat[:, :1])
    else:
        dense = np.stack([CubicSpline(k, p, axis=0, bc_type="not-a-knot" if K > 3 else "natural")(s)
                          for k, p in zip(knots, flat)])
    arc = np.concatenate([np.zeros((len(flat), 1)), np.cumsum(np.linalg.norm(np.diff(dense, axis=1), axis=-1), 1)], 1)
    target = arc[:, -1:] * np.linspace(0.0, 1.0, vertices)[None]
    # one searchsorted over all curves: row r's arc lengths shifted to be above every earlier row's
    M = arc.shape[1]
    shift = (np.arange(len(arc)) * (arc[:, -1].max() + 1.0))[:, None]
    j = np.searchsorted((arc + shift).ravel(), (target + shift).ravel(), side="right").reshape(target.shape) - 1
    j = np.clip(j - (np.arange(len(arc)) * M)[:, None], 0, M - 2)
    a0 = np.take_along_axis(arc, j, 1)
    a1 = np.take_along_axis(arc, j + 1, 1)
    t = np.clip((target - a0) / np.maximum(a1 - a0, 1e-300), 0.0, 1.0)[..., None]
    p0 = np.take_along_axis(dense, j[..., None], 1)
    p1 = np.take_along_axis(dense, j[..., None] + 1, 1)
    return ((1.0 - t) * p0 + t * p1).reshape(shape + (vertices, 3))


def guide_strands(capture, markers, params):
    """Guide strands (F, G', V, 3) from gap-filled marker positions (F, M, 3), in the head's frame.

    Each guide's chain is its root followed by the centres of its stripes that were triangulated at
    least once (a stripe never seen, say under the hair at the crown, is bridged by the spline; a
    guide with none is left out: `solved` lists the guides kept). Chains go through `reject_kinks`,
    `normalise_lengths` to the stripe width (plus half a stripe to the tip when `extend_tip`), and
    `resample_strands`. Returns (strands, solved)."""
    F = markers.shape[0]
    offsets = capture.marker_offsets
    chains = {}  # the stripes seen -> [(guide, chain (F, K, 3))]: one spline for each
    for g, n in enumerate(capture.stripes):
        track = markers[:, offsets[g]:offsets[g] + n]
        seen = tuple(np.nonzero(np.all(np.isfinite(track), axis=(0, 2)))[0].tolist())
        if seen:
            chain = np.concatenate([np.broadcast_to(capture.roots[g], (F, 1, 3)), track[:, list(seen)]], 1)
            chains.setdefault(seen, []).append((g, chain))
    if not chains:
        raise InputError(capture.path, None, "no guide could be triangulated (check first_frame_labels and the "
                                             "segmentation thresholds)")
    solved = np.array(sorted(g for group in chains.values() for g, _ in group), np.int64)
    strands = np.empty((F, len(solved), params.vertices, 3))
    for seen, group in chains.items():
        pick = np.searchsorted(solved, [g for g, _ in group])
        points, _ = reject_kinks(np.stack([c for _, c in group], 1), params.max_angle_deg)  # (F, S, K, 3)
        points = normalise_lengths(points, stripe_chain_lengths(seen, capture.stripe_width, params.extend_tip))
        strands[:, pick] = resample_strands(points, params.vertices)
    return strands, solved


# ==================================================================================================
# 6. More strands: interpolation between guides and inner layers (§5.2)
# ==================================================================================================


def strand_neighbours(roots, head_centre, max_ratio=2.5):
    """Pairs (E, 2) of neighbouring guides on the scalp: the edges of a Delaunay triangulation of the
    roots seen from the head centre (stereographic projection from the point opposite their mean
    direction), without the long edge of border slivers, and no longer than `max_ratio` times the
    median nearest-neighbour distance of the roots."""
    from scipy.spatial import Delaunay, QhullError, cKDTree

    roots = np.asarray(roots, np.float64)
    n = len(roots)
    if n < 2:
        return np.zeros((0, 2), np.int64)
    d = roots - head_centre
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    m = d.mean(0)
    m = m / np.linalg.norm(m) if np.linalg.norm(m) > 1e-9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(m, np.eye(3)[np.argmin(np.abs(m))])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(m, e1)
    denom = 1.0 + d @ m
    flat = np.stack([d @ e1, d @ e2], 1) / np.maximum(denom, 1e-9)[:, None]
    try:
        if n < 3:
            raise QhullError("two points")
        tri = Delaunay(flat).simplices
        # a sliver along the border (three roots almost in a line) must not link the outer two: drop
        # every edge that faces an angle above 150 degrees in one of its triangles
        corner = flat[tri]  # (T, 3, 2)
        a, b = np.roll(corner, -1, 1) - corner, np.roll(corner, -2, 1) - corner
        cos = np.sum(a * b, -1) / np.maximum(np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1), 1e-300)
        opposite = np.stack([tri[:, [1, 2]], tri[:, [2, 0]], tri[:, [0, 1]]], 1)  # edge facing each corner
        all_edges = np.sort(opposite.reshape(-1, 2), 1)
        sliver = np.sort(opposite[cos < math.cos(math.radians(150.0))].reshape(-1, 2), 1)
        edges = np.unique(all_edges, axis=0)
        if len(sliver):
            edges = edges[~(edges[:, None] == np.unique(sliver, axis=0)[None]).all(-1).any(1)]
    except QhullError:  # roots in a line: link them in order along it
        axis = np.linalg.svd(flat - flat.mean(0))[2][0]
        order = np.argsort(flat @ axis)
        edges = np.sort(np.stack([order[:-1], order[1:]], 1), 1)
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    nearest = cKDTree(roots).query(roots, k=2)[0][:, 1]
    length = np.linalg.norm(roots[edges[:, 0]] - roots[edges[:, 1]], axis=1)
    return edges[length <= max_ratio * np.median(nearest) + 1e-12]


def interpolate_strands(a, b, d):
    """The paper's eq. 6: T_n = ((d - n) a + n b) / d for n = 1 .. d - 1, between strands a and b
    (..., V, 3). Returns (d - 1, ..., V, 3)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    n = np.arange(1, d).reshape((-1,) + (1,) * a.ndim)
    return ((d - n) * a[None] + n * b[None]) / d


def inner_layers(strands, layers, spacing, head_centre, ramp=0.02):
    """Inner layers under the outer strands (F, S, V, 3), in the head's frame (§5.2 (2), eq. 7).

    Layer k = 1 .. L lies at depth k / (L + 1) between the outer hair (depth 0) and the scalp (depth 1,
    where hair no longer moves). Its first-frame pose is the outer strand's moved `k * spacing` toward
    the head centre, fading in over the first `ramp` metres from the root (which stays); its motion,
    the displacement from that first-frame pose, is the outer strand's scaled by 1 - k / (L + 1):
        P_k(t) = P_k(0) + (1 - k / (L + 1)) (P(t) - P(0)).
    Returns (F, L * S, V, 3), layer by layer."""
    strands = np.asarray(strands, np.float64)
    if layers <= 0:
        return strands[:, :0]
    first = strands[0]
    toward = head_centre - first
    toward /= np.maximum(np.linalg.norm(toward, axis=-1, keepdims=True), 1e-300)
    arc = np.concatenate([np.zeros((first.shape[0], 1)),
                          np.cumsum(np.linalg.norm(np.diff(first, axis=1), axis=-1), 1)], 1)
    fade = np.clip(arc / ramp, 0.0, 1.0)[..., None] if ramp > 0 else 1.0
    motion = strands - first[None]
    out = []
    for k in range(1, layers + 1):
        rest = first + k * spacing * fade * toward
        out.append(rest[None] + (1.0 - k / (layers + 1)) * motion)
    return np.concatenate(out, axis=1)


# ==================================================================================================
# The head: rigid motion and centre
# ==================================================================================================


@dataclass(frozen=True, eq=False)
class HeadTrack:
    """The capture's head (from simulation.usdc) and its rigid motion, or an identity motion."""

    transforms: np.ndarray  # (F, 4, 4) head at frame t from the first frame (world -> world)
    centre: np.ndarray  # (3,) head centre at the first frame
    name: str = None  # collider prim, None without a head
    points: np.ndarray = None  # (F, P, 3)
    face_counts: np.ndarray = None
    face_indices: np.ndarray = None
    color: tuple = SKIN_COLOR

    def to_local(self, points):
        """World points (F, ..., 3) into the first frame's pose of the head."""
        T = self.transforms
        shape = points.shape
        flat = points.reshape(shape[0], -1, 3)
        return ((flat - T[:, None, :3, 3]) @ T[:, :3, :3]).reshape(shape)

    def to_world(self, points):
        T = self.transforms
        shape = points.shape
        flat = points.reshape(shape[0], -1, 3)
        return (flat @ T[:, :3, :3].transpose(0, 2, 1) + T[:, None, :3, 3]).reshape(shape)


def load_head(capture, scalp_radius=0.06):
    """The collider of simulation.usdc (if any) at the capture's frames, with its rigid motion fitted
    (Kabsch) to the head vertices within `scalp_radius` of a root. Without one, the head is still
    and its centre is fitted to the roots."""
    F = len(capture.frames)
    path = os.path.join(capture.path, "simulation.usdc")
    collider = None
    if os.path.isfile(path):
        from io_usd.cache import CacheReader

        try:
            reader = CacheReader(path)
        except (OSError, ValueError, RuntimeError) as err:
            raise InputError(path, None, f"cannot read: {err}") from None
        collider = next((p for p in reader.prims.values() if p.role == "collider" and p.kind == "mesh"), None)
    if collider is None:
        return HeadTrack(np.tile(np.eye(4), (F, 1, 1)), _sphere_centre(capture.roots))
    points = np.stack([reader.points(collider.name, f) for f in capture.frames]).astype(np.float64)
    from scipy.spatial import cKDTree

    near = cKDTree(capture.roots).query(points[0], distance_upper_bound=scalp_radius)[0] < np.inf
    scalp = points[:, near] if near.sum() >= 8 else points
    transforms = rigid_fit(scalp[0], scalp)
    centre = _sphere_centre(scalp[0]) if near.sum() >= 8 else points[0].mean(0)
    color = collider.color if collider.color is not None else SKIN_COLOR
    return HeadTrack(transforms, centre, collider.name, points, collider.counts, collider.indices, color)


def _sphere_centre(points):
    """Least-squares sphere centre of points on a cap (|p|^2 = 2 c.p + k); the points' centroid 8 cm
    down when they cannot fix a sphere (fewer than four, or nearly flat)."""
    points = np.asarray(points, np.float64)
    fallback = points.mean(0) - np.array([0.0, 0.08, 0.0])
    if len(points) < 4:
        return fallback
    A = np.concatenate([2.0 * points, np.ones((len(points), 1))], 1)
    sol, *_ = np.linalg.lstsq(A, np.sum(points ** 2, 1), rcond=None)
    centre = sol[:3]
    radius = np.sqrt(max(sol[3] + centre @ centre, 0.0))
    if not np.isfinite(radius) or not 0.03 <= radius <= 0.5:
        return fallback
    return centre


# ==================================================================================================
# The whole solve
# ==================================================================================================


@dataclass(frozen=True)
class SolveParams:
    """Every setting of `solve`; the defaults suit the synthetic captures."""

    segment: SegmentParams = SegmentParams()
    track: TrackParams = TrackParams()
    method: str = "ring"  # 3D markers for the strands: "ring" (every camera) or "stereo" (eq. 2)
    refine: bool = True  # Gauss-Newton after the linear triangulation
    outlier_px: float = 2.0  # leave out a view off by more than this (three or more views)
    area_ratio: float = 1.6  # a blob this much smaller or larger than its stripe's median is suspect
    chain_tolerance: float = 1.25  # a stripe centre farther along its guide than this x the hair between
    consensus: bool = True  # choose each point's views by the best-agreeing pair
    max_gap: int = 5  # frames: longer gaps hold the last position
    max_angle_deg: float = 80.0  # bend between stripe segments beyond which a point is rejected
    extend_tip: bool = True  # carry each guide half a stripe past its last centre (to its tip)
    vertices: int = 16  # per output strand
    strands_between: int = 2  # interpolated strands between neighbouring guides (d - 1 of eq. 6)
    neighbour_ratio: float = 2.5  # longest neighbour edge, in median nearest-root distances
    layers: int = 1  # inner layers under the outer hair
    layer_spacing: float = 0.006  # m between layers
    card_width: float = 0.015  # m
    strand_width: float = 0.001  # m, curve widths in the cache
    swap_tolerance_px: float = 5.0  # a label this far from its own stripe and nearer another is a swap


@dataclass
class SolveResult:
    path: str
    report_path: str
    frames: int
    guides: int
    strands: int  # all strands in /World/hair
    vertices: int  # per strand
    rmse_mm: dict  # {"stereo": float or None, "ring": float or None}
    label_swaps: int  # None without truth
    filled: int  # marker-frames filled (interpolated + held)
    report: dict


def report_path_for(out_path):
    """The report's path: next to the cache, `<stem>.report.json`."""
    stem, _ = os.path.splitext(os.fspath(out_path))
    return stem + ".report.json"


@dataclass(frozen=True, eq=False)
class Markers:
    """The 3D stripe centres of a capture and how they were found (`solve_markers`)."""

    uv: np.ndarray  # (C, F, M, 2) labelled centroids, NaN where missing
    suspect: np.ndarray  # (C, F, M) bool: area off its median, or outvoted while labelling
    blob_counts: np.ndarray  # (C, F) regions found per image
    stereo: np.ndarray  # (F, M, 3) eq. 2 on the stereo pair, NaN where missing or rejected
    ring: np.ndarray  # (F, M, 3) every camera, NaN where missing or rejected
    views: np.ndarray  # (F, M) cameras used per ring point
    reprojection_px: np.ndarray  # (F, M) RMS reprojection error of ring points
    chain_rejected: dict  # {"stereo", "ring"}: (F, M) bool, points that broke their guide's chain
    filled: np.ndarray  # (F, M, 3) the chosen method's points with gaps filled
    interpolated: np.ndarray  # (F, M) bool
    held: np.ndarray  # (F, M) bool
    roots: np.ndarray  # (F, G, 3) the roots, riding on the head


def solve_markers(capture, params, head, progress=False):
    """Images to gap-filled 3D stripe centres: labelling, both triangulations, the chain check
    and gap filling (steps 1-4)."""
    F, M, C = len(capture.frames), capture.num_markers, len(capture.cameras)
    roots = head.to_world(np.broadcast_to(capture.roots, (F,) + capture.roots.shape).copy())
    uv, area, rejected, blob_counts = label_capture(capture, params, progress, roots)

    stereo = np.full((F, M, 3), np.nan)
    if capture.stereo is not None:
        left, right, baseline = capture.stereo
        cam_l = capture.cameras[left]
        stereo = camera_to_world(stereo_triangulate(uv[left], uv[right], cam_l.K, baseline), cam_l.world_to_camera)
    suspect = suspect_areas(area, params.area_ratio) | rejected
    ring, views, reproj = triangulate(uv.reshape(C, F * M, 2), capture.cameras, params.refine, params.outlier_px,
                                      suspect=suspect.reshape(C, F * M), consensus=params.consensus)
    ring, views, reproj = ring.reshape(F, M, 3), views.reshape(F, M), reproj.reshape(F, M)
    broken = {}
    for key, points in (("stereo", stereo), ("ring", ring)):
        broken[key] = chain_outliers(points, roots, capture, params.chain_tolerance) if params.chain_tolerance > 0 \
            else np.zeros((F, M), bool)
        points[broken[key]] = np.nan
    filled, interpolated, held = fill_gaps(ring if params.method == "ring" else stereo, params.max_gap)
    return Markers(uv, suspect, blob_counts, stereo, ring, views, reproj, broken, filled, interpolated, held, roots)


def build_strands(capture, markers, head, params):
    """Guides, interpolated strands and inner layers (steps 5-6), built in the head's frame.
    Returns (guides (F, G', V, 3), all strands (F, S, V, 3), both in the world, the guides kept
    (G',), the neighbour pairs (E, 2))."""
    F = len(capture.frames)
    guides, solved = guide_strands(capture, head.to_local(markers.filled), params)
    outer, edges = guides, np.zeros((0, 2), np.int64)
    if params.strands_between > 0 and guides.shape[1] >= 2:
        edges = strand_neighbours(capture.roots[solved], head.centre, params.neighbour_ratio)
        between = interpolate_strands(guides[:, edges[:, 0]], guides[:, edges[:, 1]], params.strands_between + 1)
        between = between.transpose(1, 2, 0, 3, 4).reshape(F, -1, params.vertices, 3)  # pair by pair
        outer = np.concatenate([guides, between], 1)
    inner = inner_layers(outer, params.layers, params.layer_spacing, head.centre)
    return head.to_world(guides), head.to_world(np.concatenate([outer, inner], 1)), solved, edges


def solve(capture_dir, out_path, params=None, progress=False, **options):
    """Solve a capture directory to a USD cache at `out_path` and a JSON report at
    `report_path_for(out_path)` (see REPORT_SCHEMA). `options` override fields of `params`
    (SolveParams), e.g. solve(dir, "hair.usdc", strands_between=3, layers=2).

    The cache holds /World/hair_guides (the captured guides) and /World/hair (guides, interpolated
    strands and inner layers, in that order), both BasisCurves with role `hair`; /World/hair_card,
    a Mesh of one card per /World/hair strand (role `hair_card`, with `st` texture coordinates); and
    the head (role `collider`) where the capture has one."""
    from io_usd.cache import CacheWriter, check_cache_path

    from . import __version__
    from .hair_cards import HairCards

    params = replace(params or SolveParams(), **options)
    if params.method not in ("ring", "stereo"):
        raise InputError("options", "method", f"expected ring or stereo, got {params.method!r}")
    if params.vertices < 2 or params.strands_between < 0 or params.layers < 0 or params.card_width <= 0:
        raise InputError("options", "vertices", "expected vertices >= 2, strands_between >= 0, layers >= 0, "
                                                "card_width > 0")
    check_cache_path(out_path)
    capture = load_capture(capture_dir)
    head = load_head(capture)
    markers = solve_markers(capture, params, head, progress)
    guides, hair, solved, edges = build_strands(capture, markers, head, params)

    F, V = len(capture.frames), params.vertices
    cards = HairCards.build(hair.shape[1], V)
    centres = head.to_world(np.broadcast_to(head.centre, (F, 1, 3)).copy())[:, 0]
    settings = {k: v for k, v in asdict(params).items() if not isinstance(v, dict)}
    settings.update({f"segment_{k}": v for k, v in asdict(params.segment).items()})
    settings.update({f"track_{k}": v for k, v in asdict(params.track).items()})
    settings["capture"] = os.path.abspath(capture.path)
    report = build_report(capture, params, markers, guides, solved, edges, hair.shape[1], out_path)
    with CacheWriter(out_path, capture.fps, int(capture.frames[0]), int(capture.frames[-1]),
                     settings={"capture": settings}, engine_version=__version__) as writer:
        if head.name is not None:
            writer.add_mesh(head.name, "collider", None, None, color=head.color, face_counts=head.face_counts,
                            face_indices=head.face_indices)
        writer.add_curves("hair_guides", "hair", np.full(guides.shape[1], V), np.full(guides.shape[1] * V,
                          params.strand_width), color=GUIDE_COLOR)
        writer.add_curves("hair", "hair", np.full(hair.shape[1], V), np.full(hair.shape[1] * V, params.strand_width),
                          color=HAIR_COLOR, ids=np.arange(hair.shape[1]))
        writer.add_mesh("hair_card", "hair_card", None, cards.faces, color=CARD_COLOR, uvs=cards.uvs)
        for f, frame in enumerate(capture.frames):
            samples = {"hair_guides": guides[f].reshape(-1, 3), "hair": hair[f].reshape(-1, 3),
                       "hair_card": cards.points(hair[f], centres[f], params.card_width)}
            if head.name is not None:
                samples[head.name] = head.points[f]
            writer.write_frame(int(frame), samples)
        writer.set_metadata("cfx:stats", _flat_stats(report))
    report_path = report_path_for(out_path)
    _write_json_atomically(report_path, report)
    swaps = report["label_swaps"]["count"] if report["label_swaps"] else None
    return SolveResult(os.fspath(out_path), report_path, F, guides.shape[1], hair.shape[1], V, report["rmse_mm"],
                       swaps, report["filled"]["count"], report)


# ==================================================================================================
# Report
# ==================================================================================================


REPORT_SCHEMA = """<stem>.report.json, beside the cache <stem>.usdc (solve's report_path):

capture, cache        absolute paths
frames, fps, method   time codes; "ring" or "stereo", the points the strands were built from
markers               marker names "<guide>:<stripe>", the order of every per-marker array
detections            {camera: {group, blobs (regions found, all frames), labelled (observations),
                       suspect (blob area off its median or outvoted), labelled_per_frame [F]}}
triangulated          {stereo, ring: marker-frames with a 3D point; of: frames x markers;
                       chain_rejected: {stereo, ring}; ring_views_mean; ring_reprojection_rms_px}
filled                {count = interpolated + held, interpolated, held, max_gap, never_seen [names],
                       frames: {marker: {interpolated: [time codes], held: [time codes]}}}
strands               {guides, guides_left_out [names], neighbour_pairs, interpolated, layers, total,
                       vertices}
With truth.npz (null otherwise):
rmse_mm               {stereo, ring: 3D error of the triangulated points (gaps not filled),
                       ring_filled: of the chosen method after gap filling}
marker_error_mm       {marker: {stereo_rmse, stereo_max, ring_rmse, ring_max, filled_max}}
label_swaps           {count: runs of observations labelled with another stripe's name, summed over
                       cameras, judged on labels not marked suspect; mislabelled: such observations;
                       count_with_suspect, mislabelled_with_suspect: the same over every label;
                       by_camera: {camera: {swaps, mislabelled, swaps_with_suspect,
                       mislabelled_with_suspect, events: [{frame, marker}]}}}
guide_distance_mm     {mean, max}: output guide vertices to the true guide strands
"""


def build_report(capture, params, markers, guides, solved, edges, num_strands, out_path):
    """The JSON report written next to the cache (see REPORT_SCHEMA)."""
    F, M = len(capture.frames), capture.num_markers
    names = capture.marker_names
    frames = capture.frames
    m = markers
    labelled = np.all(np.isfinite(m.uv), axis=3)  # (C, F, M)
    used = m.views >= 2
    report = {
        "capture": os.path.abspath(capture.path),
        "cache": os.path.abspath(os.fspath(out_path)),
        "frames": [int(f) for f in frames],
        "fps": capture.fps,
        "markers": names,
        "method": params.method,
        "detections": {cam.name: {"group": cam.group, "blobs": int(m.blob_counts[c].sum()),
                                  "labelled": int(labelled[c].sum()), "suspect": int(m.suspect[c].sum()),
                                  "labelled_per_frame": labelled[c].sum(1).tolist()}
                       for c, cam in enumerate(capture.cameras)},
        "triangulated": {"stereo": int(np.all(np.isfinite(m.stereo), -1).sum()),
                         "ring": int(np.all(np.isfinite(m.ring), -1).sum()),
                         "of": F * M,
                         "chain_rejected": {k: int(v.sum()) for k, v in m.chain_rejected.items()},
                         "ring_views_mean": float(m.views[used].mean()) if used.any() else 0.0,
                         "ring_reprojection_rms_px": _nanrms(m.reprojection_px)},
        "filled": {"count": int(m.interpolated.sum() + m.held.sum()), "interpolated": int(m.interpolated.sum()),
                   "held": int(m.held.sum()), "max_gap": params.max_gap,
                   "never_seen": [names[i] for i in np.nonzero(np.all(~np.isfinite(m.filled[..., 0]), 0))[0]],
                   "frames": {names[i]: {"interpolated": frames[m.interpolated[:, i]].tolist(),
                                         "held": frames[m.held[:, i]].tolist()}
                              for i in range(M) if m.interpolated[:, i].any() or m.held[:, i].any()}},
        "strands": {"guides": int(len(solved)),
                    "guides_left_out": [capture.guide_names[g] for g in range(len(capture.stripes)) if g not in solved],
                    "neighbour_pairs": int(len(edges)), "interpolated": int(len(edges) * params.strands_between),
                    "layers": params.layers, "total": int(num_strands), "vertices": params.vertices},
        "rmse_mm": {"stereo": None, "ring": None, "ring_filled": None},
        "marker_error_mm": None,
        "label_swaps": None,
        "guide_distance_mm": None,
    }
    truth = capture.truth_markers()
    if truth is None:
        return report
    gaps = m.interpolated | m.held
    report["rmse_mm"] = {"stereo": _rmse_mm(m.stereo, truth), "ring": _rmse_mm(m.ring, truth),
                         "ring_filled": _rmse_mm(m.filled, truth)}
    report["marker_error_mm"] = {
        names[i]: {"stereo_rmse": _rmse_mm(m.stereo[:, i], truth[:, i]),
                   "stereo_max": _max_mm(m.stereo[:, i], truth[:, i]),
                   "ring_rmse": _rmse_mm(m.ring[:, i], truth[:, i]),
                   "ring_max": _max_mm(m.ring[:, i], truth[:, i]),
                   "filled_max": _max_mm(np.where(gaps[:, i, None], m.filled[:, i], np.nan), truth[:, i])}
        for i in range(M)}
    by_camera = {}
    for c, cam in enumerate(capture.cameras):
        # a merged or half-hidden blob's centroid lies between stripes: judge identities on clean blobs
        clean = np.where(m.suspect[c][..., None], np.nan, m.uv[c])
        wrong, events = label_swaps(clean, cam.project(truth), capture.marker_channel, params.swap_tolerance_px)
        # the same judged on every label, suspect ones included, so the clean count hides nothing
        wrong_all, events_all = label_swaps(m.uv[c], cam.project(truth), capture.marker_channel,
                                            params.swap_tolerance_px)
        by_camera[cam.name] = {"swaps": int(events.sum()), "mislabelled": int(wrong.sum()),
                               "swaps_with_suspect": int(events_all.sum()),
                               "mislabelled_with_suspect": int(wrong_all.sum()),
                               "events": [{"frame": int(frames[f]), "marker": names[i]}
                                          for f, i in zip(*np.nonzero(events))]}
    report["label_swaps"] = {"count": sum(v["swaps"] for v in by_camera.values()),
                             "mislabelled": sum(v["mislabelled"] for v in by_camera.values()),
                             "count_with_suspect": sum(v["swaps_with_suspect"] for v in by_camera.values()),
                             "mislabelled_with_suspect": sum(v["mislabelled_with_suspect"] for v in by_camera.values()),
                             "by_camera": by_camera}
    if "guide_points" in capture.truth:
        report["guide_distance_mm"] = _guide_distance_mm(guides, capture.truth["guide_points"][:, solved])
    return report


def _nanrms(x):
    x = np.asarray(x, np.float64)
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x ** 2))) if x.size else None


def _rmse_mm(points, truth):
    d = np.linalg.norm(points - truth, axis=-1)
    return None if not np.isfinite(d).any() else 1e3 * _nanrms(d)


def _max_mm(points, truth):
    d = np.linalg.norm(points - truth, axis=-1)
    return None if not np.isfinite(d).any() else 1e3 * float(np.nanmax(d))


def _guide_distance_mm(strands, truth):
    """Distance from each output guide vertex to the true guide polyline: mean and max, mm."""
    truth = np.asarray(truth, np.float64)
    a, b = truth[:, :, None, :-1], truth[:, :, None, 1:]  # (F, G, 1, S, 3)
    p = strands[:, :, :, None]  # (F, G, V, 1, 3)
    ab = b - a
    t = np.clip(np.sum((p - a) * ab, -1) / np.maximum(np.sum(ab * ab, -1), 1e-300), 0.0, 1.0)
    d = np.linalg.norm(a + t[..., None] * ab - p, axis=-1)
    d = np.where(np.isfinite(d), d, np.inf).min(-1)
    d = d[np.isfinite(d)]
    return {"mean": 1e3 * float(d.mean()), "max": 1e3 * float(d.max())} if d.size else None


def _flat_stats(report):
    stats = {"strands": report["strands"]["total"], "guides": report["strands"]["guides"],
             "filled": report["filled"]["count"]}
    for k, v in report["rmse_mm"].items():
        if v is not None:
            stats[f"rmse_mm_{k}"] = v
    if report["label_swaps"] is not None:
        stats["label_swaps"] = report["label_swaps"]["count"]
    return stats


def _write_json_atomically(path, data):
    from io_usd.output_file import write_whole

    def write(tmp):
        with open(tmp, "w", encoding="utf-8") as f:
            json.dump(data, f, indent=1)
            f.write("\n")

    write_whole(path, write, suffix="")


def _progress(total, enabled, desc):
    from tqdm import tqdm

    return tqdm(total=total, unit="frame", desc=desc, file=sys.stderr, disable=not enabled, dynamic_ncols=True)


# ==================================================================================================
# Command line: cfx capture solve DIR -o OUT.usdc
# ==================================================================================================


def add_solve_arguments(parser):
    """The `cfx capture solve` options on an argparse (sub)parser."""
    d = SolveParams()
    parser.add_argument("capture", help="capture directory (capture.json, images/, background/)")
    parser.add_argument("-o", "--output", required=True, help="cache path (.usdc, .usd or .usda); the report is "
                                                              "written next to it as <stem>.report.json")
    parser.add_argument("--strands-between", type=int, default=d.strands_between,
                        help=f"strands interpolated between neighbouring guides (default {d.strands_between})")
    parser.add_argument("--layers", type=int, default=d.layers, help=f"inner layers (default {d.layers})")
    parser.add_argument("--card-width", type=float, default=d.card_width,
                        help=f"hair card width in metres (default {d.card_width})")
    parser.add_argument("--vertices", type=int, default=d.vertices,
                        help=f"vertices per output strand (default {d.vertices})")
    parser.add_argument("--method", choices=("ring", "stereo"), default=d.method,
                        help="3D markers the strands are built from (default ring: every camera)")
    parser.add_argument("--max-jump", type=float, default=d.track.max_jump_px,
                        help=f"pixels a stripe may move between frames (default {d.track.max_jump_px:g})")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bar")


def run_solve(args):
    """`cfx capture solve`: returns the exit status; bad input raises InputError (exit status 2)."""
    # the most a solve can hold: 1e8 strands between guides or vertices ran out of memory, 1e8 layers hung
    for flag, value, least, most in (("--strands-between", args.strands_between, 0, 64),
                                     ("--layers", args.layers, 0, 16), ("--vertices", args.vertices, 2, 1024)):
        if not least <= value <= most:
            raise InputError("command line", flag, f"expected {least} to {most}, got {value}")
    for flag, value, most in (("--card-width", args.card_width, 1.0), ("--max-jump", args.max_jump, 1e5)):
        if not 0 < value <= most:
            raise InputError("command line", flag, f"expected a number above 0 and at most {most:g}, got {value}")
    from io_usd.output_file import is_input

    for name in ("capture.json", "truth.npz", "simulation.usdc"):  # the cache would replace an input
        given = os.path.join(args.capture, name)
        if is_input(args.output, given):
            raise InputError(args.output, None, f"is the capture's {name}: choose another output")
    params = SolveParams(track=replace(TrackParams(), max_jump_px=args.max_jump, first_frame_px=args.max_jump),
                         method=args.method, vertices=args.vertices, strands_between=args.strands_between,
                         layers=args.layers, card_width=args.card_width)
    result = solve(args.capture, args.output, params, progress=not args.quiet)
    print(summary(result), file=sys.stderr)
    return 0


def summary(result):
    """A few lines for stderr: what was written and, for a synthetic capture, how well it matches."""
    r = result.report
    tri, filled = r["triangulated"], r["filled"]
    lines = [f"wrote {result.path}: {result.frames} frames, {result.guides} guides, {result.strands} strands "
             f"x {result.vertices} vertices, hair cards; report {result.report_path}",
             f"  markers triangulated: ring {tri['ring']}/{tri['of']}, stereo {tri['stereo']}/{tri['of']}; "
             f"filled {filled['interpolated']} interpolated + {filled['held']} held"]
    if r["label_swaps"] is not None:
        rmse = {k: "n/a" if v is None else f"{v:.2f} mm" for k, v in result.rmse_mm.items()}
        lines.append(f"  against truth: ring RMSE {rmse['ring']}, stereo RMSE {rmse['stereo']}, "
                     f"label swaps {result.label_swaps} ({r['label_swaps']['count_with_suspect']} counting the "
                     f"labels marked suspect, which triangulation down-weights)")
    return "\n".join(lines)
