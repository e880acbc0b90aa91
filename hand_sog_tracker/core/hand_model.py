"""Kinematic skeleton and Sum-of-Gaussians volume of the hand (paper 000, sec. 4.2).

Units: millimetres for every length, radians for every angle.

Hand frame (right hand): origin at the wrist joint, ``x`` points across the
palm toward the thumb side (radial), ``y`` points along the middle finger
(distal), ``z`` is the palmar normal (out of the palm).  Flexion is a positive
rotation about a segment's local ``x`` axis (it bends the finger toward the
palm), abduction a rotation about the segment's local ``z`` axis.

Pose vector (26,): ``tx ty tz`` (mm, camera optical frame), ``rx ry rz``
(rad, global rotation ``R = Rz(rz) @ Rx(rx) @ Ry(ry)``), then for each chain in
the order thumb, index, middle, ring, little: ``flex1 abd flex2 flex3``
(thumb: CMC flexion, CMC abduction, MCP flexion, IP flexion; fingers: MCP
flexion, MCP abduction, PIP flexion, DIP flexion).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Final, Sequence

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.rotations import rot_x, rot_y, rot_z  # re-exported
from hand_sog_tracker.errors import InputError

__all__ = [
    "FINGERS",
    "JOINT_NAMES",
    "PARAM_NAMES",
    "N_PARAMS",
    "N_JOINTS",
    "FLEX1",
    "ABD",
    "FLEX2",
    "FLEX3",
    "CHAIN_JOINTS",
    "FIRST_JOINT",
    "JOINTS",
    "FINGER_ABD",
    "FINGER_PIP",
    "FINGER_DIP",
    "FINGER_MCP",
    "chain_slice",
    "chain_joint_slice",
    "FINGER_RANGE",
    "UNIFORM_FINGERS",
    "KEYPOINT_OFFSETS_MM",
    "KEYPOINT_FACING_MM",
    "HandShape",
    "HandModel",
    "default_hand_model",
    "rest_pose",
    "rot_x",
    "rot_y",
    "rot_z",
]

FINGERS: Final[tuple[str, ...]] = ("thumb", "index", "middle", "ring", "little")
_THUMB_JOINTS: Final = ("cmc_flex", "cmc_abd", "mcp_flex", "ip_flex")
_FINGER_JOINTS: Final = ("mcp_flex", "mcp_abd", "pip_flex", "dip_flex")

#: The 20 joint-angle names, in pose-vector order (published on JointState).
JOINT_NAMES: Final[tuple[str, ...]] = tuple(
    f"thumb_{j}" for j in _THUMB_JOINTS
) + tuple(f"{f}_{j}" for f in FINGERS[1:] for j in _FINGER_JOINTS)
#: All 26 pose-parameter names.
PARAM_NAMES: Final[tuple[str, ...]] = ("tx", "ty", "tz", "rx", "ry", "rz") + JOINT_NAMES
N_PARAMS: Final[int] = 26
N_JOINTS: Final[int] = 20

# Offsets inside one finger's 4-block of the pose vector.
FLEX1, ABD, FLEX2, FLEX3 = 0, 1, 2, 3
#: Joint angles per chain (``flex1 abd flex2 flex3``).
CHAIN_JOINTS: Final[int] = 4
#: Pose-vector index of the first joint angle (before it: ``tx ty tz rx ry rz``).
FIRST_JOINT: Final[int] = 6
#: The 20 joint angles inside the pose vector (26,).
JOINTS: Final[slice] = slice(FIRST_JOINT, None)
#: MCP abductions of index .. little inside the pose vector (a strided slice, 4 values).
FINGER_ABD: Final[slice] = slice(FIRST_JOINT + CHAIN_JOINTS + ABD, None, CHAIN_JOINTS)
#: MCP flexions (flex1) of index .. little inside the pose vector (a strided slice, 4 values).
FINGER_MCP: Final[slice] = slice(FIRST_JOINT + CHAIN_JOINTS + FLEX1, None, CHAIN_JOINTS)
#: PIP (flex2) and DIP (flex3) flexions of index .. little inside the pose vector (strided).
FINGER_PIP: Final[slice] = slice(FIRST_JOINT + CHAIN_JOINTS + FLEX2, None, CHAIN_JOINTS)
FINGER_DIP: Final[slice] = slice(FIRST_JOINT + CHAIN_JOINTS + FLEX3, None, CHAIN_JOINTS)

_CHAIN_SLICES: Final = tuple(
    slice(FIRST_JOINT + CHAIN_JOINTS * c, FIRST_JOINT + CHAIN_JOINTS * (c + 1)) for c in range(5)
)
_CHAIN_JOINT_SLICES: Final = tuple(slice(CHAIN_JOINTS * c, CHAIN_JOINTS * (c + 1)) for c in range(5))


#: Where the anatomical joint centres of the wrist, the thumb CMC and the four finger MCPs
#: (the 21-keypoint convention's rows 0, 1, 5, 9, 13, 17) lie against this model's skeleton
#: (the hand frame's origin and the five chain bases), shape (6, 3), mm, hand frame, right-hand
#: semantics, at shape 1 (scaled by ``width``, ``length`` and ``depth`` per axis).  The model's
#: skeleton is its kinematic chain, not an anatomical one: where its surface lies on a hand's,
#: its origin and bases are 2-19 mm from the hand's joint centres.  Fitted once (median per
#: axis, robust line in the facing, see :data:`KEYPOINT_FACING_MM`) on tracked mesh renders:
#: the WebXR mesh hand's joints (``synth.mesh``) expressed in the fitted model's hand frame,
#: 1278 dev frames with the fingertips within 10 mm (render seeds 3000-3039, 30 frames each;
#: the ``scenes_dev`` leave, slide-out and back scenes, repeats 0-1); see
#: ``doc/design/objects_in_hand.md``, "The palm keypoints".
KEYPOINT_OFFSETS_MM: Final = np.array(
    [
        [0.4, -4.4, -6.5],  # wrist
        [8.7, 6.8, 5.8],  # thumb CMC
        [-1.3, -2.9, -2.0],  # index MCP
        [-1.7, -3.8, -8.1],  # middle MCP
        [-1.7, -5.7, -5.2],  # ring MCP
        [-1.5, -7.3, 1.1],  # little MCP
    ]
)
#: ... plus this (6,) mm along hand z times the facing ``f`` (the palm normal's cosine with
#: the viewing ray to the wrist: -1 palm to the camera, +1 back to it).  The model's wrist is
#: thinner than a wrist (its palm is 25 mm thick there), so the joint centre lies 16 mm dorsal
#: of the model's origin when the fit lies on the palmar skin (palm to the camera) and 3 mm
#: palmar of it when on the dorsal skin (back to the camera): deeper than the origin as seen
#: from the camera by 16 and 3 mm; at the MCP row the thicknesses agree (0.2-2.8 mm).
KEYPOINT_FACING_MM: Final = np.array([9.6, 8.0, 2.8, 1.2, 0.4, 0.2])

#: Allowed range of each per-finger length factor (:attr:`HandShape.fingers`, unitless).
FINGER_RANGE: Final[tuple[float, float]] = (0.5, 2.0)


def chain_slice(c: int) -> slice:
    """Slice of chain ``c``'s (0 thumb .. 4 little) four angles in the pose vector (26,)."""
    return _CHAIN_SLICES[c]


