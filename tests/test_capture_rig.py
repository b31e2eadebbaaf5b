"""The synthetic capture rig: camera conventions against what pyrender draws, the stereo pair, stripe
centres against a dense reference, the capture directory's layout, the dyes in the images, bad input."""

import argparse
import json
import os

import numpy as np
import pytest
from PIL import Image

from sim.capture_rig import (DYES, STRIPE_COLORS, CaptureCamera, CaptureConfig, Studio, arc_lengths, intrinsics,
                             load_capture_scene, occlusion_mask, points_at, project, rig_cameras, run_synth,
                             stripe_centres, synthesize)
from sim.capture_solve import load_capture
from sim.errors import InputError

from capture_scenes import tiny_capture_scene  # tests/capture_scenes.py

W, H = 320, 180
CENTRE = np.array([0.0, 0.32, 0.0])

SCENE = tiny_capture_scene(3, 0.2, """
guides = 6
stripe_width = 0.04
guide_width = 0.008
width = 320
height = 180
noise = 3.0
occlusion = 0.3
occlusion_frames = 2
seed = 3
""")


def _scene_file(tmp_path, text=SCENE, name="scene.toml"):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    folder = tmp_path_factory.mktemp("capture")
    scene, config = load_capture_scene(_scene_file(folder))
    result = synthesize(scene, config, folder / "out", progress=False)
    return result, load_capture(result.path), config


# -- cameras ----------------------------------------------------------------------------------------
def _marker_centroid(studio, index, point, radius=0.01):
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    studio.show("marker", sphere.vertices + point, sphere.faces, sphere.vertex_normals, color=(0.0, 0.0, 0.0))
    image, _ = studio.render(index)
    coverage = 1.0 - image.astype(np.float64).mean(2) / 255.0  # antialiased edges count in part
    assert np.sum(coverage > 0.5) > 10, "the marker was not drawn"
    rows, cols = np.indices(coverage.shape)
    # pixel (row r, column c) has its centre at (c + 0.5, r + 0.5), as in capture_format.md
    return np.array([np.sum(coverage * (cols + 0.5)), np.sum(coverage * (rows + 0.5))]) / coverage.sum()


def test_project_lands_where_pyrender_draws_a_marker_in_stereo_ring_and_off_centre_cameras():
    cameras = rig_cameras(CaptureConfig(width=W, height=H), CENTRE, 0.25)
    k = intrinsics(0.0, W, H)
    k[0, 0] = k[1, 1] = 300.0
    k[0, 2], k[1, 2] = 0.37 * W, 0.61 * H  # a principal point off the centre catches sign slips
    cameras.append(CaptureCamera.look_at("skewed", "ring", (0.4, 0.6, 0.9), CENTRE, k))
    point = CENTRE + [0.05, 0.04, 0.03]
    with Studio(cameras, W, H) as studio:
        for name in ("stereo_l", "stereo_r", "ring_3", "ring_6", "skewed"):
            index = [c.name for c in cameras].index(name)
            drawn = _marker_centroid(studio, index, point)
            expected = project(cameras[index], point[None])[0]
            assert np.linalg.norm(drawn - expected) < 0.3, (name, drawn, expected)


def test_stereo_pair_is_parallel_with_the_baseline_along_the_left_cameras_x():
    config = CaptureConfig(stereo_baseline=0.15)
    left, right = rig_cameras(config, CENTRE, 0.25)[:2]
    assert (left.group, right.group) == ("stereo", "stereo")
    np.testing.assert_array_equal(left.K, right.K)
    np.testing.assert_allclose(left.world_to_camera[:3, :3], right.world_to_camera[:3, :3], atol=1e-15)
    np.testing.assert_allclose(left.world_to_camera[:3, 3] - right.world_to_camera[:3, 3], [0.15, 0.0, 0.0],
                               atol=1e-12)
    x_axis = left.world_to_camera[0, :3]
    np.testing.assert_allclose(right.centre - left.centre, 0.15 * x_axis, atol=1e-12)
    # depth from disparity, as the pipeline triangulates: Z = b f / (u_l - u_r)
    point = CENTRE + [0.03, -0.02, 0.05]
    disparity = project(left, point[None])[0, 0] - project(right, point[None])[0, 0]
    depth = left.to_camera(point[None])[0, 2]
    assert 0.15 * left.K[0, 0] / disparity == pytest.approx(depth, rel=1e-9)


