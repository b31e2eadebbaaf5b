"""Pure Warp kernels of Warp CFX: arrays in, arrays out, no state and no I/O.

This package is what a host application embeds; it imports nothing from `sim` or `io_usd`.
Every kernel runs on "cpu" and "cuda".
"""

from . import body_motion, cloth, collision, detail, skinning, strands

__all__ = ["body_motion", "cloth", "collision", "detail", "load", "skinning", "strands"]

# the longest to compile first (on a CPU: strands ~14 s, collision, cloth and detail ~3 s each)
_MODULES = (strands, collision, cloth, detail, body_motion, skinning)


def load(device="cpu", threads=None, modules=_MODULES):
    """Compile every kernel module (of `modules`) for `device`, or read it from Warp's kernel cache,
    side by side.

    Warp compiles a module the first time one of its kernels launches, one module after another;
    here Warp's own loader (wp.force_load) runs their compilers in `threads` threads at once
    (default: one per core), longest first, so a first run on a cold kernel cache waits about as long
    as the longest module takes. With a warm cache it takes milliseconds. A host application calls
    it once at start-up.
    """
    import os

    import warp as wp

    workers = max(1, min(len(modules), threads or os.cpu_count() or 1))
    wp.force_load(device=device, modules=[wp.get_module(m.__name__) for m in modules], max_workers=workers)
