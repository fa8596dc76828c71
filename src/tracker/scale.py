"""The user's hand size: the global scale of the hand model estimated from depth.

The size is found by fitting: a hand of the wrong size either leaves data uncovered or puts model
surface outside the silhouette, so short all-DoF fits at probed sizes (:func:`scale_score`) are
compared by :func:`tracker.init.score`, and a golden-section search (:func:`fit_scale`) finds the best.
:func:`calibrate_scale` does it on one frame without a prior; :class:`tracker.track.FrameTracker`
refines it over the next frames; :func:`finger_scales` then finds each finger's length. A probe's
:class:`tracker.init.FitContext` is derived from the model-sized one (:mod:`tracker.resize`).
"""
from __future__ import annotations

import copy
import datetime
import math
from dataclasses import replace
from pathlib import Path

import numpy as np

from synergy.bundle import GENERATOR, generator_version

from .coupling import recoupled, uncoupled
from .errors import TrackerError
from .icp import model_to_data_mean
from .init import (
    COUPLED_RESTART_DEG,
    FINGER_OVERLAP_WEIGHT,
    MODEL_TO_DATA_WEIGHT,
    InitSettings,
    _palm_side,
    data_cost_mm,
    finger_overlap_mm,
    fit_single_frame,
    score,
    seeded_search,
    thin,
)
from .resize import FINGERS, shaped_context, shaped_hand
from .wrist import ahead_of_wrist

# (hand sha256, handedness, posture) → the palm-side surface's variances along its principal axes. The
# handedness is in the key because a mirrored hand keeps its file's sha256 but not its palm-side samples:
# keyed by the hash alone, a left hand calibrated earlier in the process gave the right hand its
# spread, and the SR305 frames' sizes and fits then depended on what had run before
_MODEL_SPREAD = {}


def extent_scale(hand, points, posture, *, keep=True, view="palm") -> float:
    """A first guess of the hand's global scale: the spread of the cloud over that of the model's
    surface as a camera sees it (at ``posture``) in their two main directions. Posture changes the
    spread, so this only brackets the scale; :func:`fit_scale` finds it. ``view``: ``"palm"`` (the
    palm-side surface, seen along the palm's normal) or ``"side"`` (seen along the knuckles' line, the
    thumb's and the little finger's side alike: a fist seen from its side is ~25 % narrower than from
    its palm). ``keep``: the model's spread at this posture is kept for the next call (the fixed
    postures; not a fitted one, met once)."""
    key = (hand.sha256, hand.handedness, np.asarray(posture, float).tobytes(), view)
    ev_m = _MODEL_SPREAD.get(key)
    if ev_m is None:
        # sampling the model's surface costs ~0.05-0.1 s, a tenth of the calibration's budget: once per hand
        ev_m = _seen_spread(hand, posture, view)
        if keep:
            _MODEL_SPREAD[key] = ev_m
    ev_d = np.linalg.svd(points - points.mean(0), compute_uv=False) ** 2 / len(points)
    return float(np.sqrt((ev_d[0] + ev_d[1]) / (ev_m[0] + ev_m[1])))


def _seen_spread(hand, posture, view) -> np.ndarray:
    """The variances along their principal axes of the model's surface samples (at ``posture``) a camera
    sees from ``view`` (:func:`extent_scale`). ``"side"``: the samples facing each side of the hand (its
    frame has the knuckles' line along x) projected on that camera's image plane, the two sides' means
    (the thumb's side spreads ~5 % more). Projected, because the samples facing a side include the fist's
    top and bottom, which reach far in depth where a depth image sees a narrow band: unprojected, a
    closed hand seen from its side at 1.5× gave 1.28-1.37× (rendered Kinect v1), projected 1.62-1.71×,
    both × the calibration's 1.1."""
    base, S, N, palm = _palm_side(hand, posture)
    if view == "palm":
        return np.linalg.svd(palm - palm.mean(0), compute_uv=False) ** 2 / len(palm)
    out = np.zeros(3)
    for sign in (1.0, -1.0):
        seen = S[sign * N[:, 0] < 0]
        flat = (seen - seen.mean(0))[:, 1:]  # the image plane of a camera looking along x
        out[:2] += np.linalg.svd(flat, compute_uv=False) ** 2 / len(seen) / 2.0
    return out


