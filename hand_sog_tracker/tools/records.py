"""Evaluation records: per-frame outcomes, one bag's evaluation, pooled totals, progress bar.

One job: the values of an evaluation; kept together because every evaluation mode fills and
pools the same records.

The values the evaluation tools pass around (see :mod:`hand_sog_tracker.tools.evaluation`
for the core-mode evaluation, :mod:`hand_sog_tracker.tools.node_eval` for the node,
:mod:`hand_sog_tracker.tools.report` for their output).  Scoring follows
:mod:`hand_sog_tracker.tools.metrics`: frames without ground truth are not
scored; scored frames without an estimate are left out of the mean errors and
count as failures in the "% of frames below" table.  :func:`pool` merges several
bags frame-weighted (the totals of the multi-bag table).

(About 400 lines: the value types only, each with its docstring; no I/O.)
"""

from __future__ import annotations

import heapq
import itertools
import math
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol, Sequence, TextIO

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.hand_model import HandModel
from hand_sog_tracker.core.types import Intrinsics, TrackResult
from hand_sog_tracker.errors import BagError
from hand_sog_tracker.tools.metrics import (
    ErrorSummary,
    TimingSummary,
    fingertip_errors_mm,
    summarize_errors,
    summarize_timings,
)

__all__ = [
    "CALIBRATION_FRAMES",
    "FIT_FRAMES",
    "STATUS_ERROR",
    "STATUS_NO_OUTPUT",
    "STATUS_NO_ESTIMATE",
    "TrackerLike",
    "FrameRecord",
    "WorstFrame",
    "WorstFrames",
    "Evaluation",
    "Pooled",
    "Progress",
    "build_evaluation",
    "pool",
    "json_clean",
]

#: Frames ``--calibrate`` fits the hand model on; the next ones up to ``CALIBRATION_FRAMES``
#: are held out to check the fit (the calibration's guard).
FIT_FRAMES = 3
CALIBRATION_FRAMES = 6
#: Status of a frame whose image could not be used (bad encoding, size mismatch).
STATUS_ERROR = "error"
#: Status of a frame the node published nothing for (``--through-node``: dropped or no hand).
STATUS_NO_OUTPUT = "no_output"
#: Status of a frame the node answered without fingertips (``--through-node``: DELETEALL markers).
STATUS_NO_ESTIMATE = "no_estimate"


class TrackerLike(Protocol):
    """What :func:`evaluate_core` needs of a tracker (the core Tracker fits)."""

    def process(self, depth_mm: NDArray, intrinsics: Intrinsics) -> TrackResult: ...


@dataclass(frozen=True, eq=False)
class FrameRecord:
    """Outcome of one depth image.

    Attributes
    ----------
    index : int
        Position among the bag's depth images.
    stamp_ns : int
        Header stamp of the depth image.
    status : str
        Core mode: ``tracking``, ``lost``, ``no_hand`` or ``error`` (unusable
        image).  Node mode: ``tracking``, ``no_estimate`` (markers deleted)
        or ``no_output`` (dropped, or no hand).
    estimate_mm : array, shape (5, 3) or None
        Tracked fingertips, mm.
    truth_mm : array, shape (5, 3) or None
        Ground-truth fingertips, mm.
    ms : float
        Processing time (core mode) or end-to-end latency (node mode), ms;
        NaN when not measured.
    """

    index: int
    stamp_ns: int
    status: str
    estimate_mm: NDArray[np.float64] | None
    truth_mm: NDArray[np.float64] | None
    ms: float

    @property
    def errors_mm(self) -> NDArray[np.float64] | None:
        """Per-finger error (5,) mm; NaN if no estimate; None without ground truth."""
        if self.truth_mm is None:
            return None
        if self.estimate_mm is None:
            return np.full(5, np.nan)
        return fingertip_errors_mm(self.estimate_mm, self.truth_mm)


@dataclass(frozen=True, eq=False)
class WorstFrame:
    """A frame kept for an overlay picture (one of the worst of its bag).

    Attributes
    ----------
    record : FrameRecord
        Its evaluation record (``errors_mm`` gives the per-finger errors).
    depth_mm : array, shape (H, W)
        The depth image, mm (0 = invalid).
    intrinsics : Intrinsics
    pose : array, shape (26,) or None
        Tracked pose (None when the tracker gave none or has no pose).
    model : HandModel or None
        Hand model the pose belongs to (None for a tracker without ``model``).
    """

    record: FrameRecord
    depth_mm: NDArray[np.float32]
    intrinsics: Intrinsics
    pose: NDArray[np.float64] | None
    model: HandModel | None

    @property
    def error_mm(self) -> float:
        """Mean fingertip error, mm; ``inf`` without an estimate (a failure ranks worst)."""
        e = self.record.errors_mm
        return math.inf if e is None or not np.all(np.isfinite(e)) else float(np.mean(e))