def test_ring_cameras_surround_the_head_and_look_at_its_centre():
    config = CaptureConfig(ring_cameras=8, ring_radius=1.1, width=W, height=H)
    ring = rig_cameras(config, CENTRE, 0.25)[2:]
    assert [c.name for c in ring] == [f"ring_{k}" for k in range(8)]
    for cam in ring:
        assert np.linalg.norm(cam.centre - CENTRE) == pytest.approx(1.1)
        np.testing.assert_allclose(project(cam, CENTRE[None])[0], [W / 2, H / 2], atol=1e-9)
    azimuth = [np.arctan2(c.centre[0], c.centre[2]) for c in ring]
    np.testing.assert_allclose(np.diff(np.unwrap(azimuth)), np.pi / 4, atol=1e-9)


# -- stripes ----------------------------------------------------------------------------------------
def test_stripe_centres_equal_a_dense_arc_length_average_of_the_polyline():
    rng = np.random.default_rng(4)
    steps = rng.normal(0.0, 1.0, (5, 30, 3)) * [0.004, 0.012, 0.004] + [0.0, -0.011, 0.0]
    points = np.cumsum(steps, axis=1)  # bent polylines with uneven segments
    width = 0.04
    stripes = np.floor(arc_lengths(points)[:, -1] / width).astype(int)
    centres = stripe_centres(points, stripes, width)
    for p, count in enumerate(stripes):
        s = (np.arange(count)[:, None] + (np.arange(20000)[None, :] + 0.5) / 20000) * width
        dense = points_at(points[p:p + 1], s.reshape(1, -1))[0].reshape(count, -1, 3)
        np.testing.assert_allclose(centres[p, :count], dense.mean(1), atol=2e-7)
        assert np.isnan(centres[p, count:]).all()


def test_stripe_centres_of_a_straight_strand_sit_at_the_stripe_midpoints():
    s = np.sort(np.concatenate([[0.0, 0.25], np.random.default_rng(1).uniform(0.0, 0.25, 9)]))
    points = np.stack([s, np.zeros_like(s), np.zeros_like(s)], 1)[None] + [0.1, 0.4, 0.0]
    centres = stripe_centres(points, [6], 0.04)
    np.testing.assert_allclose(centres[0, :, 0], 0.1 + 0.04 * (np.arange(6) + 0.5), atol=1e-12)


def test_truth_centres_lie_on_their_stripes_about_one_stripe_width_apart(capture):
    _, cap, _ = capture
    truth = cap.truth
    w = cap.stripe_width
    centres, guides = truth["stripe_centres"], truth["guide_points"]
    spacing, straight_gap = [], []
    for f in range(len(cap.frames)):
        for g, count in enumerate(cap.stripes):
            s = (np.arange(count)[:, None] + np.linspace(0.0, 1.0, 4001)[None, :]) * w
            dense = points_at(guides[f, g][None], s.reshape(1, -1))[0].reshape(count, -1, 3)
            gap = np.linalg.norm(dense - centres[f, g, :count, None], axis=2).min(1)
            chord = np.linalg.norm(dense[:, -1] - dense[:, 0], axis=1)
            # the centroid of a bent stripe lies inside its bend, within the stripe's own bulge
            bulge = np.array([np.abs(np.cross(d - d[0], (d[-1] - d[0]) / np.linalg.norm(d[-1] - d[0]))).max()
                              for d in dense])
            assert np.all(gap <= bulge + 1e-6)
            straight_gap.extend(gap[chord > 0.995 * w])
            spacing.extend(np.linalg.norm(np.diff(centres[f, g, :count], axis=0), axis=1))
    assert len(straight_gap) > 10 and max(straight_gap) < 1e-3
    spacing = np.asarray(spacing)
    assert spacing.max() <= w + 1e-9 and spacing.min() > 0.8 * w and np.median(spacing) > 0.97 * w


