"""DoF names and limit sets (handmodel.dofs): the one list agrees with the model files."""

import numpy as np

import handmodel
from handmodel import HandModel
from handmodel.dofs import ANATOMICAL_LIMITS, DOF_NAMES, POSE_DOF_NAMES, POSTURE_DOF_NAMES, anatomical_limits


def test_default_hand_spells_the_dof_names():
    for right in (False, True):
        hand = HandModel.load(right=right)
        assert tuple(hand.dof_names) == DOF_NAMES
        assert tuple(hand.posture_names) == POSTURE_DOF_NAMES
        assert tuple(np.asarray(hand.dof_names)[hand.pose_mask]) == POSE_DOF_NAMES
    assert handmodel.DOF_NAMES is DOF_NAMES and handmodel.anatomical_limits is anatomical_limits


def test_anatomical_limits_cover_the_posture_and_relate_to_the_model_limits():
    assert set(ANATOMICAL_LIMITS) == set(POSTURE_DOF_NAMES)
    hand = HandModel.load()
    model, anat = np.asarray(hand.limits), anatomical_limits(hand)
    post = ~hand.pose_mask
    # the pose stays the model's (unlimited); the posture takes the anatomical ranges
    np.testing.assert_array_equal(anat[~post], model[~post])
    np.testing.assert_array_equal(anat[post], [ANATOMICAL_LIMITS[n] for n in POSTURE_DOF_NAMES])
    assert np.all(anat[post, 0] < 0) and np.all(anat[post, 1] > 0)  # the flat rest hand is inside
    # wider than the model's everywhere, except the thumb's CMC/MCP flexion (anatomy bounds it tighter)
    assert np.all(anat[:, 1] >= model[:, 1])
    narrower = {n for n, a, m in zip(DOF_NAMES, anat[:, 0], model[:, 0]) if a > m}
    assert narrower == {"thumb1_flex", "thumb2_flex"}
    # the ranges still overlap, so clipping a model-limited posture to anatomy is well defined
    assert np.all(np.maximum(anat[:, 0], model[:, 0]) < np.minimum(anat[:, 1], model[:, 1]))
    # a model with other limits keeps them on the pose and gets anatomy on the posture
    other = hand.with_limits(np.where(np.isinf(model), np.sign(model) * 5.0, model))
    np.testing.assert_array_equal(anatomical_limits(other)[:6], np.tile([-5.0, 5.0], (6, 1)))
