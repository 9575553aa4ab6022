"""Exponential height fog: `sigma_t(p) = sigma_0 exp(-(dot(p, up) - h_0) / H)`, with closed-form optical depth and
analytic free-flight sampling (docs/estimators.md, "Height fog").

Along the ray `o + t d` the extinction is `A exp(-k t)` with `log A = log sigma_0 + b`, `b = -(dot(o, up) - h_0) / H`
and `k = dot(d, up) / H`, so the optical depth is

    tau(t) = A t phi(k t),   phi(x) = (1 - exp(-x)) / x   (phi(0) = 1: a horizontal ray sees homogeneous fog),

and `tau(t) = T` inverts to `t = (T / A) psi(k T / A)`, `psi(y) = -log1p(-y) / y`, for `k T / A < 1` (an upward ray
has the finite `tau(inf) = A / k`). Everything is computed from logarithms (`log tau = log sigma_0 + b + log t +
log phi(k t)`): far below `h_0` with a small `H`, `A` overflows float32 long before the transmittance stops being
0, and far above it `A` underflows while the ratios the path weights need stay of order 1.

Free flight uses the homogeneous medium's branch scheme (`_medium.branch_probability`: the medium branch with
probability `q = clip(1 - exp(-tau_hat(s)), Q_MIN, q_max)`, then `t` from the free-flight density truncated to
[0, s]), with the sampler's optical depth `tau_hat` in place of `sh s`. For an RGB `sigma_0` the sampler uses the
smallest channel (`sampling_extinction`); the profile (`H`, `h_0`, `up`) is shared, so every channel's density
ratio `sigma_t^c(t) / sigma_hat(t) = sigma_0^c / sigma_hat_0` is constant along the ray.

`LOG_BIG` bounds every exponent: an optical depth or density above `e^80 ~ 5.5e34` is taken as `e^80` (where
`exp(-e^80)` is exactly 0 in float32, and a weight or pdf that large is finite); see `scaled_exp`.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._fields import rgb, scalar
from ._math import dot, safe_normalize
from ._medium import (
    Q_MAX_SURFACE,
    AbstractMedium,
    FlightSample,
    branch_probability,
    check_phase_and_extent,
    sampling_extinction,
)
from ._phase import AbstractPhaseFunction, HenyeyGreenstein
from ._validate import ANY, HEIGHT_SCALE_RANGE, NON_NEGATIVE, UNIT, check_range, check_vector

LOG_BIG = 80.0
"""Largest exponent used (densities, optical depths, pdfs <= e^80 ~ 5.5e34: finite in float32 with room for a
product with weights up to ~1e3; exp(-e^80) is exactly 0)."""

SMALL_X = 1e-3
"""Below this |y| `log_distance_to_depth` uses the series of psi (truncation error < y^3 / 4 ~ 3e-10)."""

SERIES_PHI = 0.1
"""Below this |x| `log_phi` uses its series through x^6 (truncation x^8 / 9.7e6 ~ 1e-15): the closed form's
gradient cancels in float32 near 0 (3e-4 absolute just above x = 1e-3)."""

SERIES_PSI = 0.1
"""Below this y `log_psi` uses its series through y^6 (truncation ~0.04 y^7 ~ 4e-9, gradient ~3e-7)."""


# ---------------------------------------------------------------------------------------------- safe helpers
def log_phi(x: Float[Array, "..."]) -> Float[Array, "..."]:
    """`log phi(x)`, `phi(x) = (1 - exp(-x)) / x = -expm1(-x) / x`, for every finite x (phi(0) = 1).

    `log phi(x) = max(-x, 0) + log(1 - exp(-|x|)) - log|x|`: no overflow for x -> -inf (where phi ~ e^|x| / |x|),
    no cancellation for x -> +inf; the series `-x/2 + x^2/24 - x^4/2880 + x^6/181440` for |x| < SERIES_PHI
    (double where: finite, accurate gradient at and near x = 0)."""
    ax = jnp.abs(x)
    small = ax < SERIES_PHI
    axs = jnp.where(small, 1.0, ax)
    big = jnp.maximum(-x, 0.0) + jnp.log(-jnp.expm1(-axs)) - jnp.log(axs)
    xs = jnp.where(small, x, 0.0)
    x2 = xs * xs
    return jnp.where(small, -0.5 * xs + x2 * (1.0 / 24.0 - x2 * (1.0 / 2880.0 - x2 / 181440.0)), big)


def log_psi(y: Float[Array, "..."]) -> Float[Array, "..."]:
    """`log psi(y)`, `psi(y) = -log1p(-y) / y`, for y in [0, 1) (psi(0) = 1); below SERIES_PSI its series
    `y/2 + 5y^2/24 + y^3/8 + 251y^4/2880 + 19y^5/288 + 19087y^6/362880` (double where)."""
    small = y < SERIES_PSI
    ys = jnp.where(small, 0.5, y)
    big = jnp.log(-jnp.log1p(-ys)) - jnp.log(ys)
    y0 = jnp.where(small, y, 0.0)
    ser = y0 * (0.5 + y0 * (5.0 / 24.0 + y0 * (1.0 / 8.0 + y0 * (251.0 / 2880.0 + y0 * (19.0 / 288.0
                                                                                     + y0 * 19087.0 / 362880.0)))))
    return jnp.where(small, ser, big)


def log_one_minus_exp_neg_exp(L: Float[Array, "..."]) -> Float[Array, "..."]:
    """`log(1 - exp(-tau))` from `L = log tau` (L in [-inf, LOG_BIG]): `L + log phi(e^L)`, exact for tiny tau
    (where `1 - exp(-tau)` underflows to 0), 0 for large tau."""
    Lc = jnp.minimum(L, LOG_BIG)  # log(1 - exp(-e^80)) is exactly 0
    return Lc + log_phi(jnp.exp(Lc))


def scaled_exp(c: Float[Array, "..."], L: Float[Array, "..."]) -> Float[Array, "..."]:
    """`c exp(L)` for `c >= 0`, as `exp(min(log c + L, LOG_BIG))` (no overflow of `exp(L)` when `c` is small).

    At c = 0 the value is 0 and its gradient w.r.t. `c` is `exp(min(L, LOG_BIG))` (double where: the log form
    would give 0 * inf); at `L = -inf` the value and gradient are 0."""
    pos = c > 0
    log_c = jnp.log(jnp.where(pos, c, 1.0))
    fin = L > -jnp.inf
    Ls = jnp.where(fin, L, 0.0)
    v_pos = jnp.exp(jnp.minimum(log_c + Ls, LOG_BIG))
    v_zero = c * jnp.exp(jnp.minimum(Ls, LOG_BIG))
    return jnp.where(fin, jnp.where(pos, v_pos, v_zero), 0.0)


def log_depth_factor(k: Float[Array, ""], t: Float[Array, "..."]) -> Float[Array, "..."]:
    """`log(t phi(k t))` for t >= 0 finite (-inf at t = 0, zero gradient there): the optical depth over [0, t] is
    `A exp(this)`."""
    pos = t > 0
    ts = jnp.where(pos, t, 1.0)
    return jnp.where(pos, jnp.log(ts) + log_phi(k * ts), -jnp.inf)


def log_distance_to_depth(log_T: Float[Array, ""], log_A: Float[Array, ""], k: Float[Array, ""]) -> Float[Array, ""]:
    """The distance `t` at which the optical depth `A t phi(k t)` reaches `T`, from `log T` and `log A`:
    `t = (T / A) psi(k T / A)`; +inf where `k > 0` and `T >= A / k` (the ray escapes first); 0 at T = 0.

    With `y = k T / A` and `log|y| = log|k| + log T - log A` (no overflow however small A is):
    |y| < SMALL_X: `t = (T/A)(1 + y/2 + y^2/3)`; y < 0: `t = log(1 + |y|) / |k|` (softplus of log|y|);
    0 < y < 1: `t = -log1p(-y) / k`. Each branch's input is made safe before use (double where)."""
    nonzero_T = log_T > -jnp.inf
    log_r = jnp.where(nonzero_T, log_T - log_A, 0.0)
    ak = jnp.abs(k)
    kpos = ak > 0
    log_ak = jnp.log(jnp.where(kpos, ak, 1.0))
    log_ay = jnp.where(kpos, log_ak + log_r, -jnp.inf)
    small = log_ay < jnp.log(SMALL_X)
    # small |y|: the homogeneous-like series (T / A is then at most ~ the segment length: no overflow)
    y_small = jnp.where(small, jnp.sign(k) * jnp.exp(jnp.where(small, log_ay, 0.0)), 0.0)
    t_small = jnp.exp(jnp.minimum(jnp.where(small, log_r, 0.0), LOG_BIG)) * (1.0 + 0.5 * y_small
                                                                            + y_small * y_small / 3.0)
    la = jnp.where(small, 0.0, log_ay)
    inv_ak = 1.0 / jnp.where(kpos, ak, 1.0)
    t_down = jnp.logaddexp(0.0, la) * inv_ak
    escapes = ~small & (k > 0) & (la >= 0.0)
    use_up = ~small & (k > 0) & ~escapes  # double where: y = 1 (escape, or the k < 0 branch) gives log1p(-1)
    y_up = jnp.where(use_up, jnp.exp(jnp.where(use_up, la, 0.0)), 0.5)
    t_up = -jnp.log1p(-y_up) * inv_ak
    t = jnp.where(small, t_small, jnp.where(k < 0, t_down, t_up))
    return jnp.where(nonzero_T, jnp.where(escapes, jnp.inf, t), 0.0)


