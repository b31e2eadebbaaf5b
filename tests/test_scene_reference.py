"""The scene file reference: docs/scene_reference.md is what sim.scene_reference generates, it lists
every key the loader accepts, and no key goes unexplained."""

import dataclasses
from pathlib import Path

import pytest

from sim import load_scene
from sim.errors import InputError
from sim.scene_reference import field_comments, markdown, reference_rows, scene_tables, toml_value

DOC = Path(__file__).resolve().parent.parent / "docs" / "scene_reference.md"


def test_the_committed_reference_is_the_generated_one():
    assert DOC.read_text() == markdown(), "regenerate it: PYTHONPATH=. python -m sim.scene_reference > " \
                                          "docs/scene_reference.md"


@pytest.mark.parametrize("table,cls", scene_tables(), ids=[t for t, _ in scene_tables()])
def test_every_key_is_explained(table, cls):
    rows = reference_rows(cls, table)
    assert [key for key, _, _ in rows] == [f.name for f in dataclasses.fields(cls) if f.init]
    assert not [key for key, _, meaning in rows if len(meaning) < 4], f"[{table}] keys without a comment"


def test_comments_above_a_field_and_on_its_line_are_both_read():
    @dataclasses.dataclass
    class Example:
        plain: int = 1
        # the first line above
        # and the second
        spaced: float = 2.0  # and its own
        bare: str = "x"

    assert field_comments(Example) == {"spaced": "the first line above and the second and its own"}
    assert [toml_value(v) for v in (True, "a", (0.5, 1), 3)] == ["true", '"a"', "[0.5, 1]", "3"]


@pytest.mark.parametrize("table,cls", scene_tables(), ids=[t for t, _ in scene_tables()])
def test_every_key_listed_loads_and_an_unlisted_one_does_not(tmp_path, table, cls):
    """Each table's documented keys at their documented defaults make a scene the loader takes."""
    import tomllib

    lines = []
    for key, default, _ in reference_rows(cls, table):
        if default and key != "enabled":
            lines.append(f"{key} = {default}")
    header = ("[body]\n" if table.startswith("cloth") else "") + f"[{table}]\n"  # a built-in garment needs the body
    scene = tmp_path / "scene.toml"
    scene.write_text(header + "\n".join(lines) + "\n")
    tomllib.loads(scene.read_text())  # the defaults are written as TOML
    load_scene(scene)
    scene.write_text(header + "not_a_key = 1\n")
    with pytest.raises(InputError, match="not_a_key"):
        load_scene(scene)


# the settings a negative value is meaningful for: frame numbers
SIGNED = {("scene", "start_frame"), ("face", "audio_start")}


def _load_one(tmp_path, table, key, value):
    header = ("[body]\n" if table.startswith("cloth") else "") + f"[{table}]\n"
    scene = tmp_path / "scene.toml"
    scene.write_text(header + f"{key} = {value!r}\n".replace("'", '"'))
    return load_scene(scene)


@pytest.mark.parametrize("table,cls", scene_tables(), ids=[t for t, _ in scene_tables()])
def test_every_number_has_a_range_and_the_error_names_its_key(tmp_path, table, cls):
    """A setting that is a count, a length, a rate or a stiffness refuses a negative value with one line
    naming it (a QA pass had found negative widths, margins and drags accepted silently, and a negative
    seed blamed on head.scalp_faces); the default is in range."""
    defaults = cls()
    for f in dataclasses.fields(cls):
        default = getattr(defaults, f.name)
        if not f.init or isinstance(default, bool) or not isinstance(default, (int, float)):
            continue
        low = -2 ** 31 + 1 if isinstance(default, int) else -1e30
        if (table, f.name) not in SIGNED:
            with pytest.raises(InputError, match=f"{table}.{f.name}: "):
                _load_one(tmp_path, table, f.name, low)
        _load_one(tmp_path, table, f.name, default)


@pytest.mark.parametrize("table,key,value,reason", [
    ("hair", "length_jitter", 1.0, "within [0, 1)"),  # strands of no length: a traceback
    ("hair", "seed", -1, "zero or positive"),
    ("hair", "root_width", -1e-4, "positive"),
    ("hair", "wavelength", 0.0, "positive"),  # NaN strand points
    ("hair", "clearance", 1e3, "beyond a character's scale"),
    ("hair", "length", 1e30, "beyond a character's scale"),  # exploded: exit 3
    ("scene", "fps", 1e-300, "at least 1"),  # the frame's step overflowed float32: exit 3
    ("scene", "fps", 1e300, "at most 10,000"),
    ("solver", "max_speed", 0.0, "positive"),  # every frame reported as an explosion
    ("solver", "collision_search", 0.0, "positive"),
    ("solver", "wind", [0.0, 0.0, 1e6], "at most 200 long"),
    ("solver", "gravity", [0.0, -1e30, 0.0], "at most 1000 long"),
    ("solver", "rotation_iterations", 2 ** 31 - 1, "would not finish"),
    ("head", "turn_degrees", 1e6, "within [-180, 180]"),
    ("cloth.solver", "walk_refresh", 0, "positive"),  # re-seeded every step modulo zero
    ("cloth.solver", "strain_iterations", -1, "zero or positive"),
    ("cloth.solver", "collision_margin", 5.0, "beyond a character's scale"),
    ("cloth.detail", "margin", -0.01, "zero or positive"),
    ("capture", "height", 8, "within [16, 8192]"),
    ("capture", "seed", -1, "zero or positive"),
])
def test_values_a_qa_pass_found_accepted_or_crashing_are_refused(tmp_path, table, key, value, reason):
    with pytest.raises(InputError) as err:
        _load_one(tmp_path, table, key, value)
    assert f"{table}.{key}: " in str(err.value) and reason in str(err.value), str(err.value)
