"""The cost of one path sample in the two programs that matter, and A/B comparisons of two source trees (issue 17).

    python -m benchmarks.bench_sample [--case plain|jvp|both] [--reps N]                 # this tree, one process
    python -m benchmarks.bench_sample --ab TREE_A TREE_B [--reps N] [--case ...] [--label NAME] [--out DIR]
    python -m benchmarks.bench_sample --xla-option NAME=VALUE [--reps N] [--case ...] [--label NAME]

Cases (both cores as JAX devices, `jaxfog.use_cpu_cores()`, as the command-line tools and the fit run):
- `plain`: `render(spot_fog, key, 16)` at 128 x 128, max_depth 8 (the defaults).
- `techniques`: the same with Mitsuba's techniques only (`equiangular=False, light_lobe=0, distance_mix=0`).
- `unbounded`: the same scene with `max_depth = -1` (paths of any length, Russian roulette), 8 spp.
- `jvp`: the fit's program: `jax.jacfwd` over (sigma_t, g) of `render(..., estimator="proposal", proposal=<the
  medium at the same values>, variance=True)` of spot_fog downscaled to 8 x 8 px (the camera's fov kept), 2048 spp
  (the shape of `fitting.problem.Problem.pass_`).
- `jvp256`: the same at 256 spp (the fit's default spp: one call per view and Levenberg-Marquardt step).
- `call`: the same at 2 spp (128 paths): the fixed cost of one `render` call under `jax.jacfwd` (its figures are
  per path too: multiply by 128 for the time per call).
- `plaincall`: `render(spot_fog at 8 x 8 px, key, 1)` (64 paths), a new key each call (`fold_in`, as the fit draws
  them): the fixed cost of a plain call (multiply by 64).
- `scene:NAME`: `render(NAME, key, 4)`, a shipped scene (`data_synthetic/scenes/NAME.json`) at its own size.

Each case is compiled once (the first call, reported apart), then timed `--reps` times, in us per path (one path =
one sample of one pixel), wall-clock and process CPU time (all threads; steadier than wall time on a shared machine).
With `--ab`, the packages `jaxfog/` of two source trees (e.g. a copy of the last commit and the working tree) are
imported into one process (as `jaxfog_a`, `jaxfog_b`), both compiled, and their calls interleaved A B, B A, A B, ...:
each pair gives a ratio B/A (B faster: < 1), printed as median [min, max] over the pairs, so a drift of the machine's
speed hits both sides alike. With `--xla-option`, this tree's cases are each jitted whole, lowered once and compiled
twice, with XLA's defaults (A) and with the given compiler options (B), then interleaved the same way (XLA_FLAGS
cannot differ inside one process; the JSON also has the largest difference of the two programs' outputs). Only
ratios inside one run mean anything on a shared machine. Prints a table and
writes `sample.json` (with `--ab`: `sample_ab[_LABEL].json`) to `--out` (default docs/results/bench/sample in the repository).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "bench_out" / "sample"
SCENE = REPO / "data_synthetic" / "scenes" / "spot_fog.json"
TECHNIQUES = {"equiangular": False, "light_lobe": 0.0, "distance_mix": 0.0}
"""Mitsuba's techniques only: free flight, phase / BSDF sampling, one light sample per vertex."""
CASES = ("plain", "techniques", "unbounded", "jvp", "jvp256", "call", "plaincall")


