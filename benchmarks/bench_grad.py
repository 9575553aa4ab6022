"""Gradient benchmark: `python -m benchmarks.bench_grad [--quick] [--out DIR]` (from the repository root).

Three parts, printed as tables and written to `DIR/bench_grad.json` (plot: `DIR/grad_rmse_vs_time.png`):

1. **Gradient error against time, per estimator** (`error`). For `spot_fog` and `backlit` (64 x 64 px, `max_depth` 8,
   the scene files' medium), each estimator in `ESTIMATORS` computes the forward-mode derivative (3 tangents: sigma_t,
   g, albedo) of the mean image and of the 4 x 4 block means (16 x 16 px blocks) in `reps` independent runs; each run
   accumulates chunks of `chunk_spp` samples per pixel, and its running average is recorded at the spp `levels`. The
   time of a level is the sum of its chunks' wall times (each until the result is on the host); compile time is
   measured apart (`lower().compile()`). The error is the relative RMSE over runs against one long-run reference of
   the unbiased "detached" estimator (`ref_chunks` chunks with other keys), so bias counts as error:
   `rel_rmse = sqrt(mean_runs (g - g_ref)^2) / |g_ref|` for the mean image, and
   `sqrt(mean_runs mean_blocks (g_b - g_ref,b)^2) / sqrt(mean_blocks g_ref,b^2)` for the blocks. The reference's own
   error (its standard error, from the spread of its chunks) is removed in the `corrected` figures
   (`sqrt(rmse^2 - se_ref^2)`, independent keys). Also reported: the mean error over runs in units of its standard
   error (`bias_z`: a biased estimator shows |bias_z| >> 1 at the top level) and `t10`, the time to a 10% relative
   RMSE extrapolated from the top level as `t * (err / 0.1)^2` (valid for an unbiased estimator; "never" where the
   bias alone is above 10%).
2. **Primal, forward and reverse mode** (`modes`): `spot_fog` at 128 x 128, 16 spp, `max_depth` 8 (render's default
   batching: 65536 paths per compiled call): the primal render, `jax.jacfwd` of the mean image over 3 parameters and
   `jax.grad` of the mean image over the same 3, each in a fresh subprocess: compile time (`lower().compile()` of one
   jitted whole-render function), run time (median of `mode_runs`), peak memory as XLA's `memory_analysis()` of that
   compiled function (argument + output + temporary buffers), and the subprocess's peak resident set size
   (`VmHWM`) minus that of the same subprocess before compiling.
3. **The closing-note numbers** (`note`): `spot_fog` at full size (128 x 128, `max_depth` 8, sigma_t 0.5, g 0.6):
   d(mean pixel)/d sigma_t, d g, d albedo with the default estimator, mean and standard error over `note_keys` keys of
   `note_spp` spp each.

Timings are wall-clock on whatever else the machine is running (the load average is recorded); compare ratios within
one run.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from benchmarks.common import (
    REPO,
    Stopwatch,
    block_means,
    compile_timed,
    format_table,
    load,
    machine_info,
    mean_and_se,
    memory_dict,
    print_json,
    pyplot,
    run_summary,
    save_figure,
    stderr_log,
    subprocess_env,
    time_calls,
    with_args,
    write_json,
)

PARAMS = ("sigma_t", "g", "albedo")

ESTIMATORS: dict[str, dict] = {
    "detached": dict(estimator="detached"),
    "reparam": dict(estimator="reparam"),
    "proposal (ref = truth)": dict(estimator="proposal", ref=(1.0, 0.0)),
    "proposal (ref off)": dict(estimator="proposal", ref=(0.8, -0.1)),
    "detached, no equiangular": dict(estimator="detached", equiangular=False),
}
"""Gradient estimators. `ref = (factor on sigma_t, offset on g)` of the "proposal" reference medium: `(1, 0)` samples
exactly as "detached" does (the same numbers; a consistency check); `(0.8, -0.1)` is a fit's situation after a step
away from the reference."""


@dataclass
class Config:
    """What one run measures. `FULL` is the committed run, `QUICK` a smoke run of a few minutes."""

    scenes: tuple = ("spot_fog", "backlit")
    size: int = 64
    max_depth: int = 8
    chunk_spp: int = 4
    levels: tuple = (4, 16, 64)
    reps: int = 4
    ref_chunks: int = 32
    ref_chunk_spp: int = 16
    blocks: int = 4
    estimators: tuple = tuple(ESTIMATORS)
    modes: tuple = ("primal", "forward", "reverse")
    mode_depth: int = 8
    mode_size: int = 128
    mode_spp: int = 16
    mode_runs: int = 3
    note_depth: int = 8
    note_size: int = 128
    note_spp: int = 16
    note_keys: int = 24
    parts: tuple = ("error", "modes", "note")
    seed: int = 0


FULL = Config()
QUICK = Config(size=16, max_depth=4, chunk_spp=2, levels=(2, 8), reps=3, ref_chunks=8, ref_chunk_spp=8,
               mode_depth=4, mode_size=32, mode_spp=4, mode_runs=2, note_depth=4, note_size=32, note_spp=4,
               note_keys=4)


# ====================================================================================================== helpers
def load_scene(name: str, size: int, max_depth: int):
    """The shipped scene `name` at `size x size` pixels and `max_depth`, as a `Scene`."""
    return load(name, size, [f"integrator.max_depth={max_depth}"]).scene


def theta0(scene):
    """(sigma_t, g, albedo) of the scene file (grey media: channel 0)."""
    med = scene.medium
    return np.array([float(med.sigma_t[0]), float(med.g), float(med.albedo[0])], np.float32)


def with_theta(scene, theta):
    return scene.replace_medium(sigma_t=theta[0], g=theta[1], albedo=theta[2])


def gradient_fn(scene, spp: int, options: dict, n_blocks: int):
    """Jitted `(theta (3,), key) -> (d mean image / d theta (3,), d block means / d theta (3, n, n))`, forward mode,
    with every sample of the `spp` in one compiled call (`block_means` traces on the JAX image)."""
    import jax
    import jax.numpy as jnp

    import jaxfog as jf

    opts = dict(options)
    ref = opts.pop("ref", None)
    sampling = jf.SamplingOptions(**opts)
    cam = scene.camera

    def f(theta, key):
        proposal = None
        if ref is not None:
            th = jax.lax.stop_gradient(theta)
            proposal = jf.HomogeneousMedium(sigma_t=th[0] * ref[0], albedo=1.0, phase=jf.HenyeyGreenstein(th[1] + ref[1]))

        def reductions(t):
            img = jf.render(with_theta(scene, t), key, spp, sampling=sampling, proposal=proposal,
                            batch_paths=cam.width * cam.height * spp)
            return jnp.mean(img), block_means(img, n_blocks)

        _, (d_mean, d_blocks) = jax.vmap(lambda v: jax.jvp(reductions, (theta,), (v,)))(jnp.eye(3))
        return d_mean, d_blocks

    return jax.jit(f)


def _runs(compiled, theta, n: int, key) -> dict:
    """`time_calls` of `n` calls `compiled(theta, key(i))` (already compiled: no warm-up), each until its outputs are
    NumPy float64 arrays on the host (kept as `values`)."""
    return time_calls(lambda i: tuple(np.asarray(x, np.float64) for x in compiled(theta, key(i))), n, warmup=0,
                      keep=True)


def _key(seed: int, *path: int):
    import jax

    k = jax.random.key(seed)
    for p in path:
        k = jax.random.fold_in(k, p)
    return k


# ========================================================================================= 1. error against time
def reference_gradient(scene, cfg: Config, log=print) -> dict:
    """Long-run "detached" gradient: mean and standard error over `ref_chunks` chunks (keys independent of the runs)."""
    import jax.numpy as jnp

    fn = gradient_fn(scene, cfg.ref_chunk_spp, ESTIMATORS["detached"], cfg.blocks)
    theta = jnp.asarray(theta0(scene))
    compiled, t_compile = compile_timed(fn, theta, _key(cfg.seed + 1, 0))
    t = _runs(compiled, theta, cfg.ref_chunks, lambda c: _key(cfg.seed + 1, c))
    (m, m_se), (b, b_se) = (mean_and_se([v[j] for v in t["values"]]) for j in (0, 1))
    t_run = sum(t["wall_s"])
    log(f"  reference: {cfg.ref_chunks} x {cfg.ref_chunk_spp} spp in {t_run:.0f} s (+ {t_compile:.0f} s compile)")
    return {"mean": m, "mean_se": m_se, "blocks": b, "blocks_se": b_se, "spp": cfg.ref_chunks * cfg.ref_chunk_spp,
            "run_s": t_run, "compile_s": t_compile}


def error_metrics(samples_mean, samples_blocks, ref: dict) -> dict:
    """`samples_mean (runs, 3)`, `samples_blocks (runs, 3, n, n)` against the reference (see module docstring)."""
    d = samples_mean - ref["mean"]
    rmse = np.sqrt(np.mean(d**2, axis=0))
    rel = rmse / np.abs(ref["mean"])
    rel_corr = np.sqrt(np.maximum(rmse**2 - ref["mean_se"] ** 2, 0.0)) / np.abs(ref["mean"])
    runs = samples_mean.shape[0]
    se_runs = samples_mean.std(0, ddof=1) / math.sqrt(runs) if runs > 1 else np.full(3, np.nan)
    bias_z = d.mean(0) / np.sqrt(se_runs**2 + ref["mean_se"] ** 2)
    db = samples_blocks - ref["blocks"]
    rmse_b = np.sqrt(np.mean(db**2, axis=(0, 2, 3)))
    norm_b = np.sqrt(np.mean(ref["blocks"] ** 2, axis=(1, 2)))
    ref_b = np.sqrt(np.mean(ref["blocks_se"] ** 2, axis=(1, 2)))
    return {"rel_rmse": rel, "rel_rmse_corrected": rel_corr, "rel_bias": d.mean(0) / np.abs(ref["mean"]),
            "bias_z": bias_z, "block_rel_rmse": rmse_b / norm_b,
            "block_rel_rmse_corrected": np.sqrt(np.maximum(rmse_b**2 - ref_b**2, 0.0)) / norm_b}


def measure_estimator(scene, cfg: Config, options: dict, ref: dict) -> dict:
    """Runs of one estimator: compile, then `reps` runs of cumulative chunks; metrics at each level."""
    import jax.numpy as jnp

    theta = jnp.asarray(theta0(scene))
    fn = gradient_fn(scene, cfg.chunk_spp, options, cfg.blocks)
    compiled, t_compile = compile_timed(fn, theta, _key(cfg.seed, 0, 0))
    n_chunks = max(cfg.levels) // cfg.chunk_spp
    at_level = {lv: {"mean": [], "blocks": [], "time": []} for lv in cfg.levels}
    for r in range(cfg.reps):  # run r: the running averages of its chunks and their cumulative wall time
        t = _runs(compiled, theta, n_chunks, lambda c: _key(cfg.seed, r, c))
        n = np.arange(1, n_chunks + 1)
        m = np.cumsum([v[0] for v in t["values"]], axis=0) / n[:, None]
        b = np.cumsum([v[1] for v in t["values"]], axis=0) / n[:, None, None, None]
        for c, elapsed in enumerate(np.cumsum(t["wall_s"])):
            if (c + 1) * cfg.chunk_spp in at_level:
                a = at_level[(c + 1) * cfg.chunk_spp]
                a["mean"].append(m[c])
                a["blocks"].append(b[c])
                a["time"].append(float(elapsed))
    levels = []
    for lv in cfg.levels:
        a = at_level[lv]
        met = error_metrics(np.asarray(a["mean"]), np.asarray(a["blocks"]), ref)
        levels.append({"spp": lv, "time_s": float(np.mean(a["time"])), **met,
                       "grad_mean": np.mean(a["mean"], axis=0)})
    top = levels[-1]
    t10 = []
    for p in range(3):
        if abs(top["rel_bias"][p]) > 0.1 and abs(top["bias_z"][p]) > 3:
            t10.append(float("inf"))
        else:
            t10.append(top["time_s"] * (top["rel_rmse"][p] / 0.1) ** 2)  # uncorrected: conservative
    return {"options": options, "compile_s": t_compile, "levels": levels, "t10_s": t10}


def error_study(cfg: Config, log=print) -> dict:
    out = {}
    for name in cfg.scenes:
        log(f"[error] {name} ({cfg.size} x {cfg.size}, max_depth {cfg.max_depth})")
        scene = load_scene(name, cfg.size, cfg.max_depth)
        ref = reference_gradient(scene, cfg, log=log)
        res = {"reference": ref, "estimators": {}}
        for est in cfg.estimators:
            r = measure_estimator(scene, cfg, ESTIMATORS[est], ref)
            top = r["levels"][-1]
            log(f"  {est:26s} compile {r['compile_s']:5.1f} s; at {top['spp']} spp ({top['time_s']:.1f} s): "
                f"rel RMSE {np.array2string(top['rel_rmse'], precision=3)}")
            res["estimators"][est] = r
        out[name] = res
    return out


# ======================================================================================== 2. primal / fwd / rev
def _mode_child(mode: str, size: int, spp: int, max_depth: int, runs: int) -> dict:
    """Runs in a fresh subprocess: compile and time one mode; memory from XLA and from the process's peak RSS."""
    from jaxfog.tools import max_rss_mib

    import jax
    import jax.numpy as jnp

    import jaxfog as jf

    scene = load_scene("spot_fog", size, max_depth)
    theta = jnp.asarray(theta0(scene))
    key = jax.random.key(0)

    def mean_image(t):
        return jnp.mean(jf.render(with_theta(scene, t), key, spp))

    if mode == "primal":
        fn = jax.jit(lambda t: jf.render(with_theta(scene, t), key, spp))
    elif mode == "forward":
        fn = jax.jit(jax.jacfwd(mean_image))
    elif mode == "reverse":
        fn = jax.jit(jax.grad(mean_image))
    else:
        raise ValueError(mode)
    rss0 = max_rss_mib()
    compiled, t_compile = compile_timed(fn, theta)
    rss_compiled = max_rss_mib()
    t = time_calls(lambda _: jax.block_until_ready(compiled(theta)), runs, warmup=0)
    rss = max_rss_mib()
    return {"mode": mode, "compile_s": t_compile, "run_s": t["median_s"], "run_all_s": t["wall_s"],
            "xla": memory_dict(compiled.memory_analysis()), "rss_before_compile_mib": rss0,
            "rss_after_compile_mib": rss_compiled, "rss_peak_mib": rss,
            "rss_run_mib": rss - rss_compiled, "paths": size * size * spp}


