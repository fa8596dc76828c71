"""Pipeline stage ``init``: fit one frame without temporal prior (the start of tracking, and its
re-initialisation after a loss).

The search: candidate placements of the hand from the cloud's principal axes, each briefly fitted;
the best few that differ in orientation go on. From each, a coarse search over a grid of synergy
postures (and finger variants of the mean: one finger in another shape) on a thinned cloud; the best
starts are refined fully (hierarchically when synergies exist), the best-scoring fit wins, then
finger-wise restarts (one finger at a time set to a few shapes and refitted) keep any improvement.

Everything here works on a :class:`FitContext`, the parts of one hand's fits that a tracker builds once.
"""
from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np
from numba import njit
from scipy.spatial.transform import Rotation

from handmodel.geometry import surface_samples
from handmodel.rigid import euler_to_matrix, matrix_to_euler

from .coupling import recoupled, uncoupled
from ._kernel_arrays import (
    CapsuleArrays,
    HandArrays,
    SampleArrays,
    ScoreTerms,
    SilhouetteArrays,
    WristCueArrays,
)
from ._search_kernels import data_cost_mean, search_score
from .correspond import (
    DATA_CAP_MM,
    M2D_CAP_MM,
    M2D_TOLERANCE_MM,
    M2D_TOLERANCE_PX,
    CapsuleModel,
    Matcher,
    ModelSamples,
    data_to_model_mm,
)
from .errors import TrackerError
from .settings_base import SettingsGroup
from .icp import IcpSettings, fit, model_to_data_mean, search_schedule
from .wrist import WRIST_REACH_MM, WRIST_TURN_MM, wrist_cost_mm


@dataclass(frozen=True)
class HalvingSettings(SettingsGroup):
    """The successive-halving schedule of the single-frame search (:class:`InitSettings` ``strategy``
    "halving"): every start fitted briefly on ``rank_points`` points (``rank_icp`` ICP iterations of
    ``rank_gn`` Gauss-Newton steps), the best ``keep[0]`` longer on the coarse cloud, the best
    ``keep[1]`` of those for ``refine_icp`` iterations on ``refine_points``; at most ``finger_sweeps``
    sweeps of finger-wise restarts; the winner polished with ``polish_icp`` on the full cloud.
    """

    rank_points: int = 300
    rank_icp: int = 2
    rank_gn: int = 2
    keep: tuple = (12, 3)
    refine_points: int = 1500
    refine_icp: int = 8
    polish_icp: int = 4
    finger_sweeps: int = 3

    def check(self):
        if min(self.keep, default=0) < 1 or len(self.keep) != 2:
            raise TrackerError("settings", f"init keep must be two counts ≥ 1, got {self.keep!r}")


@dataclass(frozen=True)
class InitSettings(SettingsGroup):
    """The single-frame search.

    ``icp_iterations``: ICP iterations refining each start on the full cloud; ``postures``: starts from
    the mean and ±σ along this many PCs; ``search``: the coarse synergy-grid search (our addition; off =
    the paper's fit from the mean); ``finger_search``: finger variants and finger-wise restarts (ours);
    ``finger_search_icp``: ICP iterations of a finger's best restart on the full cloud; ``placements``:
    how many orientation-diverse placements go on; ``coarse_points``: size of the thinned cloud that
    ranks candidates.

    ``threads``: how many fits of a batch (:meth:`FitContext.fit_many`) run at once, in threads (the
    compiled fit releases the GIL; each fit is independent, so the result is the same for any count);
    0 = the cores this process may use, at most 4 (:func:`search_threads`).

    ``strategy``: ``"halving"`` (default, successive halving: ``halving``, :class:`HalvingSettings`,
    whose fields read as this object's too, ``rank_points`` …) ranks every start briefly
    (:meth:`FitContext.fit_many`), the coarse stage on ``coarse_points``; the finger-wise restarts
    rank all fingers' shapes at once and refit only the promising ones; the winner is converged with
    all DoF (``icp_iterations`` on ``refine_points``, then ``polish_icp`` on the full cloud); ``finger_pairs``: the restarts also set two neighbouring
    fingers at once while the fit scores poorly (:func:`finger_pair_variants`, ``PAIR_SCORE_MM``;
    3× the restarts' starts). ``refit_pose``: a given ``theta0`` may be off (a previous frame's), so
    it is also fitted longer and both go on. ``"exhaustive"``: the earlier search, every
    start refined with ``icp_iterations`` on the full cloud (2–3× the CPU time with the compiled ICP
    loop, ~14× with the Python one; kept as the reference the benchmark compares with).
    """

    icp_iterations: int = 12
    postures: int = 2
    search: bool = True
    finger_search: bool = True
    finger_search_icp: int = 10
    placements: int = 3
    coarse_points: int = 800
    strategy: str = "halving"
    halving: HalvingSettings = field(default_factory=HalvingSettings)
    refit_pose: bool = False
    finger_pairs: bool = True
    threads: int = 0

    # the halving schedule's fields, read where the search reads them
    rank_points = property(lambda self: self.halving.rank_points)
    rank_icp = property(lambda self: self.halving.rank_icp)
    rank_gn = property(lambda self: self.halving.rank_gn)
    keep = property(lambda self: self.halving.keep)
    refine_points = property(lambda self: self.halving.refine_points)
    refine_icp = property(lambda self: self.halving.refine_icp)
    polish_icp = property(lambda self: self.halving.polish_icp)
    finger_sweeps = property(lambda self: self.halving.finger_sweeps)

    @classmethod
    def cheap(cls, **changes) -> InitSettings:
        """A search about 3× cheaper than the default, for a frame whose global pose is roughly known
        (e.g. from the last tracked frame: ``fit_single_frame(ctx, points, InitSettings.cheap(),
        theta0=last, extra=(last,))``): fewer starts go on after the ranking, shorter refinements on
        fewer points, one sweep of finger-wise restarts and no pair restarts (they would add half
        again to the safety net's searches while tracking, for the few frames whose fingers swapped)."""
        halving = HalvingSettings(rank_points=200, keep=(6, 2), refine_points=800, refine_icp=6, polish_icp=2,
                                  finger_sweeps=1)
        return cls(icp_iterations=10, halving=halving, finger_pairs=False).replace(**changes)

    @classmethod
    def paper(cls):
        """The paper's fit from the synergy mean: no coarse or finger-wise search."""
        return cls(search=False, finger_search=False)

    def check(self):
        if self.strategy not in STRATEGIES:
            raise TrackerError("settings", f"init strategy must be one of {', '.join(STRATEGIES)}, got {self.strategy!r}")
        self.halving.check()
        if int(self.threads) < 0:
            raise TrackerError("settings", f"init threads must be ≥ 0 (0 = the cores available), got {self.threads!r}")


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity; the machine's count where that is unknown)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def search_threads(threads: int = 0) -> int:
    """The threads a start search's batches of fits use: ``threads``, or for 0 the cores this process
    may run on (:func:`available_cores`), at most 4 (the batches hold 10–60 fits of ~1 ms; more threads
    gain little once the Python around each fit, which holds the GIL, is a third of the work). Never
    more than the cores: more threads would only take turns on them (``--threads 100`` on 2 cores
    started 100)."""
    n = available_cores()
    return max(1, min(int(threads), n)) if threads else min(n, 4)


