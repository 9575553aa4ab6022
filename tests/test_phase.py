"""Henyey–Greenstein sampling and evaluation: distribution properties, float32 accuracy, gradients at g = 0.

References are written from conventions.md (`p = (1 - g^2) / (4 pi (1 + g^2 - 2 g cos)^(3/2))`, `E[cos] = g`, g > 0
forward) and evaluated in float64 numpy/scipy. Samples use fixed numpy seeds; every statistical tolerance is stated
in terms of the sample standard error (SE).
"""

from __future__ import annotations

from fractions import Fraction

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate, stats

import jaxfog as jf
from jaxfog._phase import hg_pdf, hg_sample

f32 = jnp.float32
N_SAMPLES = 200_000


def uniforms(seed: int, n: int = N_SAMPLES) -> np.ndarray:
    """float32 uniforms in [0, 1) from a fixed numpy seed."""
    return np.random.default_rng(seed).random(n, dtype=np.float32)


def sample_cos(g: float, seed: int) -> np.ndarray:
    omc, opc = jax.jit(jax.vmap(hg_sample, in_axes=(0, None)))(jnp.asarray(uniforms(seed)), f32(g))
    return 0.5 * (np.asarray(opc, np.float64) - np.asarray(omc, np.float64))


def hg64(cos_theta, g):
    return (1.0 - g * g) / (4.0 * np.pi * (1.0 + g * g - 2.0 * g * cos_theta) ** 1.5)


def textbook_inverse_cdf64(u, g):
    """Float64 textbook HG inverse CDF (pbrt / Mitsuba form), cos theta with g > 0 forward; g != 0."""
    u = np.asarray(u, np.float64)
    s = (1.0 - g * g) / (1.0 - g + 2.0 * g * u)
    return (1.0 + g * g - s * s) / (2.0 * g)


# ------------------------------------------------------------------------------------------------ normalization
@pytest.mark.parametrize("g", [-0.9, -0.5, 0.0, 0.3, 0.9, 0.99, 0.999])
def test_hg_pdf_integrates_to_one(g):
    """int 2 pi p d(cos) = 1, by Gauss–Legendre on intervals geometric toward both peaks (1 - cos = 0 and 2).

    The float32 evaluation is off by a few ulp (1e-6 relative); the quadrature is exact to < 1e-9. Tolerance 1e-5.
    """
    edges_lo = np.geomspace(1e-12, 1.0, 48)
    edges = np.unique(np.concatenate([[0.0], edges_lo, 2.0 - edges_lo[::-1], [2.0]]))
    x, w = np.polynomial.legendre.leggauss(16)
    a, b = edges[:-1, None], edges[1:, None]
    nodes = (0.5 * (b - a) * (x + 1) + a).reshape(-1)
    weights = (0.5 * (b - a) * w).reshape(-1)
    p = np.asarray(jax.vmap(hg_pdf, in_axes=(0, None))(jnp.asarray(nodes, f32), f32(g)), np.float64)
    total = 2 * np.pi * np.sum(p * weights)  # d(cos) = d(1 - cos) up to sign
    assert total == pytest.approx(1.0, abs=1e-5)
    # the float64 formula through the same quadrature: checks the quadrature itself
    assert 2 * np.pi * np.sum(hg64(1.0 - nodes, np.float64(np.float32(g))) * weights) == pytest.approx(1.0, abs=1e-9)


# ------------------------------------------------------------------------------------------------ sample moments
@pytest.mark.parametrize("g", [-0.9, -0.5, 0.0, 0.3, 0.9, 0.99])
def test_mean_cosine_is_g(g):
    """E[cos theta] = g (conventions.md), within 4 SE of the sample mean (SE = sample std / sqrt(N), N = 200k)."""
    cos = sample_cos(g, seed=1)
    se = cos.std(ddof=1) / np.sqrt(cos.size)
    assert abs(cos.mean() - g) <= 4 * se, (cos.mean(), g, se)


