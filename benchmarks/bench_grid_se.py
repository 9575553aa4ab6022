"""The cost of the voxel fit's dense information (`fitting.grid.dense_information`: one forward-mode tangent per
voxel) against how many tangents ride through one render (`DENSE_CHUNK`), interleaved in one process.

    python -m benchmarks.bench_grid_se [--set data_synthetic/grid_fit8] [--spp 32] [--chunks 4 8 16 64] [--rounds 3]

Renders the set's first view (`front.json` / `front.exr`, at the fit's resolution) with the constant grid 0.3 and
times one `_columns` call per chunk size and round (A B C ... per round, after one untimed call each: compilation).
Prints milliseconds per tangent and the ratio to the first chunk size (median over rounds); writes
`bench_out/grid_se/grid_se.json` (`--out` another folder). The whole information costs `voxels x 2 x views` tangents.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from .common import REPO, command, interleave, machine_info, out_dir, print_table, write_json


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.bench_grid_se", description=__doc__.split("\n\n")[0])
    ap.add_argument("--set", default=str(REPO / "data_synthetic" / "grid_fit8"), help="a voxel-fit target folder")
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--chunks", type=int, nargs="+", default=[4, 8, 16, 64])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    if args.spp < 1 or args.rounds < 1 or min(args.chunks) < 1:
        ap.error("--spp, --rounds and every --chunks must be at least 1")
    import jax
    import jax.numpy as jnp
    import numpy as np

    from fitting import grid as G

    folder = Path(args.set)
    scene, _, _ = G.load_views([(folder / "front.json", folder / "front.exr")], None)[0]
    shape = scene.medium.density.shape[:3]
    n = int(np.prod(shape))
    chunks = [c for c in args.chunks if c <= n]
    theta = jnp.full(shape, float(np.log(0.3)), jnp.float32)
    eye = jnp.eye(n, dtype=jnp.float32)

    def timed(c):
        return lambda r: jax.block_until_ready(G._columns(theta, scene, eye[:c], jax.random.key(r), args.spp))

    res = interleave({f"{c}": timed(c) for c in chunks}, args.rounds,
                     log=lambda s: print(s, flush=True))
    base = chunks[0]
    rows = []
    for c in chunks:
        r = res[f"{c}"]
        per = [w / c * 1e3 for w in r["wall_s"]]
        ratio = [p / q for p, q in zip(per, [w / base * 1e3 for w in res[f"{base}"]["wall_s"]])]
        rows.append({"chunk": c, "ms_per_tangent": float(np.median(per)), "ratio": float(np.median(ratio)),
                     "wall_s": r["wall_s"]})
    print(f"{folder.name}: {'x'.join(map(str, shape))} grid, {scene.camera.width} x {scene.camera.height} px, "
          f"{args.spp} spp")
    print_table(rows, [("tangents per render", "chunk"), ("ms per tangent", "ms_per_tangent", ".1f"),
                       (f"x chunk {base}", "ratio", ".2f")])
    out = out_dir("grid_se") if args.out is None else Path(args.out)
    write_json(Path(out) / "grid_se.json", {"command": command("benchmarks.bench_grid_se", argv), "set": str(folder),
                                            "shape": list(shape), "spp": args.spp, "rows": rows,
                                            "machine": machine_info()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
