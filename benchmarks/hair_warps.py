"""What the order of the strands costs the hair's length pass on a GPU, modelled from CPU counts.

follow_the_leader runs a thread per strand; a GPU steps 32 of them together (a warp), each particle
step as long as the slowest of the 32, and a tree walk there costs some twenty times the listed-leaf
tests. This script steps the benchmark's scene (benchmarks/hair.py, simplified1+spheres, lane order,
leaves ahead: a GPU's configuration) on the CPU with a copy of follow_the_leader that also counts
each particle step's work: 1 for the step, 4 more where it tests its four listed leaves, 85 more
where it walks the sphere tree (about the nodes a walk near the head visits). Then for each strand
order, with warps of 32 consecutive lanes:

- warp work: the sum over warps of each particle step's largest count, per substep. A launch with
  more warps than the GPU holds at once (100k strands on an H100) takes about this.
- slowest warp: the largest one warp's work, per substep. A launch that fits at once (1k, 10k
  strands) takes about this.

With --loose each count is made twice, the second time with walks where the loose pass walks
(HairSolver.loose_lists: only where a particle may be inside a leaf its list does not hold), the
rows marked "loose".

    python benchmarks/hair_warps.py --strands 1000 10000 [--loose]
"""

import argparse
import importlib.util
import inspect
import re
import sys
import tempfile
import textwrap
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import commit, table  # noqa: E402

STEP, LISTED, WALK = 1.0, 4.0, 85.0


def edited(src, edits):
    """src with each (pattern, replacement) of edits applied (re.sub, every match); each pattern must
    match at least once."""
    for pattern, replacement in edits:
        src, count = re.subn(pattern, replacement, src)
        if count == 0:
            raise RuntimeError("follow_the_leader changed: update benchmarks/hair_warps.py's counting edits")
    return src


