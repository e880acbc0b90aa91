"""The node's ``~/calibrate`` service: the recent-frame history and the fit on a worker thread.

:class:`CalibrationService` is a mixin of :class:`~hand_sog_tracker.ros.node.TrackerNode`: the
node creates the service, its callback group and the wake-up guard condition in its
``__init__`` and calls :meth:`CalibrationService._remember` after each tracked frame; the
service callback :meth:`CalibrationService._on_calibrate` lives here.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from rclpy.task import Future
from std_srvs.srv import Trigger

from hand_sog_tracker.core.calibration import CalibrationRejected, CalibrationResult, calibrate, select_frames
from hand_sog_tracker.core.model_io import calibration_metadata, save_hand_shape
from hand_sog_tracker.core.types import Intrinsics
from hand_sog_tracker.errors import CalibrationError, HandSogError

if TYPE_CHECKING:
    from rclpy.guard_condition import GuardCondition

    from hand_sog_tracker.core.tracker import Tracker
    from hand_sog_tracker.ros.params import NodeSettings

__all__ = ["CALIB_HISTORY", "CALIB_SPACING_S", "CALIB_HOLDOUT", "CalibFrame", "CalibrationService"]

#: Tracked frames kept for ~/calibrate (one at least CALIB_SPACING_S after the previous).
CALIB_HISTORY = 15
CALIB_SPACING_S = 0.06
#: Frames of the history held out of the fit to check it (the guard).
CALIB_HOLDOUT = 3


@dataclass(frozen=True, eq=False)
class CalibFrame:
    """A tracked frame kept for ~/calibrate."""

    depth: NDArray[np.float32]
    intrinsics: Intrinsics
    pose: NDArray[np.float64] | None
    stamp_ns: int


class CalibrationService:
    """Mixin of the node: ``~/calibrate`` (see :meth:`_on_calibrate`) and its frame history.

    Uses the node's ``_tracker`` and ``_tracker_lock``, ``_settings``, ``_calib_history``
    (a ``deque`` of at most :data:`CALIB_HISTORY` frames), ``_calib_wake`` (a guard condition)
    and ``get_logger``.
    """

    _tracker: Tracker
    _tracker_lock: threading.Lock
    _settings: NodeSettings
    _calib_history: deque[CalibFrame]
    _calib_wake: GuardCondition

    def _remember(
        self, depth: NDArray[np.float32], intr: Intrinsics, pose: NDArray[np.float64] | None, stamp: int
    ) -> None:
        """Keep a tracked frame for ~/calibrate (at most one per CALIB_SPACING_S)."""
        last = self._calib_history[-1] if self._calib_history else None
        if last is not None and 0 <= stamp - last.stamp_ns < CALIB_SPACING_S * 1e9:
            return
        self._calib_history.append(CalibFrame(depth, intr, None if pose is None else pose.copy(), stamp))

    async def _on_calibrate(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Fit the hand model to recent frames on a worker thread; tracking goes on meanwhile.

        The callback is a coroutine: it starts the fit on a thread and awaits its result, so
        the single-threaded executor keeps running the image callbacks in between (the
        worker triggers a guard condition when done, which wakes the executor).  The fit
        uses ``calibration_frames`` open-hand frames of the last second (the least spread
        ones) and is checked on up to CALIB_HOLDOUT other frames of it (the guard of
        :func:`~hand_sog_tracker.core.calibration.calibrate`); a refused fit changes and
        saves nothing.  Calls are served one at a time (own callback group).
        """
        with self._tracker_lock:  # a consistent snapshot of the history and the model
            history = list(self._calib_history)
            model = self._tracker.model
        settings = self._settings
        if not history:
            response.success = False
            response.message = (
                "no depth frames received yet: start the camera and hold an open hand in view"
            )
            self.get_logger().warning(f"calibration refused: {response.message}")
            return response
        intr = history[-1].intrinsics
        history = [h for h in history if h.intrinsics == intr]
        fit_idx, hold_idx = select_frames([h.pose for h in history], settings.calibration_frames, CALIB_HOLDOUT)
        if not fit_idx or not hold_idx:
            tracked = sum(h.pose is not None for h in history)
            response.success = False
            response.message = (
                f"calibration failed: {tracked} tracked frames in the last "
                f"{CALIB_HISTORY * CALIB_SPACING_S:.1f} s, {len(fit_idx)} with an open hand; need an open "
                "hand on at least one frame and one more frame to check the fit on (hold an open hand "
                "toward the camera for a second)"
            )
            self.get_logger().warning(response.message)
            return response
        fit = [history[i] for i in fit_idx]
        hold = [history[i] for i in hold_idx]
        self.get_logger().info(
            f"calibrating the hand model on {len(fit)} frames, checking it on {len(hold)} others "
            "(tracking goes on) ..."
        )
        future: Future = Future()

        def work() -> None:
            try:
                try:  # Linux: a nicer thread leaves the CPU to tracking when cores are busy
                    import os

                    os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 10)
                except (AttributeError, OSError):
                    pass
                future.set_result(
                    calibrate(
                        [h.depth for h in fit], intr, settings.tracker, model,
                        poses=[h.pose for h in fit],
                        holdout=[h.depth for h in hold], holdout_poses=[h.pose for h in hold],
                    )
                )
            except BaseException as err:  # noqa: BLE001 - handed to the service callback
                future.set_exception(err)
            finally:
                try:
                    self._calib_wake.trigger()
                except Exception:  # noqa: BLE001 - the node was destroyed meanwhile
                    pass

        threading.Thread(target=work, name="hand_sog_calibration", daemon=True).start()
        try:
            res: CalibrationResult = await future
        except CalibrationRejected as err:
            response.success = False
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
        s = res.shape
        v = res.validation
        assert v is not None
        try:
            path = save_hand_shape(
                settings.user_model_path,
                s,
                right=settings.tracker.right_hand,
                extra=calibration_metadata(
                    res,
                    fit_stamps_ns=[fit[i].stamp_ns for i in res.used_frames],
                    holdout_stamps_ns=[h.stamp_ns for h in hold],
                ),
            )
            saved = f"saved to {path}"
        except HandSogError as err:
            saved = f"NOT saved: {err}"
            self.get_logger().warning(f"calibrated model could not be saved: {err}")
        response.success = True
        response.message = (
            f"length={s.length:.3f} width={s.width:.3f} depth={s.depth:.3f} sigma={s.sigma:.3f}; "
            f"fit score {res.score_before:.4f} -> {res.score_after:.4f} "
            f"({len(res.used_frames)} frames, {res.seconds:.2f} s); {v.describe()}; {saved}"
        )
        self.get_logger().info(f"calibrated: {response.message}")
        return response
