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
