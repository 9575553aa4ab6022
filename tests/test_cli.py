"""The `jaxfog` command line: render writes EXR + PNG with header metadata; `--set` works and is validated; bad
input gives a one-line message and a non-zero exit; `python -m jaxfog --help` works. Renders: 8x8, 2 spp (one compile)."""

from __future__ import annotations

import json
import pathlib
import subprocess
import sys

import numpy as np
import OpenImageIO as oiio

from jaxfog import read_exr
from jaxfog._cli import main

SCENES = pathlib.Path(__file__).resolve().parents[1] / "data_synthetic" / "scenes"
SPOT_FOG = str(SCENES / "spot_fog.json")
TINY = ["--set", "camera.width=8", "--set", "camera.height=8", "--spp", "2", "--no-progress"]


def test_render_writes_exr_and_png_with_metadata(tmp_path, capsys):
    exr, png = tmp_path / "out.exr", tmp_path / "out.png"
    code = main(["render", SPOT_FOG, "-o", str(exr), "--png", str(png), "--exposure", "2", "--seed", "3",
                 *TINY, "--set", "medium.sigma_t=0.8"])
    out = capsys.readouterr().out
    assert code == 0
    rgb, header = read_exr(exr)
    assert rgb.shape == (8, 8, 3) and np.all(np.isfinite(rgb)) and rgb.mean() > 0
    assert header["jaxfog:scene"] == "spot_fog" and header["jaxfog:spp"] == "2" and header["jaxfog:seed"] == "3"
    assert header["jaxfog:estimator"] == "detached"
    assert json.loads(header["jaxfog:medium"]) == {"type": "homogeneous", "sigma_t": 0.8, "albedo": 0.9, "g": 0.6,
                                                     "extent": 1000.0}
    assert json.loads(header["jaxfog:overrides"])[-1] == "medium.sigma_t=0.8"
    assert json.loads(header["jaxfog:scene_json"])["camera"]["width"] == 8
    inp = oiio.ImageInput.open(str(png))
    assert (inp.spec().width, inp.spec().height, inp.spec().nchannels) == (8, 8, 3)
    inp.close()
    assert "compile" in out and "wall" in out and str(exr) in out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.exr", "out.png"]


def test_same_seed_same_image_and_set_changes_it(tmp_path):
    paths = {name: tmp_path / f"{name}.exr" for name in ("a", "b", "c", "d")}
    assert main(["render", SPOT_FOG, "-o", str(paths["a"]), "--seed", "1", *TINY]) == 0
    assert main(["render", SPOT_FOG, "-o", str(paths["b"]), "--seed", "1", *TINY]) == 0
    assert main(["render", SPOT_FOG, "-o", str(paths["c"]), "--seed", "2", *TINY]) == 0
    assert main(["render", SPOT_FOG, "-o", str(paths["d"]), "--seed", "1", *TINY, "--set", "lights.0.intensity=0"]) == 0
    a, b, c, d = (read_exr(p)[0] for p in paths.values())
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert np.all(d == 0)  # the only light switched off by --set


def _fails(argv, capsys, code=1):
    assert main(argv) == code
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err


def test_set_is_validated(tmp_path, capsys):
    out = tmp_path / "out.exr"
    err = _fails(["render", SPOT_FOG, "-o", str(out), *TINY, "--set", "medium.g=2"], capsys)
    assert err.strip() == "jaxfog: error: spot_fog.json: medium.g: 2 is out of range; valid range (-1, 1)"
    err = _fails(["render", SPOT_FOG, "-o", str(out), *TINY, "--set", "medium.sigmat=1"], capsys)
    assert "medium.sigmat: does not exist" in err and len(err.strip().splitlines()) == 1
    err = _fails(["render", SPOT_FOG, "-o", str(out), *TINY, "--set", "medium.g"], capsys)
    assert "expected KEY.PATH=VALUE" in err
    assert not out.exists()


def test_bad_scene_file_gives_one_line_message(tmp_path, capsys):
    data = json.loads(pathlib.Path(SPOT_FOG).read_text())
    data["lights"][0]["beam_width"] = 25
    bad = tmp_path / "bad_spot.json"
    bad.write_text(json.dumps(data))
    err = _fails(["render", str(bad), "-o", str(tmp_path / "out.exr"), *TINY], capsys)
    assert err.strip() == ("jaxfog: error: bad_spot.json: lights[0].beam_width: 25 is larger than cutoff_angle 20; "
                           "valid range (0, cutoff_angle]")
    err = _fails(["render", str(tmp_path / "nothere.json"), "-o", str(tmp_path / "out.exr")], capsys)
    assert "scene file not found" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad_spot.json"]


def test_bad_arguments(tmp_path, capsys):
    out = str(tmp_path / "out.exr")
    assert "--spp" in _fails(["render", SPOT_FOG, "-o", out, "--spp", "0"], capsys, code=2)
    assert "-o" in _fails(["render", SPOT_FOG], capsys, code=2)
    assert "invalid choice" in _fails(["render", SPOT_FOG, "-o", out, "--estimator", "magic"], capsys, code=2)
    assert "COMMAND" in _fails([], capsys, code=2)
    err = _fails(["render", SPOT_FOG, "-o", str(tmp_path / "no" / "out.exr")], capsys)
    assert "does not exist" in err
    err = _fails(["render", SPOT_FOG, "-o", str(tmp_path / "out.png")], capsys)
    assert "expected a .exr file name" in err


def test_python_dash_m_help():
    proc = subprocess.run([sys.executable, "-m", "jaxfog", "--help"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "usage: jaxfog" in proc.stdout and "render" in proc.stdout


def test_render_help(capsys):
    assert main(["render", "--help"]) == 0
    out = capsys.readouterr().out
    assert "usage: jaxfog render" in out and "--set KEY=VALUE" in out and "--exposure" in out
