"""Plot benchmark logs: ms per frame against problem size, ours and the peer, log-log.

Reads the tables that benchmarks/hair.py and benchmarks/cloth.py print (saved logs, e.g. those in
benchmarks/results/) and draws one panel per script.

    python benchmarks/plot.py benchmarks/results/h100-*-hair.log benchmarks/results/h100-*-cloth.log \
        -o docs/benchmarks.png
"""

import argparse
import re
from collections import defaultdict
from pathlib import Path

import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from common import CLOTH_RACE_HEADER, HAIR_HEADER  # noqa: E402


def table_rows(path):
    """The rows of every table in a log: [{column: text}]. Rows before any header line (logs of runs
    cut short, from before the scripts printed their header first) are read with the hair or cloth
    race header when they fit it. A row printed twice (streamed, then in the final table) counts once."""
    header, rows, seen = None, [], set()
    for line in Path(path).read_text().splitlines():
        if not line.startswith("|") or set(line) <= set("|- "):
            continue
        cells = [c.strip() for c in line.strip("|").split("|")]
        if cells[0] in ("case", "garment"):
            header = cells
            continue
        columns = header
        if columns is None and len(cells) == len(CLOTH_RACE_HEADER) and cells[3].startswith(("ours", "Newton")):
            columns = CLOTH_RACE_HEADER
        elif columns is None and len(cells) == len(HAIR_HEADER):
            columns = HAIR_HEADER
        if columns and len(cells) == len(columns) and line not in seen:
            seen.add(line)
            rows.append(dict(zip(columns, cells)))
    return rows


def number(text):
    return float(text.replace(",", "").rstrip("x")) if re.match(r"^[\d.,e+-]+x?$", text) else None


def series(paths, hair_cases):
    """{panel: {label: {size: ms}}} from hair and cloth logs; a later log replaces an earlier one's
    point of the same series and size."""
    out = defaultdict(lambda: defaultdict(dict))
    for path in paths:
        for row in table_rows(path):
            if "strands" in row and row["case"] in hair_cases:
                size = number(row["vertices"])
                out["hair"]["ours, " + row["case"]][size] = number(row["ms/frame"])
                peer = number(row.get("Newton chains ms/frame", "-"))
                if peer:
                    out["hair"]["Newton XPBD chains"][size] = peer
            elif "engine" in row and row["case"].startswith("grid"):  # the cloth race
                out["cloth"][row["engine"]][number(row["particles"])] = number(row["ms/frame"])
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("logs", nargs="+")
    parser.add_argument("-o", "--output", default="benchmarks.png")
    parser.add_argument("--title", default="NVIDIA H100, warp-lang 1.19, Newton 1.8")
    parser.add_argument("--hair-cases", nargs="*", default=["full+mesh", "simplified+spheres"])
    args = parser.parse_args()
    data = series(args.logs, set(args.hair_cases))
    panels = [(k, t) for k, t in (("hair", "hair: 32-vertex strands, 10 substeps per 1/24 s frame"),
                                  ("cloth", "cloth: 1 m grid over a ball, 1/60 s frames")) if k in data]
    fig, axes = plt.subplots(1, len(panels), figsize=(6.5 * len(panels), 5.0), squeeze=False)
    for ax, (key, title) in zip(axes[0], panels):
        for label, points in sorted(data[key].items()):
            points = sorted(points.items())
            peer = label.startswith("Newton")
            ax.plot(*zip(*points), marker="o", linestyle="--" if peer else "-", label=label)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("vertices" if key == "hair" else "particles")
        ax.set_ylabel("ms per frame")
        ax.set_title(title, fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(args.title)
    fig.tight_layout()
    fig.savefig(args.output, dpi=120)
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
