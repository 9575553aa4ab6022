"""Shared helpers of the jaxfog test suite (imported as `from helpers import ...`; tests/ is on sys.path).

- Scene builders: `CameraSpec` (plain floats, for the renderer and float64 references), `FLOOR_CAMERA`, `make_floor`,
  `spot_fog` / `spot_fog_dict` (the shipped `data_synthetic/scenes/spot_fog.json`, optionally overridden).
- Float64 references: `hg_np`, `spot_falloff_np`.
- Reductions: `block_mean` (means over b x b pixel blocks); finite differences: `fd_stencil`.
- Statistics: `render_keys`, `mean_and_se`, `assert_statistically_equal` (an estimate against a reference).
- Two programs: `assert_same_render_up_to_rounding` (two differently compiled programs computing the same image).

Statistics (used by every render test; see `assert_statistically_equal`)
- A render estimate is checked against a reference with per-value standard errors (SE) computed from `n_keys`
  independent renders (different keys): SE = sample std over keys (ddof=1) / sqrt(n_keys). With n_keys = 32, each
  z = (estimate - reference) / SE follows (approximately: the per-key means must be close to normal, so tests use
  enough spp per key) a Student t with nu = 31 degrees of freedom: E[z^2] = nu/(nu-2) = 1.07,
  Var[z^2] = 3 nu^2/((nu-2)(nu-4)) - E[z^2]^2 = 2.54. The checks and their false-alarm rates for an unbiased
  renderer, with n_pix pixels (the three channels of a pixel may be fully correlated, so n_pix, not 3 n_pix, counts):
  * every |z| <= 6.5 (P(|t_31| > 6.5) ~ 3e-7 per value: < 0.5% for the ~10^4 values the whole suite checks, with
    room for per-key means somewhat less normal than assumed; 5.5 was measured to be hit about once per suite run);
  * at most 3% of the values have |z| > 3 (expected 0.5%);
  * mean(z^2) <= 1.07 + 5 sqrt(2.54 / n_pix) (5 standard deviations of the mean of n_pix values);
  * per channel, |mean(z)| <= 4 sqrt(1.07 / n_pix) (a bias of a fraction of one SE shared by all pixels fails this).
  The SE gets a float32 floor of 3e-5 * |reference| (rounding of float32 sums of at most a few thousand samples).
"""

from __future__ import annotations

import struct

import dataclasses
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxfog as jf

REPO = Path(__file__).resolve().parents[1]
SCENES_DIR = REPO / "data_synthetic" / "scenes"
SPOT_FOG = SCENES_DIR / "spot_fog.json"

N_KEYS = 32
"""Independent renders per statistical estimate (t distribution with N_KEYS - 1 degrees of freedom)."""

FLOAT32_REL_FLOOR = 3e-5


# ------------------------------------------------------------------------------------------------ float64 references
@dataclasses.dataclass(frozen=True)
class CameraSpec:
    """Plain-float description of a pinhole camera (conventions.md), for both the renderer and float64 references."""

    origin: tuple
    target: tuple
    up: tuple = (0.0, 1.0, 0.0)
    fov: float = 30.0
    width: int = 16
    height: int = 12

    def build(self) -> jf.Camera:
        return jf.Camera(origin=self.origin, target=self.target, up=self.up, fov=self.fov, width=self.width,
                         height=self.height)

    def rays(self, n: int = 4):
        """Float64 rays through an n x n Gauss–Legendre grid in every pixel's square.

        Returns `(origin (3,), dirs (H, W, n*n, 3) unit, weights (n*n,) summing to 1)`. Written from conventions.md:
        fov = full horizontal field of view; pixel (row 0, col 0) is the top-left; camera +x is the image's right.
        """
        o = np.asarray(self.origin, np.float64)
        f = np.asarray(self.target, np.float64) - o
        f /= np.linalg.norm(f)
        r = np.cross(f, np.asarray(self.up, np.float64))
        r /= np.linalg.norm(r)
        u = np.cross(r, f)
        x, w = np.polynomial.legendre.leggauss(n)
        x, w = 0.5 * (x + 1.0), 0.5 * w
        W, H = self.width, self.height
        px = np.arange(W)[None, :, None, None] + x[None, None, :, None]  # (1, W, n, 1)
        py = np.arange(H)[:, None, None, None] + x[None, None, None, :]  # (H, 1, 1, n)
        tan_half = np.tan(0.5 * np.deg2rad(self.fov))
        sx = (2.0 * px / W - 1.0) * tan_half
        sy = (1.0 - 2.0 * py / H) * tan_half * (H / W)
        sx, sy = np.broadcast_arrays(sx, sy)  # (H, W, n, n)
        d = f + sx[..., None] * r + sy[..., None] * u
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        weights = (w[:, None] * w[None, :]).reshape(-1)
        return o, d.reshape(H, W, n * n, 3), weights


