"""A density grid rendered by ratio tracking (`GridMedium(tracking="ratio")`): the majorant grid bounds the density
everywhere, free flight follows the majorant's density (chi-square), residual ratio tracking's transmittance and
its forward-mode derivative are unbiased for the exact ones, a segment's weights are unbiased for its integral, a
render agrees with the exact profiles, and what ratio tracking cannot do is refused.

Statistical tests fix their seeds and state their tolerance in standard errors of the estimator (the sample
standard deviation over independent draws)."""

from __future__ import annotations

import math
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfog as jf
from jaxfog._grid import (CoarseProfile, GridMedium, block_bounds, coarse_profile, piecewise_depth,
                          piecewise_inverse, ratio_tracking, ray_seed, seeded_uniform, stochastic_trilinear,
                          trilinear)
from jaxfog._medium import box_interval, path_replay

REPO = Path(__file__).resolve().parent.parent

BOX = ((-1.0, -1.0, -1.0), (1.0, 2.0, 1.5))
LINE_O = np.array([-2.0, 0.3, 0.2], np.float32)
LINE_D = np.array([0.97, 0.2, 0.1], np.float32) / np.float32(np.linalg.norm([0.97, 0.2, 0.1]))


def _grid(shape=(4, 5, 6, 1), seed=0, lo=0.0, hi=2.0):
    return np.random.default_rng(seed).uniform(lo, hi, shape).astype(np.float32)


def _medium(grid, scale=0.7, cells=2, tracking="ratio", lookup="stochastic"):
    return GridMedium(grid, scale, 0.8, jf.HenyeyGreenstein(0.3), bounds=BOX, tracking=tracking,
                      majorant_cells=cells, lookup=lookup)


def _shifted_rays(n, seed):
    """`n` origins on one line, each a random distance (0 to 0.5) before `LINE_O`, all outside the box: the same
    segment geometry from points whose bits differ, so each ray draws its own ratio-tracking points."""
    delta = np.random.default_rng(seed).uniform(0.0, 0.5, n).astype(np.float32)
    return jnp.asarray(LINE_O[None, :] - delta[:, None] * LINE_D[None, :]), jnp.asarray(delta)


# ------------------------------------------------------------------------------------------- majorant grid
@pytest.mark.parametrize("cells", [(1, 1, 1), (2, 3, 4), (6, 5, 4)])
def test_block_bounds_hold_the_trilinear_density_everywhere_in_their_cells(cells):
    grid = _grid(shape=(4, 5, 6, 3), seed=3)
    med = _medium(grid)
    major, control = (np.asarray(x) for x in block_bounds(jnp.asarray(grid), cells))
    assert major.shape == control.shape == cells[::-1]
    rng = np.random.default_rng(4)
    lo, hi = (np.asarray(b, np.float32) for b in BOX)
    pts = rng.uniform(lo, hi, (3000, 3)).astype(np.float32)
    dens = np.asarray(jax.jit(jax.vmap(med.density_at))(jnp.asarray(pts)))  # (n, C)
    idx = np.clip(np.floor((pts - lo) / (hi - lo) * np.array(cells)).astype(int), 0, np.array(cells) - 1)
    maj, ctl = major[idx[:, 2], idx[:, 1], idx[:, 0]], control[idx[:, 2], idx[:, 1], idx[:, 0]]
    # trilinear interpolation is a convex combination of the texels the bounds come from; float32 rounding only
    assert np.all(dens.max(axis=1) <= maj + 1e-5) and np.all(dens.min(axis=1) >= ctl - 1e-5)
    assert np.any(maj > ctl)  # not trivially satisfied


def test_coarse_profile_covers_the_box_part_of_the_ray():
    major, control = block_bounds(jnp.asarray(_grid()), (3, 3, 3))
    lo, hi = (jnp.asarray(b) for b in BOX)
    cp = coarse_profile(major, control, lo, hi, jnp.asarray(LINE_O), jnp.asarray(LINE_D))
    t_in, t_out = box_interval(lo, hi, jnp.asarray(LINE_O), jnp.asarray(LINE_D))
    start, length = np.asarray(cp.start), np.asarray(cp.length)
    assert start[0] == pytest.approx(float(t_in), abs=1e-6)
    # the lengths are float32 differences of the merged crossings: each rounds once, by at most 2^-24 of t_out
    assert start[0] + length.sum() == pytest.approx(float(t_out), abs=len(length) * 2.0 ** -24 * float(t_out))
    assert np.all(np.diff(start) >= 0) and np.all(length >= 0)


