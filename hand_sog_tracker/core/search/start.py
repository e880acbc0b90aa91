"""A new track's search: from the hand found in the depth to the finalist poses.

Start poses (:mod:`..initialise`: the blob's directions, its edge-on hands, open hands along the hand
end's axis and toward the detections) are screened by the objective, aligned rigidly on coarse data
(seed 004's coarse-to-fine), the best per palm side articulated on fine data, the best by the score
kept (single fingers curled, :func:`best_combination`, when even the best scores poorly).  No
silhouette yet: it pulls poses into the outline before the depth has placed them.  Each pose drops
the data beyond its wrist; a stage's poses are fitted as one batch (:func:`~.fit.fit_parts`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.depth_sog import MAX_DATA_GAUSSIANS, ImageSoG, Preprocessed, leaf_px, quadtree_sog
from hand_sog_tracker.core.hand_model import HandModel
from hand_sog_tracker.core.handfind import HandBlob, detection_direction, find_hand
from hand_sog_tracker.core.initialise import INIT_SEARCH, best_combination, edge_on_hypotheses, initial_hypotheses
from hand_sog_tracker.core.kinematics import global_rotation
from hand_sog_tracker.core.objective import Objective
from hand_sog_tracker.core.optimizer import OptimizeResult
from hand_sog_tracker.core.region import hand_roi
from hand_sog_tracker.core.salient import detect_fingertips
from hand_sog_tracker.core.search.fit import MAX_BATCH, fit_parts, part
from hand_sog_tracker.core.search.score import assignment_cost
from hand_sog_tracker.core.types import TrackerConfig

__all__ = [
    "BLOB_BEHIND_MM", "NEW_TRACK_CANDIDATES", "NEW_TRACK_DATA", "Finalists", "back_toward", "on_hand_side",
    "start_search",
]

BLOB_BEHIND_MM = 20.0  #: the window ends this far (mm) behind the blob's farthest surface pixel (edge noise)
WRIST_MARGIN_MM = 0.0  #: data farther than this (mm) beyond the wrist plane are forearm (the model has none)
#: Most candidates of one stage: ``screened`` start poses per palm side and 2 x 2 extra directions.
NEW_TRACK_CANDIDATES = 2 * INIT_SEARCH.screened + 4
#: Most data Gaussians of a new track's search and finish (:func:`quadtree_sog` thins beyond): its
#: largest stage fits in the model x data pairs of one batch at the data cap (issue 50).
NEW_TRACK_DATA = MAX_BATCH * MAX_DATA_GAUSSIANS // NEW_TRACK_CANDIDATES
Bounds = tuple[NDArray[np.float64], NDArray[np.float64]]


@dataclass(frozen=True, eq=False)
class Finalists:
    """The search's outcome."""

    poses: list[NDArray[np.float64]]  #: the finalist poses (26,), best first
    end_mm: float = np.inf  #: where the search's depth window ended (mm): the finish's ends there too
    #: ``poses`` (indices) from a start tilted in depth: kept once refined if over ``combination_below`` (objects tilt)
    tilted: frozenset[int] = frozenset()


