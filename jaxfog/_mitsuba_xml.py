"""Mitsuba 3 XML scenes as jaxfog scene files: the inverse of `to_mitsuba` (`jaxfog/_mitsuba.py`) for the subset
jaxfog models.

`scene_from_mitsuba_xml(path)` reads a Mitsuba 3 scene (`xml.etree.ElementTree` elements, built with line numbers)
and returns the scene-file dict that `jaxfog._scene_io` loads (`scene_from_dict`, or `json.dump` it and
`load_scene`). It is validated as a scene file before it is returned. `jaxfog convert scene.xml -o scene.json` is the
command line. Units and conventions are `to_mitsuba`'s (`docs/conventions.md`, "Mitsuba 3"), so a scene exported by
`to_mitsuba` and written as XML comes back as the same scene (tests/test_mitsuba_xml.py).

What is read, plugin by plugin (each plugin is converted by one function registered under its type in a table:
`INTEGRATORS`, `SHAPES`, `BSDFS`, `EMITTERS`, `MEDIA`, `PHASES`; Mitsuba's defaults apply where the XML leaves a
parameter out):

- `<scene version>` (2.x or 3.x), `<default name value>` and `$name` in any attribute (`parameters` override the
  defaults, as `mi.load_file(path, **parameters)`), `<ref id>` to any object with an `id`;
- integrator `volpath`, `volpathmis`, `prbvolpath` (`max_depth`, default -1; `rr_depth` kept for `max_depth = -1`:
  fixed depths are unbiased either way, jaxfog uses no Russian roulette there); `path` in a scene without a medium;
- sensor `perspective`: `fov` with `fov_axis` x, y, diagonal, smaller or larger (converted to jaxfog's horizontal
  fov as Mitsuba does from the film's aspect ratio) or `focal_length` (36 x 24 mm film, diagonal), `to_world` (a
  `<lookat>` is kept as the camera's origin, target and up; any other rigid transform gives origin, origin + view
  direction and up); `hdrfilm` `width` and `height`; `rfilter` `box` (without one, Mitsuba's gaussian, jaxfog's box
  filter with a warning); a sampler's `sample_count` as `integrator.spp`;
- shapes: `sphere` (`center`, `radius`, `to_world` with a uniform scale), `rectangle` (`to_world` with perpendicular
  edges; the front face is Mitsuba's normal, `cross(to_world (1, 0, 0), to_world (0, 1, 0))`, also under a mirror;
  `flip_normals` turns it), `ply` and `obj` (`filename` relative to the XML file, `to_world` as a `matrix`, not
  mirroring; `face_normals`: false needs vertex normals in the file, read as `smooth`), `cube` with a `null` BSDF
  and an `interior` medium (the fog's box), or else six rectangles facing as Mitsuba's faces (out; in under a mirror);
- BSDFs: `diffuse` (`reflectance`), `conductor` with `material = "none"` (a mirror, `specular_reflectance`;
  Mitsuba's is one-sided, jaxfog's two-sided), `dielectric` (`int_ior`, `ext_ior`: numbers or Mitsuba's named
  indices, `IOR`), `twosided` around a conductor (exact) or a diffuse (jaxfog's is one-sided: a rectangle is turned
  to face the camera). Where the back of a surface differs, a `MitsubaXmlWarning` says so (not on spheres, whose
  back is never seen from outside);
- emitters: `point` (`position` or `to_world`, `intensity`), `spot` (`to_world`: position and +z axis,
  `intensity`, `cutoff_angle`, `beam_width`), `directional` (`direction` or `to_world`'s +z, `irradiance`), `area`
  inside a rectangle whose BSDF is black (jaxfog's area light is a black surface; `radiance`);
- one `homogeneous` medium (`sigma_t` times `scale`, `albedo`; phase `hg`, `isotropic` (g = 0), `rayleigh`,
  `blendphase` of two `hg` (two-term HG, `w = 1 - weight`), and a `tabphase` that is jaxfog's droplet table
  (`droplet_table`; its diameter is recovered): as the sensor's medium (fog filling space), or a `cube`'s interior.
  A cube centred on the camera with equal sides, which every shape has as its exterior medium, is `to_mitsuba`'s
  fog filling space (`extent` = its side); any other axis-aligned cube is bounded fog (`bounds`).

Everything else (a tag, a plugin type, a parameter, a texture, a second medium ...) raises `MitsubaXmlError` (a
`SceneError`) naming the file, the line, the element and what jaxfog has instead; nothing is silently dropped.
"""

from __future__ import annotations

import json
import math
import os
import re
import warnings
import xml.etree.ElementTree as ET
from typing import Any, Callable, NamedTuple
from xml.parsers import expat

import numpy as np

from ._mitsuba import NEAR_CLIP
from ._scene_io import SceneError

__all__ = ["scene_from_mitsuba_xml", "MitsubaXmlError", "MitsubaXmlWarning", "IOR", "scene_json_text"]


class MitsubaXmlError(SceneError):
    """A Mitsuba XML scene that jaxfog cannot read: the message names the file, the line and the element."""


class MitsubaXmlWarning(UserWarning):
    """A construct read with a difference the XML cannot avoid (a two-sided diffuse read as jaxfog's one-sided one)."""


IOR = {
    "vacuum": 1.0, "helium": 1.000036, "hydrogen": 1.000132, "air": 1.000277, "carbon dioxide": 1.00045,
    "water": 1.333, "acetone": 1.36, "ethanol": 1.361, "carbon tetrachloride": 1.461, "glycerol": 1.4729,
    "benzene": 1.501, "silicone oil": 1.52045, "bromine": 1.661, "water ice": 1.31, "fused quartz": 1.458,
    "pyrex": 1.47, "acrylic glass": 1.49, "polypropylene": 1.49, "bk7": 1.5046, "sodium chloride": 1.544,
    "amber": 1.55, "pet": 1.575, "diamond": 2.419,
}
"""Mitsuba 3's named indices of refraction (`include/mitsuba/render/ior.h`); `dielectric` defaults to `int_ior` bk7
and `ext_ior` air."""

PROPERTY_TAGS = frozenset({"float", "integer", "boolean", "string", "rgb", "spectrum", "point", "vector", "transform"})
OBJECT_TAGS = frozenset({"integrator", "sensor", "film", "rfilter", "sampler", "shape", "bsdf", "emitter", "medium",
                         "phase", "texture", "volume"})
TRANSFORM_OPS = frozenset({"translate", "scale", "rotate", "matrix", "lookat"})
SAMPLERS = frozenset({"independent", "stratified", "multijitter", "orthogonal", "ldsampler"})
"""Samplers whose `sample_count` is read as `integrator.spp` (each gives the same expected image; the seed and the
stratification only change the noise, and jaxfog's come from the render's key)."""

REL_TOL = 1e-6

MITSUBA_NEAR_CLIP = 0.01
"""Mitsuba 3's default `near_clip` of the perspective sensor (scene units): read into the camera's `near_clip`, so
that the converted scene renders as Mitsuba renders the file (in fog the clip plane leaves out
`sigma near_clip / cos` of optical depth)."""
"""Relative tolerance of the geometric checks (perpendicular edges, a uniform scale, a rigid camera)."""


# ------------------------------------------------------------------------------------------------ parsing
class _Element(ET.Element):
    """An ElementTree element that knows its line in the file (`line`)."""

    line: int = 0


def _parse(path: str) -> _Element:
    """The file's root element, every element with its `line` (expat, as ElementTree uses, for line numbers)."""
    try:
        with open(path, "rb") as fh:
            raw = fh.read()
    except FileNotFoundError:
        raise MitsubaXmlError(f"{path}: Mitsuba XML file not found") from None
    except OSError as e:
        raise MitsubaXmlError(f"{path}: cannot read the Mitsuba XML file: {e.strerror or e}") from None
    parser = expat.ParserCreate()
    stack: list[_Element] = []
    root: list[_Element] = []

    def start(tag, attrs):
        el = _Element(tag, attrs)
        el.line = parser.CurrentLineNumber
        (stack[-1].append(el) if stack else root.append(el))
        stack.append(el)

    def end(tag):
        stack.pop()

    parser.StartElementHandler, parser.EndElementHandler = start, end
    try:
        parser.Parse(raw, True)
    except expat.ExpatError as e:
        raise MitsubaXmlError(f"{os.path.basename(path)}, line {e.lineno}, column {e.offset + 1}: not well-formed "
                              f"XML: {expat.ErrorString(e.code)}") from None
    return root[0]


