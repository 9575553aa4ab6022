"""Every bad input is refused: one row per kind of bad input, for the render command line, the fit
command line and the Python API. Each row checks the exit code (2 for a usage error, 1 for a bad file) or the
exception, that the one-line message names the file / key / argument and quotes the value and the valid range, and
that the refusal comes before any work: the renderer and the fit are replaced by functions that fail the test if
they are called (except where a row needs a render: the image checks, the fit's brightness check at 4 spp)."""

from __future__ import annotations

import json
import shutil

import jax
import numpy as np
import pytest

import jaxfog
from helpers import SPOT_FOG, spot_fog, spot_fog_dict
from jaxfog import _render
from jaxfog._cli import main as cli_main
from jaxfog._validate import MAX_PIXELS, MAX_SPP, LimitError, _check_render_args, check_seed

TINY = ["--set", "camera.width=4", "--set", "camera.height=4", "--spp", "1", "--no-progress"]


@pytest.fixture
def no_render(monkeypatch):
    """`jaxfog._render.render` fails the test if called (the CLI imports it from there when it runs)."""

    def fail(*args, **kwargs):
        pytest.fail("rendered although the input should have been refused before any work")

    monkeypatch.setattr(_render, "render", fail)


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err
    return err.splitlines()[-1]


# ----------------------------------------------------------------------------------------------- jaxfog render
CLI_ROWS = [
    # (id, extra argv, exit code, substrings of the message)
    ("g rounds to 1 in float32", ["--set", "medium.g=0.99999999"], 1,
     ["spot_fog.json: medium.g: 0.99999999 rounds to 1.0 in float32", "valid range (-1, 1)"]),
    ("g rounds to -1 in float32", ["--set", "medium.g=-0.99999999"], 1,
     ["medium.g: -0.99999999 rounds to -1.0 in float32", "valid range (-1, 1)"]),
    ("sigma_t overflows float32", ["--set", "medium.sigma_t=1e39"], 1,
     ["medium.sigma_t: 1e+39 is not finite in float32", "[0, inf)"]),
    ("intensity overflows float32", ["--set", "lights.0.intensity=1e39"], 1,
     ["lights[0].intensity: 1e+39 is not finite in float32"]),
    ("exposure nan", ["--exposure", "nan"], 2, ["--exposure", "nan", "[-100, 100]"]),
    ("exposure 1e6", ["--exposure", "1e6"], 2, ["--exposure", "1e6", "[-100, 100]"]),
    ("negative seed", ["--seed", "-1"], 2, ["--seed", "-1", "[0, 4294967295]"]),
    ("seed 2^32", ["--seed", "4294967296"], 2, ["--seed", "4294967296", "[0, 4294967295]"]),
    ("seed 10^30", ["--seed", str(10**30)], 2, ["--seed", str(10**30), "[0, 4294967295]"]),
    ("100000 x 100000 camera", ["--set", "camera.width=100000", "--set", "camera.height=100000"], 2,
     ["camera.width 100000 exceeds the limit 16384", "--force"]),
    ("too many pixels", ["--set", "camera.width=8000", "--set", "camera.height=8000"], 2,
     [f"64000000 pixels exceeds the limit {MAX_PIXELS}", "--force"]),
    ("spp 10^12", ["--spp", "1000000000000"], 2, [f"--spp 1000000000000 exceeds the limit {MAX_SPP}", "--force"]),
    ("max_depth 5000", ["--set", "integrator.max_depth=5000"], 2,
     ["integrator.max_depth 5000 exceeds the limit 1024", "--force"]),
    ("estimated work", ["--spp", "1000000"], 2, ["path segments exceeds the limit 1e+11", "--force"]),
]


@pytest.mark.parametrize("argv, code, parts", [r[1:] for r in CLI_ROWS], ids=[r[0] for r in CLI_ROWS])
def test_render_cli_refuses(argv, code, parts, tmp_path, capsys, no_render):
    out = tmp_path / "out.exr"
    assert cli_main(["render", str(SPOT_FOG), "-o", str(out), *argv]) == code
    err = _one_line_error(capsys)
    for part in parts:
        assert part in err, err
    assert not out.exists()


