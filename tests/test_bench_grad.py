"""The gradient benchmark's statistics (benchmarks.bench_grad) on synthetic numbers with known answers; the end-to-end
`--quick` run (a few minutes: it compiles several programs) is marked slow."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from benchmarks import bench_grad

REPO = Path(__file__).resolve().parent.parent


def _ref(mean, se=0.0, n=2):
    mean = np.asarray(mean, float)
    return {"mean": mean, "mean_se": np.full(3, se), "blocks": np.broadcast_to(mean[:, None, None], (3, n, n)).copy(),
            "blocks_se": np.full((3, n, n), se)}


def test_error_metrics_rmse_bias_and_reference_correction():
    rng = np.random.default_rng(0)
    ref = _ref([-0.1, 0.02, 0.5], se=0.001)
    runs = 4000
    noise = np.array([0.01, 0.004, 0.02])
    bias = np.array([0.0, 0.002, 0.0])
    s = ref["mean"] + bias + noise * rng.standard_normal((runs, 3))
    blocks = np.broadcast_to(s[:, :, None, None], (runs, 3, 2, 2))
    m = bench_grad.error_metrics(s, blocks, ref)
    want = np.sqrt(noise**2 + bias**2) / np.abs(ref["mean"])
    np.testing.assert_allclose(m["rel_rmse"], want, rtol=0.05)  # 4000 runs: RMSE estimated to ~1.1%
    np.testing.assert_allclose(m["rel_rmse_corrected"], np.sqrt(noise**2 + bias**2 - 0.001**2) / np.abs(ref["mean"]),
                               rtol=0.05)
    # bias z: ~0 for unbiased parameters, large for the biased one (0.002 / (0.004/sqrt(4000) + 0.001) ~ 1.9)
    assert abs(m["bias_z"][0]) < 4 and abs(m["bias_z"][2]) < 4
    assert m["bias_z"][1] == pytest.approx(0.002 / np.hypot(0.004 / np.sqrt(runs), 0.001), rel=0.1)
    np.testing.assert_allclose(m["block_rel_rmse"], m["rel_rmse"], rtol=1e-9)  # blocks equal to the mean here


def test_choose_default_takes_the_smallest_geometric_mean_and_rejects_infinite():
    def est(t10):
        return {"t10_s": list(t10)}
    error = {"a": {"estimators": {"detached": est([1, 4]), "reparam": est([0.1, np.inf]),
                                  "detached, no equiangular": est([1, 1]), "proposal (ref off)": est([1e-3, 1e-3])}},
             "b": {"estimators": {"detached": est([1, 1]), "reparam": est([0.1, 0.1]),
                                  "detached, no equiangular": est([4, 4]), "proposal (ref off)": est([1e-3, 1e-3])}}}
    got = bench_grad.choose_default(error)
    assert got["default"] == "detached"  # geomean 1.41 vs 2 ("no equiangular"); reparam biased (inf); proposal excluded
    assert got["scores_geomean_t10_s"]["reparam"] == float("inf")
    assert "proposal (ref off)" not in got["scores_geomean_t10_s"]


@pytest.mark.slow
def test_quick_run_writes_json_and_plot(tmp_path):
    out = tmp_path / "bg"
    r = subprocess.run([sys.executable, "-m", "benchmarks.bench_grad", "--quick", "--out", str(out)], cwd=REPO,
                       capture_output=True, text=True, timeout=1800)
    assert r.returncode == 0, r.stderr[-2000:]
    assert (out / "bench_grad.json").exists() and (out / "grad_rmse_vs_time.png").exists()
    assert "default for gradients" in r.stdout
