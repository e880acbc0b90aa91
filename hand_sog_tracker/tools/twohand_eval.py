"""Scoring per-hand predictions on two-hand bags: each hand matched by handedness, identity swaps.

One job: the two-hand score; kept together because the prediction interface, the matching and the
summary are one definition.

*Prediction interface* (for any tracker): a :data:`Predictor` is a callable
``(depth_mm (H, W) mm, intrinsics) -> sequence of HandPrediction`` (handedness, fingertips (5, 3)
mm, confidence), called once per depth image in order.  :func:`one_hand_predictor` wraps today's
one-hand core :class:`~hand_sog_tracker.core.tracker.Tracker` (one prediction labelled with its
configured handedness while it tracks).

*Score* (:func:`score_two_hands`), per frame with per-hand ground truth (:mod:`.twohand_bags`):

* per hand: the prediction labelled with that hand (the most confident, if several) against that
  hand's truth, the paper's metrics of :mod:`.metrics`; no such prediction = missing (NaN error,
  a failure in the percentages);
* position match: predictions are assigned to the truth hands by the smallest summed mean
  fingertip distance (every one-to-one assignment is tried), a pair farther than
  :data:`MATCH_GATE_MM` is no match;
* handedness accuracy: of the position-matched predictions, the share labelled with the hand they
  are on;
* identity swaps: per label, the number of times its position match changes from one hand to the
  other between the frames where it is matched (a label that follows the left hand, loses it and
  comes back on the right hand swapped once); ``followed`` counts the frames each label spent on
  each hand.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Final, Sequence

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.types import Intrinsics, TrackerConfig, TrackerStatus
from hand_sog_tracker.errors import BagError, InputError
from hand_sog_tracker.synth.twohands import HANDS
from hand_sog_tracker.tools.bagio import BagTopics, DepthBagReader
from hand_sog_tracker.tools.metrics import ErrorSummary, TimingSummary, summarize_errors, summarize_timings
from hand_sog_tracker.tools.records import json_clean
from hand_sog_tracker.tools.twohand_bags import HandTruthRecord, hand_topic, read_hand_truth

__all__ = [
    "MATCH_GATE_MM",
    "HandPrediction",
    "Predictor",
    "TwoHandRecord",
    "TwoHandSummary",
    "position_match",
    "score_two_hands",
    "one_hand_predictor",
    "multi_hand_predictor",
    "evaluate_two_hands_core",
    "evaluate_two_hands_node",
    "format_two_hand_table",
    "summary_as_dict",
]

#: A prediction whose mean fingertip distance to a hand exceeds this explains neither hand (mm):
#: well above the 30 mm of the paper's last threshold, below the ~100 mm between two hands' tips.
MATCH_GATE_MM: Final[float] = 50.0


@dataclass(frozen=True, eq=False)
class HandPrediction:
    """One tracked hand in one frame.

    Attributes
    ----------
    handedness : {"left", "right"}
    fingertips_mm : array, shape (5, 3)
        Thumb .. little, camera optical frame, mm.
    confidence : float
        In [0, 1].
    """

    handedness: str
    fingertips_mm: NDArray[np.float64]
    confidence: float = 1.0

    def __post_init__(self) -> None:
        if self.handedness not in HANDS:
            raise InputError(f"handedness must be 'left' or 'right', got {self.handedness!r}")
        tips = np.asarray(self.fingertips_mm, dtype=np.float64)
        if tips.shape != (5, 3):
            raise InputError(f"fingertips_mm must have shape (5, 3), got {tips.shape}")
        object.__setattr__(self, "fingertips_mm", tips)


#: ``(depth_mm (H, W), intrinsics) -> predictions`` of one frame, called in frame order.
Predictor = Callable[[NDArray, Intrinsics], Sequence[HandPrediction]]


@dataclass(frozen=True, eq=False)
class TwoHandRecord:
    """One frame: per-hand truth (``None`` = no truth for that hand), visibility, predictions, time."""

    index: int
    stamp_ns: int
    truth: dict[str, NDArray[np.float64] | None]
    visible_fraction: dict[str, float]
    predictions: tuple[HandPrediction, ...]
    ms: float = math.nan


@dataclass(frozen=True)
class TwoHandSummary:
    """Score of one two-hand bag.

    Attributes
    ----------
    per_hand : dict
        ``left`` / ``right`` -> :class:`~.metrics.ErrorSummary` of the prediction with that label.
    handedness_accuracy_pct : float
        Of the position-matched predictions, % labelled with their hand (NaN if none matched).
    matched_predictions : int
    swaps : int
        Identity swaps, all labels.
    swap_frames : tuple of int
    followed : dict
        label -> {"left": frames, "right": frames, "none": frames} where it was on each truth hand.
    mean_visible_fraction : dict
        ``left`` / ``right`` -> mean visible fraction of that hand over the frames (NaN if unknown).
    timing : TimingSummary
    """

    bag: str
    split: str
    mode: str
    frames: int
    per_hand: dict[str, ErrorSummary]
    handedness_accuracy_pct: float
    matched_predictions: int
    swaps: int
    swap_frames: tuple[int, ...]
    followed: dict[str, dict[str, int]]
    mean_visible_fraction: dict[str, float]
    timing: TimingSummary
    extra: dict[str, Any] = field(default_factory=dict)


def _finite_mean(values: Sequence[float]) -> float:
    a = np.asarray(values, dtype=np.float64)
    a = a[np.isfinite(a)]
    return float(a.mean()) if a.size else math.nan


def _mean_dist(a: NDArray[np.float64], b: NDArray[np.float64]) -> float:
    return float(np.linalg.norm(a - b, axis=-1).mean())


def position_match(
    predictions: Sequence[HandPrediction], truth: dict[str, NDArray[np.float64] | None], gate_mm: float = MATCH_GATE_MM
) -> list[str | None]:
    """The truth hand (``left`` / ``right``) each prediction is on, or None (see the module docstring)."""
    sides = [s for s in HANDS if truth.get(s) is not None]
    n = len(predictions)
    best: tuple[float, tuple[str | None, ...]] = (math.inf, (None,) * n)
    options: list[str | None] = [*sides, None]
    for assign in itertools.product(options, repeat=n):
        used = [a for a in assign if a is not None]
        if len(used) != len(set(used)):
            continue
        cost, ok = 0.0, True
        for p, a in zip(predictions, assign):
            if a is None:
                cost += gate_mm
                continue
            d = _mean_dist(p.fingertips_mm, truth[a])  # type: ignore[arg-type]
            if d > gate_mm:
                ok = False
                break
            cost += d
        if ok and cost < best[0]:
            best = (cost, assign)
    return list(best[1])


def score_two_hands(
    records: Sequence[TwoHandRecord], bag: str = "-", split: str = "-", mode: str = "core",
    extra: dict[str, Any] | None = None,
) -> TwoHandSummary:
    """Score frames of per-hand predictions (see the module docstring)."""
    errors: dict[str, list[NDArray[np.float64]]] = {s: [] for s in HANDS}
    vis: dict[str, list[float]] = {s: [] for s in HANDS}
    matched = correct = 0
    last: dict[str, str] = {}
    swaps: list[int] = []
    followed = {s: {"left": 0, "right": 0, "none": 0} for s in HANDS}
    for r in records:
        for s in HANDS:
            gt = r.truth.get(s)
            if gt is None:
                continue
            vis[s].append(r.visible_fraction.get(s, math.nan))
            mine = [p for p in r.predictions if p.handedness == s]
            if mine:
                p = max(mine, key=lambda q: q.confidence)
                errors[s].append(np.linalg.norm(p.fingertips_mm - gt, axis=1))
            else:
                errors[s].append(np.full(5, np.nan))
        on = position_match(r.predictions, r.truth)
        for p, a in zip(r.predictions, on):
            followed[p.handedness]["none" if a is None else a] += 1
            if a is None:
                continue
            matched += 1
            correct += int(a == p.handedness)
            prev = last.get(p.handedness)
            if prev is not None and prev != a:
                swaps.append(r.index)
            last[p.handedness] = a
    per_hand = {s: summarize_errors(np.array(errors[s]).reshape(-1, 5)) for s in HANDS}
    return TwoHandSummary(
        bag=bag,
        split=split,
        mode=mode,
        frames=len(records),
        per_hand=per_hand,
        handedness_accuracy_pct=100.0 * correct / matched if matched else math.nan,
        matched_predictions=matched,
        swaps=len(swaps),
        swap_frames=tuple(swaps),
        followed=followed,
        mean_visible_fraction={s: _finite_mean(vis[s]) for s in HANDS},
        timing=summarize_timings([r.ms for r in records]),
        extra=dict(extra or {}),
    )


def one_hand_predictor(config: TrackerConfig | None = None) -> Predictor:
    """Today's one-hand core tracker as a :data:`Predictor`: one prediction, labelled with the
    configured handedness, on the frames it tracks."""
    from hand_sog_tracker.core.tracker import Tracker

    cfg = config or TrackerConfig()
    tracker = Tracker(cfg)
    side = "right" if cfg.right_hand else "left"

    def predict(depth_mm: NDArray, intrinsics: Intrinsics) -> list[HandPrediction]:
        res = tracker.process(depth_mm, intrinsics)
        if res.status is not TrackerStatus.TRACKING or res.fingertips_mm is None:
            return []
        return [HandPrediction(side, np.asarray(res.fingertips_mm, dtype=np.float64), float(res.confidence))]

    return predict


def multi_hand_predictor(
    config: TrackerConfig | None = None, max_hands: int = 2, handedness: str | None = None
) -> Predictor:
    """The core :class:`~hand_sog_tracker.core.hands.MultiHandTracker` as a :data:`Predictor`:
    one prediction per tracked hand, labelled with its track's handedness."""
    from hand_sog_tracker.core.hands import MultiHandTracker

    tracker = MultiHandTracker(config, max_hands=max_hands, handedness=handedness)

    def predict(depth_mm: NDArray, intrinsics: Intrinsics) -> list[HandPrediction]:
        out = tracker.process(depth_mm, intrinsics)
        return [
            HandPrediction(h.handedness, np.asarray(h.result.fingertips_mm, dtype=np.float64), h.result.confidence)
            for h in out.hands
            if h.result.fingertips_mm is not None
        ]

    return predict


