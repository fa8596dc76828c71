"""Numba kernels of the observe stage (:mod:`tracker.observe`): one hand window's smoothing,
back-projection and normals, and the gate of the points near the predicted hand (a uniform grid)
with the re-centring's shift."""
from __future__ import annotations

import numpy as np
from numba import njit

#: the edge-preserving smoothing averages the neighbours within this depth (m) of a pixel's own
#: (:func:`tracker.observe.smooth_depth`'s ``max_diff``)
SMOOTH_MAX_DIFF_M = 0.01
#: the grid of :func:`_grid` grows its cell until it has at most this many cells
MAX_GRID_CELLS = 1 << 20
#: the smallest grid cell (m): a gate of radius 0 still builds a grid
MIN_CELL_M = 1e-9
#: added to a normal's length before dividing (as tracker.observe.image_normals): a zero cross product stays 0
NORMAL_GUARD = 1e-300


@njit(cache=True)
def observe_window(dw, mw, fx, fy, cx, cy, smooth, max_diff, max_jump, stride, oy, ox, dsm, pts, nrm):
    """One hand window of :func:`tracker.observe.observe` compiled: the depth ``dw`` smoothed into
    ``dsm`` (:func:`tracker.observe.smooth_depth` with ``smooth`` px and ``max_diff`` m; a copy when
    0), then at the kept pixels only — the mask ``mw``, every ``stride``-th row and column from
    ``(oy, ox)``, finite depth — the back-projected point (window camera ``fx fy cx cy``) and the
    normal of :func:`tracker.observe.image_normals` (central differences, NaN at the window's border
    or across a depth jump above ``max_jump``), written to ``pts``/``nrm`` in row-major order. The
    numpy path computed smoothing, points and normals for every pixel of the window and then kept
    one in stride². ``dsm`` is smoothed at the mask's pixels and their 4-neighbours (what the points, the
    normals and the silhouette's depth read), the raw depth elsewhere (finite where the smoothed one is).
    Returns the number of kept pixels."""
    h, w = dw.shape
    for v in range(h):
        for u in range(w):
            d = dw[v, u]
            if smooth == 0:
                dsm[v, u] = d
                continue
            if not np.isfinite(d):
                dsm[v, u] = np.nan
                continue
            if not (mw[v, u] or (v > 0 and mw[v - 1, u]) or (v < h - 1 and mw[v + 1, u])
                    or (u > 0 and mw[v, u - 1]) or (u < w - 1 and mw[v, u + 1])):
                # neither in the mask nor next to it: no point, normal or silhouette depth reads its
                # smoothed value (the dropout band reads only whether it has depth, which smoothing keeps)
                dsm[v, u] = d
                continue
            # the numpy version's order of summation (rows, then columns), so the mean is bit-identical
            acc = 0.0
            cnt = 0
            for dy in range(-smooth, smooth + 1):
                vv = v + dy
                for dx in range(-smooth, smooth + 1):
                    uu = u + dx
                    if vv < 0 or vv >= h or uu < 0 or uu >= w:
                        continue
                    nb = dw[vv, uu]
                    if np.isfinite(nb) and abs(nb - d) <= max_diff:
                        acc += nb
                        cnt += 1
            dsm[v, u] = acc / cnt if cnt > 0 else np.nan
    k = 0
    for v in range(oy, h, stride):
        for u in range(ox, w, stride):
            d = dsm[v, u]
            if not mw[v, u] or not np.isfinite(d):
                continue
            X0 = d * ((u - cx) / fx)
            X1 = d * ((v - cy) / fy)
            pts[k, 0], pts[k, 1], pts[k, 2] = X0, X1, d
            n0 = n1 = n2 = np.nan
            if 0 < u < w - 1 and 0 < v < h - 1:
                dl, dr, du, dd = dsm[v, u - 1], dsm[v, u + 1], dsm[v - 1, u], dsm[v + 1, u]
                a0 = dr * ((u + 1 - cx) / fx) - dl * ((u - 1 - cx) / fx)
                a1 = dr * ((v - cy) / fy) - dl * ((v - cy) / fy)
                a2 = dr - dl
                b0 = dd * ((u - cx) / fx) - du * ((u - cx) / fx)
                b1 = dd * ((v + 1 - cy) / fy) - du * ((v - 1 - cy) / fy)
                b2 = dd - du
                c0 = a1 * b2 - a2 * b1
                c1 = a2 * b0 - a0 * b2
                c2 = a0 * b1 - a1 * b0
                nn = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2) + NORMAL_GUARD
                c0, c1, c2 = c0 / nn, c1 / nn, c2 / nn
                # oriented towards the camera; a jump (not NaN: NaN compares False) voids the normal
                dot = c0 * X0 + c1 * X1 + c2 * d
                sg = -1.0 if dot > 0 else (1.0 if dot < 0 else (0.0 if dot == 0 else np.nan))
                if not (abs(a2) > max_jump or abs(b2) > max_jump):
                    n0, n1, n2 = c0 * sg, c1 * sg, c2 * sg
            nrm[k, 0], nrm[k, 1], nrm[k, 2] = n0, n1, n2
            k += 1
    return k


