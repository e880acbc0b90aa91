"""The tracking objective and its analytic gradient (paper 000, sec. 5.2).

One job: the objective and its gradient; kept together because every term shares the model
constants and the pose's kinematics, and each gradient reads best next to its energy.

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
from hand_sog_tracker.core.hand_model import FINGER_ABD, JOINTS, N_PARAMS, HandModel, rest_pose
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

#: Near threshold ``tau_1`` of the dangling term (mm): a model Gaussian this close to data is
#: not dangling (paper 000 sec. 5.2 names tau_1, tau_2 without values: chosen here).
TAU1_MM = 15.0
#: Far threshold ``tau_2`` of the dangling term (mm): the penalty ramp ends here (chosen here).
TAU2_MM = 60.0
#: Translation unit of the smoothness term (mm per rad-equivalent; chosen here, paper 000
#: eq. 9 mixes mm and rad unweighted).
SMOOTH_TRANSLATION_MM = 50.0
#: Smallest allowed difference of neighbouring fingers' palm-plane directions (rad, chosen here); at rest
#: they fan out by 0.07-0.09 rad; a finger on its neighbour's data needs about -0.25.
ORDER_MIN_GAP_RAD = -0.05
#: Width of the flat bottom of the salient-point cost (mm; chosen here, seed 001 ignores pairs
#: under 10 mm).
SALIENT_SOFT_MM = 8.0
#: The salient cost is measured in units of this distance (mm; chosen here).
SALIENT_SCALE_MM = 100.0
_TWO_PI = 2.0 * np.pi
_INV_SQRT2 = 1.0 / np.sqrt(2.0)


def _accumulate(index: NDArray[np.int64], weights: NDArray[np.float64], size: int) -> NDArray[np.float64]:
    """Sum ``weights`` per ``index`` into a float array of length ``size`` (empty-safe)."""
    return np.bincount(index, weights=weights, minlength=size).astype(np.float64, copy=False)


_ROWS_COLS: dict[tuple[int, int], tuple[NDArray[np.int64], NDArray[np.int64]]] = {}


def _flat_rows_cols(m: int, n: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Row and column of every flat index of an (m, n) array (cached: divmod is slow)."""
    hit = _ROWS_COLS.get((m, n))
    if hit is None:
        if len(_ROWS_COLS) >= 4:  # n changes from frame to frame: keep only the latest few
            _ROWS_COLS.clear()
        hit = (np.repeat(np.arange(m), n), np.tile(np.arange(n), m))
        _ROWS_COLS[(m, n)] = hit
    return hit


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
    scatter: NDArray[np.int64]  # (2 pairs 3,): flat index into (m, 3) of i's then j's coordinates
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
        scatter=np.concatenate([(3 * pi[:, None] + np.arange(3)).ravel(), (3 * pj[:, None] + np.arange(3)).ravel()]),
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
        self._row_of, self._col_of = _flat_rows_cols(model.n_gaussians, data.n)

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
        pi, qi = self._row_of.take(flat), self._col_of.take(flat)
        du, dv, r2, dd = du_d.take(flat), dv_d.take(flat), r2_d.take(flat), dd_d.take(flat)
        sp_sq = sp * sp
        sp2 = sp_sq.take(pi)
        sq2 = sq2_all.take(qi)
        s2 = sp2 + sq2
        inv_s2 = 1.0 / s2
        e = np.exp(-0.5 * r2 * inv_s2)
        D = (_TWO_PI * sp_sq).take(pi) * sq2 * inv_s2 * e
        two_shp = (2.0 * sh).take(pi)
        delta = 1.0 - np.abs(dd) / two_shp
        inv_norm = 1.0 / data.norm
        sim = float((delta * D).sum() * inv_norm)
        # Dangling Gaussians (eq. 7): distance from each model Gaussian to the data,
        # occlusion-aware (see the module docstring), dmin its minimum over the data.  A
        # candidate pair within TAU1 settles dmin <= TAU1 (weight 0); only the other rows
        # (typically none to a few) need the distances to all data Gaussians.
        scale = z / self._f  # mm per px at the model's depth
        lat_c = np.maximum(np.sqrt(r2) - self._half.take(qi), 0.0)
        beh_c = np.maximum(-dd, 0.0)
        near_c = lat_c * lat_c * (scale * scale).take(pi) + beh_c * beh_c <= TAU1_MM * TAU1_MM
        settled = np.zeros(m, dtype=bool)
        settled[pi[near_c]] = True
        U = np.flatnonzero(~settled)
        dan = 0.0
        sel = U[:0]
        if U.size:
            du_U, dv_U, r2_U = du_d[U], dv_d[U], r2_d[U]
            r_U = np.sqrt(r2_U)
            lat_U = np.maximum(r_U - self._half, 0.0)
            scale_U = scale[U][:, None]
            behind_U = np.maximum(-dd_d[U], 0.0)  # data farther than the model's surface
            dist2_U = lat_U * lat_U * (scale_U * scale_U) + behind_U * behind_U
            nearest_U = dist2_U.argmin(axis=1)
            dmin_U = np.sqrt(dist2_U[np.arange(U.size), nearest_U])
            wdang_U = np.clip((dmin_U - TAU1_MM) / TAU1_MM, 0.0, 1.0)
            sel = np.flatnonzero(wdang_U > 0.0)
        rows = U[sel]
        if rows.size:
            dist_r = np.sqrt(dist2_U[sel])
            phi = np.clip((dist_r - TAU1_MM) / (TAU2_MM - TAU1_MM), 0.0, 1.0)
            s2r = (sp[rows] ** 2)[:, None] + sq2_all[None, :]
            r2_r = r2_U[sel]
            er = np.exp(-0.5 * r2_r / s2r)
            per_p = (phi * (1.0 - er)).sum(1) / data.n
            dan = float((wdang_U[sel] * per_p).sum())
        if g3 is None:
            return sim, dan
        # d/d(u, v, sigma_p, d_p) of E_sim, accumulated per model Gaussian.
        # The pairs come sorted by model Gaussian (row-major order of the mask): the four
        # per-Gaussian sums are one segmented sum over the columns of W.
        wD = delta * D * inv_norm
        a = wD * inv_s2
        spp = sp.take(pi)
        W = np.empty((pi.size, 4))
        np.multiply(a, du, out=W[:, 0])
        np.multiply(a, dv, out=W[:, 1])
        # wD (2 / sp - 2 sp / s2 + r2 sp / s2^2)
        np.add(2.0 * wD / spp, spp * (a * (r2 * inv_s2 - 2.0)), out=W[:, 2])
        np.multiply(D, np.sign(dd) / two_shp, out=W[:, 3])
        per_row = mask.sum(axis=1)
        acc = np.zeros((m, 4))
        if pi.size:
            nz = per_row > 0
            acc[nz] = np.add.reduceat(W, (np.cumsum(per_row) - per_row)[nz], axis=0)
        g_u = -acc[:, 0]
        g_v = -acc[:, 1]
        g_sp = acc[:, 2]
        g_dp = acc[:, 3] * -inv_norm
        g_z = np.zeros(m)  # explicit z-dependence of the dangle distances
        if rows.size and w_dan > 0:
            wn = (w_dan * wdang_U[sel] / data.n)[:, None]
            pe = wn * phi * er
            inv_s2r = 1.0 / s2r
            spr = sp[rows][:, None]
            du_r, dv_r = du_U[sel], dv_U[sel]
            # d(1 - e)/du = e du / s2 ; d(1 - e)/dsp = -e r2 sp / s2^2
            g_u[rows] -= (pe * du_r * inv_s2r).sum(1)
            g_v[rows] -= (pe * dv_r * inv_s2r).sum(1)
            g_sp[rows] += (pe * r2_r * spr * inv_s2r * inv_s2r).sum(1)
            # Derivatives of the distance: lat = max(r - half, 0) z / f, behind = max(dq - dp, 0).
            lat_px_r, scale_r = lat_U[sel], scale_U[sel]
            lat_r = lat_px_r * scale_r
            beh_r, r_r = behind_U[sel], np.maximum(r_U[sel], 1e-9)
            inv_dist = 1.0 / np.maximum(dist_r, 1e-9)
            on_lat = lat_px_r > 0.0
            k_u = np.where(on_lat, lat_r * scale_r / r_r, 0.0) * inv_dist  # d dist / du per du
            k_z = np.where(on_lat, lat_r * lat_px_r / self._f, 0.0) * inv_dist
            k_dp = -beh_r * inv_dist  # d dist / d dp
            ramp = (dist_r > TAU1_MM) & (dist_r < TAU2_MM)
            c_phi = wn * np.where(ramp, 1.0 / (TAU2_MM - TAU1_MM), 0.0) * (1.0 - er)
            # Through the dangling weight: d dmin / d(.) at the nearest data Gaussian.
            dmin_r = dmin_U[sel]
            on_ramp = (dmin_r > TAU1_MM) & (dmin_r < 2.0 * TAU1_MM)
            c_min = np.zeros_like(c_phi)
            c_min[np.arange(rows.size), nearest_U[sel]] = w_dan * on_ramp * per_p / TAU1_MM
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
        diff = P.take(c.pair_i, axis=0) - P.take(c.pair_j, axis=0)  # (faster than P[idx])
        r2 = (diff * diff).sum(1)
        D = c.pair_amp * np.exp(-0.5 * r2 / c.pair_s2)
        col = float(D.sum() / c.norm_h)
        if g3 is not None and w_col > 0:
            g = (-(D / c.pair_s2)[:, None] * diff) / c.norm_h  # dE_col/dP_i (pairs, 3)
            # incidence @ g: + g at each pair's i, - g at its j.
            g_all = np.bincount(
                c.scatter, weights=np.concatenate([g.ravel(), -g.ravel()]), minlength=3 * P.shape[0]
            )
            g3 -= w_col * g_all.reshape(-1, 3)
        return col

    def _limits(self, theta: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
        """``E_lim`` (eq. 8) and its gradient, shape (26,)."""
        q = theta[JOINTS]
        lo = np.minimum(q - self.model.limits_low, 0.0)
        hi = np.maximum(q - self.model.limits_high, 0.0)
        g = np.zeros(N_PARAMS)
        g[JOINTS] = 2.0 * (lo + hi)
        return float((lo * lo).sum() + (hi * hi).sum()), g

    def _order(self, theta: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
        """``E_ord`` and its gradient, shape (26,): neighbouring fingers may not cross."""
        abd = theta[FINGER_ABD]  # MCP abduction of index .. little, shape (4,)
        a = self._const.fan + abd
        gap = a[1:] - a[:-1]  # (3,), as np.diff
        short = np.minimum(gap - ORDER_MIN_GAP_RAD, 0.0)
        g = np.zeros(N_PARAMS)
        if not short.any():
            return 0.0, g
        # d/d abd_{c+1} of short^2 is 2 short, d/d abd_c is -2 short.
        g_abd = np.zeros(4)
        g_abd[1:] += 2.0 * short
        g_abd[:-1] -= 2.0 * short
        g[FINGER_ABD] = g_abd
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
