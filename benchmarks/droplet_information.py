"""How much each view tells a fit about the droplet diameter: the Fisher information per view.

    python benchmarks/droplet_information.py [--spp 256] [--keys 4] [--views ...] [--out FILE.json]

For each view of the `droplet_8um` targets (and the narrow halo view at a few fields of view), at the truth
(d = 8 µm, sigma_t 0.3, albedo 0.9): the Jacobian of every pixel with respect to (d, sigma_t) by forward mode
(`jax.jacfwd` of `jaxfog.render`, the "proposal" estimator with the truth as its fixed reference: the fit's own
derivative), averaged over `--keys` keys of `--spp` samples each, with a central finite difference in d (same
estimator, reference and key, d +- 0.25 µm) as a check; and each pixel's per-sample variance (the render's
`variance=True`, pooled over the keys). Then, pooled to each fit resolution (box pooling as `fitting.problem.pool`; a
fit pixel's per-sample variance is the mean of its target pixels' plus the spread of their means),
the Fisher information of one channel (the fog is grey: the three channels carry the same noise)

    F = sum over fit pixels of j j^T / v,   j = (dI/dd, dI/dsigma_t),   v = per-sample variance / N

for N = 64 samples per fit pixel (one render of the fit's, `--spp 64`), with the bias of the averaged Jacobian's own
noise taken out (mean(j) mean(j)^T - cov(j) / keys). Reported: the standard error of d alone (sigma_t known) and
jointly with sigma_t, as a fraction of d, the correlation of the two estimates, and the same at the target's noise
(256 spp at 32 x 32, i.e. N = 256 f^2 per fit pixel of f x f target pixels). Prints a table, writes the JSON to
`--out` (default `bench_out/droplet_information/droplet_information.json`).
"""

from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # as a script: `benchmarks` importable
from benchmarks.common import Stopwatch, command, load, out_dir, print_json, print_table, write_json  # noqa: E402

TRUTH = {"diameter": 8.0, "sigma_t": 0.3, "albedo": 0.9}
VIEWS = {
    # name: (scene file, overrides)
    "backlit (fov 40)": ("droplet_fit_backlit", []),
    "side (fov 40)": ("droplet_fit_side", []),
    "halo fov 4": ("droplet_fit_halo", []),
    "halo fov 6": ("droplet_fit_halo", ["camera.fov=6"]),
    "halo fov 8": ("droplet_fit_halo", ["camera.fov=8"]),
}
FIT_SPP = 64
TARGET_SPP = 256
FD_STEP = 0.25


