"""Named hand articulations: joint angles in pose-vector order (rad).

Whole-hand articulations are arrays of shape (20,) (the pose vector's ``theta[6:]``,
thumb first, see :mod:`hand_sog_tracker.core.hand_model`); single-chain articulations are
(4,) arrays ``flex1, abd, flex2, flex3`` of one chain.  All arrays are read-only.

The tracker's start and restart shapes (used by :mod:`.initialise`, :mod:`.tracker` and
:mod:`.calibration`) are round numbers chosen here, not fitted.  The synthetic motions
(:mod:`hand_sog_tracker.synth.motions`) build their key shapes from the per-finger angles in
degrees below (the thumb is solved there by inverse kinematics).
"""

from __future__ import annotations

from typing import Final

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "FINGER_EXTENDED",
    "FINGER_CURLED",
    "OPEN",
    "HALF_CLOSED",
    "CLOSED",
    "FIST_FINGER_DEG",
    "CLAW_FINGER_DEG",
    "PINCH_INDEX_DEG",
]


def _frozen(values: list[float]) -> NDArray[np.float64]:
    arr = np.array(values)
    arr.setflags(write=False)
    return arr


#: One chain nearly straight (rad, 4,): restart candidate for a dangling finger (tracker).
FINGER_EXTENDED: Final = _frozen([0.1, 0.0, 0.1, 0.1])
#: One finger curled into the palm (rad, 4,): restart candidate, and the fingers of :data:`CLOSED`.
FINGER_CURLED: Final = _frozen([1.3, 0.0, 1.5, 0.9])
#: Open hand (rad, 20,): initialisation start shape, and the joints calibration fit frames are
#: set to.  Not :func:`~hand_sog_tracker.core.hand_model.rest_pose` (fingers at 0, thumb CMC 0.1).
OPEN: Final = _frozen([0.1, 0.0, 0.1, 0.1] + [0.05, 0.0, 0.05, 0.05] * 4)
#: Half-closed hand (rad, 20,): initialisation start shape.
HALF_CLOSED: Final = _frozen([0.2, 0.2, 0.3, 0.3] + [0.6, 0.0, 0.7, 0.4] * 4)
#: Closed hand, a fist (rad, 20,): initialisation start shape; fingers as :data:`FINGER_CURLED`.
CLOSED: Final = _frozen([0.5, 0.3, 0.6, 0.6] + [1.3, 0.0, 1.5, 0.9] * 4)

#: Synthetic fist, each of index .. little (deg: MCP, abduction, PIP, DIP).
FIST_FINGER_DEG: Final[tuple[float, float, float, float]] = (80.0, 0.0, 95.0, 55.0)
#: Synthetic claw (MCP slightly hyperextended, PIP/DIP flexed), each of index .. little (deg).
CLAW_FINGER_DEG: Final[tuple[float, float, float, float]] = (-10.0, 0.0, 95.0, 75.0)
#: Index finger of the synthetic pinch, curled toward the thumb (deg).
PINCH_INDEX_DEG: Final[tuple[float, float, float, float]] = (20.0, -15.0, 80.0, 50.0)
