"""Shapes behind one interface (`AbstractShape`): nearest hit, any hit, bounding box, area sampling.

- `intersect(o, d, t_max) -> ShapeHit(t, found, prim)`: the nearest hit of the ray `o + t d` (unit `d`) at a
  distance above `T_MIN`, and `surface(o, d, hit) -> SurfacePoint(t, n)`: the (differentiable) distance and the
  front normal there. Two steps, as Mitsuba's preliminary intersection and surface interaction: the tracer finds
  the nearest of all shapes' hits first and asks for the surface of the one it keeps;
- `any_hit(o, d, t_max)`: whether anything of the shape lies on the ray at a distance in (`T_MIN`, `t_max`): the
  shadow test;
- `bounds()`: the axis-aligned box `(lo, hi)` that contains the shape;
- `sample_area(u) -> AreaSample(p, n, pdf)` and `pdf_area(p)`: a point drawn uniformly by area (what an emitting
  shape needs: `solid_angle_pdf` turns the density per area into one per solid angle seen from a point);
- `box_relation(lo, hi)`: where the shape lies relative to a box (`"inside"`, `"outside"`, `"straddles"`), for the
  scene's check of glass objects against a bounded fog;
- `bsdf`: its BSDF; `stacked` (static): whether the scene's shapes of the class are intersected together.

The tracer asks only this interface (`_integrator.intersect`, `_integrator.occluded`); `_scene.pack` stacks the shapes
of a `stacked` class (each array field gets a leading axis) and the tracer `vmap`s their methods over the stack, one
vector operation for all the scene's spheres; a shape whose arrays differ in size from instance to instance (a mesh's
BVH) is intersected on its own. Everything is written for one ray.

Adding a shape: one final class (here, or in its own module as `Mesh` in `_mesh.py`) and its registration: an entry
in `_scene_io.SHAPES`, its Mitsuba counterpart in `_mitsuba`, and `__init__.py` (see `notes/ARCHITECTURE.md`).
"""

import abc
from typing import ClassVar, NamedTuple

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from equinox import AbstractClassVar, AbstractVar
from jaxtyping import Array, Bool, Float, Int

from ._bsdf import AbstractBSDF
from ._math import INV_PI, cross, dot_unrolled, safe_div, safe_norm, safe_normalize, safe_sqrt
from ._sampling import to_direction, uniform_sphere_polar
from ._validate import POSITIVE, check_range, check_vector, concrete_values, polygons_in_box, sphere_in_box

T_MIN = 1e-4
"""Smallest accepted hit distance (scene units): avoids re-hitting the surface a ray starts on."""


def _vec3(x) -> Float[Array, "3"]:
    return jnp.asarray(x, dtype=jnp.float32).reshape(3)


def _scalar(x) -> Float[Array, ""]:
    return jnp.asarray(x, dtype=jnp.float32).reshape(())


class ShapeHit(NamedTuple):
    """The nearest hit of a ray with one shape, before its surface quantities: `t` (scene units, > `T_MIN`; inf where
    the ray misses the shape, and possibly inf beyond `t_max`), `found` (a hit closer than `t_max`) and `prim`
    (int32: which part of the shape was hit, for `surface`: a mesh's triangle slot; 0 for a sphere or rectangle)."""

    t: Float[Array, ""]
    found: Bool[Array, ""]
    prim: Int[Array, ""]


class SurfacePoint(NamedTuple):
    """Where a ray meets a shape: the distance `t` (scene units; a mesh's recomputed from its triangle's plane, so
    that it differentiates like an analytic shape's) and the unit front normal `n` (a smooth mesh's shading normal
    on the geometric front side)."""

    t: Float[Array, ""]
    n: Float[Array, "3"]


class AreaSample(NamedTuple):
    """A point `p` on a shape's surface, the unit front normal `n` there, and the density `pdf` with which it was
    drawn, per unit area (1/scene unit^2)."""

    p: Float[Array, "3"]
    n: Float[Array, "3"]
    pdf: Float[Array, ""]


