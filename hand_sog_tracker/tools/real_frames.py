"""Fingertip error on labelled single depth frames, unperturbed and under small shifts.

Usage::

    python -m hand_sog_tracker.tools.real_frames ../shared/realdata/realsense-user1 \\
        --labels test/data/realsense_fingertips.json [--frames 1-8] [--no-mirror]
        [--unperturbed | --wide] [--json OUT]

Each frame is a folder ``FRAMES_DIR/<frame>/depth.png`` (16-bit depth in mm); the labels file
gives the camera's intrinsics and, per frame, the five fingertips thumb .. little as a pixel
and a depth (``{"intrinsics": {...}, "frames": {"1": {"tips": [{"u", "v", "depth_mm"}, ...]}}}``,
the format of ``test/data/realsense_fingertips.json``).  A frame is a static sequence: a fresh
core tracker processes it :data:`PASSES` times (initialisation, then tracking on the same
image) and the last result's fingertips are scored against the labels (3D distance, mm).

Besides the frame as recorded, :data:`VARIANTS` moves the image and its labels by one whole
pixel in each direction (``np.roll``) or offsets every valid depth by +-3 mm, and ``mirror``
flips each variant left-right (``u -> W - 1 - u``, ``cx -> W - 1 - cx``) and tracks it as a
left hand: 8 frames x 7 variants x 2 hands are the documentation's "112 runs".  Such small changes
decide between the right pose and a hand one finger over on some frames (documentation, known
limitations), so a single run per frame says little.  ``--wide`` runs :data:`WIDE_VARIANTS` instead
(larger shifts, used less often for decisions: with ``--no-mirror`` the documentation's "128 runs").
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.tracker import Tracker
from hand_sog_tracker.core.types import Intrinsics, TrackerConfig
from hand_sog_tracker.errors import HandSogError, InputError

__all__ = [
    "PASSES", "VARIANTS", "WIDE_VARIANTS", "Variant", "labelled_frame", "static_tip_errors", "run_real_frames",
    "number_list", "main",
]

#: Times each frame is processed (count): the first pass finds the hand, the other nine track it
#: on the same image (the node, too, refines a single image 9 times before it answers: ``ros/node.py``).
PASSES = 10
#: A run that misses by more than this (mean over the five fingertips, mm) is counted apart:
#: typically a hand one finger over.
FAR_MM = 20.0


@dataclass(frozen=True)
class Variant:
    """A perturbation of a labelled frame: whole pixels ``du`` (right), ``dv`` (down) and a depth
    offset ``dz_mm`` (mm, added to every valid depth and to the labels)."""

    du: int = 0
    dv: int = 0
    dz_mm: float = 0.0


#: The frame as recorded, moved by a pixel in each direction, and offset by +-3 mm in depth.
VARIANTS: tuple[Variant, ...] = (
    Variant(),
    Variant(du=1),
    Variant(du=-1),
    Variant(dv=1),
    Variant(dv=-1),
    Variant(dz_mm=3.0),
    Variant(dz_mm=-3.0),
)


#: Larger shifts, checked less often for decisions (the documentation's "128 runs", right hands): the image
#: rolled by 3 px left or right and 2 px up or down, each with a depth offset of -3, -1, +1 or +3 mm.
WIDE_VARIANTS: tuple[Variant, ...] = tuple(
    Variant(du, dv, dz) for du in (-3, 3) for dv in (-2, 2) for dz in (-3.0, -1.0, 1.0, 3.0)
)


def _intrinsics(labels: dict[str, Any]) -> Intrinsics:
    k = labels["intrinsics"]
    return Intrinsics(float(k["fx"]), float(k["fy"]), float(k["cx"]), float(k["cy"]), int(k["width"]), int(k["height"]))


def labelled_frame(
    frames_dir: Path, labels: dict[str, Any], frame: int, mirror: bool = False, variant: Variant = Variant()
) -> tuple[NDArray[np.float32], Intrinsics, NDArray[np.float64]]:
    """Depth (H, W) float32 mm (0 = invalid), its intrinsics and the labelled fingertips (5, 3)
    mm (camera frame, thumb .. little) of ``frame``, mirrored and perturbed as asked.

    Raises
    ------
    InputError
        The frame has no labels, or its depth image is missing or of another size than the
        labels' intrinsics.
    """
    entry = labels["frames"].get(str(frame))
    if entry is None:
        raise InputError(f"frame {frame} has no labels")
    intr = _intrinsics(labels)
    path = Path(frames_dir) / str(frame) / "depth.png"
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise InputError(f"cannot read {path}")
    if raw.shape != (intr.height, intr.width):
        raise InputError(f"{path} is {raw.shape[1]}x{raw.shape[0]}, the labels' intrinsics {intr.width}x{intr.height}")
    depth = raw.astype(np.float32)
    tips = entry["tips"]
    uv = np.array([[t["u"], t["v"]] for t in tips], dtype=np.float64)
    z = np.array([t["depth_mm"] for t in tips], dtype=np.float64)
    if mirror:
        depth = np.ascontiguousarray(depth[:, ::-1])
        uv[:, 0] = intr.width - 1 - uv[:, 0]
        intr = Intrinsics(intr.fx, intr.fy, intr.width - 1 - intr.cx, intr.cy, intr.width, intr.height)
    if variant.du or variant.dv:
        depth = np.roll(depth, (variant.dv, variant.du), axis=(0, 1))
        uv += (variant.du, variant.dv)
    if variant.dz_mm:
        depth = np.where(depth > 0, depth + np.float32(variant.dz_mm), np.float32(0.0))
        z = z + variant.dz_mm
    return depth, intr, intr.backproject(uv, z)


def static_tip_errors(
    depth: NDArray[np.float32],
    intr: Intrinsics,
    truth_mm: NDArray[np.float64],
    right_hand: bool = True,
    withhold: bool = True,
) -> NDArray[np.float64] | None:
    """Fingertip errors (5,) mm of a fresh core tracker after :data:`PASSES` passes over the
    frame ``depth`` (mm), against ``truth_mm`` (5, 3); None when the hand is not reported
    (``withhold`` False: not tracked, whatever the hand decision; see ``Tracker``)."""
    tracker = Tracker(TrackerConfig(right_hand=right_hand), withhold=withhold)
    res = None
    for _ in range(PASSES):
        res = tracker.process(depth, intr)
    if res is None or res.fingertips_mm is None:
        return None
    return np.linalg.norm(res.fingertips_mm - truth_mm, axis=1)


def run_real_frames(
    frames_dir: Path,
    labels: dict[str, Any],
    frames: Sequence[int],
    mirrored: bool = True,
    variants: Sequence[Variant] = VARIANTS,
) -> list[dict[str, Any]]:
    """One record per run (frame x hand x variant): ``frame``, ``mirror``, ``du``, ``dv``,
    ``dz_mm`` and ``errors_mm`` (five floats, mm; None when the hand was not tracked)."""
    runs = []
    for frame in frames:
        for mirror in (False, True) if mirrored else (False,):
            for v in variants:
                depth, intr, truth = labelled_frame(frames_dir, labels, frame, mirror, v)
                err = static_tip_errors(depth, intr, truth, right_hand=not mirror)
                runs.append(
                    {
                        "frame": frame, "mirror": mirror, "du": v.du, "dv": v.dv, "dz_mm": v.dz_mm,
                        "errors_mm": None if err is None else [round(float(e), 2) for e in err],
                    }
                )
    return runs


def _run_mean(run: dict[str, Any]) -> float:
    """Mean fingertip error (mm) of a run; an untracked hand counts as ``inf``."""
    return float("inf") if run["errors_mm"] is None else float(np.mean(run["errors_mm"]))


def _summary(runs: Sequence[dict[str, Any]]) -> str:
    lines = []
    for frame in sorted({r["frame"] for r in runs}):
        means = [_run_mean(r) for r in runs if r["frame"] == frame]
        far = sum(m > FAR_MM for m in means)
        lines.append(
            f"frame {frame}: mean {np.mean(means):6.1f} mm, runs over {FAR_MM:.0f} mm {far}/{len(means)}  "
            + " ".join(f"{m:.0f}" for m in means)
        )
    means = np.array([_run_mean(r) for r in runs])
    plain = [r for r in runs if not r["mirror"] and (r["du"], r["dv"], r["dz_mm"]) == (0, 0, 0.0)]
    tips = np.array([e for r in plain for e in (r["errors_mm"] or [float("inf")] * 5)])
    lines.append(
        f"all {len(runs)} runs: mean {means.mean():.2f} mm, runs over {FAR_MM:.0f} mm {int((means > FAR_MM).sum())}"
    )
    if tips.size:
        lines.append(
            f"unperturbed right hands ({len(plain)} frames): {int((tips < 15.0).sum())} of {tips.size} fingertips "
            f"within 15 mm, mean {tips.mean():.2f} mm"
        )
    return "\n".join(lines)


def number_list(spec: str) -> list[int]:
    """``"1-8"``, ``"2,3"`` or both (``"1-3,7"``) as a list of integers; ValueError when a part
    is no integer or an empty range (``"5-1"``)."""
    out: list[int] = []
    for part in spec.split(","):
        lo, _, hi = part.partition("-")
        first, last = int(lo), int(hi or lo)
        if last < first:
            raise ValueError(f"empty range {part!r}")
        out += range(first, last + 1)
    return out


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``real_frames`` (also read by the documentation)."""
    parser = argparse.ArgumentParser(
        prog="real_frames",
        description="Fingertip error of the core tracker on labelled single depth frames, each fed "
        f"{PASSES} times, as recorded and under one-pixel shifts and +-3 mm depth offsets, as a right "
        "hand and mirrored as a left hand.",
    )
    parser.add_argument(
        "frames_dir", type=Path, help="folder with one sub-folder per frame holding depth.png (uint16, mm)"
    )
    parser.add_argument(
        "--labels", type=Path, required=True, help="fingertip labels JSON (test/data/realsense_fingertips.json)"
    )
    parser.add_argument("--frames", default=None, help="frames to run, e.g. 1-8 or 2,3 (default: every labelled frame)")
    parser.add_argument("--no-mirror", action="store_true", help="skip the mirrored (left-hand) copies")
    which = parser.add_mutually_exclusive_group()
    which.add_argument(
        "--unperturbed", action="store_true", help="only the frames as recorded (no shifts, no offsets)"
    )
    which.add_argument(
        "--wide", action="store_true",
        help="16 larger shifts instead (u +-3 px, v +-2 px, depth +-1/+-3 mm; "
        "with --no-mirror the documentation's 128 runs)",
    )
    parser.add_argument("--json", type=Path, default=None, metavar="OUT", help="also write every run to this JSON file")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        labels = json.loads(args.labels.read_text())
        frames = number_list(args.frames) if args.frames else sorted(int(k) for k in labels["frames"])
        runs = run_real_frames(
            args.frames_dir, labels, frames, mirrored=not args.no_mirror,
            variants=VARIANTS[:1] if args.unperturbed else WIDE_VARIANTS if args.wide else VARIANTS,
        )
    except (OSError, ValueError, KeyError, HandSogError) as exc:
        print(f"real_frames: {exc}", file=sys.stderr)
        return 2
    print(_summary(runs))
    if args.json is not None:
        args.json.write_text(json.dumps({"passes": PASSES, "runs": runs}, indent=1))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
