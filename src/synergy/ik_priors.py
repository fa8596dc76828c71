"""The marker IK's priors and what they tell: the weak DIP ≈ ⅔ PIP coupling, the posture prior's rows,
the Gauss-Newton refinement with them (per frame and over a trajectory), each joint's posterior SD
from the normal equations and which joints the priors decide (:func:`prior_driven`).

Used by :func:`synergy.angles.markers_to_angles`; the prior itself is :class:`synergy.prior.PosturePrior`.
"""
from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import spsolve

from threadpoolctl import threadpool_limits

from .prior import resolve_prior

#: The posture prior ``prior='auto'`` uses where the markers leave a joint weakly observed.
DEFAULT_PRIOR = "fingerfist"
#: DIP flexion ≈ this × PIP flexion in the fingers' coupled motion (Rijpkema & Girard 1991) …
IP_COUPLING = 2.0 / 3.0
#: … with this SD (degrees) as a weak prior: linear DIP-from-PIP estimates miss by a mean absolute
#: 5.9–13.7° per manipulation task (Roda-Sales, Sancho-Bru & Vergara 2022, PeerJ 10:e14051), an SD
#: of ~7–17°. Where the markers fix the DIP the prior moves it little; it decides where they leave
#: a flat valley (hand16 in a fist: PIP +23°, DIP −37° moves its two finger markers by 1.2 and
#: 0.6 mm on the true hand, within the noise).
IP_COUPLING_SD_DEG = 10.0
#: A joint whose markers give less than this share of its information (posterior variance with the
#: priors over that without, median over frames) is "weakly observed: prior-driven".
PRIOR_DRIVEN_SHARE = 0.5
#: SD (degrees/s²) of the weak prior on each finger joint's angular acceleration that ties a
#: trajectory's frames together when the markers are low-passed (:func:`refine_trajectory`). A power
#: grasp closes at ~900°/s²; a joint the markers fix keeps a 30° swing at 4 Hz (~19000°/s²) within ~2°.
ACCEL_SD_DEG_S2 = 3000.0


def dip_fixed_fingers(markerset) -> set:
    """The fingers whose DIP angle the marker set fixes by geometry: joint-centre markers at the PIP
    and the DIP and a fingertip marker (a joint-centre export such as ART's). The DIP prior has
    nothing to decide there and would only bend a measured angle (ART: residual 1.58 → 1.60 mm)."""
    have = {(m.landmark.get("type"), m.landmark.get("joint")) for m in getattr(markerset, "markers", ())
            if m.landmark}
    return {f for f in ("index", "middle", "ring", "pinky")
            if {("joint_centre", f"{f}2"), ("joint_centre", f"{f}3"), ("fingertip", f"{f}_tip")} <= have}


def ip_coupling_pairs(hand, skip=()):
    """``(pip, dip)`` DoF indices of the four fingers (not the thumb, whose three bones carry markers
    in every shipped set; nor the fingers in ``skip``, e.g. :func:`dip_fixed_fingers`) for
    :func:`refine_with_coupling`."""
    names = list(hand.dof_names)
    return np.array([(names.index(f"{f}2_flex"), names.index(f"{f}3_flex"))
                     for f in ("index", "middle", "ring", "pinky") if f"{f}3_flex" in names and f not in skip],
                    np.int64).reshape(-1, 2)


def _weighted_targets(targets, rows, nodes, weights, noise_mm):
    """The markers of frames ``rows`` in mm with missing ones zeroed, and each one's weight over the
    noise (0 where missing): what the IK refinements fit."""
    tg = 1000.0 * np.asarray(targets, float)[rows]
    present = np.isfinite(tg[..., 0])
    w = np.ones(len(nodes)) if weights is None else np.asarray(weights, float)
    return np.nan_to_num(tg), (w[None, :] * present) / float(noise_mm)


