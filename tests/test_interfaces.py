"""The sample / eval / pdf interfaces, one method at a time: phase functions, BSDFs, lights, the warps of
`_sampling`, and the validation every Module does when it is built.

Statistics: histogram tests compare N samples in K bins with the expected counts `N p_k` by Pearson's chi-square
(K - 1 degrees of freedom); with fixed seeds a test fails if the statistic's upper tail probability is below 1e-4
(an unbiased sampler fails such a test with probability 1e-4 per seed). Moments are compared with their standard
error from the same samples (|z| <= 5).
"""

from __future__ import annotations

import json
import os
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats as sps

import jaxfog as jf
from helpers import FLOOR_CAMERA, assert_same_render_up_to_rounding, make_floor
from jaxfog import _sampling as S
from jaxfog._math import safe_normalize
from jaxfog._shapes import AbstractShape, ShapeHit, SurfacePoint, sphere_distance

N = 200_000
P_MIN = 1e-4
SCENES = os.path.join(os.path.dirname(__file__), "..", "data_synthetic", "scenes")


def chi_square_pvalue(samples, edges, probs):
    """Upper-tail p-value of Pearson's statistic for `samples` against bin probabilities `probs` on `edges`."""
    counts, _ = np.histogram(samples, edges)
    expected = len(samples) * np.asarray(probs, np.float64)
    assert expected.min() > 20, "bins too thin for the chi-square approximation"
    stat = np.sum((counts - expected) ** 2 / expected)
    return sps.chi2.sf(stat, len(probs) - 1), stat


def bin_probabilities(pdf_of_mu, edges, n_gl=16):
    """Probability of each bin of mu = cos theta for a density over directions symmetric about the axis:
    `int 2 pi pdf(mu) dmu` per bin, Gauss–Legendre in float64 on the float32 pdf."""
    x, w = np.polynomial.legendre.leggauss(n_gl)
    lo, hi = edges[:-1, None], edges[1:, None]
    mu = 0.5 * (hi - lo) * x[None] + 0.5 * (hi + lo)
    p = np.asarray(pdf_of_mu(jnp.asarray(mu, jnp.float32)), np.float64)
    return np.sum(2.0 * np.pi * p * w[None] * 0.5 * (hi - lo), axis=1)


PHASES = {
    "hg-0.7": jf.HenyeyGreenstein(-0.7),
    "hg0": jf.HenyeyGreenstein(0.0),
    "hg0.9": jf.HenyeyGreenstein(0.9),
    "rayleigh": jf.Rayleigh(),
}


def _uniforms(seed, shape):
    return jax.random.uniform(jax.random.key(seed), shape, jnp.float32)


# ------------------------------------------------------------------------------------------------ phase functions
@pytest.mark.parametrize("name", PHASES)
def test_phase_pdf_integrates_to_one_and_equals_eval(name):
    phase = PHASES[name]
    x, w = np.polynomial.legendre.leggauss(400)  # mu in [-1, 1]; a smooth pdf (HG 0.9 peaks at 4.5/sr)
    omc = jnp.asarray(1.0 - x, jnp.float32)
    pdf = np.asarray(jax.vmap(phase.pdf_polar)(omc), np.float64)
    val = np.asarray(jax.vmap(phase.eval_polar)(omc), np.float64)
    assert abs(np.sum(2.0 * np.pi * pdf * w) - 1.0) < 1e-5
    if phase.sampled_exactly:
        np.testing.assert_array_equal(pdf, val)


@pytest.mark.parametrize("name", PHASES)
def test_phase_sampler_follows_its_pdf(name):
    phase = PHASES[name]
    u = _uniforms(1, (N,))
    polar = jax.vmap(phase.sample_polar)(u)
    mu = np.asarray(0.5 * (polar.one_plus_cos - polar.one_minus_cos), np.float64)
    np.testing.assert_allclose(np.asarray(polar.one_plus_cos + polar.one_minus_cos), 2.0, atol=1e-6)
    # bins of equal probability under the pdf would be ideal; 40 equal bins in mu keep > 20 expected per bin here
    edges = np.linspace(-1.0, 1.0, 41)
    if name == "hg0.9":  # the forward peak: bins in 1 - mu on a log scale
        edges = np.concatenate([[-1.0], 1.0 - np.geomspace(1.0, 1e-3, 30), [1.0]])
    probs = bin_probabilities(lambda m: jax.vmap(phase.pdf_polar)(1.0 - m), edges)
    assert abs(probs.sum() - 1.0) < 1e-4
    p, stat = chi_square_pvalue(mu, edges, probs / probs.sum())
    assert p > P_MIN, (name, stat, p)


def test_rayleigh_moments():
    """E[cos] = 0 and E[cos^2] = 2/5, from the pdf (quadrature, exact to 1e-6) and from the sampler (5 SE)."""
    phase = jf.Rayleigh()
    x, w = np.polynomial.legendre.leggauss(16)
    p = np.asarray(jax.vmap(phase.pdf_polar)(jnp.asarray(1.0 - x, jnp.float32)), np.float64) * 2 * np.pi
    assert abs(np.sum(p * x * w)) < 1e-6 and abs(np.sum(p * x * x * w) - 0.4) < 1e-6
    polar = jax.vmap(phase.sample_polar)(_uniforms(2, (N,)))
    mu = np.asarray(0.5 * (polar.one_plus_cos - polar.one_minus_cos), np.float64)
    for m, expected in ((mu, 0.0), (mu * mu, 0.4)):
        assert abs(m.mean() - expected) <= 5 * m.std(ddof=1) / np.sqrt(N), (m.mean(), expected)