def test_render_cli_refuses_bad_files(tmp_path, capsys, no_render):
    scene = tmp_path / "spot.json"
    shutil.copy(SPOT_FOG, scene)
    # -o naming an existing directory, an unwritable place, the scene itself
    (tmp_path / "d.exr").mkdir()
    assert cli_main(["render", str(scene), "-o", str(tmp_path / "d.exr"), *TINY]) == 1
    assert "d.exr: is a directory" in _one_line_error(capsys)
    assert cli_main(["render", str(scene), "-o", "/proc/x/r.exr", *TINY]) == 1
    assert "-o /proc/x/r.exr: directory /proc/x does not exist" in _one_line_error(capsys)
    assert cli_main(["render", str(scene), "-o", str(tmp_path / "a.exr"), "--png", str(scene), *TINY]) == 1
    assert "--png" in _one_line_error(capsys)
    # a binary file as scene
    binary = tmp_path / "binary.json"
    binary.write_bytes(bytes(range(256)))
    assert cli_main(["render", str(binary), "-o", str(tmp_path / "b.exr"), *TINY]) == 1
    assert "binary.json: not a text file" in _one_line_error(capsys)
    assert json.loads(scene.read_text()) == spot_fog_dict()  # nothing overwritten


def test_render_cli_force_lifts_the_limits(tmp_path, capsys, monkeypatch):
    calls = []

    def fake(scene, key, spp, **kw):
        calls.append(spp)
        return np.zeros((scene.camera.height, scene.camera.width, 3), np.float32)

    monkeypatch.setattr(_render, "render", fake)
    argv = ["render", str(SPOT_FOG), "-o", str(tmp_path / "f.exr"), *TINY, "--spp", str(MAX_SPP + 1)]
    assert cli_main(argv) == 2 and not calls
    assert cli_main([*argv, "--force"]) == 0 and calls == [MAX_SPP + 1]
    monkeypatch.setenv("JAXFOG_NO_LIMITS", "1")
    assert cli_main(argv) == 0


def test_render_cli_non_finite_image_exits_non_zero_and_writes_nothing(tmp_path, capsys, monkeypatch):
    """A render with non-finite pixels exits 1 and says so, and writes nothing: an existing valid image (and PNG)
    at the output path is kept as it was, not replaced by the NaN image."""

    def nan_image(scene, key, spp, **kw):
        img = np.full((scene.camera.height, scene.camera.width, 3), 0.5, np.float32)
        img[1, 2, 0] = np.nan
        img[3, 3, 1] = np.inf
        return img

    monkeypatch.setattr(_render, "render", nan_image)
    out, png = tmp_path / "nan.exr", tmp_path / "nan.png"
    assert cli_main(["render", str(SPOT_FOG), "-o", str(out), "--png", str(png), *TINY]) == 1
    err = _one_line_error(capsys)
    assert f"{out}: 2 of 48 values are not finite (1 NaN, 1 infinite; first at index (1, 2, 0))" in err
    assert "nothing written" in err
    assert not out.exists() and not png.exists()
    good = np.full((4, 4, 3), 0.25, np.float32)
    jaxfog.write_exr(out, good)
    jaxfog.write_png(png, good)
    before = png.read_bytes()
    assert cli_main(["render", str(SPOT_FOG), "-o", str(out), "--png", str(png), *TINY]) == 1
    assert "nothing written; the existing file is unchanged" in _one_line_error(capsys)
    np.testing.assert_array_equal(jaxfog.read_exr(out)[0], good)
    assert png.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["nan.exr", "nan.png"]  # no temp files left


def test_render_cli_mean_pixel_of_a_bright_finite_image(tmp_path, capsys, monkeypatch):
    """A finite image near float32's maximum (irradiance 3e38): the printed mean is computed in float64, not inf."""
    monkeypatch.setattr(_render, "render", lambda scene, key, spp, **kw: np.full(
        (scene.camera.height, scene.camera.width, 3), 3e38, np.float32))
    assert cli_main(["render", str(SPOT_FOG), "-o", str(tmp_path / "b.exr"), *TINY]) == 0
    assert "mean pixel 3e+38" in capsys.readouterr().out


def test_render_cli_refuses_a_read_only_output(tmp_path, capsys, no_render):
    """An existing output without write permission is refused before any work (also for the superuser, whom
    `os.access` lets write anything), and kept."""
    out = tmp_path / "ro.exr"
    jaxfog.write_exr(out, np.full((2, 2, 3), 0.5, np.float32))
    out.chmod(0o444)
    assert cli_main(["render", str(SPOT_FOG), "-o", str(out), *TINY]) == 1
    assert f"-o {out}: the file is read-only" in _one_line_error(capsys)
    np.testing.assert_array_equal(jaxfog.read_exr(out)[0], 0.5)


