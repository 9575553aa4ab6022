"""Paths of any length: cost of fixed depth 8 against unbounded depth (Russian roulette + path regeneration), and
the dense fog rendered without bias against Mitsuba 3's unbounded `volpath`.

    python -m benchmarks.bench_depth [--parts timing dense area box limit tails] [--size 128] [--cache DIR]
        [--out DIR]

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

3. `area`: the same cross-check of `area_fog_dense` (spot_fog_dense lit by a rectangular area light: no
   infinite-variance 1/r^2 weight on either side), `--area-images` unbiased and `--area-fixed-images` at the fixed
   depth a side.
4. `box`: the same cross-check of `box_fog_dense` (spot_fog_dense with the fog confined to a box that keeps every
   vertex 0.4 m from the spot light: the spot light and the long paths, with a finite variance on both sides),
   `--box-images` / `--box-mitsuba-images` unbiased and `--box-fixed-images` a side at the fixed depth.
5. `limit`: jaxfog alone on spot_fog_dense, fixed depths `--limit-depths` and -1 with the same keys (paired
   differences: the light beyond each cut), and the unbiased render without the light-seeking techniques.
6. `tails`: the tail index (Hill, survival slope) of single paths (1-spp 256 x 256 images) and of the cached
   images' means, Peng's heavy-tail mean and a truncation lower bound, and a coverage check of Peng's interval.

The JSON (`bench_depth.json` in `--out`, default `bench_out/bench_depth`) keeps the parts that did not run from an
earlier run (`runs` says when and how each part ran).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys

import numpy as np

from .common import Stopwatch, block_means, command, interleave, load, machine_info, mean_and_se, out_dir, read_json
from .common import save_npz, scene_path, write_json


def timing(size: int, spp: int, rounds: int, log=print) -> dict:
    """ms/spp of spot_fog_thin, spot_fog and spot_fog_dense at `max_depth` 8 and -1, interleaved (keys 1 + round)."""
    import jax

    import jaxfog as jf

    out = {}
    for name in ("spot_fog_thin", "spot_fog", "spot_fog_dense"):
        scenes = {d: load(name, size, [f"integrator.max_depth={d}"]).scene for d in (8, -1)}
        t = interleave({d: (lambda r, sc=sc: jf.render(sc, jax.random.key(1 + r), spp).block_until_ready())
                        for d, sc in scenes.items()}, rounds)
        ms = {d: [x / spp * 1e3 for x in t[d]["wall_s"]] for d in scenes}
        ratio = t[-1]["ratio_median"]
        out[name] = {"ms_per_spp_depth8": ms[8], "ms_per_spp_unbounded": ms[-1], "ratio_median": ratio}
        log(f"{name:16s} depth 8: {np.median(ms[8]):7.1f} ms/spp   unbounded: {np.median(ms[-1]):7.1f} ms/spp"
            f"   unbounded/8 (median of rounds): {ratio:.2f}")
    return out


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
    over the mean, the two halves' means (a heavy tail shows as halves that differ by more than their SE), Hill's
    tail index from the top 2.5, 5 and 10%, Peng's mean (k = n / 20, `peng_mean`) and a one-sided 97.5% lower bound
    of the mean valid whatever the tail (the mean of the values truncated at their 90th percentile minus 1.96 of its
    SE: an upper bound needs a model of the tail; a lower one does not)."""
    v = np.asarray(values, np.float64)
    h = len(v) // 2
    out = {"largest_share": float(v.max() / v.sum()), "median_over_mean": float(np.median(v) / v.mean()),
           "half_means": [float(v[:h].mean()), float(v[h:].mean())],
           "half_ses": [float(v[:h].std(ddof=1) / np.sqrt(h)), float(v[h:].std(ddof=1) / np.sqrt(len(v) - h))],
           "hill_alpha": hill_alpha(v, (), (0.025, 0.05, 0.1))}
    k = len(v) // 20
    if k >= 10:
        m, se, a = peng_mean(v, k)
        out["peng"] = {"k": k, "mean": m, "se": se, "alpha": a}
    # a lower confidence bound that needs no tail model: E[min(X, c)] <= E[X], and min(X, c) is bounded
    t = np.minimum(v, np.quantile(v, 0.9))
    out["lower_bound_975_trunc_q90"] = float(t.mean() - 1.96 * t.std(ddof=1) / np.sqrt(len(t)))
    return out


