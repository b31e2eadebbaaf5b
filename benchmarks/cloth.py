"""Cloth solver and detail-surface throughput.

Table 1, the coarse simulation: a square cloth falling onto a ball, explicit RK4 with body collision:
particles, device, substeps per frame (from the stability bound), ms/frame, particle-steps/s, and
the paper's figure (Oshita & Makinouchi, Table 1: 20.4 ms per frame for the 322-particle dress on a
Pentium 4 2.5 GHz, 16.0 ms integration + 4.6 ms collision).

Table 2, the detail surface per frame: the built-in dress on the built-in body at level 6 (the
paper's garment: 597 coarse triangles, 10,912 detail vertices, 51.6 ms surface on the Pentium 4) and a
1M-vertex surface; PN evaluation alone and the whole pipeline (wrinkles, lift out of the body, normals).

    python benchmarks/cloth.py                         # 322, 10k, 100k, 1M particles on cpu (and cuda)
    python benchmarks/cloth.py --particles 322 --device cuda
"""

import argparse
import subprocess
import time

import numpy as np
import trimesh
import warp as wp

from sim.cloth import ClothModel, ClothParams, ClothSolver
from sim.collider import Collider
from sim.scene import quiet_warp

FPS = 30.0
PAPER_MS = {322: 20.4}


def build(particles, device):
    n = max(3, int(round(np.sqrt(particles))))
    size = 1.2
    u = np.linspace(-size / 2, size / 2, n)
    X, Z = np.meshgrid(u, u, indexing="ij")
    pts = np.stack([X.ravel(), np.full(n * n, 0.32), Z.ravel()], 1)
    idx = np.arange(n * n).reshape(n, n)
    quads = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)
    tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    edges = np.concatenate([np.stack([idx[:-1].ravel(), idx[1:].ravel()], 1),
                            np.stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()], 1)])
    shear = np.concatenate([quads[:, [0, 2]], quads[:, [1, 3]]])
    bend = np.concatenate([np.stack([idx[:-2].ravel(), idx[2:].ravel()], 1),
                           np.stack([idx[:, :-2].ravel(), idx[:, 2:].ravel()], 1)])
    # the default material at every resolution: finer cloths get lighter particles, so the stability
    # bound (and the substep count) grows with resolution as it does for any explicit integrator
    params = ClothParams(substeps=0)
    model = ClothModel(pts, tris, edges, shear, bend, [], params, device)
    ball = trimesh.creation.icosphere(subdivisions=5, radius=0.3)
    skin_w = np.zeros((len(ball.vertices), 4))
    skin_w[:, 0] = 1.0
    body = Collider("ball", ball.vertices, ball.faces, np.zeros((len(ball.vertices), 4), np.int32), skin_w, 1,
                    device, sphere_leaves=0)
    body.set_poses(np.eye(4)[None, None])
    body.apply_pose(0)
    body.reset_motion()
    return model, body


def time_substeps(model, body, min_seconds=1.0):
    """ms per substep (body posing included) and the substeps a 1/FPS frame needs; big cloths need
    hundreds of substeps per frame, so the frame time is the measured substep time times that count."""
    solver = ClothSolver(model)
    s0, s1 = model.state(), model.state()
    substeps = model.substeps_for(1.0 / FPS)
    dt = 1.0 / (FPS * substeps)

    def substep():
        nonlocal s0, s1
        body.apply_pose(0)
        solver.step(s0, s1, body, dt)
        s0, s1 = s1, s0

    for _ in range(3):  # compile, warm caches, first contacts
        substep()
    wp.synchronize_device(model.device)
    start, done = time.perf_counter(), 0
    while done < 3 or (time.perf_counter() - start < min_seconds and done < substeps):
        substep()
        done += 1
        wp.synchronize_device(model.device)
    return 1e3 * (time.perf_counter() - start) / done, substeps


