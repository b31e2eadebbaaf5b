"""A DCC's USD stage as the scene (io_usd.scene_input) and the NumPy embedding API (sim.embed).

The stage is built the way Blender 5 exports one: Z up, a `cfx:role` string on each object's
Xform with the geometry as its child, the collider animated by its transform, settings as
`cfx:<table>:<key>` attributes and garment pins as a per-vertex primvar.
"""

import numpy as np
import pytest
import trimesh
from pxr import Gf, Sdf, Usd, UsdGeom, Vt

from io_usd.cache import INTERPOLATED_FROM, CacheReader
from io_usd.scene_input import read_usd_scene
from sim.cli import main
from sim.embed import HostFrame, Simulation
from sim.errors import InputError

FRAMES = 5
CENTRE = np.array([0.0, 0.0, 1.5])
RADIUS = 0.1


def _sphere():
    s = trimesh.creation.icosphere(2, radius=RADIUS)
    return np.asarray(s.vertices), np.asarray(s.faces)


def _strands(count=8, vertices=8):
    pts = []
    for k in range(count):
        a = 2.0 * np.pi * k / count
        d = np.array([0.6 * np.cos(a), 0.6 * np.sin(a), 0.8])
        d /= np.linalg.norm(d)
        pts.append(CENTRE + RADIUS * d + np.outer(np.linspace(0.0, 0.07, vertices), d))
    return np.concatenate(pts), np.full(count, vertices)


def _cape():
    """A 5x5 plane hanging off the sphere's side (host Z up), its top row on the surface."""
    u, w = np.meshgrid(np.linspace(-0.04, 0.04, 5), np.linspace(0.0, -0.08, 5))
    points = np.stack([u.ravel(), np.full(25, -RADIUS), w.ravel()], 1)
    quads = np.array([[i * 5 + j, i * 5 + j + 1, (i + 1) * 5 + j + 1, (i + 1) * 5 + j]
                      for i in range(4) for j in range(4)])
    pinned = np.zeros(25)
    pinned[:5] = 1.0
    return points, quads, pinned


def _head_pose(frame):
    """The collider's transform at `frame`: a drift along X and a turn about Z."""
    return (0.01 * (frame - 1), 0.0, CENTRE[2]), (0.0, 0.0, 6.0 * (frame - 1))


def build_stage(path, substeps=6, extra=None):
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(FRAMES)
    stage.SetTimeCodesPerSecond(24)
    stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, "/root").GetPrim())

    def tagged(name, role):
        xf = UsdGeom.Xform.Define(stage, f"/root/{name}")
        xf.GetPrim().CreateAttribute("cfx:role", Sdf.ValueTypeNames.String, custom=True).Set(role)
        return xf

    head = tagged("Head", "collider")
    translate, rotate = head.AddTranslateOp(), head.AddRotateXYZOp()
    for f in range(1, FRAMES + 1):
        t, r = _head_pose(f)
        translate.Set(Gf.Vec3d(*t), f)
        rotate.Set(Gf.Vec3f(*r), f)
    v, faces = _sphere()
    mesh = UsdGeom.Mesh.Define(stage, "/root/Head/Sphere")
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(v.astype(np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.ravel().astype(np.int32)))

    hair = tagged("Hair", "hair")
    hair.GetPrim().CreateAttribute("cfx:solver:substeps", Sdf.ValueTypeNames.Int, custom=True).Set(substeps)
    hair.GetPrim().CreateAttribute("cfx:scene:preroll", Sdf.ValueTypeNames.Double, custom=True).Set(0.1)
    points, counts = _strands()
    curves = UsdGeom.BasisCurves.Define(stage, "/root/Hair/HairData")
    curves.CreateTypeAttr("cubic")
    curves.CreateBasisAttr("catmullRom")
    curves.CreateCurveVertexCountsAttr(Vt.IntArray.FromNumpy(counts.astype(np.int32)))
    curves.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points.astype(np.float32)))

    cape = tagged("Cape", "cloth")
    cape.AddTranslateOp().Set(Gf.Vec3d(*CENTRE))
    cape.GetPrim().CreateAttribute("cfx:detail:level", Sdf.ValueTypeNames.Int, custom=True).Set(0)
    cape.GetPrim().CreateAttribute("cfx:solver:friction", Sdf.ValueTypeNames.Double, custom=True).Set(0.5)
    gv, quads, pinned = _cape()
    plane = UsdGeom.Mesh.Define(stage, "/root/Cape/Plane")
    plane.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(gv.astype(np.float32)))
    plane.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(quads), 4, np.int32)))
    plane.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(quads.ravel().astype(np.int32)))
    UsdGeom.PrimvarsAPI(plane).CreatePrimvar("cfx_pinned", Sdf.ValueTypeNames.FloatArray,
                                             UsdGeom.Tokens.vertex).Set(Vt.FloatArray.FromNumpy(pinned.astype(np.float32)))
    for prim, name, kind, value in extra or []:
        stage.GetPrimAtPath(prim).CreateAttribute(name, kind, custom=True).Set(value)
    stage.GetRootLayer().Save()
    return path


