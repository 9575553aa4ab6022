"""The fit's problem: target views at the fit resolution and the renders the solver asks for.

A `View` is one target image with its scene, both brought to the fit resolution (the target box-pooled by an integer
factor `f`). `Problem` turns the unconstrained parameters `y` (`fitting.params`) into renders of every view, in the
*scaled units* the solver works in: each view's pixels divided by the mean of its target (so views of different
brightness count alike) and the whole residual vector by `sqrt(n)` (n: pixel values of all views together).

Three kinds of render, each one compiled program however often it is called:
- `scan`: plain renders of many candidate parameter vectors at once (`jax.vmap` over the candidates), for the global
  search;
- `pass_`: one forward-mode pass at `y` (value, per-pixel variance and Jacobian from the same samples), with the
  "proposal" estimator whose reference medium is the medium at `y` (docs/estimators.md: for a fixed key the image is
  then a smooth function of the parameters, and the Jacobian is that of an unbiased estimate);
- `images`: renders at one `y` (figures, checks).
"""

from __future__ import annotations

import math
import warnings
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxfog

from jaxfog.tools import StoredProgram

from .params import FitError, apply, from_unconstrained, gains, jacobian_to_params, to_unconstrained


class View(NamedTuple):
    """One target image of the medium: the scene and the target at the fit resolution, and what is known of the
    target's noise.

    `target_spp`: samples per pixel of a jaxfog target (its header), else None; `target_var`: per-pixel variance of the
    pooled target estimated from the full-resolution target itself (`block_noise`, at least a photograph's
    quantisation floor); `downscale`: the pooling factor; `valid`: bool `(h, w)`, the pixels that are fitted (None:
    all; a pooled pixel is valid where all its source pixels are)."""

    scene: jaxfog.Scene
    target: np.ndarray
    name: str
    target_spp: int | None = None
    target_var: np.ndarray | None = None
    downscale: int = 1
    valid: np.ndarray | None = None
    light_pixels: int = 0
    """Source pixels not fitted because they hold a point-like light's image (`light_pixels`)."""
    fireflies: tuple = ()
    """`(x, y)` of the source pixels left out as fireflies (`fireflies`): set in `without_fireflies` only."""
    firefly_share: float = 0.0
    """The share of the view's light (the channels' sum over its fitted source pixels) in those fireflies."""
    fine_weight: np.ndarray | None = None
    """Float `(H, W)` at the target's resolution, 0 on those source pixels and 1 elsewhere (None: none): a pooled
    pixel is the mean of its other source pixels, in the target and in every pass rendered at the target's
    resolution (`Problem._render`)."""
    noise_from_image: bool = False
    """True where `target_var` is the block estimate of the target alone (no header spp, no camera model): the
    estimate's covariance then re-estimates it from the residual (`Problem.target_variance`)."""
    target_var_floor: np.ndarray | None = None
    """The part of `target_var` that no image estimate can see (a photograph's quantisation), pooled; or None."""
    tail_pixels: int = 0
    """Source pixels of a target whose noise comes from its own pixels that lie in its noise's heavy tail
    (`tail_spread`)."""
    tail_spread: float = 0.0
    """The uncertainty of the view's brightness (relative) that the tail leaves (`tail_spread`); 0 where none."""
    tail_deficit: float = 0.0
    """By how much the typical draw of such a target falls short of its expectation (relative; `tail_spread`): the
    view's target is raised by it."""
    without_fireflies: "View | None" = None
    """The same view with its firefly pixels left out (`fireflies`), for a target whose noise is estimated from the
    image and that has any; else None. The fit turns to it only where the model check refuses the targets as they are
    (`fitting.solver.fit_views`)."""


