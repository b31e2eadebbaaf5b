"""Shared parts of the benchmarks: frame timing, the bytes a frame moves, the device's copy bandwidth.

Bytes are counted the same way for every solver: one eager frame is run with wp.launch watched, and
every array handed to a launch counts its full size once (each input read once, each output
written once). BVH and sphere-tree traversals are not counted, so collision-heavy cases move more
than this figure says. Achieved bandwidth = counted bytes / measured time, compared with a large
device-to-device copy measured in the same run (bytes read + bytes written).
"""

import contextlib
import os
import platform
import subprocess
import time

import numpy as np
import warp as wp

# Degrees between the scalp and a strand's first segment in the benchmarks' grooms: straight out along
# the normal, as grooms were grown before HairstyleParams.root_lift (session 40; within 1.4 mm of them,
# the clearance now reached over the first fine step), so that their figures and the A/B runs against
# older commits time the same strands. The default groom's shallower lift lays more hair along the
# scalp, within reach of the head's collision (BENCHMARKS.md, session 40).
ROOT_LIFT = 90.0

# the tables benchmarks/hair.py and benchmarks/cloth.py print (benchmarks/plot.py reads them back)
HAIR_HEADER = ["case", "strands", "vertices", "device", "ms/frame", "vertex-updates/s", "MB/frame", "GB/s",
               "max stretch", "Newton chains ms/frame", "Newton max stretch", "speed-up"]
CLOTH_RACE_HEADER = ["case", "particles", "device", "engine", "substeps x iterations", "ms/frame", "particle-steps/s",
                     "GB/s", "max edge stretch", "penetration mm", "speed-up vs ours"]
CLOTH_DETAIL_HEADER = ["garment", "coarse particles", "detail vertices", "device", "substeps/frame", "ms/frame",
                       "of which detail ms", "GB/s", "frames/s", "coarse max edge stretch",
                       "detail vertices >2 mm inside", "Newton VBD 1M particles ms/frame (table 1)", "speed-up"]


def commit():
    """The short commit the benchmark runs; CFX_COMMIT overrides it where the checkout's .git is not this tree's
    (the device tool sends the working tree with a stale .git)."""
    if os.environ.get("CFX_COMMIT"):
        return os.environ["CFX_COMMIT"]
    out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    return out.stdout.strip() or "unknown"


def device_name(device):
    d = wp.get_device(device)
    return d.name if d.is_cuda else f"cpu ({platform.processor() or platform.machine()})"


def launch_arrays(values):
    """The distinct arrays among launch arguments, those inside @wp.struct arguments included."""
    found = {}

    def visit(value):
        if isinstance(value, wp.array):
            found.setdefault(id(value), value)
        elif hasattr(value, "_cls") and hasattr(value._cls, "vars"):  # a @wp.struct instance
            for name in value._cls.vars:
                visit(getattr(value, name))

    for value in values:
        visit(value)
    return list(found.values())


@contextlib.contextmanager
def counting_launch_bytes():
    """Count the bytes of every array passed to wp.launch or wp.launch_tiled inside the block, once per
    launch however often it is passed (inside structs too): yields a one-element list. A launch whose
    passes read an array several times (ClothSolver.block_step's whole step) counts it once, so its
    figure is a floor, below that of the launches it replaces."""
    total = [0]
    launch, launch_tiled = wp.launch, wp.launch_tiled

    def count(inputs, outputs):
        for a in launch_arrays(list(inputs or ()) + list(outputs or ())):
            total[0] += a.capacity

    def counted(kernel, dim, inputs=(), outputs=(), *args, **kwargs):
        count(inputs, outputs)
        return launch(kernel, dim, inputs, outputs, *args, **kwargs)

    def counted_tiled(*args, **kwargs):
        count(kwargs.get("inputs"), kwargs.get("outputs"))
        return launch_tiled(*args, **kwargs)

    copy = wp.copy

    def counted_copy(dest, src, dest_offset=0, src_offset=0, count=0):
        n = count if count else src.size
        total[0] += 2 * n * wp.types.type_size_in_bytes(src.dtype)
        return copy(dest, src, dest_offset, src_offset, count)

    wp.launch, wp.launch_tiled, wp.copy = counted, counted_tiled, counted_copy
    try:
        yield total
    finally:
        wp.launch, wp.launch_tiled, wp.copy = launch, launch_tiled, copy


