"""Rendering: generate rays -> `vmap(trace_path)` -> average, in batches of whole sample layers.

A batch's work is a list of items, one chunk of pixels of one sample layer each (of several layers side by side, for
an image smaller than a chunk); the devices share the items (so even a 1-spp image keeps every device busy) and each
device traces its items one after the other, adding them to its own partial sums; the devices' partial sums are added
once, at the end of the render. The devices are `jax.devices()` by default: after `jax.distributed.initialize`, those
of every process, so that one `render` call made by every process renders one image on all of them, and the only
data the processes exchange is that final sum (docs/distributed.md).

Sample `k` of every pixel draws its random numbers from `fold_in(key, k)` (hashed by `_random.uniforms`), so an image
depends only on the scene, the key and spp (never on the batch size), and memory is bounded for any spp.
"""

from __future__ import annotations

import weakref
from functools import lru_cache, partial
from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import Array, Float, PRNGKeyArray

from ._devices import is_device_list, render_devices
from ._integrator import (
    SamplingOptions,
    barrier,
    make_tracer,
    n_dims,
    n_iterations,
    trace_path,
)
from ._random import key_words, uniforms
from ._scene import Scene, pack
from ._unbounded import moments as unbounded_moments, trace_items_unbounded
from ._validate import _check_render_args

DEFAULT_BATCH_PATHS = 1 << 16
"""Paths traced per compiled call (a multiple of the pixel count is used); bounds memory (~1 KiB per path)."""

DEFAULT_CHUNK_PATHS = 1024
"""Paths traced together in one vectorized pass (a sample layer is traced in chunks of this many pixels, one after
the other). A speed knob only: each path's random numbers do not depend on it. Measured on a 2-core CPU (XLA):
1024 is ~1.4x faster per sample than a whole 128x128 layer at once; 2048 and 4096 are slower, 256 and 512 in
between (docs/results/bench/PROFILE.md; re-measure with `python -m benchmarks.bench_profile` on other hardware)."""


