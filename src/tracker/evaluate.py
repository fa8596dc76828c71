"""Evaluation against ground truth: posture error as the paper defines it (mean absolute difference
of the 20 posture angles, degrees), keypoint error (mm), shares of frames under thresholds."""
from __future__ import annotations

import numpy as np


def posture_error_deg(theta, truth, pose_mask):
    """Per frame: mean |Δ| over the posture angles in degrees (NaN where θ is NaN)."""
    th = np.asarray(theta, float)
    tr = np.asarray(truth, float)
    post = ~np.asarray(pose_mask)
    return np.degrees(np.abs(th[..., post] - tr[..., post])).mean(-1)


def keypoint_error_mm(hand, theta, truth, truth_hand=None):
    """Per frame: mean Euclidean distance of the 21 keypoints (mm), θ's on ``hand`` (the hand tracked) and
    the truth's on ``truth_hand`` (the hand rendered; default ``hand``): a hand of another size or shape
    than the model is judged where its joints really are."""
    th = np.asarray(theta, float)
    ok = np.isfinite(th).all(-1)
    out = np.full(th.shape[:-1], np.nan)
    shown = hand if truth_hand is None else truth_hand
    if ok.any():
        out[ok] = np.linalg.norm(hand.keypoints(th[ok]) - shown.keypoints(np.asarray(truth)[ok]), axis=-1).mean(-1) * 1000
    return out


def summarise(hand, theta, truth, status=None, ms=None, thresholds_deg=(2, 5, 10), thresholds_mm=(5, 10, 20),
              truth_hand=None):
    """A dict of the headline figures of one tracked sequence (``truth_hand``: :func:`keypoint_error_mm`)."""
    pe = posture_error_deg(theta, truth, hand.pose_mask)
    ke = keypoint_error_mm(hand, theta, truth, truth_hand)
    n = len(pe)
    out = {
        "frames": n,
        "posture_error_mean_deg": float(np.nanmean(pe)) if np.isfinite(pe).any() else float("nan"),
        "posture_error_median_deg": float(np.nanmedian(pe)) if np.isfinite(pe).any() else float("nan"),
        "keypoint_error_mean_mm": float(np.nanmean(ke)) if np.isfinite(ke).any() else float("nan"),
    }
    for t in thresholds_deg:
        out[f"share_posture_below_{t}deg"] = float(np.mean(np.nan_to_num(pe, nan=np.inf) < t))
    for t in thresholds_mm:
        out[f"share_keypoints_below_{t}mm"] = float(np.mean(np.nan_to_num(ke, nan=np.inf) < t))
    if status is not None:
        st = np.asarray(status)
        for s in ("tracked", "lost", "reinit", "predicted"):
            out[f"share_{s}"] = float(np.mean(st == s))
    if ms is not None:
        out["ms_median"] = float(np.median(ms))
        out["fps"] = float(1000.0 / np.median(ms))
    return out, pe, ke
