"""``evaluate_bag``: score the hand tracker on a bag with fingertip ground truth.

Usage::

    evaluate_bag BAG [--depth-topic T] [--info-topic T] [--gt-topic T]
                     [--json OUT] [--plot OUT.png] [--calibrate] [--max-frames N]
                     [--quiet] [--through-node [--domain-id N] [--rate R]
                                               [--node-timeout S] [--no-warmup]]

The bag follows contract 5 (see :mod:`hand_sog_tracker.tools.bagio`):
depth images, CameraInfo and ground-truth fingertips (PoseArray, metres,
same stamp as the depth image).

Default mode
    Runs the core :class:`~hand_sog_tracker.core.tracker.Tracker` directly
    on every depth image, as fast as it can, deterministically.  ``ms per
    frame`` is the wall time of :meth:`Tracker.process`.
``--calibrate``
    Fits the hand model on the first (up to three) usable frames with
    :func:`~hand_sog_tracker.core.calibration.calibrate`, then tracks the
    whole bag from its start with the fitted model.
``--through-node``
    Starts the ROS node (``python -m hand_sog_tracker.ros.node``, i.e.
    :class:`~hand_sog_tracker.ros.node.TrackerNode` with its own executor) as
    a child process, publishes the bag's depth images and CameraInfo to it
    over loopback DDS at the recorded rate (times ``--rate``), and scores the
    fingertip markers it publishes on ``/hand/fingertips`` (matched to
    ground truth by header stamp).  Also reports the end-to-end latency
    (publication of the image to reception of the markers) and the frames
    the node dropped (from its ``/diagnostics`` counters).  DDS is forced to
    the package's loopback profile and ``--domain-id`` (default 91).  The
    node first detects the hand on the first image alone (``--no-warmup``
    to include that slow first detection in the measurement).

Scoring (see :mod:`hand_sog_tracker.tools.metrics`): frames without ground
truth are tracked but not scored (counted); scored frames where the tracker
gave no fingertips are left out of the mean errors and count as failures in
the "% of frames below" table.

Exit status: 0 on success, 2 on a usage error or any
:class:`~hand_sog_tracker.errors.HandSogError` (``error: ...`` on stderr).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import importlib.resources
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, Protocol, Sequence, TextIO

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.hand_model import HandModel
from hand_sog_tracker.core.types import Intrinsics, TrackerConfig, TrackerStatus, TrackResult
from hand_sog_tracker.errors import BagError, CalibrationError, HandSogError, InputError
from hand_sog_tracker.tools.bagio import (
    BagFrame,
    BagTopics,
    DepthBagReader,
    deserialize,
    iter_messages,
    stamp_to_ns,
)
from hand_sog_tracker.tools.metrics import (
    FINGERS,
    THRESHOLDS_MM,
    ErrorSummary,
    TimingSummary,
    fingertip_errors_mm,
    pct_frames_below,
    summarize_errors,
    summarize_timings,
)

__all__ = [
    "FrameRecord",
    "Evaluation",
    "TrackerLike",
    "Progress",
    "evaluate_core",
    "evaluate_through_node",
    "loopback_dds",
    "build_evaluation",
    "format_table",
    "write_plot",
    "main",
]

#: Frames used by ``--calibrate`` (the calibration uses at most three).
CALIBRATION_FRAMES = 3
#: Status of a frame whose image could not be used (bad encoding, size mismatch).
STATUS_ERROR = "error"
#: Status of a frame the node published nothing for (``--through-node``: dropped or no hand).
STATUS_NO_OUTPUT = "no_output"
#: Status of a frame the node answered without fingertips (``--through-node``: DELETEALL markers).
STATUS_NO_ESTIMATE = "no_estimate"


class TrackerLike(Protocol):
    """What :func:`evaluate_core` needs of a tracker (the core Tracker fits)."""

    def process(self, depth_mm: NDArray, intrinsics: Intrinsics) -> TrackResult: ...


@dataclass(frozen=True, eq=False)
class FrameRecord:
    """Outcome of one depth image.

    Attributes
    ----------
    index : int
        Position among the bag's depth images.
    stamp_ns : int
        Header stamp of the depth image.
    status : str
        Core mode: ``tracking``, ``lost``, ``no_hand`` or ``error`` (unusable
        image).  Node mode: ``tracking``, ``no_estimate`` (markers deleted)
        or ``no_output`` (dropped, or no hand).
    estimate_mm : array, shape (5, 3) or None
        Tracked fingertips, mm.
    truth_mm : array, shape (5, 3) or None
        Ground-truth fingertips, mm.
    ms : float
        Processing time (core mode) or end-to-end latency (node mode), ms;
        NaN when not measured.
    """

    index: int
    stamp_ns: int
    status: str
    estimate_mm: NDArray[np.float64] | None
    truth_mm: NDArray[np.float64] | None
    ms: float

    @property
    def errors_mm(self) -> NDArray[np.float64] | None:
        """Per-finger error (5,) mm; NaN if no estimate; None without ground truth."""
        if self.truth_mm is None:
            return None
        if self.estimate_mm is None:
            return np.full(5, np.nan)
        return fingertip_errors_mm(self.estimate_mm, self.truth_mm)


@dataclass(frozen=True, eq=False)
class Evaluation:
    """Result of evaluating one bag (see :meth:`to_json`)."""

    bag: str
    mode: str
    records: tuple[FrameRecord, ...]
    errors: ErrorSummary
    timing: TimingSummary
    wall_s: float
    image_size: tuple[int, int] | None
    calibration: dict[str, Any] | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def frames(self) -> int:
        """Depth images evaluated."""
        return len(self.records)

    @property
    def frames_without_truth(self) -> int:
        """Depth images without ground truth (tracked, not scored)."""
        return sum(r.truth_mm is None for r in self.records)

    @property
    def status_counts(self) -> dict[str, int]:
        """Frames per status."""
        return dict(sorted(Counter(r.status for r in self.records).items()))

    @property
    def fps(self) -> float:
        """Frames per second of tracking (core: 1000 / mean ms; node: output rate)."""
        if "fps" in self.extra:
            return float(self.extra["fps"])
        return 1000.0 / self.timing.mean_ms if self.timing.count and self.timing.mean_ms > 0 else math.nan

    def frame_errors_mm(self) -> NDArray[np.float64]:
        """Mean fingertip error of each scored frame, shape (N,), mm (NaN = no estimate)."""
        rows = [e for e in (r.errors_mm for r in self.records) if e is not None]
        return np.array([float(np.mean(e)) for e in rows], dtype=np.float64)

    def to_json(self) -> dict[str, Any]:
        """JSON-ready dict (NaN written as null)."""
        e = self.errors
        out: dict[str, Any] = {
            "bag": self.bag,
            "mode": self.mode,
            "frames": self.frames,
            "frames_scored": e.frames_scored,
            "frames_without_ground_truth": self.frames_without_truth,
            "frames_with_estimate": e.frames_with_estimate,
            "mean_fingertip_error_mm": e.mean_mm,
            "per_finger_mm": dict(e.per_finger_mm),
            "pct_frames_below_mm": dict(e.pct_below_mm),
            "ms_per_frame": {
                "median": self.timing.median_ms,
                "p95": self.timing.p95_ms,
                "mean": self.timing.mean_ms,
            },
            "fps": self.fps,
            "status_counts": self.status_counts,
            "wall_time_s": self.wall_s,
            "image_size": list(self.image_size) if self.image_size else None,
            "calibration": self.calibration,
            **self.extra,
            "per_frame": [
                {
                    "index": r.index,
                    "stamp_ns": r.stamp_ns,
                    "status": r.status,
                    "error_mm": None if r.errors_mm is None else float(np.mean(r.errors_mm)),
                    "ms": r.ms,
                }
                for r in self.records
            ],
        }
        return _json_clean(out)


def _json_clean(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _json_clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_clean(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


class Progress:
    """A one-line progress bar on a terminal (disabled when not a tty).

    Parameters
    ----------
    total : int
        Expected number of steps (0 = unknown).
    stream : text stream
        Where to draw; default ``sys.stderr``.
    enabled : bool, optional
        Default: ``stream.isatty()``.
    """

    def __init__(self, total: int, stream: TextIO | None = None, enabled: bool | None = None) -> None:
        self.total = max(int(total), 0)
        self.stream = stream if stream is not None else sys.stderr
        if enabled is None:
            isatty = getattr(self.stream, "isatty", None)
            enabled = bool(isatty and isatty())
        self.enabled = enabled
        self.count = 0
        self._last = 0.0

    def update(self, n: int = 1, note: str = "") -> None:
        """Advance by ``n`` and redraw (at most ~20 times a second)."""
        self.count += n
        if not self.enabled:
            return
        now = time.monotonic()
        if now - self._last < 0.05 and self.count < self.total:
            return
        self._last = now
        width = 30
        if self.total:
            done = min(self.count / self.total, 1.0)
            bar = "#" * int(round(done * width))
            text = f"\r[{bar:<{width}}] {self.count}/{self.total} {note}"
        else:
            text = f"\r{self.count} frames {note}"
        self.stream.write(text[:120].ljust(80))
        self.stream.flush()

    def close(self) -> None:
        """Finish the line."""
        if self.enabled:
            self.stream.write("\n")
            self.stream.flush()


def _status_name(status: TrackerStatus) -> str:
    return status.value


def _calibrate_model(
    frames: Sequence[BagFrame], config: TrackerConfig, model: HandModel
) -> tuple[HandModel, dict[str, Any]]:
    """Fit the hand model on ``frames`` (usable ones, same intrinsics)."""
    from hand_sog_tracker.core.calibration import calibrate

    usable = [f for f in frames if f.depth_mm is not None and f.intrinsics is not None]
    if not usable:
        raise CalibrationError("no usable depth frame at the start of the bag to calibrate on")
    intr = usable[0].intrinsics
    assert intr is not None
    same = [f.depth_mm for f in usable if f.intrinsics == intr and f.depth_mm is not None]
    res = calibrate(same, intr, config, model)
    info = {
        "frames": len(same),
        "shape": {k: float(v) for k, v in dataclasses.asdict(res.shape).items()},
        "energy_before": res.energy_before,
        "energy_after": res.energy_after,
        "seconds": res.seconds,
    }
    return res.model, info


def evaluate_core(
    bag: str | Path,
    topics: BagTopics = BagTopics(),
    calibrate: bool = False,
    config: TrackerConfig | None = None,
    tracker: TrackerLike | None = None,
    max_frames: int | None = None,
    progress: bool | None = None,
) -> Evaluation:
    """Track every depth image of ``bag`` with the core tracker and score it.

    Parameters
    ----------
    bag : str or Path
        Bag path (see :func:`bagio.resolve_bag_path`).
    topics : BagTopics
    calibrate : bool
        Fit the hand model on the first usable frames first (core tracker only).
    config : TrackerConfig, optional
        Tracker configuration (default: ``TrackerConfig()``).
    tracker : TrackerLike, optional
        Use this object instead of a new core Tracker (tests, other trackers).
    max_frames : int, optional
        Stop after this many depth images.
    progress : bool, optional
        Draw a progress bar on stderr; default: only if stderr is a terminal.

    Returns
    -------
    Evaluation

    Raises
    ------
    BagError
        Bag unreadable, topic missing, no CameraInfo, no ground truth, no
        depth image usable.
    CalibrationError
        ``calibrate`` and the fit failed.
    """
    cfg = config or TrackerConfig()
    calib_info: dict[str, Any] | None = None
    if tracker is None:
        from hand_sog_tracker.core.tracker import Tracker

        tracker = Tracker(cfg)
    elif calibrate and not hasattr(tracker, "set_model"):
        raise InputError("calibrate=True needs a tracker with set_model()")
    records: list[FrameRecord] = []
    first_error: str | None = None
    image_size: tuple[int, int] | None = None
    t_start = time.perf_counter()
    with DepthBagReader(bag, topics, require_truth=True) as reader:
        total = reader.n_depth if max_frames is None else min(reader.n_depth, max_frames)
        bar = Progress(total, enabled=progress if progress is not None else None)
        frames: Iterable[BagFrame] = reader.frames()
        if calibrate:
            head: list[BagFrame] = []
            it = iter(frames)
            for f in it:
                head.append(f)
                if sum(h.depth_mm is not None for h in head) >= CALIBRATION_FRAMES:
                    break
            model, calib_info = _calibrate_model(head, cfg, tracker.model)  # type: ignore[attr-defined]
            tracker.set_model(model)  # type: ignore[attr-defined]
            if hasattr(tracker, "reset"):
                tracker.reset()  # type: ignore[attr-defined]
            frames = _chain(head, it)
        try:
            for f in frames:
                if max_frames is not None and len(records) >= max_frames:
                    break
                record, problem = _track_one(tracker, f)
                records.append(record)
                if problem is not None and first_error is None:
                    first_error = f"frame {f.index} (stamp {f.stamp_ns} ns): {problem}"
                if image_size is None and f.depth_mm is not None:
                    image_size = (f.depth_mm.shape[1], f.depth_mm.shape[0])
                r = records[-1]
                bar.update(1, f"{r.ms:6.1f} ms {r.status}")
        finally:
            bar.close()
    wall = time.perf_counter() - t_start
    if not records:
        raise BagError(f"bag {bag}: no depth image on {topics.depth!r} could be read")
    if all(r.status == STATUS_ERROR for r in records):
        raise BagError(f"bag {bag}: no depth image could be used; first problem: {first_error}")
    extra: dict[str, Any] = {}
    if first_error is not None:
        extra["first_frame_error"] = first_error
    return build_evaluation(str(bag), "core", records, wall, image_size, calib_info, extra)


def _chain(head: list[BagFrame], rest: Iterable[BagFrame]) -> Iterable[BagFrame]:
    yield from head
    yield from rest


def _track_one(tracker: TrackerLike, f: BagFrame) -> tuple[FrameRecord, str | None]:
    """Track one frame: its record and, for an unusable frame, why."""
    if f.depth_mm is None or f.intrinsics is None:
        return FrameRecord(f.index, f.stamp_ns, STATUS_ERROR, None, f.truth_mm, math.nan), f.error
    t0 = time.perf_counter()
    try:
        res = tracker.process(f.depth_mm, f.intrinsics)
    except InputError as err:  # DepthImageError, IntrinsicsError: frame unusable, track left intact
        return FrameRecord(f.index, f.stamp_ns, STATUS_ERROR, None, f.truth_mm, math.nan), str(err)
    ms = (time.perf_counter() - t0) * 1e3
    est = None
    if res.status is TrackerStatus.TRACKING and res.fingertips_mm is not None:
        est = np.asarray(res.fingertips_mm, dtype=np.float64)
    return FrameRecord(f.index, f.stamp_ns, _status_name(res.status), est, f.truth_mm, ms), None


def build_evaluation(
    bag: str,
    mode: str,
    records: Sequence[FrameRecord],
    wall_s: float,
    image_size: tuple[int, int] | None,
    calibration: dict[str, Any] | None = None,
    extra: dict[str, Any] | None = None,
) -> Evaluation:
    """Summarise frame records into an :class:`Evaluation`.

    Raises
    ------
    BagError
        If no frame has ground truth.
    """
    scored = [r.errors_mm for r in records if r.truth_mm is not None]
    if not scored:
        raise BagError(
            f"bag {bag}: none of the {len(records)} depth images has ground truth with the same "
            "stamp; nothing to score"
        )
    errors = summarize_errors(np.array(scored, dtype=np.float64).reshape(-1, 5))
    timing = summarize_timings([r.ms for r in records])
    return Evaluation(
        bag=bag,
        mode=mode,
        records=tuple(records),
        errors=errors,
        timing=timing,
        wall_s=wall_s,
        image_size=image_size,
        calibration=calibration,
        extra=dict(extra or {}),
    )


# -- through the ROS node -----------------------------------------------------------
#: Environment variables :func:`loopback_dds` sets (and restores afterwards).
_DDS_ENV = (
    "FASTRTPS_DEFAULT_PROFILES_FILE",
    "FASTDDS_DEFAULT_PROFILES_FILE",
    "ROS_DOMAIN_ID",
    "RMW_IMPLEMENTATION",
    "ROS_LOCALHOST_ONLY",
    "ROS_AUTOMATIC_DISCOVERY_RANGE",
    "ROS_STATIC_PEERS",
)


@contextlib.contextmanager
def loopback_dds(domain_id: int) -> Iterator[Path]:
    """Confine DDS to this machine for ``rclpy.init`` calls made inside the block.

    Forces Fast DDS (``RMW_IMPLEMENTATION=rmw_fastrtps_cpp``) with the
    package's loopback-only profile ``hand_sog_tracker/data/fastdds_loopback.xml``
    and ``ROS_DOMAIN_ID=domain_id``; the previous environment is restored on exit.

    Yields
    ------
    Path
        The profile file in use.

    Raises
    ------
    HandSogError
        If the profile is not installed with the package.
    """
    if not 0 <= int(domain_id) <= 232:
        raise InputError(f"ROS domain id must be in [0, 232], got {domain_id}")
    resource = importlib.resources.files("hand_sog_tracker") / "data" / "fastdds_loopback.xml"
    with importlib.resources.as_file(resource) as profile:
        if not Path(profile).is_file():
            raise HandSogError(f"the loopback Fast DDS profile is missing from the package ({profile})")
        saved = {k: os.environ.get(k) for k in _DDS_ENV}
        try:
            for k in ("ROS_LOCALHOST_ONLY", "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_STATIC_PEERS"):
                os.environ.pop(k, None)
            os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(profile)
            os.environ["FASTDDS_DEFAULT_PROFILES_FILE"] = str(profile)
            os.environ["ROS_DOMAIN_ID"] = str(int(domain_id))
            os.environ["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
            yield Path(profile)
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v


def _markers_to_output(msg: Any) -> tuple[int, NDArray[np.float64] | None] | None:
    """(stamp ns, fingertips (5, 3) mm or None for DELETEALL) of a MarkerArray; None if empty."""
    if not msg.markers:
        return None
    stamp = msg.markers[0].header.stamp
    stamp_ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
    tips = np.full((5, 3), np.nan)
    for m in msg.markers:
        if m.ns == "fingertips" and m.action == 0 and 0 <= m.id < 5:  # ADD
            p = m.pose.position
            tips[m.id] = (p.x * 1000.0, p.y * 1000.0, p.z * 1000.0)
    return stamp_ns, (tips if np.all(np.isfinite(tips)) else None)


_NODE_COUNTERS = ("frames_received", "frames_processed", "frames_dropped", "frames_rejected")
_COUNTER_KEYS = ("received", "processed", "dropped", "rejected")


def _diagnostic_counters(msg: Any) -> dict[str, Any] | None:
    """Counters of the tracker node's status in a DiagnosticArray, or None."""
    for status in msg.status:
        if status.name.startswith("hand_sog_tracker"):
            values = {kv.key: kv.value for kv in status.values}
            out: dict[str, Any] = {}
            for key in _NODE_COUNTERS:
                try:
                    out[key.removeprefix("frames_")] = int(values[key])
                except (KeyError, ValueError):
                    return None
            out["last_problem"] = values.get("last_problem", "")
            return out
    return None


