"""The same scene in Mitsuba 3, for the side-by-side run of `jaxfog.bench` (optional extra: `pip install -e .[compare]`).

`scene_dict(data)` turns a validated jaxfog scene-file dict (`load_scene(...).data`) into a `mi.load_dict` dict with
the conventions of `docs/conventions.md` (which are Mitsuba 3's):

- camera: `perspective`, `fov_axis = "x"`, `to_world = look_at(origin, target, up)`, `hdrfilm` with a box filter;
- fog: `homogeneous` (`sigma_t`, `albedo`, `hg` phase with `g`) inside a large cube (`scale(extent / 2)` around the
  camera) whose BSDF is `null`; the sensor's medium and every shape's exterior medium are the fog;
- floor/walls: `rectangle` with `to_world` columns `(edge_u / 2, edge_v / 2, normal, center)`, so the local +z
  normal becomes jaxfog's front normal `normalize(cross(edge_u, edge_v))`;
- BSDFs: `diffuse`, `conductor` with `material = "none"` (perfect mirror, times `specular_reflectance`), `dielectric`
  (no medium inside, as in jaxfog);
- lights: `point`, `spot` (`intensity`, `cutoff_angle`, `beam_width`, `to_world = look_at(position, position +
  direction, up)`), area lights as black one-sided `rectangle`s with an `area` emitter;
- integrator: `volpath` with the scene's `max_depth` and `rr_depth` above it (no Russian roulette).

Run as a program (`python -m jaxfog.bench_mitsuba SCENE.json --out X.npz`), it renders `--chunks` independent images
of `--spp` samples each (seeds 0, 1, ...) after one warm-up render that compiles the kernels, and writes the images,
the time of each render, the warm-up time and the process's peak resident memory to an `.npz`. `jaxfog.bench` runs it
in a subprocess so that its memory and threads are measured apart from JAX's, and so that a missing or broken
Mitsuba only skips the comparison.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

LLVM_CANDIDATES = (
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1",
    "/usr/lib/x86_64-linux-gnu/libLLVM-19.so.1",
    "/usr/lib/aarch64-linux-gnu/libLLVM.so.19.1",
)
VARIANT = "llvm_ad_rgb"


def _set_llvm_path() -> None:
    if "DRJIT_LIBLLVM_PATH" in os.environ:
        return
    for path in LLVM_CANDIDATES:
        if os.path.exists(path):
            os.environ["DRJIT_LIBLLVM_PATH"] = path
            return


def import_mitsuba():
    """`(mi, None)` with the LLVM RGB variant set, or `(None, reason)` when Mitsuba 3 or its LLVM backend is missing."""
    _set_llvm_path()
    try:
        import mitsuba as mi
    except Exception as e:  # ImportError, or a broken install
        return None, f"mitsuba not importable ({type(e).__name__}: {e}); install with pip install -e .[compare]"
    try:
        mi.set_variant(VARIANT)
    except Exception as e:
        return None, (f"mitsuba {mi.__version__}: variant {VARIANT} unavailable ({e}); its LLVM backend needs "
                      "libllvm19 (apt-get install -y libllvm19) and DRJIT_LIBLLVM_PATH")
    return mi, None


def _rgb(x) -> list[float]:
    if isinstance(x, (int, float)):
        return [float(x)] * 3
    return [float(v) for v in x]


def _rgb_tex(x) -> dict:
    return {"type": "rgb", "value": _rgb(x)}


def _extinction(sigma_t) -> dict:
    """`sigma_t` (and `scale`) of Mitsuba's `homogeneous`: a float for a grey medium; otherwise an RGB texture, which
    Mitsuba reads as a reflectance (each channel in [0, 1]), times `scale` = the largest channel."""
    v = _rgb(sigma_t)
    if max(v) == min(v):
        return {"sigma_t": v[0]}
    m = max(v)
    return {"sigma_t": {"type": "rgb", "value": [x / m for x in v]}, "scale": m}


def _albedo(albedo):
    v = _rgb(albedo)
    return v[0] if max(v) == min(v) else {"type": "rgb", "value": v}


def _perpendicular(d) -> list[float]:
    d = np.asarray(d, float)
    d = d / np.linalg.norm(d)
    a = np.array([0.0, 1.0, 0.0]) if abs(d[1]) < 0.9 else np.array([0.0, 0.0, 1.0])
    return list(np.cross(d, a) / np.linalg.norm(np.cross(d, a)))


def rectangle_matrix(center, edge_u, edge_v) -> np.ndarray:
    """4x4 `to_world` of Mitsuba's `rectangle` ([-1, 1]^2 at z = 0, normal +z) onto jaxfog's rectangle: the corner
    (+-1, +-1) goes to `center +- edge_u / 2 +- edge_v / 2`, the normal to `normalize(cross(edge_u, edge_v))`."""
    u, v, c = (np.asarray(x, float) for x in (edge_u, edge_v, center))
    n = np.cross(u, v)
    n = n / np.linalg.norm(n)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = u / 2, v / 2, n, c
    return m


def _bsdf(b: dict) -> dict:
    kind = b["type"]
    if kind == "diffuse":
        return {"type": "diffuse", "reflectance": _rgb_tex(b["reflectance"])}
    if kind == "mirror":
        return {"type": "conductor", "material": "none", "specular_reflectance": _rgb_tex(b.get("reflectance", 1.0))}
    if kind == "glass":
        return {"type": "dielectric", "int_ior": float(b.get("int_ior", 1.5)), "ext_ior": float(b.get("ext_ior", 1.0))}
    raise ValueError(f"no Mitsuba BSDF for {kind!r}")


def _phase(med: dict) -> dict:
    """Mitsuba's phase function for a medium: `hg` (bare g or type hg), `rayleigh`, and two-term HG as `blendphase`
    (Mitsuba blends `(1 - weight) phase1 + weight phase2`, so weight = 1 - w). Others raise (no exact counterpart)."""
    ph = med.get("phase") or {"type": "hg", "g": med["g"]}
    if ph["type"] == "hg":
        return {"type": "hg", "g": float(ph["g"])}
    if ph["type"] == "rayleigh":
        return {"type": "rayleigh"}
    if ph["type"] == "two_term_hg":
        return {"type": "blendphase", "weight": 1.0 - float(ph["w"]), "phase1": {"type": "hg", "g": float(ph["g1"])},
                "phase2": {"type": "hg", "g": float(ph["g2"])}}
    raise ValueError(f"no Mitsuba phase function for {ph['type']!r} in this comparison")


def scene_dict(data: dict, mi=None, spp: int = 16) -> dict:
    """The `mi.load_dict` dict of a validated jaxfog scene-file dict (see the module docstring)."""
    if mi is None:
        mi, reason = import_mitsuba()
        if mi is None:
            raise RuntimeError(reason)
    T = mi.ScalarTransform4f
    cam = data["camera"]
    max_depth = int(data["integrator"]["max_depth"])
    out: dict = {
        "type": "scene",
        "integrator": {"type": "volpath", "max_depth": max_depth, "rr_depth": max_depth + 1000},
    }
    med = data.get("medium")
    fog_ref = None
    if med is not None:
        out["fog"] = {"type": "homogeneous", "albedo": _albedo(med["albedo"]), "phase": _phase(med),
                      **_extinction(med["sigma_t"])}
        fog_ref = {"type": "ref", "id": "fog"}
        half = float(med.get("extent", 1000.0)) / 2
        out["fog_boundary"] = {
            "type": "cube",
            "to_world": T().translate(_rgb(cam["origin"])) @ T().scale(half),
            "bsdf": {"type": "null"},
            "interior": fog_ref,
        }
    sensor = {
        "type": "perspective",
        "fov": float(cam["fov"]),
        "fov_axis": "x",
        "to_world": T().look_at(origin=_rgb(cam["origin"]), target=_rgb(cam["target"]), up=_rgb(cam["up"])),
        "film": {"type": "hdrfilm", "width": int(cam["width"]), "height": int(cam["height"]),
                 "rfilter": {"type": "box"}, "pixel_format": "rgb"},
        "sampler": {"type": "independent", "sample_count": int(spp)},
    }
    if fog_ref is not None:
        sensor["medium"] = fog_ref
    out["sensor"] = sensor

    for i, s in enumerate(data.get("shapes", [])):
        if s["type"] == "rectangle":
            shape = {"type": "rectangle", "to_world": T(rectangle_matrix(s["center"], s["edge_u"], s["edge_v"]).tolist())}
        elif s["type"] == "sphere":
            shape = {"type": "sphere", "center": _rgb(s["center"]), "radius": float(s["radius"])}
        else:
            raise ValueError(f"no Mitsuba shape for {s['type']!r}")
        shape["bsdf"] = _bsdf(s["bsdf"])
        if fog_ref is not None:
            shape["exterior"] = fog_ref
        out[f"shape_{i}"] = shape

    for i, lt in enumerate(data.get("lights", [])):
        kind = lt["type"]
        if kind == "point":
            out[f"light_{i}"] = {"type": "point", "position": _rgb(lt["position"]), "intensity": _rgb_tex(lt["intensity"])}
        elif kind == "spot":
            p = np.asarray(lt["position"], float)
            d = np.asarray(lt["direction"], float)
            d = d / np.linalg.norm(d)
            cutoff = float(lt.get("cutoff_angle", 20.0))
            out[f"light_{i}"] = {
                "type": "spot",
                "to_world": T().look_at(origin=list(p), target=list(p + d), up=_perpendicular(d)),
                "intensity": _rgb_tex(lt["intensity"]),
                "cutoff_angle": cutoff,
                "beam_width": float(lt.get("beam_width", 0.75 * cutoff)),
            }
        elif kind == "area":
            shape = {
                "type": "rectangle",
                "to_world": T(rectangle_matrix(lt["center"], lt["edge_u"], lt["edge_v"]).tolist()),
                "bsdf": {"type": "diffuse", "reflectance": _rgb_tex(0.0)},
                "emitter": {"type": "area", "radiance": _rgb_tex(lt["radiance"])},
            }
            if fog_ref is not None:
                shape["exterior"] = fog_ref
            out[f"light_{i}"] = shape
        else:
            raise ValueError(f"no Mitsuba emitter for {kind!r}")
    return out


from ._measure import max_rss_mib  # noqa: E402


def render_chunks(data: dict, spp: int, chunks: int, seed0: int = 0, log=None) -> dict:
    """Render `chunks` independent `spp`-sample images of the scene (seeds `seed0 + i`) after one warm-up render.

    Returns `images` `(chunks, H, W, 3)` float32, `times` (s, each render until its pixels are on the host),
    `warmup_s` (the first render: kernel tracing and LLVM compilation included), `version`, `variant`, `threads`."""
    mi, reason = import_mitsuba()
    if mi is None:
        raise RuntimeError(reason)
    import drjit as dr

    scene = mi.load_dict(scene_dict(data, mi, spp))
    t0 = time.perf_counter()
    np.asarray(mi.render(scene, spp=spp, seed=10_000_019))
    warmup = time.perf_counter() - t0
    images, times = [], []
    for i in range(chunks):
        t0 = time.perf_counter()
        img = np.asarray(mi.render(scene, spp=spp, seed=seed0 + i), dtype=np.float32)
        times.append(time.perf_counter() - t0)
        images.append(img[..., :3])
        if log is not None:
            log(f"mitsuba chunk {i + 1}/{chunks}: {spp} spp in {times[-1]:.2f} s, mean {img[..., :3].mean():.4g}")
    try:
        threads = int(dr.thread_count())
    except Exception:  # pragma: no cover - older drjit
        threads = -1
    return {"images": np.stack(images), "times": np.asarray(times), "warmup_s": warmup, "version": mi.__version__,
            "variant": VARIANT, "threads": threads}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m jaxfog.bench_mitsuba", description=__doc__.split("\n\n")[0])
    p.add_argument("scene", metavar="SCENE.json")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--spp", type=int, default=16, help="samples per pixel of each render (default 16)")
    p.add_argument("--chunks", type=int, default=4, help="independent renders (default 4)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, metavar="OUT.npz")
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)

    mi, reason = import_mitsuba()
    if mi is None:
        print(f"mitsuba skipped: {reason}", file=sys.stderr)
        return 3
    from ._scene_io import load_scene

    sf = load_scene(args.scene, args.overrides)
    log = None if args.quiet else (lambda s: print(s, file=sys.stderr, flush=True))
    res = render_chunks(sf.data, args.spp, args.chunks, args.seed, log=log)
    tmp = args.out + ".tmp.npz"
    np.savez(tmp, images=res["images"], times=res["times"], warmup_s=res["warmup_s"], version=res["version"],
             variant=res["variant"], threads=res["threads"], max_rss_mib=max_rss_mib(), spp=args.spp)
    os.replace(tmp, args.out)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
