"""Numba kernels: closest points on round cones (tapered capsules) and rounded slabs."""
from __future__ import annotations

import numpy as np
from numba import njit

CAPSULE, SLAB = 0, 1


@njit(cache=True, inline="always")
def _round_cone_2d(x, y, L, ra, rb):
    """Closest boundary point (cx, cy), normal (nx, ny) and signed distance for (x, y≥0) in the
    profile plane of the convex hull of circles (0,0,ra) and (L,0,rb)."""
    d = ra - rb
    if abs(d) >= L:  # one sphere contains the other: the bigger sphere
        if ra >= rb:
            cxs, rr = 0.0, ra
        else:
            cxs, rr = L, rb
        vx, vy = x - cxs, y
        nn = np.sqrt(vx * vx + vy * vy)
        if nn < 1e-15:
            vx, vy, nn = 0.0, 1.0, 1.0
        nx_, ny_ = vx / nn, vy / nn
        return cxs + rr * nx_, rr * ny_, nx_, ny_, nn - rr
    nx = d / L
    ny = np.sqrt(1.0 - nx * nx)
    tax, tay = ra * nx, ra * ny              # tangent point on circle A
    side = np.sqrt(L * L - d * d)
    tx, ty = ny, -nx                          # tangent direction, from A towards B
    s = (x - tax) * tx + (y - tay) * ty
    if s < 0.0:
        nn = np.sqrt(x * x + y * y)
        if nn < 1e-15:
            return -ra, 0.0, -1.0, 0.0, -ra
        return ra * x / nn, ra * y / nn, x / nn, y / nn, nn - ra
    if s > side:
        vx, vy = x - L, y
        nn = np.sqrt(vx * vx + vy * vy)
        if nn < 1e-15:
            return L + rb, 0.0, 1.0, 0.0, -rb
        return L + rb * vx / nn, rb * vy / nn, vx / nn, vy / nn, nn - rb
    cx, cy = tax + s * tx, tay + s * ty
    dist = (x - cx) * nx + (y - cy) * ny
    return cx, cy, nx, ny, dist


@njit(cache=True, inline="always")
def _closest_on_segment_2d(px, py, ax, ay, bx, by):
    ex, ey = bx - ax, by - ay
    ll = ex * ex + ey * ey
    t = 0.0 if ll <= 0.0 else ((px - ax) * ex + (py - ay) * ey) / ll
    t = min(1.0, max(0.0, t))
    return ax + t * ex, ay + t * ey


@njit(cache=True)
def closest_local(shape, L, r0, r1, th, q, out):
    """Closest surface point of one primitive in its local frame: out = (cx,cy,cz,nx,ny,nz,dist)."""
    x, y, z = q[0], q[1], q[2]
    if shape == CAPSULE:
        # axis along local +y; radial direction in the x-z plane
        rad = np.sqrt(x * x + z * z)
        if rad < 1e-15:
            ex, ez = 1.0, 0.0
        else:
            ex, ez = x / rad, z / rad
        cx, cr, nax, nr, dist = _round_cone_2d(y, rad, L, r0, r1)
        out[0] = cr * ex
        out[1] = cx
        out[2] = cr * ez
        out[3] = nr * ex
        out[4] = nax
        out[5] = nr * ez
        out[6] = dist
        return
    # slab: trapezoid in the local x-y plane (half-widths w0 at y=0, w1 at y=L) swept by a sphere th
    w0 = max(r0 - th, 0.0)
    w1 = max(r1 - th, 0.0)
    vx0, vy0 = -w0, 0.0
    vx1, vy1 = w0, 0.0
    vx2, vy2 = w1, L
    vx3, vy3 = -w1, L
    inside = True
    c0 = (vx1 - vx0) * (y - vy0) - (vy1 - vy0) * (x - vx0)
    c1 = (vx2 - vx1) * (y - vy1) - (vy2 - vy1) * (x - vx1)
    c2 = (vx3 - vx2) * (y - vy2) - (vy3 - vy2) * (x - vx2)
    c3 = (vx0 - vx3) * (y - vy3) - (vy0 - vy3) * (x - vx3)
    if c0 < 0 or c1 < 0 or c2 < 0 or c3 < 0:
        inside = False
    if inside:
        px, py = x, y
    else:
        best = 1e300
        px, py = 0.0, 0.0
        for e in range(4):
            if e == 0:
                ax, ay, bx, by = vx0, vy0, vx1, vy1
            elif e == 1:
                ax, ay, bx, by = vx1, vy1, vx2, vy2
            elif e == 2:
                ax, ay, bx, by = vx2, vy2, vx3, vy3
            else:
                ax, ay, bx, by = vx3, vy3, vx0, vy0
            cx, cy = _closest_on_segment_2d(x, y, ax, ay, bx, by)
            dd = (x - cx) * (x - cx) + (y - cy) * (y - cy)
            if dd < best:
                best = dd
                px, py = cx, cy
    dx, dy, dz = x - px, y - py, z
    nn = np.sqrt(dx * dx + dy * dy + dz * dz)
    if nn < 1e-15:
        dx, dy, dz, nn = 0.0, 0.0, 1.0, 1.0
    nx, ny, nz = dx / nn, dy / nn, dz / nn
    out[0] = px + th * nx
    out[1] = py + th * ny
    out[2] = th * nz
    out[3] = nx
    out[4] = ny
    out[5] = nz
    out[6] = nn - th


