"""Density-grid files: Mitsuba's binary `.vol` format (read and write) and numpy `.npy` arrays, validated.

A grid is a float32 numpy array of shape `(nz, ny, nx, c)`: `c = 1` (grey extinction) or `c = 3` (RGB extinction),
one value per texel, each finite and >= 0 (a density; the medium multiplies it by its `scale`, 1/scene unit). Its
axis-aligned box `(box_min, box_max)` (scene units, float64 `(3,)` each) is where the grid lies: texel `(x, y, z)`
has its centre at `box_min + ((x, y, z) + 0.5) / (nx, ny, nz) * (box_max - box_min)`.

The `.vol` format (Mitsuba 3: src/render/volumegrid.cpp `VolumeGrid::read` / `write`, documented in
src/volumes/grid.cpp), little-endian, 48 bytes of header then the data:

| bytes  | content                                                                                   |
|--------|-------------------------------------------------------------------------------------------|
| 0-2    | ASCII `V`, `O`, `L`                                                                       |
| 3      | version, uint8: 3 (the only version Mitsuba 3 reads)                                      |
| 4-7    | encoding, int32: 1 = float32 (the only encoding Mitsuba 3 reads)                          |
| 8-19   | xres, yres, zres, int32 each                                                              |
| 20-23  | channels, int32 (Mitsuba: 1, 3 or 6; here 1 or 3)                                         |
| 24-47  | bounding box, 6 float32: xmin, ymin, zmin, xmax, ymax, zmax                               |
| 48-    | xres * yres * zres * channels float32, x fastest: `data[((z * yres + y) * xres + x) * channels + c]` |

so the data read as a C-order array has shape `(zres, yres, xres, channels)`: this module's grid as it is.

Mitsuba 3's `gridvolume` ignores the file's bounding box unless `use_grid_bbox` is true: by default its grid spans
the unit cube `[0, 1]^3` mapped by the plugin's `to_world` (src/volumes/grid.cpp: `if (props.get<bool>
("use_grid_bbox", false)) m_to_local = m_volume_grid->bbox_transform() * m_to_local;`; so in Mitsuba 3.9.1: a
gridvolume of a file with box [10, 20]^3 has `bbox()` [0, 1]^3 unless `use_grid_bbox` is set). Here the file's box
is the grid's box unless the caller gives one (`load_grid(path, bounds)`); the `grid` medium's Mitsuba export
passes that box as `to_world`.

Every refusal is one line naming the file, the problem, the value and the valid range: a `GridFileError` (a
`ValueError`), or, when the caller passes `context` (e.g. the scene file and key), a `SceneError` whose message
starts with that context, as the scene loader reports a bad mesh file.
"""

from __future__ import annotations

import os
import struct
from typing import NamedTuple

import numpy as np

__all__ = ["GridFileError", "read_vol", "write_vol", "vol_bytes", "load_grid", "validate_grid", "validate_bounds",
           "VOL_HEADER_BYTES", "MAX_GRID_VALUES", "GRID_CHANNELS"]

VOL_MAGIC = b"VOL"
VOL_VERSION = 3
VOL_FLOAT32 = 1
_HEADER = struct.Struct("<3sBiiiii6f")
VOL_HEADER_BYTES = _HEADER.size
"""Bytes before the data of a `.vol` file (48)."""

MAX_GRID_VALUES = 2**31
"""Most values (`nx * ny * nz * channels`) a grid may hold (8 GiB of float32); a resolution past it is refused before
anything is allocated (Mitsuba's `gridvolume` counts texels in 32 bits)."""

GRID_CHANNELS = (1, 3)
"""Channel counts accepted: 1 (grey extinction) or 3 (RGB extinction)."""

_CHANNELS_VALID = "expected 1 (grey extinction) or 3 (RGB extinction)"


class GridFileError(ValueError):
    """A grid file (or grid array, or its bounds) is missing, unreadable or invalid; the message names the file."""


class _Header(NamedTuple):
    """A `.vol` header: resolution (x, y, z), channels, bounding box (float64 (3,) corners)."""

    res: tuple[int, int, int]  # (x, y, z)
    channels: int
    box: tuple[np.ndarray, np.ndarray]  # float64 (3,) each


def _raise(err: GridFileError, context: str | None):
    """Raise `err`, or the `SceneError` `"{context}: {err}"` when a context is given."""
    if context is None:
        raise err
    from ._scene_io import SceneError

    raise SceneError(f"{context}: {err}") from None


def _fmt(v) -> str:
    text = repr(float(v))
    return text[:-2] if text.endswith(".0") else text


