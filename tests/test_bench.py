"""The benchmark's statistics and plumbing (benchmarks.bench, bench_stats, bench_report, bench_mitsuba, common), with a
fake renderer and a fake clock: no test here times anything real. The end-to-end `--quick` run is marked slow (it
compiles several programs)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from benchmarks import bench, bench_stats
from jaxfog._mitsuba import rectangle_matrix

REPO = Path(__file__).resolve().parent.parent


# ----------------------------------------------------------------------------------------------------- statistics
def test_default_strategy_is_renders_default():
    """The benchmark's "default" row measures what `jaxfog.render` does when called without options."""
    from jaxfog import SamplingOptions

    defaults = vars(SamplingOptions())  # what `render` samples with when called without options
    assert bench.STRATEGIES[bench.DEFAULT_STRATEGY] == {k: defaults[k] for k in bench.STRATEGIES["default"]}


def test_time_to_rmse_interpolates_and_extrapolates_on_an_inverse_sqrt_curve():
    t = np.array([1.0, 2.0, 4.0, 8.0])
    r = 0.8 / np.sqrt(t)
    for target_t in (1.5, 3.0, 7.0):  # between points: log-log interpolation is exact on a power law
        got, how = bench_stats.time_to_rmse(t, r, 0.8 / math.sqrt(target_t))
        assert how == "interpolated" and got == pytest.approx(target_t, rel=1e-9)
    for target_t in (0.25, 32.0):  # outside: extrapolated with slope -1/2, also exact here
        got, how = bench_stats.time_to_rmse(t, r, 0.8 / math.sqrt(target_t))
        assert how == "extrapolated" and got == pytest.approx(target_t, rel=1e-9)


def test_time_to_rmse_takes_the_first_crossing_of_a_noisy_curve():
    got, how = bench_stats.time_to_rmse([1, 2, 4, 8], [1.0, 0.4, 0.6, 0.3], 0.5)
    assert how == "interpolated" and 1 < got < 2


def test_reference_rmse_from_halves_and_the_correction():
    rng = np.random.default_rng(0)
    truth = rng.uniform(0.5, 1.5, (64, 64, 3))
    sigma = 0.3  # per-pixel standard deviation of one half
    a = truth + sigma * rng.standard_normal(truth.shape)
    b = truth + sigma * rng.standard_normal(truth.shape)
    ref = (a + b) / 2
    r_ref = bench_stats.reference_rmse(a, b)
    assert r_ref == pytest.approx(sigma / math.sqrt(2), rel=0.03)  # the average of the halves
    assert bench_stats.rmse(ref, truth) == pytest.approx(r_ref, rel=0.03)
    x = truth + 0.5 * rng.standard_normal(truth.shape)  # an independent image with RMSE 0.5 against the truth
    raw = bench_stats.rmse(x, ref)
    assert raw > 0.52  # against the noisy reference it looks worse ...
    assert bench_stats.corrected_rmse(raw, r_ref) == pytest.approx(0.5, rel=0.03)  # ... the correction removes that


def test_block_means_orientation():
    img = np.zeros((8, 8, 3))
    img[:4, 6:] = 1.0  # top right
    bm = bench.block_means(img, 4)
    assert bm[0, 3] == 1.0 and bm[1, 3] == 1.0 and bm[3, 0] == 0.0 and bm.sum() == 2.0


# ------------------------------------------------------------------------------ strategy study with a fake renderer
class FakeClock:
    def __init__(self):
        self.now = 1.0

    def __call__(self):
        return self.now


def fake_renderer(truth, clock, costs, sigmas):
    """`render_fn` whose image is `truth` plus Gaussian noise `sigma / sqrt(spp)` and which takes `cost * spp`
    fake seconds; the strategy is identified by `light_lobe` (an index into costs/sigmas)."""

    def fn(scene, seed, spp, **strategy):
        i = int(strategy["light_lobe"])
        clock.now += costs[i] * spp
        rng = np.random.default_rng(seed)
        return truth + sigmas[i] / math.sqrt(spp) * rng.standard_normal(truth.shape)

    return fn


