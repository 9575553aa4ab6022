"""Visibility from a fitted extinction: the meteorological optical range (MOR) and its standard error.

The WMO defines the MOR as the length of path in the atmosphere over which a collimated beam falls to 5% of its
flux (the contrast threshold of a black object against the horizon sky): `MOR = -ln(0.05) / sigma_t = 2.996 /
sigma_t`, in the scene's length unit (metres when the scene is modelled in metres). Its standard error follows from
the fit's covariance by the delta method: `se(MOR) = MOR * sqrt(d^T C d)` with `d` the gradient of `ln MOR` in the
fitted parameters (a parameter not fitted is taken as known).

For height fog, `sigma_t(h) = sigma_0 exp(-(h - h_0) / H)` along the fog's `up`: the MOR of a horizontal path at the
camera's height and at the base height `h_0` (where it is `-ln(0.05) / sigma_0`).
"""

from __future__ import annotations

import math

import numpy as np

CONTRAST = 0.05
"""The WMO's contrast threshold."""

K = -math.log(CONTRAST)
"""`-ln(0.05)` = 2.9957: MOR = K / sigma_t."""


def _entry(names, C, value: float, grad: dict) -> dict:
    """`{"mor", "se"}` for MOR `value` with `d ln MOR / d parameter` = `grad` (fitted names only)."""
    d = np.asarray([grad.get(n, 0.0) for n in names], np.float64)
    var = float(d @ np.asarray(C, np.float64) @ d) if C is not None else float("nan")
    return {"mor": float(value), "se": float(value * math.sqrt(var)) if var >= 0 else float("nan")}


def visibility(scene, names: list, values: dict, C) -> dict | None:
    """The MOR of the fitted medium (`values`: the estimates by name, `C` their covariance in the parameters' units)
    and its standard error, or None where the fit did not include the extinction. Returns `{"unit": "scene units",
    ...}` with `"mor"`, `"se"` for a grey extinction, `"channels": {"r": {...}, ...}` for a per-channel one, and
    `"camera_height"`, `"base_height"` entries (each `{"height", "mor", "se"}`) for height fog."""
    out = {"unit": "scene units", "definition": "MOR = -ln(0.05) / sigma_t (WMO, 5% contrast)"}
    if "sigma_t" in names:
        s = values["sigma_t"]
        return {**out, **_entry(names, C, K / s, {"sigma_t": -1.0 / s})}
    chans = [c for c in "rgb" if f"sigma_t[{c}]" in names]
    if chans:
        out["channels"] = {c: _entry(names, C, K / values[f"sigma_t[{c}]"],
                                     {f"sigma_t[{c}]": -1.0 / values[f"sigma_t[{c}]"]}) for c in chans}
        return out
    if {"sigma_0", "height_scale", "base_height"} & set(names):
        med = scene.medium
        s0 = values.get("sigma_0", float(np.mean(np.asarray(med.sigma_0))))
        H = values.get("height_scale", float(med.height_scale))
        h0 = values.get("base_height", float(med.base_height))
        up = np.asarray(med.up, np.float64)
        hc = float(np.asarray(scene.camera.origin, np.float64) @ up)
        dh = hc - h0
        sig_c = s0 * math.exp(-dh / H)
        out["camera_height"] = {"height": hc, **_entry(
            names, C, K / sig_c, {"sigma_0": -1.0 / s0, "height_scale": -dh / H ** 2, "base_height": -1.0 / H})}
        out["base_height"] = {"height": h0, **_entry(names, C, K / s0, {"sigma_0": -1.0 / s0})}
        return out
    return None


def describe(vis: dict | None) -> list[str]:
    """Lines for the terminal."""
    if not vis:
        return []
    unit = "scene units (metres for a scene in metres)"
    if "mor" in vis:
        return [f"visibility (MOR, WMO): {vis['mor']:.4g} ± {vis['se']:.2g} {unit}"]
    if "channels" in vis:
        return ["visibility (MOR, WMO) per channel: " + ", ".join(
            f"{c} {e['mor']:.4g} ± {e['se']:.2g}" for c, e in vis["channels"].items()) + f" {unit}"]
    return [f"visibility (MOR, WMO) at the camera's height {vis['camera_height']['height']:.4g}: "
            f"{vis['camera_height']['mor']:.4g} ± {vis['camera_height']['se']:.2g}; at the base height "
            f"{vis['base_height']['height']:.4g}: {vis['base_height']['mor']:.4g} ± {vis['base_height']['se']:.2g} "
            f"{unit}"]
