"""Image files: linear float32 OpenEXR (the data), sRGB 8-bit PNG (a tonemapped preview only; docs/conventions.md).

Every write is atomic: the image goes to a temp file in the destination's directory (`.NAME.tmp-<pid>.exr`, the real
extension last so OpenImageIO picks the format) and is `os.replace`d onto the destination; on any error the temp file
is removed, so a reader never sees a half-written image and a failed write leaves nothing behind.
"""

from __future__ import annotations

import json
import os
from typing import Callable

import numpy as np
import OpenImageIO as oiio

__all__ = ["write_exr", "read_exr", "write_png", "srgb_oetf"]


def _as_rgb(rgb, what: str = "rgb") -> np.ndarray:
    """`rgb` as a C-contiguous float32 `(H, W, 3)` array, or a ValueError naming the shape it has."""
    a = np.asarray(rgb, dtype=np.float32)
    if a.ndim != 3 or a.shape[2] != 3 or a.shape[0] < 1 or a.shape[1] < 1:
        raise ValueError(f"{what} must be an (H, W, 3) RGB image, got shape {a.shape}")
    return np.ascontiguousarray(a)


def _metadata_text(value) -> str:
    """Header attribute text: strings as they are, anything else as JSON."""
    return value if isinstance(value, str) else json.dumps(value)


def _atomic_write(path, write: Callable[[str], None]) -> None:
    """Call `write(temp_path)` and move the result onto `path`; remove the temp file on any error."""
    path = os.fspath(path)
    directory, name = os.path.split(os.path.abspath(path))
    if not os.path.isdir(directory):
        raise FileNotFoundError(f"{path}: directory {directory} does not exist")
    stem, ext = os.path.splitext(name)
    tmp = os.path.join(directory, f".{stem}.tmp-{os.getpid()}{ext}")
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.remove(tmp)
        except FileNotFoundError:
            pass
        raise


def _write_oiio(tmp: str, pixels: np.ndarray, spec: "oiio.ImageSpec", dest: str) -> None:
    out = oiio.ImageOutput.create(tmp)
    if out is None:
        raise OSError(f"{dest}: no image writer for this file type: {oiio.geterror()}")
    try:
        if not out.open(tmp, spec):
            raise OSError(f"{dest}: cannot write image: {out.geterror()}")
        if not out.write_image(pixels):
            raise OSError(f"{dest}: cannot write image: {out.geterror()}")
    finally:
        out.close()


def write_exr(path, rgb, metadata: dict | None = None) -> None:
    """Write a linear RGB image as a 32-bit float OpenEXR, atomically.

    **Arguments:** `path` (`.exr`); `rgb`: `(H, W, 3)` array of linear radiance (any float type; stored as float32);
    `metadata`: header attributes, e.g. `{"jaxfog:scene": "spot_fog", "jaxfog:spp": 64}`; string values are
    stored as they are, other values as JSON text. **Raises:** `ValueError` for a wrong shape, `FileNotFoundError`
    when the directory does not exist, `OSError` when the write fails.
    """
    pixels = _as_rgb(rgb)
    spec = oiio.ImageSpec(pixels.shape[1], pixels.shape[0], 3, oiio.FLOAT)
    spec.channelnames = ("R", "G", "B")
    spec.attribute("compression", "zip")
    for key, value in (metadata or {}).items():
        spec.attribute(str(key), _metadata_text(value))
    _atomic_write(path, lambda tmp: _write_oiio(tmp, pixels, spec, os.fspath(path)))


def read_exr(path) -> tuple[np.ndarray, dict]:
    """Read an RGB OpenEXR image (normally one written by `write_exr`); any other format is refused, whatever the
    file's name.

    **Returns:** `(rgb, metadata)`: float32 `(H, W, 3)` linear RGB (channels R, G, B by name; an alpha channel is
    dropped) and a dict of every *string* header attribute (what `write_exr` stored, plus the file's own string
    attributes such as `compression`). **Raises:** `FileNotFoundError`, or `ValueError` for a file that is not an
    RGB OpenEXR image (by its content, e.g. a PNG named `.exr`).
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: image file not found")
    inp = oiio.ImageInput.open(path)
    if inp is None:
        raise ValueError(f"{path}: not a readable image: {oiio.geterror()}")
    try:
        fmt = inp.format_name()
        if fmt != "openexr":  # OpenImageIO reads by content: a PNG renamed .exr would be read as 8-bit sRGB data
            raise ValueError(f"{path}: the file is {fmt or 'unknown format'}, not OpenEXR; expected a linear float "
                             f"OpenEXR image (PNG and other 8-bit formats are tonemapped previews, not data)")
        spec = inp.spec()
        names = list(spec.channelnames)
        if not all(c in names for c in "RGB"):
            raise ValueError(f"{path}: not an RGB image (channels {', '.join(names) or 'none'}; expected R, G, B)")
        pixels = inp.read_image(oiio.FLOAT)
        if pixels is None:
            raise ValueError(f"{path}: cannot read pixels: {inp.geterror()}")
        metadata = {a.name: a.value for a in spec.extra_attribs if isinstance(a.value, str)}
    finally:
        inp.close()
    pixels = np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
    rgb = pixels[:, :, [names.index(c) for c in "RGB"]]
    return np.ascontiguousarray(rgb), metadata


def srgb_oetf(linear: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1) for linear values clipped to [0, 1]: `12.92 x` below 0.0031308,
    `1.055 x^(1/2.4) - 0.055` above. NaN maps to 0."""
    x = np.clip(np.nan_to_num(linear, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def write_png(path, rgb, exposure: float = 0.0) -> None:
    """Write a tonemapped 8-bit sRGB preview, atomically: `rgb * 2**exposure`, clipped to [0, 1], sRGB-encoded.

    A preview only (docs/conventions.md): data go to `write_exr`. **Raises** as `write_exr`.
    """
    pixels = _as_rgb(rgb)
    encoded = srgb_oetf(pixels * np.float32(2.0 ** float(exposure)))
    rgb8 = np.ascontiguousarray(np.round(encoded * 255.0).astype(np.uint8))
    spec = oiio.ImageSpec(rgb8.shape[1], rgb8.shape[0], 3, oiio.UINT8)
    spec.channelnames = ("R", "G", "B")
    spec.attribute("oiio:ColorSpace", "sRGB")
    _atomic_write(path, lambda tmp: _write_oiio(tmp, rgb8, spec, os.fspath(path)))
