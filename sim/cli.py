"""The `cfx` command: run scenes and the demo to USD caches, preview, view and inspect caches."""

import argparse
import os
import signal
import sys

from .errors import Stopped  # noqa: F401 (cli.Stopped: what SIGTERM and SIGHUP raise)

EXIT_INPUT = 2
EXIT_SIMULATION = 3


def _fail(message, status):
    print(f"cfx: error: {message}", file=sys.stderr)
    return status


def _frames(text):
    """'12' -> [12]; '1:72:12' -> range(1, 73, 12) (inclusive end; the preview keeps the range's frames
    the cache has, so the README's 1:72:12 also suits a short test cache); '1,24,48' -> [1, 24, 48].
    ValueError naming the flag for anything else, or a range that holds no frame."""
    try:
        if ":" in text:
            parts = [int(p) for p in text.split(":")]
            if len(parts) not in (2, 3) or min(parts[2:], default=1) <= 0:
                raise ValueError
            frames = range(parts[0], parts[1] + 1, parts[2] if len(parts) == 3 else 1)
        else:
            frames = [int(p) for p in text.split(",")]
    except ValueError:
        frames = []
    if not frames:
        raise ValueError(f"--frames: expected a frame (12), a list (1,24,48) or a range start:end[:step] with a "
                         f"positive step (1:72:12), got {text!r}")
    return frames


def _size(text, example="960x720"):
    """(width, height) of a --size WIDTHxHEIGHT; ValueError naming the flag for anything else."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"--size: expected WIDTHxHEIGHT in pixels, e.g. {example}, got {text!r}") from None
    return w, h


def _views(texts):
    """--view values: names pass through, 'YAW,PITCH' become (yaw, pitch) in degrees; the preview
    names an unknown view."""
    views = []
    for text in texts or ():
        if "," in text:
            try:
                yaw, pitch = (float(v) for v in text.split(","))
            except ValueError:
                raise ValueError(f"--view: expected a view name or YAW,PITCH in degrees, e.g. 30,15, got {text!r}") \
                    from None
            views.append((yaw, pitch))
        else:
            views.append(text)
    return views


def _overrides(args):
    scene = {}
    if getattr(args, "frames", None) is not None:
        scene["frames"] = args.frames
    if getattr(args, "device", None):
        scene["device"] = args.device
    return {"scene": scene}


def _report(result, config=None):
    s = result.stats
    parts = []
    if result.strands:
        parts.append(f"{result.strands} strands ({result.particles} particles)"
                     + (f" and {result.children} render children" if result.children else ""))
    if result.cloth_particles:
        parts.append(f"{result.cloth_particles} cloth particles")
    if result.face_vertices:
        parts.append("a face")
    print(f"wrote {result.path}: {result.frames} frames, {', '.join(parts) or 'the collider alone'} in "
          f"{result.seconds:.1f} s",
          file=sys.stderr)
    if "max_stretch" in s:
        print(f"  hair: max segment stretch {100 * s['max_stretch']:.3f}%, roots within 5 mm of the surface "
              f"{100 * s['root_within_5mm']:.2f}%, points >1 mm inside {100 * s['inside_1mm']:.3f}%", file=sys.stderr)
        _sampling_hint(config)
    _timeline_hint(config, result.idle_events)
    if result.face_vertices:
        print(f"  face: {result.face_vertices} vertices, largest move from rest {1e3 * s.get('face_max_offset', 0.0):.1f} mm",
              file=sys.stderr)
    if "cloth_substeps" in s:
        chosen = "set by the scene" if result.cloth_substeps_fixed else "from the RK4 stability bound"
        print(f"  cloth: {s['cloth_substeps']} substeps per frame, {chosen} (stable dt <= "
              f"{1e3 * s['cloth_stable_dt']:.3f} ms)", file=sys.stderr)
    if "detail_inside_2mm" in s:
        print(f"  detail surface: vertices >2 mm inside {100 * s['detail_inside_2mm']:.3f}%, the coarse-to-fine "
              f"penetration test tested at most {100 * s['detail_queries']:.1f}% of its vertices (the body's BVH "
              f"decided at most {100 * s['detail_bvh']:.1f}% of those, vertex walks the rest)", file=sys.stderr)
    if "cloth_stretch_p99" in s:
        print(f"  cloth: edge stretch p99 {100 * s['cloth_stretch_p99']:.2f}% (max {100 * s['cloth_stretch_max']:.2f}%), "
              f"vertices >2 mm inside {100 * s['cloth_inside_2mm']:.3f}%, nearest-vertex walk agrees with brute "
              f"force on {100 * s['walk_agreement']:.2f}% (worst frame {100 * s['walk_agreement_worst_frame']:.2f}%)",
              file=sys.stderr)


def _sampling_hint(config):
    """A line when the groom's curls or waves turn too far between vertices to draw as curves."""
    import numpy as np

    from .hairstyle import SMOOTH_TURN

    hair = getattr(config, "hair", None)
    if hair is None or not hair.enabled or hair.guides:
        return
    turn = hair.segment_turn
    if turn is not None and turn > SMOOTH_TURN:
        what = "curls" if hair.style == "curly" else "waves"
        print(f"  hair: the {what} turn up to {np.degrees(turn):.0f} degrees between vertices and draw as zigzags; "
              f"{np.degrees(SMOOTH_TURN):.0f} or less reads as a curve ([hair] vertices = "
              f"{hair.vertices_for_smooth_curves()})", file=sys.stderr)


