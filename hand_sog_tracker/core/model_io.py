"""Reading and writing the user's calibrated hand model (a small flat YAML file).

The file stores the four :class:`~hand_sog_tracker.core.hand_model.HandShape`
scale factors, the five per-finger length factors (``finger_thumb`` .. ``finger_little``,
:attr:`~hand_sog_tracker.core.hand_model.HandShape.fingers`; optional when reading: a file
without them, as written before they existed, loads with all five at 1.0) and the handedness,
plus optional flat ``key: value`` extras (e.g. calibration energies)::

    # hand_sog_tracker user hand model
    format: hand_sog_tracker/hand_model
    version: 1
    handedness: right
    length: 1.02
    width: 0.98
    depth: 1.0
    sigma: 1.01
    finger_thumb: 1.0
    finger_index: 1.03
    finger_middle: 1.0
    finger_ring: 0.98
    finger_little: 1.01
    fit_score_before: 0.512
    holdout_score_fitted: 0.861

:func:`calibration_metadata` builds the extras the ``~/calibrate`` service
writes (when, on which frames and poses the model was fitted, and the guard's
numbers); :func:`read_calibration_info` reads them back, old names
(``energy_before``, ``energy_after``, ``frames``) mapped to the new ones.

Only this flat subset of YAML is written and read (scalars, ``#`` comments,
JSON-style double-quoted strings), so no YAML library is needed.  Writes are
atomic: a temporary file in the target directory is renamed over the target.
"""

from __future__ import annotations

import json
import math
import os
import re
import tempfile
import time
from pathlib import Path
from typing import Any, Mapping, Sequence, Union

from hand_sog_tracker.core.hand_model import FINGERS, HandShape
from hand_sog_tracker.errors import InputError, ModelFileError

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "FINGER_KEYS",
    "default_model_path",
    "side_model_path",
    "save_hand_shape",
    "load_hand_shape",
    "read_model_file",
    "calibration_metadata",
    "read_calibration_info",
]

FORMAT_NAME = "hand_sog_tracker/hand_model"
FORMAT_VERSION = 1
_SHAPE_KEYS = ("length", "width", "depth", "sigma")
#: Keys of the per-finger length factors (thumb .. little); optional when reading.
FINGER_KEYS = tuple(f"finger_{f}" for f in FINGERS)
_RESERVED = ("format", "version", "handedness") + _SHAPE_KEYS + FINGER_KEYS
_KEY_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")

Scalar = Union[bool, int, float, str]
PathLike = Union[str, "os.PathLike[str]"]


def default_model_path() -> Path:
    """Default location of the user model: ``$ROS_HOME/hand_sog_tracker/hand_model.yaml``.

    ``ROS_HOME`` defaults to ``~/.ros`` as in ROS 2 itself.
    """
    ros_home = os.environ.get("ROS_HOME") or "~/.ros"
    return Path(ros_home).expanduser() / "hand_sog_tracker" / "hand_model.yaml"


def side_model_path(path: PathLike, side: str) -> Path:
    """The file of one hand's model beside the user model ``path`` with ``max_hands: 2``:
    ``<stem>_<side><suffix>`` (``hand_model.yaml`` -> ``hand_model_left.yaml``), ``~`` expanded.

    Raises
    ------
    InputError
        ``side`` is not ``left`` or ``right``.
    """
    if side not in ("left", "right"):
        raise InputError(f"side must be 'left' or 'right', got {side!r}")
    p = Path(path).expanduser()
    return p.with_name(f"{p.stem}_{side}{p.suffix}")


def _format_value(key: str, value: Scalar) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise InputError(f"extra value {key!r} must be finite, got {value!r}")
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)  # a valid YAML double-quoted scalar, one line
    raise InputError(f"extra value {key!r} must be bool, int, float or str, got {type(value).__name__}")


