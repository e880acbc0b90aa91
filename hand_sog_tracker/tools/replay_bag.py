"""``replay_bag``: publish a bag's topics live, a stand-in for ``ros2 bag play``.

One job: the ``replay_bag`` command; kept together because the message conversion and
:class:`BagPublisher` exist only for its replay loop.

Usage::

    replay_bag BAG [--rate R] [--loop] [--start-offset S] [--topics T [T ...]]
                   [--domain-id N] [--wait-for-subscribers S] [--qos-depth N]
                   [--decompress-depth]

Reads the bag with ``rosbags`` (rosbag2 sqlite3/mcap, ROS 1) and publishes
every selected topic with rclpy at the recorded rate:

* rosbag2 (CDR) messages are published as the recorded serialized bytes
  (rclpy's raw publishing), with a publisher of the message's rclpy type;
* ROS 1 messages are deserialised and copied field by field into the rclpy
  message of the same name (``seq`` dropped, ``K`` -> ``k`` ...).

Topics whose message type has no Python package here are skipped with a
warning (an error if named with ``--topics``).

Compressed depth: a ``sensor_msgs/CompressedImage`` topic (e.g.
``/camera/depth/image_rect_raw/compressedDepth`` from compressed_depth_image_transport) is
replayed as recorded, for a node with ``input_transport: compressedDepth``.  With
``--decompress-depth`` every CompressedImage topic whose name ends in ``/compressedDepth`` is
decoded and published as ``sensor_msgs/Image`` (16UC1 mm or 32FC1 m, as the original) on the
name without that suffix, like ``image_transport republish compressedDepth raw``; frames that
cannot be decoded are skipped with a warning.

QoS: reliable, volatile, keep-last ``--qos-depth`` (default 10); best-effort
(sensor-data) subscribers connect to reliable publishers.  A topic recorded
with transient-local durability (``/tf_static``...) is replayed with it.

Networking: this tool does **not** change the DDS configuration, so it can
replay to a real network.  Tests and CI confine it by setting
``FASTRTPS_DEFAULT_PROFILES_FILE`` to a loopback-only profile (the package
ships ``hand_sog_tracker/data/fastdds_loopback.xml``) and a test
``ROS_DOMAIN_ID`` (or ``--domain-id``) in the environment.
"""

from __future__ import annotations

import argparse
import array
import importlib
import math
import os
import re
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from hand_sog_tracker.errors import BagError, HandSogError, InputError
from hand_sog_tracker.interface import COMPRESSED_SUFFIX
from hand_sog_tracker.tools.bagio import (
    COMPRESSED_TYPE,
    deserialize,
    iter_messages,
    open_bag,
    topic_table,
)

__all__ = [
    "ReplayStats",
    "ros_message_class",
    "to_rclpy",
    "BagPublisher",
    "replay",
    "main",
]

_TYPE_RE = re.compile(r"^(?:sequence<)?([A-Za-z0-9_]+)/(?:msg/)?([A-Za-z0-9_]+)")


@dataclass(frozen=True)
class ReplayStats:
    """What :func:`replay` published.

    Attributes
    ----------
    messages : int
        Messages published (all loops).
    per_topic : dict[str, int]
        Messages published per topic.
    loops : int
        Complete passes over the bag.
    seconds : float
        Wall time of the replay.
    skipped_topics : dict[str, str]
        Topics not replayed and why.
    """

    messages: int
    per_topic: dict[str, int]
    loops: int
    seconds: float
    skipped_topics: dict[str, str] = field(default_factory=dict)


def ros_message_class(msgtype: str) -> Any:
    """The rclpy message class of ``pkg/msg/Name`` (or ``pkg/Name``).

    Raises
    ------
    BagError
        If the package or message is not installed.
    """
    m = _TYPE_RE.match(msgtype)
    if m is None:
        raise BagError(f"not a ROS message type name: {msgtype!r}")
    pkg, name = m.groups()
    try:
        module = importlib.import_module(f"{pkg}.msg")
        return getattr(module, name)
    except (ImportError, AttributeError) as err:
        raise BagError(f"message type {msgtype} is not available in this Python environment") from err


def to_rclpy(record: Any, cls: Any) -> Any:
    """Copy a rosbags message record into a new rclpy message of class ``cls``.

    Fields are matched by name, falling back to the upper-case name (ROS 1
    ``CameraInfo.K`` -> ``k``); fields the record lacks keep their defaults
    and record fields ``cls`` lacks (ROS 1 ``Header.seq``) are dropped.
    """
    msg = cls()
    for name, typ in cls.get_fields_and_field_types().items():
        if hasattr(record, name):
            src = getattr(record, name)
        elif hasattr(record, name.upper()):
            src = getattr(record, name.upper())
        else:
            continue
        setattr(msg, name, _convert(src, getattr(msg, name), typ))
    return msg


