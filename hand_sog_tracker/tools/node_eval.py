"""``evaluate_bag --through-node``: score ``tracker_node`` by replaying a bag to it over loopback DDS.

The node runs as a child process (:class:`~hand_sog_tracker.tools.node_harness.NodeHarness`),
exactly as deployed, so its timing is not disturbed by this process.  This
process publishes the bag's depth images and CameraInfo on the node's input
topics (in a namespace of its own, so runs sharing a domain do not mix) at the
recorded rate (times ``rate``), receives ``hand/fingertips`` (matched to ground
truth by header stamp) and the node's counters from ``/diagnostics``.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import os
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.types import TrackerStatus
from hand_sog_tracker.errors import BagError, InputError
from hand_sog_tracker.interface import stamp_to_ns
from hand_sog_tracker.tools.bagio import BagTopics, DepthBagReader, deserialize, iter_messages
from hand_sog_tracker.tools.metrics import summarize_timings
from hand_sog_tracker.tools.node_harness import COUNTER_KEYS, NodeHarness, NodeOutputs
from hand_sog_tracker.tools.records import (
    STATUS_NO_ESTIMATE,
    STATUS_NO_OUTPUT,
    Evaluation,
    FrameRecord,
    Progress,
    build_evaluation,
)

__all__ = ["evaluate_through_node"]


class _Payloads:
    """What to publish for a bag message: its CDR bytes (rosbag2) or a converted rclpy message (ROS 1)."""

    def __init__(self, bagr: DepthBagReader) -> None:
        self.bagr = bagr
        self.raw = bool(bagr.reader.is2)

    def __call__(self, conn: Any, raw: bytes) -> Any:
        if self.raw:
            return bytes(raw)
        from hand_sog_tracker.tools.replay_bag import ros_message_class, to_rclpy

        msg = deserialize(self.bagr.reader, self.bagr.path, raw, conn)
        return to_rclpy(msg, ros_message_class(conn.msgtype))


_RUNS = itertools.count()


def _private_namespace() -> str:
    """A namespace of its own for each node this process starts (other runs may share the domain)."""
    return f"/evaluate_bag_{os.getpid()}_{next(_RUNS)}"


def _settled(outs: NodeOutputs, after: float) -> dict[str, Any] | None:
    """The first counters received after ``after`` that account for every frame received."""
    for t, c in outs.diagnostics:
        if t > after and c["processed"] + c["rejected"] + c["dropped"] >= c["received"]:
            return c
    return None


def score_outputs(
    published: Iterable[tuple[int, int, float]],
    outs: NodeOutputs,
    truth: Mapping[int, NDArray[np.float64] | None],
) -> tuple[list[FrameRecord], list[float]]:
    """One record per published image, matched by stamp with the node's fingertip markers.

    Parameters
    ----------
    published : iterable of (index, stamp ns, monotonic publish time s)
    outs : NodeOutputs
        What the node published.
    truth : mapping stamp ns -> fingertips (5, 3) mm or None

    Returns
    -------
    records, and the end-to-end latencies (ms) of the answered images.
    """
    records: list[FrameRecord] = []
    latencies: list[float] = []
    for index, stamp, t_pub in published:
        out = outs.markers.get(stamp)
        gt = truth.get(stamp)
        if out is None:
            records.append(FrameRecord(index, stamp, STATUS_NO_OUTPUT, None, gt, math.nan))
            continue
        ms = (out.t - t_pub) * 1e3
        latencies.append(ms)
        status = TrackerStatus.TRACKING.value if out.fingertips_mm is not None else STATUS_NO_ESTIMATE
        records.append(FrameRecord(index, stamp, status, out.fingertips_mm, gt, ms))
    return records, latencies


def drain(h: NodeHarness, t_last_pub: float, timeout_s: float) -> dict[str, Any] | None:
    """Wait until the node reports (1 Hz ``/diagnostics``) that it is idle with nothing pending.

    That is: it processed, rejected or dropped everything it received after ``t_last_pub``
    (monotonic s).  Returns those counters, or None after ``timeout_s`` or if the node died.
    """
    while time.monotonic() - t_last_pub < timeout_s and h.alive():
        stats = _settled(h.outputs, t_last_pub + 0.1)
        if stats is not None:
            return stats
        time.sleep(0.02)
    return None


def _warm_up(h: NodeHarness, bagr: DepthBagReader, payload: _Payloads, timeout_s: float) -> dict[str, Any]:
    """Send the first CameraInfo and depth image until the node has processed the image.

    The node's inputs are best effort, so both are re-sent every 1.5 s until
    the node publishes markers for the image or its ``/diagnostics`` count a
    processed frame (no hand: no markers).  Clears the outputs afterwards, so
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
    while time.monotonic() - t0 < timeout_s and h.alive():
        if time.monotonic() - t_sent > 1.5:
            if "info" in first:
                h.publish("info", payload(*first["info"]))
                time.sleep(0.05)
            h.publish("depth", payload(conn, raw))
            t_sent = time.monotonic()
        outs = h.outputs
        done = stamp in outs.markers or any(t > t0 and c["processed"] >= 1 for t, c in outs.diagnostics)
        if done:
            break
        time.sleep(0.01)
    seconds = time.monotonic() - t0
    # The node's counters after the warm-up (subtracted from the final ones).
    t_done = time.monotonic()
    baseline: dict[str, Any] | None = None
    while done and time.monotonic() - t_done < 2.5 and h.alive():
        baseline = _settled(h.outputs, t_done)
        if baseline is not None:
            break
        time.sleep(0.02)
    outs = h.outputs
    tracked = stamp in outs.markers and outs.markers[stamp].fingertips_mm is not None
    h.clear_outputs()
    return {"seconds": seconds, "answered": done, "tracking": tracked, "node_counters": baseline}


