"""The foreign suite's coverage over its targets' own noise: each case fitted on K Mitsuba targets of its own (other
seeds than the shipped ones), so that the errors scatter with the target's draw as they do for a user, whose target
is one draw (the suite and the coverage study keep one target per case and vary the fit's seed only).

    python -m benchmarks.foreign_resampled --cases spot_thin_forward,spot_two_view --seeds 1 2 3 4 5 6 7 8 --out OUT

Needs the `compare` extra (Mitsuba 3). Per case and seed it renders the case's views at the truth with Mitsuba's
`volpath` (`scalar_rgb`, the manifest's spp unless `--spp`; seed `10 * seed + view`) into `OUT/CASE/SEED/`, runs the
suite's `python -m fitting.fit` command on them (`fitting.suite.run_case`, the fit's defaults but `--seed SEED`: a
fit's renders share their noise wherever its seed does, so one fit seed for every target would move a case's fits
together by one draw of the renders' noise), and appends one line
to `OUT/fits.jsonl`. Targets and fits already in OUT are kept (a run can be resumed). Prints, per case and parameter,
the mean error, the standard deviation of the errors over the targets, the mean reported standard error, the mean
and rms of error / se and the share within 1 and 2 se; writes them to `OUT/summary.json`. `--average` fits also
the mean of each case's targets (K x spp samples per pixel): the error left when the target noise is averaged down.
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from fitting.suite import _make_foreign, load_manifest, run_case

from .common import print_table


def render_targets(case: dict, seed: int, spp: int, folder: Path) -> list[str]:
    """The case's views rendered by Mitsuba at the truth into `folder` (kept if there); their paths."""
    import jaxfog

    paths = []
    for i, view in enumerate(case["views"]):
        path = folder / Path(view["target"]).name
        if not path.exists():
            data = _make_foreign().truth_scene(view["rendered_scene"], case["truth"])
            t0 = time.perf_counter()
            img = np.asarray(jaxfog.render_mitsuba(data, spp=spp, seed=10 * seed + i), np.float32)
            meta = {"jaxfog:truth": json.dumps(case["truth"]), "jaxfog:scene_file": view["rendered_scene"],
                    "renderer": "mitsuba scalar_rgb", "mitsuba:spp": spp, "mitsuba:seed": 10 * seed + i}
            folder.mkdir(parents=True, exist_ok=True)
            jaxfog.write_exr(str(path), img, meta)
            print(f"{case['name']} seed {seed} view {i}: {spp} spp, {time.perf_counter() - t0:.1f} s", flush=True)
        paths.append(str(path))
    return paths


def average_targets(case: dict, folders: list[Path], out: Path) -> list[str]:
    """Per view, the mean of the targets in `folders`, written to `out` with their total spp."""
    import jaxfog

    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for view in case["views"]:
        name = Path(view["target"]).name
        imgs, spp, meta = [], 0, {}
        for folder in folders:
            img, meta = jaxfog.read_exr(str(folder / name))
            imgs.append(np.asarray(img, np.float64))
            spp += int(meta["mitsuba:spp"])
        keep = {k: meta[k] for k in ("jaxfog:truth", "jaxfog:scene_file", "renderer") if k in meta}
        jaxfog.write_exr(str(out / name), np.mean(imgs, axis=0).astype(np.float32), {**keep, "mitsuba:spp": spp})
        paths.append(str(out / name))
    return paths


def fit(case: dict, targets: list[str], folder: Path, seed: int | None = None) -> dict:
    """The suite's run of one case (`fitting.suite.run_case`: its fit command, in its own process) on `targets`,
    with the fit's `--seed` (None: its default); one row: exit code, wall, verdict and per parameter error, se,
    error / se."""
    c = copy.deepcopy(case)
    for view, path in zip(c["views"], targets):
        view["target"] = path
    run = run_case(c, folder, seed=seed)
    params = {r["param"]: {"estimate": r["estimate"], "se": r["se"], "error": r["error"], "z": r["error_over_se"]}
              for r in run["rows"] if r.get("error") is not None and r.get("se")}
    return {"case": case["name"], "exit": run["exit"], "wall_s": round(run["wall_s"], 1), "ok": run["ok"],
            "params": params}


