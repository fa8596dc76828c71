"""Tracking under the Kinect v1 noise model (tracker.sim.noise): the sensor's drop-outs along the
hand's outline must not pull the fit (tracker.observe.dropout_band)."""
from __future__ import annotations

import numpy as np
import pytest

from tracker.cameras import preset
from tracker.sim import experiments as E
from tracker.sim.motions import make_motion
from tracker.sim.noise import NoiseModel
from tracker.track import HandTracker, TrackerSettings

CAM = preset("kinect1")
KINECT = NoiseModel.preset("kinect1")


def _open_close(hand, seed, **kw):
    """The first 36 frames of open-close (the hand opens and closes into a fist) under Kinect v1
    noise, tracked from the first frame in full DoF by the default tracker at the model's size."""
    truth = make_motion("open-close", hand=hand).theta[:36]
    tr = HandTracker(hand, TrackerSettings(hand_scale=1.0).replace(**kw))
    return E.run_sequence(hand, truth, CAM, tr, noise=KINECT, seed=seed)


@pytest.mark.parametrize("seed", [0, 1])
def test_closing_into_a_fist_under_kinect_noise_keeps_the_fingers(hand, seed):
    """With the silhouette's no-depth band counted as hand, every frame stays within 5° and the mean
    within 2.8° (measured 2.1° and 1.9°, seeds 0 and 1). With the band as background
    (edge_px=0, the code before) the silhouette term pulled the fingers' edges inwards, fingers
    folded into a wrong shape while closing and stayed there: 6.0° (56 % of frames ≤ 5°) and 3.1°
    (89 %)."""
    r = _open_close(hand, seed)
    e = np.nan_to_num(r.error_deg, nan=np.inf)
    assert e.max() <= 5.0 and e.mean() <= 2.8, (e.mean(), e.max())


def test_the_band_is_what_helps(hand):
    """The same 36 frames with the band off lose a finger (the test above is not passed by an
    easy sequence): a frame beyond 10°, the mean beyond 4°."""
    e = np.nan_to_num(_open_close(hand, 0, edge_px=0).error_deg, nan=np.inf)
    assert e.max() > 10.0 and e.mean() > 4.0, (e.mean(), e.max())
