"""Projecting a face onto a moving mask: calibration homographies, LED tracking and labelling,
Kalman prediction across the capture-to-projection latency, projector frames, and `cfx mask`."""

import argparse
import gc
import json
import os

import numpy as np
import pytest

from sim.errors import InputError
from sim.mask import (MARKERS, LedTrack, MaskMotion, MaskRig, add_mask_arguments, apply_homography, drawn_face,
                      detect_leds, face_to_projector, homography_8x8, homography_affine_lsq, label_leds, led_image,
                      predict_track, projection_error, projector_frame, read_track, run_mask, synthetic_track,
                      transfer_error, write_track)


def _quad(rng, size=640.0):
    """Four points, one near each corner of a size x size square: never three in a line."""
    base = np.array([[0.1, 0.1], [0.9, 0.1], [0.9, 0.9], [0.1, 0.9]]) * size
    return base + rng.uniform(-0.08, 0.08, (4, 2)) * size


def _pose(roll_deg=0.0, yaw_deg=0.0, pitch_deg=0.0, shift=(0.0, 0.0, 0.0)):
    """Mask-to-world pose at the stage centre (the default calibration pose) turned and shifted."""
    from sim.mask import _rotation

    pose = np.eye(4)
    pose[:3, :3] = _rotation(*(np.radians([[yaw_deg], [pitch_deg], [roll_deg]])))[0]
    pose[:3, 3] = np.array([0.0, 1.6, 0.0]) + shift
    return pose


# -- calibration ------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_homography_8x8_maps_four_points_within_1e_6_and_agrees_with_skimage(seed):
    from skimage.transform import estimate_transform

    rng = np.random.default_rng(seed)
    camera, projector = _quad(rng, 640.0), _quad(rng, 1024.0)
    H = homography_8x8(camera, projector)
    assert H[2, 2] == 1.0
    assert np.abs(apply_homography(H, camera) - projector).max() < 1e-6
    reference = estimate_transform("projective", camera, projector).params
    np.testing.assert_allclose(H, reference / reference[2, 2], rtol=1e-7, atol=1e-10)


def test_homography_8x8_rows_are_the_linearised_projection():
    # each pair satisfies x' = h1 x + h2 y + h3 - h7 x x' - h8 y x' (and its y' twin) with h9 = 1
    rng = np.random.default_rng(7)
    src, dst = _quad(rng), _quad(rng)
    h = homography_8x8(src, dst).ravel()
    x, y = src.T
    xp, yp = dst.T
    np.testing.assert_allclose(h[0] * x + h[1] * y + h[2] - h[6] * x * xp - h[7] * y * xp, xp, atol=1e-8)
    np.testing.assert_allclose(h[3] * x + h[4] * y + h[5] - h[6] * x * yp - h[7] * y * yp, yp, atol=1e-8)


def test_homography_8x8_rejects_three_collinear_points():
    with pytest.raises(ValueError, match="collinear"):
        homography_8x8([[0, 0], [1, 1], [2, 2], [0, 5]], [[0, 0], [1, 0], [1, 1], [0, 1]])


def test_affine_lsq_is_exact_for_an_affine_map():
    rng = np.random.default_rng(3)
    A = np.array([[0.93, -0.12, 41.0], [0.08, 1.07, -17.5], [0.0, 0.0, 1.0]])
    for n in (4, 9):
        camera = rng.uniform(0.0, 640.0, (n, 2))
        H = homography_affine_lsq(camera, apply_homography(A, camera))
        np.testing.assert_allclose(H, A, rtol=1e-10, atol=1e-9)
        assert transfer_error(H, camera, apply_homography(A, camera)).max() < 1e-9


def test_affine_lsq_leaves_the_least_squares_residual_for_a_projective_map():
    rng = np.random.default_rng(4)
    camera, projector = _quad(rng), _quad(rng)
    H = homography_affine_lsq(camera, projector)
    np.testing.assert_array_equal(H[2], [0.0, 0.0, 1.0])
    residual = transfer_error(H, camera, projector)
    # the same fit by an independent least-squares solve of [x y 1] M = [x' y']
    design = np.hstack([camera, np.ones((4, 1))])
    M, *_ = np.linalg.lstsq(design, projector, rcond=None)
    expected = np.linalg.norm(design @ M - projector, axis=1)
    assert residual.max() > 1.0  # not exact: a projective map is not affine
    np.testing.assert_allclose(residual, expected, rtol=1e-9, atol=1e-9)


