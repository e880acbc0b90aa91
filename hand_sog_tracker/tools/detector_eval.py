"""Precision and recall of the fingertip detector on bags with ground-truth fingertips.

Usage::

    python -m hand_sog_tracker.tools.detector_eval bags/mesh_dev [BAG_OR_FOLDER ...] [--match-mm 15]

The detector (:func:`hand_sog_tracker.core.salient.detect_fingertips`) runs on every frame
in the region the tracker would search (``roi_radius_mm`` around the true fingertips'
centre).  A detection is a true positive when it lies within ``--match-mm`` (3D) of a true
fingertip not matched yet (greedy, nearest pairs first); recall counts every true fingertip,
including those hidden in a fist (no detector can see them).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

import numpy as np

from hand_sog_tracker.core.depth_sog import preprocess
from hand_sog_tracker.core.salient import detect_fingertips
from hand_sog_tracker.core.types import TrackerConfig
from hand_sog_tracker.errors import HandSogError
from hand_sog_tracker.tools.bagio import DepthBagReader
from hand_sog_tracker.tools.bagset import discover_bags

__all__ = ["match_counts", "main"]


def match_counts(truth_mm: np.ndarray, found_mm: np.ndarray, match_mm: float) -> int:
    """True positives: greedy one-to-one matches closer than ``match_mm``.

    Parameters
    ----------
    truth_mm : array, shape (T, 3)
    found_mm : array, shape (S, 3)
    """
    if found_mm.shape[0] == 0:
        return 0
    d = np.linalg.norm(truth_mm[:, None, :] - found_mm[None, :, :], axis=-1)
    tp = 0
    while d.size and d.min() < match_mm:
        t, s = np.unravel_index(int(np.argmin(d)), d.shape)
        d[t, :] = np.inf
        d[:, s] = np.inf
        tp += 1
    return tp


def _evaluate(path: str, config: TrackerConfig, match_mm: float) -> tuple[int, int, int]:
    tp = n_det = n_true = 0
    with DepthBagReader(path) as bag:
        for frame in bag.frames():
            if frame.depth_mm is None or frame.truth_mm is None:
                continue
            pre = preprocess(frame.depth_mm, frame.intrinsics, config)
            centre = frame.truth_mm.mean(axis=0)
            intr = pre.intrinsics
            uv = intr.project(centre[None, :])[0]
            r_px = config.roi_radius_mm * intr.fx / max(centre[2] - 0.5 * config.roi_radius_mm, 50.0)
            roi = (int(uv[0] - r_px), int(uv[1] - r_px), int(uv[0] + r_px) + 1, int(uv[1] + r_px) + 1)
            window = (centre[2] - config.roi_radius_mm, centre[2] + config.roi_radius_mm)
            det = detect_fingertips(pre, roi, window)
            tp += match_counts(frame.truth_mm, det.points, match_mm)
            n_det += det.n
            n_true += frame.truth_mm.shape[0]
    return tp, n_det, n_true


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``detector_eval`` (also read by the documentation)."""
    parser = argparse.ArgumentParser(prog="detector_eval", description=__doc__.split("\n\n")[0])
    parser.add_argument("bags", nargs="+", metavar="BAG_OR_FOLDER")
    parser.add_argument("--match-mm", type=float, default=15.0, help="3D match distance (default 15)")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Print precision and recall per bag and in total; exit 2 on a bag error."""
    parser = build_parser()
    args = parser.parse_args(argv)
    config = TrackerConfig()
    totals = np.zeros(3, dtype=np.int64)
    print(f"{'bag':28s} {'detections':>10s} {'precision':>10s} {'recall':>8s}")
    try:
        entries = discover_bags(args.bags)
        for entry in entries:
            tp, n_det, n_true = _evaluate(str(entry.path), config, args.match_mm)
            totals += (tp, n_det, n_true)
            print(f"{entry.name:28s} {n_det:10d} {tp / max(n_det, 1):10.1%} {tp / max(n_true, 1):8.1%}")
    except HandSogError as err:
        print(f"detector_eval: {err}", file=sys.stderr)
        return 2
    tp, n_det, n_true = totals
    print(f"{'total':28s} {n_det:10d} {tp / max(n_det, 1):10.1%} {tp / max(n_true, 1):8.1%}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
