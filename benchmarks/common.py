"""What the benchmarks share: the repository's paths, loading a shipped scene, block means, the machine and memory
records, atomic writes of JSON and `.npz` files, and the environment of a benchmark subprocess.

Paths are relative to the repository root, found from this file (`REPO`); the library itself never uses them.
"""

from __future__ import annotations

import json
import os
import platform
from pathlib import Path

import numpy as np

from jaxfog.tools import atomic_write  # noqa: F401  (the one atomic-write helper: write tmp, rename)

REPO = Path(__file__).resolve().parent.parent
"""The repository root (the folder holding `benchmarks/`, `jaxfog/` and `data_synthetic/`)."""

SCENE_DIR = REPO / "data_synthetic" / "scenes"


def scene_path(name: str) -> Path:
    """A shipped scene by name (`spot_fog`), or a path to a scene file (`.json`)."""
    p = Path(name)
    return p if p.suffix == ".json" else SCENE_DIR / f"{name}.json"


def load(name: str, size: int | None = None, overrides=()):
    """`jaxfog.load_scene` of a shipped scene (or a `.json` path) at `size x size` pixels (None: the file's), with
    further `"key.path=value"` overrides; returns the `SceneFile`."""
    import jaxfog as jf

    size_overrides = [] if size is None else [f"camera.width={size}", f"camera.height={size}"]
    return jf.load_scene(scene_path(name), [*size_overrides, *overrides])


def block_means(image, n: int = 4):
    """Means of an `(H, W, C)` image over an `n x n` grid of blocks, channels averaged: `(n, n)`, rows top to bottom,
    columns left to right.

    A NumPy (or list) image gives float64; when `n` does not divide H or W the blocks differ by at most one row or
    column (`np.array_split`). A JAX array (also a tracer inside `jit`/`jvp`) stays a JAX array; then H and W must
    be multiples of `n`."""
    if not isinstance(image, np.ndarray):
        import jax

        if isinstance(image, jax.Array):
            H, W = image.shape[:2]
            if H % n or W % n:
                raise ValueError(f"block_means of a JAX array: {H} x {W} is not a multiple of {n}")
            return image.mean(-1).reshape(n, H // n, n, W // n).mean(axis=(1, 3))
    img = np.asarray(image, np.float64).mean(axis=-1)
    H, W = img.shape
    if H % n == 0 and W % n == 0:
        return img.reshape(n, H // n, n, W // n).mean(axis=(1, 3))
    rows, cols = np.array_split(np.arange(H), n), np.array_split(np.arange(W), n)
    return np.array([[img[np.ix_(r, c)].mean() for c in cols] for r in rows])


def machine_info() -> dict:
    """Where a benchmark ran: platform, Python, jax and its devices, CPU count, load average and niceness now."""
    import jax

    cpu = ""
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), "")
    except OSError:
        pass
    return {"platform": platform.platform(), "cpu": cpu or platform.processor(), "python": platform.python_version(),
            "jax": jax.__version__,
            "backend": jax.default_backend(), "devices": [str(d) for d in jax.devices()],
            "cpu_count": os.cpu_count(), "loadavg_start": list(os.getloadavg()), "nice": os.nice(0)}


MIB = 1.0 / (1 << 20)


def memory_dict(memory_analysis) -> dict:
    """XLA's `compiled.memory_analysis()` in MiB: argument, output and temporary buffers, and their total."""
    a, o, t = (memory_analysis.argument_size_in_bytes, memory_analysis.output_size_in_bytes,
               memory_analysis.temp_size_in_bytes)
    return {"argument_mib": a * MIB, "output_mib": o * MIB, "temp_mib": t * MIB, "total_mib": (a + o + t) * MIB}


def json_default(o):
    """`json.dumps(..., default=json_default)`: numpy scalars and arrays as Python numbers and lists."""
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)


def write_json(path, obj) -> None:
    """`obj` as indented JSON (numpy values converted), written atomically (its folder created if missing)."""
    text = json.dumps(obj, indent=1, default=json_default)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)

    def write(tmp):
        with open(tmp, "w") as f:
            f.write(text)

    atomic_write(path, write)


def save_npz(path, compressed: bool = False, **arrays) -> None:
    """`np.savez` (or `np.savez_compressed`) of `arrays` to `path` (ending in `.npz`), written atomically (its folder
    created if missing)."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    save = np.savez_compressed if compressed else np.savez
    atomic_write(path, lambda tmp: save(tmp, **arrays))


def subprocess_env(env: dict | None = None) -> dict:
    """The environment for `python -m benchmarks.X` in a subprocess: `env` (default this process's) with the
    repository root first on `PYTHONPATH`, so `benchmarks` and this checkout's `jaxfog` are the ones imported."""
    env = dict(os.environ if env is None else env)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    return env
