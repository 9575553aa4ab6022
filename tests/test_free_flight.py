"""Free-flight sampling math of `jaxfog._medium`, exercised exactly as the integrator uses it.

On a segment of length `s` the integrator draws `u`, computes `q, log(1 - q) = branch_probability(sh, s)`, takes the
medium branch if `u < q` with `t = sample_truncated_exponential(u / q, sh, s)` and weight `medium_weight`, else the
surface branch with weight `surface_weight`. References are float64 numpy/scipy; samples come from fixed numpy seeds;
statistical tolerances are 4 standard errors (SE) of the sample mean unless stated.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate, stats

from jaxfog import _medium as M

f32 = jnp.float32
N = 200_000


def uniforms(seed: int, n: int = N) -> np.ndarray:
    return np.random.default_rng(seed).random(n, dtype=np.float32)


@jax.jit
def _flight(u, sh, s):
    q, log1mq = M.branch_probability(sh, s)
    is_med = u < q
    t = M.sample_truncated_exponential(u / q, sh, s)
    return jnp.where(is_med, t, s), is_med, q, log1mq


def free_flight(u, sh, s):
    """The integrator's free flight for a vector of uniforms: `(t (= s on the surface branch), is_med, q, log1mq)`."""
    t, is_med, q, log1mq = _flight(jnp.asarray(u), f32(sh), f32(s))
    return np.asarray(t, np.float64), np.asarray(is_med), float(q), float(log1mq)


# ------------------------------------------------------------------------------------------------ distribution of t
@pytest.mark.parametrize("sigma", [0.2, 0.7, 3.0])
def test_mean_free_path(sigma):
    """On a segment much longer than 1/sigma (s = 1000, the default extent) E[t] = 1/sigma within 4 SE."""
    t, is_med, q, _ = free_flight(uniforms(1), sigma, 1000.0)
    assert q == pytest.approx(1.0)
    assert is_med.all()
    se = t.std(ddof=1) / np.sqrt(t.size)
    assert abs(t.mean() - 1.0 / sigma) <= 4 * se, (t.mean(), 1 / sigma, se)


@pytest.mark.parametrize("sigma, s", [(0.5, 3.0), (2.0, 1.0), (0.05, 20.0)])
def test_survival_is_exponential(sigma, s):
    """P(t > x) = exp(-sigma x) for x < s, and P(surface branch) = exp(-sigma s): each within 4 binomial SEs
    (sqrt(p (1 - p) / N)); and the medium-branch t follows the truncated exponential CDF (Kolmogorov–Smirnov,
    p-value > 1e-4)."""
    t, is_med, q, log1mq = free_flight(uniforms(2), sigma, s)
    assert q == pytest.approx(-np.expm1(-sigma * s), rel=1e-6)
    assert log1mq == pytest.approx(-sigma * s, rel=1e-6)
    for x in np.linspace(0.0, s, 9)[1:-1]:
        p = np.exp(-sigma * x)
        assert abs(np.mean(t > x) - p) <= 4 * np.sqrt(p * (1 - p) / t.size), x
    p_surf = np.exp(-sigma * s)
    assert abs(np.mean(~is_med) - p_surf) <= 4 * np.sqrt(p_surf * (1 - p_surf) / t.size)
    assert np.all(t[is_med] < s) and np.all(t[is_med] >= 0)
    cdf = lambda x: -np.expm1(-sigma * x) / -np.expm1(-sigma * s)  # noqa: E731
    assert stats.kstest(t[is_med], cdf).pvalue > 1e-4


@pytest.mark.parametrize("sigma, s", [(0.5, 3.0), (2.0, 1.0), (0.3, 1000.0)])
def test_truncated_sampling_equals_plain_free_flight(sigma, s):
    """Where the floor Q_MIN is not active, the branch-and-truncate procedure is ordinary free flight
    `t = -log1p(-u) / sigma` clipped at s, sample by sample (same u), up to float32 rounding (1e-5 relative), and the
    branch is `medium` exactly when the plain free flight stops before s (except within rounding of the boundary)."""
    u = uniforms(3)
    t, is_med, q, _ = free_flight(u, sigma, s)
    assert q > M.Q_MIN
    plain = -np.log1p(-u.astype(np.float64)) / sigma
    near_boundary = np.abs(plain - s) < 1e-4 * s
    assert np.array_equal(is_med[~near_boundary], plain[~near_boundary] < s)
    med = is_med & ~near_boundary
    np.testing.assert_allclose(t[med], plain[med], rtol=1e-5, atol=1e-6)
    # in distribution as well: same survival curve as the plain sampler (two-sample KS)
    assert stats.ks_2samp(t, np.minimum(plain, s)).pvalue > 1e-4