def layers_per_batch(scene: Scene, spp: int, batch_paths: int = DEFAULT_BATCH_PATHS) -> int:
    """Sample layers (one sample of every pixel) per batch: as many as fit in `batch_paths`, at least 1, at most spp."""
    n_pix = scene.camera.width * scene.camera.height
    return max(1, min(spp, batch_paths // n_pix))


def n_chunks(scene: Scene, chunk_paths: int = DEFAULT_CHUNK_PATHS) -> tuple[int, int]:
    """`(chunk, n_chunks)`: a sample layer's pixels are traced in `n_chunks` chunks of `chunk` paths (the last one
    padded)."""
    n_pix = scene.camera.width * scene.camera.height
    chunk = max(1, min(int(chunk_paths), n_pix))
    return chunk, -(-n_pix // chunk)


def layers_per_chunk(scene: Scene, spp: int, batch_paths: int = DEFAULT_BATCH_PATHS,
                     chunk_paths: int = DEFAULT_CHUNK_PATHS) -> int:
    """Sample layers traced side by side in one vectorized pass: an image of fewer than `chunk_paths` pixels puts
    `chunk_paths // (H*W)` layers (at most a batch's `layers_per_batch`) into one pass, so a small image (the fit's
    8 x 8) is traced in passes as wide as a large image's chunks instead of one pass per 64-pixel layer; 1 for an
    image of at least `chunk_paths` pixels, and for `max_depth = -1` (its own regenerating loop)."""
    n_pix = scene.camera.width * scene.camera.height
    if scene.max_depth == -1 or n_pix >= chunk_paths:
        return 1
    return max(1, min(chunk_paths // n_pix, layers_per_batch(scene, spp, batch_paths)))


def items_per_call(scene: Scene, spp: int, batch_paths: int = DEFAULT_BATCH_PATHS,
                   chunk_paths: int = DEFAULT_CHUNK_PATHS, n_devices: int = 1) -> int:
    """Work items (one chunk of `layers_per_chunk` sample layers) `render` traces per compiled call: the chunks of
    `layers_per_batch` layers, rounded up to a multiple of `n_devices` (padding items are traced and dropped)."""
    group = layers_per_chunk(scene, spp, batch_paths, chunk_paths)
    n = -(-layers_per_batch(scene, spp, batch_paths) // group) * n_chunks(scene, chunk_paths)[1]
    return -(-n // n_devices) * n_devices


def _trace_items(scene: Scene, key: PRNGKeyArray, layer_ids: Array, chunk_ids: Array, valid: Array,
                 options: SamplingOptions,
                 proposal, chunk_paths: int = DEFAULT_CHUNK_PATHS, moments: bool = False):
    """Sum of every pixel's radiance over the given work items, `(n_chunks * chunk, 3)` (rows past `H*W` belong to the
    last chunk's padding); with `moments`, also the sum of the squared radiance (same shape), as `(sum, sum_sq)`.
    Item `i` traces chunk `chunk_ids[i]` of the sample layers `layer_ids[i] + j`, `j < G` (`G = valid.shape[1]`,
    `layers_per_chunk`: the layers side by side in one vectorized pass), one item after the other; a layer where
    `valid[i, j]` is False adds nothing. A padding row traces a real pixel (its index modulo `H*W`, so no NaN
    can reach a gradient) with its own random numbers, and is dropped by the caller."""
    cam = scene.camera
    H, W = cam.height, cam.width
    tracer = make_tracer(scene, pack(scene), options, proposal)
    n_iter, K = n_iterations(scene), n_dims(scene)
    chunk, n_ch = n_chunks(scene, chunk_paths)
    G = valid.shape[1]

    def paths(pixels, U):
        """The lanes' radiance (`vmap` of one path), the tracer's fusion-barrier guard taken from the lanes'
        uniforms (traced data: the barrier survives even when the scene is a constant of the compiled program)."""
        tr = tracer._replace(guard=jnp.isfinite(U.reshape(-1)[0])) if U.size else tracer  # no bounce: no barrier

        def one_path(pixel, U_p):
            o, d = cam.generate_ray(pixel)
            return trace_path(tr, o, d, U_p)

        return jax.vmap(one_path)(pixels, U)

    def draws(layer_id, row0, pix, once=lambda x: x):
        """One layer's pixel positions and path uniforms for the chunk's rows (a function of the layer and the row
        only, so of neither the chunking nor the grouping); `once`: the hash's fusion barrier."""
        k_pix, k_path = jax.random.split(jax.random.fold_in(key, layer_id))
        U = uniforms(k_path, chunk, n_iter * K, row0, once).reshape(chunk, n_iter, K)
        return pix + uniforms(k_pix, chunk, 2, row0), U

    def step(acc, xs):
        layer_id, chunk_id, ok = xs
        row0 = chunk_id * chunk
        rows, cols = jnp.divmod((row0 + jnp.arange(chunk, dtype=jnp.uint32)) % (H * W), W)
        pix = jnp.stack([cols, rows], axis=-1).astype(jnp.float32)
        # the hash's fusion barrier, guarded by the item's layer (traced data; its value decides nothing)
        once = barrier(tracer._replace(guard=layer_id != 0))
        if G == 1:
            pixels, U = draws(layer_id, row0, pix, once)
            radiance = jnp.where(ok[0], paths(pixels, U), 0.0)
            terms = (radiance, radiance * radiance) if moments else (radiance,)
        else:  # G layers side by side: one pass of G * chunk paths, summed over the layers
            pixels, U = jax.vmap(lambda j: draws(layer_id + j, row0, pix, once))(jnp.arange(G, dtype=jnp.uint32))
            radiance = paths(pixels.reshape(G * chunk, 2), U.reshape(G * chunk, n_iter, K))
            radiance = jnp.where(ok[:, None, None], radiance.reshape(G, chunk, 3), 0.0)
            terms = (radiance.sum(0), (radiance * radiance).sum(0)) if moments else (radiance.sum(0),)
        add = lambda a, x: jax.lax.dynamic_update_slice_in_dim(
            a, jax.lax.dynamic_slice_in_dim(a, row0, chunk) + x, row0, axis=0)
        return tuple(add(a, x) for a, x in zip(acc, terms)), None

    acc = tuple(jnp.zeros((n_ch * chunk, 3), jnp.float32) for _ in range(2 if moments else 1))
    acc, _ = jax.lax.scan(step, acc, (layer_ids, chunk_ids, valid))
    return acc if moments else acc[0]


def _trace_items_unbounded(scene: Scene, key: PRNGKeyArray, layer_ids: Array, chunk_ids: Array, valid: Array,
                           options: SamplingOptions, proposal, chunk_paths: int = DEFAULT_CHUNK_PATHS,
                           moments: bool = False):
    """`_trace_items` for paths of any length (`max_depth = -1`), with path regeneration (`_unbounded`): the
    image depends only on the scene, the key and spp. Differentiable in forward mode (`jax.jvp`, `jax.jacfwd`) and
    in reverse mode (`jax.grad`: path replay, memory independent of the path length; not for "reparam"). With
    `moments` (`render(..., variance=True)`), `_unbounded.moments` (the plain loop, also summing the squares):
    forward mode only."""
    chunk, n_ch = n_chunks(scene, chunk_paths)
    valid = valid[:, 0]  # one layer per item (`layers_per_chunk` is 1 for max_depth = -1)
    words = jax.vmap(lambda layer: jnp.stack([key_words(k) for k in jax.random.split(jax.random.fold_in(key, layer))])
                     )(layer_ids)  # (items, 2 [pixel, path], 3)
    if moments:
        return unbounded_moments(scene, words, chunk_ids, valid, proposal, options=options, chunk=chunk, n_ch=n_ch)
    return trace_items_unbounded(scene, words, chunk_ids, valid, options, proposal, chunk, n_ch)


def sampling_options(sampling: SamplingOptions | None = None, **fields) -> SamplingOptions:
    """`sampling` (default `SamplingOptions()`) with the given non-None fields replaced (validated)."""
    if sampling is None:
        sampling = SamplingOptions()
    if not isinstance(sampling, SamplingOptions):
        raise TypeError(f"sampling must be a jaxfog.SamplingOptions, got {type(sampling).__name__}")
    changed = {k: v for k, v in fields.items() if v is not None}
    if not changed:
        return sampling
    values = {f: getattr(sampling, f) for f in ("estimator", "equiangular", "light_lobe", "distance_mix", "phase_lobe")}
    return SamplingOptions(**{**values, **changed})


@eqx.filter_jit
def _render_items(scene: Scene, key: PRNGKeyArray, layer_ids: Array, chunk_ids: Array, valid: Array,
                  options: SamplingOptions, proposal, chunk_paths: int = DEFAULT_CHUNK_PATHS, n_devices=1,
                  moments: bool = False):
    """`_trace_items` over the work items (`valid`: `(n_items, layers_per_chunk)`, which of each item's layers are
    real), split evenly across the devices `n_devices` (static: a tuple of `jax.Device`, or an integer n for the
    first n local devices; the number of items must be a multiple of their count): one compiled program, each device
    scans its share of the items into its own sums. Returns each device's sums, `(n_devices, n_chunks * chunk, 3)`
    (with `moments`, a pair: the sums of the radiance and of its square), row `i` on device `i`: nothing is
    communicated between the devices (`_finish` adds the devices' sums once, at the end of a render). The items and
    their random numbers do not depend on the devices; only the float32 summation order does."""
    devices = _device_tuple(n_devices)
    trace = _trace_items_unbounded if scene.max_depth == -1 else _trace_items
    if len(devices) == 1:
        out = trace(scene, key, layer_ids, chunk_ids, valid, options, proposal, chunk_paths, moments)
        return jax.tree.map(lambda a: a[None], out)
    arrays, static = eqx.partition((scene, key, proposal), eqx.is_array)

    def share(arrays, layers, chunks, ok):
        sc, k, prop = eqx.combine(arrays, static)
        return jax.tree.map(lambda a: a[None], trace(sc, k, layers, chunks, ok, options, prop, chunk_paths, moments))

    d = PartitionSpec("d")
    return jax.shard_map(share, mesh=_mesh(devices), in_specs=(PartitionSpec(), d, d, d), out_specs=d,
                         check_vma=False)(arrays, layer_ids, chunk_ids, valid)


def render(
    scene: Scene,
    key: PRNGKeyArray,
    spp: int,
    *,
    sampling: SamplingOptions | None = None,
    proposal=None,
    estimator: str | None = None,
    equiangular: bool | None = None,
    light_lobe: float | None = None,
    distance_mix: float | None = None,
    batch_paths: int = DEFAULT_BATCH_PATHS,
    chunk_paths: int = DEFAULT_CHUNK_PATHS,
    devices: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    variance: bool = False,
) -> Float[Array, "H W 3"] | tuple[Float[Array, "H W 3"], Float[Array, "H W 3"]]:
    """Render `scene` with `spp` samples per pixel: linear RGB radiance, `(height, width, 3)` float32.

    **Arguments:**
    - `key`: a JAX PRNG key; the same scene, key and spp give the same image.
    - `sampling`: how paths are sampled, a `SamplingOptions` (estimator, equiangular, light_lobe, distance_mix,
      phase_lobe; default `SamplingOptions()`). The keywords `estimator`, `equiangular`, `light_lobe` and
      `distance_mix` are shorthands that replace those fields (e.g. `render(scene, key, 64, estimator="reparam")`).
    - `proposal`: for `estimator="proposal"`, the fixed reference medium (of the scene medium's kind) that samples
      distances and directions: the image is then a smooth deterministic function of the parameters for a fixed key.

    Execution (speed and memory only; the image changes at float32 rounding level, never in distribution):
    - `batch_paths`: paths per compiled call (memory bound); `progress(done_spp, spp)` is called after each batch.
    - `chunk_paths`: paths traced together in one vectorized pass (default 1024, see `DEFAULT_CHUNK_PATHS`); an
      image of fewer pixels traces `chunk_paths // (H*W)` sample layers side by side in one pass.
    - `devices`: the devices that share each batch's work: None (default) for `jax.devices()`, an integer n for
      the first n local devices, or a list of `jax.Device` (`jaxfog._devices.render_devices`). A CPU is one device
      unless `jaxfog.use_cpu_cores()` ran before JAX started, which the command-line entry points do. After
      `jax.distributed.initialize`, `jax.devices()` holds every process's devices: every process then makes the
      same call (same scene, key, spp and options) and each gets the whole image (docs/distributed.md); the
      processes exchange only the devices' final sums.

    - `variance`: also return each pixel's variance of the image's estimate, `(image, variance)`: the samples'
      variance about their mean, divided by spp (unbiased; spp >= 2), in radiance squared. Its square root is the
      pixel's standard error; with heavy-tailed (firefly) samples it is itself noisy.

    Differentiable with `jax.grad`, `jax.jvp`, `jax.jacfwd` with respect to the scene's array fields.
    """
    options = sampling_options(sampling, estimator=estimator, equiangular=equiangular, light_lobe=light_lobe,
                               distance_mix=distance_mix)
    _check_render_args(scene, key, spp, sampling=options, proposal=proposal, batch_paths=batch_paths,
                       chunk_paths=chunk_paths, devices=None if is_device_list(devices) else devices,
                       progress=progress)
    if not isinstance(variance, bool):
        raise TypeError(f"render: variance must be True or False, got {variance!r}")
    if variance and spp < 2:
        raise ValueError(f"render: variance=True needs spp >= 2 (a variance from one sample is undefined), got {spp}")
    devs = render_devices(devices)
    n_dev = len(devs)
    per = layers_per_batch(scene, spp, batch_paths)
    group = layers_per_chunk(scene, spp, batch_paths, chunk_paths)
    _, n_ch = n_chunks(scene, chunk_paths)
    n_items = items_per_call(scene, spp, batch_paths, chunk_paths, n_dev)
    item = np.arange(n_items)
    H, W = scene.camera.height, scene.camera.width
    chunks = jnp.asarray(item % n_ch, jnp.uint32)
    total = None
    scene, proposal = _replicated((scene, proposal), devs)
    key = _replicated(key, devs, keep=False)  # (a key is new each call, as a rule: placed, not kept)
    for start in range(0, spp, per):
        first = start + (item // n_ch) * group  # each item's first layer; padding items start past the batch
        valid = (first[:, None] + np.arange(group)[None, :]) < min(start + per, spp)
        out = _render_items(scene, key, jnp.asarray(first, jnp.uint32), chunks, jnp.asarray(valid), options,
                            proposal, chunk_paths, devs, variance)
        out = out if variance else (out,)
        total = out if total is None else _add(total, out)
        if progress is not None:
            progress(min(spp, start + per), spp)
    return _finish(total, spp, (H, W, 3), devs)


PLACED_MAX_ELEMENTS = 1 << 16
"""Largest array (elements) whose replicated copy `_replicated` keeps for the next call."""

_PLACED: dict = {}  # id(array) -> (weak reference to the array, its copy on every device)


def _device_tuple(devices) -> tuple:
    """`devices` as a tuple of `jax.Device`: itself, or for an integer n the first n local devices."""
    return tuple(jax.local_devices()[:devices]) if isinstance(devices, int) else tuple(devices)


@lru_cache(maxsize=None)
def _mesh(devices: tuple) -> Mesh:
    """The one-axis mesh `("d",)` of `devices` (a tuple of `jax.Device`, in order)."""
    return Mesh(np.asarray(devices, dtype=object), ("d",))


@lru_cache(maxsize=None)
def _replicated_sharding(devices) -> NamedSharding:
    """A copy on each of `devices` (a tuple of `jax.Device`, or an integer n for the first n local devices)."""
    return NamedSharding(_mesh(_device_tuple(devices)), PartitionSpec())


def _replicated(tree, devices, keep: bool = True):
    """`tree` with each concrete array leaf on all of `devices` (a tuple of `jax.Device`, or an integer n for the
    first n local devices: the layout `_render_items` reads the scene in), each array copied there once and the copy
    reused while the array lives (`keep`): a scene rendered again and again (the fit; a small image per call) is then
    not copied to every device on every call, which was most of the fixed cost of a call
    (`docs/results/bench/PROFILE.md`). Arrays of more than `PLACED_MAX_ELEMENTS` elements are copied each call (no
    copy is kept); traced values (under `jax.jit`, `jax.jacfwd`), and every array when `render` itself is traced by a
    caller's `jax.jit`, are left as they are. Speed only: the values are the same. After `jax.distributed.initialize`
    `devices` may hold other processes' devices: every process places its own copy of the same value."""
    devices = _device_tuple(devices)
    if len(devices) == 1:
        return tree
    sharding = _replicated_sharding(devices)

    def place(x):
        if not isinstance(x, jax.Array) or isinstance(x, jax.core.Tracer):
            return x
        if x.sharding == sharding:
            return x
        hit = _PLACED.get(id(x))
        if hit is not None and hit[0]() is x and hit[1].sharding == sharding:  # (another device count: placed anew)
            return hit[1]
        y = jax.device_put(x, sharding) if sharding.is_fully_addressable else _copies(x, sharding)
        if isinstance(y, jax.core.Tracer):  # inside a caller's `jax.jit`: the program places it; nothing is kept
            return x
        if keep and x.size <= PLACED_MAX_ELEMENTS:
            i = id(x)  # the entry goes when the array does, before its id can be reused
            _PLACED[i] = (weakref.ref(x, lambda _, i=i: _PLACED.pop(i, None)), y)
        return y

    return jax.tree.map(place, tree)


def _copies(x: jax.Array, sharding: NamedSharding) -> jax.Array:
    """`x` as one array with a copy on each device of `sharding` (replicated), some of them other processes': this
    process places its copies on its own devices (every process holds the same value: the same program on the same
    inputs). `jax.device_put` to such a sharding checks that the processes agree (one collective per array) and
    refuses key arrays."""
    here = [d for d in sharding.mesh.devices.flat if d.process_index == jax.process_index()]
    return jax.make_array_from_single_device_arrays(x.shape, sharding, [jax.device_put(x, d) for d in here])


@jax.jit
def _add(a, b):
    """The running sums of the batches, each device's on that device (one dispatch, where eager adds cost one each,
    and more under `jax.jacfwd`; no communication)."""
    return jax.tree.map(jnp.add, a, b)


@partial(jax.jit, static_argnames=("shape", "devices"))
def _finish(total, spp, shape, devices=None):
    """The image (and with the sums of squares, its per-pixel variance) from the devices' sums over `spp` samples
    (`(n_devices, rows, 3)` each, `rows >= H*W`), in one compiled call: the devices' sums added (the render's one
    exchange between devices: an all-reduce of `rows x 3` floats, two arrays with the variance), the mean, and
    `max(E[x^2] - mean^2, 0) / (spp - 1)`. With several `devices` the results are a copy on each of them (so every
    process of a multi-process render holds the whole image)."""
    n_pix = shape[0] * shape[1]
    sums = [t.sum(axis=0)[:n_pix] for t in total]
    if devices is not None and len(devices) > 1:
        sums = jax.lax.with_sharding_constraint(sums, _replicated_sharding(devices))
    mean = (sums[0] / spp).reshape(shape)
    if len(sums) == 1:
        return mean
    second = (sums[1] / spp).reshape(shape)
    return mean, jnp.maximum(second - mean * mean, 0.0) / (spp - 1)
