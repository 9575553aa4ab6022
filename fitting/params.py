"""Fit parameters: names, the unconstrained coordinates the solvers see, and how each is written into a scene.

| name | meaning | unconstrained coordinate |
| --- | --- | --- |
| `sigma_t` | extinction, 1/scene unit, all channels (grey fog) | `log sigma_t` |
| `g` | HG asymmetry in (-1, 1) | `atanh g` |
| `albedo` | single-scattering albedo in (0, 1), all channels | `logit albedo` |
| `intensity` | intensity (W/sr) of the scene's first light, all channels (radiance for an area light) | `log intensity` |
| `sigma_t[r]`, `sigma_t[g]`, `sigma_t[b]` | one channel of the extinction (`sigma_t:rgb`: all three) | `log` |
| `albedo[r]`, `albedo[g]`, `albedo[b]` | one channel of the albedo (`albedo:rgb`: all three) | `logit` |
| `g1`, `g2`, `w` | two-term HG's lobes in (-1, 1) and the first lobe's weight in (0, 1) | `atanh`, `atanh`, `logit` |
| `diameter` | fog-droplet diameter in µm, kept in (5, 50) (one smooth range of the fits) | `logit((d - 5) / 45)` |
| `sigma_0` | height fog: extinction at the base height, 1/scene unit, all channels | `log sigma_0` |
| `height_scale` | height fog: scale height H, scene units | `log H` |
| `base_height` | height fog: base height h_0, scene units (degenerate with sigma_0) | `h_0` |
| `scale` | grid fog: the factor on the grid's values (the extinction is `scale * D`), all voxels | `log scale` |
| `exposure` | the camera's factor on the scene's radiance, every target (photographs: `fitting.photo`) | `log` |
| `exposure[r]`, `exposure[g]`, `exposure[b]` | one channel's factor, every target (`exposure:rgb`: white balance) | `log` |
| `exposure@1` ... `exposure@8` | the factor of one target only (targets counted from 1, as given) | `log` |

Each parameter is a `ParamSpec` in `SPECS`: a `Transform` to the unconstrained coordinate and `get` / `set` on a
scene; parameters of the medium or its phase function are made with `medium_param`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxfog


class FitError(ValueError):
    """Bad fit arguments (unknown parameter, value out of range, wrong target, missing file)."""


@dataclass(frozen=True)
class Transform:
    """A bijection between a parameter's valid open interval and the real line: `to_u`, `from_u` (traceable; numpy
    on host values, so the solver's bookkeeping runs no eager JAX operation) and `dx_du(u)` (numpy, the derivative
    of `from_u`)."""

    to_u: Callable
    from_u: Callable
    dx_du: Callable


def _xp(x):
    """`jax.numpy` for JAX arrays and tracers, numpy for host values (each eager JAX operation compiles, or loads
    from the cache, a program of its own: ~40 ms each the first time in a process)."""
    return jnp if isinstance(x, jax.Array) else np


def _log(x):
    return _xp(x).log(x)


def _exp(u):
    return _xp(u).exp(u)


def _logit(x):
    xp = _xp(x)
    return xp.log(x) - xp.log1p(-x)


def _sigmoid(u):
    return 1.0 / (1.0 + _xp(u).exp(-u))


LOG = Transform(_log, _exp, np.exp)
"""(0, inf) <-> R: `u = log x`."""

ONE_BELOW = float(np.nextafter(np.float32(1.0), np.float32(0.0)))
"""The largest float32 below 1."""


def _tanh_open(u):
    """`tanh(u)` kept inside the open interval (-1, 1) in float32: for |u| > ~9 `tanh` rounds to +-1, a value the
    phase functions refuse (a fit that runs away toward |g| = 1 must report that, not crash)."""
    xp = _xp(u)
    return xp.clip(xp.tanh(u), -ONE_BELOW, ONE_BELOW)


def _atanh(x):
    return _xp(x).arctanh(x)


ATANH = Transform(_atanh, _tanh_open, lambda u: 1.0 - np.tanh(u) ** 2)
"""(-1, 1) <-> R: `u = atanh x`."""

LOGIT = Transform(_logit, _sigmoid, lambda u: (1.0 / (1.0 + np.exp(-u))) * (1.0 - 1.0 / (1.0 + np.exp(-u))))
"""(0, 1) <-> R: `u = logit x`."""


def interval(lo: float, hi: float) -> Transform:
    """(lo, hi) <-> R: `u = logit((x - lo) / (hi - lo))`."""
    w = hi - lo
    return Transform(lambda x: _logit((x - lo) / w), lambda u: lo + w * _sigmoid(u), lambda u: w * LOGIT.dx_du(u))


@dataclass(frozen=True)
class ParamSpec:
    """A fit parameter: its `name`, the `transform` to the solver's unconstrained coordinate, the open interval
    `(lo, hi)` of valid values, the `unit`, and how it is read from (`get`, a float; raises FitError when the scene
    has no such parameter) and written into (`set(scene, value)`, value a scalar or traced scalar) a scene."""

    name: str
    transform: Transform
    lo: float
    hi: float
    unit: str
    get: Callable
    set: Callable
    search: tuple | str = ()
    """The region the global search scans (`fitting.search.search_box`): a fixed `(lo, hi)` inside the valid range,
    or a kind whose range follows from the scene's size L and the starting value x0: "extinction" (optical depth
    0.01 to 20 over L, and x0 / 3 to 3 x0), "length" (L / 30 to 3 L), "offset" (x0 - L to x0 + L), "power" (x0 / 30
    to 30 x0)."""

    def to_u(self, x):
        return self.transform.to_u(x)

    def from_u(self, u):
        return self.transform.from_u(u)


def _medium(scene, name):
    if scene.medium is None:
        raise FitError(f"cannot fit {name}: the scene has no medium")
    return scene.medium


def medium_param(name: str, transform: Transform, lo: float, hi: float, unit: str = "", field: str | None = None,
                 search: tuple | str = ()):
    """A parameter that is a field of the scene's medium or of its phase function (`Scene.replace_medium` routes
    it); RGB fields are fitted grey (the mean is read, one value is written to every channel)."""
    field = field or name

    def owner(scene):
        med = _medium(scene, name)
        for obj in (med, med.phase):
            if field in {f.name for f in dataclasses.fields(obj)}:
                return obj
        raise FitError(f"cannot fit {name}: the scene's medium ({type(med).__name__} with "
                       f"{type(med.phase).__name__}) has no parameter {field!r}")

    def get(scene):
        return float(jnp.mean(getattr(owner(scene), field)))

    def set_(scene, value):
        shape = jnp.shape(getattr(owner(scene), field))
        return scene.replace_medium(**{field: jnp.broadcast_to(value, shape)})

    return ParamSpec(name, transform, lo, hi, unit, get, set_, search)


CHANNELS = ("r", "g", "b")


def channel_param(name: str, transform: Transform, lo: float, hi: float, unit: str, field: str, channel: int,
                  search: tuple | str = ()):
    """One channel (`0, 1, 2` = r, g, b) of an RGB field of the scene's medium, as its own fit parameter
    `field[r]` etc.: get reads that channel, set writes it and keeps the other two."""
    def owner_value(scene):
        med = _medium(scene, name)
        if field not in {f.name for f in dataclasses.fields(med)}:
            raise FitError(f"cannot fit {name}: the scene's medium ({type(med).__name__}) has no RGB field {field!r}")
        return getattr(med, field)

    def get(scene):
        return float(owner_value(scene)[channel])

    def set_(scene, value):
        kw = {field: owner_value(scene).at[channel].set(value)}
        if field == "sigma_t" and "spectral_mis" in {f.name for f in dataclasses.fields(scene.medium)}:
            kw["spectral_mis"] = True  # channels fitted apart differ: distances sampled by spectral MIS
        return scene.replace_medium(**kw)

    return ParamSpec(name, transform, lo, hi, unit, get, set_, search)


def _light_field(scene):
    if not scene.lights:
        raise FitError("cannot fit intensity: the scene has no light")
    return "radiance" if isinstance(scene.lights[0], jaxfog.AreaLight) else "intensity"


def _get_intensity(scene):
    field = _light_field(scene)  # first: it refuses a scene without lights
    return float(jnp.mean(getattr(scene.lights[0], field)))


def _set_intensity(scene, value):
    field = _light_field(scene)
    return eqx.tree_at(lambda s: getattr(s.lights[0], field), scene, jnp.broadcast_to(value, (3,)))


G_SEARCH = (-0.9, 0.95)
"""The asymmetries' search range: fog and haze lie in it (forward, g 0.5-0.9 for droplets), and beyond it the phase
function is a spike that a few-pixel render cannot tell from 0.9 / -0.9; the local solve may leave it."""

SPECS = {
    "sigma_t": medium_param("sigma_t", LOG, 0.0, np.inf, "1/unit", search="extinction"),
    "g": medium_param("g", ATANH, -1.0, 1.0, search=G_SEARCH),
    "albedo": medium_param("albedo", LOGIT, 0.0, 1.0, search=(0.1, 0.995)),
    "intensity": ParamSpec("intensity", LOG, 0.0, np.inf, "W/sr", _get_intensity, _set_intensity, "power"),
    # exponential height fog (jaxfog.HeightFog); sigma_0 and base_height enter only as sigma_0 exp(h_0 / H)
    "sigma_0": medium_param("sigma_0", LOG, 0.0, np.inf, "1/unit", search="extinction"),
    "height_scale": medium_param("height_scale", LOG, 0.0, np.inf, "unit", search="length"),
    # a density grid (jaxfog.GridMedium): its global factor; the voxels themselves are fitted by fitting.grid
    "scale": medium_param("scale", LOG, 0.0, np.inf, "", search="power"),
    "base_height": medium_param("base_height", Transform(lambda x: x, lambda u: u, np.ones_like), -np.inf, np.inf,
                                "unit", search="offset"),
}
"""Every fit parameter by name. A model adds its parameters here (e.g. with `medium_param`)."""

# chromatic media: one parameter per channel, `sigma_t[r]` ... `albedo[b]` (`--fit sigma_t:rgb` names all three)
for _field, _tr, _lo, _hi, _unit in (("sigma_t", LOG, 0.0, np.inf, "1/unit"), ("albedo", LOGIT, 0.0, 1.0, "")):
    for _c, _ch in enumerate(CHANNELS):
        SPECS[f"{_field}[{_ch}]"] = channel_param(f"{_field}[{_ch}]", _tr, _lo, _hi, _unit, _field, _c,
                                                  "extinction" if _field == "sigma_t" else (0.1, 0.995))

# phase functions: two-term HG's lobes and weight, the fog droplets' diameter (kept inside the fits' range 5..50 µm,
# where they are smooth: jaxfog._phase.DROPLET_PIECES)
SPECS.update({
    "g1": medium_param("g1", ATANH, -1.0, 1.0, search=G_SEARCH),
    "g2": medium_param("g2", ATANH, -1.0, 1.0, search=G_SEARCH),
    "w": medium_param("w", LOGIT, 0.0, 1.0, search=(0.05, 0.95)),
    "diameter": medium_param("diameter", interval(5.0, 50.0), 5.0, 50.0, "µm", search=(5.5, 45.0)),
})

# the camera: target = curve(exposure x render). Not a scene's parameter: `set` leaves the scene as it is, and
# `gains` gives each view's factor; a scene's "value" (the start) is 1.
MAX_VIEWS = 8


def _camera_param(name: str) -> ParamSpec:
    return ParamSpec(name, LOG, 0.0, np.inf, "", lambda scene: 1.0, lambda scene, value: scene, "power")


SPECS["exposure"] = _camera_param("exposure")
SPECS.update({f"exposure[{c}]": _camera_param(f"exposure[{c}]") for c in CHANNELS})
SPECS.update({f"exposure@{v}": _camera_param(f"exposure@{v}") for v in range(1, MAX_VIEWS + 1)})
CAMERA_PARAMS = frozenset(n for n in SPECS if n.startswith("exposure"))


def gains(values: dict, view: int):
    """The RGB factor `(3,)` on view `view`'s (0-based) render: the product of `exposure`, `exposure[c]` and
    `exposure@{view + 1}` where fitted; None where no camera parameter is."""
    if not CAMERA_PARAMS & set(values):
        return None
    g = jnp.ones(3)
    if "exposure" in values:
        g = g * values["exposure"]
    for c, ch in enumerate(CHANNELS):
        if f"exposure[{ch}]" in values:
            g = g.at[c].multiply(values[f"exposure[{ch}]"])
    if f"exposure@{view + 1}" in values:
        g = g * values[f"exposure@{view + 1}"]
    return g


EXPANSIONS = {f"{f}:rgb": [f"{f}[{c}]" for c in CHANNELS] for f in ("sigma_t", "albedo", "exposure")}
"""Names that stand for several parameters: `sigma_t:rgb` is `sigma_t[r] sigma_t[g] sigma_t[b]`."""


def check_names(names) -> list[str]:
    """The parameter names of a fit, with `EXPANSIONS` (`sigma_t:rgb`) expanded, checked and without repeats."""
    names = [m for n in names for m in EXPANSIONS.get(n, [n])]
    if not names:
        raise FitError("--fit needs at least one parameter name; valid: " + ", ".join([*SPECS, *EXPANSIONS]))
    for n in names:
        if n not in SPECS:
            raise FitError(f"unknown parameter {n!r}; valid: {', '.join([*SPECS, *EXPANSIONS])}")
    if len(set(names)) != len(names):
        raise FitError(f"parameter names repeat: {names}")
    camera = [n for n in names if n in CAMERA_PARAMS]
    if camera and "intensity" in names:
        raise FitError(f"--fit {' '.join(camera)} intensity: the camera's exposure and the light's intensity scale "
                       f"the images alike, so no target determines them apart; fit one of them")
    if "exposure" in names and len(camera) > 1:
        raise FitError(f"--fit {' '.join(camera)}: `exposure` scales every channel of every target, and "
                       f"{', '.join(n for n in camera if n != 'exposure')} scale(s) a part of them: together they are "
                       f"not determined apart; fit `exposure` or the parts")
    return names


def check_value(name: str, value: float) -> float:
    spec = SPECS[name]
    value = float(value)
    if not (spec.lo < value < spec.hi):
        raise FitError(f"{name}={value}: valid range ({spec.lo}, {spec.hi}) (open)")
    return value


def scene_values(scene: jaxfog.Scene) -> dict[str, float]:
    """The scene's current value of every fit parameter it has (grey: mean over channels)."""
    out = {}
    for name, spec in SPECS.items():
        try:
            out[name] = spec.get(scene)
        except (FitError, AttributeError):
            pass
    return out


def apply(scene: jaxfog.Scene, values: dict) -> jaxfog.Scene:
    """A copy of `scene` with the given parameter values (scalars or traced scalars) written in."""
    for name, value in values.items():
        scene = SPECS[name].set(scene, value)
    return scene


def to_unconstrained(names, values: dict) -> np.ndarray:
    """The unconstrained coordinates of `values` (float32, as the solver's coordinates are rendered)."""
    return np.asarray([SPECS[n].to_u(np.float32(values[n])) for n in names], np.float32)


def from_unconstrained(names, y) -> dict:
    return {n: SPECS[n].from_u(y[i]) for i, n in enumerate(names)}


def jacobian_to_params(names, y) -> np.ndarray:
    """d(param)/d(unconstrained), diagonal, as a vector."""
    return np.asarray([SPECS[n].transform.dx_du(float(y[i])) for i, n in enumerate(names)])
