"""The hand's size while tracking (:class:`SizeCalibration`, :class:`tracker.settings.ScaleSettings`):
calibrated on the first frames, refined over the next ones, each finger's length once the size is
settled; or calibrated on stills each fitted from its own start (:meth:`SizeCalibration.calibrate_each`).
The estimators are :mod:`tracker.scale`'s; why each default: ``docs/tracker.md``.
"""
from __future__ import annotations

import math

import numpy as np

from .errors import TrackerError
from .init import score, thin
from .parts import TrackerStats, frame_silhouette, silhouette_mask, usable_points
from .scale import calibrate_scale, finger_scales, hand_side, parabola_scale, rescaled, size_score

#: A size-refining frame's search may replace the tracked fit (:meth:`SizeCalibration.take_better_start`)
#: when its size differs from the tracked fit's by more than this (log; 6 %, as
#: :func:`tracker.scale.calibrate_scale` searches again when the size moved so far).
SIZE_RESTART_LOG = 0.06


class SizeCalibration:
    """The size state of one tracker; its methods act on the tracker ``tr`` they are given (its
    contexts per size, θ, the loss tests and the wrist cue).

    Attributes
    ----------
    scale_ : the size in use (None while ``hand_scale="auto"`` has not seen a frame)
    scale_estimates_ : the per-frame estimates the size is the median of
    calibrations_ : ``(size score, size)`` of the frames calibrated so far
    finger_scales_, finger_spread_ : finger → length factor (None: the model's), and its estimate
        before shrinking with its standard error
    calibrated_each_ : calibrated by :meth:`calibrate_each` (stills), not while tracking
    """

    def __init__(self, settings, init, margin_mm: float, stats: TrackerStats | None = None):
        self.settings, self.init, self.margin_mm = settings, init, margin_mm
        self.stats = stats or TrackerStats()
        self.auto = settings.hand_scale == "auto"
        self.scale_ = None if self.auto else float(settings.hand_scale)
        self.scale_estimates_, self.calibrations_ = [], []
        self.finger_scales_, self.finger_spread_ = None, None
        self.calibrated_each_ = False
        self._open = False  # an automatic size not settled yet: the next frame is calibrated again
        self._frames = []  # (points, normals, silhouette, θ, hand) of the frames that refined the size

    def reset(self):
        pass

    def calibrating(self) -> bool:
        """Whether the next frame calibrates the size (``"auto"`` not settled yet)."""
        return self.auto and (self.scale_ is None or self._open)

    def refining(self) -> bool:
        """Whether a tracked frame adds an estimate (:meth:`refine`)."""
        return not self.calibrated_each_ and len(self.scale_estimates_) < (self.settings.frames if self.auto else 0)

    def calibrate(self, tr, pts, nrm, sil):
        """``(θ, corr, found)`` of a frame fitted with :func:`tracker.scale.calibrate_scale`; a fit that
        found no hand (``found`` False) changes nothing. The size becomes the best-scoring
        (:func:`tracker.scale.size_score`) of the frames calibrated so far; settled when that score is
        at most ``trust_mm`` or after ``frames`` frames, until then the next frame is calibrated again."""
        st = self.settings
        s, theta, corr = calibrate_scale(tr.context_for, pts, self.init, silhouette=sil, normals=nrm,
                                         scale_range=st.range)
        if tr.loss.no_hand_sized(s, corr):
            # the sizes the search probed are not needed again (a long stretch without a hand)
            tr.keep_contexts(1.0 if self.scale_ is None else self.scale_)
            return theta, corr, False
        q = size_score(tr.context_for(s), theta, corr, sil)
        self.calibrations_.append((q, s))
        tr.use_scale(s)
        q_best, best = min(self.calibrations_)
        self._open = q_best > st.trust_mm and len(self.calibrations_) < st.frames
        self.scale_estimates_ = [best]
        self.scale_ = best
        if round(best, 5) != round(s, 5):
            old = tr.hand
            tr.use_scale(best)
            theta, corr = tr.context.fit(rescaled(old, tr.hand, theta), pts, "full", 1, self.init.icp_iterations,
                                         silhouette=sil, normals=nrm)
        # the sizes the search probed are not needed again
        tr.keep_contexts(best)
        return theta, corr, True

    def refine(self, tr, pts, nrm, sil):
        """One more tracked frame's size estimate; the size becomes the median of the estimates, θ
        follows it. ``refine="search"``: the frame calibrated on its own (one frame's wrong size is
        outvoted); ``"local"``: :func:`tracker.scale.parabola_scale` around the current size."""
        s, st = self.scale_, self.settings
        found = None
        if st.refine == "search":
            tr.cue.add(sil)
            est, th_est, _ = calibrate_scale(tr.context_for, pts, self.init, silhouette=sil, normals=nrm,
                                             scale_range=st.range)
            if abs(math.log(est / s)) > SIZE_RESTART_LOG:
                # a size far from the tracked fit's: its search may hold a better start (its hand taken
                # before the probed sizes' contexts are dropped)
                found = (tr.context_for(est).hand, th_est)
        else:
            # the points on the fingers' side of this frame's wrist (forearm points reward a larger hand)
            keep = hand_side(pts, tr.hand, tr.theta)
            pts, nrm = pts[keep], None if nrm is None else nrm[keep]
            sub = thin(pts, self.init.refine_points)
            est, _, _, _ = parabola_scale(tr.context_for, tr.theta, tr.hand, pts[sub], s, silhouette=sil,
                                          normals=None if nrm is None else nrm[sub])
        est = float(np.clip(est, *st.range))
        keep_key = round(float(np.median(self.scale_estimates_ + [est])), 5)
        # the sizes the search probed are not needed again
        tr.keep_contexts(keep_key, s)
        self.scale_estimates_.append(est)
        new = float(np.median(self.scale_estimates_))
        if round(new, 5) != round(s, 5):
            old = tr.hand
            self.scale_ = new
            tr.use_scale(new)
            tr.theta = rescaled(old, tr.hand, tr.theta)
            tr.prev = None if tr.prev is None else rescaled(old, tr.hand, tr.prev)
            tr.last_good = tr.theta
        if found is not None:
            self.take_better_start(tr, pts, nrm, sil, *found)
        if st.finger_lengths:
            self._frames.append((pts, nrm, sil, tr.theta.copy(), tr.hand))
        if st.finger_lengths and len(self.scale_estimates_) >= st.frames:
            self.find_finger_lengths(tr)

    def take_better_start(self, tr, pts, nrm, sil, hand_est, theta_est) -> bool:
        """While the size is refined by searches, the tracked θ is replaced by this frame's search
        (``theta_est`` on ``hand_est``) when that scores better by ``margin_mm``, both refitted at the
        size in use (:func:`tracker.init.score`, the wrist cue included); asked only when the frame's
        size differs from the tracked fit's by more than :data:`SIZE_RESTART_LOG`. Counted in
        ``stats.size_starts``; returns whether it replaced."""
        ctx, n = tr.context, self.init.icp_iterations
        cand, c_cand = ctx.fit(rescaled(hand_est, tr.hand, theta_est), pts, "full", 1, n, silhouette=sil,
                               normals=nrm)
        here, c_here = ctx.fit(tr.theta, pts, "full", 1, n, silhouette=sil, normals=nrm)
        if not (np.all(np.isfinite(cand))
                and score(ctx, cand, c_cand, sil) < score(ctx, here, c_here, sil) - self.margin_mm):
            return False
        tr.theta = tr.last_good = cand
        tr.prev = None
        tr.net.reset()
        self.stats.size_starts += 1
        return True

    def find_finger_lengths(self, tr):
        """Each finger's length factor at the settled size, from the frames that refined it (their θ
        moved onto the settled hand; :func:`tracker.scale.finger_scales`); θ keeps its meaning."""
        s = self.scale_
        ctx = tr.context_for(s)
        frames = [(p, n, sil, rescaled(h, ctx.hand, th)) for p, n, sil, th, h in self._frames]
        # finger → (unshrunk factor, its standard error over the frames): the calibration record's spread
        self.finger_spread_ = {}
        self.finger_scales_ = finger_scales(ctx, tr.base_hand, s, frames, spread=self.finger_spread_)
        self._frames = []
        tr.use_scale(s)

    def calibrate_each(self, tr, observations, camera, min_points, max_points):
        """Calibrate on frames each fitted from its own start (see :meth:`tracker.track.HandTracker.calibrate_each`);
        returns the indices of the frames used."""
        st = self.settings
        if not self.auto:
            raise TrackerError("calibration", "calibrate_each needs hand_scale='auto'")
        frames, used, est, seen = [], [], [], 0
        for i, ob in enumerate(observations):
            seen += 1
            sil = frame_silhouette(silhouette_mask(ob), ob.depth, camera, ob.frame_depth)
            pts, nrm = usable_points(ob.points, ob.normals, max_points)
            if len(pts) < min_points:
                continue
            tr.cue.add(sil)
            size, _, corr = calibrate_scale(tr.context_for, pts, self.init, silhouette=sil, normals=nrm,
                                            scale_range=st.range)
            if tr.loss.no_hand_sized(size, corr):
                self.stats.no_hand += 1
                continue
            est.append(size)
            frames.append((pts, nrm, sil))
            used.append(i)
        if not est:
            raise TrackerError("calibration", f"no hand found in any of the {seen} frames")
        s = float(np.median(est))
        self.finger_scales_, self.calibrated_each_ = None, True
        # settled: tracking afterwards neither calibrates nor refines it (calibrated_each_)
        self.calibrations_, self._open = [], False
        self.scale_, self.scale_estimates_ = s, [float(e) for e in est]
        tr.use_scale(s)
        tr.keep_contexts(s)
        if st.finger_lengths:
            self._frames = [(p, n, sil, tr.fit_single_frame(p, silhouette=sil, normals=n)[0], tr.hand)
                            for p, n, sil in frames]
            self.find_finger_lengths(tr)
        return used
