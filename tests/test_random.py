"""The paths' uniforms (`jaxfog._random`): range, determinism, uniformity and independence.

Each statistical check compares a statistic with its distribution under exact uniformity and independence, with a
tolerance of 6 standard deviations (a false alarm about once in 10^9 runs; seeds fixed)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxfog._random import mix, uniforms

N_ROWS, N_COLS = 16384, 63  # a 128 x 128 layer at depth 7 with 9 dimensions per bounce


@pytest.fixture(scope="module")
def u():
    return np.asarray(uniforms(jax.random.key(0), N_ROWS, N_COLS), dtype=np.float64)


def _chi2_ok(counts: np.ndarray) -> tuple[float, float]:
    """Pearson's chi-square against equal expected counts, and its 6-sigma bound (dof + 6 sqrt(2 dof))."""
    expected = counts.sum() / counts.size
    chi2 = float(((counts - expected) ** 2 / expected).sum())
    dof = counts.size - 1
    return chi2, dof + 6 * math.sqrt(2 * dof)


def test_range_dtype_and_determinism(u):
    assert u.shape == (N_ROWS, N_COLS)
    assert uniforms(jax.random.key(0), 4, 3).dtype == jnp.float32
    assert u.min() >= 0.0 and u.max() < 1.0
    np.testing.assert_array_equal(u, np.asarray(uniforms(jax.random.key(0), N_ROWS, N_COLS)))
    # Works with legacy uint32 keys too, and under jit.
    a = jax.jit(lambda k: uniforms(k, 8, 5))(jax.random.PRNGKey(3))
    assert a.shape == (8, 5) and bool(jnp.all((a >= 0) & (a < 1)))


def test_moments(u):
    n = u.size
    # mean 1/2 with sd sqrt(1/12 / n); variance 1/12 with sd sqrt(1/180 / n) (Var of (u - 1/2)^2 is 1/180)
    assert abs(u.mean() - 0.5) < 6 * math.sqrt(1 / 12 / n)
    assert abs(u.var() - 1 / 12) < 6 * math.sqrt(1 / 180 / n)


def test_one_dimensional_uniformity(u):
    counts = np.histogram(u, bins=256, range=(0, 1))[0]
    chi2, bound = _chi2_ok(counts)
    assert chi2 < bound, (chi2, bound)


@pytest.mark.parametrize("axis", ["columns", "rows"])
def test_neighbours_pairwise_uniform_and_uncorrelated(u, axis):
    """Pairs of neighbouring numbers (next dimension of a path, or the same dimension of the next pixel) fill the
    unit square evenly and are uncorrelated (sample correlation sd 1/sqrt(n))."""
    a, b = (u[:, :-1], u[:, 1:]) if axis == "columns" else (u[:-1, :], u[1:, :])
    a, b = a.ravel(), b.ravel()
    counts = np.histogram2d(a, b, bins=32, range=((0, 1), (0, 1)))[0]
    chi2, bound = _chi2_ok(counts)
    assert chi2 < bound, (chi2, bound)
    assert abs(np.corrcoef(a, b)[0, 1]) < 6 / math.sqrt(a.size)


def test_keys_give_independent_streams(u):
    v = np.asarray(uniforms(jax.random.fold_in(jax.random.key(0), 1), N_ROWS, N_COLS), dtype=np.float64)
    assert np.mean(u == v) < 1e-3  # equal float values only by chance (2^-24 per pair)
    assert abs(np.corrcoef(u.ravel(), v.ravel())[0, 1]) < 6 / math.sqrt(u.size)


def test_rows_are_not_shifted_copies(u):
    """No pixel's stream is another pixel's stream shifted by a few dimensions (the failure of a
    `hash(hash(row) + column)` design), nor do chance matches come in mirrored pairs (the failure of combining row and
    column hashes by XOR, caught by this test): across all pairs of rows, matches at any shift are as rare as chance allows."""
    values = u[:, :32]
    # For each value, which (row, column) holds it; a shifted copy would give many matches sharing one row pair.
    flat = values.ravel()
    order = np.argsort(flat, kind="stable")
    same = flat[order][1:] == flat[order][:-1]
    rows = order // values.shape[1]
    pairs = {(min(r1, r2), max(r1, r2)) for r1, r2 in zip(rows[:-1][same], rows[1:][same])}
    n_matches = int(same.sum())
    # Expected chance matches among n values on a 2^24 grid: n^2 / 2 / 2^24 (about 8000 here); a shifted copy of one
    # row would add 32 matches on one row pair. Every row pair with a match should have exactly one.
    expected = flat.size ** 2 / 2 / 2**24
    assert n_matches < expected + 6 * math.sqrt(expected)
    assert len(pairs) >= n_matches - 6  # almost every match is on its own row pair


def test_mix_is_a_bijection_on_a_sample():
    x = jnp.arange(1 << 20, dtype=jnp.uint32) * jnp.uint32(4093)
    assert np.unique(np.asarray(mix(x))).size == 1 << 20


def test_bad_sizes():
    with pytest.raises(ValueError, match="n_rows=0"):
        uniforms(jax.random.key(0), 0, 3)


def test_blocks_of_rows_match_the_whole_table(u):
    """Any block of rows drawn on its own (as each device draws its chunks) equals those rows of the whole table,
    with a static or a traced offset."""
    key = jax.random.key(0)
    np.testing.assert_array_equal(np.asarray(uniforms(key, 1000, N_COLS, 5000), np.float64), u[5000:6000])
    blk = jax.jit(lambda r: uniforms(key, 1024, N_COLS, r))(jnp.uint32(15360))
    np.testing.assert_array_equal(np.asarray(blk, np.float64), u[15360:])


def test_the_hash_barrier_changes_no_number():
    """`uniforms(..., once=barrier)` (the renderer's fusion barrier on the row and column hashes) draws bitwise the
    numbers `uniforms` draws without it."""
    from jaxfog._integrator import computed_once, make_tracer, SamplingOptions
    from jaxfog._scene import pack
    import jaxfog as jf

    scene = jf.load_scene("data_synthetic/scenes/spot_fog.json").scene
    tr = make_tracer(scene, pack(scene), SamplingOptions())._replace(barriers=True)
    key = jax.random.key(11)

    @jax.jit
    def both(row0):
        tr_g = tr._replace(guard=row0 != 7)
        return uniforms(key, 64, 45, row0), uniforms(key, 64, 45, row0, lambda x: computed_once(tr_g, x))

    a, b = both(jnp.uint32(1000))
    assert np.array_equal(np.asarray(a), np.asarray(b))