def dip_prior_rows(pairs, n, ratio, sd_deg):
    """The DIP prior's residual rows over ``n`` DoF: ``(dip − ratio · pip) / sd`` per ``(pip, dip)``
    pair (radians; none when there are no pairs)."""
    P = np.zeros((len(pairs), n))
    if len(pairs):
        P[np.arange(len(pairs)), pairs[:, 1]] = 1.0
        P[np.arange(len(pairs)), pairs[:, 0]] = -ratio
        P /= np.radians(sd_deg)
    return P


def refine_with_coupling(hand, nodes, local, targets, theta, weights, *, noise_mm, sd_deg=IP_COUPLING_SD_DEG,
                         ratio=IP_COUPLING, iterations=12, skip=()):
    """Marker IK with a weak prior that each finger's DIP follows its PIP (``ratio``, SD ``sd_deg``).

    Starts from ``theta`` (an IK solution, ``(F, n)``) and from the same posture with each DIP set to
    ``ratio`` × PIP, runs a damped Gauss-Newton on markers (SD ``noise_mm`` per coordinate) plus the
    prior from both, and keeps the lower cost per frame; limits are the model's. Frames without a
    finite ``theta`` are left alone; fingers in ``skip`` get no prior. Returns ``theta`` refined.

    >>> from handmodel import HandModel
    >>> h = HandModel.load()
    >>> import numpy as np
    >>> th = np.zeros((1, 26)); th[0, 2] = 0.5
    >>> n, l = np.arange(h.n_nodes), np.zeros((h.n_nodes, 3))
    >>> out = refine_with_coupling(h, n, l, h.points(th, n, l), th, None, noise_mm=0.5)
    >>> bool(np.abs(out - th).max() < 1e-6)
    True
    """
    pairs = ip_coupling_pairs(hand, skip)
    if not len(pairs) or not sd_deg:
        return np.array(theta, float)
    return refine_with_prior(hand, nodes, local, targets, theta, weights, noise_mm=noise_mm,
                             rows=(dip_prior_rows(pairs, hand.n_dofs, ratio, sd_deg), np.zeros(len(pairs))),
                             coupled=(pairs, ratio), iterations=iterations)


def prior_rows(hand, prior=None, *, dip_sd_deg=None, ratio=IP_COUPLING, skip=()):
    """The stacked linear residual rows ``(P, c)`` (``r = P θ − c``) of the IK's posture priors: a
    :class:`~synergy.prior.PosturePrior` and the DIP prior (:func:`dip_prior_rows`), either or both."""
    P, c = [np.zeros((0, hand.n_dofs))], [np.zeros(0)]
    if prior is not None:
        Pp, cp = prior.rows(hand)
        P.append(Pp)
        c.append(cp)
    pairs = ip_coupling_pairs(hand, skip) if dip_sd_deg else np.zeros((0, 2), np.int64)
    if len(pairs):
        P.append(dip_prior_rows(pairs, hand.n_dofs, ratio, dip_sd_deg))
        c.append(np.zeros(len(pairs)))
    return np.vstack(P), np.concatenate(c)