def evaluate_two_hands_core(
    bag: str | Path,
    predictor: Predictor | None = None,
    config: TrackerConfig | None = None,
    max_frames: int | None = None,
    split: str = "-",
    topics: BagTopics = BagTopics(),
) -> TwoHandSummary:
    """Run ``predictor`` (default :func:`one_hand_predictor`) on every depth image of a two-hand bag
    and score it (:func:`score_two_hands`); ``ms`` is the predictor's wall time per frame.

    Raises
    ------
    BagError
        Unreadable bag, or no per-hand ground truth.
    """
    truth = read_hand_truth(bag)
    if not any(truth.values()):
        raise BagError(f"bag {bag}: no per-hand ground truth (/hand/ground_truth/<left|right>/fingertips)")
    predict = predictor if predictor is not None else one_hand_predictor(config)
    records: list[TwoHandRecord] = []
    with DepthBagReader(bag, topics, require_truth=False) as reader:
        for f in reader.frames():
            if max_frames is not None and len(records) >= max_frames:
                break
            gt: dict[str, HandTruthRecord | None] = {s: truth[s].get(f.stamp_ns) for s in HANDS}
            preds: tuple[HandPrediction, ...] = ()
            ms = math.nan
            if f.depth_mm is not None and f.intrinsics is not None:
                t0 = time.perf_counter()
                preds = tuple(predict(f.depth_mm, f.intrinsics))
                ms = (time.perf_counter() - t0) * 1e3
            records.append(
                TwoHandRecord(
                    index=f.index,
                    stamp_ns=f.stamp_ns,
                    truth={s: None if g is None else g.fingertips_mm for s, g in gt.items()},
                    visible_fraction={s: math.nan if g is None else g.visible_fraction for s, g in gt.items()},
                    predictions=preds,
                    ms=ms,
                )
            )
    if not records:
        raise BagError(f"bag {bag}: no depth image")
    side = None if config is None else ("right" if config.right_hand else "left")
    return score_two_hands(records, str(bag), split, "core", {"tracker_handedness": side} if side else None)


