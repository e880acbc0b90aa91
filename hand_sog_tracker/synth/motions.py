"""Scripted hand motions in the spirit of the Dexter 1 sequences (paper 000, sec. 6).

One job: the scripted motions; kept together because each motion is a short function and
all share the key articulations and the small interpolation helpers.

Every motion is a smooth function of time ``t = k / fps`` (so the first frames
of a short and a long sequence agree), starts exactly at the start pose and
keeps all joint angles within the model's limits.  The default start pose is
:func:`~hand_sog_tracker.core.hand_model.rest_pose` (open hand, palm toward
the camera, fingers up) at :data:`START_TRANSLATION_MM`, which puts the whole
hand inside a 320 x 240, ``fx = 287`` image at about 400 mm.

Articulation motions blend from the start articulation into the scripted one
over the first :data:`RAMP_S` seconds and add a gentle global drift (a few mm,
a few degrees, about the palm centre).  ``random`` is the hard case: fast
smooth random global rotation (peak angular speed well above 90 deg/s) and
translation with varying articulation.

Units: millimetres and radians; poses are (T, 26) vectors as described in
:mod:`hand_sog_tracker.core.hand_model`.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import lru_cache
from typing import Final

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.articulations import CLAW_FINGER_DEG, FIST_FINGER_DEG, PINCH_INDEX_DEG
from hand_sog_tracker.core.hand_model import (
    ABD,
    CHAIN_JOINTS,
    JOINTS,
    N_PARAMS,
    chain_joint_slice,
    chain_slice,
    default_hand_model,
    rest_pose,
)
from hand_sog_tracker.core.kinematics import attached_points, check_pose, fingertips
from hand_sog_tracker.core.rotations import matrices_from_euler
from hand_sog_tracker.errors import InputError

__all__ = [
    "MOTIONS",
    "EXTRA_MOTIONS",
    "ALL_MOTIONS",
    "START_TRANSLATION_MM",
    "PALM_CENTRE_HAND_MM",
    "RAMP_S",
    "default_start_pose",
    "motion_poses",
    "key_articulations",
]

MOTIONS: Final[tuple[str, ...]] = (
    "abdadd",
    "fingercount",
    "fingerwave",
    "flexex",
    "pinch",
    "tigergrasp",
    "random",
)
#: Motions added for the mesh renderer's protocol sets (not in the default capsule bag set).
EXTRA_MOTIONS: Final[tuple[str, ...]] = ("fistopen", "rotate")
#: Every motion :func:`motion_poses` knows.
ALL_MOTIONS: Final[tuple[str, ...]] = MOTIONS + EXTRA_MOTIONS
#: Wrist position (mm, camera frame) of the default start pose: wrist below
#: the image centre so that the upward-pointing fingers stay in view.
START_TRANSLATION_MM: Final[tuple[float, float, float]] = (0.0, 60.0, 400.0)
#: Global rotations of the motions turn the hand about this hand-frame point (mm).
PALM_CENTRE_HAND_MM: Final[tuple[float, float, float]] = (0.0, 50.0, 0.0)
#: Seconds over which a motion blends in from the start articulation.
RAMP_S: Final[float] = 0.5

_DEG = np.pi / 180.0


def default_start_pose() -> NDArray[np.float64]:
    """The default first pose of every motion, shape (26,) (mm, rad)."""
    return rest_pose(START_TRANSLATION_MM)


def _smoothstep(x: NDArray[np.float64]) -> NDArray[np.float64]:
    """C1 ramp from 0 (x <= 0) to 1 (x >= 1)."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _cosine_cycle(t: NDArray[np.float64], period: float, phase_s: float = 0.0) -> NDArray[np.float64]:
    """0 -> 1 -> 0 once per ``period`` seconds (0 at ``t = phase_s``)."""
    return 0.5 * (1.0 - np.cos(2.0 * np.pi * (t - phase_s) / period))


