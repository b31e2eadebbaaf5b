"""Captured guides driving simulated hair: the kernel against a float64 reference, and a scene whose
strands follow guides that swing sideways."""

import numpy as np
import pytest
import warp as wp

from io_usd.cache import CacheWriter
from sim.guides import GuideTargets, read_guides
from sim.strands import StrandBuilder
from warp_kernels import strands as kernels


def _model(rng, n=6, m=8):
    roots = rng.normal(size=(n, 3)) * 0.05
    pts = [r + np.outer(np.linspace(0, 0.2, m), [0.0, -1.0, 0.0]) + rng.normal(size=(m, 3)) * 0.005 for r in roots]
    return StrandBuilder().add_strands(np.concatenate(pts), np.full(n, m), np.full(n * m, 1e-4)).finalize(
        "cpu", pinned_per_strand=1)


def test_follow_guides_matches_a_float64_reference():
    rng = np.random.default_rng(2)
    model = _model(rng)
    guides = rng.normal(size=(2, 4, 10, 3)) * 0.1
    targets = GuideTargets(model, guides, fps=10.0)
    x0 = model.rest_positions_np.astype(np.float64) + rng.normal(size=(model.num_particles, 3)) * 0.01
    x = wp.array(x0.astype(np.float32), dtype=wp.vec3)
    stiffness = 0.3
    clock = wp.array([0.04], dtype=float)  # + 0.01 offset: half way between the two captured frames
    wp.launch(kernels.follow_guides, model.num_particles,
              [x, model.inv_mass, model.particle_strand, model.strand_start, targets.pull(stiffness), clock, 0.01, 0])
    # reference: the same rule in float64
    g = 0.5 * (targets.frames[0] + targets.frames[1])
    idx, w = targets.strand_guides.numpy(), targets.strand_guide_weights.numpy().astype(np.float64)
    s = targets.particle_param.numpy().astype(np.float64)
    ref = x0.copy()
    for i in range(model.num_particles):
        if model.inv_mass.numpy()[i] == 0.0:
            continue
        k = model.particle_strand_np[i]
        offset = np.zeros(3)
        for j in range(3):
            curve = g[idx[k, j]]
            u = s[i] * (len(curve) - 1)
            a = min(int(u), len(curve) - 2)
            p = (1 - (u - a)) * curve[a] + (u - a) * curve[a + 1]
            offset += w[k, j] * (p - curve[0])
        target = x0[model.strand_start_np[k]] + offset
        ref[i] = x0[i] + stiffness * (target - x0[i])
    np.testing.assert_allclose(x.numpy(), ref, atol=2e-6)
    np.testing.assert_allclose(w.sum(1), 1.0, atol=1e-6)


@pytest.mark.parametrize("shape_matching", ["full", "simplified"])
def test_guides_pull_the_same_in_one_launch_as_apart(shape_matching):
    """strands.step_strands pulls the predicted strands toward their guides as follow_guides does
    between the launches apart: every substep bit for bit, while the guides move."""
    from sim.hair_solver import HairParams, HairSolver

    rng = np.random.default_rng(5)
    model = _model(rng, n=10, m=10)
    guides = rng.normal(size=(6, 4, 10, 3)) * 0.1
    targets = GuideTargets(model, guides, fps=24.0)
    params = HairParams(collision="none", shape_matching=shape_matching, guide_stiffness=30.0)
    dt, runs = 1.0 / 240.0, []
    for fused, pulled in ((False, targets), (True, targets), (True, None)):
        solver = HairSolver(model, params, parts=2)
        solver.fused = fused
        s0, s1 = model.state(), model.state()
        frames = []
        for k in range(1, 25):
            for part in solver.parts:
                solver.step(s0, s1, None, dt, time=k * dt, guides=pulled, part=part)
            s0, s1 = s1, s0
            frames.append(s0.x.numpy().copy())
        runs.append(frames)
    for x, x_fused in zip(runs[0], runs[1], strict=True):
        np.testing.assert_array_equal(x_fused, x)
    assert np.abs(runs[1][-1] - runs[2][-1]).max() > 0.01  # the guides, not gravity alone, moved the strands



