"""Message conversion: depth images, CameraInfo, output messages (no DDS involved)."""

from __future__ import annotations

import array
from types import SimpleNamespace

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore
from sensor_msgs.msg import CameraInfo, Image, RegionOfInterest
from std_msgs.msg import Header
from visualization_msgs.msg import Marker

from hand_sog_tracker.core.hand_model import JOINT_NAMES, default_hand_model, rest_pose
from hand_sog_tracker.core.kinematics import fingertips, global_rotation, skeleton_points
from hand_sog_tracker.errors import DepthImageError, InputError, IntrinsicsError
from hand_sog_tracker.ros.conversions import (
    SKELETON_BONES,
    SerialisedMarkers,
    bgr_to_image_msg,
    camera_info_to_intrinsics,
    delete_all_markers,
    diagnostic_array,
    fingertip_markers,
    image_to_depth_mm,
    joint_state_msg,
    pose_msg,
    rotation_to_quaternion,
    stamp_to_ns,
)

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


def image_fields(arr: np.ndarray, encoding: str, bigendian: bool = False, pad: int = 0) -> dict:
    """Fields of an Image holding ``arr`` (H, W) with ``pad`` bytes of padding per row."""
    dt = arr.dtype.newbyteorder(">" if bigendian else "<")
    rows = np.ascontiguousarray(arr.astype(dt)).view(np.uint8).reshape(arr.shape[0], -1)
    padded = np.concatenate([rows, np.full((arr.shape[0], pad), 0xAB, np.uint8)], axis=1)
    return dict(
        height=arr.shape[0],
        width=arr.shape[1],
        encoding=encoding,
        is_bigendian=int(bigendian),
        step=padded.shape[1],
        data=padded.tobytes(),
    )


def make_rclpy_image(arr: np.ndarray, encoding: str, **kw) -> Image:
    return Image(**image_fields(arr, encoding, **kw))


@pytest.mark.parametrize("bigendian", [False, True])
@pytest.mark.parametrize("pad", [0, 6])
@pytest.mark.parametrize("container", ["bytes", "array", "list", "ndarray", "rclpy"])
def test_16uc1_is_read_with_padding_endianness_and_any_container(bigendian, pad, container) -> None:
    rng = np.random.default_rng(1)
    mm = rng.integers(0, 2000, size=(7, 9)).astype(np.uint16)
    mm[0, 0] = 0
    mm[3, 4] = 65535
    fields = image_fields(mm, "16UC1", bigendian=bigendian, pad=pad)
    raw = fields["data"]
    if container == "array":
        fields["data"] = array.array("B", raw)
    elif container == "list":
        fields["data"] = list(raw)
    elif container == "ndarray":
        fields["data"] = np.frombuffer(raw, np.uint8).copy()
    msg = Image(**fields) if container == "rclpy" else SimpleNamespace(**fields)
    depth = image_to_depth_mm(msg)
    assert depth.dtype == np.float32 and depth.shape == (7, 9)
    np.testing.assert_array_equal(depth, mm.astype(np.float32))


def test_mono16_and_rosbags_record() -> None:
    rng = np.random.default_rng(2)
    mm = rng.integers(1, 1000, size=(4, 5)).astype(np.uint16)
    fields = image_fields(mm, "mono16", pad=2)
    fields["data"] = np.frombuffer(fields["data"], np.uint8)
    stamp = TYPESTORE.types["builtin_interfaces/msg/Time"](sec=1, nanosec=2)
    header = TYPESTORE.types["std_msgs/msg/Header"](stamp=stamp, frame_id="cam")
    record = TYPESTORE.types["sensor_msgs/msg/Image"](header=header, **fields)
    np.testing.assert_array_equal(image_to_depth_mm(record), mm.astype(np.float32))


