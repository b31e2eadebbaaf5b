"""How long a run waits before its first frame.

Table 1, per scene: `Scene(config)` in a fresh process with the asset cache off (every body,
garment, groom and sphere tree built) and with a warm cache (sim.asset_cache), the kernel modules
already loaded in both. Table 2 (--kernels): the six kernel modules compiled on an empty Warp kernel
cache one after another, as first launches compile them, and side by side (warp_kernels.load); then
the same with the modules of kernels only some runs launch (the GPU's ways, variants for one case:
warp_kernels._options.deferred_module), which a CUDA device loads up front and a CPU at first launch.
Table 3 (--first-run FRAMES): `cfx run` of each scene on an empty kernel cache, end to end.

    python benchmarks/startup.py [--scenes walk_dress wavy_turn] [--repeats 3] [--kernels] [--first-run 2]
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

SETUP = """
import json, sys, time
import warp as wp
from sim.scene import Scene, load_scene, quiet_warp
import warp_kernels
quiet_warp(); wp.init()
config = load_scene(sys.argv[1], {"scene": {"device": sys.argv[2]}})
warp_kernels.load(sys.argv[2])
start = time.perf_counter()
Scene(config)
print(json.dumps(time.perf_counter() - start))
"""

KERNELS = """
import json, sys, time
import warp as wp
wp.config.quiet = True
wp.init()
import warp_kernels
from warp_kernels._options import DEFERRED, OPT_IN
deferred = sys.argv[3] == "deferred"
start = time.perf_counter()
if sys.argv[1] == "side_by_side":
    warp_kernels.load(sys.argv[2], deferred=deferred)
else:
    extra = [d for d in DEFERRED if d not in OPT_IN] if deferred else []
    for name in [m.__name__ for m in warp_kernels._MODULES] + extra:
        wp.load_module(wp.get_module(name), device=sys.argv[2])
print(json.dumps(time.perf_counter() - start))
"""


def _child(script, args, env):
    out = subprocess.run([sys.executable, "-c", script, *args], capture_output=True, text=True, cwd=ROOT,
                         env={**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT),
                                                                                        os.environ.get("PYTHONPATH")])),
                              **env})
    if out.returncode != 0:  # the child's own traceback, not only its exit status
        raise RuntimeError(f"a timed child process failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def setup_times(scene, device, repeats, cache_dir):
    """(seconds built, seconds from a warm cache), medians of `repeats` fresh processes each."""
    path = str(ROOT / "examples" / "scenes" / f"{scene}.toml")
    _child(SETUP, [path, device], {"CFX_CACHE_DIR": cache_dir})  # fills the cache
    built = [_child(SETUP, [path, device], {"CFX_CACHE_DIR": "off"}) for _ in range(repeats)]
    cached = [_child(SETUP, [path, device], {"CFX_CACHE_DIR": cache_dir}) for _ in range(repeats)]
    return statistics.median(built), statistics.median(cached)


def kernel_times(device, deferred):
    """(seconds one module after another, seconds side by side), each on an empty kernel cache: the
    six modules, and with `deferred` also those of the kernels only some runs launch
    (warp_kernels._options.deferred_module)."""
    times = []
    for order in ("one_after_another", "side_by_side"):
        with tempfile.TemporaryDirectory() as kernels:
            times.append(_child(KERNELS, [order, device, "deferred" if deferred else "six"],
                                {"WARP_CACHE_PATH": kernels}))
    return tuple(times)


def first_run_time(scene, device, frames, cache_dir):
    """Wall-clock seconds of `cfx run SCENE --frames FRAMES -q` in a fresh process on an empty Warp
    kernel cache, with the asset cache `cache_dir` (filled by the set-up table): what a first run on
    a machine waits for, compiling the kernels it launches included."""
    import time

    with tempfile.TemporaryDirectory() as work:
        env = {**os.environ, "WARP_CACHE_PATH": str(Path(work) / "kernels"), "CFX_CACHE_DIR": cache_dir,
               "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
        command = [sys.executable, "-m", "sim.cli", "run", str(ROOT / "examples" / "scenes" / f"{scene}.toml"),
                   "-o", str(Path(work) / "out.usdc"), "--frames", str(frames), "-q", "--device", device]
        start = time.perf_counter()
        out = subprocess.run(command, capture_output=True, text=True, cwd=ROOT, env=env)
        seconds = time.perf_counter() - start
    if out.returncode != 0:
        raise RuntimeError(f"cfx run {scene} failed:\n{out.stderr[-3000:]}")
    return seconds


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["walk_dress", "curly_wind", "skirt_arm_raise", "wavy_turn"],
                        help="names in examples/scenes")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--kernels", action="store_true", help="also time the kernel modules' compilation")
    parser.add_argument("--first-run", type=int, default=0, metavar="FRAMES",
                        help="also time `cfx run` of each scene for FRAMES frames on an empty kernel cache")
    args = parser.parse_args(argv)

    from common import commit, device_name, table

    import warp as wp

    from sim.scene import quiet_warp

    quiet_warp()
    wp.init()
    name = device_name(args.device)
    print(f"commit {commit()}, {name}, {os.cpu_count()} cores")
    rows = []
    with tempfile.TemporaryDirectory() as cache_dir:
        for scene in args.scenes:
            built, cached = setup_times(scene, args.device, args.repeats, cache_dir)
            rows.append([scene, name, f"{built:.2f}", f"{cached:.2f}", f"{built / cached:.1f}x"])
        print(table(["scene", "device", "set-up built s", "set-up from the asset cache s", "speed-up"], rows))
        if args.first_run:
            print()
            rows = []
            for scene in args.scenes:
                seconds = first_run_time(scene, args.device, args.first_run, cache_dir)
                rows.append([scene, name, args.first_run, f"{seconds:.1f}"])
            print(table(["scene", "device", "frames", "cfx run on an empty kernel cache s"], rows))
    if args.kernels:
        print()
        rows = []
        for deferred, what in ((False, "the six, empty kernel cache"),
                               (True, "the six and the deferred ones, empty kernel cache")):
            serial, parallel = kernel_times(args.device, deferred)
            rows.append([what, name, f"{serial:.1f}", f"{parallel:.1f}", f"{serial / parallel:.2f}x"])
        print(table(["kernel modules", "device", "one after another s", "side by side s", "speed-up"], rows))


if __name__ == "__main__":
    main()