def _convert(src: Any, current: Any, typ: str) -> Any:
    if hasattr(type(current), "get_fields_and_field_types"):
        return to_rclpy(src, type(current))
    if isinstance(current, np.ndarray):
        return np.asarray(src, dtype=current.dtype).reshape(current.shape)
    if isinstance(current, array.array):
        out = array.array(current.typecode)
        out.frombytes(np.ascontiguousarray(np.asarray(src), dtype=np.dtype(current.typecode)).tobytes())
        return out
    if isinstance(current, list):
        if typ.startswith("sequence<") or "[" in typ:
            base = typ.removeprefix("sequence<").split(",")[0].rstrip(">").split("[")[0].split("<=")[0]
            if "/" in base:
                elem_cls = ros_message_class(base)
                return [to_rclpy(e, elem_cls) for e in src]
        return list(src)
    if isinstance(current, bool):
        return bool(src)
    if isinstance(current, int):
        return int(src)
    if isinstance(current, float):
        return float(src)
    if isinstance(current, str):
        return str(src)
    if isinstance(current, bytes):
        return bytes(src)
    return src


def _durability_transient(connections: Sequence[Any]) -> bool:
    for c in connections:
        for q in getattr(c.ext, "offered_qos_profiles", None) or []:
            if getattr(getattr(q, "durability", None), "name", "") == "TRANSIENT_LOCAL":
                return True
    return False


class BagPublisher:
    """rclpy publishers for the topics of an open bag.

    Parameters
    ----------
    node : rclpy.node.Node
        Node that owns the publishers.
    reader : rosbags AnyReader
        Open reader of the bag.
    path : Path
        The bag (for messages).
    topics : sequence of str, optional
        Topics to publish (default: every topic whose type is installed).
    rename : dict, optional
        Publish bag topic ``k`` under the name ``rename[k]``.
    qos_depth : int
        Keep-last depth of the reliable publishers.
    decompress_depth : bool
        Publish ``.../compressedDepth`` CompressedImage topics decoded, as ``sensor_msgs/Image``
        on the topic name without the suffix (see the module docstring).

    Raises
    ------
    BagError
        A requested topic is not in the bag or its type is not installed.
    """

    def __init__(
        self,
        node: Any,
        reader: Any,
        path: Path,
        topics: Sequence[str] | None = None,
        rename: dict[str, str] | None = None,
        qos_depth: int = 10,
        decompress_depth: bool = False,
    ) -> None:
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

        self.reader = reader
        self.path = path
        self.raw = bool(reader.is2)
        table = topic_table(reader)
        wanted = list(table) if topics is None else list(topics)
        missing = [t for t in wanted if t not in table]
        if missing:
            listing = "\n".join(f"  {n}  [{t}, {c} msgs]" for n, (t, c) in table.items()) or "  (none)"
            raise BagError(f"topic(s) {', '.join(missing)} not in bag {path}; the bag's topics are:\n{listing}")
        self.skipped: dict[str, str] = {}
        self.publishers: dict[str, Any] = {}
        self.classes: dict[str, type] = {}
        self.connections = []
        #: Topics published decoded (compressedDepth -> Image).
        self.decompressed: set[str] = set()
        for topic in wanted:
            conns = [c for c in reader.connections if c.topic == topic]
            msgtype = table[topic][0]
            out_name = topic
            if decompress_depth and msgtype == COMPRESSED_TYPE and topic.endswith(COMPRESSED_SUFFIX):
                self.decompressed.add(topic)
                msgtype, out_name = "sensor_msgs/msg/Image", topic[: -len(COMPRESSED_SUFFIX)]
            try:
                cls = ros_message_class(msgtype)
            except BagError as err:
                if topics is not None:
                    raise
                self.skipped[topic] = str(err)
                continue
            qos = QoSProfile(
                history=HistoryPolicy.KEEP_LAST,
                depth=qos_depth,
                reliability=ReliabilityPolicy.RELIABLE,
                durability=(
                    DurabilityPolicy.TRANSIENT_LOCAL if _durability_transient(conns) else DurabilityPolicy.VOLATILE
                ),
            )
            name = (rename or {}).get(topic, out_name)
            self.publishers[topic] = node.create_publisher(cls, name, qos)
            self.classes[topic] = cls
            self.connections.extend(conns)

    def payload(self, connection: Any, raw: bytes) -> Any:
        """What to publish for one bag message: CDR bytes, or a converted rclpy message.

        Raises
        ------
        DepthImageError
            A compressedDepth message to decompress cannot be decoded.
        """
        if connection.topic in self.decompressed:
            return self._decompressed(deserialize(self.reader, self.path, raw, connection))
        if self.raw:
            return bytes(raw)
        record = deserialize(self.reader, self.path, raw, connection)
        return to_rclpy(record, self.classes[connection.topic])

    def _decompressed(self, record: Any) -> Any:
        from sensor_msgs.msg import Image
        from std_msgs.msg import Header

        from hand_sog_tracker.compressed_depth import decode_compressed_depth, parse_format

        encoding = parse_format(record.format).encoding
        mm = decode_compressed_depth(record.format, record.data)
        if encoding == "16UC1":
            pix = mm.astype("<u2")
        else:
            pix = np.where(mm > 0, mm / 1000.0, np.nan).astype("<f4")
        h, w = pix.shape
        return Image(
            header=to_rclpy(record.header, Header), height=h, width=w, encoding=encoding,
            is_bigendian=0, step=w * pix.itemsize, data=pix.tobytes(),
        )

    def publish(self, topic: str, payload: Any) -> None:
        """Publish ``payload`` (bytes or message) on ``topic``."""
        self.publishers[topic].publish(payload)

    def flush(self, timeout_s: float = 2.0) -> bool:
        """Wait until the subscribers have acknowledged every message published (the publishers
        are reliable: a message lost on the way is sent again, which needs the publisher to
        live), at most ``timeout_s`` in all; whether all were acknowledged."""
        from rclpy.duration import Duration

        deadline = time.monotonic() + timeout_s
        acked = True
        for p in self.publishers.values():
            left = max(deadline - time.monotonic(), 0.0)
            acked = p.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))) and acked
        return acked

    def wait_for_subscribers(self, timeout_s: float, settle_s: float = 0.5) -> bool:
        """Wait for subscribers before publishing.

        Returns as soon as every publisher has a subscriber, or ``settle_s``
        after the first one got one (subscribers of one process are
        discovered together; other topics may have none), or at
        ``timeout_s``.  True if at least one publisher has a subscriber.
        """
        deadline = time.monotonic() + timeout_s
        first: float | None = None
        while True:
            counts = [p.get_subscription_count() > 0 for p in self.publishers.values()]
            now = time.monotonic()
            if counts and all(counts):
                return True
            if any(counts):
                first = now if first is None else first
                if now - first >= settle_s:
                    return True
            if now >= deadline:
                return any(counts)
            time.sleep(0.02)


