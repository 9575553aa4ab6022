"""One process's cost of rendering a scene (default spot_fog, 128 x 128, max_depth 8): the first call (compile and
1 spp) and 16 spp in one call after a warm-up, in wall and CPU seconds; prints one JSON line.

    python -m benchmarks.bench_arch [SCENE.json]

Run it for two checkouts in turn (A B A B ..., e.g. with `PYTHONPATH=<checkout>`) and compare the runs pair by pair:
docs/results/architecture/README.md.
"""
import json, sys, time
import jaxfog as jf
jf.use_cpu_cores()
import jax
sf = jf.load_scene(sys.argv[1] if len(sys.argv) > 1 else "data_synthetic/scenes/spot_fog.json")
t0, c0 = time.perf_counter(), time.process_time()
jf.render(sf.scene, jax.random.key(0), 1).block_until_ready()
first, first_cpu = time.perf_counter() - t0, time.process_time() - c0
jf.render(sf.scene, jax.random.key(1), 4).block_until_ready()
t0, c0 = time.perf_counter(), time.process_time()
jf.render(sf.scene, jax.random.key(2), 16).block_until_ready()
ms, ms_cpu = (time.perf_counter() - t0) / 16 * 1e3, (time.process_time() - c0) / 16 * 1e3
print(json.dumps({"code": jf.__file__, "first_call_s": first, "first_call_cpu_s": first_cpu, "ms_per_spp": ms,
                  "cpu_ms_per_spp": ms_cpu}))
