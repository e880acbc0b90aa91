"""Gradient ascent with adaptive, per-parameter step lengths (paper 000, sec. 5.3).

The paper adopts the conditioned gradient ascent of Stoll et al. (2011): every
parameter has its own step length, which grows while the gradient keeps its
sign and shrinks when it flips.  We use that rule in its Rprop form (iRprop-):
a step moves each parameter by its step length in the direction of its partial
derivative, so millimetres and radians need no common scale, and a sign flip
halves the step and skips that parameter once.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Generator, TypeVar

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.hand_model import FIRST_JOINT, JOINTS, N_PARAMS

__all__ = ["OptimizeResult", "StepSizes", "Steps", "maximise", "maximise_batch", "maximise_steps", "run"]

#: Objective signature: ``fun(theta (26,), gradient=True) -> (value, gradient (26,) or None)``;
#: with ``gradient=False`` only the value is needed (``None`` may be returned for the gradient).
ObjectiveFn = Callable[..., tuple[float, NDArray[np.float64] | None]]
#: Batch objective signature: ``fun(thetas (B, 26), gradient=True) -> (values (B,), gradients
#: (B, 26) or None)``, pose by pose what an :data:`ObjectiveFn` returns
#: (:meth:`~hand_sog_tracker.core.objective.Objective.batch`).
BatchObjectiveFn = Callable[..., tuple[NDArray[np.float64], NDArray[np.float64] | None]]

_T = TypeVar("_T")
#: A computation that can be paused: a generator that yields (nothing) between two steps of
#: its work, e.g. after each iteration of :func:`maximise_steps`, and returns its result.
#: :func:`run` runs one to its end; a caller with a deadline advances it with ``next`` and
#: may leave it for later (the node's restarts between two frames, issue 14).
Steps = Generator[None, None, _T]


def run(steps: Steps[_T]) -> _T:
    """Run ``steps`` to its end (no pauses) and return its result."""
    while True:
        try:
            next(steps)
        except StopIteration as done:
            return done.value  # type: ignore[no-any-return]


@dataclass(frozen=True)
class StepSizes:
    """Initial, minimum and maximum step lengths: translation (mm), global rotation
    (rad) and joint angles (rad)."""

    initial: tuple[float, float, float] = (2.0, 0.03, 0.06)
    minimum: tuple[float, float, float] = (0.02, 2e-4, 5e-4)
    maximum: tuple[float, float, float] = (15.0, 0.25, 0.4)
    grow: float = 1.2
    shrink: float = 0.5

    def expand(self, which: tuple[float, float, float]) -> NDArray[np.float64]:
        """Per-parameter vector, shape (26,), from a (translation, rotation, joint) triple."""
        out = np.empty(N_PARAMS)
        out[:3], out[3:FIRST_JOINT], out[JOINTS] = which
        return out


@dataclass(frozen=True, eq=False)
class OptimizeResult:
    """Outcome of :func:`maximise`, with ``scipy.optimize.OptimizeResult`` field names.

    Attributes
    ----------
    x : array, shape (26,)
        Best pose found.
    fun : float
        Objective at ``x``.
    nit : int
        Iterations run.
    success : bool
        ``True`` when the objective did not decrease from the start.
    status : int
        0 iterations exhausted, 1 steps became negligible, 2 stopped below its floor
        (:func:`maximise_batch`'s ``floor``).
    message : str
    history : array, shape (nit + 1,)
        Objective at the start and after each iteration.
    steps : array, shape (26,)
        Step lengths at the end (mm for translation, rad otherwise): a warm start for the
        next fit of a similar problem (``initial_steps``).
    """

    x: NDArray[np.float64]
    fun: float
    nit: int
    success: bool
    status: int
    message: str
    history: NDArray[np.float64]
    steps: NDArray[np.float64] | None = None


#: :attr:`OptimizeResult.message` by ``status``.
_MESSAGES = ("iterations exhausted", "step lengths became negligible", "cannot reach its floor")

#: ``a.all()`` of a boolean array without the method's Python layer.
_all = np.logical_and.reduce

_LIMITS: dict[StepSizes, tuple[NDArray[np.float64], NDArray[np.float64]]] = {}


def _limits_of(steps: StepSizes) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The minimum and maximum step lengths of ``steps`` per parameter, (26,) each, read-only
    (cached per value: a tracked frame runs several fits with the same step sizes)."""
    hit = _LIMITS.get(steps)
    if hit is None:
        hit = (steps.expand(steps.minimum), steps.expand(steps.maximum))
        for arr in hit:
            arr.setflags(write=False)
        if len(_LIMITS) >= 16:
            _LIMITS.clear()
        _LIMITS[steps] = hit
    return hit


def _step(
    x: NDArray[np.float64],
    grad: NDArray[np.float64],
    prev_sign: NDArray[np.float64],
    step: NDArray[np.float64],
    mask: NDArray[np.bool_] | None,
    grow: float,
    shrink: float,
    lo: NDArray[np.float64],
    hi: NDArray[np.float64],
    low: NDArray[np.float64] | None,
    high: NDArray[np.float64] | None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """One iRprop- step from ``x`` (26,) or (B, 26) along ``grad``: updates the step lengths
    ``step`` in place (grown where the sign agrees with ``prev_sign``, shrunk within ``lo, hi``
    where it flips, that parameter then skipped), returns the new ``x`` (projected into
    ``low, high`` unless None) and the signs of this step (the next ``prev_sign``)."""
    sign = np.sign(grad)
    if mask is not None:
        sign *= mask
    agree = sign * prev_sign
    grows, shrinks = agree > 0, agree < 0
    # (In place where the step changes: the values of
    # np.where(grows, np.minimum(step * grow, hi), step), then likewise for shrinks.)
    np.minimum(step * grow, hi, out=step, where=grows)
    np.maximum(step * shrink, lo, out=step, where=shrinks)
    np.copyto(sign, 0.0, where=shrinks)  # (= sign[shrinks] = 0.0, cheaper)
    x = x + step * sign
    if low is not None and high is not None:
        np.maximum(x, low, out=x)  # (x is a new array: clipped in place)
        np.minimum(x, high, out=x)
    return x, sign


def maximise(
    fun: ObjectiveFn,
    x0: NDArray[np.float64],
    iterations: int = 10,
    steps: StepSizes = StepSizes(),
    active: NDArray[np.bool_] | None = None,
    initial_scale: float = 1.0,
    bounds: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
    initial_steps: NDArray[np.float64] | None = None,
    extra_iterations: int = 0,
    extra_gain: float = 0.0,
) -> OptimizeResult:
    """Maximise ``fun`` from ``x0`` with adaptive per-parameter steps (:func:`maximise_steps`
    run to its end; the same arguments)."""
    return run(
        maximise_steps(
            fun, x0, iterations, steps, active, initial_scale, bounds, initial_steps,
            extra_iterations, extra_gain,
        )
    )


def maximise_steps(
    fun: ObjectiveFn,
    x0: NDArray[np.float64],
    iterations: int = 10,
    steps: StepSizes = StepSizes(),
    active: NDArray[np.bool_] | None = None,
    initial_scale: float = 1.0,
    bounds: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
    initial_steps: NDArray[np.float64] | None = None,
    extra_iterations: int = 0,
    extra_gain: float = 0.0,
) -> Steps[OptimizeResult]:
    """Maximise ``fun`` from ``x0`` with adaptive per-parameter steps; pauses (yields) after
    every iteration (see :data:`Steps`), returns the :class:`OptimizeResult`.

    Parameters
    ----------
    fun : callable
        ``fun(theta, gradient=True) -> (value, gradient)``.  The last possible iterate is
        evaluated with ``gradient=False``: only its value is used.  With ``extra_iterations``
        and a method ``fun.value_then_gradient(theta) -> (value, gradient function)``, the
        iterate that may be the last gets its gradient only when the fit goes on.
    x0 : array, shape (26,)
        Start pose.
    iterations : int
        Gradient evaluations after the first.
    steps : StepSizes
    active : bool array, shape (26,), optional
        Parameters allowed to move (default: all).
    initial_scale : float
        Multiplies the initial step lengths (e.g. larger when initialising).
    bounds : (low, high) arrays, shape (26,) each, optional
        Every iterate is projected into ``[low, high]`` (seed 004's joint limits by
        projection; use +-inf for free parameters).  ``x0`` itself is projected too.
    initial_steps : array, shape (26,), optional
        Start step lengths per parameter (mm / rad), e.g. the ``steps`` of the previous
        frame's result; overrides ``steps.initial`` and ``initial_scale``.
    extra_iterations : int
        Up to this many iterations more, one at a time, while the last one still raised the
        objective by more than ``extra_gain * |fun(x0)|`` (a fit still climbing, e.g. a fast
        motion, continues; a converged one stops at ``iterations``).
    extra_gain : float
        See ``extra_iterations`` (unitless).
    """
    x = np.array(x0, dtype=np.float64)
    if initial_steps is not None:
        step = np.array(initial_steps, dtype=np.float64)  # (a new array: updated in place)
    else:
        step = steps.expand(steps.initial) * initial_scale
    lo, hi = _limits_of(steps)
    mask = None if active is None else np.asarray(active, bool)
    # Loop invariants (the loop body is a few dozen tiny NumPy calls: each one counts).
    lo_settled = lo * 1.0001
    if mask is not None:  # inactive parameters count as settled
        lo_settled = np.where(mask, lo_settled, np.inf)
    low, high = (None, None) if bounds is None else (np.asarray(bounds[0]), np.asarray(bounds[1]))
    if bounds is not None:
        x = np.minimum(np.maximum(x, low), high)  # = np.clip, cheaper
    val, grad = fun(x)
    assert grad is not None
    # An objective that can give the value first and the gradient on demand
    # (:meth:`~hand_sog_tracker.core.objective.Objective.value_then_gradient`).
    deferred = getattr(fun, "value_then_gradient", None) if extra_iterations > 0 else None
    best_x, best_val = x.copy(), val
    history = [val]
    prev_sign = np.zeros(N_PARAMS)
    grow, shrink = steps.grow, steps.shrink
    status, nit, limit = 0, 0, iterations
    while nit < limit:
        nit += 1
        x, prev_sign = _step(x, grad, prev_sign, step, mask, grow, shrink, lo, hi, low, high)
        finish = None
        if nit == limit < iterations + extra_iterations and deferred is not None:
            # The last iterate unless the fit is still climbing: its gradient only then.
            val, finish = deferred(x)
        elif nit < iterations + extra_iterations:
            val, grad = fun(x)
            assert grad is not None
        else:  # the last possible iterate: only its value is used
            val = fun(x, gradient=False)[0]
        history.append(val)
        if nit == limit < iterations + extra_iterations and val - history[-2] > extra_gain * abs(history[0]):
            limit += 1
            if finish is not None:
                grad = finish()
        if val > best_val:
            best_x, best_val = x.copy(), val
        if _all(step <= lo_settled):
            status = 1
            break
        yield
    start = history[0]
    return OptimizeResult(
        x=best_x,
        fun=float(best_val),
        nit=nit,
        success=bool(best_val >= start),
        status=status,
        message="step lengths became negligible" if status == 1 else "iterations exhausted",
        history=np.asarray(history),
        steps=step,
    )


def maximise_batch(
    fun_batch: BatchObjectiveFn,
    x0: NDArray[np.float64],
    iterations: int = 10,
    steps: StepSizes = StepSizes(),
    active: NDArray[np.bool_] | None = None,
    initial_scale: float = 1.0,
    bounds: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
    initial_steps: NDArray[np.float64] | None = None,
    with_index: bool = False,
    floor: NDArray[np.float64] | None = None,
) -> list[OptimizeResult]:
    """Maximise from every start pose of ``x0`` (B, 26) in lockstep: one call of ``fun_batch``
    per iteration evaluates all candidates still running.

    Each candidate has its own step lengths, sign memory, best-so-far and early stop, and runs
    the very iterates :func:`maximise` would run from its start (without ``extra_iterations``):
    its result does not depend on the other candidates.  A candidate whose steps became
    negligible stops and is left out of the later calls.

    Parameters
    ----------
    fun_batch : callable
        ``fun_batch(thetas (k, 26), gradient=True) -> (values (k,), gradients (k, 26))`` for
        any ``k <= B`` (see :data:`BatchObjectiveFn`); the last iterations' poses are evaluated
        with ``gradient=False``.
    x0 : array, shape (B, 26)
        Start poses.
    iterations, steps, initial_scale
        As in :func:`maximise_steps`.
    active : bool array, shape (26,) or (B, 26), optional
        Parameters allowed to move, for all candidates or per candidate (default: all).
    bounds : (low, high) arrays, shape (26,) or (B, 26) each, optional
        Every iterate is projected into ``[low, high]`` (``x0`` too).
    initial_steps : array, shape (26,) or (B, 26), optional
        Start step lengths (mm / rad); override ``steps.initial`` and ``initial_scale``.
    with_index : bool
        Call ``fun_batch(thetas, gradient, index=index)`` with the candidates' positions in
        ``x0`` (k,) (for an objective with something of its own per candidate, e.g.
        ``Objective.batch``'s ``targets``).
    floor : array, shape (B,), optional
        The value each candidate must exceed to matter (a race: the search's fit score plus
        the candidate's margin).  From iteration ``iterations // 4`` on (its step lengths
        adapted), a candidate whose best value plus the iterations left times its last gain
        stays below its floor stops (status 2): it cannot reach the floor unless its gains
        grow again.  Without ``floor`` nothing stops early but by negligible steps.

    Returns
    -------
    list of OptimizeResult, one per candidate, in the order of ``x0``.
    """
    x = np.array(x0, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != N_PARAMS:
        raise ValueError(f"x0 must have shape (B, {N_PARAMS}), got {x.shape}")
    B = x.shape[0]
    shape = (B, N_PARAMS)
    if initial_steps is not None:
        step = np.array(np.broadcast_to(initial_steps, shape), dtype=np.float64)
    else:
        step = np.tile(steps.expand(steps.initial) * initial_scale, (B, 1))
    lo, hi = _limits_of(steps)
    mask = None if active is None else np.broadcast_to(np.asarray(active, bool), shape)
    lo_settled = np.broadcast_to(lo * 1.0001, shape)
    if mask is not None:  # inactive parameters count as settled
        lo_settled = np.where(mask, lo_settled, np.inf)
    low = high = None
    if bounds is not None:
        low = np.broadcast_to(np.asarray(bounds[0], dtype=np.float64), shape)
        high = np.broadcast_to(np.asarray(bounds[1], dtype=np.float64), shape)
        x = np.minimum(np.maximum(x, low), high)
    def evaluate(thetas: NDArray[np.float64], index: NDArray[np.int64], gradient: bool = True):
        if with_index:
            return fun_batch(thetas, gradient, index=index)
        return fun_batch(thetas, gradient)

    val, grad = evaluate(x, np.arange(B))
    assert grad is not None
    val = np.array(val, dtype=np.float64)
    grad = np.array(grad, dtype=np.float64)
    best_x, best_val = x.copy(), val.copy()
    history = np.full((iterations + 1, B), np.nan)
    history[0] = val
    prev_sign = np.zeros(shape)
    nit = np.zeros(B, dtype=np.int64)
    status = np.zeros(B, dtype=np.int64)
    run_ = np.arange(B)  # the candidates still running
    race_from = max(iterations // 4, 1)
    for it in range(1, iterations + 1):
        if not run_.size:
            break
        nit[run_] = it
        every = run_.size == B  # (typical: whole arrays, no gathers)
        sel = slice(None) if every else run_
        st = step[sel] if not every else step
        xs, sign = _step(
            x[sel], grad[sel], prev_sign[sel], st, None if mask is None else mask[sel], steps.grow,
            steps.shrink, lo, hi, None if low is None else low[sel], None if high is None else high[sel],
        )
        if not every:
            step[run_] = st
        prev_sign[sel] = sign
        x[sel] = xs
        if it < iterations:
            v, g = evaluate(xs, run_)
            assert g is not None
            grad[sel] = g
        else:  # the last iterate: only its value is used
            v = evaluate(xs, run_, False)[0]
        history[it, run_] = v
        better = v > best_val[run_]
        if better.any():
            up = run_[better]
            best_x[up] = xs[better]
            best_val[up] = v[better]
        settled = np.logical_and.reduce(st <= lo_settled[sel], axis=1)
        if settled.any():
            status[run_[settled]] = 1
            run_ = run_[~settled]
        if floor is not None and it >= race_from and it < iterations and run_.size:
            # (The best-so-far history: its last gain is >= 0.)
            gain = best_val[run_] - np.fmax.reduce(history[: it, run_], axis=0)
            out = best_val[run_] + (iterations - it) * gain < floor[run_]
            if out.any():
                status[run_[out]] = 2
                run_ = run_[~out]
    results = []
    for b in range(B):
        code = int(status[b])
        results.append(
            OptimizeResult(
                x=best_x[b].copy(),
                fun=float(best_val[b]),
                nit=int(nit[b]),
                success=bool(best_val[b] >= history[0, b]),
                status=code,
                message=_MESSAGES[code],
                history=history[: nit[b] + 1, b].copy(),
                steps=step[b].copy(),
            )
        )
    return results
