"""Scene files: JSON -> validated dict -> `Scene` Modules.

The format is described in `notes/ARCHITECTURE.md`. Loading has three stages, and nothing from JAX is built before
the last one:

1. read the JSON and apply `--set` style overrides (`apply_overrides`);
2. validate the whole dict against the declarative `SCHEMA` below with one generic validator (`_check`), filling in
   defaults: every error is a `SceneError` naming the file, the key path and the valid range;
3. build the Modules (`_build`), each section through the constructor its schema names.

The schema is data: a `Section` maps field names to kinds (`NUMBER`, `INTEGER`, `VEC3`, `RGB`, `TEXT`, another
`Section`, a `Typed` choice keyed by `"type"`, or a `ListOf` those) with a `Range`, a default and a few named
cross-field `checks`. The ranges are `jaxfog._validate`'s (`G_RANGE`, `FOV_RANGE`, ...), the ones the Modules check
their Python values against, so a file and the Python API accept the same values. Adding a light or a BSDF is one
entry in `LIGHTS` / `BSDFS`.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import os
from dataclasses import dataclass
from typing import Any, Callable, NamedTuple

from ._bsdf import Glass, Mirror
from ._grid import MAJORANT_CELLS
from ._height import HeightFog
from ._lights import SPOT_CUTOFF_DEFAULT, spot_beam_width_default
from ._medium import HomogeneousMedium
from ._validate import (
    ANY,
    AT_LEAST_1,
    DRAINE_ALPHA_RANGE,
    DROPLET_DIAMETER_RANGE,
    FOV_RANGE,
    G_RANGE,
    HEIGHT_SCALE_RANGE,
    MAX_DEPTH_RANGE,
    NON_NEGATIVE,
    POSITIVE,
    RR_DEPTH_RANGE,
    SPOT_CUTOFF_RANGE,
    UNIT,
    Range,
    polygons_in_box,
    sphere_in_box,
)

__all__ = ["SceneError", "SceneFile", "load_scene", "scene_from_dict", "apply_overrides", "SCHEMA"]


class SceneError(ValueError):
    """A scene file (or an override) is invalid. The message names the file, the key path and the valid range."""


class SceneFile(NamedTuple):
    """A loaded scene file.

    **Fields:** `scene`: the `Scene` Module; `spp`: samples per pixel from `integrator.spp` (default 64); `path`: the
    file it came from (or `"<dict>"`); `data`: the validated dict, overrides applied and defaults filled in (plain JSON
    types, ready for `json.dumps`); `name`: the scene's `name`, or the file name without `.json`.
    """

    scene: Any
    spp: int
    path: str
    data: dict
    name: str


# ------------------------------------------------------------------------------------------------------------ schema
REQUIRED = object()
"""Marker default: the field must be given."""


@dataclass(frozen=True)
class Kind:
    """A leaf kind: `NUMBER` (finite real), `INTEGER`, `VEC3` (3 finite reals), `RGB` (a number or 3), `TEXT`,
    `BOOLEAN`, `MATRIX4` (4 rows of 4 finite reals)."""

    name: str
    expects: str


NUMBER = Kind("number", "a number")
INTEGER = Kind("integer", "an integer")
VEC3 = Kind("vec3", "a 3-vector [x, y, z]")
RGB = Kind("rgb", "a number or a list of 3 numbers [r, g, b]")
TEXT = Kind("text", "a string")
BOOLEAN = Kind("boolean", "true or false")
MATRIX4 = Kind("matrix4", "a 4x4 matrix (a list of 4 rows of 4 numbers)")


@dataclass(frozen=True)
class Field:
    """One key of a section: its `kind` (a `Kind`, `Section`, `Typed` or `ListOf`), `default` (`REQUIRED`, a value,
    or a function of the already validated sibling fields), numeric `range`, and `nonzero` for vectors that must have
    a length (directions, edges, up)."""

    kind: Any
    default: Any = REQUIRED
    range: Range = ANY
    nonzero: bool = False


@dataclass(frozen=True)
class Section:
    """A JSON object with known `fields` (in validation order), cross-field `checks` (functions
    `(values, path) -> None` that raise `_Invalid`), and `build(**values)` that makes its Module (None: a dict)."""

    fields: dict
    checks: tuple = ()
    build: Callable | None = None


@dataclass(frozen=True)
class Typed:
    """A JSON object whose `"type"` key picks one of `choices` (type name -> `Section`); `default`: the type of an
    object that gives none (None: `"type"` is required)."""

    choices: dict
    default: str | None = None


@dataclass(frozen=True)
class ListOf:
    """A JSON list whose items all have kind `item`."""

    item: Any


class _Invalid(Exception):
    """Internal: `(key path, what is wrong, valid range or values)`; turned into a `SceneError` with the file name."""

    def __init__(self, path: str, problem: str, valid: str):
        super().__init__(path, problem, valid)
        self.path, self.problem, self.valid = path, problem, valid


# ----------------------------------------------------------------------------------------- cross-field checks
def _perpendicular_edges(values: dict, path: str) -> None:
    """Rectangles and area lights: `edge_u` and `edge_v` perpendicular, to 1e-6 relative."""
    u, v = values["edge_u"], values["edge_v"]
    d = _dot(u, v)
    if abs(d) > 1e-6 * _norm(u) * _norm(v):
        raise _Invalid(
            _join(path, "edge_v"),
            f"{_fmt(v)} is not perpendicular to edge_u {_fmt(u)} (dot product {d:.6g})",
            "expected dot(edge_u, edge_v) = 0 (relative tolerance 1e-6)",
        )


def _up_not_parallel(values: dict, path: str) -> None:
    """Camera: a view direction exists and `up` is not parallel to it."""
    view = [t - o for t, o in zip(values["target"], values["origin"])]
    if _norm(view) == 0:
        raise _Invalid(
            _join(path, "target"), f"{_fmt(values['target'])} equals origin", "expected a point other than origin"
        )
    up = values["up"]
    if _norm(_cross(up, view)) <= 1e-6 * _norm(up) * _norm(view):
        raise _Invalid(
            _join(path, "up"),
            f"{_fmt(up)} is parallel to the view direction target - origin = {_fmt(view)}",
            "expected an up vector not parallel to target - origin",
        )


# ------------------------------------------------------------------------------------ constructors (lazy JAX import)
def _make(class_name: str) -> Callable:
    """A builder calling `jaxfog.<class_name>(**values)`; the import happens only when a scene is built."""

    def build(**values):
        import jaxfog

        return getattr(jaxfog, class_name)(**values)

    build.__name__ = class_name
    return build


def _module_default(cls, name: str):
    """The default of the Module field `cls.name` (the scene files take their defaults from the Modules)."""
    for f in dataclasses.fields(cls):
        if f.name == name:
            return f.default
    raise KeyError(name)  # pragma: no cover


def _build_homogeneous(sigma_t, albedo, g, phase, extent, bounds):
    import jax.numpy as jnp

    from ._medium import HomogeneousMedium
    from ._phase import HenyeyGreenstein

    # g as a strongly typed float32 (a bare Python float would be weakly typed, and a fit that later passes a float32
    # array would compile a second program).
    if phase is None:
        phase = HenyeyGreenstein(jnp.asarray(g, dtype=jnp.float32))
    box = None if bounds is None else (bounds["min"], bounds["max"])
    return HomogeneousMedium(sigma_t=sigma_t, albedo=albedo, phase=phase, extent=float(extent), bounds=box)


def _build_height(sigma_0, height_scale, base_height, albedo, g, phase, up, extent):
    import jax.numpy as jnp

    from ._height import HeightFog
    from ._phase import HenyeyGreenstein

    if phase is None:
        phase = HenyeyGreenstein(jnp.asarray(g, dtype=jnp.float32))
    return HeightFog(sigma_0=sigma_0, height_scale=height_scale, base_height=base_height, albedo=albedo, phase=phase,
                     up=up, extent=float(extent))


def _tracking_mode(values: dict, path: str) -> None:
    """A grid's `tracking` is one of `_grid.TRACKING`, its `lookup` one of `_grid.LOOKUP`."""
    from ._grid import LOOKUP, TRACKING

    for name, allowed in (("tracking", TRACKING), ("lookup", LOOKUP)):
        if values[name] not in allowed:
            raise _Invalid(_join(path, name), repr(values[name]),
                           "expected one of " + ", ".join(repr(t) for t in allowed))


