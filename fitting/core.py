"""The fit: optimistix least squares on rendered-minus-target residuals, with the "proposal" estimator.

Why "proposal" (docs/estimators.md): for a fixed key and a fixed reference `theta_ref`, the rendered image is a smooth,
deterministic function of the parameters that is an unbiased estimate at every value, which is what
Levenberg–Marquardt and BFGS assume. Its weights `f(theta) / p(theta_ref)` have finite variance only while
`sigma_t > sigma_ref / 2`, so between solves `theta_ref` is re-centred on the estimate and a fresh key is drawn,
until the estimate stops moving by more than its own noise. Then a few more solves with fresh keys give the spread
that the final uncertainty reports, beside the one from the Jacobian.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import lineax as lx
import optimistix as optx

import jaxfog

from .information import fisher_report, instead, relative_scales
from .params import FitError, SPECS, apply, from_unconstrained, jacobian_to_params, to_unconstrained


class View(NamedTuple):
    """One target image of the medium: the scene (at the fit resolution), the target (same size), a name."""

    scene: jaxfog.Scene
    target: np.ndarray
    name: str
    target_spp: int | None = None
    target_var: np.ndarray | None = None
    downscale: int = 1
    """`target_var`: per-pixel noise variance of the (pooled) target, estimated from the full-resolution target itself
    (`block_noise`): used when the header has no spp."""


def block_noise(img: np.ndarray, f: int) -> np.ndarray:
    """Per-pixel noise variance of `pool(img, f)`, estimated from `img` alone: for independent pixel noise of variance
    v, the second difference `x[i-1] - 2 x[i] + x[i+1]` has variance 6 v and cancels any linear trend of the image;
    its square / 6, averaged over both directions and over each f x f block, estimates v there, and the pooled pixel
    has v / f^2. Image curvature (edges) adds to it: the estimate errs on the side of more noise."""
    x = np.asarray(img, np.float64)
    v = np.zeros_like(x)
    cnt = np.zeros_like(x)
    if x.shape[1] >= 3:
        v[:, 1:-1] += (x[:, 2:] - 2 * x[:, 1:-1] + x[:, :-2]) ** 2 / 6.0
        cnt[:, 1:-1] += 1
    if x.shape[0] >= 3:
        v[1:-1] += (x[2:] - 2 * x[1:-1] + x[:-2]) ** 2 / 6.0
        cnt[1:-1] += 1
    v = np.where(cnt > 0, v / np.maximum(cnt, 1), np.nan)
    fill = np.nanmean(v) if np.any(cnt > 0) else 0.0
    v = np.where(np.isfinite(v), v, fill)
    return pool(v, f) / (f * f)


def pool(img: np.ndarray, f: int) -> np.ndarray:
    """Box-downsample `(H, W, 3)` by an integer factor (exact: a pixel is the mean of its square)."""
    if f == 1:
        return img
    H, W, C = img.shape
    return img.reshape(H // f, f, W // f, f, C).mean(axis=(1, 3))


def make_view(scene: jaxfog.Scene, target: np.ndarray, name: str, downscale: int = 1, target_spp=None) -> View:
    """Check the target against the scene's camera and bring both to the fit resolution."""
    cam = scene.camera
    target = np.asarray(target, np.float32)
    if target.ndim != 3 or target.shape[2] != 3:
        raise FitError(f"{name}: target must be an RGB image (H, W, 3), got shape {target.shape}")
    if target.shape[:2] != (cam.height, cam.width):
        raise FitError(
            f"{name}: target is {target.shape[1]}x{target.shape[0]} px but the scene's camera is "
            f"{cam.width}x{cam.height} px"
        )
    try:
        jaxfog.check_finite(target, f"{name}: target")
    except FloatingPointError as e:
        raise FitError(str(e)) from None
    if np.any(target < 0):
        raise FitError(f"{name}: target has {int(np.sum(target < 0))} negative values (smallest {float(target.min()):.4g});"
                       f" expected linear radiance >= 0")
    if downscale < 1 or cam.width % downscale or cam.height % downscale:
        raise FitError(f"downscale {downscale} must be >= 1 and divide the image size {cam.width}x{cam.height}")
    import equinox as eqx

    small = jaxfog.Camera(origin=cam.origin, target=cam.target, up=cam.up, fov=cam.fov,
                          width=cam.width // downscale, height=cam.height // downscale)
    scene = eqx.tree_at(lambda s: s.camera, scene, small)
    return View(scene, pool(target, downscale), name, target_spp, block_noise(target, downscale), downscale)


@dataclass
class FitConfig:
    """How to fit. `spp`: samples per pixel of each render inside the solver; `solver`: "lm" (Levenberg–Marquardt,
    forward-mode Jacobian) or "bfgs" (reverse-mode gradient); `max_rounds`: re-centring rounds at most (each with a
    fresh key); the estimate is the mean of the last `repeats + 1` rounds once they show no trend, and their
    spread gives the uncertainty; `rtol`/`atol`: solver tolerances on the unconstrained parameters (loose: a round's estimate is noisier than
    1e-2 anyway, and the next round re-solves);
    `max_steps` per solve; `value_spp_factor`: the residual's value at the reference (one render per round) uses
    this many times `spp` (the noise of a round's estimate is `J^T e` with `e` that render's noise, heavy-tailed
    near a spot light, while the steps, `spp` each, only need a Jacobian; measured on the shipped targets at
    256 spp: 32x instead of 8x halved the standard error of the estimates, 0.0116 -> 0.0036 in sigma_t on `mid`,
    for ~1.3x the wall time); `chi2_max`: a fit whose residual exceeds this multiple of its expected noise is reported
    as not explaining the target; `max_gain`: the largest factor by which a round's step is scaled up to undo the
    shrinkage by a noisy Jacobian (1 = off; `fit_views.unshrink`); `average_jacobians`: after the burn-in, each
    round is one Gauss-Newton step with the Jacobians of the last this many rounds averaged (0 = LM rounds
    throughout; `fit_views.averaged_step`); `max_step_se`: an averaged step longer than this many of its own
    standard errors (Mahalanobis length in `s^2 A^-1`) is rejected (the round stays put; a second one in a row is
    taken, shortened to this length, so a fit far from the solution still moves): one firefly-ridden value render
    otherwise throws a converged fit far off (measured: `mid`, seed 0, round 13 stepped 33 of them, from
    (0.499, 0.610) to (0.149, -0.933), and the fit failed; ordinary averaged steps were 0.6-9 long over the shipped
    targets, so a bound of 6 rejected ordinary rounds and moved a `denser` fit from +0.1% to +1.4%). A rejected
    round's Jacobians are left out of the averages (a firefly can sit in them as well as in the residual);
    `max_step_u`: a trust region for the rounds' steps (LM with step gain, and averaged): a step that would change
    some unconstrained coordinate by more than this is shortened along its direction to this length in that
    coordinate (1 = a factor e in sigma_t; near the ends of a bounded range, where the coordinate's map to the
    parameter is flat, the linearised step is not to be trusted: measured, a droplet fit at d = 5.06 in (5, 50)
    stepped to 50 in one averaged round and stayed there, and an LM round with step gain 4 went from 9.5 to 5.3
    for a truth of 8; the fits of docs/results/fit_models.md start within 0.85 of their truths in every
    coordinate but the diameter's, 1.4); `decorrelate`: LM residuals take their value at the reference from a second,
    independent key (`Problem.offsets`; off = the plain fixed-key residual, biased by the render's noise).

    The loop (docs/fitting.md): `burn_in` is the most approach rounds (LM, value render at `approach_spp_factor` x
    spp; the approach ends earlier when a step is within its own noise); then averaging rounds, at least
    `repeats + 1`, until the step is within its noise and the standard error is at most `precision` (relative
    units) or limited by the target's noise. `noise_weights`: weights from the noise model in the split and averaging
    rounds, `vbar^(-weight_power / 2)` with `vbar` each element's variance averaged over its
    `(2 weight_smoothing + 1)^2` neighbourhood (`gls_weights`; False: equal weights). Measured (docs/fitting.md, "Why
    these weights"): per-pixel GLS (power 1, no smoothing) covered the foreign suite's truths at 31% / 81% within 1 /
    2 se, equal weights at 75% / 94% but too imprecise for 2% in three of its seven fits, the default (smoothing 1,
    power 1/2) at 88% / 94% with 8 of its 9 cases as asked. `first_round`: "split" (default) makes round 0 a split-pass Gauss-Newton step
    like the later approach rounds (its compiled program is theirs), "lm" an optimistix Levenberg-Marquardt solve
    (value render at `approach_spp_factor` x spp; also the fallback of any round whose split pass is not finite or
    whose normal matrix is not positive definite)."""

    spp: int = 256
    seed: int = 0
    solver: str = "lm"
    max_rounds: int = 20
    repeats: int = 2
    burn_in: int = 6
    rtol: float = 1e-2
    atol: float = 1e-3
    max_steps: int = 40
    chi2_max: float = 3.0
    decorrelate: bool = True
    value_spp_factor: int = 32
    max_gain: float = 4.0
    max_se: float = 0.1
    average_jacobians: int = 20
    max_step_se: float = 15.0
    max_step_u: float = 1.0
    approach_spp_factor: int = 4
    approach_split_factor: int = 8
    precision: float = 0.01
    noise_weights: bool = True
    first_round: str = "split"
    weight_smoothing: int = 1
    weight_power: float = 0.5

    def __post_init__(self):
        if self.first_round not in ("split", "lm"):
            raise FitError(f"first_round must be 'split' or 'lm', got {self.first_round!r}")


@dataclass
class FitResult:
    names: list
    params: dict
    init: dict
    success: bool
    messages: list
    uncertainty: dict
    iterations: int
    rounds: int
    wall_s: float
    history: list = field(default_factory=list)
    chi2: float = float("nan")
    correlation: list | None = None
    information: dict | None = None
    timing: list = field(default_factory=list)
    cov_target: list | None = None
    """The estimate's covariance from the targets' noise alone (parameters' units; `C_T`): what more views, rather
    than more rounds, can shrink."""

    def to_json(self) -> dict:
        return {
            "params": self.params, "init": self.init, "success": self.success, "messages": self.messages,
            "uncertainty": self.uncertainty, "iterations": self.iterations, "rounds": self.rounds,
            "wall_s": self.wall_s, "chi2": self.chi2, "correlation": self.correlation,
            "information": self.information, "timing": self.timing, "history": self.history,
            "cov_target": self.cov_target,
        }


def _solver(cfg: FitConfig):
    if cfg.solver == "lm":
        return optx.LevenbergMarquardt(rtol=cfg.rtol, atol=cfg.atol)
    if cfg.solver == "bfgs":
        return optx.BFGS(rtol=cfg.rtol, atol=cfg.atol)
    raise FitError(f"--solver must be lm or bfgs, got {cfg.solver!r}")


class Problem:
    """Residuals of all views as one function of the unconstrained parameters `y`; built once per fit so that
    optimistix compiles it once (the key and the reference medium are arguments, not closure constants)."""

    def __init__(self, views: list[View], names: list[str], cfg: FitConfig, on_eval: Callable | None = None):
        self.views, self.names, self.cfg = views, names, cfg
        self.scales = [float(max(np.mean(v.target), 1e-8)) for v in views]
        self.n = sum(v.target.size for v in views)
        self.targets = [jnp.asarray(v.target) for v in views]
        self.on_eval = on_eval

    def images(self, y, key, ref, estimator="proposal", spp=None, variance=False):
        """One render per view at the unconstrained parameters `y` (a list of `(h, w, 3)` images; with `variance`,
        of `(image, per-pixel variance of its estimate)` pairs)."""
        vals = from_unconstrained(self.names, y)
        out = []
        for i, v in enumerate(self.views):
            scene = apply(v.scene, vals)
            out.append(jaxfog.render(scene, jax.random.fold_in(key, i), spp or self.cfg.spp,
                                     estimator=estimator, proposal=ref, variance=variance))
        return out

    def value(self, y, key, ref, factor):
        """The residual's value at `y` from a render at `factor` x spp with `key`, and the per-element variance of
        the residual of ONE render at spp there (the render's own per-pixel sample variance, times `factor`), both
        in the scaled units of `residuals`: `(e, u)` as float64 vectors."""
        outs = self.images(y, key, ref, spp=self.cfg.spp * factor, variance=True)
        e = np.concatenate([((np.asarray(img, np.float64) - np.asarray(t, np.float64)) / s).ravel()
                            for (img, _), t, s in zip(outs, self.targets, self.scales)]) / math.sqrt(self.n)
        u = np.concatenate([(np.asarray(var, np.float64) * factor / (s * s)).ravel()
                            for (_, var), s in zip(outs, self.scales)]) / self.n
        return e, u

    def value_and_jacobian(self, y, key, ref, factor):
        """`value` and the scaled residual's Jacobian from ONE forward-mode pass at `factor` x spp with `key`:
        `(e, u, J)` (float64). A forward-mode pass costs ~1.2x a plain render for two parameters (measured, 8 x 8 px,
        2,048 spp: 1.92-2.16 s against 1.56-1.77 s CPU), so the Jacobian comes almost free with the value render,
        from its `factor` x spp samples instead of spp."""
        def f(yy):
            outs = self.images(yy, key, ref, spp=self.cfg.spp * factor, variance=True)
            flat = jnp.concatenate([(img / s).ravel() for (img, _), s in zip(outs, self.scales)])
            return flat, (jax.lax.stop_gradient(flat), [jax.lax.stop_gradient(var) for _, var in outs])
        J, (flat, var) = jax.jacfwd(f, has_aux=True)(y)
        t = np.concatenate([(np.asarray(t, np.float64) / s).ravel() for t, s in zip(self.targets, self.scales)])
        e = (np.asarray(flat, np.float64) - t) / math.sqrt(self.n)
        u = np.concatenate([(np.asarray(v, np.float64) * factor / (s * s)).ravel()
                            for v, s in zip(var, self.scales)]) / self.n
        return e, u, np.asarray(J, np.float64) / math.sqrt(self.n)

    def jacobian(self, y, key, ref):
        """The scaled residual's Jacobian at `y` (`(n, k)`, float64) from the "proposal" render with `key`."""
        J = jax.jacfwd(lambda yy: jnp.concatenate([(img / s).ravel() for img, s in
                                                   zip(self.images(yy, key, ref), self.scales)]))(y)
        return np.asarray(J, np.float64) / math.sqrt(self.n)

    def offsets(self, y_ref, key_jac, key_val, ref, factor=None):
        """Per-view constant `c = I(y_ref; key_val) - I(y_ref; key_jac)` that turns the residual of one solve into
        `I(y; key_jac) + c - T = [I(y; key_jac) - I(y_ref; key_jac)] + I(y_ref; key_val) - T`: the same smooth,
        deterministic function of `y` (its Jacobian is that of the "proposal" render with `key_jac`), but its value at
        the reference comes from an independent key. At a fixed point of the re-centring (`y = y_ref`) the normal
        equations read `J(key_jac)^T (I(key_val) - T) = 0`, whose expectation over the two independent keys is
        `E[J]^T (E[I] - T)`: the noise of the render no longer biases the estimate (with one key, the fit minimises
        `|E[I] - T|^2 + Var[I]` and `Var[I]` depends strongly on g near a spot light)."""
        factor = factor or self.cfg.value_spp_factor
        a = self.images(y_ref, key_val, ref, spp=self.cfg.spp * factor, variance=True)
        b = self.images(y_ref, key_jac, ref)
        self.last_u = np.concatenate([(np.asarray(var, np.float64) * factor / (s * s)).ravel()
                                      for (_, var), s in zip(a, self.scales)]) / self.n
        return [jax.lax.stop_gradient(x - z) for (x, _), z in zip(a, b)]

    def cross_loss(self, y, args):
        """Unbiased loss for noisy renders: mean over pixels of `(A - T)(B - T)` (relative), with A and B rendered
        with two independent keys. Its expectation is the squared bias `(E[A] - T)^2` alone, whereas `(A - T)^2` also
        carries `Var[A]`, which varies with the parameters (strongly with g near a spot light) and pulls a
        least-squares fit toward parameters where the render is less noisy."""
        key, ref, _ = args
        ka, kb = jax.random.split(key)
        A = self.images(y, ka, ref)
        B = self.images(y, kb, ref)
        loss = sum(jnp.mean((a - t) * (b - t)) / (s * s) for a, b, t, s in zip(A, B, self.targets, self.scales))
        return loss / len(self.views)

    def residuals(self, y, args):
        key, ref, offsets = args
        imgs = self.images(y, key, ref)
        offsets = offsets if offsets is not None else [0.0] * len(imgs)
        r = jnp.concatenate([((img + c - t) / s).ravel()
                             for img, c, t, s in zip(imgs, offsets, self.targets, self.scales)])
        # no progress callback in here: a program with a host callback (jax.debug.callback) is not written to the
        # persistent compilation cache (measured: the first LM solve took 25.5 s CPU on a warm cache with one, 8.7 s
        # without); the progress line comes after each solve instead (fit_views.solve)
        return r / math.sqrt(self.n)


def _reference(views: list[View], values: dict) -> jaxfog.HomogeneousMedium:
    """The proposal medium at the current estimate (parameters not being fitted keep the scene's values)."""
    med = apply(views[0].scene, values).medium
    return jax.lax.stop_gradient(med)


def fit_views(views: list[View], names: list[str], init: dict, cfg: FitConfig, log: Callable = print) -> FitResult:
    """Fit `names` starting from `init` (a value for each name) to all `views` jointly. Never raises on a failed
    fit: the result says so (`success`, `messages`)."""
    if not views:
        raise FitError("no targets given")
    for v in views:
        if v.scene.medium is None and set(names) & {"sigma_t", "g", "albedo"}:
            raise FitError(f"{v.name}: the scene has no medium to fit")
    t_start = time.perf_counter()
    c_start = time.process_time()
    log(f"(process CPU before the fit, imports, loading and checks: {c_start:.1f} s)")
    timing: list[dict] = []  # per round: wall and CPU seconds since the fit began
    history: list[dict] = []
    state = {"round": 0, "evals": 0}

    def on_eval(y, loss):
        state["evals"] += 1
        vals = {n: float(SPECS[n].from_u(jnp.asarray(y[i]))) for i, n in enumerate(names)}
        history.append({"round": state["round"], "eval": state["evals"], "loss": float(loss), **vals})
        log(f"  round {state['round']:d} eval {state['evals']:3d}  loss {float(loss):.6e}  "
            + "  ".join(f"{n} {vals[n]:.5f}" for n in names))

    problem = Problem(views, names, cfg, on_eval)
    solver = _solver(cfg)
    base_key = jax.random.key(cfg.seed)
    y = to_unconstrained(names, init)
    messages: list[str] = []
    iterations = 0
    solve_ok = True
    estimates: list[np.ndarray] = []

    sizes = [v.target.size for v in views]
    K_avg = cfg.value_spp_factor
    K_app = max(1, min(cfg.approach_spp_factor, K_avg))
    K_split = max(1, min(cfg.approach_split_factor, K_avg))
    state["noise"] = []  # per round: the per-element variance of one render at `spp` (`Problem.value`, `.offsets`)

    def noise_model():
        """Per-element variances of the (scaled) residual: the target's and one render's at `spp`. The render's, u,
        from the rounds' value renders' own per-pixel sample variances (`render(..., variance=True)`, K x spp samples
        each; the mean of the last `NOISE_ROUNDS` rounds). The target's from its header's
        spp (the same per-sample variance as the fit's renders, `1 / (spp_T f^2)` of it: a pooled pixel holds
        f^2 spp_T samples) or, without one (a foreign target), its level from the target itself (`block_noise`,
        the view's mean) and its shape over the pixels from the renders' `u`: the per-pixel block estimate is
        largest exactly where the target's own noise came out large (a firefly), and weights from it would give the
        target's fireflies less say than its dark draws, biasing the fit toward the typical, darker image (seen on
        Mitsuba targets of a spot light: most fit blocks 3.4-3.6% darker than their expectation)."""
        u = np.mean(state["noise"][-NOISE_ROUNDS:], axis=0) if state["noise"] else None
        s2_T, at = [], 0
        for v, sc, nv in zip(views, problem.scales, sizes):
            tv = v.target_var if v.target_var is not None else np.zeros(v.target.shape)
            own = np.asarray(tv, np.float64).ravel() / (sc * sc * problem.n)
            if v.target_spp and u is not None:
                s2_T.append(u[at:at + nv] * cfg.spp / (v.target_spp * v.downscale ** 2))
            elif u is not None and np.mean(u[at:at + nv]) > 0:
                s2_T.append(u[at:at + nv] * (np.mean(own) / np.mean(u[at:at + nv])))
            else:
                s2_T.append(own)
            at += nv
        return (u if u is not None else np.zeros(problem.n)), np.concatenate(s2_T)

    def solve_spd(A, b):
        """`A^-1 b` for a symmetric positive definite A, by lineax's Cholesky (`throw=False`); None where A is not
        positive definite (the factorisation gives a non-finite solution, or lineax reports failure)."""
        op = lx.MatrixLinearOperator(jnp.asarray(A, jnp.float32), lx.positive_semidefinite_tag)
        sol = lx.linear_solve(op, jnp.asarray(b, jnp.float32), lx.Cholesky(), throw=False)
        x = np.asarray(sol.value, np.float64)
        if sol.result != lx.RESULTS.successful or not np.all(np.isfinite(x)) or np.any(np.linalg.eigvalsh(A) <= 0):
            return None
        return x

    def sandwich(Ja, Jb, A, var):
        """Covariance `A^-1 B A^-1` of a step `-A^-1 J^T e` whose residual e has per-element variance `var`, given
        the Jacobians: `B = (Ja^T diag(var) Ja + Jb^T diag(var) Jb) / 2`, the mean of the two halves' forms
        (positive semi-definite; for a split step `-(Ja^T eb + Jb^T ea) / 2` it is the exact covariance, for a step
        with `(Ja + Jb) / 2` an upper bound). (Before: the two-key `sym(Ja^T diag(var) Jb)`, an unbiased estimate of
        `E[J]^T diag(var) E[J]` but indefinite where the Jacobians are noisy; with its negative eigenvalues clipped it
        came out singular, and a step along the clipped direction measured a few standard errors however long:
        the main job's first averaging round, seed 4, went from g 0.56 to 0.04 at 3.3 of them.)"""
        B = 0.5 * (Ja.T @ (var[:, None] * Ja) + Jb.T @ (var[:, None] * Jb))
        Ainv = np.linalg.inv(A)
        return Ainv @ B @ Ainv

    def solve(y0, round_id, factor, approach=False):
        nonlocal iterations, solve_ok
        state["round"] = round_id
        key = jax.random.fold_in(base_key, round_id)
        ref = _reference(views, from_unconstrained(names, y0))
        if cfg.solver == "lm":
            key, key_val = jax.random.split(key)
            if cfg.decorrelate:
                offsets = problem.offsets(y0, key, key_val, ref, factor)
            else:
                offsets = [jnp.zeros_like(t) for t in problem.targets]
            args = (key, ref, offsets)
            sol = optx.least_squares(problem.residuals, solver, y0, args=args, throw=False,
                                     max_steps=cfg.max_steps)
        else:
            args = (key, ref, None)
            sol = optx.minimise(problem.cross_loss, solver, y0, args=args, throw=False,
                                max_steps=cfg.max_steps)
        steps = int(sol.stats["num_steps"])
        iterations += steps
        # the solution as a plain host array: the solver's output carries the 2-device sharding of its program, and
        # a render from sharded parameters is a new program for jit (measured: one more trace, lowering and cache
        # load of a render program, ~1.2 s per fit)
        y_sol = jnp.asarray(np.asarray(sol.value))
        if problem.on_eval is not None:  # the progress line: the loss at the solve's end (one cheap render)
            fn = problem.residuals if cfg.solver == "lm" else problem.cross_loss
            out = np.asarray(fn(y_sol, args), np.float64)
            problem.on_eval(y_sol, float(np.sum(out * out)) if out.ndim else float(out))
        ok = sol.result == optx.RESULTS.successful
        if not ok and approach:
            # an approach round only moves the estimate toward the solution and the later rounds re-solve from
            # there: its LM stopping at `max_steps` is noted, not a failure (measured: the 7-parameter chromatic fit
            # reported failure for round 0's LM at 40 steps while every estimate ended within 0.3% / 0.0025 and
            # within 1 standard error of the truth); the stopping rule and the checks judge the fit
            messages.append(f"round {round_id} (approach): the LM solve stopped before converging "
                            f"({optx.RESULTS[sol.result]}) after {steps} steps; the later rounds re-solved")
        elif not ok:
            solve_ok = False
            messages.append(f"round {round_id}: solver did not converge ({optx.RESULTS[sol.result]}) in {steps} steps")
        y_new = y_sol
        state["normal"] = None
        state["gain"] = None
        if cfg.solver == "lm" and cfg.decorrelate:
            y_new = unshrink(y0, y_sol, args, jax.random.fold_in(key_val, 1), factor)
        step = _trust_region(np.asarray(y_new, np.float64) - np.asarray(y0, np.float64), cfg.max_step_u, log)
        y_new = jnp.asarray(np.asarray(y0, np.float64) + step, dtype=jnp.asarray(y0).dtype)
        return y_new, args

    def unshrink(y0, y_lm, args, key3, factor):
        """Undo the shrinkage of a decorrelated LM step. The step solves `J1^T J1 d = -J1^T e` with the Jacobian
        `J1` of one key; its noise inflates `J1^T J1` by the Jacobian's variance, so the step is a fraction of the
        step with the expected Jacobian (`E[J]^T E[J] d = -E[J]^T e`); for g near a spot light that fraction was
        measured at 0.1-0.3 per round. `A = sym(J1^T J3)`, with `J3` from a third independent key, is an unbiased
        estimate of `E[J]^T E[J]` (averaged over the last 5 rounds); the step is scaled by `G = A^-1 J1^T J1` (eigenvalues clipped to
        [1, max_gain]; no scaling where A is not positive definite). Also keeps `A` for the uncertainty, the
        Jacobian pair for the averaged rounds and the pair of residuals at `y0` for the noise model."""
        J1 = problem.jacobian(y0, args[0], args[1])
        J3 = problem.jacobian(y0, key3, args[1])
        if not (np.all(np.isfinite(J1)) and np.all(np.isfinite(J3))):
            log("  (step not rescaled: non-finite Jacobian)")
            return y_lm
        state["noise"].append(problem.last_u)
        state.setdefault("J_list", []).extend([(J1, 1), (J3, 1)])
        M = J1.T @ J1
        state.setdefault("A_list", []).append(0.5 * (J1.T @ J3 + J3.T @ J1))
        A = np.mean(state["A_list"][-5:], axis=0)
        if np.any(np.linalg.eigvalsh(A) <= 0):
            log("  (step not rescaled: the two-key normal matrix is not positive definite)")
            return y_lm
        state["normal"], state["pair"] = A, (J1, J3)
        state["gain"] = np.eye(len(names))
        if cfg.max_gain <= 1.0:
            return y_lm
        w, V = np.linalg.eig(np.linalg.solve(A, M))
        if np.any(np.abs(w.imag) > 1e-9 * np.abs(w.real).max()):
            return y_lm
        w = np.clip(w.real, 1.0, cfg.max_gain)
        G = (V.real * w) @ np.linalg.inv(V.real)
        state["gain"] = G
        step = G @ (np.asarray(y_lm, np.float64) - np.asarray(y0, np.float64))
        log(f"  step gain (eigenvalues of A^-1 J1^T J1, clipped to [1, {cfg.max_gain:g}]): "
            + ", ".join(f"{x:.2f}" for x in w))
        return jnp.asarray(np.asarray(y0, np.float64) + step, dtype=jnp.asarray(y0).dtype)

    def split_step(y0, round_id, wvec, K, reject):
        """One Gauss-Newton step from `y0` from ONE pass at K x spp rendered as two halves with independent keys,
        each half's Jacobian multiplying the other half's residual: `-A^-1 (Ja^T W eb + Jb^T W ea) / 2`, `A =
        sym(Ja^T W Jb)`: unbiased (no Jacobian shares its residual's samples) and without `Var[J]` in `A`, at the
        cost of one forward-mode pass. For the approach rounds after the first (K = `approach_split_factor`) and
        the first averaging round (K_avg), which has no earlier Jacobian of its precision. Returns None where the
        pass is not finite or `A` is not positive definite (the caller falls back to LM)."""
        state["round"] = round_id
        key, key_val = jax.random.split(jax.random.fold_in(base_key, round_id))
        ref = _reference(views, from_unconstrained(names, y0))
        args = (key, ref, None)
        state["warm_up"] = False
        ka, kb = jax.random.split(key_val)
        e_a, u_a, J_a = problem.value_and_jacobian(y0, ka, ref, K // 2)
        e_b, u_b, J_b = problem.value_and_jacobian(y0, kb, ref, K - K // 2)
        if not all(np.all(np.isfinite(x)) for x in (e_a, e_b, J_a, J_b)):
            return None
        wa, wb = (K // 2) / K, (K - K // 2) / K
        e, u_now, J_now = wa * e_a + wb * e_b, wa * u_a + wb * u_b, wa * J_a + wb * J_b
        state["noise"].append(u_now)
        state.setdefault("J_list", [])
        Ja, Jb = J_a * wvec[:, None], J_b * wvec[:, None]
        A = 0.5 * (Ja.T @ Jb + Jb.T @ Ja)
        step = solve_spd(A, -0.5 * (Ja.T @ (e_b * wvec) + Jb.T @ (e_a * wvec)))
        if step is None:
            log("  (split-pass normal matrix not positive definite; an LM round instead)")
            return None
        return finish_step(y0, step, A, Ja, Jb, J_now, e, wvec, args, K, reject)

    def averaged_step(y0, round_id, wvec):
        """One Gauss-Newton step from `y0` with averaged Jacobians, for the averaging rounds. The noise of a
        one-key Jacobian `J1` enters an LM round's step multiplied by the distance to the solution, and the step gain
        (`unshrink`) multiplies it again along the weakly determined direction: the rounds wander along the ridge of
        correlated parameters (measured on denser fog: round-to-round spread 3-4x what the residual's noise explains).
        Here the step is `-A^-1 Jbar^T W e`, with `e` the residual at `y0` from this round's key `key_val` at K_avg x
        spp, `Jbar_a`, `Jbar_b` the spp-weighted means of the earlier rounds' Jacobians (the last
        `average_jacobians`, alternately assigned to the two halves, each from its own key), `Jbar` their mean,
        `A = sym(Jbar_a^T W Jbar_b)` (an estimate of `E[J]^T W E[J]` without the noise's `Var[J]`) and W the noise
        weights (`wvec`, squared). The fixed point: `E[J]^T W (E[I] - T) = 0`. Returns None where `A` is not
        positive definite or fewer than two earlier Jacobians exist (the caller falls back to LM)."""
        state["round"] = round_id
        key, key_val = jax.random.split(jax.random.fold_in(base_key, round_id))
        ref = _reference(views, from_unconstrained(names, y0))
        # one forward-mode pass at K_avg x spp: the residual's value, its per-pixel variance (the noise model's, for
        # the later rounds' weights) and a Jacobian. The step takes the value with the Jacobians of EARLIER rounds
        # only (independent keys: a Jacobian and a residual from the same samples are correlated, which would bias
        # the fixed point), split into two halves of independent keys for the two-key normal matrix. This round's
        # Jacobian joins the list for the next rounds. (Before: two extra Jacobians at spp per round; their noise,
        # 32x the variance of this one's, multiplied the residual's noise in `Jbar^T W e` and made the rounds
        # wander 5-10 of their standard errors: measured on the main job, the same rounds' steps with an exact
        # Jacobian landed 2-3x closer to the truth.)
        js = state.setdefault("J_list", [])  # (Jacobian, its spp factor): the approach's at 1, these at K_avg
        good = [x for x in js[-cfg.average_jacobians:] if x[1] == K_avg]  # this phase's: the approach's are 32x noisier
        args = (key, ref, None)
        state["warm_up"] = False
        if not good and K_avg >= 2:
            # the first averaging round has no earlier Jacobian of this precision (the approach's have 8-32x the
            # variance: with them the main job's first averaged step went from (0.503, 0.594) to (0.465, 0.521)),
            # and a step with a Jacobian from the residual's own samples is biased (measured: to (0.490, 0.570)):
            # a split pass (`split_step`; before: the round rendered one pass and stayed put)
            return split_step(y0, round_id, wvec, K_avg, reject=True)
        e, u_now, J_now = problem.value_and_jacobian(y0, key_val, ref, K_avg)
        if not (np.all(np.isfinite(e)) and np.all(np.isfinite(J_now))):
            return None
        state["noise"].append(u_now)
        if not good:  # K_avg 1: no split; stay put once and keep the Jacobian
            js.append((J_now, K_avg))
            state["warm_up"] = True
            state["step_len"] = 0.0
            return y0, args
        elif len(good) == 1:
            # one earlier Jacobian of this precision: it alone multiplies the residual (independent of it); this
            # round's own enters only the normal matrix's second factor (measured: with the approach's noisy pair in
            # the two halves instead, the second averaged step of the main job was 14 of its standard errors long)
            Jg, Ja, Jb = good[0][0], good[0][0], J_now
        else:
            def mean(half):  # weighted by spp: a Jacobian's variance is inversely proportional to its samples
                return sum(J * f for J, f in half) / sum(f for _, f in half)

            Ja, Jb = mean(good[0::2]), mean(good[1::2])
            Jg = 0.5 * (Ja + Jb)
        Jg, Ja, Jb = Jg * wvec[:, None], Ja * wvec[:, None], Jb * wvec[:, None]
        ew = e * wvec
        A = 0.5 * (Ja.T @ Jb + Jb.T @ Ja)
        step = solve_spd(A, -Jg.T @ ew)
        if step is None:
            log("  (averaged Jacobians: normal matrix not positive definite; an LM round instead)")
            js.append((J_now, K_avg))
            state["warm_up"] = False
            return None
        return finish_step(y0, step, A, Ja, Jb, J_now, e, wvec, args, K_avg, True)

    def finish_step(y0, step, A, Ja, Jb, J_now, e, wvec, args, K, reject):
        """The end of an averaged round: its step's length in its own standard errors, outlier rejection, the
        Jacobian kept for the next rounds; returns `(y_new, args)`."""
        nonlocal iterations
        js = state["J_list"]
        state["normal"], state["pair"] = A, (Ja, Jb)
        # the step's noise: this round's value render against the previous round's (the target's noise is common to
        # both and cancels in the difference of two rounds' estimates)
        # (`sandwich`: given the Jacobians; the two-key form it replaced made a split approach step of the main job
        # read 5e8 standard errors)
        u, _ = noise_model()
        C_step = 2.0 * sandwich(Ja, Jb, A, u / K * wvec ** 2)
        length = _mahalanobis(step, C_step)
        if reject and state.get("C_R_prev") is not None:
            # also in the previous round's noise (scaled to this round's samples): where this round's normal matrix
            # is nearly singular (two noisy Jacobians), its own C_step is as inflated as its step, and the length in
            # it stays small (measured: the main job's first averaging round, seed 4, went from g 0.56 to 0.04 as a
            # step of 3.3 of its own standard errors; with this and the Jacobian-conditional sandwich it reads 47 and
            # is rejected)
            C_prev, K_prev = state["C_R_prev"]
            length = max(length, _mahalanobis(step, 2.0 * C_prev * (K_prev / K)))
        if reject and length > cfg.max_step_se and not state.get("rejected") and not state["warm_up"]:
            log(f"  (averaged step of {length:.0f} standard errors rejected: an outlier render; the round stays put)")
            step = np.zeros_like(step)
            state["rejected"] = True
            state["noise"].pop()  # the outlier render: its variance and Jacobian stay out of the next rounds
            J_now = None
        else:
            if reject and length > cfg.max_step_se and not state["warm_up"]:
                # twice in a row, with two independent keys: far from the solution, not an outlier; go
                log(f"  (averaged step of {length:.0f} standard errors taken: the second in a row)")
            state["rejected"] = False
        state["step_len"] = length
        if J_now is not None:
            js.append((J_now, K))
        iterations += 1
        step = _trust_region(step, cfg.max_step_u, log)
        y_new = jnp.asarray(np.asarray(y0, np.float64) + step, dtype=jnp.asarray(y0).dtype)
        if problem.on_eval is not None:  # the progress line: the residual at the round's starting point
            problem.on_eval(y0, float(e @ e))
        return y_new, args

    def gls_weights():
        """Per-element weights of the averaging rounds' residual: `1 / sqrt(v)`, with `v` the element's variance
        (the target's plus one value render's at K_avg x spp, `noise_model`), so the step is generalised least
        squares, the minimum-variance weighting (measured on the main job's views at the truth: 2.8x and 3.6x less
        variance in sigma_t and g than equal weights; docs/fitting.md). The variances come from earlier rounds'
        renders, so the weights are independent of the residual they weigh (weights from the same render would
        favour pixels whose noise happened to be low and bias the estimate). A variance is floored at
        `VAR_FLOOR` of the median (a pixel whose samples showed no spread must not take all the weight; a
        heavy-tailed pixel's variance is underestimated when no firefly was drawn). Each variance is first averaged
        over its neighbourhood in its view (`weight_smoothing`; fireflies come from regions, and one pixel's
        underestimate then carries less weight) and the weight is `v^(-weight_power / 2)` (1/2: half-way, in the
        logarithm, to equal weights; docs/fitting.md "Why these weights"). Normalised to mean square 1."""
        u, s2_T = noise_model()
        tot = s2_T + u / K_avg
        if cfg.weight_smoothing > 0:  # each view's variances averaged over (2r+1)^2 neighbouring pixels
            parts, at = [], 0
            for v in views:
                nv = v.target.size
                parts.append(box_mean(tot[at:at + nv].reshape(v.target.shape), cfg.weight_smoothing).ravel())
                at += nv
            tot = np.concatenate(parts)
        pos = tot[np.isfinite(tot) & (tot > 0)]
        if pos.size == 0:
            return ones
        tot = np.where(np.isfinite(tot), np.maximum(tot, VAR_FLOOR * float(np.median(pos))), np.inf)
        w = tot ** (-0.5 * cfg.weight_power)
        return w / math.sqrt(np.mean(w ** 2))

    def covariances(wvec, K):
        """(C_T, C_R): the covariance (unconstrained coordinates) of one round's estimate from the target's noise and
        from a value render at K x spp, by the sandwich with the current normal matrix and Jacobian pair."""
        if state.get("normal") is None or not state.get("pair"):
            return None, None
        Ja, Jb = state["pair"]
        if Ja.shape[0] != wvec.size:
            return None, None
        A = state["normal"]
        u, s2_T = noise_model()
        return sandwich(Ja, Jb, A, s2_T * wvec ** 2), sandwich(Ja, Jb, A, u / K * wvec ** 2)

    def to_params(C, y_at):
        d = jacobian_to_params(names, y_at)
        with np.errstate(invalid="ignore"):
            return C * np.outer(d, d)

    # ---- approach: LM rounds (optimistix) at a cheap value render, until a step is within its own noise; then
    #      averaging: Gauss-Newton rounds with averaged Jacobians and noise weights until the estimate is precise
    #      enough or limited by the target's own noise
    k = len(names)
    chi2_stop = _chi2_quantile(k, 0.95)
    ones = np.ones(problem.n)
    thetas: list[np.ndarray] = []
    averaging: list[np.ndarray] = []   # unconstrained estimates of the averaging rounds
    converged = False
    rounds = 0
    phase = "approach"
    wvec = ones
    C_T = C_R = None
    use_avg = cfg.solver == "lm" and cfg.decorrelate and cfg.average_jacobians > 0
    for r in range(cfg.max_rounds):
        rounds += 1
        y_prev = np.asarray(y, np.float64)
        stepped = None
        if use_avg and (phase == "average" or (K_split >= 2 and (r >= 1 or cfg.first_round == "split"))):
            if cfg.noise_weights and state["noise"]:  # from the earlier rounds' renders only: independent of
                wvec = gls_weights()                   # this round's residual (round 0: equal weights)
            if phase == "average":
                stepped = averaged_step(y, r, wvec)
            else:
                stepped = split_step(y, r, wvec, K_split, reject=False)
                if stepped is not None and r >= 1:  # trust region: no longer than the previous approach step
                    d = np.asarray(stepped[0], np.float64) - y_prev
                    n_d = float(np.linalg.norm(d))
                    if n_d > state["trust"] > 0:
                        log(f"  (approach step shortened to the previous step's length: {n_d:.3g} -> "
                            f"{state['trust']:.3g} in the unconstrained parameters)")
                        stepped = (jnp.asarray(y_prev + d * (state["trust"] / n_d), jnp.float32), stepped[1])
        if stepped is None:
            y, args = solve(y, r, K_app if phase == "approach" else K_avg, approach=phase == "approach")
            wv = ones
        else:
            y, args = stepped
            wv = wvec
        if phase == "approach":
            state["trust"] = float(np.linalg.norm(np.asarray(y, np.float64) - y_prev))
        theta = np.asarray([float(SPECS[n].from_u(y[i])) for i, n in enumerate(names)])
        thetas.append(theta)
        K_round = K_avg if (phase == "average" and stepped is not None) else K_split if stepped is not None else K_app
        C_T, C_R = covariances(wv, K_round)
        if C_R is not None and np.all(np.isfinite(C_R)):
            state["C_R_prev"] = (C_R, K_round)
        se_round = (np.sqrt(np.abs(np.diag(to_params(C_T + C_R, y)))) if C_T is not None
                    else np.full(k, np.nan))
        d = np.asarray(y, np.float64) - y_prev
        # the step in its own standard errors: two rounds' render noise (the target's cancels), through the step
        # gain of an LM round
        G = state.get("gain") if state.get("gain") is not None else np.eye(k)
        length = state.get("step_len") if stepped is not None else (
            _mahalanobis(d, 2.0 * G @ C_R @ G.T) if C_T is not None else np.inf)
        timing.append({"round": r, "phase": phase, "wall_s": time.perf_counter() - t_start,
                       "cpu_s": time.process_time() - c_start})
        log(f"round {r} ({phase}): " + "  ".join(f"{n} {theta[i]:.5f} (± {se_round[i]:.5f} per round)"
                                                  for i, n in enumerate(names))
            + f"  step {length:.1f} standard errors  [{timing[-1]['wall_s']:.1f} s, cpu {timing[-1]['cpu_s']:.1f} s]")
        if phase == "approach":
            # arrived: the step is within its own noise (chi^2 with k degrees of freedom, 95%)
            if (r >= 1 and length ** 2 <= chi2_stop) or r + 1 >= cfg.burn_in:
                phase = "average"
                # the averaged Jacobians only from rounds at the current estimate: the approach's earlier rounds
                # were far from it (main job: round 0 at (0.25, 0.3) for a solution at (0.5, 0.6)), and their
                # Jacobians in the average made the Gauss-Newton steps over- and undershoot (measured: averaging
                # rounds 5-9 standard errors apart, against 2-3 with only the last approach round's pair kept)
                state["J_list"] = state.get("J_list", [])[-2:]
                if not use_avg:
                    averaging.append(np.asarray(y, np.float64))
            continue
        if stepped is not None and (state.get("rejected") or state.get("warm_up")):
            continue  # the round stayed put, or its estimate shares its Jacobian's samples: not an averaged estimate
        averaging.append(np.asarray(y, np.float64))
        m = len(averaging)
        if m < cfg.repeats + 1 or C_T is None:
            continue
        if stepped is not None:  # the step test with C_R raised to the rounds' own spread where that is larger
            d_avg = np.asarray(averaging[-1]) - np.asarray(averaging[-2])
            length = _mahalanobis(d_avg, 2.0 * _spread_corrected(averaging, C_R))
        # stop: the last step within its own noise, and the mean's standard error below the precision goal or
        # limited by the target (the renders' share of the variance at most the target's)
        Cr_mean = _rounds_cov(averaging, C_R)
        se_rel = np.sqrt(np.abs(np.diag(to_params(C_T + Cr_mean, np.mean(averaging, axis=0))))) / \
            relative_scales(names, dict(zip(names, theta)))
        target_bound = np.all(np.diag(Cr_mean) <= np.diag(C_T))
        # out of reach: even with every round left, the renders' share shrinking as 1 / rounds, some standard error
        # stays above the goal (one view of an area light cannot give g to 0.01: measured, the suite's area_floor
        # case sat at 0.018 for 16 rounds and ended "still moving" within 1.3 standard errors of the truth); the
        # estimate is stable, so more rounds buy little: stop, and `max_se` judges whether it is pinned down
        m_left = m + (cfg.max_rounds - 1 - r)
        se_best = np.sqrt(np.abs(np.diag(to_params(C_T + Cr_mean * m / max(m_left, 1),
                                                   np.mean(averaging, axis=0))))) / \
            relative_scales(names, dict(zip(names, theta)))
        out_of_reach = m >= 2 * (cfg.repeats + 1) and np.any(se_best > cfg.precision)
        if length ** 2 <= chi2_stop and (np.all(se_rel <= cfg.precision) or target_bound or out_of_reach):
            if out_of_reach and not (np.all(se_rel <= cfg.precision) or target_bound):
                log(f"  (stopping: the precision goal {cfg.precision:g} is out of reach in the rounds left; "
                    "standard errors at the end would be " + ", ".join(f"{n} {x:.3g}" for n, x in
                                                                       zip(names, se_best)) + " relative)")
            converged = True
            break
    if not converged:
        messages.append(f"estimate still moving after {cfg.max_rounds} re-centring rounds")
        solve_ok = False
    if not averaging:
        averaging = [np.asarray(y, np.float64)]
    Y = np.asarray(averaging)
    y_mean = Y.mean(axis=0)
    est = np.asarray([float(SPECS[n].from_u(jnp.float32(y_mean[i]))) for i, n in enumerate(names)])
    estimates = [np.asarray([float(SPECS[n].from_u(jnp.float32(yy[i]))) for i, n in enumerate(names)]) for yy in Y]
    spread = np.std(estimates, axis=0, ddof=1) if len(estimates) > 1 else np.full(k, np.nan)
    if C_T is None:
        C_T, C_R = np.full((k, k), np.inf), np.full((k, k), np.inf)
    Cr_mean = _rounds_cov(averaging, C_R)
    cov_y = C_T + Cr_mean
    cov = to_params(cov_y, y_mean)
    se_target = np.sqrt(np.abs(np.diag(to_params(C_T, y_mean))))
    se_render = np.sqrt(np.abs(np.diag(to_params(Cr_mean, y_mean))))
    se_rounds = spread / math.sqrt(len(estimates))
    se_jac = np.sqrt(np.abs(np.diag(to_params(C_T + C_R, y_mean))))  # one round's
    se_final = np.sqrt(np.abs(np.diag(cov)))
    y_hat = jnp.asarray(y_mean, jnp.float32)
    values = {n: float(est[i]) for i, n in enumerate(names)}
    with np.errstate(invalid="ignore", divide="ignore"):
        try:
            fisher = np.linalg.inv(cov) if np.all(np.isfinite(cov)) else np.full((k, k), np.nan)
        except np.linalg.LinAlgError:  # e.g. a parameter saturated at its bound (d param / du = 0): no information
            fisher = np.full((k, k), np.nan)
    information = fisher_report(names, values, fisher)
    for line in information["summary"]:
        log("information: " + line)

    # ---- does the model explain the targets? residual vs the noise expected from two independent renders and the
    #      estimate's uncertainty
    k1, k2 = jax.random.split(jax.random.fold_in(base_key, 7777))
    ref = _reference(views, from_unconstrained(names, y_hat))
    # The residual may also hold the estimate's own uncertainty (cov_hat, in the unconstrained coordinates): its
    # share per block is J_b cov_hat J_b^T, with J_b the Jacobian of the (pooled) render at the estimate.
    with np.errstate(invalid="ignore", divide="ignore"):
        corr0 = cov / np.sqrt(np.outer(np.diag(cov), np.diag(cov)) + 1e-300)
    cov_hat = np.where(np.isfinite(cov_y), cov_y, 0.0)  # unknown uncertainty: the check uses the noise alone
    # a, b: plain renders at the fit's spp (the brightness check's program). Their noise, not the estimate's error,
    # must dominate the residual, so the check does not fail an estimate a few of its standard errors off (with a, b
    # at 4x spp, measured on the main job: 2.2x for an estimate 1.5-2 standard errors off). The estimate's share
    # of the residual, J cov J^T, takes the last round's Jacobian (its own K_avg x spp pass near the estimate).
    a = problem.images(y_hat, k1, ref)
    b = problem.images(y_hat, k2, ref)
    J_last = state["J_list"][-1][0] if state.get("J_list") else None  # unweighted, scaled like `residuals`
    Ja, at = [], 0
    for v, s in zip(views, problem.scales):  # back from the scaled, flattened residual Jacobian to image units
        nv = v.target.size
        Ja.append(np.zeros(v.target.shape + (k,)) if J_last is None or J_last.shape[0] != problem.n else
                  J_last[at:at + nv].reshape(v.target.shape + (k,)) * s * math.sqrt(problem.n))
        at += nv
    # Robust to heavy-tailed (firefly) noise: ratios of medians of squared pixel residuals. For a model that explains
    # the target, the residual (mean of the two renders - target) is distributed as the reference residual (mean of
    # the two renders - a third render at the target's samples per fit pixel, f^2 x the header's spp: one more
    # render per view, with key k3): the same noise, whatever its distribution. (Scaling (ia - ib)/2 by the
    # Gaussian 1 + 2 spp / (target_spp f^2) instead reads 1.1-4.5x, median 2.4, for renders of the truth
    # against the droplet halo target, whose pixels' noise is heavy-tailed and skewed at these spp; the reference
    # residual 0.8-1.5x, median 1.1: docs/results/fit_models.md.) The fit pixel's per-sample variance also holds the
    # sub-pixel variation, so the third render errs toward more noise than the pooled target's. A target without
    # spp in its header: (ia - ib)/2 plus the target's own block estimate of its noise. One ratio per view (its
    # three channels pooled) and one per channel (the views pooled): a grey model on a chromatic target fits the
    # channels' mean and leaves a residual of opposite sign in red and blue, which a per-channel ratio shows.
    # The third render has REF_SPP_FACTOR spp samples per fit pixel (not f^2 spp_T: 65,536 on the
    # main job, 8.4 M paths, ~55 s of a 130-s run), and its squared residual is scaled by the ratio of the two noise
    # levels, `(1 / (2 spp) + 1 / s_T) / (1 / (2 spp) + 1 / s_c)` (0.89 on the main job): the two renders a, b at
    # spp dominate the residual's noise, so the reference keeps its shape (skew, tail) from them.
    k3 = jax.random.fold_in(base_key, 7778)
    c, c_scale = [None] * len(views), [1.0] * len(views)
    if any(v.target_spp for v in views):
        # the reference render at REF_SPP_FACTOR x spp: the mean of that many renders at spp with independent keys
        # (the program of a and b, not one more compiled program; the mean of independent renders is the render at
        # their total samples)
        s_c = REF_SPP_FACTOR * cfg.spp
        parts = [problem.images(y_hat, jax.random.fold_in(k3, j), ref) for j in range(REF_SPP_FACTOR)]
        for i, v in enumerate(views):
            if v.target_spp:
                s_t = v.target_spp * v.downscale ** 2
                c[i] = np.mean([np.asarray(p[i], np.float64) for p in parts], axis=0)
                c_scale[i] = (0.5 / cfg.spp + 1.0 / s_t) / (0.5 / cfg.spp + 1.0 / s_c)
    num_px, den_px = [], []
    for v, ia, ib, ic, ja, cs in zip(views, a, b, c, Ja, c_scale):
        ia, ib, t = np.asarray(ia, np.float64), np.asarray(ib, np.float64), np.asarray(v.target, np.float64)
        jb = np.stack([np.asarray(ja[..., i], np.float64) for i in range(len(names))], axis=-1)
        par = np.einsum("...i,ij,...j->...", jb, cov_hat, jb)
        if v.target_spp:
            noise = cs * (0.5 * (ia + ib) - np.asarray(ic, np.float64)) ** 2
        else:
            noise = ((ia - ib) / 2.0) ** 2
            if v.target_var is not None:
                noise = noise + np.asarray(v.target_var, np.float64)
        num_px.append((0.5 * (ia + ib) - t) ** 2)
        den_px.append((noise, par))

    def ratio(nums, dens):
        num = np.median(np.concatenate([x.ravel() for x in nums]))
        den = (np.median(np.concatenate([d[0].ravel() for d in dens]))
               + np.median(np.concatenate([d[1].ravel() for d in dens])))
        return float(num / max(den, 1e-30))

    chi2s = [ratio([n], [d]) for n, d in zip(num_px, den_px)]
    chi2_channels = [ratio([n[..., c] for n in num_px], [(d[0][..., c], d[1][..., c]) for d in den_px])
                     for c in range(3)]
    log("model check (residual / expected noise): per view " + ", ".join(f"{v.name} {c:.2f}" for v, c in
                                                                        zip(views, chi2s))
        + "; per channel " + ", ".join(f"{ch} {c:.2f}" for ch, c in zip("rgb", chi2_channels)))
    chi2 = float(max(chi2s + chi2_channels))
    timing.append({"round": "check", "phase": "model check", "wall_s": time.perf_counter() - t_start,
                   "cpu_s": time.process_time() - c_start})
    explained = chi2 <= cfg.chi2_max
    if not explained:
        messages.append(
            f"the model does not explain the target(s): residual is {chi2:.1f}x the expected noise "
            f"(limit {cfg.chi2_max}); per view: " + ", ".join(f"{v.name} {c:.1f}" for v, c in zip(views, chi2s))
            + "; per channel: " + ", ".join(f"{ch} {c:.1f}" for ch, c in zip("rgb", chi2_channels))
        )
    at_bound = []
    for i, n in enumerate(names):
        if abs(float(y_hat[i])) > 6.0:  # e.g. |g| > 0.99999, sigma_t beyond e^±6 of 1
            at_bound.append(n)
    if at_bound:
        messages.append(f"parameters ran to the edge of their range: {at_bound}")

    loose = [n for i, n in enumerate(names)
             if not se_final[i] / (1.0 if n == "g" else max(abs(est[i]), 1e-12)) <= cfg.max_se]  # NaN: unknown
    if loose:
        messages.append(f"not pinned down by these targets at this budget (standard error above {cfg.max_se:g}"
                        f"{'' if loose == ['g'] else ' relative'}): {loose}; more spp, rounds or views")
        for n, text in instead(names, values, fisher, loose).items():
            messages.append(text)
    success = bool(solve_ok and explained and not at_bound and not loose)
    corr = corr0
    return FitResult(
        names=names,
        params={n: float(est[i]) for i, n in enumerate(names)},
        init={n: float(init[n]) for n in names},
        success=success,
        messages=messages,
        uncertainty={
            n: {"se_jacobian": float(se_jac[i]), "sd_repeats": float(spread[i]),
                "se_rounds": float(se_rounds[i]), "se_target": float(se_target[i]),
                "se_render": float(se_render[i]), "se": float(se_final[i])}
            for i, n in enumerate(names)
        },
        iterations=iterations,
        rounds=rounds,
        wall_s=time.perf_counter() - t_start,
        history=history,
        chi2=chi2,
        correlation=corr.tolist(),
        information=information,
        timing=timing,
        cov_target=to_params(C_T, y_mean).tolist() if np.all(np.isfinite(C_T)) else None,
    )


NOISE_ROUNDS = 4
"""The noise model's per-element render variance is the mean of the last this many rounds' estimates (each a
render's own per-pixel sample variance at K x spp samples): the rounds sit near one point once the approach has
ended, and more samples of a heavy-tailed pixel make its variance estimate less often too low."""

REF_SPP_FACTOR = 8
"""Samples per fit pixel of the model check's reference render, in multiples of the fit's spp: 8 makes its noise
variance 1/4 of the two check renders' mean's (the reference residual's squared scale `c_scale` is then 0.8 on the
main job); it is rendered as that many renders at spp (the check renders' compiled program)."""

VAR_FLOOR = 0.1
"""Floor of an element's variance in the weights (`gls_weights`), relative to the median element: at most ~3x the
median weight."""


def box_mean(img: np.ndarray, r: int) -> np.ndarray:
    """Mean of `img` (`(H, W, C)`) over the `(2r+1) x (2r+1)` pixels around each pixel, per channel; at the border
    over the pixels that exist (no padding values enter). A non-finite value stays as it is and out of its
    neighbours' means."""
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


def _trust_region(step, max_du: float, log: Callable = lambda *_: None) -> np.ndarray:
    """`step` (in the unconstrained coordinates) shortened along its direction so that no coordinate changes by more
    than `max_du` (unchanged when none does, or when `max_du` is not finite)."""
    step = np.asarray(step, np.float64)
    big = float(np.max(np.abs(step))) if step.size else 0.0
    if not (np.isfinite(max_du) and big > max_du):
        return step
    log(f"  (step shortened by {max_du / big:.2f}: a change of {big:.2f} in an unconstrained coordinate, "
        f"trust region {max_du:g})")
    return step * (max_du / big)


def _mahalanobis(d, C) -> float:
    """Length of the step `d` in standard errors of the covariance `C`: `sqrt(d^T C^-1 d)` (inf where C is singular
    or unknown)."""
    d = np.asarray(d, np.float64)
    if C is None or not np.all(np.isfinite(C)):
        return float("inf")
    try:
        return float(math.sqrt(max(float(d @ np.linalg.solve(C, d)), 0.0)))
    except np.linalg.LinAlgError:
        return float("inf")


def _chi2_quantile(k: int, p: float) -> float:
    """The p-quantile of chi^2 with k degrees of freedom: exact for k = 1, 2; Wilson-Hilferty above (within 0.6% for
    k >= 3 at p = 0.95; at k = 1 it would be 2.5% low)."""
    exact = {(1, 0.95): 3.841459, (2, 0.95): 5.991465, (1, 0.99): 6.634897, (2, 0.99): 9.210340}
    if (k, p) in exact:
        return exact[(k, p)]
    z = {0.95: 1.6448536, 0.99: 2.3263479}[p]
    a = 2.0 / (9.0 * k)
    return k * (1.0 - a + z * math.sqrt(a)) ** 3


def _spread_corrected(Y, C_R):
    """One round's render covariance `C_R`, raised per parameter to the rounds' own variance (`Y`, at least 3 rounds)
    where that is larger: the noise model's analytic `C_R` was measured ~2x short in standard deviation on the main
    job (its averaged steps were 1.5-4.7 of its standard errors, ~1.2 expected)."""
    Y = np.asarray(Y, np.float64)
    C = np.asarray(C_R, np.float64)
    if len(Y) >= 3:
        S = np.cov(Y.T, ddof=1).reshape(Y.shape[1], Y.shape[1])
        r = np.sqrt(np.maximum(np.diag(S), 0.0) / np.maximum(np.diag(C), 1e-300))
        r = np.where(np.isfinite(r), np.maximum(r, 1.0), 1.0)
        C = C * np.outer(r, r)
    return C


def _rounds_cov(Y, C_R):
    """Covariance of the mean of the averaging rounds' estimates `Y` from the renders' noise: each round's estimate
    carries its value render's noise C_R (Gauss-Newton from the previous estimate with averaged Jacobians: a full step,
    so the rounds' noise is independent, and the mean of m has C_R / m); where the rounds' own spread is larger
    than C_R says (heavy-tailed renders), the spread's variance is used for that parameter."""
    Y = np.asarray(Y, np.float64)
    m = len(Y)
    C = np.asarray(C_R, np.float64) / m
    if m >= 3:
        S = np.cov(Y.T, ddof=1).reshape(Y.shape[1], Y.shape[1]) / m
        r = np.sqrt(np.maximum(np.diag(S), 0.0) / np.maximum(np.diag(C), 1e-300))
        r = np.where(np.isfinite(r), np.maximum(r, 1.0), 1.0)
        C = C * np.outer(r, r)
        # successive rounds start where the last one ended: lag-1 autocorrelation rho inflates the variance of their
        # mean by (1 + rho) / (1 - rho) (AR(1); rho clipped to [0, 0.9], at most 19x)
        Yc = Y - Y.mean(axis=0)
        rho = np.sum(Yc[1:] * Yc[:-1], axis=0) / np.maximum(np.sum(Yc * Yc, axis=0), 1e-300)
        f = np.sqrt((1.0 + np.clip(rho, 0.0, 0.9)) / (1.0 - np.clip(rho, 0.0, 0.9)))
        C = C * np.outer(f, f)
    return C


def candidate_fisher(scene: jaxfog.Scene, names: list[str], values: dict, spp: int, target_samples: float | None,
                     key, noise: np.ndarray | None = None) -> np.ndarray:
    """The Fisher information (parameters' units) a target of `scene`'s view would add at the estimate `values`:
    `sym(Ja^T W Jb)` with Ja, Jb the Jacobians of the view's pixels (`"proposal"` renders at the estimate, `spp`
    samples each, two independent keys: no Monte Carlo `Var[J]` in it; negative eigenvalues clipped to 0) and `W`
    the inverse of the target's per-pixel noise variance, assumed to be the render's per-sample variance over
    `target_samples` samples per pixel, or `noise` (the per-element variance, e.g. a target's own block estimate)
    where given (floored at `VAR_FLOOR` of the median, as the fit's weights). `scene` at the resolution it would be
    fitted at. For `fitting.information.rank_views`."""
    y = to_unconstrained(names, values)
    d = jacobian_to_params(names, np.asarray(y))
    ref = _reference([View(scene, np.zeros((1, 1, 3)), "candidate")], values)
    Js, var = [], None
    for kk in jax.random.split(key):
        def f(yy, kk=kk):
            img, v = jaxfog.render(apply(scene, from_unconstrained(names, yy)), kk, spp, estimator="proposal",
                                   proposal=ref, variance=True)
            return img.ravel(), jax.lax.stop_gradient(v).ravel()
        J, v = jax.jacfwd(f, has_aux=True)(y)
        Js.append(np.asarray(J, np.float64) / d[None, :])
        var = np.asarray(v, np.float64) if var is None else 0.5 * (var + np.asarray(v, np.float64))
    noise = var * spp / float(target_samples) if noise is None else np.asarray(noise, np.float64).ravel()
    pos = noise[np.isfinite(noise) & (noise > 0)]
    if pos.size == 0:
        return np.full((len(names), len(names)), np.nan)
    noise = np.maximum(np.where(np.isfinite(noise), noise, np.inf), VAR_FLOOR * float(np.median(pos)))
    Ja, Jb = Js
    F = 0.5 * (Ja.T @ (Jb / noise[:, None]) + Jb.T @ (Ja / noise[:, None]))
    w, V = np.linalg.eigh(0.5 * (F + F.T))
    return (V * np.maximum(w, 0.0)) @ V.T