def chain_joint_slice(c: int) -> slice:
    """Slice of chain ``c``'s four angles in a joint vector (20,) (``theta[JOINTS]``, limits)."""
    return _CHAIN_JOINT_SLICES[c]


#: Per-finger length factors of the default model (thumb .. little, unitless).
UNIFORM_FINGERS: Final[tuple[float, float, float, float, float]] = (1.0, 1.0, 1.0, 1.0, 1.0)


@dataclass(frozen=True)
class HandShape:
    """The four user-specific scale factors of paper 000, sec. 5.4, and per-finger lengths (unitless).

    ``length`` scales lengths along the fingers and palm (hand y), ``width``
    scales positions across the palm (hand x), ``depth`` scales the palm
    thickness (the palm Gaussians' standard deviation) and ``sigma`` scales
    the finger Gaussians' standard deviation (finger thickness).
    ``fingers`` (5 values, thumb .. little; optional, default all 1.0) scales
    each chain's three segment lengths (and its Gaussians' positions along
    them) on top of ``length``: real hands do not have the default model's
    finger proportions.  All 1.0 leaves the model bit-identical to a shape
    without them.
    """

    length: float = 1.0
    width: float = 1.0
    depth: float = 1.0
    sigma: float = 1.0
    fingers: tuple[float, float, float, float, float] = UNIFORM_FINGERS

    def as_array(self) -> NDArray[np.float64]:
        """Return ``[length, width, depth, sigma]``, shape (4,) (without :attr:`fingers`)."""
        return np.array([self.length, self.width, self.depth, self.sigma])

    def as_dict(self) -> dict[str, float]:
        """The factors by name: ``length``, ``width``, ``depth``, ``sigma`` and, unless all are
        1.0, ``finger_thumb`` .. ``finger_little`` (flat floats, e.g. for JSON)."""
        out = {k: float(getattr(self, k)) for k in ("length", "width", "depth", "sigma")}
        if not self.uniform_fingers:
            out.update({f"finger_{name}": float(v) for name, v in zip(FINGERS, self.fingers)})
        return out

    def describe(self) -> str:
        """One line, e.g. ``length=1.020 width=0.980 depth=1.000 sigma=1.010`` and, unless all
        are 1.0, `` fingers=1.000/1.050/1.000/0.970/0.960`` (thumb .. little)."""
        text = f"length={self.length:.3f} width={self.width:.3f} depth={self.depth:.3f} sigma={self.sigma:.3f}"
        if not self.uniform_fingers:
            text += " fingers=" + "/".join(f"{v:.3f}" for v in self.fingers)
        return text

    def finger_array(self) -> NDArray[np.float64]:
        """Return the per-finger length factors (thumb .. little), shape (5,)."""
        return np.array(self.fingers, dtype=np.float64)

    @property
    def uniform_fingers(self) -> bool:
        """Whether every per-finger length factor is exactly 1.0 (the default model's proportions)."""
        return all(v == 1.0 for v in self.fingers)

    def with_fingers(self, fingers: "Sequence[float]") -> "HandShape":
        """This shape with the per-finger length factors ``fingers`` (5 values, thumb .. little)."""
        return replace(self, fingers=tuple(float(v) for v in fingers))

    def __post_init__(self) -> None:
        for name in ("length", "width", "depth", "sigma"):
            v = float(getattr(self, name))
            if not (0.3 <= v <= 3.0) or not np.isfinite(v):
                raise InputError(f"HandShape.{name} must be in [0.3, 3.0], got {v!r}")
        try:
            fingers = tuple(float(v) for v in self.fingers)
        except (TypeError, ValueError) as err:
            raise InputError(f"HandShape.fingers must be 5 numbers, got {self.fingers!r}") from err
        if len(fingers) != 5:
            raise InputError(f"HandShape.fingers must have 5 values (thumb .. little), got {len(fingers)}")
        for v in fingers:
            if not (np.isfinite(v) and FINGER_RANGE[0] <= v <= FINGER_RANGE[1]):
                raise InputError(f"HandShape.fingers values must be in {list(FINGER_RANGE)}, got {v!r}")
        object.__setattr__(self, "fingers", fingers)


