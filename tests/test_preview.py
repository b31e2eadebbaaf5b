"""Offscreen previews (EGL, no display needed), the preview camera, hair ribbons and the viewer guard."""

import os
import subprocess
import sys
import threading

import numpy as np
import pytest
from PIL import Image

from io_usd.cache import CacheReader, CacheWriter
from io_usd.preview import (BACKGROUND, Camera, SceneBuilder, auto_camera, contact_sheet,
                            hair_ribbons, preview, render_frame, resolve_views, strand_tangents)
from sim.head import procedural_head

W, H = 160, 120
HAIR = (0.25, 0.15, 0.08)
BG = np.round(255 * np.asarray(BACKGROUND)).astype(int)
CROWN = np.array([0.0, 0.472, 0.0])


def _strands(num=50, verts=12, length=0.2, sway=0.0):
    """Straight strands from a ring just outside the crown, hanging down and slightly outward."""
    angle = np.linspace(0.0, 2 * np.pi, num, endpoint=False)
    radial = np.stack([np.cos(angle), np.zeros(num), np.sin(angle)], 1)
    roots = np.array([0.0, 0.452, 0.003]) + 0.062 * radial
    direction = np.array([0.0, -1.0, 0.0]) + 0.45 * radial + [sway, 0.0, 0.0]
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    s = np.linspace(0.0, length, verts)
    points = roots[:, None, :] + s[None, :, None] * direction[:, None, :]
    return points.reshape(-1, 3).astype(np.float32), np.full(num, verts)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    path = str(tmp_path_factory.mktemp("preview") / "head_hair.usdc")
    head = procedural_head(rings=40, segments=32)
    points, counts = _strands()
    with CacheWriter(path, fps=24, start_frame=1, end_frame=3) as w:
        w.add_mesh("head", "collider", head.vertices, head.faces, color=(0.8, 0.65, 0.55))
        w.add_curves("hair", "hair", counts, np.full(len(points), 1e-4), color=HAIR)
        for f in (1, 2, 3):  # the hair sways so every frame differs (GIF would merge equal ones)
            sway, _ = _strands(sway=0.08 * (f - 2))
            w.write_frame(f, {"head": head.vertices, "hair": sway})
    return path


def _differs_from_background(image, tolerance=6):
    return np.abs(image.astype(int) - BG).max(axis=2) > tolerance


def _dark_brown(image):
    r, g, b = (image[..., k].astype(int) for k in range(3))
    return (r > g) & (g > b) & (r - b > 20) & (r < 150)


# -- camera -------------------------------------------------------------------------------------------
def test_look_at_target_projects_to_image_centre():
    cam = Camera.look_at(eye=(0.3, 0.5, 1.2), target=(0.05, 0.3, -0.1), yfov=0.7, width=W, height=H)
    u, v = cam.project([[0.05, 0.3, -0.1]])[0]
    assert abs(u - W / 2) < 0.5 and abs(v - H / 2) < 0.5


def test_project_matches_pinhole_formula():
    yfov = 0.6
    f = (H / 2) / np.tan(yfov / 2)
    front = Camera.look_at(eye=(0, 0, 2), target=(0, 0, 0), yfov=yfov, width=W, height=H)
    np.testing.assert_allclose(front.project([[0.1, 0.2, 0.0]])[0], [W / 2 + f * 0.1 / 2, H / 2 - f * 0.2 / 2],
                               atol=1e-9)
    # from +X looking at the origin, world -Z is screen right and the point is 2.5 m deep
    side = Camera.look_at(eye=(2, 0, 0), target=(0, 0, 0), yfov=yfov, width=W, height=H)
    np.testing.assert_allclose(side.project([[-0.5, 0.1, -0.3]])[0], [W / 2 + f * 0.3 / 2.5, H / 2 - f * 0.1 / 2.5],
                               atol=1e-9)
    np.testing.assert_allclose(side.intrinsics(), [[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]])
    assert np.isnan(side.project([[3.0, 0.0, 0.0]])).all()  # behind the camera


