"""Where labelled points belong on a hand model's surface: the wrist crease and the fingertips' ends
(behind :class:`handmodel.model.HandModel`'s ``wrist_crease``, ``wrist_crease_local`` and
``fingertip_ends``)."""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .chain import frame_points

if TYPE_CHECKING:
    from .model import HandModel


def wrist_crease(hand: HandModel, theta, frames=None) -> np.ndarray:
    """The middle of the model hand's edge towards the forearm, ``(..., 3)`` metres.

    Where a wrist-crease label (the middle of the skin crease, the hand's end in a hand mask)
    belongs on this model: the root segment's base, its rounded end past the wrist joint (the
    palm slab's half thickness, ~9 mm on the default hand), on the hand's axis. The wrist keypoint
    is the joint itself, the palm's origin.

    >>> from handmodel import HandModel
    >>> hand = HandModel.load()
    >>> np.round(wrist_crease(hand, np.zeros(26)) * 1000, 2)  # the rest pose: fingers along +y
    array([ 0.  , -8.77,  0.  ])
    """
    root, local = wrist_crease_local(hand)
    if frames is not None:  # the node frames at θ, when the caller has them
        return frame_points(frames, [root], [local])[..., 0, :]
    return hand.points(theta, [root], [local])[..., 0, :]


def wrist_crease_local(hand: HandModel) -> tuple[int, np.ndarray]:
    """``(node, offset)``: :func:`wrist_crease` as a point of the root node (its frame, metres).

    >>> from handmodel import HandModel
    >>> wrist_crease_local(HandModel.load())[0]
    0
    """
    root = int(np.flatnonzero(hand.parents < 0)[0])
    seg = next((s for s in hand.segments if s.joint == root), None)
    back = 0.0 if seg is None else (seg.half_thickness if seg.shape == "slab" else seg.radius[0])
    return root, np.array([0.0, -back, 0.0])


def fingertip_ends(hand: HandModel, theta) -> np.ndarray:
    """Where each finger's surface ends, ``(..., 5, 3)`` metres, in ``hand.tip_indices`` order.

    Where a fingertip label (the outermost point of the finger along its axis, on its centre line)
    belongs on this model: the last segment's rounded end, its end radius past the tip keypoint
    along the last bone (~5 mm on the default hand). The tip keypoint is the end of the bone, the
    centre of that rounded end.

    >>> from handmodel import HandModel
    >>> hand = HandModel.load()
    >>> k, e = hand.keypoints(np.zeros(26)), fingertip_ends(hand, np.zeros(26))
    >>> np.round(np.linalg.norm(e - k[hand.tip_indices], axis=-1) * 1000, 2)  # each tip's end radius
    array([5.19, 5.19, 5.19, 5.19, 5.19])
    """
    k = hand.keypoints(theta)
    tips = hand.tip_indices
    base = hand.parents[tips]
    radius = np.array([next(s.radius[1] for s in hand.segments if s.joint == b) for b in base])
    bone = k[..., tips, :] - k[..., base, :]
    unit = bone / np.linalg.norm(bone, axis=-1, keepdims=True)
    return k[..., tips, :] + radius[:, None] * unit
