"""Pipeline stage ``run``: a tracker over a whole recording, and the tracking-output file.

The tracking output is a CSV with ``# key: value`` header lines (recording, mode, synergies, PCs,
settings, hand model and its hash, units), then one row per frame: ``frame, time_s, status, fit_mm,
points_used, points, ms`` and the 26 DoF columns (metres, radians). :func:`write_tracking` and :func:`read_tracking` are its one writer and
reader (``tracker track`` writes it; ``tracker eval``, the experiments and users read it).

>>> import io, numpy as np, pandas as pd
>>> df = pd.DataFrame([[0, 0.0, "reinit", 1.5, 300, 310, 20.0] + [0.0] * 26],
...                   columns=list(FRAME_COLUMNS) + list(DOF_NAMES))
>>> text = tracking_csv(df, {"mode": "full", "units": "metres, radians"})
>>> back, meta = parse_tracking(io.StringIO(text), "example.csv")
>>> meta["mode"], back["status"].tolist()
('full', ['reinit'])
"""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pandas as pd

from handmodel.dofs import DOF_NAMES
from handmodel.fileio import atomic_write_text

from .errors import TrackerError
from .observe import observe

FRAME_COLUMNS = ("frame", "time_s", "status", "fit_mm", "points_used", "points", "ms")
STATUSES = ("tracked", "lost", "reinit")


def track_recording(recording, tracker, on_frame=None, *, segmenter=None) -> pd.DataFrame:
    """Track every frame of ``recording`` (anything with ``camera`` that iterates frames with
    ``index``, ``time_s``, ``depth`` in metres and ``color``) with ``tracker`` (:class:`HandTracker`).

    A frame without a usable depth image (missing, wrong size) is tracked as empty, so it is lost.
    ``on_frame(frame, result, observation)`` is called after each frame (``observation`` None for an
    unusable one): progress, overlays, keypoints. Returns one row per frame (:data:`FRAME_COLUMNS` and
    the hand's DoF names)."""
    cam = recording.camera
    rows = []
    for frame in recording:
        depth = frame.depth
        ob = None
        if depth is not None and np.ndim(depth) == 2 and np.shape(depth) == (cam.height, cam.width):
            ob = observe(depth, cam, tracker.settings.observe, segmenter=segmenter, color=frame.color)
            r = tracker.track(ob, cam)
        else:
            r = tracker.step(np.zeros((0, 3)))
        rows.append((frame.index, frame.time_s, r.status, r.fit_mm, r.points_used,
                     0 if ob is None else len(ob.points), r.ms, *r.theta))
        if on_frame is not None:
            on_frame(frame, r, ob)
    return pd.DataFrame(rows, columns=[*FRAME_COLUMNS, *tracker.hand.dof_names])


def tracking_metadata(recording_path, tracker, synergies_spec="") -> dict:
    """The header of a tracking output: what was tracked, how, with which hand model."""
    # the model file's identity (a resized hand is that file plus hand_scale)
    st, hand = tracker.settings, getattr(tracker, "base_hand", tracker.hand)
    return {"recording": str(recording_path), "mode": st.mode, "synergies": synergies_spec or "",
            "pcs": "" if tracker.n_pcs is None else str(tracker.n_pcs), "stride": str(st.observe.stride),
            "icp": str(st.icp.icp_iterations), "gn": str(st.icp.gn_iterations), "model": st.correspond.model,
            "hand_model": f"{hand.name} {hand.sha256}", "hand_scale": _scale_text(tracker),
            "hand_check": str(getattr(tracker, "hand_check_", None) or ""), "units": "metres, radians"}


def _scale_text(tracker) -> str:
    """The hand size tracked with (a factor on the hand model), how it was set, and an automatic
    calibration's per-frame estimates: ``--hand-scale`` takes the number back."""
    scale = getattr(tracker, "scale_", None)
    if scale is None:
        return ""
    est = getattr(tracker, "scale_estimates_", [])
    if tracker.settings.hand_scale != "auto":
        return f"{scale:.4f} (given)"
    return f"{scale:.4f} (auto, median of {', '.join(f'{e:.4f}' for e in est)})"


def tracking_csv(df, meta) -> str:
    """The tracking output's text: ``# key: value`` lines, then the table."""
    head = "".join(f"# {k}: {v}\n" for k, v in meta.items())
    return head + df.to_csv(index=False, float_format="%.9g")


def write_tracking(path, df, meta, *, overwrite=False) -> Path:
    """Write a tracking output atomically (never over an existing file unless ``overwrite``)."""
    _check_table(df, path)
    return atomic_write_text(path, tracking_csv(df, meta), overwrite=overwrite)


def parse_tracking(stream, where):
    """``(table, metadata)`` of a tracking output read from a text stream; ``where`` names it in errors."""
    meta = {}
    lines = []
    for line in stream:
        if line.startswith("#"):
            k, sep, v = line[1:].partition(":")
            if sep:
                meta[k.strip()] = v.strip()
        else:
            lines.append(line)
    try:
        df = pd.read_csv(io.StringIO("".join(lines)))
    except (ValueError, pd.errors.ParserError) as exc:
        raise TrackerError(where, f"cannot read tracking output ({exc})") from None
    _check_table(df, where)
    return df, meta


def read_tracking(path):
    """``(table, metadata)`` of a tracking output file (see :func:`write_tracking`)."""
    try:
        with open(path, encoding="utf-8") as f:
            return parse_tracking(f, path)
    except UnicodeDecodeError:
        raise TrackerError(path, "not a tracking output (not UTF-8 text)") from None


def _check_table(df, where):
    missing = [c for c in (*FRAME_COLUMNS, *DOF_NAMES) if c not in df.columns]
    if missing:
        raise TrackerError(where, f"not a tracking output: missing columns {', '.join(missing)}")
    bad = sorted(set(df["status"].astype(str)) - set(STATUSES))
    if bad:
        raise TrackerError(where, f"unknown status {', '.join(bad)} (expected {', '.join(STATUSES)})")


def keypoints_table(hand, df) -> pd.DataFrame:
    """The 21 keypoints of every tracked frame in mm (NaN where θ is not finite), one row per frame."""
    th = df[list(hand.dof_names)].to_numpy(float)
    kps = np.full((len(th), hand.n_nodes * 3), np.nan)
    ok = np.isfinite(th).all(1)
    if ok.any():
        kps[ok] = hand.keypoints(th[ok]).reshape(int(ok.sum()), -1) * 1000.0
    kd = pd.DataFrame(kps, columns=[f"{n}_{a}_mm" for n in hand.keypoint_names for a in "xyz"])
    kd.insert(0, "frame", df["frame"].to_numpy())
    return kd