def test_project_agrees_with_the_renderer(tmp_path):
    """A small sphere off-centre lands, in the rendered image, where Camera.project puts its centre."""
    import trimesh

    centre = np.array([0.12, -0.05, 0.03])
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.02)
    path = str(tmp_path / "ball.usdc")
    with CacheWriter(path, fps=24, start_frame=1, end_frame=1) as w:
        w.add_mesh("ball", "collider", ball.vertices + centre, ball.faces)
        w.write_frame(1, {"ball": ball.vertices + centre})
    cam = Camera.look_at(eye=(0.4, 0.3, 1.0), target=(0, 0, 0), yfov=0.5, width=W, height=H)
    image = render_frame(CacheReader(path), 1, cam, shadows=False)
    rows, cols = np.nonzero(_differs_from_background(image))
    assert len(rows) > 20
    np.testing.assert_allclose([cols.mean() + 0.5, rows.mean() + 0.5], cam.project([centre])[0], atol=1.0)


def test_supersampled_frame_is_the_large_frame_averaged_with_strands_as_wide(cache):
    """A frame is drawn SUPERSAMPLE times larger with one sample per pixel and box-filtered down;
    strands keep their on-screen width in the final image's pixels, so they darken it as much as
    strands drawn at the final size do."""
    from io_usd.preview import HAIR_PIXELS, FrameRenderer

    reader = CacheReader(cache)
    cam = auto_camera(reader, W, H)
    with FrameRenderer(reader, W, H, supersample=2) as renderer:
        image = renderer.render(2, cam)
    assert image.shape == (H, W, 3) and image.dtype == np.uint8
    large = Camera(cam.yfov, 2 * W, 2 * H, cam.pose, cam.znear, cam.zfar)
    with FrameRenderer(reader, 2 * W, 2 * H, hair_pixels=2 * HAIR_PIXELS, supersample=1) as renderer:
        drawn = renderer.render(2, large).astype(np.int64)
    averaged = (drawn.reshape(H, 2, W, 2, 3).sum(axis=(1, 3)) + 2) // 4
    # rounding apart, equal; llvmpipe's threads may settle a tie of equal depths either way in a pixel
    assert np.mean(np.abs(image.astype(np.int64) - averaged).max(axis=2) > 1) < 0.002

    def darkening(supersample):
        with FrameRenderer(reader, W, H, names=["hair"], shadows=False, supersample=supersample) as renderer:
            return float(np.sum(BG - renderer.render(2, cam).astype(np.int64)))

    one, four = darkening(1), darkening(2)
    assert one > 0.0
    assert abs(four / one - 1.0) < 0.1


