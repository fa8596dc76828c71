"""Numba kernel of the segmenter's surfaces (:func:`tracker.segment.surfaces`), which runs several
times on every tracked frame's window: scipy's labelling and the numpy step tests cost mostly their
call overhead there. It computes exactly what the numpy / scipy expression in its docstring did
(tests/tracker/test_segment.py compares them)."""
from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def surface_labels(d, jump):
    """``(labels int32 (H, W), n)``: the 4-connected surfaces of the depth image ``d`` (NaN = none),
    split where neighbours differ by more than ``jump``.

    A pixel more than ``jump`` behind a 4-neighbour (a step's far side) is not core; the core pixels
    are labelled as ``scipy.ndimage.label`` does (4-connected, numbered in raster order of each
    surface's first pixel; ``n`` counts them); each far-side pixel then takes the label of its
    4-neighbour nearest in depth within ``jump`` (right, left, down, up: the first on ties; 0 when
    none)."""
    H, W = d.shape
    core = np.zeros((H, W), np.bool_)
    for v in range(H):
        for u in range(W):
            z = d[v, u]
            if not np.isfinite(z):
                continue
            far = ((u > 0 and z - d[v, u - 1] > jump) or (u < W - 1 and z - d[v, u + 1] > jump)
                   or (v > 0 and z - d[v - 1, u] > jump) or (v < H - 1 and z - d[v + 1, u] > jump))
            core[v, u] = not far
    lab = np.zeros((H, W), np.int32)
    n = _components(core, lab, np.empty(H * W, np.int64), False)
    # the far-side pixels labelled in place: each reads its core neighbours only (labelled, never rewritten)
    for v in range(H):
        for u in range(W):
            z = d[v, u]
            if core[v, u] or not np.isfinite(z):
                continue
            best, got = np.inf, 0
            for k in range(4):
                qv = v + (1 if k == 2 else -1 if k == 3 else 0)
                qu = u + (1 if k == 0 else -1 if k == 1 else 0)
                if 0 <= qv < H and 0 <= qu < W and core[qv, qu]:
                    diff = abs(d[qv, qu] - z)
                    if diff <= jump and diff < best:
                        got, best = lab[qv, qu], diff
            lab[v, u] = got
    return lab, n


@njit(cache=True)
def city_block(mask):
    """The 4-connected (city-block) distance of every pixel to the nearest ``mask`` pixel, in pixels
    (2⁶² where the mask is empty): two raster passes. ``city_block(m) <= k`` is what ``k``
    iterations of ``scipy.ndimage.binary_dilation(m)`` (its cross) give."""
    H, W = mask.shape
    big = 1 << 62
    d = np.empty((H, W), np.int64)
    for v in range(H):
        for u in range(W):
            if mask[v, u]:
                d[v, u] = 0
            else:
                best = big
                if v > 0 and d[v - 1, u] + 1 < best:
                    best = d[v - 1, u] + 1
                if u > 0 and d[v, u - 1] + 1 < best:
                    best = d[v, u - 1] + 1
                d[v, u] = best
    for v in range(H - 1, -1, -1):
        for u in range(W - 1, -1, -1):
            if v < H - 1 and d[v + 1, u] + 1 < d[v, u]:
                d[v, u] = d[v + 1, u] + 1
            if u < W - 1 and d[v, u + 1] + 1 < d[v, u]:
                d[v, u] = d[v, u + 1] + 1
    return d


@njit(cache=True)
def closed_filled(m):
    """``binary_fill_holes(binary_closing(m) | m)`` (scipy's closing with its cross, the border outside
    counting as background; holes: background 4-connected, not reaching the array's edge)."""
    H, W = m.shape
    dil = np.zeros((H, W), np.bool_)
    for v in range(H):
        for u in range(W):
            dil[v, u] = m[v, u] or (v > 0 and m[v - 1, u]) or (v < H - 1 and m[v + 1, u]) or (
                u > 0 and m[v, u - 1]) or (u < W - 1 and m[v, u + 1])
    out = np.zeros((H, W), np.bool_)
    for v in range(H):
        for u in range(W):
            if m[v, u]:
                out[v, u] = True
            elif 0 < v < H - 1 and 0 < u < W - 1:
                out[v, u] = dil[v, u] and dil[v - 1, u] and dil[v + 1, u] and dil[v, u - 1] and dil[v, u + 1]
    return fill_holes(out)


@njit(cache=True)
def _line_extreme(x, n, h, sign, pad, g, r, out):
    """``out[i] = sign · max(sign · x[j] for |j − i| <= h, 0 <= j < n)`` (van Herk / Gil-Werman: a
    running maximum forwards and backwards in blocks of the window's width; ``pad``, ``g``, ``r``:
    work arrays of at least ``n + 2h``)."""
    w = 2 * h + 1
    m = n + 2 * h
    for i in range(h):
        pad[i] = -np.inf
        pad[m - 1 - i] = -np.inf
    for i in range(n):
        pad[h + i] = sign * x[i]
    for b in range(0, m, w):
        e = min(b + w, m)
        acc = pad[b]
        g[b] = acc
        for i in range(b + 1, e):
            if pad[i] > acc:
                acc = pad[i]
            g[i] = acc
        acc = pad[e - 1]
        r[e - 1] = acc
        for i in range(e - 2, b - 1, -1):
            if pad[i] > acc:
                acc = pad[i]
            r[i] = acc
    for i in range(n):
        x0, x1 = r[i], g[i + 2 * h]
        out[i] = sign * (x0 if x0 > x1 else x1)


@njit(cache=True)
def window_extreme(a, h, sign):
    """The maximum (``sign`` 1) or minimum (−1) of ``a`` over each pixel's ``(2h+1)²`` window, pixels
    outside the array left out: ``scipy.ndimage.maximum_filter`` / ``minimum_filter`` with
    ``size=2h+1`` under any border mode that cannot win (``constant`` with ±inf, ``reflect``,
    ``nearest``), for arrays without NaN."""
    H, W = a.shape
    L = max(H, W) + 2 * h
    pad, g, r = np.empty(L), np.empty(L), np.empty(L)
    tmp = np.empty((W, H))  # the row pass's result transposed: the column pass reads rows again
    row = np.empty(W)
    for v in range(H):
        _line_extreme(a[v], W, h, sign, pad, g, r, row)
        for u in range(W):
            tmp[u, v] = row[u]
    out = np.empty((H, W))
    col = np.empty(H)
    for u in range(W):
        _line_extreme(tmp[u], H, h, sign, pad, g, r, col)
        for v in range(H):
            out[v, u] = col[v]
    return out


@njit(cache=True)
def window_any(m, h):
    """``scipy.ndimage.maximum_filter(m, size=2h+1)`` of a boolean mask (any mask pixel in the
    ``(2h+1)²`` window; the border never wins): running counts along rows, then columns."""
    H, W = m.shape
    tmp = np.zeros((H, W), np.bool_)
    for v in range(H):
        c = 0
        for u in range(min(h, W)):
            c += m[v, u]
        for u in range(W):
            if u + h < W:
                c += m[v, u + h]
            if u - h - 1 >= 0:
                c -= m[v, u - h - 1]
            tmp[v, u] = c > 0
    out = np.zeros((H, W), np.bool_)
    cnt = np.zeros(W, np.int64)
    for v in range(min(h, H)):
        for u in range(W):
            cnt[u] += tmp[v, u]
    for v in range(H):
        if v + h < H:
            for u in range(W):
                cnt[u] += tmp[v + h, u]
        if v - h - 1 >= 0:
            for u in range(W):
                cnt[u] -= tmp[v - h - 1, u]
        for u in range(W):
            out[v, u] = cnt[u] > 0
    return out


@njit(cache=True)
def label_max(values, lab, n):
    """``scipy.ndimage.maximum(values, lab, index=range(1, n + 1))`` for labels that all occur."""
    out = np.full(n, -np.inf)
    H, W = lab.shape
    for v in range(H):
        for u in range(W):
            k = lab[v, u]
            if k > 0 and values[v, u] > out[k - 1]:
                out[k - 1] = values[v, u]
    return out


@njit(cache=True)
def _voronoi_line(fa, fo, n, c, g, out_a, out_o):
    """One line of Maurer, Qi & Raghavan's exact feature transform (PAMI 2003): positions ``0..n-1``
    along an axis, at coordinate ``c`` on the other; ``fa[i]``/``fo[i]`` the coordinates (along /
    other) of the site position ``i`` holds (``fa[i] < 0``: none). Keeps the sites whose Voronoi
    cells cross the line, then gives each position its nearest; ties go as scipy's implementation
    of the same paper sends them (a site is dropped when the test is <= 0, the earlier site is kept
    when as near)."""
    l = -1
    for i in range(n):
        if fa[i] < 0:
            continue
        w_r = float((fo[i] - c) * (fo[i] - c))
        while l >= 1:
            i1, i2 = g[l], g[l - 1]
            a = float(fa[i1] - fa[i2])
            b = float(fa[i] - fa[i1])
            cc = a + b
            u_r = float((fo[i2] - c) * (fo[i2] - c))
            v_r = float((fo[i1] - c) * (fo[i1] - c))
            if cc * v_r - b * u_r - a * w_r - a * b * cc <= 0.0:
                break
            l -= 1
        l += 1
        g[l] = i
    if l < 0:
        for i in range(n):
            out_a[i] = fa[i]
            out_o[i] = fo[i]
        return
    top = l
    l = 0
    for i in range(n):
        d1 = (fa[g[l]] - i) * (fa[g[l]] - i) + (fo[g[l]] - c) * (fo[g[l]] - c)
        while l < top:
            j = g[l + 1]
            d2 = (fa[j] - i) * (fa[j] - i) + (fo[j] - c) * (fo[j] - c)
            if d1 <= d2:
                break
            d1 = d2
            l += 1
        out_a[i] = fa[g[l]]
        out_o[i] = fo[g[l]]