def _build(jf, case: str):
    """`(fn, n_paths)`: a no-argument callable that runs the case once with the package `jf` and blocks, and the
    paths it traces."""
    import jax

    key = jax.random.key(0)
    if case.startswith("scene:"):
        scene = jf.load_scene(SCENE.parent / f"{case[len('scene:'):]}.json").scene

        def fn():
            jf.render(scene, key, 4).block_until_ready()

        return fn, scene.camera.width * scene.camera.height * 4
    if case == "plaincall":  # a new key for every call, as the fit draws them (`jax.random.fold_in`)
        scene, spp = _plain_case(jf, case)
        calls = iter(range(1 << 30))

        def fn():
            jf.render(scene, jax.random.fold_in(key, next(calls)), spp).block_until_ready()

        return fn, scene.camera.width * scene.camera.height * spp
    if case in ("plain", "techniques", "unbounded"):
        scene, spp = _plain_case(jf, case)
        kw = TECHNIQUES if case == "techniques" else {}

        def fn():
            jf.render(scene, key, spp, **kw).block_until_ready()

        return fn, scene.camera.width * scene.camera.height * spp
    if case in ("jvp", "jvp256", "call"):
        f, y0, n_paths = _fit_render(jf, case)
        jac = jax.jacfwd(f, has_aux=True)

        def fn():
            jax.block_until_ready(jac(y0))

        return fn, n_paths
    raise ValueError(case)


def _plain_case(jf, case: str):
    """`(scene, spp)` of a plain-render case: spot_fog at 16 spp, or with paths of any length at 8 spp."""
    if case == "unbounded":
        return jf.load_scene(SCENE, ["integrator.max_depth=-1"]).scene, 8
    if case == "plaincall":
        return jf.load_scene(SCENE, ["camera.width=8", "camera.height=8"]).scene, 1
    return jf.load_scene(SCENE).scene, 16


def _fit_render(jf, case: str):
    """`(f, y0, n_paths)` of a fit-render case: `f(y)` is the "proposal" render with its variance of spot_fog at
    8 x 8 px as a function of `y = (sigma_t, g)` (as `fitting.problem.Problem.pass_`), `y0` the scene's."""
    import jax
    import jax.numpy as jnp

    key = jax.random.key(0)
    scene = jf.load_scene(SCENE, overrides=["camera.width=8", "camera.height=8"]).scene
    spp = {"jvp": 2048, "jvp256": 256, "call": 2}[case]
    ref = jax.lax.stop_gradient(scene.medium)

    def f(y):
        sc = scene.replace_medium(sigma_t=jnp.full(3, y[0]), g=y[1])
        img, var = jf.render(sc, key, spp, estimator="proposal", proposal=ref, variance=True)
        return img.ravel(), jax.lax.stop_gradient(var)

    y0 = jnp.array([float(scene.medium.sigma_t[0]), float(scene.medium.phase.g)], jnp.float32)
    return f, y0, scene.camera.width * scene.camera.height * spp


def _build_jitted(jf, case: str):
    """`(jitted, args, n_paths)`: the case as one `jax.jit`-ed function of its arguments (the render inside it), to be
    lowered once and compiled with different XLA compiler options."""
    import jax

    key = jax.random.key(0)
    if case in ("plain", "techniques", "unbounded", "plaincall"):
        scene, spp = _plain_case(jf, case)
        kw = TECHNIQUES if case == "techniques" else {}
        return jax.jit(lambda k: jf.render(scene, k, spp, **kw)), (key,), scene.camera.width * scene.camera.height * spp
    f, y0, n_paths = _fit_render(jf, case)
    return jax.jit(jax.jacfwd(f, has_aux=True)), (y0,), n_paths


def run_options(options: dict, cases, reps: int) -> dict:
    """This tree's cases, each jitted whole and compiled twice: A with XLA's defaults, B with `options`; then `reps`
    interleaved pairs (A B, B A, ...). Also the largest difference of the two programs' outputs."""
    import jax
    import jax.numpy as jnp

    import jaxfog as jf

    jf.use_cpu_cores()
    out = {"devices": jax.local_device_count(), "options": options, "cases": {}}
    for c in cases:
        fn, args, n = _build_jitted(jf, c)
        lowered = fn.lower(*args)
        progs, first = {}, {}
        for tag, opts in (("A", None), ("B", options)):
            t = time.perf_counter()
            progs[tag] = lowered.compile(compiler_options=opts)
            first[tag] = time.perf_counter() - t
        ra, rb = (jax.block_until_ready(progs[t](*args)) for t in "AB")
        diff = max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(jax.tree.leaves(ra), jax.tree.leaves(rb)))
        rec = _interleaved(lambda tag: _timed(lambda: jax.block_until_ready(progs[tag](*args)), n), reps)
        out["cases"][c] = {"paths": n, "first_call_s": first, "compile_s": first, "max_abs_output_difference": diff,
                           "us_per_path": rec, **_ratios(rec)}
    return out


