"""Pipeline stage ``icp``: one ICP fit of the hand to a point cloud.

A fit is ``n_rigid`` rigid steps (Horn 1987: the whole hand moved, posture fixed), then one
non-rigid step per :class:`Stage` (paper §V: correspondences, then damped Gauss-Newton IK in that
stage's subspace). What differs between the paper's full, reduced and hierarchical modes is only the
list of stages, which the schedule builders below make (with ``stages_per_pass`` > 1 most synergy
stages take a cheap local pass instead of the closest-point search, the costly part of a fit: a fit
in the subspace loses nothing by it, one with all DoF does); the parts of a fit are named arguments,
its settings :class:`tracker.icp_settings.IcpSettings`:

>>> from handmodel import HandModel
>>> from handmodel.subspace import Subspace
>>> hand = HandModel.load()
>>> full = Subspace.full(hand, hand.limits)
>>> [s.entry for s in tracking_schedule("full", 4, full)]
['none', 'none', 'none', 'none']
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from handmodel.rigid import euler_to_matrix, horn, matrix_to_euler
from handmodel.solver import solve
from handmodel.subspace import Subspace

from . import _correspond_kernels as CK
from . import _fit_kernels as FK
from . import _observe_kernels as OK
from ._fit_arrays import keypoint_pairs, match_rules, stage_arrays, wrist_line
from ._kernel_arrays import (
    NO_SAMPLES,
    NO_SILHOUETTE,
    CapsuleArrays,
    FitTerms,
    GaussNewton,
    HandArrays,
    Pairs,
    SampleArrays,
    SilhouetteArrays,
    plain,
)
from .correspond import (
    M2D_CAP_MM,
    M2D_TOLERANCE_MM,
    M2D_TOLERANCE_PX,
    SILHOUETTE_TOLERANCE_PX,
    CapsuleModel,
    Correspondences,
    Matcher,
    local_offsets,
    silhouette_pairs,
)
from .errors import TrackerError
from .icp_settings import IcpSettings, KeypointTermSettings


@dataclass(frozen=True)
class Stage:
    """One non-rigid ICP iteration's parameter space.

    ``entry``: ``"none"`` (all DoF), ``"clamp"`` (θ is first moved into the subspace, inside its PC
    limits) or ``"through"`` (the same directions re-centred on θ, which keeps what was found outside
    the subspace). ``project``: after the step, θ is projected onto this subspace (reduced tracking's
    projected steps). ``local``: a local pass instead of the search over every primitive — each data
    point re-projected onto the primitive it was matched to in the pass before (the stage before's, or
    the last rigid step's), the stage before's silhouette pairs kept — while the model moved less than
    ``IcpSettings.local_mm`` since then.
    """

    subspace: Subspace
    entry: str = "none"
    project: Subspace | None = None
    local: bool = False


MODES = ("full", "reduced", "hierarchical")


def tracking_schedule(mode, n, full, reduced=None, *, projected_steps=0, coarse_iterations=1,
                      stages_per_pass=1) -> list[Stage]:
    """Stages of a tracked frame: ``full`` all DoF; ``reduced`` the synergy subspace (its last
    ``projected_steps`` with all DoF, projected onto it — never the first); ``hierarchical``
    ``coarse_iterations`` in the synergy subspace through θ, then all DoF.

    ``stages_per_pass``: after a closest-point search (the rigid step's counted as a stage), the
    synergy-subspace stages take local passes (:attr:`Stage.local`), up to this many stages per search
    in all; stages with all DoF always search. 1: every stage searches (the paper's).

    >>> from handmodel import HandModel
    >>> from handmodel.subspace import Subspace
    >>> hand = HandModel.load()
    >>> full = Subspace.full(hand, hand.limits)
    >>> syn = Subspace(np.eye(26)[:, :16], np.zeros(26), -np.ones(16), np.ones(16), hand.pose_mask[:16])
    >>> ["local" if s.local else "search" for s in tracking_schedule("reduced", 4, full, syn, stages_per_pass=3)]
    ['local', 'local', 'search', 'local']
    >>> ["local" if s.local else "search" for s in tracking_schedule("hierarchical", 4, full, syn, stages_per_pass=3)]
    ['local', 'search', 'search', 'search']
    """
    if mode == "full":
        return [Stage(full)] * n
    if reduced is None:
        raise TrackerError("synergies", f"mode {mode!r} needs a synergy subspace")
    if stages_per_pass < 1:
        raise TrackerError("settings", f"stages_per_pass must be ≥ 1, got {stages_per_pass}")
    if mode == "reduced":
        first_projected = max(n - projected_steps, 1) if projected_steps else n
        out = [Stage(full, project=reduced) if k >= first_projected else Stage(reduced, "clamp") for k in range(n)]
    elif mode == "hierarchical":
        out = [Stage(reduced, "through") if k < coarse_iterations else Stage(full) for k in range(n)]
    else:
        raise TrackerError("settings", f"mode must be one of {', '.join(MODES)}, got {mode!r}")
    served = 1  # the rigid step's pass
    for k, stage in enumerate(out):
        if stage.subspace is not full and served < stages_per_pass:
            out[k] = replace(stage, local=True)
            served += 1
        else:
            served = 1
    return out


def search_schedule(mode, n, full, reduced=None, ladder=(), *, through=False) -> list[Stage]:
    """Stages of a fit without temporal prior: ``hierarchical`` spreads the ``ladder`` of growing
    subspaces (ending with all DoF) over the ``n`` iterations, early ones coarse; ``through`` re-centres
    them on θ (refining a start that already holds a posture) instead of clamping θ into them."""
    if mode == "full":
        return [Stage(full)] * n
    if mode == "reduced":
        if reduced is None:
            raise TrackerError("synergies", "mode 'reduced' needs a synergy subspace")
        return [Stage(reduced, "clamp")] * n
    if mode != "hierarchical":
        raise TrackerError("settings", f"mode must be one of {', '.join(MODES)}, got {mode!r}")
    ladder = list(ladder) or [full]
    entry = "through" if through else "clamp"
    out = []
    for k in range(n):
        sp = ladder[min(int(k * len(ladder) / max(n, 1)), len(ladder) - 1)]
        out.append(Stage(sp) if sp is full else Stage(sp, entry))
    return out


def clamp(subspace, theta) -> np.ndarray:
    """θ moved into ``subspace``: projected onto it, its coordinates clipped to the limits."""
    return subspace.to_theta(np.clip(subspace.to_alpha(theta), subspace.lo, subspace.hi))


def through(subspace, theta, pose_mask) -> Subspace:
    """The same synergy directions, but through θ (a refinement keeps what an earlier stage or frame
    found outside the subspace); the PC limits shift accordingly."""
    a = subspace.to_alpha(theta)
    mu = np.array(theta, float)
    mu[pose_mask] = 0.0
    # θ itself is always admitted: a posture outside the PC limits (rarer than any training posture)
    # must not be clamped back to them by the coarse step
    return Subspace(subspace.M, mu, np.minimum(subspace.lo - a, 0.0), np.maximum(subspace.hi - a, 0.0),
                    subspace.pose, label=subspace.label + " (through θ)")


def apply_rigid(theta, R, t) -> np.ndarray:
    """θ with the global pose pre-multiplied by the rigid motion x ↦ R x + t."""
    th = np.array(theta, float)
    Rp = euler_to_matrix(th[3:6])
    th[:3] = R @ th[:3] + t
    th[3:6] = matrix_to_euler(R @ Rp)
    return th


def rigid_step(theta, data_points, corr, weights=None) -> np.ndarray:
    """One rigid ICP update from valid correspondences; θ unchanged with fewer than 3 pairs."""
    v = corr.valid
    if v.sum() < 3:
        return np.array(theta, float)
    R, t = horn(corr.model[v], data_points[v], None if weights is None else weights[v])
    return apply_rigid(theta, R, t)


def cauchy_weights(distance_m, scale_mm) -> np.ndarray:
    """IRLS weights of the Cauchy loss: pairs far off (a finger the subspace cannot bend there, a
    wrong match) lose weight instead of dragging the global pose; ``scale_mm`` 0 = all ones."""
    d = np.asarray(distance_m, float)
    if not scale_mm:
        return np.ones(len(d))
    return 1.0 / np.sqrt(1.0 + (d * 1000.0 / scale_mm) ** 2)


def fit(hand, points, theta, stages, matcher, settings: IcpSettings | None = None, *, n_rigid=0, normals=None,
        samples=None, silhouette=None, wrist=None, keypoints=None, keypoint_term=None, moments=True, stats=None):
    """ICP: ``n_rigid`` rigid steps, then one damped Gauss-Newton IK per stage of ``stages``.

    The whole loop runs in one compiled call (:func:`tracker._fit_kernels.fit_kernel`) when
    ``matcher`` is a :class:`~tracker.correspond.Matcher` on the capsule model; any other matcher
    goes through :func:`fit_reference`, the same steps as a Python loop. ``moments``: the
    Gauss-Newton steps work on per-node moment sums of the pairs (cost independent of the number of
    pairs, smaller in a smaller subspace; the same θ to round-off), else on every pair as
    :func:`handmodel.solver.solve` does. Point-to-plane pairs always take the per-pair path.

    Parameters
    ----------
    hand : HandModel
    points : (N, 3) data points, camera frame, metres
    theta : (n_dofs,) start
    stages : list of :class:`Stage` (see :func:`tracking_schedule`, :func:`search_schedule`)
    matcher : callable ``(theta, points, normals) -> Correspondences`` (:class:`tracker.correspond.Matcher`)
    settings : IcpSettings (estimation: robust weights, silhouette weight, point-to-plane, damping)
    normals : (N, 3) data normals or None (NaN rows: unknown)
    samples, silhouette : :class:`tracker.correspond.ModelSamples` and :class:`~tracker.correspond.Silhouette`
        for the model→data term (both or neither)
    wrist : :class:`tracker.wrist.WristCue` or None
        the frame's wrist cue for the wrist-line pair (:class:`IcpSettings` ``wrist_line_weight``)
    keypoints : ``(xyz (21, 3), confidence (21,))`` or None
        the frame's detected keypoints for the keypoint term (:func:`tracker._fit_arrays.keypoint_pairs`)
    keypoint_term : :class:`tracker.icp_settings.KeypointTermSettings` or None (its defaults)
        the term's weight and Cauchy scale
    moments : bool
        Gauss-Newton on moment sums (default) or on every pair.
    stats : int64 array (5,), optional
        Gauss-Newton steps taken, steps that failed to lower the energy (each ends its stage) and the
        trial steps' energy evaluations are added to ``stats[0]``, ``stats[1]`` and ``stats[2]`` (the
        compiled moment path counts; the others add nothing), the closest-point searches (the final
        one included) and the local passes to ``stats[3]`` and ``stats[4]`` (the compiled loop counts).

    Returns
    -------
    theta, Correspondences at the result
    """
    st = settings or IcpSettings()
    if stats is not None and (stats.shape != (5,) or stats.dtype != np.int64):
        raise TrackerError("stats", f"stats must be an int64 array of shape (5,), got {stats.dtype} {stats.shape}")
    if not (isinstance(matcher, Matcher) and isinstance(matcher.surface, CapsuleModel)):
        return fit_reference(hand, points, theta, stages, matcher, st, n_rigid=n_rigid, normals=normals,
                             samples=samples, silhouette=silhouette, wrist=wrist, keypoints=keypoints,
                             keypoint_term=keypoint_term)
    args = fit_arguments(hand, points, stages, matcher, st, n_rigid=n_rigid, normals=normals, samples=samples,
                         silhouette=silhouette, wrist=wrist, moments=moments)
    pts = args[2]
    out = Pairs.empty(len(pts))
    th = FK.fit_entry(np.array(hand.check_theta(theta), float), *args,
                      tuple(keypoint_pairs(keypoints, keypoint_term or KeypointTermSettings())),
                      tuple(out), np.zeros(5, np.int64) if stats is None else stats)
    return th, Correspondences(out.p, out.node, out.n, out.d, out.valid, pts)


def fit_arguments(hand, points, stages, matcher, settings: IcpSettings, *, n_rigid=0, normals=None, samples=None,
                  silhouette=None, wrist=None, moments=True) -> tuple:
    """The compiled fit's arguments after θ and before its output pairs and stats, as plain tuples
    (:func:`tracker._kernel_arrays.plain`): what :func:`fit` passes to
    :func:`tracker._fit_kernels.fit_entry` for a :class:`~tracker.correspond.Matcher` on the capsule
    model (the batched fits, :func:`tracker._fit_kernels.fit_score_many_entry`, take the same; a lone fit
    adds the keypoint pairs after them, which the searches' fits do not have). The data points are the
    third (float64, contiguous, ``(N, 3)``)."""
    st = settings
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    nrm = _NO_ROWS if normals is None else np.ascontiguousarray(normals, dtype=np.float64).reshape(-1, 3)
    sil_on = silhouette is not None and samples is not None and st.silhouette_weight > 0 and not silhouette.empty
    solver = st.solver()
    terms = FitTerms(float(st.robust_mm), bool(st.point_to_plane), bool(moments), st.local_mm / 1000.0, sil_on,
                     float(st.silhouette_weight), SILHOUETTE_TOLERANCE_PX, int(n_rigid))
    return plain(HandArrays.of(hand), CapsuleArrays.of(matcher.surface.caps), pts, nrm, match_rules(matcher, normals),
                 *stage_arrays(hand, stages, solver), GaussNewton.of(solver), terms,
                 SampleArrays.of(samples) if sil_on else NO_SAMPLES,
                 SilhouetteArrays.of(silhouette) if sil_on else NO_SILHOUETTE, wrist_line(hand, wrist, st))


#: re-centring needs this many camera-facing model samples to say where the hand is
MIN_FACING_SAMPLES = 10
_NO_ROWS = np.zeros((0, 3))


def posed_samples(hand, samples, theta):
    """``(P, N)``: the :class:`tracker.correspond.ModelSamples` posed at θ, their points and normals
    (``samples.pose(theta)`` in one compiled call: the tracker poses the predicted hand every frame
    for the gate and the re-centring)."""
    P, N = np.empty((len(samples.nodes), 3)), np.empty((len(samples.nodes), 3))
    CK.pose_samples_entry(*plain(np.ascontiguousarray(theta, dtype=np.float64), HandArrays.of(hand),
                                 SampleArrays.of(samples), P, N))
    return P, N


def centre_shift(points, samples_posed):
    """The shift (m, ``(3,)``) that moves the camera-facing model samples' per-axis median onto the
    data ``points``' (``samples_posed``: ``(P, N)`` from :func:`posed_samples`), or None with fewer
    than :data:`MIN_FACING_SAMPLES` facing samples (too little of the hand faces the camera to say where it is)."""
    P, N = samples_posed
    shift = np.empty(3)
    if OK.centre_shift(np.ascontiguousarray(points, dtype=np.float64), P, N, shift) < MIN_FACING_SAMPLES:
        return None
    return shift


def model_to_data_mean(samples, theta, silhouette, *, tolerance_mm=M2D_TOLERANCE_MM, tolerance_px=M2D_TOLERANCE_PX,
                       cap_mm=M2D_CAP_MM) -> float:
    """``np.mean(tracker.correspond.model_to_data_mm(samples, θ, silhouette, …))`` in one compiled call
    (the model→data part of :func:`tracker.init.score`, which the safety net computes on every tracked
    frame; equal to ~1e-15 relative, the sum's order differs). ``samples``:
    :class:`tracker.correspond.ModelSamples` (posed with their own hand)."""
    if silhouette.empty:
        return float(cap_mm)
    return float(CK.model_to_data_mean_entry(*plain(
        np.ascontiguousarray(theta, dtype=np.float64), HandArrays.of(samples.hand), SampleArrays.of(samples),
        SilhouetteArrays.of(silhouette, depth=np.asarray(silhouette.depth, np.float64)),
        float(tolerance_mm), float(tolerance_px), float(cap_mm))))


def capsule_pass(hand, matcher, theta, points, normals, segments=None):
    """``(Correspondences, segments)``: ``matcher``'s pass at θ (a
    :class:`tracker.correspond.Matcher` on the capsule model) and the primitive each point was matched
    to (−1: none); with ``segments``, the local pass of :func:`tracker._correspond_kernels.match_same`
    instead (every point kept on its primitive there)."""
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    nrm = _NO_ROWS if normals is None else np.ascontiguousarray(normals, dtype=np.float64).reshape(-1, 3)
    out = Pairs.empty(len(pts), None if segments is None else np.array(segments, np.int64))
    caps = CapsuleArrays.of(matcher.surface.caps)
    args = (np.ascontiguousarray(hand.node_frames(np.asarray(theta, float))), caps, pts, nrm,
            match_rules(matcher, normals), out)
    if segments is None:
        CK.match(*args)
    else:
        CK.match_same(*args)
        # the node of a primitive (match names it; match_same keeps what it was given)
        out.node[:] = np.where(out.seg >= 0, caps.node[np.maximum(out.seg, 0)], 0)
    return Correspondences(out.p, out.node, out.n, out.d, out.valid, pts), out.seg


def fit_reference(hand, points, theta, stages, matcher, settings: IcpSettings | None = None, *, n_rigid=0,
                  normals=None, samples=None, silhouette=None, wrist=None, keypoints=None, keypoint_term=None):
    """The reference implementation of :func:`fit`: the ICP loop in Python around the compiled
    correspondence, silhouette and solver kernels (any matcher; the compiled loop is checked against it).

    Parameters
    ----------
    hand : HandModel
    points : (N, 3) data points, camera frame, metres
    theta : (n_dofs,) start
    stages : list of :class:`Stage` (see :func:`tracking_schedule`, :func:`search_schedule`)
    matcher : callable ``(theta, points, normals) -> Correspondences`` (:class:`tracker.correspond.Matcher`)
    settings : IcpSettings (estimation: robust weights, silhouette weight, point-to-plane, damping)
    normals : (N, 3) data normals or None (NaN rows: unknown)
    samples, silhouette : :class:`tracker.correspond.ModelSamples` and :class:`~tracker.correspond.Silhouette`
        for the model→data term (both or neither)
    wrist : :class:`tracker.wrist.WristCue` or None
        the frame's wrist cue for the wrist-line pair
    keypoints : ``(xyz (21, 3), confidence (21,))`` or None
        the frame's detected keypoints for the keypoint term
    keypoint_term : :class:`tracker.icp_settings.KeypointTermSettings` or None (its defaults)

    Returns
    -------
    theta, Correspondences at the result
    """
    st = settings or IcpSettings()
    solver = st.solver()
    capsules = isinstance(matcher, Matcher) and isinstance(matcher.surface, CapsuleModel)
    line = wrist_line(hand, wrist, st)
    wl_node, wl_local, wl_normal = (line.node if line.on else -1), line.local, line.normal
    kps = keypoint_pairs(keypoints, keypoint_term or KeypointTermSettings())
    corr = pairs = sil_last = None
    last = None  # (θ, segments) of the pass before: where and onto which primitives it matched
    for _ in range(n_rigid):
        corr = matcher(theta, points, normals)
        last = (theta, None)
        theta = rigid_step(theta, points, corr)
    for stage in stages:
        sp = stage.subspace
        local = False
        if stage.local and st.local_mm > 0 and capsules and last is not None and corr.valid.sum() >= 3:
            # a local pass while the model moved less than local_mm since the pass before
            if pairs is not None:
                nodes, loc = pairs
                moved = hand.points(theta, nodes, loc) - hand.points(pairs_at, nodes, loc)
            else:
                v = corr.valid
                moved = hand.points(theta, corr.nodes[v], local_offsets(hand, last[0], corr.nodes[v],
                                                                        corr.model[v])) - corr.model[v]
            local = np.sqrt((moved ** 2).sum(1).max()) < st.local_mm / 1000.0
        if local:
            seg = last[1] if last[1] is not None else capsule_pass(hand, matcher, last[0], points, normals)[1]
            corr, seg = capsule_pass(hand, matcher, theta, points, normals, seg)
            last = (theta, seg)
        else:
            corr = matcher(theta, points, normals)
            last = (theta, None)
        v = corr.valid
        if v.sum() < 3:
            break
        if stage.entry == "through":
            sp = through(sp, theta, hand.pose_mask)
        elif stage.entry == "clamp":
            theta = clamp(sp, theta)
        nodes = corr.nodes[v]
        loc = local_offsets(hand, theta, nodes, corr.model[v])
        tg = points[v]
        w = cauchy_weights(corr.distance[v], st.robust_mm)
        plane = corr.normals[v] if st.point_to_plane else None
        if silhouette is not None and samples is not None and st.silhouette_weight > 0:
            if not (local and sil_last is not None):
                # a local pass keeps the silhouette pairs of the pass before too
                sil_last = silhouette_pairs(samples, theta, silhouette)
            sn, sl, stg = sil_last
            if len(sn):
                nodes, loc, tg = np.r_[nodes, sn], np.r_[loc, sl], np.r_[tg, stg]
                # weight per pair so the term counts like the data term per unit area
                w = np.r_[w, np.full(len(sn), st.silhouette_weight * np.sqrt(max(v.sum(), 1) / max(len(samples.nodes), 1)))]
                if plane is not None:
                    plane = np.r_[plane, np.zeros((len(sn), 3))]
        c = hand.points(theta, [wl_node], [wl_local])[0] if wl_node >= 0 else None
        if c is not None and abs(wl_normal @ c) > st.wrist_line_mm / 1000.0:
            off = wl_normal @ c - np.copysign(st.wrist_line_mm / 1000.0, wl_normal @ c)
            nodes, loc, tg = np.r_[nodes, [wl_node]], np.r_[loc, [wl_local]], np.r_[tg, [c - off * wl_normal]]
            w = np.r_[w, np.sqrt(st.wrist_line_weight * v.sum())]
            if plane is not None:
                plane = np.r_[plane, np.zeros((1, 3))]
        if kps.on:
            d = np.linalg.norm(hand.keypoints(theta)[kps.nodes] - kps.target, axis=1)
            nodes, loc, tg = np.r_[nodes, kps.nodes], np.r_[loc, np.zeros((len(kps.nodes), 3))], np.r_[tg, kps.target]
            w = np.r_[w, np.sqrt(kps.share * v.sum()) * cauchy_weights(d, kps.scale_m * 1000.0)]
            if plane is not None:
                plane = np.r_[plane, np.zeros((len(kps.nodes), 3))]
        pairs, pairs_at = (nodes, loc), theta
        theta, _ = solve(hand, theta, nodes, loc, tg, weights=w, normals=plane, subspace=sp, settings=solver)
        if stage.project is not None:
            theta = clamp(stage.project, theta)
    corr = matcher(theta, points, normals)
    return theta, corr
