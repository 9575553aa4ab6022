"""Fog confined to an axis-aligned box (`HomogeneousMedium(bounds=...)`, scene key `medium.bounds`).

Anchors: the slab intersection against hand-computed chords (value and gradient, rays with zero direction
components); the medium's transmittance against float64 chords; the free-flight density integrating to the branch
probability over the fog's part of the segment and vanishing outside it; renders against float64 references
(Beer–Lambert through the box, single scattering by quadrature along each camera ray), with the acceptance rules of
`helpers.assert_statistically_equal` (per-pixel SEs from `N_KEYS` independent renders, fixed seeds); the scene file's
checks; and the Mitsuba export (a cube at the box, the sensor's medium only inside it).
"""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate

import jaxfog as jf
from jaxfog._medium import box_interval, inside_box

from helpers import CameraSpec, hg_np, make_floor

LO, HI = np.array([-1.0, -0.5, -4.0]), np.array([1.0, 1.5, -1.5])


def chord_np(o, d, t_end, lo=LO, hi=HI):
    """Float64 length of `[0, t_end]` of the ray `o + t d` inside the box (slab method, d without zero components
    or with the origin handled by the caller)."""
    o, d = np.asarray(o, np.float64), np.asarray(d, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (lo - o) / d, (hi - o) / d
    near = np.where(d != 0, np.minimum(ta, tb), np.where((o >= lo) & (o <= hi), -np.inf, np.inf))
    far = np.where(d != 0, np.maximum(ta, tb), np.where((o >= lo) & (o <= hi), np.inf, -np.inf))
    t0, t1 = max(near.max(), 0.0), min(far.min(), t_end)
    return max(t1 - t0, 0.0)


# ======================================================================================== the slab intersection
@pytest.mark.parametrize(
    "o, d, expect",
    [
        ((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), (1.5, 4.0)),  # straight in through the front face
        ((0.0, 0.0, -2.0), (1.0, 0.0, 0.0), (-1.0, 1.0)),  # inside, along x (two zero components)
        ((0.0, 2.0, 0.0), (0.0, 0.0, -1.0), None),  # above the slab in y, d_y = 0: misses
        ((3.0, 0.0, -2.0), (-0.6, 0.0, -0.8), None),  # passes beside the box
        ((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), None),  # looks away: the box is behind
    ],
)
def test_box_interval_values_and_finite_gradients(o, d, expect):
    t0, t1 = box_interval(jnp.asarray(LO, jnp.float32), jnp.asarray(HI, jnp.float32), jnp.asarray(o, jnp.float32),
                          jnp.asarray(d, jnp.float32))
    if expect is None:
        assert float(t0) > float(t1) or float(t1) < 0
    else:
        assert float(t0) == pytest.approx(expect[0], abs=1e-6) and float(t1) == pytest.approx(expect[1], abs=1e-6)
    # value and gradient of what the tracer uses: the clipped length, finite for every ray (d = 0 components too)
    def length(o, d):
        a, b = box_interval(jnp.asarray(LO, jnp.float32), jnp.asarray(HI, jnp.float32), o, d)
        return jnp.maximum(jnp.minimum(b, 10.0) - jnp.maximum(a, 0.0), 0.0)

    g_o, g_d = jax.grad(length, argnums=(0, 1))(jnp.asarray(o, jnp.float32), jnp.asarray(d, jnp.float32))
    assert np.all(np.isfinite(np.asarray(g_o))) and np.all(np.isfinite(np.asarray(g_d)))
    assert float(length(jnp.asarray(o, jnp.float32), jnp.asarray(d, jnp.float32))) == pytest.approx(
        chord_np(o, d, 10.0), abs=1e-6)


def test_inside_box_is_closed():
    lo, hi = jnp.asarray(LO, jnp.float32), jnp.asarray(HI, jnp.float32)
    assert bool(inside_box(lo, hi, jnp.asarray(LO, jnp.float32)))
    assert bool(inside_box(lo, hi, jnp.asarray((0.0, 0.0, -2.0))))
    assert not bool(inside_box(lo, hi, jnp.asarray((0.0, 1.6, -2.0))))


# ============================================================================================ the medium itself
def _medium(sigma_t=(0.7, 1.1, 1.6), albedo=0.8, g=0.4, bounds=(LO, HI)):
    return jf.HomogeneousMedium(sigma_t=sigma_t, albedo=albedo, phase=jf.HenyeyGreenstein(g), bounds=bounds)


def test_transmittance_is_beer_lambert_over_the_chord_with_its_gradient():
    rng = np.random.default_rng(3)
    med = _medium()
    sig = np.array([0.7, 1.1, 1.6])
    for _ in range(20):
        o = rng.uniform(-3, 3, 3) + np.array([0, 0, -2.5])
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        t = float(rng.uniform(0.1, 8.0))
        L = chord_np(o, d, t)
        got = med.transmittance(jnp.asarray(o, jnp.float32), jnp.asarray(d, jnp.float32), jnp.float32(t))
        np.testing.assert_allclose(np.asarray(got), np.exp(-sig * L), rtol=2e-5, atol=1e-7)
        grad = jax.grad(lambda s: med.__class__(s, med.albedo, med.phase, bounds=med.bounds).transmittance(
            jnp.asarray(o, jnp.float32), jnp.asarray(d, jnp.float32), jnp.float32(t))[0])(jnp.float32(0.7))
        assert float(grad) == pytest.approx(-L * np.exp(-0.7 * L), rel=1e-4, abs=1e-6)
    # an escaping ray (t = inf) leaves through the box: finite transmittance and gradient
    inf_t = med.transmittance(jnp.zeros(3), jnp.asarray((0.0, 0.0, -1.0)), jnp.float32(jnp.inf))
    np.testing.assert_allclose(np.asarray(inf_t), np.exp(-sig * 2.5), rtol=2e-5)


def test_free_flight_density_lives_on_the_fog_part_and_integrates_to_q():
    """The medium branch's density integrates to `q` over `[a, b]` and is 0 outside; its samples fall in `[a, b]`
    with the density's first moment (SE from the sample spread, 5 SE); a segment that misses the box never scatters
    and reaches its surface with weight exactly 1."""
    med = _medium(sigma_t=0.9)
    o, d = jnp.asarray((0.3, 0.2, 0.0), jnp.float32), jnp.asarray((0.0, 0.0, -1.0), jnp.float32)
    s = jnp.float32(5.0)
    a, b = med.fog_interval(o, d, s)
    assert (float(a), float(b)) == pytest.approx((1.5, 4.0), abs=1e-6)
    u = jnp.linspace(0.0005, 0.9995, 1000, dtype=jnp.float32)
    fl = jax.vmap(lambda x: med.sample_free_flight(o, d, s, True, True, x, 0.5))(u)
    q = float(fl.q[0])
    assert q == pytest.approx(min(1 - np.exp(-0.9 * 2.5), 0.75), rel=1e-5)
    t = np.asarray(fl.t)[np.asarray(fl.scattered)]
    assert t.min() >= 1.5 - 1e-5 and t.max() <= 4.0 + 1e-5
    pdf = lambda x: float(med.free_flight_pdf(o, d, s, jnp.float32(q), jnp.float32(x)))  # noqa: E731
    total = integrate.quad(pdf, 0.0, 5.0, points=[1.5, 4.0], limit=200)[0]
    assert total == pytest.approx(q, rel=1e-4)
    assert pdf(1.0) == 0.0 and pdf(4.5) == 0.0
    mean_t = integrate.quad(lambda x: x * pdf(x), 1.5, 4.0)[0] / q
    assert abs(t.mean() - mean_t) < 5 * t.std() / np.sqrt(t.size)
    # a segment beside the box
    o2 = jnp.asarray((3.0, 0.2, 0.0), jnp.float32)
    fl2 = med.sample_free_flight(o2, d, s, True, True, jnp.float32(0.01), 0.5)
    assert not bool(fl2.scattered) and float(fl2.q) == 0.0
    np.testing.assert_array_equal(np.asarray(med.surface_weight(o2, d, s, fl2.log_one_minus_q)), 1.0)


@pytest.mark.parametrize("bad", [((0, 0, 0), (1, 1, 0)), ((0, 0, 0),), ((0, 0), (1, 1)), ((0, 0, 0), (1, np.inf, 1))])
def test_bad_bounds_are_refused(bad):
    with pytest.raises(ValueError, match="bounds"):
        _medium(bounds=bad)


def test_scene_file_bounds_are_checked_before_any_work(tmp_path):
    from helpers import spot_fog_dict

    data = spot_fog_dict()
    data["medium"]["bounds"] = {"min": [-3, -0.5, -3], "max": [3, -1, 3]}
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ValueError, match=r"medium\.bounds\.max"):
        jf.load_scene(path)
    data["medium"]["bounds"] = {"min": [-3, -0.5, -3], "max": [3, 2.4, 3]}
    path.write_text(json.dumps(data))
    med = jf.load_scene(path).scene.medium
    np.testing.assert_array_equal(np.asarray(med.bounds[1]), np.float32([3, 2.4, 3]))


