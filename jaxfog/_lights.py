"""Lights behind one interface: `sample_li`, `pdf_li`, and for point-like lights the lit interval of a ray.

- `sample_li(p, u) -> LightSample(wi, dist, rgb, scale, pdf)`: a direction `wi` from the point `p` toward the light,
  the shadow-ray length `dist`, the unoccluded, untransmitted value `value = rgb * scale` (an RGB part and a scalar
  part) and the solid-angle `pdf` of `wi`; the contribution of the sample is `f(wi) * value * T(dist) / pdf`. Delta
  lights (point, spot, directional) have `pdf = 1`; point and spot lights have `value = I(-wi) / dist^2`
  (irradiance on a surface facing the light) with the angular profile and `1 / dist^2` in the scalar `scale`; area
  lights have `value = L_e`.
- `pdf_li(p, wi, dist)`: the density with which `sample_li` picks `wi` (0 for delta lights), for MIS.
- Point-like lights (`AbstractPointLikeLight`: point and spot) have a `position` (the centre that equiangular
  sampling and the light-angle lobe aim at) and `lit_interval(o, d)`: where along the ray `o + t d` the light
  shines at all (the spot's cone), so equiangular samples are spent only there.
- Area lights (`AbstractAreaLight`) are also surfaces: `shape` (an `AbstractShape`, black: it reflects nothing) is
  intersected with the scene's shapes, `emitted(d, n)` is the radiance a ray travelling along `d` sees where it hits
  it, and `sample_li` samples the shape by area (`AbstractShape.sample_area`).

`n_dims` (static) is the number of uniforms `sample_li` consumes. Point and spot lights are delta lights: invisible
to the camera and reached only by next-event estimation.

Adding a light: one final class here and one entry in `_scene_io.LIGHTS` (see `notes/ARCHITECTURE.md`).
"""


import abc
from typing import ClassVar, NamedTuple

import equinox as eqx
from equinox import AbstractClassVar, AbstractVar
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._bsdf import Diffuse
from ._fields import rgb, scalar, vec3
from ._math import atan2, dot, safe_div, safe_normalize, safe_sqrt
from ._shapes import AbstractShape, Rectangle, check_perpendicular, solid_angle_pdf
from ._validate import ANY, NON_NEGATIVE, SPOT_CUTOFF_RANGE, POSITIVE, check_range, check_vector, concrete_values


class LightSample(NamedTuple):
    """`wi` (unit, from the shading point toward the light), `dist` (scene units), the value in two parts, `rgb`
    (RGB) and `scale` (a scalar; `value = rgb * scale`: the irradiance factor `I / dist^2` of a point-like light
    as its colour and its angular profile over `dist^2`, so that the tracer computes the scalar once for the three
    channels; `rgb = L_e`, `scale = 1` for area lights; 0 where the sample is invalid) and `pdf` (1/sr; 1 for delta
    lights; 0 where invalid)."""

    wi: Float[Array, "3"]
    dist: Float[Array, ""]
    rgb: Float[Array, "3"]
    scale: Float[Array, ""]
    pdf: Float[Array, ""]

    @property
    def value(self) -> Float[Array, "3"]:
        """The sample's unoccluded, untransmitted value `rgb * scale` (RGB)."""
        return self.rgb * self.scale


class AbstractLight(eqx.Module):
    """A light source. Concrete lights are final."""

    is_delta: AbstractClassVar[bool]
    n_dims: AbstractClassVar[int]

    @abc.abstractmethod
    def sample_li(self, p: Float[Array, "3"], u: Float[Array, "n"]) -> LightSample:
        """Sample the light as seen from the point `p`, with `n_dims` uniforms `u`."""

    @abc.abstractmethod
    def pdf_li(self, p: Float[Array, "3"], wi: Float[Array, "3"], dist: Float[Array, ""]) -> Float[Array, ""]:
        """Solid-angle density with which `sample_li(p, .)` picks the direction `wi` reaching the light at `dist`."""


