"""The Mitsuba 3 side of `benchmarks.bench` (optional extra: `pip install -e ".[compare]"`).

The scene conversion is the library's `jaxfog.to_mitsuba` (mapping: `docs/conventions.md`, "Mitsuba 3"). Here
Mitsuba runs its LLVM backend (`VARIANT`), the fast one, which the speed comparison needs, unless `--variant` names
another (`scalar_rgb` where Dr.Jit's LLVM backend aborts, as on machines whose libLLVM cannot select `fminimum`).

Run as a program (`python -m benchmarks.bench_mitsuba SCENE.json --out X.npz`), it renders `--chunks` independent
images of `--spp` samples each (seeds 0, 1, ...) after one warm-up render that compiles the kernels, and writes the
images, the time of each render, the warm-up time and the process's peak resident memory to an `.npz`.
`benchmarks.bench` runs it in a subprocess so that its memory and threads are measured apart from JAX's, and so that
a missing or broken Mitsuba (or an LLVM backend that aborts the process) only skips the comparison.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from benchmarks.common import save_npz
from jaxfog.tools import max_rss_mib
from jaxfog import to_mitsuba
from jaxfog.tools import import_mitsuba as _import_mitsuba

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
    t0 = time.perf_counter()
    np.asarray(mi.render(scene, spp=spp, seed=10_000_019))
    warmup = time.perf_counter() - t0
    images, times = [], []
    for i in range(chunks):
        t0 = time.perf_counter()
        img = np.asarray(mi.render(scene, spp=spp, seed=seed0 + i), dtype=np.float32)
        times.append(time.perf_counter() - t0)
        images.append(img[..., :3])
        if log is not None:
            log(f"mitsuba chunk {i + 1}/{chunks}: {spp} spp in {times[-1]:.2f} s, mean {img[..., :3].mean():.4g}")
    try:
        threads = int(dr.thread_count())
    except Exception:  # pragma: no cover - older drjit
        threads = -1
    return {"images": np.stack(images), "times": np.asarray(times), "warmup_s": warmup, "version": mi.__version__,
            "variant": variant, "threads": threads}


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
