"""Writing depth bags (rosbag2, mcap or sqlite3) with ``rosbags``: :class:`BagWriter`, :func:`write_depth_bag`.

Re-exported by :mod:`hand_sog_tracker.tools.bagio`; the messages come from
:mod:`hand_sog_tracker.tools.bagmsgs`.  No ROS installation needed.
"""

from __future__ import annotations

import shutil
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, Iterable, Iterator, Literal

import numpy as np
from numpy.typing import NDArray
from rosbags.interfaces import Connection
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

from hand_sog_tracker.core.types import Intrinsics
from hand_sog_tracker.errors import BagError
from hand_sog_tracker.interface import COMPRESSED_SUFFIX
from hand_sog_tracker.tools.bagmsgs import (
    OPTICAL_FRAME,
    BagTopics,
    camera_info_msg,
    compressed_depth_msg,
    depth_image_msg,
    describe_error,
    fingertips_msg,
    typestore,
)

__all__ = ["StorageName", "BagWriter", "DepthSample", "bag_in_place", "check_bag_target", "write_depth_bag"]

StorageName = Literal["mcap", "sqlite3"]


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
            raise BagError(f"cannot create bag {self.path}: {describe_error(err)}") from err
        self._conns: dict[str, Connection] = {}

    def __enter__(self) -> "BagWriter":
        try:
            self._writer.open()
        except Exception as err:
            raise BagError(f"cannot create bag {self.path}: {describe_error(err)}") from err
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
                raise BagError(f"cannot finish bag {self.path}: {describe_error(err)}") from err
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



def check_bag_target(out: Path, force: bool) -> None:
    """Refuse to write a bag at ``out`` when something is there, unless ``force`` and it is a
    rosbag2 directory (a bag written before, safe to replace).

    Raises
    ------
    BagError
        ``out`` exists (without ``force``, or is not a bag).
    """
    if out.exists():
        if not force:
            raise BagError(f"{out} exists already (use --force to replace it)")
        if not (out.is_dir() and (out / "metadata.yaml").is_file()):
            raise BagError(f"{out} exists and is not a rosbag2 directory; not replacing it")


@contextmanager
def bag_in_place(out: Path, force: bool) -> Iterator[Path]:
    """Write a bag at ``out`` through a scratch directory: yields the path to write the bag
    (and its sidecar) to, under the final name (rosbags names the storage file after the bag
    directory); on success it replaces ``out``, and the scratch directory always goes.

    Raises
    ------
    BagError
        As :func:`check_bag_target`.
    """
    check_bag_target(out, force)
    scratch = out.parent / f".{out.name}.partial"
    if scratch.exists():
        shutil.rmtree(scratch)
    scratch.mkdir(parents=True)
    tmp = scratch / out.name
    try:
        yield tmp
        if out.exists():
            shutil.rmtree(out)
        tmp.rename(out)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)

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
