"""The detector's precision/recall tool."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hand_sog_tracker.tools.detector_eval import main, match_counts
from hand_sog_tracker.tools.make_sample_bags import write_sample_bag


def test_match_counts_is_one_to_one_and_respects_the_distance() -> None:
    truth = np.array([[0.0, 0, 0], [30, 0, 0], [60, 0, 0]])
    found = np.array([[1.0, 0, 0], [2.0, 0, 0], [45.0, 0, 0], [200.0, 0, 0]])
    # Two detections near tip 0 count once; 45 mm is 15 from tips 1 and 2: not under 15.
    assert match_counts(truth, found, 15.0) == 1
    assert match_counts(truth, found, 16.0) == 2
    assert match_counts(truth, np.zeros((0, 3)), 15.0) == 0


def test_cli_reports_precision_and_recall(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = write_sample_bag(tmp_path / "abdadd", "abdadd", 4).path
    assert main([str(bag)]) == 0
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if line.startswith("abdadd"))
    precision, recall = (float(v.rstrip("%")) for v in row.split()[2:4])
    # An open hand: most fingertips found, few false detections.
    assert precision >= 80.0 and recall >= 80.0, row
    assert main([str(tmp_path / "missing")]) == 2
