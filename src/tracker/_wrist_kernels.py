"""Numba kernels of the safety net's wrist test (:mod:`tracker.wrist`,
:meth:`tracker.track.FrameTracker._frame_cue`): the per-frame image work that scipy's calls paid mostly
in call overhead on a hand's window of a few thousand pixels. Each computes exactly what the numpy /
scipy expression in its docstring does (tests/tracker/test_wrist.py compares them)."""
from __future__ import annotations

import numpy as np
from numba import njit

from ._segment_kernels import city_block, component_labels, surface_labels

#: the wrist cue's cost (:func:`tracker.wrist.wrist_cost_mm`): a hand whose wrist is behind the camera
#: costs the reach and this many turns; the arm's image direction counts from this length (a unit
#: vector's, less for an arm seen end-on), the hand's wrist → middle-base span from this many metres
BEHIND_CAMERA_TURNS = 1.5
MIN_ARM_DIRECTION = 0.3
MIN_FINGER_SPAN_M = 1e-6
MIN_DEPTH_M = 1e-3
MM = 1000.0
#: the nodes whose origins are the wrist and the middle finger's base (keypoints 0 and 9)
WRIST_NODE, MIDDLE_BASE_NODE = 0, 9


@njit(cache=True)
def surface_past_outline(dist, frame, v0, u0, reach_px):
    """Whether any ``frame`` pixel (depth, NaN = none) within ``reach_px`` of a silhouette's mask,
    outside it, has depth: ``np.isfinite(frame[v0:v0 + h, u0:u0 + w][(dist > 0) & (dist <= reach_px)]).any()``
    for the silhouette window's distance transform ``dist (h, w)`` at ``(v0, u0)`` in the frame."""
    h, w = dist.shape
    H, W = frame.shape
    for v in range(min(h, H - v0)):
        for u in range(min(w, W - u0)):
            d = dist[v, u]
            if d > 0.0 and d <= reach_px and np.isfinite(frame[v0 + v, u0 + u]):
                return True
    return False


@njit(cache=True)
def arm_entry(dist, iv, iu, frame, v0, u0, reach_px, step_m):
    """``(count, v, u)``: the ``frame`` pixels within ``reach_px`` of a silhouette's mask, outside it,
    whose depth goes on from their nearest mask pixel's (within ``step_m``: a surface such as the arm
    continuing past the outline, as :func:`tracker.wrist.wrist_cue` reads it), and their mean pixel in
    frame coordinates (NaN when none); ``dist``, ``iv``, ``iu``: the silhouette window's distance
    transform and nearest mask pixels at ``(v0, u0)`` in the frame. One pass, ~20 µs: where the arm
    enters, without the cue's line work."""
    h, w = dist.shape
    H, W = frame.shape
    n, sv, su = 0, 0.0, 0.0
    for v in range(min(h, H - v0)):
        for u in range(min(w, W - u0)):
            d = dist[v, u]
            if d > 0.0 and d <= reach_px:
                z = frame[v0 + v, u0 + u]
                zm = frame[v0 + iv[v, u], u0 + iu[v, u]]
                if np.isfinite(z) and np.isfinite(zm) and abs(z - zm) < step_m:
                    n += 1
                    sv += v0 + v
                    su += u0 + u
    if n == 0:
        return 0, np.nan, np.nan
    return n, sv / n, su / n


@njit(cache=True)
def _within_two(a, v, u):
    """Whether ``a`` is set within city-block distance 2 of (v, u): what two 4-connected dilations reach."""
    H, W = a.shape
    for dv in range(-2, 3):
        vv = v + dv
        if vv < 0 or vv >= H:
            continue
        r = 2 - abs(dv)
        for du in range(-r, r + 1):
            uu = u + du
            if 0 <= uu < W and a[vv, uu]:
                return True
    return False


@njit(cache=True)
def outline_and_ring(m, d):
    """``(inner, ring)`` of a mask window ``m`` over its depth ``d``: ``inner = m & ~binary_erosion(m)``
    (a mask pixel with a 4-neighbour off the mask or off the window) and
    ``ring = binary_dilation(m, iterations=2) & ~m & isfinite(d)`` (pixels within 2 steps of the
    mask, 4-connected, off it, with depth)."""
    H, W = m.shape
    inner = np.zeros((H, W), np.bool_)
    ring = np.zeros((H, W), np.bool_)
    for v in range(H):
        for u in range(W):
            if m[v, u]:
                if (v == 0 or u == 0 or v == H - 1 or u == W - 1 or not m[v - 1, u] or not m[v + 1, u]
                        or not m[v, u - 1] or not m[v, u + 1]):
                    inner[v, u] = True
                continue
            if not np.isfinite(d[v, u]):
                continue
            # a mask pixel within city-block distance 2 (what two 4-connected dilations reach)
            ring[v, u] = _within_two(m, v, u)
    return inner, ring


