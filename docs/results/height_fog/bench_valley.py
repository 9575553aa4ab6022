"""ms/spp of the valley scene (height fog) against the same scene with homogeneous fog, one interleaved run.

    PYTHONPATH=. python docs/results/height_fog/bench_valley.py [--spp 8] [--reps 4]

Both scenes are compiled first (a warm-up render each), then rendered alternately `reps` times at the scene's
resolution (128 x 128) with `spp` samples; reports the median ms per spp (one sample of every pixel) of each.
The homogeneous variant replaces the medium by `{"sigma_t": 0.6, "albedo": 0.92, "g": 0.6}` (sigma_0 of the
height fog, everywhere): its sun is extinguished (an infinite homogeneous medium), the path structure is the same.
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import jax
import numpy as np

import jaxfog as jf


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--spp", type=int, default=8)
    ap.add_argument("--reps", type=int, default=4)
    args = ap.parse_args()
    jf.use_cpu_cores()
    path = "data_synthetic/scenes/valley.json"
    scenes = {"height": jf.load_scene(path).scene,
              "homogeneous": jf.load_scene(path, ["medium={\"sigma_t\": 0.6, \"albedo\": 0.92, \"g\": 0.6}"]).scene}
    times = {k: [] for k in scenes}
    for k, sc in scenes.items():
        np.asarray(jf.render(sc, jax.random.key(99), args.spp))
    for r in range(args.reps):
        for k, sc in scenes.items():
            t0 = time.perf_counter()
            np.asarray(jf.render(sc, jax.random.key(r), args.spp))
            times[k].append(1e3 * (time.perf_counter() - t0) / args.spp)
    out = {k: {"ms_per_spp_median": float(np.median(v)), "ms_per_spp": v} for k, v in times.items()}
    out["machine"] = f"{platform.processor() or platform.machine()}, {jax.device_count()} JAX CPU devices"
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
