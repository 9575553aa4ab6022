"""Recover medium parameters from target images.

    python -m fitting.fit SCENE.json TARGET.exr [MORE_TARGETS.exr | SCENE2.json TARGET2.exr ...] \
        --fit sigma_t g [albedo intensity] [--init sigma_t=0.3 g=0.0] [--spp N] [--budget SECONDS] [--seed S] \
        [--downscale F] --out RESULT.json

Each target is fitted with the scene file named most recently before it; all targets are one medium, fitted jointly.
Writes RESULT.json, RESULT.png (target | fit | difference per view) and RESULT_convergence.png; prints a table of
the estimate with its uncertainty and, when the targets' headers record the truth, the true values. Exits 1 when the
fit fails (the model does not explain the targets from any start the search found, a parameter is not pinned down
or ran to the edge of its range), 2 on bad input. The solver is `fitting.solver` (docs/fitting.md).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

from .photo import fov_check, parse_curve, read_photo
from .problem import make_view
from .visibility import describe
from .solver import FitConfig, fit_views
from jaxfog.tools import LimitError, check_size

from .params import SPECS, FitError, check_names, check_value, scene_values
from jaxfog.tools import seed_argument as _seed


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




def check_outputs(out: str, inputs) -> list[str]:
    """The files the fit will write (RESULT.json and the two PNGs beside it), checked before any work: `.json`, not a
    directory, none of them one of the `inputs`, and a directory that exists (or can be made) and is writable.
    Returns the three paths."""
    if not out.lower().endswith(".json"):
        raise FitError(f"--out must name a .json file, got {out!r}")
    base = os.path.splitext(out)[0]
    paths = [out, base + ".png", base + "_convergence.png"]
    for p in paths:
        if os.path.isdir(p):
            raise FitError(f"--out {out}: {p} is a directory")
        for q in inputs:
            if os.path.abspath(p) == os.path.abspath(q) or (os.path.exists(p) and os.path.samefile(p, q)):
                raise FitError(f"--out {out}: would overwrite the input {q}")
    directory = os.path.dirname(os.path.abspath(out))
    try:
        os.makedirs(directory, exist_ok=True)
    except OSError as e:
        raise FitError(f"--out {out}: cannot create directory {directory}: {e.strerror or e}") from None
    if not os.access(directory, os.W_OK | os.X_OK):
        raise FitError(f"--out {out}: directory {directory} is not writable")
    return paths


PREVIEW_SIDE = 64
"""Largest side (px) of the figure's target: pooled by the smallest divisor of the fit's downscale that brings it to
at most this (a 128 x 128 target: 64 x 64, its noise averaged over 4 pixels, still an image to look at)."""


def preview_downscale(width: int, height: int, fit_downscale: int) -> int:
    """The pooling factor of the figure's images: the smallest divisor `d` of `fit_downscale` with
    `max(width, height) / d <= PREVIEW_SIDE` (`fit_downscale` itself if none is smaller)."""
    for d in range(1, fit_downscale + 1):
        if fit_downscale % d == 0 and max(width, height) <= PREVIEW_SIDE * d:
            return d
    return fit_downscale


def json_safe(x):
    """`x` with every non-finite float replaced by None (JSON has no NaN or Infinity)."""
    if isinstance(x, float):
        return x if np.isfinite(x) else None
    if isinstance(x, dict):
        return {k: json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, np.generic):
        return json_safe(x.item())
    return x


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
    p.add_argument("--fit", nargs="+", default=["sigma_t", "g"],
                   help=f"parameters to fit: {', '.join(SPECS)}; or density alone: every voxel of a grid medium "
                        f"(python -m fitting.grid)")
    p.add_argument("--init", nargs="*", default=[],
                   help="starting values, e.g. sigma_t=0.3 g=0.0 (default: the scene file's): a hint for the global "
                        "search, which scans the parameters' plausible range whatever the start")
    p.add_argument("--spp", type=int, default=256,
                   help="samples per pixel of the solver's unit render (default 256); its passes are multiples of it")
    p.add_argument("--seed", type=_seed, default=0,
                   help="seed of the fit's keys, in [0, 4294967295] (targets use other seeds)")
    p.add_argument("--downscale", type=int, default=None,
                   help="fit at 1/F of the target resolution (box-pooled target; default: the largest F that divides "
                        "the image size and leaves at least 8 px a side, 16 when an exposure is fitted: few pixels "
                        "with many samples each keep the Jacobian's noise low, docs/results/fit_sweep)")
    p.add_argument("--budget", type=float, default=None, metavar="SECONDS",
                   help=f"time budget of each local solve: its estimate stops with the passes it has when it is spent "
                        f"(default {FitConfig.time_budget:g}; `inf`: none; with several processes, process 0's "
                        f"clock decides for all; a solve also stops when its standard errors reach 1%% or stop "
                        f"shrinking)")
    p.add_argument("--candidates", nargs="+", default=[], metavar="SCENE.json",
                   help="after the fit, rank these views (scene files of the same medium: other cameras or lights) by "
                        "how much a target of each would shrink the uncertainty")
    p.add_argument("--candidate-spp", type=int, default=None, metavar="N",
                   help="samples per pixel assumed for a candidate's target (default: the first target's header "
                        "spp, else 256)")
    p.add_argument("--target-curve", default=None, metavar="CURVE",
                   help="the targets' transfer curve: srgb, linear or gamma:G (default: each file's own colour space; "
                        "sRGB for 8- and 16-bit files that name none, linear for EXR)")
    p.add_argument("--masks", nargs="+", default=[], metavar="MASK",
                   help="one mask image per target, in their order (white = use; `none` for a target without one): "
                        "regions the scene file does not describe")
    p.add_argument("--out", required=True, help="RESULT.json (PNG figures are written beside it)")
    p.add_argument("--quiet", action="store_true", help="no per-iteration progress")
    from jaxfog.tools import add_distributed_arguments

    add_distributed_arguments(p)  # --coordinator HOST:PORT --num-processes N --process-id I (docs/distributed.md)
    return p


def main(argv=None) -> int:
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as e:  # --help (0) or a usage error (2; argparse has printed the message)
        return e.code if isinstance(e.code, int) else 2
    from jaxfog.tools import LaunchError, launch_of

    if "density" in args.fit:  # every voxel of a grid medium: fitting.grid's fit, with this command's options
        try:
            grid_argv = density_argv(args, argv if argv is not None else sys.argv[1:])
        except FitError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        from . import grid

        return grid.main(grid_argv)
    try:  # a multi-process fit's options, checked before any work (None: one process)
        launch = launch_of(args.coordinator, args.num_processes, args.process_id)
    except LaunchError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.budget is None:
        args.budget = FitConfig.time_budget
    from jaxfog.tools import use_cpu_cores

    use_cpu_cores()  # every core as a JAX device (warns if JAX has already started with another count)
    from jaxfog.tools import use_compilation_cache

    use_compilation_cache()  # compiled programs kept on disk: a second run does not compile again ($JAXFOG_CACHE_DIR)
    if launch is not None:  # every process runs the whole fit; process 0 prints and writes (docs/distributed.md)
        from jaxfog.tools import run_process

        return run_process(lambda: _fit_as_one_of_many(args, launch), _failure_of_one)
    try:
        return _run(args)
    except (FitError, LimitError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


DENSITY_OPTIONS = ("--out", "--seed", "--downscale", "--spp", "--fit", "--quiet")
"""The options `--fit density` passes on to `fitting.grid` (the others belong to the fit of a few parameters)."""


def density_argv(args, argv: list[str]) -> list[str]:
    """`fitting.grid`'s arguments for `--fit density`: the scene / target pairs, `--out` (RESULT.json; the grid
    beside it as RESULT_density.vol and RESULT_density_se.vol), `--seed`, `--downscale` and, where given, `--spp`
    (each render of the voxel fit; its own default, 8, otherwise). Refuses, before any work, another parameter
    beside `density` and the options of the few-parameter fit."""
    if args.fit != ["density"]:
        raise FitError(f"--fit {' '.join(args.fit)}: density (every voxel of a grid medium) is fitted alone; "
                       f"fit the other parameters with the grid fixed, or use python -m fitting.grid")
    given = {a.split("=", 1)[0] for a in argv if a.startswith("--")}
    other = sorted(given - set(DENSITY_OPTIONS))
    if other:
        raise FitError(f"--fit density takes only {', '.join(DENSITY_OPTIONS)} of this command's options, not "
                       f"{', '.join(other)} (python -m fitting.grid --help: the voxel fit's own options)")
    if len(args.inputs) % 2:
        raise FitError("--fit density: expected pairs SCENE.json TARGET.exr (one scene per target)")
    out = [*args.inputs, "--out", args.out, "--seed", str(args.seed)]
    if args.downscale is not None:
        out += ["--downscale", str(args.downscale)]
    if "--spp" in given:
        out += ["--spp", str(args.spp)]
    return out


def _fit_as_one_of_many(args, launch) -> int:
    """`main`'s fit as one process of a multi-process fit: each process makes the same decisions from the same images
    (each render is shared by every process's devices, and each process gets the whole image); the processes other
    than 0 print nothing and write RESULT.json and its figures into a temporary folder that is then removed."""
    import contextlib
    import tempfile

    from jaxfog.tools import initialize_distributed, process_index

    initialize_distributed(launch)  # before anything makes a JAX array (loading a scene does)
    if process_index() == 0:
        return _run(args)
    with tempfile.TemporaryDirectory(prefix="jaxfog-fit-") as tmp, open(os.devnull, "w") as null, \
            contextlib.redirect_stdout(null), contextlib.redirect_stderr(null):
        args.out = os.path.join(tmp, os.path.basename(args.out))
        return _run(args)


def _failure_of_one(e: BaseException) -> int:
    """A multi-process fit's failure in this process, printed with the process's id; the exit code (2 for a bad
    input, as `main`)."""
    from jaxfog.tools import LaunchError, process_index, report_unexpected

    if isinstance(e, (FitError, LimitError, LaunchError)):
        print(f"error: process {process_index()}: {e}", file=sys.stderr)
        return 2
    return report_unexpected(e, "python -m fitting.fit")


def _run(args) -> int:
    names, init_given = check_arguments(args)
    pairs = pair_inputs(args.inputs)
    check_outputs(args.out, [p for pair in pairs for p in pair])
    parse_curve(args.target_curve)
    args.photos = {}
    loaded = [load_pair(scene_path, target_path, args) for scene_path, target_path in pairs]
    views = [x[0] for x in loaded]
    candidates = load_candidates(args.candidates, args.downscale)
    start = scene_values(views[0].scene)
    init = {n: init_given.get(n, start.get(n)) for n in names}
    for n in names:
        if init[n] is None:
            raise FitError(f"cannot fit {n}: the scene has no such value")
    cfg = FitConfig(spp=args.spp, seed=args.seed, time_budget=args.budget)
    from .plots import preload

    preload()  # the figures' plotting library imported while the fit runs (~1 s of a 15 s job)
    print(f"fitting {', '.join(names)} to {len(views)} target(s) at "
          f"{views[0].scene.camera.width}x{views[0].scene.camera.height} px, {args.spp} spp")
    result = fit_views(views, names, init, cfg, log=(lambda *_: None) if args.quiet else print)
    truth = common_truth([x[3] for x in loaded])
    print_table(result, truth)
    for name, pixels in result.fireflies.items():
        print(f"note: {name}: {len(pixels)} firefly pixel(s) left out (10x brighter than each neighbour; the model "
              f"check refused the targets with them): (x, y) " + ", ".join(f"({x}, {y})" for x, y in pixels[:8]))
    payload = result.to_json()
    if candidates:
        spp_c = args.candidate_spp or next((v.target_spp for v in views if v.target_spp), 256)
        payload["candidates"] = rank_candidates(result, views, candidates, spp_c, args.spp)
    payload.update({"targets": [v.name for v in views], "truth": truth, "spp": args.spp, "seed": args.seed,
                    "budget": args.budget, "downscale": args.downscale, "photos": args.photos or None})
    write_json_atomic(args.out, payload)
    write_figures(args.out, loaded, result, truth)
    if not result.success:
        print("FIT FAILED: " + "; ".join(result.messages), file=sys.stderr)
        return 1
    return 0


def check_arguments(args) -> tuple[list[str], dict]:
    """The fitted names and the starting values, after every check that renders nothing, each a `FitError` (exit 2)
    naming the argument or file, the value and what is valid: the names (`check_fitted_together`), `--init`, the
    numbers, each target given once (`check_targets_once`), outputs that would overwrite a `--candidates` scene or a
    read-only file (`check_outputs_kept`), and the scene files themselves (`check_scenes`: a light to fit with; a
    scene value outside a fitted parameter's range becomes an in-range start, said in one printed line). The scenes
    are loaded here (validated and built, nothing compiled) and again by `load_pair`."""
    names = check_names(args.fit)
    check_fitted_together(names)
    init_given = parse_assignments(args.init)
    if args.spp < 1:
        raise FitError(f"--spp must be >= 1, got {args.spp}")
    if not args.budget > 0:
        raise FitError(f"--budget must be > 0 seconds, got {args.budget}")
    if args.candidate_spp is not None and args.candidate_spp < 1:
        raise FitError(f"--candidate-spp must be >= 1, got {args.candidate_spp}")
    not_fitted = sorted(set(init_given) - set(names))
    if not_fitted:
        raise FitError(f"--init {' '.join(f'{n}={init_given[n]:g}' for n in not_fitted)}: not in --fit "
                       f"({' '.join(names)}); add it to --fit, or leave it out of --init (an unfitted parameter "
                       f"keeps the scene file's value)")
    pairs = pair_inputs(args.inputs)
    check_targets_once(pairs)
    check_outputs_kept(args.out, args.candidates)
    starts = check_scenes(pairs, args.candidates, [n for n in names if n not in init_given])
    return names, {**starts, **init_given}


CHANNEL_FIELDS = ("sigma_t", "albedo")
"""Medium fields fitted grey (`sigma_t`) or per channel (`sigma_t[r]`, ...): both write the same field."""

UNDETERMINED_TOGETHER = {
    frozenset({"sigma_0", "base_height"}): "only sigma_0 exp(base_height / height_scale) enters the image (a height "
                                           "fog's sigma_0 and base_height are one parameter; docs/conventions.md)",
}
"""Pairs of parameters that no set of targets determines apart, with the reason (documented in docs/ and
`fitting/params.py`)."""


def check_fitted_together(names) -> None:
    """Refuse the same parameter twice under two names (`sigma_t` with `sigma_t[r]`: both set the medium's
    `sigma_t`) and the pairs in `UNDETERMINED_TOGETHER`."""
    for field in CHANNEL_FIELDS:
        parts = [n for n in names if n.startswith(field + "[")]
        if field in names and parts:
            raise FitError(f"--fit {field} {' '.join(parts)}: the same parameter twice ({field} sets every channel of "
                           f"the medium's {field}, {', '.join(parts)} one channel of it); fit {field} (grey) or "
                           f"{field}:rgb (per channel), not both")
    for pair, why in UNDETERMINED_TOGETHER.items():
        if pair <= set(names):
            a, b = sorted(pair, key=list(names).index)
            raise FitError(f"--fit {a} {b}: no targets determine these two apart: {why}; fit one of them")


def _same_path(a: str, b: str) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.abspath(a) == os.path.abspath(b)


def check_targets_once(pairs) -> None:
    """Each target file at most once: one image given twice would count as two views with independent noise."""
    for i, (_, t) in enumerate(pairs):
        for j in range(i):
            if _same_path(t, pairs[j][1]):
                raise FitError(f"target {t} is given twice (targets {j + 1} and {i + 1}); expected each target once "
                               f"(the same image twice would count as two independent views)")


def check_outputs_kept(out: str, candidates) -> None:
    """The fit's outputs (RESULT.json and its two PNGs) are neither a `--candidates` scene file nor an existing
    read-only file (refused as `jaxfog render` refuses a read-only output, also for the superuser)."""
    from jaxfog.tools import read_only

    base = os.path.splitext(out)[0]
    for p in (out, base + ".png", base + "_convergence.png"):
        for c in candidates:
            if _same_path(p, c):
                raise FitError(f"--out {out}: would overwrite the --candidates scene {c}")
        if read_only(p):
            raise FitError(f"--out {out}: {p} is read-only; expected a writable file or a new name (make it "
                           f"writable to replace it)")


def _in_range_start(name: str, x0: float, L: float) -> float | None:
    """`x0` if it is a valid start for `name` (inside its open range, finite in the solver's coordinate as float32);
    else an in-range start from the parameter's search region (`ParamSpec.search`): the nearest end of a fixed region,
    the geometric middle of an "extinction" (optical depth 0.01-20 over the scene's size `L`) or "length" (L / 30 to
    3 L) region; None where the region has no scale without a valid x0 ("power", "offset")."""
    import math

    spec = SPECS[name]
    with np.errstate(all="ignore"):
        u = float(spec.to_u(np.float32(x0)))
    if spec.lo < x0 < spec.hi and math.isfinite(u):
        return x0
    kind = spec.search
    if isinstance(kind, tuple) and len(kind) == 2:
        return float(min(max(x0, kind[0]), kind[1]))
    if kind == "extinction":
        return math.sqrt(0.01 * 20.0) / L
    if kind == "length":
        return L / math.sqrt(10.0)
    return None


def check_scenes(pairs, candidates, names) -> dict:
    """Load every scene file (nothing compiled): each must have a light (a fit of an unlit scene has black images
    whatever its medium). Returns the starts of the fitted `names` whose first scene's value is outside the
    parameter's range (sigma_t 0, albedo 1, a droplet diameter of 3 µm): clamped into it (`_in_range_start`), one
    printed line each. Clamped, not refused: the global search scans the parameter's whole region whatever the start
    (a start is a hint), and such a scene is a valid scene to render; a refusal would only make the user edit it."""
    import jaxfog

    scenes = {}
    listed = [("", p) for p, _ in pairs] + [("--candidates ", c) for c in candidates if c.lower().endswith(".json")]
    for option, path in listed:  # (a candidate that is not a .json file: `load_candidates` says so)
        if path in scenes:
            continue
        try:
            sf = jaxfog.load_scene(path)
        except (jaxfog.SceneError, OSError) as e:
            raise FitError(f"{option}{e}") from None
        if not sf.scene.lights:
            raise FitError(f"{option}{path}: the scene has no light; expected at least one light (an unlit scene "
                           f"renders black whatever the medium, so there is nothing to fit)")
        scenes[path] = sf.scene
    first = scenes[pairs[0][0]]
    L = max(float(np.linalg.norm(np.asarray(scenes[p].camera.target) - np.asarray(scenes[p].camera.origin)))
            for p, _ in pairs)
    starts = {}
    for n in names:
        try:
            x0 = float(SPECS[n].get(first))
        except (FitError, AttributeError, IndexError):
            continue  # the scene has no such value: `_run` says so
        x = _in_range_start(n, x0, L)
        if x is None:
            raise FitError(f"{pairs[0][0]}: {n} {x0:g} is outside the fit's range ({SPECS[n].lo:g}, "
                           f"{SPECS[n].hi:g}); give a start with --init {n}=VALUE")
        if x != x0:
            print(f"note: {os.path.basename(pairs[0][0])}: {n} {x0:g} is outside the fit's range ({SPECS[n].lo:g}, "
                  f"{SPECS[n].hi:g}); the search starts from {x:.4g} instead (a start is a hint: the search scans the "
                  f"whole range)")
            starts[n] = x
    return starts


def load_pair(scene_path: str, target_path: str, args) -> tuple:
    """One scene file and target, checked: `(view at the fit resolution, full scene, full target, truth)`; sets
    `args.downscale` from the first scene when not given."""
    import jaxfog

    if not os.path.exists(target_path):
        raise FitError(f"target {target_path!r} not found")
    try:
        sf = jaxfog.load_scene(scene_path)
    except (jaxfog.SceneError, OSError) as e:
        raise FitError(str(e)) from None
    mask = mask_path(args, target_path)
    photo = None
    if target_path.lower().endswith(".exr") and args.target_curve in (None, "linear") and mask is None:
        try:
            target, meta = jaxfog.read_exr(target_path)
        except Exception as e:  # noqa: BLE001 - OIIO raises plain exceptions; report them as input errors
            raise FitError(f"cannot read target {target_path!r}: {e}") from None
    else:  # a photograph (or a float target with a mask): decoded through its curve, with its validity mask
        photo = read_photo(target_path, args.target_curve, mask)
        target, meta = photo.image, {}
    cam = sf.scene.camera
    if args.downscale is None:
        # with the camera's exposure fitted too, at least 16 px a side: at 8 x 8 sigma_t, g and the exposure are
        # nearly degenerate (the worked photograph stopped 15% off there; the study's photo family fits at 16 x 16)
        camera = any(n.startswith("exposure") for n in (args.fit or []))
        args.downscale = auto_downscale(cam.width, cam.height, 16 if camera else 8)
    f = max(args.downscale, 1)
    check_size(cam.width // f, cam.height // f, args.spp * FitConfig.estimate_factor // 2, sf.scene.max_depth,
               names={"width": f"{os.path.basename(scene_path)}: camera.width / --downscale",
                      "height": "camera.height / --downscale",
                      "spp": f"--spp x {FitConfig.estimate_factor // 2} (an estimate pass)",
                      "max_depth": "integrator.max_depth"}, rr_depth=int(sf.scene.rr_depth))
    spp_t = int(meta["jaxfog:spp"]) if "jaxfog:spp" in meta else None
    name = os.path.basename(target_path)
    if photo is None:
        return make_view(sf.scene, target, name, args.downscale, spp_t), sf.scene, target, true_values(meta)
    view = make_view(sf.scene, target, name, args.downscale, None, photo.valid, photo.noise_var, photo.variance)
    print(f"{name}: {photo.curve} curve, {photo.bits or 'float'} bit; pixels left out: "
          + (", ".join(f"{k} {v}" for k, v in photo.masked.items()) or "none")
          + (f"; camera: {photo.exif}" if photo.exif else ""))
    if photo.noise is not None:
        print(f"{name}: camera noise from the image: shot " + " ".join(f"{a:.3g}" for a in photo.noise["shot"])
              + " x value, read " + " ".join(f"{r:.3g}" for r in photo.noise["read"]) + " (R G B, linear values)"
              + ("; a JPEG: weights from the block estimate instead" if photo.lossy else ""))
    warning = fov_check(photo.exif, float(cam.fov), cam.width, cam.height)
    if warning:
        print(f"warning: {name}: {warning}")
    args.photos[name] = {"curve": photo.curve, "bits": photo.bits, "masked": photo.masked, "exif": photo.exif,
                         "fov_warning": warning, "noise": photo.noise, "lossy": photo.lossy}
    return view, sf.scene, target, {}


def mask_path(args, target_path: str) -> str | None:
    """The `--masks` entry of this target (in target order; `none` for a target without one)."""
    masks = getattr(args, "masks", None) or []
    targets = [t for _, t in pair_inputs(args.inputs)]
    i = targets.index(target_path)
    if masks and len(masks) != len(targets):
        raise FitError(f"--masks: {len(masks)} mask(s) for {len(targets)} target(s); give one per target in their "
                       f"order, `none` for a target without a mask")
    return None if not masks or masks[i].lower() == "none" else masks[i]


def common_truth(truths: list[dict]) -> dict:
    """The truth the targets' headers agree on (empty where they differ); a grey truth is every channel's."""
    truth = dict(truths[0]) if truths and all(t == truths[0] for t in truths) else {}
    for f in ("sigma_t", "albedo"):
        if isinstance(truth.get(f), (int, float)):
            for c in "rgb":
                truth.setdefault(f"{f}[{c}]", truth[f])
    return truth


def write_figures(out: str, loaded: list[tuple], result, truth: dict) -> None:
    """RESULT.png (target | fit | difference per view) and RESULT_convergence.png beside RESULT.json."""
    from .plots import plot_comparison, plot_convergence

    base = os.path.splitext(out)[0]
    views = [x[0] for x in loaded]
    full = [make_view(sc, t, v.name, preview_downscale(sc.camera.width, sc.camera.height, v.downscale),
                      v.target_spp) for v, sc, t, _ in loaded]
    plot_comparison(base + ".png", views, result, truth, full=full)
    plot_convergence(base + "_convergence.png", result, truth)
    print(f"wrote {out}, {base}.png, {base}_convergence.png")


def load_candidates(paths, downscale: int | None) -> list[tuple[str, object, int]]:
    """The `--candidates` scene files, checked before any work: `(name, scene at its fit resolution, downscale)`;
    the fit's `--downscale` where it divides the candidate's image, else `auto_downscale`."""
    import equinox as eqx

    import jaxfog

    out = []
    for p in paths:
        if not p.lower().endswith(".json"):
            raise FitError(f"--candidates expects scene files (.json), got {p!r}")
        try:
            sf = jaxfog.load_scene(p)
        except (jaxfog.SceneError, OSError) as e:
            raise FitError(f"--candidates: {e}") from None
        if sf.scene.medium is None:
            raise FitError(f"--candidates {p}: the scene has no medium")
        cam = sf.scene.camera
        f = downscale if downscale and cam.width % downscale == 0 and cam.height % downscale == 0 else \
            auto_downscale(cam.width, cam.height)
        small = cam.resized(cam.width // f, cam.height // f)
        out.append((os.path.basename(p), eqx.tree_at(lambda s: s.camera, sf.scene, small), f))
    return out


CANDIDATE_SPP_FACTOR = 4
"""A candidate's two Jacobian renders have this many times the fit's spp (at 8 x 8 px the rounds' forward-mode
program shape: 1,024 spp at the default 256)."""


def rank_candidates(result, views, candidates, target_spp: int, spp: int) -> list[dict]:
    """Rank the candidate views by the worst-determined standard error with a target of each (at `target_spp` x
    its downscale^2 samples per fit pixel) added to the fitted views' (`views`); prints the ranking. The
    information of every view is `fitting.problem.candidate_fisher` at the estimate, the targets' noise alone."""
    import jax

    from .problem import candidate_fisher
    from .information import rank_views

    names = result.names
    key = jax.random.key(777)
    spp_j = spp * CANDIDATE_SPP_FACTOR
    # the fitted views' information computed the same way (their targets' noise: the header's spp, else the block
    # estimate), so that a candidate is compared like with like; the fit's own render noise, most of its standard
    # error on the main job, is shrunk by more rounds, not by more views
    fisher = sum(candidate_fisher(v.scene, names, result.params, spp_j,
                                  v.target_spp * v.downscale ** 2 if v.target_spp else None,
                                  jax.random.fold_in(key, 1000 + i),
                                  noise=None if v.target_spp else v.target_var)
                 for i, v in enumerate(views))
    Fc = {name: candidate_fisher(sc, names, result.params, spp_j, target_spp * f * f, jax.random.fold_in(key, i))
          for i, (name, sc, f) in enumerate(candidates)}
    ranking = rank_views(names, result.params, fisher, Fc)
    print(f"candidate views, each as one more target at {target_spp} spp (standard errors from the targets' noise, "
          f"relative units; the worst-determined combination's with these views {ranking[0]['worst_se_before']:.3g}):")
    for r in ranking:
        print(f"  {r['view']}: worst {r['worst_se']:.3g} ({r['shrink']:.2f}x smaller, along "
              f"{r['worst_combination']}); " + ", ".join(f"{n} {x:.3g}" for n, x in r["se"].items()))
    return ranking


def print_table(result, truth: dict) -> None:
    print()
    print(f"{'param':<10} {'init':>9} {'estimate':>10} {'± se':>9} {'target':>9} {'renders':>9} {'true':>9} "
          f"{'error':>9}")
    for n in result.names:
        u = result.uncertainty[n]
        t = truth.get(n)
        err = f"{result.params[n] - t:+.4f}" if t is not None else ""
        ts = f"{t:.4f}" if t is not None else "?"
        print(f"{n:<10} {result.init[n]:>9.4f} {result.params[n]:>10.4f} {u['se']:>9.4f} {u['se_target']:>9.4f} "
              f"{u['se_render']:>9.4f} {ts:>9} {err:>9}")
    status = "converged" if result.success else "FAILED"
    print(f"{status}: {result.rounds} round(s), {result.wall_s:.1f} s, residual/noise {result.chi2:.2f} "
          f"(± se: from the residuals; target, renders: the noise model's parts)")
    if result.correlation is not None and len(result.names) > 1:
        c = np.asarray(result.correlation)
        pairs = [f"{a}~{b} {c[i, j]:+.2f}" for i, a in enumerate(result.names) for j, b in enumerate(result.names) if j > i]
        print("correlation of the estimates: " + ", ".join(pairs))
    info = getattr(result, "information", None) or {}
    for line in info.get("summary", []):
        print("what the views determine: " + line)
    for line in describe(result.visibility):
        print(line)
    for m in result.messages:
        print("note: " + m)


def write_json_atomic(path, payload) -> None:
    tmp = f"{path}.tmp-{os.getpid()}"
    try:
        with open(tmp, "w") as f:
            json.dump(json_safe(payload), f, indent=2, allow_nan=False)  # NaN (unknown) is written as null
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


if __name__ == "__main__":
    sys.exit(main())