def _warm_up(
    pub: Any,
    bagr: DepthBagReader,
    depth_conns: set[int],
    outputs: dict[int, tuple[float, NDArray[np.float64] | None]],
    diag: list[tuple[float, dict[str, Any]]],
    lock: threading.Lock,
    node_proc: "_NodeProcess",
    timeout_s: float,
) -> dict[str, Any]:
    """Send the first CameraInfo and depth image until the node has processed the image.

    The node's inputs are best effort, so both are re-sent every 1.5 s until
    the node publishes markers for the image or its ``/diagnostics`` count a
    processed frame (no hand: no markers).  Clears ``outputs`` afterwards, so
    the replayed first frame is scored afresh.
    """
    reader, path = bagr.reader, bagr.path
    first: dict[str, tuple[Any, bytes]] = {}
    for conn, _, raw in iter_messages(reader, path, bagr.connections(("info",))):
        first["info"] = (conn, raw)
        break
    for conn, _, raw in iter_messages(reader, path, bagr.connections(("depth",))):
        first["depth"] = (conn, raw)
        break
    if "depth" not in first:
        return {"seconds": 0.0, "answered": False, "tracking": False}
    conn, raw = first["depth"]
    stamp = stamp_to_ns(deserialize(reader, path, raw, conn).header.stamp)
    t0 = time.monotonic()
    t_sent = -math.inf
    done = False
    while time.monotonic() - t0 < timeout_s and node_proc.alive():
        now = time.monotonic()
        if now - t_sent > 1.5:
            if "info" in first:
                pub.publish(first["info"][0].topic, pub.payload(*first["info"]))
                time.sleep(0.05)
            pub.publish(conn.topic, pub.payload(conn, raw))
            t_sent = time.monotonic()
        with lock:
            done = stamp in outputs or any(t > t0 and c["processed"] >= 1 for t, c in diag)
        if done:
            break
        time.sleep(0.01)
    seconds = time.monotonic() - t0
    # The node's counters after the warm-up (subtracted from the final ones).
    t_done = time.monotonic()
    baseline: dict[str, Any] | None = None
    while done and time.monotonic() - t_done < 2.5 and node_proc.alive():
        with lock:
            settled = [
                c for t, c in diag
                if t > t_done and c["processed"] + c["rejected"] + c["dropped"] >= c["received"]
            ]
        if settled:
            baseline = settled[0]
            break
        time.sleep(0.02)
    with lock:
        tracked = stamp in outputs and outputs[stamp][1] is not None
        outputs.clear()
    return {"seconds": seconds, "answered": done, "tracking": tracked, "node_counters": baseline}