def compare_images(a_imgs, b_imgs, label: str, log=print, blocks: int = 4) -> dict:
    """Means of two independent sets of images (a: jaxfog, b: the other): the image mean and the `blocks x blocks`
    region means with SEs from the spread over images (independent), z per region, the relative difference of the
    image means with its SE (delta method), a bootstrap interval of the ratio, and each side's tail summary."""
    a_m = np.asarray([im.mean() for im in a_imgs], np.float64)
    b_m = np.asarray([im.mean() for im in b_imgs], np.float64)
    ma, sa = mean_and_se(a_m)
    mb, sb = mean_and_se(b_m)
    ba, bsa = mean_and_se([block_means(im, blocks) for im in a_imgs])
    bb, bsb = mean_and_se([block_means(im, blocks) for im in b_imgs])
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
    pb = row["tail_b"].get("peng")
    if pb is not None:  # a (plain mean, CLT SE) against b's heavy-tail-aware mean
        r = ma / pb["mean"]
        row["peng_b"] = {"ratio": r, "ratio_se": r * np.hypot(sa / ma, pb["se"] / pb["mean"]),
                         "z": (ma - pb["mean"]) / np.hypot(sa, pb["se"])}
    log(f"{label:40s} {ma:.5g} +- {sa:.2g} ({len(a_m)} images) vs {mb:.5g} +- {sb:.2g} ({len(b_m)}): "
        f"rel. diff {100 * rel:+.1f}% +- {100 * rel_se:.1f}%, z {zm:+.2f}, ratio 95% bootstrap [{lo:.3f}, {hi:.3f}]; "
        f"{blocks}x{blocks} regions max |z| {row['block_z_max']:.2f}, mean z^2 {row['block_mean_z2']:.2f}")
    log("    region z: " + "; ".join(" ".join(f"{x:+.1f}" for x in r) for r in z))
    for side, t in (("a", row["tail_a"]), ("b", row["tail_b"])):
        p_ = t.get("peng")
        hill = " ".join(f"k{k}:{x:.2f}" for k, x in t["hill_alpha"].items())
        log(f"    {side}: Hill alpha of the image means {hill}"
            + ("" if p_ is None else f"; Peng's mean (k {p_['k']}) {p_['mean']:.5g} +- {p_['se']:.2g}")
            + f"; 97.5% lower bound (truncated at q90) {t['lower_bound_975_trunc_q90']:.5g}")
    if pb is not None:
        log(f"    a / Peng's mean of b: {row['peng_b']['ratio']:.3f} +- {row['peng_b']['ratio_se']:.3f}, "
            f"z {row['peng_b']['z']:+.2f}")
    return row


def _cached_images(path, render_one, n: int, log=print, label: str = "") -> tuple[list, list]:
    """Images `0..n-1` from `render_one(k)` and each one's render time (s; NaN for images from an older cache without
    times), kept in an `.npz` at `path` (None: no cache) so a run can be resumed or extended; the first `n`."""
    have, secs = [], []
    if path is not None and os.path.exists(path):
        z = np.load(path)
        have = list(z["images"])
        secs = list(z["seconds"]) if "seconds" in z.files else [float("nan")] * len(have)
    total = Stopwatch()
    for k in range(len(have), n):
        with Stopwatch() as sw:
            have.append(np.asarray(render_one(k), np.float32))
        secs.append(sw.s)
        if path is not None and ((k + 1) % 8 == 0 or k + 1 == n):
            save_npz(path, images=np.stack(have), seconds=np.asarray(secs))
            log(f"  {label}: {k + 1}/{n} images, {total.s:.0f} s")
    return have[:n], secs[:n]


AREA_LIGHT = {"type": "area", "center": [0, 2.8, 0], "edge_u": [0.5, 0, 0], "edge_v": [0, 0, 0.5], "radiance": 240}
"""The rectangular light of `area_fog_dense`: 0.5 x 0.5 m facing down at the spot light's place (2.8 m above the floor),
radiance 240 W/(m^2 sr), so its radiant intensity toward the floor (L x area = 60 W/sr) is the spot's."""


def area_fog_dense() -> dict:
    """spot_fog_dense (the same camera, floor, sphere and fog: sigma_t 3, albedo 0.9, g 0.6) lit by `AREA_LIGHT`
    instead of the spot light, as a scene dict: neither renderer's estimator has the 1/r^2 weight of next-event
    estimation toward a point light (an area light is sampled by area and MIS-weighted with the phase function, which
    bounds the weight near it), so both have a finite variance and the image-spread SEs mean what they say."""
    data = json.loads(scene_path("spot_fog_dense").read_text())
    data["name"] = "area_fog_dense"
    data["description"] = "spot_fog_dense lit by a 0.5 x 0.5 m area light at the spot's place (benchmarks.bench_depth)"
    data["lights"] = [dict(AREA_LIGHT)]
    return data


