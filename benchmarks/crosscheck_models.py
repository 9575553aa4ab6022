"""Mitsuba 3 cross-check of issue 14's media (chromatic `homogeneous`, two-term HG as `blendphase`, fog droplets as
a `tabphase` of jaxfog's own pdf): image means and 4 x 4 block means per channel, with standard errors over
independent images on both sides.

    PYTHONPATH=. python benchmarks/crosscheck_models.py [--images 16] [--spp 16] [--spp-mitsuba 256] [--only NAME ...]

Writes `docs/results/crosscheck_models.json`; the table is in `docs/results/fit_models.md`. Mitsuba: `scalar_rgb`
(needs no LLVM). z = (jaxfog - Mitsuba) / sqrt(SE_j^2 + SE_m^2), SE = spread of the images / sqrt(images).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import time

import jax
import numpy as np

import jaxfog
from jaxfog._mitsuba import TABPHASE_SIZE, tabphase_error

SIZE = ["camera.width=32", "camera.height=32"]
CASES = {
    # name: (scene file, overrides, what it checks)
    "chromatic_haze": ("data_synthetic/scenes/chromatic_haze.json", SIZE + ["integrator.max_depth=4"],
                       "RGB homogeneous, sigma_t (0.5, 1.5, 3.0), albedo (0.9, 0.85, 0.8), two-term HG (blendphase); "
                       "Mitsuba's volpathmis (spectral MIS): its volpath is heavy-tailed on this medium"),
    "two_term_backlit": ("data_synthetic/scenes/twoterm_fit_backlit.json", [],
                         "grey fog, two-term HG (0.8, -0.4, w 0.7) as blendphase, backlit (forward lobe)"),
    "droplet_backlit": ("data_synthetic/scenes/droplet_backlit.json", SIZE + ["integrator.max_depth=4"],
                        "droplets d = 10 um as tabphase, backlit halo"),
    "droplet_fit_side": ("data_synthetic/scenes/droplet_fit_side.json", [],
                         "droplets d = 8 um as tabphase, side view (angles near 90 degrees: the Draine lobe)"),
}


def render_mitsuba(path, spp, seed, over, integrator):
    """`jaxfog.render_mitsuba`, with the integrator's type replaced (`volpathmis` for chromatic media)."""
    from jaxfog._mitsuba import import_mitsuba

    mi = import_mitsuba("scalar_rgb")
    d = jaxfog.to_mitsuba(path, spp=spp, seed=seed, overrides=over,
                          transform=lambda m: mi.ScalarTransform4f(np.asarray(m, np.float64).tolist()))
    d["integrator"]["type"] = integrator
    return np.asarray(mi.render(mi.load_dict(d), spp=spp, seed=seed), np.float64)[..., :3]


def stats(imgs: np.ndarray) -> dict:
    """Per channel: the image mean and the 4 x 4 block means (mean and SE over the images)."""
    n, h, w, _ = imgs.shape
    whole = imgs.reshape(n, -1, 3).mean(1)  # (n, 3)
    blocks = imgs.reshape(n, 4, h // 4, 4, w // 4, 3).mean(axis=(2, 4)).reshape(n, 16, 3)
    se = lambda x: x.std(0, ddof=1) / np.sqrt(n)  # noqa: E731
    return {"mean": whole.mean(0), "se": se(whole), "block_mean": blocks.mean(0), "block_se": se(blocks)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--images", type=int, default=16)
    ap.add_argument("--spp", type=int, default=16, help="jaxfog's spp per image")
    ap.add_argument("--spp-mitsuba", type=int, default=256, help="Mitsuba's spp per image (its volpath is noisier per"
                    " sample and much cheaper per sample on CPU)")
    ap.add_argument("--only", nargs="*")
    ap.add_argument("--out", default="docs/results/crosscheck_models.json")
    args = ap.parse_args(argv)
    out = json.load(open(args.out)) if os.path.exists(args.out) else {}
    out.update({"machine": f"{platform.machine()} {platform.processor()}, {os.cpu_count()} CPUs, CPU only",
                "date": datetime.date.today().isoformat(), "images": args.images, "spp": args.spp, "spp_mitsuba": args.spp_mitsuba,
                "command": "PYTHONPATH=. python benchmarks/crosscheck_models.py " + " ".join(argv or sys.argv[1:]),
                "tabphase_size": TABPHASE_SIZE})
    out.setdefault("tabphase_error", {})
    for d in (5.0, 8.0, 10.0, 20.0, 50.0):
        out["tabphase_error"][f"{d:g}"] = tabphase_error(d)
    out.setdefault("cases", {})
    for name, (path, over, what) in CASES.items():
        if args.only and name not in args.only:
            continue
        t0 = time.perf_counter()
        scene = jaxfog.load_scene(path, over).scene
        ours = np.stack([np.asarray(jaxfog.render(scene, jax.random.key(20_000 + k), args.spp), np.float64)
                         for k in range(args.images)])
        t1 = time.perf_counter()
        integrator = "volpathmis" if name.startswith("chromatic") else "volpath"
        theirs = np.stack([render_mitsuba(path, args.spp_mitsuba, k, over, integrator) for k in range(args.images)])
        t2 = time.perf_counter()
        j, m = stats(ours), stats(theirs)
        z = (j["mean"] - m["mean"]) / np.sqrt(j["se"] ** 2 + m["se"] ** 2)
        zb = (j["block_mean"] - m["block_mean"]) / np.sqrt(j["block_se"] ** 2 + m["block_se"] ** 2)
        res = {"scene": path, "overrides": over, "what": what, "mitsuba_integrator": integrator,
               "images": args.images, "spp": args.spp, "spp_mitsuba": args.spp_mitsuba,
               "jaxfog": {"mean": j["mean"].tolist(), "se": j["se"].tolist()},
               "mitsuba": {"mean": m["mean"].tolist(), "se": m["se"].tolist()},
               "rel_diff": ((j["mean"] - m["mean"]) / m["mean"]).tolist(), "z": z.tolist(),
               "blocks_max_abs_z": float(np.abs(zb).max()), "blocks_mean_z2": float((zb ** 2).mean()),
               "blocks_n": int(zb.size), "jaxfog_s": round(t1 - t0, 1), "mitsuba_s": round(t2 - t1, 1)}
        out["cases"][name] = res
        print(name, json.dumps({k: res[k] for k in ("jaxfog", "mitsuba", "z", "blocks_max_abs_z", "blocks_mean_z2",
                                                      "jaxfog_s", "mitsuba_s")}), flush=True)
        with open(args.out + ".tmp", "w") as f:
            json.dump(out, f, indent=1)
        os.replace(args.out + ".tmp", args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
