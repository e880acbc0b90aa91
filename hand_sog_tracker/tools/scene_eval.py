"""``scene_eval``: score the hand decision on the scene sets of issue 46 (core mode or the node).

One job: run the scene bags and compute the table of the design note; kept together because
the per-frame records and the per-scene metrics are one definition.

Usage::

    scene_eval bags/scenes_dev [--through-node --domain-id 169] [--set max_hands=2] [--json out.json]

Per frame it records the visibility (``scene_truth.json``), whether a hand was reported,
its confidence, the mean fingertip error and the mean error of the palm keypoints (wrist and
the four finger MCPs).  Core mode runs :class:`~hand_sog_tracker.core.tracker.Tracker` and
its hand decisions (:class:`~hand_sog_tracker.core.handcheck.HandGate`), as the node does; ``--through-node`` replays
each bag at its rate to ``tracker_node`` and listens to ``hand/confidence`` and
``hand/keypoints``.  ``--set NAME=VALUE`` sets a tracker parameter (the node's names, as
``evaluate_bag --set``); with ``max_hands`` 2 core mode runs
:class:`~hand_sog_tracker.core.hands.MultiHandTracker` and a frame reports a hand when it
reports any (the one nearest the truth is scored), and the node's one-hand topics carry the
hand labelled ``handedness``.  Metrics (:func:`summarise`):

* ``no_hand_reported``: share of the frames without any joint in view that report a hand;
* ``full_ok``: share of the fully visible frames with a hand reported within 20 mm mean tip error;
* ``refind``: per return into full view, frames until every tip is within 20 mm;
* ``palm_ok``: share of the fully visible frames with the palm keypoints within 15 mm (mean);
* ``longest_wrong``: the longest run of frames reporting a wrong hand (:func:`longest_wrong`);
* ``auc``: ROC AUC of the confidence separating good frames (a pose, mean tip error < 20 mm)
  from bad ones (> 40 mm, or a pose on a frame without a hand), over the frames with a pose.

Bags of the test split (``make_scene_bags --set scenes_test``) are scored, not looked at
(:data:`~hand_sog_tracker.tools.bagset.PROTOCOL`): ``--overlays`` of them is refused and their
per-frame records are left out of ``--json`` unless ``--allow-test-inspection`` is given.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np

from hand_sog_tracker.core.hands import MultiHandTracker
from hand_sog_tracker.core.kinematics import PALM_ROWS
from hand_sog_tracker.core.tracker import Tracker
from hand_sog_tracker.core.types import TrackerConfig
from hand_sog_tracker.errors import HandSogError
from hand_sog_tracker.ros.blas import limit_blas_threads
from hand_sog_tracker.synth.scenes import ABSENT, FULL, scene_group
from hand_sog_tracker.tools.bagio import DepthBagReader
from hand_sog_tracker.tools.bagset import PROTOCOL, TEST_SPLIT, read_sidecar
from hand_sog_tracker.tools.make_scene_bags import read_scene_truth
from hand_sog_tracker.tools.tracker_params import parse_set, tracker_config

__all__ = [
    "evaluate_scene_core", "evaluate_scene_hands", "evaluate_scene_node", "longest_wrong", "summarise", "roc_auc",
    "main",
]

GOOD_MM, BAD_MM, PALM_MM = 20.0, 40.0, 15.0


def _errors(joints_gt: np.ndarray | None, skel: np.ndarray | None) -> tuple[float, float, float]:
    """(mean tip error, max tip error, mean palm error) mm; NaN when either is missing."""
    if joints_gt is None or skel is None:
        return math.nan, math.nan, math.nan
    tip = np.linalg.norm(skel[4::4] - joints_gt[4::4], axis=1)
    palm = np.linalg.norm(skel[list(PALM_ROWS)] - joints_gt[list(PALM_ROWS)], axis=1)
    return float(tip.mean()), float(tip.max()), float(palm.mean())


def _scene_frames(bag: str | Path) -> Iterator[tuple[Any, Any, np.ndarray | None]]:
    """``bag``'s frames with their ground truth: (frame, visibility, joints (21, 3) mm or None)."""
    truth = read_scene_truth(bag)
    with DepthBagReader(bag, require_truth=False) as reader:
        for f in reader.frames():
            vis, joints = truth[f.stamp_ns]
            yield f, vis, joints


