"""One render (and one fit) on the devices of several processes, through JAX's multi-controller runtime
(docs/distributed.md): two CPU processes on localhost (Gloo collectives) render the one-process image up to float32
rounding and fit the one-process estimate; only process 0 writes; a process that fails ends the other within a
bounded time, and nothing is written. The option checks run in this process, before any work (default tier); the
runs start fresh JAX processes, which compile the renderer (the slow tier)."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import jaxfog
from helpers import SPOT_FOG, assert_same_render_up_to_rounding
from jaxfog import _distributed, _render
from jaxfog._cli import main as cli_main

REPO = Path(__file__).resolve().parent.parent
TINY = ["--set", "camera.width=16", "--set", "camera.height=16", "--spp", "6", "--seed", "5", "--no-progress"]


# ------------------------------------------------------------------------------------------- checks before any work
@pytest.fixture
def nothing_starts(monkeypatch):
    """Neither `jax.distributed.initialize` (through `_distributed.initialize`) nor a render may run."""

    def fail(*args, **kwargs):
        pytest.fail("started although the options should have been refused before any work")

    monkeypatch.setattr(_distributed, "initialize", fail)
    monkeypatch.setattr(_render, "render", fail)
    monkeypatch.delenv(_distributed.ENV_COORDINATOR, raising=False)


@pytest.mark.parametrize("options, message", [
    (["--coordinator", "localhost"], "--coordinator 'localhost': expected HOST:PORT"),
    (["--coordinator", "localhost:99999", "--num-processes", "2", "--process-id", "0"], "the port '99999' is not"),
    (["--coordinator", "localhost:1234", "--num-processes", "2", "--process-id", "2"],
     "--process-id 2 is out of range for --num-processes 2; valid range [0, 1]"),
    (["--coordinator", "localhost:1234", "--num-processes", "0", "--process-id", "0"], "--num-processes 0: expected"),
    (["--num-processes", "2", "--process-id", "1"], "--num-processes 2 --process-id 1: a multi-process run needs "
                                                    "--coordinator HOST:PORT"),
])
def test_bad_multi_process_options_are_one_line_errors_before_any_work(nothing_starts, tmp_path, capsys, options,
                                                                       message):
    """`jaxfog render` and `python -m fitting.fit` refuse an option that cannot work with one line naming it, before
    JAX's distributed runtime starts or anything renders."""
    from fitting.fit import main as fit_main

    assert cli_main(["render", str(SPOT_FOG), "-o", str(tmp_path / "o.exr"), *TINY, *options]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("jaxfog: error: ") and message in err, err
    assert fit_main([str(SPOT_FOG), str(tmp_path / "t.exr"), "--out", str(tmp_path / "r.json"), *options]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err, err
    assert list(tmp_path.iterdir()) == []


def test_launch_options_and_jax_s_environment_variable():
    """No option and no `$JAX_COORDINATOR_ADDRESS`: one process. The variable stands in for `--coordinator` (JAX
    reads it itself); the count and id may come from the cluster (left to JAX: None); an IPv6 host in brackets."""
    launch_of = _distributed.launch_of
    assert launch_of(None, None, None, environ={}) is None
    assert launch_of("h:1", 2, 1, environ={}) == ("h:1", 2, 1)
    assert launch_of(None, None, None, environ={"JAX_COORDINATOR_ADDRESS": "10.0.0.1:4"}) == ("10.0.0.1:4", None,
                                                                                             None)
    assert launch_of("[::1]:80", 3, 0, environ={"JAX_COORDINATOR_ADDRESS": "x:1"}).coordinator == "[::1]:80"
    with pytest.raises(_distributed.LaunchError, match=r"\$JAX_COORDINATOR_ADDRESS 'nohost:': the port"):
        launch_of(None, 2, 0, environ={"JAX_COORDINATOR_ADDRESS": "nohost:"})
    with pytest.raises(_distributed.LaunchError, match="--process-id -1"):
        launch_of("h:1", None, -1, environ={})


def test_render_devices_argument():
    """`render(..., devices=...)`: None is `jax.devices()`, n the first n local devices, a list those devices;
    an empty list, a repeated device or another kind of value is refused, naming the argument."""
    import jax

    from jaxfog._devices import render_devices

    assert render_devices() == tuple(jax.devices()) and render_devices(1) == (jax.local_devices()[0],)
    assert render_devices(jax.devices()[::-1]) == tuple(jax.devices()[::-1])
    for bad, error in (([], "empty list"), ([jax.devices()[0]] * 2, "listed twice")):
        with pytest.raises(ValueError, match=f"render: devices: .*{error}"):
            render_devices(bad)
    with pytest.raises(TypeError, match="render: devices must be None, an integer"):
        render_devices(["cpu:0"])


def test_use_cpu_cores_does_not_start_jax():
    """The entry points call `use_cpu_cores()` before `jax.distributed.initialize`, which must come before JAX starts:
    so `use_cpu_cores` asks for the devices without starting JAX (a fresh process: 2 s)."""
    code = ("import jaxfog, jax; from jax._src import xla_bridge as xb; n = jaxfog.use_cpu_cores(3); "
            "print(n, xb.backends_are_initialized(), jax.local_device_count())")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120,
                         env=_env())
    assert out.stdout.split() == ["3", "False", "3"], out.stderr[-2000:]


# ------------------------------------------------------------------------------------------- two processes (slow)
def _env(**extra) -> dict:
    env = {k: v for k, v in os.environ.items() if k != _distributed.ENV_COORDINATOR}
    return {**env, "JAX_PLATFORMS": "cpu", "JAXFOG_CPU_DEVICES": "1", "PYTHONUNBUFFERED": "1", **extra}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _start(args: list[str], **env) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, *args], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=_env(**env))


