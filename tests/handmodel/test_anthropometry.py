"""The human hand (``models/hands/human.yaml``): the paper's hand with its finger bases on the human
metacarpal arc (:mod:`handmodel.anthropometry`, Buchholz et al. 1992), checked against the raw numbers of
both files, against real motion capture (the ART hands), and for how it behaves under resizing and mirroring."""
from __future__ import annotations

import numpy as np
import pytest
import yaml
from hypothesis import given, settings, strategies as st

from handmodel.anthropometry import FINGERS, human_hand, mcp_arc_offsets, on_mcp_arc
from handmodel.fileio import models_dir
from handmodel.model import HandModel
from tests.conftest import shared

ART = "c3dorg_art_hands/ART-Human_hands_real_no6dof.c3d"


def _joints(name):
    doc = yaml.safe_load((models_dir() / "hands" / f"{name}.yaml").read_text())
    return {j["name"]: j for j in doc["joints"]}, doc


def test_the_shipped_file_is_the_default_hand_on_the_arc():
    """A stale human.yaml (the default hand changed, or the arc) fails: the file's base hash is the
    default hand's, and its keypoints in any posture are those of the arc applied now."""
    human, default = HandModel.load("human"), HandModel.load("default")
    assert human.provenance["base_sha256"] == default.sha256
    rng = np.random.default_rng(3)
    for _ in range(5):
        th = rng.uniform(-0.5, 0.5, default.n_dofs)
        np.testing.assert_allclose(human.keypoints(th), human_hand(default).keypoints(th), atol=1e-12)
    assert [repr(g) for g in human.segments] == [repr(g) for g in default.segments]
    np.testing.assert_array_equal(human.limits, default.limits)


def test_only_the_finger_bases_move_and_by_buchholz_shares():
    """From the raw YAML numbers: the hand length is the middle finger's three bones over 0.555 of it
    (Buchholz: 0.277 + 0.170 + 0.108), and each base sits (share − middle's share) × that along +y from
    the middle finger's base; every other number of every joint is the default's."""
    d, _ = _joints("default")
    h, _ = _joints("human")
    length = sum(np.linalg.norm(d[n]["rest"]["translation"]) for n in ("middle2", "middle3", "middle_tip")) / 0.555
    shares = {"index": 0.447, "middle": 0.446, "ring": 0.409, "pinky": 0.368}
    y_mid = d["middle1"]["rest"]["translation"][1]
    assert set(h) == set(d)
    for name in d:
        a, b = np.asarray(d[name]["rest"]["translation"]), np.asarray(h[name]["rest"]["translation"])
        np.testing.assert_allclose(h[name]["rest"]["rotation"], d[name]["rest"]["rotation"], atol=1e-9)
        finger = name[:-1]
        if name.endswith("1") and finger in shares:
            assert b[1] == pytest.approx(y_mid + (shares[finger] - 0.446) * length, abs=1e-9)
            np.testing.assert_allclose(b[[0, 2]], a[[0, 2]], atol=1e-12)
        else:
            np.testing.assert_allclose(b, a, atol=1e-12)
    # the little finger's base ~9 mm and the ring's ~4 mm nearer the wrist on this 117 mm hand
    assert d["pinky1"]["rest"]["translation"][1] - h["pinky1"]["rest"]["translation"][1] == pytest.approx(0.00913, abs=5e-5)
    assert d["ring1"]["rest"]["translation"][1] - h["ring1"]["rest"]["translation"][1] == pytest.approx(0.00433, abs=5e-5)


def test_real_hands_have_the_arc():
    """The ART motion-capture hands (both hands of one person, 969 frames of finger joint centres):
    measured along the hand (wrist to the middle of the four finger bases), the ring finger's base lies
    nearer the wrist than the middle finger's, the little finger's nearer still, on both hands; the
    human model has that order, the paper's hand has its four bases on one line."""
    path = shared(ART)
    ezc3d = pytest.importorskip("ezc3d")
    c = ezc3d.c3d(str(path))
    labels = c["parameters"]["POINT"]["LABELS"]["value"]
    pts = c["data"]["points"][:3]

    def marker(name):
        return pts[:, labels.index("Human4:" + name), :].T

    for side in "RL":
        wrist = marker(side + "HAN")
        bases = np.stack([marker(side + n) for n in ("IFI", "MFI", "RFI", "PIN")], 1)  # index … little
        axis = bases.mean(1) - wrist
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        along = np.einsum("fkd,fd->fk", bases - wrist[:, None], axis)
        index, middle, ring, little = np.median(along - along[:, [1]], axis=0)
        assert little < ring < 0, (side, ring, little)
    arc = mcp_arc_offsets(HandModel.load("default"))
    assert arc["pinky"] < arc["ring"] < 0 == arc["middle"]
    human = HandModel.load("human")
    y = {f: human.rest[human.node_index(f + "1"), 1, 3] for f in FINGERS}
    assert y["pinky"] < y["ring"] < y["middle"]
    default = HandModel.load("default")
    assert len({round(float(default.rest[default.node_index(f + "1"), 1, 3]), 9) for f in FINGERS}) == 1


@settings(max_examples=20, deadline=None)
@given(st.floats(0.6, 1.8), st.booleans())
def test_the_arc_is_in_hand_lengths(scale, right):
    """The arc is a share of the hand's own length: placing the bases on a resized (or mirrored) hand is
    resizing (mirroring) the hand placed at its own size (absolute millimetres would not scale)."""
    base = HandModel.load("default")
    a = on_mcp_arc(base.scaled(scale))
    b = on_mcp_arc(base).scaled(scale)
    th = np.linspace(-0.3, 0.3, base.n_dofs)
    np.testing.assert_allclose(a.keypoints(th), b.keypoints(th), atol=1e-12)
    if right:
        np.testing.assert_allclose(on_mcp_arc(base.mirrored()).keypoints(th), on_mcp_arc(base).mirrored().keypoints(th),
                                   atol=1e-12)