@njit(cache=True)
def nearest_rows(mask, rows):
    """Each pixel's nearest ``mask`` pixel in its own column, its row into ``rows`` (−1: the column has
    none; the upper one on ties, as scipy's transforms), by two sweeps in memory order. Returns whether
    the mask has a pixel at all. The first pass of both exact distance transforms
    (:func:`nearest_target`, :func:`tracker._icp_kernels.feature_transform`)."""
    H, W = mask.shape
    last = np.full(W, -1, np.int64)
    any_mask = False
    for v in range(H):
        for u in range(W):
            if mask[v, u]:
                last[u] = v
                any_mask = True
            rows[v, u] = last[u]
    last[:] = -1
    for v in range(H - 1, -1, -1):
        for u in range(W):
            if mask[v, u]:
                last[u] = v
            if last[u] >= 0 and (rows[v, u] < 0 or last[u] - v < v - rows[v, u]):
                rows[v, u] = last[u]
    return any_mask


@njit(cache=True)
def nearest_target(targets, dist, iv, iu):
    """Each pixel's nearest ``targets`` pixel (row ``iv``, column ``iu``) and its distance ``dist``, as
    ``scipy.ndimage.distance_transform_edt(~targets, return_indices=True)`` gives them, ties included
    (the same algorithm: per column along the rows, then per row along the columns). Returns False
    (outputs unset) when there is no target."""
    H, W = targets.shape
    rv = np.empty((H, W), np.int64)
    if not nearest_rows(targets, rv):
        return False
    n = max(H, W)
    g = np.empty(n, np.int64)
    fa, fo = np.empty(n, np.int64), np.empty(n, np.int64)
    oa, oo = np.empty(n, np.int64), np.empty(n, np.int64)
    # the first pass (per column along the rows, in nearest_rows above) has every site on the line
    # itself, so none is ever dropped and each pixel takes its column's nearest target row
    for v in range(H):
        for u in range(W):
            # along the row: the along coordinate is the column, "none" marked by the row
            fa[u] = u if rv[v, u] >= 0 else -1
            fo[u] = rv[v, u]
        _voronoi_line(fa, fo, W, v, g, oa, oo)
        for u in range(W):
            iu[v, u] = oa[u]
            iv[v, u] = oo[u]
            du, dv = float(oa[u] - u), float(oo[u] - v)
            dist[v, u] = np.sqrt(dv * dv + du * du)
    return True


# neighbour steps: the first four are the 4-connected ones (a flood visits them in this order)
_DV = (1, -1, 0, 0, 1, 1, -1, -1)
_DU = (0, 0, 1, -1, 1, -1, 1, -1)


@njit(cache=True)
def _flood(mask, mark, value, stack, top, eight):
    """Spread ``value`` into ``mark`` from the pixels on ``stack[:top]`` (flat indices, marked already)
    over the 4-connected (or, with ``eight``, 8-connected) pixels of ``mask`` not marked yet."""
    H, W = mask.shape
    if not eight:
        # the four neighbours unrolled (the same pixels are marked: which ones does not depend on the order)
        while top:
            top -= 1
            p = stack[top]
            pv, pu = p // W, p % W
            if pv + 1 < H and mask[pv + 1, pu] and not mark[pv + 1, pu]:
                mark[pv + 1, pu] = value
                stack[top] = p + W
                top += 1
            if pv > 0 and mask[pv - 1, pu] and not mark[pv - 1, pu]:
                mark[pv - 1, pu] = value
                stack[top] = p - W
                top += 1
            if pu + 1 < W and mask[pv, pu + 1] and not mark[pv, pu + 1]:
                mark[pv, pu + 1] = value
                stack[top] = p + 1
                top += 1
            if pu > 0 and mask[pv, pu - 1] and not mark[pv, pu - 1]:
                mark[pv, pu - 1] = value
                stack[top] = p - 1
                top += 1
        return
    nk = 8
    while top:
        top -= 1
        p = stack[top]
        pv, pu = p // W, p % W
        for k in range(nk):
            qv = pv + _DV[k]
            qu = pu + _DU[k]
            if 0 <= qv < H and 0 <= qu < W and mask[qv, qu] and not mark[qv, qu]:
                mark[qv, qu] = value
                stack[top] = qv * W + qu
                top += 1


@njit(cache=True)
def _components(mask, lab, stack, eight):
    """4-connected (or, with ``eight``, 8-connected) components of ``mask`` into ``lab`` (numbered in
    raster order of their first pixel, as ``scipy.ndimage.label`` numbers them); returns their count."""
    H, W = mask.shape
    n = 0
    for v in range(H):
        for u in range(W):
            if not mask[v, u] or lab[v, u]:
                continue
            n += 1
            lab[v, u] = n
            stack[0] = v * W + u
            _flood(mask, lab, n, stack, 1, eight)
    return n


@njit(cache=True)
def largest_component(mask):
    """The largest 4-connected component of ``mask`` (the first in raster order on ties, as
    ``np.argmax`` over ``scipy.ndimage.label``'s sizes picks it); the mask itself when it has at most one."""
    H, W = mask.shape
    lab = np.zeros((H, W), np.int32)
    n = _components(mask, lab, np.empty(H * W, np.int64), False)
    if n <= 1:
        return mask.copy()
    size = np.zeros(n + 1, np.int64)
    for v in range(H):
        for u in range(W):
            size[lab[v, u]] += 1
    best = 1
    for k in range(2, n + 1):
        if size[k] > size[best]:
            best = k
    out = np.zeros((H, W), np.bool_)
    for v in range(H):
        for u in range(W):
            out[v, u] = lab[v, u] == best
    return out


@njit(cache=True)
def components_holding(mask, seed):
    """The 4-connected components of ``mask`` that hold a ``seed`` pixel."""
    H, W = mask.shape
    out = np.zeros((H, W), np.bool_)
    stack = np.empty(H * W, np.int64)
    top = 0
    for v in range(H):
        for u in range(W):
            if seed[v, u] and mask[v, u] and not out[v, u]:
                out[v, u] = True
                stack[top] = v * W + u
                top += 1
    _flood(mask, out, True, stack, top, False)
    return out


@njit(cache=True)
def dropout_band_kernel(m, d, width, band, fill):
    """:func:`tracker.observe.dropout_band` into ``band`` (bool) and ``fill`` (NaN off the band): ring by
    ring, the pixels without depth 4-adjacent to the mask or the band so far, each given the smallest
    depth of its 4-neighbours (their own, or their fill; NaN when none has one)."""
    H, W = m.shape
    reach = m.copy()
    val = np.full((H, W), np.nan)
    for v in range(H):
        for u in range(W):
            band[v, u] = False
            if m[v, u] and np.isfinite(d[v, u]):
                val[v, u] = d[v, u]
    add = np.zeros((H, W), np.bool_)
    near = np.empty((H, W))
    for _ in range(width):
        any_add = False
        for v in range(H):
            for u in range(W):
                add[v, u] = False
                if reach[v, u] or np.isfinite(d[v, u]):
                    continue
                grow = False
                best = np.nan
                for k in range(4):
                    qv = v + (1 if k == 0 else -1 if k == 1 else 0)
                    qu = u + (1 if k == 2 else -1 if k == 3 else 0)
                    if 0 <= qv < H and 0 <= qu < W:
                        grow = grow or reach[qv, qu]
                        x = val[qv, qu]
                        if not np.isnan(x) and (np.isnan(best) or x < best):
                            best = x
                if grow:
                    add[v, u] = True
                    near[v, u] = best
                    any_add = True
        if not any_add:
            break
        for v in range(H):
            for u in range(W):
                if add[v, u]:
                    band[v, u] = True
                    reach[v, u] = True
                    val[v, u] = near[v, u]
    for v in range(H):
        for u in range(W):
            fill[v, u] = val[v, u] if band[v, u] else np.nan


@njit(cache=True)
def skin_channels(c, v0, v1, s0, s1):
    """The skin test on the channels (any hue): ``V = max(r, g, b)`` within ``[v0, v1]`` and the
    spread ``(V − min)·255`` within ``[s0·V, s1·V]``, in integers (:func:`tracker.segment.skin_mask`)."""
    H, W = c.shape[0], c.shape[1]
    out = np.empty((H, W), np.bool_)
    for v in range(H):
        for u in range(W):
            r, g, b = np.int32(c[v, u, 0]), np.int32(c[v, u, 1]), np.int32(c[v, u, 2])
            hi = max(r, max(g, b))
            spread = (hi - min(r, min(g, b))) * 255
            out[v, u] = v0 <= hi <= v1 and s0 * hi <= spread <= s1 * hi
    return out