@njit(cache=True)
def longest_line(goes_on, min_share):
    """The pixels of ``goes_on`` in its largest group — groups: the 8-connected components of
    ``binary_dilation(goes_on, iterations=3)``, ranked by their ``goes_on`` pixels, ties to the
    component met first in row order (as ``np.argmax`` over ``scipy.ndimage.label``'s numbering) —
    and whether that group holds at least ``min_share`` of all ``goes_on`` pixels."""
    H, W = goes_on.shape
    grown = city_block(goes_on) <= 3
    lab, n = component_labels(grown, True)
    sizes = np.zeros(n + 1, np.int64)
    for v in range(H):
        for u in range(W):
            if goes_on[v, u]:
                sizes[lab[v, u]] += 1
    line = np.zeros((H, W), np.bool_)
    if n == 0:
        return line, False
    k, total = 1, 0
    for j in range(1, n + 1):
        total += sizes[j]
        if sizes[j] > sizes[k]:
            k = j
    for v in range(H):
        for u in range(W):
            line[v, u] = goes_on[v, u] and lab[v, u] == k
    return line, sizes[k] >= min_share * total


@njit(cache=True)
def near_line(inner, line):
    """``inner & binary_dilation(line, iterations=2)``: the outline pixels within 2 steps (4-connected)
    of the wrist line."""
    H, W = inner.shape
    out = np.zeros((H, W), np.bool_)
    for v in range(H):
        for u in range(W):
            if inner[v, u]:
                out[v, u] = _within_two(line, v, u)
    return out


@njit(cache=True)
def surface_depth(m, d, y, x, r):
    """At each pixel ``(y[i], x[i])``: ``np.nanmedian`` of ``np.where(m, d, nan)`` over the square
    window of half-width ``r`` around it, clipped at the image's edges (NaN where it holds no depth) —
    the hand's surface depth behind an outline pixel (:func:`tracker.wrist.wrist_cue`)."""
    H, W = m.shape
    out = np.empty(y.shape[0])
    buf = np.empty((2 * r + 1) * (2 * r + 1))
    for i in range(y.shape[0]):
        n = 0
        for v in range(max(y[i] - r, 0), min(y[i] + r + 1, H)):
            for u in range(max(x[i] - r, 0), min(x[i] + r + 1, W)):
                if m[v, u] and np.isfinite(d[v, u]):
                    # insertion into the sorted buffer (at most (2r + 1)² values)
                    z = d[v, u]
                    k = n
                    while k > 0 and buf[k - 1] > z:
                        buf[k] = buf[k - 1]
                        k -= 1
                    buf[k] = z
                    n += 1
        if n == 0:
            out[i] = np.nan
            continue
        h = n // 2
        # numpy's median of an even count: the mean of the two middle values
        out[i] = buf[h] if n % 2 else (buf[h - 1] + buf[h]) / 2.0
    return out


@njit(cache=True)
def seeded_surfaces(d, seed, jump, within, dist):
    """The pixels of the surfaces of ``d`` (:func:`tracker.segment.surfaces` with ``jump``: 4-connected,
    split at depth steps, a step's far-side pixel given to its nearest-in-depth neighbour's surface)
    that hold a ``seed`` pixel, and that lie within ``within`` of one (``dist``: the exact distance to
    the nearest seed pixel, as ``distance_transform_edt(~seed)``)."""
    H, W = d.shape
    out, n = surface_labels(d, jump)
    keep = np.zeros(n + 1, np.bool_)
    for v in range(H):
        for u in range(W):
            if seed[v, u] and out[v, u] > 0:
                keep[out[v, u]] = True
    arm = np.zeros((H, W), np.bool_)
    for v in range(H):
        for u in range(W):
            arm[v, u] = keep[out[v, u]] and out[v, u] > 0 and dist[v, u] <= within
    return arm


@njit(cache=True)
def count_near(mask, depth, y0, y1, x0, x1, u, v, r, z, step_m):
    """How many pixels of ``[y0:y1, x0:x1]`` lie within ``r`` px of ``(u, v)``, off ``mask``, at a
    ``depth`` within ``step_m`` of ``z``: :func:`tracker.wrist.arm_behind`'s
    ``(((yy - v) ** 2 + (xx - u) ** 2 <= r * r) & ~mask & (abs(depth - z) <= step_m)).sum()``."""
    n = 0
    rr = r * r
    for y in range(y0, y1):
        for x in range(x0, x1):
            if (y - v) ** 2 + (x - u) ** 2 <= rr and not mask[y, x] and abs(depth[y, x] - z) <= step_m:
                n += 1
    return n


@njit(cache=True, inline="always")
def wrist_cost_at(G, point, direction, reach_mm, turn_mm):
    """:func:`tracker.wrist.wrist_cost_mm` with the hand's node frames ``G`` (keypoints 0, the wrist, and
    9, the middle finger's base, are nodes 0 and 9's origins): the same operations in order."""
    w0, w1, w2 = G[WRIST_NODE, 0, 3], G[WRIST_NODE, 1, 3], G[WRIST_NODE, 2, 3]
    if w2 <= MIN_DEPTH_M:
        return reach_mm + BEHIND_CAMERA_TURNS * turn_mm
    far = np.hypot(w0 / w2 - point[0] / point[2], w1 / w2 - point[1] / point[2]) * point[2] * MM
    cost = max(far - reach_mm, 0.0)
    a0, a1 = direction[0], direction[1]
    f0, f1 = G[MIDDLE_BASE_NODE, 0, 3] - w0, G[MIDDLE_BASE_NODE, 1, 3] - w1
    na = np.sqrt(a0 * a0 + a1 * a1)
    nf = np.sqrt(f0 * f0 + f1 * f1)
    if na > MIN_ARM_DIRECTION and nf > MIN_FINGER_SPAN_M:
        cost += turn_mm * max((a0 * f0 + a1 * f1) / (na * nf), 0.0)
    return cost