BOX_BOUNDS = {"min": [-3.0, -0.5, -3.0], "max": [3.0, 2.4, 3.0]}
"""The fog's box in `box_fog_dense`: the floor (y = 0, 6 x 6) and the sphere inside, the spot light (y = 2.8) 0.4 m
above its top and the camera (z = 4.5) 1.5 m in front of it, both in vacuum."""


def box_fog_dense() -> dict:
    """spot_fog_dense (the same camera, floor, sphere, spot light and fog: sigma_t 3, albedo 0.9, g 0.6) with the fog
    confined to `BOX_BOUNDS`, as a scene dict. No path vertex comes within 0.4 m of the spot light, so next-event
    estimation's 1/r^2 weight is bounded and both renderers have a finite variance: the image-spread SEs mean what they
    say, with the spot light and the long paths of the dense fog (a random walk of 3 mean free paths per metre)."""
    data = json.loads(scene_path("spot_fog_dense").read_text())
    data["name"] = "box_fog_dense"
    data["description"] = "spot_fog_dense with the fog in a box below the spot light (benchmarks.bench_depth)"
    data["medium"]["bounds"] = {k: list(v) for k, v in BOX_BOUNDS.items()}
    return data


def dense_vs_mitsuba(size: int, n_images: int, spp: int, mi_images: int, mi_spp: int, fixed_depth: int = 32,
                     fixed_images: int = 32, fixed_spp: int = 256, sides=("jaxfog", "mitsuba"), cache=None,
                     log=print, scene="spot_fog_dense", tag: str = "dense", variant: str = "scalar_rgb",
                     key_offset: int = 0) -> dict | None:
    """spot_fog_dense (sigma_t 3) at `size x size`: jaxfog and Mitsuba (`variant`, default `scalar_rgb`) independent
    images (`key_offset` added to every jaxfog key and Mitsuba seed below, for a run independent of an earlier one),

    1. unbiased on both sides: `max_depth = -1`, Russian roulette from `rr_depth` 5 (jaxfog keys fold_in(key(899),
       k), `spp` each; Mitsuba seeds 1000 + k, `mi_spp` each);
    2. both at the fixed depth `fixed_depth` without Russian roulette (the same transport but the paths' tails cut:
       far less noise; jaxfog keys fold_in(key(900 + depth), k), Mitsuba seeds 5000 + k, `fixed_spp` each);
    3. jaxfog's fixed depth against its unbiased render (how much light beyond `fixed_depth` segments).
    `sides` renders only those sides (into `cache`, a folder of `.npz` files, so that two processes can share the
    work); the comparison runs when both sides have all their images. `scene`: a shipped scene's name or a scene dict
    (`area_fog_dense()`), its cache files named `{tag}_{size}_...`."""
    from jaxfog.tools import import_mitsuba

    try:
        mi = import_mitsuba(variant)
    except ImportError as e:
        log(f"Mitsuba {variant} unavailable ({e}): dense-fog cross-check skipped")
        return None
    import jax

    import jaxfog as jf

    path = (lambda t: None) if cache is None else (lambda t: os.path.join(cache, f"{tag}_{size}_{t}.npz"))
    jx, mx = {}, {}
    o = key_offset
    runs = {-1: (n_images, spp, 899 + o, mi_images, mi_spp, 1000 + o),
            fixed_depth: (fixed_images, fixed_spp, 900 + fixed_depth + o, fixed_images, fixed_spp, 5000 + o)}
    times = {}
    for depth, (nj, sj, kj, nm, sm, seed_m) in runs.items():
        over = [f"integrator.max_depth={depth}"]
        if "jaxfog" in sides:
            sc = load(scene, size, over).scene
            jx[depth], secs = _cached_images(path(f"jaxfog_d{depth}_spp{sj}"), lambda k: jf.render(
                sc, jax.random.fold_in(jax.random.key(kj), k), sj), nj, log, f"jaxfog depth {depth}")
            times[f"jaxfog_{depth}"] = None if np.all(np.isnan(secs)) else secs
        if "mitsuba" in sides:
            msc = mi.load_dict(jf.to_mitsuba(load(scene, size, over)))
            mx[depth], secs = _cached_images(path(f"mitsuba_d{depth}_spp{sm}"), lambda k: np.asarray(
                mi.render(msc, spp=sm, seed=seed_m + k))[..., :3], nm, log, f"Mitsuba depth {depth}")
            times[f"mitsuba_{depth}"] = None if np.all(np.isnan(secs)) else secs
    res = {"size": size, "jaxfog_images": n_images, "jaxfog_spp": spp, "mitsuba_images": mi_images,
           "mitsuba_spp": mi_spp, "fixed_depth": fixed_depth, "fixed_images": fixed_images, "fixed_spp": fixed_spp,
           "seconds_per_image": times, "mitsuba_version": mi.__version__, "mitsuba_variant": variant,
           "key_offset": key_offset}
    if jx and mx:
        res["unbounded_vs_mitsuba"] = compare_images(jx[-1], mx[-1], "jaxfog -1 vs Mitsuba -1 (rr 5)", log)
        res["fixed_vs_mitsuba"] = compare_images(jx[fixed_depth], mx[fixed_depth],
                                                 f"jaxfog {fixed_depth} vs Mitsuba {fixed_depth} (no RR)", log)
    if jx:
        res["fixed_vs_unbounded"] = compare_images(jx[fixed_depth], jx[-1],
                                                   f"jaxfog depth {fixed_depth} vs jaxfog -1", log)
    return res


