"""Fit parameters: names, the unconstrained coordinates the solvers see, and how each is written into a scene.

| name | meaning | unconstrained coordinate |
| --- | --- | --- |
| `sigma_t` | extinction, 1/scene unit, all channels (grey fog) | `log sigma_t` |
| `g` | HG asymmetry in (-1, 1) | `atanh g` |
| `albedo` | single-scattering albedo in (0, 1), all channels | `logit albedo` |
| `intensity` | intensity (W/sr) of the scene's first light, all channels (radiance for an area light) | `log intensity` |
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import equinox as eqx
import jax.numpy as jnp
import numpy as np

import jaxfog


@dataclass(frozen=True)
class ParamSpec:
    name: str
    to_u: Callable
    from_u: Callable
    lo: float
    hi: float
    unit: str


def _logit(x):
    return jnp.log(x) - jnp.log1p(-x)


def _sigmoid(u):
    return 1.0 / (1.0 + jnp.exp(-u))


SPECS = {
    "sigma_t": ParamSpec("sigma_t", jnp.log, jnp.exp, 0.0, np.inf, "1/unit"),
    "g": ParamSpec("g", jnp.arctanh, jnp.tanh, -1.0, 1.0, ""),
    "albedo": ParamSpec("albedo", _logit, _sigmoid, 0.0, 1.0, ""),
    "intensity": ParamSpec("intensity", jnp.log, jnp.exp, 0.0, np.inf, "W/sr"),
}


class FitError(ValueError):
    """Bad fit arguments (unknown parameter, value out of range, wrong target, missing file)."""


def check_names(names) -> list[str]:
    names = list(names)
    if not names:
        raise FitError("--fit needs at least one parameter name; valid: " + ", ".join(SPECS))
    for n in names:
        if n not in SPECS:
            raise FitError(f"unknown parameter {n!r}; valid: {', '.join(SPECS)}")
    if len(set(names)) != len(names):
        raise FitError(f"parameter names repeat: {names}")
    return names


def check_value(name: str, value: float) -> float:
    spec = SPECS[name]
    value = float(value)
    if not (spec.lo < value < spec.hi):
        raise FitError(f"{name}={value}: valid range ({spec.lo}, {spec.hi}) (open)")
    return value


def scene_values(scene: jaxfog.Scene) -> dict[str, float]:
    """The scene's current value of every fit parameter (grey: mean over channels)."""
    out = {}
    if scene.medium is not None:
        out["sigma_t"] = float(jnp.mean(scene.medium.sigma_t))
        out["g"] = float(scene.medium.g)
        out["albedo"] = float(jnp.mean(scene.medium.albedo))
    if scene.lights:
        light = scene.lights[0]
        field = "radiance" if isinstance(light, jaxfog.AreaLight) else "intensity"
        out["intensity"] = float(jnp.mean(getattr(light, field)))
    return out


def apply(scene: jaxfog.Scene, values: dict) -> jaxfog.Scene:
    """A copy of `scene` with the given parameter values (scalars or traced scalars) written in."""
    med_values = {k: values[k] for k in ("sigma_t", "albedo", "g") if k in values}
    if med_values:
        if scene.medium is None:
            raise FitError(f"cannot fit {sorted(med_values)}: the scene has no medium")
        med_values = {k: (v if k == "g" else jnp.broadcast_to(v, (3,))) for k, v in med_values.items()}
        scene = scene.replace_medium(**med_values)
    if "intensity" in values:
        if not scene.lights:
            raise FitError("cannot fit intensity: the scene has no light")
        light = scene.lights[0]
        field = "radiance" if isinstance(light, jaxfog.AreaLight) else "intensity"
        scene = eqx.tree_at(lambda s: getattr(s.lights[0], field), scene, jnp.broadcast_to(values["intensity"], (3,)))
    return scene


def to_unconstrained(names, values: dict) -> jnp.ndarray:
    return jnp.stack([SPECS[n].to_u(jnp.float32(values[n])) for n in names])


def from_unconstrained(names, y) -> dict:
    return {n: SPECS[n].from_u(y[i]) for i, n in enumerate(names)}


def jacobian_to_params(names, y) -> np.ndarray:
    """d(param)/d(unconstrained), diagonal, as a vector."""
    out = []
    for i, n in enumerate(names):
        yi = float(y[i])
        if n in ("sigma_t", "intensity"):
            out.append(np.exp(yi))
        elif n == "g":
            out.append(1.0 - np.tanh(yi) ** 2)
        else:
            s = 1.0 / (1.0 + np.exp(-yi))
            out.append(s * (1.0 - s))
    return np.asarray(out)
