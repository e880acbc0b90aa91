"""The tracking objective and its analytic gradient (paper 000, sec. 5.2).

``E = E_sim - w_c E_col - w_d E_dan - w_l E_lim - w_s E_smo - w_o E_ord - w_sal E_sal
- w_sil E_sil`` is maximised over the 26 pose parameters.  ``E_sil`` (every model Gaussian
projects onto the hand's pixels) lives in :mod:`hand_sog_tracker.core.silhouette`.  The last
three terms are not in paper 000:
``E_ord`` keeps the four fingers in their order across the palm (no finger may swing over
onto its neighbour's data) and ``E_sal`` pulls fingertips toward the detections assigned to
them (seed 001, eq. 12; see :mod:`hand_sog_tracker.core.salient`).  Overlaps of unnormalised isotropic Gaussians (eq. 4)
have closed forms: in d dimensions

``D_pq = (2 pi s_p^2 s_q^2 / (s_p^2 + s_q^2))^(d/2) exp(-|mu_p - mu_q|^2 / (2 (s_p^2 + s_q^2)))``.

Choices the paper leaves open (documented here, used everywhere):

* the projected sigma uses ``f = sqrt(fx * fy)``;
* ``E_col`` counts pairs of Gaussians on different chains, and palm Gaussians
  against finger Gaussians beyond the first segment (neighbours on one chain
  overlap by design); ``E(C_h, C_h)`` is computed once per model in the rest pose;
* ``E_dan`` (eq. 7) measures how far a model Gaussian is from the data with an
  occlusion-aware distance instead of the plain 3D distance to back-projected
  quad centres (which calls every occluded or quad-interior Gaussian dangling
  and pulls a correct pose away): lateral distance in mm at the Gaussian's depth
  from its projected centre to the quad's extent, combined with how far the
  data lie *behind* the model's surface (data in front of it are occluders, not
  evidence of dangling).  The term is made continuous so that the gradient
  exists almost everywhere: membership of the dangling set ``D`` is a weight
  that ramps from 0 to 1 as the distance to the nearest data Gaussian grows from
  ``TAU1_MM`` to ``2 TAU1_MM``; ``phi`` ramps from 0 to 1 between ``TAU1_MM`` and
  ``TAU2_MM`` (the paper's ramp drops back to 0 beyond ``TAU2_MM``, a jump); the
  sum over data Gaussians is divided by their number so the term does not grow
  with image resolution;
* ``E_smo`` (eq. 9) measures translations in units of ``SMOOTH_TRANSLATION_MM``
  so that millimetres and radians are weighed alike;
* ``E_ord = sum_c max(ORDER_MIN_GAP_RAD - (a_{c+1} - a_c), 0)^2`` over the neighbouring
  finger pairs (index-middle, middle-ring, ring-little), where ``a_c`` is finger ``c``'s
  direction in the palm plane (its rest fan-out angle plus its MCP abduction), rad^2 like
  ``E_lim``;
* ``E_sal = sum_t w_t (sqrt(d_t^2 + c^2) - c) / SALIENT_SCALE_MM`` with ``d_t`` the distance
  (mm) of fingertip ``t`` from its assigned detection, ``w_t`` the detection's confidence
  (0 without one) and ``c = SALIENT_SOFT_MM``: a pseudo-Huber cost, flat within a few mm
  (the detector is not more precise, seed 001 ignores pairs under 10 mm) and growing
  linearly far away, so a wrong detection cannot dominate the data term.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.depth_sog import ImageSoG
from hand_sog_tracker.core.hand_model import N_PARAMS, HandModel, rest_pose
from hand_sog_tracker.core.kinematics import gaussian_centres
from hand_sog_tracker.core.silhouette import Silhouette, silhouette_term
from hand_sog_tracker.core.types import TrackerConfig

__all__ = [
    "EnergyTerms",
    "Objective",
    "TipTargets",
    "TAU1_MM",
    "TAU2_MM",
    "SMOOTH_TRANSLATION_MM",
    "ORDER_MIN_GAP_RAD",
    "SALIENT_SOFT_MM",
    "SALIENT_SCALE_MM",
]

TAU1_MM = 15.0
TAU2_MM = 60.0
SMOOTH_TRANSLATION_MM = 50.0
#: Smallest allowed difference of neighbouring fingers' palm-plane directions (rad); at rest
#: they fan out by 0.07-0.09 rad; a finger on its neighbour's data needs about -0.25.
ORDER_MIN_GAP_RAD = -0.05
#: Width of the flat bottom of the salient-point cost (mm).
SALIENT_SOFT_MM = 8.0
#: The salient cost is measured in units of this distance (mm).
SALIENT_SCALE_MM = 100.0
_TWO_PI = 2.0 * np.pi
_INV_SQRT2 = 1.0 / np.sqrt(2.0)


def _accumulate(index: NDArray[np.int64], weights: NDArray[np.float64], size: int) -> NDArray[np.float64]:
    """Sum ``weights`` per ``index`` into a float array of length ``size`` (empty-safe)."""
    return np.bincount(index, weights=weights, minlength=size).astype(np.float64, copy=False)


@dataclass(frozen=True)
class EnergyTerms:
    """Values of the objective and its terms (unitless)."""

    total: float
    sim: float
    col: float
    dan: float
    lim: float
    smo: float
    ord: float = 0.0
    sal: float = 0.0
    sil: float = 0.0


@dataclass(frozen=True, eq=False)
class TipTargets:
    """Where the fingertips should be: the detections assigned to them.

    Attributes
    ----------
    points : array, shape (5, 3), mm
        Target of each fingertip (thumb .. little), camera frame; ignored where the weight is 0.
    weights : array, shape (5,)
        Confidence of each target, 0 for a fingertip without a detection.
    """

    points: NDArray[np.float64]
    weights: NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class _ModelConstants:
    pair_i: NDArray[np.int64]
    pair_j: NDArray[np.int64]
    pair_s2: NDArray[np.float64]  # sigma_i^2 + sigma_j^2, mm^2
    pair_amp: NDArray[np.float64]  # overlap at zero distance, (2 pi s_i^2 s_j^2 / s2)^1.5
    incidence: NDArray[np.float64]  # (m, pairs): +1 at i, -1 at j
    norm_h: float
    fan: NDArray[np.float64]  # (4,) rest direction of index .. little in the palm plane, rad


def _collision_pairs(model: HandModel) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    ch, sg = model.g_chain, model.g_segment
    i, j = np.triu_indices(model.n_gaussians, k=1)
    fingers = (ch[i] >= 0) & (ch[j] >= 0) & (ch[i] != ch[j])
    palm_finger = ((ch[i] < 0) & (ch[j] >= 0) & (sg[j] >= 1)) | (
        (ch[j] < 0) & (ch[i] >= 0) & (sg[i] >= 1)
    )
    keep = fingers | palm_finger
    return i[keep], j[keep]


_CONST_CACHE: dict[int, tuple[HandModel, _ModelConstants]] = {}


def model_constants(model: HandModel) -> _ModelConstants:
    """Collision pairs and ``E(C_h, C_h)`` of a model (cached per model object)."""
    hit = _CONST_CACHE.get(id(model))
    if hit is not None and hit[0] is model:
        return hit[1]
    pi, pj = _collision_pairs(model)
    centres = gaussian_centres(model, rest_pose())
    d2 = ((centres[:, None, :] - centres[None, :, :]) ** 2).sum(-1)
    s2 = model.g_sigmas**2
    ss = s2[:, None] + s2[None, :]
    norm_h = float(((_TWO_PI * s2[:, None] * s2[None, :] / ss) ** 1.5 * np.exp(-0.5 * d2 / ss)).sum())
    s2p = s2[pi] + s2[pj]
    incidence = np.zeros((model.n_gaussians, pi.size))
    incidence[pi, np.arange(pi.size)] = 1.0
    incidence[pj, np.arange(pi.size)] = -1.0
    const = _ModelConstants(
        pair_i=pi,
        pair_j=pj,
        pair_s2=s2p,
        pair_amp=(_TWO_PI * s2[pi] * s2[pj] / s2p) ** 1.5,
        incidence=incidence,
        norm_h=norm_h,
        fan=np.arctan2(model.rest_rotations[1:, 1, 0], model.rest_rotations[1:, 0, 0]),
    )
    if len(_CONST_CACHE) > 32:
        _CONST_CACHE.clear()
    _CONST_CACHE[id(model)] = (model, const)
    return const


@lru_cache(maxsize=1)
def _smooth_scale() -> NDArray[np.float64]:
    s = np.ones(N_PARAMS)
    s[:3] = 1.0 / SMOOTH_TRANSLATION_MM
    return s


class Objective:
    """The objective ``E(theta)`` for one frame.

    Parameters
    ----------
    model : HandModel
    data : ImageSoG
        The frame's depth Gaussians.
    config : TrackerConfig
        Term weights ``w_col``, ``w_dan``, ``w_lim``, ``w_smo``.
    previous : (theta_{t-1}, theta_{t-2}) or None
        The two previous poses, shape (26,) each; None disables ``E_smo``.
    silhouette : Silhouette or None
        The hand's silhouette for ``E_sil`` (:mod:`hand_sog_tracker.core.silhouette`);
        None disables it.
    targets : TipTargets or None
        Assigned fingertip detections; None disables ``E_sal``.
    """

    def __init__(
        self,
        model: HandModel,
        data: ImageSoG,
        config: TrackerConfig,
        previous: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
        targets: TipTargets | None = None,
        silhouette: Silhouette | None = None,
    ) -> None:
        self.model = model
        self.data = data
        self.config = config
        self.previous = previous
        self.targets = targets
        self.silhouette = silhouette
        self._const = model_constants(model)
        intr = data.intrinsics
        self._f = float(np.sqrt(intr.fx * intr.fy))
        # Per-frame constants of the data terms.
        self._mu_u = np.ascontiguousarray(data.mu[:, 0])
        self._mu_v = np.ascontiguousarray(data.mu[:, 1])
        self._sq2 = data.sigma**2
        self._sq2_36 = 36.0 * self._sq2
        self._half = data.sigma * _INV_SQRT2  # half a quad's side, px
        self._two_sh = (2.0 * model.g_sigmas)[:, None]

    def __call__(
        self, theta: NDArray[np.float64], gradient: bool = True
    ) -> tuple[float, NDArray[np.float64] | None]:
        """Return ``E(theta)`` and, with ``gradient``, ``dE/dtheta`` of shape (26,)."""
        terms, grad = self.evaluate(theta, gradient)
        return terms.total, grad

    def evaluate(
        self, theta: NDArray[np.float64], gradient: bool = True
    ) -> tuple[EnergyTerms, NDArray[np.float64] | None]:
        """Return every term of ``E(theta)`` and optionally the gradient, shape (26,)."""
        cfg = self.config
        if gradient:
            P, J = gaussian_centres(self.model, theta, jacobian=True)
        else:
            P, J = gaussian_centres(self.model, theta), None
        g3 = np.zeros_like(P) if gradient else None
        sim, dan = self._data_terms(P, g3, cfg.w_dan)
        col = self._collision(P, g3, cfg.w_col)
        lim, g_lim = self._limits(theta)
        smo, g_smo = self._smoothness(theta)
        ordv, g_ord = self._order(theta)
        sal = self._salient(P, g3, cfg.w_sal)
        sil = 0.0
        if self.silhouette is not None and cfg.w_sil > 0:
            sil = silhouette_term(self.silhouette, P, g3, cfg.w_sil)
        total = (
            sim
            - cfg.w_col * col
            - cfg.w_dan * dan
            - cfg.w_lim * lim
            - cfg.w_smo * smo
            - cfg.w_ord * ordv
            - cfg.w_sal * sal
            - cfg.w_sil * sil
        )
        terms = EnergyTerms(
            total=total, sim=sim, col=col, dan=dan, lim=lim, smo=smo, ord=ordv, sal=sal, sil=sil
        )
        if not gradient:
            return terms, None
        grad = np.einsum("mk,mkj->j", g3, J)
        grad -= cfg.w_lim * g_lim + cfg.w_smo * g_smo + cfg.w_ord * g_ord
        return terms, grad

    # -- terms ---------------------------------------------------------------
    def _data_terms(
        self, P: NDArray[np.float64], g3: NDArray[np.float64] | None, w_dan: float
    ) -> tuple[float, float]:
        """``E_sim`` and ``E_dan``; adds ``dE/dP`` (with signs and weights) into ``g3``.

        ``E_sim`` is summed over the pairs that can contribute: depth difference
        under ``2 sigma_h`` (else ``Delta = 0`` exactly) and image distance under
        6 combined standard deviations (else ``D_pq < 1.6e-8 D_pq^0``).
        ``E_dan`` is evaluated on the rows of dangling Gaussians only.
        """
        data = self.data
        if data.n == 0 or data.norm <= 0:
            return 0.0, 0.0
        intr = data.intrinsics
        m = P.shape[0]
        sh = self.model.g_sigmas
        x, y, z = P[:, 0], P[:, 1], np.maximum(P[:, 2], 1.0)
        u = intr.fx * x / z + intr.cx
        v = intr.fy * y / z + intr.cy
        sp = sh * self._f / z
        dp = z - sh
        sq2_all = self._sq2
        # Candidate pairs (dense tests, sparse arithmetic).
        du_d = u[:, None] - self._mu_u
        dv_d = v[:, None] - self._mu_v
        r2_d = du_d * du_d + dv_d * dv_d
        dd_d = dp[:, None] - data.depth
        mask = (np.abs(dd_d) < self._two_sh) & (r2_d < (36.0 * sp * sp)[:, None] + self._sq2_36)
        flat = np.flatnonzero(mask)
        n = data.n
        pi, qi = np.divmod(flat, n)
        du, dv, r2, dd = du_d.take(flat), dv_d.take(flat), r2_d.take(flat), dd_d.take(flat)
        sp2 = sp[pi] ** 2
        sq2 = sq2_all[qi]
        s2 = sp2 + sq2
        inv_s2 = 1.0 / s2
        e = np.exp(-0.5 * r2 * inv_s2)
        D = _TWO_PI * sp2 * sq2 * inv_s2 * e
        shp = sh[pi]
        delta = 1.0 - np.abs(dd) / (2.0 * shp)
        inv_norm = 1.0 / data.norm
        sim = float((delta * D).sum() * inv_norm)
        # Dangling Gaussians (eq. 7): distance from each model Gaussian to the
        # data, occlusion-aware (see the module docstring).
        r_d = np.sqrt(r2_d)
        lat_px = np.maximum(r_d - self._half, 0.0)
        scale = (z / self._f)[:, None]  # mm per px at the model's depth
        behind = np.maximum(-dd_d, 0.0)  # data farther than the model's surface
        dist2 = lat_px * lat_px * (scale * scale) + behind * behind
        nearest = dist2.argmin(axis=1)
        dmin = np.sqrt(dist2[np.arange(m), nearest])
        wdang = np.clip((dmin - TAU1_MM) / TAU1_MM, 0.0, 1.0)
        rows = np.nonzero(wdang > 0.0)[0]
        dan = 0.0
        if rows.size:
            dist_r = np.sqrt(dist2[rows])
            phi = np.clip((dist_r - TAU1_MM) / (TAU2_MM - TAU1_MM), 0.0, 1.0)
            s2r = (sp[rows] ** 2)[:, None] + sq2_all[None, :]
            er = np.exp(-0.5 * r2_d[rows] / s2r)
            per_p = (phi * (1.0 - er)).sum(1) / data.n
            dan = float((wdang[rows] * per_p).sum())
        if g3 is None:
            return sim, dan
        # d/d(u, v, sigma_p, d_p) of E_sim, accumulated per model Gaussian.
        wD = delta * D * inv_norm
        spp = sp[pi]
        g_u = _accumulate(pi, -wD * du * inv_s2, m)
        g_v = _accumulate(pi, -wD * dv * inv_s2, m)
        g_sp = _accumulate(pi, wD * (2.0 / spp - 2.0 * spp * inv_s2 + r2 * spp * inv_s2 * inv_s2), m)
        g_dp = _accumulate(pi, D * (-np.sign(dd) / (2.0 * shp)), m) * inv_norm
        g_z = np.zeros(m)  # explicit z-dependence of the dangle distances
        if rows.size and w_dan > 0:
            wn = (w_dan * wdang[rows] / data.n)[:, None]
            pe = wn * phi * er
            inv_s2r = 1.0 / s2r
            spr = sp[rows][:, None]
            du_r, dv_r = du_d[rows], dv_d[rows]
            # d(1 - e)/du = e du / s2 ; d(1 - e)/dsp = -e r2 sp / s2^2
            g_u[rows] -= (pe * du_r * inv_s2r).sum(1)
            g_v[rows] -= (pe * dv_r * inv_s2r).sum(1)
            g_sp[rows] += (pe * r2_d[rows] * spr * inv_s2r * inv_s2r).sum(1)
            # Derivatives of the distance: lat = max(r - half, 0) z / f, behind = max(dq - dp, 0).
            lat_r = lat_px[rows] * scale[rows]
            beh_r, r_r = behind[rows], np.maximum(r_d[rows], 1e-9)
            inv_dist = 1.0 / np.maximum(dist_r, 1e-9)
            on_lat = lat_px[rows] > 0.0
            k_u = np.where(on_lat, lat_r * scale[rows] / r_r, 0.0) * inv_dist  # d dist / du per du
            k_z = np.where(on_lat, lat_r * lat_px[rows] / self._f, 0.0) * inv_dist
            k_dp = -beh_r * inv_dist  # d dist / d dp
            ramp = (dist_r > TAU1_MM) & (dist_r < TAU2_MM)
            c_phi = wn * np.where(ramp, 1.0 / (TAU2_MM - TAU1_MM), 0.0) * (1.0 - er)
            # Through the dangling weight: d dmin / d(.) at the nearest data Gaussian.
            on_ramp = (dmin[rows] > TAU1_MM) & (dmin[rows] < 2.0 * TAU1_MM)
            c_min = np.zeros_like(c_phi)
            c_min[np.arange(rows.size), nearest[rows]] = w_dan * on_ramp * per_p / TAU1_MM
            c = c_phi + c_min
            g_u[rows] -= (c * k_u * du_r).sum(1)
            g_v[rows] -= (c * k_u * dv_r).sum(1)
            g_z[rows] -= (c * k_z).sum(1)
            g_dp[rows] -= (c * k_dp).sum(1)
        f = self._f
        g3[:, 0] += g_u * intr.fx / z
        g3[:, 1] += g_v * intr.fy / z
        g3[:, 2] += (
            -g_u * intr.fx * x / (z * z)
            - g_v * intr.fy * y / (z * z)
            - g_sp * sh * f / (z * z)
            + g_dp
            + g_z
        )
        return sim, dan

    def _collision(
        self, P: NDArray[np.float64], g3: NDArray[np.float64] | None, w_col: float
    ) -> float:
        """``E_col`` (eq. 6); adds ``-w_col dE_col/dP`` into ``g3``."""
        c = self._const
        diff = P[c.pair_i] - P[c.pair_j]
        r2 = (diff * diff).sum(1)
        D = c.pair_amp * np.exp(-0.5 * r2 / c.pair_s2)
        col = float(D.sum() / c.norm_h)
        if g3 is not None and w_col > 0:
            g = (-(D / c.pair_s2)[:, None] * diff) / c.norm_h  # dE_col/dP_i (pairs, 3)
            g3 -= w_col * (c.incidence @ g)
        return col

    def _limits(self, theta: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
        """``E_lim`` (eq. 8) and its gradient, shape (26,)."""
        q = theta[6:]
        lo = np.minimum(q - self.model.limits_low, 0.0)
        hi = np.maximum(q - self.model.limits_high, 0.0)
        g = np.zeros(N_PARAMS)
        g[6:] = 2.0 * (lo + hi)
        return float((lo * lo).sum() + (hi * hi).sum()), g

    def _order(self, theta: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
        """``E_ord`` and its gradient, shape (26,): neighbouring fingers may not cross."""
        abd = theta[6 + 4 + 1 :: 4]  # MCP abduction of index .. little, shape (4,)
        gap = np.diff(self._const.fan + abd)  # (3,)
        short = np.minimum(gap - ORDER_MIN_GAP_RAD, 0.0)
        g = np.zeros(N_PARAMS)
        if not short.any():
            return 0.0, g
        # d/d abd_{c+1} of short^2 is 2 short, d/d abd_c is -2 short.
        g_abd = np.zeros(4)
        g_abd[1:] += 2.0 * short
        g_abd[:-1] -= 2.0 * short
        g[6 + 4 + 1 :: 4] = g_abd
        return float((short * short).sum()), g

    def _salient(
        self, P: NDArray[np.float64], g3: NDArray[np.float64] | None, w_sal: float
    ) -> float:
        """``E_sal``; adds ``-w_sal dE_sal/dP`` into ``g3`` at the fingertip Gaussians."""
        t = self.targets
        if t is None or w_sal <= 0 or not np.any(t.weights > 0):
            return 0.0
        tips = self.model.tip_index
        diff = P[tips] - t.points
        root = np.sqrt((diff * diff).sum(1) + SALIENT_SOFT_MM**2)
        w = t.weights / SALIENT_SCALE_MM
        val = float((w * (root - SALIENT_SOFT_MM)).sum())
        if g3 is not None:
            g3[tips] -= w_sal * (w / root)[:, None] * diff
        return val

    def _smoothness(self, theta: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
        """``E_smo`` (eq. 9) and its gradient, shape (26,)."""
        if self.previous is None:
            return 0.0, np.zeros(N_PARAMS)
        p1, p2 = self.previous
        s = _smooth_scale()
        r = s * (0.5 * (p2 + theta) - p1)
        return float((r * r).sum()), r * s
