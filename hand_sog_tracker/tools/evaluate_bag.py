"""``evaluate_bag``: score the hand tracker on bags with fingertip ground truth.

Usage::

    evaluate_bag BAG_OR_FOLDER [BAG_OR_FOLDER ...] [--json OUT] [--plot OUT.png]
                 [--overlay DIR [--overlay-worst N]] [--allow-test-inspection]
                 [--params YAML] [--set NAME=VALUE ...] [--handedness right|left]
                 [--calibrate] [--max-frames N] [--details] [--markdown] [--quiet]
                 [--depth-topic T] [--info-topic T] [--gt-topic T]
                 [--through-node [--domain-id N] [--rate R] [--node-timeout S] [--no-warmup]]

A two-hand bag (sidecar ``hands: 2``, or per-hand ground-truth topics) is scored per hand, matched by
handedness, with identity swaps and handedness accuracy (:mod:`~hand_sog_tracker.tools.twohand_eval`,
core mode or ``--through-node``).  A path that is a bag is one bag; a folder of bags stands for every bag directly
inside it (:mod:`hand_sog_tracker.tools.bagset`).  Bags follow contract 5 (see
:mod:`hand_sog_tracker.tools.bagio`).  One bag: its detailed table; several:
one row per bag in the form of the paper's Table 1 plus a total per split and
an overall total (frame-weighted).

This module is the command line only; the work is done by
:mod:`~hand_sog_tracker.tools.evaluation` (core mode),
:mod:`~hand_sog_tracker.tools.node_eval` (``--through-node``, on
:mod:`~hand_sog_tracker.tools.node_harness`),
:mod:`~hand_sog_tracker.tools.report` (tables, JSON) and
:mod:`~hand_sog_tracker.tools.figures` (plot, overlays).  The names other code
imported from here are re-exported.

Exit status: 0 on success, 2 on a usage error or any
:class:`~hand_sog_tracker.errors.HandSogError` (``error: ...`` on stderr; with
several bags the others are still evaluated), 130 when interrupted.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any, Sequence

from hand_sog_tracker.errors import HandSogError
from hand_sog_tracker.ros.blas import limit_blas_threads
from hand_sog_tracker.tools.bagio import BagTopics, open_bag, topic_table
from hand_sog_tracker.tools.bagset import PROTOCOL, BagEntry, discover_bags
from hand_sog_tracker.tools.evaluation import evaluate_core
from hand_sog_tracker.tools.figures import write_overlays, write_plot
from hand_sog_tracker.tools.node_eval import evaluate_through_node
from hand_sog_tracker.tools.node_process import loopback_dds
from hand_sog_tracker.tools.records import Evaluation, FrameRecord, Progress, TrackerLike, build_evaluation
from hand_sog_tracker.tools.report import format_table, format_table1, write_json
from hand_sog_tracker.tools.tracker_params import node_only, parse_set, read_params_file, tracker_config
from hand_sog_tracker.tools.twohand_bags import is_two_hand_bag
from hand_sog_tracker.tools.twohand_eval import (
    TwoHandSummary,
    evaluate_two_hands_core,
    evaluate_two_hands_node,
    format_two_hand_table,
    multi_hand_predictor,
    summary_as_dict,
)

__all__ = [
    "FrameRecord",
    "Evaluation",
    "TrackerLike",
    "Progress",
    "evaluate_core",
    "evaluate_through_node",
    "loopback_dds",
    "build_evaluation",
    "format_table",
    "format_table1",
    "write_plot",
    "build_parser",
    "main",
]


def build_parser() -> argparse.ArgumentParser:
    """The command-line parser of ``evaluate_bag``."""
    p = argparse.ArgumentParser(
        prog="evaluate_bag",
        description="Score the hand tracker on bags with ground-truth fingertips: mean fingertip "
        "error overall and per finger, % of frames below 15/20/25/30 mm, ms per frame. Several bags "
        "or folders of bags give one Table-1 row per bag, a total per split and an overall total.",
        epilog=f"Dev/test protocol: {PROTOCOL}.",
    )
    p.add_argument("bags", nargs="+", metavar="BAG_OR_FOLDER",
                   help="rosbag2 directory (sqlite3 or mcap), ROS 1 .bag file, or a folder of bags")
    g = p.add_argument_group("topics")
    g.add_argument("--depth-topic", default=BagTopics.depth, help="sensor_msgs/Image depth topic (default %(default)s)")
    g.add_argument("--info-topic", default=BagTopics.info, help="sensor_msgs/CameraInfo topic (default %(default)s)")
    g.add_argument(
        "--gt-topic", default=BagTopics.truth, help="geometry_msgs/PoseArray ground truth (default %(default)s)"
    )
    g = p.add_argument_group("tracker settings")
    g.add_argument("--params", metavar="YAML",
                   help="the node's params file (like config/hand_sog_tracker.yaml); node-only ones are "
                   "ignored in core mode")
    g.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="one tracker parameter (repeatable; wins over --params), e.g. --set iterations=20")
    g.add_argument("--handedness", choices=("right", "left"),
                   help="hand to track (default: the bag sidecar's handedness, else right)")
    g.add_argument(
        "--calibrate",
        action="store_true",
        help="fit the hand model on the first 3 frames, check it on the next 3 (a refused fit keeps the default), "
        "then track (without it, the model is fitted automatically as the node's auto_calibrate does; "
        "--set auto_calibrate=false turns that off)",
    )
    g.add_argument("--max-frames", type=int, metavar="N", help="evaluate only the first N depth images of each bag")
    g = p.add_argument_group("output")
    g.add_argument("--json", metavar="OUT", help="write all results (per bag, totals, per-frame records) as JSON")
    g.add_argument("--plot", metavar="OUT.png",
                   help="write a PNG: error over time and %%-of-frames-below curves (needs matplotlib: "
                   "pip install 'hand_sog_tracker[plot]')")
    g.add_argument("--overlay", metavar="DIR",
                   help="write PNGs of each bag's worst frames to DIR as <bag>_<frame>_<err>mm.png (core mode)")
    g.add_argument("--overlay-worst", type=int, default=5, metavar="N",
                   help="frames per bag for --overlay (default %(default)s)")
    g.add_argument("--allow-test-inspection", action="store_true",
                   help="allow per-frame looking aids (overlays, per-frame JSON records, error-over-time "
                   "plot) on test-split bags, e.g. for a final report")
    g.add_argument("--details", action="store_true", help="print each bag's detailed table (default: one bag only)")
    g.add_argument("--markdown", action="store_true", help="print the per-bag table as Markdown")
    g.add_argument("--quiet", action="store_true", help="do not print the tables")
    g = p.add_argument_group("through the ROS node")
    g.add_argument("--through-node", action="store_true",
                   help="run tracker_node and publish each bag to it over loopback DDS at its recorded rate")
    g.add_argument("--domain-id", type=int, default=91, help="ROS_DOMAIN_ID for --through-node (default %(default)s)")
    g.add_argument("--rate", type=float, default=1.0, help="replay rate factor for --through-node (default 1)")
    g.add_argument("--node-timeout", type=float, default=30.0, metavar="S",
                   help="--through-node: seconds to wait for the node to connect (default %(default)s)")
    g.add_argument("--no-warmup", action="store_true",
                   help="--through-node: do not let the node detect the hand on the first image before the "
                   "timed replay (then its first, slow detection is part of the measurement)")
    return p


def _note(text: str) -> None:
    print(f"note: {text}", file=sys.stderr)


def _settings(args: argparse.Namespace) -> dict[str, Any]:
    """Explicit tracker parameters: --params, then --set, then --handedness (validated)."""
    values: dict[str, Any] = {}
    if args.params:
        values.update(read_params_file(args.params))
    values.update(parse_set(args.set))
    if args.handedness:
        values["handedness"] = args.handedness
    tracker_config(values)  # fail early, naming the bad parameter
    return values


def _bag_values(entry: BagEntry, values: dict[str, Any]) -> dict[str, Any]:
    """The parameters for one bag: a sidecar's left hand applies unless handedness was set."""
    side = entry.handedness
    if "handedness" not in values:
        if side == "left":
            _note(f"{entry.name}: its sidecar says a left hand; tracking it with a left-hand tracker "
                  "(override with --handedness)")
            return {**values, "handedness": "left"}
    elif side is not None and side != values["handedness"]:
        _note(f"{entry.name}: its sidecar says a {side} hand but handedness is set to {values['handedness']}")
    return values


