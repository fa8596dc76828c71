"""A tracked frame whose points the prediction missed is asked whether it is a hand (``predict.jump_presence``):
the harder scenes' fist-side motion (Kinect v1, 1.0x, forearm and torso, noise seed 2), frame 23, whose
windowed segmentation is refused (the side fist's uncut arm runs out of the window) and whose whole-frame
segmentation is the forearm's far end (no hand pixel in it): followed there, the fit lands on the arm 201 mm
from the hand; asked, the hand-presence network calls the arm's end no hand and the frame gives the prediction."""
from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import realistic_frame
from tracker.observe import observe
from tracker.track import FrameTracker, TrackerSettings


@pytest.fixture(scope="module")
def scene():
    from handmodel import HandModel
    from synergy.bundle import load_bundle
    from tracker import TRACKING_HAND
    from tracker.sim.experiments import realistic_fingers
    from tracker.sim.hands import HandShape
    from tracker.sim.motions import make_motion

    hand = HandModel.load(TRACKING_HAND)
    shown = HandShape(1.0, realistic_fingers(1.0, 0)).apply(hand)
    truth = make_motion("fist-side", hand=shown, frames=45, seed=0).theta
    frames = [realistic_frame(hand, "kinect1", 1.0, "forearm,torso", f, noise_seed=2, motion="fist-side", frames=45)
              for f in range(19, 25)]
    return hand, load_bundle("fingerfist"), [shown.keypoints(truth[f]) for f in range(19, 25)], frames


def _track(scene, **predict):
    hand, bundle, kps, frames = scene
    tr = FrameTracker(hand, TrackerSettings().replace(scale=dict(hand_scale=1.0), predict=predict), synergies=bundle)
    out = []
    for kp, (cam, depth, color, labels) in zip(kps, frames):
        ob = observe(depth, cam, tr.settings.observe, color=color, window=tr.segment_window(cam))
        r = tr.track(ob, cam, color=color)
        seen = (labels >= 0) & np.isfinite(depth)
        err = float(np.linalg.norm(tr.hand.keypoints(r.theta) - kp, axis=1).mean() * 1000.0)
        out.append((r.status, err, int((ob.mask & seen).sum())))
    return tr, out


def test_a_jump_to_the_arms_end_gives_the_prediction(scene):
    tr, on = _track(scene)
    _, off = _track(scene, jump_presence=False)
    assert on[:4] == off[:4]  # the same until the jump: frames 19-22 tracked alike
    status, err, hand_px = on[4]  # frame 23
    assert hand_px == 0  # the case itself: the mask holds no pixel of the hand
    assert status == "predicted" and err <= 25.0 and tr.stats.jumps_refused == 1, on
    assert off[4][0] != "predicted" and off[4][1] >= 100.0, off  # followed onto the arm
    assert on[5][0] == "tracked" and on[5][1] <= 20.0, on  # and frame 24 goes on from the prediction


def test_the_paper_does_not_ask():
    assert not TrackerSettings.paper().predict.jump_presence


def test_a_doubtful_frame_on_no_hand_gives_the_prediction_without_a_search():
    """A rendered open hand (no noise) tracked for 5 frames, then a frame where a flat square plate of its
    size stands in its place: the prediction meets the plate (nothing re-centred), the fit is doubtful, and
    the safety net's search would move the hand onto the plate (``reinit``); asked first, the hand-presence
    network calls the plate no hand (p ~2e-5), so the frame gives the prediction and no search runs."""
    from handmodel import HandModel
    from synergy.bundle import load_bundle
    from tracker import TRACKING_HAND
    from tracker.io.cameras import preset
    from tracker.sim.motions import make_motion
    from tracker.sim.render import DepthRenderer

    hand, cam = HandModel.load(TRACKING_HAND), preset("kinect1")
    truth = make_motion("open-close", hand=hand, frames=30).theta[:5]
    frames = [DepthRenderer(hand, cam).render(th, labels=False).depth for th in truth]
    d = frames[-1]
    rows, cols = np.nonzero(np.isfinite(d) & (d > 0))
    rc, cc = (rows.min() + rows.max()) // 2, (cols.min() + cols.max()) // 2
    h = int(0.35 * max(np.ptp(rows), np.ptp(cols)))
    plate = np.full_like(d, np.nan)
    plate[rc - h:rc + h, cc - h:cc + h] = np.nanmedian(d[np.isfinite(d)])
    frames.append(plate)

    def run(jump_presence):
        tr = FrameTracker(hand, TrackerSettings().replace(scale=dict(hand_scale=1.0),
                                                          predict=dict(jump_presence=jump_presence)),
                          synergies=load_bundle("fingerfist"))
        out = [tr.track(observe(dep, cam, window=tr.segment_window(cam)), cam) for dep in frames]
        return tr, out

    tr, on = run(True)
    assert [r.status for r in on[:5]] == ["reinit"] + ["tracked"] * 4
    assert on[5].status == "predicted" and tr.stats.recentred == 0 and tr.stats.net_runs == 0
    assert tr.stats.jumps_refused == 1
    # the prediction: the last frame's hand moved on by its last change, within a few mm of frame 4's truth
    assert np.linalg.norm(hand.keypoints(on[5].theta) - hand.keypoints(truth[4]), axis=1).mean() < 0.01
    tr, off = run(False)
    assert off[5].status == "reinit" and tr.stats.net_runs == 1  # searched, and moved onto the plate