def test_rayleigh_sampler_is_accurate_at_the_poles():
    """Near mu = +-1 the sampler's small half (1 - mu or 1 + mu) agrees with a float64 root of the cubic in that
    small variable to float32 precision (the textbook `1 - (s - 1/s)` loses all its digits there).

    With `e = 1 - |mu|` the cdf equation `|mu|^3 + 3 |mu| = 2 |z|` reads `e^3 - 3 e^2 + 6 e = 4 - 2 |z|`, solved by
    Newton's method in float64."""
    u = np.array([2.0**-24, 1e-6, 1e-3, 0.25, 0.5, 0.75, 1 - 1e-3, 1 - 2.0**-24], np.float64)
    polar = jax.vmap(S.rayleigh_sample)(jnp.asarray(u, jnp.float32))
    z = 2.0 * (2.0 * np.float32(u).astype(np.float64) - 1.0)
    rhs = 4.0 - 2.0 * np.abs(z)
    e = rhs / 6.0
    for _ in range(30):
        e = e - (e**3 - 3 * e**2 + 6 * e - rhs) / (3 * e**2 - 6 * e + 6)
    small, large = e, 2.0 - e
    omc_ref = np.where(z >= 0, small, large)
    opc_ref = np.where(z >= 0, large, small)
    np.testing.assert_allclose(np.asarray(polar.one_minus_cos, np.float64), omc_ref, rtol=1e-6, atol=1e-30)
    np.testing.assert_allclose(np.asarray(polar.one_plus_cos, np.float64), opc_ref, rtol=1e-6, atol=1e-30)


@pytest.mark.parametrize("name", PHASES)
def test_phase_sample_direction_matches_its_polar_part(name):
    phase = PHASES[name]
    d = safe_normalize(jnp.array([0.3, -0.5, 0.8], jnp.float32))
    smp = jax.vmap(lambda u: phase.sample(d, u))(_uniforms(3, (1000, 2)))
    np.testing.assert_allclose(np.linalg.norm(np.asarray(smp.wo), axis=-1), 1.0, atol=2e-6)
    omc = 1.0 - np.asarray(smp.wo) @ np.asarray(d)
    np.testing.assert_allclose(omc, np.asarray(smp.one_minus_cos), atol=2e-6)
    np.testing.assert_allclose(np.asarray(smp.pdf), np.asarray(jax.vmap(lambda w: phase.pdf(d, w))(smp.wo)),
                               rtol=1e-4)
    np.testing.assert_allclose(np.asarray(smp.weight), 1.0, rtol=1e-6)


# ---------------------------------------------------------------------------------------------------------- BSDFs
def test_cosine_lobe_sampler_follows_its_pdf():
    polar = jax.vmap(S.cosine_sample)(_uniforms(4, (N,)))
    mu = np.asarray(0.5 * (polar.one_plus_cos - polar.one_minus_cos), np.float64)
    edges = np.linspace(0.0, 1.0, 41)
    edges[0] = -1e-9
    probs = bin_probabilities(S.cosine_pdf, np.clip(edges, 0.0, 1.0))
    assert abs(probs.sum() - 1.0) < 1e-6
    p, stat = chi_square_pvalue(mu, edges, probs)
    assert p > P_MIN, (stat, p)


def test_diffuse_sample_eval_pdf_agree():
    """weight = eval / pdf = reflectance for front-side samples; black from the back, where pdf is 0 too."""
    bsdf = jf.Diffuse((0.2, 0.5, 0.8))
    n = safe_normalize(jnp.array([0.1, 1.0, -0.2], jnp.float32))
    d = safe_normalize(jnp.array([0.4, -1.0, 0.3], jnp.float32))
    smp = jax.vmap(lambda u: bsdf.sample(d, n, u))(_uniforms(5, (1000, 3)))
    ev = jax.vmap(lambda w: bsdf.eval(d, w, n))(smp.wo)
    pdf = jax.vmap(lambda w: bsdf.pdf(d, w, n))(smp.wo)
    np.testing.assert_allclose(np.asarray(smp.weight), np.broadcast_to([0.2, 0.5, 0.8], (1000, 3)), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(ev / pdf[:, None]), np.asarray(smp.weight), rtol=1e-4)
    assert not np.any(np.asarray(smp.delta))
    back = jax.vmap(lambda w: bsdf.eval(-d, w, n))(smp.wo)  # arriving from below the surface
    assert np.all(np.asarray(back) == 0)
    assert float(bsdf.pdf(d, -n, n)) == 0.0


def test_mirror_and_glass_are_delta():
    n = jnp.array([0.0, 1.0, 0.0], jnp.float32)
    d = safe_normalize(jnp.array([0.6, -0.8, 0.0], jnp.float32))
    m = jf.Mirror(0.7).sample(d, n, jnp.zeros(3))
    np.testing.assert_allclose(np.asarray(m.wo), [0.6, 0.8, 0.0], atol=1e-6)
    assert bool(m.delta) and float(m.pdf) == 0.0 and float(jnp.sum(jf.Mirror().eval(d, m.wo, n))) == 0.0
    glass = jf.Glass(1.5, 1.0)
    F = float(jf._bsdf.fresnel_dielectric(jnp.float32(0.8), jnp.float32(1.5))[0])
    refl = glass.sample(d, n, jnp.array([0.0, 0.0, 0.5 * F]))
    refr = glass.sample(d, n, jnp.array([0.0, 0.0, 0.5 * (1 + F)]))
    assert not bool(refl.transmitted) and bool(refr.transmitted) and bool(refr.delta)
    np.testing.assert_allclose(np.asarray(refl.wo), [0.6, 0.8, 0.0], atol=1e-6)
    sin_t = float(refr.wo[0])  # Snell: sin_t = sin_i / 1.5, going down into the glass
    assert abs(sin_t - 0.6 / 1.5) < 1e-6 and float(refr.wo[1]) < 0
    np.testing.assert_allclose(np.asarray(refr.weight), 1.0 / 1.5**2, rtol=1e-6)