def refine_with_prior(hand, nodes, local, targets, theta, weights, *, noise_mm, rows, coupled=None, mean=None,
                      iterations=12):
    """Marker IK (markers with SD ``noise_mm`` per coordinate) plus linear Gaussian prior rows
    ``rows = (P, c)`` (residual ``P θ − c``, see :func:`prior_rows`), per frame.

    Starts from ``theta`` (``(F, n)``, NaN rows left alone), from the same posture with each DIP set
    to ``ratio`` × PIP where ``coupled = (pairs, ratio)``, and from the posture ``mean`` (20 angles)
    at each frame's pose where given; a damped Gauss-Newton from each, the lowest cost kept per
    frame; limits are the model's. Returns ``theta`` refined.
    """
    P, c0 = (np.asarray(x, float) for x in rows)
    th = np.array(theta, float)
    ok = np.isfinite(th).all(1)
    if not ok.any() or not len(P):
        return th
    lim = np.asarray(hand.limits, float)
    y, ww = _weighted_targets(targets, ok, nodes, weights, noise_mm)
    n = hand.n_dofs

    def cost_and_terms(t):
        p = 1000.0 * hand.points(t, nodes, local)
        r = ww[..., None] * (p - y)
        rp = t @ P.T - c0
        return np.sum(r ** 2, (1, 2)) + np.sum(rp ** 2, 1), r, rp

    def solve_from(t):
        t = np.clip(t, lim[:, 0], lim[:, 1])
        c, r, rp = cost_and_terms(t)
        mu = np.full(len(t), 1e-3)
        for _ in range(iterations):
            J = 1000.0 * ww[..., None, None] * hand.jacobian(t, nodes, local)  # (F, M, 3, n)
            J = J.reshape(len(t), -1, n)
            H = J.transpose(0, 2, 1) @ J + P.T @ P
            g = (J.transpose(0, 2, 1) @ r.reshape(len(t), -1, 1))[..., 0] + rp @ P
            H = H + (mu[:, None] * (np.einsum("fii->fi", H) + 1e-9))[..., None] * np.eye(n)
            t_new = np.clip(t - np.linalg.solve(H, g[..., None])[..., 0], lim[:, 0], lim[:, 1])
            c_new, r_new, rp_new = cost_and_terms(t_new)
            better = c_new < c
            t = np.where(better[:, None], t_new, t)
            c = np.where(better, c_new, c)
            r = np.where(better[:, None, None], r_new, r)
            rp = np.where(better[:, None], rp_new, rp)
            mu = np.where(better, mu / 3, mu * 10)
        return t, c

    t0 = th[ok]
    starts = [t0]
    if coupled is not None and len(coupled[0]):
        pairs, ratio = coupled
        s = t0.copy()
        s[:, pairs[:, 1]] = ratio * s[:, pairs[:, 0]]
        starts.append(s)
    if mean is not None:
        s = t0.copy()
        s[:, ~hand.pose_mask] = mean
        starts.append(s)
    with threadpool_limits(limits=1, user_api="blas"):  # 26×26 systems per frame: threads only contend
        best, cb = solve_from(starts[0])
        for s in starts[1:]:
            t, cs = solve_from(s)
            # ties go to the earlier start (the IK's own solution, then the DIP-coupled one)
            best = np.where((cs < cb)[:, None], t, best)
            cb = np.minimum(cs, cb)
    th[ok] = best
    return th


def posterior_sd(hand, nodes, local, theta, weights, present, *, noise_mm, rows=None):
    """Posterior SD (radians) of every coordinate per frame from the IK's normal equations at
    ``theta``: ``diag((JᵀJ/σ² + PᵀP)⁻¹)^½`` with markers of SD ``noise_mm`` per coordinate
    (``present``: ``(F, M)`` which markers a frame has) and the prior rows ``(P, c)`` if given.
    A direction the markers leave free has an infinite SD (reported as ``inf``).

    >>> from handmodel import HandModel
    >>> h = HandModel.load()
    >>> n, l = np.arange(h.n_nodes), np.tile([0.0, 0.0, 0.01], (h.n_nodes, 1))
    >>> th = np.zeros((1, 26)); th[0, 2] = 0.5
    >>> sd = posterior_sd(h, n, l, th, None, np.ones((1, h.n_nodes), bool), noise_mm=0.5)
    >>> bool(np.degrees(sd[0, 6:]).max() < 5)
    True
    """
    th = np.asarray(theta, float)
    out = np.full(th.shape, np.nan)
    ok = np.isfinite(th).all(1)
    if not ok.any():
        return out
    w = np.ones(len(nodes)) if weights is None else np.asarray(weights, float)
    ww = (w[None, :] * np.asarray(present, bool)[ok]) / float(noise_mm)
    J = (1000.0 * ww[..., None, None] * hand.jacobian(th[ok], nodes, local)).reshape(int(ok.sum()), -1, th.shape[1])
    H = J.transpose(0, 2, 1) @ J
    if rows is not None and len(rows[0]):
        H = H + rows[0].T @ rows[0]
    # the symmetric eigen-decomposition: a null direction (a joint no marker moves) is an infinite
    # variance, not the ridge's arbitrary one. One BLAS thread: on a stack of 26×26 matrices OpenBLAS's
    # threads cost 33× (969 frames: 4.2 s vs 0.13 s here)
    with threadpool_limits(limits=1, user_api="blas"):
        s, U = np.linalg.eigh(H)
    tiny = s <= 1e-10 * np.maximum(s[:, -1:], 1e-30)
    inv = np.where(tiny, 0.0, 1.0 / np.where(tiny, 1.0, s))
    var = np.einsum("fij,fj->fi", U ** 2, inv)
    var = np.where(np.einsum("fij,fj->fi", U ** 2, tiny.astype(float)) > 1e-6, np.inf, var)
    out[ok] = np.sqrt(var)
    return out


