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