def test_default_rig_calibration_maps_the_mask_on_its_calibration_plane_exactly():
    rig = MaskRig.default(640, 480)
    pose = _pose(roll_deg=35.0, shift=(0.2, -0.1, 0.0))  # moved within the calibration plane
    camera, projector = rig.camera_points(pose)[0], rig.projector_points(pose)[0]
    assert np.abs(apply_homography(rig.calibration, camera) - projector).max() < 1e-6
    # the paper's far-away (affine) assumption is good to about a pixel at stage distance
    affine = homography_affine_lsq(rig.camera_points(_pose())[0, :4], rig.projector_points(_pose())[0, :4])
    assert transfer_error(affine, camera, projector).max() < 1.5


# -- LEDs -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("roll", [0.0, 30.0, 60.0, 90.0, 135.0, 179.0, 180.0, -45.0, -90.0, -150.0])
def test_led_detection_finds_centres_within_a_tenth_pixel_and_labels_them_at_any_roll(roll):
    rig = MaskRig.default(640, 480)
    truth = rig.camera_points(_pose(roll_deg=roll, yaw_deg=20.0, pitch_deg=-12.0))[0]
    image = led_image(truth, 640, 480, noise=0.02, seed=int(roll) % 1000)
    image[10, 20] = 1.0  # a hot pixel: below the area floor
    image[400:430, 500:530] = 0.9  # a reflection: above the area ceiling
    found = detect_leds(image)
    assert len(found) == 5
    labelled = label_leds(found)
    assert np.linalg.norm(labelled - truth, axis=1).max() < 0.1


def test_label_leds_reports_a_dropped_frame_when_an_led_is_missing_or_the_label_is_on_the_hull():
    rig = MaskRig.default(640, 480)
    truth = rig.camera_points(_pose())[0]
    assert np.isnan(label_leds(truth[:4])).all()
    square = np.array([[0, 0], [10, 0], [10, 10], [0, 10], [5, -3]], float)  # fifth outside: no label
    assert np.isnan(label_leds(square)).all()


# -- latency prediction -----------------------------------------------------------------------------
@pytest.mark.parametrize("model", ["velocity", "acceleration"])
def test_kalman_prediction_at_least_halves_the_projection_error_at_100ms_latency(model):
    rig = MaskRig.default(320, 240)
    motion = MaskMotion(seed=5)
    track = synthetic_track(rig, motion, frames=120, fps=30.0, seed=5)
    latency = 0.1
    truth = rig.projector_points(motion.poses(track.times + latency))[:, :4]
    warmup = 15
    without = projection_error(track.leds[:, :4], truth, track.calibration)[warmup:]
    predicted = projection_error(predict_track(track, latency, model), truth, track.calibration)[warmup:]
    assert np.isfinite(without).all() and np.isfinite(predicted).all()
    assert without.mean() > 3.0  # the latency is visible to begin with
    assert predicted.mean() <= 0.5 * without.mean()
    assert predicted.max() <= 0.75 * without.max()


def test_constant_velocity_filter_extrapolates_straight_motion_exactly_at_irregular_times():
    from sim.mask import LatencyPredictor

    start = np.array([[100.0, 80.0], [180.0, 82.0], [178.0, 190.0], [98.0, 188.0]])
    velocity = np.array([120.0, -45.0])  # px/s, every corner
    times = np.cumsum(np.r_[0.0, np.random.default_rng(0).uniform(0.02, 0.045, 59)])
    predictor = LatencyPredictor(0.1, "velocity")
    for t in times:
        predicted = predictor.update(t, start + velocity * t)
    np.testing.assert_allclose(predicted, start + velocity * (times[-1] + 0.1), atol=0.05)


def test_recorded_truth_interpolates_the_track_at_display_time():
    from sim.mask import recorded_truth

    rig = MaskRig.default(320, 240)
    times = np.arange(10) / 30.0
    base = rig.camera_points(_pose())[0]
    leds = base[None] + np.array([60.0, 15.0]) * times[:, None, None]  # straight at 60, 15 px/s
    track = LedTrack(times, leds, (320, 240), rig.calibration, 30.0)
    truth = recorded_truth(track, 0.05)
    expected = apply_homography(rig.calibration, leds[:, :4] + np.array([60.0, 15.0]) * 0.05)
    np.testing.assert_allclose(truth[:8], expected[:8], atol=1e-9)
    assert np.isnan(truth[8:]).all()  # shown after the last capture: unknown


