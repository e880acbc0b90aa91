"""The batch fit of a frame's candidates and the selection of its answer."""

from __future__ import annotations

from typing import Any, Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.optimizer import OptimizeResult, maximise, maximise_batch
from hand_sog_tracker.core.search.candidates import Candidate, Frame, Proposal

__all__ = ["MAX_BATCH", "SEARCH_ITERATIONS", "fit_batch", "search"]

#: Iterations each candidate gets (and each detection pull before it; chosen here, commit f16019d).
SEARCH_ITERATIONS = 12
#: Most candidates fitted in one call: a batch holds its model x data arrays once per candidate
#: (a frame with many data Gaussians and 11 candidates peaked 75 MB above steady tracking).
MAX_BATCH = 4


def fit_batch(fun_batch: Callable, starts: NDArray[np.float64], **kwargs: Any) -> list[OptimizeResult]:
    """:func:`maximise_batch` of ``starts`` (B, 26) in chunks of at most ``MAX_BATCH`` (a
    candidate's fit does not depend on its batch)."""
    out: list[OptimizeResult] = []
    for k in range(0, len(starts), MAX_BATCH):
        out += maximise_batch(fun_batch, starts[k : k + MAX_BATCH], **kwargs)
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
    fits = fit_batch(frame.plain.batch, starts, iterations=SEARCH_ITERATIONS, bounds=frame.limits)
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