# --------------------------------------------------------------------------------------------------------- lights
def test_point_and_spot_light_samples():
    p = jnp.array([0.5, 0.0, -0.3], jnp.float32)
    point = jf.PointLight((0.5, 2.0, -0.3), (4.0, 3.0, 2.0))
    ls = point.sample_li(p)
    np.testing.assert_allclose(np.asarray(ls.wi), [0, 1, 0], atol=1e-7)
    np.testing.assert_allclose(np.asarray(ls.value), np.array([4.0, 3.0, 2.0]) / 4.0, rtol=1e-6)
    assert float(ls.pdf) == 1.0 and float(ls.dist) == pytest.approx(2.0) and point.is_delta
    spot = jf.SpotLight((0.0, 2.0, 0.0), (0.0, -1.0, 0.0), 10.0, cutoff_angle=30.0, beam_width=10.0)
    for theta in (5.0, 20.0, 29.0, 31.0):
        x = jnp.array([2.0 * np.tan(np.deg2rad(theta)), 0.0, 0.0], jnp.float32)
        ls = spot.sample_li(x)
        falloff = 1.0 if theta <= 10 else max(0.0, (30.0 - theta) / 20.0)
        r2 = float(jnp.sum((x - spot.position) ** 2))
        np.testing.assert_allclose(np.asarray(ls.value), 10.0 * falloff / r2, rtol=2e-5, atol=1e-7)


def test_point_like_lights_split_their_value_into_colour_and_profile():
    """`sample_li` gives a point-like light's value as `rgb * scale` (what the tracer reads: the scalar computed
    once for the three channels), equal to `intensity_toward(-wi) / dist^2`; `intensity_toward` is
    `intensity_parts` multiplied back. A light whose colour depends on the direction returns it with scale 1."""
    spot = jf.SpotLight((0.0, 2.0, 0.0), (0.0, -1.0, 0.0), (10.0, 5.0, 2.0), cutoff_angle=30.0, beam_width=10.0)
    point = jf.PointLight((0.5, 2.0, -0.3), (4.0, 3.0, 2.0))

    class Ring(jf.AbstractPointLikeLight):  # a colour that depends on the direction: no colour / profile split
        position: jax.Array

        def intensity_parts(self, w):
            return jnp.stack([1.0 + w[0] ** 2, 2.0 + w[1], 3.0 - w[2]]), jnp.float32(1.0)

        def lit_interval(self, o, d):
            return jnp.float32(-jnp.inf), jnp.float32(jnp.inf)

    ring = Ring(jnp.array([0.2, 1.5, 0.1], jnp.float32))
    for light in (spot, point, ring):
        for theta in (0.0, 5.0, 20.0, 29.0, 31.0, 120.0):
            x = jnp.array([2.0 * np.sin(np.deg2rad(theta)), 2.0 - 2.0 * np.cos(np.deg2rad(theta)), 0.3],
                          jnp.float32)
            ls = light.sample_li(x)
            np.testing.assert_allclose(np.asarray(ls.rgb * ls.scale), np.asarray(ls.value), rtol=0, atol=0)
            expected = np.asarray(light.intensity_toward(-ls.wi)) / float(ls.dist) ** 2
            np.testing.assert_allclose(np.asarray(ls.value), expected, rtol=2e-6, atol=1e-9)
            colour, profile = light.intensity_parts(-ls.wi)
            np.testing.assert_allclose(np.asarray(colour * profile), np.asarray(light.intensity_toward(-ls.wi)),
                                       rtol=1e-7)
            assert float(ls.pdf) == 1.0 and float(light.pdf_li(x, ls.wi, ls.dist)) == 0.0
    assert float(ring.sample_li(jnp.zeros(3)).scale) == pytest.approx(1.0 / float(jnp.sum(ring.position ** 2)))


def _rectangle_solid_angle(p, center, eu, ev):
    """Solid angle of a rectangle seen from p (Van Oosterom & Strackee, two triangles), float64."""
    c, eu, ev = (np.asarray(x, np.float64) for x in (center, eu, ev))
    v = [c - 0.5 * eu - 0.5 * ev, c + 0.5 * eu - 0.5 * ev, c + 0.5 * eu + 0.5 * ev, c - 0.5 * eu + 0.5 * ev]
    total = 0.0
    for a, b, cc in ((v[0], v[1], v[2]), (v[0], v[2], v[3])):
        r1, r2, r3 = a - p, b - p, cc - p
        l1, l2, l3 = (np.linalg.norm(r) for r in (r1, r2, r3))
        num = np.dot(r1, np.cross(r2, r3))
        den = l1 * l2 * l3 + np.dot(r1, r2) * l3 + np.dot(r1, r3) * l2 + np.dot(r2, r3) * l1
        total += 2.0 * np.arctan2(abs(num), den)
    return total


def test_area_light_pdf_is_its_closed_form_and_integrates_to_the_solid_angle():
    """`pdf_li` at each sampled direction equals the sample's pdf (= dist^2 / (A cos)), and E[1 / pdf] over the
    samples is the rectangle's solid angle (its standard error from the samples, |z| <= 5)."""
    light = jf.AreaLight((0.2, 2.0, -0.1), (1.2, 0.0, 0.0), (0.0, 0.0, 0.8), 3.0)  # front face -y (down)
    p = jnp.array([0.7, 0.4, 0.5], jnp.float32)
    smp = jax.vmap(lambda u: light.sample_li(p, u))(_uniforms(6, (N, 2)))
    pdf_again = jax.vmap(lambda w, t: light.pdf_li(p, w, t))(smp.wi, smp.dist)
    np.testing.assert_allclose(np.asarray(pdf_again), np.asarray(smp.pdf), rtol=1e-5)
    y = np.asarray(p)[None] + np.asarray(smp.dist)[:, None] * np.asarray(smp.wi)
    cos_l = -np.asarray(smp.wi) @ np.array([0.0, -1.0, 0.0])
    closed = np.sum((y - np.asarray(p)) ** 2, -1) / (1.2 * 0.8 * cos_l)
    np.testing.assert_allclose(np.asarray(smp.pdf), closed, rtol=1e-4)
    inv = 1.0 / np.asarray(smp.pdf, np.float64)
    omega = _rectangle_solid_angle(np.asarray(p, np.float64), light.center, light.edge_u, light.edge_v)
    assert abs(inv.mean() - omega) <= 5 * inv.std(ddof=1) / np.sqrt(N), (inv.mean(), omega)
    behind = light.sample_li(jnp.array([0.2, 3.0, -0.1], jnp.float32), jnp.array([0.5, 0.5]))
    assert float(behind.pdf) == 0.0 and float(jnp.sum(behind.value)) == 0.0  # one-sided