@pytest.mark.parametrize("bigendian", [False, True])
def test_32fc1_metres_to_mm_with_invalid_values_zeroed(bigendian) -> None:
    rng = np.random.default_rng(3)
    m = rng.uniform(0.2, 1.5, size=(6, 8)).astype(np.float32)
    m[0, 0], m[1, 1], m[2, 2], m[3, 3], m[4, 4] = np.nan, np.inf, -np.inf, 0.0, -0.5
    m[5, 5], m[0, 7] = 3e38, -0.0  # (3e38 m is Inf in mm)
    depth = image_to_depth_mm(make_rclpy_image(m, "32FC1", bigendian=bigendian, pad=4))
    with np.errstate(over="ignore"):
        expected = m * 1000.0
    bad = ~np.isfinite(expected) | (m <= 0)
    expected[bad] = 0.0
    np.testing.assert_allclose(depth, expected, rtol=1e-6)
    assert np.count_nonzero(depth == 0) == 7 and depth.flags.c_contiguous


@pytest.mark.parametrize(
    "change, match",
    [
        (dict(encoding="rgb8"), "unsupported depth encoding 'rgb8'"),
        (dict(encoding="8UC1"), "unsupported depth encoding"),
        (dict(step=15), "step 15 is smaller than width"),
        (dict(height=0), "zero size"),
        (dict(width=0), "zero size"),
        (dict(data=b"\x00" * 50), "truncated: 50 bytes, need 64"),
        (dict(data=[0, 256] * 32), "not a byte sequence"),
        (dict(data=np.zeros(32, np.uint16)), "must be uint8"),
    ],
)
def test_bad_images_raise_naming_the_problem(change, match) -> None:
    fields = image_fields(np.ones((4, 8), np.uint16), "16UC1")  # step 16, 64 bytes
    fields.update(change)
    with pytest.raises(DepthImageError, match=match):
        image_to_depth_mm(SimpleNamespace(**fields))


def test_last_row_padding_may_be_missing() -> None:
    mm = np.arange(12, dtype=np.uint16).reshape(3, 4) + 1
    fields = image_fields(mm, "16UC1", pad=4)
    fields["data"] = fields["data"][:-4]
    np.testing.assert_array_equal(image_to_depth_mm(SimpleNamespace(**fields)), mm)


def camera_info(**kw) -> CameraInfo:
    msg = CameraInfo(width=320, height=240)
    msg.k = [287.0, 0.0, 159.5, 0.0, 286.0, 119.5, 0.0, 0.0, 1.0]
    for key, value in kw.items():
        setattr(msg, key, value)
    return msg


def test_camera_info_k_and_size() -> None:
    intr = camera_info_to_intrinsics(camera_info())
    assert (intr.fx, intr.fy, intr.cx, intr.cy) == (287.0, 286.0, 159.5, 119.5)
    assert (intr.width, intr.height) == (320, 240)
    full = camera_info(roi=RegionOfInterest(x_offset=0, y_offset=0, width=320, height=240))
    assert camera_info_to_intrinsics(full) == intr


def test_camera_info_binning_scales_intrinsics() -> None:
    intr = camera_info_to_intrinsics(camera_info(binning_x=2, binning_y=4))
    assert (intr.fx, intr.cx, intr.width) == (143.5, 79.75, 160)
    assert (intr.fy, intr.cy, intr.height) == (71.5, 29.875, 60)


