"""Ray-cast depth renderer of a surface hand (ground-truth data for tests and demos).

One job: the capsule-hand renderer; kept together because its primitives, their ray
intersections and its sensor artefacts are one pipeline used only by :func:`render_depth`.

The rendered hand is deliberately *not* the tracker's Sum of Gaussians: it is a
surface made of

* one capsule per finger segment (radius = the segment's finger radius, i.e.
  the ``g_sigmas`` of the model Gaussians on that segment); the distal capsule
  ends so that its end-sphere centre is the fingertip of
  :func:`hand_sog_tracker.core.kinematics.fingertips`,
* a palm that is a rounded slab: a convex polygon (wrist, palm sides, the MCP
  row) swept by a sphere of radius ``palm sigma`` (which ``shape.depth`` scales),
* optionally a forearm: a tapered round cone with an elliptic cross-section
  running about 250 mm from the wrist away from the fingers.

Camera optical frame: ``x`` right, ``y`` down, ``z`` forward, millimetres.  The
returned depth is the ``z`` coordinate of the nearest surface point on each
pixel's ray (as depth cameras report it), float32 mm, 0 = invalid.

ToF-like artefacts (all driven by the given random generator): depth-dependent
Gaussian noise, flying pixels along depth discontinuities, dropout at grazing
angles, random small holes and random single-pixel dropout.  With
``noise_mm=0, flying_pixels=False, holes=False`` the render is exact.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.hand_model import HandModel
from hand_sog_tracker.core.kinematics import attached_points, check_pose
from hand_sog_tracker.core.types import Intrinsics
from hand_sog_tracker.errors import InputError

__all__ = ["RenderOptions", "render_depth", "hand_primitives", "HandPrimitives"]

#: Palm outline in the unscaled hand frame (mm, x radial, y distal) apart from
#: the MCP row, which is taken from the model's finger bases.  Order: wrist
#: radial, radial side, <index .. little MCP>, ulnar side, wrist ulnar.
_PALM_WRIST_RADIAL = (20.0, 6.0)
_PALM_RADIAL_SIDE = (28.0, 50.0)
_PALM_ULNAR_SIDE = (-30.0, 40.0)
_PALM_WRIST_ULNAR = (-22.0, 6.0)
_MCP_INSET_MM = 4.0  #: the palm outline ends this far proximal of the MCP joints

_FOREARM_START_Y = -5.0  #: hand-frame y of the forearm's wrist-end sphere centre (mm)
_FOREARM_LENGTH = 250.0  #: mm from the wrist, along -hand-y
_FOREARM_R_WRIST = 27.0  #: mm, radius at the wrist end
_FOREARM_R_ELBOW = 33.0  #: mm, radius at the far end
_FOREARM_FLATTEN = 0.75  #: palmar-dorsal semi-axis / radial-ulnar semi-axis

_EDGE_JUMP_MM = 20.0  #: a 4-neighbour farther than this in depth makes a discontinuity
_FLYING_SHARE = 0.35  #: share of discontinuity pixels that become flying pixels
_GRAZING_COS = 0.35  #: dropout starts when cos(view angle) falls below this
_GRAZING_MAX_DROP = 0.7  #: dropout probability at exactly grazing incidence
_RANDOM_DROPOUT = 0.002  #: share of all pixels randomly dropped


@dataclass(frozen=True)
class RenderOptions:
    """Sensor simulation options of :func:`render_depth`.

    Attributes
    ----------
    noise_mm : float
        Standard deviation (mm) of the Gaussian depth noise at 400 mm; it grows
        with ``(z / 400 mm)**2``.  0 disables noise.
    flying_pixels : bool
        Replace a share of the pixels along depth discontinuities by depths
        interpolated between the foreground and the background.
    holes : bool
        Drop pixels (0) at grazing angles, in a few small random blobs and at
        random.
    forearm : bool
        Render a forearm from the wrist out of the hand.
    background_mm : float or None
        Depth (mm) of a fronto-parallel wall behind the hand; ``None`` = no
        return (0) wherever the hand and forearm are not.
    """

    noise_mm: float = 1.0
    flying_pixels: bool = True
    holes: bool = True
    forearm: bool = True
    background_mm: float | None = 900.0

    def __post_init__(self) -> None:
        if not np.isfinite(self.noise_mm) or self.noise_mm < 0:
            raise InputError(f"noise_mm must be finite and >= 0, got {self.noise_mm!r}")
        if self.background_mm is not None and not (
            np.isfinite(self.background_mm) and self.background_mm > 0
        ):
            raise InputError(f"background_mm must be None or > 0, got {self.background_mm!r}")

    @property
    def exact(self) -> bool:
        """``True`` when no artefact is enabled (the render is noise-free geometry)."""
        return self.noise_mm == 0 and not self.flying_pixels and not self.holes


@dataclass(frozen=True, eq=False)
class HandPrimitives:
    """The surface primitives of one posed hand, camera frame, mm.

    Attributes
    ----------
    cone_a, cone_b : array, shape (k, 3)
        End-sphere centres of the round cones (capsules when radii agree), in
        each cone's canonical frame (the camera frame unless ``cone_affine``).
    cone_ra, cone_rb : array, shape (k,)
        End-sphere radii (mm).
    cone_affine : list of (A (3, 3), c (3,)) or None, length k
        Maps canonical coordinates to the camera frame: ``x = A @ p + c``;
        ``None`` = identity.
    cone_bound_centres, cone_bound_radii : arrays, shapes (k, 2, 3), (k, 2)
        Camera-frame spheres whose convex hull bounds each cone.
    palm_planes : array, shape (p, 4)
        Half-spaces ``n . x <= h`` (rows ``n_x, n_y, n_z, h``) of the palm prism.
    palm_bound_centres : array, shape (q, 3); palm_bound_radius : float
        Spheres bounding the palm prism.
    """

    cone_a: NDArray[np.float64]
    cone_b: NDArray[np.float64]
    cone_ra: NDArray[np.float64]
    cone_rb: NDArray[np.float64]
    cone_affine: list[tuple[NDArray[np.float64], NDArray[np.float64]] | None]
    cone_bound_centres: NDArray[np.float64]
    cone_bound_radii: NDArray[np.float64]
    palm_planes: NDArray[np.float64]
    palm_bound_centres: NDArray[np.float64]
    palm_bound_radius: float


def _segment_radii(model: HandModel) -> NDArray[np.float64]:
    """Finger radius (mm) of each chain segment, shape (5, 3): mean sigma of its Gaussians."""
    radii = np.empty((5, 3))
    for c in range(5):
        for s in range(3):
            sel = (model.g_chain == c) & (model.g_segment == s)
            if not np.any(sel):
                raise InputError(f"model has no Gaussian on chain {c} segment {s}")
            radii[c, s] = float(np.mean(model.g_sigmas[sel]))
    return radii


def _palm_outline(model: HandModel) -> NDArray[np.float64]:
    """Convex palm polygon in the hand frame, shape (8, 3) mm, counter-clockwise (right hand)."""
    sx, sy = model.shape.width, model.shape.length
    mcp = model.bases[1:5, :2] - np.array([0.0, _MCP_INSET_MM * sy])
    pts = [
        (_PALM_WRIST_RADIAL[0] * sx, _PALM_WRIST_RADIAL[1] * sy),
        (_PALM_RADIAL_SIDE[0] * sx, _PALM_RADIAL_SIDE[1] * sy),
        *[tuple(p) for p in mcp],
        (_PALM_ULNAR_SIDE[0] * sx, _PALM_ULNAR_SIDE[1] * sy),
        (_PALM_WRIST_ULNAR[0] * sx, _PALM_WRIST_ULNAR[1] * sy),
    ]
    out = np.zeros((len(pts), 3))
    out[:, :2] = pts
    return out


def hand_primitives(model: HandModel, theta: NDArray[np.float64], forearm: bool = True) -> HandPrimitives:
    """Build the camera-frame surface primitives of ``model`` in pose ``theta``.

    Parameters
    ----------
    model : HandModel
        Hand geometry (scaled and mirrored models work as they are).
    theta : array, shape (26,)
        Pose (mm, rad).
    forearm : bool
        Include the forearm cone.

    Returns
    -------
    HandPrimitives
    """
    theta = check_pose(theta)
    radii = _segment_radii(model)
    lengths = model.lengths
    tip_r = model.tip_radii

    # Finger capsules: start and end of each segment in its own frame.
    chain = np.repeat(np.arange(5), 3)
    seg = np.tile(np.arange(3), 5)
    start = np.zeros((15, 3))
    end = np.zeros((15, 3))
    end[:, 1] = lengths.reshape(15)
    end[2::3, 1] = lengths[:, 2] - tip_r  # distal: end-sphere centre = fingertip
    pts = attached_points(
        model,
        theta,
        np.concatenate([chain, chain]),
        np.concatenate([seg, seg]),
        np.concatenate([start, end]),
    )
    fa, fb = pts[:15], pts[15:]
    fr = radii.reshape(15)

    # Palm: hand-frame outline and axes, mapped to the camera frame.
    outline = _palm_outline(model)
    n_out = outline.shape[0]
    axes_hand = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    palm_pts = attached_points(
        model,
        theta,
        np.full(n_out + 4, -1),
        np.zeros(n_out + 4, dtype=np.int64),
        np.concatenate([outline, axes_hand]),
    )
    verts = palm_pts[:n_out]
    origin = palm_pts[n_out]
    G = (palm_pts[n_out + 1 :] - origin).T  # columns: hand x, y, z in camera frame (mirror-aware)
    normal = G[:, 2]
    palm_sig = model.g_sigmas[model.g_chain < 0]
    r_palm = float(np.mean(palm_sig)) if palm_sig.size else 12.5 * model.shape.depth
    centroid = verts.mean(axis=0)
    planes = [np.append(normal, normal @ centroid + r_palm), np.append(-normal, -normal @ centroid + r_palm)]
    for i in range(n_out):
        p, q = verts[i], verts[(i + 1) % n_out]
        m = np.cross(normal, q - p)
        m /= np.linalg.norm(m)
        if m @ (centroid - p) > 0:  # make it point outward
            m = -m
        planes.append(np.append(m, m @ p))
    palm_planes = np.array(planes)
    ea = verts
    eb = np.roll(verts, -1, axis=0)

    cone_a = [fa, ea]
    cone_b = [fb, eb]
    cone_ra = [fr, np.full(n_out, r_palm)]
    cone_rb = [fr, np.full(n_out, r_palm)]
    affine: list[tuple[NDArray[np.float64], NDArray[np.float64]] | None] = [None] * (15 + n_out)
    bc = [np.stack([fa, fb], axis=1), np.stack([ea, eb], axis=1)]
    br = [np.stack([fr, fr], axis=1), np.full((n_out, 2), r_palm)]

    if forearm:
        sh = model.shape
        S = np.diag([sh.width, sh.length, sh.depth * _FOREARM_FLATTEN])
        A = G @ S
        ca = np.array([[0.0, _FOREARM_START_Y, 0.0]])
        cb = np.array([[0.0, -_FOREARM_LENGTH, 0.0]])
        cone_a.append(ca)
        cone_b.append(cb)
        cone_ra.append(np.array([_FOREARM_R_WRIST]))
        cone_rb.append(np.array([_FOREARM_R_ELBOW]))
        affine.append((A, origin))
        scale = float(np.max(np.diag(S)))
        bc.append(np.stack([ca @ A.T + origin, cb @ A.T + origin], axis=1))
        br.append(np.array([[_FOREARM_R_WRIST * scale, _FOREARM_R_ELBOW * scale]]))

    return HandPrimitives(
        cone_a=np.concatenate(cone_a),
        cone_b=np.concatenate(cone_b),
        cone_ra=np.concatenate(cone_ra),
        cone_rb=np.concatenate(cone_rb),
        cone_affine=affine,
        cone_bound_centres=np.concatenate(bc),
        cone_bound_radii=np.concatenate(br),
        palm_planes=palm_planes,
        palm_bound_centres=verts,
        palm_bound_radius=r_palm,
    )


@lru_cache(maxsize=8)
def _ray_grid(intrinsics: Intrinsics) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per-pixel ray directions ``(dx, dy, 1)``: arrays dx (1, W) and dy (H, 1)."""
    u = np.arange(intrinsics.width, dtype=np.float64)
    v = np.arange(intrinsics.height, dtype=np.float64)
    dx = ((u - intrinsics.cx) / intrinsics.fx)[None, :]
    dy = ((v - intrinsics.cy) / intrinsics.fy)[:, None]
    dx.setflags(write=False)
    dy.setflags(write=False)
    return dx, dy


