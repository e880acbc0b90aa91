"""Bag reading/writing helpers (hand_sog_tracker.tools.bagio) on tiny bags in tmp_path."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.typesys import Stores, get_typestore

from hand_sog_tracker.core.types import Intrinsics
from hand_sog_tracker.errors import BagError
from hand_sog_tracker.tools import bagio
from hand_sog_tracker.tools.bagio import BagTopics, BagWriter, DepthBagReader, DepthSample, write_depth_bag

T0 = 1_700_000_000_000_000_000
DT = 33_333_333
INTR = Intrinsics(fx=90.0, fy=91.0, cx=31.5, cy=23.5, width=64, height=48)


def _samples(rng: np.random.Generator, n: int, truth_every: int = 1) -> list[DepthSample]:
    out = []
    for i in range(n):
        depth = rng.uniform(300.0, 700.0, (48, 64))
        depth[rng.random((48, 64)) < 0.1] = 0.0
        truth = rng.uniform(-60.0, 60.0, (5, 3)) + [0.0, 0.0, 450.0] if i % truth_every == 0 else None
        out.append(DepthSample(T0 + i * DT, depth, INTR, truth))
    return out


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
@pytest.mark.parametrize("compress", [True, False])
def test_roundtrip_16uc1(tmp_path: Path, storage: str, compress: bool) -> None:
    rng = np.random.default_rng(10)
    samples = _samples(rng, 4, truth_every=2)
    n = write_depth_bag(tmp_path / "b", samples, storage=storage, compress=compress)  # type: ignore[arg-type]
    assert n == 4
    with DepthBagReader(tmp_path / "b") as r:
        assert r.n_depth == 4
        assert r.topic_table[bagio.GT_TOPIC] == (bagio.GT_TYPE, 2)
        frames = list(r.frames())
    assert [f.index for f in frames] == [0, 1, 2, 3]
    assert [f.stamp_ns for f in frames] == [s.stamp_ns for s in samples]
    for f, s in zip(frames, samples):
        assert f.error is None and f.intrinsics == INTR
        assert f.depth_mm is not None and f.depth_mm.dtype == np.float32
        np.testing.assert_array_equal(f.depth_mm, np.rint(s.depth_mm))  # mm, rounded to uint16
        if s.truth_mm is None:
            assert f.truth_mm is None
        else:
            np.testing.assert_allclose(f.truth_mm, s.truth_mm, atol=1e-9)


def test_roundtrip_32fc1_metres_and_invalid(tmp_path: Path) -> None:
    rng = np.random.default_rng(11)
    depth = rng.uniform(200.0, 800.0, (48, 64))
    depth[5, :] = 0.0
    depth[7, 3] = np.nan
    write_depth_bag(tmp_path / "b", [DepthSample(T0, depth, INTR, np.ones((5, 3)))], encoding="32FC1")
    with DepthBagReader(tmp_path / "b") as r:
        (f,) = list(r.frames())
    assert f.depth_mm is not None
    expect = np.nan_to_num(depth, nan=0.0)
    np.testing.assert_allclose(f.depth_mm, expect, rtol=1e-6)
    assert f.depth_mm[5].max() == 0.0 and f.depth_mm[7, 3] == 0.0


def test_reads_ros1_bag(tmp_path: Path) -> None:
    rng = np.random.default_rng(12)
    ts = get_typestore(Stores.ROS1_NOETIC)
    t = ts.types
    path = tmp_path / "r1.bag"
    depth = rng.integers(300, 700, (48, 64)).astype("<u2")
    tips = rng.uniform(-0.05, 0.05, (5, 3)) + [0.0, 0.0, 0.45]
    header = t["std_msgs/msg/Header"](seq=7, stamp=t["builtin_interfaces/msg/Time"](sec=100, nanosec=5), frame_id="cam")
    info = t["sensor_msgs/msg/CameraInfo"](
        header=header, height=48, width=64, distortion_model="plumb_bob", D=np.zeros(5),
        K=np.array([90.0, 0, 31.5, 0, 91.0, 23.5, 0, 0, 1]), R=np.eye(3).ravel(), P=np.zeros(12),
        binning_x=0, binning_y=0,
        roi=t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )
    img = t["sensor_msgs/msg/Image"](
        header=header, height=48, width=64, encoding="16UC1", is_bigendian=0, step=128,
        data=np.frombuffer(depth.tobytes(), np.uint8),
    )
    Pose, Point, Quat = t["geometry_msgs/msg/Pose"], t["geometry_msgs/msg/Point"], t["geometry_msgs/msg/Quaternion"]
    gt = t["geometry_msgs/msg/PoseArray"](
        header=header,
        poses=[Pose(position=Point(x=a, y=b, z=c), orientation=Quat(x=0.0, y=0.0, z=0.0, w=1.0)) for a, b, c in tips],
    )
    with Ros1Writer(path) as w:
        for topic, msg in ((bagio.INFO_TOPIC, info), (bagio.DEPTH_TOPIC, img), (bagio.GT_TOPIC, gt)):
            conn = w.add_connection(topic, msg.__msgtype__, typestore=ts)
            w.write(conn, 100 * 10**9 + 5, ts.serialize_ros1(msg, msg.__msgtype__))
    with DepthBagReader(path) as r:
        (f,) = list(r.frames())
    assert f.stamp_ns == 100 * 10**9 + 5
    assert f.intrinsics == INTR
    assert f.depth_mm is not None
    np.testing.assert_array_equal(f.depth_mm, depth.astype(np.float32))
    assert f.truth_mm is not None
    np.testing.assert_allclose(f.truth_mm, tips * 1000.0)


def test_missing_topic_lists_the_bags_topics(tmp_path: Path) -> None:
    rng = np.random.default_rng(13)
    write_depth_bag(tmp_path / "b", _samples(rng, 2))
    with pytest.raises(BagError) as exc:
        with DepthBagReader(tmp_path / "b", BagTopics(depth="/other/depth")):
            pass
    text = str(exc.value)
    assert "'/other/depth' not in bag" in text
    for topic in (bagio.DEPTH_TOPIC, bagio.INFO_TOPIC, bagio.GT_TOPIC):
        assert topic in text
    assert "sensor_msgs/msg/Image, 2 msgs" in text


def test_no_camera_info_and_no_ground_truth(tmp_path: Path) -> None:
    rng = np.random.default_rng(14)
    samples = [DepthSample(s.stamp_ns, s.depth_mm, None, s.truth_mm) for s in _samples(rng, 2)]
    write_depth_bag(tmp_path / "noinfo", samples)
    with pytest.raises(BagError, match="CameraInfo topic '/camera/depth/camera_info' not in bag"):
        with DepthBagReader(tmp_path / "noinfo"):
            pass
    samples = [DepthSample(s.stamp_ns, s.depth_mm, INTR, None) for s in _samples(rng, 2)]
    write_depth_bag(tmp_path / "nogt", samples)
    with pytest.raises(BagError, match="ground-truth topic '/hand/ground_truth/fingertips' not in bag"):
        with DepthBagReader(tmp_path / "nogt"):
            pass
    with DepthBagReader(tmp_path / "nogt", require_truth=False) as r:
        assert [f.truth_mm for f in r.frames()] == [None, None]


def test_wrong_type_and_bad_ground_truth(tmp_path: Path) -> None:
    rng = np.random.default_rng(15)
    with BagWriter(tmp_path / "wt") as w:
        w.write(bagio.DEPTH_TOPIC, bagio.camera_info_msg(INTR, T0), T0)
    with pytest.raises(BagError, match="has type sensor_msgs/msg/CameraInfo, expected sensor_msgs/msg/Image"):
        with DepthBagReader(tmp_path / "wt"):
            pass
    gt = bagio.fingertips_msg(rng.uniform(0, 1, (5, 3)), T0)
    gt.poses.pop()
    with BagWriter(tmp_path / "gt4") as w:
        w.write(bagio.INFO_TOPIC, bagio.camera_info_msg(INTR, T0), T0)
        w.write(bagio.DEPTH_TOPIC, bagio.depth_image_msg(np.full((48, 64), 500.0), T0), T0)
        w.write(bagio.GT_TOPIC, gt, T0)
    with pytest.raises(BagError, match="has 4 poses, expected 5"):
        with DepthBagReader(tmp_path / "gt4"):
            pass


def test_size_mismatch_is_a_frame_error_and_info_matching(tmp_path: Path) -> None:
    small = Intrinsics(fx=45.0, fy=45.0, cx=15.5, cy=11.5, width=32, height=24)
    with BagWriter(tmp_path / "b") as w:
        w.write(bagio.INFO_TOPIC, bagio.camera_info_msg(INTR, T0 + DT), T0 + DT)
        w.write(bagio.INFO_TOPIC, bagio.camera_info_msg(small, T0 + 3 * DT), T0 + 3 * DT)
        for i in range(5):
            w.write(bagio.DEPTH_TOPIC, bagio.depth_image_msg(np.full((48, 64), 500.0), T0 + i * DT), T0 + i * DT)
        w.write(bagio.GT_TOPIC, bagio.fingertips_msg(np.ones((5, 3)), T0), T0)
    with DepthBagReader(tmp_path / "b") as r:
        assert r.intrinsics_at(T0) == INTR  # before the first CameraInfo: the first one
        assert r.intrinsics_at(T0 + 2 * DT) == INTR  # latest before
        assert r.intrinsics_at(T0 + 3 * DT) == small  # same stamp
        frames = list(r.frames())
    assert [f.error is None for f in frames] == [True, True, True, False, False]
    assert frames[3].depth_mm is None
    assert "64x48 but its CameraInfo is 32x24" in (frames[3].error or "")


def test_bad_paths_and_corrupt_bags(tmp_path: Path) -> None:
    rng = np.random.default_rng(16)
    with pytest.raises(BagError, match="bag not found"):
        bagio.resolve_bag_path(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(BagError, match="without metadata.yaml"):
        bagio.resolve_bag_path(tmp_path / "empty")
    write_depth_bag(tmp_path / "b", _samples(rng, 3))
    mcap = next((tmp_path / "b").glob("*.mcap"))
    assert bagio.resolve_bag_path(mcap) == tmp_path / "b"  # the storage file names its bag
    # garbage metadata
    (tmp_path / "meta").mkdir()
    (tmp_path / "meta" / "metadata.yaml").write_text("rosbag2_bagfile_information: [1, 2\n")
    with pytest.raises(BagError, match="cannot open bag"):
        with bagio.open_bag(tmp_path / "meta"):
            pass
    # truncated storage file: an error at open or while reading, always a BagError
    data = mcap.read_bytes()
    mcap.write_bytes(data[: len(data) // 2])
    with pytest.raises(BagError, match="corrupt or truncated|cannot open bag"):
        with DepthBagReader(tmp_path / "b") as r:
            list(r.frames())
    # random bytes as a ROS 1 bag
    (tmp_path / "x.bag").write_bytes(rng.integers(0, 256, 4096, dtype=np.uint8).tobytes())
    with pytest.raises(BagError, match="cannot open bag"):
        with DepthBagReader(tmp_path / "x.bag"):
            pass


def test_depth_message_encoding_details() -> None:
    d = np.array([[0.4, 70000.0], [np.nan, 1234.6]])
    msg = bagio.depth_image_msg(d, T0 + 5, "f")
    assert (msg.encoding, msg.step, msg.is_bigendian) == ("16UC1", 4, 0)
    np.testing.assert_array_equal(np.frombuffer(msg.data.tobytes(), "<u2").reshape(2, 2), [[0, 65535], [0, 1235]])
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (T0 // 10**9, 5, "f")
    with pytest.raises(BagError, match="unsupported depth encoding"):
        bagio.depth_image_msg(d, T0, encoding="8UC1")  # type: ignore[arg-type]
    with pytest.raises(BagError, match="2-D"):
        bagio.depth_image_msg(np.zeros(4), T0)


def test_writer_refuses_existing_path_and_cleans_up_on_error(tmp_path: Path) -> None:
    (tmp_path / "exists").mkdir()
    with pytest.raises(BagError, match="exists already"):
        BagWriter(tmp_path / "exists")
    with pytest.raises(RuntimeError):
        with BagWriter(tmp_path / "partial") as w:
            w.write(bagio.INFO_TOPIC, bagio.camera_info_msg(INTR, T0), T0)
            raise RuntimeError("boom")
    assert not (tmp_path / "partial").exists()


@pytest.mark.parametrize("codec", ["png", "rvl"])
@pytest.mark.parametrize("encoding", ["16UC1", "32FC1"])
def test_compressed_depth_bags_are_read(tmp_path: Path, codec: str, encoding: str) -> None:
    """compressedDepth CompressedImage on <depth topic>/compressedDepth (as image_transport records it)."""
    rng = np.random.default_rng(13)
    samples = _samples(rng, 3)
    write_depth_bag(tmp_path / "b", samples, encoding=encoding, depth_codec=codec)  # type: ignore[arg-type]
    topic = bagio.DEPTH_TOPIC + "/compressedDepth"
    with DepthBagReader(tmp_path / "b") as r:
        assert r.depth_compressed and r.depth_topic == topic and r.n_depth == 3
        assert r.topic_table[topic] == (bagio.COMPRESSED_TYPE, 3) and bagio.DEPTH_TOPIC not in r.topic_table
        assert {c.topic for c in r.connections(("depth",))} == {topic}
        frames = list(r.frames())
    for f, s in zip(frames, samples):
        assert f.error is None and f.depth_mm is not None and f.depth_mm.shape == (48, 64)
        want = np.rint(s.depth_mm)
        if encoding == "16UC1":
            np.testing.assert_array_equal(f.depth_mm, want)
        else:  # inverse-depth quantisation: one step is d^2 / (100 * 101) metres
            np.testing.assert_array_equal(f.depth_mm > 0, want > 0)
            step = (s.depth_mm / 1000.0) ** 2 / 10100.0 * 1000.0
            assert np.all(np.abs(f.depth_mm - s.depth_mm)[want > 0] <= step[want > 0] * 1.01 + 1e-3)


def test_corrupt_compressed_frame_is_a_frame_error(tmp_path: Path) -> None:
    rng = np.random.default_rng(14)
    (s,) = _samples(rng, 1)
    good = bagio.compressed_depth_msg(s.depth_mm, T0 + DT, codec="rvl")
    bad = bagio.compressed_depth_msg(s.depth_mm, T0, codec="rvl")
    bad.data = bad.data[:30]
    with BagWriter(tmp_path / "b") as w:
        w.write(bagio.INFO_TOPIC, bagio.camera_info_msg(INTR, T0), T0)
        # The compressed topic may also be the depth topic itself.
        w.write(bagio.DEPTH_TOPIC, bad, T0)
        w.write(bagio.DEPTH_TOPIC, good, T0 + DT)
    with DepthBagReader(tmp_path / "b", require_truth=False) as r:
        assert r.depth_compressed and r.depth_topic == bagio.DEPTH_TOPIC
        f0, f1 = list(r.frames())
    assert f0.depth_mm is None and "RVL" in (f0.error or "") and "truncated" in (f0.error or "")
    assert f1.error is None and f1.depth_mm is not None