def test_prediction_coasts_through_dropped_frames():
    rig = MaskRig.default(320, 240)
    motion = MaskMotion(seed=2)
    track = synthetic_track(rig, motion, frames=60, fps=30.0, seed=2)
    track.leds[30:33] = np.nan  # the LEDs were not all seen for three frames
    predicted = predict_track(track, 0.1)
    truth = rig.projector_points(motion.poses(track.times + 0.1))[:, :4]
    error = projection_error(predicted, truth, track.calibration)
    assert np.isfinite(predicted).all()
    assert error[30:33].max() < 3.0 * error[15:30].max()


# -- projector frames -------------------------------------------------------------------------------
def _distance_to_quad_edges(points, quad):
    a, b = quad, np.roll(quad, -1, axis=0)
    ab = b - a
    t = np.clip(np.einsum("nkd,kd->nk", points[:, None] - a, ab) / np.sum(ab * ab, axis=1), 0.0, 1.0)
    closest = a + t[..., None] * ab
    return np.linalg.norm(points[:, None] - closest, axis=2).min(axis=1)


def test_projector_frame_puts_the_face_image_on_the_projected_mask_quad():
    from skimage.draw import polygon

    w, h = 320, 240
    rig = MaskRig.default(w, h)
    pose = _pose(roll_deg=25.0, shift=(0.15, 0.05, 0.0))
    camera = rig.camera_points(pose)[0, :4]
    projector = rig.projector_points(pose)[0, :4]  # on the calibration plane: H is exact

    lit = projector_frame(np.ones((330, 240)), camera, rig.calibration, (w, h)).max(axis=2) > 0
    rows, cols = polygon(projector[:, 1] - 0.5, projector[:, 0] - 0.5, (h, w))
    inside = np.zeros((h, w), bool)
    inside[rows, cols] = True
    r, c = np.nonzero(lit ^ inside)
    assert lit.sum() > 1000
    assert _distance_to_quad_edges(np.stack([c + 0.5, r + 0.5], 1), projector).max() < 1.5

    face = drawn_face(240, 330)
    frame = projector_frame(face, camera, rig.calibration, (w, h))
    m = max(4, 240 // 10)
    centres = np.array([[m / 2, m / 2], [240 - m / 2, m / 2], [240 - m / 2, 330 - m / 2], [m / 2, 330 - m / 2]])
    where = apply_homography(face_to_projector(face.shape, camera, rig.calibration), centres)
    for (u, v), colour in zip(where, MARKERS):
        assert np.abs(frame[int(v), int(u)].astype(int) - colour).max() < 40


def test_projector_frame_is_black_when_the_mask_is_unknown():
    rig = MaskRig.default(64, 48)
    frame = projector_frame(drawn_face(), np.full((4, 2), np.nan), rig.calibration, (64, 48))
    assert frame.shape == (48, 64, 3) and not frame.any()


# -- track files ------------------------------------------------------------------------------------
def test_track_written_and_read_back_keeps_times_points_and_calibration(tmp_path):
    rig = MaskRig.default(320, 240)
    track = synthetic_track(rig, MaskMotion(seed=1), frames=8, fps=60.0)
    track.leds[3] = np.nan
    path = tmp_path / "track.json"
    write_track(path, track)
    back = read_track(path)
    np.testing.assert_allclose(back.times, track.times, atol=1e-6)
    np.testing.assert_allclose(back.leds, track.leds, atol=1e-3)  # NaN rows compare equal
    np.testing.assert_allclose(back.calibration, track.calibration, rtol=1e-5, atol=1e-8)
    assert back.camera_size == (320, 240) and back.fps == 60.0


def test_csv_track_labels_leds_given_in_any_order(tmp_path):
    rig = MaskRig.default(640, 480)
    truth = rig.camera_points(_pose(roll_deg=120.0))[0]
    rows = ["time,u1,v1,u2,v2,u3,v3,u4,v4,u5,v5"]
    for k, order in enumerate(([4, 2, 0, 3, 1], [1, 3, 4, 0, 2])):
        rows.append(",".join([f"{k / 30:.6f}"] + [f"{c:.4f}" for c in truth[order].ravel()]))
    rows.append("0.1," + "," * 9)  # a frame without a detection
    path = tmp_path / "track.csv"
    path.write_text("\n".join(rows) + "\n")
    track = read_track(path, rig)
    np.testing.assert_allclose(track.leds[:2], np.stack([truth, truth]), atol=1e-3)
    assert np.isnan(track.leds[2]).all()


def _json(tmp_path, doc):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc) if not isinstance(doc, str) else doc)
    return path


