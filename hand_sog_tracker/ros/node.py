"""The ``hand_sog_tracker`` ROS 2 node: depth images in, hand pose out.

One job: the node's callbacks (input, tracking, publishing, diagnostics); kept together because
they share the node's state on one executor thread (``~/calibrate`` is in
:mod:`.calibration_service`).

Topics (relative names, so a namespace or remapping moves them):

========================================  =====================================================
``camera/depth/image_rect_raw`` (sub)     ``sensor_msgs/Image`` 16UC1/mono16 (mm) or 32FC1 (m)
``.../image_rect_raw/compressedDepth``    ``sensor_msgs/CompressedImage`` instead, with
  (sub)                                   ``input_transport: compressedDepth`` (png or rvl)
``camera/depth/camera_info`` (sub)        ``sensor_msgs/CameraInfo`` (K; binning honoured, ROI rejected)
``hand/joint_states``                     ``sensor_msgs/JointState``, 20 angles (rad) (+ 6 wrist joints)
``hand/pose``                             ``geometry_msgs/PoseStamped``, wrist pose (m)
``hand/keypoints``                        ``geometry_msgs/PoseArray``, 21 points, MediaPipe order (m)
``hand/confidence``                       ``sensor_msgs/JointState``, every processed frame: present,
                                          hand and finger confidences (see ``interface``)
``hand/robot_description``                ``std_msgs/String`` URDF of the current model (latched)
``/tf``                                   ``tf2_msgs/TFMessage`` with ``publish_tf: true``
``hand/fingertips``                       ``visualization_msgs/MarkerArray`` fingertips + skeleton
``hand/debug_image``                      ``sensor_msgs/Image`` bgr8, only while subscribed
                                          (or with ``debug_image: true``)
``/diagnostics``                          ``diagnostic_msgs/DiagnosticArray`` at 1 Hz
``~/calibrate`` (service)                 ``std_srvs/Trigger``: fit the hand model to the last frames
========================================  =====================================================

Every output is stamped with the input image's header (stamp and frame_id).

Real time: the subscriptions use sensor-data QoS with depth :data:`~.frame_input.INPUT_DEPTH` (overridable
via ``qos_overrides.*`` parameters).  The images are tracked in order, each with the core
tracker's whole search (the same answers as ``evaluate_bag``'s core mode; an image re-sent with
the stamp of the last one gets the same answer again): the images that arrive while a frame is
processed wait in a backlog (:class:`~.frame_input.Backlog`, at most the subscription's depth), which the node
catches up on one frame per executor turn, and the oldest are dropped whole only when the newest
image's stamp is more than ``max_lag_ms`` ahead of theirs (0: only the newest is tracked).  A
new track's search (~100 ms) is so caught up on, without a drop, at 30-60 Hz on a machine that
keeps up on average; a machine that cannot keep up runs up to ``max_lag_ms`` behind, dropping
whole frames, never part of a frame's search.  Each image is tracked with the CameraInfo of its
stamp, else with the newest one received before it.  Frames that are never processed are
counted: ``dropped`` (received, but left behind by more than ``max_lag_ms`` before they were
processed) and ``missed`` (replaced inside DDS, so never received; estimated from gaps in the
image stamps against the camera period, the running median of recent intervals,
:class:`~.frame_input.CameraRate`).
:func:`main` spins a single-threaded executor (see :func:`make_executor`).

Robustness: a bad frame (encoding, size, truncated data, no CameraInfo yet,
stamps going backwards, resolution change, any error from the core) is
skipped with a throttled warning naming the problem and counted as rejected;
the tracker state is reset only where the track cannot continue.  Every frame is bounded:
images above ``max_image_pixels`` are refused before anything of their size is allocated,
implausible CameraInfo is refused (:func:`~hand_sog_tracker.interface.camera_info_to_intrinsics`),
the core clips its search to the image and caps its data, BLAS runs on one thread
(:func:`~hand_sog_tracker.ros.blas.limit_blas_threads`), and a frame over ``frame_budget_ms``
is warned about and counted (``frames_cut``, ``worst_frame_ms`` in /diagnostics; its search is
never cut, issue 45).  After a frame that grew the process the free heap is given back
(:class:`~hand_sog_tracker.ros.heap.HeapTrim`); after a rejected image beyond
``max_image_pixels``, the image subscription is made anew, which gives back the buffer of its
size the middleware keeps (:meth:`TrackerNode._renew_image_subscription`).
An image without ``frame_id`` is tracked in :data:`DEFAULT_FRAME_ID` (with a warning); stamps
more than :data:`STAMP_SKEW_S` from the node's clock are warned about and left out of
``latency_ms``.
"""

from __future__ import annotations

import argparse
import copy
import math
import re
import sys
import threading
import time
import traceback
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from numpy.typing import NDArray
from rcl_interfaces.msg import SetParametersResult
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.context import Context
from rclpy.exceptions import InvalidParameterValueException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.logging import get_logger
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rclpy.qos_overriding_options import QoSOverridingOptions
from rclpy.subscription import Subscription
from rclpy.utilities import remove_ros_args
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Header
from std_srvs.srv import Trigger