def _vec_text(v) -> str:
    return "[" + ", ".join(_fmt(x) for x in np.asarray(v, np.float64).reshape(-1)) + "]"


# ------------------------------------------------------------------------------------------------ validation
def _check_resolution(res_xyz, channels: int, where: str) -> None:
    """Each of x, y, z >= 1, channels 1 or 3, and at most MAX_GRID_VALUES values."""
    x, y, z = (int(r) for r in res_xyz)
    if min(x, y, z) < 1:
        raise GridFileError(f"{where}: resolution (x, y, z) = ({x}, {y}, {z}); expected each >= 1")
    if channels not in GRID_CHANNELS:
        raise GridFileError(f"{where}: {channels} channels; {_CHANNELS_VALID}")
    n = x * y * z * channels  # Python ints: no overflow
    if n > MAX_GRID_VALUES:
        raise GridFileError(f"{where}: resolution (x, y, z) = ({x}, {y}, {z}) with {channels} channel(s) is {n} "
                            f"values; expected at most 2**31 = {MAX_GRID_VALUES}")


def validate_bounds(bounds, where: str = "<grid>") -> tuple[np.ndarray, np.ndarray]:
    """The box `bounds` as `(box_min, box_max)`, float64 `(3,)` each (scene units).

    **Arguments:** `bounds`: a pair `(box_min, box_max)` of 3 numbers each, or a mapping `{"min": ..., "max": ...}`
    (the scene file's form); `where`: the name in the message. **Raises:** `GridFileError` unless both corners
    are finite, `box_min < box_max` on every axis, and both stay so when stored as float32 (as a `.vol` file does)."""
    try:
        lo, hi = (bounds["min"], bounds["max"]) if isinstance(bounds, dict) else bounds
        lo, hi = np.asarray(lo, np.float64).reshape(3), np.asarray(hi, np.float64).reshape(3)
    except (TypeError, ValueError, KeyError):
        raise GridFileError(f"{where}: bounds {bounds!r}: expected (box_min, box_max), 3 numbers each") from None
    lo32, hi32 = lo.astype(np.float32), hi.astype(np.float32)
    if not (np.all(np.isfinite(lo32)) and np.all(np.isfinite(hi32))):
        raise GridFileError(f"{where}: bounding box min {_vec_text(lo)} max {_vec_text(hi)} is not finite (in "
                            f"float32); expected finite corners with min < max on every axis")
    if not np.all(lo32 < hi32):
        axis = "xyz"[int(np.argmax(~(lo32 < hi32)))]
        raise GridFileError(f"{where}: bounding box min {_vec_text(lo)} max {_vec_text(hi)} has min >= max along "
                            f"{axis}; expected min < max on every axis")
    return lo, hi


def validate_grid(grid, where: str = "<grid>") -> np.ndarray:
    """The grid as a C-contiguous float32 `(nz, ny, nx, c)` array.

    **Arguments:** `grid`: a numeric array `(nz, ny, nx)` (one channel) or `(nz, ny, nx, c)`, c 1 or 3 (any real
    integer or float dtype; bool, complex and object arrays are refused); `where`: the name in the message.
    **Raises:** `GridFileError` for a wrong shape or dtype, a resolution < 1, more than `MAX_GRID_VALUES` values, or
    values that are not finite (as float32) or negative (saying how many and the first index)."""
    a = np.asarray(grid)
    if a.dtype == bool or a.dtype.kind not in "iuf":
        raise GridFileError(f"{where}: array of dtype {a.dtype}; expected real numbers (an integer or float dtype)")
    if a.ndim == 3:
        a = a[..., None]
    if a.ndim != 4:
        raise GridFileError(f"{where}: array of shape {a.shape} (ndim {a.ndim}); expected (nz, ny, nx) or "
                            f"(nz, ny, nx, c) with c 1 or 3")
    if a.shape[3] not in GRID_CHANNELS:
        raise GridFileError(f"{where}: array of shape {a.shape}: {a.shape[3]} channels; {_CHANNELS_VALID}")
    _check_resolution(a.shape[2::-1], a.shape[3], where)
    with np.errstate(over="ignore"):  # a value beyond float32's range becomes inf, refused below
        a = np.ascontiguousarray(a, dtype=np.float32)
    _check_values(a, where)
    return a


