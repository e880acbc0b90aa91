"""The bad-input battery (issue 50): one tracker node, well over 100 kinds of bad input.

Each kind must leave the node alive, give the expected clear reason (the rejection's
``last_problem`` or a warning), publish nothing wrong (no pose for a rejected or hand-less
frame; a published pose near the truth) and track a clean frame afterwards.  The frames go
straight into the node's image and CameraInfo callbacks (the executor's thread, no DDS round
trip: the whole battery takes seconds) and its outputs are read where it publishes them;
DDS is used for discovery and the ``~/calibrate`` calls.

The module also records the worst frame (the node's processing of one image) and the peak
resident memory over the battery against steady tracking (:func:`test_battery_memory_and_time`).
``HAND_SOG_BATTERY_SIZE=640x480`` runs the battery at 640x480 (default 320x240);
``HAND_SOG_BATTERY_RECORD=<file>`` appends one JSON line per kind (kind, expected, observed,
worst frame wall and CPU ms, peak RSS) and one summary line; ``python -m
hand_sog_tracker.tools.battery_table <files>`` prints them as the closing note's table.
"""

from __future__ import annotations

import json
import os
import struct
import threading
import time
import uuid
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.parameter import Parameter
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, RegionOfInterest
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker, MarkerArray

from hand_sog_tracker.compressed_depth import encode_compressed_depth, rvl_encode
from hand_sog_tracker.core.hand_model import default_hand_model, rest_pose
from hand_sog_tracker.core.kinematics import fingertips
from hand_sog_tracker.core.types import Intrinsics
from hand_sog_tracker.errors import CalibrationError, InputError
from hand_sog_tracker.interface import FINGERTIPS_NS, stamp_to_ns
from hand_sog_tracker.ros import calibration_service
from hand_sog_tracker.ros.blas import THREADS_ENV, blas_threads
from hand_sog_tracker.ros.node import DEFAULT_FRAME_ID, TrackerNode
from hand_sog_tracker.ros.params import PARAM_SPECS
from hand_sog_tracker.synth.render import RenderOptions, render_depth
from test_ros_node import Rig

_SIZE = os.environ.get("HAND_SOG_BATTERY_SIZE", "320x240")
W, H = (int(x) for x in _SIZE.split("x"))
INTR = Intrinsics(fx=0.8977 * W, fy=0.8977 * W, cx=W / 2 - 0.5, cy=H / 2 - 0.5, width=W, height=H)
OTHER = (640, 480) if W == 320 else (320, 240)
INTR_OTHER = Intrinsics(
    fx=0.8977 * OTHER[0], fy=0.8977 * OTHER[0], cx=OTHER[0] / 2 - 0.5, cy=OTHER[1] / 2 - 0.5,
    width=OTHER[0], height=OTHER[1],
)
FRAME = "depth_optical"
#: Mean fingertip error (mm) below which a published pose is right (the tracker's errors on
#: these renders: 3-12 mm; the resolution fault of issue 50 put poses 29-59 mm off).
TOL_MM = 25.0
DEFAULTS = {s.name: s.default for s in PARAM_SPECS}
RECORD = os.environ.get("HAND_SOG_BATTERY_RECORD")
MODEL = default_hand_model()


def _pose(i: int) -> np.ndarray:
    """The clean sequence: an open hand at 420 mm, index and middle flexing back and forth."""
    th = rest_pose((5.0 + 2.0 * np.sin(i / 5.0), 10.0, 420.0))
    th[6 + 4] = th[6 + 8] = 0.25 * (1.0 + np.sin(i / 3.0))
    return th


def _render(theta: np.ndarray, intr: Intrinsics, seed: int) -> np.ndarray:
    d = render_depth(MODEL, theta, intr, RenderOptions(noise_mm=1.0), rng=np.random.default_rng(seed))
    return np.round(d).astype(np.float32)


def image(depth: np.ndarray, stamp: int, encoding: str = "16UC1", frame: str = FRAME,
          bigendian: bool = False, pad: int = 0) -> Image:
    """A ``sensor_msgs/Image`` of ``depth`` (mm) in ``encoding`` (32FC1: metres)."""
    h, w = depth.shape
    dt = ">" if bigendian else "<"
    if encoding.upper() == "32FC1":
        px = (depth / 1000.0).astype(dt + "f4")
    else:
        px = np.round(np.nan_to_num(np.clip(depth, 0, 65535))).astype(dt + "u2")
    rows = px.view(np.uint8).reshape(h, -1)
    if pad:
        rows = np.concatenate([rows, np.zeros((h, pad), np.uint8)], axis=1)
    msg = Image(height=h, width=w, encoding=encoding, is_bigendian=int(bigendian), step=rows.shape[1])
    msg.data = rows.tobytes()
    msg.header.frame_id = frame
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 10**9)
    return msg


def compressed(fmt: str, data: bytes, stamp: int) -> CompressedImage:
    msg = CompressedImage(format=fmt)
    msg.data = data
    msg.header.frame_id = FRAME
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 10**9)
    return msg


def info(intr: Intrinsics = INTR, k: list[float] | None = None, **fields) -> CameraInfo:
    msg = CameraInfo(width=intr.width, height=intr.height, distortion_model="plumb_bob")
    msg.k = k if k is not None else [intr.fx, 0.0, intr.cx, 0.0, intr.fy, intr.cy, 0.0, 0.0, 1.0]
    for name, value in fields.items():
        setattr(msg, name, value)
    msg.header.frame_id = FRAME
    return msg


def png_of_zeros(width: int, height: int) -> bytes:
    """A 16-bit grey PNG of zeros, written row by row (never the image in memory: a 8192x8192
    one is 130 kB, the image 128 MB)."""
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    z = zlib.compressobj(9)
    row = bytes(1 + 2 * width)
    idat = b"".join(z.compress(row) for _ in range(height)) + z.flush()
    ihdr = struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


HEADER = struct.pack("<iff", 0, 0.0, 0.0)


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


class RssSampler:
    """The process's resident memory sampled every 2 ms on a thread (its peak over a stretch)."""

    def __init__(self) -> None:
        self.peak = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.002):
            self.peak = max(self.peak, rss_mb())

    def reset(self) -> float:
        peak, self.peak = self.peak, rss_mb()
        return peak

    def close(self) -> None:
        self._stop.set()
        self._thread.join()


@dataclass
class Outcome:
    """What the node did while one kind was fed: its frames, reasons and outputs."""

    rejected: int = 0
    problems: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    tips: dict[int, np.ndarray] = field(default_factory=dict)  # stamp -> published fingertips (mm)
    frames: dict[int, str] = field(default_factory=dict)  # stamp -> published frame_id
    joints: set[int] = field(default_factory=set)
    worst_ms: float = 0.0
    worst_cpu_ms: float = 0.0  # (the executor thread's CPU time: BLAS runs on it, ros/blas.py)
    cut: int = 0


