"""The inter-hand collision term ``E_int`` (seed 001): definition, analytic gradient against
central differences at random poses, one pose and batch, and what the tracker gives it."""

from __future__ import annotations

import numpy as np
import pytest
from test_core_energy import data_near, numeric_gradient

from hand_sog_tracker.core.hand_model import N_PARAMS, default_hand_model, rest_pose
from hand_sog_tracker.core.kinematics import gaussian_centres
from hand_sog_tracker.core.objective import Objective
from hand_sog_tracker.core.objective.interhand import INTERHAND_SCALE_MM, InterHand
from hand_sog_tracker.core.types import TrackerConfig


def _two_hands(seed: int):
    """A right hand at a random pose, and a left hand's spheres pushed into it (mm)."""
    rng = np.random.default_rng(seed)
    right, left = default_hand_model(right=True), default_hand_model(right=False)
    theta = rest_pose((0.0, 40.0, 420.0))
    theta[3:6] += rng.normal(0.0, 0.2, 3)
    theta[6:] = rng.uniform(0.0, 0.6, 20)
    other = rest_pose((rng.normal(35.0, 5.0), rng.normal(45.0, 5.0), 425.0))
    other[6:] = rng.uniform(0.0, 0.6, 20)
    return rng, right, theta, gaussian_centres(left, other), left.g_sigmas


def test_term_is_the_squared_penetration_of_every_sphere_pair() -> None:
    _, model, theta, q, rq = _two_hands(0)
    term = InterHand(q, rq, 2.0)
    P = gaussian_centres(model, theta)
    want = 0.0
    for p, rp in zip(P, model.g_sigmas):
        for c, rc in zip(q, rq):
            want += max(rp + rc - float(np.linalg.norm(p - c)), 0.0) ** 2
    assert want > 0.0
    assert term.term(P, model.g_sigmas, None) == pytest.approx(2.0 * want / INTERHAND_SCALE_MM**2, rel=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_objective_gradient_with_the_term_matches_central_differences(seed: int) -> None:
    rng, model, theta, q, rq = _two_hands(seed)
    obj = Objective(model, data_near(model, theta, rng), TrackerConfig())
    inter = InterHand.near(q, rq, gaussian_centres(model, theta), model.g_sigmas, 0.5, 30.0)
    assert inter is not None
    without = obj(theta, gradient=False)[0]
    obj.interhand = inter
    value, grad = obj(theta)
    assert value < without  # (the hands interpenetrate: the term costs)
    num = numeric_gradient(obj, theta)
    np.testing.assert_allclose(grad, num, rtol=1e-4, atol=1e-6 * np.abs(num).max())
    # The batch and the deferred gradient give the same, pose by pose.
    thetas = np.stack([theta, theta + rng.normal(0.0, 0.02, N_PARAMS)])
    values, grads = obj.batch(thetas)
    for b in range(2):
        v, g = obj(thetas[b])
        np.testing.assert_allclose(values[b], v, rtol=1e-12)
        np.testing.assert_allclose(grads[b], g, rtol=1e-9, atol=1e-12)
    v, finish = obj.value_then_gradient(theta)
    assert v == value
    np.testing.assert_allclose(finish(), grad, rtol=1e-12, atol=1e-15)
    # A variant (the search's objectives) keeps the term.
    assert obj.variant(obj.config, None).interhand is inter


def test_hands_apart_have_no_term() -> None:
    _, model, theta, q, rq = _two_hands(0)
    far = q + np.array([300.0, 0.0, 0.0])
    assert InterHand.near(far, rq, gaussian_centres(model, theta), model.g_sigmas, 1.0, 30.0) is None
