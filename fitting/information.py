"""What the views determine: the eigen-decomposition of the Fisher information of a fit, in words.

The Fisher information of the fitted parameters is `F = J^T W J` (J the Jacobian of the rendered pixels, W the inverse
noise variance per pixel); `F^-1` is the covariance of the estimate. Parameters have different units, so `F` is first
brought to *relative units* (`relative_scales`): a positive quantity (extinction, intensity, diameter, scale height)
in fractions of its value, a bounded one (g, albedo, a lobe weight) and an unbounded one (base height) in its own
units. In those units the eigenvector `v_k` of `F` with eigenvalue `lambda_k` is a combination of the parameters that
the views determine to a standard error of `1 / sqrt(lambda_k)`: large eigenvalues are combinations the images pin,
small ones directions along which the images barely change (a ridge). Everything here is numpy on a given `F`;
`fitting.solver` builds `F` at the end of a fit (the inverse of the estimate's covariance).
"""

from __future__ import annotations

import numpy as np

from .params import SPECS

WELL = 0.02
"""A combination with a standard error at most this (relative units: 2%, or 0.02 in g) is "well determined": the
accuracy the foreign suite asks of a fit (`fitting.suite.tolerance`)."""

WEAK = 0.1
"""Above this standard error a combination is "weakly determined" (the fit's own `max_se` threshold, 10% / 0.1)."""

MIXED = 0.25
"""A parameter takes part in a combination when its component is at least this fraction of the largest one; below,
the combination is named after its largest component alone ("g alone")."""


def relative_scales(names, values) -> np.ndarray:
    """The unit of each parameter in relative units: `|value|` for a positive quantity (range `(0, inf)`, or a lower
    bound >= 0 and an upper bound above 1), 1 for the others (bounded within [-1, 1], or unbounded)."""
    return np.asarray([max(abs(float(values[n])), 1e-12) if _positive(n) else 1.0 for n in names], np.float64)


def _fmt_coef(c: float) -> str:
    return f"{abs(c):.2g}"


def combination(names, v) -> str:
    """The eigenvector `v` as a readable combination, its largest component scaled to 1 and positive:
    "sigma_t + 0.8 g", "g - 0.45 sigma_t"; components below `MIXED` of the largest are left out."""
    v = np.asarray(v, np.float64)
    k = int(np.argmax(np.abs(v)))
    v = v / v[k]
    terms = [names[k]]
    for i in np.argsort(-np.abs(v)):
        if i == k or abs(v[i]) < MIXED:
            continue
        terms.append(f"{'+' if v[i] > 0 else '-'} {_fmt_coef(v[i])} {names[i]}")
    return " ".join(terms)


def _word(se: float) -> str:
    if not np.isfinite(se):
        return "not determined"
    if se <= WELL:
        return "well determined"
    if se <= WEAK:
        return "determined"
    return "weakly determined"


def _se_text(se: float) -> str:
    return "inf" if not np.isfinite(se) else f"{se:.2g}"


def fisher_report(names, values, fisher) -> dict:
    """Eigen-decomposition of the Fisher information `fisher` (in the parameters themselves, `values` their
    estimate) in relative units. Returns {"units", "eigenvalues", "directions" (list, best determined first: each
    {"vector" (unit, in relative units), "combination", "se" (relative), "words"}), "summary" (sentences)}."""
    names = list(names)
    F = np.asarray(fisher, np.float64)
    D = relative_scales(names, values)
    Fz = 0.5 * (F + F.T) * np.outer(D, D)
    if not np.all(np.isfinite(Fz)):
        return {"units": _units(names, D), "eigenvalues": None, "directions": [],
                "summary": ["the Fisher information is not finite: nothing can be said about what the views determine"]}
    lam, V = np.linalg.eigh(Fz)
    order = np.argsort(-lam)
    lam, V = lam[order], V[:, order]
    dirs = []
    for k in range(len(names)):
        v = V[:, k] * (1.0 if V[np.argmax(np.abs(V[:, k])), k] > 0 else -1.0)
        se = 1.0 / np.sqrt(lam[k]) if lam[k] > 0 else np.inf
        dirs.append({"vector": [float(x) for x in v], "combination": combination(names, v), "se": float(se),
                     "words": _word(se)})
    return {"units": _units(names, D), "eigenvalues": [float(x) for x in lam], "directions": dirs,
            "summary": _sentences(names, dirs)}