# ---------------------------------------------------------------------------------------------- free flight
def test_majorant_free_flight_follows_the_majorant_density():
    """Chi-square of 20,000 draws in 20 bins of equal probability under the majorant's truncated density
    `mu(t) e^-tau_mu(t) / (1 - e^-tau_mu(s))` (its CDF from the piecewise-constant depth): fails with probability
    0.1% when the sampler is right (19 degrees of freedom, 99.9% quantile 43.8); the branch rate within 4 standard
    errors of its binomial; the pdf integrates to 1."""
    med = _medium(_grid(seed=5), cells=3)
    o, d, s = jnp.asarray(LINE_O), jnp.asarray(LINE_D), jnp.float32(3.5)
    u = jax.random.uniform(jax.random.key(11), (20000,))
    fl = jax.jit(jax.vmap(lambda ui: med.sample_free_flight(o, d, s, False, True, ui, 0.5)))(u)
    cp = med.coarse(o, d)
    depth = jax.jit(jax.vmap(lambda t: med.scale * piecewise_depth(cp.start, cp.length, cp.major, t)))
    tau_s = float(med.scale * piecewise_depth(cp.start, cp.length, cp.major, s))
    q = 1.0 - math.exp(-tau_s)
    assert float(fl.q[0]) == pytest.approx(q, rel=1e-5)
    scattered = np.asarray(fl.scattered)
    t = np.asarray(fl.t)[scattered]
    cdf = (1.0 - np.exp(-np.asarray(depth(jnp.asarray(t))))) / q
    counts = np.histogram(cdf, bins=20, range=(0.0, 1.0))[0]
    expected = len(t) / 20
    assert float(np.sum((counts - expected) ** 2 / expected)) < 43.8
    assert abs(scattered.mean() - q) < 4 * math.sqrt(q * (1 - q) / len(u))
    ts = np.linspace(0.0, 3.5, 8001)
    pdf = np.asarray(jax.jit(jax.vmap(lambda t: med.free_flight_pdf(o, d, s, 1.0, t)))(jnp.asarray(ts, jnp.float32)))
    # piecewise smooth with jumps at the majorant's faces: the trapezoid rule errs by at most jump x step / 2 each
    bound = float(np.max(np.abs(np.diff(pdf)))) * (ts[1] - ts[0]) * 4 + 1e-5
    assert abs(np.trapezoid(pdf, ts) - 1.0) <= bound


def test_piecewise_inverse_inverts_the_piecewise_depth():
    start = jnp.array([0.5, 1.0, 1.0, 2.0])
    length = jnp.array([0.5, 0.0, 1.0, 1.5])
    rate = jnp.array([2.0, 7.0, 0.0, 0.5])
    cum = jnp.cumsum(rate * length) - rate * length
    for target in (0.0, 0.3, 0.99, 1.0, 1.5):
        t, _ = piecewise_inverse(start, length, rate, cum, jnp.float32(target))
        assert float(piecewise_depth(start, length, rate, t)) == pytest.approx(target, abs=1e-6)