def mode_study(cfg: Config, log=print) -> dict:
    out = {}
    for mode in cfg.modes:
        cmd = [sys.executable, "-m", "benchmarks.bench_grad", "--_mode", mode, "--_mode-args",
               json.dumps([cfg.mode_size, cfg.mode_spp, cfg.mode_depth, cfg.mode_runs])]
        log(f"[modes] {mode} ({cfg.mode_size} x {cfg.mode_size}, {cfg.mode_spp} spp) in a subprocess")
        proc = subprocess.run(cmd, capture_output=True, text=True, env=subprocess_env())
        if proc.returncode != 0:
            out[mode] = {"error": proc.stderr[-2000:]}
            log(f"  failed: {proc.stderr[-500:]}")
            continue
        out[mode] = json.loads(proc.stdout.strip().splitlines()[-1])
        r = out[mode]
        log(f"  compile {r['compile_s']:.1f} s, run {r['run_s']:.2f} s, XLA {r['xla']['total_mib']:.0f} MiB, "
            f"peak RSS {r['rss_peak_mib']:.0f} MiB")
    return out


# ======================================================================================== 3. closing-note numbers
def note_study(cfg: Config, log=print) -> dict:
    import jax.numpy as jnp

    scene = load_scene("spot_fog", cfg.note_size, cfg.note_depth)
    theta = jnp.asarray(theta0(scene))
    fn = gradient_fn(scene, cfg.note_spp, ESTIMATORS["detached"], 4)
    compiled, t_compile = compile_timed(fn, theta, _key(cfg.seed + 2, 0))
    t = _runs(compiled, theta, cfg.note_keys, lambda k: _key(cfg.seed + 2, k))
    vals, t_run, n = np.asarray([v[0] for v in t["values"]]), sum(t["wall_s"]), cfg.note_keys
    mean, se = mean_and_se(vals)
    log(f"[note] spot_fog {cfg.note_size} x {cfg.note_size}: " + ", ".join(
        f"d/d {p} {mean[i]:.4f} +- {se[i]:.4f}" for i, p in enumerate(PARAMS)) + f" ({n} x {cfg.note_spp} spp)")
    return {"estimator": "detached", "size": cfg.note_size, "spp_per_key": cfg.note_spp, "keys": n,
            "theta": theta0(scene), "d_mean": mean, "se": se, "per_key": vals, "compile_s": t_compile,
            "run_s": t_run}