GOOD_FRAME = {"time": 0.0, "leds": [[100, 100], [200, 100], [200, 240], [100, 240], [125, 125]]}


@pytest.mark.parametrize("doc, key", [
    ({"frames": [GOOD_FRAME, {"time": 0.1, "leds": [[1, 2], [3]]}]}, "frames[1].leds"),
    ({"frames": [GOOD_FRAME, {"time": "soon", "leds": []}]}, "frames[1].time"),
    ({"frames": [GOOD_FRAME, {"leds": []}]}, "frames[1].time"),
    ({"frames": [GOOD_FRAME, {"time": 0.0, "leds": []}]}, "time"),
    ({"frames": []}, "frames"),
    ({"frames": [GOOD_FRAME], "camera_size": [640]}, "camera_size"),
    ({"frames": [GOOD_FRAME], "calibration": {"camera": [[0, 0]] * 4}}, "calibration"),
    ({"frames": [GOOD_FRAME], "calibraton": {}}, "calibraton"),
    ({"frames": [{"time": 0.0, "leds": [[0, 0], [1, 1]]}]}, "frames"),
    ("{\"frames\": [", None),
])
def test_malformed_json_track_raises_input_error_naming_the_file_and_key(tmp_path, doc, key):
    path = _json(tmp_path, doc)
    with pytest.raises(InputError) as err:
        read_track(path)
    assert err.value.source == str(path)
    assert err.value.key == key
    assert str(path) in str(err.value)


def test_malformed_csv_track_raises_input_error_naming_the_line_and_column(tmp_path):
    path = tmp_path / "bad.csv"
    path.write_text("time,u1,v1,u2,v2,u3,v3,u4,v4,u5,v5\n0.0,1,2,3,4,5,6,7,8,9,10\n0.1,1,x,3,4,5,6,7,8,9,10\n")
    with pytest.raises(InputError) as err:
        read_track(path)
    assert (err.value.source, err.value.key) == (str(path), "line 3.v1")


def test_missing_track_file_raises_input_error(tmp_path):
    with pytest.raises(InputError, match="no such track file"):
        read_track(tmp_path / "nope.json")


# -- cfx mask ---------------------------------------------------------------------------------------
def _args(*argv):
    parser = argparse.ArgumentParser()
    add_mask_arguments(parser)
    if "--cache" not in argv and "--face" not in argv:
        argv = (*argv, "--face", "drawn")  # the flat test face: no simulation needed
    return parser.parse_args([str(a) for a in argv])


def _frames(path):
    import imageio.v2 as imageio

    with imageio.get_reader(str(path), format="FFMPEG") as reader:
        return [frame for frame in reader]


def test_run_mask_writes_a_playable_mp4_and_reports_both_errors(tmp_path, capsys):
    out, sheet, saved = tmp_path / "mask.mp4", tmp_path / "sheet.png", tmp_path / "track.json"
    status = run_mask(_args("-o", out, "--size", "160x120", "--frames", 18, "--sheet", sheet,
                            "--save-track", saved, "-q"))
    assert status == 0
    frames = _frames(out)
    assert len(frames) == 18 and frames[0].shape == (120, 160, 3)
    assert max(f.max() for f in frames) > 100  # the face is in the picture
    err = capsys.readouterr().err
    assert "no prediction:" in err and "Kalman prediction:" in err and "nan" not in err  # frames 16-18 measured
    assert sheet.stat().st_size > 0 and len(read_track(saved)) == 18
    assert sorted(os.listdir(tmp_path)) == ["mask.mp4", "sheet.png", "track.json"]  # no partial files

    replay = tmp_path / "replay.mp4"
    assert run_mask(_args(saved, "-o", replay, "--size", "160x120", "--no-predict", "-q")) == 0
    assert len(_frames(replay)) == 18


