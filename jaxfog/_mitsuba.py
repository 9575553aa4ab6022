"""The same scene in Mitsuba 3, to cross-check a jaxfog render (optional extra `compare`: `pip install "jaxfog[compare]"`).

`to_mitsuba(scene_file)` builds the `mi.load_dict` dict of a jaxfog scene file without Mitsuba; `render_mitsuba`
renders it (it needs Mitsuba). Each part of the file is converted by its own function, registered under the part's
`"type"` in one of the tables `PHASES`, `MEDIA`, `SHAPES`, `BSDFS`, `LIGHTS` (a new kind adds a function, not a
branch). How each part maps is in `docs/conventions.md` ("Mitsuba 3"); in short:

- camera: `perspective` with `fov_axis = "x"`, `to_world = look_at(origin, target, up)`, `hdrfilm` with a box filter;
- homogeneous medium: `homogeneous` (`sigma_t`, `albedo`; phase `hg` with `g`, `rayleigh`, two-term HG as
  `blendphase` of two `hg`, fog droplets as a `tabphase` of jaxfog's own pdf; Draine alone is refused) filling a
  cube of side `extent` around the camera with a `null` BSDF; the sensor's medium and every shape's exterior medium.
  Bounded fog (`bounds`): the cube is the box; the sensor's medium only if the camera is inside it, and only glass
  objects inside it get the fog as exterior (a reflecting surface keeps the ray's medium);
- height fog: `heterogeneous` with a `gridvolume` of the extinction along `up` (`height_grid`: texel centres at most
  `GRID_STEP` scale heights apart, so the grid's extinction is within `GRID_REL_ERROR` of jaxfog's), in a box of
  side `extent` across and from where the fog below the camera and lights is opaque to where the fog above is
  negligible; otherwise as homogeneous fog filling space;
- grid fog: `heterogeneous` with a `gridvolume` of the file's grid (`filter_type = "trilinear"`, `wrap_mode =
  "clamp"`, `to_world` mapping the unit cube onto the box), `scale`, `albedo` and the phase, inside the box's `cube`
  with a `null` BSDF as bounded homogeneous fog;
- rectangles: `rectangle` with `to_world` columns `(edge_u / 2, edge_v / 2, normal, center)`, so Mitsuba's local +z
  normal is jaxfog's front normal `normalize(cross(edge_u, edge_v))`; spheres: `sphere`; meshes: `ply` / `obj`
  (`filename`, `face_normals` unless `smooth`, `to_world`: the same matrix);
- BSDFs: `diffuse`; mirror: `conductor` with `material = "none"` times `specular_reflectance`; glass: `dielectric`
  (no medium inside, as in jaxfog);
- lights: `point`; `spot` (`cutoff_angle`, `beam_width`, `to_world = look_at(position, position + direction, up)`);
  area lights: one-sided `rectangle`s with an `area` emitter and a black `diffuse` BSDF; directional lights:
  `directional` (`direction` the light travels in, `irradiance`);
- integrator: `volpath` with the scene's `max_depth` (both count segments) and no Russian roulette.
"""

from __future__ import annotations

import math
import os
import sys
from typing import Any, Callable, NamedTuple

import numpy as np

__all__ = ["to_mitsuba", "render_mitsuba", "import_mitsuba", "look_at_matrix", "rectangle_matrix", "height_grid"]

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


# ------------------------------------------------------------------------------------------------ dispatch
class Converters:
    """The converters of one kind of scene part (`part`: "medium", "shape", ...), each registered under the scene
    file's `"type"` of the parts it converts. Calling the table converts a part: `table(value, where, *args)` is
    `converter(value, *args)`; `where` (the part's key path) names it in the error for a type with no converter."""

    def __init__(self, part: str):
        self.part = part
        self._by_type: dict[str, Callable[..., Any]] = {}

    @property
    def kinds(self) -> frozenset[str]:
        """The scene-file types with a converter."""
        return frozenset(self._by_type)

    def register(self, kind: str):
        """Decorator: the function converts the parts of `"type": kind`."""
        def add(fn):
            self._by_type[kind] = fn
            return fn
        return add

    def __call__(self, value: dict, where: str, *args):
        convert = self._by_type.get(value["type"])
        if convert is None:
            raise ValueError(f"to_mitsuba: no Mitsuba {self.part} for {where}.type {value['type']!r}")
        return convert(value, *args)


PHASES = Converters("phase function")
MEDIA = Converters("medium")
SHAPES = Converters("shape")
BSDFS = Converters("BSDF")
LIGHTS = Converters("emitter")


