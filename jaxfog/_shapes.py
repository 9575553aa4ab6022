"""Shapes: spheres and rectangles, as Modules holding their BSDF, and the pure ray-intersection math.

All shapes of one kind are intersected together as stacked arrays (see `_scene.pack`); a miss is `t = inf`.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._bsdf import AbstractBSDF
from ._math import cross, dot_unrolled, safe_normalize, safe_sqrt

T_MIN = 1e-4
"""Smallest accepted hit distance (scene units): avoids re-hitting the surface a ray starts on."""


def _vec3(x) -> Float[Array, "3"]:
    return jnp.asarray(x, dtype=jnp.float32).reshape(3)


def _scalar(x) -> Float[Array, ""]:
    return jnp.asarray(x, dtype=jnp.float32).reshape(())


class Sphere(eqx.Module):
    """A sphere: `center` (3-vector, scene units), `radius` (> 0, scene units) and its `bsdf`."""

    center: Float[Array, "3"] = eqx.field(converter=_vec3)
    radius: Float[Array, ""] = eqx.field(converter=_scalar)
    bsdf: AbstractBSDF


class Rectangle(eqx.Module):
    """A rectangle: `center`, perpendicular full edge vectors `edge_u`, `edge_v` (scene units) and its `bsdf`.

    Its front face (the side a one-sided BSDF or emitter works on) faces `normalize(cross(edge_u, edge_v))`.
    """

    center: Float[Array, "3"] = eqx.field(converter=_vec3)
    edge_u: Float[Array, "3"] = eqx.field(converter=_vec3)
    edge_v: Float[Array, "3"] = eqx.field(converter=_vec3)
    bsdf: AbstractBSDF

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
