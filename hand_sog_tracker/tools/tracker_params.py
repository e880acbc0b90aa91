"""Tracker settings for the tools: the node's params YAML, ``--set name=value``, ``--handedness``.

The tools take the same parameters as ``tracker_node`` (see
:mod:`hand_sog_tracker.ros.params` and ``config/hand_sog_tracker.yaml``):

* :func:`read_params_file` reads a ROS 2 params file (``<node>: ros__parameters:
  {...}``; blocks for ``/**`` and for any node named ``hand_sog_tracker`` are
  merged, in file order; a file with a single block is used whatever its node
  name).  ``use_sim_time`` and ``qos_overrides`` are ignored;
* :func:`parse_set` parses ``name=value`` items, typed like the parameter;
* :func:`tracker_config` validates everything as the node does and returns the
  core :class:`~hand_sog_tracker.core.types.TrackerConfig`;
* :func:`core_settings`: ``--set`` items of a tool that renders its own hands (no
  handedness, no node-only parameter), validated.

YAML is read with ``ruamel.yaml`` (installed with ``rosbags``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Sequence, Union

from hand_sog_tracker.core.types import TrackerConfig
from hand_sog_tracker.errors import InputError

__all__ = [
    "core_settings", "node_only", "read_params_file", "parse_params_yaml", "parse_set", "parse_value", "tracker_config",
]

Value = Union[bool, int, float, str]

_IGNORED = ("use_sim_time", "qos_overrides")
_NODE_NAME = "hand_sog_tracker"


def _specs() -> dict[str, Any]:
    from hand_sog_tracker.ros.params import PARAM_SPECS

    return {s.name: s for s in PARAM_SPECS}


def node_only(values: Mapping[str, Value]) -> list[str]:
    """Names in ``values`` that only the node uses (``user_model_path``, ``debug_image``, ...):
    not a :class:`TrackerConfig` field (``handedness`` is ``right_hand``)."""
    import dataclasses

    fields = {f.name for f in dataclasses.fields(TrackerConfig)} | {"handedness"}
    return [n for n in values if n not in fields]


def _unknown(name: str, where: str) -> InputError:
    return InputError(f"unknown tracker parameter {name!r} {where}; known: {', '.join(_specs())}")


def parse_params_yaml(text: str, source: str = "params file") -> dict[str, Value]:
    """Parameter values of a ROS 2 params YAML text (see the module docstring).

    Raises
    ------
    InputError
        Not YAML, not a params file, an unknown parameter or a non-scalar value.
    """
    from ruamel.yaml import YAML
    from ruamel.yaml.error import YAMLError

    try:
        doc = YAML(typ="safe", pure=True).load(text)
    except YAMLError as err:
        raise InputError(f"{source}: not valid YAML: {err}") from err
    blocks: list[tuple[str, Any]] = []
    if isinstance(doc, dict):
        blocks = [(str(k), v["ros__parameters"]) for k, v in doc.items()
                  if isinstance(v, dict) and "ros__parameters" in v]
    if not blocks:
        raise InputError(
            f"{source}: not a ROS 2 params file (expected '{_NODE_NAME}:' then 'ros__parameters:' "
            "and the parameters, like config/hand_sog_tracker.yaml)"
        )
    chosen = [b for k, b in blocks if k == "/**" or k.rstrip("/").split("/")[-1] == _NODE_NAME]
    if not chosen and len(blocks) == 1:
        chosen = [blocks[0][1]]
    if not chosen:
        found = ", ".join(k for k, _ in blocks)
        raise InputError(f"{source}: no parameters for '{_NODE_NAME}' or '/**' (found {found})")
    specs = _specs()
    out: dict[str, Value] = {}
    for block in chosen:
        if not isinstance(block, dict):
            raise InputError(f"{source}: 'ros__parameters' must be a mapping")
        for name, value in block.items():
            name = str(name)
            if name in _IGNORED:
                continue
            if name not in specs:
                raise _unknown(name, f"in {source}")
            if not isinstance(value, (bool, int, float, str)):
                raise InputError(f"{source}: parameter {name} must be a single value, got {value!r}")
            out[name] = value
    return out


def read_params_file(path: str | Path) -> dict[str, Value]:
    """Parameter values of the params file at ``path`` (see :func:`parse_params_yaml`).

    Raises
    ------
    InputError
        The file cannot be read or is not a valid params file.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as err:
        raise InputError(f"cannot read params file {p}: {err.strerror or err}") from err
    return parse_params_yaml(text, source=f"params file {p}")


def parse_value(name: str, text: str) -> Value:
    """``text`` as a value of parameter ``name`` (bool: true/false; int; float; str).

    Raises
    ------
    InputError
        Unknown parameter or a value of the wrong type.
    """
    specs = _specs()
    if name not in specs:
        raise _unknown(name, "in --set")
    default = specs[name].default
    t = text.strip()
    try:
        if isinstance(default, bool):
            if t.lower() not in ("true", "false"):
                raise ValueError
            return t.lower() == "true"
        if isinstance(default, int):
            return int(t)
        if isinstance(default, float):
            return float(t)
    except ValueError:
        raise InputError(f"--set {name}={text}: {name} must be {type(default).__name__}") from None
    return text


def parse_set(items: Sequence[str]) -> dict[str, Value]:
    """Parse ``--set name=value`` items (later items win).

    Raises
    ------
    InputError
        An item without ``=``, an unknown name or a badly typed value.
    """
    out: dict[str, Value] = {}
    for item in items:
        name, sep, text = item.partition("=")
        if not sep or not name.strip():
            raise InputError(f"--set expects name=value, got {item!r}")
        out[name.strip()] = parse_value(name.strip(), text)
    return out


def tracker_config(values: Mapping[str, Value]) -> TrackerConfig:
    """Validate ``values`` (node parameter names) as the node does; the core tracker's config.

    Raises
    ------
    InputError
        A value is out of range, of the wrong type, or the combination is invalid.
    """
    from hand_sog_tracker.ros.params import settings_from_values

    return settings_from_values(dict(values)).tracker


def core_settings(items: Sequence[str], hand: str) -> dict[str, Value]:
    """The tracker parameters of ``--set NAME=VALUE`` items for a tool that renders its own
    hands (``render_sets``, ``benchmark``), validated as the node does.

    ``hand`` says why ``handedness`` cannot be set (e.g. "each render draws its own hand").

    Raises
    ------
    InputError
        A bad item (see :func:`parse_set`), ``handedness``, or a parameter only the node uses.
    """
    values = parse_set(items)
    if "handedness" in values:
        raise InputError(f"handedness cannot be set: {hand}")
    other = node_only(values)
    if other:
        raise InputError(f"not a tracker parameter here (the node's only): {', '.join(other)}")
    tracker_config(values)
    return values