def test_measure_strategy_and_ratios_with_a_fake_renderer():
    rng = np.random.default_rng(1)
    truth = rng.uniform(0.5, 1.5, (48, 48, 3))
    clock = FakeClock()
    costs, sigmas = (1.0, 2.0), (2.0, 1.0)  # strategy 1: twice the cost, half the noise -> twice as efficient
    fn = fake_renderer(truth, clock, costs, sigmas)
    ref_sigma = 0.05
    ref = truth + ref_sigma * rng.standard_normal(truth.shape)
    levels = (4, 8, 16, 32)
    res = {"reference": {"mean": float(truth.mean())}, "strategies": {}}
    for name, idx in (("free_flight", 0), ("default", 1)):
        m = bench.measure_strategy(None, fn, {"light_lobe": idx}, levels, seed=idx + 1, reference=ref,
                                   ref_rmse=ref_sigma, mean_ref=float(truth.mean()), clock=clock)
        assert [x["spp"] for x in m["levels"]] == list(levels)
        assert m["time_per_spp_s"] == pytest.approx(costs[idx])  # the warm-up render is not counted
        assert m["warmup_s"] == pytest.approx(costs[idx] * levels[0])
        for x in m["levels"]:
            assert x["time_s"] == pytest.approx(costs[idx] * x["spp"])
            assert x["rmse_corrected"] == pytest.approx(sigmas[idx] / math.sqrt(x["spp"]), rel=0.05)
        res["strategies"][name] = m
    bench.summarize_scene(res)
    # time to a common RMSE scales like sigma^2 * cost: 4 vs 2
    assert res["strategies"]["free_flight"]["time_ratio_to_default"] == pytest.approx(2.0, rel=0.1)
    vr = bench.variance_reduction(res, "free_flight", "default")
    assert vr["geomean_equal_spp"] == pytest.approx(4.0, rel=0.1)
    assert vr["geomean_equal_time"] == pytest.approx(2.0, rel=0.1)
    text = bench.format_tables({"scenes": {"fake": {**res, "width": 48, "height": 48, "max_depth": 8, "scene": "fake",
                                                    "reference": {**res["reference"], "spp": 1, "mean_se": 0.0,
                                                                  "rmse": ref_sigma, "rel_rmse": 0.05}}}})
    assert "free_flight" in text and "default" in text


# ------------------------------------------------------------------------------- equal error against Mitsuba (fake)
def test_variance_per_spp_and_expected_rmse():
    rng = np.random.default_rng(2)
    truth = rng.uniform(0.5, 1.5, (64, 64, 3))
    sigma = 0.8  # per-sample standard deviation of every pixel
    chunks = [truth + sigma / math.sqrt(4) * rng.standard_normal(truth.shape) for _ in range(8)]  # 4 spp each
    # sample variance over 8 images of 12288 pixel-channels: relative sd sqrt(2/7)/sqrt(12288) ~ 0.5%
    assert bench_stats.variance_per_spp(chunks, 4) == pytest.approx(sigma**2, rel=0.03)
    ref_sigma = 0.05
    ref = truth + ref_sigma * rng.standard_normal(truth.shape)
    imgs = [truth + 0.3 * rng.standard_normal(truth.shape) for _ in range(10)]
    e, se, per = bench_stats.expected_rmse(imgs, ref, ref_sigma)
    assert e == pytest.approx(0.3, rel=0.01) and 0 < se < 0.01 and len(per) == 10
    with pytest.raises(ValueError):
        bench_stats.variance_per_spp(chunks[:1], 4)