def _build_grid(file, bounds, scale, albedo, g, phase, extent, tracking, majorant_cells, lookup):
    import jax.numpy as jnp

    from ._grid import GridMedium
    from ._phase import HenyeyGreenstein
    from ._volfile import load_grid

    if phase is None:
        phase = HenyeyGreenstein(jnp.asarray(g, dtype=jnp.float32))
    grid, box = load_grid(file, bounds)  # checked (and the path resolved) by `_check_grid_file` before
    return GridMedium(density=grid, scale=scale, albedo=albedo, phase=phase, bounds=box, extent=float(extent),
                      tracking=tracking, majorant_cells=int(majorant_cells), lookup=lookup)


def _min_below_max(values: dict, path: str) -> None:
    """A box's `min` corner is below its `max` corner on every axis."""
    if not all(a < b for a, b in zip(values["min"], values["max"])):
        raise _Invalid(_join(path, "max"), f"{values['max']} is not above min {values['min']} on every axis",
                       "expected min < max in x, y and z")


BOX = Section({"min": Field(VEC3), "max": Field(VEC3)}, checks=(_min_below_max,))
"""An axis-aligned box, `{"min": [x, y, z], "max": [x, y, z]}` in scene units."""


def _phase_or_g(values: dict, path: str) -> None:
    """A medium gives its phase function either as `phase` or, for Henyey–Greenstein, as the shorthand `g`."""
    if (values["g"] is None) == (values["phase"] is None):
        problem = "both g and phase given" if values["g"] is not None else "missing phase function"
        raise _Invalid(_join(path, "phase"), problem,
                       'expected either "g" (Henyey–Greenstein) or "phase": {"type": ...}, not both')


