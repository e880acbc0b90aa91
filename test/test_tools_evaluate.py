"""evaluate_bag: scoring, JSON, plot, CLI options and errors, on tiny bags in tmp_path."""

from __future__ import annotations

import io
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from hand_sog_tracker.core.types import Intrinsics, TrackerStatus, TrackResult
from hand_sog_tracker.errors import BagError, DepthImageError
from hand_sog_tracker.tools import bagio, evaluate_bag
from hand_sog_tracker.tools.bagio import BagTopics, DepthSample, write_depth_bag
from hand_sog_tracker.tools.evaluate_bag import Progress, evaluate_core, main

T0 = 1_700_000_000_000_000_000
DT = 33_333_333
INTR = Intrinsics(fx=90.0, fy=90.0, cx=39.5, cy=29.5, width=80, height=60)
#: What the fake tracker reports (mm), frame after frame.
TIPS = np.array(
    [[-40.0, 0.0, 400.0], [-20.0, -60.0, 400.0], [0.0, -70.0, 400.0], [20.0, -60.0, 400.0], [40.0, -45.0, 400.0]]
)
#: Per-frame error of all five fingertips (mm); None = frame without ground truth.
FRAME_ERRORS = [10.0, 18.0, None, 26.0, 40.0, 12.0]


class FakeTracker:
    """Reports TIPS every frame except the 5th (NO_HAND); rejects all-zero images."""

    def __init__(self) -> None:
        self.calls = 0

    def process(self, depth_mm: np.ndarray, intrinsics: Intrinsics) -> TrackResult:
        if not np.any(depth_mm > 0):
            raise DepthImageError("empty image")
        self.calls += 1
        if self.calls == 5:
            return TrackResult(TrackerStatus.NO_HAND, None, None, None, 0.0, 0.0, 0)
        return TrackResult(TrackerStatus.TRACKING, np.zeros(26), TIPS.copy(), None, 1.0, 1.0, 10)


def _known_bag(path: Path, rng: np.random.Generator, topics: BagTopics = BagTopics()) -> None:
    """Ground truth = TIPS moved by FRAME_ERRORS[i] in a random direction per finger."""
    samples = []
    for i, e in enumerate(FRAME_ERRORS):
        truth = None
        if e is not None:
            d = rng.normal(size=(5, 3))
            truth = TIPS + e * d / np.linalg.norm(d, axis=1, keepdims=True)
        depth = rng.uniform(300.0, 900.0, (60, 80))
        samples.append(DepthSample(T0 + i * DT, depth, INTR, truth))
    write_depth_bag(path, samples, topics=topics)


def _empty_bag(path: Path, n: int, truth: bool = True, depth_mm: float = 900.0) -> None:
    """A wall at ``depth_mm`` (no hand): the real tracker reports NO_HAND."""
    tips = TIPS if truth else None
    write_depth_bag(path, [DepthSample(T0 + i * DT, np.full((60, 80), depth_mm), INTR, tips) for i in range(n)])


def test_scores_known_errors_exactly(tmp_path: Path) -> None:
    rng = np.random.default_rng(20)
    _known_bag(tmp_path / "b", rng)
    ev = evaluate_core(tmp_path / "b", tracker=FakeTracker(), progress=False)
    js = ev.to_json()
    # scored frames: errors 10, 18, 26, 12 with an estimate; the 5th call (error 40) is NO_HAND
    assert js["frames"] == 6
    assert js["frames_scored"] == 5
    assert js["frames_without_ground_truth"] == 1
    assert js["frames_with_estimate"] == 4
    assert js["mean_fingertip_error_mm"] == pytest.approx((10 + 18 + 26 + 12) / 4)
    assert js["per_finger_mm"] == pytest.approx({f: 16.5 for f in ("thumb", "index", "middle", "ring", "little")})
    assert js["pct_frames_below_mm"] == pytest.approx({"15": 40.0, "20": 60.0, "25": 60.0, "30": 80.0})
    assert js["status_counts"] == {"no_hand": 1, "tracking": 5}
    assert set(js["ms_per_frame"]) >= {"median", "p95"}
    assert js["ms_per_frame"]["median"] > 0 and js["fps"] > 0
    assert [p["error_mm"] for p in js["per_frame"]] == pytest.approx([10.0, 18.0, None, 26.0, None, 12.0])
    json.dumps(js, allow_nan=False)  # strictly valid JSON


