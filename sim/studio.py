"""The interactive haircut studio: `cfx studio SCENE.toml` opens a window on the running simulation
where the mouse combs, cuts and waxes, and saves the session as a cache and as the scene file with
the equivalent [[haircut]] timeline.

Keys pick the tool: c comb, b blunt cut, h chop cut, t thinning, w wax, e erase, g grow,
i initialise (at once), r release the comb; 1-4 look from the front, left, right and back; space
pauses; p writes a screenshot (studio_frame_N.png beside the cache, or here); s saves; q or Escape
saves and quits. With a cut tool a drag draws the cut line; with erase,
grow and wax it brushes a region (wax then drags the brushed tips by the stroke's start-to-end
move); with the comb the first drag places it on the head and grabs the hair it crosses, and each
later drag moves it, until r releases it.

Every edit is applied between two frames exactly as the scene file's timeline applies it, so
`cfx run` of the saved scene file repeats the session. The window (pyglet, OpenGL 4.1) draws the
scene with the preview's own scene builder and lights; `Session` holds everything but the window,
so it is also usable (and tested) without a display.
"""

import os
import tempfile

import numpy as np

from .errors import InputError

KEY_TOOLS = {"c": "comb", "b": "blunt", "h": "chop", "t": "thinning", "w": "wax", "e": "erase", "g": "grow"}
VIEWS = {"1": 0.0, "2": 90.0, "3": -90.0, "4": 180.0}  # yaw of front, left, right, back as in cfx preview: the head
# faces +Z, so its left side is +X
BRUSH_RADIUS = 30.0  # px, erase / grow / wax brushes
GROW_LENGTH = 0.02  # m added by a grow stroke
CHOP = {"amplitude": 8.0, "period": 24.0}  # px zigzag of a chop stroke


class LiveReader:
    """The running scene's collider and hair in the shape of io_usd.cache.CacheReader, for the
    preview's SceneBuilder."""

    def __init__(self, scene):
        self.scene = scene
        self.refresh()

    def refresh(self):
        from io_usd.cache import CachePrim

        from .scene import SKIN_COLOR, head_colors

        s = self.scene
        head = s.head
        tinted = head_colors(head, s.config.hair.color) if s.model is not None else None
        self.prims = {s.collider_name: CachePrim(s.collider_name, "", "collider", "mesh", len(head.vertices),
                                                 np.full(len(head.faces), 3), indices=head.faces.reshape(-1),
                                                 color=SKIN_COLOR, vertex_colors=tinted)}
        if s.model is not None:
            self.prims["hair"] = CachePrim("hair", "", "hair", "curves", s.model.num_particles, s.model.counts,
                                           widths=s.model.widths_np, color=s.config.hair.color)

    def points(self, name, frame=None):
        s = self.scene
        return (s.collider.points if name == s.collider_name else s.state.x).numpy().astype(np.float32)

    def counts(self, name, frame=None):
        return self.prims[name].counts

    def widths(self, name, frame=None):
        return self.prims[name].widths

    def normals(self, name, frame=None):
        return None


class FrameSpool:
    """The frames a studio session has simulated, kept on disk, one .npz each in a temporary folder,
    so that a long session holds one frame in memory: a 10k-strand groom records 4 MB a frame, some
    10 GB in ten minutes at 24 frames/s. Saving reads them back in order; the folder goes with the
    spool (close, or when it is collected)."""

    FIELDS = ("hair", "counts", "widths", "ids", "collider")

    def __init__(self, folder=None):
        self._dir = tempfile.TemporaryDirectory(prefix="cfx_studio_", dir=folder)
        self.numbers = []  # the frame numbers recorded, in order

    @property
    def folder(self):
        return self._dir.name

    def _path(self, index):
        return os.path.join(self._dir.name, f"{index:07d}.npz")

    def append(self, frame, hair, counts, widths, ids, collider):
        np.savez(self._path(len(self.numbers)), hair=hair, counts=counts, widths=widths, ids=ids, collider=collider)
        self.numbers.append(int(frame))

    def pop(self):
        """Forget the last frame recorded."""
        os.remove(self._path(len(self.numbers) - 1))
        self.numbers.pop()

    def read(self, index):
        """(frame, hair points, counts, widths, strand ids, collider points) of the index-th frame recorded."""
        with np.load(self._path(index % len(self.numbers))) as data:
            return (self.numbers[index], *(data[k] for k in self.FIELDS))

    def __len__(self):
        return len(self.numbers)

    def __iter__(self):
        return (self.read(i) for i in range(len(self.numbers)))

    def close(self):
        self._dir.cleanup()
        self.numbers = []


