"""``demo``: run the product, ``tracker_node``, on a bundled bag and show what it does.

One job: the ``demo`` command; kept together because its listener, frame drawing, video writer
and run loop serve only this command (the node harness is :mod:`.node_harness`).

Usage::

    demo [BAG] [--domain-id N] [--video OUT.mp4] [--rate R] [--max-frames N]

Starts ``tracker_node`` as a child process on loopback DDS (the package's
``data/fastdds_loopback.xml``, its own ``ROS_DOMAIN_ID``, a temporary
``ROS_HOME``: :class:`~hand_sog_tracker.tools.node_harness.NodeHarness`),
replays the bag's depth images and CameraInfo into it at the recorded rate,
listens to its outputs and prints

* the rate of each output topic (``hand/joint_states``, ``hand/fingertips``,
  ``hand/keypoints``, ``/diagnostics``),
* the end-to-end latency (image published -> ``hand/fingertips`` received,
  median and p95) and how many frames the node answered,
* the Table-1 row of the bag (mean fingertip error, % of frames below
  15/20/25/30 mm, ms/frame) scored from the node's fingertip markers,

and writes a video of the depth with the node's 21 published keypoints (the
skeleton) and fingertips projected with the bag's intrinsics, and the true
fingertips as white rings (MP4 with OpenCV's ``mp4v``; an animated GIF, then a
PNG strip, when that codec is unavailable).  ``make demo`` runs it.  The
offline evaluation of the core (no node) is ``evaluate_bag``.

As in ``evaluate_bag --through-node`` (:mod:`~hand_sog_tracker.tools.node_eval`,
whose warm-up and drain steps are reused), the first image is sent alone
first, so the one-off first detection (about 0.3 s) is reported on its own and
not mixed into the latency.

Exit status: 0 on success, 2 on a usage error or any
:class:`~hand_sog_tracker.errors.HandSogError`, 130 when interrupted.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence, TextIO

import cv2
import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.overlay import TIP_COLOURS_BGR, draw_overlay
from hand_sog_tracker.core.types import Intrinsics, TrackerConfig, TrackerStatus
from hand_sog_tracker.errors import BagError, HandSogError, InputError
from hand_sog_tracker.tools.bagio import BagFrame, BagTopics, DepthBagReader, deserialize, iter_messages, stamp_to_ns
from hand_sog_tracker.tools.bagset import PROTOCOL, TEST_SPLIT, read_sidecar
from hand_sog_tracker.tools.metrics import summarize_timings
from hand_sog_tracker.tools.node_eval import _Payloads, _warm_up, drain, score_outputs
from hand_sog_tracker.tools.node_harness import COUNTER_KEYS, NodeHarness, NodeOutputs
from hand_sog_tracker.tools.records import (
    STATUS_NO_OUTPUT,
    Evaluation,
    build_evaluation,
)
from hand_sog_tracker.tools.report import format_table1

__all__ = ["DEFAULT_BAG", "DEFAULT_DOMAIN_ID", "DemoResult", "run_demo", "write_video", "main"]

#: Bag of ``make demo``: a mesh-hand dev bag (an independent hand model, not the tracker's own),
#: fast global rotation (see bags/README.md).
DEFAULT_BAG = "bags/mesh_dev/rotate"
#: ROS domain of the demo (loopback DDS only).
DEFAULT_DOMAIN_ID = 74
#: Namespace of the demo's node.
NAMESPACE = "/demo"
#: Output topics whose rates are reported (relative ones are in :data:`NAMESPACE`).
TOPICS = ("hand/joint_states", "hand/fingertips", "hand/keypoints", "/diagnostics")
#: Width the video frames are enlarged to (at least; by a whole factor).
VIDEO_WIDTH = 640
#: Keypoint pairs drawn as the skeleton (MediaPipe Hands' connections).
SKELETON = (
    (0, 1), (1, 2), (2, 3), (3, 4), (0, 5), (5, 6), (6, 7), (7, 8), (5, 9), (9, 10), (10, 11), (11, 12),
    (9, 13), (13, 14), (14, 15), (15, 16), (13, 17), (0, 17), (17, 18), (18, 19), (19, 20),
)


@dataclass(frozen=True, eq=False)
class DemoResult:
    """What :func:`run_demo` measured and wrote.

    Attributes
    ----------
    evaluation : Evaluation
        The bag scored through the node (``mode == "through_node"``; ``ms`` = end-to-end latency).
    rates_hz : dict
        Output topic (full name) -> message rate during the replay, Hz (NaN with < 2 messages).
    counts : dict
        Output topic (full name) -> messages received during the replay.
    processing_ms : float
        Mean processing time per frame inside the node (its ``/diagnostics``), ms.
    video : Path
        The video written (``.mp4``, ``.gif`` or a ``.png`` strip).
    video_frames : int
        Frames in it.
    text : str
        The report printed.
    """

    evaluation: Evaluation
    rates_hz: dict[str, float]
    counts: dict[str, int]
    processing_ms: float
    video: Path
    video_frames: int
    text: str


class _Listener:
    """``hand/keypoints`` and the node's ``/diagnostics`` timings, on the harness's own rclpy node.

    (The harness collects markers, joint states and frame counters; the demo also wants the
    keypoints and the node's processing time.)
    """

    def __init__(self, h: NodeHarness) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseArray
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        self._lock = threading.Lock()
        self._fqn = h.node_fqn
        #: stamp ns -> (reception time, keypoints (21, 3) mm)
        self.keypoints: dict[int, tuple[float, NDArray[np.float64]]] = {}
        self.keypoint_times: list[float] = []
        #: (reception time, processing ms, frames processed in the window)
        self.timings: list[tuple[float, float, float]] = []
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        h.node.create_subscription(PoseArray, h.topic("hand/keypoints"), self._on_keypoints, qos)
        #: max_hands 2: side -> stamp ns -> keypoints (21, 3) mm of ``hand/<side>/keypoints``
        self.hand_keypoints: dict[str, dict[int, NDArray[np.float64]]] = {}
        if int(h.params.get("max_hands", 1)) > 1:
            from hand_sog_tracker.ros.hand_topics import per_hand_topic

            for side in ("left", "right"):
                self.hand_keypoints[side] = {}
                h.node.create_subscription(
                    PoseArray, h.topic(per_hand_topic(side, "keypoints")),
                    lambda msg, s=side: self._on_hand_keypoints(s, msg), qos,
                )
        h.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, qos)

    def _on_keypoints(self, msg: Any) -> None:
        t = time.monotonic()
        stamp = stamp_to_ns(msg.header.stamp)
        pts = np.array([(p.position.x, p.position.y, p.position.z) for p in msg.poses], dtype=np.float64) * 1000.0
        with self._lock:
            self.keypoint_times.append(t)
            self.keypoints.setdefault(stamp, (t, pts.reshape(-1, 3)))

    def _on_hand_keypoints(self, side: str, msg: Any) -> None:
        pts = np.array([(p.position.x, p.position.y, p.position.z) for p in msg.poses], dtype=np.float64) * 1000.0
        with self._lock:
            self.hand_keypoints[side].setdefault(stamp_to_ns(msg.header.stamp), pts.reshape(-1, 3))

    def _on_diagnostics(self, msg: Any) -> None:
        t = time.monotonic()
        for status in msg.status:
            if status.name.endswith(f": {self._fqn}"):
                values = {kv.key: kv.value for kv in status.values}
                try:
                    ms, rate = float(values["processing_ms"]), float(values["output_rate_hz"])
                except (KeyError, ValueError):
                    continue
                with self._lock:
                    self.timings.append((t, ms, rate))

    def clear(self) -> None:
        with self._lock:
            self.keypoints.clear()
            self.keypoint_times.clear()
            for k in self.hand_keypoints.values():
                k.clear()

    def snapshot(
        self,
    ) -> tuple[dict[int, tuple[float, NDArray[np.float64]]], list[float], list[tuple[float, float, float]]]:
        """Copies of the keypoints by stamp, their reception times and the timings."""
        with self._lock:
            return dict(self.keypoints), list(self.keypoint_times), list(self.timings)


class _DecodedPayloads(_Payloads):
    """Payloads for a bag with ``compressedDepth`` images: published decoded, as ``sensor_msgs/Image``."""

    def __call__(self, conn: Any, raw: bytes) -> Any:
        if conn.topic != self.bagr.depth_topic:
            return super().__call__(conn, raw)
        from hand_sog_tracker.ros.conversions import compressed_image_to_depth_mm
        from hand_sog_tracker.tools.bagio import depth_image_msg, typestore

        msg = deserialize(self.bagr.reader, self.bagr.path, raw, conn)
        img = depth_image_msg(compressed_image_to_depth_mm(msg), stamp_to_ns(msg.header.stamp), msg.header.frame_id,
                              encoding="32FC1")
        return typestore().serialize_cdr(img, img.__msgtype__).tobytes()


def _rate(times: Sequence[float]) -> float:
    """Messages per second from reception times ((n - 1) / span); NaN with fewer than 2."""
    if len(times) < 2:
        return math.nan
    span = max(times) - min(times)
    return (len(times) - 1) / span if span > 0 else math.nan


def _draw_frame(
    frame: BagFrame,
    keypoints_mm: NDArray[np.float64] | None,
    tips_mm: NDArray[np.float64] | None,
    label: str,
    near_mm: float,
    far_mm: float,
    hands: Sequence[tuple[NDArray[np.float64] | None, NDArray[np.float64] | None, str]] | None = None,
    truths: Sequence[NDArray[np.float64]] = (),
) -> NDArray[np.uint8]:
    """Depth colour map with the node's skeleton and fingertips, and the true fingertips as white rings.

    ``hands``: instead of the one hand, ``(keypoints (21, 3), fingertips (5, 3), side)`` of each
    hand of a two-hand bag (the left skeleton magenta, the right cyan, each labelled); ``truths``:
    more true fingertips (5, 3) mm each."""
    intr = frame.intrinsics
    assert intr is not None
    depth = frame.depth_mm if frame.depth_mm is not None else np.zeros((intr.height, intr.width), np.float32)
    img = draw_overlay(depth, intr, None, None, near_mm=near_mm, far_mm=far_mm)
    zoom = max(1, int(round(VIDEO_WIDTH / img.shape[1])))  # small images are enlarged (pixels kept sharp)
    if zoom > 1:
        img = cv2.resize(img, None, fx=zoom, fy=zoom, interpolation=cv2.INTER_NEAREST)
    scale = max(1, int(round(img.shape[1] / 320)))

    def px(points: NDArray[np.float64], intrinsics: Intrinsics) -> list[tuple[int, int] | None]:
        out: list[tuple[int, int] | None] = []
        for (u, v), z in zip(intrinsics.project(points), points[:, 2]):
            ok = z > 0 and np.isfinite(u) and np.isfinite(v) and abs(u) < 1e5 and abs(v) < 1e5
            # pixel centres: u = 0 is the centre of the first pixel
            out.append((int(round((u + 0.5) * zoom - 0.5)), int(round((v + 0.5) * zoom - 0.5))) if ok else None)
        return out

    for truth in ([frame.truth_mm] if frame.truth_mm is not None else []) + list(truths):
        for p in px(truth, intr):
            if p is not None:
                cv2.circle(img, p, 5 * scale, (255, 255, 255), 1, cv2.LINE_AA)
    for kps, tips, side in hands if hands is not None else [(keypoints_mm, tips_mm, "")]:
        bone = (255, 0, 255) if side == "left" else (255, 255, 0)
        if kps is not None and kps.shape == (21, 3):
            kp = px(kps, intr)
            for a, b in SKELETON:
                if kp[a] is not None and kp[b] is not None:
                    cv2.line(img, kp[a], kp[b], bone, scale, cv2.LINE_AA)
            for p in kp:
                if p is not None:
                    cv2.circle(img, p, scale + 1, bone, -1, cv2.LINE_AA)
            if side and kp[0] is not None:
                cv2.putText(img, side, (kp[0][0] + 4, kp[0][1] + 14 * scale), cv2.FONT_HERSHEY_SIMPLEX,
                            0.4 * scale, bone, 1, cv2.LINE_AA)
        if tips is not None:
            for p, colour in zip(px(tips, intr), TIP_COLOURS_BGR):
                if p is not None:
                    cv2.circle(img, p, 2 * scale + 1, colour, -1, cv2.LINE_AA)
    cv2.putText(img, label, (6, 16 * scale), cv2.FONT_HERSHEY_SIMPLEX, 0.4 * scale, (255, 255, 255), 1, cv2.LINE_AA)
    return img


def write_video(frames_bgr: Sequence[NDArray[np.uint8]], path: str | Path, fps: float) -> Path:
    """Write BGR frames as an MP4 (OpenCV ``mp4v``), else an animated GIF (Pillow), else a PNG strip.

    Parameters
    ----------
    frames_bgr : sequence of arrays, shape (H, W, 3) uint8
    path : str or Path
        Wanted file; its suffix is replaced by ``.gif`` / ``.png`` for the fallbacks.
    fps : float

    Returns
    -------
    Path
        The file written.
    """
    if not frames_bgr:
        raise InputError("no frames to write")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    h, w = frames_bgr[0].shape[:2]
    if path.suffix.lower() in (".mp4", ".m4v", ".mov"):
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w, h))
        try:
            if writer.isOpened():
                for f in frames_bgr:
                    writer.write(np.ascontiguousarray(f))
        finally:
            writer.release()
        if path.is_file() and path.stat().st_size > 0:
            return path
        path = path.with_suffix(".gif")
    if path.suffix.lower() == ".gif":
        try:
            from PIL import Image
        except ImportError:
            path = path.with_suffix(".png")
        else:
            images = [Image.fromarray(np.ascontiguousarray(f[:, :, ::-1])) for f in frames_bgr]
            images[0].save(path, save_all=True, append_images=images[1:], duration=int(round(1000 / fps)), loop=0)
            return path
    # PNG strip: every frame side by side would be too wide; a grid of up to 8 columns.
    step = max(1, len(frames_bgr) // 16)
    picked = list(frames_bgr[::step])[:16]
    cols = min(8, len(picked))
    blank = np.zeros_like(picked[0])
    picked += [blank] * (-len(picked) % cols)
    rows = [np.hstack(picked[i:i + cols]) for i in range(0, len(picked), cols)]
    path = path.with_suffix(".png")
    if not cv2.imwrite(str(path), np.vstack(rows)):
        raise HandSogError(f"cannot write {path}")
    return path


def _fmt(v: float, spec: str = ".1f") -> str:
    return format(v, spec) if math.isfinite(v) else "n/a"


def run_demo(
    bag: str | Path = DEFAULT_BAG,
    domain_id: int = DEFAULT_DOMAIN_ID,
    video: str | Path | None = None,
    rate: float = 1.0,
    max_frames: int | None = None,
    params: Mapping[str, Any] | None = None,
    stream: TextIO | None = None,
    allow_test_inspection: bool = False,
    connect_timeout_s: float = 30.0,
    drain_timeout_s: float = 5.0,
    warmup_timeout_s: float = 10.0,
) -> DemoResult:
    """Start the node, replay ``bag`` into it, print rates, latency and the Table-1 row, write a video.

    Parameters
    ----------
    bag : str or Path
        A bag with depth, CameraInfo and ground-truth fingertips (contract 5).
    domain_id : int
        ROS domain of the node and the demo (loopback DDS only).
    video : str or Path, optional
        Video to write; default ``<tmp>/hand_sog_tracker_demo/<bag name>.mp4``.
    rate : float
        Replay speed factor (1 = as recorded).
    max_frames : int, optional
        Replay only the first N depth images.
    params : mapping, optional
        Node parameters (default: the bag's handedness from its sidecar).
    stream : text stream, optional
        Where to print (default ``sys.stdout``).
    allow_test_inspection : bool
        Show a bag of the held-out ``test`` split frame by frame (refused otherwise).

    Returns
    -------
    DemoResult

    Raises
    ------
    InputError
        A bag of the held-out test split (without ``allow_test_inspection``), a bad ``rate``.
    BagError
        Unreadable bag, or no frame with ground truth.
    HandSogError
        The node cannot be started, exits or does not connect.
    """
    out = sys.stdout if stream is None else stream
    if not (rate > 0 and math.isfinite(rate)):
        raise InputError(f"rate must be a positive number, got {rate}")
    bag_path = Path(bag)
    sample = read_sidecar(bag_path) if bag_path.exists() else {}
    if sample.get("split") == TEST_SPLIT and not allow_test_inspection:
        raise InputError(f"{bag}: the demo's video shows every frame; {PROTOCOL}")
    node_params: dict[str, Any] = dict(params or {})
    if "handedness" not in node_params and sample.get("handedness") in ("right", "left"):
        node_params["handedness"] = sample["handedness"]
    # A two-hand bag (its sidecar's hands: 2): the node tracks both, the right hand's truth is the
    # one-hand score's, and the video draws each hand from its own topics.
    two_hands = sample.get("hands") == 2
    hand_truth: dict[str, dict[int, Any]] = {}
    topics = BagTopics()
    if two_hands:
        from hand_sog_tracker.tools.twohand_bags import hand_topic, read_hand_truth

        node_params.setdefault("max_hands", 2)
        topics = BagTopics(truth=hand_topic("right"))
        hand_truth = read_hand_truth(bag_path)
    near = float(node_params.get("near_mm", TrackerConfig.near_mm))
    far = float(node_params.get("far_mm", TrackerConfig.far_mm))
    lines: list[str] = []

    def say(text: str = "") -> None:
        lines.append(text)
        print(text, file=out, flush=True)

    t_start = time.monotonic()
    with DepthBagReader(bag_path, topics, require_truth=True) as bagr:
        # Everything in memory first, so the replay is timed by the recording alone.
        frames = list(bagr.frames())
        if max_frames is not None:
            frames = frames[: max(int(max_frames), 1)]
        if not frames:
            raise BagError(f"bag {bag}: no depth image")
        payload = _DecodedPayloads(bagr) if bagr.depth_compressed else _Payloads(bagr)
        depth_conns = {id(c) for c in bagr.connections(("depth",))}
        messages: list[tuple[int, bool, Any, int]] = []  # (log ns, is depth, payload, stamp ns)
        n_depth = 0
        for conn, log_ns, raw in iter_messages(bagr.reader, bagr.path, bagr.connections(("depth", "info"))):
            is_depth = id(conn) in depth_conns
            if is_depth and n_depth >= len(frames):
                break
            stamp = stamp_to_ns(deserialize(bagr.reader, bagr.path, raw, conn).header.stamp)
            messages.append((int(log_ns), is_depth, payload(conn, raw), stamp))
            n_depth += is_depth
        i0 = frames[0].intrinsics
        assert i0 is not None
        duration = (frames[-1].log_time_ns - frames[0].log_time_ns) / 1e9
        fps_rec = (len(frames) - 1) / duration if duration > 0 else 30.0
        encoding = bagr.topic_table.get(bagr.depth_topic, ("?", 0))[0].rsplit("/", 1)[-1]
        say(f"hand_sog_tracker demo: tracker_node fed by {bag}")
        say(f"  bag: {len(frames)} depth frames, {i0.width}x{i0.height} {sample.get('encoding', encoding)}, "
            f"{fps_rec:.0f} Hz, {node_params.get('handedness', 'right')} hand, "
            f"{sample.get('renderer', '?')} renderer, split {sample.get('split', '-')}")

        t_node = time.monotonic()
        with NodeHarness(domain_id, params=node_params, namespace=NAMESPACE,
                         connect_timeout_s=connect_timeout_s) as h:
            say(f"  node: started and connected in {time.monotonic() - t_node:.1f} s "
                f"(loopback DDS, ROS_DOMAIN_ID {domain_id}, namespace {NAMESPACE}, temporary ROS_HOME)")
            listener = _Listener(h)
            for _, is_depth, msg, _ in messages:
                if not is_depth:
                    h.publish("info", msg)  # prime the node's intrinsics
                    break
            time.sleep(0.2)
            warm = _warm_up(h, bagr, payload, warmup_timeout_s)
            listener.clear()
            say(f"  first detection (first image alone): {warm['seconds']:.2f} s, "
                f"{'tracking' if warm['tracking'] else 'no hand yet'}")

            published: list[tuple[int, float]] = []  # (stamp, t_pub)
            t_first = time.monotonic()
            start_ns = messages[0][0]
            for log_ns, is_depth, msg, stamp in messages:
                delay = t_first + (log_ns - start_ns) / 1e9 / rate - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                h.check_alive("during the demo")
                h.publish("depth" if is_depth else "info", msg)
                if is_depth:
                    published.append((stamp, time.monotonic()))
            t_last_pub = time.monotonic()
            h.note_activity(t_last_pub)
            stats = drain(h, t_last_pub, drain_timeout_s)
            outs: NodeOutputs = h.outputs
            keypoints, kp_times, timings = listener.snapshot()
            t_end = max(t_last_pub, outs.last_activity)

    # Rates: messages received from the first image published to the end of the drain.
    def since(times: Sequence[float]) -> list[float]:
        return [t for t in times if t >= t_first]

    received = {
        h.topic("hand/joint_states"): since([t for t, _ in outs.joint_states.values()]),
        h.topic("hand/fingertips"): since([m.t for m in outs.markers.values()]),
        h.topic("hand/keypoints"): since(kp_times),
        # 1 Hz: a short replay holds one or two, so its rate is taken over the node's whole run.
        "/diagnostics": [t for t, _ in outs.diagnostics],
    }
    rates = {k: _rate(v) for k, v in received.items()}
    counts = {k: len(v) for k, v in received.items()}

    truth_by_stamp = {f.stamp_ns: f.truth_mm for f in frames}
    records, latencies = score_outputs(
        ((index, stamp, t_pub) for index, (stamp, t_pub) in enumerate(published)), outs, truth_by_stamp
    )
    lat = summarize_timings(latencies)
    base = warm.get("node_counters")
    if stats is not None and base is not None:
        stats = {k: (v - base[k] if k in COUNTER_KEYS else v) for k, v in stats.items()}
    n_out = sum(r.status != STATUS_NO_OUTPUT for r in records)
    n_track = sum(r.status == TrackerStatus.TRACKING.value for r in records)
    dropped = None if stats is None else max(len(records) - stats["processed"] - stats["rejected"], 0)
    extra = {
        "domain_id": int(domain_id),
        "rate": float(rate),
        "node_params": node_params,
        "handedness": str(node_params.get("handedness", "right")),
        "warmup": warm,
        "frames_published": len(records),
        "frames_with_output": n_out,
        "frames_dropped": dropped,
        "node_stats": stats,
        "latency_ms": {"median": lat.median_ms, "p95": lat.p95_ms, "mean": lat.mean_ms},
        "fps": n_out / max(t_end - t_first, 1e-9),
    }
    ev = build_evaluation(str(bag), "through_node", records, t_end - t_first, (i0.width, i0.height), None, extra)
    ev = dataclasses.replace(ev, split=str(sample.get("split", "-")))
    busy = [(ms, r) for t, ms, r in timings if t >= t_first and r > 0]
    processing = sum(ms * r for ms, r in busy) / sum(r for _, r in busy) if busy else math.nan

    say(f"  replay: {len(published)} frames in {t_last_pub - t_first:.1f} s at the recorded rate"
        + (f" x{rate:g}" if rate != 1.0 else ""))
    say("")
    say("output topic rates (while replaying; /diagnostics: since the node started)")
    width = max(len(k) for k in rates)
    for k in rates:
        say(f"  {k:<{width}}  {_fmt(rates[k]):>6} Hz  ({counts[k]} message{'s' if counts[k] != 1 else ''})")
    say(f"end-to-end latency (image published -> hand/fingertips received): "
        f"median {_fmt(lat.median_ms)} ms, p95 {_fmt(lat.p95_ms)} ms")
    say(f"processing inside the node (its /diagnostics: the whole search of each frame): {_fmt(processing)} ms/frame")
    say(f"frames answered: {n_out} of {len(records)} published ({n_track} with a hand, "
        f"{n_out - n_track} hand lost, dropped by the node: {'?' if dropped is None else dropped})")
    say("")
    say("Table 1 row (fingertip error of the node's hand/fingertips vs. the bag's ground truth; "
        "ms = end-to-end latency)")
    say(format_table1([ev]))
    if two_hands:
        from hand_sog_tracker.tools.twohand_eval import HandPrediction, TwoHandRecord, format_two_hand_table, score_two_hands

        two_records = []
        for f, (stamp, _) in zip(frames, published):
            gt = {s: hand_truth[s].get(stamp) for s in ("left", "right")}
            preds = []
            for s in ("left", "right"):
                m = outs.hand_markers.get(s, {}).get(stamp)
                if m is not None and m.fingertips_mm is not None:
                    preds.append(HandPrediction(s, m.fingertips_mm))
            two_records.append(TwoHandRecord(
                f.index, stamp, {s: None if g is None else g.fingertips_mm for s, g in gt.items()},
                {s: math.nan if g is None else g.visible_fraction for s, g in gt.items()}, tuple(preds),
            ))
        say("")
        say("per hand (hand/left/fingertips, hand/right/fingertips vs. each hand's truth; ms: not timed here)")
        say(format_two_hand_table([score_two_hands(two_records, bag_path.name, str(sample.get("split", "-")),
                                                   "through_node")]))

    # Video: every frame of the bag, with what the node published for it.
    images = []
    for f, r in zip(frames, records):
        kp = keypoints.get(f.stamp_ns)
        m = outs.markers.get(f.stamp_ns)
        tips = None if m is None else m.fingertips_mm
        err = r.errors_mm
        if r.status == STATUS_NO_OUTPUT:
            text = "no output"
        elif tips is None:
            text = "hand lost"
        else:
            text = f"err {_fmt(float(np.mean(err)) if err is not None else math.nan)} mm  lat {_fmt(r.ms, '.0f')} ms"
        label = f"{bag_path.name} #{f.index}  {text}"
        if two_hands:
            per_hand = []
            for side in ("left", "right"):
                hm = outs.hand_markers.get(side, {}).get(f.stamp_ns)
                per_hand.append((listener.hand_keypoints.get(side, {}).get(f.stamp_ns),
                                 None if hm is None else hm.fingertips_mm, side))
            n = sum(t is not None for _, t, _ in per_hand)
            label = f"{bag_path.name} #{f.index}  {n} hand{'s' if n != 1 else ''}"
            truths = [r.fingertips_mm for r in (hand_truth["left"].get(f.stamp_ns),) if r is not None]
            images.append(_draw_frame(f, None, None, label, near, far, per_hand, truths))
            continue
        images.append(_draw_frame(f, None if kp is None else kp[1], tips, label, near, far))
    target = Path(video) if video is not None else (
        Path(tempfile.gettempdir()) / "hand_sog_tracker_demo" / f"{bag_path.name or 'bag'}.mp4")
    written = write_video(images, target, fps_rec * rate)
    say("")
    say(f"video ({len(images)} frames, depth + the node's keypoints (cyan skeleton), fingertips (dots), "
        f"true fingertips (white rings)): {written}")
    say(f"done in {time.monotonic() - t_start:.1f} s")
    return DemoResult(ev, rates, counts, processing, written, len(images), "\n".join(lines))


def build_parser() -> argparse.ArgumentParser:
    """Command-line options of ``demo``."""
    p = argparse.ArgumentParser(
        prog="demo",
        description="Start tracker_node on loopback DDS, replay a bag into it at the recorded rate, print "
        "its topic rates, latency and Table-1 row, and write a video of the tracked hand over the depth. "
        "(The offline evaluation of the core, without the node, is evaluate_bag.)",
    )
    p.add_argument("bag", nargs="?", default=DEFAULT_BAG, help=f"bag with ground truth (default {DEFAULT_BAG})")
    p.add_argument("--domain-id", type=int, default=DEFAULT_DOMAIN_ID,
                   help=f"ROS domain of the node and the demo, loopback only (default {DEFAULT_DOMAIN_ID})")
    p.add_argument("--video", default=None,
                   help="video to write (default <tmp>/hand_sog_tracker_demo/<bag>.mp4; a .gif or .png strip "
                   "if OpenCV cannot write mp4v)")
    p.add_argument("--rate", type=float, default=1.0, help="replay speed factor (default 1: as recorded)")
    p.add_argument("--max-frames", type=int, default=None, help="replay only the first N frames")
    p.add_argument("--allow-test-inspection", action="store_true",
                   help="allow a bag of the held-out test split (bags/mesh_test; refused otherwise)")
    p.add_argument("--node-timeout", type=float, default=30.0, help="seconds to wait for the node to connect")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``demo`` (see the module docstring)."""
    args = build_parser().parse_args(argv)
    try:
        run_demo(args.bag, domain_id=args.domain_id, video=args.video, rate=args.rate,
                 max_frames=args.max_frames, allow_test_inspection=args.allow_test_inspection,
                 connect_timeout_s=args.node_timeout)
    except KeyboardInterrupt:
        return 130
    except HandSogError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