def _numbers(text: str) -> list[float]:
    """The numbers of an attribute such as `"0.1, 0.2, 0.3"` or `"1 2 3"` (Mitsuba separates by commas or spaces)."""
    return [float(t) for t in re.split(r"[\s,]+", text.strip()) if t]


def _grey(v: list[float]):
    """An RGB value as a scene file writes it: one number when the channels are equal, else three."""
    return v[0] if v[0] == v[1] == v[2] else list(v)


def _describe(el: _Element) -> str:
    """`<shape type="disk" id="x">` (the element's identifying attributes)."""
    attrs = "".join(f' {k}="{el.get(k)}"' for k in ("type", "name", "id") if el.get(k) is not None)
    return f"<{el.tag}{attrs}>"


class _Reader:
    """The state of one conversion: the file, its folder, the parameters for `$name`, the objects with an `id`."""

    def __init__(self, path: str, parameters: dict):
        self.path = path
        self.base = os.path.basename(path)
        self.folder = os.path.dirname(os.path.abspath(path))
        self.parameters = dict(parameters)
        self.ids: dict[str, _Element] = {}
        self.cache: dict[int, Any] = {}

    def error(self, el: _Element, message: str) -> MitsubaXmlError:
        return MitsubaXmlError(f"{self.base}, line {el.line}: {_describe(el)}: {message}")

    def attr(self, el: _Element, key: str, default=None):
        """Attribute `key` with `$name` parameters substituted."""
        text = el.get(key)
        if text is None:
            return default

        def sub(m):
            name = m.group(1)
            if name not in self.parameters:
                raise self.error(el, f"${name} in {key}=\"{text}\" has no value; expected a <default name=\"{name}\" "
                                     "value=\"...\"/> or a parameter of that name")
            return self.parameters[name]

        return re.sub(r"\$([A-Za-z_][A-Za-z0-9_]*)", sub, text)

    def only_attrs(self, el: _Element, allowed) -> None:
        extra = [k for k in el.keys() if k not in allowed]
        if extra:
            raise self.error(el, f"attribute {extra[0]!r} is not supported; expected only "
                                 f"{', '.join(sorted(allowed)) or 'none'}")

    def numbers(self, el: _Element, key: str, counts=(3,)) -> list[float]:
        """The numbers of attribute `key`: as many as one of `counts`, else an error naming the element."""
        text = self.attr(el, key)
        if text is None:
            raise self.error(el, f"missing {key} attribute")
        try:
            values = _numbers(text)
        except ValueError:
            values = None
        if values is None or len(values) not in counts:
            want = " or ".join(str(c) for c in counts)
            raise self.error(el, f"{key}=\"{text}\" is not {want} number{'s' if counts != (1,) else ''}")
        return values

    def resolve(self, el: _Element) -> _Element:
        """A `<ref id>` as the element it names (any other element as itself)."""
        if el.tag != "ref":
            return el
        self.only_attrs(el, {"id", "name"})
        rid = self.attr(el, "id")
        if rid is None:
            raise self.error(el, "a <ref> needs an id")
        if rid not in self.ids:
            raise self.error(el, f"no object with id {rid!r}")
        return self.ids[rid]

    def xyz(self, el: _Element, default: float) -> list[float]:
        """A vector given as `value="x, y, z"` or as attributes `x`, `y`, `z` (each `default` when left out)."""
        if el.get("value") is not None:
            return self.numbers(el, "value")
        return [self.numbers(el, k, (1,))[0] if el.get(k) is not None else default for k in "xyz"]

    def plugin(self, el: _Element) -> "_Plugin":
        return _Plugin(self, el)


class _Plugin:
    """One object element (`<shape type=...>` ...): its properties by name and its nested objects. Converters read
    what they understand with the typed getters; `done()` then refuses anything left unread."""

    def __init__(self, reader: _Reader, el: _Element):
        self.r, self.el = reader, el
        self.type = reader.attr(el, "type")
        if self.type is None:
            raise reader.error(el, "missing type attribute")
        reader.only_attrs(el, {"type", "id", "name"})
        self.props: dict[str, _Element] = {}
        self.objects: list[_Element] = []
        for child in el:
            if child.tag in PROPERTY_TAGS:
                name = reader.attr(child, "name")
                if name is None:
                    raise reader.error(child, "a property needs a name attribute")
                if name in self.props:
                    raise reader.error(child, f"{name!r} is given twice (line {self.props[name].line} and here)")
                self.props[name] = child
            elif child.tag in OBJECT_TAGS or child.tag == "ref":
                self.objects.append(child)
            else:
                raise reader.error(child, f"unknown tag inside {_describe(el)}; expected a property "
                                          f"({', '.join(sorted(PROPERTY_TAGS))}), a nested object or a <ref>")
        self.used: set[int] = set()

    def error(self, message: str) -> MitsubaXmlError:
        return self.r.error(self.el, message)

    # ------------------------------------------------------------------------------------ properties
    def has(self, name: str) -> bool:
        return name in self.props or self._named_object(name) is not None

    def _named_object(self, name: str):
        for child in self.objects:
            if child.tag != "ref" and self.r.attr(child, "name") == name:
                return child
        return None

    def _prop(self, name: str, tags) -> _Element | None:
        obj = self._named_object(name)
        if obj is not None:
            self.used.add(id(obj))
            kind = f"{obj.tag} {self.r.attr(obj, 'type')!r}"
            raise self.r.error(obj, f"a {kind} for {name!r} of {_describe(self.el)} is not supported: jaxfog takes "
                                    "constant values here (rgb, float, or a spectrum of one value)")
        el = self.props.get(name)
        if el is None:
            return None
        self.used.add(id(el))
        if el.tag not in tags:
            raise self.r.error(el, f"{name!r} must be given as {' or '.join('<' + t + '>' for t in tags)}")
        return el

    def number(self, name: str, default=None) -> float | None:
        el = self._prop(name, ("float", "integer"))
        if el is None:
            return default
        self.r.only_attrs(el, {"name", "value"})
        return self.r.numbers(el, "value", (1,))[0]

    def integer(self, name: str, default=None) -> int | None:
        el = self._prop(name, ("integer",))
        if el is None:
            return default
        self.r.only_attrs(el, {"name", "value"})
        text = self.r.attr(el, "value")
        try:
            return int(text)
        except (TypeError, ValueError):
            raise self.r.error(el, f"value=\"{text}\" is not an integer") from None

    def boolean(self, name: str, default=None) -> bool | None:
        el = self._prop(name, ("boolean",))
        if el is None:
            return default
        self.r.only_attrs(el, {"name", "value"})
        text = (self.r.attr(el, "value") or "").strip().lower()  # missing: refused below
        if text not in ("true", "false"):
            raise self.r.error(el, f"value=\"{text}\" is not true or false")
        return text == "true"

    def string(self, name: str, default=None) -> str | None:
        el = self._prop(name, ("string",))
        if el is None:
            return default
        self.r.only_attrs(el, {"name", "value"})
        return self.r.attr(el, "value")

    def rgb(self, name: str, default=None) -> list[float] | None:
        """A colour or a grey value as 3 floats: `<rgb>` (1 or 3 numbers), `<float>`, `<integer>`, or a `<spectrum>`
        of one value (uniform)."""
        el = self._prop(name, ("rgb", "float", "integer", "spectrum"))
        if el is None:
            return None if default is None else [float(default)] * 3
        self.r.only_attrs(el, {"name", "value"})
        if el.tag == "spectrum" and ":" in (self.r.attr(el, "value") or ""):
            raise self.r.error(el, "a spectrum given by wavelengths is not supported; expected one value (uniform) "
                                   "or an <rgb>")
        counts = (1, 3) if el.tag == "rgb" else (1,)
        if el.get("value") is None:
            raise self.r.error(el, "missing value attribute (a spectrum from a file is not supported)")
        v = self.r.numbers(el, "value", counts)
        return v * 3 if len(v) == 1 else v

    def vec3(self, name: str, default=None, tags=("point", "vector")) -> list[float] | None:
        el = self._prop(name, tags)
        if el is None:
            return default
        self.r.only_attrs(el, {"name", "value", "x", "y", "z"})
        return self.r.xyz(el, 0.0)

    def transform(self, name: str = "to_world") -> "_Transform | None":
        el = self._prop(name, ("transform",))
        if el is None:
            return None
        self.r.only_attrs(el, {"name"})
        return _read_transform(self.r, el)

    # --------------------------------------------------------------------------------------- objects
    def children(self, tag: str) -> list[tuple[_Element, _Element]]:
        """The nested objects of `tag` (a `<ref>` resolved to the element it names) as `(as written, resolved)`."""
        out = []
        for child in self.objects:
            target = self.r.resolve(child)
            if target.tag == tag:
                self.used.add(id(child))
                out.append((child, target))
        return out

    def child(self, tag: str) -> tuple[_Element, _Element] | None:
        found = self.children(tag)
        if len(found) > 1:
            raise self.r.error(found[1][0], f"{_describe(self.el)} has more than one <{tag}>")
        return found[0] if found else None

    def done(self) -> None:
        """Refuse every property and nested object no converter read."""
        for name, el in self.props.items():
            if id(el) not in self.used:
                raise self.r.error(el, f"parameter {name!r} of {_describe(self.el)} is not supported (jaxfog cannot "
                                       "express it); remove it or see docs/conventions.md for what jaxfog models")
        for el in self.objects:
            if id(el) not in self.used:
                target = self.r.resolve(el)
                raise self.r.error(el, f"a nested {_describe(target)} in {_describe(self.el)} is not supported here")