def prior_driven(sd_with, sd_without, names, share=PRIOR_DRIVEN_SHARE):
    """The posture joints whose markers give less than ``share`` of their information (median over
    frames of ``sd_with² / sd_without²``, both SDs per frame): name → ``[sd_with°, sd_without°]``."""
    ok = np.isfinite(sd_with).all(1)
    out = {}
    if not ok.any():
        return out
    with np.errstate(divide="ignore", invalid="ignore"):
        data_share = np.nanmedian((sd_with[ok] / sd_without[ok]) ** 2, axis=0)
    for j, name in enumerate(names):
        if j < 6 or not data_share[j] < share:
            continue
        out[name] = [_r(np.degrees(np.median(sd_with[ok, j])), 2), _r(np.degrees(np.median(sd_without[ok, j])), 1)]
    return out


def default_prior(hand, nodes, local, theta, weights, present, *, noise_mm, rows=None, frames=200):
    """The ``'auto'`` choice of :func:`markers_to_angles`: :data:`DEFAULT_PRIOR` when, at the IK's
    solution ``theta`` (a sample of ``frames`` solved frames), it would decide some posture joint
    (:func:`prior_driven`: the markers give less than half its information), else None (a set that
    observes every joint keeps its markers' angles, bit for bit)."""
    ok = np.flatnonzero(np.isfinite(theta).all(1))
    if not ok.size:
        return None
    at = ok[np.linspace(0, ok.size - 1, min(frames, ok.size)).round().astype(int)]
    cand = resolve_prior(DEFAULT_PRIOR)
    with_prior = prior_rows(hand, cand)
    if rows is not None and len(rows[0]):
        with_prior = np.vstack([with_prior[0], rows[0]]), np.concatenate([with_prior[1], rows[1]])
    sd_w = posterior_sd(hand, nodes, local, theta[at], weights, present[at], noise_mm=noise_mm, rows=with_prior)
    sd_0 = posterior_sd(hand, nodes, local, theta[at], weights, present[at], noise_mm=noise_mm, rows=rows)
    return cand if prior_driven(sd_w, sd_0, hand.dof_names) else None