def _bbox(
    centres: NDArray[np.float64], radii: NDArray[np.float64], intr: Intrinsics
) -> tuple[int, int, int, int] | None:
    """Pixel box ``(u0, u1, v0, v1)`` (half-open) covering the hull of spheres; ``None`` if empty."""
    c = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    r = np.asarray(radii, dtype=np.float64).reshape(-1)
    if np.all(c[:, 2] + r <= 1e-3):
        return None  # entirely behind the camera
    if np.any(c[:, 2] - r <= 1.0):
        u0, u1, v0, v1 = 0, intr.width, 0, intr.height
    else:
        zs = np.stack([c[:, 2] - r, c[:, 2] + r])
        xs = np.stack([c[:, 0] - r, c[:, 0] + r])
        ys = np.stack([c[:, 1] - r, c[:, 1] + r])
        ux = (xs[:, None, :] / zs[None, :, :]) * intr.fx + intr.cx
        vy = (ys[:, None, :] / zs[None, :, :]) * intr.fy + intr.cy
        u0 = max(int(np.floor(ux.min())) - 1, 0)
        u1 = min(int(np.ceil(ux.max())) + 2, intr.width)
        v0 = max(int(np.floor(vy.min())) - 1, 0)
        v1 = min(int(np.ceil(vy.max())) + 2, intr.height)
    if u0 >= u1 or v0 >= v1:
        return None
    return u0, u1, v0, v1