def pool(x, f):
    import numpy as np

    H, W = x.shape
    return x.reshape(H // f, f, W // f, f).mean(axis=(1, 3)) if f > 1 else np.asarray(x)


def measure(name, scene_name, overrides, spp, keys, seed0=30_000):
    import jax
    import jax.numpy as jnp
    import numpy as np

    import jaxfog
    from fitting.params import apply

    sf = load(scene_name, overrides=overrides)
    base = apply(sf.scene, TRUTH)
    ref = jax.lax.stop_gradient(base.medium)

    def f(p, key):
        scene = apply(base, {"diameter": p[0], "sigma_t": p[1]})
        img, var = jaxfog.render(scene, key, spp, estimator="proposal", proposal=ref, variance=True)
        return img[..., 0], (jax.lax.stop_gradient(img[..., 0]), jax.lax.stop_gradient(var[..., 0]))

    p0 = jnp.asarray([TRUTH["diameter"], TRUTH["sigma_t"]], jnp.float32)
    jac = jax.jit(jax.jacfwd(f, has_aux=True))
    Js, imgs, vs = [], [], []
    sw = Stopwatch()
    for k in range(keys):
        J, (img, var) = jac(p0, jax.random.key(seed0 + k))
        Js.append(np.asarray(J, np.float64))  # (H, W, 2)
        imgs.append(np.asarray(img, np.float64))
        vs.append(np.asarray(var, np.float64) * spp)  # per-sample variance
    key = jax.random.key(seed0)
    render = jax.jit(lambda p: f(p, key)[1][0])
    hi = np.asarray(render(p0.at[0].add(FD_STEP)), np.float64)
    lo = np.asarray(render(p0.at[0].add(-FD_STEP)), np.float64)
    fd = (hi - lo) / (2 * FD_STEP)
    wall, cpu = sw.stop(), sw.cpu_s
    J = np.stack(Js)  # (K, H, W, 2)
    v = np.mean(vs, axis=0)
    img = np.mean(imgs, axis=0)
    out = {"view": name, "scene": scene_name, "overrides": overrides, "spp": spp, "keys": keys,
           "fov": float(sf.scene.camera.fov), "size": [sf.scene.camera.width, sf.scene.camera.height],
           "mean": float(img.mean()), "dmean_dd_jvp_key0": float(J[0, ..., 0].mean()),
           "dmean_dd_fd_key0": float(fd.mean()),
           "dmean_dd": float(J[..., 0].mean()), "dmean_dd_se": float(J[..., 0].mean(axis=(1, 2)).std(ddof=1) / np.sqrt(keys)),
           "jvp_fd_max_abs_diff_rel": float(np.max(np.abs(J[0, ..., 0] - fd)) / max(np.max(np.abs(fd)), 1e-30)),
           "wall_s": round(wall, 1), "cpu_s": round(cpu, 1), "by_resolution": {}}
    H = J.shape[1]
    for fsz in (4, 2, 1):
        if H // fsz >= 8:
            out["by_resolution"][f"{H // fsz}x{H // fsz}"] = fisher(J, img, v, spp, fsz)
    return out


def fisher(J, img, v, spp: int, fsz: int) -> dict:
    """At the fit resolution of `fsz x fsz` target pixels per fit pixel, from the Jacobians `J` `(keys, H, W, 2)`,
    the mean image `img` and the per-sample variance `v`: per noise level (`fit_spp`, `target`) the Fisher information
    with the Jacobian's own noise taken out, the standard errors of d (alone and joint) and of sigma_t, and the
    correlation (module docstring)."""
    import numpy as np

    keys = J.shape[0]
    Jp = np.stack([np.stack([pool(J[k, ..., i], fsz) for i in range(2)], -1) for k in range(keys)])
    # per-sample variance of a fit pixel (a sample uniform over its f x f target pixels): the mean of their
    # variances plus the spread of their means (total variance), the latter less its estimate's own noise
    S = spp * keys
    spread = pool(img * img, fsz) - pool(img, fsz) ** 2 - (1 - 1 / fsz ** 2) * pool(v, fsz) / S
    vp = pool(v, fsz) + np.maximum(spread, 0.0)
    jm = Jp.mean(0)
    res = {}
    for label, N in (("fit_spp", FIT_SPP), ("target", TARGET_SPP * fsz * fsz)):
        w = N / np.maximum(vp, 1e-300)
        F = np.einsum("hwi,hwj,hw->ij", jm, jm, w)
        dev = Jp - jm
        Fnoise = np.einsum("khwi,khwj,hw->ij", dev, dev, w) / (keys - 1) / keys
        Fu = F - Fnoise
        C = np.linalg.inv(Fu)
        d, s = TRUTH["diameter"], TRUTH["sigma_t"]
        res[label] = {"N_per_fit_pixel": N, "F": Fu.tolist(), "F_noise_part": Fnoise.tolist(),
                      "se_d_alone_rel": float(1 / np.sqrt(Fu[0, 0]) / d),
                      "se_d_joint_rel": float(np.sqrt(C[0, 0]) / d) if C[0, 0] > 0 else float("inf"),
                      "se_sigma_joint_rel": float(np.sqrt(C[1, 1]) / s) if C[1, 1] > 0 else float("inf"),
                      "corr_d_sigma": float(C[0, 1] / np.sqrt(abs(C[0, 0] * C[1, 1])))}
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--keys", type=int, default=4)
    ap.add_argument("--views", nargs="*", default=list(VIEWS))
    ap.add_argument("--out", default=str(out_dir("droplet_information") / "droplet_information.json"))
    args = ap.parse_args(argv)
    from jaxfog.tools import use_cpu_cores

    use_cpu_cores()

    rows = []
    for name in args.views:
        scene, ov = VIEWS[name]
        r = measure(name, scene, ov, args.spp, args.keys)
        rows.append(r)
        print_json({k: r[k] for k in ("view", "mean", "dmean_dd", "dmean_dd_se", "dmean_dd_jvp_key0",
                                      "dmean_dd_fd_key0", "jvp_fd_max_abs_diff_rel", "wall_s", "cpu_s")})
        write_json(args.out, {"command": command("python benchmarks/droplet_information.py", argv), "truth": TRUTH,
                              "rows": rows})
    print()
    table = [{"view": r["view"], "res": res, **x} for r in rows for res, x in r["by_resolution"].items()]
    print_table(table, [("view", "view"), ("fit px", "res"),
                        *((h, lambda t, k=k: t["fit_spp"][k], ".3g") for h, k in (
                            ("SE(d) alone", "se_d_alone_rel"), ("SE(d) joint", "se_d_joint_rel"),
                            ("SE(s) joint", "se_sigma_joint_rel"))),
                        ("corr", lambda t: t["fit_spp"]["corr_d_sigma"], "+.2f"),
                        ("SE(d) alone, target's noise", lambda t: t["target"]["se_d_alone_rel"], ".3g"),
                        ("SE(d) joint, target's noise", lambda t: t["target"]["se_d_joint_rel"], ".3g")])
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