def rescaled(hand_from, hand_to, theta) -> np.ndarray:
    """θ for ``hand_to`` with the same posture and rotation and the same keypoint centroid as
    ``theta`` on ``hand_from`` (a hand resized about its wrist would slide off the data)."""
    th = np.array(theta, float)
    th[:3] += hand_from.keypoints(theta).mean(0) - hand_to.keypoints(theta).mean(0)
    return th


def scale_score(context_for, s, theta_from, hand_from, points, *, silhouette=None, normals=None, n_icp=6):
    """``(score, θ, corr)`` of a short all-DoF fit of the hand scaled by ``s`` from ``theta_from``
    (found on ``hand_from``); ``context_for(s)`` gives that hand's :class:`tracker.init.FitContext`."""
    ctx = context_for(s)
    th = rescaled(hand_from, ctx.hand, theta_from)
    th, corr = ctx.fit(th, points, "full", 2, n_icp, silhouette=silhouette, normals=normals)
    return size_score(ctx, th, corr, silhouette), th, corr


#: pixels of silhouette edge a model sample may overshoot for free when sizes are compared (:func:`size_score`;
#: 1 = as :func:`tracker.init.score`). Realistic scenes, the 30 runs' sizes found / true: 1 px 0.966–1.007,
#: 2 px 0.976–1.012 (the sensors lose the outline by a pixel or two beyond the mask's dropout band)
EDGE_PX = 2.0


def size_score(ctx, theta, corr, silhouette=None, *, edge_px=None):
    """:func:`tracker.init.score` as sizes are compared: without the wrist cue (:func:`without_wrist`),
    with ``edge_px`` (default :data:`EDGE_PX`) pixels of the silhouette's edge free, plus the fingers'
    overlap (:func:`tracker.init.finger_overlap_mm`, which the start search's ranking also adds).

    The start search's score measures both directions alike on either side of the right size: a
    hand too small leaves data points up to the cap away, one too large puts surface outside the
    silhouette (which includes the sensor's dropout band, :func:`tracker.observe.dropout_band`, so
    most of the hand's lost outline costs nothing; ``edge_px`` frees the rest). An earlier size score — the fit's error plus 100 mm × the
    share of rejected pairs, with 3 px of the silhouette's edge free — rose steeply below the right
    size and barely above it: parabolas through its probes leaned large, and on the realistic scenes
    (0.8–1.5× hands, clutter, Kinect v1 and SR305 noise, same tree) 9 of 30 runs came out more than
    3 % off (0.8× hands with their forearm 3–9 % large); with this score none (0.976–1.012), and the
    mean keypoint error fell from 4.0 to 3.1 mm."""
    edge_px = EDGE_PX if edge_px is None else float(edge_px)
    sil = without_wrist(silhouette)
    # fingers passing into each other let a too large hand fold into a small one's silhouette
    overlap = FINGER_OVERLAP_WEIGHT * finger_overlap_mm(ctx.hand, theta, ctx.capsules)
    if sil is None or sil.empty or edge_px == 1.0:
        return score(ctx, theta, corr, sil) + overlap
    samples = ctx.score_samples if ctx.score_samples is not None else ctx.samples
    return (data_cost_mm(ctx, theta, corr)
            + MODEL_TO_DATA_WEIGHT * model_to_data_mean(samples, theta, sil, tolerance_px=edge_px) + overlap)


#: how far behind the fitted wrist points still count for the size (:func:`hand_side`)
WRIST_MARGIN_M = 0.0


def hand_side(points, hand, theta, margin_m=None) -> np.ndarray:
    """Which ``points`` lie on the fingers' side of the wrist of ``hand`` at ``theta`` (or at most
    ``margin_m``, default :data:`WRIST_MARGIN_M`, behind it, along the wrist → middle-finger-base axis;
    a 1 cm margin left 0.8× hands 5–15 % large in rendered forearm scenes, none 0–6 %). A mask keeps up to ~15 % of
    forearm past the wrist; a larger hand covers those points and scores better for it (+9–16 % on
    rendered Kinect forearm scenes), so the size is searched without them. The cut is made once, from
    one fit: cut at each probed size's own wrist, a smaller hand drops more of the palm's base and
    scores better for that instead (−4 to −6 %)."""
    margin_m = WRIST_MARGIN_M if margin_m is None else margin_m
    kp = hand.keypoints(np.asarray(theta, float))
    ahead = ahead_of_wrist(points, kp[0], kp[9], margin_m)
    return ahead if ahead.sum() >= 30 else np.ones(len(ahead), bool)


