"""A tiny stripe-dyed capture scene shared by the capture rig and solver tests: a few straight
strands on the turning bust in a breeze, a few frames, small images."""

_BASE = """
[scene]
fps = 24
frames = {frames}
preroll = 0.1
stats = false

[head]
animation = "turn"
turn_degrees = 8.0

[hair]
style = "straight"
count = 60
length = {length}
length_jitter = 0.05
vertices = 12
# straight out of the scalp, as the capture tests' bounds were set on: the default lift (30 degrees)
# lays the roots along the head, where the ring sees a point from 4.0 cameras on average instead of
# 4.7 and the tiny rig's guides triangulate to 2.2 mm RMS instead of 1.0 (session 40)
root_lift = 90

[solver]
substeps = 2
wind = [1.5, 0.0, 1.0]

[capture]
"""


def tiny_capture_scene(frames, length, capture):
    """Scene TOML text: `frames` frames of hair `length` m long; `capture` holds the [capture] keys."""
    return _BASE.format(frames=frames, length=length) + capture
