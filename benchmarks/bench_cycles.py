"""Blender Cycles as a second peer: time to equal error, each renderer against its own converged reference
(`python -m benchmarks.bench_cycles [--quick] [--out DIR] [--cycles-python PATH]`, from the repository root).

Cycles (Blender as the `bpy` module) pins `numpy<2`, jaxfog's JAX needs `numpy>=2`, so Cycles runs in its own
interpreter (`python3.11 -m venv V && V/bin/pip install bpy`; `--cycles-python V/bin/python`, or the environment
variable `JAXFOG_CYCLES_PYTHON`), in a subprocess running `benchmarks/cycles_render.py`, which imports only `bpy`,
NumPy and the standard library. `to_cycles` (pure, tested without `bpy`) translates jaxfog's scene into the plain
dict of Cycles parameters that script builds the scene from:

- coordinates: jaxfog is Y-up, Blender Z-up: `(x, y, z) -> (x, -z, y)` (a rotation, so handedness and the camera's
  left/right are kept); the camera's matrix has columns right, up, -forward (a Blender camera looks along -Z), and
  `sensor_fit = HORIZONTAL` with `angle` = jaxfog's full horizontal fov;
- fog: the world volume (it fills all space outside the objects; jaxfog's fog ends at `extent`, 1000 m by default,
  where a sigma_t of 0.5 leaves nothing) as Volume Scatter + Volume Absorption: Cycles' scattering coefficient is
  color x density and its absorption coefficient (1 - color) x density (`svm_node_closure_volume`), so Scatter gets
  color = sigma_s / max(sigma_s), density = max(sigma_s), Absorption color = 1 - sigma_a / max(sigma_a), density =
  max(sigma_a); Henyey-Greenstein anisotropy = g (Cycles' g > 0 is forward, as jaxfog's);
- spot light: a point (radius 0, a delta light) whose Blender power P (W) gives the radiant intensity P / (4 pi)
  W/sr (Cycles' `PointLight::copy_to_kernel`: eval_fac = 1 / (pi x area) with area 4 for radius 0), so
  `power = 4 pi I`; `spot_size` = 2 x cutoff; Cycles' edge is a smoothstep in cos(theta) of width
  (1 - cos(cutoff)) x blend below the cutoff (`spot_light_attenuation`), jaxfog's (Mitsuba's) a ramp linear in theta
  from beam_width to cutoff: `spot_blend` is chosen so that the two cones carry the same power (`spot_blend_matching`;
  0.455 for 15 / 20 degrees, whose half-intensity angles then differ by 0.03 degrees);
- surfaces: Diffuse BSDF (roughness 0: Lambert); the rectangle as one quad, the sphere as an icosphere of 5
  subdivisions (20480 triangles, smooth normals; the flat facets deviate from the sphere by at most 0.2 mm at
  r = 0.5 m). Cycles' diffuse is two-sided, jaxfog's one-sided (only the floor's underside can tell);
- path length: jaxfog's `max_depth` counts segments (8: at most 7 scattering vertices, the last one's light sample
  being the 8th segment); Cycles' bounce limits count the vertices after the first (0: direct light at the first
  vertex), so every Cycles limit (total, diffuse, volume, glossy, transmission) is `max_depth - 2`;
- film: box pixel filter of 1 px (jaxfog's plain average over the pixel), no denoising, no adaptive sampling, no
  clamping, no light tree (one light), no probabilistic light-sample termination; Cycles' own Russian roulette on
  low throughput stays (it is unbiased).

The measurement (`run_benchmark`):

1. Cycles' converged reference: `ref_chunks` independent images of `ref_spp / ref_chunks` spp with
   `REFERENCE_SETTING` (equiangular), cached in `DIR/cache/`; its own noise is `RMSE(half_A - half_B) / 2`
   (`benchmarks.bench_stats.reference_rmse`), and a corrected RMSE is `sqrt(raw^2 - ref^2)`.
2. jaxfog's reference: `benchmarks.bench.reference_image` (default strategy, its cache in the same folder).
3. Cycles' settings (`SETTINGS`: volume sampling distance / equiangular / MIS, each with and without path guiding):
   `screen_images` images of `cycles_spp` spp each; the relative error of a setting is the median over its images
   of the corrected per-pixel RMSE against Cycles' reference over the reference's mean pixel value. The best setting
   is the one with the least time to a common error (RMSE falling as 1/sqrt(spp): the least `error^2 x time`).
4. The target: the median over `draws` independent `cycles_spp`-spp images of the best setting (seeds apart from the
   screen's). jaxfog then renders `draws` independent images at 1, 2, 3, ... spp (each timed as one `jaxfog.render`
   call after compilation) until the median of its corrected relative RMSEs against its own reference is at or
   below the target. Ratio = jaxfog's mean time per image / Cycles' mean time per image. jaxfog's ms/spp is timed
   right before and right after Cycles' target images, under the same load (a program of one sample layer per
   batch, 8 spp); `ratio_adjacent` = the spp found x the mean of those two ms/spp / Cycles' time per image. It
   differs from the ratio by the load's drift over the minutes the search takes, and by `render`'s padding: its
   default batch (65536 paths) is 4 sample layers at 128 x 128, and a last, partial batch is traced in full, so
   9 spp costs as much as 12.

Each renderer against its own reference, so the scenes need not match photometrically; their image means are
printed side by side (the ratio, with standard errors), not claimed equal.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from benchmarks.bench_stats import expected_rmse, reference_stats
from benchmarks.common import REPO, Stopwatch, block_means, digest, format_table, load, machine_info, mean_and_se
from benchmarks.common import out_dir, run_summary, save_npz, stderr_log, with_args, write_json

CYCLES_SCRIPT = REPO / "benchmarks" / "cycles_render.py"

SETTINGS: dict[str, dict] = {
    "distance": {"volume_sampling": "DISTANCE", "guiding": "off"},
    "equiangular": {"volume_sampling": "EQUIANGULAR", "guiding": "off"},
    "mis": {"volume_sampling": "MULTIPLE_IMPORTANCE", "guiding": "off"},
    "distance+guiding": {"volume_sampling": "DISTANCE", "guiding": "both"},
    "equiangular+guiding": {"volume_sampling": "EQUIANGULAR", "guiding": "both"},
    "mis+guiding": {"volume_sampling": "MULTIPLE_IMPORTANCE", "guiding": "both"},
}
"""Cycles' settings tried: the world volume's `volume_sampling` (free-flight distance, equiangular toward the
light, or their MIS: Cycles' default for a material, the world's being equiangular), and path guiding (Open PGL,
CPU only: volume and surface guiding, Cycles' default probabilities 0.5, 128 training samples per render)."""

REFERENCE_SETTING = "equiangular"
"""The setting of Cycles' reference: the world's default, and the lightest-tailed error of the settings tried (the
first run's MIS reference had images whose squared error was ten to a hundred times the median)."""


@dataclass
class Config:
    """One run. `FULL` is the committed run, `QUICK` a smoke run (16 x 16, a few spp)."""

    scene: str = "spot_fog"
    size: int = 128
    threads: int = 2
    cycles_spp: int = 64  # spp of each Cycles image (the target is its median error)
    draws: int = 16  # independent images of each renderer at the equal-error comparison (>= 9)
    screen_images: int = 9  # images per Cycles setting in the settings screen
    settings: tuple = tuple(SETTINGS)
    ref_spp: int = 4096  # Cycles' reference
    ref_chunks: int = 8
    jax_ref_spp: int = 256  # jaxfog's reference (benchmarks.bench's)
    jax_ref_chunks: int = 8
    max_jax_spp: int = 32
    seed: int = 0


FULL = Config()
QUICK = Config(size=16, cycles_spp=8, draws=9, screen_images=3, settings=("mis", "equiangular+guiding"), ref_spp=256,
               ref_chunks=4, jax_ref_spp=64, jax_ref_chunks=4, max_jax_spp=8)


# ============================================================================================ scene translation
def to_blender(v) -> list[float]:
    """A jaxfog (Y-up) point or direction in Blender's Z-up coordinates: `(x, y, z) -> (x, -z, y)`."""
    x, y, z = (float(a) for a in v)
    return [x, -z, y]


def _normalize(v) -> np.ndarray:
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def _rgb(x) -> list[float]:
    a = np.broadcast_to(np.asarray(x, np.float64), (3,))
    return [float(t) for t in a]


def _matrix_rows(x_axis, y_axis, z_axis, origin) -> list[list[float]]:
    """A 4 x 4 object matrix (rows) whose columns are the local axes and the origin."""
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x_axis, y_axis, z_axis, origin
    return m.tolist()


def camera_matrix(origin, target, up) -> list[list[float]]:
    """Blender's `matrix_world` (rows) of a camera at `origin` (jaxfog coordinates) looking at `target`: columns
    right, up, -forward (a Blender camera looks along its local -Z with +Y up), origin."""
    o, t, u = (np.asarray(to_blender(a)) for a in (origin, target, up))
    f = _normalize(t - o)
    r = _normalize(np.cross(f, u))
    return _matrix_rows(r, np.cross(r, f), -f, o)


def light_matrix(position, direction) -> list[list[float]]:
    """Blender's `matrix_world` (rows) of a spot light at `position` shining along `direction` (jaxfog
    coordinates): a Blender spot shines along its local -Z."""
    z = -_normalize(to_blender(direction))
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = _normalize(np.cross(helper, z))
    return _matrix_rows(x, np.cross(z, x), z, to_blender(position))


def spot_blend_matching(cutoff_deg: float, beam_deg: float) -> float:
    """Cycles' `spot_blend` whose cone carries the power of jaxfog's (Mitsuba's) spot of `cutoff_deg` and
    `beam_deg` (degrees, 0 < beam <= cutoff < 90).

    jaxfog: falloff 1 to the beam width, then linear in theta to 0 at the cutoff c, so the cone's power over the
    on-axis intensity is `2 pi (1 - (sin c - sin b) / (c - b))`. Cycles: `smoothstep((cos theta - cos c) / w)`
    with `w = (1 - cos c) blend`; a smoothstep integrates to half its width, so `2 pi (1 - cos c - w / 2)`. Equal
    powers: `blend = 2 ((sin c - sin b) / (c - b) - cos c) / (1 - cos c)` (0 for b = c, a hard edge). Cycles'
    blend is at most 1 (the smoothstep then spans the whole cone); a ramp too wide for that (about b < c / 2) gets 1,
    the closest Cycles has, and a cone of less power."""
    c, b = math.radians(cutoff_deg), math.radians(beam_deg)
    if not 0.0 < b <= c < math.pi / 2:
        raise ValueError(f"need 0 < beam_width <= cutoff_angle < 90 degrees, got {beam_deg}, {cutoff_deg}")
    if c - b < 1e-9:
        return 0.0
    return min(2.0 * ((math.sin(c) - math.sin(b)) / (c - b) - math.cos(c)) / (1.0 - math.cos(c)), 1.0)


def cycles_bounces(max_depth: int) -> dict:
    """Cycles' bounce limits for jaxfog's `max_depth` (segments from the camera to the light, >= 2): Cycles counts
    the scattering vertices after the first, so each limit is `max_depth - 2`."""
    if max_depth < 2:
        raise ValueError(f"max_depth {max_depth}: Cycles cannot show only the lights seen directly (need >= 2)")
    n = max_depth - 2
    return {"max": n, "diffuse": n, "glossy": n, "transmission": n, "volume": n, "transparent": 8}


def to_cycles(data: dict, threads: int = 2, sphere_subdivisions: int = 5) -> dict:
    """jaxfog's validated scene dict (`load_scene(...).data`) as the plain dict of Cycles parameters that
    `benchmarks/cycles_render.py` builds: Blender coordinates (Z-up), matrices as rows, angles in radians,
    densities in 1/m, light power in W. Supported: a homogeneous medium with HG phase (or none), rectangles and
    spheres with diffuse BSDFs, point and spot lights; anything else raises `ValueError` naming it."""
    cam = data["camera"]
    out = {"width": int(cam["width"]), "height": int(cam["height"]), "threads": int(threads), "filter_width": 1.0,
           "use_light_tree": False, "bounces": cycles_bounces(int(data["integrator"]["max_depth"])),
           "camera": {"fov_x": math.radians(float(cam["fov"])),
                      "matrix": camera_matrix(cam["origin"], cam["target"], cam["up"])}}
    med = data.get("medium")
    if med is None:
        out["volume"] = None
    else:
        if med.get("type", "homogeneous") != "homogeneous":
            raise ValueError(f"medium type {med.get('type')!r}: only homogeneous fog translates to Cycles")
        phase = med.get("phase")
        if phase is not None and phase.get("type") != "hg":
            raise ValueError(f"phase {phase.get('type')!r}: only Henyey-Greenstein translates to Cycles")
        g = float(phase["g"] if phase is not None else med["g"])
        st, al = np.asarray(_rgb(med["sigma_t"])), np.asarray(_rgb(med["albedo"]))
        ss, sa = st * al, st * (1.0 - al)
        ds, da = float(ss.max()), float(sa.max())
        out["volume"] = {
            "scatter_color": (ss / ds if ds > 0 else np.zeros(3)).tolist(), "scatter_density": ds,
            "absorption_color": (1.0 - sa / da if da > 0 else np.ones(3)).tolist(), "absorption_density": da,
            "anisotropy": g, "sigma_s": ss.tolist(), "sigma_a": sa.tolist()}
    shapes = []
    for i, s in enumerate(data["shapes"]):
        bsdf = s["bsdf"]
        if bsdf["type"] != "diffuse":
            raise ValueError(f"shapes.{i}.bsdf: type {bsdf['type']!r} is not translated to Cycles (diffuse only)")
        refl = _rgb(bsdf["reflectance"])
        if s["type"] == "rectangle":
            c, eu, ev = (np.asarray(s[k], np.float64) for k in ("center", "edge_u", "edge_v"))
            corners = [c - eu / 2 - ev / 2, c + eu / 2 - ev / 2, c + eu / 2 + ev / 2, c - eu / 2 + ev / 2]
            shapes.append({"type": "quad", "vertices": [to_blender(p) for p in corners], "reflectance": refl})
        elif s["type"] == "sphere":
            shapes.append({"type": "sphere", "center": to_blender(s["center"]), "radius": float(s["radius"]),
                           "subdivisions": int(sphere_subdivisions), "reflectance": refl})
        else:
            raise ValueError(f"shapes.{i}: type {s['type']!r} is not translated to Cycles")
    out["shapes"] = shapes
    lights = []
    for i, li in enumerate(data["lights"]):
        if li["type"] not in ("point", "spot"):
            raise ValueError(f"lights.{i}: type {li['type']!r} is not translated to Cycles (point, spot)")
        inten = np.asarray(_rgb(li["intensity"]))
        peak = float(inten.max())
        d = {"type": li["type"].upper(), "power": 4.0 * math.pi * peak,
             "color": (inten / peak if peak > 0 else np.ones(3)).tolist(), "intensity": inten.tolist()}
        if li["type"] == "spot":
            d["spot_size"] = 2.0 * math.radians(float(li["cutoff_angle"]))
            d["spot_blend"] = spot_blend_matching(float(li["cutoff_angle"]), float(li["beam_width"]))
            d["matrix"] = light_matrix(li["position"], li["direction"])
        else:
            d["matrix"] = _matrix_rows([1, 0, 0], [0, 1, 0], [0, 0, 1], to_blender(li["position"]))
        lights.append(d)
    out["lights"] = lights
    return out


# ================================================================================================ Cycles side
class CyclesMissing(RuntimeError):
    """The Cycles interpreter is missing or cannot import `bpy`."""


def default_cycles_python() -> str:
    """`JAXFOG_CYCLES_PYTHON` if set, else this interpreter."""
    return os.environ.get("JAXFOG_CYCLES_PYTHON") or sys.executable


def check_cycles(python: str, timeout: float = 120) -> str:
    """Blender's version string from `python -c "import bpy"`; `CyclesMissing` with the reason otherwise."""
    if not (os.path.isfile(python) and os.access(python, os.X_OK)):
        raise CyclesMissing(f"no Cycles interpreter at {python!r} (set --cycles-python or JAXFOG_CYCLES_PYTHON to a "
                            "Python with bpy: python3.11 -m venv V && V/bin/pip install bpy)")
    try:
        p = subprocess.run([python, "-c", "import bpy, numpy; print(bpy.app.version_string)"], capture_output=True,
                           text=True, timeout=timeout)
    except (OSError, subprocess.TimeoutExpired) as e:
        raise CyclesMissing(f"{python}: {e}") from e
    if p.returncode != 0:
        last = (p.stderr.strip().splitlines() or [f"exit code {p.returncode}"])[-1]
        raise CyclesMissing(f"{python} cannot import bpy: {last}")
    return p.stdout.strip().splitlines()[-1]


def run_cycles(params: dict, jobs: list[dict], python: str, workdir: Path, timeout: float = 3600,
               log=None) -> dict:
    """Run `benchmarks/cycles_render.py` under `python` (`nice -n 5` where available) on the scene `params`
    (`to_cycles`) and `jobs` (`{"name", "settings", "spp", "seeds"}`); returns `setup_s`, `version`, `threads`
    and per job `{"images", "times", "warmup_s"}` under `"jobs"`."""
    workdir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        job_path, out_path = Path(tmp) / "job.json", Path(tmp) / "out.npz"
        job_path.write_text(json.dumps({"scene": params, "jobs": jobs, "quiet": log is None}))
        cmd = [python, str(CYCLES_SCRIPT), str(job_path), str(out_path)]
        if os.name == "posix" and os.path.exists("/usr/bin/nice") and os.nice(0) < 5:
            cmd = ["/usr/bin/nice", "-n", str(5 - os.nice(0)), *cmd]
        sw = Stopwatch()
        p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        err_lines = []
        for line in p.stderr:
            if line.startswith("cycles ") and log is not None:
                log("  " + line.rstrip())
            elif "DeprecationWarning" not in line and "use_nodes" not in line:
                err_lines.append(line.rstrip())
        rc = p.wait(timeout=timeout)
        if rc != 0 or not out_path.exists():
            raise RuntimeError(f"Cycles failed (exit code {rc}): " + " | ".join(err_lines[-5:]))
        z = np.load(out_path)
        res = {"setup_s": float(z["setup_s"]), "version": str(z["version"]), "threads": int(z["threads"]),
               "process_s": sw.s, "jobs": []}
        for k in range(len(jobs)):
            res["jobs"].append({"images": z[f"images_{k}"], "times": z[f"times_{k}"],
                                "warmup_s": float(z[f"warmup_{k}"])})
    return res


def cycles_reference(params: dict, cfg: Config, python: str, cache_dir: Path, version: str, fresh: bool = False,
                     log=print) -> dict:
    """Cycles' converged reference (`REFERENCE_SETTING`, `ref_chunks` independent images), cached in `cache_dir`
    keyed by the scene parameters, the spp, the seed, Blender's version and the Cycles script."""
    key = digest({"params": params, "spp": cfg.ref_spp, "chunks": cfg.ref_chunks, "seed": cfg.seed,
                  "setting": SETTINGS[REFERENCE_SETTING], "version": version,
                  "script": hashlib.sha256(CYCLES_SCRIPT.read_bytes()).hexdigest()})
    path = cache_dir / f"cycles_ref_{params['width']}x{params['height']}_{cfg.ref_spp}spp_{key}.npz"
    if path.exists() and not fresh:
        z = np.load(path)
        chunks, times, cached = z["chunks"], z["times"], True
        log(f"  Cycles reference: cached {path.name}")
    else:
        per = cfg.ref_spp // cfg.ref_chunks
        seeds = [1_000_000 + 1000 * cfg.seed + i for i in range(cfg.ref_chunks)]
        r = run_cycles(params, [{"name": "reference", "settings": SETTINGS[REFERENCE_SETTING], "spp": per,
                                 "seeds": seeds}], python, cache_dir, log=log)
        chunks, times, cached = r["jobs"][0]["images"], r["jobs"][0]["times"], False
        save_npz(path, compressed=True, chunks=chunks, times=times)
    ref = reference_stats(chunks)
    return {**ref, "image": ref["image"].astype(np.float64), "spp": cfg.ref_spp, "render_s": float(np.sum(times)),
            "cached": cached, "file": path.name, "setting": REFERENCE_SETTING}


def error_stats(images, ref: dict) -> dict:
    """The corrected per-image RMSEs against `ref` (its own noise removed), relative to its mean: median (the
    statistic compared), mean-MSE (`benchmarks.bench_stats.expected_rmse`) and all of them."""
    e, se, per = expected_rmse(list(images), ref["image"], ref["rmse"])
    rel = [x / ref["mean"] for x in per]
    return {"median": float(np.median(rel)), "mean_mse": e / ref["mean"], "mean_mse_se": se / ref["mean"],
            "per_image": rel}


# ================================================================================================= measurement
def _jaxfog_side(sf, cfg: Config, cache_dir: Path, fresh: bool, log):
    """jaxfog's reference (`benchmarks.bench.reference_image`), a timer of ms/spp, and `draws(spp, n)`."""
    from benchmarks import bench

    n_pix = cfg.size * cfg.size
    fn = bench.jaxfog_render_fn(n_pix)  # as benchmarks.bench's strategy study (its reference cache key)
    bcfg = bench.Config(size=cfg.size, ref_spp=cfg.jax_ref_spp, ref_chunks=cfg.jax_ref_chunks, seed=cfg.seed)
    ref = bench.reference_image(sf, bcfg, cache_dir, fn, fresh=fresh, log=log)
    ref["image"] = np.asarray(ref["image"], np.float64)
    time_per_spp = bench.spp_timer(fn, sf.scene, cfg.seed, 8)
    time_per_spp()  # compiles the timing program
    return ref, time_per_spp, bench.timed_draws(sf.scene, cfg.seed, bench.STRATEGIES[bench.DEFAULT_STRATEGY])


def screen_settings(params: dict, cfg: Config, python: str, ref: dict, workdir: Path, log=print) -> dict:
    """Every setting of `cfg.settings`: `screen_images` images of `cycles_spp` spp in one Cycles process. Per
    setting: ms/spp, the median and mean-MSE relative errors, and `efficiency` = median^2 x time per image (time to
    a common error is proportional to it)."""
    jobs = [{"name": s, "settings": SETTINGS[s], "spp": cfg.cycles_spp,
             "seeds": [2_000_000 + 100_000 * cfg.seed + 1000 * j + i for i in range(cfg.screen_images)]}
            for j, s in enumerate(cfg.settings)]
    r = run_cycles(params, jobs, python, workdir, log=log)
    out = {"setup_s": r["setup_s"], "first_render_s": r["jobs"][0]["warmup_s"], "version": r["version"],
           "threads": r["threads"], "settings": {}}
    for s, jr in zip(cfg.settings, r["jobs"]):
        st = error_stats(jr["images"], ref)
        t = float(np.mean(jr["times"]))
        out["settings"][s] = {**SETTINGS[s], "images": len(jr["times"]), "spp": cfg.cycles_spp, "time_s": t,
                              "ms_per_spp": 1e3 * t / cfg.cycles_spp, "warmup_s": jr["warmup_s"],
                              "rel_rmse_median": st["median"], "rel_rmse_mean_mse": st["mean_mse"],
                              "rel_rmse_per_image": st["per_image"], "efficiency": st["median"] ** 2 * t,
                              "mean": float(jr["images"].mean())}
    best = min(out["settings"], key=lambda s: out["settings"][s]["efficiency"])
    for s, v in out["settings"].items():
        v["time_to_best_error_ratio"] = v["efficiency"] / out["settings"][best]["efficiency"]
    out["best"] = best
    return out


def equal_error(draws, ref: dict, target: float, n: int, t_cycles: float, max_spp: int, log=print) -> dict:
    """jaxfog's images at 1, 2, 3, ... spp (`n` each) until the median corrected relative RMSE against its own
    reference is <= `target` (Cycles' median relative error); the ratio is jaxfog's mean time per image over
    Cycles' (`t_cycles`)."""
    tries = []
    for spp in range(1, max_spp + 1):
        imgs, times = draws(spp, n)
        st = error_stats(imgs, ref)
        t = float(np.mean(times))
        tries.append({"spp": spp, "draws": n, "time_s": t, "time_s_median": float(np.median(times)),
                      "rel_rmse_median": st["median"], "rel_rmse_mean_mse": st["mean_mse"],
                      "rel_rmse_per_image": st["per_image"], "ratio": t / t_cycles})
        log(f"  jaxfog at {spp} spp ({n} images, {1e3 * t:.0f} ms each): median rel RMSE {st['median']:.3f} "
            f"(target {target:.3f})")
        if st["median"] <= target:
            return {"reached": True, "spp": spp, "time_s": t, "rel_rmse_median": st["median"],
                    "ratio": t / t_cycles, "tries": tries}
    return {"reached": False, "spp": None, "note": f"not reached within {max_spp} spp", "tries": tries}


def run_benchmark(cfg: Config, out: Path, python: str, version: str, fresh_ref: bool = False, log=print) -> dict:
    """The whole measurement (module docstring); writes `out/cycles.json` and returns the result."""
    from jaxfog.tools import max_rss_mib

    out.mkdir(parents=True, exist_ok=True)
    cache = out / "cache"
    sw = Stopwatch()
    sf = load(cfg.scene, cfg.size)
    params = to_cycles(sf.data, threads=cfg.threads)
    result = {"schema": 1, "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "machine": machine_info(),
              "config": dataclasses.asdict(cfg), "cycles_python": python, "blender_version": version,
              "cycles_params": params}
    log(f"{sf.name} {cfg.size}x{cfg.size}: jaxfog reference ({cfg.jax_ref_spp} spp)")
    jref, jax_time_per_spp, jax_draws = _jaxfog_side(sf, cfg, cache, fresh_ref, log)
    log(f"Cycles {version} reference ({cfg.ref_spp} spp in {cfg.ref_chunks} images, {REFERENCE_SETTING})")
    cref = cycles_reference(params, cfg, python, cache, version, fresh=fresh_ref, log=log)
    for name, r in (("jaxfog", jref), ("cycles", cref)):
        result[f"{name}_reference"] = {k: v for k, v in r.items() if k not in ("image", "chunks")}
    result["means"] = _means(jref, cref)

    log(f"Cycles settings: {', '.join(cfg.settings)} ({cfg.screen_images} images of {cfg.cycles_spp} spp each)")
    screen = screen_settings(params, cfg, python, cref, cache, log=log)
    result["screen"] = screen
    best = screen["best"]
    log(f"best setting: {best}; target: {cfg.draws} images of {cfg.cycles_spp} spp")
    t_before = jax_time_per_spp()
    tr = run_cycles(params, [{"name": best, "settings": SETTINGS[best], "spp": cfg.cycles_spp,
                              "seeds": [3_000_000 + 100_000 * cfg.seed + i for i in range(cfg.draws)]}],
                    python, cache, log=log)
    t_after = jax_time_per_spp()
    target, st = _target(tr, cfg, cref, best)
    result["cycles_target"] = target
    result["jaxfog_ms_per_spp"] = {"before": 1e3 * t_before, "after": 1e3 * t_after}
    log(f"jaxfog to Cycles' median error {st['median']:.3f} ({cfg.draws} images each)")
    t_cyc = target["time_s"]
    eq = equal_error(jax_draws, jref, st["median"], cfg.draws, t_cyc, cfg.max_jax_spp, log=log)
    if eq["reached"]:  # with jaxfog's ms/spp timed right before and after Cycles' images (no padding, same load)
        eq["ratio_adjacent"] = eq["spp"] * 0.5e-3 * (result["jaxfog_ms_per_spp"]["before"]
                                                    + result["jaxfog_ms_per_spp"]["after"]) / t_cyc
    result["equal_error"] = eq
    result["max_rss_mib_jaxfog"] = max_rss_mib()
    result["total_wall_s"] = sw.s
    write_json(out / "cycles.json", result)
    return result


def _means(jref: dict, cref: dict) -> dict:
    """The two references' image means side by side: their ratio with its standard error, and the 4 x 4 regions."""
    ratio = jref["mean"] / cref["mean"]
    return {"jaxfog": jref["mean"], "jaxfog_se": jref["mean_se"], "cycles": cref["mean"],
            "cycles_se": cref["mean_se"], "ratio_jaxfog_over_cycles": ratio,
            "ratio_se": ratio * math.hypot(jref["mean_se"] / jref["mean"], cref["mean_se"] / cref["mean"]),
            "blocks_jaxfog": block_means(jref["image"]).tolist(), "blocks_cycles": block_means(cref["image"]).tolist()}


def _target(tr: dict, cfg: Config, cref: dict, best: str) -> tuple[dict, dict]:
    """The target's record from its Cycles run `tr` (`draws` images of `cycles_spp` spp with the setting `best`), and
    its `error_stats` against Cycles' reference."""
    jt = tr["jobs"][0]
    st = error_stats(jt["images"], cref)
    t_cyc = float(np.mean(jt["times"]))
    return {"setting": best, **SETTINGS[best], "images": cfg.draws, "spp": cfg.cycles_spp, "time_s": t_cyc,
            "time_s_median": float(np.median(jt["times"])), "ms_per_spp": 1e3 * t_cyc / cfg.cycles_spp,
            "rel_rmse_median": st["median"], "rel_rmse_mean_mse": st["mean_mse"],
            "rel_rmse_per_image": st["per_image"], "setup_s": tr["setup_s"],
            "first_render_s": jt["warmup_s"], "process_s": tr["process_s"],
            "mean": mean_and_se(jt["images"].reshape(cfg.draws, -1).mean(1))}, st


# ====================================================================================================== output
def format_tables(r: dict) -> str:
    """The printed tables of a result."""
    cfg = r["config"]
    lines = [f"Blender Cycles {r['blender_version']} against jaxfog, {cfg['scene']} {cfg['size']}x{cfg['size']}, "
             f"{r['screen']['threads']} Cycles threads", "",
             f"Cycles settings ({cfg['screen_images']} images of {cfg['cycles_spp']} spp each; rel. RMSE = corrected "
             "per-pixel RMSE against Cycles' own reference / its mean):", "",
             format_table([{"setting": s + (" (best)" if s == r["screen"]["best"] else ""), **v}
                           for s, v in r["screen"]["settings"].items()],
                          [("setting", "setting"), ("volume_sampling", "volume_sampling"), ("guiding", "guiding"),
                           ("ms / spp", "ms_per_spp", ".1f"), ("median rel. RMSE", "rel_rmse_median", ".3f"),
                           ("mean-MSE rel. RMSE", "rel_rmse_mean_mse", ".3f"),
                           ("time to the best's error (x best)", "time_to_best_error_ratio", ".2f")], markdown=True)]
    t, eq, jm = r["cycles_target"], r["equal_error"], r["jaxfog_ms_per_spp"]
    lines += ["", f"Cycles setup: scene build {r['screen']['setup_s']:.2f} s, first render (BVH, kernels) "
              f"{r['screen']['first_render_s']:.2f} s", "",
              f"Target: Cycles {t['setting']}, {t['images']} images of {t['spp']} spp: {1e3 * t['time_s']:.0f} ms each "
              f"({t['ms_per_spp']:.1f} ms/spp), median rel. RMSE {t['rel_rmse_median']:.3f} "
              f"(mean-MSE {t['rel_rmse_mean_mse']:.3f})",
              f"jaxfog ms/spp right before / after Cycles: {jm['before']:.1f} / {jm['after']:.1f}"]
    if eq["reached"]:
        lines.append(f"jaxfog reaches it at {eq['spp']} spp: median rel. RMSE {eq['rel_rmse_median']:.3f}, "
                     f"{1e3 * eq['time_s']:.0f} ms per image; ratio jaxfog / Cycles time {eq['ratio']:.3f} "
                     f"({1 / eq['ratio']:.1f}x faster); with jaxfog's ms/spp from right before and after Cycles' "
                     f"images: {eq['ratio_adjacent']:.3f}")
    else:
        lines.append(f"jaxfog: {eq['note']}")
    m = r["means"]
    lines += ["", f"Image means (references): jaxfog {m['jaxfog']:.5f} ± {m['jaxfog_se']:.5f}, Cycles "
              f"{m['cycles']:.5f} ± {m['cycles_se']:.5f}, ratio jaxfog / Cycles {m['ratio_jaxfog_over_cycles']:.4f} "
              f"± {m['ratio_se']:.4f}"]
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench_cycles", description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="smoke run: 16 x 16, few spp")
    p.add_argument("--out", default=str(out_dir("cycles")), help="output folder (default bench_out/cycles)")
    p.add_argument("--cycles-python", default=None, metavar="PATH",
                   help="a Python with bpy (default: $JAXFOG_CYCLES_PYTHON, else this interpreter)")
    p.add_argument("--draws", type=int, default=None, help="independent images per renderer at equal error (>= 9)")
    p.add_argument("--cycles-spp", type=int, default=None, help="spp of each Cycles image (default 64)")
    p.add_argument("--settings", nargs="+", choices=tuple(SETTINGS), default=None, help="Cycles settings to try")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--fresh-ref", action="store_true", help="re-render the cached references")
    return p


def config_from_args(args) -> Config:
    cfg = with_args(QUICK if args.quick else FULL, args)
    if cfg.draws < 9 and not args.quick:
        raise ValueError(f"--draws {cfg.draws}: the median needs at least 9 images")
    return cfg


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        cfg = config_from_args(args)
    except ValueError as e:
        print(f"benchmarks.bench_cycles: error: {e}", file=sys.stderr)
        return 2
    python = args.cycles_python or default_cycles_python()
    try:
        version = check_cycles(python)
    except CyclesMissing as e:
        print(f"benchmarks.bench_cycles: error: {e}", file=sys.stderr)
        return 2
    from jaxfog import use_cpu_cores

    use_cpu_cores()
    out = Path(args.out)
    result = run_benchmark(cfg, out, python, version, fresh_ref=args.fresh_ref, log=stderr_log)
    print(format_tables(result))
    print("\n" + run_summary(f"{out / 'cycles.json'}", result))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