def hill_alpha(values, ks=(10, 30, 100, 300, 1000), fractions=()) -> dict:
    """Hill's estimator of the tail index alpha (P(X > x) ~ x^-alpha) from the `k` largest of `values`, for each of
    `ks` and each of `fractions` of the values (k >= 10 and below a third of the positive values), keyed by k:
    `1 / alpha_k = mean_i<k log(X_(i) / X_(k))`. A mean has a finite variance only for alpha > 2; for 1 < alpha < 2
    it converges, but neither the CLT nor SEs from the sample spread apply. `values` i.i.d.; the SE of alpha_k is
    ~ alpha_k / sqrt(k), and a large k reaches into the body, where the positive path values of the dense fog span
    many decades (transmittance e^(-3 r)): only the smallest k describe the tail."""
    v = np.sort(np.asarray(values, np.float64).ravel())[::-1]
    v = v[v > 0]
    out = {}
    for k in sorted({*ks, *(int(f * len(v)) for f in fractions)}):
        if 10 <= k < len(v) / 3:
            out[str(k)] = float(1.0 / np.mean(np.log(v[:k] / v[k])))
    return out


def survival_slope(values, top: float = 0.3, bottom_count: int = 10) -> float:
    """-slope of log P(X > x | X > 0) against log x, least squares over the positive `values` whose survival lies
    between `top` and `bottom_count` values (another tail-index estimate: the log-log survival plot's straight
    part)."""
    v = np.sort(np.asarray(values, np.float64).ravel())[::-1]
    v = v[v > 0]
    n = len(v)
    surv = (np.arange(n) + 1) / n
    m = (surv <= top) & (np.arange(n) + 1 >= bottom_count)
    if m.sum() < 5:
        return float("nan")
    return float(-np.polyfit(np.log(v[m]), np.log(surv[m]), 1)[0])


def peng_mean(values, k: int) -> tuple[float, float, float]:
    """Mean of i.i.d. non-negative `values` with a heavy right tail (tail index 1 < alpha < 2: the mean exists, the
    variance does not), by Peng's estimator (L. Peng 2001, "Estimating the mean of a heavy tailed distribution",
    Statist. Probab. Lett. 52): the sum of all but the `k` largest values, plus the tail beyond the (k+1)-th largest
    `u` as a Pareto tail fitted by Hill's estimator, `(k / n) u alpha / (alpha - 1)`; asymptotically normal where the
    plain mean is not. Returns `(mean, se, alpha)`; the SE by the delta method: the trimmed part's spread, Hill's
    `alpha / sqrt(k)` and the threshold's `1 / (alpha sqrt(k))` (relative). Valid when the top `k` follow a Pareto
    law (`k` small against n, large against 1); `peng_coverage` checks the interval on synthetic tails."""
    v = np.sort(np.asarray(values, np.float64).ravel())[::-1]
    n = len(v)
    u = v[k]
    a = 1.0 / np.mean(np.log(v[:k] / u))
    body = np.concatenate([v[k:], np.zeros(k)])
    part_a = body.sum() / n
    part_b = (k / n) * u * a / (a - 1)
    se_a = np.sqrt(body.var() / n)
    se_b = np.hypot((k / n) * u * a / ((a - 1) ** 2 * np.sqrt(k)), part_b / (a * np.sqrt(k)))
    return float(part_a + part_b), float(np.hypot(se_a, se_b)), float(a)