def without_wrist(silhouette):
    """``silhouette`` without its wrist cue, for comparing sizes: the cue's cost grows with the hand's
    size wherever the cue is not at the wrist joint (the mask's end lies 1–5 cm up the arm, or on a
    finger when no arm is seen), measured 4 → 19 mm from 0.85× to 1.1× a 0.8× rendered hand, far more
    than the data terms change; it pulled estimates 5–12 % small. The cue judges orientation only."""
    if getattr(silhouette, "wrist", None) is None:
        return silhouette
    out = copy.copy(silhouette)
    out.wrist = None
    return out


def fit_scale(context_for, theta, hand_from, points, lo, hi, *, silhouette=None, normals=None, tol=0.005,
              n_icp=6):
    """The global scale in ``[lo, hi]`` whose short fit from ``theta`` scores best (golden-section
    search on log scale, each probe an all-DoF fit: a wrong size leaves either data uncovered or model
    outside the silhouette). Returns ``(scale, θ, corr, score)``."""
    g = (np.sqrt(5.0) - 1.0) / 2.0
    # scalars by the C library (math): numpy's exp and log differ in the last bits by processor
    a, b = math.log(lo), math.log(hi)
    seen = {}

    def f(x):
        if x not in seen:
            seen[x] = scale_score(context_for, math.exp(x), theta, hand_from, points, silhouette=silhouette,
                                  normals=normals, n_icp=n_icp)
        return seen[x][0]

    c, d = b - g * (b - a), a + g * (b - a)
    while b - a > tol:
        if f(c) < f(d):
            b, d = d, c
            c = b - g * (b - a)
        else:
            a, c = c, d
            d = a + g * (b - a)
    x = min(seen, key=lambda k: seen[k][0])
    s_best, th, corr = seen[x]
    return math.exp(x), th, corr, s_best


def parabola_scale(context_for, theta, hand_from, points, centre, *, half_width=0.06, probes=7, silhouette=None,
                   normals=None, n_icp=10):
    """The global scale near ``centre``: ``probes`` sizes evenly spread on log scale within
    ``half_width`` (log) either way, each scored by a fit from ``theta`` (:func:`scale_score`), and a
    parabola through the scores; its vertex (kept within the probed sizes) is the size, the probe
    nearest it gives θ. Probe scores are noisy at the percent level (each short fit ends a little
    differently), so a golden-section search, which trusts every comparison, wanders by a few percent
    on a flat score; a parabola averages the noise over every probe. Returns ``(scale, θ, corr, score)``;
    :func:`parabola_scale_steps` is the same a probe at a time."""
    return run_steps(parabola_scale_steps(context_for, theta, hand_from, points, centre, half_width=half_width,
                                          probes=probes, silhouette=silhouette, normals=normals, n_icp=n_icp))


def parabola_scale_steps(context_for, theta, hand_from, points, centre, *, half_width=0.06, probes=7,
                         silhouette=None, normals=None, n_icp=10):
    """:func:`parabola_scale` as probes (see :func:`run_steps`): before each probe's fit it yields that
    fit's cost (:func:`probe_cost`); its return value is :func:`parabola_scale`'s."""
    x = math.log(centre) + np.linspace(-half_width, half_width, probes)
    found = []
    for v in x:
        yield probe_cost(n_icp, len(points))
        found.append(scale_score(context_for, math.exp(v), theta, hand_from, points, silhouette=silhouette,
                                 normals=normals, n_icp=n_icp))
    y = np.array([f[0] for f in found])
    a, b, _ = np.polyfit(x - x.mean(), y, 2)
    best = int(np.argmin(y))
    v = x[best] if a <= 0 else float(np.clip(x.mean() - b / (2 * a), x[0], x[-1]))
    near = int(np.argmin(np.abs(x - v)))
    return math.exp(v), found[near][1], found[near][2], float(y[near])


#: a short fit's cost as the size's work counts it (:func:`probe_cost`): ICP iterations on this many points
COST_POINTS = 1500


