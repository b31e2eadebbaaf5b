"""Capture segmentation: ms per image of sim.capture_solve.segment_image, which works in the window
around what differs from the background, against the peer, the same steps over the whole image (as
segment_image ran before session 33), on the same images in the same run. The last column says
whether the two found the same blobs to the bit (regions, order, areas, centroids).

A capture of the wind scene is synthesised for --frames frames unless --capture names one.

    python benchmarks/capture.py [--capture DIR] [--frames 2]
"""

import argparse
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from common import commit, fmt, table  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def segment_whole_image(image, background, params):
    """(channel, uv, area) of segment_image's regions with every step over the whole image and the
    centroids by ndimage.center_of_mass."""
    from scipy import ndimage

    from sim.capture_solve import _PLANE, clean_masks, color_masks

    masks = clean_masks(color_masks(image, background, params), params)
    labels, count = ndimage.label(masks, structure=_PLANE)
    area = np.bincount(labels.ravel(), minlength=count + 1)[1:]
    keep = np.nonzero(area >= params.min_area_px)[0] + 1
    if count == 0 or len(keep) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0, np.int64)
    centres = np.array(ndimage.center_of_mass(masks, labels, keep), np.float64).reshape(-1, 3)
    return np.rint(centres[:, 0]).astype(np.int64), centres[:, [2, 1]] + 0.5, area[keep - 1]


def synthesise(folder, frames):
    path = os.path.join(folder, "capture")
    subprocess.run([sys.executable, "-m", "sim.cli", "capture", "synth",
                    os.path.join(ROOT, "examples", "scenes", "capture_wind.toml"), "-o", path, "--frames",
                    str(frames), "--seed", "3", "-q"], check=True, cwd=ROOT, capture_output=True,
                   env={**os.environ, "PYTHONPATH": ROOT})
    return path


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--capture", help="a capture directory (default: synthesised for --frames)")
    parser.add_argument("--frames", type=int, default=2)
    args = parser.parse_args(argv)

    from sim.capture_solve import SegmentParams, load_capture, read_image, segment_image

    with tempfile.TemporaryDirectory() as folder:
        capture = load_capture(args.capture or synthesise(folder, args.frames))
        params = SegmentParams()
        pairs = [(read_image(capture.image_path(cam.name, frame), capture.image_size),
                  read_image(capture.background_path(cam.name), capture.image_size))
                 for cam in capture.cameras for frame in capture.frames]
    ours, theirs, same = 0.0, 0.0, True
    for image, background in pairs:
        start = time.perf_counter()
        found = segment_image(image, background, params)
        ours += time.perf_counter() - start
        start = time.perf_counter()
        channel, uv, area = segment_whole_image(image, background, params)
        theirs += time.perf_counter() - start
        same &= (np.array_equal(found.channel, channel) and np.array_equal(found.uv, uv)
                 and np.array_equal(found.area, area))
    n = len(pairs)
    width, height = capture.image_size
    print(f"# capture segmentation, commit {commit()}, {len(capture.cameras)} cameras x {len(capture.frames)} frames")
    print(table(["case", "images", "size", "device", "ms/image", "images/s", "whole image ms/image", "speed-up",
                 "same blobs"],
                [["segment_image with the background", n, f"{width}x{height}", "cpu (NumPy, SciPy)",
                  fmt(1e3 * ours / n), fmt(n / ours), fmt(1e3 * theirs / n), fmt(theirs / ours),
                  "yes" if same else "NO"]]))


if __name__ == "__main__":
    main()