# ---------------------------------------------------------------------------------------------------- the schema
BSDFS = {
    "diffuse": Section({"reflectance": Field(RGB, range=UNIT)}, build=_make("Diffuse")),
    "mirror": Section({"reflectance": Field(RGB, default=_module_default(Mirror, "reflectance"), range=UNIT)},
                      build=_make("Mirror")),
    "glass": Section(
        {"int_ior": Field(NUMBER, default=_module_default(Glass, "int_ior"), range=POSITIVE),
         "ext_ior": Field(NUMBER, default=_module_default(Glass, "ext_ior"), range=POSITIVE)},
        build=_make("Glass"),
    ),
}

SHAPES = {
    "sphere": Section(
        {"center": Field(VEC3), "radius": Field(NUMBER, range=POSITIVE), "bsdf": Field(Typed(BSDFS))},
        build=_make("Sphere"),
    ),
    "rectangle": Section(
        {
            "center": Field(VEC3),
            "edge_u": Field(VEC3, nonzero=True),
            "edge_v": Field(VEC3, nonzero=True),
            "bsdf": Field(Typed(BSDFS)),
        },
        checks=(_perpendicular_edges,),
        build=_make("Rectangle"),
    ),
}

def _transform_exclusive(values: dict, path: str) -> None:
    """A transform is either a `matrix` or any of `scale`, `rotate`, `translate`; the matrix is invertible, affine."""
    parts = [k for k in ("scale", "rotate", "translate") if values[k] is not None]
    m = values["matrix"]
    if m is not None:
        if parts:
            raise _Invalid(_join(path, "matrix"), f"given together with {', '.join(parts)}",
                           "expected either matrix or any of scale, rotate, translate")
        if m[3] != [0.0, 0.0, 0.0, 1.0]:
            raise _Invalid(_join(path, "matrix"), f"last row {_fmt(m[3])} is not [0, 0, 0, 1]",
                           "expected an affine 4x4 matrix")
        a = [r[:3] for r in m[:3]]
        det = _dot(a[0], _cross(a[1], a[2]))
        if abs(det) < 1e-12:
            raise _Invalid(_join(path, "matrix"), "is singular", "expected an invertible 4x4 matrix")
    s = values["scale"]
    if s is not None and (s == 0 if not isinstance(s, list) else any(x == 0 for x in s)):
        raise _Invalid(_join(path, "scale"), f"{_fmt(s)} has a zero factor", "expected nonzero scale factors")


ROTATION = Section({"axis": Field(VEC3, nonzero=True), "angle": Field(NUMBER)})
"""A rotation by `angle` degrees about `axis` (counter-clockwise seen from the tip of the axis)."""

TRANSFORM = Section(
    {
        "scale": Field(RGB, default=None),
        "rotate": Field(ROTATION, default=None),
        "translate": Field(VEC3, default=None),
        "matrix": Field(MATRIX4, default=None),
    },
    checks=(_transform_exclusive,),
)
"""A mesh's `to_world`: a 4x4 `matrix`, or scale (a number or 3), then rotate, then translate (M = T R S)."""


def _build_mesh(file, bsdf, to_world, smooth):
    from ._mesh import Mesh

    return Mesh.from_file(file, bsdf, to_world=to_world, smooth=smooth)


SHAPES["mesh"] = Section(
    {
        "file": Field(TEXT),
        "bsdf": Field(Typed(BSDFS)),
        "to_world": Field(TRANSFORM, default=None),
        "smooth": Field(BOOLEAN, default=False),
    },
    build=_build_mesh,
)
"""A triangle mesh from an OBJ or PLY `file` (relative to the scene file, or absolute); `smooth`: interpolated
vertex normals (the file must have them; default: flat face normals)."""

LIGHTS = {
    "point": Section({"position": Field(VEC3), "intensity": Field(RGB, range=NON_NEGATIVE)}, build=_make("PointLight")),
    "spot": Section(
        {
            "position": Field(VEC3),
            "direction": Field(VEC3, nonzero=True),
            "intensity": Field(RGB, range=NON_NEGATIVE),
            "cutoff_angle": Field(NUMBER, default=SPOT_CUTOFF_DEFAULT, range=SPOT_CUTOFF_RANGE),
            "beam_width": Field(
                NUMBER, default=lambda v: spot_beam_width_default(v["cutoff_angle"]),
                range=Range(0, "cutoff_angle", lo_open=True)
            ),
        },
        build=_make("SpotLight"),
    ),
    "area": Section(
        {
            "center": Field(VEC3),
            "edge_u": Field(VEC3, nonzero=True),
            "edge_v": Field(VEC3, nonzero=True),
            "radiance": Field(RGB, range=NON_NEGATIVE),
        },
        checks=(_perpendicular_edges,),
        build=_make("AreaLight"),
    ),
    "directional": Section(
        {"direction": Field(VEC3, nonzero=True), "irradiance": Field(RGB, range=NON_NEGATIVE)},
        build=_make("DirectionalLight"),
    ),
}

