"""USD caches: round trip, schema details, validation, and no half-written files."""

import os

import numpy as np
import pytest
from pxr import Usd, UsdGeom

from io_usd import CacheReader, CacheWriter, read_cache, validation_errors


def write_small(path, frames=4, fail_at=None):
    rng = np.random.default_rng(0)
    verts = rng.normal(size=(8, 3)).astype(np.float32)
    faces = np.array([[0, 1, 2], [2, 3, 0], [4, 5, 6], [6, 7, 4]])
    counts = np.array([3, 5, 4])
    widths = np.linspace(2e-4, 5e-5, counts.sum()).astype(np.float32)
    hair = rng.normal(size=(frames, counts.sum(), 3)).astype(np.float32)
    with CacheWriter(path, fps=30, start_frame=1, end_frame=frames, settings={"solver": {"substeps": 7}},
                     flush_every=2, engine_version="test") as w:
        w.add_mesh("head", "collider", verts, faces, color=(0.8, 0.7, 0.6))
        w.add_curves("hair", "hair", counts, widths, color=(0.2, 0.1, 0.05))
        for f in range(frames):
            if f == fail_at:
                raise RuntimeError("boom")
            w.write_frame(f + 1, {"head": verts + f, "hair": hair[f]})
    return verts, faces, counts, widths, hair


@pytest.mark.parametrize("ext", [".usdc", ".usda"])
def test_round_trip_returns_the_written_arrays(tmp_path, ext):
    path = str(tmp_path / f"cache{ext}")
    verts, faces, counts, widths, hair = write_small(path)
    data = read_cache(path)
    assert data["frames"] == [1, 2, 3, 4] and data["fps"] == 30
    np.testing.assert_array_equal(data["hair"]["points"], hair)
    np.testing.assert_array_equal(data["hair"]["counts"], counts)
    np.testing.assert_array_equal(data["hair"]["widths"], widths)
    np.testing.assert_array_equal(data["head"]["points"][2], verts + 2)
    np.testing.assert_array_equal(data["head"]["indices"], faces.reshape(-1))
    assert data["hair"]["role"] == "hair" and data["head"]["role"] == "collider"


def test_cache_follows_the_usd_conventions(tmp_path):
    path = str(tmp_path / "cache.usdc")
    _, _, counts, widths, hair = write_small(path)
    stage = Usd.Stage.Open(path)
    assert UsdGeom.GetStageUpAxis(stage) == "Y" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetTimeCodesPerSecond() == 30 and stage.GetFramesPerSecond() == 30
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (1, 4)
    assert stage.GetDefaultPrim().GetPath() == "/World"
    data = stage.GetRootLayer().customLayerData
    assert data["cfx:complete"] and data["cfx:engineVersion"] == "test"
    assert data["cfx:settings"]["solver"]["substeps"] == 7
    curves = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/hair"))
    assert curves.GetTypeAttr().Get() == "linear" and curves.GetWrapAttr().Get() == "nonperiodic"
    assert curves.GetWidthsInterpolation() == "vertex"
    ext = np.array(curves.GetExtentAttr().Get(3))
    pad = widths.max() / 2
    np.testing.assert_allclose(ext, [hair[2].min(0) - pad, hair[2].max(0) + pad], rtol=1e-6, atol=1e-6)
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/head"))
    assert mesh.GetSubdivisionSchemeAttr().Get() == "none"
    for prim in ("/World/hair", "/World/head"):
        role = stage.GetPrimAtPath(prim).GetAttribute("cfx:role")
        assert role.GetTypeName() == "token" and role.IsCustom()  # DCC importers bring in custom attributes
    assert not mesh.GetDoubleSidedAttr().Get()  # a closed collider; open surfaces are double-sided:
    assert validation_errors(path) == []


