"""The main job's two views fitted against nearly noise-free targets: is the spread of the estimate over fit seeds
the target's noise or the fit's own? (docs/results/fit_accuracy.md, "Where the seed-to-seed spread comes from")

    PYTHONPATH=. python benchmarks/fit_clean_target.py [--seeds 0 1 2 3] [--equal-weights] [--cache DIR]

The target of each view (spot_fog, spot_fog_low at the fit's 8 x 8 px) is the mean of 8 "detached" renders of 32,768
spp at the truth (keys 9000-9007; cached in `--cache` as .npy); each seed is one fit from the main job's start
(sigma_t 0.25, g 0.3) at 256 spp with `FitConfig`'s defaults (`--equal-weights`: weight_power 0). Prints each fit's
estimate, standard error and rounds.
"""

from __future__ import annotations

import argparse
import os

import jax
import numpy as np

import jaxfog


def clean_views(cache: str):
    from fitting.problem import View

    views = []
    for name in ("spot_fog", "spot_fog_low"):
        sc = jaxfog.load_scene(f"data_synthetic/scenes/{name}.json", ["camera.width=8", "camera.height=8"]).scene
        path = os.path.join(cache, f"clean_{name}_detached.npy")
        if not os.path.exists(path):
            imgs = [np.asarray(jaxfog.render(sc, jax.random.key(9000 + k), 32768, estimator="detached"), np.float64)
                    for k in range(8)]
            np.save(path, np.mean(imgs, axis=0))
            print(name, "image means of the 8 renders", [round(float(i.mean()), 6) for i in imgs], flush=True)
        t = np.load(path).astype(np.float32)
        views.append(View(sc, t, name, 8 * 32768, np.zeros_like(t), 1))
    return views


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    ap.add_argument("--cache", default="/tmp/jaxfog_clean_target")
    ap.add_argument("--equal-weights", action="store_true", help="weight_power=0 (no per-pixel weights)")
    args = ap.parse_args()
    jaxfog.use_cpu_cores()
    from jaxfog.tools import use_compilation_cache

    use_compilation_cache()
    from fitting.solver import FitConfig, fit_views

    os.makedirs(args.cache, exist_ok=True)
    views = clean_views(args.cache)
    extra = {"weight_power": 0.0} if args.equal_weights else {}
    for s in args.seeds:
        r = fit_views(views, ["sigma_t", "g"], {"sigma_t": 0.25, "g": 0.3}, FitConfig(spp=256, seed=s, **extra),
                      log=lambda *a: None)
        se = {n: r.uncertainty[n]["se"] for n in r.names}
        print(f"seed {s}: sigma_t {r.params['sigma_t']:.4f} ± {se['sigma_t']:.4f}, g {r.params['g']:.4f} ± "
              f"{se['g']:.4f}, {r.rounds} rounds, success {r.success}", flush=True)


if __name__ == "__main__":
    main()
