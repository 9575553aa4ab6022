"""Mitsuba 3 cross-check of the media models (chromatic `homogeneous`, two-term HG as `blendphase`, fog droplets as
a `tabphase` of jaxfog's own pdf): image means and 4 x 4 block means per channel, with standard errors over
independent images on both sides.

    python benchmarks/crosscheck_models.py [--only NAME ...] [--images N] [--spp N] [--spp-mitsuba N] [--out FILE.json]

Each case has its own number of images and spp per image (`CASES`); `--images`, `--spp`, `--spp-mitsuba` replace
them for the cases run. Writes the JSON to `--out` (default `bench_out/crosscheck_models/crosscheck_models.json`,
keeping the cases not run from an earlier run); the table of a run is in `docs/results/fit_models.md`.
Mitsuba: `scalar_rgb` (needs no LLVM). z = (jaxfog - Mitsuba) / sqrt(SE_j^2 + SE_m^2), SE = spread of the images /
sqrt(images).

The droplet cases (d = 8 um, where the table's local interpolation error is <= 0.5% even inside the forward peak)
leave out the light's own image, the central `exclude` x `exclude` pixels of the backlit views: the single-scattered
glow of a point light has radiance ~ 1/psi at the angle psi from it, whose square has a divergent integral over the
pixel (both renderers' images are heavy-tailed there, at any depth; Mitsuba's `volpath`, without equiangular
sampling, has a further 1/r^2 tail near the light). The other pixels' mean is well behaved at max_depth 2; at
max_depth 3 the second vertex's next-event estimate has the phase function's peak (docs/results/fit_models.md), so
those cases take many cheap images. `rings` reports the included pixels' means in rings of pixel distance from the
image centre (the light's image): the peak's profile.
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys

import jax
import numpy as np

import jaxfog
from jaxfog.tools import TABPHASE_SIZE, tabphase_error

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # as a script: `benchmarks` importable

SIZE = ["camera.width=32", "camera.height=32"]
DROPLET_8 = ["medium.phase.diameter=8"]
BACKLIT = "data_synthetic/scenes/droplet_backlit.json"
SIDE = "data_synthetic/scenes/droplet_fit_side.json"
RING_EDGES = (0.0, 2.0, 4.0, 8.0, 16.0, np.inf)
"""Rings of pixel-centre distance from the image centre (pixels) for `rings`."""
# name: scene file, overrides, what it checks, images, spp (jaxfog / Mitsuba), central pixels left out, rings
CASES = {
    "chromatic_haze": dict(path="data_synthetic/scenes/chromatic_haze.json",
                           over=SIZE + ["integrator.max_depth=4"], images=16, spp=16, spp_mitsuba=512,
                           what="RGB homogeneous, sigma_t (0.5, 1.5, 3.0), albedo (0.9, 0.85, 0.8), two-term HG "
                                "(blendphase); Mitsuba's volpathmis (spectral MIS): its volpath is heavy-tailed on "
                                "this medium"),
    "two_term_backlit": dict(path="data_synthetic/scenes/twoterm_fit_backlit.json", over=[], images=16, spp=16,
                             spp_mitsuba=256,
                             what="grey fog, two-term HG (0.8, -0.4, w 0.7) as blendphase, backlit (forward lobe)"),
    "droplet_halo_ss": dict(path=BACKLIT, over=SIZE + DROPLET_8 + ["camera.fov=10", "integrator.max_depth=2"],
                            images=32, spp=16, spp_mitsuba=256, exclude=2, rings=True,
                            what="droplets d = 8 um as tabphase, single scattering, backlit, fov 10 degrees "
                                 "(0.31 degrees per pixel): the forward peak's profile from 0.3 degrees out"),
    "droplet_backlit_ss": dict(path=BACKLIT, over=SIZE + DROPLET_8 + ["integrator.max_depth=2"],
                               images=32, spp=8, spp_mitsuba=128, exclude=4, rings=True,
                               what="droplets d = 8 um, single scattering, backlit, fov 40 (the halo from 2.5 "
                                    "degrees out)"),
    "droplet_side_ss": dict(path=SIDE, over=DROPLET_8 + ["integrator.max_depth=2"], images=64, spp=16,
                            spp_mitsuba=128,
                            what="droplets d = 8 um, single scattering, side view (angles near 90 degrees: the "
                                 "Draine lobe; the lit floor and sphere)"),
    "droplet_side_d3": dict(path=SIDE, over=DROPLET_8 + ["integrator.max_depth=3"], images=256, spp=8,
                            spp_mitsuba=128,
                            what="droplets d = 8 um, max_depth 3 (double scattering), side view"),
    "droplet_backlit_d3": dict(path=BACKLIT, over=SIZE + DROPLET_8 + ["integrator.max_depth=3"], images=256,
                               spp=8, spp_mitsuba=128, exclude=4,
                               what="droplets d = 8 um, max_depth 3, backlit, fov 40"),
}


def render_mitsuba(path, spp, seed, over, integrator):
    """`jaxfog.render_mitsuba`, with the integrator's type replaced (`volpathmis` for chromatic media)."""
    from jaxfog.tools import import_mitsuba

    mi = import_mitsuba("scalar_rgb")
    d = jaxfog.to_mitsuba(path, spp=spp, seed=seed, overrides=over,
                          transform=lambda m: mi.ScalarTransform4f(np.asarray(m, np.float64).tolist()))
    d["integrator"]["type"] = integrator
    return np.asarray(mi.render(mi.load_dict(d), spp=spp, seed=seed), np.float64)[..., :3]