def evaluate_scene_core(
    bag: str | Path, gate: bool = True, config: TrackerConfig | None = None
) -> list[dict[str, Any]]:
    """Per-frame records of ``bag`` tracked in core mode: the tracker's own hand decisions (as
    the node publishes them); ``gate`` False keeps every fitted pose and track (the evidence of
    the raw fit).  The errors are those of the frame's fit, also on frames it withheld (for the
    AUC); ``reported`` says whether the pose was given."""
    tracker = Tracker(config, withhold=gate)
    out = []
    for f, vis, joints in _scene_frames(bag):
        answer = tracker.process(f.depth_mm, f.intrinsics)
        res = tracker.last_fit if tracker.last_fit is not None else answer
        dec = answer.hand
        assert dec is not None
        model = tracker.model
        tip, tip_max, palm = _errors(joints, _keypoints(res))
        ev = dec.evidence
        out.append({
            "index": f.index, "visibility": vis, "posed": res.pose is not None,
            "reported": bool(dec.present) if gate else res.pose is not None,
            "confidence": dec.confidence, "fingers": dec.fingers.round(3).tolist(),
            "tip_mm": tip, "tip_max_mm": tip_max, "palm_mm": palm,
            "reported_skeleton": answer.pose is not None,
            "evidence": None if ev is None else [
                ev.on, ev.explained, ev.fingers_on, ev.ends, ev.in_view, ev.outline, ev.finger_edges, ev.steep
            ],
            "check_ms": answer.timings_ms.get("check", math.nan),
            "pose": None if res.pose is None else np.round(res.pose, 5).tolist(),
            "model_length": float(model.shape.length),
            "proposal": tracker.last_proposal,
        })
    return out


def evaluate_scene_hands(
    bag: str | Path, config: TrackerConfig | None = None, max_hands: int = 2
) -> list[dict[str, Any]]:
    """Per-frame records of ``bag`` tracked by :class:`MultiHandTracker` (``max_hands``), with
    the keys of :func:`evaluate_scene_core` that apply: ``reported`` when any hand is
    reported, ``hands`` how many; the errors and confidence are those of the reported hand
    nearest the truth (the most confident one on a frame without a hand; NaN without any)."""
    tracker = MultiHandTracker(config, max_hands=max_hands)
    out = []
    for f, vis, joints in _scene_frames(bag):
        hands = tracker.process(f.depth_mm, f.intrinsics).hands
        errs = [_errors(joints, _keypoints(h.result)) for h in hands]
        if not hands:
            pick = None
        elif joints is None:
            pick = max(range(len(hands)), key=lambda k: hands[k].result.confidence)
        else:
            pick = min(range(len(hands)), key=lambda k: errs[k][0])
        tip, tip_max, palm = (math.nan,) * 3 if pick is None else errs[pick]
        res = None if pick is None else hands[pick].result
        dec = None if res is None else res.hand
        out.append({
            "index": f.index, "visibility": vis, "posed": res is not None, "reported": res is not None,
            "hands": len(hands), "labels": [h.handedness for h in hands],
            "confidence": 0.0 if res is None else float(res.confidence if dec is None else dec.confidence),
            "tip_mm": tip, "tip_max_mm": tip_max, "palm_mm": palm,
            "pose": None if res is None else np.round(res.pose, 5).tolist(),
        })
    return out


def _keypoints(res: Any) -> np.ndarray | None:
    """The 21 keypoints (21, 3) mm of a result, fingertips as reported (or None)."""
    if res.skeleton_mm is None or res.fingertips_mm is None:
        return None
    out = np.array(res.skeleton_mm, dtype=np.float64)
    out[4::4] = res.fingertips_mm
    return out


def roc_auc(scores: Sequence[float], labels: Sequence[bool]) -> float:
    """ROC AUC of ``scores`` for positives ``labels`` (ties count half); NaN without both classes."""
    s = np.asarray(scores, dtype=np.float64)
    y = np.asarray(labels, dtype=bool)
    pos, neg = s[y], s[~y]
    if pos.size == 0 or neg.size == 0:
        return math.nan
    greater = (pos[:, None] > neg[None, :]).sum()
    ties = (pos[:, None] == neg[None, :]).sum()
    return float((greater + 0.5 * ties) / (pos.size * neg.size))