def _world(stage, path, frame):
    prim = stage.GetPrimAtPath(path)
    t = Usd.TimeCode(frame)
    p = np.asarray(UsdGeom.PointBased(prim).GetPointsAttr().Get(t), np.float64)
    m = np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(t), np.float64)
    return p @ m[:3, :3] + m[3, :3]


@pytest.fixture(scope="module")
def ran(tmp_path_factory):
    folder = tmp_path_factory.mktemp("dcc")
    scene = build_stage(folder / "shot.usda")
    assert main(["run", str(scene), "-o", str(folder / "cache.usdc"), "-q"]) == 0
    return folder


def test_stage_is_read_in_engine_axes(ran):
    scene = read_usd_scene(ran / "shot.usda")
    assert scene.config.timing.frames == FRAMES and scene.config.timing.start_frame == 1
    assert scene.config.solver.substeps == 6 and scene.config.cloth_solver.friction == 0.5
    assert scene.config.cloth_detail.level == 0 and scene.config.timing.preroll == pytest.approx(0.1)
    points, counts, _ = scene.assets.hair
    host, _ = _strands()
    # Z up (x, y, z) -> engine Y up (x, z, -y): the roots sit at the sphere's top in engine axes
    np.testing.assert_allclose(points, np.stack([host[:, 0], host[:, 2], -host[:, 1]], 1), atol=1e-6)
    assert list(scene.assets.garment.pinned) == [0, 1, 2, 3, 4]
    # the collider follows its transform: frame 3 is translated and turned
    t, r = _head_pose(3)
    v, _ = _sphere()
    a = np.radians(r[2])
    turned = v @ np.array([[np.cos(a), np.sin(a), 0.0], [-np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]]) + t
    np.testing.assert_allclose(scene.assets.motion.frames[2], HostFrame("Z").to_engine(turned), atol=1e-6)


def test_cache_is_a_layer_over_the_scene(ran):
    layer = Sdf.Layer.FindOrOpen(str(ran / "cache.usdc"))
    assert list(layer.subLayerPaths) == ["shot.usda"] and layer.defaultPrim == "root"
    assert layer.GetPrimAtPath("/root/Hair/HairData").specifier == Sdf.SpecifierOver
    assert layer.GetPrimAtPath("/root/Cape/Plane").specifier == Sdf.SpecifierOver
    # the input is never written to, and the cache's opinions win when stacked over it in a shot
    shot = Usd.Stage.CreateInMemory()
    shot.GetRootLayer().subLayerPaths = [str(ran / "cache.usdc"), str(ran / "shot.usda")]
    cache = Usd.Stage.Open(str(ran / "cache.usdc"))
    for frame in (1, FRAMES):
        np.testing.assert_array_equal(_world(shot, "/root/Hair/HairData", frame),
                                      _world(cache, "/root/Hair/HairData", frame))
    source = Usd.Stage.Open(str(ran / "shot.usda"))
    assert not UsdGeom.Mesh(source.GetPrimAtPath("/root/Cape/Plane")).GetPointsAttr().GetTimeSamples()


