"""The objective and the optimiser over a batch of poses: pose by pose what the one-pose
forms give, gradients against central differences."""

from __future__ import annotations

import numpy as np
import pytest
from test_core_energy import data_near, fist_of, numeric_gradient, silhouette_of

from hand_sog_tracker.core.hand_model import FINGER_ABD, N_PARAMS, default_hand_model, rest_pose
from hand_sog_tracker.core.kinematics import fingertips
from hand_sog_tracker.core.objective import Objective, TipTargets
from hand_sog_tracker.core.optimizer import StepSizes, maximise, maximise_batch
from hand_sog_tracker.core.types import TrackerConfig
from hand_sog_tracker.errors import InputError

#: The optional parts of the objective, switched on one at a time (and all together).
OPTIONS = ("previous", "targets", "silhouette", "contact", "visible_from", "joint_gaussians")


def _objective(seed: int, options: tuple[str, ...]) -> tuple[Objective, np.ndarray]:
    """An objective on random data near a random pose, with the given optional parts, and
    the pose the data were made at (26,)."""
    rng = np.random.default_rng(seed)
    model = default_hand_model(right=bool(seed % 2))
    truth = rest_pose((0.0, 60.0, 400.0))
    truth[6:] = rng.uniform(0.0, 0.8, 20)
    truth[FINGER_ABD] = 0.0  # (the fingers in their order)
    data = data_near(model, truth, rng, skip_chain=4)
    if "joint_gaussians" in options:
        model = model.with_joint_gaussians()
    kwargs: dict = {}
    if "previous" in options:
        kwargs["previous"] = (truth + rng.normal(0, 0.05, N_PARAMS), truth)
    if "targets" in options:
        tips = fingertips(model, truth)
        kwargs["targets"] = TipTargets(tips + rng.normal(0, 15, (5, 3)), np.array([0.9, 0.0, 0.5, 1.0, 0.3]))
    if "silhouette" in options:
        kwargs["silhouette"] = silhouette_of(model, truth, skip_chain=4)
    if "contact" in options:
        kwargs["contact"] = np.array([0.0, 1.0, 0.6, 1.0, 0.3])
    if "visible_from" in options:
        kwargs["visible_from"] = fist_of(truth)
    cfg = TrackerConfig(w_sal=1.0, w_ord=1.0, w_sil=1.0, w_cpl=1.0, w_curl=1.0, w_smo=0.5)
    return Objective(model, data, cfg, **kwargs), truth


def _poses(rng: np.random.Generator, truth: np.ndarray, B: int) -> np.ndarray:
    """B random poses around ``truth`` (B, 26): some beyond the joint limits, some with the
    fingers crossed, DIPs beyond their coupling and fingers curled beyond the curl limit."""
    thetas = np.tile(truth, (B, 1))
    thetas[:, :3] += rng.normal(0, 8, (B, 3))
    thetas[:, 3:6] += rng.normal(0, 0.15, (B, 3))
    thetas[:, 6:] += rng.normal(0, 0.4, (B, 20))
    thetas[::2, 6 + 4 * 2 + 1] = -0.3  # middle over the index finger: E_ord
    thetas[1::2, FINGER_ABD] = truth[FINGER_ABD]  # the fingers in order: no E_ord
    thetas[::3, 6 + 4 * 4 + 2 : 6 + 4 * 4 + 4] = (1.9, 1.1)  # little finger: E_curl, E_cpl
    return thetas


