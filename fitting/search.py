"""The global search: where in the parameters' valid box the targets' basin lies, before any local step.

A start is a hint, not a requirement: the fit scans a box of every fitted parameter's plausible values
(`search_box`: the scene's size sets the extinction's and the lengths' ranges, the starting value only widens them)
with a low-discrepancy (Halton) set of candidates, then a second, finer set around the best one. Every candidate is
rendered at the fit resolution with few samples per pixel, all candidates with the same two keys (common random
numbers: the difference between two candidates' losses is smooth in their parameters), and scored by the two-key
loss `sum((A - T)(B - T))`, whose expectation is `|E[I] - T|^2` plus a constant (unlike `|A - T|^2`, it carries no
render variance), taken as a median of means over pixel groups and plus one standard deviation (`score`). A finer
set follows around each of the best few distinct candidates (`BASINS`). The local solve starts from the best
candidate of the finer set; the next distinct ones are the restarts (`distinct_starts`).

A parameter the image is linear in (the intensity of a scene's only light) is not scanned: each candidate's best
value follows in closed form (`profile_linear`).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import jax
import numpy as np

from .params import SPECS, FitError
from .problem import Problem

PRIMES = (2, 3, 5, 7, 11, 13, 17, 19, 23, 29, 31, 37)


def halton(n: int, k: int, skip: int = 1) -> np.ndarray:
    """The first `n` points (after `skip`) of the k-dimensional Halton sequence in [0, 1)^k (k <= 12)."""
    if k > len(PRIMES):
        raise FitError(f"the global search handles at most {len(PRIMES)} parameters, got {k}")
    out = np.zeros((n, k))
    for j in range(k):
        b = PRIMES[j]
        for i in range(n):
            f, x, m = 1.0, 0.0, i + skip
            while m > 0:
                f /= b
                x += f * (m % b)
                m //= b
            out[i, j] = x
    return out


def scene_size(problem: Problem) -> float:
    """The scenes' length scale L (scene units): the longest camera-to-target distance of the views."""
    return max(float(np.linalg.norm(np.asarray(v.scene.camera.target) - np.asarray(v.scene.camera.origin)))
               for v in problem.views)


def param_range(name: str, x0: float, L: float) -> tuple[float, float]:
    """The search range of parameter `name` (its units) for starting value `x0` and scene size `L`
    (`ParamSpec.search`), always inside the valid open interval and containing `x0`."""
    spec = SPECS[name]
    kind = spec.search
    if kind == "extinction":  # optical depth 0.01 to 20 over the scene's size
        lo, hi = min(0.01 / L, x0 / 3), max(20.0 / L, 3 * x0)
    elif kind == "length":
        lo, hi = min(L / 30, x0 / 3), max(3 * L, 3 * x0)
    elif kind == "offset":
        lo, hi = x0 - L, x0 + L
    elif kind == "power":
        lo, hi = x0 / 30, 30 * x0
    elif isinstance(kind, tuple) and len(kind) == 2:
        lo, hi = min(kind[0], x0), max(kind[1], x0)
    else:
        raise FitError(f"parameter {name!r} has no search range (ParamSpec.search)")
    return max(lo, spec.lo), min(hi, spec.hi)


def search_box(names, init: dict, L: float) -> tuple[np.ndarray, np.ndarray]:
    """The box the search scans, in the unconstrained coordinates: `(lo, hi)`, each of shape `(k,)`."""
    lo, hi = [], []
    for n in names:
        a, b = param_range(n, float(init[n]), L)
        ua, ub = float(SPECS[n].to_u(np.float32(a))), float(SPECS[n].to_u(np.float32(b)))
        lo.append(min(ua, ub))
        hi.append(max(ua, ub))
    return np.asarray(lo), np.asarray(hi)


def linear_param(problem: Problem) -> int | None:
    """The index of a fitted parameter every image is linear in (the camera's `exposure`, or the intensity of the
    only light of every view's scene), or None."""
    if "exposure" in problem.names:
        return problem.names.index("exposure")
    if "intensity" in problem.names and all(len(v.scene.lights) == 1 for v in problem.views):
        return problem.names.index("intensity")
    return None