def test_open_surfaces_are_double_sided(tmp_path):
    path = str(tmp_path / "cloth.usda")
    quad = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
    with CacheWriter(path, fps=24, start_frame=1, end_frame=1) as w:
        for role in ("cloth", "cloth_detail", "hair_card", "face"):
            w.add_mesh(role, role, None, np.array([[0, 1, 2], [0, 2, 3]]))
        w.write_frame(1, {role: quad for role in ("cloth", "cloth_detail", "hair_card", "face")})
    stage = Usd.Stage.Open(path)
    sided = {role: UsdGeom.Mesh(stage.GetPrimAtPath(f"/World/{role}")).GetDoubleSidedAttr().Get()
             for role in ("cloth", "cloth_detail", "hair_card", "face")}
    assert sided == {"cloth": True, "cloth_detail": True, "hair_card": True, "face": False}  # the face covers a head


def test_a_cache_over_a_centimetre_stage_gives_its_hair_widths_in_centimetres(tmp_path):
    from pxr import Vt

    shot = Usd.Stage.CreateNew(str(tmp_path / "shot.usda"))
    UsdGeom.SetStageMetersPerUnit(shot, 0.01)
    shot.SetDefaultPrim(UsdGeom.Xform.Define(shot, "/char").GetPrim())
    curves = UsdGeom.BasisCurves.Define(shot, "/char/hair")
    curves.CreateCurveVertexCountsAttr([3])
    curves.CreatePointsAttr(Vt.Vec3fArray([(0, 0, 0), (0, -1, 0), (0, -2, 0)]))
    cape = UsdGeom.Mesh.Define(shot, "/char/cape")  # its subdivisionScheme unauthored: Catmull-Clark
    cape.CreatePointsAttr(Vt.Vec3fArray([(0, 0, 0), (1, 0, 0), (1, 1, 0)]))
    cape.CreateFaceVertexCountsAttr([3])
    cape.CreateFaceVertexIndicesAttr([0, 1, 2])
    shot.GetRootLayer().Save()
    over = str(tmp_path / "shot.usda")
    with CacheWriter(str(tmp_path / "cache.usdc"), 24, 1, 1, meters_per_unit=0.01, over=over) as w:
        w.add_over("hair", "hair", "/char/hair")
        w.add_over("cape", "cloth", "/char/cape")
        w.write_frame(1, {"hair": np.zeros((3, 3)), "cape": np.eye(3)})
    stage = Usd.Stage.Open(str(tmp_path / "cache.usdc"))
    widths = np.asarray(UsdGeom.BasisCurves(stage.GetPrimAtPath("/char/hair")).GetWidthsAttr().Get())
    np.testing.assert_allclose(widths, 0.01, rtol=1e-6)  # a tenth of a millimetre, in centimetres
    assert UsdGeom.Mesh(stage.GetPrimAtPath("/char/cape")).GetSubdivisionSchemeAttr().Get() == "none"


def test_failed_run_leaves_no_cache_behind(tmp_path):
    path = tmp_path / "cache.usdc"
    with pytest.raises(RuntimeError):
        write_small(str(path), frames=6, fail_at=3)
    assert os.listdir(tmp_path) == []


def test_failed_run_keeps_an_existing_cache(tmp_path):
    path = str(tmp_path / "cache.usdc")
    write_small(path, frames=2)
    before = os.path.getmtime(path), os.path.getsize(path)
    with pytest.raises(RuntimeError):
        write_small(path, frames=6, fail_at=3)
    assert (os.path.getmtime(path), os.path.getsize(path)) == before
    assert CacheReader(path).complete


def test_writer_rejects_unknown_roles_and_extensions(tmp_path):
    with pytest.raises(ValueError, match="must end in"):
        CacheWriter(str(tmp_path / "x.abc"), 24, 1, 2)
    with CacheWriter(str(tmp_path / "x.usdc"), 24, 1, 1) as w:
        with pytest.raises(ValueError, match="role"):
            w.add_curves("fur", "fur", [2], [1e-4, 1e-4])
        w.add_curves("hair", "hair", [2], [1e-4, 1e-4])
        w.write_frame(1, {"hair": np.zeros((2, 3), np.float32)})
