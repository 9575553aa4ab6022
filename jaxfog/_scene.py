"""The scene: camera, shapes, lights, optional medium, path length; and its packing into stacked arrays.

A `Scene`'s *structure* (how many shapes of which kind, which BSDF kinds, which light kinds, whether there is fog,
`max_depth`) is static Python, so the compiled program contains only what the scene uses. Its physical values are
traced arrays, so changing them never recompiles.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._bsdf import AbstractBSDF
from ._camera import Camera
from ._lights import AbstractLight, AbstractPointLikeLight, AreaLight
from ._medium import AbstractMedium
from ._mesh import Mesh
from ._shapes import Rectangle, Sphere

EMITTER_KIND = -1
"""`Packed.bsdf_kind` of the black rectangles that stand for area lights."""


class Scene(eqx.Module):
    """Everything the renderer needs.

    **Fields:** `camera`; `shapes`: tuple of `Sphere`/`Rectangle`/`Mesh`; `lights`: tuple of lights (`PointLight`,
    `SpotLight`, `AreaLight`, `DirectionalLight`); `medium`: a medium (`HomogeneousMedium`, `HeightFog`) or None
    (no fog: no medium code is compiled); `max_depth`: static int >= 1, the longest path in segments from the camera
    to a light, the light-sampling segment included (docs/conventions.md; 8 is the default, 2 is single scattering),
    or -1 for paths of any length, ended by Russian roulette from the `rr_depth`-th vertex on (static int >= 1,
    default 5, as in Mitsuba; fixed depths use no Russian roulette).
    """

    camera: Camera
    shapes: tuple = ()
    lights: tuple = ()
    medium: AbstractMedium | None = None
    max_depth: int = eqx.field(static=True, default=8)
    rr_depth: int = eqx.field(static=True, default=5)

    def __check_init__(self):
        if not isinstance(self.max_depth, int) or isinstance(self.max_depth, bool) or not (
                self.max_depth >= 1 or self.max_depth == -1):
            raise ValueError(f"Scene.max_depth must be an integer >= 1, or -1 (no limit), got {self.max_depth!r}")
        if not isinstance(self.rr_depth, int) or isinstance(self.rr_depth, bool) or self.rr_depth < 1:
            raise ValueError(f"Scene.rr_depth must be an integer >= 1, got {self.rr_depth!r}")
        for s in self.shapes:
            if not isinstance(s, (Sphere, Rectangle, Mesh)):
                raise TypeError(f"shapes must be Sphere, Rectangle or Mesh, got {type(s).__name__}")
            if not isinstance(s.bsdf, AbstractBSDF):
                raise TypeError(f"a shape's bsdf must be a BSDF (Diffuse, Mirror, Glass), got {type(s.bsdf).__name__}")
        for light in self.lights:
            if not isinstance(light, AbstractLight):
                raise TypeError(f"lights must be lights (PointLight, SpotLight, AreaLight, DirectionalLight), got {type(light).__name__}")
        if self.medium is not None and not isinstance(self.medium, AbstractMedium):
            raise TypeError(f"medium must be a medium (HomogeneousMedium, HeightFog) or None, got {type(self.medium).__name__}")

    @property
    def delta_lights(self) -> tuple:
        """Lights reached by next-event estimation only (point, spot, directional)."""
        return tuple(lt for lt in self.lights if lt.is_delta)

    @property
    def point_lights(self) -> tuple:
        """Delta lights at a point (point, spot): the targets of equiangular sampling and the light-angle lobe."""
        return tuple(lt for lt in self.lights if isinstance(lt, AbstractPointLikeLight))

    @property
    def area_lights(self) -> tuple:
        return tuple(lt for lt in self.lights if isinstance(lt, AreaLight))

    def replace_medium(self, **values) -> "Scene":
        """A copy with medium values replaced, e.g. `sigma_t`, `albedo` (RGB or scalar) and/or the phase function's
        parameters (`g`). The new medium is built (and validated) by its constructor: `g=1.0` raises ValueError."""
        med = self.medium
        if med is None:
            raise ValueError("this scene has no medium")
        phase_fields = {f.name for f in dataclasses.fields(med.phase)}
        medium_fields = {f.name for f in dataclasses.fields(med)} - {"phase"}
        unknown = set(values) - phase_fields - medium_fields
        if unknown:
            raise ValueError(f"replace_medium: unknown parameter(s) {sorted(unknown)}; this medium has "
                             f"{sorted(medium_fields | phase_fields)}")
        phase = type(med.phase)(**{k: values.get(k, getattr(med.phase, k)) for k in phase_fields})
        kw = {k: values.get(k, getattr(med, k)) for k in medium_fields}
        return eqx.tree_at(lambda s: s.medium, self, type(med)(phase=phase, **kw))


class Packed(NamedTuple):
    """The scene's geometry as stacked arrays, and its BSDFs grouped by type (global shape index: spheres,
    rectangles, one black rectangle per area light, then one index per mesh).

    `bsdf_types` (the BSDF classes present, in order of appearance), `bsdf_kind` (per shape: the index of its BSDF
    class in `bsdf_types`, or `EMITTER_KIND`) and `emitter_shape` (per area light, in `scene.area_lights` order: its
    shape index) are static; `bsdfs[k]` is one Module of type `bsdf_types[k]` whose array fields have a leading
    shape axis (shapes of other types hold a copy of the first one's values, never used). `meshes`: the scene's
    `Mesh` Modules (each with its own BVH) and `mesh_shape` (static): each one's shape index. A scene without
    meshes has `meshes = ()`, and no mesh code is traced.
    """

    sph_center: Float[Array, "Ns 3"]
    sph_radius: Float[Array, "Ns"]
    rect_center: Float[Array, "Nr 3"]
    rect_u: Float[Array, "Nr 3"]
    rect_v: Float[Array, "Nr 3"]
    rect_normal: Float[Array, "Nr 3"]
    bsdf_types: tuple
    bsdf_kind: np.ndarray
    bsdfs: tuple
    emitter_shape: tuple
    meshes: tuple = ()
    mesh_shape: tuple = ()

    @property
    def n_spheres(self) -> int:
        return self.sph_radius.shape[0]

    @property
    def n_shapes(self) -> int:
        return len(self.bsdf_kind)


def pack(scene: Scene) -> Packed:
    """Stack the scene's shapes (and area lights, as black emitting rectangles) into arrays for the integrator."""
    spheres = [s for s in scene.shapes if isinstance(s, Sphere)]
    rects = [s for s in scene.shapes if isinstance(s, Rectangle)]
    meshes = [s for s in scene.shapes if isinstance(s, Mesh)]
    emitters = list(scene.area_lights)
    ordered = spheres + rects
    types = []
    for s in ordered + meshes:
        if type(s.bsdf) not in types:
            types.append(type(s.bsdf))
    kind = ([types.index(type(s.bsdf)) for s in ordered] + [EMITTER_KIND] * len(emitters)
            + [types.index(type(s.bsdf)) for s in meshes])
    bsdfs = []
    for t in types:
        filler = next(s.bsdf for s in ordered + meshes if type(s.bsdf) is t)
        per_shape = ([s.bsdf if type(s.bsdf) is t else filler for s in ordered] + [filler] * len(emitters)
                     + [s.bsdf if type(s.bsdf) is t else filler for s in meshes])
        bsdfs.append(jax.tree.map(lambda *xs: jnp.stack(xs), *per_shape))

    def stack(xs, shape):
        return jnp.stack(xs) if xs else jnp.zeros((0,) + shape, jnp.float32)

    flat = rects + emitters
    return Packed(
        sph_center=stack([s.center for s in spheres], (3,)),
        sph_radius=stack([s.radius for s in spheres], ()),
        rect_center=stack([r.center for r in flat], (3,)),
        rect_u=stack([r.edge_u for r in flat], (3,)),
        rect_v=stack([r.edge_v for r in flat], (3,)),
        rect_normal=stack([r.normal for r in flat], (3,)),
        bsdf_types=tuple(types),
        bsdf_kind=np.asarray(kind, dtype=np.int32),
        bsdfs=tuple(bsdfs),
        emitter_shape=tuple(len(ordered) + j for j in range(len(emitters))),
        meshes=tuple(meshes),
        mesh_shape=tuple(len(ordered) + len(emitters) + j for j in range(len(meshes))),
    )