def hg_np(cos_theta, g):
    """Henyey–Greenstein phase function in float64 (conventions.md), as a function of cos theta."""
    return (1.0 - g * g) / (4.0 * np.pi * (1.0 + g * g - 2.0 * g * cos_theta) ** 1.5)


def spot_falloff_np(theta, cutoff_deg, beam_deg):
    """conventions.md: 1 for theta <= beam, (cutoff - theta)/(cutoff - beam) between, 0 beyond (radians)."""
    c, b = np.deg2rad(cutoff_deg), np.deg2rad(beam_deg)
    theta = np.asarray(theta, np.float64)
    ramp = (c - theta) / (c - b) if c > b else np.zeros_like(theta)
    return np.where(theta <= b, 1.0, np.where(theta < c, ramp, 0.0))


# ------------------------------------------------------------------------------------------------ rendering helpers
def render_keys(scene: jf.Scene, spp: int, *, n_keys: int = N_KEYS, seed: int = 0, **kwargs) -> np.ndarray:
    """`n_keys` independent renders (keys `fold_in(key(seed), k)`), as float64 numpy `(n_keys, H, W, 3)`.

    `batch_paths` is set so that one compiled call covers all `spp` layers (one compilation per scene structure)."""
    cam = scene.camera
    kwargs.setdefault("batch_paths", cam.width * cam.height * spp)
    base = jax.random.key(seed)
    imgs = [jf.render(scene, jax.random.fold_in(base, k), spp, **kwargs) for k in range(n_keys)]
    return np.asarray(jnp.stack(imgs), np.float64)


