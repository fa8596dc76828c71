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

from handmodel import HandModel
from handmodel.dofs import anatomical_limits
from handmodel.fileio import atomic_write_text
from handmodel.solver import SolverSettings, fit_points
from handmodel.subspace import Subspace

from .c3d import read_c3d
from .calibrate import Calibration, calibrate, golden_section, held_out_line, sample_frames
from .errors import SynergyError
from .markers import MarkerSet, load_markerset
from .ik_priors import (
    ACCEL_SD_DEG_S2,
    DEFAULT_PRIOR,
    IP_COUPLING,
    IP_COUPLING_SD_DEG,
    _r,
    default_prior,
    dip_fixed_fingers,
    ip_coupling_pairs,
    posterior_sd,
    prior_driven,
    prior_rows,
    refine_trajectory,
    refine_with_prior,
)
from .prior import resolve_prior
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
#: A joint whose zero the subject calibration fixes only within this SD (degrees) or worse is named
#: (:func:`synergy.subject.joint_zero_sd`): its angles may be off by a constant of that order.
OPEN_ZERO_DEG = 5.0
#: The posture prior (``'auto'``: :data:`DEFAULT_PRIOR`) weighs in a conversion's automatic calibration
#: without a static trial or neutral frames as this many postures in all.
CALIBRATION_PRIOR_FRAMES = 1.0


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
        why = ("" if poor_residual_mm is not None else
               f": the larger of {POOR_FACTOR:g}× and {POOR_MARGIN_MM:g} mm over the trial's median marker residual "
               f"{floor:.2f} mm")
        warnings.append(f"{100 * poor_share:.0f} % of frames poor (a frame's RMS marker residual > {thr:.1f} mm{why})")
    if per_marker:
        worst = max(per_marker.items(), key=lambda x: x[1][0])
        med = np.median([v[0] for v in per_marker.values()])
        if worst[1][0] > 3 * med + 1.0:
            warnings.append(f"marker {worst[0]} fits worst (median {worst[1][0]:.1f} mm vs {med:.1f} mm): "
                            "misplaced, mislabelled or on a loose spot?")
    return {"noise_floor_mm": _r(floor), "poor_threshold_mm": _r(thr), "poor_share": round(poor_share, 4),
            "marker_residuals_mm": per_marker, "limit_share": limits, "jumps": jumps, "warnings": warnings,
            "prior_driven": prior_driven}


def verdict(diag) -> str:
    """'poor' (do not use without a look), 'check' (warnings) or 'good'."""
    h = diag.get("handedness", {})
    if (diag.get("poor_share", 0) > POOR_TRIAL_SHARE or h.get("verdict") == "wrong hand"
            or any(v > 0.25 for k, v in diag.get("limit_share", {}).items() if k not in diag.get("prior_driven", {}))
            or diag.get("calibration_overfit")):
        return "poor"
    return "check" if diag.get("warnings") else "good"


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
        residuals, share of frames on each limit, handedness check, warnings, ``verdict``, and
        ``calibration_zero_sd_deg``: the SD of each joint's zero the subject calibration left, which
        the per-frame SD does not hold; ``calibration_open_zeros``: those over :data:`OPEN_ZERO_DEG`).
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
            msg = (f"the {'left' if right else 'right'} hand fits these markers better (median marker residual, hand "
                   f"scale only: {hand_check['other_residual_mm']:.1f} mm vs {hand_check['residual_mm']:.1f} mm as {hand})")
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
        # weighed as one posture, the markers on each chain's last bone held to their places (fretting:
        # 6.8-16.0° -> 4.9-6.6°; the rest needs a known posture, docs/experiments/marker-prior.md)
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
    # how well the subject fit fixed each joint's zero (the trial's mean angle): the per-frame SD above
    # does not hold it (a nail's place along its arc is its joint's zero, left to the priors without a
    # known posture: fretting, DIPs 10-20°; docs/experiments/marker-prior.md)
    zero = (cal.uncertainty or {}).get("joint_zero_deg") or {}
    diag["calibration_zero_sd_deg"] = dict(zero)
    diag["calibration_open_zeros"] = {k: v for k, v in zero.items() if v is not None and v > OPEN_ZERO_DEG}
    diag["calibration_overfit"] = bool(cal.held_out.get("overfit", False))
    if diag["calibration_overfit"]:
        # the refusal says the figures it was decided on, in the table's one residual definition
        diag["calibration_held_out"] = held_out_line(cal.held_out)
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