# ------------------------------------------------------------------------------------------- ratio tracking
@pytest.mark.parametrize("x", [(1.3, 2.6, 0.2), (0.0, 1.0, 2.0), (-0.4, 4.7, 3.5), (2.999, 0.001, 1.5)])
def test_a_stochastic_lookup_is_one_of_the_cells_texels_drawn_with_the_trilinear_weights(x):
    """`stochastic_trilinear` over 4,096 evenly spaced uniforms (midpoints): every value is one of the cell's texels
    (between their min and max), and the mean and its gradient in the texel values equal `trilinear`'s value and
    weights. The draw is a step function of the uniform with at most 8 steps, so the midpoint rule errs by at most 7
    steps of 1/4096 each (times the texels' range for the value), plus float32 rounding of the remapped uniform."""
    grid = _grid(shape=(4, 5, 6, 2), seed=31)
    flat = jnp.asarray(grid.reshape(-1, 2))
    res = (6, 5, 4)
    xs = jnp.asarray(x, jnp.float32)
    n = 4096
    us = (jnp.arange(n, dtype=jnp.float32) + 0.5) / n

    def mean_lookup(f):
        return jnp.mean(jax.vmap(lambda u: stochastic_trilinear(f, res, xs, u))(us), axis=0)

    draws = np.asarray(jax.vmap(lambda u: stochastic_trilinear(flat, res, xs, u))(us))
    i0 = np.floor(np.asarray(x)).astype(int)
    corners = grid[np.clip([i0[2], i0[2] + 1], 0, 3)][:, np.clip([i0[1], i0[1] + 1], 0, 4)][:, :, np.clip(
        [i0[0], i0[0] + 1], 0, 5)].reshape(-1, 2)
    assert np.all(draws >= corners.min(axis=0)) and np.all(draws <= corners.max(axis=0))
    assert all(np.any(np.all(corners == d, axis=1)) for d in draws[:: 97])  # a texel, not a blend
    spread = corners.max(axis=0) - corners.min(axis=0)
    np.testing.assert_allclose(np.asarray(mean_lookup(flat)), np.asarray(trilinear(flat, res, xs)),
                               atol=float(np.max(spread)) * 7 / n + 1e-5)
    g_stoch = np.asarray(jax.grad(lambda f: mean_lookup(f)[0])(flat))
    g_tri = np.asarray(jax.grad(lambda f: trilinear(f, res, xs)[0])(flat))
    np.testing.assert_allclose(g_stoch, g_tri, atol=7 / n + 1e-5)


@pytest.mark.parametrize("cells,channels,lookup", [(1, 1, "stochastic"), (3, 1, "stochastic"), (2, 3, "stochastic"),
                                                   (3, 1, "trilinear"), (2, 3, "trilinear")])
def test_ratio_tracking_is_unbiased_for_the_exact_transmittance(cells, channels, lookup):
    """4,000 rays along one line through the box (`_shifted_rays`), the estimate at four distances against
    `exp(-tau)` from the exact profile: within 4 standard errors of the estimates' mean, with either lookup."""
    med = _medium(_grid(shape=(4, 5, 6, channels), seed=7), cells=cells, lookup=lookup)
    exact = _medium(med.density, cells=cells, tracking="exact")
    os_, delta = _shifted_rays(4000, seed=8)
    d = jnp.asarray(LINE_D)
    for t in (1.2, 2.0, 2.9, np.inf):
        est = np.asarray(jax.jit(jax.vmap(lambda o, dl: med.transmittance(o, d, t + dl)))(os_, delta))[:, 0]
        want = float(exact.transmittance(jnp.asarray(LINE_O), d, jnp.float32(t))[0])
        se = est.std(ddof=1) / math.sqrt(len(est))
        assert est.std() > 0  # the estimator is random here: the test can fail
        assert abs(est.mean() - want) < 4 * se + 1e-6, (t, est.mean(), want, se)


def test_ratio_tracking_scale_derivative_is_unbiased_in_forward_mode():
    """`jax.jvp` of the estimate in `scale` against `d/d scale exp(-scale tau_1) = -tau_1 exp(-tau)`, 4,000 rays, 4
    standard errors."""
    grid = _grid(seed=9)
    os_, delta = _shifted_rays(4000, seed=10)
    d, t = jnp.asarray(LINE_D), 2.6

    def est(scale, o, dl):
        return _medium(grid, scale=scale, cells=2).transmittance(o, d, t + dl)[0]

    dv = np.asarray(jax.jit(jax.vmap(lambda o, dl: jax.jvp(lambda s: est(s, o, dl), (0.7,), (1.0,))[1]))(os_, delta))
    exact = _medium(grid, scale=0.7, tracking="exact")
    tau = float(exact.optical_depth(jnp.asarray(LINE_O), d, jnp.float32(t))[0])
    want = -tau / 0.7 * math.exp(-tau)
    assert abs(dv.mean() - want) < 4 * dv.std(ddof=1) / math.sqrt(len(dv)), (dv.mean(), want)


