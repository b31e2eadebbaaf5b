"""The asset cache: built bodies, garments and grooms kept on disk, equal to what a build gives."""

import dataclasses
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sim import asset_cache
from sim.mesh_topology import unique_pairs


@pytest.fixture
def folder(tmp_path, monkeypatch):
    monkeypatch.setenv("CFX_CACHE_DIR", str(tmp_path / "assets"))
    return tmp_path / "assets"


def _counting(arrays):
    calls = []

    def build():
        calls.append(1)
        return {k: np.array(v) for k, v in arrays.items()}

    return build, calls


ARRAYS = {"points": np.linspace(0.0, 1.0, 12).reshape(4, 3), "faces": np.arange(6, dtype=np.int64).reshape(2, 3),
          "mask": np.array([True, False]), "name": np.array("dress"), "ease": np.array(0.012)}


def test_a_second_request_reads_the_entry_the_first_built(folder):
    build, calls = _counting(ARRAYS)
    first = asset_cache.cached_arrays("thing", ("a", 1, 2.5), build)
    second = asset_cache.cached_arrays("thing", ("a", 1, 2.5), build)
    assert len(calls) == 1
    assert [p.name.split("-")[0] for p, _ in asset_cache.entries()] == ["thing"]
    for got in (first, second):
        assert sorted(got) == sorted(ARRAYS)
        for key, value in ARRAYS.items():
            assert got[key].dtype == value.dtype and np.array_equal(got[key], value)
    assert str(second["name"]) == "dress" and float(second["ease"]) == 0.012


@dataclasses.dataclass(frozen=True)
class _Style:
    length: float = 0.2
    style: str = "wavy"


def test_every_input_names_its_own_entry(folder):
    a = np.arange(6.0)
    keys = [("x", a), ("x", a.reshape(2, 3)), ("x", a.astype(np.float32)), ("x", a + 1e-12), ("x", 1), ("x", 1.0),
            ("x", _Style()), ("x", _Style(length=0.21)), ("x", {"a": 1.0, "b": None}), ("x", {"a": 1.0, "b": 0.0})]
    digests = {asset_cache.input_digest(k) for k in keys}
    assert len(digests) == len(keys)
    assert asset_cache.input_digest(("x", {"b": None, "a": 1.0})) == asset_cache.input_digest(keys[8])
    with pytest.raises(TypeError, match="cannot hash a object"):
        asset_cache.input_digest(("x", object()))


def test_a_torn_entry_is_built_again_and_replaced(folder):
    build, calls = _counting(ARRAYS)
    asset_cache.cached_arrays("thing", (1,), build)
    path = asset_cache.entry_path("thing", (1,))
    path.write_bytes(path.read_bytes()[:100])  # a run killed while another wrote it, a full disk
    got = asset_cache.cached_arrays("thing", (1,), build)
    assert len(calls) == 2 and np.array_equal(got["points"], ARRAYS["points"])
    assert np.array_equal(np.load(path)["points"], ARRAYS["points"])


def test_entries_of_other_code_are_removed_when_one_is_written_and_other_files_never(folder):
    folder.mkdir(parents=True)
    stale = folder / "body-0123456789abcdef-000000000000000000000000.npz"
    np.savez(stale, x=np.zeros(3))
    theirs = [folder / "mesh.npz", folder / "notes.txt", folder / ".hidden.npz"]  # a shared folder's own files
    for path in theirs:
        path.write_bytes(b"not ours")
    assert [p for p, _ in asset_cache.entries()] == [stale]
    asset_cache.cached_arrays("thing", (2,), _counting(ARRAYS)[0])
    assert [p for p, _ in asset_cache.entries()] == [asset_cache.entry_path("thing", (2,))]
    assert asset_cache.clear() == 1 and asset_cache.entries() == []
    assert all(path.read_bytes() == b"not ours" for path in theirs)


def test_off_builds_every_time_and_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.setenv("CFX_CACHE_DIR", "off")
    build, calls = _counting(ARRAYS)
    for _ in range(2):
        asset_cache.cached_arrays("thing", (3,), build)
    assert len(calls) == 2 and asset_cache.cache_dir() is None and asset_cache.entries() == []


