"""Use every CPU core: expose them to JAX as devices, so that `render` traces its sample layers on all of them.

XLA runs one render's vectorized program on a single core of the CPU (measured: CPU time = wall time,
docs/results/bench/PROFILE.md). `render` splits each batch of sample layers across `jax.local_devices()` when there is more
than one; on a CPU machine there is one device unless JAX is told otherwise before it starts. The command-line entry
points (`jaxfog render`, `python -m fitting.fit`, `python -m benchmarks.bench`, ...) call `use_cpu_cores()` first; a Python user
calls it right after `import jaxfog`, before any JAX computation (or sets `jax_num_cpu_devices` themselves).
"""

from __future__ import annotations

import os
import warnings


def use_cpu_cores(n: int | None = None) -> int:
    """Ask JAX for `n` CPU devices (default: this process's CPU count, or `$JAXFOG_CPU_DEVICES`). Must run before JAX
    initialises its backends; afterwards it changes nothing and warns (`RuntimeWarning`) if the device count JAX has
    differs from `n`. Returns the number of local devices JAX then has."""
    import jax

    if n is None:
        env = os.environ.get("JAXFOG_CPU_DEVICES")
        if env:
            n = int(env)
        else:
            n = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    if n < 1:
        raise ValueError(f"number of CPU devices must be >= 1, got {n}")
    try:
        jax.config.update("jax_num_cpu_devices", int(n))
    except RuntimeError:  # backends already initialised: keep what there is, and say so
        have = jax.local_device_count()
        if have != n:
            warnings.warn(f"use_cpu_cores({n}): JAX has already started with {have} device(s), so this changes "
                          f"nothing; call it right after `import jaxfog`, before any JAX computation, or set "
                          f"JAXFOG_CPU_DEVICES / jax_num_cpu_devices before starting", RuntimeWarning, stacklevel=2)
    return jax.local_device_count()
