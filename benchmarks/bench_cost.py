"""The cost of a sample, jaxfog against Mitsuba 3, in one run.

    python -m benchmarks.bench_cost [--scene spot_fog] [--blocks 4] [--reps 3] [--spp 16] [--mitsuba-spp 64]
                                    [--mitsuba-variant llvm_ad_rgb] [--out DIR]
    python -m benchmarks.bench_cost --pool RUN1/cost.json RUN2/cost.json ...   # the block pairs of several runs

Both renderers on every core (jaxfog: `jaxfog.use_cpu_cores()`; Mitsuba: Dr.Jit's thread pool), the scene at its
own size and `max_depth`, no Russian roulette on either side (`jaxfog.to_mitsuba`). The run alternates blocks, so a
drift of the machine's speed hits every row alike: a jaxfog block renders `--reps` images with each jaxfog
configuration (compiled before the first block), a Mitsuba block is one subprocess (`bench_mitsuba.run_mitsuba`) that
compiles its kernels on a warm-up render and then times `--reps` renders of `--mitsuba-spp`. Rows:

- `jaxfog default`: `render(scene, key, spp)` with the default sampling (equiangular, light-angle lobe, distance
  mixture): the sample the equal-error benchmark measures.
- `jaxfog, Mitsuba's techniques`: free flight, phase-function / BSDF sampling and one light sample per vertex only
  (`equiangular=False, light_lobe=0, distance_mix=0`): the work Mitsuba's `volpath` does per sample.
- `Mitsuba volpath`: its `render(scene, spp)` until the pixels are in a numpy array.
- `jaxfog per call`: the fixed cost of one `render` call: the scene at 8 x 8 px, 1 spp (64 paths), per call.

Each figure is ms per sample per pixel of the whole image (per call for the last row): the median over all timed
renders, with min and max; the ratio column divides each jaxfog block's median by the Mitsuba block next to it
(median over the block pairs). Prints a table and writes `cost.json` to `--out` (default `bench_out/cost` in the
repository).
"""

from __future__ import annotations

import argparse
import itertools
import statistics
import sys
import tempfile
from pathlib import Path

from benchmarks.bench_mitsuba import run_mitsuba
from benchmarks.common import command, git_commit, out_dir, print_table, read_json, scene_path, time_calls, write_json

CONFIGS = {
    "jaxfog default": {},
    "jaxfog, Mitsuba's techniques": {"equiangular": False, "light_lobe": 0.0, "distance_mix": 0.0},
}


def _summary(values):
    return {"median": statistics.median(values), "min": min(values), "max": max(values), "n": len(values)}


def table_rows(per: dict, block_medians: dict, mitsuba: list, mitsuba_blocks: list, first: dict) -> list[dict]:
    """The table: per configuration the median, min and max over all its timed renders (ms/spp), its first call
    (s, compile included) and, with Mitsuba, the ratio of each block's median to the Mitsuba block next to it
    (median, min, max over the block pairs); then Mitsuba's row and the per-call row (ms/call)."""
    rows = []
    for name in CONFIGS:
        row = {"row": name, "unit": "ms/spp", **_summary(per[name]), "first_call_s": first[name]}
        if mitsuba_blocks:
            ratios = [a / m["median_ms_per_spp"] for a, m in zip(block_medians[name], mitsuba_blocks)]
            row["ratio_to_mitsuba"] = _summary(ratios)
        rows.append(row)
    if mitsuba:
        rows.append({"row": f"Mitsuba volpath ({mitsuba_blocks[0]['variant']}, {mitsuba_blocks[0]['threads']} "
                            f"threads)", "unit": "ms/spp", **_summary(mitsuba),
                     "first_call_s": statistics.median(m["warmup_s"] for m in mitsuba_blocks)})
    rows.append({"row": "jaxfog per call (8 x 8 px, 1 spp)", "unit": "ms/call", **_summary(per["jaxfog per call"]),
                 "first_call_s": first["jaxfog per call"]})
    return rows