class CleanFrames:
    """What the kinds take from a bench besides :meth:`send`: the clean sequence's frames and
    strictly increasing stamps."""

    def __init__(self) -> None:
        self.out = Outcome()
        self._seq = 0
        self._stamp = time.time_ns()
        self.clean = [(_render(_pose(i), INTR, i), fingertips(MODEL, _pose(i))) for i in range(12)]

    def stamp(self) -> int:
        """The next stamp: the node's clock, strictly increasing."""
        self._stamp = max(self._stamp + 1_000_000, time.time_ns())
        return self._stamp

    def frame(self) -> tuple[np.ndarray, np.ndarray]:
        """The next clean frame: depth (mm) and its true fingertips (mm)."""
        self._seq += 1
        return self.clean[self._seq % len(self.clean)]

    def send(self, msg: Image | CompressedImage) -> int:
        """Give ``msg`` to the node; its stamp."""
        raise NotImplementedError

    def good(self, encoding: str = "16UC1") -> tuple[int, np.ndarray]:
        """The next clean frame sent: its stamp and true fingertips (mm)."""
        depth, tips = self.frame()
        return self.send(image(depth, self.stamp(), encoding)), tips


class Bench(CleanFrames):
    """The node under test (one per module), its inputs and what it publishes."""

    def __init__(self, ctx: Context, tmp: Path) -> None:
        super().__init__()
        self.rig = Rig(ctx, tmp, frame_budget_ms=DEFAULTS["frame_budget_ms"])
        self.node: TrackerNode = self.rig.node
        self.frame_ms: list[float] = []
        node = self.node
        warn, process = node._warn, node._process_pending

        def spy_warn(text: str) -> None:
            self.out.warnings.append(text)
            warn(text)

        def timed() -> None:
            t0, c0 = time.perf_counter(), time.thread_time()
            try:
                process()
            finally:
                ms = (time.perf_counter() - t0) * 1e3
                self.frame_ms.append(ms)
                self.out.worst_ms = max(self.out.worst_ms, ms)
                self.out.worst_cpu_ms = max(self.out.worst_cpu_ms, (time.thread_time() - c0) * 1e3)

        node._warn = spy_warn
        node._process_pending = timed
        for pub, sink in ((node._out.markers, self._markers), (node._out.joints, self._joints)):
            pub.publish = self._spy(pub.publish, sink)

    @staticmethod
    def _spy(publish: Callable, sink: Callable) -> Callable:
        def wrapped(msg) -> None:
            sink(msg)
            publish(msg)

        return wrapped

    def _markers(self, msg) -> None:
        if isinstance(msg, bytes):  # (the node publishes its fingertips serialised, SerialisedMarkers)
            msg = deserialize_message(msg, MarkerArray)
        tips = {m.id: m for m in msg.markers if m.ns == FINGERTIPS_NS and m.action == Marker.ADD}
        if len(tips) == 5:
            stamp = stamp_to_ns(tips[0].header.stamp)
            p = [tips[i].pose.position for i in range(5)]
            self.out.tips[stamp] = np.array([[q.x, q.y, q.z] for q in p]) * 1000.0
            self.out.frames[stamp] = tips[0].header.frame_id

    def _joints(self, msg) -> None:
        self.out.joints.add(stamp_to_ns(msg.header.stamp))

    # -- inputs ---------------------------------------------------------------------------
    def send(self, msg: Image | CompressedImage) -> int:
        """Into the image callback, as the executor would; returns the stamp."""
        before = self.node.stats.rejected
        self.node._on_image_message(msg)
        self.rig.executor.spin_once(timeout_sec=0.0)
        s = self.node.stats
        if s.rejected > before:
            self.out.rejected += s.rejected - before
            self.out.problems.append(s.last_problem)
        return stamp_to_ns(msg.header.stamp)

    def send_info(self, msg: CameraInfo) -> None:
        self.node._on_camera_info(msg)

    def set(self, **values) -> list[str]:
        """Set parameters; the reasons of those refused."""
        results = self.node.set_parameters([Parameter(k, value=v) for k, v in values.items()])
        return [r.reason for r in results if not r.successful]

    # -- checks ---------------------------------------------------------------------------
    def begin(self) -> None:
        self.out = Outcome()
        # (The rig's subscribers keep every message they receive; this bench reads its own spies.
        # Kept over the battery, those messages grew the process by several MB of small objects
        # between the node's chunks, which the memory bound then charged to the node.)
        for received in (self.rig.joints, self.rig.poses, self.rig.markers, self.rig.diagnostics):
            received.clear()
        self._cut0 = self.node.stats.cut
        sampler = getattr(self, "sampler", None)
        if sampler is not None:  # (each kind's row records its own peak)
            sampler.reset()

    def end(self) -> Outcome:
        self.out.cut = self.node.stats.cut - self._cut0
        return self.out

    def recover(self) -> float:
        """Good CameraInfo and default parameters back, then clean frames until one is tracked:
        its mean fingertip error (mm), inf when none of 5 is."""
        self.send_info(info())
        fixed = ("user_model_path", "input_transport", "auto_calibrate")
        changed = {k: v for k, v in DEFAULTS.items() if k not in fixed and self.node.get_parameter(k).value != v}
        if changed:
            self.set(**changed)
        for _ in range(5):
            stamp, truth = self.good()
            if stamp in self.out.tips:
                return float(np.linalg.norm(self.out.tips[stamp] - truth, axis=1).mean())
        return float("inf")


@dataclass(frozen=True)
class Kind:
    """One kind of bad input.

    ``expect``: ``reject`` (each bad frame rejected, nothing published for it), ``no_pose``
    (processed or rejected, no pose published for it), ``track`` (its poses right),
    ``right`` (processed, not rejected; the poses published for it right, none required),
    ``bounded`` (no claim on the output: the input is wrong in a way no check can see, e.g. a
    focal length 2x off; alive, bounded and recovers), ``refused`` (a parameter refused).
    ``reason``: words the reason must contain.  ``run`` feeds the input and returns the bad
    frames' stamps and ``(stamp, true tips)`` of frames that must be tracked right.
    """

    name: str
    group: str
    expect: str
    reason: str
    run: Callable[[Bench], tuple[list[int], list[tuple[int, np.ndarray]], list[str]]]
    xfail: str = ""


KINDS: list[Kind] = []


def kind(group: str, name: str, expect: str, reason: str = "", xfail: str = ""):
    def register(fn):
        KINDS.append(Kind(name, group, expect, reason, fn, xfail))
        return fn

    return register


def _bad(b: Bench, msgs: list) -> tuple[list[int], list, list[str]]:
    return [b.send(m) for m in msgs], [], []


def _raw(mutate: Callable[[Image], None], depth: np.ndarray | None = None, encoding: str = "16UC1"):
    """A kind whose clean frame is changed by ``mutate`` (fields of the Image)."""
    def run(b: Bench):
        d = b.frame()[0] if depth is None else depth
        msg = image(d, b.stamp(), encoding)
        mutate(msg)
        return _bad(b, [msg])

    return run