def peng_coverage(n: int = 100_000, ks=(300, 1000), alphas=(1.3, 1.5, 2.5), trials: int = 100, seed: int = 0) -> dict:
    """How often `peng_mean`'s 95% interval (+- 1.96 SE) covers the true mean, and the plain mean's (+- 1.96 SD /
    sqrt(n)) does, on synthetic samples shaped like a renderer's paths: 60% zeros, 30% exponential (mean 0.3), 10%
    Pareto(alpha) from 1."""
    rng = np.random.default_rng(seed)
    out = {}
    for a_true in alphas:
        mu = 0.3 * 0.3 + 0.1 * a_true / (a_true - 1)
        for k in ks:
            hit_p = hit_n = 0
            for _ in range(trials):
                m = rng.random(n)
                v = np.where(m < 0.6, 0.0, np.where(m < 0.9, rng.exponential(0.3, n),
                                                    (1 - rng.random(n)) ** (-1 / a_true)))
                est, se, _ = peng_mean(v, k)
                hit_p += abs(est - mu) <= 1.96 * se
                hit_n += abs(v.mean() - mu) <= 1.96 * v.std(ddof=1) / np.sqrt(n)
            out[f"alpha{a_true}_k{k}"] = {"peng": hit_p / trials, "plain": hit_n / trials}
    return out


def per_path_values(scene, side: str, n_images: int, depth: int, size: int = 256, seed0: int = 11000, cache=None,
                    log=print) -> np.ndarray:
    """Single paths' radiance (channel mean) of `scene` at `max_depth = depth`: `n_images` images of `size x size`
    at 1 spp (box filter: a pixel is one path; the pixels of the image together sample the camera's rays as the
    16 x 16 x 256-spp images do), jaxfog (keys fold_in(key(seed0), k)) or Mitsuba (seeds seed0 + k)."""
    import jax

    import jaxfog as jf

    over = [f"integrator.max_depth={depth}"]
    sf = load(scene, size, over)
    tag = sf.data.get("name", "scene")
    p = None if cache is None else os.path.join(cache, f"paths_{tag}_{side}_d{depth}_{size}.npz")
    if side == "jaxfog":
        one = lambda k: jf.render(sf.scene, jax.random.fold_in(jax.random.key(seed0), k), 1)  # noqa: E731
    else:
        from jaxfog.tools import import_mitsuba

        mi = import_mitsuba("scalar_rgb")  # the LLVM variants abort where Dr.Jit's libLLVM cannot select `fminimum`
        msc = mi.load_dict(jf.to_mitsuba(sf))
        one = lambda k: np.asarray(mi.render(msc, spp=1, seed=seed0 + k))[..., :3]  # noqa: E731
    imgs, _ = _cached_images(p, one, n_images, log, f"paths {tag} {side} depth {depth}")
    return np.asarray(imgs, np.float64).mean(-1).ravel()


def tail_report(values, label: str, log=print, peng_ks=()) -> dict:
    """Tail index of `values` (Hill at several k, log-log survival slope), the largest value's share of the sum,
    relative SD, the plain mean with its (CLT) SE, and `peng_mean` at each of `peng_ks`."""
    v = np.asarray(values, np.float64).ravel()
    h = hill_alpha(v)
    row = {"n": len(v), "n_positive": int((v > 0).sum()), "hill_alpha": h, "survival_slope": survival_slope(v),
           "largest_share": float(v.max() / v.sum()), "rel_sd": float(v.std(ddof=1) / v.mean()),
           "top10_share": float(np.sort(v)[-10:].sum() / v.sum()), "top_over_mean": float(v.max() / v.mean()),
           "mean": float(v.mean()), "se": float(v.std(ddof=1) / np.sqrt(len(v))), "peng": {}}
    for k in peng_ks:
        if 10 <= k < row["n_positive"]:
            m, se, a = peng_mean(v, k)
            row["peng"][str(k)] = {"mean": m, "se": se, "alpha": a}
            log(f"    Peng k {k}: mean {m:.5g} +- {se:.2g} (alpha {a:.2f}); "
                f"plain mean {v.mean():.5g} +- {row['se']:.2g}")
    log(f"{label:44s} n {len(v):8d}  Hill alpha " + " ".join(f"k{k}:{a:.2f}" for k, a in h.items())
        + f"  survival slope {row['survival_slope']:.2f}  largest share {row['largest_share']:.3g}"
        + f"  positive {row['n_positive']}  top 10 share {row['top10_share']:.3g}")
    return row