@njit(cache=True)
def refine_window(cmask, cdepth, depth, y0, y1, x0, x1, step, jump):
    """:func:`tracker.segment.refine`'s test in its window ``[y0:y1, x0:x1]``: each full-resolution pixel
    takes its nearest coarse sample (``rint(i / step)``, halves to even, clipped), and is kept when its
    depth lies within ``jump`` of the range of the masked samples' depths in the ``(2·step + 1)²``
    window around it (NaN depth: not kept)."""
    h, w = y1 - y0, x1 - x0
    Hc, Wc = cmask.shape
    lo_src = np.empty((h, w))
    hi_src = np.empty((h, w))
    for r in range(h):
        iy = min(max(int(np.rint((y0 + r) / step)), 0), Hc - 1)
        for c in range(w):
            ix = min(max(int(np.rint((x0 + c) / step)), 0), Wc - 1)
            if cmask[iy, ix]:
                lo_src[r, c] = cdepth[iy, ix]
                hi_src[r, c] = cdepth[iy, ix]
            else:
                lo_src[r, c] = np.inf
                hi_src[r, c] = -np.inf
    lo = window_extreme(lo_src, step, -1.0)
    hi = window_extreme(hi_src, step, 1.0)
    ok = np.empty((h, w), np.bool_)
    for r in range(h):
        for c in range(w):
            z = depth[y0 + r, x0 + c]
            ok[r, c] = z >= lo[r, c] - jump and z <= hi[r, c] + jump
    return ok


@njit(cache=True)
def mask_bounds(mask):
    """``(row_min, row_max, col_min, col_max)`` of the set pixels of a 2-D boolean mask (inclusive),
    or ``(-1, -1, -1, -1)`` when none is set: ``np.flatnonzero(mask.any(1))`` / ``(0)``'s ends in one
    pass, rows scanned from the top and bottom until a set pixel (a hand fills a few rows of its window)."""
    H, W = mask.shape
    r0 = -1
    for y in range(H):
        for x in range(W):
            if mask[y, x]:
                r0 = y
                break
        if r0 >= 0:
            break
    if r0 < 0:
        return -1, -1, -1, -1
    r1 = r0
    for y in range(H - 1, r0, -1):
        found = False
        for x in range(W):
            if mask[y, x]:
                found = True
                break
        if found:
            r1 = y
            break
    c0, c1 = W, -1
    for y in range(r0, r1 + 1):
        for x in range(W):
            if mask[y, x]:
                c0 = min(c0, x)
                break
        for x in range(W - 1, c1, -1):
            if mask[y, x]:
                c1 = max(c1, x)
                break
    return r0, r1, c0, c1


@njit(cache=True)
def nan_median(values):
    """``np.nanmedian`` of a 1-D float64 array: the middle of its non-NaN values sorted, or the mean of
    the two middle ones, (a + b) / 2 as numpy computes it; NaN when every value is NaN."""
    n = 0
    buf = np.empty(values.shape[0])
    for i in range(values.shape[0]):
        if not np.isnan(values[i]):
            buf[n] = values[i]
            n += 1
    if n == 0:
        return np.nan
    # numba's median selects the middle one(s) (quickselect) instead of sorting: the same values, and the
    # mean of two as (a + b) / 2
    return np.median(buf[:n])


@njit(cache=True)
def component_labels(mask, eight):
    """``scipy.ndimage.label(mask)`` (4-connected) or with ``structure=np.ones((3, 3))`` (``eight``):
    ``(labels int32, n)``, numbered in raster order of each component's first pixel as scipy numbers
    them."""
    H, W = mask.shape
    lab = np.zeros((H, W), np.int32)
    n = _components(mask, lab, np.empty(H * W, np.int64), eight)
    return lab, n


@njit(cache=True)
def back_points(depth, focal, cy, cx):
    """``np.stack([(u - cx) * depth / focal, (v - cy) * depth / focal, depth], -1)`` over the pixel grid
    (``v, u = np.mgrid[0:H, 0:W]``): the same operations in the same order, one pass."""
    H, W = depth.shape
    out = np.empty((H, W, 3))
    for v in range(H):
        for u in range(W):
            z = depth[v, u]
            out[v, u, 0] = (u - cx) * z / focal
            out[v, u, 1] = (v - cy) * z / focal
            out[v, u, 2] = z
    return out


@njit(cache=True)
def fronts_of_surfaces(lab, n, d, focal, min_pixels, min_area):
    """:func:`tracker.segment.surface_fronts` in one pass: each label's pixel count and area (the
    squared pixel size at its depth, summed in raster order as ``np.bincount`` sums), the kept labels'
    ``int(0.01 · count)``-th smallest depth, nearest first (a stable sort, as ``np.argsort(kind=
    "stable")``). Returns ``(ids, fronts)``."""
    H, W = lab.shape
    count = np.zeros(n + 1, np.int64)
    area = np.zeros(n + 1)
    for v in range(H):
        for u in range(W):
            k = lab[v, u]
            if k > 0:
                count[k] += 1
                q = d[v, u] / focal
                area[k] += q * q
    m = 0
    for k in range(1, n + 1):
        if count[k] >= max(min_pixels, 1) and area[k] >= min_area:
            m += 1
    ids = np.empty(m, np.int64)
    slot = np.full(n + 1, -1, np.int64)
    start = np.zeros(m + 1, np.int64)
    j = 0
    for k in range(1, n + 1):
        if count[k] >= max(min_pixels, 1) and area[k] >= min_area:
            ids[j] = k
            slot[k] = j
            start[j + 1] = start[j] + count[k]
            j += 1
    fronts = np.empty(m)
    if m == 0:
        return ids, fronts
    z = np.empty(start[m])
    fill = start[:m].copy()
    for v in range(H):
        for u in range(W):
            k = lab[v, u]
            if k > 0 and slot[k] >= 0:
                z[fill[slot[k]]] = d[v, u]
                fill[slot[k]] += 1
    for j in range(m):
        # the k-th smallest depth by selection (the value a sort puts there; sorting a body's thousands of
        # depths cost ~0.2 ms a frame)
        k = int(0.01 * count[ids[j]])
        fronts[j] = np.partition(z[start[j]:start[j + 1]], k)[k]
    o = np.argsort(fronts, kind="mergesort")
    return ids[o], fronts[o]


@njit(cache=True)
def _plane_weight(P, w, n, dn, tol, every):
    total = 0.0
    for i in range(0, P.shape[0], every):
        r = n[0] * P[i, 0] + n[1] * P[i, 1] + n[2] * P[i, 2] - dn
        if -tol <= r <= tol:
            total += w[i]
    return total * every


@njit(cache=True)
def _plane_weights4(P, w, N, D, ks, tol, every, out):
    """:func:`_plane_weight` of the planes ``N[ks[j]]``, ``D[ks[j]]`` (four) into ``out[j]``, in one pass over
    the points: four independent sums, each added in the points' order as :func:`_plane_weight` adds it
    (the same floats), whose additions the processor overlaps (one sum waits on each addition)."""
    a0, a1, a2, da = N[ks[0], 0], N[ks[0], 1], N[ks[0], 2], D[ks[0]]
    b0, b1, b2, db = N[ks[1], 0], N[ks[1], 1], N[ks[1], 2], D[ks[1]]
    c0, c1, c2, dc = N[ks[2], 0], N[ks[2], 1], N[ks[2], 2], D[ks[2]]
    e0, e1, e2, de = N[ks[3], 0], N[ks[3], 1], N[ks[3], 2], D[ks[3]]
    ta = tb = tc = te = 0.0
    for i in range(0, P.shape[0], every):
        x, y, z, wi = P[i, 0], P[i, 1], P[i, 2], w[i]
        r = a0 * x + a1 * y + a2 * z - da
        if -tol <= r <= tol:
            ta += wi
        r = b0 * x + b1 * y + b2 * z - db
        if -tol <= r <= tol:
            tb += wi
        r = c0 * x + c1 * y + c2 * z - dc
        if -tol <= r <= tol:
            tc += wi
        r = e0 * x + e1 * y + e2 * z - de
        if -tol <= r <= tol:
            te += wi
    out[0], out[1], out[2], out[3] = ta * every, tb * every, tc * every, te * every


@njit(cache=True)
def _weigh_planes(P, w, N, D, idx, m, tol, every, S):
    """``S[idx[j]]`` = :func:`_plane_weight` of plane ``idx[j]`` for ``j < m``, four planes a pass."""
    ks = np.empty(4, np.int64)
    got = np.empty(4)
    for j in range(0, m, 4):
        for q in range(4):
            ks[q] = idx[min(j + q, m - 1)]  # a short last block repeats its last plane
        _plane_weights4(P, w, N, D, ks, tol, every, got)
        for q in range(min(4, m - j)):
            S[ks[q]] = got[q]