def test_spot_lit_interval_is_the_cone():
    """Points of random lines inside `lit_interval` are inside the cutoff cone, points outside are not."""
    spot = jf.SpotLight((0.1, 2.0, -0.2), (0.3, -1.0, 0.2), 1.0, cutoff_angle=25.0, beam_width=10.0)
    rng = np.random.default_rng(7)
    o = rng.uniform(-3, 3, (500, 3)).astype(np.float32)
    d = rng.normal(size=(500, 3)).astype(np.float32)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    t0, t1 = jax.vmap(spot.lit_interval)(jnp.asarray(o), jnp.asarray(d))
    t = np.linspace(-8, 8, 401)
    x = o[:, None] + t[None, :, None] * d[:, None]
    v = x - np.asarray(spot.position)
    cosang = v @ np.asarray(spot.direction) / np.linalg.norm(v, axis=-1)
    inside = cosang > np.cos(np.deg2rad(25.0))
    predicted = (t[None] >= np.asarray(t0)[:, None]) & (t[None] <= np.asarray(t1)[:, None])
    margin = np.abs(cosang - np.cos(np.deg2rad(25.0))) > 1e-4  # float32 rounding at the cone's surface
    assert np.array_equal(inside[margin], predicted[margin])


def test_spot_lit_interval_holds_every_lit_point_of_lines_passing_next_to_the_apex():
    """Lines from anywhere in a 4 m box toward points within ~1 cm of a spot's apex 2.8 m up (a path scattered
    toward the light): every point within 3 cm of the light that the spot lights (its profile > 0) lies in
    `lit_interval`, so the equiangular technique has a density there and next-event estimation's MIS weight is not 1
    (where it was, a vertex 1 cm from the light carried I / r^2: a firefly). Computed about the origin in float32,
    127 of 14,445 such points fell outside by 0.3-2 mm or in an empty interval; none may."""
    spot = jf.SpotLight((0.0, 2.8, 0.0), (0.0, -1.0, 0.0), 60.0, cutoff_angle=20.0, beam_width=15.0)
    pos = np.asarray(spot.position)
    rng = np.random.default_rng(0)
    n = 20000
    o = rng.uniform([-2, 0, -2], [2, 5.6, 2], (n, 3)).astype(np.float32)
    d = (pos + rng.normal(0, 0.01, (n, 3)) - o).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t = (np.sum((pos - o) * d, axis=1) + rng.uniform(-0.03, 0.03, n)).astype(np.float32)
    t0, t1 = map(np.asarray, jax.vmap(spot.lit_interval)(jnp.asarray(o), jnp.asarray(d)))
    v = o + t[:, None] * d - pos
    lit = np.asarray(jax.vmap(lambda w: spot.intensity_parts(w)[1])(jnp.asarray(v / np.linalg.norm(v, axis=1,
                                                                                                 keepdims=True)))) > 0
    assert lit.sum() > 500  # the test reaches the cone next to the apex
    inside = (t >= t0) & (t <= t1)
    assert np.all(inside[lit]), np.flatnonzero(lit & ~inside)[:5]


# ----------------------------------------------------------------------------------------------------------- shapes
def _tetrahedron(bsdf):
    """A closed tetrahedron with faces of four different areas, counter-clockwise seen from outside: its vertices
    (float64) and faces."""
    v = np.array([[0.1, 0.0, -0.2], [1.6, 0.1, -0.2], [0.1, 1.1, 0.0], [0.3, 0.2, 0.6]])
    f = np.array([[0, 1, 2], [0, 1, 3], [1, 2, 3], [0, 2, 3]])
    tri = v[f]
    out = np.einsum("ij,ij->i", np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), tri.mean(1) - v.mean(0))
    f = np.where((out < 0)[:, None], f[:, ::-1], f)
    return jf.Mesh.from_arrays(v, f, bsdf), v, f


def _shapes():
    mesh, _, _ = _tetrahedron(jf.Diffuse(0.5))
    return {
        "sphere": jf.Sphere((0.3, -0.2, 0.5), 0.8, jf.Diffuse(0.5)),
        "rectangle": jf.Rectangle((0.1, 0.2, -0.3), (1.2, 0.0, 0.4), (0.0, 0.9, 0.0), jf.Diffuse(0.5)),
        "mesh": mesh,
    }


def _random_rays(seed, n, shape):
    """Rays from a box around the shape aimed at points of its bounds widened by a third (hits and misses)."""
    rng = np.random.default_rng(seed)
    lo, hi = (np.asarray(b, np.float64) for b in shape.bounds())
    o = rng.uniform(-3.0, 3.0, (n, 3))
    target = rng.uniform(lo - (hi - lo) / 6 - 0.05, hi + (hi - lo) / 6 + 0.05, (n, 3))
    d = target - o
    return jnp.asarray(o, jnp.float32), jnp.asarray(d / np.linalg.norm(d, axis=1, keepdims=True), jnp.float32)


def _per_ray(shape, f):
    """`f` over rays: `vmap` for a stacked (analytic) shape; `lax.map` for a mesh, whose batched traversal would
    compile a lane-compacting program far slower to build than these few rays need."""
    return jax.vmap(f) if shape.stacked else (lambda *xs: jax.lax.map(lambda x: f(*x), xs))


def _sphere_t64(o, d, c, r):
    oc = o - c
    b = np.einsum("ij,ij->i", oc, d)
    disc = b * b - (np.einsum("ij,ij->i", oc, oc) - r * r)
    root = np.sqrt(np.maximum(disc, 0.0))
    t0, t1 = -b - root, -b + root
    t = np.where(t0 > 1e-4, t0, np.where(t1 > 1e-4, t1, np.inf))
    return np.where(disc >= 0, t, np.inf)


