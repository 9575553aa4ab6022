"""Write the mesh of the shipped `mesh_fog` scene: a closed, bumpy torus as a binary PLY (procedural, public domain).

    PYTHONPATH=. python data_synthetic/make_mesh_fog.py  # -> data_synthetic/scenes/meshes/bumpy_torus.ply

The torus lies in the x-z plane (its axis is +y), major radius 0.55, tube radius 0.2, the tube's radius modulated by
`1 + 0.18 sin(5 phi) cos(3 theta)` (phi around the axis, theta around the tube). A `nu x nv` grid of quads, each
split into two counter-clockwise triangles seen from outside: 2 nu nv triangles, no boundary (watertight).
`torus_mesh` is also used by the tests and the benchmark (any triangle count).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parent / "scenes" / "meshes" / "bumpy_torus.ply"
NU, NV = 192, 56
"""Grid of the shipped mesh: 21504 triangles."""


def torus_mesh(nu: int = NU, nv: int = NV, major: float = 0.55, minor: float = 0.2, bump: float = 0.18):
    """Vertices (nu * nv, 3) float64 and faces (2 nu nv, 3) int64 of the bumpy torus, front faces outward."""
    phi = 2 * np.pi * np.arange(nu) / nu
    theta = 2 * np.pi * np.arange(nv) / nv
    P, T = np.meshgrid(phi, theta, indexing="ij")
    r = minor * (1 + bump * np.sin(5 * P) * np.cos(3 * T))
    rho = major + r * np.cos(T)
    v = np.stack([rho * np.cos(P), r * np.sin(T), rho * np.sin(P)], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    a = i * nv + j
    b = ((i + 1) % nu) * nv + j
    c = ((i + 1) % nu) * nv + (j + 1) % nv
    d = i * nv + (j + 1) % nv
    f = np.concatenate([np.stack([a, d, c], -1).reshape(-1, 3), np.stack([a, c, b], -1).reshape(-1, 3)])
    # orient outward: the normal of a's first triangle must point away from the tube's centre line
    tri = v[f[0]]
    n = np.cross(tri[1] - tri[0], tri[2] - tri[0])
    centre = np.array([major, 0.0, 0.0])
    if np.dot(n, tri.mean(0) - centre) < 0:
        f = f[:, ::-1]
    return v, f.astype(np.int64)


def main(argv=None) -> int:
    from jaxfog import write_ply

    v, f = torus_mesh()
    OUT.parent.mkdir(parents=True, exist_ok=True)
    write_ply(OUT, v, f)
    print(f"wrote {OUT} ({len(f)} triangles, {len(v)} vertices)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
