"""The cfx command: runs scenes to caches, reports bad input with file, key and exit status 2."""

import os
import subprocess
import sys

import numpy as np
import pytest

from io_usd import CacheReader, validation_errors
from sim.cli import main

SMALL = """
[scene]
fps = 24
frames = 3
preroll = 0.0

[head]
animation = "turn"
sphere_leaves = 48

[hair]
style = "straight"
count = 40
vertices = 8
length = 0.12

[solver]
substeps = 4
"""


def write(tmp_path, text, name="scene.toml"):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def test_run_writes_a_valid_cache_and_info_lists_it(tmp_path, capsys):
    scene = write(tmp_path, SMALL)
    out = str(tmp_path / "out" / "hair.usdc")
    assert main(["run", scene, "-o", out, "-q"]) == 0
    reader = CacheReader(out)
    assert reader.frames("hair") == [1, 2, 3]
    assert reader.prims["hair"].role == "hair" and len(reader.prims["hair"].counts) == 40
    assert reader.prims["head"].role == "collider"
    assert validation_errors(out) == []
    capsys.readouterr()
    assert main(["info", out, "--validate"]) == 0
    text = capsys.readouterr().out
    assert "role=hair" in text and "40 curves, 320 points" in text and "0 errors" in text
    # a publish gate: an interrupted run's cache (cfx:complete false) fails --validate
    from pxr import Sdf

    layer = Sdf.Layer.FindOrOpen(out)
    layer.customLayerData = dict(layer.customLayerData, **{"cfx:complete": False})
    layer.Save()
    assert main(["info", out]) == 0 and main(["info", out, "--validate"]) == 1
    assert "complete: NO" in capsys.readouterr().out


