"""The same scene in Mitsuba 3, to cross-check a jaxfog render (optional extra `compare`: `pip install "jaxfog[compare]"`).

`to_mitsuba(scene_file)` builds the `mi.load_dict` dict of a jaxfog scene file without Mitsuba; `render_mitsuba`
renders it (it needs Mitsuba). How each part maps is in `docs/conventions.md` ("Mitsuba 3"); in short:

- camera: `perspective` with `fov_axis = "x"`, `to_world = look_at(origin, target, up)`, `hdrfilm` with a box filter;
- medium: `homogeneous` (`sigma_t`, `albedo`; phase `hg` with `g`, `rayleigh`, two-term HG as `blendphase` of two
  `hg`, fog droplets as a `tabphase` of jaxfog's own pdf; Draine alone is refused) filling a cube of side `extent`
  around the camera with a `null` BSDF; the sensor's medium and every shape's exterior medium. Bounded fog
  (`bounds`): the cube is the box; the sensor's medium only if the camera is inside it, and only glass objects
  inside it get the fog as exterior (a reflecting surface keeps the ray's medium);
- rectangles: `rectangle` with `to_world` columns `(edge_u / 2, edge_v / 2, normal, center)`, so Mitsuba's local +z
  normal is jaxfog's front normal `normalize(cross(edge_u, edge_v))`; spheres: `sphere`; meshes: `ply` / `obj`
  (`filename`, `face_normals` unless `smooth`, `to_world`: the same matrix);
- BSDFs: `diffuse`; mirror: `conductor` with `material = "none"` times `specular_reflectance`; glass: `dielectric`
  (no medium inside, as in jaxfog);
- lights: `point`; `spot` (`cutoff_angle`, `beam_width`, `to_world = look_at(position, position + direction, up)`);
  area lights: one-sided `rectangle`s with an `area` emitter and a black `diffuse` BSDF;
- integrator: `volpath` with the scene's `max_depth` (both count segments) and no Russian roulette.
"""

from __future__ import annotations

import os
import sys
from typing import Any, Callable

import numpy as np

__all__ = ["to_mitsuba", "render_mitsuba", "import_mitsuba", "look_at_matrix", "rectangle_matrix"]

DEFAULT_VARIANT = "scalar_rgb"
"""The Mitsuba variant `render_mitsuba` sets when none is set: it needs no LLVM or CUDA. `llvm_ad_rgb` is much faster
where Dr.Jit's LLVM backend works (libLLVM 19 here; with an older libLLVM it can abort the process)."""

LLVM_CANDIDATES = (
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1",
    "/usr/lib/x86_64-linux-gnu/libLLVM-19.so.1",
    "/usr/lib/aarch64-linux-gnu/libLLVM.so.19.1",
)
"""Where `import_mitsuba` looks for libLLVM 19 when `DRJIT_LIBLLVM_PATH` is not set (Debian/Ubuntu `libllvm19`)."""


# ------------------------------------------------------------------------------------------------ pure geometry
def _vec(x) -> np.ndarray:
    return np.asarray(x, np.float64).reshape(3)


def _rgb(x) -> list[float]:
    """An RGB value of a scene file (a number or 3 numbers) as 3 floats."""
    if isinstance(x, (int, float)):
        return [float(x)] * 3
    return [float(v) for v in x]


def _rgb_tex(x) -> dict:
    return {"type": "rgb", "value": _rgb(x)}


