"""The automatic calibration's frame history and schedule (core/autocalibration.py)."""

from __future__ import annotations

import numpy as np

from hand_sog_tracker.core.articulations import FINGER_CURLED
from hand_sog_tracker.core.autocalibration import (
    AUTO_APPLY_S,
    AUTO_ATTEMPTS,
    AUTO_MIN_FIT_FRAMES,
    AUTO_MIN_FRAMES,
    AUTO_MIN_LENGTH,
    HISTORY_FRAMES,
    AutoCalibration,
    FrameHistory,
    choose_fit_frames,
    usable_automatically,
)
from hand_sog_tracker.core.hand_model import HandShape, chain_slice, rest_pose
from hand_sog_tracker.core.types import Intrinsics

INTR = Intrinsics(287.0, 287.0, 160.0, 120.0, 320, 240)
PERIOD_NS = 33_333_333  # 30 Hz
DEPTH = np.zeros((240, 320), np.float32)


def _open(k: int) -> np.ndarray:
    th = rest_pose((0.0, 20.0, 430.0))
    th[0] += k  # every frame a little different
    return th


def _fist(k: int) -> np.ndarray:
    th = _open(k)
    for c in range(1, 5):
        th[chain_slice(c)] = FINGER_CURLED
    return th


def test_history_keeps_one_frame_per_spacing_and_the_newest_ones() -> None:
    h = FrameHistory(size=4, spacing_s=0.05)
    kept = [h.remember(DEPTH, INTR, _open(k), k * PERIOD_NS) for k in range(12)]
    assert kept == [True, False] * 6  # 33 ms apart: every other frame
    assert len(h) == 4 and [f.stamp_ns for f in h.frames()] == [k * PERIOD_NS for k in (4, 6, 8, 10)]
    assert h.remember(DEPTH, INTR, None, 0)  # a stamp going back is kept (a new recording)
    h.clear()
    assert len(h) == 0


