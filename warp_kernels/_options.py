"""Module options shared by every kernel module of warp_kernels, and the modules compiled apart."""

import warp as wp

# no gradients are taken through these kernels: skipping the backward passes halves compile time;
# the lean launch path (no grid-stride loop) lowers per-thread overhead; -O3 on the CPU too (Warp's
# CPU default is -O2, CUDA's -O3): it unrolls the short fixed loops of shape matching, which halves
# that kernel's time on the CPU, and compiles in the same time
MODULE_OPTIONS = {"enable_backward": False, "default_grid_stride": False, "optimization_level": 3}

# names of the Warp modules made by deferred_module, in the order they were made
DEFERRED = []
# those of them that warp_kernels.load takes only where named (opt_in)
OPT_IN = []


def deferred_module(name, block_dim=None, opt_in=False, listed=True):
    """The name of a Warp module of its own, with MODULE_OPTIONS, for kernels only some runs launch
    (a GPU's way of stepping, a variant for one collision path): pass it as @wp.kernel(module=...).
    block_dim: the lanes of a block its kernels are launched with, where not Warp's default (256).
    CUDA code is generated for one block size (a BVH query keeps its traversal stack in shared memory,
    128 bytes per lane), so a module launched with other blocks must be compiled, and checked ahead by
    benchmarks/cuda_resources.py, at that size.

    Warp compiles a module whole, at the first launch of any of its kernels. A kernel kept in the
    module of the ones every run launches costs every run its compile time on a cold kernel cache;
    kept apart, it costs only the runs that launch it (the hair's module on two CPU cores: 13.4 s
    with its GPU ways and variants, 5.4 s without). warp_kernels.load compiles these modules too
    where asked (on CUDA devices by default); with opt_in only where named, for kernels that a run
    launches only when asked to (their first frame runs eager, outside a graph capture, and loads them).
    listed=False leaves a module made at run time for a timing (a frame layout of strands.frame_variant)
    out of both lists: its first launch compiles it, and the resources recorded for sm_90 do not hold it.
    """
    wp.set_module_options(MODULE_OPTIONS if block_dim is None else {**MODULE_OPTIONS, "block_dim": block_dim},
                          module=name)
    if not listed:
        return name
    if name not in DEFERRED:
        DEFERRED.append(name)
    if opt_in and name not in OPT_IN:
        OPT_IN.append(name)
    return name
