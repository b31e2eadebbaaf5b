"""Cloth throughput: our RK4 solver raced against Newton's VBD and XPBD on the same meshes, and the
coarse-plus-detail pipeline against simulating every vertex.

Table 1, the race. The same garment mesh, particle masses, gravity and pins for every engine; the
body is static (Newton collides particles with a static mesh shape; ours uses the same mesh as its
collider). Cases: the paper's one-piece dress (322 particles, pinned at the shoulders) on the
built-in body, and square 1 m cloths of 1,024 to 1,048,576 particles pinned at two corners,
falling over a 0.3 m ball (an icosphere of 10k vertices), with the spring dashpots scaled by the
particle mass so every grid has the dress's damping rate. One frame is 1/60 s: Newton takes 10
substeps x 10 iterations (the reference setup); ours takes the substeps its RK4 stability bound asks
for. Every engine runs the same number of frames from rest; the quality columns are measured at the
end: max edge stretch (largest |edge / rest - 1| over the mesh's edges) and the deepest penetration
of a particle into the body (mm, 0 = none). On a GPU every engine steps a frame as one CUDA graph.

Table 2, the detail surface (the paper's §4): the dress on the walking body simulated coarse and a
PN-triangle detail surface with wrinkles and lift out of the body evaluated each frame, at 1/30 s
frames; the paper's garment (322 coarse / 10,912 detail vertices at level 6), two ways to a 1M-vertex
surface: the same coarse dress at level 60 (3,600 detail triangles per coarse one, 1.07M vertices)
and a dress of about 28k coarse particles at level 6 (1M vertices), each compared with Newton VBD
simulating 1M particles directly (Table 1's last row, same run).

    python benchmarks/cloth.py                                  # everything, cpu (and cuda if present)
    python benchmarks/cloth.py --device cuda --grids 1024 16384 --no-detail
"""

import argparse
import sys
from dataclasses import replace

import numpy as np
import trimesh
import warp as wp

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from common import (CLOTH_DETAIL_HEADER, CLOTH_RACE_HEADER, commit, copy_bandwidth,
                    counting_launch_bytes, device_name, fmt, kernel_profile, table, time_frames)  # noqa: E402

from sim.cloth import STRETCH, ClothModel, ClothParams, ClothSolver  # noqa: E402
from sim.collider import Collider  # noqa: E402
from sim.graphs import FrameGraphs  # noqa: E402
from sim.scene import Scene, demo_scene, quiet_warp  # noqa: E402

RACE_DT = 1.0 / 60.0
DRESS_MEAN_MASS = 3.9e-4  # kg, the paper's dress on the built-in body (332 particles, 0.13 kg)
PROFILE = False  # --profile
DRESS_PARAMS = {}  # --dress-params: ClothParams fields of the race dress
DETAIL_FPS = 30.0
# the values a row switch (--sweep, --block) times: the default (None), on, off, or both
SWITCH_VALUES = {"auto": (None,), "on": (True,), "off": (False,), "both": (True, False)}


def static_collider(name, vertices, faces, device):
    skin_w = np.zeros((len(vertices), 4))
    skin_w[:, 0] = 1.0
    body = Collider(name, vertices, faces, np.zeros((len(vertices), 4), np.int32), skin_w, 1, device, sphere_leaves=0)
    body.set_poses(np.eye(4)[None, None])
    body.apply_pose(0)
    body.reset_motion()
    return body


def grid_case(particles, device):
    """A 1 m square cloth of about `particles` particles 0.15 m above a 0.3 m ball, pinned at two corners."""
    n = max(3, int(round(np.sqrt(particles))))
    u = np.linspace(-0.5, 0.5, n)
    X, Z = np.meshgrid(u, u, indexing="ij")
    pts = np.stack([X.ravel(), np.full(n * n, 0.45), Z.ravel()], 1)
    idx = np.arange(n * n).reshape(n, n)
    quads = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)
    tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    edges = np.concatenate([np.stack([idx[:-1].ravel(), idx[1:].ravel()], 1),
                            np.stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()], 1)])
    shear = np.concatenate([quads[:, [0, 2]], quads[:, [1, 3]]])
    bend = np.concatenate([np.stack([idx[:-2].ravel(), idx[2:].ravel()], 1),
                           np.stack([idx[:, :-2].ravel(), idx[:, 2:].ravel()], 1)])
    # dashpots per spring damp a fine mesh's light particles ever faster (the stability bound then
    # shrinks as 1/h^2), so they are scaled with the particle mass to keep the dress's damping rate
    params = ClothParams()
    mean_mass = params.density * 1.0 / (n * n)
    params = replace(params, spring_damping=params.spring_damping * mean_mass / DRESS_MEAN_MASS)
    model = ClothModel(pts, tris, edges, shear, bend, [idx[0, 0], idx[0, -1]], params, device, name=f"grid{n}x{n}")
    ball = trimesh.creation.icosphere(subdivisions=5, radius=0.3)
    ball = static_collider("ball", ball.vertices, ball.faces, device)
    return model, ball, ball


