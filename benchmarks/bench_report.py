"""The report of `benchmarks.bench`: its result (`bench.json`) as the printed tables (`format_tables`) and the plots
(`plot_strategies`: RMSE against time; `plot_depth`: bias and cost against `max_depth`)."""

from __future__ import annotations

from pathlib import Path

from benchmarks.bench_stats import ONE_PIXEL
from benchmarks.common import format_table, pyplot, save_figure


def _fmt_ms(s: float) -> str:
    return f"{1e3 * s:.0f}"


def format_tables(result: dict) -> str:
    """The printed report of a result: the strategy tables, variance reduction, the depth table and picks, the
    comparison with Mitsuba and the peak memory (each where the result has it)."""
    lines = []
    for name, sc in result.get("scenes", {}).items():
        lines += _strategy_lines(name, sc)
    lines += _variance_reduction_lines(result.get("variance_reduction") or {})
    if result.get("depth"):
        lines += _depth_lines(result["depth"])
    if result.get("mitsuba"):
        lines += _mitsuba_lines(result["mitsuba"])
    mem = result.get("memory")
    if mem:
        lines.append("")
        lines.append("peak memory: " + "; ".join(f"{k} {v:.0f} MiB" for k, v in mem.items()
                                                 if isinstance(v, (int, float))))
    return "\n".join(lines)


def _strategy_lines(name: str, sc: dict) -> list[str]:
    ref = sc["reference"]
    lines = [""]
    lines.append(f"== {name} ({sc['width']}x{sc['height']}, max_depth {sc['max_depth']}); reference: default strategy, "
                 f"{ref['spp']} spp, mean pixel {ref['mean']:.4g} +- {ref['mean_se']:.2g}, its own RMSE "
                 f"{ref['rmse']:.3g} ({100 * ref['rel_rmse']:.1f}% of the mean, from its halves)")
    lines.append("relative RMSE (corrected for the reference's own noise) at each spp; time to a common RMSE")
    levels = [(i, x["spp"]) for i, x in enumerate(next(iter(sc["strategies"].values()))["levels"])]
    lines.append(format_table([{"strategy": k, **v, "shared": v.get("compiled_by", sc["scene"]) != sc["scene"]}
                               for k, v in sc["strategies"].items()], [
        ("strategy", "strategy"),
        ("compile s", lambda s: f"{s.get('compile_s_first', s['compile_s']):.1f}" + ("+" if s["shared"] else " ")),
        ("ms/spp", "time_per_spp_s", _fmt_ms), ("kpath/s", lambda s: s["paths_per_s"] / 1e3, ".1f"),
        ("XLA MiB", lambda s: (s.get("xla_memory") or {}).get("total_mib"), ".1f"),
        *((f"@{n}", lambda s, i=i: s["levels"][i], lambda x: f"{x['rel_rmse_corrected']:.3g}"
           + ("!" if x.get("worst_pixel_share", 0) > ONE_PIXEL else " ")) for i, n in levels),
        (f"t to {100 * sc['target_rel_rmse']:.1f}%", lambda s: f"{s['time_to_target_s']:.1f}"
         + ("*" if s["time_to_target_how"] == "extrapolated" else " ")),
        ("vs default", lambda s: s.get("time_ratio_to_default", float("nan")), ".2f")]))
    lines.append(f"(! more than {ONE_PIXEL:.0%} of the squared error in one pixel: a firefly; "
                 "* extrapolated with RMSE ~ t^-1/2; compile = JAX trace + lower + XLA compile of the first "
                 "compilation, + where it happened for another render of the same structure (reference, earlier "
                 "scene) and this one reused the program)")
    return lines


def _variance_reduction_lines(vr: dict) -> list[str]:
    if not vr:
        return []
    lines = ["", "variance reduction (MSE ratio, corrected RMSE squared): A / B"]
    for name, v in vr.items():
        for label, r in v.items():
            if r is None:
                continue
            a = r["at_max_spp"]
            lines.append(f"  {name:14s} {r['base']} / {r['better']}: at {a['spp']} spp {a['mse_ratio_equal_spp']:.2f} "
                         f"(equal spp), {a['mse_ratio_equal_time']:.2f} (equal time); geometric mean over spp "
                         f"levels {r['geomean_equal_spp']:.2f} / {r['geomean_equal_time']:.2f}")
    return lines


