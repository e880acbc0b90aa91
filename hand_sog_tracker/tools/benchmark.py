"""``benchmark``: per-stage speed of the core tracker on one core.

Renders a deterministic synthetic sequence (not timed), then tracks it and
prints, per input resolution, the median, p95 and largest milliseconds of each stage,
the frame rate and the peak memory.  BLAS/OpenMP/OpenCV are limited to one
thread before NumPy is imported, so the numbers are single-core numbers.

The tracker's own timings give preprocessing, the data stage (quadtree, fingertip detector
and silhouette together) and the total; the detector, the quadtree, the silhouette and the
detection-to-fingertip assignment are then timed alone on the same frames, at the start
pose the tracker used (the silhouette is its cell mask: its distance map is made inside the
objective's evaluations, on the frames where a model Gaussian falls off the hand)
(the last two tracked poses extrapolated), and the model update and the objective alone
on the last frame, at poses around the last tracked one.  The objective is also timed on a
tenth of that frame's data Gaussians: an evaluation costs about as much there, because its
cost is the fixed cost of its NumPy calls, not their arithmetic on the data.

``--compare REF`` runs this benchmark (this file) on this tree's tracker and on the tracker of
another source tree ``REF`` (e.g. a checkout of the previous commit) as separate processes,
alternating, ``--rounds`` times each, and prints both per-stage medians and their ratio:
absolute times on a shared machine drift by tens of percent, the ratio of interleaved runs
much less.  Both sides run the same harness and the same rendered frames.

``--set NAME=VALUE`` times the tracker with other parameters (the node's names, as in
``evaluate_bag`` and ``render_sets``), e.g. fewer iterations; with ``--compare`` only this
tree's runs take them, so that ``--compare .`` measures a setting against the defaults.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Mapping, Sequence  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from hand_sog_tracker.core.depth_sog import preprocess, quadtree_sog  # noqa: E402
from hand_sog_tracker.core.kinematics import fingertips, gaussian_centres  # noqa: E402
from hand_sog_tracker.core.salient import assign_detections, detect_fingertips  # noqa: E402
from hand_sog_tracker.core.tracker import ALPHA, ASSIGN_LAMBDA_MM, Tracker, hand_roi  # noqa: E402
from hand_sog_tracker.core.types import TrackerConfig, TrackerStatus, TrackResult  # noqa: E402

try:  # (core/objective/ was core/energy.py in older trees that --compare may run this file on)
    from hand_sog_tracker.core.objective import Objective
except ImportError:  # pragma: no cover
    from hand_sog_tracker.core.energy import Objective
try:  # the silhouette term (absent from older trees)
    from hand_sog_tracker.core.silhouette import silhouette
except ImportError:  # pragma: no cover
    silhouette = None
from hand_sog_tracker.synth.motions import ALL_MOTIONS  # noqa: E402
from hand_sog_tracker.synth.sequence import default_intrinsics, synthetic_sequence  # noqa: E402

try:  # the two-hand scenes (absent from older trees that --compare may run this file on)
    from hand_sog_tracker.synth.twohands import SCENES as TWO_HAND_SCENES
except ImportError:  # pragma: no cover
    TWO_HAND_SCENES = ()

__all__ = ["main", "run_benchmark", "run_compare"]

RESOLUTIONS = {"320x240": (320, 240), "640x480": (640, 480)}


def _rss_mb() -> float:
    """Peak resident set size of this process so far, MiB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _stats(values: Sequence[float]) -> dict[str, float]:
    a = np.asarray(values, dtype=np.float64)
    if a.size == 0:
        return {"median": float("nan"), "p95": float("nan"), "max": float("nan")}
    return {"median": float(np.median(a)), "p95": float(np.percentile(a, 95)), "max": float(a.max())}


#: Seed of the mesh renders (not a seed of bags/mesh_test: benchmarking never looks at test data).
MESH_SEED = 900
#: Every this many frames of the last pass, a fresh tracker initialises on that frame.
INIT_EVERY = 10


