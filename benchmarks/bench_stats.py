"""The statistics of `benchmarks.bench` (and `benchmarks.bench_cycles`), pure NumPy: per-pixel RMSE against a
reference and its correction for the reference's own noise, the expected RMSE of independent images, the variance of
one sample, the time at which an RMSE-against-time curve reaches a target, a reference's summary from independent
chunks, and `pick_depth` from the depth study's table. `tests/test_bench.py` checks them on synthetic data."""

from __future__ import annotations

import math

import numpy as np

from benchmarks.common import mean_and_se


def rmse(image, reference) -> float:
    """Per-pixel RMSE over all pixels and channels."""
    d = np.asarray(image, np.float64) - np.asarray(reference, np.float64)
    return float(np.sqrt(np.mean(d * d)))


def reference_rmse(half_a, half_b) -> float:
    """RMSE against the truth of the average of two independent equal halves: `RMSE(A - B) / 2`."""
    return rmse(half_a, half_b) / 2.0


def corrected_rmse(raw: float, ref_rmse: float) -> float:
    """RMSE against the truth of an image whose RMSE against an independent unbiased reference is `raw`."""
    return float(math.sqrt(max(raw * raw - ref_rmse * ref_rmse, 0.0)))


def worst_pixel_share(image, reference) -> float:
    """Share of the squared error (`image - reference`, channels summed) carried by the single worst pixel: near 1
    means the RMSE is one firefly."""
    e = np.sum((np.asarray(image, np.float64) - np.asarray(reference, np.float64)) ** 2, axis=-1)
    total = float(e.sum())
    return float(e.max() / total) if total > 0 else 0.0


ONE_PIXEL = 0.5
"""A strategy whose final squared error is more than this share in one pixel is flagged as dominated by a firefly."""


def variance_per_spp(chunks, chunk_spp: int) -> float:
    """Variance of one sample, averaged over pixels and channels, from independent images of `chunk_spp` spp each:
    `chunk_spp * mean(var over images, ddof=1)`. An unbiased n-spp image's expected MSE against the truth is this
    over n."""
    c = np.asarray(chunks, np.float64)
    if c.shape[0] < 2:
        raise ValueError("need at least two independent images")
    return float(chunk_spp * np.mean(np.var(c, axis=0, ddof=1)))


def expected_rmse(images, reference, ref_rmse: float) -> tuple[float, float, list]:
    """Expected RMSE against the truth of independent images like `images`: `sqrt(mean MSE - ref_rmse^2)` with the
    MSE against an independent unbiased `reference`; its standard error (delta method on the mean MSE, nan for one
    image) and the images' corrected RMSEs."""
    mses = [rmse(x, reference) ** 2 for x in images]
    m, se = mean_and_se(mses)
    e = corrected_rmse(math.sqrt(m), ref_rmse)
    return e, (se / (2 * e) if e > 0 else float("nan")), [corrected_rmse(math.sqrt(x), ref_rmse) for x in mses]


def reference_stats(chunks) -> dict:
    """A reference from independent equal chunks `(k, H, W, 3)`: their average `image`, the `chunks` and their
    number `chunks_n`, the mean pixel value with its standard error over the chunks, and the average's own RMSE
    (`reference_rmse` of the two halves), also relative to the mean."""
    k = chunks.shape[0]
    mean, se = mean_and_se(chunks.reshape(k, -1).mean(1))
    r = reference_rmse(chunks[: k // 2].mean(0), chunks[k // 2:].mean(0))
    return {"image": chunks.mean(0), "chunks": chunks, "chunks_n": k, "mean": mean, "mean_se": se, "rmse": r,
            "rel_rmse": r / mean}


def time_to_rmse(times, rmses, target: float) -> tuple[float, str]:
    """Time at which a measured RMSE-vs-time curve first reaches `target`: `(seconds, how)`.

    Between measured points: log-log interpolation (`how = "interpolated"`). Before the first or after the last point:
    extrapolation with RMSE ~ time^(-1/2), the rate of an estimator with finite variance (`how = "extrapolated"`)."""
    t = np.asarray(times, np.float64)
    r = np.asarray(rmses, np.float64)
    if not (target > 0 and np.all(t > 0)) or t.size == 0:
        raise ValueError("need positive times and a positive target")
    below = np.nonzero(r <= target)[0]
    if below.size == 0:
        return float(t[-1] * (r[-1] / target) ** 2), "extrapolated"
    i = int(below[0])
    if i == 0:
        return float(t[0] * (r[0] / target) ** 2) if r[0] > 0 else float(t[0]), "extrapolated"
    lr0, lr1 = math.log(r[i - 1]), math.log(max(r[i], 1e-300))
    lt0, lt1 = math.log(t[i - 1]), math.log(t[i])
    f = (math.log(target) - lr0) / (lr1 - lr0) if lr1 != lr0 else 1.0
    return float(math.exp(lt0 + f * (lt1 - lt0))), "interpolated"


def curve_to_rmse(levels, target: float, x: str = "time_s") -> tuple[float, str]:
    """`time_to_rmse` of a curve of levels (`measure_strategy`'s `levels`): the `x` (`"time_s"`, or `"spp"`) at which
    their `rmse_corrected` first reaches `target`, and how."""
    return time_to_rmse([v[x] for v in levels], [v["rmse_corrected"] for v in levels], target)


def pick_depth(table, rel_error: float, metric: str = "pixel") -> int | None:
    """The cheapest `max_depth` whose bias against the deep reference is within `rel_error` (relative to the mean
    pixel value of the reference), from one scene's depth table.

    **Arguments:**
    - `table`: that scene's `rows` from `bench.json` (`["depth"]["scenes"][name]["rows"]`), or the scene's dict
      holding them; each row has `depth`, `time_per_spp_s`, `rel_mean_bias`, `rel_mean_bias_se`, `rel_pixel_bias`.
    - `rel_error`: the largest acceptable relative bias, e.g. 0.01 for 1%.
    - `metric`: `"pixel"` (default) bounds the per-pixel RMSE beyond noise and the mean-image difference plus two
      standard errors; `"mean"` only the mean-image difference plus two standard errors.

    Returns the depth, or None when no measured depth short of the reference is good enough (then the reference depth
    itself, or deeper, is needed; the reference's own truncation is not measured)."""
    rows = table["rows"] if isinstance(table, dict) else table
    if metric not in ("pixel", "mean"):
        raise ValueError(f"metric must be 'pixel' or 'mean', got {metric!r}")
    if not rel_error > 0:
        raise ValueError(f"rel_error must be > 0, got {rel_error!r}")
    ok = []
    for row in rows:
        if row.get("is_reference"):
            continue
        bound = abs(row["rel_mean_bias"]) + 2.0 * row["rel_mean_bias_se"]
        if metric == "pixel":
            bound = max(bound, row["rel_pixel_bias"])
        if bound <= rel_error:
            ok.append((row["time_per_spp_s"], row["depth"]))
    return min(ok)[1] if ok else None