def _timeline_hint(config, idle=()):
    """Lines naming the [[haircut]] events that did nothing: after the last frame written (a shorter
    --frames, or a typo), or missing every strand (a cut line above the hair, a stroke off the head)."""
    timing = getattr(config, "timing", None)
    if timing is None:
        return
    listed = lambda names: f"{', '.join(names[:3])}{', ...' if len(names) > 3 else ''}"  # noqa: E731
    last = timing.start_frame + timing.frames - 1
    late = [f"haircut[{i}] at frame {e.frame}" for i, e in enumerate(config.haircut) if e.frame > last]
    if late:
        print(f"  hair: {len(late)} haircut event(s) after the last frame ({last}) did not happen: {listed(late)}",
              file=sys.stderr)
    if idle:
        print(f"  hair: {len(idle)} haircut event(s) changed no strands: {listed(list(idle))}", file=sys.stderr)


def _check_preview(path):
    """The --preview path checked before the run, so a bad one costs no simulation."""
    if path:
        from io_usd.output_file import check_output_path
        from io_usd.preview import EXTENSIONS

        check_output_path(path, EXTENSIONS, "the preview")


def cmd_run(args, config=None):
    import sim

    _check_preview(args.preview)
    stage = None
    if config is None:
        from io_usd.scene_input import is_usd_scene, read_usd_scene

        if is_usd_scene(args.scene):  # a DCC's stage with cfx:role prims; the cache is a layer over it
            stage = read_usd_scene(args.scene, _overrides(args))
            config = stage.config
        else:
            config = sim.load_scene(args.scene, _overrides(args))
    result = sim.run_scene(config, args.output, progress=not args.quiet, stage=stage)
    _written.append(result.path)
    _report(result, config)
    if args.preview:
        _preview(result.path, args.preview, frames=None, quiet=args.quiet)
    return 0


# caches a command has committed, so a stop in its preview afterwards says the cache is there
_written = []


def cmd_demo(args):
    import sim

    config = sim.demo_scene(_overrides(args))
    if not args.no_preview and args.preview is None:
        args.preview = os.path.splitext(args.output)[0] + ".png"
    return cmd_run(args, config)


LIPSYNC_SOURCE = "<lipsync>"
# the scene keys cmd_lipsync sets from its options
LIPSYNC_OPTIONS = {"face.voice": "--voice", "scene.device": "--device", "face.expressions[0].weight": "--intensity",
                   "scene.fps": "--fps"}