# ---------------------------------------------------------------------------------------------- transforms
class _Transform(NamedTuple):
    """A `to_world`: its 4x4 float64 `matrix` (Mitsuba's composition: each operation multiplies from the left) and,
    when it is one `<lookat>` alone, its `(origin, target, up)`."""

    matrix: np.ndarray
    lookat: tuple | None


def _rotation(axis, angle_deg: float) -> np.ndarray:
    """Mitsuba's `Transform4f::rotate(axis, angle)`: `cos I + sin [axis]_x + (1 - cos) axis axis^T`, with the axis
    as given (Mitsuba does not normalise it)."""
    a = np.asarray(axis, np.float64)
    th = math.radians(angle_deg)
    c, s = math.cos(th), math.sin(th)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    m = np.eye(4)
    m[:3, :3] = c * np.eye(3) + s * k + (1 - c) * np.outer(a, a)
    return m


def _look_at(origin, target, up) -> np.ndarray:
    """Mitsuba's `Transform4f::look_at` (as `jaxfog._mitsuba.look_at_matrix`)."""
    from ._mitsuba import look_at_matrix

    return look_at_matrix(origin, target, up)


def _read_transform(r: _Reader, el: _Element) -> _Transform:
    """A `<transform>`: `translate`, `scale`, `rotate`, `matrix` (16 or 9 numbers, row by row) and `lookat`, each
    applied after the ones before it (multiplied from the left), as Mitsuba's parser composes them."""
    m = np.eye(4)
    ops = list(el)
    lookat = None
    for op in ops:
        if op.tag not in TRANSFORM_OPS:
            raise r.error(op, f"unknown tag inside <transform>; expected {', '.join(sorted(TRANSFORM_OPS))}")
        if op.tag == "translate":
            r.only_attrs(op, {"value", "x", "y", "z"})
            t = r.xyz(op, 0.0)
            step = np.eye(4)
            step[:3, 3] = t
        elif op.tag == "scale":
            r.only_attrs(op, {"value", "x", "y", "z"})
            if op.get("value") is not None:
                s = r.numbers(op, "value", (1, 3))
                s = s * 3 if len(s) == 1 else s
            else:
                s = r.xyz(op, 1.0)
            step = np.diag(s + [1.0])
        elif op.tag == "rotate":
            r.only_attrs(op, {"value", "x", "y", "z", "angle"})
            step = _rotation(r.xyz(op, 0.0), r.numbers(op, "angle", (1,))[0])
        elif op.tag == "matrix":
            r.only_attrs(op, {"value"})
            v = r.numbers(op, "value", (16, 9))
            step = np.eye(4)
            if len(v) == 16:
                step = np.asarray(v, np.float64).reshape(4, 4)
            else:
                step[:3, :3] = np.asarray(v, np.float64).reshape(3, 3)
            if not np.array_equal(step[3], [0.0, 0.0, 0.0, 1.0]):
                raise r.error(op, "a projective matrix (last row not 0 0 0 1) is not supported")
        else:  # lookat
            r.only_attrs(op, {"origin", "target", "up"})
            o, t, u = (r.numbers(op, k) for k in ("origin", "target", "up"))
            if np.linalg.norm(np.subtract(t, o)) == 0 or np.linalg.norm(np.cross(u, np.subtract(t, o))) == 0:
                raise r.error(op, "target equals origin, or up is parallel to the view direction")
            step = _look_at(o, t, u)
            if len(ops) == 1:
                lookat = (o, t, u)
        if not np.all(np.isfinite(step)):
            raise r.error(op, "a value is not finite")
        m = step @ m
    return _Transform(m, lookat)


def _matrix(t: _Transform | None) -> np.ndarray:
    return np.eye(4) if t is None else t.matrix


def _orthogonal(a, b) -> bool:
    return abs(float(np.dot(a, b))) <= REL_TOL * float(np.linalg.norm(a) * np.linalg.norm(b))


# ------------------------------------------------------------------------------------------------ dispatch
class Converters:
    """The converters of one kind of Mitsuba object (`tag`: "shape", "bsdf", ...), each registered under the plugin
    type it reads. Calling the table converts an element; a type with no converter is refused, naming the element,
    its line and the types jaxfog reads."""

    def __init__(self, tag: str, what: str, note: str = ""):
        self.tag, self.what, self.note = tag, what, note
        self._by_type: dict[str, Callable[..., Any]] = {}

    @property
    def kinds(self) -> frozenset[str]:
        return frozenset(self._by_type)

    def register(self, *kinds: str):
        def add(fn):
            for k in kinds:
                self._by_type[k] = fn
            return fn
        return add

    def __call__(self, r: _Reader, el: _Element, *args):
        return self.convert(r.plugin(el), *args)

    def convert(self, p: "_Plugin", *args):
        """Convert an element already read as a `_Plugin` (whose caller reads more of it afterwards)."""
        convert = self._by_type.get(p.type)
        if convert is None:
            raise p.error(f"the {self.tag} plugin {p.type!r} is not supported: jaxfog has no {self.what} of that "
                          f"kind{self.note}; it reads {', '.join(sorted(self._by_type))}")
        return convert(p, *args)


INTEGRATORS = Converters("integrator", "integrator")
SENSORS = Converters("sensor", "camera")
SHAPES = Converters("shape", "shape")
BSDFS = Converters("bsdf", "surface")
EMITTERS = Converters("emitter", "light", " (no environment light: rays that escape see black)")
MEDIA = Converters("medium", "medium", " (its height fog is exported as a heterogeneous gridvolume but not read "
                                        "back: give it as a jaxfog scene file)")
PHASES = Converters("phase", "phase function")


# ---------------------------------------------------------------------------------------------- integrator
class _Integrator(NamedTuple):
    values: dict
    handles_media: bool
    el: _Element


@INTEGRATORS.register("volpath", "volpathmis", "prbvolpath", "path")
def _volpath(p: _Plugin) -> _Integrator:
    max_depth = p.integer("max_depth", -1)
    rr_depth = p.integer("rr_depth", 5)
    if p.boolean("hide_emitters", False):
        raise p.error("hide_emitters = true is not supported: jaxfog's camera sees area lights")
    p.done()
    values = {"max_depth": max_depth}
    if max_depth == -1:
        values["rr_depth"] = rr_depth
    return _Integrator(values, p.type != "path", p.el)