class _NodeProcess:
    """The tracker node (``python -m hand_sog_tracker.ros.node``) as a child process.

    Its output goes to a log file in ``workdir``; :meth:`stop` ends it
    (SIGINT, then SIGTERM, then SIGKILL) and is safe to call twice.
    """

    def __init__(self, workdir: Path) -> None:
        import hand_sog_tracker

        self.log_path = workdir / "tracker_node.log"
        env = dict(os.environ)
        root = str(Path(hand_sog_tracker.__file__).resolve().parents[1])
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH", "")) if p)
        env["ROS_HOME"] = str(workdir)  # logs and the (absent) user model stay in the scratch dir
        cmd = [
            sys.executable,
            "-m",
            "hand_sog_tracker.ros.node",
            "--ros-args",
            "-p",
            f"user_model_path:={workdir / 'no_user_model.yaml'}",
        ]
        self._log = open(self.log_path, "wb")  # noqa: SIM115 - closed in stop()
        try:
            self.proc = subprocess.Popen(cmd, env=env, stdout=self._log, stderr=subprocess.STDOUT)
        except OSError as err:
            self._log.close()
            raise HandSogError(f"cannot start the tracker node: {err}") from err

    def alive(self) -> bool:
        """True while the node runs."""
        return self.proc.poll() is None

    def log_tail(self, n: int = 15) -> str:
        """Last lines of the node's output."""
        try:
            lines = self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            return ""
        return "\n".join(lines[-n:])

    def stop(self) -> int | None:
        """End the node; its exit code."""
        for sig, wait_s in ((signal.SIGINT, 10.0), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
            if self.proc.poll() is not None:
                break
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout=wait_s)
            except subprocess.TimeoutExpired:
                continue
        if not self._log.closed:
            self._log.close()
        return self.proc.poll()


