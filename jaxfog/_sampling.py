"""The pure warps of the renderer, each with its pdf: one place for every sampled distribution.

Directions are sampled as a *polar* part `Polar(1 - cos theta, 1 + cos theta)` around an axis (the current
direction for a phase function, the normal for a diffuse surface, the direction to a light for the light-angle lobe)
and a uniform azimuth; `to_direction` turns the two into a unit vector. Carrying `1 - cos` and `1 + cos` keeps both
poles accurate in float32, and lets the tracer build one direction per bounce whichever technique drew it.

Distances: the exponential truncated to a segment (free flight) and Kulla–Fajardo equiangular sampling toward a
point (`docs/estimators.md`). MIS weights: the power and balance heuristics.

Every function is written for one sample (scalars, 3-vectors); `vmap` happens once, in `_render`.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ._math import (
    INV_4PI,
    INV_PI,
    PI,
    atan2,
    direction_from_cos,
    dot,
    one_minus_cos_between,
    one_minus_exp_neg,
    safe_div,
    safe_normalize,
    safe_sqrt,
    sincos,
    tan,
)


class Polar(NamedTuple):
    """The polar angle of a sampled direction around its axis: `1 - cos theta` and `1 + cos theta`, each in [0, 2]."""

    one_minus_cos: Float[Array, ""]
    one_plus_cos: Float[Array, ""]


def to_direction(polar: Polar, u_azimuth: Float[Array, ""], axis: Float[Array, "3"]) -> Float[Array, "3"]:
    """Unit vector at the polar angle `polar` around the unit `axis`, azimuth `2 pi u_azimuth` (u in [0, 1))."""
    return direction_from_cos(polar.one_minus_cos, polar.one_plus_cos, 2.0 * PI * u_azimuth, axis)


# ------------------------------------------------------------------------------------------- uniform on surfaces
def uniform_sphere_polar(u: Float[Array, ""]) -> Polar:
    """Polar angle of a direction uniform over the whole sphere, u in [0, 1): `cos theta = 1 - 2u`, density
    `1 / (4 pi)` over directions (with a uniform azimuth)."""
    return Polar(2.0 * u, 2.0 - 2.0 * u)


def uniform_triangle(u0: Float[Array, ""], u1: Float[Array, ""]) -> tuple[Float[Array, ""], ...]:
    """Barycentric coordinates `(b0, b1, b2)` of a point uniform by area over a triangle, from u0, u1 in [0, 1):
    `b0 = 1 - sqrt(u0)`, `b1 = u1 sqrt(u0)` (the square-root warp; density 1 / area)."""
    su = safe_sqrt(u0)
    b0 = 1.0 - su
    b1 = u1 * su
    return b0, b1, 1.0 - b0 - b1


# --------------------------------------------------------------------------------------------------- cosine lobe
def cosine_sample(u: Float[Array, ""]) -> Polar:
    """Cosine-weighted polar angle around a normal, u in [0, 1): `cos theta = sqrt(1 - u)`, pdf `cos theta / pi`
    over directions (`cosine_pdf`). `1 - cos = u / (1 + cos)` has no cancellation."""
    z = safe_sqrt(1.0 - u)
    return Polar(u / (1.0 + z), 1.0 + z)


def cosine_pdf(cos_theta: Float[Array, ""]) -> Float[Array, ""]:
    """Solid-angle pdf (1/sr) of `cosine_sample`: `max(cos theta, 0) / pi`."""
    return jnp.maximum(cos_theta, 0.0) * INV_PI


# ---------------------------------------------------------------------------------------------- Henyey–Greenstein
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
    The power is `rsqrt(denom)^3`, not `1 / (denom sqrt(denom))`: the derivative of the quotient squares its
    divisor, which underflows to 0 at the peak for 1 - |g| <= 1e-7 (NaN gradients, `tests/test_phase.py`), while
    `rsqrt^5` stays below float32's maximum for every float32 g in (-1, 1). The denominator is floored at 1e-15 (below
    the smallest nonzero `(1 - |g|)^2` in float32, 3.6e-15), so g = +-1 itself gives 0 and finite gradients instead
    of `0 x inf`.
    """
    one_plus_cos = jnp.maximum(2.0 - one_minus_cos, 0.0)
    denom = jnp.where(g >= 0, (1.0 - g) ** 2 + 2.0 * g * one_minus_cos, (1.0 + g) ** 2 - 2.0 * g * one_plus_cos)
    r = jax.lax.rsqrt(jnp.maximum(denom, 1e-15))
    return (1.0 - g) * (1.0 + g) * INV_4PI * (r * r * r)


