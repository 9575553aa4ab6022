"""Rendering: generate rays -> `vmap(trace_path)` -> average, in batches of whole sample layers.

Sample `k` of every pixel draws its random numbers from `fold_in(key, k)`, so an image depends only on the scene, the
key and spp (never on the batch size), and memory is bounded for any spp.
"""

from __future__ import annotations

import math
from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec
from jaxtyping import Array, Float, PRNGKeyArray

from ._integrator import ESTIMATORS, Options, make_proposal, n_dims, n_iterations, trace_path
from ._scene import Scene, pack

DEFAULT_BATCH_PATHS = 1 << 16
"""Paths traced per compiled call (a multiple of the pixel count is used); bounds memory (~1 KiB per path)."""

DEFAULT_CHUNK_PATHS = 1024
"""Paths traced together in one vectorized pass (a sample layer is traced in chunks of this many pixels, one after
the other). A speed knob only: each path's random numbers do not depend on it. Measured on a 2-core CPU (XLA):
1024 is ~1.4x faster per sample than a whole 128x128 layer at once; 2048 and 4096 are slower, 256 and 512 in
between (docs/bench/PROFILE.md; re-measure with `python -m jaxfog.bench_profile` on other hardware)."""


def layers_per_batch(scene: Scene, spp: int, batch_paths: int = DEFAULT_BATCH_PATHS) -> int:
    """Sample layers (one sample of every pixel) per batch: as many as fit in `batch_paths`, at least 1, at most spp."""
    n_pix = scene.camera.width * scene.camera.height
    return max(1, min(spp, batch_paths // n_pix))


def _trace_layers(scene: Scene, key: PRNGKeyArray, layer_ids: Array, valid: Array, options: Options, proposal,
                  chunk_paths: int = DEFAULT_CHUNK_PATHS):
    """Sum over the given sample layers of every pixel's radiance: `(H*W, 3)`. Layers where `valid` is False are
    padding. Each layer is traced in chunks of `chunk_paths` pixels (static); the last chunk is padded with copies of
    the first pixels (real paths, so no NaN can reach a gradient), whose results are dropped."""
    cam = scene.camera
    H, W = cam.height, cam.width
    pk = pack(scene)
    prop = make_proposal(scene, options, proposal)
    n_iter, K = n_iterations(scene), n_dims(scene)
    rows, cols = jnp.divmod(jnp.arange(H * W), W)
    base = jnp.stack([cols, rows], axis=-1).astype(jnp.float32)
    n_pix = H * W
    chunk = max(1, min(int(chunk_paths), n_pix))
    n_chunks = -(-n_pix // chunk)
    pad = n_chunks * chunk - n_pix

    def one_layer(layer_id, valid):
        k = jax.random.fold_in(key, layer_id)
        k_pix, k_path = jax.random.split(k)
        jitter = jax.random.uniform(k_pix, (H * W, 2))
        U = jax.random.uniform(k_path, (H * W, n_iter, K))

        def one_path(pixel, U_p):
            o, d = cam.generate_ray(pixel)
            return trace_path(scene, pk, prop, options, o, d, U_p)

        pixels = base + jitter
        if n_chunks == 1:
            radiance = jax.vmap(one_path)(pixels, U)
        else:
            pixels = jnp.concatenate([pixels, pixels[:pad]]).reshape(n_chunks, chunk, 2)
            U = jnp.concatenate([U, U[:pad]]).reshape(n_chunks, chunk, n_iter, K)
            radiance = jax.lax.map(lambda xs: jax.vmap(one_path)(*xs), (pixels, U)).reshape(-1, 3)[:n_pix]
        return jnp.where(valid, radiance, 0.0)

    total = jnp.zeros((H * W, 3), jnp.float32)

    def step(acc, xs):
        return acc + one_layer(*xs), None

    total, _ = jax.lax.scan(step, total, (layer_ids, valid))
    return total


def layers_per_call(scene: Scene, spp: int, batch_paths: int = DEFAULT_BATCH_PATHS, n_devices: int = 1) -> int:
    """Sample layers `render` traces per compiled call: `layers_per_batch` rounded up to whole shares per device.
    Every device gets the same number (padding layers where needed, even at spp 1): a padding layer costs no wall
    time beside a real one, and a small spp compiles no program of its own."""
    return -(-layers_per_batch(scene, spp, batch_paths) // n_devices) * n_devices


@eqx.filter_jit
def _render_layers(scene: Scene, key: PRNGKeyArray, layer_ids: Array, n_valid: Array, options: Options, proposal,
                   chunk_paths: int = DEFAULT_CHUNK_PATHS, n_devices: int = 1):
    """`_trace_layers` over `layer_ids` (the first `n_valid` are real), split evenly across the first `n_devices`
    local devices (static; `len(layer_ids)` must be a multiple of it): one compiled program, each device scans its
    share of the layers, the shares are summed. The layers and their random numbers do not depend on `n_devices`;
    only the float32 summation order does."""
    valid = jnp.arange(layer_ids.shape[0]) < n_valid
    if n_devices == 1:
        return _trace_layers(scene, key, layer_ids, valid, options, proposal, chunk_paths)
    mesh = Mesh(np.asarray(jax.local_devices()[:n_devices]), ("d",))
    arrays, static = eqx.partition((scene, key, proposal), eqx.is_array)

    def share(arrays, ids, ok):
        sc, k, prop = eqx.combine(arrays, static)
        return _trace_layers(sc, k, ids, ok, options, prop, chunk_paths)[None]

    parts = jax.shard_map(share, mesh=mesh, in_specs=(PartitionSpec(), PartitionSpec("d"), PartitionSpec("d")),
                          out_specs=PartitionSpec("d"), check_vma=False)(arrays, layer_ids, valid)
    return parts.sum(axis=0)


def render(
    scene: Scene,
    key: PRNGKeyArray,
    spp: int,
    *,
    estimator: str = "detached",
    proposal=None,
    equiangular: bool = True,
    light_lobe: float = 0.3,
    distance_mix: float = 0.3,
    batch_paths: int = DEFAULT_BATCH_PATHS,
    chunk_paths: int = DEFAULT_CHUNK_PATHS,
    devices: int | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> Float[Array, "H W 3"]:
    """Render `scene` with `spp` samples per pixel: linear RGB radiance, `(height, width, 3)` float32.

    **Arguments:**
    - `key`: a JAX PRNG key; the same scene, key and spp give the same image.
    - `estimator`: how derivatives are estimated (values are the same in expectation): `"detached"` (default;
      detached sampling, attached weights), `"reparam"` (reparameterized free flight and HG), `"proposal"` (sampling
      from the fixed reference `proposal`, a `HomogeneousMedium`; a smooth deterministic function of the parameters
      for a fixed key). See `estimators.md`.
    - `equiangular`: equiangular sampling toward point and spot lights, MIS-combined with free flight.
    - `light_lobe`: probability (in [0, 1)) of sampling scattering directions uniformly in the angle to a point/spot
      light instead of from the phase function / cosine lobe; `distance_mix`: probability of placing a path's medium
      vertex by equiangular sampling instead of free flight (needs `equiangular`). Neither is used by "reparam".
    - `batch_paths`: paths per compiled call (memory bound); `progress(done_spp, spp)` is called after each batch.
    - `chunk_paths`: paths traced together in one vectorized pass (speed only: the image changes at float32
      rounding level, never in distribution; default 1024, see `DEFAULT_CHUNK_PATHS`).
    - `devices`: how many local devices share each batch's sample layers (default: all of them; a CPU is one device
      unless `jaxfog.use_cpu_cores()` ran before JAX started, which the command-line entry points do). The image
      changes at float32 rounding level only.

    Differentiable with `jax.grad`, `jax.jvp`, `jax.jacfwd` with respect to the scene's array fields.
    """
    if estimator not in ESTIMATORS:
        raise ValueError(f"estimator must be one of {ESTIMATORS}, got {estimator!r}")
    if not isinstance(spp, int) or spp < 1:
        raise ValueError(f"spp must be a positive integer, got {spp!r}")
    if not isinstance(chunk_paths, int) or chunk_paths < 1:
        raise ValueError(f"chunk_paths must be a positive integer, got {chunk_paths!r}")
    for name, v in (("light_lobe", light_lobe), ("distance_mix", distance_mix)):
        if not 0.0 <= v < 1.0:
            raise ValueError(f"{name} must be in [0, 1), got {v!r}")
    options = Options(estimator=estimator, equiangular=bool(equiangular), light_lobe=float(light_lobe),
                      distance_mix=float(distance_mix))
    n_dev = jax.local_device_count() if devices is None else devices
    if not isinstance(n_dev, int) or not 1 <= n_dev <= jax.local_device_count():
        raise ValueError(f"devices must be an integer in [1, {jax.local_device_count()}], got {devices!r}")
    per = layers_per_call(scene, spp, batch_paths, n_dev)
    n_batches = math.ceil(spp / per)
    H, W = scene.camera.height, scene.camera.width
    total = jnp.zeros((H * W, 3), jnp.float32)
    for i in range(n_batches):
        start = i * per
        ids = jnp.arange(start, start + per, dtype=jnp.uint32)
        n_valid = jnp.int32(min(per, spp - start))
        total = total + _render_layers(scene, key, ids, n_valid, options, proposal, chunk_paths, n_dev)
        if progress is not None:
            progress(min(spp, start + per), spp)
    return (total / spp).reshape(H, W, 3)
