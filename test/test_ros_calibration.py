"""~/calibrate through the node: tracking goes on during the fit, the guard's answer, the saved metadata.

Uses the in-process rig of test_ros_node.py (own rclpy context, unique namespace, loopback DDS).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from std_srvs.srv import Trigger
from test_core_calibration import _rows

from hand_sog_tracker.core.autocalibration import AUTO_APPLY_S
from hand_sog_tracker.core.calibration import CalibrationRejected, Validation
from hand_sog_tracker.core.hand_model import HandShape, default_hand_model, rest_pose
from hand_sog_tracker.core.model_io import load_hand_shape, read_calibration_info
from hand_sog_tracker.ros import calibration_service
from hand_sog_tracker.ros.conversions import stamp_to_ns
from test_ros_node import T0_NS, Rig, hand_depth, image_msg

PERIOD_NS = 33_333_333  # 30 Hz


def open_hand_frames(n: int, model) -> list[np.ndarray]:
    """An open hand held still (a few mm of drift) at 430 mm."""
    rng = np.random.default_rng(3)
    out = []
    for i in range(n):
        th = rest_pose((0.0, 20.0, 430.0))
        th[:3] += rng.normal(0.0, 1.5, 3)
        out.append(hand_depth(th, seed=i, model=model))
    return out


def test_tracking_goes_on_during_a_calibration_and_the_answer_has_the_numbers(ros_context, tmp_path: Path) -> None:
    """A real fit in the child process while the 30 Hz camera goes on.  The guard may accept it
    (the model is saved with its metadata) or not ("the current model already fits" on this
    static hand, whose held-out frames differ little: nothing saved); either way the numbers."""
    model = default_hand_model().scaled(HandShape(length=1.12, width=1.08, depth=1.05, sigma=1.05))
    frames = open_hand_frames(40, model)
    rig = Rig(ros_context, tmp_path)
    node, process = rig.node, rig.node._process_pending
    proc: list[float] = []  # the node's processing of each frame (ms)

    def timed() -> None:
        t = time.perf_counter()
        process()
        proc.append((time.perf_counter() - t) * 1e3)

    node._process_pending = timed
    try:
        rig.send_info()
        for i in range(12):  # fill the history (one frame per 60 ms is kept)
            rig.send(image_msg(frames[i], T0_NS + i * PERIOD_NS * 2))
        k0 = 12
        proc.clear()
        future = rig.calib.call_async(Trigger.Request())
        t_call = time.monotonic()
        sent: list[int] = []
        k = k0
        # The camera goes on at 30 Hz while the service call is pending.
        while not future.done() and time.monotonic() < t_call + 60.0:
            if time.monotonic() >= t_call + len(sent) / 30.0:
                stamp = T0_NS + k0 * PERIOD_NS * 2 + len(sent) * PERIOD_NS
                rig.image_pub.publish(image_msg(frames[k % len(frames)], stamp))
                sent.append(stamp)
                k += 1
            rig.executor.spin_once(timeout_sec=0.002)
        call_s = time.monotonic() - t_call
        assert future.done(), "no answer within 60 s"
        rig.spin_until(lambda: False, 0.3)  # let the last outputs arrive
        got = {stamp_to_ns(m.header.stamp) for m, _ in rig.joints}
        share = sum(s in got for s in sent) / max(len(sent), 1)
        answer = future.result()
        # The node can answer at most one frame per processing (the others are dropped whole):
        # on a busy machine that is fewer than the camera's 30 Hz.
        can = min(1.0, PERIOD_NS * 1e-6 / float(np.median(proc))) if proc else 1.0
        print(f"call {call_s:.2f} s, {len(sent)} frames sent meanwhile, {share:.0%} got a JointState "
              f"(processing median {np.median(proc) if proc else 0:.0f} ms: at most {can:.0%}); {answer.message}")
        assert len(sent) >= 5  # the fit takes several frame periods ...
        assert share >= 0.5 * can  # ... and most of them are still tracked (README: measured share)
        assert "held-out score" in answer.message and "re-tracked score" in answer.message
        if not answer.success:
            assert answer.message.startswith("the current model already fits") or "rejected" in answer.message
            assert not (tmp_path / "hand_model.yaml").exists() and rig.node.hand_model.shape == HandShape()
            return
        _check_saved(rig, tmp_path, answer.message)
    finally:
        rig.close()


def _check_saved(rig: Rig, tmp_path: Path, message: str) -> None:
    """The accepted fit is in use and saved with the guard's metadata."""
    assert "saved to" in message
    shape, right = load_hand_shape(tmp_path / "hand_model.yaml")
    assert right and rig.node.hand_model.shape == shape
    info = read_calibration_info(tmp_path / "hand_model.yaml")
    assert info["fit_frames"] >= 1 and info["holdout_frames"] >= 1
    assert len(str(info["fit_stamps"]).split()) == info["fit_frames"]
    assert len(str(info["fit_pose_0"]).split()) == 26
    assert info["holdout_score_fitted"] >= info["holdout_score_current"] + info["guard_margin"]
    assert len(str(info["holdout_stamps"]).split()) == info["holdout_frames"] >= 3
    assert info["holdout_worst_frame_gain"] >= -info["guard_frame_drop"]
    assert "best-pose score" in str(info["guard_rules"]) and "re-tracked score" in str(info["guard_evidence"])


