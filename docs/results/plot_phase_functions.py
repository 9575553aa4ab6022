"""docs/results/phase_functions.png: two-term HG, Draine, Rayleigh and droplets against HG at matched E[cos].

    PYTHONPATH=. python docs/results/plot_phase_functions.py
"""

import jax.numpy as jnp
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import jaxfog  # noqa: E402

# 1 - cos theta on a grid fine at the forward peak (log spaced) and uniform beyond
OMC = np.unique(np.concatenate([np.geomspace(1e-9, 1e-2, 4000), np.linspace(1e-2, 2.0, 4000)]))
THETA = np.degrees(np.arccos(np.clip(1.0 - OMC, -1, 1)))


def values(phase):
    return np.asarray(phase.eval_polar(jnp.asarray(OMC, jnp.float32)), np.float64)


def mean_cos(p):  # E[cos] = 2 pi int p(mu) mu dmu (trapezoid in mu = 1 - omc)
    mu = 1.0 - OMC
    return float(2 * np.pi * np.trapezoid(p * mu, OMC)), float(2 * np.pi * np.trapezoid(p, OMC))


def main():
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    left = [("two-term HG (0.8, -0.4, w 0.7)", jaxfog.TwoTermHG(0.8, -0.4, 0.7)),
            ("Draine (g 0.5, alpha 20)", jaxfog.Draine(0.5, 20.0)),
            ("Draine (g 0.0, alpha 1) = Rayleigh", jaxfog.Draine(0.0, 1.0))]
    right = [(f"droplet d = {d:g} um", jaxfog.Droplet(d)) for d in (1.0, 5.0, 10.0, 30.0)]
    for ax, items in ((axes[0], left), (axes[1], right)):
        for i, (label, ph) in enumerate(items):
            p = values(ph)
            g, norm = mean_cos(p)
            c = f"C{i}"
            ax.semilogy(THETA, p, color=c, label=f"{label}: E[cos] {g:.3f}")
            ax.semilogy(THETA, values(jaxfog.HenyeyGreenstein(g)), color=c, ls="--", lw=0.9,
                        label=f"HG g = {g:.3f}")
            print(label, "E[cos]", round(g, 4), "integral", round(norm, 5))
        ax.set_xlabel("scattering angle theta (degrees)")
        ax.set_xlim(0, 180) if ax is axes[0] else (ax.set_xscale("log"), ax.set_xlim(0.01, 180))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    axes[0].set_ylabel("phase function (1/sr)")
    axes[0].set_title("two-term HG, Draine (solid); HG at matched E[cos] (dashed)", fontsize=10)
    axes[1].set_title("fog droplets, Jendersie & d'Eon 2023 (log theta: the forward peak)", fontsize=10)
    fig.tight_layout()
    fig.savefig("docs/results/phase_functions.png", dpi=110)


if __name__ == "__main__":
    main()
