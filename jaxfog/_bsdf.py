"""Surface scattering: diffuse (one-sided, Lambertian), mirror, smooth glass; pure math plus small Modules.

Directions follow the camera path: `d` is the direction the path arrived along (pointing *into* the surface), `wo` the
direction it leaves along. Weights returned by samplers already divide by their pdf.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._math import safe_sqrt


def _rgb(x) -> Float[Array, "3"]:
    x = jnp.asarray(x, dtype=jnp.float32)
    return jnp.broadcast_to(x, (3,)) if x.ndim == 0 else x.reshape(3)


def _scalar(x) -> Float[Array, ""]:
    return jnp.asarray(x, dtype=jnp.float32).reshape(())


class AbstractBSDF(eqx.Module):
    """A surface's scattering model. Concrete BSDFs are final."""


class Diffuse(AbstractBSDF):
    """Lambertian, one-sided (Mitsuba `diffuse`): BRDF `reflectance / pi` on the front face, black from the back.

    `reflectance`: RGB in [0, 1].
    """

    reflectance: Float[Array, "3"] = eqx.field(converter=_rgb)


class Mirror(AbstractBSDF):
    """Perfect specular reflector with RGB `reflectance` in [0, 1] (Mitsuba `conductor`, white perfect reflector), two-sided."""

    reflectance: Float[Array, "3"] = eqx.field(converter=_rgb, default=1.0)


class Glass(AbstractBSDF):
    """Smooth dielectric with `int_ior` inside and `ext_ior` outside (defaults 1.5 / 1.0); Fresnel chooses reflection
    or refraction stochastically. Inside a glass object there is no fog."""

    int_ior: Float[Array, ""] = eqx.field(converter=_scalar, default=1.5)
    ext_ior: Float[Array, ""] = eqx.field(converter=_scalar, default=1.0)


def cosine_cos(u: Float[Array, ""]) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """Polar part of cosine-weighted sampling around a normal: `(1 - cos theta, 1 + cos theta)` for u in [0, 1)
    (`cos theta = sqrt(1 - u)`, pdf `cos theta / pi` over directions; with a uniform azimuth,
    `_math.direction_from_cos` makes the direction). `1 - cos = u / (1 + cos)` has no cancellation."""
    z = safe_sqrt(1.0 - u)
    return u / (1.0 + z), 1.0 + z


def reflect(d: Float[Array, "3"], n: Float[Array, "3"]) -> Float[Array, "3"]:
    """Mirror reflection of the incoming direction `d` about the normal `n` (either side)."""
    return d - 2.0 * jnp.sum(d * n) * n


def fresnel_dielectric(cos_i: Float[Array, ""], eta: Float[Array, ""]) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """Unpolarized Fresnel reflectance for a smooth dielectric interface.

    **Arguments:** `cos_i` in [0, 1], cosine of the incident angle on the incident side; `eta` = n_transmitted /
    n_incident (> 0).

    **Returns:** `(F, cos_t)`: reflectance in [0, 1] (1 under total internal reflection) and the cosine of the
    transmitted angle (>= 0).
    """
    sin2_t = (1.0 - cos_i * cos_i) / (eta * eta)
    tir = sin2_t >= 1.0
    cos_t = safe_sqrt(1.0 - sin2_t)
    rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    f = 0.5 * (rs * rs + rp * rp)
    return jnp.where(tir, 1.0, f), cos_t


def refract(d: Float[Array, "3"], n: Float[Array, "3"], eta: Float[Array, ""], cos_t: Float[Array, ""]) -> Float[Array, "3"]:
    """Refracted direction of unit `d` through a surface with unit normal `n` facing the incident side
    (`dot(d, n) < 0`); `eta` = n_t / n_i, `cos_t` from `fresnel_dielectric`."""
    cos_i = -jnp.sum(d * n)
    return d / eta + (cos_i / eta - cos_t) * n