def _rectangle_t64(o, d, c, u, v):
    n = np.cross(u, v) / np.linalg.norm(np.cross(u, v))
    t = ((c - o) @ n) / (d @ n)
    p = o + t[:, None] * d - c
    inside = (np.abs(p @ u / (u @ u)) <= 0.5) & (np.abs(p @ v / (v @ v)) <= 0.5) & (t > 1e-4)
    return np.where(inside, t, np.inf)


@pytest.mark.parametrize("name", ["sphere", "rectangle", "mesh"])
def test_shape_intersect_any_hit_and_normals(name):
    """`intersect` and `surface` against float64 distances (sphere, rectangle; the mesh's traversal is tested against
    brute force in tests/test_mesh.py, and here against its own triangles' planes), the normal against the surface's
    (the surface's distance is the hit's to float32 rounding); `found`
    and `any_hit` at a finite `t_max` against the distance found without one (rays whose hit lies within 1e-4 of
    t_max are left out: rounding)."""
    shape = _shapes()[name]
    n_rays = 4000 if shape.stacked else 1000
    o, d = _random_rays(1, n_rays, shape)
    t_max = jnp.asarray(np.random.default_rng(2).uniform(0.5, 5.0, n_rays), jnp.float32)
    def nearest(o_, d_, t_max_):
        hit = shape.intersect(o_, d_, t_max_)
        surface = shape.surface(o_, d_, hit)
        return hit.t, surface.t, surface.n, hit.found

    t_hit, t, n, _ = (np.asarray(x) for x in _per_ray(shape, nearest)(o, d, jnp.full(n_rays, jnp.inf)))
    found = np.asarray(_per_ray(shape, shape.intersect)(o, d, t_max).found)
    hits = np.isfinite(t_hit)
    np.testing.assert_allclose(t[hits], t_hit[hits], rtol=1e-5)  # the surface's distance is the hit's
    blocked = np.asarray(_per_ray(shape, shape.any_hit)(o, d, t_max))
    o64, d64 = np.asarray(o, np.float64), np.asarray(d, np.float64)
    assert 0.2 < hits.mean() < 0.9, hits.mean()  # both hits and misses
    p = o64 + np.where(hits, t, 0.0)[:, None] * d64
    if name == "sphere":
        c, r = np.asarray(shape.center, np.float64), float(shape.radius)
        t64 = _sphere_t64(o64, d64, c, r)
        normal = (p - c) / r
    elif name == "rectangle":
        c, u, v = (np.asarray(x, np.float64) for x in (shape.center, shape.edge_u, shape.edge_v))
        t64 = _rectangle_t64(o64, d64, c, u, v)
        normal = np.broadcast_to(np.cross(u, v) / np.linalg.norm(np.cross(u, v)), p.shape)
    if name != "mesh":
        both = np.isfinite(t64) & hits
        assert np.mean(np.isfinite(t64) != hits) < 1e-3  # rays grazing an edge may go either way in float32
        np.testing.assert_allclose(t[both], t64[both], rtol=2e-5, atol=2e-5)
        np.testing.assert_allclose(n[both], normal[both], atol=2e-5)
    else:  # each hit lies on a face, whose outward normal it returns
        _, v, f = _tetrahedron(jf.Diffuse(0.5))
        tri = v[f]
        fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        fn /= np.linalg.norm(fn, axis=1, keepdims=True)
        dist = np.abs(np.einsum("pk,fk->pf", p, fn) - np.einsum("fk,fk->f", tri[:, 0], fn)[None])
        face = np.argmin(dist, axis=1)
        assert np.all(dist[hits, face[hits]] < 1e-5)
        np.testing.assert_allclose(n[hits], fn[face[hits]], atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(n[hits], axis=1), 1.0, atol=1e-6)
    clear = np.abs(np.where(hits, t_hit, 1e9) - np.asarray(t_max)) > 1e-4
    assert np.array_equal(found[clear], (t_hit < np.asarray(t_max))[clear])
    assert np.array_equal(blocked[clear], found[clear])


@pytest.mark.parametrize("name", ["sphere", "rectangle", "mesh"])
def test_shape_area_sampling_is_uniform_with_density_one_over_area(name):
    """`sample_area`: points on the surface (a ray back along the sampled normal hits the shape there with that
    normal), inside `bounds()`, with `pdf = pdf_area(p) = 1 / area` (float64 areas), spread uniformly by area
    (chi-square: the sphere's height, which is uniform for a uniform sphere (Archimedes); the rectangle's 5 x 5
    cells; the mesh's faces by their areas)."""
    shape = _shapes()[name]
    smp = jax.vmap(shape.sample_area)(_uniforms(11, (N, 2)))
    p, n, pdf = (np.asarray(x, np.float64) for x in smp)
    lo, hi = (np.asarray(b, np.float64) for b in shape.bounds())
    assert np.all((p >= lo - 1e-6) & (p <= hi + 1e-6))
    if name == "sphere":
        area = 4.0 * np.pi * float(shape.radius) ** 2
        h = (p[:, 2] - float(shape.center[2])) / float(shape.radius)
        counts_x, edges = h, np.linspace(-1.0, 1.0, 21)
        probs = np.full(20, 1.0 / 20)
    elif name == "rectangle":
        c, u, v = (np.asarray(x, np.float64) for x in (shape.center, shape.edge_u, shape.edge_v))
        area = np.linalg.norm(np.cross(u, v))
        a, b = (p - c) @ u / (u @ u), (p - c) @ v / (v @ v)
        assert np.all(np.abs((p - c) @ np.cross(u, v)) / area < 1e-5)
        cell = np.clip(np.floor((a + 0.5) * 5), 0, 4) * 5 + np.clip(np.floor((b + 0.5) * 5), 0, 4)
        counts_x, edges, probs = cell, np.arange(26) - 0.5, np.full(25, 1.0 / 25)
    else:
        _, v, f = _tetrahedron(jf.Diffuse(0.5))
        tri = v[f]
        fa = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        area = fa.sum()
        fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]) / (2 * fa[:, None])
        dist = np.abs(np.einsum("pk,fk->pf", p, fn) - np.einsum("fk,fk->f", tri[:, 0], fn)[None])
        face = np.argmin(dist, axis=1)
        assert np.all(dist[np.arange(N), face] < 1e-5)
        np.testing.assert_allclose(n, fn[face], atol=1e-5)
        counts_x, edges, probs = face, np.arange(5) - 0.5, fa / area
    np.testing.assert_allclose(pdf, 1.0 / area, rtol=1e-5)
    np.testing.assert_allclose(float(shape.pdf_area(smp.p[0])), 1.0 / area, rtol=1e-5)
    pv, stat = chi_square_pvalue(counts_x, edges, probs)
    assert pv > P_MIN, (stat, pv)
    def surface_back(q, m):  # from 0.5 outside the point, toward it
        return shape.surface(q + 0.5 * m, -m, shape.intersect(q + 0.5 * m, -m, jnp.float32(jnp.inf)))

    back = _per_ray(shape, surface_back)(smp.p[:500], smp.n[:500])
    np.testing.assert_allclose(np.asarray(back.t), 0.5, atol=2e-5)
    np.testing.assert_allclose(np.asarray(back.n), n[:500], atol=2e-5)