def refine_trajectory(hand, nodes, local, targets, theta, weights, *, noise_mm, rate, accel_sd_deg_s2=None,
                      ip_sd_deg=IP_COUPLING_SD_DEG, ratio=IP_COUPLING, iterations=6, skip=(), posture_rows=None):
    """Marker IK of a whole trajectory at once, with a weak prior on each finger joint's angular
    acceleration (SD ``accel_sd_deg_s2``) beside the DIP prior of :func:`refine_with_coupling`.

    Where the markers fix a joint (a posture SD of ~1°), the prior changes only what lies above
    ~9 Hz; where they leave a flat valley (hand16's PIP/DIP trade in a fist: SDs of ~10°), a frame's
    noise moved the joint along the valley by several degrees from one frame to the next, and the
    prior lets the neighbouring frames decide (a low-pass at ~3 Hz along such directions only).
    Starts from ``theta`` (``(F, n)``, NaN rows for frames not solved; consecutive solved frames are
    tied); Levenberg-Marquardt on the sparse banded system; limits are the model's; fingers in
    ``skip`` get no DIP prior. ``posture_rows = (P, c)`` (:func:`prior_rows`) replaces the DIP prior by these
    posture priors. Returns ``theta`` refined.

    >>> from handmodel import HandModel
    >>> h = HandModel.load()
    >>> th = np.zeros((5, 26)); th[:, 2] = 0.5; th[:, 9] = np.linspace(-0.5, -0.3, 5)
    >>> n, l = np.arange(h.n_nodes), np.zeros((h.n_nodes, 3))
    >>> out = refine_trajectory(h, n, l, h.points(th, n, l), th, None, noise_mm=0.5, rate=100.0,
    ...                         accel_sd_deg_s2=3000.0)
    >>> bool(np.abs(out - th).max() < 1e-6)
    True
    """
    th = np.array(theta, float)
    ok = np.isfinite(th).all(1)
    if ok.sum() < 3 or not accel_sd_deg_s2 or not rate:
        return th
    at = np.flatnonzero(ok)
    F, n = len(at), hand.n_dofs
    post = np.flatnonzero(~hand.pose_mask)
    # acceleration rows for each run of three consecutive solved frames, posture DoFs only (the
    # pose is well observed by the palm markers, and its units differ)
    k = np.flatnonzero((at[1:-1] == at[:-2] + 1) & (at[2:] == at[:-2] + 2))
    a_sd = np.radians(accel_sd_deg_s2) / float(rate) ** 2  # radians per frame²
    rows = np.arange(len(k) * len(post))
    cols0 = (k[:, None] * n + post[None, :]).ravel()
    D = sparse.csr_matrix((np.r_[np.ones_like(cols0), -2 * np.ones_like(cols0), np.ones_like(cols0)] / a_sd,
                           (np.r_[rows, rows, rows], np.r_[cols0, cols0 + n, cols0 + 2 * n])),
                          shape=(len(rows), F * n))
    DtD = (D.T @ D).tocsr()
    if posture_rows is None:
        pairs = ip_coupling_pairs(hand, skip) if ip_sd_deg else np.zeros((0, 2), np.int64)
        posture_rows = dip_prior_rows(pairs, n, ratio, ip_sd_deg), np.zeros(len(pairs))
    P, c0 = (np.asarray(x, float) for x in posture_rows)
    lim = np.asarray(hand.limits, float)
    y, ww = _weighted_targets(targets, at, nodes, weights, noise_mm)

    def cost_of(t):
        r = ww[..., None] * (1000.0 * hand.points(t, nodes, local) - y)
        rp = t @ P.T - c0
        dt = D @ t.ravel()
        return float(np.sum(r ** 2) + np.sum(rp ** 2) + dt @ dt), r, rp

    t = np.clip(th[at], lim[:, 0], lim[:, 1])
    with threadpool_limits(limits=1, user_api="blas"):  # 26×26 blocks: threads only contend
        c, r, rp = cost_of(t)
        mu = 1e-3
        for _ in range(iterations):
            J = (1000.0 * ww[..., None, None] * hand.jacobian(t, nodes, local)).reshape(F, -1, n)
            JT = np.ascontiguousarray(J.transpose(0, 2, 1))
            Hb = JT @ J + P.T @ P
            g = ((JT @ r.reshape(F, -1, 1))[..., 0] + rp @ P).ravel() + DtD @ t.ravel()
            H = sparse.bsr_matrix((Hb, np.arange(F), np.arange(F + 1)), shape=(F * n, F * n)).tocsr() + DtD
            while True:
                Hd = H + sparse.diags(mu * (H.diagonal() + 1e-9))
                step = spsolve(Hd.tocsc(), -g, permc_spec="NATURAL").reshape(F, n)
                t_new = np.clip(t + step, lim[:, 0], lim[:, 1])
                c_new, r_new, rp_new = cost_of(t_new)
                if c_new < c:
                    done = c - c_new < 1e-6 * c
                    t, c, r, rp, mu = t_new, c_new, r_new, rp_new, max(mu / 3, 1e-7)
                    break
                mu *= 10
                if mu > 1e4:
                    done = True
                    break
            if done:
                break
    th[at] = t
    return th


def _r(x, nd=3):
    """``x`` rounded for a report, None when not finite."""
    x = float(x)
    return round(x, nd) if np.isfinite(x) else None
