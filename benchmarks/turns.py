"""Two checkouts of Warp CFX timed in turns, frame by frame, on the same machine: an A/B test that
holds up on a shared, noisy CPU.

On a machine whose speed drifts by tens of percent from minute to minute (other tenants, clocks),
timings of A and then B compare the machine's two moods more than the code. Here each checkout
builds the same case in a process of its own, and the two step one frame at a time in alternation,
each waiting (blocked on a pipe, taking no CPU) while the other runs: a drift hits both frames of a
pair alike, and the ratio B/A of each pair keeps what the code changed. The table gives each side's
median and fastest frame and the median and quartiles of the pair ratios.

Each frame starts after the other side's, with this side's cores idle meanwhile: that is the case
of a paced real-time loop, not of frames run back to back. Work split among the cores (graphs
run_parallel) pays a hand-over to a woken core per split step (about 50 us on a two-core VM), so a
change that adds split steps can show nothing here and gain in benchmarks/realtime.py (BENCHMARKS.md,
sessions 31 and 37). `--run N` times runs of N frames back to back instead, each side's run in its
turn, the ratio then taken per pair of runs: frames back to back with the drift still cancelled.

    python benchmarks/turns.py BEFORE_DIR AFTER_DIR --scene examples/scenes/walk_dress.toml
    python benchmarks/turns.py BEFORE_DIR AFTER_DIR --hair full+mesh --strands 1000 --frames 40
    python benchmarks/turns.py BEFORE_DIR AFTER_DIR --realtime simplified1+spheres "proxy 2.5 cm"
    python benchmarks/turns.py BEFORE_DIR AFTER_DIR --realtime none "proxy 2.5 cm" --frames 300 --run 10

A checkout to compare with is made by `git worktree add /tmp/before <commit>`; each side runs with
its own directory as the working directory and on PYTHONPATH, with this interpreter.
"""

import argparse
import os
import subprocess
import sys
import time

import numpy as np

FPS = 24.0


def build(args):
    """(advance one frame, device synchronise) for the case, built from the checkout in the working
    directory."""
    import warp as wp

    wp.config.quiet = True
    if args.scene:
        from sim.scene import Scene, load_scene

        scene = Scene(load_scene(args.scene))
        dt = 1.0 / scene.config.timing.fps
        detail = scene.cloth_detail is not None
        for _ in range(args.warmup):
            scene.advance(dt, detail=detail)
        return lambda: scene.advance(dt, detail=detail), wp.synchronize

    sys.path.insert(0, os.path.join(os.getcwd(), "benchmarks"))
    if args.realtime:
        import realtime

        hair_case, cloth_case = args.realtime
        scene = realtime.build("cpu", realtime.HAIR.get(hair_case), realtime.CLOTH.get(cloth_case), True)
        scene.advance(0.25)  # mid-stride, as realtime.time_scene starts
        for _ in range(args.warmup):
            scene.advance(1.0 / realtime.FPS, detail=True)
        return lambda: scene.advance(1.0 / realtime.FPS, detail=True), wp.synchronize

    import hair

    # the checkout's own benchmarks/hair.py builds the case; the solver is reset here, not through a
    # helper of it, so that checkouts from before any such helper can be compared too
    scene = hair.build_scene(args.strands, "cpu", args.substeps)
    x, v = hair.settle(scene)
    params = hair.HairParams(substeps=args.substeps, **hair.CASES[args.hair])
    scene.solver = hair.HairSolver(scene.model, params)
    scene.graphs.clear()
    scene.state, scene._scratch = scene.model.state(), scene.model.state()
    scene.state.x.assign(x)
    scene.state.v.assign(v)
    scene.time = 0.0
    for _ in range(args.warmup):
        scene.advance(1.0 / FPS)
    return lambda: scene.advance(1.0 / FPS), wp.synchronize


def worker(args):
    """One side: build the case, then time a run of frames each time the token arrives, and pass it on."""
    step, synchronize = build(args)
    synchronize()
    mine, theirs = os.fdopen(args.read_fd, "rb", buffering=0), os.fdopen(args.write_fd, "wb", buffering=0)
    spans = []  # each run's start and end on the system's monotonic clock, which both sides share
    for _ in range(turns(args)):
        if not mine.read(1):
            break
        start = time.perf_counter()
        for _ in range(args.run):
            step()
        synchronize()
        spans.append((start, time.perf_counter()))
        try:
            theirs.write(b".")
        except BrokenPipeError:  # the other side is done
            pass
    print("SPANS " + " ".join(f"{a:.6f} {b:.6f}" for a, b in spans), flush=True)