class Session:
    """A studio session without its window: the scene, the camera the tools act through, the edits
    made so far (as timeline tables) and the frames simulated (for the cache, spooled to disk)."""

    def __init__(self, config, width=640, height=480):
        from .scene import Scene, quiet_warp

        if not config.hair.enabled:
            raise InputError(config.source, "hair.enabled", "the studio cuts hair: the scene needs hair")
        quiet_warp()
        self.config = config
        self.scene = Scene(config)
        t = config.timing
        if t.preroll > 0.0:
            self.scene.advance(t.preroll, animate=False)
        self.frame = t.start_frame
        self.width, self.height = int(width), int(height)
        points = self.scene.state.x.numpy()  # frame the hair (the collider may be a whole body)
        self.subject = 0.5 * (points.min(0) + points.max(0))
        self.radius = float(np.linalg.norm(points.max(0) - points.min(0)))
        self.camera = self.view(0.0)
        self.events = []  # [[haircut]] tables, in the order applied
        self.frames = FrameSpool()  # (frame, hair points, counts, widths, collider points) on disk
        self.comb = None  # the held comb's timeline table while the comb is in the hair
        self._comb_drag = np.zeros(2)
        from . import haircut

        haircut.run_events(self.scene, config.haircut, self.frame)
        self._record()

    def view(self, yaw_degrees):
        """The camera looking at the head from `yaw_degrees` about the vertical (0 = the front)."""
        from io_usd.preview import Camera

        yaw = np.radians(yaw_degrees)
        eye = self.subject + 1.6 * self.radius * np.array([np.sin(yaw), 0.15, np.cos(yaw)])
        return Camera.look_at(eye, self.subject, yfov=0.7, width=self.width, height=self.height)

    def camera_table(self):
        c = self.camera
        target = c.eye - c.pose[:3, 2]
        return {"eye": [float(v) for v in c.eye], "target": [float(v) for v in target], "yfov": float(c.yfov),
                "width": int(c.width), "height": int(c.height)}

    # -- edits ------------------------------------------------------------------------------------
    def apply(self, tool, stroke):
        """Apply `tool` with a screen stroke (pixel points) at the current frame; returns its table,
        or None when the stroke did nothing (a comb that missed the head)."""
        from . import haircut

        stroke = [[float(u), float(v)] for u, v in np.asarray(stroke, np.float64).reshape(-1, 2)]
        if tool == "comb":
            return self._comb_stroke(stroke)
        table = {"frame": self.frame, "tool": tool, "camera": self.camera_table()}
        if tool in ("blunt", "chop", "thinning"):
            table["stroke"] = stroke
            if tool == "chop":
                table.update(CHOP)
            if tool == "thinning":
                table.update(fraction=0.5, seed=len(self.events))
        elif tool in ("erase", "grow", "wax"):
            table.update(stroke=stroke[:1] if tool == "wax" else stroke, radius=BRUSH_RADIUS)
            if tool == "grow":
                table["length"] = GROW_LENGTH
            if tool == "wax":
                table["drag"] = [stroke[-1][0] - stroke[0][0], stroke[-1][1] - stroke[0][1]]
        elif tool == "initialise":
            table = {"frame": self.frame, "tool": "initialise"}
        else:
            raise ValueError(f"unknown tool {tool!r}")
        event = haircut.parse_timeline([table], self.config.source)[0]
        haircut.run_event(self.scene, event)
        self.events.append(table)
        self._refresh_frame()
        return table

    def _comb_stroke(self, stroke):
        from . import haircut

        if self.comb is None:  # place the comb and grab the hair it crosses
            table = {"frame": self.frame, "tool": "comb", "stroke": stroke, "camera": self.camera_table()}
            try:
                haircut.run_event(self.scene, haircut.parse_timeline([table], self.config.source)[0])
            except ValueError:
                return None
            self.comb = table
            self._comb_drag = np.zeros(2)
            self.events.append(table)
            return table
        # a later drag moves the held comb by the stroke's start-to-end move, reached by the next frame
        self._comb_drag = self._comb_drag + np.subtract(stroke[-1], stroke[0])
        moves = self.comb.setdefault("moves", [])
        if moves and moves[-1][0] == self.frame + 1:
            moves.pop()
        moves.append([self.frame + 1, float(self._comb_drag[0]), float(self._comb_drag[1])])
        return self.comb

    def release(self):
        if self.comb is not None:
            self.comb["release"] = self.frame + 1
            self.comb = None

    # -- time -------------------------------------------------------------------------------------
    def step(self):
        """Simulate the next frame (the held comb moves toward its latest drag over it)."""
        from . import comb as combing
        from . import haircut

        nxt = self.frame + 1
        combs = [e for e in self.events if e["tool"] == "comb"]
        timeline = self.config.haircut + haircut.parse_timeline(combs, self.config.source)
        combing.before_frame(self.scene, timeline, nxt)
        self.scene.advance(1.0 / self.config.timing.fps)
        self.frame = nxt
        haircut.run_events(self.scene, self.config.haircut, nxt)  # the scene file's own timeline plays too
        self._record()

    def _record(self):
        s = self.scene
        self.frames.append(self.frame, s.state.x.numpy(), s.model.counts, s.model.widths_np, s.model.strand_ids,
                           s.collider.points.numpy())

    def _refresh_frame(self):
        """An edit at this frame replaces what was recorded for it."""
        self.frames.pop()
        self._record()

    def close(self):
        """Remove the recorded frames from disk (save first to keep them)."""
        self.frames.close()

    # -- saving -----------------------------------------------------------------------------------
    def save(self, cache_path, script_path):
        """Write the session's cache and its scene file (the scene's own tables, the frames run so
        far and the [[haircut]] timeline that repeats the edits)."""
        if script_path:
            write_script(self.config, self.events, self.frame, script_path)
        if cache_path:
            write_session_cache(self, cache_path)