def test_a_folder_that_cannot_be_written_costs_only_the_build(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("CFX_CACHE_DIR", str(blocker / "assets"))
    build, calls = _counting(ARRAYS)
    got = asset_cache.cached_arrays("thing", (4,), build)
    assert len(calls) == 1 and np.array_equal(got["faces"], ARRAYS["faces"])


def test_an_edit_to_any_engine_source_changes_the_digest(tmp_path):
    root = Path(asset_cache.__file__).resolve().parent.parent
    for package in ("sim", "warp_kernels"):
        shutil.copytree(root / package, tmp_path / package, ignore=shutil.ignore_patterns("data", "__pycache__"))
    before = asset_cache.digest_sources(tmp_path)
    assert before == asset_cache.source_digest()
    kernel = tmp_path / "warp_kernels" / "strands.py"
    kernel.write_text(kernel.read_text() + "\n# an edit\n")
    assert asset_cache.digest_sources(tmp_path) != before


def test_the_cached_body_and_dress_equal_fresh_builds():
    """The session's cache (conftest) against builds that bypass it, bit for bit."""
    from sim.body import _LANDMARK, _build_arrays, procedural_body
    from sim.garment import _BodySections, _fit, _lerp, fit_dress

    body = procedural_body()
    fresh = _build_arrays(0.0125, 4)
    for key in ("vertices", "faces", "skin_indices", "skin_weights", "scalp_faces"):
        assert np.array_equal(getattr(body, key), fresh[key]) and getattr(body, key).dtype == fresh[key].dtype
    landmarks = {k[len(_LANDMARK):]: v for k, v in fresh.items() if k.startswith(_LANDMARK)}
    assert sorted(body.landmarks) == sorted(landmarks)
    assert all(np.array_equal(body.landmarks[k], v) for k, v in landmarks.items())
    assert isinstance(body.landmarks["waist_y"], float) and body.landmarks["shoulder_l"].shape == (3,)

    dress = fit_dress(body)
    again = fit_dress(body)  # from the cache
    sections = _BodySections(body)
    lm = sections.landmarks
    built = _fit("dress", sections, 322, 0.012, sections.armpit_y() - 0.03, _lerp(lm["crotch_y"], lm["knee_y"], 0.9),
                 10.0, 0.035, float(lm["waist_y"]))
    for g in (dress, again):
        assert g.name == built.name and g.thickness == built.thickness
        for key in ("vertices", "face_counts", "face_indices", "pinned"):
            assert np.array_equal(getattr(g, key), getattr(built, key))
    again.vertices[0] += 1.0  # each call's arrays are its own
    assert not np.array_equal(fit_dress(body).vertices, again.vertices)


def test_a_scene_grows_its_groom_once(tmp_path, monkeypatch):
    """Two scenes of the same style share one groom entry, and grow what a scene without the cache
    grows; another style gets an entry of its own."""
    import sim.scene as scene_module
    from sim.scene import Scene, hair_demo_scene

    monkeypatch.setenv("CFX_CACHE_DIR", str(tmp_path / "assets"))
    grown = []
    real = scene_module.grow_hairstyle
    monkeypatch.setattr(scene_module, "grow_hairstyle", lambda *a: grown.append(1) or real(*a))
    small = {"scene": {"device": "cpu"}, "hair": {"count": 40, "vertices": 8}}
    a, b = Scene(hair_demo_scene(small)), Scene(hair_demo_scene(small))
    assert len(grown) == 1
    monkeypatch.setenv("CFX_CACHE_DIR", "off")
    c = Scene(hair_demo_scene(small))
    assert len(grown) == 2
    assert np.array_equal(a.model.rest_positions_np, c.model.rest_positions_np)
    assert np.array_equal(b.model.rest_positions_np, c.model.rest_positions_np)
    assert np.array_equal(b.model.widths_np, c.model.widths_np) and np.array_equal(b.model.counts, c.model.counts)
    monkeypatch.setenv("CFX_CACHE_DIR", str(tmp_path / "assets"))
    Scene(hair_demo_scene({**small, "hair": {"count": 40, "vertices": 8, "style": "curly"}}))
    assert len(grown) == 3
    assert sorted(p.name.split("-")[0] for p, _ in asset_cache.entries()) == ["groom", "groom"]


def test_cfx_cache_lists_and_clears(folder):
    asset_cache.cached_arrays("thing", (5,), _counting(ARRAYS)[0])
    run = lambda *a: subprocess.run([sys.executable, "-m", "sim.cli", "cache", *a], capture_output=True,  # noqa: E731
                                    text=True, check=True).stdout
    listing = run()
    assert f"asset cache {folder}: 1 entries" in listing and "thing-" in listing and "stale" not in listing
    assert "removed 1 entries" in run("--clear")
    assert asset_cache.entries() == []


def test_unique_pairs_equals_numpy_unique_by_rows():
    rng = np.random.default_rng(3)
    pairs = rng.integers(0, 50, (400, 2))
    rows, inverse = unique_pairs(pairs, return_inverse=True)
    want_rows, want_inverse = np.unique(pairs, axis=0, return_inverse=True)
    assert np.array_equal(rows, want_rows) and np.array_equal(inverse, want_inverse.reshape(-1))
    assert np.array_equal(rows[inverse], pairs) and rows.dtype == pairs.dtype
    assert unique_pairs(np.zeros((0, 2), np.int64)).shape == (0, 2)
