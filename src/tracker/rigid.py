"""Rigid ICP step (Horn 1987): move the whole hand, posture fixed, onto its correspondences."""
from __future__ import annotations

import numpy as np

from handmodel.rigid import euler_to_matrix, horn, matrix_to_euler


def apply_rigid(theta, R, t):
    """θ with the global pose pre-multiplied by the rigid motion x ↦ R x + t."""
    th = np.array(theta, float)
    Rp = euler_to_matrix(th[3:6])
    th[:3] = R @ th[:3] + t
    th[3:6] = matrix_to_euler(R @ Rp)
    return th


def rigid_step(theta, data_points, corr, weights=None):
    """One rigid ICP update from valid correspondences; returns θ unchanged with < 3 pairs."""
    v = corr.valid
    if v.sum() < 3:
        return np.array(theta, float)
    R, t = horn(corr.model[v], data_points[v], None if weights is None else weights[v])
    return apply_rigid(theta, R, t)
