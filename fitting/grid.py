"""Fit every voxel of a density grid to images from several views (a `GridMedium` scene per view).

    python -m fitting.grid SCENE1.json TARGET1.exr [SCENE2.json TARGET2.exr ...] --out OUT \\
        [--iterations 200] [--spp 8] [--downscale F] [--start 0.3] [--seed 0] [--smooth auto | WEIGHT] \\
        [--holdout SCENE.json TARGET.exr ...]
    python -m fitting.fit SCENE1.json TARGET1.exr ... --fit density --out RESULT.json   # the same fit

Every scene holds the same grid medium (shape and box; the first scene's grid is only its shape: the fit starts
from a constant grid, `--start` 1/scene unit, or the mean extinction the first view's brightness suggests).
The parameters are the voxels' logarithms (`D = exp(theta)`: positive, and a relative step in a thin voxel is as
easy as in a dense one). Each iteration renders every view twice with independent keys and takes the gradient of
`sum_px stop_gradient(I_a - T) I_b / var` through the second render (reverse mode through the tracer: the
two-key gradient, unbiased where the squared residual of one render is not) plus a smoothness prior
`weight * sum (theta_i - theta_j)^2` over neighbouring voxels; Adam (step 0.05 in log-density) moves `theta`.

The prior's weight is chosen by the data (`--smooth auto`, the discrepancy principle): the fit's chi^2 per pixel
(the residual's mean square over the render noise plus the target's pixel-to-pixel noise), averaged over 20
iterations, is compared with 1 from a third of the iterations on; below it the fit is reading noise and the weight
grows 2x, above 2 it is too smooth to explain the images and the weight halves. Adam's step decays linearly to a
fifth over the iterations. Per-voxel standard errors: the diagonal of the inverse of the Gauss-Newton information
`sym(Ja^T W Jb)` (two independent renders per view, forward mode over every voxel) plus the prior's Hessian, for
grids up to `DENSE_SE_MAX` voxels; for larger ones the inverse of its diagonal, estimated by Hutchinson's method
from random-sign vector-Jacobian products (a lower bound: it ignores the voxels' correlations).

Writes `OUT/RESULT_density.vol` (the fitted grid, in the units of the scenes' grid: with their `scale` it
renders the fitted fog), `OUT/RESULT_density_se.vol` (its standard error, same units),
`OUT/RESULT.json` (per iteration: loss, chi^2, weight, seconds; the volume error when the scenes' grid is the
truth, `--truth`; each `--holdout` view's relative RMS error and chi^2 per pixel with the starting and the fitted
grid) and `OUT/slices.png` (the middle slices of the fit, its standard error and the truth). With `--out NAME.json`
the files are NAME.json, NAME_density.vol, NAME_density_se.vol and NAME_slices.png.
"""

from __future__ import annotations

import argparse
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

DENSE_CHUNK = 64
"""Voxels per forward-mode pass of `dense_information` (tangents carried together through one render)."""


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
    n = int(np.prod(theta.shape))
    F, g = np.zeros((n, n)), np.zeros(n)
    eye = np.eye(n, dtype=np.float32)
    for i, (scene, target, var) in enumerate(views):
        halves = []
        for h in range(2):
            k = jax.random.fold_in(jax.random.fold_in(key, i), h)
            parts = [_columns(theta, scene, jnp.asarray(eye[c:c + DENSE_CHUNK]), k, spp)
                     for c in range(0, n, DENSE_CHUNK)]
            J = np.concatenate([np.asarray(p[0], np.float64) for p in parts], axis=1)
            e = np.asarray(parts[0][1], np.float64) - np.asarray(target, np.float64).ravel()
            halves.append((J, e, np.asarray(parts[0][2], np.float64)))
        (Ja, ea, va), (Jb, eb, vb) = halves
        noise = np.asarray(var, np.float64).ravel() + 0.5 * (va + vb)
        w = 1.0 / (noise + 1e-3 * np.mean(noise) + 1e-12)
        M = Ja.T @ (w[:, None] * Jb)
        F += 0.5 * (M + M.T)
        g += 0.5 * (Ja.T @ (w * eb) + Jb.T @ (w * ea))
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


def dense_gauss_newton(views, theta, spp: int, key, weight: float) -> tuple[np.ndarray, np.ndarray]:
    """`(delta, cov)`: the Gauss-Newton step of the whole objective (data term plus `weight` times the neighbour
    penalty) from `theta`, `-(F + H)^-1 (g + H theta)` with `(F, g)` of `dense_information` and `H` the prior's
    Hessian (each coordinate at most `MAX_POLISH` in log-density), and the covariance `(F + H)^-1` of the
    log-density. For grids up to `DENSE_SE_MAX` voxels."""
    shape = tuple(theta.shape)
    F, g = dense_information(views, theta, spp, key)
    H = prior_hessian(shape, weight)
    cov = np.linalg.pinv(F + H, hermitian=True)
    th = np.asarray(theta, np.float64).ravel()
    delta = np.clip(-cov @ (g + H @ th), -MAX_POLISH, MAX_POLISH)
    return delta.reshape(shape), cov


