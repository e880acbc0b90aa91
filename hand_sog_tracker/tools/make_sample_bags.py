"""``make_sample_bags``: write the deterministic synthetic sample bags of ``bags/``.

Usage::

    make_sample_bags [--out bags] [--frames N] [--motions M [M ...]]
                     [--storage mcap|sqlite3] [--no-hires] [--no-force] [--background-mm MM]

One rosbag2 per motion family of :mod:`hand_sog_tracker.synth.motions`,
rendered by :func:`hand_sog_tracker.synth.sequence.synthetic_sequence` with
a fixed seed per motion, following the bag convention of
:mod:`hand_sog_tracker.tools.bagio` (contract 5):

* ``/camera/depth/image_rect_raw``: 320x240 ``16UC1`` depth (mm), 30 fps;
* ``/camera/depth/camera_info``: one per image, same stamp;
* ``/hand/ground_truth/fingertips``: PoseArray of the 5 fingertips (m).

Frame id ``camera_depth_optical_frame``; stamps start at a fixed epoch so the
message data is identical on every run (the tests check it by hashing).
Storage: mcap with zstd chunk compression (default) or sqlite3 with zstd
per-message compression.  Unless ``--no-hires``, one more bag,
``<motion>_640x480_32fc1``, holds the first motion at 640x480 ``32FC1``
(metres; invalid = NaN) and a third of the frames.

By default nothing is rendered behind the hand and forearm (no return, 0):
a noisy wall (``--background-mm 900``) is ~60 KB per compressed 320x240 frame
and would make the bags 7x larger; the tracker ignores depth beyond
``far_mm`` (600 mm) anyway.

An existing bag directory of the same name is replaced unless ``--no-force`` (only if it holds a
``metadata.yaml``; anything else is an error).
"""

from __future__ import annotations

import argparse
import hashlib
import shutil
import sys
import time
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Literal, Sequence

from hand_sog_tracker.core.types import Intrinsics
from hand_sog_tracker.errors import BagError, HandSogError, InputError
from hand_sog_tracker.synth.motions import MOTIONS
from hand_sog_tracker.synth.render import RenderOptions
from hand_sog_tracker.synth.sequence import default_intrinsics, synthetic_sequence
from hand_sog_tracker.tools.bagio import (
    DepthSample,
    StorageName,
    iter_messages,
    open_bag,
    write_depth_bag,
)

__all__ = ["BASE_STAMP_NS", "SampleBag", "motion_seed", "write_sample_bag", "make_sample_bags", "bag_digest", "main"]

#: Stamp of the first frame of every sample bag (2024-01-01T00:00:00Z), ns.
BASE_STAMP_NS = 1_704_067_200 * 1_000_000_000
FPS = 30.0


@dataclass(frozen=True)
class SampleBag:
    """One written bag: where, what, and how big."""

    path: Path
    motion: str
    frames: int
    width: int
    height: int
    encoding: str
    size_bytes: int
    seconds: float


def motion_seed(motion: str) -> int:
    """Fixed per-motion seed (CRC32 of the name: stable across runs and Pythons)."""
    return zlib.crc32(motion.encode("utf-8")) & 0x7FFFFFFF


def _bag_size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def write_sample_bag(
    path: str | Path,
    motion: str,
    frames: int,
    width: int = 320,
    height: int = 240,
    encoding: Literal["16UC1", "32FC1"] = "16UC1",
    storage: StorageName = "mcap",
    seed: int | None = None,
    force: bool = False,
    background_mm: float | None = None,
) -> SampleBag:
    """Render one synthetic sequence and write it as a rosbag2.

    Parameters
    ----------
    path : str or Path
        Bag directory to create.
    motion : str
        One of :data:`hand_sog_tracker.synth.motions.MOTIONS`.
    frames : int
        Number of frames (30 fps).
    width, height : int
        Image size (intrinsics: :func:`synth.sequence.default_intrinsics`).
    encoding : {"16UC1", "32FC1"}
        Depth encoding (mm as uint16, or metres as float32).
    storage : {"mcap", "sqlite3"}
    seed : int, optional
        Rendering seed (default :func:`motion_seed`).
    force : bool
        Replace an existing bag at ``path``.
    background_mm : float or None
        Depth of a wall behind the hand (mm); None = no return (0) there.
        A noisy wall costs ~60 KB per 320x240 frame even compressed.

    Raises
    ------
    BagError
        ``path`` exists (without ``force``, or is not a bag), or writing fails.
    InputError
        Unknown motion or ``frames < 1``.
    """
    if motion not in MOTIONS:
        raise InputError(f"unknown motion {motion!r}; choose from {', '.join(MOTIONS)}")
    if frames < 1:
        raise InputError(f"frames must be >= 1, got {frames}")
    out = Path(path)
    if out.exists():
        if not force:
            raise BagError(f"{out} exists already (use --force to replace it)")
        if not (out.is_dir() and (out / "metadata.yaml").is_file()):
            raise BagError(f"{out} exists and is not a rosbag2 directory; not replacing it")
    t0 = time.perf_counter()
    intr = default_intrinsics(width, height)
    # Write into a scratch directory next to the target, under the final name
    # (rosbags names the storage file after the bag directory), then move it.
    scratch = out.parent / f".{out.name}.partial"
    if scratch.exists():
        shutil.rmtree(scratch)
    scratch.mkdir(parents=True)
    tmp = scratch / out.name
    try:
        _write_frames(
            tmp,
            motion,
            frames,
            intr,
            encoding,
            storage,
            motion_seed(motion) if seed is None else seed,
            RenderOptions(background_mm=background_mm),
        )
        if out.exists():
            shutil.rmtree(out)
        tmp.rename(out)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return SampleBag(
        path=out,
        motion=motion,
        frames=frames,
        width=width,
        height=height,
        encoding=encoding,
        size_bytes=_bag_size(out),
        seconds=time.perf_counter() - t0,
    )


