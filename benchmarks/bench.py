"""Speed against error: `python -m benchmarks.bench [--quick] [--out DIR] [--scenes ...]` (from the repository root).

Three studies, each printed as a table, written to `DIR/bench.json` and plotted as PNG:

1. **Strategies** (`rmse_vs_time.png`). For each benchmark scene and each sampling strategy (`STRATEGIES`: plain free
   flight with light sampling, + equiangular, + light-angle lobe, + equiangular/free-flight vertex mixture = the
   default), the per-pixel RMSE against a high-spp reference versus wall time after compilation. Each strategy first
   renders one discarded warm-up image (its compile time, measured from JAX's own compile events, is reported apart),
   then independent chunks whose running average reaches the spp `levels`; the time of a level is the sum of its
   chunks' wall times (each until the pixels are on the host). The reference is rendered once per scene with the
   default strategy in `ref_chunks` independent chunks and cached in `DIR/cache/` (keyed by the scene, the settings
   and the renderer's source); its own RMSE is `RMSE(half_A - half_B) / 2`, and `rmse_corrected =
   sqrt(rmse^2 - rmse_ref^2)` removes it (the two images are independent and unbiased). Also: throughput in paths per
   second, XLA's compiled memory for one batch, the time each strategy needs to reach a common RMSE (the largest
   final RMSE of the scene's strategies) as a ratio to the default's, and the variance reduction of equiangular
   sampling (MSE ratio at equal spp and at equal time).
2. **Depth against bias** (`depth_bias.png`). For thin, default and dense fog, the bias of `max_depth` 2, 3, 4, 8, 16
   (and 32) against a deep reference (64), with common random numbers: every depth is `jaxfog.render` of the same
   scene with the same keys, and `render` traces the same paths at every depth. Sample `k` of a pixel draws its
   numbers from the table `uniforms(k_path, ..., n_iterations * n_dims)` of `fold_in(key, k)`, bounce `i`
   dimension `j` from column `i * n_dims + j`; `n_dims` (`jaxfog.tools.n_dims`) depends only on the lights,
   the same at every depth, and each column is hashed on its own (`jaxfog.tools.uniforms`: a function of the key,
   the row and the column, not of the column count), so columns below `n_iterations * n_dims` are the same whatever
   `max_depth` is, as are the pixel jitter and the batching (an image does not depend on the batch size). So a
   depth-`d` path is exactly the start of the deep one (its first `n_iterations` bounces), and the difference of two
   images has only the noise of the longer paths (`tests/test_bench.py` checks the layout and the columns). Each
   depth renders `depth_spp / depth_layers_per_call` independent images of `depth_layers_per_call` spp (keys
   `fold_in(key, c)`, the same for every depth). Reported: the relative mean-image difference (with its standard
   error over those images), the per-pixel RMSE beyond noise (`sqrt(mean(Delta_A * Delta_B))` over two independent
   halves of the images), and the time per spp. `pick_depth` picks the cheapest depth for a requested relative
   error from that table.
3. **Mitsuba 3 side by side** (optional extra `compare`; `benchmarks.bench_mitsuba`, the scene from
   `jaxfog.to_mitsuba`): the same scene rendered in Mitsuba's
   `volpath` (LLVM backend) in a subprocess in the same run; the means (image and 4 x 4 regions) are compared within
   their standard errors, and the time-to-equal-error ratio is printed: jaxfog's time (default strategy) to reach
   Mitsuba's 64-spp RMSE against the shared reference, over Mitsuba's time for 64 spp, measured rather than
   interpolated (`measure_equal_error`): Mitsuba renders 16 independent 64-spp images, jaxfog `equal_error_draws` (32)
   independent images at 1, 2, 3, ... spp, each timed as a single render right after Mitsuba, until jaxfog's statistic
   of its per-image RMSEs is at or below Mitsuba's. Both renderers' errors are heavy-tailed (one rare image can carry
   most of the mean MSE), so the HEADLINE compares the median images; the ratio for the mean MSE (expected error) is
   printed beside it. Also printed: the fractional spp the reference's variance predicts for the mean MSE, and the
   ratios from the strategy study's one RMSE curve. Without Mitsuba the run
   says it was skipped.

Peak memory: `memory_analysis()` of the compiled batch (XLA's argument + output + temporary buffers of one call of
`paths_per_call` paths), and the process's peak resident set size (`VmHWM`, `jaxfog.tools.max_rss_mib`) after each
study; Mitsuba's peak RSS is its subprocess's own.

Timings are wall-clock on whatever else the machine is running (the load average is recorded); ratios inside one
run are the comparable numbers.

Where the code is: this module configures and measures (the stages of `run_benchmark`: `_strategy_part`,
`depth_study`, `_mitsuba_part`); the statistics are `benchmarks.bench_stats` (pure NumPy), the printed tables and
the plots `benchmarks.bench_report`; timing, JSON and the machine record come from `benchmarks.common`.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from benchmarks.bench_mitsuba import run_mitsuba
from benchmarks.bench_report import format_tables, plot_depth, plot_strategies
from benchmarks.bench_stats import (
    ONE_PIXEL,
    corrected_rmse,
    curve_to_rmse,
    expected_rmse,
    pick_depth,
    reference_stats,
    rmse,
    variance_per_spp,
    worst_pixel_share,
)
from benchmarks.common import (
    OUT,
    Stopwatch,
    block_means,
    digest,
    load,
    machine_info,
    mean_and_se,
    memory_dict,
    run_summary,
    save_npz,
    scene_path,
    stderr_log,
    time_calls,
    with_args,
    write_json,
)
from jaxfog.tools import CompileTimer, max_rss_mib

STRATEGIES: dict[str, dict] = {
    "free_flight": dict(equiangular=False, light_lobe=0.0, distance_mix=0.0),
    "equiangular": dict(equiangular=True, light_lobe=0.0, distance_mix=0.0),
    "eq+lobe": dict(equiangular=True, light_lobe=0.3, distance_mix=0.0),
    "default": dict(equiangular=True, light_lobe=0.3, distance_mix=0.15),
}
"""Sampling strategies, each adding one technique to the previous: plain free flight with light sampling (NEE) at
every vertex; + equiangular sampling toward the delta lights on every segment (clipped to the spot cone, MIS with free
flight); + the light-angle direction lobe (30%); + the equiangular/free-flight mixture for path vertices (15%), which
is `render`'s default (`tests/test_bench.py` checks that it is)."""