@dataclass(frozen=True, eq=False)
class HandModel:
    """A hand skeleton with isotropic 3D Gaussians attached to its bones.

    Attributes
    ----------
    bases : array, shape (5, 3), mm
        Position of each chain's first joint (thumb CMC, finger MCPs) in the hand frame.
    rest_rotations : array, shape (5, 3, 3)
        Orientation of each chain's first segment in the hand frame at zero angles.
    lengths : array, shape (5, 3), mm
        Segment lengths of each chain (thumb: metacarpal, proximal, distal).
    g_chain : int array, shape (m,)
        Chain (0 thumb .. 4 little) of each Gaussian, -1 for the palm.
    g_segment : int array, shape (m,)
        Segment (0, 1, 2) of each Gaussian along its chain; 0 for the palm.
    g_offsets : array, shape (m, 3), mm
        Gaussian centre in its segment's frame (palm: hand frame).
    g_sigmas : array, shape (m,), mm
        Standard deviation of each Gaussian; its 1-sigma sphere is the skin.
    tip_index : int array, shape (5,)
        Index of the Gaussian whose centre is each fingertip (the sphere that
        rounds off the distal end, one finger radius inside the skin).
    limits_low, limits_high : array, shape (20,), rad
        Anatomical joint limits.
    right : bool
        ``False`` mirrors the model into a left hand (hand x is negated).
    shape : HandShape
        The scale factors this model was built with.
    """

    bases: NDArray[np.float64]
    rest_rotations: NDArray[np.float64]
    lengths: NDArray[np.float64]
    g_chain: NDArray[np.int64]
    g_segment: NDArray[np.int64]
    g_offsets: NDArray[np.float64]
    g_sigmas: NDArray[np.float64]
    tip_index: NDArray[np.int64]
    limits_low: NDArray[np.float64]
    limits_high: NDArray[np.float64]
    right: bool = True
    shape: HandShape = field(default_factory=HandShape)

    @property
    def n_gaussians(self) -> int:
        """Number of model Gaussians ``m``."""
        return int(self.g_sigmas.shape[0])

    @property
    def tip_radii(self) -> NDArray[np.float64]:
        """Radius (mm) of each fingertip sphere, shape (5,)."""
        return self.g_sigmas[self.tip_index]

    @cached_property
    def bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The joint limits as bounds (low, high) of a pose (26,) each, read-only (+-inf: the wrist)."""
        unlimited = np.full(N_PARAMS - self.limits_low.size, np.inf)
        lo, hi = np.concatenate([-unlimited, self.limits_low]), np.concatenate([unlimited, self.limits_high])
        lo.setflags(write=False)
        hi.setflags(write=False)
        return lo, hi

    def scaled(self, shape: HandShape) -> "HandModel":
        """Return the default hand of the same handedness scaled by ``shape``.

        Scaling is always applied to the unscaled default geometry, so
        ``m.scaled(a).scaled(b)`` equals ``m.scaled(b)``.
        """
        return _apply_shape(_base_model(self.right), shape)

    def mirrored(self, right: bool) -> "HandModel":
        """Return this model as a right (``True``) or left (``False``) hand."""
        return replace(self, right=right)

    def with_joint_gaussians(self) -> "HandModel":
        """This model plus one Gaussian on the second and one on the third joint of every chain
        (PIP and DIP; the thumb's MCP and IP): ``m + 10`` Gaussians, appended after this
        model's (its indices, ``tip_index`` included, stay valid; the kinematics is the same).

        Each sits on its joint (offset 0 at the start of the segment beyond it) with that
        segment's standard deviation.  The tracking model leaves a bent joint's outer corner
        1.0-1.5 projected sigmas from its nearest Gaussians: the refinement of
        :class:`~hand_sog_tracker.core.tracker.Tracker` uses this model to explain it.
        """
        add_chain, add_segment, add_sigma = [], [], []
        for c in range(5):
            for s in (1, 2):
                on = np.flatnonzero((self.g_chain == c) & (self.g_segment == s))
                if on.size == 0:
                    raise InputError(f"chain {c} has no Gaussian on segment {s}")
                add_chain.append(c), add_segment.append(s), add_sigma.append(self.g_sigmas[on[0]])
        return replace(
            self,
            g_chain=np.concatenate([self.g_chain, add_chain]).astype(np.int64),
            g_segment=np.concatenate([self.g_segment, add_segment]).astype(np.int64),
            g_offsets=np.concatenate([self.g_offsets, np.zeros((len(add_chain), 3))]),
            g_sigmas=np.concatenate([self.g_sigmas, add_sigma]),
        )


_BASE_MODELS: dict[bool, HandModel] = {}


def _base_model(right: bool) -> HandModel:
    """The unscaled default model of a handedness, built once (a calibration scales hundreds).

    Its arrays are read-only: the models scaled from it share those that scaling keeps
    (chains, segments, rest rotations, tips, limits), which also keeps the kinematics'
    caches keyed by those arrays warm.
    """
    base = _BASE_MODELS.get(right)
    if base is None:
        base = default_hand_model(right)
        for value in vars(base).values():
            if isinstance(value, np.ndarray):
                value.setflags(write=False)
        _BASE_MODELS[right] = base
    return base


def _apply_shape(base: HandModel, shape: HandShape) -> HandModel:
    s = np.array([shape.width, shape.length, 1.0])
    # Segment directions are rotated copies of y; scale lengths by the
    # length factor and offsets along a segment the same way.
    offsets = base.g_offsets.copy()
    palm = base.g_chain < 0
    offsets[palm] *= s
    offsets[~palm, 1] *= shape.length
    lengths = base.lengths * shape.length
    if not shape.uniform_fingers:
        # Per-finger lengths: each chain's segments and its Gaussians' positions along them.
        fingers = shape.finger_array()
        lengths = lengths * fingers[:, None]
        offsets[~palm, 1] *= fingers[base.g_chain[~palm]]
    out = replace(
        base,
        bases=base.bases * s,
        lengths=lengths,
        g_offsets=offsets,
        g_sigmas=base.g_sigmas * np.where(palm, shape.depth, shape.sigma),
        shape=shape,
    )
    # Fingertip Gaussians sit one radius before the segment end: keep that
    # relation exact after scaling length and sigma independently.
    tips = base.tip_index
    out.g_offsets[tips, 1] = out.lengths[:, 2] - out.g_sigmas[tips]
    return out


def _finger_gaussians(
    chain: int, lengths: NDArray[np.float64], radii: NDArray[np.float64]
) -> tuple[list[int], list[int], list[list[float]], list[float], int]:
    """Gaussians along one chain: 2 on the first segment, 1-2 on the middle, 2 on the distal."""
    seg, off, sig = [], [], []
    l0, l1, l2 = lengths
    r0, r1, r2 = radii
    for frac in (0.3, 0.75):
        seg.append(0), off.append([0.0, frac * l0, 0.0]), sig.append(r0)
    n_mid = 2 if l1 > 2.2 * r1 else 1
    for frac in ((0.3, 0.8) if n_mid == 2 else (0.55,)):
        seg.append(1), off.append([0.0, frac * l1, 0.0]), sig.append(r1)
    seg.append(2), off.append([0.0, 0.3 * l2, 0.0]), sig.append(r2)
    seg.append(2), off.append([0.0, l2 - r2, 0.0]), sig.append(r2)
    tip_local = len(seg) - 1
    return [chain] * len(seg), seg, off, sig, tip_local


def default_hand_model(right: bool = True) -> HandModel:
    """Build the default adult right (or left) hand, about 185 mm wrist to middle tip.

    Returns
    -------
    HandModel
        Unscaled model (``HandShape()``), 46 Gaussians.
    """
    # Chain bases in the hand frame (mm): thumb CMC, then the four MCP joints.
    bases = np.array(
        [
            [20.0, 24.0, 6.0],
            [29.0, 86.0, 0.0],
            [9.0, 90.0, 0.0],
            [-10.0, 86.0, 0.0],
            [-28.0, 78.0, 0.0],
        ]
    )
    lengths = np.array(
        [
            [44.0, 32.0, 27.0],  # thumb metacarpal, proximal, distal
            [40.0, 24.0, 21.0],
            [45.0, 28.0, 22.0],
            [42.0, 27.0, 22.0],
            [33.0, 19.0, 19.0],
        ]
    )
    radii = np.array(
        [
            [12.0, 10.0, 9.0],
            [9.0, 8.0, 7.5],
            [9.5, 8.5, 8.0],
            [9.0, 8.0, 7.5],
            [8.0, 7.0, 6.5],
        ]
    )
    rest = np.empty((5, 3, 3))
    # Thumb: points radially and distally, pronated so it flexes across the palm.
    rest[0] = rot_z(-0.75) @ rot_y(0.9) @ rot_x(0.25)
    # Fingers: slight fan-out, pointing along hand y.
    for i, spread in enumerate((-0.08, 0.0, 0.07, 0.16), start=1):
        rest[i] = rot_z(spread)
    chains, segs, offs, sigs, tips = [], [], [], [], []
    # Palm: a 4 x 3 grid of Gaussians from the wrist to the MCP row.
    palm_rows = (8.0, 32.0, 56.0, 76.0)
    palm_cols = (27.0, 9.0, -9.0, -26.0)
    for y in palm_rows:
        for x in palm_cols:
            x_at = x * (0.8 if y < 20 else 1.0)
            chains.append(-1), segs.append(0), offs.append([x_at, y, 0.0]), sigs.append(12.5)
    for c in range(5):
        ch, sg, of, si, tip_local = _finger_gaussians(c, lengths[c], radii[c])
        tips.append(len(chains) + tip_local)
        chains += ch
        segs += sg
        offs += of
        sigs += si
    deg = np.deg2rad
    # Limits in pose order per chain: flex1, abd, flex2, flex3.  MCP abduction (positive
    # turns a finger toward the little-finger side) is asymmetric as in real hands: the
    # index spreads away from the middle finger (radially) far more than toward it, the
    # little finger the other way; no finger can swing far over its neighbour.
    abd = ((-25, 12), (-15, 15), (-12, 20), (-12, 25))  # index .. little, degrees
    low = np.array(
        [deg(-20), deg(-45), deg(-20), deg(-25)]
        + [v for a_lo, _ in abd for v in (deg(-25), deg(a_lo), deg(-5), deg(-10))]
    )
    high = np.array(
        [deg(60), deg(45), deg(80), deg(90)]
        + [v for _, a_hi in abd for v in (deg(95), deg(a_hi), deg(110), deg(90))]
    )
    return HandModel(
        bases=bases,
        rest_rotations=rest,
        lengths=lengths,
        g_chain=np.array(chains, dtype=np.int64),
        g_segment=np.array(segs, dtype=np.int64),
        g_offsets=np.array(offs, dtype=np.float64),
        g_sigmas=np.array(sigs, dtype=np.float64),
        tip_index=np.array(tips, dtype=np.int64),
        limits_low=low,
        limits_high=high,
        right=right,
    )


def rest_pose(translation_mm: tuple[float, float, float] = (0.0, 0.0, 400.0)) -> NDArray[np.float64]:
    """Open flat hand, palm toward the camera, fingers pointing up in the image.

    Returns
    -------
    array, shape (26,)
        Pose vector (mm, rad).
    """
    theta = np.zeros(N_PARAMS)
    theta[:3] = translation_mm
    theta[3] = np.pi  # Rx(pi): hand y -> camera -y (up), palm normal -> camera -z.
    theta[FIRST_JOINT + FLEX1] = 0.1
    return theta