def test_curves_without_widths_get_the_hairs_in_the_cache_which_then_previews(ran, tmp_path):
    """The shot's curves author no widths (renderers would draw them a unit wide); the cache gives
    them the hair's, leaving the shot untouched, and so opens alone in cfx preview."""
    from io_usd.cache import DEFAULT_CURVE_WIDTH

    shot, cache = Usd.Stage.Open(str(ran / "shot.usda")), Usd.Stage.Open(str(ran / "cache.usdc"))
    assert not UsdGeom.BasisCurves(shot.GetPrimAtPath("/root/Hair/HairData")).GetWidthsAttr().HasAuthoredValue()
    curves = UsdGeom.BasisCurves(cache.GetPrimAtPath("/root/Hair/HairData"))
    widths = np.asarray(curves.GetWidthsAttr().Get())
    assert curves.GetWidthsInterpolation() == UsdGeom.Tokens.vertex
    np.testing.assert_allclose(widths, np.full(len(_strands()[0]), DEFAULT_CURVE_WIDTH), rtol=1e-6)
    png = tmp_path / "shot.png"
    assert main(["preview", str(ran / "cache.usdc"), "-o", str(png), "-q"]) == 0
    assert png.stat().st_size > 1000


def test_the_cache_records_gravity_and_wind_in_the_stages_axes(ran):
    """The stage is Z up: its gravity is along -Z, as a TD reading the cache's settings expects."""
    settings = Sdf.Layer.FindOrOpen(str(ran / "cache.usdc")).customLayerData["cfx:settings"]
    for table in ("solver", "cloth_solver"):
        np.testing.assert_allclose(list(settings[table]["gravity"]), [0.0, 0.0, -9.81])
        np.testing.assert_allclose(list(settings[table]["wind"]), [0.0, 0.0, 0.0])
    engine = read_usd_scene(ran / "shot.usda").config
    np.testing.assert_allclose(engine.solver.gravity, [0.0, -9.81, 0.0])  # the engine's own axes: Y up


def test_simulated_hair_and_pins_follow_the_collider(ran):
    stage = Usd.Stage.Open(str(ran / "cache.usdc"))
    points, counts = _strands()
    first = np.r_[0, np.cumsum(counts)[:-1]]
    rest = np.linalg.norm(np.diff(points, axis=0), axis=1)
    inner = np.ones(len(rest), bool)
    inner[np.cumsum(counts)[:-1] - 1] = False
    gv, _, _ = _cape()
    for frame in range(1, FRAMES + 1):
        t, r = _head_pose(frame)
        hair = _world(stage, "/root/Hair/HairData", frame)
        roots = np.linalg.norm(hair[first] - t, axis=1)
        np.testing.assert_allclose(roots, RADIUS, atol=2e-3)  # on the (tessellated) moving surface
        seg = np.linalg.norm(np.diff(hair, axis=0), axis=1)
        np.testing.assert_allclose(seg[inner], rest[inner], rtol=2e-3)
        # pins are bound to the surface: they move rigidly with it
        a = np.radians(r[2])
        turn = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
        cape = _world(stage, "/root/Cape/Plane", frame)
        np.testing.assert_allclose(cape[:5], gv[:5] @ turn.T + t, atol=1e-4)
    # the free rows fell: below the pinned row by more than they started
    cape = _world(stage, "/root/Cape/Plane", FRAMES)
    assert cape[20:, 2].mean() < cape[:5, 2].mean() - 0.07


def test_reader_gives_engine_world_positions(ran):
    reader = CacheReader(ran / "cache.usdc")
    assert reader.up_axis == "Z"
    stage = Usd.Stage.Open(str(ran / "cache.usdc"))
    hair = [n for n, p in reader.prims.items() if p.role == "hair"][0]
    np.testing.assert_allclose(reader.points(hair, 3), HostFrame("Z").to_engine(_world(stage, "/root/Hair/HairData", 3)),
                               atol=1e-6)


def test_embedding_api_matches_cfx_run(ran):
    """A host stepping Simulation with the collider it evaluates per frame gets the cache's numbers."""
    source = Usd.Stage.Open(str(ran / "shot.usda"))
    v, faces = _sphere()
    points, counts = _strands()
    gv, quads, pinned = _cape()
    sim = Simulation(_world(source, "/root/Head/Sphere", 1), faces, fps=24,
                     hair_points=_world(source, "/root/Hair/HairData", 1), hair_counts=counts,
                     garment_vertices=_world(source, "/root/Cape/Plane", 1), garment_face_counts=np.full(len(quads), 4),
                     garment_face_indices=quads.ravel(), garment_pinned=np.flatnonzero(pinned),
                     settings={"scene": {"preroll": 0.1}, "solver": {"substeps": 6},
                               "cloth": {"solver": {"friction": 0.5}, "detail": {"level": 0}}},
                     up_axis="Z")
    cache = Usd.Stage.Open(str(ran / "cache.usdc"))
    for frame in range(1, FRAMES + 1):
        if frame > 1:
            sim.step(_world(source, "/root/Head/Sphere", frame))
        np.testing.assert_allclose(sim.hair_points(), _world(cache, "/root/Hair/HairData", frame), atol=1e-5)
        np.testing.assert_allclose(sim.cloth_points(), _world(cache, "/root/Cape/Plane", frame), atol=1e-5)