def tails(cache: str, n_path_images: int, n_spot_unbiased: int, log=print, sides=("jaxfog", "mitsuba")) -> dict:
    """Tail index of the single paths (1-spp images at 256 x 256, `per_path_values`) of spot_fog_dense and
    area_fog_dense, unbiased and at depth 32, on each side; and of the per-image means of the `dense` and `area`
    parts' cached images (16 x 16 x 256 spp: 65,536 paths each). `n_path_images` images a case, `n_spot_unbiased`
    for spot_fog_dense unbiased (where only ~1e-4 of the paths carry light)."""
    import glob
    out = {"paths": {}, "image_means": {}}
    for sc in ("spot_fog_dense", area_fog_dense()):
        name = sc if isinstance(sc, str) else sc["name"]
        for side in sides:
            for depth in (-1, 32):
                n_img = n_spot_unbiased if (name, depth) == ("spot_fog_dense", -1) else n_path_images
                v = per_path_values(sc, side, n_img, depth, cache=cache, log=log)
                out["paths"][f"{name}_{side}_d{depth}"] = tail_report(
                    v, f"paths {name} {side} depth {depth}", log)
    for f in sorted(glob.glob(os.path.join(cache, "*_16_*_spp256.npz"))):
        v = np.asarray(np.load(f)["images"], np.float64).mean(axis=(1, 2, 3))
        key = os.path.basename(f)[:-4]
        out["image_means"][key] = tail_report(v, f"image means {key}", log)
    out["peng_coverage"] = peng_coverage()
    log(f"Peng's interval, coverage on synthetic tails: {out['peng_coverage']}")
    return out


def depth_limit(size: int, n_images: int, spp: int, depths=(32, 64, 128), key: int = 932, cache=None,
                plain_images: int = 0, log=print) -> dict:
    """jaxfog alone on spot_fog_dense: fixed depths `depths` and `max_depth = -1`, all with the same keys
    (fold_in(key(key), k), `spp` each). A fixed depth D + d traces the same paths as D and adds their segments
    D+1 .. D+d, so each difference of two depths (paired over the images) is exactly the light beyond the shorter
    cut, with only that light's noise, and must shrink to 0; the unbiased render (the same paths until Russian
    roulette stops them, so correlated with the deep fixed depth) must equal the limit. Every estimator here is
    jaxfog's, whose tail is lighter than Mitsuba's (`tails`). With `plain_images`, also that many unbiased images
    without the light-seeking techniques (keys fold_in(key(key + 1), k)) against the default unbiased ones."""
    import jax

    import jaxfog as jf

    imgs, imgs_full = {}, {}
    for d in (*depths, -1):
        sc = load("spot_fog_dense", size, [f"integrator.max_depth={d}"]).scene
        p = None if cache is None else os.path.join(cache, f"limit_{size}_jaxfog_d{d}_k{key}_spp{spp}.npz")
        imgs[d], secs = _cached_images(p, lambda k: jf.render(sc, jax.random.fold_in(jax.random.key(key), k), spp),
                                       n_images, log, f"jaxfog depth {d} (key {key})")
        imgs_full[d] = imgs[d]
        imgs[d] = np.asarray(imgs[d], np.float64).mean(axis=(1, 2, 3))
        imgs[f"secs_{d}"] = secs
    out = {"size": size, "images": n_images, "spp": spp, "key": key, "depths": list(depths), "means": {},
           "differences": {}, "seconds_per_image": {str(d): float(np.nanmedian(imgs[f"secs_{d}"]))
                                                    for d in (*depths, -1)}}
    for d in (*depths, -1):
        m, se = mean_and_se(imgs[d])
        out["means"][str(d)] = [float(m), float(se)]
        log(f"  jaxfog depth {d:4d}: {m:.5g} +- {se:.2g} ({n_images} images, "
            f"{out['seconds_per_image'][str(d)]:.1f} s each)")
    pairs = [(b, a) for a, b in zip(depths[:-1], depths[1:])] + [(-1, depths[-1])]
    ref = imgs[depths[-1]].mean()
    for b, a in pairs:
        diff = imgs[b] - imgs[a]
        m, se = mean_and_se(diff)
        out["differences"][f"{b}-{a}"] = {"mean": float(m), "se": float(se), "rel_to_deepest": float(m / ref),
                                          "rel_se": float(se / ref), "z": float(m / se) if se > 0 else 0.0}
        log(f"  depth {b} - depth {a} (same paths): {m:.4g} +- {se:.2g} = {100 * m / ref:+.2f}% +- "
            f"{100 * se / ref:.2f}% of depth {depths[-1]}, z {m / se:+.2f}")
    if plain_images:
        out.update(_plain_parts(size, n_images, spp, depths, key, cache, plain_images, imgs_full[-1], log))
    return out


