"""Pinhole camera (docs/conventions.md): `fov` is the full horizontal field of view; pixel (0, 0) is the top-left."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._math import cross, safe_normalize
from ._validate import FOV_RANGE, check_range, check_vector, concrete_values


def _vec3(x) -> Float[Array, "3"]:
    return jnp.asarray(x, dtype=jnp.float32).reshape(3)


def _scalar(x) -> Float[Array, ""]:
    return jnp.asarray(x, dtype=jnp.float32).reshape(())


class Camera(eqx.Module):
    """Pinhole camera at `origin` looking at `target` (another point) with `up` (scene units; finite, `up` not
    parallel to `target - origin`), horizontal `fov` in degrees in (0, 180), image `width` x `height` pixels,
    integers >= 1 (static: a new resolution compiles a new program).

    `near_clip` (scene units, finite, >= 0; default 0, a physical camera): each ray starts where it crosses the plane
    `near_clip` ahead of the camera along its axis, `near_clip / cos(angle to the axis)` from `origin`, as Mitsuba 3's
    perspective camera does (its default is 0.01). It matters only in fog, where it leaves out that much optical
    depth. Static: another value compiles another program."""

    origin: Float[Array, "3"] = eqx.field(converter=_vec3)
    target: Float[Array, "3"] = eqx.field(converter=_vec3)
    up: Float[Array, "3"] = eqx.field(converter=_vec3)
    fov: Float[Array, ""] = eqx.field(converter=_scalar)
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)
    near_clip: float = eqx.field(static=True, default=0.0, converter=float)

    def __check_init__(self):
        if not (np.isfinite(self.near_clip) and self.near_clip >= 0):
            raise ValueError(f"Camera: near_clip must be finite and >= 0 (scene units), got {self.near_clip!r}")
        for name in ("width", "height"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"Camera: {name} must be a positive integer (pixels), got {v!r}")
        check_vector("Camera", "origin", self.origin, nonzero=False)
        check_vector("Camera", "target", self.target, nonzero=False)
        check_vector("Camera", "up", self.up)
        check_range("Camera", "fov", self.fov, FOV_RANGE)
        vals = concrete_values(self.origin, self.target, self.up)
        if vals is not None:
            o, t, up = vals
            view = t - o
            if not np.any(view != 0):
                raise ValueError(f"Camera.target = {t.tolist()} equals origin; expected a point other than origin")
            if np.linalg.norm(np.cross(up, view)) <= 1e-6 * np.linalg.norm(up) * np.linalg.norm(view):
                raise ValueError(f"Camera.up = {up.tolist()} is parallel to the view direction target - origin = "
                                 f"{view.tolist()}; expected an up vector not parallel to it")

    def resized(self, width: int, height: int) -> "Camera":
        """The same camera (pose, field of view, clip plane) at another resolution."""
        return Camera(origin=self.origin, target=self.target, up=self.up, fov=self.fov, width=width, height=height,
                      near_clip=self.near_clip)

    def film_position(self, point: Float[Array, "3"]) -> tuple[Float[Array, "2"], Float[Array, ""]]:
        """The inverse of `generate_ray`: the film position `(x, y)` in pixels at which `point` (scene units) is
        seen, and whether it lies in front of the camera (the position is meaningless where it does not)."""
        forward = safe_normalize(self.target - self.origin)
        right = safe_normalize(cross(forward, self.up))
        true_up = cross(right, forward)
        tan_half = jnp.tan(0.5 * jnp.deg2rad(self.fov))
        v = jnp.asarray(point, jnp.float32) - self.origin
        depth = jnp.dot(v, forward)
        safe = jnp.where(depth > 0, depth, 1.0)
        sx = jnp.dot(v, right) / safe / tan_half
        sy = jnp.dot(v, true_up) / safe / (tan_half * (self.height / self.width))
        xy = jnp.stack([0.5 * (sx + 1.0) * self.width, 0.5 * (1.0 - sy) * self.height])
        return xy, depth > 0

    def generate_ray(self, pixel: Float[Array, "2"]) -> tuple[Float[Array, "3"], Float[Array, "3"]]:
        """Ray `(origin, unit direction)` through the film position `pixel = (x, y)` in pixels, x to the right and y
        down from the top-left corner (so pixel (col, row)'s square is [col, col+1] x [row, row+1])."""
        forward = safe_normalize(self.target - self.origin)
        right = safe_normalize(cross(forward, self.up))
        true_up = cross(right, forward)
        tan_half = jnp.tan(0.5 * jnp.deg2rad(self.fov))
        sx = (2.0 * pixel[0] / self.width - 1.0) * tan_half
        sy = (1.0 - 2.0 * pixel[1] / self.height) * tan_half * (self.height / self.width)
        d = safe_normalize(forward + sx * right + sy * true_up)
        if self.near_clip == 0.0:  # static: the program of a camera without a clip plane has none of this
            return self.origin, d
        return self.origin + (self.near_clip / jnp.dot(d, forward)) * d, d