# -------------------------------------------------------------------------------------------------- camera
def _x_fov(p: _Plugin, aspect: float) -> float:
    """Mitsuba's `parse_fov`: the horizontal field of view in degrees from `fov` and `fov_axis`, or `focal_length`
    (a 36 x 24 mm film, along its diagonal)."""
    if p.has("fov") and p.has("focal_length"):
        raise p.error("give either fov or focal_length, not both")
    if p.has("fov"):
        fov = p.number("fov")
        axis = (p.string("fov_axis", "x") or "x").lower()
        if axis == "smaller":
            axis = "y" if aspect > 1 else "x"
        elif axis == "larger":
            axis = "x" if aspect > 1 else "y"
    else:
        text = p.string("focal_length", "50mm")
        try:
            f = float(text[:-2] if text.endswith("mm") else text)
        except ValueError:
            raise p.error(f"focal_length {text!r} is not of the form <x>mm") from None
        fov, axis = math.degrees(2 * math.atan(math.hypot(36, 24) / (2 * f))), "diagonal"
    if axis == "x":
        return fov
    if axis == "y":
        return math.degrees(2 * math.atan(math.tan(math.radians(fov) / 2) * aspect))
    if axis == "diagonal":
        diagonal = 2 * math.tan(math.radians(fov) / 2)
        width = diagonal / math.sqrt(1 + 1 / aspect**2)
        return math.degrees(2 * math.atan(width / 2))
    raise p.error(f"fov_axis {axis!r} is not one of x, y, diagonal, smaller, larger")


class _Sensor(NamedTuple):
    camera: dict
    spp: int | None
    medium: _Element | None
    el: _Element


def _no_rfilter(r: _Reader, el: _Element) -> None:
    warnings.warn(MitsubaXmlWarning(f"{r.base}, line {el.line}: {_describe(el)}: no rfilter: Mitsuba's default pixel "
                                    "filter is a gaussian, jaxfog's a box (add <rfilter type=\"box\"/> to match)"),
                  stacklevel=4)


@SENSORS.register("perspective")
def _perspective(p: _Plugin) -> _Sensor:
    r = p.r
    film = p.child("film")
    width, height = 768, 576
    if film is not None:
        fp = r.plugin(film[1])
        if fp.type != "hdrfilm":
            raise fp.error(f"the film plugin {fp.type!r} is not supported: jaxfog's image is an RGB hdrfilm")
        width, height = fp.integer("width", 768), fp.integer("height", 576)
        fmt = fp.string("pixel_format", "rgb")
        if fmt.lower() not in ("rgb", "rgba"):
            raise fp.error(f"pixel_format {fmt!r} is not supported: jaxfog renders RGB")
        fp.string("component_format"), fp.string("file_format"), fp.boolean("sample_border")
        crop = (fp.integer("crop_offset_x", 0), fp.integer("crop_offset_y", 0),
                fp.integer("crop_width", width), fp.integer("crop_height", height))
        if crop != (0, 0, width, height):
            raise fp.error("a crop window is not supported: jaxfog renders the whole film")
        rf = fp.child("rfilter")
        if rf is None:
            _no_rfilter(r, fp.el)
        else:
            rp = r.plugin(rf[1])
            if rp.type != "box":
                raise rp.error(f"the rfilter plugin {rp.type!r} is not supported: jaxfog's pixels are box-filtered "
                               '(use <rfilter type="box"/>)')
            rp.done()
        fp.done()
    if film is None:
        _no_rfilter(r, p.el)
    sampler = p.child("sampler")
    spp = None
    if sampler is not None:
        sp = r.plugin(sampler[1])
        if sp.type not in SAMPLERS:
            raise sp.error(f"the sampler plugin {sp.type!r} is not supported; jaxfog reads the sample_count of "
                           f"{', '.join(sorted(SAMPLERS))}")
        spp = sp.integer("sample_count", 4)
        sp.integer("seed"), sp.boolean("jitter")
        sp.done()
    fov = _x_fov(p, width / height if height else 1.0)
    near_clip = p.number("near_clip", MITSUBA_NEAR_CLIP)
    if not near_clip >= 0:
        raise p.error(f"near_clip must be >= 0, got {near_clip}")
    if p.number("far_clip", 1e4) < 1e4:
        raise p.error("far_clip below 10000 is not supported: jaxfog's camera has no far clip plane (Mitsuba's "
                      "default is accepted)")
    for k in ("principal_point_offset_x", "principal_point_offset_y"):
        if p.number(k, 0.0) != 0.0:
            raise p.error(f"{k} is not supported: jaxfog's camera looks through the image centre")
    t = p.transform()
    if t is not None and t.lookat is not None:
        origin, target, up = t.lookat
    else:
        m = _matrix(t)
        lin = m[:3, :3]
        if not (np.allclose(lin.T @ lin, np.eye(3), rtol=0, atol=1e-5) and np.linalg.det(lin) > 0):
            raise p.error("the sensor's to_world must be a rotation and a translation (a look-at); a scale or a "
                          "mirror is not supported")
        origin = m[:3, 3].tolist()
        target = (m[:3, 3] + lin[:, 2]).tolist()
        up = lin[:, 1].tolist()
    media = p.children("medium")
    if len(media) > 1:
        raise p.error("a sensor has at most one medium")
    p.done()
    camera = {"origin": list(origin), "target": list(target), "up": list(up), "fov": fov, "width": width,
              "height": height}
    if near_clip > NEAR_CLIP:  # at or below the value `to_mitsuba` writes for a camera without one: none
        camera["near_clip"] = near_clip
    return _Sensor(camera, spp, media[0][1] if media else None, p.el)


# --------------------------------------------------------------------------------------------------- BSDFs
class _BSDF(NamedTuple):
    """A converted BSDF: the scene file's `bsdf` dict (None for `null`), whether it was `twosided` in Mitsuba, and
    what differs on the back of a surface (`back`: None when nothing does)."""

    value: dict | None
    twosided: bool = False
    back: str | None = None


@BSDFS.register("diffuse")
def _diffuse(p: _Plugin) -> _BSDF:
    v = p.rgb("reflectance", 0.5)
    p.done()
    return _BSDF({"type": "diffuse", "reflectance": _grey(v)})


@BSDFS.register("conductor")
def _conductor(p: _Plugin) -> _BSDF:
    material = p.string("material", "none")
    if material != "none" or p.has("eta") or p.has("k"):
        raise p.error("a Fresnel conductor (material other than 'none', or eta/k) is not supported: jaxfog's mirror "
                      'reflects specular_reflectance at every angle (material="none")')
    v = p.rgb("specular_reflectance", 1.0)
    p.done()
    return _BSDF({"type": "mirror", "reflectance": _grey(v)},
                 back="a conductor (one-sided in Mitsuba) is read as jaxfog's mirror, which reflects on both sides: "
                      "its back is black in Mitsuba, a mirror in jaxfog")


def _ior(p: _Plugin, name: str, default: str) -> float:
    el = p.props.get(name)
    if el is not None and el.tag == "string":
        text = p.string(name)
        key = text.strip().lower()
        if key not in IOR:
            raise p.r.error(el, f"{name} {text!r} is not one of Mitsuba's named indices ({', '.join(IOR)})")
        return IOR[key]
    return p.number(name, IOR[default])


@BSDFS.register("dielectric")
def _dielectric(p: _Plugin) -> _BSDF:
    int_ior, ext_ior = _ior(p, "int_ior", "bk7"), _ior(p, "ext_ior", "air")
    for k in ("specular_reflectance", "specular_transmittance"):
        v = p.rgb(k, 1.0)
        if v != [1.0] * 3:
            raise p.error(f"{k} other than 1 is not supported: jaxfog's glass has none")
    p.done()
    return _BSDF({"type": "glass", "int_ior": int_ior, "ext_ior": ext_ior})