def _frames(motion: str, frames: int, intr, renderer: str, seed: int) -> list:
    """The rendered frames (depth in mm) of ``motion``."""
    if renderer == "mesh":
        from hand_sog_tracker.synth.mesh import MeshRenderOptions, mesh_sequence

        options = MeshRenderOptions("structured")
        seq = mesh_sequence(motion, frames, intrinsics=intr, seed=MESH_SEED + seed, options=options)
    elif renderer == "twohands":  # ``motion`` is a scene of synth.twohands: both mesh hands in view
        from hand_sog_tracker.synth.twohands import TwoHandScene, two_hand_sequence

        seq = two_hand_sequence(TwoHandScene(motion), frames, intr, seed=MESH_SEED + seed, sensor="structured")
    else:
        seq = synthetic_sequence(motion, frames, intrinsics=intr, seed=seed)
    return [f.depth_mm for f in seq]


def _node_tracker(config: TrackerConfig) -> Tracker:
    """A tracker as each tree's node runs it: with the hand check (issue 46; an older tree,
    under ``--compare``, ran it beside the tracker, in its ``CheckedTracker``)."""
    tracker = Tracker(config)
    if "hand" in getattr(TrackResult, "__dataclass_fields__", {}):
        return tracker
    try:
        from hand_sog_tracker.core.handcheck import CheckedTracker  # type: ignore[attr-defined]
    except ImportError:  # (a tree before the check)
        return tracker
    return CheckedTracker(tracker)  # type: ignore[return-value]


def _init_times(config: TrackerConfig, depth_frames: list, intr) -> tuple[list[float], list[float]]:
    """Milliseconds of each frame in which initialisation runs, for fresh trackers started
    every ``INIT_EVERY`` frames, and of the restarts the new track runs after its first answer.
    (An older tree, under ``--compare``, ran the initialisation over two frames, both counted,
    with its restarts deferred, as its node did; this tree runs all of it on one frame.)"""
    out, after = [], []
    for k in range(0, len(depth_frames) - 1, INIT_EVERY):
        tracker = _node_tracker(config)
        if hasattr(tracker, "split_initialisation"):
            tracker.split_initialisation = True
        tracker.defer_restarts = True
        for depth in depth_frames[k : k + 2]:
            t0 = time.perf_counter()
            tracker.process(depth, intr)
            out.append((time.perf_counter() - t0) * 1e3)
            if not getattr(tracker, "initialising", False):
                break
        if hasattr(tracker, "finish_frame"):
            t0 = time.perf_counter()
            tracker.finish_frame()
            after.append((time.perf_counter() - t0) * 1e3)
    return out, after


#: Batch sizes of the ``Objective.batch`` rows, and the rounds timed for each (issue 45).
BATCH_SIZES = (1, 4, 8, 16, 32)
BATCH_ROUNDS = 15


def _time_batches(obj: Objective, pose: np.ndarray, stage: dict[str, list[float]]) -> None:
    """Time ``obj.batch`` (value and gradient) of B poses near ``pose`` against B one-pose
    calls on the same poses, for each of :data:`BATCH_SIZES`, alternating which goes first; new
    poses every round (no call can reuse an earlier one's kinematics).  Adds the stages
    ``energy_batch_B`` (ms per batch call) and ``energy_singles_B`` (ms of the B calls)."""
    rng = np.random.default_rng(1)
    for B in BATCH_SIZES:
        for k in range(BATCH_ROUNDS):
            thetas = pose + rng.normal(0.0, 1e-3, (B, pose.size))
            singles = thetas + 1e-7  # (other poses than the batch's, as close)
            for part in ((0, 1) if k % 2 == 0 else (1, 0)):
                t0 = time.perf_counter()
                if part == 0:
                    obj.batch(thetas)
                else:
                    for theta in singles:
                        obj(theta)
                key = "energy_batch_" if part == 0 else "energy_singles_"
                stage.setdefault(f"{key}{B}", []).append((time.perf_counter() - t0) * 1e3)


