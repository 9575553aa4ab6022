"""The paths' uniform random numbers: a counter-based integer hash keyed by a JAX PRNG key.

A sample layer needs `H*W x n_iterations x n_dims` uniforms (a million at 128 x 128 and depth 8). Drawing them with
`jax.random.uniform` (threefry-2x32, 20 rounds) cost 15% of a sample on a CPU (docs/results/bench/PROFILE.md); this hash costs
about a tenth of that. It is for Monte Carlo sampling only, not cryptography:

    h_row = mix(row ^ k0),  a_col = mix(col ^ k1),  u[row, col] = mix(mix(h_row + a_col) ^ k2) / 2^32   (uint32 arithmetic)

where `mix` is the `lowbias32` integer finalizer (C. Wellons, "Prospecting for hash functions", 2018: a bijection
of uint32 with full avalanche) and `k0, k1, k2` come from the key. Distinct rows have distinct `h_row` and distinct
columns distinct `a_col` (bijections), so no two pixels share a shifted copy of one stream; the outer two rounds mix
the pair. The pair is combined by addition, not XOR: with XOR every chance match `h_p ^ a_j == h_q ^ a_k` comes with
its mirror `h_p ^ a_k == h_q ^ a_j` (measured: 15 such pairs in a 128 x 128 layer). `tests/test_random.py` checks uniformity, independence of neighbouring numbers, and the key dependence.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray


def mix(x: Array) -> Array:
    """`lowbias32`: a bijective avalanche hash of uint32 (any shape, elementwise)."""
    x = x ^ (x >> 16)
    x = x * jnp.uint32(0x7FEB352D)
    x = x ^ (x >> 15)
    x = x * jnp.uint32(0x846CA68B)
    return x ^ (x >> 16)


def uniforms(key: PRNGKeyArray, n_rows: int, n_cols: int, row0=0, once: Callable = lambda x: x
             ) -> Float[Array, "n_rows n_cols"]:
    """Rows `row0 .. row0 + n_rows - 1` of the key's table of float32 uniforms in [0, 1) (multiples of 2^-24): a
    pure function of the key, the row and the column, so any block of rows can be drawn on its own.

    Rows are paths (pixels), columns a path's dimensions; `n_rows` in [1, 2^32], `n_cols` in [0, 2^32] (0: an empty
    table, for paths that draw nothing, e.g. `max_depth` 1 without area lights), `row0` (an int or a traced integer)
    wraps modulo 2^32. The three words keying the hash are drawn from `key` with `jax.random.bits`
    (one threefry call per key). `once`: as in `hashed_uniforms`."""
    if not (0 < n_rows <= 1 << 32 and 0 <= n_cols <= 1 << 32):
        raise ValueError(f"uniforms: n_rows={n_rows} must be in [1, 2^32] and n_cols={n_cols} in [0, 2^32]")
    k = key_words(key)
    rows = jnp.asarray(row0).astype(jnp.uint32) + jnp.arange(n_rows, dtype=jnp.uint32)
    return hashed_uniforms(k, rows[:, None], jnp.arange(n_cols, dtype=jnp.uint32)[None, :], once)


def key_words(key: PRNGKeyArray) -> Array:
    """The three uint32 words that key the hash (one threefry call)."""
    return jax.random.bits(key, (3,), jnp.uint32)


def hashed_uniforms(k: Array, rows: Array, cols: Array, once: Callable = lambda x: x) -> Float[Array, "..."]:
    """Entries `(rows, cols)` (uint32 arrays, broadcast together) of the table `uniforms` draws for the key whose
    `key_words` are `k`: lets a path draw its own numbers wherever it is traced (path regeneration).

    `once(x)` returns the pytree `x` unchanged; a caller passes a fusion barrier (`_integrator.computed_once`) so
    that XLA hashes each row and each column once, not once per entry of the table (speed only)."""
    h_row, a_col = once((mix(rows ^ k[0]), mix(cols ^ k[1])))
    x = mix(mix(h_row + a_col) ^ k[2])
    return (x >> 8).astype(jnp.float32) * jnp.float32(2.0**-24)
