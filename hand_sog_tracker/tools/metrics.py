"""Fingertip error metrics of paper 000 (sec. 7), pure NumPy.

The paper reports, over a sequence, the mean Euclidean fingertip error
(overall and per finger) and the percentage of frames whose mean fingertip
error is below 15, 20, 25 and 30 mm.  All lengths here are millimetres.

Frames are counted as follows:

* a frame *with ground truth* is *scored*;
* a scored frame where the tracker gave no fingertips (NO_HAND, LOST, no
  output received) has an error of ``NaN``: it is left out of the mean errors
  but counts as *above every threshold* in the percentages (a failure must
  not improve the score);
* frames without ground truth are not scored at all (counted by the caller).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hand_sog_tracker.core.hand_model import FINGERS
from hand_sog_tracker.errors import InputError

__all__ = [
    "FINGERS",
    "THRESHOLDS_MM",
    "ErrorSummary",
    "TimingSummary",
    "fingertip_errors_mm",
    "pct_frames_below",
    "summarize_errors",
    "summarize_timings",
]

#: Thresholds (mm) of the paper's "% of frames below" table.
THRESHOLDS_MM: Final[tuple[int, ...]] = (15, 20, 25, 30)


@dataclass(frozen=True)
class ErrorSummary:
    """Fingertip error statistics of one sequence (millimetres).

    Attributes
    ----------
    frames_scored : int
        Frames with ground truth.
    frames_with_estimate : int
        Scored frames where the tracker produced fingertips.
    mean_mm : float
        Mean over frames with an estimate and over the five fingers; NaN if none.
    per_finger_mm : dict[str, float]
        Mean error per finger (keys :data:`FINGERS`); NaN if no estimate.
    pct_below_mm : dict[str, float]
        Percentage (0-100) of scored frames whose mean fingertip error is
        below each threshold (keys ``"15"``, ``"20"``, ...); frames without an
        estimate count as failures.  NaN if no frame was scored.
    """

    frames_scored: int
    frames_with_estimate: int
    mean_mm: float
    per_finger_mm: dict[str, float]
    pct_below_mm: dict[str, float]


@dataclass(frozen=True)
class TimingSummary:
    """Per-frame wall-time statistics (milliseconds; NaN when empty)."""

    median_ms: float
    p95_ms: float
    mean_ms: float
    count: int


def fingertip_errors_mm(estimate_mm: ArrayLike, truth_mm: ArrayLike) -> NDArray[np.float64]:
    """Euclidean distance of each fingertip.

    Parameters
    ----------
    estimate_mm, truth_mm : array, shape (..., 5, 3)
        Fingertip positions (thumb .. little), millimetres.

    Returns
    -------
    array, shape (..., 5)
        Errors in millimetres.

    Raises
    ------
    InputError
        If the shapes differ or are not (..., 5, 3).
    """
    est = np.asarray(estimate_mm, dtype=np.float64)
    gt = np.asarray(truth_mm, dtype=np.float64)
    if est.shape != gt.shape or est.shape[-2:] != (5, 3):
        raise InputError(
            f"fingertip arrays must both have shape (..., 5, 3), got {est.shape} and {gt.shape}"
        )
    return np.linalg.norm(est - gt, axis=-1)


def pct_frames_below(
    frame_errors_mm: ArrayLike, thresholds_mm: ArrayLike
) -> NDArray[np.float64]:
    """Percentage of frames whose error is strictly below each threshold.

    Parameters
    ----------
    frame_errors_mm : array, shape (N,)
        Mean fingertip error of each scored frame, mm; NaN = no estimate
        (counts as a failure).
    thresholds_mm : array, shape (K,)
        Thresholds, mm.

    Returns
    -------
    array, shape (K,)
        Percentages in [0, 100]; NaN when ``N == 0``.
    """
    err = np.asarray(frame_errors_mm, dtype=np.float64).reshape(-1)
    thr = np.asarray(thresholds_mm, dtype=np.float64).reshape(-1)
    if err.size == 0:
        return np.full(thr.shape, np.nan)
    ok = np.where(np.isnan(err), np.inf, err)
    return 100.0 * np.mean(ok[None, :] < thr[:, None], axis=1)


def summarize_errors(
    errors_mm: ArrayLike, thresholds_mm: Sequence[int] = THRESHOLDS_MM
) -> ErrorSummary:
    """Summarise per-frame, per-finger errors into the paper's table.

    Parameters
    ----------
    errors_mm : array, shape (N, 5)
        Fingertip errors of every scored frame (thumb .. little), mm; a row of
        NaN marks a frame without an estimate.
    thresholds_mm : sequence of int
        Thresholds of the percentage table, mm.

    Returns
    -------
    ErrorSummary

    Raises
    ------
    InputError
        If ``errors_mm`` is not (N, 5), has negative values, or a row is only
        partly NaN.
    """
    err = np.asarray(errors_mm, dtype=np.float64)
    if err.size == 0:
        err = err.reshape(0, 5)
    if err.ndim != 2 or err.shape[1] != 5:
        raise InputError(f"errors_mm must have shape (N, 5), got {err.shape}")
    nan = np.isnan(err)
    if np.any(nan.any(axis=1) != nan.all(axis=1)):
        raise InputError("a frame's fingertip errors must be all NaN or all finite")
    if np.any(err[~nan] < 0) or np.any(np.isinf(err)):
        raise InputError("fingertip errors must be finite and non-negative")
    have = ~nan[:, 0]
    est = err[have]
    frame_err = err.mean(axis=1)  # NaN rows stay NaN
    if est.shape[0]:
        mean = float(est.mean())
        per = {f: float(v) for f, v in zip(FINGERS, est.mean(axis=0))}
    else:
        mean = float("nan")
        per = {f: float("nan") for f in FINGERS}
    pct = pct_frames_below(frame_err, list(thresholds_mm))
    return ErrorSummary(
        frames_scored=int(err.shape[0]),
        frames_with_estimate=int(est.shape[0]),
        mean_mm=mean,
        per_finger_mm=per,
        pct_below_mm={str(int(t)): float(p) for t, p in zip(thresholds_mm, pct)},
    )


def summarize_timings(ms: ArrayLike) -> TimingSummary:
    """Median, 95th percentile and mean of per-frame times.

    Parameters
    ----------
    ms : array, shape (N,)
        Wall times, milliseconds (NaN entries are ignored).
    """
    a = np.asarray(ms, dtype=np.float64).reshape(-1)
    a = a[~np.isnan(a)]
    if a.size == 0:
        nan = float("nan")
        return TimingSummary(median_ms=nan, p95_ms=nan, mean_ms=nan, count=0)
    return TimingSummary(
        median_ms=float(np.median(a)),
        p95_ms=float(np.percentile(a, 95)),
        mean_ms=float(a.mean()),
        count=int(a.size),
    )