# --------------------------------------------------------------------------------------------------------- Rayleigh
RAYLEIGH_NORM = 3.0 / (16.0 * PI)


def rayleigh_sample(u: Float[Array, ""]) -> Polar:
    """Exact inverse-CDF sample of the Rayleigh phase function `3 (1 + mu^2) / (16 pi)`, u in [0, 1).

    The cdf in `mu = cos theta` is `(mu^3 + 3 mu + 4) / 8`, so `mu^3 + 3 mu = 2 z` with `z = 2 (2u - 1)`, whose
    single real root is `mu = s - 1/s`, `s = cbrt(z + sqrt(z^2 + 1))` (Cardano). The root is odd in z, so it is
    computed for `|z|` (mu in [0, 1], s >= 1) and mirrored; `1 - mu` near the pole comes from the factorisation
    `4 - (mu^3 + 3 mu) = (1 - mu)(mu^2 + mu + 4)`, i.e. `1 - mu = (4 - 2|z|) / (mu^2 + mu + 4)` with the
    numerator written `8 min(u, 1 - u)` (no rounding of `2u - 1`), instead of from the cancelling `1 - (s - 1/s)`.
    Both halves are accurate to float32 precision at both poles (`tests/test_interfaces.py`).
    """
    z = 2.0 * (2.0 * u - 1.0)
    az = jnp.abs(z)
    s = jnp.cbrt(az + jnp.sqrt(az * az + 1.0))  # >= 1
    mu_pos = s - 1.0 / s  # in [0, 1] for az in [0, 2]: no cancellation there (s >= 1, 1/s <= 1)
    # 1 - mu for the mirrored (forward) root from the cubic itself: mu^3 + 3 mu - 4 = (mu - 1)(mu^2 + mu + 4), so
    # 1 - mu = (4 - 2 az) / (mu^2 + mu + 4), and 4 - 2 az = 8 min(u, 1 - u) without the rounding of 2u - 1:
    # accurate as mu -> 1 (u -> 0 or 1).
    one_minus_pos = 8.0 * jnp.minimum(u, 1.0 - u) / (mu_pos * mu_pos + mu_pos + 4.0)
    one_plus_pos = 1.0 + mu_pos
    fwd = z >= 0
    omc = jnp.where(fwd, one_minus_pos, one_plus_pos)
    opc = jnp.where(fwd, one_plus_pos, one_minus_pos)
    return Polar(jnp.clip(omc, 0.0, 2.0), jnp.clip(opc, 0.0, 2.0))


def rayleigh_pdf(one_minus_cos: Float[Array, ""]) -> Float[Array, ""]:
    """Rayleigh phase function value (= its pdf, 1/sr) from `1 - cos theta` in [0, 2]: `3 (1 + mu^2) / (16 pi)`."""
    mu = 1.0 - one_minus_cos
    return RAYLEIGH_NORM * (1.0 + mu * mu)


# ------------------------------------------------------------------------------------------------ light-angle lobe
def light_lobe_cos(u: Float[Array, ""]) -> Polar:
    """Polar part of the light-angle lobe around the direction to a light: `alpha = pi (1 - sqrt(1 - u))`, u in
    [0, 1), the inverse of the lobe's polar cdf `1 - (1 - alpha / pi)^2` (density `2 (pi - alpha) / pi^2`)."""
    sin_h, cos_h = sincos(0.5 * PI * (1.0 - safe_sqrt(1.0 - u)))
    return Polar(2.0 * sin_h * sin_h, 2.0 * cos_h * cos_h)