def evaluate_two_hands_node(
    bag: str | Path,
    domain_id: int,
    params: dict[str, Any] | None = None,
    max_frames: int | None = None,
    split: str = "-",
    rate: float = 1.0,
    connect_timeout_s: float = 30.0,
    warmup: bool = True,
) -> TwoHandSummary:
    """Today's node on a two-hand bag: replayed over loopback DDS (:func:`.node_eval.evaluate_through_node`,
    which reads the right hand's truth topic as its one-hand truth), its fingertips taken as one
    prediction labelled with its ``handedness`` parameter (confidence 1), scored per hand as
    :func:`score_two_hands`; ``ms`` is the node's end-to-end latency."""
    from hand_sog_tracker.tools.node_eval import evaluate_through_node

    truth = read_hand_truth(bag)
    side = str((params or {}).get("handedness", "right"))
    ev = evaluate_through_node(
        bag, BagTopics(truth=hand_topic("right")), domain_id=domain_id, rate=rate, max_frames=max_frames,
        connect_timeout_s=connect_timeout_s, warmup=warmup, params=params, split=split,
    )
    records = []
    per_hand = ev.extra.get("hand_outputs") or {}
    for r in ev.records:
        gt = {s: truth[s].get(r.stamp_ns) for s in HANDS}
        preds: tuple[HandPrediction, ...] = () if r.estimate_mm is None else (HandPrediction(side, r.estimate_mm, 1.0),)
        if per_hand:  # max_hands 2: the per-hand topics, each labelled with its side
            outs = {s: per_hand.get(s, {}).get(r.stamp_ns) for s in HANDS}
            preds = tuple(HandPrediction(s, o[1], 1.0) for s, o in outs.items() if o is not None and o[1] is not None)
            times = [o[0] for o in outs.values() if o is not None]
            r = dataclasses.replace(r, ms=max(times) if times else math.nan)
        records.append(
            TwoHandRecord(
                index=r.index, stamp_ns=r.stamp_ns,
                truth={s: None if g is None else g.fingertips_mm for s, g in gt.items()},
                visible_fraction={s: math.nan if g is None else g.visible_fraction for s, g in gt.items()},
                predictions=preds, ms=r.ms,
            )
        )
    extra = {"tracker_handedness": side, "frames_dropped": ev.extra.get("frames_dropped"), "fps": ev.extra.get("fps")}
    return score_two_hands(records, str(bag), split, "through_node", extra)


