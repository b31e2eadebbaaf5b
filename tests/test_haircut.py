"""Haircut studio: cuts, thinning, grow, erase, wax and initialise on simulated strands, the
[[haircut]] timeline, and caches whose curve topology changes from frame to frame."""

import numpy as np
import pytest

from io_usd.cache import CacheReader, CacheWriter
from io_usd.preview import Camera
from io_usd.validate import validation_errors
from sim import haircut, strokes
from sim.errors import InputError
from sim.graphs import FrameGraphs
from sim.scene import Scene, _build_config, load_scene, run_scene

FRONT = Camera.look_at((0.0, 0.3, 1.0), (0.0, 0.3, 0.0), yfov=0.6, width=480, height=360)
CAMERA_TABLE = {"eye": [0.0, 0.3, 1.0], "target": [0.0, 0.3, 0.0], "yfov": 0.6, "width": 480, "height": 360}


def config(events=(), frames=6, count=60, animation="none", **hair):
    data = {"scene": {"frames": frames, "preroll": 0.0, "stats": False}, "head": {"animation": animation},
            "hair": {"style": "straight", "count": count, "length": 0.3, "vertices": 12, **hair}}
    if events:
        data["haircut"] = [dict(e) for e in events]
    return _build_config("<test>", data, None)


def settled(frames=6, **kw):
    scene = Scene(config(**kw))
    scene.advance(frames / 24.0)
    return scene


def strand_mask(groom, strands):
    keep = np.zeros(len(groom.counts), bool)
    keep[strands] = True
    return np.repeat(keep, groom.counts)


def polyline_lengths(points, counts):
    return haircut.Groom(points, points, points, np.zeros(len(points)), np.zeros(len(points)), np.asarray(counts),
                         np.arange(len(counts))).lengths()


# -- cuts -------------------------------------------------------------------------------------------
def test_blunt_cut_puts_every_new_tip_on_the_plane_and_leaves_other_strands_bitwise():
    scene = settled()
    before = haircut.groom_of(scene)
    plane = haircut.Plane(point=(0.0, 0.26, 0.0), normal=(0.0, 1.0, 0.25))
    section = haircut.Sphere((0.0, 0.38, -0.06), 0.09)  # the back: some strands stay uncut
    seg, frac = haircut.first_crossings(before.x, before.counts, plane.surface(), 2,
                                        section.contains(before.x[before.start]))
    edit = haircut.blunt_cut(scene, plane, section)
    after = haircut.groom_of(scene)

    cut = edit.strands
    assert 5 < len(cut) < len(before.counts) - 5
    np.testing.assert_array_equal(np.sort(cut), np.flatnonzero(seg >= 0))
    n = np.asarray(plane.normal) / np.linalg.norm(plane.normal)
    tips = after.x[after.tips[cut]].astype(np.float64)
    assert np.abs((tips - plane.point) @ n).max() < 1e-5
    # the rest shape is truncated at the same fraction of the crossed segment
    rest_len = scene.model.rest_length_np[after.tips[cut]]
    original = np.linalg.norm(before.rest[seg[cut] + 1].astype(np.float64) - before.rest[seg[cut]], axis=1)
    np.testing.assert_allclose(rest_len, frac[cut] * original, atol=1e-6)
    assert np.all(after.counts[cut] == seg[cut] - before.start[cut] + 2)
    # strands the cut did not reach: positions, velocities and rest shape untouched, bit for bit
    uncut = np.setdiff1d(np.arange(len(before.counts)), cut)
    for name in ("x", "v", "rest", "widths"):
        np.testing.assert_array_equal(getattr(before, name)[strand_mask(before, uncut)],
                                      getattr(after, name)[strand_mask(after, uncut)])
    # the kept particles of cut strands carried over too, and the run goes on
    kept = np.concatenate([np.arange(before.start[s], seg[s] + 1) for s in cut])
    kept_after = np.concatenate([np.arange(after.start[s], after.tips[s]) for s in cut])
    np.testing.assert_array_equal(before.x[kept], after.x[kept_after])
    scene.advance(4 / 24.0)
    assert np.all(np.isfinite(scene.state.x.numpy()))


