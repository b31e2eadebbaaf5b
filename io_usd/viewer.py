"""Interactive playback of a cache in pyrender's on-screen viewer.

pyrender is imported only inside `view`. PyOpenGL fixes its platform when first imported; the
offscreen preview asks for EGL, while a window needs the default (GLX / Cocoa) one, so merely
importing this module must not load either.
"""

import os
import sys
import time

import numpy as np

from .cache import CacheReader

WINDOW = (960, 720)


def has_display():
    """pyglet opens windows through X11 (XWayland included, which sets DISPLAY) or Cocoa. A local X
    display (":N") must also answer on its socket: DISPLAY=:99 with no server behind it left cfx view
    hanging after a thread's traceback."""
    if sys.platform == "darwin":
        return True
    display = os.environ.get("DISPLAY", "")
    if not display:
        return False
    host, _, number = display.partition(":")
    if host not in ("", "unix") or not number.split(".")[0].isdigit():
        return True  # a remote or unusual display: pyglet will say what is wrong
    import socket

    path = f"/tmp/.X11-unix/X{number.split('.')[0]}"
    for address in (path, "\0" + path):  # the file, or Linux's abstract socket of the same name
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
            probe.settimeout(1.0)
            try:
                probe.connect(address)
                return True
            except OSError:
                continue
    return False


def _onscreen_pyrender():
    if os.environ.get("PYOPENGL_PLATFORM") == "egl":
        if "OpenGL" in sys.modules:
            raise RuntimeError("cfx view: this process already loaded OpenGL for offscreen (EGL) rendering; "
                               "run cfx view in a fresh process")
        del os.environ["PYOPENGL_PLATFORM"]
    if not hasattr(np, "infty"):  # pyrender 0.1.45 still uses the alias numpy 2 removed
        np.infty = np.inf
    import pyrender

    return pyrender


def play(viewer, builder, nodes, frames, fps, loop=True, clock=time.monotonic, sleep=time.sleep):
    """Step the viewer's scene through `frames` at `fps` until the window closes.

    Ribbons are rebuilt to face the viewer's current camera every tick, also once playback has
    stopped on the last frame, so orbiting never shows strands edge-on. `nodes` maps prim name to
    its scene node and is updated in place. Ctrl-C (KeyboardInterrupt) closes the window before it
    propagates: the window's thread would otherwise keep the process alive.
    """
    try:
        _play(viewer, builder, nodes, frames, fps, loop, clock, sleep)
    except KeyboardInterrupt:
        viewer.close_external()
        raise


def _play(viewer, builder, nodes, frames, fps, loop, clock, sleep):
    scene = viewer.scene
    period = 1.0 / fps
    i, deadline = 0, clock()
    while viewer.is_active:
        with viewer.render_lock:
            pose = scene.get_pose(scene.main_camera_node)
            yfov = getattr(scene.main_camera_node.camera, "yfov", 1.0)
        focal = 0.5 * viewer.viewport_size[1] / np.tan(0.5 * yfov)
        meshes = builder.meshes(frames[i], pose[:3, 3], focal)  # outside the lock: the window stays responsive
        with viewer.render_lock:
            for name, mesh in meshes.items():
                if name in nodes:
                    scene.remove_node(nodes[name])
                nodes[name] = scene.add(mesh, name=name)
        if i + 1 < len(frames):
            i += 1
        elif loop:
            i = 0
        # after a stall, carry on from now rather than rushing through frames to catch up
        deadline = max(deadline + period, clock())
        sleep(max(0.0, deadline - clock()))


def view(cache_path, fps=None, loop=True):
    """Open a window that plays the cache at its fps (or `fps`), looping unless loop=False; returns
    when the window is closed. Mouse orbits, scroll zooms (pyrender's viewer controls)."""
    cache_path = os.fspath(cache_path)
    if not os.path.isfile(cache_path):
        raise FileNotFoundError(f"{cache_path}: no such cache file")
    if not has_display():
        raise RuntimeError("cfx view needs a display (DISPLAY is not set); "
                           "render offscreen instead with `cfx preview CACHE -o out.png` (or .mp4, .gif)")
    pyrender = _onscreen_pyrender()
    from .preview import BACKGROUND, SceneBuilder, auto_camera, scene_points

    reader = CacheReader(cache_path)
    frames = reader.frames()
    fps = float(fps or reader.fps or 24.0)
    if fps <= 0:
        raise ValueError(f"{cache_path}: fps must be positive, got {fps}")
    camera = auto_camera(reader, *WINDOW, frames)
    first = scene_points(reader, frames[:1])
    subject = 0.5 * (first.min(0) + first.max(0))  # what the mouse orbits about
    builder = SceneBuilder(reader)
    scene = pyrender.Scene(bg_color=np.array([*BACKGROUND, 1.0]), ambient_light=np.full(3, 0.25))
    # clip planes wider than the framing needs, so zooming in and out does not cut the subject
    scene.add(pyrender.PerspectiveCamera(yfov=camera.yfov, aspectRatio=camera.width / camera.height,
                                         znear=0.1 * camera.znear, zfar=10.0 * camera.zfar), pose=camera.pose)
    nodes = {name: scene.add(mesh, name=name)
             for name, mesh in builder.meshes(frames[0], camera.eye, camera.focal).items()}
    # the 'a' key turntable spins about the cache's Y up axis
    viewer = pyrender.Viewer(scene, viewport_size=WINDOW, run_in_thread=True, use_raymond_lighting=True,
                             view_center=subject, rotate_axis=np.array([0.0, 1.0, 0.0]),
                             window_title=f"cfx view - {os.path.basename(cache_path)}")
    play(viewer, builder, nodes, frames, fps, loop=loop)
