"""The tracking objective and its analytic gradient (paper 000, sec. 5.2), over one pose or a
batch of poses.

:class:`Objective` (``objective.py``) sums the terms, each in its own module: the data terms
``E_sim`` and ``E_dan`` (``data.py``), collision (``collision.py``), the fingertip targets
``E_sal`` (``tips.py``), the pose terms ``E_lim``, ``E_smo``, ``E_ord``, ``E_cpl`` and ``E_curl``
(``pose.py``); ``E_sil`` lives in :mod:`hand_sog_tracker.core.silhouette`.  The terms'
constants are in ``constants.py``.
"""

from hand_sog_tracker.core.objective.collision import contact_shares
from hand_sog_tracker.core.objective.constants import (
    COLLISION_CONTACT_FREE,
    CONTACT_CURL_RAD,
    COUPLING_DIP_PIP,
    CURL_MAX_RAD,
    ORDER_MIN_GAP_RAD,
    PAIR_CUT_SIGMAS,
    PALM_DISTAL_COLLISION,
    SALIENT_SCALE_MM,
    SALIENT_SOFT_MM,
    SIM_GAIN,
    SIM_SATURATION,
    SMOOTH_TRANSLATION_MM,
    TAU1_MM,
    TAU2_MM,
)
from hand_sog_tracker.core.objective.data import gaussian_support, visibility_weights
from hand_sog_tracker.core.objective.objective import EnergyTerms, Objective
from hand_sog_tracker.core.objective.tips import TipTargets

__all__ = [
    "EnergyTerms",
    "gaussian_support",
    "Objective",
    "TipTargets",
    "TAU1_MM",
    "TAU2_MM",
    "SMOOTH_TRANSLATION_MM",
    "ORDER_MIN_GAP_RAD",
    "COUPLING_DIP_PIP",
    "CURL_MAX_RAD",
    "SALIENT_SOFT_MM",
    "SALIENT_SCALE_MM",
    "SIM_SATURATION",
    "SIM_GAIN",
    "PALM_DISTAL_COLLISION",
    "COLLISION_CONTACT_FREE",
    "CONTACT_CURL_RAD",
    "PAIR_CUT_SIGMAS",
    "contact_shares",
    "visibility_weights",
]
