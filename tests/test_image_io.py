"""Image I/O: EXR round trip with header metadata, atomic writes that leave nothing behind on failure, PNG preview."""

from __future__ import annotations

import json

import numpy as np
import OpenImageIO as oiio
import pytest

from jaxfog import read_exr, write_exr, write_png
from jaxfog import _image


def _image_data(h=5, w=7, seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    rgb = rng.lognormal(-2.0, 2.0, size=(h, w, 3)).astype(np.float32)  # HDR: tiny to large values
    rgb[0, 0] = [0.0, 1e-30, 1e4]
    return rgb


def test_exr_round_trip_with_metadata(tmp_path):
    rgb = _image_data()
    medium = {"sigma_t": 0.5, "albedo": 0.9, "g": 0.6}
    meta = {"jaxfog:scene": "spot_fog", "jaxfog:spp": 64, "jaxfog:seed": "3", "jaxfog:medium": medium}
    path = tmp_path / "out.exr"
    write_exr(path, rgb, meta)
    back, header = read_exr(path)
    assert back.dtype == np.float32 and back.shape == (5, 7, 3)
    np.testing.assert_array_equal(back, rgb)  # float32, lossless
    assert header["jaxfog:scene"] == "spot_fog"
    assert header["jaxfog:spp"] == "64" and header["jaxfog:seed"] == "3"  # non-strings are stored as JSON
    assert json.loads(header["jaxfog:medium"]) == medium
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.exr"]  # no temp file left
    assert oiio.ImageInput.open(str(path)).format_name() == "openexr"


def test_exr_accepts_float64_and_overwrites(tmp_path):
    path = tmp_path / "out.exr"
    write_exr(path, np.zeros((2, 3, 3)), {})
    write_exr(path, np.full((2, 3, 3), 0.25, np.float64), {"k": "v"})
    back, header = read_exr(path)
    np.testing.assert_array_equal(back, np.full((2, 3, 3), 0.25, np.float32))
    assert header["k"] == "v"


def test_write_into_missing_directory_leaves_nothing(tmp_path):
    target = tmp_path / "missing" / "out.exr"
    with pytest.raises(FileNotFoundError, match="does not exist"):
        write_exr(target, _image_data(), {})
    with pytest.raises(FileNotFoundError, match="does not exist"):
        write_png(tmp_path / "missing" / "out.png", _image_data())
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("shape", [(4, 5), (4, 5, 4), (4, 5, 1), (0, 5, 3), (2, 4, 5, 3)])
def test_wrong_shape_is_rejected_and_leaves_nothing(tmp_path, shape):
    with pytest.raises(ValueError, match=r"must be an \(H, W, 3\) RGB image, got shape"):
        write_exr(tmp_path / "out.exr", np.zeros(shape, np.float32), {})
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        write_png(tmp_path / "out.png", np.zeros(shape, np.float32))
    assert list(tmp_path.iterdir()) == []


def test_failed_write_removes_temp_file_and_keeps_old_image(tmp_path, monkeypatch):
    path = tmp_path / "out.exr"
    old = _image_data(seed=1)
    write_exr(path, old, {"jaxfog:scene": "old"})
    seen = []

    def failing(tmp, pixels, spec, dest):
        seen.append(tmp)
        with open(tmp, "wb") as fh:  # a half-written file...
            fh.write(b"partial")
        raise OSError("disk full")  # ...then the failure

    monkeypatch.setattr(_image, "_write_oiio", failing)
    with pytest.raises(OSError, match="disk full"):
        write_exr(path, _image_data(seed=2), {"jaxfog:scene": "new"})
    assert seen and seen[0].endswith(".exr") and ".out.tmp-" in seen[0]  # real extension last, same directory
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.exr"]
    back, header = read_exr(path)
    np.testing.assert_array_equal(back, old)
    assert header["jaxfog:scene"] == "old"


def test_read_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="image file not found"):
        read_exr(tmp_path / "nothere.exr")
    gray = tmp_path / "gray.exr"
    out = oiio.ImageOutput.create(str(gray))
    out.open(str(gray), oiio.ImageSpec(4, 3, 1, oiio.FLOAT))
    out.write_image(np.zeros((3, 4, 1), np.float32))
    out.close()
    with pytest.raises(ValueError, match=r"not an RGB image \(channels Y"):
        read_exr(gray)
    junk = tmp_path / "junk.exr"
    junk.write_bytes(b"not an image at all")
    with pytest.raises(ValueError, match="not a readable image"):
        read_exr(junk)


def test_png_is_srgb_8bit_with_exposure(tmp_path):
    lin = np.array([[[0.0, 0.5, 1.0], [0.0031308, 0.25, 2.0]]], np.float32)  # (1, 2, 3)
    path = tmp_path / "preview.png"
    write_png(path, lin)
    inp = oiio.ImageInput.open(str(path))
    assert inp.format_name() == "png" and inp.spec().format == oiio.TypeDesc("uint8")
    px = inp.read_image(oiio.UINT8).reshape(1, 2, 3)
    inp.close()
    # sRGB OETF: 0.5 -> 0.7354 -> 188; 0.0031308 -> 0.04045 -> 10; 0.25 -> 0.5371 -> 137; >= 1 clips to 255
    np.testing.assert_array_equal(px, [[[0, 188, 255], [10, 137, 255]]])
    write_png(path, lin * 0.5, exposure=1.0)  # one stop up undoes halving
    inp = oiio.ImageInput.open(str(path))
    np.testing.assert_array_equal(inp.read_image(oiio.UINT8).reshape(1, 2, 3), px)
    inp.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["preview.png"]


def test_png_handles_non_finite(tmp_path):
    path = tmp_path / "p.png"
    write_png(path, np.array([[[np.nan, np.inf, -1.0]]], np.float32))
    inp = oiio.ImageInput.open(str(path))
    np.testing.assert_array_equal(inp.read_image(oiio.UINT8).reshape(3), [0, 255, 0])
    inp.close()