def _check_values(a: np.ndarray, where: str) -> None:
    """Every value finite and >= 0: otherwise how many are not and the first (C order) index (z, y, x, channel)."""
    for test, what, valid in ((lambda: ~np.isfinite(a), "not finite", "finite values"),
                              (lambda: a < 0, "negative", "densities >= 0")):
        bad = test()  # negative is tested once all are finite
        if bad.any():
            i = tuple(int(k) for k in np.unravel_index(int(np.argmax(bad)), a.shape))
            raise GridFileError(f"{where}: {int(bad.sum())} of {a.size} values are {what} (first: grid[z, y, x, "
                                f"channel] = grid{list(i)} = {float(a[i])!r}); expected {valid}")


# ---------------------------------------------------------------------------------------------------- .vol
def _unreadable(path: str, e: OSError, kind: str) -> GridFileError:
    """The one-line error for a grid file that cannot be opened or read (`kind`: ".vol" or ".npy")."""
    if isinstance(e, FileNotFoundError):
        return GridFileError(f"{path}: grid file not found")
    if isinstance(e, IsADirectoryError):
        return GridFileError(f"{path}: is a directory; expected a {kind} grid file")
    return GridFileError(f"{path}: cannot read grid file: {e.strerror or e}")


def _read_header(raw: bytes, path: str) -> _Header:
    if raw[:3] != VOL_MAGIC[:len(raw[:3])]:
        raise GridFileError(f"{path}: not a Mitsuba .vol file (starts with {raw[:3]!r}; expected {VOL_MAGIC!r})")
    if len(raw) > 3 and raw[3] != VOL_VERSION:
        raise GridFileError(f"{path}: .vol version {raw[3]}; expected {VOL_VERSION} (the only version Mitsuba 3 "
                            "reads)")
    if len(raw) < VOL_HEADER_BYTES:
        raise GridFileError(f"{path}: truncated .vol header: {len(raw)} bytes; expected {VOL_HEADER_BYTES} bytes of "
                            "header and then the data")
    _, _, encoding, x, y, z, channels, *box = _HEADER.unpack(raw[:VOL_HEADER_BYTES])
    if encoding != VOL_FLOAT32:
        raise GridFileError(f"{path}: .vol encoding {encoding}; expected {VOL_FLOAT32} (float32, the only encoding "
                            "Mitsuba 3 reads)")
    _check_resolution((x, y, z), channels, path)
    lo, hi = np.array(box[:3], np.float64), np.array(box[3:], np.float64)
    validate_bounds((lo, hi), path)
    return _Header((x, y, z), channels, (lo, hi))


def read_vol(path, context: str | None = None) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Read and validate a Mitsuba `.vol` grid file.

    **Returns:** `(grid, (box_min, box_max))`: `grid` float32 `(nz, ny, nx, c)` (c 1 or 3, values finite, >= 0),
    the file's bounding box as float64 `(3,)` corners (scene units). **Raises:** `GridFileError` (`SceneError`
    prefixed with `context` when given) naming the file: missing or unreadable file, bad magic, version (3) or
    encoding (1), a resolution < 1 or over `MAX_GRID_VALUES` values, channels other than 1 or 3, a non-finite or
    empty box, a data size other than the header's (expected vs got bytes), non-finite or negative values."""
    path = os.fspath(path)
    try:
        try:
            with open(path, "rb") as fh:
                head = _read_header(fh.read(VOL_HEADER_BYTES), path)
                (x, y, z), c = head.res, head.channels
                n = x * y * z * c
                size = os.fstat(fh.fileno()).st_size
                if size != VOL_HEADER_BYTES + 4 * n:
                    what = "truncated" if size < VOL_HEADER_BYTES + 4 * n else "trailing bytes after the data"
                    raise GridFileError(f"{path}: {what}: {size - VOL_HEADER_BYTES} bytes of data; expected "
                                        f"{4 * n} (x {x} * y {y} * z {z} * {c} channel(s) * 4 bytes)")
                data = np.fromfile(fh, dtype="<f4", count=n)
        except OSError as e:
            raise _unreadable(path, e, ".vol") from None
        if data.size != n:  # the file shrank while being read
            raise GridFileError(f"{path}: truncated: {4 * data.size} bytes of data; expected {4 * n}")
        grid = np.ascontiguousarray(data.reshape(z, y, x, c), dtype=np.float32)
        _check_values(grid, path)
    except GridFileError as e:
        _raise(e, context)
    return grid, head.box


def vol_bytes(grid, bounds, where: str = "<grid>") -> bytes:
    """The bytes of the `.vol` file of `grid` (validated as by `validate_grid`) in the box `bounds` (as by
    `validate_bounds`; stored as float32); `where` names the grid in an error."""
    a = validate_grid(grid, where)
    lo, hi = validate_bounds(bounds, where)
    z, y, x, c = a.shape
    head = _HEADER.pack(VOL_MAGIC, VOL_VERSION, VOL_FLOAT32, x, y, z, c, *lo.tolist(), *hi.tolist())
    return head + a.astype("<f4", copy=False).tobytes(order="C")