def probe_cost(n_icp, n_points) -> float:
    """A short fit's cost in ICP iterations on :data:`COST_POINTS` points: an iteration's time has a
    part that does not grow with the points (the model's samples, the solve), measured 0.17 ms + 0.27 ms
    per 1000 points on one core (an open hand, 376–1126 points, 4 and 10 iterations)."""
    per = lambda n: 0.17 + 0.27 * n / 1000.0  # noqa: E731
    return n_icp * per(n_points) / per(COST_POINTS)


def run_steps(steps):
    """Run the work ``steps`` (a generator that yields a cost before each probe and returns its
    result) to its end; returns that result."""
    try:
        while True:
            next(steps)
    except StopIteration as done:
        return done.value


def calibrate_scale_searched(context_for, points, settings: InitSettings | None = None, *, silhouette=None,
                             normals=None, scale_range=(0.6, 2.0), guesses=(1.0, 1.25, 1.5), good_score=2.0):
    """The earlier calibration (kept as the benchmark's peer). The cloud's extent against the open
    model's gives a first guess ``g`` (right for an open hand, too small for a curled one, which the
    cloud cannot tell apart). From each of ``guesses`` × ``g`` in turn, the single-frame search runs
    at that size and :func:`fit_scale` refines the size around it; when the size moved far, the search
    runs again at the new size (a much wrong size favours a wrong posture or orientation) and the size
    is refined once more. The guesses stop at the first fit scoring below ``good_score`` (mm,
    :func:`tracker.init.score`), else the best-scoring one wins; a last narrow search settles the
    size. ``context_for(s)``: the :class:`tracker.init.FitContext` of the hand scaled by ``s``.
    Returns ``(scale, θ, corr)``."""
    st = settings or InitSettings()
    base = context_for(1.0)
    lo, hi = scale_range
    g = extent_scale(base.hand, points, np.zeros(int((~base.hand.pose_mask).sum())))
    sub = thin(points, st.coarse_points)
    nsub = None if normals is None else normals[sub]

    def search(s0, width):
        th, _ = fit_single_frame(context_for(s0), points, st, silhouette=silhouette, normals=normals)
        s1, th1, _, sc = fit_scale(context_for, th, context_for(s0).hand, points[sub], max(lo, s0 / width),
                                   min(hi, s0 * width), silhouette=silhouette, normals=nsub)
        return sc, s0, s1, th1

    best = None
    for s0 in dict.fromkeys(float(np.clip(g * k, lo, hi)) for k in guesses):
        found = search(s0, 1.2)
        if abs(math.log(found[2] / s0)) > 0.08:
            found = min(found, search(found[2], 1.1), key=lambda f: f[0])
        if best is None or found[0] < best[0]:
            best = found
        if best[0] < good_score:
            break
    _, _, s1, th1 = best
    # a last narrow search from a fit at (nearly) the final size: the probes of a wide one start from
    # a pose fitted at another size, and their short fits lean towards it
    s1, th1, _, _ = fit_scale(context_for, th1, context_for(s1).hand, points[sub], max(lo, s1 / 1.06),
                              min(hi, s1 * 1.06), silhouette=silhouette, normals=nsub, n_icp=10)
    ctx = context_for(s1)
    th, corr = ctx.fit(th1, points, "full", 1, st.icp_iterations, silhouette=silhouette, normals=normals)
    return s1, th, corr


def first_sizes(base, points, size_guess=None, scale_range=(0.6, 2.0), guess=1.1) -> tuple:
    """The sizes :func:`calibrate_scale` searches first, ``(open, closed, closed from the side)``: ``guess`` ×
    the open hand's extent (:func:`extent_scale`), or ``size_guess`` where that is larger, and ``guess`` × a
    closed hand's extent (a fist's size: :func:`closed_posture`) seen from its palm and from its side, each
    within ``scale_range``. ``base``: the :class:`tracker.init.FitContext` at size 1."""
    lo, hi = scale_range
    g = extent_scale(base.hand, points, np.zeros(int((~base.hand.pose_mask).sum())))
    # both guesses err low (the extent on a curled hand; the shipped CNN's keypoints 0.8-0.95x on the real
    # SR305 stills): the larger is the nearer
    s0 = float(np.clip(g * guess if size_guess is None else max(g * guess, size_guess), lo, hi))
    closed = closed_posture(base)
    return (s0, *(float(np.clip(extent_scale(base.hand, points, closed, view=v) * guess, lo, hi))
                  for v in ("palm", "side")))