def test_an_accepted_fit_is_used_and_saved_with_the_guard_metadata(
    ros_context, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The node's side of an accepted fit (a stand-in fit whose guard's evidence all improves):
    the model switches and the file holds the fit's and the guard's numbers."""
    from hand_sog_tracker.core.calibration import CalibrationResult

    validation = Validation(**_rows([0.02, 0.03, 0.025, 0.02], [-1.0] * 4, [0.03, 0.02, 0.04, 0.03], [0.0] * 4))
    shape = HandShape(1.1, 1.05, 1.0, 1.0)

    def accept(frames, intrinsics, config, model, start_pose=None, **kwargs):  # type: ignore[no-untyped-def]
        poses = np.array([p for p in kwargs["poses"]])
        used = tuple(range(len(frames)))
        return CalibrationResult(shape, model.scaled(shape), poses[0], 0.80, 0.83, 0.3, poses, used, validation)

    monkeypatch.setattr(calibration_service, "calibrate", accept)
    monkeypatch.setattr(calibration_service, "FIT_IN_PROCESS", False)
    rig = Rig(ros_context, tmp_path)
    try:
        rig.send_info()
        for i, depth in enumerate(open_hand_frames(12, default_hand_model())):
            rig.send(image_msg(depth, T0_NS + i * 2 * PERIOD_NS))
        future = rig.calib.call_async(Trigger.Request())
        assert rig.spin_until(future.done, 30.0)
        answer = future.result()
        assert answer.success, answer.message
        assert rig.node.hand_model.shape == shape
        _check_saved(rig, tmp_path, answer.message)
    finally:
        rig.close()


@pytest.mark.parametrize("already", [False, True], ids=["refused", "already-fits"])
def test_a_refused_fit_changes_and_saves_nothing(
    ros_context, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, already: bool
) -> None:
    """A fit the guard refuses, or one within the noise ("the current model already fits"):
    ``success: false`` with the numbers, the model unchanged and nothing saved."""
    gains = [0.0, 0.001, -0.001, 0.0] if already else [-0.02, -0.01, -0.012, -0.015]
    validation = Validation(**_rows(gains, [0.0] * 4, gains, [0.0] * 4))
    assert validation.already_fits is already and not validation.accepted

    def refuse(frames, intrinsics, config, model, start_pose=None, **kwargs):  # type: ignore[no-untyped-def]
        assert len(kwargs["holdout"]) >= 1 and len(kwargs["poses"]) == len(frames)
        raise CalibrationRejected(HandShape(0.9, 0.9, 0.9, 0.9), validation)

    monkeypatch.setattr(calibration_service, "calibrate", refuse)
    monkeypatch.setattr(calibration_service, "FIT_IN_PROCESS", False)  # the stand-in runs on the worker thread
    rig = Rig(ros_context, tmp_path)
    try:
        rig.send_info()
        for i, depth in enumerate(open_hand_frames(4, default_hand_model())):
            rig.send(image_msg(depth, T0_NS + i * 10**8))
        before = rig.node.hand_model
        future = rig.calib.call_async(Trigger.Request())
        assert rig.spin_until(future.done, 30.0)
        answer = future.result()
        assert answer.success is False and "nothing changed or saved" in answer.message
        if already:
            assert answer.message.startswith("the current model already fits: held-out score 0.8000")
        else:
            assert "rejected" in answer.message and "held-out score worse" in answer.message
        assert f"{validation.score_fitted:.4f}" in answer.message and "re-tracked score" in answer.message
        assert rig.node.hand_model is before
        assert not (tmp_path / "hand_model.yaml").exists()
    finally:
        rig.close()


def test_calibration_needs_frames_to_check_the_fit_on(ros_context, tmp_path: Path) -> None:
    rig = Rig(ros_context, tmp_path)
    try:
        rig.send_info()
        rig.send(image_msg(open_hand_frames(1, default_hand_model())[0], T0_NS))
        future = rig.calib.call_async(Trigger.Request())
        assert rig.spin_until(future.done, 30.0)
        answer = future.result()
        assert answer.success is False and "one more frame to check the fit on" in answer.message
        assert not (tmp_path / "hand_model.yaml").exists()
    finally:
        rig.close()


def test_the_node_fits_a_large_hand_by_itself_keeps_tracking_and_saves_nothing(ros_context, tmp_path: Path) -> None:
    # Half a second of a hand 1.12x long and 1.1x wide at 30 Hz: the node fits the model by
    # itself (auto_calibrate, the default) in a child process, answers every frame meanwhile,
    # uses the fitted model if the guard accepts it, and writes no file.
    model = default_hand_model().scaled(HandShape(length=1.12, width=1.1, depth=1.05, sigma=1.05))
    frames = open_hand_frames(40, model)
    rig = Rig(ros_context, tmp_path, auto_calibrate=True)
    try:
        assert rig.node.settings.auto_calibrate
        rig.send_info()
        k = 0
        end = time.monotonic() + 60.0
        auto = rig.node._auto_calib

        def settled() -> bool:  # the model switched, or the fits ended without a switch
            done = auto.attempts > 0 and not auto.running and (auto.accepted or auto.attempts >= auto.max_attempts)
            return rig.node.hand_model.shape != HandShape() or (done and auto._pending is None)

        first_fit = None
        while time.monotonic() < end and not settled():
            rig.send(image_msg(frames[k % len(frames)], T0_NS + k * PERIOD_NS))
            rig.spin_until(lambda: False, 1.0 / 30.0)  # a 30 Hz camera
            first_fit = k if first_fit is None and auto.attempts else first_fit
            k += 1
        shape = rig.node.hand_model.shape
        assert auto.attempts >= 1 and first_fit is not None, f"no automatic fit after {k} frames"
        assert first_fit >= 14  # not before the history holds half a second
        if shape != HandShape():  # accepted: in use from AUTO_APPLY_S after the fit's start
            assert k >= first_fit + 30
            # On the first frame stamped AUTO_APPLY_S after the fit's start, by the stamps alone
            # (a fit still running then is waited for), unless the wait ran out (a busy machine).
            start = auto.started_ns
            assert start is not None and auto.taken_ns is not None
            due = T0_NS + -(-(start + int(AUTO_APPLY_S * 1e9) - T0_NS) // PERIOD_NS) * PERIOD_NS
            if all(ended for _, ended in rig.node.auto_fit_waits):
                assert auto.taken_ns == due, (auto.taken_ns, due, rig.node.auto_fit_waits)
            else:
                assert auto.taken_ns > due
            assert 1.05 <= shape.length <= 1.19 and 1.03 <= shape.width <= 1.17, shape
        else:  # the guard found no clear gain (a static hand: held-out frames much like the fit's)
            assert auto.accepted or auto.attempts == auto.max_attempts
        assert rig.node.stats.processed == k  # every frame was answered during the fit
        assert not (tmp_path / "hand_model.yaml").exists()
    finally:
        rig.close()


def test_an_automatic_fit_still_running_on_its_due_frame_is_waited_for(
    ros_context, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The switch lands on the first frame stamped AUTO_APPLY_S after the fit's start however
    late the fit ends (within AUTO_WAIT_S): a stand-in fit that ends only once the node waits
    for it on that frame."""
    from hand_sog_tracker.core.calibration import CalibrationResult

    shape = HandShape(1.1, 1.05, 1.0, 1.0)
    monkeypatch.setattr(calibration_service, "AUTO_WAIT_S", 60.0)  # (no machine load decides)
    frames = open_hand_frames(60, default_hand_model().scaled(shape))
    rig = Rig(ros_context, tmp_path, auto_calibrate=True)
    auto = rig.node._auto_calib

    def late_fit(args, kwargs):  # type: ignore[no-untyped-def]
        end = time.monotonic() + 60.0
        while rig.node._auto_waited_for != auto.started_ns and time.monotonic() < end:
            time.sleep(0.005)  # (ends only while the node waits on the due frame)
        poses = np.array(kwargs["poses"])
        return CalibrationResult(shape, args[3].scaled(shape), poses[0], 0.8, 0.83, 0.3, poses, (0, 1, 2))

    monkeypatch.setattr(rig.node, "_run_fit", late_fit)
    try:
        rig.send_info()
        k = 0
        while k < len(frames) and auto.taken_ns is None:
            rig.send(image_msg(frames[k], T0_NS + k * PERIOD_NS))
            # (each frame tracked before the next is sent: none dropped from the backlog, whatever
            # the machine's load)
            assert rig.spin_until(lambda n=k: rig.node.stats.processed > n, 60.0), f"frame {k} not answered"
            k += 1
        start = auto.started_ns
        assert start is not None and auto.taken_ns is not None, f"no switch after {k} frames"
        due = T0_NS + -(-(start + int(AUTO_APPLY_S * 1e9) - T0_NS) // PERIOD_NS) * PERIOD_NS
        assert auto.taken_ns == due
        assert len(rig.node.auto_fit_waits) == 1 and rig.node.auto_fit_waits[0][1]  # waited once, ended
        assert rig.node.hand_model.shape == shape
    finally:
        rig.close()


def test_no_automatic_fit_with_a_saved_user_model_or_when_switched_off(ros_context, tmp_path: Path) -> None:
    from hand_sog_tracker.core.model_io import save_hand_shape

    saved = HandShape(length=0.95, width=0.97, depth=1.0, sigma=1.0)
    save_hand_shape(tmp_path / "hand_model.yaml", saved, right=True)
    frames = open_hand_frames(20, default_hand_model().scaled(HandShape(length=1.12, width=1.1)))
    off = tmp_path / "off"
    off.mkdir()
    for where, params in ((tmp_path, {"auto_calibrate": True}), (off, {"auto_calibrate": False})):
        rig = Rig(ros_context, where, **params)
        try:
            before = rig.node.hand_model.shape
            rig.send_info()
            for k, depth in enumerate(frames):
                rig.send(image_msg(depth, T0_NS + k * PERIOD_NS))
            rig.spin_until(lambda: False, 0.5)
            assert rig.node._auto_calib.attempts == 0
            assert rig.node.hand_model.shape == before
        finally:
            rig.close()
    assert load_hand_shape(tmp_path / "hand_model.yaml")[0] == saved


def test_the_fit_worker_serves_fits_one_after_the_other_in_one_child_process() -> None:
    """The node's fits run in one child process that stays between fits (no start-up per fit);
    the child's exceptions reach the caller, start() does not wait for a fit under way (the
    tracking calls it), and a child that died is started again."""
    from hand_sog_tracker.core.types import TrackerConfig
    from hand_sog_tracker.errors import CalibrationError
    from hand_sog_tracker.synth.sequence import default_intrinsics, synthetic_sequence

    intr = default_intrinsics()
    truth = HandShape(length=1.1, width=1.05, depth=1.05, sigma=1.05)
    frames = [f.depth_mm for f in synthetic_sequence("abdadd", 3, intr, shape=truth, seed=2)]
    worker = calibration_service.FitWorker()
    try:
        worker.start()
        pid = worker._proc.pid
        res = worker.run((frames, intr, TrackerConfig(), default_hand_model(True)), {})
        assert res.shape.length == pytest.approx(1.1, rel=0.05)
        with pytest.raises(CalibrationError, match="no depth frames"):
            worker.run(([], intr, TrackerConfig(), default_hand_model(True)), {})
        again = worker.run((frames, intr, TrackerConfig(), default_hand_model(True)), {})
        assert again.shape == res.shape and worker._proc.pid == pid  # the same child served all three
        # A fit under way holds the child; start() (called by the tracking) must not wait for it.
        import threading

        job = ((frames, intr, TrackerConfig(), default_hand_model(True)), {})
        fitting = threading.Thread(target=worker.run, args=job)
        fitting.start()
        time.sleep(0.05)
        t0 = time.monotonic()
        worker.start()
        assert time.monotonic() - t0 < 0.02 and fitting.is_alive()
        fitting.join()
        worker._proc.kill()
        worker._proc.wait()
        third = worker.run((frames, intr, TrackerConfig(), default_hand_model(True)), {})
        assert third.shape == res.shape and worker._proc.pid != pid  # started again
        # close() during a fit ends the child at once; the fit fails.
        failed: list[BaseException] = []

        def fit() -> None:
            try:
                worker.run(*job)
            except RuntimeError as err:
                failed.append(err)

        fitting = threading.Thread(target=fit)
        fitting.start()
        time.sleep(0.05)
        proc = worker._proc
        t0 = time.monotonic()
        worker.close()
        assert time.monotonic() - t0 < 0.3
        fitting.join(timeout=5.0)
        assert len(failed) == 1 and not fitting.is_alive()
    finally:
        worker.close()
    assert proc.poll() is not None  # closed: the child has ended
