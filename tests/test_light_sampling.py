"""Sampling toward point and spot lights: the light-angle lobe's sampler against its pdf, the pdf's values and
gradients at the poles, and multiple-scattering renders with and without the variance-reduction techniques
(equiangular sampling, the light-angle lobe, the equiangular/free-flight distance mixture), which must change the
noise and never the expected image."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfog as jf
from jaxfog._sampling import light_lobe_pdf, light_lobe_sample
from jaxfog._math import safe_normalize

from helpers import FLOOR_CAMERA, make_floor

X = jnp.array([0.3, -0.2, 0.5], jnp.float32)
LIGHT = jnp.array([-0.4, 1.1, 0.9], jnp.float32)
_PDF = jax.jit(jax.vmap(light_lobe_pdf, (0, None, None)))


def _frame(a):
    """Orthonormal (s, t) perpendicular to unit a (float64)."""
    s = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
    s /= np.linalg.norm(s)
    return s, np.cross(a, s)


def _axis():
    a = np.asarray(LIGHT - X, np.float64)
    return a / np.linalg.norm(a)


def _directions(alpha, phi):
    """Unit directions at angle alpha to the light axis, azimuth phi (float64 numpy, (n, 3))."""
    a = _axis()
    s, t = _frame(a)
    return (np.sin(alpha)[:, None] * (np.cos(phi)[:, None] * s + np.sin(phi)[:, None] * t)
            + np.cos(alpha)[:, None] * a)


def test_light_lobe_pdf_is_its_formula_and_integrates_to_one():
    alpha = np.linspace(1e-3, np.pi - 1e-3, 2001)
    w = jnp.asarray(_directions(alpha, np.full_like(alpha, 0.7)), jnp.float32)
    pdf = np.asarray(_PDF(w, X, LIGHT), np.float64)
    np.testing.assert_allclose(pdf, (np.pi - alpha) / (np.pi**3 * np.sin(alpha)), rtol=2e-4)
    # over the sphere: integral of pdf * 2 pi sin(alpha) d alpha (Gauss-Legendre; the integrand is smooth)
    nodes, weights = np.polynomial.legendre.leggauss(64)
    a = 0.5 * np.pi * (nodes + 1.0)
    wq = jnp.asarray(_directions(a, np.full_like(a, 2.1)), jnp.float32)
    pq = np.asarray(_PDF(wq, X, LIGHT), np.float64)
    total = 0.5 * np.pi * np.sum(weights * pq * 2.0 * np.pi * np.sin(a))
    assert abs(total - 1.0) < 1e-5, total


def test_light_lobe_samples_follow_its_pdf():
    """Chi-square of 400k samples in 24 bins of alpha (expected counts from quadrature of `light_lobe_pdf`, not from
    the sampler's inverse cdf) and 16 bins of the azimuth. Threshold: dof + 6 sqrt(2 dof) (a 6-sigma excursion of
    the statistic; fixed seed)."""
    n = 400_000
    u = jax.random.uniform(jax.random.key(11), (n, 2))
    w = np.asarray(jax.jit(jax.vmap(light_lobe_sample, (0, None, None)))(u, X, LIGHT), np.float64)
    np.testing.assert_allclose(np.linalg.norm(w, axis=1), 1.0, atol=3e-6)
    a = _axis()
    s, t = _frame(a)
    alpha = np.arccos(np.clip(w @ a, -1.0, 1.0))
    phi = np.arctan2(w @ t, w @ s)

    edges = np.linspace(0.0, np.pi, 25)
    nodes, weights = np.polynomial.legendre.leggauss(16)
    expected = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        al = lo + 0.5 * (hi - lo) * (nodes + 1.0)
        wq = jnp.asarray(_directions(al, np.full_like(al, 0.3)), jnp.float32)
        pq = np.asarray(_PDF(wq, X, LIGHT), np.float64)
        expected.append(0.5 * (hi - lo) * np.sum(weights * pq * 2.0 * np.pi * np.sin(al)))
    expected = n * np.asarray(expected)
    assert abs(expected.sum() / n - 1.0) < 1e-5
    counts, _ = np.histogram(alpha, edges)
    chi2 = np.sum((counts - expected) ** 2 / expected)
    dof = len(counts) - 1
    assert chi2 <= dof + 6 * np.sqrt(2 * dof), (chi2, counts, expected)

    counts_phi, _ = np.histogram(phi, np.linspace(-np.pi, np.pi, 17))
    chi2_phi = np.sum((counts_phi - n / 16) ** 2 / (n / 16))
    assert chi2_phi <= 15 + 6 * np.sqrt(30), chi2_phi


@pytest.mark.parametrize("alpha", [0.0, 1e-4, 0.3, np.pi / 2, np.pi - 1e-3, np.pi])
def test_light_lobe_pdf_value_and_gradient_are_finite_at_the_poles(alpha):
    w = jnp.asarray(_directions(np.array([alpha]), np.array([0.4]))[0], jnp.float32)
    if alpha == 0.0:  # exactly toward the light, as the sampler computes that axis
        w = safe_normalize(LIGHT - X)
    v = light_lobe_pdf(w, X, LIGHT)
    gw, gx = jax.grad(light_lobe_pdf, argnums=(0, 1))(w, X, LIGHT)
    assert np.isfinite(v) and v >= 0
    assert np.all(np.isfinite(gw)) and np.all(np.isfinite(gx))
    if alpha == 0.0:  # the infinite peak itself (probability 0; sin alpha exactly 0 here) is reported as 0, never inf
        on_axis = light_lobe_pdf(jnp.array([0.0, 0.0, 1.0]), jnp.zeros(3), jnp.array([0.0, 0.0, 2.0]))
        assert on_axis == 0.0
    elif alpha > 3.0:
        assert abs(float(v) * np.pi**3 - 1.0) < 2e-3  # its limit 1 / pi^3 at alpha = pi, continuously


# ------------------------------------------------------------------------------- the techniques are unbiased
FOG_BOX = ((-20.0, -1.0, -20.0), (20.0, 0.6, 20.0))
"""The fog of the render tests below: a slab 0.6 deep over the floor (which lies inside it), 0.3 below the point
light (y = 0.9), 0.6 below the spot (y = 1.2) and 1.0 below the area light: no path vertex, equiangular sample or
segment in fog comes near a light, so every path's contribution is bounded and every estimator's variance finite.
In fog around a point or spot light, plain free flight with light sampling has an infinite variance from max_depth
3 on (estimators.md), and so has the light-angle lobe drawn wholly from the phase function (`phase_lobe = 1`: its
density in the angle alpha to the light is ~constant near 0, so it no longer cancels the ~1/D of the light
scattered along a segment passing at D from the light); their per-key means then have no honest standard error.
Measured without the box, 32-spp or 1024-spp per-key means of 4 x 4-pixel blocks: free flight (spot, 256 keys at
1024 spp) skewness 5.9 (median over the 36 values) and excess kurtosis 47, still 4.7 and 32 at 4096 spp; the
droplet scene at 32 spp (4096 keys) 8.7 / 165 with `phase_lobe = 0`, 13.5 / 325 with `phase_lobe = 1` (one key's
block mean 4749x the median), 8.9 / 157 with the default."""


def _fog_scene(light):
    """Floor in RGB fog (`FOG_BOX`) lit by a point or spot light inside the view, max_depth 5 (four scattering
    vertices: the lobe and the mixture act on every one of them)."""
    lights = {"point": jf.PointLight((0.3, 0.9, -0.2), 4.0),
              "spot": jf.SpotLight((0.3, 1.2, -0.2), (0.2, -1.0, 0.1), 4.0, cutoff_angle=25.0, beam_width=15.0)}
    return jf.Scene(camera=FLOOR_CAMERA.build(), shapes=(make_floor(),), lights=(lights[light],),
                    medium=jf.HomogeneousMedium(sigma_t=(0.5, 0.7, 0.9), albedo=0.9, phase=jf.HenyeyGreenstein(0.5),
                                                bounds=FOG_BOX),
                    max_depth=5)


@pytest.mark.parametrize("light", [pytest.param("point", marks=pytest.mark.slow), pytest.param("spot", marks=pytest.mark.slow)])
def test_variance_reduction_does_not_change_the_expected_image(stats, light):
    """The default techniques, and the lobe and the mixture both at a high probability (0.7, so that an error in
    their pdfs would dominate), against plain free flight with light sampling at every vertex, per pixel (192 pixels
    x 3 channels); 32 independent renders on each side (the techniques at 512 spp, free flight at 1024 spp), the
    reference's own SE included. The point light checks the same without the spot's cone.

    Honest standard errors (`assert_statistically_equal` assumes per-key means close to normal):
    - the fog is `FOG_BOX`, away from the light: in fog around it free flight's variance is infinite, and its
      32-key means were low with too small an SE (measured on the spot scene without the box, 4 x 4-pixel blocks:
      8 disjoint 32-key subsets of 1024-spp free flight all had a negative mean z per channel, -0.05 to -1.35,
      against the pooled mean of 1024 keys of the two other estimators; the former version of this test, which
      compared 32 x 64 spp against 32 x 1024 spp free flight, failed with a mean z of +0.34/+0.53/+0.64 for the
      lobe and mixture at 0.7 and had +0.52/+0.73/+0.79 for the default, while those two agreed with each other:
      512 keys each, mean z^2 1.03, max |z| 2.1);
    - with the box, the lobe and the mixture at 0.7 still give rare large (bounded: ~1/0.3 a vertex) weights: their
      per-key 4 x 4-block means at 64 spp had skewness 1.8 (median; spot), 0.9 at 256 spp and 0.55 at 512 spp,
      falling like 1/sqrt(spp) (a bounded weight); hence 512 spp;
    - per pixel rather than in 12 blocks: with 36 values, one block beyond |z| = 3 in two channels (P ~ 3% for
      normal data) already exceeds the helper's 3% of the values; with 576 values its thresholds hold as derived.
    Measured over independent replicates of this design (fog box): spot, 64 replicates of each comparison (seeds
    131-133, 2048 keys a side), no failure, mean z^2 1.05-1.06 (t: 1.07), P(|z| > 3) 0.35-0.47% (t: 0.53%), mean z
    -0.06 for the lobe and mixture at 0.7 (their per-pixel skewness, 2.3 at 512 spp; the helper allows |mean z| up
    to 0.30) and +0.02 for the default; in 4 x 4-pixel blocks 5 of the 128 comparisons failed (the 3% rule). Point
    light (512 spp as eight 64-spp keys), 16 replicates of each comparison, no failure, mean z^2 1.03-1.07, P(|z| >
    3) 0.3-0.4%. The three estimators agree in the spot scene's image mean to 4e-4 (4096 / 4096 / 1024 keys,
    |z| < 0.9). ~30 s a light on 2 busy cores."""
    scene = _fog_scene(light)
    off = stats.render_keys(scene, 1024, seed=31, equiangular=False, light_lobe=0.0, distance_mix=0.0)
    m0, s0 = stats.mean_and_se(off)
    for i, kw in enumerate([{}, dict(light_lobe=0.7, distance_mix=0.7)]):
        m, s = stats.mean_and_se(stats.render_keys(scene, 512, seed=32 + i, **kw))
        stats.assert_statistically_equal(m, s, m0, ref_se=s0, label=f"{light} {kw or 'default'}")


def _droplet_scene(diameter: float, phase=None):
    """Floor in grey fog (`FOG_BOX`) of droplets (`diameter` um; or the phase function `phase`) lit by a point light
    inside the view and a small area light facing down (the lobe's density enters the area light's MIS weights),
    max_depth 4."""
    lights = (jf.PointLight((0.3, 0.9, -0.2), 4.0),
              jf.AreaLight((-0.6, 1.6, -0.4), (0.6, 0.0, 0.0), (0.0, 0.0, 0.4), 2.0))  # front face -y (down)
    return jf.Scene(camera=FLOOR_CAMERA.build(), shapes=(make_floor(),), lights=lights,
                    medium=jf.HomogeneousMedium(sigma_t=0.6, albedo=0.9, phase=phase or jf.Droplet(diameter),
                                                bounds=FOG_BOX),
                    max_depth=4)


@pytest.mark.slow
def test_phase_lobe_does_not_change_the_expected_image(stats):
    """The light-angle lobe drawing all its directions from the phase function about the direction to the light
    (`phase_lobe = 1`, with `light_lobe = 0.7`, so that an error in that density would dominate) against the lobe's
    angle profile alone (`phase_lobe = 0`) and against the default (droplets: half and half), in fog (`FOG_BOX`)
    of 3 um droplets (g_HG 0.95, a peak the angle profile still samples with moderate noise), per pixel (192 x 3
    values), 32 independent renders a side at 128 spp, both sides' SEs.

    Honest standard errors: in fog around the point light all three were heavy-tailed (32-spp per-key means of 4 x
    4-pixel blocks, 4096 keys each: skewness 8.7-13.5 (median), excess kurtosis 157-325; one `phase_lobe = 1` key's
    block mean 4749x the median: with the phase function's polar law about the light, whose density is ~constant at
    small angles, nothing cancels the ~1/D of the light scattered along a segment passing at D from the light, so its
    variance is infinite), and every disjoint 32-key subset had a mean z per channel of -1.9 to -4.3 against the
    pooled mean: no SE from 32 keys was honest (the former version failed with z = -3.08 in one block near the
    light). In the box the same per-key block means had skewness 0.2-0.5 and kurtosis 0.1-0.5, the three estimates
    agreed (4096 keys each: mean z^2 0.64-1.03, max |z| <= 2.3), and over independent replicates of this design (32
    per comparison, per pixel, each 128-spp key four 32-spp keys) no comparison failed, with mean z^2 1.04 (t: 1.07)
    and P(|z| > 3) 0.3-0.4% (t: 0.5%); at 32 spp the reference's per-pixel skewness (1.8) shifted the mean z by
    +0.05-0.07, at 128 spp by +0.02-0.03. Per pixel rather than in 12 blocks: with 36 values one block beyond |z| = 3
    in two channels (P ~ 3% for normal data; measured 6 of 256 replicates) already fails the helper's 3% of the
    values. ~25 s on 2 busy cores."""
    scene = _droplet_scene(3.0)
    off = stats.render_keys(scene, 128, seed=41, sampling=jf.SamplingOptions(phase_lobe=0.0))
    m0, s0 = stats.mean_and_se(off)
    for i, opts in enumerate([jf.SamplingOptions(light_lobe=0.7, phase_lobe=1.0), jf.SamplingOptions()]):
        m, s = stats.mean_and_se(stats.render_keys(scene, 128, seed=42 + i, sampling=opts))
        stats.assert_statistically_equal(m, s, m0, ref_se=s0, label=f"phase lobe {opts}")


def test_phase_lobe_default_only_for_sharply_peaked_phase_functions():
    """`phase_lobe=None` resolves to `PEAKED_PHASE_LOBE` for droplets and to 0 for HG (whose program, and so its
    images, it leaves as they were); it is 0 without the light-angle lobe or fog, and an explicit value wins."""
    from jaxfog._integrator import PEAKED_PHASE_LOBE, make_tracer
    from jaxfog._scene import pack

    scene = _droplet_scene(8.0)
    hg = _droplet_scene(0.0, jf.HenyeyGreenstein(0.9))
    tr = lambda sc, **kw: make_tracer(sc, pack(sc), jf.SamplingOptions(**kw))  # noqa: E731
    assert tr(scene).phase_lobe == PEAKED_PHASE_LOBE > 0 and tr(hg).phase_lobe == 0.0
    assert tr(scene, light_lobe=0.0).phase_lobe == 0.0 and tr(hg, phase_lobe=0.25).phase_lobe == 0.25
    assert tr(scene, estimator="reparam").phase_lobe == 0.0 and tr(scene, phase_lobe=0.0).phase_lobe == 0.0
    no_fog = jf.Scene(camera=scene.camera, shapes=scene.shapes, lights=scene.lights, max_depth=4)
    assert tr(no_fog, phase_lobe=1.0).phase_lobe == 0.0
