"""Pure Warp kernels of Warp CFX: arrays in, arrays out, no state and no I/O.

This package is what a host application embeds; it imports nothing from `sim` or `io_usd`.
Every kernel runs on "cpu" and "cuda".
"""

from . import body_motion, cloth, collision, detail, skinning, strands

__all__ = ["body_motion", "cloth", "collision", "detail", "skinning", "strands"]
