"""Recover medium parameters from target images.

    python -m fitting.fit SCENE.json TARGET.exr [MORE_TARGETS.exr | SCENE2.json TARGET2.exr ...] \
        --fit sigma_t g [albedo intensity] [--init sigma_t=0.3 g=0.0] [--spp N] [--seed S] [--solver lm|bfgs] \
        [--downscale F] --out RESULT.json

Each target is fitted with the scene file named most recently before it; all targets are one medium, fitted jointly.
Writes RESULT.json, RESULT.png (target | fit | difference per view) and RESULT_convergence.png; prints a table of
the estimate with its uncertainty and, when the targets' headers record the truth, the true values. Exits 1 when the
fit fails (solver not converged, estimate still moving, or the model does not explain the targets), 2 on bad input.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

from .core import FitConfig, make_view, fit_views
from .params import SPECS, FitError, check_names, check_value, scene_values


def parse_assignments(items, what="--init") -> dict:
    out = {}
    for item in items or []:
        if "=" not in item:
            raise FitError(f"{what} expects name=value, got {item!r}")
        k, v = item.split("=", 1)
        if k not in SPECS:
            raise FitError(f"{what}: unknown parameter {k!r}; valid: {', '.join(SPECS)}")
        try:
            out[k] = check_value(k, float(v))
        except ValueError as e:
            raise FitError(f"{what} {item!r}: {e}") from None
    return out


def pair_inputs(inputs) -> list[tuple[str, str]]:
    """[scene.json, a.exr, b.exr, scene2.json, c.exr] -> [(scene.json, a.exr), (scene.json, b.exr), (scene2.json, c.exr)]."""
    pairs, scene = [], None
    for p in inputs:
        if p.lower().endswith(".json"):
            scene = p
        else:
            if scene is None:
                raise FitError(f"target {p!r} comes before any SCENE.json")
            pairs.append((scene, p))
    if not pairs:
        raise FitError("give at least one SCENE.json followed by a TARGET.exr")
    return pairs


def true_values(meta: dict) -> dict:
    """Ground truth recorded in a target's header by `fitting.make_targets` (empty if none)."""
    raw = meta.get("jaxfog:truth")
    try:
        return json.loads(raw) if raw else {}
    except (TypeError, ValueError):
        return {}


