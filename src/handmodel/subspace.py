"""Parameter subspaces θ = Mα + μ with M = blockdiag(I_pose, Cᵀ) (paper eq. 6–8).

``Subspace.full`` is the identity map with the model's joint limits; ``Subspace.from_synergies``
builds the reduced space of the first ``l`` principal components with PC limits.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import SolverError


@dataclass(frozen=True, eq=False)
class Subspace:
    """An affine parameter subspace with box limits on its coordinates.

    Attributes
    ----------
    M : ndarray (n, m)
        Basis with orthonormal columns.
    mu : ndarray (n,)
        Offset (zero on the pose entries).
    lo, hi : ndarray (m,)
        Limits of α (±inf where unlimited).
    pose : ndarray (m,) bool
        True for the coordinates that are global-pose DoFs (damped with the pose damping).
    """

    M: np.ndarray
    mu: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    pose: np.ndarray
    label: str = ""

    @property
    def dim(self) -> int:
        return self.M.shape[1]

    @property
    def is_identity(self) -> bool:
        n, m = self.M.shape
        return n == m and not np.any(self.mu) and np.array_equal(self.M, np.eye(n))

    @classmethod
    def full(cls, hand, limits=None) -> "Subspace":
        """All DoFs, with ``limits`` (default: the model's) as box limits."""
        lim = np.asarray(hand.limits if limits is None else limits, float)
        n = hand.n_dofs
        return cls(np.eye(n), np.zeros(n), lim[:, 0].copy(), lim[:, 1].copy(), np.asarray(hand.pose_mask).copy(),
                   label=f"full ({n} DoF)")

    @classmethod
    def from_synergies(cls, hand, components, mean, pc_min=None, pc_max=None, n_components=None) -> "Subspace":
        """Pose DoFs plus the first ``n_components`` synergies (rows of ``components`` over the posture).

        ``pc_min``/``pc_max`` are the PC limits (min/max of training projections); ±inf if omitted.
        """
        C = np.atleast_2d(np.asarray(components, float))
        mean = np.asarray(mean, float)
        post = np.flatnonzero(~np.asarray(hand.pose_mask))
        pose = np.flatnonzero(np.asarray(hand.pose_mask))
        if C.shape[1] != len(post) or mean.shape != (len(post),):
            raise SolverError("subspace", f"components {C.shape} / mean {mean.shape} do not match the "
                                          f"{len(post)} posture DoFs of hand model {hand.name!r}")
        l = C.shape[0] if n_components is None else int(n_components)
        if not 0 <= l <= C.shape[0]:
            raise SolverError("subspace", f"{l} components requested, {C.shape[0]} available")
        C = C[:l]
        if l and not np.allclose(C @ C.T, np.eye(l), atol=1e-6):
            raise SolverError("subspace", "synergy components are not orthonormal")
        n = hand.n_dofs
        M = np.zeros((n, len(pose) + l))
        M[pose, np.arange(len(pose))] = 1.0
        M[np.ix_(post, np.arange(len(pose), len(pose) + l))] = C.T
        mu = np.zeros(n)
        mu[post] = mean
        lo = np.concatenate([np.full(len(pose), -np.inf),
                             np.full(l, -np.inf) if pc_min is None else np.asarray(pc_min, float)[:l]])
        hi = np.concatenate([np.full(len(pose), np.inf),
                             np.full(l, np.inf) if pc_max is None else np.asarray(pc_max, float)[:l]])
        pmask = np.zeros(len(pose) + l, bool)
        pmask[: len(pose)] = True
        return cls(M, mu, lo, hi, pmask, label=f"{len(pose)} pose + {l} PCs")

    def to_alpha(self, theta) -> np.ndarray:
        """α = Mᵀ(θ − μ) (eq. 7); the orthogonal projection's coordinates."""
        return (np.asarray(theta, float) - self.mu) @ self.M

    def to_theta(self, alpha) -> np.ndarray:
        """θ = Mα + μ (eq. 7)."""
        return np.asarray(alpha, float) @ self.M.T + self.mu

    def project(self, theta) -> np.ndarray:
        """The closest θ inside the subspace (ignoring limits)."""
        return self.to_theta(self.to_alpha(theta))

    def jacobian(self, J) -> np.ndarray:
        """J_PC = J M (eq. 8)."""
        return np.asarray(J) @ self.M


def hierarchical_schedule(hand, components, mean, pc_min=None, pc_max=None, *, steps=(1, 4), n_pcs=None,
                          full_limits=None) -> list:
    """The stages of hierarchical optimisation: growing synergy subspaces, then all DoF.

    Parameters
    ----------
    hand : HandModel
    components : array (p, D)
        Synergies, rows are PCs (e.g. a model's ``all_components_``); ``D`` posture DoF.
    mean : array (D,)
    pc_min, pc_max : array (p,), optional
        PC limits (±inf if omitted).
    steps : sequence of int
        PC counts of the coarse stages; those ``≥ n_pcs`` are dropped.
    n_pcs : int, optional
        PCs of the last reduced stage (default: all ``p`` rows).
    full_limits : array (n_dofs, 2), optional
        Box limits of the final all-DoF stage (default: the model's).

    Returns
    -------
    list of Subspace
        ``[PC(s) for s in steps if s < n_pcs] + [PC(n_pcs), full]``; a list the solver takes as its
        ``schedule`` (each stage runs ``settings.iterations``; pair stages with counts to override).

    Examples
    --------
    >>> import numpy as np
    >>> from handmodel import HandModel
    >>> hand = HandModel.load()
    >>> C = np.eye(20)[:6]
    >>> [sp.label for sp in hierarchical_schedule(hand, C, np.zeros(20), steps=(1, 4, 8), n_pcs=5)]
    ['6 pose + 1 PCs', '6 pose + 4 PCs', '6 pose + 5 PCs', 'full (26 DoF)']
    """
    p = np.atleast_2d(np.asarray(components, float)).shape[0]
    l = p if n_pcs is None else int(n_pcs)
    if not 1 <= l <= p:
        raise SolverError("schedule", f"{l} PCs requested, {p} available")
    if any(int(s) < 1 for s in steps):
        raise SolverError("schedule", f"PC steps must be positive, got {tuple(steps)}")
    ks = sorted({int(s) for s in steps if int(s) < l}) + [l]
    return [Subspace.from_synergies(hand, components, mean, pc_min, pc_max, n_components=k) for k in ks] + [
        Subspace.full(hand, full_limits)]