@njit(cache=True)
def closest_local_many(shape, L, r0, r1, th, pts, out_p, out_n):
    """:func:`closest_local` of every row of ``pts`` ``(P, 3)``: surface points into ``out_p``, outward
    normals into ``out_n`` (one call instead of one per point from Python)."""
    loc = np.empty(7)
    for i in range(pts.shape[0]):
        closest_local(shape, L, r0, r1, th, pts[i], loc)
        for m in range(3):
            out_p[i, m] = loc[m]
            out_n[i, m] = loc[3 + m]


@njit(cache=True, inline="always")
def closest_on_primitive(G, j, shape, L, r0, r1, th, px, py, pz, q, loc):
    """The closest point to the world point ``(px, py, pz)`` on one primitive posed by node frame ``G[j]``,
    in its local frame: ``q`` ← the point there (Rᵀ (p − o)), ``loc`` ← :func:`closest_local`'s answer."""
    d0 = px - G[j, 0, 3]
    d1 = py - G[j, 1, 3]
    d2 = pz - G[j, 2, 3]
    for r in range(3):
        q[r] = G[j, 0, r] * d0 + G[j, 1, r] * d1 + G[j, 2, r] * d2
    closest_local(shape, L, r0, r1, th, q, loc)


@njit(cache=True, inline="always")
def to_world(G, j, loc, wp, wn):
    """``wp``, ``wn`` ← :func:`closest_local`'s point and normal ``loc`` in the world, by node frame ``G[j]``."""
    for r in range(3):
        wp[r] = G[j, r, 0] * loc[0] + G[j, r, 1] * loc[1] + G[j, r, 2] * loc[2] + G[j, r, 3]
        wn[r] = G[j, r, 0] * loc[3] + G[j, r, 1] * loc[4] + G[j, r, 2] * loc[5]


@njit(cache=True, inline="always")
def bounding_spheres(G, seg_node, seg_shape, seg_len, seg_r0, seg_r1, seg_th):
    """``(centres (S, 3), radii (S,))``: each primitive's bounding sphere at the node frames ``G`` (no surface
    of it is nearer a point than that sphere: the closest-point searches skip primitives by it)."""
    S = seg_node.shape[0]
    sc = np.empty((S, 3))
    sr = np.empty(S)
    for s in range(S):
        j = seg_node[s]
        L = seg_len[s]
        if seg_shape[s] == CAPSULE:
            sr[s] = 0.5 * L + max(seg_r0[s], seg_r1[s])
        else:
            w = max(max(seg_r0[s] - seg_th[s], 0.0), max(seg_r1[s] - seg_th[s], 0.0))
            sr[s] = np.sqrt(0.25 * L * L + w * w) + seg_th[s]
        for r in range(3):
            sc[s, r] = G[j, r, 1] * 0.5 * L + G[j, r, 3]
    return sc, sr