def pooled_ratios(results: list[dict]) -> dict:
    """Every block pair of several runs (their `cost.json` contents) pooled: per jaxfog configuration, the ratios of
    its block medians to the Mitsuba block beside them, with their count, median, geometric mean and quartiles."""
    ratios = {}
    for res in results:
        mb = [m["median_ms_per_spp"] for m in res.get("mitsuba_blocks", [])]
        for name, meds in res["block_medians"].items():
            if name in CONFIGS and mb:
                ratios.setdefault(name, []).extend(a / m for a, m in zip(meds, mb))
    out = {}
    for name, v in ratios.items():
        q = statistics.quantiles(v, n=4) if len(v) >= 2 else [v[0]] * 3
        out[name] = {"n": len(v), "median": statistics.median(v), "geometric_mean": statistics.geometric_mean(v),
                     "q25": q[0], "q75": q[2], "min": min(v), "max": max(v)}
    return out


def _pooled_table(paths) -> None:
    """`--pool`: the ratios of the block pairs of earlier runs' `cost.json` files, pooled."""
    results = [read_json(f) for f in paths]
    print(f"{len(results)} runs pooled; ratio of each jaxfog block's median to the Mitsuba block beside it")
    rows = [{"row": name, **r} for name, r in pooled_ratios(results).items()]
    print_table(rows, [("row", "row"), ("pairs", "n"), *((h, k, ".3f") for h, k in (
        ("median", "median"), ("geo mean", "geometric_mean"), ("q25", "q25"), ("q75", "q75"), ("min", "min"),
        ("max", "max")))])


def _mitsuba_block(path: Path, spp: int, reps: int, seed: int, variant: str) -> dict:
    """One Mitsuba subprocess (its warm-up render compiles, then `reps` timed renders): its record for the table."""
    with tempfile.TemporaryDirectory() as tmp:
        m = run_mitsuba(str(path), None, spp, reps, Path(tmp), seed0=seed, variant=variant)
    if "skipped" in m:
        raise RuntimeError(f"Mitsuba block failed: {m['skipped']}")
    ms = [1000.0 * t / spp for t in m["times"]]
    return {"ms": ms, "median_ms_per_spp": statistics.median(ms), "warmup_s": float(m["warmup_s"]),
            "threads": int(m["threads"]), "variant": str(m["variant"]), "version": str(m["version"]),
            "mean": float(m["images"].mean())}


def build_parser() -> argparse.ArgumentParser:
    """The command line of `python -m benchmarks.bench_cost`."""
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench_cost", description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="spot_fog", help="a shipped scene's name or a .json path (default spot_fog)")
    p.add_argument("--blocks", type=int, default=4, help="alternations of jaxfog and Mitsuba blocks (default 4)")
    p.add_argument("--reps", type=int, default=3, help="timed renders per configuration and block (default 3)")
    p.add_argument("--spp", type=int, default=16, help="jaxfog spp per render (default 16)")
    p.add_argument("--mitsuba-spp", type=int, default=64, help="Mitsuba spp per render (default 64)")
    p.add_argument("--mitsuba-variant", default="llvm_ad_rgb", help="Mitsuba variant (default llvm_ad_rgb)")
    p.add_argument("--no-mitsuba", action="store_true", help="jaxfog rows only")
    p.add_argument("--out", default=str(out_dir("cost")), help="output folder (default bench_out/cost)")
    p.add_argument("--pool", nargs="+", metavar="COST_JSON",
                   help="no run: pool the block pairs of these earlier runs' cost.json files and print the ratios")
    return p