#: Lines of the node's log searched for its automatic calibration's messages (a run logs a few
#: dozen).
_LOG_LINES_READ = 10_000


def _calibration_log(log: str) -> list[str]:
    """The messages (without the logger's level, time and name) of the node's log lines that
    report its automatic calibration (started, in use, refused, failed)."""
    out = []
    for line in log.splitlines():
        if "automatic calibration" in line:
            out.append(line.split("]: ", 1)[-1].strip())
    return out


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
    params: Mapping[str, Any] | None = None,
    split: str = "-",
) -> Evaluation:
    """Score the ROS node: replay the bag to it over loopback DDS and listen.

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
    params : mapping, optional
        Node parameters (``-p name:=value``), e.g. ``{"handedness": "left"}``.
    split : str
        Stored in :attr:`Evaluation.split`.

    Returns
    -------
    Evaluation
        ``ms`` of each frame is the end-to-end latency (publication of the
        image to reception of the markers); ``extra`` holds
        ``frames_published``, ``frames_with_output``, ``frames_dropped``
        (published but never processed by the node, from its counters),
        ``node_stats`` (the node's counters for the timed replay), ``latency_ms`` and
        ``node_calibration_log`` (the node's log messages about its automatic calibration).
        Frames without any output are ``no_output`` (dropped, or no hand found).

    Raises
    ------
    BagError
        As for :func:`~hand_sog_tracker.tools.evaluation.evaluate_core`.
    HandSogError
        If the node cannot be started, exits early or does not connect in time.
    """
    if not (rate > 0 and math.isfinite(rate)):
        raise InputError(f"rate must be a positive number, got {rate}")
    with (
        DepthBagReader(bag, topics, require_truth=True) as bagr,
        NodeHarness(domain_id, params=params, namespace=_private_namespace(),
                    connect_timeout_s=connect_timeout_s) as h,
    ):
        payload = _Payloads(bagr)
        reader, path = bagr.reader, bagr.path
        depth_conns = {id(c) for c in bagr.connections(("depth",))}
        for conn, _, raw in iter_messages(reader, path, bagr.connections(("info",))):
            h.publish("info", payload(conn, raw))  # prime the node's intrinsics
            break
        time.sleep(0.2)
        warmup_info = _warm_up(h, bagr, payload, warmup_timeout_s) if warmup else None
        records_pub: list[tuple[int, int, float]] = []  # (index, stamp, t_pub)
        total = bagr.n_depth if max_frames is None else min(bagr.n_depth, max_frames)
        bar = Progress(total, enabled=progress)
        t_first = time.monotonic()
        try:
            start_ns: int | None = None
            for conn, log_ns, raw in iter_messages(reader, path, bagr.connections(("depth", "info"))):
                is_depth = id(conn) in depth_conns
                if is_depth and max_frames is not None and len(records_pub) >= max_frames:
                    break
                if start_ns is None:
                    start_ns, t_first = log_ns, time.monotonic()
                delay = t_first + (log_ns - start_ns) / 1e9 / rate - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                h.check_alive("during the evaluation")
                msg = payload(conn, raw)
                stamp = stamp_to_ns(deserialize(reader, path, raw, conn).header.stamp) if is_depth else 0
                h.publish("depth" if is_depth else "info", msg)
                if is_depth:
                    records_pub.append((len(records_pub), stamp, time.monotonic()))
                    bar.update(1, "published")
            t_last_pub = time.monotonic()
            h.note_activity(t_last_pub)
            stats = drain(h, t_last_pub, drain_timeout_s)
            outs = h.outputs
            if stats is None:
                stats = outs.diagnostics[-1][1] if outs.diagnostics else None
            t_end = max(t_last_pub, outs.last_activity)
        finally:
            bar.close()

        calibration_log = _calibration_log(h.log_tail(_LOG_LINES_READ))
        records, latencies = score_outputs(records_pub, outs, bagr.truth)
        pub = {stamp: t for _, stamp, t in records_pub}
        if not records:
            raise BagError(f"bag {bag}: no depth image on {topics.depth!r} could be read")
        i0 = bagr.intrinsics_at(records[0].stamp_ns)
        size = (i0.width, i0.height)
    lat = summarize_timings(latencies)
    n_out = sum(r.status != STATUS_NO_OUTPUT for r in records)
    base = (warmup_info or {}).get("node_counters")
    if stats is not None and base is not None:  # count the timed replay only
        stats = {k: (v - base[k] if k in COUNTER_KEYS else v) for k, v in stats.items()}
    dropped = None if stats is None else max(len(records) - stats["processed"] - stats["rejected"], 0)
    extra = {
        "domain_id": int(domain_id),
        "rate": float(rate),
        "node_params": dict(params or {}),
        "handedness": str((params or {}).get("handedness", "right")),
        "warmup": warmup_info,
        "frames_published": len(records),
        "frames_with_output": n_out,
        "frames_dropped": dropped,
        "node_stats": stats,
        "latency_ms": {"median": lat.median_ms, "p95": lat.p95_ms, "mean": lat.mean_ms},
        "node_calibration_log": calibration_log,
        "ms_per_frame_is": "end-to-end latency (image published -> markers received)",
        "fps": n_out / max(t_end - t_first, 1e-9),
        # (max_hands 2: side -> stamp -> (end-to-end ms, fingertips (5, 3) mm or None))
        "hand_outputs": {
            side: {stamp: ((out.t - pub[stamp]) * 1e3, out.fingertips_mm) for stamp, out in m.items() if stamp in pub}
            for side, m in outs.hand_markers.items()
        },
    }
    ev = build_evaluation(str(bag), "through_node", records, t_end - t_first, size, None, extra)
    return dataclasses.replace(ev, split=split)
