"""The density-grid medium (`GridMedium`): its trilinear lookup against numpy, its exact optical depth against
quadrature, its free-flight distances against the distribution they must follow (chi-square), derivatives with
respect to single voxels against finite differences, finite values and gradients on hard cases, scene files, and
renders against the homogeneous medium it must equal when constant (and against Mitsuba 3 in the slow tier)."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfog as jf
from jaxfog._grid import GridMedium, distance_at_depth, profile
from jaxfog._medium import HomogeneousMedium

from helpers import trilinear_reference

REPO = Path(__file__).resolve().parent.parent
BOX = ((-1.0, -1.0, -1.0), (1.0, 2.0, 1.5))


def _medium(grid, scale=0.7, box=BOX, g=0.3):
    return GridMedium(grid, scale, 0.8, jf.HenyeyGreenstein(g), bounds=box)


def _grid(shape=(4, 5, 6, 1), seed=0, lo=0.0, hi=2.0):
    return np.random.default_rng(seed).uniform(lo, hi, shape).astype(np.float32)


def _numpy_trilinear(grid, box, p):
    """Reference: Mitsuba's gridvolume lookup in float64 (texel centres at (i + 1/2) / n, clamped, 0 outside)."""
    lo, hi = (np.asarray(b, np.float64) for b in box)
    if np.any(p < lo) or np.any(p > hi):
        return np.zeros(grid.shape[-1])
    return trilinear_reference(grid, (p - lo) / (hi - lo))


# ------------------------------------------------------------------------------------------------- lookups
def test_trilinear_lookup_matches_numpy_inside_at_the_border_and_outside():
    grid = _grid()
    med = _medium(grid)
    rng = np.random.default_rng(1)
    pts = np.concatenate([rng.uniform([-1.2, -1.2, -1.2], [1.2, 2.2, 1.7], (200, 3)),
                          np.array([[-1, -1, -1], [1, 2, 1.5], [0.999, 0.0, 0.0], [-0.99, 1.99, 1.49]])])
    got = np.asarray(jax.jit(jax.vmap(med.density_at))(jnp.asarray(pts, jnp.float32)))
    want = np.stack([_numpy_trilinear(grid, BOX, p) for p in pts])
    # float32 coordinates: |error| ~ 1e-6 relative in the position times the gradient (values <= 2 over a texel)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=2e-5)


# ------------------------------------------------------------------------------------------- optical depth
RAYS = [  # (origin, direction): through the box, starting inside, along an axis, grazing, missing, backwards
    ((-2.0, 0.3, 0.2), (1.0, 0.2, 0.1)),
    ((0.1, 0.5, 0.3), (-0.3, 0.8, -0.5)),
    ((-3.0, 0.25, 0.4), (1.0, 0.0, 0.0)),
    ((0.2, -3.0, -0.7), (0.0, 1.0, 0.0)),
    ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0)),
    ((3.0, 3.0, 3.0), (1.0, 0.0, 0.0)),
    ((2.0, 0.5, 0.5), (1.0, 0.1, 0.0)),
]


def _quadrature(med, o, d, t_ends, n=8001, t_max=10.0):
    """The trapezoid rule on `n` points over `[0, t_max]`, read at each of `t_ends`, and its error bound: at each
    of the (at most two) jumps where the ray crosses the box's faces the rule errs by at most jump x step / 2;
    elsewhere the piecewise cubic's error (step^2 t max|D''| / 12 ~ 1e-7) is negligible."""
    ts = np.linspace(0.0, t_max, n)
    vals = np.asarray(jax.jit(jax.vmap(lambda t: med.extinction(o + t * d)))(jnp.asarray(ts, jnp.float32)))[:, 0]
    step = ts[1] - ts[0]
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (vals[1:] + vals[:-1]) * step)])
    err = float(np.max(np.abs(np.diff(vals)), initial=0.0)) * step + 1e-6
    return [float(np.interp(min(t, t_max), ts, cum)) for t in t_ends], err


@pytest.mark.parametrize("o, d", RAYS)
def test_optical_depth_is_the_integral_of_the_extinction(o, d):
    med = _medium(_grid())
    o = jnp.asarray(o, jnp.float32)
    d = jnp.asarray(d, jnp.float32) / np.linalg.norm(d)
    ts = (0.4, 1.3, 2.6, 8.0, jnp.inf)  # grid points of the quadrature (step 1/800), and the whole ray
    wants, err = _quadrature(med, o, d, ts)
    depth = jax.jit(lambda o_, d_, t_: med.optical_depth(o_, d_, t_))
    for t, want in zip(ts, wants):
        got = float(depth(o, d, jnp.float32(t))[0])
        # the quadrature's own error bound, plus float32 in the sum of ~25 interval integrals (~1e-6 relative)
        assert abs(got - want) <= err + 2e-5 * abs(want), (t, got, want, err)
    assert np.allclose(med.transmittance(o, d, 2.0), np.exp(-float(med.optical_depth(o, d, 2.0)[0])))


def test_a_constant_grid_is_beer_lambert_in_its_box():
    med = _medium(np.full((3, 4, 2), 2.0, np.float32), scale=0.25, box=((-1, -1, -1), (1, 1, 1)))
    o, d = jnp.array([-3.0, 0.1, 0.2]), jnp.array([1.0, 0.0, 0.0])
    depth = jax.jit(lambda o_, d_, t_: med.optical_depth(o_, d_, t_))
    assert float(depth(o, d, jnp.inf)[0]) == pytest.approx(0.5 * 2.0, rel=1e-6)
    assert float(depth(o, d, jnp.float32(2.5))[0]) == pytest.approx(0.5 * 0.5, rel=1e-6)
    assert float(depth(o, d, jnp.float32(1.0))[0]) == 0.0


def test_distance_at_depth_inverts_the_optical_depth():
    med = _medium(_grid(seed=3))
    o, d = jnp.array([-2.0, 0.3, 0.2]), jnp.array([0.97, 0.2, 0.1]) / np.linalg.norm([0.97, 0.2, 0.1])
    pr = med.profile(o, d)
    total = float(med.optical_depth(o, d, jnp.inf)[0])
    invert, depth = jax.jit(lambda T: distance_at_depth(pr, med.scale, T, 0)), jax.jit(lambda o_, d_, t_: med.optical_depth(o_, d_, t_))
    for frac in (1e-4, 0.1, 0.5, 0.9, 0.9999):
        T = jnp.float32(frac * total)
        t = invert(T)
        assert float(depth(o, d, t)[0]) == pytest.approx(float(T), rel=2e-5, abs=1e-6)