def save_hand_shape(
    path: PathLike,
    shape: HandShape,
    right: bool,
    extra: Mapping[str, Scalar] | None = None,
) -> Path:
    """Write a hand model file atomically, creating missing directories.

    Parameters
    ----------
    path : str or path-like
        Target file; ``~`` is expanded.
    shape : HandShape
        The four scale factors and the five per-finger length factors (unitless).
    right : bool
        Handedness the shape was calibrated on.
    extra : mapping of str to bool, int, float or str, optional
        Additional flat values (e.g. ``energy_before``); keys must be
        identifiers and must not collide with the reserved keys.

    Returns
    -------
    Path
        The written path (expanded).

    Raises
    ------
    InputError
        Bad extra keys or values.
    ModelFileError
        The file could not be written.
    """
    target = Path(path).expanduser()
    lines = [
        "# hand_sog_tracker user hand model (written by the ~/calibrate service)",
        f"format: {FORMAT_NAME}",
        f"version: {FORMAT_VERSION}",
        f"handedness: {'right' if right else 'left'}",
    ]
    lines += [f"{k}: {float(getattr(shape, k))!r}" for k in _SHAPE_KEYS]
    lines += [f"{k}: {float(v)!r}" for k, v in zip(FINGER_KEYS, shape.fingers)]
    for key, value in (extra or {}).items():
        if not _KEY_RE.match(key) or key in _RESERVED:
            raise InputError(f"invalid or reserved extra key {key!r}")
        lines.append(f"{key}: {_format_value(key, value)}")
    text = "\n".join(lines) + "\n"
    tmp_name: str | None = None
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp_name, target)
        tmp_name = None
    except OSError as err:
        raise ModelFileError(f"cannot write hand model file {target}: {err}") from err
    finally:
        if tmp_name is not None:
            try:
                os.unlink(tmp_name)
            except OSError:
                pass
    return target


def _parse_value(raw: str) -> Scalar:
    if raw.startswith('"'):
        value = json.loads(raw)
        if not isinstance(value, str):
            raise ValueError("quoted value is not a string")
        return value
    if raw.startswith("'") and raw.endswith("'") and len(raw) >= 2:
        return raw[1:-1].replace("''", "'")
    low = raw.lower()
    if low in ("true", "false"):
        return low == "true"
    for conv in (int, float):
        try:
            return conv(raw)
        except ValueError:
            pass
    return raw


def read_model_file(path: PathLike) -> dict[str, Scalar]:
    """Parse a hand model file into a flat dict (no validation of the keys).

    Raises
    ------
    ModelFileError
        Missing, unreadable or syntactically malformed file.
    """
    p = Path(path).expanduser()
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError as err:
        raise ModelFileError(f"hand model file {p} does not exist") from err
    except (OSError, UnicodeDecodeError) as err:
        raise ModelFileError(f"cannot read hand model file {p}: {err}") from err
    out: dict[str, Scalar] = {}
    for lineno, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        key, sep, rest = stripped.partition(":")
        key = key.strip()
        rest = rest.strip()
        if not sep or not _KEY_RE.match(key):
            raise ModelFileError(f"{p}:{lineno}: expected 'key: value', got {line!r}")
        if not rest.startswith(('"', "'")):
            rest = re.split(r"\s+#", rest, maxsplit=1)[0].strip()
        if not rest:
            raise ModelFileError(f"{p}:{lineno}: key {key!r} has no value")
        if key in out:
            raise ModelFileError(f"{p}:{lineno}: duplicate key {key!r}")
        try:
            out[key] = _parse_value(rest)
        except ValueError as err:
            raise ModelFileError(f"{p}:{lineno}: bad value for {key!r}: {err}") from err
    return out


def load_hand_shape(path: PathLike) -> tuple[HandShape, bool]:
    """Load a hand model file written by :func:`save_hand_shape`.

    Parameters
    ----------
    path : str or path-like
        The file; ``~`` is expanded.

    Returns
    -------
    shape : HandShape
        The four scale factors and the per-finger length factors (all 1.0 when the file has
        none of ``finger_thumb`` .. ``finger_little``).
    right : bool
        ``True`` for a right hand.

    Raises
    ------
    ModelFileError
        Missing or malformed file, wrong format or version, missing keys (of the per-finger
        factors: some but not all five), unknown handedness, scale factors outside [0.3, 3.0]
        or per-finger factors outside
        :data:`~hand_sog_tracker.core.hand_model.FINGER_RANGE`.
    """
    p = Path(path).expanduser()
    values = read_model_file(p)
    fmt = values.get("format")
    if fmt != FORMAT_NAME:
        raise ModelFileError(f"{p}: not a hand model file (format {fmt!r}, expected {FORMAT_NAME!r})")
    if values.get("version") != FORMAT_VERSION:
        raise ModelFileError(
            f"{p}: unsupported version {values.get('version')!r} (expected {FORMAT_VERSION})"
        )
    missing = [k for k in ("handedness",) + _SHAPE_KEYS if k not in values]
    if missing:
        raise ModelFileError(f"{p}: missing keys {', '.join(missing)}")
    hand = values["handedness"]
    if hand not in ("right", "left"):
        raise ModelFileError(f"{p}: handedness must be 'right' or 'left', got {hand!r}")
    factors: dict[str, float] = {}
    for k in _SHAPE_KEYS:
        v = values[k]
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ModelFileError(f"{p}: {k} must be a number, got {v!r}")
        factors[k] = float(v)
    present = [k for k in FINGER_KEYS if k in values]
    fingers = [1.0] * len(FINGER_KEYS)
    if present:
        if len(present) != len(FINGER_KEYS):
            missing = [k for k in FINGER_KEYS if k not in values]
            raise ModelFileError(f"{p}: missing keys {', '.join(missing)} (all five per-finger factors or none)")
        for i, k in enumerate(FINGER_KEYS):
            v = values[k]
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise ModelFileError(f"{p}: {k} must be a number, got {v!r}")
            fingers[i] = float(v)
    try:
        shape = HandShape(**factors, fingers=tuple(fingers))  # type: ignore[arg-type]
    except InputError as err:
        raise ModelFileError(f"{p}: {err}") from err
    return shape, hand == "right"


