"""Numba kernels of one ICP fit (:func:`tracker.icp.fit`) in compiled code.

The Python loop of :func:`tracker.icp.fit_reference` paid its interpreter and array-wrapping costs
once per ICP iteration (correspondences, local offsets, silhouette pairs, the solver's argument
checks); here the loop runs inside one compiled call. The Gauss-Newton steps work on per-node moment
sums of the pairs (:func:`node_moments`): with the pairs fixed during a step, every energy and every
normal-equation evaluation costs O(nodes × DoF²) instead of O(pairs × DoF²); a subspace's normal
equations are projected from all DoF's (a synergy subspace is not cheaper per step: its PCs touch every
finger). What a stage in the synergy subspace can save is the closest-point search, the costly part
of a stage: a local pass (:func:`tracker._correspond_kernels.match_same`) re-projects each point onto
the primitive it was matched to. Point-to-plane pairs do not reduce to moments; they go through the
per-pair solver of :mod:`handmodel._solver_kernels`. The search over every primitive is the loop's own
(:func:`match_posed`): :func:`tracker._correspond_kernels.match`'s pairs to the bit, with each pass's
per-primitive constants computed once (:func:`posed_primitives`). The arrays come as the named tuples of
:mod:`tracker._kernel_arrays`.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from handmodel._geometry_kernels import CAPSULE, bounding_spheres, closest_local
from handmodel._solver_kernels import (
    MM,
    _limit_grad,
    cholesky_solve,
    converged,
    freeze_at_limits,
    solve_stages,
)

from ._correspond_kernels import MM as MM_PER_M
from ._correspond_kernels import _model_to_data_at, hand_frames, kept_pairs, match_same, new_frames
from ._kernel_arrays import (
    ENTRY_CLAMP,
    ENTRY_THROUGH,
    CapsuleArrays,
    FitTerms,
    GaussNewton,
    HandArrays,
    KeypointPairs,
    MatchRules,
    Pairs,
    ProjectionArrays,
    SampleArrays,
    ScoreTerms,
    SilhouetteArrays,
    StageArrays,
    WristCueArrays,
    WristLine,
)
from ._search_kernels import pairwise_sum
from ._silhouette_kernels import silhouette_pairs_kernel
from ._wrist_kernels import wrist_cost_at

#: the moments per node (:func:`node_moments`)
N_MOMENTS = 23
#: a failed Cholesky factorisation is retried with this much added to the diagonal: relative to its
#: mean, and absolute
RETRY_RIDGE, RETRY_FLOOR = 1e-9, 1e-12
#: a stage also ends when the energy (mm²) or the step (in the subspace's coordinates) falls below these
ENERGY_FLOOR, STEP_FLOOR = 1e-18, 1e-10
#: the fewest valid pairs a stage fits (a rigid step's or a fit's)
MIN_PAIRS = 3


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
    if n < MIN_PAIRS:
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
def moment_normal_equations(hand, mom, G0, G, wa, wo, Aa, ba, dids, sa, sk):
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
    parents, dof_ptr, dof_idx, dof_types = hand.parents, hand.dof_ptr, hand.dof_idx, hand.dof_types
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
def moment_energy_at(theta, hand, mom, G0, G, wa, wo, A, b):
    """½ Σ w² r² (mm²) at θ from the moments (leaves θ's frames in G)."""
    hand_frames(theta, hand, G, wa, wo)
    return moment_energy(G, G0, mom, A, b)


# ----------------------------------------------------------------------------- one stage's Gauss-Newton
@njit(cache=True)
def solve_stage_moments(theta0, hand, mom, G0, M, mu, m, lo, hi, damp, eye, gn, stats, wa0, wo0):
    """Damped Gauss-Newton in one subspace on the moments: the steps of
    :func:`handmodel._solver_kernels.solve_stages` (selective and Chan–Dubey damping, the active set
    at the limits, clamping, step halving until the energy drops, the same stopping rules) for a single
    stage. Adds the steps taken to ``stats[0]``, a step that failed to lower the energy after
    ``max_halvings`` halvings (it ends the stage) to ``stats[1]`` and the trial steps' energy
    evaluations to ``stats[2]``. ``gn``: :class:`~tracker._kernel_arrays.GaussNewton`. ``G0``, ``wa0``,
    ``wo0``: θ0's node frames, DoF axes and origins (of :func:`hand_frames`). Returns θ."""
    iters, max_halvings, tol, limit_avoid, clamp, margin = gn
    n = hand.dof_axes.shape[0]
    G, wa, wo = new_frames(hand)
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
    # G, wa, wo hold θ's frames: θ0's as given when θ is θ0 (the identity basis moves nothing), else computed
    # here; then left by the energy of each accepted step
    if eye:
        G[:] = G0
        wa[:] = wa0
        wo[:] = wo0
    else:
        hand_frames(theta, hand, G, wa, wo)
    for it in range(iters):
        E = moment_normal_equations(hand, mom, G0, G, wa, wo, A, b, dids, sa, sk)
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
                Aa[c, c] += RETRY_RIDGE * tr / m + RETRY_FLOOR
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
            E_new = moment_energy_at(th_new, hand, mom, G0, G, wa, wo, A3, b3)
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
        if E - E_new <= tol * E or E_new < ENERGY_FLOOR or big < STEP_FLOOR:
            break
    return theta


# ----------------------------------------------------------------------------- the closest-point passes
#: a primitive's row in :func:`posed_primitives`' profile constants: a round cone that is the hull of its
#: two spheres (the tangent line's normal, its touching point on the base sphere and its length), or one
#: sphere containing the other (that sphere's centre along the axis and its radius)
PROFILE_HULL, PROFILE_SPHERE = 1.0, 0.0


@njit(cache=True)
def posed_primitives(G, caps):
    """What a closest-point pass needs of each primitive at the node frames ``G``, computed once per pass
    instead of once per point and primitive visited: ``(F, K, sc, sr)``. ``F (S, 12)``: the primitive's
    node frame, its rotation row by row and its origin, contiguous; ``K (S, 6)``: a round cone's profile
    constants (:func:`_cone_posed`; a slab's row is unused); ``sc (3, S)``, ``sr (S,)``: the bounding spheres
    of :func:`handmodel._geometry_kernels.bounding_spheres`, the centres' coordinates as rows (a point's
    squared distances to all of them are one vectorised loop)."""
    node, shape, length, r0, r1 = caps.node, caps.shape, caps.length, caps.r0, caps.r1
    S = node.shape[0]
    F = np.empty((S, 12))
    K = np.zeros((S, 6))
    for s in range(S):
        j = node[s]
        for r in range(3):
            F[s, 3 * r] = G[j, r, 0]
            F[s, 3 * r + 1] = G[j, r, 1]
            F[s, 3 * r + 2] = G[j, r, 2]
            F[s, 9 + r] = G[j, r, 3]
        if shape[s] != CAPSULE:
            continue
        # _round_cone_2d's constants, by its own expressions (the same bits)
        L, ra, rb = length[s], r0[s], r1[s]
        d = ra - rb
        if abs(d) >= L:
            K[s, 0] = PROFILE_SPHERE
            if ra >= rb:
                K[s, 1], K[s, 2] = 0.0, ra
            else:
                K[s, 1], K[s, 2] = L, rb
        else:
            nx = d / L
            ny = np.sqrt(1.0 - nx * nx)
            K[s, 0] = PROFILE_HULL
            K[s, 1] = nx
            K[s, 2] = ny
            K[s, 3] = ra * nx
            K[s, 4] = ra * ny
            K[s, 5] = np.sqrt(L * L - d * d)
    sc, sr = bounding_spheres(G, node, shape, length, r0, r1, caps.thickness)
    return F, K, np.ascontiguousarray(sc.T), sr


@njit(cache=True, inline="always")
def _cone_posed(K, s, L, ra, rb, x, y, z, loc):
    """``closest_local`` (:mod:`handmodel._geometry_kernels`) of round cone ``s`` (length ``L``, radii
    ``ra``, ``rb``) at its local point ``(x, y, z)`` into ``loc`` (local point, normal, signed distance):
    ``closest_local``'s and ``_round_cone_2d``'s expressions on the same operands, so the same bits, with
    the profile's constants from ``K`` (:func:`posed_primitives`: two square roots and a division less a
    call). (Written into the search's loop, not as a function around the slab's case too: numba's
    inlining of that left the pass slower than the lone search's.)"""
    # the axis along local +y, the radial direction in the x-z plane; the profile point (y, rad)
    rad = np.sqrt(x * x + z * z)
    if rad < 1e-15:
        ex, ez = 1.0, 0.0
    else:
        ex, ez = x / rad, z / rad
    if K[s, 0] == PROFILE_SPHERE:
        cxs, rr = K[s, 1], K[s, 2]
        vx, vy = y - cxs, rad
        nn = np.sqrt(vx * vx + vy * vy)
        if nn < 1e-15:
            vx, vy, nn = 0.0, 1.0, 1.0
        nax, nr = vx / nn, vy / nn
        cx, cr, dist = cxs + rr * nax, rr * nr, nn - rr
    else:
        nx, ny, tax, tay, side = K[s, 1], K[s, 2], K[s, 3], K[s, 4], K[s, 5]
        tx, ty = ny, -nx
        t = (y - tax) * tx + (rad - tay) * ty
        if t < 0.0:
            nn = np.sqrt(y * y + rad * rad)
            if nn < 1e-15:
                cx, cr, nax, nr, dist = -ra, 0.0, -1.0, 0.0, -ra
            else:
                cx, cr, nax, nr, dist = ra * y / nn, ra * rad / nn, y / nn, rad / nn, nn - ra
        elif t > side:
            vx, vy = y - L, rad
            nn = np.sqrt(vx * vx + vy * vy)
            if nn < 1e-15:
                cx, cr, nax, nr, dist = L + rb, 0.0, 1.0, 0.0, -rb
            else:
                cx, cr, nax, nr, dist = L + rb * vx / nn, rb * vy / nn, vx / nn, vy / nn, nn - rb
        else:
            cx, cr = tax + t * tx, tay + t * ty
            nax, nr, dist = nx, ny, (y - cx) * nx + (rad - cr) * ny
    loc[0] = cr * ex
    loc[1] = cx
    loc[2] = cr * ez
    loc[3] = nr * ex
    loc[4] = nax
    loc[5] = nr * ez
    loc[6] = dist


@njit(cache=True)
def closest_pass_and_any(G, caps, points, cam, facing_only, out_p, out_n, out_seg, out_d, any_d, hinted=False):
    """The closest-point pass of :func:`handmodel._geometry_kernels.closest_points_facing` with ``cam`` and
    ``facing_only`` (the closest front-facing point, its normal, primitive and absolute distance into
    ``out_*``; −1 and +inf without one), and with ``any_d`` (not None) the same search with ``facing_only``
    False in the same visits, of which only the distance is kept (what
    :func:`tracker._search_kernels.data_cost_mean` measures). ``any_d`` None compiles a version without
    that search (numba prunes its branches). ``hinted``: ``out_seg`` holds each point's primitive from a
    pass at a nearby pose (the fit's pass before), visited first: the best found first prunes the most
    (any value there gives the same results; it orders the visits only).

    The same results to the bit as the lone searches (tests/tracker/test_h42_closest_pass.py), for less:
    each primitive's frame and profile constants are taken once per pass (:func:`posed_primitives`), a
    point's squared distances to all bounding spheres are one vectorised loop and the bound compares them
    squared (no square root per point and primitive), and a primitive is posed once when either search
    needs it. Each search keeps its own best and skips a primitive by its own bound; the visits' order and
    the bound's rounding change no result: ties go to the lowest index, and the bound only skips primitives
    farther than the best by its margin (1e-5 relative and 1 µm, for node frames orthonormal to ~1e-6),
    which cannot win. (~30 % less time a point than ``closest_points_facing`` on the start searches'
    clouds: the fits' closest-point passes are about half of a search's time.)"""
    P = points.shape[0]
    F, K, sc, sr = posed_primitives(G, caps)
    S = sr.shape[0]
    scx, scy, scz = sc[0], sc[1], sc[2]
    # the tuple's arrays as locals before the loop (see tracker._correspond_kernels.match)
    shape, length, r0, r1, thickness = caps.shape, caps.length, caps.r0, caps.r1, caps.thickness
    visits = S + 1 if S else 0  # the previous winner, then every other primitive
    c2 = np.empty(S)
    q = np.empty(3)
    loc = np.empty(7)
    prev = 0
    for i in range(P):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        for s in range(S):
            e0 = px - scx[s]
            e1 = py - scy[s]
            e2 = pz - scz[s]
            c2[s] = e0 * e0 + e1 * e1 + e2 * e2
        best, bs = 1e300, -1      # the facing search
        best_a, bs_a = 1e300, -1  # the search on any side
        w0 = w1 = w2 = m0 = m1 = m2 = 0.0
        first = prev
        if hinted and 0 <= out_seg[i] < S:
            first = out_seg[i]
        for t in range(visits):
            # first the point's own winner of a pass before, else the previous point's (neighbouring points
            # of a scan mostly share it)
            if t == 0:
                s = first
            else:
                s = t - 1
                if s == first:
                    continue
            # |p - c| - r > best + margin, squared (best 1e300: the reach's square overflows to inf)
            reach = best + 1e-5 * abs(best) + 1e-6 + sr[s]
            skip = c2[s] > reach * reach
            if any_d is not None:
                reach_a = best_a + 1e-5 * abs(best_a) + 1e-6 + sr[s]
                skip_a = c2[s] > reach_a * reach_a
            else:
                skip_a = True
            if skip and skip_a:
                continue
            # closest_on_primitive: the point in the primitive's frame, Rᵀ (p − o)
            d0 = px - F[s, 9]
            d1 = py - F[s, 10]
            d2 = pz - F[s, 11]
            x = F[s, 0] * d0 + F[s, 3] * d1 + F[s, 6] * d2
            y = F[s, 1] * d0 + F[s, 4] * d1 + F[s, 7] * d2
            z = F[s, 2] * d0 + F[s, 5] * d1 + F[s, 8] * d2
            if shape[s] == CAPSULE:
                _cone_posed(K, s, length[s], r0[s], r1[s], x, y, z, loc)
            else:
                q[0], q[1], q[2] = x, y, z
                closest_local(shape[s], length[s], r0[s], r1[s], thickness[s], q, loc)
            dist = abs(loc[6])
            if not skip_a and not (dist > best_a or (dist == best_a and s > bs_a)):
                best_a = dist
                bs_a = s
            if skip or dist > best or (dist == best and s > bs):
                continue
            # to_world's expressions
            p0 = F[s, 0] * loc[0] + F[s, 1] * loc[1] + F[s, 2] * loc[2] + F[s, 9]
            p1 = F[s, 3] * loc[0] + F[s, 4] * loc[1] + F[s, 5] * loc[2] + F[s, 10]
            p2 = F[s, 6] * loc[0] + F[s, 7] * loc[1] + F[s, 8] * loc[2] + F[s, 11]
            n0 = F[s, 0] * loc[3] + F[s, 1] * loc[4] + F[s, 2] * loc[5]
            n1 = F[s, 3] * loc[3] + F[s, 4] * loc[4] + F[s, 5] * loc[5]
            n2 = F[s, 6] * loc[3] + F[s, 7] * loc[4] + F[s, 8] * loc[5]
            if facing_only:
                view = (p0 - cam[0]) * n0 + (p1 - cam[1]) * n1 + (p2 - cam[2]) * n2
                if view > 0.0:
                    continue
            best = dist
            bs = s
            w0, w1, w2, m0, m1, m2 = p0, p1, p2, n0, n1, n2
        if bs >= 0:
            # the winner's point and normal (a point without one keeps its rows, as the lone pass does)
            out_p[i, 0], out_p[i, 1], out_p[i, 2] = w0, w1, w2
            out_n[i, 0], out_n[i, 1], out_n[i, 2] = m0, m1, m2
        out_seg[i] = bs
        out_d[i] = best if bs >= 0 else np.inf
        if any_d is not None:
            any_d[i] = best_a if bs_a >= 0 else np.inf
        if bs >= 0:
            prev = bs


@njit(cache=True)
def match_posed(G, caps, points, normals, rules, out, hinted=False):
    """:func:`tracker._correspond_kernels.match` (the same pairs to the bit) by the pass of
    :func:`closest_pass_and_any`: the fit's closest-point searches (``hinted``: ``out.seg`` holds a pass
    before's primitives, each point's first visit). Returns the number of valid pairs."""
    closest_pass_and_any(G, caps, points, rules.camera, rules.facing_only, out.p, out.n, out.seg, out.d, None,
                         hinted)
    return kept_pairs(caps, points, normals, rules, out)


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
def _solve_pairs(theta, hand, mom, G0, M, mu, m, lo, hi, damp, eye, gn, terms, pt_node, pt_local, tgt, w, plane, k,
                 st_m1, stats, wa0, wo0):
    """One stage's damped Gauss-Newton on fixed pairs: on their moments ``mom`` (reference frames
    ``G0``: θ's, with its DoF axes ``wa0`` and origins ``wo0``) or, with ``terms.point_to_plane`` or without
    ``terms.moments``, pair by pair. Returns θ."""
    n = hand.dof_axes.shape[0]
    mmax = M.shape[1]
    if terms.moments and not terms.point_to_plane:
        return solve_stage_moments(theta, hand, mom, G0, M[:, :m], mu, m, lo[:m], hi[:m], damp[:m], eye, gn, stats,
                                   wa0, wo0)
    ident = eye
    for r in range(n):
        if mu[r] != 0.0:
            ident = False
    tr = np.full(gn.iterations + 1, np.nan)
    th, _, _ = solve_stages(theta, hand.parents, hand.rest, hand.dof_ptr, hand.dof_idx, hand.dof_types, hand.dof_axes,
                            pt_node, pt_local, tgt, w, plane[:k] if terms.point_to_plane else plane,
                            M.reshape((1, n, mmax)), mu.reshape((1, n)), st_m1,
                            lo.reshape((1, mmax)), hi.reshape((1, mmax)), damp.reshape((1, mmax)),
                            np.full(1, gn.iterations, np.int64), np.full(1, ident), gn.max_halvings, gn.tol,
                            gn.limit_avoid, gn.clamp, gn.margin, tr)
    return th


@njit(cache=True, nogil=True)
def _fit_stages(theta0, hand, caps, points, normals, rules, stages, proj, gn, terms, samples, sil, wrist, kps, out,
                stats):
    """:func:`fit_kernel` but its last closest-point pass: θ after the rigid steps and the stages (``out``
    holds the pairs of the last pass before the last solve)."""
    n = hand.dof_axes.shape[0]
    N = hand.parents.shape[0]
    P = points.shape[0]
    point_to_plane = terms.point_to_plane
    out_p, out_n, out_d, out_node, out_valid = out.p, out.n, out.d, out.node, out.valid
    G, wa, wo = new_frames(hand)
    n_s = samples.nodes.shape[0] if terms.silhouette else 0
    n_k = kps.nodes.shape[0] if kps.on else 0
    n_x = n_s + (1 if wrist.on else 0) + n_k
    pt_node = np.empty(P + n_x, np.int64)
    pt_local = np.empty((P + n_x, 3))
    tgt = np.empty((P + n_x, 3))
    w = np.empty(P + n_x)
    plane = np.zeros((P + n_x if point_to_plane else 0, 3))
    s_nodes = np.empty(n_s, np.int64)
    s_local = np.empty((n_s, 3))
    s_tgt = np.empty((n_s, 3))
    mom = np.empty((N, N_MOMENTS))
    theta = theta0.copy()
    nv = 0
    passes = 0  # closest-point passes so far: a pass after the first starts each point at its last winner
    for _ in range(terms.n_rigid):
        hand_frames(theta, hand, G, wa, wo)
        nv = match_posed(G, caps, points, normals, rules, out, passes > 0)
        passes += 1
        stats[3] += 1
        theta = rigid_update(theta, out_p, points, out_valid)
    # θ's frames at a stage's start (G keeps those of the pass before until the test below)
    G1 = np.empty((N, 4, 4))
    k = -1
    ns = 0
    have_sil = False
    for s in range(stages.M.shape[0]):
        hand_frames(theta, hand, G1, wa, wo)
        # a local pass while the model moved less than local_m since the pass before (the stage
        # before's pairs, or the last rigid step's matches at the frames G it matched at)
        local = stages.local[s] and terms.local_m > 0.0 and (k >= 0 or (terms.n_rigid > 0 and nv >= MIN_PAIRS))
        if local:
            moved = pairs_moved(G, G1, pt_node, pt_local, k) if k >= 0 else matches_moved(G, G1, out_p, out_node,
                                                                                          out_valid)
            local = moved < terms.local_m
        for q in range(N):
            G[q] = G1[q]
        if local:
            nv = match_same(G, caps, points, normals, rules, out)
            stats[4] += 1
        else:
            nv = match_posed(G, caps, points, normals, rules, out, passes > 0)
            passes += 1
            stats[3] += 1
        if nv < MIN_PAIRS:
            break
        m = stages.m[s]
        M = stages.M[s]
        mu = stages.mu[s].copy()
        lo = stages.lo[s].copy()
        hi = stages.hi[s].copy()
        if stages.entry[s] == ENTRY_THROUGH:
            # the same directions through θ; θ itself is always admitted (see tracker.icp.through)
            a = np.empty(m)
            _to_alpha(theta, M, mu, m, stages.eye[s], a)
            pose_mask = stages.pose_mask
            for r in range(n):
                mu[r] = 0.0 if pose_mask[r] else theta[r]
            for c in range(m):
                lo[c] = min(lo[c] - a[c], 0.0)
                hi[c] = max(hi[c] - a[c], 0.0)
        elif stages.entry[s] == ENTRY_CLAMP:
            theta = clamp_into(theta, M, mu, lo, hi, m, stages.eye[s])
        eye = stages.eye[s]
        hand_frames(theta, hand, G, wa, wo)
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
            if terms.robust_mm > 0.0:
                q = out_d[i] * MM / terms.robust_mm
                w[k] = 1.0 / np.sqrt(1.0 + q * q)
            else:
                w[k] = 1.0
            if point_to_plane:
                for r in range(3):
                    plane[k, r] = out_n[i, r]
            k += 1
        if terms.silhouette:
            if not (local and have_sil):
                # a local pass keeps the silhouette pairs of the pass before too
                ns = silhouette_pairs_kernel(G, samples, sil, terms.silhouette_px, s_nodes, s_local, s_tgt)
                have_sil = True
            # weight per pair so the term counts like the data term per unit area
            ws = terms.silhouette_weight * np.sqrt(max(nv, 1) / max(n_s, 1))
            for q in range(ns):
                pt_node[k] = s_nodes[q]
                for r in range(3):
                    pt_local[k, r] = s_local[q, r]
                    tgt[k, r] = s_tgt[q, r]
                    if point_to_plane:
                        plane[k, r] = 0.0
                w[k] = ws
                k += 1
        if wrist.on:
            wl_node, wl_local, wl_normal, wl_free = wrist.node, wrist.local, wrist.normal, wrist.free_m
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
                w[k] = np.sqrt(wrist.share * nv)
                k += 1
        for q in range(n_k):
            # the model's keypoint is its node's origin; the pair weighs its share of the valid data pairs
            # times its own Cauchy weight (a keypoint the detector misplaced by far pulls little)
            j = kps.nodes[q]
            d2 = 0.0
            for r in range(3):
                pt_local[k, r] = 0.0
                tgt[k, r] = kps.target[q, r]
                d2 += (G[j, r, 3] - kps.target[q, r]) ** 2
                if point_to_plane:
                    plane[k, r] = 0.0
            pt_node[k] = j
            w[k] = np.sqrt(kps.share[q] * nv / (1.0 + d2 / (kps.scale_m * kps.scale_m)))
            k += 1
        if terms.moments and not point_to_plane:
            node_moments(pt_node[:k], pt_local[:k], tgt[:k], w[:k], G, N, mom)
        # G, wa, wo: θ's frames, axes and origins (hand_frames above)
        theta = _solve_pairs(theta, hand, mom, G, M, mu, m, lo, hi, stages.damp[s], eye, gn, terms, pt_node[:k],
                             pt_local[:k], tgt[:k], w[:k], plane, k, stages.m[s:s + 1], stats, wa, wo)
        if proj.on[s]:
            theta = clamp_into(theta, proj.M[s], proj.mu[s], proj.lo[s], proj.hi[s], proj.m[s], proj.eye[s])
    return theta


@njit(cache=True, nogil=True)
def fit_kernel(theta0, hand, caps, points, normals, rules, stages, proj, gn, terms, samples, sil, wrist, kps, out,
               stats):
    """One ICP fit (:func:`tracker.icp.fit_reference`'s loop): ``terms.n_rigid`` rigid steps, then per
    stage correspondences at θ, θ moved into the stage's subspace, the pairs (Cauchy-weighted data pairs
    and silhouette pairs) and one damped Gauss-Newton solve; at the end the correspondences at the
    result (in ``out``). The arguments are the named tuples of :mod:`tracker._kernel_arrays`: the
    ``hand`` and its ``caps``, the data ``points`` and ``normals``, the pairs' ``rules``, the
    ``stages`` and their projections ``proj``, the Gauss-Newton settings ``gn``, the energy's
    ``terms``, the model ``samples`` and silhouette ``sil`` of the silhouette term, the ``wrist`` line.

    A stage with ``stages.local`` takes a local pass (:func:`match_same`: each point stays on the
    primitive it was matched to; the silhouette pairs of the stage before are kept) instead of the
    search over every primitive while the model moved less than ``terms.local_m`` (m;
    :func:`pairs_moved`) since the pass before. ``wrist.on``: one more pair, the point
    ``wrist.local`` of node ``wrist.node`` (the wrist crease) to its closest point on the plane
    through the camera centre with unit normal ``wrist.normal`` (the arm's centre line), weighing like
    ``wrist.share`` × the valid data pairs, when it lies more than ``wrist.free_m`` from the plane (its
    target then that far from the plane; else no pair). ``kps.on``: one pair per detected keypoint
    (:class:`tracker._kernel_arrays.KeypointPairs`), from the model's keypoint (its node's origin) to the
    detected one, weighing ``kps.share`` × the valid data pairs × its Cauchy weight at ``kps.scale_m``
    (the searches' fits have none). ``terms.moments``: Gauss-Newton on moment sums
    (point-to-point only), else the per-pair solver; the moment path adds its steps taken and failed
    to ``stats`` (see :func:`solve_stage_moments`), every closest-point pass adds 1 to ``stats[3]``,
    every local pass to ``stats[4]``. Returns θ."""
    theta = _fit_stages(theta0, hand, caps, points, normals, rules, stages, proj, gn, terms, samples, sil, wrist, kps,
                        out, stats)
    G, wa, wo = new_frames(hand)
    hand_frames(theta, hand, G, wa, wo)
    # hinted by the last pass's primitives (without one, whatever out.seg holds only orders the visits)
    match_posed(G, caps, points, normals, rules, out, True)
    stats[3] += 1
    return theta


@njit(cache=True, nogil=True)
def fit_entry(theta0, hand, caps, points, normals, rules, stages, proj, gn, terms, samples, sil, wrist, kps, out,
              stats):
    """:func:`fit_kernel` with its named tuples given as plain tuples (:func:`tracker._kernel_arrays.plain`)."""
    return fit_kernel(theta0, HandArrays(*hand), CapsuleArrays(*caps), points, normals, MatchRules(*rules),
                      StageArrays(*stages), ProjectionArrays(*proj), GaussNewton(*gn), FitTerms(*terms),
                      SampleArrays(*samples), SilhouetteArrays(*sil), WristLine(*wrist), KeypointPairs(*kps),
                      Pairs(*out), stats)


@njit(cache=True)
def _no_keypoints():
    """The keypoint term off (a search's fits: no detected keypoints)."""
    return KeypointPairs(False, np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0), 1.0)