# ====================================================================================== renders against references
FLOOR_CAM = CameraSpec(origin=(0.0, 1.2, 1.0), target=(0.0, 0.0, -2.5), fov=40.0, width=8, height=6)
POINT = ((0.5, 2.2, -2.0), np.array([5.0, 4.0, 3.0]))  # above the box (y 1.5): in vacuum


def test_absorbing_box_over_a_lit_floor_is_beer_lambert(stats):
    """Albedo 0: each floor point's fog-free radiance times `exp(-sigma_t (chord of the camera ray + chord of the
    light ray))`, the chords inside the box only (float64)."""
    sig = np.array([0.6, 0.9, 1.4])
    R = np.array([0.7, 0.5, 0.3])
    scene = jf.Scene(camera=FLOOR_CAM.build(), shapes=(make_floor(R, half=30.0),),
                     lights=(jf.PointLight(*POINT),),
                     medium=_medium(sigma_t=sig, albedo=0.0), max_depth=2)
    o, dirs, w = FLOOR_CAM.rays(5)
    ref = np.zeros((FLOOR_CAM.height, FLOOR_CAM.width, 3))
    for r in range(FLOOR_CAM.height):
        for c in range(FLOOR_CAM.width):
            for k, dd in enumerate(dirs[r, c]):
                t = -o[1] / dd[1]
                p = o + t * dd
                assert t > 0 and np.all(np.abs(p[[0, 2]]) < 30.0)  # on the 60 x 60 floor
                v = np.asarray(POINT[0]) - p
                dist = np.linalg.norm(v)
                L = R / np.pi * POINT[1] * max(v[1] / dist, 0.0) / dist**2
                L = L * np.exp(-sig * (chord_np(o, dd, t) + chord_np(p, v / dist, dist)))
                ref[r, c] += w[k] * L
    mean, se = stats.mean_and_se(stats.render_keys(scene, 16, seed=41))
    stats.assert_statistically_equal(mean, se, ref, label="absorbing box")


