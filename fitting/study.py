"""The coverage study: do the fit's standard errors cover the truth as often as they say?

    python -m fitting.study --out DIR [--families a,b] [--seeds N] [--max-seeds K] [--foreign-seeds M] [--summary]

Each family is a scene (one or two views) and the parameters to fit. For every seed the study draws a truth from the
family's range and a start anywhere in the fit's search box (`fitting.search.search_box`: a start is only a hint),
renders fresh targets at the truth with the "detached" estimator (`TARGET_SPP` spp, `TARGET_SIDE` px a side, seeds
that no fit uses), and fits them in this process. The `foreign` family fits the Mitsuba 3 targets of
`data_synthetic/foreign/manifest.json` (cases expected to pass) with `--foreign-seeds` fit seeds and random starts;
the `photo` family fits synthetic photographs (`photo_fit`: JPEGs at an unknown exposure) with the exposure.
With `--max-seeds K`, a family with fewer than `--seeds` accepted fits draws further seeds, up to K in all: the
coverage is a claim about accepted fits (a fit that says "not pinned down" claims no standard error), and a family
whose fits are often not pinned down (the mesh: two of three at its budget) would otherwise be judged on a handful
of them. Whether a fit is accepted never depends on the truth, so the further seeds select nothing about errors.
One JSON line per fit goes to `DIR/fits.jsonl` as it finishes (an interrupted study keeps its fits and resumes);
`--summary` (also run at the end) writes `DIR/coverage.md` and `DIR/coverage.json`: per family the fraction of
parameters within 1 and 2 reported standard errors of the truth, with the binomial two-standard-error band of a
coverage over that many parameters, the mean of error / se, and the walls.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
SCENES = REPO / "data_synthetic" / "scenes"
FOREIGN = REPO / "data_synthetic" / "foreign"
TARGET_SPP = 256
TARGET_SIDE = 64
FAMILIES = {
    # name: (views, fitted parameters with their truth ranges (log-uniform for positive quantities), fixed values)
    "spot_two_views": (("spot_fog", "spot_fog_low"), {"sigma_t": (0.2, 1.5), "g": (-0.3, 0.9)}, {}),
    "spot_one_view": (("spot_fog",), {"sigma_t": (0.2, 1.5), "g": (-0.3, 0.9)}, {}),
    "point_room": (("../foreign/scenes/room_point",), {"sigma_t": (0.2, 1.0), "g": (0.0, 0.8)}, {}),
    "area_light": (("../foreign/scenes/area_floor",), {"sigma_t": (0.2, 0.8), "g": (0.0, 0.6)}, {}),
    "glass_mirror": (("mirror_glass",), {"sigma_t": (0.3, 0.8), "g": (0.3, 0.8)}, {}),
    "mesh": (("mesh_fog",), {"sigma_t": (0.3, 0.9), "g": (0.2, 0.8)}, {}),
    "height_fog": (("height_fog_ground", "height_fog_above"),
                   {"sigma_0": (0.3, 0.9), "height_scale": (0.5, 1.2), "g": (0.3, 0.7)}, {}),
    "height_point": (("height_fog_point", "height_fog_point_above"),
                     {"sigma_0": (0.3, 0.9), "height_scale": (0.5, 1.2), "g": (0.3, 0.7)}, {}),
    "chromatic": (("chromatic_fit_side", "chromatic_fit_low"),
                  {"sigma_t[r]": (0.2, 0.5), "sigma_t[g]": (0.35, 0.7), "sigma_t[b]": (0.5, 1.0), "g": (0.3, 0.7)},
                  {}),
    "droplet": (("droplet_fit_halo", "droplet_fit_side"), {"diameter": (6.0, 16.0), "sigma_t": (0.2, 0.5)}, {}),
    "light_power": (("../foreign/scenes/spot_sideways", "../foreign/scenes/spot_sideways_near"),
                    {"sigma_t": (0.25, 0.8), "g": (0.2, 0.7), "intensity": (30.0, 90.0)}, {}),
    "albedo": (("../foreign/scenes/room_point",), {"sigma_t": (0.3, 0.8), "albedo": (0.5, 0.95), "g": (0.2, 0.7)},
               {}),
}


def draw_truth(params: dict, rng) -> dict:
    from .params import SPECS

    out = {}
    for n, (lo, hi) in params.items():
        positive = SPECS[n].lo == 0.0 and not math.isfinite(SPECS[n].hi)
        out[n] = float(math.exp(rng.uniform(math.log(lo), math.log(hi))) if positive else rng.uniform(lo, hi))
    return out


def draw_start(names, scene_values: dict, L: float, rng) -> dict:
    """A start anywhere in the search box of the scene file's values (uniform in the unconstrained coordinates)."""
    from .params import SPECS
    from .search import search_box

    lo, hi = search_box(names, scene_values, L)
    u = rng.uniform(lo, hi)
    return {n: float(SPECS[n].from_u(np.float32(u[i]))) for i, n in enumerate(names)}


