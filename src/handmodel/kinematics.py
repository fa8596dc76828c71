"""Numba kernels: forward kinematics, per-DoF world axes and analytic Jacobians.

Model arrays (see :meth:`HandModel.kernel_args`): ``parents (N,)``, ``rest (N,4,4)``, ``dof_ptr (N+1,)``
and ``dof_idx`` (the DoFs of node ``j`` in product order are ``dof_idx[dof_ptr[j]:dof_ptr[j+1]]``),
``dof_types (n,)`` (0 rotation, 1 translation), ``dof_axes (n,3)`` unit axes in the joint frame.
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, inline="always")
def _right_mul_elem(M, typ, ax, q):
    """M ← M · E where E rotates by q about unit axis ax (typ 0) or translates by q·ax (typ 1)."""
    if typ == 1:
        for r in range(3):
            M[r, 3] += q * (M[r, 0] * ax[0] + M[r, 1] * ax[1] + M[r, 2] * ax[2])
        return
    c = np.cos(q)
    s = np.sin(q)
    t = 1.0 - c
    x, y, z = ax[0], ax[1], ax[2]
    r00 = t * x * x + c
    r01 = t * x * y - s * z
    r02 = t * x * z + s * y
    r10 = t * x * y + s * z
    r11 = t * y * y + c
    r12 = t * y * z - s * x
    r20 = t * x * z - s * y
    r21 = t * y * z + s * x
    r22 = t * z * z + c
    for r in range(3):
        m0, m1, m2 = M[r, 0], M[r, 1], M[r, 2]
        M[r, 0] = m0 * r00 + m1 * r10 + m2 * r20
        M[r, 1] = m0 * r01 + m1 * r11 + m2 * r21
        M[r, 2] = m0 * r02 + m1 * r12 + m2 * r22


@njit(cache=True)
def fk_single(theta, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes, G, waxis, worig):
    """Forward kinematics of one θ into ``G (N,4,4)``; also each DoF's world axis and origin.

    ``waxis[d]``/``worig[d]`` describe DoF ``d`` in the frame where its elementary transform acts.
    """
    N = parents.shape[0]
    for j in range(N):
        p = parents[j]
        if p < 0:
            for r in range(4):
                for c in range(4):
                    G[j, r, c] = rest[j, r, c]
        else:
            for r in range(3):
                for c in range(4):
                    acc = 0.0
                    for k in range(4):
                        acc += G[p, r, k] * rest[j, k, c]
                    G[j, r, c] = acc
            G[j, 3, 0] = 0.0
            G[j, 3, 1] = 0.0
            G[j, 3, 2] = 0.0
            G[j, 3, 3] = 1.0
        for k in range(dof_ptr[j], dof_ptr[j + 1]):
            d = dof_idx[k]
            ax = dof_axes[d]
            for r in range(3):
                waxis[d, r] = G[j, r, 0] * ax[0] + G[j, r, 1] * ax[1] + G[j, r, 2] * ax[2]
                worig[d, r] = G[j, r, 3]
            _right_mul_elem(G[j], dof_types[d], ax, theta[d])


@njit(cache=True)
def fk_batch(thetas, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes):
    F = thetas.shape[0]
    N = parents.shape[0]
    n = dof_axes.shape[0]
    out = np.empty((F, N, 4, 4))
    wa = np.empty((n, 3))
    wo = np.empty((n, 3))
    for f in range(F):
        fk_single(thetas[f], parents, rest, dof_ptr, dof_idx, dof_types, dof_axes, out[f], wa, wo)
    return out


@njit(cache=True, inline="always")
def point_jacobian_col(typ, wa, wo, p, out):
    if typ == 1:
        out[0] = wa[0]
        out[1] = wa[1]
        out[2] = wa[2]
    else:
        dx = p[0] - wo[0]
        dy = p[1] - wo[1]
        dz = p[2] - wo[2]
        out[0] = wa[1] * dz - wa[2] * dy
        out[1] = wa[2] * dx - wa[0] * dz
        out[2] = wa[0] * dy - wa[1] * dx


@njit(cache=True)
def jacobian_batch(thetas, nodes, local, parents, rest, dof_ptr, dof_idx, dof_types, dof_axes):
    """Jacobians of points attached to ``nodes`` at ``local`` offsets: ``(F, P, 3, n)``."""
    F = thetas.shape[0]
    N = parents.shape[0]
    n = dof_axes.shape[0]
    P = nodes.shape[0]
    out = np.zeros((F, P, 3, n))
    G = np.empty((N, 4, 4))
    wa = np.empty((n, 3))
    wo = np.empty((n, 3))
    p = np.empty(3)
    col = np.empty(3)
    for f in range(F):
        fk_single(thetas[f], parents, rest, dof_ptr, dof_idx, dof_types, dof_axes, G, wa, wo)
        for i in range(P):
            j = nodes[i]
            for r in range(3):
                p[r] = G[j, r, 0] * local[i, 0] + G[j, r, 1] * local[i, 1] + G[j, r, 2] * local[i, 2] + G[j, r, 3]
            k = j
            while k >= 0:
                for m in range(dof_ptr[k], dof_ptr[k + 1]):
                    d = dof_idx[m]
                    point_jacobian_col(dof_types[d], wa[d], wo[d], p, col)
                    out[f, i, 0, d] = col[0]
                    out[f, i, 1, d] = col[1]
                    out[f, i, 2, d] = col[2]
                k = parents[k]
    return out