_POOLS: dict = {}


def _pool(n):
    """One lasting thread pool per size and process (a search runs ~20 batches; a pool per batch costs
    more than it gains). A process forked after a search (a worker of ``-j``) gets its own: the
    parent's pool has no threads there and would never run a fit."""
    key = (n, os.getpid())
    if key not in _POOLS:
        _POOLS[key] = ThreadPoolExecutor(n, thread_name_prefix="fit")
    return _POOLS[key]


STRATEGIES = ("halving", "exhaustive")


@dataclass
class FitContext:
    """What every fit of one hand shares: the model, its joint limits, the correspondence
    ``matcher``, the model samples of the silhouette term, the ICP settings, the subspaces (all DoF,
    the synergy subspace, the hierarchical ladder) and the synergy model (or None)."""

    hand: object
    limits: np.ndarray
    matcher: Matcher
    icp: IcpSettings
    full: object
    reduced: object = None
    ladder: list = field(default_factory=list)
    synergies: object = None          # a fitted synergy.pca.SynergyModel
    samples: ModelSamples | None = None
    finger_shapes: list = field(default_factory=list)
    score_samples: ModelSamples | None = None   # the model→data part of :func:`score`
    threads: int = 1                  # fits of one batch run at once (:func:`search_threads`)
    # derived from ``hand`` (recomputed by dataclasses.replace, as a resized context needs)
    capsules: tuple = field(init=False, repr=False)

    def __post_init__(self):
        self.capsules = finger_capsules(self.hand)

    def fit(self, theta, points, mode, n_rigid, n_icp, *, silhouette=None, normals=None, through=False, wrist=None):
        """One ICP fit without temporal prior (see :func:`tracker.icp.search_schedule`; ``wrist``: the
        frame's wrist cue for the wrist-line pair, :class:`tracker.icp.IcpSettings`)."""
        stages = search_schedule(mode, n_icp, self.full, self.reduced, self.ladder, through=through)
        return fit(self.hand, points, theta, stages, self.matcher, self.icp, n_rigid=n_rigid, normals=normals,
                   samples=self.samples, silhouette=silhouette, wrist=wrist)

    def fit_many(self, thetas, points, mode, n_rigid, n_icp, *, silhouette=None, normals=None, through=False,
                 gn=None):
        """The fits of :meth:`fit` from every row of ``thetas`` and their :func:`score`, as
        ``(θs (C, n), scores (C,))``. ``gn``: Gauss-Newton steps per ICP iteration instead of the ICP
        settings' (a ranking fit needs fewer)."""
        thetas = np.atleast_2d(np.asarray(thetas, float))
        icp = self.icp if gn is None or gn == self.icp.gn_iterations else replace(self.icp, gn_iterations=int(gn))
        stages = search_schedule(mode, n_icp, self.full, self.reduced, self.ladder, through=through)
        out_t = np.empty_like(thetas)
        out_s = np.empty(len(thetas))

        def one(k):
            out_t[k], corr = fit(self.hand, points, thetas[k], stages, self.matcher, icp, n_rigid=n_rigid,
                                 normals=normals, samples=self.samples, silhouette=silhouette)
            out_s[k] = score(self, out_t[k], corr, silhouette)

        if len(thetas):
            # the first on this thread: a kernel compiled while another thread calls it gave wrong numbers
            # (uninitialised memory, NaN θ; measured with an empty numba cache) — the first fit compiles
            # every kernel the batch calls (tests/tracker/test_init_search.py, the slow cold-cache test)
            one(0)
        if self.threads > 1 and len(thetas) > 2:
            # list(): the first exception a fit raised is raised here
            list(_pool(self.threads).map(one, range(1, len(thetas))))
        else:
            for k in range(1, len(thetas)):
                one(k)
        return out_t, out_s