def _small(scene, side: int):
    import equinox as eqx

    cam = scene.camera
    if cam.width <= side and cam.height <= side:
        return scene
    cam = cam.resized(side, side * cam.height // cam.width)
    return eqx.tree_at(lambda s: s.camera, scene, cam)


def family_fit(name: str, seed: int) -> dict:
    """One fit of family `name` with study seed `seed`: fresh targets at a drawn truth, a drawn start."""
    import jax

    import jaxfog

    from .fit import auto_downscale
    from .params import apply, check_names, scene_values
    from .problem import make_view
    from .solver import FitConfig

    view_names, ranges, fixed = FAMILIES[name]
    rng = np.random.default_rng([seed, sum(map(ord, name))])
    truth = draw_truth(ranges, rng)
    names = check_names(list(ranges))
    views = []
    for i, vn in enumerate(view_names):
        scene = _small(jaxfog.load_scene(str(SCENES / f"{vn}.json")).scene, TARGET_SIDE)
        key = jax.random.key(900_000 + 1000 * seed + 17 * i + sum(map(ord, name)))
        target = np.asarray(jaxfog.render(apply(scene, {**fixed, **truth}), key, TARGET_SPP, estimator="detached"))
        f = auto_downscale(scene.camera.width, scene.camera.height)
        views.append(make_view(scene, target, f"{name}/{Path(vn).name}", f, TARGET_SPP))
    from .search import scene_size
    from .problem import Problem

    start = draw_start(names, scene_values(views[0].scene), scene_size(Problem(views, names)), rng)
    return _run(name, seed, views, names, start, truth, FitConfig(seed=seed))


PHOTO = (("spot_fog", "spot_fog_low"), {"sigma_t": (0.2, 1.2), "g": (0.2, 0.8)})
"""The `photo` family: two views of one camera at a drawn exposure (shared), fitted with `exposure` as well."""
PHOTO_DOWNSCALE = 4
"""Fit resolution of the photographs: 16 x 16 px of the 64 px targets (at 8 x 8 a three-parameter fit of sigma_t,
g and the exposure is nearly degenerate: the worked example's fit at 8 x 8 stopped 15% off with a residual 4.9x
the noise; at 32 x 32 it found each parameter within 3 se)."""


def photo_fit(seed: int) -> dict:
    """One fit of a synthetic photograph pair: targets rendered at a drawn truth, pushed through the camera model
    (`fitting.photo.camera_encode`: an exposure drawn so that 0.5-2x of the brighter view's 99th percentile reaches
    the encoding's top, Poisson-Gaussian noise, clipping), written as 8-bit sRGB JPEGs at a quality drawn from 85
    to 95, decoded as a user's photographs are (`read_photo`: masks of clipped and crushed pixels, quantisation
    floor), and fitted with `exposure` from a drawn start."""
    import tempfile

    import jax

    import jaxfog

    from .params import apply, check_names, scene_values
    from .photo import camera_encode, read_photo, write_photo
    from .problem import Problem, make_view
    from .search import scene_size
    from .solver import FitConfig

    view_names, ranges = PHOTO
    rng = np.random.default_rng([seed, sum(map(ord, "photo"))])
    truth = draw_truth(ranges, rng)
    names = check_names([*ranges, "exposure"])
    renders, scenes = [], []
    for i, vn in enumerate(view_names):
        scene = _small(jaxfog.load_scene(str(SCENES / f"{vn}.json")).scene, TARGET_SIDE)
        key = jax.random.key(700_000 + 1000 * seed + 17 * i)
        renders.append(np.asarray(jaxfog.render(apply(scene, truth), key, TARGET_SPP, estimator="detached")))
        scenes.append(scene)
    exposure = float(math.exp(rng.uniform(math.log(0.5), math.log(2.0)))
                     / max(float(np.percentile(r, 99)) for r in renders))
    truth["exposure"] = exposure
    quality = int(rng.integers(85, 96))
    views = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, (vn, img, scene) in enumerate(zip(view_names, renders, scenes)):
            path = os.path.join(tmp, f"{i}.jpg")
            write_photo(path, camera_encode(img, exposure, rng, 20000.0, 0.002), bits=8, quality=quality)
            ph = read_photo(path)
            views.append(make_view(scene, ph.image, f"photo/{vn}", PHOTO_DOWNSCALE, None, ph.valid, ph.noise_var))
    start = draw_start(names, scene_values(views[0].scene), scene_size(Problem(views, names)), rng)
    return _run("photo", seed, views, names, start, truth, FitConfig(seed=seed))


def foreign_fit(case: dict, seed: int) -> dict:
    """One fit of a foreign (Mitsuba) case with fit seed `seed` and a drawn start."""
    import jaxfog

    from .fit import auto_downscale
    from .params import check_names, scene_values
    from .problem import Problem, make_view
    from .search import scene_size
    from .solver import FitConfig

    views = []
    for v in case["views"]:
        scene = jaxfog.load_scene(str(REPO / v["scene"])).scene
        target, _ = jaxfog.read_exr(str(REPO / v["target"]))
        views.append(make_view(scene, target, f"foreign/{Path(v['target']).name}",
                               auto_downscale(scene.camera.width, scene.camera.height)))
    names = check_names(case["fit"])
    rng = np.random.default_rng([seed, sum(map(ord, case["name"]))])
    start = draw_start(names, scene_values(views[0].scene), scene_size(Problem(views, names)), rng)
    truth = {n: case["truth"][n] for n in names if n in case["truth"]}
    return _run("foreign", seed, views, names, start, truth, FitConfig(seed=seed), case=case["name"])


def _run(family, seed, views, names, start, truth, cfg, case=None) -> dict:
    from .solver import fit_views

    t0 = time.perf_counter()
    try:
        r = fit_views(views, names, start, cfg, log=lambda *a: None)
    except Exception as e:  # noqa: BLE001 - a refused or crashed fit is a result of the study
        return {"family": family, "case": case, "seed": seed, "truth": truth, "start": start, "error": repr(e),
                "wall_s": time.perf_counter() - t0}
    rows = {n: {"truth": truth[n], "estimate": r.params[n], **r.uncertainty[n]} for n in names if n in truth}
    return {"family": family, "case": case, "seed": seed, "start": start, "params": rows, "success": r.success,
            "messages": r.messages, "chi2": r.chi2, "rounds": r.rounds, "wall_s": time.perf_counter() - t0,
            "last_round": {k: v for k, v in (r.history[-1] if r.history else {}).items()
                           if k in ("phase", "batches", "step_se", "worst_se", "quality")}}


def summarise(lines: list[dict]) -> dict:
    """Coverage per family and overall, over the parameters of the accepted fits (those the fit reports as an
    estimate with a standard error; a refused fit or a parameter not pinned down makes no such claim), for the
    reported se and for the noise model's (target and renders); the share of fits accepted."""
    fams: dict[str, list] = {}
    accepted: dict[str, list] = {}
    for d in lines:
        accepted.setdefault(d["family"], []).append(bool(d.get("success")))
        if not d.get("success"):
            continue
        for n, p in (d.get("params") or {}).items():
            z = (p["estimate"] - p["truth"]) / p["se"] if p["se"] and p["se"] > 0 else float("inf")
            se_m = math.hypot(p["se_target"], p["se_render"])
            zm = (p["estimate"] - p["truth"]) / se_m if se_m > 0 else float("inf")
            se_r = p.get("se_robust") or 0.0
            zr = (p["estimate"] - p["truth"]) / se_r if se_r > 0 else float("inf")
            fams.setdefault(d["family"], []).append((z, zm, d["wall_s"], bool(d.get("success")), zr))
    out = {}
    for fam, rows in sorted(fams.items()) + [("all", [r for v in fams.values() for r in v])]:
        if not rows:
            continue
        z = np.asarray([r[0] for r in rows])
        zm = np.asarray([r[1] for r in rows])
        zr = np.asarray([r[4] for r in rows])
        m = len(z)
        out[fam] = {
            "parameters": m,
            "within_1se": float(np.mean(np.abs(z) <= 1)), "within_2se": float(np.mean(np.abs(z) <= 2)),
            "band_1se": 2 * math.sqrt(0.6827 * 0.3173 / m), "band_2se": 2 * math.sqrt(0.9545 * 0.0455 / m),
            "mean_z": float(np.mean(z[np.isfinite(z)])) if np.any(np.isfinite(z)) else float("nan"),
            "model_within_1se": float(np.mean(np.abs(zm) <= 1)), "model_within_2se": float(np.mean(np.abs(zm) <= 2)),
            "robust_within_1se": float(np.mean(np.abs(zr) <= 1)), "robust_within_2se": float(np.mean(np.abs(zr) <= 2)),
            "success": float(np.mean(accepted[fam] if fam != "all" else [a for v in accepted.values() for a in v])),
            "wall_median_s": float(np.median([r[2] for r in rows])), "wall_max_s": float(np.max([r[2] for r in rows])),
        }
    errors = [d for d in lines if "error" in d]
    return {"families": out, "fits": len(lines), "errors": [f"{d['family']} seed {d['seed']}: {d['error']}"
                                                           for d in errors]}


def write_summary(outdir: Path) -> dict:
    lines = [json.loads(x) for x in (outdir / "fits.jsonl").read_text().splitlines() if x.strip()]
    s = summarise(lines)
    rows = ["| family | parameters | within 1 se (68.3% ± band) | within 2 se (95.4% ± band) | mean error / se | "
            "noise model only: within 1 / 2 se | residuals only: within 1 / 2 se | fits accepted | "
            "wall median / max (s) |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for fam, c in s["families"].items():
        rows.append(f"| {fam} | {c['parameters']} | {100 * c['within_1se']:.0f}% (± {100 * c['band_1se']:.0f}) | "
                    f"{100 * c['within_2se']:.0f}% (± {100 * c['band_2se']:.0f}) | {c['mean_z']:+.2f} | "
                    f"{100 * c['model_within_1se']:.0f}% / {100 * c['model_within_2se']:.0f}% | "
                    f"{100 * c['robust_within_1se']:.0f}% / {100 * c['robust_within_2se']:.0f}% | "
                    f"{100 * c['success']:.0f}% | {c['wall_median_s']:.1f} / {c['wall_max_s']:.1f} |")
    text = (f"# Coverage study\n\n{s['fits']} fits (`python -m fitting.study`); a row per family, the parameters "
            f"of its accepted fits pooled (a refused fit, or one with a parameter not pinned down, reports no "
            f"estimate to trust); the share of fits accepted in its own column. Within 1 / 2 se: of the reported "
            f"standard error (recorded as `se` by the code that ran); the next two columns: the noise model's alone "
            f"and the residuals' (robust, leverage-corrected) alone.\n\n" + "\n".join(rows) + "\n")
    if s["errors"]:
        text += "\nRefused or crashed fits:\n\n" + "\n".join(f"- {e}" for e in s["errors"]) + "\n"
    (outdir / "coverage.md").write_text(text)
    (outdir / "coverage.json").write_text(json.dumps(s, indent=1))
    print(text)
    return s


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m fitting.study", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="output folder (fits.jsonl, coverage.md, coverage.json)")
    ap.add_argument("--families", default=",".join([*FAMILIES, "photo", "foreign"]),
                    help="comma-separated families (default: all, photo and foreign)")
    ap.add_argument("--seeds", type=int, default=9, help="fits per family (default 9)")
    ap.add_argument("--max-seeds", type=int, default=None,
                    help="a family with fewer than --seeds accepted fits draws further seeds, up to this many in all "
                         "(default: --seeds, no more)")
    ap.add_argument("--foreign-seeds", type=int, default=3, help="fit seeds per foreign case (default 3)")
    ap.add_argument("--first-seed", type=int, default=0,
                    help="the first study seed (default 0): another value draws other truths, starts and targets, "
                         "for a run independent of one a method was chosen on")
    ap.add_argument("--summary", action="store_true", help="only summarise DIR/fits.jsonl")
    return ap


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    outdir = Path(args.out)
    outdir.mkdir(parents=True, exist_ok=True)
    if args.summary:
        write_summary(outdir)
        return 0
    from jaxfog.tools import use_compilation_cache
    from jaxfog.tools import use_cpu_cores

    use_cpu_cores()
    use_compilation_cache()
    if (args.seeds < 1 or args.foreign_seeds < 0 or args.first_seed < 0
            or (args.max_seeds is not None and args.max_seeds < args.seeds)):
        print(f"error: --seeds must be >= 1 (got {args.seeds}), --foreign-seeds >= 0 (got {args.foreign_seeds}), "
              f"--first-seed >= 0 (got {args.first_seed}) and --max-seeds >= --seeds (got {args.max_seeds})",
              file=sys.stderr)
        return 2
    fams = [f for f in args.families.split(",") if f]
    unknown = [f for f in fams if f not in FAMILIES and f not in ("foreign", "photo")]
    if unknown:
        print(f"error: unknown families {unknown}; valid: {', '.join([*FAMILIES, 'photo', 'foreign'])}",
              file=sys.stderr)
        return 2
    path = outdir / "fits.jsonl"
    done = set()
    if path.exists():
        for x in path.read_text().splitlines():
            if x.strip():
                d = json.loads(x)
                done.add((d["family"], d.get("case"), d["seed"]))
    s0 = args.first_seed
    jobs = [(f, None, s) for s in range(s0, s0 + args.seeds) for f in fams if f != "foreign"]
    if "foreign" in fams:
        cases = [c for c in json.loads((FOREIGN / "manifest.json").read_text())["cases"] if c["expect"] == "pass"]
        jobs += [("foreign", c["name"], s) for s in range(s0, s0 + args.foreign_seeds) for c in cases]
        by_name = {c["name"]: c for c in cases}
    for fam, case, seed in jobs:
        if (fam, case, seed) not in done:
            _one(path, fam, case, seed, by_name if fam == "foreign" else None)
    for fam in [f for f in fams if f != "foreign"]:
        for seed in range(s0 + args.seeds, s0 + max(args.max_seeds or 0, args.seeds)):
            if _accepted(path, fam) >= args.seeds:
                break
            if (fam, None, seed) not in done:
                _one(path, fam, None, seed)
    write_summary(outdir)
    return 0


def _accepted(path: Path, family: str) -> int:
    """Accepted fits of `family` in the study's `fits.jsonl` so far."""
    lines = [json.loads(x) for x in path.read_text().splitlines() if x.strip()] if path.exists() else []
    return sum(1 for d in lines if d["family"] == family and d.get("success"))


def _z(p: dict) -> float:
    """A parameter's error over its standard error; +-inf where the standard error is 0 (a parameter at the edge
    of its range, whose map to the unconstrained coordinate is flat there)."""
    err = p["estimate"] - p["truth"]
    return err / p["se"] if p["se"] else math.copysign(math.inf, err)


def _one(path: Path, fam: str, case: str | None, seed: int, by_name: dict | None = None) -> None:
    """Run one fit of the study and append its line to `path`."""
    d = (foreign_fit(by_name[case], seed) if fam == "foreign" else photo_fit(seed) if fam == "photo"
         else family_fit(fam, seed))
    with open(path, "a") as f:
        f.write(json.dumps(d) + "\n")
    ok = "error" not in d
    print(f"{fam} {case or ''} seed {seed}: " + (" ".join(
        f"{n} {p['estimate']:.4g} (true {p['truth']:.4g}, {_z(p):+.1f} se)"
        for n, p in d["params"].items()) + f" {'ok' if d['success'] else 'FAILED'} {d['wall_s']:.1f} s"
        if ok else d["error"]), flush=True)


if __name__ == "__main__":
    sys.exit(main())
