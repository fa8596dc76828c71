"""A start whose segmented region is no hand looks along that region's surface (``FrameTracker._hand_along_surface``):
a forearm reaching towards the camera can be nearer than the hand, and the whole-frame segmentation then takes
the arm's near end; the hand is at its other end, on the same depth-continuous surface, where the keypoint CNN's
re-crop finds it (issue 38; docs/experiments/detector.md, "A start along the region's surface")."""
from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import harder_frame, mask_scores
from tracker.observe import observe
from tracker.track import FrameTracker, TrackerSettings


@pytest.fixture(scope="module")
def bundle():
    from synergy.bundle import load_bundle

    return load_bundle("fingerfist")


@pytest.mark.parametrize("motion, sensor, scale", [("pinch", "kinect1", 0.8), ("fist-side", "realsense", 1.0)])
def test_the_arms_near_end_leads_to_the_hand(bundle, motion, sensor, scale):
    """The harder scenes' first frames (forearm and torso, noise seed 2) whose segmentation holds no pixel of the
    hand: the presence network turns the region away, and the start begins on the hand found along the arm
    (measured 18.0 and 27.3 mm at the rendered size; before, both frames were "no hand")."""
    hand, cam, depth, color, labels, kp = harder_frame(motion, sensor, scale, 0)
    ob = observe(depth, cam, color=color)
    assert mask_scores(ob.mask, depth, labels)[0] == 0.0  # the case itself: the region is all arm
    tr = FrameTracker(hand, TrackerSettings().replace(scale=dict(hand_scale=scale)), synergies=bundle)
    r = tr.track(ob, cam, color=color)
    # counted as a surface start, not among the regions called no hand (the CLI counts those against lost frames)
    assert r.status == "reinit" and tr.stats.not_hands == 0 and tr.stats.surface_starts == 1
    assert np.linalg.norm(tr.hand.keypoints(r.theta) - kp, axis=1).mean() < 0.035


def test_a_surface_without_a_hand_stays_no_hand(bundle):
    """A flat plate alone (a hand's size, noise-free Kinect v1): the region is no hand and so is everything on its
    surface: the start is lost, nothing begun along it."""
    from handmodel import HandModel
    from tracker import TRACKING_HAND
    from tracker.io.cameras import preset
    from tracker.sim.render import DepthRenderer

    hand, cam = HandModel.load(TRACKING_HAND), preset("kinect1")
    d = DepthRenderer(hand, cam).render(np.zeros(hand.n_dofs) + np.r_[0, 0, 0.6, np.zeros(hand.n_dofs - 3)],
                                        labels=False).depth
    rows, cols = np.nonzero(np.isfinite(d) & (d > 0))
    rc, cc = (rows.min() + rows.max()) // 2, (cols.min() + cols.max()) // 2
    h = int(0.35 * max(np.ptp(rows), np.ptp(cols)))
    plate = np.full_like(d, np.nan)
    plate[rc - h:rc + h, cc - h:cc + h] = np.nanmedian(d[np.isfinite(d)])
    tr = FrameTracker(hand, TrackerSettings().replace(scale=dict(hand_scale=1.0)), synergies=bundle)
    r = tr.track(observe(plate, cam), cam)
    assert r.status == "lost" and tr.stats.not_hands == 1 and tr.stats.surface_starts == 0