@njit(cache=True)
def _fit_and_score(theta0, hand, caps, points, normals, rules, stages, proj, gn, terms, samples, sil, wrist, s_terms,
                   s_samples, s_sil, cue, out, any_d, stats):
    """:func:`fit_kernel` and :func:`tracker._search_kernels.search_score` of its result in one: the fit's
    last closest-point pass and the score's data term share one search over the primitives
    (:func:`closest_pass_and_any`); the sums are the lone kernels', in their order. Returns ``(θ, score)``."""
    theta = _fit_stages(theta0, hand, caps, points, normals, rules, stages, proj, gn, terms, samples, sil, wrist,
                        _no_keypoints(), out, stats)
    G, wa, wo = new_frames(hand)
    hand_frames(theta, hand, G, wa, wo)
    closest_pass_and_any(G, caps, points, rules.camera, rules.facing_only, out.p, out.n, out.seg, out.d, any_d,
                         True)
    stats[3] += 1
    kept_pairs(caps, points, normals, rules, out)
    out_valid = out.valid
    # search_score: the data term (data_cost_mean's sums), the model→data term, the wrist cue
    P = points.shape[0]
    cap_mm = s_terms.data_cap_mm
    if P == 0:
        sc = cap_mm
    else:
        for i in range(P):
            d = any_d[i] * MM_PER_M if np.isfinite(any_d[i]) else cap_mm
            d = min(d, cap_mm)
            if not out_valid[i]:
                d = d + s_terms.rejected_mm
            any_d[i] = min(d, cap_mm)
        sc = pairwise_sum(any_d, 0, P) / P
    if s_terms.m2d:
        sc += s_terms.m2d_weight * _model_to_data_at(G, s_samples, s_sil, s_terms.m2d_tolerance_mm,
                                                     s_terms.m2d_tolerance_px, s_terms.m2d_cap_mm)
    if cue.on:
        sc += wrist_cost_at(G, cue.point, cue.direction, cue.reach_mm, cue.turn_mm)
    return theta, sc


