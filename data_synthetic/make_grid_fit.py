"""Write the voxel-fit target set: a 4^3 blob over thin haze seen from four sides, and a fifth view from above held
out of the fit, each rendered by jaxfog with the truth grid.

    python data_synthetic/make_grid_fit.py                        # rewrites data_synthetic/grid_fit/
    python data_synthetic/make_grid_fit.py --res 8 --px 16 --out data_synthetic/grid_fit8   # the 8^3 set
    python data_synthetic/make_grid_fit.py --truth layer --seed 500 --out OUT   # other fogs (not shipped):
                                                                  # --truth two_blobs | layer

Writes `grid_fit/truth.vol` (the grid: 1/scene unit, x fastest, the box `[-1, -0.5, -1]` to `[1, 1.5, 1]`), one scene
per view (`front`, `side`, `back`, `left`, and `top`, the held-out one: spot_fog's room, a point light above the
box, max_depth 3, albedo 0.9, HG g 0.5, 8 x 8 px) and its target at 2048 spp (`VIEW.exr`, seed 100 + its index;
the header records the spp and the truth file). Fit and report the held-out error with

    python -m fitting.grid data_synthetic/grid_fit/{front,side,back,left}.{json,exr} --out OUT --truth \\
        --holdout data_synthetic/grid_fit/top.json data_synthetic/grid_fit/top.exr

(the four pairs written out: `front.json front.exr side.json side.exr ...`).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
OUT = HERE / "grid_fit"
RES = 4
BOX = ((-1.0, -0.5, -1.0), (1.0, 1.5, 1.0))
CAMERAS = {  # name: (origin, target, up)
    "front": ([0, 0.6, 4.0], [0, 0.5, 0], [0, 1, 0]),
    "side": ([4.0, 0.8, 0.3], [0, 0.5, 0], [0, 1, 0]),
    "back": ([0.3, 0.9, -4.0], [0, 0.5, 0], [0, 1, 0]),
    "left": ([-4.0, 0.7, -0.5], [0, 0.5, 0], [0, 1, 0]),
    "top": ([0.2, 4.5, 0.4], [0, 0.5, 0], [0, 0, -1]),
}
SPP = 2048


def _centres(res: int):
    lo, hi = np.array(BOX[0]), np.array(BOX[1])
    axes = [lo[i] + (np.arange(res) + 0.5) / res * (hi[i] - lo[i]) for i in range(3)]
    return np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")  # z, y, x


def blob_grid(res: int = RES) -> np.ndarray:
    """`(res, res, res)` (z, y, x) at texel centres: haze 0.1 plus a Gaussian blob of peak 1.5 (1/scene unit)."""
    z, y, x = _centres(res)
    return (0.1 + 1.5 * np.exp(-((x - 0.3) ** 2 + (y - 0.6) ** 2 + (z + 0.2) ** 2) / (2 * 0.35 ** 2))).astype(
        np.float32)


def two_blobs_grid(res: int = RES) -> np.ndarray:
    """Haze 0.05 and two Gaussian blobs (peaks 1.2 and 0.9, width 0.3), low in front and high behind."""
    z, y, x = _centres(res)
    return (0.05 + 1.2 * np.exp(-((x + 0.4) ** 2 + (y - 0.2) ** 2 + (z - 0.4) ** 2) / (2 * 0.3 ** 2))
            + 0.9 * np.exp(-((x - 0.5) ** 2 + (y - 1.0) ** 2 + (z + 0.4) ** 2) / (2 * 0.3 ** 2))).astype(np.float32)


def layer_grid(res: int = RES) -> np.ndarray:
    """A fog bank: 1.1 near the floor falling to 0.1 above y = 0.4 (a logistic of width 0.15), and a wisp of 0.6
    above it."""
    z, y, x = _centres(res)
    return (0.1 + 1.0 / (1 + np.exp(-(0.4 - y) / 0.15))
            + 0.6 * np.exp(-((x + 0.3) ** 2 + (y - 1.1) ** 2 + z ** 2) / (2 * 0.3 ** 2))).astype(np.float32)


TRUTHS = {"blob": blob_grid, "two_blobs": two_blobs_grid, "layer": layer_grid}


def scene_of(name: str, res: int = RES, px: int = 8, truth: str = "blob over haze") -> dict:
    base = json.loads((HERE / "scenes" / "spot_fog.json").read_text())
    base["name"] = f"grid_fit_{name}"
    base["description"] = (f"Voxel-fit view '{name}': a {res}^3 {truth} (truth.vol) in spot_fog's room, a point "
                           f"light above; written by data_synthetic/make_grid_fit.py")
    base["integrator"]["max_depth"] = 3
    base["medium"] = {"type": "grid", "file": "truth.vol", "albedo": 0.9, "g": 0.5}
    base["lights"] = [{"type": "point", "position": [0, 2.2, 0.5], "intensity": 20}]
    origin, target, up = CAMERAS[name]
    base["camera"].update(origin=origin, target=target, up=up, width=px, height=px)
    return base


def main(argv=None) -> None:
    import argparse

    import jax

    import jaxfog as jf

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--res", type=int, default=RES, help="texels per axis of the truth grid (default 4)")
    ap.add_argument("--px", type=int, default=8, help="each view's width and height in pixels (default 8)")
    ap.add_argument("--out", default=str(OUT), help="the folder to write (default data_synthetic/grid_fit)")
    ap.add_argument("--truth", choices=list(TRUTHS), default="blob", help="the fog (default: the blob)")
    ap.add_argument("--seed", type=int, default=100, help="the first view's key (default 100; each view adds 1)")
    args = ap.parse_args(argv)
    if args.res < 2 or args.px < 1:
        ap.error("--res must be at least 2 and --px at least 1")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    jf.write_vol(out / "truth.vol", TRUTHS[args.truth](args.res), BOX)
    for i, name in enumerate(CAMERAS):
        truth = {"blob": "blob over haze", "two_blobs": "pair of blobs over haze", "layer": "fog bank"}[args.truth]
        (out / f"{name}.json").write_text(json.dumps(scene_of(name, args.res, args.px, truth), indent=2) + "\n")
        img = jf.render(jf.load_scene(out / f"{name}.json").scene, jax.random.key(args.seed + i), SPP)
        jf.write_exr(out / f"{name}.exr", np.asarray(img), {"jaxfog:spp": SPP, "jaxfog:truth_grid": "truth.vol",
                                                           "jaxfog:seed": args.seed + i})
        print(f"{out / name}.exr: mean {float(np.mean(img)):.4g}")


if __name__ == "__main__":
    main()
