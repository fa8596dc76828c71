"""The user's hand size: a given factor, the automatic calibration on rendered hands of other sizes
(0.8–1.5 × the model), the size in the tracking output's header and the ``--hand-scale`` option."""
import numpy as np
import pytest
from test_init_orientation import CAM, kp_mm, scene

from handmodel import HandModel
from tracker.cli_common import parse_hand_scale
from tracker.errors import TrackerError
from tracker.io.tracking_file import tracking_metadata
from tracker.scale import extent_scale, rescaled
from tracker.sim.motions import POSTURES
from tracker.track import FrameTracker, TrackerSettings

BASE = HandModel.load()


@pytest.fixture(scope="module")
def bundle():
    from synergy.bundle import load_bundle

    return load_bundle("fingerfist")


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf"), "big"])
def test_bad_hand_scale_refused(bad):
    with pytest.raises(TrackerError, match="scale.hand_scale: must be 'auto' or a factor"):
        FrameTracker(BASE, TrackerSettings().replace(scale=dict(hand_scale=bad)))


@pytest.mark.parametrize("bad", [0.05, 0.59, 2.01, 50.0])
def test_hand_scale_outside_the_searched_sizes_refused(bad):
    with pytest.raises(TrackerError, match="scale.hand_scale: must be 'auto' or a factor in 0.6–2"):
        FrameTracker(BASE, TrackerSettings().replace(scale=dict(hand_scale=bad)))
    FrameTracker(BASE, TrackerSettings().replace(scale=dict(hand_scale=bad, range=(0.01, 100.0))))  # the range decides


def test_cli_hand_scale_option():
    assert parse_hand_scale("auto") == "auto" and parse_hand_scale(" AUTO ") == "auto"
    assert parse_hand_scale("1.25") == 1.25 and parse_hand_scale("0.6") == 0.6 and parse_hand_scale("2") == 2.0
    # 0.05 tracked nothing and 50 fitted nothing, each blaming the segmentation
    for bad in ("0", "-2", "nan", "inf", "large", "0.05", "50", "2.5"):
        with pytest.raises(TrackerError, match="--hand-scale: must be 'auto' or a factor in 0.6–2"):
            parse_hand_scale(bad)


def test_given_scale_tracks_the_resized_hand_and_says_so():
    tr = FrameTracker(BASE, TrackerSettings().replace(scale=dict(hand_scale=1.2)))
    th = np.zeros(BASE.n_dofs)
    th[7] = -0.5
    np.testing.assert_allclose(tr.hand.keypoints(th), BASE.scaled(1.2).keypoints(th), atol=1e-12)
    assert tr.scale_ == 1.2 and tr.base_hand is BASE
    meta = tracking_metadata("rec", tr)
    # the model file's identity, not the resized copy's: --hand-model and --hand-scale rebuild it
    assert meta["hand_model"] == f"{BASE.name} {BASE.sha256}"
    assert meta["hand_scale"] == "1.2000 (given)" and meta["hand_check"] == ""
    auto = FrameTracker(BASE, TrackerSettings().replace(scale=dict(hand_scale="auto")))
    assert auto.scale_ is None and tracking_metadata("rec", auto)["hand_scale"] == ""


def test_rescaled_keeps_the_hand_where_it_was():
    th = np.zeros(BASE.n_dofs)
    th[:3] = [0.02, -0.01, 0.7]
    th[3:6] = [0.3, -0.2, 0.1]
    big = BASE.scaled(1.4)
    moved = rescaled(BASE, big, th)
    np.testing.assert_allclose(big.keypoints(moved).mean(0), BASE.keypoints(th).mean(0), atol=1e-12)
    np.testing.assert_array_equal(moved[3:], th[3:])


def test_extent_guess_brackets_the_size():
    """The cloud's extent gives the size of an open hand within 10 % (a tilted hand looks shorter),
    and a curled one's below it."""
    for s in (0.8, 1.3):
        _, ob, _ = scene(BASE.scaled(s), "palm", POSTURES["open"])
        assert abs(extent_scale(BASE, ob.points, np.zeros(20)) / s - 1.0) < 0.10
        _, ob, _ = scene(BASE.scaled(s), "palm", POSTURES["grasp"])
        assert extent_scale(BASE, ob.points, np.zeros(20)) < s


