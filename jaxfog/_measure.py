"""Measuring a process: compile time (from JAX's monitoring events) and peak memory. Shared by the CLI and the
benchmarks."""

from __future__ import annotations

import resource


class CompileTimer:
    """Sums JAX's tracing, lowering and backend-compile durations (jax.monitoring events) while active, in seconds."""

    EVENTS = (
        "/jax/core/compile/jaxpr_trace_duration",
        "/jax/core/compile/jaxpr_to_mlir_module_duration",
        "/jax/core/compile/backend_compile_duration",
    )

    def __init__(self):
        self.seconds = 0.0
        self._jm = None

    def _listener(self, event: str, duration: float, **kwargs) -> None:
        if event in self.EVENTS:
            self.seconds += duration

    def __enter__(self):
        try:
            import jax.monitoring

            jax.monitoring.register_event_duration_secs_listener(self._listener)
            self._jm = jax.monitoring
        except ImportError:  # fake renderers in tests
            self._jm = None
        return self

    def __exit__(self, *exc):
        if self._jm is not None:
            self._jm.unregister_event_duration_listener(self._listener)
        return False


def max_rss_mib() -> float:
    """Peak resident set size of this process so far, in MiB: `VmHWM` of `/proc/self/status` where there is one (it
    starts afresh at `exec`), else `getrusage(RUSAGE_SELF).ru_maxrss` (Linux keeps that one across `exec`, so a child
    started by a big parent would report the parent's size)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
