"""A density grid: fog whose extinction is a trilinearly interpolated voxel grid in a box, with exact optical depths
and exactly inverted free flight (docs/estimators.md, "Grid media").

The extinction at a point is `scale * D(p)`: `D` the trilinear interpolation of the grid's values at texel centres
`(i + 1/2) / n` of the box (clamped at the border, zero outside the box), Mitsuba 3's `gridvolume` with
`filter_type = "trilinear"`, `wrap_mode = "clamp"` and `to_world` mapping the unit cube onto the box.

**Exact optical depth.** In grid coordinates `x = (p - box_min) / (box_max - box_min) n - 1/2` the texel centres
are the integer planes. Between two consecutive crossings of such planes (or of the box's faces) a ray stays in
one interpolation cell, where each of the three fractional coordinates is linear in `t` and `D` is a cubic
polynomial in `t` (a product of three linear weights). A ray's *profile* is its at most `nx + ny + nz + 1` such
intervals with the cubic's four coefficients on each (8 grid reads per interval); the optical depth to any `t` is
the sum of the cubics' integrals (quartics) up to `t`. Nothing is estimated: transmittance has no variance, and
its derivative with respect to every voxel is exact (plain automatic differentiation; the breakpoints depend on the
ray only).

**Exact free flight.** The medium branch is chosen as for the homogeneous medium (`_medium.branch_probability`
with the optical depth `tau(s)` in place of `sigma_t s`); its distance solves `tau(t) = -log(1 - x (1 - e^-tau(s)))`:
the interval from the cumulative depths, then the quartic by safeguarded Newton iterations (float32 precision).
The density of a vertex is therefore known exactly (`q sigma(t) e^-tau(t) / (1 - e^-tau(s))`), which is what the
equiangular MIS and the estimators need. For the "reparam" estimator the distance moves with the parameters by the
implicit function theorem, `dt = (dT - d tau(t)) / sigma(t)`, written as a first-order correction of the solved
`t` (no derivative flows through the iterations).

**Ratio tracking** (`tracking="ratio"`): the exact profile reads every cell the ray crosses, which on fine grids
costs far more than the rest of a path. A coarse *majorant grid* (`majorant_cells` per axis) holds, per cell, the
largest and smallest value the trilinear `D` takes there (`block_bounds`); a ray's coarse profile is its few
intervals through it (`coarse_profile`, one read each). Free flight then samples the majorant's piecewise-constant
density exactly (so its pdf is known: the equiangular MIS and the estimators' weights are unchanged), and every
transmittance the weights need is estimated by residual ratio tracking against it (`ratio_tracking`: the smallest
value as control, Poisson points at the rate of the difference; Novak et al. 2014), unbiased, with a cost that
follows the difference's optical depth instead of the grid's resolution. The points are drawn from a hash of the
ray (`ray_seed`), so a fixed key still gives an image that is a smooth function of the voxel values. Its loop is a
`lax.while_loop`: forward-mode derivatives (`jax.jvp`, `jacfwd`) through it; reverse mode only in path replay
(`max_depth = -1`), which draws each segment's points again (`_replayed_product`); with a fixed `max_depth`,
reverse mode raises `RATIO_REVERSE_MESSAGE`.
`docs/results/grid.md` measures the two against each other: time per sample and variance.

RGB grids (three channels of extinction) use one-sample spectral MIS over the channels: channel `c`'s technique
chooses the medium branch with `q_c` and samples its own distance; the branch is taken with `q = mean_c q_c`, the
channel in proportion to `q_c` (a channel without fog on the segment has `q_c = 0`), and the vertex density is
`mean_c q_c p_c(t)` (balance heuristic). A one-channel grid is grey (the albedo may be RGB).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._fields import concrete, rgb, scalar
from ._medium import (
    Q_MAX_SURFACE,
    Q_MIN,
    AbstractMedium,
    FlightSample,
    box_interval,
    check_bounds,
    check_phase_and_extent,
    inside_box,
    replaying,
    shared,
)
from ._phase import AbstractPhaseFunction, HenyeyGreenstein
from ._validate import NON_NEGATIVE, UNIT, check_range

SCALE_HAT_MIN = 1e-6
"""Smallest scale a sampler uses (dimensionless): a grid of scale 0 still samples medium vertices where its density
is non-zero, so the derivative with respect to `scale` is estimated at 0 too (as `SIGMA_HAT_MIN` does for the
homogeneous medium)."""

NEWTON_STEPS = 12
"""Safeguarded Newton iterations that solve one cell's quartic for the free-flight distance: quadratic convergence
from the linear guess reaches float32 precision in 3-5; the bracket's bisection (when a Newton step leaves it)
halves the error per step."""

MAX_VOXELS = 2 ** 31
"""Most values a grid may hold (flat int32 indices)."""


# ------------------------------------------------------------------------------------------------ pure math
def poly_value(c: Float[Array, "... 4"], s) -> Float[Array, "..."]:
    """The cubic `c0 + c1 s + c2 s^2 + c3 s^3` (Horner)."""
    return c[..., 0] + s * (c[..., 1] + s * (c[..., 2] + s * c[..., 3]))


def poly_integral(c: Float[Array, "... 4"], s) -> Float[Array, "..."]:
    """`integral_0^s` of the cubic `c`: `s (c0 + s (c1 / 2 + s (c2 / 3 + s c3 / 4)))`."""
    return s * (c[..., 0] + s * (c[..., 1] / 2.0 + s * (c[..., 2] / 3.0 + s * c[..., 3] / 4.0)))


def solve_quartic_depth(c: Float[Array, "4"], h, target) -> Float[Array, ""]:
    """The `s` in [0, h] with `poly_integral(c, s) = target`, for a cubic `c` that is >= 0 on [0, h] (so the
    integral increases) and `0 <= target <= poly_integral(c, h)`: safeguarded Newton from the linear guess (a step
    that leaves the bracket, or meets a zero density, bisects instead). Not differentiated (callers detach it)."""
    c, h, target = jax.lax.stop_gradient((c, h, target))
    total = poly_integral(c, h)
    pos = total > 0
    s0 = jnp.where(pos, h * jnp.clip(target / jnp.where(pos, total, 1.0), 0.0, 1.0), 0.0)

    def step(_, carry):
        s, lo, hi = carry
        f = poly_integral(c, s) - target
        lo, hi = jnp.where(f < 0, s, lo), jnp.where(f < 0, hi, s)
        dens = poly_value(c, s)
        ok = dens > 0
        s_newton = s - f / jnp.where(ok, dens, 1.0)
        inside = ok & (s_newton > lo) & (s_newton < hi)
        return jnp.where(inside, s_newton, 0.5 * (lo + hi)), lo, hi

    s, _, _ = jax.lax.fori_loop(0, NEWTON_STEPS, step, (s0, jnp.zeros_like(h), h))
    return jnp.clip(s, 0.0, h)


class Profile(NamedTuple):
    """A ray's path through the grid: `start` (m,) the intervals' first distances (scene units, ascending),
    `length` (m,) their lengths (>= 0; 0 for the unused ones), `coef` (m, C, 4) the density `D` on each interval
    as a cubic in the distance from its start, and `cum` (m, C) the integral of `D` up to each interval's start.
    Unscaled (the extinction is `scale * D`): one profile serves a medium and its sampler."""

    start: Float[Array, " m"]
    length: Float[Array, " m"]
    coef: Float[Array, "m C 4"]
    cum: Float[Array, "m C"]


def _grid_coords(p, lo, hi, n):
    """A point's grid coordinates (texel centres are the integers)."""
    return (p - lo) * (n / (hi - lo)) - 0.5