def test_camera_info_from_rosbags_record() -> None:
    T = TYPESTORE.types
    header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="c")
    roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    rec = T["sensor_msgs/msg/CameraInfo"](
        header=header, height=480, width=640, distortion_model="plumb_bob", d=np.zeros(5),
        k=np.array([580.0, 0, 320, 0, 581.0, 240, 0, 0, 1]), r=np.eye(3).ravel(), p=np.zeros(12),
        binning_x=0, binning_y=0, roi=roi,
    )
    intr = camera_info_to_intrinsics(rec)
    assert (intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height) == (580, 581, 320, 240, 640, 480)


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(k=[0.0] * 9), "all zeros"),
        (dict(roi=RegionOfInterest(x_offset=10, y_offset=0, width=100, height=100)), "ROI"),
        (dict(width=0), "zero image size"),
        (dict(k=[-287.0, 0, 160, 0, 286.0, 120, 0, 0, 1]), "focal length fx=-287 px is implausible"),
        (dict(k=[1e9, 0, 160, 0, 1e9, 120, 0, 0, 1]), "fx=1e.09 px is implausible for a 320x240"),
        (dict(k=[1e-6, 0, 160, 0, 1e-6, 120, 0, 0, 1]), "fx=1e-06 px is implausible"),
        (dict(k=[60 * 287.0, 0, 160, 0, 60 * 286.0, 120, 0, 0, 1]), "fx=17220 px is implausible"),
        (dict(k=[287.0, 0, 160, 0, 1200.0, 120, 0, 0, 1]), "differ by more than 3x"),
        (dict(k=[287.0, 0, 640, 0, 286.0, 120, 0, 0, 1]), r"principal point \(640, 120\) px lies outside"),
        (dict(k=[287.0, 0, 160, 0, 286.0, -5, 0, 0, 1]), "principal point"),
        (dict(k=[np.nan, 0, 160, 0, 286.0, 120, 0, 0, 1]), "NaN"),
    ],
)
def test_bad_camera_info_raises(kw, match) -> None:
    with pytest.raises(IntrinsicsError, match=match):
        camera_info_to_intrinsics(camera_info(**kw))


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def test_rotation_to_quaternion_round_trip_including_half_turns() -> None:
    rng = np.random.default_rng(4)
    mats = [np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0]), np.eye(3)]
    for _ in range(50):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        mats.append(q * np.sign(np.linalg.det(q)))
    for R in mats:
        q = rotation_to_quaternion(R)
        assert q[3] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
        np.testing.assert_allclose(quat_to_matrix(q), R, atol=1e-9)
    with pytest.raises(InputError):
        rotation_to_quaternion(np.eye(4))


def header(sec: int = 12, nanosec: int = 345, frame: str = "depth_optical") -> Header:
    h = Header(frame_id=frame)
    h.stamp.sec, h.stamp.nanosec = sec, nanosec
    return h


def test_joint_state_and_pose_messages() -> None:
    rng = np.random.default_rng(5)
    theta = rest_pose((10.0, -20.0, 400.0))
    theta[3:6] += rng.uniform(-0.5, 0.5, 3)
    theta[6:] = rng.uniform(-0.3, 0.3, 20)
    h = header()
    js = joint_state_msg(h, theta)
    assert tuple(js.name) == JOINT_NAMES and len(js.name) == 20
    np.testing.assert_allclose(js.position, theta[6:])
    assert js.header.stamp.sec == 12 and js.header.frame_id == "depth_optical"
    ps = pose_msg(h, theta)
    p = ps.pose.position
    np.testing.assert_allclose([p.x, p.y, p.z], [0.010, -0.020, 0.400])
    o = ps.pose.orientation
    np.testing.assert_allclose(quat_to_matrix(np.array([o.x, o.y, o.z, o.w])), global_rotation(theta), atol=1e-9)
    assert ps.header.frame_id == "depth_optical" and stamp_to_ns(ps.header.stamp) == 12_000_000_345
    with pytest.raises(InputError):
        joint_state_msg(h, theta[:20])


def test_fingertip_and_skeleton_markers_in_metres() -> None:
    model = default_hand_model()
    theta = rest_pose((0.0, 0.0, 450.0))
    tips = fingertips(model, theta)
    skel = skeleton_points(model, theta)
    arr = fingertip_markers(header(), tips, skel, model.tip_radii)
    spheres = [m for m in arr.markers if m.ns == "fingertips"]
    assert [m.id for m in spheres] == [0, 1, 2, 3, 4]
    assert all(m.type == Marker.SPHERE and m.action == Marker.ADD for m in spheres)
    got = np.array([[m.pose.position.x, m.pose.position.y, m.pose.position.z] for m in spheres])
    np.testing.assert_allclose(got, tips / 1000.0)
    np.testing.assert_allclose([m.scale.x for m in spheres], 2 * model.tip_radii / 1000.0)
    (line,) = [m for m in arr.markers if m.ns == "skeleton"]
    assert line.type == Marker.LINE_LIST and len(line.points) == 2 * len(SKELETON_BONES) == 40
    pts = np.array([[q.x, q.y, q.z] for q in line.points])
    np.testing.assert_allclose(pts[0], skel[0] / 1000.0)  # the first bone starts at the wrist
    np.testing.assert_allclose(pts[7], skel[4] / 1000.0)  # ... and the thumb ends at its tip
    assert all(m.header.frame_id == "depth_optical" for m in arr.markers)
    (clear,) = delete_all_markers(header()).markers
    assert clear.action == Marker.DELETEALL


