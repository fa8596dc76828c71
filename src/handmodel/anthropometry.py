"""Human hand proportions that the paper's hand lacks: the finger bases on the metacarpal arc.

htrack's default hand (``models/hands/default.yaml``, the hand of Schröder et al.) puts the four finger
bases (MCP joints) on one straight line across the palm. On human hands they lie on an arc: the ring
and little fingers' bases are closer to the wrist than the middle finger's. Buchholz, Armstrong and
Goldstein (1992) measured where, as shares of the hand length from the distal wrist crease
(:data:`MCP_AXIAL_HL`); the ART motion-capture hands in ``../shared/data/c3dorg_art_hands`` agree in
sign and order. :func:`on_mcp_arc` moves the bases of a hand there, at the hand's own size;
``models/hands/human.yaml`` is the default hand so moved (:func:`write_human_hand`), the hand the tracker
fits to real depth frames (on the 19 labelled SR305 frames it meets the issue's floors on more frames
than the straight line does; see docs/beyond-the-paper.md).

Source: B. Buchholz, T. J. Armstrong, S. A. Goldstein, "Anthropometric data for describing the
kinematics of the human hand", Ergonomics 35(3):261–273, 1992, doi:10.1080/00140139208967812.

Examples
--------
>>> from handmodel.model import HandModel
>>> hand = on_mcp_arc(HandModel.load())
>>> base = {f: hand.rest[hand.node_index(f + "1"), 1, 3] * 1000 for f in FINGERS}
>>> {f: round(float(base[f] - base["middle"]), 1) for f in FINGERS}
{'index': 0.1, 'middle': 0.0, 'ring': -4.3, 'pinky': -9.1}
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

#: Each finger's MCP joint from the distal wrist crease along the hand, as a share of the hand length
#: (Buchholz et al. 1992, their regressions on hand length; the model's names for the fingers).
MCP_AXIAL_HL = {"index": 0.447, "middle": 0.446, "ring": 0.409, "pinky": 0.368}

#: The middle finger's kinematic segments past its MCP joint (proximal, middle, distal phalanx) as shares
#: of the hand length (Buchholz et al. 1992: 0.277 + 0.170 + 0.108): how a model's hand length is read
#: off its middle finger.
MIDDLE_FINGER_HL = 0.277 + 0.170 + 0.108

#: The fingers whose bases :func:`on_mcp_arc` places.
FINGERS = tuple(MCP_AXIAL_HL)

#: The shipped hand :func:`write_human_hand` writes, and the one it starts from.
HUMAN_HAND, BASE_HAND = "human", "default"

SOURCE = ("B. Buchholz, T. J. Armstrong, S. A. Goldstein, Anthropometric data for describing the kinematics "
          "of the human hand, Ergonomics 35(3):261-273, 1992, doi:10.1080/00140139208967812")


def hand_length(hand) -> float:
    """The hand length (distal wrist crease to the middle fingertip, metres) that ``hand``'s middle finger
    stands for: its three bones past the MCP joint over :data:`MIDDLE_FINGER_HL`."""
    bones = [np.linalg.norm(hand.rest[hand.node_index(n), :3, 3]) for n in ("middle2", "middle3", "middle_tip")]
    return float(sum(bones)) / MIDDLE_FINGER_HL


def mcp_arc_offsets(hand) -> dict:
    """Finger name → how far (metres, along the hand towards the fingers) its MCP joint lies from the
    middle finger's on a human hand of ``hand``'s length (:func:`hand_length`)."""
    length = hand_length(hand)
    return {f: (MCP_AXIAL_HL[f] - MCP_AXIAL_HL["middle"]) * length for f in FINGERS}


def on_mcp_arc(hand):
    """``hand`` with its finger bases on the human metacarpal arc: each MCP joint's rest position along
    the hand's axis (the wrist frame's +y, the fingers' direction) set to the middle finger's plus
    :func:`mcp_arc_offsets`; across the palm and out of it they stay. The palm and every bone keep
    their sizes."""
    offsets = mcp_arc_offsets(hand)
    y_middle = float(hand.rest[hand.node_index("middle1"), 1, 3])
    moved = {}
    for f, dy in offsets.items():
        p = np.array(hand.rest[hand.node_index(f + "1"), :3, 3], float)
        p[1] = y_middle + dy
        moved[f + "1"] = p
    return hand.with_joint_positions(moved)


def human_hand(base=None):
    """The shipped default hand (or ``base``) on the metacarpal arc (:func:`on_mcp_arc`)."""
    from .model import HandModel

    return on_mcp_arc(HandModel.load(BASE_HAND) if base is None else base)


def write_human_hand(path: str | Path, *, overwrite: bool = False) -> Path:
    """Write ``models/hands/human.yaml`` (or ``path``): :func:`human_hand` with its provenance (the base
    model's name and SHA-256, the source, the offsets applied)."""
    from .model import HandModel

    base = HandModel.load(BASE_HAND)
    hand = human_hand(base)
    offsets = mcp_arc_offsets(base)
    provenance = {
        "base": BASE_HAND, "base_sha256": base.sha256, "source": SOURCE,
        "mcp_axial_hl": dict(MCP_AXIAL_HL), "middle_finger_hl": MIDDLE_FINGER_HL,
        "hand_length_m": round(hand_length(base), 9),
        "mcp_moved_mm": {f + "1": round(v * 1000, 6) for f, v in offsets.items()},
        "generator": "handmodel.anthropometry.write_human_hand (tools/make_human_hand.py)",
    }
    description = (f"The {base.name} hand (Schroeder et al., ICRA 2014, as shipped in htrack) with the finger bases "
                   "(MCP joints) on the human metacarpal arc of Buchholz et al. 1992: the ring and little finger bases "
                   "closer to the wrist than the middle finger's. Metres. Left hand: fingers along +y, palm faces -z, "
                   "thumb on +x.")
    return hand.save(path, overwrite=overwrite, name=HUMAN_HAND, description=description, provenance=provenance)