class Fog(NamedTuple):
    """A converted medium: the Mitsuba medium dict (`medium`, id `fog`), the `to_world` of the `cube` it fills
    (`cube`, numpy, Mitsuba's [-1, 1]^3 onto the box) and whether it stands for fog filling space (`fills_space`:
    every shape gets it as exterior) rather than a box of it (only glass inside the box does)."""

    medium: dict
    cube: np.ndarray
    fills_space: bool

    def contains(self, p) -> bool:
        """Whether the point `p` lies in the cube (closed, up to rounding)."""
        local = np.linalg.solve(self.cube, np.append(_vec(p), 1.0))[:3]
        return bool(np.all(np.abs(local) <= 1.0 + 1e-9))


class Export(NamedTuple):
    """What every converter may need beyond its own part: `to_world` (a 4x4 numpy matrix to the dict's transform),
    `volume` (a numpy grid `(z, y, x, channels)` to the dict's volume data), the scene-file dict `data`, and the
    converted fog (`fog`, None without a medium)."""

    to_world: Callable[[np.ndarray], Any]
    volume: Callable[[np.ndarray], Any]
    data: dict
    fog: Fog | None = None


def _fog_ref() -> dict:
    """A reference to the medium `fog` (a new dict each time: the caller may edit the dict it gets)."""
    return {"type": "ref", "id": "fog"}


# ------------------------------------------------------------------------------------------------ phase functions
def _phase(med: dict) -> dict:
    """The medium's phase function: its `phase` part, or Henyey–Greenstein for the scene file's shorthand `g`."""
    if med.get("phase") is None:
        return {"type": "hg", "g": float(med["g"])}
    return PHASES(med["phase"], "medium.phase")


@PHASES.register("hg")
def _hg(phase: dict) -> dict:
    return {"type": "hg", "g": float(phase["g"])}


@PHASES.register("rayleigh")
def _rayleigh(phase: dict) -> dict:
    return {"type": "rayleigh"}


@PHASES.register("two_term_hg")
def _two_term_hg(phase: dict) -> dict:
    """`w HG(g1) + (1 - w) HG(g2)`; `blendphase`'s weight is that of `phase2`."""
    return {"type": "blendphase", "weight": 1.0 - float(phase["w"]),
            "phase1": {"type": "hg", "g": float(phase["g1"])}, "phase2": {"type": "hg", "g": float(phase["g2"])}}


@PHASES.register("droplet")
def _droplet(phase: dict) -> dict:
    return {"type": "tabphase", "values": ",".join(f"{v:.9g}" for v in droplet_table(float(phase["diameter"])))}


# ---------------------------------------------------------------------------------------------------- media
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


def _cube(center, half_axes) -> np.ndarray:
    """`to_world` of Mitsuba's `cube` ([-1, 1]^3) onto the box with this centre and half axes (3 columns)."""
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = np.column_stack([_vec(a) for a in half_axes]), _vec(center)
    return m


@MEDIA.register("homogeneous")
def _homogeneous(med: dict, ex: Export) -> Fog:
    """`homogeneous` in a cube of side `extent` around the camera (fog filling space), or in the box `bounds`."""
    medium = {"type": "homogeneous", "albedo": _albedo(med["albedo"]), "phase": _phase(med),
              **_extinction(med["sigma_t"])}
    box = med.get("bounds")
    if box is None:
        half = float(med["extent"]) / 2
        return Fog(medium, _cube(ex.data["camera"]["origin"], np.eye(3) * half), fills_space=True)
    lo, hi = _vec(box["min"]), _vec(box["max"])
    return Fog(medium, _cube((lo + hi) / 2, np.diag((hi - lo) / 2)), fills_space=False)


GRID_REL_ERROR = 1e-3
"""Bound on the relative error of the height-fog grid's extinction between its first and last texel centres: the
grid (trilinear) interpolates `exp(-h / H)` linearly between centres `a H` apart, which overestimates it by at most
`max_t ((1 - t) e^(a t) + t e^(-a (1 - t))) - 1 ~ a^2 / 8` (9.9e-4 at `a = GRID_STEP`); an optical depth across
whole texels is too large by `(a / 2) coth(a / 2) - 1 ~ a^2 / 12` (6.6e-4). A pixel changes by this times its
log-derivative w.r.t. log sigma_0 (-0.26 and -0.36 on average, at most 0.7, in the shipped height-fog views)."""

