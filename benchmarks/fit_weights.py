"""Per-pixel noise weights (GLS) against equal weights in the fit's averaging rounds, over fit seeds, on the main
job's shipped targets (or the noise-free ones of `fit_clean_target`): which estimate is closer to the truth, and do
the reported standard errors cover it? (docs/results/fit_accuracy.md, "Noise weights or equal weights")

    PYTHONPATH=. python benchmarks/fit_weights.py [--seeds 0 1 2 3 4 5] [--clean] [--variants gls equal]
        [--out docs/results/fit_weights.json]

Each seed is one fit from the main job's start (sigma_t 0.25, g 0.3; 256 spp; `FitConfig` defaults, `noise_weights`
True for "gls", False for "equal"); the variants alternate seed by seed (gls, equal, gls, ...) so a change of the
machine's load touches both alike. Prints one row per fit and a summary per variant: mean error, the spread of the
estimates over seeds (the fit's own noise: the target is common to every seed), the mean reported standard error and
its parts, and the fraction of fits within 2 of their standard errors. Writes the rows and the summary as JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

import jaxfog

TRUTH = {"sigma_t": 0.5, "g": 0.6}
INIT = {"sigma_t": 0.25, "g": 0.3}
VARIANTS = {"gls": {"noise_weights": True}, "equal": {"noise_weights": False},
            "gls16": {"noise_weights": True, "value_spp_factor": 16},
            "equal16": {"noise_weights": False, "value_spp_factor": 16},
            "equal_lm": {"noise_weights": False, "first_round": "lm"},
            "gls_lm": {"noise_weights": True, "first_round": "lm"},
            "gls_s1": {"noise_weights": True, "weight_smoothing": 1},
            "gls_half": {"noise_weights": True, "weight_smoothing": 1, "weight_power": 0.5}}
"""Named `FitConfig` changes: per-pixel noise weights or equal weights, averaging rounds at 32 x spp (the default)
or 16 x spp, round 0 a split pass (the default) or an LM solve ("_lm"; "gls_lm" is the loop before equal weights and
the split first round); "gls_s1": GLS with each pixel's variance averaged over its 3 x 3 neighbourhood;
"gls_half": the same with weights `v^(-1/4)` instead of `v^(-1/2)` (half-way to equal weights)."""


def shipped_views():
    """The main job's two views (spot_fog, spot_fog_low, `mid` targets) at the fit's 8 x 8 px."""
    from fitting.core import make_view
    from fitting.fit import auto_downscale

    views = []
    for name in ("spot_fog", "spot_fog_low"):
        sc = jaxfog.load_scene(f"data_synthetic/scenes/{name}.json").scene
        target, meta = jaxfog.read_exr(f"data_synthetic/targets/{name}__mid.exr")
        f = auto_downscale(sc.camera.width, sc.camera.height)
        views.append(make_view(sc, target, f"{name}__mid.exr", f, int(meta["jaxfog:spp"])))
    return views


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4, 5])
    ap.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=["gls", "equal"])
    ap.add_argument("--clean", action="store_true", help="the noise-free targets of fit_clean_target instead")
    ap.add_argument("--cache", default="/tmp/jaxfog_clean_target")
    ap.add_argument("--out", default=None, help="JSON file (default: print only)")
    args = ap.parse_args()
    jaxfog.use_cpu_cores()
    from jaxfog._cache import use_compilation_cache

    use_compilation_cache()
    from benchmarks.common import machine_info
    from fitting.core import FitConfig, fit_views

    if args.clean:
        from benchmarks.fit_clean_target import clean_views

        os.makedirs(args.cache, exist_ok=True)
        views = clean_views(args.cache)
    else:
        views = shipped_views()
    names = list(TRUTH)
    rows = []
    print(f"{'variant':<6} {'seed':>4} " + " ".join(f"{n + ' (err/se)':>22}" for n in names) + f" {'rounds':>6} "
          f"{'wall s':>7}", flush=True)
    for s in args.seeds:
        for v in args.variants:
            t0 = time.perf_counter()
            r = fit_views(views, names, dict(INIT), FitConfig(spp=256, seed=s, **VARIANTS[v]),
                          log=lambda *_: None)
            wall = time.perf_counter() - t0
            row = {"variant": v, "seed": s, "success": r.success, "rounds": r.rounds, "wall_s": wall,
                   "params": r.params, "uncertainty": r.uncertainty}
            rows.append(row)
            print(f"{v:<6} {s:>4} " + " ".join(
                f"{r.params[n]:>9.4f} ({(r.params[n] - TRUTH[n]) / r.uncertainty[n]['se']:+5.1f} se)"
                for n in names) + f" {r.rounds:>6} {wall:>7.1f}" + ("" if r.success else "  FAILED"), flush=True)
    summary = {}
    for v in args.variants:
        rs = [x for x in rows if x["variant"] == v]
        out = {}
        for n in names:
            est = np.array([x["params"][n] for x in rs])
            se = np.array([x["uncertainty"][n]["se"] for x in rs])
            out[n] = {"mean_error": float(est.mean() - TRUTH[n]),
                      "sd_over_seeds": float(est.std(ddof=1)) if len(est) > 1 else None,
                      "rms_error": float(np.sqrt(np.mean((est - TRUTH[n]) ** 2))),
                      "mean_se": float(se.mean()),
                      "mean_se_render": float(np.mean([x["uncertainty"][n]["se_render"] for x in rs])),
                      "mean_se_target": float(np.mean([x["uncertainty"][n]["se_target"] for x in rs])),
                      "within_2se": float(np.mean(np.abs(est - TRUTH[n]) <= 2 * se))}
        out["mean_wall_s"] = float(np.mean([x["wall_s"] for x in rs]))
        out["rounds"] = [x["rounds"] for x in rs]
        summary[v] = out
    print()
    print(f"{'variant':<6} {'param':<8} {'mean err':>9} {'sd seeds':>9} {'rms err':>9} {'mean se':>9} "
          f"{'se rend':>9} {'se targ':>9} {'in 2 se':>7}")
    for v, out in summary.items():
        for n in names:
            o = out[n]
            print(f"{v:<6} {n:<8} {o['mean_error']:>+9.4f} {o['sd_over_seeds'] or float('nan'):>9.4f} "
                  f"{o['rms_error']:>9.4f} {o['mean_se']:>9.4f} {o['mean_se_render']:>9.4f} "
                  f"{o['mean_se_target']:>9.4f} {o['within_2se']:>7.2f}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"machine": machine_info(), "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                       "command": "PYTHONPATH=. python benchmarks/fit_weights.py " + " ".join(
                           f"--{k.replace('_', '-')} {' '.join(map(str, a)) if isinstance(a, list) else a}"
                           for k, a in vars(args).items() if a not in (None, False) and k != "cache"),
                       "truth": TRUTH, "init": INIT, "clean": args.clean, "rows": rows, "summary": summary},
                      f, indent=2)
        print("wrote", args.out)


if __name__ == "__main__":
    main()
