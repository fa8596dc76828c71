"""The single-frame search (:func:`fit_single_frame`).

The search: candidate placements of the hand from the cloud's principal axes, each briefly fitted;
the best few that differ in orientation go on. From each, a coarse search over a grid of synergy
postures (and finger variants of the mean: one finger in another shape) on a thinned cloud; the best
starts are refined fully (hierarchically when synergies exist), the best-scoring fit wins, then
finger-wise restarts (one finger at a time set to a few shapes and refitted) keep any improvement.
"""
from __future__ import annotations

import time

import numpy as np

from ..coupling import recoupled, uncoupled
from .candidates import (
    diverse,
    finger_pair_variants,
    finger_variants,
    placements,
    posture_candidates,
    posture_grid,
    thin,
)
from .overlap import FINGER_OVERLAP_WEIGHT, finger_overlap_mm
from .scoring import FitContext, score
from .settings import InitSettings


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
# an accepted detected start (seeded_search) gets this many sweeps of finger-wise restarts: one sweep fixed
# the fits that hold a finger wrong (a curled thumb after blank frames, a closing fist's little finger);
# on the harder scenes' 48 accepted-or-not starts at 1.0/1.5× three sweeps cost 144 against 78 ms CPU per
# accepted start (34 without restarts) for the same error (docs/experiments/detector.md, "On by default")
ACCEPTED_FINGER_SWEEPS = 1


class SearchBudget:
    """A start search's time budget (``budget_ms``; 0 = none), from its construction.

    The halving search asks it before each optional stage (:meth:`spent`); once spent, that stage is
    skipped — the synergy grid's and finger variants' starts, the longer fits of the best few, the
    finger-wise restarts — and the best start so far is converged as usual. ``cut_`` names the stages
    skipped. With a budget the result depends on the machine's speed; without one it does not.

    >>> b = SearchBudget(0.0)
    >>> b.spent("grid"), b.cut_
    (False, [])
    >>> b = SearchBudget(1e-9); time.sleep(0.001)
    >>> b.spent("grid"), b.spent("fingers"), b.cut_
    (True, True, ['grid', 'fingers'])
    """

    def __init__(self, budget_ms: float = 0.0):
        self.budget_ms = float(budget_ms)
        self.t0 = time.perf_counter()
        self.cut_: list[str] = []

    @property
    def elapsed_ms(self) -> float:
        return (time.perf_counter() - self.t0) * 1e3

    def spent(self, stage: str) -> bool:
        """Whether the budget is spent (then ``stage`` is skipped and named in ``cut_``)."""
        if self.budget_ms > 0 and self.elapsed_ms > self.budget_ms:
            self.cut_.append(stage)
            return True
        return False


def fit_single_frame(ctx: FitContext, points, settings: InitSettings | None = None, *, theta0=None, mode=None,
                     silhouette=None, postures=None, normals=None, extra=(), search=True, wrist=None, budget=None):
    """Fit one frame without temporal prior; returns ``(θ, Correspondences)``.

    From ``theta0``'s global pose (or candidate placements from the cloud) and several synergy
    postures (or ``postures``), each refined by ICP (``mode``: hierarchical by default when synergies
    exist); ``extra`` θ (e.g. the last good estimate before a loss) are refined through themselves,
    as they are and re-placed on the cloud. ``search`` False skips the coarse and finger-wise searches.
    ``settings.strategy`` chooses successive halving over batched candidate fits (default) or the
    exhaustive search (see :class:`InitSettings`). ``wrist``: the frame's wrist cue, which the winner's
    last fits hold the hand's wrist crease to (the wrist-line pair, :class:`tracker.icp.IcpSettings`);
    the candidates' fits leave it out (it reordered close candidates). ``budget``: a
    :class:`SearchBudget` that cuts the halving search short once spent (the exhaustive search, the
    reference, runs whole).
    """
    st = settings or InitSettings()
    st.check()
    mode = mode or ("hierarchical" if ctx.synergies is not None else "full")
    if st.strategy != "halving":
        return _search_exhaustive(ctx, points, st, theta0=theta0, mode=mode, silhouette=silhouette,
                                  postures=postures, normals=normals, extra=extra, search=search, wrist=wrist)
    return _search_halving(ctx, points, st, theta0=theta0, mode=mode, silhouette=silhouette, postures=postures,
                           normals=normals, extra=extra, search=search, wrist=wrist, budget=budget)


