"""Numba kernels of the start search's score (:func:`tracker.init.score`): the data term on the
capsule model, numpy's pairwise sum (the same bits as numpy's mean, so ranks do not change) and the
whole score in one call."""
from __future__ import annotations

import numpy as np
from numba import njit

from handmodel._geometry_kernels import closest_points_facing

from ._correspond_kernels import MM, _model_to_data_at, hand_frames, new_frames
from ._kernel_arrays import CapsuleArrays, HandArrays, SampleArrays, ScoreTerms, SilhouetteArrays, WristCueArrays
from ._wrist_kernels import wrist_cost_at

#: numpy's pairwise sum adds blocks of up to this many elements in 8 accumulators
PAIRWISE_BLOCK = 128


@njit(cache=True, inline="always")
def _pairwise_block(a, lo, n):
    """numpy's pairwise sum of ``a[lo:lo + n]`` for n ≤ :data:`PAIRWISE_BLOCK`: in order below 8, else 8 accumulators."""
    if n < 8:
        res = 0.0
        for i in range(lo, lo + n):
            res += a[i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    m = n - n % 8
    while i < m:
        r0 += a[lo + i]
        r1 += a[lo + i + 1]
        r2 += a[lo + i + 2]
        r3 += a[lo + i + 3]
        r4 += a[lo + i + 4]
        r5 += a[lo + i + 5]
        r6 += a[lo + i + 6]
        r7 += a[lo + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@njit(cache=True)
def pairwise_sum(a, lo, n):
    """``np.add.reduce(a[lo:lo + n])`` for float64 ``a`` as numpy sums it: blocks of up to :data:`PAIRWISE_BLOCK` (see
    :func:`_pairwise_block`), longer runs split in halves (a multiple of 8 first) and the halves' sums
    added — the same bits, so a compiled mean ranks fits exactly as numpy's did. The halving runs on an
    explicit stack: a recursive function in numba's cache leaves its callers an unresolved symbol."""
    if n <= PAIRWISE_BLOCK:
        return _pairwise_block(a, lo, n)
    s_lo = np.empty(64, np.int64)
    s_n = np.empty(64, np.int64)
    s_st = np.empty(64, np.int64)
    vals = np.empty(66)
    sp, vp = 1, 0
    s_lo[0], s_n[0], s_st[0] = lo, n, 0
    while sp > 0:
        t = sp - 1
        m = s_n[t]
        if m <= PAIRWISE_BLOCK:
            vals[vp] = _pairwise_block(a, s_lo[t], m)
            vp += 1
            sp -= 1
            continue
        n2 = m // 2
        n2 -= n2 % 8
        if s_st[t] == 0:  # the first half
            s_st[t] = 1
            s_lo[sp], s_n[sp], s_st[sp] = s_lo[t], n2, 0
            sp += 1
        elif s_st[t] == 1:  # the second half
            s_st[t] = 2
            s_lo[sp], s_n[sp], s_st[sp] = s_lo[t] + n2, m - n2, 0
            sp += 1
        else:  # both halves summed: their sum replaces them
            vals[vp - 2] = vals[vp - 2] + vals[vp - 1]
            vp -= 1
            sp -= 1
    return vals[0]


@njit(cache=True, nogil=True)
def data_cost_mean(G, caps, points, valid, rejected_mm, cap_mm):
    """:func:`tracker.init.data_cost_mm` on the capsule model ``caps``
    (:class:`~tracker._kernel_arrays.CapsuleArrays`) posed by the node frames ``G``, in one call: each
    point's distance (mm) to the nearest surface on any side, ``rejected_mm`` more where its pair was
    rejected (``valid`` False), capped at ``cap_mm``; their mean, summed as numpy sums."""
    P = points.shape[0]
    if P == 0:
        return cap_mm
    out_p = np.empty((P, 3))
    out_n = np.empty((P, 3))
    out_seg = np.empty(P, np.int64)
    out_d = np.empty(P)
    closest_points_facing(G, caps.node, caps.shape, caps.length, caps.r0, caps.r1, caps.thickness, points,
                          np.zeros(3), False, out_p, out_n, out_seg, out_d)
    for i in range(P):
        d = out_d[i] * MM if np.isfinite(out_d[i]) else cap_mm
        d = min(d, cap_mm)
        if not valid[i]:
            d = d + rejected_mm
        out_d[i] = min(d, cap_mm)
    return pairwise_sum(out_d, 0, P) / P


@njit(cache=True, nogil=True)
def search_score(theta, hand, caps, points, valid, terms, samples, sil, cue):
    """:func:`tracker.init.score` in one call, for a hand whose matcher, score samples and wrist cue all
    pose the same model: θ posed once, the data term (:func:`data_cost_mean`), ``m2d_weight`` × the
    model→data mean when ``terms.m2d`` (:class:`~tracker._kernel_arrays.ScoreTerms`), the wrist cue's
    cost when ``cue.on`` (:class:`~tracker._kernel_arrays.WristCueArrays`), added in that order."""
    G, wa, wo = new_frames(hand)
    hand_frames(theta, hand, G, wa, wo)
    s = data_cost_mean(G, caps, points, valid, terms.rejected_mm, terms.data_cap_mm)
    if terms.m2d:
        s += terms.m2d_weight * _model_to_data_at(G, samples, sil, terms.m2d_tolerance_mm, terms.m2d_tolerance_px,
                                                  terms.m2d_cap_mm)
    if cue.on:
        s += wrist_cost_at(G, cue.point, cue.direction, cue.reach_mm, cue.turn_mm)
    return s


@njit(cache=True, nogil=True)
def search_score_entry(theta, hand, caps, points, valid, terms, samples, sil, cue):
    """:func:`search_score` with its named tuples given as plain tuples (:func:`tracker._kernel_arrays.plain`)."""
    return search_score(theta, HandArrays(*hand), CapsuleArrays(*caps), points, valid, ScoreTerms(*terms),
                        SampleArrays(*samples), SilhouetteArrays(*sil), WristCueArrays(*cue))


@njit(cache=True, nogil=True)
def data_cost_mean_entry(G, caps, points, valid, rejected_mm, cap_mm):
    """:func:`data_cost_mean` with ``caps`` given as a plain tuple (:func:`tracker._kernel_arrays.plain`)."""
    return data_cost_mean(G, CapsuleArrays(*caps), points, valid, rejected_mm, cap_mm)
