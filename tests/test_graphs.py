"""Frame-graph bookkeeping on the CPU: capture and replay are faked, so the sequence (eager, then
captured, then replayed), the restored buffer references and the fallback after a failed capture
are checked without a GPU (tests/test_gpu.py checks real graphs against eager frames)."""

import numpy as np
import pytest
import warp as wp

from sim.graphs import AsyncReadback, FrameGraphs


class FakeCapture:
    """Stands in for wp.ScopedCapture: records that a capture happened and hands out a token."""

    count = 0
    fail = False

    def __init__(self, device=None, **kwargs):
        self.graph = None

    def __enter__(self):
        if FakeCapture.fail:
            raise RuntimeError("operation not permitted when stream is capturing")
        FakeCapture.count += 1
        self.graph = f"graph{FakeCapture.count}"
        return self

    def __exit__(self, *exc):
        return False


@pytest.fixture
def fake_graphs(monkeypatch):
    launched = []
    FakeCapture.count, FakeCapture.fail = 0, False
    monkeypatch.setattr(wp, "ScopedCapture", FakeCapture)
    monkeypatch.setattr(wp, "capture_launch", lambda graph: launched.append(graph))
    graphs = FrameGraphs("cpu")
    graphs.enabled = True  # pretend the device can capture
    return graphs, launched


def test_frames_run_eager_then_captured_then_replayed_with_references_restored(fake_graphs):
    graphs, launched = fake_graphs
    buffers = ["a", "b"]
    calls = []

    def frame():  # an odd number of ping-pong swaps per frame, like 5 substeps
        calls.append(tuple(buffers))
        for _ in range(3):
            buffers.reverse()

    refs = (lambda: tuple(buffers)), (lambda value: buffers.__setitem__(slice(None), value))
    seen = []
    for _ in range(6):
        graphs.run(("hair", buffers[0]), frame, refs)
        seen.append(buffers[0])
    # every frame ends in the other buffer, with or without a graph
    assert seen == ["b", "a", "b", "a", "b", "a"]
    # two keys (one per starting buffer): each runs eagerly once, is captured (and launched) once,
    # then replays
    assert calls == [("a", "b"), ("b", "a"), ("a", "b"), ("b", "a")]
    assert launched == ["graph1", "graph2", "graph1", "graph2"] and graphs.replays == 4


def test_a_failed_capture_falls_back_to_eager_frames_without_losing_a_frame(fake_graphs):
    graphs, launched = fake_graphs
    FakeCapture.fail = True
    state = {"frames": 0, "buffer": "a"}

    def frame():
        state["frames"] += 1
        state["buffer"] = "b" if state["buffer"] == "a" else "a"

    refs = (lambda: state["buffer"]), (lambda value: state.__setitem__("buffer", value))
    with pytest.warns(RuntimeWarning, match="graph capture failed"):
        for _ in range(3):
            graphs.run("cloth", frame, refs)
    assert state["frames"] == 3 and state["buffer"] == "b"  # three real frames, references consistent
    assert not graphs.enabled and launched == []


def test_clear_forgets_captured_frames(fake_graphs):
    graphs, launched = fake_graphs
    for _ in range(3):
        graphs.run("detail", lambda: None)
    graphs.clear()
    graphs.run("detail", lambda: None)  # eager again after clear
    assert launched == ["graph1", "graph1"]


def test_async_readback_on_the_cpu_copies_at_once():
    a = wp.array(np.arange(12, dtype=np.float32).reshape(4, 3), dtype=wp.vec3)
    wait = AsyncReadback("cpu").begin({"x": a})
    a.fill_(wp.vec3(9.0, 9.0, 9.0))  # later work must not change what was read back
    np.testing.assert_array_equal(wait()["x"], np.arange(12, dtype=np.float32).reshape(4, 3))