from hand_sog_tracker.core.autocalibration import AutoCalibration, FrameHistory
from hand_sog_tracker.core.hand_model import HandModel, HandShape
from hand_sog_tracker.core.hands import HANDS, HandsResult, MultiHandTracker
from hand_sog_tracker.core.overlay import draw_overlay
from hand_sog_tracker.core.tracker import Tracker
from hand_sog_tracker.core.types import HandDecision, Intrinsics, TrackerStatus, TrackResult
from hand_sog_tracker.errors import (
    DepthImageError,
    HandSogError,
    IntrinsicsError,
)
from hand_sog_tracker.interface import (
    CALIBRATE_SERVICE,
    COMPRESSED_DEPTH_TOPIC,
    DEBUG_IMAGE_TOPIC,
    DEPTH_TOPIC,
    DIAGNOSTICS_TOPIC,
    INFO_TOPIC,
    NODE_NAME,
    TF_TOPIC,
    camera_info_to_intrinsics,
    compressed_image_to_depth_mm,
    image_to_depth_mm,
    stamp_to_ns,
)
from hand_sog_tracker.ros.blas import limit_blas_threads
from hand_sog_tracker.ros.calibration_service import CalibrationService, FitWorker
from hand_sog_tracker.ros.conversions import (
    bgr_to_image_msg,
    diagnostic_array,
)
from hand_sog_tracker.ros.frame_input import INPUT_DEPTH, Backlog, CameraRate
from hand_sog_tracker.ros.hand_topics import HandOutputs, HandTopics, TfPublish
from hand_sog_tracker.ros.heap import HeapTrim
from hand_sog_tracker.ros.params import (
    NodeSettings,
    declare_node_parameters,
    read_settings,
    validate_parameter_change,
)
from hand_sog_tracker.ros.saved_models import hand_models, one_hand_model

__all__ = ["TrackerNode", "NodeStats", "make_executor", "main", "NODE_NAME"]

# NODE_NAME and the topic names: hand_sog_tracker.interface (relative names).
IMAGE_TOPIC = DEPTH_TOPIC
#: Where image_transport's compressedDepth plugin publishes (``<image topic>/compressedDepth``).
COMPRESSED_TOPIC = COMPRESSED_DEPTH_TOPIC
#: Minimum seconds between two warnings of the same kind.
WARN_THROTTLE_S = 2.0
#: Where outputs of an image without ``header.frame_id`` are (the usual optical frame of a
#: depth camera driver).
DEFAULT_FRAME_ID = "camera_depth_optical_frame"
#: Image stamps further than this from the node's clock (s) are warned about and left out of the
#: latency in /diagnostics (a bag replayed without use_sim_time, unsynchronised clocks).
STAMP_SKEW_S = 30.0
#: Seconds a fingertip marker stays in RViz without a newer one (so a stopped node's hand goes).
MARKER_LIFETIME_S = 1.0
#: The one-hand topics' base name (the prefix of interface.JOINTS_TOPIC, POSE_TOPIC ...).
HAND_BASE = "hand"
#: ~/calibrate requests kept while the executor is busy with a frame (each is then answered at
#: once, "busy" during a fit): more calls arriving within one frame's processing are lost.
CALIBRATE_QUEUE = 100
_NUMBERS = re.compile(r"\d+(\.\d+)?")


@dataclass(frozen=True)
class NodeStats:
    """Counters of the node since start (a snapshot).

    Attributes
    ----------
    received : int
        Depth images received by the image callback.
    processed : int
        Frames the tracker ran on.
    dropped : int
        Received frames dropped from the backlog unprocessed (more than ``max_lag_ms`` behind
        the newest image, or beyond the backlog's size).
    missed : int
        Frames the camera sent that never reached the node (replaced inside DDS while a
        frame was processed), estimated from gaps in the image stamps.
    rejected : int
        Frames skipped because of bad input.
    cut : int
        Processed frames that took longer than ``frame_budget_ms`` (never cut: reported).
    last_problem : str
        Why the last frame was rejected ("" if none was).
    status : TrackerStatus
        Tracker status after the last processed frame.
    confidence : float
        Confidence of the last processed frame.
    """

    received: int = 0
    processed: int = 0
    dropped: int = 0
    missed: int = 0
    rejected: int = 0
    cut: int = 0
    last_problem: str = ""
    status: TrackerStatus = TrackerStatus.NO_HAND
    confidence: float = 0.0


@dataclass
class _Window:
    """What happened since the last diagnostics message (frame counts, summed ms, its start)."""

    received: int = 0
    processed: int = 0
    rejected: int = 0
    proc_ms: float = 0.0
    answer_ms: float = 0.0  # from the start of a frame's processing to its result published
    latency_ms: float = 0.0
    latency_frames: int = 0  # frames whose stamp is within STAMP_SKEW_S of the clock
    worst_ms: float = 0.0  # the longest processing of a frame
    backlog_ms: float = 0.0  # the oldest backlog met: newest received stamp - stamp processed
    start: float = field(default_factory=time.monotonic)