def test_unusable_frames_are_counted_not_fatal(tmp_path: Path) -> None:
    rng = np.random.default_rng(21)
    samples = [
        DepthSample(T0, rng.uniform(300, 900, (60, 80)), INTR, TIPS),
        DepthSample(T0 + DT, np.zeros((60, 80)), INTR, TIPS),  # the fake tracker rejects it
        DepthSample(T0 + 2 * DT, rng.uniform(300, 900, (60, 80)), INTR, TIPS + [3.0, 4.0, 0.0]),
    ]
    write_depth_bag(tmp_path / "b", samples)
    ev = evaluate_core(tmp_path / "b", tracker=FakeTracker(), progress=False)
    assert ev.status_counts == {"error": 1, "tracking": 2}
    assert ev.errors.mean_mm == pytest.approx(2.5)
    assert ev.errors.pct_below_mm["15"] == pytest.approx(200.0 / 3)
    # all frames unusable: a clear error
    write_depth_bag(tmp_path / "z", [DepthSample(T0 + i * DT, np.zeros((60, 80)), INTR, TIPS) for i in range(2)])
    with pytest.raises(BagError, match="no depth image could be used; first problem: frame 0 .*empty image"):
        evaluate_core(tmp_path / "z", tracker=FakeTracker(), progress=False)


def test_no_matching_ground_truth_is_an_error(tmp_path: Path) -> None:
    rng = np.random.default_rng(22)
    with bagio.BagWriter(tmp_path / "b") as w:
        for i in range(3):
            t = T0 + i * DT
            w.write(bagio.INFO_TOPIC, bagio.camera_info_msg(INTR, t), t)
            w.write(bagio.DEPTH_TOPIC, bagio.depth_image_msg(rng.uniform(300, 900, (60, 80)), t), t)
            w.write(bagio.GT_TOPIC, bagio.fingertips_msg(TIPS, t + 1), t)  # stamps never match
    with pytest.raises(BagError, match="none of the 3 depth images has ground truth"):
        evaluate_core(tmp_path / "b", tracker=FakeTracker(), progress=False)


