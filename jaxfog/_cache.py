"""JAX's persistent compilation cache for the command-line entry points, so that a second run of the same job does
not compile its programs again (XLA compiles each render program in seconds to tens of seconds on a CPU; the cache
keeps the compiled executables on disk, keyed by the program, the JAX/XLA version and the devices).

The cache directory is `$JAXFOG_CACHE_DIR` if set, else `$XDG_CACHE_HOME/jaxfog/xla` (default `~/.cache/jaxfog/xla`);
`JAXFOG_CACHE_DIR=off` (or `0`, `none`, empty) disables it. Every program that takes at least
`MIN_COMPILE_TIME_S` to compile is cached.
"""

from __future__ import annotations

import os
import time
import warnings

MIN_COMPILE_TIME_S = 0.0
"""Every program is written to the cache, the small ones too: reading an entry back costs ~1-10 ms, while each of
the fit's ~80 small eager programs (parameter transforms, medium constructors, pooling) compiles in 30-90 ms; at the
former 0.1 s threshold they cost the main job ~3 s of XLA compilation on every run (`JAX_LOG_COMPILES=1`, 2-core
CPU)."""

_OFF = {"", "0", "off", "none", "false", "no"}

CACHE_MAX_BYTES = 4 << 30
"""The compilation cache's size limit (4 GiB; JAX evicts the least recently used entries above it). Any limit makes
JAX lock the cache directory (`filelock`) around each read and write; without one it writes entries in place, and a
process that reads an entry another process is still writing hands XLA a truncated executable: a segmentation fault
in `compilation_cache.get_executable_and_time`, seen once when a fit ran beside the test suite (2026-12-05). The
shipped runs fill about 100 MB."""


def cache_dir() -> str | None:
    """The persistent cache directory the entry points use, or None when `JAXFOG_CACHE_DIR` disables it."""
    env = os.environ.get("JAXFOG_CACHE_DIR")
    if env is not None:
        return None if env.strip().lower() in _OFF else os.path.expanduser(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "jaxfog", "xla")


def use_compilation_cache(path: str | None = None) -> str | None:
    """Turn on JAX's persistent compilation cache in `path` (default: `cache_dir()`). Returns the directory in use, or
    None when disabled or when the directory cannot be created (then it warns and the run compiles as usual)."""
    import jax

    if jax.config.jax_compilation_cache_dir and path is None:  # set by the caller already: keep theirs
        return jax.config.jax_compilation_cache_dir
    path = path if path is not None else cache_dir()
    if path is None:
        return None
    try:
        os.makedirs(path, exist_ok=True)
    except OSError as e:
        warnings.warn(f"compilation cache disabled: cannot create {path}: {e.strerror or e}", RuntimeWarning,
                      stacklevel=2)
        return None
    jax.config.update("jax_compilation_cache_dir", path)
    if jax.config.jax_compilation_cache_max_size == -1:  # unbounded (JAX's default): reads and writes are unlocked
        jax.config.update("jax_compilation_cache_max_size", CACHE_MAX_BYTES)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_TIME_S)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    repair_access_times(path)
    return path


def repair_access_times(path: str) -> int:
    """Give every entry of the cache folder `path` that has no access-time file one (now); returns how many.

    With a size limit, JAX reads every entry's access-time file before each write (`LRUCache._evict_if_needed`).
    An entry written by a process without a limit (an older jaxfog, or JAX's own defaults on the same folder) has
    none, and then every later write fails with FileNotFoundError: nothing new is cached, and each run compiles again
    (seen on a shared cache with 173 such entries: 39 failed writes in one test run)."""
    try:
        from jax._src.lru_cache import _ATIME_SUFFIX, _CACHE_SUFFIX
    except ImportError:  # JAX's private names; these are their values in JAX 0.4.30 to 0.10
        _ATIME_SUFFIX, _CACHE_SUFFIX = "-atime", "-cache"
    try:
        names = set(os.listdir(path))
    except OSError:
        return 0
    stamp = time.time_ns().to_bytes(8, "little")
    repaired = 0
    for name in names:
        if name.endswith(_CACHE_SUFFIX) and name[: -len(_CACHE_SUFFIX)] + _ATIME_SUFFIX not in names:
            try:
                with open(os.path.join(path, name[: -len(_CACHE_SUFFIX)] + _ATIME_SUFFIX), "wb") as f:
                    f.write(stamp)
                repaired += 1
            except OSError:
                pass
    return repaired
