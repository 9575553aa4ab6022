"""Checks of the public entry points' arguments, made before anything is compiled or allocated.

- `_check_render_args`: the arguments of `render` (the first line of `render`): a `TypeError` or `ValueError` whose
  message names the argument, the value given and what is valid.
- `check_size`: the size limits (resolution, spp, max_depth, estimated work) that keep a render from exhausting
  memory or running for days by mistake; `JAXFOG_NO_LIMITS=1` in the environment (or `force=True`; the CLI's
  `--force`) lifts them.
- `check_finite`: a rendered image has only finite values (public: `jaxfog.check_finite`).
- `check_seed`: a seed for `jax.random.key`, in [0, 2^32) (seeds outside would alias others, bit for bit).
"""

from __future__ import annotations

import numbers
import os

import numpy as np

MAX_SIDE = 16384
"""Largest image width or height (pixels)."""
MAX_PIXELS = 4096 * 4096
"""Largest image (pixels): the accumulated image alone is 12 bytes a pixel, one batch ~1 KiB a path."""
MAX_SPP = 1 << 20
"""Most samples per pixel."""
MAX_DEPTH = 1024
"""Longest path (segments)."""
MAX_WORK = 10**11
"""Most path segments per render (pixels x spp x max_depth): ~10 hours on a 2-core CPU at ~3e6 segments/s."""
NO_LIMITS_ENV = "JAXFOG_NO_LIMITS"
"""Environment variable: `1` lifts the size limits."""
SEED_RANGE = (0, 1 << 32)
"""Valid seeds: [0, 2^32). `jax.random.key` keeps 32 bits of a seed's two's complement (so -1 and 2^32 - 1, or 0
and 2^32, give the same key) and raises OverflowError beyond 64 bits."""


class LimitError(ValueError):
    """A render larger than the size limits (`check_size`); the message states the limit and how to lift it."""


def limits_lifted(force: bool = False) -> bool:
    """True when the size limits do not apply: `force`, or `JAXFOG_NO_LIMITS=1` in the environment."""
    return bool(force) or os.environ.get(NO_LIMITS_ENV, "") not in ("", "0")


UNBOUNDED_DEPTH_ESTIMATE = 16
"""Segments per path assumed for the work estimate of `max_depth = -1` (Russian roulette ends most paths sooner)."""


def check_size(width: int, height: int, spp: int, max_depth: int, *, force: bool = False, names=None,
               override: str | None = None) -> None:
    """Raise `LimitError` if a render of `width` x `height` pixels, `spp` samples per pixel and paths of up to
    `max_depth` segments exceeds `MAX_SIDE`, `MAX_PIXELS`, `MAX_SPP`, `MAX_DEPTH` or `MAX_WORK` (unless
    `limits_lifted(force)`). `names`: how the message calls the four values (default: the argument names);
    `override`: how the message says to lift the limit (default: the environment variable)."""
    if limits_lifted(force):
        return
    n = {"width": "camera.width", "height": "camera.height", "spp": "spp", "max_depth": "max_depth", **(names or {})}
    how = override or f"set {NO_LIMITS_ENV}=1 to lift the limit"
    for key, value in (("width", width), ("height", height)):
        if value > MAX_SIDE:
            raise LimitError(f"{n[key]} {value} exceeds the limit {MAX_SIDE} pixels; {how}")
    if width * height > MAX_PIXELS:
        raise LimitError(f"{n['width']} x {n['height']} = {width} x {height} = {width * height} pixels exceeds the "
                         f"limit {MAX_PIXELS} (4096 x 4096); {how}")
    if spp > MAX_SPP:
        raise LimitError(f"{n['spp']} {spp} exceeds the limit {MAX_SPP} samples per pixel; {how}")
    if max_depth > MAX_DEPTH:
        raise LimitError(f"{n['max_depth']} {max_depth} exceeds the limit {MAX_DEPTH} segments; {how}")
    depth = UNBOUNDED_DEPTH_ESTIMATE if max_depth == -1 else max_depth
    work = width * height * spp * depth
    if work > MAX_WORK:
        shown = f"~{depth} (max_depth -1: an estimate)" if max_depth == -1 else max_depth
        raise LimitError(f"{width} x {height} px x {spp} spp x max_depth {shown} = {work:.3g} path segments "
                         f"exceeds the limit {MAX_WORK:.0e} (~10 hours on a 2-core CPU); {how}")


def check_seed(seed, what: str = "seed") -> int:
    """`seed` as an int in [0, 2^32), or a ValueError naming `what`, the value and the range."""
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral):
        raise ValueError(f"{what} must be an integer in [0, 2^32), got {seed!r}")
    seed = int(seed)
    if not SEED_RANGE[0] <= seed < SEED_RANGE[1]:
        raise ValueError(f"{what} {seed} is out of range; valid range [0, 4294967295] (2^32 seeds; others would "
                         f"repeat one of these seeds' images)")
    return seed


