"""Numba kernels of the shared damped Gauss-Newton IK solver (see :mod:`handmodel.solver`).

Residuals are computed in millimetres (×1000) so that damping values mean what they mean in the
paper and the original code. A point ``i`` rides on node ``pt_node[i]`` at ``pt_local[i]`` (node
frame); its target is ``targets[i]``; weight ``w[i]`` (0 or a NaN target drops it). A non-zero
``normals[i]`` makes it a point-to-plane term nᵀ(t − s), otherwise point-to-point t − s.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from .kinematics import fk_single, point_jacobian_col

MM = 1000.0


@njit(cache=True, inline="always")
def _unused(w, targets, i):
    """Point ``i`` contributes nothing: zero weight or a missing (NaN) target."""
    return w[i] == 0.0 or np.isnan(targets[i, 0])


@njit(cache=True, inline="always")
def _residual(G, j, local, target, normals, i):
    """Where point ``i`` (at ``local`` in node ``j``'s frame) is, and its residual to ``target`` in mm.

    Returns ``p0, p1, p2, e0, e1, e2, en, plane``: the world position (metres), the residual vector,
    its component along the point's normal and whether that normal is set (point-to-plane term;
    ``normals`` has no rows when no point has one).
    """
    p0 = G[j, 0, 0] * local[0] + G[j, 0, 1] * local[1] + G[j, 0, 2] * local[2] + G[j, 0, 3]
    p1 = G[j, 1, 0] * local[0] + G[j, 1, 1] * local[1] + G[j, 1, 2] * local[2] + G[j, 1, 3]
    p2 = G[j, 2, 0] * local[0] + G[j, 2, 1] * local[1] + G[j, 2, 2] * local[2] + G[j, 2, 3]
    e0 = (target[0] - p0) * MM
    e1 = (target[1] - p1) * MM
    e2 = (target[2] - p2) * MM
    plane = normals.shape[0] > i and (normals[i, 0] != 0.0 or normals[i, 1] != 0.0 or normals[i, 2] != 0.0)
    en = normals[i, 0] * e0 + normals[i, 1] * e1 + normals[i, 2] * e2 if plane else 0.0
    return p0, p1, p2, e0, e1, e2, en, plane


@njit(cache=True)
def energy(theta, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes,
           pt_node, pt_local, targets, w, normals, G, wa, wo):
    """½ Σ w² r² in mm² at θ (also leaves the frames in G)."""
    fk_single(theta, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes, G, wa, wo)
    E = 0.0
    for i in range(pt_node.shape[0]):
        if _unused(w, targets, i):
            continue
        _, _, _, e0, e1, e2, en, plane = _residual(G, pt_node[i], pt_local[i], targets[i], normals, i)
        E += w[i] * w[i] * (en * en if plane else e0 * e0 + e1 * e1 + e2 * e2)
    return 0.5 * E


@njit(cache=True)
def normal_equations(theta, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes,
                     pt_node, pt_local, targets, w, normals, G, wa, wo, A, b, cols, dids, p, tmp):
    """Accumulate A = JᵀW²J and b = JᵀW²e (mm units) without forming J; returns the energy."""
    n = dof_axes.shape[0]
    fk_single(theta, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes, G, wa, wo)
    for r in range(n):
        b[r] = 0.0
        for c in range(n):
            A[r, c] = 0.0
    E = 0.0
    for i in range(pt_node.shape[0]):
        if _unused(w, targets, i):
            continue
        j = pt_node[i]
        p[0], p[1], p[2], e0, e1, e2, en, plane = _residual(G, j, pt_local[i], targets[i], normals, i)
        # the DoFs that move this point: those of the node and its ancestors
        nd = 0
        k = j
        while k >= 0:
            for m in range(dof_ptr[k], dof_ptr[k + 1]):
                d = dof_idx[m]
                point_jacobian_col(dof_types[d], wa[d], wo[d], p, tmp)
                cols[nd, 0] = tmp[0] * MM
                cols[nd, 1] = tmp[1] * MM
                cols[nd, 2] = tmp[2] * MM
                dids[nd] = d
                nd += 1
            k = parents[k]
        w2 = w[i] * w[i]
        if plane:
            nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
            E += w2 * en * en
            for a in range(nd):
                cols[a, 0] = nx * cols[a, 0] + ny * cols[a, 1] + nz * cols[a, 2]
            for a in range(nd):
                da = dids[a]
                ja = cols[a, 0]
                b[da] += w2 * ja * en
                for c in range(a, nd):
                    v = w2 * ja * cols[c, 0]
                    A[da, dids[c]] += v
                    if c != a:
                        A[dids[c], da] += v
        else:
            E += w2 * (e0 * e0 + e1 * e1 + e2 * e2)
            for a in range(nd):
                da = dids[a]
                b[da] += w2 * (cols[a, 0] * e0 + cols[a, 1] * e1 + cols[a, 2] * e2)
                for c in range(a, nd):
                    v = w2 * (cols[a, 0] * cols[c, 0] + cols[a, 1] * cols[c, 1] + cols[a, 2] * cols[c, 2])
                    A[da, dids[c]] += v
                    if c != a:
                        A[dids[c], da] += v
    return 0.5 * E


@njit(cache=True)
def cholesky_solve(A, b, x, L):
    """Solve A x = b for symmetric positive definite A; returns False if A is not positive definite.
    Column by column with four rows' sums at once (four independent chains: the solve is latency-bound;
    26 DoF 2.9 → 1.8 µs against row by row); each entry of L is the row-by-row solve's subtractions in
    its order, so the same bits, and the first non-positive diagonal ends it as it ends that one."""
    m = A.shape[0]
    for j in range(m):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if s <= 0.0:
            return False
        d = np.sqrt(s)
        L[j, j] = d
        i = j + 1
        while i + 3 < m:
            s0, s1, s2, s3 = A[i, j], A[i + 1, j], A[i + 2, j], A[i + 3, j]
            for k in range(j):
                c = L[j, k]
                s0 -= L[i, k] * c
                s1 -= L[i + 1, k] * c
                s2 -= L[i + 2, k] * c
                s3 -= L[i + 3, k] * c
            L[i, j] = s0 / d
            L[i + 1, j] = s1 / d
            L[i + 2, j] = s2 / d
            L[i + 3, j] = s3 / d
            i += 4
        while i < m:
            s0 = A[i, j]
            for k in range(j):
                s0 -= L[i, k] * L[j, k]
            L[i, j] = s0 / d
            i += 1
    for i in range(m):
        s = b[i]
        for k in range(i):
            s -= L[i, k] * x[k]
        x[i] = s / L[i, i]
    for i in range(m - 1, -1, -1):
        s = x[i]
        for k in range(i + 1, m):
            s -= L[k, i] * x[k]
        x[i] = s / L[i, i]
    return True


@njit(cache=True)
def _limit_grad(a, lo, hi):
    """|∂H/∂a| of Chan–Dubey's H = (hi−lo)² / ((hi−a)(a−lo)); 0 when unlimited."""
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return 0.0
    dh = hi - a
    dl = a - lo
    if dh <= 0.0 or dl <= 0.0:
        return 1e30
    rng = hi - lo
    return abs(rng * rng * (2.0 * a - hi - lo) / (4.0 * dh * dh * dl * dl))


