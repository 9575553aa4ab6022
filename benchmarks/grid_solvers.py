"""Adam against Gauss-Newton on a voxel fit, at equal wall time: the volume error of each fit's iterates against its
wall seconds (from the fit's start, compilation included), from the `RESULT.json` files of `python -m fitting.grid
... --truth` runs, as one figure and a table of the error of the iterate each fit holds at given times.

    python -m benchmarks.grid_solvers ADAM/RESULT.json GAUSS_NEWTON/RESULT.json [--out grid_solvers.png]
"""

from __future__ import annotations

import argparse
import json
import sys

from .common import print_table


def _curve(path):
    rec = json.load(open(path))
    hist = [h for h in rec["history"] if "volume_error" in h and isinstance(h["iteration"], int)]
    return rec.get("solver", "adam"), [h["seconds"] for h in hist], [h["volume_error"] for h in hist]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.grid_solvers", description=__doc__.split("\n\n")[0])
    ap.add_argument("results", nargs="+", help="RESULT.json of fitting.grid runs with --truth")
    ap.add_argument("--out", default="grid_solvers.png")
    ap.add_argument("--at", type=float, nargs="+", default=[60, 120, 240, 360], help="wall seconds of the table")
    args = ap.parse_args(argv)
    curves = [_curve(p) for p in args.results]
    rows = []
    for name, secs, errs in curves:
        row = {"solver": name, "iterations": len(secs), "last_s": secs[-1], "last_error": errs[-1]}
        for t in args.at:  # the iterate the fit holds at that time (not the best: picking it needs the truth)
            reached = [e for s, e in zip(secs, errs) if s <= t]
            row[f"{t:g} s"] = reached[-1] if reached else float("nan")
        rows.append(row)
    print_table(rows, [("solver", "solver"), ("iterations", "iterations"), ("wall s", "last_s", ".0f"),
                       ("last volume error", "last_error", ".3f")] + [(f"at {t:g} s", f"{t:g} s", ".3f")
                                                                      for t in args.at])
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.6))
    for name, secs, errs in curves:
        ax.plot(secs, errs, "-o" if len(secs) < 50 else "-", ms=3, label=name)
    ax.set_xlabel("wall seconds from the fit's start (compilation included)")
    ax.set_ylabel("volume error (relative L2)")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(args.out, dpi=90)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