def side(checkout, read_fd, write_fd, args):
    case = (["--scene", args.scene] if args.scene else ["--realtime", *args.realtime] if args.realtime
            else ["--hair", args.hair, "--strands", str(args.strands)])
    command = [sys.executable, os.path.abspath(__file__), "--worker", str(read_fd), str(write_fd), *case,
               "--frames", str(args.frames), "--run", str(args.run), "--warmup", str(args.warmup),
               "--substeps", str(args.substeps)]
    env = dict(os.environ, PYTHONPATH=os.path.abspath(checkout))
    return subprocess.Popen(command, cwd=checkout, env=env, stdout=subprocess.PIPE, text=True,
                            pass_fds=(read_fd, write_fd))


def turns(args):
    """How many runs of args.run frames each side times."""
    return max(1, args.frames // args.run)


def spans_of(output, name):
    lines = [line for line in output.splitlines() if line.startswith("SPANS")]
    if not lines:
        raise SystemExit(f"{name}: no frames were timed (see its output above)")
    return np.array(lines[-1].split()[1:], float).reshape(-1, 2)


def race(checkout_a, checkout_b, args):
    """Time args' case in both checkouts in turns: ((runs, 2) start and end times [s] of A's runs of
    args.run frames, the same of B's), A's k-th run before B's k-th, B's before A's next."""
    to_a, from_b = os.pipe()  # B's tokens go to A
    to_b, from_a = os.pipe()
    a = side(checkout_a, to_a, from_a, args)
    b = side(checkout_b, to_b, from_b, args)
    for fd in (to_a, to_b, from_a):
        os.close(fd)
    os.write(from_b, b".")  # A goes first
    os.close(from_b)
    out_a, out_b = a.communicate()[0], b.communicate()[0]
    return spans_of(out_a, "A"), spans_of(out_b, "B")


def case_arguments(parser):
    """The options that choose and size the case (shared with benchmarks/cpu_profile.py)."""
    parser.add_argument("--scene", help="a scene file (relative to each checkout): frames of Scene.advance")
    parser.add_argument("--hair", default="full+mesh",
                        help="without --scene: a case of benchmarks/hair.py (its CASES: straight strands on the "
                             "turning head)")
    parser.add_argument("--realtime", nargs=2, metavar=("HAIR", "CLOTH"),
                        help="the real-time case of benchmarks/realtime.py with these of its HAIR and CLOTH tables "
                             "(\"none\" for neither), 1/60 s frames")
    parser.add_argument("--strands", type=int, default=1000)
    parser.add_argument("--substeps", type=int, default=10)
    parser.add_argument("--frames", type=int, default=30, help="timed frames per side")
    parser.add_argument("--run", type=int, default=1,
                        help="frames back to back in each turn (1: every frame starts with the cores idle)")
    parser.add_argument("--warmup", type=int, default=3, help="frames run before timing")
    return parser


def arguments():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkouts", nargs="*", metavar="DIR", help="the two checkouts, A then B")
    case_arguments(parser)
    parser.add_argument("--worker", nargs=2, type=int, metavar=("READ_FD", "WRITE_FD"), help=argparse.SUPPRESS)
    return parser


def main():
    parser = arguments()
    args = parser.parse_args()
    if args.worker:
        args.read_fd, args.write_fd = args.worker
        worker(args)
        return
    if len(args.checkouts) != 2:
        parser.error("give two checkouts, A and B")
    spans_a, spans_b = race(*args.checkouts, args)
    # ms per frame of each run
    ta, tb = (1e3 / args.run * np.diff(spans, axis=1)[:, 0] for spans in (spans_a, spans_b))
    pairs = min(len(ta), len(tb))
    ratio = tb[:pairs] / ta[:pairs]
    case = (args.scene or (f"real time: hair {args.realtime[0]}, dress {args.realtime[1]}" if args.realtime else
                           f"hair {args.hair}, {args.strands} strands, {args.substeps} substeps"))
    print("| side | checkout | frames | median ms/frame | fastest ms/frame |\n| --- | --- | --- | --- | --- |")
    for name, checkout, t in (("A", args.checkouts[0], ta), ("B", args.checkouts[1], tb)):
        print(f"| {name} | {checkout} | {len(t) * args.run} | {np.median(t):.1f} | {t.min():.1f} |")
    unit = "frames" if args.run == 1 else f"runs of {args.run} frames back to back"
    print(f"\n{case}: B/A per pair of {unit}, median {np.median(ratio):.3f} "
          f"(quartiles {np.percentile(ratio, 25):.3f} to {np.percentile(ratio, 75):.3f}, {pairs} pairs)")


if __name__ == "__main__":
    main()