def _corner_indices(i0, n):
    """The two clamped indices `(clip(i0, 0, n-1), clip(i0 + 1, 0, n-1))` along one axis."""
    return jnp.clip(i0, 0, n - 1), jnp.clip(i0 + 1, 0, n - 1)


def _cell_values(flat, res, i0):
    """The 8 corner values `(2, 2, 2, C)` (z, y, x) of the interpolation cell with lower corner `i0` (x, y, z),
    indices clamped to the grid."""
    nx, ny, nz = res
    x0, x1 = _corner_indices(i0[0], nx)
    y0, y1 = _corner_indices(i0[1], ny)
    z0, z1 = _corner_indices(i0[2], nz)
    zs = jnp.stack([z0, z1])[:, None, None]
    ys = jnp.stack([y0, y1])[None, :, None]
    xs = jnp.stack([x0, x1])[None, None, :]
    return flat[(zs * ny + ys) * nx + xs]


def trilinear(flat, res, x) -> Float[Array, " C"]:
    """`D` at the grid coordinate `x` (3,): trilinear between texel centres, clamped at the border."""
    i0 = jnp.floor(x)
    f = x - i0
    v = _cell_values(flat, res, i0.astype(jnp.int32))
    v = v[:, :, 0] + f[0] * (v[:, :, 1] - v[:, :, 0])  # along x
    v = v[:, 0] + f[1] * (v[:, 1] - v[:, 0])  # along y
    return v[0] + f[2] * (v[1] - v[0])  # along z


def stochastic_trilinear(flat, res, x, u) -> Float[Array, " C"]:
    """One texel of the trilinear cell at grid coordinate `x` (3,), drawn with the trilinear weights by the uniform
    `u` in [0, 1) (its remainder reused axis by axis, x then y then z): an unbiased one-read estimate of
    `trilinear(flat, res, x)`, and every value it returns lies between the cell's smallest and largest texel
    (clamped at the border as `trilinear`)."""
    nx, ny, nz = res
    i0 = jnp.floor(x)
    f = x - i0
    i0 = i0.astype(jnp.int32)
    idx = []
    for a, n in enumerate((nx, ny, nz)):
        lo_p = 1.0 - f[a]  # the probability of the lower texel
        up = u >= lo_p
        u = jnp.where(up, (u - lo_p) / jnp.where(up, jnp.maximum(f[a], 1e-30), 1.0),
                      u / jnp.where(up, 1.0, jnp.maximum(lo_p, 1e-30)))
        u = jnp.clip(u, 0.0, 0.99999994)
        idx.append(jnp.clip(i0[a] + up.astype(jnp.int32), 0, n - 1))
    return flat[(idx[2] * ny + idx[1]) * nx + idx[0]]


def _lerp_linear(p0, p1, alpha, beta):
    """`p0 + (p1 - p0) (alpha + beta s)` for polynomials given as coefficient tuples (lowest degree first):
    one degree higher."""
    diff = [q1 - q0 for q0, q1 in zip(p0, p1)]
    out = [q0 + alpha * dq for q0, dq in zip(p0, diff)] + [0.0]
    for j, dq in enumerate(diff):
        out[j + 1] = out[j + 1] + beta * dq
    return out


def _cell_cubic(flat, res, g0, gd, start, length) -> Float[Array, "C 4"]:
    """The density `D` on the interval `[start, start + length]` of the ray `g0 + t gd` (grid coordinates) as a
    cubic in `t - start`: its cell (from the interval's midpoint, so a breakpoint's rounding cannot pick the
    neighbour), the cell's 8 values, and the three linear interpolations (x, then y, then z) as polynomial
    products, written out per coefficient."""
    i0 = jnp.floor(g0 + (start + 0.5 * length) * gd).astype(jnp.int32)
    v = _cell_values(flat, res, i0)  # (z, y, x, C)
    alpha = g0 + start * gd - i0  # fractional coordinates at the interval's start
    cx = [[_lerp_linear([v[z, y, 0]], [v[z, y, 1]], alpha[0], gd[0]) for y in (0, 1)] for z in (0, 1)]
    cx = jax.lax.optimization_barrier(cx)  # computed once: XLA would copy each product into every consumer
    cy = jax.lax.optimization_barrier([_lerp_linear(cx[z][0], cx[z][1], alpha[1], gd[1]) for z in (0, 1)])
    return jnp.stack(_lerp_linear(cy[0], cy[1], alpha[2], gd[2]), axis=-1)  # (C, 4)


MERGE_SEARCH_MIN = 32
"""Planes per axis from which `_merge_sorted` counts by binary search (`jnp.searchsorted`, O(n log n)) instead of
comparing every pair (O(n^2)). Measured (spot_fog geometry, 32 x 32 px, 16 spp, depth 8, 2 cores, one process per
variant, A B A B): a 64^3 grid renders 0.82x the time with the search, a 16^3 grid 1.3x with it."""


def _count_before(y, x, side: str):
    """For each value of `x`, how many values of the ascending `y` lie before it (`side` "right": `y <= x`, "left":
    `y < x`); the same counts either way, by whichever method is cheaper for `y`'s length."""
    if y.shape[0] >= MERGE_SEARCH_MIN:
        return jnp.searchsorted(y, x, side=side)
    return jnp.sum(y[None, :] <= x[:, None], axis=1) if side == "right" else jnp.sum(y[None, :] < x[:, None], axis=1)