def summarise(rows: list[dict]) -> list[dict]:
    """Per case and parameter over its targets: mean error, sd of the errors, mean se, mean and rms of z, coverage."""
    out = []
    for name in dict.fromkeys(r["case"] for r in rows):
        mine = [r for r in rows if r["case"] == name and r.get("seed") is not None]
        for p in dict.fromkeys(p for r in mine for p in r["params"]):
            e = np.array([r["params"][p]["error"] for r in mine if p in r["params"]])
            s = np.array([r["params"][p]["se"] for r in mine if p in r["params"]])
            z = e / s
            out.append({"case": name, "param": p, "n": len(e), "mean_error": float(e.mean()),
                        "sd_error": float(e.std(ddof=1)) if len(e) > 1 else float("nan"),
                        "mean_se": float(s.mean()), "mean_z": float(z.mean()), "rms_z": float(math.sqrt(np.mean(z * z))),
                        "within_1": float(np.mean(np.abs(z) <= 1)), "within_2": float(np.mean(np.abs(z) <= 2))})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.foreign_resampled", description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", required=True, help="comma-separated case names of the foreign manifest")
    ap.add_argument("--seeds", type=int, nargs="+", required=True, help="target seeds (one Mitsuba render each)")
    ap.add_argument("--spp", type=int, default=None, help="Mitsuba spp per target (default: the shipped targets')")
    ap.add_argument("--average", action="store_true", help="also fit the mean of each case's targets")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    manifest = load_manifest()
    cases = {c["name"]: c for c in manifest["cases"]}
    names = args.cases.split(",")
    unknown = [n for n in names if n not in cases]
    if unknown:
        ap.error(f"unknown case(s) {unknown}; the manifest has {sorted(cases)}")
    spp_of = {t["file"]: t["spp"] for t in manifest.get("targets", [])}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    log = out / "fits.jsonl"
    rows = [json.loads(line) for line in log.read_text().splitlines()] if log.exists() else []
    done = {(r["case"], r.get("seed")) for r in rows}
    for name in names:
        case = cases[name]
        spp = args.spp or spp_of.get(case["views"][0]["target"], 2048)
        for seed in args.seeds:
            if (name, seed) in done:
                continue
            targets = render_targets(case, seed, spp, out / name / str(seed))
            row = {**fit(case, targets, out / name / str(seed), seed), "seed": seed, "spp": spp}
            print(json.dumps(row), flush=True)
            rows.append(row)
            with open(log, "a") as f:
                f.write(json.dumps(row) + "\n")
        if args.average and (name, None) not in done:
            folders = [out / name / str(s) for s in args.seeds]
            row = {**fit(case, average_targets(case, folders, out / name / "mean"), out / name / "mean"),
                   "seed": None, "spp": spp * len(folders)}
            print(json.dumps(row), flush=True)
            rows.append(row)
            with open(log, "a") as f:
                f.write(json.dumps(row) + "\n")
    summary = summarise(rows)
    print_table(summary, [("case", "case"), ("parameter", "param"), ("targets", "n"), ("mean error", "mean_error", "+.4f"),
                          ("sd of errors", "sd_error", ".4f"), ("mean se", "mean_se", ".4f"), ("mean z", "mean_z", "+.2f"),
                          ("rms z", "rms_z", ".2f"), ("within 1 se", "within_1", ".0%"), ("within 2 se", "within_2", ".0%")])
    means = [r for r in rows if r.get("seed") is None]
    (out / "summary.json").write_text(json.dumps({"command": sys.argv, "per_parameter": summary, "averaged": means},
                                                 indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
