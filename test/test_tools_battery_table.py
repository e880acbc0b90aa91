"""The battery's table from its records (``hand_sog_tracker.tools.battery_table``)."""

from __future__ import annotations

import json
from pathlib import Path

from hand_sog_tracker.tools import battery_table


def _row(size: str, kind: str, problems: list[str], worst_ms: float, xfail: bool = False) -> dict:
    return dict(size=size, kind=kind, group="values", expected="track", observed="processed, tracked 3 mm",
                reason="", problems=problems, worst_ms=worst_ms, worst_cpu_ms=worst_ms / 2, recover_ms=50.0,
                recover_cpu_ms=25.0, rss_mb=150.0, recovered_mm=3.0, xfail=xfail)


def test_both_sizes_side_by_side_with_totals(tmp_path: Path, capsys) -> None:
    small, large = tmp_path / "b320.jsonl", tmp_path / "b640.jsonl"
    small.write_text("\n".join(json.dumps(r) for r in [
        _row("320x240", "a", [], 30.0), _row("320x240", "b", ["nothing tracked"], 90.0),
        dict(summary="320x240", steady_ms=20.0, steady_rss=130.0, peak_rss=160.0, after_rss=134.0),
    ]) + "\n")
    large.write_text(json.dumps(_row("640x480", "a", [], 120.0)) + "\n" + json.dumps(
        _row("640x480", "b", ["2 poses published for it"], 80.0, xfail=True)) + "\n")
    battery_table.main([str(small), str(large), "--json", str(tmp_path / "t.json")])
    out = capsys.readouterr().out
    seen = "processed, tracked 3 mm"
    row = f"| values | a | track | {seen} | ok | 30 (15) | 150 | {seen} | ok | 120 (60) |"
    assert row in out
    assert "**nothing tracked**" in out and "xfail: 2 poses published for it" in out
    assert "- 320x240: 1 of 2 kinds as expected, **failed: b**; worst frame 90 ms (b)" in out
    assert "after the battery +4 MB" in out
    totals = json.loads((tmp_path / "t.json").read_text())["totals"]
    assert totals["640x480"]["as_expected"] == 1 and totals["640x480"]["xfailed"] == ["b"]
    assert totals["640x480"]["worst_frame_ms"] == 120.0