@BSDFS.register("twosided")
def _twosided(p: _Plugin) -> _BSDF:
    inner = p.children("bsdf")
    if len(inner) != 1:
        raise p.error("a twosided with a different BSDF on each side is not supported (expected one nested BSDF)")
    b = BSDFS(p.r, inner[0][1])
    if b.value is None or b.value["type"] not in ("diffuse", "mirror"):
        raise p.error("twosided is read around a diffuse or a conductor only")
    p.done()
    if b.value["type"] == "mirror":  # jaxfog's mirror is two-sided
        return _BSDF(b.value, twosided=True)
    return _BSDF(b.value, twosided=True, back="a twosided diffuse is read as jaxfog's one-sided diffuse: light "
                                              "reaching its back is lost")


@BSDFS.register("null")
def _null(p: _Plugin) -> _BSDF:
    p.done()
    return _BSDF(None)


# -------------------------------------------------------------------------------------------------- phases
@PHASES.register("hg")
def _hg(p: _Plugin) -> dict:
    g = p.number("g", 0.8)
    p.done()
    return {"type": "hg", "g": g}


@PHASES.register("isotropic")
def _isotropic(p: _Plugin) -> dict:
    p.done()
    return {"type": "hg", "g": 0.0}


@PHASES.register("rayleigh")
def _rayleigh(p: _Plugin) -> dict:
    p.done()
    return {"type": "rayleigh"}


@PHASES.register("blendphase")
def _blendphase(p: _Plugin) -> dict:
    """`weight` is that of the second phase function: jaxfog's `w` (of `g1`) is `1 - weight`."""
    weight = p.number("weight", 0.5)
    inner = [PHASES(p.r, t) for _, t in p.children("phase")]
    if len(inner) != 2 or any(ph["type"] != "hg" for ph in inner):
        raise p.error("a blendphase is read as two-term Henyey–Greenstein: expected two nested hg (or isotropic) "
                      "phase functions")
    p.done()
    return {"type": "two_term_hg", "g1": inner[0]["g"], "g2": inner[1]["g"], "w": 1.0 - weight}


@PHASES.register("tabphase")
def _tabphase(p: _Plugin) -> dict:
    text = p.string("values")
    if text is None:
        raise p.error("missing values")
    try:
        values = np.asarray(_numbers(text), np.float64)
    except ValueError:
        raise p.error("values is not a list of numbers") from None
    p.done()
    diameter = droplet_diameter(values)
    if diameter is None:
        raise p.error("a tabulated phase function is read only when it is jaxfog's droplet table (to_mitsuba's "
                      "export of a droplet medium); this one is not, and jaxfog has no tabulated phase function")
    return {"type": "droplet", "diameter": diameter}


DROPLET_TABLE_RTOL = 1e-5
"""How closely a `tabphase` table must match `droplet_table(d)` to be read as droplets of diameter `d` (the export
writes 9 significant digits of float32 values; another platform's float32 evaluation differs by a few ulps)."""


_DROPLET_AT: list = []


def _droplet_at():
    """`(diameters (n,), one_minus_cos (k,)) -> (n, k)` droplet pdfs, compiled once per process."""
    if not _DROPLET_AT:
        import jax

        from ._phase import Droplet

        _DROPLET_AT.append(jax.jit(jax.vmap(lambda d, omc: Droplet(d).eval_polar(omc), in_axes=(0, None))))
    return _DROPLET_AT[0]


def droplet_diameter(values) -> float | None:
    """The droplet diameter `d` (µm) whose `jaxfog._mitsuba.droplet_table(d)` is `values`, or None when no `d` in
    (0, 50] gives that table (within `DROPLET_TABLE_RTOL`). Found by a scan of 4000 diameters on 257 of the table's
    nodes, a golden-section refinement and the shortest decimal among the float32 values nearby; the whole table is
    then checked."""
    import jax.numpy as jnp

    from ._mitsuba import droplet_table

    values = np.asarray(values, np.float64)
    n = len(values)
    if n < 3 or not np.all(np.isfinite(values)) or np.any(values <= 0):
        return None
    idx = np.unique(np.linspace(0, n - 1, 257).round().astype(int))
    omc = jnp.asarray((n - 1 - idx) * (2.0 / (n - 1)), jnp.float32)
    target = values[idx]
    at = _droplet_at()

    def err(ds):
        got = np.asarray(at(jnp.asarray(np.asarray(ds, np.float32)), omc), np.float64)
        return np.max(np.abs(np.log(got / target[None, :])), axis=1)

    grid = np.geomspace(1e-3, 50.0, 4000)
    e = err(grid)
    i = int(np.argmin(e))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    phi = (math.sqrt(5) - 1) / 2
    for _ in range(60):  # golden section on [lo, hi]
        a, b = hi - phi * (hi - lo), lo + phi * (hi - lo)
        ea, eb = err([a, b])
        if ea <= eb:
            hi = b
        else:
            lo = a
    best = up = down = np.float32((lo + hi) / 2)
    near = [best]
    for _ in range(4):
        up, down = np.nextafter(up, np.float32(np.inf)), np.nextafter(down, np.float32(0))
        near += [up, down]
    candidates = sorted({float(f"{float(c):.{k}g}") for c in near for k in range(1, 10)} | {float(c) for c in near})
    candidates = [c for c in candidates if 0 < c <= 50]
    scores = err(candidates)
    # the shortest decimal among those as close as the closest (up to float32 noise, a few ulps of the table)
    ok = [c for c, s in zip(candidates, scores) if s <= min(scores) + 2e-7]
    d = min(ok, key=lambda c: (len(repr(c)), abs(c - float(best))))
    full = droplet_table(d, n)
    if np.max(np.abs(full / values - 1)) > DROPLET_TABLE_RTOL:
        return None
    return d


# --------------------------------------------------------------------------------------------------- media
@MEDIA.register("homogeneous")
def _homogeneous(p: _Plugin) -> dict:
    """`sigma_t` (times `scale`) and `albedo`; a grey value as one number, the phase as `g` for Henyey–Greenstein."""
    sigma_t = p.rgb("sigma_t", 1.0)
    scale = p.number("scale", 1.0)
    albedo = p.rgb("albedo", 0.75)
    if not p.boolean("sample_emitters", True):
        raise p.error("sample_emitters = false is not supported: jaxfog always samples the lights from the fog")
    p.boolean("has_spectral_extinction")
    phases = p.children("phase")
    if len(phases) > 1:
        raise p.error("a medium has one phase function")
    phase = PHASES(p.r, phases[0][1]) if phases else {"type": "hg", "g": 0.0}  # Mitsuba's default: isotropic
    p.done()
    med = {"type": "homogeneous", "sigma_t": _grey([v * scale for v in sigma_t]), "albedo": _grey(albedo)}
    if phase["type"] == "hg":
        med["g"] = phase["g"]
    else:
        med["phase"] = phase
    return med


# -------------------------------------------------------------------------------------------------- shapes
class _Shape(NamedTuple):
    """A converted shape: the scene file's `shapes` entries (`parts`, without BSDF), the area light it carries
    (`light`, without radiance) or the fog's box (`box`: the cube's matrix), its media elements, a point for the
    inside/outside tests of bounded fog (`point`), and its element."""

    parts: list
    el: _Element
    point: np.ndarray | None = None
    box: np.ndarray | None = None


def _edges(m: np.ndarray, p: _Plugin, swap: bool) -> dict:
    """Mitsuba's `rectangle` ([-1, 1]^2 at z = 0) under `m`: `center`, `edge_u = m (2, 0, 0)`, `edge_v = m (0, 2,
    0)`, swapped when `swap`. Mitsuba's normal is `cross(edge_u, edge_v)` (also under a mirroring `m`: its ray
    intersections report it, tests/test_mitsuba_xml.py), jaxfog's front face; `flip_normals` swaps the edges."""
    lin = m[:3, :3]
    u, v = 2 * lin[:, 0], 2 * lin[:, 1]
    if np.linalg.norm(u) == 0 or np.linalg.norm(v) == 0:
        raise p.error("to_world is singular (a rectangle of zero size)")
    if not _orthogonal(u, v):
        raise p.error("to_world shears the rectangle (or the cube's face) into a parallelogram; jaxfog's rectangles "
                      "have perpendicular edges")
    if swap:
        u, v = v, u
    return {"center": m[:3, 3].tolist(), "edge_u": u.tolist(), "edge_v": v.tolist()}


