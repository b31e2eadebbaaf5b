"""The benchmark tooling: bytes counted per launch, and the plot reading the recorded H100 logs."""

import sys
from pathlib import Path

import numpy as np
import pytest
import warp as wp

BENCH = Path(__file__).resolve().parent.parent / "benchmarks"
sys.path.insert(0, str(BENCH))

import common  # noqa: E402
import plot  # noqa: E402


@wp.kernel
def _axpy(a: float, x: wp.array(dtype=wp.vec3), y: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    y[i] = y[i] + a * x[i]


def test_launch_bytes_count_every_array_once_and_copies_twice():
    x = wp.array(np.ones((100, 3), np.float32), dtype=wp.vec3)
    y = wp.zeros(100, dtype=wp.vec3)
    with common.counting_launch_bytes() as moved:
        wp.launch(_axpy, 100, [2.0, x, y])
        wp.copy(x, y, count=40)
    assert moved[0] == 2 * 100 * 12 + 2 * 40 * 12
    np.testing.assert_allclose(y.numpy(), 2.0)  # the counted launch really ran
    assert wp.launch is not None and wp.launch.__name__ == "launch"  # restored afterwards


def test_launch_bytes_count_the_arrays_inside_structs_once_per_launch():
    from warp_kernels import strands

    order = strands.LaneOrder()
    order.lanes = 4
    order.lane_of = wp.zeros(10, dtype=wp.int32)
    order.strand_of = order.lane_of  # the same array twice: counted once
    x = wp.zeros(7, dtype=wp.vec3)
    arrays = common.launch_arrays([x, order, 2.0, x])
    assert sorted(a.capacity for a in arrays) == [40, 84]


def test_plot_reads_the_recorded_h100_logs(tmp_path):
    logs = [BENCH / "results" / "h100-50cb389-hair.log", BENCH / "results" / "h100-f3d4cbe-hair.log",
            BENCH / "results" / "h100-f3d4cbe-cloth.log"]
    data = plot.series(logs, {"full+mesh"})
    # the later run replaces the earlier one's point; the cloth log was cut short before its
    # final table, so its streamed rows are read with the race header
    assert data["hair"]["ours, full+mesh"] == {32000.0: 21.73, 320000.0: 46.1, 3200000.0: 131.9}
    assert data["cloth"]["Newton VBD"][1048576.0] == 216.1
    assert sorted(data["cloth"]["ours RK4"]) == [1024.0, 16384.0, 262144.0, 1048576.0]
    out = tmp_path / "bench.png"
    sys.argv = ["plot", *map(str, logs), "-o", str(out)]
    plot.main()
    assert out.stat().st_size > 10_000


def test_warp_model_takes_each_steps_slowest_lane_and_counts_the_real_pass():
    """benchmarks/hair_warps.py: a warp's work is the sum over particle steps of its slowest lane's;
    its counting copy of follow_the_leader compiles from the kernel's source and steps the same hair
    (the counts are 1 per step, and more where a step queried the collider)."""
    import hair_warps

    work = np.zeros((1, 2, 64))
    work[0, :, :] = 1.0
    work[0, 0, 3] = 86.0  # strand 3 walks at the first step
    work[0, 1, 40] = 5.0  # strand 40 tests its listed leaves at the second
    total, slowest = hair_warps.warp_costs(work, np.arange(64))
    assert (total, slowest) == (86.0 + 1.0 + 1.0 + 5.0, 87.0)
    together = np.r_[3, 40, [s for s in range(64) if s not in (3, 40)]]  # both in the first warp
    assert hair_warps.warp_costs(work, together) == (86.0 + 5.0 + 1.0 + 1.0, 91.0)

    counted = hair_warps.counting_follow_the_leader()
    counts, model = hair_warps.count_work(40, 1, counted)
    assert counts.shape == (10, model.strand_start_np[1], model.num_strands)
    steps = counts[counts > 0]
    assert len(steps) == 10 * model.num_particles  # every particle step counted once ...
    assert np.all(steps >= 1.0) and np.any(steps >= 5.0)  # ... and some of them queried the head


_PTXAS_LOG = """ptxas info    : 0 bytes gmem
ptxas info    : Compiling entry function 'follow_the_leader_bce2c61e_cuda_kernel_forward' for 'sm_90'
ptxas info    : Function properties for follow_the_leader_bce2c61e_cuda_kernel_forward
    240 bytes stack frame, 112 bytes spill stores, 136 bytes spill loads
ptxas info    : Used 128 registers, used 0 barriers, 240 bytes cumulative stack size, 1024 bytes smem
ptxas info    : Compiling entry function 'to_lanes_52729374_cuda_kernel_forward' for 'sm_90'
ptxas info    : Function properties for to_lanes_52729374_cuda_kernel_forward
    0 bytes stack frame, 0 bytes spill stores, 0 bytes spill loads
ptxas info    : Used 18 registers, used 0 barriers, 1024 bytes smem
"""


def test_cuda_resources_reads_each_kernels_registers_spills_and_cap():
    """benchmarks/cuda_resources.py: ptxas -v's report parsed per kernel, with the .maxnreg cap from the
    PTX, and compared with a recorded baseline (a kernel that spills more is named; one the baseline
    does not hold counts as recorded without spills)."""
    import cuda_resources

    ptx = ".visible .entry follow_the_leader_bce2c61e_cuda_kernel_forward(\n .param .u64 a\n)\n.maxnreg 128\n{\n}\n" \
          ".visible .entry to_lanes_52729374_cuda_kernel_forward(\n .param .u64 a\n)\n{\n}\n"
    found = cuda_resources.parse_ptxas(_PTXAS_LOG, cuda_resources.register_caps(ptx))
    assert [(k.kernel, k.registers, k.cap, k.stack, k.spill_stores, k.spill_loads, k.shared) for k in found] == [
        ("follow_the_leader", 128, 128, 240, 112, 136, 1024), ("to_lanes", 18, None, 0, 0, 0, 1024)]
    record = cuda_resources.baseline_record({"strands": found}, "1.19.0", "9.0")
    assert record["kernels"] == {"strands.follow_the_leader": [128, 112, 136], "strands.to_lanes": [18, 0, 0]}
    assert cuda_resources.spill_regressions({"strands": found}, record) == []
    record["kernels"]["strands.follow_the_leader"] = [128, 112, 100]
    del record["kernels"]["strands.to_lanes"]
    assert cuda_resources.spill_regressions({"strands": found}, record) == [
        "strands.follow_the_leader: spills 112/136 B, recorded 112/100 B"]


def test_cuda_resources_counts_the_blocks_an_sm_holds():
    """blocks_per_sm: CUDA's occupancy rules for sm_90 (registers given a warp 256 at a time, 1 KB of
    shared memory reserved a block), checked against the H100's figures: 96 registers on one-warp blocks
    give 21 blocks, 128 on 256-lane blocks 2; 131 KB of tiles leave room for one block, 240 KB for none."""
    from cuda_resources import KernelResources, blocks_per_sm

    def kernel(registers, block, tiles=0, shared=1024):
        return KernelResources("k", registers, 128, 0, 0, 0, shared, tiles, block)

    assert blocks_per_sm(kernel(96, 32, 1936, 128)) == (21, "registers")
    assert blocks_per_sm(kernel(96, 8)) == (21, "registers")  # a block of 8 lanes still takes a warp's registers
    assert blocks_per_sm(kernel(128, 256, 82752)) == (2, "registers")
    assert blocks_per_sm(kernel(128, 256, 131840)) == (1, "shared")
    assert blocks_per_sm(kernel(128, 256, 240000)) == (0, "shared")
    assert blocks_per_sm(kernel(24, 256)) == (8, "threads")
    assert blocks_per_sm(kernel(16, 32)) == (32, "blocks")


@pytest.mark.slow
def test_frame_layouts_say_what_an_sm_holds_of_each():
    """cuda_resources --frame-layouts: the hair frame compiled for sm_90 in a layout of 2 strands a block,
    4 threads along each with runs of 2, on the sphere tree and with no collider: a row each, with the
    strands its blocks hold an SM and its chain's barriers (one a group)."""
    import cuda_resources

    ptxas = cuda_resources.find_ptxas()
    if ptxas is None or 90 not in cuda_resources.nvrtc_archs():
        pytest.skip("needs a CUDA toolkit's ptxas and a Warp whose NVRTC compiles for sm_90")
    text = cuda_resources.frame_layouts_table(["2x4x2"], 90, ptxas, cuda_resources.ptxas_isa(ptxas))
    rows = [line.split(" | ") for line in text.splitlines()[2:]]
    assert [(r[0].strip("| "), r[1]) for r in rows] == [("2x4x2", "sphere tree"), ("2x4x2", "none")]
    for r in rows:
        blocks = int(r[6].split()[0])
        assert r[5] == "8" and blocks >= 1 and int(r[7]) == 2 * blocks and r[9].strip(" |") == "4"


@pytest.mark.slow
def test_no_cuda_kernel_spills_more_than_its_recorded_baseline():
    """Every kernel of warp_kernels compiled for sm_90 (Warp's NVRTC and a CUDA toolkit's ptxas, no GPU
    needed) spills no more registers than benchmarks/cuda_resources_sm90.json records: on an H100 the
    hair's length pass lost a third of its speed to spills that CPU-only sessions had added unseen
    (BENCHMARKS.md, session 34). A change that must spill more records the baseline again, on purpose
    (python benchmarks/cuda_resources.py --record). The serial per-strand kernels hold their cap."""
    import importlib
    import json
    import tempfile

    import cuda_resources

    ptxas = cuda_resources.find_ptxas()
    if ptxas is None or 90 not in cuda_resources.nvrtc_archs():
        pytest.skip("needs a CUDA toolkit's ptxas and a Warp whose NVRTC compiles for sm_90")
    baseline = json.loads(cuda_resources.BASELINE.read_text())
    if baseline["warp"] != wp.config.version:
        pytest.skip(f"the baseline was recorded with Warp {baseline['warp']}, this is {wp.config.version}")
    isa = cuda_resources.ptxas_isa(ptxas)
    if baseline["ptx_isa"] != isa:
        pytest.skip(f"the baseline was assembled as PTX ISA {baseline['ptx_isa']}, this ptxas takes {isa}")
    modules = [importlib.import_module(f"warp_kernels.{name}") for name in cuda_resources.MODULES]
    with tempfile.TemporaryDirectory() as workdir:
        compiled = cuda_resources.modules_resources(modules, 90, ptxas, isa, workdir)
    found = {name: compiled[module.__name__][0] for name, module in zip(cuda_resources.MODULES, modules, strict=True)}
    assert cuda_resources.spill_regressions(found, baseline) == []
    # each module compiled at the block size it is launched with: a block that asks for more static
    # shared memory than a block has fails to build on the device (step_in_block at 384 lanes, session 41)
    shared = {f"{m}.{k.kernel}": k.shared for m, ks in found.items() for k in ks}
    assert 0 < max(shared.values()) <= cuda_resources.STATIC_SHARED_LIMIT
    assert shared["cloth.step_in_block"] > shared["cloth.body_collide"]  # its block is larger than 256 lanes
    by_name = {k.kernel: k for k in found["strands"]}
    for name in ("step_strands", "follow_the_leader"):
        assert by_name[name].cap == 128 and 64 < by_name[name].registers <= 128
    assert by_name["to_lanes"].registers < 64 and by_name["to_lanes"].spill_stores == 0


def test_each_frame_is_timed_after_the_warm_up_frames():
    calls = []

    def step():
        calls.append(1)

    times = common.time_each_frame(step, "cpu", frames=5, min_seconds=0.0)
    assert len(times) == 5 and len(calls) == 2 + 5  # two warm-up frames, not timed
    assert all(t >= 0.0 for t in times)
    slow = iter([0.0] * 3 + [0.02] + [0.0] * 10)  # the second timed frame sleeps 20 ms

    def uneven():
        import time
        time.sleep(next(slow))

    times = common.time_each_frame(uneven, "cpu", frames=4, min_seconds=0.0)
    assert max(times) == times[1] and times[1] >= 20.0 and sum(t > 20.0 for t in times) == 1


def test_hair_benchmark_reads_the_solver_settings_it_tries():
    """benchmarks/hair.py --try: on/off, numbers and a frame's layout (SIDExGROUPSxRUN) as a HairSolver takes
    them; an attribute it does not know or a layout not of integers is refused, naming the item."""
    import argparse

    import hair

    assert hair.solver_setting("frame_in_block=on,frame_layout=16x8x4,strand_block=64") == {
        "frame_in_block": True, "frame_layout": (16, 8, 4), "strand_block": 64}
    with pytest.raises(argparse.ArgumentTypeError, match="frame_layout=16x8xa"):
        hair.solver_setting("frame_layout=16x8xa")
    with pytest.raises(argparse.ArgumentTypeError, match="lanes=on"):
        hair.solver_setting("lanes=on")


@pytest.mark.parametrize("run", [1, 2])
def test_two_checkouts_take_turns_frame_by_frame(run):
    """benchmarks/turns.py: the two sides build the same case in processes of their own and step in
    alternation, never at once: A's k-th frame (or run of frames back to back) ends before B's k-th
    starts, and B's before A's next."""
    import turns

    root = str(BENCH.parent)
    args = turns.arguments().parse_args([root, root, "--hair", "simplified1", "--strands", "20", "--frames", "4",
                                         "--run", str(run), "--warmup", "1", "--substeps", "2"])
    spans_a, spans_b = turns.race(root, root, args)
    assert spans_a.shape == spans_b.shape == (4 // run, 2)
    order = np.stack([spans_a, spans_b], axis=1).reshape(-1)  # A0 start, A0 end, B0 start, B0 end, A1 ...
    assert np.all(np.diff(order) > 0.0)
    assert np.all(spans_a[:, 1] > spans_a[:, 0])


def test_cpu_profile_maps_generated_lines_to_python_and_samples_to_funcs(tmp_path):
    """benchmarks/cpu_profile.py: each line of Warp's generated C++ goes to the Python line it
    quotes (function headers and <L n> comments), and each sampled address to the innermost
    generated function of its inlined chain (helpers of Warp's headers skipped)."""
    import cpu_profile

    cpp = tmp_path / "m.cpp"
    cpp.write_text("#include x\n// /a/b/strands.py:10\nstatic void f_0()\n{\n    // y = 1   <L 12>\n    y = 1;\n"
                   "    // z = y   <L 14>\n    z = y;\n}\n")
    lines = cpu_profile.python_lines(cpp)
    assert lines[6] == ("strands.py", 12) and lines[8] == ("strands.py", 14) and lines[3] == ("strands.py", 10)
    out = ("0x10\nwp::vec_t<3u, float> wp::add<float>(wp::vec_t<3u, float>)\nvec.h:14\n"
           "refine_rotation_0(wp::quat_t<float>, int)\nm.cpp:120\n"
           "void step_strands_095e7ab2_cpu_kernel_forward<true>(int)\nm.cpp:900\n"
           "0x20\nvoid step_strands_095e7ab2_cpu_kernel_forward<true>(int)\nm.cpp:950\n")
    functions, by_line = cpu_profile.attribute(out, {0x10: 3, 0x20: 2})
    assert functions == {"refine_rotation": 3, "step_strands": 2}
    assert by_line == {120: 3, 950: 2}


def test_preview_benchmark_renders_the_same_pictures_both_ways(tmp_path):
    """The preview benchmark's two renderings of a head with hair, supersampled (ours) and pyrender's
    4x multisampling (the peer), agree to within a grey level on average and 3% of pixels off by
    more than 16 levels: the same four samples per pixel, resolved alike."""
    import preview as bench

    from io_usd.cache import CacheReader, CacheWriter
    from io_usd.preview import BACKGROUND, auto_camera
    from sim.head import procedural_head

    head = procedural_head(rings=40, segments=32)
    rng = np.random.default_rng(0)
    roots = head.vertices[head.vertices[:, 1] > 0.44][::3]
    strands = roots[:, None, :] + np.linspace(0.0, 0.15, 10)[None, :, None] * (
        np.array([0.0, -1.0, 0.0]) + 0.3 * rng.standard_normal((len(roots), 1, 3)))
    path = str(tmp_path / "hair.usdc")
    with CacheWriter(path, fps=24, start_frame=1, end_frame=1) as w:
        w.add_mesh("head", "collider", head.vertices, head.faces)
        w.add_curves("hair", "hair", np.full(len(roots), 10), np.full(10 * len(roots), 1e-4))
        w.write_frame(1, {"head": head.vertices, "hair": strands.reshape(-1, 3)})
    reader = CacheReader(path)
    camera = auto_camera(reader, 200, 150)
    (ours,), ours_ms = bench.supersampled(reader, camera, [1])
    (theirs,), theirs_ms = bench.multisampled(reader, camera, [1])
    assert ours_ms > 0.0 and theirs_ms > 0.0
    assert ours.shape == theirs.shape == (150, 200, 3)
    difference = np.abs(ours.astype(np.int16) - theirs.astype(np.int16))
    background = np.round(255 * np.asarray(BACKGROUND)).astype(np.int16)
    drawn = np.abs(theirs.astype(np.int16) - background).max(axis=2) > 6
    assert drawn.mean() > 0.05  # head and hair fill a good part of the picture
    assert difference.mean() < 1.0
    assert np.mean(difference.max(axis=2) > 16) < 0.03


def test_startup_benchmark_times_a_scene_built_and_from_the_cache(capsys):
    import startup

    startup.main(["--scenes", "haircut", "--repeats", "1"])
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if line.startswith("| haircut |"))
    built, cached = (float(v) for v in row.split("|")[3:5])
    assert built > 0.0 and cached > 0.0 and row.rstrip(" |").endswith("x")