def pool(img: np.ndarray, f: int) -> np.ndarray:
    """Box-downsample `(H, W, C)` by an integer factor (exact: a pixel is the mean of its f x f square); numpy or
    traced JAX arrays."""
    if f == 1:
        return img
    H, W, C = img.shape
    return img.reshape(H // f, f, W // f, f, C).mean(axis=(1, 3))


def second_difference_variance(img: np.ndarray) -> np.ndarray:
    """Per pixel of `img` `(H, W, C)`, the noise variance estimated from its second differences: for independent
    noise of variance v, `x[i-1] - 2 x[i] + x[i+1]` has variance 6 v and cancels a linear trend; its square / 6,
    averaged over the directions the pixel has both neighbours in (NaN where it has none). Image curvature (edges)
    adds to it."""
    x = np.asarray(img, np.float64)
    v = np.zeros_like(x)
    cnt = np.zeros_like(x)
    if x.shape[1] >= 3:
        v[:, 1:-1] += (x[:, 2:] - 2 * x[:, 1:-1] + x[:, :-2]) ** 2 / 6.0
        cnt[:, 1:-1] += 1
    if x.shape[0] >= 3:
        v[1:-1] += (x[2:] - 2 * x[1:-1] + x[:-2]) ** 2 / 6.0
        cnt[1:-1] += 1
    return np.where(cnt > 0, v / np.maximum(cnt, 1), np.nan)


def block_noise(img: np.ndarray, f: int, w: np.ndarray | None = None) -> np.ndarray:
    """Per-pixel noise variance of `pool(img, f)` (or of `masked_pool(img, w, f)`), estimated from `img` alone:
    `second_difference_variance` averaged over each f x f block (a pixel without one: the image's mean), and the
    pooled pixel has v / f^2 (v / k^2 over its k source pixels of weight 1). The estimate errs toward more noise at
    edges."""
    v = second_difference_variance(img)
    fill = np.nanmean(v) if np.any(np.isfinite(v)) else 0.0
    v = np.where(np.isfinite(v), v, fill)
    return pool(v, f) / (f * f) if w is None else masked_pool(v, w, f, variance=True)


RESIDUAL_NOISE_RADIUS = 2
"""`residual_noise` averages each pixel's estimate over the (2 r + 1)^2 = 25 pixels around it. One pixel's
second-difference estimate has about 2 degrees of freedom, and the covariance reads its square root, which an
estimate of k degrees of freedom biases low by about 1 / (4 k): ~1% over 25 pixels (neighbours share differences,
so fewer than 50 independent ones) against ~12% for one pixel; the noise level varies over the scale of a beam's
width (8-20 px in the fit's views), which radius 2 keeps."""


def residual_noise(r: np.ndarray, var_render: np.ndarray, radius: int = RESIDUAL_NOISE_RADIUS) -> np.ndarray:
    """Per-pixel noise variance of a target (`(h, w, C)`) from the residual `r` = render - target at the fit's
    estimate: the second differences of `r` (`second_difference_variance`) estimate the target's variance plus the
    render's (`var_render`, known from its own samples, subtracted), with the image's structure cancelled where the
    render follows the target (edges of an emitter, a beam or a shadow are in both), unlike those of the target
    alone (`block_noise`), which count curvature as noise. Averaged over `radius` (NaN-valued pixels, a masked
    pixel, are left out), at least 0; a pixel without any estimate gets the image's mean."""
    v = box_mean(second_difference_variance(r) - np.asarray(var_render, np.float64), radius)
    fill = max(float(np.nanmean(v)), 0.0) if np.any(np.isfinite(v)) else 0.0
    return np.maximum(np.where(np.isfinite(v), v, fill), 0.0)


def box_mean(img: np.ndarray, r: int) -> np.ndarray:
    """Mean of `img` (`(H, W, C)`) over the `(2r+1) x (2r+1)` pixels around each pixel, per channel; at the border
    over the pixels that exist. A non-finite value stays as it is and out of its neighbours' means."""
    x = np.asarray(img, np.float64)
    if r <= 0:
        return x
    H, W = x.shape[:2]
    ok = np.isfinite(x)
    val = np.where(ok, x, 0.0)
    tot = np.zeros_like(val)
    cnt = np.zeros_like(val)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            ys, yd = slice(max(dy, 0), H + min(dy, 0)), slice(max(-dy, 0), H + min(-dy, 0))
            xs, xd = slice(max(dx, 0), W + min(dx, 0)), slice(max(-dx, 0), W + min(-dx, 0))
            tot[yd, xd] += val[ys, xs]
            cnt[yd, xd] += ok[ys, xs]
    return np.where(ok, tot / np.maximum(cnt, 1), x)


def make_view(scene: jaxfog.Scene, target: np.ndarray, name: str, downscale: int = 1, target_spp=None,
              valid: np.ndarray | None = None, noise_floor: np.ndarray | None = None,
              noise: np.ndarray | None = None) -> View:
    """Check the target against the scene's camera and bring both to the fit resolution (1 / `downscale`). `valid`
    (bool `(H, W)`) the pixels to fit (a photograph's, `fitting.photo`); `noise_floor` (`(H, W, 3)`) each value's
    variance that the target's own block estimate cannot see (quantisation); `noise` (`(H, W, 3)`) each value's noise
    variance from a camera model (`fitting.photo.Photo.variance`), used instead of the block estimate. A target whose
    noise comes from the image alone (another renderer's) is raised by the typical shortfall of a draw of its noise's
    heavy tail, and gets the uncertainty of its brightness that the tail leaves (`tail_spread`); where it has firefly
    pixels (`fireflies`) also the view without them
    (`View.without_fireflies`), which the fit uses only where the model check refuses the targets as they are."""
    target = _checked_target(scene, target, name, downscale)
    ok = np.ones(target.shape[:2], bool) if valid is None else np.asarray(valid, bool)
    if ok.shape != target.shape[:2]:
        raise FitError(f"{name}: mask is {ok.shape[1]}x{ok.shape[0]} px, the target {target.shape[1]}x"
                       f"{target.shape[0]} px")
    lit = light_pixels(scene) & ok
    from_image = noise is None and not target_spp
    spread, deficit, events = tail_spread(target, ok & ~lit) if from_image else (0.0, 0.0, 0)
    raw, target = target, target * np.float32(1.0 + deficit)
    pooled = (scene, target, name, downscale, target_spp, valid, ok, noise_floor, noise)
    view = _pooled_view(*pooled, lit)._replace(tail_pixels=events, tail_spread=spread, tail_deficit=deficit)
    ff = fireflies(raw, ok & ~lit) if from_image else None
    if ff is not None and np.any(ff):
        alt = _pooled_view(*pooled, lit | ff)
        where = tuple((int(x), int(y)) for y, x in zip(*np.nonzero(ff)))
        lum = np.asarray(target, np.float64).sum(axis=-1)
        share = float(lum[ff].sum() / max(lum[ok & ~lit].sum(), 1e-300))
        view = view._replace(without_fireflies=alt._replace(light_pixels=view.light_pixels, fireflies=where,
                                                            firefly_share=share, tail_pixels=view.tail_pixels,
                                                            tail_spread=spread, tail_deficit=deficit))
    return view


def _checked_target(scene: jaxfog.Scene, target: np.ndarray, name: str, downscale: int) -> np.ndarray:
    """`target` as float32 `(H, W, 3)` after the checks every target passes (shape, camera size, finite, >= 0, the
    pooling factor)."""
    cam = scene.camera
    target = np.asarray(target, np.float32)
    if target.ndim != 3 or target.shape[2] != 3:
        raise FitError(f"{name}: target must be an RGB image (H, W, 3), got shape {target.shape}")
    if target.shape[:2] != (cam.height, cam.width):
        raise FitError(f"{name}: target is {target.shape[1]}x{target.shape[0]} px but the scene's camera is "
                       f"{cam.width}x{cam.height} px")
    try:
        jaxfog.check_finite(target, f"{name}: target")
    except FloatingPointError as e:
        raise FitError(str(e)) from None
    if np.any(target < 0):
        raise FitError(f"{name}: target has {int(np.sum(target < 0))} negative values (smallest "
                       f"{float(target.min()):.4g}); expected linear radiance >= 0")
    if downscale < 1 or cam.width % downscale or cam.height % downscale:
        raise FitError(f"downscale {downscale} must be >= 1 and divide the image size {cam.width}x{cam.height}")
    return target


def _pooled_view(scene, target, name, downscale, target_spp, valid, ok, noise_floor, noise, lit) -> View:
    """The view at the fit resolution with the source pixels `lit` left out (a light's image, fireflies)."""
    if np.any(lit) and downscale == 1:
        ok, valid, lit = ok & ~lit, ok & ~lit, np.zeros_like(lit)
    if not np.any(ok) or not float(np.mean(target[ok])) > 0.0:
        raise FitError(f"{name}: target is black (every pixel 0): nothing to fit; a target rendered with the light "
                       f"off, or the wrong file?")
    cam = scene.camera
    small = cam.resized(cam.width // downscale, cam.height // downscale)
    scene = eqx.tree_at(lambda s: s.camera, scene, small)
    w = (~lit).astype(np.float64)[:, :, None]
    if noise is None:
        var = block_noise(target, downscale, w)
    else:
        var = masked_pool(np.asarray(noise, np.float64), w, downscale, variance=True)
    floor = None
    if noise_floor is not None:
        floor = masked_pool(np.asarray(noise_floor, np.float64), w, downscale, variance=True)
        var = np.maximum(var, floor)
    small_ok = None if valid is None else pool(ok[:, :, None].astype(np.float64), downscale)[:, :, 0] >= 1.0
    if lit.any():
        some = pool(w, downscale)[:, :, 0] > 0
        small_ok = some if small_ok is None else small_ok & some
    if small_ok is not None and not np.any(small_ok):
        raise FitError(f"{name}: no pixel at the fit resolution (1/{downscale}) is free of masked pixels")
    return View(scene, masked_pool(target, w, downscale), name, target_spp, var, downscale, small_ok, int(lit.sum()),
                fine_weight=w[:, :, 0].astype(np.float32) if lit.any() else None,
                noise_from_image=noise is None and not target_spp, target_var_floor=floor)


def masked_pool(img, w, f: int, variance: bool = False):
    """`pool(img, f)` over the source pixels of weight `w` (`(H, W, 1)`, 0 or 1) only: the mean of a pooled pixel's
    weighted source pixels, or with `variance` the variance of that mean from the source pixels' own (numpy or
    traced JAX arrays; a pooled pixel without any: 0)."""
    xp = jnp if isinstance(img, jax.Array) else np
    k = pool(w, f)
    safe = xp.where(k > 0, k, 1.0)
    if variance:
        return xp.where(k > 0, pool(img * w, f) / (safe * safe * f * f), 0.0)
    return xp.where(k > 0, pool(img * w, f) / safe, 0.0)


LIGHT_MARGIN = 0.5
"""Pixels (`light_pixels`) within this many pixels of a point-like light's image are not fitted (at the target's
resolution: a pooled pixel keeps its other source pixels); beyond it the radiance's square over a pixel is bounded
by that of 1 / b at b = half a pixel's angle."""


def light_pixels(scene: jaxfog.Scene) -> np.ndarray:
    """Bool `(H, W)`: the pixels whose square lies within `LIGHT_MARGIN` px of a point or spot light's image in
    front of the camera. Camera rays passing such a light at distance `b` carry in-scattered radiance ~ 1 / b, whose
    square integrated over a pixel that holds the light's image diverges (`int 1 / b^2 b db`): the pixel's estimate
    has no finite variance at any spp, its typical value lies below its expectation, and its sample variance is no
    noise model (measured: a 256-spp halo target's central 4 x 4 px read 9% below the expectation, 4.4 of their
    own standard errors; the fit of the droplet diameter followed them to 3.0 standard errors off, and without the
    light's 4 source px, 1.05)."""
    cam = scene.camera
    out = np.zeros((cam.height, cam.width), bool)
    for light in scene.lights:
        if not isinstance(light, jaxfog.AbstractPointLikeLight):
            continue
        xy, front = cam.film_position(light.position)
        if not bool(front):
            continue
        x, y = (float(v) for v in np.asarray(xy))
        cols = np.arange(cam.width)
        rows = np.arange(cam.height)
        near_x = (cols + 1 + LIGHT_MARGIN > x) & (cols - LIGHT_MARGIN < x)
        near_y = (rows + 1 + LIGHT_MARGIN > y) & (rows - LIGHT_MARGIN < y)
        out |= near_y[:, None] & near_x[None, :]
    return out


FIREFLY_FACTOR = 10.0
"""A firefly (`fireflies`) is brighter than each of its 8 neighbours by this factor: no smooth image and no edge has
such a pixel (an edge pixel has a neighbour as bright on its bright side); a light's own image does, and is left out
anyway (`light_pixels`). Of the shipped targets jaxfog's renders have none; Mitsuba's 2048-spp targets 0-81 per view
(docs/results/fit_solver.md, "Fireflies")."""


def fireflies(target: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Bool `(H, W)`: the pixels of `target` (`(H, W, 3)`, among `ok`) brighter than each of their valid 8 neighbours
    by `FIREFLY_FACTOR` (the channels' sum). A path tracer without equiangular sampling draws such single-sample
    fireflies where a path vertex falls next to a point or spot light (the light's `1 / r^2` has no finite variance
    there): their expectation is spread over every pixel, not in the one that drew it. The fit keeps them (leaving
    out the large draws of a heavy tail biases the target low, and the residuals' standard errors see them) unless
    the model check refuses the targets with them (`fitting.solver.fit_views`)."""
    lum = np.where(ok, np.asarray(target, np.float64).sum(axis=-1), np.nan)
    top = brightest_neighbour(lum)
    return ok & np.isfinite(top) & (lum > FIREFLY_FACTOR * np.maximum(top, 0.0)) & (lum > 0)


def brightest_neighbour(lum: np.ndarray) -> np.ndarray:
    """Per pixel of `lum` (`(H, W)`, NaN where not valid), the largest of its valid 8 neighbours (NaN: none)."""
    H, W = lum.shape
    pad = np.pad(lum, 1, constant_values=np.nan)
    nb = np.stack([pad[1 + dy:1 + dy + H, 1 + dx:1 + dx + W] for dy in (-1, 0, 1) for dx in (-1, 0, 1)
                   if dy or dx], axis=-1)
    with warnings.catch_warnings():  # a pixel without valid neighbours: NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmax(nb, axis=-1)


TAIL_FACTOR = 4.0
"""A source pixel brighter than this many times its brightest valid neighbour (the channels' sum) is a draw from
the heavy tail of another renderer's noise (`tail_spread`), and that level its threshold. Its neighbours are other
samples, so the threshold is independent of the pixel; no smooth image and no edge has such a pixel (an edge pixel
has a neighbour as bright on its bright side), and a pixel of normal noise of relative standard deviation 0.5 (a
2048-spp Mitsuba side view of the foreign spot scene) would lie 11 of them above its mean. Measured on 16 Mitsuba
draws of that view: 20 such pixels a draw (docs/fitting.md, "Fireflies"); at 3x the view totals' errors over the
resulting standard errors read the same (rms 0.99 against 1.04 over 80 draws of five views), at 2x too small (0.73:
the threshold reaches into the body)."""

TAIL_INDEX = 1.5
"""The index of the tail (`P(X > x) ~ x^-alpha`) of a volume path tracer's samples near a light that it connects
to by next-event estimation, with path vertices drawn by free flight: a vertex falls within `r` of a point light (or
of a point of an area light) with probability `~ r^3` and brings `~ 1 / r^2`. Hill's estimate over 16 Mitsuba draws
of the foreign spot side view tends to it as the threshold rises (1.99, 1.88, 1.69, 1.61, 1.46 above 1.5, 2, 3, 4
and 12x the brightest neighbour), as in the point-lit room (1.51 above 12x); per image it is too uncertain to use (a
relative standard error of `1 / sqrt(n)` over n pixels: 22% over 20)."""

TAIL_DRAWS = 8000
"""Draws of the tail's compound Poisson-Pareto sum in `tail_spread` (its quantiles to about 1.5% of their
half-distance); seeded, so a view's spread is a function of its target."""


def tail_spread(target: np.ndarray, ok: np.ndarray, seed: int = 0) -> tuple[float, float, int]:
    """`(spread, deficit, events)` of a target rendered by another renderer: how uncertain the heavy tail of its noise
    leaves the view's brightness, and by how much its typical draw falls short of its expectation, both relative to its
    light (the channels' sum over `ok`); `events` its tail pixels (above `TAIL_FACTOR` x their brightest valid
    neighbour, `t` that threshold). (0, 0, 0) without tail pixels.

    A volume path tracer that connects free-flight vertices to a point, spot or area light draws samples with a tail of
    index `TAIL_INDEX`: a mean but no variance. Such a view's total has no standard error; its typical draw lacks the
    rare largest values and is darker than its expectation, and a dark draw's residuals show little noise (measured on
    16 draws of the foreign spot side view: the totals spread 1.9%, the residuals' standard error of the darkest
    three read 1.1-1.3%, and they were 2.4-2.7 of it low). The tail pixels measure the tail: a Poisson number of them
    (mean `events`), each its threshold (drawn from theirs) times a Pareto draw of index `TAIL_INDEX`. `spread` is the
    half-distance between the 16% and 84% quantiles of that sum, `deficit` its mean (`events x mean(t) x alpha /
    (alpha - 1)`) less its median: the fit raises the view by the deficit (the median draw's estimate of the
    expectation) and adds the spread to its noise as an uncertain brightness (`Problem.brightness_noise`); where the
    residuals show more (a draw with a large event), the residuals' covariance stands
    (`fitting.rounds.reported_covariance`). Over 80 Mitsuba draws of five views (spot, point light, glass and mirror,
    dense fog) the view totals' errors over their standard errors read rms 1.44 without, 1.04 with (mean -0.30;
    within 2: 96%; docs/fitting.md, "Fireflies")."""
    x = np.asarray(target, np.float64)
    lum = np.where(ok, x.sum(axis=-1), np.nan)
    t = TAIL_FACTOR * np.nan_to_num(brightest_neighbour(lum))
    tail = ok & (t > 0) & (np.nan_to_num(lum) > t)
    n = int(tail.sum())
    light = float(np.nansum(lum))
    if n == 0 or not light > 0:
        return 0.0, 0.0, n
    rng = np.random.default_rng(seed)
    owner = np.repeat(np.arange(TAIL_DRAWS), rng.poisson(n, TAIL_DRAWS))
    sizes = rng.choice(t[tail], owner.size) * rng.random(owner.size) ** (-1.0 / TAIL_INDEX)
    sums = np.bincount(owner, weights=sizes, minlength=TAIL_DRAWS)
    q16, q50, q84 = np.percentile(sums, [16.0, 50.0, 84.0])
    mean = n * float(np.mean(t[tail])) * TAIL_INDEX / (TAIL_INDEX - 1.0)
    return float(0.5 * (q84 - q16) / light), float((mean - q50) / light), n


STRATA_SPP_MIN = 2
"""Samples per source pixel below which a pooled view is rendered at the fit resolution instead (a pixel's sample
variance needs two samples)."""


def stratified(spp: int, f: int) -> bool:
    """Whether a pass of `spp` samples per pooled pixel renders a view pooled by `f` at the source resolution."""
    return f > 1 and spp % (f * f) == 0 and spp // (f * f) >= STRATA_SPP_MIN


def _fine_scene(scene: jaxfog.Scene, f: int) -> jaxfog.Scene:
    """`scene` with its camera at `f` times the resolution (the target's own, for a view pooled by `f`)."""
    if f == 1:
        return scene
    c = scene.camera
    cam = c.resized(c.width * f, c.height * f)
    return eqx.tree_at(lambda s: s.camera, scene, cam)


def _scan_fn(scenes, names, Y, key, spp):
    """Every candidate row of `Y` rendered in every scene (vmapped over the candidates; one program per scene
    structure, candidate count and spp)."""
    def one(y):
        vals = from_unconstrained(names, y)
        return [_gain(jaxfog.render(apply(s, vals), jax.random.fold_in(key, i), spp), vals, i)
                for i, s in enumerate(scenes)]
    return jax.vmap(one)(Y)


class _ViewData(NamedTuple):
    """What a pass renders of one view (a pytree: its arrays are the pass program's inputs, `downscale` part of its
    signature): the scene at the fit resolution and at the target's (`fine`), the target at the fit resolution,
    `View.fine_weight` and the partly masked pooled pixels (`partial`, bool `(h, w)`, or None)."""

    scene: jaxfog.Scene
    fine: jaxfog.Scene
    target: np.ndarray
    fine_weight: np.ndarray | None
    partial: np.ndarray | None
    downscale: int


def _render_view(d: _ViewData, i: int, vals: dict, key, spp: int, ref, variance=False):
    """View i's render at `vals` (times the camera's factor), "proposal" with reference `ref` where given.

    A pooled view (`downscale` f > 1) with at least `STRATA_SPP_MIN` samples per source pixel is rendered at the
    target's resolution with spp / f^2 samples a pixel and pooled like the target: the same image in
    expectation, its samples stratified over the f x f source pixels. Its variance is then the target's kind:
    the mean of the source pixels' own variances, without the spread of radiance across the pooled pixel that
    f^2 jittered samples of the coarse pixel would add (docs/fitting.md, "The pooled pixel's variance")."""
    kw = {"estimator": "proposal", "proposal": ref} if ref is not None else {}
    f = d.downscale
    coarse = not stratified(spp, f)
    if not coarse:
        out = jaxfog.render(apply(d.fine, vals), key, spp // (f * f), variance=variance, **kw)
        if d.fine_weight is None:
            out = (pool(out[0], f), pool(out[1], f) / (f * f)) if variance else pool(out, f)
        else:
            w = jnp.asarray(d.fine_weight)[:, :, None]
            out = ((masked_pool(out[0], w, f), masked_pool(out[1], w, f, variance=True)) if variance
                   else masked_pool(out, w, f))
    else:
        out = jaxfog.render(apply(d.scene, vals), key, spp, variance=variance, **kw)
    out = (_gain(out[0], vals, i), _gain(out[1], vals, i, 2)) if variance else _gain(out, vals, i)
    return _untouched(d, out, variance) if coarse else out


def _untouched(d: _ViewData, out, variance: bool = False):
    """A render at the fit resolution (camera factor applied) with its partly masked pixels (`View.fine_weight`)
    replaced by the target's, variance 0: it cannot leave their masked source pixels out, so in a pass too small
    to render at the target's resolution, and in the search, those pixels carry no residual and no Jacobian."""
    if d.partial is None:
        return out
    xp = np if isinstance(out, np.ndarray) else jnp
    t = xp.asarray(d.target, out[0].dtype if variance else out.dtype)
    m = xp.asarray(d.partial)[..., None]
    if variance:
        return xp.where(m, t, out[0]), xp.where(m, 0.0, out[1])
    return xp.where(m, t, out)


def _pass_fn(data: tuple, names: tuple, scales, valid, y, key, ref, spp: int):
    """The pass program: the Jacobian of every view's flattened render (scaled by `scales`, times `valid`) at `y`,
    with the value and each view's per-pixel variance from the same samples (forward mode, `jax.jacfwd`)."""
    def f(yy):
        vals = from_unconstrained(names, yy)
        outs = [_render_view(d, i, vals, jax.random.fold_in(key, i), spp, ref, variance=True)
                for i, d in enumerate(data)]
        flat = jnp.concatenate([(img / scales[i]).ravel() for i, (img, _) in enumerate(outs)])
        flat = flat * valid.astype(flat.dtype)
        return flat, (jax.lax.stop_gradient(flat), [jax.lax.stop_gradient(var) for _, var in outs])

    return jax.jacfwd(f, has_aux=True)(y)


_PASS = StoredProgram("fit_pass", _pass_fn)
_SCAN = StoredProgram("fit_scan", _scan_fn)


def _gain(img, vals: dict, view: int, power: int = 1):
    """`img` times the camera's factor on view `view` (`fitting.params.gains`) to `power` (2 for a variance)."""
    g = gains(vals, view)
    return img if g is None else img * jnp.reshape(g ** power, (1,) * (img.ndim - 1) + (3,))


class Pass(NamedTuple):
    """One forward-mode pass at `y` in scaled units: `e` the residual (render - target), `u` each element's variance
    of ONE sample (the render's per-pixel sample variance times its spp), `J` the Jacobian `d e / d y`, `spp` its
    samples per pixel. float64 numpy arrays: `e`, `u` of shape `(n,)`, `J` of shape `(n, k)`."""

    e: np.ndarray
    u: np.ndarray
    J: np.ndarray
    spp: int


class Problem:
    """All views' renders as functions of the unconstrained parameters `y` (`fitting.params`), in scaled units.

    `scales[v]`: the mean of view v's target (a black target is refused); `n`: pixel values of all views; `pixel_of[i]`: the
    pixel (over all views) that element i belongs to, for per-pixel sums over the three channels."""

    def __init__(self, views: list[View], names: list[str]):
        if not views:
            raise FitError("no targets given")
        masks = [np.ones(v.target.shape[:2], bool) if v.valid is None else np.asarray(v.valid, bool) for v in views]
        for v, m in zip(views, masks):
            if not np.any(m) or not float(np.mean(v.target[m])) > 0.0:
                raise FitError(f"{v.name}: target is black (every pixel 0): nothing to fit; a target rendered with "
                               f"the light off, or the wrong file?")
        self.views, self.names = views, list(names)
        self.scales = [float(np.mean(v.target[m])) for v, m in zip(views, masks)]
        self.n = sum(v.target.size for v in views)
        self.valid = np.concatenate([np.repeat(m.ravel(), 3) for m in masks]).astype(np.float64)
        self.coverage = [float(np.mean(m)) for m in masks]
        self.t = np.concatenate([(np.asarray(v.target, np.float64) / s).ravel()
                                 for v, s in zip(views, self.scales)]) / math.sqrt(self.n) * self.valid
        self.pixel_of = np.arange(self.n) // 3
        self.partial = [None if v.fine_weight is None else
                        (pool(v.fine_weight[:, :, None].astype(np.float64), v.downscale)[:, :, 0] < 1.0)
                        for v in views]
        self.data = tuple(_ViewData(v.scene, _fine_scene(v.scene, v.downscale), np.asarray(v.target, np.float32),
                                    v.fine_weight, p, int(v.downscale)) for v, p in zip(views, self.partial))

    def reference(self, y) -> jaxfog.AbstractMedium | None:
        """The "proposal" estimator's reference medium: the medium at `y`, constant to differentiation."""
        med = apply(self.views[0].scene, from_unconstrained(self.names, y)).medium
        return None if med is None else jax.lax.stop_gradient(med)

    def _render(self, i: int, vals: dict, key, spp: int, ref, variance=False):
        """View i's render at `vals` (`_render_view`)."""
        return _render_view(self.data[i], i, vals, key, spp, ref, variance)

    def images(self, y, key, spp: int) -> list[np.ndarray]:
        """One render per view at `y` (linear radiance, `(h, w, 3)` each), "proposal" with reference at `y`."""
        ref, vals = self.reference(y), from_unconstrained(self.names, jnp.asarray(y, jnp.float32))
        return [np.asarray(self._render(i, vals, jax.random.fold_in(key, i), spp, ref), np.float64)
                for i in range(len(self.views))]

    def flat(self, images) -> np.ndarray:
        """Images of every view (linear radiance) as one vector in scaled units."""
        return np.concatenate([(np.asarray(x, np.float64) / s).ravel()
                               for x, s in zip(images, self.scales)]) / math.sqrt(self.n) * self.valid

    def scan(self, Y: np.ndarray, key, spp: int) -> np.ndarray:
        """Renders of every row of `Y` (`(N, k)` unconstrained parameter vectors) with the same key (common random
        numbers: the differences between candidates are smooth), as `(N, n)` in scaled units."""
        out = _SCAN(tuple(v.scene for v in self.views), tuple(self.names), jnp.asarray(Y, jnp.float32), key, int(spp))
        out = [_untouched(d, np.asarray(o, np.float64)) for d, o in zip(self.data, out)]
        return np.stack([self.flat([o[c] for o in out]) for c in range(len(Y))])

    def pass_(self, y, key, spp: int) -> Pass:
        """Value, per-sample variance and Jacobian of the residual at `y` from ONE forward-mode pass of `spp`."""
        J, (img, var) = _PASS(self.data, tuple(self.names), np.asarray(self.scales, np.float32),
                              self.valid.astype(np.float32), jnp.asarray(y, jnp.float32), key, self.reference(y),
                              int(spp))
        root = math.sqrt(self.n)
        e = np.asarray(img, np.float64) / root - self.t
        u = np.concatenate([(np.asarray(v, np.float64) * spp / (s * s)).ravel()
                            for v, s in zip(var, self.scales)]) / self.n * self.valid
        return Pass(e, u, np.asarray(J, np.float64) / root, spp)

    def target_variance(self, u: np.ndarray | None, residual: np.ndarray | None = None,
                        var_render: np.ndarray | None = None) -> np.ndarray:
        """Each element's variance of the target (scaled units): for a jaxfog target from its header's spp (the
        render's per-sample variance `u` over the `spp_T f^2` samples of a pooled pixel), else from the target
        itself (`View.target_var`, the block estimate); with `residual` (render - target at an estimate, scaled
        units) and the render's variance of it `var_render`, a target whose noise was estimated from its own
        pixels gets `residual_noise` instead (at least its `target_var_floor`)."""
        parts, at = [], 0
        for v, s in zip(self.views, self.scales):
            sl = slice(at, at + v.target.size)
            if v.target_spp and u is not None:
                parts.append(u[sl] / (v.target_spp * v.downscale ** 2))
            elif v.noise_from_image and residual is not None and var_render is not None:
                ok = self.valid[sl].reshape(v.target.shape) > 0
                r = np.where(ok, np.reshape(residual[sl], v.target.shape), np.nan)
                tv = residual_noise(r, np.reshape(var_render[sl], v.target.shape))
                if v.target_var_floor is not None:
                    tv = np.maximum(tv, np.asarray(v.target_var_floor, np.float64) / (s * s * self.n))
                parts.append(np.where(ok, tv, 0.0).ravel())
            else:
                tv = v.target_var if v.target_var is not None else np.zeros(v.target.shape)
                parts.append(np.asarray(tv, np.float64).ravel() / (s * s * self.n))
            at += v.target.size
        return np.concatenate(parts)

    def brightness_noise(self) -> np.ndarray | None:
        """`(n, V)`: per view with a heavy-tailed target (`View.tail_spread` > 0), the residual's change (scaled
        units) when that view's brightness moves by its tail's spread: `spread x target` on its elements, 0
        elsewhere; its columns are independent noise of unit variance (`fitting.rounds.gauss_newton` adds their
        covariance to the target's). None where no view has a tail."""
        cols, at = [], 0
        for v in self.views:
            size = v.target.size
            if v.tail_spread > 0:
                col = np.zeros(self.n)
                col[at:at + size] = v.tail_spread * self.t[at:at + size]  # `t` is 0 on masked elements
                cols.append(col)
            at += size
        return np.stack(cols, axis=1) if cols else None

    def split(self, x: np.ndarray) -> list[np.ndarray]:
        """Values over all elements (the last axis) as one `(..., h, w, 3)` array per view."""
        x = np.asarray(x)
        out, at = [], 0
        for v in self.views:
            out.append(x[..., at:at + v.target.size].reshape(x.shape[:-1] + v.target.shape))
            at += v.target.size
        return out


def candidate_fisher(scene: jaxfog.Scene, names: list[str], values: dict, spp: int, target_samples: float | None,
                     key, noise: np.ndarray | None = None) -> np.ndarray:
    """The Fisher information (parameters' units) a target of `scene`'s view would add at the estimate `values`:
    `sym(Ja^T W Jb)` with Ja, Jb the Jacobians of the view's pixels from two independent `spp`-sample "proposal"
    renders (no Monte Carlo `Var[J]` in it; negative eigenvalues clipped to 0) and `W` the inverse of the target's
    per-pixel noise variance: the render's per-sample variance over `target_samples` samples per pixel, or `noise`
    (per element, e.g. a target's own block estimate) where given, floored at 0.1 of the median. `scene` at the
    resolution it would be fitted at. For `fitting.information.rank_views`."""
    y = to_unconstrained(names, values)
    d = jacobian_to_params(names, np.asarray(y))
    med = apply(scene, values).medium
    ref = None if med is None else jax.lax.stop_gradient(med)
    kw = {"estimator": "proposal", "proposal": ref} if ref is not None else {}
    Js, var = [], None
    for kk in jax.random.split(key):
        def f(yy, kk=kk):
            img, v = jaxfog.render(apply(scene, from_unconstrained(names, yy)), kk, spp, variance=True, **kw)
            return img.ravel(), jax.lax.stop_gradient(v).ravel()
        J, v = jax.jacfwd(f, has_aux=True)(y)
        Js.append(np.asarray(J, np.float64) / d[None, :])
        var = np.asarray(v, np.float64) if var is None else 0.5 * (var + np.asarray(v, np.float64))
    noise = var * spp / float(target_samples) if noise is None else np.asarray(noise, np.float64).ravel()
    pos = noise[np.isfinite(noise) & (noise > 0)]
    if pos.size == 0:
        return np.full((len(names), len(names)), np.nan)
    noise = np.maximum(np.where(np.isfinite(noise), noise, np.inf), 0.1 * float(np.median(pos)))
    Ja, Jb = Js
    F = 0.5 * (Ja.T @ (Jb / noise[:, None]) + Jb.T @ (Ja / noise[:, None]))
    w, V = np.linalg.eigh(0.5 * (F + F.T))
    return (V * np.maximum(w, 0.0)) @ V.T
