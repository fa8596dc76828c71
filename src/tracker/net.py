"""The safety net: every tracked frame tested (:meth:`SafetyNet.doubtful`), and a doubtful one given the
cheap start search, whose estimate replaces the tracked one when it scores better
(:class:`tracker.settings.SafetyNetSettings`; why each default: ``docs/tracker.md``).
"""
from __future__ import annotations

import copy
import math
import time
from collections import deque

import numpy as np

from handmodel.rigid import euler_to_matrix

from ._wrist_kernels import arm_entry
from .correspond import data_to_model_mm
from .init import InitSettings, SearchBudget, fit_single_frame, restart_fingers, score
from .parts import KeypointSeed, TrackerStats, WristCue
from .wrist import arm_length_m, wrist_cost_mm


class SafetyNet:
    """The net of one sequence: the scene's score level, the wrong-way test's last pass and the search.

    Parameters
    ----------
    settings : :class:`tracker.settings.SafetyNetSettings`
    cue : the :class:`tracker.parts.WristCue` of the tracker's frames
    stats : the tracker's :class:`tracker.parts.TrackerStats`
    keypoints : the depth keypoint detector's :class:`tracker.parts.KeypointSeed` (``start.detector``):
        the search beyond the tracked pose starts from the detected hand first
    """

    def __init__(self, settings, cue: WristCue, stats: TrackerStats | None = None, budget_ms: float = 0.0,
                 keypoints: KeypointSeed | None = None):
        self.settings, self.cue, self.stats, self.keypoints = settings, cue, stats or TrackerStats(), keypoints
        self.budget_ms = budget_ms  # a frame's searches together (start.search_budget_ms; 0 = none)
        self._scores = deque(maxlen=30)  # the undoubted frames' (and replacements') scores: the scene's level
        self.search_level = 0.0  # the last start's score: what a good fit scores in this scene
        self._wrist_passed = None  # (θ, arm entry, frames since) of the last hand the wrist test passed

    def reset(self):
        """Forget the last hand the wrist test passed (a new start follows)."""
        self._wrist_passed = None

    def threshold(self) -> float:
        """The score (mm) above which a frame is doubtful: ``score_mm``, or ``score_ratio`` × the scene's
        level (the ``level_quantile`` of the last undoubted frames' scores and, with ``level_replaced``, the
        net's replacements', or the last start's if higher). A low quantile, not the median: fits that
        pass under the threshold raise it, and where most of them are mediocre (fast sweeps under the
        Kinect v1 noise: scores of 2–3 mm where a right fit scores ~1) the median follows them up and
        the net stops seeing them (the threshold 1.2 → 6.7 mm in 80 frames, the posture 23° off)."""
        q = self.settings.level_quantile
        # the median itself at 0.5 (paper()): np.quantile's interpolation differs from it in the last bit
        level = max((np.median(self._scores) if q == 0.5 else linear_quantile(self._scores, q)) if self._scores else 0.0,
                    self.search_level)
        return max(self.settings.score_mm, self.settings.score_ratio * level)

    def doubtful(self, ctx, theta, pred, s, sil=None, points=None, near_mm=None) -> str:
        """Why a tracked frame (θ ``theta`` on ``ctx``'s hand, predicted ``pred``, scoring ``s``) is
        doubtful — ``"wrist"`` (:meth:`wrong_way`), ``"far"`` (:meth:`far_off`), ``"score"`` (above
        :meth:`threshold`) or ``"jump"`` (far from the prediction) — or ``""``. ``near_mm``: the
        ``points``' :func:`tracker.correspond.data_to_model_mm` at ``theta`` when already measured."""
        st = self.settings
        if self.wrong_way(ctx.hand, theta, sil):
            return "wrist"
        if self.far_off(ctx, theta, points, near_mm=near_mm):
            return "far"
        # the threshold is never below score_mm: most frames are decided without the level's median
        if s > st.score_mm and s > self.threshold():
            return "score"
        turn, moved = pose_change(theta, pred)
        if turn > st.jump_deg or moved > st.jump_mm:
            return "jump"
        return ""

    def is_motion(self, before, after) -> bool:
        """Whether the change of the global pose from θ ``before`` (the frame before) to a replacement
        ``after`` is within the jump limits (``jump_deg``, ``jump_mm``): the hand's motion, which the next
        prediction may go on with (:attr:`tracker.settings.PredictSettings.through_net`: a hand faster than
        the fit's reach is replaced frame after frame, and each replacement predicted without its motion
        missed the next frame again by ~37 mm), not a correction of a wrong fit (the turn to the back
        under the Kinect v1 noise: a hand turned back over, repeated as a velocity, put the next
        prediction 80–100 mm off)."""
        turn, moved = pose_change(after, before)
        return turn <= self.settings.jump_deg and moved <= self.settings.jump_mm

    def far_off(self, ctx, theta, points, *, most=None, near_mm=None) -> bool:
        """Whether more than ``far_share`` of ``points`` lie farther than ``far_mm`` from the hand at
        ``theta``. ``near_mm``: their distances when already measured; ``most``: else measured on every
        k-th point, at most that many (a share needs no more: reduced mode runs the test on every frame)."""
        st = self.settings
        if not st.far_share or points is None or not len(points):
            return False
        if near_mm is None:
            if most is not None:
                points = points[::-(-len(points) // most)]
            near_mm = data_to_model_mm(ctx.matcher, theta, points)
        return bool(np.mean(near_mm > st.far_mm) > st.far_share)

    def wrong_way(self, hand, theta, sil) -> bool:
        """Whether the scene contradicts the hand's orientation: the frame's wrist cue costs the hand at
        ``theta`` more than ``wrist.cost_mm`` (:func:`tracker.wrist.wrist_cost_mm`) and the surface
        beyond the cue goes on for ``wrist.arm_m`` (an arm, :func:`tracker.wrist.arm_length_m`). Rerun
        in full only when the pose or the arm's entry moved since it last passed, and at least every
        ``wrist.every`` frames (``stats.wrist_tests``)."""
        st = self.settings.wrist
        if not st.cost_mm:
            return False
        entry = arm_entry_point(sil)
        last = self._wrist_passed
        if last is not None and last[2] + 1 < st.every and _same_entry(entry, last[1], st.moved[1]):
            turn, moved = pose_change(theta, last[0])
            if turn <= st.moved[0] and moved <= st.moved[1]:
                # the test's two inputs as when it last passed: the hand's pose and where the arm
                # enters the frame (a scene turned round under a fit that stayed moves the entry)
                self._wrist_passed = (last[0], last[1], last[2] + 1)
                return False
        self.stats.wrist_tests += 1
        cue = self.cue.of(sil)
        wrong = (cue is not None and wrist_cost_mm(cue, hand, theta) > st.cost_mm
                 and arm_length_m(cue, sil.mask, sil.frame_depth, sil.camera) >= st.arm_m)
        self._wrist_passed = None if wrong else (np.array(theta, float), entry, 0)
        return wrong

    def __call__(self, ctx, theta, corr, pred, pts, nrm, all_pts, all_nrm, sil, last_good, absent=None):
        """``(θ, corr, points, normals, what)``: the tracked estimate (``what`` ``""``: not doubtful, or
        ``"kept"``), or the cheap start search's on the whole segmented cloud (``"replaced"``) when the
        frame is doubtful and the search scores better by ``margin_mm``; ``"absent"`` when the frame is
        doubtful and ``absent()`` says its region is no hand (nothing searched)."""
        near = None
        if corr.points is not None and (corr.points is all_pts or np.array_equal(corr.points, all_pts)):
            # the score's data term and the far-points test measure the same points at the same θ:
            # once (~0.05 ms a frame at 500 points)
            near = data_to_model_mm(ctx.matcher, theta, all_pts)
        s = score(ctx, theta, corr, sil, data_mm=near)
        why = self.doubtful(ctx, theta, pred, s, sil, all_pts, near_mm=near)
        if not why:
            # the sequence's level that later frames are judged against: undoubted frames only (a
            # level learnt from doubtful ones rises with a fit going wrong and stops the net)
            self._scores.append(s)
            return theta, corr, pts, nrm, ""
        if absent is not None and absent():
            # a search on a region that is no hand can only move the hand onto it
            return theta, corr, pts, nrm, "absent"
        t0 = time.perf_counter()
        self.stats.net_runs += 1
        self.stats.net_wrong_way += why == "wrist"
        if self.settings.wrist.cue or why == "wrist":
            # the cue made the frame doubtful: without it the comparison would keep the hand turned
            # over, which fits the depth as well as the right one
            self.cue.add(sil)
        # both on the same (whole) cloud, and with the wrist cue, so that their scores compare
        c_all = corr if all_pts is pts else ctx.matcher(theta, all_pts, all_nrm)
        s_track = score(ctx, theta, c_all, sil)
        best = self._search(ctx, theta, all_pts, all_nrm, sil, last_good, (s_track, None, None))
        self.stats.net_ms += (time.perf_counter() - t0) * 1e3
        st = self.settings
        if (best[1] is not None and best[0] < s_track - st.margin_mm
                and (why != "wrist" or _without_cue(ctx, best[1], best[2], sil)
                     <= _without_cue(ctx, theta, c_all, sil) + st.wrist.fit_mm)):
            self.stats.net_replaced += 1
            self._wrist_passed = None
            if st.level_replaced:
                # what the search found is what a right fit scores in this scene: without it, a run of
                # replaced frames leaves the level to the mediocre fits that passed, and it creeps up
                self._scores.append(best[0])
            return best[1], best[2], all_pts, all_nrm, "replaced"
        return theta, corr, pts, nrm, "kept"

    def _search(self, ctx, theta, pts, nrm, sil, last_good, best):
        """The best ``(score, θ, corr)`` of ``best`` and the cheap searches: anchored on the tracked
        global pose first (a posture gone wrong under a right pose is the common failure), from
        placements in the cloud when that still scores above the threshold (the hand may have turned
        beyond the tracked pose's reach). Both share the frame's budget (``budget_ms``): the search from
        placements does not follow the anchored one once that has spent it."""
        starts = (theta,) if last_good is None else (theta, last_good)
        budget = SearchBudget(self.budget_ms)
        if self.settings.anchored:
            th2, c2 = fit_single_frame(ctx, pts, InitSettings.cheap(refit_pose=True), theta0=theta,
                                       silhouette=sil, normals=nrm, extra=starts, budget=budget)
            self.stats.net_anchored += 1
            best = min(best, (score(ctx, th2, c2, sil), th2, c2), key=lambda b: b[0])
        found = ()
        if (self.keypoints is not None and (not self.settings.anchored or best[0] > self.threshold())
                and not budget.spent("detected")):
            # detected only when there is time to search from it
            found = self.keypoints.start(ctx.hand, sil)
        if found:
            # the detected hand's pose is a measurement of where the hand turned to: searched from first
            # (the placements' search costs ~3× as much), the placements only if that still scores poorly
            cheap = InitSettings.cheap()
            th2, c2 = fit_single_frame(ctx, pts, cheap, theta0=found[0], silhouette=sil, normals=nrm,
                                       extra=starts + found, search=False, budget=budget)
            if not budget.spent("fingers"):
                th2, c2 = restart_fingers(ctx, th2, c2, pts, cheap, silhouette=sil, normals=nrm)
            best = min(best, (score(ctx, th2, c2, sil), th2, c2), key=lambda b: b[0])
            placements = best[0] > self.threshold() and not budget.spent("placements")
        else:
            placements = not self.settings.anchored or (best[0] > self.threshold() and not budget.spent("placements"))
        if placements:
            th2, c2 = fit_single_frame(ctx, pts, InitSettings.cheap(), silhouette=sil, normals=nrm, extra=starts,
                                       budget=budget)
            self.stats.net_placed += 1
            best = min(best, (score(ctx, th2, c2, sil), th2, c2), key=lambda b: b[0])
        self.stats.net_cut += bool(budget.cut_)
        return best


def linear_quantile(values, q) -> float:
    """``np.quantile(values, q)`` (its default, linear method) of a short sequence, to the last bit: the
    same index and interpolation arithmetic on the sorted values, without numpy's ~30 µs a call (the net's
    threshold takes it on most frames of a cluttered scene).

    >>> linear_quantile([3.0, 1.0, 2.0, 10.0], 0.25), float(np.quantile([3.0, 1.0, 2.0, 10.0], 0.25))
    (1.75, 1.75)
    """
    a = sorted(float(x) for x in values)
    n = len(a)
    if any(x != x for x in a):
        return math.nan
    v = (n - 1) * q  # numpy's virtual index of the linear method
    if v >= n - 1:
        return a[-1]
    if v < 0:
        return a[0]
    lo = math.floor(v)
    t = v - lo
    x, y = a[int(lo)], a[int(lo) + 1]
    d = y - x
    return y - d * (1 - t) if t >= 0.5 else x + d * t


def pose_change(a, b) -> tuple:
    """``(degrees, mm)``: how far the global pose of θ ``a`` is turned and moved from ``b``'s."""
    R = euler_to_matrix(a[3:6]) @ euler_to_matrix(b[3:6]).T
    turn = math.degrees(math.acos(min(max(float((np.trace(R) - 1.0) / 2.0), -1.0), 1.0)))
    return turn, float(np.linalg.norm(np.asarray(a[:3]) - np.asarray(b[:3])) * 1000.0)


def arm_entry_point(sil):
    """``(count, point)`` of :func:`tracker._wrist_kernels.arm_entry` on the silhouette: how many pixels
    continue the hand's surface past its outline and their mean, lifted to 3-D (m)."""
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


def _same_entry(a, b, mm) -> bool:
    """Whether two :func:`arm_entry_point` results tell the same arm: none in both, or both within ``mm``."""
    if a[1] is None or b[1] is None:
        return a[1] is None and b[1] is None
    return float(np.linalg.norm(a[1] - b[1])) * 1000.0 <= mm


def _without_cue(ctx, theta, corr, sil) -> float:
    """:func:`tracker.init.score` of θ without the frame's wrist cue (both directions' terms only)."""
    if getattr(sil, "wrist", None) is None:
        return score(ctx, theta, corr, sil)
    bare = copy.copy(sil)
    bare.wrist = None
    return score(ctx, theta, corr, bare)
