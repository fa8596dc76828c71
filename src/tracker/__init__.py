"""Synergistic hand tracking in depth images."""

#: The hand model the tracker fits when none is named (``--hand-model``): the shipped hand with its finger
#: bases on the human metacarpal arc (:mod:`handmodel.anthropometry`), which real hands fit better than the
#: paper's straight row of finger bases; ``--paper`` fits the paper's own (:data:`PAPER_HAND`).
TRACKING_HAND = "human"

#: The paper's hand (htrack's ``default.calib``, ``models/hands/default.yaml``), fitted with ``--paper``.
PAPER_HAND = "default"