def score(ctx: FitContext, theta, corr, silhouette=None, *, data_mm=None) -> float:
    """Lower is better (mm): the mean data→model cost (:func:`data_cost_mm`: each data point's distance
    to the nearest model surface, capped), plus, with a silhouette, the mean model→data cost
    (:func:`tracker.correspond.model_to_data_mm`: model parts outside the silhouette or in front of
    the observed surface) × ``MODEL_TO_DATA_WEIGHT``. Both directions: an upside-down or mirrored
    hand can cover the data as well as the right one, but then puts fingers where the camera saw past
    them, or leaves a real finger uncovered (a hand turned over folds its thumb into the palm and
    leaves the real thumb's points up to the cap away). A silhouette that carries the frame's wrist
    cue (``silhouette.wrist``, :func:`tracker.wrist.wrist_cue`) adds :func:`tracker.wrist.wrist_cost_mm`:
    a hand whose fingers point up the arm loses even where both directions fit. (The finger-wise
    restarts add :func:`finger_overlap_mm`, see :func:`finger_search_batched`.) ``data_mm``: the
    points' :func:`tracker.correspond.data_to_model_mm` at ``theta`` when the caller has them already."""
    # the hand's frames once for the data term and the wrist cue (a search scores hundreds of fits)
    cue = getattr(silhouette, "wrist", None)
    samples = ctx.score_samples if ctx.score_samples is not None else ctx.samples
    m2d = silhouette is not None and samples is not None and not silhouette.empty
    surf = ctx.matcher.surface
    if (data_mm is None and corr.points is not None and isinstance(surf, CapsuleModel) and surf.hand is ctx.hand
            and (not m2d or samples.hand is ctx.hand)):
        # one compiled call (the same sums in the same order as the terms below)
        return _score_compiled(ctx, theta, corr, silhouette, samples if m2d else None, cue)
    G = ctx.hand.node_frames(theta) if cue is not None or (data_mm is None and corr.points is not None) else None
    s = data_cost_mm(ctx, theta, corr, data_mm=data_mm, frames=G)
    if m2d:
        s += MODEL_TO_DATA_WEIGHT * model_to_data_mean(samples, theta, silhouette)
    if cue is not None:
        s += wrist_cost_mm(cue, ctx.hand, theta, keypoints=G[:, :3, 3])
    return s


def _score_compiled(ctx, theta, corr, silhouette, samples, cue) -> float:
    """:func:`score` by :func:`tracker._search_kernels.search_score` (``samples`` None: no model→data
    term; ``cue`` None: no wrist cost)."""
    on = samples is not None
    terms = ScoreTerms(REJECTED_PAIR_MM, DATA_CAP_MM, on, MODEL_TO_DATA_WEIGHT, M2D_TOLERANCE_MM, M2D_TOLERANCE_PX,
                       M2D_CAP_MM)
    sil = (SilhouetteArrays.of(silhouette, depth=np.asarray(silhouette.depth, np.float64)) if on
           else _NO_SILHOUETTE)
    wrist = (WristCueArrays(True, np.asarray(cue.point, np.float64), np.asarray(cue.direction, np.float64),
                            WRIST_REACH_MM, WRIST_TURN_MM) if cue is not None
             else WristCueArrays(False, _ZERO3, _ZERO3, WRIST_REACH_MM, WRIST_TURN_MM))
    return float(search_score(np.array(ctx.hand.check_theta(theta), float), HandArrays.of(ctx.hand),
                              CapsuleArrays.of(ctx.matcher.surface.caps),
                              np.ascontiguousarray(corr.points, dtype=np.float64),
                              np.ascontiguousarray(corr.valid, dtype=np.bool_), terms,
                              SampleArrays.of(samples) if on else _NO_SAMPLES, sil, wrist))


# stand-ins of the model→data arrays' types when the term is off (one compiled version serves both)
_NO_SAMPLES = SampleArrays(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))
_NO_SILHOUETTE = SilhouetteArrays(1.0, 1.0, 0.0, 0.0, np.zeros((1, 1)), np.zeros((1, 1), np.int32),
                                  np.zeros((1, 1), np.int32), np.zeros((1, 1)), 0, 0)
_ZERO3 = np.zeros(3)


def data_cost_mm(ctx: FitContext, theta, corr, *, data_mm=None, frames=None) -> float:
    """The data→model half of :func:`score` (mm): the mean over the fit's data points
    (``corr.points``) of their distance to the nearest model surface on any side
    (:func:`tracker.correspond.data_to_model_mm`), plus ``REJECTED_PAIR_MM`` where ICP rejected the
    point's pair, capped at ``DATA_CAP_MM``. Correspondences without their points fall back to the
    pairs' own distances (front-facing model surface only). ``data_mm``: those distances of
    ``corr.points`` at ``theta`` when already measured (the safety net's far-points test needs them too);
    ``frames``: ``ctx.hand``'s node frames at ``theta`` when the caller has them."""
    if data_mm is None and corr.points is not None and isinstance(ctx.matcher.surface, CapsuleModel):
        # compiled (a search scores hundreds of fits; the numpy path below is its definition)
        surf = ctx.matcher.surface
        G = frames if frames is not None and surf.hand is ctx.hand else surf.hand.node_frames(theta)
        return float(data_cost_mean(np.ascontiguousarray(G, dtype=np.float64), CapsuleArrays.of(surf.caps),
                                    np.ascontiguousarray(corr.points, dtype=np.float64),
                                    np.ascontiguousarray(corr.valid, dtype=np.bool_), REJECTED_PAIR_MM, DATA_CAP_MM))
    if data_mm is not None:
        d = np.asarray(data_mm, float)
    elif corr.points is not None:
        same = frames is not None and getattr(ctx.matcher.surface, "hand", None) is ctx.hand
        d = data_to_model_mm(ctx.matcher, theta, corr.points, frames=frames if same else None)
    else:
        d = np.where(np.isfinite(corr.distance), corr.distance * 1000.0, DATA_CAP_MM)
    d = np.minimum(d + REJECTED_PAIR_MM * ~np.asarray(corr.valid, bool), DATA_CAP_MM)
    return float(np.mean(d)) if d.size else float(DATA_CAP_MM)


