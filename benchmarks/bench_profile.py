"""Where the forward renderer's time goes on the headline scene.

    python -m benchmarks.bench_profile [--quick] [--out DIR] [--scene PATH] [--spp N] [--reps N]

Times `jaxfog.render(scene, key, spp)` after compiling (the first call of each configuration, compile included, is
reported apart) for: (a) `batch_paths` (paths per compiled call); (b) `chunk_paths` (paths traced together in one
vectorized pass; 16384 = a whole 128x128 layer at once); (c) feature ablations at the
default batch: equiangular off, light_lobe 0, distance_mix 0, all three off, max_depth 2 / 4 / 8; (d) components:
the random numbers alone (threefry uniforms of one sample layer); (e) with every CPU core a JAX device (the
default of the command-line tools), the same render on one device.

The machine may be shared, so configurations are interleaved (A, B, C, A, B, C, ...) and medians are compared as
ratios to the default inside one run; never compare absolute times across runs. Writes `profile.json` to `--out`
(default `bench_out/profile` in the repository) and prints a table (ms per spp = one sample of every pixel of the
whole image).
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

import jax
import jax.numpy as jnp

import jaxfog as jf
from benchmarks.common import interleave, machine_info, out_dir, print_table, scene_path, write_json
from jaxfog import tools
from jaxfog.tools import n_dims, n_iterations, uniforms

SCENE = "spot_fog"
OUT = out_dir("profile")


def _configs(quick: bool):
    """(group, name, overrides, render kwargs); the row named "default" is the reference of every ratio."""
    rows = [("ablation", "default", [], {})]
    if jax.local_device_count() > 1:  # every core a device (use_cpu_cores, as the entry points do) vs one of them
        rows += [("devices", "devices=1", [], {"devices": 1})]
    if not quick:
        rows += [("batch", f"batch_paths={b}", [], {"batch_paths": b}) for b in (4096, 16384, 65536, 262144)]
    chunks = (16384, 1024) if quick else (16384, 4096, 2048, 1024, 512, 256)
    rows += [("chunk", f"chunk_paths={c}", [], {"chunk_paths": c}) for c in chunks]
    rows += [
        ("ablation", "equiangular=False", [], {"equiangular": False}),
        ("ablation", "light_lobe=0", [], {"light_lobe": 0.0}),
        ("ablation", "distance_mix=0", [], {"distance_mix": 0.0}),
        ("ablation", "all three off", [], {"equiangular": False, "light_lobe": 0.0, "distance_mix": 0.0}),
    ]
    depths = (2,) if quick else (2, 4, 8)
    rows += [("depth", f"max_depth={d}", [f"integrator.max_depth={d}"], {}) for d in depths]
    if quick:
        rows = [r for r in rows if r[1] in ("default", "chunk_paths=16384", "chunk_paths=1024", "all three off",
                                            "max_depth=2", "devices=1")]
    return rows


def _rng_fn(scene, spp):
    """The random numbers `render` draws for `spp` layers (same shapes and key derivation), summed."""
    cam = scene.camera
    n_pix, n_iter, K = cam.width * cam.height, n_iterations(scene), n_dims(scene)

    @jax.jit
    def f(key):
        def one(layer_id):
            k_pix, k_path = jax.random.split(jax.random.fold_in(key, layer_id))
            return uniforms(k_pix, n_pix, 2).sum() + uniforms(k_path, n_pix, n_iter * K).sum()

        return jax.lax.map(one, jnp.arange(spp, dtype=jnp.uint32)).sum()

    return f


def table_rows(rows: list, times: dict, spp: int, n_pix: int) -> list[dict]:
    """Per configuration of `rows` and for the random numbers alone, from `interleave`'s `times` of `spp` spp: ms/spp
    (median and every repetition), paths/s, the ratio to the "default" row, the first call and the compile time it
    suggests (the first call less a timed one)."""
    ms = {k: [x / spp * 1e3 for x in t["wall_s"]] for k, t in times.items()}
    ref = statistics.median(ms["default"])
    out_rows = []
    for r in rows:
        med = statistics.median(ms[r["name"]])
        first = times[r["name"]]["first_call_s"]
        out_rows.append({
            "group": r["group"], "name": r["name"], "overrides": r["overrides"], "kwargs": r["kwargs"],
            "layers_per_call": tools.layers_per_batch(
                r["scene"], spp, r["kwargs"].get("batch_paths", tools.DEFAULT_BATCH_PATHS)),
            "ms_per_spp_median": med, "ms_per_spp": ms[r["name"]], "paths_per_s": n_pix / (med / 1e3),
            "ratio_to_default": med / ref, "first_call_s": first,
            "compile_s_estimate": max(0.0, first - med * spp / 1e3),
        })
    rng_med = statistics.median(ms["random numbers only"])
    out_rows.append({"group": "component", "name": "random numbers only", "overrides": [], "kwargs": {},
                     "layers_per_call": spp, "ms_per_spp_median": rng_med, "ms_per_spp": ms["random numbers only"],
                     "paths_per_s": n_pix / (rng_med / 1e3), "ratio_to_default": rng_med / ref,
                     "first_call_s": None, "compile_s_estimate": None})
    return out_rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="few configurations, 4 spp, 2 repetitions (a smoke test)")
    ap.add_argument("--out", default=str(OUT), help="output folder (default bench_out/profile in the repository)")
    ap.add_argument("--scene", default=SCENE, help="a shipped scene's name or a .json path (default spot_fog)")
    ap.add_argument("--spp", type=int, default=None, help="samples per pixel per timing (default 16; quick 4)")
    ap.add_argument("--reps", type=int, default=None, help="interleaved repetitions (default 3; quick 2)")
    args = ap.parse_args(argv)
    jf.use_cpu_cores()  # every CPU core a device, as the command-line entry points do (a no-op once JAX has started)
    machine = machine_info()
    spp = args.spp or (4 if args.quick else 16)
    reps = args.reps or (2 if args.quick else 3)
    key = jax.random.key(0)

    rows = []
    for group, name, overrides, kw in _configs(args.quick):
        scene = jf.load_scene(scene_path(args.scene), overrides=overrides).scene
        rows.append({"group": group, "name": name, "overrides": overrides, "kwargs": kw, "scene": scene})
    cam = rows[0]["scene"].camera
    n_pix = cam.width * cam.height

    # the configurations and the random numbers alone in turn, after a first call each (compile and one render;
    # configurations sharing a compiled program compile once)
    fns = {r["name"]: (lambda _, r=r: jf.render(r["scene"], key, spp, **r["kwargs"]).block_until_ready()) for r in rows}
    rng = _rng_fn(rows[0]["scene"], spp)
    fns["random numbers only"] = lambda _: rng(key).block_until_ready()
    out_rows = table_rows(rows, interleave(fns, reps, log=print), spp, n_pix)

    print(f"\n{args.scene}: {cam.width}x{cam.height}, {spp} spp per timing, {reps} interleaved repetitions (medians)")
    print_table(out_rows, [("group", "group"), ("configuration", "name"), ("layers/call", "layers_per_call"),
                           ("ms/spp", "ms_per_spp_median", ".1f"),
                           ("Mpaths/s", lambda o: o["paths_per_s"] / 1e6, ".3f"),
                           ("ratio", "ratio_to_default", ".2f"), ("first call s", "first_call_s", ".1f")])

    out = Path(args.out)
    meta = {"scene": args.scene, "spp_per_timing": spp, "reps": reps, "quick": args.quick,
            "default_batch_paths": tools.DEFAULT_BATCH_PATHS, "default_chunk_paths": tools.DEFAULT_CHUNK_PATHS,
            "machine": machine,
            "note": "medians of interleaved repetitions; ratios are to the 'default' row of this run only"}
    write_json(out / "profile.json", {"meta": meta, "rows": out_rows, "machine": machine})  # adds its loadavg_end
    print(f"wrote {out / 'profile.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