class WorstFrames:
    """The ``n`` scored frames with the largest mean error (bounded memory)."""

    def __init__(self, n: int) -> None:
        self.n = max(int(n), 0)
        self._heap: list[tuple[float, int, WorstFrame]] = []
        self._tie = itertools.count()

    def offer(self, make: Callable[[], WorstFrame], record: FrameRecord) -> None:
        """Keep ``make()`` (a WorstFrame) if ``record`` is among the worst so far."""
        if self.n == 0 or record.truth_mm is None or record.errors_mm is None:
            return
        e = record.errors_mm
        err = math.inf if not np.all(np.isfinite(e)) else float(np.mean(e))
        key = (err, -next(self._tie))  # equal errors: the earlier frame wins
        if len(self._heap) < self.n:
            heapq.heappush(self._heap, (*key, make()))
        elif key > self._heap[0][:2]:
            heapq.heapreplace(self._heap, (*key, make()))

    def worst_first(self) -> tuple[WorstFrame, ...]:
        """The kept frames, worst first."""
        return tuple(w for *_, w in sorted(self._heap, key=lambda t: t[:2], reverse=True))


@dataclass(frozen=True, eq=False)
class Evaluation:
    """Result of evaluating one bag (see :meth:`to_json`).

    ``split`` is the bag's split from its ``hand_sog_sample.json`` sidecar
    (``dev``, ``test``, ``capsule``; ``-`` when unknown) and ``worst`` the
    frames kept for overlays (worst first; empty unless asked for).
    """

    bag: str
    mode: str
    records: tuple[FrameRecord, ...]
    errors: ErrorSummary
    timing: TimingSummary
    wall_s: float
    image_size: tuple[int, int] | None
    calibration: dict[str, Any] | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    split: str = "-"
    worst: tuple[WorstFrame, ...] = ()

    @property
    def name(self) -> str:
        """Short name of the bag (its directory or file name)."""
        return Path(self.bag).name or self.bag

    @property
    def frames(self) -> int:
        """Depth images evaluated."""
        return len(self.records)

    @property
    def frames_without_truth(self) -> int:
        """Depth images without ground truth (tracked, not scored)."""
        return sum(r.truth_mm is None for r in self.records)

    @property
    def status_counts(self) -> dict[str, int]:
        """Frames per status."""
        return dict(sorted(Counter(r.status for r in self.records).items()))

    @property
    def fps(self) -> float:
        """Frames per second of tracking (core: 1000 / mean ms; node: output rate)."""
        if "fps" in self.extra:
            return float(self.extra["fps"])
        return 1000.0 / self.timing.mean_ms if self.timing.count and self.timing.mean_ms > 0 else math.nan

    def frame_errors_mm(self) -> NDArray[np.float64]:
        """Mean fingertip error of each scored frame, shape (N,), mm (NaN = no estimate)."""
        rows = [e for e in (r.errors_mm for r in self.records) if e is not None]
        return np.array([float(np.mean(e)) for e in rows], dtype=np.float64)

    def to_json(self, per_frame: bool = True) -> dict[str, Any]:
        """JSON-ready dict (NaN written as null); ``per_frame=False`` leaves the frame records out."""
        e = self.errors
        out: dict[str, Any] = {
            "bag": self.bag,
            "name": self.name,
            "split": self.split,
            "mode": self.mode,
            "frames": self.frames,
            "frames_scored": e.frames_scored,
            "frames_without_ground_truth": self.frames_without_truth,
            "frames_with_estimate": e.frames_with_estimate,
            "mean_fingertip_error_mm": e.mean_mm,
            "per_finger_mm": dict(e.per_finger_mm),
            "pct_frames_below_mm": dict(e.pct_below_mm),
            "ms_per_frame": {
                "median": self.timing.median_ms,
                "p95": self.timing.p95_ms,
                "mean": self.timing.mean_ms,
            },
            "fps": self.fps,
            "status_counts": self.status_counts,
            "wall_time_s": self.wall_s,
            "image_size": list(self.image_size) if self.image_size else None,
            "calibration": self.calibration,
            **self.extra,
        }
        if per_frame:
            out["per_frame"] = [
                {
                    "index": r.index,
                    "stamp_ns": r.stamp_ns,
                    "status": r.status,
                    "error_mm": None if r.errors_mm is None else float(np.mean(r.errors_mm)),
                    "per_finger_mm": None if r.errors_mm is None else [float(x) for x in r.errors_mm],
                    "ms": r.ms,
                }
                for r in self.records
            ]
        return json_clean(out)


