"""The cost of a density grid: ms per spp of the patchy-fog scene (`grid_fog`) at several grid resolutions against
the homogeneous medium of the same mean extinction in the same box, interleaved (A B A B), and Mitsuba 3's time on
the same scene (optional, `--mitsuba`).

    python -m benchmarks.bench_grid [--size 32] [--spp 32] [--rounds 3] [--res 4 8 16 32] [--mitsuba]
        [--out bench_out/grid]

The grids are the shipped patchy grid resampled (`data_synthetic/make_grid_fog.patchy_grid` at each resolution);
each row's ratio is the median over rounds of (grid time / homogeneous time) within a round. Writes `grid.json`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import equinox as eqx
import jax
import numpy as np

import jaxfog as jf

from .common import REPO, Stopwatch, command, interleave, out_dir, print_table, write_json

sys.path.insert(0, str(REPO / "data_synthetic"))
from make_grid_fog import BOX, patchy_grid  # noqa: E402


def _render_fn(scene, spp):
    def fn(i):
        return np.asarray(jf.render(scene, jax.random.key(1000 + i), spp))
    return fn


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.bench_grid", description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=32)
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--res", type=int, nargs="+", default=[4, 8, 16, 32])
    ap.add_argument("--max-depth", type=int, default=8)
    ap.add_argument("--mitsuba", action="store_true", help="also time Mitsuba 3 (scalar_rgb) on the 16^3 scene")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    ov = [f"camera.width={args.size}", f"camera.height={args.size}", f"integrator.max_depth={args.max_depth}"]
    sf = jf.load_scene(REPO / "data_synthetic" / "scenes" / "grid_fog.json", ov)
    rows = []
    for res in args.res:
        grid = patchy_grid(res)
        med = jf.GridMedium(grid, 1.0, 0.9, sf.scene.medium.phase, bounds=BOX)
        hom = jf.HomogeneousMedium(float(grid.mean()), 0.9, sf.scene.medium.phase, bounds=BOX)
        fns = {"homogeneous": _render_fn(eqx.tree_at(lambda s: s.medium, sf.scene, hom), args.spp),
               "grid": _render_fn(eqx.tree_at(lambda s: s.medium, sf.scene, med), args.spp)}
        r = interleave(fns, args.rounds, warmup=1)
        rows.append({"grid": f"{res}^3", "homogeneous_ms_per_spp": 1e3 * r["homogeneous"]["median_s"] / args.spp,
                     "grid_ms_per_spp": 1e3 * r["grid"]["median_s"] / args.spp,
                     "ratio": r["grid"]["ratio_median"], "grid_compile_s": r["grid"]["compile_s"], "runs": r})
        print(f"  {res}^3: ratio {r['grid']['ratio_median']:.2f}", flush=True)
    mitsuba = None
    if args.mitsuba:
        spp_mi = 1024
        jf.render_mitsuba(REPO / "data_synthetic" / "scenes" / "grid_fog.json", spp=4, overrides=ov)  # warm-up
        with Stopwatch() as sw:
            jf.render_mitsuba(REPO / "data_synthetic" / "scenes" / "grid_fog.json", spp=spp_mi, overrides=ov)
        mitsuba = {"spp": spp_mi, "ms_per_spp": 1e3 * sw.s / spp_mi, "variant": "scalar_rgb"}
    cols = [("grid", "grid"), ("homogeneous ms/spp", "homogeneous_ms_per_spp", ".1f"),
            ("grid ms/spp", "grid_ms_per_spp", ".1f"), ("ratio (interleaved)", "ratio", ".2f"),
            ("grid compile s", "grid_compile_s", ".1f")]
    print_table(rows, cols)
    if mitsuba:
        print(f"Mitsuba 3 (scalar_rgb), 16^3: {mitsuba['ms_per_spp']:.1f} ms/spp")
    out = out_dir("grid") if args.out is None else args.out
    write_json(Path(out) / "grid.json", {"command": command("benchmarks.bench_grid", argv), "size": args.size,
                                    "spp": args.spp, "max_depth": args.max_depth, "rows": rows, "mitsuba": mitsuba})
    return 0


if __name__ == "__main__":
    sys.exit(main())
