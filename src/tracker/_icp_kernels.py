"""Numba kernels: one whole ICP fit (see :func:`tracker.icp.fit`) in compiled code.

The Python loop of :func:`tracker.icp.fit_reference` paid its interpreter and array-wrapping costs
once per ICP iteration (correspondences, local offsets, silhouette pairs, the solver's argument
checks); here the loop runs inside one compiled call. The Gauss-Newton steps work on per-node moment
sums of the pairs (:func:`node_moments`): with the pairs fixed during a step, every energy and every
normal-equation evaluation costs O(nodes × DoF²) instead of O(pairs × DoF²); a subspace's normal
equations are projected from all DoF's (a synergy subspace is not cheaper per step: its PCs touch every
finger). What a stage in the synergy subspace can save is the closest-point search, the costly part
of a stage: a local pass (:func:`match_same`) re-projects each point onto the primitive it was matched
to. Point-to-plane pairs do not reduce to moments; they go through the per-pair solver of
:mod:`handmodel._solver_kernels`.

Stage arrays (one row per stage, padded to the widest): ``st_M (S, n, m)``, ``st_mu (S, n)``,
``st_m (S,)``, ``st_lo``/``st_hi``/``st_damp (S, m)``, ``st_eye (S,)`` (M is the identity),
``st_entry (S,)`` (0 none, 1 clamp, 2 through), ``st_local (S,)`` (a local pass may replace the
closest-point search); the projection after a stage: ``pr_on (S,)`` and
``pr_M``/``pr_mu``/``pr_lo``/``pr_hi``/``pr_m`` like the stage's.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from handmodel._geometry_kernels import closest_local, closest_points_facing
from handmodel._solver_kernels import (
    MM,
    _limit_grad,
    cholesky_solve,
    converged,
    freeze_at_limits,
    solve_stages,
)
from handmodel.kinematics import fk_single

from ._segment_kernels import nearest_rows
from ._silhouette_kernels import silhouette_pairs_kernel

ENTRY_NONE, ENTRY_CLAMP, ENTRY_THROUGH = 0, 1, 2


# ----------------------------------------------------------------------------- correspondences
@njit(cache=True)
def match(G, seg_node, seg_shape, seg_len, seg_r0, seg_r1, seg_th, points, normals, cam, facing_only, reject,
          agreement, out_p, out_n, out_seg, out_d, out_node, out_valid):
    """Data→model pairs at the node frames ``G`` (:class:`tracker.correspond.Matcher` with capsules):
    the closest front-facing capsule point, rejected at ``reject`` m or farther and, with data
    ``normals`` (rows; NaN rows unknown), when the normals' cosine is below ``agreement`` (−1 = off).
    Returns the number of valid pairs."""
    closest_points_facing(G, seg_node, seg_shape, seg_len, seg_r0, seg_r1, seg_th, points, cam, facing_only,
                          out_p, out_n, out_seg, out_d)
    use_n = normals.shape[0] == points.shape[0] and agreement > -1.0
    nv = 0
    for i in range(points.shape[0]):
        s = out_seg[i]
        out_node[i] = seg_node[s] if s >= 0 else 0
        ok = s >= 0 and _pair_ok(normals, out_n, out_d, i, reject, agreement, use_n)
        out_valid[i] = ok
        if ok:
            nv += 1
    return nv


@njit(cache=True, inline="always")
def _pair_ok(normals, out_n, out_d, i, reject, agreement, use_n):
    """Pair ``i`` kept: nearer than ``reject`` and, with normals, agreeing by at least ``agreement``."""
    if not out_d[i] < reject:  # as written, a NaN distance is rejected
        return False
    if use_n:
        c = normals[i, 0] * out_n[i, 0] + normals[i, 1] * out_n[i, 1] + normals[i, 2] * out_n[i, 2]
        if c < agreement:  # NaN (unknown normal) keeps the pair
            return False
    return True


@njit(cache=True)
def match_same(G, seg_node, seg_shape, seg_len, seg_r0, seg_r1, seg_th, points, normals, cam, facing_only, reject,
               agreement, out_p, out_n, out_seg, out_d, out_node, out_valid):
    """:func:`match` with every point kept on the primitive it was matched to (``out_seg``): its
    closest point there at the frames ``G``, no search over the others (a point whose primitive now
    faces away, or that had none, is left unpaired). Returns the number of valid pairs."""
    use_n = normals.shape[0] == points.shape[0] and agreement > -1.0
    q = np.empty(3)
    loc = np.empty(7)
    nv = 0
    for i in range(points.shape[0]):
        s = out_seg[i]
        out_valid[i] = False
        if s < 0:
            continue
        j = seg_node[s]
        d0 = points[i, 0] - G[j, 0, 3]
        d1 = points[i, 1] - G[j, 1, 3]
        d2 = points[i, 2] - G[j, 2, 3]
        for r in range(3):
            q[r] = G[j, 0, r] * d0 + G[j, 1, r] * d1 + G[j, 2, r] * d2
        closest_local(seg_shape[s], seg_len[s], seg_r0[s], seg_r1[s], seg_th[s], q, loc)
        for r in range(3):
            out_p[i, r] = G[j, r, 0] * loc[0] + G[j, r, 1] * loc[1] + G[j, r, 2] * loc[2] + G[j, r, 3]
            out_n[i, r] = G[j, r, 0] * loc[3] + G[j, r, 1] * loc[4] + G[j, r, 2] * loc[5]
        out_d[i] = abs(loc[6])
        if facing_only:
            view = ((out_p[i, 0] - cam[0]) * out_n[i, 0] + (out_p[i, 1] - cam[1]) * out_n[i, 1]
                    + (out_p[i, 2] - cam[2]) * out_n[i, 2])
            if view > 0.0:
                continue
        ok = _pair_ok(normals, out_n, out_d, i, reject, agreement, use_n)
        out_valid[i] = ok
        if ok:
            nv += 1
    return nv


# ----------------------------------------------------------------------------- rigid step
@njit(cache=True)
def _euler_to_matrix(a, b, c, R):
    ca, sa = np.cos(a), np.sin(a)
    cb, sb = np.cos(b), np.sin(b)
    cc, sc = np.cos(c), np.sin(c)
    R[0, 0] = cb * cc
    R[0, 1] = -cb * sc
    R[0, 2] = sb
    R[1, 0] = ca * sc + sa * sb * cc
    R[1, 1] = ca * cc - sa * sb * sc
    R[1, 2] = -sa * cb
    R[2, 0] = sa * sc - ca * sb * cc
    R[2, 1] = sa * cc + ca * sb * sc
    R[2, 2] = ca * cb


@njit(cache=True)
def rigid_update(theta, src, dst, valid):
    """θ with the global pose moved by Horn's rigid motion from the valid ``src`` to ``dst`` rows
    (:func:`tracker.icp.rigid_step`, unweighted); unchanged with fewer than 3 valid rows."""
    n = 0
    cs = np.zeros(3)
    cd = np.zeros(3)
    for i in range(src.shape[0]):
        if valid[i]:
            n += 1
            for r in range(3):
                cs[r] += src[i, r]
                cd[r] += dst[i, r]
    out = theta.copy()
    if n < 3:
        return out
    for r in range(3):
        cs[r] /= n
        cd[r] /= n
    S = np.zeros((3, 3))
    for i in range(src.shape[0]):
        if valid[i]:
            for r in range(3):
                a = src[i, r] - cs[r]
                for c in range(3):
                    S[r, c] += a * (dst[i, c] - cd[c])
    Sxx, Sxy, Sxz = S[0, 0], S[0, 1], S[0, 2]
    Syx, Syy, Syz = S[1, 0], S[1, 1], S[1, 2]
    Szx, Szy, Szz = S[2, 0], S[2, 1], S[2, 2]
    N = np.array([[Sxx + Syy + Szz, Syz - Szy, Szx - Sxz, Sxy - Syx],
                  [Syz - Szy, Sxx - Syy - Szz, Sxy + Syx, Szx + Sxz],
                  [Szx - Sxz, Sxy + Syx, -Sxx + Syy - Szz, Syz + Szy],
                  [Sxy - Syx, Szx + Sxz, Syz + Szy, -Sxx - Syy + Szz]])
    _, vecs = np.linalg.eigh(N)
    q = vecs[:, 3]
    nq = np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    w, x, y, z = q[0] / nq, q[1] / nq, q[2] / nq, q[3] / nq
    R = np.empty((3, 3))
    R[0, 0] = 1 - 2 * (y * y + z * z)
    R[0, 1] = 2 * (x * y - w * z)
    R[0, 2] = 2 * (x * z + w * y)
    R[1, 0] = 2 * (x * y + w * z)
    R[1, 1] = 1 - 2 * (x * x + z * z)
    R[1, 2] = 2 * (y * z - w * x)
    R[2, 0] = 2 * (x * z - w * y)
    R[2, 1] = 2 * (y * z + w * x)
    R[2, 2] = 1 - 2 * (x * x + y * y)
    t = np.empty(3)
    for r in range(3):
        t[r] = cd[r] - (R[r, 0] * cs[0] + R[r, 1] * cs[1] + R[r, 2] * cs[2])
    for r in range(3):
        out[r] = R[r, 0] * theta[0] + R[r, 1] * theta[1] + R[r, 2] * theta[2] + t[r]
    Rp = np.empty((3, 3))
    _euler_to_matrix(theta[3], theta[4], theta[5], Rp)
    Q = R @ Rp
    out[3] = np.arctan2(-Q[1, 2], Q[2, 2])
    out[4] = np.arcsin(min(max(Q[0, 2], -1.0), 1.0))
    out[5] = np.arctan2(-Q[0, 1], Q[0, 0])
    return out


# ----------------------------------------------------------------------------- subspaces
@njit(cache=True)
def _to_alpha(theta, M, mu, m, eye, alpha):
    n = theta.shape[0]
    for c in range(m):
        if eye:
            alpha[c] = theta[c] - mu[c]
        else:
            acc = 0.0
            for r in range(n):
                acc += (theta[r] - mu[r]) * M[r, c]
            alpha[c] = acc


@njit(cache=True)
def _to_theta(alpha, M, mu, m, eye, theta):
    n = theta.shape[0]
    for r in range(n):
        if eye:
            theta[r] = alpha[r] + mu[r]
        else:
            acc = 0.0
            for c in range(m):
                acc += alpha[c] * M[r, c]
            theta[r] = acc + mu[r]


@njit(cache=True)
def clamp_into(theta, M, mu, lo, hi, m, eye):
    """θ moved into the subspace, its coordinates clipped to the limits (:func:`tracker.icp.clamp`)."""
    alpha = np.empty(m)
    _to_alpha(theta, M, mu, m, eye, alpha)
    for c in range(m):
        alpha[c] = min(max(alpha[c], lo[c]), hi[c])
    out = np.empty(theta.shape[0])
    _to_theta(alpha, M, mu, m, eye, out)
    return out


# ----------------------------------------------------------------------------- moment sums
@njit(cache=True)
def node_moments(pt_node, pt_local, targets, w, G, n_nodes, mom):
    """Per node ``j`` the weighted moments of its pairs: ``l`` the model point in the node's frame,
    ``u`` the target relative to the node's origin at ``G`` (the reference frames): ``mom[j]`` =
    [Σw², Σw²l (3), Σw²u (3), Σw²uᵀu, Σw² l uᵀ (9, row-major), Σw² l lᵀ (6: xx yy zz xy xz yz)],
    w² scaled by 10⁶ (residuals in mm). Relative to the node's origin both ends are a few cm long, so
    the energy expanded from the moments keeps ~1e-10 mm² of its precision (relative to the camera,
    the targets' 0.75 m would cost six digits). The node's rotation is applied as the matrix it is,
    not assumed orthonormal: the model's rest frames are orthonormal to 1e-6 only."""
    for j in range(n_nodes):
        for k in range(mom.shape[1]):
            mom[j, k] = 0.0
    for i in range(pt_node.shape[0]):
        wi = w[i]
        if wi == 0.0 or np.isnan(targets[i, 0]):
            continue
        j = pt_node[i]
        w2 = wi * wi * MM * MM
        u0 = targets[i, 0] - G[j, 0, 3]
        u1 = targets[i, 1] - G[j, 1, 3]
        u2 = targets[i, 2] - G[j, 2, 3]
        l0, l1, l2 = pt_local[i, 0], pt_local[i, 1], pt_local[i, 2]
        mom[j, 0] += w2
        mom[j, 1] += w2 * l0
        mom[j, 2] += w2 * l1
        mom[j, 3] += w2 * l2
        mom[j, 4] += w2 * u0
        mom[j, 5] += w2 * u1
        mom[j, 6] += w2 * u2
        mom[j, 7] += w2 * (u0 * u0 + u1 * u1 + u2 * u2)
        mom[j, 8] += w2 * l0 * u0
        mom[j, 9] += w2 * l0 * u1
        mom[j, 10] += w2 * l0 * u2
        mom[j, 11] += w2 * l1 * u0
        mom[j, 12] += w2 * l1 * u1
        mom[j, 13] += w2 * l1 * u2
        mom[j, 14] += w2 * l2 * u0
        mom[j, 15] += w2 * l2 * u1
        mom[j, 16] += w2 * l2 * u2
        mom[j, 17] += w2 * l0 * l0
        mom[j, 18] += w2 * l1 * l1
        mom[j, 19] += w2 * l2 * l2
        mom[j, 20] += w2 * l0 * l1
        mom[j, 21] += w2 * l0 * l2
        mom[j, 22] += w2 * l1 * l2


@njit(cache=True)
def _relative(G, G0, j, A, b):
    """Node ``j``'s frame at ``G`` relative to its reference origin: A = R, b = o − o0."""
    for r in range(3):
        for c in range(3):
            A[r, c] = G[j, r, c]
        b[r] = G[j, r, 3] - G0[j, r, 3]


@njit(cache=True)
def moment_energy(G, G0, mom, A, b):
    """½ Σ w²‖A l + b − u‖² over all nodes (mm²) from the moments: per node
    ½(Σw²uᵀu + tr(A Σw²llᵀ Aᵀ) + W bᵀb + 2 bᵀA Σw²l − 2 bᵀΣw²u − 2 tr(A Σw² l uᵀ))."""
    E = 0.0
    for j in range(mom.shape[0]):
        W = mom[j, 0]
        if W == 0.0:
            continue
        _relative(G, G0, j, A, b)
        b0, b1, b2 = b[0], b[1], b[2]
        Al0 = A[0, 0] * mom[j, 1] + A[0, 1] * mom[j, 2] + A[0, 2] * mom[j, 3]
        Al1 = A[1, 0] * mom[j, 1] + A[1, 1] * mom[j, 2] + A[1, 2] * mom[j, 3]
        Al2 = A[2, 0] * mom[j, 1] + A[2, 1] * mom[j, 2] + A[2, 2] * mom[j, 3]
        # tr(A S) with S = Σ w² l uᵀ: Σ_rc A[r, c] S[c, r]
        tr = 0.0
        for r in range(3):
            for c in range(3):
                tr += A[r, c] * mom[j, 8 + 3 * c + r]
        S00, S11, S22 = mom[j, 17], mom[j, 18], mom[j, 19]
        S01, S02, S12 = mom[j, 20], mom[j, 21], mom[j, 22]
        q = 0.0
        for r in range(3):
            a0, a1, a2 = A[r, 0], A[r, 1], A[r, 2]
            q += (a0 * (a0 * S00 + 2.0 * (a1 * S01 + a2 * S02)) + a1 * (a1 * S11 + 2.0 * a2 * S12)
                  + a2 * a2 * S22)
        E += (mom[j, 7] + q + W * (b0 * b0 + b1 * b1 + b2 * b2) + 2.0 * (b0 * Al0 + b1 * Al1 + b2 * Al2)
              - 2.0 * (b0 * mom[j, 4] + b1 * mom[j, 5] + b2 * mom[j, 6]) - 2.0 * tr)
    return 0.5 * E


@njit(cache=True)
def _node_sums(G, G0, mom, j, A, b, P1, P2, X):
    """Node ``j``'s sums at the current frames, relative to its reference origin: Σw²p (P1),
    Σw²ppᵀ (P2), Σw² p×u (X) with p = A l + b; returns W."""
    _relative(G, G0, j, A, b)
    W = mom[j, 0]
    Sl0, Sl1, Sl2 = mom[j, 1], mom[j, 2], mom[j, 3]
    Al0 = A[0, 0] * Sl0 + A[0, 1] * Sl1 + A[0, 2] * Sl2
    Al1 = A[1, 0] * Sl0 + A[1, 1] * Sl1 + A[1, 2] * Sl2
    Al2 = A[2, 0] * Sl0 + A[2, 1] * Sl1 + A[2, 2] * Sl2
    P1[0] = Al0 + W * b[0]
    P1[1] = Al1 + W * b[1]
    P1[2] = Al2 + W * b[2]
    # Σw² l lᵀ (symmetric), then A·S·Aᵀ
    S00, S11, S22 = mom[j, 17], mom[j, 18], mom[j, 19]
    S01, S02, S12 = mom[j, 20], mom[j, 21], mom[j, 22]
    for r in range(3):
        a0, a1, a2 = A[r, 0], A[r, 1], A[r, 2]
        t0 = a0 * S00 + a1 * S01 + a2 * S02
        t1 = a0 * S01 + a1 * S11 + a2 * S12
        t2 = a0 * S02 + a1 * S12 + a2 * S22
        for c in range(r, 3):
            v = t0 * A[c, 0] + t1 * A[c, 1] + t2 * A[c, 2]
            Alr = Al0 if r == 0 else (Al1 if r == 1 else Al2)
            Alc = Al0 if c == 0 else (Al1 if c == 1 else Al2)
            v += Alr * b[c] + b[r] * Alc + W * b[r] * b[c]
            P2[r, c] = v
            P2[c, r] = v
    # U[r, c] = Σw² u_r p_c = (Σw² u lᵀ Aᵀ)[r, c] + Σw²u_r b_c ; mom[8 + 3k + r] = Σw² l_k u_r
    U00 = U01 = U02 = U10 = U11 = U12 = U20 = U21 = U22 = 0.0
    for k in range(3):
        m0, m1, m2 = mom[j, 8 + 3 * k], mom[j, 9 + 3 * k], mom[j, 10 + 3 * k]
        U00 += m0 * A[0, k]
        U01 += m0 * A[1, k]
        U02 += m0 * A[2, k]
        U10 += m1 * A[0, k]
        U11 += m1 * A[1, k]
        U12 += m1 * A[2, k]
        U20 += m2 * A[0, k]
        U21 += m2 * A[1, k]
        U22 += m2 * A[2, k]
    Su0, Su1, Su2 = mom[j, 4], mom[j, 5], mom[j, 6]
    U00 += Su0 * b[0]
    U01 += Su0 * b[1]
    U02 += Su0 * b[2]
    U10 += Su1 * b[0]
    U11 += Su1 * b[1]
    U12 += Su1 * b[2]
    U20 += Su2 * b[0]
    U21 += Su2 * b[1]
    U22 += Su2 * b[2]
    X[0] = U21 - U12
    X[1] = U02 - U20
    X[2] = U10 - U01
    return W


@njit(cache=True)
def moment_normal_equations(parents, dof_ptr, dof_idx, dof_types, mom, G0, G, wa, wo, Aa, ba, dids, sa, sk):
    """A = JᵀW²J and b = JᵀW²e (mm units, all DoF) from the moments at the frames ``G`` (with the DoF
    axes ``wa`` and origins ``wo`` of the same θ); returns the energy. Relative to one point c (the
    root's reference origin) every column of the Jacobian is c(p) = ã × p + k̃ (a rotation DoF: ã its
    axis, k̃ = −ã × (its origin − c); a translation: ã = 0, k̃ its axis), the same on every node the
    DoF moves. Then Σ_pairs c_a·c_b = z_aᵀ Q z_b with z = (ã, k̃) and
    Q = [[tr P2·I − P2, [P1]×], [−[P1]×, W·I]] (P1 = Σw²p, P2 = Σw²ppᵀ, W = Σw² over the pairs both
    DoFs move), and Σ_pairs c_a·(u − p) = ã·X + k̃·(Σw²u − P1) with X = Σw² p×u. These sums are linear,
    so they are summed once per subtree (parents come before their children): DoFs a and b, a on b's
    node or an ancestor, share exactly the pairs of b's subtree. Per node the sums are formed relative
    to its own reference origin (a few cm: the moments' precision) and then moved to c. ``dids``,
    ``sa``, ``sk``: scratch of n rows."""
    n = Aa.shape[0]
    for r in range(n):
        ba[r] = 0.0
        for c in range(n):
            Aa[r, c] = 0.0
    N = mom.shape[0]
    A = np.empty((3, 3))
    b = np.empty(3)
    P1 = np.empty(3)
    P2 = np.empty((3, 3))
    X = np.empty(3)
    Q = np.empty((6, 6))
    y = np.empty(6)
    # the same expression as every trial step's energy: step halving compares like with like
    E = moment_energy(G, G0, mom, A, b)
    c0, c1, c2 = G0[0, 0, 3], G0[0, 1, 3], G0[0, 2, 3]
    # per node, relative to c: W, P1 (3), P2 (9), X (3), r = Σw²u − P1 (3)
    S = np.zeros((N, 19))
    for j in range(N):
        W = mom[j, 0]
        if W == 0.0:
            continue
        _node_sums(G, G0, mom, j, A, b, P1, P2, X)
        d0, d1, d2 = G0[j, 0, 3] - c0, G0[j, 1, 3] - c1, G0[j, 2, 3] - c2
        Su0, Su1, Su2 = mom[j, 4], mom[j, 5], mom[j, 6]
        S[j, 0] = W
        S[j, 1] = P1[0] + W * d0
        S[j, 2] = P1[1] + W * d1
        S[j, 3] = P1[2] + W * d2
        dd = (d0, d1, d2)
        for r in range(3):
            for c in range(3):
                S[j, 4 + 3 * r + c] = P2[r, c] + P1[r] * dd[c] + dd[r] * P1[c] + W * dd[r] * dd[c]
        # Σw² (p + d) × (u + d) = X + P1 × d + d × Σw²u
        S[j, 13] = X[0] + (P1[1] * d2 - P1[2] * d1) + (d1 * Su2 - d2 * Su1)
        S[j, 14] = X[1] + (P1[2] * d0 - P1[0] * d2) + (d2 * Su0 - d0 * Su2)
        S[j, 15] = X[2] + (P1[0] * d1 - P1[1] * d0) + (d0 * Su1 - d1 * Su0)
        S[j, 16] = Su0 - P1[0]
        S[j, 17] = Su1 - P1[1]
        S[j, 18] = Su2 - P1[2]
    for k in range(N - 1, 0, -1):
        p = parents[k]
        if p >= 0:
            for q in range(19):
                S[p, q] += S[k, q]
    # every DoF's column z = (ã, k̃) relative to c
    for k in range(N):
        for q in range(dof_ptr[k], dof_ptr[k + 1]):
            d = dof_idx[q]
            a0, a1, a2 = wa[d, 0], wa[d, 1], wa[d, 2]
            if dof_types[d] == 1:
                sa[d, 0] = 0.0
                sa[d, 1] = 0.0
                sa[d, 2] = 0.0
                sk[d, 0] = a0
                sk[d, 1] = a1
                sk[d, 2] = a2
            else:
                o0, o1, o2 = wo[d, 0] - c0, wo[d, 1] - c1, wo[d, 2] - c2
                sa[d, 0] = a0
                sa[d, 1] = a1
                sa[d, 2] = a2
                sk[d, 0] = -(a1 * o2 - a2 * o1)
                sk[d, 1] = -(a2 * o0 - a0 * o2)
                sk[d, 2] = -(a0 * o1 - a1 * o0)
    for kb in range(N):
        W = S[kb, 0]
        if dof_ptr[kb] == dof_ptr[kb + 1] or W == 0.0:
            continue
        trP = S[kb, 4] + S[kb, 8] + S[kb, 12]
        for r in range(3):
            for c in range(3):
                Q[r, c] = -S[kb, 4 + 3 * r + c]
                Q[r + 3, c + 3] = 0.0
            Q[r, r] += trP
            Q[r + 3, r + 3] = W
        p0, p1, p2 = S[kb, 1], S[kb, 2], S[kb, 3]
        Q[0, 3], Q[0, 4], Q[0, 5] = 0.0, -p2, p1
        Q[1, 3], Q[1, 4], Q[1, 5] = p2, 0.0, -p0
        Q[2, 3], Q[2, 4], Q[2, 5] = -p1, p0, 0.0
        for r in range(3):
            for c in range(3):
                Q[c + 3, r] = Q[r, c + 3]
        for qb in range(dof_ptr[kb], dof_ptr[kb + 1]):
            db = dof_idx[qb]
            zb = (sa[db, 0], sa[db, 1], sa[db, 2], sk[db, 0], sk[db, 1], sk[db, 2])
            for r in range(6):
                acc = 0.0
                for c in range(6):
                    acc += Q[r, c] * zb[c]
                y[r] = acc
            ba[db] = (zb[0] * S[kb, 13] + zb[1] * S[kb, 14] + zb[2] * S[kb, 15]
                      + zb[3] * S[kb, 16] + zb[4] * S[kb, 17] + zb[5] * S[kb, 18])
            # the DoFs on b's node (up to b) and on its ancestors share b's subtree's pairs
            k = kb
            while k >= 0:
                last = qb + 1 if k == kb else dof_ptr[k + 1]
                for qa in range(dof_ptr[k], last):
                    da = dof_idx[qa]
                    v = (sa[da, 0] * y[0] + sa[da, 1] * y[1] + sa[da, 2] * y[2]
                         + sk[da, 0] * y[3] + sk[da, 1] * y[4] + sk[da, 2] * y[5])
                    Aa[da, db] = v
                    Aa[db, da] = v
                k = parents[k]
    return E


@njit(cache=True)
def project_normal_equations(A, b, eye, nz_ptr, nz_row, nz_val, Aa, ba, T):
    """MᵀAM and Mᵀb into ``Aa``/``ba`` (``T``: ``(m, n)`` scratch) for the subspace basis M given by its non-zeros per column
    (column ``c``: rows ``nz_row[nz_ptr[c]:nz_ptr[c+1]]``, values ``nz_val``); the identity copies.
    A synergy basis is sparse (pose columns one entry; a PC column zero on the pose rows), so this
    costs a fraction of the dense product."""
    m = Aa.shape[0]
    n = A.shape[0]
    if eye:
        for r in range(m):
            ba[r] = b[r]
            for c in range(m):
                Aa[r, c] = A[r, c]
        return
    # T = (A M)ᵀ row by row: A is symmetric, so each term adds a row of A (contiguous, vectorised)
    for e in range(m):
        for r in range(n):
            T[e, r] = 0.0
        for q in range(nz_ptr[e], nz_ptr[e + 1]):
            l = nz_row[q]
            v = nz_val[q]
            for r in range(n):
                T[e, r] += A[l, r] * v
    for c in range(m):
        acc = 0.0
        for q in range(nz_ptr[c], nz_ptr[c + 1]):
            acc += nz_val[q] * b[nz_row[q]]
        ba[c] = acc
        for e in range(c, m):
            acc = 0.0
            for q in range(nz_ptr[c], nz_ptr[c + 1]):
                acc += nz_val[q] * T[e, nz_row[q]]
            Aa[c, e] = acc
            Aa[e, c] = acc


@njit(cache=True)
def moment_energy_at(theta, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes, mom, G0, G, wa, wo, A, b):
    """½ Σ w² r² (mm²) at θ from the moments (leaves θ's frames in G)."""
    fk_single(theta, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes, G, wa, wo)
    return moment_energy(G, G0, mom, A, b)


# ----------------------------------------------------------------------------- one stage's Gauss-Newton
@njit(cache=True)
def solve_stage_moments(theta0, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes, mom, G0,
                        M, mu, m, lo, hi, damp, eye, iters, max_halvings, tol, limit_avoid, clamp, margin, stats):
    """Damped Gauss-Newton in one subspace on the moments: the steps of
    :func:`handmodel._solver_kernels.solve_stages` (selective and Chan–Dubey damping, the active set
    at the limits, clamping, step halving until the energy drops, the same stopping rules) for a single
    stage. Adds the steps taken to ``stats[0]``, a step that failed to lower the energy after
    ``max_halvings`` halvings (it ends the stage) to ``stats[1]`` and the trial steps' energy
    evaluations to ``stats[2]``. Returns θ."""
    n = dof_axes.shape[0]
    N = parents.shape[0]
    G = np.empty((N, 4, 4))
    wa = np.empty((n, 3))
    wo = np.empty((n, 3))
    A3 = np.empty((3, 3))
    b3 = np.empty(3)
    Aa = np.empty((m, m))
    ba = np.empty(m)
    L = np.empty((m, m))
    delta = np.empty(m)
    alpha = np.empty(m)
    a_new = np.empty(m)
    g_prev = np.empty(m)
    th_new = np.empty(n)
    dids = np.empty(n, np.int64)
    sa = np.empty((n, 3))
    sk = np.empty((n, 3))
    A = np.empty((n, n))
    b = np.empty(n)
    T = np.empty((m, n))
    # the basis' non-zeros per column
    nz_ptr = np.zeros(m + 1, np.int64)
    for c in range(m):
        cnt = 0
        for r in range(n):
            if not eye and M[r, c] != 0.0:
                cnt += 1
        nz_ptr[c + 1] = nz_ptr[c] + cnt
    nz_row = np.empty(nz_ptr[m], np.int64)
    nz_val = np.empty(nz_ptr[m])
    q = 0
    for c in range(m):
        for r in range(n):
            if not eye and M[r, c] != 0.0:
                nz_row[q] = r
                nz_val[q] = M[r, c]
                q += 1
    theta = theta0.copy()
    _to_alpha(theta, M, mu, m, eye, alpha)
    if not eye:
        _to_theta(alpha, M, mu, m, eye, theta)
    for c in range(m):
        g_prev[c] = _limit_grad(alpha[c], lo[c], hi[c])
    # G, wa, wo hold θ's frames: computed here, then left by the energy of each accepted step
    fk_single(theta, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes, G, wa, wo)
    for it in range(iters):
        E = moment_normal_equations(parents, dof_ptr, dof_idx, dof_types, mom, G0, G, wa, wo, A, b, dids, sa, sk)
        project_normal_equations(A, b, eye, nz_ptr, nz_row, nz_val, Aa, ba, T)
        for c in range(m):
            lam = damp[c]
            if limit_avoid:
                g = _limit_grad(alpha[c], lo[c], hi[c])
                if g > g_prev[c]:
                    lam *= 1.0 + min(g, 1e12)
                g_prev[c] = g
            Aa[c, c] += lam
        if clamp:
            freeze_at_limits(Aa, ba, alpha, lo, hi, m, margin)
        if not cholesky_solve(Aa, ba, delta, L):
            tr = 0.0
            for c in range(m):
                tr += Aa[c, c]
            for c in range(m):
                Aa[c, c] += 1e-9 * tr / m + 1e-12
            if not cholesky_solve(Aa, ba, delta, L):
                break
        if converged(delta, ba, m, E, tol):
            break
        accepted = False
        step = 1.0
        E_new = E
        for h in range(max_halvings + 1):
            for c in range(m):
                v = alpha[c] + step * delta[c]
                if clamp:
                    vlo = lo[c] + margin
                    vhi = hi[c] - margin
                    if v < vlo:
                        v = vlo
                    elif v > vhi:
                        v = vhi
                a_new[c] = v
            _to_theta(a_new, M, mu, m, eye, th_new)
            E_new = moment_energy_at(th_new, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes, mom, G0, G, wa,
                                     wo, A3, b3)
            stats[2] += 1
            if E_new < E:
                accepted = True
                break
            step *= 0.5
        if not accepted:
            stats[1] += 1
            break
        stats[0] += 1
        big = 0.0
        for c in range(m):
            alpha[c] = a_new[c]
            big = max(big, abs(step * delta[c]))
        for r in range(n):
            theta[r] = th_new[r]
        if E - E_new <= tol * E or E_new < 1e-18 or big < 1e-10:
            break
    return theta


# ----------------------------------------------------------------------------- the fit
@njit(cache=True)
def pairs_moved(G0, G, pt_node, pt_local, k):
    """How far (m) the first ``k`` pairs' model points (``pt_local`` in their nodes' frames) lie at the
    frames ``G`` from where they lay at ``G0``: the largest distance."""
    big = 0.0
    for i in range(k):
        j = pt_node[i]
        l0, l1, l2 = pt_local[i, 0], pt_local[i, 1], pt_local[i, 2]
        d2 = 0.0
        for r in range(3):
            a = ((G[j, r, 0] - G0[j, r, 0]) * l0 + (G[j, r, 1] - G0[j, r, 1]) * l1 + (G[j, r, 2] - G0[j, r, 2]) * l2
                 + G[j, r, 3] - G0[j, r, 3])
            d2 += a * a
        big = max(big, d2)
    return np.sqrt(big)


@njit(cache=True)
def matches_moved(G0, G, model, node, valid):
    """:func:`pairs_moved` for the valid matched model points ``model`` (camera frame, on ``node``'s
    surface at the frames ``G0``)."""
    big = 0.0
    for i in range(model.shape[0]):
        if not valid[i]:
            continue
        j = node[i]
        d0 = model[i, 0] - G0[j, 0, 3]
        d1 = model[i, 1] - G0[j, 1, 3]
        d2 = model[i, 2] - G0[j, 2, 3]
        l0 = G0[j, 0, 0] * d0 + G0[j, 1, 0] * d1 + G0[j, 2, 0] * d2
        l1 = G0[j, 0, 1] * d0 + G0[j, 1, 1] * d1 + G0[j, 2, 1] * d2
        l2 = G0[j, 0, 2] * d0 + G0[j, 1, 2] * d1 + G0[j, 2, 2] * d2
        q = 0.0
        for r in range(3):
            a = G[j, r, 0] * l0 + G[j, r, 1] * l1 + G[j, r, 2] * l2 + G[j, r, 3] - model[i, r]
            q += a * a
        big = max(big, q)
    return np.sqrt(big)


@njit(cache=True)
def _solve_pairs(theta, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes, mom, G0, M, mu, m, lo, hi, damp, eye,
                 gn_iters, max_halvings, tol, limit_avoid, clamp, margin, point_to_plane, moments, pt_node, pt_local,
                 tgt, w, plane, k, mmax, st_m1, stats):
    """One stage's damped Gauss-Newton on fixed pairs: on their moments ``mom`` (reference frames
    ``G0``) or, with ``point_to_plane`` or without ``moments``, pair by pair. Returns θ."""
    n = dof_axes.shape[0]
    if moments and not point_to_plane:
        return solve_stage_moments(theta, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes, mom, G0,
                                   M[:, :m], mu, m, lo[:m], hi[:m], damp[:m], eye, gn_iters, max_halvings,
                                   tol, limit_avoid, clamp, margin, stats)
    ident = eye
    for r in range(n):
        if mu[r] != 0.0:
            ident = False
    tr = np.full(gn_iters + 1, np.nan)
    th, _, _ = solve_stages(theta, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes,
                            pt_node, pt_local, tgt, w, plane[:k] if point_to_plane else plane,
                            M.reshape((1, n, mmax)), mu.reshape((1, n)), st_m1,
                            lo.reshape((1, mmax)), hi.reshape((1, mmax)), damp.reshape((1, mmax)),
                            np.full(1, gn_iters, np.int64), np.full(1, ident), max_halvings, tol,
                            limit_avoid, clamp, margin, tr)
    return th


@njit(cache=True, nogil=True)
def fit_kernel(theta0, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes,
               seg_node, seg_shape, seg_len, seg_r0, seg_r1, seg_th,
               points, normals, cam, facing_only, reject, agreement, n_rigid, local_m,
               st_M, st_mu, st_m, st_lo, st_hi, st_damp, st_eye, st_entry, st_local, pose_mask,
               pr_on, pr_M, pr_mu, pr_m, pr_lo, pr_hi, pr_eye,
               gn_iters, max_halvings, tol, limit_avoid, clamp, margin, robust_mm, point_to_plane, moments,
               sil_on, sm_nodes, sm_local, sm_local_n, fx, fy, cx, cy, dist, iv, iu, depth, v0, u0, tol_px,
               sil_weight, wl_on, wl_node, wl_local, wl_normal, wl_share, wl_free,
               out_p, out_n, out_seg, out_d, out_node, out_valid, stats):
    """One ICP fit (:func:`tracker.icp.fit_reference`'s loop): ``n_rigid`` rigid steps, then per stage
    correspondences at θ, θ moved into the stage's subspace, the pairs (Cauchy-weighted data pairs and
    silhouette pairs) and one damped Gauss-Newton solve; at the end the correspondences at the result
    (in the ``out_*`` arrays). A stage with ``st_local`` takes a local pass (:func:`match_same`: each
    point stays on the primitive it was matched to; the silhouette pairs of the stage before are
    kept) instead of the search over every primitive while the model moved less than ``local_m`` (m;
    :func:`pairs_moved`) since the pass before. ``wl_on``: one more pair, the point ``wl_local`` of node
    ``wl_node`` (the wrist crease) to its closest point on the plane through the camera centre with unit
    normal ``wl_normal`` (the arm's centre line), weighing like ``wl_share`` × the valid data pairs, when
    it lies more than ``wl_free`` (m) from the plane (its target then that far from the plane; else no pair).
    ``moments``: Gauss-Newton on moment sums (point-to-point only), else the per-pair solver; the
    moment path adds its steps taken and failed to ``stats`` (see :func:`solve_stage_moments`), every
    closest-point pass adds 1 to ``stats[3]``, every local pass to ``stats[4]``. Returns θ."""
    n = dof_axes.shape[0]
    N = parents.shape[0]
    P = points.shape[0]
    G = np.empty((N, 4, 4))
    wa = np.empty((n, 3))
    wo = np.empty((n, 3))
    n_s = sm_nodes.shape[0] if sil_on else 0
    n_x = n_s + (1 if wl_on else 0)
    pt_node = np.empty(P + n_x, np.int64)
    pt_local = np.empty((P + n_x, 3))
    tgt = np.empty((P + n_x, 3))
    w = np.empty(P + n_x)
    plane = np.zeros((P + n_x if point_to_plane else 0, 3))
    s_nodes = np.empty(n_s, np.int64)
    s_local = np.empty((n_s, 3))
    s_tgt = np.empty((n_s, 3))
    mom = np.empty((N, 23))
    theta = theta0.copy()
    nv = 0
    for _ in range(n_rigid):
        fk_single(theta, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes, G, wa, wo)
        nv = match(G, seg_node, seg_shape, seg_len, seg_r0, seg_r1, seg_th, points, normals, cam, facing_only, reject,
                   agreement, out_p, out_n, out_seg, out_d, out_node, out_valid)
        stats[3] += 1
        theta = rigid_update(theta, out_p, points, out_valid)
    mmax = st_M.shape[2]
    # θ's frames at a stage's start (G keeps those of the pass before until the test below)
    G1 = np.empty((N, 4, 4))
    k = -1
    ns = 0
    have_sil = False
    for s in range(st_M.shape[0]):
        fk_single(theta, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes, G1, wa, wo)
        # a local pass while the model moved less than local_m since the pass before (the stage
        # before's pairs, or the last rigid step's matches at the frames G it matched at)
        local = st_local[s] and local_m > 0.0 and (k >= 0 or (n_rigid > 0 and nv >= 3))
        if local:
            moved = pairs_moved(G, G1, pt_node, pt_local, k) if k >= 0 else matches_moved(G, G1, out_p, out_node,
                                                                                          out_valid)
            local = moved < local_m
        for q in range(N):
            G[q] = G1[q]
        if local:
            nv = match_same(G, seg_node, seg_shape, seg_len, seg_r0, seg_r1, seg_th, points, normals, cam,
                            facing_only, reject, agreement, out_p, out_n, out_seg, out_d, out_node, out_valid)
            stats[4] += 1
        else:
            nv = match(G, seg_node, seg_shape, seg_len, seg_r0, seg_r1, seg_th, points, normals, cam, facing_only,
                       reject, agreement, out_p, out_n, out_seg, out_d, out_node, out_valid)
            stats[3] += 1
        if nv < 3:
            break
        m = st_m[s]
        M = st_M[s]
        mu = st_mu[s].copy()
        lo = st_lo[s].copy()
        hi = st_hi[s].copy()
        if st_entry[s] == ENTRY_THROUGH:
            # the same directions through θ; θ itself is always admitted (see tracker.icp.through)
            a = np.empty(m)
            _to_alpha(theta, M, mu, m, st_eye[s], a)
            for r in range(n):
                mu[r] = 0.0 if pose_mask[r] else theta[r]
            for c in range(m):
                lo[c] = min(lo[c] - a[c], 0.0)
                hi[c] = max(hi[c] - a[c], 0.0)
        elif st_entry[s] == ENTRY_CLAMP:
            theta = clamp_into(theta, M, mu, lo, hi, m, st_eye[s])
        eye = st_eye[s]
        fk_single(theta, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes, G, wa, wo)
        k = 0
        for i in range(P):
            if not out_valid[i]:
                continue
            j = out_node[i]
            d0 = out_p[i, 0] - G[j, 0, 3]
            d1 = out_p[i, 1] - G[j, 1, 3]
            d2 = out_p[i, 2] - G[j, 2, 3]
            pt_node[k] = j
            for r in range(3):
                pt_local[k, r] = G[j, 0, r] * d0 + G[j, 1, r] * d1 + G[j, 2, r] * d2
                tgt[k, r] = points[i, r]
            if robust_mm > 0.0:
                q = out_d[i] * 1000.0 / robust_mm
                w[k] = 1.0 / np.sqrt(1.0 + q * q)
            else:
                w[k] = 1.0
            if point_to_plane:
                for r in range(3):
                    plane[k, r] = out_n[i, r]
            k += 1
        if sil_on:
            if not (local and have_sil):
                # a local pass keeps the silhouette pairs of the pass before too
                ns = silhouette_pairs_kernel(G, sm_nodes, sm_local, sm_local_n, fx, fy, cx, cy, dist, iv, iu, depth,
                                             v0, u0, tol_px, s_nodes, s_local, s_tgt)
                have_sil = True
            # weight per pair so the term counts like the data term per unit area
            ws = sil_weight * np.sqrt(max(nv, 1) / max(n_s, 1))
            for q in range(ns):
                pt_node[k] = s_nodes[q]
                for r in range(3):
                    pt_local[k, r] = s_local[q, r]
                    tgt[k, r] = s_tgt[q, r]
                    if point_to_plane:
                        plane[k, r] = 0.0
                w[k] = ws
                k += 1
        if wl_on:
            c = np.empty(3)
            for r in range(3):
                c[r] = (G[wl_node, r, 0] * wl_local[0] + G[wl_node, r, 1] * wl_local[1]
                        + G[wl_node, r, 2] * wl_local[2] + G[wl_node, r, 3])
            off = c[0] * wl_normal[0] + c[1] * wl_normal[1] + c[2] * wl_normal[2]
            if abs(off) > wl_free:
                off -= wl_free if off > 0.0 else -wl_free
                pt_node[k] = wl_node
                for r in range(3):
                    pt_local[k, r] = wl_local[r]
                    tgt[k, r] = c[r] - off * wl_normal[r]
                    if point_to_plane:
                        plane[k, r] = 0.0
                w[k] = np.sqrt(wl_share * nv)
                k += 1
        if moments and not point_to_plane:
            node_moments(pt_node[:k], pt_local[:k], tgt[:k], w[:k], G, N, mom)
        theta = _solve_pairs(theta, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes, mom, G, M, mu, m, lo, hi,
                             st_damp[s], eye, gn_iters, max_halvings, tol, limit_avoid, clamp, margin, point_to_plane,
                             moments, pt_node[:k], pt_local[:k], tgt[:k], w[:k], plane, k, mmax, st_m[s:s + 1], stats)
        if pr_on[s]:
            theta = clamp_into(theta, pr_M[s], pr_mu[s], pr_lo[s], pr_hi[s], pr_m[s], pr_eye[s])
    fk_single(theta, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes, G, wa, wo)
    match(G, seg_node, seg_shape, seg_len, seg_r0, seg_r1, seg_th, points, normals, cam, facing_only, reject,
          agreement, out_p, out_n, out_seg, out_d, out_node, out_valid)
    stats[3] += 1
    return theta


# ----------------------------------------------------------------------------- per-frame helpers of the tracker
@njit(cache=True)
def pose_samples(theta, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes, nodes, local, local_n, P, N):
    """Model surface samples stored in their nodes' frames (:class:`tracker.correspond.ModelSamples`)
    posed at θ: points into ``P``, normals into ``N`` (what ``ModelSamples.pose`` returns)."""
    G = np.empty((parents.shape[0], 4, 4))
    wa = np.empty((dof_axes.shape[0], 3))
    wo = np.empty((dof_axes.shape[0], 3))
    fk_single(theta, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes, G, wa, wo)
    for i in range(nodes.shape[0]):
        j = nodes[i]
        l0, l1, l2 = local[i, 0], local[i, 1], local[i, 2]
        n0, n1, n2 = local_n[i, 0], local_n[i, 1], local_n[i, 2]
        for r in range(3):
            P[i, r] = G[j, r, 0] * l0 + G[j, r, 1] * l1 + G[j, r, 2] * l2 + G[j, r, 3]
            N[i, r] = G[j, r, 0] * n0 + G[j, r, 1] * n1 + G[j, r, 2] * n2


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
        if dims[0] * dims[1] * dims[2] <= 1 << 20:
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
    lo, dims, cell, start, order = _grid(model, ok, max(radius, 1e-9))
    n_near = 0
    for i in range(P):
        if np.isfinite(points[i, 0]) and np.isfinite(points[i, 1]) and np.isfinite(points[i, 2]):
            if _any_within(points[i], model, lo, dims, cell, start, order, r2):
                near[i] = True
                n_near += 1
    if n_near < max(min_points, 1):
        return False
    lo, dims, cell, start, order = _grid(points, near, max(radius, 1e-9))
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
    ``shift`` (what :meth:`tracker.track.HandTracker._recentred` compares with the rejection radius);
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


@njit(cache=True)
def feature_transform(mask, dist, iv, iu):
    """The exact Euclidean distance of every pixel to the nearest ``mask`` pixel (0 on the mask) into
    ``dist`` and that pixel's row and column into ``iv``/``iu``: what
    ``scipy.ndimage.distance_transform_edt(~mask, return_indices=True)`` returns (the same distances;
    of several equally near mask pixels either may be named), in two separable passes (Felzenszwalb &
    Huttenlocher 2012: per column the nearest mask pixel, then per row the lower envelope of the
    parabolas). Returns False (outputs unset) when the mask is empty. Every tracked frame builds its
    silhouette's transform; scipy's takes ~4× as long."""
    H, W = mask.shape
    # per column: the nearest mask pixel's row (−1: none; the upper one on ties, as scipy's)
    gr = np.empty((H, W), np.int32)
    if not nearest_rows(mask, gr):
        return False
    # per row: the lower envelope of u ↦ (u − q)² + (v − gr[v, q])² over the columns q with a mask pixel
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
            while k >= 0:
                s = (fq - fs[k]) / (2.0 * (q - cols[k]))
                if s <= zs[k]:
                    k -= 1
                else:
                    break
            k += 1
            cols[k] = q
            fs[k] = fq
            zs[k] = -np.inf if k == 0 else (fq - fs[k - 1]) / (2.0 * (q - cols[k - 1]))
            zs[k + 1] = np.inf
        j = 0
        for u in range(W):
            while zs[j + 1] < u:
                j += 1
            q = cols[j]
            rv = gr[v, q]
            du = u - q
            dv = v - rv
            dist[v, u] = np.sqrt(float(du * du + dv * dv))
            iv[v, u] = rv
            iu[v, u] = q
    return True


@njit(cache=True, nogil=True)
def model_to_data_mean(theta, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes, nodes, local, fx, fy, cx, cy,
                       dist, depth, v0, u0, tolerance_mm, tolerance_px, cap_mm):
    """The mean over the samples of :func:`tracker.correspond.model_to_data_mm` (the model→data part
    of :func:`tracker.init.score`) at θ, the samples posed here: the same per-sample costs, summed in
    order (numpy's mean sums pairwise: equal to ~1e-15 relative)."""
    if nodes.shape[0] == 0:
        return np.nan
    G = np.empty((parents.shape[0], 4, 4))
    wa = np.empty((dof_axes.shape[0], 3))
    wo = np.empty((dof_axes.shape[0], 3))
    fk_single(theta, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes, G, wa, wo)
    return _model_to_data_at(G, nodes, local, fx, fy, cx, cy, dist, depth, v0, u0, tolerance_mm, tolerance_px, cap_mm)


@njit(cache=True, inline="always")
def _model_to_data_at(G, nodes, local, fx, fy, cx, cy, dist, depth, v0, u0, tolerance_mm, tolerance_px, cap_mm):
    """:func:`model_to_data_mean` with the samples' node frames ``G`` given."""
    n = nodes.shape[0]
    if n == 0:
        return np.nan
    h, w = dist.shape
    H, W = depth.shape
    total = 0.0
    for i in range(n):
        j = nodes[i]
        l0, l1, l2 = local[i, 0], local[i, 1], local[i, 2]
        x = G[j, 0, 0] * l0 + G[j, 0, 1] * l1 + G[j, 0, 2] * l2 + G[j, 0, 3]
        y = G[j, 1, 0] * l0 + G[j, 1, 1] * l1 + G[j, 1, 2] * l2 + G[j, 1, 3]
        z = G[j, 2, 0] * l0 + G[j, 2, 1] * l1 + G[j, 2, 2] * l2 + G[j, 2, 3]
        if not z > 1e-3:
            total += cap_mm
            continue
        u = int(np.rint(fx * x / z + cx))
        v = int(np.rint(fy * y / z + cy))
        uu = min(max(u - u0, 0), w - 1)
        vv = min(max(v - v0, 0), h - 1)
        d_px = dist[vv, uu] + np.hypot(float(u - u0 - uu), float(v - v0 - vv))
        if d_px > 0:
            cost = max(d_px - tolerance_px, 0.0) * z / fx * 1000.0
        elif u >= 0 and u < W and v >= 0 and v < H:
            zo = depth[v, u]
            cost = max((zo - z) * 1000.0 - tolerance_mm, 0.0) if np.isfinite(zo) else 0.0
        else:
            cost = 0.0
        total += min(cost, cap_mm)
    return total / n


@njit(cache=True, inline="always")
def wrist_cost_at(G, point, direction, reach_mm, turn_mm):
    """:func:`tracker.wrist.wrist_cost_mm` with the hand's node frames ``G`` (keypoints 0, the wrist, and
    9, the middle finger's base, are nodes 0 and 9's origins): the same operations in order."""
    w0, w1, w2 = G[0, 0, 3], G[0, 1, 3], G[0, 2, 3]
    if w2 <= 1e-3:
        return reach_mm + 1.5 * turn_mm
    far = np.hypot(w0 / w2 - point[0] / point[2], w1 / w2 - point[1] / point[2]) * point[2] * 1000.0
    cost = max(far - reach_mm, 0.0)
    a0, a1 = direction[0], direction[1]
    f0, f1 = G[9, 0, 3] - w0, G[9, 1, 3] - w1
    na = np.sqrt(a0 * a0 + a1 * a1)
    nf = np.sqrt(f0 * f0 + f1 * f1)
    if na > 0.3 and nf > 1e-6:
        cost += turn_mm * max((a0 * f0 + a1 * f1) / (na * nf), 0.0)
    return cost


@njit(cache=True, inline="always")
def _pairwise_block(a, lo, n):
    """numpy's pairwise sum of ``a[lo:lo + n]`` for n ≤ 128: in order below 8, else 8 accumulators."""
    if n < 8:
        res = 0.0
        for i in range(lo, lo + n):
            res += a[i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    m = n - n % 8
    while i < m:
        r0 += a[lo + i]
        r1 += a[lo + i + 1]
        r2 += a[lo + i + 2]
        r3 += a[lo + i + 3]
        r4 += a[lo + i + 4]
        r5 += a[lo + i + 5]
        r6 += a[lo + i + 6]
        r7 += a[lo + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@njit(cache=True)
def pairwise_sum(a, lo, n):
    """``np.add.reduce(a[lo:lo + n])`` for float64 ``a`` as numpy sums it: blocks of up to 128 (see
    :func:`_pairwise_block`), longer runs split in halves (a multiple of 8 first) and the halves' sums
    added — the same bits, so a compiled mean ranks fits exactly as numpy's did. The halving runs on an
    explicit stack: a recursive function in numba's cache leaves its callers an unresolved symbol."""
    if n <= 128:
        return _pairwise_block(a, lo, n)
    s_lo = np.empty(64, np.int64)
    s_n = np.empty(64, np.int64)
    s_st = np.empty(64, np.int64)
    vals = np.empty(66)
    sp, vp = 1, 0
    s_lo[0], s_n[0], s_st[0] = lo, n, 0
    while sp > 0:
        t = sp - 1
        m = s_n[t]
        if m <= 128:
            vals[vp] = _pairwise_block(a, s_lo[t], m)
            vp += 1
            sp -= 1
            continue
        n2 = m // 2
        n2 -= n2 % 8
        if s_st[t] == 0:  # the first half
            s_st[t] = 1
            s_lo[sp], s_n[sp], s_st[sp] = s_lo[t], n2, 0
            sp += 1
        elif s_st[t] == 1:  # the second half
            s_st[t] = 2
            s_lo[sp], s_n[sp], s_st[sp] = s_lo[t] + n2, m - n2, 0
            sp += 1
        else:  # both halves summed: their sum replaces them
            vals[vp - 2] = vals[vp - 2] + vals[vp - 1]
            vp -= 1
            sp -= 1
    return vals[0]


@njit(cache=True, nogil=True)
def data_cost_mean(G, seg_node, seg_shape, seg_len, seg_r0, seg_r1, seg_th, points, valid, rejected_mm, cap_mm):
    """:func:`tracker.init.data_cost_mm` on the capsule model posed by the node frames ``G``, in one
    call: each point's distance (mm) to the nearest surface on any side, ``rejected_mm`` more where its
    pair was rejected (``valid`` False), capped at ``cap_mm``; their mean, summed as numpy sums."""
    P = points.shape[0]
    if P == 0:
        return cap_mm
    out_p = np.empty((P, 3))
    out_n = np.empty((P, 3))
    out_seg = np.empty(P, np.int64)
    out_d = np.empty(P)
    closest_points_facing(G, seg_node, seg_shape, seg_len, seg_r0, seg_r1, seg_th, points, np.zeros(3), False,
                          out_p, out_n, out_seg, out_d)
    for i in range(P):
        d = out_d[i] * 1000.0 if np.isfinite(out_d[i]) else cap_mm
        d = min(d, cap_mm)
        if not valid[i]:
            d = d + rejected_mm
        out_d[i] = min(d, cap_mm)
    return pairwise_sum(out_d, 0, P) / P


@njit(cache=True, nogil=True)
def search_score(theta, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes,
                 seg_node, seg_shape, seg_len, seg_r0, seg_r1, seg_th, points, valid, rejected_mm, data_cap_mm,
                 m2d_on, m2d_weight, nodes, local, fx, fy, cx, cy, dist, depth, v0, u0, tolerance_mm, tolerance_px,
                 m2d_cap_mm, cue_on, cue_point, cue_direction, reach_mm, turn_mm):
    """:func:`tracker.init.score` in one call, for a hand whose matcher, score samples and wrist cue all
    pose the same model: θ posed once, the data term (:func:`data_cost_mean`), ``m2d_weight`` × the
    model→data mean when ``m2d_on``, the wrist cue's cost when ``cue_on``, added in that order."""
    G = np.empty((parents.shape[0], 4, 4))
    wa = np.empty((dof_axes.shape[0], 3))
    wo = np.empty((dof_axes.shape[0], 3))
    fk_single(theta, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes, G, wa, wo)
    s = data_cost_mean(G, seg_node, seg_shape, seg_len, seg_r0, seg_r1, seg_th, points, valid, rejected_mm, data_cap_mm)
    if m2d_on:
        s += m2d_weight * _model_to_data_at(G, nodes, local, fx, fy, cx, cy, dist, depth, v0, u0, tolerance_mm,
                                            tolerance_px, m2d_cap_mm)
    if cue_on:
        s += wrist_cost_at(G, cue_point, cue_direction, reach_mm, turn_mm)
    return s


# ----------------------------------------------------------------------------- the observe stage's window
@njit(cache=True)
def observe_window(dw, mw, fx, fy, cx, cy, smooth, max_diff, max_jump, stride, oy, ox, dsm, pts, nrm):
    """One hand window of :func:`tracker.observe.observe` compiled: the depth ``dw`` smoothed into
    ``dsm`` (:func:`tracker.observe.smooth_depth` with ``smooth`` px and ``max_diff`` m; a copy when
    0), then at the kept pixels only — the mask ``mw``, every ``stride``-th row and column from
    ``(oy, ox)``, finite depth — the back-projected point (window camera ``fx fy cx cy``) and the
    normal of :func:`tracker.observe.image_normals` (central differences, NaN at the window's border
    or across a depth jump above ``max_jump``), written to ``pts``/``nrm`` in row-major order. The
    numpy path computed smoothing, points and normals for every pixel of the window and then kept
    one in stride². Returns the number of kept pixels."""
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
                nn = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2) + 1e-300
                c0, c1, c2 = c0 / nn, c1 / nn, c2 / nn
                # oriented towards the camera; a jump (not NaN: NaN compares False) voids the normal
                dot = c0 * X0 + c1 * X1 + c2 * d
                sg = -1.0 if dot > 0 else (1.0 if dot < 0 else (0.0 if dot == 0 else np.nan))
                if not (abs(a2) > max_jump or abs(b2) > max_jump):
                    n0, n1, n2 = c0 * sg, c1 * sg, c2 * sg
            nrm[k, 0], nrm[k, 1], nrm[k, 2] = n0, n1, n2
            k += 1
    return k