@pytest.mark.parametrize("zeros", [0, 1, 2])
def test_ratio_tracking_reverse_mode_replays_its_points_and_equals_forward_mode(zeros):
    """`ratio_tracking` on one interval of rate 1 (20 points or so), its extinction `a + b t` with `zeros` factors
    exactly 0 (the extinction equals the majorant at the first `zeros` points, where `bump` adds it): the reverse
    mode that path replay traces (`_medium.path_replay`, the points drawn again) equals forward mode through the
    plain loop in `a`, `b` and `scale`, to float32 rounding, also where a zero factor makes the product 0."""
    seed = jnp.uint32(12345)
    cp = CoarseProfile(start=jnp.array([0.0]), length=jnp.array([20.0]), major=jnp.array([1.0]),
                       control=jnp.array([0.0]), cum_major=jnp.array([0.0]), cum_control=jnp.array([0.0]))
    depths = np.cumsum([-np.log1p(-float(seeded_uniform(seed, jnp.uint32(i)))) for i in range(3)])
    bumped = depths[:zeros]  # the points (distance = depth at rate 1) where a factor is exactly 0

    def estimate(a, b, scale):
        def sigma_at(t, u):  # u: the stochastic lookup's uniform, unused here
            at_point = jnp.any(jnp.abs(t - jnp.asarray(bumped, jnp.float32)) < 1e-6) if zeros else False
            v = scale * (a + b * t)  # at a bumped point: exactly 1, with v's derivative
            return jnp.reshape(jnp.where(at_point, 1.0 + (v - jax.lax.stop_gradient(v)), v), (1,))

        return ratio_tracking(cp, 1.0, scale, sigma_at, jnp.float32(20.0), seed)[1][0]

    x = (jnp.float32(0.02), jnp.float32(0.01), jnp.float32(1.0))
    fwd = np.array(jax.jacfwd(estimate, argnums=(0, 1, 2))(*x))
    with path_replay():
        rev = np.array(jax.grad(estimate, argnums=(0, 1, 2))(*x))
        value = float(estimate(*x))
    assert value == pytest.approx(float(estimate(*x)), abs=0)  # the replayed loop computes the same product
    assert (value == 0.0) == (zeros > 0)
    assert (np.max(np.abs(fwd)) > 0) == (zeros < 2)  # two zero factors: no derivative either
    np.testing.assert_allclose(rev, fwd, rtol=1e-5, atol=1e-7)


def test_a_ray_seed_differs_between_rays_and_repeats_for_the_same_ray():
    os_, _ = _shifted_rays(1000, seed=12)
    seeds = np.asarray(jax.vmap(lambda o: ray_seed(o, jnp.asarray(LINE_D)))(os_))
    assert len(np.unique(seeds)) == 1000
    assert int(ray_seed(os_[3], jnp.asarray(LINE_D))) == int(seeds[3])


def test_segment_weights_are_unbiased_for_the_segment_integral():
    """For one segment ending on a surface: `E[w_med f(t) | medium] + E[w_surf | surface] = integral_0^s sigma_s(t)
    T(t) f(t) dt + T(s)` with `f(t) = t`, the right side by quadrature of the exact profile; 8,000 rays along one
    line (`_shifted_rays`), 4 standard errors."""
    med = _medium(_grid(seed=13), cells=2)
    sampler = jax.lax.stop_gradient(med)
    exact = _medium(med.density, tracking="exact")
    os_, delta = _shifted_rays(8000, seed=14)
    d, s = jnp.asarray(LINE_D), 3.5
    u = jax.random.uniform(jax.random.key(15), (8000,))

    def one(o, dl, ui):
        fl = sampler.sample_free_flight(o, d, s + dl, False, True, ui, 0.5)
        w_med = med.collision_weight(sampler, o, d, s + dl, jnp.where(fl.scattered, fl.q, 1.0), fl.t)[0]
        w_surf = med.surface_weight(o, d, s + dl, fl.log_one_minus_q)[0]
        return jnp.where(fl.scattered, w_med * (fl.t - dl), w_surf)

    x = np.asarray(jax.jit(jax.vmap(one))(os_, delta, u))
    o = jnp.asarray(LINE_O)
    ts = np.linspace(0.0, s, 4001).astype(np.float32)
    f = jax.jit(jax.vmap(lambda t: med.scattering(o + t * d)[0] * exact.transmittance(o, d, t)[0] * t))
    want = np.trapezoid(np.asarray(f(jnp.asarray(ts))), ts) + float(exact.transmittance(o, d, jnp.float32(s))[0])
    se = x.std(ddof=1) / math.sqrt(len(x))
    assert abs(x.mean() - want) < 4 * se + 1e-4, (x.mean(), want, se)  # 1e-4: the quadrature at kinks


