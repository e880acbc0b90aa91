"""The user's saved hand models at start-up: the one-hand model and, with ``max_hands: 2``, each hand's.

One job: read the files ``~/calibrate`` writes (:func:`~hand_sog_tracker.core.model_io.save_hand_shape`)
and say in the node's log what each hand uses.  A missing file means the default hand; an
invalid one is warned about and ignored (a bad file must not stop the node).
"""

from __future__ import annotations

from pathlib import Path

from rclpy.impl.rcutils_logger import RcutilsLogger

from hand_sog_tracker.core.hand_model import HandModel, HandShape, default_hand_model
from hand_sog_tracker.core.hands import HANDS
from hand_sog_tracker.core.model_io import load_hand_shape, side_model_path
from hand_sog_tracker.errors import ModelFileError

__all__ = ["hand_models", "one_hand_model"]


def _read(path: Path, what: str, log: RcutilsLogger) -> tuple[HandShape, bool] | None:
    """The shape in ``path`` and whether it was calibrated on a right hand; None when the file
    does not exist or is invalid (warned about as ``what``)."""
    if not path.exists():
        return None
    try:
        return load_hand_shape(path)
    except ModelFileError as err:
        log.warning(f"ignoring {what}: {err}")
        return None


def _side(right: bool) -> str:
    return "right" if right else "left"


def one_hand_model(path: Path, right: bool, log: RcutilsLogger) -> HandModel | None:
    """The one-hand tracker's model (a ``right`` hand or not) from the user model ``path``, or
    None (the default hand).  A file calibrated on the other hand gives its shape, mirrored."""
    read = _read(path, "the user hand model", log)
    if read is None:
        log.info(f"no usable user hand model at {path}: using the default hand")
        return None
    shape, file_right = read
    if file_right != right:
        log.warning(
            f"{path} was calibrated on a {_side(file_right)} hand; using its shape for the {_side(right)} "
            "hand (handedness parameter)"
        )
    log.info(f"loaded hand model {shape} from {path}")
    return default_hand_model(right).scaled(shape)


def hand_models(path: Path, log: RcutilsLogger) -> dict[str, HandModel | None]:
    """``max_hands: 2``: each hand's model by label (None: the default hand): its own file
    (:func:`~hand_sog_tracker.core.model_io.side_model_path` of ``path``, written by
    ``~/calibrate`` with two hands), else the shape of the user model ``path`` (whichever hand
    it was calibrated on, mirrored onto the other), else None."""
    shared = _read(path, "the user hand model", log)
    out: dict[str, HandModel | None] = {}
    for side in HANDS:
        right = side == "right"
        own = side_model_path(path, side)
        read, where = _read(own, f"the {side} hand's model", log), own
        if read is not None and read[1] != right:
            log.warning(f"{own} was calibrated on a {_side(read[1])} hand; using its shape for the {side} hand")
        if read is None:
            read, where = shared, path
        if read is None:
            log.info(f"no hand model at {own} or {path}: the {side} hand uses the default hand")
            out[side] = None
            continue
        shape, file_right = read
        mirrored = "" if file_right == right else f" (calibrated on the {_side(file_right)} hand)"
        log.info(f"loaded hand model {shape} from {where} for the {side} hand{mirrored}")
        out[side] = default_hand_model(right).scaled(shape)
    return out