def calibrate_scale(context_for, points, settings: InitSettings | None = None, *, silhouette=None, normals=None,
                    scale_range=(0.6, 2.0), guess=1.1, width=1.35, research=0.06, cut=True, seeds=None, size_guess=None,
                    accept_mm=0.0):
    """The user's hand size from one frame, with one single-frame search. The cloud's extent against
    the open model's gives a first guess ``g`` (right for an open hand, too small for a curled one,
    which the cloud cannot tell apart); the search runs at ``guess`` × ``g`` and :func:`fit_scale`
    finds the size within ``width`` × either way from its fit. When the size moved by more than
    ``research`` (log), the cheap search (:meth:`tracker.init.InitSettings.cheap`) runs again at the
    new size from that fit (a much wrong size favours a wrong posture) and the size is searched again
    within 10 %; a last :func:`parabola_scale` (±6 %, longer fits on ``refine_points`` of the cloud)
    from a fit at (nearly) the final size settles it (the probes of a wide search start from a pose
    fitted at another size and lean towards it). When the first fit is curled (:data:`CURLED_EXTENT`) or
    poor (:data:`POOR_SIZE_SCORE_MM`), the search also runs at the size a closed hand of the cloud's extent
    would have (:func:`closed_posture`) and that size is kept when it scores better and at most
    :data:`CLOSED_GOOD_MM` (a fist is as wide as a smaller hand half curled). Sizes are compared by :func:`size_score` on the
    points on the fingers' side of the first fit's wrist (:func:`hand_side`; ``cut=False``: all).
    ``context_for(s)``: the
    :class:`tracker.init.FitContext` of the hand scaled by ``s`` (cheap with :func:`tracker.resize.resized_context`).
    ``seeds(hand)``: a detected hand on that hand model, the first search's start
    (:func:`tracker.init.seeded_search` with ``accept_mm``), and ``size_guess`` another guess of
    the size, taken where it is larger than the extent's (a keypoint detector's:
    :func:`tracker.keypoint_fit.keypoint_scale`).
    Returns ``(scale, θ, corr)``; :func:`calibrate_scale_searched` is the earlier, ~10× slower
    calibration (several full searches)."""
    st = settings or InitSettings()
    lo, hi = scale_range
    base = context_for(1.0)
    g = extent_scale(base.hand, points, np.zeros(int((~base.hand.pose_mask).sum())))
    s0, *closed_sizes = first_sizes(base, points, size_guess, scale_range, guess)
    found = () if seeds is None else tuple(seeds(context_for(s0).hand))
    if found:
        th0, _, _ = seeded_search(context_for(s0), points, st, found[0], accept_mm=accept_mm, silhouette=silhouette,
                                  normals=normals)
    else:
        th0, _ = fit_single_frame(context_for(s0), points, st, silhouette=silhouette, normals=normals)
    all_points, all_normals = points, normals
    if cut:
        # the size is searched on the points on the fingers' side of this fit's wrist (hand_side)
        keep = hand_side(points, context_for(s0).hand, th0)
        points, normals = points[keep], None if normals is None else normals[keep]
    sub = thin(points, st.coarse_points)
    nsub = None if normals is None else normals[sub]
    kw = {"silhouette": silhouette, "normals": nsub}

    def sized(s0, th0):
        """The size within ``width`` of ``s0`` from the fit ``th0`` there: ``(score, size, θ)``."""
        s1, th1, _, q = fit_scale(context_for, th0, context_for(s0).hand, points[sub], max(lo, s0 / width),
                                  min(hi, s0 * width), **kw)
        if abs(math.log(s1 / s0)) > research:
            ctx = context_for(s1)
            th2, _ = fit_single_frame(ctx, points, InitSettings.cheap(), silhouette=silhouette, normals=normals,
                                      theta0=th1, extra=(th1,))
            s1, th1, _, q = fit_scale(context_for, th2, ctx.hand, points[sub], max(lo, s1 / 1.1), min(hi, s1 * 1.1),
                                      **kw)
        return q, s1, th1

    best = sized(s0, th0)
    # a fit curled at a size from the open hand's extent is the fist's ambiguity: a smaller hand half
    # curled covers a fist too, and the probes of fit_scale, each a short fit from that posture, cannot
    # curl it enough at the right size (a 1.5x fist seen from the palm: 0.84x); a first fit that explains
    # its cloud poorly may be that too (the same fist on SR305: 20 mm, 0.67x, then called "no hand"). The
    # search runs again at the size a closed hand of this extent would have; that size wins when it scores
    # better and well (a large closed hand covers any compact blob a little)
    if (best[0] > POOR_SIZE_SCORE_MM
            or extent_scale(base.hand, all_points, th0[~base.hand.pose_mask], keep=False) / g > CURLED_EXTENT):
        tried = []
        for s_c in closed_sizes:
            # only a larger hand (the fist's ambiguity), and not one a closed search already settled near
            if math.log(s_c / best[1]) <= research or any(abs(math.log(s_c / s)) <= research for s in tried):
                continue
            th_c, _ = fit_single_frame(context_for(s_c), points, st, silhouette=silhouette, normals=normals)
            closed = sized(s_c, th_c)
            tried.append(closed[1])
            if closed[0] <= min(best[0], CLOSED_GOOD_MM):
                best = closed
    _, s1, th1 = best
    fine = thin(points, st.refine_points)
    s1, th1, _, _ = parabola_scale(context_for, th1, context_for(s1).hand, points[fine], s1, silhouette=silhouette,
                                   normals=None if normals is None else normals[fine])
    s1 = float(np.clip(s1, lo, hi))
    ctx = context_for(s1)
    th, corr = ctx.fit(th1, all_points, "full", 1, st.icp_iterations, silhouette=silhouette, normals=all_normals)
    return s1, th, corr


