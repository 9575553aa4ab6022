"""Phase functions behind one interface: `sample`, `eval`, `pdf`.

Convention (`docs/conventions.md`): theta is the angle between the direction light travelled before scattering and
the direction it travels after. `E[cos theta] > 0` scatters forward (HG with g > 0).

For a path traced from the camera with current ray direction `d`, the light travels along `-d`; the scattering
angle to a new camera-path direction `w` (light arriving along `-w`) therefore has `cos theta = dot(d, w)`.

The media of jaxfog are isotropic, so a phase function depends on the scattering angle alone: a concrete phase
function implements the three *polar* methods (`sample_polar(u)`, `eval_polar(1 - cos)`, `pdf_polar(1 - cos)`),
and the direction-level `sample` / `eval` / `pdf` follow from them. The tracer uses the polar forms so that every
sampling technique of a bounce shares one direction construction (`_sampling.to_direction`).

Adding a phase function: one final class here (its parameters as array fields, checked in `__check_init__`), one
entry in `_scene_io.PHASES`, and its Mitsuba name in `_mitsuba` (see `notes/ARCHITECTURE.md`).
"""


import abc
from typing import ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from equinox import AbstractClassVar
from jaxtyping import Array, Float

from ._fields import scalar
from ._math import one_minus_cos_between
from ._sampling import (
    Polar,
    draine_pdf,
    draine_sample,
    draine_sampling_pdf,
    hg_pdf,
    hg_sample,
    mixture_sample,
    rayleigh_pdf,
    rayleigh_sample,
    to_direction,
)
from ._validate import DRAINE_ALPHA_RANGE, DROPLET_DIAMETER_RANGE, G_RANGE, UNIT, check_range

__all__ = ["AbstractPhaseFunction", "HenyeyGreenstein", "Rayleigh", "Draine", "TwoTermHG", "Droplet",
           "droplet_parameters", "PhaseSample", "hg_pdf", "hg_sample"]


class PhaseSample(NamedTuple):
    """A sampled direction: `wo` (unit 3-vector), `pdf` (1/sr), `weight = eval / pdf` (1 where sampling is exact)
    and `one_minus_cos` of the scattering angle."""

    wo: Float[Array, "3"]
    pdf: Float[Array, ""]
    weight: Float[Array, ""]
    one_minus_cos: Float[Array, ""]


class AbstractPhaseFunction(eqx.Module):
    """A phase function of an isotropic medium: a density over directions (1/sr) that integrates to 1.

    Concrete subclasses implement the polar methods and say whether `sample_polar` draws exactly from the phase
    function (`sampled_exactly`: `eval_polar == pdf_polar`, so a sample's weight is 1); `sample`, `eval` and `pdf`
    are shared and never overridden.
    """

    sampled_exactly: AbstractClassVar[bool]
    sharp_forward_peak: ClassVar[bool] = False
    """Whether the light-angle lobe should, by default, draw part of its directions from this phase function about
    the direction to the light (`SamplingOptions.phase_lobe`): True for a peak too sharp for the lobe's angle
    profile (the fog droplets), False (the default images unchanged) for the others."""

    @abc.abstractmethod
    def sample_polar(self, u: Float[Array, ""]) -> Polar:
        """The scattering angle's `(1 - cos, 1 + cos)` for u uniform in [0, 1), drawn with density `pdf_polar`."""

    @abc.abstractmethod
    def eval_polar(self, one_minus_cos: Float[Array, ""]) -> Float[Array, ""]:
        """Phase function value (1/sr) at the scattering angle given by `1 - cos theta` in [0, 2]."""

    @abc.abstractmethod
    def pdf_polar(self, one_minus_cos: Float[Array, ""]) -> Float[Array, ""]:
        """Solid-angle density (1/sr) with which `sample_polar` (and a uniform azimuth) produces that angle."""

    def sample(self, d: Float[Array, "3"], u: Float[Array, "2"]) -> PhaseSample:
        """A new camera-path direction for a path travelling along unit `d`; `u[0]` polar, `u[1]` azimuth."""
        polar = self.sample_polar(u[0])
        omc = polar.one_minus_cos
        pdf = self.pdf_polar(omc)
        return PhaseSample(to_direction(polar, u[1], d), pdf, self.eval_polar(omc) / pdf, omc)

    def eval(self, d: Float[Array, "3"], wo: Float[Array, "3"]) -> Float[Array, ""]:
        """Phase value (1/sr) for a camera path going along `d` and continuing along `wo` (unit vectors)."""
        return self.eval_polar(one_minus_cos_between(d, wo))

    def pdf(self, d: Float[Array, "3"], wo: Float[Array, "3"]) -> Float[Array, ""]:
        """Density (1/sr) with which `sample(d, .)` produces `wo`."""
        return self.pdf_polar(one_minus_cos_between(d, wo))