def test_max_depth_1_renders_the_lights_seen_directly():
    """`integrator.max_depth: 1` (allowed by the schema) renders: only an area light seen directly is visible."""
    for name, visible in (("spot_fog", False), ("area_light", True)):
        sc = jaxfog.load_scene(SPOT_FOG.parent / f"{name}.json",
                               ["camera.width=8", "camera.height=8", "integrator.max_depth=1"]).scene
        img = np.asarray(jaxfog.render(sc, jax.random.key(0), 2))
        assert np.all(np.isfinite(img)) and np.all(img >= 0)
        assert (img.max() > 0) == visible, (name, img.max())


# ------------------------------------------------------------------------------------------------- fitting.fit
@pytest.fixture
def fit_files(tmp_path, monkeypatch):
    """A 16 x 16 spot_fog scene, a plausible constant target and bad targets; `fit_views` fails if called."""
    import fitting.fit

    def fail(*args, **kwargs):
        pytest.fail("fitted although the input should have been refused before the fit")

    monkeypatch.setattr(fitting.fit, "fit_views", fail)
    data = spot_fog_dict()
    data["camera"].update(width=16, height=16)
    data["integrator"]["max_depth"] = 2
    scene = tmp_path / "scene.json"
    scene.write_text(json.dumps(data))
    good = np.full((16, 16, 3), 0.05, np.float32)
    files = {"scene": scene, "good": tmp_path / "good.exr", "zero": tmp_path / "zero.exr",
             "negative": tmp_path / "negative.exr", "nan": tmp_path / "nan.exr", "bright": tmp_path / "bright.exr",
             "png": tmp_path / "png.exr", "dir": tmp_path / "d.json", "tmp": tmp_path}
    jaxfog.write_exr(files["good"], good)
    jaxfog.write_exr(files["zero"], 0 * good)
    jaxfog.write_exr(files["negative"], good - 0.1)
    jaxfog.write_exr(files["nan"], np.where(np.arange(16)[:, None, None] == 3, np.nan, good))
    jaxfog.write_exr(files["bright"], 1000 * good)
    jaxfog.write_png(tmp_path / "p.png", good)
    shutil.copy(tmp_path / "p.png", files["png"])
    files["dir"].mkdir()
    return files


FIT_ROWS = [
    # (id, argv with {names} for the fixture's files, substrings of the message); every row exits 2
    ("init for a parameter not fitted", ["{scene}", "{good}", "--fit", "sigma_t", "g", "--init", "albedo=0.5"],
     ["--init albedo=0.5: not in --fit (sigma_t g)"]),
    ("negative seed", ["{scene}", "{good}", "--seed", "-1"], ["argument --seed: seed -1 is out of range", "[0, 4294967295]"]),
    ("seed 10^30", ["{scene}", "{good}", "--seed", str(10**30)], [f"argument --seed: seed {10**30} is out of range"]),
    ("unwritable --out", ["{scene}", "{good}", "--out", "/proc/x/r.json"],
     ["--out /proc/x/r.json: cannot create directory /proc/x"]),
    ("--out is the scene", ["{scene}", "{good}", "--out", "{scene}"], ["would overwrite the input", "scene.json"]),
    ("--out is a directory", ["{scene}", "{good}", "--out", "{dir}"], ["d.json is a directory"]),
    ("spp beyond the limit", ["{scene}", "{good}", "--spp", "100000000"],
     [f"--spp x 8 (an estimate pass) 800000000 exceeds the limit {MAX_SPP}", "JAXFOG_NO_LIMITS=1"]),
    ("all-zero target", ["{scene}", "{zero}"], ["zero.exr: target is black (every pixel 0)"]),
    ("negative target", ["{scene}", "{negative}"], ["negative.exr: target has 768 negative values", ">= 0"]),
    ("non-finite target", ["{scene}", "{nan}"], ["nan.exr: target: 48 of 768 values are not finite (48 NaN"]),
    ("PNG renamed .exr", ["{scene}", "{png}"], ["png.exr: the file is png, not OpenEXR"]),
]


