"""``make_scene_bags``: write the scene sets of issue 46 (is it a hand?) as bags.

One job: the scene-set specification and its writer; kept together because the seeds, shapes
and sensors of the two splits define one reproducible data set.

Usage::

    make_scene_bags --set scenes_dev --surface-frames 15     # the bundled bags/scenes_dev
    make_scene_bags --set scenes_test --out DIR [--frames 45] [--repeats 3]
    make_scene_bags --set scenes_dev --out DIR --repeats 6 --only back leave_top --sensor tof

One bag per scene type of :data:`hand_sog_tracker.synth.scenes.SCENE_TYPES` (and per repeat,
``<type>_<r>`` for ``r > 0``), rendered by :func:`~hand_sog_tracker.synth.scenes.scene_frames`
and written by :func:`~hand_sog_tracker.tools.bagio.write_depth_bag` like the sample bags
(contract 5: depth, CameraInfo, and the fingertip ground truth on the frames that have a
hand in the scene, even outside the image).  Each bag directory also holds:

* ``hand_sog_sample.json``: the sidecar (``renderer: scene``, split, scene type, seed, shape,
  sensor, handedness, size, frames);
* ``scene_truth.json``: per frame its stamp (ns), visibility (``full``/``partial``/``absent``)
  and the 21 joints (mm, MediaPipe order, null without a hand).

``--surface-frames N`` gives the scenes with large surfaces (``nohand_head``, ``nohand_objects``,
``table``: a noisy ToF surface is 30-50 kB per compressed frame) N frames instead (the bundled
``bags/scenes_dev`` uses 15 to stay small; the generator writes bigger sets).

``scenes_dev`` (look, tune) and ``scenes_test`` (score only) differ in seeds
(``crc32("<set>/<type>/<repeat>")``), hand shapes and sensor assignment.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final, Sequence

import numpy as np

from hand_sog_tracker.errors import BagError, HandSogError, InputError
from hand_sog_tracker.synth.mesh import MeshShape
from hand_sog_tracker.synth.scenes import SCENE_TYPES, scene_frames
from hand_sog_tracker.synth.sensors import SENSORS
from hand_sog_tracker.synth.sequence import default_intrinsics
from hand_sog_tracker.tools.bagio import DepthSample, write_depth_bag
from hand_sog_tracker.tools.make_sample_bags import BASE_STAMP_NS, FPS, SIDECAR

__all__ = ["SCENE_SETS", "SCENE_TRUTH", "SceneSpec", "scene_set", "write_scene_bag", "read_scene_truth", "main"]

#: Per-frame ground truth file of a scene bag.
SCENE_TRUTH: Final = "scene_truth.json"
_SETS: Final[dict[str, dict[str, Any]]] = {
    "scenes_dev": {
        "split": "dev",
        "shapes": ((1.0, 1.0, 1.0), (0.9, 1.05, 0.95), (1.1, 0.92, 1.08)),
        "sensors": ("tof", "structured"),
    },
    "scenes_test": {
        "split": "test",
        "shapes": ((0.87, 0.9, 0.88), (1.13, 1.12, 1.1), (0.95, 1.14, 1.02)),
        "sensors": ("structured", "tof"),
    },
}
#: The scene sets :func:`scene_set` knows.
SCENE_SETS: Final = tuple(_SETS)
#: Scene types with large surfaces (see ``--surface-frames``).
SURFACE_TYPES: Final = ("nohand_head", "nohand_objects", "table")


@dataclass(frozen=True)
class SceneSpec:
    """One bag of a scene set."""

    name: str
    kind: str
    seed: int
    shape: MeshShape
    sensor: str
    frames: int
    split: str


def scene_set(
    name: str, frames: int = 45, repeats: int = 1, surface_frames: int | None = None, sensor: str | None = None,
    shape: MeshShape | None = None,
) -> list[SceneSpec]:
    """The bags of scene set ``name`` (``scenes_dev`` or ``scenes_test``), deterministic;
    ``surface_frames``: frames of the :data:`SURFACE_TYPES` (default ``frames``); ``sensor``:
    every bag with this sensor instead of the set's (each scene type has one sensor in every
    repeat, so e.g. the dev set's back-of-hand scenes are otherwise all structured light);
    ``shape``: every hand of this shape instead of the set's three.

    Raises
    ------
    InputError
        Unknown set, ``frames < 1`` or ``repeats < 1``.
    """
    if name not in _SETS:
        raise InputError(f"unknown scene set {name!r}; choose from {', '.join(SCENE_SETS)}")
    if frames < 1 or repeats < 1:
        raise InputError("frames and repeats must be >= 1")
    d = _SETS[name]
    out = []
    i = 0
    for r in range(repeats):
        for kind in SCENE_TYPES:
            out.append(
                SceneSpec(
                    name=kind if r == 0 else f"{kind}_{r}",
                    kind=kind,
                    seed=zlib.crc32(f"{name}/{kind}/{r}".encode("utf-8")) & 0x7FFFFFFF,
                    shape=shape or MeshShape(*d["shapes"][i % len(d["shapes"])]),
                    sensor=sensor or d["sensors"][(i + r) % len(d["sensors"])],
                    frames=surface_frames if surface_frames and kind in SURFACE_TYPES else frames,
                    split=d["split"],
                )
            )
            i += 1
    return out


def write_scene_bag(path: str | Path, spec: SceneSpec, width: int = 320, height: int = 240) -> int:
    """Render ``spec`` and write it as a bag at ``path`` (replaced); returns its size in bytes."""
    out = Path(path)
    if out.exists():
        if not (out / "metadata.yaml").is_file():
            raise BagError(f"{out} exists and is not a rosbag2 directory; not replacing it")
        shutil.rmtree(out)
    intr = default_intrinsics(width, height)
    truth: list[dict[str, Any]] = []

    def samples():
        for f in scene_frames(spec.kind, spec.frames, intr, spec.shape, True, spec.seed, spec.sensor, FPS):
            stamp = BASE_STAMP_NS + int(round(f.index * 1e9 / FPS))
            truth.append({
                "stamp_ns": stamp,
                "visibility": f.visibility,
                "joints_mm": None if f.joints_mm is None else np.round(f.joints_mm, 2).tolist(),
            })
            yield DepthSample(stamp, f.depth_mm, intr, f.fingertips_mm)

    out.parent.mkdir(parents=True, exist_ok=True)
    write_depth_bag(out, samples(), encoding="16UC1")
    sample = {
        "renderer": "scene", "split": spec.split, "scene": spec.kind, "seed": spec.seed,
        "sensor": spec.sensor, "handedness": "right", "width": width, "height": height,
        "encoding": "16UC1", "frames": spec.frames, "background_mm": None,
        "shape": {"length": spec.shape.length, "palm_width": spec.shape.palm_width, "thickness": spec.shape.thickness},
    }
    (out / SIDECAR).write_text(json.dumps(sample, indent=2, sort_keys=True) + "\n", encoding="utf-8")
    (out / SCENE_TRUTH).write_text(json.dumps({"frames": truth}) + "\n", encoding="utf-8")
    return sum(f.stat().st_size for f in out.rglob("*") if f.is_file())


def read_scene_truth(bag: str | Path) -> dict[int, tuple[str, np.ndarray | None]]:
    """``scene_truth.json`` of a scene bag: stamp (ns) -> (visibility, joints (21, 3) mm or None).

    Raises
    ------
    BagError
        The file is missing or malformed.
    """
    f = Path(bag) / SCENE_TRUTH
    try:
        frames = json.loads(f.read_text(encoding="utf-8"))["frames"]
        return {
            int(r["stamp_ns"]): (str(r["visibility"]), None if r["joints_mm"] is None else np.asarray(r["joints_mm"]))
            for r in frames
        }
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise BagError(f"cannot read the scene truth {f}: {err}") from err


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point; returns the exit status (0 ok, 2 error)."""
    p = argparse.ArgumentParser(prog="make_scene_bags", description="Write the hand/no-hand scene sets (issue 46).")
    p.add_argument("--set", choices=SCENE_SETS, required=True, dest="scene_set")
    p.add_argument("--out", default=None, help="output directory (default bags/<set>)")
    p.add_argument("--frames", type=int, default=45, help="frames per bag (default 45, 1.5 s at 30 fps)")
    p.add_argument("--repeats", type=int, default=1, help="bags per scene type, other seeds (default 1)")
    p.add_argument("--surface-frames", type=int, default=None, metavar="N",
                   help="frames of the scenes with large surfaces (default --frames)")
    p.add_argument("--only", nargs="+", metavar="TYPE", choices=SCENE_TYPES, help="only these scene types")
    p.add_argument("--sensor", choices=SENSORS, default=None, help="every bag with this sensor (default: the set's)")
    p.add_argument("--shape", type=float, nargs=3, default=None, metavar=("LENGTH", "WIDTH", "THICKNESS"),
                   help="every hand of this shape (default: the set's)")
    args = p.parse_args(argv)
    root = Path(args.out or Path("bags") / args.scene_set)
    try:
        total = 0
        for spec in scene_set(
            args.scene_set, args.frames, args.repeats, args.surface_frames, args.sensor,
            MeshShape(*args.shape) if args.shape else None,
        ):
            if args.only and spec.kind not in args.only:
                continue
            size = write_scene_bag(root / spec.name, spec)
            total += size
            print(f"{root / spec.name}: {spec.frames} frames, {spec.sensor}, {size / 1e3:.0f} kB")
    except HandSogError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"{total / 1e6:.2f} MB in total")
    return 0


if __name__ == "__main__":
    sys.exit(main())