def light_lobe_sample(u: Float[Array, "2"], x: Float[Array, "3"], light_pos: Float[Array, "3"]) -> Float[Array, "3"]:
    """Direction from `x` at angle alpha to the direction toward `light_pos`, with density `2 (pi - alpha) / pi^2`
    in alpha (u[0]) and uniform in azimuth (phi = 2 pi u[1])."""
    return to_direction(light_lobe_cos(u[0]), u[1], safe_normalize(light_pos - x))


def light_lobe_pdf(w: Float[Array, "3"], x: Float[Array, "3"], light_pos: Float[Array, "3"],
                   once: Callable = lambda x: x) -> Float[Array, ""]:
    """Solid-angle pdf of `light_lobe_sample`: `(pi - alpha) / (pi^3 sin alpha)` (1/sr; its limit 1/pi^3 at
    alpha = pi; 0 at exactly alpha = 0, where it is infinite, a direction the sampler produces with probability 0).

    It is the angular profile of the light a point light sends into a line: a ray from `x` leaving at angle alpha
    to the light passes it at `D = r sin alpha` and, unattenuated and isotropically scattered, collects light
    `(pi - alpha) / D` (the angle the ray subtends at the light over D). So the lobe cancels the `1/D` of the light
    scattered along a segment passing near a point light (docs/estimators.md), for any direction the mixture
    produces. `once(x)` returns `x` unchanged (a caller's fusion barrier: the angle's cosine, a reduction over the
    vector components, is then computed apart from the scalar arithmetic after it; speed only)."""
    a = safe_normalize(light_pos - x)
    omc = once(one_minus_cos_between(w, a))
    sin_a = safe_sqrt(omc * jnp.maximum(2.0 - omc, 0.0))
    beta = atan2(sin_a, omc - 1.0)  # pi - alpha, accurate near alpha = pi
    # double where: beta / sin(beta) -> 1 at beta = 0 (alpha = pi); beta = pi with sin_a = 0 (alpha = 0) gives 0
    ok = sin_a > 0
    ratio = jnp.where(ok, beta / jnp.where(ok, sin_a, 1.0), jnp.where(beta < 1.0, 1.0, 0.0))
    return ratio / PI**3


# ------------------------------------------------------------------------------------------ truncated exponential
def sample_truncated_exponential(
    x: Float[Array, ""], rate: Float[Array, ""], s: Float[Array, ""]
) -> Float[Array, ""]:
    """`t` in [0, s) from the exponential with `rate` > 0 (1/scene unit) truncated to [0, s]; `x` uniform in [0, 1).

    `t = -log1p(-x (1 - exp(-rate s))) / rate`, differentiable in `rate` (the reparameterized free flight).
    """
    m = one_minus_exp_neg(rate * s)
    return -jnp.log1p(-x * m) / rate


def truncated_exponential_pdf(t, rate, s) -> Float[Array, ""]:
    """Density (1/scene unit) of `sample_truncated_exponential` at `t` in [0, s]: `rate exp(-rate t) / (1 - exp(-rate s))`."""
    return rate * jnp.exp(-rate * t) / one_minus_exp_neg(rate * s)


# ------------------------------------------------------------------------------------------------------ equiangular
HALF_PI_BELOW = 1.5707962
"""The largest float32 below pi/2: float32(pi/2) is above pi/2, where tan flips sign."""


TAN_HALF_PI_BELOW = 13245400.0
"""tan(HALF_PI_BELOW), rounded down to a float32: the largest `(t - delta) / D` the clipped angles reach."""


