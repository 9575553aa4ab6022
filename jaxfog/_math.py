"""Small, pure vector and numerics helpers shared by every module.

Every "safe" helper here uses the double-`where` idiom: the unsafe input is replaced *before* the singular
operation, so neither the value nor the gradient of the branch that is not taken can be NaN. Each one is tested for
value and gradient at its edge in `tests/test_math.py`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

PI = jnp.pi
INV_PI = 1.0 / jnp.pi
INV_4PI = 0.25 / jnp.pi


def dot(a: Float[Array, "3"], b: Float[Array, "3"]) -> Float[Array, ""]:
    """Dot product of two 3-vectors (last axis)."""
    return jnp.sum(a * b, axis=-1)


def dot_unrolled(a: Float[Array, "... 3"], b: Float[Array, "... 3"]) -> Float[Array, "..."]:
    """`dot` written as three products and two sums (no reduction). The same value up to float32 rounding; for XLA's
    CPU backend it is elementwise, so it fuses into the vectorized kernel that reads it, where a reduction over 3
    components whose result several values read becomes its own kernel of scalar code. Used by the ray-shape tests
    (3 rays a bounce; `docs/results/bench/PROFILE.md`, "Narrow values computed once": spot_fog's sample 0.93-0.94x its time, area_light
    0.56x, valley 0.60x, mirror_glass 1.09x). Not everywhere: as `dot` itself it made the whole sample 1.10x slower
    (the reductions also keep XLA from copying cheap producers into every consumer)."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def cross(a: Float[Array, "3"], b: Float[Array, "3"]) -> Float[Array, "3"]:
    """Cross product of two 3-vectors."""
    return jnp.cross(a, b)


def safe_sqrt(x: Float[Array, "..."]) -> Float[Array, "..."]:
    """`sqrt(max(x, 0))` with a finite (zero) gradient at and below 0."""
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), 0.0)


def safe_norm(v: Float[Array, "... 3"]) -> Float[Array, "..."]:
    """Euclidean length over the last axis; 0 with a zero gradient for the zero vector."""
    return safe_sqrt(jnp.sum(v * v, axis=-1))


