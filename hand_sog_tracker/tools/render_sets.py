"""Tracking accuracy on sets of random mesh renders: the development, validation and further sets.

Usage::

    python -m hand_sog_tracker.tools.render_sets 3000-3095 [--jobs 2] [--json OUT]
        [--compare OLD.json] [--frames 60] [--resolution 320x240]
        [--finger-spread 0.08] [--wall-mm 80] [--no-auto-calibration]
        [--set NAME=VALUE ...]

Each seed draws one render (:func:`render_spec`): the motion (seed modulo 10 over the nine
motions of :data:`~hand_sog_tracker.synth.motions.ALL_MOTIONS`, fist-and-open twice), the hand
(length 0.86-1.14, palm width 0.9-1.1, thickness 0.88-1.12; a right hand with probability 0.6),
the sensor (ToF, structured light or clean depth) and the forearm's bend at the wrist (up to 25
deg either way in and out of the palm plane).  Optionally each finger's length is drawn as
well (``--finger-spread``: 1 +- the spread, from a second generator, so that the rest of the
draw stays the same) and a fronto-parallel wall stands behind the hand (``--wall-mm``: that
far behind the motions' start depth of the wrist, 400 mm).  The mesh renderer
(:mod:`hand_sog_tracker.synth.mesh`) draws its frames, a fresh core tracker tracks them with
the automatic calibration on (as the node and ``evaluate_bag`` do), and every frame is scored:
the mean distance of the five fingertips from the truth (mm), 100 mm for a frame without a
hand.

The documentation's sets are the seeds 3000-3095 (development: look, tune), 5000-5095 (validation)
and 7000-7095 (further: score only).  ``--compare`` prints how a set moved against an earlier
``--json`` of the same seeds (renders better or worse by more than 0.3 mm, frames over 20 mm).
A render takes 1-2 s per core; ``--jobs`` runs renders in parallel processes (the results do
not depend on it).  ``--set`` tracks with other tracker parameters (the node's names, as in
``evaluate_bag``; the render decides the handedness).
"""

from __future__ import annotations

import os

# One thread per process, set before NumPy is imported (as in benchmark): the numbers are
# single-core numbers and parallel jobs do not compete for cores.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections import defaultdict  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from dataclasses import asdict, dataclass, replace  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any, Mapping, Sequence  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from hand_sog_tracker.core.autocalibration import AutoCalibration, FrameHistory  # noqa: E402
from hand_sog_tracker.core.tracker import Tracker  # noqa: E402
from hand_sog_tracker.core.types import TrackerStatus  # noqa: E402
from hand_sog_tracker.errors import HandSogError, InputError  # noqa: E402
from hand_sog_tracker.synth.mesh import MeshRenderOptions, MeshShape, mesh_sequence  # noqa: E402
from hand_sog_tracker.synth.motions import ALL_MOTIONS, START_TRANSLATION_MM  # noqa: E402
from hand_sog_tracker.synth.sequence import default_intrinsics  # noqa: E402
from hand_sog_tracker.tools.evaluation import auto_step  # noqa: E402
from hand_sog_tracker.tools.real_frames import number_list  # noqa: E402
from hand_sog_tracker.tools.tracker_params import Value, core_settings, tracker_config  # noqa: E402

__all__ = ["NO_HAND_MM", "SET_MOTIONS", "RenderSpec", "render_spec", "track_render", "settings", "compare", "main"]

#: The motions a seed picks from (seed modulo 10): fist-and-open, the hardest, twice.
SET_MOTIONS: tuple[str, ...] = tuple(ALL_MOTIONS) + ("fistopen",)
#: Score of a frame in which the tracker reports no hand (mm).
NO_HAND_MM = 100.0
#: Frames per second of the renders (the automatic calibration's history is timed by it).
FPS = 30.0
#: A render counts as better or worse in :func:`compare` when its mean moved by more than this (mm).
CHANGE_MM = 0.3
#: Frames worse than this (mm) are counted apart (a finger on its neighbour, a lost hand).
BAD_FRAME_MM = 20.0


