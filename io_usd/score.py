"""Score a haircut against a target hairstyle: hair silhouettes from four views and strand lengths.

Hayashimoto, Mitani & Igarashi (§4.2.1) had trainees judge each cut mannequin against the target
hairstyle from four photographs: front, left, right and back. This module makes that judgement
automatic and repeatable. Both caches are rendered from the same four level cameras, framed on the
union of their hair and head, and compared in two ways:

- **silhouette**: per view, the hair's mask (the hair drawn flat, the head drawn as an occluder so hair
  hidden behind it does not count from that view, then closed by a disk of 1/160 of the image so
  the mask is the hairstyle's outline rather than the gaps between sparse strands) and the
  intersection over union
  IoU = |result ∩ target| / |result ∪ target| of the two masks (1 where both are empty);
- **strand length**: each target strand is matched to the result strand whose root is nearest,
  within 2 mm (roots stay on the scalp when hair is cut, so a cut strand keeps its match). The
  length agreement is

      A = 1 - mean_j min(1, |L_result,j - L_target,j| / L_target,j)

  over every target strand plus every result strand with no target root within 2 mm, an unmatched
  strand (erased in the result, or added) counting as error 1. Halving every strand gives A = 0.5.

The score is 100 x mean IoU x A, in [0, 100]; 100 means identical silhouettes and lengths.
"""

import os
import time
from dataclasses import dataclass, field

import numpy as np

from .cache import CacheReader
from .output_file import check_output_path, write_whole
from .preview import (
    BACKGROUND,
    Camera,
    SceneBuilder,
    VIEWS as PREVIEW_VIEWS,
    SupersampledOffscreen,
    _font,
    _pyrender,
    build_scene,
    contact_sheet,
)

# the four level views' camera yaws about +Y, from +Z, as the preview names them
VIEWS = tuple((name, PREVIEW_VIEWS[name][0]) for name in ("front", "left", "right", "back"))
ROOT_TOLERANCE = 0.002  # m, how far a result root may be from a target root and still be the same strand
HEAD_REACH = 0.08  # m, collider/face points this close to the hair roots' box are the head, framed with the hair
CONTEXT_ROLES = ("collider", "face")  # drawn as occluders and for context; cloth and hair cards are left out

# difference image: hair in both, only in the result, only in the target, the head, the background
BOTH, RESULT_ONLY, TARGET_ONLY = (120, 120, 120), (215, 45, 40), (40, 95, 225)
HEAD_SHADE = (205, 205, 202)


@dataclass
class ViewScore:
    """One camera: the silhouette masks (H, W) bool, the shaded renders (H, W, 3) uint8 and their IoU."""

    name: str
    camera: Camera
    iou: float
    result_mask: np.ndarray
    target_mask: np.ndarray
    head_mask: np.ndarray  # where either cache's head is, for context in the difference image
    result_image: np.ndarray  # None when scored with images=False
    target_image: np.ndarray

    def difference(self):
        """(H, W, 3) uint8: hair in both grey, only in the result red, only in the target blue."""
        return difference_image(self.result_mask, self.target_mask, self.head_mask)


@dataclass
class ScoreReport:
    result_path: str
    target_path: str
    result_frame: int
    target_frame: int
    views: list
    length_agreement: float  # A in the module docstring
    matched_fraction: float  # target strands with a result root within ROOT_TOLERANCE
    result_strands: int
    target_strands: int
    score: float  # 100 x mean IoU x length_agreement
    seconds: float = 0.0
    relative_length_errors: np.ndarray = field(default=None, repr=False)  # per target strand, NaN unmatched

    @property
    def ious(self):
        return {v.name: v.iou for v in self.views}

    @property
    def mean_iou(self):
        return float(np.mean([v.iou for v in self.views]))

    def table(self):
        lines = [f"result {self.result_path} (frame {self.result_frame}, {self.result_strands} strands)",
                 f"target {self.target_path} (frame {self.target_frame}, {self.target_strands} strands)",
                 f"  {'view':<8}{'IoU':>7}"]
        lines += [f"  {v.name:<8}{v.iou:7.3f}" for v in self.views]
        lines += [f"  {'mean':<8}{self.mean_iou:7.3f}",
                  (f"  length agreement {self.length_agreement:.3f} "
                   f"({100 * self.matched_fraction:.1f}% of target strands matched by root within "
                   f"{1e3 * ROOT_TOLERANCE:g} mm)"),
                  f"  score {self.score:.1f} / 100  (100 x mean IoU x length agreement)"]
        return "\n".join(lines)


# -- strands ----------------------------------------------------------------------------------------
def _counts(reader, name, frame):
    """curveVertexCounts at `frame`: a cut changes them over time where the reader knows per-frame counts."""
    per_frame = getattr(reader, "counts", None)
    counts = per_frame(name, frame) if callable(per_frame) else reader.prims[name].counts
    return np.asarray(counts, np.int64)


