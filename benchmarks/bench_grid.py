"""The cost of a density grid, against its error: ms per spp of the patchy-fog scene (`grid_fog`) at several grid
resolutions, with exact profiles (`tracking="exact"`) and with ratio tracking (`tracking="ratio"`; "ratio" interpolates
8 texels a point, "stochastic" reads one, `lookup`), against the
homogeneous medium of the same mean extinction in the same box, interleaved (A B C A B C), and Mitsuba 3's time on
the same scene (optional, `--mitsuba`).

    python -m benchmarks.bench_grid [--size 32] [--spp 32] [--rounds 6] [--res 4 8 16 32] [--cells 8] [--mitsuba]
        [--media homogeneous exact ratio stochastic] [--out bench_out/grid]

The grids are the shipped patchy grid resampled (`data_synthetic/make_grid_fog.patchy_grid` at each resolution);
each row's ratio is the median over rounds of (its time / the homogeneous time) within a round. Error: every round
renders with its own key, so the per-pixel variance across rounds (times spp: the variance of one sample) is each
estimator's; `variance x ms` is the work-normalised error (lower is better: the time to a given error is
proportional to it). Writes `grid.json`.
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
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--cells", type=int, default=8, help="majorant cells per axis of tracking='ratio'")
    ap.add_argument("--res", type=int, nargs="+", default=[4, 8, 16, 32])
    ap.add_argument("--max-depth", type=int, default=8)
    ap.add_argument("--media", nargs="+", default=["homogeneous", "exact", "ratio", "stochastic"],
                    choices=["homogeneous", "exact", "ratio", "stochastic"],
                    help="the media timed (homogeneous first: the others' times are taken relative to it); "
                         "'stochastic' is ratio tracking with one texel read per point (lookup='stochastic')")
    ap.add_argument("--mitsuba", action="store_true", help="also time Mitsuba 3 (scalar_rgb) on the 16^3 scene")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    ov = [f"camera.width={args.size}", f"camera.height={args.size}", f"integrator.max_depth={args.max_depth}"]
    sf = jf.load_scene(REPO / "data_synthetic" / "scenes" / "grid_fog.json", ov)
    rows = []
    for res in args.res:
        grid = patchy_grid(res)
        hom = jf.HomogeneousMedium(float(grid.mean()), 0.9, sf.scene.medium.phase, bounds=BOX)
        every = {"homogeneous": hom,
                 "exact": jf.GridMedium(grid, 1.0, 0.9, sf.scene.medium.phase, bounds=BOX),
                 "ratio": jf.GridMedium(grid, 1.0, 0.9, sf.scene.medium.phase, bounds=BOX, tracking="ratio",
                                        majorant_cells=args.cells, lookup="trilinear"),
                 "stochastic": jf.GridMedium(grid, 1.0, 0.9, sf.scene.medium.phase, bounds=BOX, tracking="ratio",
                                             majorant_cells=args.cells, lookup="stochastic")}
        media = {k: every[k] for k in ["homogeneous"] + [m for m in args.media if m != "homogeneous"]}
        fns = {k: _render_fn(eqx.tree_at(lambda s: s.medium, sf.scene, m), args.spp) for k, m in media.items()}
        r = interleave(fns, args.rounds, warmup=1, keep=True)
        for k in media:
            imgs = np.stack([np.asarray(v).mean(axis=-1) for v in r[k].pop("values")])
            ms = 1e3 * r[k]["median_s"] / args.spp
            var = float(imgs.var(axis=0, ddof=1).mean()) * args.spp
            rows.append({"grid": f"{res}^3", "medium": k, "ms_per_spp": ms, "ratio": r[k]["ratio_median"],
                         "mean": float(imgs.mean()), "mean_se": float(imgs.mean(axis=(1, 2)).std(ddof=1))
                         / np.sqrt(len(imgs)), "pixel_var_per_spp": var, "var_x_ms": var * ms,
                         "compile_s": r[k]["compile_s"], "runs": r[k]})
        mine = rows[-len(media):]
        print(f"  {res}^3: " + ", ".join(f"{r_['medium']} {r_['ratio']:.1f}x homogeneous, variance x ms "
                                         f"{r_['var_x_ms']:.2f}" for r_ in mine[1:]), flush=True)
    mitsuba = None
    if args.mitsuba:
        spp_mi = 1024
        jf.render_mitsuba(REPO / "data_synthetic" / "scenes" / "grid_fog.json", spp=4, overrides=ov)  # warm-up
        with Stopwatch() as sw:
            jf.render_mitsuba(REPO / "data_synthetic" / "scenes" / "grid_fog.json", spp=spp_mi, overrides=ov)
        mitsuba = {"spp": spp_mi, "ms_per_spp": 1e3 * sw.s / spp_mi, "variant": "scalar_rgb"}
    cols = [("grid", "grid"), ("medium", "medium"), ("ms/spp", "ms_per_spp", ".1f"),
            ("x homogeneous (interleaved)", "ratio", ".1f"), ("image mean", "mean", ".4f"), ("± se", "mean_se", ".4f"),
            ("pixel variance / spp", "pixel_var_per_spp", ".3f"), ("variance x ms", "var_x_ms", ".2f"),
            ("compile s", "compile_s", ".1f")]
    print_table(rows, cols)
    if mitsuba:
        print(f"Mitsuba 3 (scalar_rgb), 16^3: {mitsuba['ms_per_spp']:.1f} ms/spp")
    out = out_dir("grid") if args.out is None else args.out
    write_json(Path(out) / "grid.json", {"command": command("benchmarks.bench_grid", argv), "size": args.size,
                                    "spp": args.spp, "max_depth": args.max_depth, "cells": args.cells, "rows": rows,
                                    "mitsuba": mitsuba})
    return 0


if __name__ == "__main__":
    sys.exit(main())
