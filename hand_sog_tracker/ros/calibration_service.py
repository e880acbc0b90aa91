"""The node's ``~/calibrate`` service and automatic calibration: the fit in a child process.

:class:`CalibrationService` is a mixin of :class:`~hand_sog_tracker.ros.node.TrackerNode`: the
node creates the service, its callback group and the wake-up guard condition in its
``__init__`` and calls :meth:`CalibrationService._remember` after each tracked frame, which
keeps the frame in the history (:class:`~hand_sog_tracker.core.autocalibration.FrameHistory`)
and starts an automatic fit when one is due
(:class:`~hand_sog_tracker.core.autocalibration.AutoCalibration`, parameter ``auto_calibrate``);
the service callback :meth:`CalibrationService._on_calibrate` lives here.
"""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, Callable

import numpy as np
from numpy.typing import NDArray
from rclpy.task import Future
from std_srvs.srv import Trigger

from hand_sog_tracker.core.autocalibration import (
    AUTO_WAIT_S,
    HISTORY_FRAMES,
    HISTORY_SPACING_S,
    AutoCalibration,
    FitFrames,
    FrameHistory,
    HistoryFrame,
    choose_fit_frames,
    why_not_used,
)
from hand_sog_tracker.core.calibration import (
    DEFAULT_HOLDOUT_FRAMES,
    CalibrationRejected,
    CalibrationResult,
    calibrate,
)
from hand_sog_tracker.core.hands import HANDS
from hand_sog_tracker.core.model_io import calibration_metadata, save_hand_shape, side_model_path
from hand_sog_tracker.core.types import Intrinsics, TrackerStatus
from hand_sog_tracker.errors import CalibrationError, HandSogError

if TYPE_CHECKING:
    from rclpy.guard_condition import GuardCondition

    from hand_sog_tracker.core.hand_model import HandModel
    from hand_sog_tracker.core.hands import HandsResult, MultiHandTracker
    from hand_sog_tracker.core.tracker import Tracker
    from hand_sog_tracker.ros.params import NodeSettings

__all__ = [
    "CALIB_HISTORY",
    "CALIB_SPACING_S",
    "CALIB_HOLDOUT",
    "FIT_IN_PROCESS",
    "CalibFrame",
    "CalibrationService",
    "FitWorker",
]

#: Tracked frames kept for ~/calibrate (one at least CALIB_SPACING_S after the previous).
CALIB_HISTORY = HISTORY_FRAMES
CALIB_SPACING_S = HISTORY_SPACING_S
#: Frames of the history held out of the fit to check it (the guard).
CALIB_HOLDOUT = DEFAULT_HOLDOUT_FRAMES
#: A tracked frame kept for ~/calibrate (the core's history frame).
CalibFrame = HistoryFrame


#: Run the fit in a child process (True) or on a thread of the node (False).  A thread shares
#: the GIL with tracking: at a lower OS priority it is descheduled while holding the GIL when
#: the cores are busy, and tracking waits for it.  Measured on 2 shared cores (load 6-10), 30 Hz
#: frames answered during a fit: thread 21% (test_ros_calibration.py) and 67-99% (node in its
#: own process); child process 87% and 70-100%; 100% without a fit (README).
FIT_IN_PROCESS = True
#: OS priority (nice) of the fit: tracking comes first when the cores are busy.
FIT_NICE = 10


def _lower_priority(tid: int = 0) -> None:
    """Lower the OS priority of thread ``tid`` (0: the calling process) by :data:`FIT_NICE` (Linux)."""
    try:
        import os

        os.setpriority(os.PRIO_PROCESS, tid, FIT_NICE)
    except (AttributeError, OSError):
        pass