def test_mitsuba_compare_measures_jaxfog_at_mitsubas_error(monkeypatch, tmp_path):
    """With a fake Mitsuba (64-spp images of per-sample sd 4, 3 s each) and a fake jaxfog (per-sample sd 4 / sqrt(8),
    so 8 spp reach Mitsuba's 64-spp error; 0.01 s per spp), jaxfog is rendered at 1, 2, ... spp until the median image and the
    mean MSE reach Mitsuba's, and the ratio is that of single-render times."""
    rng = np.random.default_rng(3)
    truth = rng.uniform(0.5, 1.5, (32, 32, 3))
    s_mi, s_jf, t_spp_jf = 4.0, 4.0 / math.sqrt(8), 0.01
    mi_imgs = np.stack([truth + s_mi / 8 * rng.standard_normal(truth.shape) for _ in range(16)]).astype(np.float32)
    monkeypatch.setattr(bench, "run_mitsuba", lambda *a, **k: {
        "images": mi_imgs, "times": np.full(16, 3.0), "spp": np.int64(64), "version": "fake", "variant": "fake",
        "threads": np.int64(2), "warmup_s": np.float64(1.0), "max_rss_mib": np.float64(1.0)})
    ref_sigma = 0.02
    chunks = np.stack([truth + s_jf / 8 * rng.standard_normal(truth.shape) for _ in range(8)])  # 64 spp each
    ref = {"image": truth + ref_sigma * rng.standard_normal(truth.shape), "chunks": chunks, "spp": 512, "chunks_n": 8,
           "mean": float(truth.mean()), "mean_se": 0.001, "rmse": ref_sigma}
    calls = []

    def draws(spp, n):
        calls.append(spp)
        return [truth + s_jf / math.sqrt(spp) * rng.standard_normal(truth.shape) for _ in range(n)], [t_spp_jf * spp] * n

    levels = [{"spp": n, "time_s": t_spp_jf * n, "rmse_corrected": s_jf / math.sqrt(n)} for n in (1, 4, 16, 64)]
    cfg = bench.Config(mitsuba_spp=64, mitsuba_chunks=16, equal_error_draws=32)
    res = bench.mitsuba_compare("fake", cfg, ref, {"strategies": {"default": {"levels": levels}}}, tmp_path,
                                log=lambda s: None, jax_time_per_spp=lambda: t_spp_jf, jax_draws=draws)
    assert res["rmse64_corrected"] == pytest.approx(s_mi / 8, rel=0.05)
    assert res["variance_based"]["jaxfog_spp_to_target"] == pytest.approx(8, rel=0.15)
    m = res["measured"]
    assert calls == list(range(1, len(calls) + 1))  # 1, 2, 3, ... spp until both targets are reached
    for k in ("median_image", "mean_mse"):
        r = m[k]
        assert r["spp"] in (7, 8, 9, 10), (k, r)
        assert r["ratio"] == pytest.approx(t_spp_jf * r["spp"] / 3.0)
        assert r["jaxfog_rel_rmse"] <= r["mitsuba_rel_rmse"]
        # one spp fewer did not reach it
        assert m["tries"][r["spp"] - 2]["rel_rmse"][k] > r["mitsuba_rel_rmse"]
    text = bench.format_tables({"mitsuba": {**res, "best_orientation": "as is"}})
    assert "HEADLINE, measured" in text and f"at {m['median_image']['spp']} spp" in text


def test_depth_study_gets_common_random_numbers_from_render():
    """The depth study renders each depth with `jaxfog.render` and the same keys: the bounce layout does not depend
    on `max_depth`, and the uniform table's columns do not depend on how many there are, so a shorter path draws the
    first columns of a longer one's numbers."""
    import jax

    from jaxfog._integrator import layout, n_iterations
    from jaxfog._random import uniforms

    scenes = {d: bench.load("spot_fog", 4, [f"integrator.max_depth={d}"]).scene for d in (2, 3, 8)}
    assert len({layout(s) for s in scenes.values()}) == 1
    K = layout(scenes[2]).n_dims
    key = jax.random.key(7)
    deep = np.asarray(uniforms(key, 16, n_iterations(scenes[8]) * K, 5))
    for d in (2, 3):
        cols = n_iterations(scenes[d]) * K
        np.testing.assert_array_equal(np.asarray(uniforms(key, 16, cols, 5)), deep[:, :cols])


