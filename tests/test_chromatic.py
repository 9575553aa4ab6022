"""Chromatic media: one-sample spectral MIS over the three channels (`jaxfog._medium`, docs/estimators.md).

(1) the free-flight decision and its weights, exactly as the tracer calls them, are unbiased for every channel
against float64 quadrature (fixed numpy seeds, 4 SE); (2) a render of an RGB medium equals, channel by channel, the
render of a grey medium with that channel's values (z-test over keys, `conftest.assert_statistically_equal`, both
sides estimates); (3) equal channels reproduce the grey scheme's decisions bit for bit, so a grey medium, which
compiles no spectral MIS by default, renders the image spectral MIS would give, up to float32 rounding.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate

import jaxfog as jf
from helpers import REPO, assert_same_render_up_to_rounding
from jaxfog import _medium as M

f32 = jnp.float32
N = 200_000


def f_medium(t):
    return np.stack([1.0 + np.cos(2.0 * t), np.exp(-0.3 * t), 0.5 + t * t / 10.0], axis=-1)


F_SURFACE = np.array([0.7, 1.3, 0.2])


@pytest.mark.parametrize("sigma_t, albedo, s, ends", [
    ((0.5, 1.5, 3.0), (0.9, 0.7, 0.5), 2.5, True),     # a haze, a segment ending on a surface
    ((0.5, 1.5, 3.0), (0.9, 0.7, 0.5), 1000.0, False),  # an escaping ray (s = extent)
    ((0.02, 0.3, 6.0), (0.9, 0.9, 0.9), 4.0, True),     # strongly chromatic: red thin (q_r floored), blue deep
    ((0.0, 0.0, 2.0), (0.5, 0.5, 0.5), 3.0, True),      # two channels without fog
])
def test_spectral_mis_weights_are_unbiased(sigma_t, albedo, s, ends):
    """E[estimate] = int_0^s sigma_s e^{-sigma_t t} f(t) dt + e^{-sigma_t s} f_s per channel, the estimate being
    `collision_weight * f(t)` on the medium branch and `surface_weight * f_s` on the surface branch, with the
    medium's own `sample_free_flight` (channel drawn by a second uniform). Tolerance 4 SE per channel."""
    med = jf.HomogeneousMedium(sigma_t=sigma_t, albedo=albedo, phase=jf.HenyeyGreenstein(0.0))
    rng = np.random.default_rng(11)
    u = jnp.asarray(rng.random((N, 2), dtype=np.float32))
    o, d = jnp.zeros(3, f32), jnp.array([0.0, 0.0, 1.0], f32)

    @jax.jit
    def one(uu):
        fl = med.sample_free_flight(o, d, f32(s), jnp.bool_(ends), jnp.bool_(True), uu[0], uu[1])
        w_med = med.collision_weight(med, o, d, f32(s), jnp.where(fl.scattered, fl.q, 1.0), fl.t)
        w_surf = med.surface_weight(o, d, f32(s), fl.log_one_minus_q)
        return fl.t, fl.scattered, w_med, w_surf

    t, scat, w_med, w_surf = (np.asarray(x, np.float64) for x in jax.vmap(one)(u))
    scat = scat.astype(bool)
    est = np.where(scat[:, None], w_med * f_medium(t), w_surf * (F_SURFACE if ends else 0.0))
    assert np.all(np.isfinite(est))
    st, ss = np.asarray(sigma_t, np.float64), np.asarray(sigma_t, np.float64) * np.asarray(albedo)
    ref = np.array([integrate.quad(lambda x: ss[c] * np.exp(-st[c] * x) * f_medium(x)[c], 0.0, s, epsabs=1e-13,
                                   limit=500)[0] for c in range(3)]) + (np.exp(-st * s) * F_SURFACE if ends else 0.0)
    se = est.std(axis=0, ddof=1) / np.sqrt(len(est))
    assert np.all(np.abs(est.mean(0) - ref) <= 4 * se + 1e-6 * np.abs(ref)), (est.mean(0), ref, se)


