"""evaluate_bag on several bags: discovery, Table-1 rows and totals, split protocol, overlays, plot extra."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from hand_sog_tracker.core import tracker as core_tracker
from hand_sog_tracker.core.types import Intrinsics, TrackerConfig, TrackerStatus, TrackResult
from hand_sog_tracker.errors import BagError
from hand_sog_tracker.tools.bagio import DepthSample, write_depth_bag
from hand_sog_tracker.tools.bagset import SIDECAR, discover_bags
from hand_sog_tracker.tools.evaluate_bag import main
from hand_sog_tracker.tools.evaluation import evaluate_core
from hand_sog_tracker.tools.records import pool
from hand_sog_tracker.tools.report import format_table1, totals

T0 = 1_700_000_000_000_000_000
DT = 33_333_333
INTR = Intrinsics(fx=90.0, fy=90.0, cx=39.5, cy=29.5, width=80, height=60)
TIPS = np.array(
    [[-20.0, 0.0, 400.0], [-10.0, -30.0, 400.0], [0.0, -35.0, 400.0], [10.0, -30.0, 400.0], [20.0, -20.0, 400.0]]
)


class FakeTracker:
    """Reports TIPS; frames whose depth is all 111 mm are NO_HAND.  Records its config."""

    configs: list[TrackerConfig] = []

    def __init__(self, config: TrackerConfig | None = None) -> None:
        self.config = config or TrackerConfig()
        FakeTracker.configs.append(self.config)

    def process(self, depth_mm: np.ndarray, intrinsics: Intrinsics) -> TrackResult:
        if np.all(depth_mm == 111.0):
            return TrackResult(TrackerStatus.NO_HAND, None, None, None, 0.0, 0.0, 0)
        return TrackResult(TrackerStatus.TRACKING, None, TIPS.copy(), None, 1.0, 1.0, 10)


@pytest.fixture
def fake_tracker(monkeypatch: pytest.MonkeyPatch) -> type[FakeTracker]:
    FakeTracker.configs = []
    monkeypatch.setattr(core_tracker, "Tracker", FakeTracker)
    return FakeTracker


def _bag(path: Path, errors: list[float | None], split: str | None = None, **sidecar: object) -> Path:
    """One frame per entry: error (mm) of every fingertip; None = the tracker finds no hand."""
    rng = np.random.default_rng(len(errors))
    samples = []
    for i, e in enumerate(errors):
        d = rng.normal(size=(5, 3))
        truth = TIPS + (e or 5.0) * d / np.linalg.norm(d, axis=1, keepdims=True)
        depth = np.full((60, 80), 111.0) if e is None else rng.uniform(300.0, 900.0, (60, 80))
        samples.append(DepthSample(T0 + i * DT, depth, INTR, truth))
    write_depth_bag(path, samples)
    if split is not None or sidecar:
        (path / SIDECAR).write_text(json.dumps({"split": split, "renderer": "capsule", **sidecar}))
    return path


def test_discover_bags_single_folders_and_sidecars(tmp_path: Path) -> None:
    root = tmp_path / "set"
    _bag(root / "b_two", [5.0], split="test", handedness="left")
    _bag(root / "a_one", [5.0], split="dev")
    (root / "not_a_bag").mkdir()
    (root / "notes.txt").write_text("x")
    entries = discover_bags([root])
    assert [e.name for e in entries] == ["a_one", "b_two"]  # sorted, non-bags skipped
    assert [e.split for e in entries] == ["dev", "test"]
    assert entries[1].is_test and entries[1].handedness == "left" and entries[0].handedness is None
    # a bag itself, one of its storage files, duplicates dropped, no sidecar -> split "-"
    _bag(tmp_path / "plain", [5.0])
    mcap = next((tmp_path / "plain").glob("*.mcap"))
    entries = discover_bags([tmp_path / "plain", mcap, root / "a_one", root])
    assert [e.name for e in entries] == ["plain", "a_one", "b_two"]
    assert entries[0].split == "-"
    with pytest.raises(BagError, match="bag not found"):
        discover_bags([tmp_path / "missing"])
    with pytest.raises(BagError, match="neither a bag .* nor a folder of bags"):
        discover_bags([root / "not_a_bag"])
    (root / "a_one" / SIDECAR).write_text("{not json")
    with pytest.raises(BagError, match="sample sidecar"):
        discover_bags([root / "a_one"])


def test_totals_are_frame_weighted(tmp_path: Path, fake_tracker: type[FakeTracker]) -> None:
    a = evaluate_core(_bag(tmp_path / "a", [10.0, 20.0]), split="dev", progress=False)
    b = evaluate_core(_bag(tmp_path / "b", [16.0, 16.0, 28.0, None]), split="dev", progress=False)
    c = evaluate_core(_bag(tmp_path / "c", [40.0]), split="test", progress=False)
    assert a.errors.mean_mm == pytest.approx(15.0) and b.errors.mean_mm == pytest.approx(20.0)
    dev = pool([a, b], "total dev")
    assert dev.frames == 6 and dev.errors.frames_scored == 6 and dev.errors.frames_with_estimate == 5
    # frame-weighted: (10 + 20 + 16 + 16 + 28) / 5 = 18, not the mean of the bag means (17.5)
    assert dev.errors.mean_mm == pytest.approx(18.0)
    assert dev.errors.pct_below_mm == pytest.approx({"15": 100 / 6, "20": 300 / 6, "25": 400 / 6, "30": 500 / 6})
    assert dev.timing.count == 6  # every processed frame is timed, NO_HAND ones too
    assert [p.label for p in totals([c, a, b])] == ["total dev", "total test", "total"]  # test last
    table = format_table1([a, c, b])
    lines = table.splitlines()
    assert lines[0].split()[:3] == ["bag", "split", "frames"] and "< 15 mm" in lines[0] and "p95" in lines[0]
    names = [ln.split()[0] for ln in lines if ln and not ln.startswith("-")][1:]
    # dev rows, their total; then the test block; then the overall total
    assert names == ["a", "b", "total", "c", "total", "total"]
    dev_row = next(ln for ln in lines if ln.startswith("total dev"))
    assert dev_row.split()[2:5] == ["dev", "6", "18.0"]
    assert "test split (held out)" in table
    all_row = lines[-1].split()
    # over all 7 frames: (10 + 20 + 16 + 16 + 28 + 40) / 6 frames with an estimate
    assert all_row[:6] == ["total", "(all", "bags)", "all", "7", "21.7"]
    md = format_table1([a, c], markdown=True)
    assert md.startswith("| bag | split | frames |") and "| **test split (held out)** |" in md


def test_cli_several_bags_table_json_and_the_test_split(
    tmp_path: Path, fake_tracker: type[FakeTracker], capsys: pytest.CaptureFixture[str]
) -> None:
    root = tmp_path / "bags"
    _bag(root / "dev1", [10.0, 20.0], split="dev")
    _bag(root / "held", [12.0], split="test")
    _bag(tmp_path / "loose", [30.0, None])
    out = tmp_path / "r.json"
    assert main([str(root), str(tmp_path / "loose"), "--json", str(out)]) == 0
    cap = capsys.readouterr()
    rows = [ln.split()[0] for ln in cap.out.splitlines()]
    assert rows.index("dev1") < rows.index("loose") < rows.index("held")  # test rows in their own block
    assert "[1/3] dev1 (split dev)" in cap.err and "[3/3] loose (split -)" in cap.err
    assert "per-frame records of test-split bags are left out" in cap.err
    js = json.loads(out.read_text())
    assert [b["name"] for b in js["bags"]] == ["dev1", "held", "loose"]
    assert [b["split"] for b in js["bags"]] == ["dev", "test", "-"]
    by = {b["name"]: b for b in js["bags"]}
    assert len(by["dev1"]["per_frame"]) == 2 and by["dev1"]["per_frame"][1]["error_mm"] == pytest.approx(20.0)
    assert "per_frame" not in by["held"] and "held out" in by["held"]["per_frame_withheld"]
    assert by["held"]["mean_fingertip_error_mm"] == pytest.approx(12.0)  # totals of test bags are fine
    assert [t["label"] for t in js["totals"]] == ["total dev", "total -", "total test", "total"]
    assert js["totals"][-1]["frames"] == 5 and js["totals"][-1]["frames_scored"] == 5
    assert js["totals"][-1]["mean_fingertip_error_mm"] == pytest.approx((10 + 20 + 12 + 30) / 4)
    # a final report may look
    assert main([str(root / "held"), "--json", str(out), "--allow-test-inspection", "--quiet"]) == 0
    assert len(json.loads(out.read_text())["bags"][0]["per_frame"]) == 1
    # one bad bag among good ones: the others are still evaluated, exit status 2
    (tmp_path / "empty").mkdir()
    _bag(tmp_path / "empty" / "x", [5.0])
    (tmp_path / "empty" / "x" / "metadata.yaml").write_text("garbage: [")
    assert main([str(root / "dev1"), str(tmp_path / "empty")]) == 2
    cap = capsys.readouterr()
    assert "error: " in cap.err and "dev1" in cap.out


def test_overlay_is_refused_on_test_bags_unless_allowed(
    tmp_path: Path, fake_tracker: type[FakeTracker], capsys: pytest.CaptureFixture[str]
) -> None:
    _bag(tmp_path / "held", [12.0, 14.0], split="test")
    _bag(tmp_path / "dev", [12.0], split="dev")
    ov = tmp_path / "ov"
    assert main([str(tmp_path / "dev"), str(tmp_path / "held"), "--overlay", str(ov)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --overlay refused for the test-split bag(s) held:")
    assert "--allow-test-inspection" in err and "Traceback" not in err
    assert not ov.exists() and FakeTracker.configs == []  # refused before any work
    assert main([str(tmp_path / "held"), "--overlay", str(ov), "--allow-test-inspection", "--quiet"]) == 0
    assert sorted(p.name for p in ov.iterdir()) == ["held_0000_12.0mm.png", "held_0001_14.0mm.png"]


def test_overlays_of_the_worst_frames(tmp_path: Path, fake_tracker: type[FakeTracker]) -> None:
    from hand_sog_tracker.core.overlay import draw_overlay

    _bag(tmp_path / "b", [10.0, 18.0, 26.0, None, 12.0, 3.0], split="dev")
    ov = tmp_path / "ov"
    assert main([str(tmp_path / "b"), "--overlay", str(ov), "--overlay-worst", "3", "--quiet"]) == 0
    # worst first: the frame without an estimate, then 26 and 18 mm
    assert sorted(p.name for p in ov.iterdir()) == ["b_0001_18.0mm.png", "b_0002_26.0mm.png", "b_0003_lost.png"]
    img = cv2.imread(str(ov / "b_0002_26.0mm.png"))
    assert img is not None and img.shape == (60, 80, 3)
    # true fingertips: white rings around their projections; tracked tips, lines and text are drawn too
    ev = evaluate_core(tmp_path / "b", progress=False, keep_worst=1)
    assert len(ev.worst) == 1 and ev.worst[0].record.index == 3
    truth_uv = INTR.project(ev.records[2].truth_mm)
    white = np.all(img > 240, axis=2)
    near = [white[max(int(v) - 6, 0): int(v) + 7, max(int(u) - 6, 0): int(u) + 7].any() for u, v in truth_uv]
    assert all(near)
    plain = draw_overlay(np.zeros((60, 80)), INTR, None, None)
    assert (np.abs(img.astype(int) - plain.astype(int)).sum(axis=2) > 60).sum() > 100


def test_overlay_with_the_real_tracker_draws_the_model(tmp_path: Path) -> None:
    from hand_sog_tracker.tools.make_sample_bags import write_sample_bag

    bag = write_sample_bag(tmp_path / "wave", "fingerwave", 3, width=160, height=120)
    ev = evaluate_core(bag.path, progress=False, keep_worst=2)
    assert [w.record.index for w in ev.worst] == sorted(
        range(3), key=lambda i: -float(np.mean(ev.records[i].errors_mm))
    )[:2]
    assert all(w.pose is not None and w.model is not None for w in ev.worst)
    from hand_sog_tracker.tools.figures import write_overlays

    files = write_overlays(ev, tmp_path / "ov")
    assert len(files) == 2 and all(cv2.imread(str(f)).shape == (120, 160, 3) for f in files)


def test_left_hand_sidecar_and_tracker_settings(
    tmp_path: Path, fake_tracker: type[FakeTracker], capsys: pytest.CaptureFixture[str]
) -> None:
    _bag(tmp_path / "lh", [5.0], split="dev", handedness="left")
    assert main([str(tmp_path / "lh"), "--quiet"]) == 0
    assert FakeTracker.configs[-1].right_hand is False
    assert "sidecar says a left hand; tracking it with a left-hand tracker" in capsys.readouterr().err
    assert main([str(tmp_path / "lh"), "--quiet", "--handedness", "right"]) == 0
    assert FakeTracker.configs[-1].right_hand is True
    params = tmp_path / "p.yaml"
    params.write_text(
        "hand_sog_tracker:\n  ros__parameters:\n    iterations: 7\n    far_mm: 700\n    debug_image: true\n"
    )
    assert main([str(tmp_path / "lh"), "--quiet", "--params", str(params), "--set", "iterations=12"]) == 0
    cfg = FakeTracker.configs[-1]
    assert (cfg.iterations, cfg.far_mm, cfg.right_hand) == (12, 700.0, False)
    assert "core mode ignores the node-only parameter(s) debug_image" in capsys.readouterr().err
    n = len(FakeTracker.configs)
    assert main([str(tmp_path / "lh"), "--set", "iterations=many"]) == 2
    assert "error: --set iterations=many: iterations must be int" in capsys.readouterr().err
    assert main([str(tmp_path / "lh"), "--set", "near_mm=1500"]) == 2
    assert "near_mm" in capsys.readouterr().err
    assert main([str(tmp_path / "lh"), "--set", "wiggle=1"]) == 2
    assert "unknown tracker parameter 'wiggle'" in capsys.readouterr().err
    assert len(FakeTracker.configs) == n  # nothing evaluated after a settings error


def test_plot_extra_absent_and_present(
    tmp_path: Path, fake_tracker: type[FakeTracker], monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    _bag(tmp_path / "d", [10.0, 30.0], split="dev")
    _bag(tmp_path / "t", [20.0], split="test")
    png = tmp_path / "p.png"
    assert main([str(tmp_path / "d"), str(tmp_path / "t"), "--plot", str(png), "--quiet"]) == 0
    img = cv2.imread(str(png))
    assert img is not None and img.shape == (420, 1120, 3)
    assert "error-over-time plot leaves out test-split bags" in capsys.readouterr().err
    for name in [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ImportError
    png.unlink()
    assert main([str(tmp_path / "d"), "--plot", str(png), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "matplotlib" in err and "pip install 'hand_sog_tracker[plot]'" in err and "Traceback" not in err
    assert not png.exists()
