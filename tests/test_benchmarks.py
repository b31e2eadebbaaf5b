"""The benchmark tooling: bytes counted per launch, and the plot reading the recorded H100 logs."""

import sys
from pathlib import Path

import numpy as np
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
