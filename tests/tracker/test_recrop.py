"""The keypoint CNN's re-crop (``tracker.keypoint_cnn.detect``'s ``recrop``): a segmentation that kept the
forearm gives a box several hands long; the network's keypoints there still lie towards the hand, and boxes
around them narrow onto it (issue 38; docs/experiments/detector.md, "The re-crop"). Frames: the harder
scenes' fist-side motion (thumb side to the camera, forearm and torso, noise seed 2 as
``tools/harder_scenes.py`` renders them)."""
from __future__ import annotations

import functools

import numpy as np
import pytest
from hypothesis import given
from hypothesis import settings as hyp_settings
from hypothesis import strategies as hst

from tests.conftest import harder_frame, mask_scores
from tracker.keypoint_cnn import detect, hand_box, load_cnn, recropped
from tracker.observe import observe


@hyp_settings(max_examples=60, deadline=None)
@given(uv=hst.lists(hst.tuples(hst.floats(-50, 250), hst.floats(-50, 200)), min_size=1, max_size=21),
       z=hst.floats(0.2, 3.0), margin=hst.floats(0.0, 0.1), fx=hst.floats(100, 1000))
def test_recropped_keeps_the_mask_in_the_keypoints_square_only(uv, z, margin, fx):
    """Every kept pixel is in the mask and within the keypoints' square (larger extent / 2 + the margin in
    pixels from their box's centre); every mask pixel well inside that square is kept."""
    rng = np.random.default_rng(len(uv))
    mask = rng.random((160, 220)) < 0.6
    kp = np.asarray(uv, float)
    out = recropped(mask, kp, np.full(len(kp), z), fx, margin)
    c = (kp.min(0) + kp.max(0)) / 2
    half = 0.5 * (kp.max(0) - kp.min(0)).max() + margin * fx / z
    vv, uu = np.mgrid[0:160, 0:220]
    inside = (np.abs(uu - c[0]) <= half - 1) & (np.abs(vv - c[1]) <= half - 1)
    outside = (np.abs(uu - c[0]) > half + 1) | (np.abs(vv - c[1]) > half + 1)
    assert not (out & ~mask).any()
    assert not (out & outside).any()
    assert (out[inside & mask]).all()


def test_recropped_without_keypoints_is_none():
    assert recropped(np.ones((10, 10), bool), np.full((21, 2), np.nan), np.full(21, 0.5), 500.0) is None


@functools.lru_cache(maxsize=None)
def _frame(sensor, scale, frame):
    """``(hand, camera, depth, colour, labels, true keypoints)`` of a fist-side frame."""
    return harder_frame("fist-side", sensor, scale, frame)


def _side_fist(sensor, scale, frame):
    """``(hand, camera, depth, mask, true keypoints, mask precision)`` of a fist-side frame, segmented alone."""
    hand, cam, depth, color, labels, kp = _frame(sensor, scale, frame)
    mask = observe(depth, cam, color=color).mask
    return hand, cam, depth, mask, kp, mask_scores(mask, depth, labels)[1]


def _error_mm(det, kp):
    return float(np.linalg.norm(det.keypoints_xyz - kp, axis=1).mean() * 1000.0)


@pytest.mark.parametrize("sensor, scale, frame, before, after", [
    ("kinect1", 0.8, 25, 35.0, 15.0),    # measured 39.1 -> 10.5 mm (box 252 -> 98 px)
    ("realsense", 0.8, 15, 40.0, 22.0),  # measured 49.3 -> 15.9 mm (box 201 -> 85 px)
])
def test_an_arm_long_box_narrows_onto_the_hand(sensor, scale, frame, before, after):
    """A small side fist at the end of the forearm the segmentation kept (the hand under a fifth of the mask):
    the network on the arm's box misplaces the keypoints by ~4-5 cm; re-cropped around its own keypoints
    it finds them within ~1.5 cm, and the hand-presence network, asked on the narrowed region, calls it a
    hand where on the arm's box it did not (below the surface start's 0.5)."""
    from tracker.hand_presence import hand_probability, load_presence

    hand, cam, depth, mask, kp, precision = _side_fist(sensor, scale, frame)
    assert precision < 0.3  # the case itself: most of the mask is the arm
    cnn = load_cnn()
    whole = detect(depth, cam, mask, hand.handedness, detector=cnn, recrop=0)
    narrowed = detect(depth, cam, mask, hand.handedness, detector=cnn)
    assert whole.region is None and narrowed.region is not None
    assert not (narrowed.region & ~mask).any()
    assert hand_box(depth, narrowed.region)[2] < 0.6 * hand_box(depth, mask)[2]
    assert _error_mm(whole, kp) > before and _error_mm(narrowed, kp) < after
    pres = load_presence()
    # the arm's box: 0.02 by presence 1.1.0, 0.20-0.24 by 1.2.0 (a hand is in it, a fifth of it)
    assert hand_probability(depth, cam, mask, hand.handedness, model=pres) < 0.5
    assert hand_probability(depth, cam, narrowed.region, hand.handedness, model=pres) > 0.5


def test_a_hand_sized_box_is_left_as_it_is():
    """A rendered hand alone (no arm, no noise): its box is the hand's, so the re-crop is not taken and the
    keypoints are those of one pass, to the bit."""
    from handmodel import HandModel
    from tracker import TRACKING_HAND
    from tracker.io.cameras import preset
    from tracker.sim.motions import make_motion
    from tracker.sim.render import DepthRenderer

    hand = HandModel.load(TRACKING_HAND)
    cam = preset("kinect1")
    cnn = load_cnn()
    for th in make_motion("open-close", hand=hand, frames=30).theta[::10]:
        depth = DepthRenderer(hand, cam).render(th, labels=False).depth
        mask = np.isfinite(depth) & (depth > 0)
        one = detect(depth, cam, mask, hand.handedness, detector=cnn, recrop=0)
        d = detect(depth, cam, mask, hand.handedness, detector=cnn)
        assert d.region is None
        np.testing.assert_array_equal(d.keypoints_xyz, one.keypoints_xyz)


def test_the_small_side_fist_is_tracked_from_its_first_frame():
    """Kinect v1, a 0.8x side fist with its forearm and torso, the size calibrated: before the re-crop the
    hand-presence network turned every one of the first frames away ("no hand": 20 frames lost); now none
    is lost and the keypoints are within ~2 cm (measured 43, 19, 19, 15, 18 mm on frames 0-4)."""
    from synergy.bundle import load_bundle
    from tracker.track import FrameTracker, TrackerSettings

    bundle = load_bundle("fingerfist")
    tr = FrameTracker(_frame("kinect1", 0.8, 0)[0], TrackerSettings(), synergies=bundle)
    errs = []
    for f in range(5):
        _, cam, depth, color, _, kp = _frame("kinect1", 0.8, f)
        r = tr.track(observe(depth, cam, color=color, window=tr.segment_window(cam)), cam, color=color)
        assert r.status != "lost", f
        errs.append(float(np.linalg.norm(tr.hand.keypoints(r.theta) - kp, axis=1).mean() * 1000.0))
    assert tr.stats.not_hands == 0
    assert np.median(errs) < 25.0, errs