def _finish(p: subprocess.Popen, timeout: float = 900) -> tuple[int, str, str]:
    """Exit code, stdout (without Gloo's own "[Gloo] Rank i is connected ..." line) and stderr."""
    out, err = p.communicate(timeout=timeout)
    return p.returncode, "".join(x for x in out.splitlines(True) if not x.startswith("[Gloo]")), err


def _launch(port: int, i: int, n: int = 2) -> list[str]:
    return ["--coordinator", f"localhost:{port}", "--num-processes", str(n), "--process-id", str(i)]


API_SCRIPT = r"""
import json, sys
from jaxfog._cli import main
code = main(sys.argv[1:])  # the CLI's render (process 0 writes); the distributed runtime stays up until exit
import jax, jaxfog
sc = jaxfog.load_scene("data_synthetic/scenes/spot_fog.json", ["camera.width=16", "camera.height=16"]).scene
img = jaxfog.render(sc, jax.random.key(5), 6, devices=jax.devices())  # the Python API on the global devices
print(json.dumps({"code": code, "processes": jax.process_count(), "devices": jax.device_count(),
                  "api": img.tolist()}))
"""


# slow tier: three fresh JAX processes compile the renderer at once (90 s on 2 cores with a cold cache)
@pytest.mark.slow
def test_two_processes_render_the_one_process_image(tmp_path):
    """Two processes with one CPU device each render the image of one process with one device (same scene, key and
    spp), up to float32 rounding (each path keeps its random numbers; only the order of the sums differs:
    `assert_same_render_up_to_rounding`), through the CLI and through `render(..., devices=jax.devices())`; only
    process 0 writes and prints the summary, and its header is the one-process header."""
    port, one_exr = _free_port(), tmp_path / "one.exr"
    argv = ["render", str(SPOT_FOG), *TINY]
    procs = [_start(["-c", API_SCRIPT, *argv, "-o", str(tmp_path / f"p{i}.exr"), *_launch(port, i)])
             for i in range(2)]
    one = _start(["-m", "jaxfog", *argv, "-o", str(one_exr)])
    results = [_finish(p) for p in procs]
    code, out, err = _finish(one)
    assert code == 0, err[-3000:]
    for c, o, e in results:
        assert c == 0, e[-3000:]
    (_, out0, _), (_, out1, _) = results
    r0, r1 = (json.loads(o.strip().splitlines()[-1]) for o in (out0, out1))
    assert r0["processes"] == 2 and r0["devices"] == 2 and r0["code"] == r1["code"] == 0
    assert "wrote" in out0 and "on 2 devices of 2 processes" in out0
    assert out1.strip().splitlines() == [out1.strip()]  # process 1 prints only the script's own line
    assert not (tmp_path / "p1.exr").exists()  # process 1 writes nothing
    ref, header_one = jaxfog.read_exr(one_exr)
    img, header = jaxfog.read_exr(tmp_path / "p0.exr")
    assert {k: v for k, v in header.items() if k.startswith("jaxfog:") and k != "jaxfog:scene_file"} == \
        {k: v for k, v in header_one.items() if k.startswith("jaxfog:") and k != "jaxfog:scene_file"}
    assert_same_render_up_to_rounding(ref, img, spp=6, label="two processes (CLI) vs one process")
    for r in (r0, r1):  # each process holds the whole image
        assert_same_render_up_to_rounding(ref, np.asarray(r["api"]), spp=6, label="two processes (API) vs one")
    assert np.array_equal(np.asarray(r0["api"]), np.asarray(r1["api"]))


