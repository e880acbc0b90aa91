"""The one score that picks a frame's answer among its candidates (seed 001, eq. 11).

``score(theta) = E_plain(theta) - w_sal * cost(theta) / SALIENT_SCALE_MM``: the objective without
its salient term (which favours the frame's start assignment) minus the optimal assignment cost of
the fingertip detections (:func:`assignment_cost`): it tells flipped or swapped fingers apart.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.hand_model import FINGER_DIP, FINGER_PIP, HandModel
from hand_sog_tracker.core.kinematics import fingertips, global_rotation
from hand_sog_tracker.core.objective import SALIENT_SCALE_MM, Objective
from hand_sog_tracker.core.salient import Detections, assign_detections

__all__ = [
    "ASSIGN_LAMBDA_MM", "assignment_cost", "lonely_detections", "own_detections", "plain", "score", "sq_distances",
    "tip_lambdas",
]

ASSIGN_LAMBDA_MM = 30.0  #: cost (mm) of a fingertip without a detection (seed 001's lambda, eq. 11)
#: A curled tip with the palm or the back to the camera (normal within acos(``HIDDEN_PALM_COS``) of
#: the view) costs less, down to ``HIDDEN_TIP_LAMBDA`` x lambda from PIP + DIP ``OPEN_TIP_RAD`` to
#: ``CURLED_TIP_RAD`` (rad): the detector cannot see it (issues 11, 46; doc/design/hand_check.md).
HIDDEN_TIP_LAMBDA = 0.0
HIDDEN_PALM_COS = 0.5
OPEN_TIP_RAD = 1.0
CURLED_TIP_RAD = 2.0
UNEXPLAINED_DETECTION_MM = 20.0  #: a detection this far (mm, the MCPs' spacing) from every fingertip ...
UNEXPLAINED_CONFIDENCE = 0.5  #: ... this confident, is a finger the model missed ...
FAR_UNEXPLAINED_MM = 40.0  #: ... and one this far ...
FAR_UNEXPLAINED_CONFIDENCE = 0.3  #: ... this confident (no neighbour's partly seen tip; issue 11)
OWN_DETECTION_MM = 10.0  #: a tip's own detection: the optimal assignment gives it one this near (mm)


def sq_distances(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Squared distances (k, l) between the points ``a`` (k, 3) and ``b`` (l, 3) (bit for bit
    ``((a[:, None] - b[None]) ** 2).sum(-1)``, without a reduction call)."""
    diff = a[:, None, :] - b[None, :, :]
    sq = np.multiply(diff, diff, out=diff)
    d2 = sq[..., 0] + sq[..., 1]
    d2 += sq[..., 2]
    return d2


def tip_lambdas(theta: NDArray[np.float64]) -> NDArray[np.float64]:
    """Cost (mm) of leaving each fingertip (5,) at ``theta`` (26,) without a detection:
    ``ASSIGN_LAMBDA_MM``, falling for a curled tip while the palm or the back faces the camera."""
    lam = np.full(5, ASSIGN_LAMBDA_MM)
    if HIDDEN_TIP_LAMBDA != 1.0 and abs(global_rotation(theta)[2, 2]) > HIDDEN_PALM_COS:
        curl = theta[FINGER_PIP] + theta[FINGER_DIP]  # index .. little, rad
        share = np.clip((curl - OPEN_TIP_RAD) / (CURLED_TIP_RAD - OPEN_TIP_RAD), 0.0, 1.0)
        lam[1:] *= 1.0 - (1.0 - HIDDEN_TIP_LAMBDA) * share
    return lam


def assignment_cost(
    model: HandModel, theta: NDArray[np.float64], det: Detections, hidden_tips: bool, tips: NDArray | None = None
) -> float:
    """Seed 001's assignment cost (eq. 11) at ``theta`` (26,; its fingertips ``tips`` (5, 3) mm when known)
    per ``SALIENT_SCALE_MM``: assigned pairs cost their distance, detections left over lambda x their
    confidence, fingertips without one lambda, less with ``hidden_tips`` (:func:`tip_lambdas`; tracked
    frames: a curled tip the detector cannot see, the palm or the back to the camera)."""
    if det.n == 0:
        return 0.0
    tips = fingertips(model, theta) if tips is None else tips
    lam = tip_lambdas(theta) if hidden_tips else np.full(5, ASSIGN_LAMBDA_MM)
    assigned = assign_detections(tips, det, ASSIGN_LAMBDA_MM, lam)
    has = assigned >= 0
    d = np.linalg.norm(tips[has] - det.points[assigned[has]], axis=1).sum()
    unused = np.ones(det.n, bool)
    unused[assigned[has]] = False
    cost = d + lam[~has].sum() + ASSIGN_LAMBDA_MM * det.confidence[unused].sum()
    return float(cost / SALIENT_SCALE_MM)


def plain(obj: Objective) -> Objective:
    """``obj`` without its salient term: the objective candidates are fitted and scored on."""
    if obj.targets is None or obj.config.w_sal == 0:
        return obj
    return obj.variant(replace(obj.config, w_sal=0.0), None)


def score(
    plain_obj: Objective, theta: NDArray[np.float64], det: Detections, w_sal: float, hidden_tips: bool,
    value: float | None = None,
) -> float:
    """``plain_obj`` (a :func:`plain` objective) at ``theta`` (26,; ``value`` when known) minus
    ``w_sal`` x the assignment cost of ``det``."""
    if value is None:
        value = plain_obj(theta, gradient=False)[0]
    return value - w_sal * assignment_cost(plain_obj.model, theta, det, hidden_tips)


def lonely_detections(model: HandModel, theta: NDArray[np.float64], det: Detections) -> NDArray[np.int64]:
    """Indices of the detections no fingertip at ``theta`` (26,) explains (``*UNEXPLAINED*``)."""
    if det.n == 0:
        return np.zeros(0, dtype=np.int64)
    dist = np.sqrt(sq_distances(det.points, fingertips(model, theta))).min(axis=1)
    return np.flatnonzero(
        ((dist > UNEXPLAINED_DETECTION_MM) & (det.confidence >= UNEXPLAINED_CONFIDENCE))
        | ((dist > FAR_UNEXPLAINED_MM) & (det.confidence >= FAR_UNEXPLAINED_CONFIDENCE))
    )


def own_detections(model: HandModel, theta: NDArray[np.float64], det: Detections) -> NDArray[np.bool_]:
    """Whether the optimal assignment gives each fingertip (5,) at ``theta`` a detection within ``OWN_DETECTION_MM``."""
    tips = fingertips(model, theta)
    assigned = assign_detections(tips, det, ASSIGN_LAMBDA_MM)
    own = assigned >= 0
    own[own] = np.linalg.norm(tips[own] - det.points[assigned[own]], axis=1) < OWN_DETECTION_MM
    return own
