"""``scene_eval --through-node``: replay a scene bag to ``tracker_node`` and collect its decisions.

One job: the node side of :mod:`hand_sog_tracker.tools.scene_eval`; kept apart because it needs
rclpy (through :class:`~hand_sog_tracker.tools.node_harness.NodeHarness`).

The bag's frames are published at 30 Hz (their stamps' rate) after the first frame alone as a
warm-up (see :func:`replay_scene`); the node's
``hand/confidence`` (every processed frame) and ``hand/keypoints`` (the reported hands) are
matched to the frames by stamp.  A frame without a ``hand/confidence`` message was not processed
(dropped): it counts as "no hand reported".
"""

from __future__ import annotations

import math
import os
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from hand_sog_tracker.interface import CONFIDENCE_NAMES, CONFIDENCE_TOPIC, KEYPOINTS_TOPIC, stamp_to_ns
from hand_sog_tracker.tools.bagio import DepthBagReader
from hand_sog_tracker.tools.make_scene_bags import read_scene_truth
from hand_sog_tracker.tools.node_harness import NodeHarness

__all__ = ["replay_scene"]

_RUN = [0]


def replay_scene(
    bag: str | Path, domain_id: int, rate_hz: float = 30.0, drain_s: float = 3.0, params: dict[str, Any] | None = None
) -> list[dict[str, Any]]:
    """Per-frame records (as :func:`scene_eval.evaluate_scene_core`'s) of ``bag`` through the node
    (its parameters ``params``, node names)."""
    from geometry_msgs.msg import PoseArray
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState

    from hand_sog_tracker.tools.scene_eval import _errors

    truth = read_scene_truth(bag)
    conf: dict[int, tuple[float, list[float]]] = {}
    kps: dict[int, np.ndarray] = {}
    lock = threading.Lock()

    def on_conf(msg: Any) -> None:
        with lock:
            conf.setdefault(stamp_to_ns(msg.header.stamp), (time.monotonic(), list(msg.position)))

    def on_kp(msg: Any) -> None:
        pts = np.array([[p.position.x, p.position.y, p.position.z] for p in msg.poses]) * 1000.0
        with lock:
            kps.setdefault(stamp_to_ns(msg.header.stamp), pts)

    _RUN[0] += 1
    ns = f"/scene_eval_{os.getpid()}_{_RUN[0]}"
    with DepthBagReader(bag, require_truth=False) as reader:
        frames = list(reader.frames())
    with NodeHarness(domain_id, namespace=ns, params=params) as h:
        qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
        h.node.create_subscription(JointState, h.topic(CONFIDENCE_TOPIC), on_conf, qos)
        h.node.create_subscription(PoseArray, h.topic(KEYPOINTS_TOPIC), on_kp, qos)
        time.sleep(1.0)  # (the new subscriptions match)
        # Warm-up as evaluate_bag --through-node does: the first frame alone, answered before the
        # replay, which then starts again from it (same stamp: the node keeps its track), so that
        # the one-off cost of the node's first detection is not part of the 30 Hz replay.
        f0 = frames[0]
        h.publish_depth(f0.depth_mm, f0.intrinsics, f0.stamp_ns)
        t_end = time.monotonic() + 15.0
        while time.monotonic() < t_end and f0.stamp_ns not in conf:
            time.sleep(0.02)
        with lock:
            conf.pop(f0.stamp_ns, None)
            kps.pop(f0.stamp_ns, None)
        t0 = time.monotonic()
        for k, f in enumerate(frames):
            delay = t0 + k / rate_hz - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            h.publish_depth(f.depth_mm, f.intrinsics, f.stamp_ns)
        t_end = time.monotonic() + drain_s
        last = frames[-1].stamp_ns
        while time.monotonic() < t_end and last not in conf:
            time.sleep(0.02)
        time.sleep(0.2)
    out = []
    i_present, i_hand = CONFIDENCE_NAMES.index("present"), CONFIDENCE_NAMES.index("hand")
    for f in frames:
        vis, joints = truth[f.stamp_ns]
        c = conf.get(f.stamp_ns)
        present = bool(c is not None and c[1][i_present] > 0.5)
        skel = kps.get(f.stamp_ns) if present else None
        tip, tip_max, palm = _errors(joints, skel)
        out.append({
            "index": f.index, "visibility": vis, "posed": skel is not None,
            "reported": present, "processed": c is not None,
            "confidence": math.nan if c is None else float(c[1][i_hand]),
            "fingers": None if c is None else [round(x, 3) for x in c[1][i_hand + 1 :]],
            "tip_mm": tip, "tip_max_mm": tip_max, "palm_mm": palm, "evidence": None,
        })
    return out
