"""Variance of chromatic free-flight sampling: one-sample spectral MIS against the former scalar rate.

For two RGB media in the `spot_fog` scene (32 x 32), both schemes render `keys` independent images of `spp`
samples each; both are unbiased, so the per-pixel MSE of an image is its variance over keys. Times are the median
of the timed renders (after compilation), alternating the two schemes. The MSE at equal time scales the scalar
scheme's MSE by its time ratio (MSE ~ 1 / time): `MSE_old * t_old / t_mis` is the old scheme's MSE had it run as
long as spectral MIS. Writes `docs/results/chromatic.json`; the table is in `docs/results/chromatic.md`.

    python -m benchmarks.bench_chromatic [--keys 16] [--spp 32] [--size 32]
"""

from __future__ import annotations

import argparse
import json
import time

import equinox as eqx
import jax
import numpy as np

import jaxfog as jf

from .common import REPO

MEDIA = {
    "haze (0.5, 1.5, 3.0)": dict(sigma_t=(0.5, 1.5, 3.0), albedo=(0.9, 0.9, 0.9)),
    "thin red, dense blue (0.05, 0.4, 2.0)": dict(sigma_t=(0.05, 0.4, 2.0), albedo=(0.95, 0.9, 0.8)),
}


def scene_with(base: jf.Scene, size: int, medium: jf.HomogeneousMedium) -> jf.Scene:
    cam = base.camera
    cam = jf.Camera(origin=cam.origin, target=cam.target, up=cam.up, fov=cam.fov, width=size, height=size)
    return eqx.tree_at(lambda s: (s.camera, s.medium), base, (cam, medium))


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--keys", type=int, default=16)
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--size", type=int, default=32)
    ap.add_argument("--scene", default="data_synthetic/scenes/spot_fog.json")
    ap.add_argument("--out", default=str(REPO / "docs" / "results" / "chromatic.json"))
    a = ap.parse_args(argv)
    base = jf.load_scene(a.scene).scene
    rows = []
    for name, kw in MEDIA.items():
        scenes = {mis: scene_with(base, a.size, jf.HomogeneousMedium(**kw, phase=base.medium.phase, spectral_mis=mis))
                  for mis in (True, False)}
        imgs = {True: [], False: []}
        times = {True: [], False: []}
        for mis in (True, False):  # compile
            jax.block_until_ready(jf.render(scenes[mis], jax.random.key(999), a.spp))
        for k in range(a.keys):
            for mis in ((True, False) if k % 2 == 0 else (False, True)):
                t0 = time.perf_counter()
                img = jax.block_until_ready(jf.render(scenes[mis], jax.random.fold_in(jax.random.key(77), k), a.spp))
                times[mis].append(time.perf_counter() - t0)
                imgs[mis].append(np.asarray(img, np.float64))
        res = {}
        for mis in (True, False):
            x = np.stack(imgs[mis])
            res[mis] = dict(mse=x.var(axis=0, ddof=1).mean(axis=(0, 1)).tolist(), mean=x.mean(axis=(0, 1, 2)).tolist(),
                            time=float(np.median(times[mis])))
        # per-channel reference: the grey medium with that channel's values (both schemes are the same there)
        ref = []
        for c in range(3):
            grey = scene_with(base, a.size, jf.HomogeneousMedium(kw["sigma_t"][c], kw["albedo"][c], base.medium.phase))
            g_imgs = [np.asarray(jf.render(grey, jax.random.fold_in(jax.random.key(5000 + c), k), a.spp), np.float64)
                      for k in range(a.keys)]
            g = np.stack(g_imgs)[..., c].mean(axis=(1, 2))
            ref.append(dict(mean=float(g.mean()), se=float(g.std(ddof=1) / np.sqrt(len(g)))))
        for mis in (True, False):
            x = np.stack(imgs[mis]).mean(axis=(1, 2))
            res[mis]["mean_se"] = (x.std(axis=0, ddof=1) / np.sqrt(len(x))).tolist()
        ratio = res[False]["time"] / res[True]["time"]
        rows.append(dict(medium=name, **kw, spp=a.spp, keys=a.keys, size=a.size, mis=res[True], scalar=res[False],
                         grey_reference=ref,
                         scalar_mse_at_equal_time=[m * ratio for m in res[False]["mse"]]))
        print(json.dumps(rows[-1]), flush=True)
    with open(a.out, "w") as f:
        json.dump(dict(scene=a.scene, rows=rows), f, indent=1)


if __name__ == "__main__":
    main()