@dataclass(frozen=True)
class RenderSpec:
    """One render of a set (what :func:`render_spec` draws for a seed).

    Attributes
    ----------
    seed : int
    motion : str
    shape : MeshShape
    right : bool
    sensor : str
        One of :data:`~hand_sog_tracker.synth.mesh.SENSORS`.
    wrist_deg : (float, float)
        The forearm's deviation and flexion at the wrist (deg).
    wall_mm : float or None
        Depth of a fronto-parallel wall (mm), or None.
    """

    seed: int
    motion: str
    shape: MeshShape
    right: bool
    sensor: str
    wrist_deg: tuple[float, float]
    wall_mm: float | None = None

    def options(self) -> MeshRenderOptions:
        """The renderer's options of this render."""
        return MeshRenderOptions(
            sensor=self.sensor, background_mm=self.wall_mm,
            wrist_deviation_deg=self.wrist_deg[0], wrist_flexion_deg=self.wrist_deg[1],
        )


def render_spec(seed: int, finger_spread: float = 0.0, wall_mm: float | None = None) -> RenderSpec:
    """The render of ``seed``: motion, hand, sensor and wrist bend drawn as the module docstring
    says; ``finger_spread`` (0 to 0.3): each finger's length factor from ``1 +- finger_spread``;
    ``wall_mm``: a wall this far (mm) behind the start depth of the wrist."""
    if not 0.0 <= finger_spread <= 0.3:
        raise InputError(f"finger_spread must be in [0, 0.3], got {finger_spread!r}")
    if wall_mm is not None and not (np.isfinite(wall_mm) and wall_mm > 0.0):
        raise InputError(f"wall_mm must be positive, got {wall_mm!r}")
    rng = np.random.default_rng(seed * 7919 + 13)
    motion = SET_MOTIONS[seed % len(SET_MOTIONS)]
    length, width, thickness = (float(rng.uniform(lo, hi)) for lo, hi in ((0.86, 1.14), (0.9, 1.1), (0.88, 1.12)))
    fingers = (1.0,) * 5
    if finger_spread > 0.0:  # (a generator of its own: the other draws stay those of the plain set)
        drawn = np.random.default_rng(seed + 111).uniform(1 - finger_spread, 1 + finger_spread, 5)
        fingers = tuple(float(v) for v in drawn)
    right = bool(rng.random() < 0.6)
    sensor = str(rng.choice(["tof", "structured", "clean"]))
    wrist = (float(rng.uniform(-25, 25)), float(rng.uniform(-25, 25)))
    return RenderSpec(
        seed=seed, motion=motion, shape=MeshShape(length, width, thickness, fingers), right=right, sensor=sensor,
        wrist_deg=wrist, wall_mm=None if wall_mm is None else START_TRANSLATION_MM[2] + wall_mm,
    )


def track_render(
    spec: RenderSpec,
    frames: int = 60,
    resolution: tuple[int, int] = (320, 240),
    auto_calibration: bool = True,
    params: Mapping[str, Value] | None = None,
) -> dict[str, Any]:
    """Render ``spec`` and track it with a fresh core tracker: ``errors_mm`` (one per frame, mean
    fingertip distance; :data:`NO_HAND_MM` without a hand), ``mean_mm``, ``seconds`` and the
    automatic fits (``fits``: what :func:`~hand_sog_tracker.tools.evaluation.auto_fit` says).
    ``params``: tracker parameters by the node's names (:func:`settings`; default: the defaults)."""
    intr = default_intrinsics(*resolution)
    config = replace(tracker_config(params or {}), right_hand=spec.right)
    tracker = Tracker(config)
    history, auto = FrameHistory(), AutoCalibration(enabled=auto_calibration)
    errors, fits = [], []
    t0 = time.perf_counter()
    sequence = mesh_sequence(
        spec.motion, frames, intrinsics=intr, shape=spec.shape, right=spec.right, seed=spec.seed,
        options=spec.options(), fps=FPS,
    )
    for k, frame in enumerate(sequence):
        res = tracker.process(frame.depth_mm, intr)
        ok = res.status is TrackerStatus.TRACKING and res.fingertips_mm is not None
        errors.append(
            float(np.linalg.norm(res.fingertips_mm - frame.fingertips_mm, axis=1).mean()) if ok else NO_HAND_MM
        )
        pose = res.pose if ok else None
        info = auto_step(tracker, history, auto, frame.depth_mm, intr, pose, int(k * 1e9 / FPS), config)
        if info is not None:
            fits.append({key: info[key] for key in ("accepted", "used", "shape") if key in info})
    return {
        "errors_mm": errors,
        "mean_mm": float(np.mean(errors)),
        "seconds": time.perf_counter() - t0,
        "fits": fits,
    }


