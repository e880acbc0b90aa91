"""The batch fit of a frame's candidates and the selection of its answer."""

from __future__ import annotations

from typing import Any, Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.depth_sog import MAX_DATA_GAUSSIANS
from hand_sog_tracker.core.optimizer import OptimizeResult, maximise, maximise_batch
from hand_sog_tracker.core.search.candidates import Candidate, Frame, Proposal

__all__ = ["MAX_BATCH", "SEARCH_ITERATIONS", "batch_size", "fit_batch", "search"]

#: Iterations each candidate gets (and each detection pull before it; chosen here, commit f16019d).
SEARCH_ITERATIONS = 12
#: Most candidates fitted in one call at the data cap: a batch holds its model x data arrays once
#: per candidate (a frame with many data Gaussians and 11 candidates peaked 75 MB above steady
#: tracking); a frame with fewer data Gaussians fits as many more in one call as the same pairs
#: hold (:func:`batch_size`).
MAX_BATCH = 4


def batch_size(n_data: int) -> int:
    """Most candidates fitted in one call on ``n_data`` data Gaussians: at most the model x data
    pairs of ``MAX_BATCH`` candidates at the data cap (``MAX_DATA_GAUSSIANS``)."""
    return MAX_BATCH * max(1, MAX_DATA_GAUSSIANS // max(n_data, 1))


def fit_batch(
    fun_batch: Callable, starts: NDArray[np.float64], n_data: int = MAX_DATA_GAUSSIANS, **kwargs: Any
) -> list[OptimizeResult]:
    """:func:`maximise_batch` of ``starts`` (B, 26) on ``n_data`` data Gaussians, in chunks of
    at most :func:`batch_size` (a candidate's fit does not depend on its batch).  With
    ``with_index``, ``fun_batch`` gets the candidates' positions in ``starts``."""
    out: list[OptimizeResult] = []
    size = batch_size(n_data)
    for k in range(0, len(starts), size):
        fun = fun_batch
        if kwargs.get("with_index") and k:

            def fun(thetas: NDArray[np.float64], gradient: bool = True, index: Any = None, _k: int = k) -> Any:
                return fun_batch(thetas, gradient, index=index + _k)

        out += maximise_batch(fun, starts[k : k + size], **kwargs)
    return out


def search(frame: Frame, proposals: Sequence[Proposal]) -> tuple[OptimizeResult, str | None]:
    """The frame's answer: its fit or the best of the candidates ``proposals`` make for it.

    Every candidate is fitted ``SEARCH_ITERATIONS`` on ``frame.plain``, all as one batch (a
    pull first on its own objective); one wins when its :meth:`Frame.score` beats the fit's by
    the candidate's margin, and of the winners the highest score is the answer.  Returns the
    answer's fit and the name of the proposal it came from (None: the frame's fit).
    """
    candidates = [c for p in proposals for c in p.generate(frame)]
    if not candidates:
        return frame.fit, None
    starts = np.array([_pulled(c, frame.limits) for c in candidates])
    fits = fit_batch(frame.plain.batch, starts, frame.plain.data.n, iterations=SEARCH_ITERATIONS, bounds=frame.limits)
    base = frame.score(frame.fit.x)
    best, best_val, name = frame.fit, -np.inf, None
    for c, res in zip(candidates, fits):
        val = frame.score(res.x, res.fun)
        if val > base + c.margin and val > best_val:
            best, best_val, name = res, val, c.proposal
    return best, name


def _pulled(c: Candidate, limits: tuple[NDArray[np.float64], NDArray[np.float64]]) -> NDArray[np.float64]:
    """The candidate's start pose (26,): after its pull, when it has one (its own objective)."""
    if c.pull is None:
        return c.x0
    return maximise(c.pull, c.x0, iterations=SEARCH_ITERATIONS, active=c.active, bounds=limits).x
