"""Fit every voxel of a density grid to images from several views (a `GridMedium` scene per view).

    python -m fitting.grid SCENE1.json TARGET1.exr [SCENE2.json TARGET2.exr ...] --out OUT \\
        [--solver gauss-newton | adam] [--iterations N] [--spp N] [--levels L] [--downscale F] [--start 0.3] \\
        [--seed 0] [--smooth auto | WEIGHT] [--holdout SCENE.json TARGET.exr ...]
    python -m fitting.fit SCENE1.json TARGET1.exr ... --fit density --out RESULT.json   # the same fit

Every scene holds the same grid medium (shape and box; the first scene's grid is only its shape: the fit starts
from a constant grid, `--start` 1/scene unit, or the mean extinction the first view's brightness suggests).
The parameters are the voxels' logarithms (`D = exp(theta)`: positive, and a relative step in a thin voxel is as
easy as in a dense one). Each iteration renders every view twice with independent keys and takes the gradient of
`sum_px stop_gradient(I_a - T) I_b / var` through the second render (reverse mode through the tracer: the
two-key gradient, unbiased where the squared residual of one render is not) plus a smoothness prior
`weight * sum (theta_i - theta_j)^2` over neighbouring voxels; Adam (step 0.05 in log-density) moves `theta`.

`--solver gauss-newton`: Levenberg-Marquardt on the same objective with matrix-free normal equations
(`gn_step`: Jacobian-vector products of a linearised render, their transpose for the vector-Jacobian products,
conjugate gradients through lineax); `--iterations` counts its steps, each from renders at `--spp` (use more than
Adam's: a step is as noisy as its gradient). docs/results/grid.md compares the two at equal wall time. `--levels L`
(Gauss-Newton only) fits from coarse to fine: `COARSE_STEPS` steps on a grid of the same box with each axis halved,
L - 1 times, each level's log-density read at the next one's texel centres as its start (`fit_coarse_to_fine`).

The prior's weight is chosen by the data (`--smooth auto`, the discrepancy principle): the fit's chi^2 per pixel
(the residual's mean square over the render noise plus the target's pixel-to-pixel noise), averaged over 20
iterations, is compared with 1 from a third of the iterations on; below it the fit is reading noise and the weight
grows 2x, above 2 it is too smooth to explain the images and the weight halves. Adam's step decays linearly to a
fifth over the iterations. Either fit ends with one Gauss-Newton step on the dense information `sym(Ja^T W Jb)`
(two independent renders per view, forward mode over every voxel) for grids up to `DENSE_SE_MAX` voxels, at the
weight that maximises the evidence of the linearised model (`evidence_weight`, MacKay's fixed point: the prior
is read as a Gaussian whose scale the data estimate); the per-voxel standard errors are the diagonal of the
inverse of that information plus the prior's Hessian. For larger grids: the last iterate, and the inverse of the
information's diagonal, estimated by Hutchinson's method from random-sign vector-Jacobian products (a lower bound:
it ignores the voxels' correlations).

Writes `OUT/RESULT_density.vol` (the fitted grid, in the units of the scenes' grid: with their `scale` it
renders the fitted fog), `OUT/RESULT_density_se.vol` (its standard error, same units),
`OUT/RESULT.json` (per iteration: loss, chi^2, weight, seconds; the volume error when the scenes' grid is the
truth, `--truth`; each `--holdout` view's relative RMS error and chi^2 per pixel with the starting and the fitted
grid) and `OUT/slices.png` (the middle slices of the fit, its standard error and the truth). With `--out NAME.json`
the files are NAME.json, NAME_density.vol, NAME_density_se.vol and NAME_slices.png.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import sys
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxfog
from jaxfog.tools import atomic_write

STEP = 0.05
"""Adam's step in log-density per iteration (a voxel can change by 5% per step; 100 steps span e^5)."""

BETAS = (0.9, 0.999)
"""Adam's moment decays."""

WINDOW = 20
"""Iterations over which the chi^2 is averaged before the discrepancy principle compares it with 1 (one
iteration's chi^2 from a few spp is noisy)."""

SMOOTH_START = 1.0
"""The prior's starting weight with `--smooth auto`, relative to the data term's scale (both are sums of squares in
units of the noise); the discrepancy principle then moves it by factors of 2."""