def test_forward_scattering_sign():
    """g = 0.95 sends most samples forward (exact P(cos > 0) = 0.989), g = -0.95 most backward."""
    assert np.mean(sample_cos(0.95, seed=2) > 0) > 0.98
    assert np.mean(sample_cos(-0.95, seed=3) < 0) > 0.98


@pytest.mark.parametrize("g", [-0.5, 0.0, 0.3, 0.9])
def test_histogram_matches_pdf(g):
    """Chi-square test of a 40-bin histogram of cos theta against bin probabilities integrated from the float64 pdf.

    Pearson's statistic has 39 degrees of freedom; fail if its p-value is below 1e-4 (fixed seed, deterministic).
    """
    cos = sample_cos(g, seed=4)
    edges = np.linspace(-1.0, 1.0, 41)
    probs = np.array([integrate.quad(lambda c: 2 * np.pi * hg64(c, g), lo, hi, epsabs=1e-13)[0]
                      for lo, hi in zip(edges[:-1], edges[1:])])
    assert probs.sum() == pytest.approx(1.0, abs=1e-9)
    observed, _ = np.histogram(cos, bins=edges)
    expected = probs * cos.size
    assert expected.min() > 20  # chi-square approximation valid
    chi2 = np.sum((observed - expected) ** 2 / expected)
    p_value = stats.chi2.sf(chi2, df=len(probs) - 1)
    assert p_value > 1e-4, (chi2, p_value)


def test_module_sample_direction_and_pdf():
    """`HenyeyGreenstein.sample` around an arbitrary direction d: E[wo] = g d (azimuthal symmetry), |wo| = 1, and
    the returned pdf equals `eval(d, wo)` and the float64 HG value at dot(d, wo). Tolerance: 4 SE per component."""
    g = 0.6
    phase = jf.HenyeyGreenstein(g)
    d = np.array([0.48, -0.6, 0.64])
    u = np.random.default_rng(5).random((50_000, 2), dtype=np.float32)
    smp = jax.vmap(lambda uu: phase.sample(jnp.asarray(d, f32), uu))(jnp.asarray(u))
    wo = np.asarray(smp.wo, np.float64)
    np.testing.assert_allclose(np.linalg.norm(wo, axis=-1), 1.0, atol=2e-6)
    se = wo.std(axis=0, ddof=1) / np.sqrt(len(wo))
    assert np.all(np.abs(wo.mean(0) - g * d) <= 4 * se), (wo.mean(0), g * d, se)
    ev = np.asarray(jax.vmap(lambda w: phase.eval(jnp.asarray(d, f32), w))(smp.wo), np.float64)
    np.testing.assert_allclose(np.asarray(smp.pdf), ev, rtol=1e-3)  # eval recomputes 1-cos from |d - wo|^2 / 2
    np.testing.assert_allclose(np.asarray(smp.pdf), hg64(wo @ d, g), rtol=2e-3)


# ------------------------------------------------------------------------------------------------ float32 numerics
@pytest.mark.parametrize("g", [0.0, 1e-7, -1e-7, 1e-3, -1e-3, 0.999, -0.999, 0.9999, -0.9999])
def test_samples_in_range_float32(g):
    """1 - cos and 1 + cos in [0, 2], finite, summing to 2; cos in [-1, 1]; for u over [0, 1) incl. its ends."""
    u = np.concatenate([uniforms(6, 20_000), np.float32([0.0, 1e-30, 1e-7, 0.5, 1 - 2**-24])])
    omc, opc = jax.vmap(hg_sample, in_axes=(0, None))(jnp.asarray(u), f32(g))
    omc, opc = np.asarray(omc), np.asarray(opc)
    assert omc.dtype == np.float32 and opc.dtype == np.float32
    for x in (omc, opc):
        assert np.all(np.isfinite(x)) and np.all(x >= 0) and np.all(x <= 2)
    cos = 0.5 * (opc - omc)
    assert np.all(cos >= -1) and np.all(cos <= 1)
    np.testing.assert_allclose(omc.astype(np.float64) + opc, 2.0, atol=1e-6)


