"""Reverse mode of unbounded paths (path replay) against the fixed depth's scan + checkpoint: memory and time.

For the spot_fog scene at each (size, spp), the derivative of the mean image with respect to the medium's
(sigma_t, g, albedo) (`benchmarks.bench_grad.theta0`):

- memory: XLA's `memory_analysis()` of the jitted program (temporary buffers), for reverse mode at fixed depths
  (`--depths`, a `lax.scan` over bounces with a `jax.checkpoint`ed body) and unbounded (replay), and for the
  unbounded forward render and forward mode (`jax.jacfwd`);
- time: the unbounded programs (render, `jax.jacfwd`, `jax.grad`) and the depth-8 `jax.grad`, interleaved in
  `--rounds` rounds after compilation; each round's ratio to the unbounded render, medians over rounds.

Every render is one compiled call (`batch_paths` = all paths), one device. Run from the repository root:
`python -m benchmarks.bench_replay` (prints the tables and writes the JSON to `--out`, default
`bench_out/bench_replay/bench_replay.json`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from benchmarks.bench_grad import load_scene, theta0, with_theta
from benchmarks.common import command, compile_timed, interleave, memory_dict, out_dir, print_table, write_json

OUT = out_dir("bench_replay") / "bench_replay.json"


def programs(size: int, spp: int, depths: list[int], forward_only: bool = False) -> dict:
    """name -> jitted function of theta (`forward_only`: the unbounded render and jacfwd only, which also run on
    a jaxfog without the replay, for a before/after comparison of forward mode)."""
    import jax
    import jax.numpy as jnp

    import jaxfog as jf

    key = jax.random.key(0)
    out = {}
    for depth in ([-1] if forward_only else [*depths, -1]):
        scene = load_scene("spot_fog", size, depth)
        render = lambda t, scene=scene: jf.render(with_theta(scene, t), key, spp, batch_paths=size * size * spp,
                                                  devices=1)
        mean = lambda t, render=render: jnp.mean(render(t))
        tag = "unbounded" if depth == -1 else f"depth {depth}"
        if not forward_only:
            out[f"{tag} grad"] = jax.jit(jax.grad(mean))
        if depth == -1 or depth == 8:
            out[f"{tag} render"] = jax.jit(render)
            out[f"{tag} jacfwd"] = jax.jit(jax.jacfwd(mean))
        if depth == -1:  # the value too (as the fit asks for it): the primal output is then used
            both = lambda t, mean=mean: (lambda m: (m, m))(mean(t))
            out[f"{tag} jacfwd+value"] = jax.jit(jax.jacfwd(both, has_aux=True))
    return out


def measure(size: int, spp: int, depths: list[int], rounds: int, forward_only: bool = False, log=print) -> dict:
    import jax
    import jax.numpy as jnp

    theta = jnp.asarray(theta0(load_scene("spot_fog", size, 8)))
    res = {"size": size, "spp": spp, "paths": size * size * spp, "programs": {}}
    compiled = {}
    for name, fn in programs(size, spp, depths, forward_only).items():
        compiled[name], t_c = compile_timed(fn, theta)
        res["programs"][name] = {"compile_s": t_c, "xla": memory_dict(compiled[name].memory_analysis()), "run_s": []}
        log(f"  {size}x{size} {spp} spp  {name:18s} compile {t_c:6.1f} s  temp "
            f"{res['programs'][name]['xla']['temp_mib']:8.2f} MiB")
    timed = ["unbounded render"] + [n for n in compiled if n.startswith("unbounded") and n != "unbounded render"
                                    or n in ("depth 8 grad", "depth 8 render")]
    runs = interleave({n: (lambda _, c=compiled[n]: jax.block_until_ready(c(theta))) for n in timed}, rounds,
                      keep=True)
    for name, t in runs.items():
        res["programs"][name].update(run_s=t["wall_s"], median_s=t["median_s"],
                                     ratio_to_unbounded_render=t["ratio_median"])
    if forward_only:
        return res
    g_rev, g_fwd = (np.asarray(runs[n]["values"][-1]) for n in ("unbounded grad", "unbounded jacfwd"))
    res["unbounded_grad_minus_jacfwd"] = {"grad": g_rev, "jacfwd": g_fwd,
                                          "max_rel": float(np.max(np.abs(g_rev - g_fwd)) / np.max(np.abs(g_fwd)))}
    return res


def print_tables(result: dict) -> None:
    """The Markdown table of every program of every run, then the check of reverse mode against forward mode."""
    rows = [{"config": f"{r['size']}x{r['size']}, {r['spp']} ({r['paths']})", "program": name, **p}
            for r in result["runs"] for name, p in r["programs"].items()]
    print_table(rows, [("image, spp (paths)", "config"), ("program", "program"),
                       ("XLA temp, MiB", lambda p: p["xla"]["temp_mib"], ".2f"), ("compile, s", "compile_s", ".1f"),
                       ("run, s (median)", "median_s", ".3f"),
                       ("run / unbounded render", "ratio_to_unbounded_render", ".2f")], markdown=True)
    print()
    for r in result["runs"]:
        if "unbounded_grad_minus_jacfwd" in r:
            d = r["unbounded_grad_minus_jacfwd"]
            print(f"{r['size']}x{r['size']} {r['spp']} spp: unbounded grad {np.round(d['grad'], 6).tolist()}, "
                  f"jacfwd {np.round(d['jacfwd'], 6).tolist()}, max |diff| / max |jacfwd| = {d['max_rel']:.2e}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", default="16x4,32x8", help="comma-separated SIZExSPP (default 16x4,32x8)")
    ap.add_argument("--depths", default="8,32", help="fixed depths whose reverse mode is compiled (default 8,32)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--forward-only", action="store_true", help="only the unbounded render and jax.jacfwd")
    args = ap.parse_args(argv)
    import jaxfog as jf

    depths = [int(d) for d in args.depths.split(",")]
    result = {"jaxfog": jf.__file__, "argv": sys.argv[1:] if argv is None else argv, "depths": depths, "runs": [],
              "command": command("python -m benchmarks.bench_replay", argv)}
    for cfg in args.configs.split(","):
        size, spp = (int(x) for x in cfg.split("x"))
        result["runs"].append(measure(size, spp, depths, args.rounds, args.forward_only))
    write_json(args.out, result)
    print_tables(result)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