def seeded_search(ctx: FitContext, points, settings: InitSettings | None, seed, *, accept_mm: float = 0.0,
                  silhouette=None, normals=None, extra=(), wrist=None, budget=None):
    """The single-frame search with a detected hand first (a keypoint detector's, as the hybrid trackers'
    re-initialisers: Sharp et al. 2015): the synergy postures fitted at ``seed``'s global pose, with
    ``seed`` itself and the ``extra`` θ (:func:`fit_single_frame` from ``theta0``, no synergy grid,
    no finger restarts: ~15× cheaper than the search; ``settings.seeded.first`` "fit": one fit from
    ``seed`` and from each ``extra`` θ first, :class:`tracker.init.SeededSettings`). When that fit scores at most
    ``accept_mm`` (:func:`score`) it is the answer, after one sweep of finger-wise restarts; otherwise
    the full search runs with it as one more start and the better of the two by score is kept
    (successive halving can drop a good start on its coarse cloud). Returns ``(θ, corr, searched)``."""
    st = settings or InitSettings()
    if st.seeded.first == "fit":
        theta, corr, first = _one_fit_each(ctx, points, st, (seed,) + tuple(extra), silhouette=silhouette,
                                           normals=normals, wrist=wrist)
        if first <= accept_mm:
            return (*_accepted(ctx, theta, corr, points, st, silhouette=silhouette, normals=normals, wrist=wrist),
                    False)
    detected = st if st.seeded.keep is None else st.replace(halving=dict(keep=tuple(st.seeded.keep)))
    theta, corr = fit_single_frame(ctx, points, detected, theta0=seed, silhouette=silhouette, normals=normals,
                                   extra=(np.asarray(seed, float),) + tuple(extra), search=False, wrist=wrist)
    first = score(ctx, theta, corr, silhouette)
    if first <= accept_mm:
        return (*_accepted(ctx, theta, corr, points, st, silhouette=silhouette, normals=normals, wrist=wrist),
                False)
    th2, c2 = fit_single_frame(ctx, points, st, silhouette=silhouette, normals=normals, extra=tuple(extra) + (theta,),
                               wrist=wrist, budget=budget)
    if first < score(ctx, th2, c2, silhouette):
        return theta, corr, True
    return th2, c2, True


def _one_fit_each(ctx: FitContext, points, st: InitSettings, starts, *, silhouette=None, normals=None, wrist=None):
    """The best by :func:`score` of one fit from each of ``starts`` (all DoF, one rigid step, then
    ``icp_iterations`` on the whole cloud: the hand-presence test's fit), as ``(θ, corr, score)``."""
    best = None
    for th0 in starts:
        theta, corr = ctx.fit(np.asarray(th0, float), points, "full", 1, st.icp_iterations, silhouette=silhouette,
                              normals=normals, wrist=wrist)
        s = score(ctx, theta, corr, silhouette)
        if best is None or s < best[2]:
            best = (theta, corr, s)
    return best


def _accepted(ctx: FitContext, theta, corr, points, st: InitSettings, *, silhouette=None, normals=None, wrist=None):
    """An accepted detected start ``(θ, corr)`` after its finger-wise restarts (``st.seeded``'s restart
    settings, ``ACCEPTED_FINGER_SWEEPS`` sweeps)."""
    # a fit that scores this well can still hold one finger in a wrong local minimum the tracking
    # never leaves (a curled thumb after blank frames: 3.2 against 0.4° on the frames after); the
    # detector's fingertips agree with that fit (it started there), so the finger-wise restarts decide
    if not st.finger_search:
        return theta, corr
    sd = st.seeded
    halving = dict(finger_sweeps=ACCEPTED_FINGER_SWEEPS)
    if sd.restart_icp is not None:
        halving["restart_icp"] = sd.restart_icp
    if sd.restart_margin_mm is not None:
        halving["restart_margin_mm"] = sd.restart_margin_mm
    if sd.restart_points is not None:
        halving["rank_points"] = sd.restart_points
    restarts = st.replace(halving=halving, finger_pairs=st.finger_pairs if sd.restart_pairs is None
                          else st.finger_pairs and sd.restart_pairs)
    return restart_fingers(ctx, theta, corr, points, restarts, silhouette=silhouette, normals=normals, wrist=wrist)


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
                    search, wrist=None, budget=None):
    """Successive halving: every start fitted briefly on a small thinned cloud (:meth:`FitContext.fit_many`
    per fit mode); the best few fitted longer on larger clouds; the finger-wise restarts
    (:func:`finger_search_batched`) from the best; the winner converged with all DoF. A spent
    ``budget`` (:class:`SearchBudget`) skips the stages after it but the convergence."""
    budget = budget or SearchBudget()
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
    if search and st.search and budget.spent("grid"):
        search = False  # the postures and extras only: no synergy grid, no finger variants, no restarts
    groups = _start_sets(ctx, poses, st, mode, points, theta0=theta0, postures=postures, extra=extra, search=search)
    T, S = [], []
    for m, starts in groups.items():
        t, s = ctx.fit_many(starts, pr, m, 1, st.rank_icp, normals=nr, gn=st.rank_gn, **kw)
        T.append(t)
        S.append(s)
    T, S = np.concatenate(T), np.concatenate(S)
    # the longer fits re-centre the subspaces on each start (the grid's postures lie off the mean)
    for k, (n_pts, n_icp) in zip(st.keep, ((st.coarse_points, 4), (st.refine_points, st.refine_icp))):
        if budget.spent(f"keep {k}"):
            break
        best = np.argsort(S, kind="stable")[:k]
        p_, n_ = cloud(n_pts)
        T, S = ctx.fit_many(T[best], p_, mode, 0, n_icp, normals=n_, through=True, **kw)
    i = int(np.argmin(S))
    return converge(ctx, T[i], points, st, silhouette=silhouette, normals=normals, wrist=wrist,
                    fingers=search and st.finger_search and not budget.spent("fingers"))


