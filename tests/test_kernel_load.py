"""warp_kernels.load: modules compiled side by side up front, and launches that use what was loaded."""

import json
import os
import subprocess
import sys
import textwrap

import pytest

import warp_kernels

TINY = {
    "tiny_add": """
        import warp as wp

        @wp.kernel
        def add_one(x: wp.array(dtype=float)):
            i = wp.tid()
            x[i] = x[i] + 1.0
    """,
    "tiny_scale": """
        import warp as wp

        @wp.kernel
        def scale(x: wp.array(dtype=float), s: float):
            i = wp.tid()
            x[i] = x[i] * s
    """,
}

SCRIPT = """
import json, sys
import warp as wp
wp.init()
import tiny_add, tiny_scale
import warp_kernels
print("LOAD", flush=True)
warp_kernels.load("cpu", threads=2, modules=(tiny_add, tiny_scale))
print("LAUNCH", flush=True)
x = wp.array([1.0, 2.0, 3.0], dtype=float)
wp.launch(tiny_add.add_one, 3, [x])
wp.launch(tiny_scale.scale, 3, [x, 10.0])
print("RESULT", json.dumps(x.numpy().tolist()), flush=True)
"""


def test_loaded_modules_are_compiled_once_and_launches_use_them(tmp_path):
    for name, source in TINY.items():
        (tmp_path / f"{name}.py").write_text(textwrap.dedent(source))
    env = dict(os.environ, WARP_CACHE_PATH=str(tmp_path / "kernels"),
               PYTHONPATH=os.pathsep.join([str(tmp_path), os.getcwd(), os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, check=True,
                         timeout=300).stdout
    loading, launching = out.split("LOAD", 1)[1].split("LAUNCH", 1)
    # Warp logs each module load; both compile (a cold cache) before the launches, none after
    assert sorted(line.split()[1] for line in loading.splitlines() if "(compiled)" in line) == \
        ["tiny_add", "tiny_scale"]
    assert "load on device" not in launching
    assert json.loads(launching.split("RESULT", 1)[1]) == [20.0, 30.0, 40.0]


# a kernel of tiny_add's kept in a module of its own, as warp_kernels keeps its GPU ways
TINY_RARE = """
    import warp as wp

    from warp_kernels._options import deferred_module

    @wp.kernel(module=deferred_module("tiny_add.rarely"))
    def halve(x: wp.array(dtype=float)):
        i = wp.tid()
        x[i] = x[i] * 0.5
"""

DEFERRED_SCRIPT = """
import warp as wp
wp.init()
import tiny_add, tiny_scale, tiny_rare
import warp_kernels
from warp_kernels._options import DEFERRED
assert DEFERRED[-1] == "tiny_add.rarely"
print("RUN", flush=True)
warp_kernels.load("cpu", threads=2, modules=(tiny_add, tiny_scale))
print("ALL", flush=True)
warp_kernels.load("cpu", threads=2, modules=(tiny_add, tiny_scale), deferred=True)
print("LAUNCH", flush=True)
x = wp.array([2.0], dtype=float)
wp.launch(tiny_rare.halve, 1, [x])
print("RESULT", x.numpy()[0], flush=True)
"""


def test_a_deferred_module_compiles_only_when_asked_for(tmp_path):
    """Kernels only some runs launch (warp_kernels._options.deferred_module) are left out of a run's
    load, so a first run on a cold cache does not wait for them; load(deferred=True) compiles them
    too, side by side."""
    for name, source in {**TINY, "tiny_rare": TINY_RARE}.items():
        (tmp_path / f"{name}.py").write_text(textwrap.dedent(source))
    env = dict(os.environ, WARP_CACHE_PATH=str(tmp_path / "kernels"),
               PYTHONPATH=os.pathsep.join([str(tmp_path), os.getcwd(), os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run([sys.executable, "-c", DEFERRED_SCRIPT], env=env, capture_output=True, text=True,
                         check=True, timeout=300).stdout
    run, rest = out.split("RUN", 1)[1].split("ALL", 1)
    everything, launching = rest.split("LAUNCH", 1)

    def compiled(log):
        return sorted(line.split()[1] for line in log.splitlines() if "(compiled)" in line)

    assert compiled(run) == ["tiny_add", "tiny_scale"]
    assert compiled(everything) == ["tiny_add.rarely"]
    assert "load on device" not in launching
    assert float(launching.split("RESULT", 1)[1]) == 1.0


def test_the_deferred_modules_take_the_package_options():
    import warp as wp

    from warp_kernels._options import DEFERRED, MODULE_OPTIONS

    assert {"warp_kernels.strands.apart", "warp_kernels.cloth.step_in_block"} <= set(DEFERRED)
    for name in DEFERRED:
        options = wp.get_module(name).options
        assert {key: options[key] for key in MODULE_OPTIONS} == MODULE_OPTIONS, name



def test_opt_in_modules_load_only_where_named(monkeypatch):
    """The hair's frame in one launch (strands.FRAME_IN_BLOCK and FRAME_IN_WARPS, each layout's variants,
    and its poses made ahead, strands.FRAME_POSES) is opt-in: load(deferred=True), a GPU's default, leaves
    it to the first frame that launches it; naming it loads it."""
    import warp as wp

    from warp_kernels import strands
    from warp_kernels._options import DEFERRED, OPT_IN

    seen = []
    monkeypatch.setattr(wp, "force_load", lambda device, modules, max_workers: seen.append({m.name for m in modules}))
    warp_kernels.load("cpu", modules=(strands,), deferred=True)
    frames = [*strands.FRAME_IN_BLOCK.values(), *strands.FRAME_IN_WARPS.values()]
    assert {kernel.module.name for kernel in frames} | {strands.FRAME_POSES} == set(OPT_IN)
    # a layout built at run time for a timing is compiled at its first launch, listed nowhere
    assert strands.frame_variant((2, 4, 2), strands.PATHS_NONE).module.name not in OPT_IN + DEFERRED
    assert "warp_kernels.strands.apart" in seen[0] and not seen[0] & set(OPT_IN)
    warp_kernels.load("cpu", modules=(strands,), deferred=OPT_IN[:1])
    assert OPT_IN[0] in seen[1]

def test_a_cpu_run_of_the_built_in_scene_launches_nothing_deferred(monkeypatch):
    """The CPU's default ways (the hair's fused substep on the mesh, the cloth's box queries, the detail
    surface, the face) launch only kernels of the six modules warp_kernels.load compiles for a run, so a
    first run on a cold kernel cache waits for those alone."""
    import warp as wp

    from sim.scene import Scene, demo_scene
    from warp_kernels._options import DEFERRED

    launched = set()
    launch = wp.launch

    def recording(kernel, *args, **kwargs):
        launched.add(kernel.module.name)
        return launch(kernel, *args, **kwargs)

    monkeypatch.setattr(wp, "launch", recording)
    scene = Scene(demo_scene({"scene": {"device": "cpu", "frames": 1, "preroll": 0.0, "stats": False},
                              "hair": {"count": 40, "vertices": 8}}))
    scene.graphs.enabled = False
    scene.advance(2.0 / scene.config.timing.fps, detail=True)
    own = {m.__name__ for m in warp_kernels._MODULES}
    assert {"warp_kernels.strands", "warp_kernels.cloth", "warp_kernels.detail"} <= launched
    assert not launched & set(DEFERRED)
    assert {name for name in launched if name.startswith("warp_kernels")} <= own


@pytest.mark.parametrize("collision,shape_matching,module", [
    ("mesh", "full", None), ("sphere_tree", "full", None),
    ("sphere_tree", "simplified", "warp_kernels.strands.step_strands_sphere_lists_simplified"),
    ("none", "full", "warp_kernels.strands.step_strands_queries")])
def test_a_scene_loads_the_fused_variant_its_hair_launches(monkeypatch, collision, shape_matching, module):
    """A CPU scene asks warp_kernels.load for the deferred module of the fused substep its hair will
    launch (sim.hair_solver.deferred_step_modules), so a first run compiles it beside the six modules
    rather than at its first frame; the kernel its frames launch is that module's (or a core one)."""
    import warp as wp

    from sim.scene import Scene, hair_demo_scene

    asked, load = [], warp_kernels.load
    monkeypatch.setattr(warp_kernels, "load", lambda device, threads, deferred: asked.append(deferred) or
                        load(device, threads, deferred=deferred))
    launched, launch = set(), wp.launch

    def recording(kernel, *args, **kwargs):
        if kernel.key.startswith("step_strands"):
            launched.add(kernel.module.name)
        return launch(kernel, *args, **kwargs)

    monkeypatch.setattr(wp, "launch", recording)
    scene = Scene(hair_demo_scene({"scene": {"device": "cpu", "frames": 1, "preroll": 0.0, "stats": False},
                                   "head": {"sphere_leaves": 48}, "hair": {"count": 20, "vertices": 6},
                                   "solver": {"collision": collision, "shape_matching": shape_matching}}))
    assert asked == [[module] if module else []]
    scene.graphs.enabled = False
    scene.advance(1.0 / scene.config.timing.fps)
    assert launched == {module or "warp_kernels.strands"}


def test_the_engine_loads_every_kernel_module():
    names = {m.__name__.rsplit(".", 1)[1] for m in warp_kernels._MODULES}
    assert names == set(warp_kernels.__all__) - {"load"}


def test_a_slow_load_says_what_the_run_waits_for(monkeypatch, capsys):
    import time

    import sim.scene as scene

    calls = []
    monkeypatch.setattr(scene, "KERNELS_NOTICE_S", 0.05)
    monkeypatch.setattr(warp_kernels, "load", lambda device, threads, deferred: calls.append(device) or time.sleep(0.3))
    scene.load_kernels("cpu", announce=True)
    assert "compiling the Warp kernels for cpu" in capsys.readouterr().err
    scene.load_kernels("cpu", announce=False)  # quiet runs (cfx -q, the Python API) say nothing
    monkeypatch.setattr(warp_kernels, "load", lambda device, threads, deferred: calls.append(device))
    scene.load_kernels("cpu", announce=True)  # a warm kernel cache: nothing to say
    assert capsys.readouterr().err == "" and calls == ["cpu"] * 3
