"""Markdown reference of the kernels, built from the live modules so that it cannot drift from the code.

    python -m warp_kernels.reference > docs/kernels.md

Every @wp.kernel, @wp.func and @wp.struct defined in the six kernel modules gets a heading, its
docstring and a table of its arguments whose Warp types are read from the signature itself, not
from the prose. Nothing is compiled or launched, so this runs without a GPU and in a second.

The docstrings follow one format, which `parse_docstring` reads back (tests/test_kernel_reference.py
checks it against the signatures):

    One line: what it does and why.

    Launch: one thread per particle (dim = num_particles).
    Inputs:
      name (dtype, shape, unit): what it is
    In/out:
      ...
    Outputs:
      ...
    Returns:          (functions)
    Fields:           (structs)

An entry is a line indented by two spaces, `name (dtype, shape, unit): text`, with as many of
dtype, shape and unit as apply; a Returns entry names the returned type instead (`vec3 (m): ...`,
`int: ...`). Longer entries continue on lines indented further.
"""

import inspect
import re
import sys

import warp as wp

from . import body_motion, cloth, collision, detail, skinning, strands

MODULES = (body_motion, cloth, collision, detail, skinning, strands)

ARGUMENT_SECTIONS = ("Inputs", "In/out", "Outputs", "Fields")  # entries named after arguments or fields
_HEADING = re.compile(r"^(Inputs|In/out|Outputs|Returns|Fields):$")
_ENTRY = re.compile(r"^  (\S+?)(?: \((.*?)\))?:\s*(.*)$")
_LAUNCH = re.compile(r"^Launch: ")

KINDS = ("struct", "kernel", "function")
_KIND_TITLES = {"struct": "Structs", "kernel": "Kernels", "function": "Functions"}
_KIND_NOTES = {
    "struct": "Passed to kernels by value; build one with the struct's constructor and set its fields.",
    "kernel": "Launched from the host with `wp.launch`.",
    "function": "`@wp.func` building blocks, callable only from inside a kernel (your own kernels included).",
}


def kind_of(obj):
    """"kernel", "function" or "struct" for a Warp object, None for anything else."""
    if isinstance(obj, wp.Kernel):
        return "kernel"
    if isinstance(obj, wp.Function):
        return "function"
    if wp.types.type_is_struct(obj):
        return "struct"
    return None


def python_object(obj):
    """The Python function or class a Warp kernel, function or struct was made from."""
    return obj.cls if kind_of(obj) == "struct" else obj.func


def definitions(module):
    """[(name, kind, obj)] of the public Warp objects defined in module (not imported into it),
    in source order."""
    found = []
    for name, obj in vars(module).items():
        kind = kind_of(obj)
        if kind is None or name.startswith("_"):
            continue
        py = python_object(obj)
        if py.__module__ != module.__name__:
            continue  # imported from a sibling module, documented there
        found.append((inspect.getsourcelines(py)[1], name, kind, obj))
    return [(name, kind, obj) for _, name, kind, obj in sorted(found, key=lambda item: item[0])]


def constants(module):
    """[(name, value)] of the module's upper-case integer constants (modes of the kernels' int
    arguments, e.g. collision.COLLIDE_MESH), in source order."""
    return [(name, value) for name, value in vars(module).items()
            if re.fullmatch(r"[A-Z][A-Z0-9_]*", name) and type(value) is int]


def signature(obj):
    """[(name, Warp type)] of a kernel's or function's arguments, or of a struct's fields, from the
    annotations Warp compiles."""
    if kind_of(obj) == "struct":
        return list(inspect.get_annotations(obj.cls).items())
    return [(name, p.annotation) for name, p in inspect.signature(obj.func).parameters.items()]


def type_name(t):
    """Warp's name of an annotated type: float32 for float, array(dtype=vec3f) for a vec3 array."""
    if wp.types.is_array(t):
        dims = "" if t.ndim == 1 else f"ndim={t.ndim}, "
        return f"array({dims}dtype={type_name(t.dtype)})"
    if t is float:
        return "float32"
    if t is int:
        return "int32"
    if t is bool:
        return "bool"
    if wp.types.type_is_vector(t) and t.__name__ == "vec_t":  # a length of its own: named as vec3f is
        return f"vec{t._length_}{type_name(t._wp_scalar_type_)[0]}"
    return getattr(t, "__name__", None) or str(t)


