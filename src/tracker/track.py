"""Pipeline stage ``track``: :class:`FrameTracker`, the per-frame loop — observe → predict → fit →
check → refine → decide — as state plus named parts (:mod:`tracker.parts`, :mod:`tracker.net`,
:mod:`tracker.sizing`), each built from its group of :class:`tracker.settings.TrackerSettings`.

The stages it drives: :mod:`tracker.observe` → :mod:`tracker.segment` → :mod:`tracker.correspond` →
:mod:`tracker.icp` → :mod:`tracker.init`; :mod:`tracker.run` runs it over a recording.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from functools import partial
from typing import NamedTuple

import numpy as np

from handmodel.rigid import wrapped_angles

from .errors import TrackerError
from .icp import fit, posed_samples, tracking_schedule
from .init import fit_single_frame, score
from .net import SafetyNet
from .observe import hand_window
from .parts import depth_detector as load_depth_detector
from .parts import (
    ColourSeed,
    FingerRestart,
    Gate,
    HandPresence,
    KeypointSeed,
    LossCheck,
    Prediction,
    Recentring,
    StartSearch,
    TrackerStats,
    UnseenPrior,
    WristCue,
    frame_silhouette,
    silhouette_mask,
    usable_points,
)
from .resize import shaped_context
from .settings import TrackerSettings
from .sizing import HandSizes, SizeCalibration, fit_context
from .wrist import ahead_of_wrist


@dataclass
class HandCheck:
    """The first frame fitted with the hand tracked and with its mirror image: their start-search
    scores (mm, lower is better; :func:`tracker.init.score`) and the other hand's side.

    >>> str(HandCheck(2.57, 2.58, "right"))
    'score 2.57, right hand 2.58: the two hands fit alike, the depth cannot tell them apart'
    >>> str(HandCheck(5.24, 2.82, "right"))
    "score 5.24, right hand 2.82: the right hand fits clearly better: is the recording's handedness wrong?"
    >>> str(HandCheck(2.82, 5.24, "left"))
    'score 2.82, left hand 5.24: ok'
    """

    score: float
    other_score: float
    other_side: str

    @property
    def other_fits_better(self) -> bool:
        """The other hand clearly better: by 0.5 mm and by a third of the score (a fit of the wrong hand
        can be nearly as good; a clearly worse one is the wrong hand, not noise)."""
        return self.other_score < self.score - 0.5 and self.other_score < 0.67 * self.score

    @property
    def alike(self) -> bool:
        """Neither hand clearly better: the scores within 15 % of the lower one. A flat open hand's
        depth is the same mirrored and turned over (the 8 open hands of the labelled SR305 frames:
        the left hand scored within 0.4–9 % of the right one, 0.2–3.5 % on 7 of them)."""
        return not self.other_fits_better and abs(self.score - self.other_score) < 0.15 * min(self.score, self.other_score)

    def __str__(self) -> str:
        if self.other_fits_better:
            verdict = f"the {self.other_side} hand fits clearly better: is the recording's handedness wrong?"
        elif self.alike:
            verdict = "the two hands fit alike, the depth cannot tell them apart"
        else:
            verdict = "ok"
        return f"score {self.score:.2f}, {self.other_side} hand {self.other_score:.2f}: {verdict}"


@dataclass
class FrameResult:
    theta: np.ndarray
    status: str                 # tracked | lost | reinit
    fit_mm: float
    points_used: int
    points_in: int
    ms: float
    rejected_share: float = 0.0
    net: str = ""               # the safety net on this frame: "" (not run), "kept" or "replaced"
    stats: TrackerStats | None = None  # the tracker's counts after this frame


class FrameFit(NamedTuple):
    """A frame's fit on its way through :meth:`FrameTracker.step`: θ and its pairs, the status so far
    (``"reinit"`` for a start or the net's replacement), what the net did, whether the prediction was
    re-centred, whether the fit left the cloud far away (reduced mode), and the points it fitted."""

    theta: np.ndarray
    corr: object
    status: str
    net: str
    recentred: bool
    far_lost: bool
    points: np.ndarray
    normals: np.ndarray | None


#: A hand looked for along a turned-away region's surface (:meth:`FrameTracker._hand_along_surface`) is
#: taken only where the hand-presence network calls it a hand more likely than not: a region the
#: segmentation offered is turned away only below ``start.presence_below`` (0.05), but one we went looking
#: for must be a hand by the network's own decision point (a real wall's edge, librealsense's sample bag:
#: a hand-sized patch of it scored above 0.05).
SURFACE_HAND_P = 0.5


def check_hand(ctx, settings, synergies, pts, nrm, sil, theta, corr) -> HandCheck:
    """:class:`HandCheck` of a frame's fit (``theta``, ``corr`` on ``ctx``'s hand) against the single-frame
    search with the mirror-image hand (same size)."""
    other = ctx.hand.mirrored()
    octx, _ = fit_context(other, settings, synergies)
    th, c = fit_single_frame(octx, pts, settings.init, silhouette=sil, normals=nrm)
    return HandCheck(score(ctx, theta, corr, sil), score(octx, th, c, sil), other.handedness)


@dataclass(frozen=True)
class Predicted:
    """A tracked frame not fitted: its output is the prediction ``theta`` (:meth:`FrameTracker._not_a_hand`)."""

    theta: np.ndarray


def _output_theta(theta) -> np.ndarray:
    """A copy of θ as a frame's result gives it: the global rotation in [−π, π) (the tracker's own θ
    keeps its turns: its fits start from it)."""
    out = np.array(theta, float)
    out[3:6] = wrapped_angles(out[3:6])
    return out


def frame_result(stats, n_dofs, theta, status, n_in, t0, fit_mm=float("nan"), used=0, rejected=1.0,
                 net="") -> FrameResult:
    """A frame's :class:`FrameResult`: θ as output (NaN when the frame gives none), the time since ``t0``
    and a snapshot of the tracker's ``stats`` after the frame."""
    out = np.full(n_dofs, np.nan) if theta is None else _output_theta(theta)
    return FrameResult(out, status, fit_mm, used, n_in, (time.perf_counter() - t0) * 1e3, rejected, net,
                       stats.snapshot())


