"""Hand files: HandModel.save / to_dict write a model that HandModel.load reads back identical
(kinematics, geometry, limits, handedness), atomically and never over an existing file."""

import numpy as np
import pytest
import yaml
from hypothesis import given, settings, strategies as st

from handmodel import HandModel, HandModelError
from handmodel.geometry import closest_points

BONES = ("thumb2", "thumb_tip", "index2", "index3", "middle_tip", "ring2", "pinky3", "pinky_tip")


def _same_model(a, b, rng):
    """Keypoints, posed surface and its closest points equal for random postures and query points."""
    assert (a.handedness, a.node_names, a.dof_names) == (b.handedness, b.node_names, b.dof_names)
    np.testing.assert_array_equal(a.limits, b.limits)
    th = rng.uniform(-0.6, 0.3, size=(4, a.n_dofs))
    th[:, :3] = rng.normal(0, 0.05, size=(4, 3))
    np.testing.assert_array_equal(a.keypoints(th), b.keypoints(th))
    q = th[0, :3] + rng.normal(0, 0.06, size=(200, 3))
    pa, sa, na, da = closest_points(a, th[0], q)
    pb, sb, nb, db = closest_points(b, th[0], q)
    np.testing.assert_array_equal(sa, sb)
    np.testing.assert_allclose(pa, pb, rtol=0, atol=1e-15)
    np.testing.assert_allclose(da, db, rtol=0, atol=1e-15)


@given(scale=st.floats(0.5, 2.0), bones=st.dictionaries(st.sampled_from(BONES), st.floats(0.7, 1.3), max_size=4),
       mirror=st.booleans(), right=st.booleans(), seed=st.integers(0, 2**31 - 1))
@settings(max_examples=20, deadline=None)
def test_saved_model_loads_back_identical(tmp_path_factory, scale, bones, mirror, right, seed):
    hand = HandModel.load().scaled(scale, bones or None)
    if mirror:
        hand = hand.mirrored()
    path = hand.save(tmp_path_factory.mktemp("hand") / "calibrated.yaml", provenance={"note": "test"})
    back = HandModel.load(path)
    _same_model(hand, back, np.random.default_rng(seed))
    assert back.provenance == {"note": "test"}
    # asked for the other hand, the file is mirrored as the shipped model is
    other = HandModel.load(path, right=right)
    assert other.handedness == ("right" if right else "left")
    _same_model(hand if hand.handedness == other.handedness else hand.mirrored(), other, np.random.default_rng(seed))


def test_to_dict_round_trip_in_memory(hand):
    shaped = hand.scaled(1.3, {"index2": 1.1}).mirrored()
    back = HandModel.from_dict(shaped.to_dict(name="mine", provenance={"x": 1}))
    assert (back.name, back.provenance, back.handedness) == ("mine", {"x": 1}, "right")
    _same_model(shaped, back, np.random.default_rng(0))


def test_save_never_overwrites_unless_asked(tmp_path, hand):
    path = tmp_path / "h.yaml"
    hand.scaled(1.2).save(path)
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match="never overwritten"):
        hand.scaled(1.5).save(path)
    assert path.read_bytes() == before
    hand.scaled(1.5).save(path, overwrite=True)
    assert HandModel.load(path).keypoints(np.zeros(26))[20, 1] == pytest.approx(
        hand.scaled(1.5).keypoints(np.zeros(26))[20, 1], abs=0)
    assert [p.name for p in tmp_path.iterdir()] == ["h.yaml"]  # no temporary file left behind


def test_save_refuses_a_file_that_reads_back_different(tmp_path, hand, monkeypatch):
    # a writer bug (here: every translation rounded to 0.1 mm) must not publish a wrong hand
    import handmodel.model_file as model_file

    real = model_file.hand_to_doc

    def rounded(*args):
        doc = real(*args)
        for j in doc["joints"]:
            j["rest"]["translation"] = [round(v, 4) for v in j["rest"]["translation"]]
        return doc

    monkeypatch.setattr(model_file, "hand_to_doc", rounded)
    with pytest.raises(HandModelError, match="differs from the one in memory"):
        hand.scaled(1.2345678).save(tmp_path / "h.yaml")
    assert not any(tmp_path.iterdir())


def test_numpy_values_in_provenance_are_written_plain(tmp_path, hand):
    path = hand.save(tmp_path / "h.yaml", provenance={"scale": np.float64(1.25), "frames": np.arange(3),
                                                      "where": tmp_path})
    doc = yaml.safe_load(path.read_text())
    assert doc["provenance"] == {"scale": 1.25, "frames": [0, 1, 2], "where": str(tmp_path)}


def test_other_kinds_of_file_are_named_as_such(tmp_path):
    p = tmp_path / "recording.yaml"
    p.write_text("fps: 30\nwidth: 640\nheight: 480\n")
    with pytest.raises(HandModelError, match="recording.yaml: not a hand-model file"):
        HandModel.load(p)
