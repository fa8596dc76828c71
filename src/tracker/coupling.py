"""The coupling of each finger's last two joints, and the finger-wise restart of a tracked fit whose
fingers break it.

A real finger bends its DIP with its PIP (the thumb its IP with its MCP): over the 6000 fingerfist
postures (htrack's Schröder recordings) the DIP is a straight-line function of the PIP within
11–25° (residual standard deviation per finger; :data:`COUPLING`). The depth data rarely hold a
finger's last joint on their own: a fingertip seen end-on while the finger curls, hidden in the fist or
frayed by the sensor's noise leaves a few points that a DIP at its limit explains about as well, and
the next frames start from there (under the Kinect v1 noise model the DIP angles carried most of the
error of counting and open-close, fingers folded into a Z at their limits for dozens of frames).
:func:`restart_uncoupled` fits such a frame once more from the coupled DIP of the fingers that break
the coupling and keeps that fit only when it scores clearly better: a restart, not a prior — a
posture the data hold (a random posture, a finger pressed on a table) keeps its fit.

>>> import numpy as np
>>> from handmodel import HandModel
>>> hand = HandModel.load()
>>> th = np.zeros(hand.n_dofs)
>>> th[[12, 13]] = np.radians([-80.0, 30.0])     # index: PIP flexed 80°, DIP hyperextended 30°
>>> uncoupled(hand, th, 30.0).tolist()
[False, True, False, False, False]
>>> round(float(np.degrees(recoupled(hand, th, uncoupled(hand, th, 30.0), hand.limits)[13])), 1)
-48.2
"""
from __future__ import annotations

import numpy as np

#: Per finger (thumb, index, middle, ring, pinky): the last joint as ``a`` × the one before it
#: ``+ b`` degrees (DIP from PIP; the thumb's IP from its MCP), least squares over the fingerfist
#: postures (residual standard deviation 11, 15, 12, 16, 25°).
COUPLING = np.array([[1.74, -19.6], [0.69, 7.0], [0.70, 6.8], [0.47, -2.1], [1.04, -3.6]])
#: Degrees of hyperextension of a finger's last two joints together beyond which it is restarted bent
#: the other way (:func:`bent_back`): over the fingerfist postures at most 24–33° (index to little finger).
BENT_BACK_DEG = 40.0
#: A bent-back finger's restart is kept only when at least this many of its fit's pairs lie on the
#: finger's last two bones (:func:`last_bones_points`): a finger hidden behind the hand fits any bend,
#: and the score then picks by small gains (a grasp seen from the back, hierarchical, Kinect v1 noise:
#: 0–6 points on the restarted fingers, 5.7 → 11.6° with them kept; the Kinect v1 0.8× index bent
#: forward: 34–61 points, from 4 bent back).
BENT_BACK_MIN_POINTS = 15


def _posture_rows(hand):
    """``(5, 4)`` indices into θ of each finger's posture DoF (abduction, then the three flexions; thumb
    first), or None for a model without the 20 posture DoF in that order."""
    post = np.flatnonzero(~np.asarray(hand.pose_mask))
    return post.reshape(5, 4) if len(post) == 20 else None


def _joints(hand):
    """Indices into θ of each finger's second-to-last and last flexion, ``(5,)`` each, or None for a
    model without the 20 posture DoF in the default order (4 per finger, thumb first)."""
    rows = _posture_rows(hand)
    return None if rows is None else (rows[:, 2], rows[:, 3])


def coupled_dip(hand, theta) -> np.ndarray:
    """``(5,)`` radians: the last joint of each finger that its second-to-last implies (:data:`COUPLING`)."""
    pip, _ = _joints(hand)
    return COUPLING[:, 0] * np.asarray(theta, float)[pip] + np.radians(COUPLING[:, 1])


def uncoupled(hand, theta, tolerance_deg=50.0) -> np.ndarray:
    """``(5,)`` bool: the fingers whose last joint is more than ``tolerance_deg`` from its coupled
    value (all False for a model without the default posture DoF)."""
    idx = _joints(hand)
    if idx is None:
        return np.zeros(5, bool)
    return np.abs(np.asarray(theta, float)[idx[1]] - coupled_dip(hand, theta)) > np.radians(tolerance_deg)


def recoupled(hand, theta, fingers, limits) -> np.ndarray:
    """θ with the last joint of the ``fingers`` (``(5,)`` bool) set to its coupled value, within
    ``limits`` (``(n_dofs, 2)``)."""
    out = np.array(theta, float)
    _, dip = _joints(hand)
    k = dip[np.asarray(fingers, bool)]
    lim = np.asarray(limits, float)
    out[k] = np.clip(coupled_dip(hand, theta)[np.asarray(fingers, bool)], lim[k, 0], lim[k, 1])
    return out