def _depth_lines(dp: dict) -> list[str]:
    lines = [""]
    lines.append(f"== depth against bias ({dp['width']}x{dp['height']}, {dp['spp']} spp, common random numbers, "
                 "default strategy): bias against the deepest row (reference) relative to its mean; 'pixel bias' is "
                 "the per-pixel RMSE beyond noise, '(noise)' that estimate's own noise level")
    rows = []
    for name, s in dp["scenes"].items():
        if s.get("largest_path_share", 0) > 0.05:
            lines.append(f"{name}: one path of the {dp['spp']} x {dp['width']}x{dp['height']} carries "
                         f"{100 * s['largest_path_share']:.0f}% of the reference's mean: its rows are not resolved")
        t8 = next((r["time_per_spp_s"] for r in s["rows"] if r["depth"] == 8), None)
        rows += [{"scene": name, **r, "rel_t": r["time_per_spp_s"] / t8 if t8 else float("nan")} for r in s["rows"]]
    lines.append(format_table(rows, [
        ("scene", "scene"), ("depth", "depth"), ("mean", "mean", ".4g"), ("mean bias", "rel_mean_bias", ".2%"),
        ("+-se", "rel_mean_bias_se", ".2%"), ("pixel bias", "rel_pixel_bias", ".2%"),
        ("(noise)", "rel_pixel_noise", ".2%"), ("ms/spp", "time_per_spp_s", _fmt_ms),
        ("x ms/spp@8", "rel_t", ".2f"), ("", lambda r: "(reference)" if r["is_reference"] else "")]))
    picks = dp.get("picks")
    max_measured = max((r["depth"] for s in dp["scenes"].values() for r in s["rows"] if not r["is_reference"]),
                       default=0)
    if picks:
        lines.append("cheapest depth within a relative error (pick_depth, metric 'pixel'):")
        for err, per in picks.items():
            lines.append(f"  {float(err):6.1%}: " + ", ".join(
                f"{n} -> {d if d is not None else 'none measured (deeper than ' + str(max_measured) + ')'}"
                for n, d in per.items()))
    return lines


def _mitsuba_lines(mt: dict) -> list[str]:
    if "skipped" in mt:
        return ["", f"== Mitsuba 3: skipped ({mt['skipped']})"]
    lines = [""]
    lines.append(f"== Mitsuba {mt['version']} ({mt['variant']}, {mt['threads']} threads, volpath) on {mt['scene']}: "
                 f"{mt['total_spp']} spp in {mt['renders']} renders, {_fmt_ms(mt['time_per_spp_s'])} ms/spp, "
                 f"{mt['paths_per_s'] / 1e3:.1f} kpaths/s, warm-up (kernel compile) {mt['warmup_s']:.1f} s")
    lines.append(f"  mean pixel: jaxfog {mt['jaxfog_mean']:.5f} +- {mt['jaxfog_mean_se']:.5f} "
                 f"({mt['jaxfog_mean_source']}), Mitsuba {mt['mean']:.5f} +- {mt['mean_se']:.5f}: "
                 f"z = {mt['z_mean']:+.2f} -> {'agree' if mt['means_agree'] else 'DISAGREE'} (|z| < 3)")
    lines.append(f"  4x4 regions: max |z| {mt['max_abs_z_block']:.2f}; best orientation: {mt['best_orientation']} "
                 "(mean z^2 per region: " + ", ".join(f"{k} {v['chi2_per_block']:.2f}"
                                                       for k, v in mt["orientation"].items()) + ")")
    hj, hm = mt["halves_jaxfog"], mt["halves_mitsuba"]
    lines.append("  halves (jaxfog / Mitsuba): " + ", ".join(f"{k} {hj[k]:.4f} / {hm[k]:.4f}" for k in hj))
    lines.append(f"  Mitsuba RMSE at 64 spp (mean MSE of {mt['rmse64_from_images']} independent 64-spp images, "
                 f"corrected): {mt['rmse64_corrected']:.4f} ({100 * mt['rel_rmse64_corrected']:.1f}% of the mean; "
                 f"median image {100 * mt['rmse64_corrected_median'] / mt['jaxfog_mean']:.1f}%; per image "
                 + " ".join(f"{100 * x:.0f}%" for x in mt["rel_rmse64_per_image"])
                 + f"), time for 64 spp {mt['time64_s']:.2f} s")
    if mt.get("measured"):
        lines += _measured_lines(mt["measured"])
    return lines + _ratio_lines(mt)


def _measured_lines(ms: dict) -> list[str]:
    lines = []
    for k in ("median_image", "mean_mse"):
        r = ms[k]
        label = "HEADLINE" if k == "median_image" else "expected"
        if r.get("spp") is None:
            lines.append(f"  {label} ({k}): jaxfog did not reach Mitsuba's {100 * r['mitsuba_rel_rmse']:.0f}% "
                         f"({r['note']})")
            continue
        lines.append(f"  {label}, measured ({k.replace('_', ' ')} of per-image RMSEs): jaxfog (default) at "
                     f"{r['spp']} spp{' (the fewest)' if r['at_fewest_spp'] else ''}: "
                     f"{100 * r['jaxfog_rel_rmse']:.0f}% in {_fmt_ms(r['time_s'])} ms per image; Mitsuba at "
                     f"64 spp: {100 * r['mitsuba_rel_rmse']:.0f}% in {_fmt_ms(ms['mitsuba_time64_s'])} ms -> "
                     f"time-to-equal-error ratio jaxfog / Mitsuba = {r['ratio']:.3f} ({1 / r['ratio']:.1f}x)")
    lines.append("    jaxfog per spp (" + str(ms["tries"][0]["draws"]) + " images each): " + "; ".join(
        f"{t['spp']} spp {_fmt_ms(t['time_s'])} ms, median {100 * t['rel_rmse']['median_image']:.0f}% "
        f"mean-MSE {100 * t['rel_rmse']['mean_mse']:.0f}%" for t in ms["tries"]))
    return lines