def strand_roots_and_lengths(points, counts):
    """Roots (S, 3) and polyline lengths (S,) of strands flattened as USD curves; empty strands have
    a NaN root and length 0."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    counts = np.asarray(counts, np.int64)
    roots, lengths = np.full((len(counts), 3), np.nan), np.zeros(len(counts))
    if len(points) == 0:
        return roots, lengths
    strand = np.repeat(np.arange(len(counts)), counts)
    segment = np.linalg.norm(np.diff(points, axis=0), axis=1)
    inside = strand[1:] == strand[:-1]  # segments that do not jump from one strand's tip to the next root
    lengths += np.bincount(strand[:-1][inside], weights=segment[inside], minlength=len(counts))
    starts = np.cumsum(counts) - counts
    roots[counts > 0] = points[starts[counts > 0]]
    return roots, lengths


def length_agreement(result_roots, result_lengths, target_roots, target_lengths, tolerance=ROOT_TOLERANCE):
    """(A, matched fraction, per-target-strand relative error with NaN where unmatched); see the
    module docstring for A."""
    from scipy.spatial import cKDTree

    r_ok, t_ok = np.isfinite(result_roots).all(1), np.isfinite(target_roots).all(1)
    errors = np.full(len(target_roots), np.nan)
    if not r_ok.any() or not t_ok.any():
        extra = int(r_ok.sum())
        total = len(target_roots) + extra
        return (1.0 if total == 0 else 0.0), 0.0, errors
    r_index, t_index = np.flatnonzero(r_ok), np.flatnonzero(t_ok)
    distance, nearest = cKDTree(result_roots[r_ok]).query(target_roots[t_ok], distance_upper_bound=tolerance)
    hit = np.isfinite(distance)
    matched_t, matched_r = t_index[hit], r_index[nearest[hit]]
    target_l = target_lengths[matched_t]
    errors[matched_t] = np.abs(result_lengths[matched_r] - target_l) / np.maximum(target_l, 1e-9)
    # result strands with no target root near them were added: they count against the result too
    distance_back, _ = cKDTree(target_roots[t_ok]).query(result_roots[r_ok], distance_upper_bound=tolerance)
    extra = int(np.sum(~np.isfinite(distance_back)))
    total = len(target_roots) + extra
    agreement = float(np.sum(1.0 - np.minimum(1.0, errors[matched_t])) / total)
    return agreement, float(hit.sum() / max(len(target_roots), 1)), errors


# -- caches -----------------------------------------------------------------------------------------
@dataclass
class _Side:
    """One cache at the frame being scored."""

    reader: CacheReader
    frame: int
    hair: list
    context: list

    def points(self, names):
        chunks = [self.reader.points(n, self.frame).reshape(-1, 3) for n in names]
        chunks = [c for c in chunks if len(c)]
        return np.concatenate(chunks).astype(np.float64) if chunks else np.zeros((0, 3))

    def strands(self):
        roots, lengths = [], []
        for name in self.hair:
            points, counts = self.reader.points(name, self.frame), _counts(self.reader, name, self.frame)
            if int(counts.sum()) != len(points):
                raise ValueError(f"{self.reader.path}: {name}: curveVertexCounts add up to {int(counts.sum())} "
                                 f"at frame {self.frame}, but the prim has {len(points)} points")
            r, length = strand_roots_and_lengths(points, counts)
            roots.append(r)
            lengths.append(length)
        return np.concatenate(roots), np.concatenate(lengths)


def _open(path, frame):
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{path}: no such cache file")
    reader = CacheReader(path)
    # the simulated strands: render children (drawn from them each frame) would count as strands of
    # their own, unmatched in a cache without them
    hair = [n for n, p in reader.prims.items() if p.role == "hair" and p.kind == "curves" and not p.interpolated_from]
    if not hair:
        found = ", ".join(f"{n} ({p.role})" for n, p in reader.prims.items()) or "none"
        raise ValueError(f"{path}: no hair prim (cfx:role 'hair' curves) to score; cfx prims: {found}")
    context = [n for n, p in reader.prims.items() if p.role in CONTEXT_ROLES and p.kind == "mesh"]
    available = sorted({f for n in hair for f in reader.frames(n)})
    if frame is None:
        frame = available[-1]
    elif int(frame) not in available:
        raise ValueError(f"{path}: frame {frame} has no hair samples (the hair's frames are {available[0]} to "
                         f"{available[-1]}, {len(available)} in all)")
    return _Side(reader, int(frame), hair, context)


def _framing_points(sides, roots):
    """Hair of both caches, plus the part of each head within HEAD_REACH of the box around the
    hair roots `roots` (a collider may be a whole body)."""
    hair = np.concatenate([s.points(s.hair) for s in sides])
    roots = roots[np.isfinite(roots).all(1)]
    if len(hair) == 0:
        hair = np.concatenate([s.points(s.context) for s in sides])
    if len(roots) == 0:
        return hair
    lo, hi = roots.min(0) - HEAD_REACH, roots.max(0) + HEAD_REACH
    head = np.concatenate([s.points(s.context) for s in sides])
    head = head[np.all((head >= lo) & (head <= hi), axis=1)]
    return np.concatenate([hair, head]) if len(hair) or len(head) else hair


def view_cameras(points, width, height, yfov=0.5, margin=1.08):
    """{view name: Camera} for the four views, level, each framing `points`."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if len(points) == 0:
        points = np.array([[x, y, z] for x in (-0.1, 0.1) for y in (-0.1, 0.1) for z in (-0.1, 0.1)])
    lo, hi = points.min(0), points.max(0)
    return {name: Camera.frame_bounds(lo, hi, width, height, yaw_degrees=yaw, pitch_degrees=0.0, yfov=yfov,
                                      margin=margin) for name, yaw in VIEWS}


