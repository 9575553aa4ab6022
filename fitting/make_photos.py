"""Synthetic photographs with a known truth: renders pushed through a camera (unknown exposure, Poisson-Gaussian
sensor noise, clipping, the sRGB curve, 8-bit JPEG), with an object the scene file does not describe painted in
and a mask that leaves it out.

    python -m fitting.make_photos [--out data_synthetic/photos] [--exposure 0.5] [--quality 90] [--seed 0]

Makes the worked example of the README's "Fit a photograph" from the shipped targets `spot_fog__mid.exr` and
`spot_fog_low__mid.exr` (jaxfog renders at sigma_t 0.5, g 0.6, albedo 0.9, 256 spp): two JPEGs, one mask and
`manifest.json` with the truth (the exposure included).
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np

from .photo import camera_encode, write_photo

SOURCES = (("data_synthetic/targets/spot_fog__mid.exr", "spot_fog.json", "spot_fog_a.jpg"),
           ("data_synthetic/targets/spot_fog_low__mid.exr", "spot_fog_low.json", "spot_fog_low_b.jpg"))
SIGN = (slice(84, 112), slice(12, 44))
"""Rows and columns of the first photograph covered by an object the scene does not describe (a sign)."""
SIGN_RADIANCE = (0.9, 0.75, 0.2)
"""The sign's linear radiance (a lit yellow board)."""


def make_photos(out: str, exposure: float = 0.5, quality: int = 90, seed: int = 0, photons: float = 20000.0,
                read_noise: float = 0.002) -> dict:
    """Write the worked example into `out`; returns the manifest."""
    import jaxfog

    os.makedirs(out, exist_ok=True)
    rng = np.random.default_rng(seed)
    views, truth = [], None
    for i, (src, scene, name) in enumerate(SOURCES):
        img, meta = jaxfog.read_exr(src)
        truth = json.loads(meta["jaxfog:truth"])
        img = np.array(img, np.float64)
        mask = None
        if i == 0:
            img[SIGN] = SIGN_RADIANCE
            m = np.ones(img.shape[:2])
            m[SIGN[0].start - 2:SIGN[0].stop + 2, SIGN[1].start - 2:SIGN[1].stop + 2] = 0.0
            mask = name.replace(".jpg", "_mask.png")
            write_photo(os.path.join(out, mask), np.repeat(m[:, :, None], 3, axis=2), bits=8)
        code = camera_encode(img, exposure, rng, photons, read_noise)
        write_photo(os.path.join(out, name), code, bits=8, quality=quality)
        views.append({"scene": f"data_synthetic/scenes/{scene}", "photo": f"{out}/{name}",
                      "mask": None if mask is None else f"{out}/{mask}", "source": src})
    manifest = {"truth": {**truth, "exposure": exposure},
                "camera": {"curve": "srgb", "bits": 8, "jpeg_quality": quality, "photons_at_1": photons,
                           "read_noise": read_noise, "seed": seed},
                "views": views,
                "note": "the first photograph shows a sign the scene does not describe; its mask leaves it out"}
    with open(os.path.join(out, "manifest.json"), "w") as f:
        json.dump(manifest, f, indent=1)
    return manifest


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m fitting.make_photos", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default="data_synthetic/photos")
    p.add_argument("--exposure", type=float, default=0.5)
    p.add_argument("--quality", type=int, default=90)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    print(json.dumps(make_photos(args.out, args.exposure, args.quality, args.seed), indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
