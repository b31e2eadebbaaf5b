"""Hair solver throughput, and a race with Newton particle chains on the same strands.

Strands of 32 vertices groomed straight (25 cm) on the built-in head, which turns and nods; one
1/24 s frame in 10 substeps through the product path (sim.Scene.advance: the head re-posed every
substep, each frame one graph launch). Every case starts from the same state, the hair settled on
the still head for 0.5 s, and times the frames after it while the head turns. The peer is Newton 1.8 (XPBD particle chains:
consecutive particles joined by springs, first two pinned, colliding with the head as a static
mesh) on the same strands, same gravity, frame and substeps, measured in the same run.

Columns: ms/frame; vertex-updates/s (particles x substeps per second); MB/frame and GB/s (bytes of
every array the frame's launches are given, see benchmarks/common.py) with the share of the
device's copy bandwidth measured in this run; max stretch (largest |segment / rest - 1| after
the timed frames) for us and for the peer.

The sphere tree's walks for the particles whose leaf lists run short can be made in a parallel pass
before the length pass (HairSolver.leaves_ahead, on by default on a GPU only); --leaves-ahead both
times each case both ways, the rows with it marked "ahead" (the mesh cases only once: they have no
leaves). The length pass can run in lane order (HairSolver.lanes, on by default on a GPU only, where
a warp's strands then read consecutive memory); --lanes both marks the rows with it "lanes". Its
lanes follow the roots (hair_solver.lanes_by_root); --lane-order both also times them in the grown
order, the rows marked "grown". A substep can run as one launch per strand range (HairSolver.fused,
on by default on the CPU, and on a GPU for simplified shape matching from 65k strands with the frame
kept in lane order, HairSolver.frame_lanes; the sphere tree's walks are then queued ahead from the
start positions); --fused both marks the rows with it "fused". --try times each case once more for each
setting of HairSolver attributes given (e.g. --try mesh_lists=on), the rows marked with it: --try
frame_in_block=on steps each frame in one launch, a block of lanes per strand (strands.frame_in_block), with
frame_warps=on 32 strands a block, with frame_layout=SIDExGROUPSxRUN any layout (strands.frame_variant: SIDE
strands a block, GROUPS threads along each, RUN particles a thread).

    python benchmarks/hair.py                        # 1k, 10k, 100k strands on cpu (and cuda if present)
    python benchmarks/hair.py --strands 1000 --device cuda --cases full+mesh
    python benchmarks/hair.py --device cuda --leaves-ahead both --lanes both
    python benchmarks/hair.py --device cuda --lane-order both
    python benchmarks/hair.py --device cuda --fused both
    python benchmarks/hair.py --device cuda --cases full+mesh --try mesh_lists=on
    python benchmarks/hair.py --device cuda --no-peer --cases simplified1+spheres --try frame_in_block=on \
        frame_in_block=on,frame_warps=on frame_in_block=on,frame_layout=16x8x4
"""

import argparse
import sys

import numpy as np
import warp as wp

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from common import (HAIR_HEADER, ROOT_LIFT, commit, copy_bandwidth, counting_launch_bytes, device_name, fmt,
                    kernel_profile, table, time_frames)  # noqa: E402

from sim.hair_solver import HairParams, HairSolver  # noqa: E402
from sim.scene import Scene, hair_demo_scene, quiet_warp  # noqa: E402

VERTICES = 32
FPS = 24.0
CASES = {
    "full+mesh": {},
    "simplified+mesh": {"shape_matching": "simplified"},
    "simplified+spheres": {"shape_matching": "simplified", "collision": "sphere_tree"},
    "simplified1+spheres": {"shape_matching": "simplified", "collision": "sphere_tree", "shape_iterations": 1},
    # no head collision: what the rest of a substep costs (not run unless asked for)
    "simplified1": {"shape_matching": "simplified", "collision": "none", "shape_iterations": 1},
}
DEFAULT_CASES = [name for name in CASES if name != "simplified1"]


def build_scene(strands, device, substeps):
    config = hair_demo_scene({
        "scene": {"device": device, "fps": FPS, "frames": 1, "preroll": 0.0, "stats": False},
        "head": {"animation": "turn_nod"},
        "hair": {"count": strands, "style": "straight", "vertices": VERTICES, "length": 0.25,
                 "root_lift": ROOT_LIFT},
        "solver": {"substeps": substeps, "collision": "sphere_tree"},  # builds the sphere tree too
    })
    return Scene(config)


