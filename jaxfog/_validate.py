"""Checks of the public entry points' arguments, made before anything is compiled or allocated.

- `_check_render_args`: the arguments of `render` (the first line of `render`): a `TypeError` or `ValueError` whose
  message names the argument, the value given and what is valid.
- `check_size`: the size limits (resolution, spp, max_depth, estimated work) that keep a render from exhausting
  memory or running for days by mistake; `JAXFOG_NO_LIMITS=1` in the environment (or `force=True`; the CLI's
  `--force`) lifts them.
- `check_finite`: a rendered image has only finite values (public: `jaxfog.check_finite`).
- `check_seed`: a seed for `jax.random.key`, in [0, 2^32) (seeds outside would alias others, bit for bit).
- `Range` and `check_range`: the one range check of every value in the library. A Module checks its fields once
  with `check_range(owner, field, value, RANGE)` (concrete values only: a traced value inside `jit` is skipped),
  and the scene file schema (`_scene_io.SCHEMA`) uses the same `Range` objects (`G_RANGE`, `FOV_RANGE`, ...), so a
  range is written once and the Python API and the files accept the same values.
- `read_only`: an existing output file that must not be replaced (shared by `jaxfog render` and `fitting.fit`).
"""

from __future__ import annotations

import numbers
import os
import stat
from dataclasses import dataclass

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


MAX_RR_DEPTH = MAX_DEPTH
"""Largest `rr_depth` (path vertices before Russian roulette starts): with `max_depth = -1` every path that neither
escapes nor is absorbed runs this many segments, so it bounds the work of a path like `MAX_DEPTH` does."""


# ---------------------------------------------------------------------------------------------------- ranges
def _num(x) -> str:
    """A bound or value as the messages show it: 1.0 -> "1", 0.001 -> "0.001", 1e+06 -> "1e+06"."""
    x = float(x)
    return str(int(x)) if x.is_integer() and abs(x) < 1e6 else f"{x:g}"


@dataclass(frozen=True)
class Range:
    """An interval of valid values for a number (or for every entry of a vector or RGB value).

    `lo`, `hi`: the bounds (None: unbounded); `hi` may name a sibling field of a scene file section
    (`"cutoff_angle"`), whose validated value is the bound there; `lo_open`, `hi_open`: the bound itself is
    excluded; `also`: one more valid value outside the interval (`max_depth = -1`). Every value must also be finite.
    """

    lo: float | None = None
    hi: float | str | None = None
    lo_open: bool = False
    hi_open: bool = False
    also: float | None = None

    def text(self, hi=None) -> str:
        """`(0, 180)`, `[0, inf)`, `[1, inf), or -1`; `hi` replaces a sibling's name by its value."""
        hi = self.hi if hi is None else hi
        lo_s = "-inf" if self.lo is None else _num(self.lo)
        hi_s = "inf" if hi is None else (hi if isinstance(hi, str) else _num(hi))
        left = "(" if (self.lo_open or self.lo is None) else "["
        right = ")" if (self.hi_open or hi is None) else "]"
        extra = "" if self.also is None else f", or {_num(self.also)}"
        return f"{left}{lo_s}, {hi_s}{right}{extra}"

    def below(self, v) -> np.ndarray:
        """Where `v` (a number or array) is below the interval (never for `also`)."""
        v = np.asarray(v, np.float64)
        out = np.zeros(v.shape, bool) if self.lo is None else ((v <= self.lo) if self.lo_open else (v < self.lo))
        return out & ~self._also(v)

    def above(self, v, hi=None) -> np.ndarray:
        """Where `v` is above the interval (`hi`: the bound's value when `self.hi` names a sibling)."""
        v = np.asarray(v, np.float64)
        hi = self.hi if hi is None else hi
        out = np.zeros(v.shape, bool) if hi is None else ((v >= hi) if self.hi_open else (v > hi))
        return out & ~self._also(v)

    def contains(self, v, hi=None) -> bool:
        """Every entry of `v` finite and in the interval (or equal to `also`)."""
        v = np.asarray(v, np.float64)
        return bool(np.all(np.isfinite(v)) and not np.any(self.below(v)) and not np.any(self.above(v, hi)))

    def _also(self, v) -> np.ndarray:
        return np.zeros(v.shape, bool) if self.also is None else (v == self.also)