def bent_back(hand, theta, max_deg=BENT_BACK_DEG) -> np.ndarray:
    """``(5,)`` bool: the fingers (not the thumb) whose last two joints are hyperextended by more than
    ``max_deg`` together (all False for a model without the default posture DoF, or ``max_deg`` None)."""
    idx = _joints(hand)
    if idx is None or max_deg is None:
        return np.zeros(5, bool)
    th = np.asarray(theta, float)
    back = np.maximum(th[idx[0]], 0.0) + np.maximum(th[idx[1]], 0.0)
    out = back > np.radians(max_deg)
    out[0] = False
    return out


def last_bones_points(hand, corr) -> np.ndarray:
    """``(5,)`` int: the valid pairs of ``corr`` (:class:`tracker.correspond.Correspondences`) on each
    finger's last two bones (the nodes its second-to-last flexion moves); zeros for a model without the
    default posture DoF."""
    idx = _joints(hand)
    if idx is None:
        return np.zeros(5, np.int64)
    counts = np.bincount(np.asarray(corr.nodes)[np.asarray(corr.valid, bool)], minlength=hand.n_nodes)
    return hand.dof_moves[idx[0]].astype(np.int64) @ counts


def unbent(hand, theta, fingers, limits) -> np.ndarray:
    """θ with the hyperextended joints of the ``fingers`` (``(5,)`` bool; the knuckle and the last two
    joints) bent as far the other way, within ``limits``: a finger pointing at the camera shows its
    side alike bent either way."""
    out = np.array(theta, float)
    k = _posture_rows(hand)[np.asarray(fingers, bool)][:, 1:].ravel()
    lim = np.asarray(limits, float)
    out[k] = np.clip(-np.abs(out[k]), lim[k, 0], lim[k, 1])
    return out


def restart_uncoupled(hand, theta, corr, refit, scorer, limits, *, tolerance_deg=50.0, gain_mm=0.05,
                      bent_back_deg=None, min_points=BENT_BACK_MIN_POINTS):
    """``(θ, corr, restarted)``: when fingers of the fit ``θ`` break the coupling by more than
    ``tolerance_deg`` (:func:`uncoupled`), ``refit(θ0) -> (θ, corr)`` from :func:`recoupled` θ; its
    result replaces the fit when ``scorer(θ, corr)`` (lower is better, mm; the tracker's is
    :func:`tracker.init.score`) is lower by more than ``gain_mm`` (a restart's fit that only ties
    has no evidence for it: the data may hold the uncoupled finger).

    Measured with 50° tolerance and 0.05 mm gain (full DoF, Kinect v1 noise, hand at the model's
    size, the tracker's defaults otherwise; noise seeds 0 and 1): count 3.3 → 2.85° and 6.1 → 5.1°,
    open-close 2.8 → 2.65° and 2.7 → 2.6°, random postures 2.5 → 2.3°. 50° because the true
    fingerfist postures break a 30° tolerance on 29 % of frames (7 % at 50°), each a refit that
    costs time; at 30° count was 2.8° and 4.8°, but random postures (joints drawn independently)
    got worse, 2.8°. A tie-breaking prior instead (the refit kept unless worse by 0.2 mm) made the
    random postures 4.4°.

    ``bent_back_deg``: the fingers :func:`bent_back` flags (None: none) are refitted too, from their
    joints bent as far forward (:func:`unbent`), and that fit is kept only when it scores clearly
    better and at least ``min_points`` of its pairs lie on each such finger's last two bones
    (:func:`last_bones_points`; 0: not asked): the finger bent forward must find data there — a
    finger hidden behind the hand fits any bend; else the coupling's restart runs alone."""
    fingers = uncoupled(hand, theta, tolerance_deg)
    back = bent_back(hand, theta, bent_back_deg)
    if not (fingers.any() or back.any()):
        return theta, corr, False
    start = recoupled(hand, theta, fingers, limits)
    own = scorer(theta, corr) - gain_mm  # what a refit must score below, once for both refits
    if back.any():
        th2, c2 = refit(unbent(hand, start, back, limits))
        seen = not min_points or bool(np.all(last_bones_points(hand, c2)[back] >= min_points))
        if seen and np.all(np.isfinite(th2)) and scorer(th2, c2) < own:
            return th2, c2, True
        if not fingers.any():
            return theta, corr, False
    th2, c2 = refit(start)
    if np.all(np.isfinite(th2)) and scorer(th2, c2) < own:
        return th2, c2, True
    return theta, corr, False