def docstring(obj):
    """The cleaned docstring of the kernel, function or struct ("" when it has none)."""
    return inspect.getdoc(python_object(obj)) or ""


def parse_docstring(doc):
    """{section: [(name, spec, text)]} of a docstring in the format of this module's docstring.

    spec is what the parentheses after the name hold (dtype, shape, unit), None when there are
    none; a Returns entry's name is the returned type. Continuation lines are joined to the text.
    """
    sections, current = {}, None
    for line in doc.splitlines():
        heading = _HEADING.match(line)
        if heading:
            current = sections.setdefault(heading.group(1), [])
            continue
        if current is None:
            continue
        entry = _ENTRY.match(line)
        if entry:
            current.append(list(entry.groups()))
        elif line.startswith("   ") and current:
            current[-1][2] = f"{current[-1][2]} {line.strip()}"
        else:
            current = None  # anything else ends the section
    return {name: [tuple(e) for e in entries] for name, entries in sections.items()}


def _markdown_docstring(doc):
    """A docstring as Markdown: prose as it is, the Launch line in bold, each section as a list."""
    out, in_section = [], False
    for line in doc.splitlines():
        heading = _HEADING.match(line)
        if heading:
            out += ([""] if out and out[-1] else []) + [f"**{heading.group(1)}:**", ""]
            in_section = True
            continue
        if in_section:
            entry = _ENTRY.match(line)
            if entry:
                name, spec, text = entry.groups()
                out.append(f"- `{name}`" + (f" ({spec})" if spec is not None else "") + f": {text}")
                continue
            if line.startswith("   ") and out[-1].startswith("- "):
                out[-1] += " " + line.strip()
                continue
            in_section = False
        if _LAUNCH.match(line):
            out.append("**Launch:** " + line[len("Launch: "):])
        else:
            out.append(line)
    return "\n".join(out).strip() + "\n"


def _table(obj):
    head = "field" if kind_of(obj) == "struct" else "argument"
    rows = [f"| {head} | Warp type |", "| --- | --- |"]
    rows += [f"| `{name}` | `{type_name(t)}` |" for name, t in signature(obj)]
    return "\n".join(rows) + "\n"