def _merge_sorted(lists) -> Float[Array, " m"]:
    """The values of ascending 1-D arrays in one ascending array, without a sort: each value's position is its index
    in its own list plus the number of values before it in the others (ties to the earlier list; `_count_before`),
    then one scatter: no sort, and for grids below `MERGE_SEARCH_MIN` planes per axis no loop (a few vectorised
    comparisons per ray)."""
    ranks = []
    for i, x in enumerate(lists):
        r = jnp.arange(x.shape[0])
        for j, y in enumerate(lists):
            if j < i:
                r = r + _count_before(y, x, "right")
            elif j > i:
                r = r + _count_before(y, x, "left")
        ranks.append(r)
    values = jnp.concatenate(lists)
    return jnp.zeros_like(values).at[jnp.concatenate(ranks)].set(values, unique_indices=True)


def profile(flat, res, lo, hi, o, d) -> Profile:
    """The ray's profile through the box (module docstring): from the box's entry `max(t_in, 0)` to its exit, the
    crossings of every texel-centre plane (per axis already in order along the ray), merged (`_merge_sorted`);
    `nx + ny + nz + 1` intervals (static) cover every ray, the surplus ones have length 0."""
    n = jnp.array(res, jnp.float32)
    g0 = _grid_coords(o, lo, hi, n)
    gd = d * (n / (hi - lo))
    t_in, t_out = box_interval(lo, hi, o, d)
    hit = (t_out >= jnp.maximum(t_in, 0.0)) & jnp.isfinite(t_out)  # (t_out is finite for a unit d that hits)
    a = jnp.where(hit, jnp.maximum(t_in, 0.0), 0.0)
    b = jnp.where(hit, t_out, 0.0)  # a ray that misses the box (or lies behind it): every interval has length 0
    lists = [a[None], b[None]]
    for axis, count in enumerate(res):
        moving = gd[axis] != 0
        k = jnp.arange(count, dtype=jnp.float32)
        k = jnp.where(gd[axis] > 0, k, count - 1 - k)  # planes in the order the ray meets them
        t = (k - g0[axis]) / jnp.where(moving, gd[axis], 1.0)  # double where: an axis the ray runs along has none
        lists.insert(-1, jnp.clip(jnp.where(moving, t, b), a, b))
    t = jax.lax.optimization_barrier(_merge_sorted(lists))
    start, length = t[:-1], jnp.maximum(t[1:] - t[:-1], 0.0)
    coef = jax.vmap(lambda s0, ln: _cell_cubic(flat, res, g0, gd, s0, ln))(start, length)  # (m, C, 4)
    coef = jax.lax.optimization_barrier(coef)  # every later use reads the coefficients, none recomputes them
    depth = jnp.maximum(poly_integral(coef, length[:, None]), 0.0)  # (m, C)
    return Profile(*jax.lax.optimization_barrier((start, length, coef, jnp.cumsum(depth, axis=0) - depth)))


def _grid_profile(density, lo, hi, o, d) -> Profile:
    """`profile` of a `(nz, ny, nx, C)` density array."""
    nz, ny, nx, c = density.shape
    return profile(density.reshape(-1, c), (nx, ny, nz), lo, hi, o, d)


def optical_depth(pr: Profile, scale, t) -> Float[Array, " C"]:
    """`tau` over `[0, t]` along the profiled ray (t in [0, inf]), per channel: `scale` times the sum of each
    interval's integral up to `t` (exact)."""
    s = jnp.clip(t - pr.start, 0.0, pr.length)  # t = inf: the whole interval
    return scale * jnp.sum(jnp.maximum(poly_integral(pr.coef, s[:, None]), 0.0), axis=0)


def distance_at_depth(pr: Profile, scale, T, channel) -> Float[Array, ""]:
    """The distance at which channel `channel`'s optical depth `scale * integral D` reaches `T` (0 <= T <=
    tau(end); `channel` may be traced), not differentiated: the interval whose cumulative depths bracket `T`, then
    its quartic solved (`solve_quartic_depth`)."""
    pr, scale, T = jax.lax.stop_gradient((pr, scale, T))
    target = T / scale
    cum = pr.cum[:, channel]
    k = jnp.clip(jnp.sum(cum <= target) - 1, 0, cum.shape[0] - 1)
    return pr.start[k] + solve_quartic_depth(pr.coef[k, channel], pr.length[k], target - cum[k])


# ------------------------------------------------------------------------------------- majorant grid, ratio tracking
TRACKING = ("exact", "ratio")
"""`GridMedium.tracking`: "exact" (the profile above: exact depths, exact free-flight inversion) or "ratio" (free
flight against a coarse majorant grid, transmittance by residual ratio tracking; `docs/estimators.md`)."""

MAJORANT_CELLS = 8
"""Default cells per axis of the coarse majorant grid of `tracking = "ratio"` (at most the grid's own texels per
axis). A ray crosses at most `3 (cells - 1) + 1` majorant intervals (one read each); finer cells make the bounds
tighter (fewer ratio-tracking points, lower variance) at more intervals: measured in docs/results/grid.md."""


class CoarseProfile(NamedTuple):
    """A ray's path through the majorant grid: `start` (m,), `length` (m,) of its intervals (scene units; unused
    ones have length 0), the unscaled bounds `major` (m,) and `control` (m,) of `D` on each (over all channels:
    `control <= D <= major` everywhere in the interval), and the cumulative integrals `cum_major`, `cum_control` up
    to each interval's start."""

    start: Float[Array, " m"]
    length: Float[Array, " m"]
    major: Float[Array, " m"]
    control: Float[Array, " m"]
    cum_major: Float[Array, " m"]
    cum_control: Float[Array, " m"]


def _texel_ranges(n: int, cells: int) -> list[tuple[int, int]]:
    """For each of `cells` equal coarse cells along an axis of `n` texels: the texels `(first, last)` whose values
    the trilinear interpolation reads anywhere in that cell (the cell spans grid coordinates `[j n / cells - 1/2,
    (j + 1) n / cells - 1/2]`, and a point reads `floor(x)` and `floor(x) + 1`, clamped)."""
    out = []
    for j in range(cells):
        a = int(np.floor(j * n / cells - 0.5))
        b = int(np.floor((j + 1) * n / cells - 0.5)) + 1
        out.append((min(max(a, 0), n - 1), min(max(b, 0), n - 1)))
    return out


def block_bounds(density: Float[Array, "nz ny nx C"], cells: tuple[int, int, int]):
    """`(major, control)`, each `(cz, cy, cx)`: the largest and smallest value of the trilinear `D` (over all
    channels) anywhere in each coarse cell, as the max and min of the texels it reads (`_texel_ranges`; trilinear
    interpolation is a convex combination of them). Static slicing, separable over the axes; not differentiated."""
    d = jax.lax.stop_gradient(density)
    hi, lo = jnp.max(d, axis=-1), jnp.min(d, axis=-1)  # (nz, ny, nx)
    for axis, cnt in zip((2, 1, 0), cells):  # x, y, z
        n = hi.shape[axis]
        rng = _texel_ranges(n, cnt)
        hi = jnp.stack([jax.lax.slice_in_dim(hi, a, b + 1, axis=axis).max(axis=axis) for a, b in rng], axis=axis)
        lo = jnp.stack([jax.lax.slice_in_dim(lo, a, b + 1, axis=axis).min(axis=axis) for a, b in rng], axis=axis)
    return hi, lo