def evaluate_through_node(
    bag: str | Path,
    topics: BagTopics = BagTopics(),
    domain_id: int = 91,
    rate: float = 1.0,
    max_frames: int | None = None,
    connect_timeout_s: float = 30.0,
    drain_timeout_s: float = 10.0,
    progress: bool | None = None,
    warmup: bool = True,
    warmup_timeout_s: float = 10.0,
) -> Evaluation:
    """Score the ROS node: replay the bag to it over loopback DDS and listen.

    The tracker node runs as a child process (``python -m
    hand_sog_tracker.ros.node``, default hand model: ``user_model_path`` and
    ``ROS_HOME`` point into a temporary directory), exactly as deployed, so
    its timing is not disturbed by this process.  This process publishes the
    bag's depth images and CameraInfo (raw CDR for rosbag2 bags) on the
    node's input topics at the recorded rate times ``rate`` (after priming
    the node with the first CameraInfo), receives ``/hand/fingertips``
    (matched to ground truth by header stamp) and the node's counters from
    ``/diagnostics``.  DDS is confined by :func:`loopback_dds` for both.

    Parameters
    ----------
    bag : str or Path
    topics : BagTopics
        Topics *in the bag*; they are published under the node's topic names.
    domain_id : int
        ROS domain of the evaluation (loopback only).
    rate : float
        Replay speed factor.
    max_frames : int, optional
        Publish only the first N depth images.
    connect_timeout_s : float
        How long to wait for the node to start and connect.
    drain_timeout_s : float
        Longest wait, after the last image, for the node to report (on
        ``/diagnostics``) that it has handled every image it received.
    progress : bool, optional
        Progress bar on stderr (default: if stderr is a terminal).
    warmup : bool
        Before the timed replay, send the first depth image alone and wait
        (up to ``warmup_timeout_s``) until the node has processed it, so the
        one-off cost of the first detection (hundreds of ms, during which a
        live node drops frames and may lose the hand) is not part of the
        measurement.  The replay then starts again from that first image
        (same stamp, so the node keeps its track).  ``extra["warmup"]``
        tells how long it took.

    Returns
    -------
    Evaluation
        ``ms`` of each frame is the end-to-end latency (publication of the
        image to reception of the markers); ``extra`` holds
        ``frames_published``, ``frames_with_output``, ``frames_dropped``
        (published but never processed by the node, from its counters),
        ``node_stats`` (the node's counters for the timed replay) and
        ``latency_ms``.  Frames without any output are
        ``no_output`` (dropped, or no hand found).

    Raises
    ------
    BagError
        As for :func:`evaluate_core`.
    HandSogError
        If the node cannot be started, exits early or does not connect in time.
    """
    if not (rate > 0 and math.isfinite(rate)):
        raise InputError(f"rate must be a positive number, got {rate}")
    with (
        DepthBagReader(bag, topics, require_truth=True) as bagr,
        loopback_dds(domain_id),
        tempfile.TemporaryDirectory(prefix="evaluate_bag_") as tmp,
    ):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from visualization_msgs.msg import MarkerArray

        from hand_sog_tracker.tools.replay_bag import BagPublisher

        node_proc = _NodeProcess(Path(tmp))
        ctx = Context()
        rclpy.init(context=ctx)
        player: Any = None
        executor: Any = None
        spin_thread: threading.Thread | None = None
        lock = threading.Lock()
        outputs: dict[int, tuple[float, NDArray[np.float64] | None]] = {}
        diag: list[tuple[float, dict[str, Any]]] = []
        activity = [time.monotonic()]
        try:
            player = rclpy.create_node("evaluate_bag_player", context=ctx, start_parameter_services=False)
            pub = BagPublisher(
                player,
                bagr.reader,
                bagr.path,
                topics=[topics.depth, topics.info],
                rename={topics.depth: "/camera/depth/image_rect_raw", topics.info: "/camera/depth/camera_info"},
            )

            def on_markers(msg: Any) -> None:
                t = time.monotonic()
                out = _markers_to_output(msg)
                if out is None:
                    return
                with lock:
                    outputs.setdefault(out[0], (t, out[1]))
                    activity[0] = t

            def on_diagnostics(msg: Any) -> None:
                counters = _diagnostic_counters(msg)
                if counters is not None:
                    with lock:
                        diag.append((time.monotonic(), counters))

            reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
            player.create_subscription(MarkerArray, "/hand/fingertips", on_markers, reliable)
            player.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, reliable)
            executor = SingleThreadedExecutor(context=ctx)
            executor.add_node(player)

            def spin() -> None:
                while ctx.ok():
                    try:
                        executor.spin_once(timeout_sec=0.05)
                    except Exception:  # noqa: BLE001 - context shut down while spinning
                        return

            spin_thread = threading.Thread(target=spin, name="evaluate_bag_spin", daemon=True)
            spin_thread.start()

            deadline = time.monotonic() + connect_timeout_s
            while not (
                all(p.get_subscription_count() > 0 for p in pub.publishers.values())
                and player.count_publishers("/hand/fingertips") > 0
            ):
                if not node_proc.alive():
                    raise HandSogError(
                        f"the tracker node exited with code {node_proc.proc.returncode} before connecting:\n"
                        f"{node_proc.log_tail()}"
                    )
                if time.monotonic() > deadline:
                    raise HandSogError(
                        f"the tracker node did not connect within {connect_timeout_s:.0f} s "
                        f"(ROS_DOMAIN_ID {domain_id}, loopback DDS); its output:\n{node_proc.log_tail()}"
                    )
                time.sleep(0.05)

            records_pub: list[tuple[int, int, float]] = []  # (index, stamp, t_pub)
            total = bagr.n_depth if max_frames is None else min(bagr.n_depth, max_frames)
            bar = Progress(total, enabled=progress)
            reader, path = bagr.reader, bagr.path
            depth_conns = {id(c) for c in bagr.connections(("depth",))}
            for conn, _, raw in iter_messages(reader, path, bagr.connections(("info",))):
                pub.publish(conn.topic, pub.payload(conn, raw))  # prime the node's intrinsics
                break
            time.sleep(0.2)
            warmup_info: dict[str, Any] | None = None
            if warmup:
                warmup_info = _warm_up(pub, bagr, depth_conns, outputs, diag, lock, node_proc, warmup_timeout_s)
            t_first = time.monotonic()
            try:
                start_ns: int | None = None
                for conn, log_ns, raw in iter_messages(reader, path, pub.connections):
                    is_depth = id(conn) in depth_conns
                    if is_depth and max_frames is not None and len(records_pub) >= max_frames:
                        break
                    if start_ns is None:
                        start_ns, t_first = log_ns, time.monotonic()
                    delay = t_first + (log_ns - start_ns) / 1e9 / rate - time.monotonic()
                    if delay > 0:
                        time.sleep(delay)
                    if not node_proc.alive():
                        raise HandSogError(
                            f"the tracker node exited with code {node_proc.proc.returncode} during the "
                            f"evaluation:\n{node_proc.log_tail()}"
                        )
                    payload = pub.payload(conn, raw)
                    stamp = stamp_to_ns(deserialize(reader, path, raw, conn).header.stamp) if is_depth else 0
                    pub.publish(conn.topic, payload)
                    if is_depth:
                        records_pub.append((len(records_pub), stamp, time.monotonic()))
                        bar.update(1, "published")
                t_last_pub = time.monotonic()
                with lock:
                    activity[0] = max(activity[0], t_last_pub)
                # Drain: until the node reports (1 Hz /diagnostics) that it is idle with
                # nothing pending, i.e. it processed, rejected or dropped all it received.
                stats: dict[str, Any] | None = None
                t_fresh = t_last_pub + 0.1
                while time.monotonic() - t_last_pub < drain_timeout_s and node_proc.alive():
                    with lock:
                        settled = [
                            c for t, c in diag
                            if t > t_fresh and c["processed"] + c["rejected"] + c["dropped"] >= c["received"]
                        ]
                    if settled:
                        stats = settled[0]
                        break
                    time.sleep(0.02)
                if stats is None:
                    with lock:
                        stats = diag[-1][1] if diag else None
                with lock:
                    t_end = max(t_last_pub, activity[0])
            finally:
                bar.close()
        finally:
            if executor is not None:
                executor.shutdown(timeout_sec=5.0)
            rclpy.try_shutdown(context=ctx)
            if spin_thread is not None:
                spin_thread.join(timeout=5.0)
            if player is not None:
                player.destroy_node()
            node_proc.stop()

        records: list[FrameRecord] = []
        latencies: list[float] = []
        for index, stamp, t_pub in records_pub:
            out = outputs.get(stamp)
            truth = bagr.truth.get(stamp)
            if out is None:
                records.append(FrameRecord(index, stamp, STATUS_NO_OUTPUT, None, truth, math.nan))
                continue
            ms = (out[0] - t_pub) * 1e3
            latencies.append(ms)
            status = TrackerStatus.TRACKING.value if out[1] is not None else STATUS_NO_ESTIMATE
            records.append(FrameRecord(index, stamp, status, out[1], truth, ms))
        if not records:
            raise BagError(f"bag {bag}: no depth image on {topics.depth!r} could be read")
        i0 = bagr.intrinsics_at(records[0].stamp_ns)
        size = (i0.width, i0.height)
    lat = summarize_timings(latencies)
    n_out = sum(r.status != STATUS_NO_OUTPUT for r in records)
    base = (warmup_info or {}).get("node_counters")
    if stats is not None and base is not None:  # count the timed replay only
        stats = {k: (v - base[k] if k in _COUNTER_KEYS else v) for k, v in stats.items()}
    dropped = None if stats is None else max(len(records) - stats["processed"] - stats["rejected"], 0)
    extra = {
        "domain_id": int(domain_id),
        "rate": float(rate),
        "warmup": warmup_info,
        "frames_published": len(records),
        "frames_with_output": n_out,
        "frames_dropped": dropped,
        "node_stats": stats,
        "latency_ms": {"median": lat.median_ms, "p95": lat.p95_ms, "mean": lat.mean_ms},
        "ms_per_frame_is": "end-to-end latency (image published -> markers received)",
        "fps": n_out / max(t_end - t_first, 1e-9),
    }
    return build_evaluation(str(bag), "through_node", records, t_end - t_first, size, None, extra)