def no_hand(stats, n_dofs, corr, n_in, t0, *, small=None) -> FrameResult:
    """The result of a frame whose start found no hand (``corr``: its fit's pairs, None when no fit was
    made), counted in ``stats``: lost, no θ. ``small``: the region was too small to fit (default: no fit
    was made; a region the hand-presence network turned away was not small)."""
    stats.no_hand += 1
    stats.too_few += corr is None if small is None else small
    return frame_result(stats, n_dofs, None, "lost", n_in, t0, rejected=1.0 if corr is None else corr.rejected_share)


class TrackerParts(NamedTuple):
    """The named parts of a :class:`FrameTracker` (:func:`build_parts`)."""

    cue: WristCue
    net: SafetyNet
    gate: Gate
    recentring: Recentring
    prediction: Prediction
    prior: UnseenPrior
    restart: FingerRestart
    loss: LossCheck
    sizing: SizeCalibration
    colour: ColourSeed | None
    search: StartSearch
    sizes: HandSizes
    presence: HandPresence | None


def build_parts(hand, settings: TrackerSettings, synergies, stats: TrackerStats, keypoint_detector=None,
                depth_detector=None) -> TrackerParts:
    """The parts tracking ``hand`` with ``settings`` (checked), each built from its settings group and
    counting into ``stats``; the arguments as :class:`FrameTracker`'s. Raises
    :class:`tracker.errors.TrackerError` when the mode needs the synergy bundle and none is given."""
    st = settings
    st.check()
    if st.mode != "full" and synergies is None:
        raise TrackerError("synergies", f"mode {st.mode!r} needs a synergy bundle (--synergies)")
    cue = WristCue(st.start.wrist_cue, stats)
    gate = Gate(st.observe, st.loss.min_points, st.net.enabled and st.mode != "reduced", stats)
    recentring = Recentring(st.correspond.reject_mm, stats)
    prediction = Prediction(st.predict, gate, recentring, stats)
    prior = UnseenPrior(hand, synergies, st.refine, st.mode, stats)
    restart = FingerRestart(st.refine, st.mode, stats)
    loss = LossCheck(st.loss, st.scale.range, stats)
    sizing = SizeCalibration(st.scale, st.init.sizing(), st.net.margin_mm, stats)
    colour = ColourSeed(keypoint_detector, stats) if st.start.rgb_seed else None
    if depth_detector is None and st.start.detector:
        depth_detector = load_depth_detector(st.start.detector)
    keypoints = None if depth_detector is None else KeypointSeed(depth_detector, synergies, stats)
    net = SafetyNet(st.net, cue, stats, st.start.search_budget_ms, keypoints)
    search = StartSearch(st.init, cue, colour, stats, st.start.search_budget_ms, keypoints,
                         st.start.detector_accept_mm)
    presence = None
    if st.start.presence:
        # loaded when named, as the depth detector is (a run without detectors loads none)
        from .hand_presence import load_presence

        presence = HandPresence(load_presence(st.start.presence), st.start.presence_below, stats,
                                None if keypoints is None else keypoints.region)
    return TrackerParts(cue, net, gate, recentring, prediction, prior, restart, loss, sizing, colour, search,
                        HandSizes(hand, st, synergies), presence)


