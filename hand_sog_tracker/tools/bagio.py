"""Reading and writing depth bags with ``rosbags`` (no ROS installation needed).

One job: reading depth bags; kept together because the reader, its topic checks and its error
messages are one contract.  The writer (:mod:`hand_sog_tracker.tools.bagwrite`) and the
message builders and bag-convention names (:mod:`hand_sog_tracker.tools.bagmsgs`) are
re-exported here, so ``from hand_sog_tracker.tools.bagio import ...`` serves both.

Bag convention (contract 5)
---------------------------
``/camera/depth/image_rect_raw`` (sensor_msgs/Image)
    Depth images: ``16UC1`` millimetres or ``32FC1`` metres.  Instead, a bag may hold them
    compressed as ``compressed_depth_image_transport`` writes them: sensor_msgs/CompressedImage
    on ``/camera/depth/image_rect_raw/compressedDepth`` (or on the depth topic itself), format
    ``"16UC1; compressedDepth png"`` / ``"32FC1; compressedDepth rvl"`` ... (decoded by
    :mod:`hand_sog_tracker.compressed_depth`).
``/camera/depth/camera_info`` (sensor_msgs/CameraInfo)
    Intrinsics of the depth images (one per image, or at least one).
``/hand/ground_truth/fingertips`` (geometry_msgs/PoseArray)
    Five poses (thumb, index, middle, ring, little) whose positions are the
    fingertips in metres, in the depth image's optical frame, with the same
    header stamp as the depth image they belong to.

Reading goes through :class:`rosbags.highlevel.AnyReader`, so rosbag2
directories (sqlite3 or mcap storage, compressed or not) and ROS 1 ``.bag``
files are accepted.  Every failure of the bag itself is raised as
:class:`~hand_sog_tracker.errors.BagError`.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace, TracebackType
from typing import Any, Iterator

import numpy as np
from numpy.typing import NDArray
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Connection

from hand_sog_tracker.core.types import Intrinsics
from hand_sog_tracker.errors import BagError, HandSogError
from hand_sog_tracker.interface import (
    COMPRESSED_SUFFIX,
    camera_info_to_intrinsics,
    compressed_image_to_depth_mm,
    image_to_depth_mm,
    stamp_to_ns,
)
from hand_sog_tracker.tools.bagmsgs import (
    COMPRESSED_TYPE,
    DEPTH_TOPIC,
    GT_TOPIC,
    GT_TYPE,
    IMAGE_TYPE,
    INFO_TOPIC,
    INFO_TYPE,
    OPTICAL_FRAME,
    BagTopics,
    camera_info_msg,
    compressed_depth_msg,
    depth_image_msg,
    fingertips_from_msg,
    fingertips_msg,
    ns_to_stamp,
    typestore,
)
from hand_sog_tracker.tools.bagmsgs import describe_error as _describe
from hand_sog_tracker.tools.bagwrite import BagWriter, DepthSample, StorageName, write_depth_bag

__all__ = [
    "DEPTH_TOPIC",
    "INFO_TOPIC",
    "GT_TOPIC",
    "OPTICAL_FRAME",
    "IMAGE_TYPE",
    "COMPRESSED_TYPE",
    "COMPRESSED_SUFFIX",
    "INFO_TYPE",
    "GT_TYPE",
    "BagTopics",
    "BagFrame",
    "DepthBagReader",
    "BagWriter",
    "DepthSample",
    "StorageName",
    "write_depth_bag",
    "typestore",
    "resolve_bag_path",
    "open_bag",
    "iter_messages",
    "deserialize",
    "topic_table",
    "stamp_to_ns",
    "ns_to_stamp",
    "depth_image_msg",
    "compressed_depth_msg",
    "camera_info_msg",
    "fingertips_msg",
    "fingertips_from_msg",
]


# -- reading -------------------------------------------------------------------
def resolve_bag_path(path: str | Path) -> Path:
    """Normalise a user-given bag path.

    Accepts a rosbag2 directory, its ``metadata.yaml`` or one of its storage
    files (``.mcap``, ``.db3``), or a ROS 1 ``.bag`` file.

    Raises
    ------
    BagError
        If nothing readable is at ``path``.
    """
    p = Path(path)
    if not p.exists():
        raise BagError(f"bag not found: {p}")
    if p.is_file():
        if p.suffix == ".bag":
            return p
        if (p.parent / "metadata.yaml").is_file():
            return p.parent
        raise BagError(
            f"{p} is neither a ROS 1 .bag file nor inside a rosbag2 directory "
            "(a rosbag2 bag is a directory holding metadata.yaml)"
        )
    if not (p / "metadata.yaml").is_file():
        raise BagError(f"{p} is a directory without metadata.yaml, not a rosbag2 bag")
    return p


class open_bag:  # lower case: used like a function: ``with open_bag(path) as reader``
    """Context manager opening a bag with :class:`AnyReader`; errors become BagError.

    Parameters
    ----------
    path : str or Path
        See :func:`resolve_bag_path`.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = resolve_bag_path(path)
        self._reader: AnyReader | None = None

    def __enter__(self) -> AnyReader:
        try:
            reader = AnyReader([self.path], default_typestore=typestore())
            reader.open()
        except HandSogError:
            raise
        except Exception as err:  # rosbags raises many types on corrupt files
            raise BagError(f"cannot open bag {self.path} (corrupt, truncated or not a bag?): {_describe(err)}") from err
        self._reader = reader
        return reader

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        reader, self._reader = self._reader, None
        if reader is not None:
            try:
                reader.close()
            except Exception:  # noqa: BLE001 - closing a broken bag must not mask the real error
                pass


