"""Hair solver throughput: strands of 32 vertices on the procedural head, one 1/24 s frame.

Prints one table: case, strands, vertices, device, ms/frame, vertex-updates/s, and the peer (a
vectorised float64 NumPy implementation of the same substep without collisions, measured in the
same run on the same strands) with our speed-up over it.

    python benchmarks/hair.py                       # 1k, 10k, 100k strands on cpu (and cuda if present)
    python benchmarks/hair.py --strands 1000 --device cuda
"""

import argparse
import subprocess
import time

import numpy as np
import warp as wp

from sim.collider import Collider
from sim.hair_solver import HairParams, HairSolver
from sim.scene import quiet_warp
from sim.hairstyle import HairstyleParams, grow_hairstyle, sample_scalp
from sim.head import HeadAnimation, procedural_head
from sim.strands import StrandBuilder

VERTICES = 32
FPS = 24.0


def build(strands, device):
    head = procedural_head()
    collider = Collider("head", head.vertices, head.faces, head.skin_indices, head.skin_weights,
                        head.num_bones, device)
    collider.set_poses(HeadAnimation().bone_matrices([0.0]))
    collider.apply_pose(0)
    roots, _, _, normals = sample_scalp(head.vertices, head.faces, head.scalp_faces, strands, seed=1)
    pts, counts, widths = grow_hairstyle(HairstyleParams(style="straight", vertices=VERTICES, length=0.25),
                                         roots, normals, collider.push_out)
    model = StrandBuilder().add_strands(pts, counts, widths).finalize(device).bind_to_mesh(
        collider.posed_points(), head.faces)
    return model, collider


def time_ours(model, collider, params, min_seconds=1.0):
    """ms per frame: substeps per frame x the measured cost of one substep (pose + step)."""
    solver = HairSolver(model, params)
    s0, s1 = model.state(), model.state()
    dt = 1.0 / (FPS * params.substeps)
    collider.set_poses(HeadAnimation().bone_matrices(dt * np.arange(1, params.substeps + 1)))

    def substep(k):
        collider.apply_pose(k % params.substeps)
        solver.step(s0, s1, collider, dt)

    substep(0)  # compile and warm caches
    wp.synchronize_device(model.device)
    n, start = 0, time.perf_counter()
    while True:
        substep(n)
        n += 1
        wp.synchronize_device(model.device)
        elapsed = time.perf_counter() - start
        if elapsed > min_seconds or n >= 4 * params.substeps:
            break
    return 1e3 * elapsed / n * params.substeps


def numpy_substep(x, v, rest_len, offsets, pinned, params, dt):
    """float64 NumPy peer on (S, N, 3) arrays: integrate, simplified shape matching, FTL, DFTL."""
    g = np.asarray(params.gravity)
    v = v + dt * (g - params.air_drag * v)
    v *= max(0.0, 1.0 - params.damping * dt)
    p = x + dt * v
    p[:, :pinned] = x[:, :pinned]
    a, b, c = p[:, :-2], p[:, 1:-1], p[:, 2:]
    centroid = (a + b + c) / 3.0
    u = c - a
    u /= np.maximum(np.linalg.norm(u, axis=2, keepdims=True), 1e-12)
    goal = np.zeros_like(p)
    count = np.zeros(p.shape[:2] + (1,))
    for k in range(3):
        goal[:, k:k + p.shape[1] - 2] += centroid + offsets[:, :, k:k + 1] * u
        count[:, k:k + p.shape[1] - 2] += 1.0
    free = slice(pinned, None)
    p[:, free] += params.shape_stiffness * (goal[:, free] / count[:, free] - p[:, free])
    before = p.copy()
    for i in range(pinned, p.shape[1]):
        d = p[:, i] - p[:, i - 1]
        p[:, i] = p[:, i - 1] + d * (rest_len[:, i:i + 1] / np.linalg.norm(d, axis=1, keepdims=True))
    corr = p - before
    v_new = (p - x) / dt
    v_new[:, pinned:-1] -= params.ftl_damping * corr[:, pinned + 1:] / dt
    return p, v_new


def time_numpy(model, params, min_seconds=1.0):
    s, n = model.num_strands, VERTICES
    x = model.rest_positions_np.reshape(s, n, 3).astype(np.float64)
    v = np.zeros_like(x)
    rest_len = model.rest_length_np.reshape(s, n).astype(np.float64)
    win = model.shape_windows(3)
    offsets = win.offsets_np.reshape(s, n - 2, 3).astype(np.float64)
    dt = 1.0 / (FPS * params.substeps)
    k, start = 0, time.perf_counter()
    while True:
        x, v = numpy_substep(x, v, rest_len, offsets, model.pinned_per_strand, params, dt)
        k += 1
        elapsed = time.perf_counter() - start
        if elapsed > min_seconds or k >= 4 * params.substeps:
            break
    return 1e3 * elapsed / k * params.substeps


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--strands", type=int, nargs="*", default=[1000, 10000, 100000])
    parser.add_argument("--device", nargs="*", default=None)
    parser.add_argument("--substeps", type=int, default=10)
    parser.add_argument("--no-peer", action="store_true")
    args = parser.parse_args()
    quiet_warp()
    wp.init()
    devices = args.device or (["cpu"] + (["cuda"] if wp.is_cuda_available() else []))
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    cases = [
        ("full+mesh", HairParams(substeps=args.substeps)),
        ("simplified+mesh", HairParams(substeps=args.substeps, shape_matching="simplified")),
        ("simplified+spheres", HairParams(substeps=args.substeps, shape_matching="simplified",
                                          collision="sphere_tree")),
        ("simplified, no collision", HairParams(substeps=args.substeps, shape_matching="simplified",
                                                collision="none")),
    ]
    print(f"# hair benchmark, commit {commit}, {VERTICES} vertices/strand, {args.substeps} substeps per 1/24 s frame")
    print("| case | strands | vertices | device | ms/frame | vertex-updates/s | NumPy f64 peer ms/frame | speed-up |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for strands in args.strands:
        peer = None
        for device in devices:
            model, collider = build(strands, device)
            if peer is None and not args.no_peer:
                peer = time_numpy(model, HairParams(substeps=args.substeps, shape_matching="simplified"))
            for name, params in cases:
                ms = time_ours(model, collider, params)
                rate = model.num_particles * params.substeps / (ms * 1e-3)
                same_work = name.startswith("simplified, no collision")
                peer_txt = f"{peer:.1f}" if peer is not None else "-"
                ratio = f"{peer / ms:.1f}x" if peer is not None and same_work else "-"
                print(f"| {name} | {strands} | {model.num_particles} | {device} | {ms:.2f} | {rate:.3g} | "
                      f"{peer_txt} | {ratio} |", flush=True)


if __name__ == "__main__":
    main()