CAMERA = Section(
    {
        "origin": Field(VEC3),
        "target": Field(VEC3),
        "up": Field(VEC3, nonzero=True),
        "fov": Field(NUMBER, range=FOV_RANGE),
        "width": Field(INTEGER, range=AT_LEAST_1),
        "height": Field(INTEGER, range=AT_LEAST_1),
        "near_clip": Field(NUMBER, default=0.0, range=NON_NEGATIVE),
    },
    checks=(_up_not_parallel,),
    build=_make("Camera"),
)

PHASES = {
    "hg": Section({"g": Field(NUMBER, range=G_RANGE)}, build=_make("HenyeyGreenstein")),
    "rayleigh": Section({}, build=_make("Rayleigh")),
    "two_term_hg": Section(
        {"g1": Field(NUMBER, range=G_RANGE),
         "g2": Field(NUMBER, range=G_RANGE),
         "w": Field(NUMBER, range=UNIT)},
        build=_make("TwoTermHG"),
    ),
    "draine": Section(
        {"g": Field(NUMBER, range=G_RANGE),
         "alpha": Field(NUMBER, range=DRAINE_ALPHA_RANGE)},
        build=_make("Draine"),
    ),
    "droplet": Section({"diameter": Field(NUMBER, range=DROPLET_DIAMETER_RANGE)}, build=_make("Droplet")),
}
"""Phase functions, selected as `"phase": {"type": ...}` in a medium; a bare `"g"` in the medium means `"hg"`."""

MEDIA = {
    "homogeneous": Section(
        {
            "sigma_t": Field(RGB, range=NON_NEGATIVE),
            "albedo": Field(RGB, range=UNIT),
            "g": Field(NUMBER, default=None, range=G_RANGE),
            "phase": Field(Typed(PHASES), default=None),
            "extent": Field(NUMBER, default=_module_default(HomogeneousMedium, "extent"), range=POSITIVE),
            "bounds": Field(BOX, default=None),
        },
        checks=(_phase_or_g,),
        build=_build_homogeneous,
    ),
    "height": Section(
        {
            "sigma_0": Field(RGB, range=NON_NEGATIVE),
            "height_scale": Field(NUMBER, range=HEIGHT_SCALE_RANGE),
            "base_height": Field(NUMBER, default=float(_module_default(HeightFog, "base_height"))),
            "albedo": Field(RGB, range=UNIT),
            "g": Field(NUMBER, default=None, range=G_RANGE),
            "phase": Field(Typed(PHASES), default=None),
            "up": Field(VEC3, default=list(_module_default(HeightFog, "up")), nonzero=True),
            "extent": Field(NUMBER, default=_module_default(HeightFog, "extent"), range=POSITIVE),
        },
        checks=(_phase_or_g,),
        build=_build_height,
    ),
    "grid": Section(
        {
            "file": Field(TEXT),
            "bounds": Field(BOX, default=None),
            "scale": Field(NUMBER, default=1.0, range=NON_NEGATIVE),
            "albedo": Field(RGB, range=UNIT),
            "g": Field(NUMBER, default=None, range=G_RANGE),
            "phase": Field(Typed(PHASES), default=None),
            "extent": Field(NUMBER, default=1000.0, range=POSITIVE),
            "tracking": Field(TEXT, default="exact"),
            "majorant_cells": Field(INTEGER, default=MAJORANT_CELLS, range=POSITIVE),
            "lookup": Field(TEXT, default="stochastic"),
        },
        checks=(_phase_or_g, _tracking_mode),
        build=_build_grid,
    ),
}
"""Media, selected by the medium's `"type"` (default `"homogeneous"`)."""

MEDIUM = Typed(MEDIA, default="homogeneous")

INTEGRATOR = Section(
    {"max_depth": Field(INTEGER, default=8, range=MAX_DEPTH_RANGE),
     "rr_depth": Field(INTEGER, default=5, range=RR_DEPTH_RANGE),
     "spp": Field(INTEGER, default=64, range=AT_LEAST_1)},
)
"""Path length: `max_depth` (>= 1, or -1 for any length), `rr_depth` (the vertex Russian roulette starts at, in
[1, 1024]: with `max_depth` -1 a path that neither escapes nor is absorbed runs that far), `spp`."""