class FitWorker:
    """A child Python process that runs :func:`~hand_sog_tracker.core.calibration.calibrate`,
    kept between fits.

    A plain ``python -c`` child (not ``multiprocessing``: that would fork the node's DDS
    threads, or re-import the node and rclpy in the child) that lowers its priority by
    :data:`FIT_NICE` and asks for Linux's idle scheduling class (it runs only on a core nothing
    else wants; fed at 100 Hz on 2 cores the node's latency p95 per bag was 9.4-12.9 ms in runs
    with an automatic fit, 8.2-11.3 ms without), imports only the NumPy core and then serves
    fits: pickled arguments in on its stdin, the pickled result or exception out on its stdout
    (:func:`~hand_sog_tracker.core.calibration.calibrate_pickled_stdio`).  :meth:`start` ahead
    of the first fit takes its start-up (0.2-0.6 s of imports) off the fit's time: the node
    starts it with the first tracked frame, half a second before the automatic fit is due.
    The exception raised in the child (e.g. :class:`CalibrationRejected`) is raised by
    :meth:`run`; a child that died is started again by the next fit.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._proc: subprocess.Popen | None = None
        self._stderr: IO[bytes] | None = None
        self.closed = False  # set by close(): the node is going

    def start(self) -> None:
        """Start the child unless it runs (cheap when it does); returns at once while a fit
        holds the child (the caller may be tracking: it must never wait for a fit)."""
        if not self._lock.acquire(blocking=False):
            return
        try:
            self._start()
        finally:
            self._lock.release()

    def _start(self) -> subprocess.Popen:
        if self._proc is not None and self._proc.poll() is None:
            return self._proc
        self._stop()
        import hand_sog_tracker

        root = os.path.dirname(os.path.dirname(os.path.abspath(hand_sog_tracker.__file__)))
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH", "")) if p)
        for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
            env.setdefault(var, "1")  # one core for the fit: the other is tracking's
        code = (
            f"import os; os.nice({int(FIT_NICE)})\n"
            "try:\n"
            "    os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))\n"
            "except (AttributeError, OSError):\n"
            "    pass\n"
            "from hand_sog_tracker.core.calibration import calibrate_pickled_stdio; calibrate_pickled_stdio()"
        )
        self._stderr = tempfile.TemporaryFile()  # (a pipe nobody reads could fill up and block it)
        self._proc = subprocess.Popen(
            [sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
            stderr=self._stderr, env=env,
        )
        return self._proc

    def run(self, args: tuple, kwargs: dict) -> CalibrationResult:
        """``calibrate(*args, **kwargs)`` in the child (one fit at a time)."""
        with self._lock:
            proc = self._start()
            assert proc.stdin is not None and proc.stdout is not None
            try:
                pickle.dump((args, kwargs), proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
                proc.stdin.flush()
                ok, value = pickle.load(proc.stdout)
            except (OSError, EOFError, pickle.UnpicklingError) as err:
                problem = self._stderr_tail() or repr(err)
                self._stop()
                raise RuntimeError(f"calibration process failed: {problem}") from err
        if not ok:
            raise value
        return value

    def _stderr_tail(self) -> str:
        if self._stderr is None:
            return ""
        self._stderr.seek(0)
        return " | ".join(self._stderr.read().decode(errors="replace").strip().splitlines()[-3:])

    def close(self) -> None:
        """End the child at once: a fit under way fails with RuntimeError (the node is going)."""
        self.closed = True
        proc = self._proc
        if proc is not None and proc.poll() is None:
            proc.kill()  # (the fit's run() then reads the end of the pipe and lets go of the lock)
        with self._lock:
            self._stop()

    def _stop(self) -> None:
        proc, self._proc = self._proc, None
        if proc is not None:
            for stream in (proc.stdin, proc.stdout):
                try:
                    if stream is not None:
                        stream.close()  # (its stdin at EOF: the child ends by itself)
                except OSError:
                    pass
            try:
                proc.wait(timeout=1.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        if self._stderr is not None:
            self._stderr.close()
            self._stderr = None


class CalibrationService:
    """Mixin of the node: ``~/calibrate`` (see :meth:`_on_calibrate`), the frame history and the
    automatic fit (see :meth:`_remember`).

    Uses the node's ``_tracker`` and ``_tracker_lock``, ``_settings``, ``_calib_history`` (a
    :class:`~hand_sog_tracker.core.autocalibration.FrameHistory`), ``_auto_calib`` (an
    :class:`~hand_sog_tracker.core.autocalibration.AutoCalibration`), ``_calib_wake`` (a guard
    condition) and ``get_logger``.  ``_model_generation`` counts the model switches made here: an
    automatic fit started before a ``~/calibrate`` that switched the model is dropped.
    """

    _tracker: Tracker
    _tracker_lock: threading.Lock
    _auto_done: threading.Condition  # on _tracker_lock: an automatic fit ended
    _settings: NodeSettings
    _calib_history: FrameHistory
    _hands: MultiHandTracker | None  # max_hands 2 (else None)
    _hand_histories: dict[str, FrameHistory]  # max_hands 2: each label's frames
    _side_models: dict[str, HandModel | None]  # max_hands 2: each label's model (None: default)
    _last_hands: HandsResult | None
    _auto_calib: AutoCalibration
    _calib_wake: GuardCondition
    _fit_worker: FitWorker
    _model_generation: int = 0
    _calibrating: bool = False  # a ~/calibrate call is being served (set on the instance)
    #: Each time a frame due to switch to an automatic fit's model waited for the fit: (seconds
    #: waited, whether the fit had ended by then).  For measurements and tests (set by the node).
    auto_fit_waits: list[tuple[float, bool]]
    _auto_waited_for: int | None = None  # started_ns of the fit last waited for (set on the instance)

    def _run_fit(self, args: tuple, kwargs: dict) -> CalibrationResult:
        """:func:`~hand_sog_tracker.core.calibration.calibrate` in the child process
        (:data:`FIT_IN_PROCESS`) or on this thread at a lower OS priority."""
        if FIT_IN_PROCESS:
            return self._fit_worker.run(args, kwargs)
        _lower_priority(threading.get_native_id())
        return calibrate(*args, **kwargs)

    def _remember(
        self, depth: NDArray[np.float32], intr: Intrinsics, pose: NDArray[np.float64] | None, stamp: int
    ) -> None:
        """Keep a tracked frame (at most one per CALIB_SPACING_S) and start an automatic fit when due.

        Called with ``_tracker_lock`` held (the node's frame processing holds it).
        """
        self._apply_auto_fit(stamp)
        if not self._calib_history.remember(depth, intr, pose, stamp):
            return
        auto = self._auto_calib
        auto.enabled = auto.enabled and self._settings.auto_calibrate
        idle = not (auto.accepted or auto.running) and auto.attempts < auto.max_attempts
        if FIT_IN_PROCESS and auto.enabled and idle:
            self._fit_worker.start()  # (its imports done before the fit is due; never waits)
        frames = auto.due(self._calib_history, stamp)
        if frames is None:
            return
        auto.started(stamp)
        self._start_auto_fit(frames, self._tracker.model, self._model_generation)

    def _remember_hands(self, depth: NDArray[np.float32], intr: Intrinsics, stamp: int) -> None:
        """max_hands 2: keep the frame in each label's history (:meth:`_remember` keeps the
        one-hand history), with that hand's pose (None while no reported hand has that label) and
        the other live tracks (model, pose), whose pixels the fit of this hand leaves out
        (:meth:`~hand_sog_tracker.core.autocalibration.HistoryFrame.hand_depth`).  Called with
        ``_tracker_lock`` held."""
        assert self._hands is not None
        hands = self._last_hands
        tracked = [] if hands is None else [h for h in hands.hands if h.result.status is TrackerStatus.TRACKING]
        reported = {h.handedness: h for h in tracked if h.result.pose is not None}
        live = self._hands.hands_in_view()
        for side in HANDS:
            hand = reported.get(side)
            others = [(m, x) for tid, m, x in live if hand is None or tid != hand.track_id]
            pose = None if hand is None else hand.result.pose
            self._hand_histories[side].remember(depth, intr, pose, stamp, others if pose is not None else ())

    def _clear_histories(self) -> None:
        """Forget the frames kept for calibration (a new resolution or camera)."""
        self._calib_history.clear()
        for history in self._hand_histories.values():
            history.clear()

    def _apply_auto_fit(self, stamp: int) -> None:
        """Switch to an accepted automatic fit's model once the frame stamped ``stamp`` is due
        (:meth:`~hand_sog_tracker.core.autocalibration.AutoCalibration.take`: by image stamps,
        so every run of a bag switches on the same frame).  Called with ``_tracker_lock`` held.

        A fit still running when its frame is due is waited for on that frame (once), up to
        :data:`~hand_sog_tracker.core.autocalibration.AUTO_WAIT_S` (the wait releases the lock,
        so the fit's thread can hand its result over; tracking waits meanwhile): the switch then
        lands on the same frame on every run whenever the fit ends within that time.
        """
        auto = self._auto_calib
        if auto.overdue(stamp) and self._auto_waited_for != auto.started_ns:
            self._auto_waited_for = auto.started_ns  # (once per fit: its due frame)
            t0 = time.perf_counter()
            ended = self._auto_done.wait_for(lambda: not auto.running, timeout=AUTO_WAIT_S)
            waited = time.perf_counter() - t0
            self.auto_fit_waits.append((waited, bool(ended)))
            if ended:
                self.get_logger().info(
                    f"automatic calibration: waited {waited * 1e3:.0f} ms for the fit on its due frame"
                )
            else:
                self.get_logger().warning(
                    f"automatic calibration: the fit has not ended {waited:.2f} s after its model was due "
                    "(a busy machine); it switches on the first frame after it ends"
                )
        pending = auto.take(stamp)
        if pending is None:
            return
        model, generation, fitted = pending  # type: ignore[misc]
        if generation == self._model_generation and self._auto_calib.enabled:
            self._tracker.set_model(model)
            self._model_generation += 1
            start = auto.started_ns or 0
            self.get_logger().info(
                f"automatic calibration in use from the frame after the one stamped {stamp * 1e-9:.3f} s "
                f"(fit started on {start * 1e-9:.3f} s; not saved, ~/calibrate saves): {fitted}"
            )
        else:
            self.get_logger().info("automatic calibration: dropped (the model was changed meanwhile)")

    def _start_auto_fit(self, frames: FitFrames, model: HandModel, generation: int) -> None:
        """Run an automatic fit on a worker thread; its model, if the guard accepts it, is
        switched to by :meth:`_apply_auto_fit`."""
        settings = self._settings
        args, kwargs = frames.calibrate_args(settings.tracker, model, automatic=True)
        attempt = self._auto_calib.attempts
        self.get_logger().info(
            f"automatic calibration (attempt {attempt}): fitting the hand model on {len(frames.fit)} "
            f"frames, checking it on {len(frames.holdout)} others (tracking goes on) ..."
        )

        def work() -> None:
            logger = self.get_logger()
            accepted = False
            pending: tuple | None = None
            try:
                res = self._run_fit(args, kwargs)
                s = res.shape
                fitted = (
                    f"{s.describe()}; "
                    f"{res.validation.describe() if res.validation else ''} ({res.seconds:.2f} s)"
                )
                accepted = True  # by the guard: no further attempts
                reason = why_not_used(s)
                if reason is not None:
                    logger.info(f"automatic calibration: {fitted}; not used: {reason}")
                    return
                pending = (res.model, generation, fitted)
            except CalibrationRejected as err:
                accepted = err.validation.already_fits  # (nothing to do: no further attempts)
                logger.info(f"automatic calibration refused, the model is unchanged: {err}")
            except HandSogError as err:
                logger.info(f"automatic calibration failed, the model is unchanged: {err}")
            except Exception as err:  # noqa: BLE001 - a bug in the fit must not kill the node
                if not self._fit_worker.closed:  # (closed: the node is going, the fit was ended)
                    logger.error(f"automatic calibration error: {err!r}")
            finally:
                with self._tracker_lock:
                    self._auto_calib.finished(accepted, pending)
                    self._auto_done.notify_all()

        threading.Thread(target=work, name="hand_sog_auto_calibration", daemon=True).start()

    async def _on_calibrate(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """The ``~/calibrate`` callback: :meth:`_calibrate`, one call at a time; a call that comes
        while one is served is answered at once, ``success: false``, ``"busy: ..."`` (the
        service's callback group is reentrant, so no call waits in a queue for the fit)."""
        if self._calibrating:
            response.success = False
            response.message = "busy: a calibration is running (call again when it has answered)"
            return response
        self._calibrating = True
        try:
            return await self._calibrate(request, response)
        finally:
            self._calibrating = False

    async def _calibrate(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Fit the hand model to recent frames in a child process; tracking goes on meanwhile.

        The callback is a coroutine: it starts a worker thread, which runs the fit in a child
        process at a lower OS priority (:data:`FIT_IN_PROCESS`; the thread only waits, so it
        does not hold the GIL) and awaits its result, so the single-threaded executor keeps
        running the image callbacks in between (the worker triggers a guard condition when
        done, which wakes the executor).  The fit
        uses ``calibration_frames`` open-hand frames of the last second (the least spread
        ones) and is checked on up to CALIB_HOLDOUT other frames of it (the guard of
        :func:`~hand_sog_tracker.core.calibration.calibrate`); a refused fit changes and
        saves nothing.  A fit that is saved ends the automatic fits.  Calls are served one at
        a time (:meth:`_on_calibrate`).  With ``max_hands: 2``: :meth:`_calibrate_hands`.
        """
        if self._hands is not None:
            return await self._calibrate_hands(response)
        with self._tracker_lock:  # a consistent snapshot of the history and the model
            history = self._calib_history.frames()
            model = self._tracker.model
        settings = self._settings
        if not history:
            response.success = False
            response.message = (
                "no depth frames received yet: start the camera and hold an open hand in view"
            )
            self.get_logger().warning(f"calibration refused: {response.message}")
            return response
        frames = choose_fit_frames(history, settings.calibration_frames, CALIB_HOLDOUT)
        if frames is None or not frames.usable:
            tracked = 0 if frames is None else frames.tracked
            n_open = 0 if frames is None else len(frames.fit)
            response.success = False
            response.message = (
                f"calibration failed: {tracked} tracked frames in the last "
                f"{CALIB_HISTORY * CALIB_SPACING_S:.1f} s, {n_open} with an open hand; need an open "
                "hand on at least one frame and one more frame to check the fit on (hold an open hand "
                "toward the camera for a second)"
            )
            self.get_logger().warning(response.message)
            return response
        fit, hold = frames.fit, frames.holdout
        self.get_logger().info(
            f"calibrating the hand model on {len(fit)} frames, checking it on {len(hold)} others "
            "(tracking goes on) ..."
        )
        args, kwargs = frames.calibrate_args(settings.tracker, model)
        future = self._in_fit_thread(lambda: self._run_fit(args, kwargs))
        try:
            res: CalibrationResult = await future
        except CalibrationRejected as err:
            response.success = False
            if err.validation.already_fits:
                response.message = f"{err}; nothing changed or saved"
                self.get_logger().info(response.message)
            else:
                response.message = f"calibration rejected, nothing changed or saved: {err}"
                self.get_logger().warning(response.message)
            return response
        except HandSogError as err:
            kind = "calibration failed" if isinstance(err, CalibrationError) else "calibration error"
            response.success = False
            response.message = f"{kind}: {err}"
            self.get_logger().warning(response.message)
            return response
        except Exception as err:  # noqa: BLE001 - a bug in the fit must not kill the node
            response.success = False
            response.message = f"calibration error: {err!r}"
            self.get_logger().error(response.message)
            return response
        with self._tracker_lock:  # atomic switch between two frames
            self._tracker.set_model(res.model)
            self._model_generation += 1
            self._auto_calib.stop()
        response.success = True
        response.message = self._save_fit(res, frames, settings.user_model_path, settings.tracker.right_hand)
        self.get_logger().info(f"calibrated: {response.message}")
        return response

    async def _calibrate_hands(self, response: Trigger.Response) -> Trigger.Response:
        """``~/calibrate`` with ``max_hands: 2``: each hand with frames in its own history
        (:meth:`_remember_hands`: its tracked poses, the other hands' pixels left out) is fitted
        on them and checked by the same guard as one hand, one after the other in the child
        process; an accepted fit is switched to (:meth:`MultiHandTracker.set_model`) and saved to
        that hand's file (:func:`~hand_sog_tracker.core.model_io.side_model_path`).  The answer
        has one part per hand (``left hand: ... | right hand: ...``); ``success`` when at least
        one hand's fit was accepted."""
        assert self._hands is not None
        with self._tracker_lock:  # a consistent snapshot of the histories and the models
            histories = {side: self._hand_histories[side].frames() for side in HANDS}
            models = {side: self._hands.model(side) for side in HANDS}
        settings = self._settings
        if not any(histories.values()):
            response.success = False
            response.message = "no depth frames received yet: start the camera and hold an open hand in view"
            self.get_logger().warning(f"calibration refused: {response.message}")
            return response
        chosen: dict[str, FitFrames] = {}
        parts: dict[str, str] = {}
        for side in HANDS:
            frames = choose_fit_frames(histories[side], settings.calibration_frames, CALIB_HOLDOUT)
            tracked = 0 if frames is None else frames.tracked
            if frames is None or tracked == 0:
                parts[side] = f"not tracked in the last {CALIB_HISTORY * CALIB_SPACING_S:.1f} s, not fitted"
            elif not frames.usable:
                parts[side] = (
                    f"calibration failed: {tracked} tracked frames in the last "
                    f"{CALIB_HISTORY * CALIB_SPACING_S:.1f} s, {len(frames.fit)} with an open hand; need an open "
                    "hand on at least one frame and one more frame to check the fit on"
                )
            else:
                chosen[side] = frames
        if not chosen:
            response.success = False
            response.message = _by_hand(parts) + " (hold an open hand toward the camera for a second)"
            self.get_logger().warning(f"calibration failed: {response.message}")
            return response
        self.get_logger().info(
            "calibrating the hand models: "
            + ", ".join(f"{side} on {len(f.fit)} frames, checked on {len(f.holdout)}" for side, f in chosen.items())
            + " (tracking goes on) ..."
        )
        configs = {side: replace(settings.tracker, right_hand=side == "right") for side in chosen}

        def fit_each() -> dict[str, CalibrationResult | BaseException]:
            out: dict[str, CalibrationResult | BaseException] = {}
            for side, frames in chosen.items():
                try:  # (the other hands' pixels masked here, off the executor's thread)
                    args, kwargs = frames.calibrate_args(configs[side], models[side])
                    out[side] = self._run_fit(args, kwargs)
                except Exception as err:  # noqa: BLE001 - answered per hand
                    out[side] = err
            return out

        future = self._in_fit_thread(fit_each)
        try:
            results: dict[str, CalibrationResult | BaseException] = await future
        except Exception as err:  # noqa: BLE001 - a bug in the fit must not kill the node
            response.success = False
            response.message = f"calibration error: {err!r}"
            self.get_logger().error(response.message)
            return response
        accepted = []
        for side, res in results.items():
            if isinstance(res, CalibrationRejected):
                if res.validation.already_fits:
                    parts[side] = f"{res}; nothing changed or saved"
                else:
                    parts[side] = f"calibration rejected, nothing changed or saved: {res}"
            elif isinstance(res, HandSogError):
                kind = "calibration failed" if isinstance(res, CalibrationError) else "calibration error"
                parts[side] = f"{kind}: {res}"
            elif isinstance(res, BaseException):
                parts[side] = f"calibration error: {res!r}"
                self.get_logger().error(f"calibration of the {side} hand: {res!r}")
            else:
                with self._tracker_lock:  # atomic switch between two frames
                    self._hands.set_model(side, res.model)
                    self._side_models[side] = res.model
                    self._model_generation += 1
                    self._auto_calib.stop()
                path = side_model_path(settings.user_model_path, side)
                parts[side] = self._save_fit(res, chosen[side], path, side == "right", f"the {side} hand's ")
                accepted.append(side)
        response.success = bool(accepted)
        response.message = _by_hand(parts)
        if accepted:
            self.get_logger().info(f"calibrated: {response.message}")
        else:
            self.get_logger().warning(f"calibration: nothing changed or saved: {response.message}")
        return response

    def _in_fit_thread(self, fit: Callable[[], Any]) -> Future:
        """Run ``fit`` (which waits for the child process) in a thread of its own; the future of
        its result, done in the executor through the wake-up guard condition."""
        future: Future = Future()

        def work() -> None:
            try:
                future.set_result(fit())
            except BaseException as err:  # noqa: BLE001 - handed to the service callback
                future.set_exception(err)
            finally:
                try:
                    self._calib_wake.trigger()
                except Exception:  # noqa: BLE001 - the node was destroyed meanwhile
                    pass

        threading.Thread(target=work, name="hand_sog_calibration", daemon=True).start()
        return future

    def _save_fit(self, res: CalibrationResult, frames: FitFrames, path: Path, right: bool, whose: str = "") -> str:
        """Save an accepted fit (of a right hand, or not) on ``frames`` to ``path`` with its
        metadata; the answer's text (the numbers, where it was saved).  ``whose``: what the warning
        of a failed save says before "calibrated model" (``"the left hand's "``)."""
        s, v = res.shape, res.validation
        assert v is not None
        try:
            where = save_hand_shape(
                path,
                s,
                right=right,
                extra={
                    **calibration_metadata(
                        res,
                        fit_stamps_ns=[frames.fit[i].stamp_ns for i in res.used_frames],
                        holdout_stamps_ns=[h.stamp_ns for h in frames.holdout],
                    ),
                    **v.metadata(),
                },
            )
            saved = f"saved to {where}"
        except HandSogError as err:
            saved = f"NOT saved: {err}"
            self.get_logger().warning(f"{whose}calibrated model could not be saved: {err}")
        return (
            f"{s.describe()}; fit score {res.score_before:.4f} -> {res.score_after:.4f} "
            f"({len(res.used_frames)} frames, {res.seconds:.2f} s); {v.describe()}; {saved}"
        )


def _by_hand(parts: dict[str, str]) -> str:
    """``left hand: ... | right hand: ...`` (the hands in :data:`HANDS` order)."""
    return " | ".join(f"{side} hand: {parts[side]}" for side in HANDS if side in parts)