def topic_table(reader: AnyReader) -> dict[str, tuple[str, int]]:
    """Topics of an open bag: ``{name: (msgtype, message count)}``."""
    return {
        name: (info.msgtype or "?", int(info.msgcount)) for name, info in sorted(reader.topics.items())
    }


def _format_topics(table: dict[str, tuple[str, int]]) -> str:
    if not table:
        return "  (the bag has no topics)"
    return "\n".join(f"  {name}  [{typ}, {n} msgs]" for name, (typ, n) in table.items())


def require_topic(
    reader: AnyReader, path: Path, topic: str, msgtype: str | tuple[str, ...], role: str
) -> list[Connection]:
    """Connections of ``topic``; BagError listing the bag's topics if absent or mistyped.

    ``msgtype`` may be a tuple of accepted types.
    """
    table = topic_table(reader)
    if topic not in table:
        raise BagError(
            f"{role} topic {topic!r} not in bag {path}; the bag's topics are:\n{_format_topics(table)}"
        )
    typ, count = table[topic]
    accepted = (msgtype,) if isinstance(msgtype, str) else msgtype
    if typ not in accepted:
        raise BagError(f"{role} topic {topic!r} in bag {path} has type {typ}, expected {' or '.join(accepted)}")
    if count == 0:
        raise BagError(
            f"{role} topic {topic!r} in bag {path} has no messages; the bag's topics are:\n"
            f"{_format_topics(table)}"
        )
    return [c for c in reader.connections if c.topic == topic]


def iter_messages(
    reader: AnyReader, path: Path, connections: list[Connection], start_ns: int | None = None
) -> Iterator[tuple[Connection, int, bytes]]:
    """Raw messages ``(connection, log time ns, serialized bytes)``; read errors become BagError."""
    gen = reader.messages(connections=connections, start=start_ns)
    while True:
        try:
            item = next(gen)
        except StopIteration:
            return
        except HandSogError:
            raise
        except Exception as err:  # truncated/corrupt storage raises many types
            raise BagError(f"bag {path} is corrupt or truncated: {_describe(err)}") from err
        yield item