@njit(cache=True)
def freeze_at_limits(Aa, ba, alpha, lo, hi, m, margin):
    """Remove from the damped normal equations ``Aa δ = ba`` (the first ``m`` coordinates) every
    coordinate that sits at its clamped bound (within ``margin`` of ``lo + margin`` / ``hi − margin``)
    while the descent direction ``ba`` (−∂E/∂α) points outwards: its row and column become the
    identity's and its right-hand side 0, so δ is 0 there and the other coordinates get the solution
    of the system without it (an active-set, projected Gauss-Newton step). Clamping such a coordinate
    after a free solve changed the direction the others had been solved for, and that clamped step
    often failed to lower the energy at any length: the stage stopped after ``max_halvings`` wasted
    energy evaluations. Returns the number of frozen coordinates."""
    k = 0
    for c in range(m):
        out_lo = alpha[c] <= lo[c] + 2.0 * margin and ba[c] < 0.0
        out_hi = alpha[c] >= hi[c] - 2.0 * margin and ba[c] > 0.0
        if not (out_lo or out_hi):
            continue
        for r in range(m):
            Aa[r, c] = 0.0
            Aa[c, r] = 0.0
        Aa[c, c] = 1.0
        ba[c] = 0.0
        k += 1
    return k


@njit(cache=True)
def converged(delta, ba, m, E, tol):
    """Whether the step δ solving the damped normal equations ``Aa δ = ba`` would lower the energy
    ``E`` by at most ``tol·E`` even on the quadratic model (½ δᵀba, its decrease for that δ): at
    convergence the energy's round-off exceeds what the step can gain, so every trial of the step
    halving fails, and the stage would end anyway after ``max_halvings + 1`` wasted energy
    evaluations."""
    pred = 0.0
    for c in range(m):
        pred += delta[c] * ba[c]
    return 0.5 * pred <= tol * E