def voxel_se(views, theta, spp: int, key, weight: float) -> tuple[np.ndarray, str]:
    """Per-voxel standard error of the log-density and how it was computed: the diagonal of the inverse of the whole
    information plus the prior's Hessian for grids up to `DENSE_SE_MAX` voxels ("dense"), else the inverse of its
    diagonal ("diagonal": a lower bound)."""
    shape = tuple(theta.shape)
    if int(np.prod(shape)) <= DENSE_SE_MAX:
        _, cov = dense_gauss_newton(views, theta, spp, key, weight)
        return _diagonal_se(cov, shape), "dense"
    info = np.asarray(hutchinson_diagonal(views, theta, spp, key))
    prior_diag = 2.0 * weight * sum(_neighbour_count(shape, a) for a in range(3))
    return 1.0 / np.sqrt(np.maximum(info, 0.0) + prior_diag), "diagonal"


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
            rec["volume_error"] = float(np.linalg.norm(np.exp(np.asarray(theta)) - truth) / np.linalg.norm(truth))
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
    theta, se_theta = _close(views, theta, spp, jax.random.fold_in(key, 10 ** 6), weight, truth, history, log)
    density = np.exp(np.asarray(theta))
    return density, density * se_theta, history


def _close(views, theta, spp, key, weight, truth, history, log):
    """The fit's last stage: for grids up to `DENSE_SE_MAX` voxels one Gauss-Newton step of the whole objective with
    the dense information (`dense_gauss_newton`, renders of at least `SE_SPP_MIN` spp) and the standard errors from
    its covariance; for larger grids Adam's last iterate and the diagonal standard errors (`voxel_se`)."""
    spp = max(spp, SE_SPP_MIN)
    if int(np.prod(theta.shape)) > DENSE_SE_MAX:
        return theta, voxel_se(views, theta, spp, key, weight)[0]
    t0 = time.perf_counter()
    delta, cov = dense_gauss_newton(views, theta, spp, key, weight)
    theta = theta + jnp.asarray(delta, theta.dtype)
    rec = {"iteration": "gauss-newton", "largest_step": float(np.max(np.abs(delta))),
           "seconds": history[-1]["seconds"] + time.perf_counter() - t0 if history else time.perf_counter() - t0}
    if truth is not None:
        rec["volume_error"] = float(np.linalg.norm(np.exp(np.asarray(theta)) - truth) / np.linalg.norm(truth))
    history.append(rec)
    log(f"  closing Gauss-Newton step: largest change {rec['largest_step']:.3f} in log-density"
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
def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m fitting.grid", description=__doc__.split("\n\n")[0])
    ap.add_argument("inputs", nargs="+", help="SCENE.json TARGET.exr [SCENE2.json TARGET2.exr ...]")
    ap.add_argument("--out", required=True,
                    help="output folder (RESULT.json, RESULT_density.vol, ... in it), or NAME.json (NAME_density.vol, "
                         "NAME_density_se.vol and NAME_slices.png beside it)")
    ap.add_argument("--iterations", type=int, default=200)
    ap.add_argument("--spp", type=int, default=8, help="samples per pixel of each render (two per view a step)")
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
    if args.iterations < 1 or args.spp < 1 or args.holdout_spp < 1:
        raise ValueError("--iterations, --spp and --holdout-spp must be >= 1")
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
    paths = output_paths(args.out)
    truth = np.asarray(views[0][0].medium.density)[..., 0] * float(views[0][0].medium.scale) if args.truth else None
    print(f"fitting a {'x'.join(map(str, truth.shape if truth is not None else views[0][0].medium.density.shape[:3]))}"
          f" grid to {len(views)} view(s), {args.iterations} iterations")
    density, se, history = fit_grid(views, iterations=args.iterations, spp=args.spp, start=args.start,
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
    text = json.dumps({"views": pairs, "heldout": heldout, "history": history}, indent=1)
    atomic_write(paths["result"], lambda tmp: open(tmp, "w").write(text))
    write_slices(paths["slices"], density, se, truth)
    chi2 = [r["chi2"] for r in history if "chi2" in r][-1]
    print(f"done: chi2/px {chi2:.3f} (Adam's last iteration)"
          + (f", volume error {history[-1]['volume_error']:.3f}" if truth is not None else "")
          + f"; wrote {paths['density']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