def test_host_units_and_axes_round_trip():
    frame = HostFrame("Z", 0.01)
    p = np.array([[1.0, 2.0, 3.0], [-4.0, 5.5, 0.25]])
    np.testing.assert_allclose(frame.to_engine(p), [[0.01, 0.03, -0.02], [-0.04, 0.0025, -0.055]])
    np.testing.assert_allclose(frame.from_engine(frame.to_engine(p)), p, rtol=1e-6)
    assert frame.direction_to_engine((0.0, 0.0, -9.81)) == (0.0, -9.81, 0.0)
    with pytest.raises(ValueError, match="up_axis"):
        HostFrame("X")


def test_embedding_in_centimetres_y_up_falls_the_same_distance():
    """Units are the host's: a garment in centimetres falls 100x the number of units it does in metres."""
    v, faces = _sphere()
    gv, quads, _ = _cape()
    far = gv + [0.0, 0.0, 0.5]  # well clear of the collider: free fall under gravity and drag
    kwargs = dict(garment_face_counts=np.full(len(quads), 4), garment_face_indices=quads.ravel(),
                  settings={"scene": {"preroll": 0.0}})
    metres = Simulation(v, faces, garment_vertices=far, up_axis="Z", **kwargs)
    centimetres = Simulation(v * 100.0, faces, garment_vertices=far * 100.0, up_axis="Z", meters_per_unit=0.01,
                             **kwargs)
    for _ in range(3):
        metres.step(v)
        centimetres.step(v * 100.0)
    drop = far[:, 2].mean() - metres.cloth_points()[:, 2].mean()
    assert drop > 0.01
    np.testing.assert_allclose(centimetres.cloth_points(), metres.cloth_points() * 100.0, rtol=1e-4, atol=1e-3)


def test_embedding_detail_surface_is_one_per_frame():
    """The host may ask for the detail surface as often as it likes: each frame's surface is made once
    (by step, beside the hair and cloth), so asking again returns it unchanged, while another update
    would carry the wrinkle heights a frame further. Its corner vertices sit on the garment."""
    v, faces = _sphere()
    gv, quads, _ = _cape()
    sim = Simulation(v, faces, garment_vertices=gv, garment_face_counts=np.full(len(quads), 4),
                     garment_face_indices=quads.ravel(),
                     settings={"scene": {"preroll": 0.0}, "cloth": {"detail": {"level": 2}}})
    for _ in range(3):
        sim.step(v)
    points, triangles = sim.detail_points()
    heights = sim.scene.cloth_detail.height.numpy().copy()
    again, _ = sim.detail_points()
    np.testing.assert_array_equal(again, points)
    np.testing.assert_array_equal(sim.scene.cloth_detail.height.numpy(), heights)
    assert triangles.max() == len(points) - 1
    # the coarse vertices are detail vertices too (PN corners, lifted by at most the heights)
    cloth = sim.cloth_points()
    nearest = np.min(np.linalg.norm(cloth[:, None] - points[None], axis=2), axis=1)
    assert nearest.max() <= np.abs(heights).max() + 1e-5
    sim.scene.update_detail()
    assert heights.any() and not np.array_equal(sim.scene.cloth_detail.height.numpy(), heights)


