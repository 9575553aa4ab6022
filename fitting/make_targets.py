"""Render the shipped fitting targets with known ground truth into `data_synthetic/targets/`.

    python -m fitting.make_targets [--spp 256] [--out data_synthetic/targets] [--only NAME ...] [--views SCENE ...]

Each target is rendered with the "detached" estimator and a seed from 10_000 up (fits use "proposal" and seed 0 by
default), so a fit never depends on reproducing its own noise. Writes `<name>.exr` (truth, spp, seed, scene and
jaxfog version in the header) and `manifest.json`.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import jax
import numpy as np
from tqdm import tqdm

import jaxfog

from .fit import write_json_atomic
from .params import apply

SCENES = "data_synthetic/scenes"
TRUTHS = {
    # name: (truth, description)
    "mid": ({"sigma_t": 0.5, "g": 0.6, "albedo": 0.9}, "the benchmark medium"),
    "denser_less_forward": ({"sigma_t": 0.8, "g": 0.3, "albedo": 0.9}, "denser fog, mildly forward"),
    "thin_backward": ({"sigma_t": 0.25, "g": -0.3, "albedo": 0.9}, "thin fog, backward scattering"),
}
VIEWS = ("spot_fog", "spot_fog_low")
HEIGHT_TRUTHS = {
    "height_mid": ({"sigma_0": 0.6, "height_scale": 0.7, "g": 0.5}, "height fog: a layer a bit denser and thinner"
                   " than the scene files' (sigma_0 0.5, H 0.8)"),
}
HEIGHT_VIEWS = ("height_fog_ground", "height_fog_above")
"""Height-fog targets: the view along the ground and the view from above pin H together."""
MODEL_GROUPS = {
    # chromatic media and the phase functions beyond HG; 32 x 32 views, max_depth 3 (docs/results/fit_models.md)
    "rgb_haze": ({"sigma_t[r]": 0.3, "sigma_t[g]": 0.5, "sigma_t[b]": 0.8, "g": 0.5, "albedo": 0.9},
                 "chromatic haze, extinction rising from red to blue, HG g 0.5", ("chromatic_fit_side", "chromatic_fit_low")),
    "droplet_8um": ({"diameter": 8.0, "sigma_t": 0.3, "albedo": 0.9}, "fog of 8 um droplets (Jendersie & d'Eon 2023)",
                    ("droplet_fit_backlit", "droplet_fit_side", ("droplet_fit_halo", 10016))),
    "two_term": ({"g1": 0.8, "g2": -0.4, "w": 0.7, "sigma_t": 0.5, "albedo": 0.9},
                 "two-term HG fog: forward lobe 0.8 (weight 0.7), backward lobe -0.4", ("twoterm_fit_backlit", "twoterm_fit_side")),
}
"""Targets of the chromatic and phase-function fits, seeds after the height-fog ones. A view added to a
group after its seeds were given is a `(view, seed)` pair with a seed after all the others (`droplet_fit_halo`: the
narrow view of the halo that pins the droplet diameter, docs/results/fit_models.md), so no other target's seed moves."""
MESH_GROUPS = {
    # a triangle mesh (a bumpy torus of 21,504 triangles, BVH) in the benchmark medium
    "mesh_mid": ({"sigma_t": 0.5, "g": 0.6, "albedo": 0.9}, "the benchmark medium around a triangle mesh",
                 ("mesh_fog",)),
}
"""Targets of the mesh-scene fit (docs/results/mesh.md), seeds after the phase-function ones."""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m fitting.make_targets", description=__doc__.split("\n\n")[0])
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--out", default="data_synthetic/targets")
    ap.add_argument("--only", nargs="*", default=None, help="truth names to render (default all)")
    ap.add_argument("--views", nargs="*", default=None, help="of those, only these views (scene names; default all)")
    args = ap.parse_args(argv)
    from jaxfog.tools import use_cpu_cores

    use_cpu_cores()  # every core as a JAX device (a no-op once JAX has started, e.g. under pytest)
    os.makedirs(args.out, exist_ok=True)
    manifest_path = os.path.join(args.out, "manifest.json")
    manifest = json.load(open(manifest_path)) if os.path.exists(manifest_path) else {"targets": []}
    done = {t["file"]: t for t in manifest["targets"]}
    seed = 10_000
    groups = [(name, value, VIEWS) for name, value in TRUTHS.items()]
    groups += [(name, value, HEIGHT_VIEWS) for name, value in HEIGHT_TRUTHS.items()]
    groups += [(name, (truth, desc), views) for name, (truth, desc, views) in MODEL_GROUPS.items()]
    groups += [(name, (truth, desc), views) for name, (truth, desc, views) in MESH_GROUPS.items()]
    for tname, (truth, desc), views in groups:
        for view in views:
            if isinstance(view, tuple):  # added later, with its own seed: the counter (the others' seeds) stays
                view, view_seed = view
            else:
                seed += 1
                view_seed = seed
            if (args.only and tname not in args.only) or (args.views and view not in args.views):
                continue
            scene_path = os.path.join(SCENES, f"{view}.json")
            sf = jaxfog.load_scene(scene_path)
            scene = apply(sf.scene, truth)
            fname = f"{view}__{tname}.exr"
            bar = tqdm(total=args.spp, desc=fname, unit="spp", file=sys.stdout)
            t0 = time.perf_counter()

            def progress(done_spp, total):
                bar.update(done_spp - bar.n)

            img = jaxfog.render(scene, jax.random.key(view_seed), args.spp, estimator="detached", progress=progress)
            img = np.asarray(img)
            bar.close()
            meta = {"jaxfog:truth": json.dumps(truth), "jaxfog:spp": args.spp, "jaxfog:seed": view_seed,
                    "jaxfog:scene_file": scene_path, "jaxfog:estimator": "detached",
                    "jaxfog:version": jaxfog.__version__}
            jaxfog.write_exr(os.path.join(args.out, fname), img, meta)
            done[fname] = {"file": fname, "scene": scene_path, "truth": truth, "description": desc,
                           "spp": args.spp, "seed": view_seed, "estimator": "detached",
                           "jaxfog_version": jaxfog.__version__, "mean_pixel": float(img.mean()),
                           "render_s": round(time.perf_counter() - t0, 1)}
            manifest["targets"] = sorted(done.values(), key=lambda t: t["file"])
            write_json_atomic(manifest_path, manifest)
    return 0


if __name__ == "__main__":
    sys.exit(main())
