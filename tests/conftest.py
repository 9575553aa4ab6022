"""Configuration and fixtures of the jaxfog test suite; the shared helpers live in `tests/helpers.py`.

Configuration
- The renderer is float32 by design; `jax_enable_x64` stays off. Exact references are computed with numpy/scipy in
  float64 instead.
- `jax_numpy_rank_promotion = "raise"`: the library must not rely on implicit rank promotion (it passes with it).
- Every CPU core is a JAX device (`jaxfog.use_cpu_cores()`), so renders split their sample layers across devices as
  the command-line tools do (tests/test_devices.py checks that this changes nothing but float32 rounding).
- Tests marked `slow` are deselected by default (`pyproject.toml`); `pytest -m slow` runs them.
"""

from __future__ import annotations

import os

import jax
import numpy as np
import pytest

import jaxfog as jf
from helpers import (
    FLOOR_CAMERA,
    N_KEYS,
    CameraSpec,
    assert_statistically_equal,
    hg_np,
    make_floor,
    mean_and_se,
    render_keys,
    spot_falloff_np,
)

jax.config.update("jax_numpy_rank_promotion", "raise")
jf.use_cpu_cores()  # every core a JAX device, as the command-line entry points do: renders run sharded



def pytest_xdist_auto_num_workers(config):
    """Workers for `-n auto` (pyproject's addopts): two for the default run, whose time is mostly XLA compiling one
    program at a time, so two processes on 2 cores take ~0.6x the wall of one; none (one process) for any other
    selection, e.g. `-m slow`, whose fits have time budgets and whose benchmarks time themselves (a second worker on
    the same cores would change what they measure)."""
    if config.option.markexpr.strip() != "not slow":
        return 0
    return min(2, os.cpu_count() or 1) if (os.cpu_count() or 1) >= 2 else 0


# ------------------------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def stats():
    """The statistical helpers as one namespace (render_keys, mean_and_se, assert_statistically_equal, N_KEYS)."""

    class _Stats:
        pass

    ns = _Stats()
    ns.render_keys = render_keys
    ns.mean_and_se = mean_and_se
    ns.assert_statistically_equal = assert_statistically_equal
    ns.N_KEYS = N_KEYS
    ns.hg_np = hg_np
    ns.spot_falloff_np = spot_falloff_np
    return ns


@pytest.fixture(scope="module")
def camera_spec():
    """Factory for `CameraSpec` (plain floats; `.build()` gives a `jf.Camera`, `.rays(n)` float64 reference rays)."""
    return CameraSpec


@pytest.fixture(scope="module")
def floor_scene():
    """Factory: a diffuse floor seen from `FLOOR_CAMERA`, lit by `lights`, optional `medium`, `max_depth`.

    Returns `(scene, camera_spec, floor_reflectance)`."""

    def build(lights, medium=None, max_depth=2, reflectance=(0.7, 0.5, 0.3), camera=FLOOR_CAMERA):
        scene = jf.Scene(camera=camera.build(), shapes=(make_floor(reflectance),), lights=tuple(lights),
                         medium=medium, max_depth=max_depth)
        return scene, camera, np.asarray(reflectance, np.float64)

    return build


@pytest.fixture(scope="module")
def fog():
    """Factory for a `HomogeneousMedium` from plain values (RGB or scalar)."""

    def build(sigma_t, albedo, g=0.0):
        return jf.HomogeneousMedium(sigma_t=sigma_t, albedo=albedo, phase=jf.HenyeyGreenstein(g))

    return build