def test_optical_depth_derivative_per_voxel_matches_finite_differences():
    grid = _grid(seed=4)
    o, d = jnp.array([-2.0, 0.3, 0.2]), jnp.array([0.97, 0.2, 0.1]) / np.linalg.norm([0.97, 0.2, 0.1])
    f = jax.jit(lambda D: _medium(D).optical_depth(o, d, 2.2)[0])
    g = np.asarray(jax.grad(f)(jnp.asarray(grid)))
    assert np.count_nonzero(g) > 4
    # the optical depth is linear in each voxel: the central difference is exact up to float32 rounding of f (~1e-7
    # of tau ~ 1, divided by 2h)
    h = 0.05
    for idx in [tuple(i) for i in np.argwhere(g != 0)[:6]] + [(0, 0, 0, 0)]:
        e = np.zeros_like(grid)
        e[idx] = h
        fd = (float(f(grid + e)) - float(f(grid - e))) / (2 * h)
        assert g[idx] == pytest.approx(fd, abs=3e-5), idx


# --------------------------------------------------------------------------------------------- free flight
def test_free_flight_distances_follow_the_exact_distribution():
    """Chi-square of 20,000 sampled distances in 20 bins of equal probability under the exact truncated density
    `sigma(t) e^-tau(t) / (1 - e^-tau(s))` (its CDF from the exact optical depth): the test fails with probability
    0.1% when the sampler is right (chi-square, 19 degrees of freedom, 99.9% quantile 43.8)."""
    med = _medium(_grid(seed=5))
    o, d = jnp.array([-2.0, 0.3, 0.2]), jnp.array([0.97, 0.2, 0.1]) / np.linalg.norm([0.97, 0.2, 0.1])
    s = jnp.float32(3.5)
    u = jax.random.uniform(jax.random.key(11), (20000,))  # ~16,000 medium vertices, ~800 per bin
    fl = jax.jit(jax.vmap(lambda ui: med.sample_free_flight(o, d, s, False, True, ui, 0.5)))(u)
    scattered = np.asarray(fl.scattered)
    tau_s = float(med.optical_depth(o, d, s)[0])
    q = 1.0 - math.exp(-tau_s)
    assert float(fl.q[0]) == pytest.approx(q, rel=1e-5)
    t = np.asarray(fl.t)[scattered]
    depth = jax.jit(jax.vmap(lambda x: med.optical_depth(o, d, x)[0]))
    cdf = (1.0 - np.exp(-np.asarray(depth(jnp.asarray(t))))) / q
    counts = np.histogram(cdf, bins=20, range=(0.0, 1.0))[0]
    expected = len(t) / 20
    chi2 = float(np.sum((counts - expected) ** 2 / expected))
    assert chi2 < 43.8, chi2
    # the branch: Binomial(20000, q), 4 standard errors
    assert abs(scattered.mean() - q) < 4 * math.sqrt(q * (1 - q) / len(u))


def test_free_flight_pdf_is_the_density_of_the_samples():
    med = _medium(_grid(seed=6))
    o, d = jnp.array([-2.0, 0.3, 0.2]), jnp.array([0.97, 0.2, 0.1]) / np.linalg.norm([0.97, 0.2, 0.1])
    s = 3.5
    ts = np.linspace(0.0, s, 4001)
    pdf = np.asarray(jax.jit(jax.vmap(lambda t: med.free_flight_pdf(o, d, s, 1.0, t)))(jnp.asarray(ts, jnp.float32)))
    # the distance density given the medium branch integrates to 1; the trapezoid rule errs by at most
    # jump x step / 2 at each of the two box faces the segment crosses
    bound = float(np.max(np.abs(np.diff(pdf)))) * (ts[1] - ts[0]) + 1e-5
    assert abs(np.trapezoid(pdf, ts) - 1.0) <= bound


def test_reparam_distance_moves_with_the_voxels_by_the_implicit_function_theorem():
    grid = _grid(seed=7)
    o, d = jnp.array([-2.0, 0.3, 0.2]), jnp.array([0.97, 0.2, 0.1]) / np.linalg.norm([0.97, 0.2, 0.1])
    # the branch probability carries no derivative (it is detached, as for every medium, and the collision weight's
    # m / q compensates); a segment ending on a surface with optical depth > log 4 has it capped at Q_MAX_SURFACE,
    # where a finite difference does not move it either: the distance is then the same function of the voxels
    f = jax.jit(lambda D: _medium(D, scale=1.5).sample_free_flight(o, d, 3.5, True, True, 0.4, 0.5).t)
    assert float(_medium(grid, scale=1.5).sample_free_flight(o, d, 3.5, True, True, 0.4, 0.5).q) == 0.75
    g = np.asarray(jax.grad(f)(jnp.asarray(grid)))
    h = 0.01
    for idx in [tuple(i) for i in np.argwhere(np.abs(g) > 1e-3)[:5]]:
        e = np.zeros_like(grid)
        e[idx] = h
        fd = (float(f(grid + e)) - float(f(grid - e))) / (2 * h)
        # t is smooth in each voxel; the central difference's error is O(h^2 t''') ~ 1e-5, float32 t ~ 3e-7 / 2h
        assert g[idx] == pytest.approx(fd, rel=2e-2, abs=1e-4), idx


# ------------------------------------------------------------------------------------------------ hard cases
def _hard_case_sum(one):
    """A jitted function of `(scale, grid)`: the sum of `one(medium, o, d)` over `RAYS` (compiled once per grid
    shape)."""
    o = jnp.asarray([r[0] for r in RAYS], jnp.float32)
    d = jnp.asarray([np.asarray(r[1]) / np.linalg.norm(r[1]) for r in RAYS], jnp.float32)

    @jax.jit
    def f(sc, D):
        med = GridMedium(D, sc, 0.8, jf.HenyeyGreenstein(0.3), bounds=BOX)
        return jnp.sum(jax.vmap(lambda a, b: one(med, a, b))(o, d))

    return f