@pytest.mark.parametrize("extra, key, reason", [
    ([("/root/Hair", "cfx:solver:substepz", Sdf.ValueTypeNames.Int, 3)], "/root/Hair.cfx:solver:substepz",
     "unknown key"),
    ([("/root/Hair", "cfx:solver:damping", Sdf.ValueTypeNames.String, "lots")], "/root/Hair.cfx:solver:damping",
     "expected a number"),
    ([("/root/Hair", "cfx:detail:level", Sdf.ValueTypeNames.Int, 2)], "/root/Hair.cfx:detail:level",
     "cfx:<table>:<key>"),
    ([("/root/Cape", "cfx:role", Sdf.ValueTypeNames.String, "cape")], "/root/Cape.cfx:role", "unknown role"),
])
def test_bad_stage_names_prim_and_attribute(tmp_path, capsys, extra, key, reason):
    scene = build_stage(tmp_path / "bad.usda", extra=extra)
    with pytest.raises(InputError) as err:
        read_usd_scene(scene)
    assert err.value.key == key and reason in err.value.reason
    out = tmp_path / "cache.usdc"
    assert main(["run", str(scene), "-o", str(out), "-q"]) == 2
    assert key in capsys.readouterr().err and not out.exists()


def test_stage_without_collider_or_cache_over_itself(tmp_path, capsys):
    scene = build_stage(tmp_path / "shot.usda")
    assert main(["run", str(scene), "-o", str(scene), "-q"]) == 2
    assert "overwrite the scene" in capsys.readouterr().err
    stage = Usd.Stage.Open(str(scene))
    stage.GetPrimAtPath("/root/Head").RemoveProperty("cfx:role")
    stage.GetRootLayer().Save()
    with pytest.raises(InputError, match="collider"):
        read_usd_scene(scene)


def _edit(stage):
    hair, head = UsdGeom.BasisCurves(stage.GetPrimAtPath("/root/Hair/HairData")), stage.GetPrimAtPath("/root/Head")
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/root/Head/Sphere"))
    faces = list(mesh.GetFaceVertexIndicesAttr().Get())
    return {
        "no counts": lambda: hair.GetCurveVertexCountsAttr().Clear(),
        "nan widths": lambda: hair.CreateWidthsAttr([float("nan")]),
        "index": lambda: mesh.GetFaceVertexIndicesAttr().Set([0, 1, 100000] + faces[3:]),
        "flat": lambda: UsdGeom.Xformable(head).AddScaleOp().Set(Gf.Vec3f(0.0, 0.0, 0.0)),
        "backwards": lambda: (stage.SetStartTimeCode(FRAMES), stage.SetEndTimeCode(1)),
        "metres": lambda: UsdGeom.SetStageMetersPerUnit(stage, 0.0),
        "rate": lambda: stage.SetTimeCodesPerSecond(1e-9),
    }


@pytest.mark.parametrize("case, key, reason", [
    ("no counts", "/root/Hair/HairData.curveVertexCounts", "not authored"),  # a traceback
    ("nan widths", "/root/Hair/HairData.widths", "finite"),  # written to the cache as NaN
    ("index", "/root/Head/Sphere.faceVertexIndices", "must lie in [0, "),  # a traceback
    ("flat", "/root/Head/Sphere", "no face has any area"),  # exploded: exit 3
    ("backwards", "endTimeCode", "before startTimeCode"),  # ran one frame without a word
    ("metres", "metersPerUnit", "positive"),  # the error named no file or key
    ("rate", "timeCodesPerSecond", "at least 1"),  # named scene.fps, which the stage has not
])
def test_stage_defects_a_qa_pass_found_are_named(tmp_path, case, key, reason):
    scene = build_stage(tmp_path / "shot.usda")
    stage = Usd.Stage.Open(str(scene))
    _edit(stage)[case]()
    stage.GetRootLayer().Save()
    with pytest.raises(InputError) as err:
        read_usd_scene(scene)
    assert err.value.key == key and reason in err.value.reason, str(err.value)


def test_uniform_curve_widths_are_spread_over_each_curves_vertices(tmp_path):
    scene = build_stage(tmp_path / "shot.usda")
    stage = Usd.Stage.Open(str(scene))
    curves = UsdGeom.BasisCurves(stage.GetPrimAtPath("/root/Hair/HairData"))
    counts = np.asarray(curves.GetCurveVertexCountsAttr().Get())
    per_curve = 1e-4 * (1.0 + np.arange(len(counts)))
    curves.CreateWidthsAttr(Vt.FloatArray.FromNumpy(per_curve.astype(np.float32)))
    curves.SetWidthsInterpolation(UsdGeom.Tokens.uniform)
    stage.GetRootLayer().Save()
    widths = read_usd_scene(scene).assets.hair[2]
    np.testing.assert_allclose(widths, np.repeat(per_curve, counts), rtol=1e-6)