# ----------------------------------------------------------------------------------------------------- pick_depth
def _row(depth, mean_bias, se, pixel, t, ref=False):
    return {"depth": depth, "rel_mean_bias": mean_bias, "rel_mean_bias_se": se, "rel_pixel_bias": pixel,
            "time_per_spp_s": t, "is_reference": ref}


TABLE = {"rows": [_row(2, 0.40, 0.01, 0.45, 1.0), _row(4, 0.05, 0.004, 0.06, 2.0), _row(8, 0.004, 0.002, 0.012, 4.0),
                  _row(16, 0.0001, 0.001, 0.003, 8.0), _row(64, 0.0, 0.0, 0.0, 30.0, ref=True)]}


def test_pick_depth_is_the_cheapest_depth_within_the_error():
    assert bench_stats.pick_depth(TABLE, 0.5) == 2
    assert bench_stats.pick_depth(TABLE, 0.07) == 4
    assert bench_stats.pick_depth(TABLE, 0.02) == 8
    assert bench_stats.pick_depth(TABLE, 0.02, metric="mean") == 8  # 0.004 + 2 * 0.002 <= 0.02
    assert bench_stats.pick_depth(TABLE, 0.009, metric="mean") == 8
    assert bench_stats.pick_depth(TABLE, 0.009) == 16  # the per-pixel bias of depth 8 (1.2%) is too large
    assert bench_stats.pick_depth(TABLE, 0.001) is None  # never the reference itself
    with pytest.raises(ValueError):
        bench_stats.pick_depth(TABLE, 0.0)


# ------------------------------------------------------------------------------------------------------- Mitsuba
def test_rectangle_matrix_maps_jaxfog_corners_and_front_normal():
    c, u, v = np.array([0.0, 0.0, 0.0]), np.array([6.0, 0, 0]), np.array([0, 0, -6.0])  # the floor: normal +y
    m = rectangle_matrix(c, u, v)
    for su, sv in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
        p = m @ np.array([su, sv, 0.0, 1.0])
        np.testing.assert_allclose(p[:3], c + su * u / 2 + sv * v / 2)
    n = np.linalg.inv(m[:3, :3]).T @ np.array([0, 0, 1.0])  # normals transform by the inverse transpose
    np.testing.assert_allclose(n / np.linalg.norm(n), [0, 1, 0], atol=1e-12)


def test_missing_mitsuba_is_reported_as_skipped(tmp_path):
    fake = tmp_path / "fakepkgs" / "mitsuba"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text("raise ImportError('no mitsuba here')\n")
    env = dict(os.environ, PYTHONPATH=str(tmp_path / "fakepkgs"))
    res = bench.run_mitsuba("spot_fog", 8, 4, 1, tmp_path / "work", env=env, timeout=120)
    assert "skipped" in res and "no mitsuba here" in res["skipped"]
    text = bench.format_tables({"mitsuba": {"scene": "spot_fog", "skipped": res["skipped"]}})
    assert "Mitsuba 3: skipped" in text


def test_report_of_the_depth_study_variance_reduction_and_memory():
    """`format_tables` (benchmarks.bench_report) of the parts the other tests leave out: the depth table with its
    picks and the unresolved-path warning, the variance reduction and the peak memory."""
    rows = [{**r, "mean": 0.5, "rel_pixel_noise": 0.001} for r in TABLE["rows"]]
    vr = {"base": "free_flight", "better": "equiangular", "geomean_equal_spp": 3.5, "geomean_equal_time": 1.75,
          "at_max_spp": {"spp": 32, "mse_ratio_equal_spp": 4.0, "mse_ratio_equal_time": 2.0}}
    text = bench.format_tables({
        "variance_reduction": {"fake": {"equiangular": vr, "all": None}},
        "depth": {"width": 16, "height": 16, "spp": 8, "scenes": {"fake": {"rows": rows, "largest_path_share": 0.2}},
                  "picks": {"0.01": {"fake": None}, "0.5": {"fake": 2}}},
        "memory": {"jaxfog process max_rss": 1234.4, "note": "not a number"}})
    lines = text.splitlines()
    assert f"  {'fake':14s} free_flight / equiangular: at 32 spp 4.00 (equal spp), 2.00 (equal time); geometric " \
           "mean over spp levels 3.50 / 1.75" in lines
    assert any(x.startswith("== depth against bias (16x16, 8 spp") for x in lines)
    assert "fake: one path of the 8 x 16x16 carries 20% of the reference's mean: its rows are not resolved" in lines
    assert "    1.0%: fake -> none measured (deeper than 16)" in lines and "   50.0%: fake -> 2" in lines
    table = [x for x in lines if x.startswith("fake ")]
    assert len(table) == 5 and table[-1].endswith("(reference)") and table[2].endswith(" 1.00")  # depth 8: x 1
    assert lines[-1] == "peak memory: jaxfog process max_rss 1234 MiB"