@SHAPES.register("rectangle")
def _rectangle(p: _Plugin) -> _Shape:
    m = _matrix(p.transform())
    part = {"type": "rectangle", **_edges(m, p, bool(p.boolean("flip_normals", False)))}
    if np.linalg.det(m[:3, :3]) == 0:
        raise p.error("to_world is singular (a rectangle with no normal)")
    return _Shape([part], p.el, point=m[:3, 3])


@SHAPES.register("sphere")
def _sphere(p: _Plugin) -> _Shape:
    center = p.vec3("center", [0.0, 0.0, 0.0], tags=("point",))
    radius = p.number("radius", 1.0)
    if p.boolean("flip_normals", False):
        raise p.error("flip_normals = true is not supported: a jaxfog sphere faces out")
    local = np.diag([radius, radius, radius, 1.0])
    local[:3, 3] = center
    m = _matrix(p.transform()) @ local
    lin = m[:3, :3]
    norms = np.linalg.norm(lin, axis=0)
    if not (np.allclose(lin.T @ lin, norms[0] ** 2 * np.eye(3), rtol=0, atol=REL_TOL * norms[0] ** 2)
            and np.linalg.det(lin) > 0):
        raise p.error("to_world with a non-uniform scale, a shear or a mirror is not supported: a jaxfog sphere is "
                      "round (center, radius)")
    part = {"type": "sphere", "center": m[:3, 3].tolist(), "radius": float(norms[0])}
    return _Shape([part], p.el, point=m[:3, 3])


@SHAPES.register("ply", "obj")
def _mesh(p: _Plugin) -> _Shape:
    from ._mesh import MeshError, apply_transform, read_mesh_cached

    name = p.string("filename")
    if name is None:
        raise p.error("missing filename")
    path = os.path.normpath(name if os.path.isabs(name) else os.path.join(p.r.folder, name))
    if os.path.splitext(path)[1].lower() != f".{p.type}":
        raise p.error(f"filename {name!r} is not a .{p.type} file")
    try:
        mesh = read_mesh_cached(path)
    except MeshError as e:
        raise p.error(str(e)) from None
    face_normals = p.boolean("face_normals", False)
    if p.boolean("flip_normals", False):
        raise p.error("flip_normals = true is not supported: a jaxfog mesh's front faces are counter-clockwise")
    p.boolean("flip_tex_coords")
    if not face_normals and mesh.normals is None:
        raise p.error(f"{name} has no vertex normals and face_normals is false: Mitsuba would compute smooth "
                      "normals, which jaxfog does not; set face_normals to true or add normals to the file")
    t = p.transform()
    if t is not None and np.linalg.det(t.matrix[:3, :3]) < 0:
        raise p.error("a mirroring to_world on a mesh is not supported: Mitsuba keeps the triangles' winding (their "
                      "normals turn inward), jaxfog turns it back (jaxfog/_mesh.py apply_transform)")
    part = {"type": "mesh", "file": path, "smooth": not face_normals}
    if t is not None:
        part["to_world"] = {"matrix": t.matrix.tolist()}
    world = apply_transform(mesh, _matrix(t))
    return _Shape([part], p.el, point=(world.vertices.min(0) + world.vertices.max(0)) / 2)


@SHAPES.register("cube")
def _cube(p: _Plugin) -> _Shape:
    """Mitsuba's `cube` ([-1, 1]^3, a mesh whose triangles face out): the fog's box when its BSDF is `null` (see
    `_fog`), else six rectangles facing as Mitsuba's faces do: out, or in under a mirroring `to_world` (Mitsuba keeps
    the triangles' winding, so its normals turn inward) or with `flip_normals`."""
    m = _matrix(p.transform())
    flip = bool(p.boolean("flip_normals", False))
    lin = m[:3, :3]
    if np.linalg.det(lin) == 0:
        raise p.error("to_world is singular (a cube of zero volume)")
    parts = []
    for a in range(3):
        b, c = (a + 1) % 3, (a + 2) % 3
        for s in (1.0, -1.0):
            face = m.copy()
            face[:3, :3] = np.column_stack([lin[:, b], lin[:, c], lin[:, a]])
            face[:3, 3] = m[:3, 3] + s * lin[:, a]
            # the face (a, s) of the unit cube has edges (e_b, e_c), normal s e_a; Mitsuba's world normal is the
            # cross product of the transformed edges (its triangles keep their winding)
            parts.append({"type": "rectangle", **_edges(face, p, (s < 0) != flip)})
    return _Shape(parts, p.el, point=m[:3, 3], box=m)


# ------------------------------------------------------------------------------------------------- emitters
@EMITTERS.register("point")
def _point(p: _Plugin) -> dict:
    t = p.transform()
    position = p.vec3("position", None, tags=("point",))
    if t is not None and position is not None:
        raise p.error("give either position or to_world, not both")
    if position is None:
        position = _matrix(t)[:3, 3].tolist()
    intensity = p.rgb("intensity", 1.0)
    p.done()
    return {"type": "point", "position": position, "intensity": _grey(intensity)}


def _axis(p: _Plugin, m: np.ndarray) -> list[float]:
    d = m[:3, 2]
    if np.linalg.norm(d) == 0:
        raise p.error("to_world maps +z to zero: no direction")
    return (d / np.linalg.norm(d)).tolist()


@EMITTERS.register("spot")
def _spot(p: _Plugin) -> dict:
    """Position `to_world(0)`, axis `to_world`'s +z; `beam_width` defaults to 3/4 of `cutoff_angle` (Mitsuba's)."""
    m = _matrix(p.transform())
    intensity = p.rgb("intensity", 1.0)
    cutoff = p.number("cutoff_angle", 20.0)
    beam = p.number("beam_width", cutoff * 0.75)
    p.done()
    return {"type": "spot", "position": m[:3, 3].tolist(), "direction": _axis(p, m), "intensity": _grey(intensity),
            "cutoff_angle": cutoff, "beam_width": beam}


@EMITTERS.register("directional")
def _directional(p: _Plugin) -> dict:
    t = p.transform()
    direction = p.vec3("direction", None, tags=("vector",))
    if t is not None and direction is not None:
        raise p.error("give either direction or to_world, not both")
    if direction is None:
        direction = _axis(p, _matrix(t))
    irradiance = p.rgb("irradiance", 1.0)
    p.done()
    return {"type": "directional", "direction": direction, "irradiance": _grey(irradiance)}


@EMITTERS.register("area")
def _area(p: _Plugin) -> dict:
    radiance = p.rgb("radiance", 1.0)
    p.done()
    return {"radiance": _grey(radiance)}


# ---------------------------------------------------------------------------------------------- the scene
class _ShapeEntry(NamedTuple):
    """A shape with what surrounds it: its converted geometry, BSDF, area emitter, interior and exterior media."""

    shape: _Shape
    bsdf: _BSDF
    emitter: dict | None
    interior: _Element | None
    exterior: _Element | None


def _shape(r: _Reader, el: _Element) -> _ShapeEntry:
    """A `<shape>`: geometry by its table entry, then the BSDF (default `diffuse` 0.5, as Mitsuba's), the area
    emitter and the `interior` / `exterior` media (nested or referenced)."""
    p = r.plugin(el)
    shape = SHAPES.convert(p)
    bsdfs = p.children("bsdf")
    if len(bsdfs) > 1:
        raise r.error(bsdfs[1][0], "a shape has one BSDF")
    bsdf = _cached(r, bsdfs[0][1], BSDFS) if bsdfs else _BSDF({"type": "diffuse", "reflectance": 0.5})
    emitters = p.children("emitter")
    emitter = None
    if emitters:
        if len(emitters) > 1:
            raise r.error(emitters[1][0], "a shape has one emitter")
        ep = r.plugin(emitters[0][1])
        if ep.type != "area":
            raise ep.error(f"the emitter plugin {ep.type!r} inside a shape is not supported (only area)")
        emitter = _area(ep)
    media = {"interior": None, "exterior": None}
    for written, target in p.children("medium"):
        name = r.attr(written, "name")
        if name not in media:
            raise r.error(written, "a shape's medium must be named interior or exterior")
        if media[name] is not None:
            raise r.error(written, f"a second {name} medium")
        media[name] = target
    sensors = p.children("sensor")
    if sensors:
        raise r.error(sensors[0][0], "a sensor attached to a shape is not supported")
    p.done()
    return _ShapeEntry(shape, bsdf, emitter, media["interior"], media["exterior"])