#: :func:`calibrate_scale` searches again at a closed hand's size when the first fit's posture makes the
#: cloud's extent guess this much larger than the open hand's (an open hand's fit: about 1.0)
CURLED_EXTENT = 1.08
#: … or when its size score (:func:`size_score`, mm) is above this (a good fit scores 1-4 mm; as
#: :class:`tracker.settings.ScaleSettings`'s default ``trust_mm``)
POOR_SIZE_SCORE_MM = 6.0
#: … and the closed hand's size is taken only where its size score is at most this (mm): the realistic
#: fist-palm scenes' first frames scored 1.4-2.6 mm closed (3.6-20 mm at the open hand's size); a strip of
#: wall edge in a hand-less recording (librealsense's sample bag) 7.0-7.8 mm as a 1.9x fist
CLOSED_GOOD_MM = 4.0


def closed_posture(ctx) -> np.ndarray:
    """The posture angles of a closed hand in ``ctx``'s limits: every finger but the thumb at the fully
    curled row of :data:`tracker.init.candidates.FINGER_SHAPES_DEG` (only its extent is used)."""
    theta = np.zeros(ctx.hand.n_dofs)
    for fi, vals in ctx.finger_shapes[1:]:
        theta[fi] = vals[3]
    return theta[~ctx.hand.pose_mask]


# ------------------------------------------------------------------------------ per-finger lengths
#: Prior spread (sd of the log factor) of a finger's length about the model's proportions: adult fingers
#: differ from the model's by some ±10 % (the realistic scenes draw them uniform within ±10 %: sd 0.058).
FINGER_PRIOR_SD = 0.06


def finger_scales(ctx, base, scale, frames, *, fingers=FINGERS, half_width=0.15, probes=5, n_icp=4,
                  limits=(0.8, 1.25), prior_sd=FINGER_PRIOR_SD, spread=None):
    """Each finger's length factor (:func:`finger_scales_steps`, run at once)."""
    return run_steps(finger_scales_steps(ctx, base, scale, frames, fingers=fingers, half_width=half_width,
                                         probes=probes, n_icp=n_icp, limits=limits, prior_sd=prior_sd, spread=spread))