# ---------------------------------------------------------------------------------------------------- the medium
class HeightFog(AbstractMedium):
    """Exponential height fog (`"type": "height"` in scene files).

    **Fields:**
    - `sigma_0`: extinction coefficient at the base height, RGB (a scalar sets all channels), 1/scene unit, >= 0.
    - `height_scale`: `H` in [1e-3, 1e6] (`HEIGHT_SCALE_RANGE`), scene units: the extinction falls by `e` every `H`
      upward; the optical depths are computed stably in that range; `H -> inf` is the homogeneous medium.
    - `base_height`: `h_0`, scene units (default 0): the height (along `up`) where the extinction is `sigma_0`.
      Only `sigma_0 exp(h_0 / H)` enters the image: `sigma_0` and `base_height` cannot be fitted together.
    - `albedo`: single-scattering albedo, RGB in [0, 1] (constant: `sigma_s = albedo sigma_t`).
    - `phase`: the phase function (any `AbstractPhaseFunction`).
    - `up`: unit vector of increasing height (default +y), normalized on construction.
    - `extent`: static; rays that meet no surface are followed this far (default 1000, as `HomogeneousMedium`).
      Shadow rays to a directional light go to infinity (`tau(inf) = A / k` upward, inf otherwise).
    """

    sigma_0: Float[Array, "3"] = eqx.field(converter=rgb)
    height_scale: Float[Array, ""] = eqx.field(converter=scalar)
    albedo: Float[Array, "3"] = eqx.field(converter=rgb)
    phase: AbstractPhaseFunction
    base_height: Float[Array, ""] = eqx.field(converter=scalar, default=0.0)
    up: Float[Array, "3"] = eqx.field(converter=lambda v: safe_normalize(jnp.asarray(v, jnp.float32).reshape(3)),
                                      default=(0.0, 1.0, 0.0))
    extent: float = eqx.field(static=True, default=1000.0)
    bounds: ClassVar[None] = None
    """Height fog fills space (no box)."""

    def __check_init__(self):
        check_range("HeightFog", "sigma_0", self.sigma_0, NON_NEGATIVE)
        check_range("HeightFog", "height_scale", self.height_scale, HEIGHT_SCALE_RANGE)
        check_range("HeightFog", "base_height", self.base_height, ANY)
        check_range("HeightFog", "albedo", self.albedo, UNIT)
        check_vector("HeightFog", "up", self.up)
        check_phase_and_extent("HeightFog", self.phase, self.extent)

    def supports_estimator(self, estimator: str) -> bool:
        return True

    def fog_interval(self, o, d, s):
        return 0.0, s

    @property
    def g(self) -> Float[Array, ""]:
        """The Henyey–Greenstein `g` of the phase function (AttributeError for other phase functions)."""
        if not isinstance(self.phase, HenyeyGreenstein):
            raise AttributeError(f"the medium's phase function is {type(self.phase).__name__}, which has no g")
        return self.phase.g

    # ------------------------------------------------------------------------------------- the ray's profile
    def line(self, o, d) -> tuple[Float[Array, ""], Float[Array, ""]]:
        """`(b, k)`: along `o + t d` the extinction is `sigma_0 exp(b - k t)`, `b = -(dot(o, up) - h_0) / H`,
        `k = dot(d, up) / H`."""
        inv_h = 1.0 / self.height_scale
        return -(dot(o, self.up) - self.base_height) * inv_h, dot(d, self.up) * inv_h

    def optical_depth(self, o, d, t) -> Float[Array, "3"]:
        """`tau_c` over `[0, t]` along the ray, RGB; t in [0, inf] (inf: `A / k` upward, else inf where sigma_0 > 0)."""
        b, k = self.line(o, d)
        fin = jnp.isfinite(t)
        tf = jnp.where(fin, t, 1.0)
        tau_fin = scaled_exp(self.sigma_0, b + log_depth_factor(k, tf))
        up = k > 0
        log_k = jnp.log(jnp.where(up, k, 1.0))
        tau_inf = jnp.where(up, scaled_exp(self.sigma_0, b - log_k), jnp.where(self.sigma_0 > 0, jnp.inf, 0.0))
        return jnp.where(fin, tau_fin, tau_inf)

    def _sampling_log_line(self, o, d):
        """`(log A_hat, k)` of the sampling extinction `sigma_hat_0 exp(b - k t)` (smallest channel of sigma_0)."""
        b, k = self.line(o, d)
        return jnp.log(sampling_extinction(self.sigma_0)) + b, k

    # ---------------------------------------------------------------------------------------- free flight
    def sample_free_flight(self, o, d, s, ends_on_surface, active, u, u_channel=None) -> FlightSample:
        # RGB sigma_0 is sampled with its smallest channel (one rate for all channels): `u_channel` is not used
        log_A, k = self._sampling_log_line(o, d)
        L_s = log_A + log_depth_factor(k, s)  # log tau_hat(s)
        q, log1mq = branch_probability(jnp.exp(jnp.minimum(L_s, LOG_BIG)), jnp.float32(1.0),
                                       jnp.where(ends_on_surface, Q_MAX_SURFACE, 1.0))
        q = jnp.where(active, q, 0.0)
        scattered = active & (u < q)
        x = jnp.where(scattered, jnp.minimum(u / jnp.where(scattered, q, 1.0), 0.99999994), 0.0)
        # T = -log1p(-x m), m = 1 - exp(-tau_hat(s)), from logarithms: log T = log(x m) + log psi(x m)
        xpos = x > 0
        log_xm = jnp.where(xpos, jnp.log(jnp.where(xpos, x, 1.0)) + log_one_minus_exp_neg_exp(L_s), -jnp.inf)
        xm = jnp.minimum(jnp.exp(log_xm), 0.99999994)
        log_T = jnp.where(xpos, log_xm + log_psi(xm), -jnp.inf)
        t = log_distance_to_depth(log_T, log_A, k)
        t = jnp.clip(jnp.where(jnp.isfinite(t), t, s), 0.0, s)  # T < tau_hat(s): t < s up to rounding
        return FlightSample(t, scattered, q, log1mq)

    def free_flight_pdf(self, o, d, s, q, t):
        """`q sigma_hat(t) exp(-tau_hat(t)) / (1 - exp(-tau_hat(s)))`, from logarithms."""
        log_A, k = self._sampling_log_line(o, d)
        tau_t = jnp.exp(jnp.minimum(log_A + log_depth_factor(k, t), LOG_BIG))
        log_m = log_one_minus_exp_neg_exp(log_A + log_depth_factor(k, s))
        return q * jnp.exp(jnp.minimum(log_A - k * t - tau_t - log_m, LOG_BIG))

    def collision_weight(self, sampler, o, d, s, q, t):
        """`sigma_s(t) T(t) / sampler.free_flight_pdf(t)` as `albedo (sigma_0 / sigma_hat_0) exp((b - b_hat) -
        (k - k_hat) t) exp(-(tau(t) - tau_hat(t))) m / q`: density and transmittance ratios never underflow."""
        b, k = self.line(o, d)
        bh, kh = sampler.line(o, d)
        sh0 = sampling_extinction(sampler.sigma_0)
        log_Ah = jnp.log(sh0) + bh
        ratio = self.albedo * scaled_exp(self.sigma_0, (b - bh) - (k - kh) * t) / sh0
        tau_t = self.optical_depth(o, d, t)
        tau_hat_t = jnp.exp(jnp.minimum(log_Ah + log_depth_factor(kh, t), LOG_BIG))
        m = jnp.exp(log_one_minus_exp_neg_exp(log_Ah + log_depth_factor(kh, s)))
        return ratio * jnp.exp(jnp.minimum(-(tau_t - tau_hat_t), LOG_BIG)) * (m / q)

    def surface_weight(self, o, d, s, log_one_minus_q):
        return jnp.exp(jnp.minimum(-self.optical_depth(o, d, s) - log_one_minus_q, LOG_BIG))

    def transmittance(self, o, d, t):
        """`exp(-tau(t))`, RGB; t may be inf (upward: `exp(-A / k)`; otherwise 0, or 1 where sigma_0 = 0)."""
        tau = self.optical_depth(o, d, t)
        fin = jnp.isfinite(tau)
        return jnp.where(fin, jnp.exp(-jnp.where(fin, tau, 0.0)), 0.0)

    def extinction(self, p) -> Float[Array, "3"]:
        """`sigma_t(p)`, RGB, 1/scene unit (capped at e^LOG_BIG)."""
        return scaled_exp(self.sigma_0, -(dot(p, self.up) - self.base_height) / self.height_scale)

    def scattering(self, p):
        return self.albedo * self.extinction(p)

