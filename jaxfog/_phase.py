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
from equinox import AbstractClassVar, AbstractVar
from jaxtyping import Array, Float

from ._fields import check_range, scalar
from ._math import one_minus_cos_between
from ._sampling import Polar, hg_pdf, hg_sample, rayleigh_pdf, rayleigh_sample, to_direction

__all__ = ["AbstractPhaseFunction", "HenyeyGreenstein", "Rayleigh", "PhaseSample", "hg_pdf", "hg_sample"]


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
        check_range("HenyeyGreenstein", "g", self.g, -1.0, 1.0, lo_open=True, hi_open=True)

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