def time_detail(device, frames=10):
    """The dress on the walking body, a few steps in, then the detail update timed."""
    from sim.body import BodyAnimation, procedural_body
    from sim.detail import ClothDetail, DetailParams
    from sim.garment import fit_dress

    body = procedural_body()
    collider = Collider("body", body.vertices, body.faces, body.skin_indices, body.skin_weights, body.num_bones,
                        device, sphere_leaves=0)
    collider.set_poses(BodyAnimation.preset("walk").bone_matrices([0.0]))
    collider.apply_pose(0)
    model = ClothModel.from_garment(fit_dress(body), ClothParams(), device)
    model.bind_to_mesh(body.vertices, body.faces)
    solver = ClothSolver(model)
    s0, s1 = model.state(), model.state()
    for _ in range(200):
        solver.step(s0, s1, collider, model.stable_dt)
        s0, s1 = s1, s0
    detail = ClothDetail(model, DetailParams(), device)
    return _time_detail_runs(detail, model, (("PN evaluation", lambda: detail.surface.update(s0.x)),
                                             ("detail pipeline", lambda: detail.update(model, s0, collider, 1 / 30))),
                             device, frames)


def time_detail_million(device, frames=3):
    """PN evaluation and the pipeline without a body (no lift) on a 1M-vertex surface."""
    from sim.detail import ClothDetail, DetailParams

    model, _ = build(28_000, device)  # 167 x 167 grid: 55.8k coarse triangles -> 1.0M detail vertices at level 6
    detail = ClothDetail(model, DetailParams(), device)
    state = model.state()
    return _time_detail_runs(detail, model, (("PN evaluation", lambda: detail.surface.update(state.x)),
                                             ("detail pipeline (no body)",
                                              lambda: detail.update(model, state, None, 1 / 30))), device, frames)


def _time_detail_runs(detail, model, runs, device, frames):
    """(label, coarse triangles, detail vertices, ms per call) for each (label, callable), warmed up once."""
    rows = []
    for label, run in runs:
        run()
        wp.synchronize_device(device)
        start = time.perf_counter()
        for _ in range(frames):
            run()
        wp.synchronize_device(device)
        rows.append((label, len(model.triangles_np), detail.surface.topology.num_vertices,
                     1e3 * (time.perf_counter() - start) / frames))
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--particles", type=int, nargs="*", default=[322, 10_000, 100_000, 1_000_000])
    parser.add_argument("--device", nargs="*", default=None)
    parser.add_argument("--detail-only", action="store_true", help="only the detail-surface table")
    args = parser.parse_args()
    quiet_warp()
    wp.init()
    devices = args.device or (["cpu"] + (["cuda"] if wp.is_cuda_available() else []))
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    print(f"# cloth benchmark, commit {commit}, {FPS:g} fps, square cloth on a 10k-vertex ball")
    print("| particles | springs | device | substeps/frame | ms/substep | ms/frame | particle-steps/s | "
          "paper (P4 2.5 GHz) ms/frame |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for target in ([] if args.detail_only else args.particles):
        for device in devices:
            model, body = build(target, device)
            ms_sub, substeps = time_substeps(model, body)
            rate = model.num_particles / (ms_sub * 1e-3)
            paper = PAPER_MS.get(target, "-")
            print(f"| {model.num_particles} | {len(model.spring_pairs_np)} | {device} | {substeps} | {ms_sub:.3f} | "
                  f"{ms_sub * substeps:.1f} | {rate:.3g} | {paper} |", flush=True)
    print()
    print("| detail surface | coarse triangles | detail vertices | device | ms/frame | paper (P4 2.5 GHz) ms/frame |")
    print("| --- | --- | --- | --- | --- | --- |")
    for device in devices:
        for label, tris, verts, ms in time_detail(device) + time_detail_million(device):
            paper = "51.6 (10,912 vertices)" if verts < 20_000 and label == "detail pipeline" else "-"
            print(f"| {label} | {tris} | {verts} | {device} | {ms:.2f} | {paper} |", flush=True)


if __name__ == "__main__":
    main()