def _depth(make: Callable[[np.ndarray], np.ndarray], encoding: str = "16UC1"):
    """A kind whose depth is ``make(clean depth)``."""
    def run(b: Bench):
        msg = image(make(b.frame()[0].copy()), b.stamp(), encoding)
        return _bad(b, [msg])

    return run


def _tracked(make: Callable[[np.ndarray, int], Image]):
    """A kind of valid but unusual images of the clean hand: each must be tracked right."""
    def run(b: Bench):
        b.good()  # (on the track)
        out = []
        for _ in range(2):
            d, tips = b.frame()
            out.append((b.send(make(d, b.stamp())), tips))
        return [], out, []

    return run


def _setattr(name: str, value):
    return lambda m: setattr(m, name, value)


# -- raw images: encodings and layout ------------------------------------------------------
for enc in ("rgb8", "", "8UC1", "32FC3", "bgra16", "16SC1", "64FC1"):
    kind("image", f"encoding {enc!r}", "reject", "unsupported depth encoding")(_raw(_setattr("encoding", enc)))
kind("image", "encoding '16uc1' (lower case)", "track")(_tracked(lambda d, s: image(d, s, "16uc1")))
kind("image", "encoding mono16", "track")(_tracked(lambda d, s: image(d, s, "mono16")))
kind("image", "32FC1 metres", "track")(_tracked(lambda d, s: image(d, s, "32FC1")))
kind("image", "big-endian 16UC1", "track")(_tracked(lambda d, s: image(d, s, bigendian=True)))
kind("image", "big-endian 32FC1", "track")(_tracked(lambda d, s: image(d, s, "32FC1", bigendian=True)))
kind("image", "row padding 64 bytes", "track")(_tracked(lambda d, s: image(d, s, pad=64)))
kind("image", "odd step (1 byte of padding)", "track")(_tracked(lambda d, s: image(d, s, pad=1)))


def _extra(msg: Image) -> None:
    msg.data = bytes(msg.data) + bytes(1000)