ANY = Range()
"""Any finite number."""
POSITIVE = Range(0, None, lo_open=True)
NON_NEGATIVE = Range(0, None)
UNIT = Range(0, 1)
"""[0, 1]: albedo, reflectance, a mixture weight."""
AT_LEAST_1 = Range(1, None)
G_RANGE = Range(-1, 1, lo_open=True, hi_open=True)
"""A Henyey–Greenstein asymmetry (g, g1, g2, Draine's g): (-1, 1)."""
DRAINE_ALPHA_RANGE = Range(0, 1000, lo_open=True)
DROPLET_DIAMETER_RANGE = Range(0, 50, lo_open=True)
"""Fog-droplet diameters (µm) covered by the fits of Jendersie & d'Eon (2023): (0, 50]."""
FOV_RANGE = Range(0, 180, lo_open=True, hi_open=True)
"""A pinhole camera's full horizontal field of view (degrees): (0, 180)."""
SPOT_CUTOFF_RANGE = Range(0, 90, lo_open=True, hi_open=True)
HEIGHT_SCALE_RANGE = Range(1e-3, 1e6)
"""A height fog's scale height H (scene units): [1e-3, 1e6], the range its optical depths are computed stably in
(`_height`, tested at both ends); H -> inf is the homogeneous medium (use `HomogeneousMedium`)."""
MAX_DEPTH_RANGE = Range(1, None, also=-1)
RR_DEPTH_RANGE = Range(1, MAX_RR_DEPTH)
"""`rr_depth`: [1, 1024] (`MAX_RR_DEPTH`)."""


def _tracer(x) -> bool:
    try:
        from jax.core import Tracer
    except ImportError:  # pragma: no cover
        return False
    return isinstance(x, Tracer)


def check_range(owner: str, name: str, x, rng: Range = ANY) -> None:
    """Raise `ValueError` unless every entry of the value `x` is finite and in `rng`, as the renderer sees it: an
    array field is checked as its float32 value (0.99999999 is 1.0 in float32; 1e39 is inf). A traced value (a
    Module rebuilt inside `jit`, `grad` or `vmap`) is skipped: it was checked where it was made. The message reads
    `HenyeyGreenstein.g = 1.0 (as float32) is outside the valid range (-1, 1)`."""
    if _tracer(x):
        return
    v = np.asarray(x)
    if v.dtype == object or not (np.issubdtype(v.dtype, np.number) or v.dtype == bool):
        raise TypeError(f"{owner}.{name} must be a number or an array of numbers, got {type(x).__name__} {x!r}")
    if not rng.contains(v):
        shown = v.item() if v.ndim == 0 else v.tolist()
        as32 = " (as float32)" if v.dtype == np.float32 else ""
        raise ValueError(f"{owner}.{name} = {shown}{as32} is outside the valid range {rng.text()}")


def check_vector(owner: str, name: str, x, nonzero: bool = True) -> None:
    """Raise `ValueError` unless the (concrete) vector `x` is finite and, with `nonzero`, has a length (a direction,
    an edge, an up vector). Traced values are skipped."""
    if _tracer(x):
        return
    v = np.asarray(x, np.float64)
    if not np.all(np.isfinite(v)) or (nonzero and not np.any(v != 0)):
        what = "a finite, non-zero vector" if nonzero else "a finite vector"
        raise ValueError(f"{owner}.{name} = {v.tolist()} must be {what}")


def concrete_values(*xs):
    """The values `xs` as float64 numpy arrays, or None if any of them is traced (nothing to check)."""
    if any(_tracer(x) for x in xs):
        return None
    return tuple(np.asarray(x, np.float64) for x in xs)


