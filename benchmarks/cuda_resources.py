"""Registers, spills and stack of every CUDA kernel of warp_kernels, without a GPU.

A kernel that runs one long serial loop per thread (the hair's length pass, step_strands) is bound
by how many warps an SM holds, and that is set by its registers; spills to local memory cost
loads in the loop. Both come from the compiler, not the device: Warp compiles each module to PTX
with NVRTC (no driver needed) and ptxas -v reports what each kernel uses on the target
architecture. So a session without a GPU can still see what a change does to a kernel's fit.

ptxas comes from a CUDA toolkit (PATH, $CUDA_HOME/bin or /usr/local/cuda*/bin). When Warp's NVRTC
writes a newer PTX ISA version than that ptxas reads, the version line is lowered to the ptxas's
own; the report says so. Kernels that use an instruction only the newer ISA has would then fail to
assemble, and are reported as such.

    python benchmarks/cuda_resources.py                       # every module, sm_90 (H100, H200)
    python benchmarks/cuda_resources.py --modules strands --arch 90
    python benchmarks/cuda_resources.py --record              # and make the result the recorded baseline

The recorded baseline (benchmarks/cuda_resources_sm90.json, every module for sm_90) is what
tests/test_benchmarks.py holds each kernel's spills to: a change that spills more fails there until
the baseline is recorded again, on purpose. Sessions without a GPU once tripled a hot kernel's spills
without noticing, and an H100 lost a third of its speed to it (BENCHMARKS.md, session 34).
"""

import argparse
import importlib
import json
import re
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import commit, table  # noqa: E402

MODULES = ["strands", "cloth", "collision", "detail", "skinning"]
BASELINE = Path(__file__).resolve().parent / "cuda_resources_sm90.json"
HEADER = ["module", "kernel", "registers", "cap", "stack B", "spill stores B", "spill loads B", "shared B", "tiles B",
          "block", "blocks an SM (limit)"]
# a block's static shared memory on every architecture since sm_70 (more is an opt-in Warp does not take)
STATIC_SHARED_LIMIT = 48 * 1024
# what an SM of sm_90 (H100, H200) holds: CUDA's occupancy rules for compute capability 9.0
SM90 = {"registers": 65536, "register_unit": 256, "warps": 64, "blocks": 32, "shared": 233472, "block_shared": 232448,
        "reserved_shared": 1024}


@dataclass
class KernelResources:
    kernel: str
    registers: int
    cap: int | None  # the kernel's register cap (.maxnreg), None for the compiler's choice
    stack: int
    spill_stores: int
    spill_loads: int
    shared: int = 0  # bytes of static shared memory a block of the module's block_dim lanes takes
    tiles: int = 0  # bytes of dynamic shared memory its tiles take a block (Warp's launch asks for them)
    block: int = 256  # the lanes of a block its module is compiled (and launched) with


