"""Face rig and lip-sync throughput.

Table 1, the face on the moving head per frame: the built-in face at each grid resolution, all 26
shapes weighted, posed on the turning bust by warp_kernels.skinning.blend_shape_bound_points. The
peer is the same blend in NumPy float64 (dense einsum over the shapes, then the per-triangle frame
change), measured in the same run on the same data.

Table 2, lip sync: seconds of 16 kHz audio analysed (LPC cepstrum, net, gate, smoothing) per second.

    python benchmarks/face.py [--device cuda]
"""

import argparse
import time

import numpy as np
import warp as wp

from sim.collider import Collider
from sim.face import EMOTIONS, FaceRig, builtin_face
from sim.head import HeadAnimation, procedural_head
from sim.mouth import VOWEL_SHAPES
from sim.scene import quiet_warp


def _timed(fn, min_seconds=0.5, device="cpu"):
    fn()
    wp.synchronize_device(device)
    start, n = time.perf_counter(), 0
    while n < 5 or time.perf_counter() - start < min_seconds:
        fn()
        n += 1
    wp.synchronize_device(device)
    return 1e3 * (time.perf_counter() - start) / n


def _frames(points, faces):
    a, b, c = (points[faces[:, k]] for k in range(3))
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t = (b - a) / np.linalg.norm(b - a, axis=1, keepdims=True)
    return np.stack([t, np.cross(n, t), n], -1)  # columns t, s, n


def face_rows(device):
    head = procedural_head()
    collider = Collider("head", head.vertices, head.faces, head.skin_indices, head.skin_weights, 2, device,
                        sphere_leaves=0)
    rows = []
    for resolution in (1, 2, 3, 4):
        rig = FaceRig(builtin_face(resolution=resolution), device)
        rig.attach(collider)
        collider.set_poses(HeadAnimation().bone_matrices([0.8]))
        collider.apply_pose(0)
        w = rig.weights(EMOTIONS["happiness"], VOWEL_SHAPES[0])
        ms = _timed(lambda: rig.posed_points(collider, w), device=device)

        # NumPy float64 peer: rest + sum w * offsets, turned by each bound triangle's frame change
        rest_mesh, tri, bary, local = (a.numpy().astype(np.float64) if a.dtype != wp.int32 else a.numpy()
                                       for a in rig._binding)
        faces = head.faces
        posed = collider.points.numpy().astype(np.float64)
        offsets = rig.offsets

        def peer():
            d = np.einsum("s,svk->vk", w, offsets)
            F0, F1 = _frames(rest_mesh, faces[tri]), _frames(posed, faces[tri])
            base = np.einsum("nk,nkj->nj", bary, posed[faces[tri]])
            return base + np.einsum("nij,nj->ni", F1, local + np.einsum("nji,nj->ni", F0, d))

        peer_ms = _timed(peer)
        np.testing.assert_allclose(rig.posed_points(collider, w).numpy(), peer(), atol=1e-5)
        rows.append((resolution, rig.mesh.num_vertices, rig.num_shapes, device, ms,
                     rig.mesh.num_vertices / (ms * 1e-3), peer_ms, peer_ms / ms))
    return rows


def lipsync_row():
    from sim import lipsync

    samples = lipsync.load_audio(lipsync.DEMO_LINE_PATH)
    seconds = len(samples) / lipsync.SAMPLE_RATE
    ms = _timed(lambda: lipsync.mouth_track(samples, 24.0))
    return seconds, ms, seconds / (ms * 1e-3)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    quiet_warp()
    print("| resolution | vertices | shapes | device | ms/frame | vertices/s | NumPy f64 peer ms/frame | speed-up |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in face_rows(args.device):
        print(f"| {r[0]} | {r[1]} | {r[2]} | {r[3]} | {r[4]:.3f} | {r[5]:.3g} | {r[6]:.3f} | {r[7]:.1f}x |")
    seconds, ms, rate = lipsync_row()
    print()
    print("| audio | ms to analyse | audio seconds per second |")
    print("| --- | --- | --- |")
    print(f"| demo line, {seconds:.2f} s | {ms:.1f} | {rate:.0f} |")


if __name__ == "__main__":
    main()