class AbstractShape(eqx.Module):
    """A surface in the scene, with its BSDF. Concrete shapes are final.

    A ray is `o + t d` with a unit direction `d`; distances are in scene units. Geometry is not differentiated
    through the hit point's position on a mesh (see `_mesh`); analytic shapes' distances and normals are plain JAX.
    """

    bsdf: AbstractVar[AbstractBSDF]
    stacked: AbstractClassVar[bool]
    """True: the scene's shapes of this class are stacked into one Module whose array fields have a leading axis,
    and the tracer `vmap`s `intersect`, `surface` and `any_hit` over it (small analytic shapes: one vector operation
    for all), keeping the distance of `intersect` (the `surface` of a stacked class returns `hit.t` unchanged);
    False: each is intersected on its own (a mesh, whose BVH's size differs from mesh to mesh)."""

    @abc.abstractmethod
    def intersect(self, o: Float[Array, "3"], d: Float[Array, "3"], t_max: Float[Array, ""]) -> ShapeHit:
        """The nearest hit at a distance above `T_MIN` (`found`: closer than `t_max`, which a shape may use to stop
        early)."""

    @abc.abstractmethod
    def surface(self, o: Float[Array, "3"], d: Float[Array, "3"], hit: ShapeHit) -> SurfacePoint:
        """The distance and front normal where the ray meets the shape at `hit` (one of this shape's hits; finite
        values, never used, where the ray misses: `t = inf`)."""

    @abc.abstractmethod
    def any_hit(self, o: Float[Array, "3"], d: Float[Array, "3"], t_max: Float[Array, ""]) -> Bool[Array, ""]:
        """Whether the ray meets the shape at a distance in (`T_MIN`, `t_max`): the shadow test (may stop at the
        first hit found)."""

    @abc.abstractmethod
    def bounds(self) -> tuple[Float[Array, "3"], Float[Array, "3"]]:
        """`(lo, hi)`: an axis-aligned box (scene units) that contains the shape."""

    @abc.abstractmethod
    def sample_area(self, u: Float[Array, "2"]) -> AreaSample:
        """A point on the surface drawn uniformly by area from two uniforms `u` in [0, 1), with its front normal
        and its density per unit area (`1 / area`)."""

    @abc.abstractmethod
    def pdf_area(self, p: Float[Array, "3"]) -> Float[Array, ""]:
        """The density per unit area with which `sample_area` draws the point `p` of the surface."""

    @abc.abstractmethod
    def box_relation(self, lo, hi) -> str | None:
        """Where the shape lies relative to the axis-aligned box `[lo, hi]` (concrete values, checked on the host):
        `"inside"` (wholly; touching allowed), `"outside"` (nothing strictly inside the box) or `"straddles"`; None
        when the shape's values are traced (nothing to check)."""


def solid_angle_pdf(pdf_area: Float[Array, ""], dist2: Float[Array, ""], cos_l: Float[Array, ""]) -> Float[Array, ""]:
    """A density per unit area at a surface point turned into one per solid angle seen from a point at the squared
    distance `dist2`, where `cos_l` is the cosine between the surface's normal and the direction back to the viewer:
    `pdf_area dist2 / cos_l` (1/sr), 0 where `cos_l <= 0` (the point's back face, or grazing)."""
    front = cos_l > 0
    return jnp.where(front, safe_div(pdf_area * dist2, jnp.where(front, cos_l, 1.0)), 0.0)


# ------------------------------------------------------------------------------------------------------- sphere
def sphere_distance(o, d, center, radius) -> Float[Array, ""]:
    """Nearest hit distance (> T_MIN, else inf) of the ray `o + t d` (unit `d`) with a sphere.

    Uses the numerically careful form (Ray Tracing Gems ch. 7): the discriminant from the ray's closest approach.
    """
    oc = o - center
    b = dot_unrolled(oc, d)
    perp = oc - b * d
    disc = radius * radius - dot_unrolled(perp, perp)
    hit = disc >= 0
    root = safe_sqrt(disc)
    t0 = -b - root
    t1 = -b + root
    t = jnp.where(t0 > T_MIN, t0, jnp.where(t1 > T_MIN, t1, jnp.inf))
    return jnp.where(hit, t, jnp.inf)


class Sphere(AbstractShape):
    """A sphere: `center` (3-vector, scene units, finite), `radius` (scene units, > 0) and its `bsdf`. Its front face
    is the outside."""

    center: Float[Array, "3"] = eqx.field(converter=_vec3)
    radius: Float[Array, ""] = eqx.field(converter=_scalar)
    bsdf: AbstractBSDF
    stacked: ClassVar[bool] = True

    def __check_init__(self):
        check_vector("Sphere", "center", self.center, nonzero=False)
        check_range("Sphere", "radius", self.radius, POSITIVE)

    def intersect(self, o, d, t_max) -> ShapeHit:
        t = sphere_distance(o, d, self.center, self.radius)
        return ShapeHit(t, t < t_max, jnp.int32(0))

    def surface(self, o, d, hit) -> SurfacePoint:
        p = o + jnp.where(jnp.isfinite(hit.t), hit.t, 0.0) * d  # double where: no inf * 0 on a miss
        return SurfacePoint(hit.t, safe_normalize(p - self.center))

    def any_hit(self, o, d, t_max):
        return sphere_distance(o, d, self.center, self.radius) < t_max

    def bounds(self):
        return self.center - self.radius, self.center + self.radius

    def sample_area(self, u) -> AreaSample:
        n = to_direction(uniform_sphere_polar(u[0]), u[1], jnp.array([0.0, 0.0, 1.0], jnp.float32))
        return AreaSample(self.center + self.radius * n, n, self.pdf_area(self.center))

    def pdf_area(self, p):
        return 0.25 * INV_PI / (self.radius * self.radius)

    def box_relation(self, lo, hi):
        vals = concrete_values(self.center, self.radius, lo, hi)
        return None if vals is None else sphere_in_box(*vals)


