"""Variance of chromatic free-flight sampling: one-sample spectral MIS against a scalar rate
(`HomogeneousMedium(..., spectral_mis=False)`).

For two RGB media in the `spot_fog` scene (32 x 32), both schemes render `keys` independent images of `spp`
samples each; both are unbiased, so the per-pixel MSE of an image is its variance over keys. Times are the median
of the timed renders (after compilation), alternating the two schemes. The MSE at equal time scales the scalar
scheme's MSE by its time ratio (MSE ~ 1 / time): `MSE_old * t_old / t_mis` is the old scheme's MSE had it run as
long as spectral MIS. Writes `chromatic.json` to `--out` (default `bench_out/bench_chromatic/`); the table of a run is
in `docs/results/chromatic.md`.

    python -m benchmarks.bench_chromatic [--keys 16] [--spp 32] [--size 32] [--out FILE.json]
"""

from __future__ import annotations

import argparse

import equinox as eqx
import jax
import numpy as np

import jaxfog as jf

from .common import command, interleave, out_dir, print_json, write_json

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
    ap.add_argument("--out", default=str(out_dir("bench_chromatic") / "chromatic.json"))
    a = ap.parse_args(argv)
    base = jf.load_scene(a.scene).scene
    rows = []
    for name, kw in MEDIA.items():
        scenes = {mis: scene_with(base, a.size, jf.HomogeneousMedium(**kw, phase=base.medium.phase, spectral_mis=mis))
                  for mis in (True, False)}
        # the two schemes alternate image by image (the same key k for both), after one compiling render each
        t = interleave({mis: (lambda k, sc=sc: np.asarray(jf.render(sc, jax.random.fold_in(jax.random.key(77), k),
                                                                    a.spp), np.float64)) for mis, sc in scenes.items()},
                       a.keys, alternate=True, keep=True)
        res = {}
        for mis in (True, False):
            x = np.stack(t[mis]["values"])
            res[mis] = dict(mse=x.var(axis=0, ddof=1).mean(axis=(0, 1)).tolist(), mean=x.mean(axis=(0, 1, 2)).tolist(),
                            time=t[mis]["median_s"])
        # per-channel reference: the grey medium with that channel's values (both schemes are the same there)
        ref = []
        for c in range(3):
            grey = scene_with(base, a.size, jf.HomogeneousMedium(kw["sigma_t"][c], kw["albedo"][c], base.medium.phase))
            g_imgs = [np.asarray(jf.render(grey, jax.random.fold_in(jax.random.key(5000 + c), k), a.spp), np.float64)
                      for k in range(a.keys)]
            g = np.stack(g_imgs)[..., c].mean(axis=(1, 2))
            ref.append(dict(mean=float(g.mean()), se=float(g.std(ddof=1) / np.sqrt(len(g)))))
        for mis in (True, False):
            x = np.stack(t[mis]["values"]).mean(axis=(1, 2))
            res[mis]["mean_se"] = (x.std(axis=0, ddof=1) / np.sqrt(len(x))).tolist()
        ratio = res[False]["time"] / res[True]["time"]
        rows.append(dict(medium=name, **kw, spp=a.spp, keys=a.keys, size=a.size, mis=res[True], scalar=res[False],
                         grey_reference=ref,
                         scalar_mse_at_equal_time=[m * ratio for m in res[False]["mse"]]))
        print_json(rows[-1])
    write_json(a.out, dict(scene=a.scene, rows=rows, command=command("python -m benchmarks.bench_chromatic", argv)))
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