# ------------------------------------------------------------------------------------------------ the views
def load_views(pairs, downscale: int | None):
    """`[(scene, target (H, W, 3), var (H, W, 3)), ...]`: each scene at the fit's resolution, its target box-pooled
    to it and the target's pixel variance from its 2x2 blocks' spread (a render's noise)."""
    views = []
    shape = None
    for scene_path, target_path in pairs:
        target, _ = jaxfog.read_exr(target_path)
        H, W = target.shape[:2]
        f = downscale or max(1, min(H, W) // 16)
        if H % f or W % f:
            raise ValueError(f"{target_path}: {W} x {H} px is not divisible by --downscale {f}")
        sf = jaxfog.load_scene(scene_path, [f"camera.width={W // f}", f"camera.height={H // f}"])
        med = sf.scene.medium
        if not isinstance(med, jaxfog.GridMedium):
            raise ValueError(f"{scene_path}: the medium is {type(med).__name__}; fitting.grid fits a grid medium")
        grid = (med.density.shape, np.asarray(med.bounds[0]).tolist(), np.asarray(med.bounds[1]).tolist())
        if shape is not None and grid != shape:
            raise ValueError(f"{scene_path}: its grid (shape and box) differs from the first view's")
        shape = grid
        small = target.reshape(H // f, f, W // f, f, 3).mean((1, 3))
        spread = target.reshape(H // f, f, W // f, f, 3).var((1, 3), ddof=1) / (f * f) if f > 1 else None
        var = spread if spread is not None else np.full_like(small, max(float(small.var()) * 1e-4, 1e-12))
        views.append((sf.scene, jnp.asarray(small), jnp.asarray(var)))
    return views


def neighbour_penalty(theta):
    """`sum (theta_i - theta_j)^2` over the grid's face neighbours (z, y, x)."""
    return sum(jnp.sum(jnp.diff(theta, axis=a) ** 2) for a in range(3))


def with_density(scene, theta):
    """The scene with the grid's extinction `exp(theta)` (1/scene unit: the values with scale 1)."""
    return eqx.tree_at(lambda s: (s.medium.density, s.medium.scale), scene,
                       (jnp.exp(theta)[..., None].astype(jnp.float32), jnp.float32(1.0)))


# ------------------------------------------------------------------------------------------------- one step
def make_step(views, spp: int):
    """`(theta, weight, key) -> (loss, chi2, grad)`: the two-key data term of every view plus the prior. One
    compiled program per view shape (the views are its arguments, not constants: four views of one size compile
    once)."""

    @eqx.filter_jit
    def one_view(theta, scene, target, var, key):
        def data(th):
            ka, kb = jax.random.split(key)
            sc = with_density(scene, th)
            img_a, var_a = jaxfog.render(sc, ka, spp, variance=True)
            img_b = jaxfog.render(sc, kb, spp)
            noise = jax.lax.stop_gradient(var + var_a)
            w = 1.0 / (noise + 1e-3 * jnp.mean(noise) + 1e-12)
            resid = jax.lax.stop_gradient(img_a - target)
            # the gradient of this is sum r w dI_b: the two-key estimate of the squared residual's half-gradient
            return jnp.sum(resid * img_b * w), jnp.mean(resid ** 2 * w)

        return jax.value_and_grad(data, has_aux=True)(theta)

    prior = jax.jit(jax.value_and_grad(neighbour_penalty))

    def step(theta, weight, key):
        loss, chi2, grad = 0.0, 0.0, jnp.zeros_like(theta)
        for i, (scene, target, var) in enumerate(views):
            (li, ci), gi = one_view(theta, scene, target, var, jax.random.fold_in(key, i))
            loss, chi2, grad = loss + li, chi2 + ci, grad + gi
        p, gp = prior(theta)
        return loss + weight * p, chi2 / len(views), grad + weight * gp

    return step


@eqx.filter_jit
def _hutchinson_probe(theta, scene, var, z, k, spp: int):
    """`J^T W^(1/2) z` of one view's render, `W` the inverse of the target's noise `var` plus the render's own (as
    in the fit's data term; module level: compiled once per view shape and spp)."""
    def f(th):
        img, v = jaxfog.render(with_density(scene, th), k, spp, variance=True)
        noise = jax.lax.stop_gradient(var + v)
        return jnp.sum(img * z / jnp.sqrt(noise + 1e-3 * jnp.mean(noise) + 1e-12))

    return jax.grad(f)(theta)


def hutchinson_diagonal(views, theta, spp: int, key, probes: int = 8):
    """`diag(J^T W J)` of the data term at `theta` (per voxel), from `probes` random-sign vector-Jacobian products:
    `E[(J^T W^(1/2) z)^2] = diag(J^T W J)` for `z` of independent +-1 entries (one compiled program for all)."""
    diag = jnp.zeros_like(theta)
    for p in range(probes):
        for i, (scene, target, var) in enumerate(views):
            k = jax.random.fold_in(jax.random.fold_in(key, p), i)
            z = jnp.where(jax.random.bernoulli(jax.random.fold_in(k, 1), shape=target.shape), 1.0, -1.0)
            diag = diag + _hutchinson_probe(theta, scene, var, z, k, spp) ** 2
    return diag / probes


DENSE_SE_MAX = 512
"""Grids of at most this many voxels get standard errors from the whole information matrix (`dense_information`:
one forward-mode column per voxel, in chunks of `DENSE_CHUNK`); larger ones from its diagonal (Hutchinson), which
ignores the voxels' correlations and so understates each voxel's standard error."""

SE_SPP_MIN = 64
"""Samples per pixel (at least) of each render behind the standard errors: once per fit, and the two-key
information's own noise falls with them."""

MAX_POLISH = 0.5
"""The largest change of a voxel's log-density in the closing Gauss-Newton step (a factor e^0.5 = 1.65): the step
corrects the noise Adam's last iterations leave, and a larger one means the linearisation is not to be trusted."""

DENSE_CHUNK = 8
"""Voxels per forward-mode pass of `dense_information` (tangents carried together through one render). Measured
(`python -m benchmarks.bench_grid_se`, 2 cores, interleaved): 8 tangents a render cost 0.41x the time per tangent
of 64 on an 8^3 grid at 16 x 16 px and 0.46x on the shipped 4^3 set (8 x 8 px); 4 and 16 cost 1.2x and 1.1x of 8
(docs/results/grid.md)."""


@eqx.filter_jit
def _columns(theta, scene, basis, k, spp: int):
    """`(J (pixels, len(basis)), image, variance)` of one render: forward mode along each row of `basis` (module
    level: compiled once per view shape, chunk and spp)."""
    def f(th):
        img, v = jaxfog.render(with_density(scene, th), k, spp, variance=True)
        return img, jax.lax.stop_gradient(v)

    def jvp(t):
        (img, v), (dimg, _) = jax.jvp(f, (theta,), (t.reshape(theta.shape),))
        return dimg.ravel(), img.ravel(), v.ravel()

    J, img, v = jax.vmap(jvp)(basis)
    return J.T, img[0], v[0]


def dense_information(views, theta, spp: int, key) -> tuple[np.ndarray, np.ndarray]:
    """`(F, g)`: the data term's Gauss-Newton information `sym(Ja^T W Jb)` over all voxels, `(n, n)` (`n` voxels,
    log-density coordinates), and its gradient `(Ja^T W eb + Jb^T W ea) / 2`, `(n,)`, from two renders per view with
    independent keys (`e` = render - target; a one-key `J^T W J` also carries the Jacobians' Monte Carlo noise,
    which reads as information, and a one-key gradient multiplies a residual by the Jacobian of its own paths),
    `W` the inverse of the target's noise plus one render's. Forward mode, one column per voxel. F's negative
    eigenvalues (noise) clipped to 0."""
    from tqdm import tqdm

    n = int(np.prod(theta.shape))
    F, g = np.zeros((n, n)), np.zeros(n)
    eye = np.eye(n, dtype=np.float32)
    bar = tqdm(total=2 * len(views) * n, unit="voxel", desc="information (forward mode, every voxel)",
               file=sys.stderr, disable=None, leave=False)  # shown on a terminal only
    for i, (scene, target, var) in enumerate(views):
        halves = []
        for h in range(2):
            k = jax.random.fold_in(jax.random.fold_in(key, i), h)
            parts = []
            for c in range(0, n, DENSE_CHUNK):
                parts.append(_columns(theta, scene, jnp.asarray(eye[c:c + DENSE_CHUNK]), k, spp))
                bar.update(min(DENSE_CHUNK, n - c))
            J = np.concatenate([np.asarray(p[0], np.float64) for p in parts], axis=1)
            e = np.asarray(parts[0][1], np.float64) - np.asarray(target, np.float64).ravel()
            halves.append((J, e, np.asarray(parts[0][2], np.float64)))
        (Ja, ea, va), (Jb, eb, vb) = halves
        noise = np.asarray(var, np.float64).ravel() + 0.5 * (va + vb)
        w = 1.0 / (noise + 1e-3 * np.mean(noise) + 1e-12)
        M = Ja.T @ (w[:, None] * Jb)
        F += 0.5 * (M + M.T)
        g += 0.5 * (Ja.T @ (w * eb) + Jb.T @ (w * ea))
    bar.close()
    lam, V = np.linalg.eigh(F)
    return (V * np.maximum(lam, 0.0)) @ V.T, g


def prior_hessian(shape, weight: float) -> np.ndarray:
    """The Hessian of `weight * neighbour_penalty` (a quadratic: `2 weight` times the grid's graph Laplacian)."""
    n = int(np.prod(shape))
    H = np.zeros((n, n))
    idx = np.arange(n).reshape(shape)
    for a in range(3):
        i = np.moveaxis(idx, a, 0)
        for p, q in zip(i[:-1].ravel(), i[1:].ravel()):
            H[p, p] += 1.0
            H[q, q] += 1.0
            H[p, q] -= 1.0
            H[q, p] -= 1.0
    return 2.0 * weight * H


def dense_gauss_newton(views, theta, spp: int, key, weight) -> tuple[np.ndarray, np.ndarray, float]:
    """`(delta, cov, weight)`: the Gauss-Newton step of the whole objective (data term plus `weight` times the
    neighbour penalty) from `theta` (`newton_step` with `(F, g)` of `dense_information`), and the covariance
    `(F + H)^-1` of the log-density. `weight`: a number, or `("evidence", w0)` for the weight that maximises the
    evidence of the linearised model (`evidence_weight`, from `w0`); the weight used is returned. For grids up to
    `DENSE_SE_MAX` voxels."""
    shape = tuple(theta.shape)
    F, g = dense_information(views, theta, spp, key)
    th = np.asarray(theta, np.float64).ravel()
    L = prior_hessian(shape, 0.5)  # the graph Laplacian
    if isinstance(weight, tuple):
        weight = evidence_weight(F, g, th, L, weight[1])
    delta, cov = newton_step(F, g, th, L, weight)
    return delta.reshape(shape), cov, float(weight)


def newton_step(F, g, theta, L, weight: float) -> tuple[np.ndarray, np.ndarray]:
    """`(delta, cov)`: `-(F + H)^-1 (g + H theta)` with the prior's Hessian `H = 2 weight L` (`L` the graph
    Laplacian, `prior_hessian(shape, 0.5)`), each coordinate at most `MAX_POLISH` in log-density, and `(F + H)^-1`
    (pseudo-inverse); `F`, `g`, `theta` flat."""
    H = 2.0 * weight * L
    cov = np.linalg.pinv(F + H, hermitian=True)
    return np.clip(-cov @ (g + H @ theta), -MAX_POLISH, MAX_POLISH), cov


EVIDENCE_STEPS = 100
"""Fixed-point iterations of `evidence_weight` at most (it converges to 1e-6 in about 15 on the shipped set)."""

EVIDENCE_RANGE = 2.0 ** 8
"""How far (a factor either way) `evidence_weight` may move the weight from where the fit left it: the linearised
model holds near the fitted point only, and its gradient's Monte Carlo noise makes the evidence grow without bound
as the weight goes to 0 (steps along directions the images do not constrain)."""


def evidence_weight(F, g, theta, L, w0: float) -> float:
    """The prior weight `w` at which the linearised model is most probable (type-II maximum likelihood, MacKay
    1992): the smoothness prior `exp(-w theta^T L theta)` is a Gaussian of precision `alpha L` (`alpha = 2 w`, `L`
    the grid's graph Laplacian, rank `r`), and the evidence is stationary where `alpha theta_w^T L theta_w = gamma
    = r - alpha tr(L (F + alpha L)^-1)` (`gamma`: the number of directions the prior does not decide), `theta_w`
    the Gauss-Newton point at `w` from `theta` (`F`, `g`: `dense_information` there). Iterated from `w0`, kept
    within `EVIDENCE_RANGE` of it. Its covariance `(F + alpha L)^-1` then counts the prior's pull (a smoothness
    the data support) where the discrepancy principle's weight is chosen for the images' residual alone: over
    three 4^3 fogs the voxels within 1 / 2 standard errors of the truth went from 42% / 70% (no closing step) and
    50% / 92% (the step at the discrepancy principle's weight) to 62% / 93% (`python -m benchmarks.grid_coverage`,
    docs/results/grid.md)."""
    lam = np.linalg.eigvalsh(L)
    rank = int(np.sum(lam > 1e-9 * max(lam.max(), 1e-30)))
    w = float(w0)
    for _ in range(EVIDENCE_STEPS):
        delta, cov = newton_step(F, g, theta, L, w)
        th = theta + delta
        rough = float(th @ L @ th)
        gamma = rank - 2.0 * w * float(np.sum(L * cov))  # tr(L cov), both symmetric
        if rough <= 0.0 or gamma <= 0.0:
            break
        w_new = float(np.clip(gamma / (2.0 * rough), w0 / EVIDENCE_RANGE, w0 * EVIDENCE_RANGE))
        done = abs(w_new - w) <= 1e-6 * w
        w = w_new
        if done:
            break
    return w


def voxel_se(views, theta, spp: int, key, weight: float) -> tuple[np.ndarray, str]:
    """Per-voxel standard error of the log-density and how it was computed: the diagonal of the inverse of the whole
    information plus the prior's Hessian for grids up to `DENSE_SE_MAX` voxels ("dense"), else the inverse of its
    diagonal ("diagonal": a lower bound)."""
    shape = tuple(theta.shape)
    if int(np.prod(shape)) <= DENSE_SE_MAX:
        _, cov, _ = dense_gauss_newton(views, theta, spp, key, weight)
        return _diagonal_se(cov, shape), "dense"
    info = np.asarray(hutchinson_diagonal(views, theta, spp, key))
    prior_diag = 2.0 * weight * sum(_neighbour_count(shape, a) for a in range(3))
    return 1.0 / np.sqrt(np.maximum(info, 0.0) + prior_diag), "diagonal"


# ------------------------------------------------------------------------------------ Gauss-Newton, matrix-free
CG_STEPS = 20
"""Conjugate-gradient iterations per Gauss-Newton step: each costs one Jacobian-vector product (forward mode) and
its transpose (a vector-Jacobian product) per view; the normal equations need not be solved exactly (a truncated
Newton step), and the damping keeps the system well conditioned."""

CG_RTOL = 1e-2
"""Relative residual at which conjugate gradients stop early."""

LM_START = 0.1
"""Levenberg damping at the start, relative to the curvature of the objective along its gradient (`g^T A g / g^T
g`): a tenth keeps the first step near the Gauss-Newton step but bounded where the images say little."""

LOSS_TOLERANCE = 2.0
"""How many standard errors of the difference of two loss estimates (each from its renders' pixels) a step's loss
may exceed the current point's before the step is undone: the estimates are Monte Carlo, and a step undone by
their noise only raises the damping."""

DAMPING_MAX = 1e6
"""The largest Levenberg damping (relative): beyond it a step is a gradient step of negligible length."""

WEIGHT_EVERY = 3
"""Kept Levenberg-Marquardt steps at one prior weight before the discrepancy principle may change it. A first
version changed the weight at every step: on the shipped four-view set (16 spp) it fell from 1 to 1/64 in 12
steps, chasing one step's chi^2 before the objective at a weight had settled. With 3 (and 128 spp) the chi^2
reached 1.0-1.3 within 5 steps and the weight stayed within a factor 2 (docs/results/grid.md). A choice, not
tuned further."""

MAX_STEP = 0.5
"""The largest change of a voxel's log-density in one Gauss-Newton step (a factor e^0.5 = 1.65), as `MAX_POLISH`."""


@eqx.filter_jit
def gn_step(theta, views, key, weight, damping, spp: int):
    """One damped Gauss-Newton step of the whole objective `L = 1/2 sum_views e^T W e + weight * penalty` from
    `theta`, matrix-free; `views` as `stack_views` groups them.

    Per view, render `a` is linearised (`jax.linearize`: its Jacobian-vector products, and their transpose, the
    vector-Jacobian products, without a second forward pass) and render `b` has an independent key: the gradient is
    `J_a^T W e_b` (unbiased, as the Adam fit's two-key gradient), the loss `1/2 e_a^T W e_b`. The normal equations
    `(J_a^T W J_a + weight H + lambda I) delta = -g` are solved by conjugate gradients (`lm_direction`). Returns
    `(delta, data loss, its standard error, penalty, chi2 per pixel, predicted decrease)`."""
    lins, g, loss, loss_var, chi2 = [], jnp.zeros_like(theta), 0.0, 0.0, 0.0
    for i, (scenes, target, var) in enumerate(views):  # groups of views stacked along a leading axis
        keys = jax.random.split(jax.random.fold_in(key, i), (target.shape[0], 2))

        def render_a(th, scenes=scenes, keys=keys):
            return jax.vmap(lambda sc, k: jaxfog.render(with_density(sc, th), k[0], spp))(scenes, keys)

        img_a, jvp_a = jax.linearize(render_a, theta)
        img_b, var_b = jax.vmap(lambda sc, k: jaxfog.render(with_density(sc, theta), k[1], spp, variance=True))(
            scenes, keys)
        noise = var + var_b
        w = 1.0 / (noise + 1e-3 * jnp.mean(noise, axis=(1, 2, 3), keepdims=True) + 1e-12)
        vjp_a = jax.linear_transpose(jvp_a, theta)
        e_a, e_b = img_a - target, img_b - target
        g = g + vjp_a(w * e_b)[0]
        terms = 0.5 * e_a * w * e_b  # independent across pixels: the loss's variance is about the sum of squares
        loss, loss_var = loss + jnp.sum(terms), loss_var + jnp.sum(terms ** 2)
        chi2 = chi2 + jnp.sum(jnp.mean(e_b ** 2 * w, axis=(1, 2, 3)))
        lins.append((jvp_a, vjp_a, w))
    n_views = sum(v[1].shape[0] for v in views)
    penalty, g_prior = jax.value_and_grad(neighbour_penalty)(theta)
    g = g + weight * g_prior

    def normal(v):
        out = weight * jax.jvp(jax.grad(neighbour_penalty), (theta,), (v,))[1]
        for jvp_a, vjp_a, w in lins:
            out = out + vjp_a(w * jvp_a(v))[0]
        return out

    delta, predicted = lm_direction(g, normal, damping)
    return delta, loss, jnp.sqrt(loss_var), penalty, chi2 / n_views, predicted


def lm_direction(g, normal, damping):
    """`(delta, predicted)`: the Levenberg-Marquardt step `-(A + lambda I)^-1 g` for the symmetric positive
    semi-definite operator `A = normal` (a function), by conjugate gradients through lineax (`CG_STEPS`,
    `CG_RTOL`), `lambda = damping * g^T A g / g^T g` (the curvature along the gradient sets the scale), each entry
    clipped to `MAX_STEP`; and the quadratic model's decrease `-(g^T delta + delta^T A delta / 2)`."""
    import lineax as lx

    lam = damping * jnp.vdot(g, normal(g)) / jnp.maximum(jnp.vdot(g, g), 1e-30)
    op = lx.FunctionLinearOperator(lambda v: normal(v) + lam * v, jax.eval_shape(lambda: g),
                                   lx.positive_semidefinite_tag)
    sol = lx.linear_solve(op, -g, lx.CG(rtol=CG_RTOL, atol=0.0, max_steps=CG_STEPS), throw=False)
    delta = jnp.clip(sol.value, -MAX_STEP, MAX_STEP)
    return delta, -(jnp.vdot(g, delta) + 0.5 * jnp.vdot(delta, normal(delta)))


def stack_views(views) -> list:
    """The views `[(scene, target, var), ...]` as groups `[(scenes, targets, vars), ...]` with a leading axis of
    views: one group when every scene has the same structure (one render traced and compiled for all of them, under
    `vmap`), else one group per view."""
    parts = [eqx.partition(v[0], eqx.is_array) for v in views]
    same = all(jax.tree.structure(p[0]) == jax.tree.structure(parts[0][0]) and eqx.tree_equal(p[1], parts[0][1])
               for p in parts)
    groups = [views] if same else [[v] for v in views]
    out = []
    for grp in groups:
        dyn = [eqx.partition(v[0], eqx.is_array)[0] for v in grp]
        scenes = eqx.combine(jax.tree.map(lambda *x: jnp.stack(x), *dyn), eqx.partition(grp[0][0], eqx.is_array)[1])
        out.append((scenes, jnp.stack([v[1] for v in grp]), jnp.stack([v[2] for v in grp])))
    return out


def fit_grid_gauss_newton(views, *, iterations: int, spp: int, start, seed: int, smooth, truth=None,
                          log=print, lift=None, standard_errors: bool = True):
    """Levenberg-Marquardt on the log-density with matrix-free normal equations (`gn_step`), `iterations` calls.

    Each call evaluates a point with new keys: the step's end point is kept when its loss is at most the current
    point's (within `LOSS_TOLERANCE` standard errors) (the damping then shrinks by the model's agreement, Nielsen's rule); otherwise the damping quadruples
    and the next call recomputes the step at the current point. The prior's weight by the discrepancy principle
    after every `WEIGHT_EVERY` kept steps; losses are compared at the current weight (`gn_step` returns the two
    terms). Then the closing step (`_close`): for grids up to `DENSE_SE_MAX` voxels one dense Gauss-Newton step at
    the evidence's weight, whose covariance gives the standard errors. `start`: a constant (1/scene unit) or a starting grid of the views' shape;
    `lift` maps the log-density to the truth's grid for the volume error (a coarse level's, `fit_coarse_to_fine`);
    without `standard_errors` the se is None. Returns `(density, se, history)` as `fit_grid`."""
    shape = views[0][0].medium.density.shape[:3]
    theta = jnp.log(jnp.broadcast_to(jnp.asarray(start, jnp.float32), shape))
    lift = lift or (lambda th: th)
    weight = SMOOTH_START if smooth == "auto" else float(smooth)
    damping, key = LM_START, jax.random.key(seed)
    history, t0 = [], time.perf_counter()
    groups = stack_views(views)
    cur, pending, at_weight = None, theta, 0  # cur: (data loss, penalty, predicted decrease, step) at theta
    for it in range(1, iterations + 1):
        delta, data, data_se, penalty, chi2, pred = (np.asarray(x) if i == 0 else float(x) for i, x in enumerate(
            gn_step(pending, groups, jax.random.fold_in(key, it), jnp.float32(weight), jnp.float32(damping), spp)))
        at_theta = pending is theta
        # a step is undone only when its loss is above the current one by more than their noise allows
        kept = (cur is None or at_theta or data + weight * penalty
                <= cur[0] + weight * cur[1] + LOSS_TOLERANCE * math.hypot(data_se, cur[4]))
        if kept and not at_theta and cur is not None:
            # the model's agreement, in [0, 1] (a loss within the noise above the current one counts as 0: x2)
            rho = min(max((cur[0] + weight * cur[1] - data - weight * penalty) / max(cur[2], 1e-30), 0.0), 1.0)
            damping = min(damping * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), DAMPING_MAX)
        if kept:
            theta, cur = pending, (data, penalty, pred, jnp.asarray(delta), data_se)
            at_weight += 1
            if smooth == "auto" and at_weight >= WEIGHT_EVERY:
                at_weight, weight = 0, weight * 2.0 if chi2 < 1.0 else weight / 2.0 if chi2 > 2.0 else weight
            pending = theta + cur[3]
        else:  # the step went too far: recompute it at the current point with more damping
            damping = min(damping * 4.0, DAMPING_MAX)
            pending = theta
        rec = {"iteration": it, "loss": data + weight * penalty, "chi2": chi2, "weight": weight, "damping": damping,
               "kept": kept, "seconds": time.perf_counter() - t0}
        if truth is not None:
            rec["volume_error"] = volume_error(lift(np.asarray(theta)), truth)
        history.append(rec)
        log(f"  step {it}: chi2/px {chi2:.3f}, {'kept' if kept else 'undone'}, damping {damping:.3g}, prior weight "
            f"{weight:.3g}, " + (f"volume error {rec['volume_error']:.3f}, " if truth is not None else "")
            + f"{rec['seconds']:.0f} s")
    if not standard_errors:
        return np.exp(np.asarray(theta)), None, history
    theta, se_theta = _close(views, theta, spp, jax.random.fold_in(key, 10 ** 6), weight, smooth, truth, history,
                             log)
    density = np.exp(np.asarray(theta))
    return density, density * se_theta, history


# ------------------------------------------------------------------------------------------- coarse to fine
COARSE_STEPS = 4
"""Gauss-Newton steps at each coarser level of `fit_coarse_to_fine` (the finest level gets the rest). A choice, not
tuned: on the shipped set's 2^3 level the chi^2 per pixel fell 14 -> 3.6 in 4 steps and the volume error no further
(a 2^3 grid cannot hold its blob); coarse to fine did not pay there (docs/results/grid.md)."""


def level_shapes(shape, levels: int) -> list[tuple[int, int, int]]:
    """The grid shapes of `levels` levels, coarsest first: each axis halved (rounded up, at least 1) per level
    below `shape`, which is the last."""
    return [tuple(max(1, -(-n // 2 ** (levels - 1 - i))) for n in shape) for i in range(levels)]


def upsample(theta, shape) -> np.ndarray:
    """A grid `theta` `(nz, ny, nx)` read at the texel centres of a grid of `shape` spanning the same box: trilinear
    between texel centres, clamped at the border (as `GridMedium` reads its values), one axis at a time."""
    x = np.asarray(theta, np.float64)
    for axis, n in enumerate(shape):
        m = x.shape[axis]
        c = np.clip((np.arange(n) + 0.5) * m / n - 0.5, 0.0, m - 1)  # the fine centres in coarse texel units
        i0 = np.minimum(np.floor(c).astype(int), m - 1)
        i1 = np.minimum(i0 + 1, m - 1)
        f = (c - i0).reshape([-1 if a == axis else 1 for a in range(3)])
        x = np.take(x, i0, axis=axis) * (1.0 - f) + np.take(x, i1, axis=axis) * f
    return x


def views_at(views, shape):
    """The views with a grid of `shape` in the same box (its values are the fit's)."""
    return [(eqx.tree_at(lambda s: s.medium.density, sc, jnp.zeros(tuple(shape) + (1,), jnp.float32)), t, v)
            for sc, t, v in views]


def volume_error(theta, truth) -> float:
    """The relative L2 error over the voxels of the grid `exp(theta)` against `truth` (same shape)."""
    return float(np.linalg.norm(np.exp(np.asarray(theta, np.float64)) - truth) / np.linalg.norm(truth))


def fit_coarse_to_fine(views, *, levels: int, iterations: int, spp: int, start: float, seed: int, smooth,
                       truth=None, log=print):
    """Gauss-Newton from coarse to fine (`--levels`): `COARSE_STEPS` steps on each coarser grid (`level_shapes`: the
    same box, each axis halved per level), its log-density read at the next grid's texel centres (`upsample`) as
    that level's start; the finest grid gets the rest of `iterations` and the standard errors. The history's
    seconds run on across the levels and each record names its level's shape. Returns `(density, se, history)` as
    `fit_grid`."""
    shapes = level_shapes(views[0][0].medium.density.shape[:3], levels)
    fine = shapes[-1]
    start_grid, history, offset = start, [], 0.0
    for i, shape in enumerate(shapes):
        last = i == len(shapes) - 1
        steps = iterations - COARSE_STEPS * (len(shapes) - 1) if last else COARSE_STEPS
        log(f"  level {i + 1} of {len(shapes)}: {'x'.join(map(str, shape))} grid, {steps} steps")
        density, se, hist = fit_grid_gauss_newton(
            views_at(views, shape), iterations=steps, spp=spp, start=start_grid, seed=seed + 7919 * i,
            smooth=smooth, truth=truth, log=log, lift=lambda th: upsample(th, fine),
            standard_errors=last)
        for rec in hist:
            history.append({**rec, "seconds": rec["seconds"] + offset, "level": list(shape)})
        offset = history[-1]["seconds"]
        if not last:
            start_grid = np.exp(upsample(np.log(density), shapes[i + 1])).astype(np.float32)
    return density, se, history


# --------------------------------------------------------------------------------------------------- the fit
def fit_grid(views, *, iterations: int, spp: int, start: float, seed: int, smooth, truth=None, log=print):
    """Adam on the log-density (module docstring). Returns `(density, se, history)`: the fitted grid `(nz, ny,
    nx)`, its per-voxel standard error (same units) and the per-iteration records."""
    shape = views[0][0].medium.density.shape[:3]
    theta = jnp.full(shape, math.log(start), jnp.float32)
    m, v = jnp.zeros_like(theta), jnp.zeros_like(theta)
    weight = SMOOTH_START if smooth == "auto" else float(smooth)
    step = make_step(views, spp)
    key = jax.random.key(seed)
    history, t0 = [], time.perf_counter()
    chi2_window = []
    for it in range(1, iterations + 1):
        loss, chi2, g = step(theta, jnp.float32(weight), jax.random.fold_in(key, it))
        m = BETAS[0] * m + (1 - BETAS[0]) * g
        v = BETAS[1] * v + (1 - BETAS[1]) * g * g
        m_hat, v_hat = m / (1 - BETAS[0] ** it), v / (1 - BETAS[1] ** it)
        lr = STEP * (1.0 - 0.8 * (it - 1) / max(iterations - 1, 1))  # decays to a fifth: the noise settles
        theta = theta - lr * m_hat / (jnp.sqrt(v_hat) + 1e-8)
        rec = {"iteration": it, "loss": float(loss), "chi2": float(chi2), "weight": weight,
               "seconds": time.perf_counter() - t0}
        if truth is not None:
            rec["volume_error"] = volume_error(theta, truth)
        history.append(rec)
        chi2_window.append(float(chi2))
        if it % WINDOW == 0:
            mean_chi2 = float(np.mean(chi2_window))
            chi2_window = []
            if smooth == "auto" and it >= iterations // 3:  # once the fit has approached the images
                weight = weight * 2.0 if mean_chi2 < 1.0 else weight / 2.0 if mean_chi2 > 2.0 else weight
            log(f"  iteration {it}: chi2/px {mean_chi2:.3f} (mean of {WINDOW}), prior weight {weight:.3g}, "
                + (f"volume error {rec['volume_error']:.3f}, " if truth is not None else "")
                + f"{rec['seconds']:.0f} s")
    theta, se_theta = _close(views, theta, spp, jax.random.fold_in(key, 10 ** 6), weight, smooth, truth, history,
                             log)
    density = np.exp(np.asarray(theta))
    return density, density * se_theta, history


def _close(views, theta, spp, key, weight, smooth, truth, history, log):
    """The fit's last stage: for grids up to `DENSE_SE_MAX` voxels one Gauss-Newton step of the whole objective with
    the dense information (`dense_gauss_newton`, renders of at least `SE_SPP_MIN` spp) at the weight of the
    evidence (`evidence_weight`; with `--smooth auto`, else the given weight), and the standard errors from its
    covariance; for larger grids the last iterate and the diagonal standard errors (`voxel_se`)."""
    spp = max(spp, SE_SPP_MIN)
    if int(np.prod(theta.shape)) > DENSE_SE_MAX:
        return theta, voxel_se(views, theta, spp, key, weight)[0]
    t0 = time.perf_counter()
    n = int(np.prod(theta.shape))
    log(f"  closing step: the information over {n} voxels ({2 * len(views) * -(-n // DENSE_CHUNK)} forward-mode "
        f"renders at {spp} spp)")
    delta, cov, used = dense_gauss_newton(views, theta, spp, key, ("evidence", weight) if smooth == "auto" else weight)
    theta = theta + jnp.asarray(delta, theta.dtype)
    rec = {"iteration": "gauss-newton", "largest_step": float(np.max(np.abs(delta))), "weight": used,
           "seconds": history[-1]["seconds"] + time.perf_counter() - t0 if history else time.perf_counter() - t0}
    if truth is not None:
        rec["volume_error"] = volume_error(theta, truth)
    history.append(rec)
    log(f"  closing Gauss-Newton step: prior weight {used:.3g}"
        + (" (evidence)" if smooth == "auto" else "") + f", largest change {rec['largest_step']:.3f} in log-density"
        + (f", volume error {rec['volume_error']:.3f}" if truth is not None else ""))
    return theta, _diagonal_se(cov, theta.shape)


def _diagonal_se(cov: np.ndarray, shape) -> np.ndarray:
    """Each voxel's standard error (the square root of the covariance's diagonal), in the grid's shape."""
    return np.sqrt(np.maximum(np.diag(cov), 0.0)).reshape(shape)


def heldout_error(view, density, spp: int, key) -> dict:
    """How well a grid predicts a view the fit did not see: `view` `(scene, target, var)` (`load_views`) rendered
    with `density` (`(nz, ny, nx)`, 1/scene unit) at `spp`; the relative RMS error `sqrt(mean((I - T)^2)) / mean(T)`
    and the chi^2 per pixel value over the target's and the render's noise (1 for a grid that explains the view)."""
    scene, target, var = view
    img, var_r = jaxfog.render(with_density(scene, jnp.log(jnp.asarray(density, jnp.float32))), key, spp,
                               variance=True)
    d = np.asarray(img, np.float64) - np.asarray(target, np.float64)
    noise = np.asarray(var, np.float64) + np.asarray(var_r, np.float64)
    return {"relative_rms": float(np.sqrt(np.mean(d * d)) / max(float(np.mean(target)), 1e-30)),
            "chi2": float(np.mean(d * d / np.maximum(noise, 1e-30))), "spp": spp}


def _neighbour_count(shape, axis):
    """Per voxel: how many neighbours it has along `axis` (1 at the ends, 2 inside, 0 for a single layer)."""
    n = shape[axis]
    c = np.full(n, 2.0) if n > 1 else np.zeros(1)
    if n > 1:
        c[0] = c[-1] = 1.0
    view = [1, 1, 1]
    view[axis] = n
    return np.broadcast_to(c.reshape(view), shape)


def write_slices(path, fit, se, truth) -> None:
    """The middle z, y and x slices of the fit, its standard error and (when known) the truth, as one PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [("fit", fit), ("standard error", se)] + ([("truth", truth)] if truth is not None else [])
    fig, axes = plt.subplots(len(rows), 3, figsize=(9, 3 * len(rows)), squeeze=False)
    vmax = float(max(np.max(fit), np.max(truth) if truth is not None else 0.0))
    for r, (name, g) in enumerate(rows):
        mids = [g[g.shape[0] // 2], g[:, g.shape[1] // 2], g[:, :, g.shape[2] // 2]]
        for c, (sl, axis) in enumerate(zip(mids, ("z", "y", "x"))):
            im = axes[r][c].imshow(sl, origin="lower", vmin=0, vmax=vmax if name != "standard error" else None)
            axes[r][c].set_title(f"{name}, middle {axis} slice", fontsize=9)
            fig.colorbar(im, ax=axes[r][c], fraction=0.046)
    fig.tight_layout()
    tmp = f"{path}.tmp.png"
    fig.savefig(tmp, dpi=80)
    plt.close(fig)
    os.replace(tmp, path)


# --------------------------------------------------------------------------------------------- command line
SOLVERS = {"gauss-newton": (12, 128), "adam": (200, 8)}
"""The solvers of the command line and their default `(iterations, spp)`: Gauss-Newton's steps settle in about 8
at 128 spp on the shipped four-view set (a step is as noisy as its renders); Adam's many cheap steps average their
noise (docs/results/grid.md, "Fitting every voxel")."""

def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m fitting.grid", description=__doc__.split("\n\n")[0])
    ap.add_argument("inputs", nargs="+", help="SCENE.json TARGET.exr [SCENE2.json TARGET2.exr ...]")
    ap.add_argument("--out", required=True,
                    help="output folder (RESULT.json, RESULT_density.vol, ... in it), or NAME.json (NAME_density.vol, "
                         "NAME_density_se.vol and NAME_slices.png beside it)")
    ap.add_argument("--solver", choices=list(SOLVERS), default="gauss-newton",
                    help="gauss-newton (Levenberg-Marquardt, matrix-free normal equations by conjugate gradients; "
                         "the default) or adam")
    ap.add_argument("--iterations", type=int, default=None,
                    help="steps (default: " + ", ".join(f"{k} {v[0]}" for k, v in SOLVERS.items()) + ")")
    ap.add_argument("--spp", type=int, default=None,
                    help="samples per pixel of each render, two per view a step (default: "
                         + ", ".join(f"{k} {v[1]}" for k, v in SOLVERS.items()) + ")")
    ap.add_argument("--levels", type=int, default=1,
                    help="gauss-newton from coarse to fine: this many grids, each axis halved per level below the "
                         f"scenes' grid, {COARSE_STEPS} steps on each coarser one (default 1: the scenes' grid only)")
    ap.add_argument("--downscale", type=int, default=None, help="fit at 1/F of the targets' size (default: 16 px)")
    ap.add_argument("--start", type=float, default=0.3, help="the starting grid's constant value, 1/scene unit")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--smooth", default="auto", help="the prior's weight, or 'auto' (discrepancy principle)")
    ap.add_argument("--truth", action="store_true", help="report the volume error against the scenes' own grid")
    ap.add_argument("--holdout", nargs=2, action="append", default=[], metavar=("SCENE.json", "TARGET.exr"),
                    help="a view the fit does not see: its error with the starting and the fitted grid is reported "
                         "(repeatable)")
    ap.add_argument("--holdout-spp", type=int, default=256, help="samples per pixel of a held-out view's render")
    return ap


def check_args(args) -> list[tuple[str, str]]:
    """Refuse bad arguments before any work: pairs of existing files, positive counts, a usable weight."""
    if len(args.inputs) % 2:
        raise ValueError("inputs: expected pairs SCENE.json TARGET.exr")
    pairs = list(zip(args.inputs[::2], args.inputs[1::2]))
    for s, t in pairs:
        for p in (s, t):
            if not os.path.isfile(p):
                raise ValueError(f"{p}: not found")
    default_iterations, default_spp = SOLVERS[args.solver]
    args.iterations = default_iterations if args.iterations is None else args.iterations
    args.spp = default_spp if args.spp is None else args.spp
    if args.iterations < 1 or args.spp < 1 or args.holdout_spp < 1:
        raise ValueError("--iterations, --spp and --holdout-spp must be >= 1")
    if args.levels < 1 or (args.levels > 1 and args.solver != "gauss-newton"):
        raise ValueError(f"--levels {args.levels}: expected an integer >= 1, and more than 1 only with --solver "
                         f"gauss-newton")
    if args.iterations <= COARSE_STEPS * (args.levels - 1):
        raise ValueError(f"--iterations {args.iterations}: --levels {args.levels} runs {COARSE_STEPS} steps on each "
                         f"of its {args.levels - 1} coarser grids; give more than {COARSE_STEPS * (args.levels - 1)}")
    for s, t in args.holdout:
        for p in (s, t):
            if not os.path.isfile(p):
                raise ValueError(f"--holdout {p}: not found")
    if not (args.start > 0 and math.isfinite(args.start)):
        raise ValueError(f"--start {args.start}: expected a finite value > 0 (1/scene unit)")
    if args.smooth != "auto":
        try:
            w = float(args.smooth)
        except ValueError:
            raise ValueError(f"--smooth {args.smooth!r}: expected 'auto' or a number >= 0") from None
        if not (w >= 0 and math.isfinite(w)):
            raise ValueError(f"--smooth {args.smooth!r}: expected 'auto' or a number >= 0")
    return pairs


def output_paths(out: str) -> dict:
    """The files a fit writes: in the folder `out`, or beside `out` when it names a `.json` file."""
    if out.endswith(".json"):
        stem = out[:-5]
        return {"result": out, "density": f"{stem}_density.vol", "se": f"{stem}_density_se.vol",
                "slices": f"{stem}_slices.png"}
    return {"result": os.path.join(out, "RESULT.json"), "density": os.path.join(out, "RESULT_density.vol"),
            "se": os.path.join(out, "RESULT_density_se.vol"), "slices": os.path.join(out, "slices.png")}


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        pairs = check_args(args)
        views = load_views(pairs, args.downscale)
        held = load_views([tuple(h) for h in args.holdout], args.downscale) if args.holdout else []
        if held and held[0][0].medium.density.shape != views[0][0].medium.density.shape:
            raise ValueError("--holdout: its grid's shape differs from the fitted views'")
    except (ValueError, jaxfog.SceneError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    from jaxfog.tools import use_compilation_cache

    use_compilation_cache()  # compiled programs kept on disk: a second run does not compile again ($JAXFOG_CACHE_DIR)
    paths = output_paths(args.out)
    truth = np.asarray(views[0][0].medium.density)[..., 0] * float(views[0][0].medium.scale) if args.truth else None
    print(f"fitting a {'x'.join(map(str, truth.shape if truth is not None else views[0][0].medium.density.shape[:3]))}"
          f" grid to {len(views)} view(s), {args.iterations} iterations")
    fit = fit_grid if args.solver == "adam" else fit_grid_gauss_newton
    if args.levels > 1:
        fit = functools.partial(fit_coarse_to_fine, levels=args.levels)
    density, se, history = fit(views, iterations=args.iterations, spp=args.spp, start=args.start,
                               seed=args.seed, smooth=args.smooth, truth=truth)
    heldout = []
    for i, ((s_path, t_path), view) in enumerate(zip(args.holdout, held)):
        key = jax.random.fold_in(jax.random.key(args.seed), 2 * 10 ** 6 + i)
        start = np.full(density.shape, args.start, np.float32)
        rec = {"scene": s_path, "target": t_path, "start": heldout_error(view, start, args.holdout_spp, key),
               "fit": heldout_error(view, density, args.holdout_spp, key)}
        heldout.append(rec)
        print(f"held-out {os.path.basename(t_path)}: relative RMS error {rec['start']['relative_rms']:.3f} (start) -> "
              f"{rec['fit']['relative_rms']:.3f} (fit), chi2/px {rec['start']['chi2']:.2f} -> {rec['fit']['chi2']:.2f}")
    os.makedirs(os.path.dirname(os.path.abspath(paths["result"])), exist_ok=True)
    lo, hi = (np.asarray(b) for b in views[0][0].medium.bounds)
    scale = float(views[0][0].medium.scale)
    jaxfog.write_vol(paths["density"], density / max(scale, 1e-30), (lo, hi))
    jaxfog.write_vol(paths["se"], se / max(scale, 1e-30), (lo, hi))
    text = json.dumps({"views": pairs, "solver": args.solver, "levels": args.levels, "heldout": heldout,
                       "history": history}, indent=1)
    atomic_write(paths["result"], lambda tmp: open(tmp, "w").write(text))
    write_slices(paths["slices"], density, se, truth)
    chi2 = [r["chi2"] for r in history if "chi2" in r][-1]
    print(f"done: chi2/px {chi2:.3f} (the last iteration)"
          + (f", volume error {history[-1]['volume_error']:.3f}" if truth is not None else "")
          + f"; wrote {paths['density']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