def dress_case(device, particles=322, proxy=0.0):
    """(model, collider, body): the paper's dress on the built-in body; the collider is the body, or
    with proxy > 0 its collision proxy of that spacing [m] (cloth.solver.body_proxy). Penetration is
    always measured against the body itself."""
    from sim.body import procedural_body
    from sim.garment import fit_dress

    body = procedural_body()
    garment = fit_dress(body, particles=particles)
    model = ClothModel.from_garment(garment, ClothParams(**DRESS_PARAMS), device)
    truth = static_collider("body", body.vertices, body.faces, device)
    collider = truth
    if proxy > 0.0:
        collider = truth.proxy(proxy)
        collider.set_poses(np.eye(4)[None, None])
        collider.apply_pose(0)
        collider.reset_motion()
    model.bind_to_mesh(collider.posed_points(), collider.faces_np)  # the pins ride the collider's triangles
    return model, collider, truth


def quality(x, model, body):
    """(max edge stretch, deepest penetration into the body in mm)."""
    x = np.asarray(x, np.float64)
    e = model.spring_pairs_np[model.spring_kind_np == STRETCH]
    rest = model.spring_rest_np[model.spring_kind_np == STRETCH]
    stretch = float(np.abs(np.linalg.norm(x[e[:, 0]] - x[e[:, 1]], axis=1) / rest - 1.0).max())
    depth = float(max(0.0, -body.signed_distance(x, max_dist=0.05).min())) * 1e3
    return stretch, depth


def run_ours(model, body, frames, block=None):
    """(ms/frame, substeps/frame, bytes/frame, final positions, BVH queries or gatherings per timed
    frame): RK4 frames of RACE_DT, graph-launched; block: ClothSolver.block_step (None: the default)."""
    solver = ClothSolver(model)
    if block is not None:
        solver.block_step = block
    states = [model.state(), model.state()]
    substeps = model.substeps_for(RACE_DT)
    dt = RACE_DT / substeps
    graphs = FrameGraphs(model.device)

    def frame():
        for _ in range(substeps):
            solver.step(states[0], states[1], body, dt)
            states.reverse()

    def refs():
        return (lambda: tuple(states)), (lambda value: states.__setitem__(slice(None), value))

    def step():
        graphs.run(("cloth", id(states[0])), frame, refs())

    with counting_launch_bytes() as moved:
        step()
    before = solver.fallback_count()  # counted on the device across replays, never zeroed here
    ms = time_frames(step, model.device, frames=frames, min_seconds=0.0, max_frames=frames)
    queries = (solver.fallback_count() - before) / (frames + 2)  # time_frames warms up with 2
    if PROFILE:
        graphs.enabled = False
        print("\n".join(kernel_profile(step, model.device)), flush=True)
    return ms, substeps, moved[0], states[0].x.numpy(), queries


def run_newton(model, body, solver, frames):
    import newton_peers

    peer = newton_peers.NewtonCloth(model.rest_positions_np, model.triangles_np, model.mass_np, model.pinned_np,
                                    solver=solver, device=model.device, frame_dt=RACE_DT, substeps=10, iterations=10,
                                    body=(body.rest_points_np, body.faces_np))
    ms = time_frames(peer.step_frame, model.device, frames=frames, min_seconds=0.0, max_frames=frames)
    return ms, peer.positions()


