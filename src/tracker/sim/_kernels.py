"""numba kernels of the synthetic lab: skinning, z-buffer passes and shading for
:mod:`tracker.sim.render`, projector shadows and lateral resampling for :mod:`tracker.sim.noise`.

Pixel convention: pixel ``(v, u)`` (row, column) samples the ray through the image point ``(u, v)``
with integer coordinates, i.e. pixel centres sit at integers (OpenCV's convention): the ray of
pixel ``(v, u)`` is ``((u − cx)/fx, (v − cy)/fy, 1)``.
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def lbs(rest, idx, w, B, out):
    """Sparse linear blend skinning: ``out[i] = Σ_k w[i,k] B[idx[i,k]] · (rest[i], 1)``.

    ``B`` is ``(N, 3, 4)`` (blend matrices ``G(θ) G(0)⁻¹``), ``idx``/``w`` ``(V, K)`` the K largest
    weights of each vertex (unused slots carry weight 0).
    """
    V, K = idx.shape
    for i in range(V):
        x, y, z = rest[i, 0], rest[i, 1], rest[i, 2]
        ox = 0.0
        oy = 0.0
        oz = 0.0
        for k in range(K):
            wk = w[i, k]
            if wk == 0.0:
                continue
            M = B[idx[i, k]]
            ox += wk * (M[0, 0] * x + M[0, 1] * y + M[0, 2] * z + M[0, 3])
            oy += wk * (M[1, 0] * x + M[1, 1] * y + M[1, 2] * z + M[1, 3])
            oz += wk * (M[2, 0] * x + M[2, 1] * y + M[2, 2] * z + M[2, 3])
        out[i, 0] = ox
        out[i, 1] = oy
        out[i, 2] = oz


@njit(cache=True, nogil=True)
def _nearer(z, d):
    """The z-buffer test of every pass: ``z`` wins over the stored ``d`` if nearer or if nothing is
    stored yet (NaN).

    The writes stay in the passes: a helper that takes the image arrays keeps numba from vectorising
    the pixel loops (the table pass went from 0.14 to 11 ms per 640×480 frame)."""
    return z < d or d != d


@njit(cache=True, nogil=True)
def raster(P, faces, face_label, face_offset, fx, fy, cx, cy, near, cull, depth, label, face_id):
    """Z-buffer rasterisation of triangles ``faces`` over vertices ``P`` (camera frame, metres).

    ``depth`` (H, W) float32 must start as NaN (no surface) or hold earlier passes; a pixel is
    overwritten where the triangle is nearer. The depth written is the exact z of the ray–plane
    intersection: 1/z is affine in the pixel coordinates, ``1/z = (n·d(u, v)) / (n·p0)``.
    Triangles with a vertex nearer than ``near`` are skipped (no near-plane clipping); with
    ``cull`` back faces (outward normal away from the camera) are skipped, which is exact for
    closed meshes. ``face_id`` receives ``face_offset + t``.
    """
    H, W = depth.shape
    ifx = 1.0 / fx
    ify = 1.0 / fy
    for t in range(faces.shape[0]):
        a = faces[t, 0]
        b = faces[t, 1]
        c = faces[t, 2]
        x0, y0, z0 = P[a, 0], P[a, 1], P[a, 2]
        x1, y1, z1 = P[b, 0], P[b, 1], P[b, 2]
        x2, y2, z2 = P[c, 0], P[c, 1], P[c, 2]
        if z0 < near or z1 < near or z2 < near:
            continue
        e1x, e1y, e1z = x1 - x0, y1 - y0, z1 - z0
        e2x, e2y, e2z = x2 - x0, y2 - y0, z2 - z0
        nx = e1y * e2z - e1z * e2y
        ny = e1z * e2x - e1x * e2z
        nz = e1x * e2y - e1y * e2x
        dn = nx * x0 + ny * y0 + nz * z0  # plane: n·p = dn; the camera (origin) is in front iff dn < 0
        if dn == 0.0 or (cull and dn > 0.0):
            continue
        u0 = fx * x0 / z0 + cx
        v0 = fy * y0 / z0 + cy
        u1 = fx * x1 / z1 + cx
        v1 = fy * y1 / z1 + cy
        u2 = fx * x2 / z2 + cx
        v2 = fy * y2 / z2 + cy
        umin = max(int(np.ceil(min(u0, min(u1, u2)))), 0)
        umax = min(int(np.floor(max(u0, max(u1, u2)))), W - 1)
        if umin > umax:
            continue
        vmin = max(int(np.ceil(min(v0, min(v1, v2)))), 0)
        vmax = min(int(np.floor(max(v0, max(v1, v2)))), H - 1)
        if vmin > vmax:
            continue
        area = (u1 - u0) * (v2 - v0) - (v1 - v0) * (u2 - u0)
        if area == 0.0:
            continue
        inv = 1.0 / area
        # barycentrics are affine in (u, v): w_i = a_i u + b_i v + c_i (normalised, orientation-free)
        a0 = (v1 - v2) * inv
        b0 = (u2 - u1) * inv
        c0 = (u1 * v2 - u2 * v1) * inv
        a1 = (v2 - v0) * inv
        b1 = (u0 - u2) * inv
        c1 = (u2 * v0 - u0 * v2) * inv
        a2 = (v0 - v1) * inv
        b2 = (u1 - u0) * inv
        c2 = (u0 * v1 - u1 * v0) * inv
        iA = nx * ifx / dn
        iB = ny * ify / dn
        iC = (nz - nx * cx * ifx - ny * cy * ify) / dn
        lab = face_label[t]
        fid = face_offset + t
        eps = -1e-9  # closes cracks along shared edges; the depth stays that of the ray-plane hit
        for v in range(vmin, vmax + 1):
            fv = float(v)
            for u in range(umin, umax + 1):
                fu = float(u)
                w0 = a0 * fu + b0 * fv + c0
                if w0 < eps:
                    continue
                w1 = a1 * fu + b1 * fv + c1
                if w1 < eps:
                    continue
                w2 = a2 * fu + b2 * fv + c2
                if w2 < eps:
                    continue
                iz = iA * fu + iB * fv + iC
                if iz <= 0.0:
                    continue
                z = np.float32(1.0 / iz)
                if _nearer(z, depth[v, u]):
                    depth[v, u] = z
                    label[v, u] = lab
                    face_id[v, u] = fid


@njit(cache=True, nogil=True)
def plane_pass(n, dn, fx, fy, cx, cy, zmax, depth, label, lab, face_id, fid):
    """Z-buffer an infinite plane ``n·p = dn`` (camera in front: ``dn < 0``) up to depth ``zmax``."""
    H, W = depth.shape
    for v in range(H):
        ry = (v - cy) / fy
        for u in range(W):
            nd = n[0] * (u - cx) / fx + n[1] * ry + n[2]
            if nd >= 0.0:
                continue
            z = dn / nd
            if z <= 0.0 or z > zmax:
                continue
            z32 = np.float32(z)
            if _nearer(z32, depth[v, u]):
                depth[v, u] = z32
                label[v, u] = lab
                face_id[v, u] = fid


@njit(cache=True, nogil=True)
def projector_shadow(depth, fb, side, out):
    """Mark pixels the structured-light projector cannot see (``out`` True = shadowed).

    The projector sits ``b`` to the side of the camera along image x (``side`` +1: to the right,
    −1: to the left) with the same orientation, so a point at pixel column ``u`` and depth ``z``
    lies on projector column ``u − side·f b / z`` (``fb = f·b`` in pixel·metres). Scanning each
    row from the projector's side, a point is shadowed when a surface already passed (nearer to
    the projector's side in the image) reaches a projector column at or beyond its own.
    """
    H, W = depth.shape
    for v in range(H):
        m = np.inf
        for k in range(W):
            u = W - 1 - k if side > 0 else k
            z = depth[v, u]
            if z != z or z <= 0.0:
                continue
            up = side * u - fb / z  # projector column, mirrored for side < 0 so the scan is the same
            if up > m:
                out[v, u] = True
            else:
                m = up


@njit(cache=True, nogil=True)
def shade(P, faces, face_id, face_material, plane_material, n_table, fx, fy, cx, cy, light, materials, background,
          color, cos_out):
    """Per-pixel flat shading and incidence from the visible-face buffer.

    ``face_id`` ≥ 0 indexes ``faces`` (hand faces first, then clutter), −2 is the plane with normal
    ``n_table``. ``materials`` rows are RGB colours: face ``f`` has ``materials[face_material[f]]``,
    the plane ``materials[plane_material]``. Writes
    ``color`` (H, W, 3) uint8 when it has pixels and ``cos_out`` (H, W) float32 (|cos| between normal
    and ray, NaN where nothing) when it has pixels.
    """
    H, W = face_id.shape
    want_color = color.shape[0] == H
    want_cos = cos_out.shape[0] == H
    for v in range(H):
        for u in range(W):
            f = face_id[v, u]
            if f == -1:
                if want_color:
                    color[v, u, 0] = background[0]
                    color[v, u, 1] = background[1]
                    color[v, u, 2] = background[2]
                if want_cos:
                    cos_out[v, u] = np.nan
                continue
            if f >= 0:
                a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
                e1x, e1y, e1z = P[b, 0] - P[a, 0], P[b, 1] - P[a, 1], P[b, 2] - P[a, 2]
                e2x, e2y, e2z = P[c, 0] - P[a, 0], P[c, 1] - P[a, 1], P[c, 2] - P[a, 2]
                nx = e1y * e2z - e1z * e2y
                ny = e1z * e2x - e1x * e2z
                nz = e1x * e2y - e1y * e2x
                m = face_material[f]
            else:
                nx, ny, nz = n_table[0], n_table[1], n_table[2]
                m = plane_material
            nn = np.sqrt(nx * nx + ny * ny + nz * nz)
            if nn == 0.0:
                nn = 1.0
            rx = (u - cx) / fx
            ry = (v - cy) / fy
            rn = np.sqrt(rx * rx + ry * ry + 1.0)
            cosr = (nx * rx + ny * ry + nz) / (nn * rn)
            if want_cos:
                cos_out[v, u] = abs(cosr)
            if want_color:
                s = -1.0 if cosr > 0.0 else 1.0  # the side facing the camera
                lam = s * (nx * light[0] + ny * light[1] + nz * light[2]) / nn
                lam = 0.35 + 0.65 * min(max(lam, 0.0), 1.0)
                for k in range(3):
                    color[v, u, k] = np.uint8(min(materials[m, k] * lam + 0.5, 255.0))


@njit(cache=True, nogil=True)
def lateral_resample(d, cosi, nu, nv, sigma0, angle, reach, out_d, out_cos):
    """Nearest-pixel resampling at Gaussian offsets: pixel (v, u) takes (v + round(σ nv), u + round(σ nu)).

    σ = ``sigma0`` (+ Nguyen's ``0.035 θ/(π/2 − θ)`` when ``angle``, θ from ``cosi``, clipped at 85°);
    offsets are clipped to ±``reach`` and to the image. ``cosi`` may be empty (0×0) when not used.
    """
    H, W = d.shape
    use_cos = cosi.shape[0] == H
    tmax = 85.0 * np.pi / 180.0
    for v in range(H):
        for u in range(W):
            s = sigma0
            if angle and use_cos:
                c = cosi[v, u]
                if c == c:
                    th = min(np.arccos(min(abs(c), 1.0)), tmax)
                    s += 0.035 * th / (np.pi / 2 - th)
            du = min(max(int(np.rint(s * nu[v, u])), -reach), reach)
            dv = min(max(int(np.rint(s * nv[v, u])), -reach), reach)
            uu = min(max(u + du, 0), W - 1)
            vv = min(max(v + dv, 0), H - 1)
            out_d[v, u] = d[vv, uu]
            if use_cos:
                out_cos[v, u] = cosi[vv, uu]
