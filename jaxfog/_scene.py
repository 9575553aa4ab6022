"""The scene: camera, shapes, lights, optional medium, path length; and its packing into stacked arrays.

A `Scene`'s *structure* (how many shapes of which kind, which BSDF kinds, which light kinds, whether there is fog,
`max_depth`) is static Python, so the compiled program contains only what the scene uses. Its physical values are
traced arrays, so changing them never recompiles.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._bsdf import Diffuse, Glass, Mirror
from ._camera import Camera
from ._lights import AreaLight, PointLight, SpotLight
from ._medium import HomogeneousMedium
from ._shapes import Rectangle, Sphere

DIFFUSE, MIRROR, GLASS, EMITTER = 0, 1, 2, 3


class Scene(eqx.Module):
    """Everything the renderer needs.

    **Fields:** `camera`; `shapes`: tuple of `Sphere`/`Rectangle`; `lights`: tuple of `PointLight`/`SpotLight`/
    `AreaLight`; `medium`: a `HomogeneousMedium` or None (no fog: no medium code is compiled); `max_depth`: static int
    >= 1, the longest path in segments from the camera to a light, the light-sampling segment included
    (docs/conventions.md; 8 is the default, 2 is single scattering).
    """

    camera: Camera
    shapes: tuple = ()
    lights: tuple = ()
    medium: HomogeneousMedium | None = None
    max_depth: int = eqx.field(static=True, default=8)

    def __check_init__(self):
        if not isinstance(self.max_depth, int) or self.max_depth < 1:
            raise ValueError(f"max_depth must be an integer >= 1, got {self.max_depth!r}")
        for s in self.shapes:
            if not isinstance(s, (Sphere, Rectangle)):
                raise TypeError(f"shapes must be Sphere or Rectangle, got {type(s).__name__}")
        for light in self.lights:
            if not isinstance(light, (PointLight, SpotLight, AreaLight)):
                raise TypeError(f"lights must be PointLight, SpotLight or AreaLight, got {type(light).__name__}")

    @property
    def delta_lights(self) -> tuple:
        return tuple(lt for lt in self.lights if isinstance(lt, (PointLight, SpotLight)))

    @property
    def area_lights(self) -> tuple:
        return tuple(lt for lt in self.lights if isinstance(lt, AreaLight))

    def replace_medium(self, **values) -> "Scene":
        """A copy with medium values replaced: `sigma_t`, `albedo` (RGB or scalar) and/or `g`."""
        med = self.medium
        if med is None:
            raise ValueError("this scene has no medium")
        new = HomogeneousMedium(
            sigma_t=values.get("sigma_t", med.sigma_t),
            albedo=values.get("albedo", med.albedo),
            phase=type(med.phase)(g=values.get("g", med.phase.g)),
            extent=med.extent,
        )
        return eqx.tree_at(lambda s: s.medium, self, new)


class Packed(NamedTuple):
    """Stacked per-kind geometry and per-shape material arrays (global shape index: spheres, rectangles, emitters).

    `kinds` is a static numpy array (what BSDF code exists is decided in Python); the rest are traced arrays.
    """

    sph_center: Float[Array, "Ns 3"]
    sph_radius: Float[Array, "Ns"]
    rect_center: Float[Array, "Nr 3"]
    rect_u: Float[Array, "Nr 3"]
    rect_v: Float[Array, "Nr 3"]
    rect_normal: Float[Array, "Nr 3"]
    kinds: np.ndarray
    reflectance: Float[Array, "N 3"]
    ior: Float[Array, "N 2"]
    emission: Float[Array, "N 3"]

    @property
    def n_spheres(self) -> int:
        return self.sph_radius.shape[0]

    @property
    def has(self):
        """Set of BSDF kinds present (static)."""
        return set(int(k) for k in self.kinds)


def pack(scene: Scene) -> Packed:
    """Stack the scene's shapes (and area lights, as black emitting rectangles) into arrays for the integrator."""
    spheres = [s for s in scene.shapes if isinstance(s, Sphere)]
    rects = [s for s in scene.shapes if isinstance(s, Rectangle)]
    emitters = list(scene.area_lights)
    ordered = spheres + rects
    kinds, refl, ior, emis = [], [], [], []
    zero3 = jnp.zeros(3, jnp.float32)
    for s in ordered:
        b = s.bsdf
        if isinstance(b, Diffuse):
            kinds.append(DIFFUSE); refl.append(b.reflectance); ior.append(jnp.ones(2, jnp.float32))
        elif isinstance(b, Mirror):
            kinds.append(MIRROR); refl.append(b.reflectance); ior.append(jnp.ones(2, jnp.float32))
        elif isinstance(b, Glass):
            kinds.append(GLASS); refl.append(zero3); ior.append(jnp.stack([b.int_ior, b.ext_ior]))
        else:
            raise TypeError(f"unknown BSDF {type(b).__name__}")
        emis.append(zero3)
    for e in emitters:
        kinds.append(EMITTER); refl.append(zero3); ior.append(jnp.ones(2, jnp.float32)); emis.append(e.radiance)

    def stack(xs, shape):
        return jnp.stack(xs) if xs else jnp.zeros((0,) + shape, jnp.float32)

    all_rects_c = [r.center for r in rects] + [e.center for e in emitters]
    all_rects_u = [r.edge_u for r in rects] + [e.edge_u for e in emitters]
    all_rects_v = [r.edge_v for r in rects] + [e.edge_v for e in emitters]
    all_rects_n = [r.normal for r in rects] + [e.normal for e in emitters]
    return Packed(
        sph_center=stack([s.center for s in spheres], (3,)),
        sph_radius=stack([s.radius for s in spheres], ()),
        rect_center=stack(all_rects_c, (3,)),
        rect_u=stack(all_rects_u, (3,)),
        rect_v=stack(all_rects_v, (3,)),
        rect_normal=stack(all_rects_n, (3,)),
        kinds=np.asarray(kinds, dtype=np.int32),
        reflectance=stack(refl, (3,)),
        ior=stack(ior, (2,)),
        emission=stack(emis, (3,)),
    )
