"""Photographs as fit targets (`fitting.photo`, `fitting.visibility`): decoding through OpenImageIO's curves, the
masks of clipped and crushed pixels, the quantisation floor, EXIF's field of view, the exposure parameters, and the
visibility's standard error against the delta method done numerically."""

from __future__ import annotations

import math
import os

import numpy as np
import pytest

from fitting.params import FitError, check_names, gains
from fitting.photo import (CLIP_MARGIN, CRUSH_MARGIN, camera_encode, camera_noise, fov_check, parse_curve, read_mask,
                           read_photo, write_photo)
from fitting.visibility import K, visibility


def _srgb_decode(v):
    """The sRGB curve (IEC 61966-2-1), float64: the reference the decoder (OpenImageIO's) is checked against."""
    v = np.asarray(v, np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def _decoder_error(codes: np.ndarray) -> float:
    """The largest difference between OpenImageIO's sRGB decode of exact code values and the float64 curve."""
    import OpenImageIO as oiio

    spec = oiio.ImageSpec(len(codes), 1, 1, oiio.FLOAT)
    buf = oiio.ImageBuf(spec)
    buf.set_pixels(oiio.ROI(), codes.astype(np.float32).reshape(1, -1, 1))
    out = oiio.ImageBufAlgo.colorconvert(buf, "srgb_rec709_scene", "lin_rec709_scene")
    return float(np.max(np.abs(out.get_pixels(oiio.FLOAT).ravel().astype(np.float64) - _srgb_decode(codes))))


def _ramp(h=8, w=64, top=1.0):
    return np.tile(np.linspace(0.0, top, w)[None, :, None], (h, 1, 3))


@pytest.mark.parametrize("ext, bits", [(".png", 8), (".png", 16), (".tif", 16), (".tif", 8)])
def test_srgb_round_trip_within_half_a_code_step(tmp_path, ext, bits):
    """Linear values written through the sRGB curve and read back: each valid value within half a code step of the
    encoding, carried through the curve's slope (the largest slope over the step, bounded by the decode of the
    neighbouring codes), and the reported noise floor is that step's uniform variance."""
    lin = _ramp(top=0.95)
    path = str(tmp_path / f"ramp{ext}")
    write_photo(path, lin, bits=bits)
    ph = read_photo(path)
    assert ph.bits == bits and "srgb" in ph.curve
    step = 1.0 / (2 ** bits - 1)
    code = np.clip(np.round(((1.055 * lin ** (1 / 2.4) - 0.055) * (lin > 0.0031308) + 12.92 * lin
                             * (lin <= 0.0031308)) / step) * step, 0, 1)
    bound = np.abs(_srgb_decode(np.minimum(code + step, 1.0)) - _srgb_decode(np.maximum(code - step, 0.0))) / 2
    # plus the decoder's own error (OpenColorIO's curves in float32), measured here on every exact code
    codes = np.arange(2 ** bits, dtype=np.float64) / (2 ** bits - 1)
    exact = _decoder_error(codes)
    ok = ph.valid
    err = np.abs(ph.image.astype(np.float64) - lin)[ok]
    assert np.all(err <= bound[ok] + exact + 1e-7), float(np.max(err - bound[ok]))
    # the floor: (L(v + step/2) - L(v - step/2))^2 / 12 of the decoded code, at most the bound's square / 3
    assert np.all(ph.noise_var[ok] <= bound[ok] ** 2 / 3.0 + 1e-12)
    assert np.all(ph.noise_var[ok] > 0)


def test_curves_linear_and_gamma(tmp_path):
    """`--target-curve linear` reads the code values themselves; `gamma:G` raises them to G (OpenImageIO's pow)."""
    path = str(tmp_path / "r.png")
    write_photo(path, _ramp(top=0.9), bits=16)
    code = read_photo(path, "linear").image.astype(np.float64)
    g = read_photo(path, "gamma:2.2").image.astype(np.float64)
    np.testing.assert_allclose(g, code ** 2.2, rtol=1e-5, atol=1e-7)
    s = read_photo(path, "srgb").image.astype(np.float64)
    np.testing.assert_allclose(s, _srgb_decode(code), rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("bad", ["gamma:0", "gamma:x", "log", "gamma:9"])
def test_bad_curves_are_refused(bad):
    with pytest.raises(FitError, match="--target-curve"):
        parse_curve(bad)


def test_clipped_and_crushed_pixels_are_masked(tmp_path):
    """A pixel with any channel at the encoding's top (within CLIP_MARGIN) or bottom (within CRUSH_MARGIN) is left
    out, and only those: a ramp from 0 to 1.3 in linear values, 64 columns."""
    lin = _ramp(top=1.3)
    path = str(tmp_path / "c.png")
    write_photo(path, np.clip(lin, 0, 1), bits=8)
    ph = read_photo(path, "linear")
    code = ph.image[0, :, 0]
    expect_clip = code >= 1.0 - CLIP_MARGIN[8] + 1e-6
    expect_crush = code <= CRUSH_MARGIN[8] + 1e-6
    assert expect_clip.sum() >= 64 * 0.3 / 1.3 - 1 and expect_crush.sum() >= 1
    np.testing.assert_array_equal(ph.valid[0], ~(expect_clip | expect_crush))
    assert ph.masked["clipped"] == 8 * expect_clip.sum()


def test_user_mask_and_its_size(tmp_path):
    """A mask image (white = use) removes its black pixels; one of another size is refused naming both sizes."""
    path, mpath, bad = str(tmp_path / "t.png"), str(tmp_path / "m.png"), str(tmp_path / "bad.png")
    write_photo(path, np.full((8, 8, 3), 0.3), bits=8)
    m = np.ones((8, 8, 3))
    m[2:4, 5:7] = 0.0
    write_photo(mpath, m, bits=8)
    ph = read_photo(path, mask=mpath)
    assert ph.masked["user"] == 4 and ph.valid.sum() == 60
    write_photo(bad, np.ones((4, 8, 3)), bits=8)
    with pytest.raises(FitError, match="8x4 px, its target 8x8"):
        read_photo(path, mask=bad)
    with pytest.raises(FitError, match="not found"):
        read_mask(str(tmp_path / "none.png"), (8, 8))


def test_raw_files_need_rawpy_or_are_decoded(tmp_path):
    """A RAW file goes to LibRaw (rawpy); a file that is not one is refused with LibRaw's reason. (No camera file is
    shipped: a DNG cannot be written by rawpy, and the decode itself is LibRaw's, tested there.)"""
    fake = tmp_path / "x.dng"
    fake.write_bytes(b"not a raw file")
    with pytest.raises(FitError, match="x.dng"):
        read_photo(str(fake))


def test_jpeg_decodes_through_the_srgb_curve_within_its_compression_error(tmp_path):
    """A grey ramp written as an sRGB JPEG (quality 100; grey: no chroma subsampling error) and read back: every value
    within 2 code steps of the encoding (JPEG's rounding of the DCT at quality 100 moves a code by at most ~1)
    carried through the curve's slope; the file is known to be lossy, so its noise model does not set the weights."""
    lin = _ramp(h=16, top=0.9)
    path = str(tmp_path / "ramp.jpg")
    write_photo(path, lin, bits=8, quality=100)
    ph = read_photo(path)
    assert ph.bits == 8 and "srgb" in ph.curve and ph.lossy and ph.variance is None
    step = 1.0 / 255.0
    enc = (1.055 * lin ** (1 / 2.4) - 0.055) * (lin > 0.0031308) + 12.92 * lin * (lin <= 0.0031308)
    bound = np.abs(_srgb_decode(np.minimum(enc + 2 * step, 1.0)) - _srgb_decode(np.maximum(enc - 2 * step, 0.0))) / 2
    ok = ph.valid
    err = np.abs(ph.image.astype(np.float64) - lin)[ok]
    assert ok.mean() > 0.9 and np.all(err <= bound[ok] + 1e-6), float(np.max(err - bound[ok]))


def test_exif_is_read_and_the_field_of_view_checked_from_the_sensor(tmp_path):
    """The camera's record written into a JPEG by OpenImageIO is read back (exposure time, ISO, f-number, focal
    lengths, the focal plane's resolution); without a 35 mm-equivalent focal length the field of view comes from the
    focal length and the sensor's width (6000 px at 250 px/mm = 24 mm; 2 atan(24 / 2 / 35) = 37.8 deg)."""
    import OpenImageIO as oiio

    spec = oiio.ImageSpec(32, 16, 3, oiio.UINT8)
    for k, v in (("ExposureTime", 0.01), ("FNumber", 2.8), ("Exif:FocalLength", 35.0),
                 ("Exif:FocalPlaneXResolution", 250.0)):
        spec.attribute(k, oiio.TypeFloat, v)
    spec.attribute("Exif:ISOSpeedRatings", oiio.TypeInt, 400)
    spec.attribute("Exif:FocalPlaneResolutionUnit", oiio.TypeInt, 4)  # mm
    spec.attribute("Exif:PixelXDimension", oiio.TypeInt, 6000)
    spec.attribute("Model", "TestCam")
    buf = oiio.ImageBuf(spec)
    oiio.ImageBufAlgo.fill(buf, (0.5, 0.5, 0.5))
    path = str(tmp_path / "exif.jpg")
    assert buf.write(path), buf.geterror()
    exif = read_photo(path).exif
    near = lambda v: pytest.approx(v, rel=1e-3)  # noqa: E731 - EXIF stores rationals (0.01 reads 0.009999)
    assert exif["exposure_time_s"] == near(0.01) and exif["f_number"] == near(2.8)
    assert exif["iso"] == 400 and exif["focal_length_mm"] == near(35.0) and exif["camera"] == "TestCam"
    assert exif["focal_plane_x_per_mm"] == near(250.0) and exif["pixel_x_dimension"] == 6000
    fov = math.degrees(2 * math.atan(24.0 / 2 / 35.0))
    assert fov_check(exif, fov, 32, 16) is None
    msg = fov_check(exif, 60.0, 32, 16)
    assert "60.0 deg" in msg and f"{fov:.1f} deg" in msg and "24.0 mm wide sensor" in msg


@pytest.mark.parametrize("photons, read", [(20000.0, 0.002), (2000.0, 0.005)])
def test_camera_noise_is_estimated_from_the_image(photons, read):
    """Poisson-Gaussian noise (`photons` per unit value, read noise `read`) on a smooth image (a ramp under a blob,
    values 0.05-0.95) with a clipped corner: the shot coefficient 1 / photons and the read noise recovered, the mean
    over 6 seeds within 3 of its standard errors (the seeds' spread / sqrt(6)) plus 5% (the binning's bias: each bin
    spans a range of brightness)."""
    h = w = 96
    yy, xx = np.mgrid[0:h, 0:w] / h
    base = 0.05 + 0.5 * xx + 0.4 * np.exp(-((xx - 0.6) ** 2 + (yy - 0.4) ** 2) / 0.05)
    img = np.stack([base, 0.8 * base, 0.6 * base], -1)
    img[:10, :10] = 2.0  # clipped by the camera: out of the estimate
    est = []
    for seed in range(6):
        x = camera_encode(img, 1.0, np.random.default_rng(seed), photons, read)
        n = camera_noise(x, ~np.any(x >= 1.0, axis=2))
        est.append([n["shot"][1], n["read"][1]])
    est = np.asarray(est)
    mean, se = est.mean(axis=0), est.std(axis=0, ddof=1) / np.sqrt(len(est))
    for m, s, true in zip(mean, se, (1.0 / photons, read)):
        assert abs(m - true) <= 3 * s + 0.05 * true, (m, s, true)
    assert camera_noise(x, np.zeros((h, w), bool)) is None  # nothing to fit it on


def test_raw_file_decodes_to_its_linear_sensor_values(tmp_path):
    """A tiny DNG (tests/helpers.py: RGGB, sensor values 1000 / 2000 / 3000 of 4095 on the left half and half of them
    on the right, neutral white balance, a colour matrix that makes the camera's RGB linear sRGB) decoded by LibRaw:
    every pixel away from the step between the halves and from the border (4 px: the demosaicing's neighbourhood) is
    its sensor value / 4095 per channel (demosaicing a constant per channel changes nothing) to 1e-4 (the colour
    matrix's rationals), linear in the sensor value, nothing masked."""
    pytest.importorskip("rawpy", reason="camera RAW files need the `photo` extra (rawpy); the test extra has it")
    from helpers import write_dng

    cfa = np.zeros((64, 96), np.uint16)
    for (dy, dx), v in {(0, 0): 1000, (0, 1): 2000, (1, 0): 2000, (1, 1): 3000}.items():
        cfa[dy::2, dx::2] = v
    cfa[:, 48:] //= 2
    path = str(tmp_path / "tiny.dng")
    write_dng(path, cfa)
    ph = read_photo(path)
    assert ph.bits == 16 and "raw" in ph.curve and ph.valid.all() and not ph.lossy
    want = np.where(np.arange(96)[None, :, None] < 48, 1.0, 0.5) * np.array([1000.0, 2000.0, 3000.0]) / 4095.0
    err = np.abs(ph.image - np.broadcast_to(want, ph.image.shape))
    assert np.max(err[4:-4, np.r_[4:44, 52:92]]) < 1e-4


def test_field_of_view_warning_names_both_numbers():
    """The 35 mm-equivalent focal length gives the horizontal field of view 2 atan(36 / 2f): a scene at 40 deg
    against a 28 mm lens (65.5 deg) is warned about with both numbers; 65 deg passes (within 5%)."""
    msg = fov_check({"focal_length_35mm": 28.0}, 40.0, 640, 480)
    assert "40.0 deg" in msg and "65.5 deg" in msg
    assert fov_check({"focal_length_35mm": 28.0}, 65.0, 640, 480) is None
    assert fov_check({}, 40.0, 640, 480) is None


def test_exposure_parameters_and_their_refusals():
    """`exposure` scales every channel of every view, `exposure[c]` one channel, `exposure@v` view v; with the
    light's intensity, or with its own parts, it is not determined and refused."""
    g = np.asarray(gains({"exposure": 2.0, "exposure[r]": 3.0, "exposure@2": 5.0}, 1))
    np.testing.assert_allclose(g, [30.0, 10.0, 10.0])
    np.testing.assert_allclose(np.asarray(gains({"exposure": 2.0, "exposure@2": 5.0}, 0)), [2.0, 2.0, 2.0])
    assert gains({"sigma_t": 1.0}, 0) is None
    assert check_names(["sigma_t", "exposure:rgb"])[1:] == ["exposure[r]", "exposure[g]", "exposure[b]"]
    with pytest.raises(FitError, match="intensity"):
        check_names(["sigma_t", "exposure", "intensity"])
    with pytest.raises(FitError, match="not determined apart"):
        check_names(["exposure", "exposure[r]"])


def test_camera_model_is_unbiased_before_clipping():
    """The synthetic camera's Poisson-Gaussian noise keeps the mean: over 200k values at 0.3 (exposure 0.5 of 0.6),
    the mean within 4 standard errors of the shot and read noise."""
    rng = np.random.default_rng(3)
    x = camera_encode(np.full((200, 1000, 1), 0.6), 0.5, rng, photons=2000.0, read_noise=0.002)
    se = math.sqrt(0.3 / 2000.0 + 0.002 ** 2) / math.sqrt(x.size)
    assert abs(float(x.mean()) - 0.3) < 4 * se


class _Med:
    sigma_0 = np.array([0.2, 0.2, 0.2])
    height_scale = 1.5
    base_height = 0.5
    up = np.array([0.0, 1.0, 0.0])


class _Cam:
    origin = np.array([0.0, 2.0, 3.0])


class _Scene:
    medium = _Med()
    camera = _Cam()


def _numeric_se(f, x, C, h=1e-6):
    """The delta method done numerically: central differences of f at x, then sqrt(d^T C d)."""
    d = np.array([(f(x + h * e) - f(x - h * e)) / (2 * h) for e in np.eye(len(x))])
    return float(math.sqrt(d @ C @ d))


def test_visibility_and_its_standard_error_by_the_delta_method():
    """MOR = -ln(0.05) / sigma_t; its standard error equals the numerical delta method's for a grey, a per-channel
    and a height fog (at the camera's height, through sigma_0, H and h_0 with correlations)."""
    C = np.array([[4e-4, 1e-4], [1e-4, 9e-4]])
    v = visibility(None, ["sigma_t", "g"], {"sigma_t": 0.4, "g": 0.6}, C)
    assert v["mor"] == pytest.approx(K / 0.4)
    assert v["se"] == pytest.approx(_numeric_se(lambda x: K / x[0], np.array([0.4, 0.6]), C), rel=1e-5)
    v = visibility(None, ["sigma_t[r]", "sigma_t[b]"], {"sigma_t[r]": 0.3, "sigma_t[b]": 0.5}, C)
    assert v["channels"]["b"]["se"] == pytest.approx(_numeric_se(lambda x: K / x[1], np.array([0.3, 0.5]), C),
                                                     rel=1e-5)
    names = ["sigma_0", "height_scale", "base_height"]
    x0 = np.array([0.25, 1.2, 0.4])
    C3 = np.array([[1e-4, 2e-5, 0.0], [2e-5, 4e-3, 1e-4], [0.0, 1e-4, 1e-3]])
    v = visibility(_Scene(), names, dict(zip(names, x0)), C3)
    mor_c = lambda x: K / (x[0] * math.exp(-(2.0 - x[2]) / x[1]))  # noqa: E731 - camera at height 2
    assert v["camera_height"]["mor"] == pytest.approx(mor_c(x0))
    assert v["camera_height"]["se"] == pytest.approx(_numeric_se(mor_c, x0, C3), rel=1e-4)
    assert v["base_height"]["mor"] == pytest.approx(K / 0.25)
    assert visibility(None, ["g"], {"g": 0.5}, np.eye(1)) is None


def test_fit_cli_refuses_bad_photo_arguments(tmp_path):
    """`--target-curve` and `--masks` are checked before any render: a bad curve, a mask count that is not one per
    target."""
    from fitting.fit import main

    here = os.path.dirname(__file__)
    scene = os.path.join(here, "..", "data_synthetic", "scenes", "spot_fog.json")
    photo = os.path.join(here, "..", "data_synthetic", "photos", "spot_fog_a.jpg")
    out = str(tmp_path / "r.json")
    assert main([scene, photo, "--fit", "sigma_t", "exposure", "--target-curve", "log", "--out", out]) == 2
    assert main([scene, photo, "--fit", "sigma_t", "exposure", "--masks", "a.png", "b.png", "--out", out]) == 2
    assert not os.path.exists(out)


# slow tier: a fit (20-40 s with a cold compilation cache on 2 cores); the default run checks the photograph's parts
# (decoding, masks, noise, exposure parameters, visibility) and the solver's fits in tests/test_fit.py
@pytest.mark.slow
def test_fit_of_a_synthetic_photograph_recovers_the_medium_and_the_exposure(tmp_path):
    """A 16-bit sRGB photograph (exposure 0.37, Poisson-Gaussian noise, the light's highlight clipped) of the small
    backlit scene of tests/test_fit.py: the fit of sigma_t, g and the exposure finds each within 3 of its standard
    errors of the truth (the photograph's noise is estimated from the image itself: the camera noise model), and
    reports the visibility."""
    import jax

    import jaxfog
    from fitting.params import apply
    from fitting.problem import make_view
    from fitting.solver import FitConfig, fit_views
    from test_fit import TRUTH, _scene

    img = np.asarray(jaxfog.render(apply(_scene(), TRUTH), jax.random.key(991), 2048, estimator="detached"))
    code = camera_encode(img, 0.37, np.random.default_rng(5), photons=20000.0, read_noise=0.001)
    path = str(tmp_path / "photo.png")
    write_photo(path, code, bits=16)
    ph = read_photo(path)
    assert not ph.lossy and ph.noise is not None  # a PNG: the camera noise model sets the weights
    view = make_view(_scene(), ph.image, "photo", 2, None, ph.valid, ph.noise_var, ph.variance)
    res = fit_views([view], ["sigma_t", "g", "exposure"], {"sigma_t": 1.0, "g": 0.0, "exposure": 1.0},
                    FitConfig(spp=32, seed=0), log=lambda *_: None)
    assert res.success, res.messages
    for n, true in {**TRUTH, "exposure": 0.37}.items():
        se = res.uncertainty[n]["se"]
        assert abs(res.params[n] - true) <= 3.0 * se, (n, res.params[n], true, se)
    assert res.visibility["mor"] == pytest.approx(K / res.params["sigma_t"])


WB = {"exposure[r]": 0.45, "exposure[g]": 0.37, "exposure[b]": 0.30}


# slow tier: three fits of 10-40 s each (compiling their programs)
@pytest.mark.slow
@pytest.mark.parametrize("names, gains", [
    (["sigma_t", "exposure:rgb"], WB),
    (["sigma_t", "g", "exposure:rgb"], WB),
    (["sigma_t", "g", "exposure@1", "exposure@2"], {"exposure@1": 0.37, "exposure@2": 0.74}),
], ids=["white_balance", "white_balance_and_g", "per_image"])
def test_fit_of_photographs_recovers_white_balance_and_per_image_exposures(tmp_path, names, gains):
    """The camera's other parameters through the same solver: an unknown white balance (`exposure:rgb`, one factor per
    channel) on one 16-bit photograph, and one exposure per photograph (`exposure@1`, `exposure@2`) on two photographs
    of the same view a stop apart (each rendered with its own key and noise). Every parameter within 3 of its
    standard errors of the truth, with g known and with g free: one photograph of this view determines g, sigma_t and
    the three channel factors together (fit seeds 0, 1, 2: sigma_t 0.611 ± 0.025, 0.612 ± 0.028, 0.584 ± 0.018 for
    0.6, exposure[r] within 0.45-1.54 se of 0.45; a solver that went back from the estimate to a flat starting
    point had stopped short of that, at sigma_t 0.61 ± 0.10 and exposure[r] 0.25 ± 0.17)."""
    import jax

    import jaxfog
    from fitting.params import apply, check_names
    from fitting.problem import make_view
    from fitting.solver import FitConfig, fit_views
    from test_fit import TRUTH, _scene

    names = check_names(names)
    per_image = "exposure@1" in gains
    views = []
    for i in range(2 if per_image else 1):
        img = np.asarray(jaxfog.render(apply(_scene(), TRUTH), jax.random.key(991 + i), 2048, estimator="detached"))
        wb = (np.full(3, gains[f"exposure@{i + 1}"]) if per_image
              else np.array([gains["exposure[r]"], gains["exposure[g]"], gains["exposure[b]"]]))
        code = camera_encode(img, wb, np.random.default_rng(5 + i), photons=20000.0, read_noise=0.001)
        path = str(tmp_path / f"photo{i}.png")
        write_photo(path, code, bits=16)
        ph = read_photo(path)
        views.append(make_view(_scene(), ph.image, f"photo{i}", 2, None, ph.valid, ph.noise_var, ph.variance))
    init = {"sigma_t": 1.0, "g": 0.0, **{n: 1.0 for n in names if n.startswith("exposure")}}
    init = {n: v for n, v in init.items() if n in names}
    res = fit_views(views, names, init, FitConfig(spp=32, seed=0), log=lambda *_: None)
    assert res.success, res.messages
    for n, true in {**TRUTH, **gains}.items():
        if n not in names:
            continue
        se = res.uncertainty[n]["se"]
        assert abs(res.params[n] - true) <= 3.0 * se, (n, res.params[n], true, se)