def _write_frames(
    path: Path,
    motion: str,
    frames: int,
    intr: Intrinsics,
    encoding: Literal["16UC1", "32FC1"],
    storage: StorageName,
    seed: int,
    options: RenderOptions,
) -> None:
    seq = synthetic_sequence(motion, frames, intrinsics=intr, seed=seed, options=options, fps=FPS)
    samples = (
        DepthSample(
            stamp_ns=BASE_STAMP_NS + int(round(f.index * 1e9 / FPS)),
            depth_mm=f.depth_mm,
            intrinsics=intr,
            truth_mm=f.fingertips_mm,
        )
        for f in seq
    )
    write_depth_bag(path, samples, encoding=encoding, storage=storage, compress=True)


def bag_digest(path: str | Path) -> str:
    """SHA-256 over every message (topic, type, log time, serialized data) of a bag.

    Independent of the container (storage, compression, file metadata), so
    two bags with the same digest hold the same messages.
    """
    h = hashlib.sha256()
    opener = open_bag(path)
    with opener as reader:
        for conn, log_ns, raw in iter_messages(reader, opener.path, list(reader.connections)):
            h.update(conn.topic.encode())
            h.update(conn.msgtype.encode())
            h.update(int(log_ns).to_bytes(8, "little"))
            h.update(bytes(raw))
    return h.hexdigest()


def make_sample_bags(
    out: str | Path = "bags",
    frames: int = 90,
    motions: Sequence[str] | None = None,
    storage: StorageName = "mcap",
    hires: bool = True,
    force: bool = True,
    background_mm: float | None = None,
    on_written: Callable[[SampleBag], None] | None = None,
) -> list[SampleBag]:
    """Write one bag per motion (plus the optional 640x480 32FC1 one) into ``out``.

    Parameters
    ----------
    out : str or Path
        Directory of the bags (created if needed).
    frames : int
        Frames per 320x240 bag; the 640x480 bag gets a third of them.
    motions : sequence of str, optional
        Motions (default: all of :data:`MOTIONS`).
    storage : {"mcap", "sqlite3"}
    hires : bool
        Also write ``<first motion>_640x480_32fc1``.
    force : bool
        Replace existing bags.
    background_mm : float or None
        See :func:`write_sample_bag`.
    on_written : callable, optional
        Called with each :class:`SampleBag` once written.

    Returns
    -------
    list of SampleBag
    """
    names = list(MOTIONS) if not motions else list(motions)
    unknown = [m for m in names if m not in MOTIONS]
    if unknown:
        raise InputError(f"unknown motion(s) {', '.join(unknown)}; choose from {', '.join(MOTIONS)}")
    root = Path(out)
    written: list[SampleBag] = []
    jobs: list[tuple[Path, str, int, int, int, Literal["16UC1", "32FC1"]]] = [
        (root / m, m, frames, 320, 240, "16UC1") for m in names
    ]
    if hires and names:
        jobs.append((root / f"{names[0]}_640x480_32fc1", names[0], max(frames // 3, 1), 640, 480, "32FC1"))
    for path, motion, n, w, h, enc in jobs:
        bag = write_sample_bag(
            path, motion, n, w, h, enc, storage=storage, force=force, background_mm=background_mm
        )
        written.append(bag)
        if on_written is not None:
            on_written(bag)
    return written


def _report(bag: SampleBag) -> None:
    print(
        f"{bag.path}: {bag.frames} frames {bag.width}x{bag.height} {bag.encoding}, "
        f"{bag.size_bytes / 1e6:.2f} MB, {bag.seconds:.1f} s"
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point; returns the exit status (0 ok, 2 error)."""
    p = argparse.ArgumentParser(
        prog="make_sample_bags",
        description="Write deterministic synthetic depth bags with fingertip ground truth, one per motion.",
    )
    p.add_argument("--out", default="bags", help="output directory (default %(default)s)")
    p.add_argument("--frames", type=int, default=90, help="frames per bag at 30 fps (default %(default)s)")
    p.add_argument("--motions", nargs="+", metavar="M", help="motions to write (default all)")
    p.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap", help="rosbag2 storage (default mcap)")
    p.add_argument("--no-hires", action="store_true", help="skip the 640x480 32FC1 bag")
    p.add_argument("--no-force", action="store_true", help="fail instead of replacing existing bags")
    p.add_argument("--background-mm", type=float, default=None, metavar="MM",
                   help="render a noisy wall at this depth behind the hand (default: none, i.e. no return; "
                   "a wall makes each 90-frame bag ~5 MB instead of ~0.7 MB)")
    args = p.parse_args(argv)
    if args.frames < 1:
        p.error("--frames must be >= 1")
    if args.background_mm is not None and not args.background_mm > 0:
        p.error("--background-mm must be > 0")
    try:
        bags = make_sample_bags(
            args.out,
            frames=args.frames,
            motions=args.motions,
            storage=args.storage,
            hires=not args.no_hires,
            force=not args.no_force,
            background_mm=args.background_mm,
            on_written=_report,
        )
    except HandSogError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    total = sum(b.size_bytes for b in bags)
    print(f"wrote {len(bags)} bags, {total / 1e6:.2f} MB in total")
    return 0


if __name__ == "__main__":
    sys.exit(main())