def counting_follow_the_leader(loose=False):
    """follow_the_leader with one more argument, a float array per lane slot that each particle step
    adds its work to; compiled from the source of the kernel and of its per-particle function
    (follow_leader), so the counting copies cannot drift apart from them. loose: a walk counted only
    where the list's bound at the particle is at or below zero, as the loose pass walks
    (HairSolver.loose_lists, collision.collide_point_listed_loose), not below the margin."""
    from warp_kernels import strands

    def source(function, name):
        src = textwrap.dedent(inspect.getsource(function.func))  # defined inside strands' variant factories
        return src[src.index(f"def {name}("):].replace(f"def {name}(", f"def {name}_counted(")

    kernel = source(strands.follow_the_leader, "follow_the_leader")
    func = source(strands.follow_leader, "follow_leader")
    # each edit keeps the indentation of the line it extends (both of the kernel's loops are counted: the
    # copy is compiled reading in turn, as FOLLOW_THE_LEADER[PATHS_ALL])
    kernel_edits = [
        (r"    order: LaneOrder,\n    first: int,\n\):",
         "    order: LaneOrder,\n    first: int,\n    work: wp.array(dtype=float),\n):"),
        (r"\n( +)correction = wp\.vec3\(0\.0\)\n", rf"\n\1correction = wp.vec3(0.0)\n\1work[i] += {STEP}\n"),
        (r"p = follow\(", "p = follow_leader_counted("),
        (r"(NO_BOUND|held_beyond)\)\n( +)x\[i\] = p", r"\1, work)\n\2x[i] = p"),
    ]
    func_edits = [
        (r"    held_beyond: float,\n\):",
         "    held_beyond: float,\n    work: wp.array(dtype=float),\n):"),
        (r"\n( +)elif listed:\n( +)if wp\.static\(loose\):\n",
         "\n\\1elif listed:\n"
         "\\2if unlisted - wp.length(p - origin) > " + ("0.0" if loose else "contact.margin + 1.0e-5") + ":\n"
         f"\\2    work[i] += {LISTED}\n"
         "\\2else:\n"
         f"\\2    work[i] += {WALK}\n"
         "\\2if wp.static(loose):\n"),
    ]
    kernel, func = edited(kernel, kernel_edits), edited(func, func_edits)
    header = ("import warp as wp\nfrom warp_kernels._options import MODULE_OPTIONS\nwp.set_module_options(MODULE_OPTIONS)\n"
              "from warp_kernels.strands import *  # noqa\nfrom warp_kernels.strands import NO_BOUND, bound_lowering\n"
              "paths = PATHS_ALL  # the variant with every collision path, reading each particle in its turn\n"
              "ahead = False\n"
              "loose = False  # the walks are counted as either pass makes them; the copy computes the exact one\n"
              "from warp_kernels.collision import *  # noqa\n\n")
    path = Path(tempfile.mkdtemp(prefix="cfx_warps_")) / "counted_ftl.py"
    path.write_text(header + "@wp.func(inline=True)\n" + func + "\n\n@wp.kernel\n" + kernel)
    spec = importlib.util.spec_from_file_location("counted_ftl", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.follow_the_leader_counted


def count_work(strands, frames, counted):
    """(substeps, particles along a strand, strands) work of each particle step, by strand."""
    import hair
    from sim.hair_solver import HairParams, HairSolver
    from warp_kernels import strands as kernels

    scene = hair.build_scene(strands, "cpu", 10)
    settled = hair.settle(scene)
    scene.solver = HairSolver(scene.model, HairParams(substeps=10, **hair.CASES["simplified1+spheres"]), parts=1)
    scene.solver.leaves_ahead = True
    scene.solver.lanes = True
    scene.solver.fused = False  # the launches apart: the counting copy is follow_the_leader's
    scene.graphs.enabled = False
    scene.state.x.assign(settled[0])
    scene.state.v.assign(settled[1])
    lane = scene.solver._lanes
    work = wp.zeros(lane.strands * lane.longest, dtype=float)
    records, launch = [], wp.launch

    def spy(kernel, dim, inputs=(), *args, **kwargs):
        if kernel not in kernels.FOLLOW_THE_LEADER.values():  # any variant: the copy has every path
            return launch(kernel, dim, inputs, *args, **kwargs)
        work.zero_()
        launch(counted, dim, [*inputs, work], *args, **kwargs)
        records.append(work.numpy().reshape(lane.longest, lane.strands).copy())

    wp.launch = spy
    try:
        for _ in range(frames):
            scene.advance(1.0 / hair.FPS)
    finally:
        wp.launch = launch
    return np.stack(records)[:, :, lane.order.lane_of.numpy()], scene.model


def warp_costs(work, strand_of):
    """(warp work, slowest warp) per substep with lane l holding strand strand_of[l]."""
    w = work[:, :, strand_of]
    full = (w.shape[2] // 32) * 32
    per_warp = w[:, :, :full].reshape(w.shape[0], w.shape[1], -1, 32).max(axis=3).sum(axis=1)
    return float(per_warp.sum(axis=1).mean()), float(per_warp.max(axis=1).mean())


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--strands", type=int, nargs="*", default=[1000, 10000])
    parser.add_argument("--frames", type=int, default=2, help="1/24 s frames of 10 substeps counted")
    parser.add_argument("--loose", action="store_true", help="also count the walks as the loose pass makes them")
    args = parser.parse_args()
    from sim.hair_solver import lanes_by_root
    from sim.scene import quiet_warp

    quiet_warp()
    wp.init()
    passes = [("", counting_follow_the_leader())]
    if args.loose:
        passes.append((" loose", counting_follow_the_leader(loose=True)))
    print(f"# the length pass's warps modelled from CPU counts, commit {commit()}: step {STEP:g}, "
          f"listed leaves +{LISTED:g}, tree walk +{WALK:g}")
    header = ["strands", "lanes", "warp work/substep", "vs grown", "slowest warp/substep", "vs grown",
              "steps querying", "steps walking"]
    rows = []
    for strands in args.strands:
        for mark, counted in passes:
            work, model = count_work(strands, args.frames, counted)
            steps = work[work > 0]
            queried = np.mean(steps >= STEP + LISTED) * 100.0
            walked = np.mean(steps >= STEP + WALK) * 100.0
            grown = warp_costs(work, np.arange(model.num_strands))
            for name, order in (("grown", np.arange(model.num_strands)), ("by root", lanes_by_root(model))):
                total, slowest = warp_costs(work, order)
                rows.append([strands, name + mark, f"{total:.0f}", f"{total / grown[0]:.2f}x", f"{slowest:.0f}",
                             f"{slowest / grown[1]:.2f}x", f"{queried:.1f}%", f"{walked:.2f}%"])
                print("| " + " | ".join(str(c) for c in rows[-1]) + " |", flush=True)
    print()
    print(table(header, rows))


if __name__ == "__main__":
    main()
