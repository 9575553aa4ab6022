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

REPO = Path(__file__).resolve().parent.parent

SCRIPT = r"""
import json, sys
import jaxfog
n = jaxfog.use_cpu_cores(int(sys.argv[1]))
import jax
sc = jaxfog.load_scene("data_synthetic/scenes/spot_fog.json",
                       ["camera.width=16", "camera.height=16", "integrator.max_depth=4"]).scene
f = lambda s: jaxfog.render(sc.replace_medium(sigma_t=s), jax.random.key(3), 7)  # 7 spp: uneven split
img = f(0.5)
val, tan = jax.jvp(lambda s: f(s).mean(), (0.5,), (1.0,))
# 1 spp in three chunks of 100 pixels (the last one padded): three work items, padded to a multiple of the devices
img1 = jaxfog.render(sc, jax.random.key(5), 1, chunk_paths=100)
img1_whole = jaxfog.render(sc, jax.random.key(5), 1)
print(json.dumps({"devices": n, "img": img.tolist(), "jvp": float(tan), "img1": img1.tolist(),
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


def test_two_devices_match_one():
    procs = _start(1), _start(2)  # both at once: each compiles mostly on one core
    one, two = (_result(p) for p in procs)
    assert one["devices"] == 1 and two["devices"] == 2
    a, b = np.asarray(one["img"]), np.asarray(two["img"])
    # float32 sums of 7 layers in another order: rounding only
    np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-7)
    assert abs(two["jvp"] - one["jvp"]) <= 1e-5 * abs(one["jvp"])
    # a 1-spp image split into chunks shared by the devices: the same paths, whatever the chunking and device count
    for r in (one, two):
        np.testing.assert_allclose(np.asarray(r["img1"]), np.asarray(one["img1_whole"]), rtol=1e-5, atol=1e-7)


def test_devices_argument_is_checked():
    import jax
    import pytest

    import jaxfog

    sc = jaxfog.load_scene(str(REPO / "data_synthetic/scenes/spot_fog.json"),
                           ["camera.width=4", "camera.height=4"]).scene
    for bad in (0, jax.local_device_count() + 1, 1.5):
        with pytest.raises(ValueError, match="devices"):
            jaxfog.render(sc, jax.random.key(0), 1, devices=bad)