PREFACE = """\
# Warp CFX kernel reference

<!-- Generated by `python -m warp_kernels.reference > docs/kernels.md` from the docstrings in
warp_kernels/. Edit those, not this file: tests/test_kernel_reference.py fails when it is stale. -->

`warp_kernels` is the part of Warp CFX that a host application (Blender, Houdini, Maya, a game
engine's tools) embeds: pure NVIDIA Warp kernels, arrays in and arrays out, with no state, no
files and no imports beyond `warp`, `numpy` and the package itself. Every kernel runs on `"cpu"`
and on `"cuda"`.

## Calling a kernel from a host

```python
import numpy as np
import warp as wp

from warp_kernels import cloth

wp.init()
device = "cuda:0" if wp.is_cuda_available() else "cpu"

# host data as float32 / int32 NumPy arrays, in metres
particles = wp.array(np.asarray(particle_points, np.float32), dtype=wp.vec3, device=device)
body = wp.array(np.asarray(body_points, np.float32), dtype=wp.vec3, device=device)
nearest = wp.zeros(len(particles), dtype=wp.int32, device=device)  # outputs are allocated by the caller

wp.launch(cloth.nearest_vertex_brute_force, dim=len(particles), inputs=[particles, body, nearest],
          device=device)
print(nearest.numpy())  # reading back waits for the launch
```

- Pass every argument in the order of the kernel's table below, outputs included: either all in
  `inputs=[...]` (as `sim` does) or the trailing ones in `outputs=[...]`. The launch dimension is
  given by each kernel's **Launch** line.
- Arrays must live on the launch device. Scalars are passed by value: `float` arguments are
  float32, `int` arguments int32, vectors `wp.vec3(x, y, z)`, meshes as `wp.Mesh(...).id`.
- Arrays documented as read only under some flag (for example `bound == 0`) may be passed as `None`
  when the flag is off.
- A kernel's module compiles on its first launch on each device and is cached by Warp afterwards,
  so the first call is slow. CUDA launches are asynchronous: `array.numpy()` or `wp.synchronize()`
  waits for them. The modules are built without backward passes (`enable_backward=False`), so the
  kernels cannot be differentiated with `wp.Tape`.

## Conventions

- **Structure of arrays.** Every attribute is its own 1-D `wp.array` (positions, velocities,
  inverse masses, ...). "per particle" means one entry per particle; "num_particles + 1" is a
  CSR offset array; "1 element" is a device-side scalar (a counter or a clock), kept on the device
  so that launches captured in a CUDA graph replay without host work.
- **Flattened strands and adjacencies.** All strands are stored back to back in one particle
  array, with `strand_start` (num_strands + 1 offsets) marking where each begins and
  `particle_strand` mapping each particle back to its strand, so one launch covers the whole groom.
  Adjacencies (particle -> springs, vertex -> faces, ...) are CSR the same way: a `*_start` array of
  count + 1 offsets and one flat list.
- **Meshes** are a `vec3` point array plus a flat `int32` index array, 3 per triangle. Collider
  meshes must be closed and wound outward, since inside and outside come from the winding. Kernels
  that query a surface also take a `wp.Mesh` id (`uint64`) built over the same points; refit it
  (`mesh.refit()`) after moving the points.
- **Pins and bindings.** Pinned particles have inverse mass 0. A point attached to a mesh is a
  binding: a triangle, barycentric weights of its corners and an offset in the triangle's
  orthonormal frame (`skinning.triangle_frame`), so it follows the triangle rigidly.
- **Units are SI**: metres, seconds, kilograms, and what follows from them (m/s, m/s^2, N, N/m,
  1/s); angles in radians. Scale scenes authored in centimetres (Maya's default unit) to metres
  before uploading. Arguments documented as a "fraction" are unitless ratios.
- **Up axis.** `sim` defaults to Y up (gravity (0, -9.81, 0)), but the kernels take gravity and
  wind as arguments, so a Z-up host passes (0, 0, -9.81) and needs no conversion. Only a few
  fallbacks for degenerate input (a zero-area normal, a point exactly at a sphere's centre or on
  its parent) pick the Y axis.

## Drivers

If you would rather not issue launches yourself, `sim.embed` wraps these kernels in NumPy-in,
NumPy-out drivers that own the buffers and launch in the right order (it needs the rest of the
engine, unlike this package). The solvers `sim.cloth.ClothSolver`, `sim.hair_solver.HairSolver`
and `sim.detail.ClothDetail` show the launch order of a step; each module below also lists it.
"""


def _anchor(text):
    """GitHub's heading anchor: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^a-z0-9 _-]", "", text.lower()).replace(" ", "-")


def markdown():
    """The whole reference as one Markdown string."""
    out = [PREFACE, "## Contents", ""]
    for module in MODULES:
        defs = definitions(module)
        numbers = {kind: sum(k == kind for _, k, _ in defs) for kind in KINDS}
        counts = ", ".join(f"{n} {_KIND_TITLES[kind].lower()[:-1] if n == 1 else _KIND_TITLES[kind].lower()}"
                           for kind, n in numbers.items() if n)
        title = f"warp_kernels.{module.__name__.rsplit('.', 1)[-1]}"
        out.append(f"- [`{title}`](#{_anchor(title)}): {counts}")
    out.append("")
    for module in MODULES:
        title = f"warp_kernels.{module.__name__.rsplit('.', 1)[-1]}"
        out += [f"## `{title}`", "", inspect.getdoc(module).strip(), ""]
        consts = constants(module)
        if consts:
            out += ["### Constants", "", "| name | value |", "| --- | --- |"]
            out += [f"| `{name}` | `{value}` |" for name, value in consts]
            out.append("")
        defs = definitions(module)
        for kind in KINDS:
            group = [(name, obj) for name, k, obj in defs if k == kind]
            if not group:
                continue
            out += [f"### {_KIND_TITLES[kind]}", "", _KIND_NOTES[kind], ""]
            for name, obj in group:
                out += [f"#### `{name}`", "", _markdown_docstring(docstring(obj)), _table(obj)]
    return "\n".join(out).rstrip("\n") + "\n"


def main():
    wp.config.quiet = True  # the output is the document: no banner on stdout
    if hasattr(sys.stdout, "reconfigure"):  # the docstrings cite Müller and use §, whatever the locale
        sys.stdout.reconfigure(encoding="utf-8")
    sys.stdout.write(markdown())


if __name__ == "__main__":
    main()