@njit(cache=True)
def _grid(X, use, cell):
    """A uniform grid of cell size ``cell`` over the rows of ``X`` with ``use`` set: its origin, shape
    and the rows sorted by cell (CSR: ``start[c]:start[c+1]`` index ``order``). The cell grows when
    the rows are spread so far that the grid would exceed 2²⁰ cells (a neighbour search of radius ≤
    cell still only needs the 27 cells around a point)."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for i in range(X.shape[0]):
        if use[i]:
            for r in range(3):
                lo[r] = min(lo[r], X[i, r])
                hi[r] = max(hi[r], X[i, r])
    while True:
        dims = np.empty(3, np.int64)
        for r in range(3):
            dims[r] = int((hi[r] - lo[r]) / cell) + 1
        if dims[0] * dims[1] * dims[2] <= MAX_GRID_CELLS:
            break
        cell *= 2.0
    n_cells = dims[0] * dims[1] * dims[2]
    start = np.zeros(n_cells + 1, np.int64)
    cid = np.full(X.shape[0], -1, np.int64)
    for i in range(X.shape[0]):
        if use[i]:
            c = 0
            for r in range(3):
                c = c * dims[r] + min(int((X[i, r] - lo[r]) / cell), dims[r] - 1)
            cid[i] = c
            start[c + 1] += 1
    for c in range(n_cells):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    order = np.empty(start[n_cells], np.int64)
    for i in range(X.shape[0]):
        c = cid[i]
        if c >= 0:
            order[fill[c]] = i
            fill[c] += 1
    return lo, dims, cell, start, order


@njit(cache=True)
def _any_within(p, X, lo, dims, cell, start, order, r2):
    """Whether any gridded row of ``X`` lies closer than √r2 to the point ``p`` (r2 ≤ cell²)."""
    c0 = np.empty(3, np.int64)
    for r in range(3):
        f = (p[r] - lo[r]) / cell
        if f < -1.0 or f >= dims[r] + 1.0:
            return False
        c0[r] = int(np.floor(f))
    # the point's own cell first: a near point mostly has its neighbour there (the answer is the same)
    own = -1
    if 0 <= c0[0] < dims[0] and 0 <= c0[1] < dims[1] and 0 <= c0[2] < dims[2]:
        own = (c0[0] * dims[1] + c0[1]) * dims[2] + c0[2]
        if _cell_within(p, X, start, order, own, r2):
            return True
    for a in range(max(c0[0] - 1, 0), min(c0[0] + 2, dims[0])):
        for b in range(max(c0[1] - 1, 0), min(c0[1] + 2, dims[1])):
            for c in range(max(c0[2] - 1, 0), min(c0[2] + 2, dims[2])):
                k = (a * dims[1] + b) * dims[2] + c
                if k != own and _cell_within(p, X, start, order, k, r2):
                    return True
    return False


@njit(cache=True, inline="always")
def _cell_within(p, X, start, order, k, r2):
    """Whether a row of ``X`` in grid cell ``k`` lies closer than √r2 to ``p``."""
    for q in range(start[k], start[k + 1]):
        i = order[q]
        d0 = X[i, 0] - p[0]
        d1 = X[i, 1] - p[1]
        d2 = X[i, 2] - p[2]
        if d0 * d0 + d1 * d1 + d2 * d2 < r2:
            return True
    return False


@njit(cache=True)
def gate_kernel(points, model, model_n, use_normals, radius, min_share, min_points, near):
    """:func:`tracker.observe.gate` compiled (a uniform grid instead of two KD-trees): ``near[i]``
    whether data point ``i`` lies closer than ``radius`` to a (finite; with ``use_normals``
    camera-facing) model sample. Returns whether the gate applies — at least ``min_points`` near
    points and at least ``min_share`` of those samples near one of them; when it returns False every
    point is to be kept."""
    nM = model.shape[0]
    ok = np.zeros(nM, np.bool_)
    n_ok = 0
    for i in range(nM):
        good = np.isfinite(model[i, 0]) and np.isfinite(model[i, 1]) and np.isfinite(model[i, 2])
        if good and use_normals:
            good = model_n[i, 0] * model[i, 0] + model_n[i, 1] * model[i, 1] + model_n[i, 2] * model[i, 2] < 0.0
        ok[i] = good
        if good:
            n_ok += 1
    P = points.shape[0]
    for i in range(P):
        near[i] = False
    if n_ok == 0 or P == 0:
        return False
    r2 = radius * radius
    lo, dims, cell, start, order = _grid(model, ok, max(radius, MIN_CELL_M))
    n_near = 0
    for i in range(P):
        if np.isfinite(points[i, 0]) and np.isfinite(points[i, 1]) and np.isfinite(points[i, 2]):
            if _any_within(points[i], model, lo, dims, cell, start, order, r2):
                near[i] = True
                n_near += 1
    if n_near < max(min_points, 1):
        return False
    lo, dims, cell, start, order = _grid(points, near, max(radius, MIN_CELL_M))
    # stops as soon as the share is reached or out of reach (the common case decides early)
    hits = 0
    left = n_ok
    for i in range(nM):
        if not ok[i]:
            continue
        left -= 1
        if _any_within(model[i], points, lo, dims, cell, start, order, r2):
            hits += 1
            if hits / n_ok >= min_share:
                return True
        elif (hits + left) / n_ok < min_share:
            return False
    return hits / n_ok >= min_share


@njit(cache=True)
def centre_shift(points, model, model_n, shift):
    """The per-axis median of the data ``points`` minus that of the camera-facing model samples into
    ``shift`` (what :meth:`tracker.track.FrameTracker._recentred` compares with the rejection radius);
    returns the number of facing samples (the shift is left unset below 1)."""
    nM = model.shape[0]
    facing = np.empty(nM, np.bool_)
    nf = 0
    for i in range(nM):
        f = model_n[i, 0] * model[i, 0] + model_n[i, 1] * model[i, 1] + model_n[i, 2] * model[i, 2] < 0.0
        facing[i] = f
        if f:
            nf += 1
    if nf == 0 or points.shape[0] == 0:
        return nf
    col = np.empty(points.shape[0])
    sel = np.empty(nf)
    for r in range(3):
        for i in range(points.shape[0]):
            col[i] = points[i, r]
        k = 0
        for i in range(nM):
            if facing[i]:
                sel[k] = model[i, r]
                k += 1
        shift[r] = np.median(col) - np.median(sel)
    return nf