def pixel_mask(h: int, w: int, exclude: int) -> np.ndarray:
    """Pixels compared: all but the central `exclude` x `exclude` ones (the light's image in the backlit views)."""
    m = np.ones((h, w), bool)
    if exclude:
        m[h // 2 - exclude // 2:h // 2 + (exclude + 1) // 2, w // 2 - exclude // 2:w // 2 + (exclude + 1) // 2] = False
    return m


def ring_index(h: int, w: int) -> np.ndarray:
    """Each pixel's ring (`RING_EDGES`) by the distance of its centre from the image centre, in pixels."""
    y, x = np.mgrid[:h, :w] + 0.5
    return np.digitize(np.hypot(y - h / 2, x - w / 2), RING_EDGES) - 1


def stats(imgs: np.ndarray, exclude: int = 0, rings: bool = False) -> dict:
    """Per channel, over the pixels of `pixel_mask`: the image mean and the 4 x 4 block means (mean and SE over the
    images), the largest image mean over the mean, the SE from each half of the images; the ring means (`rings`)
    and the left-out centre's mean (`exclude`), with their SEs."""
    n, h, w, _ = imgs.shape
    m = pixel_mask(h, w, exclude).astype(np.float64)
    masked_mean = lambda x, mm: (x * mm[None, ..., None]).sum((1, 2)) / mm.sum()  # noqa: E731
    whole = masked_mean(imgs, m)  # (n, 3)
    se = lambda x: x.std(0, ddof=1) / np.sqrt(len(x))  # noqa: E731
    bm = m.reshape(4, h // 4, 4, w // 4).sum((1, 3))
    blocks = ((imgs * m[None, ..., None]).reshape(n, 4, h // 4, 4, w // 4, 3).sum(axis=(2, 4))
              / bm[None, ..., None]).reshape(n, 16, 3)
    out = {"mean": whole.mean(0), "se": se(whole), "block_mean": blocks.mean(0), "block_se": se(blocks),
           "max_image_over_mean": float(whole[:, 0].max() / whole[:, 0].mean()),
           "se_halves": [float(se(whole[: n // 2])[0]), float(se(whole[n // 2:])[0])]}
    if rings:
        ri = ring_index(h, w)
        out["rings"] = []
        for r in range(len(RING_EDGES) - 1):
            mr = (ri == r) * m
            if mr.sum():
                v = masked_mean(imgs, mr)[:, 0]
                out["rings"].append({"from_px": RING_EDGES[r], "to_px": RING_EDGES[r + 1], "pixels": int(mr.sum()),
                                     "mean": float(v.mean()), "se": float(se(v))})
    if exclude:
        c = masked_mean(imgs, 1.0 - m)[:, 0]
        out["centre"] = {"pixels": int((1 - m).sum()), "mean": float(c.mean()), "se": float(se(c)),
                         "max_image_over_mean": float(c.max() / c.mean())}
    return out


def run_case(name: str, case: dict, args, cmd: str) -> dict:
    """One case of `CASES` (with the command line's replacements): `n` images a side, each timed (the first jaxfog
    image compiles), compared by image and block means per channel; its record for the JSON."""
    from benchmarks.common import time_calls

    path, over, what = case["path"], case["over"], case["what"]
    n = args.images or case["images"]
    spp, spp_m = args.spp or case["spp"], args.spp_mitsuba or case["spp_mitsuba"]
    exclude, rings = case.get("exclude", 0), case.get("rings", False)
    scene = jaxfog.load_scene(path, over).scene
    integrator = "volpathmis" if name.startswith("chromatic") else "volpath"
    ours = time_calls(lambda k: np.asarray(jaxfog.render(scene, jax.random.key(20_000 + args.seed + k), spp),
                                           np.float64), n, warmup=0, keep=True)
    theirs = time_calls(lambda k: render_mitsuba(path, spp_m, args.seed + k, over, integrator), n, warmup=0,
                        keep=True)
    j, m = stats(np.stack(ours["values"]), exclude, rings), stats(np.stack(theirs["values"]), exclude, rings)
    z = (j["mean"] - m["mean"]) / np.sqrt(j["se"] ** 2 + m["se"] ** 2)
    se_b = np.sqrt(j["block_se"] ** 2 + m["block_se"] ** 2)
    lit = se_b > 0  # blocks that are black in both renderers (no fog seen) have no z
    z_full = np.where(lit, (j["block_mean"] - m["block_mean"]) / np.where(lit, se_b, 1.0), np.nan)  # (16, 3)
    zb = z_full[lit]
    side = lambda s: {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in s.items()  # noqa: E731
                      if k not in ("block_mean", "block_se")}
    res = {"scene": path, "overrides": over, "what": what, "mitsuba_integrator": integrator,
           "images": n, "spp": spp, "spp_mitsuba": spp_m, "seed": args.seed, "excluded_centre_px": exclude,
           "date": datetime.date.today().isoformat(), "command": cmd,
           "jaxfog": side(j), "mitsuba": side(m),
           "rel_diff": ((j["mean"] - m["mean"]) / m["mean"]).tolist(), "z": z.tolist(),
           "blocks_max_abs_z": float(np.abs(zb).max()), "blocks_mean_z2": float((zb ** 2).mean()),
           "blocks_n": int(zb.size),
           "blocks_z_first_channel": [round(float(v), 2) if np.isfinite(v) else None for v in z_full[:, 0]],
           "jaxfog_s": round(sum(ours["wall_s"]), 1), "mitsuba_s": round(sum(theirs["wall_s"]), 1),
           "jaxfog_cpu_s": round(sum(ours["cpu_s"]), 1), "mitsuba_cpu_s": round(sum(theirs["cpu_s"]), 1)}
    if rings:
        res["rings_z"] = [(a["mean"] - b["mean"]) / np.hypot(a["se"], b["se"]) for a, b in zip(j["rings"], m["rings"])]
    if exclude:
        a, b = j["centre"], m["centre"]
        res["centre_z"] = (a["mean"] - b["mean"]) / np.hypot(a["se"], b["se"])
    return res


def main(argv=None) -> int:
    from benchmarks.common import command, machine_info, out_dir, print_json, read_json, write_json

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--images", type=int, help="images per side (default: the case's)")
    ap.add_argument("--spp", type=int, help="jaxfog's spp per image (default: the case's)")
    ap.add_argument("--spp-mitsuba", type=int, help="Mitsuba's spp per image (default: the case's; its volpath is "
                    "noisier per sample and much cheaper per sample on CPU)")
    ap.add_argument("--seed", type=int, default=0, help="first seed: jaxfog keys 20000 + seed + k, Mitsuba seeds "
                    "seed + k for image k (default 0)")
    ap.add_argument("--only", nargs="*")
    ap.add_argument("--out", default=str(out_dir("crosscheck_models") / "crosscheck_models.json"))
    args = ap.parse_args(argv)
    out = read_json(args.out, {})
    out.update({"machine": machine_info(), "tabphase_size": TABPHASE_SIZE})
    for k in ("date", "images", "spp", "spp_mitsuba", "command"):
        out.pop(k, None)  # per case now
    out.setdefault("tabphase_error", {})
    for d in (5.0, 8.0, 10.0, 20.0, 50.0):
        out["tabphase_error"][f"{d:g}"] = tabphase_error(d)
    out.setdefault("cases", {})
    cmd = command("python benchmarks/crosscheck_models.py", argv)
    for name, case in CASES.items():
        if args.only and name not in args.only:
            continue
        res = out["cases"][name] = run_case(name, case, args, cmd)
        keys = ("jaxfog", "mitsuba", "z", "blocks_max_abs_z", "blocks_mean_z2", "jaxfog_cpu_s", "mitsuba_cpu_s")
        print_json({k: res[k] for k in keys + (("rings_z",) if "rings_z" in res else ())}, name)
        write_json(args.out, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