kind("image", "data longer than the image", "track")(_tracked(lambda d, s: (lambda m: (_extra(m), m)[1])(image(d, s))))
kind("image", "step smaller than a row", "reject", "step 100 is smaller")(_raw(_setattr("step", 100)))
kind("image", "step 0", "reject", "step 0 is smaller")(_raw(_setattr("step", 0)))
kind("image", "data truncated to half", "reject", "truncated")(
    _raw(lambda m: setattr(m, "data", bytes(m.data)[: len(m.data) // 2]))
)
kind("image", "data one byte short", "reject", "truncated")(_raw(lambda m: setattr(m, "data", bytes(m.data)[:-1])))
kind("image", "data empty", "reject", "truncated")(_raw(_setattr("data", b"")))
kind("image", "width 0", "reject", "zero size")(_raw(_setattr("width", 0)))
kind("image", "height 0", "reject", "zero size")(_raw(_setattr("height", 0)))
kind("image", "width and height swapped", "reject", f"image is {H}x{W} but CameraInfo is {W}x{H}")(
    _raw(lambda m: (setattr(m, "width", H), setattr(m, "height", W), setattr(m, "step", 2 * H))))
kind("image", "half resolution", "reject", "but CameraInfo is")(
    lambda b: _bad(b, [image(b.frame()[0][::2, ::2].copy(), b.stamp())]))
kind("image", "declared 8192x8192, small data", "reject", "more than max_image_pixels")(
    _raw(lambda m: (setattr(m, "width", 8192), setattr(m, "height", 8192), setattr(m, "step", 16384))))
def _big_image(b: Bench):
    msg = image(np.zeros((1, 1), np.float32), b.stamp())
    msg.width, msg.height, msg.step = 2000, 2000, 4000
    msg.data = bytes(2000 * 4000)
    return _bad(b, [msg])


kind("image", "real 2000x2000 image (8 MB)", "reject", "more than max_image_pixels")(_big_image)
kind("image", "is_bigendian=7 on little-endian data", "no_pose")(_raw(_setattr("is_bigendian", 7)))
kind("image", "width 1", "reject", "but CameraInfo is")(lambda b: _bad(b, [image(np.full((H, 1), 400.0), b.stamp())]))
kind("image", "1x1 image", "reject", "but CameraInfo is")(lambda b: _bad(b, [image(np.full((1, 1), 400.0), b.stamp())]))

# -- depth values ---------------------------------------------------------------------------
kind("values", "all zeros", "no_pose", "no valid pixels")(_depth(np.zeros_like))
kind("values", "all NaN (32FC1)", "no_pose", "no valid pixels")(_depth(lambda d: np.full_like(d, np.nan), "32FC1"))
kind("values", "all +Inf (32FC1)", "no_pose", "no valid pixels")(_depth(lambda d: np.full_like(d, np.inf), "32FC1"))
kind("values", "all -Inf (32FC1)", "no_pose", "no valid pixels")(_depth(lambda d: np.full_like(d, -np.inf), "32FC1"))
kind("values", "negative depths (32FC1)", "no_pose", "no valid pixels")(_depth(lambda d: -d, "32FC1"))
kind("values", "float max (32FC1, overflows to Inf in mm)", "no_pose", "no valid pixels")(
    _depth(lambda d: np.where(d > 0, 3.4e41, 0.0), "32FC1"))
kind("values", "metres sent as 16UC1 (0-2)", "reject", "metres sent as 16UC1")(
    lambda b: _bad(b, [image(np.round(b.frame()[0] / 1000.0 * 3), b.stamp())]))
kind("values", "millimetres sent as 32FC1", "reject", "millimetres sent as 32FC1")(
    _depth(lambda d: d * 1000.0, "32FC1"))
kind("values", "1e30 m (32FC1)", "reject", "millimetres sent as 32FC1")(
    _depth(lambda d: np.where(d > 0, 1e33, 0.0), "32FC1")
)
kind("values", "tiny 1e-30 m (32FC1)", "no_pose")(_depth(lambda d: np.where(d > 0, 1e-27, 0.0), "32FC1"))
kind("values", "saturated 65535", "no_pose")(_depth(lambda d: np.full_like(d, 65535.0)))
kind("values", "one valid pixel", "no_pose")(_depth(lambda d: np.pad(np.full((1, 1), 420.0), ((0, H - 1), (0, W - 1)))))
kind("values", "hand 3 m away (beyond far_mm)", "no_pose")(_depth(lambda d: np.where(d > 0, d + 2600.0, 0.0)))
kind("values", "hand 50 mm away (before near_mm)", "no_pose")(_depth(lambda d: np.where(d > 0, d - 370.0, 0.0)))


def _rows_inf(d: np.ndarray) -> np.ndarray:
    d[::3] = np.inf
    return d


def _nan_some(d: np.ndarray) -> np.ndarray:
    d[np.random.default_rng(1).random(d.shape) < 0.05] = np.nan
    return d


def _salt(d: np.ndarray) -> np.ndarray:
    noisy = np.random.default_rng(2).random(d.shape) < 0.02
    d[noisy] = np.random.default_rng(3).uniform(300, 900, d.shape)[noisy]
    return d


# (Inf pixels are invalid: the frame is processed on the rows left, and a pose published for it
# must be right; whether a hand with every third row missing is reported is the hand check's
# decision, which the state the battery leaves the track in made marginal at 640x480.)
kind("values", "every third row Inf (32FC1)", "right")(_tracked(lambda d, s: image(_rows_inf(d.copy()), s, "32FC1")))
kind("values", "5% NaN pixels (32FC1)", "track")(_tracked(lambda d, s: image(_nan_some(d.copy()), s, "32FC1")))
kind("values", "2% salt noise", "track")(_tracked(lambda d, s: image(_salt(d.copy()), s)))
kind("values", "flat wall at 500 mm", "no_pose")(_depth(lambda d: np.full_like(d, 500.0)))
kind("values", "uniform noise 200-1500 mm", "no_pose")(
    _depth(lambda d: np.random.default_rng(4).uniform(200, 1500, d.shape)))


def _noise_patch(b: Bench):
    b.good()
    b.good()  # tracking
    out = []
    for k in range(3):
        d = np.zeros((H, W), np.float32)
        v0, u0 = H // 2 - 60, W // 2 - 60
        d[v0 : v0 + 120, u0 : u0 + 120] = np.random.default_rng(10 + k).uniform(350, 500, (120, 120))
        out.append(b.send(image(d, b.stamp())))
    return out, [], []


kind("values", "120x120 noise patch while tracking", "no_pose")(_noise_patch)

# -- stamps, frame ids, rates ---------------------------------------------------------------


def _stamped(offset_ns: Callable[[Bench], int], frame: str = FRAME):
    def run(b: Bench):
        d = b.frame()[0]
        return _bad(b, [image(d, offset_ns(b), frame=frame)])

    return run


kind("stamps", "stamp 1 s backwards", "reject", "went backwards")(_stamped(lambda b: b._stamp - 10**9))
kind("stamps", "stamp 1 ns backwards", "reject", "went backwards")(_stamped(lambda b: b._stamp - 1))
kind("stamps", "stamp 0", "reject", "went backwards")(_stamped(lambda b: 0))
kind("stamps", "stamp a year behind", "reject", "went backwards")(_stamped(lambda b: b._stamp - 365 * 86400 * 10**9))


def _future(years: float):
    def run(b: Bench):
        d, tips = b.frame()
        stamp = b.send(image(d, int(time.time_ns() + years * 365 * 86400 * 10**9)))
        return [], [(stamp, tips)], []

    return run


kind("stamps", "stamp a year ahead", "track", "ahead of the node's clock")(_future(1.0))
kind("stamps", "stamp in 2038 (sec = 2^31 - 1)", "track", "ahead of the node's clock")(
    lambda b: ([], [(b.send(image(b.frame()[0], (2**31 - 1) * 10**9)), b.clean[b._seq % 12][1])], []))


def _diagnostics_with_future_stamps(b: Bench):
    """/diagnostics after frames stamped a year ahead: no absurd latency (it was -3e10 ms), the
    worst frame and the cut frames reported."""
    published = []
    pub = b.node._diag_pub
    publish = pub.publish
    pub.publish = lambda msg: (published.append(msg), publish(msg))
    try:
        b.node._publish_diagnostics()  # (a fresh window)
        tracked = []
        for _ in range(2):
            d, tips = b.frame()
            tracked.append((b.send(image(d, time.time_ns() + 365 * 86400 * 10**9)), tips))
        b.node._publish_diagnostics()
    finally:
        pub.publish = publish
    # The node's own 1 Hz timer may publish (and start a new window) between the frames and the
    # call above: judge the window that holds the processed frames (output rate above 0).
    windows = [{kv.key: kv.value for kv in msg.status[0].values} for msg in published[1:]]
    with_frames = [w for w in windows if float(w.get("output_rate_hz", "0")) > 0]
    values = with_frames[-1] if with_frames else windows[-1]
    problems = []
    if values.get("latency_ms") != "nan":
        problems.append(f"latency_ms {values.get('latency_ms')}")
    if not float(values.get("worst_frame_ms", "0")) > 0 or "frames_cut" not in values:
        problems.append(f"no worst_frame_ms / frames_cut in {sorted(values)}")
    return [], tracked[:1], problems


kind("stamps", "/diagnostics after stamps a year ahead", "track", "ahead of the node's clock")(
    _diagnostics_with_future_stamps
)


def _repeat_stamp(b: Bench):
    stamp, _ = b.good()
    d, tips = b.frame()
    return [], [(b.send(image(d, stamp)), tips)], []


kind("stamps", "the same stamp twice", "track")(_repeat_stamp)
def _big_nanosec(b: Bench):
    b.good()
    d, tips = b.frame()
    msg = image(d, b.stamp())
    msg.header.stamp.sec -= 1
    msg.header.stamp.nanosec += 10**9
    return [], [(b.send(msg), tips)], []


kind("stamps", "nanosec above 1e9", "track")(_big_nanosec)


def _frame_id(frame: str):
    def run(b: Bench):
        b.good()
        d, tips = b.frame()
        stamp = b.send(image(d, b.stamp(), frame=frame))
        want = frame or DEFAULT_FRAME_ID
        got = b.out.frames.get(stamp)
        problems = [] if got in (None, want) else [f"outputs in {got!r}, expected {want!r}"]
        return [], [(stamp, tips)], problems

    return run


kind("stamps", "empty frame_id", "track", "without header.frame_id")(_frame_id(""))
kind("stamps", "frame_id with spaces and umlauts", "track")(_frame_id("kamera tiefe ü"))
kind("stamps", "frame_id of 10 000 characters", "track")(_frame_id("f" * 10_000))


def _burst_then_30hz(b: Bench):
    """200 Hz for 20 frames, then 30 Hz: no frames counted missed at 30 Hz once the burst is
    forgotten (the camera period was the shortest interval ever seen: 6 missed per frame)."""
    t = b.stamp()
    d = b.frame()[0]
    for _ in range(20):
        t += 5_000_000
        b.send(image(d, t))
    missed0 = None
    for k in range(30):
        t += 33_333_333
        b.send(image(b.frame()[0], t))
        if k == 19:
            missed0 = b.node.stats.missed
    b._stamp = max(b._stamp, t)
    grew = b.node.stats.missed - missed0
    problems = [f"{grew} frames counted missed at 30 Hz"] if grew else []
    return [], [], problems


kind("stamps", "200 Hz burst, then 30 Hz", "bounded")(_burst_then_30hz)


def _pause(b: Bench):
    b.good()
    missed = b.node.stats.missed
    d, tips = b.frame()
    b._stamp += 5 * 10**9
    stamp = b.send(image(d, b._stamp))
    return [], [(stamp, tips)], ([] if b.node.stats.missed == missed else ["a pause counted as missed frames"])


kind("stamps", "a 5 s pause", "track")(_pause)


def _one_missed(b: Bench):
    """30 Hz with one frame left out: exactly one counted missed."""
    t = b.stamp()
    for _ in range(5):
        t += 33_333_333
        b.send(image(b.frame()[0], t))
    missed = b.node.stats.missed
    t += 2 * 33_333_333
    b.send(image(b.frame()[0], t))
    b._stamp = max(b._stamp, t)
    n = b.node.stats.missed - missed
    return [], [], ([] if n == 1 else [f"{n} counted missed for one"])


kind("stamps", "one frame missing at 30 Hz", "bounded")(_one_missed)


def _jitter(b: Bench):
    t = b.stamp()
    missed = b.node.stats.missed
    rng = np.random.default_rng(5)
    for _ in range(10):
        t += int(33_333_333 * rng.uniform(0.7, 1.3))
        b.send(image(b.frame()[0], t))
    b._stamp = max(b._stamp, t)
    n = b.node.stats.missed - missed
    return [], [], ([] if n == 0 else [f"{n} counted missed under +-30% jitter"])


kind("stamps", "stamps with +-30% jitter", "bounded")(_jitter)

# -- CameraInfo -----------------------------------------------------------------------------


def _info_kind(msg: Callable[[], CameraInfo]):
    def run(b: Bench):
        b.send_info(msg())
        return _bad(b, [image(b.frame()[0], b.stamp())])

    return run


def _k(fx: float, fy: float | None = None, cx: float | None = None, cy: float | None = None) -> list[float]:
    cx, cy = INTR.cx if cx is None else cx, INTR.cy if cy is None else cy
    return [fx, 0.0, cx, 0.0, fx if fy is None else fy, cy, 0, 0, 1]


F = INTR.fx
kind("camera_info", "K all zeros", "reject", "K is all zeros")(_info_kind(lambda: info(k=[0.0] * 9)))
kind("camera_info", "K with NaN", "reject", "NaN or Inf")(_info_kind(lambda: info(k=_k(np.nan))))
kind("camera_info", "K with Inf", "reject", "NaN or Inf")(_info_kind(lambda: info(k=_k(np.inf))))
kind("camera_info", "fx = 1e9", "reject", "fx=1e+09 px is implausible")(_info_kind(lambda: info(k=_k(1e9))))
kind("camera_info", "fx = 1e-6", "reject", "fx=1e-06 px is implausible")(_info_kind(lambda: info(k=_k(1e-6))))
kind("camera_info", "fx 60x too large", "reject", "is implausible")(_info_kind(lambda: info(k=_k(60 * F))))
kind("camera_info", "fx 20x too small", "reject", "is implausible")(_info_kind(lambda: info(k=_k(F / 20))))
kind("camera_info", "fx negative", "reject", "is implausible")(_info_kind(lambda: info(k=_k(-F))))
kind("camera_info", "fy 4x fx", "reject", "differ by more than")(_info_kind(lambda: info(k=_k(F, 4 * F))))
kind("camera_info", "cx beyond the image", "reject", "principal point")(_info_kind(lambda: info(k=_k(F, cx=3.0 * W))))
kind("camera_info", "cy negative", "reject", "principal point")(_info_kind(lambda: info(k=_k(F, cy=-10.0))))
kind("camera_info", "CameraInfo width 0", "reject", "zero image size")(_info_kind(lambda: info(width=0)))
kind("camera_info", "K for the other resolution", "reject", "but CameraInfo is")(_info_kind(lambda: info(INTR_OTHER)))
kind("camera_info", "partial ROI", "reject", "ROI")(
    _info_kind(lambda: info(roi=RegionOfInterest(x_offset=10, y_offset=0, width=100, height=100))))
kind("camera_info", "binning 1000", "reject", "binning 1000x1000 leaves no pixels")(
    _info_kind(lambda: info(binning_x=1000, binning_y=1000)))


def _with_info(msg: Callable[[], CameraInfo], expect_ok: bool = True):
    """Valid but unusual CameraInfo: the hand is tracked right with it."""
    def run(b: Bench):
        b.send_info(msg())
        b.good()
        d, tips = b.frame()
        return [], [(b.send(image(d, b.stamp())), tips)], []

    return run


kind("camera_info", "full ROI given explicitly", "track")(
    _with_info(lambda: info(roi=RegionOfInterest(x_offset=0, y_offset=0, width=W, height=H))))
kind("camera_info", "binning 0", "track")(_with_info(lambda: info(binning_x=0, binning_y=0)))
kind("camera_info", "binning 2 of a double-size K", "track")(_with_info(lambda: info(
    Intrinsics(fx=2 * F, fy=2 * F, cx=2 * INTR.cx + 0.5, cy=2 * INTR.cy + 0.5, width=2 * W, height=2 * H),
    binning_x=2, binning_y=2)))
kind("camera_info", "skew and K[8] != 1 (ignored)", "track")(_with_info(lambda: info(
    k=[F, 3.0, INTR.cx, 0.0, F, INTR.cy, 0.0, 0.0, 2.0])))
kind("camera_info", "distortion with NaN (ignored)", "track")(_with_info(lambda: info(d=[np.nan] * 5)))
kind("camera_info", "principal point 1 px off every frame", "track")(
    _with_info(lambda: info(k=_k(F, cx=INTR.cx + 1.0))))
# fx 10x: the clean frame's wall then measures a hand's area in mm but fills the view: no hand,
# without a search (handfind.MAX_VIEW_SHARE; before, 1-6 s on data at the cap).
kind("camera_info", "fx 10x too large (plausible)", "no_pose")(_info_kind(lambda: info(k=_k(10 * F))))
kind("camera_info", "fx 2x too large (plausible)", "bounded")(_info_kind(lambda: info(k=_k(2 * F))))
kind("camera_info", "fx 3x too small (plausible)", "bounded")(_info_kind(lambda: info(k=_k(F / 3))))


def _alternate(b: Bench):
    """Frames alternating between the two resolutions, each with its CameraInfo: every pose
    published is right (a resolution change resets the track)."""
    out = []
    for k in range(6):
        intr = INTR_OTHER if k % 2 == 0 else INTR
        th = _pose(b._seq + k)
        b.send_info(info(intr))
        out.append((b.send(image(_render(th, intr, 100 + k), b.stamp())), fingertips(MODEL, th)))
    return [], out, []


kind("camera_info", f"resolution alternating {W}x{H} / {OTHER[0]}x{OTHER[1]}", "track")(_alternate)

# -- compressedDepth ------------------------------------------------------------------------


def _comp(make: Callable[[np.ndarray], tuple[str, bytes]]):
    def run(b: Bench):
        fmt, data = make(b.frame()[0])
        return _bad(b, [compressed(fmt, data, b.stamp())])

    return run


def _comp_tracked(encoding: str, codec: str, sparse: bool = False):
    def run(b: Bench):
        b.good()
        out = []
        for _ in range(2):
            d, tips = b.frame()
            if sparse:
                d = np.where(d < 600.0, d, 0.0)  # (the renders have a far background)
                zeros = 1.0 - np.count_nonzero(d) / d.size
                assert zeros > 0.85, zeros
            fmt, data = encode_compressed_depth(d, encoding, codec)
            out.append((b.send(compressed(fmt, data, b.stamp())), tips))
        return [], out, []

    return run


def _enc(codec: str = "png", encoding: str = "16UC1"):
    return lambda d: encode_compressed_depth(d, encoding, codec)


def _mut(codec: str, change: Callable[[bytes], bytes], encoding: str = "16UC1", fmt: str | None = None):
    def make(d: np.ndarray) -> tuple[str, bytes]:
        f, data = encode_compressed_depth(d, encoding, codec)
        return (fmt if fmt is not None else f), change(data)

    return _comp(make)


kind("compressed", "png 16UC1", "track")(_comp_tracked("16UC1", "png"))
kind("compressed", "png 32FC1", "track")(_comp_tracked("32FC1", "png"))
kind("compressed", "rvl 16UC1, sparse (hand on an empty background)", "track")(_comp_tracked("16UC1", "rvl", True))
kind("compressed", "rvl 32FC1", "track")(_comp_tracked("32FC1", "rvl"))
def _rvl_dense(b: Bench):
    b.good()
    d, tips = b.frame()
    fmt, data = encode_compressed_depth(np.where(d > 0, d, 900.0), "16UC1", "rvl")
    return [], [(b.send(compressed(fmt, data, b.stamp())), tips)], []


kind("compressed", "rvl dense (hand before a wall)", "track")(_rvl_dense)
kind("compressed", "png truncated to half", "reject", "corrupt or truncated")(_mut("png", lambda x: x[: len(x) // 2]))
kind("compressed", "png without IHDR", "reject", "truncated (no complete IHDR")(_mut("png", lambda x: x[:24]))
kind("compressed", "png bad signature", "reject", "not a PNG")(_mut("png", lambda x: x[:12] + b"JFIF" + x[16:]))
kind("compressed", "png IDAT corrupted", "reject", "corrupt or truncated")(
    _mut("png", lambda x: x[:60] + bytes(len(x) - 80) + x[-20:]))
kind("compressed", "png 8192x8192 of zeros (130 kB)", "reject", "more than max_image_pixels")(
    lambda b: _bad(b, [compressed("16UC1; compressedDepth png", HEADER + png_of_zeros(8192, 8192), b.stamp())]))
kind("compressed", "png IHDR 70000x70000", "reject", "more than max_image_pixels")(_mut(
    "png", lambda x: x[:28] + struct.pack(">II", 70000, 70000) + x[36:]))
kind("compressed", "png 8-bit", "reject", "bit depth 8")(lambda b: _bad(b, [compressed(
    "16UC1; compressedDepth png", HEADER + __import__("cv2").imencode(".png", np.zeros((H, W), np.uint8))[1].tobytes(),
    b.stamp())]))
kind("compressed", "png 16-bit colour", "reject", "colour type 2")(lambda b: _bad(b, [compressed(
    "16UC1; compressedDepth png",
    HEADER + __import__("cv2").imencode(".png", np.zeros((H, W, 3), np.uint16))[1].tobytes(), b.stamp())]))
kind("compressed", "png of half the resolution", "reject", "but CameraInfo is")(
    _comp(lambda d: _enc()(d[::2, ::2].copy()))
)
kind("compressed", "rvl truncated", "reject", "truncated")(_mut("rvl", lambda x: x[: len(x) - 64]))
kind("compressed", "rvl length not a multiple of 4", "reject", "multiple of 4")(_mut("rvl", lambda x: x[:-1]))
kind("compressed", "rvl with data after the image", "reject", "follow the image")(
    _mut("rvl", lambda x: x + rvl_encode(np.arange(1, 200, dtype=np.uint16))))
kind("compressed", "rvl size 0x5", "reject", "zero size")(
    _mut("rvl", lambda x: x[:12] + struct.pack("<II", 0, 5) + x[20:])
)
kind("compressed", "rvl size 9000x9000", "reject", "more than max_image_pixels")(
    _mut("rvl", lambda x: x[:12] + struct.pack("<II", 9000, 9000) + x[20:]))
kind("compressed", "rvl size 2^32-1 x 2^32-1", "reject", "more than max_image_pixels")(
    _mut("rvl", lambda x: x[:12] + struct.pack("<II", 2**32 - 1, 2**32 - 1) + x[20:]))
kind("compressed", "rvl rows and columns swapped", "reject", f"image is {H}x{W} but CameraInfo")(
    _mut("rvl", lambda x: x[:12] + struct.pack("<II", H, W) + x[20:]))
kind("compressed", "rvl size one row short", "reject", "RVL data is corrupt")(
    _mut("rvl", lambda x: x[:12] + struct.pack("<II", W, H - 1) + x[20:]))
kind("compressed", "rvl of random words", "reject", "RVL data is")(
    _mut("rvl", lambda x: x[:20] + np.random.default_rng(6).integers(0, 256, len(x) - 20, dtype=np.uint8).tobytes()))
kind("compressed", "rvl of 4 MB of random words", "reject", "longer than any RVL stream")(
    _mut("rvl", lambda x: x[:20] + np.random.default_rng(7).integers(0, 256, 4 * 2**20, dtype=np.uint8).tobytes()))
kind("compressed", "compressionFormat -1", "reject", "compressionFormat -1")(
    _mut("png", lambda x: struct.pack("<i", -1) + x[4:])
)
kind("compressed", "header only", "reject", "not more than the 12-byte header")(_mut("png", lambda x: x[:12]))
kind("compressed", "empty data", "reject", "not more than the 12-byte header")(_mut("png", lambda x: b""))
kind("compressed", "format 'compressed jpeg'", "reject", "unsupported compressed depth format")(
    _mut("png", lambda x: x, fmt="16UC1; compressed jpeg"))
kind("compressed", "format 'bgr8; compressedDepth png'", "reject", "unsupported encoding")(
    _mut("png", lambda x: x, fmt="bgr8; compressedDepth png"))
kind("compressed", "empty format", "reject", "unsupported encoding")(_mut("png", lambda x: x, fmt=""))
kind("compressed", "32FC1 with A = 0", "reject", "quantisation")(
    _mut("png", lambda x: x[:4] + struct.pack("<ff", 0.0, 0.0) + x[12:], "32FC1"))
kind("compressed", "32FC1 with A = NaN", "reject", "quantisation")(
    _mut("png", lambda x: x[:4] + struct.pack("<ff", np.nan, 1.0) + x[12:], "32FC1"))
kind("compressed", "16UC1 payload declared 32FC1", "reject", "quantisation")(
    _mut("png", lambda x: x, "16UC1", fmt="32FC1; compressedDepth png"))
kind("compressed", "metres as 16UC1, png", "reject", "metres sent as 16UC1")(
    _comp(lambda d: _enc()(np.round(d / 1000.0 * 3)))
)

# -- runtime parameters ---------------------------------------------------------------------


def _params(values: dict, frames: int = 3):
    """Accepted parameter values that make frames dearer: tracked, within the budget's bounds."""
    def run(b: Bench):
        refused = b.set(**values)
        out = []
        for _ in range(frames):
            d, tips = b.frame()
            out.append((b.send(image(np.where(d > 0, d, 900.0).astype(np.float32), b.stamp())), tips))
        return [], [], [f"refused: {r}" for r in refused]

    return run


kind("parameters", "roi_radius_mm at its maximum (1000)", "bounded")(_params({"roi_radius_mm": 1000.0}))
kind("parameters", "iterations at its maximum (200)", "bounded")(_params({"iterations": 200}))
kind("parameters", "init_hypotheses at its maximum (256)", "bounded")(_params({"init_hypotheses": 256}))
kind("parameters", "max_width_px 4096, min_quad_px 2", "bounded")(_params({"max_width_px": 4096, "min_quad_px": 2}))
kind("parameters", "quadtree_threshold_mm 1, min_quad_px 2", "bounded")(
    _params({"quadtree_threshold_mm": 1.0, "min_quad_px": 2}))
kind("parameters", "refine_iterations 50, median_kernel 5", "bounded")(
    _params({"refine_iterations": 50, "median_kernel": 5})
)
kind("parameters", "far_mm 10000 with a wall", "bounded")(_params({"far_mm": 10000.0, "roi_radius_mm": 1000.0}))


def _budget(b: Bench):
    b.set(frame_budget_ms=10.0)
    b.node._tracker.reset()
    b.good()
    b.good()
    cut = b.node.stats.cut - b._cut0
    return [], [], ([] if cut else ["no frame counted cut with a 10 ms budget"])


kind("parameters", "frame_budget_ms 10 (frames over it counted)", "bounded", "over its budget")(_budget)


def _refused(values: dict):
    def run(b: Bench):
        reasons = b.set(**values)
        b.out.warnings += reasons
        return [], [], ([] if reasons else ["accepted"])

    return run


kind("parameters", "near_mm above far_mm", "refused", "need 0 < near_mm < far_mm")(_refused({"near_mm": 2000.0}))
kind("parameters", "near_mm 'abc' (string)", "refused", "Wrong parameter type")(_refused({"near_mm": "abc"}))
kind("parameters", "iterations 7.5 (double)", "refused", "Wrong parameter type")(_refused({"iterations": 7.5}))
kind("parameters", "handedness 'up'", "refused", "must be one of right, left")(_refused({"handedness": "up"}))
kind("parameters", "min_quad_px 3", "refused", "min_quad_px must be 2, 4 or 8")(_refused({"min_quad_px": 3}))
kind("parameters", "roi_radius_mm beyond its range", "refused", "")(_refused({"roi_radius_mm": 1e6}))
kind("parameters", "input_transport at run time (read-only)", "refused", "read-only")(
    _refused({"input_transport": "compressedDepth"}))


def _max_pixels(b: Bench):
    b.set(max_image_pixels=10_000)
    return _bad(b, [image(b.frame()[0], b.stamp())])


kind("parameters", "max_image_pixels 10000", "reject", "more than max_image_pixels = 10000")(_max_pixels)

# -- start-up parameters --------------------------------------------------------------------


def _startup(arg: str, words: str):
    def run(b: Bench):
        try:
            node = TrackerNode(context=b.node.context, namespace=f"/s{uuid.uuid4().hex[:8]}",
                               cli_args=["--ros-args", "-p", arg, "-p", "auto_calibrate:=false"])
        except (InputError, rclpy.exceptions.InvalidParameterValueException) as err:
            text = str(err)
            b.out.warnings.append(text)
            return [], [], ([] if "\n" not in text else ["more than one line"])
        node.destroy_node()
        return [], [], ["started"]

    kind("startup", f"-p {arg}", "refused", words)(run)


_startup("near_mm:=abc", "parameter near_mm must be a double, got string 'abc'")
_startup("far_mm:=800", "parameter far_mm must be a double (write 800.0), got integer '800'")
_startup("iterations:=7.5", "parameter iterations must be an integer, got double '7.5'")
_startup("handedness:=3", "parameter handedness must be a string")
_startup("debug_image:=maybe", "parameter debug_image must be a boolean")
_startup("max_image_pixels:=1e6", "parameter max_image_pixels must be an integer")
_startup("input_transport:=jpeg", "input_transport must be one of raw, compressedDepth")
_startup("near_mm:=-5.0", "near_mm")
_startup("calibration_frames:=9", "calibration_frames")


# -- the tests ------------------------------------------------------------------------------
RESULTS: list[dict] = []


@pytest.fixture(scope="module")
def bench(tmp_path_factory) -> Iterator[Bench]:
    ctx = Context()
    rclpy.init(context=ctx)
    b = Bench(ctx, tmp_path_factory.mktemp("bounded"))
    sampler = RssSampler()
    try:
        b.send_info(info())
        for _ in range(40):  # steady tracking: the reference for time and memory
            b.good()
        b.frame_ms.clear()
        sampler.reset()
        for _ in range(40):
            b.good()
        b.steady_ms = max(b.frame_ms)
        b.steady_rss = sampler.reset()
        b.steady_trims = b.node._heap.trims
        b.sampler = sampler
        b.frame_ms.clear()
        yield b
    finally:
        sampler.close()
        b.rig.close()
        rclpy.try_shutdown(context=ctx)


def _check(b: Bench, k: Kind) -> dict:
    b.begin()
    bad, tracked, problems = k.run(b)
    out = b.end()
    bad_ms, out.worst_ms = out.worst_ms, 0.0
    bad_cpu_ms, out.worst_cpu_ms = out.worst_cpu_ms, 0.0
    problems = list(problems)
    reasons = out.problems + out.warnings
    if k.expect == "reject" and out.rejected < len(bad):
        problems.append(f"{len(bad) - out.rejected} of {len(bad)} frames not rejected")
    if k.reason and not any(k.reason in r for r in reasons):
        problems.append(f"no reason with {k.reason!r}")
    if any("internal error" in r for r in reasons):
        problems.append("internal error")
    wrong = [s for s in bad if s in out.tips or s in out.joints]
    if wrong and k.expect in ("reject", "no_pose"):
        problems.append(f"{len(wrong)} poses published for it")
    errors = []
    for stamp, truth in tracked:
        if stamp in out.tips:
            errors.append(float(np.linalg.norm(out.tips[stamp] - truth, axis=1).mean()))
    if k.expect == "track" and not errors:
        problems.append("nothing tracked")
    if k.expect in ("track", "right") and errors and max(errors) > TOL_MM:
        problems.append(f"a pose {max(errors):.0f} mm off")
    if k.expect == "right" and out.rejected:
        problems.append(f"{out.rejected} frames rejected")
    alive = b.node.context.ok()
    recovered_mm = b.recover()
    if not recovered_mm <= TOL_MM:
        problems.append(f"clean frame afterwards: {recovered_mm:.0f} mm")
    if not alive:
        problems.append("node dead")
    refused = k.expect == "refused" and any(k.reason in r for r in reasons)
    observed = ", ".join(
        (["refused"] if refused else [f"{out.rejected} rejected" if out.rejected else "processed"])
        + ([f"tracked {max(errors):.0f} mm"] if errors else [])
        + ([f"{out.cut} cut"] if out.cut else [])
        + ([f"worst {bad_ms:.0f} ms"] if bad else [])
    )
    reason = next((r for r in reasons if k.reason and k.reason in r), reasons[0] if reasons else "")
    row = dict(size=_SIZE, kind=k.name, group=k.group, expected=k.expect + (f": {k.reason}" if k.reason else ""),
               observed=observed, reason=reason[:160], problems=problems, worst_ms=round(bad_ms, 1),
               worst_cpu_ms=round(bad_cpu_ms, 1), recover_ms=round(out.worst_ms, 1),
               recover_cpu_ms=round(out.worst_cpu_ms, 1),
               rss_mb=round(b.sampler.peak, 1), recovered_mm=round(recovered_mm, 1), xfail=bool(k.xfail))
    RESULTS.append(row)
    if RECORD:
        with open(RECORD, "a") as f:
            f.write(json.dumps(row) + "\n")
    return row


@pytest.mark.parametrize(
    "k",
    [pytest.param(k, id=f"{k.group}: {k.name}",
                  marks=[pytest.mark.xfail(strict=False, reason=k.xfail)] if k.xfail else []) for k in KINDS],
)
def test_bad_input(bench: Bench, k: Kind) -> None:
    row = _check(bench, k)
    assert not row["problems"], row


def test_the_battery_has_over_100_kinds() -> None:
    assert len(KINDS) >= 100 and len({k.name for k in KINDS}) == len(KINDS)


def test_battery_memory_and_time(bench: Bench) -> None:
    """After the battery: the worst frame and peak memory against steady tracking (recorded),
    bounds that the unbounded faults of issue 50 broke (frames of 4-17 s, 12-50 initialisations
    long; +0.8-1.1 GB)."""
    if not RESULTS:
        pytest.skip("the battery did not run")
    for _ in range(20):
        bench.good()
    peak = max([r["rss_mb"] for r in RESULTS] + [bench.sampler.peak])
    after = rss_mb()
    try:  # what of it is free heap that glibc still keeps
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
        trimmed = rss_mb()
    except (OSError, AttributeError):
        trimmed = after
    worst = max(RESULTS, key=lambda r: r["worst_ms"])
    failed = [r["kind"] for r in RESULTS if r["problems"] and not r["xfail"]]
    print(f"{_SIZE}: {len(RESULTS)} kinds, {len(failed)} failed; steady tracking: worst frame "
          f"{bench.steady_ms:.0f} ms, peak RSS {bench.steady_rss:.0f} MB; battery: worst frame "
          f"{worst['worst_ms']:.0f} ms ({worst['kind']}), peak RSS {peak:.0f} MB "
          f"(+{peak - bench.steady_rss:.0f}), after {after:.0f} MB (+{after - bench.steady_rss:.0f}; "
          f"+{trimmed - bench.steady_rss:.0f} after malloc_trim; the node trimmed {bench.node._heap.trims} times, "
          f"{bench.steady_trims} in the 80 frames of steady tracking)")
    if RECORD:
        with open(RECORD, "a") as f:
            f.write(json.dumps(dict(summary=_SIZE, steady_ms=bench.steady_ms, steady_rss=bench.steady_rss,
                                    peak_rss=peak, after_rss=after, trimmed_rss=trimmed, worst=worst,
                                    blas_threads=blas_threads())) + "\n")
    assert peak - bench.steady_rss < 50.0
    # The free heap of the battery's dearest frames is given back (ros/heap.py; without it -2 to
    # +33 MB stayed).  This is the test process, whose own allocations share and fragment the
    # node's heap: +5 to +14 MB at 640x480 with the node's share +0 to +2 (after a final trim).
    # The 10 MB is a bound on the node's process: test_ros_node_memory measures it
    # there.  (Before the ~/calibrate test below, whose history of frames the node keeps.)
    assert after - bench.steady_rss < 20.0
    # No bad input costs more than a small factor of a clean frame's initialisation (the clean
    # frames after each kind, measured in the same run: the machine's load scales both).  A frame
    # runs its whole search, never cut (issue 45); the dearest are those that start a new track
    # (a resolution or intrinsics change).
    init_ms = max(r["recover_ms"] for r in RESULTS)
    assert worst["worst_ms"] <= 8.0 * init_ms, (worst, init_ms)


def test_the_node_tracks_on_one_blas_thread(bench: Bench) -> None:
    """The node set every OpenBLAS to one thread (ros/blas.py: a product split over busy cores
    waits for the slowest; a frame of ``min_quad_px`` 2 at 640x480 took 3-4x the CPU time)."""
    if any(os.environ.get(var) for var in THREADS_ENV):
        pytest.skip("the environment chooses the BLAS threads")
    assert bench.node._blas_threads == blas_threads()
    assert all(n == 1 for n in blas_threads().values()), blas_threads()


def test_every_concurrent_calibrate_call_is_answered(bench: Bench, monkeypatch: pytest.MonkeyPatch) -> None:
    """50 ~/calibrate calls at once while a fit runs: the fit's call gets its answer, every other
    one "busy" at once; all 50 within 2 s of the fit's end."""
    fit_s = 1.0

    def slow_refusal(*args, **kwargs):
        time.sleep(fit_s)
        raise CalibrationError("stand-in fit")

    monkeypatch.setattr(calibration_service, "calibrate", slow_refusal)
    monkeypatch.setattr(calibration_service, "FIT_IN_PROCESS", False)
    t = bench.stamp()
    for i in range(14):  # a history to fit on: an open hand, a frame every 70 ms
        t += 70_000_000
        bench.send(image(_render(rest_pose((0.0, 20.0, 430.0)), INTR, i), t))
    bench._stamp = max(bench._stamp, t)
    rig = bench.rig
    clients = [rig.io.create_client(Trigger, f"{rig.ns}/hand_sog_tracker/calibrate") for _ in range(50)]
    assert rig.spin_until(lambda: all(c.service_is_ready() for c in clients), 20.0)
    t0 = time.monotonic()
    futures = [c.call_async(Trigger.Request()) for c in clients]
    answered_at: dict[int, float] = {}

    def done() -> bool:
        for i, f in enumerate(futures):
            if f.done() and i not in answered_at:
                answered_at[i] = time.monotonic() - t0
        return len(answered_at) == len(futures)

    rig.spin_until(done, fit_s + 10.0)
    answers = [f.result().message for f in futures if f.done()]
    print(sorted(set(answers)))
    busy = sum(a.startswith("busy: a calibration is running") for a in answers)
    print(f"{len(answers)} of {len(futures)} answered, {busy} busy, last after {max(answered_at.values()):.2f} s")
    for c in clients:
        rig.io.destroy_client(c)
    assert len(answers) == 50
    assert busy == 49 and sum("stand-in fit" in a for a in answers) == 1
    assert max(answered_at.values()) < fit_s + 2.0
