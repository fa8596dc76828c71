"""A hand's kinematic chain from numpy: θ checks, node frames, attached points and their Jacobians,
which nodes each DoF moves (behind :class:`handmodel.model.HandModel`'s methods of the same names;
the compiled kernels they call are :mod:`handmodel.kinematics`)."""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from . import kinematics
from .errors import HandModelError

if TYPE_CHECKING:
    from .model import HandModel

#: ``HandModel.dof_types`` codes, as the kernels read them.
ROTATION, TRANSLATION = 0, 1


def read_only(a: np.ndarray) -> np.ndarray:
    """``a`` contiguous and read-only (a model's arrays are shared by its derived copies)."""
    a = np.ascontiguousarray(a)
    a.setflags(write=False)
    return a


def check_theta(theta, n_dofs: int) -> np.ndarray:
    """θ as a float64 array of shape (..., n_dofs), or raise :class:`HandModelError`.

    >>> check_theta([[0, 1]], 2).dtype, check_theta([0, 1], 2).shape
    (dtype('float64'), (2,))
    >>> check_theta([0.0, float("nan")], 2)
    Traceback (most recent call last):
    handmodel.errors.HandModelError: theta: contains NaN or infinite values
    """
    try:
        th = np.asarray(theta, dtype=np.float64)
    except (TypeError, ValueError):
        raise HandModelError("theta", "not a numeric array") from None
    if th.ndim == 0 or th.shape[-1] != n_dofs:
        raise HandModelError("theta", f"shape {th.shape}: the last axis must have {n_dofs} entries")
    if not np.isfinite(th).all():  # the method: check_theta runs thousands of times a search
        raise HandModelError("theta", "contains NaN or infinite values")
    return th


def node_frames(hand: HandModel, theta) -> np.ndarray:
    """Global 4×4 frames of every node, ``(..., n_nodes, 4, 4)``."""
    th = check_theta(theta, hand.n_dofs)
    G = kinematics.fk_batch(th.reshape(-1, hand.n_dofs), *hand.kernel_args())
    return G.reshape(th.shape[:-1] + (hand.n_nodes, 4, 4))


def points(hand: HandModel, theta, nodes, local) -> np.ndarray:
    """World positions ``(..., P, 3)`` of points rigidly attached to ``nodes`` (``local`` in the node frames)."""
    return frame_points(node_frames(hand, theta), nodes, local)


def frame_points(G, nodes, local) -> np.ndarray:
    """:func:`points` from the node frames ``G`` ``(..., n_nodes, 4, 4)`` (:func:`node_frames`) at hand."""
    nodes = np.asarray(nodes, np.int64)
    local = np.asarray(local, float)
    Gs = G[..., nodes, :, :]
    return np.einsum("...pij,pj->...pi", Gs[..., :3, :3], local) + Gs[..., :3, 3]


def jacobian(hand: HandModel, theta, nodes=None, local=None) -> np.ndarray:
    """Analytic Jacobian ∂p/∂θ (paper eq. 5) of attached points, ``(..., P, 3, n_dofs)``.

    Without ``nodes`` the points are the keypoints; without ``local`` the nodes' origins. A rotation
    column is ``a_w × (p − o)`` with ``a_w`` the DoF's axis in world coordinates and ``o`` its joint
    origin; a translation column is ``a_w``.
    """
    th = check_theta(theta, hand.n_dofs)
    if nodes is None:
        nodes = np.arange(hand.n_nodes)
        local = np.zeros((hand.n_nodes, 3))
    nodes = np.asarray(nodes, np.int64)
    local = np.zeros((len(nodes), 3)) if local is None else np.asarray(local, float).reshape(len(nodes), 3)
    J = kinematics.jacobian_batch(th.reshape(-1, hand.n_dofs), nodes, local, *hand.kernel_args())
    return J.reshape(th.shape[:-1] + (len(nodes), 3, hand.n_dofs))


def has_child(parents: np.ndarray) -> np.ndarray:
    """True for the nodes that are some node's parent (the joints; the others are the tips).

    >>> has_child(np.array([-1, 0, 1, 0]))
    array([ True,  True, False, False])
    """
    out = np.zeros(len(parents), bool)
    out[parents[parents >= 0]] = True
    return out


def dof_moves(hand: HandModel) -> np.ndarray:
    """``(n_dofs, n_nodes)`` bool: the nodes each DoF moves (the node it drives and every node below it).

    >>> from handmodel import HandModel
    >>> hand = HandModel.load()
    >>> [hand.node_names[k] for k in np.flatnonzero(dof_moves(hand)[hand.dof_index("index2_flex")])]
    ['index2', 'index3', 'index_tip']
    """
    n = hand.n_nodes
    below = np.eye(n, dtype=bool)  # below[j, k]: node k is j or hangs from it
    for k in range(n):
        j = hand.parents[k]
        while j >= 0:
            below[j, k] = True
            j = hand.parents[j]
    out = np.zeros((hand.n_dofs, n), bool)
    for k in range(n):
        out[hand.dof_idx[hand.dof_ptr[k]:hand.dof_ptr[k + 1]]] = below[k]
    return out


def root_dofs(hand: HandModel) -> np.ndarray:
    """``(n_dofs,)`` bool: the DoFs of the root joint (the global pose).

    >>> from handmodel import HandModel
    >>> np.flatnonzero(root_dofs(HandModel.load()))
    array([0, 1, 2, 3, 4, 5])
    """
    m = np.zeros(hand.n_dofs, bool)
    m[hand.dof_idx[hand.dof_ptr[0]:hand.dof_ptr[1]]] = True
    return m


def segment_of_node(hand: HandModel) -> np.ndarray:
    """Segment index per node (-1 where the node has none)."""
    out = np.full(hand.n_nodes, -1, np.int64)
    for i, s in enumerate(hand.segments):
        out[s.joint] = i
    return out
