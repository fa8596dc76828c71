"""Marker sets: shipped files, matching, attachments, schema errors."""
import numpy as np
import pytest
import yaml

from conftest import ROOT
from handmodel import HandModel
from synergy.errors import MarkerSetError
from synergy.markers import load_markerset, markerset_from_dict

HAND = HandModel.load()


@pytest.mark.parametrize("name,count", [("hand16", 16), ("hand19", 19), ("dfki-glove13", 13),
                                        ("art-joint-centres", 21)])
def test_shipped_marker_sets_load(name, count):
    ms = load_markerset(name)
    assert len(ms.markers) == count
    if "{side}" in ms.markers[0].label:
        ms = ms.for_hand("right")
    nodes, local = ms.attachments(HAND)
    assert nodes.shape == (count,) and local.shape == (count, 3)


def test_landmarks_resolve_to_model_points():
    ms = load_markerset("art-joint-centres").for_hand("left")
    assert ms.markers[0].label == "LHAN" and ms.markers[5].label == "LIFI"
    nodes, local = ms.attachments(HAND)
    th = np.random.default_rng(0).uniform(-1, 0, 26)
    # joint centres and fingertips are exactly the model keypoints, in keypoint order
    np.testing.assert_allclose(HAND.points(th, nodes, local), HAND.keypoints(th), atol=1e-15)
    hand16 = load_markerset("hand16")
    n, l = hand16.attachments(HAND)
    i = [m.label for m in hand16.markers].index("IMP")
    assert HAND.node_names[n[i]] == "index2"
    np.testing.assert_allclose(l[i], [0, 0.5 * HAND.rest[HAND.node_index("index3"), 1, 3], 0.010], atol=1e-12)


def test_right_hand_attachments_mirror():
    ms = load_markerset("hand16")
    left, right = HandModel.load(), HandModel.load(right=True)
    th = np.random.default_rng(1).uniform(-1, 0, 26)
    th[:6] = 0
    pl = left.points(th, *ms.attachments(left))
    pr = right.points(th, *ms.attachments(right, right=True))
    np.testing.assert_allclose(pr, pl * [-1, 1, 1], atol=1e-12)


def test_matching_is_prefix_and_case_tolerant_and_reports_extras():
    ms = load_markerset("hand16")
    labels = ["Subject:" + m.label.lower() for m in ms.markers] + ["Subject:ELBOW"]
    idx, extra = ms.match(labels)
    assert list(idx) == list(range(16)) and extra == ["Subject:ELBOW"]
    # aliases
    labels2 = [m.aliases[0] if m.aliases else m.label for m in ms.markers]
    assert list(ms.match(labels2)[0]) == list(range(16))


def test_missing_markers_error_lists_missing_and_present():
    ms = load_markerset("hand16")
    labels = [m.label for m in ms.markers if m.label not in ("INAIL", "PMP")]
    with pytest.raises(MarkerSetError, match=r"trial\.c3d: marker set 'hand16': missing marker\(s\) INAIL, PMP; the file has WRR, WRU"):
        ms.match(labels, where="trial.c3d")


def test_glove_ignores_arm_and_object_markers():
    ms = load_markerset("dfki-glove13")
    labels = [m.label for m in ms.markers] + ["right_elbow", "back_top", "pillow_left", "mystery"]
    _, extra = ms.match(labels)
    assert extra == ["mystery"]


def _doc():
    return yaml.safe_load((ROOT / "models" / "markersets" / "hand16.yaml").read_text())


@pytest.mark.parametrize("mutate,msg", [
    (lambda d: d.pop("markers"), "'markers' is a required property"),
    (lambda d: d["markers"][0].pop("offset"), r"field markers/0"),
    (lambda d: d["markers"][6]["landmark"].update(type="elbow"), r"field markers/6/landmark/type"),
    (lambda d: d["markers"][1].update(label=d["markers"][0]["label"]), "used twice"),
    (lambda d: d["markers"][0].update(weight=-1), r"field markers/0/weight"),
    (lambda d: d.update(schema_version=2), "field schema_version"),
])
def test_malformed_marker_sets(tmp_path, mutate, msg):
    d = _doc()
    mutate(d)
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(d))
    with pytest.raises(MarkerSetError, match=msg) as e:
        load_markerset(p)
    assert "bad.yaml" in str(e.value)


def test_unknown_joint_and_set():
    d = _doc()
    d["markers"][0]["joint"] = "elbow"
    # a reference to a node the hand model lacks fails when the set is read, naming the marker
    with pytest.raises(MarkerSetError, match=r"x.yaml.*marker WRR: unknown joint 'elbow'"):
        markerset_from_dict(d, "x.yaml")
    with pytest.raises(MarkerSetError, match="no such marker set"):
        load_markerset("nope")
    with pytest.raises(MarkerSetError, match="is for the left hand"):
        markerset_from_dict({**_doc(), "hand": "left"}).for_hand("right")


def test_hand_model_is_honoured_and_checked():
    with pytest.raises(MarkerSetError, match="field hand_model: .*no such hand model"):
        markerset_from_dict({**_doc(), "hand_model": "gorilla"}, "x.yaml")
    assert markerset_from_dict({**_doc(), "hand_model": "default"}).hand_model == "default"
    # a landmark that does not fit its node: a fingertip landmark on a joint with children
    d = _doc()
    d["markers"][0] = {"label": "WRR", "landmark": {"type": "fingertip", "joint": "index2"}}
    with pytest.raises(MarkerSetError, match="fingertip landmark needs an end joint"):
        markerset_from_dict(d, "x.yaml")


def test_hand19_three_per_digit():
    ms = load_markerset("hand19")
    nodes, _ = ms.attachments(HAND)
    names = [HAND.node_names[n] for n in nodes]
    assert len(ms.markers) == 19 and names.count("wrist") == 4
    for f in ("index", "middle", "ring", "pinky"):
        assert [n for n in names if n.startswith(f)] == [f"{f}1", f"{f}2", f"{f}3"]
    assert [n for n in names if n.startswith("thumb")] == ["thumb1", "thumb2", "thumb3"]


def test_unseen_protocol_is_expressible():
    """19 markers with 4 on the back of the hand and a dorsal joint landmark: no code change needed."""
    markers = [{"label": f"D{i}", "joint": "wrist", "offset": [0.02 * (i - 1.5), 0.03, 0.012]} for i in range(4)]
    for f in ["thumb", "index", "middle", "ring", "pinky"]:
        markers.append({"label": f"{f}_knuckle", "landmark": {"type": "dorsal", "joint": f"{f}2", "distance": 0.01}})
        markers.append({"label": f"{f}_tip", "landmark": {"type": "fingertip", "joint": f"{f}_tip"}})
    markers += [{"label": f"X{i}", "landmark": {"type": "segment", "joint": "index1", "along": 0.3 * i}, "optional": True}
                for i in range(1, 6)]
    assert len(markers) == 19
    ms = markerset_from_dict({"schema_version": 1, "name": "new19", "markers": markers})
    n, l = ms.attachments(HAND)
    assert len(n) == 19 and np.allclose(l[4], [0, 0, 0.01])
    np.testing.assert_allclose(l[-1], [0, 1.5 * HAND.rest[HAND.node_index("index2"), 1, 3], 0])