# -- output --------------------------------------------------------------------
def _fmt(v: float, spec: str = ".1f") -> str:
    return "n/a" if not math.isfinite(v) else format(v, spec)


def format_table(ev: Evaluation) -> str:
    """The paper's table plus timing, as text."""
    e = ev.errors
    size = f", {ev.image_size[0]}x{ev.image_size[1]}" if ev.image_size else ""
    lines = [
        f"bag: {ev.bag}  ({ev.mode} mode{size})",
        f"frames: {ev.frames} {'published' if ev.mode == 'through_node' else 'tracked'}, "
        f"{e.frames_scored} with ground truth "
        f"({ev.frames_without_truth} without, not scored), {e.frames_with_estimate} scored with an estimate",
        "status: " + ", ".join(f"{k} {v}" for k, v in ev.status_counts.items()),
    ]
    if ev.calibration:
        shape = ", ".join(f"{k} {v:.3f}" for k, v in ev.calibration["shape"].items())
        lines.append(f"calibration: {shape} ({ev.calibration['seconds']:.1f} s)")
    cols = ["mean"] + list(FINGERS)
    vals = [e.mean_mm] + [e.per_finger_mm[f] for f in FINGERS]
    lines += [
        "",
        "mean fingertip error (mm)",
        "  " + "".join(f"{c:>9}" for c in cols),
        "  " + "".join(f"{_fmt(v):>9}" for v in vals),
        "",
        "% of frames with mean fingertip error below",
        "  " + "".join(f"{t + ' mm':>9}" for t in e.pct_below_mm),
        "  " + "".join(f"{_fmt(v) + '%':>9}" for v in e.pct_below_mm.values()),
        "",
    ]
    what = "end-to-end latency" if ev.mode == "through_node" else "ms per frame"
    lines.append(
        f"{what}: median {_fmt(ev.timing.median_ms)} ms, p95 {_fmt(ev.timing.p95_ms)} ms, "
        f"{_fmt(ev.fps)} fps"
    )
    if ev.mode == "through_node":
        x = ev.extra
        lines.append(
            f"published {x.get('frames_published')} frames, node answered {x.get('frames_with_output')}, "
            f"dropped {x.get('frames_dropped')}"
        )
    return "\n".join(lines)