class TrackerNode(CalibrationService, Node):
    """Sum-of-Gaussians hand tracker node (see the module docstring).

    Parameters
    ----------
    **kwargs
        Passed to :class:`rclpy.node.Node` (``context``, ``parameter_overrides``,
        ``cli_args``, ``namespace`` ...).

    Raises
    ------
    InputError
        Invalid start-up parameters (message names the parameter).
    rclpy.exceptions.InvalidParameterValueException
        A start-up value is outside its declared range.
    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        try:
            self._settings: NodeSettings = declare_node_parameters(self)
        except BaseException:
            self.destroy_node()
            raise
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._on_parameters_set)

        # One executor thread runs every callback (see make_executor), so the node's state needs
        # no lock: the counters are a frozen NodeStats replaced whole, safe to read from any
        # thread.  _tracker_lock stays: ~/calibrate holds it for its snapshot of the history and
        # model and for the model switch, hand_model for reads from other threads (uncontended
        # under the single-threaded executor, so it costs nothing).
        self._tracker_lock = threading.Lock()
        # Signalled (with _tracker_lock held) when an automatic fit ends: a frame due to switch
        # to its model waits on it (calibration_service.py, _apply_auto_fit).
        self._auto_done = threading.Condition(self._tracker_lock)
        self.auto_fit_waits: list[tuple[float, bool]] = []
        self._heap = HeapTrim()  # free heap back to the system after a frame that grew the process
        # One BLAS thread: a product split over busy cores waits for the slowest (ros/blas.py).
        self._blas_threads = limit_blas_threads(1)
        self._warned_at: dict[str, float] = {}  # kind of warning -> time.monotonic() it was last logged
        self._stats = NodeStats()
        self._window = _Window()
        self._backlog = Backlog()
        self._rate = CameraRate()  # the camera period, from the received images' stamps
        self._intrinsics: Intrinsics | None = None  # of the newest CameraInfo
        # Tracking state; the tracker is also used by ~/calibrate (_tracker_lock).  With
        # max_hands 2 each hand's saved model (saved_models.py), the one-hand tracker that
        # of the hand labelled handedness.
        two = self._settings.max_hands > 1
        path, log = self._settings.user_model_path, self.get_logger()
        self._side_models: dict[str, HandModel | None] = hand_models(path, log) if two else {}
        right = self._settings.tracker.right_hand
        user_model = self._side_models[self._side] if two else one_hand_model(path, right, log)
        # The node runs the core tracker as evaluate_bag's core mode does: every frame's whole
        # search, nothing timed by the wall clock (issue 45).  A frame that arrives meanwhile
        # waits in the backlog; whole frames are dropped when it falls max_lag_ms behind.
        self._tracker = Tracker(self._settings.tracker, user_model)
        # (stamp, result, depth, intrinsics) of the last processed frame: an image
        # re-sent with its stamp is answered again, not tracked (nor checked) twice.
        self._last_answer: tuple[int, TrackResult, NDArray[np.float32], Intrinsics] | None = None
        self._last_stamp_ns: int | None = None
        self._last_shape: tuple[int, int] | None = None
        self._last_intr: Intrinsics | None = None  # of the last frame that passed the checks
        self._last_intr_shape: tuple[int, int] | None = None
        self._frame_id = ""
        # Recent tracked frames for ~/calibrate and the automatic fit (calibration_service.py),
        # which runs only without a saved user model.
        self._calib_history = FrameHistory()
        # max_hands 2: each hand's own history, its frames without the other hands' pixels.
        self._hand_histories = {s: FrameHistory() for s in HANDS}
        self._auto_calib = AutoCalibration(
            enabled=self._settings.auto_calibrate and user_model is None and self._settings.max_hands == 1
        )
        self._model_generation = 0

        # Every callback is in the node's default group except ~/calibrate: its coroutine holds
        # its callback group while it awaits the calibration worker thread, so it gets a group
        # of its own and tracking goes on in the default group meanwhile.  A reentrant group:
        # a call that comes during a fit is taken at once and answered "busy" (a mutually
        # exclusive one left such calls in the service's queue, beyond which they were lost).
        self._calib_group = ReentrantCallbackGroup()
        sensor_qos = copy.copy(qos_profile_sensor_data)
        sensor_qos.depth = INPUT_DEPTH
        out_qos = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
        overrides = QoSOverridingOptions.with_default_policies()

        compressed = self._settings.input_transport == "compressedDepth"
        self._image_sub = self.create_subscription(
            CompressedImage if compressed else Image,
            COMPRESSED_TOPIC if compressed else IMAGE_TOPIC,
            self._on_image_message,
            sensor_qos,
            qos_overriding_options=overrides,
        )
        # Bytes of the largest image processed so far: what the middleware's buffers hold for
        # the stream (_renew_image_subscription).
        self._largest_taken = 0
        self._oversized = 0  # bytes of the rejected image that calls for a new subscription
        self._renew_wake = self.create_guard_condition(self._renew_image_subscription)
        #: Times the image subscription was made anew.
        self.renewals = 0
        self._info_sub = self.create_subscription(
            CameraInfo,
            INFO_TOPIC,
            self._on_camera_info,
            sensor_qos,
            qos_overriding_options=overrides,
        )
        qos = self._image_sub.qos_profile
        self._backlog_size = max(qos.depth, 1) if qos.history == HistoryPolicy.KEEP_LAST else INPUT_DEPTH
        # Triggered while the backlog holds images: the executor's next turn tracks the next one
        # (other callbacks, ~/calibrate and /diagnostics, get their turns in between).
        self._backlog_wake = self.create_guard_condition(self._on_backlog)
        latched = QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
        )
        # The one-hand topics (hand/...): the hand decision of every processed frame (issue 46),
        # "no hand" included, and the pose of a reported hand.
        self._out = HandOutputs(
            self, HAND_BASE, out_qos, latched, overrides, frame_prefix=self._settings.frame_prefix,
            marker_lifetime_s=MARKER_LIFETIME_S,
        )
        self._models_logged: dict[str, HandShape] = {}  # (_log_model: by label, "" for one hand)
        self._tf_pub: Any = None  # created on first use (tf2_msgs is optional)
        self._debug_pub = self.create_publisher(
            Image, DEBUG_IMAGE_TOPIC, QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE)
        )
        self._diag_pub = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, 10)
        self._out.describe(self._tracker.model, None)
        # max_hands 2: every hand tracked by the multi-hand tracker and published on its own
        # topics (hand_topics.py); the one-hand topics carry the hand labelled ``handedness``.
        self._hands: MultiHandTracker | None = None
        self._hand_topics: HandTopics | None = None
        self._last_hands: HandsResult | None = None  # (max_hands 2: the last frame's, for the histories)
        if self._settings.max_hands > 1:
            self._hands = self._new_hands()
            self._hand_topics = HandTopics(
                self, self._settings.frame_prefix, out_qos, latched, overrides, MARKER_LIFETIME_S,
                models={s: self._hands.model(s) for s in HANDS},
            )

        self._calibrate_srv = self.create_service(
            Trigger,
            CALIBRATE_SERVICE,
            self._on_calibrate,
            callback_group=self._calib_group,
            qos_profile=QoSProfile(depth=CALIBRATE_QUEUE, reliability=ReliabilityPolicy.RELIABLE),
        )
        # Triggered by the calibration worker when it is done: wakes the executor, which then
        # resumes the waiting (async) service callback.
        self._calib_wake = self.create_guard_condition(lambda: None)
        self._fit_worker = FitWorker()  # the fits' child process, started with tracking
        self._diag_timer = self.create_timer(1.0, self._publish_diagnostics)
        self.get_logger().info(
            f"tracking the {self._side} hand from "
            f"{self._image_sub.topic_name} + {self._info_sub.topic_name}"
        )

    def destroy_node(self) -> None:
        """Destroy the node and end the fits' child process."""
        worker = getattr(self, "_fit_worker", None)  # (absent when __init__ failed early)
        if worker is not None:
            worker.close()
        super().destroy_node()

    # -- public -----------------------------------------------------------------
    @property
    def settings(self) -> NodeSettings:
        """The current (validated, frozen) parameter values."""
        return self._settings

    @property
    def stats(self) -> NodeStats:
        """A snapshot of the node's counters."""
        return self._stats

    @property
    def intrinsics(self) -> Intrinsics | None:
        """Intrinsics from the last usable CameraInfo (None before one arrived or after a bad one)."""
        return self._intrinsics

    @property
    def hand_model(self) -> HandModel:
        """The hand model the tracker uses (``max_hands: 2``: that of the hand labelled ``handedness``)."""
        with self._tracker_lock:
            return self._one_hand_model()

    @property
    def hand_models(self) -> dict[str, HandModel]:
        """The model of each hand label: with ``max_hands: 2`` ``{"left": ..., "right": ...}``
        (:meth:`~hand_sog_tracker.core.hands.MultiHandTracker.model`), with one hand the one-hand
        tracker's under its ``handedness``."""
        with self._tracker_lock:
            if self._hands is None:
                return {self._side: self._tracker.model}
            return {s: self._hands.model(s) for s in HANDS}

    @property
    def _side(self) -> str:
        """The label of the one-hand topics' hand: ``right`` or ``left`` (``handedness``)."""
        return "right" if self._settings.tracker.right_hand else "left"

    def _one_hand_model(self) -> HandModel:
        """The model of the one-hand topics' hand (the one-hand tracker's, or with max_hands 2
        that of the hand labelled ``handedness``)."""
        if self._hands is None:
            return self._tracker.model
        return self._hands.model(self._side)

    def _log_model(self, side: str, model: HandModel) -> None:
        """Log the shape of the model in use for the hand labelled ``side`` ("" with one hand) when
        it changed: a calibration, or a new track of a small hand on the default's small size."""
        if self._models_logged.get(side) != model.shape:
            self._models_logged[side] = model.shape
            self.get_logger().info(f"hand model in use{f' for the {side} hand' if side else ''}: {model.shape}")

    def _new_hands(self) -> MultiHandTracker:
        """The multi-hand tracker of max_hands 2, with each hand's model (saved or calibrated)."""
        hands = MultiHandTracker(self._settings.tracker, self._settings.max_hands)
        for side, model in self._side_models.items():
            if model is not None:
                hands.set_model(side, model)
        return hands

    # -- parameters -------------------------------------------------------------
    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        result = validate_parameter_change(self, params)
        if not result.successful:
            self.get_logger().warning(f"rejected parameter change: {result.reason}")
        return result

    def _on_parameters_set(self, params: list[Parameter]) -> None:
        # Validated in _on_set_parameters; the work group applies it on the next frame.
        self._settings = read_settings(self)

    # -- input ------------------------------------------------------------------
    def _on_image_message(self, msg: Image | CompressedImage) -> None:
        """The image subscription's callback: into the backlog, then track the oldest image
        unless the backlog's guard condition is due to (one frame per executor turn, so the
        other callbacks keep their turns).

        The CameraInfo messages waiting in their subscription are taken first (one may belong
        to this image), then the images waiting behind this one.
        """
        waiting = bool(self._backlog.images)  # (then the guard condition has been triggered)
        self._take_all(self._info_sub, self._on_camera_info)
        self._on_image(msg)
        self._take_all(self._image_sub, self._on_image)
        if not waiting:
            self._process_pending()

    def _on_backlog(self) -> None:
        """The backlog's guard condition: take what waits, track the oldest image."""
        self._take_all(self._info_sub, self._on_camera_info)
        self._take_all(self._image_sub, self._on_image)
        self._process_pending()

    def _on_image(self, msg: Image | CompressedImage) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        s = self._stats
        self._stats = replace(s, received=s.received + 1, missed=s.missed + self._rate.missed_before(stamp))
        self._window.received += 1
        self._backlog.images.append((msg, self._backlog.n_infos))
        self._trim_backlog()

    def _trim_backlog(self) -> None:
        """Drop (and count) the images more than ``max_lag_ms`` behind the newest one received."""
        newest = self._rate.last_stamp_ns
        if newest is None:
            return
        n = self._backlog.trim(newest, self._settings.max_lag_ms, self._backlog_size)
        if n:
            self._stats = replace(self._stats, dropped=self._stats.dropped + n)
            if self._settings.max_lag_ms > 0:
                self._warn(
                    f"{n} frames dropped: the node is more than max_lag_ms = {self._settings.max_lag_ms:g} ms "
                    "behind the camera"
                )

    def _on_camera_info(self, msg: CameraInfo) -> None:
        """Keep the intrinsics of a usable CameraInfo for the images of its stamp and after; an
        unusable one (its reason warned about) leaves none, so those images are rejected with
        that reason."""
        intr: Intrinsics | None = None
        problem = ""
        try:
            intr = camera_info_to_intrinsics(msg)
        except IntrinsicsError as err:
            problem = f"unusable CameraInfo: {err}"
            self._warn(f"unusable CameraInfo on {self._info_sub.topic_name}: {err}")
        except (TypeError, ValueError, OverflowError, AttributeError) as err:  # (fields of other types)
            problem = f"unusable CameraInfo: {err!r}"
            self._warn(f"unusable CameraInfo on {self._info_sub.topic_name}: {err!r}")
        try:
            stamp = stamp_to_ns(msg.header.stamp)
        except (TypeError, ValueError, OverflowError, AttributeError):
            stamp = -1  # (paired by arrival only)
        b = self._backlog
        b.n_infos += 1
        b.infos.append((b.n_infos, stamp, intr, problem))
        self._intrinsics = intr

    def _publish_diagnostics(self) -> None:
        now = time.monotonic()
        c, w = self._stats, self._window
        dt = max(now - w.start, 1e-3)
        n_proc = w.processed
        values = {  # keys: hand_sog_tracker.interface.DIAG_KEYS
            "input_rate_hz": w.received / dt,
            "output_rate_hz": n_proc / dt,
            "processing_ms": w.proc_ms / n_proc if n_proc else 0.0,
            "answer_ms": w.answer_ms / n_proc if n_proc else 0.0,
            # (NaN when no frame's stamp was within STAMP_SKEW_S of the clock)
            "latency_ms": w.latency_ms / w.latency_frames if w.latency_frames else (math.nan if n_proc else 0.0),
            "worst_frame_ms": w.worst_ms,
            "backlog_ms": w.backlog_ms,
            "status": c.status.value,
            "confidence": c.confidence,
            "frames_received": c.received,
            "frames_processed": c.processed,
            "frames_dropped": c.dropped,
            "frames_missed": c.missed,
            "frames_rejected": c.rejected,
            "frames_cut": c.cut,
            "last_problem": c.last_problem,
        }
        win_received, win_rejected, last_problem = w.received, w.rejected, c.last_problem
        self._window = _Window(start=now)
        if win_received == 0:
            level, message = DiagnosticStatus.WARN, "no depth images received"
        elif win_rejected:
            level, message = DiagnosticStatus.WARN, f"{win_rejected} frames rejected: {last_problem}"
        else:
            level, message = DiagnosticStatus.OK, f"{values['status']}"
        self._diag_pub.publish(
            diagnostic_array(
                self.get_clock().now().to_msg(),
                f"{NODE_NAME}: {self.get_fully_qualified_name()}",
                self._frame_id or self._image_sub.topic_name,  # hardware_id: the camera
                level,
                message,
                values,
            )
        )

    # -- tracking ---------------------------------------------------------------
    def _process_pending(self) -> None:
        """Track the oldest image of the backlog (after dropping those too far behind)."""
        backlog = self._backlog
        self._trim_backlog()
        if not backlog.images:
            return
        msg, seen = backlog.images.popleft()
        if backlog.images:
            self._backlog_wake.trigger()
        stamp = stamp_to_ns(msg.header.stamp)
        newest = self._rate.last_stamp_ns
        if newest is not None:
            self._window.backlog_ms = max(self._window.backlog_ms, (newest - stamp) * 1e-6)
        paired = backlog.intrinsics_for(stamp, seen)
        intr, intr_problem = paired if paired is not None else (None, "")
        t0 = time.perf_counter()
        try:
            with self._tracker_lock:
                answered_at = self._process(msg, intr, intr_problem)
            if answered_at is None and self._beyond_bounds(msg):
                self._oversized = len(msg.data)
                self._renew_wake.trigger()
            elif answered_at is not None:
                self._largest_taken = max(self._largest_taken, len(msg.data))
            if answered_at is not None:
                ms = (time.perf_counter() - t0) * 1e3
                self._window.proc_ms += ms
                self._window.answer_ms += (answered_at - t0) * 1e3
                self._window.worst_ms = max(self._window.worst_ms, ms)
                if ms > self._settings.frame_budget_ms:
                    # (Reported, never cut: a frame runs its whole search, issue 45; the images
                    # the camera sent meanwhile wait in the backlog, up to max_lag_ms.)
                    self._stats = replace(self._stats, cut=self._stats.cut + 1)
                    self._warn(
                        f"frame took {ms:.0f} ms, over its budget of {self._settings.frame_budget_ms:.0f} ms "
                        "(frame_budget_ms); the images that arrived meanwhile wait (max_lag_ms)"
                    )
        except Exception as err:  # noqa: BLE001 - a bug in one frame must not kill the node
            if not self.context.ok():
                return
            with self._tracker_lock:
                self._tracker.reset()
            tb = traceback.extract_tb(err.__traceback__)[-1]
            where = f"{Path(tb.filename).name}:{tb.lineno}"
            self._reject(f"internal error, tracker reset: {err!r} at {where}")
            self.get_logger().error(
                f"internal error while processing a frame (tracker reset): {err!r} at {where}",
                throttle_duration_sec=WARN_THROTTLE_S,
            )
            self.get_logger().debug(traceback.format_exc())
        finally:
            if self._heap.after_frame():
                self.get_logger().debug(f"gave free heap back to the system ({self._heap.trims} times)")

    def _beyond_bounds(self, msg: Image | CompressedImage) -> bool:
        """Whether a rejected image left the middleware a buffer larger than the node takes:
        larger than every image processed so far, and of more pixels than ``max_image_pixels``
        (a raw image's declared size) or more bytes than a 32FC1 image of that many pixels (4
        bytes a pixel, the widest encoding the node reads).  (A larger image within the bound,
        as after a resolution change, is not: the node may take the like of it next.)"""
        n = len(msg.data)
        if n <= self._largest_taken:
            return False
        limit = self._settings.max_image_pixels
        declared = msg.width * msg.height if isinstance(msg, Image) else 0
        return declared > limit or n > 4 * limit

    def _renew_image_subscription(self) -> None:
        """Make the image subscription anew after a rejected image beyond the node's bounds
        (:meth:`_beyond_bounds`), and give the freed memory back to the system.

        The middleware (rmw_fastrtps: history memory ``PREALLOCATED_WITH_REALLOC``) keeps each
        buffer of the subscription's history as large as the largest message it held, for the
        subscription's life: one 8 MB image left the node 7.6 MB larger for good, up to the
        history's depth of such buffers.  Destroying the subscription frees them (Fast DDS
        shares them among the subscriptions of one topic, so the old one goes first); images
        waiting in it are lost, and the new one receives once the publisher has matched it.
        """
        old = self._image_sub
        msg_type, qos = old.msg_type, old.qos_profile
        topic = COMPRESSED_TOPIC if msg_type is CompressedImage else IMAGE_TOPIC
        self.destroy_subscription(old)
        # (The QoS as resolved at start-up, overrides included: they are declared only once.)
        self._image_sub = self.create_subscription(msg_type, topic, self._on_image_message, qos)
        self._heap.trim()
        self.renewals += 1
        self._warn(
            f"an image of {self._oversized} bytes beyond max_image_pixels = {self._settings.max_image_pixels} "
            "was rejected: the image subscription was made anew to give back the middleware's buffer "
            "of its size (images waiting in it were lost)"
        )

    def _warn(self, text: str) -> None:
        """Per-frame warning, throttled per kind of problem (the text with its numbers masked):
        at most one of a kind every ``WARN_THROTTLE_S``, so different problems do not hide
        each other.

        The throttle is the node's own (a clock read and a dict look-up): rclpy's
        ``throttle_duration_sec`` inspects the caller's source frame on every call, about
        0.5 ms for a warning it then drops, which a replay without ``use_sim_time`` (a stamp
        warning on every frame) paid per frame.
        """
        kind = _NUMBERS.sub("#", text)
        now = time.monotonic()
        last = self._warned_at.get(kind)
        if last is not None and now - last < WARN_THROTTLE_S:
            return
        if len(self._warned_at) > 64:
            self._warned_at.clear()
        self._warned_at[kind] = now
        self.get_logger().warning(text)

    def _reject(self, problem: str) -> None:
        self._stats = replace(self._stats, rejected=self._stats.rejected + 1, last_problem=problem)
        self._window.rejected += 1

    def _process(self, msg: Image | CompressedImage, intr: Intrinsics | None, intr_problem: str) -> float | None:
        """Track one frame and publish: when its result was published (``time.perf_counter()``),
        or None when the frame was rejected."""
        header = msg.header
        settings = self._settings
        if settings.tracker != self._tracker.config:
            self._tracker.set_config(settings.tracker)
        if not header.frame_id:
            self._warn(f"image without header.frame_id: outputs are in '{DEFAULT_FRAME_ID}'")
            header = Header(stamp=header.stamp, frame_id=DEFAULT_FRAME_ID)

        stamp = stamp_to_ns(header.stamp)
        skew_s = (stamp - self.get_clock().now().nanoseconds) * 1e-9
        if abs(skew_s) > STAMP_SKEW_S:
            self._warn(
                f"image stamp is {abs(skew_s):.0f} s {'ahead of' if skew_s > 0 else 'behind'} the node's clock "
                "(unsynchronised clocks, or a bag replayed without use_sim_time?): tracked, left out of latency_ms"
            )
        if self._last_stamp_ns is not None and stamp < self._last_stamp_ns:
            back_s = (self._last_stamp_ns - stamp) * 1e-9
            self._last_stamp_ns = stamp
            self._reset_track(header)
            self._reject(f"stamp went backwards by {back_s:.3f} s")
            self._warn(
                f"image stamp went backwards by {back_s:.3f} s (bag loop or clock reset?): tracker reset, frame skipped"
            )
            return None
        self._last_stamp_ns = stamp

        if intr is None:
            problem = intr_problem or f"no CameraInfo received yet on {self._info_sub.topic_name}"
            self._reject(problem)
            self._warn(f"{problem}: frame skipped")
            return None

        try:
            if isinstance(msg, CompressedImage):
                depth = compressed_image_to_depth_mm(msg, settings.max_image_pixels)
            else:
                depth = image_to_depth_mm(msg, settings.max_image_pixels)
        except DepthImageError as err:
            self._reject(f"bad depth image: {err}")
            self._warn(f"bad depth image: {err}: frame skipped")
            return None

        shape = (int(depth.shape[0]), int(depth.shape[1]))
        if self._last_shape is not None and shape != self._last_shape:
            self._warn(
                f"depth resolution changed from {self._last_shape[1]}x{self._last_shape[0]} to "
                f"{shape[1]}x{shape[0]}: tracker reset"
            )
            self._reset_track(header)
            self._clear_histories()
        self._last_shape = shape
        if shape != (intr.height, intr.width):
            problem = (
                f"image is {shape[1]}x{shape[0]} but CameraInfo is {intr.width}x{intr.height}; "
                "waiting for a matching CameraInfo"
            )
            self._reject(problem)
            self._warn(f"{problem}: frame skipped")
            return None
        if self._last_intr is not None and intr != self._last_intr and shape == self._last_intr_shape:
            # A pose fitted with other intrinsics is wrong with these (a track carried over
            # from a K 2x off stayed 60 mm off): start anew, as on a resolution change.
            self._warn(f"CameraInfo changed ({self._last_intr} -> {intr}): tracker reset")
            self._reset_track(header)
            self._clear_histories()
        self._last_intr, self._last_intr_shape = intr, shape

        top = float(depth.max())
        if top <= 0.0:
            self._warn("depth image has no valid pixels (all 0, NaN or Inf)")
        else:
            unit_problem = self._unit_problem(msg, depth, top)
            if unit_problem:
                self._reject(unit_problem)
                self._warn(f"{unit_problem}: frame skipped")
                return None

        last = self._last_answer
        try:
            if last is not None and last[0] == stamp and last[3] == intr and np.array_equal(last[2], depth):
                result = last[1]  # (the same image again: the same answer, on every topic)
                if self._hand_topics is not None and self._last_hands is not None:
                    self._hand_topics.publish(
                        header, self._last_hands, depth, intr, self._settings.publish_wrist_joints, self._tf_publish()
                    )
            elif self._hands is not None:
                result = self._process_hands(header, depth, intr)
                self._last_answer = (stamp, result, depth, intr)
            else:
                # (the tracker's result carries the hand decision, issue 46: a tracked frame
                # that is no hand has no pose, and the track was reset when the gate says so)
                result = self._tracker.process(depth, intr)
                self._last_answer = (stamp, result, depth, intr)
        except HandSogError as err:
            self._reject(f"tracker rejected the frame: {err}")
            self._warn(f"tracker rejected the frame: {err}")
            return None

        decision = result.hand or HandDecision(result.pose is not None, float(result.confidence))
        self._frame_id = header.frame_id
        self._publish_result(header, result, depth, intr, decision)
        answered_at = time.perf_counter()
        tracked = result.pose if result.status is TrackerStatus.TRACKING else None
        if self._hands is not None:
            self._remember_hands(depth, intr, stamp)
        else:
            self._remember(depth, intr, tracked, stamp)
        latency_ms = (self.get_clock().now().nanoseconds - stamp) * 1e-6
        self._stats = replace(
            self._stats,
            processed=self._stats.processed + 1,
            status=result.status,
            confidence=float(decision.confidence),
        )
        self._window.processed += 1
        if abs(skew_s) <= STAMP_SKEW_S:
            self._window.latency_ms += latency_ms
            self._window.latency_frames += 1
        return answered_at

    def _unit_problem(self, msg: Image | CompressedImage, depth: NDArray[np.float32], top: float) -> str:
        """Why depth whose valid pixels all lie outside ``[near_mm, far_mm]`` looks like the wrong
        unit ("" if it does not): metres sent as 16UC1, or millimetres as 32FC1."""
        cfg = self._tracker.config
        encoding = msg.format if isinstance(msg, CompressedImage) else msg.encoding
        encoding = str(encoding).split(";")[0].strip().upper()
        if encoding in ("16UC1", "MONO16") and top < cfg.near_mm:
            return (
                f"every valid depth of this {encoding} image is at most {top:.0f} mm, nearer than near_mm = "
                f"{cfg.near_mm:g}: depth in metres sent as 16UC1 (which is mm)?"
            )
        if encoding == "32FC1" and top > max(cfg.far_mm, 1e5):  # (beyond 100 m: no depth camera's)
            nearest = float(depth[depth > 0.0].min())
            if nearest > max(cfg.far_mm, 1e5):
                return (
                    f"every valid depth of this 32FC1 image is at least {nearest / 1000:.0f} m: depth in "
                    "millimetres sent as 32FC1 (which is metres)?"
                )
        return ""

    def _take_all(self, sub: Subscription, callback: Callable[[Any], None]) -> None:
        """Hand the messages waiting in ``sub`` to ``callback``, oldest first (at most the
        backlog's size: a faster stream must not keep the executor here).

        The single-threaded executor runs one callback at a time, so the messages that arrived
        while a frame was processed are still in their subscription; the executor takes from it
        the same way and finds it empty afterwards.
        """
        for _ in range(self._backlog_size):
            try:
                with sub.handle:
                    taken = sub.handle.take_message(sub.msg_type, sub.raw)
            except Exception:  # noqa: BLE001 - a destroyed subscription (shutdown): nothing waits
                return
            if taken is None:
                return
            callback(taken[0])

    def _process_hands(self, header: Header, depth: NDArray[np.float32], intr: Intrinsics) -> TrackResult:
        """max_hands 2: track and publish every hand on its topics; the result (with its hand
        decision) for the one-hand topics is that of the hand labelled ``handedness`` (without it
        "no hand", with the confidence of its withheld track; each hand passed its own hand gate)."""
        assert self._hands is not None and self._hand_topics is not None
        if self._settings.tracker != self._hands.config:
            self._hands = self._new_hands()
        hands = self._hands.process(depth, intr)
        self._last_hands = hands
        decisions = self._hand_topics.publish(
            header, hands, depth, intr, self._settings.publish_wrist_joints, self._tf_publish()
        )
        for hand in hands.hands:
            if hand.handedness in decisions:
                self._log_model(hand.handedness, hand.model)
        side = self._side
        mine = hands.hand(side)
        if mine is None or side not in decisions:
            total = hands.timings_ms.get("total", 0.0)
            held = hands.withheld.get(side, HandDecision(False, 0.0))  # (as on /hand/<side>/confidence)
            return TrackResult(TrackerStatus.NO_HAND, None, None, None, 0.0, 0.0, 0, {"total": total}, hand=held)
        return replace(mine.result, hand=decisions[side])

    def _reset_track(self, header: Header) -> None:
        self._tracker.reset()
        if self._hands is not None:
            self._hands.reset()
        self._last_answer = None
        self._out.clear(header)

    def _publish_result(
        self,
        header: Header,
        result: TrackResult,
        depth: NDArray[np.float32],
        intr: Intrinsics,
        decision: HandDecision | None = None,
    ) -> None:
        model = self._one_hand_model()
        if self._hands is None and result.pose is not None:  # (max_hands 2: per hand, _process_hands)
            self._log_model("", model)
        self._out.publish(header, decision, result, model, self._settings.publish_wrist_joints, self._tf_publish())
        if self._settings.debug_image or self._debug_pub.get_subscription_count() > 0:
            cfg = self._tracker.config
            bgr = draw_overlay(
                depth,
                intr,
                model if result.pose is not None else None,
                result.pose,
                near_mm=cfg.near_mm,
                far_mm=cfg.far_mm,
                label=f"{result.status.value} conf {result.confidence:.2f}",
                result=result,
            )
            self._debug_pub.publish(bgr_to_image_msg(header, bgr))

    def _tf_publish(self) -> TfPublish | None:
        """What puts transforms on /tf with ``publish_tf`` (its publisher made on first use), else None."""
        return self._publish_transforms if self._settings.publish_tf else None

    def _publish_transforms(self, transforms: list) -> None:
        """Put ``transforms`` (TransformStamped) on /tf (publish_tf is validated: tf2_msgs exists)."""
        if self._tf_pub is None:
            from tf2_msgs.msg import TFMessage  # optional dependency, checked by the parameter

            self._tf_msg_type = TFMessage
            self._tf_pub = self.create_publisher(
                TFMessage, TF_TOPIC, QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
            )
        self._tf_pub.publish(self._tf_msg_type(transforms=transforms))