def blocks_per_sm(k, sm=SM90):
    """(blocks of kernel k an SM holds at once, what limits it: registers, shared, threads or blocks) by
    CUDA's occupancy rules: registers are given a warp in units of register_unit, and each block's shared
    memory is its static and dynamic bytes plus what the system reserves. 0 where a block does not fit."""
    warps = -(-k.block // 32)
    per_warp = -(-k.registers * 32 // sm["register_unit"]) * sm["register_unit"]
    shared = k.shared + k.tiles + sm["reserved_shared"]
    limits = {"registers": sm["registers"] // per_warp // warps if per_warp else sm["blocks"],
              "shared": sm["shared"] // shared if k.shared + k.tiles <= sm["block_shared"] else 0,
              "threads": sm["warps"] // warps, "blocks": sm["blocks"]}
    limit = min(limits, key=limits.get)
    return limits[limit], limit


def find_ptxas():
    """The ptxas executable of a CUDA toolkit, or None."""
    import os

    found = shutil.which("ptxas")
    if found:
        return found
    roots = [os.environ.get("CUDA_HOME", ""), os.environ.get("CUDA_PATH", "")]
    roots += sorted((str(p) for p in Path("/usr/local").glob("cuda*")), reverse=True)
    for root in roots:
        candidate = Path(root) / "bin" / "ptxas"
        if root and candidate.exists():
            return str(candidate)
    return None


def nvrtc_archs():
    """The architectures Warp's NVRTC compiles for (empty without a CUDA-enabled Warp). Warp keeps
    them on its runtime, which it does not export; read with a fallback so a change there reads as
    "none" rather than an error."""
    import warp as wp

    wp.init()
    runtime = getattr(getattr(getattr(wp, "_src", None), "context", None), "runtime", None)
    if runtime is None or not getattr(runtime, "is_cuda_enabled", False):
        return []
    return list(getattr(runtime, "nvrtc_supported_archs", None) or [])


def ptxas_isa(ptxas):
    """The newest PTX ISA version (e.g. '9.0') this ptxas assembles, from an empty module it rejects."""
    with tempfile.TemporaryDirectory() as tmp:
        probe = Path(tmp) / "probe.ptx"
        probe.write_text(".version 99.9\n.target sm_90\n.address_size 64\n")
        out = subprocess.run([ptxas, "-arch=sm_90", str(probe), "-o", str(Path(tmp) / "probe.cubin")],
                             capture_output=True, text=True)
    match = re.search(r"current version is '([0-9.]+)'", out.stderr + out.stdout)
    return match.group(1) if match else None


def kernel_name(entry):
    """follow_the_leader from follow_the_leader_bce2c61e_cuda_kernel_forward."""
    return re.sub(r"_[0-9a-f]{8}_cuda_kernel_forward$", "", entry)


def parse_ptxas(log, caps):
    """KernelResources per kernel entry from ptxas -v output; caps: entry -> .maxnreg."""
    found, entry, props = [], None, None
    for line in log.splitlines():
        start = re.search(r"Compiling entry function '([^']+)'", line)
        if start:
            entry, props = start.group(1), None
            continue
        spill = re.search(r"(\d+) bytes stack frame, (\d+) bytes spill stores, (\d+) bytes spill loads", line)
        if spill and entry:
            props = tuple(int(g) for g in spill.groups())
            continue
        used = re.search(r"Used (\d+) registers", line)
        if used and entry and entry.endswith("_cuda_kernel_forward"):
            stack, stores, loads = props or (0, 0, 0)
            shared = re.search(r"(\d+) bytes smem", line)
            found.append(KernelResources(kernel_name(entry), int(used.group(1)), caps.get(entry), stack, stores, loads,
                                         int(shared.group(1)) if shared else 0))
            entry = None
    return found


def register_caps(ptx):
    """entry -> the .maxnreg of that entry in a PTX module."""
    caps = {}
    for match in re.finditer(r"\.entry\s+(\w+)\s*\((.*?)\)\s*(\.maxnreg\s+(\d+))?", ptx, re.S):
        if match.group(4):
            caps[match.group(1)] = int(match.group(4))
    return caps


def warp_modules(module):
    """The names of the Warp modules of an imported warp_kernels module: its own and those its kernels
    only some runs launch are kept in (warp_kernels._options.deferred_module)."""
    from warp_kernels._options import DEFERRED

    return [module.__name__] + [name for name in DEFERRED if name.startswith(module.__name__ + ".")]


def modules_resources(modules, arch, ptxas, isa, workdir, workers=None):
    """{module name: (KernelResources list, note)} for imported warp_kernels modules compiled for
    sm_<arch>, their Warp modules compiled and assembled side by side in `workers` threads (default:
    one per core; NVRTC and ptxas run outside the interpreter's lock, as in Warp's own loader)."""
    import os
    from concurrent.futures import ThreadPoolExecutor

    names = [(module.__name__, name) for module in modules for name in warp_modules(module)]
    with ThreadPoolExecutor(max_workers=max(1, workers or os.cpu_count() or 1)) as pool:
        results = list(pool.map(lambda pair: warp_module_resources(pair[1], arch, ptxas, isa, workdir), names))
    out = {module.__name__: ([], []) for module in modules}
    for (owner, _name), (kernels, note) in zip(names, results, strict=True):
        found, notes = out[owner]
        found += kernels
        if note and note not in notes:
            notes.append(note)
    return {owner: (found, "; ".join(notes)) for owner, (found, notes) in out.items()}


def warp_module_resources(name, arch, ptxas, isa, workdir):
    """(KernelResources list, note) for the Warp module `name` compiled for sm_<arch>."""
    import warp as wp

    [ptx_path] = wp.compile_aot_module(wp.get_module(name), arch=arch, module_dir=workdir, use_ptx=True)
    ptx = Path(ptx_path).read_text(errors="replace").replace("\0", "")
    note = ""
    version = re.search(r"^\.version ([0-9.]+)", ptx, re.M)
    if isa and version and tuple(map(int, version.group(1).split("."))) > tuple(map(int, isa.split("."))):
        ptx = ptx.replace(version.group(0), f".version {isa}", 1)
        note = f"PTX {version.group(1)} assembled as {isa}"
    source = Path(workdir) / f"{name}.sm{arch}.ptx"
    source.write_text(ptx)
    out = subprocess.run([ptxas, f"-arch=sm_{arch}", "-v", str(source), "-o", str(source.with_suffix(".cubin"))],
                         capture_output=True, text=True)
    if out.returncode != 0:
        raise RuntimeError(f"ptxas failed on {name}: {(out.stderr or out.stdout).strip()[:300]}")
    found = parse_ptxas(out.stderr + out.stdout, register_caps(ptx))
    # the tiles' bytes Warp's build wrote beside the PTX ({entry}_smem_bytes), and the block it compiled for
    tiles = {}
    for meta in Path(ptx_path).parent.glob(f"wp_{name}_*.meta"):
        for key, value in json.loads(meta.read_text()).items():
            tiles[kernel_name(key.removesuffix("_smem_bytes"))] = int(value)
    block = wp.get_module(name).options.get("block_dim", 256)
    for k in found:
        k.tiles, k.block = tiles.get(k.kernel, 0), block
    return found, note


def baseline_record(found, warp_version, isa):
    """The JSON-ready baseline of {module: [KernelResources]}: per "module.kernel", registers and
    spill stores and loads in bytes, with the Warp version and PTX ISA that produced them."""
    kernels = {f"{module}.{k.kernel}": [k.registers, k.spill_stores, k.spill_loads]
               for module, ks in sorted(found.items()) for k in sorted(ks, key=lambda k: k.kernel)}
    return {"arch": 90, "warp": warp_version, "ptx_isa": isa, "kernels": kernels}


def spill_regressions(found, baseline):
    """Kernels of {module: [KernelResources]} that spill more than the baseline records (a kernel it
    does not record counts as recorded without spills): ["module.kernel: stores/loads B, recorded
    stores/loads B"]."""
    worse = []
    for module, ks in sorted(found.items()):
        for k in sorted(ks, key=lambda k: k.kernel):
            name = f"{module}.{k.kernel}"
            _registers, stores, loads = baseline["kernels"].get(name, (0, 0, 0))
            if k.spill_stores > stores or k.spill_loads > loads:
                worse.append(f"{name}: spills {k.spill_stores}/{k.spill_loads} B, recorded {stores}/{loads} B")
    return worse


# the layouts benchmarks/run_gpu.sh frame-layouts times: (side, groups, run) of strands.frame_variant
FRAME_LAYOUTS = ["32x8x4", "16x8x4", "8x8x4", "4x8x4", "1x8x4", "64x4x8"]
FRAME_HEADER = ["layout", "collider", "registers", "spill stores / loads B", "tiles B", "block", "blocks an SM (limit)",
                "strands an SM", "chain warps an SM", "barriers a substep's chain"]


def frame_layouts_table(layouts, arch, ptxas, isa):
    """A table of what an SM of sm_90 holds of the hair frame in each layout ('SIDExGROUPSxRUN'), simplified
    shape matching on the sphere tree and with no collider: its registers, spills and tiles, blocks an SM,
    the strands those hold (their chains walk side by side) and the warps their chains keep busy at each
    step (a warp per 32 strands of a block, or part of one); the barriers of a substep's chain are its
    turns, one per group."""
    import os
    from concurrent.futures import ThreadPoolExecutor

    from warp_kernels import strands

    variants = [(tuple(int(n) for n in text.split("x")), paths) for text in layouts
                for paths in (strands.PATHS_SPHERE_LISTS, strands.PATHS_NONE)]
    kernels = [strands.frame_variant(layout, paths) for layout, paths in variants]
    with tempfile.TemporaryDirectory(prefix="cfx_ptx_") as workdir, \
            ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        found = list(pool.map(lambda k: warp_module_resources(k.module.name, arch, ptxas, isa, workdir)[0][0], kernels))
    rows = []
    for ((side, groups, run), paths), k in zip(variants, found, strict=True):
        blocks, limit = blocks_per_sm(k)
        rows.append([f"{side}x{groups}x{run}", "sphere tree" if paths == strands.PATHS_SPHERE_LISTS else "none",
                     k.registers, f"{k.spill_stores} / {k.spill_loads}", k.tiles, k.block, f"{blocks} ({limit})",
                     blocks * side, blocks * -(-side // 32), groups])
    return table(FRAME_HEADER, rows)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--modules", nargs="*", default=MODULES, choices=MODULES)
    parser.add_argument("--arch", type=int, default=90, help="SM architecture (90: H100 and H200)")
    parser.add_argument("--frame-layouts", nargs="*", default=None, metavar="SIDExGROUPSxRUN",
                        help="also compile the hair frame (strands.frame_variant, simplified shape matching on the "
                             "sphere tree and with no collider) in these layouts and say what an SM holds of each "
                             "(none given: the six of run_gpu.sh frame-layouts)")
    parser.add_argument("--record", action="store_true",
                        help=f"write the result as the recorded baseline ({BASELINE.name}; every module, sm_90)")
    args = parser.parse_args()
    if args.record and (args.arch != 90 or sorted(args.modules) != sorted(MODULES)):
        parser.error("--record takes every module for sm_90")
    import warp as wp

    from sim.scene import quiet_warp

    quiet_warp()
    wp.init()
    ptxas = find_ptxas()
    if ptxas is None:
        print("cuda_resources: no ptxas found (install a CUDA toolkit or set CUDA_HOME)", file=sys.stderr)
        sys.exit(2)
    if args.arch not in nvrtc_archs():
        print(f"cuda_resources: this Warp's NVRTC does not compile for sm_{args.arch} (it does: {nvrtc_archs()})",
              file=sys.stderr)
        sys.exit(2)
    isa = ptxas_isa(ptxas)
    print(f"# CUDA kernel resources for sm_{args.arch}, commit {commit()}, Warp {wp.config.version}, {ptxas} "
          f"(PTX ISA {isa})")
    rows, by_module = [], {}
    modules = [importlib.import_module(f"warp_kernels.{name}") for name in args.modules]
    with tempfile.TemporaryDirectory(prefix="cfx_ptx_") as workdir:
        compiled = modules_resources(modules, args.arch, ptxas, isa, workdir)
        for name, module in zip(args.modules, modules, strict=True):
            found, note = compiled[module.__name__]
            by_module[name] = found
            if note:
                print(f"# {name}: {note}")
            for k in sorted(found, key=lambda k: k.kernel):
                blocks, limit = blocks_per_sm(k)
                rows.append([name, k.kernel, k.registers, k.cap or "-", k.stack, k.spill_stores, k.spill_loads,
                             k.shared, k.tiles, k.block, f"{blocks} ({limit})"])
    print(table(HEADER, rows))
    if args.frame_layouts is not None:
        print()
        print(frame_layouts_table(args.frame_layouts or FRAME_LAYOUTS, args.arch, ptxas, isa))
    if args.arch == 90 and BASELINE.exists():
        worse = spill_regressions(by_module, json.loads(BASELINE.read_text()))
        print("# spills against the recorded baseline: " + ("; ".join(worse) if worse else "none above it"))
    if args.record:
        record = baseline_record(by_module, wp.config.version, isa)
        kernels = ",\n".join(f"  {json.dumps(k)}: {json.dumps(v)}" for k, v in record.pop("kernels").items())
        head = json.dumps(record)[1:-1]
        BASELINE.write_text(f"{{{head},\n \"kernels\": {{\n{kernels}\n }}}}\n")  # a line per kernel, for diffs
        print(f"# recorded {BASELINE}")


if __name__ == "__main__":
    main()