def test_spectral_mis_pdf_is_the_sampling_density():
    """`free_flight_pdf` integrates to q over [0, s]; a histogram of the sampled t matches it (chi-square)."""
    from scipy import stats

    med = jf.HomogeneousMedium(sigma_t=(0.5, 1.5, 3.0), albedo=0.8, phase=jf.HenyeyGreenstein(0.0))
    o, d, s = jnp.zeros(3, f32), jnp.array([0.0, 0.0, 1.0], f32), 2.0
    fl = jax.vmap(lambda uu: med.sample_free_flight(o, d, f32(s), jnp.bool_(True), jnp.bool_(True), uu[0], uu[1]))(
        jnp.asarray(np.random.default_rng(12).random((N, 2), dtype=np.float32)))
    q = float(fl.q[0])
    x, w = np.polynomial.legendre.leggauss(40)
    nodes = 0.5 * s * (x + 1)
    pdf = lambda tt: np.asarray(jax.vmap(lambda t_: med.free_flight_pdf(o, d, f32(s), f32(q), t_))(
        jnp.asarray(tt, f32)), np.float64)
    assert float(np.sum(pdf(nodes) * 0.5 * s * w)) == pytest.approx(q, rel=1e-5)
    t = np.asarray(fl.t)[np.asarray(fl.scattered)]
    edges = np.linspace(0.0, s, 31)
    probs = np.array([integrate.quad(lambda v: float(pdf([v])[0]), a, b)[0] for a, b in zip(edges[:-1], edges[1:])])
    obs, _ = np.histogram(t, edges)
    exp = probs / probs.sum() * len(t)
    assert stats.chi2.sf(np.sum((obs - exp) ** 2 / exp), len(exp) - 1) > 1e-4


def test_equal_channels_reproduce_the_grey_scheme():
    """With equal channels the spectral-MIS decisions (q, log(1 - q), the branch) are bitwise those of the scalar
    scheme, whatever the channel uniform, and t and the weights equal its own to float32 rounding."""
    kw = dict(sigma_t=0.7, albedo=0.9, phase=jf.HenyeyGreenstein(0.3))
    mis, old = jf.HomogeneousMedium(**kw, spectral_mis=True), jf.HomogeneousMedium(**kw)
    assert old.spectral_mis is False  # a grey medium's default
    o, d = jnp.zeros(3, f32), jnp.array([0.0, 0.0, 1.0], f32)
    u = jnp.asarray(np.random.default_rng(13).random((4096, 2), dtype=np.float32))
    for s in (0.3, 2.0, 1000.0):
        def go(m, uu):
            fl = m.sample_free_flight(o, d, f32(s), jnp.bool_(s < 100), jnp.bool_(True), uu[0], uu[1])
            qq = jnp.where(fl.scattered, fl.q, 1.0)
            return (fl.t, fl.q, fl.log_one_minus_q, fl.scattered, m.free_flight_pdf(o, d, f32(s), qq, fl.t),
                    m.collision_weight(m, o, d, f32(s), qq, fl.t))
        a = jax.jit(jax.vmap(lambda uu: go(mis, uu)))(u)
        b = jax.jit(jax.vmap(lambda uu: go(old, uu)))(u)
        for x, y in zip(a[1:4], b[1:4]):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
        # t: the same formula on the same values; XLA fuses the two programs differently (measured: 1 ulp)
        np.testing.assert_allclose(np.asarray(a[0]), np.asarray(b[0]), rtol=3e-7)
        np.testing.assert_allclose(np.asarray(a[4]), np.asarray(b[4]), rtol=1e-6)
        np.testing.assert_allclose(np.asarray(a[5]), np.asarray(b[5]), rtol=1e-6)


def test_spectral_mis_is_compiled_only_where_the_channels_differ():
    """The default of `spectral_mis` is decided once, from `sigma_t` as built: off for a known grey value (a
    scalar, three equal channels, a grey scene file), on for RGB and for a value traced at construction (its
    channels unknown); an explicit flag wins, and `replace_medium` keeps the structure (a new value, even RGB, never
    recompiles)."""
    hg = jf.HenyeyGreenstein(0.3)
    assert not jf.HomogeneousMedium(0.5, 0.9, hg).spectral_mis
    assert not jf.HomogeneousMedium((0.5, 0.5, 0.5), 0.9, hg).spectral_mis
    assert jf.HomogeneousMedium((0.5, 0.5, 0.6), 0.9, hg).spectral_mis
    assert jf.HomogeneousMedium(0.5, 0.9, hg, spectral_mis=True).spectral_mis
    assert not jf.HomogeneousMedium((0.5, 1.5, 3.0), 0.9, hg, spectral_mis=False).spectral_mis
    flags = []
    jax.jit(lambda s: flags.append(jf.HomogeneousMedium(s, 0.9, hg).spectral_mis))(f32(0.5))
    assert flags == [True]
    scenes = REPO / "data_synthetic" / "scenes"
    grey, rgb = jf.load_scene(scenes / "spot_fog.json").scene, jf.load_scene(scenes / "chromatic_haze.json").scene
    assert not grey.medium.spectral_mis and rgb.medium.spectral_mis
    assert not grey.replace_medium(sigma_t=jnp.array([0.1, 0.2, 0.3], f32)).medium.spectral_mis
    assert grey.replace_medium(spectral_mis=True).medium.spectral_mis