def _every_method(med, o, d):
    fl = med.sample_free_flight(o, d, 3.0, False, True, 0.3, 0.5)
    q = jnp.where(fl.scattered, fl.q, 1.0)
    return (jnp.sum(med.transmittance(o, d, jnp.inf)) + jnp.sum(med.surface_weight(o, d, 3.0, fl.log_one_minus_q))
            + jnp.sum(med.collision_weight(med, o, d, 3.0, q, fl.t)) + med.free_flight_pdf(o, d, 3.0, q, fl.t)
            + fl.t)


HARD_CASES = _hard_case_sum(_every_method)


@pytest.mark.parametrize("grid", [_grid(seed=8), np.zeros((4, 5, 6, 1), np.float32),
                                  np.full((1, 1, 1, 1), 3.0, np.float32)], ids=["random", "zero", "one_voxel"])
def test_values_and_gradients_are_finite_on_hard_cases(grid):
    """Every method of the medium, with its gradient with respect to `scale` and every voxel, on rays through the
    box, from inside it, along axes, through a corner, missing it and leaving it; at scale 0, 0.7 and 1e4."""
    for scale in (0.0, 0.7, 1e4):
        v, grads = jax.value_and_grad(HARD_CASES, argnums=(0, 1))(jnp.float32(scale), jnp.asarray(grid))
        assert np.isfinite(float(v)), scale
        assert all(np.all(np.isfinite(np.asarray(x))) for x in grads), scale


@pytest.mark.parametrize("n", [5, 40])  # below and above MERGE_SEARCH_MIN: pairwise comparisons, binary search
def test_merge_sorted_equals_numpy_sort_with_ties(n):
    """`_merge_sorted` of ascending lists (repeated values inside a list and across lists, as clipped plane
    crossings have) is exactly `np.sort` of their concatenation, by either way of counting."""
    from jaxfog._grid import MERGE_SEARCH_MIN, _merge_sorted

    rng = np.random.default_rng(n)
    lists = [np.float32([0.25]), *(np.sort(rng.choice(np.float32([0.25, 0.5, 1.0, 1.5, 2.0, 3.0]), n)
                                          + np.where(rng.uniform(size=n) < 0.5, 0, rng.uniform(size=n)))
                                  .astype(np.float32) for _ in range(3)), np.float32([3.0])]
    assert (n >= MERGE_SEARCH_MIN) == (max(len(x) for x in lists) >= MERGE_SEARCH_MIN)
    out = np.asarray(jax.jit(_merge_sorted)([jnp.asarray(x) for x in lists]))
    np.testing.assert_array_equal(out, np.sort(np.concatenate(lists)))


def test_profile_of_a_ray_that_misses_the_box_is_empty():
    grid = _grid()
    pr = profile(jnp.asarray(grid).reshape(-1, 1), (6, 5, 4), jnp.array(BOX[0]), jnp.array(BOX[1]),
                 jnp.array([5.0, 5.0, 5.0]), jnp.array([1.0, 0.0, 0.0]))
    assert float(jnp.sum(pr.length)) == 0.0


def test_bad_grids_are_refused_when_built():
    with pytest.raises(ValueError, match="density must be finite and >= 0: 1 values"):
        _medium(np.array([[[1.0, -1.0]]], np.float32))
    with pytest.raises(ValueError, match=r"C = 1 or 3"):
        _medium(np.ones((2, 2, 2, 2), np.float32))
    with pytest.raises(ValueError, match="scale"):
        _medium(_grid(), scale=-1.0)
    with pytest.raises(ValueError, match="bounds"):
        _medium(_grid(), box=((0, 0, 0), (0, 1, 1)))


# ---------------------------------------------------------------------------------------------- scene files
def test_the_shipped_grid_scene_loads_with_the_file_box(tmp_path):
    sf = jf.load_scene(REPO / "data_synthetic" / "scenes" / "grid_fog.json")
    assert isinstance(sf.scene.medium, GridMedium)
    assert sf.scene.medium.resolution == (16, 16, 16)
    assert sf.data["medium"]["bounds"] == {"min": [-2.0, -0.5, -2.0], "max": [2.0, 2.5, 1.5]}


@pytest.mark.parametrize("medium, message", [
    ({"file": "nowhere.vol"}, "medium.file: .*not found"),
    ({"file": "g.npy"}, "medium.file: .*bounds"),
    ({"file": "g.vol", "scale": -1}, "medium.scale"),
    ({"file": "g.vol", "tracking": "delta"}, "medium.tracking: .*expected one of"),
    ({"file": "g.vol", "lookup": "nearest"}, "medium.lookup: .*expected one of 'stochastic', 'trilinear'"),
])
def test_bad_grid_media_in_scene_files_are_refused(tmp_path, medium, message):
    np.save(tmp_path / "g.npy", np.ones((2, 2, 2), np.float32))
    jf.write_vol(tmp_path / "g.vol", np.ones((2, 2, 2), np.float32), ((0, 0, 0), (1, 1, 1)))
    data = json.loads((REPO / "data_synthetic" / "scenes" / "grid_fog.json").read_text())
    data["medium"] = {"type": "grid", "albedo": 0.9, "g": 0.5, **medium}
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(data))
    with pytest.raises(jf.SceneError, match=message):
        jf.load_scene(path)


# ---------------------------------------------------------------------------------------------------- renders
def _with_medium(scene, med):
    return eqx.tree_at(lambda s: s.medium, scene, med)