def cmd_lipsync(args):
    """Speak a WAV with the built-in head: lip sync from the audio, an optional expression, no hair
    unless asked, the head still unless asked."""
    import math

    import sim
    from sim import lipsync
    from sim.scene import _build_config

    from .config import LIMITS
    from .errors import InputError

    top = LIMITS[("scene", "fps")]
    if not (math.isfinite(args.fps) and 1.0 <= args.fps <= top):  # the scene's own range ([scene] fps)
        raise InputError("--fps", None, f"must be from 1 to {top:g} frames a second, got {args.fps:g}")
    if not 0.0 <= args.intensity <= 1.0:
        raise InputError("--intensity", None, f"must be from 0 to 1, got {args.intensity:g}")
    _check_preview(args.preview)
    audio = str(lipsync.DEMO_LINE_PATH) if args.audio == "builtin" else args.audio  # as a scene's audio = "builtin"
    samples = lipsync.load_audio(audio)
    seconds = len(samples) / lipsync.SAMPLE_RATE
    start = 1.0
    frames = int(math.ceil(seconds * args.fps)) + 2  # the mouth closes again after the last word
    face = {"audio": os.path.abspath(audio), "audio_start": start, "voice": args.voice}
    if args.expression != "neutral":
        face["expressions"] = [{"frame": start, "emotion": args.expression, "weight": args.intensity}]
    data = {"scene": {"frames": frames, "fps": args.fps, "preroll": 0.0 if not args.hair else 1.0},
            "head": {"animation": args.head_motion}, "hair": {"enabled": bool(args.hair)}, "face": face}
    if args.device:
        data["scene"]["device"] = args.device
    try:
        config = _build_config(LIPSYNC_SOURCE, data, None)
        result = sim.run_scene(config, args.output, progress=not args.quiet)
        _written.append(result.path)
    except InputError as err:  # the scene is built from the options: name the option, not the scene key
        if err.source != LIPSYNC_SOURCE or err.key not in LIPSYNC_OPTIONS:
            raise
        raise InputError(LIPSYNC_OPTIONS[err.key], None, err.reason) from None
    _report(result, config)
    if args.preview:
        _preview(result.path, args.preview, frames=None, quiet=args.quiet, focus="face")
    return 0


def _preview(cache, out, frames, quiet, size=(960, 720), follow=False, focus=None, views=None):
    from io_usd.preview import preview

    preview(cache, out, frames=frames, width=size[0], height=size[1], follow=follow, focus=focus,
            progress=not quiet, views=views)
    if not quiet:
        print(f"wrote {out}", file=sys.stderr)


def cmd_preview(args):
    frames = _frames(args.frames) if args.frames else None
    _preview(args.cache, args.output, frames, args.quiet, _size(args.size), args.follow, args.focus,
             _views(args.view))
    return 0


def cmd_studio(args):
    """The interactive haircut studio on a scene's hair."""
    import sim
    from io_usd.viewer import has_display

    from .studio import Session, StudioWindow

    if not has_display():
        return _fail("cfx studio needs a display (DISPLAY is unset or has no X server); script the same edits as "
                     "[[haircut]] tables in the scene file and use cfx run", EXIT_INPUT)
    for path in (args.cache, args.script):
        if path and os.path.abspath(path) == os.path.abspath(args.scene):
            return _fail(f"{path}: would overwrite the scene file", EXIT_INPUT)
    from io_usd.cache import check_cache_path
    from io_usd.output_file import check_output_path

    if args.cache:
        check_cache_path(args.cache)
    if args.script:
        check_output_path(args.script, (".toml",), "the saved scene")
    width, height = _size(args.size)
    session = Session(sim.load_scene(args.scene, _overrides(args)), width, height)
    try:
        StudioWindow(session, args.cache, args.script, max_frames=args.max_frames).run()
        saved = [p for p in (args.cache, args.script) if p]
        if saved:
            print(f"wrote {' and '.join(saved)}: {len(session.events)} edits over {len(session.frames)} frames",
                  file=sys.stderr)
    finally:
        session.close()
    return 0


