"""Rendering on several local devices (CPU cores exposed as JAX devices) gives the image and forward-mode derivative of one device:
the same sample layers and random numbers, only summed in another order; a layer split into chunks shared by the
devices gives the paths of the whole layer. Runs in fresh processes, because the
device count is fixed when JAX starts."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from helpers import assert_same_render_up_to_rounding

REPO = Path(__file__).resolve().parent.parent

SCRIPT = r"""
import json, sys
import jaxfog
n = jaxfog.use_cpu_cores(int(sys.argv[1]))
import jax
sc = jaxfog.load_scene("data_synthetic/scenes/spot_fog.json",
                       ["camera.width=16", "camera.height=16", "integrator.max_depth=4"]).scene
f = lambda s: jaxfog.render(sc.replace_medium(sigma_t=s), jax.random.key(3), 7)  # 7 spp: uneven split
img, tan = jax.jvp(f, (0.5,), (1.0,))
# 1 spp in three chunks of 100 pixels (the last one padded): three work items, padded to a multiple of the devices
img1 = jaxfog.render(sc, jax.random.key(5), 1, chunk_paths=100)
img1_whole = jaxfog.render(sc, jax.random.key(5), 1)
print(json.dumps({"devices": n, "img": img.tolist(), "jvp": tan.tolist(), "img1": img1.tolist(),
                  "img1_whole": img1_whole.tolist()}))
"""


def _start(n: int) -> subprocess.Popen:
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    return subprocess.Popen([sys.executable, "-c", SCRIPT, str(n)], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)


def _result(p: subprocess.Popen) -> dict:
    out, err = p.communicate(timeout=600)
    assert p.returncode == 0, err[-2000:]
    return json.loads(out.strip().splitlines()[-1])


# slow tier: two fresh JAX processes compile the renderer (60 s on 2 cores with a cold cache)
@pytest.mark.slow
def test_two_devices_match_one():
    """One device and two (and a 1-spp layer in chunks of 100 pixels vs whole) are differently compiled programs of
    the same paths: the images and the forward-mode derivative image agree up to float32 rounding, including rare
    branch flips (the tolerance and its derivation: `helpers.assert_same_render_up_to_rounding`). A wrong split (a
    lost or repeated chunk, other random numbers) changes most pixels and fails; so does the other key's image."""
    procs = _start(1), _start(2)  # both at once: each compiles mostly on one core
    one, two = (_result(p) for p in procs)
    assert one["devices"] == 1 and two["devices"] == 2
    a, b = np.asarray(one["img"]), np.asarray(two["img"])
    assert_same_render_up_to_rounding(a, b, spp=7, label="7 spp, 1 vs 2 devices")
    assert_same_render_up_to_rounding(np.asarray(one["jvp"]), np.asarray(two["jvp"]), spp=7,
                                      scale=np.asarray(one["jvp"]), label="d image / d sigma_t, 1 vs 2 devices")
    # a 1-spp image split into chunks shared by the devices: the same paths, whatever the chunking and device count
    whole = np.asarray(one["img1_whole"])
    for r in (one, two):
        assert_same_render_up_to_rounding(np.asarray(r["img1"]), whole, spp=1,
                                          label=f"1 spp in chunks of 100, {r['devices']} device(s), vs whole")
    assert np.mean(np.asarray(one["img1"]) != np.asarray(one["img"])) > 0.5  # positive control: other key and spp


def test_devices_argument_is_checked():
    import jax
    import pytest

    import jaxfog

    sc = jaxfog.load_scene(str(REPO / "data_synthetic/scenes/spot_fog.json"),
                           ["camera.width=4", "camera.height=4"]).scene
    for bad in (0, jax.local_device_count() + 1, 1.5):
        with pytest.raises(ValueError, match="devices"):
            jaxfog.render(sc, jax.random.key(0), 1, devices=bad)


def test_the_rounding_comparison_can_fail():
    """`assert_same_render_up_to_rounding` accepts rounding and a few flipped pixels, and refuses another image."""
    import pytest

    rng = np.random.default_rng(0)
    a = rng.uniform(0.1, 2.0, (16, 16, 3))
    assert_same_render_up_to_rounding(a, a * (1 + 3e-5), spp=4)  # rounding
    b = a.copy()
    b[3, 4] *= 1.5  # one branch flip
    assert assert_same_render_up_to_rounding(a, b, spp=4) == 1
    with pytest.raises(AssertionError):
        assert_same_render_up_to_rounding(a, rng.uniform(0.1, 2.0, a.shape), spp=4)  # another key
    with pytest.raises(AssertionError):
        assert_same_render_up_to_rounding(a, a * (1 + 3e-3), spp=4)  # a bias everywhere
    c = a.copy()
    c[5, 5, 0] = -a[5, 5, 0]  # negative radiance: more than any flip of non-negative paths can change
    with pytest.raises(AssertionError):
        assert_same_render_up_to_rounding(a, c, spp=4)


