"""``benchmark``: the stage table and ``--compare`` against another source tree."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hand_sog_tracker.tools import benchmark

TREE = Path(benchmark.__file__).resolve().parents[2]


def test_stages_include_detector_quadtree_and_assignment() -> None:
    r = benchmark.run_benchmark("fingerwave", 4, 320, 240, 1)
    st = r["stages_ms"]
    assert r["frames_timed"] == 3
    for key in ("preprocess", "quadtree", "detector", "quadtree_only", "assignment",
                "model_update", "energy_gradient", "energy_gradient_tenth", "answer", "total"):
        assert np.isfinite(st[key]["median"]) and st[key]["median"] > 0, key
    # The parts timed alone are each below the frame's total; the answer is a part of it.
    assert st["detector"]["median"] < st["total"]["median"]
    assert st["quadtree_only"]["median"] < st["total"]["median"]
    assert st["answer"]["median"] <= st["total"]["median"] and st["answer"]["p95"] <= st["total"]["p95"]
    assert all(st[key]["median"] <= st[key]["p95"] <= st[key]["max"] for key in st if np.isfinite(st[key]["median"]))


def test_compare_runs_both_trees_and_prints_the_ratio(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    out = tmp_path / "cmp.json"
    code = benchmark.main(["--compare", str(TREE), "--rounds", "1", "--frames", "3",
                           "--resolution", "320x240", "--json", str(out)])
    assert code == 0
    text = capsys.readouterr().out
    assert "this/ref" in text and "total per frame" in text
    row = next(line for line in text.splitlines() if "total per frame" in line).split()
    this_ms, ref_ms, ratio = (float(x) for x in row[-3:])
    assert this_ms > 0 and ref_ms > 0 and ratio == pytest.approx(this_ms / ref_ms, abs=2e-3)
    assert out.exists()


def test_compare_rejects_a_directory_without_the_package(tmp_path: Path) -> None:
    with pytest.raises(SystemExit) as exc:
        benchmark.main(["--compare", str(tmp_path)])
    assert exc.value.code == 2


def test_set_times_the_tracker_with_other_parameters(capsys: pytest.CaptureFixture[str]) -> None:
    r = benchmark.run_benchmark("fingerwave", 3, 320, 240, 1, params={"iterations": 2})
    assert r["iterations"] == 2 and r["params"] == {"iterations": 2}
    assert benchmark.run_benchmark("fingerwave", 3, 320, 240, 1)["iterations"] != 2
    # Handedness (the benchmark renders a right hand), node-only and unknown names are refused.
    for bad in ("handedness=left", "debug_image=true", "no_such=1", "iterations=zero"):
        with pytest.raises(SystemExit) as exc:
            benchmark.main(["--set", bad, "--frames", "3"])
        assert exc.value.code == 2, bad
    assert "right hand" in capsys.readouterr().err


def test_compare_gives_the_settings_to_this_tree_only(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    calls: list[tuple[Path, list[str]]] = []

    def child(root: Path, args: list[str]) -> list[dict[str, object]]:
        calls.append((root, list(args)))
        return [{"resolution": "320x240", "stages_ms": {"total": {"median": 1.0}}}]

    monkeypatch.setattr(benchmark, "_run_child", child)
    ref = tmp_path / "ref"
    (ref / "hand_sog_tracker").mkdir(parents=True)
    (ref / "hand_sog_tracker" / "__init__.py").write_text("")
    code = benchmark.main(["--compare", str(ref), "--rounds", "2", "--frames", "3", "--set", "iterations=2"])
    assert code == 0
    this = [args for root, args in calls if root != ref.resolve()]
    other = [args for root, args in calls if root == ref.resolve()]
    assert len(this) == len(other) == 2
    assert all("--set=iterations=2" in args for args in this)
    assert not any(a.startswith("--set") for args in other for a in args)


def test_batch_rows_time_the_batched_objective_against_one_pose_calls(capsys: pytest.CaptureFixture[str]) -> None:
    from test_core_energy import data_near

    from hand_sog_tracker.core.hand_model import default_hand_model, rest_pose
    from hand_sog_tracker.core.objective import Objective
    from hand_sog_tracker.core.types import TrackerConfig

    model = default_hand_model()
    pose = rest_pose((0.0, 60.0, 400.0))
    obj = Objective(model, data_near(model, pose, np.random.default_rng(0)), TrackerConfig())
    stage: dict[str, list[float]] = {}
    benchmark._time_batches(obj, pose, stage)
    for B in benchmark.BATCH_SIZES:
        for key in (f"energy_batch_{B}", f"energy_singles_{B}"):
            assert len(stage[key]) == benchmark.BATCH_ROUNDS and min(stage[key]) > 0, key
            assert key in benchmark.STAGE_LABELS
    r = {"motion": "m", "resolution": "r", "frames_timed": 0, "frames_tracking": 0, "iterations": 0,
         "stages_ms": {k: benchmark._stats(v) for k, v in stage.items()}, "fps": 0.0, "peak_rss_mb": 0.0,
         "rss_growth_mb": 0.0}
    benchmark._print_table(r)
    rows = [line.split() for line in capsys.readouterr().out.splitlines() if line.split()[:1] == ["32"]]
    per_call, per_pose, singles, ratio = (float(x) for x in rows[-1][1:])
    assert per_pose == pytest.approx(per_call / 32, abs=2e-3) and ratio == pytest.approx(per_call / singles, abs=0.01)


def test_two_hand_scene_renders_both_hands_and_needs_its_renderer() -> None:
    from hand_sog_tracker.synth.sequence import default_intrinsics

    depth = benchmark._frames("apart", 2, default_intrinsics(160, 120), "twohands", 0)
    assert len(depth) == 2
    cols = np.nonzero((depth[0] > 0).any(axis=0))[0]
    assert cols.size and np.diff(cols).max() > 10  # two blobs with a gap between them
    with pytest.raises(SystemExit):
        benchmark.main(["--scene", "clap"])