def test_blunt_cut_along_a_screen_stroke_ends_strands_on_the_view_rays_through_it():
    scene = settled()
    stroke = haircut.Stroke([[120, 240], [240, 250], [360, 240]], FRONT)
    edit = haircut.blunt_cut(scene, stroke)
    g = haircut.groom_of(scene)
    tips = g.x[g.tips[edit.strands]]
    assert len(edit.strands) > 10
    assert edit.surface.distance(tips).max() < 1e-5
    # seen through the camera, every new tip lies on the drawn stroke
    assert strokes.stroke_distance(tips, FRONT, stroke.pixels).max() < 1e-2


def test_chop_cut_tips_lie_on_the_zigzag_and_spread_across_its_teeth():
    scene = settled()
    plane = haircut.Plane((0.0, 0.25, 0.0), (0.0, 1.0, 0.0))
    edit = haircut.chop_cut(scene, plane, amplitude=0.015, period=0.02, seed=3, jitter=0.0)
    g = haircut.groom_of(scene)
    tips = g.x[g.tips[edit.strands]].astype(np.float64)
    assert len(edit.strands) > 20
    assert edit.surface.distance(tips).max() < 1e-5
    height = tips[:, 1] - 0.25  # on the zigzag, not on the flat plane
    assert np.abs(height).max() <= 0.015 + 1e-5 and np.ptp(height) > 0.015
    # the zigzag itself: a triangle wave of the across coordinate with the seeded phase
    again = plane.zigzag(0.015, 0.02, seed=3, jitter=0.0, points=g.x)
    assert again.distance(tips).max() < 1e-5


def test_chop_along_a_stroke_cuts_on_the_jagged_stroke():
    scene = settled()
    stroke = haircut.Stroke([[120, 245], [360, 245]], FRONT)
    edit = haircut.chop_cut(scene, stroke, amplitude=8.0, period=24.0, seed=1)
    g = haircut.groom_of(scene)
    tips = g.x[g.tips[edit.strands]]
    jagged = haircut.zigzag_stroke(stroke.pixels, 8.0, 24.0, seed=1)
    assert strokes.stroke_distance(tips, FRONT, jagged).max() < 1e-2
    rows = FRONT.project(tips)[:, 1]
    assert rows.min() >= 245 - 8.0 - 1e-3 and rows.max() <= 245 + 8.0 + 1e-3 and np.ptp(rows) > 4.0


def test_thinning_with_a_seed_repeats_and_every_new_tip_lies_beyond_the_line():
    plane = haircut.Plane((0.0, 0.3, 0.0), (0.0, 1.0, 0.0))
    runs = []
    for seed in (5, 5, 6):
        scene = settled()
        edit = haircut.thinning_cut(scene, plane, fraction=0.5, seed=seed)
        runs.append((edit.strands, haircut.groom_of(scene)))
    (a, ga), (b, gb), (_, gc) = runs
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(ga.counts, gb.counts)
    np.testing.assert_array_equal(ga.x, gb.x)
    assert not np.array_equal(ga.counts, gc.counts)
    crossing = 60  # every strand of this groom hangs through the plane
    assert 0.25 * crossing < len(a) < 0.75 * crossing
    tips = ga.x[ga.tips[a]]
    assert np.all(tips[:, 1] < 0.3)  # beyond the line, on the side away from the roots
    assert np.all(ga.counts[a] < 12)


# -- grow, erase, wax, initialise -------------------------------------------------------------------
def test_grow_adds_exactly_the_requested_length_to_the_strands_rooted_in_the_region():
    scene = settled()
    before = haircut.groom_of(scene)
    region = haircut.Sphere((0.0, 0.45, 0.0), 0.06)
    inside = region.contains(before.x[before.start])
    edit = haircut.grow(scene, 0.045, region)
    after = haircut.groom_of(scene)
    np.testing.assert_array_equal(edit.strands, np.flatnonzero(inside))
    np.testing.assert_allclose(after.natural_lengths() - before.natural_lengths(), 0.045 * inside, atol=1e-6)
    np.testing.assert_allclose(after.lengths() - before.lengths(), 0.045 * inside, atol=1e-5)
    np.testing.assert_allclose(scene.model.natural_length_np, after.natural_lengths(), atol=1e-6)
    # in segments as close to the strand's own rest spacing as divide the length evenly
    spacing = before.natural_lengths() / (before.counts - 1)
    added = np.round(0.045 / spacing[inside])
    np.testing.assert_array_equal(after.counts[inside], before.counts[inside] + added)
    assert np.all(np.abs(0.045 / added - spacing[inside]) <= 0.5 * spacing[inside])
    # straight on along the last segment
    tip, parent = after.x[after.tips[inside]], after.x[after.tips[inside] - 2]
    last = before.x[before.tips[inside]] - before.x[before.tips[inside] - 1]
    direction = (tip - parent) / np.linalg.norm(tip - parent, axis=1, keepdims=True)
    np.testing.assert_allclose(direction, last / np.linalg.norm(last, axis=1, keepdims=True), atol=1e-5)