GRID_STEP = 0.089
"""Largest distance between the grid's texel centres, in scale heights `H` (see `GRID_REL_ERROR`)."""

TAU_ABOVE = 1e-4
"""The grid's last texel centre is where the extinction has fallen to `TAU_ABOVE / extent` in every channel (or
`extent` above the highest of the camera and the lights): above it a segment no longer than `extent` (jaxfog's
longest without a surface) has an optical depth below `TAU_ABOVE`, which Mitsuba leaves out beyond the grid."""

TAU_BELOW = 5.0
"""The grid's first texel centre is where the fog between it and the lowest of the camera and the lights has a
vertical optical depth of at least `TAU_BELOW` in every channel with fog (and at least one texel, at most `extent`,
below that lowest point). A path that goes below the grid crosses that layer twice (down from the camera, up to a
light), so it carries a factor below `exp(-2 TAU_BELOW) = 4.5e-5` in either renderer; Mitsuba has no fog below the
grid, jaxfog ever denser fog. (The exception, a directional light shining upward from below the horizon, reaches
the scene through the layer once in Mitsuba and never in jaxfog.) The layer's densest extinction, about
`sigma(lowest) + TAU_BELOW / H`, is Mitsuba's majorant, which sets its cost."""


class HeightGrid(NamedTuple):
    """The extinction of height fog sampled along `up` (`height_grid`): texel `i` spans the heights
    `bottom + [i, i + 1] step` and holds `sigma[i]` (RGB, 1/scene unit), the exact extinction at its centre."""

    bottom: float
    step: float
    sigma: np.ndarray

    @property
    def top(self) -> float:
        return self.bottom + len(self.sigma) * self.step


def height_grid(sigma_0, height_scale, base_height, extent, lowest, highest) -> HeightGrid:
    """The texels along height of jaxfog's `sigma_0 exp(-(h - base_height) / height_scale)` for a scene whose camera
    and lights lie between the heights `lowest` and `highest` (scene units along `up`), with fog followed `extent`
    along rays: centres from where the fog below `lowest` is opaque (`TAU_BELOW`) to where the fog above is
    negligible (`TAU_ABOVE`), at most `GRID_STEP` scale heights apart (`GRID_REL_ERROR`), a half texel beyond them
    at each end (constant there). `sigma_0` must have a channel > 0. Extinctions above e^80 are e^80, as in jaxfog."""
    from ._height import LOG_BIG

    s0, H, h0 = np.asarray(_rgb(sigma_0)), float(height_scale), float(base_height)
    fog = s0[s0 > 0]
    hi = min(h0 + H * math.log(fog.max() * extent / TAU_ABOVE), highest + extent)
    # the layer [lo, lowest] has vertical optical depth H (sigma(lo) - sigma(lowest)) = TAU_BELOW in the thinnest
    # channel: lo = lowest - H log(1 + TAU_BELOW / (H sigma(lowest))), from logarithms (sigma(lowest) may underflow)
    y = math.log(TAU_BELOW / (H * fog.min())) + (lowest - h0) / H
    lo = max(lowest - H * max(float(np.logaddexp(0.0, y)), GRID_STEP), lowest - extent)  # at least a texel below
    hi = max(hi, lo + GRID_STEP * H)
    n = math.ceil((hi - lo) / (GRID_STEP * H))
    step = (hi - lo) / n
    centres = lo + step * np.arange(n + 1)
    log_s0 = np.log(np.where(s0 > 0, s0, 1.0))
    sigma = np.where(s0 > 0, np.exp(np.minimum(log_s0[None, :] - (centres[:, None] - h0) / H, LOG_BIG)), 0.0)
    return HeightGrid(lo - step / 2, step, sigma)


def _anchors(part: dict) -> list[np.ndarray]:
    """The points of the camera or a light that the height-fog grid must hold: its origin or position, an area
    light's corners; none for a directional light (it is at infinity)."""
    if "edge_u" in part:
        c, u, v = _vec(part["center"]), _vec(part["edge_u"]) / 2, _vec(part["edge_v"]) / 2
        return [c + a * u + b * v for a in (-1, 1) for b in (-1, 1)]
    return [_vec(part[k]) for k in ("origin", "position") if k in part]