def run_blocks(fns: dict, path: Path, args) -> tuple[dict, dict, list, list]:
    """`args.blocks` alternations of a jaxfog block (`args.reps` renders of each of `fns`) and a Mitsuba block (one
    subprocess, unless `--no-mitsuba`): every timed render per configuration (ms/spp; ms/call for the per-call row),
    each block's median per configuration, every Mitsuba render (ms/spp) and each Mitsuba block's record."""
    per = {name: [] for name in fns}
    block_medians = {name: [] for name in fns}
    mitsuba, mitsuba_blocks = [], []
    for b in range(args.blocks):
        for name, fn in fns.items():
            scale = 1000.0 if name == "jaxfog per call" else 1000.0 / args.spp
            t = time_calls(fn, args.reps, warmup=0)
            per[name] += [x * scale for x in t["wall_s"]]
            block_medians[name].append(t["median_s"] * scale)
        if not args.no_mitsuba:
            m = _mitsuba_block(path, args.mitsuba_spp, args.reps, seed=100 * b, variant=args.mitsuba_variant)
            mitsuba += m.pop("ms")
            mitsuba_blocks.append(m)
        print(f"block {b + 1}/{args.blocks}: " + ", ".join(f"{k} {statistics.median(v[-args.reps:]):.2f}"
                                                          for k, v in per.items())
              + (f", Mitsuba {statistics.median(mitsuba[-args.reps:]):.2f}" if mitsuba else ""), flush=True)
    return per, block_medians, mitsuba, mitsuba_blocks


def main(argv: list[str] | None = None) -> int:
    p = build_parser()
    args = p.parse_args(argv)
    if args.pool:
        _pooled_table(args.pool)
        return 0
    for name in ("blocks", "reps", "spp", "mitsuba_spp"):
        if getattr(args, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1")

    import jaxfog

    jaxfog.use_cpu_cores()
    import jax

    path = scene_path(args.scene)
    sf = jaxfog.load_scene(path)
    scene = sf.scene
    small = jaxfog.load_scene(path, ["camera.width=8", "camera.height=8"]).scene
    cam = scene.camera
    print(f"{path.name}: {cam.width} x {cam.height}, max_depth {scene.max_depth}; {jax.local_device_count()} JAX "
          f"devices; jaxfog {args.spp} spp per render, Mitsuba {args.mitsuba_variant} {args.mitsuba_spp} spp",
          flush=True)

    keys = itertools.count()  # a fresh key for every render
    fns = {name: (lambda _, kw=kw: jaxfog.render(scene, jax.random.key(next(keys)), args.spp, **kw).block_until_ready())
           for name, kw in CONFIGS.items()}
    fns["jaxfog per call"] = lambda _: jaxfog.render(small, jax.random.key(next(keys)), 1).block_until_ready()
    first = {name: time_calls(fn, 1, warmup=0)["wall_s"][0] for name, fn in fns.items()}  # compile included
    per, block_medians, mitsuba, mitsuba_blocks = run_blocks(fns, path, args)

    rows = table_rows(per, block_medians, mitsuba, mitsuba_blocks, first)
    print()
    print_table(rows, [("row", lambda r: f"{r['row']} ({r['unit']})"), ("median", "median", ".2f"),
                       ("min", "min", ".2f"), ("max", "max", ".2f"),
                       ("ratio to Mitsuba (median [min, max])", "ratio_to_mitsuba",
                        lambda x: f"{x['median']:.3f} [{x['min']:.3f}, {x['max']:.3f}]")])
    out = Path(args.out)
    write_json(out / "cost.json", {
        "commit": git_commit(), "command": command("python -m benchmarks.bench_cost", argv),
        "scene": path.name, "width": cam.width, "height": cam.height, "max_depth": scene.max_depth,
        "spp": args.spp, "mitsuba_spp": args.mitsuba_spp, "blocks": args.blocks, "reps": args.reps,
        "rows": rows, "mitsuba_blocks": mitsuba_blocks,
        "per_render": {**per, "mitsuba": mitsuba}, "block_medians": block_medians,
    })
    print(f"wrote {out / 'cost.json'}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