def write_script(config, events, last_frame, path):
    """The scene file with this session's timeline: loading and running it repeats the session."""
    import tomli_w

    from io_usd.output_file import write_whole

    from .config import load_toml

    data = load_toml(config.source) if config.source != "<demo>" else {}
    data = {k: dict(v) if isinstance(v, dict) else v for k, v in data.items()}
    scene = dict(data.get("scene", {}))
    scene["frames"] = int(last_frame - config.timing.start_frame + 1)
    data["scene"] = scene
    base = os.path.dirname(os.path.abspath(config.source)) if config.source != "<demo>" else os.getcwd()
    here = os.path.dirname(os.path.abspath(path))
    for table in data.values():  # files the scene names stay found from the new file's folder
        if isinstance(table, dict):
            for key, value in table.items():
                if isinstance(value, str) and value and value != "builtin" and os.path.exists(os.path.join(base, value)):
                    table[key] = os.path.relpath(os.path.join(base, value), here)
    # the scene's own timeline, then the session's edits: at a shared frame the file's come first,
    # as they did in the session
    timeline = list(data.get("haircut", [])) + [dict(e) for e in events]
    data["haircut"] = sorted(timeline, key=lambda e: e["frame"])
    def write(tmp):
        with open(tmp, "wb") as f:
            tomli_w.dump(data, f)

    write_whole(path, write)


def write_session_cache(session, path):
    """The frames simulated so far as a cache, hair topology per frame."""
    from io_usd.cache import CacheWriter

    from . import __version__
    from .scene import head_colors

    s, t = session.scene, session.config.timing
    frames = session.frames
    _, _, counts, widths, ids, _ = frames.read(0)
    with CacheWriter(path, t.fps, frames.numbers[0], frames.numbers[-1], settings=session.config.settings(),
                     engine_version=__version__) as writer:
        writer.add_mesh(s.collider_name, "collider", s.head.vertices, s.head.faces,
                        color=head_colors(s.head, session.config.hair.color))
        writer.add_curves("hair", "hair", counts, widths, color=session.config.hair.color, ids=ids)
        for frame, hair, counts, widths, ids, collider in frames:
            writer.write_frame(frame, {s.collider_name: collider, "hair": hair},
                               curves={"hair": (counts, widths, ids)})
        writer.set_metadata("cfx:haircut", {"events": len(session.events)})


