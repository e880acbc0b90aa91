"""The data terms ``E_sim`` and ``E_dan`` (paper 000, eq. 5 and 7), the support of each model
Gaussian by the data and the visibility weights."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.depth_sog import ImageSoG
from hand_sog_tracker.core.hand_model import HandModel
from hand_sog_tracker.core.kinematics import gaussian_centres
from hand_sog_tracker.core.objective.arrays import (
    _INV_SQRT2,
    _TWO_PI,
    Backward,
    _accumulate,
    _flat_cols,
    _segment_sums,
    _sum,
)
from hand_sog_tracker.core.objective.constants import PAIR_CUT_SIGMAS, SIM_GAIN, TAU1_MM, TAU2_MM
from hand_sog_tracker.core.silhouette import run_or_defer
from hand_sog_tracker.core.types import Intrinsics

__all__ = ["DataTerms", "gaussian_support", "visibility_weights"]


_DATA_CACHE: list = [(None, 0, None)]  # (data, m, constants) of the last data: one tuple

#: A candidate pair whose ``r2 scale^2 + min(dd, 0)^2`` is at most this (mm^2) is within
#: ``TAU1_MM`` of its model Gaussian for certain (see :meth:`Objective._data_terms`; the
#: factor leaves 1e-12 for rounding errors below 1e-14).
_NEAR_SAFE = TAU1_MM * TAU1_MM * (1.0 - 1e-12)
#: The pairs' squared image distance cut in combined variances (:data:`PAIR_CUT_SIGMAS` squared).
_CUT2 = PAIR_CUT_SIGMAS * PAIR_CUT_SIGMAS


def _data_constants(data: ImageSoG, m: int) -> tuple:
    """Constants of the data terms for a frame's data and ``m`` model Gaussians (cached for
    the last data: a frame builds several objectives on the same data).

    Returns ``mu_u, mu_v, sigma^2, half side`` (n,) each, the candidate matrix (2, 6, n) of
    :meth:`Objective._data_terms`, the first flat index of each model Gaussian's row (m + 1,)
    and the per-data values read per pair (4, n): ``mu_u, mu_v, depth, sigma^2``.
    """
    hit = _DATA_CACHE[0]
    if hit[0] is data and hit[1] == m:
        return hit[2]
    n = data.n
    mu_u = np.ascontiguousarray(data.mu[:, 0], dtype=np.float64)
    mu_v = np.ascontiguousarray(data.mu[:, 1], dtype=np.float64)
    sq2 = data.sigma**2
    half = data.sigma * _INV_SQRT2  # half a quad's side, px
    depth = np.asarray(data.depth, dtype=np.float64)
    # Both candidate tests of every (model, data) pair are one matrix product: six values per
    # model Gaussian times two (6, n) blocks (expanded squares, see _data_terms).
    cand = np.zeros((2, 6, n))
    cand[0, 0] = 1.0
    cand[0, 2] = mu_u * mu_u + mu_v * mu_v - _CUT2 * sq2
    cand[0, 3] = -2.0 * mu_u
    cand[0, 4] = -2.0 * mu_v
    cand[1, 1] = 1.0
    cand[1, 2] = depth * depth
    cand[1, 5] = -2.0 * depth
    const = (mu_u, mu_v, sq2, half, cand, np.arange(m + 1) * n, np.array([mu_u, mu_v, depth, sq2]))
    _DATA_CACHE[0] = (data, m, const)
    return const


class _Rows:
    """The model Gaussians' constants and buffers of :meth:`Objective._data_terms` (and the
    collision term's scatter) for one pose or a batch of B poses, whose B m model Gaussians
    stand pose after pose (a plain class with slots; see :meth:`Objective._layout`).

    ``rows`` (11, B m) per model Gaussian values (rows 2 and 8 constant), ``tests`` (2, B m,
    n) and ``neg`` (B m, n) the candidate tests' buffers, ``row_starts`` (B m + 1,) the flat
    index of each row's first pair, ``col_of`` (B m n,) the image Gaussian of every flat
    index, in the pose's block (``b n + q``), ``per_q`` (4, B n) and ``sat_k`` (B n,) the
    image Gaussians' values (once per pose), ``sigmas``, ``shf``, ``two_sh``, ``four_sh2``
    and ``visibility`` (B m,) the model Gaussians' (``visibility`` None: all 1),
    ``col_scatter`` the collision gradient's flat indices into (B m 3,).
    """

    __slots__ = (
        "B", "batch", "rows", "tests", "neg", "row_starts", "col_of", "per_q", "sat_k", "sigmas", "shf",
        "two_sh", "four_sh2", "visibility", "col_scatter",
    )

    def __init__(self, B: int, batch: bool, *arrays: NDArray | None) -> None:
        self.B, self.batch = B, batch
        (
            self.rows, self.tests, self.neg, self.row_starts, self.col_of, self.per_q, self.sat_k, self.sigmas,
            self.shf, self.two_sh, self.four_sh2, self.visibility, self.col_scatter,
        ) = arrays



#: Slack (px^2 and mm^2) of the expanded-square candidate tests in :func:`gaussian_support`:
#: far above their rounding (below 1e-7 for images up to 4096 px and depths up to 10 m), so
#: that every pair the exact tests pass is a candidate.
_SUPPORT_SLACK = 1e-3


def gaussian_support(
    model: HandModel,
    theta: NDArray[np.float64],
    data: ImageSoG,
    centres: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """How well the data explain each model Gaussian at ``theta``, shape (m,), in [0, 1].

    For Gaussian ``p`` the depth-weighted overlap with the data, ``sum_q Delta_pq D_pq``,
    divided by its value under a gap-free data tiling at the right depth (``2 pi^2 sp^2``,
    px), capped at 1.  ``centres``: the model Gaussians' centres at ``theta`` (m, 3) mm, when
    already computed.  Only the pairs that can contribute count (as in the objective):
    ``Delta = 0`` beyond two radii in depth, ``D`` is below 3.7e-6 of its peak beyond
    :data:`PAIR_CUT_SIGMAS` (5) combined standard deviations.

    The pairs are found as in :meth:`Objective._data_terms` (both tests as one matrix
    product, here with a slack that keeps every pair the exact tests pass), and the exact
    tests and values are then computed on those candidates only: bit-identical to computing
    them on all ``m x n`` pairs, several times cheaper.
    """
    m = model.n_gaussians
    n = data.n
    if n == 0:
        return np.zeros(m)
    intr = data.intrinsics
    P = gaussian_centres(model, theta) if centres is None else centres
    sh = model.g_sigmas
    z = np.maximum(P[:, 2], 1.0)
    # Per model Gaussian (rows): the two tests' own terms, ones, u, v, dp, sp^2, 2 sigma_h
    # (written in place: the same operations as the expressions in the comments).
    rows = np.empty((8, m))
    u, v, dp, sp2, two_sh = rows[3:]
    np.multiply(intr.fx, P[:, 0], out=u)
    u /= z
    u += intr.cx  # fx x / z + cx
    np.multiply(intr.fy, P[:, 1], out=v)
    v /= z
    v += intr.cy  # fy y / z + cy
    np.multiply(sh, np.sqrt(intr.fx * intr.fy), out=sp2)
    sp2 /= z
    np.multiply(sp2, sp2, out=sp2)  # (sh f / z)^2
    np.subtract(z, sh, out=dp)
    np.multiply(2.0, sh, out=two_sh)
    t = u * u
    t += v * v
    t -= _CUT2 * sp2
    rows[0] = t  # u^2 + v^2 - c^2 sp^2
    np.multiply(dp, dp, out=rows[1])
    rows[1] -= two_sh * two_sh  # dp^2 - (2 sigma_h)^2
    rows[2] = 1.0
    cand, row_starts, per_q = _data_constants(data, m)[4:]
    near = np.matmul(rows[:6].T, cand) < _SUPPORT_SLACK  # (2, m, n): candidates of both tests
    flat = np.logical_and(near[0], near[1], out=near[0]).ravel().nonzero()[0]
    bounds = flat.searchsorted(row_starts)
    per_row = bounds[1:] - bounds[:-1]
    p = np.arange(m).repeat(per_row)
    per_p = rows[3:].repeat(per_row, axis=1)  # u, v, dp, sp^2, 2 sigma_h per pair
    sp2_p, two_sh_p = per_p[3:]
    q = per_q[:4].take(_flat_cols(m, n).take(flat), axis=1)  # mu_u, mu_v, depth, sigma_q^2
    sq2_q = q[3]
    diffs = np.subtract(per_p[:3], q[:3], out=q[:3])  # du, dv, dp - depth
    sq = diffs[:2] * diffs[:2]
    r2 = np.add(sq[0], sq[1], out=sq[0])  # du^2 + dv^2
    dd = np.abs(diffs[2], out=diffs[2])
    s2 = np.add(sp2_p, sq2_q, out=per_p[0])  # s2 = sp^2 + sq^2
    # D = 2 pi sp^2 sq^2 / s2 exp(-0.5 r2 / s2), in this order
    e = np.multiply(-0.5, r2, out=sq[1])
    e /= s2
    np.exp(e, out=e)
    D = np.multiply(_TWO_PI, sp2_p, out=sp2_p)
    D *= sq2_q
    D /= s2
    D *= e
    # The exact tests; a candidate failing them adds an exact 0 (the sums are unchanged).
    passed = np.less(dd, two_sh_p)
    passed &= r2 < np.multiply(_CUT2, s2, out=s2)
    delta = np.divide(dd, two_sh_p, out=dd)
    np.subtract(1.0, delta, out=delta)  # Delta = 1 - dd / (2 sigma_h)
    delta *= D
    support = _accumulate(p, np.where(passed, delta, 0.0), m)
    support /= 2 * np.pi**2 * sp2
    return np.minimum(support, 1.0, out=support)


def visibility_weights(model: HandModel, theta: NDArray[np.float64], intr: Intrinsics) -> NDArray[np.float64]:
    """How visible each model Gaussian is at ``theta`` (26,) to the camera ``intr``, as a
    weight of its overlaps in ``E_sim``, shape (m,) in [0, 1].

    Only the Gaussians whose overlaps the fingers can steal are weighted: the palm's and the
    distal segments' of index .. little (``g_segment`` 2, a joint model's DIP Gaussians
    included); the others keep 1.  Such a Gaussian ``i`` is hidden by each finger Gaussian ``j``
    (the thumb's included; ``j != i``) by ``cover_ij front_ij``: ``cover_ij = exp(-r_ij^2 / (2
    s_j^2))`` with ``r_ij`` the image distance (px) of their projected centres and ``s_j`` the
    projected sigma of ``j`` (px); ``front_ij`` ramps from 0 to 1 as the front of ``j``
    (``z_j - sigma_j``, mm) lies 0 to ``sigma_i`` in front of the front of ``i``.  The weight
    is ``prod_j (1 - cover_ij front_ij)``: 1 for a Gaussian in plain view, near 0 for the
    palm behind a curled finger or a fingertip tucked behind its own middle segment or the
    thumb.  (Without the thumb's Gaussians as occluders the mesh sets scored 0.08-0.10 mm
    worse: dev 5.70, validation 5.83, further 5.66 mm.)
    """
    P = gaussian_centres(model, theta)
    z = np.maximum(P[:, 2], 1.0)
    u = intr.fx * P[:, 0] / z
    v = intr.fy * P[:, 1] / z
    sigma = model.g_sigmas
    s = sigma * float(np.sqrt(intr.fx * intr.fy)) / z  # projected sigmas (px)
    chain = model.g_chain
    hidden = np.flatnonzero((chain < 0) | ((chain >= 1) & (model.g_segment == 2)))
    occluders = np.flatnonzero(chain >= 0)
    r2 = np.square(u[hidden, None] - u[None, occluders]) + np.square(v[hidden, None] - v[None, occluders])
    cover = np.exp(-0.5 * r2 / np.square(s[occluders])[None, :])
    front = z - sigma
    ahead = np.clip((front[hidden, None] - front[None, occluders]) / sigma[hidden, None], 0.0, 1.0)
    ahead[hidden[:, None] == occluders[None, :]] = 0.0  # (a Gaussian does not hide itself)
    weights = np.ones(model.n_gaussians)
    weights[hidden] = np.prod(1.0 - cover * ahead, axis=1)
    return weights



class DataTerms:
    """``E_sim`` and ``E_dan`` of :class:`~hand_sog_tracker.core.objective.Objective` (a mixin:
    reads its data constants, layouts and camera values)."""

    def _data_terms(
        self,
        P: NDArray[np.float64],
        g3: NDArray[np.float64] | None,
        w_dan: float,
        z: NDArray[np.float64] | None = None,
        proj: NDArray[np.float64] | None = None,
        later: list[Backward] | None = None,
        lay: _Rows | None = None,
        parts: tuple[NDArray[np.float64], ...] | None = None,
    ) -> tuple[float | NDArray[np.float64], float | NDArray[np.float64]]:
        """``E_sim`` and ``E_dan``; adds ``dE/dP`` (with signs and weights) into ``g3``.

        ``lay``: the layout of a batch of B poses (:meth:`_layout`), whose B m model
        Gaussians ``P`` (B m, 3) holds pose after pose; then both are (B,) arrays.  Every step
        below runs on the B m rows as on the m rows of one pose; only the image Gaussians'
        saturation (per pose and image Gaussian) and the two sums are taken per pose.

        ``z``, ``proj``: ``max(P_z, 1)`` (m,) mm and ``(fx x / z, fy y / z)`` (2, m) px when
        already computed (the same operations as here: the same bits).  ``later``: instead of
        adding into ``g3`` now, append the function that does (see :meth:`value_then_gradient`).

        ``E_sim`` is summed over the pairs that can contribute: depth difference
        under ``2 sigma_h`` (else ``Delta = 0`` exactly) and image distance under
        :data:`PAIR_CUT_SIGMAS` combined standard deviations ``c`` (beyond, ``D_pq < exp(-c^2 / 2) D_pq^0``).
        ``E_dan`` is evaluated on the rows of dangling Gaussians only.

        Both candidate tests of all m x n pairs are one matrix product (expanded squares:
        ``r^2 - c^2 (s_p^2 + s_q^2) = (u_p^2 + v_p^2 - c^2 s_p^2) + (mu_q^2 - c^2 s_q^2)
        - 2 u_p mu_uq - 2 v_p mu_vq`` and ``dd^2 - (2 sigma_h)^2`` likewise); the values of
        the pairs that pass are then computed exactly as their definitions (the expansion
        can only decide pairs within rounding of a test's boundary, where both the overlap
        and ``Delta`` vanish).

        ``parts`` (a batch only): each pose sees only a part of the data, as
        ``_batch_parts`` describes it (its pairs with the others fail the candidate tests, its
        sums, norm and dangling distances are its part's).
        """
        data = self.data
        n = data.n
        if n == 0 or data.norm <= 0:
            return 0.0, 0.0
        m = P.shape[0]
        if z is None or proj is None:
            z = np.maximum(P[:, 2], 1.0)
            proj = np.multiply(self._fxy, P[:, :2].T)
            proj /= z
        # Per model Gaussian (rows): 0 and 1 the tests' own terms, 2 ones, 3-5 u, v, dp (rows
        # 0-5 enter the candidate product), 6-9 sp^2, 2 pi sp^2 (times the visibility weight, if
        # any), 2 sigma_h, (mm per px)^2
        # (rows 3-9 are read per pair: contiguous rows, strided columns would slow down exp),
        # 10 sp.  Rows 2 and 8 are constant.  u, v as one (2, m) array: NumPy's per-call cost
        # dominates at this size.
        L = self._one if lay is None else lay
        rows = L.rows
        uv, dp, sp_sq, sp = rows[3:5], rows[5], rows[6], rows[10]
        np.add(proj, self._cxy, out=uv)  # u = fx x / z + cx, v = fy y / z + cy
        np.subtract(z, L.sigmas, out=dp)
        np.divide(L.shf, z, out=sp)
        np.multiply(sp, sp, out=sp_sq)
        np.multiply(_TWO_PI, sp_sq, out=rows[7])
        if L.visibility is not None:  # (a factor of every overlap of the Gaussian: D)
            rows[7] *= L.visibility
        scale = z / self._f  # mm per px at the model's depth
        np.multiply(scale, scale, out=rows[9])
        # rows 0-1: u^2 + v^2 - c^2 sp^2, dp^2 - (2 sigma_h)^2 (c: PAIR_CUT_SIGMAS)
        uv2 = uv * uv
        np.add(uv2[0], uv2[1], out=rows[0])
        rows[0] -= _CUT2 * sp * sp
        np.multiply(dp, dp, out=rows[1])
        rows[1] -= L.four_sh2
        tests = np.matmul(rows[:6].T, self._cand, out=L.tests)  # (2, m, n): < 0: pass
        # Both tests pass (< 0) exactly when the larger does: one comparison of (m, n) values.
        worst = np.maximum(tests[0], tests[1], out=tests[0])
        passed = np.less(worst, 0.0, out=L.neg)
        if parts is not None:  # (the pairs with the Gaussians outside a pose's part fail)
            passed3 = passed.reshape(L.B, m // L.B, n)
            np.logical_and(passed3, parts[4][:, None, :], out=passed3)
        flat = passed.ravel().nonzero()[0]
        # Pairs per model Gaussian (the pairs come sorted by it): where each row's run starts.
        bounds = flat.searchsorted(L.row_starts)
        per_row = bounds[1:] - bounds[:-1]
        qi = L.col_of.take(flat)  # (in a batch: its pose's block of image Gaussians, b n + q)
        # Rows 3-9 of each pair's model Gaussian: its values repeated over its run (one call
        # instead of a gather per value); its data Gaussian's values, one gather.
        per_p = rows[3:10].repeat(per_row, axis=1)
        sp_sq_p, tpsp_p, two_sh_p, scale2_p = per_p[3:]
        per_q = L.per_q.take(qi, axis=1)  # mu_u, mu_v, depth, sigma^2
        diffs = np.subtract(per_p[:3], per_q[:3], out=per_q[:3])
        du, dv, dd = diffs  # u - mu_u, v - mu_v, dp - depth
        # Per pair, in place where a value is not needed again (the same operations, fewer
        # temporary arrays).
        sq = diffs[:2] * diffs[:2]
        r2 = np.add(sq[0], sq[1], out=sq[0])  # du^2 + dv^2
        sq2 = per_q[3]
        inv_s2 = np.add(sp_sq_p, sq2, out=sp_sq_p)  # s2 = sp^2 + sq^2 ...
        np.divide(1.0, inv_s2, out=inv_s2)  # ... inverted
        r2_s2 = r2 * inv_s2
        e = np.multiply(r2_s2, -0.5, out=sq[1])
        np.exp(e, out=e)  # = exp(-0.5 r2 inv_s2) exactly (0.5: exact scaling)
        D = np.multiply(tpsp_p, sq2, out=tpsp_p)
        D *= inv_s2
        D *= e  # 2 pi sp^2 sq^2 / s2 e
        delta_D = np.abs(dd)
        delta_D /= two_sh_p
        np.subtract(1.0, delta_D, out=delta_D)  # Delta = 1 - |dd| / (2 sigma_h) ...
        delta_D *= D  # ... times D
        if not L.batch:
            self._support_src = (delta_D, bounds, z)
        inv_norm = 1.0 / data.norm if parts is None else parts[1]  # (per pose with parts)
        # Saturated per image Gaussian (module docstring): S_q, then G k_q (1 - exp(-S_q / k_q)).
        k = L.sat_k
        sat = _accumulate(qi, delta_D, k.size)
        sat /= k
        np.negative(sat, out=sat)
        np.expm1(sat, out=sat)  # exp(-S_q / k_q) - 1 (exact for small overlaps)
        if L.batch:
            sim: float | NDArray[np.float64] = _sum((k * sat).reshape(L.B, n), axis=1) * (-SIM_GAIN * inv_norm)
        else:
            sim = float(_sum(k * sat) * (-SIM_GAIN * inv_norm))
        # Dangling Gaussians (eq. 7): distance from each model Gaussian to the data,
        # occlusion-aware (see the module docstring), dmin its minimum over the data:
        # ``dist^2 = lat^2 scale^2 + beh^2`` with ``lat = max(sqrt(r2) - half, 0)`` and
        # ``beh = min(dd, 0)``.  A model Gaussian with dmin <= TAU1 has weight 0.  As ``lat``
        # is at most ``sqrt(r2)``, a candidate pair with ``r2 scale^2 + beh^2 <= _NEAR_SAFE``
        # settles dmin <= TAU1 (four passes over the pairs fewer than ``dist``; typically it
        # settles every row but none to a few).  The other rows get the distances to all data
        # Gaussians, computed per element as ``dist`` is on a pair: a row with a pair within
        # TAU1 has dmin <= TAU1 there, weight 0, and drops out as if it had been settled here.
        beh_c = np.minimum(dd, 0.0, out=e)  # minus how far the data lie behind: squared below
        beh_c *= beh_c
        bound_c = np.multiply(r2, scale2_p, out=r2)  # (r2 is not needed again)
        bound_c += beh_c
        near_c = bound_c <= _NEAR_SAFE
        nz = per_row > 0
        every_row = bool(np.logical_and.reduce(nz))  # (typical: then the segmented sums need no scatter)
        starts = bounds[:-1] if every_row else bounds[:-1][nz]
        if every_row:
            settled = np.logical_or.reduceat(near_c, starts)
        else:
            settled = np.zeros(m, dtype=bool)
            if flat.size:
                settled[nz] = np.logical_or.reduceat(near_c, starts)
        U = (~settled).nonzero()[0]
        dan: float | NDArray[np.float64] = np.zeros(L.B) if L.batch else 0.0
        sel = U[:0]
        if U.size:
            # (Per element the same operations as on the pairs; the rows' values in one gather,
            # u and v together: the per-call cost dominates at this size.)
            rows_U = rows.take(U, axis=1)
            duv_U = rows_U[3:5, :, None] - self._mu_uv  # (2, U, n): u - mu_u, v - mu_v
            du_U, dv_U = duv_U
            sq_U = duv_U * duv_U
            r2_U = np.add(sq_U[0], sq_U[1], out=sq_U[0])
            r_U = np.sqrt(r2_U)
            lat_U = r_U - self._half
            np.maximum(lat_U, 0.0, out=lat_U)
            scale_U = scale[U][:, None]
            # minus how far the data lie behind the model's surface (data in front: 0)
            nbeh_U = rows_U[5][:, None] - data.depth
            np.minimum(nbeh_U, 0.0, out=nbeh_U)
            dist2_U = lat_U * lat_U
            dist2_U *= rows_U[9][:, None]  # (row 9: scale * scale)
            dist2_U += nbeh_U * nbeh_U
            if parts is not None:  # (infinitely far: the Gaussians outside the row's pose's part)
                dist2_U += parts[0].take(U // (m // L.B), axis=0)
            dmin_U = np.sqrt(np.minimum.reduce(dist2_U, axis=1))
            # The dangling weight is positive exactly where dmin > TAU1 (typically nowhere).
            sel = (dmin_U > TAU1_MM).nonzero()[0]
        drows = U[sel]
        if drows.size:
            # (minimum of maximum: np.clip, several times cheaper on small arrays)
            wdang_r = np.minimum(np.maximum((dmin_U[sel] - TAU1_MM) / TAU1_MM, 0.0), 1.0)
            dist_r = np.sqrt(dist2_U[sel])
            phi = np.minimum(np.maximum((dist_r - TAU1_MM) / (TAU2_MM - TAU1_MM), 0.0), 1.0)
            s2r = (sp[drows] ** 2)[:, None] + self._sq2[None, :]
            r2_r = r2_U[sel]
            er = np.exp(-0.5 * r2_r / s2r)
            n_r: float | NDArray[np.float64] = n
            if parts is not None:  # (the part's Gaussians only, and their number)
                pose_r = drows // (m // L.B)
                phi *= parts[3].take(pose_r, axis=0)
                n_r = parts[2].take(pose_r)
            per_row_dan = _sum(phi * (1.0 - er), axis=1) / n_r
            if L.batch:  # (each pose's rows summed as one pose's: the same bits)
                dan = _segment_sums(wdang_r * per_row_dan, drows.searchsorted(m // L.B * np.arange(L.B + 1)))
            else:
                dan = float(_sum(wdang_r * per_row_dan))
        if g3 is None and later is None:
            return sim, dan
        sat += 1.0  # exp(-S_q / k_q): dE_sim/dS_q in units of G / norm
        if parts is not None:  # (the gradient's weights per image Gaussian carry their pose's 1 / norm)
            sat_b = sat.reshape(L.B, n)
            sat_b *= inv_norm[:, None]
            inv_norm = 1.0

        def backward(g3: NDArray[np.float64]) -> None:
            """Add the data terms' ``dE/dP`` into ``g3`` (m, 3) (only reads this evaluation's
            values: valid until the objective's next evaluation reuses its buffers)."""
            # d/d(u, v, sigma_p, d_p) of E_sim, accumulated per model Gaussian.
            # The pairs come sorted by model Gaussian (row-major order of the mask): the sums per
            # Gaussian are one segmented sum over the rows of W.  Factors of a model Gaussian alone
            # are taken out of its sums: with wD = Delta D / norm,
            # dE/dsp = sum wD (2 / sp - 2 sp / s2 + r2 sp / s2^2)
            #        = 2 / sp sum wD + sp sum wD / s2 (r2 / s2 - 2).
            W = np.empty((5, flat.size))
            np.multiply(sat, SIM_GAIN, out=sat)  # (per image Gaussian: fewer products than per pair, the same bits)
            w_pair = sat.take(qi)  # each pair's share of dE_sim/dS_q
            np.multiply(delta_D, w_pair, out=W[2])
            wD = np.multiply(W[2], inv_norm, out=W[2])
            a = np.multiply(wD, inv_s2, out=inv_s2)
            np.multiply(a, du, out=W[0])  # (two contiguous products: cheaper than one broadcast)
            np.multiply(a, dv, out=W[1])
            np.subtract(r2_s2, 2.0, out=r2_s2)
            np.multiply(a, r2_s2, out=W[3])
            np.copysign(D, dd, out=W[4])  # D sign(dd), weighted like wD
            W[4] *= w_pair
            if every_row:
                g = np.add.reduceat(W, starts, axis=1)
            else:
                g = np.zeros((5, m))
                if flat.size:
                    g[:, nz] = np.add.reduceat(W, starts, axis=1)
            # g[0:2] = -dE/d(u, v), then dE/dsp, dE/dp, and the explicit z-dependence of the
            # dangle distances (rows 2-4 replaced in place by what they are made of).
            g[2] = 2.0 * g[2] / sp + sp * g[3]
            g[3] = g[4] / L.two_sh * -inv_norm
            dangling = drows.size > 0 and w_dan > 0
            if dangling:
                g[4] = 0.0
                wn = (w_dan * wdang_r / n_r)[:, None]
                pe = wn * phi * er
                inv_s2r = 1.0 / s2r
                spr = sp[drows][:, None]
                du_r, dv_r = du_U[sel], dv_U[sel]
                # d(1 - e)/du = e du / s2 ; d(1 - e)/dsp = -e r2 sp / s2^2
                pe_s2 = pe * inv_s2r
                # Derivatives of the distance: lat = max(r - half, 0) z / f, behind = max(dq - dp, 0)
                # (both terms vanish off the lateral part, where lat = 0).
                lat_px_r, scale_r = lat_U[sel], scale_U[sel]
                lat_r = lat_px_r * scale_r
                r_r = np.maximum(r_U[sel], 1e-9)
                inv_dist = 1.0 / np.maximum(dist_r, 1e-9)
                k_u = lat_r * scale_r / r_r * inv_dist  # d dist / du per du
                k_z = lat_r * lat_px_r / self._f * inv_dist
                k_dp = nbeh_U[sel] * inv_dist  # d dist / d dp
                ramp = (dist_r > TAU1_MM) & (dist_r < TAU2_MM)
                c = wn * (ramp * (1.0 / (TAU2_MM - TAU1_MM))) * (1.0 - er)
                # Through the dangling weight: d dmin / d(.) at the nearest data Gaussian.
                dmin_r = dmin_U[sel]
                on_ramp = (dmin_r > TAU1_MM) & (dmin_r < 2.0 * TAU1_MM)
                nearest_r = dist2_U[sel].argmin(axis=1)
                c[np.arange(drows.size), nearest_r] += w_dan * on_ramp * per_row_dan / TAU1_MM
                k_uv = pe_s2 + c * k_u
                rows_sums = np.empty((5, drows.size))
                _sum(k_uv * du_r, axis=1, out=rows_sums[0])
                _sum(k_uv * dv_r, axis=1, out=rows_sums[1])
                _sum(pe_s2 * r2_r * spr * inv_s2r, axis=1, out=rows_sums[2])
                np.negative(_sum(c * k_dp, axis=1), out=rows_sums[3])
                np.negative(_sum(c * k_z, axis=1), out=rows_sums[4])
                g[:, drows] += rows_sums
            # Through u = fx x / z + cx, v = fy y / z + cy, sp = sh f / z, dp = z - sh.
            t_uv = g[:2] * self._fxy / z  # (2, m): dE/d(x, y) at fixed z, negated
            g3[:, :2] -= t_uv.T
            g_z = (t_uv[0] * P[:, 0] + t_uv[1] * P[:, 1] - g[2] * L.shf / z) / z + g[3]
            if dangling:  # (else g[4] is 0: g3, zeros before this first term, gets the same bits)
                g_z += g[4]
            g3[:, 2] += g_z

        run_or_defer(backward, g3, later)
        return sim, dan
