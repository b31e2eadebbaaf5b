"""Preview rendering: ms per image, ours (io_usd.preview.SupersampledOffscreen: drawn twice as large
with one sample per pixel and averaged down) against pyrender's own 4x multisampled framebuffer,
the peer, rendering the same pyrender scenes in the same run. The last column is how far apart the
two pictures are: the mean absolute difference over pixels and channels, in 8-bit grey levels.

Cases on the built-in demo (walking character, dress, 2,000 wavy strands, face), simulated for a few
frames unless --cache names a cache: the whole scene as `cfx preview` frames it, and a close-up of
the hair.

    python benchmarks/preview.py [--cache CACHE.usdc] [--size 960x720] [--frames 4]
"""

import argparse
import os
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from common import commit, fmt, table  # noqa: E402

from io_usd.cache import CacheReader  # noqa: E402
from io_usd.preview import Camera, FrameRenderer, SceneBuilder, _pyrender, auto_camera, build_scene  # noqa: E402


def _demo_cache(folder, frames):
    from sim.scene import demo_scene, run_scene

    path = os.path.join(folder, "demo.usdc")
    run_scene(demo_scene({"scene": {"frames": frames, "stats": False}}), path, progress=False)
    return path


def multisampled(reader, camera, frames):
    """(images, ms per image) through pyrender's OffscreenRenderer as it comes (4x multisampling)."""
    pyrender = _pyrender()
    builder = SceneBuilder(reader)
    gl = pyrender.OffscreenRenderer(camera.width, camera.height)
    flags = pyrender.RenderFlags.SHADOWS_DIRECTIONAL
    try:
        gl.render(build_scene(builder, frames[0], camera), flags=flags)  # shaders compiled
        start, images = time.perf_counter(), []
        for f in frames:
            images.append(np.ascontiguousarray(gl.render(build_scene(builder, f, camera), flags=flags)[0][:, :, :3]))
        return images, 1e3 * (time.perf_counter() - start) / len(frames)
    finally:
        gl.delete()


def supersampled(reader, camera, frames):
    """(images, ms per image) through FrameRenderer (supersampled)."""
    with FrameRenderer(reader, camera.width, camera.height) as renderer:
        renderer.render(frames[0], camera)
        start = time.perf_counter()
        images = [renderer.render(f, camera) for f in frames]
        return images, 1e3 * (time.perf_counter() - start) / len(frames)


def gl_renderer_name():
    pyrender = _pyrender()
    gl = pyrender.OffscreenRenderer(16, 16)
    try:
        from OpenGL.GL import GL_RENDERER, glGetString

        return glGetString(GL_RENDERER).decode()
    finally:
        gl.delete()


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cache", help="a cache to render (default: the demo, simulated for --frames)")
    parser.add_argument("--size", default="960x720", help="WIDTHxHEIGHT of the images")
    parser.add_argument("--frames", type=int, default=4, help="frames rendered per case (and simulated)")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.lower().split("x"))

    with tempfile.TemporaryDirectory() as folder:
        path = args.cache or _demo_cache(folder, args.frames)
        reader = CacheReader(path)
        frames = reader.frames()[-args.frames:]
        hair = [n for n, p in reader.prims.items() if p.role == "hair"]
        cases = [("whole scene", auto_camera(reader, width, height, frames))]
        if hair:
            strands = np.concatenate([reader.points(n, frames[-1]).reshape(-1, 3) for n in hair])
            cases.append(("hair close-up", Camera.frame_points(strands, width, height)))
        device = gl_renderer_name()
        rows = []
        for name, camera in cases:
            ours, ours_ms = supersampled(reader, camera, frames)
            theirs, theirs_ms = multisampled(reader, camera, frames)
            apart = np.mean([np.abs(a.astype(np.int16) - b.astype(np.int16)).mean() for a, b in zip(ours, theirs)])
            rows.append([name, f"{width}x{height}", device, fmt(ours_ms), fmt(1e3 / ours_ms), fmt(theirs_ms),
                         fmt(theirs_ms / ours_ms), fmt(float(apart), 2)])
    print(f"# preview rendering, commit {commit()}, {len(frames)} frames per case")
    print(table(["case", "size", "GL renderer", "ms/image", "images/s", "pyrender 4x MSAA ms/image",
                 "speed-up", "mean abs difference, grey levels"], rows))


if __name__ == "__main__":
    main()
