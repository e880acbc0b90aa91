"""render_sets: the README's sets of random mesh renders, drawn per seed and tracked."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hand_sog_tracker.errors import InputError
from hand_sog_tracker.tools.render_sets import (
    NO_HAND_MM,
    SET_MOTIONS,
    compare,
    main,
    render_spec,
    settings,
    track_render,
)


def test_a_seed_draws_one_render_and_the_options_change_only_their_part() -> None:
    spec = render_spec(3001)
    assert spec == render_spec(3001)  # (deterministic)
    assert spec.motion == SET_MOTIONS[3001 % 10] == "fingercount"
    assert spec.right and spec.sensor == "clean" and spec.wall_mm is None
    assert 0.86 <= spec.shape.length <= 1.14 and spec.shape.fingers == (1.0,) * 5
    assert all(abs(a) <= 25.0 for a in spec.wrist_deg)
    assert sorted({render_spec(s).motion for s in range(10)}) == sorted(set(SET_MOTIONS))
    odd = render_spec(3001, finger_spread=0.08, wall_mm=50.0)
    assert odd.wall_mm == 450.0  # (behind the motions' start depth of the wrist, 400 mm)
    assert odd.shape.fingers != (1.0,) * 5 and all(0.92 <= f <= 1.08 for f in odd.shape.fingers)
    # Everything else as drawn without them.
    assert (odd.motion, odd.right, odd.sensor, odd.wrist_deg) == (spec.motion, spec.right, spec.sensor, spec.wrist_deg)
    assert odd.shape.as_tuple() == spec.shape.as_tuple()
    for bad in ({"finger_spread": 0.5}, {"finger_spread": -0.1}, {"wall_mm": 0.0}, {"wall_mm": float("nan")}):
        with pytest.raises(InputError):
            render_spec(3001, **bad)


def test_a_render_is_tracked_and_scored_per_frame() -> None:
    result = track_render(render_spec(3000), frames=4)  # (an open hand spreading its fingers)
    assert len(result["errors_mm"]) == 4 and result["fits"] == []  # (no fit before 15 frames)
    assert max(result["errors_mm"]) < 15.0
    assert result["mean_mm"] == pytest.approx(np.mean(result["errors_mm"]))


def test_tracker_parameters_are_set_by_the_nodes_names() -> None:
    assert settings(["iterations=2", "w_sal=0"]) == {"iterations": 2, "w_sal": 0.0}
    spec = render_spec(3000)
    plain = track_render(spec, frames=3)
    assert track_render(spec, frames=3, params={})["errors_mm"] == plain["errors_mm"]
    fewer = track_render(spec, frames=3, params=settings(["iterations=1"]))
    assert fewer["errors_mm"][1:] != plain["errors_mm"][1:]  # (the tracked frames' fits differ)
    for bad, message in (("handedness=left", "each render draws"), ("debug_image=true", "the node's only"),
                         ("iterations=0", "outside"), ("w_nope=1", "unknown")):
        with pytest.raises(InputError, match=message):
            settings([bad])


def test_compare_counts_renders_that_moved_and_bad_frames() -> None:
    old = {"1": {"motion": "pinch", "mean_mm": 5.0, "errors_mm": [5.0, 5.0]},
           "2": {"motion": "rotate", "mean_mm": 30.0, "errors_mm": [10.0, 50.0]}}
    new = {"1": {"motion": "pinch", "mean_mm": 6.0, "errors_mm": [6.0, 6.0]},
           "2": {"motion": "rotate", "mean_mm": 10.0, "errors_mm": [10.0, 10.0]},
           "3": {"motion": "abdadd", "mean_mm": NO_HAND_MM, "errors_mm": [NO_HAND_MM]}}
    text = compare(old, new)
    assert text.startswith("2 renders: 17.500 -> 8.000 mm; better by > 0.3 mm: 1, worse: 1; frames over 20 mm: 1 -> 0")
    assert "2 rotate      30.00 -> 10.00 mm" in text
    assert compare({}, new) == "no common seeds to compare"


def test_the_command_writes_its_records_and_compares(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "set.json"
    assert main(["3000,3002", "--frames", "2", "--json", str(out), "--quiet"]) == 0
    written = json.loads(out.read_text())
    assert written["options"]["frames"] == 2 and sorted(written["renders"]) == ["3000", "3002"]
    assert written["renders"]["3002"]["motion"] == "fingerwave"
    text = capsys.readouterr().out
    assert "abdadd" in text and "fingerwave" in text and "all                2" in text
    assert main(["3000", "--frames", "2", "--compare", str(out), "--quiet", "--jobs", "2"]) == 0
    moved = capsys.readouterr().out.splitlines()[-1]
    first = written["renders"]["3000"]["mean_mm"]
    assert moved == (
        f"1 renders: {first:.3f} -> {first:.3f} mm; better by > 0.3 mm: 0, worse: 0; frames over 20 mm: 0 -> 0"
    )
    assert main(["3005-3001"]) == 2 and "empty range" in capsys.readouterr().err
    assert main(["3000", "--frames", "0"]) == 2
    assert main(["3000", "--set", "handedness=left"]) == 2 and "each render draws" in capsys.readouterr().err
    other = tmp_path / "other.json"
    other.write_text('{"3000": {"mean_mm": 5.0}}')  # (not a --json file)
    assert main(["3000", "--compare", str(other)]) == 2 and "not a render_sets --json file" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # (argparse: exit status 2 and the message)
        main(["3000", "--resolution", "640"])
    assert "expected WIDTHxHEIGHT" in capsys.readouterr().err