# ---------------------------------------------------------------------------------------------------------- CLI
def test_bench_arguments_validate_levels():
    build_parser = bench.build_parser  # `python -m benchmarks.bench` (not a `jaxfog` subcommand)
    args = build_parser().parse_args(["--quick", "--levels", "4", "6"])
    with pytest.raises(ValueError, match="multiples"):
        bench.config_from_args(args)
    args = build_parser().parse_args(["--quick", "--scenes", "no_such_scene"])
    with pytest.raises(ValueError, match="no scene"):
        bench.config_from_args(args)
    cfg = bench.config_from_args(build_parser().parse_args(["--quick", "--depth-ref", "6"]))
    assert cfg.depth_refs == (6, 6, 6) and cfg.size == 16


@pytest.mark.slow
def test_quick_run_end_to_end(tmp_path):
    """`python -m benchmarks.bench --quick` (minutes: it compiles one program per strategy and depth)."""
    out = tmp_path / "b"
    p = subprocess.run([sys.executable, "-m", "benchmarks.bench", "--quick", "--out", str(out), "--depths", "2",
                        "--depth-ref", "3", "--depth-scenes", "spot_fog"], capture_output=True, text=True, cwd=REPO)
    assert p.returncode == 0, p.stderr[-2000:]
    res = json.loads((out / "bench.json").read_text())
    sc = res["scenes"]["spot_fog"]
    assert set(sc["strategies"]) == set(bench.STRATEGIES)
    assert all(s["levels"][-1]["rmse"] > 0 for s in sc["strategies"].values())
    rows = res["depth"]["scenes"]["spot_fog"]["rows"]
    assert [r["depth"] for r in rows] == [2, 3]
    assert rows[0]["rel_mean_bias"] > 0  # depth 3 adds light to the same paths
    assert (out / "rmse_vs_time.png").exists() and (out / "depth_bias.png").exists()
    assert "Mitsuba" in p.stdout