def test_sample_matches_float64_inverse_cdf_small_g():
    """At g = 1e-5 the textbook float32 inverse CDF is off by ~1e-2 in cos; hg_sample must match the float64
    reference to 1e-6 (a few float32 ulp of cos)."""
    g = np.float32(1e-5)
    u = uniforms(7, 5_000)
    omc, opc = jax.vmap(hg_sample, in_axes=(0, None))(jnp.asarray(u), f32(g))
    cos = 0.5 * (np.asarray(opc, np.float64) - np.asarray(omc, np.float64))
    ref = textbook_inverse_cdf64(u, np.float64(g))  # float64: cancellation costs ~1e-11 here
    np.testing.assert_allclose(cos, ref, atol=1e-6)


def test_sample_matches_float64_inverse_cdf_near_forward_peak():
    """At g = 0.999 the forward lobe has 1 - cos ~ 1e-6; hg_sample's 1 - cos and 1 + cos must match the textbook
    inverse CDF to 1e-5 relative (tens of float32 ulp; the textbook in float32 has no correct digit there).

    Reference: the textbook formula in float64 for the bulk (1 - cos >= 1e-10 there, so its cancellation error
    ~1e-16 / (1 - cos) <= 1e-6 relative), and in exact rational arithmetic for u up to 1 - 2^-23 (1 - cos ~ 1e-13).
    """
    g = np.float32(0.999)
    u = uniforms(8, 5_000)
    omc, opc = jax.vmap(hg_sample, in_axes=(0, None))(jnp.asarray(u), f32(g))
    ref_cos = textbook_inverse_cdf64(u, np.float64(g))
    assert np.min(1.0 - ref_cos) > 1e-10
    np.testing.assert_allclose(np.asarray(omc, np.float64), 1.0 - ref_cos, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(opc, np.float64), 1.0 + ref_cos, rtol=1e-5)

    u_edge = np.float32([1e-6, 0.9, 0.99, 0.999, 0.9999, 1 - 2**-23])
    omc, opc = jax.vmap(hg_sample, in_axes=(0, None))(jnp.asarray(u_edge), f32(g))
    gq = Fraction(float(g))
    for ui, o1, o2 in zip(u_edge, np.asarray(omc), np.asarray(opc)):
        s = (1 - gq * gq) / (1 - gq + 2 * gq * Fraction(float(ui)))
        cos = (1 + gq * gq - s * s) / (2 * gq)
        assert float(o1) == pytest.approx(float(1 - cos), rel=1e-5)
        assert float(o2) == pytest.approx(float(1 + cos), rel=1e-5)


def test_pdf_float32_matches_float64_near_forward_peak():
    """hg_pdf in float32 vs the naive formula in float64 at g = 0.999 over 1 - cos in [1e-9, 2]: rel. error 1e-5.
    (The naive float32 formula is 16% off at g = 0.999.) At g = 0.9999 the value stays finite and accurate."""
    omc = np.geomspace(1e-9, 2.0, 400).astype(np.float32)
    for g in (0.999, 0.9999):
        g64 = np.float64(np.float32(g))
        p = np.asarray(jax.vmap(hg_pdf, in_axes=(0, None))(jnp.asarray(omc), f32(g)), np.float64)
        assert np.all(np.isfinite(p))
        ref = hg64(1.0 - omc.astype(np.float64), g64)
        np.testing.assert_allclose(p, ref, rtol=1e-5)


# ------------------------------------------------------------------------------------------------ gradients at g = 0
def omc_stable64(u, g):
    """1 - cos from the cancellation-free form in float64 (valid at g = 0)."""
    a, b, v = 1 - g, 1 + g, 1 - u
    d = a * v + b * u
    return 2 * a * a * v * (v + b * u) / d**2