@pytest.mark.parametrize("B", [1, 3, 16])
@pytest.mark.parametrize("options", [(), *((o,) for o in OPTIONS), OPTIONS])
def test_batch_equals_one_pose_at_a_time(B: int, options: tuple[str, ...]) -> None:
    obj, truth = _objective(B + len(options), options)
    thetas = _poses(np.random.default_rng(B), truth, B)
    values, grads = obj.batch(thetas)
    only, none = obj.batch(thetas, gradient=False)
    assert values.shape == (B,) and grads is not None and grads.shape == (B, N_PARAMS) and none is None
    if options == OPTIONS and B == 16:  # every term is active at some pose of the batch
        terms = [obj.evaluate(t, gradient=False)[0] for t in thetas]
        for name in ("sim", "col", "dan", "lim", "smo", "ord", "sal", "sil", "cpl", "curl"):
            assert max(getattr(t, name) for t in terms) > 0, name
        assert min(t.ord for t in terms) == 0  # ... and inactive at another
    for b in range(B):
        v, g = obj(thetas[b])
        np.testing.assert_allclose(values[b], v, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(only[b], v, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(grads[b], g, rtol=1e-9, atol=1e-9 * np.abs(g).max())


def test_a_poses_result_does_not_depend_on_its_batch() -> None:
    obj, truth = _objective(2, OPTIONS)
    thetas = _poses(np.random.default_rng(2), truth, 16)
    values, grads = obj.batch(thetas)
    for size in (1, 3, 7):
        for start in range(0, 16, size):
            v, g = obj.batch(thetas[start : start + size])
            assert np.array_equal(v, values[start : start + size])
            assert np.array_equal(g, grads[start : start + size])


@pytest.mark.parametrize("B", [1, 5])
def test_batch_with_each_poses_own_targets_equals_the_variant_with_them(B: int) -> None:
    obj, truth = _objective(4, ("targets", "silhouette"))
    rng = np.random.default_rng(4)
    thetas = _poses(rng, truth, B)
    tips = fingertips(obj.model, truth)
    own = [TipTargets(tips + rng.normal(0, 20, (5, 3)), rng.uniform(0, 1, 5) * (rng.random(5) < 0.7))
           for _ in range(B)]
    own[0] = None  # (a pose without detections: no E_sal)
    values, grads = obj.batch(thetas, targets=own)
    for b in range(B):
        v, g = obj.variant(obj.config, own[b])(thetas[b])
        assert values[b] == v and np.array_equal(grads[b], g)
    plain, _ = obj.batch(thetas)  # (the objective's own targets again)
    assert plain[0] == obj(thetas[0])[0] != values[0]
    with pytest.raises(InputError, match="one per pose"):
        obj.batch(thetas, targets=own + [None])


def test_maximise_batch_tells_the_objective_which_candidates_it_evaluates() -> None:
    obj, truth = _objective(6, ("targets",))
    rng = np.random.default_rng(6)
    x0 = _poses(rng, truth, 3)
    tips = fingertips(obj.model, truth)
    own = [TipTargets(tips + rng.normal(0, 10, (5, 3)), np.ones(5)) for _ in range(3)]
    seen = []

    def fun(thetas, gradient=True, index=None):
        seen.append(index.tolist())
        return obj.batch(thetas, gradient, [own[i] for i in index])

    steps = StepSizes(initial=(0.02, 2e-4, 5e-4))  # (small: candidates settle at different iterations)
    results = maximise_batch(fun, x0, iterations=12, steps=steps, with_index=True)
    assert seen[0] == [0, 1, 2]
    for b in range(3):
        _same(results[b], maximise(obj.variant(obj.config, own[b]), x0[b], iterations=12, steps=steps))


@pytest.mark.parametrize("seed", [0, 1])
def test_batch_gradients_match_central_differences(seed: int) -> None:
    obj, truth = _objective(seed, OPTIONS[:-1] if seed else OPTIONS)
    thetas = _poses(np.random.default_rng(seed), truth, 3)
    _, grads = obj.batch(thetas)
    for theta, grad in zip(thetas, grads):
        num = numeric_gradient(obj, theta)
        np.testing.assert_allclose(grad, num, rtol=1e-4, atol=1e-6 * np.abs(num).max())


def test_batch_rejects_bad_shapes_and_values() -> None:
    obj, truth = _objective(0, ())
    with pytest.raises(InputError, match="shape"):
        obj.batch(truth)
    values, grads = obj.batch(np.zeros((0, N_PARAMS)))
    assert values.shape == (0,) and grads is not None and grads.shape == (0, N_PARAMS)
    bad = np.tile(truth, (2, 1))
    bad[1, 3] = np.nan
    with pytest.raises(InputError, match="NaN"):
        obj.batch(bad)


class BatchBowl:
    """``-sum w (theta - peak)^2`` per pose with its gradient, for a batch of poses; counts
    the poses it evaluates."""

    def __init__(self, peak: np.ndarray, weights: np.ndarray) -> None:
        self.peak, self.weights, self.poses = peak, weights, 0

    def one(self, theta: np.ndarray, gradient: bool = True):
        d = theta - self.peak
        return -float(self.weights @ (d * d)), (-2.0 * self.weights * d if gradient else None)

    def __call__(self, thetas: np.ndarray, gradient: bool = True):
        self.poses += thetas.shape[0]
        # (pose by pose: a matrix product's rounding could depend on the batch's size)
        values = np.array([self.one(t, False)[0] for t in thetas])
        return values, (-2.0 * self.weights * (thetas - self.peak) if gradient else None)


def _same(a, b) -> None:
    assert np.array_equal(a.x, b.x) and a.fun == b.fun and a.nit == b.nit and a.status == b.status
    assert np.array_equal(a.history, b.history) and np.array_equal(a.steps, b.steps)
    assert a.success == b.success and a.message == b.message


def test_maximise_batch_of_one_runs_the_iterates_of_maximise() -> None:
    rng = np.random.default_rng(3)
    peak = rng.normal(0, 1, N_PARAMS)
    bowl = BatchBowl(peak, rng.uniform(0.5, 2.0, N_PARAMS))
    x0 = peak + rng.normal(0, 5, N_PARAMS)
    active = rng.random(N_PARAMS) < 0.8
    bounds = (peak - 3.0, peak + 3.0)
    for kwargs in ({}, {"active": active, "bounds": bounds, "initial_scale": 2.0},
                   {"initial_steps": rng.uniform(0.01, 0.5, N_PARAMS), "iterations": 40}):
        (batch,) = maximise_batch(bowl, x0[None], **kwargs)
        _same(batch, maximise(bowl.one, x0, **kwargs))
    # An early stop (negligible steps) too: a flat objective shrinks no step, a tiny one settles.
    tiny = StepSizes(initial=(0.02, 2e-4, 5e-4))
    (batch,) = maximise_batch(bowl, peak[None] + 1e-9, iterations=60, steps=tiny)
    one = maximise(bowl.one, peak + 1e-9, iterations=60, steps=tiny)
    assert one.status == 1
    _same(batch, one)


def test_maximise_batch_candidates_are_independent() -> None:
    rng = np.random.default_rng(4)
    peak = rng.normal(0, 1, N_PARAMS)
    bowl = BatchBowl(peak, rng.uniform(0.5, 2.0, N_PARAMS))
    x0 = peak + rng.normal(0, 5, (6, N_PARAMS))
    x0[2] = peak + 1e-9  # settles early: left out of the later calls
    active = rng.random((6, N_PARAMS)) < 0.8
    steps = StepSizes(initial=(0.02, 2e-4, 5e-4))
    results = maximise_batch(bowl, x0, iterations=30, active=active, steps=steps)
    assert results[2].status == 1 and results[2].nit < 30
    assert bowl.poses < 6 * 31
    for b in range(6):
        (alone,) = maximise_batch(bowl, x0[b : b + 1], iterations=30, active=active[b], steps=steps)
        _same(results[b], alone)
        _same(alone, maximise(bowl.one, x0[b], iterations=30, active=active[b], steps=steps))


def test_maximise_batch_with_the_objective_runs_what_maximise_runs_for_each_candidate() -> None:
    obj, truth = _objective(5, OPTIONS[:-1])
    x0 = _poses(np.random.default_rng(5), truth, 4)
    bounds = (obj._limits_low, obj._limits_high)
    results = maximise_batch(obj.batch, x0, iterations=8, bounds=bounds)
    for b, (res, start) in enumerate(zip(results, x0)):
        (alone,) = maximise_batch(obj.batch, x0[b : b + 1], iterations=8, bounds=bounds)
        _same(res, alone)  # (the batch's values and gradients do not depend on its other poses)
        _same(alone, maximise(obj, start, iterations=8, bounds=bounds))  # (one pose: the one-pose path)
        assert res.success and res.fun > res.history[0]


@pytest.mark.parametrize("options", [(), OPTIONS])
def test_a_batch_with_parts_gives_each_pose_its_parts_objective(options: tuple[str, ...]) -> None:
    """``parts``: pose ``b`` sees only the data Gaussians ``parts[b]`` and gets what the
    objective of that subset gives it (up to rounding), dangling rows included; its gradient
    matches central differences."""
    obj, truth = _objective(4, options)
    rng = np.random.default_rng(14)
    thetas = truth + rng.normal(0.0, 0.05, (5, N_PARAMS)) * np.r_[30.0, 30.0, 30.0, np.ones(23)]
    parts = rng.random((5, obj.data.n)) < 0.7
    parts[0] = True
    parts[1, obj.data.points[:, 1] > np.median(obj.data.points[:, 1])] = False  # (a hand's half without data)
    values, grads = obj.batch(thetas, parts=parts)
    dangling = 0
    for b in range(5):
        sub = Objective(
            obj.model, obj.data.subset(parts[b]), obj.config, obj.previous, obj.targets, obj.silhouette, obj.contact,
            obj.visible_from,
        )
        value, grad = sub(thetas[b])
        assert values[b] == pytest.approx(value, rel=1e-12, abs=1e-14)
        np.testing.assert_allclose(grads[b], grad, rtol=1e-9, atol=1e-12 * np.abs(grad).max())
        dangling += sub.evaluate(thetas[b])[0].dan > 0
    assert dangling >= 2  # (the dangling rows' own code ran with parts)

    def value_at(theta: np.ndarray) -> float:
        return float(obj.batch(np.stack([theta, thetas[2]]), gradient=False, parts=parts[1:3])[0][0])

    stand_in = type("F", (), {"__call__": lambda self, th, gradient=False: (value_at(th), None)})()
    np.testing.assert_allclose(grads[1], numeric_gradient(stand_in, thetas[1]), rtol=2e-4, atol=2e-6)
    with pytest.raises(InputError):
        obj.batch(thetas, parts=parts[:2])
    with pytest.raises(InputError):
        obj.batch(thetas[:1], parts=np.zeros((1, obj.data.n), dtype=bool))


def test_a_candidate_that_cannot_reach_its_floor_stops_and_the_others_run_as_without() -> None:
    rng = np.random.default_rng(6)
    peak = rng.normal(0, 1, N_PARAMS)
    bowl = BatchBowl(peak, rng.uniform(0.5, 2.0, N_PARAMS))
    x0 = peak + rng.normal(0, 5, (5, N_PARAMS))
    free = maximise_batch(bowl, x0, iterations=12)
    # Candidates 1 and 3 must beat the peak's value (0): they cannot, and stop after a quarter
    # of the iterations; the others' floors are below anything they reach.
    floor = np.array([-np.inf, 1.0, -1e9, 1.0, -np.inf])
    poses = bowl.poses
    raced = maximise_batch(bowl, x0, iterations=12, floor=floor)
    assert bowl.poses - poses < 5 * 13 - 2 * 8
    for b in (1, 3):
        assert raced[b].status == 2 and raced[b].nit == 3 and raced[b].fun < floor[b]
        assert np.array_equal(raced[b].history, free[b].history[:4])
    for b in (0, 2, 4):
        _same(raced[b], free[b])
