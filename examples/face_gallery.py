"""Every basic emotion and every mouth base of the built-in face, as one contact sheet.

    python examples/face_gallery.py out/face_gallery.png

Frames 1-7 hold the seven expressions (neutral and the six emotions as FACS action-unit mixes),
frames 8-13 the mouth bases a, i, u, e, o and closed, given as a mouth-parameter track; each tile is
labelled with its name.
"""

import os
import sys
import tempfile

import numpy as np

import sim
from io_usd.preview import preview


def main(out="out/face_gallery.png"):
    emotions = list(sim.EMOTIONS)
    keys = tuple(sim.ExpressionKey(frame=i + 1, emotion=name) for i, name in enumerate(emotions))
    keys += (sim.ExpressionKey(frame=len(emotions) + 1, emotion="neutral"),)
    mouth = np.zeros((len(emotions) + len(sim.VOWELS), 13))
    mouth[len(emotions):] = sim.VOWEL_SHAPES  # after the emotions, one vowel per frame
    with tempfile.TemporaryDirectory() as tmp:
        track = os.path.join(tmp, "mouth.npy")
        np.save(track, mouth)
        config = sim.hair_demo_scene({
            "scene": {"frames": len(mouth), "preroll": 0.0, "stats": False},
            "head": {"animation": "none"}, "hair": {"enabled": False},
            "face": {"enabled": True, "mouth": track, "audio_start": 1.0, "expressions": keys}})
        cache = os.path.join(tmp, "gallery.usdc")
        sim.run_scene(config, cache, progress=False)
        labels = emotions + [f"/{v}/" if v != "closed" else "closed mouth" for v in sim.VOWELS]
        preview(cache, out, frames=list(range(1, len(mouth) + 1)), width=360, height=360, columns=7, focus="face",
                labels=labels)
    print(f"wrote {out}: " + ", ".join(labels))


if __name__ == "__main__":
    main(*sys.argv[1:])
