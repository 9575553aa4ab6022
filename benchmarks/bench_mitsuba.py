"""The Mitsuba 3 side of `benchmarks.bench` (optional extra: `pip install -e ".[compare]"`).

The scene conversion is the library's `jaxfog.to_mitsuba` (mapping: `docs/conventions.md`, "Mitsuba 3"). Here
Mitsuba runs its LLVM backend (`VARIANT`), the fast one, which the speed comparison needs, unless `--variant` names
another (`scalar_rgb` where Dr.Jit's LLVM backend aborts, as on machines whose libLLVM cannot select `fminimum`).

Run as a program (`python -m benchmarks.bench_mitsuba SCENE.json --out X.npz`), it renders `--chunks` independent
images of `--spp` samples each (seeds 0, 1, ...) after one warm-up render that compiles the kernels, and writes the
images, the time of each render (s), the warm-up time (s) and the process's peak resident memory (MiB) to an `.npz`.
`run_mitsuba` runs it in a subprocess (for `benchmarks.bench` and `benchmarks.bench_cost`) so that its memory and
threads are measured apart from JAX's, and so that a missing or broken Mitsuba (or an LLVM backend that aborts the
process) only skips the comparison.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np

from benchmarks.common import save_npz, scene_path, subprocess_env, time_calls
from jaxfog import to_mitsuba
from jaxfog.tools import import_mitsuba as _import_mitsuba
from jaxfog.tools import max_rss_mib

VARIANT = "llvm_ad_rgb"


def import_mitsuba(variant: str = VARIANT):
    """`(mi, None)` with `variant` set (default the LLVM RGB variant), or `(None, reason)` when Mitsuba 3 or that
    variant is missing."""
    try:
        return _import_mitsuba(variant), None
    except ImportError as e:
        return None, (f"{e}; its LLVM backend needs libllvm19 (apt-get install -y libllvm19) and DRJIT_LIBLLVM_PATH"
                      if "variant" in str(e) else str(e))


def render_chunks(data: dict, spp: int, chunks: int, seed0: int = 0, log=None, variant: str = VARIANT) -> dict:
    """Render `chunks` independent `spp`-sample images of the scene (seeds `seed0 + i`) after one warm-up render.

    Returns `images` `(chunks, H, W, 3)` float32, `times` (s, each render until its pixels are on the host),
    `warmup_s` (the first render: kernel tracing and LLVM compilation included), `version`, `variant`, `threads`."""
    mi, reason = import_mitsuba(variant)
    if mi is None:
        raise RuntimeError(reason)
    import drjit as dr

    scene = mi.load_dict(to_mitsuba(data, spp=spp))
    t = time_calls(lambda i: np.asarray(mi.render(scene, spp=spp, seed=seed0 + i), np.float32)[..., :3], chunks,
                   keep=True)
    if log is not None:
        for i, (img, s) in enumerate(zip(t["values"], t["wall_s"])):
            log(f"mitsuba chunk {i + 1}/{chunks}: {spp} spp in {s:.2f} s, mean {img.mean():.4g}")
    try:
        threads = int(dr.thread_count())
    except Exception:  # pragma: no cover - older drjit
        threads = -1
    return {"images": np.stack(t["values"]), "times": np.asarray(t["wall_s"]), "warmup_s": t["first_call_s"],
            "version": mi.__version__, "variant": variant, "threads": threads}


def run_mitsuba(name: str, size: int | None, spp: int, chunks: int, workdir: Path, python: str = sys.executable,
                env: dict | None = None, timeout: float = 1800, seed0: int = 0, variant: str | None = None) -> dict:
    """Renders the scene `name` (a shipped scene or a `.json` path) at `size x size` pixels (None: the file's) in
    Mitsuba 3 in a subprocess (this module as a program): the `.npz` fields (images, times, memory; Mitsuba seeds
    `seed0`, `seed0 + 1`, ...) as a dict, or `{"skipped": reason}` when Mitsuba (or its LLVM backend) is not
    there or the process fails."""
    workdir.mkdir(parents=True, exist_ok=True)
    out = workdir / f"mitsuba_{Path(name).stem}_{size}.npz"
    out.unlink(missing_ok=True)
    sets = [] if size is None else ["--set", f"camera.width={size}", "--set", f"camera.height={size}"]
    cmd = [python, "-m", "benchmarks.bench_mitsuba", str(scene_path(name)), *sets, "--spp", str(spp), "--chunks",
           str(chunks), "--seed", str(seed0), "--out", str(out), "--quiet"] + ([] if variant is None else
                                                                            ["--variant", variant])
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, env=subprocess_env(env), timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"skipped": f"Mitsuba did not finish within {timeout:.0f} s"}
    if p.returncode != 0 or not out.exists():
        lines = [x.strip() for x in (p.stderr or "").strip().splitlines() if x.strip()]
        reason = lines[-1] if lines else f"exit code {p.returncode}"
        if p.returncode < 0 or p.returncode > 128:  # killed by a signal, e.g. an LLVM backend that aborts
            first = next((x for x in lines if "error" in x.lower()), reason)
            reason = f"Mitsuba's process died (exit code {p.returncode}): {first[:200]}"
        return {"skipped": reason.replace("mitsuba skipped: ", "")}
    with np.load(out) as z:
        res = {k: z[k] for k in z.files}
    out.unlink()
    return res


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench_mitsuba", description=__doc__.split("\n\n")[0])
    p.add_argument("scene", metavar="SCENE.json")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--spp", type=int, default=16, help="samples per pixel of each render (default 16)")
    p.add_argument("--chunks", type=int, default=4, help="independent renders (default 4)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, metavar="OUT.npz")
    p.add_argument("--variant", default=VARIANT, help=f"Mitsuba variant (default {VARIANT})")
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)

    mi, reason = import_mitsuba(args.variant)
    if mi is None:
        print(f"mitsuba skipped: {reason}", file=sys.stderr)
        return 3
    from jaxfog import load_scene

    sf = load_scene(args.scene, args.overrides)
    log = None if args.quiet else (lambda s: print(s, file=sys.stderr, flush=True))
    res = render_chunks(sf.data, args.spp, args.chunks, args.seed, log=log, variant=args.variant)
    save_npz(args.out, images=res["images"], times=res["times"], warmup_s=res["warmup_s"], version=res["version"],
             variant=res["variant"], threads=res["threads"], max_rss_mib=max_rss_mib(), spp=args.spp)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
