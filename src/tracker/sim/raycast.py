"""A plain numpy ray caster: the reference the compiled z-buffer renderer is checked against and
benchmarked beside. It shares nothing with the renderer's kernels (ray–triangle intersection instead
of rasterisation), and is slow: use it for checks, not for synthesis."""
from __future__ import annotations

import numpy as np


def raycast(V, F, cam, tile=16):
    """Nearest hit of every pixel ray (two-sided Möller–Trumbore, numpy): depth (NaN = miss), face index.

    Triangles are binned into tiles by their projected bounding box (+1 px) only to prune pairs.
    """
    H, W = cam.height, cam.width
    depth = np.full((H, W), np.nan)
    fid = np.full((H, W), -1, np.int64)
    T = V[F]
    z = T[..., 2]
    keep = (z > 0.05).all(1)
    uu = cam.fx * T[..., 0] / np.where(keep[:, None], z, 1.0) + cam.cx
    vv = cam.fy * T[..., 1] / np.where(keep[:, None], z, 1.0) + cam.cy
    tu0 = np.clip(np.floor(uu.min(1) - 1) // tile, 0, (W - 1) // tile).astype(int)
    tu1 = np.clip(np.ceil(uu.max(1) + 1) // tile, 0, (W - 1) // tile).astype(int)
    tv0 = np.clip(np.floor(vv.min(1) - 1) // tile, 0, (H - 1) // tile).astype(int)
    tv1 = np.clip(np.ceil(vv.max(1) + 1) // tile, 0, (H - 1) // tile).astype(int)
    bins: dict = {}
    for t in np.flatnonzero(keep):
        for a in range(tv0[t], tv1[t] + 1):
            for b in range(tu0[t], tu1[t] + 1):
                bins.setdefault((a, b), []).append(t)
    for (a, b), tris in bins.items():
        vs = np.arange(a * tile, min((a + 1) * tile, H))
        us = np.arange(b * tile, min((b + 1) * tile, W))
        gv, gu = np.meshgrid(vs, us, indexing="ij")
        d = np.stack([(gu.ravel() - cam.cx) / cam.fx, (gv.ravel() - cam.cy) / cam.fy, np.ones(gu.size)], 1)
        tris = np.asarray(tris)
        v0, e1, e2 = T[tris, 0], T[tris, 1] - T[tris, 0], T[tris, 2] - T[tris, 0]
        p = np.cross(d[:, None, :], e2[None])  # (R, T, 3)
        det = np.einsum("tk,rtk->rt", e1, p)
        ok = np.abs(det) > 1e-18
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = -v0  # ray origin is the camera centre
        bu = np.einsum("tk,rtk->rt", s, p) * inv
        q = np.cross(s, e1)  # (T, 3)
        bv = np.einsum("rk,tk->rt", d, q) * inv
        tt = np.einsum("tk,tk->t", e2, q)[None] * inv
        hit = ok & (bu >= 0) & (bv >= 0) & (bu + bv <= 1) & (tt > 0)
        tt = np.where(hit, tt, np.inf)
        k = np.argmin(tt, axis=1)
        best = tt[np.arange(len(k)), k]
        m = np.isfinite(best)
        depth[gv.ravel()[m], gu.ravel()[m]] = best[m]  # d has z = 1, so t is the depth
        fid[gv.ravel()[m], gu.ravel()[m]] = tris[k[m]]
    return depth, fid