PLACEMENT_SCRIPT = r"""
import gc, json
import jaxfog
jaxfog.use_cpu_cores(2)
import jax, jax.numpy as jnp, numpy as np
from jaxfog import _render as R

sc = jaxfog.load_scene("data_synthetic/scenes/spot_fog.json", ["camera.width=8", "camera.height=8"]).scene
key = jax.random.key(4)
values = lambda x: np.asarray(jax.random.key_data(x) if jnp.issubdtype(x.dtype, jax.dtypes.prng_key) else x)
a, b = R._replicated((sc, key), 2), R._replicated((sc, key), 2)
la, lb, lo = jax.tree.leaves(a), jax.tree.leaves(b), jax.tree.leaves((sc, key))
out = {"n_leaves": len(lo),
       "reused": all(x is y for x, y in zip(la, lb)),
       "same_values": all(np.array_equal(values(x), values(y)) for x, y in zip(la, lo)),
       "on_both": all(x.sharding == R._replicated_sharding(2) for x in la),
       "cached": len(R._PLACED)}
del a, b, la, lb, lo
img = np.asarray(jaxfog.render(sc, key, 4))
img_again = np.asarray(jaxfog.render(sc, key, 4))
# a scene whose arrays are committed to one device (the output of a jitted function) renders the same image
sc1 = jax.tree.map(lambda x: jax.device_put(x, jax.devices()[1]) if isinstance(x, jax.Array) else x, sc)
img_committed = np.asarray(jaxfog.render(sc1, key, 4))
big = jnp.ones(R.PLACED_MAX_ELEMENTS + 1)
R._replicated(big, 2)
out["big_cached"] = id(big) in R._PLACED
out["tracer_kept"] = bool(jax.jit(lambda x: jnp.asarray(R._replicated(x, 2) is x))(jnp.ones(3)))
# render traced by a caller's jit (the scene a constant of that program): nothing traced is kept for later calls
fresh = jaxfog.load_scene("data_synthetic/scenes/spot_fog.json", ["camera.width=8", "camera.height=8"]).scene
n_before = len(R._PLACED)
img_jit = np.asarray(jax.jit(lambda k: jaxfog.render(fresh, k, 4))(key))
out["kept_under_jit"] = len(R._PLACED) - n_before
img_after = np.asarray(jaxfog.render(fresh, key, 4))
out["img_jit"], out["img_after_jit"] = img_jit.tolist(), img_after.tolist()
del fresh
del sc, sc1, key
gc.collect()
out["cached_after_del"] = len(R._PLACED)
out["images_equal"] = bool(np.array_equal(img, img_again)) and bool(np.array_equal(img, img_committed))
out["image_mean"] = float(img.mean())
print(json.dumps(out))
"""


# slow tier: a fresh JAX process with two devices compiles the renderer (36 s on 2 cores with a cold cache)
@pytest.mark.slow
def test_the_scene_is_copied_to_the_devices_once_and_released_with_it():
    """`render` copies the scene's arrays to every device once and reuses the copies while the arrays live (the fixed
    cost of a call): the copies hold the same values, on both devices; the cache lets go of them with the scene,
    keeps no copy of a large array, leaves traced values alone (and keeps nothing when a caller's `jax.jit` traces
    `render`, after which a plain call still works), and the image is the same on the second call and for a scene
    committed to one device."""
    p = subprocess.Popen([sys.executable, "-c", PLACEMENT_SCRIPT], cwd=REPO, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, env=dict(os.environ, JAX_PLATFORMS="cpu"))
    r = _result(p)
    assert r["n_leaves"] > 10 and r["reused"] and r["same_values"] and r["on_both"], r
    assert r["cached"] >= r["n_leaves"] - 1, r  # every leaf (equal leaves may be one array)
    assert not r["big_cached"] and r["tracer_kept"], r
    assert r["kept_under_jit"] == 0, r
    # two differently compiled programs (the scene a constant of the caller's), the same paths
    assert_same_render_up_to_rounding(np.asarray(r["img_jit"]), np.asarray(r["img_after_jit"]), spp=4,
                                      label="render under a caller's jit, then a plain call")
    assert r["cached_after_del"] == 0, r
    assert r["images_equal"] and r["image_mean"] > 0, r
