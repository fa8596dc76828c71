"""The skin-marker subject fit behind :func:`synergy.calibrate.calibrate`: every observable bone
length, each finger base's place on the palm and each marker's place on its bone, estimated together
with the calibration frames' postures (Gauss-Newton, the postures eliminated by a Schur complement),
with priors from the marker set (``offset_sd``) and on bone lengths (``bone_sd``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from threadpoolctl import threadpool_limits

from handmodel.dofs import anatomical_limits
from handmodel.solver import SolverSettings, fit_points

from .errors import SynergyError

#: Default prior SD (mm) of a marker's place on its bone, by how the marker set places it.
OFFSET_SD_MM = {"skin": 5.0, "calibrate_offset": 15.0, "joint_centre": 2.0}

#: Every residual of the held-out check is the *median marker residual*: the median over frames of a
#: frame's RMS marker distance (mm, weighted by the markers' weights), the figure of the conversion's
#: table (its "med mm") on the same frames.
#:
#: A calibration whose held-out residual exceeds its training residual by this factor (+0.02 mm) does
#: not generalise as it trains …
OVERFIT_RATIO = 1.25
#: … which makes it overfit only where its held-out residual is not clearly below the scale-only hand's
#: on the same frames (below this share of it): the fit's extra freedom then bought nothing the
#: simpler hand lacks. Far below it, the calibration is kept: the held-out frames hold postures the
#: fitted frames do not, which the scale-only hand misfits much more (issue 40's trial: 0.42 mm held
#: out vs 0.17 mm fitted, 3.3 mm for the scale-only hand, whose angles came out absurd; simulated
#: weakly observed trials, docs/experiments/marker-prior.md).
CLEARLY_BETTER = 0.5
#: A calibration worse than the scale-only hand on its held-out frames by more than this (mm) is
#: overfit whatever its training residual.
WORSE_THAN_SCALE_MM = 0.3


def overfits(held_mm, train_mm, scale_only_mm) -> bool:
    """The held-out check of a subject fit (median marker residuals, mm): overfit when its held-out
    residual is above the scale-only hand's on the same frames (by :data:`WORSE_THAN_SCALE_MM`), or
    above its training residual (by :data:`OVERFIT_RATIO`) without being clearly below the scale-only
    hand's (:data:`CLEARLY_BETTER`). A missing scale-only figure (NaN) is never clearly better.

    >>> overfits(0.42, 0.17, 3.3), overfits(0.42, 0.17, 0.5), overfits(0.30, 0.29, 0.31)
    (False, True, False)
    >>> overfits(0.70, 0.69, 0.30)
    True
    """
    if held_mm > scale_only_mm + WORSE_THAN_SCALE_MM:
        return True
    return bool(held_mm > OVERFIT_RATIO * train_mm + 0.02 and not held_mm < CLEARLY_BETTER * scale_only_mm)
#: Without a known posture (no static trial, no neutral frames), the prior SD (mm) of the place of a
#: skin marker on the last marked bone of a chain (a nail marker) at most: its place along the arc about
#: the chain's last joint is that joint's zero, which only the nominal place fixes, and a looser
#: prior lets the fit's other misfits turn it (weakly observed fretting, tuning seeds 100-107:
#: mean 5.86 -> 5.30°, worst 10.3 -> 6.7°; docs/experiments/marker-prior.md).
LAST_BONE_SD_MM = 1.5


def marker_offset_sd_mm(marker) -> float:
    """Prior SD (mm) of a marker's place on its bone: the marker set's ``offset_sd`` (metres) or a
    default by kind (a calibrated glove offset is loose, a joint centre tight, a skin marker 5 mm)."""
    if getattr(marker, "offset_sd", None) is not None:
        return 1000.0 * float(marker.offset_sd)
    if marker.calibrate_offset:
        return OFFSET_SD_MM["calibrate_offset"]
    if marker.landmark is not None and marker.landmark["type"] in ("joint_centre", "fingertip"):
        return OFFSET_SD_MM["joint_centre"]
    return OFFSET_SD_MM["skin"]


@dataclass
class _Layout:
    """Which numbers a skin-marker calibration estimates, and how each marker depends on them."""

    bases: list          # finger-base nodes (free 3-D place on the palm, mm)
    lengths: list        # nodes whose bone (parent → node) gets a length factor
    markers: list        # marker indices with a free place (3-D, mm)
    anc: np.ndarray      # (N, N): anc[n, k] = k is n or one of its ancestors
    seg_child: np.ndarray  # (M,) the child node whose bone a segment landmark's place follows, or −1
    along: np.ndarray    # (M,) fraction along that bone
    prior_sd: np.ndarray  # (n_s,)
    base_sd_mm: float
    last_bone_sd_mm: float | None = None

    @property
    def size(self):
        return 3 * len(self.bases) + len(self.lengths) + 3 * len(self.markers)


def last_bone_markers(parents, nodes):
    """Whether each marker rides on the last marked bone of its chain (no other marker below it).

    >>> last_bone_markers(np.array([-1, 0, 1, 2]), np.array([0, 1, 3, 3])).tolist()
    [False, False, True, True]
    """
    below = np.zeros(len(parents), bool)  # nodes with a marked node strictly below them
    for n in set(int(k) for k in nodes):
        k = int(parents[n])
        while k >= 0:
            below[k] = True
            k = int(parents[k])
    return ~below[np.asarray(nodes)]


def _layout(model, ms, nodes, *, bone_sd, offset_scale, base_sd_fraction=0.15, last_bone_sd_mm=None):
    N = model.n_nodes
    par = model.parents
    anc = np.zeros((N, N), bool)
    for n in range(N):
        k = n
        while k >= 0:
            anc[n, k] = True
            k = int(par[k])
    M = len(nodes)
    seg_child = np.full(M, -1, np.int64)
    along = np.zeros(M)
    for i, m in enumerate(ms.markers):
        if m.landmark is not None and m.landmark["type"] == "segment":
            kids = [k for k in range(N) if par[k] == nodes[i]]
            if len(kids) == 1:
                seg_child[i], along[i] = kids[0], m.landmark.get("along", 0.5)
    carried = anc[nodes].any(0)  # nodes some marker rides on or below
    bases = [k for k in range(N) if par[k] == 0 and carried[k]]
    lengths = [k for k in range(N) if par[k] > 0 and (carried[k] or k in seg_child)]
    sd_m = np.array([marker_offset_sd_mm(m) * offset_scale for m in ms.markers])
    if last_bone_sd_mm is not None:
        # a marker the set says to calibrate (a glove's) has no nominal place worth holding it to
        held = last_bone_markers(par, nodes) & ~np.array([bool(m.calibrate_offset) for m in ms.markers])
        sd_m = np.where(held & (sd_m > 0), np.minimum(sd_m, last_bone_sd_mm), sd_m)
    free = [i for i in range(M) if sd_m[i] > 0]
    bsd = [max(base_sd_fraction * 1000.0 * np.linalg.norm(model.rest[k, :3, 3]), 5.0) for k in bases]
    prior = np.r_[np.repeat(bsd, 3), np.full(len(lengths), bone_sd), np.repeat(sd_m[free], 3)]
    return _Layout(bases, lengths, free, anc, seg_child, along, prior, float(np.mean(bsd)) if bsd else 0.0,
                   last_bone_sd_mm)


def _apply(model0, ms, right, scale, lay, s):
    """Model and marker places (node frames, metres) for the subject vector ``s``."""
    nb, nl = 3 * len(lay.bases), len(lay.lengths)
    factors = {model0.node_names[k]: float(f) for k, f in zip(lay.lengths, 1.0 + s[nb:nb + nl])}
    model = model0.scaled(1.0, factors)
    pos = {model0.node_names[k]: model0.rest[k, :3, 3] + s[3 * j:3 * j + 3] / 1000.0 for j, k in enumerate(lay.bases)}
    if pos:
        model = model.with_joint_positions(pos)
    nodes, local = ms.attachments(model, right, scale=scale)
    local = local.copy()
    for j, i in enumerate(lay.markers):
        local[i] += s[nb + nl + 3 * j:nb + nl + 3 * j + 3] / 1000.0
    return model, nodes, local, factors, pos


def _jacobians(model0, model, nodes, local, theta, lay):
    """Marker positions (mm) and their Jacobians w.r.t. θ and the subject vector (mm per unit)."""
    G = model.node_frames(theta)                       # (F, N, 4, 4)
    Gm = G[:, nodes]                                   # (F, M, 4, 4)
    p = np.einsum("fmij,mj->fmi", Gm[..., :3, :3], local) + Gm[..., :3, 3]
    Jt = 1000.0 * model.jacobian(theta, nodes, local)  # (F, M, 3, n)
    F, M = p.shape[:2]
    Js = np.zeros((F, M, 3, lay.size))
    col = 0
    for k in lay.bases:
        on = lay.anc[nodes, k]
        Js[:, on, :, col:col + 3] = G[:, None, 0, :3, :3]
        col += 3
    for k in lay.lengths:
        t0 = 1000.0 * model0.rest[k, :3, 3]
        on = lay.anc[nodes, k]
        Jc = Js[..., col]  # a view: boolean indexing next to a scalar index would reorder the axes
        Jc[:, on] = (G[:, int(model.parents[k]), :3, :3] @ t0)[:, None, :]
        seg = lay.seg_child == k
        if seg.any():
            Jc[:, seg] += np.einsum("fmij,j->fmi", Gm[:, seg, :3, :3], t0) * lay.along[seg][None, :, None]
        col += 1
    for i in lay.markers:
        Js[:, i, :, col:col + 3] = Gm[:, i, :3, :3]
        col += 3
    return 1000.0 * p, Jt, Js


def _gauss_newton(*args, **kw):
    """:func:`_gauss_newton_run` on one BLAS thread: its products are a few hundred rows wide, where
    threads only contend (hand16 calibration on 2 busy cores: 2 s on one thread, 27 s on all)."""
    with threadpool_limits(limits=1, user_api="blas"):
        return _gauss_newton_run(*args, **kw)


def _gauss_newton_run(model0, ms, right, scale, lay, theta, tg_mm, w, lim, *, data_sd_mm, iterations, huber_mm,
                      theta_ref=None, theta_w=None, s0=None):
    """Joint Levenberg-Marquardt over the postures of the calibration frames and the subject vector;
    the postures are eliminated per frame (Schur complement), so a step costs F small solves.
    ``theta_ref``/``theta_w`` (F, n): a known posture and its weight (1/SD, 0 = unknown) per frame,
    e.g. the neutral posture of a static trial."""
    n_s = lay.size
    if theta_w is None:
        theta_w = np.zeros_like(theta)
        theta_ref = np.zeros_like(theta)
    tw2 = theta_w ** 2
    s = np.zeros(n_s) if s0 is None else np.array(s0, float)
    present = np.isfinite(tg_mm[..., 0])
    y = np.nan_to_num(tg_mm)
    mu = 1e-3

    def evaluate(s, theta):
        model, nodes, local, _, _ = _apply(model0, ms, right, scale, lay, s)
        p, Jt, Js = _jacobians(model0, model, nodes, local, theta, lay)
        r = np.where(present[..., None], p - y, 0.0)
        d = np.linalg.norm(r, axis=-1)
        hub = np.where(d > huber_mm, huber_mm / np.maximum(d, 1e-12), 1.0)  # robust to swapped/ghost markers
        ww = (w[None, :] * present * np.sqrt(hub)) / data_sd_mm
        prior = s / lay.prior_sd
        cost = float(np.sum((ww[..., None] * r) ** 2) + prior @ prior + np.sum(tw2 * (theta - theta_ref) ** 2))
        return cost, r, Jt, Js, ww

    cost, r, Jt, Js, ww = evaluate(s, theta)
    F, M = r.shape[:2]
    n = theta.shape[1]
    H_s = None
    for _ in range(iterations):
        rw = (ww[..., None] * r).reshape(F, 3 * M)
        At = (ww[..., None, None] * Jt).reshape(F, 3 * M, n)
        As = (ww[..., None, None] * Js).reshape(F, 3 * M, n_s)
        # contiguous: matmul on a transposed view skips BLAS (this loop was 3/4 of a calibration)
        AtT = np.ascontiguousarray(At.transpose(0, 2, 1))
        A = AtT @ At
        A += tw2[..., None] * np.eye(n)
        A += (mu * (np.einsum("fii->fi", A) + 1e-6))[..., None] * np.eye(n)
        B = AtT @ As
        As2 = As.reshape(-1, n_s)
        C = As2.T @ As2 + np.diag(1.0 / lay.prior_sd ** 2)
        gt = (AtT @ rw[..., None])[..., 0] + tw2 * (theta - theta_ref)
        gs = As2.T @ rw.reshape(-1) + s / lay.prior_sd ** 2
        Ainv_B = np.linalg.solve(A, B)
        Ainv_g = np.linalg.solve(A, gt[..., None])[..., 0]
        S = C - B.reshape(-1, n_s).T @ Ainv_B.reshape(-1, n_s)  # Σ_f B_fᵀ A_f⁻¹ B_f
        H_s = S.copy()
        S[np.diag_indices(n_s)] *= 1.0 + mu
        rhs = gs - np.einsum("fij,fi->j", B, Ainv_g)
        try:
            ds = -np.linalg.solve(S, rhs)
        except np.linalg.LinAlgError:
            break
        dth = -(Ainv_g + np.einsum("fij,j->fi", Ainv_B, ds))
        th_new = np.clip(theta + dth, lim[:, 0], lim[:, 1])
        s_new = s + ds
        nb = 3 * len(lay.bases)
        s_new[nb:nb + len(lay.lengths)] = np.clip(s_new[nb:nb + len(lay.lengths)], -0.5, 1.0)
        c_new, r_new, Jt_new, Js_new, ww_new = evaluate(s_new, th_new)
        if c_new < cost:
            done = cost - c_new < 1e-6 * cost
            s, theta, cost, r, Jt, Js, ww = s_new, th_new, c_new, r_new, Jt_new, Js_new, ww_new
            mu = max(mu / 3, 1e-7)
            if done:
                break
        else:
            mu *= 10
            if mu > 1e4:
                break
    return s, theta, H_s, cost


def joint_zero_sd(model0, ms, right, scale, lay, s, theta, tg_mm, w, *, data_sd_mm, theta_w, frames):
    """SD (radians, per DoF) of the mean angle over the calibration frames ``frames`` that the subject
    fit leaves open: the uncertainty of the subject vector (bone lengths, finger bases, marker places,
    with their priors) carried through the postures, at the fit ``s``, ``theta`` (all fitted frames,
    ``theta_w`` their posture weights as in the fit). A marker on the last bone of a chain turns about
    its joint together with that joint's angle unseen, so without a known posture this is about the
    prior SD of the marker's place over its distance from the joint (~10-20° for a nail); a frame's
    own noise is not in it (the IK's posterior SD says that).

    From the joint normal equations ``[[A, B], [Bᵀ, C]]`` (A block-diagonal over frames): the mean
    angle moves by ``−mean_f(A_f⁻¹ B_f) δs`` when the subject moves by ``δs``, whose covariance is the
    inverse of the subject's Schur complement."""
    n_s = lay.size
    model, nodes, local, _, _ = _apply(model0, ms, right, scale, lay, s)
    _, Jt, Js = _jacobians(model0, model, nodes, local, theta, lay)
    present = np.isfinite(tg_mm[..., 0])
    ww = (w[None, :] * present) / data_sd_mm
    F, M = present.shape
    n = theta.shape[1]
    At = (ww[..., None, None] * Jt).reshape(F, 3 * M, n)
    As = (ww[..., None, None] * Js).reshape(F, 3 * M, n_s)
    AtT = np.ascontiguousarray(At.transpose(0, 2, 1))
    A = AtT @ At + (theta_w ** 2)[..., None] * np.eye(n)
    A += (1e-9 * (np.einsum("fii->fi", A) + 1e-9))[..., None] * np.eye(n)
    B = AtT @ As
    AiB = np.linalg.solve(A, B)
    S = As.reshape(-1, n_s).T @ As.reshape(-1, n_s) + np.diag(1.0 / lay.prior_sd ** 2)
    S -= B.reshape(-1, n_s).T @ AiB.reshape(-1, n_s)
    W = AiB[frames].mean(0)  # (n, n_s)
    V = W @ np.linalg.pinv(0.5 * (S + S.T)) @ W.T
    return np.sqrt(np.clip(np.diag(V), 0.0, None))


def _ik(model, nodes, local, tg, weights, lim, theta0=None):
    """Marker IK over sample frames; returns θ, per-frame RMS (mm) and the share of frames per DoF at a limit."""
    hm = model.with_limits(lim)
    th, rep = fit_points(hm, nodes, local, tg, theta0, weights=weights,
                         settings=SolverSettings(iterations=20, damping=0.1), restarts=2, restart_rms_mm=3.0)
    return th, rep


def _median(x):
    x = np.asarray(x, float)
    return float(np.nanmedian(x)) if np.isfinite(x).any() else float("nan")


def refine_subject(hand, ms, right, scale, tg_train, tg_held, weights, *, bone_sd, offset_scale, data_sd_mm,
                    iterations, cal, tg_static=None, static_posture=None, static_sd_deg=3.0, rounds=3,
                    posture_prior=None, prior_frames=None):
    """Route 2 of the module docstring, on top of the hand scale in ``cal``; fills ``cal``.
    Frames of a static trial (``tg_static``) are fitted with their posture pulled to
    ``static_posture`` (default: the model's zero, a flat hand): a marker on the last bone of a
    chain can turn about its joint together with that joint's angle without changing any marker
    position, so only a known posture fixes where such a joint's zero is; without one (a
    ``posture_prior`` instead), such markers keep their nominal places (:data:`LAST_BONE_SD_MM`)."""
    model0 = hand.scaled(scale)
    lim = anatomical_limits(model0)
    nodes0, local0 = ms.attachments(model0, right, scale=scale)
    known = tg_static is not None and len(tg_static)
    lay = _layout(model0, ms, nodes0, bone_sd=bone_sd, offset_scale=offset_scale,
                  last_bone_sd_mm=None if known or posture_prior is None else LAST_BONE_SD_MM)
    th0, rep0 = _ik(model0, nodes0, local0, tg_train, weights, lim)
    ok = rep0.iterations >= 0
    if ok.sum() < 3:
        raise SynergyError(cal.source or ms.name, "fewer than 3 calibration frames could be solved")
    tg_fit, th_fit = 1000.0 * tg_train[ok], th0[ok]
    th_ref = np.zeros_like(th_fit)
    th_w = np.zeros_like(th_fit)
    if tg_static is not None and len(tg_static):
        post = ~model0.pose_mask
        ref = np.zeros(model0.n_dofs)
        if static_posture is not None:
            ref[post] = static_posture
        st0 = _ik(model0, nodes0, local0, tg_static, weights, lim)[0]
        st0[:, post] = ref[post]
        ws = np.zeros((len(tg_static), model0.n_dofs))
        ws[:, post] = 1.0 / np.radians(static_sd_deg)
        tg_fit = np.concatenate([tg_fit, 1000.0 * tg_static])
        th_fit = np.concatenate([th_fit, st0])
        th_ref = np.concatenate([th_ref, np.broadcast_to(ref, st0.shape)])
        th_w = np.concatenate([th_w, ws])
        cal.method += " + static posture"
    n_tr = int(ok.sum())
    if posture_prior is not None:
        post = ~model0.pose_mask
        share = 1.0 if prior_frames is None else min(float(prior_frames) / n_tr, 1.0)
        th_ref[:n_tr, post] = posture_prior.mean
        th_w[:n_tr, post] = np.sqrt(share) / np.radians(posture_prior.sd_deg)
        cal.method += f" + posture prior {posture_prior.name}"
        if lay.last_bone_sd_mm is not None:
            cal.method += f" + last-bone markers within {lay.last_bone_sd_mm:g} mm of their places"
    s = None
    for rnd in range(rounds):
        if s is not None:
            # postures that started in the wrong branch (a finger read hyperextended, say) keep the
            # joint fit in a local minimum: re-solve every frame from scratch on the current hand
            # and keep whichever posture fits better
            m_, n_, l_, _, _ = _apply(model0, ms, right, scale, lay, s)
            fresh, rep_f = _ik(m_, n_, l_, tg_fit[:n_tr] / 1000.0, weights, lim)
            warm, rep_w = _ik(m_, n_, l_, tg_fit[:n_tr] / 1000.0, weights, lim, theta0=th_fit[:n_tr])
            better = (rep_f.rms_mm < rep_w.rms_mm - 1e-3) & (rep_f.iterations >= 0)
            th_fit = th_fit.copy()
            th_fit[:n_tr] = np.where(better[:, None], fresh, warm)
            if not better.any():
                break
        s, th_fit, H, _cost = _gauss_newton(model0, ms, right, scale, lay, th_fit, tg_fit, weights, lim,
                                            data_sd_mm=data_sd_mm, iterations=iterations,
                                            huber_mm=max(3.0 * data_sd_mm, 2.0), theta_ref=th_ref, theta_w=th_w, s0=None)
    model, nodes, local, factors, pos = _apply(model0, ms, right, scale, lay, s)
    th_tr, rep_tr = _ik(model, nodes, local, tg_train, weights, lim)
    train = _median(rep_tr.rms_mm)
    # uncertainty: the inverse reduced Hessian, rescaled by how far the residuals are from the assumed noise
    sd = np.full(lay.size, np.nan)
    if H is not None:
        dof = max(int(np.isfinite(tg_train[ok][..., 0]).sum()) * 3 - ok.sum() * model.n_dofs - lay.size, 1)
        rms = np.sqrt(np.nanmean(rep_tr.rms_mm[ok] ** 2))
        with np.errstate(invalid="ignore"):
            sd = np.sqrt(np.clip(np.diag(np.linalg.pinv(H)), 0, None)) * max(rms / data_sd_mm, 1.0) * np.sqrt(
                max(dof, 1) / max(dof, 1))
    nb, nl = 3 * len(lay.bases), len(lay.lengths)
    unc = {"joint_positions_mm": {model0.node_names[k]: sd[3 * j:3 * j + 3].tolist() for j, k in enumerate(lay.bases)},
           "bone_scales": {model0.node_names[k]: float(sd[nb + j]) for j, k in enumerate(lay.lengths)},
           "offsets_mm": {ms.markers[i].label: sd[nb + nl + 3 * j:nb + nl + 3 * j + 3].tolist()
                          for j, i in enumerate(lay.markers)}}
    # how well the fit fixes each joint's zero (the trial's mean angle), scaled as the SDs above
    z = joint_zero_sd(model0, ms, right, scale, lay, s, th_fit, tg_fit, weights, data_sd_mm=data_sd_mm,
                      theta_w=th_w, frames=np.arange(n_tr))
    if H is not None:
        z = z * max(rms / data_sd_mm, 1.0)
    unc["joint_zero_deg"] = {model0.dof_names[j]: round(float(np.degrees(z[j])), 2)
                             for j in np.flatnonzero(~model0.pose_mask)}
    cal.bone_scales = factors
    cal.joint_positions = pos
    cal.offsets = {m.label: local[i].copy() for i, m in enumerate(ms.markers)}
    cal.marker_shift_mm = {ms.markers[i].label: float(np.linalg.norm(s[nb + nl + 3 * j:nb + nl + 3 * j + 3]))
                           for j, i in enumerate(lay.markers)}
    cal.uncertainty = unc
    cal.method += " + bone lengths, finger bases and marker places (joint fit with priors)"
    held = {"frames": int(len(tg_held)), "train_frames": int(ok.sum()), "train_residual_mm": train,
            "residual_mm": float("nan"), "scale_only_residual_mm": float("nan"), "overfit": False}
    if len(tg_held):
        _, rep_h = _ik(model, nodes, local, tg_held, weights, lim)
        _, rep_h0 = _ik(model0, nodes0, local0, tg_held, weights, lim)
        held["residual_mm"] = _median(rep_h.rms_mm)
        held["scale_only_residual_mm"] = _median(rep_h0.rms_mm)
        _, rep_tr0 = _ik(model0, nodes0, local0, tg_train, weights, lim)
        held["scale_only_train_residual_mm"] = _median(rep_tr0.rms_mm)
        # fitting noise lowers the training residual but not the held-out one: a gap between them
        # (beyond what per-frame posture freedom explains) is freedom the data did not support, unless
        # the held-out frames still fit far better than on the scale-only hand (healthy fits on
        # simulated subjects: held-out / train 0.96-1.07; 4 fitted frames with loose priors: 1.5)
        held["overfit"] = overfits(held["residual_mm"], train, held["scale_only_residual_mm"])
        if held["overfit"]:
            cal.warnings.append(f"calibration does not generalise: median marker residual on {held['frames']} "
                                f"held-out frames {held['residual_mm']:.2f} mm (hand scale only "
                                f"{held['scale_only_residual_mm']:.2f} mm), on the fitted frames {train:.2f} mm; "
                                "too much freedom for this trial")
    cal.held_out = held
    return cal


