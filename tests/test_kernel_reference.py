"""The kernel reference: every public kernel, function and struct of warp_kernels documents each of
its arguments, and docs/kernels.md is what warp_kernels.reference generates from them.

A host application embeds the kernels from their documentation alone, so a renamed argument or a
new kernel without a docstring has to fail here rather than surface as a wrong launch in a
pipeline. No kernel is compiled or launched.
"""

import ast
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import warp as wp

from warp_kernels import reference

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "kernels.md"
REGENERATE = "regenerate it: PYTHONPATH=. python -m warp_kernels.reference > docs/kernels.md"
# what an array argument's shape field looks like: "per particle", "2 per spring", "num_particles + 1",
# "1 element", "2 elements", "num_poses * num_bones"
SHAPE = re.compile(r"(^|\s)per\s|\+ 1$|^\d+ elements?$|\s\*\s")
LAUNCH = re.compile(r"^Launch: one thread per .+ \(dim = .+\)", re.MULTILINE)

DEFINITIONS = [(module, name, kind, obj) for module in reference.MODULES
               for name, kind, obj in reference.definitions(module)]


def short(module):
    return module.__name__.rsplit(".", 1)[-1]


def documented_dtypes(t):
    """The dtype words a docstring may use for an argument of Warp type t; None for a generic one
    (typing.Any: an array or a tile, its word the elements' own)."""
    if t is Any:
        return None
    name = reference.type_name(t.dtype if wp.types.is_array(t) else t)
    if name == "float32":
        return {"float", "float32"}
    if name == "int32":
        return {"int", "int32"}
    return {name, re.sub(r"^(vec\d|mat\d\d|quat)f$", r"\1", name)}


def problems(kind, doc, signature):
    """What is wrong with a docstring against its signature [(name, Warp type)]; [] when nothing."""
    found = []
    sections = reference.parse_docstring(doc)
    if not doc.strip():
        return ["no docstring"]
    wanted = ("Fields",) if kind == "struct" else ("Inputs", "In/out")
    if not any(s in sections for s in wanted):
        found.append(f"no {' or '.join(wanted)} section")
    if kind == "kernel":
        if not LAUNCH.search(doc):
            found.append("no 'Launch: one thread per ... (dim = ...)' line")
        if "Returns" in sections:
            found.append("a kernel returns nothing: Returns section")
        if not ({"Outputs", "In/out"} & set(sections)):
            found.append("writes nothing: no Outputs or In/out section")
    if kind == "function" and not ({"Returns", "Outputs"} & set(sections)):
        found.append("no Returns or Outputs section")
    if kind == "function" and LAUNCH.search(doc):
        found.append("a function is not launched: Launch line")

    entries = [e for s in reference.ARGUMENT_SECTIONS for e in sections.get(s, [])]
    names = [name for name, _, _ in entries]
    types = dict(signature)
    for name in sorted({n for n in names if names.count(n) > 1}):
        found.append(f"{name} documented more than once")
    for name in types:
        if name not in names:
            found.append(f"argument {name} is not documented")
    for name, spec, _ in entries:
        if name not in types:
            found.append(f"{name} is documented but not in the signature")
            continue
        if spec is None:
            found.append(f"{name} has no (dtype, shape, unit)")
            continue
        fields = [f.strip() for f in spec.split(",")]
        dtypes = documented_dtypes(types[name])
        if dtypes is not None and fields[0] not in dtypes:
            found.append(f"{name} is documented as {fields[0]}, the signature has {reference.type_name(types[name])}")
        if wp.types.is_array(types[name]) and not (len(fields) > 1 and SHAPE.search(fields[1])):
            found.append(f"{name} is an array but its shape is not given as the second field")
    return found


def decorated(path):
    """{kind: {names}} of the public top-level @wp.kernel/@wp.func defs and @wp.struct classes of a
    source file, and of those a private top-level factory defines (strands' compiled variants, made
    public as module attributes of the same name), read with ast: an account independent of how
    reference.py discovers them."""
    kinds = {"kernel": "kernel", "func": "function", "struct": "struct"}
    out = {k: set() for k in kinds.values()}
    body = ast.parse(path.read_text()).body
    factories = [n for n in body if isinstance(n, ast.FunctionDef) and n.name.startswith("_")]
    for node in body + [inner for f in factories for inner in f.body]:
        if not isinstance(node, (ast.FunctionDef, ast.ClassDef)) or node.name.startswith("_"):
            continue
        for dec in node.decorator_list:
            target = dec.func if isinstance(dec, ast.Call) else dec
            if isinstance(target, ast.Attribute) and target.attr in kinds:
                out[kinds[target.attr]].add(node.name)
    return out


