"""Hair cards: one textured strip mesh along each strand (the "strip" hair model of games).

A card is a ribbon `width` metres wide centred on its strand. Each strand vertex becomes two card
vertices, left (u = 0) and right (u = 1), offset along the strand's *across* direction, which is
perpendicular both to the strand's tangent and to the direction to the head centre: the card lies
flat over the head, and its outward face (the face winding's normal) points away from the head.
v runs from 0 at the root to 1 at the tip, so a texture with the hair drawn down its length maps
the same way onto every card.

Vertex layout: strand s, vertex i -> card vertices 2 (s V + i) (left) and 2 (s V + i) + 1 (right);
strand s has V - 1 quads. Points are recomputed every frame from the strands; topology and UVs
are static.
"""

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class HairCards:
    """Static topology of the cards of `num_strands` strands of `vertices` vertices each."""

    num_strands: int
    vertices: int  # per strand
    faces: np.ndarray  # (num_strands * (vertices - 1), 4) quads, outward winding
    uvs: np.ndarray  # (2 * num_strands * vertices, 2): u across 0..1, v root (0) to tip (1)

    @classmethod
    def build(cls, num_strands, vertices):
        if vertices < 2:
            raise ValueError(f"hair cards need at least 2 vertices per strand, got {vertices}")
        s = np.arange(num_strands)[:, None]
        i = np.arange(vertices - 1)[None, :]
        left = 2 * (s * vertices + i)
        # left_i, left_i+1, right_i+1, right_i: normal = tangent x across, away from the head
        faces = np.stack([left, left + 2, left + 3, left + 1], -1).reshape(-1, 4)
        v = np.repeat(np.linspace(0.0, 1.0, vertices), 2)
        u = np.tile([0.0, 1.0], vertices)
        uvs = np.tile(np.stack([u, v], 1), (num_strands, 1))
        return cls(num_strands, vertices, faces.astype(np.int32), uvs.astype(np.float32))

    @property
    def num_points(self):
        return 2 * self.num_strands * self.vertices

    def points(self, strands, head_centre, width):
        """Card vertices (2 S V, 3) for strands (S, V, 3) around `head_centre` (3,), `width` metres wide."""
        strands = np.asarray(strands, np.float64)
        if strands.shape[:2] != (self.num_strands, self.vertices):
            raise ValueError(f"expected strands of shape ({self.num_strands}, {self.vertices}, 3), "
                             f"got {strands.shape}")
        across = card_across(strands, head_centre)
        half = 0.5 * float(width) * across
        return np.stack([strands - half, strands + half], 2).reshape(-1, 3)


def card_across(strands, head_centre):
    """Unit across directions (S, V, 3): perpendicular to each vertex's tangent and to the direction
    from the vertex to the head centre.

    Where a strand points straight at (or away from) the centre that cross product vanishes; there
    the strand's mean across direction takes over smoothly, so a card does not flip along a strand
    that leaves the scalp radially and then falls."""
    strands = np.asarray(strands, np.float64)
    tangent = _unit(np.gradient(strands, axis=1))
    inward = _unit(np.asarray(head_centre, np.float64) - strands)
    across = np.cross(tangent, inward)  # |across| = sin(angle between strand and head direction)
    mean = _unit(across.sum(axis=1, keepdims=True))
    weight = np.clip(0.25 - np.linalg.norm(across, axis=-1, keepdims=True), 0.0, None)
    across = across + weight * mean
    across -= tangent * np.sum(across * tangent, axis=-1, keepdims=True)
    length = np.linalg.norm(across, axis=-1, keepdims=True)
    # a strand lying wholly along the head direction: any direction across the tangent will do
    axis = np.eye(3)[np.argmin(np.abs(tangent), axis=-1)]
    fallback = np.cross(tangent, axis)
    across = np.where(length > 1e-9, across, fallback)
    return _unit(across)


def _unit(v):
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, 1e-300)
