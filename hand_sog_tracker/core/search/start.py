"""A new track's search: from the hand found in the depth to the finalist poses.

The start poses (:func:`~hand_sog_tracker.core.initialise.initial_hypotheses`: the hand
blob's directions, palm toward and away, open, half-closed and closed, plus open hands along
the hand end's own axis and toward the fingertip detections) are screened by the objective at
the start, aligned rigidly on a coarse quadtree (seed 004's coarse-to-fine), the best of each
palm side articulated on the fine one, and the best by the score become the finalists.  When
even the best scores poorly, single fingers curled (:func:`best_combination`) are tried too.
No silhouette term yet: it would pull the poses into the outline before the depth has placed
them.  Each pose drops the data beyond its own wrist; the poses that keep the same data share
one objective; the poses of a stage are fitted as one batch, each on its own part of the data
(:meth:`Objective.batch`'s ``parts``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.depth_sog import MAX_DATA_GAUSSIANS, ImageSoG, Preprocessed, leaf_px, quadtree_sog
from hand_sog_tracker.core.hand_model import HandModel
from hand_sog_tracker.core.initialise import (
    INIT_SEARCH,
    HandBlob,
    best_combination,
    detection_direction,
    find_hand,
    initial_hypotheses,
)
from hand_sog_tracker.core.kinematics import global_rotation
from hand_sog_tracker.core.objective import Objective
from hand_sog_tracker.core.optimizer import OptimizeResult
from hand_sog_tracker.core.region import hand_roi
from hand_sog_tracker.core.salient import detect_fingertips
from hand_sog_tracker.core.search.fit import MAX_BATCH, fit_batch
from hand_sog_tracker.core.search.score import assignment_cost
from hand_sog_tracker.core.types import TrackerConfig

__all__ = [
    "BLOB_BEHIND_MM", "NEW_TRACK_CANDIDATES", "NEW_TRACK_DATA", "Finalists", "back_toward", "fit_each",
    "hand_side", "on_hand_side", "start_search",
]

#: The search's depth window ends this far behind the blob's farthest surface pixel (mm; depth
#: noise at the blob's edge): what lies farther was cut off as a body or a wall.
BLOB_BEHIND_MM = 20.0
#: Data farther than this beyond the wrist plane are forearm (mm: the model has no forearm).
WRIST_MARGIN_MM = 0.0
#: Most candidates of one stage of a new track's search: the rigid alignment of the ``screened``
#: start poses per palm side and the two open hands of each of the two extra directions.
NEW_TRACK_CANDIDATES = 2 * INIT_SEARCH.screened + 4
#: Most data Gaussians a new track's search and finish run on (evenly thinned beyond, as
#: :func:`quadtree_sog` thins at ``MAX_DATA_GAUSSIANS``): a new track fits many candidates on
#: one frame, so its work is bounded by its largest stage fitting within the model x data pairs
#: of one batch at the data cap (``MAX_BATCH`` candidates on ``MAX_DATA_GAUSSIANS``), whatever
#: the input (issue 50: a wrong K or ``min_quad_px`` 2 gave data near the cap).
NEW_TRACK_DATA = MAX_BATCH * MAX_DATA_GAUSSIANS // NEW_TRACK_CANDIDATES
Bounds = tuple[NDArray[np.float64], NDArray[np.float64]]


@dataclass(frozen=True, eq=False)
class Finalists:
    """The search's outcome: ``poses`` (26,) each, best first, and ``end_mm``, where its depth
    window ended (mm): the finish's window ends there too."""

    poses: list[NDArray[np.float64]]
    end_mm: float = np.inf


