"""Where a Warp kernel spends its time on the CPU, by Python source line: a sampling profile of one
kernel (by default the hair's fused substep, `strands.step_strands`) while a case runs.

Warp compiles a module's kernels into an object it loads into memory of its own, so a profiler sees
their samples at addresses without names or lines. This script compiles the module's generated C++
again with g++ -O3 -g into an object with line tables, puts it in the kernel cache in place of
Warp's for one run (Warp's is put back afterwards), records that run with `perf record -e cpu-clock`,
and maps each sample inside the object to its inlined call chain with `addr2line`, then to the
Python line the generated C++ quotes above it. The table gives each line's and each `@wp.func`'s
share of the kernel object's samples. g++ inlines and copies differently from Warp's own compiler:
read the shares as where to look, and confirm a change with benchmarks/turns.py (a function's `def`
line, for one, collects its arguments' copies, which Warp's build does not pay). Needs g++, perf
and addr2line.

    python benchmarks/cpu_profile.py --hair full+mesh
    python benchmarks/cpu_profile.py --realtime simplified1+spheres "proxy 2.5 cm" --module warp_kernels.cloth \\
        --kernel body_collide
"""

import argparse
import collections
import ctypes
import importlib
import os
import re
import shutil
import subprocess
import sys
import tempfile

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import turns  # noqa: E402  (the cases: a hair case, a scene file, or the real-time case)

GENERATED = re.compile(r"^(\w+?)_\d+$|^(\w+)_[0-9a-f]{8}_cpu_kernel_forward")  # Warp's names for funcs and kernels


def kernel_module(args):
    """The kernel and its loaded module's exec (after the case has run a frame)."""
    kernel = getattr(importlib.import_module(args.module), args.kernel)
    execs = [e for key, e in kernel.module.execs.items() if key[0] is None]  # None: the CPU
    if not execs:
        raise SystemExit(f"{args.module}.{args.kernel} did not run on the CPU in this case")
    return kernel, execs[0]


def worker(args):
    """Build the case and print the module's object path (info), or print the kernel's entry
    address and time frames (run, under perf)."""
    step, synchronize = turns.build(args)
    step()
    synchronize()
    kernel, module_exec = kernel_module(args)
    if args.worker == "info":
        print(f"OBJECT {module_exec.binary_path}", flush=True)
        return
    forward = module_exec.get_kernel_hooks(kernel).forward
    print(f"FORWARD {ctypes.cast(forward, ctypes.c_void_p).value}", flush=True)
    for _ in range(args.frames):
        step()
    synchronize()


def run_worker(mode, args, perf_data=None):
    command = [sys.executable, os.path.abspath(__file__), "--worker", mode, *passed_on(args)]
    if perf_data:
        command = ["perf", "record", "-q", "-F", str(args.rate), "-e", "cpu-clock", "-o", perf_data, "--"] + command
    out = subprocess.run(command, capture_output=True, text=True)
    found = {line.split()[0]: line.split()[1] for line in out.stdout.splitlines()
             if line.startswith(("OBJECT", "FORWARD"))}
    if not found:
        raise SystemExit(f"the case did not run:\n{out.stdout[-2000:]}\n{out.stderr[-2000:]}")
    return found


def passed_on(args):
    case = (["--scene", args.scene] if args.scene else ["--realtime", *args.realtime] if args.realtime
            else ["--hair", args.hair, "--strands", str(args.strands)])
    return case + ["--frames", str(args.frames), "--warmup", str(args.warmup), "--substeps", str(args.substeps),
                   "--module", args.module, "--kernel", args.kernel]


def python_lines(cpp_path):
    """For each line of Warp's generated C++, the (file, line) of the Python it was generated from:
    each function opens with a `// file.py:line` comment and each statement is quoted with `<L n>`."""
    where, source, out = "?", 0, {}
    with open(cpp_path) as cpp:
        for number, line in enumerate(cpp, start=1):
            header = re.match(r"^// (/\S+\.py):(\d+)\s*$", line)
            if header:
                where, source = os.path.basename(header.group(1)), int(header.group(2))
            quoted = re.search(r"<L (\d+)>\s*$", line)
            if quoted:
                source = int(quoted.group(1))
            out[number] = (where, source)
    return out


