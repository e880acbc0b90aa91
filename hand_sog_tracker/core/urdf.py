"""URDF description of a :class:`~hand_sog_tracker.core.hand_model.HandModel` (no ROS needed).

Tree (metres, radians)::

    [camera frame]                          only with ``camera_frame``: six virtual joints
      hand_tx, hand_ty, hand_tz (prismatic along the optical x, y, z)
      hand_rz, hand_rx, hand_ry (revolute; R = Rz(rz) Rx(rx) Ry(ry), the pose's rotation)
    hand_wrist                              the hand frame (x radial, y distal, z palmar)
      <chain>_<first>_abd (revolute, z)     origin = chain base, rpy = rest rotation
        <chain>_base_link                   massless link between the two DOF of the first joint
          <chain>_<first>_flex (revolute, x)
            segment 0 link
              <chain>_<second>_flex (revolute, x) at (0, length0, 0)
                segment 1 link
                  <chain>_<third>_flex (revolute, x) at (0, length1, 0)
                    segment 2 link
                      <chain>_tip_joint (fixed) -> <chain>_tip: the fingertip point the tracker
                      reports (centre of the fingertip sphere)

``<first>`` is ``cmc`` for the thumb and ``mcp`` for the fingers; the 20 revolute joints carry
exactly the names of :data:`~hand_sog_tracker.core.hand_model.JOINT_NAMES` (published on
``hand/joint_states``) and their limits.  This mirrors
:func:`~hand_sog_tracker.core.kinematics.chain_frames`: segment ``s`` of a chain has the
orientation ``R0 @ Rz(abd) @ Rx(flex_1 + ... + flex_{s+1})``.

A left hand (``model.right == False``) is the mirror image (hand x negated) of the right one.
A mirror is not a rigid motion, so the left description is built mirrored instead: every
origin ``p`` becomes ``M p`` and every rotation ``R`` becomes ``M R M`` with ``M = diag(-1, 1,
1)``, and every revolute axis ``a`` becomes ``-M a`` (so the same joint values bend the
mirrored hand the mirrored way).  ``hand_wrist`` of a left hand then has the orientation
published on ``hand/pose`` and its links lie where the tracker's left model puts them.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import Final, Mapping, Sequence
from xml.sax.saxutils import quoteattr

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.hand_model import FINGERS, JOINT_NAMES, HandModel, chain_joint_slice, default_hand_model
from hand_sog_tracker.core.rotations import rpy_from_matrix as rotation_to_rpy  # re-exported

__all__ = [
    "WRIST_LINK",
    "WRIST_JOINT_NAMES",
    "SEGMENT_LINKS",
    "TIP_LINKS",
    "rotation_to_rpy",
    "hand_urdf",
    "UrdfJoint",
    "urdf_joints",
    "joint_transforms",
]

#: The hand frame (origin at the wrist joint).
WRIST_LINK: Final[str] = "hand_wrist"
#: Virtual joints from the camera frame to the wrist, in chain order (metres, radians).
WRIST_JOINT_NAMES: Final[tuple[str, ...]] = ("hand_tx", "hand_ty", "hand_tz", "hand_rz", "hand_rx", "hand_ry")
#: The three segment links of each chain (thumb .. little).
SEGMENT_LINKS: Final[tuple[tuple[str, str, str], ...]] = (
    ("thumb_metacarpal", "thumb_proximal", "thumb_distal"),
    *((f"{f}_proximal", f"{f}_middle", f"{f}_distal") for f in FINGERS[1:]),
)
#: Fingertip links (thumb .. little): the points of ``kinematics.fingertips``.
TIP_LINKS: Final[tuple[str, ...]] = tuple(f"{f}_tip" for f in FINGERS)

_MM: Final[float] = 1e-3


def _num(v: float) -> str:
    s = f"{float(v):.9g}"
    return "0" if s in ("-0", "0") else s


def _vec(v: NDArray[np.float64]) -> str:
    return " ".join(_num(x) for x in v)


class _Builder:
    def __init__(self, right: bool, prefix: str = "", joint_prefix: str = "") -> None:
        self.m = np.diag([1.0 if right else -1.0, 1.0, 1.0])
        self.prefix = prefix
        self.joint_prefix = joint_prefix
        self.camera_frame = ""  # the root link with the virtual wrist joints: never prefixed
        self.lines: list[str] = []

    def frame(self, name: str) -> str:
        return name if name == self.camera_frame else self.prefix + name

    def origin(self, xyz_m: NDArray[np.float64], rot: NDArray[np.float64] | None = None) -> str:
        p = self.m @ np.asarray(xyz_m, dtype=np.float64)
        r = np.eye(3) if rot is None else self.m @ rot @ self.m
        return f'<origin xyz="{_vec(p)}" rpy="{_vec(np.array(rotation_to_rpy(r)))}"/>'

    def axis(self, a: NDArray[np.float64]) -> str:
        v = np.asarray(a, dtype=np.float64)
        if self.m[0, 0] < 0:
            v = -(self.m @ v)
        return f'<axis xyz="{_vec(v)}"/>'

    def link(self, name: str, visual: str = "") -> None:
        name = self.frame(name)
        if visual:
            self.lines += [f"  <link name={quoteattr(name)}>", visual, "  </link>"]
        else:
            self.lines.append(f"  <link name={quoteattr(name)}/>")

    def joint(self, name: str, kind: str, parent: str, child: str, origin: str, extra: tuple[str, ...] = ()) -> None:
        self.lines.append(f"  <joint name={quoteattr(self.joint_prefix + name)} type={quoteattr(kind)}>")
        self.lines.append(f"    <parent link={quoteattr(self.frame(parent))}/>")
        self.lines.append(f"    <child link={quoteattr(self.frame(child))}/>")
        self.lines.append(f"    {origin}")
        self.lines += [f"    {e}" for e in extra]
        self.lines.append("  </joint>")

    def visual(self, geometry: str, origin: str, material: str) -> str:
        return (
            f"    <visual>\n      {origin}\n      <geometry>{geometry}</geometry>\n"
            f"      <material name={quoteattr(material)}/>\n    </visual>"
        )


def hand_urdf(
    model: HandModel | None = None, camera_frame: str | None = None, name: str = "hand", prefix: str = "",
    joint_prefix: str = "",
) -> str:
    """URDF text of a hand model.

    Parameters
    ----------
    model : HandModel, optional
        Default: the unscaled right hand.  Calibrated models (``HandShape``) and left hands
        are described exactly (see the module docstring for the mirror).
    camera_frame : str, optional
        If given, the root link is this frame (the depth image's optical frame) and six
        virtual joints :data:`WRIST_JOINT_NAMES` lead from it to ``hand_wrist``; otherwise the
        root is ``hand_wrist``.
    name : str
        The robot name.
    prefix : str
        Put in front of every link name of the hand (``<prefix>hand_wrist`` ...), not of
        ``camera_frame`` nor of the joint names: the node's ``frame_prefix``, so that two
        trackers' frames never clash.
    joint_prefix : str
        Put in front of every joint name (``left_`` for the left hand of two, whose
        ``hand/left/joint_states`` carry the same names).

    Returns
    -------
    str
        The URDF document (UTF-8 text ending in a newline).
    """
    model = model or default_hand_model()
    b = _Builder(model.right, prefix, joint_prefix)
    side = "right" if model.right else "left"
    shape = model.shape
    b.lines += [
        '<?xml version="1.0"?>',
        "<!-- Generated by hand_sog_tracker.core.urdf.hand_urdf: do not edit. -->",
        f"<!-- {side} hand, HandShape(length={shape.length:g}, width={shape.width:g}, "
        f"depth={shape.depth:g}, sigma={shape.sigma:g}"
        + ("" if shape.uniform_fingers else ", fingers=(" + ", ".join(f"{v:g}" for v in shape.fingers) + ")")
        + "); metres, radians. -->",
        f"<robot name={quoteattr(name)}>",
        '  <material name="skin"><color rgba="0.93 0.75 0.62 1"/></material>',
        '  <material name="tip"><color rgba="0.9 0.2 0.2 1"/></material>',
    ]
    if camera_frame:
        b.camera_frame = camera_frame
        b.link(camera_frame)
        parent = camera_frame
        axes = {"x": np.array([1.0, 0, 0]), "y": np.array([0, 1.0, 0]), "z": np.array([0, 0, 1.0])}
        for jname in WRIST_JOINT_NAMES:
            child = WRIST_LINK if jname == WRIST_JOINT_NAMES[-1] else f"{jname}_link"
            if child != WRIST_LINK:
                b.link(child)
            prismatic = jname[-2] == "t"
            # Virtual joints act in the camera frame: never mirrored.
            extra = (
                f'<axis xyz="{_vec(axes[jname[-1]])}"/>',
                '<limit lower="-10" upper="10" effort="0" velocity="10"/>' if prismatic else "",
            )
            b.joint(
                jname, "prismatic" if prismatic else "continuous", parent, child,
                '<origin xyz="0 0 0" rpy="0 0 0"/>', tuple(e for e in extra if e),
            )
            parent = child
    # Palm: a box from the wrist to the knuckles, as thick as the palm Gaussians.
    palm = model.g_chain < 0
    lo, hi = model.g_offsets[palm].min(axis=0), model.g_offsets[palm].max(axis=0)
    sig = float(model.g_sigmas[palm].mean())
    size = np.array([hi[0] - lo[0] + 2 * sig, hi[1] - lo[1] + 2 * sig, 2 * sig]) * _MM
    centre = np.array([(hi[0] + lo[0]) / 2, (hi[1] + lo[1]) / 2, 0.0]) * _MM
    b.link(WRIST_LINK, b.visual(f'<box size="{_vec(size)}"/>', b.origin(centre), "skin"))
    # Cylinders lie along z in URDF; Rx(pi/2) lays that axis along the segment (y).
    along_y = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    for c in range(5):
        first = "cmc" if c == 0 else "mcp"
        names = JOINT_NAMES[chain_joint_slice(c)]  # flex1, abd, flex2, flex3
        lows, highs = model.limits_low[chain_joint_slice(c)], model.limits_high[chain_joint_slice(c)]
        limits = [
            f'<limit lower="{_num(lo)}" upper="{_num(hi)}" effort="0" velocity="10"/>' for lo, hi in zip(lows, highs)
        ]

        base_link = f"{FINGERS[c]}_{first}_link"
        b.link(base_link)
        b.joint(
            names[1], "revolute", WRIST_LINK, base_link,
            b.origin(model.bases[c] * _MM, model.rest_rotations[c]), (b.axis(np.array([0, 0, 1.0])), limits[1]),
        )
        parent = base_link
        seg_sigma = [
            float(model.g_sigmas[(model.g_chain == c) & (model.g_segment == s)].mean()) for s in range(3)
        ]
        for s, (jk, link) in enumerate(zip((0, 2, 3), SEGMENT_LINKS[c])):
            length = float(model.lengths[c, s])
            cyl = b.visual(
                f'<cylinder radius="{_num(seg_sigma[s] * _MM)}" length="{_num(length * _MM)}"/>',
                b.origin(np.array([0.0, length / 2, 0.0]) * _MM, along_y),
                "skin",
            )
            b.link(link, cyl)
            offset = np.zeros(3) if s == 0 else np.array([0.0, model.lengths[c, s - 1], 0.0]) * _MM
            b.joint(names[jk], "revolute", parent, link, b.origin(offset), (b.axis(np.array([1.0, 0, 0])), limits[jk]))
            parent = link
        tip = int(model.tip_index[c])
        r = float(model.g_sigmas[tip])
        b.link(TIP_LINKS[c], b.visual(f'<sphere radius="{_num(r * _MM)}"/>', b.origin(np.zeros(3)), "tip"))
        b.joint(f"{FINGERS[c]}_tip_joint", "fixed", parent, TIP_LINKS[c], b.origin(model.g_offsets[tip] * _MM))
    b.lines.append("</robot>")
    return "\n".join(b.lines) + "\n"


@dataclass(frozen=True)
class UrdfJoint:
    """One joint of a URDF tree, as :func:`joint_transforms` needs it.

    Attributes
    ----------
    name, kind, parent, child : str
        ``kind`` is ``revolute``, ``continuous``, ``prismatic`` or ``fixed``.
    xyz : array, shape (3,), m
        Origin of the child frame in the parent frame (at joint value 0).
    rot : array, shape (3, 3)
        Rotation of the origin (URDF ``rpy``: ``R = Rz(y) Ry(p) Rx(r)``).
    axis : array, shape (3,)
        Unit joint axis in the child frame (zeros for a fixed joint).
    """

    name: str
    kind: str
    parent: str
    child: str
    xyz: NDArray[np.float64]
    rot: NDArray[np.float64]
    axis: NDArray[np.float64]


def _axis_rotation(axis: NDArray[np.float64], q: float) -> NDArray[np.float64]:
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + math.sin(q) * k + (1.0 - math.cos(q)) * (k @ k)


def urdf_joints(text: str) -> tuple[UrdfJoint, ...]:
    """The joints of a URDF document, parents before children (document order).

    Raises
    ------
    ValueError
        The text is not a URDF with ``origin`` elements on every joint.
    """
    out = []
    for j in ET.fromstring(text).findall("joint"):
        o = j.find("origin")
        parent, child = j.find("parent"), j.find("child")
        if o is None or parent is None or child is None:
            raise ValueError(f"URDF joint {j.get('name')!r} lacks origin, parent or child")
        roll, pitch, yaw = (float(v) for v in o.get("rpy", "0 0 0").split())
        rot = _axis_rotation(np.array([0.0, 0, 1]), yaw) @ _axis_rotation(np.array([0.0, 1, 0]), pitch)
        rot = rot @ _axis_rotation(np.array([1.0, 0, 0]), roll)
        ax = j.find("axis")
        axis = np.zeros(3) if j.get("type") == "fixed" else np.array(
            [float(v) for v in (ax.get("xyz", "1 0 0") if ax is not None else "1 0 0").split()]
        )
        norm = float(np.linalg.norm(axis))
        out.append(UrdfJoint(
            str(j.get("name")), str(j.get("type")), str(parent.get("link")), str(child.get("link")),
            np.array([float(v) for v in o.get("xyz", "0 0 0").split()]), rot, axis / norm if norm else axis,
        ))
    return tuple(out)


def joint_transforms(
    joints: Sequence[UrdfJoint], values: Mapping[str, float]
) -> list[tuple[str, str, NDArray[np.float64], NDArray[np.float64]]]:
    """Parent-to-child transform of every joint at the given joint values (what
    ``robot_state_publisher`` puts on TF).

    Parameters
    ----------
    joints : sequence of UrdfJoint
        From :func:`urdf_joints`.
    values : mapping
        Joint name -> position (rad, or m for a prismatic joint); a missing joint is at 0.

    Returns
    -------
    list of (parent, child, translation, rotation)
        ``translation`` shape (3,) in m, ``rotation`` shape (3, 3): the child frame in the parent.
    """
    out = []
    for j in joints:
        q = float(values.get(j.name, 0.0))
        xyz, rot = j.xyz, j.rot
        if j.kind in ("revolute", "continuous"):
            rot = rot @ _axis_rotation(j.axis, q)
        elif j.kind == "prismatic":
            xyz = xyz + rot @ (j.axis * q)
        out.append((j.parent, j.child, xyz, rot))
    return out


def main(argv: list[str] | None = None) -> int:
    """``python -m hand_sog_tracker.core.urdf [--model FILE] [--left] [--camera-frame F]``: print a URDF.

    Without arguments it prints ``urdf/hand.urdf`` (regenerate the shipped file with
    ``python -m hand_sog_tracker.core.urdf > urdf/hand.urdf``).
    """
    import argparse
    import sys

    from hand_sog_tracker.core.model_io import load_hand_shape
    from hand_sog_tracker.errors import HandSogError

    parser = argparse.ArgumentParser(
        prog="python -m hand_sog_tracker.core.urdf",
        description="Print the URDF of the hand model (default: the unscaled right hand, as urdf/hand.urdf).",
    )
    parser.add_argument("--model", metavar="FILE", help="calibrated hand model file (saved by ~/calibrate)")
    parser.add_argument("--left", action="store_true", help="a left hand (mirrored)")
    parser.add_argument("--camera-frame", metavar="F", help="root the tree at F with the six virtual wrist joints")
    args = parser.parse_args(argv)
    model = default_hand_model(not args.left)
    if args.model:
        try:
            shape, _ = load_hand_shape(args.model)
        except HandSogError as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
        model = model.scaled(shape)
    sys.stdout.write(hand_urdf(model, camera_frame=args.camera_frame))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