def _round_cone_t(
    dx: NDArray[np.float64],
    dy: NDArray[np.float64],
    dz: NDArray[np.float64] | float,
    o: NDArray[np.float64],
    pa: NDArray[np.float64],
    pb: NDArray[np.float64],
    ra: float,
    rb: float,
) -> NDArray[np.float64]:
    """Ray parameter of the first hit of rays ``o + t d`` with a round cone (inf = miss).

    The round cone is the convex hull of the spheres (``pa``, ``ra``) and
    (``pb``, ``rb``).  ``d`` need not be unit length (after Inigo Quilez's
    analytic rounded-cone intersection, generalised to non-unit directions).
    """
    ba = pb - pa
    oa = o - pa
    ob = o - pb
    rr = ra - rb
    m0 = float(ba @ ba)
    m1 = float(ba @ oa)
    m5 = float(oa @ oa)
    m7 = float(ob @ ob)
    m2 = ba[0] * dx + ba[1] * dy + ba[2] * dz
    m3 = oa[0] * dx + oa[1] * dy + oa[2] * dz
    m6 = ob[0] * dx + ob[1] * dy + ob[2] * dz
    dd = dx * dx + dy * dy + dz * dz
    d2 = m0 - rr * rr
    k2 = d2 * dd - m2 * m2
    k1 = d2 * m3 - m1 * m2 + m2 * (rr * ra)
    k0 = d2 * m5 - m1 * m1 + m1 * rr * ra * 2.0 - m0 * ra * ra
    h = k1 * k1 - k0 * k2
    with np.errstate(invalid="ignore", divide="ignore"):
        t_body = (-np.sqrt(h) - k1) / k2
        y = (m1 - ra * rr) + t_body * m2
        body_ok = (h >= 0) & (k2 > 1e-12 * d2 * dd) & (y > 0) & (y < d2)
        h1 = m3 * m3 - dd * (m5 - ra * ra)
        t1 = np.where(h1 >= 0, (-m3 - np.sqrt(h1)) / dd, np.inf)
        h2 = m6 * m6 - dd * (m7 - rb * rb)
        t2 = np.where(h2 >= 0, (-m6 - np.sqrt(h2)) / dd, np.inf)
    t = np.where(body_ok, t_body, np.minimum(t1, t2))
    return np.where(t > 0, t, np.inf)


