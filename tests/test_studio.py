"""The haircut studio: a session's edits are the scene file's timeline (its saved script repeats it
through `cfx run`), and the real window, driven by the mouse under Xvfb, cuts the hair."""

import os
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest

import sim
from io_usd.cache import CacheReader
from sim.studio import Session

SCENE = """
[scene]
fps = 24
frames = 200
preroll = 0.2
[head]
animation = "none"
[hair]
style = "straight"
count = 150
vertices = 14
length = 0.2
[solver]
substeps = 4
shape_matching = "simplified"
"""


def _lengths(points, counts):
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    ends = np.cumsum(counts)[:-1] - 1
    seg[ends] = 0.0
    return seg.sum()


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("studio") / "bob.toml"
    path.write_text(SCENE)
    return path


def _across_the_hair(session, fraction=0.55):
    """A horizontal stroke across the whole image at `fraction` of its height (below the ears,
    where the straight hair hangs on both sides of the face)."""
    v = fraction * session.height
    return [[5.0, v], [0.5 * session.width, v + 1.0], [session.width - 5.0, v]]


def test_session_edits_replay_from_the_saved_script(scene_file, tmp_path):
    session = Session(sim.load_scene(scene_file), width=320, height=240)
    for _ in range(2):
        session.step()
    before = _lengths(session.scene.state.x.numpy(), session.scene.model.counts)
    table = session.apply("blunt", _across_the_hair(session))
    assert table["tool"] == "blunt" and table["frame"] == session.frame
    after = _lengths(session.scene.state.x.numpy(), session.scene.model.counts)
    assert after < 0.9 * before
    for _ in range(3):
        session.step()
    script, cache = tmp_path / "session.toml", tmp_path / "session.usdc"
    session.save(cache, script)

    replay = sim.run_scene(sim.load_scene(script), tmp_path / "replay.usdc", progress=False)
    assert replay.frames == len(session.frames)
    ours, theirs = CacheReader(cache), CacheReader(tmp_path / "replay.usdc")
    last = session.frame
    np.testing.assert_allclose(theirs.points("hair", last), ours.points("hair", last), atol=1e-5)
    np.testing.assert_array_equal(theirs.counts("hair", last), ours.counts("hair", last))


def test_comb_lifts_hair_in_a_session_and_releases(scene_file):
    session = Session(sim.load_scene(scene_file), width=320, height=240)
    session.step()
    assert session.apply("comb", _across_the_hair(session, 0.5)) is not None
    grip = session.scene.held_comb
    held = session.scene.model.strand_start_np[grip.comb.strands] + grip.comb.grip
    start = session.scene.state.x.numpy()[held].copy()
    session.apply("comb", [[100.0, 150.0], [100.0, 110.0]])  # drag the comb 40 px up
    for _ in range(4):
        session.step()
    lifted = session.scene.state.x.numpy()[session.scene.model.strand_start_np[grip.comb.strands] + grip.grips()]
    assert np.all(lifted[:, 1] > start[:, 1] + 0.01)
    session.release()
    for _ in range(6):
        session.step()
    assert session.scene.solver.comb is None
    events = [e for e in session.events if e["tool"] == "comb"]
    assert len(events) == 1 and events[0]["release"] > events[0]["frame"] and events[0]["moves"]


def _free_display():
    """A display number no live X server holds: a lock left by a server that was killed names a
    process that is gone, and the next server removes such a lock and its socket itself."""
    for n in range(90, 120):
        lock = f"/tmp/.X{n}-lock"
        if not os.path.exists(lock):
            if not os.path.exists(f"/tmp/.X11-unix/X{n}"):
                return f":{n}"
            continue
        try:
            pid = int(open(lock).read().strip())
            os.kill(pid, 0)
        except ProcessLookupError:
            return f":{n}"
        except (ValueError, OSError):
            continue
    pytest.skip("no free X display number")


@pytest.mark.slow
@pytest.mark.skipif(not (shutil.which("Xvfb") and shutil.which("xdotool")), reason="needs Xvfb and xdotool")
def test_studio_window_cuts_hair_with_the_mouse(scene_file, tmp_path):
    display = _free_display()
    xvfb = subprocess.Popen(["Xvfb", display, "-screen", "0", "800x600x24"], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    env = {**os.environ, "DISPLAY": display}
    env.pop("PYOPENGL_PLATFORM", None)
    script, cache = tmp_path / "window.toml", tmp_path / "window.usdc"
    studio = None
    try:
        time.sleep(1.0)
        studio = subprocess.Popen([sys.executable, "-m", "sim.cli", "studio", str(scene_file), "--cache", str(cache),
                                   "--script", str(script), "--size", "320x240", "--max-frames", "6"], env=env,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

        def xdo(*args):
            return subprocess.run(["xdotool", *args], env=env, capture_output=True, text=True, timeout=120)

        found = xdo("search", "--sync", "--onlyvisible", "--name", "cfx studio")
        assert found.returncode == 0, found.stderr
        window = found.stdout.split()[0]
        time.sleep(3.0)  # let it run a few frames
        xdo("windowfocus", "--sync", window)
        xdo("key", "--window", window, "b")
        xdo("mousemove", "--window", window, "5", "132")
        xdo("mousedown", "1")
        for x in range(20, 321, 20):
            xdo("mousemove", "--window", window, str(min(x, 315)), "132")
        xdo("mouseup", "1")
        time.sleep(1.5)
        xdo("key", "--window", window, "q")
        out, err = studio.communicate(timeout=120)
        assert studio.returncode == 0, err
    finally:
        if studio is not None and studio.poll() is None:
            studio.kill()
        xvfb.terminate()  # not kill: on SIGTERM the server removes its lock and socket
        try:
            xvfb.wait(timeout=10)
        except subprocess.TimeoutExpired:
            xvfb.kill()
    import tomllib

    events = tomllib.loads(script.read_text())["haircut"]
    assert [e["tool"] for e in events] == ["blunt"]
    assert events[0]["stroke"][0][0] < 40 and events[0]["stroke"][-1][0] > 280
    reader = CacheReader(cache)
    frames = reader.frames()
    first, last = frames[0], frames[-1]
    assert _lengths(reader.points("hair", last), reader.counts("hair", last)) < \
        0.9 * _lengths(reader.points("hair", first), reader.counts("hair", first))


def test_recorded_frames_wait_on_disk_and_read_back_exactly(tmp_path):
    """A long session keeps its frames in a spool on disk, not in memory: each reads back bit for
    bit, an edit's re-record replaces the last, and closing removes the folder."""
    from sim.studio import FrameSpool

    rng = np.random.default_rng(2)
    spool = FrameSpool(folder=tmp_path)
    frames = []
    for frame in range(1, 5):
        counts = np.full(3 + frame % 2, 8, np.int64)
        record = (frame, rng.random((int(counts.sum()), 3)).astype(np.float32), counts,
                  rng.random(int(counts.sum())).astype(np.float32), np.arange(len(counts), dtype=np.int32),
                  rng.random((50, 3)).astype(np.float32))
        spool.append(*record)
        frames.append(record)
    spool.pop()
    spool.append(*frames[-1])
    assert len(spool) == 4 and spool.numbers == [1, 2, 3, 4]
    assert len(os.listdir(spool.folder)) == 4
    for got, want in zip(spool, frames, strict=True):
        assert got[0] == want[0]
        for a, b in zip(got[1:], want[1:], strict=True):
            np.testing.assert_array_equal(a, b)
            assert a.dtype == b.dtype
    assert spool.read(-1)[0] == 4
    folder = spool.folder
    spool.close()
    assert not os.path.exists(folder) and len(spool) == 0