def safe_normalize(v: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """`v / |v|` over the last axis; the zero vector maps to the zero vector, with a finite gradient."""
    n2 = jnp.sum(v * v, axis=-1, keepdims=True)
    pos = n2 > 0
    inv = jnp.where(pos, 1.0 / jnp.sqrt(jnp.where(pos, n2, 1.0)), 0.0)
    return v * inv


def safe_div(a: Float[Array, "..."], b: Float[Array, "..."]) -> Float[Array, "..."]:
    """`a / b`, and 0 (with a zero gradient) where `b == 0`."""
    nz = b != 0
    return jnp.where(nz, a / jnp.where(nz, b, 1.0), 0.0)


def safe_mul(x: Float[Array, "..."], y: Float[Array, "..."]) -> Float[Array, "..."]:
    """`x * y`, and exactly 0 with a zero derivative (in both arguments, forward and reverse) where `y == 0`,
    whatever `x` and its derivative are there (an overflowed inf included: no `inf * 0`). For a factor `y` that is
    0 only where it has underflowed (a transmittance `exp(-tau)`), whose own derivative is then 0 as well, so the
    product's true derivative is 0 too. Where `y != 0` it is the plain product (the same float32 value)."""
    nz = y != 0
    return jnp.where(nz, jnp.where(nz, x, 0.0) * y, 0.0)


def safe_log(x: Float[Array, "..."]) -> Float[Array, "..."]:
    """`log(x)` for x > 0, `-inf` for x <= 0, with a zero (finite) gradient there."""
    pos = x > 0
    return jnp.where(pos, jnp.log(jnp.where(pos, x, 1.0)), -jnp.inf)


def one_minus_exp_neg(x: Float[Array, "..."]) -> Float[Array, "..."]:
    """`1 - exp(-x)` for x >= 0, accurate for small x (`-expm1(-x)`); equals 1 at x = +inf, gradient 0 there."""
    fin = jnp.isfinite(x)
    return jnp.where(fin, -jnp.expm1(-jnp.where(fin, x, 0.0)), 1.0)


def exp_neg(x: Float[Array, "..."]) -> Float[Array, "..."]:
    """`exp(-x)` for x in [0, +inf]; exactly 0 with a zero gradient at +inf (no `0 * inf` in the backward pass)."""
    fin = jnp.isfinite(x)
    return jnp.where(fin, jnp.exp(-jnp.where(fin, x, 0.0)), 0.0)


def finite_or(x: Float[Array, "..."], fallback: float | Float[Array, "..."]) -> Float[Array, "..."]:
    """`x` where finite, else `fallback`; the gradient of the replaced entries is zero."""
    fin = jnp.isfinite(x)
    return jnp.where(fin, x, fallback)


def coordinate_frame(n: Float[Array, "3"]) -> tuple[Float[Array, "3"], Float[Array, "3"]]:
    """Two unit vectors `(s, t)` completing the unit vector `n` to a right-handed orthonormal frame.

    Duff et al. 2017, "Building an Orthonormal Basis, Revisited": branch-free except for the sign, no division by
    a quantity that can vanish (`1 + |n_z| >= 1`).
    """
    sign = jnp.where(n[2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[2])
    b = n[0] * n[1] * a
    s = _vec3(1.0 + sign * n[0] * n[0] * a, sign * b, -sign * n[0])
    t = _vec3(b, sign + n[1] * n[1] * a, -n[1])
    return s, t


_E = np.eye(3, dtype=np.float32)


def _vec3(x, y, z):
    """The 3-vector `(x, y, z)` from scalars, as a sum of scaled unit vectors (elementwise for XLA, where
    `jnp.stack` of per-lane scalars becomes a slow concatenation under `vmap`)."""
    return x * _E[0] + y * _E[1] + z * _E[2]


def to_world(local: Float[Array, "3"], n: Float[Array, "3"]) -> Float[Array, "3"]:
    """Rotate `local` (z along `n`) into world space."""
    s, t = coordinate_frame(n)
    return local[0] * s + local[1] * t + local[2] * n


def direction_from_cos(
    one_minus_cos: Float[Array, ""], one_plus_cos: Float[Array, ""], phi: Float[Array, ""], axis: Float[Array, "3"]
) -> Float[Array, "3"]:
    """Unit vector at polar angle theta around `axis`, given `1 - cos theta` and `1 + cos theta` (both in [0, 2]).

    Carrying both halves keeps `sin theta = sqrt((1 - cos)(1 + cos))` accurate at both poles.
    """
    sin_theta = safe_sqrt(one_minus_cos * one_plus_cos)
    cos_theta = 0.5 * (one_plus_cos - one_minus_cos)
    sin_phi, cos_phi = sincos(phi)
    s, t = coordinate_frame(axis)
    return (sin_theta * cos_phi) * s + (sin_theta * sin_phi) * t + cos_theta * axis


def one_minus_cos_between(a: Float[Array, "3"], b: Float[Array, "3"]) -> Float[Array, ""]:
    """`1 - cos(angle)` between unit vectors a and b, as `|a - b|^2 / 2` (no cancellation near cos = 1)."""
    d = a - b
    return 0.5 * jnp.sum(d * d, axis=-1)


class RGB(NamedTuple):
    """An RGB value as three separate channels (each of any shape; a path's channels are scalars).

    The tracer carries its throughputs, weights and radiance as `RGB` inside a bounce, not as `(3,)` arrays: under
    `vmap` a `(3,)` array becomes `(lanes, 3)`, whose XLA CPU kernels index the minor axis of 3 per element and are
    often scalar code, while each channel of an `RGB` is a contiguous `(lanes,)` array in vectorized kernels
    (`docs/results/bench/PROFILE.md`, "RGB values as three channels"). Arithmetic is per channel; the other operand may be an `RGB`, a
    `(..., 3)` array (taken channel by channel) or a scalar (every channel). The values are those of the array
    arithmetic (the same float32 operations)."""

    r: Array
    g: Array
    b: Array

    @staticmethod
    def of(x) -> "RGB":
        """`x` as an `RGB`: an `RGB` as it is, a `(..., 3)` array by channel, a scalar on every channel."""
        if isinstance(x, RGB):
            return x
        x = jnp.asarray(x)
        if x.ndim == 0:
            return RGB(x, x, x)
        return RGB(x[..., 0], x[..., 1], x[..., 2])

    def array(self) -> Float[Array, "... 3"]:
        """The `(..., 3)` array (built elementwise: a sum of scaled unit vectors, see `_vec3`; so a non-finite
        channel makes every channel NaN, and a render with it fails its finiteness check all the same)."""
        return _vec3(self.r, self.g, self.b)

    def _zip(self, other, f) -> "RGB":
        o = _channels(other)
        return RGB(f(self.r, o[0]), f(self.g, o[1]), f(self.b, o[2]))

    def __add__(self, other):
        return self._zip(other, lambda a, b: a + b)

    __radd__ = __add__

    def __mul__(self, other):
        return self._zip(other, lambda a, b: a * b)

    __rmul__ = __mul__

    def __truediv__(self, other):
        return self._zip(other, lambda a, b: a / b)

    def __rtruediv__(self, other):
        return self._zip(other, lambda a, b: b / a)

    def __sub__(self, other):
        return self._zip(other, lambda a, b: a - b)

    def __rsub__(self, other):
        return self._zip(other, lambda a, b: b - a)

    def __neg__(self):
        return RGB(-self.r, -self.g, -self.b)

    __array_ufunc__ = None  # numpy operands defer to the methods above (not broadcast against a 3-tuple)


def _channels(x):
    """The three channels of an `RGB`, a `(..., 3)` array, or a scalar (the same value thrice)."""
    if isinstance(x, RGB):
        return x
    x = jnp.asarray(x)
    if x.ndim == 0:
        return (x, x, x)
    return (x[..., 0], x[..., 1], x[..., 2])


def where_rgb(mask, a, b) -> RGB:
    """`jnp.where(mask, a, b)` per channel (`a`, `b`: `RGB`, `(..., 3)` arrays or scalars; `mask` per path)."""
    ca, cb = _channels(a), _channels(b)
    return RGB(*(jnp.where(mask, x, y) for x, y in zip(ca, cb)))


def luminance(rgb: Float[Array, "... 3"]) -> Float[Array, "..."]:
    """Rec. 709 luminance of linear RGB."""
    return 0.2126 * rgb[..., 0] + 0.7152 * rgb[..., 1] + 0.0722 * rgb[..., 2]


# ---------------------------------------------------------------- vectorizable trigonometry (polynomials, float32)
# XLA on a CPU evaluates jnp.sin / cos / tan / arctan2 as scalar library calls (5-17 ns per element on the benchmark
# machine, against 0.3-0.5 ns for exp, sqrt or a polynomial; docs/results/bench/PROFILE.md). The paths' angles need float32
# accuracy only, so these use the Cephes single-precision polynomials (S. Moshier), which XLA vectorizes.

_PIO4_1, _PIO4_2, _PIO4_3 = 0.78515625, 2.4187564849853515625e-4, 3.77489497744594108e-8  # pi/4 in three parts
_FOUR_OVER_PI = 1.27323954473516


def sincos(x: Float[Array, "..."]) -> tuple[Float[Array, "..."], Float[Array, "..."]]:
    """`(sin x, cos x)` for float32 |x| <= 1e4 (radians): octant reduction (Cody-Waite, pi/4 in three parts) and
    Cephes' minimax polynomials on [-pi/4, pi/4]; max error ~1.5e-7 for |x| <= 2 pi (`tests/test_math.py`).
    Differentiable (the derivative of the polynomial, within ~1e-6 of cos / -sin)."""
    x = jnp.asarray(x, jnp.float32)
    ax = jnp.abs(x)
    j = jnp.floor(ax * _FOUR_OVER_PI).astype(jnp.int32)
    j = j + (j & 1)  # even octant index: reduce to [-pi/4, pi/4]
    y = j.astype(jnp.float32)
    r = ((ax - y * _PIO4_1) - y * _PIO4_2) - y * _PIO4_3
    z = r * r
    ps = ((-1.9515295891e-4 * z + 8.3321608736e-3) * z - 1.6666654611e-1) * z * r + r
    pc = ((2.443315711809948e-5 * z - 1.388731625493765e-3) * z + 4.166664568298827e-2) * z * z - 0.5 * z + 1.0
    q = (j >> 1) & 3  # quadrant of |x|
    swap = (q & 1) == 1
    s = jnp.where(swap, pc, ps)
    c = jnp.where(swap, ps, pc)
    s = jnp.where((q == 2) | (q == 3), -s, s)
    c = jnp.where((q == 1) | (q == 2), -c, c)
    return jnp.where(jnp.signbit(x), -s, s), c


def tan(x: Float[Array, "..."]) -> Float[Array, "..."]:
    """`tan x` for |x| < pi/2 as `sin x / cos x` from `sincos` (relative error ~3e-7 away from +-pi/2)."""
    s, c = sincos(x)
    return s / c


def atan2(y: Float[Array, "..."], x: Float[Array, "..."]) -> Float[Array, "..."]:
    """`arctan2(y, x)` in [-pi, pi] (float32): Cephes' `atanf` polynomial after reduction to |t| <= tan(pi/8); max
    error ~2.5e-7 rad; `atan2(0, 0) = 0` and infinities follow numpy. Differentiable away from (0, 0), with a
    finite gradient there (double `where`)."""
    y = jnp.asarray(y, jnp.float32)
    x = jnp.asarray(x, jnp.float32)
    ay, ax = jnp.abs(y), jnp.abs(x)
    steep = ay > ax
    big, small = jnp.where(steep, ay, ax), jnp.where(steep, ax, ay)  # not max/min: their gradient halves at ties
    ok = big > 0
    both_inf = jnp.isinf(ay) & jnp.isinf(ax)
    # ratio in [0, 1]: atan of small/big, then reflect (double where: no 0/0 or inf/inf in either branch)
    t = jnp.where(ok & ~both_inf, small / jnp.where(ok & ~both_inf, big, 1.0), 1.0)
    hi = t > 0.4142135623730950
    u = jnp.where(hi, (t - 1.0) / (t + 1.0), t)
    z = u * u
    a = (((8.05374449538e-2 * z - 1.38776856032e-1) * z + 1.99777106478e-1) * z - 3.33329491539e-1) * z * u + u
    a = jnp.where(hi, a + 0.25 * PI, a)
    a = jnp.where(steep, 0.5 * PI - a, a)
    a = jnp.where(x < 0, PI - a, a)
    a = jnp.where(ok, a, jnp.where(jnp.signbit(x), PI, 0.0))  # atan2(+-0, -0) = +-pi, atan2(+-0, +0) = +-0
    return jnp.where(jnp.signbit(y), -a, a)