def tracking_stages(settings: TrackerSettings, context) -> list:
    """The tracking ICP's stages on ``context``'s parametrisations (:func:`tracker.icp.tracking_schedule`)."""
    st = settings.icp
    return tracking_schedule(settings.mode, st.icp_iterations, context.full, context.reduced,
                             projected_steps=st.projected_steps, coarse_iterations=st.coarse_iterations,
                             stages_per_pass=st.stages_per_pass)


def next_window(tracker: FrameTracker, camera):
    """Where to segment ``tracker``'s next frame (``observe(..., window=...)``): :func:`tracker.observe.hand_window`
    of the hand predicted for it, grown by ``observe.window_m``; None — the whole frame — when no hand is
    tracked (not started, lost, its size still being calibrated) or windows are off."""
    st = tracker.settings
    if not st.observe.window_m or tracker.lost or tracker.theta is None or tracker.sizing.calibrating():
        return None
    P, _ = posed_samples(tracker.hand, tracker.context.score_samples, tracker.predict())
    return hand_window(P, camera, st.observe.window_m)


class FrameTracker:
    """Track one hand through a sequence of point clouds (camera frame, metres).

    State (θ, the last θ, lost or not, the hand at its size) plus named parts built from the settings
    groups (:mod:`tracker.parts`, :class:`tracker.net.SafetyNet`, :class:`tracker.sizing.SizeCalibration`),
    counting into one :class:`tracker.parts.TrackerStats` (``stats``, also on every :class:`FrameResult`).

    Parameters
    ----------
    hand : HandModel
    settings : TrackerSettings
    synergies : a synergy bundle (``synergy.bundle.Bundle``) or ``None`` (full mode only)
    keypoint_detector : the colour seed's detector instead of MediaPipe (``start.rgb_seed``)
    depth_detector : ``detect(depth_m, camera, mask, hand) -> Detection`` seeding the start searches, instead
        of the one ``start.detector`` names (:class:`tracker.parts.KeypointSeed`)

    Attributes
    ----------
    hand : the model tracked, ``base_hand`` at the size in use
    scale_, scale_estimates_, finger_scales_, finger_spread_, calibrated_each_ : the size
        (:class:`tracker.sizing.SizeCalibration`)
    hand_check_ : :class:`HandCheck` of the first frame (``start.check_hand``), else None
    colour : the :class:`tracker.parts.ColourSeed` with ``start.rgb_seed``, else None
    """

    def __init__(self, hand, settings: TrackerSettings | None = None, synergies=None, keypoint_detector=None,
                 depth_detector=None):
        self.base_hand, self.synergies, self.hand_check_ = hand, synergies, None
        self.settings = settings or TrackerSettings()
        self.stats = TrackerStats()
        (self.cue, self.net, self.gate, self.recentring, self.prediction, self.prior, self.restart, self.loss,
         self.sizing, self.colour, self.search, self.sizes, self.presence) = build_parts(hand, self.settings, synergies, self.stats,
                                                                          keypoint_detector, depth_detector)
        self.use_scale(1.0 if self.sizing.scale_ is None else self.sizing.scale_)
        self.reset()

    scale_ = property(lambda self: self.sizing.scale_)
    scale_estimates_ = property(lambda self: self.sizing.scale_estimates_)
    finger_scales_ = property(lambda self: self.sizing.finger_scales_)
    finger_spread_ = property(lambda self: self.sizing.finger_spread_)
    calibrated_each_ = property(lambda self: self.sizing.calibrated_each_)

    def context_for(self, scale):
        """The :class:`tracker.init.FitContext` of the hand scaled by ``scale`` (:class:`tracker.sizing.HandSizes`)."""
        return self.sizes(scale)

    def use_scale(self, scale):
        """Track the hand at ``scale`` (with the finger lengths found, if any) from now on."""
        self.context, self.n_pcs = self.sizes(scale), self.sizes.n_pcs
        if self.sizing.finger_scales_:
            self.context = shaped_context(self.context, self.base_hand, scale, self.sizing.finger_scales_)
        self.hand = self.context.hand
        self.limits, self.full, self.reduced = self.context.limits, self.context.full, self.context.reduced
        self.stages = tracking_stages(self.settings, self.context)

    def reset(self):
        """Forget the sequence: the next frame starts afresh (the size is kept)."""
        self.last_good = self.theta = self.prev = None
        self.lost = True
        self.net.reset()

    def fit_single_frame(self, points, **kw):
        """A fit without temporal prior with this tracker's parts (see :func:`tracker.init.fit_single_frame`)."""
        return fit_single_frame(self.context, points, self.settings.init, **kw)

    def calibrate_each(self, observations, camera):
        """Calibrate the hand (``"auto"``) on frames each fitted from its own start (stills, postures far
        apart in time): :meth:`tracker.sizing.SizeCalibration.calibrate_each`; then track on it from a
        fresh start. Returns the indices of the frames used (measurements: ``docs/tracker.md``)."""
        used = self.sizing.calibrate_each(self, observations, camera, self.settings.loss.min_points,
                                          self.settings.loss.max_points)
        self.reset()
        return used

    def predict(self) -> np.ndarray:
        """The start of the next frame (:meth:`tracker.parts.Prediction.theta`)."""
        C = self.synergies.model.all_components_[: self.n_pcs] if self.settings.mode == "reduced" else None
        return self.prediction.theta(self.theta, self.prev, self.hand, self.limits, C)

    def track(self, observation, camera, color=None) -> FrameResult:
        """Track one :class:`tracker.observe.Observation` (``color``: its registered colour frame)."""
        return self.step(observation.points, normals=observation.normals, mask=silhouette_mask(observation),
                         depth=observation.depth, camera=camera, frame_depth=observation.frame_depth, color=color)

    def step(self, points, *, normals=None, mask=None, depth=None, camera=None, frame_depth=None,
             color=None) -> FrameResult:
        """Track one frame's segmented points ``(N, 3)`` (camera frame, metres; NaN rows ignored): observe
        → predict → fit → check → refine → decide.

        With the hand ``mask``, the ``depth`` image (metres) and the ``camera``, model parts that
        leave the silhouette are pulled back (the silhouette term); with the whole ``frame_depth`` too,
        the start searches use the wrist cue (``start.wrist_cue``); with the ``color`` frame (and
        ``start.rgb_seed``) they start also from the colour keypoints."""
        sil = frame_silhouette(mask, depth, camera, frame_depth)
        t0 = time.perf_counter()
        pts, nrm = usable_points(points, normals, self.settings.loss.max_points)
        pts, nrm = self._before_detected_wrist(pts, nrm, sil)
        n_in = len(pts)
        if n_in < self.settings.loss.min_points:
            # nothing seen: no θ is output (an unreadable frame's row repeated the frame before it, which
            # a user of the rows cannot tell from a measurement); the next start may still begin there
            self.lost = True
            return frame_result(self.stats, self.hand.n_dofs, None, "lost", n_in, t0)
        if self.sizing.calibrating() or self.lost or self.theta is None:
            whole = frame_depth if frame_depth is not None else depth
            frame = self._start(pts, nrm, sil, n_in, t0, color, whole, camera)
        else:
            frame = self._follow(pts, nrm, sil)
        if isinstance(frame, Predicted):  # a jump to no hand: the prediction, the state as before it
            return frame_result(self.stats, self.hand.n_dofs, frame.theta, "predicted", n_in, t0)
        if isinstance(frame, FrameResult):  # a start that found no hand: lost, the state as before it
            self.lost = True
            return frame
        # refine: a start has no earlier frame that holds its unseen joints: all the way. The net's
        # replacement half the way, as tracked frames: it starts from the tracked fit too, and all the way
        # there made the hard cases' fast sweeps 7.6 -> 8.7 deg (Kinect v1 noise 14.0 -> 16.1) and the
        # turn 6.5 -> 7.1 with noise
        share = 1.0 if frame.status == "reinit" and frame.net != "replaced" else None
        frame = frame._replace(theta=self.prior(self.hand, frame.theta, frame.corr, self.limits, share))
        if self.settings.start.check_hand and self.hand_check_ is None and frame.status == "reinit":
            self.hand_check_ = check_hand(self.context, self.settings, self.synergies, frame.points, frame.normals,
                                          sil, frame.theta, frame.corr)
        return self._decide(frame, sil, n_in, t0)

    def _before_detected_wrist(self, pts, nrm, sil):
        """The points the keypoint detector's wrist leaves (``start.detector_wrist_m``), or all of them."""
        margin = self.settings.start.detector_wrist_m
        seed = self.search.keypoints
        if not margin > 0 or seed is None or sil is None or len(pts) < self.settings.loss.min_points:
            return pts, nrm
        if self.theta is not None and not self.lost and not self.sizing.calibrating():
            # the detector runs (~3.5 ms) only where the points reach this far behind the last frame's wrist
            kp = self.hand.keypoints(self.theta)
            if ahead_of_wrist(pts, kp[0], kp[9], margin).all():
                return pts, nrm
        det = seed.detection(sil, self.base_hand.handedness)
        if det is None or not np.all(np.isfinite(det.keypoints_xyz[[0, 9]])):
            return pts, nrm
        keep = ahead_of_wrist(pts, det.keypoints_xyz[0], det.keypoints_xyz[9], margin)
        if keep.all() or keep.sum() < self.settings.loss.min_points:
            return pts, nrm
        self.stats.wrist_cuts += 1
        return pts[keep], None if nrm is None else nrm[keep]

    def _start(self, pts, nrm, sil, n_in, t0, color, depth, camera):
        """A frame fitted without one before it: a size calibration, or the start search (re-initialisation)."""
        if self.loss.too_small(n_in, sil):
            return no_hand(self.stats, self.hand.n_dofs, None, n_in, t0)
        if self._region_absent(None if self.sizing.calibrating() else self.context, pts, nrm, sil):
            along = self._hand_along_surface(sil, depth, camera)
            if along is None:
                return no_hand(self.stats, self.hand.n_dofs, None, n_in, t0, small=False)
            # a hand's frame after all: counted as a surface start, not among the regions called no hand
            # (tracker track's "no hand" line counts those against the frames lost)
            self.stats.not_hands -= 1
            pts, nrm, sil = along
        if self.sizing.calibrating():
            self.cue.add(sil)
            theta, corr, found = self.sizing.calibrate(self, pts, nrm, sil)
        else:
            refit = partial(self._fit, pts=pts, nrm=nrm, sil=sil)  # the colour seed's refinement
            theta, corr = self.search(self.context, pts, nrm, sil, self.last_good, refit, color, depth, camera)
            found = not self.loss.found_nothing(corr)
        if not found:
            return no_hand(self.stats, self.hand.n_dofs, corr, n_in, t0)
        self.prev = None
        self.net.reset()
        if self.settings.net.enabled:
            # what a good fit scores in this scene: clutter that stays (a forearm, a table) raises it
            self.net.search_level = score(self.context, theta, corr, sil)
        return FrameFit(theta, corr, "reinit", "", False, False, pts, nrm)

    def _hand_along_surface(self, sil, depth, camera):
        """``(points, normals, silhouette)`` of a hand found along the surface a start's region belongs to,
        when that region is no hand, or None. A segmentation can take the near end of a forearm reaching
        towards the camera for the hand; the hand lies at the arm's other end, on the same surface: the
        keypoint CNN, given the whole surface (depth-continuous, :func:`tracker.segment.surfaces.surfaces`),
        narrows its box onto the hand by its re-crop (:func:`tracker.keypoint_cnn.detect`), and the region it
        narrowed to is taken when the hand-presence network calls it a hand."""
        from .observe import backproject
        from .segment.surfaces import surfaces

        seed = self.search.keypoints
        if seed is None or self.presence is None or sil is None or depth is None or camera is None:
            return None
        with np.errstate(invalid="ignore"):
            depth = np.where(np.asarray(depth, float) > 0, depth, np.nan)  # 0: no depth
        lab, _ = surfaces(depth)
        under = lab[sil.mask & (lab > 0)]
        if not len(under):
            return None
        surface = lab == np.bincount(under).argmax()
        det = seed.detect(depth, camera, surface, self.base_hand.handedness)
        region = det.region
        if region is None or not (region & ~sil.mask).any():
            return None  # nothing narrowed, or back onto the region turned away
        seen = np.where(region, depth, np.nan)
        found = frame_silhouette(region, seen, camera, depth)
        self.presence.absent(found, self.base_hand.handedness, counted=False)
        if not self.presence.probability_ >= SURFACE_HAND_P:
            return None
        P = backproject(seen, camera).reshape(-1, 3)
        pts, nrm = usable_points(P[np.isfinite(P).all(axis=1)], None, self.settings.loss.max_points)
        if len(pts) < self.settings.loss.min_points:
            return None
        self.stats.surface_starts += 1
        pts, nrm = self._before_detected_wrist(pts, nrm, found)
        return pts, nrm, found

    def _region_absent(self, ctx, pts, nrm, sil, *, counted=True) -> bool:
        """Whether the frame's region is no hand: the hand-presence network says so and the detected hand
        does not fit it (:meth:`tracker.parts.StartSearch.detected_fits` on ``ctx``'s hand; None: at the size
        calibration's first guesses); False without the network. ``counted``: as a start's answer."""
        if self.presence is None:
            return False
        fits = partial(self.search.detected_fits, ctx, self.context_for, pts, nrm, sil, self.settings.scale.range)
        return self.presence.absent(sil, self.base_hand.handedness, fits, counted=counted)

    def _not_a_hand(self, ctx, pts, nrm, sil) -> bool:
        """Whether a tracked frame whose points the prediction missed (re-centred: the hand jumped, or the
        segmentation took something else), or whose fit the safety net doubts, is no hand, asked as a start
        asks (:meth:`_region_absent`): a forearm's far end is not followed."""
        if not (self.settings.predict.jump_presence and self._region_absent(ctx, pts, nrm, sil, counted=False)):
            return False
        self.stats.jumps_refused += 1
        return True

    def _follow(self, pts, nrm, sil):
        """A tracked frame: predict (gate, re-centre), fit, the coupling restarts, check (the safety net)."""
        st, ctx = self.settings, self.context
        predicted = self.predict()
        pred, recentred, pts, nrm, all_pts, all_nrm = self.prediction.points(self.hand, ctx.score_samples,
                                                                             predicted, pts, nrm)
        if recentred and self._not_a_hand(ctx, all_pts, all_nrm, sil):
            return Predicted(predicted)
        kp = self._detected_keypoints(sil)
        theta, corr = self._fit(pred, pts, nrm, sil, kp)
        theta, corr = self.restart(self.hand, theta, corr, partial(self._fit, pts=pts, nrm=nrm, sil=sil, keypoints=kp),
                                   partial(score, ctx, silhouette=sil), self.limits)
        status, net, far_lost = "tracked", "", False
        if st.net.enabled and st.mode != "reduced":
            theta, corr, pts, nrm, net = self.net(ctx, theta, corr, pred, pts, nrm, all_pts, all_nrm, sil,
                                                  self.last_good,
                                                  partial(self._not_a_hand, ctx, all_pts, all_nrm, sil))
            if net == "absent":
                return Predicted(predicted)
            if net == "replaced":
                status, self.prev = "reinit", None
        elif st.net.enabled and self.net.far_off(ctx, theta, all_pts, most=200):
            # reduced mode has no net (its all-DoF searches would undo the subspace), but a fit that
            # leaves most of the segmented cloud far away is on something else: lost, not tracked
            # (a rendered hand in front of the body, segmented with the body: 284 of 2329 points
            # kept by the gate, fitted onto the torso 270 mm away and reported tracked)
            far_lost = True
        return FrameFit(theta, corr, status, net, recentred, far_lost, pts, nrm)

    def _decide(self, frame: FrameFit, sil, n_in, t0) -> FrameResult:
        """Keep the fit (tracked, and the size refined by it) or lose the frame."""
        theta, corr, status = frame.theta, frame.corr, frame.status
        fit_mm, rejected = corr.fit_error_mm(), corr.rejected_share
        if self.loss.kept(fit_mm, rejected) and not frame.far_lost:
            before = self.theta
            self.prev, self.theta = (before if status == "tracked" else None), theta
            if frame.net == "replaced" and self.settings.predict.through_net and self.net.is_motion(before, theta):
                # the global pose moves on from the frame before; the posture does not: the net's
                # replacement corrects a posture gone wrong, and that correction is no motion
                self.prev = theta.copy()
                self.prev[:6] = before[:6]
            if frame.recentred and self.prev is not None:
                # the jump was no velocity: the next prediction must not repeat it
                self.prev = self.prev.copy()
                self.prev[:3] = theta[:3]
            self.last_good = theta
            self.lost = False
            if status == "tracked" and self.sizing.refining():
                self.sizing.refine(self, frame.points, frame.normals, sil)
        else:
            self.lost, status, self.theta, self.prev = True, "lost", theta, None
        # a fit on something else gives no θ (as a start that found no hand: the frame's row must not
        # read as a hand's pose)
        return frame_result(self.stats, self.hand.n_dofs, None if frame.far_lost else theta, status, n_in, t0, fit_mm,
                            corr.used, float(rejected), frame.net)

    def segment_window(self, camera):
        """Where to segment the next frame (``observe(..., window=...)``; :func:`next_window`)."""
        return next_window(self, camera)

    def _detected_keypoints(self, sil):
        """The keypoint term's keypoints on this frame, ``(xyz, confidence)``: the keypoint detector's
        (``start.detector``, found once per frame) but those the last fit left without data (confidence 0:
        the synergy prior fills them), or None (the term off, no detector, nothing found, or with
        ``refine.keypoints.unseen_only`` the last fit left no joint without data)."""
        seed = self.search.keypoints
        term = self.settings.refine.keypoints
        if not (term.on and term.weight > 0) or seed is None or sil is None:
            return None
        if term.unseen_only and not self.prior.hidden_:
            return None
        det = seed.detection(sil, self.base_hand.handedness)
        if det is None:
            return None
        conf = det.confidence
        if self.prior.hidden_nodes_ is not None:
            # the keypoints of joints the data left unseen are the synergy prior's to fill: the CNN's, 10-17 mm
            # off there, pulled the occluded grasp's hidden fingers 1.29 -> 6.0 deg off (with them left out 1.59)
            conf = np.where(self.prior.hidden_nodes_, 0.0, conf)
        self.stats.keypoint_frames += 1
        return det.keypoints_xyz, conf

    def _fit(self, start, pts, nrm, sil, keypoints=None):
        """The tracking ICP from ``start`` (:func:`tracker.icp.fit`, this frame's stages; ``keypoints``:
        the detected ones of the keypoint term)."""
        ctx, st = self.context, self.settings
        return fit(self.hand, pts, start, self.stages, ctx.matcher, st.icp, n_rigid=st.icp.rigid_iterations,
                   normals=nrm, samples=ctx.samples, silhouette=sil, keypoints=keypoints,
                   keypoint_term=st.refine.keypoints)


__all__ = ["FrameResult", "HandCheck", "FrameTracker", "TrackerParts", "TrackerSettings", "TrackerStats", "build_parts",
           "check_hand", "fit_context", "frame_result", "next_window", "no_hand", "tracking_stages"]