def test_supersampled_depth_is_the_nearest_surface_a_pixels_samples_saw(tmp_path):
    """The depth a capture's visibility test reads: along the view axis to the ball's front at its
    centre, 0 off it, and at its rim the ball wherever one of the pixel's four samples hit it."""
    import trimesh

    from io_usd.preview import SupersampledOffscreen, _pyrender

    pyrender = _pyrender()
    radius, distance = 0.05, 0.5
    ball = trimesh.creation.icosphere(subdivisions=5, radius=radius)
    cam = Camera.look_at(eye=(0.0, 0.0, distance), target=(0.0, 0.0, 0.0), yfov=0.3, width=W, height=H)

    def draw(width, height, supersample):  # a scene's meshes belong to the one GL context that drew them
        scene = pyrender.Scene()
        scene.add(pyrender.Mesh.from_trimesh(ball, smooth=False))
        scene.add(pyrender.PerspectiveCamera(yfov=cam.yfov, aspectRatio=W / H, znear=0.01, zfar=10.0), pose=cam.pose)
        gl = SupersampledOffscreen(width, height, supersample)
        try:
            return gl.render_with_depth(scene, pyrender.RenderFlags.NONE)
        finally:
            gl.delete()

    image, depth = draw(W, H, 2)
    _, drawn = draw(2 * W, 2 * H, 1)
    assert image.shape == (H, W, 3) and depth.shape == (H, W)
    assert depth[H // 2, W // 2] == pytest.approx(distance - radius, abs=1e-3)
    assert depth[0, 0] == 0.0
    samples = np.where(drawn > 0.0, drawn, np.inf).reshape(H, 2, W, 2).min(axis=(1, 3))
    # equal, but for a pixel or two where the two draws settled a tie differently
    assert np.count_nonzero(depth != np.where(np.isfinite(samples), samples, 0.0)) <= 4
    hit_by_some = (drawn > 0.0).reshape(H, 2, W, 2).any(axis=(1, 3))
    hit_by_all = (drawn > 0.0).reshape(H, 2, W, 2).all(axis=(1, 3))
    rim = np.count_nonzero(hit_by_some & ~hit_by_all)
    assert rim > 60  # the rim is there (one sample per pixel would miss about half of it), and counts as the ball
    assert np.count_nonzero((depth > 0.0) != hit_by_some) <= 4


def test_a_sequence_renders_each_frame_as_render_does_while_building_the_next(cache):
    """render_sequence builds frame k+1's scene on a second thread while frame k is drawn: the same
    images in the same order, each with its own camera (llvmpipe's threads may settle a tie of
    equal depths differently, so a few pixels may differ)."""
    from io_usd.preview import FrameRenderer

    reader = CacheReader(cache)
    cameras = {f: auto_camera(reader, W, H, [f]) for f in (1, 2, 3)}
    with FrameRenderer(reader, W, H) as renderer:
        one_by_one = [renderer.render(f, cameras[f]) for f in (3, 1, 2)]
        sequence = list(renderer.render_sequence([(3, "a"), (1, "b"), (2, "c")], lambda f, view: cameras[f]))
    assert len(sequence) == 3
    for a, b in zip(one_by_one, sequence):
        assert np.mean(np.abs(a.astype(int) - b).max(axis=2) > 0) < 0.002
    assert np.abs(sequence[0].astype(int) - sequence[1]).max() > 40  # the frames do differ


def test_an_image_near_the_gls_largest_framebuffer_is_drawn_with_fewer_samples():
    from OpenGL.GL import GL_MAX_RENDERBUFFER_SIZE, glGetIntegerv

    from io_usd.preview import SupersampledOffscreen

    gl = SupersampledOffscreen(16, 16)
    limit = int(glGetIntegerv(GL_MAX_RENDERBUFFER_SIZE))
    assert gl.supersample == 2
    gl.delete()
    gl = SupersampledOffscreen(limit // 2 + 1, 8)
    assert gl.supersample == 1  # twice as wide would not fit
    gl.delete()
    with pytest.raises(ValueError, match=f"larger than this GL draws \\({limit} pixels a side\\)"):
        SupersampledOffscreen(limit + 1, 8)


def test_frame_bounds_keeps_the_box_in_view():
    lo, hi = np.array([-0.2, 0.0, -0.15]), np.array([0.2, 0.6, 0.1])
    cam = Camera.frame_bounds(lo, hi, W, H, yaw_degrees=25, pitch_degrees=10)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    uv = cam.project(corners)
    assert np.all((uv >= 0) & (uv <= [W, H]))
    assert uv[:, 1].max() - uv[:, 1].min() > 0.75 * H  # tall box: fills the height, not lost in the middle
    np.testing.assert_allclose(0.5 * (uv.min(0) + uv.max(0)), [W / 2, H / 2], atol=0.5)  # and is centred
    assert cam.eye[2] > hi[2] and cam.eye[0] > 0 and cam.eye[1] > 0.3  # in front, turned right, raised


# -- ribbons ------------------------------------------------------------------------------------------
def test_hair_ribbons_face_the_eye():
    rng = np.random.default_rng(3)
    counts = np.array([5, 2, 9, 4])
    steps = rng.normal(0, 0.01, (counts.sum(), 3)) + [0, -0.02, 0]
    points = np.concatenate([np.cumsum(s, 0) + rng.normal(0, 0.1, 3)
                             for s in np.split(steps, np.cumsum(counts)[:-1])])
    eye = np.array([0.3, 0.2, 1.5])
    widths = rng.uniform(0.004, 0.02, counts.sum())
    vertices, faces, normals = hair_ribbons(points, counts, widths, eye, min_width=0.008)

    assert vertices.shape == (2 * counts.sum(), 3) and normals.shape == vertices.shape
    assert faces.shape == (2 * (counts - 1).sum(), 3)
    centre = 0.5 * (vertices[0::2] + vertices[1::2])
    np.testing.assert_allclose(centre, points, atol=1e-6)
    span = (vertices[1::2] - vertices[0::2]).astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(span, axis=1), np.maximum(widths, 0.008), rtol=1e-5)
    across = span / np.linalg.norm(span, axis=1, keepdims=True)
    tangent = strand_tangents(points, counts)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    view = eye - points
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    assert np.abs(np.sum(across * tangent, 1)).max() < 1e-5
    assert np.abs(np.sum(across * view, 1)).max() < 1e-5
    # triangles stay within a strand and are wound towards the eye
    tri = vertices[faces].astype(np.float64)
    assert np.all(np.abs(np.diff(faces // 2, axis=1)).max(1) <= 1)
    facing = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert np.all(np.sum(facing * (eye - tri.mean(1)), 1) > 0)
    assert np.all(np.sum(normals * np.repeat(view, 2, 0), 1) > 0)
    # every segment's two triangles, the segments nearest the eye first
    np.testing.assert_array_equal(faces[0::2, 0], faces[1::2, 0])
    assert sorted(faces[0::2, 0] // 2) == [p for p in range(counts.sum()) if p + 1 not in np.cumsum(counts)]
    assert np.all(np.diff(np.linalg.norm(points[faces[0::2, 0] // 2] - eye, axis=1)) >= 0.0)


def test_strand_tangents_are_one_sided_at_the_ends():
    points = np.array([[0, 0, 0], [1, 0, 0], [3, 0, 0], [0, 0, 0], [0, 2, 0]], float)
    t = strand_tangents(points, [3, 2])
    np.testing.assert_allclose(t, [[1, 0, 0], [3, 0, 0], [2, 0, 0], [0, 2, 0], [0, 2, 0]])


def test_reader_fans_polygons_from_their_first_corner(tmp_path):
    points = np.random.default_rng(0).normal(size=(9, 3))
    polygons = [[0, 1, 2, 3], [3, 2, 4], [4, 5, 6, 7, 8], [8, 7, 1]]
    path = str(tmp_path / "polys.usda")
    with CacheWriter(path, fps=24, start_frame=1, end_frame=1) as w:
        w.add_mesh("poly", "cloth", points, [np.array(p) for p in polygons])
        w.write_frame(1, {"poly": points})
    reader = CacheReader(path)
    expected = [[0, 1, 2], [0, 2, 3], [3, 2, 4], [4, 5, 6], [4, 6, 7], [4, 7, 8], [8, 7, 1]]
    np.testing.assert_array_equal(reader.triangles("poly"), expected)


# -- rendering ----------------------------------------------------------------------------------------
def test_png_preview_shows_head_and_hair(cache, tmp_path):
    out = preview(cache, str(tmp_path / "still.png"), width=W, height=H)
    assert out == str(tmp_path / "still.png") and os.path.isfile(out)
    image = np.asarray(Image.open(out).convert("RGB"))
    assert image.shape == (H, W, 3)
    for corner in (image[:8, :8], image[:8, -8:], image[-8:, :8], image[-8:, -8:]):
        assert not _differs_from_background(corner).any()
    covered = _differs_from_background(image).mean()
    assert 0.05 < covered < 0.8
    # hair shows around the crown, where the (light) skin would be otherwise
    cam = auto_camera(CacheReader(cache), W, H, [3])
    u, v = np.round(cam.project([CROWN])[0]).astype(int)
    crown = image[max(0, v - 12): v + 25, max(0, u - 25): u + 25]
    assert _dark_brown(crown).sum() > 40
    assert _dark_brown(image).sum() > 150


def test_contact_sheet_grid(cache, tmp_path):
    out = preview(cache, str(tmp_path / "sheet.png"), frames=[1, 2, 3], width=W, height=H)
    assert Image.open(out).size == (2 * W, 2 * H)  # three tiles, near-square: 2 x 2
    out = preview(cache, str(tmp_path / "row.png"), frames=[1, 2, 3], width=W, height=H, columns=3)
    sheet = np.asarray(Image.open(out).convert("RGB"))
    assert sheet.shape == (H, 3 * W, 3)
    assert not np.array_equal(sheet[:, :W], sheet[:, W:2 * W])  # different frames
    # named tiles: the same images under other labels (a longer label darkens more of the corner)
    named = preview(cache, str(tmp_path / "named.png"), frames=[1, 2, 3], width=W, height=H, columns=3,
                    labels=["neutral", "a much longer label", "x"])
    named = np.asarray(Image.open(named).convert("RGB"))
    assert np.array_equal(named[H // 3:], sheet[H // 3:])
    assert (named[:H // 3, W:2 * W] < 60).sum() > (sheet[:H // 3, W:2 * W] < 60).sum()
    with pytest.raises(ValueError, match="one label per frame"):
        preview(cache, str(tmp_path / "bad.png"), frames=[1, 2], width=W, height=H, labels=["one"])


def test_views_side_by_side_are_the_single_views(cache, tmp_path):
    """Several views: a tile each, side by side, each the image that view alone gives (its label
    aside); a .png row per frame, a movie frame holding them all."""
    front = np.asarray(Image.open(preview(cache, str(tmp_path / "front.png"), width=W, height=H, views=["front"])))
    back = np.asarray(Image.open(preview(cache, str(tmp_path / "back.png"), width=W, height=H, views=[(180, 0)])))
    both = np.asarray(Image.open(preview(cache, str(tmp_path / "both.png"), width=W, height=H,
                                         views=["front", "back"])))
    assert both.shape == (H, 2 * W, 3)
    below_label = slice(H // 4, H - 1)
    for tile, alone in ((both[:, :W], front), (both[:, W:], back)):
        assert np.mean(np.abs(tile[below_label, 1:-1].astype(int) - alone[below_label, 1:-1]).max(axis=2) > 0) < 0.002
    # the head hides the face's side of the hair from behind: the two views do differ
    assert np.abs(front[below_label].astype(int) - back[below_label]).max() > 40
    sheet = Image.open(preview(cache, str(tmp_path / "sheet.png"), frames=[1, 3], width=W, height=H,
                               views=["turnaround"]))
    assert sheet.size == (4 * W, 2 * H)  # front, left, back, right in a row per frame
    with Image.open(preview(cache, str(tmp_path / "both.gif"), width=W, height=H, views=["left", "right"])) as gif:
        assert gif.n_frames == 3 and gif.size == (2 * W, H)


def test_unknown_views_are_named():
    assert resolve_views(None) == [("three-quarter", 25.0, 10.0)]
    assert [v[0] for v in resolve_views(["turnaround", "top", (30, -20)])] == [
        "front", "left", "back", "right", "top", "yaw 30, pitch -20"]
    with pytest.raises(ValueError, match="unknown view 'side': use three-quarter, front"):
        resolve_views(["side"])
    with pytest.raises(ValueError, match="pitch must be within -89 to 89"):
        resolve_views([(0, 90)])


def test_contact_sheet_helper_labels_tiles():
    tiles = [np.full((40, 50, 3), 200, np.uint8) for _ in range(5)]
    sheet = contact_sheet(tiles, ["frame 1", "frame 2", "frame 3", "frame 4", "frame 5"], columns=2)
    assert sheet.size == (100, 120)
    pixels = np.asarray(sheet)
    assert (pixels[:15, :40] < 100).any()  # dark label box in the first tile's corner
    assert (pixels[80:, 50:] != 200).any()  # the empty sixth cell is filled with the background


def test_gif_has_every_frame(cache, tmp_path):
    out = preview(cache, str(tmp_path / "anim.gif"), width=W, height=H)
    with Image.open(out) as gif:
        assert gif.n_frames == 3
        assert gif.size == (W, H)
        assert gif.info.get("loop") == 0
        assert abs(gif.info["duration"] - 1000 / 24) <= 10


def test_mp4_has_every_frame(cache, tmp_path):
    import imageio.v2 as imageio

    out = preview(cache, str(tmp_path / "anim.mp4"), width=W, height=H)
    with imageio.get_reader(out, format="FFMPEG") as reader:
        frames = [frame for frame in reader]
        assert abs(reader.get_meta_data()["fps"] - 24) < 1e-3
    assert len(frames) == 3 and frames[0].shape == (H, W, 3)
    with pytest.raises(ValueError, match="even"):
        preview(cache, str(tmp_path / "odd.mp4"), width=W + 1, height=H)


# -- errors -------------------------------------------------------------------------------------------
def test_missing_cache_names_the_path(tmp_path):
    missing = str(tmp_path / "nope.usdc")
    with pytest.raises(FileNotFoundError, match="nope.usdc"):
        preview(missing, str(tmp_path / "out.png"))


def test_bad_requests_raise_value_error(cache, tmp_path):
    with pytest.raises(ValueError, match=r"out\.jpg"):
        preview(cache, str(tmp_path / "out.jpg"))
    with pytest.raises(ValueError, match="frame 9 is not in the cache"):
        preview(cache, str(tmp_path / "out.png"), frame=9, width=W, height=H)
    assert os.listdir(tmp_path) == []


def test_failed_render_leaves_nothing(cache, tmp_path, monkeypatch):
    from io_usd import preview as module

    def broken(self, camera, scene):
        raise RuntimeError("GL went away")

    monkeypatch.setattr(module.FrameRenderer, "_draw", broken)
    for name in ("x.png", "x.gif", "x.mp4"):
        with pytest.raises(RuntimeError, match="GL went away"):
            preview(cache, str(tmp_path / name), width=W, height=H)
    assert os.listdir(tmp_path) == []


# -- viewer -------------------------------------------------------------------------------------------
def test_view_needs_a_display(cache, monkeypatch):
    from io_usd import viewer

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.setattr(viewer.sys, "platform", "linux")
    with pytest.raises(RuntimeError, match="display"):
        viewer.view(cache)


def test_importing_does_not_load_pyrender():
    code = "import sys, io_usd, io_usd.preview, io_usd.viewer; sys.exit('pyrender' in sys.modules)"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in [os.getcwd(), os.environ.get("PYTHONPATH")] if p))
    assert subprocess.run([sys.executable, "-c", code], env=env).returncode == 0


class _FakeViewer:
    """Stands in for pyrender.Viewer: the same scene, lock and size, active for `ticks` checks."""

    def __init__(self, scene, ticks):
        self.scene, self.render_lock, self.viewport_size = scene, threading.RLock(), (W, H)
        self._ticks = ticks

        self.closed = False

    @property
    def is_active(self):
        self._ticks -= 1
        return self._ticks >= 0 and not self.closed

    def close_external(self):
        self.closed = True


def test_ctrl_c_during_playback_closes_the_window(cache):
    """Otherwise the window's thread keeps the process running after the interrupt."""
    from io_usd.viewer import play

    class Interrupted:
        def meshes(self, frame, eye, focal):
            raise KeyboardInterrupt

    viewer = _FakeViewer(_pyrender_scene(), 5)
    with pytest.raises(KeyboardInterrupt):
        play(viewer, Interrupted(), {}, [1, 2], fps=24.0, sleep=lambda s: None)
    assert viewer.closed


def _pyrender_scene():
    from io_usd.preview import _pyrender

    pyrender = _pyrender()
    scene = pyrender.Scene()
    scene.add(pyrender.PerspectiveCamera(yfov=0.6), pose=Camera.look_at((0, 0.3, 1.5), (0, 0.3, 0)).pose)
    return scene


@pytest.mark.parametrize("loop, expected", [(True, [1, 2, 3, 1, 2, 3, 1]), (False, [1, 2, 3, 3, 3, 3, 3])])
def test_viewer_playback_updates_the_scene(cache, loop, expected):
    from io_usd.viewer import play

    reader = CacheReader(cache)
    builder = SceneBuilder(reader)
    shown = []
    meshes = builder.meshes
    builder.meshes = lambda frame, eye, focal: shown.append(frame) or meshes(frame, eye, focal)
    scene = _pyrender_scene()
    nodes = {}
    play(_FakeViewer(scene, len(expected)), builder, nodes, [1, 2, 3], fps=1000.0, loop=loop, sleep=lambda s: None)
    assert shown == expected
    assert set(nodes) == {"head", "hair"} and len(scene.mesh_nodes) == 2
    hair = next(iter(nodes["hair"].mesh.primitives)).positions
    assert hair.shape == (2 * reader.prims["hair"].num_points, 3)