def _cached(r: _Reader, el: _Element, table: Converters):
    """Convert an element once (a referenced BSDF or medium is the same object wherever it is used)."""
    key = id(el)
    if key not in r.cache:
        r.cache[key] = table(r, el)
    return r.cache[key]


def _version(r: _Reader, root: _Element) -> None:
    if root.tag != "scene":
        raise r.error(root, "the root element must be <scene>")
    r.only_attrs(root, {"version"})
    text = r.attr(root, "version", "3.0.0")
    try:
        major = int(text.split(".")[0])
    except ValueError:
        raise r.error(root, f"version {text!r} is not a version number") from None
    if major < 2:
        raise r.error(root, f"version {text}: a Mitsuba 0.x scene (older plugin and parameter names) is not read; "
                            "load and re-export it with Mitsuba 3 first")


def _defaults(r: _Reader, root: _Element) -> None:
    for el in root:
        if el.tag == "default":
            r.only_attrs(el, {"name", "value"})
            name, value = el.get("name"), el.get("value")
            if name is None or value is None:
                raise r.error(el, "a <default> needs name and value")
            r.parameters.setdefault(name, value)


def _register_ids(r: _Reader, root: _Element) -> None:
    for el in root.iter():
        if el is root or el.tag == "ref":
            continue
        oid = el.get("id")
        if oid is None:
            continue
        oid = r.attr(el, "id")
        if oid in r.ids:
            raise r.error(el, f"id {oid!r} is already used on line {r.ids[oid].line}")
        r.ids[oid] = el


UNSUPPORTED_TOP = {
    "include": "<include> is not supported: merge the included file into this one",
    "alias": "<alias> is not supported: use the id itself",
    "path": "<path> is not supported: give file names relative to this file",
    "texture": "textures are not supported: jaxfog takes constant colours (rgb, float, a one-value spectrum)",
}


def _fog(r: _Reader, sensor: _Sensor, entries: list[_ShapeEntry], integrator: _Integrator):
    """The scene file's `medium` (or None) and the shape entries without the fog's box: one `homogeneous` medium,
    filling space (the sensor's medium, no box; or `to_mitsuba`'s cube around the camera that every shape has as
    exterior) or bounded by an axis-aligned box (a `cube` with a `null` BSDF and the medium inside)."""
    boxes = [e for e in entries if e.shape.box is not None and e.bsdf.value is None]
    for e in entries:
        if e.bsdf.value is None and e.shape.box is None:
            raise r.error(e.shape.el, "a shape with a null BSDF is read only as a <shape type=\"cube\"> holding the "
                                      "fog (interior medium): jaxfog has no invisible shapes or media in other shapes")
    if len(boxes) > 1:
        raise r.error(boxes[1].shape.el, "a second cube of fog: jaxfog has at most one medium")
    box = boxes[0] if boxes else None
    if box is not None and (box.interior is None or box.exterior is not None or box.emitter is not None):
        raise r.error(box.shape.el, "a cube with a null BSDF is read as the fog's box: it needs an interior medium "
                                    "and no exterior medium or emitter")
    shapes = [e for e in entries if e is not box]

    used = [(sensor.el, sensor.medium)] + [(e.shape.el, m) for e in entries for m in (e.interior, e.exterior)]
    used = [(el, m) for el, m in used if m is not None]
    if not used:
        return None, shapes
    converted = sorted(((el, m, _cached(r, m, MEDIA)) for el, m in used), key=lambda c: c[1].line)
    first = converted[0]
    for el, m, med in converted[1:]:
        if med != first[2]:
            raise r.error(m, f"a second medium (the first is {_describe(first[1])} on line {first[1].line}): jaxfog "
                             "has at most one medium")
    medium = dict(first[2])
    if not integrator.handles_media:
        raise r.error(integrator.el, "the path integrator (Mitsuba's default when the scene has none) ignores media: "
                                     'use <integrator type="volpath"> for a scene with a medium')
    for e in shapes:
        if e.interior is not None and (e.bsdf.value or {}).get("type") == "glass":
            raise r.error(e.shape.el, "a medium inside a dielectric is not supported: jaxfog has no fog inside glass")
    origin = np.asarray(sensor.camera["origin"], np.float64)
    if box is None:
        if sensor.medium is None:
            raise r.error(first[1], "a medium that is neither the sensor's (fog filling space) nor inside a cube with "
                                    "a null BSDF (a box of fog) is not supported")
        _check_glass_exterior(r, shapes, lambda e: True)
        return medium, shapes
    m = box.shape.box
    lin = m[:3, :3]
    if np.count_nonzero(np.abs(lin) > REL_TOL * np.abs(lin).max()) != 3 or np.any(
            np.count_nonzero(np.abs(lin) > REL_TOL * np.abs(lin).max(), axis=0) != 1):
        raise r.error(box.shape.el, "the fog's cube must be an axis-aligned box (a scale and a translation): jaxfog's "
                                    "bounded fog is an axis-aligned box")
    half = np.abs(lin).sum(axis=1)
    center = m[:3, 3]
    inside = bool(np.all(np.abs(origin - center) <= half))
    if inside != (sensor.medium is not None):
        raise r.error(sensor.el, "the camera is inside the fog's cube but the sensor has no medium" if inside else
                      "the sensor's medium is the fog but the camera is outside its cube")
    fills = (inside and np.allclose(center, origin, rtol=0, atol=1e-9 * half.max())
             and np.allclose(half, half[0], rtol=1e-9, atol=0) and all(e.exterior is not None for e in shapes))
    if fills:  # to_mitsuba's fog filling space: a cube of side `extent` around the camera
        medium["extent"] = float(2 * half[0])
        _check_glass_exterior(r, shapes, lambda e: True)
    else:
        medium["bounds"] = {"min": (center - half).tolist(), "max": (center + half).tolist()}

        def in_box(e):
            return e.shape.point is not None and bool(np.all(np.abs(e.shape.point - center) <= half))

        _check_glass_exterior(r, shapes, in_box)
        for e in shapes:
            if e.exterior is not None and not in_box(e):
                raise r.error(e.shape.el, "the fog is this shape's exterior medium but the shape is outside the "
                                          "fog's cube: jaxfog's bounded fog is only inside its box")
    return medium, shapes


def _check_glass_exterior(r: _Reader, shapes, in_fog) -> None:
    """A glass object in the fog must name the fog as its exterior medium (else Mitsuba carries the fog into the
    glass, which jaxfog never does); one outside the fog must not."""
    for e in shapes:
        if (e.bsdf.value or {}).get("type") != "glass":
            continue
        if in_fog(e) and e.exterior is None:
            raise r.error(e.shape.el, "a dielectric in the fog without the fog as its exterior medium: Mitsuba "
                                      "would fill it with the fog, jaxfog has no fog inside glass (add <ref "
                                      "name=\"exterior\" id=\"...\"/>)")
        if not in_fog(e) and e.exterior is not None:
            raise r.error(e.shape.el, "a dielectric outside the fog's cube with the fog as its exterior medium")


def _front_toward(part: dict, eye) -> dict:
    """A rectangle turned (its edges swapped) so that its front face faces `eye` (for a two-sided surface)."""
    n = np.cross(part["edge_u"], part["edge_v"])
    if float(np.dot(n, np.subtract(eye, part["center"]))) < 0:
        part = {**part, "edge_u": part["edge_v"], "edge_v": part["edge_u"]}
    return part