def test_grey_medium_renders_the_spectral_mis_image():
    """spot_fog (grey sigma_t 0.5) at 12 x 12, 4 spp, max_depth 8, one key: the default (no spectral MIS) and
    `spectral_mis=True` make the same decisions (test above), so the images are one image computed by two programs,
    equal up to float32 rounding (`helpers.assert_same_render_up_to_rounding`; measured at 64 x 64 x 128 spp: max
    relative difference 4e-7)."""
    sf = jf.load_scene(REPO / "data_synthetic" / "scenes" / "spot_fog.json", ["camera.width=12", "camera.height=12"])
    grey = sf.scene
    mis = grey.replace_medium(spectral_mis=True)
    key = jax.random.key(5)
    a, b = np.asarray(jf.render(grey, key, 4)), np.asarray(jf.render(mis, key, 4))
    assert a.mean() > 0
    assert_same_render_up_to_rounding(a, b, spp=4, label="grey vs spectral MIS")


def test_deep_chromatic_weights_are_finite_with_finite_gradients():
    """A channel 200x denser than another at t = 50: its weight underflows to 0 gracefully (log-space balance
    heuristic, no 0 * inf), and the gradients w.r.t. sigma_t are finite in reparam (sampler = medium)."""
    o, d, s = jnp.zeros(3, f32), jnp.array([0.0, 0.0, 1.0], f32), f32(1000.0)

    def w(sig):
        med = jf.HomogeneousMedium(sigma_t=sig, albedo=0.9, phase=jf.HenyeyGreenstein(0.0))
        fl = med.sample_free_flight(o, d, s, jnp.bool_(False), jnp.bool_(True), f32(0.99), f32(0.1))
        return med.collision_weight(med, o, d, s, fl.q, fl.t), fl.t

    sig = jnp.array([0.05, 1.0, 10.0], f32)
    val, t = w(sig)
    assert float(t) > 50 and np.all(np.isfinite(np.asarray(val)))
    assert float(val[2]) == 0.0 and float(val[0]) > 0
    jac = jax.jacrev(lambda x: w(x)[0])(sig)
    assert np.all(np.isfinite(np.asarray(jac))), jac


# ------------------------------------------------------------------------------------------------ renders
CHROMA_SIGMA_T, CHROMA_ALBEDO = (0.5, 1.5, 3.0), (0.9, 0.7, 0.5)


@pytest.mark.parametrize("estimator", ["detached"])
def test_chromatic_render_equals_grey_render_per_channel(floor_scene, stats, estimator):
    """Point-lit diffuse floor in RGB fog sigma_t = (0.5, 1.5, 3.0), max_depth 3: channel c of the chromatic
    render equals channel c of the render of grey fog with (sigma_t_c, albedo_c), in expectation (both estimated
    from 32 keys; z-test with both standard errors).

    "reparam" is left out: at 8 spp x 32 keys its blue channel (sigma_t = 3, no light-angle lobe) is heavy-tailed
    for the grey reference as much as for the chromatic render (measured at 32 spp: per-pixel mean z +0.34 with
    spectral MIS and +0.42 with the scalar sampling (`spectral_mis=False`), while the image sums differ the other
    way, 0.91 and 0.90: a few large samples, not a bias of spectral MIS); the unit test above covers the weights it
    uses."""
    light = jf.PointLight((0.4, 1.2, 0.3), (6.0, 6.0, 6.0))
    spp = 8
    scene, _, _ = floor_scene([light], medium=jf.HomogeneousMedium(CHROMA_SIGMA_T, CHROMA_ALBEDO,
                                                                  jf.HenyeyGreenstein(0.4)), max_depth=3)
    mean, se = stats.mean_and_se(stats.render_keys(scene, spp, seed=21, estimator=estimator))
    ref, ref_se = np.zeros_like(mean), np.zeros_like(mean)
    for c in range(3):
        grey, _, _ = floor_scene([light], medium=jf.HomogeneousMedium(CHROMA_SIGMA_T[c], CHROMA_ALBEDO[c],
                                                                     jf.HenyeyGreenstein(0.4)), max_depth=3)
        m, e = stats.mean_and_se(stats.render_keys(grey, spp, seed=100 + c, estimator=estimator))
        ref[..., c], ref_se[..., c] = m[..., c], e[..., c]
    stats.assert_statistically_equal(mean, se, ref, ref_se=ref_se, label=f"chromatic vs grey ({estimator})")