@pytest.mark.parametrize("argv, parts", [r[1:] for r in FIT_ROWS], ids=[r[0] for r in FIT_ROWS])
def test_fit_cli_refuses(argv, parts, fit_files, capsys):
    from fitting.fit import main as fit_main

    argv = [a.format(**{k: str(v) for k, v in fit_files.items()}) for a in argv]
    if "--out" not in argv:
        argv += ["--out", str(fit_files["tmp"] / "r.json")]
    assert fit_main(argv) == 2
    err = _one_line_error(capsys)
    for part in parts:
        assert part in err, err
    assert not (fit_files["tmp"] / "r.json").exists()


def test_fit_cli_refuses_a_target_brighter_than_the_searched_region_renders(fit_files, capsys, monkeypatch):
    """A target 1000x too bright: refused after the global search (which renders the whole searched box) and before
    any local solve, with the box in the message; nothing written."""
    import fitting.solver
    from fitting.fit import main as fit_main

    def fail(*args, **kwargs):
        pytest.fail("a local solve ran although the search should have refused the target")

    import fitting.fit

    monkeypatch.setattr(fitting.fit, "fit_views", fitting.solver.fit_views)   # the fixture's guard, lifted: the
    monkeypatch.setitem(fitting.solver.ROUNDS, "approach", fail)              # search runs, no local solve may
    out = fit_files["tmp"] / "r.json"
    assert fit_main([str(fit_files["scene"]), str(fit_files["bright"]), "--spp", "16", "--out", str(out)]) == 2
    err = _one_line_error(capsys)
    assert "bright.exr: the target is" in err and "as bright as the renders of the whole searched region" in err
    assert "sigma_t" in err
    assert not out.exists()


def test_fit_result_json_has_no_nan_tokens(tmp_path):
    """An unknown uncertainty (NaN) or an infinite ratio: RESULT.json stays valid JSON, with null there."""
    from fitting.fit import write_json_atomic

    path = tmp_path / "r.json"
    write_json_atomic(str(path), {"se": float("nan"), "chi2": [1.0, float("inf")], "x": np.float32(0.5)})
    text = path.read_text()
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == {"se": None, "chi2": [1.0, None], "x": 0.5}


# -------------------------------------------------------------------------------------------------- Python API
SCENE = spot_fog(width=4, height=4, max_depth=2)
KEY = jax.random.key(0)


def _render_kwargs(**kw):
    base = dict(sampling=jaxfog.SamplingOptions(), proposal=None, batch_paths=1 << 16, chunk_paths=1024, devices=None,
                progress=None)
    return {**base, **kw}


API_ROWS = [
    # (id, call, exception, substrings of the message)
    ("spp=True", lambda: jaxfog.render(SCENE, KEY, True), TypeError, ["spp must be a positive integer", "bool True"]),
    ("spp=0", lambda: jaxfog.render(SCENE, KEY, 0), ValueError, ["spp must be a positive integer (>= 1), got 0"]),
    ("int key", lambda: jaxfog.render(SCENE, 0, 2), TypeError, ["key: got int 0", "jax.random.key(seed)"]),
    ("key array of shape (2,)", lambda: jaxfog.render(SCENE, jax.random.split(KEY), 2), ValueError,
     ["key: got a key array of shape (2,)", "jax.random.key(seed)"]),
    ("uint32 array of shape (3,)", lambda: jaxfog.render(SCENE, np.zeros(3, np.uint32), 2), TypeError,
     ["key: got ndarray of shape (3,) and dtype uint32", "legacy jax.random.PRNGKey(seed) (uint32, shape (2,))"]),
    ("proposal=0.5", lambda: jaxfog.render(SCENE, KEY, 2, estimator="proposal", proposal=0.5), TypeError,
     ["proposal must be None or a jaxfog.HomogeneousMedium", "float 0.5"]),
    ("proposal estimator without proposal", lambda: jaxfog.render(SCENE, KEY, 2, estimator="proposal"), ValueError,
     ['estimator="proposal" needs proposal=']),
    ("SceneFile instead of .scene", lambda: jaxfog.render(jaxfog.load_scene(SPOT_FOG), KEY, 2), TypeError,
     ["got a SceneFile", "pass its .scene"]),
    ("not a scene", lambda: jaxfog.render({"camera": 1}, KEY, 2), TypeError, ["scene must be a jaxfog.Scene", "dict"]),
    ("light_lobe nan", lambda: jaxfog.render(SCENE, KEY, 2, light_lobe=float("nan")), ValueError,
     ["light_lobe must be in [0, 1), got nan"]),
    ("estimator typo", lambda: jaxfog.render(SCENE, KEY, 2, estimator="detach"), ValueError,
     ["estimator must be one of", "'detach'"]),
    ("progress not callable", lambda: jaxfog.render(SCENE, KEY, 2, progress=True), TypeError, ["progress must be"]),
    ("Camera(width=0)", lambda: jaxfog.Camera(origin=(0, 0, 1), target=(0, 0, 0), up=(0, 1, 0), fov=40, width=0,
                                              height=4), ValueError, ["Camera: width must be a positive integer", "0"]),
    ("Camera(height=2.5)", lambda: jaxfog.Camera(origin=(0, 0, 1), target=(0, 0, 0), up=(0, 1, 0), fov=40, width=4,
                                                 height=2.5), ValueError, ["Camera: height", "2.5"]),
    ("100000 x 100000 camera", lambda: jaxfog.render(spot_fog(width=100000, height=100000), KEY, 1), LimitError,
     ["scene.camera.width 100000 exceeds the limit 16384", "JAXFOG_NO_LIMITS=1"]),
    ("spp beyond the limit", lambda: jaxfog.render(SCENE, KEY, MAX_SPP + 1), LimitError,
     [f"spp {MAX_SPP + 1} exceeds the limit {MAX_SPP}"]),
    ("seed out of range", lambda: check_seed(-1), ValueError, ["seed -1 is out of range; valid range [0, 4294967295]"]),
    ("non-finite image", lambda: jaxfog.check_finite(np.array([1.0, np.nan]), what="img"), FloatingPointError,
     ["img: 1 of 2 values are not finite (1 NaN, 0 infinite; first at index (1,))"]),
]


