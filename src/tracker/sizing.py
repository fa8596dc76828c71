"""The hand's size while tracking (:class:`SizeCalibration`, :class:`tracker.settings.ScaleSettings`):
calibrated on the first frames, refined over the next ones, each finger's length once the size is
settled; or calibrated on stills each fitted from its own start (:meth:`SizeCalibration.calibrate_each`).
The estimators are :mod:`tracker.scale`'s; why each default: ``docs/tracker.md``.
"""
from __future__ import annotations

import math

import numpy as np

from handmodel.dofs import anatomical_limits
from handmodel.subspace import Subspace, hierarchical_schedule

from .correspond import Matcher, ModelSamples
from .errors import TrackerError
from .init import FitContext, finger_shapes, score, search_threads, thin
from .parts import TrackerStats, frame_silhouette, silhouette_mask, usable_points
from .resize import resized_context
from .scale import (
    calibrate_scale,
    finger_scales_steps,
    hand_side,
    parabola_scale_steps,
    rescaled,
    size_score,
)

#: A size-refining frame's search may replace the tracked fit (:meth:`SizeCalibration.take_better_start`)
#: when its size differs from the tracked fit's by more than this (log; 6 %, as
#: :func:`tracker.scale.calibrate_scale` searches again when the size moved so far).
SIZE_RESTART_LOG = 0.06

#: the factors each finger's length is probed at while tracking with a budget (``scale.budget`` > 0;
#: :func:`tracker.scale.finger_scales_steps`' ``probes``, 5 at once): 40 % less work, the lengths
#: applied ~6 frames sooner. Realistic scenes, 36 runs, mean keypoint mm: at once 2.788 with 5, 2.775
#: with 3; spread at 40 iterations a frame 3.167 with 5, 2.964 with 3 (no finger lengths: 3.18–3.21)
FINGER_PROBES = 3
#: … and each frame's points thinned to this many for them (:func:`tracker.init.thin`; all at once: every
#: point). Realistic scenes, at once: 2.788 mm with every point (~1,100–2,000), 2.781 with 500, 2.788 with 800
FINGER_POINTS = 500


class SpreadWork:
    """Size work done a probe at a time, spread over frames: ``steps`` yields each probe's cost (ICP
    iterations) before it runs the probe, and returns the work's result (as
    :func:`tracker.scale.parabola_scale_steps` and :func:`tracker.scale.finger_scales_steps`).

    Attributes
    ----------
    finished : whether the work is done; result : what it returned then
    """

    def __init__(self, steps):
        self.steps, self.finished, self.result = steps, False, None
        self._cost = None  # the next probe's cost; None: not asked yet

    def run(self, budget: int, spent: int = 0) -> int:
        """Run probes while the frame's ICP iterations (``spent`` so far) stay within ``budget``, at
        least one probe a frame (0: every probe); returns the iterations spent then. Counted in
        iterations, not time: the same frames get the same work on any machine."""
        while not self.finished:
            if self._cost is None:
                self._advance()  # up to the first probe (no fit)
                continue
            if budget and spent and spent + self._cost > budget:
                break
            spent += self._cost
            self._advance()
        return spent

    def _advance(self):
        """Run the work up to its next probe (the one whose cost it then yields) or its end."""
        try:
            self._cost = next(self.steps)
        except StopIteration as end:
            self.finished, self.result = True, end.value


def fit_context(hand, settings, synergies=None):
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
        sub = settings.subspace
        n_pcs = int(sub.n_pcs) if sub.n_pcs is not None else model.n_components_for(sub.variance or 0.99)
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


