"""Traced programs kept on disk, so that a second run of the same job neither traces nor compiles them again.

JAX's persistent compilation cache (`_cache.py`) keeps XLA's executables, but every new process still traces its
Python functions and lowers them to find the cache entry: for the fit's forward-mode pass through the path tracer
that is ~3-4 s of Python per process (2-core CPU), and as much again for the search's batched render. A
`StoredProgram` also keeps the *traced* program: on its first call with a new signature it exports the function
(`jax.export`, StableHLO, serialized) to `<cache dir>-programs/`, and every later process that calls it with the
same signature deserializes it instead of tracing (then XLA's cache supplies the executable).

The key of a stored program is a SHA-256 of everything that can change the traced program:
- the program's name and the source of every Python file of `jaxfog` and of the package defining the function;
- the versions of jax, jaxlib and equinox, the backend, its devices, `jax_enable_x64`, `XLA_FLAGS`;
- the arguments' pytree structure (every node type by module and name, with its static data: an equinox Module's
  static fields), the shapes and dtypes of their arrays, and the value of every non-array leaf.
The function must depend on nothing but its arguments and the source code (no closure over values): every caller in
this project passes a module-level function. Where a non-array value cannot be keyed exactly (its `repr` names an
object address or elides values), or several processes share the run (`jax.distributed`), or the cache is off
(`JAXFOG_CACHE_DIR=off`, or no compilation cache in use), the program is only `jax.jit`-compiled, as before.
A stored program that cannot be read or called is deleted and traced again.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import os
import sys
import warnings
from pathlib import Path
from typing import Callable

import equinox as eqx
import jax
import numpy as np

SUFFIX = ".jaxexport"

MAX_FILES = 256
"""Stored programs kept per folder: writing one more removes the least recently written beyond this (each is
~0.1 MB; a change of the code or of a scene's structure makes new ones, never reused by the old)."""

_SOURCE_HASHES: dict[str, str] = {}


def _file_hash(path: str) -> str:
    h = _SOURCE_HASHES.get(path)
    if h is None:
        try:
            h = hashlib.sha256(Path(path).read_bytes()).hexdigest()
        except OSError:
            h = "unreadable:" + path
        _SOURCE_HASHES[path] = h
    return h


def _package_hash(root: Path | None = None) -> str:
    """The hash of every `.py` file of a package folder (default: jaxfog's), its sorted relative paths and contents."""
    root = Path(__file__).resolve().parent if root is None else root
    key = f"<{root}>"
    if key not in _SOURCE_HASHES:
        h = hashlib.sha256()
        for p in sorted(root.rglob("*.py")):
            h.update(str(p.relative_to(root)).encode())
            h.update(_file_hash(str(p)).encode())
        _SOURCE_HASHES[key] = h.hexdigest()
    return _SOURCE_HASHES[key]


class _Unkeyable(Exception):
    """A value whose exact identity cannot be written into a key."""


def _exact_repr(x) -> str:
    r = repr(x)
    if " at 0x" in r or "..." in r or "object at" in r:
        raise _Unkeyable(r[:80])
    return r


@functools.lru_cache(maxsize=None)
def _type_name(t: type) -> str:
    src = None
    try:
        src = inspect.getsourcefile(t)
    except TypeError:
        pass
    tag = f"{t.__module__}.{t.__qualname__}"
    return tag if src is None else f"{tag}@{_file_hash(src)[:16]}"


def _structure(treedef) -> str:
    """A canonical text of a pytree structure: every node's type (module, name, the hash of its source file) and its
    static data, recursively."""
    if treedef.num_nodes == 1 and treedef.num_leaves == 1:
        return "*"
    data = treedef.node_data()
    if data is None:
        return "None" if treedef.num_leaves == 0 else "*"
    t, aux = data
    kids = ",".join(_structure(c) for c in treedef.children())
    return f"{_type_name(t)}[{_exact_repr(aux)}]({kids})"


def _leaf_text(x) -> str:
    if isinstance(x, (bool, int, float, complex, str, bytes, type(None))):
        return f"{type(x).__name__}:{x!r}"
    if isinstance(x, np.generic):
        return f"{x.dtype}:{x.item()!r}"
    raise _Unkeyable(type(x).__name__)


def _environment() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        jaxlib_version = version("jaxlib")
    except PackageNotFoundError:
        jaxlib_version = "?"
    devs = jax.devices()
    return "|".join([
        jax.__version__, jaxlib_version, eqx.__version__, sys.version.split()[0],
        jax.default_backend(), str(len(devs)), ",".join(sorted({d.device_kind for d in devs})),
        str(jax.config.jax_enable_x64), os.environ.get("XLA_FLAGS", ""), _package_hash(),
    ])


def _xla_cache_dir() -> str | None:
    return jax.config.jax_compilation_cache_dir


def program_dir() -> str | None:
    """The folder of the stored programs: beside JAX's compilation cache (`<its folder>-programs`), or None when no
    compilation cache is in use or several processes share the run."""
    xla = _xla_cache_dir()
    if not xla or jax.process_count() > 1:
        return None
    return os.path.normpath(xla) + "-programs"


def _split_keys(leaves: list) -> tuple[list, list]:
    """Typed PRNG keys as their raw data (what an exported program can take), with each leaf's key implementation
    (None for an ordinary array)."""
    out, impls = [], []
    for x in leaves:
        if isinstance(x, jax.Array) and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
            impls.append(str(jax.random.key_impl(x)))
            out.append(jax.random.key_data(x))
        else:
            impls.append(None)
            out.append(x)
    return out, impls


def _function_source(fn: Callable) -> str:
    """The hash of the source a function depends on: its top-level package's files (every module it may call), or
    its own file where it is not in a package."""
    module = sys.modules.get(getattr(fn, "__module__", None) or "")
    top = sys.modules.get((getattr(module, "__name__", "") or "").split(".")[0])
    folder = getattr(top, "__path__", None)
    if folder:
        return _package_hash(Path(list(folder)[0]).resolve())
    src = inspect.getsourcefile(fn)
    return "" if src is None else _file_hash(src)


class StoredProgram:
    """`fn` compiled, its traced program stored on disk per signature (the module docstring).

    `fn(*args)` must be a pure function of its arguments (pytrees: arrays are the program's inputs, every other leaf
    and every static field is part of its signature) returning tuples, lists or dicts of arrays; `folder`: where
    its programs are kept (default `program_dir()`, looked up at each new signature). Calling the
    `StoredProgram` with the same arguments returns what `jax.jit(fn)(*args)` returns (up to the float rounding of
    another compilation of the same computation)."""

    def __init__(self, name: str, fn: Callable, folder: str | None = None):
        self.name, self.fn, self.folder = name, fn, folder
        self._calls: dict[str, Callable] = {}
        self._source = _function_source(fn)

    def __call__(self, *args):
        dynamic, static = eqx.partition(args, eqx.is_array)
        leaves, treedef = jax.tree.flatten(dynamic)
        leaves, impls = _split_keys(leaves)
        sig = self._signature(static, treedef, leaves, impls)
        call = self._calls.get(sig)
        if call is not None:
            return call(*leaves)
        call, path = self._program(sig, static, treedef, leaves, impls)
        if path is not None:
            try:
                out = call(*leaves)
            except Exception:  # a stored program this JAX cannot run after all: removed, traced as usual
                _remove(path)
                call, path = jax.jit(self._flat(static, treedef, impls)), None
            else:
                self._calls[sig] = call
                return out
        self._calls[sig] = call
        return call(*leaves)

    def _signature(self, static, treedef, leaves, impls) -> str:
        """The key text of one call, or "" where the call cannot be keyed (it is then only jit-compiled)."""
        try:
            s_leaves, s_def = jax.tree.flatten(static)
            parts = [self.name, self._source, _structure(s_def), ";".join(_leaf_text(x) for x in s_leaves),
                     _structure(treedef),
                     ";".join(f"{np.dtype(x.dtype)}{tuple(x.shape)}{getattr(x, 'weak_type', False)}{i}"
                              for x, i in zip(leaves, impls))]
        except _Unkeyable:
            return ""
        return "\n".join(parts)

    def _flat(self, static, treedef, impls) -> Callable:
        fn = self.fn

        def flat(*leaves):
            leaves = [x if i is None else jax.random.wrap_key_data(x, impl=i) for x, i in zip(leaves, impls)]
            return fn(*eqx.combine(jax.tree.unflatten(treedef, leaves), static))
        return flat

    def _program(self, sig: str, static, treedef, leaves, impls) -> tuple[Callable, str | None]:
        """The compiled call and the stored program's path (None where it is only jit-compiled)."""
        flat = self._flat(static, treedef, impls)
        folder = (self.folder or program_dir()) if sig else None
        if folder is None:
            return jax.jit(flat), None
        digest = hashlib.sha256((_environment() + "\n" + sig).encode()).hexdigest()[:40]
        path = os.path.join(folder, f"{self.name}-{digest}{SUFFIX}")
        mesh = jax.sharding.Mesh(np.array(jax.devices()), ("d",))
        rep = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
        exported = _read(path)
        if exported is None:
            try:
                exported = jax.export.export(jax.jit(flat, in_shardings=rep, out_shardings=rep))(*leaves)
                blob = exported.serialize()
            except Exception as e:  # a program export cannot express: compiled as usual
                warnings.warn(f"{self.name}: not stored ({type(e).__name__}: {str(e)[:200]})", RuntimeWarning,
                              stacklevel=3)
                return jax.jit(flat), None
            _write(path, blob)
        return jax.jit(exported.call, in_shardings=rep, out_shardings=rep), path


def _read(path: str):
    """The stored program at `path`, or None (missing, or unreadable: then removed)."""
    try:
        blob = Path(path).read_bytes()
    except OSError:
        return None
    try:
        return jax.export.deserialize(bytearray(blob))
    except Exception:
        _remove(path)
        return None


def _remove(path: str) -> None:
    try:
        os.remove(path)
    except OSError:
        pass


def _write(path: str, blob) -> None:
    """Write `blob` to `path` atomically; a folder that cannot be written only costs the next run its tracing."""
    from ._image import _atomic_write

    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        _atomic_write(path, lambda tmp: Path(tmp).write_bytes(bytes(blob)))
    except OSError as e:
        warnings.warn(f"stored program not written: {path}: {e.strerror or e}", RuntimeWarning, stacklevel=3)
        return
    _prune(os.path.dirname(path))


def _prune(folder: str) -> None:
    """Remove the stored programs of `folder` beyond the `MAX_FILES` most recently written."""
    keep = MAX_FILES
    try:
        files = [e for e in os.scandir(folder) if e.name.endswith(SUFFIX) and e.is_file()]
        files.sort(key=lambda e: e.stat().st_mtime, reverse=True)
    except OSError:
        return
    for e in files[keep:]:
        _remove(e.path)
