"""``make_sample_bags``: write the deterministic synthetic sample bags of ``bags/``.

One job: the ``make_sample_bags`` command; kept together because the bag specifications, the
writer and the digest define one reproducible data set (its hashes are tested).

Usage::

    make_sample_bags [--out bags] [--frames N] [--motions M [M ...]]
                     [--storage mcap|sqlite3] [--no-hires] [--no-force] [--background-mm MM]
                     [--renderer capsule|mesh] [--sensor tof|structured|clean]
    make_sample_bags --set mesh_dev|mesh_test [--out bags/<set>]
    make_sample_bags --set twohands_dev|twohands_test [--frames N] [--out bags/<set>]

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
and would make the bags 7x larger; the tracker cuts off what lies well behind the hand
anyway.

An existing bag directory of the same name is replaced unless ``--no-force`` (only if it holds a
``metadata.yaml``; anything else is an error).

``--renderer mesh`` renders the skinned WebXR mesh hand of
:mod:`hand_sog_tracker.synth.mesh` instead of the capsule hand (default, whose
output is unchanged).  Every bag directory also gets a sidecar
``hand_sog_sample.json`` (renderer, split, motion, seed, handedness, shape
factors, sensor model, width, height, encoding, frames); it is a separate file,
so the messages (and :func:`bag_digest`) do not change.

``--set mesh_dev`` / ``--set mesh_test`` write the protocol sets of
:func:`protocol_set` (9 motions each, mesh renderer, fixed seeds, shapes and
sensors that differ between the sets) into ``bags/mesh_dev`` / ``bags/mesh_test``:
tune and look at ``mesh_dev``; only score ``mesh_test``.

``--set twohands_dev`` / ``--set twohands_test`` write the two-hand sets of
:mod:`hand_sog_tracker.tools.twohand_bags` (one bag per scene of
:mod:`hand_sog_tracker.synth.twohands`, per-hand ground-truth topics); ``--frames`` makes bigger sets.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Literal, Sequence

from hand_sog_tracker.core.types import Intrinsics
from hand_sog_tracker.errors import HandSogError, InputError
from hand_sog_tracker.synth.mesh import SENSORS, MeshRenderOptions, MeshShape, mesh_sequence
from hand_sog_tracker.synth.motions import ALL_MOTIONS, MOTIONS
from hand_sog_tracker.synth.render import RenderOptions
from hand_sog_tracker.synth.sequence import SyntheticFrame, default_intrinsics, synthetic_sequence
from hand_sog_tracker.tools.bagio import (
    DepthSample,
    StorageName,
    iter_messages,
    open_bag,
    write_depth_bag,
)
from hand_sog_tracker.tools.bagwrite import bag_in_place
from hand_sog_tracker.tools.twohand_bags import TWOHAND_SETS, write_twohand_set

__all__ = [
    "BASE_STAMP_NS",
    "SIDECAR",
    "PROTOCOL_SETS",
    "PROTOCOL_MOTIONS",
    "SampleBag",
    "BagSpec",
    "motion_seed",
    "protocol_set",
    "write_sample_bag",
    "write_protocol_set",
    "make_sample_bags",
    "bag_digest",
    "main",
]

#: Stamp of the first frame of every sample bag (2024-01-01T00:00:00Z), ns.
BASE_STAMP_NS = 1_704_067_200 * 1_000_000_000
FPS = 30.0
#: Sidecar file written into every bag directory.
SIDECAR = "hand_sog_sample.json"
#: Sensor label of the capsule renderer's artefacts in the sidecar.
CAPSULE_SENSOR = "capsule_tof"
Renderer = Literal["capsule", "mesh"]


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
    renderer: Renderer = "capsule",
    sensor: str | None = None,
    shape: MeshShape | None = None,
    right: bool = True,
    split: str | None = None,
    fps: float = FPS,
) -> SampleBag:
    """Render one synthetic sequence and write it as a rosbag2 (plus its sidecar).

    Parameters
    ----------
    path : str or Path
        Bag directory to create.
    motion : str
        One of :data:`hand_sog_tracker.synth.motions.ALL_MOTIONS`.
    frames : int
        Number of frames (at ``fps``).
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
    renderer : {"capsule", "mesh"}
        Capsule hand (:mod:`synth.render`) or skinned mesh hand (:mod:`synth.mesh`).
    sensor : str, optional
        Mesh renderer only: one of :data:`synth.mesh.SENSORS` (default ``tof``).
    shape : MeshShape, optional
        Mesh renderer only: hand shape factors (default all 1).
    right : bool
        Right or left hand.
    split : str, optional
        Sidecar ``split``; default ``capsule`` for the capsule renderer, ``dev`` for the mesh.
    fps : float
        Frame rate (Hz): the motion is sampled and the images stamped at this rate (default 30).

    Raises
    ------
    BagError
        ``path`` exists (without ``force``, or is not a bag), or writing fails.
    InputError
        Unknown motion or ``frames < 1``.
    """
    known = ALL_MOTIONS
    if renderer not in ("capsule", "mesh"):
        raise InputError(f"unknown renderer {renderer!r}; choose capsule or mesh")
    if motion not in known:
        raise InputError(f"unknown motion {motion!r}; choose from {', '.join(known)}")
    if frames < 1:
        raise InputError(f"frames must be >= 1, got {frames}")
    if not (1.0 <= fps <= 1000.0):
        raise InputError(f"fps must be in [1, 1000], got {fps}")
    if renderer == "capsule" and (sensor is not None or shape is not None):
        raise InputError("sensor and shape are options of the mesh renderer")
    if renderer == "mesh":
        sensor = "tof" if sensor is None else sensor
        if sensor not in SENSORS:
            raise InputError(f"unknown sensor {sensor!r}; choose from {', '.join(SENSORS)}")
        shape = MeshShape() if shape is None else shape
    seed_used = motion_seed(motion) if seed is None else int(seed)
    out = Path(path)
    t0 = time.perf_counter()
    intr = default_intrinsics(width, height)
    with bag_in_place(out, force) as tmp:
        if renderer == "capsule":
            seq = synthetic_sequence(
                motion, frames, intrinsics=intr, right=right, seed=seed_used,
                options=RenderOptions(background_mm=background_mm), fps=fps,
            )
            sample = {
                "renderer": "capsule",
                "split": split or "capsule",
                "sensor": CAPSULE_SENSOR,
                "shape": {"length": 1.0, "width": 1.0, "depth": 1.0, "sigma": 1.0},
            }
        else:
            assert shape is not None and sensor is not None
            seq = mesh_sequence(
                motion, frames, intrinsics=intr, shape=shape, right=right, seed=seed_used,
                options=MeshRenderOptions(sensor=sensor, background_mm=background_mm), fps=fps,
            )
            sample = {
                "renderer": "mesh",
                "split": split or "dev",
                "sensor": sensor,
                "shape": {"length": shape.length, "palm_width": shape.palm_width, "thickness": shape.thickness},
            }
        _write_frames(tmp, seq, intr, encoding, storage, fps)
        sample.update(
            motion=motion,
            seed=seed_used,
            handedness="right" if right else "left",
            width=int(width),
            height=int(height),
            encoding=encoding,
            frames=int(frames),
            background_mm=background_mm,
        )
        if fps != FPS:  # (the 30 fps bags' sidecars stay as they were)
            sample["fps"] = float(fps)
        (tmp / SIDECAR).write_text(json.dumps(sample, indent=2, sort_keys=True) + "\n", encoding="utf-8")
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
    seq: Iterable[SyntheticFrame],
    intr: Intrinsics,
    encoding: Literal["16UC1", "32FC1"],
    storage: StorageName,
    fps: float = FPS,
) -> None:
    samples = (
        DepthSample(
            stamp_ns=BASE_STAMP_NS + int(round(f.index * 1e9 / fps)),
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
    renderer: Renderer = "capsule",
    sensor: str | None = None,
    fps: float = FPS,
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
    renderer : {"capsule", "mesh"}
        See :func:`write_sample_bag`.  Both renderers know :data:`synth.motions.ALL_MOTIONS`;
        the default set stays :data:`MOTIONS` (without ``fistopen``, ``rotate``).
    sensor : str, optional
        Mesh renderer's sensor model (default ``tof``).
    fps : float
        See :func:`write_sample_bag`.

    Returns
    -------
    list of SampleBag
    """
    known = ALL_MOTIONS
    names = list(MOTIONS) if not motions else list(motions)
    unknown = [m for m in names if m not in known]
    if unknown:
        raise InputError(f"unknown motion(s) {', '.join(unknown)}; choose from {', '.join(known)}")
    root = Path(out)
    written: list[SampleBag] = []
    jobs: list[tuple[Path, str, int, int, int, Literal["16UC1", "32FC1"]]] = [
        (root / m, m, frames, 320, 240, "16UC1") for m in names
    ]
    if hires and names:
        jobs.append((root / f"{names[0]}_640x480_32fc1", names[0], max(frames // 3, 1), 640, 480, "32FC1"))
    for path, motion, n, w, h, enc in jobs:
        bag = write_sample_bag(
            path, motion, n, w, h, enc, storage=storage, force=force, background_mm=background_mm,
            renderer=renderer, sensor=sensor, fps=fps,
        )
        written.append(bag)
        if on_written is not None:
            on_written(bag)
    return written


#: Motions of the mesh protocol sets.
PROTOCOL_MOTIONS: tuple[str, ...] = (
    "abdadd", "fingercount", "fingerwave", "flexex", "pinch", "random", "tigergrasp", "fistopen", "rotate",
)
#: Names of the protocol sets.
PROTOCOL_SETS: tuple[str, ...] = ("mesh_dev", "mesh_test")

# Per set: split, hand shapes (length, palm_width, thickness) cycled over the
# motions, sensors cycled over the motions, indices of the 640x480 32FC1 bags
# and of the left-hand bag.  The sets share no shape, seed or (motion, sensor,
# shape) assignment.
_SET_DEFS = {
    "mesh_dev": dict(
        split="dev",
        shapes=((1.0, 1.0, 1.0), (0.9, 1.05, 0.95), (1.1, 0.92, 1.08)),
        sensors=("tof", "structured"),
        hires=(4, 7),  # pinch (tof), fistopen (structured)
        left=(2,),  # fingerwave (tof)
    ),
    "mesh_test": dict(
        split="test",
        shapes=((0.87, 0.9, 0.88), (1.13, 1.12, 1.1), (0.95, 1.14, 1.02)),
        sensors=("structured", "tof"),
        hires=(3, 8),  # flexex (tof), rotate (structured)
        left=(6,),  # tigergrasp (structured)
    ),
}


@dataclass(frozen=True)
class BagSpec:
    """One bag of a protocol set (see :func:`protocol_set`)."""

    name: str
    motion: str
    seed: int
    shape: MeshShape
    sensor: str
    right: bool
    width: int
    height: int
    encoding: Literal["16UC1", "32FC1"]
    frames: int
    split: str


def protocol_set(name: str, frames: int = 60, hires_frames: int = 20) -> list[BagSpec]:
    """The bags of a mesh protocol set, deterministic.

    ``mesh_dev`` (split ``dev``: look, tune) and ``mesh_test`` (split ``test``:
    score only) hold the 9 :data:`PROTOCOL_MOTIONS` each, with seeds
    ``crc32("<set>/<motion>")``, three hand shapes cycled over the motions,
    sensors ``tof`` / ``structured`` alternating, two bags at 640x480
    ``32FC1`` (``<motion>_640x480_32fc1``, ``hires_frames`` frames), one left
    hand (``<motion>_left``) and the rest 320x240 ``16UC1`` (``frames`` frames).
    Shapes, seeds and sensor assignment differ between the sets.

    Raises
    ------
    InputError
        Unknown set name or frame counts < 1.
    """
    if name not in _SET_DEFS:
        raise InputError(f"unknown protocol set {name!r}; choose from {', '.join(PROTOCOL_SETS)}")
    if frames < 1 or hires_frames < 1:
        raise InputError("frame counts must be >= 1")
    d = _SET_DEFS[name]
    out = []
    for i, motion in enumerate(PROTOCOL_MOTIONS):
        hires = i in d["hires"]
        right = i not in d["left"]
        suffix = "_640x480_32fc1" if hires else ("" if right else "_left")
        out.append(
            BagSpec(
                name=motion + suffix,
                motion=motion,
                seed=zlib.crc32(f"{name}/{motion}".encode("utf-8")) & 0x7FFFFFFF,
                shape=MeshShape(*d["shapes"][i % len(d["shapes"])]),
                sensor=d["sensors"][i % len(d["sensors"])],
                right=right,
                width=640 if hires else 320,
                height=480 if hires else 240,
                encoding="32FC1" if hires else "16UC1",
                frames=hires_frames if hires else frames,
                split=str(d["split"]),
            )
        )
    return out


def write_protocol_set(
    name: str,
    out: str | Path | None = None,
    frames: int = 60,
    hires_frames: int = 20,
    storage: StorageName = "mcap",
    force: bool = True,
    on_written: Callable[[SampleBag], None] | None = None,
    fps: float = FPS,
) -> list[SampleBag]:
    """Write every bag of :func:`protocol_set` ``name`` into ``out`` (default ``bags/<name>``,
    ``bags/<name>_<fps>hz`` at another ``fps``: the same hands, seeds and motions sampled at that
    rate, e.g. to feed the node the held-out set like a fast camera)."""
    if out is None:
        out = Path("bags") / (name if fps == FPS else f"{name}_{fps:g}hz")
    root = Path(out)
    written = []
    for spec in protocol_set(name, frames, hires_frames):
        bag = write_sample_bag(
            root / spec.name, spec.motion, spec.frames, spec.width, spec.height, spec.encoding,
            storage=storage, seed=spec.seed, force=force, renderer="mesh", sensor=spec.sensor,
            shape=spec.shape, right=spec.right, split=spec.split, fps=fps,
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


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``make_sample_bags`` (also read by the documentation)."""
    p = argparse.ArgumentParser(
        prog="make_sample_bags",
        description="Write deterministic synthetic depth bags with fingertip ground truth, one per motion.",
    )
    p.add_argument("--out", default=None, help="output directory (default bags, with --set bags/<set>)")
    p.add_argument("--frames", type=int, default=None,
                   help="frames per bag (default 90; with --set 2 s of motion per 320x240 bag, "
                   "60 frames at 30 fps, and a third of it per 640x480 bag)")
    p.add_argument("--motions", nargs="+", metavar="M",
                   help=f"motions to write (default: {' '.join(MOTIONS)}; also known: "
                   f"{' '.join(m for m in ALL_MOTIONS if m not in MOTIONS)})")
    p.add_argument("--renderer", choices=("capsule", "mesh"), default="capsule",
                   help="capsule hand (default) or the skinned WebXR mesh hand")
    p.add_argument("--sensor", choices=SENSORS, default=None, help="mesh renderer's sensor model (default tof)")
    p.add_argument("--set", choices=PROTOCOL_SETS + TWOHAND_SETS, default=None, dest="protocol_set",
                   help="write a mesh protocol set (mesh_dev: look and tune; mesh_test: score only) "
                   "or a two-hand set (twohands_dev, twohands_test: 45 frames per scene unless --frames) "
                   "instead of one bag per motion")
    p.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap", help="rosbag2 storage (default mcap)")
    p.add_argument("--no-hires", action="store_true", help="skip the 640x480 32FC1 bag")
    p.add_argument("--no-force", action="store_true", help="fail instead of replacing existing bags")
    p.add_argument("--fps", type=float, default=FPS,
                   help="frame rate of the motion and the image stamps (default 30; e.g. 100 to "
                   "feed the node like a fast camera; with --set the bags go to bags/<set>_<fps>hz "
                   "unless --out is given)")
    p.add_argument("--background-mm", type=float, default=None, metavar="MM",
                   help="render a noisy wall at this depth behind the hand (default: none, i.e. no return; "
                   "a wall makes each 90-frame bag ~5 MB instead of ~0.7 MB)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point; returns the exit status (0 ok, 2 error)."""
    p = build_parser()
    args = p.parse_args(argv)
    if args.frames is not None and args.frames < 1:
        p.error("--frames must be >= 1")
    if args.sensor is not None and args.renderer != "mesh":
        p.error("--sensor needs --renderer mesh")
    if args.protocol_set is not None and (args.motions or args.sensor or args.background_mm is not None):
        p.error("--set fixes motions, sensors and background; drop --motions/--sensor/--background-mm")
    if not (1.0 <= args.fps <= 1000.0):
        p.error("--fps must be in [1, 1000]")
    if args.background_mm is not None and not args.background_mm > 0:
        p.error("--background-mm must be > 0")
    try:
        if args.protocol_set in TWOHAND_SETS:
            n = max(int(round(45 * args.fps / FPS)), 1) if args.frames is None else args.frames
            paths = write_twohand_set(
                args.protocol_set, args.out, frames=n, force=not args.no_force, fps=args.fps,
                on_written=lambda path, spec, size, secs: print(
                    f"{path}: {spec.frames} frames {spec.width}x{spec.height} 16UC1, two hands, "
                    f"{size / 1e6:.2f} MB, {secs:.1f} s"
                ),
            )
            total = sum(f.stat().st_size for p in paths for f in p.rglob("*") if f.is_file())
            print(f"wrote {len(paths)} bags, {total / 1e6:.2f} MB in total")
            return 0
        if args.protocol_set is not None:
            n = max(int(round(60 * args.fps / FPS)), 1) if args.frames is None else args.frames
            bags = write_protocol_set(
                args.protocol_set,
                args.out,
                frames=n,
                hires_frames=max(n // 3, 1),
                storage=args.storage,
                force=not args.no_force,
                on_written=_report,
                fps=args.fps,
            )
        else:
            bags = make_sample_bags(
                "bags" if args.out is None else args.out,
                frames=90 if args.frames is None else args.frames,
                motions=args.motions,
                storage=args.storage,
                hires=not args.no_hires,
                force=not args.no_force,
                background_mm=args.background_mm,
                on_written=_report,
                renderer=args.renderer,
                sensor=args.sensor,
                fps=args.fps,
            )
    except HandSogError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    total = sum(b.size_bytes for b in bags)
    print(f"wrote {len(bags)} bags, {total / 1e6:.2f} MB in total")
    return 0


if __name__ == "__main__":
    sys.exit(main())
