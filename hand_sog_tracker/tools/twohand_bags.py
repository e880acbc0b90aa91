"""Two-hand bags: the sets ``twohands_dev`` / ``twohands_test``, their per-hand ground-truth topics.

One job: writing and reading the per-hand ground truth of the two-hand scenes of
:mod:`hand_sog_tracker.synth.twohands`; kept together because the topic names, the set
definitions and the reader are one convention.

A two-hand bag has the depth image and CameraInfo of the bag convention (``bags/README.md``) and,
per hand ``<side>`` = ``left`` / ``right``, with the image's stamp and frame id:

* ``/hand/ground_truth/<side>/fingertips``: ``geometry_msgs/PoseArray``, 5 poses (thumb .. little),
  metres, the same meaning as the one-hand ``/hand/ground_truth/fingertips``;
* ``/hand/ground_truth/<side>/keypoints``: ``geometry_msgs/PoseArray``, 21 poses (wrist, then per
  finger its three joints and its fingertip), metres;
* ``/hand/ground_truth/<side>/visibility``: ``sensor_msgs/JointState`` used as named values:
  ``visible_fraction`` (share of the hand's pixels not hidden by the other hand or the object) and
  ``<finger>_tip_visible`` (1 or 0) for thumb .. little.

The one-hand topic ``/hand/ground_truth/fingertips`` is *not* written: it means "the hand" and a
two-hand bag has two; one-hand tools refuse such a bag (no ground-truth topic) instead of scoring
the wrong hand.  The sidecar has ``hands: 2``.
"""

from __future__ import annotations

import json
import time
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Final, Literal

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.hand_model import FINGERS
from hand_sog_tracker.errors import BagError, InputError
from hand_sog_tracker.interface import stamp_to_ns
from hand_sog_tracker.synth.mesh import MeshShape
from hand_sog_tracker.synth.sequence import default_intrinsics
from hand_sog_tracker.synth.twohands import HANDS, SCENES, TwoHandScene, two_hand_sequence
from hand_sog_tracker.tools.bagio import (
    GT_TYPE,
    OPTICAL_FRAME,
    BagTopics,
    BagWriter,
    camera_info_msg,
    depth_image_msg,
    deserialize,
    fingertips_msg,
    iter_messages,
    open_bag,
)
from hand_sog_tracker.tools.bagmsgs import ns_to_stamp, points_from_msg, points_msg, typestore
from hand_sog_tracker.tools.bagwrite import bag_in_place

__all__ = [
    "TWOHAND_SETS",
    "VISIBILITY_TYPE",
    "hand_topic",
    "TwoHandBagSpec",
    "HandTruthRecord",
    "twohand_set",
    "write_twohand_bag",
    "write_twohand_set",
    "read_hand_truth",
    "is_two_hand_bag",
]

#: Names of the two-hand sets (``bags/<name>``).
TWOHAND_SETS: Final[tuple[str, ...]] = ("twohands_dev", "twohands_test")
#: Message type of the per-hand visibility topic.
VISIBILITY_TYPE: Final[str] = "sensor_msgs/msg/JointState"
_KINDS: Final = ("fingertips", "keypoints", "visibility")
_FPS: Final = 30.0
_BASE_STAMP_NS: Final = 1_704_067_200 * 1_000_000_000  # (= make_sample_bags.BASE_STAMP_NS)
_SIDECAR: Final = "hand_sog_sample.json"


def hand_topic(side: str, kind: Literal["fingertips", "keypoints", "visibility"] = "fingertips") -> str:
    """Absolute topic of one hand's ground truth, e.g. ``/hand/ground_truth/left/fingertips``."""
    if side not in HANDS or kind not in _KINDS:
        raise InputError(f"no ground-truth topic for hand {side!r} / {kind!r}")
    return f"/hand/ground_truth/{side}/{kind}"


@dataclass(frozen=True)
class TwoHandBagSpec:
    """One bag of a two-hand set (see :func:`twohand_set`)."""

    name: str
    scene: TwoHandScene
    seed: int
    sensor: str
    frames: int
    split: str
    width: int = 320
    height: int = 240


