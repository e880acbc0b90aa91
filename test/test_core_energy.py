"""The objective: analytic gradient vs central differences, and the terms' behaviour."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from hand_sog_tracker.core.depth_sog import ImageSoG
from hand_sog_tracker.core.hand_model import (
    FINGER_DIP,
    FINGER_MCP,
    FINGER_PIP,
    N_PARAMS,
    default_hand_model,
    rest_pose,
)
from hand_sog_tracker.core.kinematics import fingertips, gaussian_centres
from hand_sog_tracker.core.objective import (
    COUPLING_DIP_PIP,
    CURL_MAX_RAD,
    ORDER_MIN_GAP_RAD,
    PAIR_CUT_SIGMAS,
    SIM_GAIN,
    SIM_SATURATION,
    Objective,
    TipTargets,
    gaussian_support,
    visibility_weights,
)
from hand_sog_tracker.core.optimizer import maximise
from hand_sog_tracker.core.silhouette import Silhouette
from hand_sog_tracker.core.types import TrackerConfig
from helpers import INTR


def data_near(
    model,
    theta: np.ndarray,
    rng: np.random.Generator,
    n: int = 300,
    spread_mm: float = 12.0,
    skip_chain: int | None = None,
) -> ImageSoG:
    """Random data Gaussians scattered around the hand's surface (mm, px).

    ``skip_chain`` leaves one finger without data (so that it dangles).
    """
    P = gaussian_centres(model, theta)
    allowed = np.flatnonzero(model.g_chain != skip_chain)
    pick = rng.choice(allowed, n)
    pts = P[pick] + rng.normal(0.0, spread_mm, (n, 3))
    pts[:, 2] -= model.g_sigmas[pick]  # front surface
    uv = INTR.project(pts)
    sigma = rng.choice([1.0, 2.0, 4.0], n) / np.sqrt(2.0) * 2.0
    return ImageSoG(
        mu=uv,
        sigma=sigma,
        depth=pts[:, 2],
        points=INTR.backproject(uv, pts[:, 2]),
        intrinsics=INTR,
        norm=float(2.0 * np.pi**2 * (sigma**2).sum()),
    )


def silhouette_of(model, theta: np.ndarray, skip_chain: int | None = None) -> Silhouette:
    """The silhouette of the model's Gaussians (discs of one sigma) at ``theta``, one chain left out."""
    P = gaussian_centres(model, theta)
    uv = INTR.project(P)
    r = model.g_sigmas * INTR.fx / P[:, 2]
    mask = np.zeros((INTR.height, INTR.width), np.uint8)
    for (u, v), rad, c in zip(uv, r, model.g_chain):
        if c != skip_chain:
            cv2.circle(mask, (int(round(u)), int(round(v))), int(round(rad)), 1, -1)
    dist = cv2.distanceTransform(1 - mask, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return Silhouette(distance=dist, origin=(0, 0), intrinsics=INTR)


def fist_of(theta: np.ndarray) -> np.ndarray:
    """``theta`` (26,) with index .. little curled into a fist (MCP 85, PIP 100, DIP 70 deg)."""
    fist = theta.copy()
    fist[FINGER_MCP], fist[FINGER_PIP], fist[FINGER_DIP] = np.radians([85.0, 100.0, 70.0])
    return fist


def numeric_gradient(obj: Objective, theta: np.ndarray) -> np.ndarray:
    g = np.zeros(N_PARAMS)
    for j in range(N_PARAMS):
        h = 1e-4 if j < 3 else 1e-6
        e = np.zeros(N_PARAMS)
        e[j] = h
        g[j] = (obj(theta + e, gradient=False)[0] - obj(theta - e, gradient=False)[0]) / (2 * h)
    return g


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_gradient_matches_central_differences(seed: int) -> None:
    rng = np.random.default_rng(seed)
    model = default_hand_model(right=bool(seed % 2))
    truth = rest_pose((0.0, 60.0, 400.0))
    truth[6:] = rng.uniform(0.0, 0.8, 20)
    data = data_near(model, truth, rng, skip_chain=4)
    theta = truth.copy()
    theta[:3] += rng.normal(0, 8, 3)
    theta[3:6] += rng.normal(0, 0.15, 3)
    theta[6:] += rng.normal(0, 0.4, 20)  # some beyond the joint limits
    # Middle swung over the index finger: the order term is active.
    theta[6 + 4 * 1 + 1] = 0.1
    theta[6 + 4 * 2 + 1] = -0.3
    # (PIP, DIP) of index .. little: two DIPs flexed beyond 2/3 of their PIP (coupling term
    # active), two within it; the little finger's PIP + DIP beyond CURL_MAX_RAD (curl term
    # active); none near a term's kink.
    for c, (pip, dip) in enumerate([(0.3, 0.8), (0.9, 0.2), (0.5, 0.75), (1.9, 1.1)], start=1):
        theta[6 + 4 * c + 2], theta[6 + 4 * c + 3] = pip + rng.normal(0, 0.02), dip + rng.normal(0, 0.02)
    prev = (truth + rng.normal(0, 0.05, N_PARAMS), truth)
    tips = fingertips(model, truth)
    targets = TipTargets(points=tips + rng.normal(0, 15, (5, 3)), weights=np.array([0.9, 0.0, 0.5, 1.0, 0.3]))
    cfg = TrackerConfig(w_sal=1.0, w_ord=1.0, w_sil=1.0, w_cpl=1.0, w_curl=1.0)
    sil = silhouette_of(model, truth, skip_chain=4)
    # Curled fingers' touching pairs with part of their overlap free (E_col's contact).
    contact = np.array([0.0, 1.0, 0.6, 1.0, 0.3])
    if seed == 3:  # (the model of the tracker's answer refinement, on the same data)
        model = model.with_joint_gaussians()
    # Seeds 2 and 3 weight the overlaps by their visibility in a fist (as the refinement does).
    visible_from = fist_of(truth) if seed >= 2 else None
    if visible_from is not None:
        assert visibility_weights(model, visible_from, INTR).min() < 0.1
    obj = Objective(
        model, data, cfg, previous=prev, targets=targets, silhouette=sil, contact=contact,
        visible_from=visible_from,
    )
    terms, grad = obj.evaluate(theta)
    # Every term is active in this configuration, so each one's gradient is checked.
    assert terms.sim > 0 and terms.col > 0 and terms.dan > 0 and terms.lim > 0 and terms.smo > 0
    assert terms.ord > 0 and terms.sal > 0 and terms.sil > 0 and terms.cpl > 0 and terms.curl > 0
    num = numeric_gradient(obj, theta)
    np.testing.assert_allclose(grad, num, rtol=1e-4, atol=1e-6 * np.abs(num).max())


def test_each_term_weight_enters_the_gradient() -> None:
    rng = np.random.default_rng(7)
    model = default_hand_model()
    theta = rest_pose((0.0, 60.0, 400.0))
    data = data_near(model, theta, rng)
    theta = theta + rng.normal(0, 0.3, N_PARAMS)
    base = TrackerConfig(
        w_col=0.0, w_dan=0.0, w_lim=0.0, w_smo=0.0, w_ord=0.0, w_sal=0.0, w_sil=0.0, w_cpl=0.0, w_curl=0.0
    )
    _, g0 = Objective(model, data, base).evaluate(theta)
    theta[6 + 4 * 2 + 1] = 0.3  # middle swung over the ring finger: order term active
    theta[6 + 4 * 3 + 2], theta[6 + 4 * 3 + 3] = 0.3, 0.9  # ring DIP beyond 2/3 PIP: coupling active
    theta[6 + 4 * 4 + 2], theta[6 + 4 * 4 + 3] = 1.9, 1.2  # little PIP + DIP beyond 165 deg: curl active
    targets = TipTargets(points=fingertips(model, theta) + 20.0, weights=np.ones(5))
    _, g0 = Objective(model, data, base, targets=targets).evaluate(theta)
    sil = silhouette_of(model, rest_pose((0.0, 60.0, 400.0)), skip_chain=2)
    _, g0 = Objective(model, data, base, targets=targets, silhouette=sil).evaluate(theta)
    for name in ("w_col", "w_dan", "w_lim", "w_ord", "w_sal", "w_sil", "w_cpl", "w_curl"):
        cfg = TrackerConfig(**{**base.__dict__, name: 1.0})
        terms, g = Objective(model, data, cfg, targets=targets, silhouette=sil).evaluate(theta)
        assert not np.allclose(g, g0), name


def test_order_term_is_zero_for_fingers_in_order_and_grows_when_they_cross() -> None:
    model = default_hand_model()
    rng = np.random.default_rng(3)
    theta = rest_pose((0.0, 60.0, 400.0))
    data = data_near(model, theta, rng)
    obj = Objective(model, data, TrackerConfig())
    assert obj.evaluate(theta, gradient=False)[0].ord == 0.0
    values = []
    for swing in (0.0, 0.1, 0.2, 0.3):
        crossed = theta.copy()
        crossed[6 + 4 * 4 + 1] = -swing  # little toward the ring finger
        values.append(obj.evaluate(crossed, gradient=False)[0].ord)
    # Little and ring fan apart by 0.09 rad at rest: crossing starts beyond 0.09 - gap.
    assert values[0] == 0.0 and values[1] == 0.0
    assert 0.0 < values[2] < values[3]
    np.testing.assert_allclose(values[3], (0.09 - 0.3 - ORDER_MIN_GAP_RAD) ** 2, rtol=1e-6)


def test_coupling_term_costs_only_a_dip_flexed_beyond_two_thirds_of_its_pip() -> None:
    model = default_hand_model()
    theta = rest_pose((0.0, 60.0, 400.0))
    obj = Objective(model, data_near(model, theta, np.random.default_rng(5)), TrackerConfig(w_cpl=1.0))
    pip, dip = 6 + 4 * 2 + 2, 6 + 4 * 2 + 3  # middle finger
    values = []
    for pip_v, dip_v in ((1.5, 1.0), (1.5, 0.5), (0.0, 0.0), (1.5, 1.2), (1.5, 1.4), (0.0, 0.3)):
        posed = theta.copy()
        posed[pip], posed[dip] = pip_v, dip_v
        values.append(obj.evaluate(posed, gradient=False)[0].cpl)
    assert values[:3] == [0.0, 0.0, 0.0]  # DIP = 2/3 PIP, less, or both straight: no cost
    np.testing.assert_allclose(values[3:], [(1.2 - 1.0) ** 2, (1.4 - 1.0) ** 2, 0.3**2], rtol=1e-9)
    assert COUPLING_DIP_PIP == pytest.approx(2.0 / 3.0)


def test_curl_term_costs_only_pip_and_dip_flexed_beyond_165_degrees_together() -> None:
    model = default_hand_model()
    theta = rest_pose((0.0, 60.0, 400.0))
    obj = Objective(model, data_near(model, theta, np.random.default_rng(5)), TrackerConfig(w_curl=1.0))
    pip, dip = 6 + 4 * 2 + 2, 6 + 4 * 2 + 3  # middle finger
    limit = np.deg2rad(165.0)
    values = []
    for pip_v, dip_v in ((1.65, 0.95), (0.1, 1.5), (0.0, 0.0), (1.9, 1.57), (1.92, 1.1)):
        posed = theta.copy()
        posed[pip], posed[dip] = pip_v, dip_v
        values.append(obj.evaluate(posed, gradient=False)[0].curl)
    # A fist's 95 + 55 deg, a DIP flexed with a straight PIP, a straight finger: no cost.
    assert values[:3] == [0.0, 0.0, 0.0]
    np.testing.assert_allclose(values[3:], [(1.9 + 1.57 - limit) ** 2, (1.92 + 1.1 - limit) ** 2], rtol=1e-9)
    assert CURL_MAX_RAD == pytest.approx(limit)


def test_salient_term_pulls_fingertips_to_their_targets() -> None:
    model = default_hand_model()
    rng = np.random.default_rng(4)
    truth = rest_pose((0.0, 60.0, 400.0))
    data = data_near(model, truth, rng, n=20)  # almost no depth evidence
    moved = truth.copy()
    moved[6 + 4 * 2] = 1.0  # middle finger flexed
    targets = TipTargets(points=fingertips(model, truth), weights=np.array([0, 0, 1.0, 0, 0]))
    cfg = TrackerConfig(w_sal=5.0)
    obj = Objective(model, data, cfg, targets=targets)
    res = maximise(obj, moved, iterations=40)
    err = lambda th: np.linalg.norm(fingertips(model, th)[2] - targets.points[2])  # noqa: E731
    assert err(res.x) < 0.3 * err(moved)


def test_similarity_is_highest_at_the_data() -> None:
    rng = np.random.default_rng(8)
    model = default_hand_model()
    truth = rest_pose((0.0, 60.0, 400.0))
    data = data_near(model, truth, rng, n=500)
    obj = Objective(model, data, TrackerConfig())
    e_true = obj.evaluate(truth, gradient=False)[0].sim
    for shift in ([20, 0, 0], [0, 20, 0], [0, 0, 30]):
        moved = truth.copy()
        moved[:3] += shift
        assert obj.evaluate(moved, gradient=False)[0].sim < e_true


def test_optimiser_recovers_a_perturbed_pose() -> None:
    rng = np.random.default_rng(9)
    model = default_hand_model()
    truth = rest_pose((0.0, 60.0, 400.0))
    data = data_near(model, truth, rng, n=600, spread_mm=4.0)
    obj = Objective(model, data, TrackerConfig())
    start = truth.copy()
    start[:3] += [8.0, -6.0, 5.0]
    start[6:] += rng.normal(0.0, 0.15, 20)
    res = maximise(obj, start, iterations=40)
    assert res.success and res.nit >= 1 and res.fun >= res.history[0]

    def tip_error(theta: np.ndarray) -> float:
        return float(np.linalg.norm(fingertips(model, theta) - fingertips(model, truth), axis=1).mean())

    assert tip_error(res.x) < tip_error(start) / 2
    assert res.x.shape == (N_PARAMS,) and isinstance(res.message, str)


def test_silhouette_term_is_zero_inside_and_grows_outside() -> None:
    model = default_hand_model()
    rng = np.random.default_rng(5)
    theta = rest_pose((0.0, 60.0, 400.0))
    data = data_near(model, theta, rng)
    sil = silhouette_of(model, theta)
    obj = Objective(model, data, TrackerConfig(w_sil=1.0), silhouette=sil)
    assert obj.evaluate(theta, gradient=False)[0].sil == 0.0
    values = []
    for shift in (10.0, 20.0, 40.0):
        moved = theta.copy()
        moved[0] += shift
        values.append(obj.evaluate(moved, gradient=False)[0].sil)
    assert 0.0 < values[0] < values[1] < values[2]


def _saturated(data: ImageSoG, overlap: np.ndarray) -> float:
    """``E_sim`` from each image Gaussian's overlap with the model ``S_q`` (n,): the saturated
    sum of the module docstring."""
    k = SIM_SATURATION * np.pi * data.sigma**2
    return float((SIM_GAIN * k * (1.0 - np.exp(-overlap / k))).sum() / data.norm)


def _dense_data_terms(
    obj: Objective, theta: np.ndarray, visibility: np.ndarray | None = None
) -> tuple[float, float]:
    """``E_sim`` and ``E_dan`` over all model x data pairs, straight from the module docstring
    (``visibility`` (m,): each model Gaussian's weight of its overlaps)."""
    model, data = obj.model, obj.data
    intr = data.intrinsics
    f = np.sqrt(intr.fx * intr.fy)
    P = gaussian_centres(model, theta)
    z = P[:, 2]
    u = intr.fx * P[:, 0] / z + intr.cx
    v = intr.fy * P[:, 1] / z + intr.cy
    sp2 = ((model.g_sigmas * f / z) ** 2)[:, None]
    sq2 = (data.sigma**2)[None, :]
    r2 = (u[:, None] - data.mu[None, :, 0]) ** 2 + (v[:, None] - data.mu[None, :, 1]) ** 2
    s2 = sp2 + sq2
    D = 2 * np.pi * sp2 * sq2 / s2 * np.exp(-0.5 * r2 / s2) * (r2 < PAIR_CUT_SIGMAS**2 * s2)
    if visibility is not None:
        D = D * visibility[:, None]
    dd = (z - model.g_sigmas)[:, None] - data.depth[None, :]
    delta = np.maximum(1.0 - np.abs(dd) / (2.0 * model.g_sigmas[:, None]), 0.0)
    sim = _saturated(data, (delta * D).sum(axis=0))
    lat = np.maximum(np.sqrt(r2) - data.sigma[None, :] / np.sqrt(2.0), 0.0) * (z / f)[:, None]
    dist = np.sqrt(lat**2 + np.maximum(-dd, 0.0) ** 2)
    w = np.clip((dist.min(axis=1) - 15.0) / 15.0, 0.0, 1.0)
    phi = np.clip((dist - 15.0) / 45.0, 0.0, 1.0)
    dan = float((w * (phi * (1.0 - np.exp(-0.5 * r2 / s2))).sum(axis=1)).sum() / data.n)
    return sim, dan


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sparse_data_terms_equal_the_dense_definition(seed: int) -> None:
    # The objective evaluates E_sim on candidate pairs only and the dangle distances of all
    # data only for the model Gaussians no candidate pair settles: same values as all pairs,
    # with dangling fingers, data in front of the model (occluders) and model off the data.
    model = default_hand_model()
    rng = np.random.default_rng(seed)
    truth = rest_pose((0.0, 60.0, 400.0))
    data = data_near(model, truth, rng, skip_chain=seed + 1)
    front = data.depth.copy()
    front[: data.n // 5] -= 40.0  # a fifth of the data 40 mm nearer: occluders
    data = ImageSoG(data.mu, data.sigma, front, INTR.backproject(data.mu, front), INTR, data.norm)
    # Seed 2: the overlaps weighted by their visibility in a fist.
    visible_from = fist_of(truth) if seed == 2 else None
    obj = Objective(model, data, TrackerConfig(), visible_from=visible_from)
    vis = None if visible_from is None else visibility_weights(model, visible_from, INTR)
    for shift in (0.0, 8.0, 30.0):
        theta = truth.copy()
        theta[0] += shift
        theta[6:] += rng.normal(0.0, 0.1, theta.size - 6)
        terms, _ = obj.evaluate(theta)
        sim, dan = _dense_data_terms(obj, theta, vis)
        assert terms.sim == pytest.approx(sim, rel=1e-6)
        assert terms.dan == pytest.approx(dan, rel=1e-9, abs=1e-12)
        if shift == 30.0:
            assert terms.dan > 0


def test_visibility_weights_hide_what_curled_fingers_cover() -> None:
    # The palm faces the camera in the rest pose.  Open, only the palm's radial column lies
    # partly under the thumb's base; in a fist the palm behind the curled fingers and the
    # fingertips behind their middle segments are hidden; seen from the back, the palm is in
    # front of the fingers and stays visible.  Only the palm's and the distal segments'
    # Gaussians are ever weighted.
    model = default_hand_model()
    open_hand = rest_pose((0.0, 60.0, 400.0))
    fist = fist_of(open_hand)
    back = fist.copy()
    back[4] += np.pi  # (turned about the camera's y axis: the back of the hand toward it)
    palm = model.g_chain < 0
    weighted = palm | ((model.g_chain >= 1) & (model.g_segment == 2))
    w_open, w_fist, w_back = (visibility_weights(model, t, INTR) for t in (open_hand, fist, back))
    for w in (w_open, w_fist, w_back):
        assert np.all((w >= 0.0) & (w <= 1.0))
        assert np.all(w[~weighted] == 1.0)
    radial = palm & (model.g_offsets[:, 0] > 20.0)  # (the right hand's thumb side)
    assert w_open[weighted & ~radial].min() > 0.85
    assert w_open[radial].min() < 0.5
    assert np.sum(w_fist[palm] < 0.1) >= 6  # the palm's distal rows, under the fingers
    assert w_fist[palm].max() > 0.95  # the rows near the wrist stay in view
    assert np.median(w_fist[weighted & ~palm]) < 0.35
    assert w_back[palm].min() > 0.99


def test_objective_with_visibility_weights_the_overlaps() -> None:
    # A fist's hidden palm earns less overlap; the weights are the objective's for every
    # variant of it, and its support is not taken from the weighted overlaps.
    model = default_hand_model()
    rng = np.random.default_rng(7)
    fist = fist_of(rest_pose((0.0, 60.0, 400.0)))
    data = data_near(model, fist, rng)
    plain = Objective(model, data, TrackerConfig())
    weighted = Objective(model, data, TrackerConfig(), visible_from=fist)
    sim_plain = plain.evaluate(fist, gradient=False)[0].sim
    sim_weighted = weighted.evaluate(fist, gradient=False)[0].sim
    assert 0.0 < sim_weighted < 0.95 * sim_plain
    other = weighted.variant(TrackerConfig(w_sal=0.0), None)
    assert other.evaluate(fist, gradient=False)[0].sim == sim_weighted
    assert weighted.support(fist) is None
    assert plain.support(fist) is not None


def test_call_and_evaluate_agree_with_and_without_gradient() -> None:
    # __call__ (the optimiser's path, no EnergyTerms) and evaluate share one body: the same
    # value and gradient, and the value-only path gives the same value.
    rng = np.random.default_rng(4)
    model = default_hand_model()
    truth = rest_pose((0.0, 60.0, 400.0))
    data = data_near(model, truth, rng)
    targets = TipTargets(points=fingertips(model, truth) + 5.0, weights=np.array([1.0, 0.0, 0.5, 1.0, 0.2]))
    obj = Objective(
        model, data, TrackerConfig(w_sil=1.0), previous=(truth, truth), targets=targets,
        silhouette=silhouette_of(model, truth, skip_chain=3),
    )
    theta = truth + rng.normal(0.0, 0.05, N_PARAMS)
    terms, grad = obj.evaluate(theta)
    value, grad2 = obj(theta)
    assert value == terms.total
    np.testing.assert_array_equal(grad, grad2)
    assert obj(theta, gradient=False) == (terms.total, None)
    assert obj.evaluate(theta, gradient=False)[0] == terms


@pytest.mark.parametrize("seed", [0, 1])
def test_candidate_product_keeps_exactly_the_pairs_of_the_definition(seed: int) -> None:
    # The candidate tests are one matrix product of expanded squares; E_sim over the pairs it
    # keeps equals the sum over the pairs of the plain tests (|dd| < 2 sigma_h, r^2 < c^2 s^2)
    # to rounding, and its exact differences give the plain per-pair values.
    model = default_hand_model()
    rng = np.random.default_rng(10 + seed)
    truth = rest_pose((0.0, 60.0, 400.0))
    data = data_near(model, truth, rng, n=400)
    obj = Objective(model, data, TrackerConfig())
    intr = data.intrinsics
    f = np.sqrt(intr.fx * intr.fy)
    for _ in range(4):
        theta = truth + rng.normal(0.0, 0.1, N_PARAMS) * np.r_[50.0, 50.0, 50.0, np.ones(23)]
        P = gaussian_centres(model, theta)
        sh = model.g_sigmas
        z = P[:, 2]
        u = intr.fx * P[:, 0] / z + intr.cx
        v = intr.fy * P[:, 1] / z + intr.cy
        sp = sh * f / z
        du = u[:, None] - data.mu[None, :, 0]
        dv = v[:, None] - data.mu[None, :, 1]
        r2 = du * du + dv * dv
        dd = (z - sh)[:, None] - data.depth[None, :]
        c2 = PAIR_CUT_SIGMAS**2
        keep = (np.abs(dd) < 2.0 * sh[:, None]) & (r2 < (c2 * sp * sp)[:, None] + c2 * data.sigma**2)
        s2 = (sp * sp)[:, None] + data.sigma**2
        D = 2 * np.pi * (sp * sp)[:, None] * data.sigma**2 / s2 * np.exp(-0.5 * r2 / s2)
        sim = _saturated(data, np.where(keep, (1.0 - np.abs(dd) / (2.0 * sh[:, None])) * D, 0.0).sum(axis=0))
        assert 0.1 < keep.mean() < 0.9  # both tests decide
        assert obj._data_terms(P, None, 0.0)[0] == pytest.approx(sim, rel=1e-12)


@pytest.mark.parametrize("seed", [0, 1])
def test_gaussian_support_equals_the_dense_definition(seed: int) -> None:
    # gaussian_support tests only the candidates of the expanded-square product (with slack)
    # exactly: bit for bit the support computed from all m x n pairs.
    model = default_hand_model()
    rng = np.random.default_rng(20 + seed)
    truth = rest_pose((0.0, 60.0, 400.0))
    data = data_near(model, truth, rng, n=400, skip_chain=seed + 2)
    intr = data.intrinsics
    for k in range(6):
        theta = truth + rng.normal(0.0, 0.08, N_PARAMS) * np.r_[60.0, 60.0, 60.0, np.ones(23)] * (k > 0)
        P = gaussian_centres(model, theta)
        sh = model.g_sigmas
        z = np.maximum(P[:, 2], 1.0)
        u = intr.fx * P[:, 0] / z + intr.cx
        v = intr.fy * P[:, 1] / z + intr.cy
        sp2 = (sh * np.sqrt(intr.fx * intr.fy) / z) ** 2
        sq2 = data.sigma**2
        du = u[:, None] - data.mu[:, 0]
        dv = v[:, None] - data.mu[:, 1]
        r2 = du * du + dv * dv
        dd = np.abs((z - sh)[:, None] - data.depth)
        p, q = np.nonzero((dd < (2.0 * sh)[:, None]) & (r2 < PAIR_CUT_SIGMAS**2 * (sp2[:, None] + sq2)))
        s2 = sp2[p] + sq2[q]
        D = 2 * np.pi * sp2[p] * sq2[q] / s2 * np.exp(-0.5 * r2[p, q] / s2)
        delta = 1.0 - dd[p, q] / (2.0 * sh)[p]
        dense = np.minimum(np.bincount(p, weights=delta * D, minlength=sh.size) / (2 * np.pi**2 * sp2), 1.0)
        assert 0 < p.size < r2.size // 2
        np.testing.assert_array_equal(gaussian_support(model, theta, data), dense)
        np.testing.assert_array_equal(gaussian_support(model, theta, data, centres=P), dense)
    empty = ImageSoG(np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros((0, 3)), intr, 0.0)
    np.testing.assert_array_equal(gaussian_support(model, truth, empty), np.zeros(model.n_gaussians))


def test_objective_support_is_the_support_of_its_last_evaluation() -> None:
    # The tracker's confidence reads the support of the fit's last evaluation when that was at
    # the result's pose: the same as gaussian_support up to rounding, and only at that pose.
    model = default_hand_model()
    rng = np.random.default_rng(31)
    truth = rest_pose((0.0, 60.0, 400.0))
    data = data_near(model, truth, rng, n=400, skip_chain=3)
    obj = Objective(model, data, TrackerConfig())
    assert obj.support(truth) is None  # nothing evaluated yet
    for k, gradient in enumerate((True, False, True)):
        theta = truth + rng.normal(0.0, 0.05, N_PARAMS) * np.r_[40.0, 40.0, 40.0, np.ones(23)] * (k > 0)
        obj(theta, gradient=gradient)
        support = obj.support(theta)
        assert support is not None
        expected = gaussian_support(model, theta, data)
        assert 0.1 < expected.mean() and (expected < 1.0).any()
        np.testing.assert_allclose(support, expected, rtol=1e-12, atol=1e-14)
        assert obj.support(theta + 1e-9) is None  # another pose: not known
    empty = ImageSoG(np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros((0, 3)), data.intrinsics, 0.0)
    no_data = Objective(model, empty, TrackerConfig())
    no_data(truth)
    assert no_data.support(truth) is None


def test_objective_and_support_where_no_pair_overlaps() -> None:
    # A pose far from every data Gaussian (e.g. a restart pulled off the data): no pair passes
    # the candidate tests.  The sums per data and per model Gaussian are then empty, which once
    # raised (an empty weighted bincount is an integer array) on a real frame.
    model = default_hand_model()
    rng = np.random.default_rng(41)
    truth = rest_pose((0.0, 60.0, 400.0))
    data = data_near(model, truth, rng, n=200)
    away = truth.copy()
    away[:3] += (400.0, 0.0, 300.0)
    obj = Objective(model, data, TrackerConfig())
    value, grad = obj(away)
    assert grad is not None and np.all(np.isfinite(grad)) and np.isfinite(value)
    terms, _ = obj.evaluate(away, gradient=False)
    assert terms.sim == 0.0 and terms.dan > 0.0  # nothing overlaps; every Gaussian dangles
    np.testing.assert_array_equal(obj.support(away), np.zeros(model.n_gaussians))
    np.testing.assert_array_equal(gaussian_support(model, away, data), np.zeros(model.n_gaussians))


def test_similarity_saturates_where_two_model_parts_explain_the_same_data() -> None:
    # E_sim counts an image Gaussian's overlap with the model saturated (module docstring):
    # a second model Gaussian on data already explained adds less than the first did, so two
    # model fingers on one finger's data gain little over one.  With eq. 5's plain sum the
    # pair would score exactly the sum of the two.
    model = default_hand_model()
    sh = model.g_sigmas
    i, j = np.flatnonzero(np.isclose(sh, sh[-1]))[:2]  # two Gaussians of equal radius
    centre = np.array([0.0, 0.0, 400.0])
    uv = INTR.project(centre[None, :] - [0.0, 0.0, sh[i]])
    sigma = np.full(1, 1.5)
    depth = np.array([centre[2] - sh[i]])
    data = ImageSoG(uv, sigma, depth, INTR.backproject(uv, depth), INTR, float(2.0 * np.pi**2 * 1.5**2))
    obj = Objective(model, data, TrackerConfig())

    def sim_with(parts: list[int]) -> float:
        P = np.tile([0.0, 0.0, 2000.0], (model.n_gaussians, 1))  # far behind: Delta = 0
        P[parts] = centre
        return obj._data_terms(P, None, 0.0)[0]

    one, other, both = sim_with([i]), sim_with([j]), sim_with([i, j])
    assert one == pytest.approx(other) and one > 0.0
    assert one < both < 0.85 * (one + other)
    assert both == pytest.approx(_saturated(data, np.array([2.0 * _saturated_inverse(data, one)])))


def _saturated_inverse(data: ImageSoG, sim: float) -> float:
    """The overlap ``S`` of a single image Gaussian that :func:`_saturated` maps to ``sim``."""
    k = SIM_SATURATION * np.pi * data.sigma[0] ** 2
    return float(-k * np.log(1.0 - sim * data.norm / (SIM_GAIN * k)))


def test_palm_presses_on_distal_segments_weigh_less_in_the_collision_term() -> None:
    """``E_col``: the palm against a distal segment weighs ``PALM_DISTAL_COLLISION`` (a fist
    presses the finger pads into the palm), every other pair 1; no pair within one chain."""
    from hand_sog_tracker.core.objective.collision import PALM_DISTAL_COLLISION, _collision_pairs

    model = default_hand_model()
    i, j, weight, _ = _collision_pairs(model)
    ch, sg = model.g_chain, model.g_segment
    assert not np.any(ch[i] == ch[j])
    palm_distal = ((ch[i] < 0) & (sg[j] == 2)) | ((ch[j] < 0) & (sg[i] == 2))
    assert palm_distal.any() and (~palm_distal).any()
    assert 0.0 < PALM_DISTAL_COLLISION < 1.0
    np.testing.assert_array_equal(weight[palm_distal], PALM_DISTAL_COLLISION)
    np.testing.assert_array_equal(weight[~palm_distal], 1.0)


def test_curled_fingers_touching_side_by_side_or_on_the_palm_pay_only_beyond_their_free_share() -> None:
    """``E_col`` per pair: two of the fingers index .. little, or the palm and a distal
    segment, pay ``max(D - share COLLISION_CONTACT_FREE D_touch, 0)`` (``D_touch``: the overlap
    at centres ``s_i + s_j`` apart; ``share``: the ``contact`` of the pair's less curled
    finger); the thumb against a finger, or the palm against a middle segment, pay all of
    ``D``, and so does every pair without ``contact``.  Checked pair by pair, every other
    Gaussian far away, with the gradient against central differences."""
    from hand_sog_tracker.core.objective.collision import COLLISION_CONTACT_FREE, PALM_DISTAL_COLLISION, model_constants

    model = default_hand_model()
    ch, sg, s = model.g_chain, model.g_segment, model.g_sigmas
    data = data_near(model, rest_pose(), np.random.default_rng(0))
    norm_h = model_constants(model).norm_h
    contact = np.array([1.0, 1.0, 1.0, 0.5, 0.0])  # thumb, index, middle curled, ring half, little open

    def first(chain: int, segment: int) -> int:
        return int(np.flatnonzero((ch == chain) & (sg == segment))[0])

    def pair_cost(p: int, q: int, dist: float, contact: np.ndarray | None = contact) -> tuple[float, np.ndarray]:
        obj = Objective(model, data, TrackerConfig(), contact=contact)
        P = np.arange(model.n_gaussians)[:, None] * np.array([1000.0, 0.0, 0.0])  # 1 m apart
        P[q] = P[p] + np.array([0.0, dist, 0.0])
        g3 = np.zeros_like(P)
        col = obj._collision(P, g3, 1.0)
        h = 1e-4
        num = []
        for sign in (1.0, -1.0):
            Ph = P.copy()
            Ph[q, 1] += sign * h
            num.append(obj._collision(Ph, None, 1.0))
        # g3 holds -dE_col/dP: check the moved Gaussian's y component.
        np.testing.assert_allclose(-g3[q, 1], (num[0] - num[1]) / (2 * h), rtol=1e-5, atol=1e-12)
        return col * norm_h, g3

    def overlap(p: int, q: int, dist: float, weight: float = 1.0) -> float:
        s2 = s[p] ** 2 + s[q] ** 2
        return weight * (2 * np.pi * s[p] ** 2 * s[q] ** 2 / s2) ** 1.5 * np.exp(-0.5 * dist**2 / s2)

    index, middle, ring, little = (first(c, 1) for c in (1, 2, 3, 4))
    thumb, palm = first(0, 1), first(-1, 0)
    cases = (
        (index, middle, 1.0, 1.0),  # two curled fingers
        (palm, first(2, 2), PALM_DISTAL_COLLISION, 1.0),  # the palm and a curled finger's pad
        (middle, ring, 1.0, 0.5),  # the less curled finger counts
    )
    for p, q, weight, share in cases:
        touch = s[p] + s[q]
        free = share * COLLISION_CONTACT_FREE * overlap(p, q, touch, weight)
        for dist in (0.0, 0.5 * touch, touch):
            cost, _ = pair_cost(p, q, dist)
            assert cost == pytest.approx(overlap(p, q, dist, weight) - free, rel=1e-9)
            # Without contact (initialisation, calibration) the pair pays its whole overlap.
            assert pair_cost(p, q, dist, None)[0] == pytest.approx(overlap(p, q, dist, weight), rel=1e-9)
        if share == 1.0:
            cost, g3 = pair_cost(p, q, 1.3 * touch)  # a little apart: within the free share
            assert cost == 0.0 and not g3.any()
    # These pay the whole overlap: an open finger, the thumb, the palm against a middle segment.
    for p, q in ((ring, little), (thumb, index), (palm, first(2, 1))):
        touch = s[p] + s[q]
        assert pair_cost(p, q, touch)[0] == pytest.approx(overlap(p, q, touch), rel=1e-9)


def test_contact_shares_grow_with_a_fingers_curl() -> None:
    """:func:`contact_shares`: 0 for the thumb and for fingers flexed (MCP + PIP) up to
    ``CONTACT_CURL_RAD[0]``, 1 from ``CONTACT_CURL_RAD[0] + CONTACT_CURL_RAD[1]``, linear between."""
    from hand_sog_tracker.core.articulations import CLOSED, OPEN
    from hand_sog_tracker.core.objective import CONTACT_CURL_RAD, contact_shares

    theta = rest_pose()
    theta[6:] = OPEN
    np.testing.assert_array_equal(contact_shares(theta), 0.0)
    theta[6:] = CLOSED
    np.testing.assert_array_equal(contact_shares(theta), [0.0, 1.0, 1.0, 1.0, 1.0])
    lo, span = CONTACT_CURL_RAD
    theta[6 + 4 * 2] = lo + 0.25 * span - theta[6 + 4 * 2 + 2]  # the middle finger's MCP
    assert contact_shares(theta)[2] == pytest.approx(0.25)