class AbstractPointLikeLight(AbstractLight):
    """A delta light at a point: `position`; its radiant intensity in each direction as a colour and an angular
    profile (`intensity_parts`); where along a ray it shines at all (`lit_interval`). `sample_li` / `pdf_li` follow
    from them (final)."""

    position: AbstractVar[Float[Array, "3"]]
    is_delta: ClassVar[bool] = True
    n_dims: ClassVar[int] = 0

    @abc.abstractmethod
    def intensity_parts(self, w: Float[Array, "3"]) -> tuple[Float[Array, "3"], Float[Array, ""]]:
        """`(rgb, scale)`: the radiant intensity (W/sr) the light sends along the unit direction `w` (away from the
        light) is `rgb * scale`; a light whose colour does not depend on `w` returns its colour and its angular
        profile (a scalar, computed once for the three channels), one whose colour does returns it and 1."""

    @abc.abstractmethod
    def lit_interval(self, o: Float[Array, "3"], d: Float[Array, "3"]) -> tuple[Float[Array, ""], Float[Array, ""]]:
        """`(t0, t1)`: the light shines on the line `o + t d` only for `t0 <= t <= t1` (possibly empty: t0 > t1;
        possibly infinite)."""

    def intensity_toward(self, w: Float[Array, "3"]) -> Float[Array, "3"]:
        """RGB radiant intensity (W/sr) the light sends along the unit direction `w`: `rgb * scale`."""
        colour, profile = self.intensity_parts(w)
        return colour * profile

    def sample_li(self, p, u=None) -> LightSample:
        """The direction to `position` (no uniforms), `rgb` the colour toward `p` and `scale` its profile over the
        squared distance."""
        v = self.position - p
        dist2 = dot(v, v)
        wi = safe_normalize(v)
        colour, profile = self.intensity_parts(-wi)
        return LightSample(wi, safe_sqrt(dist2), colour, safe_div(profile, dist2), jnp.float32(1.0))

    def pdf_li(self, p, wi, dist):
        return jnp.float32(0.0)


class PointLight(AbstractPointLikeLight):
    """Isotropic point light: `position` (scene units), radiant `intensity` (W/sr, RGB >= 0)."""

    position: Float[Array, "3"] = eqx.field(converter=vec3)
    intensity: Float[Array, "3"] = eqx.field(converter=rgb)

    def __check_init__(self):
        check_range("PointLight", "position", self.position, ANY)
        check_range("PointLight", "intensity", self.intensity, NON_NEGATIVE)

    def intensity_parts(self, w):
        return self.intensity, jnp.float32(1.0)

    def lit_interval(self, o, d):
        return jnp.float32(-jnp.inf), jnp.float32(jnp.inf)


SPOT_CUTOFF_DEFAULT = 20.0
"""Mitsuba's default spot cutoff angle (degrees)."""


def spot_beam_width_default(cutoff_angle: float) -> float:
    """Mitsuba's default spot beam width: 3/4 of the cutoff angle (degrees)."""
    return 0.75 * cutoff_angle


class SpotLight(AbstractPointLikeLight):
    """Spot light (Mitsuba `spot`): `position`, unit `direction` of the axis, on-axis `intensity` (W/sr, RGB >= 0),
    `cutoff_angle` in (0, 90) and `beam_width` in (0, cutoff_angle] degrees (Mitsuba's defaults: 20, and 3/4 of the
    cutoff). Intensity at angle theta from the axis is `intensity * spot_falloff(theta)`."""

    position: Float[Array, "3"] = eqx.field(converter=vec3)
    direction: Float[Array, "3"] = eqx.field(converter=lambda v: safe_normalize(vec3(v)))
    intensity: Float[Array, "3"] = eqx.field(converter=rgb)
    cutoff_angle: Float[Array, ""] = eqx.field(converter=scalar)
    beam_width: Float[Array, ""] = eqx.field(converter=scalar)

    def __init__(self, position, direction, intensity, cutoff_angle=SPOT_CUTOFF_DEFAULT, beam_width=None):
        self.position = position
        self.direction = direction
        self.intensity = intensity
        self.cutoff_angle = cutoff_angle
        self.beam_width = spot_beam_width_default(cutoff_angle) if beam_width is None else beam_width

    def __check_init__(self):
        check_range("SpotLight", "position", self.position, ANY)
        check_vector("SpotLight", "direction", self.direction)
        check_range("SpotLight", "intensity", self.intensity, NON_NEGATIVE)
        check_range("SpotLight", "cutoff_angle", self.cutoff_angle, SPOT_CUTOFF_RANGE)
        check_range("SpotLight", "beam_width", self.beam_width, POSITIVE)
        vals = concrete_values(self.cutoff_angle, self.beam_width)
        if vals is not None and vals[1] > vals[0]:
            raise ValueError(f"SpotLight.beam_width = {float(vals[1])} must not exceed cutoff_angle = "
                             f"{float(vals[0])}")

    def intensity_parts(self, w):
        return self.intensity, spot_falloff(dot(w, self.direction), self.cutoff_angle, self.beam_width)

    def lit_interval(self, o, d):
        return spot_cone_interval(self.position, self.direction, self.cutoff_angle, o, d)