def settings(items: Sequence[str]) -> dict[str, Value]:
    """The tracker parameters of ``--set NAME=VALUE`` items, validated as the node does
    (:func:`~hand_sog_tracker.tools.tracker_params.core_settings`: no ``handedness``, each
    render has its own; no parameter only the node uses).

    Raises
    ------
    InputError
        A bad item, ``handedness`` or a node-only parameter.
    """
    return core_settings(items, "each render draws its own hand")


def _job(args: tuple[RenderSpec, int, tuple[int, int], bool, Mapping[str, Value]]) -> tuple[int, dict[str, Any]]:
    cv2.setNumThreads(1)
    spec = args[0]
    return spec.seed, track_render(*args)


def _record(spec: RenderSpec, result: dict[str, Any]) -> dict[str, Any]:
    return {
        "motion": spec.motion, "shape": asdict(spec.shape), "right": spec.right,
        "sensor": spec.sensor, "wrist_deg": list(spec.wrist_deg), "wall_mm": spec.wall_mm, **result,
    }


def run_set(
    seeds: Sequence[int],
    frames: int = 60,
    resolution: tuple[int, int] = (320, 240),
    finger_spread: float = 0.0,
    wall_mm: float | None = None,
    auto_calibration: bool = True,
    jobs: int = 1,
    progress: bool = False,
    params: Mapping[str, Value] | None = None,
) -> dict[str, dict[str, Any]]:
    """Every render of ``seeds`` tracked (:func:`track_render`, with ``params``):
    ``{str(seed): record}``, in seed order; each record holds the spec (motion, shape, right,
    sensor, wrist_deg, wall_mm) and the result."""
    specs = {s: render_spec(s, finger_spread, wall_mm) for s in seeds}
    work = [(specs[s], frames, resolution, auto_calibration, dict(params or {})) for s in seeds]
    out: dict[int, dict[str, Any]] = {}

    def done(seed: int, result: dict[str, Any]) -> None:
        out[seed] = _record(specs[seed], result)
        if progress:
            r = out[seed]
            print(
                f"{seed} {r['motion']:<11} {r['shape']['length']:.2f} {'R' if r['right'] else 'L'} {r['sensor']:<10} "
                f"{r['mean_mm']:6.2f} mm", file=sys.stderr, flush=True,
            )

    if jobs <= 1:
        for w in work:
            done(*_job(w))
    else:
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            for seed, result in pool.map(_job, work):
                done(seed, result)
    return {str(s): out[s] for s in seeds}


def summary(renders: dict[str, dict[str, Any]]) -> str:
    """Mean error per motion and per sensor, and over all renders (mm), with frames over
    :data:`BAD_FRAME_MM` and without a hand."""
    lines = [f"{'':<12} {'renders':>7} {'mean mm':>8} {'frames > 20 mm':>15}"]
    groups: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for r in renders.values():
        groups[r["motion"]].append(r)
    for key in ("tof", "structured", "clean"):
        groups[key] = [r for r in renders.values() if r["sensor"] == key]

    def row(name: str, rs: list[dict[str, Any]]) -> str:
        bad = sum(e > BAD_FRAME_MM for r in rs for e in r["errors_mm"])
        return f"{name:<12} {len(rs):>7} {np.mean([r['mean_mm'] for r in rs]):>8.2f} {bad:>15}"

    motions = sorted(k for k in groups if k not in ("tof", "structured", "clean"))
    lines += [row(m, groups[m]) for m in motions]
    lines += [row(s, groups[s]) for s in ("tof", "structured", "clean") if groups[s]]
    everything = list(renders.values())
    no_hand = sum(e >= NO_HAND_MM for r in everything for e in r["errors_mm"])
    lines.append(f"{row('all', everything)}   (frames without a hand: {no_hand})")
    return "\n".join(lines)