def _ratio_lines(mt: dict) -> list[str]:
    lines = []
    vb = mt.get("variance_based")
    if vb:
        lines.append(f"  from the reference's variance ({vb['from_chunks']} chunks): jaxfog needs "
                     f"{vb['jaxfog_spp_to_target']:.2f} spp (fractional) -> ratio {vb['ratio']:.3f}")
    adj = mt.get("adjacent")
    if adj:
        lines.append(f"  from the strategy study's single curve (timed next to Mitsuba: jaxfog "
                     f"{_fmt_ms(adj['jaxfog_time_per_spp_s_before'])} / "
                     f"{_fmt_ms(adj['jaxfog_time_per_spp_s_after'])} ms/spp before / after, Mitsuba "
                     f"{_fmt_ms(adj['mitsuba_time_per_spp_s'])} ms/spp): jaxfog default needs "
                     f"{adj['jaxfog_spp_to_target']:.2f} spp ({adj['how']}) for Mitsuba's 64-spp RMSE: "
                     f"time-to-equal-error ratio jaxfog / Mitsuba = {adj['ratio']:.3f} "
                     f"(median-image target: {adj['jaxfog_spp_to_median_target']:.2f} spp, "
                     f"{adj['ratio_median_target']:.3f})")
        lines.append("  with the strategy study's own timings (taken earlier in the run, under other load):")
    for sname, r in mt["time_to_mitsuba64"].items():
        lines.append(f"  jaxfog {sname:12s} reaches it in {r['time_s']:7.2f} s ({r['how']}): time-to-equal-error "
                     f"ratio jaxfog / Mitsuba = {r['ratio_jaxfog_over_mitsuba']:.3f} (median-image target: "
                     f"{r['ratio_median_target']:.3f}, {r['how_median_target']})")
    return lines


def _axis_style(ax) -> None:
    ax.grid(True, which="both", lw=0.3)
    ax.tick_params(labelsize=7)


def plot_strategies(result: dict, path: Path) -> None:
    """Relative RMSE against wall time, per scene and strategy (and Mitsuba's, on its scene)."""
    plt = pyplot()
    scenes = result["scenes"]
    n = len(scenes)
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n, 3.6), squeeze=False)
    mt = result.get("mitsuba") or {}
    for ax, (name, sc) in zip(axes[0], scenes.items()):
        for sname, s in sc["strategies"].items():
            lv = [x for x in s["levels"] if x["rel_rmse_corrected"] > 0]
            ax.loglog([x["time_s"] for x in lv], [x["rel_rmse_corrected"] for x in lv], "o-", ms=3, label=sname)
        if mt.get("scene") == name and "levels" in mt:
            lv = [x for x in mt["levels"] if x["rel_rmse_corrected"] > 0]
            ax.loglog([x["time_s"] for x in lv], [x["rel_rmse_corrected"] for x in lv], "k^--", ms=3,
                      label=f"Mitsuba {mt['version']}")
        ax.axhline(sc["reference"]["rel_rmse"], color="grey", ls=":", lw=1, label="reference's own RMSE")
        ax.set_title(f"{name} ({sc['width']}x{sc['height']})", fontsize=9)
        ax.set_xlabel("wall time after compilation (s)", fontsize=8)
        _axis_style(ax)
    axes[0][0].set_ylabel("per-pixel RMSE / mean pixel", fontsize=8)
    axes[0][0].legend(fontsize=7)
    save_figure(fig, path)


def plot_depth(depth: dict, path: Path) -> None:
    """Bias against max_depth (per pixel and of the mean) and the time per spp, per depth scene."""
    fig, (a1, a2) = pyplot().subplots(1, 2, figsize=(8.4, 3.4))
    for name, s in depth["scenes"].items():
        rows = [r for r in s["rows"] if not r["is_reference"]]
        d = [r["depth"] for r in rows]
        a1.semilogy(d, [max(r["rel_pixel_bias"], 1e-5) for r in rows], "o-", ms=3, label=f"{name} per-pixel")
        a1.semilogy(d, [max(abs(r["rel_mean_bias"]), 1e-5) for r in rows], "x--", ms=4, label=f"{name} mean")
        a2.plot([r["depth"] for r in s["rows"]], [1e3 * r["time_per_spp_s"] for r in s["rows"]], "o-", ms=3, label=name)
    a1.set_xscale("log", base=2)
    a2.set_xscale("log", base=2)
    a1.set_xlabel("max_depth", fontsize=8)
    a2.set_xlabel("max_depth", fontsize=8)
    a1.set_ylabel("bias / mean (vs each scene's deepest)", fontsize=8)
    a2.set_ylabel(f"ms per spp at {depth['width']}x{depth['height']}", fontsize=8)
    for a in (a1, a2):
        _axis_style(a)
        a.legend(fontsize=6)
    save_figure(fig, path)
