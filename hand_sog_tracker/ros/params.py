"""ROS parameters of the tracker node: specs, descriptors, validation, freezing.

Every tunable of :class:`~hand_sog_tracker.core.types.TrackerConfig` becomes a
parameter of the same name (units in the name), except ``right_hand`` which is
the string parameter ``handedness`` (``right`` / ``left``).  Node-only
parameters: ``user_model_path``, ``debug_image``, ``calibration_frames``,
``auto_calibrate``, ``input_transport``, ``publish_wrist_joints``, ``publish_tf``,
``frame_prefix``, ``max_image_pixels``, ``frame_budget_ms`` and ``max_lag_ms``.

The values are validated as a whole by building a :class:`NodeSettings` (which
builds a ``TrackerConfig``), both at start-up and in the on-set callback, so a
rejected change names the reason (e.g. ``need 0 < near_mm < far_mm``).  A start-up value of
the wrong type (``-p near_mm:=abc``, ``-p far_mm:=800`` for a double, ``-p iterations:=7.5``)
is one :class:`~hand_sog_tracker.errors.InputError` naming the parameter, the value and the
type expected (:func:`declare_node_parameters`), not a traceback.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Union

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
    SetParametersResult,
)
from rclpy.exceptions import InvalidParameterTypeException
from rclpy.node import Node
from rclpy.parameter import Parameter

from hand_sog_tracker.compressed_depth import MAX_IMAGE_PIXELS
from hand_sog_tracker.core.model_io import default_model_path
from hand_sog_tracker.core.types import TrackerConfig
from hand_sog_tracker.errors import InputError

__all__ = [
    "ParamSpec",
    "NodeSettings",
    "PARAM_SPECS",
    "PARAM_NAMES",
    "settings_from_values",
    "tf_available",
    "declare_node_parameters",
    "read_settings",
    "validate_parameter_change",
    "params_yaml",
]

Value = Union[bool, int, float, str]


@dataclass(frozen=True)
class ParamSpec:
    """One node parameter.

    Attributes
    ----------
    name : str
    default : bool, int, float or str
        Also fixes the parameter type.
    description : str
        Shown by ``ros2 param describe``; states the unit.
    low, high : int or float, optional
        Inclusive range (both or neither), enforced by rclpy itself.
    read_only : bool
        Settable only at start-up (params file, ``-p``).
    choices : tuple of str
        Allowed values of a string parameter (checked by :func:`settings_from_values`).
    """

    name: str
    default: Value
    description: str
    low: float | None = None
    high: float | None = None
    read_only: bool = False
    choices: tuple[str, ...] = ()

    def descriptor(self) -> ParameterDescriptor:
        """The ``rcl_interfaces/ParameterDescriptor`` of this parameter."""
        d = ParameterDescriptor(description=self.description, read_only=self.read_only)
        d.type = _param_type(self.default)
        if self.choices:
            d.additional_constraints = "one of: " + ", ".join(self.choices)
        if self.low is not None and self.high is not None:
            if isinstance(self.default, bool):
                raise TypeError(f"bool parameter {self.name} cannot have a range")
            if isinstance(self.default, int):
                d.integer_range = [IntegerRange(from_value=int(self.low), to_value=int(self.high), step=1)]
            else:
                d.floating_point_range = [
                    FloatingPointRange(from_value=float(self.low), to_value=float(self.high), step=0.0)
                ]
        return d


def _param_type(value: Value) -> int:
    if isinstance(value, bool):
        return ParameterType.PARAMETER_BOOL
    if isinstance(value, int):
        return ParameterType.PARAMETER_INTEGER
    if isinstance(value, float):
        return ParameterType.PARAMETER_DOUBLE
    return ParameterType.PARAMETER_STRING


# Descriptions and ranges of the TrackerConfig fields; an unknown future field still becomes a
# parameter (with a generic description and no range).
_TRACKER_META: dict[str, tuple[str, float | None, float | None]] = {
    "near_mm": ("Depth below this is ignored (mm).", 10.0, 5000.0),
    "far_mm": ("Depth beyond this is ignored (mm); must exceed near_mm.", 20.0, 10000.0),
    "quadtree_threshold_mm": (
        "Quadtree split threshold: a cell whose depth range exceeds this is split (mm).", 1.0, 200.0),
    "min_quad_px": (
        "Smallest quadtree leaf side at processing resolution (px): 2, 4 or 8; halved for a far hand.", 2, 8),
    "median_kernel": ("Median filter size on the depth image: 0 or 1 = off, 3 or 5.", 0, 5),
    "max_width_px": ("Wider images are decimated to at most this width first (px).", 80, 4096),
    "min_focal_px": (
        "... but not below this focal length at the processing resolution (px; 0 = off): "
        "a wide-angle camera keeps more pixels.", 0.0, 10000.0),
    "iterations": ("Gradient-ascent iterations per frame.", 1, 200),
    "refine_iterations": (
        "Iterations refining the answer of a frame with a curled finger on the model with joint Gaussians "
        "(0 = off: about 1-1.5 ms less on such frames).", 0, 50),
    "w_col": ("Weight of the self-collision term.", 0.0, 100.0),
    "w_dan": ("Weight of the dangling-Gaussian term (model parts far from any data).", 0.0, 100.0),
    "w_lim": ("Weight of the joint-limit term.", 0.0, 100.0),
    "w_smo": ("Weight of the temporal smoothness term.", 0.0, 100.0),
    "w_ord": ("Weight of the finger-order term (neighbouring fingers may not cross).", 0.0, 100.0),
    "w_sal": ("Weight of the salient-point term (fingertip detections pull fingertips).", 0.0, 100.0),
    "w_sil": ("Weight of the silhouette term (model parts outside the hand's pixels).", 0.0, 100.0),
    "w_cpl": ("Weight of the DIP-PIP coupling term (a DIP flexed beyond 2/3 of its PIP costs).", 0.0, 100.0),
    "w_curl": ("Weight of the finger curl term (PIP + DIP flexed beyond 165 degrees costs).", 0.0, 100.0),
    "roi_radius_mm": ("Depth data farther than this from the last hand centre is ignored (mm).", 20.0, 1000.0),
    "lost_confidence": ("Confidence below this for lost_frames frames means the track is lost.", 0.0, 1.0),
    "lost_frames": ("Consecutive low-confidence frames before the track is declared lost.", 1, 1000),
    "init_hypotheses": ("Starting poses tried when (re)initialising.", 1, 256),
}


def _tracker_specs() -> tuple[ParamSpec, ...]:
    defaults = TrackerConfig()
    specs = []
    for f in dataclasses.fields(TrackerConfig):
        if f.name == "right_hand":
            specs.append(
                ParamSpec(
                    "handedness",
                    "right" if defaults.right_hand else "left",
                    "Which hand is tracked: right or left.",
                    choices=("right", "left"),
                )
            )
            continue
        default = getattr(defaults, f.name)
        desc, low, high = _TRACKER_META.get(f.name, (f"Tracker setting {f.name}.", None, None))
        if isinstance(default, int) and not isinstance(default, bool):
            low = None if low is None else int(low)
            high = None if high is None else int(high)
        specs.append(ParamSpec(f.name, default, desc, low, high))
    return tuple(specs)


#: All parameters of the node, in declaration order.
PARAM_SPECS: tuple[ParamSpec, ...] = _tracker_specs() + (
    ParamSpec(
        "user_model_path",
        "",
        "Calibrated hand model file (read at start-up, written by ~/calibrate); "
        "empty = $ROS_HOME/hand_sog_tracker/hand_model.yaml (ROS_HOME defaults to ~/.ros). "
        "With max_hands 2 ~/calibrate writes each hand's own file beside it (<stem>_left.yaml, "
        "<stem>_right.yaml), read first for that hand.",
        read_only=True,
    ),
    ParamSpec(
        "debug_image",
        False,
        "Always render /hand/debug_image (otherwise only while someone subscribes).",
    ),
    ParamSpec(
        "calibration_frames",
        3,
        "Number of most recent depth frames the ~/calibrate service fits the hand model to.",
        1,
        3,
    ),
    ParamSpec(
        "auto_calibrate",
        True,
        "Fit the hand model by itself once, about half a second after tracking starts, with the fit and "
        "guard of ~/calibrate (kept in memory, not saved); off while a saved user model is in use.",
    ),
    ParamSpec(
        "input_transport",
        "raw",
        "How depth images arrive: raw = sensor_msgs/Image on camera/depth/image_rect_raw; "
        "compressedDepth = sensor_msgs/CompressedImage on camera/depth/image_rect_raw/compressedDepth "
        "(compressed_depth_image_transport, png or rvl).",
        read_only=True,
        choices=("raw", "compressedDepth"),
    ),
    ParamSpec(
        "publish_wrist_joints",
        False,
        "Append the six virtual wrist joints hand_tx, hand_ty, hand_tz (m) and hand_rz, hand_rx, hand_ry "
        "(rad) to hand/joint_states; hand/robot_description then starts at the image frame.",
    ),
    ParamSpec(
        "publish_tf",
        False,
        "Broadcast the hand on /tf: hand_wrist in the image frame, every link of hand/robot_description "
        "and the <finger>_fingertip frames (needs the tf2_msgs package).",
    ),
    ParamSpec(
        "frame_prefix",
        "",
        "Put in front of every frame the node names: the TF frames and the links of hand/robot_description "
        "(e.g. left_ for a second tracker); the image frame and the joint names keep theirs.",
        read_only=True,
    ),
    ParamSpec(
        "max_hands",
        1,
        "Hands tracked at most: 1 = one hand of the handedness parameter; 2 = up to two hands, each "
        "labelled left or right from the data, on hand/left/... and hand/right/... (the one-hand topics "
        "then carry the hand labelled with handedness).",
        1,
        2,
        read_only=True,
    ),
    ParamSpec(
        "max_image_pixels",
        MAX_IMAGE_PIXELS,
        "Depth images of more pixels (width x height) are rejected before they are converted or "
        "decoded (a compressed image by the size its header declares).",
        10_000,
        50_000_000,
    ),
    ParamSpec(
        "frame_budget_ms",
        200.0,
        "Time budget of one frame (ms): a frame that takes longer is warned about and counted "
        "in /diagnostics (frames_cut); its search is never cut, the frames that arrive meanwhile "
        "are dropped whole.",
        10.0,
        10000.0,
    ),
    ParamSpec(
        "max_lag_ms",
        200.0,
        "Longest backlog of images (ms, by their header stamps) the node catches up on: images are "
        "tracked in order, and the oldest are dropped whole (frames_dropped) only when the newest "
        "received image is more than this ahead of them. 0 = track only the newest image.",
        0.0,
        5000.0,
    ),
)
PARAM_NAMES: tuple[str, ...] = tuple(s.name for s in PARAM_SPECS)
_SPEC_BY_NAME = {s.name: s for s in PARAM_SPECS}


@dataclass(frozen=True)
class NodeSettings:
    """All parameters of the node, validated and frozen.

    Attributes
    ----------
    tracker : TrackerConfig
        Handed to the core tracker.
    user_model_path : Path
        Expanded path of the user hand-model file.
    debug_image : bool
    calibration_frames : int
    auto_calibrate : bool
    input_transport : {"raw", "compressedDepth"}
    publish_wrist_joints : bool
    publish_tf : bool
    frame_prefix : str
    max_hands : int
    max_image_pixels : int
    frame_budget_ms : float
    max_lag_ms : float
    """

    tracker: TrackerConfig
    user_model_path: Path
    debug_image: bool
    calibration_frames: int
    auto_calibrate: bool = True
    input_transport: str = "raw"
    publish_wrist_joints: bool = False
    publish_tf: bool = False
    frame_prefix: str = ""
    max_hands: int = 1
    max_image_pixels: int = MAX_IMAGE_PIXELS
    frame_budget_ms: float = 200.0
    max_lag_ms: float = 200.0


#: Characters a frame prefix may hold (those of ROS names and TF frame ids).
_FRAME_CHARS = frozenset("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_/")


def tf_available() -> bool:
    """Whether the ``tf2_msgs`` Python package (needed by ``publish_tf``) is importable."""
    try:
        return importlib.util.find_spec("tf2_msgs") is not None
    except (ImportError, ValueError):
        return False


def settings_from_values(values: Mapping[str, Any]) -> NodeSettings:
    """Validate a full set of parameter values and freeze them.

    Parameters
    ----------
    values : mapping
        Name -> value for every name in :data:`PARAM_NAMES` (missing names take
        their defaults; unknown names are ignored).

    Raises
    ------
    InputError
        A value has the wrong type, is out of range or the combination is
        invalid; the message names the parameter.
    """
    v = {s.name: values.get(s.name, s.default) for s in PARAM_SPECS}
    for s in PARAM_SPECS:
        x = v[s.name]
        expected = type(s.default)
        ok = isinstance(x, expected) and not (expected is not bool and isinstance(x, bool))
        if expected is float and isinstance(x, int) and not isinstance(x, bool):
            x = v[s.name] = float(x)
            ok = True
        if not ok:
            raise InputError(f"parameter {s.name} must be {expected.__name__}, got {x!r}")
        if s.low is not None and s.high is not None and not (s.low <= x <= s.high):
            raise InputError(f"parameter {s.name}={x!r} is outside [{s.low}, {s.high}]")
        if s.choices and x not in s.choices:
            raise InputError(f"parameter {s.name} must be one of {', '.join(s.choices)}, got {x!r}")
    tracker_kwargs = {
        f.name: v[f.name] for f in dataclasses.fields(TrackerConfig) if f.name != "right_hand"
    }
    tracker_kwargs["right_hand"] = v["handedness"] == "right"
    tracker = TrackerConfig(**tracker_kwargs)  # raises InputError naming the problem
    if v["publish_tf"] and not tf_available():
        raise InputError(
            "parameter publish_tf=true needs the tf2_msgs Python package, which is not installed here "
            "(install ros-jazzy-tf2-msgs / source a ROS installation); use hand/pose instead"
        )
    bad = sorted(set(v["frame_prefix"]) - _FRAME_CHARS)
    if bad:
        raise InputError(f"parameter frame_prefix may hold letters, digits, _ and / only, got {v['frame_prefix']!r}")
    path = Path(v["user_model_path"]).expanduser() if v["user_model_path"] else default_model_path()
    return NodeSettings(
        tracker=tracker,
        user_model_path=path,
        debug_image=bool(v["debug_image"]),
        calibration_frames=int(v["calibration_frames"]),
        auto_calibrate=bool(v["auto_calibrate"]),
        input_transport=str(v["input_transport"]),
        publish_wrist_joints=bool(v["publish_wrist_joints"]),
        publish_tf=bool(v["publish_tf"]),
        frame_prefix=str(v["frame_prefix"]),
        max_hands=int(v["max_hands"]),
        max_image_pixels=int(v["max_image_pixels"]),
        frame_budget_ms=float(v["frame_budget_ms"]),
        max_lag_ms=float(v["max_lag_ms"]),
    )


def declare_node_parameters(node: Node) -> NodeSettings:
    """Declare every parameter in one batch (overrides applied) and return the settings.

    Raises
    ------
    InputError
        The start-up values (params file, ``-p``, ``parameter_overrides``) are invalid, or of
        the wrong type (one line naming the parameter, the value and the type expected).
    rclpy.exceptions.InvalidParameterValueException
        A value is outside a descriptor range.
    """
    try:
        node.declare_parameters("", [(s.name, s.default, s.descriptor()) for s in PARAM_SPECS])
    except InvalidParameterTypeException as err:
        raise InputError(_type_mistake(err)) from None
    return read_settings(node)


_TYPE_NAMES = {bool: "a boolean (true or false)", int: "an integer", float: "a double", str: "a string"}


_TYPE_MISTAKE = re.compile(r"parameter '(?P<name>[^']*)' to '(?P<value>.*)' of type '(?P<type>\w+)'", re.S)


def _type_mistake(err: InvalidParameterTypeException) -> str:
    """One line for a start-up value of the wrong type: the parameter, the value, what it must be.

    (rclpy 7.1's exception keeps neither the parameter nor the value: they are read from its
    message, which is used as it is when it cannot be read.)
    """
    found = _TYPE_MISTAKE.search(str(err))
    spec = _SPEC_BY_NAME.get(found["name"]) if found else None
    if found is None or spec is None:
        return str(err)
    value, expected = found["value"], type(spec.default)
    hint = ""
    if expected is float and found["type"] == "INTEGER":
        hint = f" (write {value}.0)"
    elif expected is str:
        hint = f' (quote it: {spec.name}:="\'{value}\'")'
    return f"parameter {spec.name} must be {_TYPE_NAMES[expected]}{hint}, got {found['type'].lower()} {value!r}"


def read_settings(node: Node) -> NodeSettings:
    """Freeze the node's current parameter values into :class:`NodeSettings`."""
    return settings_from_values({p.name: p.value for p in node.get_parameters(PARAM_NAMES)})