def time_frames(step, device, frames=10, min_seconds=0.5, max_frames=200):
    """Median-free mean ms per frame of `step()` after two warm-up frames (the first loads modules and
    fills caches, the second captures a graph where the step uses one); at least `frames` frames and
    at least `min_seconds` unless that exceeds `max_frames`."""
    for _ in range(2):
        step()
    wp.synchronize_device(device)
    done, start = 0, time.perf_counter()
    while done < frames or (time.perf_counter() - start < min_seconds and done < max_frames):
        step()
        done += 1
        if done % 8 == 0:
            wp.synchronize_device(device)
    wp.synchronize_device(device)
    return 1e3 * (time.perf_counter() - start) / done


def time_each_frame(step, device, frames=10, min_seconds=0.5, max_frames=200):
    """ms of each frame of `step()` after the two warm-up frames of time_frames, the device synchronised
    after every frame, as an application that shows each frame must: at least `frames` frames and at
    least `min_seconds` unless that exceeds `max_frames`. Frames slower than the rest show here, where
    a mean hides them."""
    for _ in range(2):
        step()
    wp.synchronize_device(device)
    times, start = [], time.perf_counter()
    while len(times) < frames or (time.perf_counter() - start < min_seconds and len(times) < max_frames):
        begin = time.perf_counter()
        step()
        wp.synchronize_device(device)
        times.append(1e3 * (time.perf_counter() - begin))
    return times


def copy_bandwidth(device, megabytes=1024, repeats=10):
    """GB/s of a large device-to-device copy, counting bytes read plus bytes written."""
    n = megabytes * (1 << 20) // 16
    a = wp.array(np.random.default_rng(0).random((n, 4), dtype=np.float32), dtype=wp.vec4, device=device)
    b = wp.empty_like(a)
    wp.copy(b, a)
    wp.synchronize_device(device)
    start = time.perf_counter()
    for _ in range(repeats):
        wp.copy(b, a)
    wp.synchronize_device(device)
    return 2.0 * a.capacity * repeats / (time.perf_counter() - start) / 1e9


def table(header, rows):
    """Markdown table text."""
    lines = ["| " + " | ".join(header) + " |", "| " + " | ".join("---" for _ in header) + " |"]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def fmt(value, digits=3):
    if value is None:
        return "-"
    if isinstance(value, str):
        return value
    return f"{value:.{digits}g}" if abs(value) < 1e4 else f"{value:.3e}"


def kernel_profile(step, device, top=10):
    """Per-kernel device time of one eager call of step() on a CUDA device: text lines, largest first."""
    if not wp.get_device(device).is_cuda:
        return []
    step()  # warm
    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL | wp.TIMING_MEMCPY | wp.TIMING_MEMSET)
    step()
    results = wp.timing_end()
    totals = {}
    for r in results:
        name = r.name.split("_", 1)[-1] if r.name.startswith("forward_") else r.name
        t, n = totals.get(name, (0.0, 0))
        totals[name] = (t + r.elapsed, n + 1)
    whole = sum(t for t, _ in totals.values())
    lines = [f"#   device busy {whole:.3f} ms in {sum(n for _, n in totals.values())} operations"]
    for name, (t, n) in sorted(totals.items(), key=lambda kv: -kv[1][0])[:top]:
        lines.append(f"#   {t:8.3f} ms {100 * t / max(whole, 1e-12):5.1f}%  x{n:<5d} {name}")
    return lines
