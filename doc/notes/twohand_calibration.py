"""Two hands, each calibrated from its own frames: tip error per hand, default model vs calibrated.

Core mode, deterministic.  Each scene of the two-hand dev set (``twohand_set("twohands_dev",
frames)``: its shapes, sensors and seeds; ``--set twohands_test`` for the test set, scored
once) is rendered in process and tracked twice by
``MultiHandTracker``: with each hand's default model throughout, and with the node's
``~/calibrate`` at frame ``--at`` (each label's history of the last half second as the node keeps
it: the reported hand's pose, the other live tracks' pixels masked; ``choose_fit_frames``, the
same fit and guard; an accepted fit switched in with ``set_model``).  ``--no-mask`` fits on the
whole frames (the other hand left in); ``--alone`` is the one-hand reference: each hand of the
same scene rendered alone (``shown``), the one-hand ``Tracker`` of its handedness and the one-hand
``~/calibrate`` at the same frame; ``--open-until K`` holds both hands' fingers open up to
frame K (what the calibration asks the user to do) and blends into the scene's motion after it.
Prints, per scene and hand, the fit's verdict and factors and the mean fingertip error (mm) over
the frames after ``--at`` for both runs.

    cd <worktree> && python doc/notes/twohand_calibration.py --frames 90 --at 20 [--scenes apart approach]
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from hand_sog_tracker.core.articulations import OPEN
from hand_sog_tracker.core.autocalibration import FrameHistory, choose_fit_frames
from hand_sog_tracker.core.calibration import CalibrationRejected, calibrate
from hand_sog_tracker.core.hand_model import JOINTS
from hand_sog_tracker.core.hands import HANDS, MultiHandTracker
from hand_sog_tracker.core.tracker import Tracker
from hand_sog_tracker.core.types import TrackerConfig, TrackerStatus
from hand_sog_tracker.errors import HandSogError
from hand_sog_tracker.synth.twohands import TwoHandFrame, render_two_hands, scene_poses, two_hand_sequence
from hand_sog_tracker.tools.twohand_bags import twohand_set

PERIOD_NS = 33_333_333


def run(frames, at: int | None, mask: bool = True) -> dict:
    """Track ``frames``; with ``at``, calibrate each hand there.  Per side: errors after ``at``."""
    config = TrackerConfig()
    mt = MultiHandTracker(config, max_hands=2)
    histories = {s: FrameHistory() for s in HANDS}
    errors: dict[str, list[float]] = {s: [] for s in HANDS}
    fits: dict[str, str] = {}
    for k, fr in enumerate(frames):
        out = mt.process(fr.depth_mm, INTR)
        stamp = k * PERIOD_NS
        live = mt.hands_in_view()
        reported = {h.handedness: h for h in out.hands if h.result.status is TrackerStatus.TRACKING}
        for side in HANDS:
            h = reported.get(side)
            others = [(m, x) for tid, m, x in live if h is None or tid != h.track_id] if mask else []
            pose = None if h is None else h.result.pose
            histories[side].remember(fr.depth_mm, INTR, pose, stamp, others if pose is not None else ())
        if at is not None and k == at:
            for side in HANDS:
                chosen = choose_fit_frames(histories[side].frames(), 3, 4)
                if chosen is None or not chosen.usable:
                    fits[side] = "not fitted"
                    continue
                cfg = replace(config, right_hand=side == "right")
                args, kwargs = chosen.calibrate_args(cfg, mt.model(side))
                try:
                    res = calibrate(*args, **kwargs)
                    mt.set_model(side, res.model)
                    fits[side] = f"accepted {res.shape.describe()}"
                except CalibrationRejected as err:
                    fits[side] = ("already fits " if err.validation.already_fits else "refused ") + err.shape.describe()
                except HandSogError as err:
                    fits[side] = f"failed: {err}"
        if at is None or k > at:
            truth = {t.handedness: t.fingertips_mm for t in fr.hands}
            for side in HANDS:
                h = reported.get(side)
                tips = None if h is None else h.result.fingertips_mm
                err = np.nan if tips is None else float(np.linalg.norm(tips - truth[side], axis=1).mean())
                errors[side].append(err)
    return {"errors": errors, "fits": fits}


def run_alone(frames, side: str, at: int | None) -> dict:
    """The one-hand reference: ``frames`` show the ``side`` hand alone; the one-hand ``Tracker``
    of that handedness, and with ``at`` the one-hand node's ``~/calibrate`` there."""
    config = TrackerConfig(right_hand=side == "right")
    tracker = Tracker(config)
    history = FrameHistory()
    errors: list[float] = []
    fit = ""
    for k, fr in enumerate(frames):
        res = tracker.process(fr.depth_mm, INTR)
        pose = res.pose if res.status is TrackerStatus.TRACKING else None
        history.remember(fr.depth_mm, INTR, pose, k * PERIOD_NS)
        if at is not None and k == at:
            chosen = choose_fit_frames(history.frames(), 3, 4)
            if chosen is not None and chosen.usable:
                args, kwargs = chosen.calibrate_args(config, tracker.model)
                try:
                    out = calibrate(*args, **kwargs)
                    tracker.set_model(out.model)
                    fit = f"accepted {out.shape.describe()}"
                except CalibrationRejected as err:
                    fit = ("already fits " if err.validation.already_fits else "refused ") + err.shape.describe()
                except HandSogError as err:
                    fit = f"failed: {err}"
        if at is None or k > at:
            truth = next(t.fingertips_mm for t in fr.hands if t.handedness == side)
            tips = res.fingertips_mm if pose is not None else None
            errors.append(np.nan if tips is None else float(np.linalg.norm(tips - truth, axis=1).mean()))
    return {"errors": errors, "fit": fit}


