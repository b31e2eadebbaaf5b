"""Hair motion capture: segmentation, labelling, triangulation, gap filling, cleaning, densification,
hair cards, and the whole solve on a small capture drawn here from known 3D strands."""

import argparse
import json
import math
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from sim.capture_rig import CaptureCamera
from sim.capture_solve import (Blobs, LabelTracker, SegmentParams, TrackParams, camera_to_world,
                               fill_gaps, inner_layers, interpolate_strands, label_swaps, load_capture,
                               normalise_lengths, reject_kinks, resample_strands, segment_angles, segment_image,
                               stereo_triangulate, strand_neighbours, triangulate)
from sim.errors import InputError
from sim.hair_cards import HairCards

from capture_scenes import tiny_capture_scene  # tests/capture_scenes.py

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
from capture import segment_whole_image  # noqa: E402  (benchmarks/capture.py: the whole-image peer)

COLORS = {"red": (0.85, 0.1, 0.08), "green": (0.1, 0.72, 0.15), "blue": (0.1, 0.15, 0.85)}
BACKGROUND = 0.92


# --------------------------------------------------------------------------------------------------
# A small capture drawn with numpy
# --------------------------------------------------------------------------------------------------


def look_at(eye, target, up=(0.0, 1.0, 0.0)):
    """OpenCV world_to_camera: x right, y down, z toward the target."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    M = np.eye(4)
    M[:3, :3] = np.stack([x, y, z])
    M[:3, 3] = -M[:3, :3] @ eye
    return M


def intrinsics(f=360.0, size=(320, 240)):
    return np.array([[f, 0.0, size[0] / 2], [0.0, f, size[1] / 2], [0.0, 0.0, 1.0]])


def rig_cameras(size=(320, 240), baseline=0.12):
    K = intrinsics(size=size)
    left = look_at((-baseline / 2, 0.02, 0.7), (-baseline / 2, 0.02, 0.0))
    right = left.copy()
    right[:3, 3] -= [baseline, 0.0, 0.0]  # centre `baseline` along the left camera's +x
    cams = [CaptureCamera("stereo_l", "stereo", K, left), CaptureCamera("stereo_r", "stereo", K, right)]
    target = np.array([0.0, 0.02, 0.0])
    for name, azimuth, elevation in (("ring_a", -45, 5), ("ring_b", 45, -5), ("ring_c", 150, 10), ("ring_d", 10, 40)):
        a, e = math.radians(azimuth), math.radians(elevation)
        eye = target + 0.7 * np.array([math.sin(a) * math.cos(e), math.sin(e), math.cos(a) * math.cos(e)])
        cams.append(CaptureCamera(name, "ring", K, look_at(eye, target)))
    return cams


HEAD_CENTRE = np.array([0.0, -0.02, -0.1])


def head_rotation(t, degrees=6.0):
    """The head turns about the vertical axis through its centre."""
    a = math.radians(degrees) * math.sin(2.0 * math.pi * 0.8 * t)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def strand_points(root, t, g, length, samples=240):
    """A hanging guide in the head's frame: a gentle arc swinging about its root."""
    s = np.linspace(0.0, length, samples)
    swing = 0.25 * math.sin(2.0 * math.pi * 1.1 * t + 1.3 * g)
    bend = 2.0 + 1.5 * g  # 1/m
    a = swing + bend * s
    b = 0.4 * (g - 1)
    d = np.stack([np.sin(a) * math.cos(b), -np.cos(a), np.sin(a) * math.sin(b) + 0.15], 1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ds = np.diff(s, prepend=0.0)[:, None]
    return root + np.cumsum(d * ds, 0), s


def stripe_centre(points, s, lo, hi):
    """Arc-length weighted centroid of the centre line over s in [lo, hi)."""
    mid = 0.5 * (points[1:] + points[:-1])
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    sm = 0.5 * (s[1:] + s[:-1])
    w = seg * ((sm >= lo) & (sm < hi))
    return (mid * w[:, None]).sum(0) / w.sum()


def draw_polyline(image, uv, color, radius, caps=False):
    """Anti-aliased stroke of `radius` px along a 2D polyline, composited over the image. Its ends are
    cut square (so consecutive stripes share their boundary), or rounded with `caps` (a disc from a
    one-point polyline)."""
    h, w = image.shape[:2]
    lo = np.floor(uv.min(0) - radius - 2).astype(int)
    hi = np.ceil(uv.max(0) + radius + 2).astype(int)
    lo, hi = np.maximum(lo, 0), np.minimum(hi, [w, h])
    if np.any(hi <= lo):
        return
    cols, rows = np.meshgrid(np.arange(lo[0], hi[0]) + 0.5, np.arange(lo[1], hi[1]) + 0.5)
    p = np.stack([cols.ravel(), rows.ravel()], 1)
    if caps:
        uv = np.concatenate([uv, uv[-1:] + 1e-9])
    a, b = uv[:-1], uv[1:]
    ab = b - a
    length = np.maximum(np.linalg.norm(ab, axis=1), 1e-12)
    along = ((p[:, None] - a[None]) * ab[None]).sum(-1) / length  # px from a, along the segment
    t = np.clip(along / length, 0, 1)
    d = np.linalg.norm(a[None] + t[..., None] * ab[None] - p[:, None], axis=-1)
    cover = np.clip(radius + 0.5 - d, 0.0, 1.0)  # round joins
    if not caps:  # square ends of the whole polyline
        cover[:, 0] *= np.clip(along[:, 0] + 0.5, 0.0, 1.0)
        cover[:, -1] *= np.clip(length[-1] - along[:, -1] + 0.5, 0.0, 1.0)
    cover = cover.max(1)
    cover = cover.reshape(rows.shape)[..., None]
    region = image[lo[1]:hi[1], lo[0]:hi[0]]
    region[:] = cover * np.asarray(color) + (1.0 - cover) * region


def make_capture(folder, frames=8, guides=3, stripes=3, width=0.04, size=(320, 240), hidden=(), specks=True,
                 head=True):
    """Write a capture directory. hidden: (camera index or None for all, guide, stripe, frame index)."""
    import imageio.v3 as iio

    os.makedirs(folder, exist_ok=True)
    cams = rig_cameras(size)
    colors = ["red", "green", "blue"]
    fps = 24.0
    codes = list(range(1, frames + 1))
    dirs = [np.array([x, 0.55, 0.85]) for x in np.linspace(-0.6, 0.6, guides)]
    roots0 = np.array([HEAD_CENTRE + 0.1 * d / np.linalg.norm(d) for d in dirs])
    length = stripes * width + 0.02
    centres = np.full((frames, guides, stripes, 3), np.nan)
    dense = []
    for f in range(frames):
        t = f / fps
        R = head_rotation(t)
        per_guide = []
        for g in range(guides):
            local, s = strand_points(roots0[g], t, g, length)
            world = (local - HEAD_CENTRE) @ R.T + HEAD_CENTRE
            per_guide.append((world, s))
            for k in range(stripes):
                centres[f, g, k] = stripe_centre(world, s, k * width, (k + 1) * width)
        dense.append(per_guide)
    hide = set(hidden)
    occluded = np.zeros((frames, len(cams), guides, stripes), bool)
    rng = np.random.default_rng(3)
    bg = np.full((size[1], size[0], 3), BACKGROUND, np.float64)
    bg[150:200, 20:70] = (0.8, 0.15, 0.1)  # a red object in the scene, not hair
    os.makedirs(os.path.join(folder, "background"), exist_ok=True)
    labels = {}
    for c, cam in enumerate(cams):
        iio.imwrite(os.path.join(folder, "background", f"{cam.name}.png"), np.round(bg * 255).astype(np.uint8))
        os.makedirs(os.path.join(folder, "images", cam.name), exist_ok=True)
        for f in range(frames):
            image = bg.copy()
            strokes = []
            for g in range(guides):
                world, s = dense[f][g]
                for k in range(stripes):
                    if (None, g, k, f) in hide or (c, g, k, f) in hide:
                        occluded[f, c, g, k] = True
                        continue
                    along = np.linspace(k * width, (k + 1) * width, 17)
                    pts = np.stack([np.interp(along, s, world[:, i]) for i in range(3)], 1)
                    depth = cam.to_camera(pts)[:, 2].mean()
                    strokes.append((depth, cam.project(pts), COLORS[colors[k % 3]]))
            for _, uv, color in sorted(strokes, key=lambda x: -x[0]):  # far first
                draw_polyline(image, uv, color, 1.6)
            if specks:  # dust: two-pixel dots of dye colour
                for _ in range(6):
                    r, q = rng.integers(5, size[1] - 5), rng.integers(5, size[0] - 5)
                    image[r:r + 1, q:q + 2] = COLORS[colors[rng.integers(3)]]
            iio.imwrite(os.path.join(folder, "images", cam.name, f"{codes[f]:04d}.png"),
                        np.round(np.clip(image, 0, 1) * 255).astype(np.uint8))
        named = []
        for g in range(guides):
            for k in range(stripes):
                if not occluded[0, c, g, k]:
                    uv = cam.project(centres[0, g, k]) + rng.normal(0.0, 1.0, 2)  # an operator's click
                    named.append({"guide": g, "stripe": k, "uv": uv.tolist()})
        labels[cam.name] = named
    doc = {
        "version": 1, "fps": fps, "frames": codes, "image_size": list(size), "units": "m",
        "stripe": {"width": width, "colors": colors},
        "guides": [{"name": f"g{g:02d}", "root": roots0[g].tolist(), "stripes": stripes} for g in range(guides)],
        "cameras": [{"name": c.name, "group": c.group, "K": c.K.tolist(), "world_to_camera": c.world_to_camera.tolist()}
                    for c in cams],
        "stereo": {"left": "stereo_l", "right": "stereo_r", "baseline": 0.12},
        "first_frame_labels": labels,
    }
    with open(os.path.join(folder, "capture.json"), "w") as fh:
        json.dump(doc, fh)
    guide_points = np.stack([np.stack([w[::8] for w, _ in per]) for per in dense])
    np.savez(os.path.join(folder, "truth.npz"), stripe_centres=centres, guide_points=guide_points,
             frames=np.array(codes), occluded=occluded)
    if head:
        write_head(os.path.join(folder, "simulation.usdc"), codes, fps)
    return doc, centres


def write_head(path, codes, fps):
    import trimesh

    from io_usd.cache import CacheWriter

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    with CacheWriter(path, fps, codes[0], codes[-1]) as w:
        w.add_mesh("head", "collider", None, sphere.faces, color=(0.8, 0.7, 0.6))
        for f, code in enumerate(codes):
            R = head_rotation(f / fps)
            w.write_frame(code, {"head": sphere.vertices @ R.T + HEAD_CENTRE})


@pytest.fixture(scope="module")
def solved(tmp_path_factory):
    from sim.capture_solve import solve

    folder = tmp_path_factory.mktemp("capture")
    # stripe 2 of guide 1 hidden from every camera on frames 3-4 (a two-frame gap); stripe 1 of guide 0
    # hidden from the left stereo camera on frame 6 (stereo loses it, the ring does not)
    hidden = [(None, 1, 2, 3), (None, 1, 2, 4), (0, 0, 1, 6)]
    doc, centres = make_capture(str(folder / "cap"), hidden=hidden)
    out = folder / "out" / "hair.usdc"
    result = solve(str(folder / "cap"), str(out), strands_between=2, layers=1, vertices=12)
    return result, doc, centres, folder


# --------------------------------------------------------------------------------------------------
# 3. Triangulation
# --------------------------------------------------------------------------------------------------


def test_parallel_stereo_formulas_recover_a_point_exactly():
    K = np.array([[800.0, 0.0, 310.0], [0.0, 780.0, 250.0], [0.0, 0.0, 1.0]])
    left = look_at((0.1, 0.3, 1.2), (0.0, 0.1, 0.0))
    b = 0.15
    right = left.copy()
    right[:3, 3] -= [b, 0.0, 0.0]
    cl, cr = CaptureCamera("l", "stereo", K, left), CaptureCamera("r", "stereo", K, right)
    points = np.random.default_rng(0).uniform(-0.2, 0.2, (50, 3))
    uvl, uvr = cl.project(points), cr.project(points)
    assert np.allclose(uvl[:, 1], uvr[:, 1])  # rectified: same rows
    cam = stereo_triangulate(uvl, uvr, K, b)
    np.testing.assert_allclose(cam, cl.to_camera(points), atol=1e-9)
    np.testing.assert_allclose(camera_to_world(cam, left), points, atol=1e-9)
    # the paper's eq. 2 verbatim for square pixels: X = b u/(u-u'), Y = b v/(u-u'), Z = b f/(u-u')
    Ks = K.copy()
    Ks[1, 1] = Ks[0, 0]
    cl, cr = CaptureCamera("l", "stereo", Ks, left), CaptureCamera("r", "stereo", Ks, right)
    u, v = (cl.project(points) - Ks[:2, 2]).T
    u2 = cr.project(points)[:, 0] - Ks[0, 2]
    expected = np.stack([b * u / (u - u2), b * v / (u - u2), b * Ks[0, 0] / (u - u2)], 1)
    np.testing.assert_allclose(stereo_triangulate(cl.project(points), cr.project(points), Ks, b), expected, atol=1e-12)


def test_multiview_triangulation_recovers_points_exactly_without_noise():
    cams = rig_cameras()
    points = np.random.default_rng(1).uniform(-0.1, 0.1, (40, 3))
    uv = np.stack([c.project(points) for c in cams])
    uv[2:, :10] = np.nan  # the first ten points seen by two cameras only
    uv[0, 10:20] = np.nan
    for refine in (False, True):
        x, views, rms = triangulate(uv, cams, refine=refine)
        np.testing.assert_allclose(x, points, atol=1e-9)
        assert np.all(views[:10] == 2) and np.all(views[10:20] == 5) and np.all(views[20:] == 6)
        assert np.nanmax(rms) < 1e-6
    uv[1, :5] = np.nan  # one view left: no point
    x, views, _ = triangulate(uv, cams)
    assert np.all(np.isnan(x[:5])) and np.all(views[:5] < 2)


def test_triangulation_drops_a_view_whose_centroid_is_off():
    cams = rig_cameras()
    points = np.random.default_rng(2).uniform(-0.1, 0.1, (10, 3))
    uv = np.stack([c.project(points) for c in cams])
    uv[3, :, 0] += 12.0  # one camera's centroids shifted (a partly hidden stripe)
    x, views, _ = triangulate(uv, cams, outlier_px=3.0)
    np.testing.assert_allclose(x, points, atol=1e-9)
    assert np.all(views == 5)


# --------------------------------------------------------------------------------------------------
# 1. Segmentation
# --------------------------------------------------------------------------------------------------


def test_segmentation_finds_blob_centroids_ignores_specks_and_the_background():
    h, w = 120, 200
    bg = np.full((h, w, 3), BACKGROUND)
    bg[80:110, 150:190] = COLORS["red"]  # red, but part of the background
    image = bg.copy()
    blobs = [("red", (30.3, 25.7), 5.2), ("green", (80.6, 40.2), 4.0), ("blue", (120.1, 70.9), 6.5),
             ("red", (60.45, 90.15), 3.5)]
    for color, centre, radius in blobs:
        draw_polyline(image, np.array([centre]), COLORS[color], radius, caps=True)  # a disc
    draw_polyline(image, np.array([[20.0, 100.0], [60.0, 108.0]]), COLORS["blue"], 1.6)  # a stroke
    image[10:12, 180:182] = COLORS["green"]  # specks: 4 pixels
    image[50, 100] = COLORS["red"]
    found = segment_image(image.astype(np.float32), bg.astype(np.float32), SegmentParams(min_area_px=12))
    assert len(found) == 5
    expected = [(c, np.array(uv)) for c, uv, _ in blobs] + [("blue", np.array([40.0, 104.0]))]
    names = ("red", "green", "blue")
    for color, uv in expected:
        same = found.channel == names.index(color)
        d = np.linalg.norm(found.uv[same] - uv, axis=1).min()
        assert d < 0.5, (color, uv, d)
    assert found.records()[0][0] in names and all(a >= 12 for a in found.area)
    # without the background image the red background object is found too
    assert len(segment_image(image.astype(np.float32), None)) == 6


@pytest.mark.parametrize("closing, median", [(1, 3), (0, 1), (2, 5), (3, 3)])
def test_segmentation_in_a_window_finds_what_the_whole_image_does(closing, median):
    """Blobs and strokes inside the image and against each of its edges, speckle and noise, with and
    without the background: the same regions in the same order, areas and centroids to the bit."""
    rng = np.random.default_rng(closing * 10 + median)
    h, w = 90, 140
    names = list(COLORS)
    params = SegmentParams(closing_px=closing, median_px=median, min_area_px=4)
    for inset in (-3.0, 15.0):  # discs anywhere (some cut by an edge), or all inside, away from the edges
        bg = np.full((h, w, 3), BACKGROUND) + rng.normal(0.0, 0.01, (h, w, 3))
        image = bg.copy()
        for _ in range(12):
            centre = rng.uniform([inset, inset], [w - inset, h - inset])
            draw_polyline(image, centre[None], COLORS[names[rng.integers(3)]], rng.uniform(1.0, 6.0), caps=True)
        lines = ([[0.0, 40.0], [30.0, 45.0]], [[w - 1.0, 10.0], [w - 20.0, 80.0]], [[50.0, 0.0], [60.0, 12.0]],
                 [[70.0, h - 1.0], [100.0, h - 8.0]])
        for line in (np.clip(line, inset, [w - inset, h - inset]) for line in lines):
            draw_polyline(image, np.array(line), COLORS[names[rng.integers(3)]], 1.5)
        specks = rng.integers(int(max(inset, 0)), [h - max(inset, 0), w - max(inset, 0)], (30, 2))
        image[specks[:, 0], specks[:, 1]] = np.array(COLORS["green"])
        image, bg = image.astype(np.float32), bg.astype(np.float32)
        for background in (bg, None):
            found = segment_image(image, background, params)
            channel, uv, area = segment_whole_image(image, background, params)
            assert len(found) >= 6
            assert np.array_equal(found.channel, channel) and np.array_equal(found.area, area)
            assert np.array_equal(found.uv, uv)
    blank = segment_image(bg, bg, params)
    assert len(blank) == 0 and blank.uv.shape == (0, 2)


# --------------------------------------------------------------------------------------------------
# 2. Labels
# --------------------------------------------------------------------------------------------------


def test_label_propagation_keeps_labels_on_slowly_moving_blobs():
    rng = np.random.default_rng(4)
    frames, markers = 30, 9
    channel = np.arange(markers) % 3
    start = rng.uniform(50, 450, (markers, 2))
    velocity = rng.uniform(-6, 6, (markers, 2))
    truth = start[None] + np.arange(frames)[:, None, None] * velocity[None]
    truth[:, 3] = truth[:, 0] + [25.0, 0.0]  # a same-colour neighbour 25 px away, moving alongside
    tracker = LabelTracker(channel, np.arange(markers), truth[0] + rng.normal(0, 2.0, (markers, 2)),
                           TrackParams(max_jump_px=20.0, first_frame_px=20.0))
    uv = np.zeros((frames, markers, 2))
    for f in range(frames):
        order = rng.permutation(markers)  # blobs arrive in any order
        blobs = Blobs(channel[order], truth[f, order] + rng.normal(0, 0.3, (markers, 2)), np.full(markers, 50))
        uv[f], index = tracker.update(blobs)
        assert np.all(index >= 0)
        np.testing.assert_array_equal(order[index], np.arange(markers))
    wrong, swaps = label_swaps(uv, truth, channel)
    assert wrong.sum() == 0 and swaps.sum() == 0
    # a forced swap of two same-colour labels is counted once
    uv[10:, [0, 3]] = uv[10:, [3, 0]]
    wrong, swaps = label_swaps(uv, truth, channel)
    assert swaps.sum() == 2 and wrong.sum() == 2 * 20


def test_a_blob_that_jumps_too_far_is_missing_for_that_frame():
    tracker = LabelTracker(np.array([0]), np.array([0]), np.array([[100.0, 100.0]]),
                           TrackParams(max_jump_px=10.0, predict_motion=False))
    blob = lambda u: Blobs(np.array([0]), np.array([[u, 100.0]]), np.array([30]))  # noqa: E731
    assert tracker.update(blob(103.0))[1][0] == 0
    assert tracker.update(blob(140.0))[1][0] == -1  # 37 px: refused
    assert tracker.update(blob(115.0))[1][0] == 0  # 12 px after a missed frame: within 2 x 10 px


def test_a_blob_near_another_same_colour_stripes_prediction_is_ambiguous():
    from sim.capture_solve import _ambiguous_labels

    channel = np.array([0, 0, 1, 0])
    same = (channel[:, None] == channel[None, :]) & ~np.eye(4, dtype=bool)
    projected = np.array([[100.0, 100.0], [106.0, 100.0], [101.0, 100.0], [300.0, 100.0]])
    uv = np.array([[103.0, 100.0], [np.nan, np.nan], [101.0, 100.0], [300.0, 100.0]])
    # marker 0's blob sits between its own prediction and marker 1's (crossed, merged stripes); marker
    # 2 is as near but another colour; marker 3 is alone; marker 1 has no blob
    assert _ambiguous_labels(uv, projected, same, 8.0).tolist() == [True, False, False, False]


# --------------------------------------------------------------------------------------------------
# 4. Gaps
# --------------------------------------------------------------------------------------------------


def test_gaps_up_to_five_frames_are_interpolated_longer_gaps_hold():
    F = 40
    t = np.arange(F, dtype=float)
    line = np.stack([0.1 * t, -0.02 * t, 0.3 + 0.0 * t], 1)
    track = np.repeat(line[:, None], 7, 1)  # seven markers on the same linear motion
    gaps = {0: (10, 1), 1: (10, 3), 2: (10, 5), 3: (10, 6), 4: (10, 9)}
    for m, (start, n) in gaps.items():
        track[start:start + n, m] = np.nan
    track[:3, 5] = np.nan  # leading
    track[-4:, 6] = np.nan  # trailing
    filled, interp, held = fill_gaps(track, max_gap=5)
    for m in (0, 1, 2):
        np.testing.assert_allclose(filled[:, m], line, atol=1e-12)  # exact for linear motion
        assert interp[:, m].sum() == gaps[m][1] and held[:, m].sum() == 0
    for m in (3, 4):
        start, n = gaps[m]
        np.testing.assert_allclose(filled[start:start + n, m], np.repeat(line[start - 1][None], n, 0), atol=1e-12)
        assert held[:, m].sum() == n and interp[:, m].sum() == 0
    np.testing.assert_allclose(filled[:3, 5], np.repeat(line[3][None], 3, 0))
    np.testing.assert_allclose(filled[-4:, 6], np.repeat(line[-5][None], 4, 0))
    assert interp.sum() == 1 + 3 + 5 and held.sum() == 6 + 9 + 3 + 4
    never = np.full((5, 1, 3), np.nan)
    assert np.all(np.isnan(fill_gaps(never)[0]))


# --------------------------------------------------------------------------------------------------
# 5-6. Cleaning and densification
# --------------------------------------------------------------------------------------------------


def test_interpolated_strands_follow_the_papers_formula_exactly():
    rng = np.random.default_rng(5)
    a, b = rng.normal(size=(3, 12, 3)), rng.normal(size=(3, 12, 3))
    d = 4
    T = interpolate_strands(a, b, d)
    assert T.shape == (d - 1, 3, 12, 3)
    for n in range(1, d):
        np.testing.assert_allclose(T[n - 1], ((d - n) * a + n * b) / d, atol=1e-15)
    assert interpolate_strands(a, b, 1).shape[0] == 0


def test_inner_layers_move_less_linearly_toward_the_scalp():
    rng = np.random.default_rng(6)
    F, S, V, L = 5, 4, 10, 3
    base = np.cumsum(np.full((S, V, 3), [0.0, -0.01, 0.0]), 1) + rng.normal(0, 0.05, (S, 1, 3)) + [0, 0.1, 0.1]
    strands = base[None] + rng.normal(0, 0.01, (F, S, V, 3)) * np.linspace(0, 1, V)[None, None, :, None]
    layers = inner_layers(strands, L, 0.006, np.zeros(3))
    assert layers.shape == (F, L * S, V, 3)
    outer_motion = strands - strands[0]
    for k in range(1, L + 1):
        inner = layers[:, (k - 1) * S:k * S]
        np.testing.assert_allclose(inner - inner[0], (1.0 - k / (L + 1)) * outer_motion, atol=1e-14)
        np.testing.assert_allclose(inner[0, :, 0], strands[0, :, 0], atol=1e-14)  # roots stay
        closer = np.linalg.norm(inner[0, :, -1], axis=-1) - np.linalg.norm(strands[0, :, -1], axis=-1)
        np.testing.assert_allclose(closer, -k * 0.006, atol=1e-4)  # k spacings toward the centre


def test_neighbours_on_a_grid_of_roots_are_its_edges_and_diagonals():
    g = np.stack(np.meshgrid(np.arange(3), np.arange(3)), -1).reshape(-1, 2) * 0.02
    angles = g - 0.02
    roots = np.stack([np.sin(angles[:, 0]), np.cos(angles[:, 0]) * np.cos(angles[:, 1]), np.sin(angles[:, 1])], 1) * 0.1
    edges = strand_neighbours(roots, np.zeros(3))
    length = np.linalg.norm(roots[edges[:, 0]] - roots[edges[:, 1]], axis=1)
    assert len(edges) == 12 + 4  # grid edges and one diagonal per cell
    assert length.max() < 1.5 * 0.002  # sides 2 mm, diagonals 2.8 mm, nothing across the grid


def test_spline_resampling_keeps_segment_lengths_within_one_percent():
    w = 0.04
    lengths = np.array([w / 2, w, w, w, w / 2])
    # a measured chain on a gentle arc, lengths wrong by up to 10%
    rng = np.random.default_rng(7)
    angles = np.cumsum(np.r_[0.0, np.full(5, 0.35)])
    radial = np.cumsum(np.r_[0.0, lengths * rng.uniform(0.9, 1.1, 5)])
    chain = np.stack([np.sin(angles) * radial * 0.3, -radial, np.zeros(6)], 1)
    chain = normalise_lengths(chain, lengths)
    np.testing.assert_allclose(np.linalg.norm(np.diff(chain, axis=0), axis=1), lengths, atol=1e-12)
    out = resample_strands(chain, 21)
    seg = np.linalg.norm(np.diff(out, axis=0), axis=1)
    target = lengths.sum() / 20
    assert np.abs(seg / target - 1.0).max() < 0.01
    np.testing.assert_allclose(out[0], chain[0], atol=1e-12)
    np.testing.assert_allclose(out[-1], chain[-1], atol=1e-9)
    # a tip extension carries on straight, half a stripe
    short = normalise_lengths(chain[:4], lengths[:4])
    np.testing.assert_allclose(np.linalg.norm(short[-1] - short[-2]), w, atol=1e-12)


def test_a_kinked_point_is_replaced_by_its_previous_frame_position():
    w = 0.04
    straight = np.array([[0.0, 0.0, 0.0], [0.0, -w / 2, 0.0], [0.0, -1.5 * w, 0.0], [0.0, -2.5 * w, 0.0],
                         [0.0, -3.5 * w, 0.0]])
    strands = np.stack([straight, straight + [0.001, 0.0, 0.0]])[:, None].repeat(2, 1)  # (2 frames, 2 strands)
    strands[1, 0, 2] = [0.03, -0.5 * w, 0.0]  # point 2 of strand 0 thrown back up: a kink
    assert np.degrees(segment_angles(strands[1, 0])).max() > 80
    cleaned, replaced = reject_kinks(strands, 80.0)
    np.testing.assert_array_equal(cleaned[1, 0, 2], strands[0, 0, 2])
    assert replaced.sum() == 1 and replaced[1, 0, 2]
    np.testing.assert_array_equal(cleaned[1, 1], strands[1, 1])  # the straight strand is untouched
    np.testing.assert_array_equal(cleaned[0], strands[0])


# --------------------------------------------------------------------------------------------------
# 7. Hair cards
# --------------------------------------------------------------------------------------------------


def test_hair_cards_have_uvs_in_range_two_vertices_per_strand_vertex_and_the_width_asked():
    rng = np.random.default_rng(8)
    S, V, width = 5, 9, 0.012
    roots = rng.normal(size=(S, 3))
    roots = 0.1 * roots / np.linalg.norm(roots, axis=1, keepdims=True)
    strands = roots[:, None] + np.linspace(0, 0.15, V)[None, :, None] * np.array([0.2, -1.0, 0.3])
    strands[0] = roots[0] + np.linspace(0, 0.15, V)[:, None] * roots[0] / 0.1  # straight out from the centre
    cards = HairCards.build(S, V)
    pts = cards.points(strands, np.zeros(3), width)
    assert pts.shape == (2 * S * V, 3) and cards.uvs.shape == (2 * S * V, 2)
    assert cards.uvs.min() >= 0.0 and cards.uvs.max() <= 1.0
    assert cards.faces.shape == (S * (V - 1), 4) and cards.faces.max() == 2 * S * V - 1
    left, right = pts[0::2], pts[1::2]
    np.testing.assert_allclose(np.linalg.norm(right - left, axis=1), width, atol=1e-12)
    np.testing.assert_allclose(0.5 * (left + right), strands.reshape(-1, 3), atol=1e-12)
    uv = cards.uvs.reshape(S, V, 2, 2)
    np.testing.assert_array_equal(uv[:, :, 0, 0], 0.0)
    np.testing.assert_array_equal(uv[:, :, 1, 0], 1.0)
    np.testing.assert_allclose(uv[:, :, 0, 1], np.tile(np.linspace(0, 1, V), (S, 1)))
    # the cards of strands lying over the head face away from it
    q = pts[cards.faces[S - 1::S]]  # a quad of each other strand
    normal = np.cross(q[:, 1] - q[:, 0], q[:, 3] - q[:, 0])
    assert np.all(np.sum(normal[1:] * q[1:, 0], -1) > 0)


# --------------------------------------------------------------------------------------------------
# The whole solve
# --------------------------------------------------------------------------------------------------


def test_solve_end_to_end_recovers_the_stripes_and_writes_a_valid_cache(solved):
    from pxr import Usd, UsdGeom

    from io_usd import CacheReader, validation_errors

    result, doc, centres, folder = solved
    report = json.load(open(result.report_path))
    assert os.path.basename(result.report_path) == "hair.report.json"
    for key in ("rmse_mm", "marker_error_mm", "label_swaps", "filled", "detections", "triangulated", "strands"):
        assert key in report
    assert report["rmse_mm"]["ring"] < 1.0, report["rmse_mm"]
    assert report["rmse_mm"]["stereo"] < 5.0, report["rmse_mm"]
    assert report["label_swaps"]["count"] == 0
    assert report["filled"]["interpolated"] == 2 and report["filled"]["held"] == 0
    assert report["filled"]["frames"] == {"g01:2": {"interpolated": [4, 5], "held": []}}
    assert report["triangulated"]["stereo"] == 8 * 9 - 2 - 1 and report["triangulated"]["ring"] == 8 * 9 - 2
    assert set(report["detections"]) == {c["name"] for c in doc["cameras"]}
    assert report["guide_distance_mm"]["mean"] < 3.0, report["guide_distance_mm"]
    assert result.label_swaps == 0 and result.filled == 2

    path = result.path
    assert validation_errors(path) == []
    reader = CacheReader(path)
    assert reader.frames() == list(range(1, 9)) and reader.fps == 24.0
    roles = {name: p.role for name, p in reader.prims.items()}
    assert roles == {"head": "collider", "hair_guides": "hair", "hair": "hair", "hair_card": "hair_card"}
    # 3 guides, 2 neighbour pairs x 2 strands between, one inner layer: (3 + 4) x 2
    assert result.strands == 14 and reader.prims["hair"].num_points == 14 * 12
    assert reader.prims["hair_card"].num_points == 2 * 14 * 12
    st = UsdGeom.PrimvarsAPI(reader.stage.GetPrimAtPath("/World/hair_card")).GetPrimvar("st")
    assert st.GetInterpolation() == UsdGeom.Tokens.vertex and len(st.Get()) == 2 * 14 * 12
    # the roots ride on the turning head, and the guides pass through the stripe centres
    guides = reader.read_points("hair_guides").reshape(8, 3, 12, 3)
    roots0 = np.array([g["root"] for g in doc["guides"]])
    for f in range(8):
        R = head_rotation(f / 24.0)
        np.testing.assert_allclose(guides[f, :, 0], (roots0 - HEAD_CENTRE) @ R.T + HEAD_CENTRE, atol=2e-6)
    head = reader.read_points("head")
    assert head.shape[0] == 8 and not np.allclose(head[0], head[4])
    assert Usd.Stage.Open(path).GetRootLayer().customLayerData["cfx:complete"]


def test_solve_reports_per_marker_errors_for_both_methods(solved):
    report = solved[0].report
    errors = report["marker_error_mm"]
    assert len(errors) == 9
    assert max(e["ring_max"] for e in errors.values()) < 2.0
    assert all(e["stereo_rmse"] is not None for e in errors.values())


def test_a_camera_without_first_frame_names_is_labelled_from_the_other_cameras(solved):
    from dataclasses import replace

    from sim.capture_solve import SolveParams, label_capture

    capture = load_capture(str(solved[3] / "cap"))
    ring_b = [c.name for c in capture.cameras].index("ring_b")
    names = {k: v for k, v in capture.first_frame_labels.items() if k != "ring_b"}
    uv, _, _, _ = label_capture(replace(capture, first_frame_labels=names), SolveParams())
    labelled = np.all(np.isfinite(uv[ring_b]), -1)
    assert labelled[0].sum() == 0 and labelled[1:].sum(1).min() >= 8  # named from frame 2 on
    truth = np.stack([capture.cameras[ring_b].project(x) for x in capture.truth_markers()])
    wrong, _ = label_swaps(uv[ring_b], truth, capture.marker_channel)
    assert wrong.sum() == 0  # each label on its own stripe
    assert np.nanmedian(np.linalg.norm(uv[ring_b, 1:] - truth[1:], axis=-1)) < 0.5  # px


def test_stripe_centres_farther_along_the_guide_than_its_hair_allows_are_rejected(solved):
    from sim.capture_solve import chain_outliers

    capture = load_capture(str(solved[3] / "cap"), check_images=False)
    truth = capture.truth_markers()
    roots = np.broadcast_to(capture.roots, (len(truth),) + capture.roots.shape)
    roots = np.stack([(roots[f] - HEAD_CENTRE) @ head_rotation(f / 24.0).T + HEAD_CENTRE for f in range(len(truth))])
    assert not chain_outliers(truth, roots, capture).any()
    moved = truth.copy()
    moved[2, 4] += [0.0, 0.0, 0.06]  # g01:1 on another guide's place, 6 cm off
    moved[5, 0] = moved[5, 6]  # g00:0 labelled with g02:0's stripe
    out = chain_outliers(moved, roots, capture)
    assert out.sum() == 2 and out[2, 4] and out[5, 0]


def test_a_stripe_never_seen_is_bridged_and_the_guide_keeps_its_length(solved):
    from sim.capture_solve import SolveParams, guide_strands

    capture = load_capture(str(solved[3] / "cap"), check_images=False)
    truth = capture.truth_markers()[:1]  # the first frame: the head's frame is the world's
    truth[:, 1] = np.nan  # g00:1 never seen
    strands, kept = guide_strands(capture, truth, SolveParams(vertices=40))
    np.testing.assert_array_equal(kept, [0, 1, 2])
    length = np.linalg.norm(np.diff(strands[0, 0], axis=0), axis=1).sum()
    assert abs(length / (3 * capture.stripe_width) - 1.0) < 0.01
    for k in (0, 2):  # passes by the centres it was built from (a bent stripe's centre lies off the hair)
        d = np.linalg.norm(strands[0, 0] - capture.truth_markers()[0, k], axis=1).min()
        assert d < 2e-3, (k, d)


def test_cli_solve_runs_and_bad_captures_raise_input_errors(solved, capsys, tmp_path):
    from sim.capture_solve import add_solve_arguments, run_solve

    folder = solved[3]
    parser = argparse.ArgumentParser()
    add_solve_arguments(parser)
    out = tmp_path / "cli.usda"
    args = parser.parse_args([str(folder / "cap"), "-o", str(out), "--strands-between", "0", "--layers", "0",
                              "--vertices", "8", "--card-width", "0.01", "-q"])
    assert run_solve(args) == 0
    assert out.exists() and (tmp_path / "cli.report.json").exists()
    err = capsys.readouterr().err
    assert "ring RMSE" in err and "label swaps 0" in err

    with pytest.raises(InputError, match="capture.json"):
        load_capture(str(tmp_path))
    bad = tmp_path / "bad"
    bad.mkdir()
    doc = json.load(open(folder / "cap" / "capture.json"))
    for key, value, match in (("colour", 1, "unknown key"), ("fps", "fast", "fps"),
                              ("stereo", {"left": "stereo_l", "right": "ring_a", "baseline": 0.12}, "parallel")):
        broken = dict(doc, **{key: value})
        (bad / "capture.json").write_text(json.dumps(broken))
        with pytest.raises(InputError, match=match):
            load_capture(str(bad), check_images=False)
    (bad / "capture.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match="missing background image"):
        load_capture(str(bad))
    assert not list(tmp_path.glob("*.partial*"))


RIG_SCENE = tiny_capture_scene(4, 0.16, """
guides = 4
stripe_width = 0.04
guide_width = 0.008
ring_cameras = 6
width = 480
height = 270
seed = 1
""")


def test_solve_a_tiny_capture_from_the_synthetic_rig(tmp_path):
    from io_usd import validation_errors
    from sim.capture_rig import load_capture_scene, synthesize
    from sim.capture_solve import solve

    scene_path = tmp_path / "scene.toml"
    scene_path.write_text(RIG_SCENE)
    scene, config = load_capture_scene(str(scene_path))
    synthesize(scene, config, tmp_path / "cap", progress=False)
    result = solve(str(tmp_path / "cap"), str(tmp_path / "out.usdc"), vertices=10)
    report = result.report
    print(json.dumps({k: report[k] for k in ("rmse_mm", "triangulated", "guide_distance_mm")}))
    assert report["rmse_mm"]["ring"] < 2.0, report["rmse_mm"]
    assert report["label_swaps"]["count"] == 0
    assert report["strands"]["guides"] == 4
    assert validation_errors(result.path) == []


def test_the_segmentation_benchmark_finds_the_same_blobs_both_ways(solved, capsys):
    import capture

    capture.main(["--capture", str(solved[3] / "cap")])
    row = capsys.readouterr().out.strip().splitlines()[-1].split("|")
    assert row[1].strip() == "segment_image with the background" and int(row[2]) > 0
    assert row[-2].strip() == "yes" and float(row[5]) > 0.0


def test_a_solve_refuses_damaged_inputs_and_its_own_inputs_as_output(tmp_path, capsys):
    """From a QA pass: a cut-off truth.npz or PNG raised tracebacks, --vertices 1e8 ran out of memory,
    and `-o CAP/simulation.usdc` replaced the capture's own simulation."""
    import shutil

    from sim.cli import main

    make_capture(str(tmp_path / "cap"), frames=3)
    cap = tmp_path / "cap"
    (cap / "simulation.usdc").write_bytes(b"kept")
    assert main(["capture", "solve", str(cap), "-o", str(cap / "simulation.usdc"), "-q"]) == 2
    assert "is the capture's simulation.usdc" in capsys.readouterr().err
    assert (cap / "simulation.usdc").read_bytes() == b"kept"
    (cap / "simulation.usdc").unlink()
    assert main(["capture", "solve", str(cap), "-o", str(tmp_path / "x.usdc"), "--vertices", "100000000", "-q"]) == 2
    assert "--vertices: expected 2 to 1024" in capsys.readouterr().err
    images = sorted(p for p in (cap / "images").rglob("*.png"))
    shutil.copy(images[0], tmp_path / "whole.png")
    images[0].write_bytes((tmp_path / "whole.png").read_bytes()[:40])
    assert main(["capture", "solve", str(cap), "-o", str(tmp_path / "x.usdc"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "cannot read image" in err and err.count("\n") == 1, err
    shutil.copy(tmp_path / "whole.png", images[0])
    truth = cap / "truth.npz"
    truth.write_bytes(truth.read_bytes()[:200])
    assert main(["capture", "solve", str(cap), "-o", str(tmp_path / "x.usdc"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "truth.npz: cannot read" in err and err.count("\n") == 1, err
    assert not (tmp_path / "x.usdc").exists()
