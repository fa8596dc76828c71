"""Numba kernel: model→data silhouette pairs (pose the model samples, keep the front-facing ones,
project them, look up the distance transform and fetch the nearest silhouette pixel's 3-D point)."""
from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def silhouette_pairs_kernel(G, nodes, local, local_n, fx, fy, cx, cy, dist, iv, iu, depth, v0, u0, tol,
                            out_nodes, out_local, out_tgt):
    """One pass over the samples (``nodes (P,)``, ``local``/``local_n (P,3)`` in the node frames
    ``G (N,4,4)``). Each sample facing the camera (P·N < 0, z > 1e-3) whose pixel (rounded half to
    even) lies more than ``tol`` px from the silhouette — ``dist`` at the pixel clipped into the
    window starting at ``(v0, u0)`` plus the length of the clipping — and whose nearest silhouette
    pixel has finite depth is written, in sample order, to ``out_nodes``/``out_local``/``out_tgt``
    (the target is that pixel back-projected at the sample's depth, or the pixel's own depth when
    that is farther). Returns the number written."""
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
        if not (px * nx + py * ny + pz * nz < 0.0 and pz > 1e-3):
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