@pytest.mark.parametrize("brushed", [False, True])
def test_erase_removes_exactly_the_strands_rooted_in_the_region(brushed):
    scene = settled()
    before = haircut.groom_of(scene)
    roots = before.x[before.start]
    if brushed:
        region = haircut.Brush([[200, 60], [280, 60]], FRONT, radius=30.0)
        covered = strokes.stroke_distance(roots, FRONT, region.stroke) <= 30.0
        # a brush touches only what its camera sees: roots behind the crown stay
        seen = scene.collider.visible_from(roots, FRONT.eye)
        assert (covered & ~seen).any()
        inside = covered & seen
    else:
        region = haircut.Sphere((0.05, 0.42, 0.0), 0.05)
        inside = np.linalg.norm(roots - region.center, axis=1) <= 0.05
    assert 0 < inside.sum() < len(inside)
    edit = haircut.erase(scene, region)
    np.testing.assert_array_equal(edit.strands, np.flatnonzero(inside))
    after = haircut.groom_of(scene)
    assert scene.model.num_strands == len(before.counts) - inside.sum()
    np.testing.assert_array_equal(after.x, before.x[np.repeat(~inside, before.counts)])
    scene.advance(2 / 24.0)
    np.testing.assert_array_equal(scene.state.x.numpy()[scene.model.strand_start_np[:-1]], roots[~inside])


def test_erase_of_every_strand_is_refused():
    scene = settled(frames=1)
    with pytest.raises(ValueError, match="every strand"):
        haircut.erase(scene, haircut.Sphere((0.0, 0.3, 0.0), 5.0))


def waxed_scene(hold, drag=(60.0, -60.0)):
    scene = settled(frames=12)
    edit = haircut.wax(scene, haircut.Sphere((0.0, 0.42, 0.08), 0.05), drag=drag, camera=FRONT, select="roots",
                       hold=hold)
    return scene, edit


def test_wax_never_makes_a_strand_longer_than_its_natural_length():
    scene = settled(frames=12)
    before = haircut.groom_of(scene)
    edit = haircut.wax(scene, haircut.Sphere((0.0, 0.42, 0.08), 0.05), offset=(0.0, 2.0, 1.0), select="roots")
    after = haircut.groom_of(scene)
    s = edit.strands
    assert len(s) >= 3
    natural = before.natural_lengths()[s]
    reach = np.linalg.norm(after.x[after.tips[s]].astype(np.float64) - after.x[after.start[s]], axis=1)
    assert np.all(reach <= natural + 1e-5)
    np.testing.assert_allclose(after.lengths()[s], natural, atol=2e-5)  # re-laid with its rest lengths
    # pulled as far as it goes: straight out from the follicle (the last pinned particle) toward the target
    follicle = after.x[after.start[s] + 1].astype(np.float64)
    free = natural - np.linalg.norm(before.rest[before.start[s] + 1] - before.rest[before.start[s]], axis=1)
    tip = after.x[after.tips[s]].astype(np.float64)
    stretched = np.linalg.norm(tip - follicle, axis=1)
    assert np.all(stretched <= free + 1e-5) and np.all(stretched > 0.98 * free)  # the scalp bends it a little
    toward = np.array([0.0, 2.0, 1.0]) / np.sqrt(5.0)
    assert np.all((tip - follicle) @ toward > 0.95 * free)
    # only the tip was dragged: the pinned root particles did not move
    pinned = np.concatenate([before.start[s], before.start[s] + 1])
    np.testing.assert_array_equal(after.x[pinned], before.x[pinned])


