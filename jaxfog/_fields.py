"""Field converters and value checks shared by the scene Modules.

Converters make every physical value a strongly typed float32 array (a weakly typed Python float would compile a
second program when a fit later passes a float32 array). Checks run in the Modules' `__check_init__`: they test the
*float32* value (0.99999999 rounds to 1.0 in float32; 1e39 overflows), raise a `ValueError` naming the class, the
field and the valid range, and skip traced values (a Module rebuilt inside `jit` has no concrete values to check).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float


def vec3(x) -> Float[Array, "3"]:
    """A float32 3-vector."""
    return jnp.asarray(x, dtype=jnp.float32).reshape(3)


def rgb(x) -> Float[Array, "3"]:
    """A float32 RGB triple; a scalar sets all three channels."""
    x = jnp.asarray(x, dtype=jnp.float32)
    return jnp.broadcast_to(x, (3,)) if x.ndim == 0 else x.reshape(3)


def scalar(x) -> Float[Array, ""]:
    """A float32 scalar."""
    return jnp.asarray(x, dtype=jnp.float32).reshape(())


def concrete(x) -> np.ndarray | None:
    """`x` as a numpy array, or None if it is traced (inside `jit`, `grad`, `vmap`: nothing to check)."""
    if isinstance(x, jax.core.Tracer):
        return None
    return np.asarray(x)


def check_range(owner: str, name: str, x, lo=None, hi=None, lo_open=False, hi_open=False) -> None:
    """Raise `ValueError` unless every entry of the (float32) value `x` is finite and in the interval.

    `lo`/`hi` None mean unbounded; `*_open` exclude the bound. The message reads
    `"HenyeyGreenstein.g = 1.0 (as float32) is outside the valid range (-1, 1)"`.
    """
    v = concrete(x)
    if v is None:
        return
    ok = np.isfinite(v)
    if lo is not None:
        ok &= (v > lo) if lo_open else (v >= lo)
    if hi is not None:
        ok &= (v < hi) if hi_open else (v <= hi)
    if not np.all(ok):
        left = "(" if (lo_open or lo is None) else "["
        right = ")" if (hi_open or hi is None) else "]"
        text = f"{left}{'-inf' if lo is None else f'{lo:g}'}, {'inf' if hi is None else f'{hi:g}'}{right}"
        shown = v.item() if v.ndim == 0 else v.tolist()
        raise ValueError(f"{owner}.{name} = {shown} (as float32) is outside the valid range {text}")


def check_nonzero(owner: str, name: str, x) -> None:
    """Raise `ValueError` if the (concrete) vector `x` is zero or not finite: a direction or edge needs a length."""
    v = concrete(x)
    if v is None:
        return
    if not np.all(np.isfinite(v)) or not np.any(v != 0):
        raise ValueError(f"{owner}.{name} = {v.tolist()} must be a finite, non-zero vector")
