"""Surface scattering behind one interface: `sample`, `eval`, `pdf`; diffuse (one-sided), mirror, smooth glass.

Directions follow the camera path: `d` is the direction the path arrived along (pointing *into* the surface), `wo`
the direction it leaves along, `n` the surface's geometric front normal. Weights returned by `sample` already divide
by the pdf. Delta BSDFs (mirror, glass) have no density: their `eval` and `pdf` are 0 for every direction a light
sample can produce, and their sample is flagged `delta`.

Non-delta BSDFs here are sampled by a lobe that is rotationally symmetric about the normal (`AbstractLobeBSDF`,
the cosine lobe of `Diffuse`): the tracer takes their polar sample (`sample_polar`) so that all techniques of a
bounce share one direction construction.

Adding a BSDF: one final class here and one entry in `_scene_io.BSDFS` (see `notes/ARCHITECTURE.md`).
"""


import abc
from typing import ClassVar, NamedTuple

import equinox as eqx
from equinox import AbstractClassVar
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ._fields import rgb, scalar
from ._math import INV_PI, dot, safe_normalize, safe_sqrt
from ._sampling import Polar, cosine_pdf, cosine_sample, to_direction
from ._validate import POSITIVE, UNIT, check_range


class BSDFSample(NamedTuple):
    """A sampled outgoing direction: `wo` (unit), `weight` (RGB, `f |cos| / pdf`, or the delta lobe's weight),
    `pdf` (1/sr; 0 for delta samples), `delta` (a specular sample: no MIS with lights) and `transmitted` (the
    direction crossed the surface)."""

    wo: Float[Array, "3"]
    weight: Float[Array, "3"]
    pdf: Float[Array, ""]
    delta: Bool[Array, ""]
    transmitted: Bool[Array, ""]


class AbstractBSDF(eqx.Module):
    """A surface's scattering model. Concrete BSDFs are final."""

    is_delta: AbstractClassVar[bool]

    @abc.abstractmethod
    def sample(self, d: Float[Array, "3"], n: Float[Array, "3"], u: Float[Array, "3"]) -> BSDFSample:
        """Sample `wo` for a path arriving along `d` at a surface with front normal `n`; `u`: (polar, azimuth,
        choice) uniforms in [0, 1)."""

    @abc.abstractmethod
    def eval(self, d: Float[Array, "3"], wo: Float[Array, "3"], n: Float[Array, "3"]) -> Float[Array, "3"]:
        """`f(d, wo) |cos theta_o|` (RGB, 1/sr): the BSDF times the cosine at the outgoing direction."""

    @abc.abstractmethod
    def pdf(self, d: Float[Array, "3"], wo: Float[Array, "3"], n: Float[Array, "3"]) -> Float[Array, ""]:
        """Solid-angle density (1/sr) with which `sample` produces `wo`."""


class AbstractLobeBSDF(AbstractBSDF):
    """A non-delta BSDF sampled by a lobe symmetric about the front normal (`sample_polar`, `pdf_cos`)."""

    is_delta: ClassVar[bool] = False

    @abc.abstractmethod
    def sample_polar(self, u: Float[Array, ""]) -> Polar:
        """Polar angle about the front normal, u in [0, 1)."""

    @abc.abstractmethod
    def pdf_cos(self, cos_o: Float[Array, ""]) -> Float[Array, ""]:
        """Density (1/sr) of the lobe at a direction with `cos theta_o = dot(n, wo)`."""

    @abc.abstractmethod
    def eval_cos(self, cos_i: Float[Array, ""], cos_o: Float[Array, ""]) -> Float[Array, "3"]:
        """`f |cos theta_o|` from `cos theta_i = -dot(d, n)` and `cos theta_o = dot(n, wo)`."""

    def sample(self, d, n, u) -> BSDFSample:
        polar = self.sample_polar(u[0])
        wo = to_direction(polar, u[1], n)
        cos_o = 0.5 * (polar.one_plus_cos - polar.one_minus_cos)
        pdf = self.pdf_cos(cos_o)
        weight = self.eval_cos(-dot(d, n), cos_o) / jnp.where(pdf > 0, pdf, 1.0)
        return BSDFSample(wo, weight, pdf, jnp.bool_(False), jnp.bool_(False))

    def eval(self, d, wo, n):
        return self.eval_cos(-dot(d, n), dot(n, wo))

    def pdf(self, d, wo, n):
        return self.pdf_cos(dot(n, wo))