# the model→data cost is a mean over the whole surface, most of it hidden and costing nothing when
# the fit is right: this weight makes a finger's worth of wrong surface count like a few mm of data
# error (measured on the labelled SR305 frames: with 1 none of the five open-hand frames is fitted
# turned over, with 2 one is)
MODEL_TO_DATA_WEIGHT = 1.0
# what a point whose ICP pair was rejected (no front-facing model surface within the rejection
# distance, or normals disagreeing) pays on top of its distance: a little, so that on clean data a
# hand whose surface faces the wrong way still ranks below the right one (rendered frames from no
# pose: 21 of 24 within 2° with it, 20 without), but not the 100 mm of the earlier score, which on
# real sensors' noisy normals let a hand turned over win (labelled SR305 frames: tips within 15 px
# 85 of 95 with 5 mm, 77 with 10 mm, 64 with the earlier score)
REJECTED_PAIR_MM = 5.0
# what a mm of two fingers' overlap (:func:`finger_overlap_mm`) costs the finger-wise restarts'
# scores (with the pairs, :func:`finger_search_batched`), and the share of
# two phalanges' summed radii they may come closer than without cost (touching fingers flatten, a
# curled finger lies against its neighbour; the model's radii are a little generous). Measured on
# the labelled SR305 frames with the pair restarts (fixed sizes 1.336 / 1.399): tips within 15 px
# 81/95 without the term, 84/95 with 0.1 and 0.75 (80 with 0.1 and the full radii); 0.3 as 0.1
FINGER_OVERLAP_WEIGHT = 0.1
FINGER_OVERLAP_SHARE = 0.75


def finger_capsules(hand):
    """The capsules of the fingers' phalanges (index … pinky) as index arrays: ``(base node, end
    node, base radius, end radius, pairs a, pairs b)`` where the pairs are every two capsules of
    different fingers. Not the thumb's: a fist's thumb lies pressed over the curled index and middle
    fingers (the rendered open-close fist: 16 mm of overlap, all thumb against finger), while a
    finger on its neighbour's place is a finger against a finger."""
    parents = np.asarray(hand.parents)
    rows = []
    for seg in hand.segments:
        kids = np.flatnonzero(parents == seg.joint)
        finger = hand.node_names[seg.joint].rstrip("0123456789")
        if seg.shape == "capsule" and kids.size == 1 and finger != "thumb":
            rows.append((seg.joint, int(kids[0]), seg.radius[0], seg.radius[1], finger))
    a, b = np.triu_indices(len(rows), 1)
    other = np.array([rows[i][4] != rows[j][4] for i, j in zip(a, b)], bool)
    cols = list(zip(*rows)) if rows else [()] * 5
    return (np.array(cols[0], np.int64), np.array(cols[1], np.int64), np.array(cols[2], float),
            np.array(cols[3], float), a[other], b[other])


def finger_overlap_mm(hand, theta, capsules=None) -> float:
    """How far (mm, summed over every two phalanges of different fingers) the model's fingers pass
    into each other at ``theta``: closer than ``FINGER_OVERLAP_SHARE`` × their radii summed at the
    closest points of their axes. Zero for every synergy posture and the rendered motions' postures
    (≤ 2 mm on 2 % of the fingerfist postures); a finger laid over its neighbour (both on one real
    finger) or two fingers crossed costs 10–60 mm. ``capsules``: :func:`finger_capsules` of
    ``hand`` (computed when not given)."""
    j0, j1, r0, r1, a, b = finger_capsules(hand) if capsules is None else capsules
    if not a.size:
        return 0.0
    kp = np.ascontiguousarray(hand.keypoints(theta), dtype=np.float64)
    return 1000.0 * _overlap_kernel(kp, j0, j1, r0, r1, a, b, FINGER_OVERLAP_SHARE)


@njit(cache=True)
def _overlap_kernel(kp, j0, j1, r0, r1, a, b, share):
    # a loop over ~90 capsule pairs in scalars: in numpy the per-call overhead of ~20 small array
    # operations was a sixth of the start search's time (it scores every fit)
    total = 0.0
    for k in range(a.size):
        i, j = a[k], b[k]
        d, s, t = _segment_distance(kp[j0[i]], kp[j1[i]], kp[j0[j]], kp[j1[j]])
        reach = share * (r0[i] + s * (r1[i] - r0[i]) + r0[j] + t * (r1[j] - r0[j]))
        if reach > d:
            total += reach - d
    return total


@njit(cache=True)
def segment_distances(p0, p1, q0, q1):
    """Closest distances between the segments ``p0[k]→p1[k]`` and ``q0[k]→q1[k]`` (rows ``(n, 3)``)
    and the closest points' parameters ``s, t`` in [0, 1] along each, as three ``(n,)`` arrays."""
    n = p0.shape[0]
    d, s, t = np.empty(n), np.empty(n), np.empty(n)
    for k in range(n):
        d[k], s[k], t[k] = _segment_distance(p0[k], p1[k], q0[k], q1[k])
    return d, s, t


@njit(cache=True)
def _segment_distance(p0, p1, q0, q1):
    """Closest distance between segments ``p0→p1`` and ``q0→q1`` and the closest points' parameters
    ``s, t`` in [0, 1] along each (Ericson, Real-Time Collision Detection, 5.1.9)."""
    a = b = c = e = f = 0.0
    for m in range(3):
        d1, d2, r = p1[m] - p0[m], q1[m] - q0[m], p0[m] - q0[m]
        a += d1 * d1
        e += d2 * d2
        b += d1 * d2
        c += d1 * r
        f += d2 * r
    a, e = max(a, 1e-12), max(e, 1e-12)
    den = a * e - b * b
    # parallel axes (den 0): any s does, take the base
    s = min(max((b * f - c * e) / den, 0.0), 1.0) if den > 1e-12 else 0.0
    t = (b * s + f) / e
    # t outside the segment: clamp it and take the s closest to that end
    if t < 0.0:
        t, s = 0.0, min(max(-c / a, 0.0), 1.0)
    elif t > 1.0:
        t, s = 1.0, min(max((b - c) / a, 0.0), 1.0)
    g = 0.0
    for m in range(3):
        x = p0[m] + s * (p1[m] - p0[m]) - q0[m] - t * (q1[m] - q0[m])
        g += x * x
    return np.sqrt(g), s, t


def _palm_side(hand, posture):
    """θ at ``posture`` (pose zero), the model's surface samples and normals there, and the samples of
    its palm-side half (what a camera in front of the palm sees)."""
    base = np.zeros(hand.n_dofs)
    base[~hand.pose_mask] = posture
    S, _, N = surface_samples(hand, base, spacing=0.004)
    return base, S, N, S[N[:, 2] < 0]