def test_shape_bounds_and_box_relation():
    """`bounds()` is the shape's box (sphere: center +- radius; rectangle: its corners'; mesh: its vertices', rounded
    outward in float32); `box_relation` says inside, outside or straddles for each shape, None when traced."""
    shapes = _shapes()
    sph, rect, mesh = shapes["sphere"], shapes["rectangle"], shapes["mesh"]
    np.testing.assert_allclose(np.asarray(sph.bounds()[0]), [-0.5, -1.0, -0.3], atol=1e-6)
    np.testing.assert_allclose(np.asarray(sph.bounds()[1]), [1.1, 0.6, 1.3], atol=1e-6)
    c, u, v = (np.asarray(x, np.float64) for x in (rect.center, rect.edge_u, rect.edge_v))
    corners = np.array([c + 0.5 * (a * u + b * v) for a in (-1, 1) for b in (-1, 1)])
    np.testing.assert_allclose(np.asarray(rect.bounds()[0]), corners.min(0), atol=1e-6)
    np.testing.assert_allclose(np.asarray(rect.bounds()[1]), corners.max(0), atol=1e-6)
    _, verts, _ = _tetrahedron(jf.Diffuse(0.5))
    mlo, mhi = (np.asarray(b, np.float64) for b in mesh.bounds())
    assert np.all(mlo <= verts.min(0)) and np.all(mhi >= verts.max(0))
    np.testing.assert_allclose(mlo, verts.min(0), atol=1e-6)
    big = (-np.full(3, 5.0), np.full(3, 5.0))
    far = (np.full(3, 3.0), np.full(3, 4.0))
    for s in (sph, rect, mesh):
        assert s.box_relation(*big) == "inside" and s.box_relation(*far) == "outside"
        lo, hi = (np.asarray(b, np.float64) for b in s.bounds())
        mid = 0.5 * (lo + hi)
        assert s.box_relation(lo - 5.0, np.where(np.arange(3) == 0, mid[0], hi + 5.0)) == "straddles"
    seen = []
    jax.jit(lambda c: seen.append(jf.Sphere(c, 0.8, jf.Diffuse(0.5)).box_relation(*big)) or c)(jnp.zeros(3))
    assert seen == [None]  # traced values: nothing to check


class Ball(AbstractShape):
    """A sphere as a shape class the tracer has never seen, intersected on its own (not stacked): the tracer and
    `pack` reach it only through `AbstractShape`."""

    center: jax.Array
    radius: jax.Array
    bsdf: jf.AbstractBSDF
    stacked: ClassVar[bool] = False

    def _sphere(self):
        return jf.Sphere(self.center, self.radius, self.bsdf)

    def intersect(self, o, d, t_max):
        t = sphere_distance(o, d, self.center, self.radius)
        found = t < t_max
        return ShapeHit(jnp.where(found, t, jnp.inf), found, jnp.int32(0))

    def surface(self, o, d, hit):
        p = o + jnp.where(hit.found, hit.t, 0.0) * d
        return SurfacePoint(hit.t, safe_normalize(p - self.center))

    def any_hit(self, o, d, t_max):
        return sphere_distance(o, d, self.center, self.radius) < t_max

    def bounds(self):
        return self._sphere().bounds()

    def sample_area(self, u):
        return self._sphere().sample_area(u)

    def pdf_area(self, p):
        return self._sphere().pdf_area(p)

    def box_relation(self, lo, hi):
        return self._sphere().box_relation(lo, hi)


class Lamp(jf.AbstractPointLikeLight):
    """An isotropic point light as a light class the tracer has never seen."""

    position: jax.Array
    intensity: jax.Array

    def intensity_parts(self, w):
        return self.intensity, jnp.float32(1.0)

    def lit_interval(self, o, d):
        return jnp.float32(-jnp.inf), jnp.float32(jnp.inf)