def test_guides_pull_the_same_in_a_frame_in_block():
    """strands.frame_in_block (HairSolver.step_frame, a frame in one launch) pulls the strands toward
    their moving guides as the substeps one by one do: every frame bit for bit, each substep at its
    own time."""
    from sim.hair_solver import HairParams, HairSolver

    rng = np.random.default_rng(6)
    model = _model(rng, n=10, m=10)
    targets = GuideTargets(model, rng.normal(size=(6, 4, 10, 3)) * 0.1, fps=24.0)
    params = HairParams(collision="none", shape_matching="simplified", guide_stiffness=30.0, substeps=5)
    dt = 1.0 / (24.0 * params.substeps)
    runs = []
    for whole in (False, True):
        solver = HairSolver(model, params)
        solver.frame_in_block = whole
        s0, s1 = model.state(), model.state()
        frames = []
        for f in range(6):
            times = (f * params.substeps + np.arange(params.substeps + 1)) * dt
            solver.set_clock(times[0])
            if whole:
                solver.step_frame(s0, s1, None, dt, times, guides=targets)
                s0, s1 = s1, s0
            else:
                for t in times[1:]:
                    solver.step(s0, s1, None, dt, time=t, guides=targets)
                    s0, s1 = s1, s0
            frames.append(s0.x.numpy().copy())
        runs.append(frames)
    for x, x_block in zip(runs[0], runs[1], strict=True):
        np.testing.assert_array_equal(x_block, x)
    assert np.abs(runs[1][-1] - model.rest_positions_np).max() > 0.01

def _swing(points, angle, roots):
    """Rotate each guide about its root around the Z axis by `angle`."""
    c, s = np.cos(angle), np.sin(angle)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return (points - roots[:, None]) @ R.T + roots[:, None]


@pytest.mark.parametrize("stiffness", [40.0, 0.0])
def test_scene_hair_follows_swinging_guides(tmp_path, stiffness):
    from sim.scene import Scene, hair_demo_scene

    base = {"scene": {"frames": 12, "preroll": 0.0, "stats": False}, "head": {"animation": "none"},
            "hair": {"count": 60, "style": "straight", "vertices": 12}}
    groom = Scene(hair_demo_scene(base)).model
    start = groom.strand_start_np
    picks = np.arange(0, groom.num_strands, 6)
    rest = np.stack([groom.rest_positions_np[start[k]:start[k + 1]] for k in picks]).astype(np.float64)
    roots = rest[:, 0]
    fps, frames = 24.0, 12
    angles = 0.6 * np.sin(np.linspace(0.0, np.pi / 2, frames))  # swing out to 0.6 rad and hold
    path = tmp_path / "guides.usdc"
    with CacheWriter(str(path), fps, 1, frames) as w:
        w.add_curves("hair_guides", "hair", np.full(len(picks), rest.shape[1]), np.full(rest.size // 3, 1e-4))
        for f, a in enumerate(angles):
            w.write_frame(f + 1, {"hair_guides": _swing(rest, a, roots).reshape(-1, 3)})
    g, g_fps = read_guides(str(path))
    assert g.shape == (frames, len(picks), rest.shape[1], 3) and g_fps == fps

    config = hair_demo_scene({**base, "hair": {**base["hair"], "guides": str(path)},
                              "solver": {"guide_stiffness": stiffness}})
    scene = Scene(config)
    scene.advance((frames - 1) / fps)
    x = scene.state.x.numpy().astype(np.float64)
    sim_tips = x[start[1:] - 1] - x[start[:-1]]
    rest_tips = groom.rest_positions_np[start[1:] - 1] - groom.rest_positions_np[start[:-1]]
    moved = np.mean(sim_tips[:, 0] - rest_tips[:, 0])
    guide_tips = g[-1][:, -1] - g[-1][:, 0]
    guide_moved = np.mean(guide_tips[:, 0] - (rest[:, -1, 0] - rest[:, 0, 0]))
    if stiffness > 0.0:
        # the guides swing their tips sideways; the followed hair goes the same way by a similar amount
        assert guide_moved > 0.04
        assert 0.6 * guide_moved < moved < 1.4 * guide_moved
    else:
        assert abs(moved) < 0.01  # without the pull, hair only hangs