def seed_argument(text: str) -> int:
    """argparse `type=` for a seed: an int in [0, 2^32) (`check_seed`; outside it, seeds would repeat other seeds'
    images), else `argparse.ArgumentTypeError` with the valid range. Shared by `jaxfog render` and `fitting.fit`."""
    import argparse

    try:
        return check_seed(int(text))
    except ValueError as e:
        raise argparse.ArgumentTypeError(f"expected an integer in [0, 4294967295], got {text!r}"
                                         if "invalid literal" in str(e) else str(e)) from None


def check_finite(image, what: str = "image"):
    """Return `image` (any array) if every value is finite; otherwise raise `FloatingPointError` saying how many
    values are NaN or infinite and where the first one is. Used by the command line and the fit on every image they
    render; call it on `render`'s result to be sure (`render` itself returns what it computed, so that a traced or
    batched call stays possible)."""
    a = np.asarray(image)
    bad = ~np.isfinite(a)
    if bad.any():
        first = tuple(int(i) for i in np.argwhere(bad)[0])
        n_nan, n_inf = int(np.isnan(a).sum()), int(np.isinf(a).sum())
        raise FloatingPointError(f"{what}: {int(bad.sum())} of {a.size} values are not finite ({n_nan} NaN, {n_inf} "
                                 f"infinite; first at index {first}); expected finite radiance")
    return image


def _describe(x) -> str:
    if isinstance(x, (bool, int, float, str)) or x is None:
        return f"{type(x).__name__} {x!r}"
    shape, dtype = getattr(x, "shape", None), getattr(x, "dtype", None)
    if shape is not None:
        return f"{type(x).__name__} of shape {tuple(shape)} and dtype {dtype}"
    return type(x).__name__


def _positive_int(name: str, value) -> None:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise TypeError(f"render: {name} must be a positive integer, got {_describe(value)}")
    if value < 1:
        raise ValueError(f"render: {name} must be a positive integer (>= 1), got {value}")


def _check_key(key) -> None:
    import jax

    expected = ("expected a JAX PRNG key: jax.random.key(seed) (a typed key array of shape ()), or a legacy "
                "jax.random.PRNGKey(seed) (uint32, shape (2,))")
    dtype, shape = getattr(key, "dtype", None), getattr(key, "shape", None)
    if dtype is None or shape is None or isinstance(key, (bool, int, float)):
        raise TypeError(f"render: key: got {_describe(key)}; {expected}")
    if jax.dtypes.issubdtype(dtype, jax.dtypes.prng_key):
        if tuple(shape) != ():
            raise ValueError(f"render: key: got a key array of shape {tuple(shape)}; {expected} (one key: index or "
                             f"vmap a batch of keys)")
        return
    if np.dtype(dtype) == np.uint32 and tuple(shape) == (2,):
        return
    raise TypeError(f"render: key: got {_describe(key)}; {expected}")


def _check_render_args(scene, key, spp, *, sampling, proposal, batch_paths, chunk_paths, devices, progress) -> None:
    """Every argument of `render` (same names), checked before anything is traced: a `TypeError` for the wrong kind
    of value, a `ValueError` for a value out of range, a `LimitError` (a ValueError) for a render beyond the size
    limits. The message names the argument, the value and what is valid."""
    from ._medium import AbstractMedium
    from ._scene import Scene
    from ._scene_io import SceneFile

    if isinstance(scene, SceneFile):
        raise TypeError("render: scene: got a SceneFile (what load_scene returns); pass its .scene, "
                        "e.g. render(load_scene(path).scene, key, spp)")
    if not isinstance(scene, Scene):
        raise TypeError(f"render: scene must be a jaxfog.Scene, got {_describe(scene)}")
    _check_key(key)
    _positive_int("spp", spp)
    if proposal is not None and not isinstance(proposal, AbstractMedium):
        raise TypeError(f"render: proposal must be None or a jaxfog.HomogeneousMedium (or another medium of the "
                        f"scene medium's kind: the reference medium of estimator=\"proposal\"), got "
                        f"{_describe(proposal)}")
    if proposal is not None and scene.medium is not None and type(proposal) is not type(scene.medium):
        raise TypeError(f"render: proposal must be a {type(scene.medium).__name__} like the scene's medium, got "
                        f"{type(proposal).__name__}")
    if sampling.estimator == "proposal" and proposal is None and scene.medium is not None:
        raise ValueError('render: estimator="proposal" needs proposal=<a medium of the scene medium\'s kind with '
                         'the reference values>, got proposal=None')
    _positive_int("batch_paths", batch_paths)
    _positive_int("chunk_paths", chunk_paths)
    if devices is not None:
        import jax

        n = jax.local_device_count()
        if isinstance(devices, bool) or not isinstance(devices, numbers.Integral) or not 1 <= devices <= n:
            raise ValueError(f"render: devices must be None or an integer in [1, {n}], got {devices!r}")
    if progress is not None and not callable(progress):
        raise TypeError(f"render: progress must be None or a function progress(done_spp, spp), got "
                        f"{_describe(progress)}")
    cam = scene.camera
    check_size(cam.width, cam.height, int(spp), scene.max_depth,
               names=dict(width="scene.camera.width", height="scene.camera.height", max_depth="scene.max_depth"))
