"""Hands derived from a hand: the mirror image, resized, with measured joint positions, rest rotations
or limits (behind :class:`handmodel.model.HandModel`'s ``mirrored``, ``scaled`` and ``with_*``)."""
from __future__ import annotations

import dataclasses
import hashlib
import json
from typing import TYPE_CHECKING

import numpy as np

from .chain import ROTATION
from .chain import read_only as _ro
from .errors import HandModelError

if TYPE_CHECKING:
    from .model import HandModel

_MIRROR = np.diag([-1.0, 1.0, 1.0])


def mirrored(hand: HandModel) -> HandModel:
    """The mirror-image hand (left ↔ right) for the same parameter vector (behind :meth:`HandModel.mirrored`).

    Every joint below the root is conjugated by ``S = diag(-1, 1, 1)`` and each rotation axis
    ``a`` becomes ``-S a`` (so ``S R_a(q) S = R_{-Sa}(q)``); the root's global pose is unchanged.
    """
    S = _MIRROR
    rest = hand.rest.copy()
    rest[1:, :3, :3] = S @ rest[1:, :3, :3] @ S
    rest[1:, :3, 3] = rest[1:, :3, 3] @ S
    axes = hand.dof_axes.copy()
    root_dofs = set(hand.dof_idx[hand.dof_ptr[0]:hand.dof_ptr[1]].tolist())
    for d in range(hand.n_dofs):
        if d in root_dofs:
            continue
        axes[d] = -(S @ axes[d]) if hand.dof_types[d] == ROTATION else S @ axes[d]
    side = "right" if hand.handedness == "left" else "left"
    return dataclasses.replace(hand, handedness=side, rest=_ro(rest), dof_axes=_ro(axes))


def scaled(hand: HandModel, scale: float, bone_scales: dict | None) -> HandModel:
    """A resized copy: every bone and radius × ``scale``, then the bones ending at the nodes in
    ``bone_scales`` (node name → factor) × their factor. Capsule lengths follow their bones (behind
    :meth:`HandModel.scaled`)."""
    if not np.isfinite(scale) or scale <= 0:
        raise HandModelError(hand.path, f"scale must be positive, got {scale}")
    rest = hand.rest.copy()
    rest[:, :3, 3] *= scale
    for name, f in (bone_scales or {}).items():
        if not np.isfinite(f) or f <= 0:
            raise HandModelError(hand.path, f"bone scale of {name!r} must be positive, got {f}")
        rest[hand.node_index(name), :3, 3] *= f
    segs = []
    for sg in hand.segments:
        f = scale
        kids = [k for k in range(hand.n_nodes) if hand.parents[k] == sg.joint]
        if sg.shape == "capsule" and len(kids) == 1 and abs(np.linalg.norm(hand.rest[kids[0], :3, 3]) - sg.length) < 1e-9:
            length = float(np.linalg.norm(rest[kids[0], :3, 3]))  # the capsule spans its bone
        else:
            length = sg.length * f
        segs.append(dataclasses.replace(sg, length=length, radius=(sg.radius[0] * f, sg.radius[1] * f),
                                        half_thickness=sg.half_thickness * f))
    key = json.dumps({"base": hand.sha256, "scale": scale, "bones": bone_scales or {}}, sort_keys=True).encode()
    return dataclasses.replace(hand, sha256=hashlib.sha256(key).hexdigest(), rest=_ro(rest), segments=tuple(segs))


def with_joint_positions(hand: HandModel, positions: dict) -> HandModel:
    """A copy with the rest positions (in the parent's frame, metres) of some joints replaced, e.g. the
    finger bases on the palm measured from a subject (behind :meth:`HandModel.with_joint_positions`)."""
    rest = hand.rest.copy()
    for name, v in positions.items():
        v = np.asarray(v, float)
        if v.shape != (3,) or not np.all(np.isfinite(v)):
            raise HandModelError(hand.path, f"joint position of {name!r} must be 3 finite numbers")
        rest[hand.node_index(name), :3, 3] = v
    key = json.dumps({"base": hand.sha256, "positions": {k: list(map(float, v)) for k, v in positions.items()}},
                     sort_keys=True).encode()
    return dataclasses.replace(hand, rest=_ro(rest), sha256=hashlib.sha256(key).hexdigest())


def with_rest_rotations(hand: HandModel, rotations: dict) -> HandModel:
    """See :meth:`HandModel.with_rest_rotations`."""
    rest = hand.rest.copy()
    for name, R in rotations.items():
        R = np.asarray(R, float)
        if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise HandModelError(hand.path, f"rest rotation of {name!r} is not a proper rotation")
        rest[hand.node_index(name), :3, :3] = R
    key = json.dumps({"base": hand.sha256, "rotations": {k: np.asarray(v).round(12).tolist()
                                                         for k, v in rotations.items()}}, sort_keys=True).encode()
    return dataclasses.replace(hand, rest=_ro(rest), sha256=hashlib.sha256(key).hexdigest())


def with_limits(hand: HandModel, limits) -> HandModel:
    """See :meth:`HandModel.with_limits`."""
    lim = np.asarray(limits, float)
    if lim.shape != (hand.n_dofs, 2) or np.any(lim[:, 0] >= lim[:, 1]):
        raise HandModelError(hand.path, f"limits must be ({hand.n_dofs}, 2) with lower < upper")
    return dataclasses.replace(hand, limits=_ro(lim.copy()))