class Diffuse(AbstractLobeBSDF):
    """Lambertian, one-sided (Mitsuba `diffuse`): BRDF `reflectance / pi` on the front face, black from the back.

    `reflectance`: RGB in [0, 1]. Sampled with the cosine lobe: `weight = reflectance` exactly.
    """

    reflectance: Float[Array, "3"] = eqx.field(converter=rgb)

    def __check_init__(self):
        check_range("Diffuse", "reflectance", self.reflectance, UNIT)

    def sample_polar(self, u):
        return cosine_sample(u)

    def pdf_cos(self, cos_o):
        return cosine_pdf(cos_o)

    def eval_cos(self, cos_i, cos_o):
        return jnp.where((cos_i > 0) & (cos_o > 0), self.reflectance * INV_PI * cos_o, 0.0)


class Mirror(AbstractBSDF):
    """Perfect specular reflector with RGB `reflectance` in [0, 1] (Mitsuba `conductor`, white perfect reflector),
    two-sided."""

    reflectance: Float[Array, "3"] = eqx.field(converter=rgb, default=1.0)
    is_delta: ClassVar[bool] = True

    def __check_init__(self):
        check_range("Mirror", "reflectance", self.reflectance, UNIT)

    def sample(self, d, n, u) -> BSDFSample:
        return BSDFSample(reflect(d, n), self.reflectance, jnp.float32(0.0), jnp.bool_(True), jnp.bool_(False))

    def eval(self, d, wo, n):
        return jnp.zeros(3, jnp.float32)

    def pdf(self, d, wo, n):
        return jnp.float32(0.0)


class Glass(AbstractBSDF):
    """Smooth dielectric with `int_ior` inside and `ext_ior` outside (> 0; defaults 1.5 / 1.0); Fresnel chooses
    reflection or refraction stochastically (`u[2]`). Inside a glass object there is no fog. Radiance is compressed
    by `1 / eta^2` across the interface (as in Mitsuba for radiance transport)."""

    int_ior: Float[Array, ""] = eqx.field(converter=scalar, default=1.5)
    ext_ior: Float[Array, ""] = eqx.field(converter=scalar, default=1.0)
    is_delta: ClassVar[bool] = True

    def __check_init__(self):
        check_range("Glass", "int_ior", self.int_ior, POSITIVE)
        check_range("Glass", "ext_ior", self.ext_ior, POSITIVE)

    def sample(self, d, n, u) -> BSDFSample:
        cos_d = dot(d, n)
        entering = cos_d < 0
        n_i = jnp.where(entering, n, -n)
        eta = jnp.where(entering, self.int_ior / self.ext_ior, self.ext_ior / self.int_ior)
        F, cos_t = fresnel_dielectric(jnp.abs(cos_d), eta)
        refl = u[2] < F
        wo = jnp.where(refl, reflect(d, n_i), safe_normalize(refract(d, n_i, eta, cos_t)))
        scale = jnp.where(refl, 1.0, 1.0 / (eta * eta))  # radiance compression across the interface
        return BSDFSample(wo, jnp.broadcast_to(scale, (3,)), jnp.float32(0.0), jnp.bool_(True), ~refl)

    def eval(self, d, wo, n):
        return jnp.zeros(3, jnp.float32)

    def pdf(self, d, wo, n):
        return jnp.float32(0.0)


# ---------------------------------------------------------------------------------------------------- pure math
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
