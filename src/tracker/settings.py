"""Every knob of the tracker, grouped by concern: :class:`TrackerSettings` holds the mode and one
small frozen settings group per concern — the stages' (:class:`tracker.observe.ObserveSettings`,
:class:`tracker.correspond.CorrespondSettings`, :class:`tracker.icp.IcpSettings`,
:class:`tracker.init.InitSettings`) and the tracker's own below. Each group checks itself
(``check()``) and has the paper's values (``paper()``); ``TrackerSettings.paper()`` is the paper's
method (§VI, FORMAT.md §5), the defaults are ours. Why each default is what it is (the measurements):
``docs/tracker.md``, "Settings: why each default".

Change fields with :meth:`~tracker.settings_base.SettingsGroup.replace`: top-level ones by name, a
group's by a dict (or a whole group):

>>> s = TrackerSettings.paper()
>>> (s.icp.rigid_iterations, s.icp.icp_iterations, s.icp.gn_iterations, s.observe.stride)
(1, 4, 5, 3)
>>> t = TrackerSettings().replace(mode="reduced", icp=dict(robust_mm=0.0), net=dict(wrist=dict(every=1)))
>>> (t.mode, t.icp.robust_mm, t.net.wrist.every, t.net.score_mm)
('reduced', 0.0, 1, 0.7)
>>> TrackerSettings().replace(scale=dict(hand_scale=9.0)).check()
Traceback (most recent call last):
...
tracker.errors.TrackerError: scale.hand_scale: must be 'auto' or a factor in 0.6–2 (the hand model's size × it), got 9.0
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

from .correspond import CorrespondSettings
from .coupling import BENT_BACK_DEG
from .errors import TrackerError
from .icp import MODES, IcpSettings
from .icp_settings import KeypointTermSettings
from .init import InitSettings
from .observe import ObserveSettings
from .settings_base import SettingsGroup

LIMITS = ("anatomical", "data", "model")


def _need(ok, where, reason):
    if not ok:
        raise TrackerError(where, reason)


@dataclass(frozen=True)
class SubspaceSettings(SettingsGroup):
    """The synergy subspace and the joint limits.

    n_pcs : PCs of the reduced modes (None: those that explain ``variance``)
    variance : share of the synergies' variance the PCs explain, in (0, 1) (0.99)
    hierarchy : PC counts of the reduced stages before all DoF in single-frame fits ((1, 4))
    limits : joint limits, "anatomical" (handmodel's), "data" (the bundle's joint min/max) or "model"
        (the model file's) ("anatomical")
    """

    n_pcs: int | None = None
    variance: float | None = 0.99
    hierarchy: tuple = (1, 4)
    limits: str = "anatomical"

    def check(self):
        _need(self.limits in LIMITS, "subspace.limits", f"must be one of {', '.join(LIMITS)}, got {self.limits!r}")
        _need(self.n_pcs is None or int(self.n_pcs) >= 1, "subspace.n_pcs", f"must be ≥ 1, got {self.n_pcs!r}")
        _need(self.n_pcs is not None or self.variance is None or 0.0 < self.variance < 1.0, "subspace.variance",
              f"must be a fraction in (0, 1), got {self.variance}")


@dataclass(frozen=True)
class PredictSettings(SettingsGroup):
    """The start of a tracked frame's fit.

    share : share of the last frame's change added to its θ (0 = off; 1.0)
    recentre : move the prediction onto the cloud when their centres lie farther apart than the
        rejection radius (:class:`tracker.recentre.Recentring`; True, the paper: False)
    turn : the global rotation's last change added too (``share`` of it, as a rotation about the same
        axis; False: on, a real still's wrist in the 19 stills tracked as one recording went to 51 px)
    through_net : the safety net's replacement keeps the hand's motion: the next prediction moves the
        global pose on by its change from the frame before to the replacement, when that is within the
        net's jump limits (:meth:`tracker.net.SafetyNet.is_motion`; the posture's change is a correction,
        not motion) (True, the paper: False)
    jump_presence : a frame whose points the prediction missed (re-centred), or whose fit the safety net
        doubts (before its search), is asked the start's question first, whether its region is a hand
        (``start.presence``, the detected hand's fit overruling as at a start); where not, the frame gives
        the prediction (status ``"predicted"``) and nothing more is fitted or searched: a segmentation that
        took the forearm's far end is not followed there (True; no effect without ``start.presence``)
    """

    share: float = 1.0
    recentre: bool = True
    turn: bool = False
    through_net: bool = True
    jump_presence: bool = True

    @classmethod
    def paper(cls):
        return cls(recentre=False, turn=False, through_net=False, jump_presence=False)


@dataclass(frozen=True)
class LossSettings(SettingsGroup):
    """When a frame is lost, or found no hand (:class:`tracker.loss.LossCheck`).

    lost_fit_mm : a fit error above this loses the frame (mm; 12)
    lost_rejected : so does a larger share of rejected points (0.6)
    min_points : a frame with fewer points is lost unfitted (30)
    max_points : at most this many points are fitted, evenly spread (None = all)
    no_hand_rejected : a start whose fit rejects more than this share of its points found no hand:
        lost, no θ (0 = off; 0.2, the paper: 0)
    start_min_pixels : a start needs a segmented region of this many pixels (0 = off; 150, the paper: 0)
    """

    lost_fit_mm: float = 12.0
    lost_rejected: float = 0.6
    min_points: int = 30
    max_points: int | None = None
    no_hand_rejected: float = 0.2
    start_min_pixels: int = 150

    @classmethod
    def paper(cls):
        return cls(no_hand_rejected=0.0, start_min_pixels=0)

    def check(self):
        _need(self.start_min_pixels >= 0, "loss.start_min_pixels",
              f"must be ≥ 0 (0 = off), got {self.start_min_pixels!r}")
        _need(0.0 <= self.no_hand_rejected < 1.0, "loss.no_hand_rejected",
              f"must be a share in [0, 1) (0 = off), got {self.no_hand_rejected}")


@dataclass(frozen=True)
class StartSettings(SettingsGroup):
    """What a start (a frame fitted without one before it) uses besides the depth.

    wrist_cue : score the start searches also by the frame's wrist cue, and hold a start's last fits'
        wrist crease on the arm's line (:func:`tracker.wrist.wrist_cue`; True, the paper: False)
    rgb_seed : start the searches also from the hand fitted to the colour keypoints
        (:mod:`tracker.rgb`, extra ``[rgb]``; False)
    check_hand : on the first frame also fit the mirror-image hand (``hand_check_``; False)
    detector : a depth keypoint detector (a name or file under ``models/detectors/``,
        :func:`tracker.parts.depth_detector`) whose fitted hand the searches start from first
        ("hand-keypoints-cnn", the shipped keypoint CNN's newest version; "" = none, the paper's:
        every start the full search; docs/experiments/detector.md)
    detector_accept_mm : with a ``detector``, a start fits the synergy postures at the detected hand's
        global pose first (:func:`tracker.init.seeded_search`, ~15× cheaper than the full search); when
        that scores at most this (mm, :func:`tracker.init.score`) the full search does not run (1.5,
        chosen on rendered scenes of other motions and clutter than those it is measured on:
        docs/experiments/detector.md, "The detected hand first"; 0 = the full search always runs)
    search_budget_ms : a start search's budget (ms): once spent, its optional stages are skipped and
        its best start so far converged (:class:`tracker.init.SearchBudget`; 0 = none, the default:
        with a budget the result depends on the machine's speed)
    presence : a hand-presence network (a name or file under ``models/detectors/``,
        :mod:`tracker.hand_presence`) asked before a start searches whether its region is a hand at all
        ("hand-presence-cnn", the newest shipped; "" = none, the paper's: every region is searched, and
        the fit's rejections decide). A region it calls no hand is searched all the same when the
        ``detector``'s hand fits it within ``detector_accept_mm`` (:meth:`tracker.parts.StartSearch.detected_fits`:
        the network calls a fist seen from the back with no arm in view no hand; without a ``detector``
        nothing overrules it): docs/experiments/detector.md, "Is it a hand?"
    presence_below : … and the probability below which the region is "no hand" without a search (0.05:
        99 % of the held-out rendered hands above it; docs/experiments/detector.md, "Is it a hand?")
    detector_wrist_m : with a ``detector``, a frame's points farther than this (m) behind its detected wrist
        (along the detected wrist → middle finger base) are left out: an arm the segmentation did not cut (a
        fist seen from its side is as narrow as its forearm). While tracking, the detector is asked only
        where the points reach this far behind the last frame's wrist (0.03: 1.5 × the keypoint CNN's
        median wrist error on its held-out frames through the segmentation, 19 mm; 0 = none;
        docs/experiments/detector.md, "The detected wrist")
    """

    wrist_cue: bool = True
    rgb_seed: bool = False
    check_hand: bool = False
    detector: str = "hand-keypoints-cnn"
    detector_accept_mm: float = 1.5
    search_budget_ms: float = 0.0
    presence: str = "hand-presence-cnn"
    presence_below: float = 0.05
    detector_wrist_m: float = 0.03

    @classmethod
    def paper(cls):
        return cls(wrist_cue=False, detector="", presence="")

    def check(self):
        b = self.search_budget_ms
        _need(isinstance(b, (int, float)) and not isinstance(b, bool) and 0 <= b < math.inf,
              "start.search_budget_ms", f"must be a number of ms ≥ 0 (0 = no budget), got {b!r}")
        _need(isinstance(self.detector, str), "start.detector",
              f"must be a detector's name or file (\"\" = none), got {self.detector!r}")
        a = self.detector_accept_mm
        _need(isinstance(a, (int, float)) and not isinstance(a, bool) and 0 <= a < math.inf,
              "start.detector_accept_mm", f"must be a score in mm ≥ 0 (0 = the full search always runs), got {a!r}")
        _need(isinstance(self.presence, str), "start.presence",
              f"must be a hand-presence network's name or file (\"\" = none), got {self.presence!r}")
        q = self.presence_below
        _need(isinstance(q, (int, float)) and not isinstance(q, bool) and 0 <= q < 1,
              "start.presence_below", f"must be a probability in [0, 1), got {q!r}")
        w = self.detector_wrist_m
        _need(isinstance(w, (int, float)) and not isinstance(w, bool) and 0 <= w < math.inf,
              "start.detector_wrist_m", f"must be a distance in m ≥ 0 (0 = off), got {w!r}")


@dataclass(frozen=True)
class ScaleSettings(SettingsGroup):
    """The hand's size (:class:`tracker.sizing.SizeCalibration`).

    hand_scale : the user's hand size as a factor on the model, or "auto": calibrated on the first
        frames ("auto", the paper: 1.0)
    frames : frames whose estimates the automatic size is the median of (5)
    trust_mm : while the calibrated frames' fits score above this (mm), the next frame is calibrated
        again (6.0)
    refine : how the next frames estimate it, "search" (each calibrated alone), "local" (around
        the current size) or "checked" (around the current size, calibrated alone only where that
        disagrees) ("checked")
    budget : the size work (short probe fits, in ICP iterations on 1,500 points:
        :func:`tracker.scale.probe_cost`) a tracked frame spends at most: the refining estimates and
        the finger lengths are spread over the frames, a probe at a time (≥ 0; 0 = each done on its
        frame at once, as before; 40)
    finger_lengths : with "auto", each finger's length factor too (True, the paper: False)
    range : the sizes searched, (low, high) factors ((0.6, 2.0))
    """

    hand_scale: float | str = "auto"
    frames: int = 5
    trust_mm: float = 6.0
    refine: str = "checked"
    budget: int = 40
    finger_lengths: bool = True
    range: tuple = (0.6, 2.0)

    @classmethod
    def paper(cls):
        return cls(hand_scale=1.0, finger_lengths=False)

    def check(self):
        lo, hi = self.range
        _need(0 < lo < hi and self.frames >= 1, "scale.range", "must be 0 < low < high, and scale.frames ≥ 1")
        v = self.hand_scale
        ok = v == "auto" if isinstance(v, str) else math.isfinite(v) and lo <= v <= hi
        _need(ok, "scale.hand_scale", f"must be 'auto' or a factor in {lo:g}–{hi:g} (the hand model's size × it), "
                                      f"got {v!r}")
        _need(self.refine in ("search", "local", "checked"), "scale.refine",
              f"must be 'search', 'local' or 'checked', got {self.refine!r}")
        b = self.budget
        _need(isinstance(b, (int, float)) and not isinstance(b, bool) and b >= 0 and float(b).is_integer(), "scale.budget",
              f"must be a whole number of ICP iterations ≥ 0 (0 = no bound), got {self.budget!r}")


@dataclass(frozen=True)
class WristTestSettings(SettingsGroup):
    """The safety net's test of a hand pointing the wrong way for the scene (:class:`tracker.net.WristTest`).

    cost_mm : doubtful when the frame's wrist cue costs the hand more than this (mm; 0 = off; 20)
    arm_m : … and the surface beyond the cue goes on this far (m; an arm; 0.12)
    cue : the net's searches use the wrist cue on every doubtful frame, not only this test's (False)
    fit_mm : this test's replacement must also score within this of the tracked fit without the cue
        (mm, ≥ 0; 0)
    every : the test runs in full at least every this many frames (≥ 1; 6)
    moved : … and whenever the pose turned or moved more than these (degrees, mm; (15, 15))
    """

    cost_mm: float = 20.0
    arm_m: float = 0.12
    cue: bool = False
    fit_mm: float = 0.0
    every: int = 6
    moved: tuple = (15.0, 15.0)

    def check(self):
        _need(self.fit_mm >= 0, "net.wrist.fit_mm", f"must be ≥ 0, got {self.fit_mm!r}")
        _need(int(self.every) >= 1 and len(self.moved) == 2 and min(self.moved) >= 0, "net.wrist",
              f"every must be ≥ 1 and moved two limits ≥ 0 (degrees, mm), got {self.every!r} and {self.moved!r}")


@dataclass(frozen=True)
class SafetyNetSettings(SettingsGroup):
    """The per-frame test of a tracked fit and its cheap start search (:class:`tracker.net.SafetyNet`).

    enabled : test every tracked frame (reduced mode: the far-points test only; True, the paper: False)
    score_mm : doubtful above this start-search score (mm; 0.7) …
    score_ratio : … and above this × the scene's level (2.5)
    jump_deg, jump_mm : doubtful when the pose jumps more than this from the prediction (30°, 40 mm)
    anchored : search from the tracked global pose first (True)
    margin_mm : the search's estimate wins by this much score (mm; 0.2)
    far_share : doubtful when more than this share of the points lie farther than ``far_mm`` from
        the hand (0 = off; 0.1)
    far_mm : see ``far_share`` (mm; 15)
    level_replaced : a replacement's score counts towards the scene's level too (True, the paper: False)
    level_quantile : the scene's level is this quantile of those scores (0.25; the paper: 0.5, the median)
    wrist : the wrong-way test (:class:`WristTestSettings`)
    """

    enabled: bool = True
    score_mm: float = 0.7
    score_ratio: float = 2.5
    jump_deg: float = 30.0
    jump_mm: float = 40.0
    anchored: bool = True
    margin_mm: float = 0.2
    far_share: float = 0.1
    far_mm: float = 15.0
    level_replaced: bool = True
    level_quantile: float = 0.25
    wrist: WristTestSettings = field(default_factory=WristTestSettings)

    @classmethod
    def paper(cls):
        return cls(enabled=False, level_replaced=False, level_quantile=0.5)

    def check(self):
        _need(0.0 < self.level_quantile <= 0.5, "net.level_quantile",
              f"must be a quantile in (0, 0.5] (the scene's level is a low score), got {self.level_quantile!r}")
        self.wrist.check()


@dataclass(frozen=True)
class RefineSettings(SettingsGroup):
    """What refines a tracked fit (:class:`tracker.refine.UnseenPrior`, :class:`tracker.refine.FingerRestart`).

    unseen_prior : share of the way joints without data are pulled to their most likely values
        given the seen ones, per frame (0–1, 0 = off; 0.5, the paper: 0)
    unseen_points : a joint is unseen with fewer valid pairs than this on the parts it moves (3)
    finger_restart_deg : refit a finger whose last joint is this far off its coupling (degrees;
        0 = off; 50, the paper: 0)
    finger_bent_back_deg : in that refit, fingers hyperextended this much start bent the other way
        (degrees; 0 = off; :data:`tracker.coupling.BENT_BACK_DEG`)
    keypoints : the keypoint detector's keypoints in the tracked fit where the last fit left joints unseen
        (:class:`tracker.icp_settings.KeypointTermSettings`; off by default, ``--keypoint-term``)
    """

    unseen_prior: float = 0.5
    unseen_points: int = 3
    finger_restart_deg: float = 50.0
    finger_bent_back_deg: float = BENT_BACK_DEG
    keypoints: KeypointTermSettings = field(default_factory=KeypointTermSettings)

    @classmethod
    def paper(cls):
        return cls(unseen_prior=0.0, finger_restart_deg=0.0)

    def check(self):
        _need(0.0 <= self.unseen_prior <= 1.0, "refine.unseen_prior", f"must be within 0..1, got {self.unseen_prior}")
        self.keypoints.check()



@dataclass(frozen=True)
class TrackerSettings(SettingsGroup):
    """Every knob of the tracker (see the module's docstring).

    mode : "full" (all DoF), "reduced" (the synergy subspace) or "hierarchical" ("full")
    subspace, predict, loss, start, scale, net, refine : the tracker's own groups
    observe, correspond, icp, init : the stages' settings
    """

    mode: str = "full"
    subspace: SubspaceSettings = field(default_factory=SubspaceSettings)
    predict: PredictSettings = field(default_factory=PredictSettings)
    loss: LossSettings = field(default_factory=LossSettings)
    start: StartSettings = field(default_factory=StartSettings)
    scale: ScaleSettings = field(default_factory=ScaleSettings)
    net: SafetyNetSettings = field(default_factory=SafetyNetSettings)
    refine: RefineSettings = field(default_factory=RefineSettings)
    observe: ObserveSettings = field(default_factory=ObserveSettings)
    correspond: CorrespondSettings = field(default_factory=CorrespondSettings)
    icp: IcpSettings = field(default_factory=IcpSettings)
    init: InitSettings = field(default_factory=InitSettings)

    @classmethod
    def paper(cls, **changes) -> "TrackerSettings":
        """The paper's method: every group's ``paper()`` (fixed stride 3 without smoothing, plain least
        squares on data→model pairs rejected at 50 mm, 1 rigid + 4 non-rigid ICP iterations × 5
        Gauss-Newton steps, single-frame fits from the synergy mean, the model's own size, none of our
        additions); ``changes`` as in :meth:`replace`."""
        groups = {f: getattr(cls, "__dataclass_fields__")[f].default_factory.paper() for f in _GROUPS}
        return cls(**groups).replace(**changes)

    def check(self):
        _need(self.mode in MODES, "mode", f"must be {', '.join(MODES[:-1])} or {MODES[-1]}, got {self.mode!r}")
        for name in _GROUPS:
            getattr(self, name).check()


_GROUPS = ("subspace", "predict", "loss", "start", "scale", "net", "refine", "observe", "correspond", "icp", "init")
