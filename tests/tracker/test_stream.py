"""The streaming API (tracker.stream.HandTracker): one depth image in, one hand out, as tracker track does."""
import numpy as np
import pytest

from handmodel.model import HandModel
from tracker import TRACKING_HAND
from tracker.errors import TrackerError
from tracker.recording import Recording
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