@njit(cache=True, inline="always")
def _closest(G, seg_node, seg_shape, seg_len, seg_r0, seg_r1, seg_th, points, cam, facing_only, signed,
             out_p, out_n, out_seg, out_d):
    """The closest candidate over all primitives for every point (see the two kernels below); the
    smallest signed distance wins when ``signed``, else the smallest absolute one; of equally close
    candidates the lowest segment index.

    Every primitive lies inside a bounding sphere, and no surface inside it is nearer than the
    distance to the sphere: primitives whose sphere is farther than the best candidate so far are
    skipped without their closest-point computation. The search starts with the previous point's
    winner (neighbouring points of a scan mostly share it), so the bound prunes from the start.
    The order of the visits does not change the result (ties go to the lowest index)."""
    P = points.shape[0]
    q = np.empty(3)
    loc = np.empty(7)
    wp = np.empty(3)
    wn = np.empty(3)
    sc, sr = bounding_spheres(G, seg_node, seg_shape, seg_len, seg_r0, seg_r1, seg_th)
    S = sr.shape[0]
    prev = 0
    for i in range(P):
        best = 1e300
        bs = -1
        for t in range(S):
            # prev first, then the others in index order
            s = prev if t == 0 else (t - 1 if t - 1 < prev else t)
            c0 = points[i, 0] - sc[s, 0]
            c1 = points[i, 1] - sc[s, 1]
            c2 = points[i, 2] - sc[s, 2]
            # margin: the node frames are orthonormal to ~1e-6 only, so local and world lengths differ
            bound = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2) - sr[s]
            if bound > best + 1e-5 * abs(best) + 1e-6:
                continue
            j = seg_node[s]
            closest_on_primitive(G, j, seg_shape[s], seg_len[s], seg_r0[s], seg_r1[s], seg_th[s], points[i, 0],
                                 points[i, 1], points[i, 2], q, loc)
            dist = loc[6] if signed else abs(loc[6])
            if dist > best or (dist == best and s > bs):
                continue
            to_world(G, j, loc, wp, wn)
            if facing_only:
                view = (wp[0] - cam[0]) * wn[0] + (wp[1] - cam[1]) * wn[1] + (wp[2] - cam[2]) * wn[2]
                if view > 0.0:
                    continue
            best = dist
            bs = s
            for r in range(3):
                out_p[i, r] = wp[r]
                out_n[i, r] = wn[r]
        out_seg[i] = bs
        out_d[i] = best if bs >= 0 else np.inf
        if bs >= 0:
            prev = bs


@njit(cache=True)
def closest_points(G, seg_node, seg_shape, seg_len, seg_r0, seg_r1, seg_th, points, out_p, out_n, out_seg, out_d):
    """Closest point on the union of primitives posed by node frames ``G`` for every point; a point
    inside the model takes the primitive it is deepest in (smallest signed distance)."""
    _closest(G, seg_node, seg_shape, seg_len, seg_r0, seg_r1, seg_th, points, np.zeros(3), False, True,
             out_p, out_n, out_seg, out_d)


@njit(cache=True, nogil=True)
def closest_points_facing(G, seg_node, seg_shape, seg_len, seg_r0, seg_r1, seg_th, points, cam, facing_only,
                          out_p, out_n, out_seg, out_d):
    """Like :func:`closest_points`, but the smallest absolute distance wins and a candidate whose
    surface normal faces away from the camera centre ``cam`` is skipped when ``facing_only`` (a depth
    camera sees only front surfaces). Points with no front-facing candidate get segment −1 and
    distance +inf."""
    _closest(G, seg_node, seg_shape, seg_len, seg_r0, seg_r1, seg_th, points, cam, facing_only, False,
             out_p, out_n, out_seg, out_d)
