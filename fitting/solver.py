"""The fit as a solver: `init`, `step`, `terminate`, `postprocess` over an explicit `FitState`.

The shape is optimistix's (`AbstractIterativeSolver`), the loop runs on the host: its rounds render with fresh keys
and make decisions from noisy estimates, which a jitted loop cannot. One round is one of four kinds, each a
module-level function of named inputs returning the next state (docs/fitting.md gives the reasons and measurements):

1. `search_round`: the global search (`fitting.search`) and the brightness check against what it can render;
2. `approach_round`: a Gauss-Newton step from one forward-mode pass rendered as two independent halves, in a trust
   region, until the step is within its own render noise;
3. `estimate_round`: passes at one point `y0` accumulated until the estimate `y0 + delta` is precise enough (or
   the renders' share of its variance is small, or the budget is spent); a step too long for its standard errors
   re-centres `y0` first;
4. `check_round`: the model check on the estimate's residuals; where the first solve reads above `CHI2_GOOD`, the
   search's other distinct starts (up to `FitConfig.max_starts`) are screened, and one that reads clearly lower
   (`SCREEN_MARGIN`) is solved in full.

`fit_views` runs the loop: `state = init(...)`, `while not terminate(state): state = step(state)`, `postprocess`.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import Callable, NamedTuple

import jax
import numpy as np

from .information import fisher_report, instead, relative_scales
from .params import SPECS, FitError, jacobian_to_params, to_unconstrained
from .problem import LIGHT_MARGIN, TAIL_FACTOR, Pass, Problem, View, stratified
from .rounds import (QUALITY_MIN, Check, Step, chi2_quantile, damped_step, gauss_newton, mahalanobis, model_check,
                     trust_region, two_key_loss, weights)
from .search import Scan, check_brightness, distinct_starts, global_search
from .visibility import visibility


@dataclass(frozen=True)
class FitConfig:
    """What a fit may spend and how it decides (the defaults are measured in docs/fitting.md).

    - `spp`: samples per pixel of the unit render; an approach pass has `approach_factor` x spp, an estimate pass
      `estimate_factor` x spp (each as two halves of independent keys). `scan_spp`: per candidate and key.
    - `seed`: every key of the fit derives from it; the same inputs and seed give the same result.
    - `time_budget`: seconds of each local solve (from its start to its check, without the first pass of each pass
      size, which pays for compiling its program: a cold cache must not cost the fit its precision; None: no
      limit); an approach that reaches it goes to the estimate, an estimate that reaches it stops with the passes
      it has. A restart from another start of the search has a budget of its own.
    - `precision`: the estimate stops once every standard error is at most this (relative for positive
      quantities, absolute for g and albedo), or once more batches cannot shrink it much (`render_share`).
    - `max_se`: a parameter whose standard error exceeds this (relative / absolute) is "not pinned down".
    - `chi2_max`: the model check's limit on residual / expected noise.
    - `max_starts`: distinct starts of the search, the first solved, the others screened where it is not explained
      well enough (`check_round`), before the fit says the model does not explain the targets."""

    spp: int = 256
    seed: int = 0
    time_budget: float | None = 20.0
    precision: float = 0.01
    max_se: float = 0.1
    chi2_max: float = 6.0
    max_starts: int = 5
    scan_spp: int = 32
    approach_factor: int = 8
    estimate_factor: int = 16
    max_approach: int = 12
    min_batches: int = 2
    max_batches: int = 16
    render_share: float = 0.2
    linear_du: float = 0.05
    max_recentres: int = 3
    max_step_u: float = 1.0
    weight_power: float = 0.5
    weight_smoothing: int = 1

    def __post_init__(self):
        for f in ("spp", "scan_spp", "approach_factor", "estimate_factor", "max_approach", "min_batches",
                  "max_batches", "max_starts"):
            if int(getattr(self, f)) < 1:
                raise FitError(f"FitConfig.{f} must be >= 1, got {getattr(self, f)}")
        if self.min_batches > self.max_batches:
            raise FitError(f"FitConfig.min_batches ({self.min_batches}) exceeds max_batches ({self.max_batches})")
        if self.time_budget is not None and not self.time_budget > 0:
            raise FitError(f"FitConfig.time_budget must be > 0 seconds, got {self.time_budget}")
        for f in ("precision", "max_se", "chi2_max", "max_step_u", "linear_du"):
            if not getattr(self, f) > 0:
                raise FitError(f"FitConfig.{f} must be > 0, got {getattr(self, f)}")


class Attempt(NamedTuple):
    """One local solve that ran to its check: the point `y0` of its estimate passes, the estimate's `step`, the
    per-sample render variances `u` there, and the model `check`."""

    y0: np.ndarray
    step: Step
    u: np.ndarray
    check: Check
    screened: bool = False          # a screen (`SCREEN_MARGIN`): never the result


@dataclass(frozen=True)
class FitState:
    """Everything the loop carries from one round to the next (host arrays; replaced, never mutated)."""

    phase: str                      # "search", "approach", "estimate", "check", "done"
    round: int
    y: np.ndarray                   # the current point, unconstrained coordinates
    init: dict
    t0: float
    c0: float
    t_attempt: float = 0.0          # when the current local solve began (its time budget counts from there)
    compiled: frozenset = frozenset()  # pass sizes rendered once (their first pass paid for compilation)
    scan: Scan | None = None
    starts: tuple = ()
    start: int = 0                  # index of the current start in `starts`
    screen: bool = False            # the current start is screened: its estimate stops at `min_batches` passes
    u: np.ndarray | None = None     # per-sample render variances of the approach's passes (the weights' source)
    w: np.ndarray | None = None     # the estimate's weights, fixed while its passes accumulate
    passes: tuple = ()              # the estimate's passes at `y`: ((a, b), ...)
    step: Step | None = None        # the estimate's latest step
    approach: int = 0               # approach rounds of this start
    trial: np.ndarray | None = None # the approach's pending trial point (rendered next round)
    base: tuple | None = None       # the approach's accepted point's pass pair and its two-key loss
    lam: float = 1e-2               # the approach's damping
    recentres: int = 0
    failures: int = 0               # non-finite passes in a row
    attempts: tuple = ()
    records: tuple = ()
    messages: tuple = ()

    def replace(self, **kw) -> "FitState":
        return dataclasses.replace(self, **kw)


@dataclass
class FitResult:
    names: list
    params: dict
    init: dict
    success: bool
    messages: list
    uncertainty: dict
    rounds: int
    wall_s: float
    chi2: float = float("nan")
    correlation: list | None = None
    covariance: list | None = None
    information: dict | None = None
    history: list = field(default_factory=list)
    timing: list = field(default_factory=list)
    search: dict | None = None
    visibility: dict | None = None
    """The meteorological optical range of the fitted extinction with its standard error (`fitting.visibility`);
    None where the fit did not include the extinction."""
    fireflies: dict = field(default_factory=dict)
    """Per view, the `(x, y)` source pixels left out as fireflies (`fit_views`): empty unless the model check refused
    the targets with them and the fit succeeded without them."""
    tails: dict = field(default_factory=dict)
    """Per view whose target's noise comes from its own pixels and has a heavy tail (`fitting.problem.tail_spread`):
    its tail pixels, the typical shortfall the target was raised by, and the uncertainty of the view's brightness
    they leave (both relative)."""
    images: list | None = None
    """Per view, the render at the estimate at the fit resolution (linear radiance; the estimate's passes moved to the
    estimate by their Jacobian): for figures, not written to JSON."""

    def to_json(self) -> dict:
        out = dataclasses.asdict(self)
        out.pop("images")
        return out


# ---- the rounds -------------------------------------------------------------------------------------------------


def _key(cfg: FitConfig, r: int):
    return jax.random.fold_in(jax.random.key(cfg.seed), r)


def _record(state: FitState, problem: Problem, kind: str, y, log, **extra) -> tuple:
    vals = _values(problem.names, y)
    rec = {"round": state.round, "phase": kind, "start": state.start, **vals,
           "wall_s": time.perf_counter() - state.t0, "cpu_s": time.process_time() - state.c0, **extra}
    log(f"round {state.round} ({kind}): " + "  ".join(f"{n} {vals[n]:.5g}" for n in problem.names)
        + "".join(f"  {k} {v:.3g}" if isinstance(v, float) else f"  {k} {v}" for k, v in extra.items())
        + f"  [{rec['wall_s']:.1f} s]")
    return state.records + (rec,)


def search_round(problem: Problem, state: FitState, cfg: FitConfig, log) -> FitState:
    """The global search (`fitting.search.global_search`), the brightness check against it, the starts."""
    scan = global_search(problem, state.init, _key(cfg, 100_000), cfg.scan_spp)
    check_brightness(problem, scan)
    starts = tuple(distinct_starts(scan, cfg.max_starts))
    if not starts:
        raise FitError("no candidate of the searched region renders finite images")
    state = state.replace(scan=scan, starts=starts, y=starts[0], phase="approach", t_attempt=time.perf_counter())
    return state.replace(records=_record(state, problem, "search", starts[0], log, candidates=len(scan.Y),
                                         best_loss=float(scan.loss[0])))


def _halves(problem: Problem, state: FitState, y, cfg: FitConfig, factor: int) -> tuple[tuple | None, FitState]:
    """A pass of `factor` x spp at `y` as two independent halves (None where a render is not finite), and the state
    with the time of a pass size's first pass (its compilation: seconds to a minute on a cold cache) taken out of
    the local solve's budget."""
    t = time.perf_counter()
    ka, kb = jax.random.split(_key(cfg, state.round))
    half = max(1, factor // 2) * cfg.spp
    size = _program_size(problem, half, max(1, cfg.approach_factor // 2) * cfg.spp)
    pa, pb = _half_pass(problem, y, ka, half, size), _half_pass(problem, y, kb, half, size)
    ok = all(np.all(np.isfinite(x)) for p in (pa, pb) for x in (p.e, p.u, p.J))
    if size not in state.compiled:
        state = state.replace(compiled=state.compiled | {size}, t_attempt=state.t_attempt + time.perf_counter() - t)
    return ((pa, pb) if ok else None), state


def _program_size(problem: Problem, half: int, unit: int) -> int:
    """The samples of one pass program call for a half of `half` samples: the approach's half `unit` where it divides
    `half` and pools every view alike (`fitting.problem.stratified`), so one compiled program serves both kinds of round
    (a cold start compiles one forward-mode program, not two: docs/fitting.md, "Start-up"), else `half`."""
    alike = all(stratified(unit, v.downscale) == stratified(half, v.downscale) for v in problem.views)
    return unit if half % unit == 0 and alike else half


def _half_pass(problem: Problem, y, key, half: int, size: int) -> Pass:
    """`half` samples at `y` as `half / size` independent passes of `size` (their spp-weighted mean)."""
    n = half // size
    if n == 1:
        return problem.pass_(y, key, half)
    return _combine([problem.pass_(y, k, size) for k in jax.random.split(key, n)])


def _failed_pass(problem, state: FitState, log) -> FitState:
    msg = f"round {state.round}: a render was not finite; the round is repeated with new keys"
    log("  (" + msg + ")")
    if state.failures + 1 >= 3:
        raise FitError(f"three passes in a row rendered non-finite values at {_values(problem.names, state.y)}: "
                       f"no estimate (a render's image must be finite)")
    return state.replace(round=state.round + 1, failures=state.failures + 1, messages=state.messages + (msg,))


def _over_budget(state: FitState, cfg: FitConfig) -> bool:
    """Whether the local solve has spent its time budget. Called once in every approach and estimate round, whatever
    the round decides otherwise: with several processes (docs/distributed.md) process 0's clock decides and its
    answer is broadcast to the others (one collective a round, reached by every process in the same order), so all
    processes stop at the same pass."""
    over = cfg.time_budget is not None and time.perf_counter() - state.t_attempt > cfg.time_budget
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        over = bool(multihost_utils.broadcast_one_to_all(np.int32(over)))
    return over


def approach_round(problem: Problem, state: FitState, cfg: FitConfig, log) -> FitState:
    """One Levenberg-Marquardt round from a pass of `approach_factor` x spp (two halves).

    The pass is rendered at the pending trial point, if any: its two-key loss against the accepted point's decides
    (accepted when it is not higher by more than the two losses' noise; the damping shrinks on acceptance and grows
    on rejection), then the next trial step is solved from the accepted point's pass. The approach hands over to the
    estimate when a step of little damping is within the linear range `linear_du` or within its own render noise
    (chi^2_k at 95%), when no damping finds a lower loss, after `max_approach` rounds, or at the budget."""
    trial = state.trial
    halves, state = _halves(problem, state, state.y if trial is None else trial, cfg, cfg.approach_factor)
    if halves is None:
        return _failed_pass(problem, state.replace(trial=None), log)
    loss = two_key_loss(*halves)
    y, base, lam, verdict = state.y, state.base, state.lam, ""
    if trial is None or base is None:
        base = (halves, loss)
    elif loss[0] <= base[1][0] + math.hypot(loss[1], base[1][1]):
        y, base, lam, verdict = trial, (halves, loss), max(lam / 3.0, LAMBDA_MIN), "accepted"
    else:
        lam, verdict = lam * 5.0, "rejected"
    (pa, pb), _ = base
    u_now = 0.5 * (pa.u + pb.u)
    u = u_now if state.u is None else 0.5 * (state.u + u_now)
    w = weights(problem, state.u, cfg.weight_power, cfg.weight_smoothing, _render_spp(cfg))
    delta = damped_step(pa, pb, w, lam)
    if delta is None:
        raise FitError(f"the images do not change with the fitted parameters at {_values(problem.names, y)}: "
                       f"nothing to fit")
    step = gauss_newton(pa, pb, w, problem.target_variance(u), problem.pixel_of)
    length = mahalanobis(delta, step.cov_render) if step is not None else float("inf")
    small = float(np.max(np.abs(delta))) <= cfg.linear_du or length ** 2 <= chi2_quantile(len(problem.names))
    over = _over_budget(state, cfg)
    done = (small and lam <= LAMBDA_SMALL) or lam >= LAMBDA_MAX or state.approach + 1 >= cfg.max_approach or over
    records = _record(state, problem, "approach", y, log, loss=loss[0], damping=lam, step_se=length,
                      **({"trial": verdict} if verdict else {}))
    nxt = dict(y=y, u=u, base=base, lam=lam, round=state.round + 1, approach=state.approach + 1, failures=0,
               records=records)
    if state.screen and verdict == "accepted" and _joined(problem, state, y, cfg):
        log(f"  (screened start {state.start + 1} reached a full solve's estimate within its 95% region: the same "
            f"basin, not solved again)")
        return _next_start(state.replace(**nxt), log)
    if done:
        return state.replace(**nxt, trial=None, phase="estimate",
                             w=weights(problem, u, cfg.weight_power, cfg.weight_smoothing, _render_spp(cfg)))
    return state.replace(**nxt, trial=y + trust_region(delta, cfg.max_step_u))


def _render_spp(cfg: FitConfig) -> int:
    """The samples of one estimate pass (both halves): the render's share of the residual's variance in the weights'
    view levels (`rounds.weights`)."""
    return 2 * cfg.estimate_factor * cfg.spp


LAMBDA_START, LAMBDA_MIN, LAMBDA_SMALL, LAMBDA_MAX = 1e-2, 1e-4, 0.1, 1e4
"""The approach's damping (relative to the normal matrix's diagonal): its start, its floor, the most with which a
small step still ends the approach, and the most before the approach ends at a point no damped step improves."""


def _moved(p: Pass, delta: np.ndarray) -> Pass:
    """A pass at `y0` as seen from `y0 + delta`, to first order: its residual moved by its own Jacobian (the
    Jacobian's own change over `delta` enters the next step at second order)."""
    return Pass(p.e + p.J @ delta, p.u, p.J, p.spp)


def _combine(passes: list[Pass]) -> Pass:
    """Passes at one point as one pass of all their samples (spp-weighted means)."""
    n = sum(p.spp for p in passes)
    mean = lambda f: sum(getattr(p, f) * p.spp for p in passes) / n  # noqa: E731
    return Pass(mean("e"), mean("u"), mean("J"), n)


def estimate_round(problem: Problem, state: FitState, cfg: FitConfig, log) -> FitState:
    """One more pass of `estimate_factor` x spp at `y0 = state.y`, the step from all of them together. Where the step
    changes some unconstrained coordinate by more than `linear_du`, `y0` moves to the estimate and the passes so far
    move with it by their Jacobians (`_moved`; at most `max_recentres` times, never by more than half the trust
    region); a step beyond that and significant sends the fit back to the approach, started from the estimate (within
    the trust region: from the passes' own point, a start where the Jacobians are flat, as at a bound of g, handed
    over to the estimate at once and came back three times), one within its noise leaves the passes where they are.
    A screen whose estimate lies in a full solve's 95% region ends (`_joined`). Else stop when precise enough, when
    more passes would barely help, or at the budget."""
    halves, state = _halves(problem, state, state.y, cfg, cfg.estimate_factor)
    if halves is None:
        return _failed_pass(problem, state, log)
    passes = state.passes + (halves,)
    pa, pb = _combine([p[0] for p in passes]), _combine([p[1] for p in passes])
    u = 0.5 * (pa.u + pb.u)
    B = problem.brightness_noise()
    step = gauss_newton(pa, pb, state.w, problem.target_variance(u), problem.pixel_of, brightness=B)
    if step is None:
        raise FitError(f"the images do not change with the fitted parameters at {_values(problem.names, state.y)}: "
                       f"nothing to fit")
    if any(v.noise_from_image for v in problem.views):  # the target's noise from the residual at the estimate
        step = gauss_newton(pa, pb, state.w, problem.target_variance(u, step.r, step.var_render),
                            problem.pixel_of, brightness=B) or step
    length = mahalanobis(step.delta, step.cov)
    y_hat = state.y + step.delta
    rel = _relative_se(problem.names, y_hat, step.cov)
    records = _record(state, problem, "estimate", y_hat, log, batches=len(passes), step_se=length,
                      worst_se=float(np.max(rel)), quality=step.quality)
    state = state.replace(round=state.round + 1, failures=0, records=records)
    if state.screen and _joined(problem, state, y_hat, cfg):
        log(f"  (screened start {state.start + 1}'s estimate lies within a full solve's 95% region: the same basin, "
            f"not solved again)")
        return _next_start(state, log)
    over = _over_budget(state, cfg)
    big = float(np.max(np.abs(step.delta)))
    if big > cfg.max_step_u / 2 and length > SIGNIFICANT and state.recentres < cfg.max_recentres:
        log(f"  (the estimate is {big:.2f} from the passes' point in an unconstrained coordinate and {length:.1f} "
            f"standard errors: too far for one linearisation, back to the approach from it)")
        return state.replace(phase="approach", y=state.y + trust_region(step.delta, cfg.max_step_u), passes=(),
                             recentres=state.recentres + 1, base=None, trial=None, lam=LAMBDA_START)
    if cfg.linear_du < big <= cfg.max_step_u / 2 and state.recentres < cfg.max_recentres and not over:
        log(f"  (re-centred on the estimate, {big:.3f} away in an unconstrained coordinate; the passes so far moved "
            f"with it by their Jacobians)")
        return state.replace(y=y_hat, passes=tuple((_moved(a, step.delta), _moved(b, step.delta)) for a, b in passes),
                             recentres=state.recentres + 1)
    # a step beyond half the trust region but within its noise: noise along a weakly determined direction; the
    # passes accumulate where they are (the estimate then cannot stop: it is not within the linear range)
    model = np.diag(step.cov_render) + np.diag(step.cov_target)
    render_small = np.all(np.diag(step.cov_render) <= cfg.render_share * model)
    linear = float(np.max(np.abs(step.delta))) <= cfg.linear_du and step.quality >= QUALITY_MIN
    enough = len(passes) >= cfg.min_batches and (state.screen or linear and (np.all(rel <= cfg.precision)
                                                                         or render_small))
    if enough or len(passes) >= cfg.max_batches or over:
        return state.replace(passes=passes, step=step, phase="check")
    return state.replace(passes=passes, step=step)


SIGNIFICANT = 3.0
"""An estimate step beyond the linear range sends the fit back to the approach only when it is longer than this many
of its standard errors; a shorter one is the noise along a weakly determined direction, which more passes shrink."""


def check_round(problem: Problem, state: FitState, cfg: FitConfig, log) -> FitState:
    """The model check of the estimate. The first start's solve ends the fit where the check reads at most
    `CHI2_GOOD`; otherwise every other distinct start of the search is screened (approach and `min_batches` estimate
    passes), and a screen whose check reads below the best full solve's by more than `SCREEN_MARGIN` is solved in
    full from where it stands (its passes kept)."""
    pa = _combine([p[0] for p in state.passes])
    pb = _combine([p[1] for p in state.passes])
    u = 0.5 * (pa.u + pb.u)
    check = model_check(problem, state.step, u)
    log("model check (residual / expected noise): per view " + ", ".join(
        f"{v.name} {c:.2f}" for v, c in zip(problem.views, check.per_view))
        + "; per channel " + ", ".join(f"{ch} {c:.2f}" for ch, c in zip("rgb", check.per_channel)))
    best = min((a.check.worst for a in state.attempts if not a.screened), default=float("inf"))
    n = state.start + 1
    if state.screen and check.worst * SCREEN_MARGIN < best:
        log(f"  (start {n} reads {check.worst:.1f}x the noise against the best solve's {best:.1f}x: solved in full)")
        return state.replace(phase="estimate", screen=False)
    attempts = state.attempts + (Attempt(state.y, state.step, u, check, screened=state.screen),)
    best = min(best, check.worst) if not state.screen else best
    if not state.screen and check.worst <= CHI2_GOOD:
        return state.replace(attempts=attempts, phase="done")
    log(f"  ({'screened' if state.screen else 'solved'} start {n}: {check.worst:.1f}x the noise, the best solve "
        f"{best:.1f}x)")
    return _next_start(state.replace(attempts=attempts), log)


def _next_start(state: FitState, log) -> FitState:
    """The next distinct start of the search, screened; the end of the fit after the last."""
    n = state.start + 1
    if n >= len(state.starts):
        return state.replace(phase="done")
    log(f"  (start {n + 1} of {len(state.starts)} screened)")
    return state.replace(phase="approach", start=n, screen=True, y=state.starts[n], u=None, w=None, passes=(),
                         step=None, approach=0, recentres=0, trial=None, base=None, lam=LAMBDA_START,
                         t_attempt=time.perf_counter())


def _joined(problem: Problem, state: FitState, y: np.ndarray, cfg: FitConfig) -> bool:
    """Whether `y` (a screen's accepted approach point or estimate) lies in the 95% region (`chi^2_k`, its own
    covariance) of a full solve's estimate whose region is resolved (the two Jacobians agree, `QUALITY_MIN`, and every
    standard error within half the trust region: one basin's region, not a weakly determined direction's). A screen
    there has joined that basin: its solve would end at the same minimum, whose check cannot read below the solve's by
    `SCREEN_MARGIN` except by the checks' noise (and the lower of two checks of one basin gains no accuracy), so it
    is not run on. Measured on the foreign mesh case, whose truth's basin reads 3.7x the noise and so screens its four
    other starts: the screens ran 2-6 approach rounds and 2-3 estimate passes each (25 s of the fit's 45), and every
    one ended in the first start's basin; ended here, the fit took 21 rounds instead of 29, 25 s from process start
    instead of 35 (interleaved medians), with the same estimate."""
    limit = chi2_quantile(len(problem.names))
    for a in state.attempts:
        if a.screened or a.step.quality < QUALITY_MIN:
            continue
        if not np.all(np.sqrt(np.maximum(np.diag(a.step.cov), 0.0)) <= cfg.max_step_u / 2):
            continue
        if mahalanobis(y - (a.y0 + a.step.delta), a.step.cov) ** 2 <= limit:
            return True
    return False


CHI2_GOOD = 2.0
"""A full local solve whose model check reads at most this many times the noise ends the fit; above it the search's
other distinct starts are screened (`check_round`). Measured: the truth's basin read 0.7-3.8 (Mitsuba's dense fog
side view 2.9-3.8, a mesh scene's 4.9-5.8); wrong basins accepted by earlier rules read 4.6-5.8: a point-lit room's
albedo fit (g -0.19 for 0.5, albedo 0.92 for 0.7, at 3.4-5.0 from two of its five starts, the third found the truth
at 0.98), a synthetic photograph (g -21.8 se) and a study fit at 5.77 (g 0.05 for 0.31)."""

SCREEN_MARGIN = 1.5
"""A screened start is solved in full where its check reads below the best full solve's by more than this factor.
The check of one channel is a median over 64 fit pixels (8 x 8): its relative standard deviation is
`0.5 / (sqrt(64) f(m)) / m` = 0.29 (`m` = 0.455 the median of chi^2_1, `f(m)` = 0.471 its density), and that of the
ratio of two independent checks about 0.41, so a factor 1.5 (log 0.41) is about one standard deviation: a screen of
the same basin is solved again about one time in six (a cost in time, not in accuracy, as the lowest check wins),
while wrong basins read 3-80x their truth's check (above)."""


ROUNDS = {"search": search_round, "approach": approach_round, "estimate": estimate_round, "check": check_round}


# ---- the solver -------------------------------------------------------------------------------------------------


class FogFitSolver:
    """The fit in the shape of an optimistix solver; `fit_views` runs it. `max_rounds` only stops a runaway loop: at
    60 it cut the forward-fog room's fits before their third and fourth starts, which found the truth (five
    starts of up to ~30 rounds each fit under 200)."""

    def __init__(self, cfg: FitConfig, log: Callable = print, max_rounds: int = 200):
        self.cfg, self.log, self.max_rounds = cfg, log, max_rounds

    def init(self, problem: Problem, init: dict) -> FitState:
        y = np.asarray(to_unconstrained(problem.names, init), np.float64)
        return FitState(phase="search", round=0, y=y, init=dict(init), t0=time.perf_counter(),
                        c0=time.process_time())

    def step(self, problem: Problem, state: FitState) -> FitState:
        return ROUNDS[state.phase](problem, state, self.cfg, self.log)

    def terminate(self, state: FitState) -> bool:
        return state.phase == "done" or state.round >= self.max_rounds

    def postprocess(self, problem: Problem, state: FitState) -> FitResult:
        return summarise(problem, state, self.cfg)


def fit_views(views: list[View], names: list[str], init: dict, cfg: FitConfig | None = None,
              log: Callable = print) -> FitResult:
    """Fit `names` (starting from `init`, a value for each: a hint for the search) to all `views` jointly. Raises
    FitError for inputs no fit can use (a target darker or brighter than anything the searched region renders);
    a fit that runs but fails says so in the result (`success`, `messages`). Where the model check refuses the
    targets and a target whose noise comes from the image has fireflies (`View.without_fireflies`), the fit is run
    again without them, and that fit stands where it succeeds (`FitResult.fireflies` names the pixels left out). A
    fit that fails for another reason (a parameter not pinned down at the budget) is not run again: its fireflies
    are noise its standard errors count."""
    cfg = cfg or FitConfig()
    for v in views:
        if v.scene.medium is None and set(names) - {"intensity"}:
            raise FitError(f"{v.name}: the scene has no medium to fit")
    _log_views(views, log)
    result = _solve(Problem(views, names), init, cfg, log)
    result.tails = {v.name: {"pixels": v.tail_pixels, "raised_by": v.tail_deficit, "brightness_se": v.tail_spread}
                    for v in views if v.tail_pixels}
    if not _refused(result, cfg) or not any(v.without_fireflies for v in views):
        return result
    alt = [v.without_fireflies or v for v in views]
    pixels = "; ".join(f"{v.name} {len(v.fireflies)} px" for v in alt if v.fireflies)
    log(f"the model check refused the targets; the fit again without their firefly pixels (10x brighter than each "
        f"neighbour): {pixels}")
    retry = _solve(Problem(alt, names), init, cfg, log)
    if not retry.success:
        result.messages.append(f"fitted again without the targets' firefly pixels ({pixels}): failed as well")
        return result
    retry.fireflies = {v.name: [list(p) for p in v.fireflies] for v in alt if v.fireflies}
    shares = ", ".join(f"{v.name} {100 * v.firefly_share:.2g}%" for v in alt if v.fireflies)
    retry.messages.append(f"fitted without the targets' firefly pixels, which held this share of their view's light: "
                          f"{shares}. Such a target's noise has no finite variance (docs/fitting.md, 'Fireflies'): "
                          f"without them a view is darker than its expectation, and the standard errors do not count "
                          f"it; a target with more samples per pixel is the remedy")
    retry.tails = result.tails
    retry.rounds += result.rounds
    retry.wall_s += result.wall_s
    return retry


def _log_views(views: list[View], log: Callable) -> None:
    """What the fit leaves out of or changes in each target before it starts."""
    for v in views:
        if v.light_pixels:
            log(f"{v.name}: {v.light_pixels} px within {LIGHT_MARGIN:g} px of a point-like light's image are not fitted "
                f"(their radiance has no finite variance)")
        if v.tail_pixels:
            log(f"{v.name}: the target's noise has a heavy tail ({v.tail_pixels} px above {TAIL_FACTOR:g}x their "
                f"brightest neighbour): raised by its typical shortfall, {100 * v.tail_deficit:.2g}%, and its "
                f"brightness uncertain by {100 * v.tail_spread:.2g}%, which the standard errors include "
                f"(docs/fitting.md, 'Fireflies')")


def _refused(result: FitResult, cfg: FitConfig) -> bool:
    """Whether the model check refused the targets: no point of the searched region explains them (a finite check
    above `chi2_max`)."""
    return bool(np.isfinite(result.chi2) and result.chi2 > cfg.chi2_max)


def _solve(problem: Problem, init: dict, cfg: FitConfig, log: Callable) -> FitResult:
    solver = FogFitSolver(cfg, log)
    state = solver.init(problem, init)
    while not solver.terminate(state):
        state = solver.step(problem, state)
    return solver.postprocess(problem, state)


# ---- the result -------------------------------------------------------------------------------------------------


def _values(names, y) -> dict:
    return {n: float(SPECS[n].from_u(np.float32(y[i]))) for i, n in enumerate(names)}


def _to_params(names, y, C) -> np.ndarray:
    d = jacobian_to_params(names, y)
    return C * np.outer(d, d)


def _relative_se(names, y, C) -> np.ndarray:
    se = np.sqrt(np.abs(np.diag(_to_params(names, y, C))))
    return se / relative_scales(names, _values(names, y))


def _at_edge(names, y) -> list[str]:
    """Bounded parameters whose unconstrained coordinate is beyond 6 (g beyond +-0.99999, an albedo within 0.0025
    of 0 or 1): the map is flat there and the fit cannot come back."""
    return [n for i, n in enumerate(names)
            if np.isfinite(SPECS[n].lo) and np.isfinite(SPECS[n].hi) and abs(float(y[i])) > 6.0]


def _best_attempt(attempts, chi2_max: float = float("inf")) -> Attempt | None:
    """The attempt whose model check reads lowest (None before any); among the attempts in its basin (estimates
    within 3 combined standard errors of its own, in the unconstrained coordinates) and explained as well as it
    (check within `chi2_max`, or no worse than its own) the one with the smallest largest standard error: two solves
    of one basin are one solution, and the better-measured one is kept; an attempt the model check refuses is
    never kept over one it accepts (a droplet fit's refusal at 9.6x the noise replaced its own basin's 2.0x)."""
    attempts = [a for a in attempts if not a.screened]
    if not attempts:
        return None
    best = min(attempts, key=lambda a: a.check.worst)
    y = best.y0 + best.step.delta
    limit = max(chi2_max, best.check.worst)

    def in_basin(a: Attempt) -> bool:  # per coordinate
        d = a.y0 + a.step.delta - y
        return bool(np.all(np.abs(d) <= 3.0 * np.sqrt(np.abs(np.diag(a.step.cov) + np.diag(best.step.cov)))))

    return min((a for a in attempts if a is best or (in_basin(a) and a.check.worst <= limit)),
               key=lambda a: float(np.max(np.diag(a.step.cov))))


def summarise(problem: Problem, state: FitState, cfg: FitConfig) -> FitResult:
    """The result of the best attempt: estimate, standard errors (total, the renders' and the target's parts),
    correlation, what the views determine, and every reason not to trust it."""
    names = problem.names
    k = len(names)
    wall = time.perf_counter() - state.t0
    best = _best_attempt(state.attempts, cfg.chi2_max)
    search = None if state.scan is None else _search_summary(names, state.scan)
    if search is not None:
        search["starts"] = [_values(names, y) for y in state.starts[:max(len(state.attempts), 1)]]
    if best is None:
        return FitResult(names, _values(names, state.y), dict(state.init), False,
                         list(state.messages) + [f"no estimate after {state.round} rounds"],
                         {n: {"se": float("nan"), "se_render": float("nan"), "se_target": float("nan")}
                          for n in names}, state.round, wall, history=list(state.records), search=search)
    y = best.y0 + best.step.delta
    vals = _values(names, y)
    C = _to_params(names, y, best.step.cov)
    se = np.sqrt(np.abs(np.diag(C)))
    se_r = np.sqrt(np.abs(np.diag(_to_params(names, y, best.step.cov_render))))
    se_t = np.sqrt(np.abs(np.diag(_to_params(names, y, best.step.cov_target))))
    se_rob = np.sqrt(np.abs(np.diag(_to_params(names, y, best.step.cov_robust))))
    nu = best.step.nu if best.step.nu is not None else np.full(k, np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = C / np.sqrt(np.outer(np.diag(C), np.diag(C)))
    fisher = np.linalg.pinv(C) if np.all(np.isfinite(C)) else np.full((k, k), np.nan)
    information = fisher_report(names, vals, fisher)
    messages = list(state.messages)
    explained = best.check.worst <= cfg.chi2_max
    if not explained:
        messages.append(_not_explained(problem, state, best, cfg))
    edge = _at_edge(names, y)
    if edge:
        messages.append(f"parameters ran to the edge of their range: {edge}")
    rel = se / relative_scales(names, vals)
    loose = [n for i, n in enumerate(names) if not rel[i] <= cfg.max_se]
    if loose:
        messages.append(f"not pinned down by these targets at this budget (standard error above {cfg.max_se:g}"
                        f"{'' if loose == ['g'] else ' relative'}): {loose}; more spp, a larger budget or views")
        messages.extend(instead(names, vals, fisher, loose).values())
    return FitResult(
        names=names, params=vals, init=dict(state.init), success=bool(explained and not edge and not loose),
        messages=messages,
        uncertainty={n: {"se": float(se[i]), "se_render": float(se_r[i]), "se_target": float(se_t[i]),
                         "se_robust": float(se_rob[i]), "nu": float(nu[i])} for i, n in enumerate(names)},
        rounds=state.round, wall_s=wall, chi2=float(best.check.worst), correlation=corr.tolist(),
        covariance=C.tolist(), information=information, history=list(state.records),
        timing=[{k2: r[k2] for k2 in ("round", "phase", "wall_s", "cpu_s")} for r in state.records], search=search,
        visibility=visibility(problem.views[0].scene, names, vals, C),
        images=[x * sc * math.sqrt(problem.n) for x, sc in zip(problem.split(best.step.r + problem.t),
                                                                 problem.scales)])


def _search_summary(names, scan: Scan) -> dict:
    return {"box": {n: [float(SPECS[n].from_u(np.float32(a))), float(SPECS[n].from_u(np.float32(b)))]
                    for n, a, b in zip(names, scan.lo, scan.hi)},
            "candidates": int(len(scan.Y)), "best": _values(names, scan.Y[0]), "best_loss": float(scan.loss[0]),
            "points": [[*_values(names, y).values(), float(l)] for y, l in zip(scan.Y, scan.loss)]}


def _not_explained(problem: Problem, state: FitState, best: Attempt, cfg: FitConfig) -> str:
    box = ", ".join(f"{n} {a:.3g}..{b:.3g}" for n, (a, b) in _search_summary(problem.names, state.scan)["box"].items())
    at = ", ".join(f"{n} {v:.4g}" for n, v in _values(problem.names, best.y0 + best.step.delta).items())
    return (f"the model does not explain the target(s): searched {box} ({len(state.scan.Y)} candidates, local solves "
            f"or screens from {len(state.attempts)} distinct start(s)); the best residual is {best.check.worst:.1f}x the "
            f"expected noise (limit {cfg.chi2_max:g}), at {at}; per view: "
            + ", ".join(f"{v.name} {c:.1f}" for v, c in zip(problem.views, best.check.per_view))
            + "; per channel: " + ", ".join(f"{ch} {c:.1f}" for ch, c in zip("rgb", best.check.per_channel)))
