"""Memory after bad input, measured on the node's own process (issue 50: within 10 MB of steady
tracking).

:mod:`test_ros_node_bounded` runs the node in the test process, whose own allocations (the
messages it builds, its records, rclpy's objects) share and fragment the node's heap: what it
measures after the battery is the test process.  Here the node runs as the product runs it, a
process of its own (:class:`~hand_sog_tracker.tools.node_harness.NodeHarness`), fed over
loopback DDS with the battery's kinds that grow a process (oversized images, wrong intrinsics,
resolution changes, the dearest parameters) and a burst of oversized images; its resident set
(``/proc/PID/statm``) after them is compared with its peak over steady tracking.  The node's
answers to these kinds are the battery's to check, not this test's.
``HAND_SOG_BATTERY_SIZE=640x480`` runs it at 640x480 (default 320x240).
"""

from __future__ import annotations

import os
import threading
import time
from typing import Iterator

import numpy as np
import pytest

from helpers import test_domain

pytest.importorskip("hand_sog_tracker.ros.node", reason="the tracker node (hand_sog_tracker.ros.node) is not there")

import test_ros_node_bounded as battery
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image, JointState

from hand_sog_tracker.interface import CONFIDENCE_TOPIC, stamp_to_ns
from hand_sog_tracker.tools.node_harness import NodeHarness

DOMAIN = test_domain(5)
#: The battery's kinds that leave a process larger (measured: oversized messages, a new track
#: after a K or resolution change, the parameters that multiply a frame's data).
HEAP_KINDS = (
    "real 2000x2000 image (8 MB)",
    "one valid pixel",
    "uniform noise 200-1500 mm",
    "120x120 noise patch while tracking",
    "binning 2 of a double-size K",
    "principal point 1 px off every frame",
    "fx 10x too large (plausible)",
    "fx 2x too large (plausible)",
    "fx 3x too small (plausible)",
    f"resolution alternating {battery.W}x{battery.H} / {battery.OTHER[0]}x{battery.OTHER[1]}",
    "roi_radius_mm at its maximum (1000)",
    "iterations at its maximum (200)",
    "init_hypotheses at its maximum (256)",
    "max_width_px 4096, min_quad_px 2",
    "quadtree_threshold_mm 1, min_quad_px 2",
    "refine_iterations 50, median_kernel 5",
    "far_mm 10000 with a wall",
)
#: Oversized images sent back to back: each one the middleware holds at once keeps a buffer.
BURST = 6
#: How long a frame may take to be answered (s; a frame no answer comes for, a rejected one,
#: costs this).
ANSWER_S = 3.0