def replay(
    bag: str | Path,
    rate: float = 1.0,
    loop: bool = False,
    start_offset_s: float = 0.0,
    topics: Sequence[str] | None = None,
    context: Any = None,
    wait_for_subscribers_s: float = 0.0,
    qos_depth: int = 10,
    stop: threading.Event | None = None,
    on_publish: Callable[[str, int, float], None] | None = None,
    decompress_depth: bool = False,
) -> ReplayStats:
    """Publish a bag's topics at the recorded rate.

    Parameters
    ----------
    bag : str or Path
        Bag (see :func:`bagio.resolve_bag_path`).
    rate : float
        Speed factor (2 = twice as fast); > 0.
    loop : bool
        Start over at the end until ``stop`` is set (or Ctrl-C).
    start_offset_s : float
        Skip the first seconds of the bag (by record time).
    topics : sequence of str, optional
        Topics to publish (default all with an installed type).
    context : rclpy Context, optional
        Initialised context to use; default: a new one, initialised and shut
        down here from the environment (ROS_DOMAIN_ID, Fast DDS profile).
    wait_for_subscribers_s : float
        Before starting, wait up to this long for subscribers (see
        :meth:`BagPublisher.wait_for_subscribers`; 0 = do not wait).
    qos_depth : int
        Keep-last depth of the publishers.
    stop : threading.Event, optional
        Set it to end the replay early.
    on_publish : callable, optional
        Called as ``on_publish(topic, log_time_ns, monotonic_time)`` after each publication.
    decompress_depth : bool
        See :class:`BagPublisher`.

    Raises
    ------
    BagError
        Unreadable bag, unknown topic, or a requested type not installed.
    InputError
        Invalid rate or offset.
    """
    if not (rate > 0 and math.isfinite(rate)):
        raise InputError(f"rate must be a positive number, got {rate}")
    if not (start_offset_s >= 0 and math.isfinite(start_offset_s)):
        raise InputError(f"start offset must be >= 0 s, got {start_offset_s}")
    if qos_depth < 1:
        raise InputError("qos_depth must be >= 1")
    import rclpy

    own_context = context is None
    if own_context:
        from rclpy.context import Context

        context = Context()
        rclpy.init(context=context)
    node = None
    stop = stop or threading.Event()
    counts: dict[str, int] = {}
    loops = 0
    t_begin = time.monotonic()
    try:
        node = rclpy.create_node("replay_bag", context=context, start_parameter_services=False)
        opener = open_bag(bag)
        with opener as reader:
            path = opener.path
            pub = BagPublisher(node, reader, path, topics, qos_depth=qos_depth, decompress_depth=decompress_depth)
            for topic, why in pub.skipped.items():
                node.get_logger().warning(f"not replaying {topic}: {why}")
            if not pub.publishers:
                raise BagError(f"bag {path}: no topic to replay")
            start_ns = reader.start_time + int(round(start_offset_s * 1e9))
            if start_ns >= reader.end_time:
                raise InputError(
                    f"start offset {start_offset_s} s is past the end of the bag "
                    f"({(reader.end_time - reader.start_time) / 1e9:.3f} s long)"
                )
            if wait_for_subscribers_s > 0:
                pub.wait_for_subscribers(wait_for_subscribers_s)
            while not stop.is_set():
                t0 = time.monotonic()
                for conn, log_ns, raw in iter_messages(reader, path, pub.connections, start_ns):
                    due = t0 + (log_ns - start_ns) / 1e9 / rate
                    delay = due - time.monotonic()
                    if delay > 0 and stop.wait(delay):
                        break
                    if not context.ok():
                        stop.set()
                        break
                    try:
                        payload = pub.payload(conn, raw)
                    except InputError as err:  # an undecodable compressedDepth frame
                        node.get_logger().warning(f"skipping a message on {conn.topic}: {err}")
                        continue
                    pub.publish(conn.topic, payload)
                    counts[conn.topic] = counts.get(conn.topic, 0) + 1
                    if on_publish is not None:
                        on_publish(conn.topic, log_ns, time.monotonic())
                else:
                    loops += 1
                    if not loop:
                        break
            if context.ok() and not stop.is_set():
                pub.flush()  # (the last messages reach their subscribers before the node goes)
            skipped = dict(pub.skipped)
    finally:
        if node is not None:
            node.destroy_node()
        if own_context:
            rclpy.try_shutdown(context=context)
    return ReplayStats(
        messages=sum(counts.values()),
        per_topic=dict(sorted(counts.items())),
        loops=loops,
        seconds=time.monotonic() - t_begin,
        skipped_topics=skipped,
    )