@pytest.mark.slow
@pytest.mark.parametrize("scale,facing,posture", [(0.8, "palm", "open"), (1.0, "back", "mean"),
                                                  (1.3, "palm", "mean"), (1.5, "back", "open")])
def test_automatic_scale_recovered(bundle, scale, facing, posture):
    """Hands 0.8–1.5 × the model, palm or back towards the camera, tracked from the default model
    with ``hand_scale="auto"``: the size within 3 % and the keypoints within 10 mm on the first
    frame; two more frames refine the size (the median of three estimates; each frame's size work at
    once, ``budget=0``: spread over frames in ``test_scale_budget.py``)."""
    hand = BASE.scaled(scale)
    p = bundle.model.mean_ if posture == "mean" else POSTURES[posture]
    th, ob, _ = scene(hand, facing, p)
    tr = FrameTracker(BASE, TrackerSettings().replace(scale=dict(hand_scale="auto", budget=0)), synergies=bundle)
    r = tr.track(ob, CAM)
    err = kp_mm(hand, th, tr.hand, r.theta)
    first = tr.scale_
    print(f"\nscale {scale} {facing} {posture}: estimated {first:.4f} ({100 * (first / scale - 1):+.1f} %), "
          f"keypoints {err:.1f} mm")
    assert r.status == "reinit"
    assert abs(first / scale - 1.0) <= 0.03
    assert err <= 10.0
    for _ in range(2):
        r = tr.track(ob, CAM)
    assert len(tr.scale_estimates_) == 3 and tr.scale_ == pytest.approx(np.median(tr.scale_estimates_))
    assert abs(tr.scale_ / scale - 1.0) <= 0.03
    assert kp_mm(hand, th, tr.hand, r.theta) <= 10.0
    assert tracking_metadata("rec", tr)["hand_scale"].startswith(f"{tr.scale_:.4f} (auto, median of ")


def test_a_better_start_found_while_the_size_is_refined_replaces_the_tracked_fit(bundle):
    """While the size is refined (``scale_refine="search"``) each frame's own search is compared with
    the tracked fit (:meth:`tracker.sizing.SizeCalibration.take_better_start`): a tracked hand turned round (180° in the
    image about its centre, as a first frame searched at a wrong size can leave it) is replaced by the
    search's right fit, and a right tracked hand is kept against that turned-round candidate. Realistic
    SR305 frame (forearm, 1.0×), depth only."""
    from tests.conftest import realistic_frame
    from tracker.observe import observe
    from tracker.sim import experiments as E
    from tracker.sim.hands import HandShape
    from tracker.sim.motions import make_motion
    from tracker.parts import frame_silhouette, silhouette_mask, usable_points
    from test_upside_down import _turned

    shown = HandShape(1.0, E.realistic_fingers(1.0, 0)).apply(BASE)
    truth = make_motion("open-close", hand=shown, frames=30, seed=0).theta[2]
    cam, depth, _, _ = realistic_frame(BASE, "realsense", 1.0, "forearm", 2)
    ob = observe(depth, cam)
    tr = FrameTracker(BASE, TrackerSettings().replace(scale=dict(hand_scale=1.0)), synergies=bundle)
    tr.track(ob, cam)

    def err(th):
        return float(np.linalg.norm(tr.hand.keypoints(th) - shown.keypoints(truth), axis=-1).mean() * 1000)

    right = tr.theta.copy()
    wrong = _turned(tr.hand, right)
    assert err(right) <= 10.0 and err(wrong) >= 50.0, (err(right), err(wrong))  # the scene's premise
    sil = frame_silhouette(silhouette_mask(ob), ob.depth, cam, ob.frame_depth)
    tr.cue.add(sil)
    pts, nrm = usable_points(ob.points, ob.normals, tr.settings.loss.max_points)
    tr.theta = wrong.copy()
    tr.sizing.take_better_start(tr, pts, nrm, sil, tr.hand, right)
    assert tr.stats.size_starts == 1 and err(tr.theta) <= 10.0, err(tr.theta)
    assert tr.prev is None and np.array_equal(tr.last_good, tr.theta)
    tr.theta = right.copy()
    tr.sizing.take_better_start(tr, pts, nrm, sil, tr.hand, wrong)
    assert tr.stats.size_starts == 1 and np.array_equal(tr.theta, right)
