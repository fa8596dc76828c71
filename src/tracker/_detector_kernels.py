"""Numba kernels of the hand-part detector (:mod:`tracker.detector`): the probe of one depth pixel, the
depth-difference feature its forests split on (:func:`tracker.detector.feature_matrix`,
:func:`tracker.detector.forest_proba` walk them) and the weighted mean shift that finds a part's keypoint
(:func:`tracker.detector.parts_to_keypoints`)."""
from __future__ import annotations

import numba as nb
import numpy as np

#: What a probe off the image or on a pixel without depth reads (metres): far behind any hand.
BACKGROUND_M = 10.0


@nb.njit(cache=True, inline="always")
def probe(depth, r, c, dr, dc):
    """The depth at pixel ``(r + dr, c + dc)`` rounded; :data:`BACKGROUND_M` off the image or without depth."""
    rr = int(np.floor(r + dr + 0.5))
    cc = int(np.floor(c + dc + 0.5))
    if rr < 0 or cc < 0 or rr >= depth.shape[0] or cc >= depth.shape[1]:
        return BACKGROUND_M
    v = depth[rr, cc]
    if not (v > 0.0):  # NaN or no data
        return BACKGROUND_M
    return v


@nb.njit(cache=True)
def feature(depth, r, c, d0, fx, fy, A, ux, uy, vx, vy):
    """One depth-difference feature at pixel (r, c) whose depth is ``d0`` (float32 result, as the
    forest was trained on); ``A`` (2, 2) maps the offsets into the image (mirror, roll)."""
    pu = A[0, 0] * ux + A[0, 1] * uy
    pv = A[1, 0] * ux + A[1, 1] * uy
    qu = A[0, 0] * vx + A[0, 1] * vy
    qv = A[1, 0] * vx + A[1, 1] * vy
    a = probe(depth, r, c, fy * pv / d0, fx * pu / d0)
    b = probe(depth, r, c, fy * qv / d0, fx * qu / d0)
    return np.float32(a - b)


@nb.njit(cache=True)
def mean_shift(P, w, seeds, bandwidth, iterations):
    """The densest mode of the weighted points ``P`` (N, 3) reached from ``seeds`` (S, 3) by a
    Gaussian mean shift; returns ``(mode, density)``."""
    best = np.full(3, np.nan)
    best_d = -1.0
    inv = 1.0 / (bandwidth * bandwidth)
    for s in range(seeds.shape[0]):
        m = seeds[s].copy()
        dens = 0.0
        for _ in range(iterations):
            acc = np.zeros(3)
            dens = 0.0
            for i in range(P.shape[0]):
                d2 = 0.0
                for a in range(3):
                    q = P[i, a] - m[a]
                    d2 += q * q
                k = w[i] * np.exp(-d2 * inv)
                dens += k
                for a in range(3):
                    acc[a] += k * P[i, a]
            if dens <= 0.0:
                break
            step = 0.0
            for a in range(3):
                q = acc[a] / dens
                step += (q - m[a]) ** 2
                m[a] = q
            if step < 1e-10:
                break
        if dens > best_d:
            best_d = dens
            best[:] = m
    return best, best_d
