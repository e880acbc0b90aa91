"""replay_bag: publishes a bag's messages to an in-process subscriber (loopback DDS, test domain)."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.typesys import Stores, get_typestore

from hand_sog_tracker.core.types import Intrinsics
from hand_sog_tracker.errors import BagError, InputError
from hand_sog_tracker.tools import bagio
from hand_sog_tracker.tools.bagio import DepthSample, write_depth_bag
from hand_sog_tracker.tools.replay_bag import main, replay, ros_message_class, to_rclpy
from helpers import test_domain

REPO = Path(__file__).resolve().parents[1]
PROFILE = REPO / "hand_sog_tracker" / "data" / "fastdds_loopback.xml"
DOMAIN = str(test_domain(1))
T0 = 1_700_000_000_000_000_000
DT = 20_000_000  # 50 Hz
INTR = Intrinsics(fx=60.0, fy=60.0, cx=15.5, cy=11.5, width=32, height=24)


@pytest.fixture(autouse=True)
def _loopback_env(monkeypatch: pytest.MonkeyPatch) -> None:
    """Never start DDS outside loopback, whatever conftest did."""
    monkeypatch.setenv("FASTRTPS_DEFAULT_PROFILES_FILE", str(PROFILE))
    monkeypatch.setenv("ROS_DOMAIN_ID", DOMAIN)
    monkeypatch.setenv("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    monkeypatch.delenv("ROS_LOCALHOST_ONLY", raising=False)
    monkeypatch.delenv("ROS_AUTOMATIC_DISCOVERY_RANGE", raising=False)


class Listener:
    """Subscribers in their own rclpy context, spun by a background thread."""

    def __init__(self, topics: dict[str, Any], best_effort: tuple[str, ...] = ()) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

        self.ctx = Context()
        rclpy.init(context=self.ctx)
        self.node = rclpy.create_node("replay_test_listener", context=self.ctx)
        self.received: dict[str, list[Any]] = {t: [] for t in topics}
        self.lock = threading.Lock()
        for topic, cls in topics.items():
            reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
            qos = qos_profile_sensor_data if topic in best_effort else reliable
            self.node.create_subscription(cls, topic, self._cb(topic), qos)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _cb(self, topic: str) -> Any:
        def cb(msg: Any) -> None:
            with self.lock:
                self.received[topic].append(msg)

        return cb

    def _spin(self) -> None:
        while self.ctx.ok():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception:  # noqa: BLE001 - context shut down under us
                return

    def count(self, topic: str) -> int:
        with self.lock:
            return len(self.received[topic])

    def wait_for(self, topic: str, n: int, timeout: float = 5.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.count(topic) >= n:
                return True
            time.sleep(0.02)
        return False

    def close(self) -> None:
        import rclpy

        rclpy.try_shutdown(context=self.ctx)
        self.thread.join(timeout=5)
        self.executor.shutdown()
        self.node.destroy_node()


@pytest.fixture
def listener_factory() -> Iterator[Any]:
    made: list[Listener] = []

    def make(topics: dict[str, Any], best_effort: tuple[str, ...] = ()) -> Listener:
        lst = Listener(topics, best_effort)
        made.append(lst)
        return lst

    yield make
    for lst in made:
        lst.close()


def _bag(path: Path, rng: np.random.Generator, n: int = 4) -> list[DepthSample]:
    samples = [
        DepthSample(T0 + i * DT, rng.uniform(300.0, 700.0, (24, 32)), INTR, rng.uniform(-50, 50, (5, 3)))
        for i in range(n)
    ]
    write_depth_bag(path, samples)
    return samples


def _types() -> dict[str, Any]:
    from geometry_msgs.msg import PoseArray
    from sensor_msgs.msg import CameraInfo, Image

    return {bagio.DEPTH_TOPIC: Image, bagio.INFO_TOPIC: CameraInfo, bagio.GT_TOPIC: PoseArray}


def test_replays_every_message_with_identical_content(tmp_path: Path, listener_factory: Any) -> None:
    assert os.environ["ROS_DOMAIN_ID"] == DOMAIN
    rng = np.random.default_rng(30)
    samples = _bag(tmp_path / "b", rng)
    lst = listener_factory(_types())
    stats = replay(tmp_path / "b", rate=5.0, wait_for_subscribers_s=10.0)
    assert stats.per_topic == {bagio.INFO_TOPIC: 4, bagio.DEPTH_TOPIC: 4, bagio.GT_TOPIC: 4}
    assert stats.loops == 1 and stats.messages == 12
    for topic in _types():
        assert lst.wait_for(topic, 4), topic
    images = lst.received[bagio.DEPTH_TOPIC]
    for img, s in zip(images, samples):
        assert (img.width, img.height, img.encoding) == (32, 24, "16UC1")
        assert img.header.stamp.sec * 10**9 + img.header.stamp.nanosec == s.stamp_ns
        depth = np.frombuffer(bytes(img.data), "<u2").reshape(24, 32)
        np.testing.assert_array_equal(depth, np.rint(s.depth_mm))
    info = lst.received[bagio.INFO_TOPIC][0]
    assert (info.k[0], info.k[2], info.k[5]) == (60.0, 15.5, 11.5)
    gt = lst.received[bagio.GT_TOPIC][-1]
    assert gt.poses[4].position.x == pytest.approx(samples[-1].truth_mm[4, 0] / 1000.0)
    # real time at rate 5: 3 intervals of 20 ms / 5 -> at least 12 ms in total
    assert stats.seconds >= 0.012


def test_topics_and_start_offset(tmp_path: Path, listener_factory: Any) -> None:
    rng = np.random.default_rng(31)
    _bag(tmp_path / "b", rng, n=5)
    types = _types()
    lst = listener_factory({bagio.DEPTH_TOPIC: types[bagio.DEPTH_TOPIC], bagio.INFO_TOPIC: types[bagio.INFO_TOPIC]})
    # skip the first 2 frames (40 ms) of the bag; publish only the depth images
    stats = replay(
        tmp_path / "b", rate=2.0, start_offset_s=0.035, topics=[bagio.DEPTH_TOPIC], wait_for_subscribers_s=10.0
    )
    assert stats.per_topic == {bagio.DEPTH_TOPIC: 3}
    assert lst.wait_for(bagio.DEPTH_TOPIC, 3)
    stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in lst.received[bagio.DEPTH_TOPIC]]
    assert stamps == [T0 + k * DT for k in (2, 3, 4)]
    time.sleep(0.1)
    assert lst.count(bagio.INFO_TOPIC) == 0


def test_best_effort_subscriber_is_served(tmp_path: Path, listener_factory: Any) -> None:
    rng = np.random.default_rng(36)
    _bag(tmp_path / "b", rng, n=3)
    types = _types()
    lst = listener_factory({bagio.DEPTH_TOPIC: types[bagio.DEPTH_TOPIC]}, best_effort=(bagio.DEPTH_TOPIC,))
    stop = threading.Event()
    th = threading.Thread(
        target=replay,
        args=(tmp_path / "b",),
        kwargs={"rate": 2.0, "loop": True, "wait_for_subscribers_s": 10.0, "stop": stop},
    )
    th.start()
    try:
        # best effort: the first samples may go before the reader matched, but it gets served
        assert lst.wait_for(bagio.DEPTH_TOPIC, 2, timeout=10.0)
    finally:
        stop.set()
        th.join(timeout=10.0)
    assert not th.is_alive()


def test_loop_until_stopped(tmp_path: Path, listener_factory: Any) -> None:
    rng = np.random.default_rng(32)
    _bag(tmp_path / "b", rng, n=2)
    lst = listener_factory({bagio.INFO_TOPIC: _types()[bagio.INFO_TOPIC]})
    stop = threading.Event()
    result: list[Any] = []
    th = threading.Thread(
        target=lambda: result.append(
            replay(
                tmp_path / "b", rate=4.0, loop=True, topics=[bagio.INFO_TOPIC], wait_for_subscribers_s=10.0, stop=stop
            )
        )
    )
    th.start()
    try:
        assert lst.wait_for(bagio.INFO_TOPIC, 7, timeout=10.0)  # more than 3 passes over 2 messages
    finally:
        stop.set()
        th.join(timeout=10.0)
    assert not th.is_alive()
    assert result[0].loops >= 3 and result[0].per_topic[bagio.INFO_TOPIC] >= 7


def test_ros1_bag_is_converted_field_by_field(tmp_path: Path, listener_factory: Any) -> None:
    ts = get_typestore(Stores.ROS1_NOETIC)
    t = ts.types
    header = t["std_msgs/msg/Header"](seq=3, stamp=t["builtin_interfaces/msg/Time"](sec=12, nanosec=34), frame_id="cam")
    info = t["sensor_msgs/msg/CameraInfo"](
        header=header, height=24, width=32, distortion_model="plumb_bob", D=np.array([0.1, 0.2, 0.0, 0.0, 0.0]),
        K=np.array([60.0, 0, 15.5, 0, 60.0, 11.5, 0, 0, 1]), R=np.eye(3).ravel(), P=np.zeros(12),
        binning_x=0, binning_y=0,
        roi=t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )
    path = tmp_path / "r1.bag"
    with Ros1Writer(path) as w:
        conn = w.add_connection(bagio.INFO_TOPIC, info.__msgtype__, typestore=ts)
        for k in range(2):
            w.write(conn, 12 * 10**9 + 34 + k * DT, ts.serialize_ros1(info, info.__msgtype__))
    lst = listener_factory({bagio.INFO_TOPIC: _types()[bagio.INFO_TOPIC]})
    stats = replay(path, rate=4.0, wait_for_subscribers_s=10.0)
    assert stats.messages == 2
    assert lst.wait_for(bagio.INFO_TOPIC, 2)
    msg = lst.received[bagio.INFO_TOPIC][0]
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (12, 34, "cam")
    np.testing.assert_allclose(msg.k, info.K)
    np.testing.assert_allclose(list(msg.d), [0.1, 0.2, 0.0, 0.0, 0.0])


def test_to_rclpy_copies_nested_sequences() -> None:
    rng = np.random.default_rng(33)
    tips = rng.uniform(-80, 80, (5, 3)) + [0, 0, 400]
    record = bagio.fingertips_msg(tips, T0 + 7)
    msg = to_rclpy(record, ros_message_class("geometry_msgs/msg/PoseArray"))
    assert len(msg.poses) == 5 and msg.header.stamp.nanosec == 7
    assert [p.position.z for p in msg.poses] == pytest.approx(list(tips[:, 2] / 1000.0))
    img = to_rclpy(bagio.depth_image_msg(np.full((2, 3), 513.0), T0), ros_message_class("sensor_msgs/Image"))
    assert bytes(img.data) == np.full(6, 513, "<u2").tobytes()
    with pytest.raises(BagError, match="not available"):
        ros_message_class("no_such_pkg/msg/Thing")


def test_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rng = np.random.default_rng(34)
    _bag(tmp_path / "b", rng, n=2)
    assert main([str(tmp_path / "b"), "--topics", "/nope"]) == 2
    err = capsys.readouterr().err
    assert "/nope not in bag" in err and bagio.DEPTH_TOPIC in err and "Traceback" not in err
    assert main([str(tmp_path / "missing")]) == 2
    assert "bag not found" in capsys.readouterr().err
    assert main([str(tmp_path / "b"), "--start-offset", "5"]) == 2
    assert "past the end of the bag" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main([str(tmp_path / "b"), "--rate", "0"])
    assert exc.value.code == 2
    with pytest.raises(InputError):
        replay(tmp_path / "b", rate=-1.0)


def test_cli_publishes_with_domain_option(
    tmp_path: Path, listener_factory: Any, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    rng = np.random.default_rng(35)
    _bag(tmp_path / "b", rng, n=3)
    lst = listener_factory({bagio.GT_TOPIC: _types()[bagio.GT_TOPIC]})
    monkeypatch.setenv("ROS_DOMAIN_ID", "0")  # the option must override it
    assert main([str(tmp_path / "b"), "--domain-id", DOMAIN, "--rate", "5", "--wait-for-subscribers", "10"]) == 0
    assert os.environ["ROS_DOMAIN_ID"] == DOMAIN
    assert "published 9 messages" in capsys.readouterr().out
    assert lst.wait_for(bagio.GT_TOPIC, 3)


@pytest.mark.parametrize("decompress", [False, True])
def test_compressed_depth_is_replayed_as_recorded_or_decompressed(tmp_path: Path, decompress: bool) -> None:
    """What BagPublisher creates and publishes for a compressedDepth topic (a recording node: no DDS)."""
    from sensor_msgs.msg import CompressedImage, Image

    from hand_sog_tracker.tools.bagio import BagTopics, iter_messages, open_bag
    from hand_sog_tracker.tools.replay_bag import BagPublisher

    class RecordingNode:
        def __init__(self) -> None:
            self.created: dict[str, type] = {}
            self.sent: dict[str, list[Any]] = {}

        def create_publisher(self, cls: type, name: str, qos: Any) -> Any:
            self.created[name] = cls
            sent = self.sent.setdefault(name, [])
            return type("P", (), {"publish": lambda _self, m: sent.append(m)})()

    base = "/cam/depth"
    topics = BagTopics(depth=base, info=f"{base}_info", truth=f"{base}_truth")
    rng = np.random.default_rng(37)
    samples = [DepthSample(T0 + i * DT, rng.uniform(300.0, 700.0, (24, 32)), INTR) for i in range(3)]
    samples[1].depth_mm[2:5] = 0.0
    write_depth_bag(tmp_path / "b", samples, topics=topics, encoding="32FC1", depth_codec="rvl")
    compressed = base + "/compressedDepth"
    node = RecordingNode()
    with open_bag(tmp_path / "b") as reader:
        pub = BagPublisher(node, reader, tmp_path / "b", [compressed], decompress_depth=decompress)
        for conn, _, raw in iter_messages(reader, tmp_path / "b", pub.connections):
            pub.publish(conn.topic, pub.payload(conn, raw))
    if decompress:  # decoded, as sensor_msgs/Image on the topic without the suffix
        assert node.created == {base: Image} and pub.decompressed == {compressed}
        for img, s in zip(node.sent[base], samples, strict=True):
            assert (img.width, img.height, img.encoding, img.step) == (32, 24, "32FC1", 128)
            assert img.header.stamp.sec * 10**9 + img.header.stamp.nanosec == s.stamp_ns
            assert img.header.frame_id == bagio.OPTICAL_FRAME
            metres = np.frombuffer(bytes(img.data), "<f4").reshape(24, 32)
            valid = s.depth_mm > 0
            np.testing.assert_array_equal(np.isfinite(metres), valid)
            np.testing.assert_allclose(metres[valid] * 1000.0, s.depth_mm[valid], atol=0.05)  # < 50 um at 0.7 m
    else:  # as recorded: the CDR bytes of the CompressedImage
        assert node.created == {compressed: CompressedImage} and not pub.decompressed
        assert len(node.sent[compressed]) == 3
        rec = bagio.typestore().deserialize_cdr(node.sent[compressed][0], "sensor_msgs/msg/CompressedImage")
        want = bagio.compressed_depth_msg(samples[0].depth_mm, T0, encoding="32FC1", codec="rvl")
        assert rec.format == "32FC1; compressedDepth rvl" and bytes(rec.data) == want.data.tobytes()


def test_undecodable_compressed_frames_are_skipped_with_a_warning(tmp_path: Path, listener_factory: Any, capfd) -> None:
    """Through DDS: a corrupt frame is skipped, the others arrive decoded (unique topic names)."""
    import uuid

    from sensor_msgs.msg import Image

    base = f"/r{uuid.uuid4().hex[:8]}/depth"
    rng = np.random.default_rng(38)
    good = [bagio.compressed_depth_msg(rng.uniform(300.0, 700.0, (24, 32)), T0 + i * DT) for i in range(3)]
    good[1].data = good[1].data[:20]  # truncated PNG
    with bagio.BagWriter(tmp_path / "b") as w:
        for i, m in enumerate(good):
            w.write(base + "/compressedDepth", m, T0 + i * DT)
    lst = listener_factory({base: Image})
    stats = replay(tmp_path / "b", rate=5.0, wait_for_subscribers_s=10.0, decompress_depth=True)
    assert stats.per_topic == {base + "/compressedDepth": 2}
    assert lst.wait_for(base, 2, timeout=10.0), lst.count(base)
    assert "skipping a message" in capfd.readouterr().err
