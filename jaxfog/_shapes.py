"""Shapes: spheres and rectangles, as Modules holding their BSDF, and the pure ray-intersection math.

All shapes of one kind are intersected together as stacked arrays (see `_scene.pack`); a miss is `t = inf`.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._bsdf import AbstractBSDF
from ._math import cross, dot_unrolled, safe_normalize, safe_sqrt
from ._validate import NON_NEGATIVE, check_range, check_vector, concrete_values

T_MIN = 1e-4
"""Smallest accepted hit distance (scene units): avoids re-hitting the surface a ray starts on."""


def _vec3(x) -> Float[Array, "3"]:
    return jnp.asarray(x, dtype=jnp.float32).reshape(3)


def _scalar(x) -> Float[Array, ""]:
    return jnp.asarray(x, dtype=jnp.float32).reshape(())


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


class Sphere(eqx.Module):
    """A sphere: `center` (3-vector, scene units, finite), `radius` (scene units, > 0; 0 is accepted in Python as a
    placeholder that is never seen but keeps a scene's structure, i.e. its compiled program; scene files need > 0)
    and its `bsdf`."""

    center: Float[Array, "3"] = eqx.field(converter=_vec3)
    radius: Float[Array, ""] = eqx.field(converter=_scalar)
    bsdf: AbstractBSDF

    def __check_init__(self):
        check_vector("Sphere", "center", self.center, nonzero=False)
        check_range("Sphere", "radius", self.radius, NON_NEGATIVE)


class Rectangle(eqx.Module):
    """A rectangle: `center`, perpendicular full edge vectors `edge_u`, `edge_v` (scene units; finite, non-zero) and
    its `bsdf`.

    Its front face (the side a one-sided BSDF or emitter works on) faces `normalize(cross(edge_u, edge_v))`.
    """

    center: Float[Array, "3"] = eqx.field(converter=_vec3)
    edge_u: Float[Array, "3"] = eqx.field(converter=_vec3)
    edge_v: Float[Array, "3"] = eqx.field(converter=_vec3)
    bsdf: AbstractBSDF

    def __check_init__(self):
        check_vector("Rectangle", "center", self.center, nonzero=False)
        check_vector("Rectangle", "edge_u", self.edge_u)
        check_vector("Rectangle", "edge_v", self.edge_v)
        check_perpendicular("Rectangle", self.edge_u, self.edge_v)

    @property
    def normal(self) -> Float[Array, "3"]:
        return safe_normalize(cross(self.edge_u, self.edge_v))


def intersect_spheres(o, d, center, radius):
    """Nearest hit distances (> T_MIN, else inf) of the ray `o + t d` (unit `d`) with spheres `center` (N, 3), `radius` (N,).

    Uses the numerically careful form (Ray Tracing Gems ch. 7): the discriminant from the ray's closest approach.
    """
    oc = o[None, :] - center
    b = dot_unrolled(oc, d[None, :])
    perp = oc - b[:, None] * d[None, :]
    disc = radius * radius - dot_unrolled(perp, perp)
    hit = disc >= 0
    root = safe_sqrt(disc)
    t0 = -b - root
    t1 = -b + root
    t = jnp.where(t0 > T_MIN, t0, jnp.where(t1 > T_MIN, t1, jnp.inf))
    return jnp.where(hit, t, jnp.inf)


def intersect_rectangles(o, d, center, edge_u, edge_v, normal):
    """Hit distances (> T_MIN, else inf) of the ray `o + t d` with rectangles given as stacked (N, 3) arrays."""
    denom = dot_unrolled(normal, d[None, :])
    ok = jnp.abs(denom) > 1e-12
    t = dot_unrolled(center - o[None, :], normal) / jnp.where(ok, denom, 1.0)
    p = o[None, :] + t[:, None] * d[None, :] - center
    a = dot_unrolled(p, edge_u) / dot_unrolled(edge_u, edge_u)
    b = dot_unrolled(p, edge_v) / dot_unrolled(edge_v, edge_v)
    inside = ok & (t > T_MIN) & (jnp.abs(a) <= 0.5) & (jnp.abs(b) <= 0.5)
    return jnp.where(inside, t, jnp.inf)
