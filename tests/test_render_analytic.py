"""Renders through `jaxfog.render` against exact float64 references (estimators.md, "Exact references for tests").

Every reference is written from conventions.md (camera, lights, BSDFs, HG) and computed in float64 numpy/scipy,
averaged over each pixel's square with a Gauss–Legendre grid (the renderer jitters its samples uniformly over the
pixel, so a pixel's expected value is that average). Each estimate comes from `N_KEYS` = 32 independent renders
(fixed keys); per-pixel standard errors come from their spread. Acceptance rules (max |z| 5.5, <= 3% of |z| > 3,
mean z^2 <= 1.5, per-channel |mean z| <= 4/sqrt(n_pixels)): `conftest.assert_statistically_equal`.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest
from scipy import integrate

import jaxfog as jf
from jaxfog._lights import spot_falloff

# tests/ is on sys.path (pytest's default rootdir-relative import of conftest)
from helpers import CameraSpec, hg_np, make_floor, spot_falloff_np

POINT_POS = (0.8, 1.5, 0.4)
POINT_I = np.array([6.0, 5.0, 4.0])
FLOOR_R = np.array([0.7, 0.5, 0.3])
EXTENT = 1000.0  # HomogeneousMedium's default extent: the renderer integrates each escaping ray up to here


# ================================================================================ float64 reference helpers
def floor_hits(cam: CameraSpec, n: int):
    """Camera rays (n x n per pixel) meeting the floor y = 0: `(points (H, W, n*n, 3), camera distance, weights)`."""
    o, d, w = cam.rays(n)
    assert np.all(d[..., 1] < 0)
    t = -o[1] / d[..., 1]
    p = o + t[..., None] * d
    assert np.all(np.abs(p[..., 0]) < 7.5) and np.all(np.abs(p[..., 2]) < 7.5)  # inside the 16 x 16 floor
    return p, t, w


def point_lit_floor_reference(cam, n, light_pos, intensity, reflectance, sigma_t=None, spot=None):
    """Pixel averages of `R/pi * I(theta) cos / d^2 * exp(-sigma_t (d_cam + d))` on the floor (normal +y)."""
    p, t_cam, w = floor_hits(cam, n)
    v = np.asarray(light_pos) - p
    dist = np.linalg.norm(v, axis=-1)
    cos_l = np.maximum(v[..., 1] / dist, 0.0)
    falloff = 1.0
    if spot is not None:
        axis, cutoff, beam = spot
        axis = np.asarray(axis) / np.linalg.norm(axis)
        theta = np.arccos(np.clip(np.sum(-v * axis, axis=-1) / dist, -1, 1))
        falloff = spot_falloff_np(theta, cutoff, beam)
    scalar = falloff * cos_l / dist**2
    L = (reflectance / np.pi * intensity) * scalar[..., None]
    if sigma_t is not None:
        L = L * np.exp(-np.asarray(sigma_t) * (t_cam + dist)[..., None])
    return np.einsum("hwkc,k->hwc", L, w)


def rect_vertices(center, edge_u, edge_v):
    c, u, v = (np.asarray(x, np.float64) for x in (center, edge_u, edge_v))
    return np.stack([c - 0.5 * u - 0.5 * v, c + 0.5 * u - 0.5 * v, c + 0.5 * u + 0.5 * v, c - 0.5 * u + 0.5 * v])


def irradiance_lambert(p, normal, verts, radiance):
    """Irradiance at points `p` (..., 3) with unit `normal` from a uniformly emitting polygon (all of it above the
    points' horizon, its front facing them): Lambert's closed form E = L/2 |sum_i Theta_i n . normalize(v_i x v_i+1)|,
    v_i = vertex_i - p, Theta_i the angle between v_i and v_i+1."""
    v = verts[None] - p.reshape(-1, 1, 3)
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    w = np.roll(v, -1, axis=1)
    theta = np.arccos(np.clip(np.sum(v * w, axis=-1), -1, 1))
    c = np.cross(v, w)
    c /= np.linalg.norm(c, axis=-1, keepdims=True)
    e = 0.5 * np.abs(np.sum(theta * (c @ np.asarray(normal, np.float64)), axis=-1))
    return e.reshape(p.shape[:-1])[..., None] * np.asarray(radiance, np.float64)


def irradiance_quadrature(p, normal, center, edge_u, edge_v, radiance, n_light=48):
    """The same irradiance by Gauss–Legendre over the rectangle: int_A L cos_x cos_l / r^2 dA (front side only)."""
    x, wl = np.polynomial.legendre.leggauss(n_light)
    a, b = np.meshgrid(0.5 * x, 0.5 * x, indexing="ij")
    center, edge_u, edge_v = (np.asarray(q, np.float64) for q in (center, edge_u, edge_v))
    y = center + a.reshape(-1, 1) * edge_u + b.reshape(-1, 1) * edge_v
    cr = np.cross(edge_u, edge_v)
    area_w = (0.25 * np.outer(wl, wl)).reshape(-1) * np.linalg.norm(cr)
    v = y[None] - p.reshape(-1, 1, 3)
    r2 = np.sum(v * v, axis=-1)
    cos_x = np.maximum(v @ np.asarray(normal, np.float64), 0.0) / np.sqrt(r2)
    cos_l = np.maximum(-(v @ (cr / np.linalg.norm(cr))), 0.0) / np.sqrt(r2)
    e = np.sum(cos_x * cos_l / r2 * area_w, axis=-1)
    return e.reshape(p.shape[:-1])[..., None] * np.asarray(radiance, np.float64)


def area_lit_floor_reference(cam, n, center, edge_u, edge_v, radiance, reflectance):
    """Pixel averages of `R/pi * E` on the floor (normal +y) under a rectangular area light, E from Lambert's form."""
    p, _, w = floor_hits(cam, n)
    E = irradiance_lambert(p, (0.0, 1.0, 0.0), rect_vertices(center, edge_u, edge_v), radiance)
    return np.einsum("hwkc,k->hwc", reflectance / np.pi * E, w)


def test_lambert_irradiance_matches_quadrature():
    """The closed form used by the area-light references equals a 48 x 48 Gauss–Legendre integral (1e-6 relative)."""
    p = np.array([[0.0, 0.0, 0.0], [1.5, 0.0, -2.0], [-2.0, 0.0, 2.5], [0.3, 0.0, -0.8]])
    for center, eu, ev in [((0.3, 1.5, -0.8), (2.4, 0.0, 0.0), (0.0, 0.0, 1.6)),
                           ((0.0, 1.5, -1.0), (12.0, 0.0, 0.0), (0.0, 0.0, 12.0))]:
        exact = irradiance_lambert(p, (0.0, 1.0, 0.0), rect_vertices(center, eu, ev), (1.0, 2.0, 3.0))
        quad = irradiance_quadrature(p, (0.0, 1.0, 0.0), center, eu, ev, (1.0, 2.0, 3.0), n_light=200)
        np.testing.assert_allclose(exact, quad, rtol=1e-6)


def _ray_light_geometry(o, dirs, c, extent):
    """Projection `delta` of the light on each ray, distance `D` from the ray's line, and the angles
    `phi_a, phi_b` of the ray's ends [0, extent] seen from the light (t = delta + D tan(phi))."""
    delta = dirs @ (c - o)
    D = np.linalg.norm((c - o)[None] - delta[:, None] * dirs, axis=-1)
    # the half-line t >= 0 must keep away from the light (its line may pass close when the ray points away)
    dist_to_ray = np.where(delta > 0, D, np.linalg.norm(c - o))
    assert dist_to_ray.min() > 0.05, "a ray passes too close to the light for this reference"
    return delta, D, np.arctan2(-delta, D), np.arctan2(extent - delta, D)


def _in_scatter_integrand(tau, o, dirs, c, intensity, sigma_t, sigma_s, g, geometry, spot):
    """Integrand over tau in [0, 1] (phi = phi_a + tau (phi_b - phi_a)), rays x channels; tau broadcasts (N, K)."""
    delta, D, phi_a, phi_b = (x[:, None] for x in geometry)
    phi = phi_a + tau * (phi_b - phi_a)
    t = delta + D * np.tan(phi)
    r = D / np.cos(phi)
    phase = g if callable(g) else (lambda c: hg_np(c, g))  # g: HG's g, or a float64 phase function of cos
    val = (phi_b - phi_a) / D * phase(-np.sin(phi))  # cos(theta_s) = -sin(phi)
    if spot is not None:
        axis = np.asarray(spot[0], np.float64) / np.linalg.norm(spot[0])
        x = o + t[..., None] * dirs[:, None, :]
        cos_axis = np.sum((x - c) * axis, axis=-1) / r
        val = val * spot_falloff_np(np.arccos(np.clip(cos_axis, -1, 1)), spot[1], spot[2])
    return val[..., None] * np.exp(-sigma_t * (t + r)[..., None]) * (sigma_s * np.asarray(intensity))


def _cone_crossings(o, dirs, c, spot, geometry, n_grid=1025, n_bisect=50):
    """Values of tau where each ray crosses the spot's beam or cutoff cone (kinks of the integrand): sign changes
    on a dense grid, refined by bisection. Returns a list (per ray) of sorted crossing taus."""
    axis = np.asarray(spot[0], np.float64) / np.linalg.norm(spot[0])
    delta, D, phi_a, phi_b = geometry

    def angle(tau, rows):
        phi = phi_a[rows] + tau * (phi_b[rows] - phi_a[rows])
        x = o + (delta[rows] + D[rows] * np.tan(phi))[..., None] * dirs[rows]
        v = x - c
        return np.arccos(np.clip(v @ axis / np.linalg.norm(v, axis=-1), -1, 1))

    grid = np.linspace(0.0, 1.0, n_grid)
    rows = np.arange(len(dirs))
    ang = np.stack([angle(grid, np.full(n_grid, i)) for i in rows])  # (N, n_grid)
    found = [[] for _ in rows]
    for limit in np.deg2rad([spot[1], spot[2]]):
        h = ang - limit
        ri, ji = np.nonzero(np.sign(h[:, :-1]) != np.sign(h[:, 1:]))
        lo, hi = grid[ji], grid[ji + 1]
        s_lo = np.sign(h[ri, ji])
        for _ in range(n_bisect):
            mid = 0.5 * (lo + hi)
            same = np.sign(angle(mid, ri) - limit) == s_lo
            lo, hi = np.where(same, mid, lo), np.where(same, hi, mid)
        for i, x in zip(ri, 0.5 * (lo + hi)):
            found[i].append(x)
    return [sorted(f) for f in found]


def single_scatter_reference(cam, n, lights, sigma_t, albedo, g, extent=EXTENT):
    """Pixel averages of the single-scattered radiance along each camera ray in an unbounded medium:

        sum over lights of  int_0^extent sigma_s e^{-sigma_t t} p_HG(cos theta_s) I(x) e^{-sigma_t r} / r^2 dt,

    `lights`: list of `(position, intensity RGB, spot or None)`, `spot = (axis, cutoff_deg, beam_deg)`.
    Substituting t = Delta + D tan(phi) (Delta, D: the light's projection on and distance from the ray) turns the
    integrand into sigma_s I / D e^{-sigma_t (t + r)} p_HG(-sin phi) falloff, smooth in phi except at spot cone
    crossings. Point lights: one `scipy.integrate.quad_vec` call per light integrates all rays and channels at once
    over tau in [0, 1] (phi = phi_a + tau (phi_b - phi_a)), adaptively, to 1e-10 relative. Spot lights: composite
    16-point Gauss–Legendre on 16 panels between consecutive cone crossings (kinks located to 1e-15), cross-checked
    against scipy quad in `test_single_scatter_reference_matches_plain_quad`.
    """
    o, d, w = cam.rays(n)
    dirs = d.reshape(-1, 3)
    sigma_t, albedo = np.asarray(sigma_t, np.float64), np.asarray(albedo, np.float64)
    sigma_s = sigma_t * albedo
    total = np.zeros((dirs.shape[0], 3))
    for pos, intensity, spot in lights:
        c = np.asarray(pos, np.float64)
        geometry = _ray_light_geometry(o, dirs, c, extent)
        args = (o, dirs, c, intensity, sigma_t, sigma_s, g, geometry, spot)
        if spot is None:
            res, _ = integrate.quad_vec(lambda tau: _in_scatter_integrand(np.array([[tau]]), *args)[:, 0], 0.0, 1.0,
                                        epsrel=1e-10, epsabs=1e-12, norm="max", limit=20000)
            total += res
            continue
        crossings = _cone_crossings(o, dirs, c, spot, geometry)
        n_pieces = 1 + max(len(x) for x in crossings)
        bounds = np.ones((len(dirs), n_pieces + 1))
        bounds[:, 0] = 0.0
        for i, x in enumerate(crossings):
            bounds[i, 1:1 + len(x)] = x
        gx, gw = np.polynomial.legendre.leggauss(16)
        panel = (np.arange(16)[:, None] + 0.5 * (gx[None] + 1)).reshape(-1) / 16  # 16 panels x 16 nodes in [0, 1]
        panel_w = np.tile(gw, 16) / 32
        lo, hi = bounds[:, :-1], bounds[:, 1:]  # (N, P)
        tau = (lo[..., None] + (hi - lo)[..., None] * panel).reshape(len(dirs), -1)
        wts = ((hi - lo)[..., None] * panel_w).reshape(len(dirs), -1)
        total += np.einsum("nkc,nk->nc", _in_scatter_integrand(tau, *args), wts)
    return np.einsum("hwkc,k->hwc", total.reshape(d.shape[0], d.shape[1], d.shape[2], 3), w)


def test_single_scatter_reference_matches_plain_quad():
    """The phi-substituted references (quad_vec for point lights, kink-aware Gauss–Legendre for spots) equal scipy
    quad directly over t, for a few rays of each kind (float64, 1e-7 relative)."""
    sigma_t, albedo, g = np.array([0.4, 0.6, 0.9]), np.array([0.9, 0.8, 0.7]), 0.6
    cases = [
        (CameraSpec(origin=(0.0, 0.0, 0.0), target=(0.0, 0.0, -1.0), fov=30.0, width=2, height=1),
         ((1.2, 0.3, -2.5), (4.0, 3.0, 2.0), None)),
        (CameraSpec(origin=(0.0, 0.0, 0.0), target=(0.0, 0.5, -3.0), fov=30.0, width=3, height=1),
         ((0.0, 2.0, -3.0), (30.0, 25.0, 20.0), ((0.0, -1.0, 0.0), 25.0, 15.0))),
        (CameraSpec(origin=(0.1, 1.0, -3.1), target=(0.4, -2.0, -3.0), up=(0.0, 0.0, -1.0), fov=30.0, width=2,
                    height=1), ((0.0, 2.0, -3.0), (30.0, 25.0, 20.0), ((0.0, -1.0, 0.0), 25.0, 15.0))),
    ]
    for cam, light in cases:
        ref = single_scatter_reference(cam, 1, [light], sigma_t, albedo, g)
        o, d, _ = cam.rays(1)
        c = np.asarray(light[0])
        for col in range(cam.width):
            dd = d[0, col, 0]

            def integrand(t, ch):
                x = o + t * dd
                v = c - x
                r = np.linalg.norm(v)
                cos_s = dd @ v / r  # light travels along -v, then along -dd toward the camera
                fall = 1.0
                if light[2] is not None:
                    axis = np.asarray(light[2][0]) / np.linalg.norm(light[2][0])
                    fall = spot_falloff_np(np.arccos(np.clip(-v @ axis / r, -1, 1)), light[2][1], light[2][2])
                return (sigma_t[ch] * albedo[ch] * np.exp(-sigma_t[ch] * t) * hg_np(cos_s, g) * light[1][ch]
                        * fall * np.exp(-sigma_t[ch] * r) / r**2)

            for ch in range(3):
                val = integrate.quad(integrand, 0.0, 60.0, args=(ch,), limit=2000, points=[max(dd @ (c - o), 0.0)],
                                     epsabs=1e-13, epsrel=1e-11)[0]
                assert ref[0, col, ch] == pytest.approx(val, rel=1e-7, abs=1e-12)


# ================================================================================ (e) Lambertian floor, point light
def test_lambertian_floor_point_light(floor_scene, stats):
    """No fog: pixel = R/pi * I cos / d^2 (conventions.md), per pixel. The only noise is the pixel jitter."""
    scene, cam, R = floor_scene([jf.PointLight(POINT_POS, POINT_I)], max_depth=2, reflectance=FLOOR_R)
    ref = point_lit_floor_reference(cam, 6, POINT_POS, POINT_I, R)
    mean, se = stats.mean_and_se(stats.render_keys(scene, 4, seed=11))
    stats.assert_statistically_equal(mean, se, ref, label="lambertian floor")
    # the floor must not be lit from behind: the same light below the floor gives black
    below, _, _ = floor_scene([jf.PointLight((0.8, -1.5, 0.4), POINT_I)], max_depth=2, reflectance=FLOOR_R)
    img = jf.render(below, jax.random.key(0), 4, batch_paths=cam.width * cam.height * 4)
    assert float(np.max(np.asarray(img))) == 0.0


# ================================================================================ (a) absorption only
@pytest.mark.parametrize("sigma_t", [(0.3, 0.5, 0.8), (0.0, 0.0, 0.0)])
def test_absorbing_fog_is_beer_lambert(floor_scene, fog, stats, sigma_t):
    """Albedo 0: pixel = (fog-free pixel) * exp(-sigma_t (d_camera + d_light)) per channel (estimators.md).
    sigma_t = 0 is a valid medium and must give the fog-free image (conventions.md). max_depth 3: the extra bounce
    finds nothing to add."""
    medium = fog(sigma_t, 0.0, g=0.3)
    scene, cam, R = floor_scene([jf.PointLight(POINT_POS, POINT_I)], medium=medium, max_depth=3, reflectance=FLOOR_R)
    ref = point_lit_floor_reference(cam, 6, POINT_POS, POINT_I, R, sigma_t=sigma_t)
    mean, se = stats.mean_and_se(stats.render_keys(scene, 16, seed=12))
    stats.assert_statistically_equal(mean, se, ref, label=f"absorbing fog {sigma_t}")


# ================================================================================ (b) single scattering
SS_CAMERA = CameraSpec(origin=(0.0, 0.0, 0.0), target=(0.0, 0.0, -1.0), fov=30.0, width=16, height=12)
SS_POINTS = [((1.2, 0.3, -2.5), (4.0, 3.0, 2.0), None),  # in front, just outside the view
             ((-0.8, -0.5, 1.0), (2.0, 2.0, 3.0), None)]  # behind the camera
SS_SPOT = ((0.0, 2.0, -3.0), (30.0, 25.0, 20.0), ((0.0, -1.0, 0.0), 25.0, 15.0))  # position, I, (axis, cutoff, beam)
SS_SIGMA_T, SS_ALBEDO = (0.4, 0.6, 0.9), (0.9, 0.8, 0.7)
SS_G = (-0.5, 0.0, 0.6)
SS_BATCH = 16 * 12 * 16  # 16 layers per compiled call, whatever the spp: one compilation per `equiangular`


def single_scatter_scene(cam: CameraSpec, fog, g, points_on: bool, spot_on: bool) -> jf.Scene:
    """No surfaces, max_depth 2 (single scattering), two point lights and a spot light; switching a light off sets
    its intensity to 0 (a traced value: every variant shares one compiled program)."""
    pos, intensity, (axis, cutoff, beam) = SS_SPOT
    lights = tuple(jf.PointLight(p, np.asarray(i) * points_on) for p, i, _ in SS_POINTS)
    lights += (jf.SpotLight(pos, axis, np.asarray(intensity) * spot_on, cutoff, beam),)
    return jf.Scene(camera=cam.build(), lights=lights, medium=fog(SS_SIGMA_T, SS_ALBEDO, g), max_depth=2)


@pytest.fixture(scope="module")
def single_scatter_refs():
    return {g: single_scatter_reference(SS_CAMERA, 3, SS_POINTS, SS_SIGMA_T, SS_ALBEDO, g) for g in SS_G}


@pytest.mark.parametrize("equiangular", [True, False])
def test_single_scattering_point_lights(fog, stats, single_scatter_refs, equiangular):
    """max_depth 2, two point lights (the spot is off), no surfaces, RGB fog: each pixel matches the float64
    quadrature of the in-scattering integral, for g in {-0.5, 0, 0.6}, with and without equiangular sampling."""
    for g in SS_G:
        scene = single_scatter_scene(SS_CAMERA, fog, g, points_on=True, spot_on=False)
        mean, se = stats.mean_and_se(stats.render_keys(scene, 16, seed=13, equiangular=equiangular,
                                                       batch_paths=SS_BATCH))
        stats.assert_statistically_equal(mean, se, single_scatter_refs[g],
                                         label=f"single scatter g={g} eq={equiangular}")


def rayleigh_np(cos_theta):
    """Rayleigh phase function in float64: 3 (1 + cos^2) / (16 pi)."""
    return 3.0 * (1.0 + cos_theta**2) / (16.0 * np.pi)


def test_single_scattering_rayleigh(stats):
    """max_depth 2 in Rayleigh haze (the phase function behind the interface, sampled by its cubic), two point
    lights, RGB fog: each pixel matches the float64 quadrature of the in-scattering integral with p = 3(1+mu^2)/16pi."""
    ref = single_scatter_reference(SS_CAMERA, 3, SS_POINTS, SS_SIGMA_T, SS_ALBEDO, rayleigh_np)
    haze = lambda sigma_t, albedo, g: jf.HomogeneousMedium(sigma_t=sigma_t, albedo=albedo, phase=jf.Rayleigh())
    scene = single_scatter_scene(SS_CAMERA, haze, None, points_on=True, spot_on=False)
    mean, se = stats.mean_and_se(stats.render_keys(scene, 16, seed=17, batch_paths=SS_BATCH))
    stats.assert_statistically_equal(mean, se, ref, label="single scatter rayleigh")


# ================================================================================ (c) spot lights
@pytest.mark.parametrize("cutoff, beam", [(20.0, 15.0), (30.0, 10.0), (25.0, 25.0)])
def test_spot_falloff_formula(cutoff, beam):
    """`spot_falloff(cos theta)` = 1 for theta <= beam, (cutoff - theta)/(cutoff - beam) between, 0 beyond (radians;
    conventions.md), at angles across [0, 45] degrees including both edges. Tolerance: float32 arccos near the
    ramp, 1e-4 of the ramp's unit height."""
    theta_deg = np.unique(np.concatenate([np.linspace(0.0, 45.0, 181), [beam, cutoff, beam + 1e-3, cutoff - 1e-3]]))
    theta = np.deg2rad(theta_deg)
    got = np.asarray(jax.vmap(lambda c: spot_falloff(c, cutoff, beam))(np.cos(theta).astype(np.float32)))
    expected = spot_falloff_np(theta, cutoff, beam)
    away_from_edges = (np.abs(theta_deg - beam) > 1e-2) & (np.abs(theta_deg - cutoff) > 1e-2)
    np.testing.assert_allclose(got[away_from_edges], expected[away_from_edges], atol=1e-4)
    assert np.all((got >= 0) & (got <= 1))
    assert np.all(got[theta_deg > cutoff + 1e-2] == 0.0) and np.all(got[theta_deg < beam - 1e-2] == 1.0)


SPOT_POS = (0.3, 2.0, -0.5)
SPOT_AXIS = (0.2, -1.0, 0.1)
SPOT_I = np.array([20.0, 15.0, 10.0])


def test_spot_lit_floor(floor_scene, stats):
    """No fog: floor pixel = I falloff(theta) R/pi cos / d^2; the cone's edge and ramp fall inside the image."""
    spot = jf.SpotLight(SPOT_POS, SPOT_AXIS, SPOT_I, cutoff_angle=25.0, beam_width=15.0)
    scene, cam, R = floor_scene([spot], max_depth=2, reflectance=FLOOR_R)
    ref = point_lit_floor_reference(cam, 12, SPOT_POS, SPOT_I, R, spot=(SPOT_AXIS, 25.0, 15.0))
    assert np.mean(ref[..., 0] == 0) > 0.3 and np.mean(ref[..., 0] > 0) > 0.1  # both inside and outside the cone
    # 64 spp per key: pixels that the cone's edge barely touches are lit by a few % of their samples; the per-key
    # means must contain enough of those for their spread to estimate the SE (at 4 spp they were often all 0).
    mean, se = stats.mean_and_se(stats.render_keys(scene, 64, seed=14))
    stats.assert_statistically_equal(mean, se, ref, label="spot-lit floor")


SPOT_SS_CAMERAS = {
    # outside the cone, looking across the beam (rays enter and leave the cone: a bounded interval)
    "across": CameraSpec(origin=(0.0, 0.0, 0.0), target=(0.0, 0.5, -3.0), fov=30.0, width=16, height=12),
    # on the axis below the spot, looking up and sideways: rays inside the cone's angle (toward the apex) and outside
    "up_from_inside": CameraSpec(origin=(0.0, -0.5, -3.0), target=(1.0, 2.0, -3.0), up=(0.0, 0.0, -1.0),
                                 fov=20.0, width=16, height=12),
    # inside the cone under the spot, looking down and away from it (half-infinite intervals)
    "down_from_inside": CameraSpec(origin=(0.1, 1.0, -3.1), target=(0.4, -2.0, -3.0), up=(0.0, 0.0, -1.0),
                                   fov=30.0, width=16, height=12),
}


@pytest.fixture(scope="module")
def spot_scatter_refs():
    return {name: single_scatter_reference(cam, 3, [SS_SPOT], SS_SIGMA_T, SS_ALBEDO, 0.3)
            for name, cam in SPOT_SS_CAMERAS.items()}


@pytest.mark.parametrize("equiangular", [True, False])
def test_single_scattering_spot_light(fog, stats, spot_scatter_refs, equiangular):
    """Spot light in fog (point lights off), max_depth 2, no surfaces: matches the quadrature for three camera
    placements that cover the cases of the ray/cone interval that equiangular sampling is restricted to (bounded,
    toward the apex, away from it)."""
    for name, cam in SPOT_SS_CAMERAS.items():
        scene = single_scatter_scene(cam, fog, 0.3, points_on=False, spot_on=True)
        ref = spot_scatter_refs[name]
        assert np.mean(ref[..., 0] > 1e-6) > 0.2  # the beam is in view
        # 64 spp per key: the per-key means must be close to normal for the t statistics (per-sample skewness is
        # up to 0.8 without equiangular sampling; at 16 spp it inflated mean z^2 to 1.6 with an unbiased image mean)
        mean, se = stats.mean_and_se(stats.render_keys(scene, 64, seed=15, equiangular=equiangular,
                                                       batch_paths=SS_BATCH))
        # ref_atol: the 3 x 3 pixel-footprint rule is inexact for pixels straddling the cone's silhouette, where the
        # radiance vanishes like (depth into the cone)^(3/2) (chord ~ sqrt, falloff ~ linear): ~1e-6 of the maximum
        stats.assert_statistically_equal(mean, se, ref, label=f"spot scatter {name} eq={equiangular}",
                                         ref_atol=1e-5 * ref.max())


# ================================================================================ (f) area lights
AREA_CENTER, AREA_U, AREA_V = (0.3, 1.5, -0.8), (2.4, 0.0, 0.0), (0.0, 0.0, 1.6)  # front face: -y (down)
AREA_L = np.array([5.0, 4.0, 3.0])
AREA_CAMERA = CameraSpec(origin=(0.0, 1.2, 3.0), target=(0.0, 0.0, 0.5), fov=40.0, width=16, height=12)
"""Below the light's height and looking down: sees only the floor (which it fills)."""


def test_area_light_seen_directly():
    """A camera facing the emitting side sees exactly L in every pixel (max_depth 1: only lights seen directly);
    the back side is black."""
    cam = CameraSpec(origin=(0.0, 0.0, 2.0), target=(0.0, 0.0, 0.0), fov=30.0, width=8, height=6)
    front = jf.AreaLight((0.0, 0.0, 0.0), (3.0, 0.0, 0.0), (0.0, 3.0, 0.0), AREA_L)  # normal +z, toward the camera
    back = jf.AreaLight((0.0, 0.0, 0.0), (0.0, 3.0, 0.0), (3.0, 0.0, 0.0), AREA_L)  # normal -z
    img = jf.render(jf.Scene(camera=cam.build(), lights=(front,), max_depth=1), jax.random.key(1), 4)
    np.testing.assert_allclose(np.asarray(img), np.broadcast_to(AREA_L, img.shape), rtol=1e-6)
    img = jf.render(jf.Scene(camera=cam.build(), lights=(back,), max_depth=1), jax.random.key(1), 4)
    assert float(np.max(np.asarray(img))) == 0.0


@pytest.mark.parametrize("near_clip", [0.0, 0.7])
def test_area_light_through_absorbing_fog(fog, stats, near_clip):
    """Albedo-0 fog: the emitter seen directly is L exp(-sigma_t d) per channel, d = distance to the light; with a
    near clip plane the ray starts `near_clip / cos` along (cos: its angle to the camera's axis), as Mitsuba's."""
    cam = CameraSpec(origin=(0.0, 0.0, 2.0), target=(0.0, 0.0, 0.0), fov=30.0, width=16, height=12)
    sigma_t = np.array([0.3, 0.5, 0.8])
    camera = jf.Camera(origin=cam.origin, target=cam.target, up=cam.up, fov=cam.fov, width=cam.width,
                       height=cam.height, near_clip=near_clip)
    scene = jf.Scene(camera=camera, lights=(jf.AreaLight((0.0, 0.0, 0.0), (3.0, 0.0, 0.0), (0.0, 3.0, 0.0),
                                                         AREA_L),),
                     medium=fog(sigma_t, 0.0), max_depth=2)
    o, d, w = cam.rays(6)
    t = -o[2] / d[..., 2] - near_clip / -d[..., 2]  # the axis is -z
    ref = np.einsum("hwkc,k->hwc", AREA_L * np.exp(-sigma_t * t[..., None]), w)
    mean, se = stats.mean_and_se(stats.render_keys(scene, 16, seed=16))
    stats.assert_statistically_equal(mean, se, ref, label="area light through absorbing fog")


def test_area_lit_floor_matches_quadrature(floor_scene, stats):
    """Diffuse floor under a rectangular area light: pixel = R/pi * int L cos cos / r^2 dA. Light sampling and BSDF
    sampling both reach the light on the second segment (max_depth 2), combined by MIS: the sum must be unbiased."""
    light = jf.AreaLight(AREA_CENTER, AREA_U, AREA_V, AREA_L)
    ref = area_lit_floor_reference(AREA_CAMERA, 4, AREA_CENTER, AREA_U, AREA_V, AREA_L, FLOOR_R)
    scene, cam, _ = floor_scene([light], max_depth=2, reflectance=FLOOR_R, camera=AREA_CAMERA)
    mean, se = stats.mean_and_se(stats.render_keys(scene, 16, seed=17))
    stats.assert_statistically_equal(mean, se, ref, label="area-lit floor")


# ================================================================================ (d) glass and mirror
def test_index_matched_glass_is_invisible(stats):
    """A glass sphere with int_ior = ext_ior = 1 on the floor's path to the light and in view changes nothing in
    expectation: the image matches the exact image of the floor without it. Light sampling is blocked by the
    sphere; BSDF sampling through it must make up for it. The emitter is large (12 x 12, above the camera and out
    of view) so that those BSDF samples hit it often: with a small light they are rare events (a few per thousand
    samples in the penumbra) whose per-key means are too skewed for the t statistics. max_depth 6 covers
    camera -> sphere -> floor -> sphere -> light."""
    center, eu, ev, L = (0.0, 1.5, -1.0), (12.0, 0.0, 0.0), (0.0, 0.0, 12.0), np.array([2.0, 1.5, 1.0])
    light = jf.AreaLight(center, eu, ev, L)
    sphere = jf.Sphere((0.2, 0.6, -0.6), 0.45, jf.Glass(int_ior=1.0, ext_ior=1.0))
    scene = jf.Scene(camera=AREA_CAMERA.build(), shapes=(sphere, make_floor(FLOOR_R)), lights=(light,), max_depth=6)
    ref = area_lit_floor_reference(AREA_CAMERA, 4, center, eu, ev, L, FLOOR_R)
    mean, se = stats.mean_and_se(stats.render_keys(scene, 16, seed=18))
    stats.assert_statistically_equal(mean, se, ref, label="index-matched glass sphere")


def test_mirror_shows_the_mirrored_scene(stats):
    """A mirror wall z = 0 (reflectance R) in front of the camera, a diffuse sphere and a point light behind the
    camera: the image equals R times the image of the mirrored sphere and light (z -> -z) seen without the mirror.
    Both sides are estimates; their standard errors add."""
    cam = CameraSpec(origin=(0.0, 1.0, 3.0), target=(0.0, 1.0, 0.0), fov=20.0, width=16, height=12)
    R = np.array([0.9, 0.8, 0.7])
    sphere_c, light_p = np.array([0.3, 1.2, 4.5]), np.array([-1.0, 2.5, 3.6])
    flip = np.array([1.0, 1.0, -1.0])
    diffuse = jf.Diffuse((0.6, 0.7, 0.8))
    mirror = jf.Rectangle((0.0, 1.0, 0.0), (6.0, 0.0, 0.0), (0.0, 6.0, 0.0), jf.Mirror(R))
    with_mirror = jf.Scene(camera=cam.build(), shapes=(jf.Sphere(sphere_c, 0.7, diffuse), mirror),
                           lights=(jf.PointLight(light_p, (5.0, 5.0, 5.0)),), max_depth=3)
    mirrored = jf.Scene(camera=cam.build(), shapes=(jf.Sphere(sphere_c * flip, 0.7, diffuse),),
                        lights=(jf.PointLight(light_p * flip, (5.0, 5.0, 5.0)),), max_depth=2)
    a_mean, a_se = stats.mean_and_se(stats.render_keys(with_mirror, 4, seed=19))
    b_mean, b_se = stats.mean_and_se(stats.render_keys(mirrored, 4, seed=20))
    assert np.mean(b_mean[..., 0] > 0) > 0.15  # the sphere covers a good part of the image
    stats.assert_statistically_equal(a_mean, a_se, R * b_mean, ref_se=R * b_se, label="mirror")