def write_plot(ev: Evaluation, path: str | Path) -> None:
    """PNG with the error over time (left) and the %-of-frames-below curve (right).

    Raises
    ------
    InputError
        If the image cannot be written to ``path``.
    """
    import cv2

    w_panel, h_img = 560, 420
    img = np.full((h_img, 2 * w_panel, 3), 255, dtype=np.uint8)
    records = [r for r in ev.records if r.truth_mm is not None]
    t0 = ev.records[0].stamp_ns if ev.records else 0
    t = np.array([(r.stamp_ns - t0) / 1e9 for r in records], dtype=np.float64)
    err = np.array([float(np.mean(r.errors_mm)) for r in records if r.errors_mm is not None])
    finite = err[np.isfinite(err)]
    y_max = max(50.0, float(np.ceil(np.max(finite) / 10.0) * 10.0)) if finite.size else 50.0
    t_max = float(t.max()) if t.size and t.max() > 0 else 1.0

    left = _Axes(img, x0=0, width=w_panel, height=h_img, x_range=(0.0, t_max), y_range=(0.0, y_max))
    left.frame("time (s)", "mean fingertip error (mm)", f"fingertip error over time ({ev.mode})")
    for thr in THRESHOLDS_MM:
        if thr < y_max:
            left.hline(float(thr), (215, 215, 215))
    prev: tuple[int, int] | None = None
    for ti, ei in zip(t, err):
        if not math.isfinite(ei):
            # no estimate: a red tick on the time axis
            x, y = left.to_px(ti, 0.0)
            cv2.line(img, (x, y), (x, y - 8), (0, 0, 220), 1)
            prev = None
            continue
        p = left.to_px(ti, min(ei, y_max))
        if prev is not None:
            cv2.line(img, prev, p, (180, 90, 0), 1, cv2.LINE_AA)
        if len(t) <= 120 or prev is None:
            cv2.circle(img, p, 2, (180, 90, 0), -1)
        prev = p

    thr_max = max(50.0, float(np.ceil(np.max(finite) / 10.0) * 10.0)) if finite.size else 50.0
    thr_max = min(thr_max, 200.0)
    grid = np.linspace(0.0, thr_max, 201)
    pct = pct_frames_below(err, grid) if err.size else np.zeros_like(grid)
    right = _Axes(img, x0=w_panel, width=w_panel, height=h_img, x_range=(0.0, thr_max), y_range=(0.0, 100.0))
    right.frame("error threshold (mm)", "% of frames below", "frames with mean error below threshold")
    pts = np.array([right.to_px(x, y) for x, y in zip(grid, pct)], dtype=np.int32)
    cv2.polylines(img, [pts.reshape(-1, 1, 2)], False, (0, 140, 0), 2, cv2.LINE_AA)
    for key, v in ev.errors.pct_below_mm.items():
        if math.isfinite(v):
            x, y = right.to_px(float(key), v)
            cv2.circle(img, (x, y), 3, (0, 0, 200), -1)
            cv2.putText(img, f"{v:.0f}%", (x + 4, y - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 200), 1, cv2.LINE_AA)
    out = Path(path)
    try:
        ok = cv2.imwrite(str(out), img)
    except cv2.error as err:
        raise InputError(f"cannot write plot {out}: {err}") from err
    if not ok:
        raise InputError(f"cannot write plot {out} (unwritable path or not a .png name?)")


