"""The node's input bookkeeping (hand_sog_tracker.ros.frame_input), without a node."""

from __future__ import annotations

from sensor_msgs.msg import Image

from hand_sog_tracker.core.types import Intrinsics
from hand_sog_tracker.ros.frame_input import RATE_WINDOW, Backlog, CameraRate

MS = 1_000_000  # ns


def _image(stamp_ns: int) -> Image:
    msg = Image()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    return msg


def test_missed_frames_follow_the_camera_period_after_a_burst() -> None:
    rate = CameraRate()
    stamps = [i * 5 * MS for i in range(40)]  # 200 Hz burst
    stamps += [stamps[-1] + (i + 1) * 33 * MS for i in range(RATE_WINDOW + 5)]  # then 30 Hz
    missed = [rate.missed_before(s) for s in stamps]
    assert sum(missed[40 + RATE_WINDOW :]) == 0  # the burst is forgotten
    assert rate.period_ns == 33 * MS
    assert rate.missed_before(stamps[-1] + 4 * 33 * MS) == 3  # three frames lost in DDS
    assert rate.missed_before(stamps[-1] + 4 * 33 * MS + 2_000 * MS) == 0  # a pause, not losses
    assert rate.period_ns is None


def test_backlog_drops_the_oldest_beyond_the_lag_and_keeps_the_newest() -> None:
    backlog = Backlog()
    for i in range(10):
        backlog.images.append((_image(i * 10 * MS), 0))
    assert backlog.trim(90 * MS, max_lag_ms=25.0, size=20) == 7
    assert [m.header.stamp.nanosec // MS for m, _ in backlog.images] == [70, 80, 90]
    assert backlog.trim(90 * MS, max_lag_ms=0.0, size=20) == 2  # newest only
    assert backlog.trim(10_000 * MS, max_lag_ms=0.0, size=20) == 0  # never the last one


def test_an_image_gets_the_camera_info_of_its_stamp_else_the_one_before() -> None:
    backlog = Backlog()
    a = Intrinsics(fx=300.0, fy=300.0, cx=160.0, cy=120.0, width=320, height=240)
    b = Intrinsics(fx=600.0, fy=600.0, cx=320.0, cy=240.0, width=640, height=480)
    backlog.infos.append((1, 100 * MS, a, ""))
    backlog.infos.append((2, 200 * MS, b, ""))
    assert backlog.intrinsics_for(100 * MS, seen=2) == (a, "")  # same stamp, though received later
    assert backlog.intrinsics_for(150 * MS, seen=1) == (a, "")  # none of its stamp: the one before
    assert backlog.intrinsics_for(150 * MS, seen=0) is None