def test_curves_drawn_from_the_strands_are_not_simulated(tmp_path):
    """Hair curves marked `cfx:interpolatedFrom` (a cache's render children, carried into a DCC's shot)
    are left out of the strands a stage gives; the tagged strands are read as before."""
    path = build_stage(tmp_path / "shot.usda")
    stage = Usd.Stage.Open(str(path))
    kids = UsdGeom.BasisCurves.Define(stage, "/root/HairChildren")
    kids.GetPrim().CreateAttribute("cfx:role", Sdf.ValueTypeNames.String, custom=True).Set("hair")
    kids.GetPrim().CreateAttribute(INTERPOLATED_FROM, Sdf.ValueTypeNames.String, custom=True).Set("/root/Hair")
    points, counts = _strands(count=3)
    kids.CreateCurveVertexCountsAttr(Vt.IntArray.FromNumpy(counts.astype(np.int32)))
    kids.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points.astype(np.float32)))
    stage.GetRootLayer().Save()
    scene = read_usd_scene(path)
    assert [p.geometry.GetPath().pathString for p in scene.hair] == ["/root/Hair/HairData"]
    assert len(scene.assets.hair[1]) == len(_strands()[1])


def test_a_cache_given_as_a_shot_says_so(ran, tmp_path, capsys):
    """The cache is a layer over the shot, so its stage has every tagged prim and more; run it and
    the error says what the file is rather than which role it does not know."""
    out = tmp_path / "again.usdc"
    assert main(["run", str(ran / "cache.usdc"), "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err
    assert "cache.usdc: cfx:engine: this is a cache cfx wrote, not a shot" in err and not out.exists()


def test_embedding_rejects_bad_arrays():
    v, faces = _sphere()
    with pytest.raises(InputError, match="collider_faces"):
        Simulation(v, faces[:, :2])
    with pytest.raises(InputError, match="hair_counts"):
        Simulation(v, faces, hair_points=v[:10])
    with pytest.raises(InputError, match=r"\[head\]"):
        Simulation(v, faces, hair_points=v[:10], hair_counts=[10], settings={"head": {}})
    points, counts = _strands()
    sim = Simulation(v + CENTRE, faces, hair_points=points, hair_counts=counts, up_axis="Z",
                     settings={"scene": {"preroll": 0.0}})
    with pytest.raises(InputError, match="collider_points"):
        sim.step(v[:5])
    bad = v.copy()
    bad[0, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        sim.step(bad)


def test_embedding_checks_widths_and_counts_keeps_few_frames_and_takes_turns_across_threads():
    """From a QA pass: NaN, negative or too few hair_widths and fractional hair_counts were taken (the
    counts truncated); every collider frame was kept (+562 MB over 600 frames of a 41k-vertex
    collider); two Simulations stepped in two threads crashed the process."""
    import threading

    v, faces = _sphere()
    points, counts = _strands()
    for widths in ([1e-4] * 3, np.full(len(points), np.nan), np.full(len(points), -1e-4)):
        with pytest.raises(InputError, match="hair_widths"):
            Simulation(v + CENTRE, faces, hair_points=points, hair_counts=counts, hair_widths=widths, up_axis="Z")
    with pytest.raises(InputError, match="hair_counts"):
        Simulation(v + CENTRE, faces, hair_points=points, hair_counts=counts + 0.5, up_axis="Z")
    for kwargs, key in (({"settings": [1]}, "settings"), ({"settings": {"scene": 5}}, r"\[scene\]"),
                        ({"fps": None}, "fps"), ({"meters_per_unit": "0.01"}, "meters_per_unit")):
        with pytest.raises(InputError, match=key):  # AttributeError and TypeError before
            Simulation(v + CENTRE, faces, hair_points=points, hair_counts=counts, up_axis="Z", **kwargs)
    with pytest.raises(InputError, match="collider_faces"):
        Simulation(v + CENTRE, None)
    sims = [Simulation(v + CENTRE, faces, hair_points=points, hair_counts=counts, up_axis="Z",
                       settings={"scene": {"preroll": 0.0}}) for _ in range(3)]
    errors = []

    def drive(sim):
        try:
            for k in range(1, 13):
                sim.step(v + CENTRE + [0.002 * k, 0.0, 0.0])
        except Exception as err:  # noqa: BLE001 (reported below)
            errors.append(err)

    threads = [threading.Thread(target=drive, args=(sim,)) for sim in sims[:2]]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    drive(sims[2])
    assert not errors
    np.testing.assert_array_equal(sims[0].hair_points(), sims[2].hair_points())  # the same as alone
    np.testing.assert_array_equal(sims[1].hair_points(), sims[2].hair_points())
    assert len(sims[0]._motion.frames) <= 4 and sims[0]._motion.first == 12 - 3


def test_several_garments_simulate_as_one_and_write_back_to_their_prims(tmp_path):
    """A second cape on the other side of the head: both prims get their own points back, both sets
    of pins ride the collider, and the detail surface spans both, under the stage's default prim (so a
    reference to the cache brings it), in that prim's space: here turned a quarter about Z and moved."""
    scene = build_stage(tmp_path / "two.usda", extra=[("/root/Cape", "cfx:detail:level", Sdf.ValueTypeNames.Int, 2)])
    stage = Usd.Stage.Open(str(scene))
    back = UsdGeom.Xform.Define(stage, "/root/BackCape")
    back.GetPrim().CreateAttribute("cfx:role", Sdf.ValueTypeNames.String, custom=True).Set("cloth")
    back.AddTranslateOp().Set(Gf.Vec3d(*CENTRE))
    gv, quads, pinned = _cape()
    mirrored = gv * [1.0, -1.0, 1.0]  # hanging off the +Y side, its top row on the surface
    plane = UsdGeom.Mesh.Define(stage, "/root/BackCape/Plane")
    plane.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(mirrored.astype(np.float32)))
    plane.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(quads), 4, np.int32)))
    plane.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(quads[:, ::-1].ravel().astype(np.int32)))
    plane.GetPrim().CreateAttribute("cfx:pinned", Sdf.ValueTypeNames.IntArray).Set([0, 1, 2, 3, 4])
    root = UsdGeom.Xformable(stage.GetPrimAtPath("/root"))
    root.AddTranslateOp().Set(Gf.Vec3d(0.3, -0.2, 0.0))
    root.AddRotateZOp().Set(90.0)
    stage.GetRootLayer().Save()
    quarter = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # the root's turn, column vectors

    def world(local):
        return local @ quarter.T + [0.3, -0.2, 0.0]

    read = read_usd_scene(scene)
    assert [p.path for p in read.cloth] == ["/root/Cape/Plane", "/root/BackCape/Plane"]
    assert len(read.assets.garment.vertices) == 50 and list(read.assets.garment.pinned) == [0, 1, 2, 3, 4, 25, 26,
                                                                                             27, 28, 29]
    out = tmp_path / "two_cache.usdc"
    assert main(["run", str(scene), "-o", str(out), "-q"]) == 0
    cache = Usd.Stage.Open(str(out))
    for frame in (1, FRAMES):
        t, r = _head_pose(frame)
        a = np.radians(r[2])
        turn = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
        front, rear = _world(cache, "/root/Cape/Plane", frame), _world(cache, "/root/BackCape/Plane", frame)
        np.testing.assert_allclose(front[:5], world(gv[:5] @ turn.T + t), atol=1e-4)
        np.testing.assert_allclose(rear[:5], world(mirrored[:5] @ turn.T + t), atol=1e-4)
    detail = _world(cache, "/root/cfx_cloth_detail", FRAMES)
    across = (detail - [0.3, -0.2, 0.0]) @ quarter  # back in the root's axes
    assert across[:, 1].min() < -RADIUS + 0.01 and across[:, 1].max() > RADIUS - 0.01  # spans both sides
    # the normals are in the root's space too: turned to the world they agree with the surface's winding
    mesh = UsdGeom.Mesh(cache.GetPrimAtPath("/root/cfx_cloth_detail"))
    tris = np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
    normals = np.asarray(mesh.GetNormalsAttr().Get(Usd.TimeCode(FRAMES)), np.float64) @ quarter.T
    winding = np.zeros_like(detail)
    for k in range(3):
        np.add.at(winding, tris[:, k], np.cross(detail[tris[:, 1]] - detail[tris[:, 0]], detail[tris[:, 2]] -
                                                 detail[tris[:, 0]]))
    assert np.mean(np.einsum("ij,ij->i", normals, winding) > 0.0) > 0.99
    reader = CacheReader(out)
    assert {p.role for p in reader.prims.values()} >= {"cloth", "cloth_detail", "hair", "collider"}
