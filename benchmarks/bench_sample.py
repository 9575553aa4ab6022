"""The cost of one path sample in the two programs that matter, and A/B comparisons of two source trees (issue 17).

    python -m benchmarks.bench_sample [--case plain|jvp|both] [--reps N]                 # this tree, one process
    python -m benchmarks.bench_sample --ab TREE_A TREE_B [--pairs N] [--case ...] [--out DIR]

Cases (both cores as JAX devices, `jaxfog.use_cpu_cores()`, as the command-line tools and the fit run):
- `plain`: `render(spot_fog, key, 16)` at 128 x 128, max_depth 8 (the defaults).
- `jvp`: the fit's program: `jax.jacfwd` over (sigma_t, g) of `render(..., estimator="proposal", proposal=<the
  medium at the same values>, variance=True)` of spot_fog downscaled to 8 x 8 px (the camera's fov kept), 2048 spp
  (the shape of `fitting.core.Problem.value_and_jacobian`).

One process compiles each case once (the first call, reported apart), then times `--reps` calls and prints one JSON
line per case: the median and all times, in us per path (one path = one sample of one pixel). With `--ab`, processes
of tree A and tree B (each a source tree holding `jaxfog/`, put first on PYTHONPATH) alternate A B A B ... `--pairs`
times; each pair gives the ratio B/A of the in-process medians (B faster: < 1). Only ratios inside one run mean
anything on a shared machine. Prints a table and writes `sample_ab.json` to `--out` (default
docs/results/bench/sample in the repository).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "docs" / "results" / "bench" / "sample"
SCENE = REPO / "data_synthetic" / "scenes" / "spot_fog.json"
CASES = ("plain", "jvp")


def _build(case: str):
    """`(fn, n_paths)`: a no-argument callable that runs the case once and blocks, and the paths it traces."""
    import jax
    import jax.numpy as jnp

    import jaxfog as jf

    key = jax.random.key(0)
    if case == "plain":
        scene = jf.load_scene(SCENE).scene
        spp = 16

        def fn():
            jf.render(scene, key, spp).block_until_ready()

        return fn, scene.camera.width * scene.camera.height * spp
    if case == "jvp":
        scene = jf.load_scene(SCENE, overrides=["camera.width=8", "camera.height=8"]).scene
        spp = 2048
        ref = jax.lax.stop_gradient(scene.medium)

        def f(y):
            sc = scene.replace_medium(sigma_t=jnp.full(3, y[0]), g=y[1])
            img, var = jf.render(sc, key, spp, estimator="proposal", proposal=ref, variance=True)
            return img.ravel(), jax.lax.stop_gradient(var)

        y0 = jnp.array([float(scene.medium.sigma_t[0]), float(scene.medium.phase.g)], jnp.float32)
        jac = jax.jacfwd(f, has_aux=True)

        def fn():
            jax.block_until_ready(jac(y0))

        return fn, scene.camera.width * scene.camera.height * spp
    raise ValueError(case)


def run_here(cases, reps: int) -> list[dict]:
    """Time `cases` in this process (compile first); one dict per case."""
    import jaxfog as jf

    jf.use_cpu_cores()
    out = []
    for case in cases:
        fn, n = _build(case)
        t = time.perf_counter()
        fn()
        first = time.perf_counter() - t
        times = []
        for _ in range(reps):
            t = time.perf_counter()
            fn()
            times.append((time.perf_counter() - t) / n * 1e6)
        out.append({"case": case, "paths": n, "first_call_s": first, "us_per_path": times,
                    "median_us_per_path": statistics.median(times)})
    return out


def _child(tree: str, cases, reps: int) -> dict:
    env = dict(os.environ, PYTHONPATH=str(Path(tree).resolve()))
    # the benchmark code itself is this file's, whichever tree is measured
    cmd = [sys.executable, str(Path(__file__).resolve()), "--case", ",".join(cases), "--reps", str(reps), "--json"]
    res = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
    return {r["case"]: r for r in map(json.loads, res.stdout.strip().splitlines())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--case", default="both", help="plain, jvp, both, or a comma-separated list")
    ap.add_argument("--reps", type=int, default=3, help="timed calls per case per process (default 3)")
    ap.add_argument("--ab", nargs=2, metavar=("TREE_A", "TREE_B"), help="alternate processes of two source trees")
    ap.add_argument("--pairs", type=int, default=3, help="A/B process pairs (default 3)")
    ap.add_argument("--out", default=str(OUT), help="output folder for sample_ab.json")
    ap.add_argument("--label", default="", help="a name for this comparison (stored in the JSON)")
    ap.add_argument("--json", action="store_true", help="print one JSON line per case only")
    args = ap.parse_args(argv)
    cases = list(CASES) if args.case == "both" else args.case.split(",")
    if not args.ab:
        rows = run_here(cases, args.reps)
        for r in rows:
            if args.json:
                print(json.dumps(r))
            else:
                print(f"{r['case']:<6} {r['median_us_per_path']:7.3f} us/path (median of {args.reps}; "
                      f"{', '.join(f'{x:.3f}' for x in r['us_per_path'])}), first call {r['first_call_s']:.1f} s")
        return 0
    pairs = []
    for i in range(args.pairs):
        a = _child(args.ab[0], cases, args.reps)
        b = _child(args.ab[1], cases, args.reps)
        pairs.append({"A": a, "B": b})
        print(f"  pair {i + 1}/{args.pairs}: " + ", ".join(
            f"{c} {a[c]['median_us_per_path']:.3f} -> {b[c]['median_us_per_path']:.3f} us/path" for c in cases),
            flush=True)
    print(f"\nA = {args.ab[0]}\nB = {args.ab[1]}\n{args.pairs} alternating process pairs, {args.reps} timed calls each")
    print(f"{'case':<6} {'A us/path':>10} {'B us/path':>10} {'B/A median':>10} {'B/A min':>8} {'B/A max':>8}"
          f" {'A first s':>9} {'B first s':>9}")
    summary = {}
    for c in cases:
        ra = [p["A"][c]["median_us_per_path"] for p in pairs]
        rb = [p["B"][c]["median_us_per_path"] for p in pairs]
        ratios = [b / a for a, b in zip(ra, rb)]
        fa = statistics.median(p["A"][c]["first_call_s"] for p in pairs)
        fb = statistics.median(p["B"][c]["first_call_s"] for p in pairs)
        summary[c] = {"A_us_per_path": ra, "B_us_per_path": rb, "ratio_B_over_A": ratios,
                      "ratio_median": statistics.median(ratios), "A_first_call_s": fa, "B_first_call_s": fb}
        print(f"{c:<6} {statistics.median(ra):10.3f} {statistics.median(rb):10.3f} {statistics.median(ratios):10.3f}"
              f" {min(ratios):8.3f} {max(ratios):8.3f} {fa:9.1f} {fb:9.1f}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    from benchmarks.common import machine_info, write_json

    name = f"sample_ab{('_' + args.label) if args.label else ''}.json"
    write_json(out / name, {"label": args.label, "A": args.ab[0], "B": args.ab[1], "cases": cases,
                            "reps": args.reps, "pairs": pairs, "summary": summary, "machine": machine_info(),
                            "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime())})
    print(f"wrote {out / name}")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(REPO)) if str(REPO) not in sys.path else None
    raise SystemExit(main())