class AbstractAreaLight(AbstractLight):
    """A light that is also a surface: its `shape` is intersected with the scene's shapes (a black surface: a path
    that hits it ends there) and seen by the camera; `emitted(d, n)` is the radiance a ray travelling along `d` sees
    where it hits the shape with front normal `n`. Not a delta light."""

    is_delta: ClassVar[bool] = False

    @property
    @abc.abstractmethod
    def shape(self) -> AbstractShape:
        """The emitting surface, as a shape (its `bsdf` black)."""

    @abc.abstractmethod
    def emitted(self, d: Float[Array, "3"], n: Float[Array, "3"]) -> Float[Array, "3"]:
        """Radiance (RGB, W/(m^2 sr)) seen by a ray travelling along `d` that hits the light where its front normal
        is `n`."""


class AreaLight(AbstractAreaLight):
    """One-sided emitting rectangle: `center`, perpendicular full edges `edge_u`, `edge_v` (scene units), emitted
    `radiance` (W/(m^2 sr), RGB >= 0) on the front face `normalize(cross(edge_u, edge_v))`. It is also a black
    surface that blocks light (in Mitsuba: give its shape a `diffuse` BSDF with reflectance 0). Sampled uniformly
    by area (2 uniforms)."""

    center: Float[Array, "3"] = eqx.field(converter=vec3)
    edge_u: Float[Array, "3"] = eqx.field(converter=vec3)
    edge_v: Float[Array, "3"] = eqx.field(converter=vec3)
    radiance: Float[Array, "3"] = eqx.field(converter=rgb)
    n_dims: ClassVar[int] = 2

    def __check_init__(self):
        check_range("AreaLight", "center", self.center, ANY)
        check_vector("AreaLight", "edge_u", self.edge_u)
        check_vector("AreaLight", "edge_v", self.edge_v)
        check_perpendicular("AreaLight", self.edge_u, self.edge_v)
        check_range("AreaLight", "radiance", self.radiance, NON_NEGATIVE)

    @property
    def shape(self) -> Rectangle:
        return Rectangle(self.center, self.edge_u, self.edge_v, bsdf=Diffuse(0.0))

    @property
    def normal(self) -> Float[Array, "3"]:
        """The unit front normal `normalize(cross(edge_u, edge_v))`."""
        return self.shape.normal

    @property
    def area(self) -> Float[Array, ""]:
        return self.shape.area

    def sample_li(self, p, u) -> LightSample:
        s = self.shape.sample_area(u)
        v = s.p - p
        dist2 = dot(v, v)
        wi = safe_normalize(v)
        cos_l = -dot(wi, s.n)
        pdf = solid_angle_pdf(s.pdf, dist2, cos_l)
        return LightSample(wi, safe_sqrt(dist2), jnp.where(cos_l > 0, self.radiance, 0.0), jnp.float32(1.0), pdf)

    def pdf_li(self, p, wi, dist):
        shape = self.shape
        return solid_angle_pdf(shape.pdf_area(p + dist * wi), dist * dist, -dot(wi, shape.normal))

    def emitted(self, d, n):
        return jnp.where(dot(d, n) < 0, self.radiance, 0.0)


# ---------------------------------------------------------------------------------------------------- pure math
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