def test_wax_drags_tips_parallel_to_the_screen_and_the_styled_shape_becomes_the_rest_shape():
    scene, edit = waxed_scene(hold=True)
    g = haircut.groom_of(scene)
    s = edit.strands
    tips = g.x[g.tips[s]]
    np.testing.assert_allclose(FRONT.depth(tips), FRONT.depth(edit.targets), atol=1e-6)
    np.testing.assert_allclose(tips, edit.targets, atol=1e-4)
    mask = strand_mask(g, s)
    np.testing.assert_allclose(scene.model.rest_positions_np[mask], g.x[mask], atol=1e-5)


def test_waxed_shape_holds_under_gravity_and_an_unwaxed_drag_falls_back():
    moved = {}
    for hold in (True, False):
        scene, edit = waxed_scene(hold)
        g = haircut.groom_of(scene)
        styled = g.x[g.tips[edit.strands]].copy()
        scene.advance(24 / 24.0)
        g = haircut.groom_of(scene)
        moved[hold] = np.linalg.norm(g.x[g.tips[edit.strands]] - styled, axis=1).mean()
    assert moved[False] > 0.02
    assert moved[True] < 0.1 * moved[False]


def test_wax_on_a_turned_head_stores_the_rest_shape_in_the_groom_pose():
    scene = Scene(config(animation="turn"))
    scene.advance(0.5)  # the head has turned away from the pose the groom was bound on
    edit = haircut.wax(scene, haircut.Sphere((0.0, 0.42, 0.08), 0.08), offset=(0.02, 0.03, 0.0), select="roots")
    _, to_world = haircut._pose_maps(scene, scene.model)
    g = haircut.groom_of(scene)
    mask = strand_mask(g, edit.strands)
    world = to_world(scene.model.rest_positions_np[mask], scene.model.particle_strand_np[mask])
    np.testing.assert_allclose(world, g.x[mask], atol=2e-5)
    scene.advance(0.25)
    assert np.all(np.isfinite(scene.state.x.numpy()))


def test_a_timeline_wax_drags_over_its_frames_and_ends_where_one_at_once_does():
    table = {"frame": 4, "tool": "wax", "sphere": {"center": [0.0, 0.42, 0.08], "radius": 0.05}, "select": "roots",
             "offset": [0.0, 0.06, 0.04]}
    runs = {}
    for until in (None, 9):
        scene = Scene(config([table if until is None else dict(table, until=until)], frames=12))
        events, tips, last = scene.config.haircut, [], None
        for frame in range(1, 11):
            if frame > 1:
                scene.advance(1.0 / 24.0)
            for edit in haircut.run_events(scene, events, frame):
                last = edit
            if last is not None:
                g = haircut.groom_of(scene)
                tips.append(g.x[g.tips[last.strands]].astype(np.float64))
        assert scene.wax_drags == {}
        runs[until] = last, np.array(tips)
    (at_once, _), (eased, tips_eased) = runs[None], runs[9]
    assert len(at_once.strands) >= 3
    np.testing.assert_array_equal(eased.strands, at_once.strands)
    np.testing.assert_allclose(eased.targets, at_once.targets, atol=1e-5)  # the same goal, reached at frame 9
    total = np.linalg.norm(eased.targets - tips_eased[0], axis=1)
    steps = np.linalg.norm(np.diff(tips_eased, axis=0), axis=2)
    assert total.mean() > 0.05
    # smoothstep over the six frames 4..9: at most 26% of the way in a frame (the one-frame wax: all of it)
    assert np.all(steps[:5] <= 0.27 * total + 1e-3) and np.all(steps[:5].sum(axis=0) > 0.7 * total)
    assert np.all(steps[5:] < 2e-3)  # then the wax holds the styled shape