@njit(cache=True)
def plane_ransac(P, w, tries, tol, every, keep, max_cos):
    """The plane ``n·x = dn`` (``n`` a unit normal) through three of the points ``P (N, 3)`` that
    collects the largest weight ``w`` of points within ``tol`` of it, among the triplets ``tries
    (K, 3)`` (indices into ``P``) whose plane is seen obliquely (``|n · the direction to the three
    points' centroid| ≤ max_cos``): each triplet's plane is weighed on every ``every``-th point, the
    best ``keep`` on all of them (preemptive RANSAC). Returns ``(n, dn, weight)``; weight 0 when
    no triplet qualifies (collinear within 1e-9 m², or facing the camera). The planes are weighed four
    at a time (:func:`_weigh_planes`): each weight is the sum one plane at a time gave."""
    K = tries.shape[0]
    N = np.zeros((K, 3))
    D = np.zeros(K)
    S = np.full(K, -1.0)
    ok = np.empty(K, np.int64)
    m = 0
    for k in range(K):
        a, b, c = P[tries[k, 0]], P[tries[k, 1]], P[tries[k, 2]]
        e1, e2 = b - a, c - a
        n = np.array([e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]])
        s = np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
        if s < 1e-9:
            continue
        n /= s
        mm = a + b + c
        if abs(n[0] * mm[0] + n[1] * mm[1] + n[2] * mm[2]) > max_cos * np.sqrt(
                mm[0] * mm[0] + mm[1] * mm[1] + mm[2] * mm[2]):
            continue
        N[k] = n
        D[k] = n[0] * a[0] + n[1] * a[1] + n[2] * a[2]
        ok[m] = k
        m += 1
    _weigh_planes(P, w, N, D, ok, m, tol, every, S)
    order = np.argsort(-S, kind="mergesort")
    best_n, best_d, best_w = np.zeros(3), 0.0, 0.0
    top = np.empty(min(keep, K), np.int64)
    t = 0
    for j in range(min(keep, K)):
        if S[order[j]] < 0.0:
            break
        top[t] = order[j]
        t += 1
    full = np.full(K, -1.0)
    _weigh_planes(P, w, N, D, top, t, tol, 1, full)
    for j in range(t):
        k = top[j]
        if full[k] > best_w:
            best_n, best_d, best_w = N[k].copy(), D[k], full[k]
    return best_n, best_d, best_w


@njit(cache=True)
def plane_pixels(d, nx, ny, nz, dn, focal, cy, cx, band):
    """Boolean ``(H, W)``: the pixels of the depth image ``d`` (NaN = none) whose back-projection
    (:func:`back_points` with ``focal``, ``cy``, ``cx``) lies within ``band`` of the plane
    ``n·x = dn``."""
    H, W = d.shape
    out = np.zeros((H, W), np.bool_)
    for v in range(H):
        gy = ny * (v - cy) / focal
        for u in range(W):
            z = d[v, u]
            if np.isfinite(z):
                r = (nx * (u - cx) / focal + gy + nz) * z - dn
                out[v, u] = -band <= r <= band
    return out