class HenyeyGreenstein(AbstractPhaseFunction):
    """Henyey–Greenstein phase function with asymmetry `g` = E[cos theta] in (-1, 1) (traced; g > 0 forward).

    Sampled exactly (`eval == pdf`) with the cancellation-free inverse cdf of `_sampling.hg_sample`; differentiable
    in `g` in value and in the sampled direction (the reparameterized HG sample).
    """

    g: Float[Array, ""] = eqx.field(converter=scalar)
    sampled_exactly: ClassVar[bool] = True

    def __check_init__(self):
        check_range("HenyeyGreenstein", "g", self.g, G_RANGE)

    def sample_polar(self, u):
        return Polar(*hg_sample(u, self.g))

    def eval_polar(self, one_minus_cos):
        return hg_pdf(one_minus_cos, self.g)

    def pdf_polar(self, one_minus_cos):
        return hg_pdf(one_minus_cos, self.g)


class Rayleigh(AbstractPhaseFunction):
    """Rayleigh phase function `3 (1 + cos^2 theta) / (16 pi)` (scattering by particles much smaller than the
    wavelength: clear-air haze; Mitsuba `rayleigh`). No parameters; `E[cos] = 0`, `E[cos^2] = 2/5`; sampled exactly
    by solving its cubic (`_sampling.rayleigh_sample`)."""

    sampled_exactly: ClassVar[bool] = True

    def sample_polar(self, u):
        return rayleigh_sample(u)

    def eval_polar(self, one_minus_cos):
        return rayleigh_pdf(one_minus_cos)

    def pdf_polar(self, one_minus_cos):
        return rayleigh_pdf(one_minus_cos)


class Draine(AbstractPhaseFunction):
    """Draine's phase function (Draine 2003) with `g` in (-1, 1) and `alpha` in (0, 1000] (traced): HG times
    `(1 + alpha cos^2) / (1 + alpha (1 + 2 g^2) / 3)`; `(g, alpha) = (0, 1)` is Rayleigh. Sampled by its closed-form
    inverse cdf (`_sampling.draine_sample`); for |g| < 1e-2 that draws from Draine(0, alpha), so `sampled_exactly`
    is False and the weight `eval / pdf` (1 + O(g)) keeps the estimate exact."""

    g: Float[Array, ""] = eqx.field(converter=scalar)
    alpha: Float[Array, ""] = eqx.field(converter=scalar)
    sampled_exactly: ClassVar[bool] = False

    def __check_init__(self):
        check_range("Draine", "g", self.g, G_RANGE)
        check_range("Draine", "alpha", self.alpha, DRAINE_ALPHA_RANGE)

    def sample_polar(self, u):
        return draine_sample(u, self.g, self.alpha)

    def eval_polar(self, one_minus_cos):
        return draine_pdf(one_minus_cos, self.g, self.alpha)

    def pdf_polar(self, one_minus_cos):
        return draine_sampling_pdf(one_minus_cos, self.g, self.alpha)


