"""Lights: point, spot (Mitsuba's linear falloff) and one-sided rectangular area lights, plus their pure math.

Point and spot lights are delta lights: invisible to the camera and reached only by next-event estimation.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._math import atan2, cross, dot, safe_normalize, safe_sqrt


def _vec3(x) -> Float[Array, "3"]:
    return jnp.asarray(x, dtype=jnp.float32).reshape(3)


def _rgb(x) -> Float[Array, "3"]:
    x = jnp.asarray(x, dtype=jnp.float32)
    return jnp.broadcast_to(x, (3,)) if x.ndim == 0 else x.reshape(3)


def _scalar(x) -> Float[Array, ""]:
    return jnp.asarray(x, dtype=jnp.float32).reshape(())


class AbstractLight(eqx.Module):
    """A light source. Concrete lights are final."""


class PointLight(AbstractLight):
    """Isotropic point light: `position` (scene units), radiant `intensity` (W/sr, RGB >= 0)."""

    position: Float[Array, "3"] = eqx.field(converter=_vec3)
    intensity: Float[Array, "3"] = eqx.field(converter=_rgb)


class SpotLight(AbstractLight):
    """Spot light (Mitsuba `spot`): `position`, unit `direction` of the axis, on-axis `intensity` (W/sr, RGB),
    `cutoff_angle` and `beam_width` in degrees (0 < beam_width <= cutoff_angle < 90 in the shipped scenes; Mitsuba's
    defaults are 20 and 15). Intensity at angle theta from the axis is `intensity * spot_falloff(theta)`."""

    position: Float[Array, "3"] = eqx.field(converter=_vec3)
    direction: Float[Array, "3"] = eqx.field(converter=lambda v: safe_normalize(_vec3(v)))
    intensity: Float[Array, "3"] = eqx.field(converter=_rgb)
    cutoff_angle: Float[Array, ""] = eqx.field(converter=_scalar, default=20.0)
    beam_width: Float[Array, ""] = eqx.field(converter=_scalar, default=15.0)


class AreaLight(AbstractLight):
    """One-sided emitting rectangle: `center`, perpendicular full edges `edge_u`, `edge_v` (scene units), emitted
    `radiance` (W/(m^2 sr), RGB) on the front face `normalize(cross(edge_u, edge_v))`. It is also a black surface
    that blocks light (in Mitsuba: give its shape a `diffuse` BSDF with reflectance 0)."""

    center: Float[Array, "3"] = eqx.field(converter=_vec3)
    edge_u: Float[Array, "3"] = eqx.field(converter=_vec3)
    edge_v: Float[Array, "3"] = eqx.field(converter=_vec3)
    radiance: Float[Array, "3"] = eqx.field(converter=_rgb)

    @property
    def normal(self) -> Float[Array, "3"]:
        return safe_normalize(cross(self.edge_u, self.edge_v))

    @property
    def area(self) -> Float[Array, ""]:
        return jnp.linalg.norm(cross(self.edge_u, self.edge_v))


def spot_falloff(cos_theta, cutoff_deg, beam_width_deg) -> Float[Array, ""]:
    """Mitsuba's spot falloff at angle theta from the axis (given as `cos theta`): 1 inside `beam_width`,
    `(cutoff - theta) / (cutoff - beam_width)` (radians) between, 0 beyond `cutoff`."""
    cutoff = jnp.deg2rad(cutoff_deg)
    beam = jnp.deg2rad(beam_width_deg)
    inside_beam = cos_theta >= jnp.cos(beam)
    in_ramp = ~inside_beam & (cos_theta > jnp.cos(cutoff))
    # double where: arccos has an infinite derivative at +-1, which only the beam/outside branches can reach;
    # arccos(c) = atan2(sqrt(1 - c^2), c) with the vectorized `atan2` (jnp.arccos is a scalar call on a CPU)
    c = jnp.where(in_ramp, cos_theta, jnp.cos(0.5 * (cutoff + beam)))
    theta = atan2(safe_sqrt((1.0 - c) * (1.0 + c)), c)
    width = cutoff - beam
    ramp = (cutoff - theta) / jnp.where(width > 0, width, 1.0)
    return jnp.where(inside_beam, 1.0, jnp.where(in_ramp, ramp, 0.0))


def delta_light_radiant_intensity(light, w_from_light: Float[Array, "3"]) -> Float[Array, "3"]:
    """RGB radiant intensity (W/sr) a point or spot light sends along the unit direction `w_from_light`."""
    if isinstance(light, SpotLight):
        cos_theta = dot(w_from_light, light.direction)
        return light.intensity * spot_falloff(cos_theta, light.cutoff_angle, light.beam_width)
    return light.intensity