def json_clean(obj: Any) -> Any:
    """``obj`` with numpy scalars made Python numbers and non-finite floats made None."""
    if isinstance(obj, dict):
        return {str(k): json_clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_clean(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj



class Progress:
    """A one-line progress bar on a terminal (disabled when not a tty).

    Parameters
    ----------
    total : int
        Expected number of steps (0 = unknown).
    stream : text stream
        Where to draw; default ``sys.stderr``.
    enabled : bool, optional
        Default: ``stream.isatty()``.
    """

    def __init__(self, total: int, stream: TextIO | None = None, enabled: bool | None = None) -> None:
        self.total = max(int(total), 0)
        self.stream = stream if stream is not None else sys.stderr
        if enabled is None:
            isatty = getattr(self.stream, "isatty", None)
            enabled = bool(isatty and isatty())
        self.enabled = enabled
        self.count = 0
        self._last = 0.0

    def update(self, n: int = 1, note: str = "") -> None:
        """Advance by ``n`` and redraw (at most ~20 times a second)."""
        self.count += n
        if not self.enabled:
            return
        now = time.monotonic()
        if now - self._last < 0.05 and self.count < self.total:
            return
        self._last = now
        width = 30
        if self.total:
            done = min(self.count / self.total, 1.0)
            bar = "#" * int(round(done * width))
            text = f"\r[{bar:<{width}}] {self.count}/{self.total} {note}"
        else:
            text = f"\r{self.count} frames {note}"
        self.stream.write(text[:120].ljust(80))
        self.stream.flush()

    def close(self) -> None:
        """Finish the line."""
        if self.enabled:
            self.stream.write("\n")
            self.stream.flush()


def build_evaluation(
    bag: str,
    mode: str,
    records: Sequence[FrameRecord],
    wall_s: float,
    image_size: tuple[int, int] | None,
    calibration: dict[str, Any] | None = None,
    extra: dict[str, Any] | None = None,
) -> Evaluation:
    """Summarise frame records into an :class:`Evaluation`.

    Raises
    ------
    BagError
        If no frame has ground truth.
    """
    scored = [r.errors_mm for r in records if r.truth_mm is not None]
    if not scored:
        raise BagError(
            f"bag {bag}: none of the {len(records)} depth images has ground truth with the same "
            "stamp; nothing to score"
        )
    errors = summarize_errors(np.array(scored, dtype=np.float64).reshape(-1, 5))
    timing = summarize_timings([r.ms for r in records])
    return Evaluation(
        bag=bag,
        mode=mode,
        records=tuple(records),
        errors=errors,
        timing=timing,
        wall_s=wall_s,
        image_size=image_size,
        calibration=calibration,
        extra=dict(extra or {}),
    )




@dataclass(frozen=True)
class Pooled:
    """Several bags' frames taken together (frame-weighted totals).

    Attributes
    ----------
    label : str
        What was pooled (``total dev``, ``total``, ...).
    bags : int
    frames : int
        Depth images of all the bags.
    errors : ErrorSummary
        Over every scored frame of every bag.
    timing : TimingSummary
        Over every timed frame of every bag.
    """

    label: str
    bags: int
    frames: int
    errors: ErrorSummary
    timing: TimingSummary

    def to_json(self) -> dict[str, Any]:
        """JSON-ready dict (NaN written as null)."""
        e = self.errors
        return json_clean(
            {
                "label": self.label,
                "bags": self.bags,
                "frames": self.frames,
                "frames_scored": e.frames_scored,
                "frames_with_estimate": e.frames_with_estimate,
                "mean_fingertip_error_mm": e.mean_mm,
                "per_finger_mm": dict(e.per_finger_mm),
                "pct_frames_below_mm": dict(e.pct_below_mm),
                "ms_per_frame": {"median": self.timing.median_ms, "p95": self.timing.p95_ms,
                                 "mean": self.timing.mean_ms},
            }
        )


def pool(evaluations: Sequence[Evaluation], label: str) -> Pooled:
    """Pool the frames of ``evaluations``: every scored frame and every timing counts once."""
    scored = [r.errors_mm for ev in evaluations for r in ev.records if r.truth_mm is not None]
    errors = summarize_errors(np.array(scored, dtype=np.float64).reshape(-1, 5))
    timing = summarize_timings([r.ms for ev in evaluations for r in ev.records])
    return Pooled(label, len(evaluations), sum(ev.frames for ev in evaluations), errors, timing)