def on_hand_side(points: NDArray[np.float64], theta: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Which ``points`` (n, 3) mm lie on the hand side of the wrist plane at ``theta`` (26,)."""
    return (points - theta[:3]) @ global_rotation(theta)[:, 1] > -WRIST_MARGIN_MM


def back_toward(theta: NDArray[np.float64]) -> bool:
    """Whether the back of the hand at ``theta`` faces the camera (the palm normal points away)."""
    return bool(global_rotation(theta)[2, 2] > 0)


def _balanced(ranked: list[tuple], n: int) -> list[tuple]:
    """The first ``n`` of ``ranked`` (best first, last item: which way the palm faces), half from
    each side while both have enough (a rigid fit prefers the back of a hand to its palm)."""
    chosen: list[int] = []
    for side in (True, False):
        chosen += [k for k, a in enumerate(ranked) if a[-1] == side][: (n + 1) // 2 if side else n // 2]
    chosen += [k for k in range(len(ranked)) if k not in chosen][: max(0, n - len(chosen))]
    return [ranked[k] for k in sorted(chosen)]


def _screened(
    model: HandModel, config: TrackerConfig, data: ImageSoG, starts: list, keeps: list[NDArray[np.bool_]], n: int,
    sides: list[bool],
) -> set[int]:
    """Indices of the ``n`` start poses per palm side (``sides[i]``: back to the camera) best by the
    objective of their part ``keeps[i]`` (n,) of ``data`` (a batch per distinct part; first on a tie)."""
    values = [-np.inf] * len(starts)
    groups: dict[bytes, list[int]] = {}
    for i, keep in enumerate(keeps):
        if keep.any():
            groups.setdefault(keep.tobytes(), []).append(i)
    for ks in groups.values():
        batch = _values(Objective(model, part(data, keeps[ks[0]]), config))(np.array([starts[i] for i in ks]))
        for i, value in zip(ks, batch.tolist()):
            values[i] = value
    scored = [(value, -i, side) for i, (value, side) in enumerate(zip(values, sides))]
    chosen: set[int] = set()
    for side in (True, False):
        chosen.update(-s[1] for s in sorted((s for s in scored if s[2] == side), reverse=True)[:n])
    return chosen


def _values(obj: Objective) -> Callable[[NDArray[np.float64]], NDArray[np.float64]]:
    """The values (k,) of ``obj`` at poses (k, 26), one batch evaluation without gradient."""
    return lambda thetas: obj.batch(thetas, gradient=False)[0]


def start_search(pre: Preprocessed, model: HandModel, config: TrackerConfig, bounds: Bounds) -> Finalists | None:
    """The finalist poses for the hand in ``pre`` (see the module docstring), or None (no hand)."""
    cfg, eff = config, INIT_SEARCH
    blob = find_hand(pre, cfg)
    if blob is None:
        return None
    starts = initial_hypotheses(model, blob, cfg.init_hypotheses)
    roi, window = hand_roi(model, starts[0], pre.intrinsics, cfg.roi_radius_mm)
    fine_px = leaf_px(cfg.min_quad_px, 0.5 * (window[0] + window[1]), pre.intrinsics)
    end_mm = blob.far_mm + BLOB_BEHIND_MM
    window = (window[0], min(window[1], end_mm))
    coarse_px = max(eff.coarse_quad_px, cfg.min_quad_px)
    coarse = quadtree_sog(pre, cfg.quadtree_threshold_mm, roi, window, coarse_px, NEW_TRACK_DATA)
    fine = quadtree_sog(pre, cfg.quadtree_threshold_mm, roi, window, fine_px, NEW_TRACK_DATA)
    det = detect_fingertips(pre, roi, window)
    if det.n:
        det = det.subset(on_hand_side(det.points, starts[0]))
    # The edge-on start poses count on the side they were rolled from (their palm normal lies in the
    # image plane, its sign there is rounding); they compete with the blob's.
    starts += edge_on_hypotheses(model, blob)
    sides = [back_toward(x) for x in starts[:-2]] + [False, True]
    n_blob = len(starts)
    for d in (blob.hand_direction, detection_direction(blob, det.points)):
        if d is not None:  # (a wrist bent sideways turns the blob's axis off the hand's)
            more = initial_hypotheses(model, HandBlob(blob.palm, [d]), 2)
            starts += more
            sides += [back_toward(x) for x in more]
    rigid = np.zeros(starts[0].size, dtype=bool)
    rigid[:6] = True

    def fitted(data: ImageSoG, poses: list, **kwargs: object) -> list[tuple[int, NDArray, OptimizeResult]]:
        """(k, pose, fit) of each of ``poses`` with data on its hand side, fitted on its part."""
        keeps = [on_hand_side(data.points, x) for x in poses]
        ks = [k for k, keep in enumerate(keeps) if keep.any()]
        fits = fit_parts(
            Objective(model, data, cfg), np.array([poses[k] for k in ks]), np.array([keeps[k] for k in ks]),
            bounds=bounds, initial_scale=2.0, **kwargs,
        )
        return [(k, poses[k], r) for k, r in zip(ks, fits)]

    def align(ranks: list[int], poses: list) -> list[tuple]:
        """(value, -rank, pose, back toward) of each start rigidly aligned on the coarse data (the
        side of a start pose of rank under ``len(sides)``: its count, see above)."""
        fits = fitted(coarse, poses, iterations=eff.rigid_iterations, active=rigid)
        return [
            (r.fun, -ranks[k], r.x, sides[ranks[k]] if ranks[k] < len(sides) else back_toward(x0))
            for k, x0, r in fits
        ]

    def articulate(kept: list[tuple]) -> list[tuple[float, int, NDArray[np.float64]]]:
        """(score, -rank, pose) of each kept pose articulated on the fine data."""
        fits = fitted(fine, [a[2] for a in kept], iterations=eff.full_iterations)
        return [
            (r.fun - cfg.w_sal * assignment_cost(model, r.x, det, hidden_tips=False), kept[k][1], r.x)
            for k, _, r in fits
        ]

    keeps = [on_hand_side(coarse.points, x) for x in starts]
    screened = _screened(model, cfg, coarse, starts[:n_blob], keeps[:n_blob], eff.screened, sides)
    chosen = [i for i in range(len(starts)) if i >= n_blob or i in screened]
    aligned = align(chosen, [starts[i] for i in chosen])
    # The blob's start poses compete for ``kept``; the best of the extra directions' joins them.
    blob_aligned = [a for a in aligned if -a[1] < n_blob]
    kept = _balanced(sorted(blob_aligned, key=lambda a: a[:2], reverse=True), eff.kept)
    if len(blob_aligned) < len(aligned):
        kept.append(max((a for a in aligned if -a[1] >= n_blob), key=lambda a: a[:2]))
    ranked = sorted(articulate(kept), key=lambda s: s[:2], reverse=True)
    if not ranked:
        return None
    if ranked[0][0] < eff.combination_below:
        # A poor best: maybe a hand found mid-motion.  The best combination of curled fingers at
        # the first two start poses (palm toward and away) competes by ``combination_margin``.
        ks = [k for k in range(2) if keeps[k].any()]
        combos = [best_combination(starts[k], _values(Objective(model, part(coarse, keeps[k]), cfg))) for k in ks]
        tried = sorted(articulate(align([len(starts) + k for k in ks], combos)), key=lambda s: s[:2], reverse=True)
        if tried and tried[0][0] >= ranked[0][0] + eff.combination_margin:
            ranked = sorted(ranked + tried, key=lambda s: s[:2], reverse=True)
    # The best of the other palm side joins the finalists when none of them has it: the search
    # scores without the silhouette, and the finish's full objective tells the two apart.
    best = ranked[: eff.finalists]
    best += [s for s in ranked if back_toward(s[2]) not in {back_toward(x) for _, _, x in best}][:1]
    # (A flat start's R[2, 1] is 0 to rounding; the combinations, ranks len(starts) on, are flat.)
    tilted = [-r < len(starts) and abs(global_rotation(starts[-r])[2, 1]) > 1e-9 for _, r, _ in best]
    return Finalists([x for _, _, x in best], end_mm, frozenset(np.flatnonzero(tilted).tolist()))