def _glass_inside_or_outside_fog(values: dict, path: str) -> None:
    """Glass spheres and rectangles lie wholly inside or wholly outside a bounded fog's box (the fog does not enter
    glass, and a glass object across the box's face would need the fog inside it; docs/conventions.md). Meshes are
    checked where their files are read (`_check_mesh_files`)."""
    box = _fog_box(values)
    if box is None:
        return
    for i, shape in enumerate(values["shapes"]):
        if shape["bsdf"]["type"] != "glass" or shape["type"] == "mesh":
            continue
        if shape["type"] == "sphere":
            where = sphere_in_box(shape["center"], shape["radius"], *box)
            what = f"a glass sphere (center {_fmt(shape['center'])}, radius {_fmt(shape['radius'])})"
        else:
            c, u, v = shape["center"], shape["edge_u"], shape["edge_v"]
            corners = [[c[k] + a * u[k] / 2 + b * v[k] / 2 for k in range(3)]
                       for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
            where = polygons_in_box([corners], *box)
            what = f"a glass rectangle (center {_fmt(c)})"
        if where == "straddles":
            raise _Invalid(f"shapes[{i}]", _straddles(what, box), _GLASS_VALID)


_GLASS_VALID = ("expected a glass object wholly inside or wholly outside the fog's box (the fog does not enter glass; "
                "docs/conventions.md)")


def _fog_box(values: dict):
    """`(min, max)` of a medium with a box (bounded homogeneous fog, a grid), or None."""
    med = values.get("medium")
    if med is None or med.get("bounds") is None:
        return None
    return med["bounds"]["min"], med["bounds"]["max"]


def _straddles(what: str, box) -> str:
    return f"{what} straddles a face of medium.bounds (min {_fmt(box[0])}, max {_fmt(box[1])})"


SCHEMA = Section(
    {
        "name": Field(TEXT, default=None),
        "description": Field(TEXT, default=""),
        "camera": Field(CAMERA),
        "integrator": Field(INTEGRATOR, default=lambda v: {}),
        "medium": Field(MEDIUM, default=None),
        "shapes": Field(ListOf(Typed(SHAPES)), default=lambda v: []),
        "lights": Field(ListOf(Typed(LIGHTS)), default=lambda v: []),
    },
    checks=(_glass_inside_or_outside_fog,),
)
"""The whole scene file. `medium` absent (or null) means no fog."""


# ------------------------------------------------------------------------------------------------- the validator
def _check(value, spec, path: str, rng: Range = ANY, nonzero: bool = False, siblings: dict | None = None):
    """Validate `value` against `spec` at key path `path`; return it normalized (floats, defaults filled in)."""
    if isinstance(spec, Kind):
        return _check_leaf(value, spec, path, rng, nonzero, siblings or {})
    if isinstance(spec, ListOf):
        if not isinstance(value, list):
            raise _Invalid(path, f"got {_describe(value)}", "expected a list")
        return [_check(item, spec.item, f"{path}[{i}]") for i, item in enumerate(value)]
    if isinstance(spec, Typed):
        names = ", ".join(repr(k) for k in spec.choices)
        if not isinstance(value, dict):
            raise _Invalid(path, f"got {_describe(value)}", f"expected an object with \"type\" one of {names}")
        kind = value.get("type", REQUIRED if spec.default is None else spec.default)
        if kind is REQUIRED:
            raise _Invalid(_join(path, "type"), "missing required field", f"valid types: {names}")
        if not isinstance(kind, str) or kind not in spec.choices:
            raise _Invalid(_join(path, "type"), f"{kind!r} is not a known type", f"valid types: {names}")
        out = _check_section({k: v for k, v in value.items() if k != "type"}, spec.choices[kind], path)
        return {"type": kind, **out}
    if isinstance(spec, Section):
        if not isinstance(value, dict):
            raise _Invalid(path, f"got {_describe(value)}", f"expected an object with keys {_keys(spec)}")
        return _check_section(value, spec, path)
    raise TypeError(f"bad schema entry {spec!r}")  # pragma: no cover


def _check_section(value: dict, spec: Section, path: str) -> dict:
    unknown = [k for k in value if k not in spec.fields]
    if unknown:
        raise _Invalid(_join(path, unknown[0]), "unknown key", f"valid keys: {_keys(spec)}")
    out = {}
    for key, f in spec.fields.items():
        sub = _join(path, key)
        if key not in value or (value[key] is None and f.default is None):
            if f.default is REQUIRED:
                raise _Invalid(sub, "missing required field", _valid_text(f))
            default = f.default(out) if callable(f.default) else f.default
            if default is None:
                out[key] = None
                continue
            value_k = default
        else:
            value_k = value[key]
        out[key] = _check(value_k, f.kind, sub, f.range, f.nonzero, out)
    for check in spec.checks:
        check(out, path)
    return out


def _check_leaf(value, kind: Kind, path: str, rng: Range, nonzero: bool, siblings: dict):
    valid = _valid_text(Field(kind, range=rng, nonzero=nonzero))
    if kind is TEXT:
        if not isinstance(value, str):
            raise _Invalid(path, f"got {_describe(value)}", "expected a string")
        return value
    if kind is BOOLEAN:
        if not isinstance(value, bool):
            raise _Invalid(path, f"got {_describe(value)}", valid)
        return value
    if kind is MATRIX4:
        if not (isinstance(value, list) and len(value) == 4 and all(isinstance(r, list) and len(r) == 4 for r in value)):
            raise _Invalid(path, f"got {_describe(value)}", valid)
        return [[_number(x, f"{path}[{i}][{j}]", valid) for j, x in enumerate(r)] for i, r in enumerate(value)]
    if kind is INTEGER:
        if not (isinstance(value, int) and not isinstance(value, bool)):
            raise _Invalid(path, f"got {_describe(value)}", valid)
        _check_range(value, rng, path, siblings)
        return value
    if kind is NUMBER:
        return _check_range(_number(value, path, valid), rng, path, siblings)
    if kind is RGB and not isinstance(value, list):
        return _check_range(_number(value, path, valid), rng, path, siblings)
    # VEC3, or RGB given as a list
    if not isinstance(value, list):
        raise _Invalid(path, f"got {_describe(value)}", valid)
    if len(value) != 3:
        raise _Invalid(path, f"got a list of {len(value)}", valid)
    vec = [_number(x, f"{path}[{i}]", valid) for i, x in enumerate(value)]
    for i, x in enumerate(vec):
        _check_range(x, rng, f"{path}[{i}]", siblings)
    if nonzero and _norm(vec) == 0:
        raise _Invalid(path, f"{_fmt(vec)} has zero length", valid)
    return vec


FLOAT32_MAX = 3.4028234663852886e38
"""The largest finite float32: the renderer computes in float32, so a number beyond it would become infinite."""


def _number(value, path: str, valid: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _Invalid(path, f"got {_describe(value)}", valid)
    if not math.isfinite(value):
        raise _Invalid(path, f"{value} is not finite", valid)
    if abs(value) > FLOAT32_MAX:
        raise _Invalid(path, f"{value:g} is not finite in float32 (the renderer's precision; largest 3.40282e+38)",
                       valid)
    return float(value)


def _float32(x: float) -> float:
    """`x` rounded to float32 (the value the renderer sees)."""
    import struct

    return struct.unpack("f", struct.pack("f", x))[0]


def _check_range(x, rng: Range, path: str, siblings: dict):
    """`x` if it is in `rng` (`Range.below` / `above`, as the Modules check), as the renderer sees it too: a float is
    also checked after rounding to float32 (0.99999999 becomes 1). Else `_Invalid` with the key and the range."""
    hi, hi_text = rng.hi, None
    if isinstance(hi, str):
        hi_text = f"{hi} {_fmt(siblings[hi])}"
        hi = siblings[hi]
    if rng.below(x) or rng.above(x, hi):
        problem = f"{_fmt(x)} is larger than {hi_text}" if rng.above(x, hi) and hi_text is not None else \
            f"{_fmt(x)} is out of range"
        raise _Invalid(path, problem, f"valid range {rng.text()}")
    if isinstance(x, float):  # the renderer sees the float32 value: 0.99999999 becomes 1
        x32 = _float32(x)
        if rng.below(x32) or rng.above(x32, hi):
            raise _Invalid(path, f"{x!r} rounds to {x32!r} in float32 (the renderer's precision), which is out of range",
                           f"valid range {rng.text()}")
    return x


def _valid_text(f: Field) -> str:
    """What a field accepts, as the tail of a message: `expected a number in range (0, 180)`."""
    kind = f.kind
    if isinstance(kind, Section):
        return f"expected an object with keys {_keys(kind)}"
    if isinstance(kind, Typed):
        return "expected an object with \"type\" one of " + ", ".join(repr(k) for k in kind.choices)
    if isinstance(kind, ListOf):
        return "expected a list"
    text = f"expected {kind.expects}"
    if f.nonzero:
        text += " of nonzero length"
    if f.range != ANY:
        text += f" in range {f.range.text()}" if kind is not RGB else f", each in range {f.range.text()}"
    return text


# ------------------------------------------------------------------------------------------------------ overrides
def apply_overrides(data: dict, overrides=(), source: str = "<dict>") -> dict:
    """A deep copy of `data` with each override `"dotted.key.path=value"` applied, in order.

    List indices are integers (`shapes.1.bsdf.reflectance=0.3`); the value is parsed as JSON (a bare word that is not
    JSON is taken as a string). A key the file leaves out but the schema knows may be set (`lights.0.beam_width=10`,
    `integrator.spp=16`); any other missing path is an error. The result is not validated here; `scene_from_dict`
    validates after applying overrides.
    """
    data = copy.deepcopy(data)
    for text in overrides:
        if not isinstance(text, str) or "=" not in text:
            raise SceneError(f"{_base(source)}: override {text!r}: expected KEY.PATH=VALUE, e.g. medium.sigma_t=0.8")
        key, raw = text.split("=", 1)
        parts = key.strip().split(".")
        if not key.strip() or any(p == "" for p in parts):
            raise SceneError(f"{_base(source)}: override {text!r}: empty key in {key!r}; expected KEY.PATH=VALUE")
        try:
            value = json.loads(raw)
        except json.JSONDecodeError:
            value = raw.strip()
        try:
            _set_path(data, parts, value)
        except _Invalid as e:
            raise SceneError(f"{_base(source)}: override {text!r}: {e.path}: {e.problem}; {e.valid}") from None
    return data


def _set_path(data, parts: list, value) -> None:
    """Set `data[parts...] = value`, walking the schema alongside so that known-but-absent keys may be created."""
    node, spec, path = data, SCHEMA, ""
    for i, part in enumerate(parts):
        last = i == len(parts) - 1
        if isinstance(spec, Typed):  # the object's own "type" picks the schema; "type" itself is in the object
            spec = spec.choices.get(node.get("type", spec.default)) if isinstance(node, dict) else None
        if isinstance(node, list):
            if not part.lstrip("-").isdigit():
                raise _Invalid(path, f"{part!r} is not a list index", f"valid indices: 0..{len(node) - 1}")
            idx = int(part)
            if not 0 <= idx < len(node):
                raise _Invalid(f"{path}[{part}]", f"does not exist ({path} has {len(node)} entries)",
                               f"valid indices: 0..{len(node) - 1}" if node else "the list is empty")
            sub_path = f"{path}[{idx}]"
            spec = spec.item if isinstance(spec, ListOf) else None
            if last:
                node[idx] = value
            else:
                node, path = node[idx], sub_path
            continue
        if not isinstance(node, dict):
            problem = f"does not exist ({path} is {_describe(node)})"
            raise _Invalid(_join(path, part), problem, "expected an existing key path")
        sub_path = _join(path, part)
        fields = spec.fields if isinstance(spec, Section) else {}
        if part not in node and part not in fields:
            raise _Invalid(sub_path, "does not exist", f"valid keys: {', '.join(fields) or ', '.join(node)}")
        f = fields.get(part)
        if last:
            node[part] = value
        else:
            if node.get(part) is None:
                if f is None or not isinstance(f.kind, Section):
                    raise _Invalid(sub_path, "does not exist", "expected an existing key path")
                node[part] = {}
            node, path = node[part], sub_path
        spec = f.kind if f is not None else None


# --------------------------------------------------------------------------------------------------------- loading
def scene_from_dict(data: dict, source: str = "<dict>", overrides=()) -> SceneFile:
    """Validate a scene dict (after applying `overrides`) and build its `Scene`.

    **Arguments:** `data`: the parsed JSON; `source`: the file name used in error messages; `overrides`: strings
    `"key.path=value"` (see `apply_overrides`).

    **Returns:** a `SceneFile`. **Raises:** `SceneError` before any JAX object is built if anything is invalid.
    """
    data = apply_overrides(data, overrides, source)
    try:
        valid = _check(data, SCHEMA, "")
    except _Invalid as e:
        raise SceneError(f"{_base(source)}: {e.path or '<top level>'}: {e.problem}; {e.valid}") from None
    _check_grid_file(valid, source)
    _check_mesh_files(valid, source)
    stem = os.path.splitext(_base(source))[0]
    name = valid["name"] if valid["name"] is not None else stem
    valid["name"] = name
    try:
        scene = _build_scene(valid)
    except ValueError as e:  # a Module's own check that the schema does not repeat: still one line, the file named
        raise SceneError(f"{_base(source)}: {' '.join(str(e).split())}") from None
    return SceneFile(scene=scene, spp=valid["integrator"]["spp"], path=source, data=valid, name=name)


def _check_grid_file(valid: dict, source: str) -> None:
    """A grid medium's `file` resolved (relative to the scene file's folder) to an absolute path, read and validated
    (`_volfile.load_grid`: a `SceneError` naming the scene file, the key and the grid file's problem); a `.vol`
    file's own box becomes `medium.bounds` where the scene gives none, and glass objects are checked against it."""
    from ._volfile import load_grid

    med = valid.get("medium")
    if med is None or med.get("type") != "grid":
        return
    base = os.path.dirname(os.path.abspath(source)) if source and not source.startswith("<") else os.getcwd()
    path = os.path.normpath(med["file"] if os.path.isabs(med["file"]) else os.path.join(base, med["file"]))
    _, (lo, hi) = load_grid(path, med["bounds"], context=f"{_base(source)}: medium.file")
    med["file"] = path
    if med["bounds"] is None:
        med["bounds"] = {"min": [float(x) for x in lo], "max": [float(x) for x in hi]}
        try:
            _glass_inside_or_outside_fog(valid, "")
        except _Invalid as e:
            raise SceneError(f"{_base(source)}: {e.path or '<top level>'}: {e.problem}; {e.valid}") from None


def _check_mesh_files(valid: dict, source: str) -> None:
    """Resolve each mesh's `file` (relative to the scene file's folder; to the working directory for a dict) to an
    absolute path, stored in the validated dict, and read and validate it: a `SceneError` names the scene file, the
    key and the mesh file's problem (missing, unreadable, no faces, non-finite or degenerate)."""
    from ._mesh import MeshError, read_mesh_cached

    base = os.path.dirname(os.path.abspath(source)) if source and not source.startswith("<") else os.getcwd()
    for i, shape in enumerate(valid["shapes"]):
        if shape["type"] != "mesh":
            continue
        path = shape["file"] if os.path.isabs(shape["file"]) else os.path.join(base, shape["file"])
        path = os.path.normpath(path)
        key = f"shapes[{i}].file"
        try:
            mesh = read_mesh_cached(path)
        except MeshError as e:
            raise SceneError(f"{_base(source)}: {key}: {e}") from None
        if shape["smooth"] and mesh.normals is None:
            raise SceneError(f"{_base(source)}: shapes[{i}].smooth: {path} has no vertex normals; "
                             "expected smooth: false (flat normals) or a file with vertex normals")
        box = _fog_box(valid)
        if box is not None and shape["bsdf"]["type"] == "glass":
            from ._mesh import apply_transform, transform_matrix

            world = apply_transform(mesh, transform_matrix(shape["to_world"]))
            if polygons_in_box(world.vertices[world.faces], *box) == "straddles":
                what = f"a glass mesh ({os.path.basename(path)})"
                raise SceneError(f"{_base(source)}: shapes[{i}]: {_straddles(what, box)}; {_GLASS_VALID}")
        shape["file"] = path


def load_scene(path, overrides=()) -> SceneFile:
    """Read, override, validate and build a JSON scene file (format: `notes/ARCHITECTURE.md`).

    **Arguments:** `path`: the `.json` file; `overrides`: strings `"key.path=value"`, e.g. `"medium.sigma_t=0.8"`,
    `"lights.0.intensity=50"`, `"camera.width=32"` (a scalar sets all channels of an RGB value).

    **Returns:** a `SceneFile(scene, spp, path, data, name)`. **Raises:** `SceneError` (a `ValueError`) naming the
    file, the key path and the valid range; also for a missing or unreadable file and for invalid JSON.
    """
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8") as fh:
            text = fh.read()
    except FileNotFoundError:
        raise SceneError(f"{path}: scene file not found") from None
    except OSError as e:
        raise SceneError(f"{path}: cannot read scene file: {e.strerror or e}") from None
    except UnicodeDecodeError as e:
        raise SceneError(f"{_base(path)}: not a text file (byte 0x{e.object[e.start]:02x} at offset {e.start} is not "
                         f"UTF-8); expected a JSON scene file") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise SceneError(f"{_base(path)}: invalid JSON at line {e.lineno}, column {e.colno}: {e.msg}") from None
    return scene_from_dict(data, source=path, overrides=overrides)


def _build(value, spec):
    """Turn a validated value into Modules, bottom-up, with each section's `build`."""
    if isinstance(spec, ListOf):
        return tuple(_build(v, spec.item) for v in value)
    if isinstance(spec, Typed):
        return _build({k: v for k, v in value.items() if k != "type"}, spec.choices[value["type"]])
    if isinstance(spec, Section):
        built = {k: (None if value[k] is None else _build(value[k], f.kind)) for k, f in spec.fields.items()}
        return spec.build(**built) if spec.build is not None else built
    return value


def _build_scene(valid: dict):
    from ._scene import Scene

    parts = _build(valid, SCHEMA)
    return Scene(
        camera=parts["camera"],
        shapes=parts["shapes"],
        lights=parts["lights"],
        medium=parts["medium"],
        max_depth=valid["integrator"]["max_depth"],
        rr_depth=valid["integrator"]["rr_depth"],
    )


# --------------------------------------------------------------------------------------------------------- helpers
def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


def _base(source: str) -> str:
    return os.path.basename(source) if source and not source.startswith("<") else source


def _keys(spec: Section) -> str:
    return ", ".join(spec.fields)


def _describe(value) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return f"boolean {str(value).lower()}"
    if isinstance(value, str):
        return f"string {value!r}"
    if isinstance(value, list):
        return f"a list of {len(value)}"
    if isinstance(value, dict):
        return "an object"
    return f"{type(value).__name__} {value!r}"


def _fmt(x) -> str:
    if isinstance(x, list):
        return "[" + ", ".join(_fmt(v) for v in x) + "]"
    if isinstance(x, float) and x.is_integer() and abs(x) < 1e6:
        return str(int(x))
    return f"{x:g}" if isinstance(x, float) else str(x)


def _dot(a, b) -> float:
    return sum(x * y for x, y in zip(a, b))


def _norm(a) -> float:
    return math.sqrt(_dot(a, a))


def _cross(a, b) -> list:
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
