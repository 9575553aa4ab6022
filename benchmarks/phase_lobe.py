"""The light-angle lobe with and without the phase function's peak aimed at the light (`SamplingOptions.phase_lobe`)
on fog droplets at max_depth 3: variance of the image mean per image and CPU time per image, interleaved A/B.

    python benchmarks/phase_lobe.py [--images 64] [--spp 8] [--out FILE.json]

Each image is one `jaxfog.render` at `spp` with its own key (keys 30000 + k, the same for both settings); the two
settings alternate image by image, so a change in machine load touches both. Writes the JSON to `--out` (default
`bench_out/phase_lobe/phase_lobe.json`); the table of a run is in `docs/results/fit_models.md`. Statistic: the image
mean over all pixels but the central `exclude` x `exclude` (the light's image in the backlit view, as in
`crosscheck_models.py`). Efficiency = 1 / (variance x CPU time); the ratio is phase_lobe 0.5 (the droplets' default)
over 0 (the angle profile alone).
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys

import jax
import numpy as np

import jaxfog

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # as a script: `benchmarks` importable
from benchmarks.common import command, interleave, out_dir, print_table, write_json  # noqa: E402
from benchmarks.crosscheck_models import BACKLIT, DROPLET_8, SIDE, SIZE, pixel_mask  # noqa: E402

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
    ap.add_argument("--out", default=str(out_dir("phase_lobe") / "phase_lobe.json"))
    args = ap.parse_args(argv)
    out = {"date": datetime.date.today().isoformat(), "images": args.images, "spp": args.spp,
           "command": command("python benchmarks/phase_lobe.py", argv), "cases": {}}
    for name, (path, over, exclude) in CASES.items():
        scene = jaxfog.load_scene(path, over).scene
        m = pixel_mask(scene.camera.height, scene.camera.width, exclude)
        opts = {s: jaxfog.SamplingOptions(phase_lobe=s) for s in SETTINGS}
        # per setting, the image means over the mask (the first, compiling call is not timed)
        t = interleave({s: (lambda k, s=s: float(np.asarray(jaxfog.render(
            scene, jax.random.key(30_000 + k), args.spp, sampling=opts[s]))[m, 0].mean())) for s in SETTINGS},
            args.images, alternate=True, keep=True)
        res = {}
        for s in SETTINGS:
            x = np.array(t[s]["values"])
            res[str(s)] = {"mean": x.mean(), "se": x.std(ddof=1) / np.sqrt(len(x)),
                           "rel_sd_per_image": x.std(ddof=1) / x.mean(), "max_image_over_mean": x.max() / x.mean(),
                           "cpu_s_per_image": float(np.mean(t[s]["cpu_s"]))}
        a, b = res["0.0"], res["0.5"]
        res["variance_ratio"] = (a["se"] / b["se"]) ** 2
        res["cpu_ratio"] = b["cpu_s_per_image"] / a["cpu_s_per_image"]
        res["efficiency_ratio"] = res["variance_ratio"] / res["cpu_ratio"]
        res["z"] = (b["mean"] - a["mean"]) / np.hypot(a["se"], b["se"])
        res.update(scene=path, overrides=over, excluded_centre_px=exclude)
        print_table([{"case": name, "phase_lobe": s, **res[str(s)]} for s in SETTINGS], [
            ("case", "case"), ("phase_lobe", "phase_lobe", ".1f"), ("mean", "mean", ".5g"),
            ("SE", lambda r: r["se"] / r["mean"], ".2%"), ("rel SD/img", "rel_sd_per_image", ".3f"),
            ("max/mean", "max_image_over_mean", ".2f"), ("CPU s/img", "cpu_s_per_image", ".3f")])
        print(f"{name:20s} variance ratio {res['variance_ratio']:.2f}, CPU ratio {res['cpu_ratio']:.2f}, "
              f"efficiency ratio {res['efficiency_ratio']:.2f}, z(0.5 - 0) {res['z']:+.2f}", flush=True)
        out["cases"][name] = res
        write_json(args.out, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
