"""Rigid registration (Horn 1987, closed-form unit quaternions) and XYZ Euler angles (R = Rx·Ry·Rz)."""
from __future__ import annotations

import math

import numpy as np

from . import libm


def horn(src, dst, weights=None):
    """Rotation ``R`` and translation ``t`` minimising Σ w‖R·src + t − dst‖² (Horn's quaternion method).

    Batched over leading axes: ``src``/``dst`` ``(..., P, 3)``, ``weights`` ``(..., P)`` (0 drops a point).

    Examples
    --------
    >>> import numpy as np
    >>> R0 = euler_to_matrix([0.3, -0.2, 1.0]); p = np.random.default_rng(0).normal(size=(5, 3))
    >>> R, t = horn(p, p @ R0.T + [1, 2, 3])
    >>> bool(np.allclose(R, R0) and np.allclose(t, [1, 2, 3]))
    True
    """
    src = np.asarray(src, float)
    dst = np.asarray(dst, float)
    w = np.ones(src.shape[:-1]) if weights is None else np.broadcast_to(np.asarray(weights, float), src.shape[:-1])
    src = np.where(w[..., None] > 0, src, 0.0)
    dst = np.where(w[..., None] > 0, dst, 0.0)
    ws = w.sum(-1)[..., None]
    cs = (w[..., None] * src).sum(-2) / ws
    cd = (w[..., None] * dst).sum(-2) / ws
    S = np.einsum("...pi,...pj->...ij", (src - cs[..., None, :]) * w[..., None], dst - cd[..., None, :])
    Sxx, Sxy, Sxz = S[..., 0, 0], S[..., 0, 1], S[..., 0, 2]
    Syx, Syy, Syz = S[..., 1, 0], S[..., 1, 1], S[..., 1, 2]
    Szx, Szy, Szz = S[..., 2, 0], S[..., 2, 1], S[..., 2, 2]
    N = np.stack([
        np.stack([Sxx + Syy + Szz, Syz - Szy, Szx - Sxz, Sxy - Syx], -1),
        np.stack([Syz - Szy, Sxx - Syy - Szz, Sxy + Syx, Szx + Sxz], -1),
        np.stack([Szx - Sxz, Sxy + Syx, -Sxx + Syy - Szz, Syz + Szy], -1),
        np.stack([Sxy - Syx, Szx + Sxz, Syz + Szy, -Sxx - Syy + Szz], -1),
    ], -2)
    _, vecs = np.linalg.eigh(N)
    R = quat_to_matrix(vecs[..., :, -1])
    return R, cd - np.einsum("...ij,...j->...i", R, cs)


def quat_to_matrix(q):
    """Rotation matrices of unit quaternions ``(..., 4)`` given as (w, x, y, z)."""
    q = np.asarray(q, float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def wrapped_angles(angles):
    """Euler angles each moved by whole turns into [−π, π): the same :func:`euler_to_matrix` (every
    factor is a rotation about one axis). A fit that turned the hand round several times reads as
    the rotation it is (an SR305 frame's fit came out at −17.8 rad).

    >>> a = np.array([-17.8, 3.0, 7.0])
    >>> bool(np.allclose(euler_to_matrix(wrapped_angles(a)), euler_to_matrix(a))), bool(np.all(np.abs(wrapped_angles(a)) <= np.pi))
    (True, True)
    """
    a = np.asarray(angles, float)
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def euler_to_matrix(angles):
    """R = Rx(a)·Ry(b)·Rz(c), batched over leading axes."""
    a = np.asarray(angles, float)
    if a.shape == (3,):
        # one rotation (the tracker's per-frame tests): the same products on Python floats, half the time
        (ca, cb, cc), (sa, sb, sc) = np.cos(a).tolist(), np.sin(a).tolist()
        return np.array([[cb * cc, -cb * sc, sb],
                         [ca * sc + sa * sb * cc, ca * cc - sa * sb * sc, -sa * cb],
                         [sa * sc - ca * sb * cc, sa * cc + ca * sb * sc, ca * cb]])
    ca, sa = np.cos(a[..., 0]), np.sin(a[..., 0])
    cb, sb = np.cos(a[..., 1]), np.sin(a[..., 1])
    cc, sc = np.cos(a[..., 2]), np.sin(a[..., 2])
    R = np.empty(a.shape[:-1] + (3, 3))
    R[..., 0, 0] = cb * cc
    R[..., 0, 1] = -cb * sc
    R[..., 0, 2] = sb
    R[..., 1, 0] = ca * sc + sa * sb * cc
    R[..., 1, 1] = ca * cc - sa * sb * sc
    R[..., 1, 2] = -sa * cb
    R[..., 2, 0] = sa * sc - ca * sb * cc
    R[..., 2, 1] = sa * cc + ca * sb * sc
    R[..., 2, 2] = ca * cb
    return R


def matrix_to_euler(R):
    """Angles (a, b, c) with R = Rx(a)·Ry(b)·Rz(c), b in [−π/2, π/2]."""
    R = np.asarray(R, float)
    # the C library's inverse trigonometry (handmodel.libm): numpy's differs in the last bits by processor
    b = libm.asin(np.clip(R[..., 0, 2], -1.0, 1.0))
    a = libm.atan2(-R[..., 1, 2], R[..., 2, 2])
    c = libm.atan2(-R[..., 0, 1], R[..., 0, 0])
    return np.stack([a, b, c], axis=-1)


def turned_on(angles, before, share=1.0) -> np.ndarray:
    """XYZ Euler angles of the rotation ``angles`` turned on by ``share`` of its last change (from
    ``before``), about the same axis: constant angular velocity. The angles are the solution nearest
    ``angles`` (θ keeps its turns: a fit starts from it; two Euler triples give each rotation, and a
    difference of Euler angles is no rotation near the middle angle's ±90°).

    >>> np.round(turned_on(np.array([0.0, 0.3, 0.0]), np.array([0.0, 0.1, 0.0])), 6).tolist()
    [0.0, 0.5, 0.0]
    >>> np.round(turned_on(np.array([0.2, 1.5, 0.0]), np.array([0.2, 1.4, 0.0])), 6).tolist()  # past +90°
    [0.2, 1.6, 0.0]
    """
    R, R0 = euler_to_matrix(angles), euler_to_matrix(before)
    step = R @ R0.T
    if share != 1.0:
        step = scaled_rotation(step, share)
    a, b, c = matrix_to_euler(step @ R)
    best = None
    for cand in (np.array([a, b, c]), np.array([a + math.pi, math.pi - b, c + math.pi])):
        # the turns nearest the last angles, each angle on its own
        cand = cand + 2.0 * math.pi * np.round((np.asarray(angles, float) - cand) / (2.0 * math.pi))
        if best is None or np.abs(cand - angles).sum() < np.abs(best - angles).sum():
            best = cand
    return best


def scaled_rotation(R, share) -> np.ndarray:
    """The rotation about ``R``'s axis by ``share`` of its angle (Rodrigues; scalars by :mod:`math`, so that
    the bits do not depend on the processor)."""
    angle = math.acos(min(1.0, max(-1.0, (float(np.trace(R)) - 1.0) / 2.0)))
    if angle < 1e-12:
        return np.eye(3)
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / (2.0 * math.sin(angle))
    K = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    t = share * angle
    return np.eye(3) + math.sin(t) * K + (1.0 - math.cos(t)) * (K @ K)