KILLED_SCRIPT = r"""
import os, signal, sys, time
import numpy as np
import jaxfog
from jaxfog import _distributed as D
jaxfog.use_cpu_cores(1)
port, i, out, marker = sys.argv[1], int(sys.argv[2]), sys.argv[3], sys.argv[4]
D.initialize(D.Launch(f"localhost:{port}", 2, i))
import jax
sc = jaxfog.load_scene("data_synthetic/scenes/spot_fog.json", ["camera.width=16", "camera.height=16"]).scene
np.asarray(jaxfog.render(sc, jax.random.key(1), 2))  # one render together: the processes' Gloo connections are up
if i == 0:
    open(marker, "w").close()  # process 0 has its image: nothing of that render is in flight any more
else:
    t = time.monotonic()
    while not os.path.exists(marker) and time.monotonic() - t < 300:
        time.sleep(0.1)
    os.kill(os.getpid(), signal.SIGKILL)

def second():  # process 0 alone: its sums cannot be added to process 1's
    jaxfog.write_exr(out, np.asarray(jaxfog.render(sc, jax.random.key(2), 2)))
    return 0

sys.exit(D.run_process(second, lambda e: D.report_unexpected(e, "jaxfog")))
"""


# slow tier: four fresh JAX processes compile the renderer (60-120 s on 2 cores), and a heartbeat timeout (30 s)
@pytest.mark.slow
def test_a_failed_process_ends_the_other_and_nothing_is_written(tmp_path):
    """A process that fails ends the other with an error, within a bounded time, and nothing is written:
    - `jaxfog render`'s process 1 fails right after joining (its scene file does not exist: one line, exit 1):
      process 0, loading or compiling, is ended by JAX's coordination service once process 1's heartbeats stop
      (`HEARTBEAT_TIMEOUT_S`; JAX's message "another task died");
    - process 1 is killed after a first render together (once process 0 has that image): process 0's next render
      fails at once in its collective ("another process of the run failed or was stopped", exit 1).
    Neither waits for JAX's 300 s shutdown timeout or forever."""
    bound = _distributed.HEARTBEAT_TIMEOUT_S + 120
    t0 = time.monotonic()
    port, out = _free_port(), tmp_path / "fails.exr"
    fails = [_start(["-m", "jaxfog", "render", str(scene), *TINY, "-o", str(out), *_launch(port, i)])
             for i, scene in enumerate((SPOT_FOG, tmp_path / "missing.json"))]
    port = _free_port()
    marker = tmp_path.parent / f"{tmp_path.name}.first-render-done"
    killed = [_start(["-c", KILLED_SCRIPT, str(port), str(i), str(tmp_path / "killed.exr"), str(marker)])
              for i in range(2)]
    c1, _, e1 = _finish(fails[1], timeout=bound)
    assert c1 == 1 and e1.strip().splitlines()[-1].startswith("jaxfog: error: process 1: "), e1[-2000:]
    assert "missing.json" in e1
    c0, o0, e0 = _finish(fails[0], timeout=max(1.0, bound - (time.monotonic() - t0)))
    assert c0 != 0 and "another task died" in e0, (c0, o0, e0[-3000:])
    assert "wrote" not in o0
    c1, _, _ = _finish(killed[1], timeout=max(1.0, bound - (time.monotonic() - t0)))
    assert c1 == -signal.SIGKILL
    c0, _, e0 = _finish(killed[0], timeout=max(1.0, bound - (time.monotonic() - t0)))
    assert c0 == 1 and "jaxfog: error: process 0: another process of the run failed or was stopped" in e0, \
        (c0, e0[-3000:])
    marker.unlink()
    assert time.monotonic() - t0 < bound
    assert list(tmp_path.iterdir()) == []