@pytest.mark.slow  # two render programs compiled (~30 s on 2 cores): the default run keeps the unit tests above
def test_a_constant_grid_renders_like_the_homogeneous_medium_in_its_box():
    """Independent keys; the two image means agree within 3 standard errors of their difference (each from the
    renders' own per-pixel variances)."""
    scene = jf.load_scene(REPO / "data_synthetic" / "scenes" / "spot_fog.json",
                          ["camera.width=8", "camera.height=8", "integrator.max_depth=3"]).scene
    box = ((-2.0, -0.5, -2.0), (2.0, 2.5, 1.5))
    hom = HomogeneousMedium(0.5, 0.9, scene.medium.phase, bounds=box)
    grid = GridMedium(np.full((3, 3, 3), 2.0, np.float32), 0.25, 0.9, scene.medium.phase, bounds=box)
    means, ses = [], []
    for med, key in ((hom, 1), (grid, 2)):
        img, var = jf.render(_with_medium(scene, med), jax.random.key(key), 64, variance=True)
        img, var = np.asarray(img), np.asarray(var)
        means.append(img.mean())
        ses.append(math.sqrt(var.sum()) / img.size)
    assert abs(means[0] - means[1]) < 3 * math.hypot(*ses), (means, ses)


@pytest.mark.slow  # reverse mode through a render: ~1 min of compilation on 2 cores
def test_voxel_gradients_of_a_render_match_finite_differences():
    """`jax.grad` of an image's mean with respect to every voxel of a 3^3 grid, against central differences of the
    same estimator ("proposal": for a fixed key the image is a smooth function of the voxels). Tolerance: the
    difference's truncation error O(h^2) and float32 rounding of the mean (~1e-7 / 2h)."""
    scene = jf.load_scene(REPO / "data_synthetic" / "scenes" / "spot_fog.json",
                          ["camera.width=6", "camera.height=6", "integrator.max_depth=3"]).scene
    box = ((-2.0, -0.5, -2.0), (2.0, 2.5, 1.5))
    D0 = np.random.default_rng(0).uniform(0.2, 1.0, (3, 3, 3, 1)).astype(np.float32)
    prop = GridMedium(D0, 0.6, 0.9, scene.medium.phase, bounds=box)

    def f(D):
        med = GridMedium(D, 0.6, 0.9, scene.medium.phase, bounds=box)
        return jnp.mean(jf.render(_with_medium(scene, med), jax.random.key(3), 16, estimator="proposal",
                                  proposal=prop))

    g = np.asarray(jax.grad(f)(jnp.asarray(D0)))
    assert np.all(np.isfinite(g))
    h = 0.02
    for idx in [(1, 1, 1, 0), (2, 0, 0, 0), (0, 2, 1, 0)]:
        e = np.zeros_like(D0)
        e[idx] = h
        fd = (float(f(D0 + e)) - float(f(D0 - e))) / (2 * h)
        assert g[idx] == pytest.approx(fd, rel=0.02, abs=2e-6), idx


@pytest.mark.parametrize("tracking", ["exact", "ratio"])
def test_reverse_mode_over_every_voxel_replays_the_paths_and_equals_forward_mode(tracking):
    """With paths of any length (`max_depth = -1`), `jax.grad` over all 27 voxels of a 3^3 grid runs path replay
    (memory independent of the path length); it must equal `jax.jacfwd` of the same render (the loop's own
    tangents, same key) to float32 rounding of sums over 576 paths: 1e-5 of the largest entry. With ratio tracking
    (one majorant cell: many tracking points per segment) the replay also draws each segment's points again."""
    scene = jf.load_scene(REPO / "data_synthetic" / "scenes" / "spot_fog.json",
                          ["camera.width=6", "camera.height=6", "integrator.max_depth=-1"]).scene
    box = ((-2.0, -0.5, -2.0), (2.0, 2.5, 1.5))
    D0 = jnp.asarray(_grid(shape=(3, 3, 3, 1), seed=21, lo=0.2, hi=1.0))
    scene = eqx.tree_at(lambda s: s.medium, scene, GridMedium(D0, 1.0, 0.9, scene.medium.phase, bounds=box,
                                                              tracking=tracking, majorant_cells=1))

    def f(D):
        return jf.render(eqx.tree_at(lambda s: s.medium.density, scene, D), jax.random.key(3), 16).mean()

    rev, fwd = np.asarray(jax.jit(jax.grad(f))(D0)), np.asarray(jax.jit(jax.jacfwd(f))(D0))
    assert np.max(np.abs(fwd)) > 0
    np.testing.assert_allclose(rev, fwd, rtol=0, atol=1e-5 * np.max(np.abs(fwd)))


def test_reverse_mode_through_ratio_tracking_at_a_fixed_depth_says_what_works():
    """A fixed max_depth has no path replay: `jax.grad` through ratio tracking raises the renderer's message (paths
    of any length, forward mode, or exact profiles), not JAX's loop error; forward mode works."""
    scene = jf.load_scene(REPO / "data_synthetic" / "scenes" / "spot_fog.json",
                          ["camera.width=4", "camera.height=4", "integrator.max_depth=2"]).scene
    D0 = jnp.asarray(_grid(shape=(3, 3, 3, 1), seed=21, lo=0.2, hi=1.0))
    scene = eqx.tree_at(lambda s: s.medium, scene, GridMedium(D0, 1.0, 0.9, scene.medium.phase, tracking="ratio",
                                                              bounds=((-2.0, -0.5, -2.0), (2.0, 2.5, 1.5))))

    def f(D):
        return jf.render(eqx.tree_at(lambda s: s.medium.density, scene, D), jax.random.key(3), 4).mean()

    assert np.max(np.abs(np.asarray(jax.jacfwd(f)(D0)))) > 0
    with pytest.raises(Exception, match=r'tracking="ratio" needs paths of any length \(integrator max_depth = -1\)'):
        jax.grad(f)(D0)


@pytest.mark.slow  # Mitsuba 3 at 4 x 4096 spp and jaxfog at 512 spp: a few minutes on 2 cores
def test_the_patchy_grid_agrees_with_mitsuba():
    """The shipped patchy grid (16^3) at 16 x 16 px, max_depth 3, with exact profiles and with ratio tracking: each
    image mean agrees with Mitsuba's within 2% plus 3 standard errors of the difference (jaxfog's from its per-pixel
    variances, Mitsuba's from four independent renders)."""
    pytest.importorskip("mitsuba")
    scene = REPO / "data_synthetic" / "scenes" / "grid_fog.json"
    ov = ["camera.width=16", "camera.height=16", "integrator.max_depth=3"]
    means = [jf.render_mitsuba(scene, spp=4096, seed=s, overrides=ov).mean() for s in range(4)]
    mi_mean, mi_se = float(np.mean(means)), float(np.std(means, ddof=1)) / 2.0
    for tracking in ("exact", "ratio"):
        sc = jf.load_scene(scene, ov + [f'medium.tracking="{tracking}"']).scene
        img, var = jf.render(sc, jax.random.key(5), 512, variance=True)
        img, var = np.asarray(img), np.asarray(var)
        se = math.hypot(math.sqrt(var.sum()) / img.size, mi_se)
        assert abs(img.mean() - mi_mean) < 0.02 * mi_mean + 3 * se, (tracking, img.mean(), mi_mean, se)


