"""Basic gradient identities on a tiny fog scene: forward mode equals reverse mode, the "proposal" estimator's
fixed-key image has AD derivatives equal to its own finite differences, and all three estimators give the same
image in expectation at the same parameters."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfog


def _scene(width=8):
    cam = jaxfog.Camera(origin=[0, 1, 4.5], target=[0, 0.8, 0], up=[0, 1, 0], fov=40.0, width=width, height=width)
    floor = jaxfog.Rectangle(center=[0, 0, 0], edge_u=[6, 0, 0], edge_v=[0, 0, -6], bsdf=jaxfog.Diffuse(0.5))
    sphere = jaxfog.Sphere(center=[0.6, 0.5, -0.3], radius=0.5, bsdf=jaxfog.Diffuse(0.7))
    spot = jaxfog.SpotLight(position=[0, 2.8, 0], direction=[0, -1, 0], intensity=60.0, cutoff_angle=20.0,
                            beam_width=15.0)
    med = jaxfog.HomogeneousMedium(sigma_t=0.5, albedo=0.9, phase=jaxfog.HenyeyGreenstein(0.6))
    return jaxfog.Scene(camera=cam, shapes=(floor, sphere), lights=(spot,), medium=med, max_depth=3)


SCENE = _scene()
REF = SCENE.medium


def _mean(theta, estimator, key=0, spp=4):
    scene = SCENE.replace_medium(sigma_t=theta[0], albedo=theta[1], g=theta[2])
    return jaxfog.render(scene, jax.random.key(key), spp, estimator=estimator, proposal=REF).mean()


THETA = jnp.array([0.5, 0.9, 0.6])


@pytest.mark.parametrize(
    "estimator", ["detached", pytest.param("proposal", marks=pytest.mark.slow), pytest.param("reparam", marks=pytest.mark.slow)]
)
def test_forward_equals_reverse(estimator):
    fwd = jax.jacfwd(_mean)(THETA, estimator)
    rev = jax.grad(_mean)(THETA, estimator)
    assert np.all(np.isfinite(fwd)) and np.all(np.isfinite(rev))
    # Same key, same function: the two modes differ only by float32 rounding.
    np.testing.assert_allclose(fwd, rev, rtol=2e-3, atol=1e-6)


def test_proposal_fixed_key_ad_matches_finite_differences():
    # With a fixed key and a fixed proposal the image is a smooth deterministic function of theta (estimators.md),
    # so central differences (h = 1e-3, float32 renders in float64 arithmetic of the difference) must agree.
    theta = THETA + jnp.array([0.05, -0.05, -0.1])  # away from the reference, weights != 1
    ad = np.asarray(jax.grad(_mean)(theta, "proposal"))
    h = 2e-3
    fd = []
    for i in range(3):
        e = jnp.zeros(3).at[i].set(h)
        fd.append((float(_mean(theta + e, "proposal")) - float(_mean(theta - e, "proposal"))) / (2 * h))
    np.testing.assert_allclose(ad, fd, rtol=1e-2, atol=1e-4)


@pytest.mark.slow
def test_estimators_agree_in_expectation():
    # Same parameters, independent keys: the mean pixel of each estimator agrees with "detached" within 4 standard
    # errors of the difference (standard errors from the spread over 6 keys each).
    vals = {}
    for est in ["detached", "proposal", "reparam"]:
        vals[est] = np.array([float(_mean(THETA, est, key=100 + k + 10 * len(vals), spp=8)) for k in range(6)])
    for est in ["proposal", "reparam"]:
        a, b = vals["detached"], vals[est]
        se = np.sqrt(a.var(ddof=1) / a.size + b.var(ddof=1) / b.size)
        assert abs(a.mean() - b.mean()) < 4 * se, (est, a.mean(), b.mean(), se)