class HandSizes:
    """The :class:`tracker.init.FitContext` of each hand size, made once per size from the model-sized
    hand's (:func:`tracker.resize.resized_context`; building one anew samples the surface again, ~30×
    the time); ``n_pcs``: the PCs of the reduced modes."""

    def __init__(self, base_hand, settings, synergies=None):
        self.base_hand, self.settings, self.synergies = base_hand, settings, synergies
        self._contexts = {}
        self._base = None  # the model-sized hand's (FitContext, n_pcs): every size is made from it

    def __call__(self, scale):
        """The context of the hand scaled by ``scale``."""
        key = round(float(scale), 5)
        if key not in self._contexts:
            if self._base is None:
                self._base = fit_context(self.base_hand, self.settings, self.synergies)
            ctx, n_pcs = self._base
            if key != 1.0:
                ctx = resized_context(ctx, self.base_hand.scaled(key), key)
            self._contexts[key] = (ctx, n_pcs)
        return self._contexts[key][0]

    @property
    def n_pcs(self):
        return None if self._base is None else self._base[1]

    def keep(self, *sizes):
        """Drop the contexts of every size but ``sizes``."""
        keep = {round(float(x), 5) for x in sizes}
        self._contexts = {k: v for k, v in self._contexts.items() if k in keep}

    def sizes(self) -> list:
        """The sizes whose contexts are kept."""
        return list(self._contexts)


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
    work_ : the size work each refining frame spent (:meth:`refine`; ICP iterations on 1,500 points,
        :func:`tracker.scale.probe_cost`; a frame's own search not counted)
    searches_ : refining frames calibrated on their own because their local estimate disagreed
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
        self._work = None  # ("estimate" | "fingers", SpreadWork, its frame | spread dict): work under way
        self._queued = []  # (points, normals, silhouette, θ, hand) of refining frames whose estimate is to come
        self._fingers_started = False
        self.work_, self.searches_ = [], 0

    def reset(self):
        pass

    def calibrating(self) -> bool:
        """Whether the next frame calibrates the size (``"auto"`` not settled yet)."""
        return self.auto and (self.scale_ is None or self._open)

    def refining(self) -> bool:
        """Whether a tracked frame adds an estimate or goes on with the size's work (:meth:`refine`)."""
        return not self.calibrated_each_ and (len(self.scale_estimates_) < (self.settings.frames if self.auto else 0)
                                              or self._work is not None or bool(self._queued))

    def calibrate(self, tr, pts, nrm, sil):
        """``(θ, corr, found)`` of a frame fitted with :func:`tracker.scale.calibrate_scale`; a fit that
        found no hand (``found`` False) changes nothing. The size becomes the best-scoring
        (:func:`tracker.scale.size_score`) of the frames calibrated so far; settled when that score is
        at most ``trust_mm`` or after ``frames`` frames, until then the next frame is calibrated again."""
        st = self.settings
        s, theta, corr = calibrate_scale(tr.context_for, pts, self.init, silhouette=sil, normals=nrm,
                                         scale_range=st.range, **self._detected(tr, sil))
        if tr.loss.no_hand_sized(s, corr):
            # the sizes the search probed are not needed again (a long stretch without a hand)
            tr.sizes.keep(1.0 if self.scale_ is None else self.scale_)
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
        tr.sizes.keep(best)
        return theta, corr, True

    def _detected(self, tr, sil) -> dict:
        """The keypoint detector's part in a calibration (``start.detector``): the size from its
        keypoints and the hand fitted to them, searched first at that size (``start.detector_accept_mm``)."""
        seed = tr.search.keypoints
        if seed is None:
            return {}
        # loaded with a detector only: without one a run loads neither the fit nor the forests
        from .keypoint_fit import keypoint_scale

        det = seed.detection(sil, tr.base_hand.handedness)
        if det is None:
            return {}
        return {"seeds": lambda hand: seed.fit(det, hand), "accept_mm": tr.search.accept_mm,
                "size_guess": keypoint_scale(det, tr.context_for(1.0).hand)}

    def refine(self, tr, pts, nrm, sil):
        """One more tracked frame's part in the size: its estimate, the size the median of the estimates,
        θ following it; once ``frames`` estimates are in, each finger's length. ``refine="search"``: the
        frame calibrated on its own (one frame's wrong size is outvoted); ``"local"``:
        :func:`tracker.scale.parabola_scale` around the current size from the tracked fit; ``"checked"``:
        that, and the frame calibrated on its own instead where the tracked fit is poor (:meth:`disagrees`).
        The local estimates and the finger lengths run as probes (:class:`SpreadWork`): this frame
        spends at most ``budget`` on them (ICP iterations on 1,500 points, :func:`tracker.scale.probe_cost`;
        at least one probe; 0 = all at once) and the next tracked frames go on where it stopped
        (:meth:`finish`: the rest at once). The frames that refine are still the first
        ``frames`` − 1 tracked ones (each kept until its estimate's turn: frames later in a motion
        gave other sizes and finger lengths, a hand 0.8× on a table 2.6 → 3.1 mm); the finger lengths
        go first once those frames are in (:meth:`fingers_due`); a frame's own search is not split."""
        st = self.settings
        if len(self.scale_estimates_) + len(self._queued) + (self._work is not None) < st.frames:
            if st.refine == "search":
                self._searched(tr, pts, nrm, sil)
            else:
                self._queued.append((pts, nrm, sil, tr.theta.copy(), tr.hand))
                if st.finger_lengths:
                    self._frames.append(self._queued[-1])
        self.work_.append(self._run_work(tr, st.budget, (pts, nrm, sil)))

    def _run_work(self, tr, budget, seen) -> float:
        """Go on with the work under way (the finger lengths once due, else the estimates of the frames
        kept, in turn) within ``budget`` (0: all of it); ``seen``: this frame's ``(points, normals,
        silhouette)``, searched where a local estimate is distrusted (None: that estimate's own frame).
        Returns the work spent."""
        spent = 0
        while True:
            if self._work is None and self.fingers_due():
                self._fingers_started = True
                self._work = ("fingers", *self._finger_work(tr))
            if self._work is None and self._queued:
                self._work = ("estimate", *self._local_work(tr, *self._queued.pop(0)))
            if self._work is None:
                break
            kind, work, frame = self._work
            spent = work.run(budget, spent)
            if not work.finished:
                break
            self._work = None
            if kind == "fingers":
                self._fingers_found(tr, work.result, frame)
            elif self.settings.refine == "checked" and self.disagrees(work.result[0], work.result[3]):
                # the tracked fit cannot tell the size: a frame's own search does (and may hold a better start)
                self.searches_ += 1
                self._searched(tr, *(seen or frame[:3]), better_start=seen is not None)
            else:
                self._add_estimate(tr, work.result[0], frame)
        return spent

    def finish(self, tr) -> bool:
        """Do the size's work still under way at once: the estimates of the refining frames kept and the
        finger lengths (a recording that ended before its frames' budgets did the work, or a calibration
        with no frame rate to keep). A distrusted estimate's search runs on its own frame, without
        replacing the tracked fit (there is no next frame to track). Returns whether there was any."""
        if not (self._work is not None or self._queued or self.fingers_due()):
            return False
        self._run_work(tr, 0, None)
        return True

    def fingers_due(self) -> bool:
        """Whether the finger lengths' work may begin: every refining frame is in (``frames`` − 1). It
        goes before the size's estimates still to come, at the size then (the lengths are factors on
        it): the finger lengths are what the first frames miss most (realistic scenes, 36 runs, work
        spread at 40 iterations a frame: size estimates at once or spread, no finger lengths, 3.21 and
        3.18 mm; finger lengths at once 2.79 mm), the size's later estimates moved it by ~1 %."""
        st = self.settings
        return (st.finger_lengths and not self._fingers_started and self.finger_scales_ is None
                and len(self._frames) >= max(1, st.frames - 1))

    def disagrees(self, est, score_mm) -> bool:
        """Whether a local estimate (its probe's size score ``score_mm``) cannot be trusted: the
        tracked fit explains its frame poorly at every probed size (above ``trust_mm``: a wrong posture
        or orientation). An estimate at the edge of the probes (±6 %) is kept: the median moves the
        size that way and the next frame probes around it (on the 1.5× fast sweeps the edge's searches
        found 1.50 and 1.14, the local estimates 1.39–1.49)."""
        return score_mm > self.settings.trust_mm

    def _local_work(self, tr, pts, nrm, sil, theta, hand):
        """``(work, frame)``: the probes of :func:`tracker.scale.parabola_scale_steps` around the current
        size from a frame's tracked fit ``theta`` on ``hand``, and the frame as the finger lengths take it."""
        # the points on the fingers' side of this frame's wrist (forearm points reward a larger hand)
        keep = hand_side(pts, hand, theta)
        cut, cut_nrm = pts[keep], None if nrm is None else nrm[keep]
        sub = thin(cut, self.init.refine_points)
        steps = parabola_scale_steps(tr.context_for, theta, hand, cut[sub], self.scale_, silhouette=sil,
                                     normals=None if cut_nrm is None else cut_nrm[sub])
        return SpreadWork(steps), (pts, nrm, sil, theta, hand)

    def _searched(self, tr, pts, nrm, sil, better_start=True):
        """This frame calibrated on its own (:func:`tracker.scale.calibrate_scale`) as its estimate; its
        search may replace the tracked fit (:meth:`take_better_start`; ``better_start`` False: not)."""
        s = self.scale_
        tr.cue.add(sil)
        est, th_est, _ = calibrate_scale(tr.context_for, pts, self.init, silhouette=sil, normals=nrm,
                                         scale_range=self.settings.range, **self._detected(tr, sil))
        # a size far from the tracked fit's: its search may hold a better start (its hand taken before the
        # probed sizes' contexts are dropped)
        far = better_start and abs(math.log(est / s)) > SIZE_RESTART_LOG
        found = (tr.context_for(est).hand, th_est) if far else None
        self._add_estimate(tr, est, None, (pts, nrm, sil), found)

    def _add_estimate(self, tr, est, frame, seen=None, found=None):
        """Add the estimate ``est`` of a frame (``frame``: its ``(points, normals, silhouette, θ, hand)``;
        None: the frame ``seen`` = ``(points, normals, silhouette)``, its θ the tracked one after the size
        is updated and ``found``, a better start, is tried; it joins the finger lengths' frames)."""
        st, s = self.settings, self.scale_
        est = float(np.clip(est, *st.range))
        keep_key = round(float(np.median(self.scale_estimates_ + [est])), 5)
        # the sizes the search probed are not needed again
        tr.sizes.keep(keep_key, s)
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
            self.take_better_start(tr, *seen, *found)
        if st.finger_lengths and frame is None and not self._fingers_started:
            # a frame calibrated on its own: its θ after the size and the better start (a local frame is
            # kept as it was tracked, when it is taken)
            self._frames.append((*seen, tr.theta.copy(), tr.hand))

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
        moved onto the settled hand; :func:`tracker.scale.finger_scales`), at once; θ keeps its meaning."""
        work, spread = self._finger_work(tr)
        work.run(0)
        self._fingers_found(tr, work.result, spread)

    def _finger_work(self, tr):
        """``(work, spread)``: the probes of :func:`tracker.scale.finger_scales_steps` at the settled size
        on the frames that refined it, and the dict that receives each finger's unshrunk factor and
        standard error (the calibration record's spread)."""
        s = self.scale_
        ctx = tr.context_for(s)
        spread_over = bool(self.settings.budget)
        frames = []
        for p, n, sil, th, h in self._frames:
            # spread over frames, fitted on FINGER_POINTS of each frame: less work a probe, as accurate
            k = thin(p, FINGER_POINTS) if spread_over else slice(None)
            frames.append((p[k], None if n is None else n[k], sil, rescaled(h, ctx.hand, th)))
        self._frames = []
        spread = {}
        steps = finger_scales_steps(ctx, tr.base_hand, s, frames, spread=spread,
                                    probes=FINGER_PROBES if spread_over else 5)
        return SpreadWork(steps), spread

    def _fingers_found(self, tr, found, spread):
        """Track with the finger length factors ``found`` from now on (θ keeps its meaning)."""
        self.finger_spread_, self.finger_scales_ = spread, found
        tr.use_scale(self.scale_)

    def calibrate_each(self, tr, observations, camera, min_points, max_points):
        """Calibrate on frames each fitted from its own start: each frame's size found alone, the size
        their median, and with ``finger_lengths`` each finger's length from every frame's start search
        at that size (postures apart tell lengths apart best). Frames with fewer than ``min_points``
        points, or whose fit found no hand, are skipped; the size is kept however few frames it came
        from. Returns the indices of the frames used."""
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
        tr.sizes.keep(s)
        if st.finger_lengths:
            self._frames = [(p, n, sil, tr.fit_single_frame(p, silhouette=sil, normals=n)[0], tr.hand)
                            for p, n, sil in frames]
            self.find_finger_lengths(tr)
        return used