def max_stretch(x, model):
    seg = np.linalg.norm(np.diff(x.astype(np.float64), axis=0), axis=1)
    child = np.arange(1, model.num_particles)
    keep = model.rest_length_np[child] > 0.0
    return float(np.abs(seg[keep] / model.rest_length_np[child][keep] - 1.0).max())


def settle(scene, seconds=0.5):
    """Let the hair fall onto the still head once; every case then starts from this state, so the
    cases time the same motion instead of each timing its own first fall. Returns (x, v)."""
    scene.advance(seconds, animate=False)
    return scene.state.x.numpy(), scene.state.v.numpy()


def solver_setting(text):
    """'attr=value[,attr=value...]' as {attr: value}: on/off as booleans, numbers as numbers, AxBxC (a frame's
    layout: frame_layout=32x8x4) as a tuple of ints."""
    setting = {}
    for item in text.split(","):
        attr, sep, value = item.partition("=")
        if not sep or attr not in SOLVER_ATTRS:
            raise argparse.ArgumentTypeError(f"{item!r}: expected ATTR=VALUE with ATTR one of {sorted(SOLVER_ATTRS)}")
        words = {"on": True, "off": False, "true": True, "false": False}
        if value.lower() in words:
            setting[attr] = words[value.lower()]
        elif "x" in value:
            try:
                setting[attr] = tuple(int(n) for n in value.split("x"))
            except ValueError:
                raise argparse.ArgumentTypeError(f"{item!r}: expected a layout SIDExGROUPSxRUN") from None
        else:
            try:
                setting[attr] = int(value)
            except ValueError:
                setting[attr] = float(value)
    return setting


# the HairSolver switches a --try may set
SOLVER_ATTRS = {"mesh_lists", "contact_bounds", "leaves_ahead", "fused", "read_ahead", "frame_lanes", "loose_lists",
                "strand_block", "frame_in_block", "frame_warps", "frame_layout"}


def run_ours(scene, params, frames, settled, profile=False, ahead=None, lanes=None, by_root=True, fused=None,
             setting=None):
    """(ms/frame, bytes/frame, max stretch) for one solver variant on a built scene, from `settled`;
    ahead, lanes, fused: HairSolver.leaves_ahead, .lanes and .fused, None for the device's default;
    by_root: lanes that follow the roots (HairSolver.set_lanes); setting: other HairSolver
    attributes to set (solver_setting)."""

    def start(parts):
        scene.solver = HairSolver(scene.model, params, parts=1 if lanes else parts)
        if ahead is not None:
            scene.solver.leaves_ahead = ahead
        if fused is not None:
            scene.solver.fused = fused
        for attr, value in (setting or {}).items():
            setattr(scene.solver, attr, value)
        if lanes is not None or not by_root:
            scene.solver.set_lanes(scene.solver.lanes if lanes is None else lanes, by_root)
        scene.graphs.clear()
        scene.state, scene._scratch = scene.model.state(), scene.model.state()
        scene.state.x.assign(settled[0])
        scene.state.v.assign(settled[1])
        scene.time = 0.0

    # the bytes of one eager frame with all strands in one range (split across the CPU's cores, each
    # launch would count every array it is given once per range)
    start(1)
    with counting_launch_bytes() as moved:
        scene.advance(1.0 / FPS)  # eager: modules load; counts the bytes
    start(None)  # the solver as a scene makes it: one strand range per CPU core, one on a GPU
    device = scene.device
    ms = time_frames(lambda: scene.advance(1.0 / FPS), device, frames=frames)
    if profile:
        enabled, scene.graphs.enabled = scene.graphs.enabled, False
        print("\n".join(kernel_profile(lambda: scene.advance(1.0 / FPS), device)), flush=True)
        scene.graphs.enabled = enabled
    return ms, moved[0], max_stretch(scene.state.x.numpy(), scene.model)


