"""Marker IK over trials: marker data → joint-angle tables (DESIGN.md "joint-angle table").

The shared solver fits the calibrated hand model to each frame's markers (fixed correspondences),
warm-started from the previous frame; missing markers drop out per frame; frames left with a large
residual are re-solved from a rigid placement. Limits are anatomical (generous), not the original
tracker's narrow ones, which real data exceeds.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import sparse
from scipy.sparse.linalg import spsolve
from threadpoolctl import threadpool_limits

from handmodel import HandModel
from handmodel.dofs import anatomical_limits
from handmodel.fileio import atomic_write_text
from handmodel.solver import SolverSettings, fit_points
from handmodel.subspace import Subspace

from .c3d import read_c3d
from .calibrate import Calibration, calibrate, golden_section, sample_frames
from .errors import SynergyError
from .markers import MarkerSet, load_markerset
from .prior import PosturePrior, resolve_prior
from .smoothing import lowpass_markers

#: A joint on a limit in more than this share of frames is reported.
LIMIT_SHARE_WARN = 0.05
#: Frames whose residual exceeds this multiple of the trial's noise floor are ``poor`` …
POOR_FACTOR = 3.0
#: … and also exceed the floor by this much (mm): sub-millimetre floors would flag good frames.
POOR_MARGIN_MM = 2.0
#: Automatic calibration keeps the bone and marker fit when its held-out residual is below this
#: share of the scale-only one.
AUTO_GAIN = 0.8
#: A trial with more poor frames than this share is a poor trial.
POOR_TRIAL_SHARE = 0.10
#: The other hand "fits clearly better" when its residual is below this share of the chosen one's.
HAND_CLEARLY_BETTER = 0.5
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
#: The posture prior (``'auto'``: :data:`DEFAULT_PRIOR`) weighs in a conversion's automatic calibration
#: without a static trial or neutral frames as this many postures in all.
CALIBRATION_PRIOR_FRAMES = 1.0
#: The posture prior ``prior='auto'`` uses where the markers leave a joint weakly observed.
DEFAULT_PRIOR = "fingerfist"
#: SD (degrees/s²) of the weak prior on each finger joint's angular acceleration that ties a
#: trajectory's frames together when the markers are low-passed (:func:`refine_trajectory`). A power
#: grasp closes at ~900°/s²; a joint the markers fix keeps a 30° swing at 4 Hz (~19000°/s²) within ~2°.
ACCEL_SD_DEG_S2 = 3000.0


def _targets(data, ms, where):
    idx, extra = ms.match(list(data.labels), where=where)
    pts = np.asarray(data.points, float)
    return np.where((idx >= 0)[None, :, None], pts[:, np.maximum(idx, 0)], np.nan), extra


def check_handedness(data, markerset, hand, *, model="default", frames=60, where=None):
    """Fit both hands (hand scale only) on a sample of frames; which one explains the markers?

    Returns a dict: ``chosen``, ``residual_mm`` (median, chosen hand), ``other_residual_mm``,
    ``limit_share`` / ``other_limit_share`` (share of joint values on a limit), ``verdict``
    ('ok', 'other hand fits better', 'wrong hand').
    """

    ms = markerset.for_hand(hand)
    tg, _ = _targets(data, ms, where)
    tg = tg[sample_frames(tg, frames)]
    weights = np.array([m.weight for m in ms.markers])
    out = {"chosen": hand}
    for key, h in (("", hand), ("other_", "left" if hand == "right" else "right")):
        right = h == "right"
        base = HandModel.load(model, right=right)

        def fit(scale, base=base, right=right):
            hm = base.scaled(scale)
            hm = hm.with_limits(anatomical_limits(hm))
            n, l = ms.attachments(hm, right, scale=scale)
            return _solve(hm, n, l, tg, weights)

        scale = golden_section(lambda s: float(np.nanmedian(fit(s)[1].rms_mm)), 0.6, 1.6, iterations=10)
        _, rep = fit(scale)
        out[f"{key}residual_mm"] = float(np.nanmedian(rep.rms_mm))
        out[f"{key}limit_share"] = float(rep.at_limit[:, 6:].mean())
    ratio = out["other_residual_mm"] / max(out["residual_mm"], 1e-9)
    out["verdict"] = ("wrong hand" if ratio < HAND_CLEARLY_BETTER and out["residual_mm"] - out["other_residual_mm"] > 1.0
                      else "other hand fits better" if ratio < 0.8 and out["residual_mm"] - out["other_residual_mm"] > 0.5
                      else "ok")
    return out


def _solve(hm, nodes, local, tg, weights):

    return fit_points(hm, nodes, local, tg, weights=weights, settings=SolverSettings(iterations=15, damping=0.1),
                      restarts=1)


def diagnose(df, residuals, labels, rep, *, rate, poor_residual_mm=None, prior_driven=None):
    """Per-trial diagnostics of a conversion (fills ``df['quality']``; returns a dict for ``df.attrs``).

    ``residuals`` is ``(F, M)`` per-marker distances (mm, NaN where missing); ``rep`` the solver report;
    ``prior_driven`` the joints the markers leave weakly observed (:func:`prior_driven`): named as
    such, and a limit they sit on is the prior's or the IK's guess, not a reason to refuse the trial.
    """
    prior_driven = dict(prior_driven or {})
    solved = rep.iterations >= 0
    rms = rep.rms_mm
    floor = float(np.nanmedian(rms[solved])) if solved.any() else float("nan")
    thr = (float(poor_residual_mm) if poor_residual_mm is not None
           else max(POOR_FACTOR * floor, floor + POOR_MARGIN_MM))
    q = np.where(~solved, "gap", np.where(rms > thr, "poor", "ok"))
    df["quality"] = q
    with np.errstate(all="ignore"):
        per_marker = {lab: [_r(np.nanmedian(residuals[:, i])), _r(np.nanpercentile(residuals[:, i], 95))]
                      for i, lab in enumerate(labels) if np.isfinite(residuals[:, i]).any()}
    dofs = list(df.columns[2:2 + rep.at_limit.shape[1]])
    share = rep.at_limit[solved].mean(0) if solved.any() else np.zeros(len(dofs))
    limits = {d: round(float(v), 4) for d, v in zip(dofs, share) if v > 0 and d not in dofs[:6]}
    warnings = []
    pinned = {d: v for d, v in limits.items() if v > LIMIT_SHARE_WARN and d not in prior_driven}
    if pinned:
        warnings.append("on a joint limit in more than 5 % of frames: "
                        + ", ".join(f"{d} {100 * v:.0f} %" for d, v in sorted(pinned.items(), key=lambda x: -x[1])))
    th = df[dofs[6:]].to_numpy()
    jumps = 0
    if len(th) > 1 and rate >= 50:
        d = np.abs(np.diff(th, axis=0))
        jumps = int(np.nansum(d > np.radians(30)))
        if jumps:
            warnings.append(f"{jumps} jump(s) of more than 30° between consecutive frames (a joint flipping "
                            "between two solutions: marker places or calibration?)")
    poor_share = float((q == "poor").mean())
    if poor_share > POOR_TRIAL_SHARE:
        warnings.append(f"{100 * poor_share:.0f} % of frames poor (residual > {thr:.1f} mm)")
    if per_marker:
        worst = max(per_marker.items(), key=lambda x: x[1][0])
        med = np.median([v[0] for v in per_marker.values()])
        if worst[1][0] > 3 * med + 1.0:
            warnings.append(f"marker {worst[0]} fits worst (median {worst[1][0]:.1f} mm vs {med:.1f} mm): "
                            "misplaced, mislabelled or on a loose spot?")
    return {"noise_floor_mm": _r(floor), "poor_threshold_mm": _r(thr), "poor_share": round(poor_share, 4),
            "marker_residuals_mm": per_marker, "limit_share": limits, "jumps": jumps, "warnings": warnings,
            "prior_driven": prior_driven}


def _r(x, nd=3):
    x = float(x)
    return round(x, nd) if np.isfinite(x) else None


def verdict(diag) -> str:
    """'poor' (do not use without a look), 'check' (warnings) or 'good'."""
    h = diag.get("handedness", {})
    if (diag.get("poor_share", 0) > POOR_TRIAL_SHARE or h.get("verdict") == "wrong hand"
            or any(v > 0.25 for k, v in diag.get("limit_share", {}).items() if k not in diag.get("prior_driven", {}))
            or diag.get("calibration_overfit")):
        return "poor"
    return "check" if diag.get("warnings") else "good"


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
    # variance, not the ridge's arbitrary one
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


def markers_to_angles(data, markerset, *, hand: str = "left", model=None, calibration="trial",
                      settings=None, poor_residual_mm: float | None = None, min_markers: int = 4, smooth_hz=None,
                      check_hand="stop", static=None, ip_coupling_sd_deg=IP_COUPLING_SD_DEG,
                      accel_sd_deg_s2=ACCEL_SD_DEG_S2, prior="auto"):
    """Joint angles of every frame of a trial.

    Parameters
    ----------
    data : marker data (from :func:`synergy.c3d.read_c3d`) or a path to a C3D file
    markerset : :class:`~synergy.markers.MarkerSet` or its name/path
    hand : 'left' or 'right'
    model : hand model name/path or a :class:`~handmodel.HandModel`; default: the marker set's
        ``hand_model``
    calibration : 'trial' (estimate from this trial), None (the model as it is), a
        :class:`~synergy.calibrate.Calibration` (e.g. from ``synergy calibrate``), or marker data
        of a static trial
    poor_residual_mm : frames whose RMS marker residual exceeds this are ``poor``; default relative
        to the trial's own noise floor (its median residual): above 3× the floor and 2 mm above it
    min_markers : frames with fewer markers are not solved (NaN, flagged ``gap``)
    smooth_hz : optional zero-phase low-pass cut-off (Hz) for the marker trajectories before IK
    check_hand : 'stop' (raise when the other hand fits clearly better), 'warn', or None
    static : a static trial in the flat-hand posture calibrated together with this one (``'trial'``)
    ip_coupling_sd_deg : SD (degrees) of the weak prior that each finger's DIP flexes ~2/3 as much as
        its PIP (see :data:`IP_COUPLING_SD_DEG`); decides only where the markers leave the DIP
        undetermined; None or 0 turns it off
    accel_sd_deg_s2 : SD (degrees/s²) of the weak prior on the finger joints' angular acceleration
        (:func:`refine_trajectory`, :data:`ACCEL_SD_DEG_S2`), applied with ``smooth_hz`` (a smooth
        trajectory asked for); None or 0, or no ``smooth_hz``, solves every frame on its own
    prior : the Gaussian posture prior (:class:`~synergy.prior.PosturePrior`, a bundle name such as
        ``'fingerfist'`` or a path), None for none, or ``'auto'``: :data:`DEFAULT_PRIOR` where the
        markers leave a posture joint weakly observed (:func:`default_prior`), else none. Its rows
        stand beside the markers divided by the trial's own noise, so well-observed joints follow
        the markers and weakly observed ones the prior. With ``calibration='trial'`` and no static
        trial or neutral frames, the prior (``'auto'``: :data:`DEFAULT_PRIOR`) also holds the
        calibration frames' postures (:data:`CALIBRATION_PRIOR_FRAMES`)

    Returns
    -------
    pandas.DataFrame
        ``frame, time_s``, the 26 DoF columns (radians, metres), ``residual_mm``, ``markers``,
        ``quality`` (ok / poor / gap), and ``<dof>_sd`` for each posture DoF (radians: the posterior
        SD from the IK's normal equations, with the priors used); ``df.attrs`` holds the metadata (rate, source, units,
        marker set, hand, calibration, extra markers) and ``diagnostics`` (noise floor, per-marker
        residuals, share of frames on each limit, handedness check, warnings, ``verdict``).
    """



    if isinstance(data, (str, Path)):

        data = read_c3d(data)
    ms0 = markerset if isinstance(markerset, MarkerSet) else load_markerset(markerset)
    ms = ms0.for_hand(hand)
    right = hand == "right"
    model = ms.hand_model if model is None else model
    base = model if isinstance(model, HandModel) else HandModel.load(model, right=right)
    ms.check_model(base)
    where = getattr(data, "path", None)
    targets, extra = _targets(data, ms, where)
    warnings = []
    hand_check = {}
    if check_hand:
        hand_check = check_handedness(data, ms0, hand, model=base.path if not isinstance(model, str) else model,
                                      where=where)
        if hand_check["verdict"] != "ok":
            msg = (f"the {'left' if right else 'right'} hand fits these markers better "
                   f"({hand_check['other_residual_mm']:.1f} mm vs {hand_check['residual_mm']:.1f} mm as {hand})")
            if hand_check["verdict"] == "wrong hand" and check_hand == "stop":
                raise SynergyError(where or "trial", msg + "; use --hand, or --no-hand-check to convert anyway")
            warnings.append(msg)
    if isinstance(calibration, str) and calibration == "trial":
        # automatic: the bone and marker fit is kept only where it clearly beats the hand scale on
        # held-out frames (a trial without a range of motion or a static posture leaves some of
        # it to the priors, and then the simpler hand is the safer one). It sees the markers as this
        # conversion does (smoothed only if asked): a short trial low-passed holds few independent
        # samples, and its calibration then fails the held-out check (a 0.5 s grasp at 6 Hz)
        # without a static trial, the trial's own open-hand frames (if any) stand in for one; a trial
        # without those (a fretting hand) has the posture prior hold its calibration frames' postures,
        # weighed as one posture (fretting: 6.8-16.0° -> 5.6-7.1°, docs/experiments/marker-prior.md)
        named = resolve_prior(DEFAULT_PRIOR if isinstance(prior, str) and prior == "auto" else prior)
        cal = calibrate(data, ms, base, right=right, static=static, require_gain=AUTO_GAIN, smooth_hz=smooth_hz,
                        neutral=static is None, posture_prior=named, prior_frames=CALIBRATION_PRIOR_FRAMES)
    elif calibration is None:
        cal = Calibration(method="none")
    elif isinstance(calibration, Calibration):
        cal = calibration
        if cal.hand and cal.hand != hand:
            raise SynergyError(cal.source or "calibration", f"calibrated for the {cal.hand} hand, not the {hand}")
        if cal.markerset and cal.markerset != ms.name:
            warnings.append(f"calibration made with marker set {cal.markerset!r}, used with {ms.name!r}")
        unknown = sorted(set(cal.offsets) - {m.label for m in ms.markers})
        if unknown:
            raise SynergyError(cal.source or "calibration", f"calibration places markers the set {ms.name!r} "
                                                            f"does not have: {', '.join(unknown)}")
    else:
        cal = calibrate(calibration, ms, base, right=right, subject=False)
        cal.source = str(getattr(calibration, "path", "static trial"))
    warnings += [f"calibration: {w}" for w in cal.warnings]
    hm = cal.model(base)
    lim = anatomical_limits(hm)
    hm = hm.with_limits(lim)
    nodes, local = ms.attachments(hm, right, cal.offsets or None, scale=cal.scale)
    rate = float(getattr(data, "rate", 1.0) or 1.0)
    if smooth_hz:
        targets = lowpass_markers(targets, rate, smooth_hz)
    weights = np.array([m.weight for m in ms.markers])
    n_present = (~np.isnan(targets[..., 0])).sum(1)
    settings = settings or SolverSettings(iterations=15, damping=0.1, min_points=min_markers)
    settings.min_points = max(settings.min_points, min_markers)
    theta, rep = fit_points(hm, nodes, local, targets, weights=weights, warm_start=True, settings=settings,
                            subspace=Subspace.full(hm, lim), restarts=2, restart_rms_mm=max(3 * np.nanmedian(
                                np.r_[cal.median_residual_mm, 1.0]), 2.0))
    # tying frames together trades residual for steadiness: on raw real recordings it costs residual
    # the frames' own fits do not (DFKI glove median 0.61 → 0.77 mm, 95th 1.53 → 2.39 mm; ART
    # 1.60 → 1.70 mm), so it comes with the low-pass, when a smooth trajectory is what was asked for
    accel_sd_deg_s2 = accel_sd_deg_s2 if smooth_hz else None
    solved0 = rep.iterations >= 0
    present = np.isfinite(targets[..., 0])
    # per-coordinate noise of the markers as fitted (smoothed, if asked), from the trial's own
    # median residual (a frame's 3-D RMS) with the DoFs' share of it restored (3M coordinates,
    # n DoF). A larger value (e.g. the calibration's raw-frame residual) lets the prior bend
    # well-observed DIPs: ROM trials of simulated subjects 1.7 → 5.3° RMS
    res = float(np.nanmedian(rep.rms_mm[solved0])) if solved0.any() else 1.0
    m3 = 3 * float(np.median(n_present[solved0])) if solved0.any() else 3.0 * len(nodes)
    noise = max(res * np.sqrt(m3 / max(m3 - hm.n_dofs, 1.0) / 3.0), 0.01)
    skip = dip_fixed_fingers(ms)
    th_ik = np.where(solved0[:, None], theta, np.nan)
    dip_rows = prior_rows(hm, None, dip_sd_deg=ip_coupling_sd_deg, skip=skip)
    if isinstance(prior, str) and prior == "auto":
        prior = default_prior(hm, nodes, local, th_ik, weights, present, noise_mm=noise, rows=dip_rows)
    prior = resolve_prior(prior)
    rows = prior_rows(hm, prior, dip_sd_deg=ip_coupling_sd_deg, skip=skip)
    if len(rows[0]) or accel_sd_deg_s2:
        th_out = th_ik
        if len(rows[0]):
            pairs = ip_coupling_pairs(hm, skip) if ip_coupling_sd_deg else np.zeros((0, 2), np.int64)
            th_out = refine_with_prior(hm, nodes, local, targets, th_out, weights, noise_mm=noise, rows=rows,
                                       coupled=(pairs, IP_COUPLING), mean=None if prior is None else prior.mean)
        if accel_sd_deg_s2:
            th_out = refine_trajectory(hm, nodes, local, targets, th_out, weights, noise_mm=noise, rate=rate,
                                       accel_sd_deg_s2=accel_sd_deg_s2, posture_rows=rows)
        theta = np.where(solved0[:, None], th_out, theta)
        if solved0.any():
            # the report as the solver would give it for the refined postures (weighted RMS, limits)
            e = np.linalg.norm(hm.points(theta[solved0], nodes, local) - targets[solved0], axis=-1) * 1000.0
            w2 = np.where(np.isnan(e), 0.0, weights[None, :] ** 2)
            rep.rms_mm[solved0] = np.sqrt(np.nansum(w2 * e ** 2, axis=1) / w2.sum(1))
            tol = 2 * settings.clamp_margin + 1e-9
            rep.at_limit[solved0] = ((np.abs(theta[solved0] - lim[:, 0]) <= tol)
                                     | (np.abs(theta[solved0] - lim[:, 1]) <= tol))
    th_sd = np.where(solved0[:, None], theta, np.nan)
    sd_with = posterior_sd(hm, nodes, local, th_sd, weights, present, noise_mm=noise, rows=rows)
    sd_without = posterior_sd(hm, nodes, local, th_sd, weights, present, noise_mm=noise)
    F = len(targets)
    first = int(getattr(data, "first_frame", 0) or 0)
    df = pd.DataFrame(theta, columns=hm.dof_names)
    df.insert(0, "time_s", (np.arange(F)) / rate)
    df.insert(0, "frame", np.arange(F) + first)
    df["residual_mm"] = rep.rms_mm
    df["markers"] = n_present
    post = np.flatnonzero(~hm.pose_mask)
    for j in post:
        df[f"{hm.dof_names[j]}_sd"] = sd_with[:, j]
    solved = rep.iterations >= 0
    res = np.full(targets.shape[:2], np.nan)
    if solved.any():
        res[solved] = 1000.0 * np.linalg.norm(hm.points(theta[solved], nodes, local) - targets[solved], axis=-1)
    driven = prior_driven(sd_with, sd_without, hm.dof_names)
    diag = diagnose(df, res, [m.label for m in ms.markers], rep, rate=rate, poor_residual_mm=poor_residual_mm,
                    prior_driven=driven)
    with np.errstate(all="ignore"):
        diag["posterior_sd_deg"] = {hm.dof_names[j]: [_r(np.degrees(np.nanmedian(sd_with[solved, j])), 2),
                                                      _r(np.degrees(np.nanmedian(sd_without[solved, j])), 2)]
                                    for j in post} if solved.any() else {}
    diag["warnings"] = warnings + diag["warnings"]
    if hand_check:
        diag["handedness"] = {k: (_r(v) if isinstance(v, float) else v) for k, v in hand_check.items()}
    diag["calibration_overfit"] = bool(cal.held_out.get("overfit", False))
    diag["verdict"] = verdict(diag)
    df.attrs.update({
        "source": str(where) if where else "", "rate_hz": rate, "units": {"angles": "rad", "translation": "m"},
        "markerset": ms.name, "hand": hand, "hand_model": base.name, "calibration": cal.to_dict(),
        "extra_markers": extra, "frames": F, "smooth_hz": smooth_hz,
        "dip_prior": {"ratio": IP_COUPLING, "sd_deg": ip_coupling_sd_deg} if ip_coupling_sd_deg else None,
        "posture_prior": None if prior is None else prior.to_dict(), "marker_noise_mm": _r(noise),
        "accel_prior_sd_deg_s2": float(accel_sd_deg_s2) if accel_sd_deg_s2 else None,
        "gap_fraction": float(np.isnan(targets[..., 0]).mean()), "diagnostics": diag,
    })
    return df


def write_angles_csv(df, path, *, overwrite=False):
    """CSV with ``# key: value`` metadata lines (JSON values) before the header; atomic."""

    head = "".join(f"# {k}: {json.dumps(v, default=str)}\n" for k, v in df.attrs.items())
    body = df.to_csv(index=False, float_format="%.9g")
    return atomic_write_text(path, head + body, overwrite=overwrite)


def read_angles_csv(path):
    """Read a joint-angle CSV written by :func:`write_angles_csv` (metadata back into ``df.attrs``)."""

    meta = {}
    with open(path) as fh:
        for line in fh:
            if not line.startswith("#"):
                break
            k, _, v = line[1:].partition(":")
            try:
                meta[k.strip()] = json.loads(v)
            except json.JSONDecodeError:
                meta[k.strip()] = v.strip()
    df = pd.read_csv(path, comment="#")
    df.attrs.update(meta)
    return df