def _plain_parts(size: int, n_images: int, spp: int, depths, key: int, cache, plain_images: int, default_imgs,
                 log=print) -> dict:
    """`depth_limit`'s comparison of the unbiased render without jaxfog's light-seeking techniques (keys
    fold_in(key(key + 1), k)) with the default one (`default_imgs`): `plain_vs_default`, and its light beyond the
    first of `depths` (`plain_deep`)."""
    import jax

    import jaxfog as jf

    out = {}
    # the unbiased render without jaxfog's light-seeking techniques (no equiangular sampling, no light-angle
    # lobe, no equiangular vertices): next-event estimation from the free-flight vertices only, as in Mitsuba's
    # volpath (but with the exact transmittance): the same expectation, a different (heavy-tailed) estimator
    opts = jf.SamplingOptions(equiangular=False, light_lobe=0.0, distance_mix=0.0)
    sc = load("spot_fog_dense", size, ["integrator.max_depth=-1"]).scene
    p = None if cache is None else os.path.join(cache, f"plain_{size}_jaxfog_d-1_k{key + 1}_spp{spp}.npz")
    im, secs = _cached_images(p, lambda k: jf.render(sc, jax.random.fold_in(jax.random.key(key + 1), k), spp,
                                                     sampling=opts), plain_images, log, "jaxfog -1 plain")
    out["plain_vs_default"] = compare_images(im, default_imgs, "jaxfog -1 plain vs jaxfog -1 (default)", log)
    out["plain_vs_default"]["seconds_per_image"] = float(np.nanmedian(secs))
    # and its light beyond depth 32: plain depths 32 and 64 with the same keys (paired), against the default's
    pl = {}
    for d in depths[:2]:
        sc = load("spot_fog_dense", size, [f"integrator.max_depth={d}"]).scene
        p = None if cache is None else os.path.join(cache, f"plain_{size}_jaxfog_d{d}_k{key + 1}_spp{spp}.npz")
        im, _ = _cached_images(p, lambda k: jf.render(sc, jax.random.fold_in(jax.random.key(key + 1), k), spp,
                                                      sampling=opts), n_images, log, f"jaxfog {d} plain")
        pl[d] = np.asarray(im, np.float64).mean(axis=(1, 2, 3))
    a, b = depths[:2]
    m, se = mean_and_se(pl[b] - pl[a])
    out["plain_deep"] = {"depths": [a, b], "means": {str(d): list(map(float, mean_and_se(pl[d]))) for d in pl},
                         "diff": float(m), "diff_se": float(se), "rel": float(m / pl[a].mean()),
                         "rel_se": float(se / pl[a].mean())}
    log(f"  plain: depth {b} - depth {a} (same paths): {100 * m / pl[a].mean():+.1f}% +- "
        f"{100 * se / pl[a].mean():.1f}% of depth {a}")
    return out