# ------------------------------------------------------------------------------- bench_depth's dense-fog statistics
def test_dense_comparison_statistics_and_resumable_cache(tmp_path):
    """`benchmarks.bench_depth.compare_images` on constant images whose values are heavy-tailed (log-normal, sigma 1)
    with known means (b = 2 x a's distribution), 120 repetitions, fixed seed: the ratio's delta-method SE matches the
    spread of the ratio within 20%; the bootstrap interval holds the true ratio 0.5 in 88-99% of them (nominal 95%,
    binomial SE 2%; a percentile bootstrap undercovers a little on skewed data); the block z values are the image z
    (every block of a constant image is the image). `_cached_images` renders only the images a cache lacks and keeps
    their times."""
    from benchmarks.bench_depth import _cached_images, compare_images

    rng = np.random.default_rng(5)
    ratios, ses, covered = [], [], 0
    for _ in range(120):
        a = [np.full((8, 8, 3), x) for x in rng.lognormal(0.0, 1.0, 60)]
        b = [np.full((8, 8, 3), 2.0 * x) for x in rng.lognormal(0.0, 1.0, 90)]
        row = compare_images(a, b, "", log=lambda s: None)
        ratios.append(row["ratio"])
        ses.append(row["rel_diff_se"])
        lo, hi = row["ratio_bootstrap_95"]
        covered += lo <= 0.5 <= hi
        np.testing.assert_allclose(row["block_z"], np.full((4, 4), row["z_mean"]), rtol=1e-9)
        assert 0 < row["tail_a"]["largest_share"] < 1 and row["tail_b"]["median_over_mean"] < 1
    assert abs(np.mean(ratios) - 0.5) < 0.02
    assert 0.8 < np.mean(ses) / np.std(ratios) < 1.2
    assert 0.88 <= covered / 120 <= 0.99

    calls = []

    def render_one(k):
        calls.append(k)
        return np.full((2, 2, 3), float(k))

    path = str(tmp_path / "c.npz")
    imgs, secs = _cached_images(path, render_one, 3, log=lambda s: None)
    imgs2, secs2 = _cached_images(path, render_one, 5, log=lambda s: None)
    assert calls == [0, 1, 2, 3, 4] and len(imgs2) == 5 and [float(x[0, 0, 0]) for x in imgs2] == [0, 1, 2, 3, 4]
    assert np.all(np.isfinite(secs2)) and secs2[:3] == secs


def test_tail_index_and_heavy_tail_mean_on_pareto_samples():
    """`hill_alpha` and `peng_mean` (benchmarks.bench_depth) on Pareto samples with known alpha and mean (fixed
    seeds, 200,000 values with 40% zeros in front): Hill's alpha from the top k = 1000 within 4 of its SE (alpha /
    sqrt(k)) of the true alpha, Peng's mean within 4 of its SE of the true mean, for alpha 1.5 (infinite variance)
    and 3 (finite; then Peng's mean also agrees with the plain mean within 4 of the plain mean's SE); the truncation
    lower bound of `tail_summary` is below the true mean."""
    from benchmarks.bench_depth import hill_alpha, peng_mean, tail_summary

    for seed, alpha in ((1, 1.5), (2, 3.0)):
        rng = np.random.default_rng(seed)
        n = 200_000
        v = np.where(rng.random(n) < 0.4, 0.0, (1.0 - rng.random(n)) ** (-1.0 / alpha))
        mu = 0.6 * alpha / (alpha - 1.0)
        a = hill_alpha(v, ks=(1000,))["1000"]
        assert abs(a - alpha) < 4 * alpha / np.sqrt(1000), (alpha, a)
        m, se, a_p = peng_mean(v, 1000)
        assert a_p == pytest.approx(a) and abs(m - mu) < 4 * se, (alpha, m, se, mu)
        if alpha > 2:
            assert abs(m - v.mean()) < 4 * v.std() / np.sqrt(n)
        assert tail_summary(v[:2000])["lower_bound_975_trunc_q90"] < mu


