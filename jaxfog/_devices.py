"""Use every CPU core: expose them to JAX as devices, so that `render` traces its sample layers on all of them.

XLA runs one render's vectorized program on a single core of the CPU (measured: CPU time = wall time,
docs/results/bench/PROFILE.md). `render` splits each batch of sample layers across `jax.devices()` when there is more
than one; on a CPU machine there is one device unless JAX is told otherwise before it starts. The command-line entry
points (`jaxfog render`, `python -m fitting.fit`, `python -m benchmarks.bench`, ...) call `use_cpu_cores()` first; a Python user
calls it right after `import jaxfog`, before any JAX computation (or sets `jax_num_cpu_devices` themselves).

`render_devices(devices)` is the device list `render(..., devices=...)` splits a render's work items over: by default
`jax.devices()`, which after `jax.distributed.initialize` (`jaxfog._distributed`, docs/distributed.md) holds the
devices of every process of the run, so the same `render` call made by every process renders one image on all of them.
"""

from __future__ import annotations

import numbers
import os
import warnings
from collections.abc import Sequence


def use_cpu_cores(n: int | None = None) -> int:
    """Ask JAX for `n` CPU devices (default: this process's CPU count, or `$JAXFOG_CPU_DEVICES`). Must run before JAX
    initialises its backends; afterwards it changes nothing and warns (`RuntimeWarning`) if the device count JAX has
    differs from `n`. Returns the number of CPU devices JAX will start with (`n`), or once started the number of local
    devices it has. It does not start JAX itself, so `jax.distributed.initialize` may still follow it."""
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
        return have
    return int(n)  # (asking JAX for its device count here would start it: no jax.distributed.initialize after)


def render_devices(devices=None) -> tuple:
    """The devices `render` shares a render's work items among, in order, from its `devices` argument:

    - `None` (the default): `jax.devices()`, every device of the default backend; after `jax.distributed.initialize`
      those of every process (each process must then make the same `render` call: one image on all of them), else
      this process's;
    - an integer `n`: the first `n` of this process's devices (`jax.local_devices()`), in `[1, local device count]`;
    - a sequence of `jax.Device`: those, distinct, on one platform, at least one of them this process's (after
      `jax.distributed.initialize` it may hold other processes' devices, e.g. `jax.devices()`; each of their
      processes must make the same call with the same list).

    Raises `TypeError` / `ValueError` naming the argument, the value and what is valid."""
    import jax

    if devices is None:
        return tuple(jax.devices())
    if isinstance(devices, numbers.Integral) and not isinstance(devices, bool):
        n = jax.local_device_count()
        if not 1 <= devices <= n:
            raise ValueError(f"render: devices must be None, an integer in [1, {n}] or a list of jax devices, "
                             f"got {devices!r}")
        return tuple(jax.local_devices()[:int(devices)])
    if not is_device_list(devices):
        raise TypeError(f"render: devices must be None, an integer (the first n local devices) or a list of jax "
                        f"devices (e.g. jax.devices()), got {devices!r}")
    devs = tuple(devices)
    if not devs:
        raise ValueError("render: devices: got an empty list; expected at least one jax device (e.g. jax.devices())")
    if len(set(devs)) != len(devs):
        raise ValueError(f"render: devices: a device is listed twice in {list(devs)}; expected distinct devices")
    platforms = sorted({d.platform for d in devs})
    if len(platforms) > 1:
        raise ValueError(f"render: devices: devices of several platforms ({', '.join(platforms)}); expected "
                         f"devices of one platform")
    if not any(d.process_index == jax.process_index() for d in devs):
        raise ValueError(f"render: devices: none of the {len(devs)} devices belongs to this process (process "
                         f"{jax.process_index()} of {jax.process_count()}); a process renders on its own devices "
                         f"(and, after jax.distributed.initialize, on other processes' too)")
    return devs


def is_device_list(devices) -> bool:
    """Whether `devices` is a sequence (not a string) of `jax.Device`s (the list form of `render`'s `devices`)."""
    import jax

    return (isinstance(devices, Sequence) and not isinstance(devices, (str, bytes))
            and all(isinstance(d, jax.Device) for d in devices))