DEFAULT_STRATEGY = "default"


@dataclass
class Config:
    """What one run measures. `FULL` is the committed run (12 to 20 minutes on 2 busy cores), `QUICK` a smoke run."""

    scenes: tuple = ("spot_fog", "backlit", "spot_fog_thin")
    size: int = 128  # image width = height for the strategy study
    levels: tuple = (1, 2, 4, 8, 16, 32, 64)  # cumulative spp at which RMSE is recorded (multiples of the first)
    ref_spp: int = 256
    ref_chunks: int = 8
    strategies: tuple = tuple(STRATEGIES)
    depth_scenes: tuple = ("spot_fog_thin", "spot_fog", "spot_fog_dense")
    depths: tuple = (2, 3, 4, 8, 16, 32, 64)  # measured where below the scene's reference depth
    depth_refs: tuple = (32, 64, 128)  # deep reference max_depth of each depth scene (dense fog needs long paths)
    depth_size: int = 64
    depth_spp: int = 16  # two halves of depth_spp / 2
    depth_layers_per_call: int = 1  # spp of each independent image (the depth statistics are over these images)
    mitsuba_scene: str = "spot_fog"
    mitsuba_spp: int = 64  # per Mitsuba render (the equal-error target is its 64-spp RMSE)
    mitsuba_chunks: int = 16
    mitsuba_variant: str = "llvm_ad_rgb"  # scalar_rgb where Dr.Jit's LLVM backend aborts (slower: say so)
    equal_error_draws: int = 32  # independent jaxfog images at the spp that matches Mitsuba's error
    seed: int = 0
    parts: tuple = ("strategies", "depth", "mitsuba")


FULL = Config()
QUICK = Config(scenes=("spot_fog",), size=16, levels=(4, 8, 16), ref_spp=64, ref_chunks=4, depths=(2, 4),
               depth_refs=(8, 8, 8), depth_size=16, depth_spp=8, depth_layers_per_call=1, mitsuba_spp=16, mitsuba_chunks=8,
               equal_error_draws=4)


# ================================================================================================ measurement
RenderFn = Callable[..., np.ndarray]
"""`render_fn(scene, seed, spp, **strategy) -> (H, W, 3) numpy image`; the result must be on the host."""


def measure_strategy(scene, render_fn: RenderFn, strategy: dict, levels, seed: int, reference, ref_rmse: float,
                     mean_ref: float, clock: Callable[[], float] = time.perf_counter) -> dict:
    """RMSE against `reference` versus wall time (after a discarded warm-up render that compiles) at the cumulative
    spp `levels`; chunk `i` uses seed `seed * 1000 + i`. See the module docstring."""
    levels = [int(x) for x in levels]
    n_pix = int(np.prod(np.shape(reference)[:2]))
    with CompileTimer() as ct, Stopwatch(clock) as warmup:
        render_fn(scene, seed * 1000 + 999, levels[0], **strategy)
    total = None
    elapsed, done, out = 0.0, 0, []
    for i, lv in enumerate(levels):
        chunk = lv - done
        with Stopwatch(clock) as sw:
            img = np.asarray(render_fn(scene, seed * 1000 + i, chunk, **strategy), np.float64)
        elapsed += sw.s
        total = img * chunk if total is None else total + img * chunk
        done = lv
        mean_img = total / done
        raw = rmse(mean_img, reference)
        corr = corrected_rmse(raw, ref_rmse)
        out.append({"spp": lv, "time_s": elapsed, "rmse": raw, "rmse_corrected": corr,
                    "rel_rmse_corrected": corr / mean_ref, "mean": float(mean_img.mean()),
                    "worst_pixel_share": worst_pixel_share(mean_img, reference), "max_pixel": float(mean_img.max()),
                    "paths_per_s": n_pix * lv / elapsed if elapsed > 0 else float("nan")})
    return {
        "options": dict(strategy),
        "compile_s": ct.seconds,
        "warmup_s": warmup.s,
        "warmup_spp": levels[0],
        "time_per_spp_s": elapsed / levels[-1],
        "paths_per_s": n_pix * levels[-1] / elapsed if elapsed > 0 else float("nan"),
        "levels": out,
        "final_mean": out[-1]["mean"],
    }


def summarize_scene(result: dict) -> None:
    """Adds the common target RMSE (the largest final RMSE of the strategies not dominated by one pixel, see
    `ONE_PIXEL`), each strategy's time to reach it and its ratio to the default strategy."""
    strategies = result["strategies"]
    finals = [s["levels"][-1] for s in strategies.values()]
    clean = [x["rmse_corrected"] for x in finals if x.get("worst_pixel_share", 0.0) <= ONE_PIXEL]
    target = max(clean or [x["rmse_corrected"] for x in finals])
    result["target_rmse"] = target
    result["target_rel_rmse"] = target / result["reference"]["mean"]
    for s in strategies.values():
        s["time_to_target_s"], s["time_to_target_how"] = curve_to_rmse(s["levels"], target)
    if DEFAULT_STRATEGY in strategies:
        t_def = strategies[DEFAULT_STRATEGY]["time_to_target_s"]
        for s in strategies.values():
            s["time_ratio_to_default"] = s["time_to_target_s"] / t_def


def variance_reduction(result: dict, base: str = "free_flight", better: str = "equiangular") -> dict | None:
    """MSE ratio `base / better` at equal spp and at equal time (MSE x time, the inverse efficiency), per level."""
    st = result["strategies"]
    if base not in st or better not in st:
        return None
    rows = []
    for a, b in zip(st[base]["levels"], st[better]["levels"]):
        if a["spp"] != b["spp"] or b["rmse_corrected"] <= 0:
            continue
        equal_spp = (a["rmse_corrected"] / b["rmse_corrected"]) ** 2
        rows.append({"spp": a["spp"], "mse_ratio_equal_spp": equal_spp,
                     "mse_ratio_equal_time": equal_spp * a["time_s"] / b["time_s"]})
    if not rows:
        return None
    geo = lambda k: float(np.exp(np.mean([np.log(r[k]) for r in rows])))  # noqa: E731
    return {"base": base, "better": better, "levels": rows, "at_max_spp": rows[-1],
            "geomean_equal_spp": geo("mse_ratio_equal_spp"), "geomean_equal_time": geo("mse_ratio_equal_time")}