def _interleaved(run, reps: int) -> dict:
    """`reps` pairs of `run("A")`, `run("B")` in alternating order (A B, B A, ...); each returns `(wall, cpu)` (us per
    path). Returns `{"A": {"wall": [...], "cpu": [...]}, "B": ...}`."""
    rec = {tag: {"wall": [], "cpu": []} for tag in "AB"}
    for r in range(reps):
        for tag in ("AB" if r % 2 == 0 else "BA"):
            w, cpu = run(tag)
            rec[tag]["wall"].append(w)
            rec[tag]["cpu"].append(cpu)
    return rec


def _ratios(rec: dict) -> dict:
    """Per measure, the pairs' ratios B / A and their median."""
    out = {}
    for m in ("wall", "cpu"):
        ratios = [b / a for a, b in zip(rec["A"][m], rec["B"][m])]
        out[f"{m}_ratio_B_over_A"] = ratios
        out[f"{m}_ratio_median"] = statistics.median(ratios)
    return out


def _load_tree(tree: str, name: str):
    """The package `jaxfog` of the source tree `tree`, imported under the module name `name` (its modules import
    one another relatively). While its scenes are built, `jaxfog` names it (the scene loader builds Modules of
    `jaxfog`), so each tree renders its own classes."""
    import importlib.util

    root = Path(tree).resolve() / "jaxfog"
    spec = importlib.util.spec_from_file_location(name, root / "__init__.py", submodule_search_locations=[str(root)])
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def _timed(fn, n: int) -> tuple[float, float]:
    """One call of `fn`: (wall, process CPU) microseconds per path."""
    w, c = time.perf_counter(), time.process_time()
    fn()
    return (time.perf_counter() - w) / n * 1e6, (time.process_time() - c) / n * 1e6


def run_ab(tree_a: str, tree_b: str, cases, reps: int) -> dict:
    """Both trees in this process: each case compiled for both, then `reps` interleaved pairs (A B, then B A, ...)."""
    import jax

    saved = sys.modules.get("jaxfog")
    mods = {}
    fns = {}
    for tag, tree in (("A", tree_a), ("B", tree_b)):
        mods[tag] = _load_tree(tree, f"jaxfog_{tag.lower()}")
        if not fns:
            mods[tag].use_cpu_cores()
        sys.modules["jaxfog"] = mods[tag]
        try:
            for c in cases:
                fn, n = _build(mods[tag], c)
                t = time.perf_counter()
                fn()
                fns[tag, c] = (fn, n, time.perf_counter() - t)
        finally:
            if saved is None:
                sys.modules.pop("jaxfog", None)
            else:
                sys.modules["jaxfog"] = saved
    out = {"devices": jax.local_device_count(), "cases": {}}
    for c in cases:
        rec = _interleaved(lambda tag: _timed(fns[tag, c][0], fns[tag, c][1]), reps)
        out["cases"][c] = {"paths": fns["A", c][1], "first_call_s": {t: fns[t, c][2] for t in "AB"},
                           "us_per_path": rec, **_ratios(rec)}
    return out