def race(devices, grids, frames, peers, ceilings, blocks=(None,)):
    header = CLOTH_RACE_HEADER
    print(table(header, []), flush=True)  # the streamed rows below stay readable if the run is cut short
    rows, newton_1m = [], {}
    for device in devices:
        cases = [("dress (paper)", lambda: dress_case(device)),
                 ("dress (paper), 2.5 cm proxy", lambda: dress_case(device, proxy=0.025))]
        cases += [(f"grid {p}", lambda p=p: grid_case(p, device)) for p in grids]
        for name, build in cases:
            model, body, truth = build()
            n = model.num_particles
            f = frames if n < 200_000 else max(3, frames // 6)
            for block in blocks:
                ms, substeps, moved, x, queries = run_ours(model, body, f, block)
                stretch, depth = quality(x, model, truth)
                gbs = moved / (ms * 1e-3) / 1e9
                engine = "ours RK4" + ({True: " block", False: " launches"}[block] if len(blocks) > 1 else "")
                rows.append([name, n, device, engine, f"{substeps} x 1", fmt(ms, 4),
                             fmt(n * substeps / (ms * 1e-3)), f"{gbs:.0f} ({100 * gbs / ceilings[device]:.0f}%)",
                             fmt(stretch, 2), fmt(depth, 2), "1.0x"])
                print("| " + " | ".join(str(c) for c in rows[-1]) + " |", flush=True)
                if body is not None:
                    print(f"# {name}, {engine}: {queries:.1f} BVH queries or gatherings per frame after the first",
                          flush=True)
            for solver in peers:
                peer_ms, px = run_newton(model, body, solver, f)
                stretch, depth = quality(px, model, truth)
                rows.append([name, n, device, f"Newton {solver.upper()}", "10 x 10", fmt(peer_ms, 4),
                             fmt(n * 10 / (peer_ms * 1e-3)), "-", fmt(stretch, 2), fmt(depth, 2),
                             f"{peer_ms / ms:.2f}x"])
                print("| " + " | ".join(str(c) for c in rows[-1]) + " |", flush=True)
                if n >= 1_000_000 and solver == "vbd":
                    newton_1m[device] = peer_ms
    return header, rows, newton_1m


def param_setting(text):
    """'body_candidates=0': a ClothParams field and its value, typed as the field's default."""
    key, _, value = text.partition("=")
    defaults = ClothParams()
    if not hasattr(defaults, key) or not value:
        raise argparse.ArgumentTypeError(f"{text!r}: expected FIELD=VALUE with a ClothParams field")
    kind = type(getattr(defaults, key))
    return key, (value.lower() in ("1", "true", "yes") if kind is bool else kind(value))


def detail_spec(text):
    """'322' or '322:60': coarse particles, and the tessellation level (default the paper's 6)."""
    particles, _, level = text.partition(":")
    return int(particles), int(level or 6)


def detail_scene(device, particles, level=6):
    # a finer dress gets the paper dress's damping rate, as the grids do (the dashpots scale with
    # the particle mass, so the stiffness sets the step and not the dashpots)
    damping = ClothParams().spring_damping * min(1.0, 332.0 / particles)
    config = demo_scene({"scene": {"device": device, "fps": DETAIL_FPS, "frames": 1, "preroll": 0.0,
                                   "stats": False},
                         "hair": {"enabled": False}, "face": {"enabled": False},
                         "cloth": {"particles": particles}, "cloth.solver": {"spring_damping": damping},
                         "cloth.detail": {"level": level}})
    return Scene(config)


def detail(devices, sizes, frames, newton_1m, ceilings, sweeps=(None,), blocks=(None,)):
    """The walking body's rows; sweeps: Scene.cloth_sweep values to time (None: the device's default),
    the rows marked "swept" or "refitted" when there are several; blocks likewise for
    ClothSolver.block_step, marked "block" or "launches"."""
    header = CLOTH_DETAIL_HEADER
    print(table(header, []), flush=True)
    rows = []
    for device, (particles, level), sweep, block in ((d, z, w, b) for d in devices for z in sizes for w in sweeps
                                                     for b in blocks):
        scene = detail_scene(device, particles, level)
        if sweep is not None:
            scene.cloth_sweep = sweep
        if block is not None:
            scene.cloth_solver.block_step = block
        label = f"dress on the walking body, level {level}" + (
            (" swept" if sweep else " refitted") if len(sweeps) > 1 else "") + (
            (" block" if block else " launches") if len(blocks) > 1 else "")

        def frame():
            scene.advance(1.0 / DETAIL_FPS)
            scene.update_detail()

        with counting_launch_bytes() as moved:
            frame()
        ms = time_frames(frame, device, frames=frames)
        ms_detail = time_frames(scene.update_detail, device, frames=frames)
        if PROFILE:
            scene.graphs.enabled = False
            print("\n".join(kernel_profile(frame, device)), flush=True)
        verts = scene.cloth_detail.surface.topology.num_vertices
        stretch = scene.cloth_stats()["cloth_stretch_max"]
        depth = scene.cloth_body.signed_distance(scene.cloth_detail.positions.numpy(), max_dist=0.05)
        inside = f"{100.0 * np.mean(depth < -0.002):.3f}%"
        gbs = moved[0] / (ms * 1e-3) / 1e9
        peer = newton_1m.get(device) if verts >= 900_000 else None
        rows.append([label, scene.cloth_model.num_particles, verts, device,
                     scene.cloth_substeps, fmt(ms, 4), fmt(ms_detail, 3),
                     f"{gbs:.0f} ({100 * gbs / ceilings[device]:.0f}%)", fmt(1e3 / ms, 4), fmt(stretch, 2), inside,
                     fmt(peer, 4),
                     f"{peer / ms:.1f}x" if peer else "-"])
        print("| " + " | ".join(str(c) for c in rows[-1]) + " |", flush=True)
    return header, rows


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--grids", type=int, nargs="*", default=[1024, 16384, 262144, 1048576])
    parser.add_argument("--device", nargs="*", default=None)
    parser.add_argument("--frames", type=int, default=30, help="frames per engine (fewer above 200k particles)")
    parser.add_argument("--peers", nargs="*", default=["vbd", "xpbd"], choices=["vbd", "xpbd"])
    parser.add_argument("--detail-sizes", type=detail_spec, nargs="*", default=[(322, 6), (322, 60), (28000, 6)],
                        help="coarse particles[:tessellation level] (default level 6, the paper's)")
    parser.add_argument("--dress-params", type=param_setting, nargs="*", default=[], metavar="FIELD=VALUE",
                        help="ClothParams of the race dress, e.g. body_candidates=0 reseed_drift=0 (ablations)")
    parser.add_argument("--sweep", choices=["auto", "on", "off", "both"], default="auto",
                        help="Scene.cloth_sweep for the walking body's rows (the body's triangle boxes bounded over "
                             "the frame, or refitted each substep): the device's default, on, off, or both")
    parser.add_argument("--block", choices=["auto", "on", "off", "both"], default="auto",
                        help="ClothSolver.block_step (a step as one launch of one thread block, or as its "
                             "launches): the default (on for a small cloth on a GPU), on, off, or both")
    parser.add_argument("--no-race", action="store_true")
    parser.add_argument("--no-detail", action="store_true")
    parser.add_argument("--profile", action="store_true", help="print per-kernel device time of one frame (CUDA)")
    args = parser.parse_args()
    global PROFILE
    PROFILE = args.profile
    DRESS_PARAMS.update(args.dress_params)
    quiet_warp()
    wp.init()
    import newton_peers

    peers = args.peers if newton_peers.available() else []
    devices = args.device or (["cpu"] + (["cuda"] if wp.is_cuda_available() else []))
    ceilings = {}
    print(f"# cloth benchmark, commit {commit()}, peer: {'Newton ' + newton_peers.version() if peers else 'none'}"
          + (f", race dress with {DRESS_PARAMS}" if DRESS_PARAMS else ""))
    for device in devices:
        ceilings[device] = copy_bandwidth(device, 1024 if wp.get_device(device).is_cuda else 128)
        print(f"# {device}: {device_name(device)}, copy bandwidth {ceilings[device]:.0f} GB/s (read + write)",
              flush=True)
    newton_1m, out = {}, []
    blocks = SWITCH_VALUES[args.block]
    if not args.no_race:
        header, rows, newton_1m = race(devices, args.grids, args.frames, peers, ceilings, blocks)
        out.append(table(header, rows))
    if not args.no_detail:
        sweeps = SWITCH_VALUES[args.sweep]
        header, rows = detail(devices, args.detail_sizes, 10, newton_1m, ceilings, sweeps, blocks)
        out.append(table(header, rows))
    print()
    print("\n\n".join(out))


if __name__ == "__main__":
    main()