@MEDIA.register("height")
def _height(med: dict, ex: Export) -> Fog:
    """`heterogeneous` with a `gridvolume` of `height_grid` along `up` (2 texels across: the fog is constant there),
    in a box of side `extent` across, centred on the camera; grey fog as one channel, RGB as three."""
    up = _vec(med["up"]) / np.linalg.norm(med["up"])
    extent = float(med["extent"])
    if max(_rgb(med["sigma_0"])) == 0:  # no fog: an empty homogeneous medium
        return _homogeneous({**med, "sigma_t": 0.0}, ex)
    heights = [float(p @ up) for part in (ex.data["camera"], *ex.data.get("lights", [])) for p in _anchors(part)]
    grid = height_grid(med["sigma_0"], med["height_scale"], med["base_height"], extent, min(heights), max(heights))
    across = _perpendicular(up)
    cam = _vec(ex.data["camera"]["origin"])
    center = cam + (0.5 * (grid.bottom + grid.top) - cam @ up) * up
    # (across, up, cross(across, up)) is right-handed: the cube's normals point out of the fog
    cube = _cube(center, [across * extent / 2, up * (grid.top - grid.bottom) / 2, np.cross(across, up) * extent / 2])
    unit_to_cube = np.array([[2.0, 0, 0, -1], [0, 2, 0, -1], [0, 0, 2, -1], [0, 0, 0, 1]])  # gridvolume's [0, 1]^3
    grey = bool(np.all(grid.sigma == grid.sigma[:, :1]))
    values = grid.sigma[:, :1] if grey else grid.sigma
    data = np.ascontiguousarray(np.broadcast_to(values[None, :, None, :], (2, len(values), 2, values.shape[1])),
                                dtype=np.float32)
    sigma_t = {"type": "gridvolume", "grid": ex.volume(data), "to_world": ex.to_world(cube @ unit_to_cube),
               "filter_type": "trilinear"}
    medium = {"type": "heterogeneous", "sigma_t": sigma_t, "scale": 1.0, "albedo": _albedo(med["albedo"]),
              "phase": _phase(med)}
    return Fog(medium, cube, fills_space=True)


@MEDIA.register("grid")
def _grid_medium(med: dict, ex: Export) -> Fog:
    """`heterogeneous` with `sigma_t` a `gridvolume` of the file's density grid (`_volfile.load_grid`: a `.vol` or
    `.npy`, 1 or 3 channels passed through: in an RGB variant a 3-channel `gridvolume` is an RGB extinction),
    `filter_type` trilinear, `wrap_mode` clamp, its `to_world` mapping the unit cube onto `bounds` (else the `.vol`
    file's own box: Mitsuba ignores a file's box unless `use_grid_bbox` is set), and the medium's `scale`; the fog
    fills that box as bounded homogeneous fog does (a `cube` with a `null` BSDF). A grid that is zero everywhere (or
    `scale` 0) is an empty homogeneous medium in the box."""
    from ._volfile import load_grid

    box = med.get("bounds")
    grid, (lo, hi) = load_grid(med["file"], None if box is None else (box["min"], box["max"]))
    cube = _cube((lo + hi) / 2, np.diag((hi - lo) / 2))
    bounds = {"min": lo.tolist(), "max": hi.tolist()}
    scale = float(med["scale"])
    if scale * float(grid.max()) == 0:
        return _homogeneous({**med, "sigma_t": 0.0, "bounds": bounds}, ex)
    unit_to_cube = np.array([[2.0, 0, 0, -1], [0, 2, 0, -1], [0, 0, 2, -1], [0, 0, 0, 1]])  # gridvolume's [0, 1]^3
    sigma_t = {"type": "gridvolume", "grid": ex.volume(grid), "to_world": ex.to_world(cube @ unit_to_cube),
               "filter_type": "trilinear", "wrap_mode": "clamp"}
    medium = {"type": "heterogeneous", "sigma_t": sigma_t, "scale": scale, "albedo": _albedo(med["albedo"]),
              "phase": _phase(med)}
    return Fog(medium, cube, fills_space=False)


# --------------------------------------------------------------------------------------- shapes and BSDFs
@SHAPES.register("rectangle")
def _rectangle(s: dict, ex: Export) -> dict:
    return {"type": "rectangle", "to_world": ex.to_world(rectangle_matrix(s["center"], s["edge_u"], s["edge_v"]))}


@SHAPES.register("sphere")
def _sphere(s: dict, ex: Export) -> dict:
    return {"type": "sphere", "center": _rgb(s["center"]), "radius": float(s["radius"])}


@SHAPES.register("mesh")
def _mesh(s: dict, ex: Export) -> dict:
    from ._mesh import transform_matrix

    ext = os.path.splitext(s["file"])[1].lower()
    return {"type": "ply" if ext == ".ply" else "obj", "filename": s["file"], "face_normals": not s["smooth"],
            "to_world": ex.to_world(transform_matrix(s["to_world"]))}