def test_occlusion_hides_runs_of_frames_never_the_first_and_only_real_stripes():
    stripes = np.array([6, 4, 5])
    hidden = occlusion_mask(200, 4, stripes, 0.2, 3, np.random.default_rng(0))
    assert hidden.shape == (200, 4, 3, 6)
    assert not hidden[0].any()
    assert not hidden[:, :, 1, 4:].any() and not hidden[:, :, 2, 5:].any()
    real = np.arange(6)[None, :] < stripes[:, None]
    assert 0.14 < hidden[:, :, real].mean() < 0.22
    runs = np.diff(np.concatenate([np.zeros((1, 4, 3, 6), int), hidden.astype(int)]), axis=0)
    assert runs.max() == 1  # hidden stretches start and end, several frames long on average
    assert hidden[:, :, real].sum() / (runs == 1)[:, :, real].sum() > 1.5


# -- the capture directory --------------------------------------------------------------------------
def _first_frame_labels(cap, camera):
    """The first frame's naming in one camera as guide and stripe indices and pixel positions."""
    markers, uv = cap.first_frame_labels[camera]
    return {"guide": cap.marker_guide[markers], "stripe": cap.marker_stripe[markers], "uv": uv}


def test_synthesize_writes_the_documented_layout(capture):
    result, cap, config = capture
    folder = result.path
    with open(os.path.join(folder, "capture.json")) as f:
        data = json.load(f)
    assert set(data) == {"version", "fps", "frames", "image_size", "units", "stripe", "guides", "cameras", "stereo",
                         "first_frame_labels"}
    assert data["version"] == 1 and data["units"] == "m" and data["fps"] == 24.0
    assert data["frames"] == [1, 2, 3] and data["image_size"] == [W, H]
    assert data["stripe"] == {"width": 0.04, "colors": ["red", "green", "blue"]}
    assert len(data["guides"]) == 6 and all(set(g) == {"name", "root", "stripes"} for g in data["guides"])
    names = [c["name"] for c in data["cameras"]]
    assert names == ["stereo_l", "stereo_r"] + [f"ring_{k}" for k in range(8)]
    assert data["stereo"] == {"left": "stereo_l", "right": "stereo_r", "baseline": 0.12}
    for name in names:
        images = sorted(os.listdir(os.path.join(folder, "images", name)))
        assert images == ["0001.png", "0002.png", "0003.png"]
        for path in [cap.image_path(name, 2), cap.background_path(name)]:
            with Image.open(path) as im:
                assert im.size == (W, H) and im.mode == "RGB"
    assert os.path.isfile(os.path.join(folder, "simulation.usdc"))
    assert not [p for p in os.listdir(os.path.dirname(folder)) if "partial" in p or ".old-" in p]

    truth = cap.truth
    k_max = int(cap.stripes.max())
    assert truth["stripe_centres"].shape == (3, 6, k_max, 3) and truth["stripe_centres"].dtype == np.float64
    assert truth["guide_points"].shape == (3, 6, 12, 3)
    assert truth["occluded"].shape == (3, 10, 6, k_max) and truth["occluded"].dtype == bool
    assert truth["occluded"][1:].any() and not truth["occluded"][0].any()
    assert truth["visible"].shape == (3, 10, 6, k_max)
    assert np.all(truth["visible"][truth["occluded"]] == 0.0)
    np.testing.assert_array_equal(truth["frames"], [1, 2, 3])
    np.testing.assert_array_equal(truth["cameras"], names)
    np.testing.assert_allclose(cap.roots, truth["guide_points"][0, :, 0])


def test_first_frame_labels_are_the_visible_stripes_at_their_centres_projections(capture):
    _, cap, _ = capture
    truth = cap.truth
    labelled = 0
    for index, cam in enumerate(cap.cameras):
        labels = _first_frame_labels(cap, cam.name)
        expected = project(cam, truth["stripe_centres"][0, labels["guide"], labels["stripe"]])
        assert np.abs(labels["uv"] - expected).max() < 1.5
        seen = truth["visible"][0, index][labels["guide"], labels["stripe"]]
        assert np.all(seen >= 0.5)
        hidden = np.nan_to_num(truth["visible"][0, index], nan=1.0) < 0.5
        named = np.zeros_like(hidden)
        named[labels["guide"], labels["stripe"]] = True
        assert not (named & hidden).any()
        labelled += len(labels["uv"])
    assert labelled > 0.3 * len(cap.cameras) * cap.stripes.sum()


