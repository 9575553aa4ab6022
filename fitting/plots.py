"""Figures of a fit: target | fit | difference for every view, and the convergence of loss and parameters."""

from __future__ import annotations

import os
import threading

import numpy as np


def _import_pyplot() -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot  # noqa: F401


def preload() -> threading.Thread:
    """Import matplotlib (Agg) on a background thread: the fit's renders release the interpreter while XLA runs, so
    the import (~1 s on a 2-core CPU) overlaps them instead of delaying the figures. Importing the same module
    from two threads is safe (Python's per-module import locks); a failed import shows when the figures import it."""
    t = threading.Thread(target=lambda: _quiet(_import_pyplot), name="preload-matplotlib", daemon=True)
    t.start()
    return t


def _quiet(fn) -> None:
    try:
        fn()
    except Exception:  # reported where the figures import it
        pass


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


def plot_comparison(path, views, result, truth, full=None) -> None:
    """Per view: the target (at `full`'s finer resolution where given: people look at images), the target at the fit
    resolution, the fit there (`FitResult.images`: no render of its own) and fit - target (the mean of RGB, what the
    fit compared); a photograph's masked pixels (clipped, crushed or the user's) tinted red and grey."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(views), 4, figsize=(12, 3.1 * len(views)), squeeze=False)
    for row, v in enumerate(views):
        big = full[row].target if full is not None else v.target
        img = np.asarray(result.images[row]) if result.images else np.full(v.target.shape, np.nan)
        scale = float(np.percentile(big, 99.5)) or 1.0
        h, w = v.target.shape[:2]
        masked = np.zeros((h, w), bool) if getattr(v, "valid", None) is None else ~np.asarray(v.valid, bool)
        diff = np.where(masked, np.nan, (img - v.target).mean(axis=2))
        lim = float(np.nanpercentile(np.abs(diff), 99)) or 1.0
        small = _tonemap(v.target, scale)
        small[masked] = 0.6 * small[masked] + 0.4 * np.array([1.0, 0.0, 0.0])  # masked pixels tinted red
        tag = f", {int(masked.sum())} masked (red)" if masked.any() else ""
        for col, (pic, title) in enumerate([(_tonemap(big, scale), f"target {v.name}"),
                                            (small, f"target at {w} x {h} px{tag}"), (_tonemap(img, scale), "fit")]):
            axes[row, col].imshow(pic, interpolation="nearest")
            axes[row, col].set_title(title, fontsize=8)
        cmap = matplotlib.colormaps["RdBu_r"].with_extremes(bad="0.5")
        im = axes[row, 3].imshow(diff, cmap=cmap, vmin=-lim, vmax=lim,
                                 interpolation="nearest")
        axes[row, 3].set_title("fit - target (mean of RGB)" + (", masked grey" if masked.any() else ""), fontsize=8)
        fig.colorbar(im, ax=axes[row, 3], fraction=0.046)
        for a in axes[row]:
            a.set_xticks([])
            a.set_yticks([])
    est = ", ".join(f"{n}={result.params[n]:.4g}" + (f" (true {truth[n]:.4g})" if n in truth else "")
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
