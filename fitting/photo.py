"""Targets from cameras: decoding through the file's transfer curve, the pixels that carry no information, the noise a
photograph adds, its EXIF record, and the camera model that makes synthetic photographs from renders.

A photograph's pixel is `curve(exposure x radiance)` in code values, quantised to the file's bit depth (and JPEG
compressed, and noisy): the fit works on the linear values `curve^-1(code)`, with

- the **curve** from OpenImageIO's colour management: the file's own colour space (`oiio:ColorSpace`; an 8- or 16-bit
  file without one is taken as sRGB, as cameras and browsers do), or `--target-curve srgb | linear | gamma:G`;
  `gamma:G` is OpenImageIO's `pow`; RAW camera files (`RAW_EXTENSIONS`) are decoded to linear sensor values by LibRaw
  (`rawpy`, the optional extra `photo`), with the camera's white balance and no curve;
- a **validity mask**: a pixel with any channel within `CLIP_MARGIN` of the encoding's top (a clipped highlight) or
  within `CRUSH_MARGIN` of its bottom (a crushed black) says only that the radiance is beyond a bound, and is not
  fitted; a user mask (white = use) removes what the scene file does not describe;
- a **noise model** estimated from the image itself (`camera_noise`): the camera's shot and read noise, and the
  pixel-to-pixel part of the JPEG error, as a variance `a_c L + b_c` per channel in linear values (Poisson-Gaussian:
  `a` from the photons per unit value, `b` the read noise squared), fitted to second-difference statistics of the
  flat regions binned by brightness; with a **floor**, the linear variance of one code step of quantisation through
  the curve's slope, `(dL/dv)^2 step^2 / 12`, which second differences cannot see in flat regions, where
  quantisation turns noise into steps.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import numpy as np

from .params import FitError
from .problem import box_mean, second_difference_variance

RAW_EXTENSIONS = (".dng", ".cr2", ".cr3", ".nef", ".nrw", ".arw", ".srf", ".sr2", ".raf", ".orf", ".rw2", ".pef",
                  ".srw", ".erf", ".kdc", ".3fr", ".iiq", ".x3f")
"""Camera RAW files, decoded by LibRaw through `rawpy` (the `photo` extra)."""

FLOAT_EXTENSIONS = (".exr", ".hdr", ".pfm")
"""Linear float images: no curve, no clipping, no quantisation."""

CLIP_MARGIN = {8: 3.0 / 255.0, 16: 0.002}
"""How close to the encoding's top a channel may come and still be trusted (in code values over the top): 3 codes
at 8 bits (JPEG's ringing moves a clipped 255 down to 252-254 around an edge), 0.2% at 16 bits (a sensor's
saturation is soft over its last fraction of a percent; RAW files use 0.02 below)."""

CRUSH_MARGIN = {8: 2.0 / 255.0, 16: 0.0005}
"""How close to 0 a channel may come: 2 codes at 8 bits (below, the curve's toe and JPEG's rounding leave only
"dark"), 0.05% at 16 bits."""

RAW_CLIP = 0.98
"""A RAW pixel at 98% of the white level or above is taken as saturated (the sensor's response bends there)."""

CURVES = ("srgb", "linear", "gamma:G")
"""The `--target-curve` choices."""

_SRGB = "srgb_rec709_scene"
_LINEAR = "lin_rec709_scene"
_LINEAR_NAMES = {"linear", "lin_rec709_scene", "lin_srgb", "scene_linear", "lin_rec709", "raw",
                 "linear rec.709 (srgb)"}


@dataclass(frozen=True)
class Photo:
    """A target decoded to linear values. `image` float32 `(H, W, 3)`; `valid` bool `(H, W)` (pixels to fit);
    `noise_var` float64 `(H, W, 3)` the quantisation noise floor of each linear value (zeros for float files);
    `curve` what decoded it; `bits` the code depth (None for float files); `exif` what the file says of the camera
    (`exposure_time_s`, `iso`, `f_number`, `focal_length_mm`, `focal_length_35mm`, `focal_plane_x_per_mm`);
    `masked` counts by reason; `noise` the camera noise model `{"shot": a, "read": sqrt(b)}` per channel (linear
    values; None for float files, or when too few flat pixels are left to fit it)."""

    image: np.ndarray
    valid: np.ndarray
    noise_var: np.ndarray
    curve: str
    bits: int | None
    exif: dict = field(default_factory=dict)
    masked: dict = field(default_factory=dict)
    noise: dict | None = None
    lossy: bool = False

    @property
    def variance(self) -> np.ndarray | None:
        """Each linear value's noise variance `(H, W, 3)`: the camera model at the pixel's local mean brightness, at
        least the quantisation floor. None without a model, and for a lossy (JPEG) file: JPEG removes most of the
        noise's high frequencies, which second differences measure, and keeps its low ones, which a pooled pixel
        holds (measured, docs/photographs.md: at quality 95 the model reads 30% of the shot noise, at 85 19%); the
        fit then estimates the noise block by block and its standard errors from the residuals."""
        if self.noise is None or self.lossy:
            return None
        a = np.asarray(self.noise["shot"], np.float64)
        b = np.asarray(self.noise["read"], np.float64) ** 2
        mu = _local_mean(np.asarray(self.image, np.float64))
        return np.maximum(a * np.maximum(mu, 0.0) + b, self.noise_var)


def parse_curve(curve: str | None) -> tuple[str, float | None] | None:
    """`(kind, gamma)` of a `--target-curve` value (None: the file's own); raises FitError naming the valid ones."""
    if curve is None:
        return None
    c = curve.strip().lower()
    if c in ("srgb", "linear"):
        return c, None
    if c.startswith("gamma:"):
        try:
            g = float(c[6:])
        except ValueError:
            g = float("nan")
        if not (0.2 <= g <= 5.0):
            raise FitError(f"--target-curve {curve!r}: the gamma must be a number in [0.2, 5] (e.g. gamma:2.2)")
        return "gamma", g
    raise FitError(f"--target-curve {curve!r}: valid: {', '.join(CURVES)}")


def _oiio():
    import OpenImageIO as oiio

    return oiio


def read_exif(spec) -> dict:
    """The camera's record from an OpenImageIO `ImageSpec`: only the values the file has."""
    keys = {"exposure_time_s": ("ExposureTime", "Exif:ExposureTime"),
            "iso": ("Exif:ISOSpeedRatings", "Exif:PhotographicSensitivity", "ISOSpeedRatings"),
            "f_number": ("FNumber", "Exif:FNumber"),
            "focal_length_mm": ("Exif:FocalLength", "FocalLength"),
            "focal_length_35mm": ("Exif:FocalLengthIn35mmFilm", "FocalLengthIn35mmFilm"),
            "focal_plane_x_resolution": ("Exif:FocalPlaneXResolution",),
            "pixel_x_dimension": ("Exif:PixelXDimension",),
            "camera": ("Model", "Make")}
    out = {}
    for k, names in keys.items():
        for n in names:
            v = spec.getattribute(n)
            if v is None or v == "":
                continue
            if k != "camera":
                try:
                    v = float(v[0] if isinstance(v, (tuple, list)) else v)
                except (TypeError, ValueError):
                    continue
                if not (math.isfinite(v) and v > 0):
                    continue
            out[k] = v
            break
    res = out.pop("focal_plane_x_resolution", None)  # pixels per unit of the sensor plane: per mm below
    unit = spec.getattribute("Exif:FocalPlaneResolutionUnit")
    per_mm = {2: 1 / 25.4, 3: 0.1, 4: 1.0}.get(int(unit) if isinstance(unit, (int, float)) else 2)  # 2 = inch
    if res is not None and per_mm is not None:
        out["focal_plane_x_per_mm"] = res * per_mm
    return out


def fov_check(exif: dict, fov_deg: float, width: int, height: int) -> str | None:
    """A warning when the scene's horizontal field of view and the one the focal length gives differ by more than 5%;
    None when they agree or the file does not say. From the 35 mm-equivalent focal length (a 36 mm wide frame for a
    landscape image, 24 mm for a portrait one), else from the focal length and the sensor's width: the image's width
    in the camera's pixels (`Exif:PixelXDimension`, else the file's) over the focal plane's pixels per mm."""
    f35, f, per_mm = exif.get("focal_length_35mm"), exif.get("focal_length_mm"), exif.get("focal_plane_x_per_mm")
    if f35:
        focal, sensor = f35, 36.0 if width >= height else 24.0
        what = f"{f35:g} mm, 35 mm equivalent"
    elif f and per_mm:
        focal, sensor = f, exif.get("pixel_x_dimension", width) / per_mm
        what = f"{f:g} mm on a {sensor:.1f} mm wide sensor"
    else:
        return None
    fov_exif = math.degrees(2.0 * math.atan(sensor / (2.0 * focal)))
    if abs(fov_exif - fov_deg) > 0.05 * fov_deg:
        return (f"the scene's camera has a {fov_deg:.1f} deg horizontal field of view; the photograph's focal length "
                f"({what}) gives {fov_exif:.1f} deg: a scene of another camera or zoom?")
    return None


def _decode(oiio, buf, kind: str, gamma: float | None, cs: str):
    """Linear float pixels of a float `ImageBuf` of code values, by OpenImageIO."""
    if kind == "linear":
        return buf.get_pixels(oiio.FLOAT)
    if kind == "gamma":
        out = oiio.ImageBufAlgo.pow(buf, (gamma,) * buf.nchannels)
    else:
        out = oiio.ImageBufAlgo.colorconvert(buf, cs, _LINEAR)
    if out.has_error:
        raise FitError(f"cannot decode through the curve {cs!r}: {out.geterror()}")
    return out.get_pixels(oiio.FLOAT)


def read_photo(path: str, curve: str | None = None, mask: str | None = None) -> Photo:
    """Decode a target (EXR, PNG, JPEG, TIFF 8/16 bit, or a camera RAW file) to linear RGB with its validity mask,
    noise floor and EXIF record (see the module's docstring). `curve`: `--target-curve` (None: the file's own colour
    space, sRGB for integer files that name none); `mask`: a mask image path (white = use; the same size). Raises
    FitError for an unreadable file, a wrong curve or a mask of another size."""
    if not os.path.exists(path):
        raise FitError(f"target {path!r} not found")
    ext = os.path.splitext(path)[1].lower()
    if ext in RAW_EXTENSIONS:
        photo = _read_raw(path, curve)
    else:
        photo = _read_encoded(path, curve)
    if mask is not None:
        user = read_mask(mask, photo.image.shape[:2])
        masked = dict(photo.masked, user=int(np.sum(~user & photo.valid)))
        photo = Photo(photo.image, photo.valid & user, photo.noise_var, photo.curve, photo.bits, photo.exif, masked,
                      photo.noise, photo.lossy)
    if not np.any(photo.valid):
        raise FitError(f"{path}: every pixel is masked ({photo.masked}): nothing to fit")
    return photo


def _read_encoded(path: str, curve: str | None) -> Photo:
    oiio = _oiio()
    buf = oiio.ImageBuf()
    buf.reset(path)
    if not buf.read(0, 0, True, oiio.FLOAT) or buf.has_error:
        raise FitError(f"cannot read target {path!r}: {buf.geterror() or 'unknown format'}")
    spec = buf.spec()
    if spec.nchannels < 3:
        raise FitError(f"{path}: the target must be an RGB image, it has {spec.nchannels} channel(s)")
    if spec.nchannels > 3:
        buf = oiio.ImageBufAlgo.channels(buf, (0, 1, 2))
    fmt = str(oiio.ImageBuf(path).spec().format)
    bits = {"uint8": 8, "uint16": 16}.get(fmt)
    is_float = bits is None or os.path.splitext(path)[1].lower() in FLOAT_EXTENSIONS
    own = (spec.get_string_attribute("oiio:ColorSpace") or "").strip()
    parsed = parse_curve(curve)
    if parsed is None:
        if is_float or own.lower() in _LINEAR_NAMES:
            parsed = ("linear", None)
        else:
            parsed = ("file", None)
    kind, gamma = parsed
    cs = _SRGB if kind == "srgb" or (kind == "file" and not own) else own
    if kind == "file" and cs.lower() in _LINEAR_NAMES:
        kind = "linear"
    name = f"gamma:{gamma:g}" if kind == "gamma" else {"linear": "linear", "srgb": "srgb"}.get(kind, cs)
    code = buf.get_pixels(oiio.FLOAT)
    lin = np.asarray(_decode(oiio, buf, kind, gamma, cs), np.float32)
    exif = read_exif(spec)
    if is_float:
        if not np.all(np.isfinite(lin)):
            raise FitError(f"{path}: {int(np.sum(~np.isfinite(lin)))} non-finite values")
        return Photo(lin, np.ones(lin.shape[:2], bool), np.zeros(lin.shape), name, None, exif, {})
    step = 1.0 / (2 ** bits - 1)
    clipped = np.any(code >= 1.0 - CLIP_MARGIN[bits] + 1e-6, axis=2)
    crushed = np.any(code <= CRUSH_MARGIN[bits] + 1e-6, axis=2)
    noise = _quantisation(oiio, code, step, kind, gamma, cs)
    masked = {"clipped": int(clipped.sum()), "crushed": int((crushed & ~clipped).sum())}
    valid = ~(clipped | crushed)
    lossy = (os.path.splitext(path)[1].lower() in (".jpg", ".jpeg")
             or "jpeg" in (spec.get_string_attribute("compression") or "").lower())
    return Photo(lin, valid, noise, name, bits, exif, masked, camera_noise(lin, valid), lossy)


def _quantisation(oiio, code: np.ndarray, step: float, kind, gamma, cs) -> np.ndarray:
    """`(L(v + step/2) - L(v - step/2))^2 / 12`: the variance of a uniform error of one code step, carried through
    the curve L (OpenImageIO's, as for the image)."""
    spec = oiio.ImageSpec(code.shape[1], code.shape[0], code.shape[2], oiio.FLOAT)
    out = []
    for d in (0.5 * step, -0.5 * step):
        b = oiio.ImageBuf(spec)
        b.set_pixels(oiio.ROI(), np.clip(code + d, 0.0, 1.0).astype(np.float32))
        out.append(np.asarray(_decode(oiio, b, kind, gamma, cs), np.float64))
    return (out[0] - out[1]) ** 2 / 12.0


def _read_raw(path: str, curve: str | None) -> Photo:
    try:
        import rawpy
    except ImportError:
        raise FitError(f"{path}: camera RAW files need rawpy (LibRaw): pip install 'jaxfog[photo]'") from None
    if curve not in (None, "linear"):
        raise FitError(f"{path}: a RAW file holds linear sensor values; --target-curve {curve} does not apply")
    try:
        with rawpy.imread(path) as raw:
            rgb = raw.postprocess(gamma=(1, 1), no_auto_bright=True, output_bps=16, use_camera_wb=True,
                                  output_color=rawpy.ColorSpace.sRGB, user_flip=0)
    except Exception as e:  # noqa: BLE001 - LibRaw's errors are input errors here
        raise FitError(f"cannot read RAW file {path!r}: {e}") from None
    code = rgb.astype(np.float64) / 65535.0
    exif = {}
    try:
        oiio = _oiio()
        inp = oiio.ImageInput.open(path)
        if inp:
            exif = read_exif(inp.spec())
            inp.close()
    except Exception:  # noqa: BLE001 - EXIF is optional
        exif = {}
    clipped = np.any(code >= RAW_CLIP, axis=2)
    crushed = np.any(code <= 0.0, axis=2)
    noise = np.full(code.shape, (1.0 / 65535.0) ** 2 / 12.0)
    masked = {"clipped": int(clipped.sum()), "crushed": int((crushed & ~clipped).sum())}
    valid = ~(clipped | crushed)
    return Photo(code.astype(np.float32), valid, noise, "raw (linear sensor values)", 16, exif, masked,
                 camera_noise(code, valid))


# ---- the camera's noise, from the image itself ------------------------------------------------------------------


def _local_mean(x: np.ndarray) -> np.ndarray:
    """The 3 x 3 box mean of `x` `(H, W, C)` (at the border, over the pixels that exist)."""
    return box_mean(x, 1)


def _median_to_mean() -> float:
    """median / mean of `second_difference_variance` under independent Gaussian noise (it is a scaled sum of two
    correlated squares, not a named distribution): simulated once, 512 x 512 values, fixed seed (the ratio's own
    standard error ~0.002)."""
    if not _MEDIAN_TO_MEAN:
        v = second_difference_variance(np.random.default_rng(12345).standard_normal((514, 514, 1)))[1:-1, 1:-1]
        _MEDIAN_TO_MEAN.append(float(np.median(v) / np.mean(v)))
    return _MEDIAN_TO_MEAN[0]


_MEDIAN_TO_MEAN: list = []
NOISE_MIN_PIXELS = 64
"""Flat-region pixels needed per channel to fit a camera noise model (at least 4 brightness bins of 16); fewer: no
model, the fit estimates the noise block by block (`fitting.problem.block_noise`)."""


def camera_noise(lin: np.ndarray, valid: np.ndarray) -> dict | None:
    """The camera's noise in linear values `lin` `(H, W, 3)`, estimated from the image: per channel the
    Poisson-Gaussian variance `a L + b` (shot noise `a`: 1 / photons per unit value, read noise `sqrt(b)`), the
    pixel-to-pixel part of JPEG's error included. Method (after Foi et al. 2008, "Practical Poissonian-Gaussian noise
    modeling and fitting for single-image raw-data"): each pixel's second-difference variance (`valid` pixels whose
    3 x 3 neighbourhood is valid, so clipping does not truncate it), binned by the brightness of its four diagonal
    neighbours (which the second differences do not use: a brightness that shared their noise would sort the pixels
    by it) into quantile bins; in each bin the median (robust to the edges and texture of a minority of its pixels) over the
    median-to-mean ratio of pure noise estimates the noise variance; `a >= 0`, `b >= 0` by weighted least squares
    over the bins (weight: pixels / variance^2). Returns `{"shot": [a_r, a_g, a_b], "read": [...], "pixels": n}`, or
    None with too few flat pixels (`NOISE_MIN_PIXELS`)."""
    x = np.asarray(lin, np.float64)
    ok = np.asarray(valid, bool)
    inner = np.zeros_like(ok)  # the 3 x 3 neighbourhood valid
    inner[1:-1, 1:-1] = np.all([ok[1 + dy:ok.shape[0] - 1 + dy, 1 + dx:ok.shape[1] - 1 + dx]
                                for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=0)
    n = int(inner.sum())
    if n < NOISE_MIN_PIXELS:
        return None
    diag = np.full(x.shape, np.nan)  # the brightness from the four diagonal neighbours: no pixel of the second
    diag[1:-1, 1:-1] = 0.25 * (x[:-2, :-2] + x[:-2, 2:] + x[2:, :-2] + x[2:, 2:])  # differences, so binning by it
    v, mu = second_difference_variance(x)[inner], diag[inner]  # does not select pixels by their own noise
    m = _median_to_mean()
    bins = int(np.clip(n // 200, 4, 16))
    shot, read = [], []
    for c in range(x.shape[2]):
        order = np.argsort(mu[:, c])
        s, L, w = [], [], []
        for idx in np.array_split(order, bins):
            est = float(np.median(v[idx, c])) / m
            if est > 0:
                s.append(est)
                L.append(float(np.mean(mu[idx, c])))
                w.append(len(idx) / est ** 2)
        a, b = _line_nonnegative(np.asarray(L), np.asarray(s), np.asarray(w))
        shot.append(a)
        read.append(math.sqrt(b))
    return {"shot": shot, "read": read, "pixels": n}


def _line_nonnegative(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[float, float]:
    """Weighted least squares `y ~ a x + b` with `a, b >= 0` (the unconstrained solution, else the better of the two
    one-parameter fits)."""
    if len(x) == 0:
        return 0.0, 0.0
    sw, sx, sy = w.sum(), (w * x).sum(), (w * y).sum()
    sxx, sxy = (w * x * x).sum(), (w * x * y).sum()
    det = sw * sxx - sx * sx
    if det > 0:
        a = (sw * sxy - sx * sy) / det
        b = (sy - a * sx) / sw
        if a >= 0 and b >= 0:
            return float(a), float(b)
    cands = [(0.0, sy / sw)]
    if sxx > 0:
        cands.append((max(sxy / sxx, 0.0), 0.0))
    cost = [float((w * (y - a * x - b) ** 2).sum()) for a, b in cands]
    return cands[int(np.argmin(cost))]


def read_mask(path: str, shape: tuple[int, int]) -> np.ndarray:
    """A user mask as bool `(H, W)`: a pixel is used where the mask's mean over its channels is above one half of its
    range (white = use). Raises FitError for an unreadable file or another size than the target's."""
    if not os.path.exists(path):
        raise FitError(f"mask {path!r} not found")
    oiio = _oiio()
    buf = oiio.ImageBuf()
    buf.reset(path)
    if not buf.read(0, 0, True, oiio.FLOAT) or buf.has_error:
        raise FitError(f"cannot read mask {path!r}: {buf.geterror()}")
    m = np.asarray(buf.get_pixels(oiio.FLOAT), np.float64)
    if m.shape[:2] != tuple(shape):
        raise FitError(f"mask {path!r} is {m.shape[1]}x{m.shape[0]} px, its target {shape[1]}x{shape[0]} px")
    return m.mean(axis=2) > 0.5


# ---- the camera model, for synthetic photographs -----------------------------------------------------------------


def camera_encode(linear: np.ndarray, exposure: float | np.ndarray, rng: np.random.Generator,
                  photons: float | None = 2000.0, read_noise: float = 0.002) -> np.ndarray:
    """A camera's code values in [0, 1] (before its curve) of linear radiance `linear` `(H, W, 3)`: scaled by
    `exposure` (a scalar, or an RGB white balance), Poisson-Gaussian sensor noise (`photons` electrons at value 1,
    None for none; `read_noise` in values), clipped to [0, 1]."""
    x = np.asarray(linear, np.float64) * np.asarray(exposure, np.float64)
    if photons is not None:
        x = rng.poisson(np.maximum(x, 0.0) * photons) / photons + rng.normal(0.0, read_noise, x.shape)
    return np.clip(x, 0.0, 1.0)


def write_photo(path: str, values: np.ndarray, bits: int = 8, quality: int | None = None) -> None:
    """Encode linear sensor values (`camera_encode`) through the sRGB curve (OpenImageIO) to an 8- or 16-bit PNG/TIFF,
    or a JPEG at `quality` (1-100), atomically."""
    oiio = _oiio()
    h, w, c = values.shape
    spec = oiio.ImageSpec(w, h, c, oiio.FLOAT)
    buf = oiio.ImageBuf(spec)
    buf.set_pixels(oiio.ROI(), np.asarray(values, np.float32))
    enc = oiio.ImageBufAlgo.colorconvert(buf, _LINEAR, _SRGB)
    enc.specmod().attribute("oiio:ColorSpace", _SRGB)
    if quality is not None:
        enc.specmod().attribute("Compression", f"jpeg:{int(quality)}")

    stem, ext = os.path.splitext(path)
    tmp = f"{stem}.partial{ext}"
    try:
        if not enc.write(tmp, "uint8" if bits == 8 else "uint16"):
            raise OSError(f"cannot write {path}: {enc.geterror()}")
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