class Equiangular(NamedTuple):
    """Kulla–Fajardo equiangular sampling of `t` in `[ta, tb]` along a ray toward a point `c`: `delta = dot(c - o, d)`
    (the ray parameter of the closest approach), `D` its distance (floored at 1e-7), the angles `theta_a`, `theta_b`
    of the interval's ends seen from `c`, `valid` (a non-empty interval), and the interval's ends `t_a`, `t_b` as
    the clipped angles reach them (scene units; `equiangular_pdf` compares distances, not angles)."""

    delta: Float[Array, ""]
    D: Float[Array, ""]
    theta_a: Float[Array, ""]
    theta_b: Float[Array, ""]
    valid: Bool[Array, ""]
    t_a: Float[Array, ""]
    t_b: Float[Array, ""]


def equiangular_setup(c, o, d, ta, tb, once: Callable = lambda x: x) -> Equiangular:
    """The equiangular sampler of `t` in `[ta, tb]` (scene units) on the ray `o + t d` (unit `d`) toward the point `c`.

    `once(x)` returns the pytree `x` unchanged; the tracer passes its fusion barrier, which makes XLA compute the
    two arctangents once, not inside every value that reads them (speed only)."""
    delta = dot(c - o, d)
    v = c - o - delta * d
    D = jnp.maximum(safe_sqrt(dot(v, v)), 1e-7)
    valid = tb > ta
    ta = jnp.where(valid, ta, 0.0)
    tb = jnp.where(valid, tb, 1.0)
    th_a, th_b = once((jnp.clip(atan2(ta - delta, D), -HALF_PI_BELOW, HALF_PI_BELOW),
                       jnp.clip(atan2(tb - delta, D), -HALF_PI_BELOW, HALF_PI_BELOW)))
    # the ends the clipped angles reach: [ta, tb] itself unless an end is beyond tan(HALF_PI_BELOW) D of delta
    reach = TAN_HALF_PI_BELOW * D
    t_a = jnp.maximum(ta, delta - reach)
    t_b = jnp.minimum(tb, delta + reach)
    return Equiangular(delta, D, th_a, th_b, valid & (th_b > th_a), t_a, t_b)


def equiangular_sample(eq: Equiangular, u: Float[Array, ""], s: Float[Array, ""]) -> Float[Array, ""]:
    """`t = delta + D tan(theta)`, theta uniform in `[theta_a, theta_b]` (u in [0, 1)); clipped to `[0, s]`, 0 if
    the interval is empty."""
    th = eq.theta_a + u * (eq.theta_b - eq.theta_a)
    return jnp.clip(jnp.where(eq.valid, eq.delta + eq.D * tan(th), 0.0), 0.0, s)


EQUIANGULAR_ANGLE_TOL = 1e-6
"""Angle (radians) by which `equiangular_pdf` widens the sampled interval at each end, so that a sample whose
`delta + D tan(theta)` rounds just outside `[t_a, t_b]` keeps its density."""


def equiangular_pdf(eq: Equiangular, t: Float[Array, ""]) -> Float[Array, ""]:
    """Density (1/scene unit) of `equiangular_sample` at `t`: `D / ((theta_b - theta_a) (D^2 + (t - delta)^2))`
    inside the interval, else 0.

    The interval test compares distances: `t` in `[t_a - e, t_b + e]` with `e = EQUIANGULAR_ANGLE_TOL (D^2 + r^2) /
    D`, the distance an angle step of `EQUIANGULAR_ANGLE_TOL` moves `t` at `r = t - delta` (no arctangent: this
    density is evaluated several times per bounce). The ends are finite and `r` is a distance on the segment, so
    nothing overflows for rays grazing the light."""
    r = t - eq.delta
    den = eq.D * eq.D + r * r  # >= 1e-14
    tol = EQUIANGULAR_ANGLE_TOL * den / eq.D
    inside = eq.valid & (t >= eq.t_a - tol) & (t <= eq.t_b + tol)
    return jnp.where(inside, eq.D / (jnp.where(eq.valid, eq.theta_b - eq.theta_a, 1.0) * den), 0.0)


# --------------------------------------------------------------------------------------------------------- MIS
def power_heuristic(a, b):
    """MIS weight `a^2 / (a^2 + b^2)` (0 where both are 0)."""
    return safe_div(a * a, a * a + b * b)