# ===================================================================================================== jaxfog side
def jaxfog_render_fn(paths_per_call: int) -> RenderFn:
    """`render_fn` for `measure_strategy`: `jaxfog.render` with a fixed batch size (so every chunk reuses one
    compiled program), waiting for the pixels."""
    import jax

    import jaxfog as jf

    def fn(scene, seed, spp, **strategy):
        return np.asarray(jf.render(scene, jax.random.key(seed), spp, sampling=jf.SamplingOptions(**strategy),
                                    batch_paths=paths_per_call))

    return fn


def spp_timer(render_fn: RenderFn, scene, seed: int, spp: int) -> Callable[[], float]:
    """`timer()`: wall seconds per spp of one `render_fn` call of `spp` spp with the default strategy (key
    `9_000_000 + seed`; the caller compiles that program first), to time jaxfog right before and after another
    renderer's run, under the same load."""
    return lambda: time_calls(lambda _: render_fn(scene, 9_000_000 + seed, spp, **STRATEGIES[DEFAULT_STRATEGY]), 1,
                              warmup=0)["median_s"] / spp


def timed_draws(scene, seed: int, strategy: dict) -> Callable[[int, int], tuple[list, list]]:
    """`draws(spp, n)`: `n` independent jaxfog images of `spp` spp as `jaxfog.render(scene, key, spp)` makes them
    (its default batching), each timed as one call after a compiling call (a program per spp below a full batch),
    and their wall times (s). Keys `8_000_000 + 100_000 seed + 1000 spp + i`."""
    from jaxfog.tools import DEFAULT_BATCH_PATHS

    render_default = jaxfog_render_fn(DEFAULT_BATCH_PATHS)

    def draws(spp: int, n: int):
        t = time_calls(lambda i: render_default(scene, 8_000_000 + 100_000 * seed + 1000 * spp + i, spp, **strategy),
                       n, keep=True)
        return t["values"], t["wall_s"]

    return draws


def xla_memory(scene, strategy: dict, paths_per_call: int) -> dict | None:
    """XLA's `memory_analysis()` of the compiled batch that `render` runs (hits the in-memory compile cache); it
    lowers `jaxfog.tools.render_items`, the render loop's own batch, so it reports `{"error": ...}` where that
    function's arguments have changed shape."""
    try:
        import jax
        import jax.numpy as jnp

        from jaxfog import SamplingOptions
        from jaxfog.tools import (DEFAULT_CHUNK_PATHS, items_per_call, layers_per_batch, layers_per_chunk,
                                    render_items as _render_items)

        n_dev = jax.local_device_count()  # as `render` splits a batch
        n = items_per_call(scene, 1 << 30, paths_per_call, DEFAULT_CHUNK_PATHS, n_dev)
        per = layers_per_batch(scene, 1 << 30, paths_per_call)
        ids = jnp.zeros(n, jnp.uint32)
        valid = jnp.ones((n, layers_per_chunk(scene, 1 << 30, paths_per_call, DEFAULT_CHUNK_PATHS)), bool)
        args = (scene, jax.random.key(0), ids, ids, valid, SamplingOptions(**strategy), None,
                DEFAULT_CHUNK_PATHS, n_dev)
        ma = _render_items.lower(*args).compile().compiled.memory_analysis()
        return {**memory_dict(ma), "paths_per_call": per * scene.camera.width * scene.camera.height}
    except Exception as e:  # pragma: no cover - depends on private internals
        return {"error": f"{type(e).__name__}: {e}"}


def _source_hash() -> str:
    """A hash of the library's source files (the renderer's source), part of the reference cache's key."""
    import jaxfog as jf

    h = hashlib.sha256()
    for p in sorted(Path(jf.__file__).resolve().parent.glob("_*.py")):
        h.update(p.name.encode())
        h.update(p.read_bytes())
    return h.hexdigest()[:16]


def reference_image(sf, cfg: Config, cache_dir: Path, render_fn: RenderFn, fresh: bool = False, log=print) -> dict:
    """The scene's high-spp reference (default strategy, `ref_chunks` independent chunks), cached in `cache_dir`."""
    key = digest({"data": sf.data, "spp": cfg.ref_spp, "chunks": cfg.ref_chunks, "seed": cfg.seed,
                  "strategy": STRATEGIES[DEFAULT_STRATEGY], "src": _source_hash()})
    W, H = sf.data["camera"]["width"], sf.data["camera"]["height"]
    path = cache_dir / f"ref_{sf.name}_{W}x{H}_{cfg.ref_spp}spp_{key}.npz"
    compile_s = None
    if path.exists() and not fresh:
        z = np.load(path)
        chunks, times, cached = z["chunks"], z["times"], True
        log(f"  reference: cached {path.name}")
    else:
        per_chunk = cfg.ref_spp // cfg.ref_chunks
        t = time_calls(lambda i: render_fn(sf.scene, 1_000_000 + 1000 * cfg.seed + i, per_chunk,
                                           **STRATEGIES[DEFAULT_STRATEGY]), cfg.ref_chunks, keep=True)
        compile_s = t["compile_s"]
        chunks, times, cached = np.stack(t["values"]).astype(np.float32), np.asarray(t["wall_s"]), False
        log(f"  reference: {cfg.ref_chunks} chunks of {per_chunk} spp in {times.sum():.1f} s")
        save_npz(path, compressed=True, chunks=chunks, times=times)
    return {**reference_stats(chunks), "spp": cfg.ref_spp, "render_s": float(np.sum(times)), "cached": cached,
            "file": path.name, "compile_s": compile_s}