def on_hand_side(points: NDArray[np.float64], theta: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Which ``points`` (n, 3) mm lie on the hand side of the wrist plane at ``theta`` (26,)."""
    return (points - theta[:3]) @ global_rotation(theta)[:, 1] > -WRIST_MARGIN_MM


def hand_side(data: ImageSoG, theta: NDArray[np.float64]) -> ImageSoG:
    """``data`` without the Gaussians beyond the wrist at ``theta`` (``data`` itself when none is)."""
    if data.n == 0:
        return data
    keep = on_hand_side(data.points, theta)
    return data if keep.all() else data.subset(keep)


def back_toward(theta: NDArray[np.float64]) -> bool:
    """Whether the back of the hand at ``theta`` faces the camera (the palm normal points away)."""
    return bool(global_rotation(theta)[2, 2] > 0)


def _parts(data: ImageSoG, poses: Sequence[NDArray[np.float64]]) -> list[ImageSoG]:
    """:func:`hand_side` of ``data`` at each pose; poses that keep the same Gaussians get the
    same object (so that they share one objective)."""
    seen: dict[bytes, ImageSoG] = {}
    out = []
    for x in poses:
        if data.n == 0:
            out.append(data)
            continue
        keep = on_hand_side(data.points, x)
        key = keep.tobytes()
        if key not in seen:
            seen[key] = data if keep.all() else data.subset(keep)
        out.append(seen[key])
    return out


def _keeps(data: ImageSoG, poses: Sequence[NDArray[np.float64]]) -> list[NDArray[np.bool_]]:
    """Which Gaussians of ``data`` (n,) bool lie on the hand side of each pose's wrist plane."""
    return [on_hand_side(data.points, x) for x in poses]


def fit_each(
    model: HandModel,
    config: TrackerConfig,
    data: ImageSoG,
    items: Sequence[tuple[NDArray[np.float64], NDArray[np.bool_]]],
    bounds: Bounds,
    **kwargs: object,
) -> list[OptimizeResult]:
    """Fit each ``(start pose (26,), part (n,) bool)`` of ``items`` on the plain objective of
    its part of ``data`` (each part with at least one Gaussian), all as one batch
    (:func:`~.fit.fit_batch`; a lone pose on its part's own objective).  Results in order."""
    if not items:
        return []
    if len(items) == 1:
        x0, keep = items[0]
        obj = Objective(model, data if keep.all() else data.subset(keep), config)
        return fit_batch(obj.batch, x0[None], obj.data.n, bounds=bounds, **kwargs)
    obj = Objective(model, data, config)
    parts = np.array([keep for _, keep in items])
    whole = bool(parts.all())

    def fun(
        thetas: NDArray[np.float64], gradient: bool = True, index: NDArray[np.int64] | None = None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        return obj.batch(thetas, gradient, parts=None if whole else parts[index])

    starts = np.array([x0 for x0, _ in items])
    return fit_batch(fun, starts, data.n, bounds=bounds, with_index=True, **kwargs)


def _balanced(ranked: list[tuple], n: int) -> list[tuple]:
    """The first ``n`` of ``ranked`` (best first, last item: which way the palm faces), half
    from each side while both have enough (a rigid fit prefers the back of a hand to a palm
    it cannot articulate yet)."""
    chosen: list[int] = []
    for side in (True, False):
        chosen += [k for k, a in enumerate(ranked) if a[-1] == side][: (n + 1) // 2 if side else n // 2]
    chosen += [k for k in range(len(ranked)) if k not in chosen][: max(0, n - len(chosen))]
    return [ranked[k] for k in sorted(chosen)]


def _screened(model: HandModel, config: TrackerConfig, starts: list, parts: list[ImageSoG], n: int) -> set[int]:
    """Indices of the ``n`` start poses per palm side that score best by the objective at the
    start pose itself (one evaluation each, no gradient, those sharing a part as one batch;
    the first on a tie)."""
    values = [-np.inf] * len(starts)
    groups: dict[int, list[int]] = {}
    for i, part in enumerate(parts):
        if part.n:
            groups.setdefault(id(part), []).append(i)
    for ks in groups.values():
        batch = Objective(model, parts[ks[0]], config).batch(np.array([starts[i] for i in ks]), gradient=False)[0]
        for i, value in zip(ks, batch.tolist()):
            values[i] = value
    scored = [(value, -i, back_toward(x0)) for i, (x0, value) in enumerate(zip(starts, values))]
    chosen: set[int] = set()
    for side in (True, False):
        chosen.update(-s[1] for s in sorted((s for s in scored if s[2] == side), reverse=True)[:n])
    return chosen


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
    n_blob = len(starts)
    # Open hands along the hand end's own axis and toward the detections (a wrist bent sideways
    # turns the blob's axis off the hand's).
    for d in (blob.hand_direction, detection_direction(blob, det.points)):
        if d is not None:
            starts += initial_hypotheses(model, HandBlob(blob.palm, [d]), 2)
    rigid = np.zeros(starts[0].size, dtype=bool)
    rigid[:6] = True

    def align(indexed: list[tuple[int, NDArray[np.float64], NDArray[np.bool_]]]) -> list[tuple]:
        """(value, -rank, pose, back toward) of each start rigidly aligned on its part of the
        coarse data."""
        fits = fit_each(
            model, cfg, coarse, [(x0, keep) for _, x0, keep in indexed], bounds,
            iterations=eff.rigid_iterations, initial_scale=2.0, active=rigid,
        )
        return [(r.fun, -i, r.x, back_toward(x0)) for (i, x0, _), r in zip(indexed, fits)]

    def articulate(kept: list[tuple]) -> list[tuple[float, int, NDArray[np.float64]]]:
        """(score, -rank, pose) of each kept pose articulated on the fine data."""
        poses = [a[2] for a in kept]
        items = [(k, x, keep) for k, (x, keep) in enumerate(zip(poses, _keeps(fine, poses))) if keep.any()]
        fits = fit_each(
            model, cfg, fine, [(x, keep) for _, x, keep in items], bounds, iterations=eff.full_iterations,
            initial_scale=2.0,
        )
        return [
            (r.fun - cfg.w_sal * assignment_cost(model, r.x, det, hidden_tips=False), kept[k][1], r.x)
            for (k, _, _), r in zip(items, fits)
        ]

    parts = _parts(coarse, starts)
    keeps = _keeps(coarse, starts)
    screened = _screened(model, cfg, starts[:n_blob], parts[:n_blob], eff.screened)
    chosen = [
        (i, x0, keep) for i, (x0, keep) in enumerate(zip(starts, keeps))
        if (i >= n_blob or i in screened) and keep.any()
    ]
    aligned = align(chosen)
    # The blob's start poses compete for ``kept``; the best of the hand axis' and the detection
    # direction's is articulated besides them.
    blob_aligned = [a for a in aligned if -a[1] < n_blob]
    kept = _balanced(sorted(blob_aligned, key=lambda a: a[:2], reverse=True), eff.kept)
    if len(blob_aligned) < len(aligned):
        kept.append(max((a for a in aligned if -a[1] >= n_blob), key=lambda a: a[:2]))
    ranked = sorted(articulate(kept), key=lambda s: s[:2], reverse=True)
    if not ranked:
        return None
    if ranked[0][0] < eff.combination_below:
        # A poor best: maybe a hand found mid-motion, some fingers curled and others not.  The
        # best combination of curled fingers at the start of the blob's main direction, palm
        # toward and away, competes when it beats the others by ``combination_margin``.
        n = len(starts)
        combos = []
        for k, (x0, part) in enumerate(zip(starts[:2], parts)):
            if part.n:
                screen = Objective(model, part, cfg)
                best = best_combination(x0, lambda c, s=screen: s.batch(c, gradient=False)[0])
                combos.append((n + k, best, keeps[k]))
        tried = sorted(articulate(align(combos)), key=lambda s: s[:2], reverse=True)
        if tried and tried[0][0] >= ranked[0][0] + eff.combination_margin:
            ranked = sorted(ranked + tried, key=lambda s: s[:2], reverse=True)
    # The best of the other palm side joins the finalists when none of them has it: the search
    # scores without the silhouette, and the finish's full objective tells the two apart.
    poses = [x for _, _, x in ranked[: eff.finalists]]
    sides = {back_toward(x) for x in poses}
    return Finalists(poses + [x for _, _, x in ranked if back_toward(x) not in sides][:1], end_mm)


