"""Paths of any length (`max_depth = -1`): Russian roulette after `rr_depth` and path regeneration.

Each check compares two independent estimators over `N_KEYS` keys with `assert_statistically_equal` (tolerances
from both standard errors; thresholds in `tests/conftest.py`): the unbounded render against a fixed depth deep enough
that the paths it cuts carry less than 1e-3 of one standard error (albedo 0.6: the throughput after k scattering
vertices is below 0.6^k; at depth 24 the remainder is < 0.6^23 / (1 - 0.6) ~ 2e-5 of the image).
"""

from __future__ import annotations

import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfog as jf

SCENES = os.path.join(os.path.dirname(__file__), "..", "data_synthetic", "scenes")
SIZE = ["camera.width=12", "camera.height=10"]


def _scene(depth, extra=()):
    return jf.load_scene(os.path.join(SCENES, "spot_fog.json"),
                         SIZE + [f"integrator.max_depth={depth}", "medium.albedo=0.6", *extra]).scene


# slow tier: a 24-segment and an unbounded tracer compiled and rendered at 8 keys (31 s on 2 cores)
@pytest.mark.slow
def test_unbounded_equals_a_deep_fixed_depth(stats):
    unbounded = stats.mean_and_se(stats.render_keys(_scene(-1), 8, seed=21))
    deep = stats.mean_and_se(stats.render_keys(_scene(24), 8, seed=22))
    stats.assert_statistically_equal(unbounded[0], unbounded[1], deep[0], ref_se=deep[1], label="max_depth -1 vs 24")


@pytest.mark.slow
def test_unbounded_image_depends_only_on_key_and_spp():
    """The lanes' regeneration order changes with the chunk size; the paths and so the image do not (float32
    summation order aside)."""
    scene = _scene(-1)
    key = jax.random.key(3)
    a = np.asarray(jf.render(scene, key, 4, batch_paths=120 * 8))
    b = np.asarray(jf.render(scene, key, 4, chunk_paths=37))
    # The same paths, traced by two differently compiled programs (lane counts 120 and 37) and summed in another
    # order: float32 rounding of the sums moves a value by a few ulps (rtol 1e-5), and a rounding difference may
    # flip a path's branch (then that pixel differs by up to one path's share); such flips are rare (< 1e-3 of the
    # paths where measured), so at most 1% of the values may differ beyond the rounding tolerance.
    differs = np.abs(a - b) > 1e-5 * np.abs(a) + 1e-8
    assert differs.mean() <= 0.01, differs.mean()
    assert not np.array_equal(a, np.asarray(jf.render(scene, jax.random.key(4), 4, batch_paths=120 * 8)))


@pytest.mark.slow
def test_unbounded_forward_derivative_equals_the_deep_fixed_depth(stats):
    """d(image)/d(sigma_t) by `jax.jvp` (detached estimator) through the regenerating loop, against the same
    derivative at depth 24, over independent keys."""

    def tangents(depth, seed):
        scene = _scene(depth)
        out = []
        for k in range(stats.N_KEYS):
            f = lambda s: jf.render(scene.replace_medium(sigma_t=jnp.broadcast_to(s, (3,))), jax.random.fold_in(
                jax.random.key(seed), k), 8, devices=1)
            out.append(np.asarray(jax.jvp(f, (jnp.float32(0.5),), (jnp.float32(1.0),))[1], np.float64))
        return stats.mean_and_se(np.stack(out))

    unb, deep = tangents(-1, 31), tangents(24, 32)
    assert np.all(np.isfinite(unb[0]))
    stats.assert_statistically_equal(unb[0], unb[1], deep[0], ref_se=deep[1], label="d/d sigma_t, -1 vs 24")


def test_max_depth_minus_one_in_files_and_modules():
    data = json.load(open(os.path.join(SCENES, "spot_fog.json")))
    data["integrator"] = {"max_depth": -1, "rr_depth": 3}
    scene = jf._scene_io.scene_from_dict(data).scene
    assert scene.max_depth == -1 and scene.rr_depth == 3
    data["integrator"] = {"max_depth": 0}
    with pytest.raises(jf.SceneError, match=r"integrator.max_depth: 0 is out of range; valid range \[1, inf\), or -1"):
        jf._scene_io.scene_from_dict(data)
    with pytest.raises(ValueError, match="max_depth"):
        jf.Scene(camera=scene.camera, max_depth=-2)
    with pytest.raises(ValueError, match="rr_depth"):
        jf.Scene(camera=scene.camera, max_depth=-1, rr_depth=0)