def structure(sf) -> str:
    """What decides the compiled program of a scene file (scenes with equal structure share programs)."""
    d = sf.data
    return json.dumps([d["camera"]["width"], d["camera"]["height"], d["integrator"]["max_depth"],
                       d.get("medium") is not None, [(x["type"], x["bsdf"]["type"]) for x in d["shapes"]],
                       [x["type"] for x in d["lights"]]])


def bench_scene(name: str, cfg: Config, cache_dir: Path, fresh_ref: bool = False, log=print,
                compiled: dict | None = None) -> tuple[dict, dict]:
    """The strategy study on one scene: reference, then every strategy (see `measure_strategy`); the scene's result
    and its reference. `compiled` maps `(structure, strategy)` to `(scene, compile seconds)` of the first
    compilation seen in this run."""
    compiled = {} if compiled is None else compiled
    sf = load(name, cfg.size)
    sig = structure(sf)
    n_pix = cfg.size * cfg.size
    paths_per_call = n_pix * cfg.levels[0]
    render_fn = jaxfog_render_fn(paths_per_call)
    log(f"{sf.name}: {cfg.size}x{cfg.size}")
    ref = reference_image(sf, cfg, cache_dir, render_fn, fresh=fresh_ref, log=log)
    if ref["compile_s"] is not None and (sig, DEFAULT_STRATEGY) not in compiled:
        compiled[(sig, DEFAULT_STRATEGY)] = (f"{sf.name} (reference render)", ref["compile_s"])
    res = {"scene": sf.name, "width": cfg.size, "height": cfg.size, "max_depth": sf.data["integrator"]["max_depth"],
           "reference": {k: v for k, v in ref.items() if k not in ("image", "chunks")}, "strategies": {}}
    for j, sname in enumerate(cfg.strategies):
        opts = STRATEGIES[sname]
        m = measure_strategy(sf.scene, render_fn, opts, cfg.levels, cfg.seed * 100 + j + 1, ref["image"],
                             ref["rmse"], ref["mean"])
        m["xla_memory"] = xla_memory(sf.scene, opts, paths_per_call)
        if (sig, sname) in compiled:
            m["compiled_by"], m["compile_s_first"] = compiled[(sig, sname)]
        else:
            compiled[(sig, sname)] = (sf.name, m["compile_s"])
            m["compiled_by"], m["compile_s_first"] = sf.name, m["compile_s"]
        res["strategies"][sname] = m
        lv = m["levels"][-1]
        log(f"  {sname:12s} compile {m['compile_s_first']:5.1f} s, {1e3 * m['time_per_spp_s']:7.0f} ms/spp, "
            f"{m['paths_per_s'] / 1e3:6.1f} kpaths/s, rel RMSE {lv['rel_rmse_corrected']:.3f} at {lv['spp']} spp")
    summarize_scene(res)
    res["max_rss_mib_after"] = max_rss_mib()
    return res, ref