def node_rss_mb(pid: int) -> float:
    """The resident set (MB) of process ``pid``."""
    with open(f"/proc/{pid}/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


class PeakSampler:
    """The resident set of process ``pid`` sampled every 2 ms on a thread (its peak over a stretch)."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.peak = node_rss_mb(pid)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.002):
            try:
                self.peak = max(self.peak, node_rss_mb(self.pid))
            except OSError:  # (the node has ended)
                return

    def reset(self) -> float:
        peak, self.peak = self.peak, node_rss_mb(self.pid)
        return peak

    def close(self) -> None:
        self._stop.set()
        self._thread.join()


class DdsBench(battery.CleanFrames):
    """What the battery's kinds use of :class:`test_ros_node_bounded.Bench` (frames, stamps,
    parameters), for a node in its own process: messages go over DDS, and each image waits
    for the node's answer (``hand/confidence``, on every processed frame) or ``ANSWER_S``."""

    def __init__(self, harness: NodeHarness) -> None:
        from rclpy.parameter_client import AsyncParameterClient

        super().__init__()
        self.h = harness
        self._answered: set[int] = set()
        self._changed: set[str] = set()  # parameters set since the last recover()
        self._lock = threading.Lock()
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        harness.node.create_subscription(JointState, harness.topic(CONFIDENCE_TOPIC), self._on_answer, qos)
        self._params = AsyncParameterClient(harness.node, harness.node_fqn)
        assert self._params.wait_for_services(20.0), "the node's parameter services did not come up"

    def _on_answer(self, msg: JointState) -> None:
        with self._lock:
            self._answered.add(stamp_to_ns(msg.header.stamp))

    def send(self, msg: Image) -> int:
        stamp = stamp_to_ns(msg.header.stamp)
        self.h.publish("depth", msg)
        end = time.monotonic() + ANSWER_S
        while time.monotonic() < end:
            with self._lock:
                if stamp in self._answered:
                    break
            self.h.check_alive("while a kind ran")
            time.sleep(0.002)
        return stamp

    def send_info(self, msg: CameraInfo) -> None:
        self.h.publish("info", msg)
        time.sleep(0.03)  # (before the next image: the two topics are not ordered)

    def set(self, **values) -> list[str]:
        self._changed |= set(values)
        future = self._params.set_parameters([Parameter(k, value=v) for k, v in values.items()])
        end = time.monotonic() + 10.0
        while not future.done() and time.monotonic() < end:
            time.sleep(0.005)
        assert future.done(), f"no answer to setting {values}"
        return [r.reason for r in future.result().results if not r.successful]

    def recover(self) -> None:
        self.send_info(battery.info())
        changed, self._changed = self._changed, set()
        if changed:
            refused = self.set(**{k: battery.DEFAULTS[k] for k in changed})
            assert not refused, refused
            self._changed = set()
        for _ in range(5):
            self.good()

    def burst_of_oversized_images(self, n: int) -> None:
        """``n`` images of 2000x2000 (8 MB each) back to back, then a pause for the node."""
        for _ in range(n):
            msg = battery.image(np.zeros((1, 1), np.float32), self.stamp())
            msg.width, msg.height, msg.step = 2000, 2000, 4000
            msg.data = bytes(2000 * 4000)
            self.h.publish("depth", msg)
        time.sleep(ANSWER_S)


@pytest.fixture(scope="module")
def node(tmp_path_factory) -> Iterator[NodeHarness]:
    params = {"auto_calibrate": False, "frame_budget_ms": float(battery.DEFAULTS["frame_budget_ms"])}
    with NodeHarness(DOMAIN, params=params, workdir=tmp_path_factory.mktemp("memory"), namespace="/memory") as h:
        yield h


def test_the_node_process_returns_to_steady_tracking_after_bad_input(node: NodeHarness) -> None:
    """Issue 50's target, "memory after the battery within 10 MB of steady tracking", on the
    node's own process."""
    kinds = {k.name: k for k in battery.KINDS}
    missing = [name for name in HEAP_KINDS if name not in kinds]
    assert not missing, missing
    bench = DdsBench(node)
    pid = node.process.proc.pid
    sampler = PeakSampler(pid)
    try:
        bench.send_info(battery.info())
        for _ in range(40):
            bench.good()
        sampler.reset()
        for _ in range(40):  # steady tracking: the reference (as the battery's)
            bench.good()
        steady = sampler.reset()
        for name in HEAP_KINDS:
            kinds[name].run(bench)
            bench.recover()
        bench.burst_of_oversized_images(BURST)
        bench.recover()
        answered = sum(bench.good()[0] in bench._answered for _ in range(20))
        after = node_rss_mb(pid)
        peak = sampler.peak
    finally:
        sampler.close()
    print(f"{battery._SIZE}, the node's own process: steady tracking {steady:.1f} MB, peak {peak:.1f} MB "
          f"(+{peak - steady:.1f}), after {len(HEAP_KINDS)} kinds and {BURST} oversized images {after:.1f} MB "
          f"({after - steady:+.1f})")
    assert answered == 20, f"{answered} of 20 clean frames answered after the oversized images"
    assert after - steady < 10.0
