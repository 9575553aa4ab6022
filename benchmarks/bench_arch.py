"""One process's cost of rendering a scene (default spot_fog, 128 x 128, max_depth 8): the first call (compile and
1 spp) and 16 spp in one call after a warm-up, in wall and CPU seconds; prints one JSON line.

    python -m benchmarks.bench_arch [SCENE.json]

Run it for two checkouts in turn (A B A B ..., e.g. with `PYTHONPATH=<checkout>`) and compare the runs pair by pair:
docs/results/architecture/README.md.
"""
import argparse
import sys


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.bench_arch", description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", nargs="?", metavar="SCENE.json", help="the scene file (default spot_fog)")
    args = ap.parse_args(argv)
    import jaxfog as jf

    jf.use_cpu_cores()
    import jax

    from benchmarks.common import print_json, scene_path, time_calls

    sf = jf.load_scene(args.scene or scene_path("spot_fog"))
    first = time_calls(lambda _: jf.render(sf.scene, jax.random.key(0), 1).block_until_ready(), 1, warmup=0)
    jf.render(sf.scene, jax.random.key(1), 4).block_until_ready()  # warm-up
    t = time_calls(lambda _: jf.render(sf.scene, jax.random.key(2), 16).block_until_ready(), 1, warmup=0)
    print_json({"code": jf.__file__, "first_call_s": first["wall_s"][0], "first_call_cpu_s": first["cpu_s"][0],
                "ms_per_spp": t["wall_s"][0] / 16 * 1e3, "cpu_ms_per_spp": t["cpu_s"][0] / 16 * 1e3})
    return 0


if __name__ == "__main__":
    sys.exit(main())