# slow tier: a one-process fit and a two-process fit of the same tiny problem at once (2-3 min on 2 cores)
@pytest.mark.slow
def test_two_processes_fit_the_one_process_estimate(tmp_path):
    """`python -m fitting.fit` on two processes (one CPU device each) makes the decisions of one process with two
    devices (no time budget in either, `--budget inf`: the clock must not decide where the two are compared): the
    same rounds and the same estimate (measured: equal to the last bit; allowed: float32 rounding of the renders);
    only process 0 prints and writes RESULT.json and its figures. Then a two-process fit with a short time budget
    (3 s, spent within the first rounds after compiling): process 0's clock decides for both (one broadcast a round),
    so both make the same decisions and end, where processes deciding by their own clocks could stop at different
    passes and wait on each other's collectives."""
    from test_fit import SCENE, TRUTH

    from fitting.params import apply
    from jaxfog._scene_io import scene_from_dict
    import jax

    scene_path, target = tmp_path / "tiny.json", tmp_path / "t.exr"
    scene_path.write_text(json.dumps(SCENE))
    img = jaxfog.render(apply(scene_from_dict(json.loads(json.dumps(SCENE))).scene, TRUTH), jax.random.key(991), 512)
    jaxfog.write_exr(str(target), np.asarray(img), {"jaxfog:spp": "512"})
    args = ["-m", "fitting.fit", str(scene_path), str(target), "--fit", "sigma_t", "g", "--spp", "32",
            "--downscale", "2"]
    port = _free_port()
    procs = [_start([*args, "--budget", "inf", "--out", str(tmp_path / f"p{i}.json"), *_launch(port, i)])
             for i in range(2)]
    one = _start([*args, "--budget", "inf", "--out", str(tmp_path / "one.json")], JAXFOG_CPU_DEVICES="2")
    (c0, o0, e0), (c1, o1, e1), (c, o, e) = (_finish(p) for p in (*procs, one))
    assert c == 0 and c0 == 0 and c1 == 0, (e[-2000:], e0[-2000:], e1[-2000:])
    assert "wrote" in o0 and o1.strip() == ""
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["tiny.json", "t.exr", "one.json", "one.png", "one_convergence.png", "p0.json", "p0.png",
         "p0_convergence.png"])
    a, b = (json.loads((tmp_path / f).read_text()) for f in ("one.json", "p0.json"))
    assert a["success"] and b["success"] and a["rounds"] == b["rounds"]
    for n in ("sigma_t", "g"):
        se = a["uncertainty"][n]["se"]
        assert abs(a["params"][n] - b["params"][n]) <= 1e-3 * se + 1e-5 * abs(a["params"][n]), (n, a["params"],
                                                                                                  b["params"])
    port = _free_port()
    procs = [_start([*args, "--budget", "3", "--out", str(tmp_path / f"budget{i}.json"), *_launch(port, i)])
             for i in range(2)]
    (c0, o0, e0), (c1, o1, e1) = (_finish(p) for p in procs)
    assert c0 == 0 and c1 == 0, (e0[-2000:], e1[-2000:])
    r = json.loads((tmp_path / "budget0.json").read_text())
    assert r["success"] and not (tmp_path / "budget1.json").exists()