def _f(v: float, fmt: str = "5.1f") -> str:
    return "  -  " if not np.isfinite(v) else format(v, fmt)


def format_two_hand_table(summaries: Sequence[TwoHandSummary]) -> str:
    """One row per bag and hand: mean error, % frames < 20 mm, frames with an estimate, what the
    hand's label followed, visible fraction; then handedness accuracy and swaps per bag."""
    lines = [
        f"{'bag':<12} {'split':<5} {'hand':<5} {'mean mm':>7} {'<20mm %':>7} {'est/fr':>7} "
        f"{'on L/R/none':>12} {'visible':>7} {'hand. %':>7} {'swaps':>5} {'ms':>6}"
    ]
    for s in summaries:
        name = Path(s.bag).name
        for side in HANDS:
            e = s.per_hand[side]
            fol = s.followed[side]
            lines.append(
                f"{name:<12} {s.split:<5} {side:<5} {_f(e.mean_mm):>7} {_f(e.pct_below_mm['20']):>7} "
                f"{e.frames_with_estimate:>3}/{e.frames_scored:<3} "
                f"{fol['left']:>4}/{fol['right']}/{fol['none']:<3} {_f(s.mean_visible_fraction[side], '.2f'):>7} "
                f"{_f(s.handedness_accuracy_pct):>7} {s.swaps:>5} {_f(s.timing.median_ms):>6}"
            )
    return "\n".join(lines)


def summary_as_dict(s: TwoHandSummary, per_frame: bool = True) -> dict[str, Any]:
    """JSON-ready form (NaN as null; ``swap_frames`` only with ``per_frame``: not for test bags)."""
    out: dict[str, Any] = {
        "bag": s.bag, "split": s.split, "mode": s.mode, "frames": s.frames,
        "per_hand": {
            side: {"mean_mm": e.mean_mm, "per_finger_mm": e.per_finger_mm, "pct_below_mm": e.pct_below_mm,
                   "frames_scored": e.frames_scored, "frames_with_estimate": e.frames_with_estimate}
            for side, e in s.per_hand.items()
        },
        "handedness_accuracy_pct": s.handedness_accuracy_pct,
        "matched_predictions": s.matched_predictions,
        "swaps": s.swaps,
        "followed": s.followed,
        "mean_visible_fraction": s.mean_visible_fraction,
        "median_ms": s.timing.median_ms,
        **s.extra,
    }
    if per_frame:
        out["swap_frames"] = list(s.swap_frames)
    return json_clean(out)