# ============================================================================================= report and plot
DEFAULT_CANDIDATES = ("detached", "reparam", "detached, no equiangular")
"""Estimators that need no reference medium, i.e. that can be `render`'s default for gradients."""


def choose_default(error: dict) -> dict:
    """Among `DEFAULT_CANDIDATES`, the one with the smallest geometric mean over scenes and parameters of `t10` (time
    to a 10% relative RMSE of the gradient of the mean image; infinite for an estimator biased by more than 10%)."""
    scores = {}
    for est in next(iter(error.values()))["estimators"]:
        if est not in DEFAULT_CANDIDATES:
            continue
        t = [v for res in error.values() for v in res["estimators"][est]["t10_s"]]
        scores[est] = float(np.exp(np.mean(np.log(np.maximum(t, 1e-9))))) if np.all(np.isfinite(t)) else float("inf")
    best = min(scores, key=scores.get)
    return {"scores_geomean_t10_s": scores, "default": best}


def _f(x, nd=3):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "never" if x == float("inf") else "-"
    return f"{x:.{nd}g}"


def format_tables(result: dict) -> str:
    lines = []
    cfg = result["config"]
    per_param = lambda head, key, spec: [(f"{head} {p}", lambda r, i=i: r[key][i], spec)  # noqa: E731
                                         for i, p in enumerate(PARAMS)]
    if "error" in result:
        lines.append(f"Gradient error against time ({cfg['size']} x {cfg['size']} px, max_depth {cfg['max_depth']}, "
                     f"forward mode over (sigma_t, g, albedo); relative RMSE over {cfg['reps']} runs against a "
                     f"detached reference; 'corr' removes the reference's own error; RMSE: of the mean image, corr; "
                     "block: of the block means, corr; z: bias z)")
        rows = [{"scene": name, "estimator": est, **lv} for name, res in result["error"].items()
                for est, r in res["estimators"].items() for lv in r["levels"]]
        lines.append(format_table(rows, [("scene", "scene"), ("estimator", "estimator"), ("spp", "spp"),
                                         ("time s", "time_s", ".2f"),
                                         *per_param("RMSE", "rel_rmse_corrected", ".3g"),
                                         *per_param("block", "block_rel_rmse_corrected", ".3g"),
                                         *per_param("z", "bias_z", ".1f")]))
        lines.append("")
        lines.append("Time to a 10% relative RMSE of d(mean image) (s, extrapolated from the top level; compile apart)")
        rows = [{"scene": name, "estimator": est, **r} for name, res in result["error"].items()
                for est, r in res["estimators"].items()]
        lines.append(format_table(rows, [("scene", "scene"), ("estimator", "estimator"),
                                         ("compile s", "compile_s", ".1f"), *per_param("t10", "t10_s", _f)]))
        ch = result.get("default_choice")
        if ch:
            lines.append(f"-> default for gradients: {ch['default']} (geometric mean of t10 over scenes and "
                         f"parameters, estimators that need no reference: "
                         + ", ".join(f"{k} {_f(v)}" for k, v in ch["scores_geomean_t10_s"].items()) + ")")
        for name, res in result["error"].items():
            ref = res["reference"]
            lines.append(f"reference {name}: d(mean image)/d(sigma_t, g, albedo) = "
                         + ", ".join(f"{m:.5f} +- {s:.5f}" for m, s in zip(ref["mean"], ref["mean_se"]))
                         + f" ({ref['spp']} spp)")
    if "modes" in result:
        m = result["modes"]
        lines.append("")
        lines.append(f"Primal, forward and reverse mode (spot_fog {cfg['mode_size']} x {cfg['mode_size']}, "
                     f"{cfg['mode_spp']} spp, max_depth {cfg['mode_depth']}; each in a fresh process)")
        base = m.get("primal", {}).get("run_s")
        labels = {"primal": "primal render", "forward": "jacfwd, 3 params (forward)",
                  "reverse": "grad, 3 params (reverse)"}
        rows = [{"mode": labels.get(mode, mode) + (" failed" if "error" in r else ""), **r,
                 "x_primal": r["run_s"] / base if base and "run_s" in r else None,
                 "xla_mib": r["xla"]["total_mib"] if "xla" in r else None} for mode, r in m.items()]
        lines.append(format_table(rows, [
            ("mode", "mode"), ("compile s", "compile_s", ".1f"), ("run s", "run_s", ".2f"),
            ("x primal", "x_primal", ".2f"), ("XLA MiB", "xla_mib", ".0f"), ("RSS peak MiB", "rss_peak_mib", ".0f"),
            ("RSS run MiB", "rss_run_mib", ".0f")]))
    if "note" in result:
        n = result["note"]
        lines.append("")
        lines.append(f"spot_fog {n['size']} x {n['size']}, max_depth {cfg['note_depth']}, (sigma_t, g, albedo) = "
                     f"{tuple(round(float(x), 3) for x in n['theta'])}, {n['estimator']}, {n['keys']} keys x "
                     f"{n['spp_per_key']} spp:")
        lines.append("  " + ", ".join(f"d(mean pixel)/d {p} = {n['d_mean'][i]:.4f} +- {n['se'][i]:.4f}"
                                      for i, p in enumerate(PARAMS)))
    return "\n".join(lines)


