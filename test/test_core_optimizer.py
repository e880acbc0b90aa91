"""The adaptive gradient ascent: extra iterations while still climbing, warm-started steps."""

from __future__ import annotations

import numpy as np

from hand_sog_tracker.core.hand_model import N_PARAMS
from hand_sog_tracker.core.optimizer import StepSizes, maximise, maximise_steps, run


class Bowl:
    """``-|theta - peak|^2`` (a concave bowl) with its gradient; counts the gradient calls."""

    def __init__(self, peak: np.ndarray) -> None:
        self.peak = peak
        self.gradients = 0

    def __call__(self, theta: np.ndarray, gradient: bool = True):
        d = theta - self.peak
        self.gradients += gradient
        return -float(d @ d), (-2.0 * d if gradient else None)


def test_maximise_steps_pauses_after_every_iteration_and_ends_where_maximise_ends() -> None:
    peak = np.linspace(-1.0, 1.0, N_PARAMS)
    bowl = Bowl(peak)
    steps = maximise_steps(bowl, peak + 20.0, iterations=6)
    pauses, evaluations = 0, []
    while True:
        evaluations.append(bowl.gradients)
        try:
            next(steps)
        except StopIteration as done:
            result = done.value
            break
        pauses += 1
    assert pauses == result.nit == 6
    # Nothing runs before the first step; then one gradient per iteration (the start's with the
    # first; the last possible iterate's value goes without one).
    assert evaluations == [0, 2, 3, 4, 5, 6, 6], evaluations
    whole = maximise(Bowl(peak), peak + 20.0, iterations=6)
    again = run(maximise_steps(Bowl(peak), peak + 20.0, iterations=6))
    assert np.array_equal(result.x, whole.x) and np.array_equal(again.history, whole.history)


def test_extra_iterations_run_only_while_the_fit_still_climbs() -> None:
    peak = np.linspace(-1.0, 1.0, N_PARAMS)
    far = maximise(Bowl(peak), peak + 20.0, iterations=4, extra_iterations=3, extra_gain=1e-3)
    assert far.nit == 7 and far.fun > far.history[4]  # still climbing after 4: all 3 more
    flat = maximise(lambda theta, gradient=True: (1.0, np.zeros(N_PARAMS) if gradient else None),
                    peak, iterations=4, extra_iterations=3, extra_gain=1e-3)
    assert flat.nit == 4  # nothing to gain: stops at 4
    plain = maximise(Bowl(peak), peak + 20.0, iterations=4)
    assert plain.nit == 4 and np.array_equal(plain.history, far.history[:5])


def test_only_the_last_possible_iterate_goes_without_gradient_and_steps_warm_start() -> None:
    peak = np.zeros(N_PARAMS)
    fun = Bowl(peak)
    res = maximise(fun, peak + 5.0, iterations=6)
    assert fun.gradients == 6  # the start and iterates 1..5; the 6th only needs its value
    assert res.steps is not None and res.steps.shape == (N_PARAMS,)
    warm = maximise(Bowl(peak), res.x, iterations=3, initial_steps=res.steps)
    cold = maximise(Bowl(peak), res.x, iterations=3, initial_steps=StepSizes().expand(StepSizes().initial))
    assert warm.fun >= cold.fun  # near the optimum, small remembered steps do not overshoot


def test_inactive_parameters_stay_and_settle_and_all_active_is_no_mask() -> None:
    # An active mask freezes the other parameters (and they count as settled for the early
    # stop); a mask with every parameter active gives the very same run as none.
    peak = np.linspace(-2.0, 2.0, N_PARAMS)
    start = peak + 3.0
    rigid = np.zeros(N_PARAMS, dtype=bool)
    rigid[:6] = True
    res = maximise(Bowl(peak), start, iterations=200, active=rigid)
    np.testing.assert_array_equal(res.x[6:], start[6:])
    assert res.status == 1 and res.nit < 200  # the rigid part settled, the rest is ignored
    np.testing.assert_allclose(res.x[:6], peak[:6], atol=0.05)
    lo, hi = np.full(N_PARAMS, -np.inf), np.full(N_PARAMS, np.inf)
    hi[6:] = peak[6:] + 1.0  # bounds: the joints stop short of the peak
    a = maximise(Bowl(peak), start, iterations=30, bounds=(lo, hi))
    b = maximise(Bowl(peak), start, iterations=30, bounds=(lo, hi), active=np.ones(N_PARAMS, dtype=bool))
    np.testing.assert_array_equal(a.history, b.history)
    np.testing.assert_array_equal(a.x, b.x)
    assert np.all(a.x[6:] <= hi[6:])


class LazyBowl(Bowl):
    """A :class:`Bowl` that can give its value first and its gradient on demand (as
    ``Objective.value_then_gradient``); counts the gradients actually computed."""

    def value_then_gradient(self, theta: np.ndarray):
        value = self(theta, gradient=False)[0]

        def finish() -> np.ndarray:
            self.gradients += 1
            return -2.0 * (theta - self.peak)

        return value, finish


def test_the_iterate_that_may_be_last_gets_its_gradient_only_when_the_fit_goes_on() -> None:
    peak = np.linspace(-1.0, 1.0, N_PARAMS)
    # Far from the peak the fit still climbs after 4 iterations; with a gain threshold no
    # step can reach (|E| is 0 at the peak: any gain counts otherwise) it stops at 4.
    for start, gain, more in ((peak + 20.0, 1e-3, True), (peak + 20.0, 1e9, False)):
        eager, lazy = Bowl(peak), LazyBowl(peak)
        a = maximise(eager, start, iterations=4, extra_iterations=3, extra_gain=gain)
        b = maximise(lazy, start, iterations=4, extra_iterations=3, extra_gain=gain)
        np.testing.assert_array_equal(a.history, b.history)  # the very same run
        np.testing.assert_array_equal(a.x, b.x)
        assert (a.nit > 4) == more
        # Stopped at 4: the 4th iterate's gradient is never computed.
        assert lazy.gradients == eager.gradients - (0 if more else 1)