# ---------------------------------------------------------------------------------------------------- rectangle
PERPENDICULAR_TOLERANCE = 1e-5
"""Largest `|dot(edge_u, edge_v)| / (|edge_u| |edge_v|)` of a rectangle's edges (float32 edges of a rotated
rectangle are perpendicular to ~1e-7; the scene files check their float64 values to 1e-6)."""


def check_perpendicular(owner: str, edge_u, edge_v) -> None:
    """Raise `ValueError` unless the (concrete) edges are perpendicular to `PERPENDICULAR_TOLERANCE`."""
    vals = concrete_values(edge_u, edge_v)
    if vals is None:
        return
    u, v = vals
    d = float(u @ v)
    if abs(d) > PERPENDICULAR_TOLERANCE * float(np.linalg.norm(u) * np.linalg.norm(v)):
        raise ValueError(f"{owner}.edge_v = {v.tolist()} is not perpendicular to edge_u = {u.tolist()} (dot product "
                         f"{d:.6g}); expected dot(edge_u, edge_v) = 0 (relative tolerance {PERPENDICULAR_TOLERANCE:g})")


def rectangle_distance(o, d, center, edge_u, edge_v, normal) -> Float[Array, ""]:
    """Hit distance (> T_MIN, else inf) of the ray `o + t d` with the rectangle `center`, full edges `edge_u`,
    `edge_v`, unit `normal` (either face)."""
    denom = dot_unrolled(normal, d)
    ok = jnp.abs(denom) > 1e-12
    t = dot_unrolled(center - o, normal) / jnp.where(ok, denom, 1.0)
    p = o + t * d - center
    a = dot_unrolled(p, edge_u) / dot_unrolled(edge_u, edge_u)
    b = dot_unrolled(p, edge_v) / dot_unrolled(edge_v, edge_v)
    inside = ok & (t > T_MIN) & (jnp.abs(a) <= 0.5) & (jnp.abs(b) <= 0.5)
    return jnp.where(inside, t, jnp.inf)


class Rectangle(AbstractShape):
    """A rectangle: `center`, perpendicular full edge vectors `edge_u`, `edge_v` (scene units; finite, non-zero) and
    its `bsdf`.

    Its front face (the side a one-sided BSDF or emitter works on) faces `normalize(cross(edge_u, edge_v))`.
    """

    center: Float[Array, "3"] = eqx.field(converter=_vec3)
    edge_u: Float[Array, "3"] = eqx.field(converter=_vec3)
    edge_v: Float[Array, "3"] = eqx.field(converter=_vec3)
    bsdf: AbstractBSDF
    stacked: ClassVar[bool] = True

    def __check_init__(self):
        check_vector("Rectangle", "center", self.center, nonzero=False)
        check_vector("Rectangle", "edge_u", self.edge_u)
        check_vector("Rectangle", "edge_v", self.edge_v)
        check_perpendicular("Rectangle", self.edge_u, self.edge_v)

    @property
    def normal(self) -> Float[Array, "3"]:
        """The unit front normal `normalize(cross(edge_u, edge_v))`."""
        return safe_normalize(cross(self.edge_u, self.edge_v))

    @property
    def area(self) -> Float[Array, ""]:
        """`|cross(edge_u, edge_v)|` (scene units^2)."""
        return safe_norm(cross(self.edge_u, self.edge_v))

    def intersect(self, o, d, t_max) -> ShapeHit:
        t = rectangle_distance(o, d, self.center, self.edge_u, self.edge_v, self.normal)
        return ShapeHit(t, t < t_max, jnp.int32(0))

    def surface(self, o, d, hit) -> SurfacePoint:
        return SurfacePoint(hit.t, self.normal)

    def any_hit(self, o, d, t_max):
        return rectangle_distance(o, d, self.center, self.edge_u, self.edge_v, self.normal) < t_max

    def bounds(self):
        half = 0.5 * (jnp.abs(self.edge_u) + jnp.abs(self.edge_v))
        return self.center - half, self.center + half

    def sample_area(self, u) -> AreaSample:
        p = self.center + (u[0] - 0.5) * self.edge_u + (u[1] - 0.5) * self.edge_v
        return AreaSample(p, self.normal, self.pdf_area(p))

    def pdf_area(self, p):
        return 1.0 / self.area

    def box_relation(self, lo, hi):
        vals = concrete_values(self.center, self.edge_u, self.edge_v, lo, hi)
        if vals is None:
            return None
        c, u, v, lo, hi = vals
        corners = [c + 0.5 * (a * u + b * v) for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
        return polygons_in_box(np.asarray([corners]), lo, hi)