# ------------------------------------------------------------------------------------------------------ bench_cost
def test_cost_table_pairs_each_jaxfog_block_with_the_mitsuba_block_beside_it():
    from benchmarks import bench_cost

    per = {"jaxfog default": [10.0, 12.0, 30.0, 31.0], "jaxfog, Mitsuba's techniques": [8.0, 8.0, 20.0, 22.0],
           "jaxfog per call": [2.0, 3.0, 4.0, 5.0]}
    blocks = {"jaxfog default": [11.0, 30.5], "jaxfog, Mitsuba's techniques": [8.0, 21.0], "jaxfog per call": [2.5, 4.5]}
    mitsuba_blocks = [{"median_ms_per_spp": 10.0, "warmup_s": 1.0, "threads": 2, "variant": "llvm_ad_rgb"},
                      {"median_ms_per_spp": 20.0, "warmup_s": 3.0, "threads": 2, "variant": "llvm_ad_rgb"}]
    first = {k: 1.0 for k in per}
    rows = {r["row"]: r for r in bench_cost.table_rows(per, blocks, [9.0, 11.0, 19.0, 21.0], mitsuba_blocks, first)}
    d = rows["jaxfog default"]
    assert d["median"] == 21.0 and d["min"] == 10.0 and d["max"] == 31.0
    # block 1: 11 / 10, block 2: 30.5 / 20: the machine slowed down by 2x and the ratios do not see it
    assert d["ratio_to_mitsuba"]["min"] == pytest.approx(1.1) and d["ratio_to_mitsuba"]["max"] == pytest.approx(1.525)
    assert rows["jaxfog, Mitsuba's techniques"]["ratio_to_mitsuba"]["median"] == pytest.approx((0.8 + 1.05) / 2)
    assert rows["Mitsuba volpath (llvm_ad_rgb, 2 threads)"]["median"] == 15.0
    assert rows["Mitsuba volpath (llvm_ad_rgb, 2 threads)"]["first_call_s"] == 2.0
    assert rows["jaxfog per call (8 x 8 px, 1 spp)"]["unit"] == "ms/call"
    alone = bench_cost.table_rows(per, blocks, [], [], first)
    assert all("ratio_to_mitsuba" not in r for r in alone) and len(alone) == 3


def test_cost_pooling_takes_every_block_pair_of_every_run():
    from benchmarks import bench_cost

    def run(meds, techs, mits):
        return {"block_medians": {"jaxfog default": meds, "jaxfog, Mitsuba's techniques": techs,
                                  "jaxfog per call": [1.0] * len(meds)},
                "mitsuba_blocks": [{"median_ms_per_spp": m} for m in mits]}

    pooled = bench_cost.pooled_ratios([run([10.0, 22.0], [8.0, 16.0], [10.0, 20.0]), run([9.0], [9.0], [10.0])])
    d = pooled["jaxfog default"]
    assert d["n"] == 3 and d["median"] == pytest.approx(1.0) and d["min"] == pytest.approx(0.9)
    assert d["max"] == pytest.approx(1.1) and d["geometric_mean"] == pytest.approx((0.9 * 1.0 * 1.1) ** (1 / 3))
    assert pooled["jaxfog, Mitsuba's techniques"]["median"] == pytest.approx(0.8)
    assert "jaxfog per call" not in pooled