SS_CAM_OUT = CameraSpec(origin=(0.2, 0.4, 1.0), target=(0.0, 0.5, -3.0), fov=35.0, width=6, height=5)
SS_CAM_IN = CameraSpec(origin=(0.2, 0.4, -1.7), target=(0.0, 0.5, -4.0), fov=60.0, width=6, height=5)


@pytest.mark.parametrize("cam", [SS_CAM_OUT, SS_CAM_IN], ids=["camera outside", "camera inside"])
def test_single_scattering_in_a_box_matches_quadrature(stats, cam):
    """max_depth 2, no surfaces, a point light outside the box above it: each pixel is
    `integral over the camera ray's chord of sigma_s exp(-sigma_t (t - t_in)) p(cos) I / r^2 exp(-sigma_t c(x))`,
    `c(x)` the light ray's chord in the box, by adaptive quadrature at a 3 x 3 grid of rays per pixel."""
    sig_t, alb, g = 0.8, 0.85, 0.5
    scene = jf.Scene(camera=cam.build(), lights=(jf.PointLight(POINT[0], 4.0),), medium=_medium(sig_t, alb, g),
                     max_depth=2)
    o, dirs, w = cam.rays(3)
    lp = np.asarray(POINT[0])
    ref = np.zeros((cam.height, cam.width))
    for r in range(cam.height):
        for c in range(cam.width):
            for k, dd in enumerate(dirs[r, c]):
                with np.errstate(divide="ignore"):
                    ta, tb = (LO - o) / dd, (HI - o) / dd
                t_in, t_out = max(np.minimum(ta, tb).max(), 0.0), np.maximum(ta, tb).min()
                if t_out <= t_in:
                    continue

                def f(t):
                    x = o + t * dd
                    v = lp - x
                    dist = np.linalg.norm(v)
                    wi = v / dist
                    return (alb * sig_t * np.exp(-sig_t * (t - t_in)) * hg_np(dd @ wi, g) * 4.0 / dist**2
                            * np.exp(-sig_t * chord_np(x, wi, dist)))

                ref[r, c] += w[k] * integrate.quad(f, t_in, t_out, limit=200, epsrel=1e-9)[0]
    mean, se = stats.mean_and_se(stats.render_keys(scene, 16, seed=43))
    stats.assert_statistically_equal(mean, se, np.repeat(ref[..., None], 3, -1), label=f"single scattering {cam}")


# slow tier: a bounded and an unbounded tracer compiled and compared (18 s on 2 cores with a cold cache)
@pytest.mark.slow
def test_a_box_around_everything_changes_nothing_but_rounding():
    """A box that holds every path of the scene renders the unbounded fog's image: with `extent` 2 every segment
    stays within 8 units of the camera (4 segments), inside a box of +-50, so the fog's part of each segment is all
    of it (a = 0, L = s) and the same random numbers make the same decisions. The two programs differ in their
    operations, so XLA may round differently: 1e-4 relative per pixel, at most 1% of the pixels beyond (a flipped
    branch)."""
    from helpers import spot_fog_dict
    from jaxfog._scene_io import scene_from_dict

    data = spot_fog_dict()
    data["camera"]["width"] = data["camera"]["height"] = 12
    data["integrator"]["max_depth"] = 4
    data["medium"]["extent"] = 2.0
    plain = scene_from_dict(data, source="plain").scene
    data["medium"]["bounds"] = {"min": [-50, -50, -50], "max": [50, 50, 50]}
    boxed = scene_from_dict(data, source="boxed").scene
    key = jax.random.key(5)
    a, b = (np.asarray(jf.render(s, key, 8), np.float64) for s in (plain, boxed))
    assert np.all(np.isfinite(b)) and a.mean() > 0
    rel = np.abs(a - b) / np.maximum(np.abs(a), 1e-3 * a.mean())
    assert np.mean(rel > 1e-4) <= 0.01, np.sort(rel.ravel())[-10:]