def _convert(r: _Reader, root: _Element, where: dict) -> dict:
    """The scene-file dict; `where` receives `("shapes" | "lights", index) -> element` (for errors)."""
    _version(r, root)
    _defaults(r, root)
    _register_ids(r, root)
    integrator = sensor = None
    entries: list[_ShapeEntry] = []
    order: list[tuple[str, Any, _Element]] = []  # ("shape", entry, el), ("emitter", light, el), in file order
    for el in root:
        tag = el.tag
        if tag == "default":
            continue
        if tag == "integrator":
            if integrator is not None:
                raise r.error(el, f"a second integrator (the first is on line {integrator.el.line})")
            integrator = INTEGRATORS(r, el)
        elif tag == "sensor":
            if sensor is not None:
                raise r.error(el, f"a second sensor (the first is on line {sensor.el.line}): jaxfog renders one camera")
            sensor = SENSORS(r, el)
        elif tag == "shape":
            entry = _shape(r, el)
            entries.append(entry)
            order.append(("shape", entry, el))
        elif tag == "emitter":
            p = r.plugin(el)
            if p.type == "area":
                raise p.error("an area emitter belongs inside a <shape type=\"rectangle\">")
            order.append(("emitter", EMITTERS.convert(p), el))
        elif tag == "bsdf":
            _cached(r, el, BSDFS)  # a named BSDF: read now, so an unsupported one is named even if unused
        elif tag == "medium":
            _cached(r, el, MEDIA)
        elif tag in UNSUPPORTED_TOP:
            raise r.error(el, UNSUPPORTED_TOP[tag])
        else:
            raise r.error(el, f"unknown tag <{tag}> in <scene>; expected default, integrator, sensor, shape, emitter, "
                              "bsdf or medium")
    if sensor is None:
        raise r.error(root, "no <sensor>: a jaxfog scene needs a camera (a perspective sensor)")
    if integrator is None:  # Mitsuba's default
        integrator = _Integrator({"max_depth": -1, "rr_depth": 5}, False, root)
    medium, shapes = _fog(r, sensor, entries, integrator)
    kept = {id(e) for e in shapes}
    eye = sensor.camera["origin"]
    out_shapes, lights = [], []
    for kind, item, el in order:
        if kind == "emitter":
            where[("lights", len(lights))] = el
            lights.append(item)
            continue
        if id(item) not in kept:
            continue  # the fog's box
        e: _ShapeEntry = item
        if e.emitter is not None:
            where[("lights", len(lights))] = el
            lights.append(_area_light(r, e))
            continue
        turn = e.bsdf.twosided and e.bsdf.back is not None  # either face may be the front: the camera's
        for part in e.shape.parts:
            if turn and part["type"] == "rectangle":
                part = _front_toward(part, eye)
            where[("shapes", len(out_shapes))] = el
            out_shapes.append({**part, "bsdf": e.bsdf.value})
        if e.bsdf.back is not None and e.shape.parts[0]["type"] != "sphere":  # a sphere's back is never seen
            turned = " (turned to face the camera)" if turn and e.shape.parts[0]["type"] == "rectangle" else ""
            warnings.warn(f"{r.base}, line {el.line}: {_describe(el)}: {e.bsdf.back}{turned}", MitsubaXmlWarning,
                          stacklevel=3)
    values = dict(integrator.values)
    if sensor.spp is not None:
        values["spp"] = sensor.spp
    stem = os.path.splitext(r.base)[0]
    data = {"name": stem, "description": f"imported from the Mitsuba 3 scene {r.base}", "camera": sensor.camera,
            "integrator": values}
    if medium is not None:
        medium.pop("type")
        data["medium"] = medium
    data["shapes"] = out_shapes
    data["lights"] = lights
    return _float32_clean(data)


def _area_light(r: _Reader, e: _ShapeEntry) -> dict:
    """A rectangle with an area emitter: jaxfog's area light, which is also a black surface."""
    parts = e.shape.parts
    if len(parts) != 1 or parts[0]["type"] != "rectangle":
        raise r.error(e.shape.el, "an area emitter on this shape is not supported: jaxfog's area lights are "
                                  "rectangles")
    b = e.bsdf.value
    if b is None or b["type"] != "diffuse" or b["reflectance"] != 0:
        raise r.error(e.shape.el, "an area light's shape must have a black BSDF: jaxfog's area light is a black "
                                  "surface (<bsdf type=\"diffuse\"><rgb name=\"reflectance\" value=\"0\"/></bsdf>; "
                                  "Mitsuba's default BSDF is a grey diffuse)")
    return {"type": "area", **{k: v for k, v in parts[0].items() if k != "type"}, **e.emitter}


def _float32_clean(value):
    """Floats written as the shortest decimal of their float32 value (what the renderer sees): `0.49999999999999994`
    becomes `0.5`, and a 3-vector's components below 1e-12 of its largest (`cos 90° = 6e-17`) become 0. Integers,
    booleans and strings are kept, and a mesh's `matrix` (applied in float64) as it is."""
    if isinstance(value, dict):
        return {k: v if k == "matrix" else _float32_clean(v) for k, v in value.items()}
    if isinstance(value, list):
        if len(value) == 3 and all(isinstance(v, float) for v in value):  # a vector: rounding noise of trig is 0
            big = max(abs(v) for v in value)
            value = [0.0 if abs(v) <= 1e-12 * big else v for v in value]
        return [_float32_clean(v) for v in value]
    if isinstance(value, float):
        f32 = np.float32(value)
        return float(str(f32)) if np.isfinite(f32) else value
    return value


_KEY = re.compile(r"^(shapes|lights)\[(\d+)\]")


def scene_from_mitsuba_xml(path, parameters=None) -> dict:
    """The jaxfog scene-file dict of a Mitsuba 3 XML scene (see the module docstring for what is read).

    **Arguments:**
    - `path`: the `.xml` file; mesh file names in it are relative to its folder.
    - `parameters`: `{name: value}` for `$name` in the XML, overriding its `<default>`s (as `mi.load_file(path,
      **parameters)`); values as text or numbers.

    **Returns:** the scene-file dict (`name`: the file's stem; mesh files as absolute paths), validated as a scene
    file (`jaxfog._scene_io.scene_from_dict`): `json.dump` it, or pass it to `jaxfog.to_mitsuba`.

    **Raises:** `MitsubaXmlError` (a `SceneError`) naming the file, the line and the element of anything jaxfog
    cannot express, or the scene-file key (and the XML line of its shape or light) that is out of range.
    **Warns:** `MitsubaXmlWarning` for a two-sided diffuse read as jaxfog's one-sided diffuse.
    """
    path = os.fspath(path)
    r = _Reader(path, {str(k): str(v) for k, v in (parameters or {}).items()})
    root = _parse(path)
    where: dict = {}
    data = _convert(r, root, where)
    from ._scene_io import scene_from_dict

    try:
        scene_from_dict(data, source=r.base)
    except SceneError as e:
        text = str(e)
        rest = text[len(r.base) + 2:] if text.startswith(r.base + ": ") else text
        m = _KEY.match(rest)
        el = where.get((m.group(1), int(m.group(2)))) if m is not None else None
        origin = f" ({m.group(0)} is {_describe(el)} on line {el.line})" if el is not None else ""
        raise MitsubaXmlError(f"{r.base}: as a jaxfog scene: {rest}{origin}") from None
    return data


# ---------------------------------------------------------------------------------------------- JSON text
def scene_json_text(data: dict) -> str:
    """A scene-file dict as JSON text in the shipped files' layout: one top-level key per line, each shape and
    light on its own line, short objects and number lists inline."""

    def inline(v) -> str:
        return json.dumps(v, ensure_ascii=False)

    lines = ["{"]
    items = list(data.items())
    for i, (k, v) in enumerate(items):
        comma = "," if i < len(items) - 1 else ""
        if isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            lines.append(f'  {inline(k)}: [')
            lines += [f"    {inline(x)}{',' if j < len(v) - 1 else ''}" for j, x in enumerate(v)]
            lines.append(f"  ]{comma}")
        else:
            lines.append(f"  {inline(k)}: {inline(v)}{comma}")
    lines.append("}")
    return "\n".join(lines) + "\n"