# --------------------------------------------------------------------------------------------------- renders
def test_a_patchy_grid_renders_alike_with_ratio_tracking_and_exact_profiles():
    """spot_fog at 8 x 8 px, max_depth 3, 128 spp each, independent keys: the image means within 4 standard errors
    of their difference (each from the render's per-pixel variances), every pixel finite."""
    scene = jf.load_scene(REPO / "data_synthetic" / "scenes" / "spot_fog.json",
                          ["camera.width=8", "camera.height=8", "integrator.max_depth=3"]).scene
    box = ((-2.0, -0.5, -2.0), (2.0, 2.5, 1.5))
    grid = _grid(shape=(6, 6, 6), seed=16, lo=0.0, hi=1.2)
    means, ses = [], []
    for tracking, key in (("exact", 1), ("ratio", 2)):
        med = GridMedium(grid, 1.0, 0.9, scene.medium.phase, bounds=box, tracking=tracking, majorant_cells=3)
        img, var = jf.render(eqx.tree_at(lambda s: s.medium, scene, med), jax.random.key(key), 128, variance=True)
        img, var = np.asarray(img), np.asarray(var)
        assert np.all(np.isfinite(img))
        means.append(img.mean())
        ses.append(math.sqrt(var.sum()) / img.size)
    assert abs(means[0] - means[1]) < 4 * math.hypot(*ses), (means, ses)


# ------------------------------------------------------------------------------------------- what is refused
def test_ratio_tracking_refuses_the_reparam_estimator_and_bad_settings():
    scene = jf.load_scene(REPO / "data_synthetic" / "scenes" / "spot_fog.json", ["camera.width=4", "camera.height=4"]).scene
    med = GridMedium(_grid(), 1.0, 0.9, scene.medium.phase, bounds=BOX, tracking="ratio")
    with pytest.raises(ValueError, match='estimator="reparam" is not defined for this GridMedium'):
        jf.render(eqx.tree_at(lambda s: s.medium, scene, med), jax.random.key(0), 1, estimator="reparam")
    with pytest.raises(ValueError, match="tracking must be one of"):
        GridMedium(_grid(), 1.0, 0.9, scene.medium.phase, bounds=BOX, tracking="delta")
    for bad in (0, -2, 2.5, True):
        with pytest.raises(ValueError, match="majorant_cells must be an integer >= 1"):
            GridMedium(_grid(), 1.0, 0.9, scene.medium.phase, bounds=BOX, majorant_cells=bad)
    with pytest.raises(ValueError, match="lookup must be one of"):
        GridMedium(_grid(), 1.0, 0.9, scene.medium.phase, bounds=BOX, tracking="ratio", lookup="nearest")


@pytest.mark.parametrize("grid,scale", [(np.zeros((3, 3, 3, 1), np.float32), 0.7), (_grid(seed=17), 0.0),
                                        (_grid(seed=18), 1e4), (np.full((2, 2, 2, 1), 3.0, np.float32), 1.0)])
def test_ratio_tracking_values_and_forward_derivatives_are_finite_on_hard_cases(grid, scale):
    """Empty grid, scale 0, optical depths ~1e4 (every transmittance underflows), a constant grid (the majorant
    equals the control: only `RESIDUAL_MARGIN`'s points, each factor 1); rays through the box, from inside it,
    missing it; t = 0 and inf."""
    d = jnp.asarray(LINE_D)

    def values(s):
        med = _medium(grid, scale=s, cells=2)
        sampler = jax.lax.stop_gradient(med)
        out = []
        for o in (jnp.asarray(LINE_O), jnp.array([0.0, 0.5, 0.2]), jnp.array([5.0, 5.0, 5.0])):
            fl = sampler.sample_free_flight(o, d, 3.5, False, True, 0.3, 0.5)
            out += [med.transmittance(o, d, jnp.float32(t)) for t in (0.0, 1.0, np.inf)]
            out += [med.collision_weight(sampler, o, d, 3.5, jnp.where(fl.scattered, fl.q, 1.0), fl.t),
                    med.surface_weight(o, d, 3.5, fl.log_one_minus_q),
                    sampler.free_flight_pdf(o, d, 3.5, fl.q, fl.t)[None]]
        return jnp.concatenate([jnp.ravel(x) for x in out])

    val, tan = jax.jit(lambda s: jax.jvp(values, (s,), (1.0,)))(jnp.float32(scale))
    assert np.all(np.isfinite(np.asarray(val))) and np.all(np.isfinite(np.asarray(tan)))
    assert np.all(np.asarray(val) >= 0)