@njit(cache=True)
def plane_samples(d, step, focal, cy, cx, z_min, z_max):
    """The back-projections ``(N, 3)`` (:func:`back_points`) of every ``step``-th pixel each way of
    ``d`` with a depth in ``(z_min, z_max)``, and each one's fronto-parallel area ``(z · step /
    focal)²``."""
    H, W = d.shape
    n = 0
    P = np.empty((((H + step - 1) // step) * ((W + step - 1) // step), 3))
    w = np.empty(P.shape[0])
    for v in range(0, H, step):
        for u in range(0, W, step):
            z = d[v, u]
            if z > z_min and z < z_max:  # False for NaN
                P[n, 0] = (u - cx) * z / focal
                P[n, 1] = (v - cy) * z / focal
                P[n, 2] = z
                w[n] = (z * step / focal) ** 2
                n += 1
    return P[:n], w[:n]


@njit(cache=True)
def plane_refit(P, w, n, dn, tol):
    """The least-squares plane ``(n, dn)`` of the points of ``P`` within ``tol`` of the plane ``n·x =
    dn`` (their centroid, and the direction of their least spread), then the points within ``tol`` of
    it: ``(n, dn, their weight w summed, the median absolute deviation of their distances, their
    centroid)``."""
    c = np.zeros(3)
    m = 0
    for i in range(P.shape[0]):
        if abs(n[0] * P[i, 0] + n[1] * P[i, 1] + n[2] * P[i, 2] - dn) <= tol:
            for a in range(3):
                c[a] += P[i, a]
            m += 1
    if m < 3:
        return n, dn, 0.0, 0.0, c
    c /= m
    C = np.zeros((3, 3))
    for i in range(P.shape[0]):
        if abs(n[0] * P[i, 0] + n[1] * P[i, 1] + n[2] * P[i, 2] - dn) <= tol:
            for a in range(3):
                for b in range(3):
                    C[a, b] += (P[i, a] - c[a]) * (P[i, b] - c[b])
    n2 = np.linalg.eigh(C)[1][:, 0].copy()
    d2 = n2[0] * c[0] + n2[1] * c[1] + n2[2] * c[2]
    r = np.empty(P.shape[0])
    k = 0
    area = 0.0
    c2 = np.zeros(3)
    for i in range(P.shape[0]):
        x = n2[0] * P[i, 0] + n2[1] * P[i, 1] + n2[2] * P[i, 2] - d2
        if abs(x) <= tol:
            r[k] = x
            k += 1
            area += w[i]
            for a in range(3):
                c2[a] += P[i, a]
    if k == 0:
        return n2, d2, 0.0, 0.0, c2
    r = r[:k]
    return n2, d2, area, np.median(np.abs(r - np.median(r))), c2 / k


@njit(cache=True)
def disk_counts(raw, ys, xs, lo, hi):
    """How many set pixels of ``raw`` lie in the disk at each place ``(ys[i], xs[i])``: the disk's row ``r``
    (``r − k`` rows from the centre, ``k = (len(lo) − 1) // 2``) spans the columns ``lo[r]``..``hi[r]`` from
    the centre (``lo > hi``: none); pixels outside the image count as unset. By each row's running count, so a
    place costs one subtraction per disk row, not one look per disk pixel."""
    H, W = raw.shape
    run = np.zeros((H, W + 1), np.int64)
    for y in range(H):
        s = 0
        for x in range(W):
            if raw[y, x]:
                s += 1
            run[y, x + 1] = s
    k = (lo.shape[0] - 1) // 2
    out = np.zeros(ys.shape[0], np.int64)
    for i in range(ys.shape[0]):
        n = 0
        for r in range(lo.shape[0]):
            y = ys[i] + r - k
            if y < 0 or y >= H or lo[r] > hi[r]:
                continue
            a = min(max(xs[i] + lo[r], 0), W)
            b = min(max(xs[i] + hi[r] + 1, 0), W)
            if b > a:
                n += run[y, b] - run[y, a]
        out[i] = n
    return out


@njit(cache=True, inline="always")
def _skin_px(c, v, u, v0, v1, s0, s1):
    """:func:`skin_channels`'s test of pixel ``(v, u)``."""
    r, g, b = np.int32(c[v, u, 0]), np.int32(c[v, u, 1]), np.int32(c[v, u, 2])
    hi = max(r, max(g, b))
    spread = (hi - min(r, min(g, b))) * 255
    return v0 <= hi <= v1 and s0 * hi <= spread <= s1 * hi


@njit(cache=True)
def valid_pixels(d, c, use_c, z_min, z_max, v0, v1, s0, s1, least, use_plane, nx, ny, nz, dn, focal, cy, cx, band):
    """:meth:`tracker.segment.Segmenter._valid` without a box in one pass over the pixels (two with a colour
    frame or a plane): the depths within ``(z_min, z_max)`` (NaN out); with ``use_c``, only the skin-coloured
    ones of them (:func:`skin_channels` on ``c``) when at least ``least`` are; with ``use_plane``, none within
    ``band`` of the plane (:func:`plane_pixels`' test with its arithmetic)."""
    H, W = d.shape
    out = np.empty((H, W), np.bool_)
    n = 0
    for v in range(H):
        for u in range(W):
            z = d[v, u]
            ok = z > z_min and z < z_max  # False for NaN; the bounds are finite
            out[v, u] = ok
            if use_c and ok and _skin_px(c, v, u, v0, v1, s0, s1):
                n += 1
    skin = use_c and n >= least
    if skin or use_plane:
        for v in range(H):
            gy = ny * (v - cy) / focal
            for u in range(W):
                if not out[v, u]:
                    continue
                ok = True
                if skin:
                    ok = _skin_px(c, v, u, v0, v1, s0, s1)
                if ok and use_plane:
                    r = (nx * (u - cx) / focal + gy + nz) * d[v, u] - dn
                    ok = not (-band <= r <= band)
                out[v, u] = ok
    return out


@njit(cache=True)
def near_front(d, lo, hi, use_reach, focal, cy, cx, c0, c1, c2, reach2):
    """:func:`tracker.segment.hand_region`'s depth band and reach in one pass: the pixels of ``d`` with a
    finite depth within ``[lo, hi]`` and, with ``use_reach``, whose back-projection (:func:`back_points`'s
    arithmetic: ``focal``, principal point ``cy, cx``) lies within √``reach2`` of ``(c0, c1, c2)`` (the
    squared distance summed x, y, z in turn, as ``tracker.segment.ops._sq_dist``)."""
    H, W = d.shape
    out = np.empty((H, W), np.bool_)
    for v in range(H):
        for u in range(W):
            z = d[v, u]
            ok = np.isfinite(z) and z <= hi and z >= lo
            if ok and use_reach:
                a = (u - cx) * z / focal - c0
                b = (v - cy) * z / focal - c1
                c = z - c2
                ok = a * a + b * b + c * c <= reach2
            out[v, u] = ok
    return out


@njit(cache=True)
def fill_holes(m):
    """``scipy.ndimage.binary_fill_holes(m)`` (its cross): ``m`` with every background pixel that is not
    4-connected through background to the array's edge set."""
    H, W = m.shape
    reach = np.zeros((H, W), np.bool_)
    stack = np.empty(H * W, np.int64)
    top = 0
    for v in range(H):
        for u in range(W):
            if (v == 0 or u == 0 or v == H - 1 or u == W - 1) and not m[v, u] and not reach[v, u]:
                reach[v, u] = True
                stack[top] = v * W + u
                top += 1
    _flood(~m, reach, True, stack, top, False)
    return ~reach


@njit(cache=True)
def label_extents(lab, n):
    """``(rows, cols)`` (int64 ``(n,)``): the height and width of each label ``1..n``'s bounding box, as
    ``scipy.ndimage.find_objects(lab)``'s slices span them (``stop − start``; 0 for a label absent)."""
    H, W = lab.shape
    r0 = np.full(n, H, np.int64)
    r1 = np.full(n, -1, np.int64)
    c0 = np.full(n, W, np.int64)
    c1 = np.full(n, -1, np.int64)
    for v in range(H):
        for u in range(W):
            k = lab[v, u] - 1
            if 0 <= k < n:
                r0[k] = min(r0[k], v)
                r1[k] = max(r1[k], v)
                c0[k] = min(c0[k], u)
                c1[k] = max(c1[k], u)
    rows = np.zeros(n, np.int64)
    cols = np.zeros(n, np.int64)
    for k in range(n):
        if r1[k] >= 0:
            rows[k] = r1[k] - r0[k] + 1
            cols[k] = c1[k] - c0[k] + 1
    return rows, cols


@njit(cache=True)
def mask_sums(mask):
    """``(count, row sum, column sum)`` of a 2-D boolean mask's set pixels (integers: their means are
    ``np.nonzero(mask)[i].mean()`` exactly, the sums being exact in float64 too)."""
    H, W = mask.shape
    n = 0
    sr = 0
    sc = 0
    for v in range(H):
        for u in range(W):
            if mask[v, u]:
                n += 1
                sr += v
                sc += u
    return n, sr, sc


@njit(cache=True)
def touch_close(dist, iy, ix, da, dw, px, dz):
    """:func:`tracker.segment.layers._joins`' test: the pixels within ``px`` (``dist``) of the region whose
    depth ``da`` lies within ``dz`` of their nearest region pixel's (``dw[iy, ix]``; NaN: not)."""
    H, W = dist.shape
    out = np.zeros((H, W), np.bool_)
    for v in range(H):
        for u in range(W):
            if dist[v, u] <= px:
                out[v, u] = abs(da[v, u] - dw[iy[v, u], ix[v, u]]) <= dz
    return out


@njit(cache=True)
def touches_border(mask, px):
    """Whether ``mask`` has a pixel within ``px`` (> 0) rows or columns of its edge:
    ``mask[:px].any() or mask[-px:].any() or mask[:, :px].any() or mask[:, -px:].any()``."""
    H, W = mask.shape
    for v in range(H):
        edge_row = v < px or v >= H - px
        for u in range(W):
            if mask[v, u] and (edge_row or u < px or u >= W - px):
                return True
    return False


@njit(cache=True)
def arm_strip(solid, cy, cx, ay, ax, half):
    """:func:`tracker.segment.cut_forearm`'s coordinates along the arm ``(ay, ax)`` from the palm's centre
    ``(cy, cx)``, ``t = vy·ay + vx·ax`` (``vy``, ``vx``: each pixel's integer offsets), and its strip: the
    ``solid`` pixels with ``|−vy·ax + vx·ay| <= half`` — numpy's operations on the offsets, in its order."""
    H, W = solid.shape
    t = np.empty((H, W))
    strip = np.empty((H, W), np.bool_)
    for v in range(H):
        vy = v - cy
        for u in range(W):
            vx = u - cx
            t[v, u] = vy * ay + vx * ax
            strip[v, u] = solid[v, u] and abs(-vy * ax + vx * ay) <= half
    return t, strip


@njit(cache=True)
def valid_depths(d, c, use_c, z_min, z_max, v0, v1, s0, s1, least, use_plane, nx, ny, nz, dn, focal, cy, cx, band):
    """``(valid, dv, d_all)``: :func:`valid_pixels`, the depths there (NaN elsewhere: ``np.where(valid, d,
    nan)``) and the depths within ``(z_min, z_max)`` (the working volume's, before the skin test and the
    plane)."""
    valid = valid_pixels(d, c, use_c, z_min, z_max, v0, v1, s0, s1, least, use_plane, nx, ny, nz, dn, focal, cy,
                         cx, band)
    H, W = d.shape
    dv = np.empty((H, W))
    d_all = np.empty((H, W))
    for v in range(H):
        for u in range(W):
            z = d[v, u]
            dv[v, u] = z if valid[v, u] else np.nan
            d_all[v, u] = z if (z > z_min and z < z_max) else np.nan
    return valid, dv, d_all


@njit(cache=True)
def np_sum(a):
    """``np.sum(a)`` of a 1-D float64 array, to the bit: the reduction's identity 0.0 plus numpy's pairwise
    sum of the values (:func:`_pairwise`; the identity turns a sum of −0.0 into 0.0)."""
    return 0.0 + _pairwise(a)


@njit(cache=True)
def _pairwise(a):
    """numpy's pairwise summation of a 1-D float64 array: fewer than 8 values one after the other from
    −0.0; up to 128 in eight running sums, combined pairwise, the rest added in order; more split in two
    halves of a multiple of 8."""
    n = a.shape[0]
    if n < 8:
        res = -0.0
        for i in range(n):
            res += a[i]
        return res
    if n <= 128:
        r0, r1, r2, r3 = a[0], a[1], a[2], a[3]
        r4, r5, r6, r7 = a[4], a[5], a[6], a[7]
        i = 8
        while i < n - (n % 8):
            r0 += a[i]
            r1 += a[i + 1]
            r2 += a[i + 2]
            r3 += a[i + 3]
            r4 += a[i + 4]
            r5 += a[i + 5]
            r6 += a[i + 6]
            r7 += a[i + 7]
            i += 8
        res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
        while i < n:
            res += a[i]
            i += 1
        return res
    n2 = n // 2
    n2 -= n2 % 8
    return _pairwise(a[:n2]) + _pairwise(a[n2:])


@njit(cache=True)
def uniform1d(x, size):
    """``tracker.segment.ops._uniform1d(x, size)`` (``scipy.ndimage.uniform_filter1d(x, size,
    mode="nearest")``): the first window summed in order, then each step adding its entering minus its
    leaving value, each running sum divided by ``size``."""
    n = x.shape[0]
    before = size // 2
    ext = np.empty(n + size - 1)
    for i in range(before):
        ext[i] = x[0]
    for i in range(n):
        ext[before + i] = x[i]
    for i in range(before + n, n + size - 1):
        ext[i] = x[n - 1]
    out = np.empty(n)
    s = ext[0]
    for i in range(1, size):
        s += ext[i]
    out[0] = s / size
    for i in range(1, n):
        s += ext[i + size - 1] - ext[i - 1]
        out[i] = s / size
    return out


@njit(cache=True)
def _opposite(py, px, width, cy_p, cx_p, fingers, r):
    """``tracker.segment.forearm._opposite_fingers``: whether ``(py, px)`` lies opposite the parts
    ``fingers`` weighted by their width (numpy's sums, :func:`np_sum`)."""
    k = 0
    for j in range(fingers.shape[0]):
        if fingers[j]:
            k += 1
    w, wy, wx = np.empty(k), np.empty(k), np.empty(k)
    k = 0
    for j in range(fingers.shape[0]):
        if fingers[j]:
            w[k] = width[j]
            wy[k] = width[j] * cy_p[j]
            wx[k] = width[j] * cx_p[j]
            k += 1
    if np_sum(w) < 0.3 * r:
        return False
    fy, fx = np_sum(wy), np_sum(wx)
    return (py * fy + px * fx) / (math.hypot(py, px) * math.hypot(fy, fx) + 1e-12) < -0.5


@njit(cache=True)
def _widest(owner, piece_size, j, r):
    """``tracker.segment.forearm._widest_piece``: part ``j``'s widest ring piece of at least 0.05 r², or −1
    when it has fewer than two."""
    best, count = -1, 0
    for k in range(piece_size.shape[0]):
        if owner[k] == j + 1 and piece_size[k] >= 0.05 * r * r:
            count += 1
            if best < 0 or piece_size[k] > piece_size[best]:
                best = k
    return best if count >= 2 else -1


@njit(cache=True)
def _end_narrowing(p, window, drop):
    """``tracker.segment.forearm._end_of_narrowing``."""
    for i in range(p.shape[0] - window):
        if p[i] - p[i + window] < drop * p[i]:
            return i
    return p.shape[0] - 1


@njit(cache=True)
def _end_taper(p, window, drop):
    """``tracker.segment.forearm._end_of_taper``."""
    n = p.shape[0]
    for i in range(n - 1):
        lo = p[i]
        for k in range(i, min(i + window + 1, n)):
            if p[k] < lo:
                lo = p[k]
        if p[i] - lo < drop * p[i]:
            return i
    return n - 1


@njit(cache=True)
def _profile(t, strip, lo, hi):
    """The strip's pixels per rounded distance ``lo``..``hi`` along the arm (``np.bincount`` of
    ``np.round(t[strip])`` within them) and whether any lies there."""
    prof = np.zeros(hi - lo + 1)
    anyk = False
    H, W = t.shape
    for v in range(H):
        for u in range(W):
            if strip[v, u]:
                ti = int(np.rint(t[v, u]))
                if lo <= ti <= hi:
                    prof[ti - lo] += 1.0
                    anyk = True
    return prof, anyk


@njit(cache=True)
def wrist_cut(solid, cy, cx, r, go_on, touch, use_touch, m_px, at_end, w0, w1, arm_reach, opp_reach, sure_reach,
              finger_max, cos_bend, taper_r, taper_min, no_narrow, heel_reach, heel_tol):
    """``(cut, strip)`` of :func:`tracker.segment.forearm.cut_forearm` from its palm on (its ``_parts``,
    ``_going_on_parts``, ``_arm_axis``, the arm's coordinates and ``_wrist_distance`` or ``_heel_end``, in
    their arithmetic): whether a cut is made, and the crop's pixels it removes. ``solid``: the crop's
    closed, filled mask; ``(cy, cx)``, ``r``: the palm circle; ``go_on``, ``touch`` (``use_touch``): where
    the region goes on and where another object meets it; ``m_px``: metres per pixel at the palm;
    ``at_end``: the palm is at the region's far end (the heel's end is the wrist); ``w0``, ``w1``: the
    wrist's range (r); the rest: :class:`tracker.segment.constants.SegmentConstants`' (``cos_bend``: the
    cosine of its ``arm_bend_deg``)."""
    H, W = solid.shape
    none = np.zeros((H, W), np.bool_)
    rho = np.empty((H, W))
    outside = np.empty((H, W), np.bool_)
    for v in range(H):
        for u in range(W):
            rho[v, u] = math.hypot(float(v - cy), float(u - cx))
            outside[v, u] = solid[v, u] and rho[v, u] > 1.6 * r
    # _parts: the parts outside 1.6 r (8-connected), their width where they leave the palm, reach,
    # mean offsets there; the pieces on the ring 2.0-2.4 r
    lab = np.zeros((H, W), np.int32)
    stack = np.empty(H * W, np.int64)
    n = _components(outside, lab, stack, True)
    if n == 0:
        return False, none
    ring_in = np.zeros((H, W), np.bool_)
    for v in range(H):
        for u in range(W):
            ring_in[v, u] = outside[v, u] and rho[v, u] >= 2.0 * r and rho[v, u] <= 2.4 * r
    ring_lab = np.zeros((H, W), np.int32)
    nr = _components(ring_in, ring_lab, stack, True)
    cnt = np.zeros(n, np.int64)
    sy, sx = np.zeros(n), np.zeros(n)
    reach_r = np.full(n, -np.inf)
    piece_size = np.zeros(nr + 1 if nr > 0 else 0, np.int64)
    owner = np.zeros(piece_size.shape[0], np.int64)
    for v in range(H):
        for u in range(W):
            k = lab[v, u]
            if k == 0:
                continue
            if rho[v, u] > reach_r[k - 1]:
                reach_r[k - 1] = rho[v, u]
            if rho[v, u] <= 1.9 * r:
                cnt[k - 1] += 1
                sy[k - 1] += v - cy
                sx[k - 1] += u - cx
            q = ring_lab[v, u]
            if q > 0:
                piece_size[q] += 1
                owner[q] = k
    width, cy_p, cx_p = np.empty(n), np.empty(n), np.empty(n)
    for j in range(n):
        width[j] = cnt[j] / (0.3 * r) / 2.0
        nb = max(cnt[j], 1)
        cy_p[j] = sy[j] / nb
        cx_p[j] = sx[j] / nb
    pieces = np.zeros(n, np.int64)
    for q in range(1, piece_size.shape[0]):
        if piece_size[q] >= 0.05 * r * r:
            pieces[owner[q] - 1] += 1
    # _going_on_parts
    cont = np.zeros(n, np.bool_)
    for v in range(H):
        for u in range(W):
            k = lab[v, u]
            if k > 0 and (go_on[v, u] or (use_touch and touch[v, u])):
                cont[k - 1] = True
    for j in range(n):
        cont[j] |= reach_r[j] > arm_reach * r
    several = pieces >= 2
    first = several & cont
    for j in range(n):
        if not first[j]:
            continue
        touched = False
        k = _widest(owner, piece_size, j, r)
        # the ring is 0.4 r thick: a piece's area over that is its chord across the ring
        if k >= 0 and not piece_size[k] / (0.4 * r) * m_px <= finger_max:
            s_y, s_x, c = 0, 0, 0
            for v in range(H):
                for u in range(W):
                    if ring_lab[v, u] == k:
                        s_y += v - cy
                        s_x += u - cx
                        c += 1
            touched = _opposite(float(s_y) / c, float(s_x) / c, width, cy_p, cx_p, ~cont & ~several, r)
        several[j] = not touched
    cont &= ~several
    ends = ~cont
    wide = width >= 0.45 * r
    for j in range(n):
        if not (ends[j] and wide[j] and reach_r[j] >= opp_reach * r):
            continue
        others = ends.copy()
        others[j] = False
        others &= ~(wide & (reach_r < opp_reach * r))
        cont[j] |= _opposite(cy_p[j], cx_p[j], width, cy_p, cx_p, others, r)
    for j in range(n):
        cont[j] &= not several[j] or reach_r[j] > sure_reach * r
    # the arm: the widest part that goes on
    j = 0
    best = -1.0
    for i in range(n):
        w = width[i] if cont[i] else 0.0
        if w > best:
            best, j = w, i
    if best < 0.45 * r:
        return False, none
    # _arm_axis
    piece = _widest(owner, piece_size, j, r) if pieces[j] >= 2 else -1
    near_piece = none
    if piece >= 0:
        near_piece = np.zeros((H, W), np.bool_)
        for v in range(H):
            for u in range(W):
                if ring_lab[v, u] == piece:
                    for dv in range(-2, 3):
                        for du in range(abs(dv) - 2, 3 - abs(dv)):
                            if 0 <= v + dv < H and 0 <= u + du < W:
                                near_piece[v + dv, u + du] = True
    ry, rx, rc = 0, 0, 0
    ay_, ax_, ac = 0, 0, 0
    top = -np.inf
    for v in range(H):
        for u in range(W):
            if lab[v, u] != j + 1:
                continue
            ay_ += v - cy
            ax_ += u - cx
            ac += 1
            if rho[v, u] > top:
                top = rho[v, u]
            if rho[v, u] < 2.6 * r and (piece < 0 or near_piece[v, u]):
                ry += v - cy
                rx += u - cx
                rc += 1
    whole = rc == 0  # no pixel of the arm near the palm: the whole arm stands for its ring
    if whole:
        ry, rx, rc = ay_, ax_, ac
    ay, ax = float(ry) / rc, float(rx) / rc
    norm = math.hypot(ay, ax)
    if norm == 0:
        return False, none
    ay, ax = ay / norm, ax / norm
    ly, lx, lc, fy, fx, fc = 0, 0, 0, 0, 0, 0
    for v in range(H):
        for u in range(W):
            if lab[v, u] != j + 1:
                continue
            if pieces[j] >= 2:
                leave = (whole or (rho[v, u] < 2.6 * r and near_piece[v, u])) and rho[v, u] <= 2.4 * r
            else:
                leave = rho[v, u] <= 1.9 * r
            if leave:
                ly += v - cy
                lx += u - cx
                lc += 1
            if rho[v, u] >= top - 0.5 * r:
                fy += v - cy
                fx += u - cx
                fc += 1
    if lc > 0 and fc > 0:
        dy, dx = float(fy) / fc - float(ly) / lc, float(fx) / fc - float(lx) / lc
        n_arm = math.hypot(dy, dx)
        cos = (dy * ay + dx * ax) / max(n_arm, 1e-12)
        if n_arm >= 0.5 * r and 0.5 <= cos < cos_bend:
            ay, ax = dy / n_arm, dx / n_arm
    t, strip = arm_strip(solid, cy, cx, ay, ax, 2.5 * r)
    if at_end:
        # _heel_end
        t0 = np.inf
        for v in range(H):
            for u in range(W):
                if strip[v, u] and t[v, u] < t0:
                    t0 = t[v, u]
        lo, hi = int(np.floor(0.9 * r)), int(np.ceil(t0 + heel_reach * r))
        if hi <= lo:
            return False, none
        prof, anyk = _profile(t, strip, lo, hi)
        if not anyk:
            return False, none
        prof = uniform1d(prof, 5)
        i = int(np.argmin(prof))
        t_w = lo + prof.shape[0] - 1
        for k in range(i, prof.shape[0]):
            if prof[k] > (1.0 + heel_tol) * prof[i]:
                t_w = lo + k - 1
                break
    else:
        # _wrist_distance
        lo, hi = int(np.floor(w0 * r)), int(np.ceil(w1 * r))
        prof, anyk = _profile(t, strip, lo, hi)
        if not anyk:
            return False, none
        prof = uniform1d(prof, 5)
        i = _end_narrowing(prof, max(int(np.rint(0.3 * r)), 2), 0.10)
        if i > 0:
            t_w = lo + i
        else:
            taper = _end_taper(prof, max(int(np.rint(taper_r * r)), taper_min), 0.10)
            t_w = max(lo + taper, int(np.rint(no_narrow * r)))
    cut = np.empty((H, W), np.bool_)
    for v in range(H):
        for u in range(W):
            cut[v, u] = strip[v, u] and t[v, u] > t_w
    return True, cut


@njit(cache=True)
def filled_places(cand, raw, rad, slack, least):
    """``tracker.segment.forearm._filled_places(cand, raw, rad, slack, least)``: the places of ``cand`` whose
    disk of radius ``rad`` (offsets ``hypot ≤ rad``) ``raw`` fills within ``slack`` of the best-filled one or
    at least ``least`` (a share of the disk's pixels: :func:`disk_counts` over their count) — ``cand`` itself
    when it holds fewer than two places."""
    H, W = cand.shape
    n = 0
    for v in range(H):
        for u in range(W):
            if cand[v, u]:
                n += 1
    if n < 2:
        return cand.copy()
    ys, xs = np.empty(n, np.int64), np.empty(n, np.int64)
    n = 0
    for v in range(H):
        for u in range(W):
            if cand[v, u]:
                ys[n], xs[n] = v, u
                n += 1
    k = int(np.ceil(rad))
    lo, hi = np.empty(2 * k + 1, np.int64), np.empty(2 * k + 1, np.int64)
    size = 0
    for i in range(2 * k + 1):
        lo[i], hi[i] = k + 1, -k - 1
        for j in range(2 * k + 1):
            if math.hypot(float(i - k), float(j - k)) <= rad:
                size += 1
                lo[i] = min(lo[i], j - k)
                hi[i] = max(hi[i], j - k)
    counts = disk_counts(raw, ys, xs, lo, hi)
    fill = np.empty(n)
    for i in range(n):
        fill[i] = counts[i] / size
    bar = min(fill.max() - slack, least)
    out = np.zeros((H, W), np.bool_)
    for i in range(n):
        if fill[i] >= bar:
            out[ys[i], xs[i]] = True
    return out


@njit(cache=True)
def finger_pieces(thin, min_size, elong2, min_len, oy, ox):
    """``(labels, sizes, big)`` of :func:`tracker.segment.fingers._finger_pieces` from its ``thin`` pixels
    (4-connected pieces as ``scipy.ndimage.label`` numbers them, each one's pixels, and which are
    finger-like: at least ``min_size`` pixels, the second moments' major axis at least ``elong2`` times
    the minor, ``4·sqrt(major)`` at least ``min_len``), in numpy's arithmetic (the moments summed over
    the pixels in raster order, as ``np.bincount`` sums its weights); ``(oy, ox)``: the coordinates of
    ``thin``'s first pixel in the image the moments are taken in (a crop's moments are then its image's,
    to the bit: the means are rounded where they lie)."""
    H, W = thin.shape
    lab = np.zeros((H, W), np.int32)
    n = _components(thin, lab, np.empty(H * W, np.int64), False)
    size = np.zeros(n + 1, np.int64)
    sy, sx = np.zeros(n + 1), np.zeros(n + 1)
    for v in range(H):
        for u in range(W):
            k = lab[v, u]
            size[k] += 1
            if k > 0:
                sy[k] += v + oy
                sx[k] += u + ox
    cnt = np.empty(n + 1)
    for k in range(n + 1):
        cnt[k] = max(size[k], 1)
    my, mx = sy / cnt, sx / cnt
    syy, sxx, sxy = np.zeros(n + 1), np.zeros(n + 1), np.zeros(n + 1)
    for v in range(H):
        for u in range(W):
            k = lab[v, u]
            if k > 0:
                ey, ex = (v + oy) - my[k], (u + ox) - mx[k]
                syy[k] += ey * ey
                sxx[k] += ex * ex
                sxy[k] += ey * ex
    big = np.zeros(n + 1, np.bool_)
    for k in range(1, n + 1):
        yy, xx, xy = syy[k] / cnt[k], sxx[k] / cnt[k], sxy[k] / cnt[k]
        q = (yy - xx) / 2
        half_gap = math.sqrt(q * q + xy * xy)
        major = (yy + xx) / 2 + half_gap
        minor = max((yy + xx) / 2 - half_gap, 1e-9)
        big[k] = size[k] >= min_size and major >= elong2 * minor and 4.0 * math.sqrt(major) >= min_len
    return lab, size, big


@njit(cache=True)
def blob_labels(lab, d, zone, near, core, k, n, focal, blob_area):
    """:func:`tracker.segment.hand_region`'s fingertip blobs in its window (labels ``lab`` up to ``n``):
    the labels (ascending) of the pixels in ``zone`` and ``near`` off ``core`` and off surface ``k`` whose
    ``near`` pixels cover less than ``blob_area`` m² — each pixel's area ``(d / focal)²`` summed in raster
    order, as ``np.bincount`` with :func:`tracker.segment.surfaces.pixel_area`'s weights."""
    H, W = lab.shape
    area = np.zeros(n + 1)
    cand = np.zeros(n + 1, np.bool_)
    for v in range(H):
        for u in range(W):
            if near[v, u]:
                q = d[v, u] / focal
                area[lab[v, u]] += q * q
                if zone[v, u] and not core[v, u] and lab[v, u] > 0 and lab[v, u] != k:
                    cand[lab[v, u]] = True
    m = 0
    for j in range(1, n + 1):
        if cand[j] and area[j] < blob_area:
            m += 1
    out = np.empty(m, np.int64)
    m = 0
    for j in range(1, n + 1):
        if cand[j] and area[j] < blob_area:
            out[m] = j
            m += 1
    return out


@njit(cache=True)
def edge_hits(lab, d, small, others, jump, gap):
    """Which labels (a table up to ``lab``'s largest) :func:`tracker.segment.region._edge_pieces` finds: those
    of ``small`` (a table of labels) with a pixel within the depths of ``others``' pixels (a table) in the
    ``2·gap + 1`` square around it, widened by ``jump`` — its nearest such depth minus ``jump`` to its
    farthest plus ``jump``, as the minimum and maximum filters gave them."""
    H, W = lab.shape
    hit = np.zeros(small.shape[0], np.bool_)
    for v in range(H):
        for u in range(W):
            k = lab[v, u]
            if not small[k] or hit[k]:
                continue
            lo, hi = np.inf, -np.inf
            for vv in range(max(v - gap, 0), min(v + gap + 1, H)):
                for uu in range(max(u - gap, 0), min(u + gap + 1, W)):
                    kk = lab[vv, uu]
                    if kk < others.shape[0] and others[kk]:
                        x = d[vv, uu]
                        if x < lo:
                            lo = x
                        if x > hi:
                            hi = x
            if d[v, u] >= lo - jump and d[v, u] <= hi + jump:
                hit[k] = True
    return hit


@njit(cache=True)
def percentile_linear(values, q):
    """``np.percentile(values, 100 · q)`` of a 1-D float64 array (its default, linear method): the values
    at ``floor((n − 1)·q)`` and the next in sorted order, interpolated by numpy's ``_lerp`` (from the lower
    one below a weight of 0.5, from the upper one from 0.5 on); the largest value at or past the end; NaN
    when a value is NaN."""
    n = values.shape[0]
    if n == 0:
        raise IndexError("the percentile of no values")
    for i in range(n):
        if np.isnan(values[i]):
            return np.nan
    s = np.sort(values)
    virtual = (n - 1) * q
    if virtual >= n - 1:
        lo, hi = -1, -1
    elif virtual < 0:
        lo, hi = 0, 0
    else:
        lo = int(math.floor(virtual))
        hi = lo + 1
    t = virtual - lo
    a, b = s[lo], s[hi]
    diff = b - a
    if t >= 0.5:
        return b - diff * (1 - t)
    return a + diff * t


@njit(cache=True)
def far_end_seed(surface, dist, y0, x0, d, X, focal, reach2):
    """``(seed, front)`` of :func:`tracker.segment.fingers._far_end` from its distances ``dist`` of the
    surface's bounding box (first pixel ``(y0, x0)``) to its pixels at the image border: the largest
    4-connected piece of the surface within 2 cm (at its median depth) of its farthest pixel, and the 1st
    percentile (:func:`percentile_linear`) of the depths of the surface within ``sqrt(reach2)`` of that
    piece's mean point (``X``: the back-projected points), in numpy's arithmetic."""
    H, W = surface.shape
    h, w = dist.shape
    top = -1.0
    n = 0
    for v in range(h):
        for u in range(w):
            if surface[y0 + v, x0 + u]:
                n += 1
                if dist[v, u] > top:
                    top = dist[v, u]
    z = np.empty(n)
    n = 0
    for v in range(H):
        for u in range(W):
            if surface[v, u]:
                z[n] = d[v, u]
                n += 1
    bar = top - 0.02 * focal / nan_median(z)
    cand = np.zeros((h, w), np.bool_)
    for v in range(h):
        for u in range(w):
            cand[v, u] = surface[y0 + v, x0 + u] and dist[v, u] >= bar
    piece = largest_component(cand)
    seed = np.zeros((H, W), np.bool_)
    c0, c1, c2 = 0.0, 0.0, 0.0
    m = 0
    for v in range(h):
        for u in range(w):
            if piece[v, u]:
                seed[y0 + v, x0 + u] = True
                c0 += X[y0 + v, x0 + u, 0]
                c1 += X[y0 + v, x0 + u, 1]
                c2 += X[y0 + v, x0 + u, 2]
                m += 1
    c0, c1, c2 = c0 / m, c1 / m, c2 / m
    near = np.empty(n)
    k = 0
    for v in range(H):
        for u in range(W):
            if surface[v, u]:
                e0, e1, e2 = X[v, u, 0] - c0, X[v, u, 1] - c1, X[v, u, 2] - c2
                if e0 * e0 + e1 * e1 + e2 * e2 <= reach2:
                    near[k] = d[v, u]
                    k += 1
    return seed, percentile_linear(near[:k], 0.01)


@njit(cache=True)
def _first_max(mask, values):
    """``np.unravel_index(np.argmax(np.where(mask, values, -1.0)), shape)``: the first place in raster order
    of the largest ``values`` in ``mask`` (values ≥ 0), ``(0, 0)`` when the mask is empty."""
    H, W = mask.shape
    best, by, bx = -1.0, 0, 0
    for v in range(H):
        for u in range(W):
            x = values[v, u] if mask[v, u] else -1.0
            if x > best:
                best, by, bx = x, v, u
    return by, bx


@njit(cache=True)
def palm_place(cand, far, dt, sub, solid, reach, width_share, palm_share, slack, least):
    """``(cy, cx, at_end)`` of :func:`tracker.segment.forearm._palm_centre` where the region goes on: the
    candidate place farthest from there (``far``: the distance), or the palm at the region's far end
    (:func:`tracker.segment.forearm._hand_end_palm`, in its arithmetic; ``reach``, ``width_share``,
    ``palm_share``, ``slack``, ``least``: its constants, the last three :func:`filled_places`')."""
    cy, cx = _first_max(cand, far)
    ey, ex = _first_max(solid, far)
    if math.hypot(float(cy - ey), float(cx - ex)) <= reach * dt[cy, cx]:
        return cy, cx, False
    H, W = dt.shape
    near = np.zeros((H, W), np.bool_)
    top, widest, any_near = -np.inf, -np.inf, False
    for v in range(H):
        for u in range(W):
            if dt[v, u] > widest:
                widest = dt[v, u]
            if solid[v, u] and math.hypot(float(v - ey), float(u - ex)) <= reach * dt[v, u]:
                near[v, u] = True
                any_near = True
                if dt[v, u] > top:
                    top = dt[v, u]
    if not any_near:
        top = 0.0
    if top < width_share * widest:
        return cy, cx, False
    for v in range(H):
        for u in range(W):
            near[v, u] = near[v, u] and dt[v, u] >= palm_share * top
    ny, nx = _first_max(filled_places(near, sub, top, slack, least), far)
    return ny, nx, True


@njit(cache=True)
def front_layer(d, back, region, by0, by1, bx0, bx1, wy0, wy1, wx0, wx1, half, step_m, jump, focal, min_area, share,
                behind_area):
    """:func:`tracker.segment.layers._in_front`'s test, in its arithmetic: ``(status, layer, ring, step)``.
    The local background is the grey closing of the depths of ``back`` (the farthest within ``half`` px,
    then the nearest of those) over the box ``by0:by1, bx0:bx1``; in the region's box ``wy0:wy1,
    wx0:wx1`` the region's pixels nearer than it by more than ``step_m`` fall into surfaces
    (:func:`surface_labels`), the largest by area (``(d / focal)²`` summed in raster order) is the layer —
    and then its outline (``ring``: within 3 px of it, with depth) and where the region there lies behind
    it by more than ``step_m`` (``step``). ``status``: 0 when no layer covers ``min_area``, 1 when the
    layer does not stand out over ``share`` of its outline, 2 when it does but less than ``behind_area``
    of the region lies outside it (both: nothing changes), 3 when the layer is taken. Masks of the
    region's box; empty unless a layer was found."""
    bh, bw = by1 - by0, bx1 - bx0
    a = np.empty((bh, bw))
    for v in range(bh):
        for u in range(bw):
            a[v, u] = d[by0 + v, bx0 + u] if back[v, u] else -np.inf
    far = window_extreme(a, half, 1.0)
    for v in range(bh):
        for u in range(bw):
            if not np.isfinite(far[v, u]):
                far[v, u] = np.inf
    far = window_extreme(far, half, -1.0)
    h, w = wy1 - wy0, wx1 - wx0
    fz = np.full((h, w), np.nan)
    anyf = False
    for v in range(h):
        for u in range(w):
            z = d[wy0 + v, wx0 + u]
            if region[wy0 + v, wx0 + u] and z < far[wy0 - by0 + v, wx0 - bx0 + u] - step_m:
                fz[v, u] = z
                anyf = True
    layer = np.zeros((h, w), np.bool_)
    ring = np.zeros((h, w), np.bool_)
    step = np.zeros((h, w), np.bool_)
    if not anyf:
        return 0, layer, ring, step
    lab, n = surface_labels(fz, jump)
    if n == 0:
        return 0, layer, ring, step
    area = np.zeros(n + 1)
    for v in range(h):
        for u in range(w):
            k = lab[v, u]
            if k > 0:
                q = d[wy0 + v, wx0 + u] / focal
                area[k] += q * q
    area[0] = 0.0
    best = 0
    for k in range(1, n + 1):
        if area[k] > area[best]:
            best = k
    if area[best] < min_area:
        return 0, layer, ring, step
    lw = np.empty((h, w))
    for v in range(h):
        for u in range(w):
            layer[v, u] = lab[v, u] == best
            lw[v, u] = d[wy0 + v, wx0 + u] if layer[v, u] else -np.inf
    layer_far = window_extreme(lw, 3, 1.0)
    n_ring, n_step, n_rest = 0, 0, 0
    for v in range(h):
        for u in range(w):
            z = d[wy0 + v, wx0 + u]
            ring[v, u] = np.isfinite(layer_far[v, u]) and not layer[v, u] and np.isfinite(z)
            step[v, u] = region[wy0 + v, wx0 + u] and ring[v, u] and z - layer_far[v, u] > step_m
            n_ring += ring[v, u]
            n_step += step[v, u]
            n_rest += region[wy0 + v, wx0 + u] and not layer[v, u]
    if not n_step >= share * n_ring:
        return 1, layer, ring, step
    rest = np.empty(n_rest)
    k = 0
    for v in range(h):
        for u in range(w):
            if region[wy0 + v, wx0 + u] and not layer[v, u]:
                q = d[wy0 + v, wx0 + u] / focal
                rest[k] = q * q
                k += 1
    if np_sum(rest) < behind_area:
        return 2, layer, ring, step
    return 3, layer, ring, step


@njit(cache=True)
def reach_part(surface, y0, y1, x0, x1, cy, cx, r):
    """:func:`tracker.segment.fingers._has_fingers`' part: the pixels of ``surface`` in the window ``y0:y1,
    x0:x1`` with ``(v − cy)² + (u − cx)² <= r²`` (numpy's arithmetic), as a mask of the window, and its
    bounding box in the window's pixels ``(ya, yb, xa, xb)``, inclusive (``ya < 0``: empty)."""
    h, w = y1 - y0, x1 - x0
    part = np.zeros((h, w), np.bool_)
    ya, yb, xa, xb = -1, -1, w, -1
    rr = r * r
    for v in range(h):
        dy = (v + y0) - cy
        for u in range(w):
            if surface[y0 + v, x0 + u]:
                dx = (u + x0) - cx
                if dy * dy + dx * dx <= rr:
                    part[v, u] = True
                    if ya < 0:
                        ya = v
                    yb = v
                    xa = min(xa, u)
                    xb = max(xb, u)
    return part, ya, yb, xa, xb


@njit(cache=True)
def join_surfaces(da, surface, close, jump, focal, min_area):
    """:func:`tracker.segment.layers._joins` after its contact test, in its arithmetic: the pixels of ``close``
    on a surface (:func:`surface_labels` of ``da`` off ``surface``, no data left out) covering at least
    ``min_area`` (``(depth / focal)²`` summed in raster order, as ``np.bincount`` sums)."""
    H, W = da.shape
    other = np.empty((H, W))
    for v in range(H):
        for u in range(W):
            z = da[v, u]
            other[v, u] = z if np.isfinite(z) and not surface[v, u] else np.nan
    lab, n = surface_labels(other, jump)
    out = np.zeros((H, W), np.bool_)
    if n == 0:
        return out
    area = np.zeros(n + 1)
    for v in range(H):
        for u in range(W):
            k = lab[v, u]
            if k > 0:
                q = other[v, u] / focal
                area[k] += q * q
    for v in range(H):
        for u in range(W):
            k = lab[v, u]
            out[v, u] = close[v, u] and k > 0 and area[k] >= min_area
    return out