class TwoTermHG(AbstractPhaseFunction):
    """Two-term Henyey–Greenstein `w HG(g1) + (1 - w) HG(g2)` (a forward and a backward lobe, e.g. g1 = 0.8,
    g2 = -0.4, w = 0.7; Mitsuba `blendphase` of two `hg`, weight `1 - w` on the first). `g1`, `g2` in (-1, 1),
    `w` in [0, 1], all traced. `E[cos] = w g1 + (1 - w) g2`.

    Sampling: the lobe with probability `w` from the polar uniform (`_sampling.split_uniform`), then that lobe's
    exact HG sample. The lobe choice is a discrete decision: its probability is `stop_gradient(w)` in
    `sample_polar` and `pdf_polar`, so a reparameterized sample moves within its lobe (with g1, g2) and never across
    lobes, and the weight `eval / pdf` (value 1) carries the derivative w.r.t. `w`. Hence `sampled_exactly` is
    False: the values of eval and pdf agree, their derivatives do not."""

    g1: Float[Array, ""] = eqx.field(converter=scalar)
    g2: Float[Array, ""] = eqx.field(converter=scalar)
    w: Float[Array, ""] = eqx.field(converter=scalar)
    sampled_exactly: ClassVar[bool] = False

    def __check_init__(self):
        check_range("TwoTermHG", "g1", self.g1, G_RANGE)
        check_range("TwoTermHG", "g2", self.g2, G_RANGE)
        check_range("TwoTermHG", "w", self.w, UNIT)

    def _mix(self, one_minus_cos, w):
        return w * hg_pdf(one_minus_cos, self.g1) + (1.0 - w) * hg_pdf(one_minus_cos, self.g2)

    def sample_polar(self, u):
        return mixture_sample(u, jax.lax.stop_gradient(self.w), lambda v: Polar(*hg_sample(v, self.g1)),
                              lambda v: Polar(*hg_sample(v, self.g2)))

    def eval_polar(self, one_minus_cos):
        return self._mix(one_minus_cos, self.w)

    def pdf_polar(self, one_minus_cos):
        return self._mix(one_minus_cos, jax.lax.stop_gradient(self.w))


DROPLET_PIECES = (0.1, 1.5, 5.0)
"""The fits' range boundaries (µm): d <= 0.1, 0.1 < d < 1.5, 1.5 <= d < 5, 5 <= d <= 50. The parameters are smooth
inside a range and not differentiable (in places not continuous) across a boundary: a fit of `diameter` must stay
inside one range (fitting/params.py keeps it in [5, 50], the fog and cloud droplets)."""


def droplet_parameters(d: Float[Array, ""]) -> tuple[Float[Array, ""], ...]:
    """`(g_HG, g_D, alpha, w_D)` of the fog-droplet phase function for the droplet diameter `d` in µm.

    The closed-form fits of Jendersie & d'Eon, "An Approximate Mie Scattering Function for Fog and Cloud
    Rendering", SIGGRAPH 2023 Talks (supplemental, eqs. 7-22), as in Blender Cycles
    (`intern/cycles/kernel/closure/volume_util.h: phase_mie_fitted_parameters`, blender/blender@23641358; Cycles
    uses fast approximations of exp/log/cos, we use the exact functions). Four ranges:

    - `d <= 0.1` (eqs. 11-14): `g_HG = 13.8 d^2`, `g_D = 1.1456 d sin(9.29044 d)`, `alpha = 250`,
      `w_D = 0.252977 - 312.983 d^4.3`;
    - `0.1 < d < 1.5` (eqs. 15-18, in `l = ln d`): `g_HG = 0.862 - 0.143 l^2`,
      `g_D = 0.379685 cos(1.19692 cos(a / b) + 1.37932 l + 0.0625835) + 0.344213` with
      `a = (l - 0.238604)(l + 1.00667)`, `b = 0.507522 - 0.15677 l`, `alpha = 250`,
      `w_D = 0.146209 cos(3.38707 l + 2.11193) + 0.316072 + 0.0778917 l`;
    - `1.5 <= d < 5` (eqs. 19-22): `g_HG = 0.0604931 ln(l) + 0.940256`,
      `g_D = 0.500411 - 0.081287 / (-2 l + tan(l) + 1.27551)`, `alpha = 7.30354 l + 6.31675`,
      `w_D = 0.026914 (l - cos(5.68947 (ln(l) - 0.0292149))) + 0.3764`;
    - `5 <= d <= 50` (eqs. 7-10): `g_HG = exp(-0.0990567 / (d - 1.67154))`,
      `g_D = exp(-2.20679 / (d + 3.91029) - 0.428934)`, `alpha = exp(3.62489 - 8.29288 / (d + 5.52825))`,
      `w_D = exp(-0.599085 / (d - 0.641583) - 0.665888)`.

    At d = 10: (0.988, 0.556, 22.0, 0.482) (docs/conventions.md, tests/test_phase_mixtures.py). Each range is
    evaluated at `d` clipped into it and one is selected (double where: finite values and gradients everywhere).
    """
    d = jnp.asarray(d, jnp.float32)
    d1 = jnp.clip(d, 0.0, 0.1)
    p1 = (13.8 * d1 * d1, 1.1456 * d1 * jnp.sin(9.29044 * d1), jnp.full_like(d1, 250.0),
          0.252977 - 312.983 * jnp.power(jnp.maximum(d1, 1e-30), 4.3))
    l2 = jnp.log(jnp.clip(d, 0.1, 1.5))
    a = (l2 - 0.238604) * (l2 + 1.00667)
    b = 0.507522 - 0.15677 * l2
    c = 1.19692 * jnp.cos(a / b) + 1.37932 * l2 + 0.0625835
    p2 = (0.862 - 0.143 * l2 * l2, 0.379685 * jnp.cos(c) + 0.344213, jnp.full_like(l2, 250.0),
          0.146209 * jnp.cos(3.38707 * l2 + 2.11193) + 0.316072 + 0.0778917 * l2)
    l3 = jnp.log(jnp.clip(d, 1.5, 5.0))
    ll3 = jnp.log(l3)
    p3 = (0.0604931 * ll3 + 0.940256, 0.500411 - 0.081287 / (-2.0 * l3 + jnp.tan(l3) + 1.27551),
          7.30354 * l3 + 6.31675, 0.026914 * (l3 - jnp.cos(5.68947 * (ll3 - 0.0292149))) + 0.3764)
    d4 = jnp.clip(d, 5.0, 50.0)
    p4 = (jnp.exp(-0.0990567 / (d4 - 1.67154)), jnp.exp(-2.20679 / (d4 + 3.91029) - 0.428934),
          jnp.exp(3.62489 - 8.29288 / (d4 + 5.52825)), jnp.exp(-0.599085 / (d4 - 0.641583) - 0.665888))
    r1, r2, r3 = d <= 0.1, d < 1.5, d < 5.0
    return tuple(jnp.where(r1, x1, jnp.where(r2, x2, jnp.where(r3, x3, x4))) for x1, x2, x3, x4 in zip(p1, p2, p3, p4))