def cmd_score(args):
    """Score a haircut against a target hairstyle: four-view hair silhouettes and strand lengths."""
    from io_usd.score import check_report_path, score_caches, write_report

    if args.output:
        check_report_path(args.output)
    size = _size(args.size, example="480x480")
    report = score_caches(args.result, args.target, frame=args.frame, size=size, images=bool(args.output))
    print(report.table())
    if args.output:
        write_report(report, args.output)
        if not args.quiet:
            print(f"wrote {args.output} in {report.seconds:.1f} s", file=sys.stderr)
    return 0


def cmd_view(args):
    from io_usd.viewer import has_display, view

    if not has_display():
        return _fail("cfx view needs a display (DISPLAY is unset or has no X server); use cfx preview for images "
                     "and movies", EXIT_INPUT)
    try:
        view(args.cache)
    except Stopped:
        raise  # SIGTERM / SIGHUP: said and exited as for any command (main)
    except KeyboardInterrupt:
        return _fail("interrupted", 130)
    return 0


def cmd_cache(args):
    """Where the asset cache is, what it holds, and --clear to empty it."""
    from . import asset_cache

    folder = asset_cache.cache_dir()
    if folder is None:
        print("asset cache: off (CFX_CACHE_DIR=off); bodies, garments, grooms and sphere trees are built on every run")
        return 0
    if args.clear:
        print(f"asset cache {folder}: removed {asset_cache.clear()} entries")
        return 0
    found = asset_cache.entries()
    current = f"-{asset_cache.source_digest()}-"
    print(f"asset cache {folder}: {len(found)} entries, {sum(size for _, size in found) / 1e6:.1f} MB")
    for path, size in found:
        state = "" if current in path.name else "  (stale: other engine code or libraries)"
        print(f"  {path.name}  {size / 1e6:.2f} MB{state}")
    return 0


def cmd_info(args):
    from io_usd.cache import CacheReader
    from io_usd.validate import cache_errors, validation_errors

    reader = CacheReader(args.cache)
    frames = reader.frames() if reader.prims else []
    print(f"{args.cache}")
    print(f"  up axis {reader.up_axis}, {reader.meters_per_unit} m per unit, {reader.fps:g} fps, "
          f"time codes {reader.start_frame}..{reader.end_frame}, {len(frames)} frames sampled")
    print(f"  complete: {'yes' if reader.complete else 'NO (interrupted run)'}")
    version = reader.metadata.get("cfx:engineVersion")
    if version:
        print(f"  written by warp-cfx {version}")
    for name, prim in reader.prims.items():
        if prim.kind == "curves":
            detail = f"{len(prim.counts)} curves, {prim.num_points} points"
            if getattr(prim, "varying", False):  # cut, grown or erased: the strands change over time
                last = reader.counts(name, frames[-1])
                detail += f" at the start; {len(last)} curves, {int(last.sum())} points at frame {frames[-1]}"
        else:
            detail = f"{len(prim.counts)} faces, {prim.num_points} points"
        print(f"  {prim.path:24s} role={prim.role:12s} {prim.kind:6s} {detail}")
    from pxr import Usd, UsdSkel

    for prim in reader.stage.Traverse():  # rigs carry no role: the same animation in the form DCCs retarget
        if prim.IsA(UsdSkel.Root):
            shapes = [p for p in Usd.PrimRange(prim) if p.IsA(UsdSkel.BlendShape)]
            print(f"  {str(prim.GetPath()):24s} UsdSkel rig, {len(shapes)} blend shapes (invisible: retarget it)")
    stats = reader.metadata.get("cfx:stats")
    if isinstance(stats, dict) and stats:  # another tool's layer may hold anything under the key
        print("  stats: " + ", ".join(f"{k}={v:.6g}" if isinstance(v, (int, float)) else f"{k}={v}"
                                      for k, v in stats.items()))
    if args.validate:
        errors = validation_errors(args.cache) + cache_errors(reader)
        print(f"  UsdValidation: {len(errors)} errors")
        for e in errors:
            print(f"    {e}")
        return 1 if errors or not reader.complete else 0  # a gate: an interrupted run's cache fails it too
    return 0


