"""The streaming API (tracker.stream.HandTracker): one depth image in, one hand out, as tracker track does."""
import numpy as np
import pytest

from handmodel.model import HandModel
from tracker import TRACKING_HAND
from tracker.errors import TrackerError
from tracker.io.recording import Recording
from tracker.run import TrackJob, run_job
from tracker.sim.synthesize import synthesize
from tracker.stream import HandResult, HandTracker


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    out = tmp_path_factory.mktemp("stream") / "rec"
    synthesize("open-close", "kinect1", "kinect1", out, frames=6, seed=2, hand=HandModel.load(TRACKING_HAND))
    return out


def test_stream_gives_the_cli_path_bit_for_bit_and_the_true_hand(recording, tmp_path):
    rec = Recording.open(recording)
    ht = HandTracker(rec.camera, hand=rec.handedness, synergies="fingerfist")
    results = [ht.step(f.depth, color=f.color) for f in rec]
    job = TrackJob(str(recording), str(tmp_path / "t.csv"), synergies="fingerfist")
    df = run_job(job).df
    theta = np.array([r.theta for r in results])
    assert np.array_equal(theta, df[list(ht.model.dof_names)].to_numpy(), equal_nan=True)
    assert [r.status for r in results] == df["status"].tolist()
    assert all(r.found for r in results)
    # keypoints are the tracked hand's, in the camera frame: near the rendered hand's (the truth)
    truth = HandModel.load(TRACKING_HAND).keypoints(rec.truth_array())
    err_mm = np.linalg.norm(np.array([r.keypoints for r in results]) - truth, axis=-1).mean() * 1000.0
    assert err_mm < 15.0, err_mm
    assert results[-1].mask.shape == (rec.camera.height, rec.camera.width) and results[-1].mask.any()


def test_lost_frame_has_nan_hand_and_bad_input_is_refused():
    ht = HandTracker("kinect1", hand="right")
    r = ht.step(np.full((ht.camera.height, ht.camera.width), np.nan))
    assert isinstance(r, HandResult) and r.status == "lost" and not r.found
    assert np.isnan(r.theta).all() and np.isnan(r.keypoints).all() and r.keypoints.shape == (21, 3)
    with pytest.raises(TrackerError, match="shape"):
        ht.step(np.zeros((10, 10)))
    with pytest.raises(TrackerError, match="left' or 'right"):
        HandTracker("kinect1", hand="middle")


def test_real_time_mode_never_waits_for_a_slow_fit(recording):
    """A fit made slow on purpose (a search that takes long): the frames that come meanwhile return at
    once with the last fitted hand moved on by its last motion, and the worker takes up the newest frame
    after it. Deterministic: the slow fit waits for an event the test sets only after those frames."""
    import threading

    rec = Recording.open(recording)
    frames = list(rec)
    sync = HandTracker(rec.camera, hand=rec.handedness, synergies="fingerfist")
    expected = [sync.step(f.depth) for f in frames[:3]]
    with HandTracker(rec.camera, hand=rec.handedness, synergies="fingerfist", budget_ms=1e7) as ht:
        got = [ht.step(f.depth) for f in frames[:3]]  # a budget nothing exceeds: every frame fitted in turn
        assert all(np.array_equal(a.theta, b.theta) for a, b in zip(got, expected))
        hand2 = ht.model  # the hand of frame 2's fit (a calibrating frame may change its size)
        gate, released_late = threading.Event(), []
        track = ht.core.track

        def slow(*a, **kw):
            released_late.append(not gate.wait(60.0))
            return track(*a, **kw)

        ht.core.track = slow
        ht.budget_ms = 20.0
        waiting = [ht.step(f.depth) for f in frames[3:6]]
        gate.set()
        slow_frame = ht.wait()  # frame 3's fit, done once released
        assert slow_frame.status in ("tracked", "reinit") and ht.wait() is None
        assert [r.status for r in waiting] == ["predicted"] * 3
        # the last fit moved on by its last change, the rotation kept (the default predict.turn=False)
        moved = 2 * got[2].theta - got[1].theta
        moved[3:6] = got[2].theta[3:6]
        assert np.allclose(waiting[0].theta, moved)
        assert np.allclose(waiting[0].keypoints, hand2.keypoints(moved))
        ht.core.track = track
        ht.budget_ms = 1e7
        after = ht.step(frames[5].depth)  # the worker is free again: the newest frame is fitted
        assert after.status in ("tracked", "reinit") and released_late == [False]
    with pytest.raises(TrackerError, match="budget_ms"):
        HandTracker("kinect1", budget_ms=0)
