"""Automatic initialisation: start poses for the hand found in a depth image (:mod:`.handfind`),
palm toward / away from the camera, open / closed, in-plane rotations; the search over them:
:func:`~hand_sog_tracker.core.search.start.start_search` (measurements: doc/design/search.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.articulations import CLOSED, FINGER_CURLED, FINGER_EXTENDED, HALF_CLOSED, OPEN
from hand_sog_tracker.core.hand_model import JOINTS, N_PARAMS, HandModel, chain_slice
from hand_sog_tracker.core.handfind import HandBlob
from hand_sog_tracker.core.rotations import euler_from_matrix, rot_y  # euler_from_matrix re-exported

__all__ = [
    "InitSearch", "INIT_SEARCH", "finger_combinations", "best_combination", "initial_hypotheses", "edge_on_hypotheses",
    "euler_from_matrix",
]


@dataclass(frozen=True)
class InitSearch:
    """Effort of a new track's search (counts and score thresholds; chosen here, issues 11 and 14)."""

    coarse_quad_px: int = 8  #: smallest quadtree leaf (px) of the coarse data the start poses are aligned on
    #: start poses of the blob's directions aligned per palm side, the best at the start (the extra
    #: directions' always)
    screened: int = 4
    rigid_iterations: int = 3  #: rigid (wrist pose only) iterations of every start pose on the coarse data
    kept: int = 4  #: poses articulated after the rigid alignment, the best, half per palm side
    full_iterations: int = 8  #: iterations (all parameters) of each kept pose on the fine data
    finalists: int = 2  #: best-scoring poses refined with the full objective (+ the other palm side's best)
    final_iterations: int = 10  #: iterations of each finalist with the full objective
    combination_below: float = 0.36  #: single fingers curled are tried when the best score is below this
    combination_margin: float = 0.045  #: ... and compete when their best beats the others by this much


#: The effort the tracker uses.
INIT_SEARCH = InitSearch()


def _frame(y_dir: NDArray[np.float64], palm_to_camera: bool, roll: float) -> NDArray[np.float64]:
    """Hand-frame axes in camera coordinates (columns x, y, z), rolled about the finger axis."""
    y = y_dir / np.linalg.norm(y_dir)
    view = np.array([0.0, 0.0, -1.0]) if palm_to_camera else np.array([0.0, 0.0, 1.0])
    z = view - (view @ y) * y
    if np.linalg.norm(z) < 1e-6:
        z = np.array([1.0, 0.0, 0.0]) - y[0] * y
    z /= np.linalg.norm(z)
    x = np.cross(y, z)
    return np.stack([x, y, z], axis=1) @ rot_y(roll)


def initial_hypotheses(model: HandModel, blob: HandBlob, n: int) -> list[NDArray[np.float64]]:
    """Up to ``n`` start poses (26,) for the hand in ``blob``, most likely first: each direction
    open with the palm toward and away from the camera, closed and half-closed for the first; a
    direction tilted in depth (the hand end's plane) with the back toward it only (seen from above)."""
    combos = []
    for i, d in enumerate(blob.directions):
        for joints in (OPEN, CLOSED, HALF_CLOSED) if i == 0 else (OPEN,):
            combos += [(d, palm, joints) for palm in (True, False) if not (palm and d[2])]
    return [_start(model, blob.palm, _frame(d, palm, 0.0), joints) for d, palm, joints in combos][:n]


def edge_on_hypotheses(model: HandModel, blob: HandBlob) -> list[NDArray[np.float64]]:
    """The two edge-on start poses (26,) of ``blob``'s first direction, open: palm toward and away
    from the camera rolled 90 deg about the finger axis (a hand seen from its side has its own)."""
    d = blob.directions[0]
    return [_start(model, blob.palm, _frame(d, palm, 0.5 * np.pi), OPEN) for palm in (True, False)]


def _start(
    model: HandModel, palm: NDArray[np.float64], R: NDArray[np.float64], joints: NDArray[np.float64]
) -> NDArray[np.float64]:
    """The pose (26,) of hand frame ``R`` (3, 3) with its palm centre at ``palm`` (3,) mm and ``joints``."""
    # (The mirror of a left hand acts inside the hand frame: the same rotation serves both.)
    theta = np.zeros(N_PARAMS)
    theta[:3] = palm - R @ np.array([0.0, 0.55 * float(model.bases[2, 1]), 0.0])
    theta[3:6] = euler_from_matrix(R)
    theta[JOINTS] = joints
    return theta


def finger_combinations(start: NDArray[np.float64]) -> list[NDArray[np.float64]]:
    """``start`` (26,) with each finger extended or curled: the 31 combinations with at least one
    curled (the thumb as in :data:`CLOSED`), in the order of the bits of 1..31 (bit c: chain c)."""
    curled = (CLOSED[:4], *[FINGER_CURLED] * 4)  # (CLOSED[:4]: the thumb's joints)
    out = []
    for bits in range(1, 32):
        x = np.array(start, dtype=np.float64)
        for c in range(5):
            x[chain_slice(c)] = curled[c] if (bits >> c) & 1 else FINGER_EXTENDED
        out.append(x)
    return out


def best_combination(
    start: NDArray[np.float64], values: Callable[[NDArray[np.float64]], NDArray[np.float64]]
) -> NDArray[np.float64]:
    """The pose of :func:`finger_combinations` at ``start`` (26,) that ``values`` (scores (k,) of poses
    (k, 26)) scores highest (the first of equal scores), from 17 of the 31 in two calls: the 15 of index
    .. little, thumb extended, then the thumb alone and with their best.  Exact when it adds per chain."""
    combos = finger_combinations(start)
    # combos[i] curls the chains of the bits of i + 1 (bit 0: the thumb).
    first = [i for i in range(31) if (i + 1) % 2 == 0]
    scored = dict(zip(first, np.asarray(values(np.array([combos[i] for i in first]))).tolist()))
    fingers = max(scored, key=lambda i: (scored[i], -i))  # (the first of equal scores)
    then = (0, fingers + 1)  # the thumb alone, and with the best fingers
    scored.update(zip(then, np.asarray(values(np.array([combos[i] for i in then]))).tolist()))
    return combos[max(scored, key=lambda i: (scored[i], -i))]
