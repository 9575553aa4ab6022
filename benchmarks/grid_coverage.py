"""How often the voxel fit's standard errors hold the truth, with and without its closing step: a Gauss-Newton fit
of a target set (`--iterations` steps at `--spp`, as `python -m fitting.grid` runs it), then, on one dense
information at the end point (`fitting.grid.dense_information`), the standard errors three ways:

- "no closing step": the end point, with the covariance at the weight the discrepancy principle left;
- "closing at that weight": one dense Gauss-Newton step at that weight, its covariance;
- "closing at the evidence's weight" (what the fit does): the same at `evidence_weight`'s weight.

    python data_synthetic/make_grid_fit.py --truth layer --seed 500 --out SET   # or any set of four views
    python -m benchmarks.grid_coverage SET [SET2 ...] [--iterations 12] [--spp 128]

Each set is a folder with `front`, `side`, `back` and `left` (`.json` / `.exr`) whose scenes hold the truth grid.
Prints, per set and variant, the voxels within 1 and 2 standard errors of the truth (log-density), the mean and
rms of the errors in standard errors, and the volume error; writes `bench_out/grid_coverage/grid_coverage.json`.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from .common import command, machine_info, out_dir, print_table, write_json

VIEWS = ("front", "side", "back", "left")


def coverage(theta, cov, truth) -> dict:
    import numpy as np

    from fitting.grid import volume_error

    se = np.sqrt(np.maximum(np.diag(cov), 0.0))
    z = (theta - np.log(truth).ravel()) / se
    return {"within_1": float(np.mean(np.abs(z) < 1)), "within_2": float(np.mean(np.abs(z) < 2)),
            "mean_z": float(z.mean()), "rms_z": float(np.sqrt(np.mean(z ** 2))),
            "volume_error": volume_error(theta.reshape(truth.shape), truth)}


def one_set(folder: Path, iterations: int, spp: int) -> list[dict]:
    import jax
    import jax.numpy as jnp
    import numpy as np

    from fitting import grid as G

    views = G.load_views([(folder / f"{v}.json", folder / f"{v}.exr") for v in VIEWS], None)
    truth = np.asarray(views[0][0].medium.density)[..., 0] * float(views[0][0].medium.scale)
    t0 = time.perf_counter()
    density, _, hist = G.fit_grid_gauss_newton(views, iterations=iterations, spp=spp, start=0.3, seed=0,
                                               smooth="auto", truth=truth, standard_errors=False)
    fit_s = time.perf_counter() - t0
    w_end = hist[-1]["weight"]
    theta0 = np.log(density).ravel()
    key = jax.random.fold_in(jax.random.key(0), 10 ** 6)  # the fit's own closing key
    F, g = G.dense_information(views, jnp.asarray(np.log(density), jnp.float32), max(spp, G.SE_SPP_MIN), key)
    L = G.prior_hessian(density.shape, 0.5)  # the graph Laplacian

    def closed(w):
        delta, cov = G.newton_step(F, g, theta0, L, w)
        return theta0 + delta, cov

    w_ev = G.evidence_weight(F, g, theta0, L, w_end)
    rows = [{"variant": "no closing step", "weight": w_end, **coverage(theta0, closed(w_end)[1], truth)},
            {"variant": "closing at that weight", "weight": w_end, **coverage(*closed(w_end), truth)},
            {"variant": "closing at the evidence's weight", "weight": w_ev, **coverage(*closed(w_ev), truth)}]
    for r in rows:
        r.update(set=folder.name, voxels=int(truth.size), fit_s=fit_s)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.grid_coverage", description=__doc__.split("\n\n")[0])
    ap.add_argument("sets", nargs="+", help="target-set folders (four views each)")
    ap.add_argument("--iterations", type=int, default=12)
    ap.add_argument("--spp", type=int, default=128)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    missing = [f"{s}/{v}.{e}" for s in args.sets for v in VIEWS for e in ("json", "exr")
               if not (Path(s) / f"{v}.{e}").is_file()]
    if missing:
        ap.error(f"missing: {', '.join(missing)}")
    rows = []
    for s in args.sets:
        rows += one_set(Path(s), args.iterations, args.spp)
        print_table(rows[-3:], [("set", "set"), ("variant", "variant"), ("weight", "weight", ".3g"),
                                ("within 1 se", "within_1", ".0%"), ("within 2 se", "within_2", ".0%"),
                                ("mean z", "mean_z", "+.2f"), ("rms z", "rms_z", ".2f"),
                                ("volume error", "volume_error", ".3f")])
    out = out_dir("grid_coverage") if args.out is None else Path(args.out)
    write_json(Path(out) / "grid_coverage.json", {"command": command("benchmarks.grid_coverage", argv),
                                                  "rows": rows, "machine": machine_info()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