def test_bounded_render_has_finite_derivatives_at_hard_values():
    """d image / d (sigma_t, g) of a box render is finite at sigma_t -> 0 and large, albedo 0 and 1, g -> +-1."""
    from helpers import spot_fog_dict
    from jaxfog._scene_io import scene_from_dict

    data = spot_fog_dict()
    data["camera"]["width"] = data["camera"]["height"] = 6
    data["integrator"]["max_depth"] = 4
    data["medium"]["bounds"] = {"min": [-3, -0.5, -3], "max": [3, 2.4, 3]}
    base = scene_from_dict(data, source="box").scene

    def image(p):  # one compiled program: all three values traced
        med = jf.HomogeneousMedium(p[0], p[1], jf.HenyeyGreenstein(p[2]), bounds=base.medium.bounds)
        return jf.render(jf.Scene(camera=base.camera, shapes=base.shapes, lights=base.lights, medium=med,
                                  max_depth=base.max_depth), jax.random.key(2), 4)

    f = jax.jit(lambda p, v: jax.jvp(image, (p,), (v,)))
    for sig, alb, g in [(0.0, 0.9, 0.6), (40.0, 0.9, 0.6), (0.5, 0.0, 0.0), (0.5, 1.0, 0.999), (0.5, 0.9, -0.999)]:
        val, jac = f(jnp.asarray([sig, alb, g], jnp.float32), jnp.asarray([1.0, 0.0, 0.3], jnp.float32))
        assert np.all(np.isfinite(np.asarray(val))) and np.all(np.isfinite(np.asarray(jac))), (sig, alb, g)


# ============================================================================================ the Mitsuba export
def test_mitsuba_export_puts_the_cube_at_the_box():
    from helpers import spot_fog_dict

    data = spot_fog_dict()
    data["medium"]["bounds"] = {"min": [-3, -0.5, -3], "max": [3, 2.4, 3]}
    d = jf.to_mitsuba(data, transform=lambda m: m)  # plain arrays even after another test imported Mitsuba
    m = np.asarray(d["fog_boundary"]["to_world"])
    np.testing.assert_allclose(np.diag(m)[:3], [3.0, 1.45, 3.0])
    np.testing.assert_allclose(m[:3, 3], [0.0, 0.95, 0.0])
    assert "medium" not in d["sensor"]  # the camera (z = 4.5) is in vacuum
    assert all("exterior" not in v for k, v in d.items() if k.startswith("shape_"))  # reflectors keep the medium
    data["medium"]["bounds"] = {"min": [-3, -0.5, -3], "max": [3, 2.4, 5]}
    assert jf.to_mitsuba(data, transform=lambda m: m)["sensor"]["medium"] == {"type": "ref", "id": "fog"}


def _box_scene(size=8, depth=3):
    from helpers import spot_fog_dict
    from jaxfog._scene_io import scene_from_dict

    data = spot_fog_dict()
    data["camera"]["width"] = data["camera"]["height"] = size
    data["integrator"]["max_depth"] = depth
    data["medium"]["bounds"] = {"min": [-3, -0.5, -3], "max": [3, 2.4, 3]}
    return scene_from_dict(data, source="box").scene


def test_proposal_without_the_box_is_refused():
    scene = _box_scene()
    med = scene.medium
    with pytest.raises(ValueError, match="bounds"):
        jf.render(scene, jax.random.key(9), 4, estimator="proposal",
                  proposal=jf.HomogeneousMedium(med.sigma_t, med.albedo, med.phase))


@pytest.mark.slow
def test_proposal_takes_the_scene_medium_box():
    """estimator="proposal": the proposal's values sample, the box is the scene's. A proposal at the medium's own
    values (with another box) renders the detached estimator's image (the same sampler)."""
    scene = _box_scene()
    med, key = scene.medium, jax.random.key(9)
    same = jf.HomogeneousMedium(med.sigma_t, med.albedo, med.phase, bounds=((-9, -9, -9), (9, 9, 9)))
    a = np.asarray(jf.render(scene, key, 4, estimator="proposal", proposal=same))
    b = np.asarray(jf.render(scene, key, 4))
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7 * b.max())