def coarse_profile(major, control, lo, hi, o, d) -> CoarseProfile:
    """The ray's `CoarseProfile` through the box: the crossings of the majorant cells' faces (per axis in order
    along the ray) merged with the entry and exit (`_merge_sorted`); each interval's bounds from its midpoint's
    cell."""
    cz, cy, cx = major.shape
    cells = (cx, cy, cz)
    f0 = (o - lo) / (hi - lo)
    fd = d / (hi - lo)
    t_in, t_out = box_interval(lo, hi, o, d)
    hit = (t_out >= jnp.maximum(t_in, 0.0)) & jnp.isfinite(t_out)
    a = jnp.where(hit, jnp.maximum(t_in, 0.0), 0.0)
    b = jnp.where(hit, t_out, 0.0)
    lists = [a[None], b[None]]
    for axis, count in enumerate(cells):
        if count == 1:
            continue
        moving = fd[axis] != 0
        k = jnp.arange(1, count, dtype=jnp.float32)
        k = jnp.where(fd[axis] > 0, k, count - k)  # faces in the order the ray meets them
        t = (k / count - f0[axis]) / jnp.where(moving, fd[axis], 1.0)
        lists.insert(-1, jnp.clip(jnp.where(moving, t, b), a, b))
    t = _merge_sorted(lists)
    start, length = t[:-1], jnp.maximum(t[1:] - t[:-1], 0.0)
    mid = f0[None, :] + (start + 0.5 * length)[:, None] * fd[None, :]  # (m, 3)
    idx = jnp.clip(jnp.floor(mid * jnp.array(cells, jnp.float32)[None, :]).astype(jnp.int32), 0,
                   jnp.array(cells, jnp.int32)[None, :] - 1)
    flat = (idx[:, 2] * cy + idx[:, 1]) * cx + idx[:, 0]
    maj, ctl = major.reshape(-1)[flat], control.reshape(-1)[flat]
    cm, cc = jnp.cumsum(maj * length), jnp.cumsum(ctl * length)
    return CoarseProfile(start, length, maj, ctl, cm - maj * length, cc - ctl * length)


def piecewise_depth(start, length, rate, t) -> Float[Array, ""]:
    """`integral_0^t` of a piecewise-constant rate (`rate` on `[start, start + length]`); `t` may be inf."""
    return jnp.sum(rate * jnp.clip(t - start, 0.0, length))


def piecewise_inverse(start, length, rate, cum, target) -> tuple[Float[Array, ""], Array]:
    """`(t, k)`: the distance at which `piecewise_depth` reaches `target` (0 <= target < the total) and its
    interval `k`, the last whose cumulative depth is <= target (so its rate is > 0 but for rounding; a rate of 0
    gives the interval's end)."""
    k = jnp.clip(jnp.sum(cum <= target) - 1, 0, cum.shape[0] - 1)
    r = rate[k]
    ok = r > 0
    t = start[k] + jnp.where(ok, jnp.clip((target - cum[k]) / jnp.where(ok, r, 1.0), 0.0, length[k]), length[k])
    return t, k


def piecewise_rate_at(start, length, rate, t) -> Float[Array, ""]:
    """The rate of the interval that holds `t` (0 outside all of them)."""
    inside = (t >= start) & (t < start + length)
    return jnp.sum(jnp.where(inside, rate, 0.0))


_GOLDEN = np.uint32(0x9E3779B9)
_LOOKUP_SALT = np.uint32(0x5BD1E995)  # the stream of the stochastic lookups' uniforms (beside the steps')
LOOKUP = ("stochastic", "trilinear")
RESIDUAL_MARGIN = 2.0 ** -6
"""How far above the majorant grid's bound (relative) ratio tracking's residual rate reaches: every factor is then at
least about `RESIDUAL_MARGIN` (never 0) where `scale` is the sampling scale. A one-texel lookup reaches the bound
whenever it draws a cell's largest texel, and a factor of exactly 0 makes a path's throughput 0: path replay
(`_unbounded.py`), which divides the future radiance by the throughput, then loses that vertex's derivative (found
by `tests/test_grid.py::test_reverse_mode_over_every_voxel_replays_the_paths_and_equals_forward_mode`: the largest
voxel's reverse-mode derivative 0.0074 against forward mode's 0.0052). Costs 1.6% more tracking points."""
TRACKING_BATCH = 4
"""Ratio-tracking points per pass of its loop. Under `vmap` every pass costs all lanes until the longest is done;
four a pass took 0.71x the time of one (patchy 16^3 grid, 32 x 32 px, depth 8, majorant_cells 1; the same
numbers drawn), eight no less than four."""


def ray_seed(o, d) -> Array:
    """A uint32 seed from the bits of a ray's origin and direction (both carry the path's randomness: the camera
    ray's jittered pixel, every later vertex and direction), so each ray draws its own ratio-tracking points and a
    ray that does not move draws the same ones (a fixed key gives a smooth image in the voxel values)."""
    from ._random import mix

    bits = jax.lax.bitcast_convert_type(jax.lax.stop_gradient(jnp.concatenate([o, d])).astype(jnp.float32),
                                        jnp.uint32)
    h = jnp.uint32(0x243F6A88)
    for i in range(6):
        h = mix(h ^ bits[i]) + _GOLDEN
    return h


def seeded_uniform(seed, i) -> Float[Array, ""]:
    """The `i`-th uniform in [0, 1) (multiples of 2^-24) of the stream `seed` (`_random.mix` of both)."""
    from ._random import mix

    x = mix(mix(seed + jnp.asarray(i, jnp.uint32) * _GOLDEN) ^ jnp.uint32(0x85EBCA6B))
    return (x >> 8).astype(jnp.float32) * jnp.float32(2.0 ** -24)