def _is_two_hand(entry: BagEntry) -> bool:
    """A sidecar with ``hands: 2``, or (a bag without a sidecar) per-hand ground-truth topics."""
    if "hands" in entry.sample:
        return entry.sample.get("hands") == 2
    try:
        with open_bag(entry.path) as reader:
            return is_two_hand_bag(set(topic_table(reader)))
    except HandSogError:  # an unreadable bag: the one-hand path reports why
        return False


def _evaluate_two_hands(entry: BagEntry, args: argparse.Namespace, values: dict[str, Any]) -> TwoHandSummary:
    """A two-hand bag (sidecar ``hands: 2``): each hand scored, matched by handedness."""
    if args.through_node:
        return evaluate_two_hands_node(
            entry.path, args.domain_id, params=values, max_frames=args.max_frames, split=entry.split,
            rate=args.rate, connect_timeout_s=args.node_timeout, warmup=not args.no_warmup,
        )
    config = tracker_config(values)
    hands = int(values.get("max_hands", 1))
    return evaluate_two_hands_core(
        entry.path, predictor=multi_hand_predictor(config, hands) if hands > 1 else None, config=config,
        max_frames=args.max_frames, split=entry.split,
    )


def _evaluate(entry: BagEntry, args: argparse.Namespace, topics: BagTopics, values: dict[str, Any]) -> Evaluation:
    if args.through_node:
        return evaluate_through_node(
            entry.path, topics, domain_id=args.domain_id, rate=args.rate, max_frames=args.max_frames,
            connect_timeout_s=args.node_timeout, warmup=not args.no_warmup, params=values, split=entry.split,
        )
    return evaluate_core(
        entry.path, topics, calibrate=args.calibrate, config=tracker_config(values), max_frames=args.max_frames,
        keep_worst=args.overlay_worst if args.overlay else 0, split=entry.split,
        auto_calibrate=bool(values.get("auto_calibrate", True)),
    )