# -- rendering --------------------------------------------------------------------------------------
def _disk(radius):
    r = int(radius)
    y, x = np.mgrid[-r:r + 1, -r:r + 1]
    return x * x + y * y <= r * r + r


def close_mask(mask, radius):
    """Morphological closing by a disk: fills the gaps between strands narrower than about 2 radius."""
    if radius < 1:
        return mask
    from scipy import ndimage

    pad = int(radius) + 1
    padded = np.pad(mask, pad)
    return ndimage.binary_closing(padded, structure=_disk(radius))[pad:-pad, pad:-pad]


class _Renderer:
    """One GL context: per cache and camera a shaded image and, from the same pyrender scene, a
    segmentation pass with the hair in red and the head in green (flat, no lighting)."""

    def __init__(self, width, height):
        self.pyrender = _pyrender()
        self.gl = SupersampledOffscreen(width, height)

    def render(self, builder, side, camera, shaded=True):
        """(shaded image or None, hair mask, head mask). The flat pass costs a few percent of the
        shaded one on software GL."""
        pr = self.pyrender
        scene = build_scene(builder, side.frame, camera)
        image = None
        if shaded:
            image = self.gl.render(scene, pr.RenderFlags.SHADOWS_DIRECTIONAL)
        hair = set(side.hair)
        colours = {node: ((255, 0, 0) if node.name in hair else (0, 255, 0)) for node in scene.mesh_nodes}
        seg = self.gl.render(scene, pr.RenderFlags.SEG, seg_node_map=colours)
        return image, seg[:, :, 0] > 127, seg[:, :, 1] > 127

    def close(self):
        self.gl.delete()


def iou(a, b):
    """|a ∩ b| / |a ∪ b| of two boolean masks; 1 when both are empty (they agree there is nothing)."""
    union = int(np.count_nonzero(a | b))
    return 1.0 if union == 0 else float(np.count_nonzero(a & b)) / union


def difference_image(result_mask, target_mask, head_mask=None):
    image = np.empty((*result_mask.shape, 3), np.uint8)
    image[:] = np.round(255 * np.asarray(BACKGROUND)).astype(np.uint8)
    if head_mask is not None:
        image[head_mask] = HEAD_SHADE
    image[result_mask & target_mask] = BOTH
    image[result_mask & ~target_mask] = RESULT_ONLY
    image[target_mask & ~result_mask] = TARGET_ONLY
    return image


def score_caches(result, target, frame=None, size=(480, 480), images=True):
    """Score the hair of cache `result` against cache `target` (paths); see the module docstring.

    frame: the frame of both caches (default: each cache's last hair frame). size: (width, height)
    of each view's render. images=False skips the shaded renders the report shows (the score needs
    only the flat masks, which are about ten times faster on software GL). Raises FileNotFoundError
    or ValueError naming the file for bad input."""
    started = time.perf_counter()
    width, height = (int(v) for v in size)
    if width < 16 or height < 16:
        raise ValueError(f"size: each view must be at least 16x16 pixels, got {width}x{height}")
    sides = [_open(result, frame), _open(target, frame)]

    (r_roots, r_lengths), (t_roots, t_lengths) = (s.strands() for s in sides)
    agreement, matched, errors = length_agreement(r_roots, r_lengths, t_roots, t_lengths)

    cameras = view_cameras(_framing_points(sides, np.concatenate([r_roots, t_roots])), width, height)
    radius = max(1, round(min(width, height) / 160))
    builders = [SceneBuilder(s.reader, names=s.hair + s.context) for s in sides]
    renderer = _Renderer(width, height)
    views = []
    try:
        for name, camera in cameras.items():
            (r_image, r_hair, r_head), (t_image, t_hair, t_head) = (
                renderer.render(b, s, camera, images) for b, s in zip(builders, sides))
            r_hair, t_hair = close_mask(r_hair, radius), close_mask(t_hair, radius)
            views.append(ViewScore(name, camera, iou(r_hair, t_hair), r_hair, t_hair, r_head | t_head,
                                   r_image, t_image))
    finally:
        renderer.close()

    score = 100.0 * float(np.mean([v.iou for v in views])) * agreement
    return ScoreReport(sides[0].reader.path, sides[1].reader.path, sides[0].frame, sides[1].frame, views, agreement,
                       matched, len(r_lengths), len(t_lengths), float(np.clip(score, 0.0, 100.0)),
                       time.perf_counter() - started, errors)