def test_a_cut_during_a_wax_drag_is_refused_with_its_key():
    wax = {"frame": 2, "tool": "wax", "sphere": {"center": [0, 0.4, 0], "radius": 0.1}, "offset": [0, 0.1, 0],
           "until": 6}
    cut = {"frame": 4, "tool": "blunt", "plane": {"point": [0, 0.2, 0], "normal": [0, 1, 0]}}
    data = {"hair": {"count": 10}, "haircut": [wax, cut]}
    with pytest.raises(InputError) as err:
        _build_config("cut.toml", data, None)
    assert err.value.key == "haircut[1].frame" and "until frame 6" in str(err.value)
    _build_config("cut.toml", {"hair": {"count": 10}, "haircut": [wax, dict(cut, frame=7)]}, None)


def test_initialise_returns_to_the_template_groom():
    scene = settled()
    template = scene.model
    haircut.blunt_cut(scene, haircut.Plane((0.0, 0.3, 0.0), (0.0, 1.0, 0.0)))
    haircut.erase(scene, haircut.Sphere((0.0, 0.47, 0.0), 0.04))
    assert scene.model.counts.sum() < template.counts.sum()
    haircut.initialise(scene)
    assert scene.model is template
    np.testing.assert_allclose(scene.state.x.numpy(), template.rest_positions_np, atol=1e-6)
    assert not scene.state.v.numpy().any()


# -- timeline and caches ----------------------------------------------------------------------------
EVENTS = [
    {"frame": 3, "tool": "blunt", "plane": {"point": [0.0, 0.24, 0.0], "normal": [0.0, 1.0, 0.0]}},
    {"frame": 5, "tool": "chop", "stroke": [[100, 225], [380, 225]], "camera": CAMERA_TABLE, "amplitude": 6,
     "period": 20, "seed": 2},
    {"frame": 7, "tool": "thinning", "plane": {"point": [0.0, 0.3, 0.0], "normal": [0.0, 1.0, 0.0]},
     "fraction": 0.5, "seed": 1},
    {"frame": 9, "tool": "grow", "length": 0.02, "sphere": {"center": [0.0, 0.45, 0.0], "radius": 0.05}},
    {"frame": 10, "tool": "erase", "stroke": [[240, 90]], "radius": 20, "camera": CAMERA_TABLE},
    {"frame": 11, "tool": "wax", "sphere": {"center": [0.0, 0.42, 0.08], "radius": 0.05}, "select": "roots",
     "drag": [40, -40], "camera": CAMERA_TABLE},
]


@pytest.fixture(scope="module")
def timeline_cache(tmp_path_factory):
    path = str(tmp_path_factory.mktemp("haircut") / "cut.usdc")
    counts = {}
    result = run_scene(config(EVENTS, frames=12), path, progress=False,
                       on_frame=lambda frame, scene: counts.__setitem__(frame, scene.model.counts.copy()))
    return path, counts, result


def total_length(reader, frame):
    return polyline_lengths(reader.points("hair", frame), reader.counts("hair", frame)).sum()


def test_cache_total_hair_length_falls_at_each_cut_and_rises_at_the_grow(timeline_cache):
    path, _, _ = timeline_cache
    reader = CacheReader(path)
    length = {f: total_length(reader, f) for f in reader.frames("hair")}
    for cut in (3, 5, 7):
        assert length[cut] < length[cut - 1] - 0.05, cut
    assert length[9] > length[8]
    assert length[10] < length[9]  # erased strands
    for steady in (2, 4, 6, 8, 12):  # between events the strands keep their length
        assert abs(length[steady] - length[steady - 1]) < 1e-3 * length[steady]


def test_cache_names_each_strand_across_the_erase(timeline_cache):
    """The uniform primvar strandId says which strand of the groom each curve is: the erase at frame 10
    removes some, and every id left names a curve whose root stays where that id's root was."""
    from pxr import Usd, UsdGeom

    path, _, _ = timeline_cache
    reader = CacheReader(path)
    primvar = UsdGeom.PrimvarsAPI(reader.stage.GetPrimAtPath("/World/hair")).GetPrimvar("strandId")
    assert primvar.GetInterpolation() == "uniform"
    ids = {f: np.asarray(primvar.Get(Usd.TimeCode(f))) for f in (9, 10)}
    before, after = ids[9], ids[10]
    np.testing.assert_array_equal(before, np.arange(60))
    assert 0 < len(after) < len(before) and np.all(np.diff(after) > 0)
    roots = {f: reader.points("hair", f)[np.concatenate([[0], np.cumsum(reader.counts("hair", f))[:-1]])]
             for f in (9, 10)}
    assert len(roots[10]) == len(after)
    np.testing.assert_allclose(roots[10], roots[9][after], atol=1e-3)  # the head is still: roots stay put