def compare(old: dict[str, dict[str, Any]], new: dict[str, dict[str, Any]], show: int = 4) -> str:
    """How ``new`` moved against ``old`` on their common seeds: means, renders better or worse
    by more than :data:`CHANGE_MM`, frames over :data:`BAD_FRAME_MM`, the largest changes."""
    seeds = sorted(set(old) & set(new), key=int)
    if not seeds:
        return "no common seeds to compare"
    a = np.array([old[s]["mean_mm"] for s in seeds])
    b = np.array([new[s]["mean_mm"] for s in seeds])
    bad_a = sum(e > BAD_FRAME_MM for s in seeds for e in old[s]["errors_mm"])
    bad_b = sum(e > BAD_FRAME_MM for s in seeds for e in new[s]["errors_mm"])
    lines = [
        f"{len(seeds)} renders: {a.mean():.3f} -> {b.mean():.3f} mm; better by > {CHANGE_MM} mm: "
        f"{int((b < a - CHANGE_MM).sum())}, worse: {int((b > a + CHANGE_MM).sum())}; "
        f"frames over {BAD_FRAME_MM:.0f} mm: {bad_a} -> {bad_b}"
    ]
    order = np.argsort(b - a)
    for i in list(order[:show]) + list(order[::-1][:show]):
        if abs(b[i] - a[i]) > CHANGE_MM:
            s = seeds[i]
            lines.append(f"  {s} {new[s]['motion']:<11} {a[i]:.2f} -> {b[i]:.2f} mm")
    return "\n".join(lines)


def _resolution(text: str) -> tuple[int, int]:
    """``"640x480"`` as ``(640, 480)``."""
    w, _, h = text.lower().partition("x")
    try:
        size = int(w), int(h)
    except ValueError:
        size = (0, 0)
    if min(size) < 16:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, e.g. 640x480, got {text!r}")
    return size


def _renders_of(path: Path) -> dict[str, dict[str, Any]]:
    """The records of an earlier ``--json`` file.

    Raises
    ------
    InputError
        Not JSON or not written by ``--json``.
    """
    try:
        renders = json.loads(path.read_text())["renders"]
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{path} is not a render_sets --json file ({type(exc).__name__}: {exc})") from exc
    if not isinstance(renders, dict):
        raise InputError(f"{path} is not a render_sets --json file (its 'renders' is not a mapping)")
    return renders


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``render_sets`` (also read by the documentation)."""
    parser = argparse.ArgumentParser(
        prog="render_sets",
        description="Track sets of random mesh renders (motion, hand, sensor and wrist bend drawn per "
        "seed) with a fresh core tracker each, automatic calibration on, and print the mean fingertip "
        "error per motion and sensor. The documentation's sets: 3000-3095 (development), 5000-5095 "
        "(validation), 7000-7095 (further).",
    )
    parser.add_argument("seeds", help="seeds, e.g. 3000-3095 or 3001,3005")
    parser.add_argument("--frames", type=int, default=60, help="frames per render (default 60, at 30 Hz)")
    parser.add_argument("--resolution", type=_resolution, default=(320, 240), help="image size WxH (default 320x240)")
    parser.add_argument("--finger-spread", type=float, default=0.0,
                        help="each finger's length factor drawn from 1 +- this (default 0: the mesh's proportions)")
    parser.add_argument("--wall-mm", type=float, default=None,
                        help="a wall this far behind the wrist's start depth of 400 mm (default: none)")
    parser.add_argument("--no-auto-calibration", action="store_true", help="track with the default model only")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="one tracker parameter, by the node's name (repeatable), e.g. --set refine_iterations=4")
    parser.add_argument("--jobs", type=int, default=1, help="renders tracked in parallel processes (default 1)")
    parser.add_argument("--json", type=Path, default=None, metavar="OUT", help="write every render's record here")
    parser.add_argument("--compare", type=Path, default=None, metavar="OLD",
                        help="an earlier --json of these seeds to compare with")
    parser.add_argument("--quiet", action="store_true", help="no line per render (on stderr)")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        seeds = number_list(args.seeds)
        if not 1 <= args.frames <= 10000:
            raise InputError("--frames must be in [1, 10000]")
        params = settings(args.set)
        old = _renders_of(args.compare) if args.compare else None
        renders = run_set(
            seeds, args.frames, args.resolution, args.finger_spread, args.wall_mm,
            not args.no_auto_calibration, max(1, args.jobs), progress=not args.quiet, params=params,
        )
    except (OSError, ValueError, KeyError, HandSogError) as exc:
        print(f"render_sets: {exc}", file=sys.stderr)
        return 2
    print(summary(renders))
    if old is not None:
        print(compare(old, renders))
    if args.json is not None:
        options = {
            "frames": args.frames, "resolution": list(args.resolution), "finger_spread": args.finger_spread,
            "wall_mm": args.wall_mm, "auto_calibration": not args.no_auto_calibration, "params": params,
        }
        args.json.write_text(json.dumps({"options": options, "renders": renders}, indent=1))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