def run_benchmark(
    motion: str,
    frames: int,
    width: int,
    height: int,
    repeat: int,
    seed: int = 0,
    renderer: str = "capsule",
    params: Mapping[str, bool | int | float | str] | None = None,
) -> dict[str, object]:
    """Track ``frames`` rendered frames ``repeat`` times; return the timing table.

    ``params``: tracker parameters by the node's names, as
    :func:`~hand_sog_tracker.tools.tracker_params.core_settings` returns them (no
    ``handedness``: the frames show a right hand); default: the defaults.

    Returns
    -------
    dict
        ``stages_ms`` (each median/p95: preprocess; quadtree = the tracker's data stage:
        quadtree, detector and silhouette together; detector, quadtree_only, silhouette and
        assignment timed alone; model_update, energy_gradient, energy_gradient_tenth (the
        objective on a tenth of the data Gaussians); answer = a frame until its
        result, its restarts deferred as in the node, and total = with them; initialise = the
        frames of fresh trackers' initialisations, initialise_after = the restarts of the new
        track after its first answer), ``iterations``,
        ``fps``, ``peak_rss_mb``,
        ``rss_growth_mb`` (peak RSS after the last pass minus after the first), ``params``.
    """
    intr = default_intrinsics(width, height)
    depth_frames = _frames(motion, frames, intr, renderer, seed)
    config = TrackerConfig()
    if params:
        # (Imported here: a tree benchmarked by --compare may not have it, and gets no --set.)
        from hand_sog_tracker.tools.tracker_params import tracker_config

        config = tracker_config(params)
    tracker = _node_tracker(config)
    # As each tree's node: an older tree (--compare) answered a frame before its restarts, which
    # ran after it ("answer" times the first part, "total" both); this tree has no deferral
    # (the attributes set here are unused) and answers with its whole search.
    tracker.defer_restarts = True
    finish_frame = getattr(tracker, "finish_frame", lambda: False)
    stages = (
        "preprocess", "quadtree", "detector", "quadtree_only", "silhouette", "assignment",
        "model_update", "energy_gradient", "energy_gradient_tenth", "answer", "total", "initialise",
        "initialise_after",
    )
    stage: dict[str, list[float]] = {k: [] for k in stages}
    rss_first = None
    n_tracked = 0
    wall = 0.0
    poses: list = []
    for rep in range(repeat):
        tracker.reset()
        poses = []
        for k, depth in enumerate(depth_frames):
            t0 = time.perf_counter()
            res = tracker.process(depth, intr)
            t_answer = time.perf_counter() - t0
            finish_frame()
            dt = time.perf_counter() - t0
            poses.append(tracker.last_pose)
            if k == 0:
                continue  # initialisation is not per-frame work
            wall += dt
            stage["answer"].append(t_answer * 1e3)
            stage["total"].append(dt * 1e3)
            stage["preprocess"].append(res.timings_ms.get("preprocess", 0.0))
            stage["quadtree"].append(res.timings_ms.get("quadtree", 0.0))
            n_tracked += res.status is TrackerStatus.TRACKING
        if rep == 0:
            rss_first = _rss_mb()
    rss_last = _rss_mb()  # (before the stage timings and the fresh trackers below)
    # The data stage's parts alone, on the frames of the last pass, at the start pose the
    # tracker used there (the two previous poses extrapolated, as in Tracker._track).
    for k in range(2, len(depth_frames)):
        p1, p2 = poses[k - 1], poses[k - 2]
        if p1 is None or p2 is None:
            continue
        x0 = p1 + ALPHA * (p1 - p2)
        pre = preprocess(depth_frames[k], intr, config)
        t0 = time.perf_counter()
        roi, window = hand_roi(tracker.model, x0, pre.intrinsics, config.roi_radius_mm)
        det = detect_fingertips(pre, roi, window)
        t1 = time.perf_counter()
        quadtree_sog(pre, config.quadtree_threshold_mm, roi, window, config.min_quad_px)
        t2 = time.perf_counter()
        assign_detections(fingertips(tracker.model, x0), det, ASSIGN_LAMBDA_MM)
        t3 = time.perf_counter()
        stage["detector"].append((t1 - t0) * 1e3)
        stage["quadtree_only"].append((t2 - t1) * 1e3)
        stage["assignment"].append((t3 - t2) * 1e3)
        if silhouette is not None and getattr(config, "w_sil", 0.0) > 0:
            t4 = time.perf_counter()
            silhouette(pre, window)
            stage["silhouette"].append((time.perf_counter() - t4) * 1e3)
    # Per-call costs of the two inner stages, on the last frame around the last tracked pose:
    # at poses about 1e-3 mm / rad apart (distinct, as the optimiser's iterates: no call
    # can reuse the kinematics of an earlier one, which the tracker keeps for repeated poses).
    pose = tracker.last_pose
    if pose is not None:
        pre = preprocess(depth_frames[-1], intr, config)
        roi, window = hand_roi(tracker.model, pose, pre.intrinsics, config.roi_radius_mm)
        data = quadtree_sog(pre, config.quadtree_threshold_mm, roi, window, config.min_quad_px)
        obj = Objective(tracker.model, data, config, previous=(pose, pose))
        # The same objective on a tenth of the frame's data Gaussians: what an evaluation costs
        # whatever the data (the per-call cost of its NumPy operations, not their arithmetic).
        tenth = Objective(
            tracker.model, data.subset(np.arange(data.n) < max(data.n // 10, 1)), config, previous=(pose, pose)
        )
        nearby = pose + np.random.default_rng(0).normal(0.0, 1e-3, (200, pose.size))
        for theta in nearby:
            t0 = time.perf_counter()
            gaussian_centres(tracker.model, theta, jacobian=True)
            t1 = time.perf_counter()
            obj(theta)
            t2 = time.perf_counter()
            tenth(theta)
            t3 = time.perf_counter()
            stage["model_update"].append((t1 - t0) * 1e3)
            stage["energy_gradient"].append((t2 - t1) * 1e3)
            stage["energy_gradient_tenth"].append((t3 - t2) * 1e3)
        if hasattr(obj, "batch"):  # (absent from older trees)
            _time_batches(obj, pose, stage)
    stage["initialise"], stage["initialise_after"] = _init_times(config, depth_frames, intr)
    n = max(len(stage["total"]), 1)
    return {
        "motion": motion,
        "renderer": renderer,
        "resolution": f"{width}x{height}",
        "frames_timed": len(stage["total"]),
        "frames_tracking": n_tracked,
        "iterations": config.iterations,
        "params": dict(params or {}),
        "stages_ms": {k: _stats(v) for k, v in stage.items()},
        "fps": n / wall if wall > 0 else float("nan"),
        "peak_rss_mb": _rss_mb(),
        "rss_growth_mb": rss_last - (rss_first or rss_last),
    }


STAGE_LABELS = {
    "preprocess": "preprocessing (+decimation)",
    "quadtree": "data: quadtree, detector, ...",
    "quadtree_only": "  quadtree alone",
    "detector": "  detector alone",
    "silhouette": "  silhouette (mask) alone",
    "assignment": "assignment (one call)",
    "model_update": "model update (FK + J)",
    "energy_gradient": "energy+gradient / iteration",
    "energy_gradient_tenth": "  on a tenth of the data",
    "answer": "answer (restarts after it)",
    "total": "total per frame",
    "initialise": "initialisation, per frame",
    "initialise_after": "  its restarts after the answer",
    **{
        key: label
        for B in BATCH_SIZES
        for key, label in ((f"energy_batch_{B}", f"Objective.batch of {B} (1 call)"),
                           (f"energy_singles_{B}", f"  {B} one-pose calls"))
    },
}


def _print_table(r: dict[str, object]) -> None:
    st = r["stages_ms"]
    assert isinstance(st, dict)
    print(f"\n{r['motion']} ({r.get('renderer', 'capsule')} hand) at {r['resolution']}: "
          f"{r['frames_timed']} frames timed, "
          f"{r['frames_tracking']} tracking, {r['iterations']} iterations/frame, 1 thread")
    if r.get("params"):
        print("  with " + ", ".join(f"{k}={v}" for k, v in r["params"].items()))  # type: ignore[union-attr]
    print(f"  {'stage':<30}{'median ms':>10}{'p95 ms':>10}{'max ms':>10}")
    for key, label in STAGE_LABELS.items():
        if key in st and not np.isnan(st[key]["median"]):
            print(f"  {label:<30}{st[key]['median']:>10.2f}{st[key]['p95']:>10.2f}{st[key]['max']:>10.2f}")
    print(f"  fps {r['fps']:.1f}   peak RSS {r['peak_rss_mb']:.1f} MiB   "
          f"RSS growth after first pass {r['rss_growth_mb']:.2f} MiB")
    batches = [B for B in BATCH_SIZES if f"energy_batch_{B}" in st]
    if batches:
        print(f"  {'Objective.batch: poses':<30}{'ms/call':>10}{'ms/pose':>10}{'B calls ms':>12}{'ratio':>8}")
        for B in batches:
            one, many = st[f"energy_batch_{B}"]["median"], st[f"energy_singles_{B}"]["median"]
            print(f"  {B:<30}{one:>10.3f}{one / B:>10.3f}{many:>12.3f}{one / many:>8.2f}")


def _tree_root() -> Path:
    """The directory that holds this ``hand_sog_tracker`` package."""
    import hand_sog_tracker

    return Path(hand_sog_tracker.__file__).resolve().parents[1]


def _run_child(root: Path, args: list[str]) -> list[dict[str, object]]:
    """Run this benchmark on the package of the source tree ``root`` in a fresh process; its
    JSON results."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "bench.json"
        env = dict(os.environ)
        env["PYTHONPATH"] = str(root) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        proc = subprocess.run(
            [sys.executable, str(Path(__file__).resolve()), *args, "--json", str(out)],
            cwd=root, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        )
        if proc.returncode != 0 or not out.exists():
            raise RuntimeError(f"benchmark of {root} failed: {proc.stderr.strip()[-2000:]}")
        with open(out, encoding="utf-8") as fh:
            return json.load(fh)


def run_compare(
    ref: Path, args: list[str], rounds: int, this: Path | None = None, this_args: Sequence[str] = ()
) -> dict[str, dict[str, dict[str, list[float]]]]:
    """Benchmark ``this`` tree (default: the running one) and ``ref``, alternating; both with
    the benchmark's arguments ``args``, ``this`` also with ``this_args`` (e.g. ``--set``).

    Returns ``{resolution: {"this"|"ref": {stage: [median ms of each round]}}}``.
    """
    this = this or _tree_root()
    runs: dict[str, dict[str, dict[str, list[float]]]] = {}
    for k in range(rounds):
        order = (("this", this), ("ref", ref)) if k % 2 == 0 else (("ref", ref), ("this", this))
        for name, root in order:
            print(f"round {k + 1}/{rounds}: {name} ({root})", file=sys.stderr, flush=True)
            for r in _run_child(root, args + list(this_args) if name == "this" else args):
                per = runs.setdefault(str(r["resolution"]), {"this": {}, "ref": {}})[name]
                stages = r["stages_ms"]
                assert isinstance(stages, dict)
                for stage, st in stages.items():
                    per.setdefault(stage, []).append(float(st["median"]))
    return runs


def _print_compare(
    runs: dict[str, dict[str, dict[str, list[float]]]], ref: Path, rounds: int, sets: Sequence[str] = ()
) -> None:
    print(f"\nthis tree {_tree_root()} against {ref}: median over {rounds} interleaved runs "
          "of each run's median ms")
    if sets:
        print(f"this tree with {', '.join(sets)}; {ref} with its defaults")
    for res, both in runs.items():
        print(f"\n{res}")
        print(f"  {'stage':<30}{'this ms':>10}{'ref ms':>10}{'this/ref':>10}")
        keys = [k for k in STAGE_LABELS if k in both["this"] or k in both["ref"]]
        keys += [k for k in both["this"] if k not in keys]
        for key in keys:
            a = float(np.median(both["this"][key])) if key in both["this"] else float("nan")
            b = float(np.median(both["ref"][key])) if key in both["ref"] else float("nan")
            ratio = f"{a / b:.3f}" if b >= 0.01 else "-"  # (a stage the other tree does not run)
            label = STAGE_LABELS.get(key, key)
            print(f"  {label:<30}{a:>10.2f}{b:>10.2f}{ratio:>10}")


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point; returns the exit status."""
    parser = argparse.ArgumentParser(
        prog="benchmark",
        description="Time the hand tracker per stage on a deterministic synthetic sequence "
        "(single-threaded: BLAS/OpenMP/OpenCV limited to 1 thread).",
    )
    parser.add_argument("--motion", default="fingerwave", choices=ALL_MOTIONS,
                        help="synthetic motion (default fingerwave; fistopen is a hard case)")
    parser.add_argument("--renderer", default="capsule", choices=("capsule", "mesh", "twohands"),
                        help="capsule: the tracker's own model shapes (default); mesh: the skinned "
                        "mesh hand of the evaluation bags, e.g. --renderer mesh --motion fistopen "
                        "for the hard case; twohands: two mesh hands, see --scene")
    parser.add_argument("--scene", default=None, choices=TWO_HAND_SCENES,
                        help="with --renderer twohands: the two-hand scene (default apart: both hands in "
                        "view, each with its own motion)")
    parser.add_argument("--hands", action="store_true",
                        help="with --renderer twohands: time the two-hand tracker (max_hands 2) on the scene "
                        "against the one-hand tracker on its right hand alone, interleaved, and print the ratio")
    parser.add_argument("--frames", type=int, default=120, help="frames in the sequence (default 120)")
    parser.add_argument("--repeat", type=int, default=1,
                        help="passes over the sequence; e.g. --frames 200 --repeat 50 for a 10,000-frame memory check")
    parser.add_argument("--resolution", action="append", choices=sorted(RESOLUTIONS),
                        help="input resolution(s) (default both)")
    parser.add_argument("--json", metavar="OUT", help="also write the results as JSON")
    parser.add_argument("--compare", metavar="REF_DIR",
                        help="also benchmark the source tree REF_DIR (the directory holding its "
                        "hand_sog_tracker package), in separate processes alternating with this "
                        "tree, and print both and the ratio")
    parser.add_argument("--rounds", type=int, default=3,
                        help="with --compare: runs of each tree (default 3)")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="one tracker parameter, by the node's name (repeatable), e.g. --set iterations=6; "
                        "with --compare for this tree only (the reference runs its defaults)")
    args = parser.parse_args(argv)
    if args.frames < 2 or args.repeat < 1:
        parser.error("--frames must be >= 2 and --repeat >= 1")
    if args.scene is not None and args.renderer != "twohands":
        parser.error("--scene needs --renderer twohands")
    motion = (args.scene or "apart") if args.renderer == "twohands" else args.motion
    params = {}
    if args.set:
        from hand_sog_tracker.errors import InputError
        from hand_sog_tracker.tools.tracker_params import core_settings

        try:
            params = core_settings(args.set, "the benchmark renders a right hand")
        except InputError as exc:
            parser.error(f"--set: {exc}")
    if args.compare is not None:
        ref = Path(args.compare).resolve()
        if not (ref / "hand_sog_tracker" / "__init__.py").is_file():
            parser.error(f"--compare: {ref} holds no hand_sog_tracker package")
        if args.rounds < 1:
            parser.error("--rounds must be >= 1")
        child = ["--motion", args.motion, "--frames", str(args.frames), "--repeat", str(args.repeat)]
        if args.renderer != "capsule":
            child += ["--renderer", args.renderer]
        if args.scene is not None:
            child += ["--scene", args.scene]
        for name in args.resolution or []:
            child += ["--resolution", name]
        try:
            runs = run_compare(ref, child, args.rounds, this_args=[f"--set={item}" for item in args.set])
        except RuntimeError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        _print_compare(runs, ref, args.rounds, args.set)
        if args.json:
            with open(args.json, "w", encoding="utf-8") as fh:
                json.dump({"this": str(_tree_root()), "ref": str(ref), "runs": runs}, fh, indent=2)
        return 0
    cv2.setNumThreads(1)
    if args.hands:
        if args.renderer != "twohands":
            parser.error("--hands needs --renderer twohands")
        from hand_sog_tracker.tools.hands_benchmark import format_hands_ratio, run_hands_ratio

        config = None
        if params:
            from hand_sog_tracker.tools.tracker_params import tracker_config

            config = tracker_config(params)
        out = []
        for name in args.resolution or ["320x240"]:
            w, h = RESOLUTIONS[name]
            out.append(run_hands_ratio(motion, args.frames, w, h, MESH_SEED, config))
            print(format_hands_ratio(out[-1]))
        if args.json:
            with open(args.json, "w", encoding="utf-8") as fh:
                json.dump(out, fh, indent=2)
        return 0
    results = []
    for name in args.resolution or list(RESOLUTIONS):
        w, h = RESOLUTIONS[name]
        r = run_benchmark(motion, args.frames, w, h, args.repeat, renderer=args.renderer, params=params)
        _print_table(r)
        results.append(r)
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(results, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