def run_peer(scene, substeps, frames, settled):
    import newton_peers

    m = scene.model
    peer = newton_peers.NewtonChains(settled[0], m.strand_start_np, pinned_per_strand=m.pinned_per_strand,
                                     device=scene.device, frame_dt=1.0 / FPS, substeps=substeps,
                                     head=(scene.head.vertices, scene.head.faces))
    ms = time_frames(peer.step_frame, scene.device, frames=frames)
    return ms, max_stretch(peer.positions(), m)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--strands", type=int, nargs="*", default=[1000, 10000, 100000])
    parser.add_argument("--device", nargs="*", default=None)
    parser.add_argument("--cases", nargs="*", default=DEFAULT_CASES, choices=list(CASES))
    parser.add_argument("--substeps", type=int, default=10)
    parser.add_argument("--frames", type=int, default=10, help="timed frames (at least)")
    parser.add_argument("--no-peer", action="store_true", help="skip Newton")
    parser.add_argument("--profile", action="store_true", help="print per-kernel device time of one frame (CUDA)")
    parser.add_argument("--leaves-ahead", choices=["auto", "on", "off", "both"], default="auto",
                        help="HairSolver.leaves_ahead: the device's default, on, off, or each case both ways")
    parser.add_argument("--lanes", choices=["auto", "on", "off", "both"], default="auto",
                        help="HairSolver.lanes (the length pass in lane order), likewise")
    parser.add_argument("--lane-order", choices=["root", "grown", "both"], default="root",
                        help="the lanes follow the roots (lanes_by_root) or the grown strand order, or both")
    parser.add_argument("--fused", choices=["auto", "on", "off", "both"], default="auto",
                        help="HairSolver.fused (a substep in one launch), likewise")
    parser.add_argument("--try", dest="tries", type=solver_setting, nargs="*", default=[], metavar="ATTR=VALUE,...",
                        help="also time each case with these HairSolver attributes set, one row per setting")
    args = parser.parse_args()
    quiet_warp()
    wp.init()
    import newton_peers

    peer_ok = newton_peers.available() and not args.no_peer
    devices = args.device or (["cpu"] + (["cuda"] if wp.is_cuda_available() else []))
    print(f"# hair benchmark, commit {commit()}, {VERTICES} vertices/strand, {args.substeps} substeps per 1/24 s "
          f"frame, peer: {'Newton ' + newton_peers.version() if peer_ok else 'none'}")
    header = HAIR_HEADER
    print(table(header, []), flush=True)  # the streamed rows below stay readable if the run is cut short
    rows = []
    for device in devices:
        ceiling = copy_bandwidth(device, 1024 if wp.get_device(device).is_cuda else 128)
        print(f"# {device}: {device_name(device)}, copy bandwidth {ceiling:.0f} GB/s (read + write)", flush=True)
        for strands in args.strands:
            scene = build_scene(strands, device, args.substeps)
            settled = settle(scene)
            peer_ms, peer_stretch = run_peer(scene, args.substeps, args.frames, settled) if peer_ok else (None, None)
            ways = {"auto": [None], "on": [True], "off": [False], "both": [False, True]}
            orders = {"root": [True], "grown": [False], "both": [True, False]}[args.lane_order]
            variants = [(n, a, lane, r, f) for n in args.cases for lane in ways[args.lanes]
                        for a in ways[args.leaves_ahead] for f in ways[args.fused]
                        # the lane order matters only where the lanes are on (auto: on a GPU)
                        for r in (orders if (lane if lane is not None else wp.get_device(device).is_cuda) else [True])
                        if not (a and "mesh" in n and args.leaves_ahead == "both")]  # the mesh has no leaves
            variants = [(*v, setting) for v in variants for setting in [{}, *args.tries]]
            for name, ahead, lanes, by_root, fused, setting in variants:
                params = HairParams(substeps=args.substeps, **CASES[name])
                ms, moved, stretch = run_ours(scene, params, args.frames, settled, args.profile, ahead, lanes,
                                              by_root, fused, setting)
                rate = scene.model.num_particles * params.substeps / (ms * 1e-3)
                gbs = moved / (ms * 1e-3) / 1e9
                label = (name + (" ahead" if ahead and args.leaves_ahead == "both" else "")
                         + (" lanes" if lanes and args.lanes == "both" else "")
                         + (" grown" if not by_root and args.lane_order != "root" else "")
                         + (" fused" if fused and args.fused == "both" else "")
                         + "".join(f" {attr}={'x'.join(map(str, value)) if isinstance(value, tuple) else value}"
                                   for attr, value in setting.items()))
                rows.append([label, strands, scene.model.num_particles, device, fmt(ms, 4), fmt(rate),
                             fmt(moved / 1e6), f"{gbs:.0f} ({100 * gbs / ceiling:.0f}%)", fmt(stretch, 2),
                             fmt(peer_ms, 4), fmt(peer_stretch, 2),
                             f"{peer_ms / ms:.1f}x" if peer_ms else "-"])
                print("| " + " | ".join(str(c) for c in rows[-1]) + " |", flush=True)
    print()
    print(table(header, rows))


if __name__ == "__main__":
    main()