def test_fit_frames_come_from_the_newest_camera_open_hands_to_fit_others_to_check() -> None:
    other = Intrinsics(500.0, 500.0, 320.0, 240.0, 640, 480)
    h = FrameHistory()
    for k in range(5):
        h.remember(DEPTH, other, _open(k), k * PERIOD_NS)
    for k in range(5, 15):
        h.remember(DEPTH, INTR, _open(k) if k % 2 else _fist(k), k * PERIOD_NS)
    chosen = choose_fit_frames(h.frames(), n_fit=3, n_holdout=4)
    assert chosen is not None and chosen.usable and chosen.intrinsics == INTR and chosen.tracked == 10
    assert len(chosen.fit) == 3 and len(chosen.holdout) == 4
    assert all(f.intrinsics == INTR and f.stamp_ns // PERIOD_NS % 2 for f in chosen.fit)  # open hands
    assert not {id(f) for f in chosen.fit} & {id(f) for f in chosen.holdout}
    args, kwargs = chosen.calibrate_args(config="cfg", model="model")  # type: ignore[arg-type]
    assert args[1:] == (INTR, "cfg", "model") and len(kwargs["holdout_poses"]) == 4
    assert "margin" not in kwargs and "frame_drop" not in kwargs  # ~/calibrate: the guard's defaults
    _, auto = chosen.calibrate_args(config="cfg", model="model", automatic=True)  # type: ignore[arg-type]
    assert auto.keys() == kwargs.keys()  # the automatic fit: the same guard


def test_schedule_waits_for_a_full_history_retries_after_a_refusal_and_stops_after_success() -> None:
    h = FrameHistory()
    auto = AutoCalibration(retry_s=1.0)
    assert AUTO_MIN_FRAMES == HISTORY_FRAMES
    stamp = 0
    due = None
    for k in range(HISTORY_FRAMES):
        stamp = k * PERIOD_NS
        h.remember(DEPTH, INTR, _open(k) if k else None, stamp)  # the first frame not tracked
        due = auto.due(h, stamp)
        assert due is None  # fewer tracked frames than AUTO_MIN_FRAMES
    stamp += PERIOD_NS
    h.remember(DEPTH, INTR, _open(99), stamp)
    due = auto.due(h, stamp)
    assert due is not None and due.usable
    auto.started(stamp)
    assert auto.due(h, stamp + PERIOD_NS) is None  # one fit at a time
    auto.finished(False)
    assert auto.due(h, stamp + 10 * PERIOD_NS) is None  # refused: the next try waits retry_s
    assert auto.due(h, stamp + 31 * PERIOD_NS) is not None
    for _ in range(AUTO_ATTEMPTS - 1):
        auto.started(stamp)
        auto.finished(False)
        stamp += 2 * 10**9
    assert auto.attempts == AUTO_ATTEMPTS and auto.due(h, stamp) is None  # attempts used up
    ok = AutoCalibration()
    assert ok.due(h, stamp) is not None
    ok.started(stamp)
    ok.finished(True)
    assert ok.due(h, stamp + 10**10) is None  # done for good
    fists = FrameHistory()
    for k in range(HISTORY_FRAMES + 2):
        fists.remember(DEPTH, INTR, _fist(k), k * PERIOD_NS)
    assert AutoCalibration().due(fists, 20 * PERIOD_NS) is None  # no open hand to fit on
    one_open = FrameHistory()
    for k in range(HISTORY_FRAMES + 2):
        one_open.remember(DEPTH, INTR, _open(k) if k == 5 else _fist(k), k * PERIOD_NS)
    assert choose_fit_frames(one_open.frames()).usable  # (~/calibrate would fit on it)
    assert AUTO_MIN_FIT_FRAMES == 2 and AutoCalibration().due(one_open, 20 * PERIOD_NS) is None
    assert AutoCalibration(enabled=False).due(h, stamp) is None


def test_an_automatic_fit_that_shrinks_the_hand_too_much_is_not_used() -> None:
    assert usable_automatically(HandShape(length=1.1, width=1.1))
    assert usable_automatically(HandShape(length=AUTO_MIN_LENGTH, width=0.9))
    assert not usable_automatically(HandShape(length=AUTO_MIN_LENGTH - 0.01, width=1.2))


def test_an_automatic_fit_at_an_end_of_its_search_range_is_not_used() -> None:
    """The best fit lay beyond the search range: its frames did not hold the hand's size (a
    mesh render 50 mm in front of a wall: length 1.25 and width 0.8 for a hand of 0.99 x 1.06)."""
    from hand_sog_tracker.core.calibration import SEARCH_RANGE

    lo, hi = SEARCH_RANGE
    assert not usable_automatically(HandShape(length=hi, width=lo))
    assert not usable_automatically(HandShape(length=hi, width=1.0))
    assert not usable_automatically(HandShape(length=1.0, width=lo))
    assert not usable_automatically(HandShape(length=1.0, width=hi))
    assert usable_automatically(HandShape(length=hi - 0.01, width=lo + 0.01))
    # The node logs why a fit is not used.
    from hand_sog_tracker.core.autocalibration import why_not_used

    assert "search range" in (why_not_used(HandShape(length=hi, width=lo)) or "")
    assert "smaller than length" in (why_not_used(HandShape(length=AUTO_MIN_LENGTH - 0.01)) or "")
    assert why_not_used(HandShape(length=1.1, width=1.1)) is None


def test_an_accepted_fit_is_handed_out_by_image_stamps() -> None:
    """The model switch goes by the frames' stamps: the same frame on every run of a bag,
    whenever the fit (in another process) happens to end before it."""
    auto = AutoCalibration(apply_s=AUTO_APPLY_S)
    start = 5 * 10**9
    apply_ns = int(AUTO_APPLY_S * 1e9)
    assert not auto.overdue(start)  # no fit running
    auto.started(start)
    assert not auto.overdue(start + apply_ns - 1)  # running, its frame not due yet
    assert auto.overdue(start + apply_ns)  # due and still running: the node waits for it
    assert auto.take(start + apply_ns) is None  # nothing finished yet
    auto.finished(True, "fitted model")
    assert not auto.overdue(start + apply_ns)  # ended: nothing to wait for
    assert auto.take(start + apply_ns - 1) is None
    assert auto.take(start + apply_ns) == "fitted model"
    assert auto.started_ns == start and auto.taken_ns == start + apply_ns
    assert auto.take(start + 2 * apply_ns) is None  # once
    late = AutoCalibration(apply_s=AUTO_APPLY_S)
    late.started(start)
    late.finished(True, "late model")  # ended after its frame was due: the next frame takes it
    assert late.take(start + 3 * apply_ns) == "late model"
    refused = AutoCalibration()
    refused.started(start)
    refused.finished(False)
    assert refused.take(start + 10 * apply_ns) is None
