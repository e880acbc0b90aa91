"""The node's input bookkeeping: the backlog of images waiting to be tracked, and the camera rate.

Plain Python (no rclpy calls): the node feeds it the messages its subscriptions deliver.  The
images are tracked in order; :meth:`Backlog.trim` drops the oldest whole when the node falls
``max_lag_ms`` (by image stamps) behind the newest, and :class:`CameraRate` counts the frames
the camera sent that never arrived.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass, field

import numpy as np
from sensor_msgs.msg import CompressedImage, Image

from hand_sog_tracker.core.types import Intrinsics
from hand_sog_tracker.interface import stamp_to_ns

__all__ = ["INPUT_DEPTH", "INFO_HISTORY", "MAX_GAP_S", "RATE_WINDOW", "Backlog", "CameraRate"]

#: Depth (KEEP_LAST) of the image and CameraInfo subscriptions, and the most images the backlog
#: holds (a KEEP_LAST override of the depth sets both): 200 ms of a 100 Hz camera, what
#: ``max_lag_ms`` keeps by default; images of 640x480 16UC1 take 0.6 MB each.
INPUT_DEPTH = 20
#: CameraInfo messages kept to pair with the images of the backlog by stamp.
INFO_HISTORY = 2 * INPUT_DEPTH
#: A gap between two received images longer than this is a pause, not missed frames.
MAX_GAP_S = 1.0
#: Intervals between received images whose running median is the camera period (a burst at
#: 200 Hz is forgotten after this many intervals at the camera's own rate).
RATE_WINDOW = 15


@dataclass
class Backlog:
    """Images received but not yet processed, oldest first, with the CameraInfo to pair them with.

    ``images`` holds (image, CameraInfo count when it was received); ``infos`` the last
    :data:`INFO_HISTORY` CameraInfo messages as (count, stamp ns, intrinsics or None, problem).
    """

    images: collections.deque[tuple[Image | CompressedImage, int]] = field(default_factory=collections.deque)
    infos: collections.deque[tuple[int, int, Intrinsics | None, str]] = field(
        default_factory=lambda: collections.deque(maxlen=INFO_HISTORY)
    )
    n_infos: int = 0  # CameraInfo messages received

    def intrinsics_for(self, stamp: int, seen: int) -> tuple[Intrinsics | None, str] | None:
        """The intrinsics (or the problem) for an image of ``stamp`` received after ``seen``
        CameraInfo messages: those of the newest CameraInfo of the same stamp (it may come just
        after the image), else of the newest received before the image; None if there is none."""
        before = None
        for n, info_stamp, intr, problem in reversed(self.infos):
            if info_stamp == stamp:
                return intr, problem
            if before is None and n <= seen:
                before = (intr, problem)
        return before

    def trim(self, newest_ns: int, max_lag_ms: float, size: int) -> int:
        """Drop the oldest images while more than ``size`` wait or the newest received stamp
        is more than ``max_lag_ms`` ahead of theirs (never the last); how many were dropped."""
        dropped = 0
        while len(self.images) > 1 and (
            len(self.images) > size or (newest_ns - stamp_to_ns(self.images[0][0].header.stamp)) * 1e-6 > max_lag_ms
        ):
            self.images.popleft()
            dropped += 1
        return dropped


class CameraRate:
    """The camera period from the stamps of the images received, and the frames it implies lost."""

    def __init__(self) -> None:
        self.last_stamp_ns: int | None = None  # stamp of the last received image
        self.period_ns: int | None = None  # camera period: median of the recent intervals
        self._intervals: collections.deque[int] = collections.deque(maxlen=RATE_WINDOW)

    def missed_before(self, stamp: int) -> int:
        """Frames the camera must have sent between the last received image and this one.

        The camera period is the running median of the last :data:`RATE_WINDOW` intervals
        between the images received (robust to a burst, a stall or a missed frame, and forgotten
        within that many frames when the rate changes); a gap over :data:`MAX_GAP_S` is a pause
        of the stream, not lost frames, and like a jump back starts the estimate anew.
        """
        prev, self.last_stamp_ns = self.last_stamp_ns, stamp
        if prev is None or stamp == prev:
            return 0
        gap = stamp - prev
        if gap < 0 or gap > MAX_GAP_S * 1e9:  # bag loop, clock reset or pause: learn the period anew
            self._intervals.clear()
            self.period_ns = None
            return 0
        period = self.period_ns
        self._intervals.append(gap)
        self.period_ns = int(np.median(self._intervals))
        if period is None:
            return 0
        return max(int(round(gap / period)) - 1, 0)
