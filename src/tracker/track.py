"""Pipeline stage ``track``: :class:`HandTracker`, the per-frame loop — observe → predict → fit →
check → refine → decide — as state plus named parts (:mod:`tracker.parts`, :mod:`tracker.net`,
:mod:`tracker.sizing`), each built from its group of :class:`tracker.settings.TrackerSettings`.

The stages it drives: :mod:`tracker.observe` → :mod:`tracker.segment` → :mod:`tracker.correspond` →
:mod:`tracker.icp` → :mod:`tracker.init`; :mod:`tracker.run` runs it over a recording.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from handmodel.dofs import anatomical_limits
from handmodel.rigid import wrapped_angles
from handmodel.subspace import Subspace, hierarchical_schedule

from .correspond import Matcher, ModelSamples
from .errors import TrackerError
from .icp import fit, posed_samples, tracking_schedule
from .init import FitContext, finger_shapes, fit_single_frame, score, search_threads
from .net import SafetyNet
from .observe import hand_window, past_wrist, predicted_near
from .parts import (
    FingerRestart,
    LossCheck,
    Recentring,
    TrackerStats,
    UnseenPrior,
    WristCue,
    frame_silhouette,
    silhouette_mask,
    usable_points,
)
from .rgb import RgbSeed
from .scale import resized_context, shaped_context
from .settings import TrackerSettings
from .sizing import SizeCalibration


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


def _output_theta(theta) -> np.ndarray:
    """A copy of θ as a frame's result gives it: the global rotation in [−π, π) (the tracker's own θ
    keeps its turns: its fits start from it)."""
    out = np.array(theta, float)
    out[3:6] = wrapped_angles(out[3:6])
    return out


def fit_context(hand, settings: TrackerSettings, synergies=None):
    """The parts of every fit of ``hand`` (:class:`tracker.init.FitContext`) and the number of PCs."""
    lim = np.array(hand.limits, float)
    if settings.subspace.limits == "anatomical":
        lim = anatomical_limits(hand)
    elif settings.subspace.limits == "data" and synergies is not None:
        post = ~hand.pose_mask
        lim[post, 0] = synergies.model.joint_min_
        lim[post, 1] = synergies.model.joint_max_
    full = Subspace.full(hand, lim)
    reduced, ladder, n_pcs, model = None, [], None, None
    if synergies is not None:
        model = synergies.model
        n_pcs = int(settings.subspace.n_pcs) if settings.subspace.n_pcs is not None else model.n_components_for(settings.subspace.variance or 0.99)
        if not 1 <= n_pcs <= model.all_components_.shape[0]:
            raise TrackerError("synergies", f"{n_pcs} PCs requested, the bundle has {model.all_components_.shape[0]}")
        reduced = synergies.subspace(n_pcs, hand=hand)
        # the ladder's last stage is `full` itself: the fit tells all-DoF stages by identity
        ladder = hierarchical_schedule(hand, model.all_components_, model.mean_, model.pc_min_, model.pc_max_,
                                       steps=settings.subspace.hierarchy, n_pcs=n_pcs)[:-1] + [full]
    matcher = Matcher(hand, settings.correspond)
    samples = ModelSamples(hand) if settings.icp.silhouette_weight > 0 else None
    # the start search scores both directions even when the fit itself has no silhouette term
    ctx = FitContext(hand, lim, matcher, settings.icp, full, reduced, ladder, model, samples, finger_shapes(hand, lim),
                     score_samples=ModelSamples(hand, spacing=0.006), threads=search_threads(settings.init.threads))
    return ctx, n_pcs


class HandTracker:
    """Track one hand through a sequence of point clouds (camera frame, metres).

    The tracker is state (θ, the last frame's θ, lost or not, the hand at its size) plus named parts,
    each built from its settings group: :class:`tracker.sizing.SizeCalibration` (``sizing``),
    :class:`tracker.net.SafetyNet` (``net``), :class:`tracker.parts.Recentring` (``recentring``),
    :class:`tracker.parts.UnseenPrior` (``prior``), :class:`tracker.parts.FingerRestart` (``restart``),
    :class:`tracker.parts.LossCheck` (``loss``) and the frame's :class:`tracker.parts.WristCue` (``cue``);
    they count into one :class:`tracker.parts.TrackerStats` (``stats``, also on every
    :class:`FrameResult`).

    Parameters
    ----------
    hand : HandModel
    settings : TrackerSettings
    synergies : a synergy bundle (``synergy.bundle.Bundle``) or ``None`` (full mode only)
    keypoint_detector : the colour seed's detector instead of MediaPipe (``start.rgb_seed``)

    Attributes
    ----------
    hand : the model tracked, ``base_hand`` at the size in use
    scale_, scale_estimates_, finger_scales_, finger_spread_, calibrated_each_ : the size
        (:class:`tracker.sizing.SizeCalibration`)
    hand_check_ : :class:`HandCheck` of the first frame (``start.check_hand``), else None
    rgb_ : the :class:`tracker.rgb.RgbSeed` with ``start.rgb_seed``, else None
    """

    def __init__(self, hand, settings: TrackerSettings | None = None, synergies=None, keypoint_detector=None):
        self.base_hand = hand
        self.settings = st = settings or TrackerSettings()
        st.check()
        if st.mode != "full" and synergies is None:
            raise TrackerError("synergies", f"mode {st.mode!r} needs a synergy bundle (--synergies)")
        self.synergies = synergies
        self.stats = TrackerStats()
        self.cue = WristCue(st.start.wrist_cue, self.stats)
        self.net = SafetyNet(st.net, self.cue, self.stats)
        self.recentring = Recentring(st.correspond.reject_mm, self.stats)
        self.prior = UnseenPrior(hand, synergies, st.refine, st.mode, self.stats)
        self.restart = FingerRestart(st.refine, st.mode, self.stats)
        self.loss = LossCheck(st.loss, st.scale.range, self.stats)
        self.sizing = SizeCalibration(st.scale, st.init, st.net.margin_mm, self.stats)
        self.rgb_ = RgbSeed(keypoint_detector) if st.start.rgb_seed else None
        self.hand_check_ = None
        self._contexts = {}
        self._base = None  # the model-sized hand's (FitContext, n_pcs): every size is made from it
        self.use_scale(1.0 if self.sizing.scale_ is None else self.sizing.scale_)
        self.reset()

    scale_ = property(lambda self: self.sizing.scale_)
    scale_estimates_ = property(lambda self: self.sizing.scale_estimates_)
    finger_scales_ = property(lambda self: self.sizing.finger_scales_)
    finger_spread_ = property(lambda self: self.sizing.finger_spread_)
    calibrated_each_ = property(lambda self: self.sizing.calibrated_each_)

    def context_for(self, scale):
        """The :class:`tracker.init.FitContext` of the hand scaled by ``scale`` (made once per size):
        the model-sized hand's context resized (:func:`tracker.scale.resized_context`; building one
        anew samples the surface again, ~30× the time)."""
        key = round(float(scale), 5)
        if key not in self._contexts:
            if self._base is None:
                self._base = fit_context(self.base_hand, self.settings, self.synergies)
            ctx, n_pcs = self._base
            if key != 1.0:
                ctx = resized_context(ctx, self.base_hand.scaled(key), key)
            self._contexts[key] = (ctx, n_pcs)
        return self._contexts[key][0]

    def keep_contexts(self, *sizes):
        """Drop the contexts (:meth:`context_for`) of every size but ``sizes``."""
        keep = {round(float(x), 5) for x in sizes}
        self._contexts = {k: v for k, v in self._contexts.items() if k in keep}

    def context_sizes(self) -> list:
        """The sizes whose contexts are kept (the others were dropped after a calibration's probes)."""
        return list(self._contexts)

    def use_scale(self, scale):
        """Track the hand at ``scale`` (with the finger lengths found, if any) from now on."""
        self.context_for(scale)
        self.context, self.n_pcs = self._contexts[round(float(scale), 5)]
        if self.sizing.finger_scales_:
            self.context = shaped_context(self.context, self.base_hand, scale, self.sizing.finger_scales_)
        self.hand = self.context.hand
        self.limits, self.full, self.reduced = self.context.limits, self.context.full, self.context.reduced
        st = self.settings.icp
        self.stages = tracking_schedule(self.settings.mode, st.icp_iterations, self.full, self.reduced,
                                        projected_steps=st.projected_steps, coarse_iterations=st.coarse_iterations,
                                        stages_per_pass=st.stages_per_pass)

    def reset(self):
        """Forget the sequence: the next frame starts afresh (the size is kept)."""
        self.last_good = None
        self.theta = None
        self.prev = None
        self.lost = True
        self.net.reset()

    def fit_single_frame(self, points, **kw):
        """A fit without temporal prior with this tracker's parts (see :func:`tracker.init.fit_single_frame`)."""
        return fit_single_frame(self.context, points, self.settings.init, **kw)

    def calibrate_each(self, observations, camera):
        """Calibrate the hand (``hand_scale="auto"``) on frames that are each fitted from their own
        start: stills, or postures far apart in time, which tracking from frame to frame would not
        follow. Each frame's size is found alone, the size is their median, and with
        ``finger_lengths`` each finger's length comes from every frame's start search at that size.
        Frames with fewer than ``min_points`` points, or whose fit found no hand, are skipped. The
        tracker then tracks on the calibrated hand from a fresh start, and keeps it. Returns the
        indices of the frames used (measurements: ``docs/tracker.md``)."""
        used = self.sizing.calibrate_each(self, observations, camera, self.settings.loss.min_points,
                                          self.settings.loss.max_points)
        self.reset()
        return used

    def predict(self) -> np.ndarray:
        """The start of the next frame: the last θ plus ``predict.share`` × its last change, except the
        global rotation (as the original code); in reduced mode the posture moves along the synergies
        only (hierarchical mode predicts all DoF: motion outside the synergies is real motion there)."""
        theta = self.theta.copy()
        st = self.settings
        if st.predict.share and self.prev is not None:
            step = (self.theta - self.prev) * float(st.predict.share)
            step[3:6] = 0.0
            post = ~self.hand.pose_mask
            if st.mode == "reduced":
                C = self.synergies.model.all_components_[: self.n_pcs]
                step[post] = (step[post] @ C.T) @ C
            theta = theta + step
            theta[post] = np.clip(theta[post], self.limits[post, 0], self.limits[post, 1])
        return theta

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
        n_in = len(pts)
        if n_in < self.settings.loss.min_points:
            # nothing seen: no θ is output (an unreadable frame's row repeated the frame before it, which
            # a user of the rows cannot tell from a measurement); the next start may still begin there
            self.lost = True
            return self._result(None, "lost", n_in, t0, rejected=1.0)
        if self.sizing.calibrating() or self.lost or self.theta is None:
            frame = self._start(pts, nrm, sil, n_in, t0, color, frame_depth if frame_depth is not None else depth, camera)
        else:
            frame = self._follow(pts, nrm, sil)
        if isinstance(frame, FrameResult):  # a start that found no hand
            return frame
        theta, corr, status, net, recentred, far_lost, pts, nrm = frame
        # refine: a start has no earlier frame that holds its unseen joints: all the way. The net's
        # replacement half the way, as tracked frames: it starts from the tracked fit too, and all the way
        # there made the hard cases' fast sweeps 7.6 -> 8.7 deg (Kinect v1 noise 14.0 -> 16.1) and the
        # turn 6.5 -> 7.1 with noise
        theta = self.prior(self.hand, theta, corr, self.limits, 1.0 if status == "reinit" and net != "replaced" else None)
        if self.settings.start.check_hand and self.hand_check_ is None and status == "reinit":
            self.hand_check_ = self._check_hand(pts, nrm, sil, theta, corr)
        return self._decide(theta, corr, status, net, recentred, far_lost, pts, nrm, sil, n_in, t0)

    def _start(self, pts, nrm, sil, n_in, t0, color, depth, camera):
        """A frame fitted without one before it: a size calibration, or the start search (re-initialisation)."""
        if self.loss.too_small(n_in, sil):
            return self._no_hand(None, n_in, t0)
        if self.sizing.calibrating():
            self.cue.add(sil)
            theta, corr, found = self.sizing.calibrate(self, pts, nrm, sil)
            if not found:
                return self._no_hand(corr, n_in, t0)
        else:
            extra = () if self.last_good is None else (self.last_good,)
            seed = self._rgb_start(color, depth, camera)
            self.cue.add(sil)
            # the start's last fits hold its crease on the arm's centre line (IcpSettings.wrist_line_weight);
            # not a size calibration's (it moved a real recording's calibrated size, 1.276 → 1.256, and
            # tips by up to 40 px) nor the net's, whose result is compared with the tracked fit's
            theta, corr = self.fit_single_frame(pts, silhouette=sil, normals=nrm, extra=extra + seed,
                                                wrist=self.cue.of(sil))
            if seed:
                theta, corr = self._rgb_refine(seed[0], theta, corr, pts, nrm, sil)
            if self.loss.found_nothing(corr):
                return self._no_hand(corr, n_in, t0)
        self.prev = None
        self.net.reset()
        if self.settings.net.enabled:
            # what a good fit scores in this scene: clutter that stays (a forearm, a table) raises it
            self.net.search_level = score(self.context, theta, corr, sil)
        return theta, corr, "reinit", "", False, False, pts, nrm

    def _follow(self, pts, nrm, sil):
        """A tracked frame: predict (gate, re-centre), fit, the coupling restarts, check (the safety net)."""
        st, ctx = self.settings, self.context
        pred = self.predict()
        recentred = False
        all_pts, all_nrm = pts, nrm
        # clutter the segmentation left beside the hand (table, torso, arm) cannot pull the fit; the
        # gate tests the prediction first, so that clutter cannot re-centre a prediction that was right
        keep, arm = self._gate(pred, pts) if st.observe.gate_mm > 0 else (None, None)
        if st.predict.recentre and (keep is None or keep.all()):
            moved = self.recentring(self.hand, ctx.score_samples, pred, pts)
            recentred, pred = moved is not pred, moved
            if recentred and keep is not None:
                keep, arm = self._gate(pred, pts)
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

        def tracking_fit(start):
            return fit(self.hand, pts, start, self.stages, ctx.matcher, st.icp, n_rigid=st.icp.rigid_iterations,
                       normals=nrm, samples=ctx.samples, silhouette=sil)

        theta, corr = tracking_fit(pred)
        theta, corr = self.restart(self.hand, theta, corr, tracking_fit, lambda t, c: score(ctx, t, c, sil), self.limits)
        status, net, far_lost = "tracked", "", False
        if st.net.enabled and st.mode != "reduced":
            theta, corr, pts, nrm, net = self.net(ctx, theta, corr, pred, pts, nrm, all_pts, all_nrm, sil,
                                                  self.last_good)
            if net == "replaced":
                status, self.prev = "reinit", None
        elif st.net.enabled and self.net.far_off(ctx, theta, all_pts, most=200):
            # reduced mode has no net (its all-DoF searches would undo the subspace), but a fit that
            # leaves most of the segmented cloud far away is on something else: lost, not tracked
            # (a rendered hand in front of the body, segmented with the body: 284 of 2329 points
            # kept by the gate, fitted onto the torso 270 mm away and reported tracked)
            far_lost = True
        return theta, corr, status, net, recentred, far_lost, pts, nrm

    def _decide(self, theta, corr, status, net, recentred, far_lost, pts, nrm, sil, n_in, t0) -> FrameResult:
        """Keep the fit (tracked, and the size refined by it) or lose the frame."""
        fit_mm, rejected = corr.fit_error_mm(), corr.rejected_share
        if self.loss.kept(fit_mm, rejected) and not far_lost:
            self.prev, self.theta = (self.theta if status == "tracked" else None), theta
            if recentred and self.prev is not None:
                # the jump was no velocity: the next prediction must not repeat it
                self.prev = self.prev.copy()
                self.prev[:3] = theta[:3]
            self.last_good = theta
            self.lost = False
            if status == "tracked" and self.sizing.refining():
                self.sizing.refine(self, pts, nrm, sil)
        else:
            self.lost, status, self.theta, self.prev = True, "lost", theta, None
        # a fit on something else gives no θ (as a start that found no hand: the frame's row must not
        # read as a hand's pose)
        return self._result(None if far_lost else theta, status, n_in, t0, fit_mm, corr.used, float(rejected), net)

    def _result(self, theta, status, n_in, t0, fit_mm=float("nan"), used=0, rejected=1.0, net="") -> FrameResult:
        out = np.full(self.hand.n_dofs, np.nan) if theta is None else _output_theta(theta)
        return FrameResult(out, status, fit_mm, used, n_in, (time.perf_counter() - t0) * 1e3, rejected, net,
                           dataclasses.replace(self.stats))

    def _no_hand(self, corr, n_in, t0) -> FrameResult:
        """A frame whose start found no hand (``corr``: its fit's pairs, None when its region was too
        small to fit): lost, no θ, the tracker's state as before it."""
        self.lost = True
        self.stats.no_hand += 1
        self.stats.too_few += corr is None
        return self._result(None, "lost", n_in, t0, rejected=1.0 if corr is None else corr.rejected_share)

    def segment_window(self, camera):
        """Where to segment the next frame (``observe(..., window=...)``): :func:`tracker.observe.hand_window`
        of the hand predicted for it, grown by ``observe.window_m``; None — the whole frame — when no
        hand is tracked (not started, lost, its size still being calibrated) or windows are off."""
        st = self.settings
        if not st.observe.window_m or self.lost or self.theta is None or self.sizing.calibrating():
            return None
        P, _ = posed_samples(self.hand, self.context.score_samples, self.predict())
        return hand_window(P, camera, st.observe.window_m)

    def _gate(self, pred, pts):
        """``(keep, arm)``: :func:`tracker.observe.gate` of the points by the hand predicted at ``pred``
        (all True when the prediction is not trusted or nothing is far), and those of the kept ones
        past its wrist (:func:`tracker.observe.past_wrist`; None when off, without the safety net, when
        the prediction is not trusted, none is past or too few would remain)."""
        st = self.settings
        P, N = posed_samples(self.hand, self.context.score_samples, pred)
        near = predicted_near(pts, P, st.observe.gate_mm / 1000.0, normals=N, min_share=st.observe.gate_min_share,
                              min_points=st.loss.min_points)
        if near is None:
            return np.ones(len(pts), bool), None
        if st.observe.arm_gate_mm is None or not st.net.enabled or st.mode == "reduced":
            # without the net's far-points test nothing would see the hand cut off past a wrong wrist
            # (fast and turning hands alone without the net: 32.0 -> 35.4 and 26.7 -> 32.0 deg)
            return near, None
        axis = self.hand.joint_frames(pred)[0, :3, 1]
        arm = near & past_wrist(pts, self.hand.wrist_crease(pred), axis, st.observe.arm_gate_mm / 1000.0)
        if not arm.any() or np.count_nonzero(near & ~arm) < max(st.loss.min_points, 1):
            return near, None
        return near, arm

    def _check_hand(self, pts, nrm, sil, theta, corr) -> HandCheck:
        """The single-frame search with the mirror-image hand (same size) against this frame's fit."""
        other = self.hand.mirrored()
        ctx, _ = fit_context(other, self.settings, self.synergies)
        th, c = fit_single_frame(ctx, pts, self.settings.init, silhouette=sil, normals=nrm)
        return HandCheck(score(self.context, theta, corr, sil), score(ctx, th, c, sil), other.handedness)

    def _rgb_start(self, color, depth, camera) -> tuple:
        """``(θ,)`` fitted to the colour keypoints of this frame, or ``()`` (no ``rgb_seed``, no
        colour, no hand found)."""
        if self.rgb_ is None or color is None or depth is None or camera is None:
            return ()
        th = self.rgb_(self.hand, color, depth, camera)
        if th is None:
            return ()
        self.stats.rgb_seeds += 1
        return (th,)

    def _rgb_refine(self, seed, theta, corr, pts, nrm, sil):
        """The colour seed refined by the tracking ICP alone, kept over the search's winner when the
        depth fits it at least as well (fit error no higher, no more than 5 % more points rejected).
        Not by :func:`tracker.init.score`: a hand turned over explains the depth about as well, and
        the score's wrist cue can favour it; the colour image sees which way the hand faces."""
        ctx, st = self.context, self.settings
        th, c = fit(self.hand, pts, seed, self.stages, ctx.matcher, st.icp, n_rigid=st.icp.rigid_iterations,
                    normals=nrm, samples=ctx.samples, silhouette=sil)
        if (np.all(np.isfinite(th)) and c.fit_error_mm() <= corr.fit_error_mm()
                and c.valid.mean() >= corr.valid.mean() - 0.05):
            self.stats.rgb_kept += 1
            return th, c
        return theta, corr


# the names the tests and tools import from here
_usable, _silhouette, _silhouette_mask = usable_points, frame_silhouette, silhouette_mask