def look_at_matrix(origin, target, up) -> np.ndarray:
    """4x4 `to_world` of Mitsuba's `ScalarTransform4f().look_at(origin, target, up)`: columns `(left, new_up, dir,
    origin)` with `dir = normalize(target - origin)`, `left = normalize(cross(up, dir))`, `new_up = cross(dir, left)`."""
    o = _vec(origin)
    d = _vec(target) - o
    d = d / np.linalg.norm(d)
    left = np.cross(_vec(up), d)
    left = left / np.linalg.norm(left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, np.cross(d, left), d, o
    return m


def rectangle_matrix(center, edge_u, edge_v) -> np.ndarray:
    """4x4 `to_world` of Mitsuba's `rectangle` ([-1, 1]^2 at z = 0, normal +z) onto jaxfog's rectangle: the corner
    (+-1, +-1) goes to `center +- edge_u / 2 +- edge_v / 2`, the normal to `normalize(cross(edge_u, edge_v))`."""
    u, v, c = _vec(edge_u), _vec(edge_v), _vec(center)
    n = np.cross(u, v)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = u / 2, v / 2, n / np.linalg.norm(n), c
    return m


def _perpendicular(d) -> np.ndarray:
    """A unit vector perpendicular to `d` (the `up` of a spot light's frame; the spot is symmetric about its axis)."""
    d = _vec(d) / np.linalg.norm(d)
    a = np.array([0.0, 1.0, 0.0]) if abs(d[1]) < 0.9 else np.array([0.0, 0.0, 1.0])
    p = np.cross(d, a)
    return p / np.linalg.norm(p)


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


def _phase(med: dict) -> dict:
    phase = med.get("phase")
    if phase is None:  # the scene file's shorthand: a bare g is Henyey–Greenstein
        return {"type": "hg", "g": float(med["g"])}
    if phase["type"] == "hg":
        return {"type": "hg", "g": float(phase["g"])}
    if phase["type"] == "rayleigh":
        return {"type": "rayleigh"}
    if phase["type"] == "two_term_hg":  # w HG(g1) + (1 - w) HG(g2); blendphase's weight is that of phase2
        return {"type": "blendphase", "weight": 1.0 - float(phase["w"]),
                "phase1": {"type": "hg", "g": float(phase["g1"])}, "phase2": {"type": "hg", "g": float(phase["g2"])}}
    if phase["type"] == "droplet":
        return {"type": "tabphase", "values": ",".join(f"{v:.9g}" for v in droplet_table(float(phase["diameter"])))}
    raise ValueError(f"to_mitsuba: no Mitsuba phase function for medium.phase.type {phase['type']!r}")


TABPHASE_SIZE = 2**17 + 1
"""Entries of the `tabphase` table of the droplet phase function (nodes at cos theta = -1 + 2 i / (n - 1), spacing
1.5e-5: the forward peak of d = 5..50 um droplets, HG with g_HG = 0.97..0.998, is 1 - g_HG ~ 1e-3..0.03 rad wide, i.e.
(1 - g_HG)^2 / 2 ~ 2e-6..5e-4 in cos). The integral of |p_table - p| over the sphere (`tabphase_error`) is 6e-5 at
5 um, 7e-4 at 8 um, 2e-3 at 10 um, 0.04 at 20 um and 0.5 at 50 um, where the regular table cannot resolve the peak
(docs/results/fit_models.md); about 1.8 MB of text per table."""


def droplet_table(diameter: float, n: int = TABPHASE_SIZE) -> np.ndarray:
    """jaxfog's droplet pdf (1/sr) at Mitsuba `tabphase`'s nodes. tabphase (src/phase/tabphase.cpp) lays its values
    out regularly over cos theta in [-1, 1] in the *physics* convention, cos theta = 1 forward (it evaluates at
    `-dot(wo, wi)` with Mitsuba's wi pointing away from the interaction point), which is jaxfog's convention
    (docs/conventions.md: cos theta = 1 is forward scattering); the last value is the forward peak. tabphase
    interpolates linearly in cos theta and renormalises the table."""
    import jax.numpy as jnp

    from ._phase import Droplet

    omc = np.arange(n - 1, -1, -1, dtype=np.float64) * (2.0 / (n - 1))  # 1 - mu, exact at the forward end
    return np.asarray(Droplet(diameter).eval_polar(jnp.asarray(omc, jnp.float32)), np.float64)


def tabphase_error(diameter: float, n: int = TABPHASE_SIZE, sub: int = 16) -> float:
    """Integral over the sphere of |p_table - p| (a fraction of the phase function's integral, 1) for the droplet
    `tabphase` table: p_table is the linear interpolant of the table, renormalised as tabphase does; each cell is
    sampled at `sub` points (midpoint rule in cos theta)."""
    import jax.numpy as jnp

    from ._phase import Droplet

    table = droplet_table(diameter, n)
    h = 2.0 / (n - 1)
    norm = 2.0 * np.pi * h * (table.sum() - 0.5 * (table[0] + table[-1]))  # trapezoid = integral of the interpolant
    t = (np.arange(sub) + 0.5) / sub
    omc_nodes = np.arange(n - 1, -1, -1, dtype=np.float64) * h
    # cell i spans omc_nodes[i] .. omc_nodes[i + 1] (cos increasing)
    omc = omc_nodes[:-1, None] - t[None, :] * h
    exact = np.asarray(Droplet(diameter).eval_polar(jnp.asarray(omc.ravel(), jnp.float32)), np.float64).reshape(omc.shape)
    interp = (table[:-1, None] * (1 - t) + table[1:, None] * t) / norm
    return float(2.0 * np.pi * h / sub * np.abs(interp - exact).sum())


def _bsdf(b: dict, where: str) -> dict:
    kind = b["type"]
    if kind == "diffuse":
        return {"type": "diffuse", "reflectance": _rgb_tex(b["reflectance"])}
    if kind == "mirror":
        return {"type": "conductor", "material": "none", "specular_reflectance": _rgb_tex(b.get("reflectance", 1.0))}
    if kind == "glass":
        return {"type": "dielectric", "int_ior": float(b.get("int_ior", 1.5)), "ext_ior": float(b.get("ext_ior", 1.0))}
    raise ValueError(f"to_mitsuba: no Mitsuba BSDF for {where}.bsdf.type {kind!r}")


# --------------------------------------------------------------------------------------------------- the dict
def _scene_data(scene, overrides) -> dict:
    """The validated scene-file dict of a path, a `SceneFile` or a scene-file dict."""
    from ._scene_io import SceneFile, load_scene, scene_from_dict

    if isinstance(scene, SceneFile):
        if overrides:
            return scene_from_dict(scene.data, scene.path, overrides).data
        return scene.data
    if isinstance(scene, dict):
        return scene_from_dict(scene, "<dict>", overrides).data
    if isinstance(scene, (str, os.PathLike)):
        return load_scene(scene, overrides).data
    raise TypeError("to_mitsuba: scene must be a scene file path, a jaxfog SceneFile (load_scene(...)) or a scene-file "
                    f"dict, got {type(scene).__name__} (a Scene Module has no file form; pass its SceneFile)")


def _default_transform() -> Callable[[np.ndarray], Any]:
    """`mi.ScalarTransform4f` when Mitsuba is imported and has a variant set, else the numpy matrix itself."""
    mi = sys.modules.get("mitsuba")
    try:
        if mi is not None and mi.variant() is not None:
            return lambda m: mi.ScalarTransform4f(np.asarray(m, np.float64).tolist())
    except Exception:  # a half-imported or broken Mitsuba: plain matrices
        pass
    return lambda m: m


def _positive_int(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"to_mitsuba: {name} must be a positive integer, got {value!r}")
    return int(value)


def to_mitsuba(scene, *, spp: int | None = None, max_depth: int | None = None, seed: int = 0, overrides=(),
               transform: Callable[[np.ndarray], Any] | None = None) -> dict:
    """The Mitsuba 3 scene dict (for `mi.load_dict`) of a jaxfog scene file. Needs no Mitsuba to build.

    **Arguments:**
    - `scene`: a scene file path, a `SceneFile` (`jaxfog.load_scene(...)`) or a scene-file dict (validated here).
    - `spp`: the sampler's `sample_count` (default: the file's `integrator.spp`; `mi.render(..., spp=N)` overrides it).
    - `max_depth`: the `volpath` integrator's `max_depth`, in segments as in jaxfog (default: the file's
      `integrator.max_depth`). Russian roulette is off (`rr_depth` above `max_depth`), as in jaxfog, except for
      `max_depth = -1` (paths of any length), where both use Russian roulette from the file's `rr_depth` on.
    - `seed`: the `independent` sampler's seed (default 0).
    - `overrides`: `"key.path=value"` strings applied before conversion, as in `load_scene`.
    - `transform`: turns each 4x4 `to_world` matrix (numpy float64) into what the dict holds. Default: a
      `mi.ScalarTransform4f` when `mitsuba` is imported and a variant is set (so `mi.load_dict(to_mitsuba(path))`
      works), otherwise the numpy matrix (for inspection; `mi.load_dict` accepts only Mitsuba transforms).

    **Returns:** a dict with `"type": "scene"`, `"integrator"`, `"sensor"`, `"fog"` and `"fog_boundary"` (when the
    scene has a medium), `"shape_<i>"` per shape and `"light_<i>"` per light (scene order). **Raises:** `SceneError`
    for an invalid scene, `ValueError` for a part Mitsuba has no counterpart for or a bad `spp`/`max_depth`.
    """
    data = _scene_data(scene, overrides)
    to_world = transform if transform is not None else _default_transform()
    spp = _positive_int(data["integrator"]["spp"] if spp is None else spp, "spp")
    max_depth = data["integrator"]["max_depth"] if max_depth is None else max_depth
    if max_depth != -1:
        max_depth = _positive_int(max_depth, "max_depth")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= seed < 2**32:
        raise ValueError(f"to_mitsuba: seed must be an integer in [0, 2^32), got {seed!r}")
    cam = data["camera"]
    out: dict = {
        "type": "scene",
        # fixed depths: no Russian roulette, as in jaxfog; max_depth = -1: Russian roulette from rr_depth on
        "integrator": {"type": "volpath", "max_depth": max_depth,
                       "rr_depth": int(data["integrator"].get("rr_depth", 5)) if max_depth == -1 else max_depth + 1000},
    }
    med = data.get("medium")
    bounded = med is not None and med.get("bounds") is not None
    fog_ref = None
    if med is not None:
        if med.get("type", "homogeneous") != "homogeneous":
            raise ValueError(f"to_mitsuba: no Mitsuba medium for medium.type {med['type']!r}")
        out["fog"] = {"type": "homogeneous", "albedo": _albedo(med["albedo"]), "phase": _phase(med),
                      **_extinction(med["sigma_t"])}
        fog_ref = {"type": "ref", "id": "fog"}
        box = med.get("bounds")
        if box is None:  # fog filling space: a cube of side `extent` around the camera
            cube = np.diag([float(med["extent"]) / 2] * 3 + [1.0])
            cube[:3, 3] = _vec(cam["origin"])
        else:
            lo, hi = _vec(box["min"]), _vec(box["max"])
            cube = np.diag(list((hi - lo) / 2) + [1.0])
            cube[:3, 3] = (lo + hi) / 2
        out["fog_boundary"] = {"type": "cube", "to_world": to_world(cube), "bsdf": {"type": "null"},
                               "interior": fog_ref}
        if box is not None and not _inside(box)(cam["origin"]):
            fog_ref = None  # the camera starts in vacuum; rays enter the fog through the cube
    sensor = {
        "type": "perspective",
        "fov": float(cam["fov"]),
        "fov_axis": "x",
        "to_world": to_world(look_at_matrix(cam["origin"], cam["target"], cam["up"])),
        "film": {"type": "hdrfilm", "width": int(cam["width"]), "height": int(cam["height"]),
                 "rfilter": {"type": "box"}, "pixel_format": "rgb"},
        "sampler": {"type": "independent", "sample_count": spp, "seed": int(seed)},
    }
    if fog_ref is not None:
        sensor["medium"] = fog_ref
    out["sensor"] = sensor

    for i, s in enumerate(data.get("shapes", [])):
        if s["type"] == "rectangle":
            shape = {"type": "rectangle", "to_world": to_world(rectangle_matrix(s["center"], s["edge_u"], s["edge_v"]))}
        elif s["type"] == "sphere":
            shape = {"type": "sphere", "center": _rgb(s["center"]), "radius": float(s["radius"])}
        elif s["type"] == "mesh":
            from ._mesh import transform_matrix

            ext = os.path.splitext(s["file"])[1].lower()
            shape = {"type": "ply" if ext == ".ply" else "obj", "filename": s["file"],
                     "face_normals": not s["smooth"], "to_world": to_world(transform_matrix(s["to_world"]))}
        else:
            raise ValueError(f"to_mitsuba: no Mitsuba shape for shapes.{i}.type {s['type']!r}")
        shape["bsdf"] = _bsdf(s["bsdf"], f"shapes.{i}")
        if bounded:
            # bounded fog: a reflecting surface keeps the ray's medium (no transition); a glass object is a medium
            # transition and must know what surrounds it (conventions: wholly inside or outside the box)
            if s["bsdf"]["type"] == "glass":
                if s["type"] == "mesh":
                    raise ValueError(f"to_mitsuba: shapes.{i}: a glass mesh in bounded fog is not exported")
                if _inside(med["bounds"])(s["center"]):
                    shape["exterior"] = {"type": "ref", "id": "fog"}
        elif fog_ref is not None:
            shape["exterior"] = fog_ref
        out[f"shape_{i}"] = shape

    for i, lt in enumerate(data.get("lights", [])):
        kind = lt["type"]
        if kind == "point":
            out[f"light_{i}"] = {"type": "point", "position": _rgb(lt["position"]), "intensity": _rgb_tex(lt["intensity"])}
        elif kind == "spot":
            p, d = _vec(lt["position"]), _vec(lt["direction"])
            d = d / np.linalg.norm(d)
            out[f"light_{i}"] = {
                "type": "spot",
                "to_world": to_world(look_at_matrix(p, p + d, _perpendicular(d))),
                "intensity": _rgb_tex(lt["intensity"]),
                "cutoff_angle": float(lt["cutoff_angle"]),
                "beam_width": float(lt["beam_width"]),
            }
        elif kind == "area":
            shape = {
                "type": "rectangle",
                "to_world": to_world(rectangle_matrix(lt["center"], lt["edge_u"], lt["edge_v"])),
                "bsdf": {"type": "diffuse", "reflectance": _rgb_tex(0.0)},
                "emitter": {"type": "area", "radiance": _rgb_tex(lt["radiance"])},
            }
            if fog_ref is not None and not bounded:
                shape["exterior"] = fog_ref
            out[f"light_{i}"] = shape
        else:
            raise ValueError(f"to_mitsuba: no Mitsuba emitter for lights.{i}.type {kind!r}")
    return out


def _inside(box):
    """A test of whether a point lies in the closed box `{"min": ..., "max": ...}`."""
    lo, hi = _vec(box["min"]), _vec(box["max"])
    return lambda p: bool(np.all(_vec(p) >= lo) and np.all(_vec(p) <= hi))


# ------------------------------------------------------------------------------------------------ with Mitsuba
def _set_llvm_path() -> None:
    if "DRJIT_LIBLLVM_PATH" in os.environ:
        return
    for path in LLVM_CANDIDATES:
        if os.path.exists(path):
            os.environ["DRJIT_LIBLLVM_PATH"] = path
            return


def import_mitsuba(variant: str | None = None):
    """The `mitsuba` module with an RGB variant set: `variant`, else the one already set, else `DEFAULT_VARIANT`.

    **Raises:** `ImportError` naming the `compare` extra when Mitsuba 3 is missing or broken, or the variant is
    unavailable."""
    _set_llvm_path()
    try:
        import mitsuba as mi
    except Exception as e:  # ImportError, or a broken install
        raise ImportError(f"Mitsuba 3 is not importable ({type(e).__name__}: {e}); install the optional extra: "
                          'pip install "jaxfog[compare]" (or pip install -e ".[compare]" in a checkout)') from e
    if variant is None:
        current = mi.variant()
        variant = current if current is not None and current.endswith("_rgb") else DEFAULT_VARIANT
    if not variant.endswith("_rgb"):
        raise ValueError(f"render_mitsuba: variant must be an RGB variant (e.g. scalar_rgb, llvm_ad_rgb), got {variant!r}")
    try:
        mi.set_variant(variant)
    except Exception as e:
        raise ImportError(f"Mitsuba {mi.__version__}: variant {variant} unavailable ({e}); available: "
                          f"{', '.join(mi.variants())}") from e
    return mi


def render_mitsuba(scene, spp: int | None = None, seed: int = 0, *, max_depth: int | None = None, overrides=(),
                   variant: str | None = None) -> np.ndarray:
    """Render a jaxfog scene file in Mitsuba 3 (`volpath`): linear RGB radiance, `(height, width, 3)` float32.

    **Arguments:** `scene`, `spp`, `max_depth`, `overrides` as in `to_mitsuba`; `seed`: Mitsuba's seed (its images
    are independent of jaxfog's whatever the seeds); `variant`: the Mitsuba variant (see `import_mitsuba`; default
    `scalar_rgb` unless one is set). **Raises:** `ImportError` naming the `compare` extra when Mitsuba is missing.
    """
    mi = import_mitsuba(variant)
    d = to_mitsuba(scene, spp=spp, max_depth=max_depth, seed=seed, overrides=overrides,
                   transform=lambda m: mi.ScalarTransform4f(np.asarray(m, np.float64).tolist()))
    loaded = mi.load_dict(d)
    img = mi.render(loaded, spp=d["sensor"]["sampler"]["sample_count"], seed=int(seed))
    return np.asarray(img, dtype=np.float32)[..., :3]
