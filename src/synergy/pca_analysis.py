"""Checks of fitted synergy models: how well the PCs reconstruct postures they were not fitted on
(:func:`heldout_curve`) and how far apart two models' subspaces are (:func:`principal_angles`).

>>> import numpy as np
>>> X = np.random.default_rng(0).normal(size=(200, 3)) @ np.diag([3.0, 1.0, 0.2])
>>> rms, method = heldout_curve([X[:100], X[100:]])
>>> method, bool(np.all(np.diff(rms) < 0)), round(float(rms[-1]), 12)
('leave-one-trial-out', True, 0.0)
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.linalg import subspace_angles
from sklearn.utils.validation import check_is_fitted

from synergy.errors import SynergyError
from synergy.pca import SufficientStats, SynergyModel, as_2d_finite, sq_error_curve


def heldout_curve(groups: Sequence, n_folds: int = 5) -> tuple[np.ndarray, str]:
    """Out-of-sample reconstruction RMS (radians, all DoF pooled) for k = 0..D PCs.

    With two or more groups (trials) each is held out in turn and the model is refitted
    from the merged statistics of the others. A single group is cut into ``n_folds``
    contiguous blocks instead (frames are correlated in time, so random folds would flatter).

    Returns
    -------
    rms : ndarray (D + 1,)
    method : str
        ``"leave-one-trial-out"`` or ``"blocked-<n>-fold"``.
    """
    groups = [as_2d_finite(g, "heldout_curve") for g in groups]
    if len(groups) == 1:
        X = groups[0]
        if X.shape[0] < 2 * n_folds:
            raise SynergyError("heldout_curve", f"needs at least {2 * n_folds} samples")
        groups = np.array_split(X, n_folds)
        method = f"blocked-{n_folds}-fold"
    else:
        method = "leave-one-trial-out"
    stats = [SufficientStats.from_array(g) for g in groups]
    sq = None
    total = 0
    for i, g in enumerate(groups):
        rest = SufficientStats.merge_all(s for j, s in enumerate(stats) if j != i)
        if rest.n < 2 or g.shape[0] == 0:
            continue
        part = sq_error_curve(rest.finalize(), g).sum(axis=1)
        sq = part if sq is None else sq + part
        total += g.size
    if sq is None:
        raise SynergyError("heldout_curve", "not enough data to hold any group out")
    return np.sqrt(sq / total), method


def principal_angles(A, B, k: int | None = None) -> np.ndarray:
    """Principal angles (radians, ascending) between the spans of the first ``k`` PCs.

    ``A`` and ``B`` are fitted :class:`SynergyModel` s or arrays whose rows are PCs.
    """
    def rows(M):
        if isinstance(M, SynergyModel):
            check_is_fitted(M, "all_components_")
            return M.all_components_
        return np.atleast_2d(np.asarray(M, dtype=float))

    a, b = rows(A), rows(B)
    if a.shape[1] != b.shape[1]:
        raise SynergyError("principal_angles", f"{a.shape[1]} vs {b.shape[1]} DoF")
    k = min(a.shape[0], b.shape[0]) if k is None else int(k)
    if not 1 <= k <= min(a.shape[0], b.shape[0]):
        raise SynergyError("principal_angles", f"k must be in 1..{min(a.shape[0], b.shape[0])}")
    return np.sort(subspace_angles(a[:k].T, b[:k].T))