def open_then_scene(spec, n: int, until: int, blend: int = 10, shown=HANDS):
    """The scene's frames with both hands' fingers held open (``OPEN``, the calibration's
    protocol) up to frame ``until``, then blended into the scene's own motion over ``blend``
    frames; the global motion is the scene's throughout (:func:`two_hand_sequence` otherwise)."""
    left, right, ball = scene_poses(spec.scene, n, seed=spec.seed)
    w = np.clip((np.arange(n) - until) / float(blend), 0.0, 1.0)[:, None]
    for poses in (left, right):
        poses[:, JOINTS] = (1.0 - w) * np.asarray(OPEN)[None, :] + w * poses[:, JOINTS]
    rng = np.random.default_rng(np.random.SeedSequence(spec.seed).spawn(4)[3])
    out = []
    for k in range(n):
        depth, truths, owner = render_two_hands(
            left[k], right[k], INTR, spec.scene.shapes, spec.sensor, rng, ball[k, :3], shown=shown
        )
        out.append(TwoHandFrame(index=k, stamp_s=k / 30.0, depth_mm=depth, hands=truths, owner=owner))
    return out


def main() -> None:
    global INTR
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=90)
    ap.add_argument("--set", default="twohands_dev", choices=("twohands_dev", "twohands_test"),
                    help="the set whose scenes, shapes, sensors and seeds are rendered (test: score once)")
    ap.add_argument("--at", type=int, default=20)
    ap.add_argument("--scenes", nargs="*", default=None)
    ap.add_argument("--no-mask", action="store_true")
    ap.add_argument("--json", default=None)
    ap.add_argument("--alone", action="store_true", help="each hand rendered alone, the one-hand tracker and fit")
    ap.add_argument("--open-until", type=int, default=None, metavar="K",
                    help="fingers held open up to frame K (then the scene's motion, blended over 10 frames)")
    a = ap.parse_args()
    from hand_sog_tracker.synth.sequence import default_intrinsics

    INTR = default_intrinsics()
    rows = []
    for spec in twohand_set(a.set, a.frames):
        if a.scenes and spec.name not in a.scenes:
            continue
        if a.alone:
            for side in HANDS:
                frames = open_then_scene(spec, spec.frames, a.open_until, shown=(side,)) if a.open_until else list(
                    two_hand_sequence(spec.scene, spec.frames, INTR, seed=spec.seed, sensor=spec.sensor, shown=(side,))
                )
                base, cal = run_alone(frames, side, None), run_alone(frames, side, a.at)
                e0, e1 = np.array(base["errors"][a.at + 1:]), np.array(cal["errors"])
                row = {
                    "scene": spec.name, "side": side, "sensor": spec.sensor, "alone": True, "fit": cal["fit"],
                    "default_mm": float(np.nanmean(e0)), "calibrated_mm": float(np.nanmean(e1)),
                    "frames": [int(np.isfinite(e0).sum()), int(np.isfinite(e1).sum())],
                }
                rows.append(row)
                print(f"{spec.name:9s} {side:5s} alone default {row['default_mm']:6.2f} ({row['frames'][0]}) "
                      f"calibrated {row['calibrated_mm']:6.2f} ({row['frames'][1]})  {row['fit']}", flush=True)
            continue
        if a.open_until:
            frames = open_then_scene(spec, spec.frames, a.open_until)
        else:
            frames = list(two_hand_sequence(spec.scene, spec.frames, INTR, seed=spec.seed, sensor=spec.sensor))
        base = run(frames, None)
        cal = run(frames, a.at, mask=not a.no_mask)
        for i, side in enumerate(HANDS):
            e0 = np.array(base["errors"][side][a.at + 1:])
            e1 = np.array(cal["errors"][side])
            shape = spec.scene.shapes[i]
            row = {
                "scene": spec.name, "side": side, "sensor": spec.sensor,
                "shape": [shape.length, shape.palm_width, shape.thickness],
                "fit": cal["fits"].get(side, ""),
                "default_mm": float(np.nanmean(e0)) if np.isfinite(e0).any() else float("nan"),
                "calibrated_mm": float(np.nanmean(e1)) if np.isfinite(e1).any() else float("nan"),
                "frames": [int(np.isfinite(e0).sum()), int(np.isfinite(e1).sum())],
            }
            rows.append(row)
            print(f"{spec.name:9s} {side:5s} {spec.sensor:10s} L/W/T {row['shape']} default {row['default_mm']:6.2f} "
                  f"({row['frames'][0]}) calibrated {row['calibrated_mm']:6.2f} ({row['frames'][1]})  {row['fit']}",
                  flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


INTR = None

if __name__ == "__main__":
    main()