# --------------------------------------------------------------------------------------------------------- Draine
DRAINE_G_SMALL = 0.05
"""Below this |g| the Draine sampler draws from Draine(g = 0, alpha): the closed form divides by g and loses
float32 precision as g -> 0 (measured: E[cos] off by 2.8 SE at g = 0.02, alpha = 22, and by 2.2 SE at alpha = 250;
within 1 SE from g = 0.05 on). Cycles splits at 1e-2. `draine_sampling_pdf` is the density of what is drawn, so
the weight `eval / pdf` (between 0.86 and 1.16 at |g| < 0.05) keeps the estimate exact."""


def draine_pdf(one_minus_cos: Float[Array, ""], g: Float[Array, ""], alpha: Float[Array, ""]) -> Float[Array, ""]:
    """Draine's phase function (Draine 2003, ApJ 598:1017, eq. 4), 1/sr, from `1 - cos theta` in [0, 2]:

        p = (1 - g^2)(1 + alpha mu^2) / ((1 + alpha (1 + 2 g^2) / 3) 4 pi (1 + g^2 - 2 g mu)^(3/2))
          = hg_pdf(1 - mu, g) (1 + alpha mu^2) / (1 + alpha (1 + 2 g^2) / 3),

    written with HG's cancellation-free denominator. g in (-1, 1), alpha >= 0; alpha = 0 is HG, (g, alpha) = (0, 1)
    Rayleigh. Positive everywhere, integrates to 1."""
    mu = 1.0 - one_minus_cos
    return hg_pdf(one_minus_cos, g) * (1.0 + alpha * mu * mu) / (1.0 + alpha * (1.0 + 2.0 * g * g) / 3.0)


def _draine_cos_small_g(u, alpha):
    """Exact inverse cdf of Draine(g = 0, alpha) (a depressed cubic in mu; Cycles `phase_draine_sample_cos`,
    small-g branch): `mu = s - 1 / (alpha s)`, `s = cbrt(b + sqrt(b^2 + alpha^-3))`, `b = (3 + alpha)(2u - 1) /
    (2 alpha)`. Written with the root's sign mirrored so that the cube root has a positive argument."""
    inv_alpha = 1.0 / alpha
    b = (3.0 + alpha) * inv_alpha * (u - 0.5)
    ab = jnp.abs(b)
    s = jnp.cbrt(ab + jnp.sqrt(ab * ab + inv_alpha * inv_alpha * inv_alpha))
    mu = s - inv_alpha / s
    return jnp.where(b >= 0, mu, -mu)


def _draine_cos_general(u, g, alpha):
    """Closed-form inverse cdf of Draine(g, alpha), g != 0 (Jendersie & d'Eon 2023, supplemental, as in Blender
    Cycles `intern/cycles/kernel/closure/volume_util.h: phase_draine_sample_cos`, blender/blender@23641358)."""
    g2 = g * g
    g3 = g * g2
    g4 = g2 * g2
    g6 = g2 * g4
    pgp1_2 = (1.0 + g2) * (1.0 + g2)
    t1a = alpha * (g4 - 1.0)
    t1a3 = t1a * t1a * t1a
    t2 = -1296.0 * (g2 - 1.0) * (alpha - alpha * g2) * t1a * (4.0 * g2 + alpha * pgp1_2)
    t9 = 2.0 + g2 + g3 * (1.0 + 2.0 * g2) * (2.0 * u - 1.0)
    t3 = 3.0 * g2 * (1.0 + g * (2.0 * u - 1.0)) + alpha * t9
    t4a = 432.0 * t1a3 + t2 + 432.0 * (alpha * (1.0 - g2)) * t3 * t3
    t10 = alpha * (2.0 * g4 - g2 - g6)
    t4b = 144.0 * t10
    t4 = t4a + safe_sqrt(-4.0 * t4b * t4b * t4b + t4a * t4a)
    cbrt_t4 = jnp.cbrt(t4)
    cbrt2 = 2.0 ** (1.0 / 3.0)
    t8 = 48.0 * cbrt2 * t10
    t6 = (2.0 * t1a + t8 / cbrt_t4 + cbrt_t4 / (3.0 * cbrt2)) / (alpha * (1.0 - g2))
    t5 = 6.0 * (1.0 + g2) + t6
    t7 = 6.0 * (1.0 + g2) - (8.0 * t3) / (alpha * (g2 - 1.0) * safe_sqrt(t5)) - t6
    r = safe_sqrt(t7) - safe_sqrt(t5)
    return (1.0 + g2 - 0.25 * r * r) / (2.0 * g)


