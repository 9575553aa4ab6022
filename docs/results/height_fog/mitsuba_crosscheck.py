"""Height fog against Mitsuba 3: `heterogeneous` medium with a `gridvolume` of the same exponential profile.

    PYTHONPATH=. python docs/results/height_fog/mitsuba_crosscheck.py [--keys 16] [--spp 64] [--mitsuba-keys 256]

For each view (`height_fog_ground`, `height_fog_above`: 32 x 32, max_depth 3, a spot light and the sun):

- jaxfog (`HeightFog`, "detached", keys 0..K-1, `--spp` each);
- Mitsuba 3.9 `volpath` (scalar_rgb, seeds 0..M-1, `--spp` each, the same seeds at both grids) with the fog as
  `heterogeneous` + `gridvolume` (trilinear) sampled at the voxel centres from `sigma_0 exp(-(y - h_0) / H)`, the
  first centre at y = 0 (the ground), at two grid resolutions along y (the profile is constant in x and z, so the grid
  is 2 x N x 2 over a box of 1000 x 12 x 1000 units holding the camera and every surface; outside the box Mitsuba has
  no fog: the optical depth above y = 12 is sigma_0 H e^-15 ~ 1e-7, and below y = 0 no camera ray goes in these
  views, since the floor fills them);
- the grid's discretisation error, predicted: trilinear interpolation of the exponential is the trapezoid rule, so a
  ray crossing whole voxels sees the optical depth times `(a / 2) coth(a / 2) = 1 + a^2 / 12 + ...`, `a = dy / H`,
  i.e. Mitsuba renders jaxfog's scene with sigma_0 scaled by that factor (+0.80% at N = 49, +0.05% at N = 193 for
  H = 0.8). Its effect on each region is measured with jaxfog itself: `--grid-keys` pairs of renders with the same
  key, "proposal" estimator (the same paths), sigma_0 and 1.01 sigma_0, the difference scaled to each grid's factor
  (a correlated difference: low noise). It is checked against the measured Mitsuba difference m_49 - m_193.

Compares the means of 16 regions (8 x 8 pixel blocks): z = (jaxfog - mitsuba) / sqrt(SE_j^2 + SE_m^2 + e_N^2), with
each SE from the spread of that renderer's independent images and e_N the predicted grid effect; and z_corr, the
same with jaxfog shifted by the predicted grid effect (e_N signed) instead of e_N in the variance.

Mitsuba's images here are heavy-tailed (its free-flight sampling of the spot light's 1/r^2 near the light; the spot
sits in region 1 of the view from above): a few of its images carry a large part of a region's mean, so few images
give a low mean with a low *estimated* SE (16 images of 64 spp: region 1 at 0.1199 +- 0.0020 against 0.1253 +- 0.0014
from 240 more). The default `--mitsuba-keys 256` makes that tail show; the JSON reports, per region, the share of
Mitsuba's sum carried by its largest image.

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
from jaxfog._mitsuba import import_mitsuba, to_mitsuba  # noqa: E402

VIEWS = ("height_fog_ground", "height_fog_above")
BOX_Y = 12.0
HALF_XZ = 500.0
SENS_STEP = 0.01
"""Relative step of sigma_0 in the sensitivity renders (the grid effect is scaled from it: linear at 1% and below)."""


def grid_spacing(ny: int) -> float:
    """dy of the N-voxel grid whose first centre is at y = 0 and whose box ends at BOX_Y."""
    return BOX_Y / (ny - 0.5)


def grid_factor(ny: int, height_scale: float) -> float:
    """Optical depth of the trilinear grid over the exact one for a ray crossing whole voxels: `(a/2) coth(a/2)`."""
    a = grid_spacing(ny) / height_scale
    return float((a / 2) / np.tanh(a / 2))


def grid_dict(mi, med: dict, ny: int) -> tuple[dict, dict]:
    """The `heterogeneous` medium and its bounding cube for a HeightFog scene-file dict, `ny` voxels along y."""
    T = mi.ScalarTransform4f
    s0 = np.asarray(med["sigma_0"] if isinstance(med["sigma_0"], list) else [med["sigma_0"]] * 3, float)
    H, h0 = float(med["height_scale"]), float(med["base_height"])
    assert med["up"] == [0.0, 1.0, 0.0]
    assert np.all(s0 == s0[0]), "grey sigma_0 only in this script"
    dy = grid_spacing(ny)  # first voxel centre at y = 0 (the ground), the box from -dy/2 to BOX_Y
    y_lo = -0.5 * dy
    centres = y_lo + (np.arange(ny) + 0.5) * dy
    prof = np.exp(-(centres - h0) / H)
    arr = np.broadcast_to(prof[None, :, None, None], (2, ny, 2, 1)).astype(np.float32).copy()
    box = T().translate([-HALF_XZ, y_lo, -HALF_XZ]) @ T().scale([2 * HALF_XZ, BOX_Y - y_lo, 2 * HALF_XZ])
    sigma = {"type": "gridvolume", "grid": mi.VolumeGrid(arr), "to_world": box, "filter_type": "trilinear"}
    alb = med["albedo"]
    albedo = float(alb) if not isinstance(alb, list) else {"type": "rgb", "value": alb}
    fog = {"type": "heterogeneous", "sigma_t": sigma, "scale": float(s0[0]), "albedo": albedo,
           "phase": {"type": "hg", "g": float(med["g"])}}
    cube = {"type": "cube", "to_world": box @ T().translate([0.5, 0.5, 0.5]) @ T().scale(0.5),
            "bsdf": {"type": "null"}, "interior": {"type": "ref", "id": "fog"}}
    return fog, cube


def mitsuba_dict(mi, data: dict, ny: int, spp: int) -> dict:
    """`jaxfog.to_mitsuba` of the scene with a stand-in homogeneous fog, then the fog replaced by the grid and the
    directional lights added (`directional`: `direction` the light travels in, `irradiance` on a facing surface)."""
    plain = dict(data)
    med = data["medium"]
    plain["medium"] = {"type": "homogeneous", "sigma_t": 1.0, "albedo": 0.5, "g": float(med["g"]), "extent": 10.0}
    plain["lights"] = [lt for lt in data["lights"] if lt["type"] != "directional"]
    out = to_mitsuba(plain, spp=spp, transform=lambda m: mi.ScalarTransform4f(np.asarray(m, float).tolist()))
    out["fog"], out["fog_boundary"] = grid_dict(mi, med, ny)
    for i, lt in enumerate(data["lights"]):
        if lt["type"] == "directional":
            irr = lt["irradiance"]
            out[f"sun_{i}"] = {"type": "directional", "direction": [float(x) for x in lt["direction"]],
                               "irradiance": {"type": "rgb",
                                              "value": [float(irr)] * 3 if not isinstance(irr, list) else irr}}
    return out


def regions(img, b=8):
    H, W = img.shape[:2]
    return img.reshape(H // b, b, W // b, b, 3).mean(axis=(1, 3, 4)).reshape(-1)


def mean_se(r):
    return r.mean(0), r.std(0, ddof=1) / np.sqrt(len(r))


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--keys", type=int, default=16, help="jaxfog images")
    ap.add_argument("--spp", type=int, default=64, help="spp per image, both renderers")
    ap.add_argument("--mitsuba-keys", type=int, default=256, help="Mitsuba images per grid")
    ap.add_argument("--grid-keys", type=int, default=8, help="jaxfog image pairs for the grid-effect prediction")
    ap.add_argument("--grids", type=int, nargs=2, default=(49, 193))
    ap.add_argument("--out", default="bench_out/height_fog", help="output folder for crosscheck.json")
    ap.add_argument("--variant", default="scalar_rgb",
                    help="Mitsuba variant (default scalar_rgb: llvm_ad_rgb aborts in LLVM instruction selection "
                         "('Cannot select: fminimum') on this machine's libLLVM for the heterogeneous medium)")
    args = ap.parse_args()
    try:
        mi = import_mitsuba(args.variant)
    except ImportError as e:
        print("skipped:", e)
        return 3
    import jaxfog as jf

    jf.use_cpu_cores()
    import jax

    report = {"keys": args.keys, "spp": args.spp, "mitsuba_keys": args.mitsuba_keys, "grid_keys": args.grid_keys,
              "grids": list(args.grids), "mitsuba": mi.__version__, "variant": args.variant, "views": {}}
    for view in VIEWS:
        sf = jf.load_scene(f"data_synthetic/scenes/{view}.json")
        med = sf.data["medium"]
        cache = f"/tmp/height_fog_crosscheck_{view}_{args.keys}_{args.spp}.npz"
        t0 = time.perf_counter()
        if os.path.exists(cache):
            jimgs, t_j = np.load(cache)["images"], float(np.load(cache)["t"])
        else:
            jimgs = np.stack([np.asarray(jf.render(sf.scene, jax.random.key(k), args.spp))
                              for k in range(args.keys)])
            t_j = time.perf_counter() - t0
            np.savez(cache, images=jimgs, t=t_j)
        # the grid effect: d(region) / d(log sigma_0) from same-key pairs (same paths: the "proposal" estimator)
        ref = sf.scene.medium
        bumped = sf.scene.replace_medium(sigma_0=ref.sigma_0 * (1.0 + SENS_STEP))
        t0 = time.perf_counter()
        sens = []
        for k in range(args.grid_keys):
            key = jax.random.key(1000 + k)
            a = np.asarray(jf.render(sf.scene, key, args.spp, estimator="proposal", proposal=ref), np.float64)
            b = np.asarray(jf.render(bumped, key, args.spp, estimator="proposal", proposal=ref), np.float64)
            sens.append(regions(b - a) / SENS_STEP)
        t_sens = time.perf_counter() - t0
        ds, ds_se = mean_se(np.stack(sens))
        mres = {}
        for ny in args.grids:
            scene = mi.load_dict(mitsuba_dict(mi, sf.data, ny, args.spp))
            t0 = time.perf_counter()
            ims = np.stack([np.asarray(mi.render(scene, spp=args.spp, seed=k))[..., :3]
                            for k in range(args.mitsuba_keys)])
            mres[ny] = (np.stack([regions(x) for x in ims]), time.perf_counter() - t0)
        rj = np.stack([regions(x) for x in jimgs])
        mj, sej = mean_se(rj)
        coarse, fine = args.grids
        disc_meas = mres[coarse][0].mean(0) - mres[fine][0].mean(0)
        disc_meas_se = np.sqrt((mres[coarse][0].var(0, ddof=1) + mres[fine][0].var(0, ddof=1)) / args.mitsuba_keys)
        H = float(med["height_scale"])
        pred = {ny: (grid_factor(ny, H) - 1.0) * ds for ny in args.grids}
        pred_diff = pred[coarse] - pred[fine]
        rows = {}
        for ny in args.grids:
            r, t_m = mres[ny]
            mm, sem = mean_se(r)
            e = pred[ny]
            z = (mj - mm) / np.sqrt(sej**2 + sem**2 + e**2)
            z_corr = (mj + e - mm) / np.sqrt(sej**2 + sem**2)
            share = r.max(0) / r.sum(0)
            rows[ny] = {"dy": grid_spacing(ny), "grid_factor": grid_factor(ny, H), "mitsuba_s": t_m,
                        "image_mean": float(mm.mean()), "mean_rel_diff": float(np.mean(mj - mm) / np.mean(mm)),
                        "mean_rel_diff_se": float(np.sqrt(np.sum(sej**2 + sem**2)) / len(mm) / np.mean(mm)),
                        "grid_effect_rel": float(np.mean(e) / np.mean(mm)),
                        "max_abs_z": float(np.abs(z).max()), "mean_z2": float(np.mean(z**2)),
                        "max_abs_z_corr": float(np.abs(z_corr).max()), "mean_z2_corr": float(np.mean(z_corr**2)),
                        "regions_mitsuba": mm.tolist(), "regions_se_mitsuba": sem.tolist(),
                        "regions_z": z.tolist(), "regions_z_corr": z_corr.tolist(),
                        "regions_grid_effect": e.tolist(), "regions_largest_image_share": share.tolist()}
        z_disc = (disc_meas - pred_diff) / np.sqrt(disc_meas_se**2 + (ds_se * (grid_factor(coarse, H)
                                                                               - grid_factor(fine, H)))**2)
        report["views"][view] = {
            "jaxfog_mean": float(mj.mean()), "jaxfog_s": t_j, "sensitivity_s": t_sens, "grids": rows,
            "regions_jaxfog": mj.tolist(), "regions_se_jaxfog": sej.tolist(),
            "regions_dlog_sigma0": ds.tolist(), "regions_dlog_sigma0_se": ds_se.tolist(),
            "grid_difference_measured": disc_meas.tolist(), "grid_difference_measured_se": disc_meas_se.tolist(),
            "grid_difference_predicted": pred_diff.tolist(),
            "grid_difference_z": z_disc.tolist(),
            "grid_difference_mean_rel": [float(disc_meas.mean() / mj.mean()), float(pred_diff.mean() / mj.mean())]}
        print(view, f"jaxfog mean {mj.mean():.5g}", flush=True)
        for ny in args.grids:
            g = rows[ny]
            print(f"  N={ny}: mitsuba {g['image_mean']:.5g}, rel diff {100 * g['mean_rel_diff']:+.2f}% "
                  f"(SE {100 * g['mean_rel_diff_se']:.2f}%), grid effect {100 * g['grid_effect_rel']:+.2f}%, "
                  f"max|z| {g['max_abs_z']:.2f}, mean z^2 {g['mean_z2']:.2f}, max|z_corr| {g['max_abs_z_corr']:.2f}, "
                  f"mean z_corr^2 {g['mean_z2_corr']:.2f}")
            print("    z:", np.round(np.asarray(g["regions_z"]).reshape(4, 4), 2).tolist())
        print(f"  m_{coarse} - m_{fine}: measured {disc_meas.mean():.3g} (rel {disc_meas.mean() / mj.mean():+.3%}), "
              f"predicted {pred_diff.mean():.3g}; per region z {np.round(z_disc, 2).tolist()}", flush=True)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "crosscheck.json"), "w") as fh:
        json.dump(report, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