def finger_scales_steps(ctx, base, scale, frames, *, fingers=FINGERS, half_width=0.15, probes=5, n_icp=4,
                        limits=(0.8, 1.25), prior_sd=FINGER_PRIOR_SD, spread=None):
    """Each finger's length factor on the hand ``base`` × ``scale`` (whose context is ``ctx``), from
    tracked ``frames``: ``(points, normals, silhouette, θ)`` with θ fitted on that hand. Finger by
    finger (the others at their factors found so far), ``probes`` factors evenly spread on log scale
    within ``half_width`` either way are each scored by short all-DoF fits from every frame's θ
    (:func:`size_score`), and a parabola through the scores summed over the frames gives the
    estimate (kept within the probes). A finger's length trades against its flexion in one view (a
    longer finger bent more covers the same pixels), so frames of several postures tell lengths
    apart better than many of one — and one frame's fit can prefer a wrong length by 10 %. A frame
    whose finger breaks the coupling of its last two joints (:mod:`tracker.coupling`; a too long model
    finger folded at its last joint to hide the excess) is fitted at every probe from its θ and from
    the coupled joint, the better fit scoring.

    The estimate is trusted by how well the frames agree: each frame's own parabola gives a vertex,
    their standard error ``se`` (spread / √frames) is the estimate's uncertainty, and the log factor is
    shrunk towards 1 by ``prior_sd² / (prior_sd² + se²)`` (a normal prior of ``prior_sd`` on the
    log factor; ``prior_sd=None``: no shrinking); a summed parabola that opens downwards says nothing
    and leaves the finger at 1. The factor is then kept within ``limits``. ``spread``: a dict that
    receives finger name → ``(raw factor, se)``. Returns finger name → factor. As probes (see
    :func:`run_steps`): before each short fit it yields that fit's cost (:func:`probe_cost`)."""
    found = dict.fromkeys(FINGERS, 1.0)
    x = np.linspace(-half_width, half_width, probes)
    for f in fingers:
        y = np.zeros((len(frames), probes))
        which = np.asarray(FINGERS) == f
        # a frame whose finger folds its last joint off the coupling (a too long model finger hides its
        # excess so) is also fitted from the coupled joint at every probe, the better fit scoring:
        # from the folded start alone a shorter finger cannot unfold in a short fit, and the frame
        # votes for the length it was fitted at
        starts = [[theta] + ([recoupled(ctx.hand, theta, which, ctx.limits)]
                             if uncoupled(ctx.hand, theta, COUPLED_RESTART_DEG)[which].any() else [])
                  for _, _, _, theta in frames]
        for k, v in enumerate(x):
            c = shaped_context(ctx, base, scale, {**found, f: math.exp(v)})
            for i, (points, normals, sil, _) in enumerate(frames):
                lowest = np.inf
                for theta in starts[i]:
                    yield probe_cost(n_icp, len(points))
                    th, corr = c.fit(theta, points, "full", 0, n_icp, silhouette=sil, normals=normals)
                    lowest = min(lowest, size_score(c, th, corr, sil))
                y[i, k] = lowest
        best = _vertex(x, y.sum(0), none_if_flat=True)
        per = [_vertex(x, row) for row in y]
        shrunk, se = trusted_log_factor(best, per, prior_sd)
        if spread is not None:
            spread[f] = (math.exp(best) if best is not None else float("nan"), se)
        found[f] = float(np.clip(math.exp(shrunk), *limits))
    return found


def trusted_log_factor(best, per_frame, prior_sd=FINGER_PRIOR_SD):
    """``(log factor, se)``: the log length factor ``best`` (None: no estimate) shrunk towards 0 by
    its standard error ``se`` over the frames' own estimates ``per_frame`` — the posterior mean under
    a normal prior of ``prior_sd`` (None: not shrunk). One frame has no spread to judge it by: its
    factor stays at 1.

    >>> [round(v, 6) for v in trusted_log_factor(0.1, [0.1, 0.1, 0.1])]
    [0.1, 0.0]
    >>> round(trusted_log_factor(0.1, [-0.1, 0.3, 0.1, 0.0, 0.2])[0], 3)  # frames 0.16 apart: se 0.07
    0.042
    >>> trusted_log_factor(None, [0.1, 0.1]), trusted_log_factor(0.1, [0.1])
    ((0.0, 0.0), (0.0, inf))
    """
    per = np.asarray(per_frame, float)
    se = float(np.std(per, ddof=1) / np.sqrt(len(per))) if len(per) > 1 else float("inf")
    if best is None:
        return 0.0, se
    if prior_sd is None:
        return float(best), se
    return float(best * prior_sd**2 / (prior_sd**2 + se**2)), se