class Droplet(AbstractPhaseFunction):
    """The fog-droplet phase function of Jendersie & d'Eon (2023): `(1 - w_D) HG(g_HG) + w_D Draine(g_D, alpha)`,
    its four parameters closed-form fits in the droplet `diameter` (µm, traced, in (0, 50]; `droplet_parameters`).
    Large droplets (d >= 5) have a very sharp forward peak (g_HG = 0.988 at 10 µm) and a broad Draine lobe that
    makes the backward glory HG lacks (the model behind Blender Cycles' "Mie" phase function).

    Sampling: the Draine lobe with probability `w_D` (detached, as `TwoTermHG`'s `w`) from the polar uniform, then
    that lobe's exact inverse cdf; `sampled_exactly` is False (the weight carries d/d(diameter) through `w_D`)."""

    diameter: Float[Array, ""] = eqx.field(converter=scalar)
    sampled_exactly: ClassVar[bool] = False
    sharp_forward_peak: ClassVar[bool] = True

    def __check_init__(self):
        check_range("Droplet", "diameter", self.diameter, DROPLET_DIAMETER_RANGE)

    @property
    def parameters(self) -> tuple[Float[Array, ""], ...]:
        """`(g_HG, g_D, alpha, w_D)` at this diameter."""
        return droplet_parameters(self.diameter)

    def _mix(self, one_minus_cos, detach_w: bool, draine):
        g_hg, g_d, alpha, w_d = self.parameters
        if detach_w:
            w_d = jax.lax.stop_gradient(w_d)
        return (1.0 - w_d) * hg_pdf(one_minus_cos, g_hg) + w_d * draine(one_minus_cos, g_d, alpha)

    def sample_polar(self, u):
        g_hg, g_d, alpha, w_d = self.parameters
        return mixture_sample(u, jax.lax.stop_gradient(w_d), lambda v: draine_sample(v, g_d, alpha),
                              lambda v: Polar(*hg_sample(v, g_hg)))

    def eval_polar(self, one_minus_cos):
        return self._mix(one_minus_cos, False, draine_pdf)

    def pdf_polar(self, one_minus_cos):
        return self._mix(one_minus_cos, True, draine_sampling_pdf)
