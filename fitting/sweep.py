"""Parameter error against fit wall time, as the fit's spp and image size change.

    python -m fitting.sweep [--target mid] [--settings 16:64 16:128 ...] [--out DIR]

Runs `python -m fitting.fit` (in this process, one fit after another) on the two shipped views of one truth
(`spot_fog` + `spot_fog_low`) for each `DOWNSCALE:SPP` setting, from the same start (a factor 2 off in sigma_t, 0.3 off
in g), and prints a table of |error| in sigma_t (relative) and g (absolute), the fit's own standard error and its wall
time; writes `sweep.json` and `sweep.png` (error against wall time, log-log) into the output directory. One fit per
setting: an error is one draw, to be read beside its standard error.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
TARGETS = REPO / "data_synthetic" / "targets"
SCENES = REPO / "data_synthetic" / "scenes"
START = {"mid": "sigma_t=0.25 g=0.3", "denser_less_forward": "sigma_t=0.4 g=0.0", "thin_backward": "sigma_t=0.5 g=0.0"}
DEFAULT_SETTINGS = ("32:512", "16:64", "16:128", "16:256", "8:64")


def run_one(target: str, downscale: int, spp: int, workdir: str) -> dict:
    from .fit import main as fit_main

    out = os.path.join(workdir, f"{target}_{downscale}_{spp}.json")
    argv = [str(SCENES / "spot_fog.json"), str(TARGETS / f"spot_fog__{target}.exr"),
            str(SCENES / "spot_fog_low.json"), str(TARGETS / f"spot_fog_low__{target}.exr"),
            "--fit", "sigma_t", "g", "--init", *START[target].split(), "--spp", str(spp),
            "--downscale", str(downscale), "--quiet", "--out", out]
    rc = fit_main(argv)
    res = json.loads(Path(out).read_text())
    t = res["truth"]
    return {"downscale": downscale, "size": 128 // downscale, "spp": spp, "exit": rc, "success": res["success"],
            "wall_s": res["wall_s"], "params": res["params"], "truth": t,
            "se": {n: res["uncertainty"][n]["se"] for n in ("sigma_t", "g")},
            "err_sigma_t_rel": abs(res["params"]["sigma_t"] - t["sigma_t"]) / t["sigma_t"],
            "err_g_abs": abs(res["params"]["g"] - t["g"]), "rounds": res["rounds"]}


def table(rows: list[dict]) -> str:
    out = [f"{'size':>7} {'spp':>5} {'wall s':>7} {'sigma_t':>8} {'± se':>7} {'|err|%':>7} {'g':>8} {'± se':>7} "
           f"{'|err|':>7} {'rounds':>6}  verdict"]
    for r in rows:
        p, se = r["params"], r["se"]
        out.append(f"{r['size']:>3} px^2 {r['spp']:>5} {r['wall_s']:>7.0f} {p['sigma_t']:>8.4f} {se['sigma_t']:>7.4f} "
                   f"{100 * r['err_sigma_t_rel']:>7.1f} {p['g']:>8.4f} {se['g']:>7.4f} {r['err_g_abs']:>7.3f} "
                   f"{r['rounds']:>6}  {'ok' if r['success'] else 'FAILED'}")
    return "\n".join(out)


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, key, se_key, label, scale in ((axes[0], "err_sigma_t_rel", "sigma_t", "|error| of sigma_t (relative)", "rel"),
                                          (axes[1], "err_g_abs", "g", "|error| of g", "abs")):
        for r in rows:
            se = r["se"][se_key] / (r["truth"]["sigma_t"] if scale == "rel" else 1.0)
            ax.errorbar(r["wall_s"], max(r[key], 1e-4), yerr=se, fmt="o", capsize=3)
            ax.annotate(f"{r['size']}px {r['spp']}spp", (r["wall_s"], max(r[key], 1e-4)), fontsize=7,
                        xytext=(4, 4), textcoords="offset points")
        ax.axhline(0.02, color="grey", ls="--", lw=0.8)
        ax.set_yscale("log")  # wall times span less than a decade: a linear axis keeps its labels readable
        ax.set_xlabel("fit wall time (s)"), ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    fig.suptitle("fit error against wall time (bars: the fit's own standard error; dashed: the 2% / 0.02 goal)")
    fig.tight_layout()
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=90)
    os.replace(tmp, path)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m fitting.sweep", description=__doc__.split("\n\n")[0])
    p.add_argument("--target", choices=sorted(START), default="mid")
    p.add_argument("--settings", nargs="+", default=list(DEFAULT_SETTINGS), metavar="DOWNSCALE:SPP")
    p.add_argument("--out", default="bench_out/fit_sweep")
    args = p.parse_args(argv)
    from jaxfog.tools import use_cpu_cores

    use_cpu_cores()  # every core as a JAX device (a no-op once JAX has started, e.g. under pytest)
    try:
        settings = [tuple(int(x) for x in s.split(":")) for s in args.settings]
    except ValueError:
        print(f"error: --settings expects DOWNSCALE:SPP pairs, got {args.settings}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    with tempfile.TemporaryDirectory() as work:
        for i, (ds, spp) in enumerate(settings):
            print(f"[{i + 1}/{len(settings)}] {args.target}: {128 // ds} x {128 // ds} px, {spp} spp", flush=True)
            rows.append(run_one(args.target, ds, spp, work))
            print(table(rows[-1:]).splitlines()[-1], flush=True)
            (out / "sweep.json").write_text(json.dumps({"target": args.target, "rows": rows}, indent=1))
    print()
    print(table(rows))
    plot(rows, out / "sweep.png")
    print(f"wrote {out / 'sweep.json'}, {out / 'sweep.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
