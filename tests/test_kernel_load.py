"""warp_kernels.load: modules compiled side by side up front, and launches that use what was loaded."""

import json
import os
import subprocess
import sys
import textwrap

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


def test_the_engine_loads_every_kernel_module():
    names = {m.__name__.rsplit(".", 1)[1] for m in warp_kernels._MODULES}
    assert names == set(warp_kernels.__all__) - {"load"}


def test_a_slow_load_says_what_the_run_waits_for(monkeypatch, capsys):
    import time

    import sim.scene as scene

    calls = []
    monkeypatch.setattr(scene, "KERNELS_NOTICE_S", 0.05)
    monkeypatch.setattr(warp_kernels, "load", lambda device, threads: calls.append(device) or time.sleep(0.3))
    scene.load_kernels("cpu", announce=True)
    assert "compiling the Warp kernels for cpu" in capsys.readouterr().err
    scene.load_kernels("cpu", announce=False)  # quiet runs (cfx -q, the Python API) say nothing
    monkeypatch.setattr(warp_kernels, "load", lambda device, threads: calls.append(device))
    scene.load_kernels("cpu", announce=True)  # a warm kernel cache: nothing to say
    assert capsys.readouterr().err == "" and calls == ["cpu"] * 3