@pytest.mark.parametrize("g", [0.0, 1e-7, -1e-7])
def test_sample_gradient_wrt_g_at_zero(g):
    """d(1 - cos)/dg at g = 0 is -6 u (1 - u) (so that d E[cos]/dg = 1); at and right beside g = 0 it is finite and
    equal to it (no guard that zeroes it). Checked against the analytic value and a float64 central difference."""
    u = np.float32([0.01, 0.2, 0.5, 0.77, 0.99])
    def dg(i):
        return jax.vmap(jax.grad(lambda uu, gg: hg_sample(uu, gg)[i], argnums=1), in_axes=(0, None))(jnp.asarray(u), f32(g))

    d_omc, d_opc = dg(0), dg(1)
    assert np.all(np.isfinite(d_omc)) and np.all(np.isfinite(d_opc))
    u64 = u.astype(np.float64)
    analytic = -6 * u64 * (1 - u64)
    h = 1e-5
    fd = (omc_stable64(u64, g + h) - omc_stable64(u64, g - h)) / (2 * h)
    np.testing.assert_allclose(fd, analytic, atol=1e-6)
    np.testing.assert_allclose(np.asarray(d_omc), analytic, atol=1e-5)
    np.testing.assert_allclose(np.asarray(d_opc), -analytic, atol=1e-5)  # (1 - cos) + (1 + cos) = 2


@pytest.mark.parametrize("g", [0.0, 1e-7, -1e-7])
def test_pdf_gradient_wrt_g_at_zero(g):
    """d p / d g at g = 0 is 3 cos / (4 pi); finite at and beside g = 0."""
    omc = np.float32([0.0, 0.3, 1.0, 1.7, 2.0])
    dp = jax.vmap(jax.grad(hg_pdf, argnums=1), in_axes=(0, None))(jnp.asarray(omc), f32(g))
    assert np.all(np.isfinite(dp))
    np.testing.assert_allclose(np.asarray(dp), 3 * (1 - omc.astype(np.float64)) / (4 * np.pi), atol=1e-6)


@pytest.mark.parametrize("g", [0.9999999, 0.99999994, -0.9999999, -0.99999994])
def test_hg_pdf_value_and_gradient_at_the_float32_edge_of_g(g):
    """1 - |g| of 6e-8 and 1.2e-7 (the two float32 values next to +-1; a fit's unconstrained g = tanh(y) reaches
    them for |y| > 8): value and d p / d g at the peak, beside it and far from it agree with the float64 formula
    (rel. 1e-4: the peak's value ~1e13 comes from (1 - g)^2 rounded once), and are finite: the derivative of
    `1 / (d sqrt d)` written directly squares a divisor that underflows, a NaN at the peak."""
    g32 = jnp.float32(g)
    gd = float(g32)
    peak = 0.0 if gd > 0 else 2.0
    for omc in (peak, abs(peak - 1e-7), abs(peak - 1e-4), 1.0):
        value = float(hg_pdf(jnp.float32(omc), g32))
        dg = float(jax.grad(hg_pdf, argnums=1)(jnp.float32(omc), g32))
        assert np.isfinite(value) and np.isfinite(dg), (omc, value, dg)
        cos = 1.0 - float(np.float32(omc))
        den = (1 - gd) ** 2 + 2 * gd * (1 - cos) if gd > 0 else (1 + gd) ** 2 - 2 * gd * (1 + cos)
        ref = (1 - gd * gd) / (4 * np.pi * den ** 1.5)
        dref = -2 * gd / (4 * np.pi * den ** 1.5) - 1.5 * (1 - gd * gd) * (2 * gd - 2 * cos) / (4 * np.pi * den ** 2.5)
        assert value == pytest.approx(ref, rel=1e-4), (omc, value, ref)
        assert dg == pytest.approx(dref, rel=1e-3), (omc, dg, dref)


@pytest.mark.parametrize("g", [1.0, -1.0])
def test_hg_pdf_finite_at_g_plus_minus_one(g):
    """g = +-1 (outside the valid range, but where tanh of a large unconstrained fit parameter rounds): the value
    0 away from the peak and finite everywhere, gradients finite (no 0 x inf)."""
    for omc in (0.0, 1e-7, 1.0, 2.0):
        value = float(hg_pdf(jnp.float32(omc), jnp.float32(g)))
        grads = jax.grad(hg_pdf, argnums=(0, 1))(jnp.float32(omc), jnp.float32(g))
        assert np.isfinite(value) and all(np.isfinite(float(x)) for x in grads), (omc, value, grads)