def summarise(records: list[dict[str, Any]]) -> dict[str, Any]:
    """The metrics of the module docstring over one or more bags' records."""
    absent = [r for r in records if r["visibility"] == ABSENT]
    full = [r for r in records if r["visibility"] == FULL]
    ok = [r["reported"] and r["tip_mm"] < GOOD_MM for r in full]
    palm = [r["reported"] and r["palm_mm"] < PALM_MM for r in full]
    posed = [r for r in records if r["posed"]]
    labels, scores = [], []
    for r in posed:
        bad = r["visibility"] == ABSENT or r["tip_mm"] > BAD_MM
        good = r["visibility"] != ABSENT and r["tip_mm"] < GOOD_MM
        if good or bad:
            labels.append(good)
            scores.append(r["confidence"])
    return {
        "frames": len(records),
        "no_hand_frames": len(absent),
        "no_hand_reported": float(np.mean([r["reported"] for r in absent])) if absent else math.nan,
        "full_frames": len(full),
        "full_ok": float(np.mean(ok)) if full else math.nan,
        "palm_ok": float(np.mean(palm)) if full else math.nan,
        "full_tip_mm_median": float(np.nanmedian([r["tip_mm"] for r in full])) if full else math.nan,
        "auc": roc_auc(scores, labels),
        "auc_frames": (int(sum(labels)), int(len(labels) - sum(labels))),
        "longest_wrong": longest_wrong(records),
    }


def longest_wrong(records: list[dict[str, Any]]) -> int:
    """The longest run of frames reporting a wrong hand: a hand reported on a frame without
    one, or with a mean tip error over 40 mm (issue 46: no wrong lock lasts over 0.5 s)."""
    run = longest = 0
    for r in records:
        wrong = r["reported"] and (r["visibility"] == ABSENT or r["tip_mm"] > BAD_MM)
        run = run + 1 if wrong else 0
        longest = max(longest, run)
    return longest


def refind_frames(records: list[dict[str, Any]]) -> list[int | None]:
    """Per return into full view after frames out of it: frames until every tip is within 20 mm
    and reported (None: never within the bag)."""
    out: list[int | None] = []
    k = 1
    while k < len(records):
        if records[k]["visibility"] == FULL and records[k - 1]["visibility"] != FULL and any(
            r["visibility"] == ABSENT for r in records[:k]
        ):
            lag = None
            for j in range(k, len(records)):
                r = records[j]
                if r["reported"] and r["tip_max_mm"] < GOOD_MM:
                    lag = j - k
                    break
            out.append(lag)
        k += 1
    return out


def write_overlays(bag: str | Path, records: list[dict[str, Any]], out_dir: str | Path, n: int = 2) -> list[Path]:
    """Overlay PNGs (:func:`~hand_sog_tracker.core.overlay.draw_overlay`) of the ``n`` worst
    frames of a core-mode run of ``bag``: the most confident frames without a hand, or the
    frames with a hand reported farthest off or not reported at all (largest tip error)."""
    import cv2

    from hand_sog_tracker.core.hand_model import HandShape, default_hand_model
    from hand_sog_tracker.core.overlay import draw_overlay

    def badness(r: dict[str, Any]) -> float:
        if r["visibility"] == ABSENT:
            return r["confidence"] if r["reported"] else -1.0
        if r["visibility"] != FULL:
            return -1.0
        return (0.0 if r["reported"] else 1000.0) + (r["tip_mm"] if r["tip_mm"] == r["tip_mm"] else 500.0)

    worst = sorted((r for r in records if badness(r) >= 0), key=badness, reverse=True)[:n]
    want = {r["index"]: r for r in worst}
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    with DepthBagReader(bag, require_truth=False) as reader:
        for f in reader.frames():
            r = want.get(f.index)
            if r is None:
                continue
            model = default_hand_model().scaled(HandShape(length=r.get("model_length", 1.0)))
            pose = None if r.get("pose") is None else np.asarray(r["pose"])
            label = (
                f"{Path(bag).name} #{f.index} {r['visibility']} conf {r['confidence']:.2f} "
                f"{'hand' if r['reported'] else 'no hand'} tip {r['tip_mm']:.0f} mm"
            )
            img = draw_overlay(f.depth_mm, f.intrinsics, model, pose, 150.0, 900.0, label)
            path = out / f"{Path(bag).name}_{f.index:03d}.png"
            cv2.imwrite(str(path), img)
            written.append(path)
    return written