def make_executor(context: Context | None = None) -> SingleThreadedExecutor:
    """The executor :func:`main` uses: single-threaded.

    rclpy 7.1's ``MultiThreadedExecutor`` re-wakes itself thousands of times a second while
    callbacks run in its pool (end-to-end latency of seconds with this node), so the node runs
    single-threaded.  A ``~/calibrate`` call
    does not pause tracking: its callback is a coroutine awaiting a worker thread.
    """
    return SingleThreadedExecutor(context=context)


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``tracker_node``: only ``--help``; the node is configured by ROS parameters."""
    parser = argparse.ArgumentParser(
        prog="tracker_node",
        description="Sum-of-Gaussians hand tracker (ROS 2 node). Configure it with ROS "
        "parameters: --ros-args --params-file config/hand_sog_tracker.yaml, -p name:=value; "
        "remap topics with -r from:=to.",
        epilog="Subscribes camera/depth/image_rect_raw (or .../compressedDepth with "
        "-p input_transport:=compressedDepth) and camera/depth/camera_info; publishes "
        "hand/joint_states, hand/pose, hand/keypoints, hand/fingertips, hand/robot_description, "
        "hand/debug_image, /diagnostics (and /tf with -p publish_tf:=true); joint states, pose, keypoints, fingertips "
        "and the debug image only while something subscribes to them; "
        "service ~/calibrate (see calibrate_hand). Without a saved hand model it fits the model "
        "by itself once, half a second into tracking (-p auto_calibrate:=false turns that off).",
    )
    return parser


def _parse_cli(argv: Sequence[str]) -> None:
    build_parser().parse_args(list(argv))


def main(args: list[str] | None = None) -> None:
    """Run the node until Ctrl-C or an external shutdown.

    Parameters
    ----------
    args : list of str, optional
        Command line (default ``sys.argv``); ROS arguments after ``--ros-args``.
    """
    argv = sys.argv if args is None else args
    _parse_cli(remove_ros_args(args=argv)[1:])  # only --help; configuration is by parameters
    rclpy.init(args=argv)
    node: TrackerNode | None = None
    executor: SingleThreadedExecutor | None = None
    failed = False
    try:
        node = TrackerNode()
        executor = make_executor()
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (HandSogError, InvalidParameterValueException) as err:
        get_logger(NODE_NAME).error(f"cannot start: {err}")
        failed = True
    finally:
        if executor is not None:
            executor.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    if failed:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
