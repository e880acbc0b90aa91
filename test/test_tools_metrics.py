"""Fingertip error metrics (hand_sog_tracker.tools.metrics) on hand-made errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hand_sog_tracker.errors import InputError
from hand_sog_tracker.tools.metrics import (
    FINGERS,
    THRESHOLDS_MM,
    fingertip_errors_mm,
    pct_frames_below,
    summarize_errors,
    summarize_timings,
)


def test_fingertip_errors_are_euclidean_per_finger() -> None:
    rng = np.random.default_rng(1)
    truth = rng.uniform(-80.0, 80.0, (5, 3)) + [0.0, 0.0, 400.0]
    offsets = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 12.0], [5.0, 0.0, 12.0], [0.0, 0.0, 0.0], [8.0, 15.0, 0.0]])
    err = fingertip_errors_mm(truth + offsets, truth)
    np.testing.assert_allclose(err, [5.0, 12.0, 13.0, 0.0, 17.0], atol=1e-9)
    # batched (N, 5, 3)
    batch = fingertip_errors_mm(np.stack([truth + offsets, truth]), np.stack([truth, truth]))
    assert batch.shape == (2, 5)
    np.testing.assert_allclose(batch[1], 0.0)


def test_fingertip_errors_reject_bad_shapes() -> None:
    with pytest.raises(InputError, match=r"\(\.\.\., 5, 3\)"):
        fingertip_errors_mm(np.zeros((4, 3)), np.zeros((4, 3)))
    with pytest.raises(InputError):
        fingertip_errors_mm(np.zeros((5, 3)), np.zeros((2, 5, 3)))


def test_summary_exact_values_with_a_failed_frame() -> None:
    rng = np.random.default_rng(2)
    errors = np.array(
        [
            [10.0, 10.0, 10.0, 10.0, 10.0],  # frame mean 10
            [14.0, 16.0, 18.0, 20.0, 22.0],  # frame mean 18
            [30.0, 20.0, 25.0, 25.0, 25.0],  # frame mean 25 (exactly: not below 25)
            [np.nan] * 5,  # tracker gave nothing: failure
        ]
    )
    # row order must not matter
    s = summarize_errors(errors[rng.permutation(4)])
    assert s.frames_scored == 4
    assert s.frames_with_estimate == 3
    assert s.mean_mm == pytest.approx((50.0 + 90.0 + 125.0) / 15.0)
    assert s.per_finger_mm == pytest.approx(
        {"thumb": 54.0 / 3, "index": 46.0 / 3, "middle": 53.0 / 3, "ring": 55.0 / 3, "little": 57.0 / 3}
    )
    assert list(s.per_finger_mm) == list(FINGERS)
    # below 15: {10} -> 1/4; below 20: {10, 18} -> 2/4; below 25: 2/4 (25 is not < 25); below 30: 3/4
    assert s.pct_below_mm == pytest.approx({"15": 25.0, "20": 50.0, "25": 50.0, "30": 75.0})
    assert tuple(int(k) for k in s.pct_below_mm) == THRESHOLDS_MM


def test_summary_without_estimates_and_without_frames() -> None:
    s = summarize_errors(np.full((3, 5), np.nan))
    assert s.frames_scored == 3 and s.frames_with_estimate == 0
    assert math.isnan(s.mean_mm) and all(math.isnan(v) for v in s.per_finger_mm.values())
    assert s.pct_below_mm == {"15": 0.0, "20": 0.0, "25": 0.0, "30": 0.0}
    empty = summarize_errors(np.zeros((0, 5)))
    assert empty.frames_scored == 0
    assert all(math.isnan(v) for v in empty.pct_below_mm.values())


def test_summary_rejects_malformed_errors() -> None:
    with pytest.raises(InputError, match=r"\(N, 5\)"):
        summarize_errors(np.zeros((3, 4)))
    with pytest.raises(InputError, match="all NaN or all finite"):
        summarize_errors(np.array([[1.0, np.nan, 1.0, 1.0, 1.0]]))
    with pytest.raises(InputError, match="non-negative"):
        summarize_errors(np.array([[1.0, -1.0, 1.0, 1.0, 1.0]]))


def test_pct_curve_is_monotone_and_counts_failures() -> None:
    rng = np.random.default_rng(3)
    err = rng.uniform(0.0, 60.0, 200)
    err[:20] = np.nan
    grid = np.linspace(0.0, 100.0, 51)
    pct = pct_frames_below(err, grid)
    assert np.all(np.diff(pct) >= 0.0)
    assert pct[0] == 0.0
    assert pct[-1] == pytest.approx(90.0)  # the 20 failures never count as below


def test_timing_summary_matches_numpy() -> None:
    rng = np.random.default_rng(4)
    ms = rng.gamma(4.0, 5.0, 101)
    t = summarize_timings(np.append(ms, np.nan))
    assert t.count == 101
    assert t.median_ms == pytest.approx(float(np.median(ms)))
    assert t.p95_ms == pytest.approx(float(np.percentile(ms, 95)))
    assert t.mean_ms == pytest.approx(float(ms.mean()))
    empty = summarize_timings([])
    assert empty.count == 0 and math.isnan(empty.median_ms)
