"""The light-angle lobe with and without the phase function's peak aimed at the light (`SamplingOptions.phase_lobe`)
on fog droplets at max_depth 3: variance of the image mean per image and CPU time per image, interleaved A/B.

    PYTHONPATH=. python benchmarks/phase_lobe.py [--images 64] [--spp 8]

Each image is one `jaxfog.render` at `spp` with its own key (keys 30000 + k, the same for both settings); the two
settings alternate image by image, so a change in machine load touches both. Writes `docs/results/phase_lobe.json`;
the table is in `docs/results/fit_models.md`. Statistic: the image mean over all pixels but the central `exclude` x
`exclude` (the light's image in the backlit view, as in `crosscheck_models.py`). Efficiency = 1 / (variance x CPU
time); the ratio is phase_lobe 0.5 (the droplets' default) over 0 (the angle profile alone).
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys
import time

import jax
import numpy as np

import jaxfog

sys.path.insert(0, os.path.dirname(__file__))
from crosscheck_models import BACKLIT, DROPLET_8, SIDE, SIZE, pixel_mask, save_json  # noqa: E402

CASES = {
    "droplet_side_d3": (SIDE, DROPLET_8 + ["integrator.max_depth=3"], 0),
    "droplet_backlit_d3": (BACKLIT, SIZE + DROPLET_8 + ["integrator.max_depth=3"], 4),
    "droplet_side_d4": (SIDE, DROPLET_8 + ["integrator.max_depth=4"], 0),
}
SETTINGS = (0.0, 0.5)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--images", type=int, default=64)
    ap.add_argument("--spp", type=int, default=8)
    ap.add_argument("--out", default="docs/results/phase_lobe.json")
    args = ap.parse_args(argv)
    out = {"machine": f"{platform.machine()} {platform.processor()}, {os.cpu_count()} CPUs, CPU only",
           "date": datetime.date.today().isoformat(), "images": args.images, "spp": args.spp,
           "command": "PYTHONPATH=. python benchmarks/phase_lobe.py " + " ".join(argv or sys.argv[1:]), "cases": {}}
    print(f"{'case':20s} {'phase_lobe':>10s} {'mean':>10s} {'SE':>7s} {'rel SD/img':>10s} {'max/mean':>8s} "
          f"{'CPU s/img':>9s}")
    for name, (path, over, exclude) in CASES.items():
        scene = jaxfog.load_scene(path, over).scene
        h, w = scene.camera.height, scene.camera.width
        m = pixel_mask(h, w, exclude)
        opts = {s: jaxfog.SamplingOptions(phase_lobe=s) for s in SETTINGS}
        for s in SETTINGS:  # compile outside the timed loop
            jaxfog.render(scene, jax.random.key(0), args.spp, sampling=opts[s]).block_until_ready()
        means = {s: [] for s in SETTINGS}
        cpu = {s: 0.0 for s in SETTINGS}
        for k in range(args.images):
            for s in (SETTINGS if k % 2 == 0 else SETTINGS[::-1]):
                c0 = time.process_time()
                img = np.asarray(jaxfog.render(scene, jax.random.key(30_000 + k), args.spp, sampling=opts[s]))
                cpu[s] += time.process_time() - c0
                means[s].append(float(img[m, 0].mean()))
        res = {}
        for s in SETTINGS:
            x = np.array(means[s])
            res[str(s)] = {"mean": x.mean(), "se": x.std(ddof=1) / np.sqrt(len(x)),
                           "rel_sd_per_image": x.std(ddof=1) / x.mean(), "max_image_over_mean": x.max() / x.mean(),
                           "cpu_s_per_image": cpu[s] / len(x)}
            r = res[str(s)]
            print(f"{name:20s} {s:10.1f} {r['mean']:10.5g} {r['se'] / r['mean']:7.2%} {r['rel_sd_per_image']:10.3f} "
                  f"{r['max_image_over_mean']:8.2f} {r['cpu_s_per_image']:9.3f}", flush=True)
        a, b = res["0.0"], res["0.5"]
        res["variance_ratio"] = (a["se"] / b["se"]) ** 2
        res["cpu_ratio"] = b["cpu_s_per_image"] / a["cpu_s_per_image"]
        res["efficiency_ratio"] = res["variance_ratio"] / res["cpu_ratio"]
        res["z"] = (b["mean"] - a["mean"]) / np.hypot(a["se"], b["se"])
        res.update(scene=path, overrides=over, excluded_centre_px=exclude)
        print(f"{name:20s} variance ratio {res['variance_ratio']:.2f}, CPU ratio {res['cpu_ratio']:.2f}, "
              f"efficiency ratio {res['efficiency_ratio']:.2f}, z(0.5 - 0) {res['z']:+.2f}", flush=True)
        out["cases"][name] = res
        save_json(args.out, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
