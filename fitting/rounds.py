"""The fit's rounds as pure functions of named inputs: the Gauss-Newton step from two independent halves, its
covariance, the pixel weights, and the model check.

Notation (scaled units, `fitting.problem`): `e` the residual (render - target) per element, `J` its Jacobian in the
unconstrained coordinates, `w` per-element weights (the weight matrix is `W = diag(w^2)`), `u` each element's
per-sample render variance. A pass is rendered as two halves `a`, `b` with independent keys.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .problem import Pass, Problem, box_mean

MEDIAN_CHI2_1 = 0.454936
"""The median of chi^2 with one degree of freedom: `median(z^2)` of standard normal residuals."""


class Step(NamedTuple):
    """A Gauss-Newton step from a pair of independent halves and what it knows of its own noise.

    `delta` (k,): the step in the unconstrained coordinates; `A` (k, k) the two-key normal matrix; `cov` (k, k) the
    estimate's covariance from the residuals themselves (`robust_covariance`, with the leverage correction; the same
    array as `cov_robust`);
    `cov_render` the renders' noise's (`model_covariance` with the renders' own variances), `cov_target` the target
    noise model's; `r` (n,) the residual after the step (linearised); `J` (n, k) the halves' mean Jacobian;
    `var_render` (n,) the render's variance of each element of the mean residual; `quality` the smallest eigenvalue
    of the two-key normal matrix relative to the halves' own (`(Ja^T W Ja + Jb^T W Jb) / 2`, which also carries
    the Jacobians' noise): 1 for noise-free Jacobians, near 0 or below where their noise is as large as their
    signal along some direction (the step is then solved with the halves' own matrix: shorter, never wild; the
    covariances use the two-key matrix along the directions it resolves and call the others unresolved,
    `_information`); `nu` (k,) each parameter's effective number of pixels (`effective_pixels`)."""

    delta: np.ndarray
    A: np.ndarray
    cov: np.ndarray
    cov_render: np.ndarray
    cov_target: np.ndarray
    r: np.ndarray
    J: np.ndarray
    var_render: np.ndarray
    quality: float = 1.0
    cov_robust: np.ndarray | None = None
    nu: np.ndarray | None = None


def spd_solve(A: np.ndarray, b: np.ndarray) -> np.ndarray | None:
    """`A^-1 b` for a symmetric positive definite `A` (Cholesky); None where A is not positive definite."""
    try:
        L = np.linalg.cholesky(0.5 * (A + A.T))
    except np.linalg.LinAlgError:
        return None
    x = np.linalg.solve(L.T, np.linalg.solve(L, b))
    return x if np.all(np.isfinite(x)) else None


def weights(problem: Problem, u: np.ndarray | None, power: float, smoothing: int,
            render_spp: int | None = None) -> np.ndarray:
    """Per-element weights `w = v^(-power / 4)` (so `W = w^2 = v^(-power / 2)`), normalised to mean square 1, from the
    renders' per-sample variances `u` of EARLIER passes (independent of the residuals they weigh).

    `v` is `u` averaged over each pixel's `(2 smoothing + 1)^2` neighbourhood in its view (a heavy-tailed pixel's
    sample variance is too low where no firefly was drawn; its neighbours' are not all low) and floored at 0.1 of the
    median (no element gets more than ~3x the median weight at power 1/2). `power` 1 would be generalised least
    squares with exact variances, 0 equal weights; docs/fitting.md measures the choice. Equal weights where `u` is
    None."""
    if u is None or power == 0:
        return np.ones(problem.n)
    u = np.where(problem.valid > 0, u, np.nan)  # a masked pixel's zero variance is no neighbour's
    v = np.concatenate([box_mean(x, smoothing).ravel() for x in problem.split(u)])
    if render_spp:
        smooth = np.nan_to_num(v)  # the target's variance follows the renders' where it is known from them
        v = _view_levels(problem, v, problem.target_variance(smooth) + smooth / render_spp)
    pos = v[np.isfinite(v) & (v > 0)]
    if pos.size == 0:
        return np.ones(problem.n)
    v = np.where(np.isfinite(v), np.maximum(v, VAR_FLOOR * float(np.median(pos))), np.inf)
    w = v ** (-0.25 * power)
    return w / math.sqrt(np.mean(w ** 2))


def _view_levels(problem: Problem, v: np.ndarray, total: np.ndarray) -> np.ndarray:
    """`v` (the renders' per-sample variances, smoothed) rescaled per view to the mean of `total` (the residual's
    expected variance: the target's plus an estimate pass's render): the pattern within a view from the renders,
    its level from the target's noise as well. For a jaxfog target `total` is proportional to `v` and nothing
    changes; for another renderer's target the views' levels follow their own noise."""
    out, at = v.copy(), 0
    for view in problem.views:
        sl = slice(at, at + view.target.size)
        ok = np.isfinite(v[sl]) & (problem.valid[sl] > 0)
        if np.any(ok) and np.mean(v[sl][ok]) > 0:
            out[sl] = v[sl] * (np.mean(total[sl][ok]) / np.mean(v[sl][ok]))
        at += view.target.size
    return out


VAR_FLOOR = 0.1
"""An element's variance in the weights is at least this fraction of the median element's."""


def normal_matrix(Ja: np.ndarray, Jb: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The two-key normal matrix `sym(Ja^T W Jb)`: an unbiased estimate of `E[J]^T W E[J]` without the Jacobians'
    own noise `Var[J]` (which a one-key `J^T W J` carries, and which shortens every step)."""
    W = w * w
    M = Ja.T @ (W[:, None] * Jb)
    return 0.5 * (M + M.T)


def per_pixel(x: np.ndarray, pixel_of: np.ndarray) -> np.ndarray:
    """Sums of `x` (`(n,)` or `(n, k)`, one row per element) over each pixel's elements: `(P,)` or `(P, k)`."""
    out = np.zeros((int(pixel_of.max()) + 1,) + x.shape[1:])
    np.add.at(out, pixel_of, x)
    return out


def model_covariance(A_inv: np.ndarray, J: np.ndarray, w: np.ndarray, var: np.ndarray,
                     pixel_of: np.ndarray) -> np.ndarray:
    """The sandwich `A^-1 B A^-1` of a weighted least-squares step whose residual has elements of variance `var`,
    independent between pixels and fully correlated between a pixel's channels (its three channels are estimated
    from the same paths; for grey media and white lights they move together): `B = sum_p s_p s_p^T` with
    `s_p = sum_c J_c W_c sqrt(var_c)` over pixel p's channels. (Channels taken as independent instead would
    understate a grey fit's variance up to 3x.)"""
    W = w * w
    S = per_pixel(J * (W * np.sqrt(np.maximum(var, 0.0)))[:, None], pixel_of)
    return A_inv @ (S.T @ S) @ A_inv


def brightness_covariance(A_inv: np.ndarray, J: np.ndarray, w: np.ndarray, B: np.ndarray | None) -> np.ndarray:
    """The covariance of a weighted least-squares step from independent unit-variance noises that move the residual
    by the columns of `B` (`(n, V)`: each a view's brightness by its heavy tail's spread,
    `fitting.problem.Problem.brightness_noise`): `A^-1 (J^T W B) (J^T W B)^T A^-1`; zeros where `B` is None."""
    k = J.shape[1]
    if B is None:
        return np.zeros((k, k))
    S = A_inv @ (J.T @ ((w * w)[:, None] * B))
    return S @ S.T


def robust_covariance(A_inv: np.ndarray, J: np.ndarray, w: np.ndarray, r: np.ndarray, pixel_of: np.ndarray,
                      leverage: bool = False) -> np.ndarray:
    """The step's covariance from its own residuals `r` (the cluster-robust sandwich: a pixel's three channels share
    their paths, so each pixel is one cluster): `A^-1 B A^-1`, `B = P / (P - k) sum_p s_p s_p^T`, `s_p` the sum over
    pixel p's elements of `J^T W r`. It needs no noise model: `E[r^2]` is the target's variance plus the renders',
    whatever their distribution, and a model that misses the target by more than the noise widens it. With
    `leverage`, each pixel's sum is divided by `sqrt(1 - h_p)` instead of the `P / (P - k)` factor (`h_p` the
    pixel's share of the fit, `sum_c W J A^-1 J^T`, at most 0.9): the CR2 correction (Bell and McCaffrey 2002), under
    which the sandwich is unbiased where the noise model holds (`E[r_p^2] = (1 - h_p) var_p` for the residual a
    pixel keeps after a fit it pulls toward itself). The jackknife form, `1 - h_p`, overstates each pixel's share
    by another `1 / (1 - h_p)`."""
    W = w * w
    S = per_pixel(J * (W * r)[:, None], pixel_of)
    P, k = S.shape
    if leverage:
        h = per_pixel(W * np.einsum("ij,jk,ik->i", J, A_inv, J), pixel_of)
        S = S / np.sqrt(1.0 - np.clip(h, 0.0, 0.9))[:, None]
        return A_inv @ (S.T @ S) @ A_inv
    B = (S.T @ S) * (P / max(P - k, 1))
    return A_inv @ B @ A_inv


def normal_equations(pa: Pass, pb: Pass, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`(g, A2, A1)` of two independent halves: the gradient `(Ja^T W eb + Jb^T W ea) / 2`, in which no Jacobian
    multiplies the residual of its own paths, the two-key normal matrix `sym(Ja^T W Jb)` and the halves' own
    `(Ja^T W Ja + Jb^T W Jb) / 2` (which also carries the Jacobians' noise)."""
    W = w * w
    g = 0.5 * (pa.J.T @ (W * pb.e) + pb.J.T @ (W * pa.e))
    A1 = 0.5 * (normal_matrix(pa.J, pa.J, w) + normal_matrix(pb.J, pb.J, w))
    return g, normal_matrix(pa.J, pb.J, w), A1


QUALITY_MIN = 0.5
"""The smallest relative eigenvalue of the two-key normal matrix (`Step.quality`) along which the covariances trust
it, and below which the estimate does not stop: at 0.5 the Jacobians' noise equals their signal along that
direction. Measured over the coverage study at 76b4828 (docs/results/fit_solver.md, 156 fits): accepted fits whose
last step read 0.5-1 had errors of rms 0.92-1.11 standard errors; the three below 0.5 (0.33-0.36) rms 2.14, one a
mesh fit 3.9 and 2.9 standard errors off; at 0.085 a one-view spot fit was 2.5-3.8 off."""


def floored(cov: np.ndarray, floor: np.ndarray) -> np.ndarray:
    """`cov`, raised along every direction where it is below `floor` to the floor (in the coordinates that whiten
    `floor`, eigenvalues clipped at 1): at least both, in every direction (`reported_covariance`; measured: a
    droplet fit with a residual-based standard error of sigma_t 0.0030 against the renders' own 0.0043 was 4.5 of
    it from the truth)."""
    try:
        L = np.linalg.cholesky(0.5 * (floor + floor.T))
    except np.linalg.LinAlgError:
        return cov
    Li = np.linalg.inv(L)
    lam, V = np.linalg.eigh(Li @ (0.5 * (cov + cov.T)) @ Li.T)
    out = L @ (V * np.maximum(lam, 1.0)) @ V.T @ L.T
    return 0.5 * (out + out.T)


def gauss_newton(pa: Pass, pb: Pass, w: np.ndarray, var_target: np.ndarray, pixel_of: np.ndarray,
                 quality_min: float = QUALITY_MIN, brightness: np.ndarray | None = None) -> Step | None:
    """One Gauss-Newton step from two independent halves: `delta = -A^-1 (Ja^T W eb + Jb^T W ea) / 2`,
    `A = sym(Ja^T W Jb)`. No Jacobian multiplies the residual from its own samples (a Jacobian and a residual from
    the same paths are correlated, which biases the fixed point), and `A` carries no `Var[J]`. Where the Jacobians'
    noise is too large for `A` (`Step.quality` below `quality_min`), the halves' own normal matrix instead. None
    where that is singular too (a parameter without effect on the images). `brightness`: the views' uncertain
    brightness from a heavy-tailed target (`brightness_covariance`), part of the target's noise model."""
    g, A2, A1 = normal_equations(pa, pb, w)
    quality, A_cov = _information(A2, A1, quality_min)
    A = A2 if quality >= quality_min else A1
    delta = spd_solve(A, -g)
    if delta is None:
        return None
    A_inv = np.linalg.inv(A_cov)
    J = 0.5 * (pa.J + pb.J)
    r = 0.5 * (pa.e + pb.e) + J @ delta
    var_render = 0.5 * (pa.u + pb.u) / (pa.spp + pb.spp)
    robust = robust_covariance(A_inv, J, w, r, pixel_of, leverage=True)
    cov_r = model_covariance(A_inv, J, w, var_render, pixel_of)
    cov_t = model_covariance(A_inv, J, w, var_target, pixel_of) + brightness_covariance(A_inv, J, w, brightness)
    nu = effective_pixels(A_inv, J, w, var_render + var_target, pixel_of)
    return Step(delta, A, reported_covariance(robust, cov_r, cov_t, nu), cov_r, cov_t, r, J, var_render, quality,
                robust, nu)


NU_MIN = 3.0
"""The effective number of pixels (`effective_pixels`) the reported variance rests on at least: where the residuals
give fewer, the noise model makes up the rest (`reported_covariance`). With `nu` pixels the residual-based variance
`V_r` is about a `chi^2_nu / nu` draw around the variance `V`, and an error over its standard error has
`E[z^2] = V E[1 / V_r] = nu / (nu - 2)`: infinite for `nu <= 2`; 3 is the smallest whole number of pixels for which it
is finite. Measured on the coverage study (docs/results/fit_solver.md, "Few pixels"): the residual-based one alone
covered an area light's sigma_t (`nu` about 2) 78% within 2 se; the noise model wherever `nu < 9` (the count at which
+-2 residual-based standard errors would cover 92%, `P(|t_9| < 2)`) 78% within 1 se overall, too wide (heavy-tailed
errors put more than 68% within one standard deviation)."""


def effective_pixels(A_inv: np.ndarray, J: np.ndarray, w: np.ndarray, var: np.ndarray,
                     pixel_of: np.ndarray) -> np.ndarray:
    """Per parameter, the effective number of pixels behind its variance (Kish's effective sample size of the
    sandwich's sum): `(sum_p c_p)^2 / sum_p c_p^2`, `c_p` pixel p's share of the noise model's variance of that
    parameter (`model_covariance`'s terms with the residual's expected variance `var`). P for pixels that share it
    equally, 1 where one pixel carries it all (measured: an area light's fit of sigma_t read 2.1, two pixels of the
    emitter seen through the fog carrying 98% of it; its residual-based standard error was 0.4x the model's)."""
    W = w * w
    c = per_pixel((J * W[:, None]) @ A_inv * np.sqrt(np.maximum(var, 0.0))[:, None], pixel_of) ** 2
    return c.sum(axis=0) ** 2 / np.maximum((c * c).sum(axis=0), 1e-300)


def reported_covariance(robust: np.ndarray, cov_render: np.ndarray, cov_target: np.ndarray,
                        nu: np.ndarray) -> np.ndarray:
    """The covariance a step reports: the residual-based `robust`; where some parameter rests on fewer than `NU_MIN`
    effective pixels (`nu`, the least over the parameters), completed to `NU_MIN` of them by the noise model's
    (renders' plus target's): `(nu C + (NU_MIN - nu) C_model) / NU_MIN`, the pooled estimate of two variance
    estimates weighted by their degrees of freedom, the noise model's counted as the pixels the residuals lack;
    then raised to the noise model's along any direction where it is below it (`floored`). The residuals estimate
    the renders' variance plus the target's plus any misfit; one below the noise model's (the renders' variance
    measured from their many samples, the target's from its header's spp or its own pixels) is the residuals'
    sampling luck. Measured on two coverage studies on seeds no rule was chosen on (docs/results/fit_solver.md,
    "The floor"): with the floor at the renders' part alone +-2 reported standard errors covered the truth 91% of
    the time on both; at the whole noise model, re-scored from the same fits, 94% and 96%, and an albedo's
    residual-based standard error on 2.3 pixels, 0.37x the model's, was 7.4 of it off."""
    cov = robust
    nu_min = float(np.min(nu))
    model = cov_render + cov_target
    if nu_min < NU_MIN:
        cov = (nu_min * cov + (NU_MIN - nu_min) * model) / NU_MIN
    return floored(cov, model)


UNRESOLVED = 1e-6
"""The relative eigenvalue the covariances' normal matrix gives a direction the two Jacobians do not resolve
(relative eigenvalue below `quality_min`): its standard error becomes 1000x the halves' own matrix's, and the fit
says the parameters along it are not pinned down, naming the combination that is."""


def _information(A2: np.ndarray, A1: np.ndarray, quality_min: float) -> tuple[float, np.ndarray]:
    """`(quality, A_cov)`: the smallest eigenvalue of the two-key `A2` relative to the positive definite `A1`
    (-inf where A1 is not), and the covariances' normal matrix: `A2` along the directions it resolves (relative
    eigenvalue at least `quality_min`), `UNRESOLVED` times `A1` along the others. Below `quality_min` the Jacobians'
    noise exceeds their signal, and the inverse of so noisy an eigenvalue is no standard error (`QUALITY_MIN`)."""
    try:
        L = np.linalg.cholesky(0.5 * (A1 + A1.T))
    except np.linalg.LinAlgError:
        return float("-inf"), A1
    Li = np.linalg.inv(L)
    M = Li @ (0.5 * (A2 + A2.T)) @ Li.T
    lam, V = np.linalg.eigh(0.5 * (M + M.T))
    A_cov = L @ (V * np.where(lam >= quality_min, lam, UNRESOLVED)) @ V.T @ L.T
    return float(lam.min()), 0.5 * (A_cov + A_cov.T)


def damped_step(pa: Pass, pb: Pass, w: np.ndarray, lam: float) -> np.ndarray | None:
    """The Levenberg-Marquardt step from two independent halves: `(A + lam diag(A)) delta = -g`, with the two-key
    normal matrix `A` and gradient `g` of `gauss_newton` (`lam` 0: its step). None where the matrix is not positive
    definite even with each half's own normal matrix."""
    g, A2, A1 = normal_equations(pa, pb, w)
    for A in (A2, A1):
        D = np.diag(np.maximum(np.diag(A), 1e-12 * max(float(np.trace(A)), 1e-300)))
        delta = spd_solve(A + lam * D, -g)
        if delta is not None:
            return delta
    return None


def two_key_loss(pa: Pass, pb: Pass) -> tuple[float, float]:
    """The unbiased loss of a pair of independent halves, `L = sum(ea eb)` (its expectation is `|E[I] - T|^2` plus
    the target's noise, which every point shares: unlike `|e|^2` it carries no render variance), and a standard
    deviation of it (the pixels' terms taken as independent)."""
    t = pa.e * pb.e
    per_pixel = t.reshape(-1, 3).sum(axis=1)
    return float(t.sum()), float(math.sqrt(np.sum(per_pixel ** 2)))


def mahalanobis(d: np.ndarray, C: np.ndarray) -> float:
    """`sqrt(d^T C^-1 d)`: the length of `d` in standard errors of `C` (inf where C is singular or not finite)."""
    d = np.asarray(d, np.float64)
    if C is None or not np.all(np.isfinite(C)):
        return float("inf")
    try:
        return float(math.sqrt(max(float(d @ np.linalg.solve(C, d)), 0.0)))
    except np.linalg.LinAlgError:
        return float("inf")


def chi2_quantile(k: int, p: float = 0.95) -> float:
    """The p-quantile (p 0.95 or 0.99) of chi^2 with k degrees of freedom: exact for k = 1, 2; Wilson-Hilferty
    above (within 0.6% for k >= 3 at p = 0.95)."""
    exact = {(1, 0.95): 3.841459, (2, 0.95): 5.991465, (1, 0.99): 6.634897, (2, 0.99): 9.210340}
    if (k, p) in exact:
        return exact[(k, p)]
    z = {0.95: 1.6448536, 0.99: 2.3263479}[p]
    a = 2.0 / (9.0 * k)
    return k * (1.0 - a + z * math.sqrt(a)) ** 3


def trust_region(step: np.ndarray, max_du: float) -> np.ndarray:
    """`step` shortened along its direction so that no unconstrained coordinate changes by more than `max_du`."""
    step = np.asarray(step, np.float64)
    big = float(np.max(np.abs(step))) if step.size else 0.0
    if not (np.isfinite(max_du) and big > max_du):
        return step
    return step * (max_du / big)


class Check(NamedTuple):
    """The model check: per view and per channel the ratio of the residual to the expected noise (1 for a model
    that explains the targets), and their maximum."""

    per_view: list
    per_channel: list
    worst: float


def model_check(problem: Problem, step: Step, u: np.ndarray) -> Check:
    """Does the model explain the targets? Each element's residual after the step `r` over its expected noise (the
    target's variance from its header's spp and the renders' per-sample variance `u`, or from its own block
    estimate, plus the render's), as `z^2 = r^2 / var`; the ratio is `median(z^2) / median(chi^2_1)`: 1 for residuals
    that are the noise, robust to heavy-tailed pixels. One ratio per view (its channels pooled) and one per channel
    (the views pooled): a grey model on a chromatic target fits the channels' mean and leaves residuals of opposite
    sign in red and blue."""
    var = problem.target_variance(u) + step.var_render
    z2 = np.where(problem.valid > 0, step.r ** 2 / np.maximum(var, 1e-300), np.nan)  # masked pixels: not fitted
    parts = problem.split(z2)
    views = [float(np.nanmedian(x) / MEDIAN_CHI2_1) for x in parts]
    chan = np.concatenate([x.reshape(-1, 3) for x in parts])
    channels = [float(np.nanmedian(chan[:, c]) / MEDIAN_CHI2_1) for c in range(3)]
    return Check(views, channels, max(views + channels))