# ---------------------------------------------------------------------------------- glass and a bounded fog
def sphere_in_box(center, radius, lo, hi) -> str:
    """Where a sphere lies relative to the box `[lo, hi]`: `"inside"` (wholly, touching allowed), `"outside"` (no
    point strictly inside the box) or `"straddles"` (across a face; also a sphere that contains the box)."""
    c, lo, hi = (np.asarray(x, np.float64) for x in (center, lo, hi))
    r = float(radius)
    if np.all(c - r >= lo) and np.all(c + r <= hi):
        return "inside"
    gap = np.maximum(np.maximum(lo - c, c - hi), 0.0)
    return "outside" if float(gap @ gap) >= r * r else "straddles"


def polygons_in_box(points, lo, hi) -> str:
    """Where a set of flat convex polygons `points` (n, k, 3) (a rectangle's 4 corners, a mesh's triangles) lies
    relative to the box `[lo, hi]`: `"inside"` (every vertex in it), `"outside"` (no polygon meets the box's
    interior: the separating axis test over the box's axes, each polygon's normal and the cross products of both's
    edges; touching counts as outside) or `"straddles"`."""
    P = np.asarray(points, np.float64)
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    if np.all((P >= lo) & (P <= hi)):
        return "inside"
    c, h = 0.5 * (lo + hi), 0.5 * (hi - lo)
    Q = P - c
    edges = np.roll(Q, -1, axis=1) - Q
    axes = [np.broadcast_to(e, Q[:, 0].shape) for e in np.eye(3)] + [np.cross(edges[:, 0], edges[:, 1])]
    axes += [np.cross(e, edges[:, j]) for e in np.eye(3) for j in range(P.shape[1])]
    separated = np.zeros(len(P), bool)
    for A in axes:
        proj = np.einsum("nkc,nc->nk", Q, A)
        r = np.abs(A) @ h
        used = np.any(A != 0, axis=1)
        separated |= used & ((proj.min(axis=1) >= r) | (proj.max(axis=1) <= -r))
    return "outside" if np.all(separated) else "straddles"


def read_only(path) -> bool:
    """True for an existing file that may not be replaced: not writable by this process, or without any write
    permission bit (a file made read-only with `chmod a-w`; checked by its mode as well, since `os.access` grants
    the superuser everything). An output the user protected is refused, never silently replaced."""
    try:
        st = os.stat(path)
    except OSError:
        return False
    if not stat.S_ISREG(st.st_mode):
        return False
    return not os.access(path, os.W_OK) or not (st.st_mode & (stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH))


class LimitError(ValueError):
    """A render larger than the size limits (`check_size`); the message states the limit and how to lift it."""


def limits_lifted(force: bool = False) -> bool:
    """True when the size limits do not apply: `force`, or `JAXFOG_NO_LIMITS=1` in the environment."""
    return bool(force) or os.environ.get(NO_LIMITS_ENV, "") not in ("", "0")


UNBOUNDED_DEPTH_ESTIMATE = 16
"""Segments per path assumed for the work estimate of `max_depth = -1` at the default `rr_depth` 5 (Russian roulette
ends most paths sooner); a larger `rr_depth` adds its excess over 5 (every path runs to it unless it escapes)."""


def check_size(width: int, height: int, spp: int, max_depth: int, *, force: bool = False, names=None,
               override: str | None = None, rr_depth: int = 5) -> None:
    """Raise `LimitError` if a render of `width` x `height` pixels, `spp` samples per pixel and paths of up to
    `max_depth` segments exceeds `MAX_SIDE`, `MAX_PIXELS`, `MAX_SPP`, `MAX_DEPTH` or `MAX_WORK` (unless
    `limits_lifted(force)`). `names`: how the message calls the four values (default: the argument names);
    `override`: how the message says to lift the limit (default: the environment variable); `rr_depth`: where
    Russian roulette starts (enters the work estimate of `max_depth = -1`)."""
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
    depth = UNBOUNDED_DEPTH_ESTIMATE + max(int(rr_depth) - 5, 0) if max_depth == -1 else max_depth
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
    check_size(cam.width, cam.height, int(spp), scene.max_depth, rr_depth=scene.rr_depth,
               names=dict(width="scene.camera.width", height="scene.camera.height", max_depth="scene.max_depth"))