# -- report -----------------------------------------------------------------------------------------
def report_image(report):
    """The report as a PIL image: a header with the score, then one column per view (result,
    target, difference) with the view's IoU under it."""
    from PIL import Image, ImageDraw

    views = report.views
    if any(v.result_image is None or v.target_image is None for v in views):
        raise ValueError(f"{report.result_path}: the report needs the shaded renders; score with images=True")
    h, w = views[0].result_mask.shape
    tiles, labels = [], []
    for row, title in (("result_image", "result"), ("target_image", "target"), (None, "difference")):
        for v in views:
            tiles.append(getattr(v, row) if row else v.difference())
            labels.append(f"{v.name} · {title}")
    grid = contact_sheet(tiles, labels, columns=len(views))

    font, big, small = _font(max(12, h // 18)), _font(max(16, h // 12)), _font(max(10, h // 24))
    pad = max(6, h // 40)
    line, big_line, small_line = (_text_height(f) + pad // 2 for f in (font, big, small))
    header_h = 2 * pad + big_line + 3 * small_line
    footer_h = 2 * pad + line
    fill = tuple(round(255 * c) for c in BACKGROUND)
    sheet = Image.new("RGB", (grid.width, header_h + grid.height + footer_h), fill)
    sheet.paste(grid, (0, header_h))
    draw = ImageDraw.Draw(sheet)
    dark = (30, 30, 30)

    draw.text((pad, pad), f"Haircut score {report.score:.1f} / 100", fill=dark, font=big)
    summary = (f"= 100 x mean silhouette IoU {report.mean_iou:.3f} x length agreement {report.length_agreement:.3f}"
               f"   ({100 * report.matched_fraction:.0f}% of {report.target_strands} target strands matched by root)")
    y = pad + big_line
    draw.text((pad, y), summary, fill=dark, font=small)
    y += small_line
    draw.text((pad, y), f"result: {os.path.basename(report.result_path)} (frame {report.result_frame})    "
                        f"target: {os.path.basename(report.target_path)} (frame {report.target_frame})",
              fill=dark, font=small)
    y += small_line
    x = pad
    for colour, text in ((RESULT_ONLY, "hair only in the result (too long / extra)"),
                         (TARGET_ONLY, "hair only in the target (cut too short / missing)"),
                         (BOTH, "hair in both")):
        box = small_line - pad // 3
        draw.rectangle([x, y + 2, x + box, y + box], fill=colour)
        draw.text((x + box + pad // 2, y), text, fill=dark, font=small)
        x += box + pad + int(draw.textlength(text, font=small)) + 2 * pad

    y = header_h + grid.height + pad
    for k, v in enumerate(views):
        text = f"{v.name}: IoU {v.iou:.3f}"
        width = draw.textlength(text, font=font)
        draw.text((k * w + 0.5 * (w - width), y), text, fill=_iou_colour(v.iou), font=font)
    return sheet


def _text_height(font):
    from PIL import Image, ImageDraw

    box = ImageDraw.Draw(Image.new("L", (1, 1))).textbbox((0, 0), "Hgy", font=font)
    return box[3] - box[1]


def _iou_colour(value):
    """Dark green for a close match through amber to red for a poor one."""
    t = float(np.clip((value - 0.5) / 0.5, 0.0, 1.0))
    return tuple(round(a + (b - a) * t) for a, b in zip((190, 40, 30), (30, 130, 50)))


def write_report(report, path):
    """Write the report PNG to `path` (the file appears only once fully written); returns path."""
    path = check_report_path(path)
    return write_whole(path, lambda tmp: report_image(report).save(tmp, format="PNG"))


def check_report_path(path):
    """InputError unless a report PNG may be written at `path` (output_file.check_output_path)."""
    return check_output_path(path, (".png",), "the score report")


__all__ = ["ROOT_TOLERANCE", "VIEWS", "ScoreReport", "ViewScore", "check_report_path", "close_mask",
           "difference_image", "iou", "length_agreement", "report_image", "score_caches", "strand_roots_and_lengths",
           "view_cameras", "write_report"]
