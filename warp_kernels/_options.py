"""Module options shared by every kernel module of warp_kernels."""

# no gradients are taken through these kernels: skipping the backward passes halves compile time;
# the lean launch path (no grid-stride loop) lowers per-thread overhead; -O3 on the CPU too (Warp's
# CPU default is -O2, CUDA's -O3): it unrolls the short fixed loops of shape matching, which halves
# that kernel's time on the CPU, and compiles in the same time
MODULE_OPTIONS = {"enable_backward": False, "default_grid_stride": False, "optimization_level": 3}