def run_here(cases, reps: int) -> list[dict]:
    """Time `cases` with this process's `jaxfog` (compiled first); one dict per case."""
    import jaxfog as jf

    jf.use_cpu_cores()
    out = []
    for case in cases:
        fn, n = _build(jf, case)
        t = time.perf_counter()
        fn()
        first = time.perf_counter() - t
        wall, cpu = zip(*(_timed(fn, n) for _ in range(reps)))
        out.append({"case": case, "paths": n, "first_call_s": first, "us_per_path": list(wall),
                    "cpu_us_per_path": list(cpu), "median_us_per_path": statistics.median(wall)})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--case", default="both", help="plain, jvp, both, or a comma-separated list")
    ap.add_argument("--reps", type=int, default=3, help="timed calls (with --ab: interleaved pairs) per case (default 3)")
    ap.add_argument("--ab", nargs=2, metavar=("TREE_A", "TREE_B"), help="compare the jaxfog/ of two source trees")
    ap.add_argument("--xla-option", action="append", metavar="NAME=VALUE", default=[],
                    help="compare this tree's programs compiled with XLA's defaults (A) and with these compiler options "
                         "(B), e.g. xla_cpu_prefer_vector_width=512 (repeatable)")
    ap.add_argument("--out", default=str(OUT), help="output folder for sample_ab.json")
    ap.add_argument("--label", default="", help="a name for this comparison (stored in the JSON)")
    ap.add_argument("--json", action="store_true", help="print one JSON line per case only")
    args = ap.parse_args(argv)
    cases = list(CASES) if args.case == "both" else args.case.split(",")
    from benchmarks.common import machine_info, write_json

    if not args.ab and not args.xla_option:
        rows = run_here(cases, args.reps)
        if args.json:
            for r in rows:
                print(json.dumps(r))
            return 0
        print(f"{'case':<6} {'paths':>7} {'us/path':>8} {'cpu us/path':>11} {'first call s':>12}  (medians of "
              f"{args.reps})")
        for r in rows:
            print(f"{r['case']:<6} {r['paths']:7d} {r['median_us_per_path']:8.3f}"
                  f" {statistics.median(r['cpu_us_per_path']):11.3f} {r['first_call_s']:12.1f}")
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        write_json(out / "sample.json", {"rows": rows, "reps": args.reps, "machine": machine_info(),
                                         "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime())})
        print(f"wrote {out / 'sample.json'}")
        return 0
    if args.xla_option:
        opts = {}
        for o in args.xla_option:
            k, v = o.split("=", 1)
            opts[k] = int(v) if v.lstrip("-").isdigit() else {"true": True, "false": False}.get(v.lower(), v)
        res = run_options(opts, cases, args.reps)
        args.ab = ("XLA defaults", f"compiler options {opts}")
    else:
        res = run_ab(args.ab[0], args.ab[1], cases, args.reps)
    print(f"A = {args.ab[0]}\nB = {args.ab[1]}\none process, {res['devices']} devices, {args.reps} interleaved "
          f"pairs per case (A B, B A, ...); us per path: medians; ratios B/A pair by pair: median [min, max]")
    print(f"{'case':<6} {'A wall':>7} {'B wall':>7} {'B/A wall':>22} {'A cpu':>7} {'B cpu':>7} {'B/A cpu':>22}"
          f" {'first call s A/B':>16}")
    for c, r in res["cases"].items():
        u = r["us_per_path"]
        med = lambda t, m: statistics.median(u[t][m])
        rng = lambda m: (f"{r[m + '_ratio_median']:.3f} [{min(r[m + '_ratio_B_over_A']):.3f}, "
                         f"{max(r[m + '_ratio_B_over_A']):.3f}]")
        print(f"{c:<6} {med('A', 'wall'):7.3f} {med('B', 'wall'):7.3f} {rng('wall'):>22} {med('A', 'cpu'):7.3f}"
              f" {med('B', 'cpu'):7.3f} {rng('cpu'):>22} {r['first_call_s']['A']:7.1f} /{r['first_call_s']['B']:5.1f}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    name = f"sample_ab{('_' + args.label) if args.label else ''}.json"
    write_json(out / name, {"label": args.label, "A": args.ab[0], "B": args.ab[1], "cases": cases,
                            "reps": args.reps, **res, "machine": machine_info(),
                            "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime())})
    print(f"wrote {out / name}")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(REPO)) if str(REPO) not in sys.path else None
    raise SystemExit(main())