def draine_sample(u: Float[Array, ""], g: Float[Array, ""], alpha: Float[Array, ""]) -> Polar:
    """Inverse-cdf sample of Draine(g, alpha) for alpha > 0 (u in [0, 1)): the closed form for |g| >= DRAINE_G_SMALL,
    the g = 0 cubic below it (then the density is `draine_sampling_pdf`, not `draine_pdf`). Differentiable in g and
    alpha (both branches computed with safe arguments and selected: double where). `1 - cos` and `1 + cos` come
    from cos itself (absolute error ~1e-7: the Draine lobes of the droplet model are broad, g <= 0.75)."""
    small = jnp.abs(g) < DRAINE_G_SMALL
    g_safe = jnp.where(small, DRAINE_G_SMALL, g)
    mu = jnp.where(small, _draine_cos_small_g(u, alpha), _draine_cos_general(u, g_safe, alpha))
    mu = jnp.clip(mu, -1.0, 1.0)
    return Polar(1.0 - mu, 1.0 + mu)


def draine_sampling_pdf(one_minus_cos, g, alpha) -> Float[Array, ""]:
    """Density (1/sr) of `draine_sample`: `draine_pdf` with g replaced by 0 where |g| < DRAINE_G_SMALL."""
    return draine_pdf(one_minus_cos, jnp.where(jnp.abs(g) < DRAINE_G_SMALL, 0.0, g), alpha)


# ------------------------------------------------------------------------------------------------------- mixtures
ONE_BELOW = 1.0 - 2.0**-24
"""The largest float32 below 1."""


def split_uniform(u: Float[Array, ""], w: Float[Array, ""]) -> tuple[Bool[Array, ""], Float[Array, ""]]:
    """A discrete choice and a fresh uniform from one uniform: `first = u < w`, and `u / w` (first) or
    `(u - w) / (1 - w)` (second), kept in [0, 1). `w` in [0, 1] (no derivative is taken through it).

    Precision: `u` is a multiple of 2^-24; the rescaled uniform of a lobe with probability `p` is a multiple of
    2^-24 / p, so it keeps `24 + log2(p)` bits (23 for p = 1/2, 21.4 for p = 0.18): the lobe sampler's inverse cdf
    sees a coarser grid of at most 2^24 p values. Measured in tests/test_phase_mixtures.py: no effect on the chi-square
    tests at 10^5 samples; with 2^-24 / p far below the width of any lobe in u, it cannot bias a render."""
    first = u < w
    v1 = u / jnp.where(first, w, 1.0)
    v2 = (u - w) / jnp.where(first, 1.0, 1.0 - w)
    return first, jnp.minimum(jnp.where(first, v1, v2), ONE_BELOW)


def mixture_sample(u, w, sample_first: Callable, sample_second: Callable) -> Polar:
    """Polar sample of the mixture `w p1 + (1 - w) p2`: the lobe from `split_uniform(u, w)`, then that lobe's
    sampler with the rescaled uniform (both evaluated at it, one selected)."""
    first, v = split_uniform(u, w)
    a, b = sample_first(v), sample_second(v)
    return Polar(jnp.where(first, a.one_minus_cos, b.one_minus_cos), jnp.where(first, a.one_plus_cos, b.one_plus_cos))