def auto_downscale(width: int, height: int, min_size: int = 8) -> int:
    """The largest factor that divides both sides and leaves at least `min_size` px a side (1 if none)."""
    best = 1
    for f in range(1, min(width, height) // min_size + 1):
        if width % f == 0 and height % f == 0:
            best = f
    return best


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m fitting.fit", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("inputs", nargs="+", help="SCENE.json TARGET.exr [MORE_TARGETS.exr | SCENE2.json TARGET2.exr ...]")
    p.add_argument("--fit", nargs="+", default=["sigma_t", "g"], help=f"parameters to fit: {', '.join(SPECS)}")
    p.add_argument("--init", nargs="*", default=[], help="starting values, e.g. sigma_t=0.3 g=0.0 (default: the scene file's)")
    p.add_argument("--spp", type=int, default=256, help="samples per pixel of each render inside the solver (default 256)")
    p.add_argument("--seed", type=int, default=0, help="seed of the fit's keys (targets use other seeds)")
    p.add_argument("--solver", choices=["lm", "bfgs"], default="lm", help="Levenberg–Marquardt (default) or BFGS")
    p.add_argument("--downscale", type=int, default=None,
                   help="fit at 1/F of the target resolution (box-pooled target; default: the largest F that divides "
                        "the image size and leaves at least 8 px a side: few pixels with many samples each keep "
                        "the Jacobian's noise low, docs/results/fit_sweep)")
    p.add_argument("--rounds", type=int, default=20, help="re-centring rounds at most, each with a fresh key (default 20)")
    p.add_argument("--repeats", type=int, default=7, help="the estimate is the mean of the last REPEATS+1 rounds (default 7)")
    p.add_argument("--value-spp-factor", type=int, default=None, metavar="K",
                   help="each round's residual value is rendered at K x --spp (default: FitConfig's)")
    p.add_argument("--steps", choices=["averaged", "lm"], default="averaged",
                   help="rounds after the burn-in: one Gauss-Newton step with Jacobians averaged over rounds "
                        "(default), or an LM solve with step gain as in the burn-in")
    p.add_argument("--residuals", choices=["decorrelated", "plain"], default="decorrelated",
                   help="LM residuals: value at the reference from an independent key (default), or plain fixed-key "
                        "residuals (biased toward parameters with less render noise; for comparison)")
    p.add_argument("--out", required=True, help="RESULT.json (PNG figures are written beside it)")
    p.add_argument("--quiet", action="store_true", help="no per-iteration progress")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from jaxfog._devices import use_cpu_cores

    use_cpu_cores()  # every core as a JAX device (a no-op once JAX has started, e.g. under pytest)
    try:
        return _run(args)
    except FitError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


def _run(args) -> int:
    import jaxfog

    names = check_names(args.fit)
    init_given = parse_assignments(args.init)
    if args.spp < 1:
        raise FitError(f"--spp must be >= 1, got {args.spp}")
    if args.value_spp_factor is not None and args.value_spp_factor < 1:
        raise FitError(f"--value-spp-factor must be >= 1, got {args.value_spp_factor}")
    if args.rounds < 1 or args.repeats < 1:
        raise FitError(f"--rounds and --repeats must be >= 1, got {args.rounds} and {args.repeats}")
    if not args.out.lower().endswith(".json"):
        raise FitError(f"--out must name a .json file, got {args.out!r}")
    views, truths, scenes_full, targets_full = [], [], [], []
    for scene_path, target_path in pair_inputs(args.inputs):
        if not os.path.exists(target_path):
            raise FitError(f"target {target_path!r} not found")
        try:
            sf = jaxfog.load_scene(scene_path)
        except (jaxfog.SceneError, OSError) as e:
            raise FitError(str(e)) from None
        try:
            target, meta = jaxfog.read_exr(target_path)
        except Exception as e:  # noqa: BLE001 - OIIO raises plain exceptions; report them as input errors
            raise FitError(f"cannot read target {target_path!r}: {e}") from None
        spp_t = int(meta["jaxfog:spp"]) if "jaxfog:spp" in meta else None
        if args.downscale is None:
            args.downscale = auto_downscale(sf.scene.camera.width, sf.scene.camera.height)
        name = os.path.basename(target_path)
        views.append(make_view(sf.scene, target, name, args.downscale, spp_t))
        scenes_full.append(sf.scene)
        targets_full.append(target)
        truths.append(true_values(meta))
    start = scene_values(views[0].scene)
    init = {n: init_given.get(n, start.get(n)) for n in names}
    for n in names:
        if init[n] is None:
            raise FitError(f"cannot fit {n}: the scene has no such value")
    extra = {} if args.value_spp_factor is None else {"value_spp_factor": args.value_spp_factor}
    if args.steps == "lm":
        extra["average_jacobians"] = 0
    cfg = FitConfig(spp=args.spp, seed=args.seed, solver=args.solver, max_rounds=args.rounds, repeats=args.repeats,
                    decorrelate=args.residuals == "decorrelated", **extra)
    print(f"fitting {', '.join(names)} to {len(views)} target(s) at "
          f"{views[0].scene.camera.width}x{views[0].scene.camera.height} px, {args.spp} spp, solver {args.solver}")
    log = (lambda *_: None) if args.quiet else print
    result = fit_views(views, names, init, cfg, log=log)

    truth = truths[0] if truths and all(t == truths[0] for t in truths) else {}
    print_table(result, truth)
    payload = result.to_json()
    payload.update({"targets": [v.name for v in views], "truth": truth, "spp": args.spp, "seed": args.seed,
                    "solver": args.solver, "downscale": args.downscale})
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    write_json_atomic(args.out, payload)
    base = os.path.splitext(args.out)[0]
    from .plots import plot_convergence, plot_comparison

    full = [make_view(sc, t, v.name, 1, v.target_spp) for sc, t, v in zip(scenes_full, targets_full, views)]
    plot_comparison(base + ".png", views, result, truth, full=full)
    plot_convergence(base + "_convergence.png", result, truth)
    print(f"wrote {args.out}, {base}.png, {base}_convergence.png")
    if not result.success:
        print("FIT FAILED: " + "; ".join(result.messages), file=sys.stderr)
        return 1
    return 0


def print_table(result, truth: dict) -> None:
    print()
    print(f"{'param':<10} {'init':>9} {'estimate':>10} {'± se':>9} {'sd(keys)':>9} {'true':>9} {'error':>9}")
    for n in result.names:
        u = result.uncertainty[n]
        t = truth.get(n)
        err = f"{result.params[n] - t:+.4f}" if t is not None else ""
        ts = f"{t:.4f}" if t is not None else "?"
        print(f"{n:<10} {result.init[n]:>9.4f} {result.params[n]:>10.4f} {u['se']:>9.4f} {u['sd_repeats']:>9.4f} "
              f"{ts:>9} {err:>9}")
    status = "converged" if result.success else "FAILED"
    print(f"{status}: {result.iterations} solver steps in {result.rounds} round(s) + repeats, {result.wall_s:.1f} s, "
          f"residual/noise {result.chi2:.2f}")
    if result.correlation is not None and len(result.names) > 1:
        c = np.asarray(result.correlation)
        pairs = [f"{a}~{b} {c[i, j]:+.2f}" for i, a in enumerate(result.names) for j, b in enumerate(result.names) if j > i]
        print("correlation of the estimates (from the Jacobian): " + ", ".join(pairs))
    for m in result.messages:
        print("note: " + m)


def write_json_atomic(path, payload) -> None:
    tmp = f"{path}.tmp-{os.getpid()}"
    try:
        with open(tmp, "w") as f:
            json.dump(payload, f, indent=2)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


if __name__ == "__main__":
    sys.exit(main())