def _write_two_hand_json(path: str, summaries: list[TwoHandSummary], inspect_test: bool, replace: bool) -> None:
    """Put the two-hand results under ``two_hands`` of the JSON file (a new file with ``replace``);
    test bags without their swap frames unless ``inspect_test``."""
    data: dict[str, Any] = {} if replace else json.loads(Path(path).read_text(encoding="utf-8"))
    data["two_hands"] = [summary_as_dict(s, per_frame=s.split != "test" or inspect_test) for s in summaries]
    Path(path).write_text(json.dumps(data, indent=2, allow_nan=False) + "\n", encoding="utf-8")


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point; returns the exit status (0 ok, 2 error, 130 interrupted)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.max_frames is not None and args.max_frames < 1:
        parser.error("--max-frames must be >= 1")
    if args.overlay_worst < 1:
        parser.error("--overlay-worst must be >= 1")
    if not (args.rate > 0 and math.isfinite(args.rate)):
        parser.error("--rate must be a positive number")
    if args.calibrate and args.through_node:
        parser.error("--calibrate cannot be combined with --through-node (call the node's ~/calibrate service instead)")
    if not 0 <= args.domain_id <= 232:
        parser.error("--domain-id must be in [0, 232]")
    if not args.through_node:
        limit_blas_threads(1)  # (the node's one BLAS thread: core mode gives the node's answers to the bit)
    topics = BagTopics(depth=args.depth_topic, info=args.info_topic, truth=args.gt_topic)
    try:
        entries = discover_bags(args.bags)
        values = _settings(args)
        test_bags = [e.name for e in entries if e.is_test]
        inspect_test = args.allow_test_inspection
        if args.overlay and test_bags and not inspect_test:
            raise HandSogError(f"--overlay refused for the test-split bag(s) {', '.join(test_bags)}: {PROTOCOL}")
        if args.overlay and args.through_node:
            _note("--overlay needs core mode; no overlays with --through-node")
        ignored = [n for n in node_only(values) if n not in ("auto_calibrate", "max_hands")]
        if not args.through_node and ignored:
            _note(f"core mode ignores the node-only parameter(s) {', '.join(ignored)}")
    except HandSogError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    evaluations: list[Evaluation] = []
    two_hands: list[TwoHandSummary] = []
    failed = 0
    try:
        for i, entry in enumerate(entries):
            if len(entries) > 1:
                print(f"[{i + 1}/{len(entries)}] {entry.name} (split {entry.split})", file=sys.stderr)
            if _is_two_hand(entry):
                try:
                    two_hands.append(_evaluate_two_hands(entry, args, values))
                except HandSogError as err:
                    print(f"error: {err}", file=sys.stderr)
                    failed += 1
                continue
            try:
                ev = _evaluate(entry, args, topics, _bag_values(entry, values))
                if args.overlay and not args.through_node:
                    cfg = tracker_config(values)
                    same = sum(e.name == entry.name for e in entries) > 1  # same name in two folders
                    name = f"{entry.path.parent.name}_{entry.name}" if same else entry.name
                    write_overlays(ev, args.overlay, cfg.near_mm, cfg.far_mm, name=name)
            except HandSogError as err:
                print(f"error: {err}", file=sys.stderr)
                failed += 1
                continue
            evaluations.append(ev)
            if not args.quiet and (args.details or len(entries) == 1):
                print(format_table(ev))
                if len(entries) > 1:
                    print()
        if two_hands and not args.quiet:
            print(format_two_hand_table(two_hands))
        if not evaluations:
            if two_hands and args.json:
                _write_two_hand_json(args.json, two_hands, inspect_test, replace=True)
            return 2 if failed or not two_hands else 0
        if not args.quiet and len(entries) > 1:
            print(format_table1(evaluations, markdown=args.markdown))
        elif not args.quiet and args.markdown:
            print("\n" + format_table1(evaluations, markdown=True))
        shown = [ev.split != "test" or inspect_test for ev in evaluations]
        if args.json:
            if not all(shown):
                _note("per-frame records of test-split bags are left out of the JSON (" + PROTOCOL + ")")
            write_json(evaluations, args.json, per_frame=shown, withheld_note=PROTOCOL)
            if two_hands:
                _write_two_hand_json(args.json, two_hands, inspect_test, replace=False)
        if args.plot:
            if not all(shown):
                _note("the error-over-time plot leaves out test-split bags (--allow-test-inspection shows them)")
            write_plot(evaluations, args.plot, time_series=shown)
    except HandSogError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    return 2 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
