"""The calibration benchmark (tools/calibration_benchmark.py): one capsule hand end to end, the
mesh truth mapping, the summary row and the command line."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import pytest

from hand_sog_tracker.tools.calibration_benchmark import (
    FACTOR_RANGE,
    MESH_AT_ONE,
    HandResult,
    RendererSummary,
    draw_factors,
    format_hand,
    format_notes,
    format_summary,
    main,
    mesh_length_ratio,
    run_calibration_benchmark,
    summarise,
    true_factors,
)


def test_one_capsule_hand_is_fitted_accepted_and_tracked() -> None:
    """Dev hand 2002 (1.12 x 1.14 x 1.05, far from the default model): the capsule renderer
    draws the model itself, so the fit must come back accepted and within 3% of the drawn
    factors, and the fitted model must track the hand better than the default one."""
    out = run_calibration_benchmark(["capsule"], "dev", hands=1, first_seed=2002)
    assert out["seeds"] == [2002] and len(out["hands"]) == 1
    hand = out["hands"][0]
    print(format_hand(HandResult(**{k: v for k, v in hand.items() if k != "within_5pct"})))
    lo, hi = FACTOR_RANGE
    assert all(lo <= v <= hi for v in hand["drawn"]) and tuple(hand["truth"]) == tuple(hand["drawn"])
    assert hand["accepted"] and hand["reason"] == "" and hand["within_5pct"]
    assert (hand["fit_frames"], hand["holdout_frames"], hand["tracked_frames"]) == (3, 4, 15)
    fitted = hand["fitted"]
    assert fitted[2] == fitted[3]  # palm depth follows the measured finger thickness
    for f, t, e in zip((fitted[0], fitted[1], fitted[3]), hand["truth"], hand["errors"]):
        assert f == pytest.approx(t, rel=0.03) and e == pytest.approx(f / t - 1.0)
    assert hand["guard_gain"] >= 0.003 and 0.0 < hand["fit_cpu_s"] < 30.0
    assert 0.5 < hand["tip_calibrated_mm"] < hand["tip_default_mm"] < 10.0
    assert hand["tip_fitted_mm"] == hand["tip_calibrated_mm"] and 0.5 < hand["tip_truth_mm"] < 10.0
    row = out["summary"]["capsule"]
    assert row["accepted"] == row["within_5pct"] == row["hands"] == 1 and row["worse"] == 0
    assert row["gain_accepted_mm"] == pytest.approx(hand["tip_default_mm"] - hand["tip_calibrated_mm"])
    line = format_summary(RendererSummary(**row))
    assert line.startswith("| capsule | 1 of 1 | <= ") and "| 1 of 1 |" in line and "| 0 |" in line


def test_truth_and_drawing() -> None:
    assert draw_factors(9000) == draw_factors(9000) != draw_factors(9001)
    assert true_factors("capsule", (0.9, 1.1, 1.0)) == (0.9, 1.1, 1.0)
    assert true_factors("mesh", (1.0, 1.0, 1.0)) == pytest.approx(MESH_AT_ONE)
    # The mesh's length factor scales the fingers only: the hand grows less than the factor.
    assert 1.0 < mesh_length_ratio(1.1) < 1.1 and 0.9 < mesh_length_ratio(0.9) < 1.0
    assert true_factors("mesh", (1.0, 1.1, 0.9))[1:] == pytest.approx((MESH_AT_ONE[1] * 1.1, MESH_AT_ONE[2] * 0.9))
    with pytest.raises(ValueError, match="renderer"):
        true_factors("clay", (1.0, 1.0, 1.0))


def _result(seed: int, accepted: bool, errors: tuple[float, float, float] | None, tips: tuple[float, float],
            cpu: float) -> HandResult:
    return HandResult("mesh", seed, (1.0, 1.0, 1.0), (1.0, 1.0, 1.0), None if errors is None else (1.0,) * 4,
                      accepted, "" if accepted else "refused", errors, 3, 4, 15, 0.01, 0.0, cpu, *tips)


def test_summary_counts_only_accepted_fits() -> None:
    rows = [
        _result(1, True, (0.01, -0.054, 0.02), (5.0, 4.0), 0.3),  # width 5.4% off, tracks better
        _result(2, True, (-0.02, 0.01, 0.0), (4.0, 4.25), 0.4),  # tracks 0.25 mm worse
        replace(_result(3, False, (0.30, 0.30, 0.30), (6.0, 6.0), 0.2), tip_fitted_mm=5.5, tip_truth_mm=6.5),
        _result(4, False, None, (7.0, 7.0), 0.1),  # failed before a shape
    ]  # the third was refused (its errors do not count; its shape would have tracked 0.5 mm better)
    s = summarise(rows)
    assert (s.hands, s.accepted, s.within_5pct, s.worse) == (4, 2, 1, 1)
    assert s.max_error == pytest.approx((0.02, 0.054, 0.02))
    assert s.tip_default_mm == pytest.approx(5.5) and s.tip_calibrated_mm == pytest.approx(5.3125)
    assert s.gain_accepted_mm == pytest.approx(0.375) and s.worse_range_mm == pytest.approx((0.25, 0.25))
    assert s.fit_cpu_s == (0.1, 0.4)
    none = summarise([rows[3]])
    assert none.accepted == 0 and math.isnan(none.max_error[0]) and math.isnan(none.gain_accepted_mm)
    assert "by 0.25-0.25 mm" in format_summary(s) and "<= 2.0%, 5.4%, 2.0%" in format_summary(s)
    assert s.truth_worse == 1 and s.truth_worse_range_mm == (0.5, 0.5) and s.refused_change_mm == (-0.5,)
    assert "1 of 4 (by 0.50-0.50 mm)" in format_notes(s) and "-0.50" in format_notes(s)


def test_command_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["--help"])
    assert info.value.code == 0 and "--renderer" in capsys.readouterr().out
    out = tmp_path / "calib.json"
    assert main(["--renderer", "capsule", "--split", "dev", "--hands", "1", "--no-track", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "capsule seed 2000:" in text and "| capsule | " in text
    data = json.loads(out.read_text())
    assert data["split"] == "dev" and data["seeds"] == [2000] and set(data["summary"]) == {"capsule"}
    assert math.isnan(data["hands"][0]["tip_default_mm"])  # --no-track


def test_the_bag_check_fits_guards_and_reports_without_a_node(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """``calibration_benchmark --bag``: on the bundled capsule bag (the default model's own hand)
    the fit runs, the guard answers and the rest of the bag is tracked with both models."""
    bag = Path(__file__).resolve().parents[1] / "bags" / "abdadd"
    out = tmp_path / "check.json"
    assert main(["--bag", str(bag), "--json", str(out)]) == 0
    line = capsys.readouterr().out
    check = json.loads(out.read_text())[0]
    print(line)
    assert check["verdict"] in ("accepted", "already fits", "refused") and check["shape"] is not None
    assert "held-out score" in check["message"] and check["verdict"] in line
    assert 0.5 < check["tip_default_mm"] < 10.0 and 0.5 < check["tip_fitted_mm"] < 10.0
    assert check["stamp_ns"] > 0 and check["fit_s"] > 0.0