@njit(cache=True, nogil=True)
def fit_score_many_entry(thetas, hand, caps, points, normals, rules, stages, proj, gn, terms, samples, sil, wrist,
                         score_terms, score_samples, score_sil, cue, out_t, out_s, stats):
    """A batch of fits and their scores in one call (:meth:`tracker.init.FitContext.fit_many`): from
    each row of ``thetas`` :func:`fit_kernel` with the same arguments (as :func:`fit_entry`'s, plain
    tuples), its result into ``out_t``'s row and :func:`tracker._search_kernels.search_score` of it
    (``score_terms``, ``score_samples``, ``score_sil``, ``cue``: that kernel's) into ``out_s``. Each
    fit's and score's arithmetic is a lone fit's and score's (its pairs start from fresh rows; the fit's
    last closest-point pass and the score's data term share one search, :func:`_fit_and_score`): the batch
    saves the Python around each fit and score and one search over the primitives a fit."""
    h, c, r = HandArrays(*hand), CapsuleArrays(*caps), MatchRules(*rules)
    st, pj, g, t = StageArrays(*stages), ProjectionArrays(*proj), GaussNewton(*gn), FitTerms(*terms)
    sa, si, wl = SampleArrays(*samples), SilhouetteArrays(*sil), WristLine(*wrist)
    s_terms, s_samples = ScoreTerms(*score_terms), SampleArrays(*score_samples)
    s_sil, s_cue = SilhouetteArrays(*score_sil), WristCueArrays(*cue)
    P = points.shape[0]
    out = Pairs(np.zeros((P, 3)), np.zeros((P, 3)), np.empty(P, np.int64), np.empty(P), np.zeros(P, np.int64),
                np.empty(P, np.bool_))
    any_d = np.empty(P)
    for k in range(thetas.shape[0]):
        # the rows a lone fit's Pairs.empty starts from (a pass leaves a point without a pair untouched)
        out.p[:] = 0.0
        out.n[:] = 0.0
        out.node[:] = 0
        th, sc = _fit_and_score(thetas[k], h, c, points, normals, r, st, pj, g, t, sa, si, wl, s_terms, s_samples,
                                s_sil, s_cue, out, any_d, stats)
        out_t[k] = th
        out_s[k] = sc