def placements(hand, points, posture) -> list[np.ndarray]:
    """Candidate global poses from the cloud: the model's palm-side surface centroid on the data
    centroid, its principal axes on the data's (the four sign choices, each rolled about the main
    axis by 0, ±45 and ±90°: a curled hand's main axis need not be the fingers')."""
    base, S, N, ms = _palm_side(hand, posture)
    # the palm-side half gives the axes only: each placement is centred by the half that faces the
    # camera in it, the palm or the back
    mc = ms.mean(0)
    dc = points.mean(0)
    _, _, Vm = np.linalg.svd(ms - mc, full_matrices=False)
    _, _, Vd = np.linalg.svd(points - dc, full_matrices=False)
    A = np.stack([Vm[0], np.cross(Vm[2], Vm[0]), Vm[2]], 1)
    out = []
    for s1 in (1, -1):
        for s3 in (1, -1):
            d1, d3 = s1 * Vd[0], s3 * Vd[2]
            B = np.stack([d1, np.cross(d3, d1), d3], 1)
            for roll in (0.0, 45.0, -45.0, 90.0, -90.0):
                R = Rotation.from_rotvec(np.radians(roll) * d1).as_matrix() @ B @ A.T
                th = base.copy()
                th[3:6] = matrix_to_euler(R)
                RS = S @ R.T
                seen = RS[(N @ R.T)[:, 2] < 0]
                th[:3] = dc - (seen.mean(0) if len(seen) else R @ mc)
                out.append(th)
    return out


def posture_candidates(synergies, k, n_posture) -> list[np.ndarray]:
    """Start postures: the synergy mean and ±1.5σ along PC1, ±1.2σ along PC2 and PC3 (the first
    ``k`` PCs); zeros without synergies."""
    if synergies is None:
        return [np.zeros(n_posture)]
    out = [synergies.mean_.copy()]
    for pc, amp in ((0, 1.5), (1, 1.2), (2, 1.2))[:k]:
        for sgn in (1, -1):
            coef = np.zeros(pc + 1)
            coef[pc] = sgn * amp
            out.append(synergies.posture(coef))
    return out


def posture_grid(synergies) -> list[np.ndarray]:
    """The coarse search space: PC1 at −2…+2σ, PC2 and PC3 at −1, 0, +1σ, inside the PC limits."""
    return [synergies.posture(np.array([a1, a2, a3]), clip=True)
            for a1 in (-2.0, -1.0, 0.0, 1.0, 2.0) for a2 in (-1.0, 0.0, 1.0) for a3 in (-1.0, 0.0, 1.0)]


def diverse(scored, k, min_deg=60.0) -> list[np.ndarray]:
    """The best ``k`` of ``(score, θ)`` sorted by score whose global rotations differ pairwise by at
    least ``min_deg`` (a palm-facing and a back-facing placement both go on when the cloud alone cannot
    tell them apart), filled up with the next best if fewer are that different."""
    picked, Rs = [], []
    for _, th in scored:
        R = euler_to_matrix(th[3:6])
        if all(math.degrees(math.acos(float(np.clip((np.trace(R @ Q.T) - 1) / 2, -1, 1)))) >= min_deg for Q in Rs):
            picked.append(th)
            Rs.append(R)
            if len(picked) == k:
                return picked
    rest = [th for _, th in scored if not any(th is p for p in picked)]
    return picked + rest[: k - len(picked)]


# finger shapes for finger-wise restarts: flexion (°) of the first, second and third flexion joint
# (MCP, PIP, DIP; for the thumb CMC, MCP, IP): straight, evenly curled, PIP-led curl (a finger flexed
# alone, as in fingerfist), MCP-led bend, hook
FINGER_SHAPES_DEG = ((5.0, 5.0, 5.0), (-25.0, -25.0, -25.0), (-55.0, -55.0, -55.0), (-85.0, -85.0, -85.0),
                     (-45.0, -100.0, -10.0), (-80.0, -20.0, -10.0), (0.0, -90.0, -60.0))


# the shapes (rows of FINGER_SHAPES_DEG) the pair restarts combine: straight, evenly curled and
# fully curled, MCP-led bend and hook (25 combinations a pair instead of 49; half the pairs' cost)
PAIR_SHAPES = (0, 1, 3, 5, 6)
# the pair restarts run only while θ scores above this (mm, on the ranking cloud): a fit that
# explains its frame this well has no finger on its neighbour's place to undo (rendered frames score
# 0.1–0.8 — the pairs there cost 60 % of the search's time for nothing —, the SR305 frames 1.5–5)
PAIR_SCORE_MM = 1.5
# the finger-wise restarts also start a finger from its coupled last joint (tracker.coupling) when it is
# more than this far (°) off it. The tracker's own restart uses 50° (TrackerSettings.finger_restart_deg: the
# true fingerfist postures break 30° on 29 % of frames, 50° on 7 %, each a refit); here the restart is one more
# start among the search's, and 50° gave worse real frames (the SR305 stills' calibrated protocol: median tip
# 3.8 -> 4.2 px, worst 19 -> 44 px; the one-frame protocol 5.0 -> 5.3 px)
COUPLED_RESTART_DEG = 30.0


