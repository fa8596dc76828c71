"""Fast motion (the hard cases' 1.1 m/s sweeps, ~37 mm and ~7° a frame): the prediction turns with the
hand (``predict.turn``), keeps its motion through the safety net's replacements (``predict.through_net``),
and the net's level of the scene is learnt from what its searches found (``net.level_replaced``,
``net.level_quantile``), so it does not creep up with mediocre fits and stop the net."""
from __future__ import annotations

import numpy as np
import pytest

from handmodel import HandModel
from handmodel.rigid import euler_to_matrix
from synergy.bundle import load_bundle
from tracker.observe import ObserveSettings
from handmodel.rigid import turned_on
from tracker.parts import Gate, Prediction, Recentring
from tracker.settings import PredictSettings, SafetyNetSettings
from tracker.sim import experiments as E
from tracker.sim.motions import make_motion
from tracker.sim.noise import NoiseModel
from tracker.track import FrameTracker, TrackerSettings

HAND = HandModel.load()
BUNDLE = load_bundle("fingerfist")


def _turn_deg(a, b) -> float:
    R = euler_to_matrix(a) @ euler_to_matrix(b).T
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


@pytest.mark.parametrize("name, without, with_turn", [("fast", 6.0, 2.5), ("rotate", 1.5, 0.2)])
def test_prediction_turns_on_with_the_hands_last_turn(name, without, with_turn):
    """The rendered scenarios' own θ: from the two frames before, the predicted rotation of each frame
    lies within 2.5° of the truth on the fast sweeps (measured 2.0° mean; 7.9° keeping the rotation)
    and 0.2° on the turn to the back (0.07°; 2.0°), whose middle Euler angle reaches 85°, where
    differences of Euler angles are no rotation."""
    th = make_motion(name, hand=HAND).theta
    lim = np.array(HAND.limits, float)
    errs = {}
    for turn in (False, True):
        pred = Prediction(PredictSettings(turn=turn), Gate(ObserveSettings(), 30, False), Recentring(50.0))
        errs[turn] = np.mean([_turn_deg(pred.theta(th[f - 1], th[f - 2], HAND, lim)[3:6], th[f, 3:6])
                              for f in range(2, len(th))])
    assert errs[True] <= with_turn and errs[False] >= without, errs


def test_turned_on_by_a_share_turns_by_that_share_of_the_angle():
    a, b = np.array([0.3, -0.2, 0.5]), np.array([0.25, -0.1, 0.45])
    step = _turn_deg(a, b)
    half = turned_on(a, b, 0.5)
    assert abs(_turn_deg(half, a) - 0.5 * step) < 1e-9
    assert abs(_turn_deg(turned_on(a, b), half) - 0.5 * step) < 1e-9  # the same axis: half-way there
    # the nearest Euler triple: no 2π jumps, so that a fit starting from it keeps the track's turns
    far = a + np.array([2 * np.pi, 0.0, -2 * np.pi])
    assert np.abs(turned_on(far, b + far - a) - far).max() < 0.2


@pytest.mark.slow
def test_the_nets_replacement_keeps_the_motion():
    """The fast sweeps' first 12 frames: the tracking fit from a prediction 37 mm off fails and the net
    replaces it (10 of the 11 frames). Predicted from the replacement without the motion, the next frame
    is again 16–45 mm off (mean 30 mm) and the posture goes 8–34° wrong from frame 8 (mean 8.9° over
    frames 1–11); the global pose moved on by its change from the frame before, the prediction is
    2–12 mm off (mean 8.4 mm) and the mean 4.8°."""
    truth = make_motion("fast", hand=HAND).theta[:12]
    out = {}
    for through in (True, False):
        st = TrackerSettings().replace(scale=dict(hand_scale=1.0), predict=dict(through_net=through))
        tr = FrameTracker(HAND, st, synergies=BUNDLE)
        preds, predict = [], tr.predict
        tr.predict = lambda: preds.append(predict()) or preds[-1]
        r = E.run_sequence(HAND, truth, E.default_camera(), tr)
        mm = [np.linalg.norm(p[:3] - truth[f + 1, :3]) * 1000.0 for f, p in enumerate(preds)]
        out[through] = (np.mean(mm[1:]), np.nanmean(r.error_deg[1:]), tr.stats.net_replaced)
    on, off = out[True], out[False]
    assert on[2] >= 5  # the frames the test is about
    assert on[0] <= 12.0 and off[0] >= 25.0, out
    assert on[1] <= 6.0 and off[1] > 1.5 * on[1], out


@pytest.mark.slow
def test_the_scenes_level_does_not_creep_up_with_mediocre_fits():
    """The fast sweeps under the Kinect v1 noise, 60 frames: with the level the median of the undoubted
    frames alone, fits that score 2–3 mm pass under a threshold they raise (7.0 mm at frame 60) and
    the posture goes wrong (mean 13.5°, 13–43° over the last 10 frames); with the replacements' scores
    counted and the lower quartile taken, the threshold is 1.4 mm there and the mean 7.9°."""
    truth = make_motion("fast", hand=HAND).theta[:60]
    noise = NoiseModel.preset("kinect1")
    res = {}
    for new in (True, False):
        net = SafetyNetSettings() if new else dict(level_replaced=False, level_quantile=0.5)
        st = TrackerSettings().replace(scale=dict(hand_scale=1.0), net=net)
        tr = FrameTracker(HAND, st, synergies=BUNDLE)
        r = E.run_sequence(HAND, truth, E.default_camera(), tr, noise=noise)
        res[new] = (r.mean_error, tr.net.threshold())
    assert res[True][0] <= 9.0 and res[True][1] <= 2.0, res
    assert res[False][1] > 2.0 * res[True][1] and res[False][0] > 1.5 * res[True][0], res


def test_the_papers_method_predicts_and_judges_as_before():
    """``TrackerSettings.paper()`` keeps the paper's prediction (no turn, nothing through a net it does not
    have) and the net's old level, so that its runs stay bit-identical."""
    p = TrackerSettings.paper()
    assert (p.predict.turn, p.predict.through_net) == (False, False)
    assert (p.net.enabled, p.net.level_replaced, p.net.level_quantile) == (False, False, 0.5)
    d = TrackerSettings()
    # the turn is opt-in: on by default it moved a real still's wrist to 51 px (the 19 stills as one recording,
    # test_upside_down) and a closing fist's arm-gate error to 4.8 mm (test_arm_gate)
    assert not d.predict.turn and d.predict.through_net and d.net.level_replaced and d.net.level_quantile == 0.25
