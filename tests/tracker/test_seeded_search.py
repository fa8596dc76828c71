"""The detected hand first (:func:`tracker.init.seeded_search`, ``start.detector_accept_mm``): a start, a size
calibration and the safety net's search beyond the tracked pose begin at a keypoint detector's hand and run
the full search only when that fits poorly. Ground truth: rendered frames and an exact detector."""
import numpy as np
import pytest

import tracker.init.search as search_module
from handmodel import HandModel
from handmodel.rigid import euler_to_matrix, matrix_to_euler
from tracker.detector import Detection
from tracker.evaluate import posture_error_deg
from tracker.init import InitSettings, score, seeded_search
from tracker.io.cameras import preset
from tracker.net import SafetyNet
from tracker.observe import observe
from tracker.parts import KeypointSeed, frame_silhouette, silhouette_mask, usable_points
from tracker.sim.motions import make_motion
from tracker.sim.render import DepthRenderer
from tracker.track import FrameTracker, TrackerSettings

HAND = HandModel.load()
CAM = preset("kinect1")
FIXED = TrackerSettings().replace(scale=dict(hand_scale=1.0))


def oracle(truth):
    """A detector that finds every keypoint where the rendered hand has it."""
    def detect(depth, camera, mask, hand):
        kp = HAND.keypoints(truth)
        return Detection(np.full((21, 2), np.nan), kp[:, 2].copy(), kp, np.ones(21), 1.0, int(mask.sum()))
    return detect


def frame(motion="grasp-back", index=45):
    truth = make_motion(motion, hand=HAND).theta[index]
    ob = observe(DepthRenderer(HAND, CAM).render(truth, labels=False).depth, CAM)
    sil = frame_silhouette(silhouette_mask(ob), ob.depth, CAM, ob.frame_depth)
    pts, nrm = usable_points(ob.points, ob.normals, FIXED.loss.max_points)
    return truth, ob, sil, pts, nrm


def turned(theta, degrees):
    """θ with its hand turned by ``degrees`` about the camera's viewing axis."""
    out = np.array(theta, float)
    z = np.radians(degrees)
    Rz = np.array([[np.cos(z), -np.sin(z), 0], [np.sin(z), np.cos(z), 0], [0, 0, 1]])
    out[3:6] = matrix_to_euler(Rz @ euler_to_matrix(out[3:6]))
    return out


@pytest.fixture(scope="module")
def fist():
    return frame()


def count_searches(monkeypatch):
    """Count the full single-frame searches (``search=True``) that run."""
    calls = []
    real = search_module.fit_single_frame

    def spy(*args, **kw):
        calls.append(kw.get("search", True))
        return real(*args, **kw)
    monkeypatch.setattr(search_module, "fit_single_frame", spy)
    return calls


def test_a_detected_hand_that_fits_well_skips_the_full_search(fist, monkeypatch):
    truth, _, sil, pts, nrm = fist
    ctx = FrameTracker(HAND, FIXED).context
    calls = count_searches(monkeypatch)
    theta, corr, searched = seeded_search(ctx, pts, InitSettings(), truth, accept_mm=10.0, silhouette=sil,
                                          normals=nrm)
    assert not searched and calls == [False]
    assert posture_error_deg(theta, truth, HAND.pose_mask) < 3.0
    assert np.linalg.norm(HAND.keypoints(theta) - HAND.keypoints(truth), axis=1).mean() < 0.004


def test_a_poor_first_fit_runs_the_search_and_the_better_score_wins(fist, monkeypatch):
    """A detected hand turned 120° in the image fits the fist poorly: the full search runs (with it as
    one more start), and what comes out scores no worse than either the detected hand's fit or the search
    alone."""
    truth, _, sil, pts, nrm = fist
    ctx = FrameTracker(HAND, FIXED).context
    wrong = turned(truth, 120.0)
    first, c_first = search_module.fit_single_frame(ctx, pts, InitSettings(), theta0=wrong, silhouette=sil,
                                                    normals=nrm, extra=(wrong,), search=False)
    alone, c_alone = search_module.fit_single_frame(ctx, pts, InitSettings(), silhouette=sil, normals=nrm)
    s_first, s_alone = score(ctx, first, c_first, sil), score(ctx, alone, c_alone, sil)
    calls = count_searches(monkeypatch)
    theta, corr, searched = seeded_search(ctx, pts, InitSettings(), wrong, accept_mm=min(s_first, s_alone) / 2,
                                          silhouette=sil, normals=nrm)
    assert searched and calls == [False, True]
    assert score(ctx, theta, corr, sil) <= min(s_first, s_alone) + 1e-9


def test_accept_zero_always_searches(fist, monkeypatch):
    truth, _, sil, pts, nrm = fist
    ctx = FrameTracker(HAND, FIXED).context
    calls = count_searches(monkeypatch)
    _, _, searched = seeded_search(ctx, pts, InitSettings(), truth, accept_mm=0.0, silhouette=sil, normals=nrm)
    assert searched and calls == [False, True]


def test_the_tracker_starts_from_the_detected_hand(fist):
    """The fist from the back that the search without its grid misses (the paper's start from the mean):
    with an exact detector the start is the fist, and no full search ran."""
    truth, ob, _, _, _ = fist
    st = FIXED.replace(init=dict(search=False, finger_search=False))
    plain = FrameTracker(HAND, st).track(ob, CAM)
    tr = FrameTracker(HAND, st, depth_detector=oracle(truth))
    r = tr.track(ob, CAM)
    assert (tr.stats.detector_seeds, tr.stats.detector_starts, tr.stats.searches) == (1, 1, 0)
    e_plain = posture_error_deg(plain.theta, truth, HAND.pose_mask)
    e_seed = posture_error_deg(r.theta, truth, HAND.pose_mask)
    print(f"\nposture {e_plain:.1f} deg without the detector, {e_seed:.1f} deg with it")
    assert e_seed < 3.0 < e_plain


def test_the_accept_setting_is_checked():
    from tracker.errors import TrackerError

    for bad in (-1.0, float("inf"), "1.5", True):
        with pytest.raises(TrackerError, match="detector_accept_mm"):
            TrackerSettings().replace(start=dict(detector_accept_mm=bad)).check()
    assert FrameTracker(HAND, TrackerSettings().replace(start=dict(detector_accept_mm=0.0))).search.accept_mm == 0.0


def test_the_net_searches_from_the_detected_hand_before_the_placements():
    """A tracked fit turned 90° away from the hand (beyond the anchored search's reach): with a detector the
    net's second search starts at the detected hand, finds it, and the placements' search does not run."""
    truth, ob, sil, pts, nrm = frame("open-close", 0)
    tr = FrameTracker(HAND, FIXED)
    ctx = tr.context
    tr.cue.add(sil)
    wrong = turned(truth, 90.0)
    c_wrong = ctx.matcher(wrong, pts, nrm)
    s_wrong = score(ctx, wrong, c_wrong, sil)
    for keypoints, placed in ((None, 1), (KeypointSeed(oracle(truth), None, tr.stats), 0)):
        tr.stats.net_placed = 0
        net = SafetyNet(FIXED.net.replace(anchored=False), tr.cue, tr.stats, 0.0, keypoints)
        s, theta, _ = net._search(ctx, wrong, pts, nrm, sil, None, (s_wrong, None, None))
        assert tr.stats.net_placed == placed
        assert s < s_wrong and np.linalg.norm(HAND.keypoints(theta) - HAND.keypoints(truth), axis=1).mean() < 0.005
