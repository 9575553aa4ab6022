"""Paths of any length: cost of fixed depth 8 against unbounded depth (Russian roulette + path regeneration), and
the dense fog rendered without bias against Mitsuba 3's unbounded `volpath`.

    python -m benchmarks.bench_depth [--parts timing dense] [--size 128] [--cache DIR] [--out docs/results/unbounded]

1. `timing`: ms/spp of spot_fog_thin, spot_fog and spot_fog_dense at `max_depth` 8 and -1, interleaved in one
   process (A B A B ..., after compilation; median of the rounds and the median of the per-round ratios).
2. `dense`: spot_fog_dense (sigma_t = 3) at a small size (default 16 x 16) with many independent images a side:
   jaxfog and Mitsuba (`scalar_rgb` variant) both unbiased (`max_depth` -1, Russian roulette from `rr_depth` 5) and
   both at a fixed depth (default 32) without Russian roulette, and jaxfog's fixed depth against its unbiased
   render. For each pair: the image mean and the 4 x 4 region means with SEs from the spread over the independent
   images, z per region, the relative difference of the image means with its SE, a percentile bootstrap interval of
   the ratio (no normality assumed: the image means are heavy-tailed in this scene) and each side's tail summary
   (largest image's share, median / mean, the two halves' means). `--cache DIR` keeps the images (resumable and
   extendable; `--sides` lets two processes render the two sides). Needs the `compare` extra (skipped without it).

The JSON keeps the part that did not run from an earlier run (`runs` says when and how each part ran).
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


def bootstrap_ratio_ci(a, b, n_boot: int = 4000, seed: int = 0, level: float = 0.95) -> tuple[float, float]:
    """Percentile bootstrap interval of `mean(a) / mean(b)` over independent per-image values `a` and `b` (each side
    resampled on its own): no normal approximation, so it follows the skew of heavy-tailed image means."""
    rng = np.random.default_rng(seed)
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    ra = a[rng.integers(0, len(a), (n_boot, len(a)))].mean(1)
    rb = b[rng.integers(0, len(b), (n_boot, len(b)))].mean(1)
    q = np.quantile(ra / rb, [(1 - level) / 2, (1 + level) / 2])
    return float(q[0]), float(q[1])


def tail_summary(values) -> dict:
    """How heavy-tailed a set of independent per-image means is: the largest image's share of the sum, the median
    over the mean, and the two halves' means (a heavy tail shows as halves that differ by more than their SE)."""
    v = np.asarray(values, np.float64)
    h = len(v) // 2
    return {"largest_share": float(v.max() / v.sum()), "median_over_mean": float(np.median(v) / v.mean()),
            "half_means": [float(v[:h].mean()), float(v[h:].mean())],
            "half_ses": [float(v[:h].std(ddof=1) / np.sqrt(h)), float(v[h:].std(ddof=1) / np.sqrt(len(v) - h))]}


def compare_images(a_imgs, b_imgs, label: str, log=print, blocks: int = 4) -> dict:
    """Means of two independent sets of images (a: jaxfog, b: the other): the image mean and the `blocks x blocks`
    region means with SEs from the spread over images (independent), z per region, the relative difference of the
    image means with its SE (delta method), a bootstrap interval of the ratio, and each side's tail summary."""
    a_m = np.asarray([im.mean() for im in a_imgs], np.float64)
    b_m = np.asarray([im.mean() for im in b_imgs], np.float64)
    ma, sa = _mean_se(a_m)
    mb, sb = _mean_se(b_m)
    ba, bsa = _mean_se([block_means(im, blocks) for im in a_imgs])
    bb, bsb = _mean_se([block_means(im, blocks) for im in b_imgs])
    z = (ba - bb) / np.sqrt(bsa**2 + bsb**2)
    zm = (ma - mb) / np.hypot(sa, sb)
    rel = ma / mb - 1.0
    rel_se = (ma / mb) * np.hypot(sa / ma, sb / mb)
    lo, hi = bootstrap_ratio_ci(a_m, b_m)
    row = {"n_a": len(a_m), "n_b": len(b_m), "mean_a": ma, "se_a": sa, "mean_b": mb, "se_b": sb, "z_mean": zm,
           "ratio": ma / mb, "rel_diff": rel, "rel_diff_se": rel_se, "ratio_bootstrap_95": [lo, hi],
           "block_means_a": ba.tolist(), "block_means_b": bb.tolist(), "block_z": z.tolist(),
           "block_z_max": float(np.abs(z).max()), "block_mean_z2": float(np.mean(z**2)),
           "block_frac_z_gt_3": float(np.mean(np.abs(z) > 3)), "tail_a": tail_summary(a_m), "tail_b": tail_summary(b_m)}
    log(f"{label:40s} {ma:.5g} +- {sa:.2g} ({len(a_m)} images) vs {mb:.5g} +- {sb:.2g} ({len(b_m)}): "
        f"rel. diff {100 * rel:+.1f}% +- {100 * rel_se:.1f}%, z {zm:+.2f}, ratio 95% bootstrap [{lo:.3f}, {hi:.3f}]; "
        f"{blocks}x{blocks} regions max |z| {row['block_z_max']:.2f}, mean z^2 {row['block_mean_z2']:.2f}")
    log("    region z: " + "; ".join(" ".join(f"{x:+.1f}" for x in r) for r in z))
    return row