def build_parser():
    parser = argparse.ArgumentParser(prog="cfx", description="Warp CFX: hair, cloth and faces simulated to USD caches.")
    parser.add_argument("--version", action="version", version=_version())
    sub = parser.add_subparsers(dest="command", required=True)

    def sim_options(p):
        p.add_argument("--frames", type=int, help="override the number of frames")
        p.add_argument("--device", help="override the device (cpu, cuda, cuda:0)")
        p.add_argument("--preview", help="also render this preview (.png/.mp4/.gif)")
        p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")

    p = sub.add_parser("run", help="run a TOML scene, or a USD stage with cfx:role prims, to a USD cache")
    p.add_argument("scene")
    p.add_argument("-o", "--output", required=True, help="cache path (.usdc, .usd or .usda)")
    sim_options(p)
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("demo", help="run the built-in scene (no files needed) and preview it")
    p.add_argument("-o", "--output", default="out/demo.usdc")
    p.add_argument("--no-preview", action="store_true")
    sim_options(p)
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("lipsync", help="make the built-in head speak a WAV (lip sync) to a USD cache")
    p.add_argument("audio", help="a WAV file at any sample rate (mixed to mono, resampled to 16 kHz); builtin: "
                                 "the demo's line")
    p.add_argument("-o", "--output", required=True, help="cache path (.usdc, .usd or .usda)")
    p.add_argument("--fps", type=float, default=24.0)
    p.add_argument("--voice", default="general",
                   help="lip-sync weights: general, a training voice, or a folder with a.wav i.wav u.wav e.wav o.wav "
                        "of this speaker (speaker adaptation picks the best weight set)")
    p.add_argument("--expression", default="neutral", help="emotion held while speaking",
                   choices=("neutral", "happiness", "sadness", "surprise", "fear", "anger", "disgust"))
    p.add_argument("--intensity", type=float, default=0.7, help="strength of the expression, 0..1")
    p.add_argument("--head-motion", default="none", choices=("none", "nod", "turn", "turn_nod"))
    p.add_argument("--hair", action="store_true", help="grow and simulate the default hairstyle too")
    p.add_argument("--device", help="cpu, cuda or cuda:N")
    p.add_argument("--preview", help="also render this preview of the face (.png/.mp4/.gif)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_lipsync)

    p = sub.add_parser("mask", help="render projector frames that put the face on a tracked, moving mask (MP4)")
    from .mask import add_mask_arguments, run_mask

    add_mask_arguments(p)
    p.set_defaults(func=run_mask)

    p = sub.add_parser("capture", help="hair motion capture: synthesise a stripe-dyed capture, solve one to USD")
    capture = p.add_subparsers(dest="capture_command", required=True)
    from .capture_rig import add_synth_arguments, run_synth
    from .capture_solve import add_solve_arguments, run_solve

    q = capture.add_parser("synth", help="simulate a scene and render its dyed guide hairs from calibrated cameras")
    add_synth_arguments(q)
    q.set_defaults(func=run_synth)
    q = capture.add_parser("solve", help="segment, track and triangulate a capture directory into strands and cards")
    add_solve_arguments(q)
    q.set_defaults(func=run_solve)

    p = sub.add_parser("preview", help="render a cache offscreen to .png, .mp4 or .gif")
    p.add_argument("cache")
    p.add_argument("-o", "--output", required=True)
    p.add_argument("--frames", help="frame (12), list (1,24,48) or range start:end:step; "
                                    "several frames in a .png make a contact sheet")
    p.add_argument("--size", default="960x720", help="WIDTHxHEIGHT in pixels")
    p.add_argument("--follow", action="store_true", help="frame every frame on its own (a tracking camera)")
    p.add_argument("--focus", help="frame only this prim or role, e.g. face")
    p.add_argument("--view", action="append", metavar="VIEW",
                   help="three-quarter (the default), front, left, right, back, top, turnaround (front, left, "
                        "back, right) or YAW,PITCH in degrees; repeat it for several views side by side")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_preview)

    p = sub.add_parser("studio", help="the interactive haircut studio: comb, cut and wax the scene's hair with "
                                      "the mouse (needs a display)")
    p.add_argument("scene")
    p.add_argument("--cache", help="save the session's frames to this cache (.usdc, .usd or .usda)")
    p.add_argument("--script", help="save the scene file with the session's [[haircut]] timeline (.toml)")
    p.add_argument("--size", default="960x720", help="window WIDTHxHEIGHT in pixels")
    p.add_argument("--max-frames", type=int, help="stop simulating after this many frames (the window stays)")
    p.add_argument("--device", help="override the device (cpu, cuda, cuda:0)")
    p.set_defaults(func=cmd_studio)

    p = sub.add_parser("score", help="score a haircut against a target: hair silhouettes from four views "
                                     "(front, left, right, back) and per-strand lengths, 0-100")
    p.add_argument("result", help="the cut hairstyle's cache")
    p.add_argument("target", help="the target hairstyle's cache")
    p.add_argument("-o", "--output", help="also write a side-by-side PNG report (result, target, difference)")
    p.add_argument("--frame", type=int, help="frame of both caches (default: each cache's last)")
    p.add_argument("--size", default="480x480", help="WIDTHxHEIGHT of each view in pixels")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_score)

    p = sub.add_parser("view", help="open the interactive viewer (needs a display)")
    p.add_argument("cache")
    p.set_defaults(func=cmd_view)

    p = sub.add_parser("cache", help="the asset cache: built bodies, garments, grooms and sphere trees kept between runs "
                                     "(CFX_CACHE_DIR sets its folder, or off)")
    p.add_argument("--clear", action="store_true", help="delete every entry")
    p.set_defaults(func=cmd_cache)

    p = sub.add_parser("info", help="list a cache's prims, roles, frames and counts")
    p.add_argument("cache")
    p.add_argument("--validate", action="store_true",
                   help="also run usd-core's validators; exit 1 if they find errors or the cache is incomplete")
    p.set_defaults(func=cmd_info)
    return parser


