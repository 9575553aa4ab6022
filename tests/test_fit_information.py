"""The Fisher-information report (fitting/information.py) on synthetic Jacobians: no rendering."""

from __future__ import annotations

import numpy as np
import pytest

from fitting.information import combination, fisher_report, instead, relative_scales


def test_relative_scales():
    # sigma_t (positive) in fractions of its value, g (bounded) in its own units
    np.testing.assert_allclose(relative_scales(["sigma_t", "g"], {"sigma_t": 0.5, "g": 0.6}), [0.5, 1.0])


def test_eigen_directions_of_a_ridge():
    # Pixels that see (sigma_t/0.5 + 0.8 g) strongly and the orthogonal combination weakly: in relative units
    # z = (sigma_t / 0.5, g), J_z = a u^T + b w^T with u ~ (1, 0.8), w ~ (-0.8, 1)
    rng = np.random.default_rng(0)
    n = 400
    u = np.array([1.0, 0.8]) / np.hypot(1.0, 0.8)
    w = np.array([-0.8, 1.0]) / np.hypot(1.0, 0.8)
    Jz = np.outer(rng.normal(size=n) * 5.0, u) + np.outer(rng.normal(size=n) * 0.1, w)
    Jz -= 0  # noise variance 1 per pixel: F = J^T J
    D = np.array([0.5, 1.0])
    J_theta = Jz / D  # d pixel / d theta = d pixel / d z * dz/dtheta
    F = J_theta.T @ J_theta
    rep = fisher_report(["sigma_t", "g"], {"sigma_t": 0.5, "g": 0.6}, F)
    best, weak = rep["directions"]
    np.testing.assert_allclose(np.abs(best["vector"]), np.abs(u), atol=0.01)
    np.testing.assert_allclose(np.abs(weak["vector"]), np.abs(w), atol=0.01)
    assert best["combination"] == "sigma_t + 0.8 g"
    assert weak["combination"].startswith("g - 0.8 sigma_t")
    # standard errors along the directions: 1 / sqrt(n * variance of the coefficient)
    np.testing.assert_allclose(best["se"], 1 / np.sqrt(n * 25.0), rtol=0.1)
    np.testing.assert_allclose(weak["se"], 1 / np.sqrt(n * 0.01), rtol=0.1)
    assert best["words"] == "well determined" and weak["words"] == "weakly determined"
    assert "sigma_t and g are well determined together along sigma_t + 0.8 g" in rep["summary"][0]
    assert "weakly determined" in rep["summary"][1]
    # the eigen-directions reproduce the covariance: se along sigma_t alone from F^-1
    cov = np.linalg.inv(F)
    V = np.array([d["vector"] for d in rep["directions"]]).T
    cov_z = V @ np.diag(np.array([d["se"] for d in rep["directions"]]) ** 2) @ V.T
    np.testing.assert_allclose(cov_z, cov / np.outer(D, D), rtol=1e-6)
    # g on its own is too uncertain: the report names the combination that is determined instead
    msg = instead(["sigma_t", "g"], {"sigma_t": 0.5, "g": 0.6}, F, ["g"])["g"]
    assert "sigma_t + 0.8 g" in msg and "instead" in msg


def test_independent_parameters_are_named_alone():
    F = np.diag([1e6, 1e2])  # sigma_t to 0.1% of 1 (relative), g to 0.1
    rep = fisher_report(["sigma_t", "g"], {"sigma_t": 1.0, "g": 0.0}, F)
    assert rep["summary"][0].startswith("sigma_t alone is well determined")
    assert rep["summary"][1].startswith("g alone is determined")
    msg = instead(["sigma_t", "g"], {"sigma_t": 1.0, "g": 0.0}, np.diag([1e6, 1.0]), ["g"])["g"]
    assert "not pinned down, alone or in any combination" in msg


def test_singular_and_non_finite_information():
    F = np.array([[1.0, 1.0], [1.0, 1.0]]) * 1e4  # only sigma_t + g is seen (relative units, sigma_t = 1)
    rep = fisher_report(["sigma_t", "g"], {"sigma_t": 1.0, "g": 0.0}, F)
    assert rep["directions"][0]["combination"] == "sigma_t + 1 g" or rep["directions"][0]["combination"] == "g + 1 sigma_t"
    assert rep["directions"][1]["words"] in ("not determined", "weakly determined")
    rep = fisher_report(["sigma_t"], {"sigma_t": 1.0}, [[np.nan]])
    assert rep["directions"] == [] and "not finite" in rep["summary"][0]