def test_new_shape_and_light_classes_render_through_the_interfaces():
    """A scene whose sphere and point light are replaced by classes defined here (`Ball`, not stacked; `Lamp`)
    renders the same image, up to float32 rounding, as with `Sphere` and `PointLight`: `pack` and the tracer know
    shapes and lights only by their interfaces (a new shape is one class plus its registration in the scene files).
    Fog, a spot of shadow on the floor and the ball seen directly: nearest hits, shadow rays, equiangular sampling
    and next-event estimation all go through them."""
    cam = FLOOR_CAMERA.build()
    medium = jf.HomogeneousMedium(0.3, 0.8, jf.HenyeyGreenstein(0.4))
    pos, power = jnp.array([0.3, 2.0, 0.2], jnp.float32), jnp.array([3.0, 2.0, 1.0], jnp.float32)
    center, radius = jnp.array([0.2, 0.5, 0.0], jnp.float32), jnp.float32(0.5)
    known = jf.Scene(camera=cam, shapes=(make_floor(), jf.Sphere(center, radius, jf.Diffuse(0.6))),
                     lights=(jf.PointLight(pos, power),), medium=medium, max_depth=2)
    new = jf.Scene(camera=cam, shapes=(make_floor(), Ball(center, radius, jf.Diffuse(0.6))),
                   lights=(Lamp(pos, power),), medium=medium, max_depth=2)
    a, b = (np.asarray(jf.render(sc, jax.random.key(3), 2)) for sc in (known, new))
    assert a.max() > 0
    assert_same_render_up_to_rounding(a, b, spp=2, label="new shape and light classes")


def test_modules_are_abstract_or_final():
    """No Module of the library overrides a concrete method of a base class (equinox's abstract-or-final rule:
    concrete classes implement abstract methods only), and every medium says whether it has a box through the
    interface (`bounds`: None for fog that fills space)."""
    import inspect

    import equinox as eqx
    from jaxfog import _bsdf, _camera, _height, _integrator, _lights, _medium, _mesh, _phase, _scene, _shapes

    overridden = []
    for m in (_bsdf, _camera, _height, _integrator, _lights, _medium, _mesh, _phase, _scene, _shapes):
        for cls in vars(m).values():
            if not (inspect.isclass(cls) and issubclass(cls, eqx.Module) and cls.__module__ == m.__name__):
                continue
            for attr, val in vars(cls).items():
                if attr.startswith("__") or not (inspect.isfunction(val) or isinstance(val, property)):
                    continue
                base = next((b for b in cls.__mro__[1:] if attr in vars(b)), None)
                if base is None or base in (eqx.Module, object):
                    continue
                bv = vars(base)[attr]
                if not getattr(bv.fget if isinstance(bv, property) else bv, "__isabstractmethod__", False):
                    overridden.append(f"{cls.__name__}.{attr} overrides {base.__name__}.{attr}")
    assert overridden == []
    hg = jf.HenyeyGreenstein(0.5)
    assert jf.HeightFog(sigma_0=0.5, height_scale=1.0, albedo=0.9, phase=hg).bounds is None
    assert jf.HomogeneousMedium(0.5, 0.9, hg).bounds is None
    assert jf.HomogeneousMedium(0.5, 0.9, hg, bounds=((0, 0, 0), (1, 1, 1))).bounds is not None


# ----------------------------------------------------------------------------------------------------- the warps
def test_equiangular_sampler_follows_its_pdf():
    c = jnp.array([0.5, 1.0, -2.0], jnp.float32)
    o = jnp.zeros(3, jnp.float32)
    d = jnp.array([0.0, 0.0, -1.0], jnp.float32)
    eq = S.equiangular_setup(c, o, d, jnp.float32(0.5), jnp.float32(6.0))
    t = np.asarray(jax.vmap(lambda u: S.equiangular_sample(eq, u, jnp.float32(6.0)))(_uniforms(8, (N,))))
    edges = np.linspace(0.5, 6.0, 41)
    x, w = np.polynomial.legendre.leggauss(16)
    mid = 0.5 * (edges[1:] + edges[:-1])[:, None] + 0.5 * np.diff(edges)[:, None] * x[None]
    p = np.asarray(jax.vmap(lambda tt: S.equiangular_pdf(eq, tt))(jnp.asarray(mid.reshape(-1), jnp.float32)))
    probs = np.sum(p.reshape(mid.shape) * w[None], axis=1) * 0.5 * np.diff(edges)
    assert abs(probs.sum() - 1.0) < 1e-5
    pv, stat = chi_square_pvalue(t, edges, probs / probs.sum())
    assert pv > P_MIN, (stat, pv)


def test_equiangular_pdf_tests_the_interval_in_distances_as_the_angles_do():
    """`equiangular_pdf` decides "inside the sampled interval" by comparing distances (`t_a`, `t_b`, widened by the
    distance an angle of EQUIANGULAR_ANGLE_TOL moves t), not arctangents. It must agree with the angle test
    (float64 reference) everywhere outside that tolerance band, including a ray that grazes the light (D ~ 1e-6),
    an interval with an infinite end (clipped at HALF_PI_BELOW) and an empty one, and give the formula's value."""
    rng = np.random.default_rng(5)
    o = jnp.zeros(3, jnp.float32)
    d = jnp.array([0.0, 0.0, -1.0], jnp.float32)
    cases = [((0.5, 1.0, -2.0), 0.5, 6.0), ((1e-6, 0.0, -3.0), 0.2, 8.0), ((0.3, 0.0, -1.0), 0.0, np.inf),
             ((0.2, 0.1, -50.0), 1.0, 2.0), ((0.4, 0.0, -1.0), 3.0, 2.0)]
    for c, ta, tb in cases:
        eq = S.equiangular_setup(jnp.asarray(c, jnp.float32), o, d, jnp.float32(ta), jnp.float32(tb))
        t = np.concatenate([rng.uniform(0.0, 12.0, 4000), [ta, min(tb, 1e3), 0.0, 2.99, 3.0]]).astype(np.float32)
        p = np.asarray(jax.vmap(lambda x: S.equiangular_pdf(eq, x))(jnp.asarray(t)), np.float64)
        delta, D = float(eq.delta), float(eq.D)
        th = np.arctan2(t.astype(np.float64) - delta, D)
        th_a, th_b = float(eq.theta_a), float(eq.theta_b)
        valid = bool(eq.valid)
        assert valid == (tb > ta)
        inside = valid & (th >= th_a) & (th <= th_b)
        band = (np.abs(th - th_a) < 2e-6) | (np.abs(th - th_b) < 2e-6)
        assert np.array_equal(p[~band] > 0, inside[~band]), (c, ta, tb)
        if valid:
            expect = D / ((th_b - th_a) * (D * D + (t - delta) ** 2))
            np.testing.assert_allclose(p[inside & ~band], expect[inside & ~band], rtol=2e-5)
        g = jax.grad(lambda x: S.equiangular_pdf(eq, x))(jnp.float32(2.0))
        assert np.isfinite(float(g))