class _Axes:
    """Minimal axes drawing in one panel of an image (cv2 only)."""

    ML, MR, MT, MB = 70, 20, 36, 52  # margins, px

    def __init__(
        self,
        img: NDArray[np.uint8],
        x0: int,
        width: int,
        height: int,
        x_range: tuple[float, float],
        y_range: tuple[float, float],
    ) -> None:
        self.img, self.x0, self.w, self.h = img, x0, width, height
        self.xr, self.yr = x_range, y_range

    def to_px(self, x: float, y: float) -> tuple[int, int]:
        """Data coordinates to pixel coordinates."""
        px0, px1 = self.x0 + self.ML, self.x0 + self.w - self.MR
        py0, py1 = self.h - self.MB, self.MT
        fx = (x - self.xr[0]) / max(self.xr[1] - self.xr[0], 1e-12)
        fy = (y - self.yr[0]) / max(self.yr[1] - self.yr[0], 1e-12)
        return int(round(px0 + fx * (px1 - px0))), int(round(py0 + fy * (py1 - py0)))

    def hline(self, y: float, colour: tuple[int, int, int]) -> None:
        """A horizontal grid line at data ``y``."""
        import cv2

        a, b = self.to_px(self.xr[0], y), self.to_px(self.xr[1], y)
        cv2.line(self.img, a, b, colour, 1)

    def frame(self, xlabel: str, ylabel: str, title: str) -> None:
        """Axes, ticks, tick labels, axis labels and title."""
        import cv2

        font, black = cv2.FONT_HERSHEY_SIMPLEX, (0, 0, 0)
        o = self.to_px(self.xr[0], self.yr[0])
        xe = self.to_px(self.xr[1], self.yr[0])
        ye = self.to_px(self.xr[0], self.yr[1])
        cv2.line(self.img, o, xe, black, 1)
        cv2.line(self.img, o, ye, black, 1)
        xt = _ticks(*self.xr)
        for v in xt:
            x, y = self.to_px(v, self.yr[0])
            cv2.line(self.img, (x, y), (x, y + 4), black, 1)
            label = _tick_label(v, xt)
            cv2.putText(self.img, label, (x - 4 * len(label), y + 18), font, 0.4, black, 1, cv2.LINE_AA)
        yt = _ticks(*self.yr)
        for v in yt:
            x, y = self.to_px(self.xr[0], v)
            cv2.line(self.img, (x - 4, y), (x, y), black, 1)
            label = _tick_label(v, yt)
            cv2.putText(self.img, label, (x - 10 - 8 * len(label), y + 4), font, 0.4, black, 1, cv2.LINE_AA)
        mid_x = (o[0] + xe[0]) // 2
        cv2.putText(self.img, xlabel, (mid_x - 4 * len(xlabel), self.h - 12), font, 0.45, black, 1, cv2.LINE_AA)
        cv2.putText(self.img, title, (self.x0 + self.ML, 22), font, 0.5, black, 1, cv2.LINE_AA)
        # vertical y label: draw on a strip and rotate it
        (tw, th), _ = cv2.getTextSize(ylabel, font, 0.45, 1)
        strip = np.full((th + 8, tw + 4, 3), 255, dtype=np.uint8)
        cv2.putText(strip, ylabel, (2, th + 2), font, 0.45, black, 1, cv2.LINE_AA)
        rot = cv2.rotate(strip, cv2.ROTATE_90_COUNTERCLOCKWISE)
        rh, rw = rot.shape[:2]
        cy = (o[1] + ye[1]) // 2
        top = max(cy - rh // 2, 0)
        rh = min(rh, self.h - top)
        self.img[top : top + rh, self.x0 + 4 : self.x0 + 4 + rw] = rot[:rh]


def _ticks(lo: float, hi: float, n: int = 6) -> NDArray[np.float64]:
    span = max(hi - lo, 1e-9)
    raw = span / n
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw)
    start = math.ceil(lo / step) * step
    return np.arange(start, hi + 1e-9 * span, step)