def _lerp(a: NDArray[np.float64], b: NDArray[np.float64], s: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per-frame blend of articulations: a, b (20,) or (T, 20); s (T,) or (T, k) broadcastable."""
    return a + (b - a) * s


def _thumb_ik(
    theta: NDArray[np.float64], target: NDArray[np.float64], distance: float
) -> NDArray[np.float64]:
    """Thumb angles (4,) rad that bring the thumb tip ``distance`` mm from ``target``.

    Damped Gauss-Newton on the default right hand with a numerical Jacobian,
    clipped to the joint limits, from a few starting guesses; best result.
    """
    model = default_hand_model(True)
    lo, hi = model.limits_low[chain_joint_slice(0)], model.limits_high[chain_joint_slice(0)]

    def residual(x: NDArray[np.float64]) -> NDArray[np.float64]:
        th = theta.copy()
        th[chain_slice(0)] = x
        diff = fingertips(model, th)[0] - target
        n = float(np.linalg.norm(diff))
        return diff * (1.0 - distance / max(n, 1e-9))

    best_x, best_e = np.zeros(4), np.inf
    for x0 in ((0.3, 0.5, 0.5, 0.3), (0.0, 0.0, 0.0, 0.0), (0.8, 0.6, 0.3, 0.2), (0.3, 0.7, 0.0, 0.0)):
        x = np.clip(np.array(x0), lo, hi)
        for _ in range(40):
            f = residual(x)
            J = np.empty((3, 4))
            for j in range(4):
                xp = x.copy()
                xp[j] += 1e-5
                J[:, j] = (residual(xp) - f) / 1e-5
            step = np.linalg.solve(J.T @ J + 1e-3 * np.eye(4), -J.T @ f)
            x = np.clip(x + step, lo, hi)
        e = float(np.linalg.norm(residual(x)))
        if e < best_e:
            best_x, best_e = x, e
    return best_x


@lru_cache(maxsize=1)
def _key_articulations_cached() -> dict[str, tuple[float, ...]]:
    model = default_hand_model(True)
    d = _DEG
    open_q = rest_pose()[JOINTS].copy()

    fist = open_q.copy()
    for c in range(1, 5):
        fist[chain_joint_slice(c)] = tuple(v * d for v in FIST_FINGER_DEG)
    # Thumb of the fist: over the dorsal side of the curled index middle phalanx.
    th = rest_pose()
    th[JOINTS] = fist
    on_index = attached_points(
        model, th, np.array([1, -1, -1]), np.array([1, 0, 0]),
        np.array([[0.0, 0.5 * model.lengths[1, 1], 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
    )
    palmar = on_index[2] - on_index[1]  # unit hand-z (palmar normal) in the camera frame
    r_mid = float(np.mean(model.g_sigmas[(model.g_chain == 1) & (model.g_segment == 1)]))
    target = on_index[0] + palmar * (r_mid + float(model.tip_radii[0]))
    fist[chain_joint_slice(0)] = _thumb_ik(th, target, 0.0)

    claw = open_q.copy()
    for c in range(1, 5):
        claw[chain_joint_slice(c)] = tuple(v * d for v in CLAW_FINGER_DEG)
    claw[chain_joint_slice(0)] = 0.5 * (open_q[chain_joint_slice(0)] + fist[chain_joint_slice(0)])

    # Pinch: index curls toward the thumb; thumb tip touches the index tip.
    pinch = open_q.copy()
    pinch[chain_joint_slice(1)] = tuple(v * d for v in PINCH_INDEX_DEG)
    for c, f in ((2, 0.25), (3, 0.3), (4, 0.35)):  # the other fingers relax a little
        pinch[chain_joint_slice(c)] = tuple(f * v * d for v in FIST_FINGER_DEG)
    th = rest_pose()
    th[JOINTS] = pinch
    index_tip = fingertips(model, th)[1]
    pinch[chain_joint_slice(0)] = _thumb_ik(th, index_tip, float(model.tip_radii[0] + model.tip_radii[1]))

    spread = open_q.copy()
    spread[chain_joint_slice(0)] = (0.1, -35 * d, 0.0, 0.0)
    for c, abd in ((1, -20), (2, -3), (3, 15), (4, 24)):
        spread[chain_joint_slice(c).start + ABD] = abd * d
    close = open_q.copy()
    close[chain_joint_slice(0)] = (0.1, 25 * d, 0.0, 0.0)
    for c, abd in ((1, 4.5), (2, 0.0), (3, -4), (4, -8)):
        close[chain_joint_slice(c).start + ABD] = abd * d
    out = {"open": open_q, "fist": fist, "claw": claw, "pinch": pinch, "spread": spread, "close": close}
    lo, hi = model.limits_low, model.limits_high
    return {k: tuple(np.clip(v, lo, hi)) for k, v in out.items()}


def key_articulations() -> dict[str, NDArray[np.float64]]:
    """Key hand shapes used by the motions: name -> joint angles (20,) rad.

    Names: ``open`` (rest), ``fist``, ``claw`` (MCP extended, PIP/DIP flexed),
    ``pinch`` (thumb tip touching the index tip), ``spread``, ``close``.
    """
    return {k: np.array(v) for k, v in _key_articulations_cached().items()}


# --- articulation scripts: t (T,) seconds, rng -> (T, 20) joint angles ---------------------------


def _abdadd(t: NDArray[np.float64], rng: np.random.Generator) -> NDArray[np.float64]:
    k = key_articulations()
    s = _cosine_cycle(t, 1.6)[:, None]  # 0 = spread, 1 = closed
    return _lerp(k["spread"], k["close"], s)


def _flexex(t: NDArray[np.float64], rng: np.random.Generator) -> NDArray[np.float64]:
    k = key_articulations()
    return _lerp(k["open"], k["fist"], _cosine_cycle(t, 1.5)[:, None])


def _fingerwave(t: NDArray[np.float64], rng: np.random.Generator) -> NDArray[np.float64]:
    k = key_articulations()
    bent = k["open"] + 0.75 * (k["fist"] - k["open"])
    s = np.empty((t.size, 20))
    for c in range(5):  # little finger first, then ring ... thumb
        s[:, chain_joint_slice(c)] = _cosine_cycle(t, 1.3, phase_s=0.16 * (4 - c))[:, None]
    return _lerp(k["open"], bent, s)


def _fingercount(t: NDArray[np.float64], rng: np.random.Generator) -> NDArray[np.float64]:
    """Fold into a fist, then extend thumb .. little one by one, fold them back one by one."""
    k = key_articulations()
    step, hold = 0.45, 0.4
    fold_in = 0.6
    cycle = 10 * step + 2 * hold
    ext = np.empty((t.size, 20))  # 1 = extended
    tc = np.mod(np.maximum(t - fold_in, 0.0), cycle)
    for c in range(5):
        up = _smoothstep((tc - step * c) / step)
        down = _smoothstep((tc - (5 * step + hold + step * (4 - c))) / step)
        e = np.where(t < fold_in, 1.0 - _smoothstep(t / fold_in), up - down)
        ext[:, chain_joint_slice(c)] = e[:, None]
    return _lerp(k["fist"], k["open"], ext)


def _pinch(t: NDArray[np.float64], rng: np.random.Generator) -> NDArray[np.float64]:
    k = key_articulations()
    s = _smoothstep(1.25 * _cosine_cycle(t, 1.4) - 0.125)[:, None]  # dwell at open and at contact
    return _lerp(k["open"], k["pinch"], s)


def _tigergrasp(t: NDArray[np.float64], rng: np.random.Generator) -> NDArray[np.float64]:
    """open -> claw -> fist -> claw -> open, 3.2 s per cycle."""
    k = key_articulations()
    ph = np.mod(t, 3.2) / 0.8  # 0..4
    to_claw = _smoothstep(ph)[:, None]
    to_fist = _smoothstep(ph - 1.0)[:, None]
    back_claw = _smoothstep(ph - 2.0)[:, None]
    back_open = _smoothstep(ph - 3.0)[:, None]
    q = _lerp(k["open"], k["claw"], to_claw)
    q = _lerp(q, k["fist"], to_fist)
    q = _lerp(q, k["claw"], back_claw)
    return _lerp(q, k["open"], back_open)


def _smooth_random(
    t: NDArray[np.float64], rng: np.random.Generator, n: int, amplitude: float, f_lo: float, f_hi: float
) -> NDArray[np.float64]:
    """``n`` smooth random signals, shape (T, n): sums of 3 sinusoids, |value| <= amplitude."""
    freqs = rng.uniform(f_lo, f_hi, (3, n))
    phases = rng.uniform(0.0, 2.0 * np.pi, (3, n))
    weights = rng.uniform(0.5, 1.0, (3, n))
    weights /= weights.sum(axis=0, keepdims=True)
    sig = np.zeros((t.size, n))
    for i in range(3):
        sig += weights[i] * np.sin(2.0 * np.pi * freqs[i] * t[:, None] + phases[i])
    return amplitude * sig


def _random_articulation(t: NDArray[np.float64], rng: np.random.Generator) -> NDArray[np.float64]:
    k = key_articulations()
    level = np.clip(0.35 + _smooth_random(t, rng, 5, 0.5, 0.3, 0.9), 0.0, 0.8)  # (T, 5) flexion
    s = np.repeat(level, 4, axis=1)
    q = _lerp(k["open"], k["fist"], s)
    abd = _smooth_random(t, rng, 5, 10 * _DEG, 0.2, 0.6)
    q[:, ABD::CHAIN_JOINTS] += abd
    return q


@lru_cache(maxsize=1)
def _deep_fist_cached() -> tuple[float, ...]:
    """A full fist near the upper joint limits, thumb folded across the curled fingers."""
    model = default_hand_model(True)
    d = _DEG
    q = rest_pose()[JOINTS].copy()
    for c, (mcp, pip, dip) in zip(range(1, 5), ((86, 102, 72), (88, 104, 75), (89, 104, 77), (90, 105, 78))):
        q[chain_joint_slice(c)] = (mcp * d, 0.0, pip * d, dip * d)
    # Thumb: its tip over the dorsal side of the curled index and middle middle phalanges.
    th = rest_pose()
    th[JOINTS] = q
    pts = attached_points(
        model, th, np.array([1, 2, -1, -1]), np.array([1, 1, 0, 0]),
        np.array([[0.0, 0.45 * model.lengths[1, 1], 0.0], [0.0, 0.3 * model.lengths[2, 1], 0.0],
                  [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
    )
    palmar = pts[3] - pts[2]
    r_mid = float(np.mean(model.g_sigmas[(model.g_chain == 1) & (model.g_segment == 1)]))
    target = 0.6 * pts[0] + 0.4 * pts[1] + palmar * (r_mid + float(model.tip_radii[0]))
    q[chain_joint_slice(0)] = _thumb_ik(th, target, 0.0)
    return tuple(np.clip(q, model.limits_low, model.limits_high))


def _fistopen(t: NDArray[np.float64], rng: np.random.Generator) -> NDArray[np.float64]:
    """Open hand -> full fist (near the limits) -> open, 1.2 s per cycle, fingers staggered."""
    k = key_articulations()
    fist = np.array(_deep_fist_cached())
    s = np.empty((t.size, 20))
    for c in range(5):  # index closes first, little last; the thumb follows the fingers
        lag = 0.1 if c == 0 else 0.04 * (c - 1)
        s[:, chain_joint_slice(c)] = _smoothstep(1.3 * _cosine_cycle(t, 1.2, phase_s=lag) - 0.15)[:, None]
    return _lerp(k["open"], fist, s)


def _rotate_articulation(t: NDArray[np.float64], rng: np.random.Generator) -> NDArray[np.float64]:
    """Half-open hand whose flexion varies mildly (the global rotation is added in motion_poses)."""
    k = key_articulations()
    level = np.clip(0.4 + _smooth_random(t, rng, 5, 0.15, 0.3, 0.8), 0.0, 0.8)
    q = _lerp(k["open"], k["fist"], np.repeat(level, 4, axis=1))
    q[:, ABD::CHAIN_JOINTS] += _smooth_random(t, rng, 5, 6 * _DEG, 0.2, 0.6)
    return q


_SCRIPTS: Final[dict[str, Callable[[NDArray[np.float64], np.random.Generator], NDArray[np.float64]]]] = {
    "abdadd": _abdadd,
    "fingercount": _fingercount,
    "fingerwave": _fingerwave,
    "flexex": _flexex,
    "pinch": _pinch,
    "tigergrasp": _tigergrasp,
    "random": _random_articulation,
    "fistopen": _fistopen,
    "rotate": _rotate_articulation,
}


def _global_motion(
    start: NDArray[np.float64],
    t: NDArray[np.float64],
    d_angles: NDArray[np.float64],
    d_centre: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Global pose rows (T, 6): Euler offsets (T, 3) rad, palm-centre shifts (T, 3) mm.

    The hand turns about :data:`PALM_CENTRE_HAND_MM` (it has x = 0, so the
    mirror of a left hand does not move it).
    """
    c_hand = np.array(PALM_CENTRE_HAND_MM)
    R0 = matrices_from_euler(start[None, 3:6])[0]
    centre0 = start[:3] + R0 @ c_hand
    angles = start[3:6] + d_angles
    R = matrices_from_euler(angles)
    trans = centre0 + d_centre - R @ c_hand
    return np.concatenate([trans, angles], axis=1)


def motion_poses(
    name: str,
    n_frames: int,
    fps: float = 30.0,
    seed: int = 0,
    start: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """Poses of a scripted motion.

    Parameters
    ----------
    name : str
        One of :data:`ALL_MOTIONS` (:data:`MOTIONS` plus :data:`EXTRA_MOTIONS`).
    n_frames : int
        Number of frames ``T`` (>= 1).
    fps : float
        Frame rate (Hz); frame ``k`` is at ``t = k / fps`` seconds.
    seed : int
        Seeds the random parts (drift phases, the ``random`` motion).
    start : array, shape (26,), optional
        First pose (mm, rad); default :func:`default_start_pose`.

    Returns
    -------
    array, shape (T, 26)
        Poses (mm, rad); row 0 equals ``start`` (its joint angles clipped into
        the limits); all joint angles within the default model's limits.

    Raises
    ------
    InputError
        Unknown motion, ``n_frames < 1``, ``fps <= 0`` or a bad ``start``.
    """
    if name not in _SCRIPTS:
        raise InputError(f"unknown motion {name!r}; choose one of {', '.join(ALL_MOTIONS)}")
    if int(n_frames) != n_frames or n_frames < 1:
        raise InputError(f"n_frames must be a positive integer, got {n_frames!r}")
    if not (np.isfinite(fps) and fps > 0):
        raise InputError(f"fps must be positive, got {fps!r}")
    start_pose = default_start_pose() if start is None else check_pose(start).copy()
    model = default_hand_model(True)
    lo, hi = model.limits_low, model.limits_high

    t = np.arange(int(n_frames)) / float(fps)
    # Independent streams: articulation randomness and global motion.
    rng_art, rng_glob = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(2))
    ramp = _smoothstep(t / RAMP_S)[:, None]
    target = _SCRIPTS[name](t, rng_art)
    q0 = np.clip(start_pose[JOINTS], lo, hi)
    q = np.clip(q0 + ramp * (target - q0), lo, hi)

    if name == "random":
        # Fast: roll (camera z) and tilt up to ~35 deg, twist about the hand axis up to ~45 deg.
        amp = np.array([30.0, 45.0, 35.0]) * _DEG
        d_angles = np.concatenate(
            [_smooth_random(t, rng_glob, 1, a, 0.35, 0.8) for a in amp], axis=1
        )
        d_centre = np.concatenate(
            [
                _smooth_random(t, rng_glob, 1, 30.0, 0.3, 0.7),
                _smooth_random(t, rng_glob, 1, 12.0, 0.3, 0.7),
                _smooth_random(t, rng_glob, 1, 30.0, 0.3, 0.7),
            ],
            axis=1,
        )
        glob_ramp = _smoothstep(t / 0.3)[:, None]
    elif name == "rotate":
        # Fast turns: pronation/supination about the hand axis up to ~70 deg (palm sideways),
        # tilt (palm away) up to ~40 deg, roll ~25 deg; peaks > 150 deg/s.
        period = rng_glob.uniform(1.7, 2.1, 3)
        sign = np.where(rng_glob.random(3) < 0.5, -1.0, 1.0)
        amp = np.array([40.0, 70.0, 25.0]) * _DEG * rng_glob.uniform(0.9, 1.0, 3) * sign
        d_angles = amp * np.sin(2.0 * np.pi * t[:, None] / period)
        d_centre = np.concatenate([_smooth_random(t, rng_glob, 1, a, 0.3, 0.6) for a in (15.0, 8.0, 15.0)], axis=1)
        glob_ramp = _smoothstep(t / 0.3)[:, None]
    else:
        # Gentle drift: a few degrees, a few millimetres.
        d_angles = _smooth_random(t, rng_glob, 3, 3.0 * _DEG, 0.1, 0.3)
        d_centre = _smooth_random(t, rng_glob, 3, 4.0, 0.1, 0.3)
        glob_ramp = ramp
    glob = _global_motion(start_pose, t, glob_ramp * d_angles, glob_ramp * d_centre)

    poses = np.empty((t.size, N_PARAMS))
    poses[:, :6] = glob
    poses[:, JOINTS] = q
    poses[0] = start_pose
    poses[0, JOINTS] = q0
    return poses
