"""Write the patchy-fog grid of `scenes/grid_fog.json`: `grids/patchy.vol`, a 16^3 density grid of three soft
blobs (a bank low over the floor, a wisp in the spot light's beam, a patch to the side) over a thin haze.

    python data_synthetic/make_grid_fog.py      # rewrites data_synthetic/grids/patchy.vol

Values are the extinction in 1/scene unit before the scene's `scale` (Mitsuba's `.vol`, x fastest); the box is the
scene's fog box, `[-2, -0.5, -2]` to `[2, 2.5, 1.5]`. Deterministic (no random numbers).
"""

from pathlib import Path

import numpy as np

import jaxfog as jf

RES = 16
BOX = ((-2.0, -0.5, -2.0), (2.0, 2.5, 1.5))
BLOBS = (  # (centre in scene units, radius, peak extinction)
    ((0.0, 0.1, -0.4), 1.2, 1.2),
    ((0.1, 1.6, 0.0), 0.45, 1.6),
    ((-1.2, 0.8, 0.6), 0.6, 0.9),
)
HAZE = 0.05


def patchy_grid(res: int = RES) -> np.ndarray:
    """The grid `(res, res, res)` (z, y, x) at texel centres: haze plus Gaussian blobs (1/scene unit)."""
    lo, hi = (np.asarray(b, np.float64) for b in BOX)
    axes = [lo[i] + (np.arange(res) + 0.5) / res * (hi[i] - lo[i]) for i in range(3)]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    grid = np.full(x.shape, HAZE)
    for (cx, cy, cz), r, peak in BLOBS:
        grid += peak * np.exp(-((x - cx) ** 2 + (y - cy) ** 2 + (z - cz) ** 2) / (2 * r * r))
    return grid.astype(np.float32)


def main() -> None:
    out = Path(__file__).resolve().parent / "grids" / "patchy.vol"
    out.parent.mkdir(exist_ok=True)
    jf.write_vol(out, patchy_grid(), BOX)
    print(f"wrote {out} ({RES}^3, max {patchy_grid().max():.3f} per scene unit)")


if __name__ == "__main__":
    main()