def test_cache_samples_curve_topology_per_frame_and_validates(timeline_cache):
    path, counts, result = timeline_cache
    reader = CacheReader(path)
    hair = reader.prims["hair"]
    assert hair.varying and result.strands == len(counts[12])
    for frame in reader.frames("hair"):
        np.testing.assert_array_equal(reader.counts("hair", frame), counts[frame])
        assert len(reader.points("hair", frame)) == counts[frame].sum() == len(reader.widths("hair", frame))
    np.testing.assert_array_equal(hair.counts, counts[1])
    assert len(counts[10]) < len(counts[9])
    assert validation_errors(path) == []
    assert reader.metadata["cfx:settings"]["haircut"]["0"]["tool"] == "blunt"


def test_preview_draws_the_strands_of_each_frame(timeline_cache):
    from io_usd.preview import SceneBuilder

    path, counts, _ = timeline_cache
    reader = CacheReader(path)
    builder = SceneBuilder(reader)
    for frame in (1, 3, 12):
        mesh = builder.mesh("hair", frame, FRONT.eye, FRONT.focal)
        assert len(mesh.primitives[0].positions) == 2 * counts[frame].sum()


def test_writer_samples_topology_only_once_it_changes(tmp_path):
    path = str(tmp_path / "t.usda")
    pts = np.random.default_rng(0).normal(size=(9, 3))
    with CacheWriter(path, 24, 1, 4) as w:
        w.add_curves("hair", "hair", [4, 5], np.full(9, 1e-4))
        w.write_frame(1, {"hair": pts}, curves={"hair": ([4, 5], np.full(9, 1e-4))})
        w.write_frame(2, {"hair": pts}, curves={"hair": ([4, 5], np.full(9, 1e-4))})
        w.write_frame(3, {"hair": pts[:7]}, curves={"hair": ([4, 3], np.full(7, 2e-4))})
        w.write_frame(4, {"hair": pts[:7]}, curves={"hair": ([4, 3], np.full(7, 2e-4))})
    reader = CacheReader(path)
    assert [reader.counts("hair", f).tolist() for f in (1, 2, 3, 4)] == [[4, 5], [4, 5], [4, 3], [4, 3]]
    attr = reader.stage.GetPrimAtPath("/World/hair").GetAttribute("curveVertexCounts")
    assert attr.GetTimeSamples() == [1.0, 2.0, 3.0, 4.0]
    assert reader.widths("hair", 3).tolist() == pytest.approx([2e-4] * 7)
    assert [len(p) for p in reader.read_points("hair")] == [9, 9, 7, 7]
    assert validation_errors(path) == []
    static = str(tmp_path / "s.usdc")
    with CacheWriter(static, 24, 1, 2) as w:
        w.add_curves("hair", "hair", [4, 5], np.full(9, 1e-4))
        for f in (1, 2):
            w.write_frame(f, {"hair": pts}, curves={"hair": ([4, 5], np.full(9, 1e-4))})
    assert not CacheReader(static).prims["hair"].varying


