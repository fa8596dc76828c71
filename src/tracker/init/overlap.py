"""How far the model's fingers pass into each other (:func:`finger_overlap_mm`: what the finger-wise
restarts' ranking adds to :func:`tracker.init.score`, see :func:`tracker.init.finger_search_batched`),
and the closest distance of two segments it is built on, as compiled kernels."""
from __future__ import annotations

import numpy as np
from numba import njit


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
