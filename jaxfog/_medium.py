"""Homogeneous participating medium: the Module, and the pure free-flight sampling math.

Free-flight sampling in jaxfog is one formula for every gradient estimator (`docs/estimators.md`). A segment of length
`s` (to the next surface, or to the medium's `extent` for a ray that escapes) is split into two branches chosen with a
probability `q` that never carries a derivative:

- medium branch (probability `q`): `t = -log(1 - x (1 - exp(-sh s))) / sh` with `x = u / q` uniform in [0, 1), the
  truncated exponential on [0, s] with rate `sh` (the *sampling* extinction); the path weight is
  `sigma_s exp(-sigma_t t) / pdf(t)`, `pdf(t) = q sh exp(-sh t) / (1 - exp(-sh s))`;
- surface branch (probability `1 - q`): weight `exp(-sigma_t s) / (1 - q)`.

With `q = 1 - exp(-sh s)` this *is* ordinary free-flight sampling `t = -log(1 - u) / sh`. The three estimators differ
only in `sh`: `stop_gradient(sigma_t)` ("detached"), a caller's fixed reference ("proposal"), or `sigma_t` itself
("reparam": `t` then moves with `sigma_t`, and the branch, decided by `u < q` with a detached `q`, does not jump).
`q` is floored at `Q_MIN` so that very thin fog (even `sigma_t = 0`) still samples medium vertices that carry the
derivative with respect to `sigma_t`.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._math import finite_or, one_minus_exp_neg
from ._phase import HenyeyGreenstein

Q_MIN = 0.05
"""Smallest probability of choosing the medium branch on a segment (no derivative; a variance/cost trade-off)."""

Q_MAX_SURFACE = 0.75
"""Largest probability of the medium branch on a segment that ends on a surface (variance trade-off, no bias)."""

SIGMA_HAT_MIN = 1e-6
"""Smallest sampling extinction (1/scene unit); below it the truncated exponential is uniform on [0, s] anyway."""


def _rgb(x) -> Float[Array, "3"]:
    x = jnp.asarray(x, dtype=jnp.float32)
    return jnp.broadcast_to(x, (3,)) if x.ndim == 0 else x


class HomogeneousMedium(eqx.Module):
    """One homogeneous medium filling all space outside the objects (the camera is inside it).

    **Fields:**
    - `sigma_t`: extinction coefficient, RGB, in 1/scene unit, >= 0 (0 means no fog). A scalar sets all channels.
    - `albedo`: single-scattering albedo `sigma_s / sigma_t`, RGB, in [0, 1].
    - `phase`: the phase function (Henyey–Greenstein, `g` in (-1, 1), g > 0 forward).
    - `extent`: static; a ray that travels this far (scene units) without meeting a surface leaves the fog.
      Default 1000: light scattered beyond it is below `sigma_s * I / extent` and negligible for the shipped scenes.
    """

    sigma_t: Float[Array, "3"] = eqx.field(converter=_rgb)
    albedo: Float[Array, "3"] = eqx.field(converter=_rgb)
    phase: HenyeyGreenstein
    extent: float = eqx.field(static=True, default=1000.0)

    @property
    def sigma_s(self) -> Float[Array, "3"]:
        """Scattering coefficient `albedo * sigma_t`, RGB, 1/scene unit."""
        return self.albedo * self.sigma_t

    @property
    def g(self) -> Float[Array, ""]:
        return self.phase.g


def sampling_extinction(sigma_t: Float[Array, "3"]) -> Float[Array, ""]:
    """The scalar rate used to sample distances for an RGB medium: the smallest channel, floored at SIGMA_HAT_MIN.

    The smallest channel keeps every channel's weight ratio `exp(-(sigma_c - sh) t)` at most 1 (bounded variance).
    """
    return jnp.maximum(jnp.min(sigma_t), SIGMA_HAT_MIN)


def branch_probability(
    sh: Float[Array, ""], s: Float[Array, ""], q_max: float | Float[Array, ""] = 1.0
) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """Probability `q` of the medium branch on a segment of finite length `s`, and `log(1 - q)`; never differentiated.

    `q = clip(1 - exp(-sh s), Q_MIN, q_max)`. The integrator passes `q_max = Q_MAX_SURFACE` when the segment ends
    on a surface, so that a surface behind optically thick fog is still reached by a fixed share of the paths (with
    weight `exp(-sigma_t s) / (1 - q) < 1`) instead of by a rare, heavy one. `log(1 - q)` is exact (`-sh s`) where
    no clamp is active, so surface weights `exp(-sigma_t s) / (1 - q)` never underflow to 0/0 in deep fog.
    """
    sh = jax.lax.stop_gradient(sh)
    m = one_minus_exp_neg(sh * s)
    floored = m < Q_MIN
    capped = m > q_max
    q = jnp.where(floored, Q_MIN, jnp.where(capped, q_max, m))
    log_one_minus_q = jnp.where(floored, jnp.log1p(-Q_MIN), jnp.where(capped, jnp.log1p(-q_max), -sh * s))
    return q, log_one_minus_q


def sample_truncated_exponential(
    x: Float[Array, ""], sh: Float[Array, ""], s: Float[Array, ""]
) -> Float[Array, ""]:
    """`t` in [0, s) from the exponential with rate `sh` > 0 truncated to [0, s]; `x` uniform in [0, 1).

    `t = -log1p(-x (1 - exp(-sh s))) / sh`, differentiable in `sh` (the reparameterized free flight).
    """
    m = one_minus_exp_neg(sh * s)
    return -jnp.log1p(-x * m) / sh


def medium_pdf(t, sh, s, q) -> Float[Array, ""]:
    """Density of sampling a medium vertex at `t` on the segment (1/scene unit): `q sh exp(-sh t) / (1 - exp(-sh s))`."""
    return q * sh * jnp.exp(-sh * t) / one_minus_exp_neg(sh * s)


def medium_weight(sigma_t, sigma_s, sh, t, s, q) -> Float[Array, "3"]:
    """Path weight of a medium vertex at `t`: `sigma_s exp(-sigma_t t) / medium_pdf(t)`, RGB, computed without underflow."""
    return sigma_s / sh * jnp.exp(-(sigma_t - sh) * t) * (one_minus_exp_neg(sh * s) / q)


def surface_weight(sigma_t, s, log_one_minus_q) -> Float[Array, "3"]:
    """Path weight of reaching the surface at finite `s`: `exp(-sigma_t s) / (1 - q)`, RGB, as one exponential."""
    return jnp.exp(-sigma_t * s - log_one_minus_q)


def transmittance(sigma_t: Float[Array, "3"], d: Float[Array, ""]) -> Float[Array, "3"]:
    """Beer–Lambert transmittance `exp(-sigma_t d)` over a distance `d` >= 0 (may be inf: 0 where sigma_t > 0, 1 where
    sigma_t = 0), RGB; the gradient is finite (zero) at d = inf."""
    fin = jnp.isfinite(d)
    tr = jnp.exp(-sigma_t * finite_or(d, 0.0))
    return jnp.where(fin, tr, jnp.where(sigma_t > 0, 0.0, 1.0))