@BSDFS.register("diffuse")
def _diffuse(b: dict) -> dict:
    return {"type": "diffuse", "reflectance": _rgb_tex(b["reflectance"])}


@BSDFS.register("mirror")
def _mirror(b: dict) -> dict:
    return {"type": "conductor", "material": "none", "specular_reflectance": _rgb_tex(b.get("reflectance", 1.0))}


@BSDFS.register("glass")
def _glass(b: dict) -> dict:
    return {"type": "dielectric", "int_ior": float(b.get("int_ior", 1.5)), "ext_ior": float(b.get("ext_ior", 1.0))}


def _shape(s: dict, i: int, ex: Export) -> dict:
    """Shape `i` with its BSDF and, in fog, its exterior medium: every shape in fog filling space; in a box of fog
    only a glass object inside it (a medium transition must know what surrounds it; a reflecting surface keeps the
    ray's medium; conventions: glass lies wholly inside or outside the box)."""
    shape = SHAPES(s, f"shapes.{i}", ex)
    shape["bsdf"] = BSDFS(s["bsdf"], f"shapes.{i}.bsdf")
    fog = ex.fog
    if fog is not None and fog.fills_space:
        shape["exterior"] = _fog_ref()
    elif fog is not None and shape["bsdf"]["type"] == "dielectric":
        if "center" not in s:
            raise ValueError(f"to_mitsuba: shapes.{i}: a glass {s['type']} in bounded fog is not exported")
        if fog.contains(s["center"]):
            shape["exterior"] = _fog_ref()
    return shape


# ---------------------------------------------------------------------------------------------------- lights
@LIGHTS.register("point")
def _point(lt: dict, ex: Export) -> dict:
    return {"type": "point", "position": _rgb(lt["position"]), "intensity": _rgb_tex(lt["intensity"])}


@LIGHTS.register("spot")
def _spot(lt: dict, ex: Export) -> dict:
    p, d = _vec(lt["position"]), _vec(lt["direction"])
    d = d / np.linalg.norm(d)
    return {"type": "spot", "to_world": ex.to_world(look_at_matrix(p, p + d, _perpendicular(d))),
            "intensity": _rgb_tex(lt["intensity"]), "cutoff_angle": float(lt["cutoff_angle"]),
            "beam_width": float(lt["beam_width"])}


@LIGHTS.register("area")
def _area(lt: dict, ex: Export) -> dict:
    shape = {"type": "rectangle", "to_world": ex.to_world(rectangle_matrix(lt["center"], lt["edge_u"], lt["edge_v"])),
             "bsdf": {"type": "diffuse", "reflectance": _rgb_tex(0.0)},
             "emitter": {"type": "area", "radiance": _rgb_tex(lt["radiance"])}}
    if ex.fog is not None and ex.fog.fills_space:
        shape["exterior"] = _fog_ref()
    return shape


@LIGHTS.register("directional")
def _directional(lt: dict, ex: Export) -> dict:
    """`directional`: `direction` the light travels in (unit), `irradiance` on a surface facing it. Mitsuba's shadow
    rays end outside the scene's bounding sphere (the fog's cube included), jaxfog's at infinity: they differ by the
    fog beyond the cube (negligible above a height-fog grid, `TAU_ABOVE`)."""
    d = _vec(lt["direction"])
    return {"type": "directional", "direction": (d / np.linalg.norm(d)).tolist(),
            "irradiance": _rgb_tex(lt["irradiance"])}


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


def _positive_int(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"to_mitsuba: {name} must be a positive integer, got {value!r}")
    return int(value)


def _adapters(transform, volume) -> tuple[Callable[[np.ndarray], Any], Callable[[np.ndarray], Any]]:
    """What the dict holds for a 4x4 matrix and for a grid: the given functions, else `mi.ScalarTransform4f` and
    `mi.VolumeGrid` when Mitsuba is imported and has a variant set, else the numpy arrays themselves."""
    keep = lambda a: a  # noqa: E731
    mi = sys.modules.get("mitsuba")
    matrix, grid = keep, keep
    try:
        if mi is not None and mi.variant() is not None:
            matrix = lambda m: mi.ScalarTransform4f(np.asarray(m, np.float64).tolist())  # noqa: E731
            grid = mi.VolumeGrid
    except Exception:  # a half-imported or broken Mitsuba: plain arrays
        pass
    return (transform or matrix), (volume or grid)