def test_run_mask_renders_the_face_from_a_usd_cache(tmp_path):
    from io_usd.cache import CacheWriter
    from sim.head import procedural_head

    head = procedural_head(rings=24, segments=20)
    cache = tmp_path / "head.usdc"
    with CacheWriter(str(cache), fps=24, start_frame=1, end_frame=2) as writer:
        writer.add_mesh("head", "collider", head.vertices, head.faces)
        for f in (1, 2):
            writer.write_frame(f, {"head": head.vertices})
    out = tmp_path / "face.mp4"
    assert run_mask(_args("-o", out, "--cache", cache, "--size", "96x72", "--frames", 3, "-q")) == 0
    assert len(_frames(out)) == 3


def test_run_mask_leaves_nothing_at_the_output_when_it_fails(tmp_path, monkeypatch):
    import sim.mask

    calls = []

    def failing_face(width=240, height=330, time=0.0):
        calls.append(time)
        if len(calls) > 1:  # a movie writer started, ffmpeg not yet at its output file
            raise RuntimeError("renderer died")
        return drawn_face(width, height, time)

    monkeypatch.setattr(sim.mask, "drawn_face", failing_face)
    with pytest.raises(RuntimeError):
        run_mask(_args("-o", tmp_path / "mask.mp4", "--size", "96x72", "--frames", 8, "-q"))
    gc.collect()  # a movie writer left open would finish its file now, after the clean-up
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("argv, source", [
    (["--size", "161x120"], "--size"),
    (["--size", "big"], "--size"),
    (["--latency", "-0.1"], "--latency"),
    (["--frames", "0"], "--frames"),
])
def test_run_mask_rejects_bad_options_with_input_error(tmp_path, argv, source):
    with pytest.raises(InputError) as err:
        run_mask(_args("-o", tmp_path / "m.mp4", *argv))
    assert err.value.source == source


def test_run_mask_rejects_an_output_that_is_not_mp4(tmp_path):
    with pytest.raises(InputError, match="mp4"):
        run_mask(_args("-o", tmp_path / "m.gif"))


def test_synthetic_track_is_seeded():
    rig = MaskRig.default(160, 120)
    a = synthetic_track(rig, MaskMotion(seed=9), frames=5, seed=9)
    b = synthetic_track(rig, MaskMotion(seed=9), frames=5, seed=9)
    assert isinstance(a, LedTrack)
    np.testing.assert_array_equal(a.leds, b.leds)


def test_run_mask_projects_the_built_in_talking_face_by_default(tmp_path):
    out = tmp_path / "mask.mp4"
    assert run_mask(_args("-o", out, "--face", "builtin", "--size", "320x240", "--frames", 3, "-q")) == 0
    import imageio.v3 as iio

    frames = iio.imread(out)
    assert frames.shape[0] == 3
    skin = frames[..., 0].astype(int) - frames[..., 2].astype(int)
    assert (skin > 30).sum() > 50  # warm skin tones of the rendered face land in the projector image


def test_a_track_shorter_than_the_filters_settling_says_no_error_was_measured(tmp_path, capsys):
    out = tmp_path / "short.mp4"
    assert run_mask(_args("-o", out, "--size", "64x48", "--frames", 6, "-q")) == 0
    err = capsys.readouterr().err
    assert "none measured: the errors count from frame 16" in err and "the track has 6 frames" in err
    assert "nan" not in err and "calibration alone" not in err


def test_outputs_are_checked_before_the_track_is_rendered(tmp_path):
    (tmp_path / "afile").write_text("")
    for args, reason in [(("-o", tmp_path / "m.avi"), "the output must end in .mp4, not .avi"),
                         (("-o", tmp_path / "m.mp4", "--sheet", tmp_path / "afile" / "s.png"), "afile is not a folder"),
                         (("-o", tmp_path / "m.mp4", "--save-track", tmp_path / "t.csv"), "must end in .json")]:
        with pytest.raises(InputError, match=reason):
            run_mask(_args(*args, "-q"))
    assert os.listdir(tmp_path) == ["afile"]
