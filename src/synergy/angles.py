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

from handmodel.dofs import anatomical_limits


def lowpass_markers(points, rate, cutoff_hz, order=4):
    """Zero-phase Butterworth low-pass of marker trajectories ``(F, M, 3)``, gap-aware: each
    contiguous run of valid samples is filtered on its own; runs too short to filter stay raw."""
    from scipy.signal import butter, filtfilt

    if not cutoff_hz or cutoff_hz >= rate / 2:
        return points
    b, a = butter(order, cutoff_hz / (rate / 2))
    pad = 3 * max(len(a), len(b))
    out = points.copy()
    valid = ~np.isnan(points[..., 0])
    for m in range(points.shape[1]):
        v = np.r_[False, valid[:, m], False].astype(np.int8)
        starts, ends = np.flatnonzero(np.diff(v) == 1), np.flatnonzero(np.diff(v) == -1)
        for s, e in zip(starts, ends):
            if e - s > pad:
                out[s:e, m] = filtfilt(b, a, points[s:e, m], axis=0)
    return out


def markers_to_angles(data, markerset, *, hand: str = "left", model="default", calibration="trial",
                      settings=None, poor_residual_mm: float = 10.0, min_markers: int = 4, smooth_hz=None):
    """Joint angles of every frame of a trial.

    Parameters
    ----------
    data : marker data (from :func:`synergy.c3d.read_c3d`) or a path to a C3D file
    markerset : :class:`~synergy.markers.MarkerSet` or its name/path
    hand : 'left' or 'right'
    model : hand model name/path or a :class:`~handmodel.HandModel`
    calibration : 'trial' (estimate from this trial), None (the model as it is), a
        :class:`~synergy.calibrate.Calibration`, or marker data of a static trial
    poor_residual_mm : frames whose RMS marker residual exceeds this are flagged ``poor``
    min_markers : frames with fewer markers are not solved (NaN, flagged ``gap``)
    smooth_hz : optional zero-phase low-pass cut-off (Hz) for the marker trajectories before IK

    Returns
    -------
    pandas.DataFrame
        ``frame, time_s``, the 26 DoF columns (radians, metres), ``residual_mm``, ``markers``,
        ``quality`` (ok / poor / gap); ``df.attrs`` holds the metadata (rate, source, units,
        marker set, hand, calibration, extra markers).
    """
    import pandas as pd

    from handmodel import HandModel
    from handmodel.solver import SolverSettings, fit_points
    from handmodel.subspace import Subspace

    from .calibrate import Calibration, calibrate
    from .markers import MarkerSet, load_markerset

    if isinstance(data, (str, Path)):
        from .c3d import read_c3d

        data = read_c3d(data)
    ms = markerset if isinstance(markerset, MarkerSet) else load_markerset(markerset)
    ms = ms.for_hand(hand)
    right = hand == "right"
    base = model if isinstance(model, HandModel) else HandModel.load(model, right=right)
    where = getattr(data, "path", None)
    idx, extra = ms.match(list(data.labels), where=where)
    if calibration == "trial":
        cal = calibrate(data, ms, base, right=right)
    elif calibration is None:
        cal = Calibration(method="none")
    elif isinstance(calibration, Calibration):
        cal = calibration
    else:
        cal = calibrate(calibration, ms, base, right=right)
        cal.source = str(getattr(calibration, "path", "static trial"))
    hm = cal.model(base)
    lim = anatomical_limits(hm)
    hm = hm.with_limits(lim)
    nodes, local = ms.attachments(hm, right, cal.offsets or None, scale=cal.scale)
    pts = np.asarray(data.points, float)
    targets = np.where((idx >= 0)[None, :, None], pts[:, np.maximum(idx, 0)], np.nan)
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
    F = len(targets)
    first = int(getattr(data, "first_frame", 0) or 0)
    df = pd.DataFrame(theta, columns=hm.dof_names)
    df.insert(0, "time_s", (np.arange(F)) / rate)
    df.insert(0, "frame", np.arange(F) + first)
    df["residual_mm"] = rep.rms_mm
    df["markers"] = n_present
    q = np.where(rep.iterations < 0, "gap", np.where(rep.rms_mm > poor_residual_mm, "poor", "ok"))
    df["quality"] = q
    df.attrs.update({
        "source": str(where) if where else "", "rate_hz": rate, "units": {"angles": "rad", "translation": "m"},
        "markerset": ms.name, "hand": hand, "hand_model": base.name, "calibration": cal.to_dict(),
        "extra_markers": extra, "frames": F, "smooth_hz": smooth_hz,
        "gap_fraction": float(np.isnan(targets[..., 0]).mean()),
    })
    return df


def write_angles_csv(df, path, *, overwrite=False):
    """CSV with ``# key: value`` metadata lines (JSON values) before the header; atomic."""
    from handmodel.fileio import atomic_write_text

    head = "".join(f"# {k}: {json.dumps(v, default=str)}\n" for k, v in df.attrs.items())
    body = df.to_csv(index=False, float_format="%.9g")
    return atomic_write_text(path, head + body, overwrite=overwrite)


def read_angles_csv(path):
    """Read a joint-angle CSV written by :func:`write_angles_csv` (metadata back into ``df.attrs``)."""
    import pandas as pd

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
