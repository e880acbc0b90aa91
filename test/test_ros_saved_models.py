"""The saved hand models read at the node's start (ros/saved_models.py), with a recording logger."""

from __future__ import annotations

from pathlib import Path

from hand_sog_tracker.core.hand_model import HandShape
from hand_sog_tracker.core.model_io import save_hand_shape, side_model_path
from hand_sog_tracker.ros.saved_models import hand_models, one_hand_model


class _Log:
    def __init__(self) -> None:
        self.lines: list[tuple[str, str]] = []

    def info(self, text: str) -> None:
        self.lines.append(("info", text))

    def warning(self, text: str) -> None:
        self.lines.append(("warning", text))

    def said(self, level: str, words: str) -> bool:
        return any(lv == level and words in text for lv, text in self.lines)


SMALL = HandShape(0.9, 0.92, 1.0, 0.95)
LARGE = HandShape(1.1, 1.08, 1.0, 1.02)


def test_the_one_hand_model_is_the_files_shape_on_the_tracked_side(tmp_path: Path) -> None:
    path = tmp_path / "hand_model.yaml"
    log = _Log()
    assert one_hand_model(path, True, log) is None and log.said("info", "using the default hand")
    save_hand_shape(path, SMALL, right=False)
    model = one_hand_model(path, True, log)
    assert model is not None and model.shape == SMALL and model.right
    assert log.said("warning", "calibrated on a left hand") and log.said("info", "loaded hand model")
    path.write_text("length: [not a number\n", encoding="utf-8")
    log = _Log()
    assert one_hand_model(path, True, log) is None
    assert log.said("warning", "ignoring the user hand model") and log.said("info", "using the default hand")


def test_each_hand_takes_its_own_file_else_the_user_model_else_the_default(tmp_path: Path) -> None:
    path = tmp_path / "hand_model.yaml"
    log = _Log()
    assert hand_models(path, log) == {"left": None, "right": None}
    save_hand_shape(path, SMALL, right=True)
    save_hand_shape(side_model_path(path, "left"), LARGE, right=True)
    log = _Log()
    models = hand_models(path, log)
    assert models["right"] is not None and models["right"].shape == SMALL and models["right"].right
    assert models["left"] is not None and models["left"].shape == LARGE and not models["left"].right
    assert log.said("warning", "hand_model_left.yaml was calibrated on a right hand")
    assert log.said("info", f"from {path} for the right hand")
