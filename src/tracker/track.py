"""Pipeline stage ``track``: the per-frame loop's state — prediction, one ICP fit, loss detection and
re-initialisation by the single-frame search.

The stages it drives: :mod:`tracker.observe` → :mod:`tracker.segment` → :mod:`tracker.correspond` →
:mod:`tracker.icp` → :mod:`tracker.init`; :mod:`tracker.run` runs it over a recording.
:class:`TrackerSettings` is composed of the stages' settings; ``TrackerSettings.paper()`` is the
paper's method (§VI, FORMAT.md §5), the defaults are ours.

"""
from __future__ import annotations

import copy
import dataclasses
import math
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from handmodel.dofs import anatomical_limits
from handmodel.rigid import euler_to_matrix, wrapped_angles
from handmodel.subspace import Subspace, hierarchical_schedule

from ._wrist_kernels import arm_entry, surface_past_outline
from .correspond import (
    CorrespondSettings,
    Matcher,
    ModelSamples,
    Silhouette,
    data_to_model_mm,
)
from .coupling import BENT_BACK_DEG, restart_uncoupled
from .errors import TrackerError
from .icp import MODES, IcpSettings, centre_shift, fit, posed_samples, tracking_schedule
from .init import FitContext, InitSettings, finger_shapes, fit_single_frame, score, search_threads, thin
from .observe import ObserveSettings, hand_window, past_wrist, predicted_near
from .rgb import RgbSeed
from .settings import TrackerSettings
from .scale import (
    calibrate_scale,
    finger_scales,
    hand_side,
    parabola_scale,
    rescaled,
    resized_context,
    shaped_context,
    size_score,
)
from .wrist import arm_behind, arm_length_m, wrist_cost_mm, wrist_cue

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


def _same_entry(a, b, mm) -> bool:
    """Whether two :meth:`HandTracker._arm_entry` results tell the same arm: none in both, or both
    within ``mm`` of each other."""
    if a[1] is None or b[1] is None:
        return a[1] is None and b[1] is None
    return float(np.linalg.norm(a[1] - b[1])) * 1000.0 <= mm