def evaluate_scene_node(
    bag: str | Path, domain_id: int, rate_hz: float = 30.0, params: dict[str, Any] | None = None
) -> list[dict[str, Any]]:
    """Per-frame records of ``bag`` replayed to ``tracker_node`` (node ``params``) at ``rate_hz``
    (the bags: 30 Hz)."""
    from hand_sog_tracker.tools.scene_node import replay_scene

    return replay_scene(bag, domain_id, rate_hz, params=params)


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point; returns the exit status (0 ok, 2 error)."""
    p = argparse.ArgumentParser(prog="scene_eval", description="Score the hand decision on scene bags (issue 46).")
    p.add_argument("paths", nargs="+", help="scene bags or directories of them")
    p.add_argument("--through-node", action="store_true",
                   help="replay each bag to tracker_node (loopback DDS) and score what it publishes")
    p.add_argument("--domain-id", type=int, default=91, help="--through-node: ROS domain id (default 91)")
    p.add_argument("--rate-hz", type=float, default=30.0, help="--through-node: publishing rate (default 30)")
    p.add_argument("--no-gate", action="store_true", help="core mode without the hand gate (evidence only)")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="one tracker parameter (repeatable), e.g. --set max_hands=2")
    p.add_argument("--json", default=None, help="write the per-frame records and summaries here")
    p.add_argument("--overlays", default=None, metavar="DIR", help="core mode: overlays of the 2 worst frames per bag")
    p.add_argument("--allow-test-inspection", action="store_true",
                   help="allow --overlays and per-frame --json records of test-split bags (a final report)")
    args = p.parse_args(argv)
    bags: list[Path] = []
    for a in args.paths:
        pa = Path(a)
        bags += [pa] if (pa / "metadata.yaml").is_file() else sorted(q.parent for q in pa.glob("*/scene_truth.json"))
    if not args.through_node:
        limit_blas_threads(1)  # (the node's one BLAS thread: core mode gives the node's answers to the bit)
    results: dict[str, Any] = {}
    try:
        values = parse_set(args.set)
        config = tracker_config(values)
        hands = int(values.get("max_hands", 1))
        if hands > 1 and (args.no_gate or args.overlays) and not args.through_node:
            print("error: --no-gate and --overlays need max_hands 1", file=sys.stderr)
            return 2
        held_out = [b.name for b in bags if read_sidecar(b).get("split") == TEST_SPLIT]
        if held_out and args.overlays and not args.allow_test_inspection:
            print(f"error: --overlays of {', '.join(held_out)}: {PROTOCOL}", file=sys.stderr)
            return 2
        for bag in bags:
            kind = read_sidecar(bag).get("scene", bag.name)
            if args.through_node:
                recs = evaluate_scene_node(bag, args.domain_id, args.rate_hz, values or None)
            elif hands > 1:
                recs = evaluate_scene_hands(bag, config, hands)
            else:
                recs = evaluate_scene_core(bag, gate=not args.no_gate, config=config)
            s = summarise(recs)
            s["refind"] = refind_frames(recs)
            if args.overlays and not args.through_node:
                write_overlays(bag, recs, args.overlays)
            results[bag.name] = {"scene": kind, "split": read_sidecar(bag).get("split"), "summary": s, "records": recs}
            print(f"{bag.name:16s} " + " ".join(f"{k}={_fmt(v)}" for k, v in s.items()), flush=True)
    except HandSogError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in results.values():
        groups.setdefault(scene_group(r["scene"]), []).extend(r["records"])
    groups["all"] = [x for r in results.values() for x in r["records"]]
    for g, recs in groups.items():
        s = summarise(recs)
        print(f"[{g}] " + " ".join(f"{k}={_fmt(v)}" for k, v in s.items()))
    if args.json:
        if not args.allow_test_inspection:  # (a test bag's summary only: PROTOCOL)
            results = {k: r if r["split"] != TEST_SPLIT else {**r, "records": []} for k, r in results.items()}
        Path(args.json).write_text(json.dumps(results, default=float) + "\n", encoding="utf-8")
    return 0


def _fmt(v: Any) -> str:
    return f"{v:.3f}" if isinstance(v, float) else str(v)


if __name__ == "__main__":
    sys.exit(main())
