"""Helpers for command-line tools, fitting scripts and benchmarks built on jaxfog: the public names of what the
library's own entry points use, so that no script reaches into a private module.

Running
- `use_cpu_cores()`: every CPU core a JAX device (call before JAX starts).
- `use_compilation_cache(path=None)`, `cache_dir()`: JAX's persistent compilation cache (`$JAXFOG_CACHE_DIR`).
- `StoredProgram(name, fn)`, `program_dir()`: `fn` compiled with its traced program kept beside that cache, so that
  the next process neither traces nor compiles it again.
- One run on several processes (docs/distributed.md): `add_distributed_arguments(parser)` (`--coordinator`,
  `--num-processes`, `--process-id`), `launch_of(...)` (checked, `LaunchError`), `initialize_distributed(launch)`,
  `process_index()`, `run_process(body, report)` and `report_unexpected(e, prog)` (a failed process ends at once).

Checking inputs and writing outputs
- `check_size(width, height, spp, max_depth, ...)`, `LimitError`, `limits_lifted()`: the size limits of a render.
- `seed_argument(text)`: an argparse type for seeds in [0, 2^32 - 1].
- `read_only(path)`: whether an existing file must not be replaced (also for the superuser).
- `atomic_write(path, write)`: call `write(temp_path)`, then move the result onto `path` (nothing half-written).
- `scene_from_dict(d, source=...)`: a scene file's dict, validated, as a `SceneFile`.

Measuring
- `CompileTimer`, `max_rss_mib()`: compile time of JAX programs and the process's peak memory.
- `render_items`, `items_per_call`, `layers_per_batch`, `layers_per_chunk`, `DEFAULT_BATCH_PATHS`,
  `DEFAULT_CHUNK_PATHS`: the render loop's work items and batch sizes (for profiling the loop's parts).
- `n_dims(scene)`, `n_iterations(scene)`, `uniforms(key, n, k)`: the random-number layout of a path.
- `mesh_nearest(mesh, o, d, t_max, compaction=True)`, `mesh_occluded(mesh, o, d, dist)`,
  `brute_force_nearest(mesh, o, d, t_max)`: a `Mesh`'s ray queries by its BVH (with or without the lane compaction
  of a batch of rays) and by testing every triangle (for measuring the BVH).

Mitsuba 3 (the optional extra `compare`)
- `import_mitsuba(variant=None)`, `TABPHASE_SIZE`, `tabphase_error(diameter)`: the Mitsuba module with a variant set,
  and the tabulated droplet phase function's size and interpolation error.
"""

from __future__ import annotations

from ._cache import cache_dir as cache_dir, use_compilation_cache as use_compilation_cache
from ._devices import use_cpu_cores as use_cpu_cores
from ._programs import StoredProgram as StoredProgram, program_dir as program_dir
from ._distributed import (
    LaunchError as LaunchError,
    add_arguments as add_distributed_arguments,
    initialize as initialize_distributed,
    launch_of as launch_of,
    process_index as process_index,
    report_unexpected as report_unexpected,
    run_process as run_process,
)
from ._image import _atomic_write as atomic_write
from ._integrator import n_dims as n_dims, n_iterations as n_iterations
from ._measure import CompileTimer as CompileTimer, max_rss_mib as max_rss_mib
from ._mesh import brute_force_nearest as brute_force_nearest, mesh_occluded as mesh_occluded
from ._mitsuba import TABPHASE_SIZE as TABPHASE_SIZE, import_mitsuba as import_mitsuba
from ._mitsuba import tabphase_error as tabphase_error
from ._random import uniforms as uniforms
from ._render import (
    DEFAULT_BATCH_PATHS as DEFAULT_BATCH_PATHS,
    DEFAULT_CHUNK_PATHS as DEFAULT_CHUNK_PATHS,
    _render_items as render_items,
    items_per_call as items_per_call,
    layers_per_batch as layers_per_batch,
    layers_per_chunk as layers_per_chunk,
)
from ._scene_io import scene_from_dict as scene_from_dict
from ._validate import (
    LimitError as LimitError,
    check_size as check_size,
    limits_lifted as limits_lifted,
    read_only as read_only,
    seed_argument as seed_argument,
)

__all__ = ["CompileTimer", "DEFAULT_BATCH_PATHS", "DEFAULT_CHUNK_PATHS", "LaunchError", "LimitError", "TABPHASE_SIZE",
           "add_distributed_arguments", "atomic_write", "brute_force_nearest", "cache_dir", "check_size",
           "import_mitsuba", "initialize_distributed", "items_per_call", "launch_of", "layers_per_batch",
           "layers_per_chunk", "limits_lifted", "max_rss_mib", "mesh_nearest", "mesh_occluded", "n_dims",
           "n_iterations", "process_index", "read_only", "render_items", "report_unexpected", "run_process",
           "scene_from_dict", "seed_argument", "tabphase_error", "uniforms", "use_compilation_cache", "use_cpu_cores"]


def mesh_nearest(mesh, o, d, t_max=float("inf"), compaction: bool = True):
    """The nearest hit of the ray from `o` along unit `d` (scene units) with a `Mesh`, closer than `t_max`, by its
    BVH: `(t, slot)`, the distance and the hit triangle's slot in the BVH's leaves (inf and -1 on a miss); not
    differentiated. Under `jax.vmap` over rays the walk runs with lane compaction, as the renderer's does;
    `compaction=False` gives the same per-ray walk vectorized lane by lane (the same results; for measuring what
    compaction gains)."""
    from ._mesh import _walk_one, mesh_nearest as nearest

    if compaction:
        return nearest(mesh, o, d, t_max)
    import jax
    import jax.numpy as jnp

    o, d, t_max = jax.lax.stop_gradient((jnp.asarray(o, jnp.float32), jnp.asarray(d, jnp.float32),
                                         jnp.asarray(t_max, jnp.float32)))
    return _walk_one(jax.lax.stop_gradient(mesh.rows), o, d, t_max, root=mesh.root, S=mesh.stack_size, box=mesh.box,
                     n_leaves=mesh.n_leaves, any_hit=False)
