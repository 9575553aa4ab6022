"""Height fog against Mitsuba 3: `heterogeneous` medium with a `gridvolume` of the same exponential profile.

    PYTHONPATH=. python docs/results/height_fog/mitsuba_crosscheck.py [--keys 16] [--spp 64] [--out DIR]

For each view (`height_fog_ground`, `height_fog_above`: 32 x 32, max_depth 3, a spot light and the sun), renders
jaxfog (`HeightFog`, "detached", keys 0..K-1) and Mitsuba 3.9 `volpath` (scalar_rgb, seeds 0..K-1) with the fog as
`heterogeneous` + `gridvolume` (trilinear) sampled at the voxel centres from `sigma_0 exp(-(y - h_0) / H)`, at two
grid resolutions along y (the profile is constant in x and z, so the grid is 2 x N x 2 over a box of 1000 x 12 x
1000 units; outside the box Mitsuba has no fog, and the optical depth above y = 12 is sigma_0 H e^-15 ~ 1e-7).
Compares the means of 16 regions (8 x 8 pixel blocks): z = (jaxfog - mitsuba) / sqrt(SE_j^2 + SE_m^2 + e_disc^2),
e_disc = |m_fine - m_coarse| (the coarse grid's discretisation error; for the fine grid, a quarter of it: trilinear
interpolation error ~ (dy / H)^2 / 8, dy halving twice from coarse to fine divides it by 16; we use 1/4 to be safe).
Writes `crosscheck.json` and prints a table.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.getcwd())
from jaxfog.bench_mitsuba import import_mitsuba, scene_dict  # noqa: E402

VIEWS = ("height_fog_ground", "height_fog_above")
BOX_Y = 12.0
HALF_XZ = 500.0


def grid_dict(mi, med: dict, origin_half_extent, ny: int) -> tuple[dict, dict]:
    """The `heterogeneous` medium and its bounding cube for a HeightFog scene-file dict, `ny` voxels along y."""
    T = mi.ScalarTransform4f
    s0 = np.asarray(med["sigma_0"] if isinstance(med["sigma_0"], list) else [med["sigma_0"]] * 3, float)
    H, h0 = float(med["height_scale"]), float(med["base_height"])
    assert med["up"] == [0.0, 1.0, 0.0]
    dy = (BOX_Y + 0.0) / (ny - 0.5)  # first voxel centre at y = 0 (the ground), the box from -dy/2 to BOX_Y
    y_lo = -0.5 * dy
    centres = y_lo + (np.arange(ny) + 0.5) * dy
    prof = np.exp(-(centres - h0) / H)
    smax = float(s0.max())
    arr = np.broadcast_to(prof[None, :, None, None], (2, ny, 2, 1)).astype(np.float32).copy()
    box = (T().translate([-HALF_XZ, y_lo, -HALF_XZ]) @ T().scale([2 * HALF_XZ, BOX_Y - y_lo, 2 * HALF_XZ]))
    sigma = {"type": "gridvolume", "grid": mi.VolumeGrid(arr), "to_world": box, "filter_type": "trilinear"}
    alb = med["albedo"]
    albedo = float(alb) if not isinstance(alb, list) else {"type": "rgb", "value": alb}
    assert np.all(s0 == s0[0]), "grey sigma_0 only in this script"
    fog = {"type": "heterogeneous", "sigma_t": sigma, "scale": smax, "albedo": albedo,
           "phase": {"type": "hg", "g": float(med["g"])}}
    cube = {"type": "cube", "to_world": box @ T().translate([0.5, 0.5, 0.5]) @ T().scale(0.5),
            "bsdf": {"type": "null"}, "interior": {"type": "ref", "id": "fog"}}
    return fog, cube


def mitsuba_dict(mi, data: dict, ny: int, spp: int) -> dict:
    """`jaxfog.bench_mitsuba.scene_dict` of the scene with the fog replaced, and the directional light added."""
    plain = dict(data)
    med = data["medium"]
    plain["medium"] = {"type": "homogeneous", "sigma_t": 1.0, "albedo": 0.5, "g": float(med["g"]), "extent": 10.0}
    plain["lights"] = [lt for lt in data["lights"] if lt["type"] != "directional"]
    out = scene_dict(plain, mi, spp)
    out["fog"], out["fog_boundary"] = grid_dict(mi, med, None, ny)
    for i, lt in enumerate(data["lights"]):
        if lt["type"] == "directional":
            out[f"sun_{i}"] = {"type": "directional", "direction": [float(x) for x in lt["direction"]],
                               "irradiance": {"type": "rgb", "value": [float(lt["irradiance"])] * 3
                                              if not isinstance(lt["irradiance"], list) else lt["irradiance"]}}
    return out


def regions(img, b=8):
    H, W = img.shape[:2]
    return img.reshape(H // b, b, W // b, b, 3).mean(axis=(1, 3, 4)).reshape(-1)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--keys", type=int, default=16)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--grids", type=int, nargs=2, default=(49, 193))
    ap.add_argument("--out", default="docs/results/height_fog")
    ap.add_argument("--variant", default="scalar_rgb",
                    help="Mitsuba variant (default scalar_rgb: llvm_ad_rgb aborts in LLVM instruction selection "
                         "('Cannot select: fminimum') on this machine's libLLVM for the heterogeneous medium)")
    args = ap.parse_args()
    mi, reason = import_mitsuba()
    if mi is None:
        print("skipped:", reason)
        return 3
    mi.set_variant(args.variant)
    import jax

    import jaxfog as jf

    report = {"keys": args.keys, "spp": args.spp, "grids": list(args.grids), "mitsuba": mi.__version__,
              "variant": args.variant, "views": {}}
    for view in VIEWS:
        sf = jf.load_scene(f"data_synthetic/scenes/{view}.json")
        cache = f"/tmp/height_fog_crosscheck_{view}_{args.keys}_{args.spp}.npz"
        t0 = time.perf_counter()
        if os.path.exists(cache):
            jimgs, t_j = np.load(cache)["images"], float(np.load(cache)["t"])
        else:
            jimgs = np.stack([np.asarray(jf.render(sf.scene, jax.random.key(k), args.spp))
                              for k in range(args.keys)])
            t_j = time.perf_counter() - t0
            np.savez(cache, images=jimgs, t=t_j)
        mres = {}
        for ny in args.grids:
            scene = mi.load_dict(mitsuba_dict(mi, sf.data, ny, args.spp))
            t0 = time.perf_counter()
            ims = np.stack([np.asarray(mi.render(scene, spp=args.spp, seed=k))[..., :3] for k in range(args.keys)])
            mres[ny] = (ims, time.perf_counter() - t0)
        rj = np.stack([regions(x) for x in jimgs])
        mj, sej = rj.mean(0), rj.std(0, ddof=1) / np.sqrt(args.keys)
        coarse, fine = args.grids
        rc = np.stack([regions(x) for x in mres[coarse][0]])
        rf = np.stack([regions(x) for x in mres[fine][0]])
        disc = np.abs(rf.mean(0) - rc.mean(0))
        rows = {}
        for ny, r, e in ((coarse, rc, disc), (fine, rf, 0.25 * disc)):
            mm, sem = r.mean(0), r.std(0, ddof=1) / np.sqrt(args.keys)
            z = (mj - mm) / np.sqrt(sej**2 + sem**2 + e**2)
            z_noisy = (mj - mm) / np.sqrt(sej**2 + sem**2)
            rows[ny] = {"max_abs_z": float(np.abs(z).max()), "mean_z2": float(np.mean(z**2)),
                        "max_abs_z_without_disc": float(np.abs(z_noisy).max()),
                        "mean_rel_diff": float(np.mean(mj - mm) / np.mean(mm)),
                        "disc_rel": float(np.mean(e) / np.mean(mm)), "mitsuba_s": mres[ny][1],
                        "image_mean": float(mm.mean())}
        report["views"][view] = {"jaxfog_mean": float(mj.mean()), "jaxfog_s": t_j, "grids": rows,
                                 "regions_jaxfog": mj.tolist(), "regions_se_jaxfog": sej.tolist(),
                                 "regions_mitsuba_fine": rf.mean(0).tolist(),
                                 "regions_mitsuba_coarse": rc.mean(0).tolist()}
        print(view, json.dumps(report["views"][view]["grids"], indent=1), f"jaxfog mean {mj.mean():.5g}", flush=True)
    with open(os.path.join(args.out, "crosscheck.json"), "w") as fh:
        json.dump(report, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