def _vertex(x, y, *, none_if_flat=False):
    """The vertex of the parabola through ``(x, y)``, kept within ``x``'s range; for a parabola that
    opens downwards, the best probe (or None with ``none_if_flat``)."""
    a, b, _ = np.polyfit(x, y, 2)
    if a <= 0:
        return None if none_if_flat else float(x[int(np.argmin(y))])
    return float(np.clip(-b / (2 * a), x[0], x[-1]))


# ------------------------------------------------------------------------------ the calibrated hand as a file
def calibration_record(tracker, *, recording=None, frames=None) -> dict:
    """What a calibrated hand file's provenance says about its calibration (plain values, see
    :func:`calibrated_hand`): the size and its per-frame estimates with their spread (half the range
    over the median), the finger length factors (None: the base model's proportions) with each one's
    estimate before shrinking and its standard error (log) over the frames, the recording
    and the ``frames`` (indices) tracked until the size was settled, the settings that shaped the
    estimate, the tool and its version, and the time (UTC)."""
    est = [float(e) for e in tracker.scale_estimates_]
    med = float(np.median(est)) if est else float(tracker.scale_)
    st = tracker.settings
    fingers = getattr(tracker, "finger_scales_", None)
    spread = getattr(tracker, "finger_spread_", None) if fingers else None
    return {
        "hand_scale": round(float(tracker.scale_), 6),
        "scale_estimates": [round(e, 6) for e in est],
        "scale_spread": round((max(est) - min(est)) / (2.0 * med), 6) if len(est) > 1 else None,
        "finger_lengths": None if not fingers else {k: round(float(v), 6) for k, v in fingers.items()},
        # each finger's estimate before it was shrunk by its standard error over the frames (finger_scales)
        "finger_estimates": None if not spread else {
            k: {"unshrunk": _finite_or_none(a, 6), "se_log": _finite_or_none(se, 6)} for k, (a, se) in spread.items()},
        "recording": None if recording is None else _where(recording),
        "frames": None if frames is None else [int(f) for f in frames],
        # each frame fitted from its own start (FrameTracker.calibrate_each), or tracked frame to frame
        "each_frame": bool(getattr(tracker, "calibrated_each_", False)),
        "settings": {"scale_frames": int(st.scale.frames), "scale_refine": st.scale.refine,
                     "scale_budget": int(st.scale.budget),
                     "finger_lengths": bool(st.scale.finger_lengths), "scale_range": [float(v) for v in st.scale.range]},
        "tool": f"{GENERATOR} {generator_version()} (tracker.scale.calibrated_hand)",
        "written_utc": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
    }


def _where(recording) -> str:
    """A recording's absolute path when it is one on disk (a hand file outlives the working folder),
    else its name as given (a live camera)."""
    p = Path(str(recording))
    return str(p.resolve()) if p.exists() else str(recording)


def _finite_or_none(v, digits):
    """``v`` rounded, or None where it is NaN or infinite (YAML's ``.nan`` reads back unequal to itself)."""
    return round(float(v), digits) if np.isfinite(v) else None


def calibrated_hand(tracker, *, recording=None, frames=None):
    """The hand a :class:`tracker.track.FrameTracker` calibrated (``base_hand`` × ``scale_`` with
    ``finger_scales_``), with its record in ``provenance`` (:func:`calibration_record`, and the base
    model's name, SHA-256, handedness and own provenance), ready for :meth:`handmodel.HandModel.save`.
    Tracking with the saved file at ``hand_scale=1`` is tracking on this hand; the handedness is the
    tracked hand's, and loading it for the other hand mirrors it as the shipped model is mirrored
    (a person's two hands taken as mirror images)."""
    if tracker.scale_ is None:
        raise TrackerError("calibration", "no hand size yet: no frame has been calibrated")
    base = tracker.base_hand
    hand = shaped_hand(base, tracker.scale_, getattr(tracker, "finger_scales_", None) or {})
    provenance = {"calibration": calibration_record(tracker, recording=recording, frames=frames),
                  "base_model": {"name": base.name, "sha256": base.sha256, "path": str(base.path),
                                 "handedness": base.handedness, "provenance": base.provenance}}
    return replace(hand, name=f"{base.name}-calibrated", provenance=provenance,
                   description=f"{base.name} calibrated from depth: size {tracker.scale_:.4f}"
                               + ("" if recording is None else f", recording {recording}"))