def _version():
    from sim import __version__

    return f"warp-cfx {__version__}"


def _raise_stopped(signum, _frame):
    from .errors import record_stop

    record_stop(signum)
    if signum == signal.SIGINT:
        raise KeyboardInterrupt
    raise Stopped(signum)


def _stop_on_signals():
    """Install _raise_stopped for SIGINT, SIGTERM and SIGHUP; returns the handlers it replaced."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        return {}
    names = [n for n in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, n)]
    return {getattr(signal, n): signal.signal(getattr(signal, n), _raise_stopped) for n in names}


def main(argv=None):
    from .errors import clear_stops

    args = build_parser().parse_args(argv)
    clear_stops()
    _written.clear()
    replaced = _stop_on_signals()
    try:
        return _run(args)
    finally:
        for signum, handler in replaced.items():
            signal.signal(signum, handler)
        clear_stops()  # a stop ends this command only, not later runs of the Python API in this process


def _run(args):
    from .errors import InputError, SimulationError, stop_requested

    try:
        try:
            return args.func(args)
        except Exception:
            # a signal's exception raised inside a lock's release or a pool becomes another error
            if stop_requested() is None:
                raise
            signum = stop_requested()
            raise (KeyboardInterrupt() if signum == signal.SIGINT else Stopped(signum)) from None
    except InputError as err:
        return _fail(str(err), EXIT_INPUT)
    except (FileNotFoundError, IsADirectoryError) as err:
        return _fail(str(err), EXIT_INPUT)
    except ValueError as err:
        return _fail(str(err), EXIT_INPUT)
    except OSError as err:  # the file system refused a read or write the checks before the work could not foresee
        return _fail(str(err), EXIT_INPUT)
    except SimulationError as err:
        return _fail(f"simulation failed: {err}", EXIT_SIMULATION)
    except (Stopped, KeyboardInterrupt) as err:
        what = f"stopped by {signal.Signals(err.signum).name}" if isinstance(err, Stopped) else "interrupted"
        kept = f"; {_written[-1]} is complete, the preview was not written" if _written else "; no output was written"
        return _fail(what + kept, 128 + err.signum if isinstance(err, Stopped) else 130)


if __name__ == "__main__":
    sys.exit(main())