def profile_linear(A: np.ndarray, B: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Per candidate (rows of A, B: two independent renders, scaled units) the factor `a` that minimises the two-key
    loss `sum((a A - t)(a B - t))`: `a = sum((A + B) t) / (2 sum(A B))` (kept positive)."""
    num = 0.5 * ((A + B) @ t)
    den = np.sum(A * B, axis=1)
    return np.where(den > 0, np.maximum(num / np.where(den > 0, den, 1.0), 1e-6), 1.0)


@dataclass(frozen=True)
class Scan:
    """Candidates `Y` (`(N, k)`, unconstrained), their two-key losses, each view's render mean over its target's
    (`brightness`, `(N, views)`), the box `lo`, `hi` and the spacing `cell` of the coarse set (per coordinate)."""

    Y: np.ndarray
    loss: np.ndarray
    brightness: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    cell: np.ndarray


GROUPS = 8
"""The pixels of a candidate's loss are summed in this many interleaved groups, and the loss is the groups' median
sum times their number (median of means): one firefly pixel of a 32-spp render (seen: a backscattering candidate of
a point-lit room whose loss came out at -2.96, fifty times every other candidate's, from one pixel) moves one group,
not the loss. Eight groups: the median of 8 normal means has 1.16x the standard deviation of their mean (the
efficiency of a small-sample median), a price paid on every candidate alike."""


def robust_loss(terms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Median-of-means estimate of the summed per-pixel `terms` (`(N, P)`) and its standard deviation, per row:
    `(loss, sd)`, with the sd from the groups' median absolute deviation (1.4826 MAD, normal consistency) times the
    small-sample median's 1.16 and the square root of the number of groups (a sum of G group sums)."""
    n, p = terms.shape
    g = min(GROUPS, p)
    sums = np.stack([terms[:, j::g].sum(axis=1) * (p / len(range(j, p, g))) / g for j in range(g)], axis=1)
    med = np.median(sums, axis=1)
    mad = np.median(np.abs(sums - med[:, None]), axis=1)
    return g * med, 1.4826 * 1.16 * math.sqrt(g) * mad


def score(problem: Problem, Y: np.ndarray, key, spp: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Scores of the candidates `Y` (`(Y', score, brightness)`; a linear parameter profiled out, so `Y'` carries its
    best value; non-finite renders score +inf). The score is the two-key loss (`robust_loss`: a median of means over
    pixel groups, so a firefly pixel cannot carry a candidate) plus one standard deviation of it: the loss alone is
    unbiased but its noise differs between candidates, and its minimum over many candidates favours a noisy one
    (measured: a backlit spot fitted at g -0.9 and 4.5x the light's power, whose 32-spp renders' loss came out far
    below every other's)."""
    ka, kb = jax.random.split(key)
    A, B = problem.scan(Y, ka, spp), problem.scan(Y, kb, spp)
    Y = np.array(Y, np.float64)
    j = linear_param(problem)
    if j is not None:
        a = profile_linear(A, B, problem.t)
        A, B = A * a[:, None], B * a[:, None]
        Y[:, j] += np.log(a)
    terms = ((A - problem.t) * (B - problem.t)).reshape(len(Y), -1, 3).sum(axis=2)
    loss, sd = robust_loss(terms)
    loss = loss + sd
    loss = np.where(np.isfinite(loss), loss, np.inf)
    bright = np.stack([robust_brightness(x, t) for x, t in zip(problem.split(0.5 * (A + B)), problem.split(problem.t))],
                      axis=1)
    return Y, loss, bright


def robust_brightness(renders: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Each render's brightness relative to the target (`renders` `(N, h, w, C)`, `target` `(h, w, C)`): the median
    over `GROUPS` interleaved pixel groups of the group's render sum over its target sum, as the loss's median of
    means. One firefly pixel, in a render or in the target, moves one group (seen: a valid 256-spp target whose
    single pixel of 2195, the mean being 0.037, made its mean 15x its expectation and the plain-mean check refused
    it); without one, every group's ratio is the image's. NaN where no group has target light."""
    X = renders.reshape(len(renders), -1, renders.shape[-1]).sum(axis=2)
    T = target.reshape(-1, target.shape[-1]).sum(axis=1)
    g = min(GROUPS, T.size)
    num = np.stack([X[:, j::g].sum(axis=1) for j in range(g)], axis=1)
    den = np.array([T[j::g].sum() for j in range(g)])
    ratio = np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)
    if not np.any(den > 0):
        return np.full(len(renders), np.nan)
    with warnings.catch_warnings():  # a row of non-finite renders: NaN, which the check leaves out
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(ratio[:, den > 0], axis=1)


def candidates_count(k: int) -> int:
    """Candidates per scan stage for k parameters: 24 + 12 k, at most 128 (48 for the usual two). Measured: with
    16 + 8 k (40 for three parameters), a height fog lit by a point light (sigma_0, H, g) was started in three wrong
    basins and refused; with 60 it was found (+1.1%, +0.3%, -0.0002, within 0.2 se)."""
    return min(24 + 12 * k, 128)


BASINS = 3
"""The finer stage scans around this many distinct coarse candidates (each more than one coarse spacing from the
others), a third of its candidates each: around the single best one, a point-lit room with forward fog was started
in its backscattering basin, whose best coarse candidate (loss 0.06-0.11) beat the coarse ones nearest the truth
(0.10-0.13); scanned finer, the truth's basin reaches a loss near 0 and the wrong one stays at its bias."""


def global_search(problem: Problem, init: dict, key, spp: int) -> Scan:
    """The coarse Halton scan of `search_box`, the starting point among its candidates, then a finer scan of the
    same number of candidates in the boxes of one coarse spacing around the `BASINS` best distinct coarse ones."""
    names = problem.names
    k = len(names)
    lo, hi = search_box(names, init, scene_size(problem))
    N = candidates_count(k)
    Y0 = lo + (hi - lo) * halton(N - 1, k)
    y_init = np.asarray([float(SPECS[n].to_u(np.float32(init[n]))) for n in names])
    Y0 = np.vstack([y_init[None, :], Y0])
    Y0, loss0, b0 = score(problem, Y0, jax.random.fold_in(key, 0), spp)
    cell = (hi - lo) / N ** (1.0 / k)
    order0 = np.argsort(loss0)
    centres = distinct_starts(Scan(Y0[order0], loss0[order0], b0[order0], lo, hi, cell), BASINS)
    per = -(-N // max(len(centres), 1))
    Y1 = np.vstack([np.clip(c + cell * (2.0 * halton(per, k, skip=N) - 1.0), lo, hi) for c in centres])
    Y1, loss1, b1 = score(problem, Y1, jax.random.fold_in(key, 1), spp)
    # the two stages' losses share no keys: each stage's are comparable among themselves, the finer stage's best
    # is taken as the first start
    order1 = np.argsort(loss1)
    Y = np.vstack([Y1[order1], Y0[order0]])
    loss = np.concatenate([loss1[order1], loss0[order0]])
    bright = np.vstack([b1[order1], b0[order0]])
    return Scan(Y, loss, bright, lo, hi, cell)


def distinct_starts(scan: Scan, n: int) -> list[np.ndarray]:
    """Up to `n` starting points, best first: the finer stage's best, then the coarse candidates in order of loss,
    each more than one coarse spacing (in every coordinate's units of `cell`, max-norm) from every start before it."""
    starts: list[np.ndarray] = []
    for y, l in zip(scan.Y, scan.loss):
        if not np.isfinite(l):
            continue
        if all(np.max(np.abs(y - s) / scan.cell) > 1.0 for s in starts):
            starts.append(y)
        if len(starts) >= n:
            break
    return starts


def check_brightness(problem: Problem, scan: Scan, factor: float = 3.0) -> None:
    """Refuse a target that no candidate of the searched box renders within `factor` of its brightness: a target
    of another scene or at another exposure."""
    names = problem.names
    box = ", ".join(f"{n} {float(SPECS[n].from_u(np.float32(a))):.3g}..{float(SPECS[n].from_u(np.float32(b))):.3g}"
                    for n, a, b in zip(names, scan.lo, scan.hi))
    for i, v in enumerate(problem.views):
        b = scan.brightness[:, i]
        b = b[np.isfinite(b)]
        if b.size == 0:
            raise FitError(f"{v.name}: no render of the searched region ({box}) is finite")
        if b.max() < 1.0 / factor or b.min() > factor:
            raise FitError(
                f"{v.name}: the target is {1 / b.max():.3g}x to {1 / b.min():.3g}x as bright as the renders of the "
                f"whole searched region ({box}; {len(scan.Y)} candidates): a target of another scene, or at "
                f"another exposure?")