def write_vol(path, grid, bounds) -> None:
    """Write a Mitsuba `.vol` file (version 3, float32, little-endian), atomically: a temp file in the destination's
    folder moved onto `path`, so a reader never sees half a file and a failure leaves the old one.

    **Arguments:** `path`; `grid`: `(nz, ny, nx)` or `(nz, ny, nx, c)` (c 1 or 3) densities, finite and >= 0 (stored
    as float32); `bounds`: `(box_min, box_max)` (or `{"min", "max"}`), finite, min < max per axis (stored as
    float32). **Raises:** `GridFileError` for an invalid grid or box (nothing is written), `FileNotFoundError` when
    the folder does not exist."""
    path = os.fspath(path)
    data = vol_bytes(grid, bounds, path)
    from ._image import _atomic_write

    def write(tmp: str) -> None:
        with open(tmp, "wb") as fh:
            fh.write(data)

    _atomic_write(path, write)


# ---------------------------------------------------------------------------------------------------- .npy
def _read_npy(path: str) -> np.ndarray:
    """The array of a `.npy` file; its header (dtype, shape) is checked before the data is read."""
    fmt = np.lib.format
    try:
        with open(path, "rb") as fh:
            try:
                version = fmt.read_magic(fh)
                shape, _, dtype = (fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0)(fh)
            except Exception as e:  # noqa: BLE001 - numpy's header parser raises assorted errors on garbage
                raise GridFileError(f"{path}: not a .npy array ({' '.join(str(e).split())})") from None
            if dtype.hasobject or dtype == bool or dtype.kind not in "iuf":
                raise GridFileError(f"{path}: .npy array of dtype {dtype}; expected real numbers (an integer or "
                                    "float dtype)")
            where = f"{path}: .npy array of shape {tuple(shape)}"
            if len(shape) not in (3, 4):
                raise GridFileError(f"{where} (ndim {len(shape)}); expected (nz, ny, nx) or (nz, ny, nx, c) with "
                                    "c 1 or 3")
            c = shape[3] if len(shape) == 4 else 1
            _check_resolution(shape[2::-1], c, where)
            fh.seek(0)
            return np.load(fh, allow_pickle=False)
    except OSError as e:
        raise _unreadable(path, e, ".npy") from None
    except ValueError as e:
        if isinstance(e, GridFileError):
            raise
        raise GridFileError(f"{path}: truncated or malformed .npy data ({' '.join(str(e).split())})") from None


def load_grid(path, bounds=None, context: str | None = None) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Load and validate a density grid from a `.vol` or `.npy` file.

    **Arguments:**
    - `path`: a `.vol` file (Mitsuba's format) or a `.npy` array `(nz, ny, nx)` or `(nz, ny, nx, c)`, c 1 or 3, of
      any real integer or float dtype (converted to float32; bool, complex and object arrays are refused).
    - `bounds`: the grid's box `(box_min, box_max)` or `{"min": ..., "max": ...}` (scene units): required for a
      `.npy`; for a `.vol` it replaces the file's box (default: the file's box).
    - `context`: when given, errors are `SceneError`s whose message starts with it (e.g. `"fog.json: medium.file"`).

    **Returns:** `(grid, (box_min, box_max))`: float32 `(nz, ny, nx, c)`, values finite and >= 0; float64 `(3,)`
    corners, min < max. **Raises:** `GridFileError` (or `SceneError`) naming the file, the problem, the value and
    the valid range, for everything `read_vol` and `validate_grid` refuse, an unknown extension, or a `.npy` without
    `bounds`.
    """
    path = os.fspath(path)
    try:
        if bounds is not None:
            box = validate_bounds(bounds, f"{path}: bounds")
        ext = os.path.splitext(path)[1].lower()
        if ext == ".vol":
            grid, file_box = read_vol(path)
            return grid, (box if bounds is not None else file_box)
        if ext != ".npy":
            raise GridFileError(f"{path}: unknown grid format {ext or '(no extension)'!r}; expected .vol (Mitsuba's "
                                "volume grid) or .npy (a numpy array)")
        if not os.path.exists(path):
            raise GridFileError(f"{path}: grid file not found")
        if bounds is None:
            raise GridFileError(f"{path}: a .npy grid has no bounding box; give bounds (box_min, box_max), finite "
                                "with min < max on every axis")
        return validate_grid(_read_npy(path), path), box
    except GridFileError as e:
        _raise(e, context)