def _tick_label(v: float, ticks: NDArray[np.float64]) -> str:
    step = float(ticks[1] - ticks[0]) if len(ticks) > 1 else 1.0
    decimals = next((d for d in range(5) if abs(step * 10**d - round(step * 10**d)) < 1e-6), 4)
    return f"{v:.{decimals}f}"


# -- CLI -------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    """The command-line parser of ``evaluate_bag``."""
    p = argparse.ArgumentParser(
        prog="evaluate_bag",
        description="Score the hand tracker on a bag with ground-truth fingertips: mean fingertip "
        "error overall and per finger, % of frames below 15/20/25/30 mm, ms per frame.",
    )
    p.add_argument("bag", help="rosbag2 directory (sqlite3 or mcap) or ROS 1 .bag file")
    p.add_argument("--depth-topic", default=BagTopics.depth, help="sensor_msgs/Image depth topic (default %(default)s)")
    p.add_argument("--info-topic", default=BagTopics.info, help="sensor_msgs/CameraInfo topic (default %(default)s)")
    p.add_argument("--gt-topic", default=BagTopics.truth, help="geometry_msgs/PoseArray ground truth (default %(default)s)")
    p.add_argument("--json", metavar="OUT", help="write the results as JSON to OUT")
    p.add_argument("--plot", metavar="OUT.png", help="write a PNG: error over time and %%-of-frames-below curve")
    p.add_argument("--calibrate", action="store_true", help="fit the hand model on the first frames, then track")
    p.add_argument("--max-frames", type=int, metavar="N", help="evaluate only the first N depth images")
    p.add_argument("--through-node", action="store_true",
                   help="run the ROS node and publish the bag to it over loopback DDS at its recorded rate")
    p.add_argument("--domain-id", type=int, default=91, help="ROS_DOMAIN_ID for --through-node (default %(default)s)")
    p.add_argument("--rate", type=float, default=1.0, help="replay rate factor for --through-node (default 1)")
    p.add_argument("--node-timeout", type=float, default=30.0, metavar="S",
                   help="--through-node: seconds to wait for the node to connect (default %(default)s)")
    p.add_argument("--no-warmup", action="store_true",
                   help="--through-node: do not let the node detect the hand on the first image before the "
                   "timed replay (then its first, slow detection is part of the measurement)")
    p.add_argument("--quiet", action="store_true", help="do not print the table")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point; returns the exit status (0 ok, 2 error)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.max_frames is not None and args.max_frames < 1:
        parser.error("--max-frames must be >= 1")
    if not (args.rate > 0 and math.isfinite(args.rate)):
        parser.error("--rate must be a positive number")
    if args.calibrate and args.through_node:
        parser.error("--calibrate cannot be combined with --through-node (call the node's ~/calibrate service instead)")
    if not 0 <= args.domain_id <= 232:
        parser.error("--domain-id must be in [0, 232]")
    topics = BagTopics(depth=args.depth_topic, info=args.info_topic, truth=args.gt_topic)
    try:
        if args.through_node:
            ev = evaluate_through_node(
                args.bag,
                topics,
                domain_id=args.domain_id,
                rate=args.rate,
                max_frames=args.max_frames,
                connect_timeout_s=args.node_timeout,
                warmup=not args.no_warmup,
            )
        else:
            ev = evaluate_core(args.bag, topics, calibrate=args.calibrate, max_frames=args.max_frames)
        if not args.quiet:
            print(format_table(ev))
        if args.json:
            _write_json(ev, args.json)
        if args.plot:
            write_plot(ev, args.plot)
    except HandSogError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    return 0


def _write_json(ev: Evaluation, path: str) -> None:
    try:
        with open(path, "w", encoding="utf-8") as fh:
            json.dump(ev.to_json(), fh, indent=2, allow_nan=False)
            fh.write("\n")
    except OSError as err:
        raise InputError(f"cannot write JSON to {path}: {err}") from err


if __name__ == "__main__":
    sys.exit(main())
