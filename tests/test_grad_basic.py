"""Basic gradient identities on a tiny fog scene: the "proposal" estimator's fixed-key image has AD derivatives equal
to its own finite differences, and all three estimators give the same image in expectation at the same parameters.
(Forward mode == reverse mode: `test_hard_cases.test_forward_equals_reverse`, the one test of it.)"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfog
from helpers import spot_fog


def _scene(width=8):
    """spot_fog at `width` x `width` px and max_depth 3 (spot light, sphere, floor, HG fog g = 0.6)."""
    return spot_fog(width=width, height=width, max_depth=3)


SCENE = _scene()
REF = SCENE.medium


def _mean(theta, estimator, key=0, spp=4):
    scene = SCENE.replace_medium(sigma_t=theta[0], albedo=theta[1], g=theta[2])
    return jaxfog.render(scene, jax.random.key(key), spp, estimator=estimator, proposal=REF).mean()


THETA = jnp.array([0.5, 0.9, 0.6])


@pytest.mark.slow
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
