"""Numba kernels of the silhouette (:class:`tracker.correspond.Silhouette`): its distance transform
(:func:`feature_transform`, also the segmentation's and the wrist cue's) and the model→data
silhouette pairs (pose the model samples, keep the front-facing ones, project them, look up the
distance transform and fetch the nearest silhouette pixel's 3-D point)."""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from ._correspond_kernels import MIN_DEPTH_M
from ._segment_kernels import nearest_rows


@njit(cache=True)
def silhouette_pairs_kernel(G, samples, sil, tol, out_nodes, out_local, out_tgt):
    """One pass over the ``samples`` (:class:`~tracker._kernel_arrays.SampleArrays`: ``nodes (P,)``,
    ``local``/``local_n (P,3)`` in the node frames ``G (N,4,4)``). Each sample facing the camera
    (P·N < 0, z > :data:`MIN_DEPTH_M`) whose pixel (rounded half to even) lies more than ``tol`` px
    from the silhouette ``sil`` (:class:`~tracker._kernel_arrays.SilhouetteArrays`) — ``dist`` at the
    pixel clipped into the window starting at ``(v0, u0)`` plus the length of the clipping — and whose nearest silhouette
    pixel has finite depth is written, in sample order, to ``out_nodes``/``out_local``/``out_tgt``
    (the target is that pixel back-projected at the sample's depth, or the pixel's own depth when
    that is farther). Returns the number written."""
    nodes, local, local_n = samples.nodes, samples.local, samples.local_n
    fx, fy, cx, cy, dist, iv, iu, depth, v0, u0 = sil
    h, w = dist.shape
    n = 0
    for p in range(nodes.shape[0]):
        g = G[nodes[p]]
        l0, l1, l2 = local[p, 0], local[p, 1], local[p, 2]
        m0, m1, m2 = local_n[p, 0], local_n[p, 1], local_n[p, 2]
        px = g[0, 0] * l0 + g[0, 1] * l1 + g[0, 2] * l2 + g[0, 3]
        py = g[1, 0] * l0 + g[1, 1] * l1 + g[1, 2] * l2 + g[1, 3]
        pz = g[2, 0] * l0 + g[2, 1] * l1 + g[2, 2] * l2 + g[2, 3]
        nx = g[0, 0] * m0 + g[0, 1] * m1 + g[0, 2] * m2
        ny = g[1, 0] * m0 + g[1, 1] * m1 + g[1, 2] * m2
        nz = g[2, 0] * m0 + g[2, 1] * m1 + g[2, 2] * m2
        if not (px * nx + py * ny + pz * nz < 0.0 and pz > MIN_DEPTH_M):
            continue
        u = np.int64(np.rint(fx * px / pz + cx)) - u0
        v = np.int64(np.rint(fy * py / pz + cy)) - v0
        uu = min(max(u, 0), w - 1)
        vv = min(max(v, 0), h - 1)
        d_px = dist[vv, uu] + math.hypot(float(u - uu), float(v - vv))
        if not d_px > tol:
            continue
        tv = np.int64(iv[vv, uu]) + v0
        tu = np.int64(iu[vv, uu]) + u0
        d = depth[tv, tu]
        if not np.isfinite(d):
            continue
        # the pull is across the image: a sample behind the surface keeps its depth (a finger curled
        # away from the camera pulled forward to the surface unbent the hidden joints — grasp seen from
        # the back, fitted from the truth: 9–15° off with the surface's depth, ≤ 2° with its own); one
        # in front of it goes back to the surface, where the camera saw nothing nearer
        d = max(d, pz)
        out_nodes[n] = nodes[p]
        out_local[n, 0] = l0
        out_local[n, 1] = l1
        out_local[n, 2] = l2
        out_tgt[n, 0] = (tu - cx) / fx * d
        out_tgt[n, 1] = (tv - cy) / fy * d
        out_tgt[n, 2] = d
        n += 1
    return n


@njit(cache=True)
def feature_transform(mask, dist, iv, iu):
    """The exact Euclidean distance of every pixel to the nearest ``mask`` pixel (0 on the mask) into
    ``dist`` and that pixel's row and column into ``iv``/``iu``: what
    ``scipy.ndimage.distance_transform_edt(~mask, return_indices=True)`` returns (the same distances;
    of several equally near mask pixels this names the one of the smallest column, then of the
    smallest row), in two separable passes (Felzenszwalb & Huttenlocher 2012: per column the nearest
    mask pixel, then per row the lower envelope of the parabolas). Returns False (outputs unset) when
    the mask is empty. Every tracked frame builds its silhouette's transform: ~150 µs on a hand's
    207 × 167 window, scipy's ~1 ms."""
    H, W = mask.shape
    # per column: the nearest mask pixel's row (−1: none; the upper one on ties, as scipy's)
    gr = np.empty((H, W), np.int32)
    if not nearest_rows(mask, gr):
        return False
    # per row: the lower envelope of u ↦ (u − q)² + (v − gr[v, q])² over the columns q with a mask pixel;
    # parabola k of the envelope is the lowest from zs[k] on (zs[0] = −inf)
    cols = np.empty(W, np.int64)
    fs = np.empty(W)
    zs = np.empty(W + 1)
    for v in range(H):
        k = -1
        for q in range(W):
            r = gr[v, q]
            if r < 0:
                continue
            fq = float((v - r) * (v - r) + q * q)
            # where the new parabola drops below parabola k (one division a step: the pass is bound by
            # it); parabola 0 is never dropped, its zs is −inf
            s = -np.inf
            while k >= 0:
                s = (fq - fs[k]) / (2.0 * (q - cols[k]))
                if s <= zs[k]:
                    k -= 1
                else:
                    break
            k += 1
            cols[k] = q
            fs[k] = fq
            zs[k] = s
        zs[k + 1] = np.inf
        # pixel u takes the first parabola j with zs[j + 1] >= u (the left one at a breakpoint): whole
        # runs of pixels at a time, the distances in a loop the compiler vectorises
        u = 0
        for j in range(k + 1):
            z = zs[j + 1]
            end = W if z >= W else int(math.floor(z)) + 1
            if end <= u:
                continue
            q = cols[j]
            rv = gr[v, q]
            dv2 = float((v - rv) * (v - rv))
            for x in range(u, end):
                du = float(x - q)
                dist[v, x] = np.sqrt(du * du + dv2)
            iv[v, u:end] = rv
            iu[v, u:end] = q
            u = end
    return True
