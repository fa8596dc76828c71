"""The size calibration on a fist (issue 38): the first frame of the realistic fist-palm scenes (the
tracker's hand closed, palm to the camera, forearm and a torso behind, noise seed 2 as
``tools/harder_scenes.py`` runs them), where the cloud's extent guesses an open hand's size."""
from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import realistic_frame
from tracker.observe import observe
from tracker.scale import closed_posture, extent_scale


@pytest.fixture(scope="module")
def tracking_hand():
    from handmodel import HandModel
    from tracker import TRACKING_HAND

    return HandModel.load(TRACKING_HAND)


@pytest.mark.parametrize("sensor, scale", [("kinect1", 1.0), ("kinect1", 1.5), ("realsense", 1.0),
                                           ("realsense", 1.5)])
def test_a_fist_is_sized_as_a_closed_hand(tracking_hand, sensor, scale):
    """Before the closed hand's search the sizes found on these frames were 0.89, 0.84, 0.72 of the true
    size (keypoints 21-23 mm off), and SR305 1.5x was "no hand" (the first fit, at 0.67x, rejected 69 % of
    its points); with it 1.00-1.05 and 5.5-13 mm, each fit rejecting 3-7 %."""
    from synergy.bundle import load_bundle
    from tracker import FrameTracker, TrackerSettings
    from tracker.sim.experiments import realistic_fingers
    from tracker.sim.hands import HandShape
    from tracker.sim.motions import make_motion

    cam, depth, color, _ = realistic_frame(tracking_hand, sensor, scale, "forearm,torso", 0, noise_seed=2,
                                           motion="fist-palm", frames=45)
    tr = FrameTracker(tracking_hand, TrackerSettings().replace(scale={"hand_scale": "auto"}),
                      synergies=load_bundle("fingerfist"))
    res = tr.track(observe(depth, cam, tr.settings.observe, color=color), cam, color=color)
    assert res.status == "reinit"
    assert abs(tr.scale_ / scale - 1.0) <= 0.07, tr.scale_ / scale
    shown = HandShape(scale, realistic_fingers(scale, 0)).apply(tracking_hand)
    truth = make_motion("fist-palm", hand=shown, frames=45, seed=0).theta[0]
    err_mm = np.linalg.norm(tr.hand.keypoints(res.theta) - shown.keypoints(truth), axis=1).mean() * 1000.0
    assert err_mm <= 15.0


def test_a_closed_hand_spreads_less_than_an_open_one(tracking_hand):
    """The same cloud means a larger hand when the hand is closed: the closed posture's palm-side
    surface spreads less than the open hand's (so its extent guess is larger), and it curls the four
    fingers, not the thumb."""
    from tracker.init import finger_shapes
    from types import SimpleNamespace

    lim = np.asarray(tracking_hand.limits, float)
    ctx = SimpleNamespace(hand=tracking_hand, finger_shapes=finger_shapes(tracking_hand, lim))
    closed = closed_posture(ctx)
    names = [n for n, p in zip(tracking_hand.dof_names, tracking_hand.pose_mask) if not p]
    thumb = [i for i, n in enumerate(names) if n.startswith("thumb")]
    fingers = [i for i, n in enumerate(names) if "flex" in n and not n.startswith("thumb")]
    assert np.all(closed[thumb] == 0.0) and np.all(closed[fingers] < np.radians(-45.0))
    cloud = tracking_hand.keypoints(np.zeros(tracking_hand.n_dofs))
    open_guess = extent_scale(tracking_hand, cloud, np.zeros(len(names)))
    assert extent_scale(tracking_hand, cloud, closed) > 1.2 * open_guess


@pytest.mark.parametrize("sensor", ["kinect1", "realsense"])
def test_a_side_fist_is_sized_from_its_side(tracking_hand, sensor):
    """The fist-side scene's first frame at 1.5x (thumb side to the camera, forearm and torso, noise seed 2):
    a fist seen from its side is ~25 % narrower than from its palm, so the closed hand's palm-view guess
    (1.31x) is searched too small and the search there finds no side fist: sized 0.66 and 0.60 of the true
    size (keypoints 76 mm off on Kinect v1). With the closed hand's side-view guess (1.66-1.67x) searched as
    well: 0.98 and 1.05."""
    from synergy.bundle import load_bundle
    from tracker import FrameTracker, TrackerSettings
    from tracker.sim.experiments import realistic_fingers
    from tracker.sim.hands import HandShape
    from tracker.sim.motions import make_motion

    scale = 1.5
    cam, depth, color, _ = realistic_frame(tracking_hand, sensor, scale, "forearm,torso", 0, noise_seed=2,
                                           motion="fist-side", frames=45)
    tr = FrameTracker(tracking_hand, TrackerSettings().replace(scale={"hand_scale": "auto"}),
                      synergies=load_bundle("fingerfist"))
    res = tr.track(observe(depth, cam, tr.settings.observe, color=color), cam, color=color)
    assert abs(tr.scale_ / scale - 1.0) <= 0.07, tr.scale_ / scale
    shown = HandShape(scale, realistic_fingers(scale, 0)).apply(tracking_hand)
    truth = make_motion("fist-side", hand=shown, frames=45, seed=0).theta[0]
    err_mm = np.linalg.norm(tr.hand.keypoints(res.theta) - shown.keypoints(truth), axis=1).mean() * 1000.0
    assert err_mm <= 20.0, err_mm


@pytest.mark.parametrize("s", [0.8, 1.0, 1.3])
@pytest.mark.parametrize("turn", [0.0, 180.0])
@pytest.mark.parametrize("tilt", [(0.0, 0.0, 0.0), (10.0, -15.0, 5.0), (-15.0, 10.0, 20.0)])
def test_the_side_guess_of_a_closed_hand_seen_from_its_side(tracking_hand, s, turn, tilt):
    """The model's closed hand rendered (Kinect v1, no noise) from its thumb side (turn 0) or little finger
    side (turn 180), tilted: the side-view guess (``first_sizes``' third) is 1.1 × s within -5/+30 % (the
    closed posture's straight thumb makes the model's side view wider than a fist's with its thumb across:
    measured 1.15-1.23), where the palm-view guess is below 1.1 × s (0.91-0.97); a side spread taken without
    projecting on the image plane would guess 0.8 × 1.1 × s."""
    from test_init_orientation import scene
    from tracker.sim.hands import HandShape
    from tracker.track import fit_context, TrackerSettings
    from tracker.scale import first_sizes

    ctx = fit_context(tracking_hand, TrackerSettings())[0]
    shown = HandShape(s).apply(tracking_hand)
    _, ob, _ = scene(shown, "side", closed_posture(ctx), tilt_deg=(tilt[0], tilt[1] + turn, tilt[2]))
    _, palm, side = first_sizes(ctx, ob.points, None, (0.6, 2.0), 1.1)
    assert 0.95 <= side / (1.1 * s) <= 1.3
    assert palm / (1.1 * s) < 1.0
