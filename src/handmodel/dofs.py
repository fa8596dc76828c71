"""Names of the degrees of freedom and the joint-limit sets: the one list every package reads.

θ has 26 entries in the paper's order (also the column order of the real posture data
``fingerfist.txt``): the global pose ``tx ty tz rx ry rz``, then for thumb, index, middle, ring
and pinky ``<finger>1_abd <finger>1_flex <finger>2_flex <finger>3_flex``. The 20 posture entries
alone are "the posture"; PCA works on the posture only.

Two limit sets exist. The *model limits* are the hand model's own (``HandModel.limits``, from its
YAML file, the original tracker's narrow ranges). The *anatomical limits* (:data:`ANATOMICAL_LIMITS`)
are generous ranges of motion that real data stays inside; marker IK and the tracker's default use
them. They are wider than the model limits everywhere except the flexion of the thumb's CMC and MCP
joints (``thumb1_flex``, ``thumb2_flex``), which anatomy tables bound at about 70–80°.

Examples
--------
>>> DOF_NAMES[:7]
('tx', 'ty', 'tz', 'rx', 'ry', 'rz', 'thumb1_abd')
>>> len(POSTURE_DOF_NAMES), POSTURE_DOF_NAMES[-1]
(20, 'pinky3_flex')
>>> ANATOMICAL_LIMITS["index2_flex"]
(-2.3, 0.4)
"""
from __future__ import annotations

import numpy as np

FINGERS: tuple[str, ...] = ("thumb", "index", "middle", "ring", "pinky")
#: The 6 global pose DoF that precede the posture in θ.
POSE_DOF_NAMES: tuple[str, ...] = ("tx", "ty", "tz", "rx", "ry", "rz")
#: The 20 posture DoF in the paper's (= fingerfist) order.
POSTURE_DOF_NAMES: tuple[str, ...] = tuple(
    f"{finger}{part}" for finger in FINGERS for part in ("1_abd", "1_flex", "2_flex", "3_flex")
)
#: All 26 DoF of θ: pose, then posture. The default hand model's ``dof_names`` equal this.
DOF_NAMES: tuple[str, ...] = POSE_DOF_NAMES + POSTURE_DOF_NAMES

# Anatomical ranges (rad) around the default hand's rest posture; wide enough for fingerfist (PIP/DIP to
# −123°) and typical ROM tables (MCP 90–100° flexion / up to 45° hyperextension, PIP 100–120°, DIP 80–90°
# with up to 30° hyperextension, finger ab/adduction 20–40°, thumb CMC ±45–50°).
#: Anatomical limits (radians) of the 20 posture DoF, ``name -> (lower, upper)``.
ANATOMICAL_LIMITS: dict[str, tuple[float, float]] = {
    "thumb1_abd": (-0.9, 0.9), "thumb1_flex": (-1.2, 0.8), "thumb2_flex": (-1.4, 0.8), "thumb3_flex": (-1.7, 0.8),
    **{f"{f}1_abd": (-0.8, 0.8) for f in FINGERS[1:]},
    **{f"{f}1_flex": (-1.75, 0.8) for f in FINGERS[1:]},
    **{f"{f}2_flex": (-2.3, 0.4) for f in FINGERS[1:]},
    **{f"{f}3_flex": (-2.3, 0.6) for f in FINGERS[1:]},
}


def anatomical_limits(hand) -> np.ndarray:
    """``(n_dofs, 2)`` limits of ``hand``: anatomical for the DoF named in :data:`ANATOMICAL_LIMITS`,
    the model's own for the rest (the global pose: unlimited).

    >>> from handmodel import HandModel
    >>> lim = anatomical_limits(HandModel.load())
    >>> lim.shape, float(lim[DOF_NAMES.index("index2_flex"), 0])
    ((26, 2), -2.3)
    """
    lim = np.array(hand.limits, float)
    for i, n in enumerate(hand.dof_names):
        if n in ANATOMICAL_LIMITS:
            lim[i] = ANATOMICAL_LIMITS[n]
    return lim
