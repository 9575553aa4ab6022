"""Figures of a fit: target | fit | difference for every view, and the convergence of loss and parameters."""

from __future__ import annotations

import os

import jax
import numpy as np


def _save(fig, path) -> None:
    tmp = f"{os.path.splitext(path)[0]}.tmp-{os.getpid()}.png"
    try:
        fig.savefig(tmp, dpi=90)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def _tonemap(x, scale):
    x = np.clip(x / scale, 0, 1)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def plot_comparison(path, views, result, truth, spp=16, full=None) -> None:
    """Per view: target | fit | fit - target. `full`: the same views at a finer resolution than the fit's (shown
    instead of the fit resolution: people look at images; `fit.preview_downscale`: at most 64 px a side), the
    difference pooled to the fit's resolution (what the fit compared; pooling averages the render noise). `spp` 16:
    the pooled difference still averages 16 x f^2 samples a block."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import jaxfog

    from .params import apply

    fig, axes = plt.subplots(len(views), 3, figsize=(9, 3.1 * len(views)), squeeze=False)
    from .problem import pool

    for row, v_fit in enumerate(views):
        v = full[row] if full is not None else v_fit
        scene = apply(v.scene, result.params)
        img = np.asarray(jaxfog.render(scene, jax.random.key(4242), spp))
        scale = float(np.percentile(v.target, 99.5)) or 1.0
        f = v.target.shape[0] // v_fit.target.shape[0]
        diff = pool(img - v.target, f).mean(axis=2)
        lim = float(np.percentile(np.abs(diff), 99)) or 1.0
        axes[row, 0].imshow(_tonemap(v.target, scale))
        axes[row, 0].set_title(f"target {v.name}", fontsize=8)
        axes[row, 1].imshow(_tonemap(img, scale))
        axes[row, 1].set_title(f"fit ({spp} spp)", fontsize=8)
        im = axes[row, 2].imshow(diff, cmap="RdBu_r", vmin=-lim, vmax=lim)
        axes[row, 2].set_title(f"fit - target (mean of RGB, {diff.shape[1]} x {diff.shape[0]} px)", fontsize=8)
        fig.colorbar(im, ax=axes[row, 2], fraction=0.046)
        for a in axes[row]:
            a.set_xticks([]); a.set_yticks([])
    est = ", ".join(f"{n}={result.params[n]:.4f}" + (f" (true {truth[n]:.4f})" if n in truth else "")
                    for n in result.names)
    fig.suptitle(("fit: " if result.success else "FAILED fit: ") + est, fontsize=9)
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)


def plot_convergence(path, result, truth) -> None:
    """The search and the rounds: the searched candidates over the first two parameters (colour: their two-key
    loss, lower is better; the starts, the estimate with its 2-se box, the truth where known), then each parameter
    per round with the estimate's 2-se band."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h, names = result.history, result.names
    search = result.search or {}
    fig, axes = plt.subplots(1, 1 + len(names), figsize=(3.2 * (1 + len(names)), 3))
    ax = axes[0]
    pts = np.asarray(search.get("points") or np.zeros((0, len(names) + 1)), np.float64)
    if len(pts) and len(names) >= 2:
        loss = pts[:, -1]
        ok = np.isfinite(loss)
        c = np.log10(np.maximum(loss[ok] - loss[ok].min(), 0) + 1e-4 * max(abs(loss[ok]).max(), 1e-12))
        sc = ax.scatter(pts[ok, 0], pts[ok, 1], c=c, s=10, cmap="viridis_r")
        fig.colorbar(sc, ax=ax, fraction=0.046).set_label("log10 loss above the best", fontsize=7)
        for st in search.get("starts", []):
            ax.plot(st[names[0]], st[names[1]], "o", mfc="none", mec="r", ms=8)
        se = [result.uncertainty[n]["se"] for n in names[:2]]
        ax.errorbar(result.params[names[0]], result.params[names[1]], xerr=2 * se[0], yerr=2 * se[1], fmt="r+")
        if names[0] in truth and names[1] in truth:
            ax.plot(truth[names[0]], truth[names[1]], "kx", ms=8)
        if SPECS_LOG(names[0]):
            ax.set_xscale("log")
        ax.set_xlabel(names[0], fontsize=8)
        ax.set_ylabel(names[1], fontsize=8)
        ax.set_title("search (o starts, + estimate ± 2 se, x truth)", fontsize=7)
    else:
        ax.axis("off")
    x = np.arange(len(h))
    for i, n in enumerate(names):
        ax = axes[1 + i]
        ax.plot(x, [e[n] for e in h], ".-", ms=3)
        est, se = result.params[n], result.uncertainty[n]["se"]
        if np.isfinite(se):
            ax.axhspan(est - 2 * se, est + 2 * se, color="C1", alpha=0.3, lw=0, label="estimate ± 2 se")
        if n in truth:
            ax.axhline(truth[n], color="k", ls="--", lw=1, label="true")
        ax.legend(fontsize=6)
        ax.set_title(n, fontsize=9)
        ax.set_xticks(x)
        ax.set_xticklabels([e["phase"][0] for e in h], fontsize=6)
        ax.set_xlabel("round (s search, a approach, e estimate)", fontsize=7)
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)


def SPECS_LOG(name) -> bool:
    """Whether a parameter is positive with a log coordinate (plotted on a log axis)."""
    from .params import LOG, SPECS

    return SPECS[name].transform is LOG