GRID_FIT = REPO / "data_synthetic" / "grid_fit"
FIT_VIEWS, HELD_OUT = ("front", "side", "back", "left"), "top"


@pytest.mark.parametrize("folder, res, px", [("grid_fit", 4, 8), ("grid_fit8", 8, 16)])
def test_the_shipped_voxel_fit_set_is_consistent(folder, res, px):
    """`data_synthetic/grid_fit/` and `grid_fit8/` (written by `make_grid_fit.py`, the second with `--res 8 --px
    16`): every view's scene holds the truth grid and its target is the camera's size (`px`), finite, with its spp
    in the header; the truth is the script's grid at `res` texels an axis."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("make_grid_fit", REPO / "data_synthetic" / "make_grid_fit.py")
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    truth, box = jf.read_vol(REPO / "data_synthetic" / folder / "truth.vol")
    np.testing.assert_array_equal(np.asarray(truth)[..., 0], gen.blob_grid(res))
    for name in FIT_VIEWS + (HELD_OUT,):
        sc = jf.load_scene(REPO / "data_synthetic" / folder / f"{name}.json").scene
        assert isinstance(sc.medium, jf.GridMedium)
        np.testing.assert_array_equal(np.asarray(sc.medium.density), np.asarray(truth))
        img, meta = jf.read_exr(REPO / "data_synthetic" / folder / f"{name}.exr")
        assert img.shape == (px, px, 3) == (sc.camera.height, sc.camera.width, 3)
        assert np.all(np.isfinite(img)) and img.mean() > 0
        assert int(json.loads(str(meta["jaxfog:spp"]))) == gen.SPP


@pytest.mark.slow  # reverse mode through four views' renders for 120 iterations: about 4 minutes on 2 cores
def test_a_small_grid_fit_finds_a_known_blob_and_predicts_a_held_out_view():
    """The shipped set (`data_synthetic/grid_fit/`): a 4^3 blob over thin haze, four views (8 x 8 px, 2048 spp); the
    fit starts from a constant grid. Checks what this fit achieves (docs/results/grid.md): the volume error (relative
    L2 over the voxels) falls by at least a quarter, the fitted blob's voxels are over twice as dense as the haze's,
    and the view from above, which the fit did not see, is predicted better by the fitted grid than by the start
    (both rendered with one key, so their difference is not the renders' noise). It does not check that the voxels
    reach the truth (measured: 0.74 -> 0.46 after 240 iterations)."""
    from fitting.grid import fit_grid, heldout_error, load_views

    truth = np.asarray(jf.read_vol(GRID_FIT / "truth.vol")[0])[..., 0]
    views = load_views([(str(GRID_FIT / f"{n}.json"), str(GRID_FIT / f"{n}.exr")) for n in FIT_VIEWS], 1)
    density, se, history = fit_grid(views, iterations=120, spp=16, start=0.3, seed=0, smooth="auto", truth=truth,
                                    log=lambda s: None)
    assert np.all(np.isfinite(density)) and np.all(np.isfinite(se)) and np.all(se > 0)
    assert history[-1]["volume_error"] <= 0.75 * history[0]["volume_error"], (history[0], history[-1])
    blob = truth > 0.8
    assert density[blob].mean() > 2 * density[~blob].mean()
    held = load_views([(str(GRID_FIT / f"{HELD_OUT}.json"), str(GRID_FIT / f"{HELD_OUT}.exr"))], 1)[0]
    key = jax.random.key(7)
    start = heldout_error(held, np.full(truth.shape, 0.3, np.float32), 512, key)
    fit = heldout_error(held, density, 512, key)
    assert fit["relative_rms"] < start["relative_rms"], (start, fit)


@pytest.mark.slow  # four views linearised in one program (~1.5 min to compile) and 8 steps at 128 spp: ~4 minutes
def test_a_gauss_newton_grid_fit_finds_the_blob_closer_than_its_start():
    """The shipped set as above, Levenberg-Marquardt with matrix-free normal equations (`--solver gauss-newton`),
    8 steps at 128 spp. Checks what it achieves (docs/results/grid.md, measured 0.756 -> 0.29 in 8 steps): the
    volume error at most half the start's, the blob's voxels over twice as dense as the haze's, the view from
    above predicted better than by the start (one key for both renders), and the standard errors of the closing
    step: at least 80% of the 64 voxels within 2 se of the truth (95% for calibrated errors; the binomial's standard
    deviation is 2.7% for 64 independent voxels, about 5% for the ~20 independent ones a smooth fit has, so 80% is
    3 of those below; measured 94%, and 78% with the discrepancy principle's weight and no closing step)."""
    from fitting.grid import fit_grid_gauss_newton, heldout_error, load_views

    truth = np.asarray(jf.read_vol(GRID_FIT / "truth.vol")[0])[..., 0]
    views = load_views([(str(GRID_FIT / f"{n}.json"), str(GRID_FIT / f"{n}.exr")) for n in FIT_VIEWS], 1)
    density, se, history = fit_grid_gauss_newton(views, iterations=8, spp=128, start=0.3, seed=0, smooth="auto",
                                                 truth=truth, log=lambda s: None)
    assert np.all(np.isfinite(density)) and np.all(np.isfinite(se)) and np.all(se > 0)
    start_error = float(np.linalg.norm(0.3 - truth) / np.linalg.norm(truth))
    assert history[-1]["volume_error"] <= 0.5 * start_error, (start_error, history[-1])
    blob = truth > 0.8
    assert density[blob].mean() > 2 * density[~blob].mean()
    held = load_views([(str(GRID_FIT / f"{HELD_OUT}.json"), str(GRID_FIT / f"{HELD_OUT}.exr"))], 1)[0]
    key = jax.random.key(7)
    start = heldout_error(held, np.full(truth.shape, 0.3, np.float32), 512, key)
    assert heldout_error(held, density, 512, key)["relative_rms"] < start["relative_rms"]
    z = (np.log(density) - np.log(truth)) / (se / density)  # se of the log-density
    assert np.mean(np.abs(z) < 2) >= 0.8, np.round(z, 2)


def test_coarse_to_fine_levels_halve_each_axis_and_a_coarse_grid_is_read_as_the_renderer_reads_it():
    """`level_shapes` halves each axis per level (rounded up, at least 1); `upsample` of a coarse grid at a finer
    grid's texel centres (same box) equals the renderer's own trilinear lookup (`_grid.trilinear`, clamped at the
    border) of the coarse grid at those points, and a grid read at its own shape is itself."""
    from fitting.grid import level_shapes, upsample
    from jaxfog._grid import trilinear

    assert level_shapes((4, 4, 4), 2) == [(2, 2, 2), (4, 4, 4)]
    assert level_shapes((5, 3, 1), 3) == [(2, 1, 1), (3, 2, 1), (5, 3, 1)]
    coarse = np.random.default_rng(3).uniform(-1.0, 1.0, (2, 3, 4))  # (nz, ny, nx)
    fine_shape = (5, 6, 7)
    got = upsample(coarse, fine_shape)
    flat = jnp.asarray(coarse.reshape(-1, 1), jnp.float32)
    res = (4, 3, 2)  # (nx, ny, nz)
    for z, y, x in [(0, 0, 0), (4, 5, 6), (2, 3, 3), (1, 0, 5), (3, 4, 1)]:
        fine_centre = np.array([x, y, z], np.float64) + 0.5  # in fine texels, (x, y, z)
        coarse_coord = fine_centre * np.array(res) / np.array(fine_shape[::-1]) - 0.5
        want = float(trilinear(flat, res, jnp.asarray(coarse_coord, jnp.float32))[0])
        assert got[z, y, x] == pytest.approx(want, abs=1e-6)
    np.testing.assert_allclose(upsample(coarse, coarse.shape), coarse, atol=1e-12)


def test_the_levenberg_marquardt_direction_solves_the_damped_normal_equations():
    """`lm_direction` with an explicit symmetric positive semi-definite matrix (rank-deficient, as a voxel Jacobian
    is): the conjugate-gradient step against `numpy.linalg.solve` of `(A + lambda I) delta = -g` within CG's
    relative tolerance (with the condition number of the damped system), the clip, and the model decrease."""
    from fitting.grid import CG_RTOL, MAX_STEP, lm_direction

    rng = np.random.default_rng(0)
    J = rng.normal(size=(12, 20))
    A = J.T @ J  # rank 12 of 20
    g = rng.normal(size=20) * 0.05
    for damping in (0.1, 1.0):
        delta, pred = lm_direction(jnp.asarray(g, jnp.float32), lambda v: jnp.asarray(A, jnp.float32) @ v,
                                   jnp.float32(damping))
        lam = damping * g @ A @ g / (g @ g)
        want = np.linalg.solve(A + lam * np.eye(20), -g)
        cond = np.linalg.cond(A + lam * np.eye(20))
        assert np.max(np.abs(want)) < MAX_STEP  # no clip active in this case
        np.testing.assert_allclose(np.asarray(delta), want, atol=CG_RTOL * cond * np.max(np.abs(want)) + 1e-5)
        assert float(pred) == pytest.approx(-(g @ want + 0.5 * want @ A @ want), rel=0.05)
    big, _ = lm_direction(jnp.asarray(g * 1e3, jnp.float32), lambda v: jnp.asarray(A, jnp.float32) @ v,
                          jnp.float32(1e-3))
    assert float(jnp.max(jnp.abs(big))) <= MAX_STEP


def test_views_of_one_structure_are_stacked_into_one_group():
    """Four views of the shipped set (the same scene structure, other cameras) make one group with a leading axis
    of 4 (one render traced for all); a view with another `max_depth` (static structure) its own group."""
    from fitting.grid import load_views, stack_views

    views = load_views([(str(GRID_FIT / f"{n}.json"), str(GRID_FIT / f"{n}.exr")) for n in FIT_VIEWS], 1)
    groups = stack_views(views)
    assert len(groups) == 1 and groups[0][1].shape == (4, 8, 8, 3)
    assert np.allclose(np.asarray(groups[0][0].camera.origin[2]), np.asarray(views[2][0].camera.origin))
    other = jf.load_scene(GRID_FIT / "side.json", ["camera.width=8", "camera.height=8",
                                                   f"integrator.max_depth={views[1][0].max_depth + 1}"]).scene
    assert len(stack_views([views[0], (other, views[1][1], views[1][2])])) == 2


def test_fit_density_passes_its_options_to_the_voxel_fit_and_refuses_the_others():
    """`python -m fitting.fit ... --fit density` is `fitting.grid`'s fit: the pairs, --out, --seed, --downscale and a
    given --spp pass on; another parameter beside density, or an option of the few-parameter fit, is refused with
    one line before any work (exit 2)."""
    from fitting import fit

    def argv_of(cmd):
        return fit.density_argv(fit.build_parser().parse_args(cmd), cmd)

    cmd = ["a.json", "a.exr", "b.json", "b.exr", "--fit", "density", "--out", "r.json", "--seed", "3", "--spp", "16"]
    assert argv_of(cmd) == ["a.json", "a.exr", "b.json", "b.exr", "--out", "r.json", "--seed", "3", "--spp", "16"]
    assert "--spp" not in argv_of(cmd[:-2]), "the voxel fit's own spp unless one is given"
    pair = ["a.json", "a.exr", "--out", "r.json"]
    for extra, words in [(["--fit", "density", "g"], "fitted alone"),
                         (["--fit", "density", "--init", "sigma_t=0.3"], "--init"),
                         (["--fit", "density", "--budget", "5"], "--budget")]:
        with pytest.raises(fit.FitError, match=words):
            argv_of(pair + extra)
    with pytest.raises(fit.FitError, match="pairs"):
        argv_of(["a.json", "a.exr", "b.exr", "--fit", "density", "--out", "r.json"])


def test_fit_density_refuses_a_scene_without_a_grid(tmp_path, capsys):
    """A scene whose medium is not a grid: one line naming the file and the medium, exit 2, nothing written."""
    from fitting import fit

    scene = REPO / "data_synthetic" / "scenes" / "spot_fog.json"
    target = REPO / "data_synthetic" / "targets" / "spot_fog__mid.exr"
    out = tmp_path / "r.json"
    assert fit.main([str(scene), str(target), "--fit", "density", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "spot_fog.json" in err and "HomogeneousMedium" in err and "grid" in err
    assert not out.exists()


def test_a_coarse_to_fine_grid_fit_refuses_levels_it_cannot_run(tmp_path, capsys):
    """`--levels` below 1, with Adam, or with no step left for the finest grid: one line, exit 2, nothing written."""
    from fitting import grid

    pair = [str(GRID_FIT / "front.json"), str(GRID_FIT / "front.exr")]
    out = tmp_path / "r"
    for extra, words in [(["--levels", "0"], "--levels 0"), (["--levels", "2", "--solver", "adam"], "gauss-newton"),
                         (["--levels", "3", "--iterations", "8"], "more than 8")]:
        assert grid.main(pair + ["--out", str(out)] + extra) == 2
        assert words in capsys.readouterr().err
    assert not out.exists()


def test_grid_fit_output_paths_beside_a_result_file_or_in_a_folder():
    from fitting.grid import output_paths

    assert output_paths("out/fog.json") == {"result": "out/fog.json", "density": "out/fog_density.vol",
                                            "se": "out/fog_density_se.vol", "slices": "out/fog_slices.png"}
    assert output_paths("out")["density"] == os.path.join("out", "RESULT_density.vol")


def test_a_grid_sampled_from_height_fog_has_its_optical_depths():
    """A 3 x 64 x 3 grid of the height fog's extinction at the texel centres, against the height fog's closed form
    on rays inside the box: linear interpolation of `exp(-y / H)` with spacing `h` errs by at most `h^2 / (8 H^2)`
    relative (plus the clamped half texels at the top and bottom, where the ray's part is excluded)."""
    H, ny = 0.8, 64
    lo, hi = np.array([-1.0, 0.0, -1.0]), np.array([1.0, 3.0, 1.0])
    centres = lo[1] + (np.arange(ny) + 0.5) / ny * (hi[1] - lo[1])
    grid = np.broadcast_to((0.6 * np.exp(-centres / H))[None, :, None], (3, ny, 3)).astype(np.float32)
    med = GridMedium(grid, 1.0, 0.8, jf.HenyeyGreenstein(0.3), bounds=(lo, hi))
    fog = jf.HeightFog(sigma_0=0.6, height_scale=H, albedo=0.8, phase=jf.HenyeyGreenstein(0.3))
    h = (hi[1] - lo[1]) / ny
    bound = h * h / (8 * H * H)
    depth = jax.jit(lambda o, d, t: (med.optical_depth(o, d, t)[0], fog.optical_depth(o, d, t)[0]))
    for o, d in (((-0.9, 0.1, 0.0), (0.6, 0.8, 0.0)), ((0.5, 2.9, -0.5), (-0.3, -0.9, 0.3)), ((-0.9, 1.0, 0.2),
                                                                                            (1.0, 0.0, 0.0))):
        o = jnp.asarray(o, jnp.float32)
        d = jnp.asarray(d, jnp.float32) / np.linalg.norm(d)
        # stop where the ray would enter the clamped half texel at the box's top or bottom
        t_end = 1.5  # (every ray stays inside the box in x and z that far)
        if d[1] < 0:
            t_end = min(t_end, float((lo[1] + h / 2 + 1e-3 - o[1]) / d[1]))
        if d[1] > 0:
            t_end = min(t_end, float((hi[1] - h / 2 - 1e-3 - o[1]) / d[1]))
        got, want = depth(o, d, jnp.float32(t_end))
        assert abs(float(got) - float(want)) <= bound * float(want) + 1e-6, (float(got), float(want), bound)


def test_the_prior_hessian_is_the_neighbour_penalty_s():
    """`fitting.grid.prior_hessian` against `jax.hessian` of the penalty on a 2 x 3 x 4 grid (the penalty is
    quadratic, so the two agree to float32 rounding of the automatic one)."""
    from fitting.grid import neighbour_penalty, prior_hessian

    shape = (2, 3, 4)
    theta = jnp.asarray(np.random.default_rng(0).normal(size=shape), jnp.float32)
    auto = np.asarray(jax.hessian(lambda t: 0.7 * neighbour_penalty(t.reshape(shape)))(theta.ravel()))
    np.testing.assert_allclose(prior_hessian(shape, 0.7), auto, atol=1e-5)


def test_the_evidence_weight_recovers_the_prior_a_grid_was_drawn_from():
    """`fitting.grid.evidence_weight` on a linear-Gaussian model whose truth is drawn from the smoothness prior
    itself: a 6^3 grid `theta = c + sum_k z_k v_k / sqrt(alpha lambda_k)` over the graph Laplacian's eigenpairs
    (`alpha = 2 w`, w = 10), seen through 400 random projections with unit noise (`F = J^T J`; linearised at the
    posterior mean for the starting weight 1, with `g` the data gradient there). The evidence's fixed point
    estimates `w`; the log of its ratio to the truth has a standard deviation of about `sqrt(2 / gamma)` (gamma,
    the directions the data decide: about 150 here, so 0.12). So 12 seeded draws must give a mean log-ratio within
    4 of its standard errors (from their spread) of 0, each estimate within a factor 1.5 (3.5 such deviations), and
    a start 16x off must reach the same fixed point."""
    from fitting.grid import evidence_weight, prior_hessian

    shape, w_true = (6, 6, 6), 10.0
    L = prior_hessian(shape, 0.5)  # the graph Laplacian
    lam, V = np.linalg.eigh(L)
    n = lam.size
    logs = []
    for seed in range(12):
        rng = np.random.default_rng(seed)
        z = rng.normal(size=n)
        theta = 0.1 * z[0] + V[:, 1:] @ (z[1:] / np.sqrt(2.0 * w_true * lam[1:]))
        J = rng.normal(size=(400, n))
        y = J @ theta + rng.normal(size=400)
        F = J.T @ J
        theta0 = np.linalg.solve(F + 2.0 * L, J.T @ y)  # the fit's point at the starting weight 1
        g = F @ theta0 - J.T @ y
        w = evidence_weight(F, g, theta0, L, 1.0)
        assert 1 / 1.5 < w / w_true < 1.5, (seed, w)
        assert abs(evidence_weight(F, g, theta0, L, 16.0) - w) <= 1e-4 * w
        logs.append(math.log(w / w_true))
    mean, se = np.mean(logs), np.std(logs, ddof=1) / math.sqrt(len(logs))
    assert abs(mean) <= 4 * se, (mean, se, logs)


@pytest.mark.slow  # forward mode over every voxel of a grid, twice per view: ~1 min of compilation on 2 cores
def test_dense_voxel_information_matches_the_hutchinson_diagonal():
    """The dense two-key information's diagonal against Hutchinson's estimate of it (32 random-sign probes) on a
    2^3 grid seen by one 6 x 6 px view: both estimate `diag(J^T W J)`; the tolerance is 4 of the Hutchinson mean's
    standard errors (from its probes' spread) plus 10% for the dense matrix's own Monte Carlo noise (two 64-spp
    renders); `voxel_se` is the square root of the diagonal of the inverse of that matrix plus the prior's Hessian,
    which is at least the inverse square root of its diagonal (correlations only add variance)."""
    from fitting.grid import dense_information, hutchinson_diagonal, prior_hessian, voxel_se

    scene = jf.load_scene(REPO / "data_synthetic" / "scenes" / "spot_fog.json",
                          ["camera.width=6", "camera.height=6", "integrator.max_depth=3"]).scene
    box = ((-2.0, -0.5, -2.0), (2.0, 2.5, 1.5))
    med = GridMedium(np.full((2, 2, 2, 1), 0.5, np.float32), 1.0, 0.9, scene.medium.phase, bounds=box)
    scene = _with_medium(scene, med)
    img, var = jf.render(scene, jax.random.key(1), 256, variance=True)
    views = [(scene, img, var)]
    theta = jnp.full((2, 2, 2), math.log(0.5), jnp.float32)
    F, _ = dense_information(views, theta, 64, jax.random.key(2))
    probes = np.stack([np.asarray(hutchinson_diagonal(views, theta, 64, jax.random.key(10 + p), probes=1)).ravel()
                       for p in range(32)])
    hut, hut_se = probes.mean(0), probes.std(0, ddof=1) / math.sqrt(len(probes))
    assert np.all(np.abs(np.diag(F) - hut) <= 4 * hut_se + 0.1 * hut), (np.diag(F), hut, hut_se)
    se, how = voxel_se(views, theta, 64, jax.random.key(2), 0.1)
    A = F + prior_hessian((2, 2, 2), 0.1)
    assert how == "dense"
    np.testing.assert_allclose(se.ravel(), np.sqrt(np.diag(np.linalg.inv(A))), rtol=1e-6)
    assert np.all(se.ravel() >= (1 - 1e-9) / np.sqrt(np.diag(A)))


def test_shared_ray_values_compute_once_per_block_and_key_by_identity():
    """`_medium.shared` inside a `shared_ray_values` block calls its function once for the same argument objects
    (and again for equal values in other objects: traced arrays are compared by identity); outside a block, at every
    call; blocks do not see each other's values."""
    from jaxfog._medium import shared, shared_ray_values

    calls = []

    def fn(a, b):
        calls.append((a, b))
        return a + b

    x, y = np.ones(2), np.zeros(2)
    shared(fn, x, y)
    shared(fn, x, y)
    assert len(calls) == 2
    with shared_ray_values():
        r1, r2 = shared(fn, x, y), shared(fn, x, y)
        assert r1 is r2 and len(calls) == 3
        shared(fn, x.copy(), y)
        assert len(calls) == 4
        with shared_ray_values():
            shared(fn, x, y)
            assert len(calls) == 5
    shared(fn, x, y)
    assert len(calls) == 6


def test_a_render_with_shared_profiles_equals_one_without():
    """The tracer builds a grid's profile once per segment and medium (`shared_ray_values` in `_integrator.bounce`):
    the image and its forward-mode derivative along a random direction over the voxels equal those of the same
    render that builds the profile at every call, with the default ("detached") estimator, whose sampler's profile
    must carry no derivative (a cache keyed on the ray alone would give it the medium's). Tolerance: float32 rounding
    of the sums, which the two compiled programs may order differently."""
    import jaxfog._grid as G

    scene = jf.load_scene(REPO / "data_synthetic" / "scenes" / "spot_fog.json",
                          ["camera.width=4", "camera.height=4", "integrator.max_depth=2"]).scene
    box = ((-2.0, -0.5, -2.0), (2.0, 2.5, 1.5))
    D0 = jnp.asarray(_grid(shape=(2, 3, 2, 1), seed=5, lo=0.2, hi=1.0))
    dD = jnp.asarray(_grid(shape=(2, 3, 2, 1), seed=6, lo=-1.0, hi=1.0))

    def f(D):
        med = GridMedium(D, 0.6, 0.9, scene.medium.phase, bounds=box)
        return jf.render(_with_medium(scene, med), jax.random.key(4), 4)

    def run():  # traced afresh (the renderer keeps its traced programs)
        jax.clear_caches()
        return jax.jit(lambda D: jax.jvp(f, (D,), (dD,)))(D0)

    on = run()
    original = G.shared
    try:
        G.shared = lambda fn, *args: fn(*args)
        off = run()
    finally:
        G.shared = original
        jax.clear_caches()
    for a, b in zip(on, off):
        a, b = np.asarray(a), np.asarray(b)
        assert np.all(np.isfinite(a)) and np.max(np.abs(b)) > 0
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5 * float(np.max(np.abs(b))))