#: Extras written by earlier versions, and their current names.
_OLD_NAMES = {"energy_before": "fit_score_before", "energy_after": "fit_score_after", "frames": "fit_frames"}


def _stamps(stamps_ns: Sequence[int]) -> str:
    return " ".join(f"{int(t) // 10**9}.{int(t) % 10**9:09d}" for t in stamps_ns)


def calibration_metadata(
    result: Any,
    fit_stamps_ns: Sequence[int] = (),
    holdout_stamps_ns: Sequence[int] = (),
) -> dict[str, Scalar]:
    """Flat extras describing a calibration, for :func:`save_hand_shape`.

    Parameters
    ----------
    result : CalibrationResult
        From :func:`hand_sog_tracker.core.calibration.calibrate` (read: ``score_before``,
        ``score_after``, ``seconds``, ``poses``, ``used_frames``, ``validation``).
    fit_stamps_ns, holdout_stamps_ns : sequence of int
        Image stamps (ns) of the frames the model was fitted on / checked on.

    Returns
    -------
    dict
        ``calibrated_at`` (UTC, ISO 8601), ``fit_frames``, ``fit_stamps`` (``sec.nsec``
        separated by spaces), ``fit_pose_<k>`` (the 26 pose values of fit frame ``k``:
        mm, rad), ``fit_score_before`` / ``fit_score_after`` (mean shape score on the fit
        frames), ``fit_seconds`` and, with a guard result, ``holdout_frames``,
        ``holdout_stamps``, ``holdout_score_current`` / ``holdout_score_fitted`` and
        ``guard_margin``.
    """
    out: dict[str, Scalar] = {
        "calibrated_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "fit_frames": len(result.used_frames) if result.used_frames else 1,
        "fit_score_before": float(result.score_before),
        "fit_score_after": float(result.score_after),
        "fit_seconds": round(float(result.seconds), 3),
    }
    if fit_stamps_ns:
        out["fit_stamps"] = _stamps(fit_stamps_ns)
    poses = result.poses if result.poses is not None else [result.pose]
    for k, pose in enumerate(poses):
        out[f"fit_pose_{k}"] = " ".join(f"{float(v):.4g}" for v in pose)
    v = result.validation
    if v is not None:
        out["holdout_frames"] = int(v.frames)
        if holdout_stamps_ns:
            out["holdout_stamps"] = _stamps(holdout_stamps_ns)
        out["holdout_score_current"] = float(v.score_current)
        out["holdout_score_fitted"] = float(v.score_fitted)
        out["guard_margin"] = float(v.margin)
    return out


def read_calibration_info(path: PathLike) -> dict[str, Scalar]:
    """The extras of a hand model file (everything but format, version, handedness, factors).

    Names written by earlier versions are returned under their current names
    (``energy_before`` -> ``fit_score_before``, ``energy_after`` -> ``fit_score_after``,
    ``frames`` -> ``fit_frames``).

    Raises
    ------
    ModelFileError
        Missing, unreadable or malformed file.
    """
    values = read_model_file(path)
    out: dict[str, Scalar] = {}
    for key, value in values.items():
        if key in _RESERVED:
            continue
        if key in _OLD_NAMES and _OLD_NAMES[key] in values:
            continue  # both names present: the current one wins
        out[_OLD_NAMES.get(key, key)] = value
    return out