def attribute(addr2line_output, counts):
    """From `addr2line -a -i -f` output (an address line, then function and file:line pairs from the
    innermost inlined frame out): samples per innermost generated function and per generated C++
    line of it, for the given sample counts per address."""
    functions, lines = collections.Counter(), collections.Counter()
    address, frames = None, []

    def flush():
        named = [(name, where) for name, where in frames if GENERATED.match(name.split("(")[0].split()[-1])]
        if address is None or not named:
            return
        name, where = named[0]
        match = GENERATED.match(name.split("(")[0].split()[-1])
        functions[match.group(1) or match.group(2)] += counts[address]
        if where.rsplit(":", 1)[-1].split()[0].isdigit():
            lines[int(where.rsplit(":", 1)[-1].split()[0])] += counts[address]

    rows = addr2line_output.splitlines()
    i = 0
    while i < len(rows):
        if rows[i].startswith("0x"):
            flush()
            address, frames = int(rows[i], 16), []
            i += 1
        else:
            frames.append((rows[i], rows[i + 1].rsplit("/", 1)[-1] if i + 1 < len(rows) else "?"))
            i += 2
    flush()
    return functions, lines


def main():
    parser = turns.case_arguments(argparse.ArgumentParser(description=__doc__,
                                                          formatter_class=argparse.RawDescriptionHelpFormatter))
    parser.add_argument("--module", default="warp_kernels.strands", help="the kernel's module")
    parser.add_argument("--kernel", default="step_strands", help="the kernel profiled")
    parser.add_argument("--rate", type=int, default=2000, help="samples per second")
    parser.add_argument("--top", type=int, default=25, help="rows per table")
    parser.add_argument("--worker", choices=["info", "run"], help=argparse.SUPPRESS)
    parser.set_defaults(frames=15)
    args = parser.parse_args()
    if args.worker:
        worker(args)
        return
    for tool in ("g++", "perf", "addr2line", "nm"):
        if shutil.which(tool) is None:
            raise SystemExit(f"cpu_profile: needs {tool}")
    import warp

    obj = run_worker("info", args)["OBJECT"]
    cpp = re.sub(r"\.cpu[^.]*\.o$", ".cpp", obj)
    work = tempfile.mkdtemp(prefix="cpu_profile_")
    debug, saved, data = (os.path.join(work, name) for name in ("debug.o", "warp.o", "perf.data"))
    native = os.path.join(os.path.dirname(warp.__file__), "native")
    print(f"# compiling {os.path.basename(cpp)} with line tables", flush=True)
    subprocess.run(["g++", "-O3", "-g", "-std=c++17", "-fPIC", "-fno-exceptions", "-DNDEBUG", "-I", native, "-c", cpp,
                    "-o", debug], check=True)
    shutil.copy(obj, saved)
    try:
        shutil.copy(debug, obj)
        forward = int(run_worker("run", args, data)["FORWARD"])
    finally:
        shutil.copy(saved, obj)
    symbols = subprocess.run(["nm", debug], capture_output=True, text=True, check=True).stdout
    entry = [line.split()[0] for line in symbols.splitlines()
             if re.search(rf" T {args.kernel}_[0-9a-f]+_cpu_forward$", line)]
    base = forward - int(entry[0], 16)
    text = subprocess.run(["size", "-A", debug], capture_output=True, text=True, check=True).stdout
    size = int(re.search(r"^\.text\s+(\d+)", text, re.M).group(1))
    ips = subprocess.run(["perf", "script", "-i", data, "-F", "ip"], capture_output=True, text=True).stdout.split()
    counts = collections.Counter(int(ip, 16) - base for ip in ips if 0 <= int(ip, 16) - base < size)
    inside = sum(counts.values())
    if not inside:
        raise SystemExit("no samples fell inside the kernel's object")
    located = subprocess.run(["addr2line", "-a", "-i", "-f", "-C", "-e", debug, *map(hex, sorted(counts))],
                             capture_output=True, text=True, check=True).stdout
    functions, lines = attribute(located, counts)
    sources = python_lines(cpp)
    by_source = collections.Counter()
    for line, c in lines.items():
        by_source[sources.get(line, ("?", 0))] += c
    print(f"# {args.module}.{args.kernel}: {inside} of {len(ips)} samples inside its module's object")
    print("\n| share | innermost @wp.func or kernel |\n| --- | --- |")
    for name, c in functions.most_common(args.top):
        print(f"| {c / inside:.1%} | {name} |")
    print("\n| share | Python line |\n| --- | --- |")
    for (where, source), c in by_source.most_common(args.top):
        print(f"| {c / inside:.1%} | {where}:{source} |")
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
