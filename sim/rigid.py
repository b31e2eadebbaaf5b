"""Best-fit rigid motion between point sets (Kabsch), for whatever moves as one piece: the head a
face rides, the scalp a capture's strands grow from."""

import numpy as np


def rigid_fit(rest, posed):
    """4x4 rigid transforms (column vectors) minimising |T rest - posed|: rest (P, 3), posed (P, 3)
    gives one (4, 4); posed (F, P, 3) gives (F, 4, 4), one per frame."""
    rest = np.asarray(rest, np.float64)
    posed = np.asarray(posed, np.float64)
    single = posed.ndim == 2
    frames = posed[None] if single else posed
    c0, c = rest.mean(0), frames.mean(1)
    H = np.einsum("pi,fpj->fij", rest - c0, frames - c[:, None])
    U, _, Vt = np.linalg.svd(H)
    V, Ut = Vt.transpose(0, 2, 1), U.transpose(0, 2, 1)
    D = np.tile(np.eye(3), (len(frames), 1, 1))
    D[:, 2, 2] = np.sign(np.linalg.det(V @ Ut))  # a rotation, never a reflection
    R = V @ D @ Ut
    T = np.tile(np.eye(4), (len(frames), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = c - np.einsum("fij,j->fi", R, c0)
    return T[0] if single else T
