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
    from .core import pool

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
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h = result.history
    names = result.names
    fig, axes = plt.subplots(1, 1 + len(names), figsize=(3.2 * (1 + len(names)), 3))
    x = np.arange(len(h))
    rounds = np.asarray([e["round"] for e in h]) if h else np.zeros(0)
    axes[0].semilogy(x, [e["loss"] for e in h], ".-", ms=3)
    axes[0].set_title("loss (sum of squared relative residuals)", fontsize=8)
    axes[0].set_xlabel("function evaluation")
    for i, n in enumerate(names):
        ax = axes[1 + i]
        ax.plot(x, [e[n] for e in h], ".-", ms=3)
        if n in truth:
            ax.axhline(truth[n], color="k", ls="--", lw=1, label="true")
            ax.legend(fontsize=7)
        ax.set_title(n, fontsize=9)
        ax.set_xlabel("function evaluation")
    for ax in axes:
        for b in np.flatnonzero(np.diff(rounds)) + 0.5:
            ax.axvline(b, color="0.8", lw=0.8)
    fig.suptitle("convergence (grey lines: a new round, re-centred proposal and fresh key)", fontsize=8)
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)