def test_combination_text():
    assert combination(["a", "b", "c"], [0.1, -1.0, 0.5]) == "b - 0.5 c"
    assert combination(["a", "b"], [-2.0, -1.0]) == "a + 0.5 b"


def test_block_noise_estimates_the_pooled_pixel_variance():
    from fitting.problem import block_noise, pool

    rng = np.random.default_rng(1)
    H = W = 64
    yy, xx = np.mgrid[0:H, 0:W]
    ramp = (0.5 + 0.01 * xx + 0.02 * yy)[..., None] * np.ones(3)  # a linear trend: second differences cancel it
    assert np.max(block_noise(ramp, 8)) < 1e-20
    sd = 0.1
    noisy = ramp + rng.normal(scale=sd, size=ramp.shape)
    v = block_noise(noisy, 8)
    assert v.shape == pool(noisy, 8).shape
    np.testing.assert_allclose(np.mean(v), sd ** 2 / 64, rtol=0.05)  # a pooled pixel: v / f^2


def test_compilation_cache_dir(monkeypatch, tmp_path):
    from jaxfog._cache import cache_dir

    monkeypatch.setenv("JAXFOG_CACHE_DIR", "off")
    assert cache_dir() is None
    monkeypatch.setenv("JAXFOG_CACHE_DIR", str(tmp_path / "c"))
    assert cache_dir() == str(tmp_path / "c")
    monkeypatch.delenv("JAXFOG_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert cache_dir() == str(tmp_path / "jaxfog" / "xla")


def test_the_compilation_cache_is_locked_for_processes_that_share_it(tmp_path):
    """`use_compilation_cache` gives JAX's cache a size limit, which makes JAX lock the directory around each read and
    write (`filelock`): without one a process could read an entry another is still writing (a segfault in XLA).
    A limit the caller set stays; the caller's settings are restored afterwards."""
    import jax

    from jaxfog._cache import CACHE_MAX_BYTES, use_compilation_cache

    keep = (jax.config.jax_compilation_cache_dir, jax.config.jax_compilation_cache_max_size)
    try:
        jax.config.update("jax_compilation_cache_max_size", -1)
        assert use_compilation_cache(str(tmp_path / "a")) == str(tmp_path / "a")
        assert jax.config.jax_compilation_cache_max_size == CACHE_MAX_BYTES
        jax.config.update("jax_compilation_cache_max_size", 123 << 20)
        use_compilation_cache(str(tmp_path / "b"))
        assert jax.config.jax_compilation_cache_max_size == 123 << 20
    finally:
        jax.config.update("jax_compilation_cache_dir", keep[0])
        jax.config.update("jax_compilation_cache_max_size", keep[1])


def test_cache_entries_without_an_access_time_get_one_so_that_later_writes_succeed(tmp_path):
    """An entry written without a size limit has no access-time file, and JAX's size-limited cache then fails every
    later write (FileNotFoundError while it reads each entry's access time before evicting). `use_compilation_cache`
    gives such entries one; entries that have one keep theirs."""
    import jax
    from jax._src.lru_cache import LRUCache

    from jaxfog._cache import repair_access_times, use_compilation_cache

    folder = tmp_path / "c"
    LRUCache(str(folder), max_size=1 << 20).put("kept", b"y" * 10)
    kept_time = (folder / "kept-atime").read_bytes()
    LRUCache(str(folder), max_size=-1).put("old", b"x" * 10)  # no limit: no access-time file
    assert not (folder / "old-atime").exists()
    with pytest.raises(FileNotFoundError):  # the failure this repairs
        LRUCache(str(folder), max_size=1 << 20).put("new", b"z" * 10)
    keep = (jax.config.jax_compilation_cache_dir, jax.config.jax_compilation_cache_max_size)
    try:
        assert use_compilation_cache(str(folder)) == str(folder)
    finally:
        jax.config.update("jax_compilation_cache_dir", keep[0])
        jax.config.update("jax_compilation_cache_max_size", keep[1])
    assert len((folder / "old-atime").read_bytes()) == 8 and (folder / "kept-atime").read_bytes() == kept_time
    LRUCache(str(folder), max_size=1 << 20).put("new", b"z" * 10)
    assert LRUCache(str(folder), max_size=1 << 20).get("new") == b"z" * 10
    assert repair_access_times(str(folder)) == 0 and repair_access_times(str(tmp_path / "missing")) == 0