def ratio_tracking(cp: CoarseProfile, scale_hat, scale, sigma_at, t_end, seed) -> Float[Array, " C"]:
    """Residual ratio tracking (Novak et al. 2014) of the transmittance over `[0, t_end]`, per channel, unbiased:
    `exp(-scale tau_control) prod_i (1 - (sigma(x_i) - scale c_i) / rho_i)` over the points `x_i` of a Poisson
    process of rate `rho = scale_hat (major - control)` (no derivative), drawn by exponential steps in its depth.

    `sigma_at(t, u)` (C,) is the medium's extinction at distance `t`, or an unbiased estimate of it from the point's
    own uniform `u` (a one-texel lookup; differentiable: the voxel and scale derivatives come from the factors);
    the control's depth carries `scale`'s derivative with zero variance. Each factor is in [0, 1] while `scale =
    scale_hat`. Returns `(tau_control (C,) or scalar, product (C,))`: the transmittance is
    `exp(-tau_control) * product`, kept apart so that callers divide by a pdf without underflow.

    Derivatives: the points do not move with the parameters, so `d prod = sum_i (prod_{j != i} f_j) d f_i`. Forward
    mode differentiates the `lax.while_loop`; reverse mode, which JAX has not for such a loop, is traced only in
    path replay (`_medium.path_replay`), where `_replayed_product` draws the same points again and pulls the
    cotangent through each factor: memory independent of the number of points, but one cotangent of the grid's
    size per lane of the replay (docs/results/grid.md, "Reverse mode and memory"). Elsewhere reverse mode raises
    `RATIO_REVERSE_MESSAGE`."""
    rho = scale_hat * (cp.major - cp.control)
    cum = scale_hat * (cp.cum_major - cp.cum_control)
    r_end = piecewise_depth(cp.start, cp.length, rho, t_end)
    tau_c = scale * piecewise_depth(cp.start, cp.length, cp.control, t_end)
    sg = jax.lax.stop_gradient
    control = sg(cp.control)
    geo = tuple(sg(x) for x in (cp.start, cp.length, rho, cum, r_end)) + (seed,)
    scale = jnp.asarray(scale, jnp.float32)
    ex_fn, consts = jax.closure_convert(lambda t, k, s, u: sigma_at(t, u) - s * control[k], jnp.float32(0.0),
                                        jnp.int32(0), scale, jnp.float32(0.0))
    if replaying():  # reverse mode's trace (`_medium.path_replay`): the loop with its own replay
        return tau_c, _replayed_product(ex_fn, geo, scale, *consts)
    c = jax.eval_shape(sigma_at, jnp.float32(0.0), jnp.float32(0.0)).shape[0]
    prod = _replay_loop(ex_fn, geo, scale, consts, lambda acc, fn: acc * jnp.prod(fn(scale, *consts), axis=0),
                        jnp.ones((c,), jnp.float32))
    return tau_c, eqxi.nondifferentiable_backward(prod, msg=RATIO_REVERSE_MESSAGE)


RATIO_REVERSE_MESSAGE = (
    'reverse mode (jax.grad, jax.vjp) through a grid with tracking="ratio" needs paths of any length '
    '(integrator max_depth = -1), whose path replay draws the ratio-tracking points again; with a fixed max_depth '
    'use forward mode (jax.jvp, jax.jacfwd) or tracking="exact"')


def _track_pass(ex_fn, geo, r, i):
    """One pass of `ratio_tracking`'s loop from residual depth `r` (its `i`-th exponential step on): `(the next
    depth, the function (scale, *consts) -> factors (P, C) of its TRACKING_BATCH points)`, as the loop draws them."""
    start, length, rho, cum, r_end, seed = geo
    steps = jax.vmap(lambda j: -jnp.log1p(-seeded_uniform(seed, j)))(
        i + jnp.arange(1, TRACKING_BATCH + 1, dtype=jnp.uint32))
    rs = r + jnp.concatenate([jnp.zeros((1,), jnp.float32), jnp.cumsum(steps)])
    us = jax.vmap(lambda j: seeded_uniform(seed ^ _LOOKUP_SALT, j))(  # each point's lookup uniform
        i + jnp.arange(TRACKING_BATCH, dtype=jnp.uint32))

    def factors(s, *c):
        def one(rr, uu):
            t, k = piecewise_inverse(start, length, rho, cum, rr)
            rk = rho[k]
            ok = (rk > 0) & (rr < r_end)
            return jnp.where(ok, 1.0 - ex_fn(t, k, s, uu, *c) / jnp.where(ok, rk, 1.0), 1.0)

        return jax.vmap(one)(rs[:-1], us)

    return rs[-1], factors


def _replay_loop(ex_fn, geo, scale, consts, body, init):
    """Run `acc = body(acc, factors_fn)` over `ratio_tracking`'s passes (the same points as its loop)."""
    seed = geo[5]

    def step(carry):
        r, i, acc = carry
        r_next, fn = _track_pass(ex_fn, geo, r, i)
        return r_next, i + TRACKING_BATCH, body(acc, fn)

    r0 = -jnp.log1p(-seeded_uniform(seed, jnp.uint32(0)))
    return jax.lax.while_loop(lambda carry: carry[0] < geo[4], step, (r0, jnp.uint32(0), init))[2]


def _product_and_zeros(ex_fn, geo, scale, consts):
    """Per channel: the product of the nonzero factors and the number of zero ones."""
    c = jax.eval_shape(lambda: ex_fn(jnp.float32(0.0), jnp.int32(0), scale, jnp.float32(0.0), *consts)).shape[0]

    def body(acc, fn):
        f = fn(scale, *consts)
        zero = f == 0.0
        return acc[0] * jnp.prod(jnp.where(zero, 1.0, f), axis=0), acc[1] + jnp.sum(zero, axis=0, dtype=jnp.int32)

    return _replay_loop(ex_fn, geo, scale, consts, body, (jnp.ones((c,), jnp.float32), jnp.zeros((c,), jnp.int32)))


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _replayed_product(ex_fn, geo, scale, *consts):
    """`ratio_tracking`'s product, for reverse mode: its loop forward, and backward the same points drawn again
    (`_replayed_product_bwd`), with memory independent of their number."""
    prod, zeros = _product_and_zeros(ex_fn, geo, scale, consts)
    return jnp.where(zeros > 0, 0.0, prod)


def _replayed_product_fwd(ex_fn, geo, scale, *consts):
    prod, zeros = _product_and_zeros(ex_fn, geo, scale, consts)
    return jnp.where(zeros > 0, 0.0, prod), (geo, scale, consts, prod, zeros)


def _replayed_product_bwd(ex_fn, res, ct):
    """`d prod = sum_i (prod_{j != i} f_j) d f_i`; the others' product is `prod / f_i` where no factor is 0, the
    nonzero factors' product for the one zero factor, and 0 beside two zeros (per channel)."""
    geo, scale, consts, prod, zeros = res

    def body(g, fn):
        f, pull = jax.vjp(fn, scale, *consts)
        zero = f == 0.0
        p, z = prod[None, :], zeros[None, :]
        others = jnp.where(z == 0, p / jnp.where(zero, 1.0, f), jnp.where((z == 1) & zero, p, 0.0))
        return jax.tree.map(jnp.add, g, pull(ct[None, :] * others))

    g = _replay_loop(ex_fn, geo, scale, consts, body, jax.tree.map(jnp.zeros_like, (scale, *consts)))
    no_ct = tuple(np.zeros(np.shape(x), jax.dtypes.float0) if not jnp.issubdtype(jnp.result_type(x), jnp.floating)
                  else jnp.zeros_like(x) for x in geo)
    return (no_ct, *g)


