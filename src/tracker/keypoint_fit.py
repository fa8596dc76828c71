"""A start of the model fit from a keypoint detector's answer (either detector's
:class:`tracker.detector.Detection`): the frame's detection, the hand's size from its keypoints and the
hand fitted to them."""
from __future__ import annotations

import numpy as np

from .detector import Detection


def detect_in(detect, sil, hand: str, mask=None):
    """``detect``'s answer on a frame's :class:`tracker.correspond.Silhouette` (its whole depth frame where
    it has one, the segmentation as the mask, or ``mask`` where given), or None when the frame has no hand
    region or no depth."""
    if sil is None or sil.empty or sil.camera is None:
        return None
    depth = sil.frame_depth if getattr(sil, "frame_depth", None) is not None else sil.depth
    return None if depth is None else detect(depth, sil.camera, sil.mask if mask is None else mask, hand)


def confident(detection: Detection, min_confidence: float = 0.2) -> np.ndarray:
    """Which keypoints were found: finite and at least ``min_confidence`` confident."""
    kp = np.asarray(detection.keypoints_xyz, float)
    return np.isfinite(kp).all(axis=1) & (np.asarray(detection.confidence) >= min_confidence)


def keypoint_scale(detection: Detection, hand_model, *, min_confidence: float = 0.2, min_bones: int = 4):
    """The hand's size relative to ``hand_model`` from the detected keypoints, or None: the summed length of
    the bones whose two ends were found (joint to joint, posture-free) over the model's. Long bones weigh
    most, as a detector's error is about the same in millimetres on each keypoint.

    >>> from handmodel import HandModel
    >>> h = HandModel.load()
    >>> kp = 1.3 * h.keypoints(np.zeros(h.n_dofs))
    >>> d = Detection(np.full((21, 2), np.nan), kp[:, 2], kp, np.ones(21), 1.0, 100)
    >>> round(keypoint_scale(d, h), 3)
    1.3
    """
    kp = np.asarray(detection.keypoints_xyz, float)
    ok = confident(detection, min_confidence)
    child = np.arange(1, len(kp))
    parent = np.where((child - 1) % 4 == 0, 0, child - 1)  # wrist, then each finger base → tip
    both = ok[child] & ok[parent]
    if both.sum() < min_bones:
        return None
    model = hand_model.keypoints(np.zeros(hand_model.n_dofs))
    seen = np.linalg.norm(kp[child] - kp[parent], axis=1)[both].sum()
    return float(seen / np.linalg.norm(model[child] - model[parent], axis=1)[both].sum())


def fit_start(detection: Detection, hand_model, synergies=None, *, min_confidence: float = 0.2,
              min_keypoints: int = 6, n_components=None):
    """A start θ of ``hand_model`` fitted to the detected keypoints (:func:`handmodel.solver.fit_keypoints`,
    each keypoint weighted by its confidence), or None when fewer than ``min_keypoints`` are confident.

    With ``synergies`` (a synergy :class:`~synergy.bundle.Bundle`) the posture is fitted in its
    subspace first — the seen keypoints and the subspace fill the hidden fingers — then every DoF
    from there on the seen keypoints alone (a hidden finger keeps the subspace's bend)."""
    from handmodel.solver import fit_keypoints

    kp = np.array(detection.keypoints_xyz, float)
    use = confident(detection, min_confidence)
    if use.sum() < min_keypoints:
        return None
    kp[~use] = np.nan
    w = np.where(use, np.asarray(detection.confidence, float), 0.0)
    sub = None if synergies is None else synergies.subspace(n_components, hand_model)
    theta, _ = fit_keypoints(hand_model, kp, subspace=sub, weights=w)
    if sub is not None:
        theta, _ = fit_keypoints(hand_model, kp, theta0=theta, weights=w, restarts=0)
    return theta if np.all(np.isfinite(theta)) else None