def test_thin_segment_uses_floor():
    """With sigma s tiny (even sigma = 0) the medium branch still has probability Q_MIN and t is uniform on [0, s]."""
    for sigma in (0.0, 1e-9, 1e-3):
        sh = float(M.sampling_extinction(jnp.full(3, sigma, f32)))
        t, is_med, q, log1mq = free_flight(uniforms(4), sh, 2.0)
        assert q == pytest.approx(M.Q_MIN)
        assert log1mq == pytest.approx(np.log1p(-M.Q_MIN))
        assert abs(is_med.mean() - M.Q_MIN) <= 4 * np.sqrt(M.Q_MIN * (1 - M.Q_MIN) / N)
        assert stats.kstest(t[is_med], stats.uniform(0, 2.0).cdf).pvalue > 1e-4


# ------------------------------------------------------------------------------------------------ weights: unbiased
def f_medium(t):
    """A smooth test integrand along the segment (RGB)."""
    return np.stack([1.0 + np.cos(2.0 * t), np.exp(-0.3 * t), 0.5 + t * t / 10.0], axis=-1)


F_SURFACE = np.array([0.7, 1.3, 0.2])


@pytest.mark.parametrize("sigma_t, albedo, s, sh", [
    ((0.3, 0.8, 1.5), (0.9, 0.5, 0.2), 2.5, None),      # RGB, sampling at the smallest channel ("detached")
    ((0.3, 0.8, 1.5), (0.9, 0.5, 0.2), 2.5, 0.6),       # a fixed proposal rate ("proposal")
    ((1.0, 1.2, 4.0), (0.8, 0.8, 0.8), 6.0, None),      # deep: the surface is rarely reached
    ((1e-3, 2e-3, 4e-3), (0.9, 0.9, 0.9), 2.0, None),   # thin: q floored at Q_MIN
    ((0.0, 0.0, 0.0), (0.9, 0.9, 0.9), 2.0, None),      # sigma_t = 0: no fog, still unbiased
])
def test_weights_are_unbiased(sigma_t, albedo, s, sh):
    """E[estimate] = int_0^s sigma_s e^{-sigma_t t} f(t) dt + e^{-sigma_t s} f_s, where the estimate is
    `medium_weight * f(t)` on the medium branch (probability q) and `surface_weight * f_s` on the surface branch
    (probability 1 - q). Float64 reference by scipy quad; tolerance 4 SE per channel."""
    sigma_t = np.asarray(sigma_t, np.float64)
    sigma_s = sigma_t * np.asarray(albedo)
    st, ss = jnp.asarray(sigma_t, f32), jnp.asarray(sigma_s, f32)
    sh = float(M.sampling_extinction(st)) if sh is None else sh
    u = uniforms(5)
    t, is_med, q, log1mq = free_flight(u, sh, s)
    w_med = np.asarray(jax.vmap(lambda tt: M.medium_weight(st, ss, f32(sh), tt, f32(s), f32(q)))(jnp.asarray(t, f32)),
                       np.float64)
    w_surf = np.asarray(M.surface_weight(st, f32(s), f32(log1mq)), np.float64)
    est = np.where(is_med[:, None], w_med * f_medium(t), w_surf * F_SURFACE)
    assert np.all(np.isfinite(est))
    ref = np.array([integrate.quad(lambda x: sigma_s[c] * np.exp(-sigma_t[c] * x) * f_medium(x)[c], 0.0, s,
                                   epsabs=1e-13)[0] for c in range(3)]) + np.exp(-sigma_t * s) * F_SURFACE
    se = est.std(axis=0, ddof=1) / np.sqrt(len(est))
    assert np.all(np.abs(est.mean(0) - ref) <= 4 * se + 1e-6 * np.abs(ref)), (est.mean(0), ref, se)
    # the two parts separately: E[w_med f | medium] q and E[w_surf] (1 - q)
    part_med = np.where(is_med[:, None], w_med * f_medium(t), 0.0)
    ref_med = ref - np.exp(-sigma_t * s) * F_SURFACE
    se_med = part_med.std(axis=0, ddof=1) / np.sqrt(len(est))
    assert np.all(np.abs(part_med.mean(0) - ref_med) <= 4 * se_med + 1e-6 * np.abs(ref_med))
    np.testing.assert_allclose(w_surf * np.exp(log1mq), np.exp(-sigma_t * s), rtol=1e-5)


