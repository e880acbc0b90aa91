"""Reading and writing depth bags with ``rosbags`` (no ROS installation needed).

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
import functools
import shutil
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace, TracebackType
from typing import Any, Final, Iterable, Iterator, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Connection
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from hand_sog_tracker import interface
from hand_sog_tracker.core.types import Intrinsics
from hand_sog_tracker.errors import BagError, HandSogError, InputError
from hand_sog_tracker.interface import (
    COMPRESSED_SUFFIX,
    camera_info_to_intrinsics,
    compressed_image_to_depth_mm,
    image_to_depth_mm,
    stamp_to_ns,
)

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

#: Topics of the bag convention (:mod:`hand_sog_tracker.interface`, absolute names).
DEPTH_TOPIC: Final[str] = interface.BAG_DEPTH_TOPIC
INFO_TOPIC: Final[str] = interface.BAG_INFO_TOPIC
GT_TOPIC: Final[str] = interface.GROUND_TRUTH_TOPIC
OPTICAL_FRAME: Final[str] = "camera_depth_optical_frame"
IMAGE_TYPE: Final[str] = "sensor_msgs/msg/Image"
COMPRESSED_TYPE: Final[str] = "sensor_msgs/msg/CompressedImage"
INFO_TYPE: Final[str] = "sensor_msgs/msg/CameraInfo"
GT_TYPE: Final[str] = "geometry_msgs/msg/PoseArray"

StorageName = Literal["mcap", "sqlite3"]


@functools.lru_cache(maxsize=1)
def typestore() -> Typestore:
    """The ROS 2 Jazzy type store used to build and serialise messages."""
    return get_typestore(Stores.ROS2_JAZZY)


# -- small message helpers ---------------------------------------------------
# stamp_to_ns is :func:`hand_sog_tracker.interface.stamp_to_ns` (imported above).
def ns_to_stamp(ns: int) -> Any:
    """Nanoseconds to a rosbags ``builtin_interfaces/msg/Time``."""
    try:
        return interface.ns_to_stamp(ns, typestore().types["builtin_interfaces/msg/Time"])
    except InputError as err:
        raise BagError(str(err)) from None


def _header(stamp_ns: int, frame_id: str) -> Any:
    Header = typestore().types["std_msgs/msg/Header"]
    return Header(stamp=ns_to_stamp(stamp_ns), frame_id=frame_id)


def depth_image_msg(
    depth_mm: ArrayLike,
    stamp_ns: int,
    frame_id: str = OPTICAL_FRAME,
    encoding: Literal["16UC1", "32FC1"] = "16UC1",
) -> Any:
    """Build a rosbags ``sensor_msgs/msg/Image`` from a depth map.

    Parameters
    ----------
    depth_mm : array, shape (H, W)
        Depth in millimetres; 0, NaN or Inf = invalid.
    stamp_ns : int
        Header stamp, nanoseconds.
    frame_id : str
    encoding : {"16UC1", "32FC1"}
        ``16UC1``: uint16 millimetres (rounded, invalid = 0, clipped to 65535);
        ``32FC1``: float32 **metres** (REP 118), invalid = NaN.
    """
    d = np.asarray(depth_mm, dtype=np.float64)
    if d.ndim != 2:
        raise BagError(f"depth image must be 2-D (H, W), got shape {d.shape}")
    valid = np.isfinite(d) & (d > 0)
    if encoding == "16UC1":
        pix = np.where(valid, np.clip(np.rint(d), 0, 65535), 0).astype("<u2")
    elif encoding == "32FC1":
        pix = np.where(valid, d / 1000.0, np.nan).astype("<f4")
    else:
        raise BagError(f"unsupported depth encoding {encoding!r} (use 16UC1 or 32FC1)")
    Image = typestore().types[IMAGE_TYPE]
    h, w = pix.shape
    return Image(
        header=_header(stamp_ns, frame_id),
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=0,
        step=w * pix.itemsize,
        data=np.frombuffer(np.ascontiguousarray(pix).tobytes(), dtype=np.uint8),
    )


def compressed_depth_msg(
    depth_mm: ArrayLike,
    stamp_ns: int,
    frame_id: str = OPTICAL_FRAME,
    encoding: Literal["16UC1", "32FC1"] = "16UC1",
    codec: Literal["png", "rvl"] = "png",
) -> Any:
    """A rosbags ``sensor_msgs/msg/CompressedImage`` as compressed_depth_image_transport writes it.

    See :func:`hand_sog_tracker.compressed_depth.encode_compressed_depth` (32FC1 quantises
    inverse depth with the plugin's default parameters).
    """
    from hand_sog_tracker.compressed_depth import encode_compressed_depth
    from hand_sog_tracker.errors import DepthImageError

    try:
        fmt, data = encode_compressed_depth(depth_mm, encoding, codec)
    except DepthImageError as err:
        raise BagError(str(err)) from err
    return typestore().types[COMPRESSED_TYPE](
        header=_header(stamp_ns, frame_id), format=fmt, data=np.frombuffer(data, dtype=np.uint8)
    )


def camera_info_msg(intrinsics: Intrinsics, stamp_ns: int, frame_id: str = OPTICAL_FRAME) -> Any:
    """Build a rosbags ``sensor_msgs/msg/CameraInfo`` (plumb bob, zero distortion)."""
    i = intrinsics
    CameraInfo = typestore().types[INFO_TYPE]
    Roi = typestore().types["sensor_msgs/msg/RegionOfInterest"]
    return CameraInfo(
        header=_header(stamp_ns, frame_id),
        height=i.height,
        width=i.width,
        distortion_model="plumb_bob",
        d=np.zeros(5, dtype=np.float64),
        k=np.array([i.fx, 0.0, i.cx, 0.0, i.fy, i.cy, 0.0, 0.0, 1.0]),
        r=np.eye(3).reshape(-1),
        p=np.array([i.fx, 0.0, i.cx, 0.0, 0.0, i.fy, i.cy, 0.0, 0.0, 0.0, 1.0, 0.0]),
        binning_x=0,
        binning_y=0,
        roi=Roi(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )


def fingertips_msg(fingertips_mm: ArrayLike, stamp_ns: int, frame_id: str = OPTICAL_FRAME) -> Any:
    """Ground truth as a rosbags ``geometry_msgs/msg/PoseArray``.

    Parameters
    ----------
    fingertips_mm : array, shape (5, 3)
        Fingertips thumb .. little, millimetres (written as metres).
    """
    tips = np.asarray(fingertips_mm, dtype=np.float64)
    if tips.shape != (5, 3) or not np.all(np.isfinite(tips)):
        raise BagError(f"fingertips must be a finite (5, 3) array, got shape {tips.shape}")
    t = typestore().types
    Pose, Point, Quat = t["geometry_msgs/msg/Pose"], t["geometry_msgs/msg/Point"], t["geometry_msgs/msg/Quaternion"]
    poses = [
        Pose(position=Point(x=float(x), y=float(y), z=float(z)), orientation=Quat(x=0.0, y=0.0, z=0.0, w=1.0))
        for x, y, z in tips / 1000.0
    ]
    return t[GT_TYPE](header=_header(stamp_ns, frame_id), poses=poses)


def fingertips_from_msg(msg: Any) -> NDArray[np.float64]:
    """Fingertips (5, 3) in millimetres from a PoseArray (metres).

    Raises
    ------
    BagError
        If the array does not hold exactly five finite poses.
    """
    poses = list(msg.poses)
    if len(poses) != 5:
        raise BagError(
            f"ground-truth PoseArray at stamp {stamp_to_ns(msg.header.stamp)} ns has "
            f"{len(poses)} poses, expected 5 (thumb, index, middle, ring, little)"
        )
    tips = np.array([[p.position.x, p.position.y, p.position.z] for p in poses], dtype=np.float64) * 1000.0
    if not np.all(np.isfinite(tips)):
        raise BagError(f"ground-truth PoseArray at stamp {stamp_to_ns(msg.header.stamp)} ns is not finite")
    return tips


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


def _describe(err: BaseException) -> str:
    text = str(err).strip()
    return f"{type(err).__name__}: {text}" if text else type(err).__name__


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


@dataclass(frozen=True)
class BagTopics:
    """Topic names of a depth bag (defaults: contract 5)."""

    depth: str = DEPTH_TOPIC
    info: str = INFO_TOPIC
    truth: str = GT_TOPIC


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


# -- writing -------------------------------------------------------------------
class BagWriter:
    """Write a rosbag2 (ROS 2 Jazzy types, CDR) with ``rosbags``.

    Parameters
    ----------
    path : str or Path
        Bag directory to create; must not exist.
    storage : {"mcap", "sqlite3"}
    compress : bool
        zstd compression: per chunk for mcap (the mcap storage's own chunk
        compression, read by ``ros2 bag`` and rosbags), per message for sqlite3.

    Examples
    --------
    >>> with BagWriter(tmp / "bag") as w:                      # doctest: +SKIP
    ...     w.write(DEPTH_TOPIC, depth_image_msg(d, t), t)
    """

    def __init__(self, path: str | Path, storage: StorageName = "mcap", compress: bool = True) -> None:
        self.path = Path(path)
        if storage not in ("mcap", "sqlite3"):
            raise BagError(f"unknown storage {storage!r} (use mcap or sqlite3)")
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        try:
            self._writer = Writer(self.path, version=Writer.VERSION_LATEST, storage_plugin=plugin)
            if compress:
                mode = CompressionMode.STORAGE if storage == "mcap" else CompressionMode.MESSAGE
                self._writer.set_compression(mode, CompressionFormat.ZSTD)
        except Exception as err:  # rosbags WriterError etc.
            raise BagError(f"cannot create bag {self.path}: {_describe(err)}") from err
        self._conns: dict[str, Connection] = {}

    def __enter__(self) -> "BagWriter":
        try:
            self._writer.open()
        except Exception as err:
            raise BagError(f"cannot create bag {self.path}: {_describe(err)}") from err
        return self

    def write(self, topic: str, msg: Any, log_time_ns: int) -> None:
        """Serialise ``msg`` (a rosbags message) and append it on ``topic``."""
        ts = typestore()
        conn = self._conns.get(topic)
        if conn is None:
            conn = self._writer.add_connection(topic, msg.__msgtype__, typestore=ts)
            self._conns[topic] = conn
        elif conn.msgtype != msg.__msgtype__:
            raise BagError(f"topic {topic!r} already has type {conn.msgtype}, got {msg.__msgtype__}")
        self._writer.write(conn, int(log_time_ns), ts.serialize_cdr(msg, msg.__msgtype__))

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is None:
            try:
                self._writer.close()
            except Exception as err:
                shutil.rmtree(self.path, ignore_errors=True)
                raise BagError(f"cannot finish bag {self.path}: {_describe(err)}") from err
        else:
            try:
                self._writer.abort()
            finally:
                shutil.rmtree(self.path, ignore_errors=True)


@dataclass(frozen=True, eq=False)
class DepthSample:
    """One frame to write with :func:`write_depth_bag`.

    Attributes
    ----------
    stamp_ns : int
        Header stamp (and record time) of the image, CameraInfo and ground truth.
    depth_mm : array, shape (H, W)
        Depth, millimetres, 0/NaN invalid.
    intrinsics : Intrinsics or None
        Written as CameraInfo when not None.
    truth_mm : array, shape (5, 3) or None
        Ground-truth fingertips (mm), written when not None.
    """

    stamp_ns: int
    depth_mm: NDArray
    intrinsics: Intrinsics | None
    truth_mm: NDArray[np.float64] | None = None


def write_depth_bag(
    path: str | Path,
    samples: Iterable[DepthSample],
    topics: BagTopics = BagTopics(),
    encoding: Literal["16UC1", "32FC1"] = "16UC1",
    storage: StorageName = "mcap",
    compress: bool = True,
    frame_id: str = OPTICAL_FRAME,
    depth_codec: Literal["png", "rvl"] | None = None,
) -> int:
    """Write frames as a contract-5 bag: CameraInfo, then depth, then ground truth per frame.

    With ``depth_codec`` the depth images are written as compressedDepth
    ``CompressedImage`` on ``topics.depth + "/compressedDepth"`` instead of raw images.

    Returns
    -------
    int
        Number of depth images written.
    """
    n = 0
    with BagWriter(path, storage=storage, compress=compress) as w:
        for s in samples:
            if s.intrinsics is not None:
                w.write(topics.info, camera_info_msg(s.intrinsics, s.stamp_ns, frame_id), s.stamp_ns)
            if depth_codec is None:
                w.write(topics.depth, depth_image_msg(s.depth_mm, s.stamp_ns, frame_id, encoding), s.stamp_ns)
            else:
                msg = compressed_depth_msg(s.depth_mm, s.stamp_ns, frame_id, encoding, depth_codec)
                w.write(topics.depth + COMPRESSED_SUFFIX, msg, s.stamp_ns)
            if s.truth_mm is not None:
                w.write(topics.truth, fingertips_msg(s.truth_mm, s.stamp_ns, frame_id), s.stamp_ns)
            n += 1
    return n
