"""Run the foreign fit suite: every case of `data_synthetic/foreign/manifest.json` through `python -m fitting.fit`.

    python -m fitting.suite [--cases a,b] [--out DIR] [--spp N] [--seed S] [--agreement [--agreement-spp N]]

Each case is one `python -m fitting.fit` process (scene files and Mitsuba targets from the manifest, `--fit`, `--init`
as listed there, everything else the fit's defaults), timed from process start to exit, so its wall time includes
JAX's start-up and compilation. Writes `DIR/suite.md` (a markdown table) and `DIR/suite.json`: per case and fitted
parameter the truth, estimate, standard error, error, error / se, wall time (and the fit process's CPU time, which
shows the cost whatever the machine's load), and the verdict; and the coverage of
the standard errors: the fraction of determined parameters of the cases expected to pass with |error| <= 1 se and
<= 2 se (about 68% and 95% for honest standard errors).

A case expected to pass passes when the fit exits 0 and, for each parameter the views determine, |error| <= z se
and |error| <= 2% (sigma_t, intensity: relative) or 0.02 (g, albedo: absolute), z the suite's family-wise bound
(`se_bound`: 3.12 for the manifest's 28 determined parameters, where 2 per parameter would fail a fit with honest
standard errors somewhere in the suite in most runs). The second is waived where the
targets' own noise leaves a standard error above half the tolerance and the renders' share is smaller
(`target_limited`): no fit of those images can promise the tolerance, and the fit says so by its standard error and
names the combination the views determine. A case expected to fail passes
when the fit exits 1 with success false and a message saying the model does not explain the targets.

`--agreement`: before the fits, renders each target's scene at its truth with jaxfog (`--agreement-spp`, per-pixel
variance from the render) and compares the image mean per channel with the Mitsuba target's (the target's own
noise from `fitting.problem.block_noise`): the relative difference and its z-score, so a fit's miss can be told from
the two renderers disagreeing at the truth.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
MANIFEST = REPO / "data_synthetic" / "foreign" / "manifest.json"
RELATIVE = ("sigma_t", "intensity")
"""Parameters whose tolerance is relative (2%); the others (g, albedo) are absolute (0.02)."""
REL_TOL, ABS_TOL, SE_TOL = 0.02, 0.02, 2.0
EXPLAIN_MESSAGE = "does not explain"
LOOSE_MESSAGE = "not pinned down"
EDGE_MESSAGE = "edge of their range"


def honest_loose(rc: int, success, messages: list) -> bool:
    """Whether a fit ended with the honest "not pinned down" verdict alone (exit 1, the message naming what the views
    determine instead; the model explained the targets and no parameter ran to the edge of its range): for a case
    expected to pass, acceptable where every parameter is still within its error bound and each one beyond the
    tolerance is limited by the targets themselves (`target_limited`), as the fit-solver issue allows ("or an honest
    'not determined' naming the determined combination")."""
    return (rc == 1 and success is False and any(LOOSE_MESSAGE in m for m in messages)
            and not any(EXPLAIN_MESSAGE in m or EDGE_MESSAGE in m for m in messages))


def load_manifest(path: Path = MANIFEST) -> dict:
    with open(path) as f:
        return json.load(f)


def tolerance(name: str, truth: float) -> float:
    """The accuracy a determined parameter must reach: 2% of the truth (sigma_t, intensity) or 0.02 (g, albedo)."""
    base = name.split("[")[0]
    return REL_TOL * abs(truth) if base in RELATIVE else ABS_TOL


def error_bound(n_params: int, alpha: float = 0.05) -> float:
    """The bound in standard errors on each of `n_params` parameters judged at once, so that honest standard errors
    (normal errors) fail the whole set by chance in at most `alpha` of runs: the two-sided normal quantile at
    `alpha / n_params` (Bonferroni; the coverage study's family-wise bands use the same rule). With 2 per parameter
    and 28 independent parameters, 1 - 0.954^28 = 73% of runs would fail one."""
    from statistics import NormalDist

    return NormalDist().inv_cdf(1.0 - alpha / (2 * max(int(n_params), 1)))


def se_bound(manifest: dict | None = None) -> float:
    """`error_bound` over the determined parameters of the manifest's cases expected to pass."""
    cases = (manifest or load_manifest())["cases"]
    return error_bound(sum(len(c["determined"]) for c in cases if c["expect"] == "pass"))


def target_limited(unc: dict, tol: float, information: dict | None) -> bool:
    """Whether the targets themselves do not determine a parameter to `tol`: the standard error the targets' own
    noise leaves (`se_target`, the fit's noise model) exceeds `tol / SE_TOL`, the renders' share is below the
    target's (`se_render <= se_target`: more render passes would not bring the tolerance within reach), and the fit
    names what the views determine (`information.summary`). Such a parameter is judged by its standard error alone
    (`|error| <= 2 se`): the honest "determined only to +-se, and this combination to ..." that the tolerance allows."""
    se_t, se_r = unc.get("se_target"), unc.get("se_render")
    if se_t is None or se_r is None or not (information or {}).get("summary"):
        return False
    return bool(SE_TOL * se_t > tol and se_r <= se_t)


def fit_argv(case: dict, out: str, spp: int | None = None, seed: int | None = None) -> list[str]:
    """The `python -m fitting.fit` arguments of one case (paths relative to the repository root)."""
    argv = []
    for v in case["views"]:
        argv += [v["scene"], v["target"]]
    argv += ["--fit", *case["fit"], "--init", *[f"{k}={v:g}" for k, v in case["init"].items()], "--quiet",
             "--out", out]
    if spp is not None:
        argv += ["--spp", str(spp)]
    if seed is not None:
        argv += ["--seed", str(seed)]
    return argv


def run_case(case: dict, outdir: Path, spp: int | None = None, seed: int | None = None, timeout: float = 1800) -> dict:
    """Run one case's fit as its own process; the verdict and one row per fitted parameter."""
    out = outdir / f"{case['name']}.json"
    log = outdir / f"{case['name']}.log"
    if out.exists():
        out.unlink()
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    cmd = [sys.executable, "-m", "fitting.fit", *fit_argv(case, str(out), spp, seed)]
    t0, c0 = time.perf_counter(), _children_cpu()
    with open(log, "w") as f:
        rc = subprocess.run(cmd, cwd=REPO, env=env, stdout=f, stderr=subprocess.STDOUT, timeout=timeout).returncode
    wall, cpu = time.perf_counter() - t0, _children_cpu() - c0
    res = json.loads(out.read_text()) if out.exists() else {}
    return dict(judge(case, rc, res, wall, log.read_text().splitlines()[-20:]), cpu_s=cpu)


def _children_cpu() -> float:
    """CPU seconds (user + system) of this process's finished children: the fit's CPU time, whatever the load."""
    import resource

    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def judge(case: dict, rc: int, res: dict, wall: float, log_tail=(), bound: float | None = None) -> dict:
    """The verdict of one case from the fit's exit code and RESULT.json; `bound`: the errors' bound in standard
    errors (default: the suite's, `se_bound`)."""
    bound = se_bound() if bound is None else bound
    truth, rows = case["truth"], []
    params, unc = res.get("params", {}), res.get("uncertainty", {})
    for n in case["fit"]:
        est = params.get(n)
        se = (unc.get(n) or {}).get("se")
        t = truth.get(n)
        row = {"param": n, "truth": t, "init": case["init"].get(n), "estimate": est, "se": se,
               "determined": n in case["determined"]}
        if t is not None and est is not None:
            err = est - t
            row["error"] = err
            row["error_rel"] = err / t if n.split("[")[0] in RELATIVE else None
            row["error_over_se"] = err / se if se else None
            row["tolerance"] = tolerance(n, t)
            row["within_2se"] = bool(se is not None and abs(err) <= SE_TOL * se)
            row["within_bound"] = bool(se is not None and abs(err) <= bound * se)
            row["within_tol"] = bool(abs(err) <= row["tolerance"])
            row["target_limited"] = target_limited(unc.get(n) or {}, row["tolerance"], res.get("information"))
        rows.append(row)
    messages = res.get("messages", [])
    success = res.get("success")
    if case["expect"] == "pass":
        problems = []
        if rc != 0 and not honest_loose(rc, success, messages):
            problems.append(f"fit exited {rc}" + (f": {'; '.join(_short(m) for m in messages)}" if messages else ""))
        for r in rows:
            if r["determined"]:
                if "error" not in r:
                    problems.append(f"{r['param']}: no estimate")
                    continue
                if not r["within_bound"]:
                    problems.append(f"{r['param']}: error {r['error']:+.4g} beyond {bound:.2f} se ({r['se']})")
                if not r["within_tol"] and not r["target_limited"]:
                    problems.append(f"{r['param']}: error {r['error']:+.4g} beyond {r['tolerance']:.4g}")
        ok = not problems
    else:
        refused = rc == 1 and success is False and any(EXPLAIN_MESSAGE in m for m in messages)
        problems = [] if refused else [f"not refused: exit {rc}, success {success}, messages {messages}"]
        ok = refused
    return {"case": case["name"], "description": case["description"], "views": len(case["views"]),
            "expect": case["expect"], "exit": rc, "success": success, "ok": ok, "problems": problems,
            "messages": messages, "chi2": res.get("chi2"), "rounds": res.get("rounds"),
            "fit_wall_s": res.get("wall_s"), "wall_s": wall, "rows": rows, "log_tail": list(log_tail)}


def _short(message: str, n: int = 160) -> str:
    """A fit message on one line, at most `n` characters (a solver's message can run to a page)."""
    one = " ".join(message.split())
    return one if len(one) <= n else one[: n - 3] + "..."


def coverage(results: list[dict]) -> dict:
    """Fraction of determined parameters (cases expected to pass) with |error| <= 1 se and <= 2 se."""
    z = [abs(r["error_over_se"]) for c in results if c["expect"] == "pass" for r in c["rows"]
         if r["determined"] and r.get("error_over_se") is not None]
    n = len(z)
    return {"n": n, "within_1se": float(np.mean([x <= 1 for x in z])) if n else None,
            "within_2se": float(np.mean([x <= 2 for x in z])) if n else None,
            "rms_error_over_se": float(np.sqrt(np.mean(np.square(z)))) if n else None}


def agreement(manifest: dict, cases: list[dict], spp: int = 256, seed: int = 7) -> list[dict]:
    """jaxfog against Mitsuba at the truth, per target: image mean per channel, difference and its z-score."""
    import jax

    import jaxfog
    from jaxfog.tools import scene_from_dict

    from .problem import block_noise

    truth_scene = _make_foreign().truth_scene

    out = []
    for case in cases:
        for v in case["views"]:
            target, _ = jaxfog.read_exr(REPO / v["target"])
            sf = scene_from_dict(truth_scene(v["rendered_scene"], case["truth"]), v["rendered_scene"])
            t0 = time.perf_counter()
            img, var = jax.device_get(jaxfog.render(sf.scene, jax.random.key(seed), spp, variance=True))
            wall = time.perf_counter() - t0
            n = img.shape[0] * img.shape[1]
            mj, mm = img.mean(axis=(0, 1)), target.mean(axis=(0, 1))
            se_j = np.sqrt(np.asarray(var, np.float64).sum(axis=(0, 1))) / n
            se_m = np.sqrt(block_noise(target, 1).sum(axis=(0, 1))) / n
            se = np.sqrt(se_j ** 2 + se_m ** 2)
            out.append({"case": case["name"], "target": v["target"], "jaxfog_mean": mj.tolist(),
                        "mitsuba_mean": mm.tolist(), "rel_diff": (mj / mm - 1).tolist(),
                        "rel_se": (se / mm).tolist(), "z": ((mj - mm) / se).tolist(), "jaxfog_spp": spp,
                        "jaxfog_wall_s": wall})
            print(f"agreement {v['target']}: jaxfog/mitsuba - 1 = "
                  + " ".join(f"{d:+.2%}" for d in out[-1]["rel_diff"])
                  + f" (se {np.max(out[-1]['rel_se']):.2%}), z " + " ".join(f"{x:+.1f}" for x in out[-1]["z"]),
                  flush=True)
    return out


def _make_foreign():
    """`data_synthetic/foreign/make_foreign.py` as a module (it is a script, not part of a package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("make_foreign", REPO / "data_synthetic" / "foreign" / "make_foreign.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def fmt(x, spec=".4f"):
    return "" if x is None else format(x, spec)


def table(results: list[dict]) -> str:
    lines = ["| case | views | parameter | truth | estimate | se | error | error / se | wall s | CPU s | verdict |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for c in results:
        for i, r in enumerate(c["rows"]):
            err = r.get("error")
            if err is not None and r.get("error_rel") is not None:
                es = f"{err:+.4f} ({100 * r['error_rel']:+.1f}%)"
            else:
                es = fmt(err, "+.4f")
            name = r["param"] + ("" if r["determined"] or c["expect"] == "fail" else " (not determined)")
            if r["determined"] and c["expect"] == "pass" and r.get("target_limited") and not r.get("within_tol"):
                name += " (targets: se above tolerance / 2)"
            verdict = ("ok" if c["ok"] else "**FAILED**") if i == 0 else ""
            if i == 0 and c["expect"] == "fail":
                verdict = "refused, as expected" if c["ok"] else "**NOT REFUSED**"
            lines.append(f"| {c['case'] if i == 0 else ''} | {c['views'] if i == 0 else ''} | {name} | "
                         f"{fmt(r['truth'], '.4g')} | {fmt(r['estimate'])} | {fmt(r['se'])} | {es} | "
                         f"{fmt(r.get('error_over_se'), '+.2f')} | {fmt(c['wall_s'], '.0f') if i == 0 else ''} | "
                         f"{fmt(c.get('cpu_s'), '.0f') if i == 0 else ''} | "
                         f"{verdict} |")
    return "\n".join(lines)


def agreement_table(rows: list[dict]) -> str:
    lines = ["| case | target | jaxfog / Mitsuba - 1 (R, G, B) | se | z (R, G, B) |", "| --- | --- | --- | --- | --- |"]
    for a in rows:
        lines.append(f"| {a['case']} | {os.path.basename(a['target'])} | "
                     + ", ".join(f"{d:+.2%}" for d in a["rel_diff"]) + f" | {max(a['rel_se']):.2%} | "
                     + ", ".join(f"{x:+.1f}" for x in a["z"]) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m fitting.suite", description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default=None, help="comma-separated case names (default: all)")
    ap.add_argument("--out", default="suite_out", help="output directory (default suite_out)")
    ap.add_argument("--spp", type=int, default=None, help="the fit's --spp (default: the fit's own)")
    ap.add_argument("--seed", type=int, default=None, help="the fit's --seed (default: the fit's own)")
    ap.add_argument("--agreement", action="store_true", help="also compare jaxfog and Mitsuba at the truth")
    ap.add_argument("--agreement-spp", type=int, default=256)
    ap.add_argument("--report", nargs="+", default=None, metavar="SUITE.json",
                    help="run nothing: merge these suite.json files (results and agreement) into --out")
    args = ap.parse_args(argv)
    if args.report:
        return report(args.report, Path(args.out))
    manifest = load_manifest()
    cases = manifest["cases"]
    if args.cases:
        want = args.cases.split(",")
        unknown = sorted(set(want) - {c["name"] for c in cases})
        if unknown:
            print(f"unknown case(s) {unknown}; known: {', '.join(c['name'] for c in cases)}", file=sys.stderr)
            return 2
        cases = [c for c in cases if c["name"] in want]
    outdir = Path(args.out)
    outdir.mkdir(parents=True, exist_ok=True)
    payload = {"manifest": str(MANIFEST.relative_to(REPO)), "spp": args.spp, "seed": args.seed,
               "command": "python -m fitting.suite " + " ".join(argv if argv is not None else sys.argv[1:])}
    if args.agreement:
        from jaxfog.tools import use_cpu_cores

        use_cpu_cores()
        payload["agreement"] = agreement(manifest, cases, args.agreement_spp)
    results = []
    for case in cases:
        r = run_case(case, outdir, args.spp, args.seed)
        results.append(r)
        print(f"{case['name']}: {'ok' if r['ok'] else 'FAILED'} in {r['wall_s']:.0f} s"
              + ("" if r["ok"] else f" ({'; '.join(r['problems'])})"), flush=True)
        payload.update({"results": results, "coverage": coverage(results)})
        write(outdir, payload)
    cov = coverage(results)
    print(table(results))
    if cov["n"]:
        print(f"coverage over {cov['n']} determined parameters: {cov['within_1se']:.0%} within 1 se, "
              f"{cov['within_2se']:.0%} within 2 se, rms error/se {cov['rms_error_over_se']:.2f}")
    return 0 if all(r["ok"] for r in results) else 1


def report(paths, outdir: Path) -> int:
    """Merge earlier runs' suite.json (e.g. cases run in separate invocations) into one table and coverage."""
    payload = {"merged_from": [str(p) for p in paths], "results": [], "agreement": []}
    for p in paths:
        d = json.loads(Path(p).read_text())
        payload["results"] += [r for r in d.get("results", []) if r["exit"] >= 0]  # < 0: killed by a signal
        payload["agreement"] += d.get("agreement", []) or []
        payload.setdefault("commands", []).append(d.get("command"))
    payload["coverage"] = coverage(payload["results"])
    outdir.mkdir(parents=True, exist_ok=True)
    write(outdir, payload)
    print((outdir / "suite.md").read_text())
    return 0 if all(r["ok"] for r in payload["results"]) else 1


def write(outdir: Path, payload: dict) -> None:
    from .fit import write_json_atomic

    write_json_atomic(str(outdir / "suite.json"), payload)
    md = [table(payload["results"]), ""]
    cov = payload["coverage"]
    if cov["n"]:
        md.append(f"Coverage over {cov['n']} determined parameters: {cov['within_1se']:.0%} within 1 se, "
                  f"{cov['within_2se']:.0%} within 2 se (rms error / se {cov['rms_error_over_se']:.2f}).")
    if payload.get("agreement"):
        md += ["", agreement_table(payload["agreement"])]
    (outdir / "suite.md").write_text("\n".join(md) + "\n")


if __name__ == "__main__":
    sys.exit(main())