def test_cli_json_plot_and_table(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _empty_bag(tmp_path / "b", 4)
    out_json, out_png = tmp_path / "r.json", tmp_path / "r.png"
    assert main([str(tmp_path / "b"), "--json", str(out_json), "--plot", str(out_png)]) == 0
    text = capsys.readouterr().out
    assert "mean fingertip error (mm)" in text and "15 mm" in text and "ms per frame: median" in text
    js = json.loads(out_json.read_text())["bags"][0]
    for key in ("frames", "mean_fingertip_error_mm", "per_finger_mm", "pct_frames_below_mm", "ms_per_frame", "fps"):
        assert key in js
    # no hand in a flat wall: nothing tracked, every scored frame is a failure
    assert js["frames"] == 4 and js["frames_scored"] == 4 and js["frames_with_estimate"] == 0
    assert js["status_counts"] == {"no_hand": 4}
    assert js["mean_fingertip_error_mm"] is None
    assert js["pct_frames_below_mm"] == {"15": 0.0, "20": 0.0, "25": 0.0, "30": 0.0}
    assert set(js["ms_per_frame"]) >= {"median", "p95"}
    img = cv2.imread(str(out_png))
    assert img is not None and img.shape == (420, 1120, 3)
    assert int((img < 128).sum()) > 1000  # axes, labels and curves were drawn


def test_plot_of_known_errors(tmp_path: Path) -> None:
    rng = np.random.default_rng(23)
    _known_bag(tmp_path / "b", rng)
    ev = evaluate_core(tmp_path / "b", tracker=FakeTracker(), progress=False)
    evaluate_bag.write_plot(ev, tmp_path / "p.png")
    img = cv2.imread(str(tmp_path / "p.png"))
    assert img is not None
    # the %-below curve is green (0, 140, 0) in the right panel only
    green = (img[:, :, 1] > 100) & (img[:, :, 0] < 80) & (img[:, :, 2] < 80)
    assert green[:, 560:].sum() > 100 and green[:, :560].sum() == 0


def test_cli_topic_options_and_max_frames(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rng = np.random.default_rng(24)
    topics = BagTopics(depth="/d/image", info="/d/info", truth="/gt")
    _known_bag(tmp_path / "b", rng, topics)
    out = tmp_path / "r.json"
    assert main([str(tmp_path / "b"), "--json", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: depth topic '/camera/depth/image_rect_raw' not in bag")
    assert "/d/image" in err and "/d/info" in err and "/gt" in err and "Traceback" not in err
    args = [str(tmp_path / "b"), "--depth-topic", "/d/image", "--info-topic", "/d/info", "--gt-topic", "/gt"]
    assert main(args + ["--json", str(out), "--max-frames", "3", "--quiet"]) == 0
    assert capsys.readouterr().out == ""
    js = json.loads(out.read_text())["bags"][0]
    assert js["frames"] == 3 and js["frames_without_ground_truth"] == 1 and js["frames_scored"] == 2


def test_cli_errors_exit_2_without_traceback(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_depth_bag(tmp_path / "nogt", [DepthSample(T0, np.full((60, 80), 900.0), INTR, None)])
    assert main([str(tmp_path / "nogt")]) == 2
    err = capsys.readouterr().err
    assert "ground-truth topic '/hand/ground_truth/fingertips' not in bag" in err and "Traceback" not in err
    write_depth_bag(tmp_path / "noinfo", [DepthSample(T0, np.full((60, 80), 900.0), None, TIPS)])
    assert main([str(tmp_path / "noinfo")]) == 2
    assert "CameraInfo topic '/camera/depth/camera_info' not in bag" in capsys.readouterr().err
    assert main([str(tmp_path / "missing")]) == 2
    assert capsys.readouterr().err.startswith("error: bag not found")
    _empty_bag(tmp_path / "t", 3)
    mcap = next((tmp_path / "t").glob("*.mcap"))
    mcap.write_bytes(mcap.read_bytes()[:300])
    assert main([str(tmp_path / "t")]) == 2
    assert "corrupt" in capsys.readouterr().err
    _empty_bag(tmp_path / "ok", 1)
    assert main([str(tmp_path / "ok"), "--plot", str(tmp_path / "no_dir" / "p.png")]) == 2
    assert "cannot write plot" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main([str(tmp_path / "ok"), "--calibrate", "--through-node"])
    assert exc.value.code == 2
    with pytest.raises(SystemExit):
        main([str(tmp_path / "ok"), "--max-frames", "0"])


def test_cli_calibrate_reports_calibration_failure(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _empty_bag(tmp_path / "b", 3)
    assert main([str(tmp_path / "b"), "--calibrate"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "hand" in err and "Traceback" not in err


def test_progress_bar_only_on_a_terminal() -> None:
    class Tty(io.StringIO):
        def isatty(self) -> bool:
            return True

    tty, pipe = Tty(), io.StringIO()
    for stream in (tty, pipe):
        bar = Progress(3, stream=stream)
        for _ in range(3):
            bar.update(1, "x")
        bar.close()
    assert "\r[" in tty.getvalue() and "3/3" in tty.getvalue() and tty.getvalue().endswith("\n")
    assert pipe.getvalue() == ""


def test_json_has_no_nan(tmp_path: Path) -> None:
    _empty_bag(tmp_path / "b", 2)
    ev = evaluate_core(tmp_path / "b", progress=False)
    js = ev.to_json()
    assert js["per_finger_mm"] == {f: None for f in ("thumb", "index", "middle", "ring", "little")}
    assert not any(isinstance(v, float) and math.isnan(v) for v in js.values())


def test_calibrate_fits_on_the_first_frames_then_tracks_all(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from hand_sog_tracker.core import calibration
    from hand_sog_tracker.core.hand_model import HandShape, default_hand_model

    rng = np.random.default_rng(25)
    _known_bag(tmp_path / "b", rng)
    seen: dict[str, object] = {}
    fitted_shape = HandShape(length=1.1, width=0.9, sigma=1.0, depth=1.05)

    def fake_calibrate(frames, intrinsics, config, model, start_pose=None, holdout=()):  # type: ignore[no-untyped-def]
        seen["n"], seen["intr"], seen["model"], seen["holdout"] = len(frames), intrinsics, model, len(holdout)
        fitted = default_hand_model(True).scaled(fitted_shape)
        return calibration.CalibrationResult(fitted_shape, fitted, np.zeros(26), 1.0, 2.0, 0.25)

    class CalibratableTracker(FakeTracker):
        def __init__(self) -> None:
            super().__init__()
            self.model = default_hand_model(True)
            self.resets = 0

        def set_model(self, model: object) -> None:
            self.model = model

        def reset(self) -> None:
            self.resets += 1

    monkeypatch.setattr(calibration, "calibrate", fake_calibrate)
    tr = CalibratableTracker()
    ev = evaluate_core(tmp_path / "b", calibrate=True, tracker=tr, progress=False)
    assert seen["n"] == 3 and seen["intr"] == INTR  # fitted on the first three usable frames
    assert seen["holdout"] == 3  # checked on the next three
    assert tr.model.shape == fitted_shape and tr.resets == 1
    assert ev.frames == 6 and tr.calls == 6  # the calibration frames are tracked too
    js = ev.to_json()
    assert js["calibration"]["shape"] == pytest.approx({"length": 1.1, "width": 0.9, "sigma": 1.0, "depth": 1.05})
    assert js["calibration"]["fit_score_after"] == 2.0 and js["calibration"]["accepted"]
    assert js["mean_fingertip_error_mm"] == pytest.approx(16.5)  # same scoring as without calibration


def test_core_mode_is_deterministic_on_a_synthetic_hand(tmp_path: Path) -> None:
    from hand_sog_tracker.tools.make_sample_bags import write_sample_bag

    bag = write_sample_bag(tmp_path / "b", "fingerwave", 5, width=160, height=120)
    runs = [evaluate_core(bag.path, progress=False).to_json() for _ in range(2)]
    errors = [[p["error_mm"] for p in r["per_frame"]] for r in runs]
    assert errors[0] == errors[1]
    assert runs[0]["status_counts"] == runs[1]["status_counts"]
    assert runs[0]["status_counts"].get("tracking", 0) >= 1
    assert runs[0]["image_size"] == [160, 120]


def test_calibrate_keeps_the_model_when_the_guard_refuses_the_fit(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from hand_sog_tracker.core import calibration
    from hand_sog_tracker.core.hand_model import HandShape, default_hand_model

    _known_bag(tmp_path / "b", np.random.default_rng(26))

    def refusing(frames, intrinsics, config, model, start_pose=None, holdout=()):  # type: ignore[no-untyped-def]
        raise calibration.CalibrationRejected(HandShape(length=1.2), calibration.Validation(3, 0.8, 0.79, 0.01))

    class CalibratableTracker(FakeTracker):
        def __init__(self) -> None:
            super().__init__()
            self.model = default_hand_model(True)

        def set_model(self, model: object) -> None:
            self.model = model

    monkeypatch.setattr(calibration, "calibrate", refusing)
    tr = CalibratableTracker()
    ev = evaluate_core(tmp_path / "b", calibrate=True, tracker=tr, progress=False)
    assert tr.model.shape == HandShape()  # the default model stays
    info = ev.to_json()["calibration"]
    assert info["accepted"] is False and "rejected" in info["reason"]
    assert info["holdout_score_fitted"] == pytest.approx(0.79)


def test_core_mode_fits_the_model_automatically_as_the_node_does(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The real tracker on a rendered open hand (30 Hz): once the history holds AUTO_MIN_FRAMES
    # tracked frames, the fit runs on open-hand frames with their tracked poses, checked on
    # others, and its model is used from the first frame stamped AUTO_APPLY_S after the fit's
    # start on (as in the node: by image stamps); auto_calibrate=False fits nothing.
    from hand_sog_tracker.core import calibration
    from hand_sog_tracker.core.autocalibration import AUTO_APPLY_S, AUTO_MIN_FRAMES, AUTO_MIN_LENGTH
    from hand_sog_tracker.core.hand_model import HandShape, default_hand_model
    from hand_sog_tracker.tools.make_sample_bags import write_sample_bag

    n_frames = AUTO_MIN_FRAMES + int(AUTO_APPLY_S * 30) + 3  # (30 Hz)
    bag = write_sample_bag(tmp_path / "b", "abdadd", n_frames, width=160, height=120)
    calls: list[dict] = []
    fitted_shape = HandShape(length=1.1, width=1.05)

    def stand_in(frames, intrinsics, config, model, start_pose=None, **kwargs):  # type: ignore[no-untyped-def]
        calls.append({"n": len(frames), "poses": kwargs["poses"], "holdout": kwargs["holdout"]})
        return calibration.CalibrationResult(
            fitted_shape, default_hand_model(True).scaled(fitted_shape), np.zeros(26), 1.0, 2.0, 0.25
        )

    monkeypatch.setattr(calibration, "calibrate", stand_in)
    from hand_sog_tracker.core.tracker import Tracker

    tracker = Tracker()
    js = evaluate_core(bag.path, tracker=tracker, progress=False).to_json()
    assert len(calls) == 1 and calls[0]["n"] == 3 and len(calls[0]["holdout"]) == 4
    assert all(p is not None and p.shape == (26,) for p in calls[0]["poses"])
    fits = js["auto_calibration"]
    assert len(fits) == 1 and fits[0]["frame"] == AUTO_MIN_FRAMES - 1 and fits[0]["accepted"]
    assert fits[0]["shape"]["length"] == pytest.approx(1.1)
    assert tracker.model.shape == fitted_shape
    assert fits[0]["used"]
    # A fit that shrinks the hand below AUTO_MIN_LENGTH keeps the default model (no retry).
    fitted_shape = HandShape(length=AUTO_MIN_LENGTH - 0.05)
    calls.clear()
    tracker = Tracker()
    fits = evaluate_core(bag.path, tracker=tracker, progress=False).to_json()["auto_calibration"]
    assert len(calls) == 1 and fits[0]["accepted"] and not fits[0]["used"]
    assert tracker.model.shape == HandShape()
    calls.clear()
    js = evaluate_core(bag.path, tracker=Tracker(), progress=False, auto_calibrate=False).to_json()
    assert calls == [] and "auto_calibration" not in js