# ------------------------------------------------------------------------------------------------- depth study
def depth_study(cfg: Config, log=print) -> dict:
    """Bias of each `max_depth` in `cfg.depths` (those below the scene's reference depth, `cfg.depth_refs`) against the
    reference depth, with common random numbers: `jaxfog.render` with the same keys at every depth (see the module
    docstring for why that traces the same paths)."""
    import jax

    import jaxfog as jf

    sampling = jf.SamplingOptions(**STRATEGIES[DEFAULT_STRATEGY])
    L = cfg.depth_layers_per_call
    n_calls = max(2, -(-cfg.depth_spp // L))
    n_calls += n_calls % 2
    spp = n_calls * L
    key = jax.random.key(5_000_000 + cfg.seed)
    keys = [jax.random.fold_in(key, c) for c in range(n_calls)]  # image c: the same key at every depth
    out = {"width": cfg.depth_size, "height": cfg.depth_size, "spp": spp, "images": n_calls, "spp_per_image": L,
           "strategy": DEFAULT_STRATEGY, "scenes": {}}
    for name, ref_depth in zip(cfg.depth_scenes, cfg.depth_refs):
        depths = sorted({d for d in cfg.depths if d < ref_depth} | {ref_depth})
        per_depth = {d: _depth_images(name, d, cfg.depth_size, keys, L, sampling, log) for d in depths}
        ref_layers = per_depth[ref_depth]["layers"]  # (images, n_pix, 3)
        per_path = ref_layers.sum(-1)  # one path per (image, pixel) when depth_layers_per_call is 1
        sf = load(name, cfg.depth_size)
        out["scenes"][name] = {"sigma_t": sf.data["medium"]["sigma_t"] if sf.data.get("medium") else 0.0,
                               "ref_depth": ref_depth, "mean_ref": float(ref_layers.mean()),
                               "rows": [_depth_row(d, per_depth[d], ref_layers, d == ref_depth) for d in depths],
                               "largest_path_share": float(per_path.max() / per_path.sum()) if per_path.sum() > 0
                               else 0.0}
    out["max_rss_mib_after"] = max_rss_mib()
    return out


def _depth_images(name: str, depth: int, size: int, keys: list, spp: int, sampling, log=print) -> dict:
    """`len(keys)` images of `spp` spp of the scene `name` at `max_depth = depth` with `sampling` (key `keys[c]` for
    image `c`), timed after a warm-up render, which compiles where no earlier render had this structure: `layers`
    `(images, pixels, 3)`, `time_per_spp_s` and `compile_s` (None where nothing compiled)."""
    import jaxfog as jf

    scene = load(name, size, [f"integrator.max_depth={depth}"]).scene
    n = len(keys)
    t = time_calls(lambda c: np.asarray(jf.render(scene, keys[c], spp, sampling=sampling), np.float64), n, keep=True)
    compile_s = t["compile_s"] or None
    elapsed = sum(t["wall_s"])
    log(f"  {name} max_depth {depth:3d}: {1e3 * elapsed / (n * spp):7.0f} ms/spp at {size}x{size}"
        + (f" (compile {compile_s:.1f} s)" if compile_s is not None else ""))
    return {"layers": np.stack(t["values"]).reshape(n, size * size, 3), "time_per_spp_s": elapsed / (n * spp),
            "compile_s": compile_s}


def _depth_row(depth: int, images: dict, ref_layers, is_reference: bool) -> dict:
    """One depth's row: its mean, its bias against the reference depth's images `ref_layers` (the same paths, image
    by image): the mean-image difference with its standard error, the per-pixel RMSE beyond noise
    (`sqrt(mean(Delta_A * Delta_B))` of two independent halves of the images) and that estimate's noise; its cost."""
    lay = images["layers"]
    n_calls, n_pix = lay.shape[:2]
    mean_ref = float(ref_layers.mean())
    diff = ref_layers - lay  # per image: the contribution of segments depth+1 .. ref_depth (the same paths)
    m, se = mean_and_se(diff.reshape(n_calls, -1).mean(1))
    h = n_calls // 2
    da, db = diff[:h].mean(0), diff[h:].mean(0)
    b2 = float(np.mean(da * db))
    noise = float(np.sqrt(np.mean((da - db) ** 2)) / 2)
    return {"depth": depth, "is_reference": is_reference, "mean": float(lay.mean()),
            "rel_mean_bias": m / mean_ref, "rel_mean_bias_se": se / mean_ref,
            "rel_pixel_bias": math.sqrt(max(b2, 0.0)) / mean_ref, "rel_pixel_noise": noise / mean_ref,
            "time_per_spp_s": images["time_per_spp_s"], "paths_per_s": n_pix / images["time_per_spp_s"],
            "compile_s": images["compile_s"]}


# ---------------------------------------------------------------------------------------------------- mitsuba
def mitsuba_compare(name: str, cfg: Config, ref: dict, jax_result: dict, workdir: Path, log=print,
                    jax_time_per_spp: Callable[[], float] | None = None,
                    jax_draws: Callable[[int, int], tuple[list, list]] | None = None, **kw) -> dict:
    """Means within standard errors (whole image, 4 x 4 regions, orientation) and the time-to-equal-error ratio.

    `jax_time_per_spp()`, when given, times jaxfog's default strategy right before and right after Mitsuba's renders,
    so that the ratios compare the two under the same machine load. `jax_draws(spp, n)`, when given, renders `n`
    independent jaxfog images (default strategy, `render`'s own batching) of `spp` spp and returns them with their
    wall times: the measured ratios of `measure_equal_error` (the HEADLINE)."""
    t_jax_before = jax_time_per_spp() if jax_time_per_spp is not None else None
    # the run's --seed also draws Mitsuba's images (seeds from 1000 x seed), so repeated runs are independent
    kw.setdefault("variant", cfg.mitsuba_variant)
    mr = run_mitsuba(name, cfg.size, cfg.mitsuba_spp, cfg.mitsuba_chunks, workdir, seed0=1000 * cfg.seed, **kw)
    if "skipped" in mr:
        return {"scene": name, "skipped": mr["skipped"]}
    t_jax_after = jax_time_per_spp() if jax_time_per_spp is not None else None
    imgs = mr["images"].astype(np.float64)  # (chunks, H, W, 3)
    n, spp = imgs.shape[0], int(mr["spp"])
    t_per_spp = float(np.mean(mr["times"])) / spp
    t_mi = 64 * t_per_spp
    res = {
        "scene": name, "version": str(mr["version"]), "variant": str(mr["variant"]), "threads": int(mr["threads"]),
        "spp_per_render": spp, "renders": n, "total_spp": n * spp, "warmup_s": float(mr["warmup_s"]),
        "time_per_spp_s": t_per_spp, "paths_per_s": cfg.size ** 2 / t_per_spp, "max_rss_mib": float(mr["max_rss_mib"]),
        **_agreement(imgs, ref), "levels": _running_levels(imgs, mr["times"], spp, ref),
        **_error64(imgs, spp, ref, t_mi),
    }
    rmse64, rmse64_median = res["rmse64_corrected"], res["rmse64_corrected_median"]
    res["time_to_mitsuba64"] = {sname: _time_to_mitsuba(s["levels"], rmse64, rmse64_median, t_mi)
                                for sname, s in jax_result["strategies"].items()}
    if t_jax_before is not None and DEFAULT_STRATEGY in jax_result["strategies"]:
        lv = jax_result["strategies"][DEFAULT_STRATEGY]["levels"]
        res["adjacent"], res["variance_based"] = _adjacent(lv, ref, res, t_jax_before, t_jax_after)
    if jax_draws is not None and rmse64 > 0:
        res["measured"] = measure_equal_error(jax_draws, cfg, ref, rmse64, rmse64_median, t_mi, log=log)
    return res


def _halves(img) -> dict:
    """The means of an image's left, right, top and bottom halves (channels averaged)."""
    g = np.asarray(img, np.float64).mean(-1)
    H, W = g.shape
    return {"left": g[:, : W // 2].mean(), "right": g[:, W // 2:].mean(), "top": g[: H // 2].mean(),
            "bottom": g[H // 2:].mean()}


def _agreement(imgs, ref: dict) -> dict:
    """Mitsuba's images `(n, H, W, 3)` against jaxfog's reference: the image means with their standard errors and z;
    the 4 x 4 region means (standard errors over the images or chunks) with z per region, also against flipped
    Mitsuba images (which orientation fits best); the means of the images' halves."""
    n = imgs.shape[0]
    mi_mean, mi_se = mean_and_se(imgs.reshape(n, -1).mean(1))
    jf_mean, jf_se = ref["mean"], ref["mean_se"]
    z = (jf_mean - mi_mean) / math.hypot(jf_se, mi_se)
    mb = np.stack([block_means(x) for x in imgs])  # (chunks, 4, 4)
    jb = np.stack([block_means(x) for x in ref["chunks"]])
    mi_b, mi_bse = mb.mean(0), mb.std(0, ddof=1) / math.sqrt(n)
    jf_b, jf_bse = jb.mean(0), jb.std(0, ddof=1) / math.sqrt(jb.shape[0])

    def zs(mi_blocks, mi_se_blocks):
        return (jf_b - mi_blocks) / np.sqrt(jf_bse ** 2 + mi_se_blocks ** 2 + 1e-30)

    orient = {}
    for label, f in (("as is", lambda a: a), ("left-right flipped", lambda a: a[:, ::-1]),
                     ("up-down flipped", lambda a: a[::-1, :])):
        zz = zs(f(mi_b), f(mi_bse))
        orient[label] = {"chi2_per_block": float(np.mean(zz ** 2)), "max_abs_z": float(np.max(np.abs(zz)))}
    z_blocks = zs(mi_b, mi_bse)
    return {"mean": mi_mean, "mean_se": mi_se, "jaxfog_mean": jf_mean, "jaxfog_mean_se": jf_se,
            "jaxfog_mean_source": f"reference, {ref['spp']} spp", "z_mean": z, "means_agree": bool(abs(z) < 3.0),
            "z_blocks": z_blocks.tolist(), "max_abs_z_block": float(np.max(np.abs(z_blocks))),
            "blocks_jaxfog": jf_b.tolist(), "blocks_mitsuba": mi_b.tolist(), "orientation": orient,
            "best_orientation": min(orient, key=lambda x: orient[x]["chi2_per_block"]),
            "halves_jaxfog": _halves(ref["image"]), "halves_mitsuba": _halves(imgs.mean(0))}


def _running_levels(imgs, times, spp: int, ref: dict) -> list[dict]:
    """The RMSE against the shared reference of the running average of Mitsuba's images, at 1, 2, 4, ... images and
    all of them, with the summed render time."""
    n = imgs.shape[0]
    levels, elapsed, acc = [], 0.0, np.zeros_like(imgs[0])
    k = 1
    for i in range(n):
        acc += imgs[i]
        elapsed += float(times[i])
        if i + 1 == k or i + 1 == n:
            raw = rmse(acc / (i + 1), ref["image"])
            corr = corrected_rmse(raw, ref["rmse"])
            levels.append({"spp": spp * (i + 1), "time_s": elapsed, "rmse": raw, "rmse_corrected": corr,
                           "rel_rmse_corrected": corr / ref["mean"]})
            k *= 2
    return levels


def _error64(imgs, spp: int, ref: dict, t_mi: float) -> dict:
    """Mitsuba's error at 64 spp against the shared reference, with the same statistics as jaxfog's side
    (`expected_rmse`, the median of the per-image corrected RMSEs), over independent 64-spp images (groups of its
    renders); `t_mi`, its time for 64 spp, is recorded beside them."""
    n = imgs.shape[0]
    group = max(1, 64 // spp)
    n_groups = n // group
    images64 = [imgs[g * group:(g + 1) * group].mean(0) for g in range(n_groups)]
    rmse64_raw = math.sqrt(float(np.mean([rmse(x, ref["image"]) ** 2 for x in images64])))
    rmse64, rmse64_se, per_image64 = expected_rmse(images64, ref["image"], ref["rmse"])
    return {"rmse64": rmse64_raw, "rmse64_corrected": rmse64, "rel_rmse64_corrected": rmse64 / ref["mean"],
            "rmse64_from_images": n_groups, "time64_s": t_mi, "rmse64_corrected_median": float(np.median(per_image64)),
            "rmse64_corrected_se": rmse64_se,
            "rel_rmse64_per_image": [x / ref["mean"] for x in per_image64],
            "rel_rmse_all_corrected": corrected_rmse(rmse(imgs.mean(0), ref["image"]), ref["rmse"]) / ref["mean"]}


def _time_to_mitsuba(levels, rmse64: float, rmse64_median: float, t_mi: float) -> dict:
    """From one strategy's RMSE curve: its time to Mitsuba's 64-spp error (mean MSE and median image) and the ratio
    to Mitsuba's time for 64 spp."""
    t, how = curve_to_rmse(levels, rmse64)
    t_med, how_med = curve_to_rmse(levels, rmse64_median)
    return {"time_s": t, "how": how, "ratio_jaxfog_over_mitsuba": t / t_mi, "time_s_median_target": t_med,
            "how_median_target": how_med, "ratio_median_target": t_med / t_mi}


def _adjacent(levels, ref: dict, res: dict, t_before: float, t_after: float) -> tuple[dict, dict]:
    """The ratios with jaxfog's time per spp measured right before and after Mitsuba's renders (`t_before`,
    `t_after`): from the default strategy's RMSE curve against spp (`adjacent`), and from the variance of the
    reference's independent chunks, expected MSE = sigma^2 / spp (`variance_based`)."""
    rmse64, rmse64_median, t_mi = res["rmse64_corrected"], res["rmse64_corrected_median"], res["time64_s"]
    spp_mean, how = curve_to_rmse(levels, rmse64, "spp")
    spp_med, how_med = curve_to_rmse(levels, rmse64_median, "spp")
    t_adj = 0.5 * (t_before + t_after)
    adjacent = {
        "strategy": DEFAULT_STRATEGY, "jaxfog_time_per_spp_s_before": t_before,
        "jaxfog_time_per_spp_s_after": t_after, "mitsuba_time_per_spp_s": res["time_per_spp_s"],
        "jaxfog_spp_to_target": spp_mean, "how": how, "ratio": spp_mean * t_adj / t_mi,
        "jaxfog_spp_to_median_target": spp_med, "how_median": how_med, "ratio_median_target": spp_med * t_adj / t_mi,
    }
    sigma2 = variance_per_spp(ref["chunks"], ref["spp"] // ref["chunks_n"])
    n_star = sigma2 / rmse64 ** 2
    return adjacent, {"sigma2_per_spp": sigma2, "from_chunks": ref["chunks_n"], "jaxfog_spp_to_target": n_star,
                      "ratio": n_star * t_adj / t_mi}


EQUAL_ERROR_TARGETS = {
    "median_image": "the median of the per-image RMSEs (the typical image; the HEADLINE)",
    "mean_mse": "the root of the mean per-image MSE (the expected error; dominated by rare firefly-ridden images)",
}


def measure_equal_error(jax_draws, cfg: Config, ref: dict, rmse64: float, rmse64_median: float, t_mi: float,
                        log=print, max_spp: int = 16) -> dict:
    """jaxfog's measured time to Mitsuba's 64-spp error, for each statistic of `EQUAL_ERROR_TARGETS`: jaxfog renders
    `cfg.equal_error_draws` independent images at 1, 2, 3, ... spp (each timed as a single render) until the same
    statistic of its per-image corrected RMSEs is at or below Mitsuba's (at most `max_spp`); the ratio is jaxfog's
    mean time per image over Mitsuba's mean time per 64-spp image."""
    n_draws = cfg.equal_error_draws
    targets = {"median_image": rmse64_median, "mean_mse": rmse64}
    tries, found = [], {}
    for spp in range(1, max_spp + 1):
        imgs, times_j = jax_draws(spp, n_draws)
        e_mean, e_se, per_image = expected_rmse(imgs, ref["image"], ref["rmse"])
        stats = {"median_image": float(np.median(per_image)), "mean_mse": e_mean}
        t_j = float(np.mean(times_j))
        row = {"spp": spp, "draws": n_draws, "time_s": t_j, "time_s_median": float(np.median(times_j)),
               "rel_rmse": {k: v / ref["mean"] for k, v in stats.items()},
               "rel_rmse_mean_mse_se": e_se / ref["mean"], "ratio": t_j / t_mi,
               "rel_rmse_per_image": [x / ref["mean"] for x in per_image]}
        tries.append(row)
        log(f"  jaxfog at {spp} spp ({n_draws} images, {1e3 * t_j:.0f} ms each): rel RMSE median image "
            f"{stats['median_image'] / ref['mean']:.3f}, mean-MSE {e_mean / ref['mean']:.3f}; Mitsuba at 64 spp "
            f"({1e3 * t_mi:.0f} ms): {rmse64_median / ref['mean']:.3f}, {rmse64 / ref['mean']:.3f}")
        for k, target in targets.items():
            if k not in found and stats[k] <= target:
                found[k] = {"spp": spp, "time_s": t_j, "ratio": t_j / t_mi, "jaxfog_rel_rmse": stats[k] / ref["mean"],
                            "mitsuba_rel_rmse": target / ref["mean"], "at_fewest_spp": spp == 1}
        if len(found) == len(targets):
            break
    for k, target in targets.items():
        found.setdefault(k, {"spp": None, "reached": False, "mitsuba_rel_rmse": target / ref["mean"],
                             "note": f"not reached within {max_spp} spp"})
    return {"targets": EQUAL_ERROR_TARGETS, "mitsuba_time64_s": t_mi, **found, "tries": tries}


# ========================================================================================================= CLI
def build_parser() -> argparse.ArgumentParser:
    """The command line of `python -m benchmarks.bench`."""
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="a small, fast smoke run (16x16, few spp)")
    p.add_argument("--out", default=str(OUT), metavar="DIR",
                   help="output folder: bench.json, PNGs, cache/ with the references (default: bench_out in the "
                        "repository root)")
    p.add_argument("--scenes", nargs="+", metavar="SCENE", help="benchmark scenes (names or .json paths)")
    p.add_argument("--parts", nargs="+", choices=("strategies", "depth", "mitsuba"),
                   help="which studies to run (default all; mitsuba needs strategies)")
    p.add_argument("--size", type=int, metavar="N", help="image width = height of the strategy study")
    p.add_argument("--levels", type=int, nargs="+", metavar="SPP",
                   help="cumulative spp levels, multiples of the first (default 1 2 4 8 16 32 64)")
    p.add_argument("--ref-spp", type=int, metavar="N", help="reference spp (default 256)")
    p.add_argument("--strategies", nargs="+", choices=tuple(STRATEGIES), help="strategies (default all)")
    p.add_argument("--depth-scenes", nargs="+", metavar="SCENE")
    p.add_argument("--depths", type=int, nargs="+", metavar="D",
                   help="depths to measure where below the reference depth (default 2 3 4 8 16 32 64)")
    p.add_argument("--depth-ref", type=int, metavar="D",
                   help="deep reference max_depth for every depth scene (default 32 thin, 64 spot_fog, 128 dense)")
    p.add_argument("--depth-size", type=int, metavar="N", help="image size of the depth study (default 64)")
    p.add_argument("--depth-spp", type=int, metavar="N", help="spp of the depth study (default 16)")
    p.add_argument("--mitsuba-chunks", type=int, metavar="N", help="Mitsuba renders of --mitsuba-spp each (default 16)")
    p.add_argument("--mitsuba-spp", type=int, metavar="N", help="spp of one Mitsuba render (default 64)")
    p.add_argument("--mitsuba-variant", metavar="V", help="Mitsuba variant (default llvm_ad_rgb; scalar_rgb where "
                   "the LLVM backend aborts)")
    p.add_argument("--equal-error-draws", type=int, metavar="N",
                   help="independent jaxfog images measured at Mitsuba's 64-spp error (default 32, at most 999)")
    p.add_argument("--max-bias", type=float, nargs="+", metavar="E", default=[0.01, 0.03, 0.1],
                   help="relative errors for which the cheapest depth is picked (default 0.01 0.03 0.1)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--fresh-ref", action="store_true", help="re-render references even if cached")
    p.add_argument("--no-plots", action="store_true")
    return p


def config_from_args(args: argparse.Namespace) -> Config:
    cfg = with_args(QUICK if args.quick else FULL, args)
    if args.depth_ref is not None:
        cfg.depth_refs = (args.depth_ref,) * len(cfg.depth_scenes)
    elif len(cfg.depth_refs) != len(cfg.depth_scenes):
        cfg.depth_refs = (max(cfg.depth_refs),) * len(cfg.depth_scenes)
    lv = list(cfg.levels)
    if lv != sorted(set(lv)) or lv[0] < 1 or any(x % lv[0] for x in lv):
        raise ValueError(f"--levels must be increasing multiples of the first, got {lv}")
    if cfg.ref_spp % cfg.ref_chunks or (cfg.ref_spp // cfg.ref_chunks) % lv[0]:
        raise ValueError(f"--ref-spp must be a multiple of {cfg.ref_chunks * lv[0]}, got {cfg.ref_spp}")
    if not 1 <= cfg.equal_error_draws <= 999:
        raise ValueError(f"--equal-error-draws must be in [1, 999], got {cfg.equal_error_draws}")
    if cfg.mitsuba_spp < 1 or cfg.mitsuba_chunks < 2 or cfg.mitsuba_spp * cfg.mitsuba_chunks < 64:
        raise ValueError("--mitsuba-spp must be >= 1, --mitsuba-chunks >= 2, and together at least 64 spp "
                         "(the equal-error target is Mitsuba's 64-spp error)")
    if min(cfg.depths) < 1 or min(cfg.depth_refs) < 2:
        raise ValueError("--depths must be >= 1 and --depth-ref >= 2")
    for name in set(cfg.scenes) | set(cfg.depth_scenes):
        if not scene_path(name).exists():
            raise ValueError(f"no scene {name!r} ({scene_path(name)})")
    return cfg


def run_benchmark(cfg: Config, out: Path, fresh_ref: bool = False, max_bias=(0.01,), plots: bool = True,
                  log=print) -> dict:
    """The studies of `cfg.parts` in turn; writes `out/bench.json` (and, with `plots`, the PNGs); returns the result.
    `max_bias`: the relative errors for which `pick_depth` picks each depth scene's cheapest depth."""
    out.mkdir(parents=True, exist_ok=True)
    cache = out / "cache"
    result: dict = {"schema": 1, "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "machine": machine_info(),
                    "config": dataclasses.asdict(cfg),
                    "memory_method": "xla_memory: compiled memory_analysis() of one render batch (argument + output + "
                                     "temporary buffers); max_rss: peak resident set size of the process "
                                     "(VmHWM), Mitsuba's in its own subprocess"}
    sw = Stopwatch()
    refs = _strategy_part(result, cfg, cache, fresh_ref, log) if "strategies" in cfg.parts else {}
    if "depth" in cfg.parts:
        log(f"depth study: {cfg.depth_scenes}, depths {cfg.depths} against {cfg.depth_refs}")
        result["depth"] = depth_study(cfg, log=log)
        result["depth"]["picks"] = {
            str(e): {n: pick_depth(s, e) for n, s in result["depth"]["scenes"].items()} for e in max_bias}
    if "mitsuba" in cfg.parts:
        result["mitsuba"] = _mitsuba_part(cfg, refs, result.get("scenes"), cache, log)
    result["memory"] = _memory(result)
    result["total_wall_s"] = sw.s
    write_json(out / "bench.json", result)
    if plots:
        if result.get("scenes"):
            plot_strategies(result, out / "rmse_vs_time.png")
        if result.get("depth"):
            plot_depth(result["depth"], out / "depth_bias.png")
    return result


def _strategy_part(result: dict, cfg: Config, cache: Path, fresh_ref: bool, log) -> dict:
    """The strategy study of every scene into `result` (`scenes`, `variance_reduction`); returns the references."""
    refs, compiled = {}, {}
    result["scenes"] = {}
    for name in cfg.scenes:
        res, ref = bench_scene(name, cfg, cache, fresh_ref=fresh_ref, log=log, compiled=compiled)
        result["scenes"][res["scene"]] = res
        refs[res["scene"]] = ref
    result["variance_reduction"] = {}
    for name, res in result["scenes"].items():
        result["variance_reduction"][name] = {
            "equiangular": variance_reduction(res, "free_flight", "equiangular"),
            "all": variance_reduction(res, "free_flight", "default"),
        }
    return refs


def _mitsuba_part(cfg: Config, refs: dict, scenes: dict | None, cache: Path, log) -> dict:
    """`mitsuba_compare` on `cfg.mitsuba_scene`, with jaxfog timed beside Mitsuba; skipped where the strategy study
    did not run on that scene."""
    name = cfg.mitsuba_scene
    if name not in refs:
        return {"scene": name, "skipped": f"{name} is not among the benchmark scenes of this run"}
    log(f"Mitsuba 3 on {name}: {cfg.mitsuba_chunks} renders of {cfg.mitsuba_spp} spp")
    sf = load(name, cfg.size)
    fn = jaxfog_render_fn(cfg.size * cfg.size * cfg.levels[0])
    timer = spp_timer(fn, sf.scene, cfg.seed, max(8, cfg.levels[0]))
    jax_draws = timed_draws(sf.scene, cfg.seed, STRATEGIES[DEFAULT_STRATEGY])
    return mitsuba_compare(name, cfg, refs[name], scenes[name], cache, log=log, jax_time_per_spp=timer,
                           jax_draws=jax_draws)


def _memory(result: dict) -> dict:
    """The peak memory of the run: this process's, Mitsuba's process's and XLA's largest batch per scene (MiB)."""
    mem = {"jaxfog process max_rss": max_rss_mib()}
    mt = result.get("mitsuba") or {}
    if "max_rss_mib" in mt:
        mem["Mitsuba process max_rss"] = mt["max_rss_mib"]
    for name, sc in (result.get("scenes") or {}).items():
        mem[f"XLA batch {name} (max over strategies)"] = max(
            (s["xla_memory"] or {}).get("total_mib", 0.0) for s in sc["strategies"].values())
    return mem


def main(argv: list[str] | None = None) -> int:
    """Runs the benchmark (`python -m benchmarks.bench ...`); prints the tables; returns the exit code."""
    args = build_parser().parse_args(argv)
    from jaxfog import use_cpu_cores

    use_cpu_cores()  # every core as a JAX device (a no-op once JAX has started, e.g. under pytest)
    try:
        cfg = config_from_args(args)
    except ValueError as e:
        print(f"benchmarks.bench: error: {e}", file=sys.stderr)
        return 2
    out = Path(args.out)
    result = run_benchmark(cfg, out, fresh_ref=args.fresh_ref, max_bias=tuple(args.max_bias),
                           plots=not args.no_plots, log=stderr_log)
    print(format_tables(result))
    print("\n" + run_summary(f"{out / 'bench.json'}" + ("" if args.no_plots else " and PNGs"), result))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