@pytest.mark.slow
def test_cost_run_without_mitsuba_end_to_end(tmp_path):
    out = tmp_path / "cost"
    r = subprocess.run([sys.executable, "-m", "benchmarks.bench_cost", "--no-mitsuba", "--blocks", "1", "--reps", "1",
                        "--spp", "1", "--scene", "spot_fog_thin", "--out", str(out)],
                       cwd=REPO, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    data = json.loads((out / "cost.json").read_text())
    assert [row["row"] for row in data["rows"]] == ["jaxfog default", "jaxfog, Mitsuba's techniques",
                                                    "jaxfog per call (8 x 8 px, 1 spp)"]
    assert all(row["median"] > 0 for row in data["rows"])


# ------------------------------------------------------------------------------------------------------ the harness
def test_time_calls_and_interleave_order_indices_and_ratios():
    """`time_calls` warms up with index 0 then passes each timed call its index; `interleave` runs the labels in turn
    (reversed every other round with `alternate`) and its ratios are per round against the first label."""
    from benchmarks.common import interleave, time_calls

    calls = []
    t = time_calls(lambda i: calls.append(i) or 10 * i, 3, warmup=2, keep=True)
    assert calls == [0, 0, 0, 1, 2] and t["values"] == [0, 10, 20] and len(t["wall_s"]) == len(t["cpu_s"]) == 3
    assert t["first_call_s"] >= 0 and t["median_s"] == sorted(t["wall_s"])[1] and t["min_s"] == min(t["wall_s"])
    assert time_calls(lambda i: None, 1, warmup=0)["first_call_s"] is None

    order = []
    r = interleave({"a": lambda i: order.append(("a", i)), "b": lambda i: order.append(("b", i))}, 3, alternate=True)
    assert order == [("a", 0), ("b", 0), ("a", 0), ("b", 0), ("b", 1), ("a", 1), ("a", 2), ("b", 2)]
    assert r["a"]["ratio"] == [1.0, 1.0, 1.0]
    assert r["b"]["ratio"] == pytest.approx([b / a for a, b in zip(r["a"]["wall_s"], r["b"]["wall_s"])])
    assert r["b"]["ratio_median"] == pytest.approx(float(np.median(r["b"]["ratio"])))


def test_write_json_adds_the_machine_and_replaces_the_file_whole(tmp_path):
    from benchmarks.common import write_json

    path = tmp_path / "sub" / "r.json"
    write_json(path, {"x": np.float32(1.5), "a": np.arange(3)})
    d = json.loads(path.read_text())
    assert d["x"] == 1.5 and d["a"] == [0, 1, 2]
    m = d["machine"]
    assert {"cpu", "cpu_count", "jax", "devices", "date_utc", "commit", "loadavg_start", "loadavg_end"} <= set(m)
    write_json(path, {"machine": "kept", "y": 1})
    assert json.loads(path.read_text()) == {"machine": "kept", "y": 1}
    assert [p.name for p in path.parent.iterdir()] == ["r.json"]  # no temporary file left


def test_stopwatch_and_the_json_helpers(tmp_path, capsys):
    """`Stopwatch` reads its clock while it runs and keeps the time at `stop()` or a `with` block's end; `read_json`,
    `print_json`, `run_summary` and `digest` (the cache files' key)."""
    from benchmarks.common import Stopwatch, digest, print_json, read_json, run_summary, write_json

    clock = FakeClock()
    with Stopwatch(clock) as sw:
        clock.now += 2.5
    clock.now += 10.0
    assert sw.s == 2.5 and sw.cpu_s >= 0
    running = Stopwatch(clock)
    clock.now += 1.0
    assert running.s == 1.0
    clock.now += 1.0
    assert running.stop() == 2.0
    clock.now += 5.0
    assert running.s == 2.0
    assert read_json(tmp_path / "none.json", {}) == {}
    with pytest.raises(FileNotFoundError):
        read_json(tmp_path / "none.json")
    write_json(tmp_path / "r.json", {"total_wall_s": 61.6, "v": np.float64(0.5)})
    r = read_json(tmp_path / "r.json")
    assert r["v"] == 0.5 and run_summary("X", r).startswith("wrote X in 62 s (load average ")
    print_json({"a": np.arange(2)}, "case")
    assert capsys.readouterr().out == 'case {"a": [0, 1]}\n'
    assert digest({"b": 1, "a": [2]}) == digest({"a": [2], "b": 1}) != digest({"a": [3], "b": 1})
    assert len(digest({})) == 12


def test_format_table_aligns_numbers_and_marks_missing_values():
    from benchmarks.common import format_table

    rows = [{"name": "a", "t": 1.25, "flag": "2.0!"}, {"name": "longer", "t": None, "flag": "10.5"}]
    text = format_table(rows, [("name", "name"), ("t s", "t", ".1f"), ("flag", "flag")])
    assert text.splitlines() == ["name   t s flag", "a      1.2 2.0!", "longer   - 10.5"]
    md = format_table(rows, [("name", "name"), ("t", lambda r: r["t"], ".2f")], markdown=True)
    assert md.splitlines() == ["| name | t |", "| --- | --- |", "| a | 1.25 |", "| longer | - |"]


def test_benchmarks_import_no_private_module():
    """The benchmarks use the public `jaxfog` and `jaxfog.tools` only (no `jaxfog._x` import of any form)."""
    import ast

    for path in sorted((REPO / "benchmarks").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module:
                mods = [node.module] + ([f"{node.module}.{a.name}" for a in node.names] if node.module == "jaxfog"
                                        else [])
            elif isinstance(node, ast.Import):
                mods = [a.name for a in node.names]
            else:
                continue
            assert not any(m.startswith("jaxfog._") for m in mods), (path.name, node.lineno, mods)
