"""The hand on TF: every link of the node's own description, with the node's frame prefix.

The node publishes the URDF of the model it uses (``hand/robot_description``, rebuilt when the
model changes) and, with ``publish_tf``, the transforms of that same description for each
tracked frame, so RViz's RobotModel display (description topic ``hand/robot_description``)
shows the hand the tracker fits, without a ``robot_state_publisher`` and its static file.
"""

from __future__ import annotations

import numpy as np
from geometry_msgs.msg import TransformStamped
from numpy.typing import NDArray
from std_msgs.msg import Header

from hand_sog_tracker.core.rotations import quaternion_from_matrix
from hand_sog_tracker.core.urdf import UrdfJoint, joint_transforms
from hand_sog_tracker.ros.conversions import hand_transforms, joint_state_msg

__all__ = ["description_transforms"]


def _transform(header: Header, parent: str, child: str, xyz: NDArray[np.float64],
               rot: NDArray[np.float64]) -> TransformStamped:
    tf = TransformStamped()
    tf.header.stamp = header.stamp
    tf.header.frame_id = parent
    tf.child_frame_id = child
    t = tf.transform
    t.translation.x, t.translation.y, t.translation.z = (float(v) for v in xyz)
    t.rotation.x, t.rotation.y, t.rotation.z, t.rotation.w = (float(v) for v in quaternion_from_matrix(rot))
    return tf


def description_transforms(
    header: Header,
    joints: tuple[UrdfJoint, ...],
    pose: NDArray[np.float64],
    fingertips_mm: NDArray[np.float64],
    wrist_joints: bool,
    prefix: str = "",
    joint_prefix: str = "",
) -> list[TransformStamped]:
    """The TF frames of one tracked frame.

    Parameters
    ----------
    header : std_msgs/Header
        The input image's stamp and frame.
    joints : tuple of UrdfJoint
        The joints of the published description (``core.urdf.urdf_joints``), links already
        prefixed.
    pose : array, shape (26,)
        The tracked pose (mm, rad).
    fingertips_mm : array, shape (5, 3), mm
        The tracked fingertips (camera frame).
    wrist_joints : bool
        Whether the description starts at the image frame with the six virtual wrist joints;
        otherwise ``<prefix>hand_wrist`` is placed in the image frame directly.
    prefix : str
        The node's ``frame_prefix``.
    joint_prefix : str
        The description's joint-name prefix (``hand_urdf(joint_prefix=...)``).

    Returns
    -------
    list of geometry_msgs/TransformStamped
        The wrist in the image frame (or the virtual joints' links), every joint of the
        description, then ``<prefix><finger>_fingertip`` in ``<prefix>hand_wrist``.
    """
    js = joint_state_msg(header, pose, wrist_joints)
    values = {joint_prefix + n: v for n, v in zip(js.name, js.position)}
    wrist_and_tips = hand_transforms(header, pose, fingertips_mm, prefix)
    out = [] if wrist_joints else [wrist_and_tips[0]]
    for parent, child, xyz, rot in joint_transforms(joints, values):
        out.append(_transform(header, parent, child, xyz, rot))
    return out + wrist_and_tips[1:]