def validate_parameter_change(node: Node, changed: list[Parameter]) -> SetParametersResult:
    """On-set callback body: accept ``changed`` only if the resulting settings are valid.

    Parameters that are not ours (``use_sim_time``, QoS overrides) are accepted untouched.
    """
    mine = [p for p in changed if p.name in _SPEC_BY_NAME]
    if not mine:
        return SetParametersResult(successful=True)
    values = {p.name: p.value for p in node.get_parameters(PARAM_NAMES)}
    for p in mine:
        values[p.name] = p.value
    try:
        settings_from_values(values)
    except InputError as err:
        return SetParametersResult(successful=False, reason=str(err))
    return SetParametersResult(successful=True)


def _yaml_value(value: Value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, int):
        return str(value)
    return f'"{value}"'


def params_yaml(node_name: str = "/**") -> str:
    """A ROS 2 params file with every parameter at its default.

    Keyed ``/**`` (any node name, any namespace) by default: a file keyed by the node's name
    is ignored once the node runs in a namespace (``-r __ns:=/robot``).

    ``config/hand_sog_tracker.yaml`` is this text (a test checks it); regenerate it with
    ``python -m hand_sog_tracker.ros.params > config/hand_sog_tracker.yaml``.
    """
    lines = [
        "# Parameters of the hand_sog_tracker node (all of them, at their defaults).",
        "# ros2 run hand_sog_tracker tracker_node --ros-args --params-file <this file>",
        f"{node_name}:",
        "  ros__parameters:",
    ]
    for s in PARAM_SPECS:
        rng = f" [{s.low} .. {s.high}]" if s.low is not None else ""
        ro = " (read-only)" if s.read_only else ""
        lines.append(f"    # {s.description}{rng}{ro}")
        lines.append(f"    {s.name}: {_yaml_value(s.default)}")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":  # regenerate the shipped file: python -m hand_sog_tracker.ros.params
    import sys

    sys.stdout.write(params_yaml())