def build_parser() -> argparse.ArgumentParser:
    """The command line of `python -m benchmarks.bench_depth`."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--parts", nargs="+", choices=("timing", "dense", "area", "box", "limit", "tails"),
                   default=["timing", "dense"],
                   help="which studies to run (default timing, dense); the JSON keeps the others' earlier results")
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
    p.add_argument("--area-images", type=int, default=512, help="unbiased images a side, area_fog_dense (512)")
    p.add_argument("--area-fixed-images", type=int, default=256,
                   help="images a side at the fixed depth, area_fog_dense (default 256)")
    p.add_argument("--box-images", type=int, default=128, help="jaxfog unbiased images, box_fog_dense (128)")
    p.add_argument("--box-mitsuba-images", type=int, default=256, help="Mitsuba unbiased images, box_fog_dense (256)")
    p.add_argument("--box-fixed-images", type=int, default=64,
                   help="images a side at the fixed depth, box_fog_dense (64)")
    p.add_argument("--limit-images", type=int, default=64, help="jaxfog images per depth of the limit part (64)")
    p.add_argument("--limit-depths", type=int, nargs="+", default=[32, 64, 128],
                   help="fixed depths of the limit part, increasing (default 32 64 128)")
    p.add_argument("--plain-images", type=int, default=64,
                   help="jaxfog unbiased images without equiangular sampling / light lobe in the limit part (64)")
    p.add_argument("--path-images", type=int, default=16,
                   help="1-spp 256 x 256 images per case for the single paths' tail index (default 16)")
    p.add_argument("--spot-path-images", type=int, default=128,
                   help="1-spp 256 x 256 images of spot_fog_dense unbiased for the tail index (default 128)")
    p.add_argument("--sides", nargs="+", choices=("jaxfog", "mitsuba"), default=["jaxfog", "mitsuba"],
                   help="render only these sides of the cross-check (with --cache, two processes can share it)")
    p.add_argument("--mitsuba-variant", default="scalar_rgb",
                   help="Mitsuba variant of the dense / area / box cross-checks (default scalar_rgb; llvm_ad_rgb is "
                        "much faster where Dr.Jit's LLVM backend runs)")
    p.add_argument("--key-offset", type=int, default=0,
                   help="added to the cross-checks' jaxfog keys and Mitsuba seeds: images independent of a run with "
                        "another offset (default 0)")
    p.add_argument("--cache", default=None, help="folder for the cross-check's images (resumable; default none)")
    p.add_argument("--out", default=str(out_dir("bench_depth")),
                   help="output folder of bench_depth.json (default bench_out/bench_depth)")
    return p


def _studies(args, sides: tuple) -> dict:
    """part -> (the study, a function of no argument; what the JSON keeps beside its result)."""
    cross = dict(cache=args.cache, variant=args.mitsuba_variant, key_offset=args.key_offset)
    return {
        "timing": (lambda: timing(args.size, args.spp, args.rounds), {}),
        "dense": (lambda: dense_vs_mitsuba(args.dense_size, args.dense_images, args.dense_spp, args.mitsuba_images,
                                           args.mitsuba_spp, args.fixed_depth, args.fixed_images, args.fixed_spp,
                                           sides, **cross), {}),
        "area": (lambda: dense_vs_mitsuba(args.dense_size, args.area_images, args.dense_spp, args.area_images,
                                          args.dense_spp, args.fixed_depth, args.area_fixed_images, args.fixed_spp,
                                          sides, scene=area_fog_dense(), tag="area", **cross), {"light": AREA_LIGHT}),
        "box": (lambda: dense_vs_mitsuba(args.dense_size, args.box_images, args.dense_spp, args.box_mitsuba_images,
                                         args.dense_spp, args.fixed_depth, args.box_fixed_images, args.fixed_spp,
                                         sides, scene=box_fog_dense(), tag="box", **cross), {"bounds": BOX_BOUNDS}),
        "limit": (lambda: depth_limit(args.dense_size, args.limit_images, args.dense_spp, tuple(args.limit_depths),
                                      cache=args.cache, plain_images=args.plain_images), {}),
        "tails": (lambda: tails(args.cache, args.path_images, args.spot_path_images, sides=sides), {}),
    }


def main(argv=None) -> int:
    p = build_parser()
    args = p.parse_args(argv)
    import jaxfog as jf

    jf.use_cpu_cores()
    if args.cache:
        os.makedirs(args.cache, exist_ok=True)
    elif "tails" in args.parts:
        p.error("--parts tails needs --cache (it reads the dense and area parts' images)")
    out_json = os.path.join(args.out, "bench_depth.json")
    result = read_json(out_json, {})
    result["machine"] = machine_info()
    cmd = command("python -m benchmarks.bench_depth", argv)
    sides = tuple(args.sides)
    studies = _studies(args, sides)
    result.setdefault("runs", {})
    for part in studies:
        if part not in args.parts:
            continue
        study, extra = studies[part]
        res = study()
        if part in ("dense", "area", "box", "tails") and set(sides) != {"jaxfog", "mitsuba"}:
            print("rendered", args.sides, "only: nothing written")  # the other side renders in another process
            return 0
        result[part] = res if res is None else {**res, **extra}
        result["runs"][part] = {"date": datetime.date.today().isoformat(), "command": cmd, "machine": machine_info()}
    write_json(out_json, result)
    print(f"wrote {out_json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