def _positive(n) -> bool:
    spec = SPECS.get(n)
    return spec is not None and spec.lo >= 0.0 and spec.hi > 1.0


def _units(names, D):
    return {n: ("fraction of its value" if _positive(n) else "its own units") for n in names}


def _involved(names, v):
    v = np.asarray(v)
    m = np.max(np.abs(v))
    return [names[i] for i in range(len(names)) if abs(v[i]) >= MIXED * m]


def _sentences(names, dirs) -> list[str]:
    out = []
    for d in dirs:
        inv = _involved(names, d["vector"])
        se = _se_text(d["se"])
        if len(names) == 1:
            out.append(f"{names[0]} is {d['words']} (standard error {se})")
        elif len(inv) == 1:
            out.append(f"{inv[0]} alone is {d['words']} (standard error {se})")
        else:
            who = ", ".join(inv[:-1]) + " and " + inv[-1]
            out.append(f"{who} are {d['words']} together along {d['combination']} (standard error {se})")
    return out


def instead(names, values, fisher, loose) -> dict:
    """For each parameter in `loose` (its own standard error too large), the best-determined combination in which it
    takes part, as a sentence: "g: not pinned down alone; the views determine sigma_t + 0.8 g to 0.004 instead"."""
    rep = fisher_report(names, values, fisher)
    out = {}
    for n in loose:
        i = names.index(n)
        for d in rep["directions"]:
            if n in _involved(names, d["vector"]) and len(_involved(names, d["vector"])) > 1 \
                    and d["se"] <= WEAK:
                out[n] = (f"{n} is not pinned down alone; the views determine {d['combination']} to a standard "
                          f"error of {_se_text(d['se'])} (relative units) instead")
                break
        else:
            se_dir = [d["se"] for d in rep["directions"] if abs(d["vector"][i]) >= MIXED * max(map(abs, d["vector"]))]
            out[n] = (f"{n} is not pinned down, alone or in any combination the views determine (best standard "
                      f"error of a combination with it: {_se_text(min(se_dir) if se_dir else np.inf)})")
    return out


def rank_views(names, values, fisher, candidates: dict) -> list[dict]:
    """Which candidate view would shrink the uncertainty most. `fisher`: the fit's Fisher information (parameters'
    units; `C^-1` of its estimate); `candidates`: `{name: F_c}`, each candidate view's own Fisher information in the
    same units (a target of that view with the noise assumed by the caller). For each candidate, the information
    with it added, `F + F_c`, in relative units: the standard error of each parameter (`sqrt(diag((F + F_c)^-1))`)
    and of the worst-determined combination (`1 / sqrt(smallest eigenvalue)`). Returns one dict per candidate,
    smallest worst-determined standard error first: {"view", "se" (per parameter, relative units), "worst_se",
    "worst_se_before", "shrink" (worst_se_before / worst_se), "worst_combination" (the combination after adding it)}.
    A non-finite or singular sum gives infinite standard errors (ranked last)."""
    names = list(names)
    D = relative_scales(names, values)
    F0 = 0.5 * (np.asarray(fisher, np.float64) + np.asarray(fisher, np.float64).T) * np.outer(D, D)

    def worst(Fz):
        if not np.all(np.isfinite(Fz)):
            return np.inf, None
        lam, V = np.linalg.eigh(Fz)
        return (1.0 / np.sqrt(lam[0]) if lam[0] > 0 else np.inf), V[:, 0]

    before, _ = worst(F0)
    out = []
    for view, Fc in candidates.items():
        Fz = F0 + 0.5 * (np.asarray(Fc, np.float64) + np.asarray(Fc, np.float64).T) * np.outer(D, D)
        w, v = worst(Fz)
        try:
            se = np.sqrt(np.abs(np.diag(np.linalg.inv(Fz)))) if np.isfinite(w) else np.full(len(names), np.inf)
        except np.linalg.LinAlgError:
            se = np.full(len(names), np.inf)
        out.append({"view": view, "se": {n: float(x) for n, x in zip(names, se)}, "worst_se": float(w),
                    "worst_se_before": float(before), "shrink": float(before / w) if w > 0 else float("inf"),
                    "worst_combination": combination(names, v) if v is not None else None})
    return sorted(out, key=lambda d: d["worst_se"])