@pytest.mark.parametrize("call, exc, parts", [r[1:] for r in API_ROWS], ids=[r[0] for r in API_ROWS])
def test_python_api_refuses(call, exc, parts, no_render):
    # `no_render` replaces the module attribute only; `jaxfog.render` is the real function, whose checks run first
    with pytest.raises(exc) as info:
        call()
    for part in parts:
        assert part in str(info.value), str(info.value)


def test_render_accepts_legacy_and_typed_keys():
    _check_render_args(SCENE, jax.random.PRNGKey(0), 1, **_render_kwargs())  # legacy uint32 (2,)
    _check_render_args(SCENE, KEY, np.int64(3), **_render_kwargs())  # numpy integer spp
    assert check_seed(4294967295) == 4294967295 and check_seed(0) == 0


def test_read_exr_refuses_a_png_renamed_exr(tmp_path):
    jaxfog.write_png(tmp_path / "p.png", np.full((2, 3, 3), 0.5, np.float32))
    shutil.copy(tmp_path / "p.png", tmp_path / "p.exr")
    with pytest.raises(ValueError, match=r"p\.exr: the file is png, not OpenEXR"):
        jaxfog.read_exr(tmp_path / "p.exr")


def test_load_scene_refuses_a_binary_file(tmp_path):
    path = tmp_path / "bin.json"
    path.write_bytes(b"\x89PNG\r\n\x1a\n\x00")
    with pytest.raises(jaxfog.SceneError, match=r"bin\.json: not a text file \(byte 0x89 at offset 0"):
        jaxfog.load_scene(path)


def test_use_cpu_cores_warns_when_too_late():
    """Under pytest JAX has started (conftest): asking for another device count warns; the same count does not."""
    import warnings

    n = jax.local_device_count()
    with pytest.warns(RuntimeWarning, match=rf"use_cpu_cores\({n + 1}\): JAX has already started with {n} device"):
        assert jaxfog.use_cpu_cores(n + 1) == n
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert jaxfog.use_cpu_cores(n) == n


# ---------------------------------------------------------------------------------------------- Module validation
MODULE_ROWS = [("g = 1", dict(g=1.0)), ("g = 1.5", dict(g=1.5)), ("sigma_t = -1", dict(sigma_t=-1.0)),
               ("albedo = 2", dict(albedo=2.0))]


@pytest.mark.parametrize("values", [r[1] for r in MODULE_ROWS], ids=[r[0] for r in MODULE_ROWS])
def test_replace_medium_refuses_invalid_values(values):
    with pytest.raises(ValueError, match="|".join(values)):
        SCENE.replace_medium(**values)


def test_henyey_greenstein_refuses_g_1():
    with pytest.raises(ValueError, match="g"):
        jaxfog.HenyeyGreenstein(1.0)
