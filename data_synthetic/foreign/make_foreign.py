"""Render the foreign fit suite's targets with Mitsuba 3 and write `manifest.json` (needs the `compare` extra).

    PYTHONPATH=. python data_synthetic/foreign/make_foreign.py [--spp 2048] [--only CASE ...]

Each case of `CASES` is one fit: one or two views (a scene file of `scenes/`), the parameters to fit, where the fit
starts, the truth, and which fitted parameters the views determine (the fit must be within 2% / 0.02 of the truth
there). Each target is the scene file with the truth's medium (and light power) rendered by Mitsuba 3's `volpath`
(`jaxfog.render_mitsuba`, variant `scalar_rgb`) at the file's resolution (64 x 64) and max_depth (4), with a fixed
seed per target (`SEED0` + its index; `EXTRA_SEEDS` for views added later), and written with `jaxfog.write_exr`.

Header keys: `jaxfog:truth` (JSON, read by `fitting.fit.true_values`), `jaxfog:scene_file` (the file rendered),
`renderer` (`mitsuba 3.9.1 scalar_rgb`), `mitsuba:spp`, `mitsuba:seed`, `mitsuba:max_depth`. There is deliberately
no `jaxfog:spp`: the fit would take the target's noise as that many samples with jaxfog's own per-sample variance,
and Mitsuba's estimator (other distance sampling, other MIS, no equiangular sampling) has another variance per
sample. Without it the fit estimates the target's noise from the image itself (`fitting.problem.block_noise`), which
errs on the side of more noise at edges.

Two cases must fail: a chromatic haze fitted with the grey model, and a target of another layout fitted with the
wrong scene file.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))
REL = os.path.relpath(HERE, REPO)  # data_synthetic/foreign
SEED0 = 20_000
SPP = 2048
EXTRA_SEEDS = {"spot_sideways_power__spot_sideways_near": SEED0 + 14, "box_fog__box_side": SEED0 + 15,
               "box_fog__box_low": SEED0 + 16,
               "room_forward__room_point": SEED0 + 17, "spot_thin_far_start__spot_side": SEED0 + 18,
               "spot_thin_far_start__spot_low": SEED0 + 19, "spot_denser__spot_side": SEED0 + 20,
               "spot_denser__spot_low": SEED0 + 21, "glass_mirror__glass_mirror_side": SEED0 + 22,
               "glass_mirror__glass_mirror_low": SEED0 + 23, "mesh_torus__mesh_side": SEED0 + 24,
               "mesh_torus__mesh_low": SEED0 + 25}
"""Views added after the first 13 targets (seeds SEED0 + 1 ... + 13 in order) keep the earlier targets' seeds. The
cases from `room_forward` on are the hard starts and scenes: a start far from a forward-scattering truth in the
point-lit room, thin forward fog from backward-leaning starts, denser fog, a glass and a mirror sphere in the beam,
and a triangle mesh, each in two views but the room."""

GREY = {"albedo": 0.9}
CASES = [
    # name, description, views (scene name, or (scene fitted, scene rendered)), truth, fit, init, determined, expect
    dict(name="spot_two_view", description="benchmark geometry, moderate fog, two views (side and low)",
         views=["spot_side", "spot_low"], truth={"sigma_t": 0.5, "g": 0.6, **GREY},
         fit=["sigma_t", "g"], init={"sigma_t": 0.3, "g": 0.2}, determined=["sigma_t", "g"], expect="pass"),
    dict(name="room_point", description="another scene: a closed room lit by a point light only, one view",
         views=["room_point"], truth={"sigma_t": 0.5, "g": 0.5, **GREY},
         fit=["sigma_t", "g"], init={"sigma_t": 0.3, "g": 0.2}, determined=["sigma_t", "g"], expect="pass"),
    dict(name="area_floor", description="another scene: an area light only over a floor with two spheres, one view",
         views=["area_floor"], truth={"sigma_t": 0.35, "g": 0.3, **GREY},
         fit=["sigma_t", "g"], init={"sigma_t": 0.2, "g": 0.0}, determined=["sigma_t", "g"], expect="pass"),
    dict(name="spot_sideways_power", description="another scene: a spot light from the side, unknown light power "
         "(sigma_t, g and intensity fitted), two views (front, and near the beam looking back toward the light; one "
         "view alone did not determine them)",
         views=["spot_sideways", "spot_sideways_near"], truth={"sigma_t": 0.4, "g": 0.5, "intensity": 60.0, **GREY},
         fit=["sigma_t", "g", "intensity"], init={"sigma_t": 0.3, "g": 0.2, "intensity": 40.0},
         determined=["sigma_t", "g", "intensity"], expect="pass"),
    dict(name="spot_dense", description="benchmark geometry, fog denser than any shipped truth, two views",
         views=["spot_side", "spot_low"], truth={"sigma_t": 1.2, "g": 0.4, **GREY},
         fit=["sigma_t", "g"], init={"sigma_t": 0.7, "g": 0.1}, determined=["sigma_t", "g"], expect="pass"),
    dict(name="room_albedo", description="the room with the point light, albedo fitted too (sigma_t, albedo, g), "
         "one view", views=["room_point"], truth={"sigma_t": 0.5, "g": 0.5, "albedo": 0.7},
         fit=["sigma_t", "albedo", "g"], init={"sigma_t": 0.3, "albedo": 0.9, "g": 0.2},
         determined=["sigma_t", "albedo", "g"], expect="pass"),
    dict(name="spot_thin_forward", description="benchmark geometry, thin strongly forward fog (g 0.85), two views",
         views=["spot_side", "spot_low"], truth={"sigma_t": 0.2, "g": 0.85, **GREY},
         fit=["sigma_t", "g"], init={"sigma_t": 0.35, "g": 0.5}, determined=["sigma_t", "g"], expect="pass"),
    dict(name="box_fog", description="benchmark geometry with the fog confined to a box below the spot light "
         "(medium.bounds; light and camera in vacuum), two views", views=["box_side", "box_low"],
         truth={"sigma_t": 0.8, "g": 0.5, **GREY},
         fit=["sigma_t", "g"], init={"sigma_t": 0.5, "g": 0.2}, determined=["sigma_t", "g"], expect="pass"),
    dict(name="chromatic_grey", description="chromatic haze (sigma_t 0.3 / 0.5 / 0.8 in R / G / B) fitted with the "
         "grey model: must fail (the model cannot explain it)", views=["spot_side", "spot_low"],
         truth={"sigma_t[r]": 0.3, "sigma_t[g]": 0.5, "sigma_t[b]": 0.8, "g": 0.5, **GREY},
         fit=["sigma_t", "g"], init={"sigma_t": 0.3, "g": 0.2}, determined=[], expect="fail"),
    dict(name="wrong_scene", description="a target of another layout of the room (sphere and light moved) fitted "
         "with room_point.json: must fail (another scene)", views=[("room_point", "room_point_moved")],
         truth={"sigma_t": 0.5, "g": 0.5, **GREY},
         fit=["sigma_t", "g"], init={"sigma_t": 0.3, "g": 0.2}, determined=[], expect="fail"),
    dict(name="room_forward", description="the point-lit room with forward fog, started at the scene file's "
         "backward-leaning values (a wrong basin of the loop before)", views=["room_point"],
         truth={"sigma_t": 0.35, "g": 0.7, **GREY}, fit=["sigma_t", "g"], init={"sigma_t": 0.7, "g": 0.3},
         determined=["sigma_t", "g"], expect="pass"),
    dict(name="spot_thin_far_start", description="benchmark geometry, thin forward fog, two views, started at "
         "isotropic scattering and nearly twice the extinction", views=["spot_side", "spot_low"],
         truth={"sigma_t": 0.25, "g": 0.85, **GREY}, fit=["sigma_t", "g"], init={"sigma_t": 0.45, "g": 0.0},
         determined=["sigma_t", "g"], expect="pass"),
    dict(name="spot_denser", description="benchmark geometry, denser fog, mildly forward, two views",
         views=["spot_side", "spot_low"], truth={"sigma_t": 1.4, "g": 0.2, **GREY}, fit=["sigma_t", "g"],
         init={"sigma_t": 0.5, "g": 0.6}, determined=["sigma_t", "g"], expect="pass"),
    dict(name="glass_mirror", description="a glass sphere and a mirror sphere in the spot's beam, two views",
         views=["glass_mirror_side", "glass_mirror_low"], truth={"sigma_t": 0.45, "g": 0.55, **GREY},
         fit=["sigma_t", "g"], init={"sigma_t": 0.3, "g": 0.2}, determined=["sigma_t", "g"], expect="pass"),
    dict(name="mesh_torus", description="a bumpy torus of 21,504 triangles in the spot's beam, two views",
         views=["mesh_side", "mesh_low"], truth={"sigma_t": 0.65, "g": 0.4, **GREY}, fit=["sigma_t", "g"],
         init={"sigma_t": 0.3, "g": 0.7}, determined=["sigma_t", "g"], expect="pass"),
]


def scene_path(name: str) -> str:
    return f"{REL}/scenes/{name}.json"


def truth_scene(path: str, truth: dict) -> dict:
    """The scene-file dict of `path` with the truth's medium (and the first light's power) in it."""
    with open(os.path.join(REPO, path)) as f:
        data = json.load(f)
    data = copy.deepcopy(data)
    for shape in data.get("shapes", []):  # a mesh file relative to the scene file: absolute in the dict
        if "file" in shape:
            shape["file"] = os.path.normpath(os.path.join(REPO, os.path.dirname(path), shape["file"]))
    med = data["medium"]
    if "sigma_t[r]" in truth:
        med["sigma_t"] = [truth[f"sigma_t[{c}]"] for c in "rgb"]
    else:
        med["sigma_t"] = truth["sigma_t"]
    med["albedo"] = truth["albedo"]
    med["g"] = truth["g"]
    if "intensity" in truth:
        light = data["lights"][0]
        light["radiance" if light["type"] == "area" else "intensity"] = truth["intensity"]
    return data


def target_path(case: str, rendered: str) -> str:
    return f"{REL}/targets/{case}__{rendered}.exr"


def case_views(case: dict) -> list[dict]:
    out = []
    for v in case["views"]:
        fitted, rendered = (v, v) if isinstance(v, str) else v
        out.append({"scene": scene_path(fitted), "rendered_scene": scene_path(rendered),
                    "target": target_path(case["name"], rendered)})
    return out


def manifest_case(case: dict) -> dict:
    return {"name": case["name"], "description": case["description"], "views": case_views(case),
            "fit": case["fit"], "init": case["init"], "truth": case["truth"], "determined": case["determined"],
            "expect": case["expect"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--spp", type=int, default=SPP)
    ap.add_argument("--only", nargs="*", default=None, help="case names to render (default all)")
    args = ap.parse_args(argv)
    import jaxfog
    from jaxfog.tools import import_mitsuba

    mi = import_mitsuba("scalar_rgb")
    renderer = f"mitsuba {mi.__version__} {mi.variant()}"
    os.makedirs(os.path.join(HERE, "targets"), exist_ok=True)
    mpath = os.path.join(HERE, "manifest.json")
    old = json.load(open(mpath)) if os.path.exists(mpath) else {}
    done = {t["file"]: t for t in old.get("targets", [])}
    index = 0
    for case in CASES:
        for view in case_views(case):
            stem = os.path.splitext(os.path.basename(view["target"]))[0]
            if stem in EXTRA_SEEDS:
                seed = EXTRA_SEEDS[stem]
            else:
                index += 1
                seed = SEED0 + index
            if args.only and case["name"] not in args.only:
                continue
            data = truth_scene(view["rendered_scene"], case["truth"])
            t0, c0 = time.perf_counter(), time.process_time()
            img = np.asarray(jaxfog.render_mitsuba(data, spp=args.spp, seed=seed), np.float32)
            wall = time.perf_counter() - t0
            meta = {"jaxfog:truth": json.dumps(case["truth"]), "jaxfog:scene_file": view["rendered_scene"],
                    "renderer": renderer, "mitsuba:spp": args.spp, "mitsuba:seed": seed,
                    "mitsuba:max_depth": data["integrator"]["max_depth"], "jaxfog:version": jaxfog.__version__}
            jaxfog.write_exr(os.path.join(REPO, view["target"]), img, meta)
            done[view["target"]] = {"file": view["target"], "case": case["name"], "scene": view["rendered_scene"],
                                    "truth": case["truth"], "renderer": renderer, "spp": args.spp, "seed": seed,
                                    "max_depth": data["integrator"]["max_depth"],
                                    "mean_pixel": float(img.mean()), "render_wall_s": round(wall, 1),
                                    "render_cpu_s": round(time.process_time() - c0, 1)}
            print(f"{view['target']}: {args.spp} spp, {wall:.1f} s, mean {img.mean():.4g}", flush=True)
            write_manifest(mpath, renderer, done)
    write_manifest(mpath, renderer, done)
    return 0


def write_manifest(path: str, renderer: str, done: dict) -> None:
    manifest = {"description": "Fit cases on targets rendered by another renderer (Mitsuba 3); generated by "
                               f"{REL}/make_foreign.py. Paths are relative to the repository root.",
                "renderer": renderer, "cases": [manifest_case(c) for c in CASES],
                "targets": sorted(done.values(), key=lambda t: t["file"])}
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(manifest, f, indent=1)
    os.replace(tmp, path)


if __name__ == "__main__":
    sys.path.insert(0, REPO)
    sys.exit(main())
