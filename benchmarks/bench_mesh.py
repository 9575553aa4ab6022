"""Triangle-mesh benchmark: rays/s of the BVH against brute force, and ms/spp of a mesh scene against the analytic one.

    python -m benchmarks.bench_mesh                       # table on stdout, JSON in bench_out/mesh/bench_mesh.json
    python -m benchmarks.bench_mesh --counts 1000 10000   # fewer triangle counts

1. Rays/s: nearest hits of `--rays` (1024) rays, `vmap`-ed once (as in a render chunk), with a bumpy torus of about
   1k, 10k, 100k and 1M triangles (`data_synthetic/make_mesh_fog.torus_mesh`): by the BVH (`jaxfog.tools.mesh_nearest`,
   batched with lane compaction), by shadow rays of random lengths in [0.5, 5] (`mesh_occluded`, any hit), by the same
   walk under a plain `vmap` (no compaction) and by brute force over every triangle (brute force traces fewer rays at
   large counts, to bound memory and time: its cost is linear in rays). Rays start on a sphere of radius 3 around
   the torus and aim at random points of its bounding box. Also the BVH's build time and the device memory of the
   mesh's arrays. The BVH's hits are checked equal to brute force's (distances and shadow-ray answers).
2. ms/spp: spot_fog (`--size` pixels square) with its analytic sphere, and with the sphere replaced by an inscribed
   UV sphere of about 100k flat triangles; the two renders timed in turn (interleaved) after a warm-up (compile)
   render each, best of `--repeats` each, wall and process CPU time (CPU time is steadier on a shared machine).
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from .common import REPO, Stopwatch, command, interleave, load, out_dir, print_table, time_calls, write_json

sys.path.insert(0, str(REPO / "data_synthetic"))

DEFAULT_JSON = out_dir("mesh") / "bench_mesh.json"


def _grid(n_tris: int) -> tuple[int, int]:
    """Torus grid (nu, nv) with about n_tris = 2 nu nv triangles, nu = 3.5 nv."""
    nv = max(3, int(round((n_tris / 7) ** 0.5)))
    return int(round(n_tris / (2 * nv))), nv


def uv_sphere(nu, nv, r, center):
    th = np.linspace(0, np.pi, nv + 1)[1:-1]
    ph = 2 * np.pi * np.arange(nu) / nu
    T, P = np.meshgrid(th, ph, indexing="ij")
    ring = np.stack([np.sin(T) * np.cos(P), np.cos(T), np.sin(T) * np.sin(P)], -1).reshape(-1, 3)
    n = np.concatenate([[[0, 1, 0]], ring, [[0, -1, 0]]])
    j = np.arange(nu)
    f = [np.stack([0 * j, 1 + (j + 1) % nu, 1 + j], -1)]
    for i in range(nv - 2):
        a, b = 1 + i * nu + j, 1 + i * nu + (j + 1) % nu
        f += [np.stack([a, b, b + nu], -1), np.stack([a, b + nu, a + nu], -1)]
    last, base = len(n) - 1, 1 + (nv - 2) * nu
    f.append(np.stack([0 * j + last, base + j, base + (j + 1) % nu], -1))
    return n * r + np.asarray(center), np.concatenate(f)


def _rays(v, n_rays, rng):
    """Rays from a sphere of radius 3 toward random points of the mesh's bounding box, and random shadow-ray
    lengths in [0.5, 5]."""
    import jax.numpy as jnp

    o = rng.normal(size=(n_rays, 3))
    o = 3.0 * o / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.uniform(v.min(0), v.max(0), (n_rays, 3)) - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    lim = rng.uniform(0.5, 5.0, n_rays)
    return jnp.asarray(o, jnp.float32), jnp.asarray(d, jnp.float32), jnp.asarray(lim, jnp.float32)


def rays_per_second(counts, n_rays, repeats, seed=0) -> list[dict]:
    import jax

    import jaxfog as jf
    from jaxfog.tools import brute_force_nearest, mesh_nearest, mesh_occluded
    from make_mesh_fog import torus_mesh

    rng = np.random.default_rng(seed)
    rows = []
    for count in counts:
        v, f = torus_mesh(*_grid(count))
        o, d, lim = _rays(v, n_rays, rng)
        with Stopwatch() as build:
            mesh = jf.Mesh.from_arrays(v, f, jf.Diffuse(0.5))
        nbytes = sum(x.nbytes for x in jax.tree.leaves(mesh) if hasattr(x, "nbytes"))
        nearest = jax.jit(jax.vmap(lambda a, b: mesh_nearest(mesh, a, b)))
        shadow = jax.jit(jax.vmap(lambda a, b, c: mesh_occluded(mesh, a, b, c)))
        # the same walk vectorized per ray, without lane compaction
        plain = jax.jit(jax.vmap(lambda a, b: mesh_nearest(mesh, a, b, compaction=False)))
        times = interleave({"nearest": lambda _: jax.block_until_ready(nearest(o, d)),
                            "shadow": lambda _: jax.block_until_ready(shadow(o, d, lim)),
                            "plain": lambda _: jax.block_until_ready(plain(o, d))}, repeats)
        times = {k: (t["min_s"], t["min_cpu_s"]) for k, t in times.items()}
        tb, sb = nearest(o, d)
        tp, sp = plain(o, d)
        assert np.array_equal(np.asarray(tb), np.asarray(tp)) and np.array_equal(np.asarray(sb), np.asarray(sp))
        row = {"triangles": int(len(f)), "rays": n_rays, "bvh_rays_per_s": n_rays / times["nearest"][0],
               "shadow_rays_per_s": n_rays / times["shadow"][0], "plain_vmap_rays_per_s": n_rays / times["plain"][0],
               "build_s": build.s, "mesh_bytes": int(nbytes), "stack_size": mesh.stack_size,
               "rows": int(mesh.rows.shape[0]), "leaves": mesh.n_leaves,
               "hit_fraction": float(np.isfinite(np.asarray(tb)).mean()),
               "shadow_blocked_fraction": float(np.asarray(shadow(o, d, lim)).mean())}
        n_bf = int(max(8, min(n_rays, 2**30 // (len(f) * 64))))  # bounded intermediates
        bf = jax.jit(jax.vmap(lambda a, b: brute_force_nearest(mesh, a, b)))
        t_bf = time_calls(lambda _: jax.block_until_ready(bf(o[:n_bf], d[:n_bf])), max(1, repeats // 2))["min_s"]
        tr, _ = bf(o[:n_bf], d[:n_bf])
        assert np.array_equal(np.asarray(tr), np.asarray(tb)[:n_bf]), "BVH and brute force disagree"
        occ = np.asarray(shadow(o, d, lim))[:n_bf]
        assert np.array_equal(occ, np.asarray(tr) < np.asarray(lim)[:n_bf]), "shadow rays and brute force disagree"
        row.update(brute_rays=n_bf, brute_rays_per_s=n_bf / t_bf, speedup=row["bvh_rays_per_s"] / (n_bf / t_bf))
        rows.append(row)
        print(f"  {row['triangles']} triangles: {row['bvh_rays_per_s']:.4g} rays/s", flush=True)
    return rows


def ms_per_spp(size, spp, repeats, n_tris) -> dict:
    import jax

    import jaxfog as jf

    sf = load("spot_fog", size)
    scene = sf.scene
    sph = scene.shapes[1]
    nv = int(round((n_tris / 4) ** 0.5))
    v, f = uv_sphere(2 * nv, nv, float(sph.radius), np.asarray(sph.center, np.float64))
    mesh = jf.Mesh.from_arrays(v, f, sph.bsdf)
    mesh_scene = jf.Scene(camera=scene.camera, shapes=(scene.shapes[0], mesh), lights=scene.lights,
                          medium=scene.medium, max_depth=scene.max_depth)
    out = {"size": size, "spp": spp, "mesh_triangles": int(len(f)), "repeats": repeats}
    scenes = {"analytic": scene, "mesh": mesh_scene}
    key = jax.random.key(0)
    times = interleave({k: (lambda _, s=s: jax.block_until_ready(jf.render(s, key, spp))) for k, s in scenes.items()},
                       repeats)
    times = {k: (t["min_s"], t["min_cpu_s"]) for k, t in times.items()}
    for name, s in scenes.items():
        img = np.asarray(jf.render(s, key, spp))
        out[f"{name}_ms_per_spp"] = 1e3 * times[name][0] / spp
        out[f"{name}_cpu_ms_per_spp"] = 1e3 * times[name][1] / spp
        out[f"{name}_mean"] = float(img.mean())
        print(f"{name:>9}: {1e3 * times[name][0] / spp:8.1f} ms/spp wall, {1e3 * times[name][1] / spp:8.1f} CPU ms/spp "
              f"({size}x{size}, mean pixel {img.mean():.5f})", flush=True)
    out["ratio"] = out["mesh_ms_per_spp"] / out["analytic_ms_per_spp"]
    out["cpu_ratio"] = out["mesh_cpu_ms_per_spp"] / out["analytic_cpu_ms_per_spp"]
    print(f"    ratio: {out['ratio']:.2f}x wall, {out['cpu_ratio']:.2f}x CPU time (target <= 3x)")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--counts", type=int, nargs="*", default=[1000, 10000, 100000, 1000000])
    ap.add_argument("--rays", type=int, default=1024)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--size", type=int, default=64, help="spot_fog image size for ms/spp")
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--scene-triangles", type=int, default=100000)
    ap.add_argument("--json", default=str(DEFAULT_JSON))
    args = ap.parse_args(argv)
    import jaxfog as jf

    jf.use_cpu_cores()
    rows = rays_per_second(args.counts, args.rays, args.repeats) if args.counts else []
    print_table(rows, [("triangles", "triangles"), ("nearest/s", "bvh_rays_per_s", ".4g"),
                       ("shadow/s", "shadow_rays_per_s", ".4g"), ("plain vmap/s", "plain_vmap_rays_per_s", ".4g"),
                       ("brute/s", "brute_rays_per_s", ".4g"), ("speedup", "speedup", lambda v: f"{v:.1f}x"),
                       ("build s", "build_s", ".2f"), ("mesh MiB", lambda r: r["mesh_bytes"] / 2**20, ".1f"),
                       ("stack", "stack_size")])
    scene = ms_per_spp(args.size, args.spp, args.repeats, args.scene_triangles)
    write_json(args.json, {"date": time.strftime("%Y-%m-%d"), "rays": rows, "scene": scene,
                           "command": command("python -m benchmarks.bench_mesh", argv)})
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
