"""Two-term HG, Draine and the fog-droplet phase function (Jendersie & d'Eon 2023): distribution properties,
the droplet fits at d = 10 µm, finite values and gradients at the ends of every parameter's range, and single
scattering renders against the float64 quadrature of tests/test_render_analytic.py.

Float64 references evaluate the phase functions from their formulas (with the droplet's four parameters taken from
`droplet_parameters` in float32 and widened: the fits themselves are checked separately). Samples use fixed numpy
seeds; tolerances are stated in standard errors (SE).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate, stats

import jaxfog as jf
from jaxfog._phase import droplet_parameters

f32 = jnp.float32
N_SAMPLES = 200_000


def hg64(mu, g):
    return (1.0 - g * g) / (4.0 * np.pi * (1.0 + g * g - 2.0 * g * mu) ** 1.5)


def draine64(mu, g, a):
    return hg64(mu, g) * (1.0 + a * mu * mu) / (1.0 + a * (1.0 + 2.0 * g * g) / 3.0)


def phase64(phase):
    """A float64 function of cos theta for the phase function Module `phase`."""
    if isinstance(phase, jf.TwoTermHG):
        g1, g2, w = (float(x) for x in (phase.g1, phase.g2, phase.w))
        return lambda mu: w * hg64(mu, g1) + (1 - w) * hg64(mu, g2)
    if isinstance(phase, jf.Draine):
        g, a = float(phase.g), float(phase.alpha)
        return lambda mu: draine64(mu, g, a)
    g_hg, g_d, a, w = (float(x) for x in phase.parameters)
    return lambda mu: (1 - w) * hg64(mu, g_hg) + w * draine64(mu, g_d, a)


def quad_nodes():
    """Gauss–Legendre nodes and weights in 1 - cos on [0, 2], intervals geometric toward both poles."""
    lo = np.geomspace(1e-12, 1.0, 48)
    edges = np.unique(np.concatenate([[0.0], lo, 2.0 - lo[::-1], [2.0]]))
    x, w = np.polynomial.legendre.leggauss(16)
    a, b = edges[:-1, None], edges[1:, None]
    return (0.5 * (b - a) * (x + 1) + a).reshape(-1), (0.5 * (b - a) * w).reshape(-1)


PHASES = {
    "two_term": jf.TwoTermHG(0.8, -0.4, 0.7),
    "two_term_sharp": jf.TwoTermHG(0.99, -0.9, 0.2),
    "draine_d10": jf.Draine(0.5556713, 21.995522),
    "draine_rayleigh_like": jf.Draine(0.3, 1.0),
    "draine_small_g": jf.Draine(0.02, 22.0),
    "droplet_0.05": jf.Droplet(0.05),
    "droplet_0.8": jf.Droplet(0.8),
    "droplet_3": jf.Droplet(3.0),
    "droplet_10": jf.Droplet(10.0),
    "droplet_50": jf.Droplet(50.0),
}


@pytest.mark.parametrize("name", list(PHASES))
def test_integrates_to_one_and_matches_float64(name):
    """2 pi int p d(cos) = 1 to 1e-5 (float32 evaluation), and eval equals the float64 formula to 1e-5 relative."""
    ph = PHASES[name]
    nodes, weights = quad_nodes()
    p = np.asarray(jax.vmap(ph.eval_polar)(jnp.asarray(nodes, f32)), np.float64)
    assert 2 * np.pi * np.sum(p * weights) == pytest.approx(1.0, abs=1e-5)
    ref = phase64(ph)(1.0 - np.asarray(nodes, np.float32).astype(np.float64))
    np.testing.assert_allclose(p, ref, rtol=2e-5)


def sample_omc(ph, seed, n=N_SAMPLES):
    u = jnp.asarray(np.random.default_rng(seed).random(n, dtype=np.float32))
    pol = jax.jit(jax.vmap(ph.sample_polar))(u)
    return np.asarray(pol.one_minus_cos, np.float64), np.asarray(pol.one_plus_cos, np.float64)


@pytest.mark.parametrize("name", list(PHASES))
def test_sampler_matches_pdf_chi_square(name):
    """Histogram of 1 - cos (40 bins, geometric toward the forward peak, so the droplet's HG peak is resolved)
    against bin probabilities integrated from `pdf_polar` (the sampling density); p-value > 1e-4 (fixed seed)."""
    ph = PHASES[name]
    omc, opc = sample_omc(ph, seed=31)
    assert np.all(np.isfinite(omc)) and np.all((omc >= 0) & (omc <= 2)) and np.allclose(omc + opc, 2.0, atol=1e-6)
    edges = np.concatenate([[0.0], np.geomspace(1e-5, 2.0, 40)])
    x, w = np.polynomial.legendre.leggauss(32)  # per bin; the pdf is smooth inside each (geometric) bin
    a, b = edges[:-1, None], edges[1:, None]
    nodes = 0.5 * (b - a) * (x + 1) + a
    pdf = np.asarray(jax.jit(jax.vmap(ph.pdf_polar))(jnp.asarray(nodes.reshape(-1), f32)), np.float64)
    probs = 2 * np.pi * np.sum(pdf.reshape(nodes.shape) * 0.5 * (b - a) * w, axis=1)
    assert probs.sum() == pytest.approx(1.0, abs=1e-4)
    obs, _ = np.histogram(omc, edges)
    keep = probs * len(omc) > 20
    exp = probs[keep] / probs[keep].sum() * obs[keep].sum()
    chi2 = np.sum((obs[keep] - exp) ** 2 / exp)
    assert stats.chi2.sf(chi2, keep.sum() - 1) > 1e-4, (chi2, keep.sum())


@pytest.mark.parametrize("name", list(PHASES))
def test_mean_cosine_matches_quadrature(name):
    """E[cos] of the weighted samples (`eval / pdf`) equals the float64 quadrature of cos p, within 4 SE."""
    ph = PHASES[name]
    omc, opc = sample_omc(ph, seed=32)
    w = np.asarray(jax.vmap(lambda x: ph.eval_polar(x) / ph.pdf_polar(x))(jnp.asarray(omc, f32)), np.float64)
    mu = 0.5 * (opc - omc)
    est = mu * w
    ref = integrate.quad(lambda m: 2 * np.pi * m * phase64(ph)(m), -1, 1, points=[0.9, 0.99, 0.999], limit=400)[0]
    assert abs(est.mean() - ref) <= 4 * est.std(ddof=1) / np.sqrt(len(est)), (est.mean(), ref)


def test_two_term_mean_cosine_formula():
    ph = jf.TwoTermHG(0.8, -0.4, 0.7)
    ref = integrate.quad(lambda m: 2 * np.pi * m * phase64(ph)(m), -1, 1, limit=200)[0]
    assert ref == pytest.approx(0.7 * 0.8 + 0.3 * -0.4, abs=1e-7)  # float32 parameters


def test_droplet_parameters_at_10um():
    """docs models: at d = 10 µm, g_HG = 0.988, g_D = 0.556, alpha = 22.0, w_D = 0.482 (three digits)."""
    g_hg, g_d, a, w = (float(x) for x in droplet_parameters(f32(10.0)))
    assert g_hg == pytest.approx(0.988, abs=5e-4)
    assert g_d == pytest.approx(0.556, abs=5e-4)
    assert a == pytest.approx(22.0, abs=5e-2)
    assert w == pytest.approx(0.482, abs=5e-4)


def test_droplet_is_sharper_forward_than_hg_with_the_same_mean_cosine():
    """At 10 µm the droplet's forward peak is far above that of HG with the same E[cos], and it has a glory:
    more backscatter at 180 degrees than HG."""
    ph = jf.Droplet(10.0)
    mean_cos = integrate.quad(lambda m: 2 * np.pi * m * phase64(ph)(m), -1, 1, points=[0.99, 0.999], limit=400)[0]
    assert float(ph.eval_polar(f32(0.0))) > 20 * hg64(1.0, mean_cos)
    assert float(ph.eval_polar(f32(2.0))) > hg64(-1.0, mean_cos)


# ------------------------------------------------------------------------------------- ends of the parameter ranges
def _check_finite(fn, params):
    val = fn(*params)
    grads = jax.grad(lambda *p: fn(*p), argnums=tuple(range(len(params))))(*params)
    assert np.isfinite(float(val)), val
    assert all(np.isfinite(float(g)) for g in grads), grads


@pytest.mark.parametrize("g1, g2, w", [(-0.999, 0.999, 0.0), (0.999, -0.999, 1.0), (0.0, 0.0, 0.5),
                                       (0.9999, 0.9999, 1.0), (-0.9999, -0.9999, 0.0)])
def test_two_term_finite_at_range_ends(g1, g2, w):
    """eval, pdf and the sampled 1 - cos (u at both ends of [0, 1)) with their gradients w.r.t. (g1, g2, w)."""
    for omc in (0.0, 1.0, 2.0):
        _check_finite(lambda a, b, c: jf.TwoTermHG(a, b, c).eval_polar(f32(omc)), (f32(g1), f32(g2), f32(w)))
    for u in (0.0, 0.5, 1.0 - 2.0**-24):
        _check_finite(lambda a, b, c: jf.TwoTermHG(a, b, c).sample_polar(f32(u)).one_minus_cos,
                      (f32(g1), f32(g2), f32(w)))


@pytest.mark.parametrize("d", [1e-4, 0.1, 0.1001, 1.4999, 1.5, 4.81, 4.9999, 5.0, 10.0, 50.0])
def test_droplet_finite_at_range_ends(d):
    """Droplet eval and sampled 1 - cos with the gradient w.r.t. the diameter at the ends of every fit range and at
    the pole of tan(ln d) inside 1.5..5 (d = e^(pi/2) = 4.81)."""
    for omc in (0.0, 1e-4, 1.0, 2.0):
        _check_finite(lambda x: jf.Droplet(x).eval_polar(f32(omc)), (f32(d),))
    for u in (0.0, 0.3, 0.7, 1.0 - 2.0**-24):
        _check_finite(lambda x: jf.Droplet(x).sample_polar(f32(u)).one_minus_cos, (f32(d),))


def test_invalid_parameters_are_rejected():
    for bad in (lambda: jf.TwoTermHG(1.0, 0.0, 0.5), lambda: jf.TwoTermHG(0.0, 0.0, 1.5), lambda: jf.Droplet(0.0),
                lambda: jf.Droplet(51.0), lambda: jf.Draine(0.5, 0.0)):
        with pytest.raises(ValueError, match="outside the valid range"):
            bad()


def test_split_uniform_stays_below_one():
    from jaxfog._sampling import split_uniform

    u = jnp.asarray(np.concatenate([np.random.default_rng(3).random(10000, dtype=np.float32),
                                    [0.0, 1.0 - 2.0**-24]]).astype(np.float32))
    for w in (0.0, 1e-7, 0.3, 0.7, 1.0 - 2.0**-24, 1.0):
        first, v = jax.vmap(lambda x: split_uniform(x, f32(w)))(u)
        v = np.asarray(v)
        assert np.all((v >= 0) & (v < 1)), w


# ------------------------------------------------------------------------------------- single scattering renders
@pytest.mark.parametrize("name", ["two_term", "droplet_10"])
def test_single_scattering_matches_quadrature(fog, stats, name):
    """max_depth 2, two point lights, no surfaces, RGB fog (tests/test_render_analytic.py's scene): each pixel
    equals the float64 quadrature of the in-scattering integral with this phase function."""
    from test_render_analytic import SS_ALBEDO, SS_BATCH, SS_CAMERA, SS_POINTS, SS_SIGMA_T, single_scatter_reference

    ph = PHASES[name]
    ref = single_scatter_reference(SS_CAMERA, 3, SS_POINTS, SS_SIGMA_T, SS_ALBEDO, phase64(ph))
    lights = tuple(jf.PointLight(p, i) for p, i, _ in SS_POINTS)
    scene = jf.Scene(camera=SS_CAMERA.build(), lights=lights,
                     medium=jf.HomogeneousMedium(SS_SIGMA_T, SS_ALBEDO, ph), max_depth=2)
    mean, se = stats.mean_and_se(stats.render_keys(scene, 16, seed=41, batch_paths=SS_BATCH))
    stats.assert_statistically_equal(mean, se, ref, label=f"single scatter {name}")