def finger_shapes(hand, limits) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per finger (thumb … pinky): the θ indices of its flexion joints and FINGER_SHAPES_DEG as values
    for them, inside ``limits`` — one row per shape."""
    names = list(hand.dof_names)
    lo, hi = limits[:, 0], limits[:, 1]
    out = []
    for f in ("thumb", "index", "middle", "ring", "pinky"):
        fi = np.array([i for i, n in enumerate(names) if n.startswith(f) and "flex" in n], np.int64)
        if fi.size:
            vals = np.radians([np.resize(shape, fi.size) for shape in FINGER_SHAPES_DEG])
            out.append((fi, np.clip(vals, lo[fi], hi[fi])))
    return out


def finger_variants(theta, shapes, finger=None) -> list[np.ndarray]:
    """Copies of ``theta`` with one finger's flexion joints set to each of its ``shapes``, every
    finger in turn (or only ``finger``, an index into ``shapes``), the rest unchanged."""
    out = []
    for k, (fi, vals) in enumerate(shapes):
        if finger is None or finger == k:
            for v in vals:
                th = np.array(theta, float)
                th[fi] = v
                out.append(th)
    return out


def finger_search(ctx: FitContext, best, points, settings: InitSettings, *, silhouette=None, normals=None,
                  sweeps=2):
    """Finger-wise restarts: synergies couple the fingers, so a finger flexed alone (a ring finger
    curled into the palm, a thumb tucked under) lies outside every start the synergy grid gives. Each
    finger in turn is set to a few shapes (the rest of the hand as found), refitted briefly with all
    DoF on a thinned cloud; the best is refitted on the full cloud and kept only when the whole-frame
    score improves. Repeated while a sweep improves something. ``best``: ``(score, θ, corr)``."""
    sub = thin(points, settings.coarse_points)
    nsub = None if normals is None else normals[sub]
    s_best, theta, corr = best
    for _ in range(sweeps):
        improved = False
        for k, (fi, _) in enumerate(ctx.finger_shapes):
            tried = []
            for th in finger_variants(theta, ctx.finger_shapes, k):
                if np.max(np.abs(th[fi] - theta[fi])) < np.radians(12.0):
                    continue  # the finger has that shape already
                th, c = ctx.fit(th, points[sub], "full", 0, 4, silhouette=silhouette, normals=nsub)
                tried.append((score(ctx, th, c, silhouette), th))
            if not tried:
                continue
            tried.sort(key=lambda x: x[0])
            th, c = ctx.fit(tried[0][1], points, "full", 0, settings.finger_search_icp, silhouette=silhouette,
                            normals=normals)
            s = score(ctx, th, c, silhouette)
            if s < s_best - 1e-3:
                s_best, theta, corr, improved = s, th, c, True
        if not improved:
            break
    return s_best, theta, corr


def thin(points, n):
    """Every k-th point, about ``n`` of them: the cloud that ranks candidates."""
    return slice(None, None, max(1, len(points) // n))


def fit_single_frame(ctx: FitContext, points, settings: InitSettings | None = None, *, theta0=None, mode=None,
                     silhouette=None, postures=None, normals=None, extra=(), search=True, wrist=None):
    """Fit one frame without temporal prior; returns ``(θ, Correspondences)``.

    From ``theta0``'s global pose (or candidate placements from the cloud) and several synergy
    postures (or ``postures``), each refined by ICP (``mode``: hierarchical by default when synergies
    exist); ``extra`` θ (e.g. the last good estimate before a loss) are refined through themselves,
    as they are and re-placed on the cloud. ``search`` False skips the coarse and finger-wise searches.
    ``settings.strategy`` chooses successive halving over batched candidate fits (default) or the
    exhaustive search (see :class:`InitSettings`). ``wrist``: the frame's wrist cue, which the winner's
    last fits hold the hand's wrist crease to (the wrist-line pair, :class:`tracker.icp.IcpSettings`);
    the candidates' fits leave it out (it reordered close candidates).
    """
    st = settings or InitSettings()
    st.check()
    mode = mode or ("hierarchical" if ctx.synergies is not None else "full")
    run = _search_halving if st.strategy == "halving" else _search_exhaustive
    return run(ctx, points, st, theta0=theta0, mode=mode, silhouette=silhouette, postures=postures, normals=normals,
               extra=extra, search=search, wrist=wrist)


def _start_sets(ctx: FitContext, poses, st: InitSettings, mode, points, *, theta0, postures, extra, search):
    """The starts of the search, grouped by the mode of their first fit: ``{mode: [θ, ...]}`` (the
    synergy postures of :func:`posture_candidates` on every pose, ``extra`` as they are and re-placed
    on the cloud, and with ``search`` the synergy grid and the finger variants of the mean)."""
    hand = ctx.hand
    post = ~hand.pose_mask
    n_post = int(post.sum())
    groups = {}
    posts = posture_candidates(ctx.synergies, st.postures, n_post) if postures is None else postures
    for pose in poses:
        for p in posts:
            th = pose.copy()
            if theta0 is None or len(posts) > 1:
                th[post] = p
            groups.setdefault(mode, []).append(th)
    for th in extra:
        groups.setdefault(mode, []).append(np.array(th, float))
        moved = np.array(th, float)
        moved[:3] += points.mean(0) - hand.keypoints(moved)[[0, 5, 9, 13, 17]].mean(0)
        groups[mode].append(moved)
    if search and st.search and ctx.synergies is not None and postures is None:
        grid = posture_grid(ctx.synergies)
        for pose in poses:
            for p in grid:
                th = pose.copy()
                th[post] = p
                groups.setdefault("reduced" if mode != "full" else "full", []).append(th)
            if st.finger_search:
                at_mean = pose.copy()
                at_mean[post] = ctx.synergies.mean_
                groups.setdefault("full", []).extend(finger_variants(at_mean, ctx.finger_shapes))
    return groups


def _search_halving(ctx: FitContext, points, st: InitSettings, *, theta0, mode, silhouette, postures, normals, extra,
                    search, wrist=None):
    """Successive halving: every start fitted briefly on a small thinned cloud (:meth:`FitContext.fit_many`
    per fit mode); the best few fitted longer on larger clouds; the finger-wise restarts
    (:func:`finger_search_batched`) from the best; the winner converged with all DoF."""
    hand = ctx.hand

    def cloud(n):
        sub = thin(points, n)
        return points[sub], None if normals is None else normals[sub]

    kw = {"silhouette": silhouette}
    pr, nr = cloud(st.rank_points)
    pc, nc = cloud(st.coarse_points)
    if theta0 is not None:
        poses = [np.array(theta0, float)]
        if st.refit_pose:
            # the given pose may be off (a previous frame's): the same start fitted longer goes on beside it
            poses += list(ctx.fit_many(poses, pc, mode, 1, 3 * st.refine_icp // 2, normals=nc, **kw)[0])
    else:
        # every placement × a few postures, briefly fitted; the best few that differ in orientation go on
        n_post = int((~hand.pose_mask).sum())
        mean = ctx.synergies.mean_ if ctx.synergies is not None else np.zeros(n_post)
        quick = []
        for pose in placements(hand, points, mean):
            for p in posture_candidates(ctx.synergies, 1, n_post):
                th = pose.copy()
                th[~hand.pose_mask] = p
                quick.append(th)
        T, S = ctx.fit_many(quick, pr, mode, 2, 3, normals=nr, gn=st.rank_gn, **kw)
        order = np.argsort(S, kind="stable")
        poses = diverse([(S[i], T[i]) for i in order], st.placements)
        # a placement is only roughly turned (the cloud's axes are not the hand's): the synergy grid
        # below is fitted briefly from each pose, so the poses are fitted longer first
        poses = list(ctx.fit_many(poses, pc, mode, 1, 3 * st.refine_icp // 2, normals=nc, **kw)[0])
    groups = _start_sets(ctx, poses, st, mode, points, theta0=theta0, postures=postures, extra=extra, search=search)
    T, S = [], []
    for m, starts in groups.items():
        t, s = ctx.fit_many(starts, pr, m, 1, st.rank_icp, normals=nr, gn=st.rank_gn, **kw)
        T.append(t)
        S.append(s)
    T, S = np.concatenate(T), np.concatenate(S)
    # the longer fits re-centre the subspaces on each start (the grid's postures lie off the mean)
    for k, (n_pts, n_icp) in zip(st.keep, ((st.coarse_points, 4), (st.refine_points, st.refine_icp))):
        best = np.argsort(S, kind="stable")[:k]
        p_, n_ = cloud(n_pts)
        T, S = ctx.fit_many(T[best], p_, mode, 0, n_icp, normals=n_, through=True, **kw)
    i = int(np.argmin(S))
    theta = T[i]
    if search and st.finger_search:
        theta = finger_search_batched(ctx, theta, points, st, silhouette=silhouette, normals=normals)
    # all DoF at the end (the short hierarchical fits above spend most iterations in the subspaces):
    # converged on the refinement cloud, then a few iterations on the full cloud
    p_, n_ = cloud(st.refine_points)
    theta, _ = ctx.fit(theta, p_, "full", 0, st.icp_iterations, normals=n_, wrist=wrist, **kw)
    theta, corr = ctx.fit(theta, points, "full", 0, st.polish_icp, normals=normals, wrist=wrist, **kw)
    return theta, corr


def finger_search_batched(ctx: FitContext, theta, points, settings: InitSettings, *, silhouette=None, normals=None):
    """The finger-wise restarts of :func:`finger_search` as successive halving: all fingers' shapes
    (from the current θ) fitted briefly in one batch on ``rank_points`` points; the best shape of each
    finger that comes within 2 mm of θ's own score there is fitted longer on ``refine_points`` beside θ
    with the same fit, and the best one replaces θ when it scores better. With
    ``settings.finger_pairs``, while θ scores above ``PAIR_SCORE_MM`` there, the pair restarts are
    ranked too (:func:`finger_pair_variants`; the best of each pair goes on like a finger's best).
    With the pairs, every restart's score there also pays ``FINGER_OVERLAP_WEIGHT`` ×
    :func:`finger_overlap_mm`: two model fingers in one place cover the data and stay inside the
    silhouette as well as two fingers side by side, but real fingers cannot pass through each other
    (a curled finger's blob taken by its neighbour, which then leaves its own finger's few points
    uncovered). Repeated while a sweep improves something, at most ``finger_sweeps`` times. Returns θ."""
    st = settings

    def cloud(n):
        sub = thin(points, n)
        return points[sub], None if normals is None else normals[sub]

    pr, nr = cloud(st.rank_points)
    pf, nf = cloud(st.refine_points)
    n = len(ctx.finger_shapes)

    def overlap(thetas):
        # with the pair restarts the fingers' places are compared, so two fingers in one place pay
        # (not in score itself: the safety net's searches compare orientations by it, and an
        # edge-on hand's fingers pass into each other in the tracked pose — 8° turns on test_safety_net)
        if not settings.finger_pairs:
            return np.zeros(len(thetas))
        return np.array([FINGER_OVERLAP_WEIGHT * finger_overlap_mm(ctx.hand, th, ctx.capsules) for th in thetas])
    for _ in range(st.finger_sweeps):
        starts, owner = [theta], [-1]
        for k, (fi, _) in enumerate(ctx.finger_shapes):
            for th in finger_variants(theta, ctx.finger_shapes, k):
                if np.max(np.abs(th[fi] - theta[fi])) >= np.radians(12.0):  # else the finger has that shape already
                    starts.append(th)
                    owner.append(k)
        if len(starts) == 1:
            break
        T, S = ctx.fit_many(starts, pr, "full", 0, st.rank_icp + 2, silhouette=silhouette, normals=nr, gn=st.rank_gn)
        S = S + overlap(T)
        if settings.finger_pairs and S[0] > PAIR_SCORE_MM:
            pairs = finger_pair_variants(ctx, theta)
            if pairs:
                Tp, Sp = ctx.fit_many([th for _, th in pairs], pr, "full", 0, st.rank_icp + 2, silhouette=silhouette,
                                      normals=nr, gn=st.rank_gn)
                T, S = np.concatenate([T, Tp]), np.concatenate([S, Sp + overlap(Tp)])
                owner += [n + k for k, _ in pairs]
        # each finger whose last joint breaks its coupling with the one before it (the tracker's
        # restart_uncoupled: a straight fingertip on a curled finger, a DIP folded to its limit) also
        # starts from the coupled DIP, the rest of θ as found: its own group, not one of the shapes
        broken = uncoupled(ctx.hand, theta, COUPLED_RESTART_DEG)
        if broken.any():
            Tc, Sc = ctx.fit_many([recoupled(ctx.hand, theta, np.arange(5) == k, ctx.limits)
                                   for k in np.flatnonzero(broken)], pr, "full", 0, st.rank_icp + 2,
                                  silhouette=silhouette, normals=nr, gn=st.rank_gn)
            T, S = np.concatenate([T, Tc]), np.concatenate([S, Sc + overlap(Tc)])
            owner += [2 * n + k for k in np.flatnonzero(broken)]
        owner = np.asarray(owner)
        finalists = [theta]
        for k in range(3 * n):
            idx = np.flatnonzero(owner == k)
            if idx.size:
                i = idx[np.argmin(S[idx])]
                if S[i] < S[0] + 2.0:
                    finalists.append(T[i])
        if len(finalists) == 1:
            break
        T, S = ctx.fit_many(finalists, pf, "full", 0, st.refine_icp, silhouette=silhouette, normals=nf)
        S = S + overlap(T)
        i = int(np.argmin(S))
        if i == 0 or not S[i] < S[0] - 1e-3:
            break
        theta = T[i]
    return theta


def finger_pair_variants(ctx: FitContext, theta) -> list[tuple[int, np.ndarray]]:
    """The pair restarts: for every two neighbouring fingers among index … pinky (``(k, k+1)`` in
    ``ctx.finger_shapes``), copies of ``theta`` with both fingers set to every combination of their
    ``PAIR_SHAPES`` and both abductions back to the synergy mean's (zero without synergies), as
    ``(k, θ)``.
    A curled finger whose blob its neighbour took (the pinky spread onto the curled ring finger's
    place, the ring curled into the palm) comes back only when both move at once: either alone
    leaves the two on one place."""
    names = list(ctx.hand.dof_names)
    post = np.flatnonzero(~ctx.hand.pose_mask)
    rest = np.zeros(ctx.hand.n_dofs)
    if ctx.synergies is not None:
        rest[post] = ctx.synergies.mean_
    fingers = [names[fi[0]].split("1_")[0].rstrip("0123456789") for fi, _ in ctx.finger_shapes]
    order = ("index", "middle", "ring", "pinky")
    out = []
    for k in range(len(fingers) - 1):
        f, g = fingers[k], fingers[k + 1]
        if f not in order or g not in order or order.index(g) != order.index(f) + 1:
            continue
        (fa, va), (fb, vb) = ctx.finger_shapes[k], ctx.finger_shapes[k + 1]
        abd = [names.index(x + "1_abd") for x in (f, g) if x + "1_abd" in names]
        for u in va[list(PAIR_SHAPES)]:
            for v in vb[list(PAIR_SHAPES)]:
                th = np.array(theta, float)
                th[fa], th[fb] = u, v
                th[abd] = rest[abd]
                out.append((k, th))
    return out


def _search_exhaustive(ctx: FitContext, points, st: InitSettings, *, theta0, mode, silhouette, postures, normals,
                       extra, search, wrist=None):
    """The exhaustive search: every start refined with ``icp_iterations`` on the full cloud (with a
    ``wrist`` cue the best is polished once more with the wrist-line pair: its last fits are the
    candidates' own)."""
    hand = ctx.hand
    sub = thin(points, st.coarse_points)
    nsub = None if normals is None else normals[sub]
    post = ~hand.pose_mask
    n_post = int(post.sum())
    if theta0 is not None:
        poses = [np.array(theta0, float)]
    else:
        # many candidate placements, each briefly fitted; the best few that differ in orientation go on
        quick = []
        mean = ctx.synergies.mean_ if ctx.synergies is not None else np.zeros(n_post)
        for pose in placements(hand, points, mean):
            for p in posture_candidates(ctx.synergies, 1, n_post):
                th = pose.copy()
                th[post] = p
                th, corr = ctx.fit(th, points[sub], mode, 2, 4, silhouette=silhouette, normals=nsub)
                quick.append((score(ctx, th, corr, silhouette), th))
        quick.sort(key=lambda x: x[0])
        poses = diverse(quick, st.placements)
    posts = posture_candidates(ctx.synergies, st.postures, n_post) if postures is None else postures
    starts = []
    for pose in poses:
        for p in posts:
            th = pose.copy()
            if theta0 is None or len(posts) > 1:
                th[post] = p
            starts.append((th, False))
    for th in extra:
        starts.append((np.array(th, float), True))
        moved = np.array(th, float)
        centre = hand.keypoints(moved)[[0, 5, 9, 13, 17]].mean(0)
        moved[:3] += points.mean(0) - centre
        starts.append((moved, True))
    if search and st.search and ctx.synergies is not None and postures is None:
        # coarse search: short fits from a synergy grid on a thinned cloud, the best few refined fully
        coarse = []
        grid = posture_grid(ctx.synergies)
        for pose in poses:
            for p in grid:
                th = pose.copy()
                th[post] = p
                th, corr = ctx.fit(th, points[sub], "reduced" if mode != "full" else "full", 1, 4,
                                   silhouette=silhouette, normals=nsub)
                coarse.append((score(ctx, th, corr, silhouette), th))
            if st.finger_search:
                # and the synergy mean with one finger in another shape (what no synergy posture holds)
                at_mean = pose.copy()
                at_mean[post] = ctx.synergies.mean_
                for th in finger_variants(at_mean, ctx.finger_shapes):
                    th, corr = ctx.fit(th, points[sub], "full", 1, 4, silhouette=silhouette, normals=nsub)
                    coarse.append((score(ctx, th, corr, silhouette), th))
        coarse.sort(key=lambda x: x[0])
        starts = [(th, True) for _, th in coarse[:3]] + starts
    best = None
    for th, refine in starts:
        th, corr = ctx.fit(th, points, mode, 2, st.icp_iterations, silhouette=silhouette, normals=normals,
                           through=refine)
        s = score(ctx, th, corr, silhouette)
        if best is None or s < best[0]:
            best = (s, th, corr)
    if search and st.finger_search:
        best = finger_search(ctx, best, points, st, silhouette=silhouette, normals=normals)
    if wrist is not None:
        return ctx.fit(best[1], points, "full", 0, st.polish_icp, silhouette=silhouette, normals=normals, wrist=wrist)
    return best[1], best[2]