@njit(cache=True)
def solve_stages(theta0, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes,
                 pt_node, pt_local, targets, w, normals,
                 st_M, st_mu, st_m, st_lo, st_hi, st_damp, st_iters, st_ident,
                 max_halvings, tol, limit_avoid, clamp, margin, trace):
    """Run the damped Gauss-Newton stages from θ0; returns (θ, GN iterations done, clamp events).

    ``trace`` (≥ 1 + Σ iterations) receives the energy (mm², ½Σw²r²) before the first and after
    every accepted step; unused entries are left as they are.
    """
    n = dof_axes.shape[0]
    N = parents.shape[0]
    G = np.empty((N, 4, 4))
    wa = np.empty((n, 3))
    wo = np.empty((n, 3))
    A = np.empty((n, n))
    b = np.empty(n)
    cols = np.empty((n, 3))
    dids = np.empty(n, np.int64)
    p = np.empty(3)
    tmp = np.empty(3)
    theta = theta0.copy()
    th_new = np.empty(n)
    mmax = st_M.shape[2]
    Aa = np.empty((mmax, mmax))
    ba = np.empty(mmax)
    AM = np.empty((n, mmax))
    L = np.empty((mmax, mmax))
    delta = np.empty(mmax)
    alpha = np.empty(mmax)
    a_new = np.empty(mmax)
    g_prev = np.empty(mmax)
    E = energy(theta, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes, pt_node, pt_local, targets, w, normals, G, wa, wo)
    t_i = 0
    trace[t_i] = E
    iters = 0
    clamps = 0
    for s in range(st_M.shape[0]):
        m = st_m[s]
        M = st_M[s]
        mu = st_mu[s]
        ident = st_ident[s]
        # α = Mᵀ(θ − μ)
        for c in range(m):
            if ident:
                alpha[c] = theta[c]
            else:
                acc = 0.0
                for r in range(n):
                    acc += M[r, c] * (theta[r] - mu[r])
                alpha[c] = acc
        if not ident:
            for r in range(n):
                acc = mu[r]
                for c in range(m):
                    acc += M[r, c] * alpha[c]
                theta[r] = acc
            E = energy(theta, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes, pt_node, pt_local, targets, w, normals, G, wa, wo)
        for c in range(m):
            g_prev[c] = _limit_grad(alpha[c], st_lo[s, c], st_hi[s, c])
        for it in range(st_iters[s]):
            E = normal_equations(theta, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes,
                                 pt_node, pt_local, targets, w, normals, G, wa, wo, A, b, cols, dids, p, tmp)
            if ident:
                for r in range(m):
                    ba[r] = b[r]
                    for c in range(m):
                        Aa[r, c] = A[r, c]
            else:
                for r in range(n):
                    for c in range(m):
                        acc = 0.0
                        for k in range(n):
                            acc += A[r, k] * M[k, c]
                        AM[r, c] = acc
                for r in range(m):
                    acc = 0.0
                    for k in range(n):
                        acc += M[k, r] * b[k]
                    ba[r] = acc
                    for c in range(m):
                        acc = 0.0
                        for k in range(n):
                            acc += M[k, r] * AM[k, c]
                        Aa[r, c] = acc
            # selective damping, slowed near limits when moving towards them (Chan & Dubey)
            for c in range(m):
                lam = st_damp[s, c]
                if limit_avoid:
                    g = _limit_grad(alpha[c], st_lo[s, c], st_hi[s, c])
                    if g > g_prev[c]:
                        lam *= 1.0 + min(g, 1e12)
                    g_prev[c] = g
                Aa[c, c] += lam
            if clamp:
                freeze_at_limits(Aa, ba, alpha, st_lo[s], st_hi[s], m, margin)
            if not cholesky_solve(Aa[:m, :m], ba[:m], delta[:m], L[:m, :m]):
                tr = 0.0
                for c in range(m):
                    tr += Aa[c, c]
                for c in range(m):
                    Aa[c, c] += 1e-9 * tr / m + 1e-12
                if not cholesky_solve(Aa[:m, :m], ba[:m], delta[:m], L[:m, :m]):
                    break
            if converged(delta, ba, m, E, tol):
                break
            # step halving until the energy drops
            accepted = False
            step = 1.0
            E_new = E
            n_clamped = 0
            for h in range(max_halvings + 1):
                n_clamped = 0
                for c in range(m):
                    v = alpha[c] + step * delta[c]
                    if clamp:
                        lo = st_lo[s, c] + margin
                        hi = st_hi[s, c] - margin
                        if v < lo:
                            v = lo
                            n_clamped += 1
                        elif v > hi:
                            v = hi
                            n_clamped += 1
                    a_new[c] = v
                if ident:
                    for r in range(n):
                        th_new[r] = a_new[r]
                else:
                    for r in range(n):
                        acc = mu[r]
                        for c in range(m):
                            acc += M[r, c] * a_new[c]
                        th_new[r] = acc
                E_new = energy(th_new, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes,
                               pt_node, pt_local, targets, w, normals, G, wa, wo)
                if E_new < E:
                    accepted = True
                    break
                step *= 0.5
            if not accepted:
                break
            clamps += n_clamped
            iters += 1
            for c in range(m):
                alpha[c] = a_new[c]
            for r in range(n):
                theta[r] = th_new[r]
            t_i += 1
            if t_i < trace.shape[0]:
                trace[t_i] = E_new
            big = 0.0
            for c in range(m):
                big = max(big, abs(step * delta[c]))
            done = E - E_new <= tol * E or E_new < 1e-18 or big < 1e-10
            E = E_new
            if done:
                break
    return theta, iters, clamps