def _cached_images(path, render_one, n: int, log=print, label: str = "") -> tuple[list, list]:
    """Images `0..n-1` from `render_one(k)` and each one's render time (s; NaN for images from an older cache without
    times), kept in an `.npz` at `path` (None: no cache) so a run can be resumed or extended; the first `n`."""
    import os

    have, secs = [], []
    if path is not None and os.path.exists(path):
        z = np.load(path)
        have = list(z["images"])
        secs = list(z["seconds"]) if "seconds" in z.files else [float("nan")] * len(have)
    t_start = time.perf_counter()
    for k in range(len(have), n):
        t0 = time.perf_counter()
        have.append(np.asarray(render_one(k), np.float32))
        secs.append(time.perf_counter() - t0)
        if path is not None and ((k + 1) % 8 == 0 or k + 1 == n):
            np.savez(path, images=np.stack(have), seconds=np.asarray(secs))
            log(f"  {label}: {k + 1}/{n} images, {time.perf_counter() - t_start:.0f} s")
    return have[:n], secs[:n]


def dense_vs_mitsuba(size: int, n_images: int, spp: int, mi_images: int, mi_spp: int, fixed_depth: int = 32,
                     fixed_images: int = 32, fixed_spp: int = 256, sides=("jaxfog", "mitsuba"), cache=None,
                     log=print) -> dict | None:
    """spot_fog_dense (sigma_t 3) at `size x size`: jaxfog and Mitsuba (`scalar_rgb`) independent images,

    1. unbiased on both sides: `max_depth = -1`, Russian roulette from `rr_depth` 5 (jaxfog keys fold_in(key(899),
       k), `spp` each; Mitsuba seeds 1000 + k, `mi_spp` each);
    2. both at the fixed depth `fixed_depth` without Russian roulette (the same transport but the paths' tails cut:
       far less noise; jaxfog keys fold_in(key(900 + depth), k), Mitsuba seeds 5000 + k, `fixed_spp` each);
    3. jaxfog's fixed depth against its unbiased render (how much light beyond `fixed_depth` segments).
    `sides` renders only those sides (into `cache`, a folder of `.npz` files, so that two processes can share the
    work); the comparison runs when both sides have all their images."""
    import os

    try:
        import mitsuba as mi
    except ImportError:
        log("mitsuba not installed (pip install '.[compare]'): dense-fog cross-check skipped")
        return None
    import jax

    import jaxfog as jf

    mi.set_variant("scalar_rgb")  # the LLVM variants abort on this machine's libLLVM
    name = "spot_fog_dense"
    path = (lambda tag: None) if cache is None else (lambda tag: os.path.join(cache, f"dense_{size}_{tag}.npz"))
    jx, mx = {}, {}
    runs = {-1: (n_images, spp, 899, mi_images, mi_spp, 1000), fixed_depth: (fixed_images, fixed_spp, 900 + fixed_depth,
                                                                            fixed_images, fixed_spp, 5000)}
    times = {}
    for depth, (nj, sj, kj, nm, sm, seed_m) in runs.items():
        over = [f"integrator.max_depth={depth}"]
        if "jaxfog" in sides:
            sc = load(name, size, over).scene
            jx[depth], secs = _cached_images(path(f"jaxfog_d{depth}_spp{sj}"), lambda k: jf.render(
                sc, jax.random.fold_in(jax.random.key(kj), k), sj), nj, log, f"jaxfog depth {depth}")
            times[f"jaxfog_{depth}"] = None if np.all(np.isnan(secs)) else secs
        if "mitsuba" in sides:
            msc = mi.load_dict(jf.to_mitsuba(load(name, size, over)))
            mx[depth], secs = _cached_images(path(f"mitsuba_d{depth}_spp{sm}"), lambda k: np.asarray(
                mi.render(msc, spp=sm, seed=seed_m + k))[..., :3], nm, log, f"Mitsuba depth {depth}")
            times[f"mitsuba_{depth}"] = None if np.all(np.isnan(secs)) else secs
    res = {"size": size, "jaxfog_images": n_images, "jaxfog_spp": spp, "mitsuba_images": mi_images,
           "mitsuba_spp": mi_spp, "fixed_depth": fixed_depth, "fixed_images": fixed_images, "fixed_spp": fixed_spp,
           "seconds_per_image": times, "mitsuba_version": mi.__version__, "mitsuba_variant": "scalar_rgb"}
    if jx and mx:
        res["unbounded_vs_mitsuba"] = compare_images(jx[-1], mx[-1], "jaxfog -1 vs Mitsuba -1 (rr 5)", log)
        res["fixed_vs_mitsuba"] = compare_images(jx[fixed_depth], mx[fixed_depth],
                                                 f"jaxfog {fixed_depth} vs Mitsuba {fixed_depth} (no RR)", log)
    if jx:
        res["fixed_vs_unbounded"] = compare_images(jx[fixed_depth], jx[-1],
                                                   f"jaxfog depth {fixed_depth} vs jaxfog -1", log)
    return res


