"""Drive the engine from NumPy arrays, as a DCC plug-in would: no scene file, no USD.

A sphere "head" in a Z-up host turns and drifts for one second; 200 strands grow from its top and a
small cape hangs from its side. Each frame the host hands over the head's new vertex positions and
reads back hair and cloth in its own axes.

    python examples/embed_numpy.py
"""

import numpy as np
import trimesh

from sim.embed import Simulation

FPS, FRAMES = 24, 24
CENTRE = np.array([0.0, 0.0, 1.6])  # Z up, metres


def head_at(frame, rest):
    angle = np.radians(40.0) * np.sin(2.0 * np.pi * frame / FRAMES)
    c, s = np.cos(angle), np.sin(angle)
    turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return rest @ turn.T + CENTRE + [0.02 * frame / FRAMES, 0.0, 0.0]


def main():
    sphere = trimesh.creation.icosphere(3, radius=0.1)
    rest, triangles = np.asarray(sphere.vertices), np.asarray(sphere.faces)

    rng = np.random.default_rng(7)
    tops = rest[rest[:, 2] > 0.05]
    roots = tops[rng.choice(len(tops), 200)]
    normals = roots / np.linalg.norm(roots, axis=1, keepdims=True)
    steps = np.linspace(0.0, 0.15, 16)[None, :, None]
    hair = (roots[:, None] + normals[:, None] * steps).reshape(-1, 3) + CENTRE

    u, w = np.meshgrid(np.linspace(-0.05, 0.05, 6), np.linspace(0.0, -0.12, 7))
    cape = np.stack([u.ravel(), np.full(u.size, -0.1), w.ravel()], 1) + CENTRE
    quads = np.array([[r * 6 + k, r * 6 + k + 1, (r + 1) * 6 + k + 1, (r + 1) * 6 + k] for r in range(6) for k in range(5)])

    sim = Simulation(head_at(0, rest), triangles, fps=FPS, up_axis="Z",
                     hair_points=hair, hair_counts=np.full(200, 16),
                     garment_vertices=cape, garment_face_counts=np.full(len(quads), 4),
                     garment_face_indices=quads.ravel(), garment_pinned=np.arange(6),
                     settings={"scene": {"preroll": 0.5}, "cloth": {"detail": {"level": 0}}})
    rest_lengths = np.linalg.norm(np.diff(hair.reshape(200, 16, 3), axis=1), axis=2)
    for frame in range(1, FRAMES + 1):
        sim.step(head_at(frame, rest))
        strands = sim.hair_points().reshape(200, 16, 3)
        stretch = np.abs(np.linalg.norm(np.diff(strands, axis=1), axis=2) / rest_lengths - 1.0).max()
        tips = strands[:, -1, 2].mean()
        print(f"frame {frame:2d}: hair tips at z = {tips:.3f} m, worst stretch {100 * stretch:.3f}%, "
              f"cape hem at z = {sim.cloth_points()[-6:, 2].mean():.3f} m")


if __name__ == "__main__":
    main()