def test_serialised_markers_are_the_messages_bytes() -> None:
    """The node's fingertip markers written into a template: received, the same message as the
    one built and serialised (stamps, frame ids, radii, a fallback without a skeleton)."""
    from builtin_interfaces.msg import Time
    from rclpy.serialization import deserialize_message, serialize_message
    from visualization_msgs.msg import MarkerArray

    model = default_hand_model()
    rng = np.random.default_rng(11)
    markers = SerialisedMarkers(1.0)
    stamps = [(0, 0), (-(2**31), 999_999_999), (2**31 - 1, 1), (12, 345)]
    for i in range(24):
        sec, nanosec = stamps[i % 4]
        h = Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=("cam", "", "camera_depth_optical_frame")[i % 3])
        tips, skel = rng.normal(0.0, 300.0, (5, 3)), rng.normal(0.0, 300.0, (21, 3))
        radii = model.tip_radii * (1.0 + 0.1 * (i % 2))
        for sk in (skel, None) if i % 6 == 0 else (skel,):
            got = deserialize_message(markers(h, tips, sk, radii), MarkerArray)
            assert got == deserialize_message(serialize_message(markers.message(h, tips, sk, radii)), MarkerArray)
            assert all((m.lifetime.sec, m.lifetime.nanosec) == (1, 0) for m in got.markers)
        assert markers._template is not None  # (the template path was taken)
    # Without a lifetime (the per-hand topics): what fingertip_markers builds.
    h = Header(stamp=Time(sec=7, nanosec=8), frame_id="cam")
    got = deserialize_message(SerialisedMarkers(0.0)(h, tips, skel, model.tip_radii), MarkerArray)
    assert got == deserialize_message(serialize_message(fingertip_markers(h, tips, skel, model.tip_radii)), MarkerArray)


def test_bgr_image_and_diagnostics() -> None:
    rng = np.random.default_rng(6)
    bgr = rng.integers(0, 256, size=(5, 7, 3)).astype(np.uint8)
    msg = bgr_to_image_msg(header(), bgr)
    assert (msg.encoding, msg.step, msg.height, msg.width) == ("bgr8", 21, 5, 7)
    np.testing.assert_array_equal(np.frombuffer(bytes(msg.data), np.uint8).reshape(5, 7, 3), bgr)
    d = diagnostic_array(header().stamp, "n", "cam", b"\x01", "slow", {"rate": 29.97123, "dropped": 3})
    (st,) = d.status
    assert st.level == b"\x01" and st.hardware_id == "cam"
    assert {kv.key: kv.value for kv in st.values} == {"rate": "29.971", "dropped": "3"}


def test_keypoints_follow_the_mediapipe_order() -> None:
    from hand_sog_tracker.ros.conversions import KEYPOINT_NAMES, keypoints_msg

    model = default_hand_model()
    th = rest_pose((10.0, -20.0, 400.0))
    th[6:] = np.linspace(0.05, 0.5, 20)
    sk, tips = skeleton_points(model, th), fingertips(model, th)
    msg = keypoints_msg(Header(frame_id="cam"), sk, tips)
    assert msg.header.frame_id == "cam" and len(msg.poses) == 21
    pts = np.array([[p.position.x, p.position.y, p.position.z] for p in msg.poses]) * 1000.0
    assert all(p.orientation.w == 1.0 for p in msg.poses)
    # MediaPipe: 0 wrist, 1-4 thumb CMC MCP IP TIP, 5-8 index MCP PIP DIP TIP, ... 17-20 little.
    assert KEYPOINT_NAMES[0] == "wrist" and KEYPOINT_NAMES[1:5] == ("thumb_cmc", "thumb_mcp", "thumb_ip", "thumb_tip")
    assert KEYPOINT_NAMES[5:9] == ("index_mcp", "index_pip", "index_dip", "index_tip")
    assert KEYPOINT_NAMES[17] == "little_mcp" and KEYPOINT_NAMES[20] == "little_tip"
    np.testing.assert_allclose(pts[0], th[:3], atol=1e-9)  # wrist = pose translation
    np.testing.assert_allclose(pts[[4, 8, 12, 16, 20]], tips, atol=1e-9)  # TIPs = reported fingertips
    for c in range(5):  # the chain's three joints: CMC/MCP, MCP/PIP, IP/DIP
        np.testing.assert_allclose(pts[1 + 4 * c : 4 + 4 * c], sk[1 + 4 * c : 4 + 4 * c], atol=1e-9)
    # The index MCP is the index chain's base: model.bases[1] in the hand frame.
    np.testing.assert_allclose(pts[5], global_rotation(th) @ model.bases[1] + th[:3], atol=1e-9)