def mean_and_se(samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean over the first axis and its standard error (sample std with ddof=1 / sqrt(n))."""
    n = samples.shape[0]
    return samples.mean(axis=0), samples.std(axis=0, ddof=1) / np.sqrt(n)


def assert_statistically_equal(mean, se, ref, *, label: str = "", ref_se=None, ref_atol: float = 0.0):
    """Check an estimate `mean` with standard error `se` against `ref` (exact, or itself an estimate with `ref_se`).

    `ref_atol`: a stated absolute accuracy of the reference itself, added to the SE in quadrature.
    Thresholds and their justification: module docstring.
    """
    mean, se, ref = (np.asarray(x, np.float64) for x in (mean, se, ref))
    var = se**2 + (FLOAT32_REL_FLOOR * np.abs(ref)) ** 2 + ref_atol**2 + 1e-14
    if ref_se is not None:
        var = var + np.asarray(ref_se, np.float64) ** 2
    z = (mean - ref) / np.sqrt(var)
    assert np.all(np.isfinite(mean)), f"{label}: non-finite estimate"
    flat = np.abs(z).reshape(-1)
    worst = np.unravel_index(np.argmax(np.abs(z)), z.shape)
    info = (f"{label}: worst z={z[worst]:.2f} at {worst} (estimate {mean[worst]:.6g}, reference {ref[worst]:.6g}, "
            f"se {np.sqrt(var[worst]):.3g}); mean z^2={np.mean(z**2):.3f}; frac|z|>3={np.mean(flat > 3):.4f}; "
            f"mean z per channel={z.reshape(-1, z.shape[-1]).mean(0)}")
    nu = N_KEYS - 1
    e_z2 = nu / (nu - 2)
    var_z2 = 3 * nu**2 / ((nu - 2) * (nu - 4)) - e_z2**2
    n_pix = z.reshape(-1, z.shape[-1]).shape[0]
    assert flat.max() <= 6.5, info
    assert np.mean(flat > 3.0) <= 0.03, info
    assert np.mean(z**2) <= e_z2 + 5 * np.sqrt(var_z2 / n_pix), info
    assert np.all(np.abs(z.reshape(-1, z.shape[-1]).mean(0)) <= 4.0 * np.sqrt(e_z2 / n_pix)), info
    return z


FLOOR_CAMERA = CameraSpec(origin=(0.0, 2.0, 3.0), target=(0.0, 0.0, 0.0), fov=40.0, width=16, height=12)
"""Looks down at the floor; the floor fills the whole view (the top rays meet the floor ~6 units away)."""


def make_floor(reflectance=(0.7, 0.5, 0.3), half=8.0):
    """Diffuse floor y = 0, front face +y (edge_u = +x, edge_v = -z), 2*half wide."""
    return jf.Rectangle(center=(0.0, 0.0, 0.0), edge_u=(2 * half, 0.0, 0.0), edge_v=(0.0, 0.0, -2 * half),
                        bsdf=jf.Diffuse(reflectance))


def spot_fog_dict() -> dict:
    """The shipped spot_fog scene file as a dict (a fresh copy each call)."""
    return json.loads(SPOT_FOG.read_text())


def spot_fog(*overrides: str, width: int | None = None, height: int | None = None,
             max_depth: int | None = None) -> jf.Scene:
    """The shipped spot_fog `Scene`, with `--set`-style `overrides` and optional resolution and max_depth."""
    extra = [f"camera.width={width}"] * (width is not None) + [f"camera.height={height}"] * (height is not None)
    extra += [f"integrator.max_depth={max_depth}"] * (max_depth is not None)
    return jf.load_scene(SPOT_FOG, [*overrides, *extra]).scene


def fd_stencil(theta0, steps, four_point):
    """Parameter values for central finite differences around `theta0`: parameter p moves by `steps[p] * |theta0[p]|`,
    with the 4-point stencil (error O(h^4)) where `four_point[p]`, else the 2-point one (O(h^2)). Returns
    `(thetas (n, len(theta0)) float32, [(p, row indices into thetas, weights)])`: the derivative along p is
    `weights @ values[rows]`."""
    theta0 = np.asarray(theta0, np.float64)
    thetas, plan = [], []
    for p in range(theta0.size):
        h = steps[p] * abs(theta0[p])
        offsets, weights = ((-2, -1, 1, 2), (1, -8, 8, -1)) if four_point[p] else ((-1, 1), (-1, 1))
        denom = 12.0 * h if four_point[p] else 2.0 * h
        idx = []
        for o in offsets:
            t = theta0.copy()
            t[p] += o * h
            idx.append(len(thetas))
            thetas.append(t)
        plan.append((p, idx, np.asarray(weights, np.float64) / denom))
    return np.asarray(thetas, np.float32), plan


def block_mean(imgs, b: int) -> np.ndarray:
    """Means over b x b pixel blocks of `(..., H, W, C)` images (H and W multiples of b): `(..., H/b, W/b, C)`."""
    imgs = np.asarray(imgs)
    *lead, h, w, c = imgs.shape
    return imgs.reshape(*lead, h // b, b, w // b, b, c).mean(axis=(-4, -2))


# ------------------------------------------------------------------------------------------ two compiled programs
ROUNDING_RTOL = 1e-4
"""Relative difference float32 rounding alone can make between two compilations of one path tracer (see
`assert_same_render_up_to_rounding`)."""

MAX_FLIP_FRACTION = 0.05
"""Largest fraction of pixels in which a branch flip may be seen (see `assert_same_render_up_to_rounding`)."""


def assert_same_render_up_to_rounding(a, b, *, spp: int, label: str = "", scale=None,
                                      rtol: float = ROUNDING_RTOL, max_flip_fraction: float = MAX_FLIP_FRACTION):
    """`a` and `b` (`(H, W, 3)`) are one image (or one derivative image) computed by two differently compiled
    programs (another device count, chunking, batch size, vector width, or forward vs reverse mode): equal up to
    what float32 rounding can do. Two effects, two bounds:

    1. **Rounding of the arithmetic.** A path's radiance is a chain of at most ~100 float32 operations per segment
       (a few hundred at the depths the tests use), each rounded to 2^-24 relative; two compilations may contract
       them differently (FMA or not), use other polynomial approximations of exp/log/sin (vector widths differ in
       their last few ulps) and sum the `spp` samples in another order (non-negative terms: at most `spp` x 2^-24 of
       the sum). That is below ~400 x 4 ulps = 1e-4 relative (`ROUNDING_RTOL`); absolute where a value is near 0:
       `rtol` x 1e-3 x the image's (or `scale`'s) largest value.
    2. **A branch flip.** A rounding difference in a quantity compared with a threshold (a uniform against a
       probability, a hit distance against another) changes that decision, and the path then takes another
       branch: its contribution changes entirely, by anything up to the path's own contribution / spp, at most the
       pixel's value itself when the contributions are non-negative (`(S + x)/spp` vs `(S + y)/spp`). Such flips
       need a rounding difference within ~1e-6 relative of a threshold, so they are rare; they are counted per
       pixel, and at most `max_flip_fraction` (5%; at least one pixel) of the pixels may differ beyond bound 1
       (measured: 2 of 256 pixels at 1 spp on an AVX-512 CPU). For images (`scale=None`) a differing pixel must still
       be bounded by the flip bound `max(|a|, |b|)` per channel, and finite.

    A wrong result (another key, another spp, a lost chunk) changes most pixels beyond bound 1 and fails.
    """
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    assert a.shape == b.shape, (label, a.shape, b.shape)
    assert np.all(np.isfinite(a)) and np.all(np.isfinite(b)), f"{label}: non-finite values"
    ref = np.abs(a).max() if scale is None else float(np.abs(np.asarray(scale)).max())
    tol = rtol * np.maximum(np.abs(a), np.abs(b)) + rtol * 1e-3 * ref + 1e-30
    diff = np.abs(a - b)
    px_bad = (diff > tol).reshape(-1, a.shape[-1]).any(axis=1)
    n_pix = px_bad.size
    allowed = max(1, int(max_flip_fraction * n_pix))
    worst = np.unravel_index(np.argmax(diff / tol), diff.shape)
    info = (f"{label}: {int(px_bad.sum())} of {n_pix} pixels differ beyond the rounding bound (allowed {allowed}); "
            f"worst at {worst}: {a[worst]:.7g} vs {b[worst]:.7g} (bound {tol[worst]:.3g}); spp {spp}")
    assert px_bad.sum() <= allowed, info
    if scale is None:
        assert np.all(diff <= np.maximum(np.abs(a), np.abs(b)) + tol), "beyond the flip bound: " + info
    return int(px_bad.sum())


def image_and_quadrant_means(imgs):
    """For `(n, H, W, 3)` independent images (H, W even): per image the mean and the four quadrant means (channels
    averaged), then their mean over images and its standard error: `(mean (5,), se (5,))`. Used to compare two
    renderers' independent images with z = difference / combined SE."""
    n, H, W = imgs.shape[:3]
    g = imgs.mean(-1)
    q = g.reshape(n, 2, H // 2, 2, W // 2).mean(axis=(2, 4)).reshape(n, 4)
    v = np.concatenate([imgs.reshape(n, -1).mean(1, keepdims=True), q], axis=1)
    return v.mean(0), v.std(0, ddof=1) / np.sqrt(n)


def jaxfog_and_mitsuba_images(path, overrides, n: int, spp: int):
    """`n` independent images of the scene file `path` (with `overrides`) from each renderer, `spp` samples each:
    jaxfog with keys 0..n-1, Mitsuba (`jaxfog.render_mitsuba`, needs the compare extra) with seeds 0..n-1; two
    float64 arrays `(n, H, W, 3)`."""
    import jax

    import jaxfog as jf

    scene = jf.load_scene(path, overrides).scene
    ours = np.stack([np.asarray(jf.render(scene, jax.random.key(k), spp), np.float64) for k in range(n)])
    theirs = np.stack([jf.render_mitsuba(path, spp, seed=k, overrides=overrides).astype(np.float64)
                       for k in range(n)])
    return ours, theirs


def trilinear_reference(grid: np.ndarray, u: np.ndarray) -> np.ndarray:
    """float64 trilinear interpolation of `grid` (nz, ny, nx, c) at unit-cube points `u` (x, y, z): texel centres
    at (i + 0.5) / n, coordinates clamped to the outermost centres."""
    n = np.array(grid.shape[2::-1], np.float64)  # (nx, ny, nz)
    p = np.clip(u * n - 0.5, 0.0, n - 1)
    i0 = np.minimum(np.floor(p).astype(int), (n - 1).astype(int))
    i1 = np.minimum(i0 + 1, (n - 1).astype(int))
    t = p - i0
    out = 0.0
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                w = (t[0] if dx else 1 - t[0]) * (t[1] if dy else 1 - t[1]) * (t[2] if dz else 1 - t[2])
                ix, iy, iz = ((i1 if d else i0)[k] for k, d in enumerate((dx, dy, dz)))
                out = out + w * grid[iz, iy, ix].astype(np.float64)
    return out


def write_dng(path, cfa, white: int = 4095, black: int = 0) -> None:
    """A minimal uncompressed Bayer (RGGB) DNG 1.4 of the uint16 sensor values `cfa` `(H, W)` (LibRaw needs at least
    ~22 px a side), white level `white`; its colour matrix makes the camera's RGB linear sRGB and its white balance
    neutral, so LibRaw's linear sRGB output is the sensor values over `white` (the reference for the RAW decoder:
    rawpy cannot write a RAW file, and a camera's file is megabytes)."""
    h, w = cfa.shape
    data = np.ascontiguousarray(cfa, '<u2').tobytes()
    entries = []  # (tag, type, count, value bytes)
    def add(tag, typ, vals):
        fmt = {1: 'B', 2: 's', 3: 'H', 4: 'I', 5: 'II', 10: 'ii', 7: 'B'}[typ]
        if typ == 2:
            b = vals.encode() + b'\0'; entries.append((tag, typ, len(b), b)); return
        if typ in (5, 10):
            b = b''.join(struct.pack('<' + fmt, *v) for v in vals); entries.append((tag, typ, len(vals), b)); return
        b = struct.pack('<%d%s' % (len(vals), fmt), *vals); entries.append((tag, typ, len(vals), b))
    add(254, 4, [0]); add(256, 4, [w]); add(257, 4, [h]); add(258, 3, [16]); add(259, 3, [1]); add(262, 3, [32803])
    add(271, 2, "jaxfog"); add(272, 2, "test")
    add(273, 4, [0])  # strip offset, patched
    add(274, 3, [1]); add(277, 3, [1]); add(278, 4, [h]); add(279, 4, [len(data)]); add(284, 3, [1])
    add(33421, 3, [2, 2]); add(33422, 1, [0, 1, 1, 2])
    add(50706, 1, [1, 4, 0, 0]); add(50707, 1, [1, 1, 0, 0]); add(50708, 2, "jaxfog test camera")
    add(50714, 4, [black]); add(50717, 4, [white])
    M = [3.2406, -1.5372, -0.4986, -0.9689, 1.8758, 0.0415, 0.0557, -0.2040, 1.0570]
    add(50721, 10, [(int(round(m * 10000)), 10000) for m in M])  # ColorMatrix1: XYZ -> camera = linear sRGB
    add(50728, 5, [(1, 1), (1, 1), (1, 1)])  # AsShotNeutral
    add(50778, 3, [21])  # CalibrationIlluminant1 D65
    entries.sort()
    n = len(entries)
    ifd_off = 8
    extra_off = ifd_off + 2 + 12 * n + 4
    extra = b''; body = []
    for tag, typ, cnt, b in entries:
        if len(b) <= 4:
            body.append((tag, typ, cnt, b.ljust(4, b'\0')))
        else:
            if len(extra) % 2: extra += b'\0'
            body.append((tag, typ, cnt, struct.pack('<I', extra_off + len(extra)))); extra += b
    if len(extra) % 2: extra += b'\0'
    data_off = extra_off + len(extra)
    out = b'II*\0' + struct.pack('<I', ifd_off) + struct.pack('<H', n)
    for tag, typ, cnt, b in body:
        if tag == 273: b = struct.pack('<I', data_off)
        out += struct.pack('<HHI', tag, typ, cnt) + b
    out += struct.pack('<I', 0) + extra + data
    open(path, 'wb').write(out)
