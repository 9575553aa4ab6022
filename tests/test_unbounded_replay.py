"""Reverse mode of unbounded paths (`max_depth = -1`) by path replay (`jaxfog/_unbounded.py`).

Reverse mode (`jax.grad`) and forward mode (`jax.jacfwd`) of the same render (same key, same estimator) estimate the
same derivative with the same random numbers: they are the same sum over paths and bounces, computed in another
order and, in the replay, through `L - L_{j+1}` instead of the bounce-by-bounce tangents. They differ by float32
rounding only (tolerance in `_assert_same_gradient`). Finite differences check the common value (`proposal`
estimator: for a fixed key the image is a smooth function of the parameters, except where Russian roulette flips).

Scene: a diffuse floor under a spot light in a chromatic HG medium, 4 x 4 pixels, 2 spp; the parameters are the
medium's sigma_t, albedo and g, the spot light's intensity and the floor's reflectance (13 scalars). Russian
roulette from the 8th vertex on: with albedo <= 0.7 the survival probability there is below 0.7^7 ~ 0.08, so a
parameter step of 1e-3 moves it by ~1e-4 of itself and flips a path's survival with probability ~1e-5 per path.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfog as jf

EPS32 = float(np.finfo(np.float32).eps)
SPP = 2


def _scene(sigma_t=(0.4, 0.6, 0.9), albedo=(0.7, 0.6, 0.5), g=0.5, rr_depth=8):
    cam = jf.Camera(origin=(0.0, 1.5, 3.0), target=(0.0, 0.3, 0.0), up=(0.0, 1.0, 0.0), fov=45.0, width=4, height=4)
    floor = jf.Rectangle(center=(0.0, 0.0, 0.0), edge_u=(6.0, 0.0, 0.0), edge_v=(0.0, 0.0, -6.0),
                         bsdf=jf.Diffuse((0.6, 0.5, 0.4)))
    spot = jf.SpotLight(position=(0.0, 2.5, 0.0), direction=(0.0, -1.0, 0.0), intensity=(30.0, 25.0, 20.0),
                        cutoff_angle=30.0, beam_width=20.0)
    med = jf.HomogeneousMedium(sigma_t=sigma_t, albedo=albedo, phase=jf.HenyeyGreenstein(g))
    return jf.Scene(camera=cam, shapes=(floor,), lights=(spot,), medium=med, max_depth=-1, rr_depth=rr_depth)


def _params(scene):
    return (scene.medium, scene.lights[0].intensity, scene.shapes[0].bsdf.reflectance)


def _with(scene, p):
    return eqx.tree_at(lambda s: (s.medium, s.lights[0].intensity, s.shapes[0].bsdf.reflectance), scene, p)


def _loss_fn(scene, estimator, key=jax.random.key(7)):
    weights = jnp.linspace(0.5, 1.5, 4 * 4 * 3, dtype=jnp.float32).reshape(4, 4, 3)
    proposal = scene.medium if estimator == "proposal" else None

    def loss(p):
        img = jf.render(_with(scene, p), key, SPP, estimator=estimator, proposal=proposal, devices=1)
        return jnp.sum(weights * img)

    return loss


def _flat(tree):
    return np.concatenate([np.ravel(np.asarray(x, np.float64)) for x in jax.tree.leaves(tree)])


def _assert_same_gradient(rev, fwd, theta, loss, label):
    """Reverse vs forward mode, entry by entry. Both sum the same per-path terms (SPP x 16 paths x ~8 bounces) in
    float32, in other orders: 64 eps (a generous count of roundings along one path's chain) times the entry and
    the gradient's largest entry (the terms' scale). The replay also forms each bounce's future radiance as
    `L - L_{j+1}` (error eps |L| per bounce, relative to the path's whole radiance) and multiplies it by the
    bounce's log-derivative `d log w / d theta_k`, which is 1 / theta_k for a parameter that scales the weight
    (sigma_s = albedo sigma_t, reflectance): a further 64 eps |loss| / |theta_k|."""
    rev, fwd, theta = _flat(rev), _flat(fwd), _flat(theta)
    assert np.all(np.isfinite(rev)) and np.all(np.isfinite(fwd)), label
    tol = 64 * EPS32 * (np.abs(fwd) + np.max(np.abs(fwd)) + abs(float(loss)) / np.abs(theta))
    assert np.all(np.abs(rev - fwd) <= tol), (label, rev, fwd, np.abs(rev - fwd) / tol)


# Each mode and estimator compiles its own program (tens of seconds on a 2-core CPU). The default run checks
# "proposal" (whose reference is the scene's own medium here: the same samples and numbers as "detached"; the two
# differ only in which medium `sampling_medium` detaches), and the finite differences and hard cases reuse its two
# programs (`jax.value_and_grad`, `jax.jacfwd`); "detached" itself is opt-in.
BOTH = ["proposal", pytest.param("detached", marks=pytest.mark.slow)]


@pytest.mark.parametrize("estimator", BOTH)
def test_reverse_mode_equals_forward_mode(estimator):
    scene = _scene()
    loss = _loss_fn(scene, estimator)
    p = _params(scene)
    value, rev = jax.value_and_grad(loss)(p)
    fwd = jax.jacfwd(loss)(p)
    _assert_same_gradient(rev, fwd, p, value, estimator)
    assert np.max(np.abs(_flat(rev))) > 0


def test_reverse_mode_matches_finite_differences():
    """<grad, v> against the central difference along a random direction v (relative steps), h = 1e-3 and 2e-3.
    Tolerance: the truncation error of the h estimate is ~ |D(2h) - D(h)| / 3 (error ~ h^2); float32 rounding of
    each loss is ~ eps sqrt(paths x bounces) |loss| at most 1e-5 |loss|, over 2 h."""
    scene = _scene()
    loss = _loss_fn(scene, "proposal")
    p = _params(scene)
    rng = np.random.default_rng(3)
    v = jax.tree.map(lambda x: jnp.asarray(rng.normal(size=np.shape(x)), jnp.float32) * x, p)
    value_and_grad = jax.value_and_grad(loss)  # the losses too: one compiled program for the whole test
    g = value_and_grad(p)[1]
    dot = float(sum(np.vdot(np.asarray(a, np.float64), np.asarray(b, np.float64))
                    for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(v))))
    at = lambda s: float(value_and_grad(jax.tree.map(lambda x, d: x + s * d, p, v))[0])
    d1 = (at(1e-3) - at(-1e-3)) / 2e-3
    d2 = (at(2e-3) - at(-2e-3)) / 4e-3
    l0 = abs(at(0.0))
    tol = abs(d2 - d1) + 1e-5 * l0 / 1e-3
    assert abs(dot - d1) <= tol, (dot, d1, d2, tol)


@pytest.mark.parametrize("estimator", BOTH)
def test_reverse_mode_is_nan_free_on_hard_cases(estimator):
    """Albedo 0, 1e-3 and 1, sigma_t tiny and large, g near +-1: the gradients are finite and equal forward mode's
    (one compiled program per mode: only values change). At albedo exactly 0 a medium vertex's throughput is 0, and
    with it the future radiance the replay divides by it: the albedo's derivative of the paths that continue past
    such a vertex (to the floor) is lost (docs/estimators.md); the other parameters' derivatives agree."""
    base = _scene()
    cases = [dict(albedo=0.0), dict(albedo=1e-3), dict(albedo=1.0), dict(sigma_t=1e-6), dict(sigma_t=40.0),
             dict(g=0.99), dict(g=-0.99), dict(sigma_t=(1e-6, 1.0, 40.0), albedo=(1e-3, 0.5, 1.0))]
    albedo = slice(3, 6)  # entries of the flattened parameters: sigma_t, albedo, g, intensity, reflectance
    for case in cases:
        scene = base.replace_medium(**{k: jnp.broadcast_to(jnp.float32(v), (3,)) if k != "g" else jnp.float32(v)
                                       for k, v in case.items()})
        loss = _loss_fn(scene, estimator)
        p = _params(scene)
        value, rev = jax.value_and_grad(loss)(p)
        rev, fwd = _flat(rev), _flat(jax.jacfwd(loss)(p))
        assert np.all(np.isfinite(rev)), (estimator, case, rev)
        keep = np.ones(rev.size, bool)
        if case.get("albedo") == 0.0:
            keep[albedo] = False
        _assert_same_gradient(rev[keep], fwd[keep], _flat(p)[keep], value, f"{estimator} {case}")


def test_reverse_mode_refuses_reparam():
    """Raised while the backward pass is traced: under one `jax.jit` nothing has been compiled or run yet."""
    scene = _scene()
    loss = _loss_fn(scene, "reparam")
    with pytest.raises(ValueError, match='reverse-mode derivatives of an unbounded render.*"reparam"'):
        jax.jit(jax.grad(loss))(_params(scene))


@pytest.mark.slow
def test_reverse_mode_over_a_whole_scene():
    """`jax.grad` over every leaf of a Scene (camera, geometry and the spot's position, direction and cone included:
    those by forward mode inside the reverse pass) against `jax.jvp` along a random tangent of all of them."""
    scene = _scene()
    arrays, static = eqx.partition(scene, eqx.is_inexact_array)
    weights = jnp.linspace(0.5, 1.5, 48, dtype=jnp.float32).reshape(4, 4, 3)
    loss = lambda s: jnp.sum(weights * jf.render(s, jax.random.key(7), SPP))
    rng = np.random.default_rng(5)
    v = jax.tree.map(lambda x: jnp.asarray(rng.normal(size=x.shape), jnp.float32), arrays)
    g, _ = eqx.partition(jax.grad(loss)(scene), eqx.is_inexact_array)
    dot = sum(np.vdot(np.asarray(a, np.float64), np.asarray(b, np.float64))
              for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(v)))
    jv = float(jax.jvp(lambda a: loss(eqx.combine(a, static)), (arrays,), (v,))[1])
    scale = sum(np.sum(np.abs(np.asarray(a) * np.asarray(b))) for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(v)))
    assert abs(dot - jv) <= 64 * EPS32 * scale, (dot, jv)
