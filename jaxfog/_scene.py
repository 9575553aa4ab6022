"""The scene: camera, shapes, lights, optional medium, path length; and its packing into groups of shapes.

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

from ._bsdf import AbstractBSDF, Glass
from ._camera import Camera
from ._lights import AbstractAreaLight, AbstractLight, AbstractPointLikeLight
from ._medium import AbstractMedium
from ._shapes import AbstractShape
from ._validate import RR_DEPTH_RANGE, check_range

EMITTER_KIND = -1
"""`Packed.bsdf_kind` of the black shapes that stand for area lights."""


class Scene(eqx.Module):
    """Everything the renderer needs.

    **Fields:** `camera`; `shapes`: tuple of shapes (`Sphere`, `Rectangle`, `Mesh`: any `AbstractShape`; a glass
    one wholly inside or wholly outside the medium's `bounds`, if it has a box); `lights`: tuple of lights
    (`PointLight`, `SpotLight`, `AreaLight`, `DirectionalLight`); `medium`: a medium (`HomogeneousMedium`, `HeightFog`, `GridMedium`) or None
    (no fog: no medium code is compiled); `max_depth`: static int >= 1, the longest path in segments from the camera
    to a light, the light-sampling segment included (docs/conventions.md; 8 is the default, 2 is single scattering),
    or -1 for paths of any length, ended by Russian roulette from the `rr_depth`-th vertex on (static int in
    [1, 1024], `RR_DEPTH_RANGE`; default 5, as in Mitsuba; fixed depths use no Russian roulette).
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
        if not isinstance(self.rr_depth, int) or isinstance(self.rr_depth, bool):
            raise ValueError(f"Scene.rr_depth must be an integer in {RR_DEPTH_RANGE.text()}, got {self.rr_depth!r}")
        # a hard range (no --force): with max_depth -1 every path that neither escapes nor is absorbed runs to it
        check_range("Scene", "rr_depth", self.rr_depth, RR_DEPTH_RANGE)
        for s in self.shapes:
            if not isinstance(s, AbstractShape):
                raise TypeError(f"shapes must be shapes (Sphere, Rectangle, Mesh), got {type(s).__name__}")
            if not isinstance(s.bsdf, AbstractBSDF):
                raise TypeError(f"a shape's bsdf must be a BSDF (Diffuse, Mirror, Glass), got {type(s.bsdf).__name__}")
        for light in self.lights:
            if not isinstance(light, AbstractLight):
                raise TypeError(f"lights must be lights (PointLight, SpotLight, AreaLight, DirectionalLight), got {type(light).__name__}")
        if self.medium is not None and not isinstance(self.medium, AbstractMedium):
            raise TypeError(f"medium must be a medium (HomogeneousMedium, HeightFog, GridMedium) or None, got {type(self.medium).__name__}")
        self._check_glass_in_fog_box()

    def _check_glass_in_fog_box(self):
        """Glass objects lie wholly inside or wholly outside a bounded fog's box (the fog does not enter glass, and
        a glass object across the box's face would need the fog inside it; docs/conventions.md)."""
        box = None if self.medium is None else self.medium.bounds
        if box is None:
            return
        for i, s in enumerate(self.shapes):
            if isinstance(s.bsdf, Glass) and s.box_relation(*box) == "straddles":
                lo, hi = (np.asarray(b, np.float64).tolist() for b in box)
                raise ValueError(f"Scene.shapes[{i}]: a glass {type(s).__name__} straddles a face of the medium's "
                                 f"bounds (min {lo}, max {hi}); expected a glass object wholly inside or wholly "
                                 f"outside the fog's box (the fog does not enter glass)")

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
        """Lights that are also surfaces (`AbstractAreaLight`): their shapes are intersected with the scene's."""
        return tuple(lt for lt in self.lights if isinstance(lt, AbstractAreaLight))

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


class ShapeGroup(NamedTuple):
    """Shapes intersected together: `shapes`, one Module (of a `stacked` class: its array fields with a leading
    axis of `size` shapes, `vmap`-ed over; else one shape), with the global shape indices `start .. start + size -
    1` (static)."""

    shapes: AbstractShape
    start: int
    size: int
    stacked: bool


class Packed(NamedTuple):
    """The scene's geometry as groups of shapes, and its BSDFs grouped by type.

    Global shape index: the shapes of each `stacked` class (in order of the classes' first appearance; a class's
    scene shapes first, then the area lights' shapes of that class), then the others one by one (the scene's in
    order, then the area lights'). `groups`: `ShapeGroup`s in that order, the stacked ones first. `bsdf_types` (the
    BSDF classes present, in order of appearance), `bsdf_kind` (per shape: the index of its BSDF class in
    `bsdf_types`, or `EMITTER_KIND` for an area light's shape) and `emitter_shape` (per area light, in
    `scene.area_lights` order: its shape index) are static; `bsdfs[k]` is one Module of type `bsdf_types[k]`
    whose array fields have a leading shape axis (shapes of other types hold a copy of the first one's values,
    never used). A scene without shapes of a class traces none of that class's code.
    """

    groups: tuple
    bsdf_types: tuple
    bsdf_kind: np.ndarray
    bsdfs: tuple
    emitter_shape: tuple

    @property
    def n_shapes(self) -> int:
        return len(self.bsdf_kind)


def _stack(shapes: list) -> AbstractShape:
    """One Module of the shapes' class whose array fields are the shapes' stacked along a new leading axis (the
    BSDFs are left out, as None: `Packed.bsdfs` holds them); built without `__init__`, so without its checks."""
    geometry = [eqx.tree_at(lambda s: s.bsdf, s, None) for s in shapes]
    return jax.tree.map(lambda *xs: jnp.stack(xs), *geometry)


def pack(scene: Scene) -> Packed:
    """The scene's shapes and its area lights' shapes (black, `EMITTER_KIND`) as `ShapeGroup`s for the tracer."""
    emitters = [lt.shape for lt in scene.area_lights]
    entries = [(s, False) for s in scene.shapes] + [(s, True) for s in emitters]  # (shape, is an emitter)
    classes = []
    for s, _ in entries:
        if type(s).stacked and type(s) not in classes:
            classes.append(type(s))
    ordered = [e for c in classes for e in entries if type(e[0]) is c] + [e for e in entries if not type(e[0]).stacked]
    groups, start = [], 0
    for c in classes:
        members = [s for s, _ in ordered if type(s) is c]
        groups.append(ShapeGroup(_stack(members), start, len(members), True))
        start += len(members)
    for s, _ in ordered[start:]:
        groups.append(ShapeGroup(s, start, 1, False))
        start += 1
    surfaces = [s for s, emitter in ordered if not emitter]
    types = []
    for s in surfaces:
        if type(s.bsdf) not in types:
            types.append(type(s.bsdf))
    kind = [EMITTER_KIND if emitter else types.index(type(s.bsdf)) for s, emitter in ordered]
    bsdfs = []
    for t in types:
        filler = next(s.bsdf for s in surfaces if type(s.bsdf) is t)
        per_shape = [s.bsdf if (not emitter and type(s.bsdf) is t) else filler for s, emitter in ordered]
        bsdfs.append(jax.tree.map(lambda *xs: jnp.stack(xs), *per_shape))
    position = {id(s): i for i, (s, _) in enumerate(ordered)}
    return Packed(
        groups=tuple(groups),
        bsdf_types=tuple(types),
        bsdf_kind=np.asarray(kind, dtype=np.int32),
        bsdfs=tuple(bsdfs),
        emitter_shape=tuple(position[id(s)] for s in emitters),
    )