def plot(result: dict, path: Path) -> None:
    plt = pyplot()
    error = result["error"]
    scenes = list(error)
    fig, axes = plt.subplots(len(scenes), 3, figsize=(12, 3.4 * len(scenes)), squeeze=False)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, name in enumerate(scenes):
        for p, pname in enumerate(PARAMS):
            ax = axes[i, p]
            for j, (est, r) in enumerate(error[name]["estimators"].items()):
                t = [lv["time_s"] for lv in r["levels"]]
                ax.loglog(t, [max(lv["rel_rmse_corrected"][p], 1e-4) for lv in r["levels"]], "o-",
                          color=colors[j % len(colors)], label=est)
                ax.loglog(t, [max(lv["block_rel_rmse_corrected"][p], 1e-4) for lv in r["levels"]], "s--",
                          color=colors[j % len(colors)], alpha=0.5)
            ax.set_title(f"{name}: d/d {pname}", fontsize=9)
            ax.set_xlabel("wall time per gradient (s)", fontsize=8)
            ax.set_ylabel("relative RMSE", fontsize=8)
            ax.tick_params(labelsize=7)
            ax.grid(True, which="both", alpha=0.3)
    axes[0, 0].legend(fontsize=7, title="solid: mean image, dashed: blocks", title_fontsize=7)
    save_figure(fig, path, dpi=70)