def _prism_t(
    dx: NDArray[np.float64], dy: NDArray[np.float64], planes: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Entry depth of rays ``t (dx, dy, 1)`` from the origin into a convex polyhedron (inf = miss)."""
    shape = np.broadcast_shapes(dx.shape, dy.shape)
    t_in = np.zeros(shape)
    t_out = np.full(shape, np.inf)
    for nx, ny, nz, h in planes:
        nd = nx * dx + ny * dy + nz
        with np.errstate(divide="ignore", invalid="ignore"):
            t = h / nd
        entering = nd < 0
        t_in = np.where(entering, np.maximum(t_in, t), t_in)
        exiting = nd > 0
        t_out = np.where(exiting, np.minimum(t_out, t), t_out)
        if h < 0:  # origin outside this half-space: parallel rays never enter
            t_out = np.where(nd == 0, -np.inf, t_out)
    hit = (t_in <= t_out) & (t_in > 0)
    return np.where(hit, t_in, np.inf)


def _render_geometry(
    prims: HandPrimitives, intr: Intrinsics
) -> tuple[NDArray[np.float64], tuple[int, int, int, int] | None]:
    """Exact z-buffer (H, W) mm of the primitives (inf = no hit) and the union pixel box."""
    dx_all, dy_all = _ray_grid(intr)
    zbuf = np.full((intr.height, intr.width), np.inf)
    union: list[tuple[int, int, int, int]] = []

    def splat(box: tuple[int, int, int, int], z: NDArray[np.float64]) -> None:
        u0, u1, v0, v1 = box
        view = zbuf[v0:v1, u0:u1]
        np.minimum(view, z, out=view)
        union.append(box)

    for k in range(prims.cone_a.shape[0]):
        box = _bbox(prims.cone_bound_centres[k], prims.cone_bound_radii[k], intr)
        if box is None:
            continue
        u0, u1, v0, v1 = box
        dx = dx_all[:, u0:u1]
        dy = dy_all[v0:v1, :]
        aff = prims.cone_affine[k]
        if aff is None:
            o = np.zeros(3)
            ex, ey, ez = dx, dy, 1.0
        else:
            A, c = aff
            Ainv = np.linalg.inv(A)
            o = -Ainv @ c
            ex = Ainv[0, 0] * dx + Ainv[0, 1] * dy + Ainv[0, 2]
            ey = Ainv[1, 0] * dx + Ainv[1, 1] * dy + Ainv[1, 2]
            ez = Ainv[2, 0] * dx + Ainv[2, 1] * dy + Ainv[2, 2]
        z = _round_cone_t(
            ex, ey, ez, o, prims.cone_a[k], prims.cone_b[k], float(prims.cone_ra[k]), float(prims.cone_rb[k])
        )
        splat(box, np.broadcast_to(z, (v1 - v0, u1 - u0)))

    r = np.full(prims.palm_bound_centres.shape[0], prims.palm_bound_radius)
    box = _bbox(prims.palm_bound_centres, r, intr)
    if box is not None:
        u0, u1, v0, v1 = box
        z = _prism_t(dx_all[:, u0:u1], dy_all[v0:v1, :], prims.palm_planes)
        splat(box, np.broadcast_to(z, (v1 - v0, u1 - u0)))

    if not union:
        return zbuf, None
    b = np.array(union)
    return zbuf, (int(b[:, 0].min()), int(b[:, 1].max()), int(b[:, 2].min()), int(b[:, 3].max()))


def _neighbours(z: NDArray[np.float32], fill: float) -> NDArray[np.float32]:
    """The 4-neighbours of every pixel, shape (4, H, W); outside the image = ``fill``."""
    p = np.pad(z, 1, mode="constant", constant_values=fill)
    return np.stack([p[:-2, 1:-1], p[2:, 1:-1], p[1:-1, :-2], p[1:-1, 2:]])


def _surface_slope(z: NDArray[np.float32], axis: int) -> NDArray[np.float32]:
    """Depth change (mm per pixel) along ``axis`` on the same surface (one-sided at edges)."""
    p = np.pad(z, 1, mode="edge")
    c = p[1:-1, 1:-1]
    if axis == 1:
        fwd, bwd = p[1:-1, 2:] - c, c - p[1:-1, :-2]
        nf, nb = p[1:-1, 2:], p[1:-1, :-2]
    else:
        fwd, bwd = p[2:, 1:-1] - c, c - p[:-2, 1:-1]
        nf, nb = p[2:, 1:-1], p[:-2, 1:-1]
    okf = (nf > 0) & (np.abs(fwd) < _EDGE_JUMP_MM)
    okb = (nb > 0) & (np.abs(bwd) < _EDGE_JUMP_MM)
    both = okf & okb
    return np.where(both, 0.5 * (fwd + bwd), np.where(okf, fwd, np.where(okb, bwd, 0.0))).astype(np.float32)


def _apply_artefacts(
    depth: NDArray[np.float32],
    hand_box: tuple[int, int, int, int] | None,
    intr: Intrinsics,
    options: RenderOptions,
    rng: np.random.Generator,
) -> None:
    """Add ToF-like artefacts to ``depth`` (H, W) mm in place (0 = invalid)."""
    H, W = depth.shape
    if hand_box is not None and (options.flying_pixels or options.holes):
        u0, u1, v0, v1 = hand_box
        u0, v0 = max(u0 - 2, 0), max(v0 - 2, 0)
        u1, v1 = min(u1 + 2, W), min(v1 + 2, H)
        roi = depth[v0:v1, u0:u1]  # a view: edits go into depth
        clean = roi.copy()
        if options.holes:
            # Dropout at grazing angles: cos of the angle between the surface normal and the ray.
            scale = np.maximum(clean, 1.0) / np.float32(intr.fx)  # mm per pixel
            sx = _surface_slope(clean, 1) / scale
            sy = _surface_slope(clean, 0) / scale
            cos = 1.0 / np.sqrt(1.0 + sx * sx + sy * sy)
            p_drop = _GRAZING_MAX_DROP * np.clip((_GRAZING_COS - cos) / _GRAZING_COS, 0.0, 1.0)
            cand = np.nonzero((clean > 0) & (p_drop > 0))
            drop = rng.random(cand[0].size) < p_drop[cand]
            roi[cand[0][drop], cand[1][drop]] = 0.0
        if options.flying_pixels:
            nb = _neighbours(clean, -1.0)  # -1: outside the image (neither valid nor a hole)
            valid_nb = nb > 0
            lo = np.minimum(np.where(valid_nb, nb, np.inf).min(axis=0), clean)
            hi = np.maximum(np.where(valid_nb, nb, -np.inf).max(axis=0), clean)
            ok = clean > 0
            jump = ok & (hi - lo > _EDGE_JUMP_MM)
            cand = np.nonzero(jump)
            pick = rng.random(cand[0].size) < _FLYING_SHARE
            iy, ix = cand[0][pick], cand[1][pick]
            frac = rng.uniform(0.15, 0.85, iy.size)
            roi[iy, ix] = (lo[iy, ix] + frac * (hi[iy, ix] - lo[iy, ix])).astype(np.float32)
            # Next to "no return" the mixed signal is weak: drop some of those pixels instead.
            cand = np.nonzero(ok & ~jump & np.any(nb == 0, axis=0))
            drop = rng.random(cand[0].size) < _FLYING_SHARE * 0.7
            roi[cand[0][drop], cand[1][drop]] = 0.0
    if options.noise_mm > 0:
        sigma = np.float32(options.noise_mm / 400.0**2) * depth * depth  # 0 where invalid
        depth += sigma * rng.standard_normal(depth.shape, dtype=np.float32)
        np.maximum(depth, 0.0, out=depth)
    if options.holes:
        # A few small blobs, mostly on the hand, and random single-pixel dropout.
        n_blobs = int(rng.integers(1, 5))
        if hand_box is not None:
            u0, u1, v0, v1 = hand_box
            on_hand = np.nonzero((depth[v0:v1, u0:u1] > 0) & (depth[v0:v1, u0:u1] < 650.0))
            on_hand = (on_hand[0] + v0, on_hand[1] + u0)
        else:
            on_hand = (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
        rad_scale = W / 320.0
        yy, xx = np.ogrid[:H, :W]
        for _ in range(n_blobs):
            if on_hand[0].size and rng.random() < 0.7:
                i = int(rng.integers(on_hand[0].size))
                cy, cx = on_hand[0][i], on_hand[1][i]
            else:
                cy, cx = int(rng.integers(H)), int(rng.integers(W))
            r = rng.uniform(1.0, 2.5) * rad_scale
            ri = int(np.ceil(r))
            y0, y1 = max(cy - ri, 0), min(cy + ri + 1, H)
            x0, x1 = max(cx - ri, 0), min(cx + ri + 1, W)
            blob = (yy[y0:y1] - cy) ** 2 + (xx[:, x0:x1] - cx) ** 2 <= r * r
            depth[y0:y1, x0:x1][blob] = 0.0
        n_drop = rng.binomial(H * W, _RANDOM_DROPOUT)
        idx = rng.integers(0, H * W, n_drop)
        depth.reshape(-1)[idx] = 0.0


def render_depth(
    model: HandModel,
    theta: NDArray[np.float64],
    intrinsics: Intrinsics,
    options: RenderOptions = RenderOptions(),
    rng: np.random.Generator | None = None,
) -> NDArray[np.float32]:
    """Render the depth image of a posed hand.

    Parameters
    ----------
    model : HandModel
        Hand geometry (handedness and :class:`HandShape` scaling are honoured).
    theta : array, shape (26,)
        Pose (mm, rad) in the camera optical frame.
    intrinsics : Intrinsics
        Pinhole camera; the output has shape ``(height, width)``.
    options : RenderOptions
        Sensor artefacts, forearm and background.
    rng : numpy.random.Generator, optional
        Source of all artefact randomness; ``None`` uses ``default_rng(0)``
        (so renders are deterministic either way).

    Returns
    -------
    array, shape (H, W), float32
        Depth (``z``) in millimetres; 0 = no measurement.

    Raises
    ------
    InputError
        If ``theta`` is not a finite (26,) vector.
    """
    theta = check_pose(theta)
    if rng is None:
        rng = np.random.default_rng(0)
    prims = hand_primitives(model, theta, forearm=options.forearm)
    zbuf, box = _render_geometry(prims, intrinsics)
    if options.background_mm is not None:
        zbuf = np.minimum(zbuf, options.background_mm)
    depth = np.where(np.isfinite(zbuf), zbuf, 0.0).astype(np.float32)
    if not options.exact:
        _apply_artefacts(depth, box, intrinsics, options, rng)
    return depth
