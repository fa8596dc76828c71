"""What every fit of one hand shares and how a fit is ranked.

Everything in :mod:`tracker.init` works on a :class:`FitContext`, the parts of one hand's fits that a
tracker builds once; :func:`score` ranks the fits (lower is better, both directions: data→model and
model→data).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .._kernel_arrays import (
    NO_SAMPLES,
    NO_SILHOUETTE,
    CapsuleArrays,
    HandArrays,
    SampleArrays,
    ScoreTerms,
    SilhouetteArrays,
    WristCueArrays,
    plain,
)
from .._fit_kernels import fit_score_many_entry
from .._search_kernels import data_cost_mean_entry, search_score_entry
from ..correspond import (
    DATA_CAP_MM,
    M2D_CAP_MM,
    M2D_TOLERANCE_MM,
    M2D_TOLERANCE_PX,
    CapsuleModel,
    Matcher,
    ModelSamples,
    data_to_model_mm,
)
from ..icp import IcpSettings, fit, fit_arguments, model_to_data_mean, search_schedule
from ..wrist import WRIST_REACH_MM, WRIST_TURN_MM, wrist_cost_mm
from .overlap import finger_capsules
from .settings import _pool


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
        first, which = distinct_rows(thetas)
        if len(first) < len(thetas):
            # a fit is a function of its start (each starts from fresh pairs), so a start given twice is
            # fitted once and its θ and score copied: the synergy grid's postures clipped to the PCs'
            # limits repeat 9 of its 45 (a fifth of a search's grid fits)
            T, S = self.fit_many(thetas[first], points, mode, n_rigid, n_icp, silhouette=silhouette,
                                 normals=normals, through=through, gn=gn)
            return T[which], S[which]
        icp = self.icp if gn is None or gn == self.icp.gn_iterations else replace(self.icp, gn_iterations=int(gn))
        stages = search_schedule(mode, n_icp, self.full, self.reduced, self.ladder, through=through)
        out_t = np.empty_like(thetas)
        out_s = np.empty(len(thetas))
        scored = _score_arguments(self, silhouette)
        if scored is not None and isinstance(self.matcher, Matcher):
            # the whole batch in compiled calls (fit_score_many_entry: each fit and score as one by one)
            args = fit_arguments(self.hand, points, stages, self.matcher, icp, n_rigid=n_rigid, normals=normals,
                                 samples=self.samples, silhouette=silhouette)
            starts = np.ascontiguousarray(self.hand.check_theta(thetas))

            def one(k):
                k = slice(k, k + 1) if isinstance(k, int) else k
                fit_score_many_entry(starts[k], *args, *scored, out_t[k], out_s[k], np.zeros(5, np.int64))
        else:
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
        elif scored is not None and isinstance(self.matcher, Matcher):
            one(slice(1, len(thetas)))
        else:
            for k in range(1, len(thetas)):
                one(k)
        # a fit gone to NaN raises as score's check of it does one by one
        self.hand.check_theta(out_t)
        return out_t, out_s


def distinct_rows(a) -> tuple:
    """``(first, which)``: the indices of the rows of ``a`` (2-D) that differ from every row before them,
    in order, and for every row the position in ``first`` of the row equal to it. Rows are equal when
    their bytes are (so 0.0 and -0.0 differ, and a NaN row equals its copy): ``a[first][which]`` is ``a``
    to the bit.

    >>> distinct_rows(np.array([[1.0, 2.0], [3.0, 4.0], [1.0, 2.0]]))
    (array([0, 1]), array([0, 1, 0]))
    """
    seen: dict = {}
    which = np.empty(len(a), np.int64)
    first = []
    for k, row in enumerate(np.ascontiguousarray(a)):
        key = row.tobytes()
        i = seen.get(key)
        if i is None:
            i = seen[key] = len(first)
            first.append(k)
        which[k] = i
    return np.array(first, np.int64), which


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
    samples, m2d, cue, compiled = _score_parts(ctx, silhouette)
    if data_mm is None and corr.points is not None and compiled:
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
    return float(search_score_entry(np.array(ctx.hand.check_theta(theta), float), *plain(HandArrays.of(ctx.hand),
                                    CapsuleArrays.of(ctx.matcher.surface.caps)),
                                    np.ascontiguousarray(corr.points, dtype=np.float64),
                                    np.ascontiguousarray(corr.valid, dtype=np.bool_),
                                    *_score_terms(samples, silhouette, cue)))


def _score_terms(samples, silhouette, cue) -> tuple:
    """The last four arguments of :func:`tracker._search_kernels.search_score_entry` (terms, samples,
    silhouette, wrist cue) as plain tuples (``samples`` None: no model→data term; ``cue`` None: no wrist
    cost)."""
    on = samples is not None
    terms = ScoreTerms(REJECTED_PAIR_MM, DATA_CAP_MM, on, MODEL_TO_DATA_WEIGHT, M2D_TOLERANCE_MM, M2D_TOLERANCE_PX,
                       M2D_CAP_MM)
    sil = (SilhouetteArrays.of(silhouette, depth=np.asarray(silhouette.depth, np.float64)) if on
           else NO_SILHOUETTE)
    wrist = (WristCueArrays(True, np.asarray(cue.point, np.float64), np.asarray(cue.direction, np.float64),
                            WRIST_REACH_MM, WRIST_TURN_MM) if cue is not None
             else WristCueArrays(False, _ZERO3, _ZERO3, WRIST_REACH_MM, WRIST_TURN_MM))
    return plain(terms, SampleArrays.of(samples) if on else NO_SAMPLES, sil, wrist)


def _score_parts(ctx, silhouette) -> tuple:
    """What :func:`score` scores with on ``silhouette``: ``(samples, m2d, cue, compiled)``: the model→data
    samples, whether that term is on, the frame's wrist cue (or None) and whether the compiled score
    applies (a capsule matcher posing ``ctx.hand``, the score samples too, for fits with their points)."""
    cue = getattr(silhouette, "wrist", None)
    samples = ctx.score_samples if ctx.score_samples is not None else ctx.samples
    m2d = silhouette is not None and samples is not None and not silhouette.empty
    surf = ctx.matcher.surface
    compiled = isinstance(surf, CapsuleModel) and surf.hand is ctx.hand and (not m2d or samples.hand is ctx.hand)
    return samples, m2d, cue, compiled


def _score_arguments(ctx, silhouette):
    """:func:`_score_terms` for the fits of :meth:`FitContext.fit_many` when :func:`score` of them takes
    its compiled path (:func:`_score_parts`), else None."""
    samples, m2d, cue, compiled = _score_parts(ctx, silhouette)
    return _score_terms(samples if m2d else None, silhouette, cue) if compiled else None


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
        return float(data_cost_mean_entry(*plain(np.ascontiguousarray(G, dtype=np.float64), CapsuleArrays.of(surf.caps),
                                                 np.ascontiguousarray(corr.points, dtype=np.float64),
                                                 np.ascontiguousarray(corr.valid, dtype=np.bool_), REJECTED_PAIR_MM,
                                                 DATA_CAP_MM)))
    if data_mm is not None:
        d = np.asarray(data_mm, float)
    elif corr.points is not None:
        same = frames is not None and getattr(ctx.matcher.surface, "hand", None) is ctx.hand
        d = data_to_model_mm(ctx.matcher, theta, corr.points, frames=frames if same else None)
    else:
        d = np.where(np.isfinite(corr.distance), corr.distance * 1000.0, DATA_CAP_MM)
    d = np.minimum(d + REJECTED_PAIR_MM * ~np.asarray(corr.valid, bool), DATA_CAP_MM)
    return float(np.mean(d)) if d.size else float(DATA_CAP_MM)
