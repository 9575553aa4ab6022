"""Henyey–Greenstein phase function: pure sampling and evaluation, and the Module the integrator uses.

Convention (`docs/conventions.md`): theta is the angle between the direction light travelled before scattering and the
direction it travels after. `g > 0` scatters forward, `E[cos theta] = g`, valid range `-1 < g < 1`.

For a path traced from the camera with current ray direction `d`, the light travels along `-d`; the scattering
angle to a new camera-path direction `w` (light arriving along `-w`) therefore has `cos theta = dot(d, w)`.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._math import INV_4PI, PI, direction_from_cos, one_minus_cos_between


def hg_sample(u: Float[Array, ""], g: Float[Array, ""]) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """Inverse-CDF sample of the HG scattering angle, cancellation-free, with no division by g and no branch.

    **Arguments:** `u` uniform in [0, 1); `g` in (-1, 1).

    **Returns:** `(1 - cos theta, 1 + cos theta)`, each in [0, 2], accurate in float32 for every g in (-1, 1)
    (including g = 0 and |g| -> 1). With `a = 1 - g`, `b = 1 + g`, `v = 1 - u`, `d = a v + b u`:
    `1 - cos = 2 a^2 v (v + b u) / d^2`, `1 + cos = 2 b^2 u (a v + u) / d^2`.
    Differentiable in `g` (the reparameterized HG sample).
    """
    a = 1.0 - g
    b = 1.0 + g
    v = 1.0 - u
    d = a * v + b * u
    inv_d2 = 1.0 / (d * d)
    one_minus_cos = 2.0 * a * a * v * (v + b * u) * inv_d2
    one_plus_cos = 2.0 * b * b * u * (a * v + u) * inv_d2
    return jnp.clip(one_minus_cos, 0.0, 2.0), jnp.clip(one_plus_cos, 0.0, 2.0)


def hg_pdf(one_minus_cos: Float[Array, ""], g: Float[Array, ""]) -> Float[Array, ""]:
    """HG phase function value (= its pdf over solid angle, 1/sr), from `1 - cos theta` in [0, 2] and g in (-1, 1).

    `p = (1 - g)(1 + g) / (4 pi ((1 - g)^2 + 2 g (1 - cos))^(3/2))`: no cancellation near the forward peak. For
    g < 0 the same denominator is written `(1 + g)^2 - 2 g (1 + cos)` (a sum of two terms >= 0): the first form
    cancels at the backward peak and rounds to <= 0 for g -> -1 (NaN from the square root, e.g. g = -0.999).
    """
    one_plus_cos = jnp.maximum(2.0 - one_minus_cos, 0.0)
    denom = jnp.where(g >= 0, (1.0 - g) ** 2 + 2.0 * g * one_minus_cos, (1.0 + g) ** 2 - 2.0 * g * one_plus_cos)
    return (1.0 - g) * (1.0 + g) * INV_4PI / (denom * jnp.sqrt(denom))


class PhaseSample(eqx.Module):
    """A sampled direction: `wo` (unit 3-vector), `pdf` (1/sr) and `one_minus_cos` of the scattering angle."""

    wo: Float[Array, "3"]
    pdf: Float[Array, ""]
    one_minus_cos: Float[Array, ""]


class HenyeyGreenstein(eqx.Module):
    """Henyey–Greenstein phase function with asymmetry `g` in (-1, 1) (traced; g > 0 forward)."""

    g: Float[Array, ""] = eqx.field(converter=lambda x: jnp.asarray(x, dtype=jnp.float32))  # one dtype, never weak

    def sample(self, d: Float[Array, "3"], u: Float[Array, "2"]) -> PhaseSample:
        """Sample a new camera-path direction around the current direction `d`; pdf is the HG value."""
        omc, opc = hg_sample(u[0], self.g)
        wo = direction_from_cos(omc, opc, 2.0 * PI * u[1], d)
        return PhaseSample(wo=wo, pdf=hg_pdf(omc, self.g), one_minus_cos=omc)

    def eval(self, d: Float[Array, "3"], wo: Float[Array, "3"]) -> Float[Array, ""]:
        """Phase value (1/sr) for a camera path going along `d` and continuing along `wo` (both unit vectors)."""
        return hg_pdf(one_minus_cos_between(d, wo), self.g)