# Per set: split, (left, right) shape pairs cycled over the scenes, sensors cycled, the front hand,
# the scene depth.  The sets share no shape, seed or (scene, sensor) assignment.
_SET_DEFS: Final[dict[str, dict[str, Any]]] = {
    "twohands_dev": dict(
        split="dev",
        shapes=(((0.9, 1.05, 0.95), (1.0, 1.0, 1.0)), ((1.0, 1.0, 1.0), (1.1, 0.92, 1.08)),
                ((1.1, 0.92, 1.08), (0.9, 1.05, 0.95))),
        sensors=("tof", "structured"),
        front="right",
        depth_mm=460.0,
    ),
    "twohands_test": dict(
        split="test",
        shapes=(((0.95, 1.14, 1.02), (0.87, 0.9, 0.88)), ((1.13, 1.12, 1.1), (0.95, 1.14, 1.02)),
                ((0.87, 0.9, 0.88), (1.13, 1.12, 1.1))),
        sensors=("structured", "tof"),
        front="left",
        depth_mm=490.0,
    ),
}


def twohand_set(name: str, frames: int = 45) -> list[TwoHandBagSpec]:
    """The bags of a two-hand set, deterministic: one per scene of :data:`SCENES`.

    Seeds ``crc32("<set>/<scene>")``; three (left, right) shape pairs and two sensors cycled over
    the scenes; ``twohands_dev`` has the right hand in front (``occlude``, ``cross``) and holding the
    ball first (``pass``), ``twohands_test`` the left, farther from the camera.

    Raises
    ------
    InputError
        Unknown set or ``frames < 1``.
    """
    if name not in _SET_DEFS:
        raise InputError(f"unknown two-hand set {name!r}; choose from {', '.join(TWOHAND_SETS)}")
    if frames < 1:
        raise InputError("frames must be >= 1")
    d = _SET_DEFS[name]
    out = []
    for i, scene in enumerate(SCENES):
        pair = d["shapes"][i % len(d["shapes"])]
        out.append(
            TwoHandBagSpec(
                name=scene,
                scene=TwoHandScene(scene, (MeshShape(*pair[0]), MeshShape(*pair[1])), d["front"], d["depth_mm"]),
                seed=zlib.crc32(f"{name}/{scene}".encode("utf-8")) & 0x7FFFFFFF,
                sensor=d["sensors"][i % len(d["sensors"])],
                frames=int(frames),
                split=str(d["split"]),
            )
        )
    return out


def _visibility_msg(fraction: float, tips_visible: NDArray[np.bool_], stamp_ns: int, frame_id: str) -> Any:
    t = typestore().types
    Header = t["std_msgs/msg/Header"]
    names = ["visible_fraction"] + [f"{f}_tip_visible" for f in FINGERS]
    values = np.concatenate([[fraction], np.asarray(tips_visible, dtype=np.float64)])
    return t[VISIBILITY_TYPE](
        header=Header(stamp=ns_to_stamp(stamp_ns), frame_id=frame_id),
        name=names,
        position=values.astype(np.float64),
        velocity=np.zeros(0, dtype=np.float64),
        effort=np.zeros(0, dtype=np.float64),
    )


def write_twohand_bag(
    path: str | Path, spec: TwoHandBagSpec, force: bool = True, fps: float = _FPS
) -> tuple[Path, int, float]:
    """Render one two-hand bag (mcap, zstd chunks) and its sidecar.

    Returns
    -------
    (path, size in bytes, seconds)

    Raises
    ------
    BagError
        ``path`` exists (without ``force``, or is not a bag), or writing fails.
    """
    out = Path(path)
    t0 = time.perf_counter()
    intr = default_intrinsics(spec.width, spec.height)
    topics = BagTopics()
    with bag_in_place(out, force) as tmp:
        with BagWriter(tmp, storage="mcap", compress=True) as w:
            for f in two_hand_sequence(spec.scene, spec.frames, intr, seed=spec.seed, sensor=spec.sensor, fps=fps):
                ns = _BASE_STAMP_NS + int(round(f.index * 1e9 / fps))
                w.write(topics.info, camera_info_msg(intr, ns, OPTICAL_FRAME), ns)
                w.write(topics.depth, depth_image_msg(f.depth_mm, ns, OPTICAL_FRAME, "16UC1"), ns)
                for h in f.hands:
                    w.write(hand_topic(h.handedness), fingertips_msg(h.fingertips_mm, ns, OPTICAL_FRAME), ns)
                    w.write(hand_topic(h.handedness, "keypoints"), points_msg(h.keypoints_mm, ns, OPTICAL_FRAME), ns)
                    w.write(hand_topic(h.handedness, "visibility"),
                            _visibility_msg(h.visible_fraction, h.tips_visible, ns, OPTICAL_FRAME), ns)
        sc = spec.scene
        sample: dict[str, Any] = {
            "renderer": "mesh_two_hands",
            "split": spec.split,
            "scene": sc.scene,
            "motion": sc.scene,
            "hands": 2,
            "handedness": "both",
            "front": sc.front,
            "depth_mm": sc.depth_mm,
            "shapes": {
                side: {"length": s.length, "palm_width": s.palm_width, "thickness": s.thickness}
                for side, s in zip(HANDS, sc.shapes)
            },
            "sensor": spec.sensor,
            "seed": spec.seed,
            "width": spec.width,
            "height": spec.height,
            "encoding": "16UC1",
            "frames": spec.frames,
            "background_mm": None,
        }
        if fps != _FPS:
            sample["fps"] = float(fps)
        (tmp / _SIDECAR).write_text(json.dumps(sample, indent=2, sort_keys=True) + "\n", encoding="utf-8")
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    return out, size, time.perf_counter() - t0