@pytest.mark.parametrize("module", reference.MODULES, ids=short)
def test_reference_finds_every_definition(module):
    found = {kind: {name for name, k, _ in reference.definitions(module) if k == kind} for kind in reference.KINDS}
    assert found == decorated(Path(module.__file__))


def test_the_modules_hold_the_expected_number_of_kernels():
    # a sanity floor: a discovery bug that finds nothing must not pass the per-definition checks vacuously
    kinds = [kind for _, _, kind, _ in DEFINITIONS]
    assert kinds.count("kernel") >= 44 and kinds.count("function") >= 30 and kinds.count("struct") >= 1


@pytest.mark.parametrize(("module", "name", "kind", "obj"), DEFINITIONS,
                         ids=[f"{short(m)}.{n}" for m, n, _, _ in DEFINITIONS])
def test_docstring_documents_every_argument(module, name, kind, obj):
    assert problems(kind, reference.docstring(obj), reference.signature(obj)) == []


def test_the_docstring_check_catches_mistakes():
    sig = [("x", wp.array(dtype=wp.vec3)), ("dt", float), ("out", wp.array(dtype=float))]
    good = """Do it.

Launch: one thread per particle (dim = num_particles).
Inputs:
  x (vec3, per particle, m): positions
  dt (float, s): step
Outputs:
  out (float, per particle, m): result
"""
    assert problems("kernel", good, sig) == []
    assert problems("kernel", good.replace("  dt (float, s): step\n", ""), sig) == ["argument dt is not documented"]
    assert problems("kernel", good.replace("  dt (", "  h ("), sig) == [
        "argument dt is not documented", "h is documented but not in the signature"]
    assert problems("kernel", good.replace("x (vec3,", "x (float,"), sig) == [
        "x is documented as float, the signature has array(dtype=vec3f)"]
    assert problems("kernel", good.replace("x (vec3, per particle, m)", "x (vec3, m)"), sig) == [
        "x is an array but its shape is not given as the second field"]
    assert problems("kernel", good.replace("Launch: one", "Runs one"), sig) == [
        "no 'Launch: one thread per ... (dim = ...)' line"]
    assert problems("kernel", good.replace("Inputs:", "Arguments:"), sig) == [
        "no Inputs or In/out section", "argument x is not documented", "argument dt is not documented"]
    assert problems("function", good, sig) == ["a function is not launched: Launch line"]
    assert problems("kernel", "", sig) == ["no docstring"]


def test_continuation_lines_join_their_entry():
    doc = "Inputs:\n  a (float, m): first\n      and more\n  b (int): second\nReturns:\n  vec3 (m): point\n"
    assert reference.parse_docstring(doc) == {
        "Inputs": [("a", "float, m", "first and more"), ("b", "int", "second")],
        "Returns": [("vec3", "m", "point")],
    }


def test_docs_kernels_md_is_current():
    assert DOC.exists(), f"docs/kernels.md is missing; {REGENERATE}"
    assert DOC.read_text(encoding="utf-8") == reference.markdown(), f"docs/kernels.md is stale; {REGENERATE}"


def test_reference_mentions_every_kernel_function_and_struct():
    text = reference.markdown()
    headings = re.findall(r"^#### `(\w+)`$", text, re.MULTILINE)
    assert sorted(headings) == sorted(name for _, name, _, _ in DEFINITIONS)
    for module, name, kind, obj in DEFINITIONS:
        section = text.split(f"#### `{name}`\n", 1)[1].split("\n#### ", 1)[0]
        for arg, t in reference.signature(obj):
            assert f"| `{arg}` | `{reference.type_name(t)}` |" in section, f"{short(module)}.{name}: {arg}"


def test_reference_builds_without_launching(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("the reference must not launch kernels")

    monkeypatch.setattr(wp, "launch", refuse)
    assert reference.markdown().startswith("# Warp CFX kernel reference\n")


def test_kernel_package_imports_only_warp_numpy_and_the_standard_library():
    allowed = {"warp", "numpy", *sys.stdlib_module_names}
    for path in sorted((ROOT / "warp_kernels").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                roots = [alias.name.split(".")[0] for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                roots = [node.module.split(".")[0]]
            else:
                continue
            assert set(roots) <= allowed, f"{path.name} imports {roots}"


def test_command_line_prints_the_reference_and_imports_no_engine():
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    run = subprocess.run([sys.executable, "-m", "warp_kernels.reference"], cwd=ROOT, env=env, capture_output=True,
                         text=True, encoding="utf-8", check=True, timeout=120)
    assert run.stdout == reference.markdown()
    code = ("import sys, warp_kernels.reference as r; r.markdown(); "
            "sys.exit(sorted(m for m in sys.modules if m.split('.')[0] in ('sim', 'io_usd')) or 0)")
    probe = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True,
                           check=False, timeout=120)
    assert probe.returncode == 0, probe.stderr