@njit(cache=True)
def solve_sequence(thetas0, warm, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes,
                   pt_node, pt_local, targets, w, normals, min_points,
                   st_M, st_mu, st_m, st_lo, st_hi, st_damp, st_iters, st_ident,
                   max_halvings, tol, limit_avoid, clamp, margin, out, iters, clamps, energies, traces):
    """Solve F frames; with ``warm`` each frame starts from the previous result.

    Frames with fewer than ``min_points`` valid points are skipped (θ left NaN, iterations −1).
    """
    F = targets.shape[0]
    n = dof_axes.shape[0]
    have_prev = False
    prev = np.empty(n)
    use_n = normals.shape[0] == F
    empty_normals = np.zeros((0, 3))
    for f in range(F):
        cnt = 0
        for i in range(pt_node.shape[0]):
            if w[f, i] != 0.0 and not np.isnan(targets[f, i, 0]):
                cnt += 1
        if cnt < min_points:
            for r in range(n):
                out[f, r] = np.nan
            iters[f] = -1
            clamps[f] = 0
            energies[f] = np.nan
            continue
        start = prev if (warm and have_prev) else thetas0[f]
        th, it, cl = solve_stages(start, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes,
                                  pt_node, pt_local, targets[f], w[f], normals[f] if use_n else empty_normals,
                                  st_M, st_mu, st_m, st_lo, st_hi, st_damp, st_iters, st_ident,
                                  max_halvings, tol, limit_avoid, clamp, margin, traces[f])
        for r in range(n):
            out[f, r] = th[r]
            prev[r] = th[r]
        have_prev = True
        iters[f] = it
        clamps[f] = cl
        last = 0
        for k in range(traces.shape[1]):
            if not np.isnan(traces[f, k]):
                last = k
        energies[f] = traces[f, last]
