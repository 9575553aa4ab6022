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

from helpers import FLOOR_CAMERA, block_mean, make_floor

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
def _fog_scene(light):
    """Floor in RGB fog lit by a point or spot light inside the view, max_depth 5 (four scattering vertices: the lobe
    and the mixture act on every one of them)."""
    lights = {"point": jf.PointLight((0.3, 0.9, -0.2), 4.0),
              "spot": jf.SpotLight((0.3, 1.2, -0.2), (0.2, -1.0, 0.1), 4.0, cutoff_angle=25.0, beam_width=15.0)}
    return jf.Scene(camera=FLOOR_CAMERA.build(), shapes=(make_floor(),), lights=(lights[light],),
                    medium=jf.HomogeneousMedium(sigma_t=(0.5, 0.7, 0.9), albedo=0.9, phase=jf.HenyeyGreenstein(0.5)),
                    max_depth=5)


def _blocks(imgs, b=4):
    """Means over b x b pixel blocks: (keys, H/b, W/b, 3)."""
    return block_mean(imgs, b)


@pytest.mark.parametrize("light", [pytest.param("point", marks=pytest.mark.slow), pytest.param("spot", marks=pytest.mark.slow)])
def test_variance_reduction_does_not_change_the_expected_image(stats, light):
    """The default techniques, and the lobe and the mixture both at a high probability (0.7, so that an error in
    their pdfs would dominate), against plain free flight with light sampling at every vertex, on 4 x 4-pixel block
    means (12 blocks x 3 channels); 32 independent renders on each side (64 spp; the reference 1024 spp), the
    reference's own SE included. Blocks and the reference's 1024 spp because free flight's estimate near a light in
    fog is heavy-tailed (its variance diverges from max_depth 3 on, estimators.md), so at fewer samples its
    per-key means are skewed low with too small an SE: measured on the spot scene, free flight 0.00623 +- 0.00006
    at 32 x 256 spp (z = -3.4 against the default's 0.00646 +- 0.00003) but 0.006369 +- 0.000038 at 64 x 1024 spp
    (z = -1.1 against 0.006417 +- 0.000019). The point light (slow) checks the same without the spot's cone."""
    scene = _fog_scene(light)
    off = _blocks(stats.render_keys(scene, 1024, seed=31, equiangular=False, light_lobe=0.0, distance_mix=0.0))
    m0, s0 = stats.mean_and_se(off)
    for i, kw in enumerate([{}, dict(light_lobe=0.7, distance_mix=0.7)]):
        m, s = stats.mean_and_se(_blocks(stats.render_keys(scene, 64, seed=32 + i, **kw)))
        stats.assert_statistically_equal(m, s, m0, ref_se=s0, label=f"{light} {kw or 'default'}")


def _droplet_scene(diameter: float, phase=None):
    """Floor in grey fog of droplets (`diameter` um; or the phase function `phase`) lit by a point light inside the
    view and a small area light facing down (the lobe's density enters the area light's MIS weights), max_depth 4."""
    lights = (jf.PointLight((0.3, 0.9, -0.2), 4.0),
              jf.AreaLight((-0.6, 1.6, -0.4), (0.6, 0.0, 0.0), (0.0, 0.0, 0.4), 2.0))  # front face -y (down)
    return jf.Scene(camera=FLOOR_CAMERA.build(), shapes=(make_floor(),), lights=lights,
                    medium=jf.HomogeneousMedium(sigma_t=0.6, albedo=0.9, phase=phase or jf.Droplet(diameter)),
                    max_depth=4)


@pytest.mark.slow
def test_phase_lobe_does_not_change_the_expected_image(stats):
    """The light-angle lobe drawing all its directions from the phase function about the direction to the light
    (`phase_lobe = 1`, with `light_lobe = 0.7`, so that an error in that density would dominate) against the lobe's
    angle profile alone (`phase_lobe = 0`) and against the default (droplets: half and half), in fog of 3 um
    droplets (g_HG 0.95, a peak the angle profile still samples with moderate noise), 4 x 4-pixel block means
    (12 blocks x 3 channels), 32 independent renders a side at 32 spp, both sides' SEs. ~1-2 minutes on 2 busy
    cores (three compilations of a max_depth 4 scene with an area light)."""
    scene = _droplet_scene(3.0)
    off = _blocks(stats.render_keys(scene, 32, seed=41, sampling=jf.SamplingOptions(phase_lobe=0.0)))
    m0, s0 = stats.mean_and_se(off)
    for i, opts in enumerate([jf.SamplingOptions(light_lobe=0.7, phase_lobe=1.0), jf.SamplingOptions()]):
        m, s = stats.mean_and_se(_blocks(stats.render_keys(scene, 32, seed=42 + i, sampling=opts)))
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
