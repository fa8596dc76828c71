"""The small named parts of :class:`tracker.track.FrameTracker`'s per-frame pipeline, each built from
its settings group and testable alone: the frame's wrist cue (:class:`WristCue`), re-centring
(:class:`Recentring`), the unseen-joint prior (:class:`UnseenPrior`), the coupling restarts
(:class:`FingerRestart`), the loss / "no hand" tests (:class:`LossCheck`), the gate and the prediction
(:class:`Gate`, :class:`Prediction`) and the start search (:class:`StartSearch`, :class:`ColourSeed`).
Every part has the one interface :class:`FramePart`: its counts go to the tracker's
:class:`TrackerStats`, ``reset()`` forgets what it learnt of the sequence. The safety net (:mod:`tracker.net`) and the size calibration
(:mod:`tracker.sizing`) are parts too.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Protocol

import numpy as np

from handmodel.rigid import turned_on

from ._wrist_kernels import surface_past_outline
from .correspond import Silhouette
from .coupling import restart_uncoupled
from .icp import centre_shift, posed_samples
from .init import SearchBudget, fit_single_frame, score, seeded_search
from .observe import past_wrist, predicted_near
from .rgb import RgbSeed
from .wrist import arm_behind, wrist_cue


@dataclass
class TrackerStats:
    """What a tracker did so far, counted over its frames (as Open3D's ``RegistrationResult`` reports a fit).

    net_runs, net_replaced, net_ms : safety-net searches, how often their estimate won, their time (ms)
    net_anchored, net_placed : searches from the tracked pose, and from placements in the cloud
    net_cut : frames whose net searches were cut short by ``start.search_budget_ms``
    net_wrong_way, wrist_tests : frames doubtful for a hand pointing against the arm; wrong-way tests
        run in full
    recentred : predictions moved onto the cloud
    unseen_frames : frames whose unseen joints were pulled (``refine.unseen_prior``)
    no_hand, too_few, size_out : starts that found no hand; of them, regions too small to start from,
        and sizes at an end of ``scale.range``
    size_starts : size-refining searches whose fit replaced the tracked one
    rgb_seeds, rgb_kept : start searches seeded by colour keypoints; how often the seed alone won
    detector_seeds : hands fitted to the depth keypoint detector's keypoints (``start.detector``: starts,
        size calibrations, the safety net's searches beyond the tracked pose)
    detector_starts : starts whose detected hand's first fit scored well enough that the full search did
        not run (``start.detector_accept_mm``)
    searches, searches_cut, search_ms : start searches, of them cut short by ``start.search_budget_ms``,
        their time (ms)
    not_hands : starts whose region the hand-presence network called no hand (``start.presence``): no
        search ran
    hands_fitted : starts the network called no hand where the detected hand fitted the region as an
        accepted start does (:meth:`StartSearch.detected_fits`): searched as hands
    wrist_cuts : frames whose points behind the detected wrist were left out (``start.detector_wrist_m``)
    jumps_refused : tracked frames whose points the prediction missed, or whose fit the safety net doubted,
        and whose region the hand-presence network called no hand: the prediction output (status
        ``"predicted"``), nothing fitted or searched
    surface_starts : starts whose region the hand-presence network called no hand, begun instead on the hand
        the keypoint CNN found along that region's surface (``FrameTracker._hand_along_surface``; not counted
        in ``not_hands``)
    keypoint_frames : tracked frames fitted with the detected keypoints' term (``refine.keypoints``)
    """

    net_runs: int = 0
    net_replaced: int = 0
    net_ms: float = 0.0
    net_anchored: int = 0
    net_placed: int = 0
    net_cut: int = 0
    net_wrong_way: int = 0
    wrist_tests: int = 0
    recentred: int = 0
    unseen_frames: int = 0
    no_hand: int = 0
    too_few: int = 0
    size_out: int = 0
    size_starts: int = 0
    rgb_seeds: int = 0
    rgb_kept: int = 0
    detector_seeds: int = 0
    detector_starts: int = 0
    searches: int = 0
    searches_cut: int = 0
    search_ms: float = 0.0
    not_hands: int = 0
    hands_fitted: int = 0
    wrist_cuts: int = 0
    jumps_refused: int = 0
    surface_starts: int = 0
    keypoint_frames: int = 0

    def snapshot(self) -> "TrackerStats":
        """A copy (each frame's result carries one: ~4 µs, where ``dataclasses.replace`` takes ~15)."""
        out = object.__new__(TrackerStats)
        out.__dict__.update(self.__dict__)
        return out


class FramePart(Protocol):
    """A named part of the per-frame pipeline: built from its settings, counting into ``stats``."""

    stats: TrackerStats

    def reset(self) -> None:
        """Forget the sequence (a fresh start follows)."""


class WristCue:
    """The frame's wrist cue (:func:`tracker.wrist.wrist_cue`) when an arm's worth of surface lies
    behind it (:func:`tracker.wrist.arm_behind`), found once per frame and kept on its silhouette
    (``enabled``: :attr:`tracker.settings.StartSettings.wrist_cue`)."""

    def __init__(self, enabled: bool, stats: TrackerStats | None = None):
        self.enabled, self.stats = enabled, stats or TrackerStats()

    def reset(self):
        pass

    def of(self, sil):
        """The cue of the frame of ``sil``, or None (found once per frame: kept on the silhouette as
        ``arm_cue``, which :func:`tracker.init.score` does not read)."""
        if sil is None or not self.enabled:
            return None
        if not hasattr(sil, "arm_cue"):
            frame = getattr(sil, "frame_depth", None)
            cue = None
            if frame is not None and not sil.empty:
                # the net tests every tracked frame: a hand with no surface right past its outline (a
                # hand alone) has no wrist line, which the silhouette's distance transform tells
                # (compiled, stops at the first such pixel: ~5 µs; wrist_cue takes ~0.2 ms there)
                if surface_past_outline(sil.dist, frame, int(sil.v0), int(sil.u0), 2.0):
                    cue = wrist_cue(sil.mask, frame, sil.camera)
            sil.arm_cue = cue if cue is None or arm_behind(cue, sil.mask, frame, sil.camera) else None
        return sil.arm_cue

    def add(self, sil):
        """Put the frame's cue on ``sil`` where :func:`tracker.init.score` finds it (``sil.wrist``; added
        only when a search is about to run: tracking does not score by it)."""
        if sil is not None and self.enabled and not hasattr(sil, "wrist"):
            sil.wrist = self.of(sil)


class Recentring:
    """The prediction moved onto the cloud when their centres are farther apart than the rejection
    radius ``reject_mm`` (a hand faster than the prediction: no correspondence would reach it). The
    cloud is the near side of the hand, so only the model's camera-facing samples are its counterpart."""

    def __init__(self, reject_mm: float, stats: TrackerStats | None = None):
        self.reject_mm, self.stats = reject_mm, stats or TrackerStats()

    def reset(self):
        pass

    def __call__(self, hand, samples, pred, pts, posed=None):
        """``pred`` itself, or a moved copy (``samples``: the context's score samples; ``posed``: them
        posed at ``pred``, :func:`tracker.icp.posed_samples`, when at hand)."""
        shift = centre_shift(pts, posed_samples(hand, samples, pred) if posed is None else posed)
        if shift is None or np.linalg.norm(shift) * 1000.0 <= self.reject_mm:
            return pred
        self.stats.recentred += 1
        out = pred.copy()
        out[:3] += shift
        return out


class UnseenPrior:
    """Joints without data pulled towards their most likely values given the seen ones: the synergy
    model's Gaussian conditional mean (:attr:`tracker.settings.RefineSettings.unseen_prior`). Off (θ
    unchanged) without synergies, in reduced mode or with ``unseen_prior`` 0."""

    def __init__(self, hand, synergies, settings, mode: str, stats: TrackerStats | None = None):
        self.settings, self.stats = settings, stats or TrackerStats()
        self.on = bool(settings.unseen_prior) and synergies is not None and mode != "reduced"
        self.hidden_ = True  # whether the last fit left a posture DoF without data (unknown: True)
        self.hidden_nodes_ = None  # the nodes such DoF move (None: unknown)
        self.moves_, self.mean_, self.cov_ = _unseen_parts(hand, synergies) if synergies is not None else (None,) * 3

    def reset(self):
        pass

    def __call__(self, hand, theta, corr, limits, share=None) -> np.ndarray:
        """θ with the posture DoF that no data point constrains (fewer than ``unseen_points`` valid pairs
        of ``corr`` on the parts it moves) moved ``unseen_prior`` (``share`` when given) of the way to
        the conditional mean given the other posture DoF. Unchanged when every DoF, or none, is seen
        (nothing to condition on). Records in ``hidden_`` whether any DoF was unseen and in ``hidden_nodes_``
        the nodes those move (with synergies, when the prior or the keypoint term, ``keypoints.on``, is on:
        the term asks them)."""
        if self.moves_ is None or not (self.on or self.settings.keypoints.on):
            return theta  # neither the prior nor the keypoint term asks which joints the data left unseen
        counts = np.bincount(corr.nodes[corr.valid], minlength=hand.n_nodes)
        hid = self.moves_ @ counts < self.settings.unseen_points
        self.hidden_ = bool(hid.any())
        # the nodes a hidden DoF moves: their keypoints are the prior's to fill, not the keypoint term's
        self.hidden_nodes_ = (self.moves_[hid] > 0).any(axis=0)
        if not self.on or not hid.any() or hid.all():
            return theta
        seen, mu, S = ~hid, self.mean_, self.cov_
        post = np.flatnonzero(~hand.pose_mask)
        x = theta[post]
        cond = mu[hid] + S[np.ix_(hid, seen)] @ np.linalg.solve(S[np.ix_(seen, seen)], x[seen] - mu[seen])
        out = np.array(theta, float)
        idx = post[hid]
        share = self.settings.unseen_prior if share is None else share
        out[idx] = np.clip(x[hid] + share * (cond - x[hid]), limits[idx, 0], limits[idx, 1])
        self.stats.unseen_frames += 1
        return out


def _unseen_parts(hand, synergies):
    """``(moves, mean, covariance)`` of :class:`UnseenPrior`: ``moves (20, nodes)`` is 1 where a posture
    DoF moves a node (the node it drives and every node below it); the covariance is the synergy
    model's over all its components, with a small ridge (1e-4 rad²) so that the seen joints' block is
    always invertible."""
    moves = hand.dof_moves[~hand.pose_mask].astype(float)
    m = synergies.model
    C, lam = np.asarray(m.all_components_, float), np.asarray(m.all_explained_variance_, float)
    S = C.T @ (lam[:, None] * C) + 1e-4 * np.eye(C.shape[1])
    return moves, np.asarray(m.mean_, float), S


class FingerRestart:
    """A tracked fit whose fingers break their last joints' coupling refitted from the coupled angles,
    kept when it scores clearly better (:func:`tracker.coupling.restart_uncoupled`;
    :class:`tracker.settings.RefineSettings` ``finger_restart_deg``, ``finger_bent_back_deg``; off in
    reduced mode)."""

    def __init__(self, settings, mode: str, stats: TrackerStats | None = None):
        self.settings, self.stats = settings, stats or TrackerStats()
        self.on = bool(settings.finger_restart_deg) and mode != "reduced"

    def reset(self):
        pass

    def __call__(self, hand, theta, corr, refit, score, limits):
        """``(θ, corr)``: ``refit(start)`` fits from a start, ``score(θ, corr)`` judges."""
        if not self.on:
            return theta, corr
        st = self.settings
        theta, corr, _ = restart_uncoupled(hand, theta, corr, refit, score, limits, tolerance_deg=st.finger_restart_deg,
                                           bent_back_deg=st.finger_bent_back_deg or None)
        return theta, corr


class LossCheck:
    """When a frame is lost, and when a start found no hand (:class:`tracker.settings.LossSettings`;
    ``scale_range``: the sizes an automatic calibration searches)."""

    def __init__(self, settings, scale_range=(0.6, 2.0), stats: TrackerStats | None = None):
        self.settings, self.scale_range, self.stats = settings, scale_range, stats or TrackerStats()

    def reset(self):
        pass

    def too_small(self, n_points, sil) -> bool:
        """Whether a start's region is too small to start a hand from (``start_min_pixels``): 26 DoF fitted
        to a few dozen points fit anything. The region's pixels, not its points (a coarse stride, Fig. 9's
        1/36, samples a whole hand sparsely); its points without a mask."""
        if not self.settings.start_min_pixels:
            return False
        region = n_points if sil is None or sil.empty else int(np.count_nonzero(sil.mask))
        return region < self.settings.start_min_pixels

    def found_nothing(self, corr) -> bool:
        """Whether a start's fit (its pairs ``corr``) rejects more than ``no_hand_rejected`` of its points:
        what it fitted is no hand."""
        limit = self.settings.no_hand_rejected
        return bool(limit) and len(corr.valid) > 0 and corr.rejected_share > limit

    def size_out(self, s) -> bool:
        """Whether a calibrated size ``s`` lies at an end of ``scale_range`` (within 1 %): what was
        fitted is beyond the sizes of hands (a shoulder left in by a ``--box`` fitted at 2.0×, the
        range's end; the 19 SR305 stills: 1.21–1.31×). Off with ``no_hand_rejected`` 0."""
        lo, hi = self.scale_range
        return bool(self.settings.no_hand_rejected) and not lo * 1.01 < s < hi / 1.01

    def no_hand_sized(self, s, corr) -> bool:
        """Whether a calibrating start (size ``s``, pairs ``corr``) found no hand: its size at an end of the
        range (counted in ``stats.size_out``) or its fit's rejections."""
        out = self.size_out(s)
        self.stats.size_out += out
        return out or self.found_nothing(corr)

    def kept(self, fit_mm, rejected) -> bool:
        """Whether a fit is good enough to track from (not lost): ``lost_fit_mm``, ``lost_rejected``."""
        st = self.settings
        return bool(np.isfinite(fit_mm) and fit_mm <= st.lost_fit_mm and rejected <= st.lost_rejected)


class HandPresence:
    """Whether a start's region is a hand at all, asked of the hand-presence network
    (:mod:`tracker.hand_presence`, ``start.presence``) before any search: a region it calls no hand
    (probability below ``below``) is "no hand" without a search, counted in ``stats.not_hands``, unless
    the model fit says otherwise (``fits``: :meth:`StartSearch.detected_fits`, counted in
    ``stats.hands_fitted``); the last answer is ``probability_`` (NaN: the region had no box, or the
    frame no depth). ``region(sil, hand)``: a narrower mask to ask it on (:meth:`KeypointSeed.region`), or
    None."""

    def __init__(self, model, below: float, stats: TrackerStats | None = None, region=None):
        self.model, self.below, self.stats = model, float(below), stats or TrackerStats()
        self.region = region  # region(sil, hand): the keypoint detector's narrowed mask, or None
        self.probability_ = float("nan")

    def reset(self):
        pass

    def absent(self, sil, hand: str, fits=None, *, counted: bool = True) -> bool:
        """Whether the frame's :class:`tracker.correspond.Silhouette` region is no hand (False where it
        cannot be asked: no mask, no depth or no camera), asked as the keypoint detector is
        (:func:`tracker.keypoint_fit.detect_in`: the whole frame's depth, the segmentation as the mask).
        ``fits()``: whether a hand fitted to the region all the same, asked only when the network says no.
        ``counted``: the answer counts in ``stats`` (a start's; a tracked frame's jump counts its own)."""
        # loaded with the network only: a run without detectors loads none (test_startup)
        from .hand_presence import hand_probability
        from .keypoint_fit import detect_in

        # a region narrowed to the hand by the keypoint CNN's re-crop (a forearm's length kept by the
        # segmentation) is asked as the network was trained: a box about one hand long
        narrowed = None if self.region is None else self.region(sil, hand)
        p = detect_in(partial(hand_probability, model=self.model), sil, hand, mask=narrowed)
        self.probability_ = float("nan") if p is None else p
        absent = bool(self.probability_ < self.below)  # NaN: no answer, not "no hand"
        if absent and fits is not None and fits():
            # two answers to one question: the network's misses (a fist seen from its back without the
            # arm, 0.01-0.07) are fitted within 0.7 mm; none of the 38 regions it turned away on the harder
            # scenes' starts (a forearm's end, a torso's edge), nor a real wall's edge, fits within the
            # threshold (docs/experiments/detector.md, "On by default: the model fit overrules the network")
            self.stats.hands_fitted += counted
            return False
        self.stats.not_hands += absent and counted
        return absent


def silhouette_mask(observation):
    """The mask an observation's silhouette term fits: its mask widened by the sensor's dropout band
    (:func:`tracker.observe.dropout_band`) where it has one."""
    return observation.mask if observation.silhouette is None else observation.silhouette


def frame_silhouette(mask, depth, camera, frame_depth):
    """The :class:`~tracker.correspond.Silhouette` of a frame (None without a mask, depth or camera),
    carrying the whole frame's depth for the wrist cue."""
    if mask is None or camera is None or depth is None:
        return None
    sil = Silhouette(mask, depth, camera)
    sil.frame_depth = frame_depth
    return sil


def usable_points(points, normals, max_points):
    """Finite points (at most ``max_points``, evenly spread) and their normals; NaN normals (unknown)
    stay: the normal test is skipped for them."""
    pts = np.asarray(points, float).reshape(-1, 3)
    if np.isfinite(pts).all() and not (max_points and len(pts) > max_points):
        # every point finite, none to drop: copies, as the selection below makes (~20 µs a frame less)
        return pts.copy(), None if normals is None else np.asarray(normals, float).reshape(-1, 3).copy()
    keep = np.isfinite(pts).all(1)
    if max_points and keep.sum() > max_points:
        idx = np.flatnonzero(keep)
        keep[:] = False
        keep[idx[np.linspace(0, len(idx) - 1, max_points).astype(int)]] = True
    nrm = None if normals is None else np.asarray(normals, float).reshape(-1, 3)[keep]
    return pts[keep], nrm


class Gate:
    """While tracking, the points near the hand predicted for the frame only
    (:func:`tracker.observe.predicted_near`, ``observe.gate_mm``; a table, torso or object the
    segmentation left cannot pull the fit), and those past its wrist out of the fit
    (:func:`tracker.observe.past_wrist`, ``observe.arm_gate_mm``; ``arm``: only where the safety net's
    far-points test runs, which sees the hand cut off past a wrong wrist)."""

    def __init__(self, observe, min_points: int, arm: bool, stats: TrackerStats | None = None):
        self.observe, self.min_points, self.stats = observe, min_points, stats or TrackerStats()
        self.on = observe.gate_mm > 0
        # without the net's far-points test nothing would see the hand cut off past a wrong wrist
        # (fast and turning hands alone without the net: 32.0 -> 35.4 and 26.7 -> 32.0 deg)
        self.arm = arm and observe.arm_gate_mm is not None

    def reset(self):
        pass

    def __call__(self, hand, samples, pred, pts, posed=None):
        """``(keep, arm)``: the points near the hand at ``pred`` (all True when the prediction is not
        trusted), and those of them past its wrist (None when off, not trusted, none is past or too few
        would remain). ``posed``: the ``samples`` posed at ``pred`` when at hand."""
        ob = self.observe
        P, N = posed_samples(hand, samples, pred) if posed is None else posed
        near = predicted_near(pts, P, ob.gate_mm / 1000.0, normals=N, min_share=ob.gate_min_share,
                              min_points=self.min_points)
        if near is None:
            return np.ones(len(pts), bool), None
        if not self.arm:
            return near, None
        G = hand.node_frames(pred)
        axis = G[hand.joint_indices[0], :3, 1]  # the root joint's frame: the hand's direction
        arm = near & past_wrist(pts, hand.wrist_crease(pred, frames=G), axis, ob.arm_gate_mm / 1000.0)
        if not arm.any() or np.count_nonzero(near & ~arm) < max(self.min_points, 1):
            return near, None
        return near, arm


class ColourSeed:
    """Start searches seeded by the hand fitted to the colour keypoints (:class:`tracker.rgb.RgbSeed`,
    ``start.rgb_seed``; ``detector``: instead of MediaPipe)."""

    def __init__(self, detector=None, stats: TrackerStats | None = None):
        self.rgb, self.stats = RgbSeed(detector), stats or TrackerStats()

    def reset(self):
        pass

    def start(self, hand, color, depth, camera) -> tuple:
        """``(θ,)`` fitted to the frame's colour keypoints, or ``()`` (no colour, no hand found)."""
        if color is None or depth is None or camera is None:
            return ()
        th = self.rgb(hand, color, depth, camera)
        if th is None:
            return ()
        self.stats.rgb_seeds += 1
        return (th,)

    def refine(self, refit, seed, theta, corr):
        """The seed refitted by the tracking ICP (``refit(seed)``) kept over the search's winner when the
        depth fits it at least as well (fit error no higher, no more than 5 % more points rejected).
        Not by :func:`tracker.init.score`: a hand turned over explains the depth about as well, and the
        score's wrist cue can favour it; the colour image sees which way the hand faces."""
        th, c = refit(seed)
        if (np.all(np.isfinite(th)) and c.fit_error_mm() <= corr.fit_error_mm()
                and c.valid.mean() >= corr.valid.mean() - 0.05):
            self.stats.rgb_kept += 1
            return th, c
        return theta, corr


def depth_detector(name: str):
    """The depth keypoint detector called ``name`` as ``detect(depth_m, camera, mask, hand) -> Detection``:
    a model file or name under ``models/detectors/`` — the ONNX keypoint CNN (:mod:`tracker.keypoint_cnn`,
    onnxruntime) for ``.onnx`` files and names starting with ``hand-keypoints``, else the hand-part
    forest (:mod:`tracker.detector`). Loaded here, once: a missing or damaged file is a
    :class:`tracker.errors.TrackerError` when the tracker is built, not on its first start."""
    if str(name).endswith(".onnx") or str(name).startswith("hand-keypoints"):
        from .keypoint_cnn import detect, load_cnn

        return partial(detect, detector=load_cnn(name))
    from .detector import detect, load_detector

    return partial(detect, detector=load_detector(name))


class KeypointSeed:
    """The hand fitted to a depth keypoint detector's keypoints (``start.detector``):
    ``detect(depth_m, camera, mask, hand) -> tracker.detector.Detection`` on the frame and its
    segmentation, :func:`tracker.keypoint_fit.fit_start` (with the synergy bundle, the subspace fills the
    fingers it did not find). The searches start from it first (:func:`tracker.init.seeded_search`: the
    start, the size calibration, the safety net's search beyond the tracked pose), as Sharp et al. 2015
    start their model fit from a learned re-initialiser's proposals."""

    def __init__(self, detect, synergies=None, stats: TrackerStats | None = None):
        self.detect, self.synergies, self.stats = detect, synergies, stats or TrackerStats()

    def reset(self):
        pass

    @property
    def model(self):
        """The loaded detector (its ``manifest`` names it), or None for a ``detect`` given in code."""
        return getattr(self.detect, "keywords", {}).get("detector")

    def start(self, hand, sil) -> tuple:
        """``(θ,)`` fitted to the keypoints detected in the frame's hand region, or ``()``."""
        return self.fit(self.detection(sil, hand.handedness), hand)

    def detection(self, sil, handedness: str):
        """The detector's answer on the frame of ``sil`` (:func:`tracker.keypoint_fit.detect_in`), or None;
        found once per frame and hand side (kept on the silhouette as ``detected``: the presence
        test's fit, the start and the size calibration ask for it)."""
        from .keypoint_fit import detect_in

        kept = getattr(sil, "detected", None)
        if kept is None or kept[0] != handedness:
            kept = (handedness, detect_in(self.detect, sil, handedness))
            if sil is not None:
                sil.detected = kept
        return kept[1]

    def region(self, sil, handedness: str):
        """The mask the detector narrowed the frame's region to (:attr:`tracker.detector.Detection.region`),
        or None (nothing detected, or the whole region kept)."""
        det = self.detection(sil, handedness)
        return None if det is None else det.region

    def fit(self, detection, hand) -> tuple:
        """``(θ,)`` of ``hand`` fitted to a ``detection`` (None: nothing detected), or ``()``; counted in
        ``stats.detector_seeds``."""
        from .keypoint_fit import fit_start

        th = None if detection is None else fit_start(detection, hand, self.synergies)
        if th is None:
            return ()
        self.stats.detector_seeds += 1
        return (th,)


class Prediction:
    """The start of a tracked frame's fit and the points it fits (:class:`tracker.settings.PredictSettings`):
    the last θ moved on by its last change, the points gated by the hand predicted there (``gate``)
    and the prediction moved onto the cloud when it missed it (``recentring``)."""

    def __init__(self, settings, gate: Gate, recentring: Recentring, stats: TrackerStats | None = None):
        self.settings, self.gate, self.recentring = settings, gate, recentring
        self.stats = stats or TrackerStats()

    def reset(self):
        pass

    def theta(self, theta, prev, hand, limits, components=None) -> np.ndarray:
        """The last θ plus ``share`` × its last change (``prev`` → ``theta``), except the global rotation
        (as the original code); with ``components`` (reduced mode's PCs) the posture moves along them
        only (hierarchical mode predicts all DoF: motion outside the synergies is real motion there)."""
        out = theta.copy()
        if self.settings.share and prev is not None:
            step = (theta - prev) * float(self.settings.share)
            step[3:6] = 0.0
            post = ~hand.pose_mask
            if components is not None:
                step[post] = (step[post] @ components.T) @ components
            out = out + step
            out[post] = np.clip(out[post], limits[post, 0], limits[post, 1])
            if self.settings.turn:
                out[3:6] = turned_on(theta[3:6], prev[3:6], float(self.settings.share))
        return out

    def points(self, hand, samples, pred, pts, nrm):
        """``(pred, recentred, fit_points, fit_normals, points, normals)``: the prediction (re-centred or
        not), the points the fit takes and those the safety net tests and searches."""
        recentred = False
        # clutter the segmentation left beside the hand (table, torso, arm) cannot pull the fit; the
        # gate tests the prediction first, so that clutter cannot re-centre a prediction that was right
        # the samples posed once for the gate and the re-centring
        posed = posed_samples(hand, samples, pred) if self.gate.on or self.settings.recentre else None
        keep, arm = self.gate(hand, samples, pred, pts, posed) if self.gate.on else (None, None)
        if self.settings.recentre and (keep is None or keep.all()):
            moved = self.recentring(hand, samples, pred, pts, posed)
            recentred, pred = moved is not pred, moved
            if recentred and keep is not None:
                keep, arm = self.gate(hand, samples, pred, pts)
        if keep is not None:
            # the safety net searches the gated cloud too (a start search on the whole cloud would
            # find the clutter); the gate keeps every point when it does not trust the prediction
            pts, nrm = pts[keep], None if nrm is None else nrm[keep]
        all_pts, all_nrm = pts, nrm
        if arm is not None:
            # the arm left past the predicted wrist is out of the fit (a closing fist followed it down
            # the arm) but not out of the net's tests and search: past a wrong prediction's wrist lies
            # the hand itself, which only the points far from the fit then tell
            fit_keep = ~arm[keep]
            pts, nrm = all_pts[fit_keep], None if all_nrm is None else all_nrm[fit_keep]
        return pred, recentred, pts, nrm, all_pts, all_nrm


class StartSearch:
    """A frame fitted without one before it (the first, after a loss): the single-frame search
    (:func:`tracker.init.fit_single_frame`, ``init``) from the last good θ, the colour seed
    (``colour``) and the depth keypoint detector's (``keypoints``, :class:`KeypointSeed`), its last fits
    holding the hand's wrist crease on the arm's line (the frame's ``cue``;
    :class:`tracker.icp.IcpSettings` ``wrist_line_weight``). With a detected hand the search goes
    :func:`tracker.init.seeded_search`'s way: the detected hand first, the full search only when that
    scores above ``accept_mm``."""

    def __init__(self, init, cue: WristCue, colour: ColourSeed | None = None, stats: TrackerStats | None = None,
                 budget_ms: float = 0.0, keypoints: KeypointSeed | None = None, accept_mm: float = 0.0):
        self.init, self.cue, self.colour, self.stats = init, cue, colour, stats or TrackerStats()
        self.budget_ms, self.keypoints, self.accept_mm = budget_ms, keypoints, float(accept_mm)

    def reset(self):
        pass

    def detected_fits(self, ctx, context_for, pts, nrm, sil, scale_range=(0.6, 2.0)) -> bool:
        """Whether the detector's hand, fitted to this frame's region (one fit from the hand fitted to its
        keypoints, the search's ``icp_iterations``), scores at most ``accept_mm`` (:func:`tracker.init.score`):
        as well as a start accepted without the full search. On ``ctx``'s hand; with ``ctx`` None (the size
        not known yet) at the size calibration's first guesses (:func:`tracker.scale.first_sizes`) through
        ``context_for(scale)``, the first that fits. False without a detector, a detection or a threshold."""
        if self.keypoints is None or not self.accept_mm:
            return False
        from .keypoint_fit import fit_start, keypoint_scale
        from .scale import first_sizes

        det = self.keypoints.detection(sil, (ctx or context_for(1.0)).hand.handedness)
        if det is None:
            return False
        if ctx is None:
            base = context_for(1.0)
            sizes = first_sizes(base, pts, keypoint_scale(det, base.hand), scale_range)
        for c in [ctx] if ctx is not None else (context_for(s) for s in sizes):  # a size's context only if asked
            seed = fit_start(det, c.hand, self.keypoints.synergies)
            if seed is None:
                continue
            # one fit, not seeded_search's first step with its synergy starts (~20 ms): the same answers on the fists from the back
            # (0.63-0.67 against 0.60-0.61 mm) and the real hand-less frames (8-13 against 7-10 mm), ~2 ms
            theta, corr = c.fit(seed, pts, "full", 1, self.init.icp_iterations, silhouette=sil, normals=nrm,
                                wrist=self.cue.of(sil))
            if score(c, theta, corr, sil) <= self.accept_mm:
                return True
        return False

    def __call__(self, ctx, pts, nrm, sil, last_good, refit, color=None, depth=None, camera=None):
        """``(θ, corr)`` on ``ctx``'s hand; ``refit(start)``: the tracking ICP the colour seed is refined by."""
        budget = SearchBudget(self.budget_ms)  # the seeds' detection and fits count too
        extra = () if last_good is None else (last_good,)
        seed = () if self.colour is None else self.colour.start(ctx.hand, color, depth, camera)
        self.cue.add(sil)
        found = () if self.keypoints is None else self.keypoints.start(ctx.hand, sil)
        # a size calibration's fits do not hold the crease (it moved a real recording's calibrated size,
        # 1.276 → 1.256, and tips by up to 40 px), nor the net's, whose result is compared with the tracked fit's
        if found:
            theta, corr, searched = seeded_search(ctx, pts, self.init, found[0], accept_mm=self.accept_mm,
                                                  silhouette=sil, normals=nrm, extra=extra + seed,
                                                  wrist=self.cue.of(sil), budget=budget)
            self.stats.detector_starts += not searched
        else:
            theta, corr = fit_single_frame(ctx, pts, self.init, silhouette=sil, normals=nrm, extra=extra + seed,
                                           wrist=self.cue.of(sil), budget=budget)
            searched = True
        self.stats.searches += searched
        self.stats.searches_cut += bool(budget.cut_)
        self.stats.search_ms += budget.elapsed_ms
        if seed:
            theta, corr = self.colour.refine(refit, seed[0], theta, corr)
        return theta, corr