def test_joint_state_with_virtual_wrist_joints() -> None:
    th = rest_pose((10.0, -20.0, 400.0))
    th[3:6] = (2.9, 0.1, -0.3)
    msg = joint_state_msg(Header(), th, wrist_joints=True)
    assert list(msg.name) == list(JOINT_NAMES) + ["hand_tx", "hand_ty", "hand_tz", "hand_rz", "hand_rx", "hand_ry"]
    np.testing.assert_allclose(msg.position[20:], [0.01, -0.02, 0.4, -0.3, 2.9, 0.1])
    assert len(joint_state_msg(Header(), th).name) == 20


@pytest.mark.parametrize("right", [True, False])
def test_hand_transforms_put_the_fingertips_where_the_tracker_reports_them(right: bool) -> None:
    from hand_sog_tracker.ros.conversions import TF_TIP_FRAMES, hand_transforms

    model = default_hand_model(right)
    th = rest_pose((10.0, -20.0, 400.0))
    th[3:6] += (0.3, -0.2, 0.5)
    th[6:] = np.linspace(0.05, 0.5, 20)
    tips = fingertips(model, th)
    header = Header(frame_id="cam")
    header.stamp.sec = 5
    tfs = hand_transforms(header, th, tips)
    assert [t.child_frame_id for t in tfs] == ["hand_wrist", *TF_TIP_FRAMES]
    assert tfs[0].header.frame_id == "cam" and all(t.header.frame_id == "hand_wrist" for t in tfs[1:])
    assert all(t.header.stamp.sec == 5 for t in tfs)
    r = tfs[0].transform.rotation
    q = np.array([r.x, r.y, r.z, r.w])
    np.testing.assert_allclose(q, rotation_to_quaternion(global_rotation(th)))
    tr = tfs[0].transform.translation
    wrist = np.array([tr.x, tr.y, tr.z])
    rot = global_rotation(th)
    for t, tip in zip(tfs[1:], tips):
        local = np.array([t.transform.translation.x, t.transform.translation.y, t.transform.translation.z])
        np.testing.assert_allclose((rot @ local + wrist) * 1000.0, tip, atol=1e-9)


@pytest.mark.parametrize("codec", ["png", "rvl"])
def test_compressed_depth_from_rclpy_and_rosbags_messages(codec: str) -> None:
    from sensor_msgs.msg import CompressedImage

    from hand_sog_tracker.compressed_depth import encode_compressed_depth
    from hand_sog_tracker.ros.conversions import compressed_image_to_depth_mm

    d = np.random.default_rng(4).integers(0, 1500, (12, 16)).astype(np.float64)
    fmt, data = encode_compressed_depth(d, "16UC1", codec)
    msg = CompressedImage(format=fmt, data=data)  # rclpy stores data as array.array('B')
    np.testing.assert_array_equal(compressed_image_to_depth_mm(msg), d)
    rec = TYPESTORE.types["sensor_msgs/msg/CompressedImage"](
        header=TYPESTORE.types["std_msgs/msg/Header"](
            stamp=TYPESTORE.types["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="c"
        ),
        format=fmt,
        data=np.frombuffer(data, np.uint8),
    )
    np.testing.assert_array_equal(compressed_image_to_depth_mm(rec), d)
    with pytest.raises(DepthImageError, match="truncated"):
        compressed_image_to_depth_mm(CompressedImage(format=fmt, data=data[:10]))