def _pose_change(a, b) -> tuple:
    """``(degrees, mm)``: how far the global pose of θ ``a`` is turned and moved from ``b``'s."""
    R = euler_to_matrix(a[3:6]) @ euler_to_matrix(b[3:6]).T
    turn = math.degrees(math.acos(float(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))
    return turn, float(np.linalg.norm(np.asarray(a[:3]) - np.asarray(b[:3])) * 1000.0)


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

    Parameters
    ----------
    hand : HandModel
    settings : TrackerSettings
    synergies : a synergy bundle (``synergy.bundle.Bundle``) or ``None`` (full mode only)

    Attributes
    ----------
    hand : the model tracked, ``base_hand`` scaled by ``scale_``
    scale_ : the hand size in use (None while ``hand_scale="auto"`` has not seen a frame)
    scale_estimates_ : the per-frame estimates an automatic calibration took the median of
    hand_check_ : :class:`HandCheck` of the first frame (``check_hand``), else None
    net_runs_, net_replaced_, net_ms_ : how often the safety net ran, how often its estimate won, and
        the time it took (ms, all runs together); net_anchored_, net_placed_ : how often it searched
        from the tracked pose and from placements
    recentred_ : how often the prediction was moved onto the cloud
    unseen_frames_ : the frames on which joints without data were pulled (``unseen_prior``)
    size_starts_ : the frames whose size-refining search replaced the tracked fit
        (:meth:`_take_better_start`)
    no_hand_ : the frames whose start found no hand (``no_hand_rejected``, ``start_min_pixels``);
        too_few_ : those of them with a region of fewer than ``start_min_pixels`` pixels
    rgb_ : the :class:`tracker.rgb.RgbSeed` with ``rgb_seed`` (``keypoint_detector``: its detector
        instead of MediaPipe), else None; rgb_seeds_ : the searches it seeded; rgb_kept_ : how often
        the seed refined alone beat the search
    """

    def __init__(self, hand, settings: TrackerSettings | None = None, synergies=None, keypoint_detector=None):
        self.base_hand = hand
        self.settings = settings = settings or TrackerSettings()
        settings.check()
        if settings.mode != "full" and synergies is None:
            raise TrackerError("synergies", f"mode {settings.mode!r} needs a synergy bundle (--synergies)")
        self.synergies = synergies
        self._contexts = {}
        self._base = None  # the model-sized hand's (FitContext, n_pcs): every size is made from it
        self._calibrations = []  # (size score, size) of the frames calibrated so far
        self._scale_open = False  # an automatic size not settled yet: the next frame is calibrated again
        self.scale_estimates_ = []
        self.finger_scales_ = None  # finger name → length factor (finger_lengths), None: the model's
        self._size_frames = []  # (points, normals, silhouette, θ, hand) of the frames that refined the size
        self.calibrated_each_ = False  # calibrated by calibrate_each (stills), not while tracking
        self.hand_check_ = None
        self.net_runs_, self.net_replaced_, self.net_ms_, self.recentred_ = 0, 0, 0.0, 0
        self.net_anchored_, self.net_placed_, self.net_wrong_way_ = 0, 0, 0
        self.wrist_tests_ = 0  # the wrist tests run in full (_wrong_way: the others found nothing changed)
        self.rgb_ = RgbSeed(keypoint_detector) if settings.start.rgb_seed else None
        self.rgb_seeds_, self.rgb_kept_ = 0, 0
        self._scores = deque(maxlen=30)  # the undoubted frames' scores the scene's level is taken from
        self._wrist_passed = None  # (θ, arm entry, frames since) of the last hand the wrist test passed
        self._search_level = 0.0
        auto = settings.scale.hand_scale == "auto"
        self._use_scale(1.0 if auto else float(settings.scale.hand_scale))
        self.scale_ = None if auto else float(settings.scale.hand_scale)
        # the synergy model's joint covariance and which parts each posture DoF moves (unseen_prior)
        self._unseen = _unseen_parts(hand, synergies)
        self.unseen_frames_ = 0
        self.no_hand_, self.too_few_, self.size_out_ = 0, 0, 0
        self.size_starts_ = 0  # size-refining searches whose fit replaced the tracked one
        self.reset()

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

    def _use_scale(self, scale):
        self.context_for(scale)
        self.context, self.n_pcs = self._contexts[round(float(scale), 5)]
        if self.finger_scales_:
            self.context = shaped_context(self.context, self.base_hand, scale, self.finger_scales_)
        self.hand = self.context.hand
        self.limits, self.full, self.reduced = self.context.limits, self.context.full, self.context.reduced
        st = self.settings.icp
        self.stages = tracking_schedule(self.settings.mode, st.icp_iterations, self.full, self.reduced,
                                        projected_steps=st.projected_steps, coarse_iterations=st.coarse_iterations,
                                        stages_per_pass=st.stages_per_pass)

    def reset(self):
        self.last_good = None
        self.theta = None
        self.prev = None
        self.lost = True
        self._wrist_passed = None

    def fit_single_frame(self, points, **kw):
        """A fit without temporal prior with this tracker's parts (see :func:`tracker.init.fit_single_frame`)."""
        return fit_single_frame(self.context, points, self.settings.init, **kw)

    def track(self, observation, camera, color=None) -> FrameResult:
        """Track one :class:`tracker.observe.Observation` (``color``: its registered colour frame)."""
        return self.step(observation.points, normals=observation.normals, mask=_silhouette_mask(observation),
                         depth=observation.depth, camera=camera, frame_depth=observation.frame_depth, color=color)

    def _check_hand(self, pts, nrm, sil, theta, corr) -> HandCheck:
        """The single-frame search with the mirror-image hand (same size) against this frame's fit."""
        other = self.hand.mirrored()
        ctx, _ = fit_context(other, self.settings, self.synergies)
        th, c = fit_single_frame(ctx, pts, self.settings.init, silhouette=sil, normals=nrm)
        return HandCheck(score(self.context, theta, corr, sil), score(ctx, th, c, sil), other.handedness)

    def _calibrate(self, pts, nrm, sil):
        """``(θ, corr, found)`` of a frame fitted with :func:`tracker.scale.calibrate_scale`; a fit
        that found no hand (:meth:`_found_nothing`, ``found`` False) changes nothing. The size in use
        (``scale_``) becomes the best-scoring (:func:`tracker.scale.size_score`) of the frames
        calibrated so far. The calibration is settled when that score is at most ``scale_trust_mm``
        or after ``scale_frames`` frames; until then the next frame is calibrated again (a first frame
        whose segmentation kept the arm or the object instead of the hand gives the size of whatever
        was fitted: rendered scenes scored 7–24 there, ≤ 6 where the hand was found). A size at an end
        of ``scale_range`` (:meth:`_size_out`) found no hand either."""
        st = self.settings
        s, theta, corr = calibrate_scale(self.context_for, pts, st.init, silhouette=sil, normals=nrm,
                                         scale_range=st.scale.range)
        if self._no_hand_sized(s, corr):
            # the sizes the search probed are not needed again (a long stretch without a hand)
            self._keep_contexts(1.0 if self.scale_ is None else self.scale_)
            return theta, corr, False
        q = size_score(self.context_for(s), theta, corr, sil)
        self._calibrations.append((q, s))
        self._use_scale(s)
        q_best, best = min(self._calibrations)
        self._scale_open = q_best > st.scale.trust_mm and len(self._calibrations) < st.scale.frames
        self.scale_estimates_ = [best]
        self.scale_ = best
        if round(best, 5) != round(s, 5):
            old = self.hand
            self._use_scale(best)
            theta, corr = self.context.fit(rescaled(old, self.hand, theta), pts, "full", 1, st.init.icp_iterations,
                                           silhouette=sil, normals=nrm)
        # the sizes the search probed are not needed again
        self._keep_contexts(best)
        return theta, corr, True

    def _keep_contexts(self, *sizes):
        """Drop the contexts (:meth:`context_for`) of every size but ``sizes``."""
        keep = {round(float(x), 5) for x in sizes}
        self._contexts = {k: v for k, v in self._contexts.items() if k in keep}

    def _calibrating(self) -> bool:
        """Whether the next frame calibrates the size (``hand_scale="auto"`` not settled yet)."""
        return self.settings.scale.hand_scale == "auto" and (self.scale_ is None or self._scale_open)

    def _found_nothing(self, corr) -> bool:
        """Whether a start's fit (its correspondences ``corr``) rejects more than ``no_hand_rejected``
        of its points: what it fitted is no hand."""
        limit = self.settings.loss.no_hand_rejected
        return bool(limit) and len(corr.valid) > 0 and corr.rejected_share > limit

    def _size_out(self, s) -> bool:
        """Whether a calibrated size ``s`` lies at an end of ``scale_range`` (within 1 %): the best size
        of what was fitted lies beyond the sizes of hands, so it is no hand (a person's shoulder, left
        in by a ``--box`` that cut the hand out, fitted at 2.0× the model, the range's end, with 23 % of
        its points rejected; the 19 SR305 stills: 1.21–1.31×). A test of the no-hand tests: off with
        ``no_hand_rejected`` 0."""
        lo, hi = self.settings.scale.range
        return bool(self.settings.loss.no_hand_rejected) and not lo * 1.01 < s < hi / 1.01

    def _no_hand_sized(self, s, corr) -> bool:
        """Whether a calibrating start (size ``s``, pairs ``corr``) found no hand: its size at an end of
        the range (:meth:`_size_out`, counted in ``size_out_``) or its fit's rejections
        (:meth:`_found_nothing`)."""
        out = self._size_out(s)
        self.size_out_ += out
        return out or self._found_nothing(corr)

    def _no_hand(self, corr, n_in, t0) -> FrameResult:
        """A frame whose start found no hand (``corr``: its fit's pairs, None when it had too few points
        to fit): lost, no θ, the tracker's state as before it."""
        self.lost = True
        self.no_hand_ += 1
        self.too_few_ += corr is None
        return FrameResult(np.full(self.hand.n_dofs, np.nan), "lost", float("nan"), 0, n_in,
                           (time.perf_counter() - t0) * 1e3, 1.0 if corr is None else corr.rejected_share)

    def _refine_scale(self, pts, nrm, sil):
        """One more frame's size estimate; the size becomes the median of the estimates so far, θ
        follows it. ``scale_refine="search"``: the frame calibrated on its own
        (:func:`tracker.scale.calibrate_scale`, ~0.4 s), so that one frame's wrong size is outvoted (a
        first frame 16 % off stayed off: the local estimates, fitted from its size, lean towards it);
        ``"local"``: :func:`tracker.scale.parabola_scale` around the current size from this frame's fit
        (~30 ms)."""
        s, st = self.scale_, self.settings
        found = None
        if st.scale.refine == "search":
            self._add_wrist(sil)
            est, th_est, _ = calibrate_scale(self.context_for, pts, st.init, silhouette=sil, normals=nrm,
                                             scale_range=st.scale.range)
            if abs(math.log(est / s)) > SIZE_RESTART_LOG:
                # a size far from the tracked fit's: its search may hold a better start (its hand taken
                # before the probed sizes' contexts are dropped)
                found = (self.context_for(est).hand, th_est)
        else:
            # the points on the fingers' side of this frame's wrist (forearm points reward a larger hand)
            keep = hand_side(pts, self.hand, self.theta)
            pts, nrm = pts[keep], None if nrm is None else nrm[keep]
            sub = thin(pts, st.init.refine_points)
            est, _, _, _ = parabola_scale(self.context_for, self.theta, self.hand, pts[sub], s, silhouette=sil,
                                          normals=None if nrm is None else nrm[sub])
        est = float(np.clip(est, *st.scale.range))
        keep_key = round(float(np.median(self.scale_estimates_ + [est])), 5)
        # the sizes the search probed are not needed again
        self._keep_contexts(keep_key, s)
        self.scale_estimates_.append(est)
        new = float(np.median(self.scale_estimates_))
        if round(new, 5) != round(s, 5):
            old = self.hand
            self.scale_ = new
            self._use_scale(new)
            self.theta = rescaled(old, self.hand, self.theta)
            self.prev = None if self.prev is None else rescaled(old, self.hand, self.prev)
            self.last_good = self.theta
        if found is not None:
            self._take_better_start(pts, nrm, sil, *found)
        if st.scale.finger_lengths:
            self._size_frames.append((pts, nrm, sil, self.theta.copy(), self.hand))
        if st.scale.finger_lengths and len(self.scale_estimates_) >= st.scale.frames:
            self._find_finger_lengths()

    def _take_better_start(self, pts, nrm, sil, hand_est, theta_est):
        """While the size is refined by searches, the tracked θ is replaced by this frame's search
        (``theta_est`` on ``hand_est``) when that scores better by ``net_margin_mm``, both refitted at the
        size now in use (:func:`tracker.init.score`, the frame's wrist cue included). Asked only when the
        frame's size differs from the tracked fit's by more than :data:`SIZE_RESTART_LOG` (log): the
        first frame was searched at its own size, a size far off favours a wrong pose, and tracking
        then keeps that pose while the later frames' sizes outvote the size (realistic Kinect v1 0.8×
        scene, torso 4 cm behind, depth only: the first frame sized 0.97, its hand turned 38 mm off; the
        next frame's own search found 0.805 and a fit 1.8 mm off, and was thrown away). Not at sizes
        that agree: there a search scoring better is no better fit more often than it is (the 19 real
        stills tracked as one recording, each still a jump: every size frame replaced, the wrist of the
        next frames 50–65 px off against 17–40). ``size_starts_`` counts the replacements."""
        st, ctx = self.settings, self.context
        n = st.init.icp_iterations
        cand, c_cand = ctx.fit(rescaled(hand_est, self.hand, theta_est), pts, "full", 1, n, silhouette=sil,
                               normals=nrm)
        here, c_here = ctx.fit(self.theta, pts, "full", 1, n, silhouette=sil, normals=nrm)
        if (np.all(np.isfinite(cand))
                and score(ctx, cand, c_cand, sil) < score(ctx, here, c_here, sil) - st.net.margin_mm):
            self.theta = self.last_good = cand
            self.prev = None
            self._wrist_passed = None
            self.size_starts_ += 1

    def _find_finger_lengths(self):
        """Each finger's length factor at the settled size, from the frames that refined it (their θ
        moved onto the settled hand; :func:`tracker.scale.finger_scales`); θ keeps its meaning."""
        s = self.scale_
        ctx = self.context_for(s)
        frames = [(p, n, sil, rescaled(h, ctx.hand, th)) for p, n, sil, th, h in self._size_frames]
        # finger → (unshrunk factor, its standard error over the frames): the calibration record's spread
        self.finger_spread_ = {}
        self.finger_scales_ = finger_scales(ctx, self.base_hand, s, frames, spread=self.finger_spread_)
        self._size_frames = []
        self._use_scale(s)

    def calibrate_each(self, observations, camera):
        """Calibrate the hand (``hand_scale="auto"``) on frames that are each fitted from their own
        start: stills, or postures far apart in time, which tracking from frame to frame would not
        follow. Each frame's size is found alone (:func:`tracker.scale.calibrate_scale`, as the first
        frame's is), the size is their median, and with ``finger_lengths`` each finger's length comes
        from every frame's start search at that size (:func:`tracker.scale.finger_scales`: postures
        apart tell lengths apart best). Frames with fewer than ``min_points`` points are skipped. The
        tracker then tracks on the calibrated hand from a fresh start, and keeps it (however few
        frames it was calibrated on). Frames whose fit found no hand (``no_hand_rejected``) are skipped
        too. Returns the indices of the frames used.

        On the 19 labelled SR305 stills (one hand), calibrated on each recording's first 5 frames: size
        1.263 and 1.238, thumb 1.06, index 0.97, little finger 0.91 on 230536 — the ways the labelled tips
        lie beyond or short of the model's tips at the model's proportions — and the median fingertip
        error over the 19 frames 5.4 → 4.0 px against the size from one frame; but frames within every
        floor of issue 12 16 → 12 (a middle finger pointing at the camera 39 px off, fits that score
        alike; the report's "real labelled frames"). On an AMD EPYC, with the finger lengths' probes
        also fitted from the coupled last joint: size 1.279 and 1.237, index 0.90 and 0.93, little finger
        0.88 and 0.87; median 5.0 → 3.8 px, worst tip 19 px, frames within every floor 15 → 14."""
        st = self.settings
        if st.scale.hand_scale != "auto":
            raise TrackerError("calibration", "calibrate_each needs hand_scale='auto'")
        frames, used, est, seen = [], [], [], 0
        for i, ob in enumerate(observations):
            seen += 1
            sil = _silhouette(_silhouette_mask(ob), ob.depth, camera, ob.frame_depth)
            pts, nrm = _usable(ob.points, ob.normals, st.loss.max_points)
            if len(pts) < st.loss.min_points:
                continue
            self._add_wrist(sil)
            size, _, corr = calibrate_scale(self.context_for, pts, st.init, silhouette=sil, normals=nrm,
                                            scale_range=st.scale.range)
            if self._no_hand_sized(size, corr):
                self.no_hand_ += 1
                continue
            est.append(size)
            frames.append((pts, nrm, sil))
            used.append(i)
        if not est:
            raise TrackerError("calibration", f"no hand found in any of the {seen} frames")
        s = float(np.median(est))
        self.finger_scales_, self.calibrated_each_ = None, True
        # settled: tracking afterwards neither calibrates nor refines it (calibrated_each_)
        self._calibrations, self._scale_open = [], False
        self.scale_, self.scale_estimates_ = s, [float(e) for e in est]
        self._use_scale(s)
        self._keep_contexts(s)
        if st.scale.finger_lengths:
            self._size_frames = [(p, n, sil, self.fit_single_frame(p, silhouette=sil, normals=n)[0], self.hand)
                                 for p, n, sil in frames]
            self._find_finger_lengths()
        self.reset()
        return used

    def predict(self) -> np.ndarray:
        """The start of the next frame: the last θ plus ``prediction`` × its last change, except the
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

    def step(self, points, *, normals=None, mask=None, depth=None, camera=None, frame_depth=None,
             color=None) -> FrameResult:
        """Track one frame's segmented points ``(N, 3)`` (camera frame, metres; NaN rows ignored).

        With the hand ``mask``, the ``depth`` image (metres) and the ``camera``, model parts that
        leave the silhouette are pulled back (the silhouette term); with the whole ``frame_depth`` too,
        the start searches use the wrist cue (``wrist_cue``); with the ``color`` frame (and
        ``rgb_seed``) they start also from the colour keypoints."""
        sil = _silhouette(mask, depth, camera, frame_depth)
        t0 = time.perf_counter()
        st = self.settings
        pts, nrm = _usable(points, normals, st.loss.max_points)
        n_in = len(pts)
        net, recentred, far_lost = "", False, False
        if n_in < st.loss.min_points:
            # nothing seen: no θ is output (an unreadable frame's row repeated the frame before it, which
            # a user of the rows cannot tell from a measurement); the next start may still begin there
            self.lost = True
            return FrameResult(np.full(self.hand.n_dofs, np.nan), "lost", float("nan"), 0, n_in,
                               (time.perf_counter() - t0) * 1e3, 1.0)
        starting = self._calibrating() or self.lost or self.theta is None
        if starting and st.loss.start_min_pixels:
            # too little of anything to start a hand from: 26 DoF fitted to a few dozen points fit anything.
            # The region's pixels, not its points: a coarse stride (Fig. 9's 1/36) samples a whole hand sparsely
            region = n_in if sil is None or sil.empty else int(np.count_nonzero(sil.mask))
            if region < st.loss.start_min_pixels:
                return self._no_hand(None, n_in, t0)
        if self._calibrating():
            self._add_wrist(sil)
            theta, corr, found = self._calibrate(pts, nrm, sil)
            if not found:
                return self._no_hand(corr, n_in, t0)
            status = "reinit"
            self.prev = None
            self._wrist_passed = None
            if st.net.enabled:
                # what a good fit scores in this scene: clutter that stays (a forearm, a table) raises it
                self._search_level = score(self.context, theta, corr, sil)
        elif self.lost or self.theta is None:
            extra = () if self.last_good is None else (self.last_good,)
            seed = self._rgb_start(color, frame_depth if frame_depth is not None else depth, camera)
            self._add_wrist(sil)
            # the start's last fits hold its crease on the arm's centre line (IcpSettings.wrist_line_weight);
            # not a size calibration's (it moved a real recording's calibrated size, 1.276 → 1.256, and
            # tips by up to 40 px) nor the net's, whose result is compared with the tracked fit's
            theta, corr = self.fit_single_frame(pts, silhouette=sil, normals=nrm, extra=extra + seed,
                                                wrist=self._frame_cue(sil))
            if seed:
                theta, corr = self._rgb_refine(seed[0], theta, corr, pts, nrm, sil)
            if self._found_nothing(corr):
                return self._no_hand(corr, n_in, t0)
            status = "reinit"
            self.prev = None
            self._wrist_passed = None
            if st.net.enabled:
                # what a good fit scores in this scene: clutter that stays (a forearm, a table) raises it
                self._search_level = score(self.context, theta, corr, sil)
        else:
            ctx = self.context
            pred = self.predict()
            all_pts, all_nrm = pts, nrm
            # clutter the segmentation left beside the hand (table, torso, arm) cannot pull the fit; the
            # gate tests the prediction first, so that clutter cannot re-centre a prediction that was right
            keep, arm = self._gate(pred, pts) if st.observe.gate_mm > 0 else (None, None)
            if st.predict.recentre and (keep is None or keep.all()):
                moved = self._recentred(pred, pts)
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
            status = "tracked"
            if st.refine.finger_restart_deg and st.mode != "reduced":
                theta, corr, _ = restart_uncoupled(self.hand, theta, corr, tracking_fit,
                                                   lambda t, c: score(ctx, t, c, sil), self.limits,
                                                   tolerance_deg=st.refine.finger_restart_deg,
                                                   bent_back_deg=st.refine.finger_bent_back_deg or None)
            if st.net.enabled and st.mode != "reduced":
                theta, corr, pts, nrm, net = self._safety_net(theta, corr, pred, pts, nrm, all_pts, all_nrm, sil)
                if net == "replaced":
                    status = "reinit"
            elif st.net.enabled and self._far_off(theta, all_pts, most=200):
                # reduced mode has no net (its all-DoF searches would undo the subspace), but a fit that
                # leaves most of the segmented cloud far away is on something else: lost, not tracked
                # (a rendered hand in front of the body, segmented with the body: 284 of 2329 points
                # kept by the gate, fitted onto the torso 270 mm away and reported tracked)
                far_lost = True
        # a start has no earlier frame that holds its unseen joints: all the way. The net's replacement
        # half the way, as tracked frames: it starts from the tracked fit too, and all the way there made the
        # hard cases' fast sweeps 7.6 -> 8.7 deg (Kinect v1 noise 14.0 -> 16.1) and the turn 6.5 -> 7.1 with noise
        theta = self._unseen_pulled(theta, corr, 1.0 if status == "reinit" and net != "replaced" else None)
        if st.start.check_hand and self.hand_check_ is None and status == "reinit":
            self.hand_check_ = self._check_hand(pts, nrm, sil, theta, corr)
        fit_mm = corr.fit_error_mm()
        rejected = corr.rejected_share
        if np.isfinite(fit_mm) and fit_mm <= st.loss.lost_fit_mm and rejected <= st.loss.lost_rejected and not far_lost:
            self.prev, self.theta = (self.theta if status == "tracked" else None), theta
            if recentred and self.prev is not None:
                # the jump was no velocity: the next prediction must not repeat it
                self.prev = self.prev.copy()
                self.prev[:3] = theta[:3]
            self.last_good = theta
            self.lost = False
            if (status == "tracked" and not self.calibrated_each_
                    and len(self.scale_estimates_) < (st.scale.frames if st.scale.hand_scale == "auto" else 0)):
                self._refine_scale(pts, nrm, sil)
        else:
            self.lost, status, self.theta, self.prev = True, "lost", theta, None
        # a fit on something else gives no θ (as a start that found no hand: the frame's row must not
        # read as a hand's pose)
        out = np.full(self.hand.n_dofs, np.nan) if far_lost else _output_theta(theta)
        return FrameResult(out, status, fit_mm, corr.used, n_in, (time.perf_counter() - t0) * 1e3, float(rejected), net)

    def segment_window(self, camera):
        """Where to segment the next frame (``observe(..., window=...)``): :func:`tracker.observe.hand_window`
        of the hand predicted for it, grown by ``observe.window_m``; None — the whole frame — when no
        hand is tracked (not started, lost, its size still being calibrated) or windows are off."""
        st = self.settings
        if not st.observe.window_m or self.lost or self.theta is None or self._calibrating():
            return None
        P, _ = posed_samples(self.hand, self.context.score_samples, self.predict())
        return hand_window(P, camera, st.observe.window_m)

    def _unseen_pulled(self, theta, corr, share=None) -> np.ndarray:
        """θ with the posture DoF that no data point constrains moved ``unseen_prior`` (``share``
        when given) of the way to the synergy model's Gaussian conditional mean given the other
        posture DoF (``corr``: the fit's correspondences; a DoF is unseen when fewer than
        ``unseen_points`` valid pairs lie on the parts it moves). Unchanged when every DoF, or none, is
        seen (nothing to condition on), or when ``unseen_prior`` is 0 (off)."""
        st = self.settings
        if not st.refine.unseen_prior or self._unseen is None or st.mode == "reduced":
            return theta
        moves, mu, S = self._unseen
        counts = np.bincount(corr.nodes[corr.valid], minlength=self.hand.n_nodes)
        hid = moves @ counts < st.refine.unseen_points
        if not hid.any() or hid.all():
            return theta
        seen = ~hid
        post = np.flatnonzero(~self.hand.pose_mask)
        x = theta[post]
        cond = mu[hid] + S[np.ix_(hid, seen)] @ np.linalg.solve(S[np.ix_(seen, seen)], x[seen] - mu[seen])
        out = np.array(theta, float)
        idx = post[hid]
        share = st.refine.unseen_prior if share is None else share
        out[idx] = np.clip(x[hid] + share * (cond - x[hid]), self.limits[idx, 0], self.limits[idx, 1])
        self.unseen_frames_ += 1
        return out

    def _rgb_start(self, color, depth, camera) -> tuple:
        """``(θ,)`` fitted to the colour keypoints of this frame, or ``()`` (no ``rgb_seed``, no
        colour, no hand found)."""
        if self.rgb_ is None or color is None or depth is None or camera is None:
            return ()
        th = self.rgb_(self.hand, color, depth, camera)
        if th is None:
            return ()
        self.rgb_seeds_ += 1
        return (th,)

    def _rgb_refine(self, seed, theta, corr, pts, nrm, sil):
        """The colour seed refined by the tracking ICP alone, kept over the search's winner when the
        depth fits it at least as well (fit error no higher, no more than 5 % more points rejected).
        Not by :func:`tracker.init.score`: a hand turned over explains the depth about as well, and
        the score's wrist cue can favour it (measured on rendered hands alone: the seed refined to
        0.5 mm fit error scored 70 against a turned-over hand's 28, 87 mm off); the colour image
        sees which way the hand faces and where its wrist is."""
        ctx, st = self.context, self.settings
        th, c = fit(self.hand, pts, seed, self.stages, ctx.matcher, st.icp, n_rigid=st.icp.rigid_iterations,
                    normals=nrm, samples=ctx.samples, silhouette=sil)
        if (np.all(np.isfinite(th)) and c.fit_error_mm() <= corr.fit_error_mm()
                and c.valid.mean() >= corr.valid.mean() - 0.05):
            self.rgb_kept_ += 1
            return th, c
        return theta, corr

    def _add_wrist(self, sil):
        """The frame's wrist cue on its silhouette, where :func:`tracker.init.score` finds it (added only
        when a search is about to run: tracking does not score by it)."""
        if sil is not None and self.settings.start.wrist_cue and not hasattr(sil, "wrist"):
            sil.wrist = self._frame_cue(sil)

    def _frame_cue(self, sil):
        """The frame's wrist cue (:func:`tracker.wrist.wrist_cue`) when an arm's worth of surface lies
        behind it (:func:`tracker.wrist.arm_behind`), else None; found once per frame (kept on the
        silhouette as ``arm_cue``, which :func:`tracker.init.score` does not read)."""
        if sil is None or not self.settings.start.wrist_cue:
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

    def _recentred(self, pred, pts):
        """The prediction moved onto the cloud when their centres are farther apart than the rejection
        radius (a hand faster than the prediction: no correspondence would reach it). The cloud is the
        near side of the hand, so only the model's camera-facing samples are its counterpart."""
        shift = centre_shift(pts, posed_samples(self.hand, self.context.score_samples, pred))
        if shift is None or np.linalg.norm(shift) * 1000.0 <= self.settings.correspond.reject_mm:
            return pred
        self.recentred_ += 1
        out = pred.copy()
        out[:3] += shift
        return out

    def _net_threshold(self) -> float:
        """The score (mm) above which a frame is doubtful: ``net_score_mm``, or ``net_score_ratio`` ×
        the scene's level when higher."""
        st = self.settings
        level = max(np.median(self._scores) if self._scores else 0.0, self._search_level)
        return max(st.net.score_mm, st.net.score_ratio * level)

    def _doubtful(self, theta, pred, s, sil=None, points=None, near_mm=None) -> str:
        """The safety net's test of a tracked frame: why it is doubtful — ``"wrist"`` (the hand points
        the wrong way: :meth:`_wrong_way`), ``"far"`` (more than ``net_far_share`` of the ``points``
        farther than ``net_far_mm`` from the hand's surface), ``"score"`` (a poor score for this
        sequence) or ``"jump"`` (far from the prediction) — or ``""``. ``near_mm``: the ``points``'
        :func:`tracker.correspond.data_to_model_mm` at ``theta`` when already measured (the score's
        data term measures the same points: :meth:`_safety_net` passes them)."""
        st = self.settings
        if self._wrong_way(theta, sil):
            return "wrist"
        if self._far_off(theta, points, near_mm=near_mm):
            return "far"
        # the threshold is never below net_score_mm: most frames are decided without the level's median
        if s > st.net.score_mm and s > self._net_threshold():
            return "score"
        turn, moved = _pose_change(theta, pred)
        if turn > st.net.jump_deg or moved > st.net.jump_mm:
            return "jump"
        return ""

    def _far_off(self, theta, points, *, most=None, near_mm=None) -> bool:
        """Whether more than ``net_far_share`` of ``points`` lie farther than ``net_far_mm`` from the hand
        at ``theta`` (the safety net's far-points test, :meth:`_doubtful`). ``near_mm``: the points'
        :func:`tracker.correspond.data_to_model_mm` when already measured; ``most``: else measured on
        every k-th point, at most that many (a share needs no more: reduced mode runs the test on every
        frame, 0.18 ms at 900 points, 0.12 ms at 200)."""
        st = self.settings
        if not st.net.far_share or points is None or not len(points):
            return False
        if near_mm is None:
            if most is not None:
                points = points[::-(-len(points) // most)]
            near_mm = data_to_model_mm(self.context.matcher, theta, points)
        return bool(np.mean(near_mm > st.net.far_mm) > st.net.far_share)

    def _wrong_way(self, theta, sil) -> bool:
        """Whether the scene contradicts the hand's orientation: the frame's wrist cue
        (:meth:`_frame_cue`) costs the hand at ``theta`` more than ``net_wrist_mm``
        (:func:`tracker.wrist.wrist_cost_mm`: its wrist far from where the arm enters, or its fingers
        pointing up the arm), and the surface beyond the cue goes on for at least ``net_arm_m`` — an
        arm, not a piece of the hand the segmentation cut off (:func:`tracker.wrist.arm_length_m`;
        only measured when the cost is high, ~1–3 ms). A hand turned over fits a flat palm about as
        well as the right one and need not jump, so neither the score nor the jump test sees it.

        Its price is the cue on every tracked frame: where an arm goes on past the outline
        :func:`tracker.wrist.wrist_cue` and :func:`tracker.wrist.arm_behind` take ~0.9 ms (rendered forearm
        and torso, Kinect v1; SR305 noise ~0.7 ms; 1.6 / 1.3 ms before their window work was compiled);
        ~5 µs where nothing does (a hand alone)."""
        st = self.settings
        if not st.net.wrist.cost_mm:
            return False
        entry = self._arm_entry(sil)
        last = self._wrist_passed
        if last is not None and last[2] + 1 < st.net.wrist.every and _same_entry(entry, last[1], st.net.wrist.moved[1]):
            turn, moved = _pose_change(theta, last[0])
            if turn <= st.net.wrist.moved[0] and moved <= st.net.wrist.moved[1]:
                # the test's two inputs as when it last passed: the hand's pose and where the arm
                # enters the frame (a scene turned round under a fit that stayed moves the entry)
                self._wrist_passed = (last[0], last[1], last[2] + 1)
                return False
        self.wrist_tests_ += 1
        cue = self._frame_cue(sil)
        wrong = (cue is not None and wrist_cost_mm(cue, self.hand, theta) > st.net.wrist.cost_mm
                 and arm_length_m(cue, sil.mask, sil.frame_depth, sil.camera) >= st.net.wrist.arm_m)
        self._wrist_passed = None if wrong else (np.array(theta, float), entry, 0)
        return wrong

    @staticmethod
    def _arm_entry(sil):
        """``(count, point)`` of :func:`tracker._wrist_kernels.arm_entry` on the silhouette: how many
        pixels continue the hand's surface past its outline and their mean, lifted to 3-D (m)."""
        frame = getattr(sil, "frame_depth", None)
        if sil is None or sil.empty or frame is None:
            return 0, None
        n, v, u = arm_entry(sil.dist, sil.iv, sil.iu, frame, int(sil.v0), int(sil.u0), 2.0, 0.015)
        if not n:
            return 0, None
        z = frame[int(round(v)), int(round(u))]
        if not np.isfinite(z):
            z = np.nanmedian(frame[sil.mask])
        c = sil.camera
        return n, np.array([(u - c.cx) * z / c.fx, (v - c.cy) * z / c.fy, z])

    def _safety_net(self, theta, corr, pred, pts, nrm, all_pts, all_nrm, sil):
        """``(θ, corr, points, normals, what)``: the tracked estimate, or the cheap start search's on the
        whole segmented cloud when the frame is doubtful and the search scores better."""
        ctx = self.context
        near = None
        if corr.points is not None and (corr.points is all_pts or np.array_equal(corr.points, all_pts)):
            # the score's data term and the far-points test measure the same points at the same θ:
            # once (~0.05 ms a frame at 500 points)
            near = data_to_model_mm(ctx.matcher, theta, all_pts)
        s = score(ctx, theta, corr, sil, data_mm=near)
        why = self._doubtful(theta, pred, s, sil, all_pts, near_mm=near)
        if not why:
            # the sequence's level that later frames are judged against: undoubted frames only (a
            # level learnt from doubtful ones rises with a fit going wrong and stops the net)
            self._scores.append(s)
            return theta, corr, pts, nrm, ""
        t0 = time.perf_counter()
        self.net_runs_ += 1
        if why == "wrist":
            self.net_wrong_way_ += 1
        if self.settings.net.wrist.cue or why == "wrist":
            # the cue made the frame doubtful: without it the comparison would keep the hand turned
            # over, which fits the depth as well as the right one
            self._add_wrist(sil)
        # both on the same (whole) cloud, and with the wrist cue, so that their scores compare
        c_all = corr if all_pts is pts else ctx.matcher(theta, all_pts, all_nrm)
        s_track = score(ctx, theta, c_all, sil)
        starts = (theta,) if self.last_good is None else (theta, self.last_good)
        st = self.settings
        best = (s_track, None, None)
        if st.net.anchored:
            # a posture gone wrong under a right global pose (fingers hidden, a fast close) is the
            # common failure: the posture search from the tracked pose fits no placements and cannot
            # pick a wrong one
            th2, c2 = fit_single_frame(ctx, all_pts, InitSettings.cheap(refit_pose=True), theta0=theta,
                                       silhouette=sil, normals=all_nrm, extra=starts)
            self.net_anchored_ += 1
            best = min(best, (score(ctx, th2, c2, sil), th2, c2), key=lambda b: b[0])
        if not st.net.anchored or best[0] > self._net_threshold():
            # still doubtful: the hand may have turned beyond the tracked pose's reach
            th2, c2 = fit_single_frame(ctx, all_pts, InitSettings.cheap(), silhouette=sil, normals=all_nrm, extra=starts)
            self.net_placed_ += 1
            best = min(best, (score(ctx, th2, c2, sil), th2, c2), key=lambda b: b[0])
        self.net_ms_ += (time.perf_counter() - t0) * 1e3
        if (best[1] is not None and best[0] < s_track - st.net.margin_mm
                and (why != "wrist" or _without_cue(ctx, best[1], best[2], sil)
                     <= _without_cue(ctx, theta, c_all, sil) + st.net.wrist.fit_mm)):
            self.net_replaced_ += 1
            self.prev = None
            self._wrist_passed = None
            return best[1], best[2], all_pts, all_nrm, "replaced"
        return theta, corr, pts, nrm, "kept"


#: A size-refining frame's search may replace the tracked fit (:meth:`HandTracker._take_better_start`)
#: when its size differs from the tracked fit's by more than this (log; 6 %, as
#: :func:`tracker.scale.calibrate_scale` searches again when the size moved so far).
SIZE_RESTART_LOG = 0.06


def _without_cue(ctx, theta, corr, sil) -> float:
    """:func:`tracker.init.score` of θ without the frame's wrist cue (both directions' terms only)."""
    if getattr(sil, "wrist", None) is None:
        return score(ctx, theta, corr, sil)
    bare = copy.copy(sil)
    bare.wrist = None
    return score(ctx, theta, corr, bare)


def _unseen_parts(hand, synergies):
    """``(moves, mean, covariance)`` for :meth:`HandTracker._unseen_pulled`, or None without
    synergies: ``moves (20, nodes)`` is 1 where a posture DoF moves a node (the node it drives and
    every node below it); the covariance is the synergy model's over all its components, with a
    small ridge (1e-4 rad²) so that the seen joints' block is always invertible."""
    if synergies is None:
        return None
    moves = hand.dof_moves[~hand.pose_mask].astype(float)
    m = synergies.model
    C, lam = np.asarray(m.all_components_, float), np.asarray(m.all_explained_variance_, float)
    S = C.T @ (lam[:, None] * C) + 1e-4 * np.eye(C.shape[1])
    return moves, np.asarray(m.mean_, float), S


def _silhouette_mask(observation):
    """The mask an observation's silhouette term fits: its mask widened by the sensor's dropout band
    (:func:`tracker.observe.dropout_band`) where it has one."""
    return observation.mask if observation.silhouette is None else observation.silhouette


def _silhouette(mask, depth, camera, frame_depth):
    """The :class:`~tracker.correspond.Silhouette` of a frame (None without a mask, depth or camera),
    carrying the whole frame's depth for the wrist cue."""
    if mask is None or camera is None or depth is None:
        return None
    sil = Silhouette(mask, depth, camera)
    sil.frame_depth = frame_depth
    return sil


def _usable(points, normals, max_points):
    """Finite points (at most ``max_points``, evenly spread) and their normals; NaN normals (unknown)
    stay: the normal test is skipped for them."""
    pts = np.asarray(points, float).reshape(-1, 3)
    keep = np.isfinite(pts).all(1)
    if max_points and keep.sum() > max_points:
        idx = np.flatnonzero(keep)
        keep[:] = False
        keep[idx[np.linspace(0, len(idx) - 1, max_points).astype(int)]] = True
    nrm = None if normals is None else np.asarray(normals, float).reshape(-1, 3)[keep]
    return pts[keep], nrm