@pytest.mark.parametrize("event, key", [
    ({"frame": 2, "tool": "shave"}, "haircut[1].tool"),
    ({"frame": 2, "tool": "blunt"}, "haircut[1].plane"),
    ({"frame": 2, "tool": "blunt", "plane": {"point": [0, 0, 0], "normal": [0, 0, 0]}}, "haircut[1].plane.normal"),
    ({"frame": 2, "tool": "blunt", "stroke": [[0, 0], [9, 9]]}, "haircut[1].camera"),
    ({"frame": "2", "tool": "erase", "sphere": {"center": [0, 0, 0], "radius": 1}}, "haircut[1].frame"),
    ({"frame": 2, "tool": "grow", "length": -1}, "haircut[1].length"),
    ({"frame": 2, "tool": "grow", "length": 0.1, "fraction": 0.5}, "haircut[1].fraction"),
    ({"frame": 2, "tool": "thinning", "plane": {"point": [0, 0, 0], "normal": [0, 1, 0]}, "fraction": 2},
     "haircut[1].fraction"),
    ({"frame": 2, "tool": "wax", "sphere": {"center": [0, 0, 0], "radius": 1}}, "haircut[1].drag"),
    ({"frame": 2, "tool": "wax", "sphere": {"center": [0, 0], "radius": 1}, "offset": [0, 1, 0]},
     "haircut[1].sphere.center"),
    ({"frame": 2, "tool": "erase", "sphere": {"center": [0, 0, 0], "radius": 1}, "camera": {"eye": [0, 0, 1]}},
     "haircut[1].camera.target"),
    ({"frame": 2, "tool": "wax", "sphere": {"center": [0, 0, 0], "radius": 1}, "offset": [0, 1, 0], "until": 1},
     "haircut[1].until"),
])
def test_bad_event_names_its_key(event, key):
    data = {"hair": {"count": 10}, "haircut": [{"frame": 1, "tool": "initialise"}, event]}
    with pytest.raises(InputError) as err:
        _build_config("bad.toml", data, None)
    assert err.value.key == key, err.value


def test_cfx_run_rejects_a_bad_event_with_file_key_and_reason(tmp_path, capsys):
    from sim.cli import main

    path = tmp_path / "bad.toml"
    path.write_text('[hair]\ncount = 10\n\n[[haircut]]\nframe = 1\ntool = "initialise"\n\n'
                    '[[haircut]]\nframe = 3\ntool = "trim"\n')
    assert main(["run", str(path), "-o", str(tmp_path / "x.usdc"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "bad.toml: haircut[1].tool:" in err and "blunt" in err
    assert not (tmp_path / "x.usdc").exists()


def test_event_that_fails_while_running_names_its_entry(tmp_path):
    events = [{"frame": 2, "tool": "erase", "sphere": {"center": [0.0, 0.3, 0.0], "radius": 5.0}}]
    with pytest.raises(InputError) as err:
        run_scene(config(events, frames=3), str(tmp_path / "x.usdc"), progress=False)
    assert err.value.key == "haircut[0]" and "every strand" in str(err.value)
    assert not (tmp_path / "x.usdc").exists()


def test_example_scene_scripts_the_cut_tools_within_a_cpu_budget(tmp_path):
    config = load_scene("examples/scenes/haircut.toml")
    tools = [e.tool for e in config.haircut]
    assert {"blunt", "chop", "thinning", "grow", "wax", "comb"} <= set(tools)
    assert 48 <= config.timing.frames <= 96 and config.hair.count <= 1500


def test_forgetting_a_solver_keeps_the_other_solvers_graphs():
    graphs = FrameGraphs("cpu")
    for key in (("hair", True, 1), (("hair", 0), True, 2), ("cloth", True, 3)):
        graphs._seen.add(key)
        graphs._graphs[key] = (None, None)
    graphs.forget("hair")
    assert set(graphs._graphs) == {("cloth", True, 3)} and graphs._seen == {("cloth", True, 3)}


def test_a_stroke_cuts_only_the_hair_its_camera_sees():
    """Scissors drawn across the face in the front view: strands whose crossing of the cut surface
    is hidden behind the head are not cut, the others are."""
    scene = settled(count=150)
    before = haircut.groom_of(scene)
    stroke = haircut.Stroke([[5.0, 230.0], [475.0, 230.0]], FRONT)
    surface = stroke.surface()
    seg, t = haircut.first_crossings(before.x, before.counts, surface, 2)
    crossing = np.flatnonzero(seg >= 0)
    points = before.x[seg[crossing]] + t[crossing, None] * (before.x[seg[crossing] + 1] - before.x[seg[crossing]])
    seen = scene.collider.visible_from(points, FRONT.eye)
    assert seen.any() and (~seen).any()
    edit = haircut.blunt_cut(scene, stroke)
    np.testing.assert_array_equal(np.sort(edit.strands), crossing[seen])
    after = haircut.groom_of(scene)
    np.testing.assert_array_equal(after.counts[crossing[~seen]], before.counts[crossing[~seen]])
