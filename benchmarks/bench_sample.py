"""The cost of one path sample in the two programs that matter, and A/B comparisons of two source trees.

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
writes `sample.json` (with `--ab`: `sample_ab[_LABEL].json`) to `--out` (default `bench_out/sample` in the repository).
"""

from __future__ import annotations

import argparse
import itertools
import statistics
import sys
import time
from pathlib import Path

from benchmarks.common import compile_timed, interleave, out_dir, print_json, print_table, scene_path, time_calls
from benchmarks.common import write_json

OUT = out_dir("sample")
SCENE = scene_path("spot_fog")
TECHNIQUES = {"equiangular": False, "light_lobe": 0.0, "distance_mix": 0.0}
"""Mitsuba's techniques only: free flight, phase / BSDF sampling, one light sample per vertex."""
CASES = ("plain", "techniques", "unbounded", "jvp", "jvp256", "call", "plaincall")


def _case(jf, case: str):
    """`(f, arg, n_paths)`: the case as a function `f(arg)` of a key (the renders) or of `(sigma_t, g)` (the fit's
    derivative), with the package `jf`; its argument; the paths one call traces."""
    import jax

    if case in ("jvp", "jvp256", "call"):
        f, y0, n_paths = _fit_render(jf, case)
        return jax.jacfwd(f, has_aux=True), y0, n_paths
    kw = TECHNIQUES if case == "techniques" else {}
    if case.startswith("scene:"):
        scene, spp = jf.load_scene(scene_path(case[len("scene:"):])).scene, 4
    elif case in ("plain", "techniques", "plaincall"):
        small = ["camera.width=8", "camera.height=8"] if case == "plaincall" else []
        scene, spp = jf.load_scene(SCENE, small).scene, 1 if case == "plaincall" else 16
    elif case == "unbounded":
        scene, spp = jf.load_scene(SCENE, ["integrator.max_depth=-1"]).scene, 8
    else:
        raise ValueError(case)
    return (lambda k: jf.render(scene, k, spp, **kw)), jax.random.key(0), scene.camera.width * scene.camera.height * spp


def _build(jf, case: str):
    """`(fn, n_paths)`: a no-argument callable that runs the case once and blocks (`plaincall`: a new key for every
    call, as the fit draws them with `jax.random.fold_in`), and the paths it traces."""
    import jax

    f, arg, n_paths = _case(jf, case)
    if case == "plaincall":
        calls = itertools.count()
        return (lambda: jax.block_until_ready(f(jax.random.fold_in(arg, next(calls))))), n_paths
    return (lambda: jax.block_until_ready(f(arg))), n_paths


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


def run_options(options: dict, cases, reps: int) -> dict:
    """This tree's cases, each jitted whole and compiled twice: A with XLA's defaults, B with `options`; then `reps`
    interleaved pairs (A B, B A, ...). Also the largest difference of the two programs' outputs."""
    import jax
    import jax.numpy as jnp

    import jaxfog as jf

    jf.use_cpu_cores()
    out = {"devices": jax.local_device_count(), "options": options, "cases": {}}
    for c in cases:
        f, arg, n = _case(jf, c)
        fn, args = jax.jit(f), (arg,)  # the case jitted whole: one program to compile with other options
        progs, first = {}, {}
        for tag, opts in (("A", {}), ("B", options)):
            progs[tag], first[tag] = compile_timed(fn, *args, **opts)
        ra, rb = (jax.block_until_ready(progs[t](*args)) for t in "AB")
        diff = max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(jax.tree.leaves(ra), jax.tree.leaves(rb)))
        rec = _pairs({tag: (lambda _, p=progs[tag]: jax.block_until_ready(p(*args))) for tag in "AB"}, n, reps)
        out["cases"][c] = {"paths": n, "first_call_s": first, "compile_s": first, "max_abs_output_difference": diff,
                           **rec}
    return out