def spot_cone_interval(position, axis, cutoff_deg, o, d):
    """Interval `[t0, t1]` (possibly empty: t0 > t1; possibly infinite) where the line `o + t d` is inside the cone
    of half-angle `cutoff_deg` with apex `position` around the unit `axis` (the forward nappe only)."""
    a = axis
    c2 = jnp.cos(jnp.deg2rad(cutoff_deg)) ** 2
    # the quadratic in s = t - tc, about the line's closest approach `tc` to the apex: there w is perpendicular to
    # d and as short as the line's distance from the apex, so the coefficients carry no large cancelling terms (from
    # the origin, a line passing 1 cm from the apex of a spot 3 m away lost the cone's ends by ~1 mm in float32, and
    # points the spot lights went without their equiangular density: a firefly of I / r^2 at r ~ 1 cm)
    tc = dot(position - o, d)
    w = o + tc * d - position
    da, wa = dot(d, a), dot(w, a)
    A = da * da - c2
    B = 2.0 * (da * wa - c2 * dot(d, w))
    C = wa * wa - c2 * dot(w, w)
    disc = B * B - 4.0 * A * C
    sq = safe_sqrt(disc)
    A_safe = jnp.where(jnp.abs(A) > 1e-12, A, 1e-12)
    # the root of the larger magnitude by the usual formula, the other as C / (A root) (no -B + sq cancellation)
    q = -0.5 * (B + jnp.where(B >= 0, sq, -sq))
    q_safe = jnp.where(jnp.abs(q) > 1e-30, q, 1e-30)
    r1 = q / A_safe
    r2 = jnp.where(jnp.abs(q) > 1e-30, C / q_safe, r1)
    lo, hi = jnp.minimum(r1, r2) + tc, jnp.maximum(r1, r2) + tc
    inf = jnp.inf
    # A < 0: inside between the roots (one nappe; check which). A > 0: outside the roots, the nappe d points into.
    mid = 0.5 * (lo + hi) - tc
    mid_fwd = (wa + mid * da) >= 0
    t0_neg = jnp.where((disc >= 0) & mid_fwd, lo, inf)
    t1_neg = jnp.where((disc >= 0) & mid_fwd, hi, -inf)
    # A > 0 and no real root (a line through the apex, up to rounding): inside the double cone everywhere, so in the
    # forward nappe on the half-line past the apex, `wa + s da >= 0`
    apex = tc - wa / jnp.where(jnp.abs(da) > 1e-12, da, 1e-12)
    t0_pos = jnp.where(disc >= 0, jnp.where(da > 0, hi, -inf), jnp.where(da > 0, apex, -inf))
    t1_pos = jnp.where(disc >= 0, jnp.where(da > 0, inf, lo), jnp.where(da > 0, inf, apex))
    neg = A < 0
    return jnp.where(neg, t0_neg, t0_pos), jnp.where(neg, t1_neg, t1_pos)


class DirectionalLight(AbstractLight):
    """A distant light (the sun; Mitsuba `directional`): unit `direction` in which the light travels, and the
    `irradiance` E (W/m^2, RGB >= 0) it delivers on a surface facing it. A delta light, reached by next-event
    estimation only: `sample_li` returns `wi = -direction`, `dist = inf` (the shadow ray is blocked by any surface
    along it; the medium's transmittance is taken to infinity) and `value = E`, with no 1/r^2."""

    direction: Float[Array, "3"] = eqx.field(converter=lambda v: safe_normalize(vec3(v)))
    irradiance: Float[Array, "3"] = eqx.field(converter=rgb)
    is_delta: ClassVar[bool] = True
    n_dims: ClassVar[int] = 0

    def __check_init__(self):
        check_vector("DirectionalLight", "direction", self.direction)
        check_range("DirectionalLight", "irradiance", self.irradiance, NON_NEGATIVE)

    def sample_li(self, p, u=None) -> LightSample:
        one = jnp.float32(1.0)
        return LightSample(-self.direction, jnp.float32(jnp.inf), self.irradiance, one, one)

    def pdf_li(self, p, wi, dist):
        return jnp.float32(0.0)