def converge(ctx: FitContext, theta, points, settings: InitSettings, *, silhouette=None, normals=None, wrist=None,
             fingers=True):
    """A search's end from its best start ``theta``: with ``fingers`` the finger-wise restarts
    (:func:`finger_search_batched`), then all DoF converged on ``refine_points`` of the cloud and polished
    on all of it (``wrist``: the frame's wrist line, :func:`tracker.icp.fit`). Returns ``(θ, corr)``."""
    st = settings
    if fingers:
        theta = finger_search_batched(ctx, theta, points, st, silhouette=silhouette, normals=normals)
    # all DoF at the end (the short hierarchical fits of a search spend most iterations in the subspaces):
    # converged on the refinement cloud, then a few iterations on the full cloud
    sub = thin(points, st.refine_points)
    theta, _ = ctx.fit(theta, points[sub], "full", 0, st.icp_iterations,
                       normals=None if normals is None else normals[sub], wrist=wrist, silhouette=silhouette)
    return ctx.fit(theta, points, "full", 0, st.polish_icp, normals=normals, wrist=wrist, silhouette=silhouette)


def restart_fingers(ctx: FitContext, theta, corr, points, settings: InitSettings, *, silhouette=None, normals=None,
                    wrist=None):
    """A converged fit ``(θ, corr)`` after the finger-wise restarts (:func:`finger_search_batched`):
    converged again (:func:`converge`) only when a restart replaced a finger, else returned as it is."""
    th = finger_search_batched(ctx, theta, points, settings, silhouette=silhouette, normals=normals)
    if th is theta:
        return theta, corr
    return converge(ctx, th, points, settings, silhouette=silhouette, normals=normals, wrist=wrist, fingers=False)


def finger_search_batched(ctx: FitContext, theta, points, settings: InitSettings, *, silhouette=None, normals=None):
    """The finger-wise restarts of :func:`finger_search` as successive halving: all fingers' shapes
    (from the current θ) fitted briefly in one batch on ``rank_points`` points (``restart_icp`` ICP
    iterations); the best shape of each finger that comes within ``restart_margin_mm`` of θ's own score
    there is fitted longer on ``refine_points`` beside θ
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
        T, S = ctx.fit_many(starts, pr, "full", 0, st.restart_icp, silhouette=silhouette, normals=nr, gn=st.rank_gn)
        S = S + overlap(T)
        if settings.finger_pairs and S[0] > PAIR_SCORE_MM:
            pairs = finger_pair_variants(ctx, theta)
            if pairs:
                Tp, Sp = ctx.fit_many([th for _, th in pairs], pr, "full", 0, st.restart_icp, silhouette=silhouette,
                                      normals=nr, gn=st.rank_gn)
                T, S = np.concatenate([T, Tp]), np.concatenate([S, Sp + overlap(Tp)])
                owner += [n + k for k, _ in pairs]
        # each finger whose last joint breaks its coupling with the one before it (the tracker's
        # restart_uncoupled: a straight fingertip on a curled finger, a DIP folded to its limit) also
        # starts from the coupled DIP, the rest of θ as found: its own group, not one of the shapes
        broken = uncoupled(ctx.hand, theta, COUPLED_RESTART_DEG)
        if broken.any():
            Tc, Sc = ctx.fit_many([recoupled(ctx.hand, theta, np.arange(5) == k, ctx.limits)
                                   for k in np.flatnonzero(broken)], pr, "full", 0, st.restart_icp,
                                  silhouette=silhouette, normals=nr, gn=st.rank_gn)
            T, S = np.concatenate([T, Tc]), np.concatenate([S, Sc + overlap(Tc)])
            owner += [2 * n + k for k in np.flatnonzero(broken)]
        owner = np.asarray(owner)
        finalists = [theta]
        for k in range(3 * n):
            idx = np.flatnonzero(owner == k)
            if idx.size:
                i = idx[np.argmin(S[idx])]
                if S[i] < S[0] + st.restart_margin_mm:
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