def _pairs(fns: dict, n: int, reps: int) -> dict:
    """`reps` interleaved pairs of the compiled `fns["A"]`, `fns["B"]` (A B, B A, ...): `us_per_path` (`{"A": {"wall":
    [...], "cpu": [...]}, "B": ...}`, microseconds per path of `n` paths) and, per measure, the pairs' ratios B / A
    and their median."""
    t = interleave(fns, reps, warmup=0, alternate=True)
    us = lambda x: [v / n * 1e6 for v in x]  # noqa: E731
    return {"us_per_path": {tag: {"wall": us(t[tag]["wall_s"]), "cpu": us(t[tag]["cpu_s"])} for tag in "AB"},
            "wall_ratio_B_over_A": t["B"]["ratio"], "wall_ratio_median": t["B"]["ratio_median"],
            "cpu_ratio_B_over_A": t["B"]["cpu_ratio"], "cpu_ratio_median": t["B"]["cpu_ratio_median"]}


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
                fns[tag, c] = (fn, n, time_calls(lambda _: fn(), 0)["first_call_s"])
        finally:
            if saved is None:
                sys.modules.pop("jaxfog", None)
            else:
                sys.modules["jaxfog"] = saved
    out = {"devices": jax.local_device_count(), "cases": {}}
    for c in cases:
        rec = _pairs({t: (lambda _, f=fns[t, c][0]: f()) for t in "AB"}, fns["A", c][1], reps)
        out["cases"][c] = {"paths": fns["A", c][1], "first_call_s": {t: fns[t, c][2] for t in "AB"}, **rec}
    return out


def run_here(cases, reps: int) -> list[dict]:
    """Time `cases` with this process's `jaxfog` (compiled first); one dict per case."""
    import jaxfog as jf

    jf.use_cpu_cores()
    out = []
    for case in cases:
        fn, n = _build(jf, case)
        t = time_calls(lambda _: fn(), reps)
        us = [x / n * 1e6 for x in t["wall_s"]]
        out.append({"case": case, "paths": n, "first_call_s": t["first_call_s"], "us_per_path": us,
                    "cpu_us_per_path": [x / n * 1e6 for x in t["cpu_s"]], "median_us_per_path": statistics.median(us)})
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
    if not args.ab and not args.xla_option:
        rows = run_here(cases, args.reps)
        if args.json:
            for r in rows:
                print_json(r)
            return 0
        print(f"medians of {args.reps} calls")
        print_table(rows, [("case", "case"), ("paths", "paths"), ("us/path", "median_us_per_path", ".3f"),
                           ("cpu us/path", lambda r: statistics.median(r["cpu_us_per_path"]), ".3f"),
                           ("first call s", "first_call_s", ".1f")])
        out = Path(args.out)
        write_json(out / "sample.json", {"rows": rows, "reps": args.reps,
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
    med = lambda r, t, m: statistics.median(r["us_per_path"][t][m])  # noqa: E731
    rng = lambda r, m: (f"{r[m + '_ratio_median']:.3f} [{min(r[m + '_ratio_B_over_A']):.3f}, "  # noqa: E731
                        f"{max(r[m + '_ratio_B_over_A']):.3f}]")
    print_table([{"case": c, **r} for c, r in res["cases"].items()], [
        ("case", "case"),
        *(c for m in ("wall", "cpu") for c in ((f"A {m}", lambda r, m=m: med(r, "A", m), ".3f"),
                                                (f"B {m}", lambda r, m=m: med(r, "B", m), ".3f"),
                                                (f"B/A {m}", lambda r, m=m: rng(r, m)))),
        ("first call s A/B", lambda r: f"{r['first_call_s']['A']:.1f} / {r['first_call_s']['B']:.1f}")])
    out = Path(args.out)
    name = f"sample_ab{('_' + args.label) if args.label else ''}.json"
    write_json(out / name, {"label": args.label, "A": args.ab[0], "B": args.ab[1], "cases": cases,
                            "reps": args.reps, **res, "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime())})
    print(f"wrote {out / name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
