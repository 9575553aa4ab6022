"""The main job's two views fitted against nearly noise-free targets: is the spread of the estimate over fit seeds
the target's noise or the fit's own? (docs/results/fit_accuracy.md, "Where the seed-to-seed spread comes from")

    PYTHONPATH=. python benchmarks/fit_clean_target.py [--seeds 0 1 2 3] [--long] [--equal-weights] [--cache DIR]

The target of each view (spot_fog, spot_fog_low at the fit's 8 x 8 px) is the mean of 8 "detached" renders of 32,768
spp at the truth (keys 9000-9007; cached in `--cache` as .npy); each seed is one fit from the main job's start
(sigma_t 0.25, g 0.3) at 256 spp with `FitConfig`'s defaults, or with `--long` 18 rounds (precision 1e-6, repeats 7:
only max_rounds stops it). Prints each fit's estimate, standard error and rounds, and the rounds of `--long` fits.
"""

from __future__ import annotations

import argparse
import os

import jax
import numpy as np

import jaxfog


def clean_views(cache: str):
    from fitting.core import View

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
    ap.add_argument("--long", action="store_true")
    ap.add_argument("--cache", default="/tmp/jaxfog_clean_target")
    ap.add_argument("--equal-weights", action="store_true", help="noise_weights=False (no per-pixel GLS weights)")
    args = ap.parse_args()
    jaxfog.use_cpu_cores()
    from jaxfog._cache import use_compilation_cache

    use_compilation_cache()
    from fitting.core import FitConfig, fit_views

    os.makedirs(args.cache, exist_ok=True)
    views = clean_views(args.cache)
    extra = dict(precision=1e-6, repeats=7, max_rounds=18) if args.long else {}
    if args.equal_weights:
        extra["noise_weights"] = False
    for s in args.seeds:
        lines: list[str] = []
        r = fit_views(views, ["sigma_t", "g"], {"sigma_t": 0.25, "g": 0.3}, FitConfig(spp=256, seed=s, **extra),
                      log=lambda *a: lines.append(" ".join(map(str, a))))
        if args.long:
            for line in lines:
                if line.startswith("round"):
                    print(f"seed {s} {line}", flush=True)
        se = {n: r.uncertainty[n]["se"] for n in r.names}
        print(f"seed {s}: sigma_t {r.params['sigma_t']:.4f} ± {se['sigma_t']:.4f}, g {r.params['g']:.4f} ± "
              f"{se['g']:.4f}, {r.rounds} rounds, success {r.success}", flush=True)


if __name__ == "__main__":
    main()