class StudioWindow:
    """The studio's window: draws the session every tick and turns mouse strokes into edits."""

    def __init__(self, session, cache_path=None, script_path=None, fps=None, max_frames=None):
        from io_usd.viewer import _onscreen_pyrender

        self.pyrender = _onscreen_pyrender()
        import pyglet

        self.pyglet = pyglet
        self.session = session
        self.cache_path, self.script_path = cache_path, script_path
        self.max_frames = max_frames
        self.tool, self.paused, self.stroke = "blunt", False, None
        config = pyglet.gl.Config(major_version=4, minor_version=1, forward_compatible=True, depth_size=24,
                                  double_buffer=True)
        self.window = pyglet.window.Window(session.width, session.height, config=config,
                                           caption=f"cfx studio - {os.path.basename(session.config.source)}")
        self.renderer = self.pyrender.Renderer(session.width, session.height)
        from io_usd.preview import SceneBuilder

        self.reader = LiveReader(session.scene)
        self.builder = SceneBuilder(self.reader)
        self._counts = None
        w = self.window
        w.push_handlers(on_mouse_press=self.on_mouse_press, on_mouse_drag=self.on_mouse_drag,
                        on_mouse_release=self.on_mouse_release, on_key_press=self.on_key_press,
                        on_close=self.on_close)
        pyglet.clock.schedule_interval(self.tick, 1.0 / float(fps or session.config.timing.fps))

    def _pixel(self, x, y):
        return [float(x), float(self.session.height - y)]  # pyglet counts y up from the bottom

    def on_mouse_press(self, x, y, button, modifiers):
        self.stroke = [self._pixel(x, y)]

    def on_mouse_drag(self, x, y, dx, dy, buttons, modifiers):
        if self.stroke is not None:
            self.stroke.append(self._pixel(x, y))

    def on_mouse_release(self, x, y, button, modifiers):
        if self.stroke is None:
            return
        self.stroke.append(self._pixel(x, y))
        stroke, self.stroke = self.stroke, None
        if np.linalg.norm(np.subtract(stroke[-1], stroke[0])) < 2.0 and len(stroke) < 3:
            return  # a click, not a stroke
        self.session.apply(self.tool, stroke)

    def on_key_press(self, symbol, modifiers):
        key = self.pyglet.window.key
        name = key.symbol_string(symbol).lower().lstrip("_")
        if name in KEY_TOOLS:
            self.tool = KEY_TOOLS[name]
        elif name == "i":
            self.session.apply("initialise", [[0.0, 0.0]])
        elif name == "r":
            self.session.release()
        elif name in VIEWS:
            self.session.camera = self.session.view(VIEWS[name])
        elif name == "space":
            self.paused = not self.paused
        elif name == "p":
            self.screenshot()
        elif name == "s":
            self.save()
        elif name in ("q", "escape"):
            self.save()
            self.close()
            return True
        self.window.set_caption(f"cfx studio - {self.tool} - frame {self.session.frame}")
        return True

    def screenshot(self):
        folder = os.path.dirname(os.path.abspath(self.cache_path)) if self.cache_path else os.getcwd()
        path = os.path.join(folder, f"studio_frame_{self.session.frame}.png")
        self.draw()
        self.pyglet.image.get_buffer_manager().get_color_buffer().save(path)
        return path

    def on_close(self):
        self.close()
        return True

    def save(self):
        self.session.save(self.cache_path, self.script_path)

    def close(self):
        self.pyglet.clock.unschedule(self.tick)
        self.pyglet.app.exit()

    def tick(self, dt):
        s = self.session
        if not self.paused:
            s.step()
            if self.max_frames is not None and s.frame - s.config.timing.start_frame + 1 >= self.max_frames:
                self.paused = True
        self.draw()

    def draw(self):
        from io_usd.preview import build_scene

        s = self.session
        if self._counts is None or not np.array_equal(self._counts, s.scene.model.counts):
            self.reader.refresh()  # a cut or a grow changed the strands: new ribbons and colours
            from io_usd.preview import SceneBuilder

            self.builder = SceneBuilder(self.reader)
            self._counts = s.scene.model.counts.copy()
        scene = build_scene(self.builder, s.frame, s.camera)
        if self.stroke is not None and len(self.stroke) > 1:
            scene.add(self._stroke_mesh(self.stroke))
        self.window.switch_to()
        self.renderer.render(scene, self.pyrender.RenderFlags.NONE)
        self.window.flip()

    def _stroke_mesh(self, stroke):
        """The stroke being drawn, as a line just in front of the camera."""
        from .strokes import pixel_rays

        eye, directions = pixel_rays(self.session.camera, stroke)
        points = (eye + directions * (2.0 * self.session.camera.znear + 0.05)).astype(np.float32)
        material = self.pyrender.MetallicRoughnessMaterial(baseColorFactor=(1.0, 0.85, 0.1, 1.0),
                                                           emissiveFactor=(1.0, 0.85, 0.1))
        primitive = self.pyrender.Primitive(positions=points, mode=3, material=material)  # GL_LINE_STRIP
        return self.pyrender.Mesh([primitive])

    def run(self):
        self.pyglet.app.run()