def test_the_hairs_colour_reaches_the_cache_and_the_preview(tmp_path, capsys):
    """[hair] color is the curves' displayColor, which the preview draws: blond hair renders lighter
    than the default brown where the two images differ (the strands); the groom is not grown again
    for a new colour (its shape is the same), and a colour out of range is a one-line error."""
    from PIL import Image

    from sim.asset_cache import cache_dir

    blond = (0.85, 0.66, 0.36)
    images = {}
    for name, extra in (("brown", ""), ("blond", f"color = {list(blond)}\n")):
        scene = write(tmp_path, SMALL.replace("[hair]\n", "[hair]\n" + extra), f"{name}.toml")
        out, still = str(tmp_path / f"{name}.usdc"), str(tmp_path / f"{name}.png")
        grooms = sorted(p.name for p in cache_dir().glob("groom*")) if cache_dir() else None
        assert main(["run", scene, "-o", out, "-q", "--preview", still]) == 0
        if name == "blond" and grooms is not None:
            assert sorted(p.name for p in cache_dir().glob("groom*")) == grooms
        images[name] = np.asarray(Image.open(still).convert("RGB")).astype(int)
    np.testing.assert_allclose(CacheReader(str(tmp_path / "blond.usdc")).prims["hair"].color, blond, atol=1e-6)
    strands = np.abs(images["blond"] - images["brown"]).max(axis=2) > 30
    assert strands.sum() > 200
    assert images["blond"][strands].mean() > images["brown"][strands].mean() + 40
    capsys.readouterr()
    bad = write(tmp_path, SMALL.replace("[hair]\n", "[hair]\ncolor = [1.2, 0.5, 0.5]\n"), "bad.toml")
    assert main(["run", bad, "-o", str(tmp_path / "bad.usdc"), "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "bad.toml: hair.color: color must be three linear RGB values" in err, err
    assert not (tmp_path / "bad.usdc").exists()


def test_preview_command_renders_a_still_and_a_contact_sheet(tmp_path, capsys):
    scene = write(tmp_path, SMALL)
    out = str(tmp_path / "hair.usdc")
    assert main(["run", scene, "-o", out, "-q"]) == 0
    capsys.readouterr()
    from PIL import Image

    still, sheet = tmp_path / "still.png", tmp_path / "sheet.png"
    assert main(["preview", out, "-o", str(still), "--size", "160x120", "-q"]) == 0
    assert Image.open(still).size == (160, 120)
    assert main(["preview", out, "-o", str(sheet), "--frames", "1:3", "--size", "160x120", "-q"]) == 0
    assert Image.open(sheet).size == (320, 240)  # 3 frames in a 2 x 2 grid
    views = tmp_path / "views.png"
    assert main(["preview", out, "-o", str(views), "--view", "turnaround", "--view", "20,35", "--size", "160x120",
                 "-q"]) == 0
    assert Image.open(views).size == (5 * 160, 120)
    assert capsys.readouterr().err == ""  # -q: no progress bar either
    assert main(["preview", out, "-o", str(tmp_path / "x.png"), "--frames", "9", "-q"]) == 2
    assert main(["preview", out, "-o", str(tmp_path / "x.png"), "--frames", "5:9", "-q"]) == 2  # none of them
    sheet.unlink()
    assert main(["preview", out, "-o", str(sheet), "--frames", "1:72:2", "--size", "160x120", "-q"]) == 0
    assert Image.open(sheet).size == (320, 120)  # the frames of the range the cache has: 1 and 3
    # a malformed size and one beyond what the GL draws: one line each, exit 2, nothing written
    capsys.readouterr()
    for flag, value, reason in (("--size", "160x120x", "--size: expected WIDTHxHEIGHT in pixels"),
                                ("--size", "100000x120", "image size 100000x120: larger than this GL draws"),
                                ("--frames", "abc", "--frames: expected a frame (12), a list"),
                                ("--frames", "1:3:0", "with a positive step (1:72:12), got '1:3:0'"),
                                ("--frames", "3:1", "--frames: expected"),
                                ("--view", "side", "y.png: unknown view 'side'"),
                                ("--view", "10,x", "--view: expected a view name or YAW,PITCH")):
        assert main(["preview", out, "-o", str(tmp_path / "y.png"), flag, value, "-q"]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and reason in err, err
    assert not (tmp_path / "y.png").exists()


@pytest.mark.parametrize("command", ["info", "preview"])
def test_a_file_that_is_not_usd_exits_2_with_one_line(tmp_path, capsys, command):
    text = tmp_path / "notes.usdc"
    text.write_text("not a cache")
    args = [command, str(text)] + (["-o", str(tmp_path / "x.png")] if command == "preview" else [])
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and str(text) in err and "not a USD file" in err
    assert not (tmp_path / "x.png").exists()


def test_view_without_a_display_exits_2(tmp_path, monkeypatch, capsys):
    scene = write(tmp_path, SMALL)
    out = str(tmp_path / "hair.usdc")
    assert main(["run", scene, "-o", out, "-q"]) == 0
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert main(["view", out]) == 2
    assert "display" in capsys.readouterr().err
    # a DISPLAY with no X server behind it hung cfx view after a thread's traceback (a QA pass)
    free = next(n for n in range(500, 600) if not os.path.exists(f"/tmp/.X11-unix/X{n}"))
    monkeypatch.setenv("DISPLAY", f":{free}")
    assert main(["view", out]) == 2 and main(["studio", scene]) == 2
    assert capsys.readouterr().err.count("has no X server") == 2


@pytest.mark.parametrize("text,where,reason", [
    (SMALL.replace("count = 40", "cout = 40"), "hair.cout", "did you mean 'count'"),
    (SMALL.replace("fps = 24", 'fps = "fast"'), "scene.fps", "expected a number"),
    (SMALL.replace('style = "straight"', 'style = "afro"'), "hair.style", "must be one of"),
    (SMALL.replace("substeps = 4", "substeps = 0"), "solver.substeps", "at least 1"),
    (SMALL + "\n[wind]\nspeed = 3\n", "[wind]", "unknown table"),
    (SMALL.replace("[head]", '[head]\nmesh = "missing.obj"'), "head.mesh", "file not found"),
    (SMALL.replace("frames = 3", "frames = [3"), "", "not valid TOML"),
    (SMALL.replace("[solver]", "[solver]\ngravity = [0, -9.8]"), "solver.gravity", "list of 3"),
    (SMALL.replace("preroll = 0.0", 'preroll = 0.0\nhair_frames = "blocks"'), "scene.hair_frames", "must be"),
    (SMALL + '\n[face]\n[[face.expressions]]\nframe = 1\nemotion = "fear"\nweight = 3.0\n',
     "face.expressions[0].weight", "from 0 to 1"),
    (SMALL + '\n[face]\n[[face.expressions]]\nframe = 1\naus = { "12" = -1 }\n', "face.expressions[0].aus.12",
     "from 0 to 1"),
    (SMALL.replace("preroll = 0.0", 'preroll = 0.0\nhair_frames = "in_block"').replace("vertices = 8", "vertices = 70"),
     "scene.hair_frames", "at most 64 particles"),
    (SMALL.replace("preroll = 0.0", 'preroll = 0.0\nhair_frames = "in_warps"').replace("vertices = 8", "vertices = 40"),
     "scene.hair_frames", "at most 32 particles"),
])
def test_bad_scene_files_exit_2_naming_the_key(tmp_path, capsys, text, where, reason):
    scene = write(tmp_path, text)
    out = tmp_path / "never.usdc"
    assert main(["run", scene, "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert scene in err and where in err and reason in err
    assert not out.exists()



def test_hair_frames_in_block_write_the_cache_of_the_substeps(tmp_path):
    """[scene] hair_frames = "in_block" (each hair frame one launch, a block of lanes per strand) and
    "in_warps" (32 strands a block) write the cache the substeps write: the same curves, bit for bit on
    the CPU, on a turning head with the sphere tree."""
    text = SMALL.replace("[solver]", '[solver]\ncollision = "sphere_tree"\nshape_matching = "simplified"')
    caches = []
    for way in ("substeps", "in_block", "in_warps"):
        scene = write(tmp_path, text.replace("preroll = 0.0", f'preroll = 0.0\nhair_frames = "{way}"'), f"{way}.toml")
        out = str(tmp_path / f"{way}.usdc")
        assert main(["run", scene, "-o", out, "-q"]) == 0
        assert validation_errors(out) == []
        caches.append(CacheReader(out))
    for frame in (1, 3):
        a, *others = (cache.points("hair", frame) for cache in caches)
        for b in others:
            np.testing.assert_array_equal(b, a)
    assert np.abs(caches[1].points("hair", 3) - caches[1].points("hair", 1)).max() > 1e-3

def test_missing_scene_file_exits_2(tmp_path, capsys):
    assert main(["run", str(tmp_path / "nope.toml"), "-o", str(tmp_path / "x.usdc")]) == 2
    assert "nope.toml" in capsys.readouterr().err


def test_exploding_simulation_is_reported_with_frame_and_prim(tmp_path, capsys):
    scene = write(tmp_path, SMALL.replace("[solver]", "[solver]\ngravity = [0.0, -1000.0, 0.0]\nmax_speed = 5.0"))
    out = tmp_path / "boom.usdc"
    assert main(["run", scene, "-o", str(out), "-q"]) == 3
    err = capsys.readouterr().err
    assert "frame 2" in err and "/World/hair" in err
    assert os.listdir(tmp_path) == ["scene.toml"]


def test_scene_can_use_its_own_head_mesh_and_roots(tmp_path, head):
    import trimesh

    trimesh.Trimesh(head.vertices, head.faces).export(tmp_path / "bust.obj")
    top = head.vertices[head.vertices[:, 1] > 0.44]
    np.save(tmp_path / "roots.npy", top[:12])
    scene = write(tmp_path, SMALL.replace("[head]", '[head]\nmesh = "bust.obj"\nroots = "roots.npy"'))
    out = str(tmp_path / "own.usdc")
    assert main(["run", scene, "-o", out, "-q"]) == 0
    reader = CacheReader(out)
    assert len(reader.prims["hair"].counts) == 12
    first = reader.points("hair", 1).reshape(12, 8, 3)[:, 0]
    np.testing.assert_allclose(first, top[:12], atol=1e-4)


def test_collider_and_root_files_a_qa_pass_broke_are_refused_in_one_line(tmp_path, head, capsys):
    """A head in centimetres, a flat head, roots off the head, a body whose points all sit in one spot
    or that has no frames: each exploded the hair (exit 3), ran in silence or raised a traceback."""
    import trimesh

    trimesh.Trimesh(head.vertices, head.faces).export(tmp_path / "bust.obj")
    trimesh.Trimesh(100.0 * head.vertices, head.faces).export(tmp_path / "bust_cm.obj")
    trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], [[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]],
                    process=False).export(tmp_path / "flat.obj")
    np.save(tmp_path / "far.npy", [[0.0, 3.0, 0.0]])
    box = trimesh.creation.box()
    box.export(tmp_path / "box.obj")
    np.save(tmp_path / "still.npy", np.zeros((2, len(box.vertices), 3)))
    np.save(tmp_path / "none.npy", np.zeros((0, len(box.vertices), 3)))
    no_hair = SMALL.replace("[hair]", "[hair]\nenabled = false")
    for text, reason in (
        (SMALL.replace("[head]", '[head]\nmesh = "bust_cm.obj"'), "head.mesh: bust_cm.obj spans 47.2 m; meshes are "
                                                                  "read in metres"),
        (SMALL.replace("[head]", '[head]\nmesh = "flat.obj"'), "head.mesh: flat.obj encloses no volume"),
        (SMALL.replace("[head]", '[head]\nmesh = "bust.obj"\nroots = "far.npy"'),
         "head.roots: 1 of 1 roots lie more than 5 cm off the head"),
        (no_hair + '[body]\nmesh = "box.obj"\npoints = "still.npy"\n', "body.points: still.npy: no face has any area"),
        (no_hair + '[body]\nmesh = "box.obj"\npoints = "none.npy"\n', "body.points: holds no frames"),
    ):
        scene = write(tmp_path, text)
        assert main(["run", scene, "-o", str(tmp_path / "x.usdc"), "-q"]) == 2
        err = capsys.readouterr().err
        assert reason in err and err.count("\n") == 1, err
    assert not (tmp_path / "x.usdc").exists()


def test_cfx_entry_point_runs_as_a_module():
    proc = subprocess.run([sys.executable, "-m", "sim.cli", "--version"], capture_output=True, text=True)
    assert proc.returncode == 0 and "warp-cfx" in proc.stdout


def test_the_package_loads_its_parts_on_first_use():
    """`cfx --help` and `cfx info` start without Warp; `sim.X` loads X's submodule the first time."""
    code = ("import sys, sim, sim.cli; assert 'warp' not in sys.modules and 'scipy' not in sys.modules; "
            "assert 'HairParams' in dir(sim) and sim.HairParams().substeps > 0 and 'warp' in sys.modules; "
            "from sim import Scene, run_scene; assert sim.Scene is Scene; "
            "sim.no_such_name")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=os.getcwd(),
                          env=dict(os.environ, PYTHONPATH=os.getcwd()))
    assert proc.returncode == 1 and proc.stderr.strip().endswith("AttributeError: module 'sim' has no attribute "
                                                                 "'no_such_name'"), proc.stderr


@pytest.mark.slow
@pytest.mark.parametrize("signum", ["SIGTERM", "SIGHUP"])
def test_a_run_stopped_by_a_farm_or_a_closed_terminal_leaves_nothing_and_says_so(tmp_path, signum):
    """SIGTERM (a farm's cancel) and SIGHUP (an ssh drop) stop a run as Ctrl-C does: the partial cache
    beside the output is removed, exit status 128 + the signal, one line saying so."""
    import signal
    import time

    scene = write(tmp_path, SMALL.replace("frames = 3", "frames = 100000"))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([os.getcwd(), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.Popen([sys.executable, "-m", "sim.cli", "run", scene, "-o", str(tmp_path / "c.usdc"), "-q"],
                            stderr=subprocess.PIPE, text=True, env=env)
    try:
        deadline = time.monotonic() + 300.0  # a cold kernel cache compiles first
        while not any(".partial-" in p.name for p in tmp_path.iterdir()) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert proc.poll() is None
        time.sleep(0.5)  # some frames written
        proc.send_signal(getattr(signal, signum))
        _, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 128 + getattr(signal, signum), err
    assert err.strip().splitlines()[-1] == f"cfx: error: stopped by {signum}; no output was written"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.toml"]


def test_quiet_run_prints_nothing_to_stderr(tmp_path):
    """-q on a CPU machine: no progress bar and no Warp start-up lines (its native no-CUDA-driver
    warning included), only the summary."""
    scene = write(tmp_path, SMALL)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([os.getcwd(), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run([sys.executable, "-m", "sim.cli", "run", scene, "-o", str(tmp_path / "c.usdc"), "-q"],
                          capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stderr.splitlines()
    assert lines[0].startswith("wrote ") and all(line.startswith("  ") for line in lines[1:]), proc.stderr


def test_warp_start_up_drops_only_the_no_driver_line(monkeypatch, capfd):
    import warp as wp

    from sim import scene as scene_module

    def noisy_init():  # what warp.so writes straight to descriptor 2, around another line
        os.write(2, b"Warp CUDA warning: Could not find or load the NVIDIA CUDA driver. GPU execution will not "
                    b"be available.\nsomething else Warp says\n")

    monkeypatch.setattr(wp, "init", noisy_init)
    scene_module.quiet_warp()
    err = capfd.readouterr().err
    assert err == "something else Warp says\n"


def test_bad_output_path_and_missing_device_fail_before_simulating(tmp_path, capsys):
    import warp as wp

    scene = write(tmp_path, SMALL)
    assert main(["run", scene, "-o", str(tmp_path / "cache.abc"), "-q"]) == 2
    assert "must end in .usd, .usdc or .usda" in capsys.readouterr().err
    if not wp.is_cuda_available():
        assert main(["run", scene, "-o", str(tmp_path / "c.usdc"), "--device", "cuda", "-q"]) == 2
        err = capsys.readouterr().err
        assert "scene.device" in err and "not available" in err
    assert os.listdir(tmp_path) == ["scene.toml"]


def test_outputs_that_cannot_be_written_fail_before_simulating(tmp_path, capsys):
    """A folder where the cache should go, a preview of an unknown type or under a file: each one line
    naming the path, exit 2, before any frame is simulated, and nothing written."""
    scene = write(tmp_path, SMALL)
    (tmp_path / "folder.usdc").mkdir()
    (tmp_path / "afile").write_text("")
    cache = str(tmp_path / "c.usdc")
    for args, reason in [(["-o", str(tmp_path / "folder.usdc")], "folder.usdc: is a folder; name a file in it"),
                         (["-o", cache, "--preview", str(tmp_path / "p.bmp")], "the preview must end in .png"),
                         (["-o", cache, "--preview", str(tmp_path / "afile" / "p.png")], "afile is not a folder")]:
        assert main(["run", scene, "-q", *args]) == 2
        err = capsys.readouterr().err
        assert reason in err and err.count("\n") == 1 and "partial" not in err
    assert sorted(os.listdir(tmp_path)) == ["afile", "folder.usdc", "scene.toml"]
    assert os.listdir(tmp_path / "folder.usdc") == []


def test_scalp_mask_decides_where_hair_grows(tmp_path, head):
    top = np.flatnonzero(head.vertices[head.faces].mean(1)[:, 1] > 0.45)  # a crown patch
    np.save(tmp_path / "crown.npy", top)
    scene = write(tmp_path, SMALL.replace("[head]", '[head]\nscalp_faces = "crown.npy"'))
    out = str(tmp_path / "crown.usdc")
    assert main(["run", scene, "-o", out, "-q"]) == 0
    roots = CacheReader(out).points("hair", 1).reshape(40, 8, 3)[:, 0]
    assert roots[:, 1].min() > 0.445  # every root on the crown patch (its lowest corner is above 0.445 m)
    bad = write(tmp_path, SMALL.replace("[head]", '[head]\nscalp_faces = "crown.npy"'), "bad.toml")
    np.save(tmp_path / "crown.npy", np.array([10 ** 7]))
    assert main(["run", bad, "-o", str(tmp_path / "bad.usdc"), "-q"]) == 2


def test_follow_camera_keeps_a_moving_subject_centred(tmp_path):
    """A ball that moves 2 m stays in the middle of every tile with --follow, not without."""
    import trimesh
    from PIL import Image

    from io_usd.cache import CacheWriter

    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.2)
    out = str(tmp_path / "moving.usdc")
    with CacheWriter(out, 24, 1, 3) as w:
        w.add_mesh("ball", "collider", ball.vertices, ball.faces)
        for f in (1, 2, 3):
            w.write_frame(f, {"ball": ball.vertices + [(f - 1) * 1.0, 0.0, 0.0]})
    spread = {}
    for follow in (False, True):
        png = tmp_path / f"sheet_{follow}.png"
        args = ["preview", out, "-o", str(png), "--frames", "1,3", "--size", "160x120", "-q"] + (["--follow"] if follow else [])
        assert main(args) == 0
        img = np.asarray(Image.open(png).convert("L")).astype(float)
        centres = []
        for tile in (img[:120, :160], img[:120, 160:320]):
            mask = np.abs(tile - tile[-5, -5]) > 20  # away from the label in the top-left corner
            mask[:30, :70] = False  # the frame label
            centres.append(np.argwhere(mask)[:, 1].mean())
        spread[follow] = abs(centres[0] - centres[1])
    assert spread[True] < 5.0 < spread[False]


def test_a_run_says_when_the_curls_are_too_coarse_to_draw_as_curves(tmp_path, capsys):
    """Curls whose segments turn more than SMOOTH_TURN draw as zigzags: the report says so with the
    vertices that would do; a groom sampled finely enough gets no such line."""
    coarse = SMALL.replace('style = "straight"', 'style = "curly"\ncurl_radius = 0.009\ncurl_pitch = 0.03')
    assert main(["run", write(tmp_path, coarse), "-o", str(tmp_path / "coarse.usdc"), "-q"]) == 0
    err = capsys.readouterr().err
    assert "hair: the curls turn up to" in err and "draw as zigzags" in err
    from sim.hairstyle import HairstyleParams

    needed = HairstyleParams(style="curly", vertices=8, length=0.12, curl_radius=0.009,
                             curl_pitch=0.03).vertices_for_smooth_curves()
    assert f"[hair] vertices = {needed})" in err
    fine = coarse.replace("vertices = 8", f"vertices = {needed}")
    assert main(["run", write(tmp_path, fine, "fine.toml"), "-o", str(tmp_path / "fine.usdc"), "-q"]) == 0
    assert "zigzags" not in capsys.readouterr().err


def test_the_scalp_under_the_hair_is_painted_toward_the_roots_shade(tmp_path):
    """Bare skin showed through a parting as a white line: under the hair the head's displayColor is
    SCALP_TINT of the way from the skin to the roots' shade, away from the scalp it is the skin, and a
    head without hair is the skin all over."""
    from pxr import Usd, UsdGeom

    from sim.scene import ROOT_SHADE, SCALP_TINT, SKIN_COLOR, Scene, _build_config, head_colors

    scene = Scene(_build_config("<test>", {"hair": {"count": 10}}, None))
    colors = head_colors(scene.head, scene.config.hair.color)
    faces = np.asarray(scene.head.faces).reshape(-1, 3)
    scalp = np.asarray(scene.head.scalp_faces, bool)
    inside = np.setdiff1d(faces[scalp].ravel(), faces[~scalp].ravel())
    outside = np.setdiff1d(faces[~scalp].ravel(), faces[scalp].ravel())
    skin, roots = np.asarray(SKIN_COLOR), ROOT_SHADE * np.asarray(scene.config.hair.color)
    np.testing.assert_allclose(colors[inside], np.tile(skin + SCALP_TINT * (roots - skin), (len(inside), 1)))
    np.testing.assert_allclose(colors[outside], np.tile(skin, (len(outside), 1)))
    assert head_colors(scene.head) == SKIN_COLOR
    out = str(tmp_path / "c.usdc")
    assert main(["run", write(tmp_path, SMALL), "-o", out, "-q"]) == 0
    stage = Usd.Stage.Open(out)
    primvar = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/World/head")).GetPrimvar("displayColor")
    assert primvar.GetInterpolation() == "vertex" and np.asarray(primvar.Get()).min() < 0.5 * min(SKIN_COLOR)


def test_the_face_takes_the_scalps_tint_where_it_reaches_over_the_scalp():
    """The face's top reaches over the scalp: there its colours take the tint under them, so the face's
    edge does not draw a line of bare skin across the hairline; below the hairline they are unchanged."""
    from sim.scene import Scene, _build_config

    tables = {"face": {"resolution": 1}, "head": {"animation": "none"}}
    bald = Scene(_build_config("<test>", dict(tables, hair={"enabled": False}), None)).face_rig.mesh
    haired = Scene(_build_config("<test>", dict(tables, hair={"count": 10}), None)).face_rig.mesh
    darker = (bald.colors - haired.colors).max(axis=1)
    assert np.all(darker >= -1e-9) and darker.max() > 0.2  # toward the roots' shade, up to the full tint
    height = bald.vertices[:, 1]
    top, lower = height > np.percentile(height, 95), height < np.percentile(height, 70)
    assert np.mean(darker[top] > 0.01) > 0.5 and np.all(darker[lower] < 1e-9)  # the hairline's, not the brows


def test_a_cache_never_replaces_one_of_the_scenes_inputs_and_absurd_sizes_are_refused(tmp_path, capsys):
    """The output named as the scene's garment file (or a link to it) would have been overwritten by the
    cache; integers past 32 bits wrapped silently in the kernels, and substeps of 2^31 ran out of memory
    after a minute: each is one line naming the file and key, exit 2, nothing written."""
    garment = tmp_path / "g.usda"
    garment.write_text("#usda 1.0\n")
    scene = write(tmp_path, '[body]\n[hair]\nenabled = false\n[cloth]\ngarment = "g.usda"\nprim = "/G"\n')
    (tmp_path / "link.usda").symlink_to(garment)
    for out in (garment, tmp_path / "link.usda"):
        assert main(["run", scene, "-o", str(out), "-q"]) == 2
        assert "is the scene's cloth.garment input" in capsys.readouterr().err
    assert garment.read_text() == "#usda 1.0\n"
    for old, new, reason in (("substeps = 4", "substeps = 4294967297", "solver.substeps: must lie within 32-bit"),
                             ("substeps = 4", "substeps = 20000", "solver.substeps: at most 10,000"),
                             ("[solver]", "[cloth.detail]\nlevel = 100000\n[solver]",
                              "cloth.detail.level: at most 64")):
        bad = write(tmp_path, SMALL.replace(old, new), "bad.toml")
        assert main(["run", bad, "-o", str(tmp_path / "x.usdc"), "-q"]) == 2
        err = capsys.readouterr().err
        assert reason in err and err.count("\n") == 1, err
    assert main(["run", write(tmp_path, SMALL), "-o", str(tmp_path / "x.usdc"), "--frames", "2000000", "-q"]) == 2
    assert "scene.frames: at most 1,000,000" in capsys.readouterr().err
    assert not (tmp_path / "x.usdc").exists()


def test_a_run_names_the_haircut_events_that_did_nothing(tmp_path, capsys):
    """A cut above every strand, or an event past a shorter --frames, was silently no edit at all; the run
    says which events did not happen and which changed no strands."""
    cut = '[[haircut]]\nframe = {}\ntool = "blunt"\nplane = {{ point = [0.0, {}, 0.0], normal = [0.0, 1.0, 0.0] }}\n'
    scene = write(tmp_path, SMALL + cut.format(2, 5.0) + cut.format(3, 0.2) + cut.format(9, 0.1))
    assert main(["run", scene, "-o", str(tmp_path / "c.usdc"), "--frames", "4"]) == 0
    err = capsys.readouterr().err
    assert "1 haircut event(s) after the last frame (4) did not happen: haircut[2] at frame 9" in err
    assert "1 haircut event(s) changed no strands: haircut[0] (blunt at frame 2)\n" in err


def test_a_stop_whose_exception_was_swallowed_still_stops_the_run(tmp_path):
    """A signal's exception can land where it is swallowed (a Warp object's __del__, a lock's release in
    a pool); the handler also records the stop and the run raises it again at the next frame, so no
    cache is committed (a QA pass saw SIGINT and SIGTERM 1.4-1.9 s into a run lost: exit 0, output written)."""
    import signal

    import sim
    from sim.errors import Stopped, clear_stops, record_stop

    config = sim.load_scene(write(tmp_path, SMALL))
    out = tmp_path / "c.usdc"
    clear_stops()
    try:
        with pytest.raises(Stopped) as err:
            sim.run_scene(config, str(out), progress=False, on_frame=lambda frame, scene: record_stop(signal.SIGTERM))
    finally:
        clear_stops()
    assert err.value.signum == signal.SIGTERM
    assert os.listdir(tmp_path) == ["scene.toml"]


def test_info_validate_fails_what_usds_validators_let_through(tmp_path, capsys):
    """From a QA pass: --validate passed a cache with an unknown role, non-finite points, a time range
    run backwards or no frame rate, and read cfx:complete = "false" (a string) as complete."""
    from pxr import Gf, Usd

    out = str(tmp_path / "c.usdc")
    assert main(["run", write(tmp_path, SMALL), "-o", out, "-q"]) == 0
    assert main(["info", out, "--validate"]) == 0
    capsys.readouterr()
    for name, edit, said in (
        ("role", lambda s: s.GetPrimAtPath("/World/hair").GetAttribute("cfx:role").Set("wig"), "unknown role 'wig'"),
        ("nan", lambda s: s.GetPrimAtPath("/World/hair").GetAttribute("points").Set(
            [Gf.Vec3f(float("nan"), 0.0, 0.0)] * 320, 2), "non-finite positions at time 2"),
        ("backwards", lambda s: s.SetEndTimeCode(0), "endTimeCode: 0 is before startTimeCode 1"),
        ("rate", lambda s: s.SetTimeCodesPerSecond(0.0), "timeCodesPerSecond: must be positive"),
        ("complete", lambda s: setattr(s.GetRootLayer(), "customLayerData",
                                       dict(s.GetRootLayer().customLayerData, **{"cfx:complete": "false"})),
         "complete: NO"),
    ):
        bad = str(tmp_path / f"{name}.usda")
        stage = Usd.Stage.Open(out)
        stage.GetRootLayer().Export(bad)
        stage = Usd.Stage.Open(bad)
        edit(stage)
        stage.GetRootLayer().Save()
        assert main(["info", bad, "--validate"]) == 1, name
        assert said in capsys.readouterr().out, name


def test_mask_and_capture_synth_never_replace_their_own_inputs(tmp_path, capsys):
    """From a QA pass: `mask T.json --save-track T.json` rewrote the track read (rounded), and
    `capture synth CAP/scene.toml -o CAP` deleted the scene file with the capture folder it replaced."""
    track = tmp_path / "t.json"
    track.write_text("{}")
    assert main(["mask", str(track), "--save-track", str(track), "-o", str(tmp_path / "m.mp4"), "-q"]) == 2
    assert "is the track read" in capsys.readouterr().err and track.read_text() == "{}"
    cap = tmp_path / "cap"
    cap.mkdir()
    (cap / "capture.json").write_text("{}")
    scene = write(cap, SMALL + "[capture]\n")
    assert main(["capture", "synth", scene, "-o", str(cap), "-q"]) == 2
    assert "holds the scene file" in capsys.readouterr().err and os.path.exists(scene)


def test_info_names_a_role_prim_without_its_topology(tmp_path, capsys):
    """A tagged BasisCurves without curveVertexCounts, or a Mesh without faces, raised tracebacks in
    info, view and preview; an empty displayColor an IndexError (a QA pass)."""
    from pxr import Sdf, Usd, UsdGeom

    for name, define, said in (("curves", UsdGeom.BasisCurves.Define, "/W/p.curveVertexCounts: not authored"),
                               ("mesh", UsdGeom.Mesh.Define, "/W/p: faceVertexCounts or faceVertexIndices")):
        path = str(tmp_path / f"{name}.usda")
        stage = Usd.Stage.CreateNew(path)
        prim = define(stage, "/W/p")
        prim.GetPrim().CreateAttribute("cfx:role", Sdf.ValueTypeNames.Token, custom=True).Set("hair")
        prim.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set([])
        stage.GetRootLayer().Save()
        assert main(["info", path]) == 2
        err = capsys.readouterr().err
        assert said in err and err.count("\n") == 1, err