_replayed_product.defvjp(_replayed_product_fwd, _replayed_product_bwd)


# -------------------------------------------------------------------------------------------------- the medium
class GridMedium(AbstractMedium):
    """Fog whose extinction is a voxel grid in a box (`"type": "grid"` in scene files; module docstring).

    **Fields:**
    - `density`: float32 `(nz, ny, nx, C)`, `C` = 1 (grey extinction) or 3 (RGB), values >= 0 at the texel centres
      (x fastest in memory, as Mitsuba's `.vol`); a 3-D array is taken as one channel. Any size >= 1 per axis, at
      most 2^31 values. Static structure: its shape (a new shape compiles a new program; new values do not).
    - `scale`: the extinction is `scale * D`, 1/scene unit per grid unit, >= 0 (the global density factor a fit
      recovers beside the voxels).
    - `albedo`: single-scattering albedo, RGB in [0, 1].
    - `phase`: the phase function.
    - `bounds`: `(box_min, box_max)` in scene units, required: the grid's box (outside it there is no fog).
    - `extent`: static; as `HomogeneousMedium` (rays leave the box long before it).
    - `tracking`: static, "exact" (default: exact optical depths along each ray's profile; zero-variance
      transmittance, every derivative mode) or "ratio" (free flight against a coarse majorant grid and residual
      ratio tracking: cost per segment independent of the grid's resolution, unbiased, some variance; forward-mode
      derivatives only, and no "reparam" estimator). `docs/results/grid.md` measures both.
    - `majorant_cells`: static, cells per axis of the majorant grid of "ratio" (default `MAJORANT_CELLS`, at most
      the grid's texels on each axis), an integer >= 1.
    - `lookup`: static, how "ratio" reads the grid at its tracking points: "stochastic" (default: one texel of the
      trilinear cell drawn with the trilinear weights, `stochastic_trilinear`; unbiased, as every factor is linear
      in the density, and 0.63-0.68x the time of "trilinear" at the same variance per sample, docs/results/grid.md)
      or "trilinear" (the 8 texels interpolated). Free-flight vertices and "exact" always interpolate.
    """

    density: Float[Array, "nz ny nx C"]
    scale: Float[Array, ""] = eqx.field(converter=scalar)
    albedo: Float[Array, "3"] = eqx.field(converter=rgb)
    phase: AbstractPhaseFunction
    bounds: tuple[Float[Array, "3"], Float[Array, "3"]]
    extent: float = eqx.field(static=True, default=1000.0)
    tracking: str = eqx.field(static=True, default="exact")
    majorant_cells: int = eqx.field(static=True, default=MAJORANT_CELLS)
    lookup: str = eqx.field(static=True, default="stochastic")

    def __init__(self, density, scale, albedo, phase, bounds, extent=1000.0, tracking="exact",
                 majorant_cells=MAJORANT_CELLS, lookup="stochastic"):
        density = jnp.asarray(density, jnp.float32)
        if density.ndim == 3:
            density = density[..., None]
        if density.ndim != 4 or density.shape[-1] not in (1, 3) or min(density.shape[:3]) < 1:
            raise ValueError(f"GridMedium.density must have shape (nz, ny, nx) or (nz, ny, nx, C) with C = 1 or 3 "
                             f"and every size >= 1, got {tuple(density.shape)}")
        if int(np.prod(density.shape)) > MAX_VOXELS:
            raise ValueError(f"GridMedium.density holds {int(np.prod(density.shape))} values; at most {MAX_VOXELS}")
        self.density = density
        self.scale = scale
        self.albedo = albedo
        self.phase = phase
        self.bounds = check_bounds("GridMedium", bounds)
        self.extent = extent
        if tracking not in TRACKING:
            raise ValueError(f"GridMedium.tracking must be one of {TRACKING}, got {tracking!r}")
        self.tracking = tracking
        if isinstance(majorant_cells, bool) or not isinstance(majorant_cells, (int, np.integer)) or majorant_cells < 1:
            raise ValueError(f"GridMedium.majorant_cells must be an integer >= 1, got {majorant_cells!r}")
        self.majorant_cells = int(majorant_cells)
        if lookup not in LOOKUP:
            raise ValueError(f"GridMedium.lookup must be one of {LOOKUP}, got {lookup!r}")
        self.lookup = lookup

    def __check_init__(self):
        v = concrete(self.density)
        if v is not None:
            bad = ~np.isfinite(v) | (v < 0)
            if bad.any():
                first = tuple(int(i) for i in np.argwhere(bad)[0])
                raise ValueError(f"GridMedium.density must be finite and >= 0: {int(bad.sum())} values are not, the "
                                 f"first at (z, y, x, c) = {first}: {float(v[first])!r}")
        check_range("GridMedium", "scale", self.scale, NON_NEGATIVE)
        check_range("GridMedium", "albedo", self.albedo, UNIT)
        check_phase_and_extent("GridMedium", self.phase, self.extent)

    # ---------------------------------------------------------------------------------------------- structure
    @property
    def resolution(self) -> tuple[int, int, int]:
        """`(nx, ny, nz)`, static."""
        nz, ny, nx, _ = self.density.shape
        return nx, ny, nz

    @property
    def channels(self) -> int:
        """1 (grey) or 3 (RGB), static."""
        return self.density.shape[-1]

    @property
    def g(self) -> Float[Array, ""]:
        """The Henyey–Greenstein `g` of the phase function (AttributeError for other phase functions)."""
        if not isinstance(self.phase, HenyeyGreenstein):
            raise AttributeError(f"the medium's phase function is {type(self.phase).__name__}, which has no g")
        return self.phase.g

    def _flat(self):
        return self.density.reshape(-1, self.channels)

    def _sampling_scale(self):
        return jnp.maximum(self.scale, SCALE_HAT_MIN)

    def profile(self, o, d) -> Profile:
        """The ray's `Profile` through this grid, built once per ray where the tracer shares its per-ray values
        (`_medium.shared_ray_values`; the same grid and ray objects)."""
        return shared(_grid_profile, self.density, self.bounds[0], self.bounds[1], o, d)

    def density_at(self, p) -> Float[Array, " C"]:
        """`D(p)` (unscaled), per channel; 0 outside the box."""
        lo, hi = self.bounds
        x = _grid_coords(p, lo, hi, jnp.array(self.resolution, jnp.float32))
        return jnp.where(inside_box(lo, hi, p), trilinear(self._flat(), self.resolution, x), 0.0)

    def extinction(self, p) -> Float[Array, "3"]:
        """`sigma_t(p) = scale D(p)`, RGB, 1/scene unit."""
        return jnp.broadcast_to(self.scale * self.density_at(p), (3,))

    def scattering(self, p):
        return self.albedo * self.extinction(p)

    def fog_interval(self, o, d, s):
        t0, t1 = box_interval(self.bounds[0], self.bounds[1], o, d)
        return jnp.clip(t0, 0.0, s), jnp.clip(t1, 0.0, s)

    def supports_estimator(self, estimator: str) -> bool:
        # "ratio": the majorant's distances never move with the values, and the ratio-tracking points would move
        # with a reparameterised direction without their density's change: no pathwise estimator
        return estimator != "reparam" or self.tracking == "exact"

    # ------------------------------------------------------------------------------- "ratio": majorant grid
    @property
    def majorant_resolution(self) -> tuple[int, int, int]:
        """Cells per axis `(cx, cy, cz)` of the majorant grid (static)."""
        return tuple(min(self.majorant_cells, n) for n in self.resolution)

    def coarse(self, o, d) -> CoarseProfile:
        """The ray's `CoarseProfile` through this grid's majorant grid (no derivative), once per ray and medium
        where the tracer shares per-ray values."""
        return shared(_medium_coarse_profile, self, o, d)

    def _ratio_transmittance(self, o, d, t):
        """`(tau_control, product)` of `ratio_tracking` over `[0, t]` (per channel; t may be inf), its bounds'
        upper one raised by `RESIDUAL_MARGIN` (so no factor is 0)."""
        cp = self.coarse(o, d)
        cp = cp._replace(major=cp.major * (1.0 + RESIDUAL_MARGIN), cum_major=cp.cum_major * (1.0 + RESIDUAL_MARGIN))
        scale_hat = jax.lax.stop_gradient(self._sampling_scale())
        if self.lookup == "stochastic":
            lo, hi = self.bounds
            n = jnp.array(self.resolution, jnp.float32)

            def sigma_at(tt, uu):
                return self.scale * stochastic_trilinear(self._flat(), self.resolution,
                                                         _grid_coords(o + tt * d, lo, hi, n), uu)
        else:
            def sigma_at(tt, uu):
                return self.scale * self.density_at(o + tt * d)
        return ratio_tracking(cp, scale_hat, self.scale, sigma_at, t, ray_seed(o, d))

    def _majorant_branch(self, o, d, s, q_max):
        """The sampler's `(coarse profile, scale_hat, tau_major(s), m = 1 - e^-tau, q, log(1 - q))`."""
        cp = self.coarse(o, d)
        sh = jax.lax.stop_gradient(self._sampling_scale())
        tau_s = sh * piecewise_depth(cp.start, cp.length, cp.major, s)
        m = -jnp.expm1(-tau_s)
        q = jnp.where(tau_s > 0, jnp.clip(m, Q_MIN, q_max), 0.0)
        exact = (m >= Q_MIN) & (m <= q_max)
        return cp, sh, tau_s, m, q, jnp.where(exact, -tau_s, jnp.log1p(-q))

    def _majorant_log_density(self, o, d, s, t):
        """`(log(mu(t) e^-tau_mu(t) / m), mu(t), tau_mu(t), m, q_c)`: the majorant's truncated free-flight density
        at `t` (1/scene unit; -inf where it is 0)."""
        cp, sh, _, m, q, _ = self._majorant_branch(o, d, s, 1.0)
        mu = sh * piecewise_rate_at(cp.start, cp.length, cp.major, t)
        tau_t = sh * piecewise_depth(cp.start, cp.length, cp.major, t)
        ok = (mu > 0) & (m > 0)
        log_p = jnp.where(ok, jnp.log(jnp.where(ok, mu, 1.0)) - tau_t - jnp.log(jnp.where(ok, m, 1.0)), -jnp.inf)
        return log_p, mu, tau_t, m, q

    def optical_depth(self, o, d, t) -> Float[Array, " C"]:
        """`tau` over `[0, t]` per channel (t may be inf)."""
        return optical_depth(self.profile(o, d), self.scale, t)

    # ---------------------------------------------------------------------------------------------- free flight
    def _branches(self, o, d, s, q_max):
        """The sampler's per-channel branch probabilities: `(pr, tau_hat(s), q_c, log(1 - q_c))`, no derivative in
        the q's; a channel without fog on the segment has `q_c = 0`."""
        sh = self._sampling_scale()
        pr = self.profile(o, d)
        tau_s = optical_depth(pr, sh, s)
        m = -jnp.expm1(-jax.lax.stop_gradient(tau_s))
        some = tau_s > 0
        q = jnp.where(some, jnp.clip(m, Q_MIN, q_max), 0.0)
        exact = (m >= Q_MIN) & (m <= q_max)
        log1mq = jnp.where(exact, -jax.lax.stop_gradient(tau_s), jnp.log1p(-q))
        return pr, tau_s, q, log1mq

    def sample_free_flight(self, o, d, s, ends_on_surface, active, u, u_channel) -> FlightSample:
        q_max = jnp.where(ends_on_surface, Q_MAX_SURFACE, 1.0)
        if self.tracking == "ratio":
            return self._majorant_free_flight(o, d, s, q_max, active, u)
        pr, tau_s, q_c, log1mq_c = self._branches(o, d, s, q_max)
        q = jnp.mean(q_c)
        log1mq = jnp.log(jnp.mean(jnp.exp(log1mq_c)))
        q = jnp.where(active, q, 0.0)
        scattered = active & (u < q)
        # the channel in proportion to q_c (one channel: always it); then its distance, exactly inverted
        share = jnp.cumsum(q_c) / jnp.where(q > 0, jnp.sum(q_c), 1.0)
        c = jnp.minimum(jnp.sum(share <= u_channel), self.channels - 1)
        x = jnp.where(scattered, jnp.minimum(u / jnp.where(scattered, q, 1.0), 0.99999994), 0.0)
        tau_c = tau_s[c]
        T = -jnp.log1p(-x * -jnp.expm1(-tau_c))  # the depth to reach: differentiable (reparam)
        sh = self._sampling_scale()
        t0 = distance_at_depth(pr, sh, T, c)
        # implicit function theorem: tau_c(t) = T moves t by (dT - d tau_c(t)) / sigma_c(t); zero for a detached sampler
        tau_t = optical_depth(pr, sh, t0)[c]
        sig = jax.lax.stop_gradient(sh * self.density_at(o + t0 * d)[c])
        ok = sig > 0
        dt = ((T - jax.lax.stop_gradient(T)) - (tau_t - jax.lax.stop_gradient(tau_t))) / jnp.where(ok, sig, 1.0)
        t = t0 + jnp.where(ok & scattered, dt, 0.0)
        # a segment through the box's empty part: the surface is reached with weight exactly its transmittance (1)
        log1mq = jnp.where(active & (q > 0), log1mq, 0.0)
        return FlightSample(jnp.clip(t, 0.0, s), scattered, q, log1mq)

    def _majorant_free_flight(self, o, d, s, q_max, active, u) -> FlightSample:
        """Free flight from the majorant grid's piecewise-constant density (exact, no derivative)."""
        cp, sh, _, m, q, log1mq = self._majorant_branch(o, d, s, q_max)
        q = jnp.where(active, q, 0.0)
        scattered = active & (u < q)
        x = jnp.where(scattered, jnp.minimum(u / jnp.where(scattered, q, 1.0), 0.99999994), 0.0)
        depth = -jnp.log1p(-x * m) / sh
        t, _ = piecewise_inverse(cp.start, cp.length, cp.major, cp.cum_major, depth)
        log1mq = jnp.where(active & (q > 0), log1mq, 0.0)
        return FlightSample(jnp.clip(t, 0.0, s), scattered, q, log1mq)

    def _log_vertex_densities(self, o, d, s, t):
        """Per channel: `log(sigma_hat_c(t) e^-tau_hat_c(t) / m_c)` (the truncated free-flight density, 1/scene unit,
        -inf where it is 0) and the branch probabilities, from the sampler's values."""
        pr, tau_s, q_c, _ = self._branches(o, d, s, 1.0)
        sh = self._sampling_scale()
        sig = sh * self.density_at(o + t * d)
        tau_t = optical_depth(pr, sh, t)
        m = -jnp.expm1(-tau_s)
        ok = (sig > 0) & (m > 0)
        log_p = jnp.where(ok, jnp.log(jnp.where(ok, sig, 1.0)) - tau_t - jnp.log(jnp.where(ok, m, 1.0)), -jnp.inf)
        return log_p, sig, tau_t, m, q_c

    def free_flight_pdf(self, o, d, s, q, t):
        """`mean_c q_c p_c(t)` scaled to the branch probability `q` the caller passes (`q / mean_c q_c` is 1 for the
        sampled branch, and the equiangular mixture passes 1 for the distance density alone)."""
        if self.tracking == "ratio":
            log_p = self._majorant_log_density(o, d, s, t)[0]
            return jnp.where(log_p > -jnp.inf, q * jnp.exp(jnp.minimum(log_p, 80.0)), 0.0)
        log_p, _, _, _, q_c = self._log_vertex_densities(o, d, s, t)
        qm = jnp.mean(q_c)
        w = q_c / jnp.where(qm > 0, qm, 1.0)
        return q * jnp.mean(jnp.where(log_p > -jnp.inf, w * jnp.exp(jnp.minimum(log_p, 80.0)), 0.0))

    def collision_weight(self, sampler, o, d, s, q, t):
        """`sigma_s(t) T(t) / sampler.free_flight_pdf(t)`, RGB; for a grey grid as the ratio `albedo (sigma /
        sigma_hat) e^-(tau - tau_hat) m / q`, which never underflows."""
        sigma = self.scale * self.density_at(o + t * d)
        if self.tracking == "ratio":
            return self._ratio_collision_weight(sampler, o, d, s, q, t, sigma)
        tau = self.optical_depth(o, d, t)
        if self.channels == 1 and sampler.channels == 1:
            _, sig_h, tau_h, m, _ = sampler._log_vertex_densities(o, d, s, t)
            ok = sig_h > 0
            ratio = jnp.where(ok, sigma / jnp.where(ok, sig_h, 1.0), 0.0)
            w = ratio * jnp.exp(jnp.minimum(-(tau - tau_h), 80.0)) * (m / q)
            return self.albedo * w[0]
        pdf = sampler.free_flight_pdf(o, d, s, q, t)
        val = jnp.broadcast_to(sigma * jnp.exp(-tau), (3,))
        ok = pdf > 0
        return self.albedo * jnp.where(ok, val / jnp.where(ok, pdf, 1.0), 0.0)

    def _ratio_collision_weight(self, sampler, o, d, s, q, t, sigma):
        """`sigma_s(t) T_hat(t) / p(t)` with the ratio-tracked transmittance; against a majorant sampler as
        `albedo (sigma / mu) e^(tau_mu - tau_control) prod m / q`, which never underflows."""
        tau_c, prod = self._ratio_transmittance(o, d, t)
        if sampler.tracking == "ratio":  # a sampler is a grid like the medium (`_integrator.sampling_medium`)
            log_p, mu, tau_mu, m, _ = sampler._majorant_log_density(o, d, s, t)
            ok = (mu > 0) & (q > 0)
            ratio = jnp.where(ok, sigma / jnp.where(ok, mu, 1.0), 0.0)
            w = ratio * jnp.exp(jnp.minimum(tau_mu - tau_c, 80.0)) * prod * jnp.where(ok, m / jnp.where(ok, q, 1.0),
                                                                                         0.0)
            return self.albedo * jnp.broadcast_to(w, (3,))
        pdf = sampler.free_flight_pdf(o, d, s, q, t)
        val = jnp.broadcast_to(sigma * jnp.exp(-tau_c) * prod, (3,))
        ok = pdf > 0
        return self.albedo * jnp.where(ok, val / jnp.where(ok, pdf, 1.0), 0.0)

    def surface_weight(self, o, d, s, log_one_minus_q):
        if self.tracking == "ratio":
            tau_c, prod = self._ratio_transmittance(o, d, s)
            return jnp.broadcast_to(jnp.exp(jnp.minimum(-tau_c - log_one_minus_q, 80.0)) * prod, (3,))
        tau = jnp.broadcast_to(self.optical_depth(o, d, s), (3,))
        return jnp.exp(jnp.minimum(-tau - log_one_minus_q, 80.0))

    def transmittance(self, o, d, t):
        if self.tracking == "ratio":
            tau_c, prod = self._ratio_transmittance(o, d, t)
            return jnp.broadcast_to(jnp.exp(-tau_c) * prod, (3,))
        return jnp.broadcast_to(jnp.exp(-self.optical_depth(o, d, t)), (3,))


def _medium_coarse_profile(medium: GridMedium, o, d) -> CoarseProfile:
    """`coarse_profile` of a grid medium's majorant grid (`block_bounds`)."""
    major, control = block_bounds(medium.density, medium.majorant_resolution)
    return coarse_profile(major, control, medium.bounds[0], medium.bounds[1], jax.lax.stop_gradient(o),
                          jax.lax.stop_gradient(d))
