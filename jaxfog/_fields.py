"""Field converters shared by the scene Modules.

Converters make every physical value a strongly typed float32 array (a weakly typed Python float would compile a
second program when a fit later passes a float32 array). The checks of the values are `_validate`'s
(`check_range` with a `Range`, `check_vector`), run in the Modules' `__check_init__`.
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
