"""Value and gradient of every safe helper in `jaxfog._math`, at its edge and at an ordinary point.

"Safe" means: finite value where documented, and a finite gradient (forward and reverse mode) even where the
unguarded expression would give inf or NaN in the branch not taken. Expected values are written from the helpers'
documented meaning, in float64 numpy where a formula is needed.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxfog import _math as m

f32 = jnp.float32
INF = float("inf")


def grad_both(f, x):
    """Reverse- and forward-mode derivative of a scalar function of a scalar."""
    x = f32(x)
    rev = jax.grad(f)(x)
    fwd = jax.jvp(f, (x,), (f32(1.0),))[1]
    return float(rev), float(fwd)


# ----------------------------------------------------------------------------------------------------- safe_sqrt
@pytest.mark.parametrize("x, value, grad", [(4.0, 2.0, 0.25), (1e-6, 1e-3, 0.5e3), (0.0, 0.0, 0.0), (-1.0, 0.0, 0.0),
                                            (-INF, 0.0, 0.0), (INF, INF, 0.0)])
def test_safe_sqrt(x, value, grad):
    assert float(m.safe_sqrt(f32(x))) == pytest.approx(value, rel=1e-6)
    for g in grad_both(m.safe_sqrt, x):
        assert np.isfinite(g)
        assert g == pytest.approx(grad, rel=1e-5)


# ----------------------------------------------------------------------------------------------------- safe_norm
def test_safe_norm_values_and_gradient():
    v = jnp.array([3.0, -4.0, 12.0])
    assert float(m.safe_norm(v)) == pytest.approx(13.0, rel=1e-6)
    np.testing.assert_allclose(jax.grad(m.safe_norm)(v), np.array([3.0, -4.0, 12.0]) / 13.0, rtol=1e-6)


def test_safe_norm_zero_vector():
    z = jnp.zeros(3)
    assert float(m.safe_norm(z)) == 0.0
    for jac in (jax.jacrev(m.safe_norm)(z), jax.jacfwd(m.safe_norm)(z)):
        assert np.all(np.isfinite(jac)), jac
    # batched: a zero row does not poison its neighbours' gradients
    vs = jnp.array([[0.0, 0.0, 0.0], [0.0, 3.0, 4.0]])
    gr = jax.grad(lambda v: jnp.sum(m.safe_norm(v)))(vs)
    np.testing.assert_allclose(gr, [[0, 0, 0], [0, 0.6, 0.8]], atol=1e-7)


# ------------------------------------------------------------------------------------------------ safe_normalize
def test_safe_normalize_values_and_jacobian():
    v = np.array([1.0, -2.0, 2.0])
    out = m.safe_normalize(jnp.asarray(v, f32))
    np.testing.assert_allclose(out, v / 3.0, rtol=1e-6)
    # d(v/|v|)/dv = (I - n n^T) / |v|
    n = v / 3.0
    expected = (np.eye(3) - np.outer(n, n)) / 3.0
    np.testing.assert_allclose(jax.jacrev(m.safe_normalize)(jnp.asarray(v, f32)), expected, atol=1e-6)
    np.testing.assert_allclose(jax.jacfwd(m.safe_normalize)(jnp.asarray(v, f32)), expected, atol=1e-6)


def test_safe_normalize_zero_vector():
    z = jnp.zeros(3)
    np.testing.assert_array_equal(m.safe_normalize(z), np.zeros(3))
    for jac in (jax.jacrev(m.safe_normalize)(z), jax.jacfwd(m.safe_normalize)(z)):
        assert np.all(np.isfinite(jac)), jac
    vs = jnp.array([[0.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    out = m.safe_normalize(vs)
    np.testing.assert_allclose(out, [[0, 0, 0], [0, 0, 1]])
    gr = jax.grad(lambda v: jnp.sum(m.safe_normalize(v)[..., 0]))(vs)
    assert np.all(np.isfinite(gr))
    np.testing.assert_allclose(gr[1], [0.5, 0.0, 0.0], atol=1e-7)  # d(x/|v|)/dx at (0,0,2) = 1/2


def test_dot_unrolled_is_dot():
    rng = np.random.default_rng(3)
    a, b = (jnp.asarray(rng.normal(size=(5, 3)), f32) for _ in range(2))
    np.testing.assert_allclose(m.dot_unrolled(a, b), m.dot(a, b), rtol=1e-6, atol=1e-7)
    ga = jax.grad(lambda x: jnp.sum(m.dot_unrolled(x, b)))(a)
    np.testing.assert_allclose(ga, b, rtol=1e-7)
    assert float(m.dot_unrolled(jnp.ones(3), jnp.asarray([1.0, 2.0, 3.0]))) == 6.0


# ----------------------------------------------------------------------------------------------------- safe_div
@pytest.mark.parametrize("a, b, value, da, db", [
    (3.0, 2.0, 1.5, 0.5, -0.75),
    (3.0, 0.0, 0.0, 0.0, 0.0),
    (0.0, 0.0, 0.0, 0.0, 0.0),
    (INF, 0.0, 0.0, 0.0, 0.0),
    (3.0, INF, 0.0, 0.0, 0.0),
    (-3.0, 1e-15, -3e15, 1e15, 3e30),  # tiny but nonzero b divides (no threshold)
])
def test_safe_div(a, b, value, da, db):
    out = float(m.safe_div(f32(a), f32(b)))
    assert out == pytest.approx(value, rel=1e-6)
    ga, gb = jax.grad(m.safe_div, argnums=(0, 1))(f32(a), f32(b))
    assert np.isfinite(ga)
    assert float(ga) == pytest.approx(da, rel=1e-5)
    if db is not None:
        assert np.isfinite(gb)
        assert float(gb) == pytest.approx(db, rel=1e-5)
    _, tangent = jax.jvp(m.safe_div, (f32(a), f32(b)), (f32(1.0), f32(0.0)))
    assert np.isfinite(tangent) and float(tangent) == pytest.approx(da, rel=1e-5)


# ----------------------------------------------------------------------------------------------------- safe_log
@pytest.mark.parametrize("x, value, grad", [(np.e, 1.0, 1 / np.e), (1e-30, np.log(1e-30), 1e30), (0.0, -INF, 0.0),
                                            (-2.0, -INF, 0.0), (INF, INF, 0.0)])
def test_safe_log(x, value, grad):
    out = float(m.safe_log(f32(x)))
    if np.isinf(value):
        assert out == value
    else:
        assert out == pytest.approx(value, rel=1e-6)
    for g in grad_both(m.safe_log, x):
        assert np.isfinite(g)
        assert g == pytest.approx(grad, rel=1e-5)


# ------------------------------------------------------------------------------------ one_minus_exp_neg, exp_neg
@pytest.mark.parametrize("x", [0.0, 1e-12, 1e-7, 1e-3, 0.5, 3.0, 50.0, 100.0, INF])
def test_one_minus_exp_neg(x):
    out = float(m.one_minus_exp_neg(f32(x)))
    expected = -np.expm1(-np.float64(np.float32(x)))
    assert out == pytest.approx(expected, rel=2e-7, abs=0.0)  # accurate for tiny x: no 1 - exp cancellation
    expected_grad = 0.0 if np.isinf(x) else np.exp(-np.float64(np.float32(x)))
    for g in grad_both(m.one_minus_exp_neg, x):
        assert np.isfinite(g)
        # abs: float32 resolution of the value's scale (1): JAX differentiates expm1 as `expm1 + 1`, which is 0 once
        # exp(-x) < 2^-24; the derivative is then off by less than 6e-8 absolute.
        assert g == pytest.approx(expected_grad, rel=1e-6, abs=6e-8)


@pytest.mark.parametrize("x", [0.0, 1e-7, 0.5, 3.0, 87.0, 100.0, 200.0, INF])
def test_exp_neg(x):
    out = float(m.exp_neg(f32(x)))
    expected = np.exp(-np.float64(np.float32(x)))
    assert out == pytest.approx(expected, rel=1e-6, abs=2e-38)  # abs: below float32's normal range
    for g in grad_both(m.exp_neg, x):
        assert np.isfinite(g)
        assert g == pytest.approx(-expected, rel=1e-6, abs=2e-38)


# ----------------------------------------------------------------------------------------------------- finite_or
@pytest.mark.parametrize("x, expected", [(2.5, 2.5), (INF, 7.0), (-INF, 7.0), (float("nan"), 7.0)])
def test_finite_or(x, expected):
    assert float(m.finite_or(f32(x), 7.0)) == expected
    g = jax.grad(lambda y: m.finite_or(y, 7.0))(f32(x))
    assert np.isfinite(g)
    assert float(g) == (1.0 if np.isfinite(x) else 0.0)


# ------------------------------------------------------------------------------------- coordinate_frame, to_world
FRAME_NORMALS = [
    (0.0, 0.0, 1.0), (0.0, 0.0, -1.0), (1.0, 0.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, 0.0),  # last: replaced below
    (1e-8, 0.0, -1.0), (-1e-8, 1e-8, 1.0), (0.6, 0.0, -0.8), (0.48, -0.6, 0.64), (0.0, 1.0, 0.0),
]


@pytest.mark.parametrize("n", [v for v in FRAME_NORMALS if any(v)])
def test_coordinate_frame_is_orthonormal_right_handed(n):
    n64 = np.asarray(n, np.float64)
    n64 /= np.linalg.norm(n64)
    nn = jnp.asarray(n64, f32)
    s, t = m.coordinate_frame(nn)
    frame = np.stack([np.asarray(s, np.float64), np.asarray(t, np.float64), n64])
    np.testing.assert_allclose(frame @ frame.T, np.eye(3), atol=2e-6)
    assert np.linalg.det(frame) == pytest.approx(1.0, abs=2e-6)  # (s, t, n) right-handed
    jac = jax.jacfwd(lambda v: jnp.concatenate(m.coordinate_frame(v)))(nn)
    assert np.all(np.isfinite(jac))
    jac = jax.jacrev(lambda v: jnp.concatenate(m.coordinate_frame(v)))(nn)
    assert np.all(np.isfinite(jac))
    local = jnp.array([0.2, -0.3, 0.9])
    w = np.asarray(m.to_world(local, nn), np.float64)
    np.testing.assert_allclose(w, frame.T @ np.asarray(local, np.float64), atol=2e-6)


# -------------------------------------------------------------------------------------------- direction_from_cos
@pytest.mark.parametrize("cos_theta", [1.0, 1.0 - 1e-7, 0.3, 0.0, -0.7, -1.0])
@pytest.mark.parametrize("axis", [(0.0, 0.0, 1.0), (0.0, 0.0, -1.0), (0.48, -0.6, 0.64)])
def test_direction_from_cos(cos_theta, axis):
    a = np.asarray(axis, np.float64)
    a /= np.linalg.norm(a)
    omc, opc = 1.0 - cos_theta, 1.0 + cos_theta  # exact in float64; both halves given, as hg_sample does
    w = m.direction_from_cos(f32(omc), f32(opc), f32(1.234), jnp.asarray(a, f32))
    w64 = np.asarray(w, np.float64)
    assert np.linalg.norm(w64) == pytest.approx(1.0, abs=1e-6)
    assert float(w64 @ a) == pytest.approx(cos_theta, abs=2e-6)

    # gradients w.r.t. both halves, at the poles too (sin = sqrt((1-cos)(1+cos)) is not differentiable there)
    def f(o1, o2):
        return jnp.sum(m.direction_from_cos(o1, o2, f32(1.234), jnp.asarray(a, f32)) * jnp.array([0.3, 0.5, 0.7]))

    grads = jax.grad(f, argnums=(0, 1))(f32(omc), f32(opc))
    assert all(np.isfinite(g) for g in grads)


def test_direction_from_cos_tiny_angle_is_accurate():
    """At 1 - cos = 1e-10 (below float32 resolution of cos) the direction still has sin theta = sqrt(2e-10)."""
    axis = jnp.array([0.0, 0.0, 1.0])
    w = m.direction_from_cos(f32(1e-10), f32(2.0 - 1e-10), f32(0.0), axis)
    assert float(jnp.hypot(w[0], w[1])) == pytest.approx(np.sqrt(1e-10 * (2 - 1e-10)), rel=1e-5)


# ----------------------------------------------------------------------------------------- one_minus_cos_between
@pytest.mark.parametrize("angle", [0.0, 1e-5, 1e-3, 0.5, np.pi / 2, 3.0, np.pi])
def test_one_minus_cos_between(angle):
    a = np.array([0.0, 0.6, 0.8])
    perp = np.array([1.0, 0.0, 0.0])
    b = np.cos(angle) * a + np.sin(angle) * perp
    out = float(m.one_minus_cos_between(jnp.asarray(a, f32), jnp.asarray(b, f32)))
    expected = 2.0 * np.sin(angle / 2) ** 2  # = 1 - cos, without cancellation
    assert out == pytest.approx(expected, rel=1e-5, abs=1e-7)
    ga, gb = jax.grad(m.one_minus_cos_between, argnums=(0, 1))(jnp.asarray(a, f32), jnp.asarray(b, f32))
    assert np.all(np.isfinite(ga)) and np.all(np.isfinite(gb))
    np.testing.assert_allclose(ga, a - b, atol=1e-6)  # d/da |a-b|^2/2 = a - b


def test_one_minus_cos_between_small_angle_beats_dot():
    """At an angle of 1e-4 rad, 1 - dot(a, b) in float32 is mostly rounding; |a - b|^2 / 2 is accurate."""
    angle = 1e-4
    a = np.array([0.0, 0.0, 1.0])
    b = np.array([np.sin(angle), 0.0, np.cos(angle)])
    out = float(m.one_minus_cos_between(jnp.asarray(a, f32), jnp.asarray(b, f32)))
    assert out == pytest.approx(2 * np.sin(angle / 2) ** 2, rel=1e-3)


# ------------------------------------------------------------------------- polynomial trigonometry (sincos, atan2)
def test_sincos_and_tan_match_float64_numpy():
    """Within a few float32 ulps of the float64 values (bounds: 3e-7 absolute for sin/cos on |x| <= 8, which
    covers every angle the tracer forms; 5e-7 relative (to max(1, |tan|)) for tan on |x| < pi/2)."""
    x = np.linspace(-8.0, 8.0, 400_001).astype(np.float32)
    s, c = (np.asarray(v, np.float64) for v in m.sincos(jnp.asarray(x)))
    x64 = x.astype(np.float64)
    assert np.abs(s - np.sin(x64)).max() < 3e-7 and np.abs(c - np.cos(x64)).max() < 3e-7
    assert np.all(np.signbit(np.asarray(m.sincos(jnp.asarray([0.0, -0.0], jnp.float32))[0])) == [False, True])
    xt = np.linspace(-1.5707962, 1.5707962, 200_001).astype(np.float32)
    t = np.asarray(m.tan(jnp.asarray(xt)), np.float64)
    ref = np.tan(xt.astype(np.float64))
    assert (np.abs(t - ref) / np.maximum(np.abs(ref), 1.0)).max() < 5e-7


def test_sincos_gradient_is_cos_and_minus_sin():
    for x in (-5.0, -0.3, 0.0, 0.7, 2.5, 6.2):
        ds = grad_both(lambda v: m.sincos(v)[0], x)
        dc = grad_both(lambda v: m.sincos(v)[1], x)
        np.testing.assert_allclose(ds, [np.cos(x)] * 2, atol=2e-6)
        np.testing.assert_allclose(dc, [-np.sin(x)] * 2, atol=2e-6)


def test_atan2_matches_numpy_over_many_scales_and_edges():
    rng = np.random.default_rng(0)
    n = 200_000
    y = (rng.standard_normal(n) * 10.0 ** rng.uniform(-8, 4, n)).astype(np.float32)
    x = (rng.standard_normal(n) * 10.0 ** rng.uniform(-8, 4, n)).astype(np.float32)
    a = np.asarray(m.atan2(jnp.asarray(y), jnp.asarray(x)), np.float64)
    assert np.abs(a - np.arctan2(y.astype(np.float64), x.astype(np.float64))).max() < 4e-7
    edges = np.array([0.0, -0.0, 1.0, -1.0, INF, -INF, 1e-30, -1e-30], np.float32)
    yy, xx = np.meshgrid(edges, edges)
    got = np.asarray(m.atan2(jnp.asarray(yy), jnp.asarray(xx)))
    want = np.arctan2(yy, xx)
    np.testing.assert_allclose(got, want, atol=1e-6)
    assert np.array_equal(np.signbit(got), np.signbit(want))  # signed zeros and +-pi as numpy


def test_atan2_gradient_finite_at_origin_and_exact_elsewhere():
    # d/dy atan2(y, x) = x / (x^2 + y^2); d/dx = -y / (x^2 + y^2)
    for y, x in ((1.0, 2.0), (-3.0, 0.5), (0.2, -4.0), (-1.0, -1.0)):
        dy = grad_both(lambda v: m.atan2(v, f32(x)), y)
        dx = grad_both(lambda v: m.atan2(f32(y), v), x)
        np.testing.assert_allclose(dy, [x / (x * x + y * y)] * 2, rtol=1e-5)
        np.testing.assert_allclose(dx, [-y / (x * x + y * y)] * 2, rtol=1e-5)
    for v in grad_both(lambda v: m.atan2(v, f32(0.0)), 0.0) + grad_both(lambda v: m.atan2(f32(0.0), v), 0.0):
        assert np.isfinite(v)


def test_rgb_channels_do_the_array_arithmetic():
    """`RGB` (the tracer's channels) gives the values and gradients of the same arithmetic on (3,) arrays, with
    scalars, arrays and other RGBs as operands, under `vmap` (channels of shape (lanes,))."""
    rng = np.random.default_rng(3)
    a, b, c = (jnp.asarray(rng.uniform(0.1, 2.0, (7, 3)), jnp.float32) for _ in range(3))
    s = jnp.asarray(rng.uniform(0.1, 2.0, 7), jnp.float32)
    mask = jnp.asarray(rng.uniform(size=7) < 0.5)

    def with_arrays(a, b, c, s, m):
        x = (a * b + c) / s - 0.5 * a
        return jnp.where(m, x * s, 0.0) + 1.0

    def with_rgb(a, b, c, s, m):
        x = (m_.RGB.of(a) * b + m_.RGB.of(c)) / s - m_.RGB.of(a) * 0.5
        return (m_.where_rgb(m, x * s, 0.0) + 1.0).array()

    m_ = m
    want = jax.vmap(with_arrays)(a, b, c, s, mask)
    got = jax.vmap(with_rgb)(a, b, c, s, mask)
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-6)
    g_want = jax.grad(lambda a: jnp.sum(jax.vmap(with_arrays)(a, b, c, s, mask) ** 2))(a)
    g_got = jax.grad(lambda a: jnp.sum(jax.vmap(with_rgb)(a, b, c, s, mask) ** 2))(a)
    np.testing.assert_allclose(np.asarray(g_got), np.asarray(g_want), rtol=1e-5)
    # reflected operators, numpy and JAX scalars on the left, negation
    x = m.RGB.of(jnp.asarray([1.0, 2.0, 4.0], jnp.float32))
    for got, want in (((2.0 - x).array(), [1.0, 0.0, -2.0]), ((4.0 / x).array(), [4.0, 2.0, 1.0]),
                      ((np.float32(3.0) * x).array(), [3.0, 6.0, 12.0]), ((jnp.float32(1.0) + x).array(), [2, 3, 5]),
                      ((-x).array(), [-1.0, -2.0, -4.0])):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want, np.float32))
    # of: a scalar on every channel; an RGB as it is; array() builds the (3,) array back
    x = m.RGB.of(jnp.float32(2.5))
    assert np.asarray(x.array()).tolist() == [2.5, 2.5, 2.5] and m.RGB.of(x) is x
    np.testing.assert_array_equal(np.asarray(m.RGB.of(a[0]).array()), np.asarray(a[0]))