def test_medium_pdf_is_the_sampling_density():
    """`medium_pdf` integrates to q over [0, s], and `medium_weight = sigma_s exp(-sigma_t t) / medium_pdf`."""
    sigma_t = jnp.array([0.3, 0.8, 1.5], f32)
    sigma_s = sigma_t * 0.7
    s = 2.5
    for sh in (0.3, 0.6, 1e-6):
        q, _ = M.branch_probability(f32(sh), f32(s))
        x, w = np.polynomial.legendre.leggauss(40)
        nodes = 0.5 * s * (x + 1)
        pdf = np.asarray(jax.vmap(lambda tt: M.medium_pdf(tt, f32(sh), f32(s), q))(jnp.asarray(nodes, f32)))
        assert float(np.sum(pdf * 0.5 * s * w)) == pytest.approx(float(q), rel=1e-5)
        wm = np.asarray(jax.vmap(lambda tt: M.medium_weight(sigma_t, sigma_s, f32(sh), tt, f32(s), q))(
            jnp.asarray(nodes, f32)), np.float64)
        s64, t64 = np.asarray(sigma_s, np.float64), np.asarray(sigma_t, np.float64)
        expected = s64 * np.exp(-np.outer(nodes, t64)) / pdf[:, None]
        np.testing.assert_allclose(wm, expected, rtol=1e-4)


def test_deep_fog_weights_do_not_underflow():
    """Optical depth 1000 (far beyond float32 exp's range): the surface weight is exp(-(sigma_c - sh) s), exact
    ratios, no 0/0; medium weights stay finite."""
    sigma_t = jnp.array([100.0, 101.0, 110.0], f32)
    s = 10.0
    sh = M.sampling_extinction(sigma_t)
    q, log1mq = M.branch_probability(sh, f32(s))
    w = np.asarray(M.surface_weight(sigma_t, f32(s), log1mq), np.float64)
    np.testing.assert_allclose(w, np.exp(-np.array([0.0, 1.0, 10.0]) * s), rtol=1e-4, atol=1e-37)  # float32 range
    wm = np.asarray(M.medium_weight(sigma_t, 0.5 * sigma_t, sh, f32(9.0), f32(s), q), np.float64)
    assert np.all(np.isfinite(wm))
    # sigma_s / sh * exp(-(sigma_c - sh) t) * (1 - exp(-sh s)) / q; the last channel's exp(-90) is below float32 range
    np.testing.assert_allclose(wm, 0.5 * np.array([100.0, 101.0, 110.0]) / 100.0 * np.exp(-np.array([0, 1, 10]) * 9.0),
                               rtol=1e-4, atol=1e-37)


# ------------------------------------------------------------------------------------------------ transmittance
def test_transmittance():
    """Beer–Lambert exp(-sigma d) per channel, including d = 0 and d = inf (0 for sigma > 0, 1 for sigma = 0), with
    a finite gradient w.r.t. sigma everywhere."""
    sigma = jnp.array([0.0, 0.5, 2.0], f32)
    for d in (0.0, 0.3, 10.0, 100.0):
        np.testing.assert_allclose(M.transmittance(sigma, f32(d)), np.exp(-np.array([0.0, 0.5, 2.0]) * d), rtol=1e-6,
                                   atol=1e-37)  # atol: below float32's normal range
        jac = jax.jacfwd(M.transmittance)(sigma, f32(d))
        np.testing.assert_allclose(np.diag(jac), -d * np.exp(-np.array([0.0, 0.5, 2.0]) * d), rtol=1e-5, atol=1e-30)
    np.testing.assert_array_equal(M.transmittance(sigma, f32(np.inf)), [1.0, 0.0, 0.0])
    for jac in (jax.jacfwd(M.transmittance)(sigma, f32(np.inf)), jax.jacrev(M.transmittance)(sigma, f32(np.inf))):
        assert np.all(np.isfinite(jac)), jac
