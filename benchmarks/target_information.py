"""How precisely can the foreign suite's Mitsuba targets determine each parameter? The standard error their own noise
leaves, per fit resolution and weighting.

    python benchmarks/target_information.py [--cases spot_dense,...] [--downscales 8,4,2] [--spp 1024] [--out F.json]

For each case of `data_synthetic/foreign/manifest.json` expected to pass, at its truth: the Jacobian of every fit
pixel from two independent forward-mode passes of `--spp` samples per pixel (`fitting.problem.Problem.pass_`, the
fit's own derivative), the targets' noise from the fit's block estimate (`fitting.problem.block_noise`, measured
within 0.8-1.4x of the difference of two Mitsuba renders of spot_denser), and the fit's own sandwich covariance
(`fitting.rounds.model_covariance`, a pixel's three channels one draw) with only the target's variance in it: the
standard error that no number of render passes can take below, for

- `downscale` f: the fit pools f x f target pixels into one (the fit's default: 8 x 8 fit pixels);
- `weights`: the fit's default (`render^0.5`: the renders' per-sample variance to the power -1/2) and generalised
  least squares with the target's own variance (`target^1`, which the block estimate allows only where it is
  smooth), the best a fit with these weights could do.

A parameter with `2 se > tolerance` (`fitting.suite.tolerance`) at every row is one the targets do not determine to
the suite's tolerance. Prints a table, writes JSON (default `bench_out/target_information/target_information.json`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks import common  # noqa: E402

WEIGHTINGS = (("render^0.5", "render", 0.5), ("target^1", "target", 1.0))


def case_rows(case: dict, downscales: list[int], spp: int) -> list[dict]:
    """One row per (downscale, weighting, parameter) of `case` at its truth."""
    import jax

    import jaxfog
    from fitting import suite
    from fitting.params import jacobian_to_params, to_unconstrained
    from fitting.problem import Problem, make_view
    from fitting.rounds import model_covariance, normal_matrix, weights

    names, rows = case["fit"], []
    y = np.asarray(to_unconstrained(names, {n: case["truth"][n] for n in names}), np.float64)
    for f in downscales:
        views = []
        for v in case["views"]:
            target, _ = jaxfog.read_exr(suite.REPO / v["target"])
            views.append(make_view(jaxfog.load_scene(suite.REPO / v["scene"]).scene, target, v["scene"], f))
        problem = Problem(views, names)
        sw = common.Stopwatch()
        a = problem.pass_(y, jax.random.key(1), spp)
        b = problem.pass_(y, jax.random.key(2), spp)
        var_t = problem.target_variance(None)
        J = 0.5 * (a.J + b.J)
        for label, kind, power in WEIGHTINGS:
            base = 0.5 * (a.u + b.u) if kind == "render" else var_t
            w = weights(problem, base, power, 1)
            A_inv = np.linalg.inv(normal_matrix(a.J, b.J, w))
            d = jacobian_to_params(names, y)  # d(parameter) / d(unconstrained coordinate)
            se = np.abs(d) * np.sqrt(np.diag(model_covariance(A_inv, J, w, var_t, problem.pixel_of)))
            for n, s in zip(names, se):
                tol = suite.tolerance(n, case["truth"][n])
                rows.append({"case": case["name"], "fit_px": f"{views[0].target.shape[1]}x{views[0].target.shape[0]}",
                             "downscale": f, "weights": label, "param": n, "se_target": float(s),
                             "tolerance": tol, "reachable": bool(2 * s <= tol),
                             "seconds": sw.s})
    return rows


def main(argv=None) -> int:
    from fitting import suite

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default=None, help="comma-separated case names (default: every case expected to pass)")
    ap.add_argument("--downscales", default="8,4,2", help="fit pooling factors of the 64 x 64 targets (default 8,4,2)")
    ap.add_argument("--spp", type=int, default=1024, help="samples per fit pixel of each Jacobian pass")
    ap.add_argument("--out", default=str(common.out_dir("target_information") / "target_information.json"))
    args = ap.parse_args(argv)
    cases = [c for c in suite.load_manifest()["cases"] if c["expect"] == "pass"]
    if args.cases:
        want = args.cases.split(",")
        unknown = sorted(set(want) - {c["name"] for c in cases})
        if unknown:
            ap.error(f"--cases: unknown or not expected to pass: {unknown}")
        cases = [c for c in cases if c["name"] in want]
    downscales = [int(x) for x in args.downscales.split(",")]
    rows = [r for c in cases for r in case_rows(c, downscales, args.spp)]
    common.print_table(rows, [("case", "case"), ("fit px", "fit_px"), ("weights", "weights"), ("param", "param"),
                              ("se (targets)", "se_target", ".4f"), ("tolerance", "tolerance", ".4f"),
                              ("2 se <= tol", "reachable")], markdown=True)
    common.write_json(args.out, {"command": common.command("python benchmarks/target_information.py", argv),
                                 "spp": args.spp, "rows": rows})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
