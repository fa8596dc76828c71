"""A fit's arguments as the arrays of the compiled loop (:func:`tracker._fit_kernels.fit_kernel`,
called by :func:`tracker.icp.fit`): the stages padded into :class:`~tracker._kernel_arrays.StageArrays`
and :class:`~tracker._kernel_arrays.ProjectionArrays` (:func:`stage_arrays`), the matcher's rules
(:func:`match_rules`), the wrist-line pair (:func:`wrist_line`), the detected keypoints' pairs
(:func:`keypoint_pairs`) and the stand-ins of the silhouette term's arrays when it is off.
"""
from __future__ import annotations

import numpy as np

from ._kernel_arrays import (
    ENTRY_CLAMP,
    ENTRY_NONE,
    ENTRY_THROUGH,
    NO_KEYPOINTS,
    KeypointPairs,
    MatchRules,
    ProjectionArrays,
    StageArrays,
    WristLine,
)
from .errors import TrackerError
from .wrist import arm_line_normal

_NO_POINT = np.zeros(3)
_CAMERA_CENTRE = np.zeros(3)
_ENTRIES = {"none": ENTRY_NONE, "clamp": ENTRY_CLAMP, "through": ENTRY_THROUGH}
_PACKED: dict = {}


def wrist_line(hand, cue, settings):
    """The wrist-line pair (:class:`tracker.icp_settings.IcpSettings` ``wrist_line_weight``) as
    :class:`~tracker._kernel_arrays.WristLine`: the model's wrist crease as a point of its node and
    the plane of the wrist ``cue`` (:func:`tracker.wrist.arm_line_normal`); off when the term is off
    or there is no cue."""
    if cue is None or not settings.wrist_line_weight > 0:
        return WristLine(False, 0, _NO_POINT, _NO_POINT, float(settings.wrist_line_weight),
                         settings.wrist_line_mm / 1000.0)
    node, local = hand.wrist_crease_local()
    return WristLine(True, int(node), np.asarray(local, np.float64), arm_line_normal(cue),
                     float(settings.wrist_line_weight), settings.wrist_line_mm / 1000.0)


def keypoint_pairs(keypoints, term):
    """The detected keypoints' pairs as :class:`~tracker._kernel_arrays.KeypointPairs`: of ``keypoints`` =
    ``(xyz (21, 3), confidence (21,))`` (a :class:`tracker.detector.Detection`'s) those found (finite,
    confidence > 0), each weighing ``term.weight`` × its confidence / 21 of the valid data pairs, Cauchy at
    ``term.mm`` (:class:`tracker.icp_settings.KeypointTermSettings`; whether the term is ``on`` is the
    caller's); none when nothing was given or the weight is 0."""
    if keypoints is None or not term.weight > 0:
        return NO_KEYPOINTS
    xyz, conf = (np.asarray(a, np.float64) for a in keypoints)
    if xyz.shape != (21, 3) or conf.shape != (21,):
        raise TrackerError("keypoints", f"need (21, 3) positions and (21,) confidences, got {xyz.shape} and "
                                        f"{conf.shape}")
    found = np.isfinite(xyz).all(axis=1) & np.isfinite(conf) & (conf > 0)
    if not found.any():
        return NO_KEYPOINTS
    return KeypointPairs(True, np.flatnonzero(found).astype(np.int64), np.ascontiguousarray(xyz[found]),
                         term.weight * np.minimum(conf[found], 1.0) / 21.0, term.mm / 1000.0)


def match_rules(matcher, normals):
    """The pairs' rules of ``matcher`` (:class:`tracker.correspond.Matcher`) as
    :class:`~tracker._kernel_arrays.MatchRules`; no normal test without data ``normals``."""
    cs = matcher.settings
    return MatchRules(_CAMERA_CENTRE, bool(cs.facing_only), cs.reject_mm / 1000.0,
                      float(cs.normal_agreement) if normals is not None else -1.0)


def stage_arrays(hand, stages, solver):
    """The stages as the padded arrays of :func:`tracker._fit_kernels.fit_kernel`, ``(StageArrays,
    ProjectionArrays)`` (kept per list of stages and settings: a tracker fits with the same stages
    every frame)."""
    key = (tuple(stages), solver.damping, solver.pose_damping, hand.n_dofs)
    hit = _PACKED.get(key)
    if hit is not None:
        return hit
    n, S = hand.n_dofs, len(stages)
    mmax = max([st.subspace.dim for st in stages] + [1])
    pmax = max([st.project.dim for st in stages if st.project is not None] + [1])
    st_M, st_mu = np.zeros((S, n, mmax)), np.zeros((S, n))
    st_m = np.zeros(S, np.int64)
    st_lo, st_hi, st_damp = np.full((S, mmax), -np.inf), np.full((S, mmax), np.inf), np.zeros((S, mmax))
    st_eye, st_entry, st_local = np.zeros(S, np.bool_), np.zeros(S, np.int64), np.zeros(S, np.bool_)
    pr_on, pr_eye, pr_m = np.zeros(S, np.bool_), np.zeros(S, np.bool_), np.zeros(S, np.int64)
    pr_M, pr_mu = np.zeros((S, n, pmax)), np.zeros((S, n))
    pr_lo, pr_hi = np.full((S, pmax), -np.inf), np.full((S, pmax), np.inf)
    for s, stage in enumerate(stages):
        sp = stage.subspace
        if sp.M.shape[0] != n:
            raise TrackerError("stages", f"stage {s}: subspace has {sp.M.shape[0]} rows, the model has {n} DoFs")
        m = sp.dim
        st_M[s, :, :m], st_mu[s], st_m[s] = sp.M, sp.mu, m
        st_lo[s, :m], st_hi[s, :m] = sp.lo, sp.hi
        st_damp[s, :m] = np.where(sp.pose, solver.pose_damping, solver.damping)
        st_eye[s] = sp.M.shape == (n, n) and np.array_equal(sp.M, np.eye(n))
        st_entry[s] = _ENTRIES[stage.entry]
        st_local[s] = stage.local
        if stage.project is not None:
            pj = stage.project
            k = pj.dim
            pr_on[s], pr_m[s], pr_M[s, :, :k], pr_mu[s] = True, k, pj.M, pj.mu
            pr_lo[s, :k], pr_hi[s, :k] = pj.lo, pj.hi
            pr_eye[s] = pj.M.shape == (n, n) and np.array_equal(pj.M, np.eye(n))
    out = (StageArrays(st_M, st_mu, st_m, st_lo, st_hi, st_damp, st_eye, st_entry, st_local,
                       np.asarray(hand.pose_mask, np.bool_)),
           ProjectionArrays(pr_on, pr_M, pr_mu, pr_m, pr_lo, pr_hi, pr_eye))
    if len(_PACKED) > 64:
        _PACKED.clear()
    _PACKED[key] = out
    return out