def write_twohand_set(
    name: str,
    out: str | Path | None = None,
    frames: int = 45,
    force: bool = True,
    fps: float = _FPS,
    on_written: Callable[[Path, TwoHandBagSpec, int, float], None] | None = None,
) -> list[Path]:
    """Write every bag of :func:`twohand_set` ``name`` into ``out`` (default ``bags/<name>``)."""
    root = Path("bags") / name if out is None else Path(out)
    written = []
    for spec in twohand_set(name, frames):
        path, size, secs = write_twohand_bag(root / spec.name, spec, force=force, fps=fps)
        written.append(path)
        if on_written is not None:
            on_written(path, spec, size, secs)
    return written


@dataclass(frozen=True, eq=False)
class HandTruthRecord:
    """One hand's ground truth at one stamp, as read from a bag.

    Attributes
    ----------
    fingertips_mm : array, shape (5, 3)
    keypoints_mm : array, shape (21, 3) or None
    visible_fraction : float
        NaN when the bag has no visibility topic.
    tips_visible : bool array, shape (5,) or None
    """

    fingertips_mm: NDArray[np.float64]
    keypoints_mm: NDArray[np.float64] | None = None
    visible_fraction: float = float("nan")
    tips_visible: NDArray[np.bool_] | None = None


def is_two_hand_bag(topic_names: set[str] | list[str]) -> bool:
    """Whether a bag's topics hold per-hand ground truth (either hand's fingertips)."""
    return any(hand_topic(s) in topic_names for s in HANDS)


def read_hand_truth(path: str | Path) -> dict[str, dict[int, HandTruthRecord]]:
    """Per-hand ground truth of a bag: ``{"left": {stamp_ns: record}, "right": {...}}``.

    A hand without topics maps to ``{}``.

    Raises
    ------
    BagError
        Unreadable bag, wrong message types, a PoseArray of the wrong size.
    """
    parts: dict[str, dict[str, dict[int, Any]]] = {s: {k: {} for k in _KINDS} for s in HANDS}
    wanted = {hand_topic(s, k): (s, k) for s in HANDS for k in _KINDS}
    opener = open_bag(path)
    with opener as reader:
        conns = [c for c in reader.connections if c.topic in wanted]
        for c in conns:
            kind = wanted[c.topic][1]
            expect = VISIBILITY_TYPE if kind == "visibility" else GT_TYPE
            if c.msgtype != expect:
                raise BagError(f"bag {opener.path}: {c.topic} has type {c.msgtype}, expected {expect}")
        for conn, _, raw in iter_messages(reader, opener.path, conns):
            side, kind = wanted[conn.topic]
            msg = deserialize(reader, opener.path, raw, conn)
            stamp = stamp_to_ns(msg.header.stamp)
            if kind == "visibility":
                values = dict(zip(list(msg.name), np.asarray(msg.position, dtype=np.float64)))
                parts[side][kind][stamp] = (
                    float(values.get("visible_fraction", np.nan)),
                    np.array([values.get(f"{f}_tip_visible", 1.0) > 0.5 for f in FINGERS]),
                )
            else:
                n = 5 if kind == "fingertips" else 21
                parts[side][kind][stamp] = points_from_msg(msg, n)
    out: dict[str, dict[int, HandTruthRecord]] = {}
    for side in HANDS:
        p = parts[side]
        recs = {}
        for stamp, tips in p["fingertips"].items():
            vis = p["visibility"].get(stamp)
            recs[stamp] = HandTruthRecord(
                fingertips_mm=tips,
                keypoints_mm=p["keypoints"].get(stamp),
                visible_fraction=float("nan") if vis is None else vis[0],
                tips_visible=None if vis is None else vis[1],
            )
        out[side] = recs
    return out