def test_each_label_sits_on_pixels_of_its_stripes_dye(capture):
    _, cap, _ = capture
    hits, total, seen_colors = 0, 0, set()
    for cam in cap.cameras:
        image = np.asarray(Image.open(cap.image_path(cam.name, cap.frames[0])), np.float64)
        labels = _first_frame_labels(cap, cam.name)
        for stripe, (u, v) in zip(labels["stripe"], labels["uv"]):
            color = STRIPE_COLORS[stripe % 3]
            channel = int(np.argmax(DYES[color]))
            rgb = image[int(v), int(u)]
            others = np.delete(rgb, channel)
            hits += rgb[channel] > 1.8 * others.max()
            total += 1
            seen_colors.add(color)
    assert seen_colors == set(STRIPE_COLORS)
    assert hits >= 0.9 * total


def test_background_images_have_no_dye_and_the_noise_has_the_asked_spread(capture):
    _, cap, config = capture
    for cam in cap.cameras:
        image = np.asarray(Image.open(cap.background_path(cam.name)), np.float64)
        ratio = image.max(2) / np.maximum(np.sort(image, 2)[..., 1], 1.0)
        assert np.mean(ratio > 1.8) < 1e-3  # skin and backdrop only: no strongly dyed pixels
    # the white backdrop is 255 plus rounded, clipped Gaussian noise: compare its mean shortfall
    image = np.asarray(Image.open(cap.background_path("ring_0")), np.float64)
    corner = image[:12, :40].ravel()
    model = np.clip(np.rint(255.0 + np.random.default_rng(0).normal(0.0, config.noise, 200000)), 0, 255)
    assert np.mean(255.0 - corner) == pytest.approx(np.mean(255.0 - model), rel=0.15)


# -- bad input --------------------------------------------------------------------------------------
def test_unknown_capture_key_names_the_key(tmp_path):
    path = _scene_file(tmp_path, SCENE.replace("stripe_width = 0.04", "stripe_widht = 0.04"))
    with pytest.raises(InputError) as err:
        load_capture_scene(path)
    assert err.value.key == "capture.stripe_widht" and "stripe_width" in err.value.reason


def test_negative_stripe_width_names_the_key(tmp_path):
    path = _scene_file(tmp_path, SCENE.replace("stripe_width = 0.04", "stripe_width = -0.04"))
    with pytest.raises(InputError) as err:
        load_capture_scene(path)
    assert err.value.key == "capture.stripe_width" and "positive" in err.value.reason


def test_bad_size_and_wrong_types_name_their_option(tmp_path):
    args = argparse.Namespace(scene=_scene_file(tmp_path), output=str(tmp_path / "out"), frames=None, size="wide",
                              noise=None, occlusion=None, guides=None, seed=None, background_hair=None, device=None,
                              quiet=True)
    with pytest.raises(InputError) as err:
        run_synth(args)
    assert err.value.key == "--size"
    path = _scene_file(tmp_path, SCENE.replace("noise = 3.0", 'noise = "high"'))
    with pytest.raises(InputError) as err:
        load_capture_scene(path)
    assert err.value.key == "capture.noise"
    with pytest.raises(InputError) as err:
        load_capture_scene(_scene_file(tmp_path, SCENE + "\n[studio]\nlights = 3\n"))
    assert err.value.key == "[studio]"


def test_a_failed_capture_leaves_nothing_behind_and_a_foreign_folder_is_not_overwritten(tmp_path):
    scene, config = load_capture_scene(_scene_file(tmp_path), {"scene": {"frames": 1}}, {"guides": 500})
    out = tmp_path / "out"
    with pytest.raises(InputError) as err:
        synthesize(scene, config, out, progress=False)
    assert err.value.key == "capture.guides"
    assert not out.exists() and not [p for p in os.listdir(tmp_path) if "partial" in p]
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    with pytest.raises(InputError):
        synthesize(scene, config, out, progress=False)
    assert (out / "notes.txt").read_text() == "keep me"
