"""Paths of any length: cost of fixed depth 8 against unbounded depth (Russian roulette + path regeneration), and
the dense fog rendered without bias against Mitsuba 3's unbounded `volpath`.

    python -m benchmarks.bench_depth [--size 128] [--out docs/results/unbounded]

1. ms/spp of spot_fog_thin, spot_fog and spot_fog_dense at `max_depth` 8 and -1, interleaved in one process
   (A B A B ..., after compilation; median of the rounds and the median of the per-round ratios).
2. spot_fog_dense (sigma_t = 3) at `max_depth` -1 in jaxfog and in Mitsuba (`scalar_rgb` variant, `rr_depth` 5,
   `max_depth` -1), independent images on both sides: the image mean and 4 x 4 block means with their standard
   errors, z = difference / combined SE; and the bias of jaxfog at fixed depths 8 and 32 against the same
   unbounded estimate. Needs the `compare` extra (skipped without Mitsuba).
"""

from __future__ import annotations

import argparse
import datetime
import time

import numpy as np

from .common import REPO, block_means, load, machine_info, write_json


def timing(size: int, spp: int, rounds: int, log=print) -> dict:
    import jax

    import jaxfog as jf

    out = {}
    for name in ("spot_fog_thin", "spot_fog", "spot_fog_dense"):
        scenes = {d: load(name, size, [f"integrator.max_depth={d}"]).scene for d in (8, -1)}
        for d, sc in scenes.items():  # compile
            jf.render(sc, jax.random.key(0), spp).block_until_ready()
        times = {8: [], -1: []}
        for r in range(rounds):
            for d, sc in scenes.items():
                t0 = time.perf_counter()
                jf.render(sc, jax.random.key(1 + r), spp).block_until_ready()
                times[d].append((time.perf_counter() - t0) / spp * 1e3)
        ratio = np.median(np.asarray(times[-1]) / np.asarray(times[8]))
        out[name] = {"ms_per_spp_depth8": times[8], "ms_per_spp_unbounded": times[-1], "ratio_median": float(ratio)}
        log(f"{name:16s} depth 8: {np.median(times[8]):7.1f} ms/spp   unbounded: {np.median(times[-1]):7.1f} ms/spp"
            f"   unbounded/8 (median of rounds): {ratio:.2f}")
    return out


def _mean_se(images):
    a = np.asarray(images, np.float64)
    return a.mean(0), a.std(0, ddof=1) / np.sqrt(len(a))


def dense_vs_mitsuba(size: int, n_images: int, spp: int, mi_spp: int, log=print) -> dict | None:
    try:
        import mitsuba as mi
    except ImportError:
        log("mitsuba not installed (pip install '.[compare]'): dense-fog cross-check skipped")
        return None
    import jax

    import jaxfog as jf

    mi.set_variant("scalar_rgb")  # the LLVM variants need a newer libLLVM than some machines have
    name = "spot_fog_dense"
    jx = {}
    for depth in (-1, 8, 32):
        sc = load(name, size, [f"integrator.max_depth={depth}"]).scene
        imgs = [np.asarray(jf.render(sc, jax.random.fold_in(jax.random.key(900 + depth), k), spp))
                for k in range(n_images)]
        jx[depth] = imgs
    msc = mi.load_dict(jf.to_mitsuba(load(name, size, ["integrator.max_depth=-1"])))
    t0 = time.perf_counter()
    mimgs = [np.asarray(mi.render(msc, spp=mi_spp, seed=1000 + k)) for k in range(n_images)]
    mi_time = time.perf_counter() - t0
    res = {"size": size, "n_images": n_images, "jaxfog_spp": spp, "mitsuba_spp": mi_spp,
           "mitsuba_seconds": mi_time}

    def compare(a_imgs, b_imgs, label):
        ma, sa = _mean_se([im.mean() for im in a_imgs])
        mb, sb = _mean_se([im.mean() for im in b_imgs])
        ba, bsa = _mean_se([block_means(im) for im in a_imgs])
        bb, bsb = _mean_se([block_means(im) for im in b_imgs])
        z = (ba - bb) / np.sqrt(bsa**2 + bsb**2)
        zm = (ma - mb) / np.hypot(sa, sb)
        row = {"mean_a": ma, "se_a": sa, "mean_b": mb, "se_b": sb, "z_mean": zm, "ratio": ma / mb,
               "block_z_max": float(np.abs(z).max()), "block_frac_z_gt_3": float(np.mean(np.abs(z) > 3))}
        log(f"{label:36s} {ma:.5g} +- {sa:.2g} vs {mb:.5g} +- {sb:.2g}: ratio {ma / mb:.4f}, z {zm:+.2f}; "
            f"4x4 blocks max |z| {row['block_z_max']:.2f}")
        return row

    res["unbounded_vs_mitsuba"] = compare(jx[-1], mimgs, "jaxfog -1 vs Mitsuba -1 (rr 5)")
    res["depth8_vs_unbounded"] = compare(jx[8], jx[-1], "jaxfog depth 8 vs jaxfog -1")
    res["depth32_vs_unbounded"] = compare(jx[32], jx[-1], "jaxfog depth 32 vs jaxfog -1")
    return res


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--size", type=int, default=128, help="image size for the timing (default 128)")
    p.add_argument("--spp", type=int, default=8, help="spp per timed call (default 8)")
    p.add_argument("--rounds", type=int, default=3, help="interleaved rounds (default 3)")
    p.add_argument("--dense-size", type=int, default=64, help="image size of the dense-fog cross-check")
    p.add_argument("--dense-images", type=int, default=16, help="independent images per side")
    p.add_argument("--dense-spp", type=int, default=32, help="jaxfog spp per image")
    p.add_argument("--mitsuba-spp", type=int, default=32, help="Mitsuba spp per image")
    p.add_argument("--out", default=str(REPO / "docs" / "results" / "unbounded"), help="output folder")
    args = p.parse_args(argv)
    import jaxfog as jf

    jf.use_cpu_cores()
    result = {"date": datetime.date.today().isoformat(), "command": "python -m benchmarks.bench_depth "
              + " ".join(argv or []), "machine": machine_info()}
    result["timing"] = timing(args.size, args.spp, args.rounds)
    result["dense"] = dense_vs_mitsuba(args.dense_size, args.dense_images, args.dense_spp, args.mitsuba_spp)
    write_json(f"{args.out}/bench_depth.json", result)
    print(f"wrote {args.out}/bench_depth.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
