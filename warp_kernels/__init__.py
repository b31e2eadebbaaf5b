"""Pure Warp kernels of Warp CFX: arrays in, arrays out, no state and no I/O.

This package is what a host application embeds; it imports nothing from `sim` or `io_usd`.
Every kernel runs on "cpu" and "cuda".
"""

from . import body_motion, cloth, collision, detail, skinning, strands

__all__ = ["body_motion", "cloth", "collision", "detail", "load", "skinning", "strands"]

# the longest to compile first (on a CPU: strands ~5 s, cloth and collision ~2 s each, detail 1.4 s), the
# kernels only some runs launch kept apart (_options.deferred_module)
_MODULES = (strands, cloth, collision, detail, body_motion, skinning)


def load(device="cpu", threads=None, modules=_MODULES, deferred=None):
    """Compile every kernel module (of `modules`) for `device`, or read it from Warp's kernel cache,
    side by side.

    Warp compiles a module the first time one of its kernels launches, one module after another;
    here Warp's own loader (wp.force_load) runs their compilers in `threads` threads at once
    (default: one per core), longest first, so a first run on a cold kernel cache waits about as long
    as the longest module takes. With a warm cache it takes milliseconds. A host application calls
    it once at start-up.

    deferred: also the Warp modules of kernels only some runs launch (_options.deferred_module: a
    GPU's hair substep in launches apart, the sphere tree's and no collider's fused variants, a small
    cloth's step in one block), those of `modules`; or a list of those a run will launch
    (sim.hair_solver.deferred_step_modules). All of them but the opt-in ones (the hair's frame in one
    block, HairSolver.frame_in_block) by default on a CUDA device, where its
    compiler is quick and a module must not load during a graph capture; none on a CPU, which compiles
    each at its first launch, if any, so a run that never launches them does not wait for them.
    """
    import os

    import warp as wp

    from ._options import DEFERRED, OPT_IN

    if deferred is None:
        deferred = wp.get_device(device).is_cuda
    names = [m.__name__ for m in modules]
    if deferred is True:
        names += [d for d in DEFERRED if any(d.startswith(n + ".") for n in names) and d not in OPT_IN]
    elif deferred:
        unknown = sorted(set(deferred) - set(DEFERRED))
        if unknown:
            raise ValueError(f"not deferred kernel modules: {unknown}")
        names += list(deferred)
    workers = max(1, min(len(names), threads or os.cpu_count() or 1))
    wp.force_load(device=device, modules=[wp.get_module(n) for n in names], max_workers=workers)
