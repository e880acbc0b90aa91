"""Z-buffer rasteriser of triangle meshes in NumPy (used by the mesh-hand renderer).

:func:`rasterise`: vertices are projected with any pinhole
:class:`~hand_sog_tracker.core.types.Intrinsics`; triangles are grouped by the
power-of-two size of their pixel bounding box, each group is tested on the
pixel centres of its boxes at once (edge functions), depth is interpolated
as ``1/z`` (exact for planar triangles) and the nearest hit per pixel is kept
with ``np.minimum.at``.  :func:`view_cosine` gives the angle between each
pixel's viewing ray and the surface it hit, for the sensor models of
:mod:`hand_sog_tracker.synth.sensors`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.types import Intrinsics

__all__ = ["rasterise", "view_cosine"]

_NEAR_MM = 1.0  #: triangles with a vertex closer than this (or behind the camera) are skipped
_SIZE_CLASSES = (1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024, 2048, 4096, 8192)


def rasterise(
    vertices: NDArray[np.float64], triangles: NDArray[np.int64], intrinsics: Intrinsics
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Z-buffer a triangle mesh.

    Parameters
    ----------
    vertices : array, shape (n, 3), mm, camera optical frame
    triangles : int array, shape (t, 3)
    intrinsics : Intrinsics

    Returns
    -------
    zbuf : array, shape (H, W), float64
        Depth ``z`` (mm) of the nearest triangle at each pixel centre; ``inf`` = none.
    tri_id : int array, shape (H, W)
        Index of that triangle, -1 where none.
    """
    W, H = intrinsics.width, intrinsics.height
    v = np.asarray(vertices, dtype=np.float64)
    tris = np.asarray(triangles, dtype=np.int64)
    zbuf = np.full(H * W, np.inf)
    tri_id = np.full(H * W, -1, dtype=np.int64)
    z = v[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = intrinsics.fx * v[:, 0] / z + intrinsics.cx
        w = intrinsics.fy * v[:, 1] / z + intrinsics.cy
    tu, tv, tz = u[tris], w[tris], z[tris]  # (t, 3)
    ok = np.all(tz > _NEAR_MM, axis=1)
    u0 = np.ceil(tu.min(axis=1))
    u1 = np.floor(tu.max(axis=1))
    v0 = np.ceil(tv.min(axis=1))
    v1 = np.floor(tv.max(axis=1))
    u0, v0 = np.maximum(u0, 0), np.maximum(v0, 0)
    u1, v1 = np.minimum(u1, W - 1), np.minimum(v1, H - 1)
    area = (tu[:, 1] - tu[:, 0]) * (tv[:, 2] - tv[:, 0]) - (tu[:, 2] - tu[:, 0]) * (tv[:, 1] - tv[:, 0])
    ok &= (u1 >= u0) & (v1 >= v0) & (np.abs(area) > 1e-12)
    idx = np.nonzero(ok)[0]
    if idx.size == 0:
        return zbuf.reshape(H, W), tri_id.reshape(H, W)
    bw = (u1[idx] - u0[idx] + 1).astype(np.int64)
    bh = (v1[idx] - v0[idx] + 1).astype(np.int64)
    cw = np.searchsorted(_SIZE_CLASSES, bw)
    ch = np.searchsorted(_SIZE_CLASSES, bh)
    key = cw * 64 + ch
    pix_all, z_all, id_all = [], [], []
    for k in np.unique(key):
        sel = idx[key == k]
        SW, SH = _SIZE_CLASSES[int(k) // 64], _SIZE_CLASSES[int(k) % 64]
        pu = u0[sel][:, None, None] + np.arange(SW)[None, None, :]  # (m, 1, SW)
        pv = v0[sel][:, None, None] + np.arange(SH)[None, :, None]  # (m, SH, 1)
        a, b_, c = tu[sel], tv[sel], tz[sel]
        inv_area = 1.0 / area[sel][:, None, None]
        U = [a[:, i][:, None, None] for i in range(3)]
        Vv = [b_[:, i][:, None, None] for i in range(3)]
        # barycentric weights from edge functions
        l0 = ((U[1] - pu) * (Vv[2] - pv) - (U[2] - pu) * (Vv[1] - pv)) * inv_area
        l1 = ((U[2] - pu) * (Vv[0] - pv) - (U[0] - pu) * (Vv[2] - pv)) * inv_area
        l2 = 1.0 - l0 - l1
        eps = -1e-9
        inside = (l0 >= eps) & (l1 >= eps) & (l2 >= eps)
        inside &= (pu <= u1[sel][:, None, None]) & (pv <= v1[sel][:, None, None])
        if not inside.any():
            continue
        invz = l0 / c[:, 0][:, None, None] + l1 / c[:, 1][:, None, None] + l2 / c[:, 2][:, None, None]
        m_i, y_i, x_i = np.nonzero(inside)
        pix_all.append((v0[sel][m_i] + y_i).astype(np.int64) * W + (u0[sel][m_i] + x_i).astype(np.int64))
        z_all.append(1.0 / invz[m_i, y_i, x_i])
        id_all.append(sel[m_i])
    if not pix_all:
        return zbuf.reshape(H, W), tri_id.reshape(H, W)
    pix = np.concatenate(pix_all)
    zz = np.concatenate(z_all)
    ids = np.concatenate(id_all)
    np.minimum.at(zbuf, pix, zz)
    win = zz <= zbuf[pix]
    tri_id[pix[win]] = ids[win]
    return zbuf.reshape(H, W), tri_id.reshape(H, W)


def view_cosine(
    vertices: NDArray[np.float64], triangles: NDArray[np.int64], tri_id: NDArray[np.int64], intr: Intrinsics
) -> NDArray[np.float32]:
    """|cos| of the angle between each pixel's ray and its triangle's normal, (H, W); 1 off the mesh."""
    p = vertices[triangles]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    H, W = tri_id.shape
    uu = (np.arange(W) - intr.cx) / intr.fx
    vv = (np.arange(H) - intr.cy) / intr.fy
    ray = np.empty((H, W, 3))
    ray[:, :, 0] = uu[None, :]
    ray[:, :, 1] = vv[:, None]
    ray[:, :, 2] = 1.0
    ray /= np.linalg.norm(ray, axis=2, keepdims=True)
    hit = tri_id >= 0
    cos = np.ones((H, W), dtype=np.float32)
    cos[hit] = np.abs(np.einsum("ki,ki->k", n[tri_id[hit]], ray[hit]))
    return cos
