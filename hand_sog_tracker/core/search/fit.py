"""The batch fit of a frame's candidates and the selection of its answer."""

from __future__ import annotations

from typing import Any, Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.depth_sog import MAX_DATA_GAUSSIANS, ImageSoG
from hand_sog_tracker.core.hand_model import N_PARAMS
from hand_sog_tracker.core.objective import Objective, TipTargets
from hand_sog_tracker.core.optimizer import OptimizeResult, maximise_batch
from hand_sog_tracker.core.search.candidates import Candidate, Frame, Proposal, pull_objective

__all__ = ["MAX_BATCH", "SEARCH_ITERATIONS", "batch_size", "fit_batch", "fit_parts", "part", "search", "with_targets"]

#: Iterations each candidate gets (and each detection pull before it; chosen here, commit f16019d).
SEARCH_ITERATIONS = 12
#: Most candidates fitted in one call at the data cap: a batch holds its model x data arrays once
#: per candidate (memory, issue 50); fewer data Gaussians fit as many more (:func:`batch_size`).
MAX_BATCH = 4


def batch_size(n_data: int) -> int:
    """Most candidates fitted in one call on ``n_data`` data Gaussians: ``MAX_BATCH``'s pairs at the cap."""
    return MAX_BATCH * max(1, MAX_DATA_GAUSSIANS // max(n_data, 1))


def part(data: ImageSoG, keep: NDArray[np.bool_]) -> ImageSoG:
    """The Gaussians of ``data`` where ``keep`` (n,) is True (``data`` itself when all are)."""
    return data if keep.all() else data.subset(keep)


def fit_batch(
    fun_batch: Callable, starts: NDArray[np.float64], n_data: int = MAX_DATA_GAUSSIANS, **kwargs: Any
) -> list[OptimizeResult]:
    """:func:`maximise_batch` of ``starts`` (B, 26) on ``n_data`` data Gaussians in chunks of
    :func:`batch_size` (a fit does not depend on its batch); ``with_index``: positions in ``starts``."""
    out: list[OptimizeResult] = []
    size = batch_size(n_data)
    for k in range(0, len(starts), size):
        fun = fun_batch
        if kwargs.get("with_index") and k:

            def fun(thetas: NDArray[np.float64], gradient: bool = True, index: Any = None, _k: int = k) -> Any:
                return fun_batch(thetas, gradient, index=index + _k)

        # (Per-candidate ``active`` or ``initial_steps`` (B, 26), ``floor`` (B,): this chunk's rows.)
        chunk = {
            key: value[k : k + size]
            if (key in ("active", "initial_steps") and np.ndim(value) == 2) or key == "floor"
            else value
            for key, value in kwargs.items()
        }
        out += maximise_batch(fun, starts[k : k + size], **chunk)
    return out


def with_targets(
    obj: Objective, targets: Sequence[TipTargets | None] | None = None, parts: NDArray[np.bool_] | None = None
) -> Callable[..., tuple]:
    """``obj.batch`` as :func:`maximise_batch` calls it ``with_index``: candidate ``i`` with
    ``targets[i]`` (as ``obj.variant(obj.config, targets[i])`` alone) and on the data ``parts[i]`` (n,)."""

    def fun(
        thetas: NDArray[np.float64], gradient: bool = True, index: NDArray[np.int64] | None = None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        assert index is not None
        return obj.batch(
            thetas, gradient, targets=None if targets is None else [targets[i] for i in index.tolist()],
            parts=None if parts is None else parts[index],
        )

    return fun


def fit_parts(
    obj: Objective, starts: NDArray[np.float64], parts: NDArray[np.bool_],
    targets: Sequence[TipTargets | None] | None = None, **kwargs: Any,
) -> list[OptimizeResult]:
    """Each of ``starts`` (B, 26) fitted on ``obj`` with only its part ``parts[b]`` (B, n) of the data
    and ``targets[b]`` as one batch (a lone pose without targets: on its part's own objective)."""
    if len(starts) == 1 and targets is None:
        keep = parts[0]
        if not keep.all():
            obj = Objective(obj.model, obj.data.subset(keep), obj.config, silhouette=obj.silhouette)
        return fit_batch(obj.batch, starts, obj.data.n, **kwargs)
    fun = with_targets(obj, targets, None if parts.all() else parts)
    return fit_batch(fun, starts, obj.data.n, with_index=True, **kwargs)


def search(frame: Frame, proposals: Sequence[Proposal]) -> tuple[OptimizeResult, str | None]:
    """The frame's answer and the name of the proposal it came from (None: the frame's fit).

    Every candidate is fitted ``SEARCH_ITERATIONS`` on ``frame.plain`` as one batch (a pull first on
    its own objective); the best :meth:`Frame.score` beating the fit's by its margin wins.  A
    candidate whose value cannot reach that (a score is the value minus a cost >= 0) stops early.
    """
    candidates = [c for p in proposals if not p.rides_along for c in p.generate(frame)]
    if not candidates:
        return frame.fit, None
    candidates += [c for p in proposals if p.rides_along for c in p.generate(frame)]
    starts = _pulled(candidates, frame.obj, frame.limits)
    floor = frame.score(frame.fit.x, _plain_value(frame)) + np.array([c.margin for c in candidates])
    fits = fit_batch(
        frame.plain.batch, starts, frame.plain.data.n, iterations=SEARCH_ITERATIONS, bounds=frame.limits, floor=floor
    )
    best, best_val, name = frame.fit, -np.inf, None
    for c, res, low in zip(candidates, fits, floor.tolist()):
        # (a score is at most the value: a candidate whose value cannot win is not scored)
        if res.fun > max(low, best_val) and (val := frame.score(res.x, res.fun)) > max(low, best_val):
            best, best_val, name = res, val, c.proposal
    return best, name


def _plain_value(frame: Frame) -> float:
    """``frame.plain`` at the fit's pose: the fit's value on ``frame.obj`` with its salient term
    added back (the only term the two differ in), without evaluating the data terms again."""
    if frame.plain is frame.obj:
        return frame.fit.fun
    return frame.fit.fun + frame.obj.config.w_sal * frame.obj.salient(frame.fit.x)


def _pulled(
    candidates: Sequence[Candidate], obj: Objective, limits: tuple[NDArray[np.float64], NDArray[np.float64]]
) -> NDArray[np.float64]:
    """The candidates' start poses (B, 26), a pulled one's after ``SEARCH_ITERATIONS`` on the frame's
    :func:`pull_objective` with its targets and ``active`` parameters (all pulls as one batch)."""
    starts = np.array([c.x0 for c in candidates])
    ks = [i for i, c in enumerate(candidates) if c.pull is not None]
    if ks:
        pull, rows = pull_objective(obj), [candidates[i] for i in ks]
        active = np.array([np.ones(N_PARAMS, bool) if c.active is None else c.active for c in rows])
        fits = fit_batch(
            with_targets(pull, [c.pull for c in rows]), starts[ks], pull.data.n, iterations=SEARCH_ITERATIONS,
            active=active, bounds=limits, with_index=True,
        )
        starts[ks] = [r.x for r in fits]
    return starts