def test_truncated_exponential_pdf_integrates_to_one():
    x, w = np.polynomial.legendre.leggauss(64)
    for rate, s in ((0.5, 3.0), (4.0, 2.0), (1e-4, 10.0)):
        t = jnp.asarray(0.5 * s * (x + 1), jnp.float32)
        p = np.asarray(S.truncated_exponential_pdf(t, jnp.float32(rate), jnp.float32(s)), np.float64)
        assert abs(np.sum(p * w) * 0.5 * s - 1.0) < 1e-5, (rate, s)


# ------------------------------------------------------------------------------------------------------ validation
@pytest.mark.parametrize("build, message", [
    (lambda: jf.HenyeyGreenstein(1.0), r"HenyeyGreenstein\.g = 1\.0 .* valid range \(-1, 1\)"),
    (lambda: jf.HenyeyGreenstein(0.99999999), r"HenyeyGreenstein\.g = 1\.0 \(as float32\)"),
    (lambda: jf.HenyeyGreenstein(-1.5), r"HenyeyGreenstein\.g = -1\.5"),
    (lambda: jf.HomogeneousMedium(sigma_t=-1.0, albedo=0.5, phase=jf.Rayleigh()), r"HomogeneousMedium\.sigma_t"),
    (lambda: jf.HomogeneousMedium(sigma_t=1e39, albedo=0.5, phase=jf.Rayleigh()), r"HomogeneousMedium\.sigma_t"),
    (lambda: jf.HomogeneousMedium(sigma_t=1.0, albedo=(0.5, 2.0, 0.5), phase=jf.Rayleigh()),
     r"HomogeneousMedium\.albedo = \[0\.5, 2\.0, 0\.5\] .* \[0, 1\]"),
    (lambda: jf.SpotLight((0, 0, 0), (0, -1, 0), 1.0, cutoff_angle=20.0, beam_width=25.0), r"beam_width"),
    (lambda: jf.SpotLight((0, 0, 0), (0, 0, 0), 1.0), r"SpotLight\.direction"),
    (lambda: jf.PointLight((0, 0, 0), -1.0), r"PointLight\.intensity"),
    (lambda: jf.Diffuse(1.5), r"Diffuse\.reflectance"),
    (lambda: jf.Glass(int_ior=0.0), r"Glass\.int_ior"),
    (lambda: jf.SamplingOptions(estimator="nope"), r"SamplingOptions\.estimator"),
    (lambda: jf.SamplingOptions(light_lobe=1.0), r"SamplingOptions\.light_lobe"),
    (lambda: jf.SamplingOptions(phase_lobe=1.5), r"SamplingOptions\.phase_lobe"),
    (lambda: jf.SamplingOptions(phase_lobe=float("nan")), r"SamplingOptions\.phase_lobe"),
])
def test_modules_refuse_bad_values_when_built(build, message):
    with pytest.raises(ValueError, match=message):
        build()


def test_replace_medium_validates_and_traced_values_pass():
    scene = jf.load_scene(os.path.join(SCENES, "spot_fog.json")).scene
    for bad in ({"g": 1.0}, {"g": 1.5}, {"sigma_t": -1.0}, {"albedo": 2.0}):
        with pytest.raises(ValueError):
            scene.replace_medium(**bad)
    with pytest.raises(ValueError, match="unknown parameter"):
        scene.replace_medium(sigma=1.0)
    # inside jit the values are traced: nothing to check, nothing raised
    g = jax.jit(lambda x: scene.replace_medium(g=x).medium.phase.g)(jnp.float32(0.3))
    assert float(g) == pytest.approx(0.3)


def test_scene_file_defaults_are_the_modules_defaults():
    """A scene file that leaves out every optional key builds the same Modules as Python code that leaves out the
    same arguments (spot cutoff and beam width, mirror reflectance, glass IORs, medium extent)."""
    data = json.load(open(os.path.join(SCENES, "mirror_glass.json")))
    data["lights"] = [{"type": "spot", "position": [0, 2, 0], "direction": [0, -1, 0], "intensity": 5.0}]
    data["shapes"] = [{"type": "sphere", "center": [0, 0, 0], "radius": 1, "bsdf": {"type": "mirror"}},
                      {"type": "sphere", "center": [2, 0, 0], "radius": 1, "bsdf": {"type": "glass"}}]
    data["medium"] = {"sigma_t": 0.5, "albedo": 0.9, "g": 0.3}
    scene = jf._scene_io.scene_from_dict(data).scene
    expected = (jf.SpotLight((0, 2, 0), (0, -1, 0), 5.0), jf.Mirror(), jf.Glass(),
                jf.HomogeneousMedium(sigma_t=0.5, albedo=0.9, phase=jf.HenyeyGreenstein(0.3)))
    got = (scene.lights[0], scene.shapes[0].bsdf, scene.shapes[1].bsdf, scene.medium)
    for a, b in zip(got, expected):
        la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
        assert jax.tree.structure(a) == jax.tree.structure(b), (a, b)
        for x, y in zip(la, lb):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_rayleigh_in_a_scene_file():
    data = json.load(open(os.path.join(SCENES, "spot_fog.json")))
    data["medium"] = {"sigma_t": 0.5, "albedo": 0.9, "phase": {"type": "rayleigh"}}
    assert isinstance(jf._scene_io.scene_from_dict(data).scene.medium.phase, jf.Rayleigh)
    data["medium"]["g"] = 0.3
    with pytest.raises(jf.SceneError, match="both g and phase"):
        jf._scene_io.scene_from_dict(data)
