"""The face from the command line: cfx lipsync end to end, its errors, and previews focused on the face."""

import numpy as np

from io_usd import CacheReader
from sim.cli import main


def test_lipsync_writes_a_talking_face(tmp_path, capsys):
    from sim import lipsync

    wav = tmp_path / "line.wav"
    samples = lipsync.load_audio(lipsync.DEMO_LINE_PATH)[: int(1.2 * lipsync.SAMPLE_RATE)]
    lipsync.write_wav(wav, samples)
    out = tmp_path / "talk.usdc"
    png = tmp_path / "talk.png"
    assert main(["lipsync", str(wav), "-o", str(out), "--fps", "12", "--expression", "happiness",
                 "--preview", str(png), "-q"]) == 0
    reader = CacheReader(str(out))
    assert reader.prims["face"].role == "face"
    frames = reader.frames("face")
    assert len(frames) == int(np.ceil(1.2 * 12)) + 2
    p = np.stack([reader.points("face", f) for f in frames])
    moved = np.linalg.norm(p - p[:1], axis=2).max(axis=1)
    assert moved.max() > 0.004  # the mouth moves with the words
    assert png.stat().st_size > 10_000
    capsys.readouterr()
    assert main(["info", str(out)]) == 0  # the rig has no role, and info lists it all the same
    rig = [line for line in capsys.readouterr().out.splitlines() if "/World/face_rig" in line]
    assert len(rig) == 1 and "UsdSkel rig, 26 blend shapes" in rig[0]


def test_lipsync_speaks_the_builtin_line(tmp_path):
    """`builtin` names the demo's line, as a scene's audio = "builtin" does."""
    from sim import lipsync

    out = tmp_path / "talk.usdc"
    assert main(["lipsync", "builtin", "-o", str(out), "--fps", "6", "-q"]) == 0
    seconds = len(lipsync.load_audio(lipsync.DEMO_LINE_PATH)) / lipsync.SAMPLE_RATE
    assert len(CacheReader(str(out)).frames("face")) == int(np.ceil(seconds * 6)) + 2


def test_lipsync_rejects_a_file_that_is_not_audio(tmp_path, capsys):
    bad = tmp_path / "notes.wav"
    bad.write_text("not audio")
    assert main(["lipsync", str(bad), "-o", str(tmp_path / "x.usdc"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "notes.wav" in err and err.count("\n") == 1
    assert not (tmp_path / "x.usdc").exists()


def test_preview_focus_names_what_it_cannot_find(tmp_path, capsys):
    import sim

    out = tmp_path / "head.usdc"
    sim.run_scene(sim.hair_demo_scene({"scene": {"frames": 1, "preroll": 0.0}, "hair": {"enabled": False}}), out,
                  progress=False)
    assert main(["preview", str(out), "-o", str(tmp_path / "p.png"), "--focus", "face", "-q"]) == 2
    assert "nothing to focus on called 'face'" in capsys.readouterr().err


def test_lipsync_names_the_option_a_bad_value_came_from(tmp_path, capsys):
    """The command builds a scene from its options: an error names the option, not the scene key."""
    from sim import lipsync

    wav = tmp_path / "line.wav"
    lipsync.write_wav(wav, lipsync.load_audio(lipsync.DEMO_LINE_PATH)[: int(0.3 * lipsync.SAMPLE_RATE)])
    out = tmp_path / "x.usdc"
    for options, named in [(["--intensity", "3", "--expression", "happiness"], "--intensity: must be from 0 to 1"),
                           (["--intensity=-0.5"], "--intensity: must be from 0 to 1"),
                           (["--fps", "0"], "--fps: must be from 1 to 10000 frames a second"),
                           (["--voice", str(tmp_path / "no_such_speaker")], "--voice: expected one of")]:
        assert main(["lipsync", str(wav), "-o", str(out), "-q", *options]) == 2, options
        err = capsys.readouterr().err
        assert named in err and err.count("\n") == 1 and "<lipsync>" not in err
        assert not out.exists()
