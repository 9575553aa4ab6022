"""Triangle-mesh benchmark: rays/s of the BVH against brute force, and ms/spp of a mesh scene against the analytic one.

    python -m benchmarks.bench_mesh                       # table on stdout, JSON in docs/results/mesh/bench_mesh.json
    python -m benchmarks.bench_mesh --counts 1000 10000   # fewer triangle counts

1. Rays/s: nearest hits of `--rays` (1024) rays, `vmap`-ed once (as in a render chunk), with a bumpy torus of about
   1k, 10k, 100k and 1M triangles (`data_synthetic/make_mesh_fog.torus_mesh`), by BVH traversal and by brute force
   over every triangle (brute force traces fewer rays at large counts, to bound memory and time: its cost is linear
   in rays). Rays start on a sphere of radius 3 around the torus and aim at random points of its bounding box. Also
   the BVH's build time and the device memory of the mesh's arrays.
2. ms/spp: spot_fog (`--size` pixels square) with its analytic sphere, and with the sphere replaced by an inscribed
   UV sphere of about 100k flat triangles; best of `--repeats` timed renders after a warm-up (compile) render.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from .common import REPO, load, machine_info, write_json

sys.path.insert(0, str(REPO / "data_synthetic"))

DEFAULT_JSON = REPO / "docs" / "results" / "mesh" / "bench_mesh.json"


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


def _best(fn, repeats):
    fn()  # warm-up: compile
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return min(ts)


def rays_per_second(counts, n_rays, repeats, leaf_sizes, seed=0) -> list[dict]:
    import jax
    import jax.numpy as jnp

    import jaxfog as jf
    from jaxfog._mesh import brute_force_nearest, mesh_nearest
    from make_mesh_fog import torus_mesh

    rng = np.random.default_rng(seed)
    rows = []
    for count in counts:
        v, f = torus_mesh(*_grid(count))
        o = rng.normal(size=(n_rays, 3))
        o = 3.0 * o / np.linalg.norm(o, axis=1, keepdims=True)
        lo, hi = v.min(0), v.max(0)
        d = rng.uniform(lo, hi, (n_rays, 3)) - o
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        o, d = jnp.asarray(o, jnp.float32), jnp.asarray(d, jnp.float32)
        for leaf in leaf_sizes:
            t0 = time.perf_counter()
            mesh = jf.Mesh.from_arrays(v, f, jf.Diffuse(0.5), leaf_size=leaf)
            build = time.perf_counter() - t0
            nbytes = sum(x.nbytes for x in jax.tree.leaves(mesh) if hasattr(x, "nbytes"))
            bvh = jax.jit(jax.vmap(lambda a, b: mesh_nearest(mesh, a, b)))
            t_bvh = _best(lambda: jax.block_until_ready(bvh(o, d)), repeats)
            tb, _ = bvh(o, d)
            row = {"triangles": int(len(f)), "leaf_size": leaf, "rays": n_rays, "bvh_rays_per_s": n_rays / t_bvh,
                   "build_s": build, "mesh_bytes": int(nbytes), "stack_size": mesh.stack_size,
                   "hit_fraction": float(np.isfinite(np.asarray(tb)).mean())}
            if leaf == LEAF_SIZE:
                n_bf = int(max(8, min(n_rays, 2**30 // (len(f) * 64))))  # bounded intermediates
                bf = jax.jit(jax.vmap(lambda a, b: brute_force_nearest(mesh, a, b)))
                t_bf = _best(lambda: jax.block_until_ready(bf(o[:n_bf], d[:n_bf])), max(1, repeats // 2))
                tr, _ = bf(o[:n_bf], d[:n_bf])
                assert np.array_equal(np.asarray(tr), np.asarray(tb)[:n_bf]), "BVH and brute force disagree"
                row.update(brute_rays=n_bf, brute_rays_per_s=n_bf / t_bf, speedup=(n_rays / t_bvh) / (n_bf / t_bf))
            rows.append(row)
            print(_row_text(row), flush=True)
    return rows


def _row_text(r) -> str:
    bf = f"{r['brute_rays_per_s']:>12.4g} {r['speedup']:>8.1f}x" if "brute_rays_per_s" in r else f"{'':>12} {'':>9}"
    return (f"{r['triangles']:>9} {r['leaf_size']:>5} {r['bvh_rays_per_s']:>12.4g} {bf} {r['build_s']:>8.2f} "
            f"{r['mesh_bytes'] / 2**20:>9.1f}")


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
    out = {"size": size, "spp": spp, "mesh_triangles": int(len(f))}
    for name, s in (("analytic", scene), ("mesh", mesh_scene)):
        key = jax.random.key(0)
        t = _best(lambda: jax.block_until_ready(jf.render(s, key, spp)), repeats)
        img = np.asarray(jf.render(s, key, spp))
        out[f"{name}_ms_per_spp"] = 1e3 * t / spp
        out[f"{name}_mean"] = float(img.mean())
        print(f"{name:>9}: {1e3 * t / spp:8.1f} ms/spp ({size}x{size}, mean pixel {img.mean():.5f})", flush=True)
    out["ratio"] = out["mesh_ms_per_spp"] / out["analytic_ms_per_spp"]
    print(f"    ratio: {out['ratio']:.2f}x (target <= 3x)")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--counts", type=int, nargs="+", default=[1000, 10000, 100000, 1000000])
    ap.add_argument("--rays", type=int, default=1024)
    ap.add_argument("--leaf-sizes", type=int, nargs="+", default=[4, 8])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--size", type=int, default=64, help="spot_fog image size for ms/spp")
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--scene-triangles", type=int, default=100000)
    ap.add_argument("--json", default=str(DEFAULT_JSON))
    args = ap.parse_args(argv)
    import jaxfog as jf

    jf.use_cpu_cores()
    print(f"{'triangles':>9} {'leaf':>5} {'BVH rays/s':>12} {'brute rays/s':>12} {'speedup':>9} {'build s':>8} "
          f"{'mesh MiB':>9}")
    rows = rays_per_second(args.counts, args.rays, args.repeats, args.leaf_sizes)
    scene = ms_per_spp(args.size, args.spp, args.repeats, args.scene_triangles)
    write_json(args.json, {"machine": machine_info(), "date": time.strftime("%Y-%m-%d"),
                           "command": "python -m benchmarks.bench_mesh " + " ".join(argv or sys.argv[1:]),
                           "rays": rows, "scene": scene})
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