def _integrator(integrator: dict, max_depth) -> dict:
    """`volpath` at the file's (or the given) `max_depth`: fixed depths without Russian roulette, as in jaxfog;
    `max_depth = -1` with Russian roulette from the file's `rr_depth` on."""
    max_depth = integrator["max_depth"] if max_depth is None else max_depth
    if max_depth != -1:
        max_depth = _positive_int(max_depth, "max_depth")
    rr_depth = int(integrator.get("rr_depth", 5)) if max_depth == -1 else max_depth + 1000
    return {"type": "volpath", "max_depth": max_depth, "rr_depth": rr_depth}


NEAR_CLIP = 1e-5
"""Mitsuba's `near_clip` (scene units) for a camera without one: Mitsuba's perspective camera starts each ray
`near_clip / cos(angle to the axis)` ahead of its origin (default 0.01), which in fog of extinction sigma leaves out
that much optical depth: its images are brighter by about `sigma near_clip` (0.4% measured for sigma = 0.8 at the
default; docs/conventions.md, "Mitsuba's own small biases"). 1e-5 keeps this below 1e-4 for sigma up to 10 per
scene unit; images at 1e-4 and 1e-6 agree (Mitsuba 3.9.1, scalar_rgb)."""


def _sensor(cam: dict, spp: int, seed: int, ex: Export) -> dict:
    sensor = {
        "type": "perspective",
        "fov": float(cam["fov"]),
        "fov_axis": "x",
        "to_world": ex.to_world(look_at_matrix(cam["origin"], cam["target"], cam["up"])),
        "film": {"type": "hdrfilm", "width": int(cam["width"]), "height": int(cam["height"]),
                 "rfilter": {"type": "box"}, "pixel_format": "rgb"},
        "sampler": {"type": "independent", "sample_count": spp, "seed": seed},
        "near_clip": max(float(cam.get("near_clip", 0.0)), NEAR_CLIP),
    }
    if ex.fog is not None and ex.fog.contains(cam["origin"]):
        sensor["medium"] = _fog_ref()
    return sensor


def to_mitsuba(scene, *, spp: int | None = None, max_depth: int | None = None, seed: int = 0, overrides=(),
               transform: Callable[[np.ndarray], Any] | None = None,
               volume: Callable[[np.ndarray], Any] | None = None) -> dict:
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
    - `volume`: likewise for the height-fog grid (numpy float32 `(z, y, x, channels)`): default `mi.VolumeGrid`
      when Mitsuba is imported with a variant set, otherwise the numpy array.

    **Returns:** a dict with `"type": "scene"`, `"integrator"`, `"sensor"`, `"fog"` and `"fog_boundary"` (when the
    scene has a medium), `"shape_<i>"` per shape and `"light_<i>"` per light (scene order). **Raises:** `SceneError`
    for an invalid scene, `ValueError` for a part Mitsuba has no counterpart for or a bad `spp`/`max_depth`/`seed`.
    """
    data = _scene_data(scene, overrides)
    spp = _positive_int(data["integrator"]["spp"] if spp is None else spp, "spp")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= seed < 2**32:
        raise ValueError(f"to_mitsuba: seed must be an integer in [0, 2^32), got {seed!r}")
    ex = Export(*_adapters(transform, volume), data)
    out: dict = {"type": "scene", "integrator": _integrator(data["integrator"], max_depth)}
    if data.get("medium") is not None:
        ex = ex._replace(fog=MEDIA(data["medium"], "medium", ex))
        out["fog"] = ex.fog.medium
        out["fog_boundary"] = {"type": "cube", "to_world": ex.to_world(ex.fog.cube), "bsdf": {"type": "null"},
                               "interior": _fog_ref()}
    out["sensor"] = _sensor(data["camera"], spp, int(seed), ex)
    for i, s in enumerate(data.get("shapes", [])):
        out[f"shape_{i}"] = _shape(s, i, ex)
    for i, lt in enumerate(data.get("lights", [])):
        out[f"light_{i}"] = LIGHTS(lt, f"lights.{i}", ex)
    return out


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
                   transform=lambda m: mi.ScalarTransform4f(np.asarray(m, np.float64).tolist()), volume=mi.VolumeGrid)
    loaded = mi.load_dict(d)
    img = mi.render(loaded, spp=d["sensor"]["sampler"]["sample_count"], seed=int(seed))
    return np.asarray(img, dtype=np.float32)[..., :3]