def build_parser() -> argparse.ArgumentParser:
    """The command-line parser of ``replay_bag``."""
    p = argparse.ArgumentParser(
        prog="replay_bag",
        description="Publish a bag's topics live at the recorded rate (a stand-in for `ros2 bag play`). "
        "The DDS configuration is taken from the environment: set FASTRTPS_DEFAULT_PROFILES_FILE and "
        "ROS_DOMAIN_ID to confine it (tests/CI use the package's loopback profile).",
    )
    p.add_argument("bag", help="rosbag2 directory (sqlite3 or mcap) or ROS 1 .bag file")
    p.add_argument("--rate", type=float, default=1.0, help="speed factor (default 1)")
    p.add_argument("--loop", action="store_true", help="start over at the end until Ctrl-C")
    p.add_argument("--start-offset", type=float, default=0.0, metavar="S", help="skip the first S seconds")
    p.add_argument("--topics", nargs="+", metavar="T", help="topics to publish (default all)")
    p.add_argument("--domain-id", type=int, help="set ROS_DOMAIN_ID for this process")
    p.add_argument("--wait-for-subscribers", type=float, default=0.0, metavar="S",
                   help="wait up to S seconds for subscribers before starting (until every topic has one, "
                   "or 0.5 s after the first one appeared)")
    p.add_argument("--qos-depth", type=int, default=10, help="publisher keep-last depth (default 10)")
    p.add_argument("--decompress-depth", action="store_true",
                   help="publish .../compressedDepth CompressedImage topics decoded, as sensor_msgs/Image on the "
                   "topic without the suffix (like image_transport republish)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point; returns the exit status (0 ok, 2 error)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not (args.rate > 0 and math.isfinite(args.rate)):
        parser.error("--rate must be a positive number")
    if not (args.start_offset >= 0 and math.isfinite(args.start_offset)):
        parser.error("--start-offset must be >= 0")
    if args.qos_depth < 1:
        parser.error("--qos-depth must be >= 1")
    if args.domain_id is not None:
        if not 0 <= args.domain_id <= 232:
            parser.error("--domain-id must be in [0, 232]")
        os.environ["ROS_DOMAIN_ID"] = str(args.domain_id)
    stop = threading.Event()
    try:
        stats = replay(
            args.bag,
            rate=args.rate,
            loop=args.loop,
            start_offset_s=args.start_offset,
            topics=args.topics,
            wait_for_subscribers_s=args.wait_for_subscribers,
            qos_depth=args.qos_depth,
            stop=stop,
            decompress_depth=args.decompress_depth,
        )
    except HandSogError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        stop.set()
        print("interrupted", file=sys.stderr)
        return 0
    per = ", ".join(f"{t} {n}" for t, n in stats.per_topic.items())
    print(f"published {stats.messages} messages in {stats.seconds:.2f} s ({stats.loops} loops): {per}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