def deserialize(reader: AnyReader, path: Path, raw: bytes, connection: Connection) -> Any:
    """Deserialise one message; failures become BagError."""
    try:
        return reader.deserialize(raw, connection.msgtype)
    except Exception as err:
        raise BagError(
            f"bag {path}: cannot decode a {connection.msgtype} message on {connection.topic}: {_describe(err)}"
        ) from err


@dataclass(frozen=True, eq=False)
class BagFrame:
    """One depth image of a bag with its intrinsics and ground truth.

    Attributes
    ----------
    index : int
        0-based position among the depth images of the bag.
    stamp_ns : int
        Header stamp of the depth image, nanoseconds.
    log_time_ns : int
        Time the message was recorded, nanoseconds (drives replay rate).
    depth_mm : array, shape (H, W) float32, or None
        Depth in millimetres (0 = invalid); None if the image could not be
        decoded (see ``error``).
    intrinsics : Intrinsics or None
        Intrinsics of the CameraInfo matched to this image.
    truth_mm : array, shape (5, 3) or None
        Ground-truth fingertips (thumb .. little), millimetres, optical frame;
        None when the bag has none for this stamp.
    error : str or None
        Why the image is unusable (bad encoding, size mismatch...).
    """

    index: int
    stamp_ns: int
    log_time_ns: int
    depth_mm: NDArray[np.float32] | None
    intrinsics: Intrinsics | None
    truth_mm: NDArray[np.float64] | None
    error: str | None = None


def _ros1_info_adapter(msg: Any) -> Any:
    """ROS 1 CameraInfo (``K``, ``D``...) seen with ROS 2 field names."""
    if hasattr(msg, "k") or not hasattr(msg, "K"):
        return msg
    return SimpleNamespace(
        header=msg.header,
        height=msg.height,
        width=msg.width,
        distortion_model=msg.distortion_model,
        d=msg.D,
        k=msg.K,
        r=msg.R,
        p=msg.P,
        binning_x=msg.binning_x,
        binning_y=msg.binning_y,
        roi=msg.roi,
    )