def main(argv=None) -> int:
    import json
    import os
    import sys

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--parts", nargs="+", choices=("timing", "dense"), default=["timing", "dense"],
                   help="which studies to run (default both); the JSON keeps the other's earlier result")
    p.add_argument("--size", type=int, default=128, help="image size for the timing (default 128)")
    p.add_argument("--spp", type=int, default=8, help="spp per timed call (default 8)")
    p.add_argument("--rounds", type=int, default=3, help="interleaved rounds (default 3)")
    p.add_argument("--dense-size", type=int, default=16, help="image size of the dense-fog cross-check (default 16)")
    p.add_argument("--dense-images", type=int, default=48, help="jaxfog unbiased images (default 48)")
    p.add_argument("--dense-spp", type=int, default=256, help="jaxfog spp per unbiased image (default 256)")
    p.add_argument("--mitsuba-images", type=int, default=192, help="Mitsuba unbiased images (default 192)")
    p.add_argument("--mitsuba-spp", type=int, default=256, help="Mitsuba spp per unbiased image (default 256)")
    p.add_argument("--fixed-depth", type=int, default=32, help="the fixed depth both render too (default 32)")
    p.add_argument("--fixed-images", type=int, default=32, help="images per side at the fixed depth (default 32)")
    p.add_argument("--fixed-spp", type=int, default=256, help="spp per image at the fixed depth (default 256)")
    p.add_argument("--sides", nargs="+", choices=("jaxfog", "mitsuba"), default=["jaxfog", "mitsuba"],
                   help="render only these sides of the cross-check (with --cache, two processes can share it)")
    p.add_argument("--cache", default=None, help="folder for the cross-check's images (resumable; default none)")
    p.add_argument("--out", default=str(REPO / "docs" / "results" / "unbounded"), help="output folder")
    args = p.parse_args(argv)
    import jaxfog as jf

    jf.use_cpu_cores()
    out_json = f"{args.out}/bench_depth.json"
    result = {}
    if os.path.exists(out_json):
        with open(out_json) as fh:
            result = json.load(fh)
    cmd = "python -m benchmarks.bench_depth " + " ".join(sys.argv[1:] if argv is None else argv)
    result.setdefault("runs", {})
    if "timing" in args.parts:
        result["timing"] = timing(args.size, args.spp, args.rounds)
        result["runs"]["timing"] = {"date": datetime.date.today().isoformat(), "command": cmd,
                                    "machine": machine_info()}
    if "dense" in args.parts:
        if args.cache:
            os.makedirs(args.cache, exist_ok=True)
        dense = dense_vs_mitsuba(args.dense_size, args.dense_images, args.dense_spp, args.mitsuba_images,
                                 args.mitsuba_spp, args.fixed_depth, args.fixed_images, args.fixed_spp,
                                 tuple(args.sides), args.cache)
        if set(args.sides) != {"jaxfog", "mitsuba"}:
            print("rendered", args.sides, "only: nothing written")
            return 0
        result["dense"] = dense
        result["runs"]["dense"] = {"date": datetime.date.today().isoformat(), "command": cmd,
                                   "machine": machine_info()}
    write_json(out_json, result)
    print(f"wrote {out_json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
