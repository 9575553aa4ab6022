"""`jaxfog.tools.StoredProgram`: a function's traced program kept on disk and used by the next process.

Every check compares a stored program's outputs with `jax.jit` of the same function on the same inputs. Both compile
the same computation, so they agree to float32 rounding: the tolerance is a few units in the last place (rtol 1e-6),
not a statistical one."""

from __future__ import annotations

import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxfog.tools import StoredProgram, program_dir


class Lens(eqx.Module):
    """A pytree with an array and a static field, as the renderer's Modules are."""

    power: jax.Array
    mode: str = eqx.field(static=True)


def _fn(lens, x, key, n):
    """A function of arrays, a Module with a static field, a typed PRNG key and a Python int."""
    noise = jax.random.normal(key, x.shape)
    y = x * lens.power + noise
    y = jnp.tanh(y) if lens.mode == "tanh" else jnp.sin(y)
    return jax.jacfwd(lambda p: (y * p) ** n)(lens.power), [y.sum()]


@pytest.fixture
def store(tmp_path):
    """A folder of the test's own for the stored programs."""
    return tmp_path / "programs"


def _args(mode="tanh", n=2, seed=0):
    return (Lens(jnp.float32(1.5), mode), jnp.linspace(-1, 1, 7, dtype=jnp.float32), jax.random.key(seed), n)


def _same(a, b):
    for u, v in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_allclose(np.asarray(u), np.asarray(v), rtol=1e-6, atol=1e-7)


def test_a_stored_program_is_written_then_read_back_by_a_new_instance_and_gives_jits_outputs(store):
    args = _args()
    want = jax.jit(_fn, static_argnums=3)(*args)
    first = StoredProgram("t", _fn, str(store))
    _same(first(*args), want)
    files = sorted(os.listdir(store))
    assert len(files) == 1 and files[0].startswith("t-") and files[0].endswith(".jaxexport")
    # a fresh instance (as in the next process) reads it: nothing new is written, same outputs on new inputs
    second = StoredProgram("t", _fn, str(store))
    other = _args(seed=3)
    _same(second(*other), jax.jit(_fn, static_argnums=3)(*other))
    assert sorted(os.listdir(store)) == files


def test_a_change_of_a_static_value_is_another_program(store):
    prog = StoredProgram("t", _fn, str(store))
    for mode, n in [("tanh", 2), ("sin", 2), ("tanh", 3)]:
        args = _args(mode, n)
        _same(prog(*args), jax.jit(_fn, static_argnums=3)(*args))
    assert len(os.listdir(store)) == 3


def test_another_shape_is_another_program(store):
    prog = StoredProgram("t", _fn, str(store))
    lens, _, key, n = _args()
    for size in (7, 9):
        x = jnp.linspace(-1, 1, size, dtype=jnp.float32)
        _same(prog(lens, x, key, n), jax.jit(_fn, static_argnums=3)(lens, x, key, n))
    assert len(os.listdir(store)) == 2


def test_a_value_that_cannot_be_keyed_is_only_compiled(store):
    """A static value whose repr names an object's address cannot be told apart from another: no file."""
    class Opaque:
        pass

    def fn(x, tag):
        return (x * 2.0,)

    prog = StoredProgram("t", fn, str(store))
    _same(prog(jnp.ones(3), Opaque()), (2.0 * jnp.ones(3),))
    assert not store.exists() or not os.listdir(store)


def test_a_damaged_stored_program_is_replaced(store):
    args = _args()
    StoredProgram("t", _fn, str(store))(*args)
    (path,) = [store / f for f in os.listdir(store)]
    path.write_bytes(b"not a program")
    _same(StoredProgram("t", _fn, str(store))(*args), jax.jit(_fn, static_argnums=3)(*args))
    assert path.read_bytes() != b"not a program"


def test_without_a_compilation_cache_nothing_is_stored(monkeypatch):
    """Without JAX's persistent cache there is no folder and the program is only jit-compiled; with it, the
    programs go beside it."""
    import jaxfog._programs as programs

    monkeypatch.setattr(programs, "_xla_cache_dir", lambda: "/somewhere/xla/")
    assert program_dir() == "/somewhere/xla-programs"
    monkeypatch.setattr(programs, "_xla_cache_dir", lambda: None)
    assert program_dir() is None
    args = _args()
    prog = StoredProgram("t", _fn)
    _same(prog(*args), jax.jit(_fn, static_argnums=3)(*args))
    assert prog._program("x", *_parts(args))[1] is None


def _parts(args):
    dynamic, static = eqx.partition(args, eqx.is_array)
    leaves, treedef = jax.tree.flatten(dynamic)
    from jaxfog._programs import _split_keys

    leaves, impls = _split_keys(leaves)
    return static, treedef, leaves, impls


def test_the_folder_keeps_the_most_recently_written_programs(store, monkeypatch):
    import jaxfog._programs as programs

    monkeypatch.setattr(programs, "MAX_FILES", 2)
    prog = StoredProgram("t", _fn, str(store))
    lens, _, key, n = _args()
    written = []
    for size in (5, 6, 7):
        before = set(os.listdir(store)) if store.exists() else set()
        prog(lens, jnp.linspace(-1, 1, size, dtype=jnp.float32), key, n)
        written += sorted(set(os.listdir(store)) - before)
    assert len(written) == 3  # one program per shape
    assert sorted(os.listdir(store)) == sorted(written[1:])  # the oldest removed
