"""Density-grid files (`jaxfog._volfile`): Mitsuba's `.vol` format written and read back (1 and 3 channels, a
non-cubic resolution), its byte layout against a file packed by hand (x fastest), one test per refusal and its
message, `.npy` grids, and, where Mitsuba 3 is installed, Mitsuba's own `VolumeGrid` reading our files and ours
reading its files, and the `grid` medium's Mitsuba dict (`to_mitsuba`'s converter) evaluated by Mitsuba."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from helpers import trilinear_reference
from jaxfog import _mitsuba
from jaxfog._scene_io import SceneError
from jaxfog._volfile import (MAX_GRID_VALUES, VOL_HEADER_BYTES, GridFileError, load_grid, read_vol, validate_grid,
                             write_vol)

BOX = (np.array([-1.0, 0.0, 2.0]), np.array([3.0, 1.5, 4.0]))  # float32-exact corners
RES = (3, 4, 5)  # (nz, ny, nx): every axis a different length


def _grid(channels: int, res=RES, seed: int = 0) -> np.ndarray:
    """A float32 grid (nz, ny, nx, channels) of distinct non-negative values."""
    rng = np.random.default_rng(seed)
    return rng.uniform(0.0, 5.0, (*res, channels)).astype(np.float32)


def _pack(grid: np.ndarray, box=BOX, magic=b"VOL", version=3, encoding=1, res_xyz=None, channels=None) -> bytes:
    """A `.vol` file packed value by value from the format's description: header fields, then
    data[((z * yres + y) * xres + x) * channels + c] with x fastest (no numpy reshaping)."""
    nz, ny, nx, c = grid.shape
    x_res, y_res, z_res = res_xyz if res_xyz is not None else (nx, ny, nz)
    out = bytearray(magic + bytes([version]))
    out += struct.pack("<iiiii", encoding, x_res, y_res, z_res, c if channels is None else channels)
    out += struct.pack("<6f", *box[0], *box[1])
    for z in range(nz):
        for y in range(ny):
            for x in range(nx):
                for ch in range(c):
                    out += struct.pack("<f", float(grid[z, y, x, ch]))
    return bytes(out)


def _refused(match: str, fn, *args, **kwargs) -> str:
    """`fn(*args)` raises a one-line GridFileError matching `match`; its message."""
    with pytest.raises(GridFileError, match=match) as info:
        fn(*args, **kwargs)
    message = str(info.value)
    assert "\n" not in message
    return message


# ------------------------------------------------------------------------------------------------ round trips
@pytest.mark.parametrize("channels", [1, 3])
def test_round_trip(tmp_path, channels):
    grid = _grid(channels)
    path = tmp_path / "fog.vol"
    write_vol(path, grid, BOX)
    assert path.stat().st_size == VOL_HEADER_BYTES + grid.size * 4
    got, (lo, hi) = read_vol(path)
    assert got.dtype == np.float32 and got.shape == grid.shape and got.flags.c_contiguous
    np.testing.assert_array_equal(got, grid)
    assert lo.dtype == hi.dtype == np.float64 and lo.shape == hi.shape == (3,)
    np.testing.assert_array_equal(lo, BOX[0])
    np.testing.assert_array_equal(hi, BOX[1])
    again, box = load_grid(str(path))  # the file's box unless bounds are given
    np.testing.assert_array_equal(again, grid)
    np.testing.assert_array_equal(box[1], BOX[1])
    _, box = load_grid(path, {"min": [0, 0, 0], "max": [1, 2, 3]})
    np.testing.assert_array_equal(box[0], [0, 0, 0])
    np.testing.assert_array_equal(box[1], [1, 2, 3])


def test_a_3d_grid_is_one_channel_and_writes_are_atomic(tmp_path):
    grid = _grid(1)[..., 0].astype(np.float64)
    path = tmp_path / "fog.vol"
    write_vol(path, grid, BOX)
    got, _ = read_vol(path)
    np.testing.assert_array_equal(got, grid[..., None].astype(np.float32))
    _refused("not finite", write_vol, path, np.full(RES, np.nan), BOX)  # a refused write leaves the old file
    np.testing.assert_array_equal(read_vol(path)[0], got)
    assert [p.name for p in tmp_path.iterdir()] == ["fog.vol"]  # no temp file left behind


def test_byte_layout_is_x_fastest(tmp_path):
    """What `write_vol` writes is, byte for byte, the file packed by hand from the format's description, and a
    hand-packed file reads back as the grid (z, y, x, channel)."""
    grid = (np.arange(np.prod(RES) * 3, dtype=np.float32) * 0.25).reshape(*RES, 3)
    path = tmp_path / "fog.vol"
    write_vol(path, grid, BOX)
    raw = path.read_bytes()
    assert raw == _pack(grid)
    assert raw[:4] == b"VOL\x03" and struct.unpack("<iiiii", raw[4:24]) == (1, 5, 4, 3, 3)  # x, y, z resolution
    # value (x=1, y=0, z=0, channel 0) is the second voxel: byte 48 + 3 channels * 4
    assert struct.unpack("<f", raw[48 + 12:48 + 16])[0] == grid[0, 0, 1, 0]
    hand = tmp_path / "hand.vol"
    hand.write_bytes(_pack(grid))
    np.testing.assert_array_equal(read_vol(hand)[0], grid)


# ---------------------------------------------------------------------------------------------- .vol refusals
def _write(tmp_path, data: bytes, name="bad.vol"):
    path = tmp_path / name
    path.write_bytes(data)
    return path


def test_missing_file_and_header_refusals(tmp_path):
    good = _pack(_grid(1))
    _refused(r"nope\.vol: grid file not found", read_vol, tmp_path / "nope.vol")
    _refused(r"not a Mitsuba \.vol file \(starts with b'VOX'; expected b'VOL'\)", read_vol,
             _write(tmp_path, b"VOX" + good[3:]))
    _refused(r"\.vol version 2; expected 3", read_vol, _write(tmp_path, good[:3] + b"\x02" + good[4:]))
    _refused(r"\.vol encoding 2; expected 1 \(float32", read_vol, _write(tmp_path, _pack(_grid(1), encoding=2)))
    _refused(r"truncated \.vol header: 20 bytes; expected 48", read_vol, _write(tmp_path, good[:20]))
    _refused(r"truncated \.vol header: 0 bytes", read_vol, _write(tmp_path, b""))


def test_data_size_refusals(tmp_path):
    good = _pack(_grid(3))
    n = np.prod(RES) * 3 * 4
    _refused(rf"truncated: {n - 4} bytes of data; expected {n} \(x 5 \* y 4 \* z 3 \* 3 channel\(s\) \* 4 bytes\)",
             read_vol, _write(tmp_path, good[:-4]))
    _refused(rf"trailing bytes after the data: {n + 2} bytes of data; expected {n}", read_vol,
             _write(tmp_path, good + b"\0\0"))


@pytest.mark.parametrize("res_xyz, match", [
    ((5, 0, 3), r"resolution \(x, y, z\) = \(5, 0, 3\); expected each >= 1"),
    ((5, 4, -3), r"resolution \(x, y, z\) = \(5, 4, -3\); expected each >= 1"),
    ((2**16, 2**16, 2**10), rf"is {2**42} values; expected at most 2\*\*31 = {MAX_GRID_VALUES}"),
    ((2**31 - 1, 2**31 - 1, 2**31 - 1), r"expected at most 2\*\*31"),  # overflows 32 and 64-bit products
])
def test_resolution_refusals(tmp_path, res_xyz, match):
    _refused(match, read_vol, _write(tmp_path, _pack(_grid(1), res_xyz=res_xyz)))


@pytest.mark.parametrize("channels", [0, 2, 4, 6])
def test_channel_refusals(tmp_path, channels):
    _refused(rf"{channels} channels; expected 1 \(grey extinction\) or 3 \(RGB extinction\)", read_vol,
             _write(tmp_path, _pack(_grid(1), channels=channels)))


@pytest.mark.parametrize("box, match", [
    (([0, 0, 0], [1, 0, 1]), r"bounding box min \[0, 0, 0\] max \[1, 0, 1\] has min >= max along y"),
    (([0, 0, 2], [1, 1, 1]), r"has min >= max along z; expected min < max on every axis"),
    (([0, np.nan, 0], [1, 1, 1]), r"min \[0, nan, 0\] max \[1, 1, 1\] is not finite"),
    (([0, 0, 0], [np.inf, 1, 1]), r"is not finite \(in float32\); expected finite corners"),
])
def test_bounding_box_refusals(tmp_path, box, match):
    _refused(match, read_vol, _write(tmp_path, _pack(_grid(1), box=box)))
    _refused(match, write_vol, tmp_path / "out.vol", _grid(1), box)
    assert not (tmp_path / "out.vol").exists()


def test_value_refusals(tmp_path):
    grid = _grid(3)
    grid[1, 2, 3, 2] = np.nan
    grid[2, 0, 0, 0] = np.inf
    _refused(r"2 of 180 values are not finite \(first: grid\[z, y, x, channel\] = grid\[1, 2, 3, 2\] = nan\); "
             r"expected finite values", read_vol, _write(tmp_path, _pack(grid)))
    grid = _grid(1)
    grid[0, 3, 1, 0] = -0.5
    grid[2, 0, 4, 0] = -1.0
    _refused(r"2 of 60 values are negative \(first: grid\[z, y, x, channel\] = grid\[0, 3, 1, 0\] = -0\.5\); "
             r"expected densities >= 0", read_vol, _write(tmp_path, _pack(grid)))
    _refused(r"out\.vol: 2 of 60 values are negative", write_vol, tmp_path / "out.vol", grid, BOX)


def test_context_makes_a_scene_error(tmp_path):
    with pytest.raises(SceneError, match=r"^fog\.json: medium\.file: .*nope\.vol: grid file not found$"):
        load_grid(tmp_path / "nope.vol", context="fog.json: medium.file")
    with pytest.raises(SceneError, match=r"^fog\.json: medium\.file: .*bad\.vol: \.vol version 7"):
        read_vol(_write(tmp_path, b"VOL\x07" + bytes(44)), context="fog.json: medium.file")


# ------------------------------------------------------------------------------------------------------ .npy
def test_npy_grids(tmp_path):
    grid = _grid(3)
    np.save(tmp_path / "rgb.npy", grid.astype(np.float64))
    got, (lo, hi) = load_grid(tmp_path / "rgb.npy", BOX)
    assert got.dtype == np.float32 and got.shape == RES + (3,)
    np.testing.assert_array_equal(got, grid)
    np.testing.assert_array_equal(lo, BOX[0])
    counts = np.arange(60, dtype=np.uint16).reshape(RES)
    np.save(tmp_path / "grey.npy", counts)
    got, _ = load_grid(tmp_path / "grey.npy", {"min": BOX[0], "max": BOX[1]})
    np.testing.assert_array_equal(got, counts[..., None].astype(np.float32))
    np.save(tmp_path / "fortran.npy", np.asfortranarray(grid))
    np.testing.assert_array_equal(load_grid(tmp_path / "fortran.npy", BOX)[0], grid)


def test_npy_refusals(tmp_path):
    def save(name, a):
        np.save(tmp_path / name, a, allow_pickle=True)
        return tmp_path / name

    _refused(r"a \.npy grid has no bounding box; give bounds", load_grid, save("a.npy", _grid(1)))
    _refused(r"nope\.npy: grid file not found", load_grid, tmp_path / "nope.npy", BOX)
    _refused(r"shape \(4, 5\) \(ndim 2\); expected \(nz, ny, nx\) or \(nz, ny, nx, c\)", load_grid,
             save("b.npy", np.ones((4, 5))), BOX)
    _refused(r"shape \(1, 2, 3, 4, 1\) \(ndim 5\)", load_grid, save("c.npy", np.ones((1, 2, 3, 4, 1))), BOX)
    _refused(r"2 channels; expected 1 \(grey extinction\) or 3", load_grid, save("d.npy", np.ones((2, 2, 2, 2))), BOX)
    _refused(r"dtype bool; expected real numbers", load_grid, save("e.npy", np.ones((2, 2, 2), bool)), BOX)
    _refused(r"dtype object; expected real numbers", load_grid, save("f.npy", np.full((2, 2, 2), None)), BOX)
    _refused(r"dtype complex128; expected real numbers", load_grid, save("g.npy", np.ones((2, 2, 2), complex)), BOX)
    _refused(r"resolution \(x, y, z\) = \(2, 0, 2\); expected each >= 1", load_grid, save("h.npy", np.ones((2, 0, 2))),
             BOX)
    _refused(r"1 of 8 values are negative", load_grid, save("i.npy", -np.eye(8)[0].reshape(2, 2, 2)), BOX)
    _refused(r"1 of 8 values are not finite .* = inf\)", load_grid, save("j.npy", np.array([1e39] + [0.0] * 7)
                                                                        .reshape(2, 2, 2)), BOX)  # inf in float32
    _refused(r"bounds: bounding box min \[0, 0, 0\] max \[1, 1, 0\] has min >= max along z", load_grid,
             save("k.npy", np.ones((2, 2, 2))), ([0, 0, 0], [1, 1, 0]))
    _refused(r"unknown grid format '\.raw'; expected \.vol .* or \.npy", load_grid, tmp_path / "x.raw", BOX)
    _refused(r"not a \.npy array", load_grid, _write(tmp_path, b"not numpy at all", "l.npy"), BOX)
    trunc = save("m.npy", np.ones((4, 4, 4), np.float32))
    trunc.write_bytes(trunc.read_bytes()[:-8])
    _refused(r"truncated or malformed \.npy data", load_grid, trunc, BOX)


def test_validate_grid_needs_no_file():
    assert validate_grid(np.zeros((1, 1, 1), np.int8)).shape == (1, 1, 1, 1)
    _refused(r"<grid>: 3 of 3 values are not finite", validate_grid, np.full((1, 1, 1, 3), np.nan))


# ----------------------------------------------------------------------------------------- the Mitsuba converter
def _grid_medium(path, bounds=None, **kw) -> dict:
    return {"type": "grid", "file": str(path), "bounds": bounds, "scale": 2.0, "albedo": [0.9, 0.8, 0.7],
            "g": 0.3, "phase": None, **kw}


KEEP = _mitsuba.Export(to_world=lambda m: m, volume=lambda a: a, data={})


def test_grid_medium_dict(tmp_path):
    """`to_mitsuba`'s `grid` medium: a `heterogeneous` medium whose `sigma_t` is a trilinear, clamped `gridvolume`
    of the file's grid, the unit cube mapped onto the box, confined to the box by the fog's cube."""
    assert "grid" in _mitsuba.MEDIA.kinds
    grid = _grid(3)
    write_vol(tmp_path / "fog.vol", grid, BOX)
    fog = _mitsuba.MEDIA(_grid_medium(tmp_path / "fog.vol"), "medium", KEEP)
    med = fog.medium
    assert med["type"] == "heterogeneous" and med["scale"] == 2.0 and not fog.fills_space
    assert med["albedo"] == {"type": "rgb", "value": [0.9, 0.8, 0.7]} and med["phase"] == {"type": "hg", "g": 0.3}
    vol = med["sigma_t"]
    assert (vol["type"], vol["filter_type"], vol["wrap_mode"]) == ("gridvolume", "trilinear", "clamp")
    np.testing.assert_array_equal(vol["grid"], grid)
    lo, hi = BOX
    for corner, want in (([0, 0, 0], lo), ([1, 1, 1], hi), ([0.5, 0.5, 0.5], (lo + hi) / 2)):
        np.testing.assert_allclose((vol["to_world"] @ [*corner, 1.0])[:3], want)
    np.testing.assert_allclose((fog.cube @ [-1.0, -1, -1, 1])[:3], lo)
    np.testing.assert_allclose((fog.cube @ [1.0, 1, 1, 1])[:3], hi)
    assert fog.contains((lo + hi) / 2) and not fog.contains(hi + 0.1)
    other = _mitsuba.MEDIA(_grid_medium(tmp_path / "fog.vol", {"min": [0, 0, 0], "max": [1, 1, 1]}), "medium", KEEP)
    np.testing.assert_allclose(other.medium["sigma_t"]["to_world"][:3], np.eye(4)[:3])  # given bounds win
    np.save(tmp_path / "zero.npy", np.zeros((2, 2, 2)))
    empty = _mitsuba.MEDIA(_grid_medium(tmp_path / "zero.npy", {"min": lo, "max": hi}), "medium", KEEP)
    assert empty.medium["type"] == "homogeneous" and empty.medium["sigma_t"] == 0.0 and not empty.fills_space
    with pytest.raises(GridFileError, match="a .npy grid has no bounding box"):
        _mitsuba.MEDIA(_grid_medium(tmp_path / "zero.npy"), "medium", KEEP)


# ------------------------------------------------------------------------------------------------- with Mitsuba
@pytest.fixture(scope="module")
def mi():
    pytest.importorskip("mitsuba")
    try:
        return _mitsuba.import_mitsuba("scalar_rgb")
    except ImportError as e:
        pytest.skip(str(e))


@pytest.mark.parametrize("channels", [1, 3])
def test_mitsuba_reads_our_file_and_we_read_its_file(mi, tmp_path, channels):
    grid = _grid(channels, seed=channels)
    ours = tmp_path / "ours.vol"
    write_vol(ours, grid, BOX)
    vg = mi.VolumeGrid(str(ours))
    assert list(vg.size()) == [5, 4, 3] and vg.channel_count() == channels  # (x, y, z)
    as_array = np.array(vg, np.float32)  # (z, y, x, c); (z, y, x) for one channel
    assert as_array.shape == (grid.shape if channels > 1 else RES)
    np.testing.assert_array_equal(as_array.reshape(grid.shape), grid)
    bbox = mi.load_dict({"type": "gridvolume", "filename": str(ours), "use_grid_bbox": True}).bbox()
    np.testing.assert_allclose([list(bbox.min), list(bbox.max)], [BOX[0], BOX[1]], rtol=1e-6)  # via its to_local
    theirs = tmp_path / "theirs.vol"
    mi.VolumeGrid(grid).write(str(theirs))
    got, (lo, hi) = read_vol(theirs)
    np.testing.assert_array_equal(got, grid)
    np.testing.assert_array_equal(lo, [0, 0, 0])  # a VolumeGrid made from an array spans the unit cube
    np.testing.assert_array_equal(hi, [1, 1, 1])
    assert theirs.read_bytes()[VOL_HEADER_BYTES:] == ours.read_bytes()[VOL_HEADER_BYTES:]


def test_mitsuba_evaluates_the_grid_medium(mi, tmp_path):
    """Mitsuba's `gridvolume` from the converter, at points in the box (inside and in the clamped border), is the
    grid's trilinear interpolation with texel centres at (i + 0.5) / n of the box; the heterogeneous medium scales
    it and loads in a scene with its boundary cube."""
    grid = _grid(3, seed=7)
    write_vol(tmp_path / "fog.vol", grid, BOX)
    ex = _mitsuba.Export(to_world=lambda m: mi.ScalarTransform4f(np.asarray(m).tolist()), volume=mi.VolumeGrid,
                         data={})
    fog = _mitsuba.MEDIA(_grid_medium(tmp_path / "fog.vol"), "medium", ex)
    vol = mi.load_dict(fog.medium["sigma_t"])
    lo, hi = BOX
    rng = np.random.default_rng(3)
    for u in [*rng.uniform(0.0, 1.0, (12, 3)), np.array([0.01, 0.99, 0.5]), np.array([0.5 / 5, 0.5 / 4, 0.5 / 3])]:
        it = mi.Interaction3f()
        it.p = mi.Point3f(*(lo + u * (hi - lo)).tolist())
        np.testing.assert_allclose(np.array(vol.eval(it), np.float64), trilinear_reference(grid, u), rtol=1e-5,
                                   atol=1e-6)
    medium = mi.load_dict(fog.medium)
    m = mi.MediumInteraction3f()
    m.p = mi.Point3f(*((lo + hi) / 2).tolist())
    m.wavelengths = []
    _, _, sigma_t = medium.get_scattering_coefficients(m)
    np.testing.assert_allclose(np.array(sigma_t, np.float64), 2.0 * trilinear_reference(grid, np.full(3, 0.5)),
                               rtol=1e-5)
    scene = mi.load_dict({"type": "scene", "fog": fog.medium,
                          "box": {"type": "cube", "to_world": ex.to_world(fog.cube), "bsdf": {"type": "null"},
                                  "interior": {"type": "ref", "id": "fog"}}})
    np.testing.assert_allclose([list(scene.bbox().min), list(scene.bbox().max)], [lo, hi], rtol=1e-6)
