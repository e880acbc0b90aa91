"""``benchmark``: per-stage speed of the core tracker on one core.

Renders a deterministic synthetic sequence (not timed), then tracks it and
prints, per input resolution, the median and p95 milliseconds of each stage,
the frame rate and the peak memory.  BLAS/OpenMP/OpenCV are limited to one
thread before NumPy is imported, so the numbers are single-core numbers.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from typing import Sequence  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from hand_sog_tracker.core.depth_sog import preprocess, quadtree_sog  # noqa: E402
from hand_sog_tracker.core.energy import Objective  # noqa: E402
from hand_sog_tracker.core.kinematics import gaussian_centres  # noqa: E402
from hand_sog_tracker.core.tracker import Tracker, hand_roi  # noqa: E402
from hand_sog_tracker.core.types import TrackerConfig, TrackerStatus  # noqa: E402
from hand_sog_tracker.synth.motions import MOTIONS  # noqa: E402
from hand_sog_tracker.synth.sequence import default_intrinsics, synthetic_sequence  # noqa: E402

__all__ = ["main", "run_benchmark"]

RESOLUTIONS = {"320x240": (320, 240), "640x480": (640, 480)}


def _rss_mb() -> float:
    """Peak resident set size of this process so far, MiB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _stats(values: Sequence[float]) -> dict[str, float]:
    a = np.asarray(values, dtype=np.float64)
    if a.size == 0:
        return {"median": float("nan"), "p95": float("nan")}
    return {"median": float(np.median(a)), "p95": float(np.percentile(a, 95))}


def run_benchmark(
    motion: str, frames: int, width: int, height: int, repeat: int, seed: int = 0
) -> dict[str, object]:
    """Track ``frames`` rendered frames ``repeat`` times; return the timing table.

    Returns
    -------
    dict
        ``stages_ms`` (preprocess, quadtree, model_update, energy_gradient,
        total: each median/p95), ``iterations``, ``fps``, ``peak_rss_mb``,
        ``rss_growth_mb`` (peak RSS after the last pass minus after the first).
    """
    intr = default_intrinsics(width, height)
    seq = list(synthetic_sequence(motion, frames, intrinsics=intr, seed=seed))
    depth_frames = [f.depth_mm for f in seq]
    config = TrackerConfig()
    tracker = Tracker(config)
    stages = ("preprocess", "quadtree", "model_update", "energy_gradient", "total")
    stage: dict[str, list[float]] = {k: [] for k in stages}
    rss_first = None
    n_tracked = 0
    wall = 0.0
    for rep in range(repeat):
        tracker.reset()
        for k, depth in enumerate(depth_frames):
            t0 = time.perf_counter()
            res = tracker.process(depth, intr)
            dt = time.perf_counter() - t0
            if k == 0:
                continue  # initialisation is not per-frame work
            wall += dt
            stage["total"].append(dt * 1e3)
            stage["preprocess"].append(res.timings_ms.get("preprocess", 0.0))
            stage["quadtree"].append(res.timings_ms.get("quadtree", 0.0))
            n_tracked += res.status is TrackerStatus.TRACKING
        if rep == 0:
            rss_first = _rss_mb()
    # Per-call costs of the two inner stages, measured on the last tracked pose.
    pose = tracker.last_pose
    if pose is not None:
        pre = preprocess(depth_frames[-1], intr, config)
        roi, window = hand_roi(tracker.model, pose, pre.intrinsics, config.roi_radius_mm)
        data = quadtree_sog(pre, config.quadtree_threshold_mm, roi, window, config.min_quad_px)
        obj = Objective(tracker.model, data, config, previous=(pose, pose))
        for _ in range(200):
            t0 = time.perf_counter()
            gaussian_centres(tracker.model, pose, jacobian=True)
            t1 = time.perf_counter()
            obj(pose)
            t2 = time.perf_counter()
            stage["model_update"].append((t1 - t0) * 1e3)
            stage["energy_gradient"].append((t2 - t1) * 1e3)
    n = max(len(stage["total"]), 1)
    return {
        "motion": motion,
        "resolution": f"{width}x{height}",
        "frames_timed": len(stage["total"]),
        "frames_tracking": n_tracked,
        "iterations": config.iterations,
        "stages_ms": {k: _stats(v) for k, v in stage.items()},
        "fps": n / wall if wall > 0 else float("nan"),
        "peak_rss_mb": _rss_mb(),
        "rss_growth_mb": _rss_mb() - (rss_first or _rss_mb()),
    }


def _print_table(r: dict[str, object]) -> None:
    st = r["stages_ms"]
    assert isinstance(st, dict)
    print(f"\n{r['motion']} at {r['resolution']}: {r['frames_timed']} frames timed, "
          f"{r['frames_tracking']} tracking, {r['iterations']} iterations/frame, 1 thread")
    print(f"  {'stage':<28}{'median ms':>10}{'p95 ms':>10}")
    labels = {
        "preprocess": "preprocessing (+decimation)",
        "quadtree": "quadtree",
        "model_update": "model update (FK + J)",
        "energy_gradient": "energy+gradient / iteration",
        "total": "total per frame",
    }
    for key, label in labels.items():
        print(f"  {label:<28}{st[key]['median']:>10.2f}{st[key]['p95']:>10.2f}")
    print(f"  fps {r['fps']:.1f}   peak RSS {r['peak_rss_mb']:.1f} MiB   "
          f"RSS growth after first pass {r['rss_growth_mb']:.2f} MiB")


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point; returns the exit status."""
    parser = argparse.ArgumentParser(
        prog="benchmark",
        description="Time the hand tracker per stage on a deterministic synthetic sequence "
        "(single-threaded: BLAS/OpenMP/OpenCV limited to 1 thread).",
    )
    parser.add_argument("--motion", default="fingerwave", choices=MOTIONS, help="synthetic motion (default fingerwave)")
    parser.add_argument("--frames", type=int, default=120, help="frames in the sequence (default 120)")
    parser.add_argument("--repeat", type=int, default=1,
                        help="passes over the sequence; e.g. --frames 200 --repeat 50 for a 10,000-frame memory check")
    parser.add_argument("--resolution", action="append", choices=sorted(RESOLUTIONS),
                        help="input resolution(s) (default both)")
    parser.add_argument("--json", metavar="OUT", help="also write the results as JSON")
    args = parser.parse_args(argv)
    if args.frames < 2 or args.repeat < 1:
        parser.error("--frames must be >= 2 and --repeat >= 1")
    cv2.setNumThreads(1)
    results = []
    for name in args.resolution or list(RESOLUTIONS):
        w, h = RESOLUTIONS[name]
        r = run_benchmark(args.motion, args.frames, w, h, args.repeat)
        _print_table(r)
        results.append(r)
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(results, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