def run_benchmark(cfg: Config, out: Path, plots: bool = True, log=print) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    sw = Stopwatch()
    result = {"config": asdict(cfg), "machine": machine_info()}
    if "error" in cfg.parts:
        result["error"] = error_study(cfg, log=log)
        result["default_choice"] = choose_default(result["error"])
    if "modes" in cfg.parts:
        result["modes"] = mode_study(cfg, log=log)
    if "note" in cfg.parts:
        result["note"] = note_study(cfg, log=log)
    result["total_wall_s"] = sw.s
    write_json(out / "bench_grad.json", result)
    if plots and "error" in result:
        plot(result, out / "grad_rmse_vs_time.png")
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench_grad", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="a small smoke run (a few minutes)")
    p.add_argument("--out", default=str(REPO / "bench_grad_out"), metavar="DIR",
                   help="output directory (JSON, PNG; default: bench_grad_out in the repository root)")
    p.add_argument("--parts", nargs="+", choices=("error", "modes", "note"), help="parts to run (default all)")
    p.add_argument("--no-plots", action="store_true")
    p.add_argument("--_mode", help=argparse.SUPPRESS)
    p.add_argument("--_mode-args", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    from jaxfog import use_cpu_cores

    use_cpu_cores()  # every core as a JAX device (a no-op once JAX has started, e.g. under pytest)
    if args._mode:
        size, spp, depth, runs = json.loads(args._mode_args)
        print_json(_mode_child(args._mode, size, spp, depth, runs))
        return 0
    cfg = with_args(QUICK if args.quick else FULL, args)
    result = run_benchmark(cfg, Path(args.out), plots=not args.no_plots, log=stderr_log)
    print(format_tables(result))
    print("\n" + run_summary(f"{Path(args.out) / 'bench_grad.json'}", result))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