class DepthBagReader:
    """Depth frames, intrinsics and ground truth of one bag (contract 5).

    Use as a context manager; on entry the topics are checked and the
    (small) CameraInfo and ground-truth messages are loaded, then
    :meth:`frames` streams the depth images in recording order.

    Parameters
    ----------
    path : str or Path
        Bag (see :func:`resolve_bag_path`).
    topics : BagTopics
        Topic names.
    require_truth : bool
        If True a missing or empty ground-truth topic is a BagError; if False
        the bag is read without ground truth.

    Raises
    ------
    BagError
        Missing topic (the message lists the bag's topics), wrong type, no
        CameraInfo, unusable CameraInfo, corrupt or truncated bag.
    """

    def __init__(self, path: str | Path, topics: BagTopics = BagTopics(), require_truth: bool = True) -> None:
        self._opener = open_bag(path)
        self.path: Path = self._opener.path
        self.topics = topics
        self.require_truth = require_truth
        self._reader: AnyReader | None = None
        self._depth_conns: list[Connection] = []
        self._infos: list[tuple[int, Intrinsics]] = []
        #: Ground truth by header stamp (ns): fingertips (5, 3) mm.
        self.truth: dict[int, NDArray[np.float64]] = {}
        #: ``{topic: (msgtype, count)}`` of the whole bag.
        self.topic_table: dict[str, tuple[str, int]] = {}
        #: Number of depth images announced by the bag index.
        self.n_depth: int = 0
        #: The topic the depth images are read from (``topics.depth`` or its ``/compressedDepth``).
        self.depth_topic: str = topics.depth
        #: Whether that topic holds compressedDepth ``CompressedImage`` messages.
        self.depth_compressed: bool = False

    def __enter__(self) -> "DepthBagReader":
        self._reader = self._opener.__enter__()
        try:
            self._load()
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._reader = None
        self._opener.__exit__(exc_type, exc, tb)

    def _load(self) -> None:

        reader = self._reader
        assert reader is not None
        self.topic_table = topic_table(reader)
        depth_topic = self.topics.depth
        alt = depth_topic + COMPRESSED_SUFFIX
        if depth_topic not in self.topic_table and self.topic_table.get(alt, ("", 0))[0] == COMPRESSED_TYPE:
            depth_topic = alt
        self._depth_conns = require_topic(reader, self.path, depth_topic, (IMAGE_TYPE, COMPRESSED_TYPE), "depth")
        self.depth_topic = depth_topic
        self.depth_compressed = self.topic_table[depth_topic][0] == COMPRESSED_TYPE
        self.n_depth = self.topic_table[depth_topic][1]
        info_conns = require_topic(reader, self.path, self.topics.info, INFO_TYPE, "CameraInfo")
        truth_conns: list[Connection] = []
        if self.require_truth or self.topics.truth in self.topic_table:
            truth_conns = require_topic(reader, self.path, self.topics.truth, GT_TYPE, "ground-truth")
        infos: dict[int, Intrinsics] = {}
        for conn, _, raw in iter_messages(reader, self.path, info_conns + truth_conns):
            msg = deserialize(reader, self.path, raw, conn)
            stamp = stamp_to_ns(msg.header.stamp)
            if conn.topic == self.topics.info:
                if stamp in infos:
                    continue
                try:
                    infos[stamp] = camera_info_to_intrinsics(_ros1_info_adapter(msg))
                except HandSogError as err:
                    raise BagError(f"bag {self.path}: unusable CameraInfo at stamp {stamp} ns: {err}") from err
            else:
                self.truth[stamp] = fingertips_from_msg(msg)
        if not infos:
            raise BagError(f"bag {self.path}: no CameraInfo message could be read on {self.topics.info!r}")
        self._infos = sorted(infos.items())

    def intrinsics_at(self, stamp_ns: int) -> Intrinsics:
        """CameraInfo with this stamp, else the latest before it, else the first one."""
        k = bisect.bisect_right(self._infos, stamp_ns, key=lambda item: item[0]) - 1
        return self._infos[max(k, 0)][1]

    @property
    def reader(self) -> AnyReader:
        """The open rosbags reader."""
        if self._reader is None:
            raise BagError("DepthBagReader is not open (use it as a context manager)")
        return self._reader

    def connections(self, which: tuple[str, ...] = ("depth", "info")) -> list[Connection]:
        """Connections of the named roles (``depth`` = :attr:`depth_topic`, ``info``, ``truth``)."""
        names = {self.depth_topic if w == "depth" else getattr(self.topics, w) for w in which}
        return [c for c in self.reader.connections if c.topic in names]

    def frames(self) -> Iterator[BagFrame]:
        """Depth images in recording order.

        Raises
        ------
        BagError
            If the bag turns out to be truncated or corrupt while reading.
        """

        decode = compressed_image_to_depth_mm if self.depth_compressed else image_to_depth_mm

        reader = self._reader
        if reader is None:
            raise BagError("DepthBagReader is not open (use it as a context manager)")
        for index, (conn, log_ns, raw) in enumerate(iter_messages(reader, self.path, self._depth_conns)):
            msg = deserialize(reader, self.path, raw, conn)
            stamp = stamp_to_ns(msg.header.stamp)
            intr = self.intrinsics_at(stamp)
            depth: NDArray[np.float32] | None = None
            error: str | None = None
            try:
                depth = decode(msg)
                if depth.shape != (intr.height, intr.width):
                    raise BagError(
                        f"depth image is {depth.shape[1]}x{depth.shape[0]} but its CameraInfo is "
                        f"{intr.width}x{intr.height}"
                    )
            except HandSogError as err:
                depth, error = None, str(err)
            yield BagFrame(
                index=index,
                stamp_ns=stamp,
                log_time_ns=int(log_ns),
                depth_mm=depth,
                intrinsics=intr,
                truth_mm=self.truth.get(stamp),
                error=error,
            )
